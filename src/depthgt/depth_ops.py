"""Operators on depth images shared by training and evaluation (a leaf module).

Valid-aware average pooling (:func:`valid_avg_pool`, the one implementation behind
LapDEN's pyramid, its push-pull hole fill, the losses' coarse targets and the box fill
of the JF baseline), forward gradients, surface normals (:func:`depth_normals`, the
training losses' normal terms), and the structure term L_S of the paper's eq. 6
(:func:`structure_loss`), which is both a training loss (:mod:`depthgt.enhance.losses`)
and a table metric (:func:`depthgt.eval.metrics.ls_distance`).

Conventions: depth (B, 1, H, W) in metres, 0 = invalid; validity (B, 1, H, W) bool or
{0, 1} float.
"""

from __future__ import annotations

import functools

import torch
import torch.nn.functional as F

from depthgt.shapes import check_shape

__all__ = [
    "valid_avg_pool",
    "masked_avg_pool",
    "masked_mean",
    "forward_gradients",
    "depth_normals",
    "window_max",
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
    # the last column / row appended by cat, not F.pad: torch.compile's CPU code for a
    # padded bool image summed in the same kernel does not compile (torch 2.13)
    vx = torch.cat([v[..., :, 1:] & v[..., :, :-1], torch.zeros_like(v[..., :, :1])], dim=-1)
    vy = torch.cat([v[..., 1:, :] & v[..., :-1, :], torch.zeros_like(v[..., :1, :])], dim=-2)
    return gx, gy, vx, vy


def depth_normals(depth_m: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Unit surface normals of depth images, as kornia's ``depth_to_normals`` defines them.

    The normal is the normalised cross product of the derivatives along the columns (x)
    and the rows (y) of the unprojected points ``((u - cx) z / fx, (v - cy) z / fy, z)``,
    each derivative the normalised 3x3 Sobel filter (weights 1/8, 2/8, 1/8) with the
    border replicated; a fronto-parallel plane gets (0, 0, 1), a hole's point is the
    origin. Written with shifted slices rather than kornia's convolution: oneDNN runs the
    one-channel 3x3 convolution and its backward at ~1 GFLOP/s, which made the normal
    terms about 3/4 of LapDEN's loss (and a third of its training step) on CPU. The
    values agree with kornia's to float rounding (the sums run in another order).

    Args:
        depth_m: (B, 1, H, W) metres, H and W at least 2.
        K: (B, 3, 3) intrinsics of the (H, W) images (the skew is not read, as in kornia).

    Returns:
        (B, 3, H, W) unit normals (0 where the cross product is 0).
    """
    dims = check_shape(depth_m, "B 1 H W", "depth_m")
    check_shape(K, "B 3 3", "K", dims)
    B, _, H, W = depth_m.shape
    if H < 2 or W < 2:
        raise ValueError(f"depth_normals needs H >= 2 and W >= 2, got {tuple(depth_m.shape)}")
    K = K.to(depth_m.dtype)
    u = torch.arange(W, dtype=depth_m.dtype, device=depth_m.device).view(1, 1, 1, W)
    v = torch.arange(H, dtype=depth_m.dtype, device=depth_m.device).view(1, 1, H, 1)
    x = (u - K[:, 0, 2].view(B, 1, 1, 1)) / K[:, 0, 0].view(B, 1, 1, 1)
    y = (v - K[:, 1, 2].view(B, 1, 1, 1)) / K[:, 1, 1].view(B, 1, 1, 1)
    points = F.pad(torch.cat([x * depth_m, y * depth_m, depth_m], dim=1), (1, 1, 1, 1), mode="replicate")
    dx = points[..., :, 2:] - points[..., :, :-2]  # (B, 3, H + 2, W): central differences along x
    dy = points[..., 2:, :] - points[..., :-2, :]  # (B, 3, H, W + 2)
    gx = 0.125 * (dx[..., :-2, :] + dx[..., 2:, :]) + 0.25 * dx[..., 1:-1, :]
    gy = 0.125 * (dy[..., :-2] + dy[..., 2:]) + 0.25 * dy[..., 1:-1]
    # the cross product and the normalisation as kornia runs them, on (B, H, W, 3): the
    # same kernels give the same values where the normal is undefined (parallel
    # derivatives, e.g. a window with one point off a hole, where the cross product is
    # rounding noise), and a norm over a dim of 3 strided by H x W would be ~20x slower
    compiled = gx.device.type == "cpu" and gx.dtype in (torch.float32, torch.float64)  # (numpy has no bfloat16)
    if compiled and not (torch.is_grad_enabled() and gx.requires_grad):
        cross = torch.empty((B, H, W, 3), dtype=gx.dtype)
        _compiled_cross()(gx.contiguous().numpy(), gy.contiguous().numpy(), cross.numpy())
    else:
        cross = torch.linalg.cross(gx.permute(0, 2, 3, 1).contiguous(), gy.permute(0, 2, 3, 1).contiguous(), dim=-1)
    return F.normalize(cross, dim=-1).permute(0, 3, 1, 2)


def _cross_planes(a, b, out):  # pragma: no cover (compiled by _compiled_cross)
    """out (B, H, W, 3) = a x b, of a and b (B, 3, H, W): ``torch.linalg.cross``'s
    products and differences, read from the planes (no channels-last copies)."""
    for i in range(a.shape[0]):
        for y in range(a.shape[2]):
            for x in range(a.shape[3]):
                a0, a1, a2 = a[i, 0, y, x], a[i, 1, y, x], a[i, 2, y, x]
                b0, b1, b2 = b[i, 0, y, x], b[i, 1, y, x], b[i, 2, y, x]
                out[i, y, x, 0] = a1 * b2 - a2 * b1
                out[i, y, x, 1] = a2 * b0 - a0 * b2
                out[i, y, x, 2] = a0 * b1 - a1 * b0


@functools.cache
def _compiled_cross():
    """:func:`_cross_planes` compiled (numba, imported on first use). For normals that
    need no gradient on the CPU: the renderer's and the refinement's, a training's target
    normals (the prediction's keep torch's kernel, for autograd). torch's CPU cross kernel
    took 24 ms for a frame set's 7 x 256 x 256 normals (one thread), this 1.4 ms, and the
    two planes' channels-last copies are saved as well. Compiled with a product and a
    difference contracted into one fused multiply-add, as torch's kernel is built: on an
    AVX2 machine its values were torch's to the bit on 7 x 256 x 256 random vectors and on real
    frames' normals (elsewhere they may differ by a rounding;
    ``tests/test_train_fast_paths.py`` holds them together). Written by hand: no library
    takes the cross product of two planar images without copying them first."""
    import numba

    return numba.njit(cache=True, nogil=True, fastmath={"contract"})(_cross_planes)


def window_max(x: torch.Tensor, window: int) -> torch.Tensor:
    """Max over each ``window`` x ``window`` neighbourhood (stride 1, centred, the border
    left out): ``F.max_pool2d(x, window, stride=1, padding=window // 2)``.

    Without autograd (``x`` needs no gradient, or grad mode is off) as running maxima of
    shifted views along the rows, then the columns: the same values to the bit (a max
    is exact in any order), ~10-20x faster on CPU than max_pool2d's kernel for the
    one-channel images here. With autograd, max_pool2d itself (its gradient goes to one
    element of a tie; the maxima's would split it).

    Args:
        x: (B, C, H, W); window: odd int.
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd int, got {window}")
    r = window // 2
    if torch.is_grad_enabled() and x.requires_grad:
        return F.max_pool2d(x, window, stride=1, padding=r)
    H, W = x.shape[-2:]
    padded = F.pad(x, (r, r, 0, 0), value=float("-inf"))
    rows = padded[..., :, :W]
    for i in range(1, window):
        rows = torch.maximum(rows, padded[..., :, i : i + W])
    padded = F.pad(rows, (0, 0, r, r), value=float("-inf"))
    out = padded[..., :H, :]
    for i in range(1, window):
        out = torch.maximum(out, padded[..., i : i + H, :])
    return out


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
    return window_max(mag, window)


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
