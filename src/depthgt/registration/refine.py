"""Beyond the paper: joint SE(3) refinement of all poses of a frame set.

After the correspondence-based alignment, the poses ``T_f_to_t`` of all frames are
refined jointly by minimising the same two consistency terms as the R&R losses -- depth
(as a point-to-plane distance) and photometric -- over every ordered pair of frames
(paper eq. 4: target-neighbour and neighbour-neighbour), directly over se(3)
increments. Instead of soft splatting, each source point is moved into the
destination camera and the destination's depth/normal/intensity are sampled there
(inverse warping with bilinear interpolation): for a dense image this is exact,
sub-pixel and has closed-form Jacobians, so Levenberg-Marquardt with robust (Huber or
Cauchy) IRLS weights converges in a few dozen iterations, coarse to fine.

Hand-written parts and why: the closed-form Jacobians of the two residuals and their
chaining through the SE(3) adjoint into a joint 6(F-1) x 6(F-1) normal system (no
library solves this multi-frame direct alignment); the exponential map, normals,
gradients and sampling come from kornia/torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
import torch
import torch.nn.functional as F
from kornia.filters import spatial_gradient

from depthgt.depth_ops import depth_normals, window_max
from depthgt.device import plain_cpu_convolutions
from depthgt.framecache import FrameCache
from depthgt.geometry import backproject, resize_depth_nearest, resize_rgb, scale_intrinsics
from depthgt.noise_law import (
    estimate_noise_sigma_1m,
    noise_sigma_1m_of,
    second_difference_residuals,
    sorted_residuals,
)
from depthgt.registration.pair_terms import costs_seen_by_both, kernel_maps, pair_terms, point_residuals
from depthgt.registration.settings import RefineSettings
from depthgt.shapes import check_shape

__all__ = [
    "RefineResult",
    "Level",
    "LevelSettings",
    "frame_pairs",
    "refine_poses",
    "adjoint",
    "normal_system",
    "pair_mean_cost",
    "pair_information",
    "target_residuals",
]


@dataclass
class RefineResult:
    """Refined poses and diagnostics.

    Attributes:
        T_f_to_t: (F, 4, 4) float64 poses of every frame in the target camera (T_0 = I).
        cost_curve: robust cost per LM iteration (all scales).
        inlier_fraction: (F,) fraction of each frame's valid points associated with the
            target at the finest scale (1 for the target).
        condition: (F,) condition number of each neighbour's target-pair information
            matrix (translation in m, rotation scaled by the median depth); large =
            geometrically and photometrically degenerate.
        initial_cost, final_cost: (F,) per-neighbour robust cost of its target pairs at
            the finest scale before and after.
        residual_m: (F,) median absolute point-to-plane residual (metres) of each
            neighbour's associated points in the target at the finest scale (0 for the
            target, NaN when none is associated): near the sensor noise when aligned,
            larger when the refinement settled off the surface.
        residual_sigmas: (F,) median of the same residuals in units of the depth noise
            at each point's depth, ``noise_sigma_1m * z^2`` (0 for the target, NaN when
            none is associated; gate max(the finest gate, 4 sigma), a point seen on a
            target surface but beyond it counts as off): 0.4-0.8 when aligned on both
            synthetic sensor profiles, up to 1.06 on 7-Scenes, whatever the noise.
        noise_sigma_1m: the frame set's depth sigma at 1 m (metres), estimated from its
            depth (:func:`depthgt.noise_law.estimate_noise_sigma_1m`).
        normals: (F, 3, H, W) the full-resolution level's normals
            (:func:`depthgt.depth_ops.depth_normals` of ``depth_m`` and ``K``), which the
            GT renderer reuses;
            None without a scale-1 level.
    """

    T_f_to_t: torch.Tensor
    cost_curve: list[float] = field(default_factory=list)
    inlier_fraction: torch.Tensor | None = None
    condition: torch.Tensor | None = None
    initial_cost: torch.Tensor | None = None
    final_cost: torch.Tensor | None = None
    residual_m: torch.Tensor | None = None
    residual_sigmas: torch.Tensor | None = None
    noise_sigma_1m: float | None = None
    normals: torch.Tensor | None = None

    def diagnostics(self) -> dict:
        """The neighbours' (frames 1..F-1) diagnostics as plain lists, for poses.json."""
        return {
            "refine_cost_curve": self.cost_curve,
            "inlier_fraction": self.inlier_fraction[1:].cpu().tolist(),
            "condition": self.condition[1:].cpu().tolist(),
            "residual_m": self.residual_m[1:].cpu().tolist(),
            "residual_sigmas": self.residual_sigmas[1:].cpu().tolist(),
            "noise_sigma_1m": self.noise_sigma_1m,
        }


def frame_pairs(n_frames: int, mode: str, offsets: list[int] | None = None) -> torch.Tensor:
    """Ordered pairs (a, b) (b's points into a's camera) as a (P, 2) long tensor."""
    a, b = torch.meshgrid(torch.arange(n_frames), torch.arange(n_frames), indexing="ij")
    keep = a != b
    if mode == "target":
        keep &= (a == 0) | (b == 0)
    elif mode == "adjacent":
        order = torch.tensor(offsets if offsets is not None else list(range(n_frames)))
        rank = order.argsort().argsort()
        keep &= (a == 0) | (b == 0) | ((rank[a] - rank[b]).abs() == 1)
    return torch.stack([a[keep], b[keep]], dim=1)


def _skew(v: torch.Tensor) -> torch.Tensor:
    z = torch.zeros_like(v[..., 0])
    return torch.stack([z, -v[..., 2], v[..., 1], v[..., 2], z, -v[..., 0], -v[..., 1], v[..., 0], z], -1).reshape(
        *v.shape[:-1], 3, 3
    )


def adjoint(T: torch.Tensor) -> torch.Tensor:
    """SE(3) adjoint for twists ordered (v, w): [[R, [t]x R], [0, R]]; (..., 6, 6)."""
    R, t = T[..., :3, :3], T[..., :3, 3]
    top = torch.cat([R, _skew(t) @ R], -1)
    bot = torch.cat([torch.zeros_like(R), R], -1)
    return torch.cat([top, bot], -2)


def _erode(mask: torch.Tensor) -> torch.Tensor:
    return -window_max(-mask, 3)  # max_pool2d's values


@dataclass(frozen=True)
class LevelSettings:
    """The residual settings of one scale (see :class:`~depthgt.settings.RefineSettings`):
    robust scales of the point-to-plane (metres) and intensity residuals, the weight of
    the photometric term, the robust kernel ("huber" | "cauchy") and the depth beyond
    which the geometric scale and gate grow as (z / geo_ref_depth_m)^2 (0: constant)."""

    geo_scale_m: float
    photo_scale: float
    photo_weight: float
    robust: str
    geo_ref_depth_m: float = 0.0


