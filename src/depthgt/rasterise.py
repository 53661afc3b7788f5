"""The point rasteriser shared by the soft splat (:mod:`depthgt.splatting`) and the GT
renderer (:mod:`depthgt.gt.render`): every point is paired with the pixels whose sample
positions lie strictly within ``radius_px`` of its sub-pixel projection (pixel-centre
convention of :mod:`depthgt.geometry`; the GT renderer can sample each pixel at the
source pixel its nearest-resized input came from instead, see
:func:`resampled_positions`). The (point, pixel) pairs are "candidates"; the sorts and
ranks within a pixel are the compositors' building blocks. A leaf module (torch only).

Written here rather than taken from PyTorch3D's point rasteriser because PyTorch3D is
not among the project's dependencies and its rasteriser keeps the K nearest points by
depth, not every point within the radius that the GT's surface choice needs.

Layouts: points (B, N, 3) metres in the camera frame, intrinsics (B, 3, 3) at the
output resolution."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from depthgt.geometry import project
from depthgt.shapes import check_shape

__all__ = [
    "Candidates",
    "candidates",
    "check_points",
    "resampled_positions",
    "front_to_back",
    "segment_rank_keep",
    "rank_in_pixel",
]


def check_points(points_cam: torch.Tensor, K: torch.Tensor, valid: torch.Tensor | None, size_hw) -> torch.Tensor:
    """``valid`` (B, N) bool (all True for None) once ``points_cam`` (B, N, 3), ``K``
    (B, 3, 3) and ``size_hw`` (H, W) are checked."""
    sizes = check_shape(points_cam, "B N 3", "points_cam")
    check_shape(K, "B 3 3", "K", sizes)
    if len(size_hw) != 2 or int(size_hw[0]) <= 0 or int(size_hw[1]) <= 0:
        raise ValueError(f"size_hw must be (H, W) with positive sizes, got {size_hw}")
    if valid is None:
        return torch.ones(sizes["B"], sizes["N"], dtype=torch.bool, device=points_cam.device)
    check_shape(valid, "B N", "valid", sizes)
    if valid.dtype != torch.bool:
        raise ValueError(f"valid must be a bool tensor, got {valid.dtype}")
    return valid


class Candidates(NamedTuple):
    """Flat (point, pixel) pairs; C = number of candidates.

    point: (C,) long index into the flattened (B*N) points.
    pixel: (C,) long index into the flattened (B*H*W) output pixels.
    d2: (C,) squared distance in pixels between the projection and the pixel centre.
    dx, dy: (C,) pixel centre minus projection, d2 = dx^2 + dy^2.
    d2, dx and dy are differentiable w.r.t. the points.
    """

    point: torch.Tensor
    pixel: torch.Tensor
    d2: torch.Tensor
    dx: torch.Tensor
    dy: torch.Tensor


def candidates(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    valid: torch.Tensor,
    size_hw: tuple[int, int],
    *,
    radius_px: float,
    min_depth: float,
) -> tuple[Candidates, torch.Tensor]:
    """Pair every valid point with the pixel centres strictly inside ``radius_px`` (the
    soft splat's rasteriser; the GT renderer's, which samples the pixels off their
    centres and works in row blocks, is :mod:`depthgt.gt.render.rasteriser`). The
    candidates come point by point, in the order of the flattened points. Returns the
    candidates and the (B*N,) depth of every point (differentiable).
    """
    b, n, _ = points_cam.shape
    h, w = int(size_hw[0]), int(size_hw[1])
    uv, z = project(points_cam, K, eps=min_depth)
    uv_f = uv.reshape(-1, 2)
    z_f = z.reshape(-1)
    r = float(radius_px)
    with torch.no_grad():
        u, v = uv_f[:, 0], uv_f[:, 1]
        ok = valid.reshape(-1) & (z_f > min_depth) & torch.isfinite(u) & torch.isfinite(v)
        ok &= (u > -r) & (u < w - 1 + r) & (v > -r) & (v < h - 1 + r)
        pid = ok.nonzero().squeeze(1)
        u, v = u.index_select(0, pid), v.index_select(0, pid)
        # Every pixel centre within r of (u, v) lies in [ceil(u - r), floor(u + r)]:
        # at most floor(2r) + 1 columns (and rows) starting at ceil(u - r).
        span = int(math.floor(2 * r)) + 1
        off = torch.arange(span, device=points_cam.device, dtype=u.dtype)
        x0 = torch.ceil(u - r)
        y0 = torch.ceil(v - r)
        cols = x0[:, None] + off[None, :]  # (P, span) candidate pixel columns
        rows = y0[:, None] + off[None, :]
        inf = torch.tensor(float("inf"), dtype=u.dtype, device=u.device)
        # per-axis squared distances; out-of-image columns/rows get +inf so that the
        # (P, span, span) sum below needs a single comparison
        dx2 = torch.where((cols >= 0) & (cols < w), (cols - u[:, None]) ** 2, inf)
        dy2 = torch.where((rows >= 0) & (rows < h), (rows - v[:, None]) ** 2, inf)
        inside = (dy2[:, :, None] + dx2[:, None, :]) < r * r  # (P, span, span)
        del dx2, dy2, cols, rows  # free the temporaries early
        slot, oy, ox = _cells_inside(inside)
        del inside
        point = pid.index_select(0, slot)
        batch = torch.div(pid, n, rounding_mode="floor")
        base = (batch * h + y0.long()) * w + x0.long()  # pixel index of the window corner
        pixel = base.index_select(0, slot) + oy * w + ox
    # differentiable offsets (pixel centre - projection), gathered per candidate
    uv_p = uv_f.index_select(0, pid)
    dx = (x0 - uv_p[:, 0]).index_select(0, slot) + ox.to(uv_f.dtype)
    dy = (y0 - uv_p[:, 1]).index_select(0, slot) + oy.to(uv_f.dtype)
    d2 = dx * dx + dy * dy
    return Candidates(point, pixel, d2, dx, dy), z_f


def _cells_inside(inside: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(point slot, row offset, column offset) of every True cell of ``inside`` (P, S, S),
    in row-major order: ``inside.nonzero()`` unravelled by hand, because torch's nonzero
    on the flat tensor and this unravelling take half the time of nonzero on three
    dimensions. The slot of flat index i = S^2 k + j (0 <= j < S^2) is
    floor((i + 1/2) / S^2) in float64: (j + 1/2) / S^2 lies at least 1 / (2 S^2) from
    any integer, far beyond the product's rounding error (< 2^-12 for i < 2^40), so it
    is exact, and cheaper than torch's integer division; the cell j gives both offsets
    from a table of S^2 entries."""
    span = inside.shape[-1]
    cells = span * span
    if inside.numel() >= 2**40:
        raise ValueError(f"too many candidate cells for one rasterisation: {inside.numel()}")
    flat = inside.reshape(-1).nonzero().squeeze(1)
    slot = flat.to(torch.float64).add_(0.5).mul_(1.0 / cells).long()
    cell = flat - slot * cells
    table = torch.arange(cells, device=flat.device)
    return (
        slot,
        torch.div(table, span, rounding_mode="floor").index_select(0, cell),
        (table % span).index_select(0, cell),
    )


