"""The frames of a frame set as one cloud in the target camera (the renderer's first part).

What depends on a frame alone -- its points back-projected at the source pixels'
positions, its normals, its depth-edge scores and its noise residuals -- is a
:class:`FrameGeometry`, computed once per frame (a batch of frame sets shares each
frame with up to six others: :func:`cached_geometry`); what depends on the frame
set -- its noise estimate, the poses, the normals kept -- is put together per set by
:func:`cloud_from_geometry`. :func:`cloud_in_target` is both in a row.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numba
import numpy as np
import torch
from kornia.geometry.linalg import transform_points

from depthgt.depth_ops import depth_normals, window_max
from depthgt.framecache import FrameCache
from depthgt.geometry import backproject
from depthgt.gt.render.settings import RenderSettings
from depthgt.noise_law import (
    Residuals,
    depth_sigma_m,
    noise_sigma_1m_of,
    second_difference_residuals,
    sorted_residuals,
)
from depthgt.rasterise import resampled_positions
from depthgt.shapes import check_shape

__all__ = [
    "TargetCloud",
    "FrameGeometry",
    "cached_geometry",
    "frame_geometry",
    "cloud_from_geometry",
    "cloud_in_target",
]

#: the normals' edge test: a second difference beyond this many sigmas of the noise
_EDGE_SIGMAS = 6.0


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
    return torch.stack([x * z, y * z, z], dim=-1).reshape(depth_m.shape[0], h * w, 3)  # -1: ambiguous for J = 0


def _edge_scores(res: Residuals, max_rel: float) -> torch.Tensor:
    """(J, H*W) float64: over each pixel's 3x3 window, the largest second difference of
    inverse depth (``res``, along x or y: zero on any plane however slanted) beyond
    ``max_rel`` x the inverse depth, +inf where the window holds an invalid pixel. A
    pixel's window holds a depth edge for a noise sigma s exactly when its score
    exceeds ``_EDGE_SIGMAS`` x s (:func:`cloud_from_geometry`)."""
    score = torch.where(res.ok, -torch.inf, torch.inf).to(torch.float64)
    for r, both in zip(res.r, res.both):
        score = torch.maximum(score, torch.where(both, r.abs() - max_rel * res.iz, -torch.inf))
    return window_max(score, 3).flatten(1)  # max_pool2d's values; pads with -inf: the border is no edge


class FrameGeometry(NamedTuple):
    """What the renderer needs of J frames, each on its own (no frame set yet).

    points: (J, H*W, 3) metres in each frame's own camera, row-major, at the source
        pixels' positions; normals: (J, H*W, 3) their normals (kornia's definition,
        :func:`depthgt.depth_ops.depth_normals`; non-finite where undefined); edge: (J,
        H*W) float64 edge scores (:func:`_edge_scores`);
    depth: (J, H*W) metres, 0 = invalid; residuals: per frame, the sorted |second
        differences| of inverse depth where defined (float64, CPU; the noise estimate
        of any set of frames, :func:`depthgt.noise_law.noise_sigma_1m_of`).
    """

    points: torch.Tensor
    normals: torch.Tensor
    edge: torch.Tensor
    depth: torch.Tensor
    residuals: tuple[torch.Tensor, ...]

    def take(self, index: Sequence[int]) -> FrameGeometry:
        """The frames ``index`` (in that order)."""
        i = torch.as_tensor(list(index), dtype=torch.long, device=self.points.device)
        return FrameGeometry(
            self.points.index_select(0, i),
            self.normals.index_select(0, i),
            self.edge.index_select(0, i),
            self.depth.index_select(0, i),
            tuple(self.residuals[k] for k in index),
        )

    @staticmethod
    def stack(parts: Sequence[FrameGeometry]) -> FrameGeometry:
        """The frames of ``parts`` one after the other."""
        return FrameGeometry(
            torch.cat([p.points for p in parts]),
            torch.cat([p.normals for p in parts]),
            torch.cat([p.edge for p in parts]),
            torch.cat([p.depth for p in parts]),
            tuple(r for p in parts for r in p.residuals),
        )


def frame_geometry(
    depth_m: torch.Tensor,
    K: torch.Tensor,
    *,
    src_hw: tuple[int, int] | None = None,
    normal_max_jump_rel: float = 0.05,
    normals: torch.Tensor | None = None,
) -> FrameGeometry:
    """:class:`FrameGeometry` of J depth images.

    Args:
        depth_m: (J, 1, H, W) depth in metres, 0 = invalid.
        K: (J, 3, 3) intrinsics of each frame at (H, W).
        src_hw: when ``depth_m`` was made by :func:`depthgt.geometry.resize_depth_nearest`
            from images of size ``src_hw``, every pixel holds the depth of the source
            pixel nearest to its centre, up to 0.5 source pixels away; passing
            ``src_hw`` back-projects each depth at that source pixel's exact position
            (in output pixel units) instead of at the output pixel centre, which puts
            the points on the surface (it matters on slanted surfaces and at edges).
        normal_max_jump_rel: the normals' edge test (:func:`cloud_from_geometry`).
        normals: (J, 3, H, W) :func:`depthgt.depth_ops.depth_normals` of
            ``depth_m`` and ``K`` when the caller has them (the registration's
            refinement computes the same), else computed here.
    """
    sizes = check_shape(depth_m, "J 1 H W", "depth_m")
    j, _, h, w = depth_m.shape
    K = K.to(depth_m.dtype)
    points = backproject(depth_m, K) if src_hw is None else _backproject_resampled(depth_m, K, src_hw)
    if normals is None:
        normals = depth_normals(depth_m, K)  # (J, 3, H, W); kornia's to float rounding, half its time
    else:
        check_shape(normals, "J 3 H W", "normals", sizes)
    res = second_difference_residuals(depth_m, src_hw)
    return FrameGeometry(
        points,
        normals.flatten(2).transpose(1, 2),
        _edge_scores(res, normal_max_jump_rel),
        depth_m.reshape(j, h * w),
        tuple(sorted_residuals(res)),
    )


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


@numba.njit(cache=True, nogil=True)
def _moved_frames(points, normals, edge, edge_max, T):  # pragma: no cover (compiled)
    """The points (J, N, 3) moved by ``T`` (J, 4, 4) and their normals rotated, set to
    zero where the edge score (J, N) exceeds ``edge_max`` or a component is not finite,
    in one pass (:func:`cloud_from_geometry`'s tensors: a homogeneous batched product
    and five (J, N) planes for the mask). The products are summed in order, the
    tensors' BLAS in its own order: the points agree to a float32 rounding."""
    j_n, n = points.shape[0], points.shape[1]
    pts = np.empty_like(points)
    nrm = np.empty_like(normals)
    zero = normals.dtype.type(0.0)
    for j in range(j_n):
        r00, r01, r02, t0 = T[j, 0, 0], T[j, 0, 1], T[j, 0, 2], T[j, 0, 3]
        r10, r11, r12, t1 = T[j, 1, 0], T[j, 1, 1], T[j, 1, 2], T[j, 1, 3]
        r20, r21, r22, t2 = T[j, 2, 0], T[j, 2, 1], T[j, 2, 2], T[j, 2, 3]
        for i in range(n):
            x, y, z = points[j, i, 0], points[j, i, 1], points[j, i, 2]
            pts[j, i, 0] = r00 * x + r01 * y + r02 * z + t0
            pts[j, i, 1] = r10 * x + r11 * y + r12 * z + t1
            pts[j, i, 2] = r20 * x + r21 * y + r22 * z + t2
            a, b, c = normals[j, i, 0], normals[j, i, 1], normals[j, i, 2]
            if edge[j, i] <= edge_max and math.isfinite(a) and math.isfinite(b) and math.isfinite(c):
                nrm[j, i, 0] = r00 * a + r01 * b + r02 * c
                nrm[j, i, 1] = r10 * a + r11 * b + r12 * c
                nrm[j, i, 2] = r20 * a + r21 * b + r22 * c
            else:
                nrm[j, i, 0] = nrm[j, i, 1] = nrm[j, i, 2] = zero
    return pts, nrm