class _Maps(NamedTuple):
    """One scale's images of J frames (:func:`_level_maps`): intrinsics K (3, 3) at (h,
    w); geo (J, 8, h, w): points X (metres), normals, normal validity and a 0; photo (J,
    4, h, w): gray, its gradients and a 0; depth (J, 1, h, w) metres. The points, normals
    and gray are views of the maps, so that the batch's frame cache keeps (and a set
    stacks) each value once."""

    K: torch.Tensor
    geo: torch.Tensor
    photo: torch.Tensor
    depth: torch.Tensor

    @property
    def X(self) -> torch.Tensor:
        """(J, 3, h, w) the points, metres."""
        return self.geo[:, 0:3]

    @property
    def gray(self) -> torch.Tensor:
        """(J, 1, h, w) the gray image."""
        return self.photo[:, 0:1]

    def take(self, k: int) -> _Maps:
        return _Maps(self.K, self.geo[k : k + 1], self.photo[k : k + 1], self.depth[k : k + 1])

    @staticmethod
    def stack(parts: list[_Maps]) -> _Maps:
        if len(parts) == 1:
            return parts[0]
        return _Maps(
            parts[0].K,
            torch.cat([p.geo for p in parts]),
            torch.cat([p.photo for p in parts]),
            torch.cat([p.depth for p in parts]),
        )


def _level_maps(rgb: torch.Tensor, depth_m: torch.Tensor, K: torch.Tensor, scale: int) -> _Maps:
    """The images of one scale (downscale factor ``scale``) of J frames (rgb (J, 3, H, W),
    depth_m (J, 1, H, W), K (3, 3) at (H, W))."""
    Fn, _, H, W = depth_m.shape
    h, w = H // scale, W // scale
    Ks = scale_intrinsics(K, (H, W), (h, w)) if scale != 1 else K
    Kb = Ks.expand(Fn, 3, 3).contiguous()
    d = resize_depth_nearest(depth_m, (h, w)) if scale != 1 else depth_m
    c = resize_rgb(rgb, (h, w)) if scale != 1 else rgb
    gray = c.mean(1, keepdim=True)
    valid = (d > 0).to(d.dtype)
    X = backproject(d, Kb).transpose(1, 2).reshape(Fn, 3, h, w)
    N = depth_normals(d, Kb)  # kornia's depth_to_normals to float rounding, in half its time
    with plain_cpu_convolutions():  # 3x3 filters: ~3x faster than oneDNN's on one thread
        g = spatial_gradient(gray, mode="sobel", order=1, normalized=True)[:, 0]  # (F, 2, h, w) per pixel
    nvalid = _erode(valid)  # normals need all 3x3 neighbours valid
    # two maps, the geometric term's texel apart from the photometric one's
    # (pair_terms._GEO, _PHOTO): X(3) N(3) valid 0, and gray gx gy 0
    zero = torch.zeros_like(valid)
    geo, photo = torch.cat([X, N, nvalid, zero], 1), torch.cat([gray, g, zero], 1)
    if geo.device.type == "cpu":
        # channels last in memory, as the compiled terms read them (pair_terms.kernel_maps
        # is then a view): a batch job computes a frame's maps once and reads them in up to
        # seven sets, where the copy had been made for each set's level (~13 ms per set)
        geo, photo = (m.contiguous(memory_format=torch.channels_last) for m in (geo, photo))
    return _Maps(Ks, geo, photo, d)


class Level:
    """Per-scale images of all frames of a set: sample maps and source points.

    Args:
        rgb: (F, 3, H, W) colour in [0, 1]; depth_m: (F, 1, H, W) metres, 0 = invalid;
        K: (3, 3) the frames' one camera at (H, W); scale: downscale factor; stride:
        source pixel stride.
        maps_of: a dict shared by the levels of one frame set (the same rgb, depth_m
            and K), in which each scale's maps, which do not depend on ``stride``, are
            computed once (the chaining and the refinement both use scale 2).
        cache, positions: the batch job's :class:`~depthgt.framecache.FrameCache` and
            the frames' positions: each frame's maps are computed once per batch.

    Attributes:
        geo: (F, 8, h, w) points X (3, metres), normals (3), normal validity and a 0;
            photo: (F, 4, h, w) gray, its gradients gx, gy and a 0: the maps sampled at
            the warped positions.
        points: (F, 3, N) source points (planar layout); gray (F, N); valid (F, N) bool.
        K: (3, 3) intrinsics at (h, w); hw: (h, w); median_depth: metres.
    """

    def __init__(
        self,
        rgb,
        depth_m,
        K,
        scale: int,
        stride: int,
        maps_of: dict | None = None,
        cache: FrameCache | None = None,
        positions: tuple[int, ...] | None = None,
    ):
        if maps_of is not None and scale in maps_of:
            m = maps_of[scale]
        elif cache is not None and positions is not None:
            index = {p: i for i, p in enumerate(positions)}

            def compute(todo: list[int]) -> list[_Maps]:
                rows = [index[p] for p in todo]
                maps = _level_maps(rgb[rows], depth_m[rows], K, scale)
                return [maps.take(k) for k in range(len(rows))]

            m = _Maps.stack(cache.get(f"refine.level{scale}", positions, compute))
        else:
            m = _level_maps(rgb, depth_m, K, scale)
        if maps_of is not None:
            maps_of[scale] = m
        self.K, self.geo, self.photo, self._depth = m.K, m.geo, m.photo, m.depth
        h, w = self.hw = tuple(m.depth.shape[-2:])
        ys = torch.arange(0, h, stride, device=m.X.device)
        xs = torch.arange(0, w, stride, device=m.X.device)
        idx = (ys[:, None] * w + xs[None, :]).reshape(-1)
        self.points = m.X.flatten(2)[:, :, idx].contiguous()  # (F, 3, N) planar
        self.gray = m.gray.flatten(2)[:, 0, idx]  # (F, N)
        self.valid = m.depth.flatten(2)[:, 0, idx] > 0  # (F, N)

    @property
    def median_depth(self) -> torch.Tensor:
        """The median valid depth of the frames at this scale, metres (1 without any)."""
        return _median_depth(self._depth)


def _median_depth(d: torch.Tensor) -> torch.Tensor:
    """The median valid depth of the depth maps ``d``, metres (1 without any): the lower
    of the two middle values, as ``torch.median``. On the CPU numpy's mask and selection
    find it: 2.0 against 10.8 ms for torch's mask and median over a set's 7 x 256 x 256
    depths (one thread, best of 15)."""
    if d.device.type != "cpu" or d.dtype == torch.bfloat16:  # (numpy has no bfloat16)
        return d[d > 0].median() if (d > 0).any() else torch.tensor(1.0)
    x = d.detach().contiguous().numpy().reshape(-1)
    x = x[x > 0]  # 1.6 against 9.3 ms for torch's boolean index here
    if x.size == 0:
        return torch.tensor(1.0)
    k = (x.size - 1) // 2
    return torch.tensor(np.partition(x, k)[k], dtype=d.dtype)


