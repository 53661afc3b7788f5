"""Views added for coverage (``frameset.selection: coverage``).

The paper's window (t +- k*stride) shares the target's projector shadows, black and
specular surfaces and undistortion border, so some of the target's pixels get no GT
from it however the renderer is set (docs/decisions.md "What more completeness would cost"). Coverage keeps
that window as the core, rendered exactly as with ``window``, and adds up to
``coverage_views`` frames from within +-``coverage_span`` frames:

1. candidates: the scene's frames in the span, outside the core, of the target's split
   (the planning's split guard, :func:`depthgt.gt.planning.coverage_candidates`), that
   read fine and lie within the baseline and viewing-angle limits by the source's
   poses (a view the registration could not align is never chosen);
2. each candidate's valid depth is projected into the target with those poses; views
   are chosen greedily by how many of the core's still-empty pixels they would fill
   (:func:`choose_views`);
   With ``overfit`` (no source poses) the candidates' poses come from a chain through
   the core (:func:`chain_poses`): from the outermost registered core member on each
   side outwards at the core's stride, each frame refined against the previous one;
   the chain stops where a link fails the neighbour checks;
3. the chosen views go through the registration of the frame set's method (``given``:
   the source's poses; ``refine``: refined on the target and the added views, with the
   neighbour checks; ``overfit``: the same refinement started from the chain's poses;
   one that fails is left out with its reason, never fused unaligned);
4. the core's fused members and the registered views are rendered together by the
   same renderer (its agreement check, front-surface guard and sigma); the result is
   taken only where the core has no GT, so every pixel the core decides is the core's,
   bit for bit (:func:`add_coverage_views`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numba
import numpy as np
import torch
from kornia.geometry.depth import unproject_meshgrid
from kornia.geometry.liegroup import Se3

from depthgt import geometry
from depthgt.depth_ops import window_max
from depthgt.errors import FrameError
from depthgt.gt.render import Fusion, fuse, whole_frame_threshold
from depthgt.gt.render.cloud import FrameGeometry, cached_geometry
from depthgt.gt.render.settings import RenderSettings
from depthgt.gt.settings import FrameSetSettings
from depthgt.metric_vocabulary import depth_errors
from depthgt.registration import Alignment, FrameSetData, load_depth, load_frameset, load_poses, photometric_for
from depthgt.registration.local import refine_source_poses
from depthgt.registration.methods import METHODS
from depthgt.registration.settings import RegistrationSettings
from depthgt.shapes import check_shape
from depthgt.sources.base import Scene, check_frame
from depthgt.status import Status

__all__ = [
    "view_limits",
    "fill_maps",
    "mixed_samples",
    "choose_views",
    "chain_poses",
    "CoverageResult",
    "add_coverage_views",
]


def view_limits(T_c_to_t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Baseline (metres) and angle between the viewing directions (degrees) of each
    candidate camera relative to the target.

    Args:
        T_c_to_t: (C, 4, 4) poses mapping candidate-camera points into the target camera.

    Returns:
        baseline_m (C,), angle_deg (C,): the distance between the optical centres and
        the angle between the optical axes (a roll about the axis does not count).
    """
    check_shape(T_c_to_t, "C 4 4", "T_c_to_t")
    baseline = T_c_to_t[:, :3, 3].norm(dim=1)
    angle = torch.rad2deg(torch.arccos(T_c_to_t[:, 2, 2].clamp(-1.0, 1.0)))  # z axis of c seen in t, against t's
    return baseline, angle