def cloud_from_geometry(
    geom: FrameGeometry,
    T_j_to_t: torch.Tensor,
    *,
    noise_sigma_1m: float | None = None,
    noise_sigma_abs_m: float = RenderSettings.noise_sigma_abs_m,
    compiled: bool | None = None,
) -> TargetCloud:
    """The frames of ``geom`` moved into the target camera by ``T_j_to_t`` (J, 4, 4).

    Normals are set to zero (unknown) wherever the 3x3 neighbourhood holds an invalid
    pixel or a depth edge: a second difference of inverse depth above the geometry's
    ``normal_max_jump_rel`` times the inverse depth plus 6 sigma of the noise (planes
    have none at any slant, so grazing surfaces keep their normals while edges lose
    them). Each point's sigma is the z^2 law with the sensor's sigma at 1 m,
    ``noise_sigma_1m`` or, None, estimated from these frames (:func:`noise_sigma_1m_of`).
    ``compiled``: the points and normals moved in one compiled pass (:func:`_moved_frames`;
    default: CPU tensors, no gradients wanted) or as tensors (a GPU's path, gradients);
    the same cloud to a float32 rounding.
    """
    j = geom.points.shape[0]
    check_shape(T_j_to_t, "J 4 4", "T_j_to_t", {"J": j})
    dtype = geom.points.dtype
    T = T_j_to_t.to(dtype)
    sigma_1m = noise_sigma_1m_of(geom.residuals) if noise_sigma_1m is None else float(noise_sigma_1m)
    on_cpu = geom.points.device.type == "cpu"
    if compiled is None:
        grads = torch.is_grad_enabled() and any(t.requires_grad for t in (T, geom.points, geom.normals))
        compiled = on_cpu and not grads
    elif compiled and not on_cpu:
        raise ValueError(f"the compiled cloud takes CPU tensors, got {geom.points.device.type}")
    if compiled:
        pts, nrm = (
            torch.from_numpy(a)
            for a in _moved_frames(
                *(t.detach().contiguous().numpy() for t in (geom.points, geom.normals.to(dtype), geom.edge)),
                float(_EDGE_SIGMAS * sigma_1m),
                T.detach().contiguous().numpy(),
            )
        )
    else:
        pts = transform_points(T, geom.points)  # (J, HW, 3)
        flat = (geom.edge <= _EDGE_SIGMAS * sigma_1m)[..., None] & torch.isfinite(geom.normals).all(
            dim=-1, keepdim=True
        )
        nrm = torch.where(flat, geom.normals, torch.zeros_like(geom.normals))
        nrm = nrm @ T[:, :3, :3].transpose(1, 2)  # rotate into the target camera
    valid = geom.depth > 0
    sigma = depth_sigma_m(geom.depth, sigma_1m, noise_sigma_abs_m)  # each point's own sensor depth
    frame = torch.arange(j, device=pts.device)[:, None].expand(j, geom.depth.shape[1])
    return TargetCloud(
        pts.reshape(1, -1, 3), nrm.reshape(1, -1, 3), valid.reshape(1, -1), frame.reshape(1, -1), sigma.reshape(1, -1)
    )


