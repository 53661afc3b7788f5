"""Camera geometry at the working resolution.

Conventions (see docs/output-layout.md): depth (B, 1, H, W) float32 metres with 0 = invalid;
intrinsics (B, 3, 3); poses (B, 4, 4) camera-to-world, ``T_j_to_t`` maps points of
camera j into camera t; points (B, N, 3).

Pixel-centre convention: integer pixel coordinates (u, v) are pixel *centres*
(OpenCV/kornia). Resizing an image from W to W' pixels maps u to
u' = (u + 0.5) * W'/W - 0.5, so the principal point is scaled with that half-pixel
shift; fx, fy scale by W'/W and H'/H per axis. Using ``c * s`` alone (corner
convention) shifts every reprojected point by up to half a pixel at 640 -> 256, which
shows as millimetres of error on slanted surfaces.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from kornia.geometry.depth import depth_to_3d_v2
from kornia.geometry.linalg import transform_points

from depthgt.shapes import check_shape

__all__ = [
    "scale_intrinsics",
    "resize_depth_nearest",
    "resize_rgb",
    "backproject",
    "project",
    "transform_points",
    "relative_poses",
]


def scale_intrinsics(K: np.ndarray | torch.Tensor, src_hw: tuple[int, int], dst_hw: tuple[int, int]):
    """Intrinsics after resizing an image from ``src_hw`` to ``dst_hw`` (H, W).

    Args:
        K: (3, 3) or (B, 3, 3) pinhole matrix at ``src_hw``.

    Returns:
        Same type and shape as ``K``, at ``dst_hw`` (pixel-centre convention).

    >>> import numpy as np
    >>> K = np.array([[585., 0, 320], [0, 585, 240], [0, 0, 1]])
    >>> scale_intrinsics(K, (480, 640), (256, 256)).round(3).tolist()[0]
    [234.0, 0.0, 127.7]
    """
    sy = dst_hw[0] / src_hw[0]
    sx = dst_hw[1] / src_hw[1]
    K2 = K.clone() if isinstance(K, torch.Tensor) else np.array(K, dtype=np.float64, copy=True)
    K2[..., 0, 0] = K[..., 0, 0] * sx
    K2[..., 0, 1] = K[..., 0, 1] * sx
    K2[..., 1, 1] = K[..., 1, 1] * sy
    K2[..., 0, 2] = (K[..., 0, 2] + 0.5) * sx - 0.5
    K2[..., 1, 2] = (K[..., 1, 2] + 0.5) * sy - 0.5
    return K2


def _centre_indices(n_src: int, n_dst: int, device: torch.device) -> torch.Tensor:
    # Nearest source pixel of each destination pixel centre (same as OpenCV's
    # INTER_NEAREST_EXACT); written here because torch's "nearest" uses the corner
    # convention and "nearest-exact" is not available for every dtype/device path.
    pos = (torch.arange(n_dst, device=device, dtype=torch.float64) + 0.5) * (n_src / n_dst)
    return pos.floor().long().clamp_(0, n_src - 1)


def resize_depth_nearest(depth_m: torch.Tensor, size_hw: tuple[int, int]) -> torch.Tensor:
    """Valid-aware resize of depth: every output pixel takes the depth of the source
    pixel nearest to its centre, so valid and invalid depth are never mixed.

    Args:
        depth_m: (B, 1, H, W) float depth in metres, 0 = invalid.
        size_hw: output (H', W').

    Returns:
        (B, 1, H', W') depth.
    """
    check_shape(depth_m, "B 1 H W", "depth_m")
    h, w = depth_m.shape[-2:]
    iy = _centre_indices(h, size_hw[0], depth_m.device)
    ix = _centre_indices(w, size_hw[1], depth_m.device)
    return depth_m[:, :, iy][:, :, :, ix]


def resize_rgb(rgb: torch.Tensor, size_hw: tuple[int, int]) -> torch.Tensor:
    """Area-averaged resize of colour (B, 3, H, W) in [0, 1] (antialiased bilinear)."""
    check_shape(rgb, "B 3 H W", "rgb")
    return F.interpolate(rgb, size=size_hw, mode="bilinear", align_corners=False, antialias=True).clamp_(0, 1)


def backproject(depth_m: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """3D points of every pixel in its camera frame.

    Args:
        depth_m: (B, 1, H, W) depth in metres (0 = invalid gives the origin).
        K: (B, 3, 3) intrinsics.

    Returns:
        (B, H*W, 3) points in metres, row-major pixel order; B = 0 gives (0, H*W, 3).
    """
    sizes = check_shape(K, "B 3 3", "K", check_shape(depth_m, "B 1 H W", "depth_m"))
    pts = depth_to_3d_v2(depth_m[:, 0], K.to(depth_m.dtype), normalize_points=False)  # (B, H, W, 3)
    # the sizes spelled out: -1 is ambiguous for a batch of none (0 elements)
    return pts.reshape(sizes["B"], sizes["H"] * sizes["W"], 3)


def project(points_cam: torch.Tensor, K: torch.Tensor, eps: float = 1e-6) -> tuple[torch.Tensor, torch.Tensor]:
    """Project camera-frame points to pixel coordinates.

    Args:
        points_cam: (B, N, 3) points in metres.
        K: (B, 3, 3) intrinsics.

    Returns:
        uv (B, N, 2) pixel coordinates (pixel-centre convention) and z (B, N) depth;
        points with z <= eps get uv = -inf so that they fall outside every image.
    """
    z = points_cam[..., 2]
    zs = z.clamp(min=eps)
    u = K[:, None, 0, 0] * points_cam[..., 0] / zs + K[:, None, 0, 1] * points_cam[..., 1] / zs + K[:, None, 0, 2]
    v = K[:, None, 1, 1] * points_cam[..., 1] / zs + K[:, None, 1, 2]
    uv = torch.stack([u, v], dim=-1)
    uv = torch.where((z > eps)[..., None], uv, torch.full_like(uv, float("-inf")))
    return uv, z


def relative_poses(T_world_t: np.ndarray, T_world_js: np.ndarray) -> np.ndarray:
    """``T_j_to_t = inv(T_world_t) @ T_world_j`` for each neighbour j.

    Args:
        T_world_t: (4, 4) float64 camera-to-world pose of the target.
        T_world_js: (J, 4, 4) poses of the neighbours.

    Returns:
        (J, 4, 4) float64 relative poses.
    """
    return np.linalg.inv(T_world_t)[None] @ np.asarray(T_world_js, dtype=np.float64)