#: an LM trial step smaller than this (metres of translation, radians of rotation, the
#: largest component) after a rejected one is not evaluated: the level has converged.
#: Such steps, accepted, moved the poses by under 0.3 um (docs/decisions.md
#: "Refinement: convergence").
MIN_TRIAL_STEP = 1e-6

#: an accepted LM step whose largest component (metres, radians) is under this ends the
#: finest scale (the others: ``RefineSettings.coarse_converged_step``, if larger)
FINEST_SETTLED = 1e-7

#: an LM trial whose step differs from the set's last rejected trial's by less than this
#: (the largest component; metres, radians) is not evaluated: it would land within a
#: micrometre of a pose just rejected. The damping grows as after a rejection. The damping
#: is relative to the diagonal, so its first increases barely change the step: 5 of 30
#: evaluations per 7-Scenes set were such repeats (docs/decisions.md "Refinement:
#: convergence": the refined poses of 36 real and synthetic sets bit-identical).
SAME_TRIAL = 1e-6

#: likewise a trial whose step differs from the last rejected one's by less than this share
#: of that step (the largest components): the first damping increases shrink a rejected
#: step by a few per cent, and no such trial was accepted where they were evaluated
#: (docs/decisions.md "Refinement: near repeats"). A skipped trial counts as rejected.
SAME_TRIAL_SHARE = 0.1


def se3_exp(xi: torch.Tensor) -> torch.Tensor:
    """(J, 4, 4) float64: the SE(3) exponential of the twists ``xi`` (J, 6) (translation
    part v, then rotation w), as ``kornia``'s ``Se3.exp(xi).matrix()``: ``torch.linalg.
    matrix_exp`` of their 4 x 4 matrices [[w]x, v; 0, 0]. The same transforms to 4e-16
    (``tests/test_refine_jacobians.py``) in a sixth of the time: kornia's quaternion
    classes spent ~1.6 ms of Python per call, and the refinement takes one per trial
    (~17 per refinement)."""
    xi = xi.to(torch.float64)
    v, w = xi[:, :3], xi[:, 3:]
    zero = torch.zeros_like(w[:, 0])
    hat = torch.stack(
        [
            torch.stack([zero, -w[:, 2], w[:, 1], v[:, 0]], 1),
            torch.stack([w[:, 2], zero, -w[:, 0], v[:, 1]], 1),
            torch.stack([-w[:, 1], w[:, 0], zero, v[:, 2]], 1),
            torch.stack([zero, zero, zero, zero], 1),
        ],
        1,
    )
    return torch.linalg.matrix_exp(hat)


