"""Depth and pose metrics, tidy-table friendly.

Conventions: depth float32 metres with 0 = invalid (numpy (H, W) or torch
(B, 1, H, W)); poses 4x4 camera-to-world (or relative) float64.

Depth metrics of a prediction against a reference (GT or true depth):

* ``rmse_m``, ``mae_m``: over pixels where the reference AND the prediction are valid;
* ``rmse_fill_m``, ``mae_fill_m``: over all reference-valid pixels, a missing
  prediction counting as predicting 0 m (error = the reference depth);
* ``completeness``: fraction of reference-valid pixels that the prediction covers;
* ``ssim``: kornia SSIM of depth/10 m (data_range 1, 11x11 Gaussian window,
  sigma 1.5), the SSIM map averaged over pixels where both are valid;
* ``ls``: L_S of paper eq. 6 (5x5 window), gradients trusted where both are valid.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch
from kornia.metrics import ssim as kornia_ssim

from depthgt.enhance.losses import structure_loss

__all__ = [
    "METRIC_UNITS",
    "rmse",
    "mae",
    "completeness",
    "ssim_depth",
    "ls_distance",
    "depth_metrics",
    "rotation_error_deg",
    "translation_error_cm",
    "pose_errors",
    "to_long",
]

METRIC_UNITS = {
    "rmse_m": "m",
    "mae_m": "m",
    "rmse_fill_m": "m",
    "mae_fill_m": "m",
    "completeness": "fraction",
    "ssim": "1",
    "ls": "m^2/px^2",
    "n_valid": "px",
    "rot_err_deg": "deg",
    "trans_err_cm": "cm",
}

SSIM_DEPTH_SCALE_M = 10.0


def _as_bchw(x, name: str) -> torch.Tensor:
    t = torch.as_tensor(np.asarray(x, dtype=np.float32)) if not isinstance(x, torch.Tensor) else x
    if t.ndim == 2:
        t = t[None, None]
    if t.ndim != 4 or t.shape[1] != 1:
        raise ValueError(f"{name} must be (H, W) or (B, 1, H, W) depth, got {tuple(t.shape)}")
    return t.float()


def _pair(pred, ref):
    p, r = _as_bchw(pred, "pred"), _as_bchw(ref, "ref")
    if p.shape != r.shape:
        raise ValueError(f"pred {tuple(p.shape)} and ref {tuple(r.shape)} differ in shape")
    p = torch.nan_to_num(p, nan=0.0, posinf=0.0, neginf=0.0)
    r = torch.nan_to_num(r, nan=0.0, posinf=0.0, neginf=0.0)
    return p, r.to(p.device)


def rmse(pred, ref, fill: bool = False) -> float:
    """Root mean squared error in metres over reference-valid pixels.

    ``fill=False``: only where the prediction is valid too; ``fill=True``: missing
    predictions count as 0 m. NaN when no pixel qualifies.
    """
    p, r = _pair(pred, ref)
    m = (r > 0) if fill else (r > 0) & (p > 0)
    if not m.any():
        return float("nan")
    return float(torch.sqrt(((p - r)[m] ** 2).mean()))


def mae(pred, ref, fill: bool = False) -> float:
    """Mean absolute error in metres; masks as in :func:`rmse`."""
    p, r = _pair(pred, ref)
    m = (r > 0) if fill else (r > 0) & (p > 0)
    if not m.any():
        return float("nan")
    return float((p - r)[m].abs().mean())


def completeness(pred, ref) -> float:
    """Fraction of reference-valid pixels where the prediction is valid (> 0)."""
    p, r = _pair(pred, ref)
    n = (r > 0).sum()
    if n == 0:
        return float("nan")
    return float(((p > 0) & (r > 0)).sum() / n)


def ssim_depth(pred, ref, scale_m: float = SSIM_DEPTH_SCALE_M) -> float:
    """SSIM of depth/``scale_m`` (data_range 1, 11x11 Gaussian window, sigma 1.5 --
    kornia's window), averaged over pixels where both images are valid; NaN for
    images smaller than the window."""
    p, r = _pair(pred, ref)
    m = (r > 0) & (p > 0)
    if not m.any() or min(p.shape[-2:]) < 11:  # no valid pixel, or smaller than the window
        return float("nan")
    smap = kornia_ssim(p / scale_m, r / scale_m, window_size=11, max_val=1.0)
    return float(smap[m].mean())


def ls_distance(pred, ref, window: int = 5) -> float:
    """L_S of paper eq. 6 between two depth images (m^2/px^2), over pixels where
    both are valid (gradients undefined at holes contribute 0 to the max)."""
    p, r = _pair(pred, ref)
    m = (r > 0) & (p > 0)
    if not m.any():
        return float("nan")
    return float(structure_loss(p, r, m, window))


def depth_metrics(pred, ref) -> dict[str, float]:
    """All depth metrics of ``pred`` against ``ref`` (see module docstring).

    Args:
        pred, ref: (H, W) or (B, 1, H, W) depth in metres, 0 = invalid.

    Returns:
        dict metric name -> value; units in :data:`METRIC_UNITS`.
    """
    p, r = _pair(pred, ref)
    return {
        "rmse_m": rmse(p, r),
        "mae_m": mae(p, r),
        "rmse_fill_m": rmse(p, r, fill=True),
        "mae_fill_m": mae(p, r, fill=True),
        "completeness": completeness(p, r),
        "ssim": ssim_depth(p, r),
        "ls": ls_distance(p, r),
        "n_valid": float(((p > 0) & (r > 0)).sum()),
    }


def _check_pose(T, name: str) -> np.ndarray:
    T = np.asarray(T, dtype=np.float64)
    if T.shape[-2:] != (4, 4):
        raise ValueError(f"{name} must be (..., 4, 4), got {T.shape}")
    return T


def rotation_error_deg(T_est, T_ref) -> np.ndarray | float:
    """Angle of R_est^T R_ref in degrees. T_*: (4, 4) or (N, 4, 4)."""
    a, b = _check_pose(T_est, "T_est"), _check_pose(T_ref, "T_ref")
    R = np.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    out = np.degrees(np.arccos(cos))
    return float(out) if out.ndim == 0 else out


def translation_error_cm(T_est, T_ref) -> np.ndarray | float:
    """Euclidean distance of the translations in centimetres. T_*: (4, 4) or (N, 4, 4)."""
    a, b = _check_pose(T_est, "T_est"), _check_pose(T_ref, "T_ref")
    out = 100.0 * np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1)
    return float(out) if out.ndim == 0 else out


def pose_errors(T_est, T_ref) -> dict[str, float]:
    """Mean rotation error (deg) and translation error (cm) over (N, 4, 4) or one pose."""
    return {
        "rot_err_deg": float(np.mean(rotation_error_deg(T_est, T_ref))),
        "trans_err_cm": float(np.mean(translation_error_cm(T_est, T_ref))),
    }


def to_long(values: dict[str, float], **ids) -> pd.DataFrame:
    """Tidy long table: one row per metric with the id columns (e.g. dataset, scene,
    method), ``metric``, ``unit``, ``value``."""
    rows = [{**ids, "metric": k, "unit": METRIC_UNITS.get(k, ""), "value": float(v)} for k, v in values.items()]
    return pd.DataFrame(rows, columns=[*ids.keys(), "metric", "unit", "value"])