def _footprint(u: torch.Tensor, v: torch.Tensor, r: float, shift: float):
    """The pixels a point's footprint of radius ``r`` at (``u``, ``v``) may reach, on a grid
    whose sample positions lie within ``shift`` of the pixel centres: sample positions
    within r of u lie in columns [ceil(u - r - shift), floor(u + r + shift)]. Returns the
    first column and row of each point, (P,) long, and the offsets 0..span-1 of its
    window."""
    span = int(math.floor(2 * (r + shift))) + 1
    off = torch.arange(span, device=u.device)
    return torch.ceil(u - r - shift).long(), torch.ceil(v - r - shift).long(), off


def resampled_positions(n_src: int, n_dst: int, device=None, dtype=torch.float32) -> torch.Tensor:
    """(n_dst,) position, in output pixel units, of the source pixel centre that
    :func:`depthgt.geometry.resize_depth_nearest` takes each output pixel from (the
    same index rule): where the resized input and the resized truth were sampled.
    Within 0.5 px of the output pixel centres."""
    i = ((torch.arange(n_dst, device=device, dtype=torch.float64) + 0.5) * (n_src / n_dst)).floor().clamp_(0, n_src - 1)
    return ((i + 0.5) * (n_dst / n_src) - 0.5).to(dtype)


def front_to_back(iz: torch.Tensor) -> torch.Tensor:
    """(N,) permutation of points by decreasing inverse depth ``iz`` (N,) > 0, equal
    values in index order.

    One stable integer sort of the floats' bit patterns, which order as the positive
    floats they encode (IEEE 754): exact, and a radix sort on the CPU (~7x faster than a
    float sort). Written by hand: torch sorts floats by comparison only. NaN (no depth)
    sorts first; such points have no candidates.
    """
    ints = {
        torch.float64: torch.int64,
        torch.float32: torch.int32,
        torch.float16: torch.int16,
        torch.bfloat16: torch.int16,
    }
    bits = iz.detach().contiguous().view(ints[iz.dtype])
    return torch.sort(-bits, stable=True).indices


def segment_rank_keep(
    pixel: torch.Tensor, key: torch.Tensor, active: torch.Tensor, limit: int, n_pixels: int
) -> torch.Tensor:
    """Restrict ``active`` (C,) bool to the ``limit`` active candidates of smallest ``key``
    in every pixel.

    Only candidates of pixels holding more than ``limit`` active candidates are sorted
    (by the composite key pixel + normalised key, in float64), so the common case
    costs one ``bincount``. Ties keep candidate order (stable sort): deterministic.
    """
    if pixel.numel() == 0:
        return active
    counts = torch.bincount(pixel, weights=active.to(torch.float32), minlength=n_pixels)
    over = (active & (counts.index_select(0, pixel) > limit)).nonzero().squeeze(1)
    if over.numel() == 0:
        return active
    out = active.clone()
    out[over[rank_in_pixel(pixel[over], key.detach()[over]) >= limit]] = False
    return out


def rank_in_pixel(pixel: torch.Tensor, key: torch.Tensor) -> torch.Tensor:
    """(C,) rank of every candidate among the candidates of its pixel by ascending key
    (0 = smallest). One stable sort on the composite key pixel + normalised key in
    float64, so ties keep candidate order (deterministic)."""
    k = key.to(torch.float64)
    lo, hi = k.min(), k.max()
    kn = (k - lo) / (hi - lo).clamp_min(1e-30) * 0.5  # in [0, 0.5]: stays inside its pixel's unit interval
    order = torch.sort(pixel.to(torch.float64) + kn, stable=True).indices
    pix_sorted = pixel.index_select(0, order)
    pos = torch.arange(order.numel(), device=pixel.device)
    starts = torch.ones_like(pix_sorted, dtype=torch.bool)
    starts[1:] = pix_sorted[1:] != pix_sorted[:-1]
    first = torch.cummax(torch.where(starts, pos, torch.zeros_like(pos)), dim=0).values
    rank = torch.empty_like(pos)
    rank[order] = pos - first
    return rank