@numba.njit(cache=True, nogil=True)
def _landing(depth, grid, K, T, empty, eps):  # pragma: no cover (compiled)
    """:func:`fill_maps` in one compiled pass over the candidates' pixels: each valid
    point (``grid`` (H, W, 3) kornia's unprojection grid times its depth) moved by ``T``
    (C, 4, 4), projected with ``K`` and rounded to its nearest pixel, marks that pixel
    when ``empty``. The tensors' float operations in their order, but for the rotation's
    products, which BLAS sums in its own order (a point off by a float rounding). Tried
    and not kept (2026-11-29): each row's projections in a branch-free loop (numpy's
    error model, so that it vectorises), then the marks: the same maps, no faster (30
    candidates of 256x256 with 20 % holes: 35.3 against 36.7 ms in float32, 21.8 against
    21.1 in float64)."""
    c_n, h, w = depth.shape
    hit = np.zeros((c_n, h * w), np.bool_)
    k00, k01, k02, k11, k12 = K[0, 0], K[0, 1], K[0, 2], K[1, 1], K[1, 2]
    half = depth.dtype.type(0.5)
    for c in range(c_n):
        r00, r01, r02, t0 = T[c, 0, 0], T[c, 0, 1], T[c, 0, 2], T[c, 0, 3]
        r10, r11, r12, t1 = T[c, 1, 0], T[c, 1, 1], T[c, 1, 2], T[c, 1, 3]
        r20, r21, r22, t2 = T[c, 2, 0], T[c, 2, 1], T[c, 2, 2], T[c, 2, 3]
        for y in range(h):
            for x in range(w):
                z = depth[c, y, x]
                if not z > 0:
                    continue
                px, py, pz = grid[y, x, 0] * z, grid[y, x, 1] * z, grid[y, x, 2] * z
                zt = (px * r20 + py * r21 + pz * r22) + t2
                if not zt > eps:  # behind the camera (the tensors' uv = -inf)
                    continue
                xt = (px * r00 + py * r01 + pz * r02) + t0
                yt = (px * r10 + py * r11 + pz * r12) + t1
                u = math.floor(k00 * xt / zt + k01 * yt / zt + k02 + half)
                v = math.floor(k11 * yt / zt + k12 + half)
                if 0 <= u < w and 0 <= v < h and empty[int(v), int(u)]:
                    hit[c, int(v) * w + int(u)] = True
    return hit


def fill_maps(
    depth_m: torch.Tensor, K: torch.Tensor, T_c_to_t: torch.Tensor, empty: torch.Tensor, *, compiled: bool | None = None
) -> torch.Tensor:
    """Which of the target's empty pixels each candidate's valid depth lands on.

    Args:
        depth_m: (C, 1, H, W) candidates' depth in metres, 0 = invalid (C = 0: no
            candidate, an empty (0, H*W) map).
        K: (3, 3) the frame set's one camera (every frame's intrinsics) at (H, W).
        T_c_to_t: (C, 4, 4) poses of the candidates in the target camera.
        empty: (H, W) bool, the target's pixels without GT.
        compiled: one compiled pass (:func:`_landing`; default on the CPU) or the
            tensors (a GPU's path); the same maps up to a point at a rounding edge.

    Returns:
        (C, H*W) bool: pixel p of the target is empty and some valid point of candidate c
        projects (nearest pixel, in front of the camera) onto it.
    """
    sizes = check_shape(depth_m, "C 1 H W", "fill_maps: depth_m")
    check_shape(T_c_to_t, "C 4 4", "fill_maps: T_c_to_t", sizes)
    check_shape(empty, "H W", "fill_maps: empty", sizes)
    check_shape(K, "3 3", "fill_maps: K (the frame set's one camera)")
    c, h, w = sizes["C"], sizes["H"], sizes["W"]
    dt = depth_m.dtype
    if compiled is None:
        compiled = depth_m.device.type == "cpu"
    elif compiled and depth_m.device.type != "cpu":
        raise ValueError(f"the compiled fill maps take CPU tensors, got {depth_m.device.type}")
    if compiled and c > 0:
        # ~6x faster than the tensors' dozen (C, H*W) planes: 0.10-0.14 s against 17-25 ms
        # per frame set of 25-34 candidates on TUM
        grid = unproject_meshgrid(h, w, K.to(dt)[None], False, depth_m.device, dt)[0]
        hit = _landing(
            *(t.contiguous().numpy() for t in (depth_m[:, 0], grid, K.to(dt), T_c_to_t.to(dt), empty)),
            depth_m.detach().numpy().dtype.type(1e-6),  # the tensors' eps, in their precision
        )
        return torch.from_numpy(hit)
    Kb = K.to(dt)[None].expand(c, 3, 3)
    pts = geometry.backproject(depth_m, Kb)
    T = T_c_to_t.to(dt)
    pts_t = pts @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    uv, z = geometry.project(pts_t, Kb)
    u, v = torch.floor(uv[..., 0] + 0.5), torch.floor(uv[..., 1] + 0.5)
    ok = (depth_m.reshape(c, h * w) > 0) & (z > 0) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    pix = torch.where(ok, v * w + u, torch.zeros_like(u)).long()
    slot = torch.arange(c, device=depth_m.device)[:, None] * (h * w) + pix
    hit = torch.zeros(c * h * w, dtype=torch.bool, device=depth_m.device)
    hit[slot[ok]] = True
    return hit.reshape(c, h * w) & empty.reshape(1, -1)


