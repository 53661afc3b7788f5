"""The sensor noise law: the depth std of a disparity sensor grows as z^2
(``sigma(z) = sqrt(sigma_abs^2 + (sigma_1m z^2)^2)``), and its coefficient estimated
from a frame set's own depth. A leaf module (torch; numba for one search, imported on
first use) below the registration (the residual check in units of the noise) and the GT
renderer (tolerances, confidence)."""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F

from depthgt.rasterise import resampled_positions
from depthgt.shapes import check_shape

__all__ = [
    "KINECT_SIGMA_1M",
    "sorted_residuals",
    "noise_sigma_1m_of",
    "depth_sigma_m",
    "estimate_noise_sigma_1m",
    "second_differences",
    "Residuals",
    "second_difference_residuals",
    "noise_sigma_1m_from",
]

#: sigma of one depth sample at 1 m (metres) used when neither the settings nor the
#: caller give one: Kinect v1 (1/8-px disparity steps and noise, bench/calibrate_noise.py)
KINECT_SIGMA_1M = 0.0012


def depth_sigma_m(z_m: torch.Tensor, sigma_1m: float, sigma_abs_m: float) -> torch.Tensor:
    """Expected std (metres) of a disparity sensor's depth sample at depth ``z_m``:
    ``sqrt(sigma_abs_m^2 + (sigma_1m z^2)^2)``."""
    return torch.sqrt(sigma_abs_m**2 + (sigma_1m * z_m * z_m) ** 2)


