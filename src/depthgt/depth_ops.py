"""Operators on depth images shared by training and evaluation (a leaf module).

Valid-aware average pooling (:func:`valid_avg_pool`, the one implementation behind
LapDEN's pyramid, its push-pull hole fill, the losses' coarse targets and the box fill
of the JF baseline), forward gradients, and the structure term L_S of the paper's
eq. 6 (:func:`structure_loss`), which is both a training loss
(:mod:`depthgt.enhance.losses`) and a table metric (:func:`depthgt.eval.metrics.ls_distance`).

Conventions: depth (B, 1, H, W) in metres, 0 = invalid; validity (B, 1, H, W) bool or
{0, 1} float.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from depthgt.shapes import check_shape

__all__ = [
    "valid_avg_pool",
    "masked_avg_pool",
    "masked_mean",
    "forward_gradients",
    "max_gradient_magnitude",
    "structure_loss",
]


def valid_avg_pool(
    depth_m: torch.Tensor,
    valid: torch.Tensor,
    kernel: int,
    stride: int | None = None,
    padding: int = 0,
    ceil_mode: bool = False,
    count_include_pad: bool = True,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean of the valid pixels in each pooling window (``F.avg_pool2d``'s windows).

    Computed as the ratio of two average pools (depth x validity, validity) with the
    same divisor, so the divisor cancels: also right at ceil-mode and padded borders.

    Args:
        depth_m: (B, 1, H, W) metres.
        valid: (B, 1, H, W) bool or {0, 1} float.
        kernel, stride, padding, ceil_mode, count_include_pad: as ``F.avg_pool2d``.

    Returns:
        mean (B, 1, h, w) metres, 0 where a window holds no valid pixel, and that
        validity (B, 1, h, w) bool.

    >>> d = torch.tensor([[[[1.0, 0.0], [3.0, 0.0]]]])
    >>> mean, ok = valid_avg_pool(d, d > 0, 2)
    >>> float(mean), bool(ok)
    (2.0, True)
    """
    w = valid.to(depth_m.dtype)
    num = F.avg_pool2d(
        depth_m * w, kernel, stride=stride, padding=padding, ceil_mode=ceil_mode, count_include_pad=count_include_pad
    )
    den = F.avg_pool2d(
        w, kernel, stride=stride, padding=padding, ceil_mode=ceil_mode, count_include_pad=count_include_pad
    )
    ok = den > 0
    return torch.where(ok, num / den.clamp_min(1e-12), torch.zeros_like(num)), ok


def masked_avg_pool(depth_m: torch.Tensor, valid: torch.Tensor, factor: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Valid-aware average pooling of depth by an integer factor (blocks of
    ``factor`` x ``factor`` pixels, :func:`valid_avg_pool`).

    Args:
        depth_m: (B, 1, H, W) metres, 0 = invalid.
        valid: (B, 1, H, W) bool or {0, 1} float.
        factor: pooling factor; H and W must be divisible by it.

    Returns:
        depth (B, 1, H/f, W/f), mean of the valid pixels of each block (0 where none),
        and its validity (B, 1, H/f, W/f) bool.
    """
    check_shape(depth_m, "B 1 H W", "depth_m")
    if depth_m.shape[-1] % factor or depth_m.shape[-2] % factor:
        raise ValueError(f"depth shape {tuple(depth_m.shape)} not divisible by pooling factor {factor}")
    if factor == 1:
        v = valid.bool()
        return depth_m * v, v
    return valid_avg_pool(depth_m, valid, factor)


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x`` over ``mask`` (broadcast); 0 when the mask is empty (no NaN)."""
    m = mask.to(x.dtype).expand_as(x)
    return (x * m).sum() / m.sum().clamp_min(1.0)


def forward_gradients(depth_m: torch.Tensor, valid: torch.Tensor):
    """Forward-difference depth gradients with their validity.

    Hand-written rather than kornia's ``spatial_gradient``: a 2-pixel forward
    difference lets the validity be exact (both pixels valid) where a Sobel kernel
    would mix in holes from a 3x3 support.

    Args:
        depth_m: (B, 1, H, W) metres.
        valid: (B, 1, H, W) bool.

    Returns:
        gx, gy (B, 1, H, W) metres per pixel (last column / row 0) and their
        validity vx, vy (B, 1, H, W) bool.
    """
    check_shape(depth_m, "B 1 H W", "depth_m")
    gx = F.pad(depth_m[..., :, 1:] - depth_m[..., :, :-1], (0, 1, 0, 0))
    gy = F.pad(depth_m[..., 1:, :] - depth_m[..., :-1, :], (0, 0, 0, 1))
    v = valid.bool()
    vx = F.pad(v[..., :, 1:] & v[..., :, :-1], (0, 1, 0, 0))
    vy = F.pad(v[..., 1:, :] & v[..., :-1, :], (0, 0, 0, 1))
    return gx, gy, vx, vy


def max_gradient_magnitude(depth_m: torch.Tensor, valid: torch.Tensor, window: int = 5, eps: float = 1e-12):
    """max_{q in W(p)} |grad d_q| of eq. 6 over a ``window`` x ``window`` neighbourhood.

    |grad d| uses forward differences; pixels whose gradient is undefined (a hole
    among p, its right or lower neighbour) contribute 0 to the max.

    Args:
        depth_m: (B, 1, H, W) metres; valid: (B, 1, H, W) bool; window: odd int.

    Returns:
        (B, 1, H, W) metres per pixel.
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd int, got {window}")
    gx, gy, vx, vy = forward_gradients(depth_m, valid)
    vg = vx & vy
    mag = torch.sqrt(gx * gx + gy * gy + eps) * vg.to(depth_m.dtype)
    return F.max_pool2d(mag, window, stride=1, padding=window // 2)


def structure_loss(pred: torch.Tensor, target: torch.Tensor, valid: torch.Tensor, window: int = 5) -> torch.Tensor:
    """L_S (paper eq. 6): mean over valid pixels of the squared difference of the
    windowed max gradient magnitudes of ``pred`` and ``target`` (units m^2/px^2).

    Args:
        pred, target: (B, 1, H, W) metres; valid: (B, 1, H, W) bool, where the
            target's gradients are trusted (both images are masked with it).
    """
    check_shape(target, "B 1 H W", "target", check_shape(pred, "B 1 H W", "pred"))
    mp = max_gradient_magnitude(pred, valid, window)
    mt = max_gradient_magnitude(target, valid, window)
    return masked_mean((mp - mt) ** 2, valid)