def mixed_samples(depth_m: torch.Tensor, margin_px: int, jump_rel: float) -> torch.Tensor:
    """The valid samples a sensor may have mixed from fore- and background: within
    ``margin_px`` pixels (Chebyshev) of an invalid pixel of their own frame, or where the
    depth range of that (2 margin + 1)^2 window exceeds ``jump_rel`` times their depth.

    Inside the window the target's neighbours outvote such samples; a view added for
    coverage fills the pixels where they see nothing, so there nothing would. Chosen on
    tuning data (docs/decisions.md "Mixed samples of the added views"): beside holes on the synthetic
    tuning set (the added pixels' mean error 129 -> 48 mm; the jumps changed nothing
    there), at jumps on the shared real recordings (the added views' leave-target-out
    check 164 -> 103 mm on 7-Scenes, 111 -> 80 mm on TUM).

    Args:
        depth_m: (N, 1, H, W) depth in metres, 0 = invalid.
        margin_px: 0: none is mixed.
        jump_rel: 0: holes only.

    Returns:
        (N, 1, H, W) bool.

    >>> d = torch.ones(1, 1, 1, 8); d[..., 0] = 0.0; d[..., 6:] = 2.0
    >>> mixed_samples(d, 1, 0.0)[0, 0, 0].int().tolist()
    [0, 1, 0, 0, 0, 0, 0, 0]
    >>> mixed_samples(d, 1, 0.03)[0, 0, 0].int().tolist()
    [0, 1, 0, 0, 0, 1, 1, 0]
    """
    valid = depth_m > 0
    if margin_px <= 0:
        return torch.zeros_like(valid)
    k = 2 * margin_px + 1
    # window_max (max_pool2d's values) pads with -inf: the image border is neither a hole nor a jump
    mixed = window_max((~valid).to(depth_m.dtype), k) > 0
    if jump_rel > 0:
        hi = window_max(torch.where(valid, depth_m, 0.0), k)
        lo = -window_max(torch.where(valid, -depth_m, -float("inf")), k)
        mixed |= hi - lo > jump_rel * depth_m
    return valid & mixed


