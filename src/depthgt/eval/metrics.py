"""Depth metrics of the evaluation tables: the metric vocabulary plus the structure metrics.

The names, units, depth and pose errors live in the leaf module
:mod:`depthgt.metric_vocabulary` (numpy only, shared by every stage) and are
re-exported here; this module adds the structure metrics of the paper's tables (torch):

* ``ssim``: kornia SSIM of depth/10 m (data_range 1, 11x11 Gaussian window,
  sigma 1.5), the SSIM map averaged over pixels where both are valid;
* ``ls``: L_S of paper eq. 6 (5x5 window, :func:`depthgt.depth_ops.structure_loss`),
  gradients trusted where both are valid.

:func:`depth_metrics` gives all of them for one estimate.
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


def ssim_depth(estimate_m, reference_m, scale_m: float = SSIM_DEPTH_SCALE_M) -> float:
    """SSIM of depth/``scale_m`` (data_range 1, 11x11 Gaussian window, sigma 1.5 --
    kornia's window), averaged over pixels where both images are valid; NaN for
    images smaller than the window or without a pixel valid in both."""
    p, r = _tensors(estimate_m, reference_m)
    m = (r > 0) & (p > 0)
    if not m.any() or min(p.shape[-2:]) < 11:  # no valid pixel, or smaller than the window
        return float("nan")
    smap = kornia_ssim(p / scale_m, r / scale_m, window_size=11, max_val=1.0)
    return float(smap[m].mean())


def ls_distance(estimate_m, reference_m, window: int = 5) -> float:
    """L_S of paper eq. 6 between two depth images (m^2/px^2), over pixels where
    both are valid (gradients undefined at holes contribute 0 to the max)."""
    p, r = _tensors(estimate_m, reference_m)
    m = (r > 0) & (p > 0)
    if not m.any():
        return float("nan")
    return float(structure_loss(p, r, m, window))


def depth_metrics(estimate_m, reference_m) -> dict[str, float]:
    """:func:`depth_errors` plus ``ssim`` and ``ls`` (the evaluation tables' metrics).

    Args:
        estimate_m, reference_m: (H, W) or (B, 1, H, W) depth in metres, 0 = invalid.

    Returns:
        dict metric name -> value; units in :data:`METRIC_UNITS`.
    """
    return {**depth_errors(estimate_m, reference_m), "ssim": ssim_depth(estimate_m, reference_m),
            "ls": ls_distance(estimate_m, reference_m)}
