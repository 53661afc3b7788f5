"""Depth metrics of the evaluation tables: the metric vocabulary plus the structure metrics.

The names, units, depth and pose errors live in the leaf module
:mod:`depthgt.metric_vocabulary` (numpy only, shared by every stage) and are
re-exported here; this module adds the structure metrics of the paper's tables (torch):

* ``ssim``: kornia SSIM of depth/10 m (data_range 1, 11x11 Gaussian window,
  sigma 1.5), the SSIM map averaged over pixels where both are valid (Table 1: a GT
  against the input);
* ``ssim_missing_counted``: the same SSIM map with a missing estimate taken as 0 m,
  averaged over every reference-valid pixel: one pixel set for every method (the
  method tables' SSIM column);
* ``ls``: L_S of paper eq. 6 (5x5 window, :func:`depthgt.depth_ops.structure_loss`),
  gradients trusted where both are valid.

:func:`depth_metrics` gives all of them for one estimate and, given the raw input, the
errors over the denoising mask (input and reference valid): ``mae_input_valid_m``,
``rmse_input_valid_m`` (a missing estimate counted as predicting 0 m there).
"""

from __future__ import annotations

import numpy as np
import torch
from kornia.metrics import ssim as kornia_ssim

from depthgt.depth_ops import structure_loss
from depthgt.metric_vocabulary import (
    DEPTH_ERRORS,
    METRIC_UNITS,
    PoseErrors,
    depth_errors,
    depth_pair,
    pose_delta,
    pose_errors,
    to_long,
    unit_of,
)

__all__ = [
    "METRIC_UNITS",
    "DEPTH_ERRORS",
    "SSIM_DEPTH_SCALE_M",
    "depth_errors",
    "ssim_depth",
    "ls_distance",
    "input_valid_errors",
    "depth_metrics",
    "PoseErrors",
    "pose_errors",
    "pose_delta",
    "unit_of",
    "to_long",
]

SSIM_DEPTH_SCALE_M = 10.0


def _tensors(estimate_m, reference_m):
    e, r = depth_pair(estimate_m, reference_m)
    if e.ndim == 2:
        e, r = e[None, None], r[None, None]
    return torch.from_numpy(e.astype(np.float32)), torch.from_numpy(r.astype(np.float32))


def _ssim_both(estimate_m, reference_m, scale_m: float = SSIM_DEPTH_SCALE_M) -> tuple[float, float]:
    """(SSIM over pixels valid in both, SSIM over every reference-valid pixel) from one
    SSIM map (see :func:`ssim_depth`)."""
    p, r = _tensors(estimate_m, reference_m)
    if min(p.shape[-2:]) < 11:  # smaller than the window
        return float("nan"), float("nan")
    ref_ok = r > 0
    both = ref_ok & (p > 0)
    smap = kornia_ssim(p / scale_m, r / scale_m, window_size=11, max_val=1.0)
    return tuple(float(smap[m].mean()) if m.any() else float("nan") for m in (both, ref_ok))


def ssim_depth(estimate_m, reference_m, scale_m: float = SSIM_DEPTH_SCALE_M, missing_counted: bool = False) -> float:
    """SSIM of depth/``scale_m`` (data_range 1, 11x11 Gaussian window, sigma 1.5 --
    kornia's window), averaged over pixels where both images are valid, or with
    ``missing_counted`` over every reference-valid pixel (a missing estimate enters the
    windows as 0 m: the same pixel set for every estimate); NaN for images smaller than
    the window or without a pixel to average."""
    return _ssim_both(estimate_m, reference_m, scale_m)[1 if missing_counted else 0]


def ls_distance(estimate_m, reference_m, window: int = 5) -> float:
    """L_S of paper eq. 6 between two depth images (m^2/px^2), over pixels where
    both are valid (gradients undefined at holes contribute 0 to the max)."""
    p, r = _tensors(estimate_m, reference_m)
    m = (r > 0) & (p > 0)
    if not m.any():
        return float("nan")
    return float(structure_loss(p, r, m, window))


def input_valid_errors(estimate_m, reference_m, input_m) -> dict[str, float]:
    """Errors over the denoising mask: pixels where ``input_m`` and ``reference_m`` are
    both valid, the same for every estimate; a missing estimate there counts as
    predicting 0 m (its error is the reference depth).

    Returns:
        ``mae_input_valid_m``, ``rmse_input_valid_m`` (NaN without such a pixel) and
        ``n_input_valid_px``.

    >>> e = input_valid_errors(np.array([[1.1, 0.0, 9.0]]), np.array([[1.0, 2.0, 3.0]]), np.array([[1.2, 2.2, 0.0]]))
    >>> round(e["mae_input_valid_m"], 3), e["n_input_valid_px"]
    (1.05, 2)
    """
    inp, _ = depth_pair(input_m, reference_m)
    e = depth_errors(estimate_m, reference_m, mask=inp > 0)
    return {
        "mae_input_valid_m": e["mae_missing_counted_m"],
        "rmse_input_valid_m": e["rmse_missing_counted_m"],
        "n_input_valid_px": e["n_reference_px"],
    }


def depth_metrics(estimate_m, reference_m, input_m=None) -> dict[str, float]:
    """:func:`depth_errors` plus ``ssim``, ``ssim_missing_counted`` and ``ls`` and, given
    the raw input, :func:`input_valid_errors` (the evaluation tables' metrics).

    Args:
        estimate_m, reference_m: (H, W) or (B, 1, H, W) depth in metres, 0 = invalid.
        input_m: the raw input depth of the same shape (the denoising mask), or None.

    Returns:
        dict metric name -> value; units in :data:`METRIC_UNITS`.
    """
    ssim_both, ssim_counted = _ssim_both(estimate_m, reference_m)  # one SSIM map, two pixel sets
    out = {
        **depth_errors(estimate_m, reference_m),
        "ssim": ssim_both,
        "ssim_missing_counted": ssim_counted,
        "ls": ls_distance(estimate_m, reference_m),
    }
    if input_m is not None:
        out.update(input_valid_errors(estimate_m, reference_m, input_m))
    return out