def choose_views(fill: torch.Tensor, n_views: int, min_fill_px: int) -> list[tuple[int, int]]:
    """Greedy set cover: repeatedly the candidate that fills the most still-uncovered
    pixels, until ``n_views`` are chosen or none would fill ``min_fill_px``.

    Args:
        fill: (C, P) bool, the pixels each candidate would fill (:func:`fill_maps`).

    Returns:
        (candidate index, pixels it fills beyond the views chosen before it), in the
        order chosen.

    >>> choose_views(torch.tensor([[1, 1, 0, 0], [1, 1, 1, 0], [0, 0, 0, 1]], dtype=torch.bool), 3, 1)
    [(1, 3), (2, 1)]
    """
    fill = fill[:, fill.any(0)]  # the pixels some candidate fills: a few of the image's
    uncovered = torch.ones(fill.shape[1], dtype=torch.bool, device=fill.device)
    chosen: list[tuple[int, int]] = []
    for _ in range(n_views):  # a handful of views: one vectorised count per pick
        gain = (fill & uncovered).sum(dim=1)
        if chosen:
            gain[[i for i, _ in chosen]] = -1
        best = int(gain.argmax()) if gain.numel() else -1
        if best < 0 or int(gain[best]) < min_fill_px:
            break
        chosen.append((best, int(gain[best])))
        uncovered &= ~fill[best]
    return chosen


def chain_poses(
    frames: dict[int, tuple[torch.Tensor, torch.Tensor]],
    K: torch.Tensor,
    known: dict[int, torch.Tensor],
    wanted: list[int],
    step: int,
    reg: RegistrationSettings,
) -> tuple[dict[int, torch.Tensor], dict[str, Any]]:
    """Poses of frames beyond the core without the source's poses: a chain through the
    core's registered members (``overfit`` with ``selection: coverage``).

    On each side the chain starts at the registered member farthest from the target
    and walks outwards at ``step`` frames (the core's stride); each frame is refined
    against the previous link (:func:`~depthgt.registration.local.refine_source_poses`
    on the pair, started at the previous link's motion: constant velocity) and goes
    through the neighbour checks; its pose in the target is the composition. A frame
    that is not in ``frames`` (unusable) is stepped over; a link that fails its checks
    ends the chain on that side (the frames beyond are not reached: never chosen,
    never fused unaligned).

    Args:
        frames: offset -> (rgb (3, H, W), depth_m (1, H, W)) of every frame at hand:
            the core's members and the candidates.
        K: (3, 3) the frame set's one camera at (H, W).
        known: offset -> (4, 4) float64 pose in the target of the core's registered
            members (the target, offset 0, included).
        wanted: the candidates' offsets; the chain walks as far as the farthest of them.
        step: frames between links.
        reg: the frame set's registration settings (refinement and checks).

    Returns:
        offset -> (4, 4) pose in the target of each chained frame on the ``step`` grid
        of its side, and the record: the links made (offset, from, status, reason) and
        where each side stopped and why.
    """
    out: dict[int, torch.Tensor] = {}
    links: list[dict[str, Any]] = []
    stopped: dict[str, str] = {}
    for sign in (-1, 1):
        side = sorted((o for o in known if o * sign >= 0), key=abs)
        far = max((abs(o) for o in wanted if o * sign > 0), default=0)
        last = side[-1]
        if far <= abs(last):
            continue
        # the motion per link from the two outermost known members (constant velocity)
        inner = side[-2] if len(side) > 1 else None
        if inner is not None:
            per = abs(last - inner) / step
            motion = torch.linalg.inv(known[inner]) @ known[last]
            velocity = _matrix_root(motion, per)
        else:
            velocity = torch.eye(4, dtype=torch.float64, device=K.device)
        T_last, gap = known[last], 1
        for o in range(last + sign * step, sign * (far + 1), sign * step):
            if o not in frames:
                gap += 1
                continue
            init = torch.linalg.matrix_power(velocity, gap)
            (rgb_a, d_a), (rgb_b, d_b) = frames[last], frames[o]
            res = refine_source_poses(
                torch.stack([rgb_a, rgb_b]), torch.stack([d_a, d_b]), K, [0, o - last], init[None], reg
            )
            status, reason = res.neighbour_status[0], res.neighbour_reasons[0]
            links.append({"offset": o, "from": last, "status": status, "reason": reason})
            if status != Status.OK:
                stopped["-" if sign < 0 else "+"] = f"link {last:+d} -> {o:+d}: {reason}"
                break
            T_rel = res.T_j_to_t[0].to(T_last.device, torch.float64)
            T_last = T_last @ T_rel
            out[o] = T_last
            velocity = _matrix_root(T_rel, gap) if gap > 1 else T_rel
            last, gap = o, 1
    return out, {"step": step, "links": links, "stopped": stopped}


