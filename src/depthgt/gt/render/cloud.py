"""The frames of a frame set as one cloud in the target camera: back-projection at the
source pixels' positions, normals, each point's noise sigma (the renderer's first part)."""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.geometry.depth import depth_to_normals
from kornia.geometry.linalg import transform_points

from depthgt.device import plain_cpu_convolutions
from depthgt.geometry import backproject
from depthgt.gt.render.settings import RenderSettings
from depthgt.noise_law import Residuals, depth_sigma_m, noise_sigma_1m_from, second_difference_residuals
from depthgt.rasterise import resampled_positions

__all__ = ["TargetCloud", "cloud_in_target"]


def _backproject_resampled(depth_m: torch.Tensor, K: torch.Tensor, src_hw: tuple[int, int]) -> torch.Tensor:
    """Back-project (J, 1, H, W) depth made by nearest resizing from ``src_hw``, each pixel
    at the position of its source pixel centre: (J, H*W, 3) metres.

    Written by hand: kornia's depth_to_3d assumes the regular output pixel grid.
    """
    h, w = depth_m.shape[-2:]
    dev, dt = depth_m.device, depth_m.dtype
    v, u = torch.meshgrid(
        resampled_positions(src_hw[0], h, dev, dt), resampled_positions(src_hw[1], w, dev, dt), indexing="ij"
    )
    z = depth_m[:, 0]
    fx, fy = K[:, 0, 0, None, None], K[:, 1, 1, None, None]
    cx, cy, s = K[:, 0, 2, None, None], K[:, 1, 2, None, None], K[:, 0, 1, None, None]
    y = (v - cy) / fy
    x = (u - cx - s * y) / fx
    return torch.stack([x * z, y * z, z], dim=-1).reshape(depth_m.shape[0], -1, 3)


def _smooth_3x3(res: Residuals, max_rel: float, sigma_1m: float, noise_sigmas: float = 6.0) -> torch.Tensor:
    """(J, 1, H, W) bool: the 3x3 neighbourhood is valid and holds no depth edge.

    An edge is a second difference of inverse depth (``res``, along x or y, zero on any
    plane however slanted) above ``max_rel`` x the inverse depth plus ``noise_sigmas``
    times its noise, anywhere in the 3x3 window."""
    bad = ~res.ok
    for r, both in zip(res.r, res.both):
        bad |= both & (r.abs() > max_rel * res.iz + noise_sigmas * sigma_1m)
    return F.max_pool2d(bad.to(torch.float32), 3, stride=1, padding=1) == 0


class TargetCloud(NamedTuple):
    """The frames of a frame set merged in the target camera (one batch element).

    points: (1, J*H*W, 3) metres; normals: (1, J*H*W, 3) unit normals (zeros where
    unknown); valid: (1, J*H*W) bool (valid depth); frame: (1, J*H*W) long index j of
    each point's frame; sigma_m: (1, J*H*W) expected std of each point's depth in
    metres (the z^2 law of :func:`depth_sigma_m` with the sensor's noise at 1 m).
    """

    points: torch.Tensor
    normals: torch.Tensor
    valid: torch.Tensor
    frame: torch.Tensor
    sigma_m: torch.Tensor


