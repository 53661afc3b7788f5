"""Point rendering: the differentiable soft splat (registration losses) and the GT
renderer of paper eq. 5 (weighted z-buffer average of the merged frame-set cloud).

Both renderers share one rasteriser written with tensor ops: every point is paired
with the pixels whose *centres* lie strictly within ``radius_px`` of its sub-pixel
projection (pixel-centre convention of :mod:`depthgt.geometry`: pixel (u, v) covers
[u - 0.5, u + 0.5] x [v - 0.5, v + 0.5]). The (point, pixel) pairs are "candidates";
per-pixel selection (z-buffer, m nearest) is done with ``scatter_reduce`` and a
sort restricted to the pixels that hold more candidates than the cap, so the common
case needs no global sort. No Python loop runs over points or pixels.

Written here rather than taken from PyTorch3D's point rasteriser because PyTorch3D is
not a dependency (its CPU wheels are not available for our torch) and because eq. 5
needs a selection rule (front-surface guard, then m nearest by *pixel distance*)
that its rasteriser (K nearest by depth) does not implement.

Layouts: points (B, N, 3) metres in the camera frame, intrinsics (B, 3, 3) at the
output resolution, images (B, C, H, W), depth (B, 1, H, W) metres with 0 = nothing.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from depthgt.geometry import project

__all__ = ["SoftSplat", "splat_soft"]


# --------------------------------------------------------------------------- helpers


def _check_points(points_cam: torch.Tensor, K: torch.Tensor, valid: torch.Tensor | None, size_hw) -> torch.Tensor:
    if points_cam.ndim != 3 or points_cam.shape[-1] != 3:
        raise ValueError(f"points_cam must be (B, N, 3), got {tuple(points_cam.shape)}")
    b, n, _ = points_cam.shape
    if K.shape != (b, 3, 3):
        raise ValueError(f"K must be ({b}, 3, 3) to match points_cam {tuple(points_cam.shape)}, got {tuple(K.shape)}")
    if len(size_hw) != 2 or int(size_hw[0]) <= 0 or int(size_hw[1]) <= 0:
        raise ValueError(f"size_hw must be (H, W) with positive sizes, got {size_hw}")
    if valid is None:
        return torch.ones(b, n, dtype=torch.bool, device=points_cam.device)
    if valid.shape != (b, n) or valid.dtype != torch.bool:
        raise ValueError(f"valid must be a ({b}, {n}) bool tensor, got {tuple(valid.shape)} {valid.dtype}")
    return valid


class _Candidates(NamedTuple):
    """Flat (point, pixel) pairs; C = number of candidates.

    point: (C,) long index into the flattened (B*N) points.
    pixel: (C,) long index into the flattened (B*H*W) output pixels.
    d2: (C,) squared distance in pixels between the projection and the pixel centre
        (differentiable w.r.t. the points).
    ray: (C, 3) K^-1 [u_c, v_c, 1] of the pixel centre (detached), for plane corrections.
    """

    point: torch.Tensor
    pixel: torch.Tensor
    d2: torch.Tensor
    ray: torch.Tensor | None


def _candidates(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    valid: torch.Tensor,
    size_hw: tuple[int, int],
    radius_px: float,
    min_depth: float,
    want_rays: bool = False,
) -> tuple[_Candidates, torch.Tensor]:
    """Pair every valid point with the pixel centres strictly inside ``radius_px``.

    Returns the candidates and the (B*N,) depth of every point (differentiable).
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
        u, v = u[pid], v[pid]
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
        inside = ((dy2[:, :, None] + dx2[:, None, :]) < r * r).reshape(-1)
        flat = inside.nonzero().squeeze(1)  # index into (P, span, span)
        slot = torch.div(flat, span * span, rounding_mode="floor")
        rem = flat - slot * (span * span)
        oy = torch.div(rem, span, rounding_mode="floor")
        ox = rem - oy * span
        point = pid[slot]
        batch = torch.div(pid, n, rounding_mode="floor")
        base = (batch * h + y0.long()) * w + x0.long()  # pixel index of the window corner
        pixel = base[slot] + oy * w + ox
    # differentiable offsets of the window corner from the projection, gathered per candidate
    corner = torch.stack([x0, y0], dim=1).to(uv_f.dtype) - uv_f[pid]  # (P, 2)
    dc = corner[slot] + torch.stack([ox, oy], dim=1).to(uv_f.dtype)  # (C, 2) pixel centre - projection
    d2 = (dc * dc).sum(dim=1)
    ray = None
    if want_rays:
        with torch.no_grad():
            Kinv = torch.linalg.inv(K.to(torch.float64)).to(points_cam.dtype)
            pix_h = torch.stack([x0[slot] + ox, y0[slot] + oy, torch.ones_like(d2)], dim=1).to(points_cam.dtype)
            ray = torch.einsum("cij,cj->ci", Kinv[batch[slot]], pix_h)
    return _Candidates(point, pixel, d2, ray), z_f


