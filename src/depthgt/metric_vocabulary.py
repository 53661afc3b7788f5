"""The metric vocabulary: metric names with their units, depth and pose errors (a leaf
module, numpy only).

One vocabulary for every stage: the frame-set statistics (:mod:`depthgt.gt.build`), the
registration's pose checks, the dataset assembly, the evaluation and the tables take
their names and units from here. Units are in the names; :data:`METRIC_UNITS` gives the
unit of every name.

Conventions: depth float32 metres with 0 = invalid (numpy (H, W) or torch
(B, 1, H, W)); poses 4x4 camera-to-world or relative, float64.

Depth errors of an estimate (a GT, a prediction, the input) against a reference (the
clean truth, depthgt's GT, the raw target depth), :func:`depth_errors`:

* ``mae_m``, ``rmse_m``: over pixels where the reference AND the estimate are valid:
  is the estimate accurate where it has data?
* ``mae_missing_counted_m``, ``rmse_missing_counted_m``: over every reference-valid
  pixel, a missing estimate counting as predicting 0 m (its error is the reference
  depth): accuracy and completeness in one number;
* ``completeness``: fraction of reference-valid pixels that the estimate covers;
* ``n_reference_px``, ``n_both_px``: pixel counts behind these numbers.

``mae_m``/``rmse_m`` are taken over a pixel set that depends on the estimate, so they
cannot rank methods; the evaluation tables use masks that are the same for every method
(:mod:`depthgt.eval.metrics`): the *filling* task (every reference-valid pixel, missing
counted: the ``*_missing_counted_m`` values) and the *denoising* task
(``mae_input_valid_m``, ``rmse_input_valid_m``: the pixels where the raw input and the
reference are both valid, a missing estimate again counting as predicting 0 m).

The structure metrics ``ssim``, ``ssim_missing_counted`` and ``ls`` (torch) are computed
by :mod:`depthgt.eval.metrics`. Pose errors (:func:`pose_errors`): rotation angle in
degrees and translation distance in centimetres; :func:`pose_delta` the size of a motion.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from depthgt.shapes import check_shape

if TYPE_CHECKING:
    import pandas as pd

__all__ = [
    "METRIC_UNITS",
    "DEPTH_ERRORS",
    "unit_of",
    "depth_errors",
    "depth_pair",
    "PoseErrors",
    "pose_errors",
    "pose_delta",
    "to_long",
]

METRIC_UNITS = {
    # depth errors (depth_errors)
    "mae_m": "m",
    "rmse_m": "m",
    "mae_missing_counted_m": "m",
    "rmse_missing_counted_m": "m",
    "completeness": "fraction",
    "n_reference_px": "px",
    "n_both_px": "px",
    # the denoising mask: raw input and reference valid (depth_metrics with the input)
    "mae_input_valid_m": "m",
    "rmse_input_valid_m": "m",
    "n_input_valid_px": "px",
    # structure (depth_metrics)
    "ssim": "1",
    "ssim_missing_counted": "1",
    "ls": "m^2/px^2",
    # pose errors (pose_errors)
    "rot_err_deg": "deg",
    "trans_err_cm": "cm",
    # frame-set statistics (frameset.json "statistics", framesets.parquet)
    "input_missing": "fraction",
    "gt_missing": "fraction",
    "rde_missing": "fraction",
    "gt_mean_points": "points",
    "neighbours_fused": "frames",
    "gt_median_sigma_m": "m",
    "render_agreement": "fraction",  # per neighbour (keyed by frame offset): share of samples agreeing with the target
    "render_left_out": "frame offsets",  # neighbours the renderer left out whole (too little agreement)
    "render_kept_share": "fraction",  # share of the neighbours' compared samples the agreement check kept
    "patches_drawn": "patches",
    "patches_kept": "patches",
}
DEPTH_ERRORS = (
    "mae_m",
    "rmse_m",
    "mae_missing_counted_m",
    "rmse_missing_counted_m",
    "completeness",
    "n_reference_px",
    "n_both_px",
)


def unit_of(metric: str) -> str:
    """The unit of a metric name of :data:`METRIC_UNITS` (a KeyError names unknown ones:
    a metric without a unit is a bug, not a blank cell)."""
    if metric not in METRIC_UNITS:
        raise KeyError(f"metric {metric!r} has no unit in depthgt.metric_vocabulary.METRIC_UNITS")
    return METRIC_UNITS[metric]


def _as_hw(x: Any, name: str) -> np.ndarray:
    """(H, W) or (B, 1, H, W) depth (numpy or torch) as a float64 numpy array of the same
    shape, non-finite values set to 0 (invalid)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    check_shape(a, "H W | B 1 H W", f"{name} depth")
    return np.nan_to_num(a, nan=0.0, posinf=0.0, neginf=0.0)