def cloud_in_target(
    depth_m: torch.Tensor,
    K: torch.Tensor,
    T_j_to_t: torch.Tensor,
    *,
    normal_max_jump_rel: float = 0.05,
    src_hw: tuple[int, int] | None = None,
    noise_sigma_1m: float | None = None,
    noise_sigma_abs_m: float = RenderSettings.noise_sigma_abs_m,
    residuals: Residuals | None = None,
    normals: torch.Tensor | None = None,
) -> TargetCloud:
    """Back-project J depth images and move their points and normals into the target camera.

    Normals come from :func:`kornia.geometry.depth.depth_to_normals`; they are set to
    zero (unknown) wherever the 3x3 neighbourhood holds an invalid pixel or a depth
    edge: a second difference of inverse depth above ``normal_max_jump_rel`` times the
    inverse depth (plus 6 sigma of the noise). Planes have none at any slant, so
    grazing surfaces keep their normals while edges lose them.

    Args:
        depth_m: (J, 1, H, W) depth in metres, 0 = invalid.
        K: (J, 3, 3) intrinsics of each frame at (H, W).
        T_j_to_t: (J, 4, 4) poses mapping points of frame j into the target camera.
        src_hw: when ``depth_m`` was made by :func:`depthgt.geometry.resize_depth_nearest`
            from images of size ``src_hw``, every pixel holds the depth of the source
            pixel nearest to its centre, up to 0.5 source pixels away; passing
            ``src_hw`` back-projects each depth at that source pixel's exact position
            (in output pixel units) instead of at the output pixel centre, which puts
            the points on the surface (it matters on slanted surfaces and at edges).
        noise_sigma_1m: the sensor's depth sigma at 1 m (metres); None estimates it
            from ``depth_m`` (:func:`estimate_noise_sigma_1m`).
        noise_sigma_abs_m: floor of every point's sigma (metres).
        residuals: :func:`depthgt.noise_law.second_difference_residuals` of ``depth_m``
            when the caller has them (they are computed here otherwise).
        normals: (J, 3, H, W) :func:`kornia.geometry.depth.depth_to_normals` of
            ``depth_m`` and ``K`` when the caller has them (the registration's
            refinement computes the same), else computed here.

    Returns:
        :class:`TargetCloud` with J*H*W points in row-major pixel order, frame by frame.
    """
    if depth_m.ndim != 4 or depth_m.shape[1] != 1:
        raise ValueError(f"depth_m must be (J, 1, H, W), got {tuple(depth_m.shape)}")
    j = depth_m.shape[0]
    if T_j_to_t.shape != (j, 4, 4):
        raise ValueError(f"T_j_to_t must be ({j}, 4, 4) to match depth_m, got {tuple(T_j_to_t.shape)}")
    dtype = depth_m.dtype
    K = K.to(dtype)
    T = T_j_to_t.to(dtype)
    if src_hw is None:
        pts_j = backproject(depth_m, K)
    else:
        pts_j = _backproject_resampled(depth_m, K, src_hw)
    pts = transform_points(T, pts_j)  # (J, HW, 3)
    res = second_difference_residuals(depth_m, src_hw) if residuals is None else residuals
    sigma_1m = noise_sigma_1m_from(res) if noise_sigma_1m is None else float(noise_sigma_1m)
    if normals is None:
        with plain_cpu_convolutions():  # 3x3 filters: ~3x faster than oneDNN's on one thread
            nrm = depth_to_normals(depth_m, K)  # (J, 3, H, W)
    elif normals.shape != (j, 3, *depth_m.shape[-2:]):
        raise ValueError(
            f"normals must be ({j}, 3, H, W) to match depth_m {tuple(depth_m.shape)}, got {tuple(normals.shape)}"
        )
    else:
        nrm = normals
    flat = _smooth_3x3(res, normal_max_jump_rel, sigma_1m)
    nrm = torch.where(flat & torch.isfinite(nrm).all(dim=1, keepdim=True), nrm, torch.zeros_like(nrm))
    nrm = nrm.flatten(2).transpose(1, 2) @ T[:, :3, :3].transpose(1, 2)  # rotate into the target camera
    valid = (depth_m > 0).reshape(j, -1)
    sigma = depth_sigma_m(depth_m.reshape(j, -1), sigma_1m, noise_sigma_abs_m)  # each point's own sensor depth
    frame = torch.arange(j, device=depth_m.device)[:, None].expand(j, depth_m.shape[-2] * depth_m.shape[-1])
    return TargetCloud(
        pts.reshape(1, -1, 3), nrm.reshape(1, -1, 3), valid.reshape(1, -1), frame.reshape(1, -1), sigma.reshape(1, -1)
    )
