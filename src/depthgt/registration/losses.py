"""R&R consistency losses for a batch of frame pairs (paper eq. 3, summed as in eq. 4).

* depth L1: the source cloud, moved by ``T_src_to_dst`` and rendered into the
  destination camera, against the destination's raw depth, over pixels where both are
  valid;
* photometric L1: the rendered source colours against the destination image over
  rendered pixels;
* correspondence loss: weighted mean squared 3D residual of the matches.

The renderer is passed in (``render_fn``, signature of
:func:`depthgt.splatting.splat_soft`) so that the losses do not depend on one splatting
implementation.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from depthgt.geometry import transform_points
from depthgt.shapes import check_shape
from depthgt.splatting import splat_soft

__all__ = ["default_render_fn", "render_losses", "correspondence_loss"]

RenderFn = Callable[..., object]


def default_render_fn() -> RenderFn:
    """The project's differentiable soft splatting, :func:`depthgt.splatting.splat_soft`."""
    return splat_soft


def render_losses(
    points_src: torch.Tensor,
    rgb_src: torch.Tensor,
    valid_src: torch.Tensor,
    T_src_to_dst: torch.Tensor,
    depth_dst: torch.Tensor,
    rgb_dst: torch.Tensor,
    K: torch.Tensor,
    render_fn: RenderFn,
    radius_px: float = 2.0,
    max_points: int = 16,
    min_weight: float = 1e-4,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Depth and photometric L1 of the source cloud rendered into the destination view.

    Args:
        points_src: (P, N, 3) source points in the source camera (metres).
        rgb_src: (P, N, 3) their colours in [0, 1].
        valid_src: (P, N) bool.
        T_src_to_dst: (P, 4, 4) source-to-destination transforms (differentiable).
        depth_dst: (P, 1, H, W) destination depth (metres, 0 invalid).
        rgb_dst: (P, 3, H, W) destination colour.
        K: (P, 3, 3) intrinsics at (H, W).
        render_fn: ``splat_soft``-like renderer returning ``.features``, ``.depth``
            and ``.weight``.

    Returns:
        depth L1 (P,) in metres and photometric L1 (P,) per pair (0 where a pair has
        no overlapping pixel).
    """
    P, N, _ = points_src.shape
    sizes = check_shape(depth_dst, "P 1 H W", "depth_dst", {"P": P})
    check_shape(rgb_dst, "P 3 H W", "rgb_dst", sizes)
    pts = transform_points(T_src_to_dst.to(points_src.dtype), points_src)
    out = render_fn(pts, rgb_src, K, tuple(depth_dst.shape[-2:]), valid_src, radius_px=radius_px, max_points=max_points)
    rendered = out.weight > min_weight  # (P, 1, H, W)
    m_depth = (rendered & (depth_dst > 0)).to(pts.dtype)
    m_photo = rendered.to(pts.dtype)
    l_depth = ((out.depth - depth_dst).abs() * m_depth).flatten(1).sum(1) / m_depth.flatten(1).sum(1).clamp(min=1)
    l_photo = ((out.features - rgb_dst).abs().mean(1, keepdim=True) * m_photo).flatten(1).sum(1) / m_photo.flatten(
        1
    ).sum(1).clamp(min=1)
    return l_depth, l_photo


def correspondence_loss(
    T_src_to_dst: torch.Tensor, points_src: torch.Tensor, points_dst: torch.Tensor, weights: torch.Tensor
) -> torch.Tensor:
    """``|M|^-1 sum_M w |T p - q|^2`` per pair: (P,) in m^2 (paper eq. 3, L_C)."""
    R = T_src_to_dst[:, :3, :3].to(points_src.dtype)
    t = T_src_to_dst[:, :3, 3].to(points_src.dtype)
    res = (points_src @ R.transpose(1, 2) + t[:, None] - points_dst).pow(2).sum(-1)
    return (weights * res).mean(1)