def _matrix_root(T: torch.Tensor, n: float) -> torch.Tensor:
    """The rigid motion done ``n`` times giving ``T`` (4, 4): the screw motion's
    fraction ``exp(log(T) / n)`` on SE(3) (kornia's Lie group)."""
    if n == 1:
        return T
    with torch.no_grad():
        return Se3.exp(Se3.from_matrix(T[None]).log() / n).matrix()[0].to(T.dtype)


@dataclass
class CoverageResult:
    """What :func:`add_coverage_views` made.

    Attributes:
        render: the GT: the core's render where it has GT, the render of the core with
            the added views where it has none (``agreement``, ``disagreement`` and
            ``left_out`` are the core's).
        record: frameset.json's ``coverage``: the candidates, each added view with why
            (its planned fill), its status and reason.
        statistics: on real data ``leave_target_out_all_views`` (the core's neighbours and
            the added views fused without the target, against the target's raw depth)
            and ``leave_target_out_added`` (that check only where the core's neighbours
            alone left the target empty: the added views' own accuracy).
        T_j_to_t: offset -> (4, 4) pose of each added view that entered the render.
        full: the render of the core with the added views at the pixels the core left
            empty (the only ones it is taken at; its frame agreement and, on real data,
            its ``left_out`` over every pixel); None when no view was added.
    """

    render: Fusion
    record: dict[str, Any]
    statistics: dict[str, Any] = field(default_factory=dict)
    T_j_to_t: dict[int, list] = field(default_factory=dict)
    full: Fusion | None = None


def _usable(scene: Scene, positions: list[int], need_pose: bool) -> tuple[list[int], dict[int, str]]:
    good, bad = [], {}
    for p in positions:
        check = getattr(scene, "check", None)  # a ResizedScene remembers each frame's outcome
        if check is not None:
            c = check(p)
            if c.valid:
                good.append(p)
            else:
                bad[p] = c.problem
            continue
        try:
            check_frame(scene.read(p), scene.image_size, f"{scene.name} frame {scene.frame_id(p)}", need_pose=need_pose)
            good.append(p)
        except FrameError as err:
            bad[p] = f"{err.reason} ({err})"
    return good, bad


def _register(
    data: FrameSetData, offsets: list[int], reg: RegistrationSettings, T_start: torch.Tensor | None = None
) -> tuple[torch.Tensor, list[str], list[str]]:
    """Poses of the added views (target first in ``data``): by the frame set's method
    (:data:`depthgt.registration.METHODS`) from the source's poses (``given``,
    ``refine``), or (``overfit``) refined on the target and the views from ``T_start``
    (F-1, 4, 4), the chain's poses."""
    settings = photometric_for(reg, data.colour_matches_depth)
    if reg.uses_source_poses:
        register = METHODS[reg.method]  # looked up at call time so tests can replace it
        res = register(data, offsets, settings)
    else:
        if T_start is None:
            raise ValueError(f"coverage views of registration.method {reg.method!r} need their chain's poses")
        res = refine_source_poses(
            data.rgb, data.depth_m, data.K, offsets, T_start, settings, cache=data.cache, positions=data.positions
        )
    T = torch.as_tensor(res.T_j_to_t, dtype=torch.float64, device=data.depth_m.device)
    return T, list(res.neighbour_status), list(res.neighbour_reasons)


