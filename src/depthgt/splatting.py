"""The differentiable soft splat of the registration losses (the point rendering of
UnsupervisedR&R: radius ~2 px, up to 16 points per pixel, normalised weighted sum of
depth and features). A leaf module below the registration and the GT renderer
(torch and :mod:`depthgt.rasterise` only).

Layouts: points (B, N, 3) metres in the camera frame, intrinsics (B, 3, 3) at the
output resolution, images (B, C, H, W), depth (B, 1, H, W) metres with 0 = nothing."""

from __future__ import annotations

from typing import NamedTuple

import torch

from depthgt.rasterise import candidates, check_points, segment_rank_keep
from depthgt.shapes import check_shape

__all__ = ["SoftSplat", "splat_soft"]


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

    Long for its docstring (the weights and the compositing rule); its code is 48 lines.
    """
    valid = check_points(points_cam, K, valid, size_hw)
    b, n, _ = points_cam.shape
    check_shape(features, "B N C", "features", {"B": b, "N": n})
    if radius_px <= 0 or max_points < 1:
        raise ValueError(f"radius_px must be > 0 and max_points >= 1, got {radius_px}, {max_points}")
    h, w = int(size_hw[0]), int(size_hw[1])
    c = features.shape[-1]
    n_pix = b * h * w
    cand, z_all = candidates(points_cam, K, valid, (h, w), radius_px=radius_px, min_depth=min_depth)
    z = z_all[cand.point]
    pixel = cand.pixel
    if depth_band_rel is not None:
        with torch.no_grad():
            z_front = torch.full((n_pix,), float("inf"), dtype=z.dtype, device=z.device)
            z_front.scatter_reduce_(0, pixel, z.detach(), reduce="amin")
            keep = z.detach() <= z_front[pixel] * (1.0 + depth_band_rel)
    else:
        keep = torch.ones_like(pixel, dtype=torch.bool)
    keep = segment_rank_keep(pixel, z, keep, max_points, n_pix)
    wgt = (1.0 - cand.d2 / (radius_px * radius_px)).clamp_min(0.0) ** 2 * keep
    feats = features.reshape(b * n, c)[cand.point]
    dtype = torch.promote_types(features.dtype, points_cam.dtype)
    wsum = torch.zeros(n_pix, dtype=wgt.dtype, device=wgt.device).index_add(0, pixel, wgt)
    zsum = torch.zeros(n_pix, dtype=wgt.dtype, device=wgt.device).index_add(0, pixel, wgt * z)
    fsum = torch.zeros(n_pix, c, dtype=dtype, device=wgt.device).index_add(
        0, pixel, wgt[:, None].to(dtype) * feats.to(dtype)
    )
    has = wsum > 0
    denom = torch.where(has, wsum, torch.ones_like(wsum))
    depth = torch.where(has, zsum / denom, torch.zeros_like(zsum))
    fout = torch.where(has[:, None], fsum / denom[:, None].to(dtype), torch.zeros_like(fsum))
    return SoftSplat(
        features=fout.reshape(b, h, w, c).permute(0, 3, 1, 2),
        depth=depth.reshape(b, 1, h, w),
        weight=wsum.reshape(b, 1, h, w),
    )