def cloud_in_target(
    depth_m: torch.Tensor,
    K: torch.Tensor,
    T_j_to_t: torch.Tensor,
    *,
    normal_max_jump_rel: float = 0.05,
    src_hw: tuple[int, int] | None = None,
    noise_sigma_1m: float | None = None,
    noise_sigma_abs_m: float = RenderSettings.noise_sigma_abs_m,
    normals: torch.Tensor | None = None,
) -> TargetCloud:
    """Back-project J depth images (J, 1, H, W) with their intrinsics ``K`` (J, 3, 3) and
    move their points and normals into the target camera by ``T_j_to_t`` (J, 4, 4):
    :func:`frame_geometry` then :func:`cloud_from_geometry` (their arguments).

    Returns:
        :class:`TargetCloud` with J*H*W points in row-major pixel order, frame by frame.
    """
    geom = frame_geometry(depth_m, K, src_hw=src_hw, normal_max_jump_rel=normal_max_jump_rel, normals=normals)
    return cloud_from_geometry(geom, T_j_to_t, noise_sigma_1m=noise_sigma_1m, noise_sigma_abs_m=noise_sigma_abs_m)


def cached_geometry(
    cache: FrameCache,
    positions: Sequence[int],
    depth_m: torch.Tensor,
    K: torch.Tensor,
    *,
    src_hw: tuple[int, int] | None = None,
    normal_max_jump_rel: float = 0.05,
    normals: torch.Tensor | None = None,
    of: str = "render.geometry",
) -> FrameGeometry:
    """:func:`frame_geometry` of the frames at ``positions`` (their depth ``depth_m`` (F,
    1, H, W), ``K`` (3, 3) their one camera), each frame's computed once per batch job
    (``cache``: the job's :class:`~depthgt.framecache.FrameCache`), in that order;
    ``normals`` (F, 3, H, W) as :func:`frame_geometry` takes them (the refinement's),
    used for the frames not yet in the cache. ``of`` names the depth (the raw depth's
    default; another name for another depth of the same frames, e.g. coverage's views
    without their mixed samples)."""
    index = {p: i for i, p in enumerate(positions)}

    def compute(todo: list[int]) -> list[FrameGeometry]:
        rows = [index[p] for p in todo]
        g = frame_geometry(
            depth_m[rows],
            K[None].expand(len(rows), 3, 3),
            src_hw=src_hw,
            normal_max_jump_rel=normal_max_jump_rel,
            normals=None if normals is None else normals[rows],
        )
        return [g.take([k]) for k in range(len(rows))]

    return FrameGeometry.stack(cache.get(f"{of}:{normal_max_jump_rel}", positions, compute))