def _without_mixed(
    data: FrameSetData,
    positions: list[int],
    depth_of: Callable[[list[int]], torch.Tensor],
    fs: FrameSetSettings,
) -> torch.Tensor:
    """The depth (C, 1, H, W) of the candidates at ``positions`` (``depth_of(positions)``,
    raw) with their mixed samples (:func:`mixed_samples`) set to 0, each frame's found
    (and its raw depth read) once per batch job when the frame set has the job's frame
    cache (a candidate serves the targets around it)."""
    margin, jump = fs.coverage_mixed_margin_px, fs.coverage_mixed_jump_rel
    if data.cache is None or not positions:
        depth_m = depth_of(positions)
        return depth_m.masked_fill(mixed_samples(depth_m, margin, jump), 0.0)

    def compute(todo: list[int]) -> list[torch.Tensor]:
        rows = depth_of(todo)
        # each frame's own copy: a view would keep the whole batch of rows alive in the cache
        return [r.clone() for r in rows.masked_fill(mixed_samples(rows, margin, jump), 0.0).unbind(0)]

    return torch.stack(data.cache.get(f"coverage.without_mixed:{margin}:{jump}", positions, compute))


def _geometry(
    data: FrameSetData, positions: list[int], added_depth: torch.Tensor, fs: FrameSetSettings
) -> FrameGeometry | None:
    """The :class:`~depthgt.gt.render.cloud.FrameGeometry` of the core's members and the
    added views (at ``positions``, their depth ``added_depth`` (V, 1, H, W) without their
    mixed samples, :func:`_without_mixed`) in that order, each frame's from the batch
    job's frame cache (the core's computed by the window's render; an added view's by the
    first frame set that adds it: a view serves several targets around it); None without a
    cache (:func:`fuse` computes all)."""
    if data.cache is None or data.positions is None:
        return None
    core = cached_geometry(data.cache, data.positions, data.depth_m, data.K, src_hw=data.src_hw)
    of = f"coverage.geometry:{fs.coverage_mixed_margin_px}:{fs.coverage_mixed_jump_rel}"
    added = cached_geometry(data.cache, positions, added_depth, data.K, src_hw=data.src_hw, of=of)
    return FrameGeometry.stack([core, added])


