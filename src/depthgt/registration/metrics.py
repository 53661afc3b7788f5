"""Pose error metrics for relative poses (numpy or torch inputs, float64 math)."""

from __future__ import annotations

import numpy as np

__all__ = ["rotation_error_deg", "translation_error_cm", "pose_errors", "pose_delta"]


def _np(x) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def rotation_error_deg(T_est, T_ref) -> np.ndarray:
    """Angle of ``R_est^T R_ref`` in degrees for (..., 4, 4) poses; (...,) array."""
    R = np.swapaxes(_np(T_est)[..., :3, :3], -1, -2) @ _np(T_ref)[..., :3, :3]
    c = (np.trace(R, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


def translation_error_cm(T_est, T_ref) -> np.ndarray:
    """Euclidean distance of the translations in centimetres; (...,) array."""
    return 100.0 * np.linalg.norm(_np(T_est)[..., :3, 3] - _np(T_ref)[..., :3, 3], axis=-1)


def pose_errors(T_est, T_ref) -> tuple[np.ndarray, np.ndarray]:
    """(rotation error in degrees, translation error in cm) of (..., 4, 4) relative poses."""
    return rotation_error_deg(T_est, T_ref), translation_error_cm(T_est, T_ref)


def pose_delta(T) -> tuple[np.ndarray, np.ndarray]:
    """Magnitude of a (..., 4, 4) motion: (translation in metres, rotation in degrees)."""
    T = _np(T)
    return np.linalg.norm(T[..., :3, 3], axis=-1), rotation_error_deg(T, np.broadcast_to(np.eye(4), T.shape))