def _segment_rank_keep(pixel: torch.Tensor, key: torch.Tensor, active: torch.Tensor, limit: int, n_pixels: int) -> torch.Tensor:
    """Restrict ``active`` (C,) bool to the ``limit`` active candidates of smallest ``key``
    in every pixel.

    Only candidates of pixels holding more than ``limit`` active candidates are sorted
    (by the composite key pixel + normalised key, in float64), so the common case
    costs one ``bincount``. Ties keep candidate order (stable sort): deterministic.
    """
    if pixel.numel() == 0:
        return active
    counts = torch.bincount(pixel, weights=active.to(torch.float32), minlength=n_pixels)
    over = (active & (counts[pixel] > limit)).nonzero().squeeze(1)
    if over.numel() == 0:
        return active
    k = key.detach()[over].to(torch.float64)
    lo, hi = k.min(), k.max()
    kn = (k - lo) / (hi - lo).clamp_min(1e-30) * 0.5  # in [0, 0.5]: stays inside its pixel's unit interval
    pix_over = pixel[over]
    order = torch.sort(pix_over.to(torch.float64) + kn, stable=True).indices
    pix_sorted = pix_over[order]
    pos = torch.arange(order.numel(), device=pixel.device)
    starts = torch.ones_like(pix_sorted, dtype=torch.bool)
    starts[1:] = pix_sorted[1:] != pix_sorted[:-1]
    first = torch.cummax(torch.where(starts, pos, torch.zeros_like(pos)), dim=0).values
    rank = pos - first
    out = active.clone()
    out[over[order[rank >= limit]]] = False
    return out


# --------------------------------------------------------------------------- soft splat


class SoftSplat(NamedTuple):
    """Output of :func:`splat_soft`.

    features: (B, C, H, W) normalised weighted sum of the point features (0 where
        nothing was rendered).
    depth: (B, 1, H, W) normalised weighted sum of the point depths in metres (0 =
        nothing rendered).
    weight: (B, 1, H, W) sum of the splat weights of the kept points (0 = nothing).
    """

    features: torch.Tensor
    depth: torch.Tensor
    weight: torch.Tensor