def add_coverage_views(
    scene: Scene,
    target: int,
    candidates: list[int],
    data: FrameSetData,
    alignment: Alignment,
    core: Fusion,
    fs: FrameSetSettings,
    reg: RegistrationSettings,
    render: RenderSettings,
    core_offsets: list[int] | None = None,
) -> CoverageResult:
    """Fill the pixels the core left without GT from added views (module docstring).

    Args:
        scene: the frame set's scene (frames read through it, at ``data``'s size).
        target: the target's position; ``candidates``: positions the planning allows
            (:func:`depthgt.gt.planning.coverage_candidates`).
        data, alignment, core: the core frame set, its registration and its render.
        core_offsets: the core members' offsets (``data``'s order); needed by a method
            without the source's poses (the chain starts at the core's members).
        fs: the limits and counts (``coverage_*``); reg, render: the frame set's
            registration and renderer settings.

    Long because its steps (usable candidates, limits, fill maps, choice, registration,
    the render with the added views, the merge, the record of each view) share the
    candidate views' tensors and records; the computations are functions of their own
    (:func:`view_limits`, :func:`fill_maps`, :func:`choose_views`, ``_register``).
    """
    h, w = data.depth_m.shape[-2:]
    empty = core.gt.depth[0, 0] <= 0
    record: dict[str, Any] = {
        "selection": "coverage",
        "candidates": len(candidates),
        "gt_missing_core": round(float(empty.float().mean()), 6),
        "added": [],
    }

    def keep() -> Fusion:  # nothing added: the core's render as it is
        return core

    need_pose = reg.uses_source_poses
    usable, bad = _usable(scene, candidates, need_pose)
    record["unusable"] = {str(p - target): why for p, why in bad.items()}
    if not usable or fs.coverage_views == 0 or not bool(empty.any()):
        record["beyond_limits"] = 0
        return CoverageResult(keep(), record)
    dev = data.depth_m.device
    cand = None  # with the source's poses, a candidate's images are read only as needed
    if need_pose:
        T_world_cam = load_poses(scene, [target, *usable], dev)
        T_c_to_t = torch.linalg.inv(T_world_cam[:1]) @ T_world_cam[1:]
    else:
        cand = load_frameset(scene, [target, *usable], (h, w), need_poses=False, device=dev)
        if core_offsets is None or len(core_offsets) != data.depth_m.shape[0]:
            raise ValueError(f"coverage with registration.method {reg.method!r} needs the core's offsets")
        known = {0: torch.eye(4, dtype=torch.float64, device=dev)}
        known.update({core_offsets[i]: alignment.T_j_to_t[i - 1].to(dev, torch.float64) for i in alignment.fused if i})
        frames = {o: (data.rgb[i], data.depth_m[i]) for i, o in enumerate(core_offsets) if o in known}
        frames.update({p - target: (cand.rgb[k + 1], cand.depth_m[k + 1]) for k, p in enumerate(usable)})
        chained, record["chain"] = chain_poses(
            frames,
            data.K,
            known,
            [p - target for p in usable],
            fs.stride,
            photometric_for(reg, data.colour_matches_depth),
        )
        nan = torch.full((4, 4), math.nan, dtype=torch.float64, device=dev)
        T_c_to_t = torch.stack([chained.get(p - target, nan) for p in usable])
    reached = torch.isfinite(T_c_to_t).flatten(1).all(dim=1)
    baseline, angle = view_limits(T_c_to_t)
    within = reached & (baseline <= fs.coverage_max_baseline_m) & (angle <= fs.coverage_max_angle_deg)
    record["beyond_limits"] = int((reached & ~within).sum())
    if not need_pose:
        record["not_chained"] = int((~reached).sum())
    idx = torch.nonzero(within).flatten()
    if idx.numel() == 0:  # none reached (overfit: the chain stopped before them) or within the limits
        return CoverageResult(keep(), record)
    # what a candidate within the limits fills with: its samples away from its own holes
    # and depth jumps
    row = {p: k for k, p in enumerate(usable)}

    def depth_of(positions: list[int]) -> torch.Tensor:
        if cand is not None:
            return cand.depth_m[[1 + row[p] for p in positions]]
        return load_depth(scene, positions, (h, w), dev)

    usable_depth = _without_mixed(data, [usable[i] for i in idx.tolist()], depth_of, fs)
    fill = fill_maps(usable_depth, data.K, T_c_to_t[idx], empty)
    picks = choose_views(fill, fs.coverage_views, fs.coverage_min_fill_px)
    if not picks:
        return CoverageResult(keep(), record)
    picked = [i for i, _ in picks]  # positions in idx
    chosen = [int(idx[i]) for i in picked]  # positions in cand's neighbours
    offsets = [0, *(usable[c] - target for c in chosen)]
    sel = [0, *(c + 1 for c in chosen)]
    # the raw frames at the frame set's size: their refinement pyramids and noise
    # residuals come from (and stay in) the batch job's frame cache
    positions = (target, *(usable[c] for c in chosen)) if data.cache is not None else None
    if cand is None:
        added = replace(
            load_frameset(scene, [target, *(usable[c] for c in chosen)], (h, w), True, dev, cache=data.cache),
            positions=positions,
        )
    else:
        added = FrameSetData(
            cand.rgb[sel],
            cand.depth_m[sel],
            cand.K,
            cand.T_world_cam[sel] if cand.T_world_cam is not None else None,
            cand.truth_m[sel] if cand.truth_m is not None else None,
            [cand.frame_ids[i] for i in sel],
            cand.src_hw,
            cand.colour_matches_depth,
            positions=positions,
            cache=data.cache,
        )
    T_added, status, reasons = _register(added, offsets, reg, T_c_to_t[chosen])
    views = [
        {
            "offset": o,
            "planned_fill_px": g,
            "baseline_m": round(float(baseline[c]), 4),
            "angle_deg": round(float(angle[c]), 2),
            "status": st,
            "reason": why,
        }
        for o, (_, g), c, st, why in zip(offsets[1:], picks, chosen, status, reasons)
    ]
    record["added"] = views
    ok = [k for k, v in enumerate(views) if v["status"] == Status.OK]
    if not ok:
        return CoverageResult(keep(), record)

    # the core's fused members and the registered views, rendered together
    n = data.depth_m.shape[0]
    both = FrameSetData(
        torch.cat([data.rgb, added.rgb[1:]]),
        torch.cat([data.depth_m, usable_depth[picked]]),
        data.K,
        None,
        torch.cat([data.truth_m, added.truth_m[1:]])
        if data.truth_m is not None and added.truth_m is not None
        else None,
        [*data.frame_ids, *added.frame_ids[1:]],
        data.src_hw,
        data.colour_matches_depth,
    )
    T_both = torch.cat([alignment.T_j_to_t.to(torch.float64), T_added.to(alignment.T_j_to_t.device, torch.float64)])
    members = [*alignment.fused, *(n + k for k in ok)]
    # the core's members come first, with the same poses: their cells are the core render's
    same_core = core.cells is not None and tuple(members[: len(core.members)]) == tuple(core.members)
    full = fuse(
        both,
        T_both,
        render,
        members=members,
        leave_target_out=data.truth_m is None,
        geometry=_geometry(data, [usable[c] for c in chosen], usable_depth[picked], fs),
        pixels=empty,  # only the core's empty pixels take its GT (the agreement sees all)
        prior=core.cells if same_core else None,
    )
    share = full.gt.agreement[0].cpu().numpy() if full.gt.agreement.numel() else np.full(len(members), np.nan)
    filled = empty & (full.gt.depth[0, 0] > 0)
    left_whole = set(full.frames_left_out)
    for j, k in enumerate(ok):
        a = float(share[len(alignment.fused) + j])
        views[k]["render_agreement"] = round(a, 4) if math.isfinite(a) else None
        if n + k in left_whole:  # the renderer left it out whole: it fills nothing
            views[k]["status"], views[k]["reason"] = (
                Status.FAILED,
                f"render_agreement {a:.3f} < {whole_frame_threshold(render)}",
            )
        planned = fill[picks[k][0]].reshape(h, w)
        views[k]["filled_px"] = int((planned & filled).sum()) if views[k]["status"] == Status.OK else 0
    record["filled_px"] = int(filled.sum())
    m = filled[None, None]
    c, f = core.gt, full.gt
    merged = core._replace(
        gt=c._replace(
            depth=torch.where(m, f.depth, c.depth),
            weight_sum=torch.where(m, f.weight_sum, c.weight_sum),
            count=torch.where(m, f.count, c.count),
            sigma=torch.where(m, f.sigma, c.sigma),
        )
    )
    stats: dict[str, Any] = {}
    lto = full.left_out_depth()
    if lto is not None:
        depth_in = full.on_lto_grid(data.depth_m[0, 0].cpu().numpy().astype(np.float32))
        stats["leave_target_out_all_views"] = depth_errors(lto, depth_in)
        # where the core's neighbours alone left the target empty: the added views' own check
        core_lto = core.left_out_depth()
        core_empty = core_lto <= 0 if core_lto is not None else np.ones_like(lto, dtype=bool)
        stats["leave_target_out_added"] = depth_errors(lto, depth_in, mask=core_empty)
    poses = {offsets[1 + k]: T_added[k].detach().cpu().numpy().tolist() for k in ok if views[k]["status"] == Status.OK}
    return CoverageResult(merged, record, stats, poses, full)