def _cross(a, b):
    """Cross product of planar 3-vectors a, b: tuples of three (P, N) planes."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _residuals(level: Level, T_ab: torch.Tensor, pairs: torch.Tensor, s: LevelSettings, gate: float):
    """Scaled residuals r (P, 2N) (N geometric, then N photometric), Jacobians
    J (P, 6, 2N) w.r.t. a left twist (v, w) of T_ab, validity (P, 2N) (associated:
    seen and within the gate) and visibility (P, 2N) (a valid source point that lands
    on a destination pixel with a surface, whether or not within the gate); N columns
    in place of 2N without the photometric term (``photo_weight`` 0).

    Planar layout (one contiguous (P, N) plane per component) keeps the element-wise
    work cache friendly."""
    r, valid, vis, r_geo, jac = _residuals_lazy(level, T_ab, pairs, s, gate)
    return r, jac(), valid, vis, r_geo


def _residuals_lazy(level: Level, T_ab: torch.Tensor, pairs: torch.Tensor, s: LevelSettings, gate: float):
    """:func:`_residuals` with the Jacobians left to a function ``jac()`` (same values):
    r, valid, vis, r_geo, jac. A trial pose that the LM step rejects (or a cost-only
    evaluation) never builds them. Without the photometric term (``photo_weight`` 0)
    r, valid, vis and J hold the N geometric columns only (the photometric ones would
    be invalid and invisible: no weight, no cost).

    The element-wise work runs in the samples' layout (G, m, N) (:func:`_sample_grouped`:
    pair p = g m + i), so that the sampled maps are read where grid_sample wrote them
    instead of being copied into pair order; the results are (P, ...) views.

    Long because the residuals, their validity and the deferred Jacobians share the
    warped points and the sampled maps (a dozen (G, m, N) planes); split, they would
    travel between functions as long argument lists."""
    a, b = pairs[:, 0], pairs[:, 1]
    p = level.points.index_select(0, b)  # (P, 3, N)
    R = T_ab[:, :3, :3].to(p.dtype)
    t = T_ab[:, :3, 3].to(p.dtype)
    q = torch.baddbmm(t[..., None], R, p)  # (P, 3, N)
    n_pairs, _, N = q.shape
    K = level.K.to(p.dtype)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    zi = 1.0 / q[:, 2].clamp(min=1e-6)
    u = fx * q[:, 0] * zi + cx
    v = fy * q[:, 1] * zi + cy
    h, w = level.hw
    # (P, N, 2), each coordinate's last step written in place (a stack of the two planes
    # costs more than computing them: the same values)
    grid = torch.empty(*u.shape, 2, dtype=u.dtype, device=u.device)
    torch.sub((u + 0.5) * (2.0 / w), 1, out=grid[..., 0])
    torch.sub((v + 0.5) * (2.0 / h), 1, out=grid[..., 1])
    # X, N and normal validity, with the photometric term its gray and gradients (each
    # channel is sampled on its own: the same values either way)
    smp = _sample_grouped(_tensor_maps(level, s.photo_weight > 0), grid, a)  # (G, 7 or 10, m, N)
    nvalid = smp[:, 6]
    G, m = smp.shape[0], smp.shape[2]

    def grouped(x: torch.Tensor) -> torch.Tensor:  # (P, N) -> (G, m, N), a view
        return x.view(G, m, N)

    qx, qy, qz = grouped(q[:, 0]), grouped(q[:, 1]), grouped(q[:, 2])
    zi = grouped(zi)
    X = (smp[:, 0], smp[:, 1], smp[:, 2])
    n_inv = torch.rsqrt((smp[:, 3:6] * smp[:, 3:6]).sum(1).clamp(min=1e-12))
    Nrm = (smp[:, 3] * n_inv, smp[:, 4] * n_inv, smp[:, 5] * n_inv)
    # in front of the camera and on a pixel whose 3x3 neighbourhood is valid (the sampled
    # normal validity: a position off the image, u outside (-0.5, w - 0.5) or v likewise,
    # samples the zero padding with a weight of at least a half, so the image bounds
    # need no test of their own)
    src_valid = grouped(level.valid.index_select(0, b))
    seen = src_valid & (qz > 1e-3) & (nvalid > 0.999)
    d = (qx - X[0], qy - X[1], qz - X[2])
    r_geo = Nrm[0] * d[0] + Nrm[1] * d[1] + Nrm[2] * d[2]
    if s.geo_ref_depth_m > 0:
        # a disparity sensor's depth noise and quantisation grow as z^2: so do the
        # robust scale and the gate of the point-to-plane residual
        sz = (X[2] * (1.0 / s.geo_ref_depth_m)).square().clamp(min=1.0)
        gate_pt = gate * sz
        inv_geo = 1.0 / (s.geo_scale_m * sz)
    else:
        gate_pt, inv_geo = gate, 1.0 / s.geo_scale_m
    ok = seen & ((qz - X[2]).abs() < gate_pt) & (r_geo.abs() < gate_pt)
    qv = (qx, qy, qz)

    def scaled(planes, factor, cols: int, at: int = 0, out: torch.Tensor | None = None) -> torch.Tensor:
        # planes (each (G, m, N)) times factor written side by side into out (G, m, len, cols)
        # at column ``at``: a stack, a product and a cat in one pass (the same values)
        if out is None:
            out = torch.empty(G, m, len(planes), cols, dtype=qx.dtype, device=qx.device)
        for j, plane in enumerate(planes):
            torch.mul(plane, factor, out=out[:, :, j, at : at + N])
        return out

    def pairwise(x: torch.Tensor, *cols: int) -> torch.Tensor:  # (G, m, [6,] C) -> (P, [6,] C), a view
        return x.reshape(n_pairs, *cols)

    if not s.photo_weight > 0:
        # without the photometric term its half would be all invalid and invisible
        # (zero weight, zero cost): the geometric residuals alone, (P, N), (P, 6, N)
        def jac_geo() -> torch.Tensor:
            return pairwise(scaled((*Nrm, *_cross(qv, Nrm)), inv_geo, N), 6, N)

        return pairwise(r_geo * inv_geo, N), pairwise(ok, N), pairwise(seen, N), pairwise(r_geo, N), jac_geo
    r_ph = smp[:, 7] - grouped(level.gray.index_select(0, b))
    wp = math.sqrt(s.photo_weight)
    # geometric then photometric residuals side by side: (P, 2N), (P, 6, 2N)
    r = pairwise(scaled((r_geo,), inv_geo, 2 * N, out=scaled((r_ph,), wp / s.photo_scale, 2 * N, N)), 2 * N)
    valid = pairwise(torch.cat([ok, ok], -1), 2 * N)
    vis = pairwise(torch.cat([seen, seen], -1), 2 * N)

    def jac() -> torch.Tensor:
        J = scaled((*Nrm, *_cross(qv, Nrm)), inv_geo, 2 * N)  # (G, m, 6, 2N), geometric half
        # d(u, v)/dq of the pinhole projection chained with the image gradient (gx, gy).
        gx, gy = smp[:, 8] * fx * zi, smp[:, 9] * fy * zi
        ga = (gx, gy, -(gx * qx + gy * qy) * zi)
        return pairwise(scaled((*ga, *_cross(qv, ga)), wp / s.photo_scale, 2 * N, N, out=J), 6, 2 * N)

    return r, valid, vis, pairwise(r_geo, N), jac


def _tensor_maps(level: Level, photo: bool) -> torch.Tensor:
    """The maps the tensor path samples: X, N and validity (F, 7, h, w), a view of
    ``level.geo``; with ``photo`` then gray, gx, gy (F, 10, h, w), kept while
    ``level.geo`` is the same tensor."""
    if not photo:
        return level.geo[:, :7]
    cached = getattr(level, "_with_photo", None)
    if cached is None or cached[0] is not level.geo:
        cached = (level.geo, torch.cat([level.geo[:, :7], level.photo[:, :3]], 1))
        level._with_photo = cached
    return cached[1]


def _sample_grouped(maps: torch.Tensor, grid: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Bilinear samples of ``maps[a[p]]`` at ``grid[p]`` without copying a map per pair:
    the pairs are grouped by destination frame and each frame's map is sampled once.

    maps (F, C, h, w); grid (P, N, 2) normalised coordinates; a (P,) -> (G, C, m, N)
    with G m = P, pair p at [p // m, :, p % m]: when every frame is the destination of
    m pairs and the pairs come in frame order (a frame set's pairs, typically) it is
    grid_sample's output as written (G frames); else m = 1 (G = P pairs).
    """
    Fn, C = maps.shape[:2]
    P, N, _ = grid.shape
    used = torch.bincount(a, minlength=Fn) > 0
    if not bool(used.all()):
        # only the frames some pair lands in (e.g. the target alone): the others' maps
        # would be sampled at padding only
        frames = torch.nonzero(used)[:, 0]
        remap = torch.cumsum(used, 0) - 1
        maps, a, Fn = maps.index_select(0, frames), remap.index_select(0, a), int(frames.numel())
    counts = torch.bincount(a, minlength=Fn)
    m = int(counts.max())
    if P == Fn * m and bool((a[1:] >= a[:-1]).all()):
        # the grid is already in the frames' layout (the same samples, no padding slots to
        # fill, and no copy into pair order: the caller works in this layout)
        out = F.grid_sample(
            maps, grid.reshape(Fn, m * N, 1, 2), mode="bilinear", padding_mode="zeros", align_corners=False
        )
        return out.view(Fn, C, m, N)
    order = torch.argsort(a, stable=True)
    start = torch.cumsum(counts, 0) - counts
    slot = torch.empty_like(a)
    slot[order] = torch.arange(P, device=a.device) - start[a[order]]
    G = torch.full((Fn, m, N, 2), -3.0, dtype=grid.dtype, device=grid.device)
    G[a, slot] = grid
    out = F.grid_sample(maps, G.reshape(Fn, m * N, 1, 2), mode="bilinear", padding_mode="zeros", align_corners=False)
    out = out.reshape(Fn, C, m, N)
    return out.permute(0, 2, 1, 3)[a, slot][:, :, None]


def _robust(r: torch.Tensor, kind: str) -> tuple[torch.Tensor, torch.Tensor]:
    """IRLS weights and costs rho(r) of scaled residuals."""
    a = r.abs()
    if kind == "huber":
        # 1 and a^2 / 2 within 1, 1 / a and a - 1/2 beyond; written without torch.where
        # (a third of its time): m = min(a, 1) gives both exactly
        w = 1.0 / a.clamp(min=1.0)
        m = a.clamp(max=1.0)
        rho = (a - 0.5 * m) * m
    else:
        w = 1.0 / (1.0 + a * a)
        rho = 0.5 * torch.log1p(a * a)
    return w, rho


def _gate_cost(gate: float, s: LevelSettings) -> float:
    # A point that lands on a surface of the destination but outside the gate pays the
    # cost of a residual at the gate (a truncated robust cost).
    _, rho = _robust(torch.tensor([gate / s.geo_scale_m]), s.robust)
    return float(rho[0])