def splat_soft(
    points_cam: torch.Tensor,
    features: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    valid: torch.Tensor | None = None,
    radius_px: float = 2.0,
    max_points: int = 16,
    depth_band_rel: float | None = 0.05,
    min_depth: float = 1e-3,
) -> SoftSplat:
    """Differentiable point rendering with soft splats (SynSin / UnsupervisedR&R style).

    Each point touches the pixels whose centres lie within ``radius_px`` of its
    sub-pixel projection, with weight ``w = (1 - d^2 / r^2)^2`` (``d`` the distance
    in pixels): smooth, 1 at the centre, falling to zero with zero slope at the radius,
    so the output is continuous in the point positions.

    Compositing (a soft z-buffer with a normalised weighted sum): per pixel, the
    candidates farther than ``z_front * (1 + depth_band_rel)`` are dropped (``z_front``
    the nearest candidate depth at that pixel; a hard occlusion test so that surfaces
    seen through gaps of the front surface do not bleed in), then the ``max_points``
    nearest in depth are kept, and the pixel receives ``sum(w f) / sum(w)`` for the
    features and ``sum(w z) / sum(w)`` for the depth. We chose the normalised sum over
    alpha compositing because the registration losses compare depth and colour
    values, which a normalised sum reproduces without a fall-off at splat borders.

    Gradients flow to ``points_cam`` (through the projection, the weights and the
    depth) and to ``features``; the selection itself (radius, occlusion, cap) is
    piecewise constant.

    Args:
        points_cam: (B, N, 3) points in metres in the camera to render into.
        features: (B, N, C) per-point features (e.g. RGB in [0, 1]).
        K: (B, 3, 3) intrinsics at ``size_hw``.
        size_hw: output (H, W).
        valid: (B, N) bool, points to render; None = all. Points behind the camera
            (z <= ``min_depth``) or projecting outside the image are ignored.
        radius_px: splat radius in output pixels.
        max_points: at most this many points per pixel (nearest in depth).
        depth_band_rel: relative depth band behind the front candidate; None keeps
            all candidates (only the ``max_points`` cap applies).
        min_depth: points with z at or below this (metres) are ignored.

    Returns:
        :class:`SoftSplat` with features (B, C, H, W), depth and weight (B, 1, H, W).
    """
    valid = _check_points(points_cam, K, valid, size_hw)
    b, n, _ = points_cam.shape
    if features.ndim != 3 or features.shape[:2] != (b, n):
        raise ValueError(f"features must be ({b}, {n}, C) to match points_cam, got {tuple(features.shape)}")
    if radius_px <= 0 or max_points < 1:
        raise ValueError(f"radius_px must be > 0 and max_points >= 1, got {radius_px}, {max_points}")
    h, w = int(size_hw[0]), int(size_hw[1])
    c = features.shape[-1]
    n_pix = b * h * w
    cand, z_all = _candidates(points_cam, K, valid, (h, w), radius_px, min_depth)
    z = z_all[cand.point]
    pixel = cand.pixel
    if depth_band_rel is not None:
        with torch.no_grad():
            z_front = torch.full((n_pix,), float("inf"), dtype=z.dtype, device=z.device)
            z_front.scatter_reduce_(0, pixel, z.detach(), reduce="amin")
            keep = z.detach() <= z_front[pixel] * (1.0 + depth_band_rel)
    else:
        keep = torch.ones_like(pixel, dtype=torch.bool)
    keep = _segment_rank_keep(pixel, z, keep, max_points, n_pix)
    wgt = (1.0 - cand.d2 / (radius_px * radius_px)).clamp_min(0.0) ** 2 * keep
    feats = features.reshape(b * n, c)[cand.point]
    dtype = torch.promote_types(features.dtype, points_cam.dtype)
    wsum = torch.zeros(n_pix, dtype=wgt.dtype, device=wgt.device).index_add(0, pixel, wgt)
    zsum = torch.zeros(n_pix, dtype=wgt.dtype, device=wgt.device).index_add(0, pixel, wgt * z)
    fsum = torch.zeros(n_pix, c, dtype=dtype, device=wgt.device).index_add(0, pixel, wgt[:, None].to(dtype) * feats.to(dtype))
    has = wsum > 0
    denom = torch.where(has, wsum, torch.ones_like(wsum))
    depth = torch.where(has, zsum / denom, torch.zeros_like(zsum))
    fout = torch.where(has[:, None], fsum / denom[:, None].to(dtype), torch.zeros_like(fsum))
    return SoftSplat(
        features=fout.reshape(b, h, w, c).permute(0, 3, 1, 2),
        depth=depth.reshape(b, 1, h, w),
        weight=wsum.reshape(b, 1, h, w),
    )
