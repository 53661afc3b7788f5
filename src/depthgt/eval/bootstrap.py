"""Bootstrap intervals over frames (numpy only).

The tables average per-frame values; their 95 % intervals come from the percentile
bootstrap over frames: ``resamples`` draws of n frames with replacement from the n
frames of a group (numpy ``default_rng(seed)``), the mean of each draw, and the 2.5 and
97.5 percentiles of those means. The draws are one (resamples, n) count matrix, so every
column of a group (every method, every metric, every paired difference) is resampled
with the same frames and the means of all draws are one matrix product: no loop over
draws or frames.

Non-finite values (a frame on which a metric is undefined) are left out of the mean of
a draw, as ``np.nanmean`` would.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from depthgt.shapes import check_shape

__all__ = [
    "BOOTSTRAP_RESAMPLES",
    "BOOTSTRAP_SEED",
    "BOOTSTRAP_LEVEL",
    "MeanInterval",
    "resample_counts",
    "bootstrap_means",
]

BOOTSTRAP_RESAMPLES = 2000
BOOTSTRAP_SEED = 0
BOOTSTRAP_LEVEL = 0.95


class MeanInterval(NamedTuple):
    """Per column (k,): the mean over frames, the interval's bounds, the frames counted."""

    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    frames: np.ndarray


def resample_counts(n: int, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED) -> np.ndarray:
    """(resamples, n) float64: how often each of ``n`` frames is drawn in each resample
    (n draws with replacement per resample, ``np.random.default_rng(seed)``)."""
    if n < 0 or resamples < 1:
        raise ValueError(f"bootstrap: need n >= 0 frames and resamples >= 1, got n={n}, resamples={resamples}")
    if n == 0:
        return np.zeros((resamples, 0))
    idx = np.random.default_rng(seed).integers(0, n, size=(resamples, n))
    flat = (np.arange(resamples)[:, None] * n + idx).ravel()
    return np.bincount(flat, minlength=resamples * n).reshape(resamples, n).astype(np.float64)


def bootstrap_means(
    values: np.ndarray, resamples: int = BOOTSTRAP_RESAMPLES, seed: int = BOOTSTRAP_SEED, level: float = BOOTSTRAP_LEVEL
) -> MeanInterval:
    """Mean of each column over frames with its percentile bootstrap interval.

    Args:
        values: (n_frames, k) per-frame values (NaN/inf: the frame has no value in that
            column); a 1-D array is one column.
        resamples, seed, level: the draws (:func:`resample_counts`) and the interval's
            coverage.

    Returns:
        :class:`MeanInterval` of (k,) arrays (NaN where a column has no finite value).

    >>> m = bootstrap_means(np.array([1.0, 2.0, 3.0, np.nan]))
    >>> float(m.mean[0]), int(m.frames[0]), bool(1.0 <= m.low[0] < 2.0 < m.high[0] <= 3.0)
    (2.0, 3, True)
    """
    v = np.asarray(values, dtype=np.float64)
    if v.ndim == 1:
        v = v[:, None]
    check_shape(v, "n_frames k", "bootstrap: values")
    if not 0.0 < level < 1.0:
        raise ValueError(f"bootstrap: level must be in (0, 1), got {level}")
    ok = np.isfinite(v)
    v0 = np.where(ok, v, 0.0)
    frames = ok.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = v0.sum(axis=0) / frames
        counts = resample_counts(v.shape[0], resamples, seed)
        draws = (counts @ v0) / (counts @ ok)  # (resamples, k): NaN where a draw holds no finite value
    tail = 50.0 * (1.0 - level)
    low = np.full(v.shape[1], np.nan)
    high = np.full(v.shape[1], np.nan)
    has = frames > 0
    if has.any():
        sub = draws[:, has]
        # a draw without any finite frame of a column (possible with very few) is left out
        low[has], high[has] = np.nanpercentile(sub, [tail, 100.0 - tail], axis=0)
    mean[~has] = np.nan
    return MeanInterval(mean, low, high, frames)