class _System:
    """The linearisation of every pair at one set of poses (see :func:`normal_system`),
    with the per-point costs and visibility the LM acceptance test compares on.

    ``H_rel`` (P, 6, 6) and ``g_rel`` (P, 6) are built on first use: the costs alone
    decide whether an LM trial is accepted, and most trials are rejected.

    Attributes:
        pair_cost, inliers, Tinv: see :func:`normal_system`.
        cost_pts: (P, 2N) robust cost of every visible point, 0 elsewhere ((P, N)
            without the photometric term, as every residual array).
        vis: (P, 2N) bool (likewise).
    """

    def __init__(self, pair_cost, inliers, Tinv, cost_pts, vis, linearise):
        self.pair_cost, self.inliers, self.Tinv, self.cost_pts, self.vis = pair_cost, inliers, Tinv, cost_pts, vis
        self._linearise = linearise
        self._H = self._g = None

    def _normal(self):
        if self._H is None:
            self._H, self._g = self._linearise()
            self._linearise = None  # frees the residuals' intermediates
        return self._H, self._g

    @property
    def H_rel(self) -> torch.Tensor:
        return self._normal()[0]

    @property
    def g_rel(self) -> torch.Tensor:
        return self._normal()[1]

    def astuple(self):
        return self.H_rel, self.g_rel, self.pair_cost, self.inliers, self.Tinv


def _system(
    level: Level, T: torch.Tensor, pairs: torch.Tensor, s: LevelSettings, gate: float, compiled: bool | None = None
) -> _System:
    """The :class:`_System` of every pair at the poses ``T``; ``compiled``: its terms
    from :func:`~depthgt.registration.pair_terms.pair_terms`, in float32 (default: float32
    frames on the CPU) rather than from the tensors of :func:`_residuals_lazy` (a GPU's
    path, and float64 frames')."""
    a, b = pairs[:, 0], pairs[:, 1]
    Tinv = torch.linalg.inv(T)
    T_ab = Tinv[a] @ T[b]
    on_cpu = level.points.device.type == "cpu"
    if compiled is None:
        compiled = on_cpu and level.points.dtype == torch.float32
    elif compiled and not on_cpu:
        raise ValueError(f"the compiled refinement terms run on the CPU; the frames are on {level.points.device.type}")
    if compiled:
        return _system_compiled(level, T_ab, Tinv, pairs, s, gate)
    r, valid, vis, _, jac = _residuals_lazy(level, T_ab, pairs, s, gate)
    wgt, rho = _robust(r, s.robust)

    def linearise():
        J = jac()
        Jw = J * (wgt * valid)[:, None]  # (P, 6, 2N)
        H_rel = (Jw @ J.transpose(1, 2)).to(torch.float64)
        g_rel = (Jw @ r[..., None])[..., 0].to(torch.float64)
        return H_rel, g_rel

    # Only points that land on a surface of the destination take part in the cost: an
    # associated point its robust cost, a seen point outside the gate the gate's cost.
    # A point that leaves the view (or lands in a hole) costs nothing here and is left
    # out of the comparison of two poses (:func:`_accept`): charging it, as a mismatch,
    # would make the pose with the largest overlap -- the identity, the start -- a false
    # minimum that holds the refinement near where it began.
    # (valid implies vis: rho where valid, the gate's cost where only visible, else 0;
    # written without torch.where, a third of its time)
    cost_pts = rho * valid + (vis & ~valid) * _gate_cost(gate, s)
    N_ = level.valid.shape[1]
    pair_cost = cost_pts.sum(1).to(torch.float64)
    inl = (valid[:, :N_] & level.valid.index_select(0, b)).sum(1)
    return _System(pair_cost, inl, Tinv, cost_pts, vis, linearise)


def _maps_hwc(level: Level):
    """``level.geo`` and ``level.photo`` channels last, as the compiled terms read them
    (kept while ``level.geo`` is the same tensor)."""
    cached = getattr(level, "_hwc", None)
    if cached is None or cached[0] is not level.geo:
        cached = (level.geo, kernel_maps(level.geo, level.photo))
        level._hwc = cached
    return cached[1]


def _system_compiled(
    level: Level, T_ab: torch.Tensor, Tinv: torch.Tensor, pairs: torch.Tensor, s: LevelSettings, gate: float
) -> _System:
    """:func:`_system` from the compiled terms. The normal equations come with the costs:
    in the compiled pass they add a fifth to its time, where a second pass for an
    accepted trial (about half of them) would add all of it."""
    t = pair_terms(
        level.points, level.gray, level.valid, _maps_hwc(level), level.K, T_ab, pairs,
        geo_scale_m=s.geo_scale_m, geo_ref_depth_m=s.geo_ref_depth_m, gate=gate,
        photo_weight=s.photo_weight, photo_scale=s.photo_scale, huber=s.robust == "huber",
        gate_cost=_gate_cost(gate, s),
    )  # fmt: skip
    return _System(t.pair_cost, t.inliers, Tinv, t.cost_pts, t.vis, lambda: (t.H_rel, t.g_rel))


def normal_system(level: Level, T: torch.Tensor, pairs: torch.Tensor, s: LevelSettings, gate: float):
    """Robust Gauss-Newton normal equations of every pair at the poses ``T``.

    Args:
        T: (F', 4, 4) poses of the frames in the target camera; pairs: (P, 2) long
            (a, b): b's points warped into a's maps; gate: association gate (metres).

    Returns:
        ``(H_rel (P, 6, 6), g_rel (P, 6), pair_cost (P,), inliers (P,), T^-1 (F', 4, 4))``
        in float64, Jacobians w.r.t. a left twist (v, w) of ``T_ab = T_a^-1 T_b``.
        ``pair_cost`` sums the robust cost over the points that land on a surface of
        the destination (gate cost beyond the gate); :func:`pair_mean_cost` normalises it.
    """
    return _system(level, T, pairs, s, gate).astuple()


