"""One estimator of depth-sensor statistics, applied alike to real and synthetic depth.

There is no clean depth for real Kinect frames, so the noise is measured from the
noisy depth alone: on pixels whose 5x5 neighbourhood is fully valid and locally
smooth (depth range within the window below ``smooth_rel`` x depth), the residual of
the depth minus its 5x5 box mean is a local-plane residual (a box mean reproduces a
linear function at the window centre). Its robust standard deviation (1.4826 x MAD)
binned by depth is the noise-versus-distance curve. Holes are counted over the whole
image and over the interior (``border_px`` from every side).

:func:`sensor_statistics` returns a tidy long table; :func:`compare_statistics` puts
a real and a synthetic table side by side with their ratio. The synthetic source is
calibrated so that every ratio lies within a factor 1.5 (see bench/calibrate_noise.py
and tests/test_synth.py).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import cv2
import numpy as np
import pandas as pd

from depthgt.shapes import check_shape

__all__ = ["DEFAULT_BINS_M", "hole_fractions", "plane_residuals", "sensor_statistics", "compare_statistics"]

DEFAULT_BINS_M: tuple[float, ...] = (0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5)


def _check_depth(depth_m: np.ndarray, name: str = "depth_m") -> np.ndarray:
    depth_m = np.asarray(depth_m)
    check_shape(depth_m, "H W", name)
    if not np.isfinite(depth_m).all():
        raise ValueError(f"{name} holds non-finite values")
    return depth_m.astype(np.float32, copy=False)


def hole_fractions(depth_m: np.ndarray, border_px: int = 16) -> tuple[float, float]:
    """Fraction of invalid (0) pixels over the image and over its interior.

    Args:
        depth_m: (H, W) depth in metres, 0 = invalid.
        border_px: width of the border left out for the interior fraction.

    Returns:
        (overall, interior) fractions in [0, 1].
    """
    depth_m = _check_depth(depth_m)
    b = int(border_px)
    inner = depth_m[b : depth_m.shape[0] - b, b : depth_m.shape[1] - b]
    return float((depth_m <= 0).mean()), float((inner <= 0).mean())


def plane_residuals(depth_m: np.ndarray, window: int = 5, smooth_rel: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
    """Local-plane residuals of a depth image.

    Args:
        depth_m: (H, W) depth in metres, 0 = invalid.
        window: odd box size in pixels.
        smooth_rel: a pixel is used when max - min depth over its window is below
            ``smooth_rel * depth`` (no discontinuity, not too steep a slope).

    Returns:
        depth (N,) and residual (N,) in metres of the qualifying pixels.
    """
    depth_m = _check_depth(depth_m)
    if window < 3 or window % 2 == 0:
        raise ValueError(f"window must be odd and >= 3, got {window}")
    valid = (depth_m > 0).astype(np.float32)
    kernel = np.ones((window, window), np.uint8)
    full = cv2.erode(valid, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    mean = cv2.blur(depth_m, (window, window), borderType=cv2.BORDER_REFLECT)
    hi = cv2.dilate(depth_m, kernel)
    lo = cv2.erode(depth_m, kernel)
    use = full & ((hi - lo) < smooth_rel * depth_m)
    return depth_m[use], (depth_m - mean)[use]


def _robust_std(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x)))) if len(x) else float("nan")


def sensor_statistics(
    depths_m: Iterable[np.ndarray],
    bins_m: Sequence[float] = DEFAULT_BINS_M,
    border_px: int = 16,
    window: int = 5,
    smooth_rel: float = 0.03,
) -> pd.DataFrame:
    """Hole fractions and noise versus distance of a set of depth images.

    Args:
        depths_m: (H, W) depth images in metres, 0 = invalid.
        bins_m: depth bin edges in metres for the noise curve.

    Returns:
        Long table with columns metric, bin_lo_m, bin_hi_m, value, unit, n_pixels:
        ``holes_overall`` and ``holes_interior`` (fraction, mean over images; bins NaN)
        and ``noise_std`` per depth bin (metres, robust std of the plane residual).
    """
    overall, interior, zs, rs = [], [], [], []
    for k, d in enumerate(depths_m):
        d = _check_depth(d, f"depths_m[{k}]")
        o, i = hole_fractions(d, border_px)
        overall.append(o)
        interior.append(i)
        z, r = plane_residuals(d, window, smooth_rel)
        zs.append(z)
        rs.append(r)
    if not overall:
        raise ValueError("sensor_statistics: no depth images given")
    z = np.concatenate(zs)
    r = np.concatenate(rs)
    n_img = len(overall)
    rows = [
        dict(
            metric="holes_overall",
            bin_lo_m=np.nan,
            bin_hi_m=np.nan,
            value=float(np.mean(overall)),
            unit="fraction",
            n_pixels=n_img,
        ),
        dict(
            metric="holes_interior",
            bin_lo_m=np.nan,
            bin_hi_m=np.nan,
            value=float(np.mean(interior)),
            unit="fraction",
            n_pixels=n_img,
        ),
    ]
    for lo, hi in zip(bins_m[:-1], bins_m[1:]):
        sel = (z >= lo) & (z < hi)
        rows.append(
            dict(
                metric="noise_std",
                bin_lo_m=float(lo),
                bin_hi_m=float(hi),
                value=_robust_std(r[sel]),
                unit="m",
                n_pixels=int(sel.sum()),
            )
        )
    return pd.DataFrame(rows)


def compare_statistics(real: pd.DataFrame, synth: pd.DataFrame, min_pixels: int = 2000) -> pd.DataFrame:
    """Real and synthetic statistics side by side.

    Returns:
        Table with metric, bin_lo_m, bin_hi_m, unit, real, synthetic, ratio
        (synthetic / real) and ``comparable`` (both bins hold >= ``min_pixels``
        pixels; always true for the hole fractions).
    """
    keys = ["metric", "bin_lo_m", "bin_hi_m", "unit"]
    m = real.merge(synth, on=keys, suffixes=("_real", "_synth"), how="outer")
    out = m[keys].copy()
    out["real"] = m["value_real"]
    out["synthetic"] = m["value_synth"]
    out["ratio"] = m["value_synth"] / m["value_real"]
    is_noise = m["metric"] == "noise_std"
    out["comparable"] = ~is_noise | ((m["n_pixels_real"] >= min_pixels) & (m["n_pixels_synth"] >= min_pixels))
    return out