def depth_pair(estimate_m, reference_m) -> tuple[np.ndarray, np.ndarray]:
    """Estimate and reference depth as float64 numpy arrays of one shape (see :func:`depth_errors`)."""
    e, r = _as_hw(estimate_m, "estimate"), _as_hw(reference_m, "reference")
    if e.shape != r.shape:
        raise ValueError(f"estimate {e.shape} and reference {r.shape} differ in shape")
    return e, r


def depth_errors(estimate_m, reference_m, mask: np.ndarray | None = None) -> dict[str, float]:
    """Error of ``estimate_m`` against ``reference_m`` (see the module docstring).

    Args:
        estimate_m, reference_m: (H, W) or (B, 1, H, W) depth in metres, 0 = invalid
            (numpy or torch; computed in float64).
        mask: optional bool array of the same shape restricting the pixels considered.

    Returns:
        dict with the keys of :data:`DEPTH_ERRORS` (NaN where no pixel qualifies).

    >>> e = depth_errors(np.array([[1.1, 0.0], [2.8, 5.0]]), np.array([[1.0, 2.0], [3.0, 0.0]]))
    >>> round(e["mae_m"], 3), round(e["mae_missing_counted_m"], 3), round(e["completeness"], 3), e["n_both_px"]
    (0.15, 0.767, 0.667, 2)
    """
    est, ref = depth_pair(estimate_m, reference_m)
    ref_ok = ref > 0
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != ref.shape:
            raise ValueError(f"mask {mask.shape} and reference {ref.shape} differ in shape")
        ref_ok &= mask
    est_ok = est > 0
    both = ref_ok & est_ok
    n_ref, n_both = int(ref_ok.sum()), int(both.sum())
    nan = float("nan")
    err = np.abs(est - ref)
    err_counted = np.where(est_ok, err, ref)[ref_ok]
    return {
        "mae_m": float(err[both].mean()) if n_both else nan,
        "rmse_m": float(np.sqrt((err[both] ** 2).mean())) if n_both else nan,
        "mae_missing_counted_m": float(err_counted.mean()) if n_ref else nan,
        "rmse_missing_counted_m": float(np.sqrt((err_counted**2).mean())) if n_ref else nan,
        "completeness": n_both / n_ref if n_ref else nan,
        "n_reference_px": n_ref,
        "n_both_px": n_both,
    }


# --------------------------------------------------------------------------- poses


class PoseErrors(NamedTuple):
    """Errors of (..., 4, 4) poses against reference poses, per pose.

    rot_err_deg: (...,) angle of ``R_est^T R_ref`` in degrees.
    trans_err_cm: (...,) distance of the translations in centimetres.
    """

    rot_err_deg: np.ndarray
    trans_err_cm: np.ndarray

    def mean(self) -> dict[str, float]:
        """``{"rot_err_deg": mean, "trans_err_cm": mean}`` (units in :data:`METRIC_UNITS`)."""
        return {"rot_err_deg": float(np.mean(self.rot_err_deg)), "trans_err_cm": float(np.mean(self.trans_err_cm))}


def _poses(T, name: str) -> np.ndarray:
    if hasattr(T, "detach"):
        T = T.detach().cpu().numpy()
    T = np.asarray(T, dtype=np.float64)
    check_shape(T, "... 4 4", name)
    return T


def pose_errors(T_est, T_ref) -> PoseErrors:
    """Rotation (deg) and translation (cm) error of each pose (numpy or torch, (4, 4) or
    (..., 4, 4); float64 math).

    >>> e = pose_errors(np.eye(4), np.diag([1.0, 1.0, 1.0, 1.0]))
    >>> float(e.rot_err_deg), float(e.trans_err_cm)
    (0.0, 0.0)
    """
    a, b = _poses(T_est, "T_est"), _poses(T_ref, "T_ref")
    R = np.swapaxes(a[..., :3, :3], -1, -2) @ b[..., :3, :3]
    cos = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0, -1.0, 1.0)
    return PoseErrors(np.degrees(np.arccos(cos)), 100.0 * np.linalg.norm(a[..., :3, 3] - b[..., :3, 3], axis=-1))


def pose_delta(T) -> tuple[np.ndarray, np.ndarray]:
    """Magnitude of a (..., 4, 4) motion: (translation in metres, rotation in degrees)."""
    T = _poses(T, "T")
    err = pose_errors(T, np.broadcast_to(np.eye(4), T.shape))
    return np.linalg.norm(T[..., :3, 3], axis=-1), err.rot_err_deg


def to_long(values: dict[str, float], **ids) -> pd.DataFrame:
    """Tidy long table: one row per metric with the id columns (e.g. dataset, scene,
    method), ``metric``, ``unit`` (from :data:`METRIC_UNITS`), ``value``."""
    import pandas as pd  # heavy: only the tables need it

    rows = [{**ids, "metric": k, "unit": unit_of(k), "value": float(v)} for k, v in values.items()]
    return pd.DataFrame(rows, columns=[*ids.keys(), "metric", "unit", "value"])