def pair_mean_cost(
    level: Level, T: torch.Tensor, pairs: torch.Tensor, s: LevelSettings, gate: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean robust cost per visible point (P,) and the visible points (P,) of every pair:
    a score that compares poses of different overlap (e.g. candidate initialisations)."""
    sys_ = _system(level, T, pairs, s, gate)
    n_vis = sys_.vis.sum(1).to(torch.float64)
    return sys_.pair_cost / n_vis.clamp(min=1), n_vis


def _accept(old: _System, new: _System, rows: torch.Tensor, n_sets: int) -> list[bool]:
    """Whether each of ``n_sets`` frame sets takes its trial: ``new`` holds the sets'
    rows ``rows`` of ``old`` (each set's pairs in turn), and a set's trial is taken when
    its cost over the points visible in both linearisations is no larger (a fair
    comparison whatever the change of overlap). Each set's cost is one float64 sum
    over all its points (not per pair, then over pairs: those round otherwise); on the
    CPU in one compiled pass."""
    if old.vis.device.type == "cpu":
        c_old, c_new = costs_seen_by_both(old.cost_pts, old.vis, rows, new.cost_pts, new.vis, n_sets)
        return (c_new <= c_old).tolist()
    whole = rows.numel() == len(old.vis)  # every row (one set): no copy
    old_vis = old.vis if whole else old.vis.index_select(0, rows)
    old_cost = old.cost_pts if whole else old.cost_pts.index_select(0, rows)
    both = old_vis & new.vis
    c_old = (old_cost * both).reshape(n_sets, -1).sum(1, dtype=torch.float64)
    c_new = (new.cost_pts * both).reshape(n_sets, -1).sum(1, dtype=torch.float64)
    return (c_new <= c_old).tolist()


def _assemble(H_rel, g_rel, Tinv, pairs, n_frames):
    A = adjoint(Tinv[pairs[:, 0]])  # (P, 6, 6)
    M = A.transpose(1, 2) @ H_rel @ A
    gA = (A.transpose(1, 2) @ g_rel[..., None])[..., 0]
    H = torch.zeros(n_frames, n_frames, 6, 6, dtype=torch.float64, device=H_rel.device)
    g = torch.zeros(n_frames, 6, dtype=torch.float64, device=H_rel.device)
    a, b = pairs[:, 0], pairs[:, 1]
    H.index_put_((b, b), M, accumulate=True)
    H.index_put_((a, a), M, accumulate=True)
    H.index_put_((a, b), -M, accumulate=True)
    H.index_put_((b, a), -M, accumulate=True)
    g.index_put_((b,), gA, accumulate=True)
    g.index_put_((a,), -gA, accumulate=True)
    return H, g


def pair_information(level_H_rel: torch.Tensor, median_depth: float) -> torch.Tensor:
    """Condition numbers (P,) of 6x6 information matrices with rotation columns scaled
    by ``median_depth`` (so both blocks are in metres)."""
    S = torch.diag(
        torch.tensor(
            [1, 1, 1, median_depth, median_depth, median_depth], dtype=level_H_rel.dtype, device=level_H_rel.device
        )
    ).inverse()
    Hs = S @ level_H_rel @ S
    ev = torch.linalg.eigvalsh(Hs)
    return ev[..., -1] / ev[..., 0].clamp(min=1e-30)


@torch.no_grad()
def refine_poses(
    rgb: torch.Tensor,
    depth_m: torch.Tensor,
    K: torch.Tensor,
    T_f_to_t: torch.Tensor,
    settings: RefineSettings = RefineSettings(),
    offsets: list[int] | None = None,
    maps_of: dict | None = None,
    cache: FrameCache | None = None,
    positions: tuple[int, ...] | None = None,
) -> RefineResult:
    """Jointly refine the poses of a frame set (frame 0 = target, kept at identity):
    :func:`refine_poses_many` of this one set (the coarse-to-fine Levenberg-Marquardt
    loop has that one home; with one set it is this set's own refinement, no evaluation
    or rounding added).

    Args:
        rgb: (F, 3, H, W) colour in [0, 1].
        depth_m: (F, 1, H, W) depth in metres, 0 = invalid.
        K: (3, 3) the frame set's one camera (every frame's intrinsics) at (H, W).
        T_f_to_t: (F, 4, 4) initial poses of each frame in the target camera
            (``T_f_to_t[0]`` is replaced by the identity).
        settings: :class:`RefineSettings`.
        offsets: frame offsets (for ``pairs="adjacent"``).
        maps_of: the :class:`Level` maps already computed for this frame set, by scale
            (a dict shared with the caller's own levels of the same frames), or None.
        cache, positions: the batch job's :class:`~depthgt.framecache.FrameCache` and
            the frames' positions in their scene: what depends on a frame alone (its
            pyramid, its noise residuals) is computed once per batch.

    Returns:
        :class:`RefineResult` with float64 poses on the input device.
    """
    sizes = check_shape(depth_m, "F 1 H W", "depth_m")
    check_shape(rgb, "F 3 H W", "rgb", sizes)
    check_shape(T_f_to_t, "F 4 4", "T_f_to_t", sizes)
    check_shape(K, "3 3", "K (the frame set's one camera)")
    return refine_poses_many([RefineSet(rgb, depth_m, T_f_to_t, offsets, positions)], K, settings, cache, maps_of)[0]


def _noise_sigma_1m(depth_m: torch.Tensor, cache: FrameCache | None, positions: tuple[int, ...] | None) -> float:
    """The frame set's depth noise at 1 m (:func:`depthgt.noise_law.estimate_noise_sigma_1m`
    of ``depth_m`` (F, 1, H, W) at the pixel centres), each frame's residuals sorted once
    per batch job when there is a ``cache``."""
    if cache is None or positions is None:
        return estimate_noise_sigma_1m(depth_m.detach().cpu())
    index = {p: i for i, p in enumerate(positions)}

    def compute(todo: list[int]) -> list[torch.Tensor]:
        return sorted_residuals(second_difference_residuals(depth_m[[index[p] for p in todo]].detach()))

    return noise_sigma_1m_of(cache.get("noise.residuals", positions, compute))


NOISE_GATE_SIGMAS = 4.0  # association gate of the noise-relative residual (sigmas; the renderer's gap_sigmas)


def target_residuals(
    level: Level, T: torch.Tensor, pairs: torch.Tensor, s: LevelSettings, gate: float, n_frames: int
) -> torch.Tensor:
    """(F,) median |point-to-plane residual| (metres) of the associated points of the
    pairs (0, b), b's points in the target."""
    return target_residual_stats(level, T, pairs, s, gate, n_frames, None)[0]