def second_differences(
    iz: torch.Tensor, ok: torch.Tensor, dim: int, pos: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Residual of each pixel's inverse depth from the line through its two neighbours
    along ``dim`` (3: x, 2: y) at their sample positions ``pos``, scaled to the std of
    one sample (zero on any plane), and where all three are valid. Shapes: the input's,
    zero-padded at the two ends of ``dim``."""
    n = iz.shape[dim]
    f0, f1, f2 = iz.narrow(dim, 0, n - 2), iz.narrow(dim, 1, n - 2), iz.narrow(dim, 2, n - 2)
    both = ok.narrow(dim, 0, n - 2) & ok.narrow(dim, 1, n - 2) & ok.narrow(dim, 2, n - 2)
    shape = [1] * iz.ndim
    shape[dim] = n - 2
    a = ((pos[2:] - pos[1:-1]) / (pos[2:] - pos[:-2])).view(shape)
    r = (f1 - a * f0 - (1 - a) * f2) / torch.sqrt(1 + a * a + (1 - a) ** 2)
    pad = [0, 0] * (iz.ndim - dim - 1) + [1, 1]
    return F.pad(r, pad), F.pad(both, pad)


class Residuals(NamedTuple):
    """The :func:`second_differences` of J depth images along x and y (float64).

    iz: (J, 1, H, W) inverse depth, 0 where invalid; ok: (J, 1, H, W) valid depth;
    r, both: the residuals and their validity along x then y (a direction with fewer
    than 3 pixels is left out).
    """

    iz: torch.Tensor
    ok: torch.Tensor
    r: tuple[torch.Tensor, ...]
    both: tuple[torch.Tensor, ...]


def second_difference_residuals(depth_m: torch.Tensor, src_hw: tuple[int, int] | None = None) -> Residuals:
    """:class:`Residuals` of (J, 1, H, W) depth in metres (0 = invalid), nearest-resized
    from ``src_hw`` (None: sampled at the pixel centres). Computed once per frame set,
    they give the noise estimate of every subset of its frames
    (:func:`noise_sigma_1m_from`) and the renderer's depth-edge test."""
    check_shape(depth_m, "J 1 H W", "depth_m")
    d = depth_m.detach().to(torch.float64)
    h, w = d.shape[-2:]
    ok = d > 0
    iz = torch.where(ok, 1.0 / d.clamp_min(1e-9), torch.zeros_like(d))
    src = (h, w) if src_hw is None else src_hw
    rs, boths = [], []
    for dim, n_src, n in ((3, src[1], w), (2, src[0], h)):
        if n < 3:
            continue
        r, both = second_differences(iz, ok, dim, resampled_positions(n_src, n, d.device, torch.float64))
        rs.append(r)
        boths.append(both)
    return Residuals(iz, ok, tuple(rs), tuple(boths))


def noise_sigma_1m_from(res: Residuals, frames: slice = slice(None), min_pixels: int = 2000) -> float:
    """:func:`estimate_noise_sigma_1m` of the frames ``frames`` of ``res`` (the same
    value as estimating it from those frames' depth alone)."""
    if len(res.r) < 2:
        return KINECT_SIGMA_1M
    n = sum(int(both[frames].sum()) for both in res.both)
    if n == 0 or n < min_pixels:
        return KINECT_SIGMA_1M
    # the invalid residuals as +inf: the k-th smallest of all is the k-th of the valid ones
    # (k <= n), without gathering them into a copy first
    r = torch.cat(
        [torch.where(both[frames], r[frames].abs(), float("inf")).reshape(-1) for r, both in zip(res.r, res.both)]
    )
    return float(r.kthvalue(max(1, int(round(0.6827 * n)))).values)


def estimate_noise_sigma_1m(
    depth_m: torch.Tensor, src_hw: tuple[int, int] | None = None, min_pixels: int = 2000
) -> float:
    """Sigma of one depth sample at 1 m (metres, the z^2 law) estimated from noisy depth alone.

    In inverse depth a disparity sensor's noise is about constant and every plane is
    affine in screen space, so the residual of a pixel from the line through its two
    neighbours (along x and along y, at the true sample positions when the depth was
    nearest-resized from ``src_hw``) is pure noise on any plane, at any slant or
    range. Its 68th percentile of |residual| (sigma for Gaussian noise; robust to the
    depth edges and to the zero residuals of quantised fronto-parallel surfaces) is
    the sigma in 1/m, i.e. the depth sigma at 1 m. Measured: 1.17e-3 on the 7-Scenes
    fixture and on the synthetic Kinect v1 model, 3.2e-3 on the coarse_stereo
    profile, ~0 on clean depth.

    Args:
        depth_m: (J, 1, H, W) depth in metres, 0 = invalid.
        src_hw: size the depth was nearest-resized from, or None (pixel centres).

    Returns:
        sigma at 1 m in metres; :data:`KINECT_SIGMA_1M` when fewer than ``min_pixels``
        residuals exist.
    """
    return noise_sigma_1m_from(second_difference_residuals(depth_m, src_hw), min_pixels=min_pixels)


def sorted_residuals(res: Residuals) -> list[torch.Tensor]:
    """Per frame of ``res`` (J frames), its valid |residuals| along x and y, sorted
    (float64, CPU): what :func:`noise_sigma_1m_of` estimates any set of frames from."""
    out = []
    for k in range(res.iz.shape[0]):
        if len(res.r) < 2:
            out.append(torch.zeros(0, dtype=torch.float64))
            continue
        r = torch.cat([r_[k][both[k]].abs() for r_, both in zip(res.r, res.both)])
        # numpy's sort of float64 (SIMD): the same values ~15x faster than torch.sort on one thread
        out.append(torch.from_numpy(np.sort(r.detach().to("cpu", torch.float64).numpy())))
    return out


def noise_sigma_1m_of(residuals: list[torch.Tensor], min_pixels: int = 2000) -> float:
    """The sensor's depth sigma at 1 m estimated from the frames whose sorted residuals
    are ``residuals`` (:func:`sorted_residuals`): exactly :func:`noise_sigma_1m_from`
    of those frames -- the 68th percentile of their residuals, the k-th smallest of
    their union, found by bisection on the values without merging them -- or
    :data:`KINECT_SIGMA_1M` when fewer than ``min_pixels`` residuals exist.

    Written by hand: torch has no k-th value of a union of sorted arrays."""
    arrays = [r.numpy() for r in residuals if r.numel()]
    n = sum(a.size for a in arrays)
    if n == 0 or n < min_pixels:
        return KINECT_SIGMA_1M
    k = max(1, int(round(0.6827 * n)))
    # the non-negative float64s order as their bit patterns: the search runs on those
    from numba.typed import List

    bits = _compiled_kth()(List([a.view(np.int64) for a in arrays]), k)
    return float(np.int64(bits).view(np.float64))


def _kth_bits(arrays, k):  # pragma: no cover (compiled by _compiled_kth)
    """The k-th smallest of the union of the sorted int64 ``arrays``: the smallest value
    with at least k of them at or below it, by bisection on the values (each step one
    binary search per array)."""
    lo, hi = 0, 0
    for a in arrays:
        hi = max(hi, a[-1])
    while lo < hi:
        mid = lo + (hi - lo) // 2
        at_or_below = 0
        for a in arrays:
            at_or_below += np.searchsorted(a, mid, side="right")
        if at_or_below >= k:
            hi = mid
        else:
            lo = mid + 1
    return lo


@functools.cache
def _compiled_kth():
    """:func:`_kth_bits` compiled (numba, imported on first use): the bisection's ~60
    steps of a binary search per frame had cost ~1.2 ms of Python per call (0.15 ms
    compiled), several calls per frame set (the renderer's and the refinement's noise
    law). Written by hand: no library takes the k-th value of a union of sorted arrays."""
    import numba

    return numba.njit(cache=True, nogil=True)(_kth_bits)