def target_residual_stats(
    level: Level,
    T: torch.Tensor,
    pairs: torch.Tensor,
    s: LevelSettings,
    gate: float,
    n_frames: int,
    sigma_1m: float | None,
    compiled: bool | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per frame (F,): the median |point-to-plane residual| (metres) of the associated
    points of the pairs (0, b), b's points in the target, and the median of the same
    residuals in units of the depth noise at each point's depth, ``sigma_1m * z^2``
    (the z^2 law of :func:`depthgt.noise_law.estimate_noise_sigma_1m`; NaN without
    ``sigma_1m``), associated within max(``gate``, 4 sigma) and taken over every point
    seen on a surface of the target (one beyond the gate counts as infinitely off). 0 for
    the target, NaN where nothing is associated / seen. ``compiled``: the residuals from
    :func:`~depthgt.registration.pair_terms.point_residuals` (default: float32 frames on
    the CPU, as :func:`_system`) rather than the tensors; the same to float32 rounding."""
    T_ab = torch.linalg.inv(T[pairs[:, 0]]) @ T[pairs[:, 1]]
    n = level.valid.shape[1]
    with_sigma = sigma_1m is not None and sigma_1m > 0
    # with the noise: the same association with the gate widened to NOISE_GATE_SIGMAS
    # sigma where that is wider (beyond ref the gate grows as (z / ref)^2, like the
    # noise), so that a noisy sensor's far points stay associated ...
    ref = math.sqrt(gate / (NOISE_GATE_SIGMAS * sigma_1m)) if with_sigma else 0.0
    if compiled is None:
        compiled = level.points.device.type == "cpu" and level.points.dtype == torch.float32
    if compiled:
        r_geo, vis, ok = point_residuals(
            level.points, level.valid, _maps_hwc(level), level.K, T_ab, pairs, gate, [s.geo_ref_depth_m, ref]
        )
        valid, valid_ref = ok[0], ok[1]
    else:
        _, valid, vis, r_geo, _ = _residuals_lazy(level, T_ab, pairs, s, gate)
        valid_ref = None
    r_geo = r_geo.abs().to(torch.float64)
    nan = torch.full_like(r_geo, float("nan"))
    med = torch.where(valid[:, :n], r_geo, nan).nanmedian(dim=1).values
    out = torch.zeros(n_frames, dtype=torch.float64, device=r_geo.device)
    out[pairs[:, 1]] = med
    out_sig = torch.zeros(n_frames, dtype=torch.float64, device=r_geo.device)
    if not with_sigma:
        out_sig[pairs[:, 1]] = float("nan")
        return out, out_sig
    if valid_ref is not None:
        valid = valid_ref
    else:
        _, valid, vis, r_geo, _ = _residuals_lazy(level, T_ab, pairs, replace(s, geo_ref_depth_m=ref), gate)
        r_geo = r_geo.abs().to(torch.float64)
    p = level.points[pairs[:, 1]].to(torch.float64)  # (P, 3, N)
    z = (T_ab[:, 2, :3, None] * p).sum(1) + T_ab[:, 2, 3, None]  # depth in the target camera
    sig = sigma_1m * z.clamp(min=0.1).square()
    # ... and over every point seen on a surface of the target: one beyond the gate counts
    # as off by more than any bound (the gate must not hide a large misregistration)
    q = torch.where(valid[:, :n], r_geo / sig, torch.full_like(r_geo, float("inf")))
    med_sig = torch.where(vis[:, :n], q, nan).nanmedian(dim=1).values
    out_sig[pairs[:, 1]] = med_sig
    return out, out_sig


def _per_frame(pcost, tgt_pairs, other, Fn):
    c = torch.zeros(Fn, dtype=torch.float64, device=pcost.device)
    c.index_add_(0, other[tgt_pairs], pcost[tgt_pairs])
    return c


class RefineSet(NamedTuple):
    """One frame set for :func:`refine_poses_many`: its members' colour (F, 3, H, W) and
    depth (F, 1, H, W), the poses ``T_f_to_t`` (F, 4, 4) to start from, the frame
    ``offsets`` (None: 0 .. F-1, as :func:`frame_pairs` takes them) and the members'
    ``positions`` in their scene (None: no frame cache)."""

    rgb: torch.Tensor
    depth_m: torch.Tensor
    T_f_to_t: torch.Tensor
    offsets: list[int] | None
    positions: tuple[int, ...] | None = None


def _merged(cur: _System, taken: list[tuple[_System, torch.Tensor, torch.Tensor]], T: torch.Tensor) -> _System:
    """``cur`` with the rows of the sets whose trial was accepted taken from the trial's
    system (``taken``: the system, its rows, the batch's rows they replace): the system
    at the accepted poses ``T`` without evaluating the residuals again. When one trial's
    system holds every row (one set, or every set accepted in the same trial), it is that
    system itself (the same values, nothing copied)."""
    first = taken[0][0]
    if all(new is first for new, _, _ in taken) and sum(int(rows.numel()) for _, _, rows in taken) == len(cur.vis):
        return first
    H, g = cur.H_rel.clone(), cur.g_rel.clone()
    pair_cost, inliers, cost_pts, vis = (
        cur.pair_cost.clone(),
        cur.inliers.clone(),
        cur.cost_pts.clone(),
        cur.vis.clone(),
    )
    for new, mine, rows in taken:
        H[rows], g[rows] = new.H_rel.index_select(0, mine), new.g_rel.index_select(0, mine)
        pair_cost[rows], inliers[rows] = new.pair_cost.index_select(0, mine), new.inliers.index_select(0, mine)
        cost_pts[rows], vis[rows] = new.cost_pts.index_select(0, mine), new.vis.index_select(0, mine)
    return _System(pair_cost, inliers, torch.linalg.inv(T), cost_pts, vis, lambda: (H, g))


@torch.no_grad()
def refine_poses_many(
    sets: list[RefineSet],
    K: torch.Tensor,
    settings: RefineSettings = RefineSettings(),
    cache: FrameCache | None = None,
    maps_of: dict | None = None,
    compiled: bool | None = None,
) -> list[RefineResult]:
    """:func:`refine_poses` of several frame sets of one camera (its intrinsics ``K`` (3, 3),
    the same number of members and offsets) at once: every set's pairs in the same
    residual evaluations (what keeps a GPU busy), each set with its own Levenberg-
    Marquardt damping, trials and stopping. The same poses as one set at a time up to
    the rounding of the batched products; after a step the accepted sets' rows of the
    trial's system replace theirs (no evaluation beyond one set at a time's). With one
    set this is :func:`refine_poses` itself (the CPU build's path), the same numbers.

    ``maps_of``: the :class:`Level` maps of the sets' frames (in the sets' order) by
    scale, read and filled (refine_poses' argument, one set's), or None. ``compiled``:
    the residuals' terms compiled (:func:`_system`; default: on the CPU).

    Long because the coarse-to-fine loop carries every set's poses, damping and state
    across scales, iterations and trials side by side; its parts (``_system``,
    ``_accept``, ``_assemble``, ``_merged``, the per-frame statistics) are functions.
    """
    check_shape(K, "3 3", "K (the frame sets' one camera)")
    if not sets:  # a group with no set left (every one skipped): nothing to refine
        return []
    n_sets, Fn = len(sets), sets[0].depth_m.shape[0]
    offsets = [list(s.offsets) if s.offsets is not None else list(range(Fn)) for s in sets]
    if any(s.depth_m.shape != sets[0].depth_m.shape or o != offsets[0] for s, o in zip(sets, offsets)):
        raise ValueError("refine_poses_many: every frame set needs the same members' shape and offsets")
    dev = sets[0].depth_m.device
    if n_sets == 1:
        rgb, depth = sets[0].rgb, sets[0].depth_m
    else:
        rgb, depth = torch.cat([s.rgb for s in sets]), torch.cat([s.depth_m for s in sets])
    positions = None
    if cache is not None and all(s.positions is not None for s in sets):
        positions = tuple(p for s in sets for p in s.positions)
    eye = torch.eye(4, dtype=torch.float64, device=dev)
    T = torch.cat([s.T_f_to_t.to(dev, torch.float64) for s in sets]).clone()
    T[::Fn] = eye
    one = frame_pairs(Fn, settings.pairs, offsets[0]).to(dev)
    n_p = one.shape[0]
    pairs = torch.cat([one + b * Fn for b in range(n_sets)]) if n_sets > 1 else one
    tgt_pairs = (one[:, 0] == 0) | (one[:, 1] == 0)
    other = torch.where(one[:, 0] == 0, one[:, 1], one[:, 0])
    outs = [RefineResult(T_f_to_t=T[b * Fn : (b + 1) * Fn]) for b in range(n_sets)]
    eye6 = torch.eye(6 * (Fn - 1), dtype=torch.float64, device=dev)
    last = None
    for li, (scale, n_it, stride, gate) in enumerate(
        zip(settings.scales, settings.iters, settings.point_stride, settings.max_dist_m)
    ):
        # a scale before the finest stops at a coarser step: the next one moves further
        finest = li == len(settings.scales) - 1
        settled = FINEST_SETTLED if finest else max(FINEST_SETTLED, settings.coarse_converged_step)
        level = Level(rgb, depth, K, scale, stride, maps_of, cache, positions)
        if scale == 1:
            for b in range(n_sets):
                outs[b].normals = level.geo[b * Fn : (b + 1) * Fn, 3:6]  # channels X(3) N(3) ...
        ls = LevelSettings(
            settings.geo_scale_m[li], settings.photo_scale, settings.photo_weight, settings.robust,
            settings.geo_ref_depth_m,
        )  # fmt: skip
        lam = [settings.damping] * n_sets
        active = [True] * n_sets
        cur = _system(level, T, pairs, ls, gate, compiled)
        if li == len(settings.scales) - 1:
            for b in range(n_sets):
                outs[b].initial_cost = _per_frame(cur.pair_cost[b * n_p : (b + 1) * n_p], tgt_pairs, other, Fn)
        for _ in range(n_it):
            if not any(active):
                break
            H, g = _assemble(cur.H_rel, cur.g_rel, cur.Tinv, pairs, n_sets * Fn)
            Hr, gr = [], []
            for b in range(n_sets):
                f = slice(b * Fn + 1, (b + 1) * Fn)
                Hr.append(H[f, f].permute(0, 2, 1, 3).reshape(6 * (Fn - 1), 6 * (Fn - 1)))
                gr.append(g[f].reshape(-1))
            step = [0.0] * n_sets
            improved = [False] * n_sets
            taken = []  # (the trial's system, its rows, the batch's rows) of each accepted set
            trying = [b for b in range(n_sets) if active[b]]
            rejected: dict[int, torch.Tensor] = {}  # each set's last evaluated, rejected step
            for _try in range(5):
                if not trying:
                    break
                A = torch.stack(
                    [Hr[b] + lam[b] * torch.diag(torch.diagonal(Hr[b]).clamp(min=1e-9)) + 1e-9 * eye6 for b in trying]
                )
                deltas = torch.linalg.solve(A, -torch.stack([gr[b] for b in trying])[..., None])[..., 0]
                deltas = deltas.reshape(len(trying), Fn - 1, 6)
                sizes = deltas.abs().flatten(1).max(1).values.tolist()
                keep = [i for i, b in enumerate(trying) if not (_try and sizes[i] < MIN_TRIAL_STEP)]
                trying, deltas = [trying[i] for i in keep], deltas[keep]
                if not trying:
                    break  # damped below a micrometre (microradian): those sets have settled
                repeat = [
                    b in rejected
                    and float((deltas[i] - rejected[b]).abs().max())
                    < max(SAME_TRIAL, SAME_TRIAL_SHARE * float(rejected[b].abs().max()))
                    for i, b in enumerate(trying)
                ]
                waiting = [b for b, r in zip(trying, repeat) if r]  # damped further, not evaluated
                for i, b in enumerate(trying):
                    if repeat[i]:
                        lam[b] *= 10.0
                        rejected[b] = deltas[i]
                fresh = [i for i, r in enumerate(repeat) if not r]
                if not fresh:
                    trying = waiting
                    continue
                trying, deltas = [trying[i] for i in fresh], deltas[fresh]
                T_new = T.clone()
                for i, b in enumerate(trying):
                    f = slice(b * Fn + 1, (b + 1) * Fn)
                    T_new[f] = se3_exp(deltas[i]) @ T[f]
                rows = torch.cat([torch.arange(b * n_p, (b + 1) * n_p, device=dev) for b in trying])
                new = _system(level, T_new, pairs.index_select(0, rows), ls, gate, compiled)
                accept = _accept(cur, new, rows, len(trying))
                still = []
                for i, b in enumerate(trying):
                    if accept[i]:
                        f = slice(b * Fn, (b + 1) * Fn)
                        T[f] = T_new[f]
                        taken.append(
                            (new, torch.arange(i * n_p, (i + 1) * n_p, device=dev), rows[i * n_p : (i + 1) * n_p])
                        )
                        lam[b] = max(lam[b] / 3.0, 1e-7)
                        improved[b] = True
                        step[b] = float(deltas[i].abs().max())
                    else:
                        lam[b] *= 10.0
                        rejected[b] = deltas[i]
                        still.append(b)
                trying = sorted(still + waiting)
            if taken:
                cur = _merged(cur, taken, T)  # the linearisation at the accepted poses
            for b in range(n_sets):
                if active[b]:
                    outs[b].cost_curve.append(float(cur.pair_cost[b * n_p : (b + 1) * n_p].sum()))
                    active[b] = improved[b] and not step[b] < settled  # (NaN: not settled)
        last = (level, cur)
    level, cur = last
    sel = one[:, 0] == 0  # neighbour b into the target
    ls = replace(ls, geo_ref_depth_m=0.0)
    for b in range(n_sets):
        out = outs[b]
        r = slice(b * n_p, (b + 1) * n_p)
        H_rel, pcost, inl = cur.H_rel[r], cur.pair_cost[r], cur.inliers[r]  # the finest scale's only
        out.T_f_to_t = T[b * Fn : (b + 1) * Fn]
        out.final_cost = _per_frame(pcost, tgt_pairs, other, Fn)
        n_valid = level.valid[b * Fn : (b + 1) * Fn].sum(1).clamp(min=1)
        frac = torch.ones(Fn, dtype=torch.float64, device=dev)
        frac[one[sel, 1]] = inl[sel].to(torch.float64) / n_valid[one[sel, 1]].to(torch.float64)
        out.inlier_fraction = frac
        cond = torch.ones(Fn, dtype=torch.float64, device=dev)
        H_tgt = torch.zeros(Fn, 6, 6, dtype=torch.float64, device=dev)
        H_tgt.index_add_(0, other[tgt_pairs], H_rel[tgt_pairs])
        cond[1:] = pair_information(H_tgt[1:], float(_median_depth(level._depth[b * Fn : (b + 1) * Fn])))
        out.condition = cond
        # the statistics of the high_residual check, calibrated with constant scale and
        # gate: in metres and in units of the sensor noise the frame set shows
        out.noise_sigma_1m = _noise_sigma_1m(sets[b].depth_m, cache, sets[b].positions)
        res_m, res_s = target_residual_stats(
            level, T, one[sel] + b * Fn, ls, settings.max_dist_m[-1], n_sets * Fn, out.noise_sigma_1m
        )
        out.residual_m, out.residual_sigmas = res_m[b * Fn : (b + 1) * Fn], res_s[b * Fn : (b + 1) * Fn]
    return outs
