"""One frame set: load -> align -> render GT -> quality -> patches -> write.

:func:`process_frameset` reads like the algorithm; each step is a small function that
the tests call on their own. Outputs (docs/output-layout.md, every path given by the caller
in :class:`FrameSetOutputs`) are written atomically (:func:`depthgt.atomic.write_atomic`)
so that a killed job leaves no half file.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
import torch

from depthgt import geometry, io, registration
from depthgt.atomic import save_npz, write_atomic
from depthgt.device import resolve_device
from depthgt.gt import store
from depthgt.gt.patches import make_patches, patch_record
from depthgt.gt.planning import coverage_candidates, stable_seed
from depthgt.gt.render import GTRender, cloud_in_target, composite_gt, rasterise_gt
from depthgt.metric_vocabulary import METRIC_UNITS, depth_errors
from depthgt.noise_law import depth_sigma_m, noise_sigma_1m_from, second_difference_residuals
from depthgt.registration.frameset import FrameSetData, poses_from_source
from depthgt.settings import STAGES, RegistrationSettings, RenderSettings, Settings
from depthgt.sources.base import Scene, check_frame
from depthgt.status import Status

if TYPE_CHECKING:  # depthgt.gt.coverage imports this module
    from depthgt.gt.coverage import CoverageResult

__all__ = [
    "FrameSetData",
    "FrameSetOutputs",
    "Alignment",
    "load_frameset",
    "poses_from_source",
    "align",
    "photometric_for",
    "fuse",
    "quality_statistics",
    "FrameSetId",
    "StoredImages",
    "process_frameset",
    "render_target",
    "cover",
    "stored_images",
    "frameset_statistics",
    "draw_patches",
    "write_images",
    "poses_record",
    "frameset_record",
]

log = logging.getLogger(__name__)


class FrameSetOutputs(NamedTuple):
    """The files of one frame set (docs/output-layout.md)."""

    gt: Path
    input: Path
    rgb: Path
    poses: Path
    patches: Path
    meta: Path

    @classmethod
    def in_dir(cls, out_dir: str | Path) -> FrameSetOutputs:
        """The standard names (``gt.exr`` ... ``frameset.json``) in ``out_dir``."""
        d = Path(out_dir)
        return cls(
            d / "gt.exr", d / "input.exr", d / "rgb.webp", d / "poses.json", d / "patches.npz", d / "frameset.json"
        )


OUTPUT_FILES = tuple(p.name for p in FrameSetOutputs.in_dir("."))


def load_frameset(
    scene: Scene, members: list[int], size_hw: tuple[int, int], need_poses: bool, device: torch.device
) -> FrameSetData:
    """Read the member frames of any :class:`~depthgt.sources.base.Scene` and bring them
    to ``size_hw`` (depth nearest/valid-aware, colour area-averaged, intrinsics scaled).

    A scene whose frames already have the working size (a
    :class:`depthgt.gt.cache.ResizedScene`) is not resized again; it tells the size of
    the images it was resized from by ``source_size``.

    Raises:
        FrameError: a member frame is unusable (the batch job checks the members
            before it builds a frame set, and records such a set as skipped).
    """
    frames = []
    for m in members:
        where = f"{scene.name} frame {scene.frame_id(m)}"
        frames.append(check_frame(scene.read(m), scene.image_size, where, need_pose=need_poses))
    size_hw = (int(size_hw[0]), int(size_hw[1]))
    same = tuple(scene.image_size) == size_hw

    def depth_at_size(arrays: list[np.ndarray]) -> torch.Tensor:
        d = torch.from_numpy(np.stack(arrays))[:, None].to(device)
        return d if same else geometry.resize_depth_nearest(d, size_hw)

    rgb = torch.from_numpy(np.stack([f.rgb for f in frames])).permute(0, 3, 1, 2).to(device).float() / 255.0
    truth = None
    if all(f.clean_depth_m is not None for f in frames):
        truth = depth_at_size([f.clean_depth_m for f in frames])
    poses = None
    if all(f.T_world_cam is not None for f in frames) and all(np.isfinite(f.T_world_cam).all() for f in frames):
        poses = torch.from_numpy(np.stack([f.T_world_cam for f in frames])).to(device)
    K = np.asarray(scene.intrinsics, dtype=np.float64)
    if not same:
        K = geometry.scale_intrinsics(K, scene.image_size, size_hw)
    return FrameSetData(
        rgb=rgb if same else geometry.resize_rgb(rgb, size_hw),
        depth_m=depth_at_size([f.depth_m for f in frames]),
        K=torch.as_tensor(K, device=device),
        T_world_cam=poses,
        truth_m=truth,
        frame_ids=[scene.frame_id(m) for m in members],
        src_hw=tuple(getattr(scene, "source_size", scene.image_size)),
        colour_matches_depth=bool(getattr(scene, "colour_matches_depth", True)),  # test doubles may not say
    )


@dataclass
class Alignment:
    """The neighbours' poses in the target camera and what enters the GT.

    Attributes:
        T_j_to_t: (F-1, 4, 4) float64.
        fused: positions of the members rendered into the GT (0 = the target).
        status, reason: "ok" | "failed" and why.
        info: the registration record written to poses.json.
        normals: (F, 3, H, W) the members' normals as the registration's refinement
            computed them (the renderer's own, reused), or None.
    """

    T_j_to_t: torch.Tensor
    fused: list[int]
    status: str = Status.OK
    reason: str = ""
    info: dict | None = None
    normals: torch.Tensor | None = None


def align(
    data: FrameSetData, offsets: list[int], settings: RegistrationSettings, seed: int, encoder_state: dict | None = None
) -> Alignment:
    """Poses of the neighbours in the target camera by the method ``settings.method``
    names in :data:`depthgt.registration.METHODS` (the source's, the source's refined
    on the set, or the overfit registration's), with the photometric rule of
    :func:`photometric_for`. A neighbour that did not register never enters the GT;
    with ``on_failure: exclude`` the set fails.

    Args:
        offsets: frame offsets of the members, ``offsets[0] == 0``.
        seed: seed of the registration (initialisation, candidates, subsets).
    """
    settings = photometric_for(settings, data.colour_matches_depth)
    register = registration.METHODS[settings.method]  # looked up at call time so tests can replace it
    result = register(data, offsets, settings, seed=seed, encoder_state=encoder_state)
    T_j_to_t = torch.as_tensor(result.T_j_to_t, dtype=torch.float64, device=data.depth_m.device)
    status, reason = result.status, result.reason
    failed = [o for o, st in zip(offsets[1:], result.neighbour_status) if st != Status.OK]
    if failed and status == Status.OK and settings.on_failure == "exclude":
        status, reason = Status.FAILED, f"neighbours_not_registered(offsets {','.join(f'{o:+d}' for o in failed)})"
    fused = [0] + [i + 1 for i, st in enumerate(result.neighbour_status) if st == Status.OK]
    info: dict[str, Any] = {"method": settings.method}
    if result.estimated:
        info["photometric_weight"] = settings.refine_settings.photo_weight
        info.update(result.to_dict())
        info["fused_offsets"] = [offsets[i] for i in fused]
    return Alignment(T_j_to_t, fused, status, reason, info, result.normals)


def photometric_for(settings: RegistrationSettings, colour_matches_depth: bool) -> RegistrationSettings:
    """The registration settings with the refinement's photometric term off where
    ``registration.photometric`` says so: ``off``, or ``auto`` on a source whose colour
    is not the depth's camera at the depth's instant (on the TUM tuning frames the term
    biased the refined poses: residuals in units of the noise, median 1.33 with it and
    0.99 without, docs/decisions.md "The photometric term")."""
    if settings.photometric == "on" or (settings.photometric == "auto" and colour_matches_depth):
        return settings
    return replace(settings, refine_settings=replace(settings.refine_settings, photo_weight=0.0))


def fuse(
    data: FrameSetData,
    T_j_to_t: torch.Tensor,
    settings: RenderSettings,
    depth_m: torch.Tensor | None = None,
    members: slice | list[int] = slice(None),
    leave_target_out: bool = False,
    normals: torch.Tensor | None = None,
) -> GTRender:
    """Render the aligned members into the target view (paper eq. 5).

    Args:
        T_j_to_t: (F-1, 4, 4) poses of the neighbours (the target's is the identity).
        depth_m: (F, 1, H, W) depth to fuse (default: the raw depth of the members).
        members: which members to use (``slice(1, None)`` leaves the target out; a
            list of positions, 0 = the target, keeps those).
        leave_target_out: with the target among the members and neighbours beside it,
            also render the neighbours alone into ``left_out`` (the leave-target-out
            check of :func:`quality_statistics`): the same result as fusing
            ``members`` without the target (at the pixels of every
            ``settings.leave_target_out_stride``-th row and column), sharing the clouds,
            the projection and the sort with the GT render.
        normals: (F, 3, H, W) kornia's ``depth_to_normals`` of all F members' raw depth
            when the caller has them (``Alignment.normals``); used when every member is
            fused (a batch of other frames rounds the convolution differently, which
            the normalisation can amplify where the gradients vanish), for the raw
            depth (no ``depth_m``) and when they match it in shape and dtype.
    """
    depth = (data.depth_m if depth_m is None else depth_m)[members]
    n_all = data.depth_m.shape[0]
    chosen = list(range(n_all))[members] if isinstance(members, slice) else list(members)
    if normals is not None and (
        depth_m is not None
        or chosen != list(range(n_all))
        or normals.shape != (n_all, 3, *data.depth_m.shape[-2:])
        or normals.dtype != depth.dtype
        or normals.device != depth.device
    ):
        normals = None
    eye = torch.eye(4, dtype=T_j_to_t.dtype, device=T_j_to_t.device)[None]
    T = torch.cat([eye, T_j_to_t], dim=0)[members]
    K = data.K[None].expand(depth.shape[0], 3, 3)
    residuals = second_difference_residuals(depth, data.src_hw)  # the noise estimates and the normals' edge test
    cloud = cloud_in_target(
        depth,
        K,
        T,
        src_hw=data.src_hw,
        noise_sigma_1m=settings.noise_sigma_1m,
        noise_sigma_abs_m=settings.noise_sigma_abs_m,
        residuals=residuals,
        normals=normals,
    )
    h, w = data.depth_m.shape[-2:]
    with_target = bool(chosen) and chosen[0] == 0  # the target's own depth is fused, as frame 0 of the cloud
    cands = rasterise_gt(
        cloud.points,
        data.K[None].to(depth.dtype),
        (h, w),
        settings,
        valid=cloud.valid,
        normals_cam=cloud.normals,
        sigma_m=cloud.sigma_m,
        frame=cloud.frame,
        src_hw=data.src_hw,
    )
    gt = composite_gt(cands, settings, target_frame=0 if with_target else None)
    if not (with_target and leave_target_out and len(chosen) > 1):
        return gt
    lo_sigma = None
    if settings.noise_sigma_1m is None:
        # the noise law as fusing the neighbours alone estimates it (without the target's depth)
        sigma_1m = noise_sigma_1m_from(residuals, frames=slice(1, None))
        lo_sigma = torch.cat(
            [torch.zeros_like(depth[:1]), depth_sigma_m(depth[1:], sigma_1m, settings.noise_sigma_abs_m)]
        )
        lo_sigma = lo_sigma.reshape(1, -1).to(cloud.sigma_m.dtype)
    # the leave-target-out render: the same compositor over the same candidates minus the target's
    neighbours = cands.without_frame(0, stride=settings.leave_target_out_stride, sigma_m=lo_sigma)
    return gt._replace(left_out=composite_gt(neighbours, settings, with_sigma=False))


def quality_statistics(
    data: FrameSetData,
    alignment: Alignment,
    gt_m: np.ndarray,
    settings: RenderSettings,
    left_out: GTRender | None = None,
) -> dict:
    """Depth errors of the GT (:func:`depthgt.metric_vocabulary.depth_errors`).

    With a clean truth: ``gt_vs_truth``, ``input_vs_truth`` and
    ``gt_vs_truth_input_valid`` (the fair accuracy comparison: only where the sensor has
    data). Without: ``leave_target_out``, the neighbours fused alone against the target's
    raw valid depth -- the only accuracy check possible on real data (``left_out``: that
    render when :func:`fuse` made it beside the GT, else it is rendered here).
    """
    depth_in = data.depth_m[0, 0].cpu().numpy().astype(np.float32)
    stats: dict[str, Any] = {}
    if data.truth_m is None:
        fused = alignment.fused
        if len(fused) > 1:
            if left_out is None:
                left_out = fuse(data, alignment.T_j_to_t, settings, members=fused[1:])
            lto = left_out.depth[0, 0].detach().cpu().numpy()
            k = settings.leave_target_out_stride  # fuse(leave_target_out=True) rendered these pixels only
            stats["leave_target_out"] = depth_errors(lto[::k, ::k].astype(np.float32), depth_in[::k, ::k])
    else:
        truth = data.truth_m[0, 0].cpu().numpy().astype(np.float32)
        stats["gt_vs_truth"] = depth_errors(gt_m, truth)
        stats["input_vs_truth"] = depth_errors(depth_in, truth)
        stats["gt_vs_truth_input_valid"] = depth_errors(gt_m, truth, mask=depth_in > 0)
    return stats


class FrameSetId(NamedTuple):
    """Which frame set is built: its dataset (source name), scene, target position,
    member positions (target first) and split tag."""

    dataset: str
    scene: str
    target: int
    members: list[int]
    split: str

    @property
    def offsets(self) -> list[int]:
        """The members' frame offsets from the target (``offsets[0] == 0``)."""
        return [m - self.target for m in self.members]


class StoredImages(NamedTuple):
    """The target's images as the shard stores them (fixed point,
    :data:`depthgt.gt.store.GT_UNITS`): the statistics and the patches are those of what
    every reader gets.

    Attributes:
        gt: gt.exr's channels, (H, W) float32 each: ``Z`` depth (m, 0 = none), ``S``
            sigma (m), ``N`` points, ``W`` weight sum.
        depth_in: (H, W) float32 the target's raw depth (m, 0 = invalid).
        truth: (H, W) float32 its clean depth (m), or None.
        rgb8: (H, W, 3) uint8 its colour.
    """

    gt: dict[str, np.ndarray]
    depth_in: np.ndarray
    truth: np.ndarray | None
    rgb8: np.ndarray


class _StepClock:
    """Wall and process CPU seconds (all threads) of each named step, in the order the
    steps ran (poses.json's ``timings_s`` and ``cpu_s``)."""

    def __init__(self) -> None:
        self.wall_s: dict[str, float] = {}
        self.cpu_s: dict[str, float] = {}
        self._wall, self._cpu = time.perf_counter(), time.process_time()

    def lap(self, name: str) -> None:
        wall, cpu = time.perf_counter(), time.process_time()
        self.wall_s[name], self.cpu_s[name] = round(wall - self._wall, 4), round(cpu - self._cpu, 4)
        self._wall, self._cpu = wall, cpu


def process_frameset(
    scene: Scene,
    dataset: str,
    target: int,
    members: list[int],
    split: str,
    out: FrameSetOutputs,
    settings: Settings,
    encoder_state: dict | None = None,
    candidates: list[int] | None = None,
) -> dict[str, Any]:
    """Build every output of one frame set and return frameset.json's content: read,
    align, render (with the coverage views when selected), statistics, patches, write.

    Args:
        scene: the scene (:class:`~depthgt.gt.cache.ResizedScene` in the
            workflow, or a source scene; frames are resized when needed).
        members: frame positions, target first.
        out: the output paths (:class:`FrameSetOutputs`).
        settings: :class:`~depthgt.settings.Settings` (frame set, render, registration,
            patches, seed, device, resize).
        encoder_state: pretrained registration encoder weights, or None.
        candidates: with ``frameset.selection: coverage``, the frames the views added
            for coverage may come from (the batch job's
            :func:`~depthgt.gt.planning.coverage_candidates`); None: every frame within
            ``coverage_span`` (the scene in one split).
    """
    fid = FrameSetId(dataset, scene.name, target, list(members), split)
    out = FrameSetOutputs(*(Path(p) for p in out))
    clock = _StepClock()
    reg = settings.registration
    device = resolve_device(settings.device)
    data = load_frameset(scene, fid.members, settings.size_hw, need_poses=reg.uses_source_poses, device=device)
    clock.lap("load_resize")
    alignment = align(data, fid.offsets, reg, stable_seed(settings.seed, dataset, scene.name, target), encoder_state)
    clock.lap("align")
    gt = render_target(data, alignment, settings.render)
    clock.lap("render")
    coverage = None
    if settings.frameset.selection == "coverage":
        coverage = cover(scene, fid, data, alignment, gt, settings, candidates=candidates)
        gt = coverage.render  # the core's GT where it has one, the added views' only where it has none
        clock.lap("coverage")
    images = stored_images(data, gt, out)
    stats = frameset_statistics(data, alignment, gt, images, fid.offsets, settings.render)
    if coverage is not None:
        stats.update(coverage.statistics)
    clock.lap("quality")
    patches = draw_patches(images, fid, settings)
    stats["patches_drawn"] = int(len(patches["kept"]))
    stats["patches_kept"] = int(patches["kept"].sum())
    clock.lap("patches")
    write_images(out, images, patch_record(patches, settings.patches.max_gt_sigma_m))
    poses_doc = poses_record(data, alignment, fid.offsets, coverage)
    clock.lap("write")
    write_atomic(out.poses, io.write_json, {**poses_doc, "timings_s": clock.wall_s, "cpu_s": clock.cpu_s})
    doc = frameset_record(fid, data, alignment, stats, settings, coverage)
    write_atomic(out.meta, io.write_json, doc)
    return doc


def render_target(data: FrameSetData, alignment: Alignment, settings: RenderSettings) -> GTRender:
    """The GT of the target from the members the alignment fused (:func:`fuse`); without
    a clean truth also the leave-target-out render that :func:`quality_statistics`
    checks the GT with (real data)."""
    fused = alignment.fused
    return fuse(
        data,
        alignment.T_j_to_t,
        settings,
        members=fused if len(fused) < data.depth_m.shape[0] else slice(None),
        leave_target_out=data.truth_m is None,
        normals=alignment.normals,
    )


def cover(
    scene: Scene,
    fid: FrameSetId,
    data: FrameSetData,
    alignment: Alignment,
    gt: GTRender,
    settings: Settings,
    candidates: list[int] | None = None,
) -> CoverageResult:
    """The GT with views added where ``gt`` (the core's) has none
    (:func:`depthgt.gt.coverage.add_coverage_views`, ``frameset.selection: coverage``).

    Args:
        candidates: the frames the added views may come from; None: every frame of the
            scene within ``frameset.coverage_span`` (the scene in one split).
    """
    # depthgt.gt.coverage builds on this module (load_frameset, fuse): imported here, where it is used
    from depthgt.gt.coverage import add_coverage_views

    if candidates is None:
        splits = np.full(len(scene), fid.split, dtype=object)
        candidates = coverage_candidates(splits, fid.target, fid.members, settings.frameset)
    return add_coverage_views(
        scene,
        fid.target,
        list(candidates),
        data,
        alignment,
        gt,
        settings.frameset,
        settings.registration,
        settings.render,
        core_offsets=fid.offsets,
    )


def stored_images(data: FrameSetData, gt: GTRender, out: FrameSetOutputs) -> StoredImages:
    """The target's GT, raw depth, truth and colour as the shard stores them
    (:func:`depthgt.gt.store.stored_gt`, :func:`depthgt.gt.store.stored_input`)."""
    channels = {
        "Z": gt.depth[0, 0].detach().cpu().numpy().astype(np.float32),
        "S": gt.sigma[0, 0].detach().cpu().numpy().astype(np.float32),
    }
    gt_images = store.stored_gt(channels, str(out.gt))
    depth_in = data.depth_m[0, 0].cpu().numpy().astype(np.float32)
    truth = data.truth_m[0, 0].cpu().numpy().astype(np.float32) if data.truth_m is not None else None
    depth_in, truth = store.stored_input(depth_in, truth, str(out.input))
    rgb8 = (data.rgb[0].permute(1, 2, 0).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
    return StoredImages(gt_images, depth_in, truth, rgb8)


def frameset_statistics(
    data: FrameSetData,
    alignment: Alignment,
    gt: GTRender,
    images: StoredImages,
    offsets: list[int],
    settings: RenderSettings,
) -> dict[str, Any]:
    """frameset.json's ``statistics`` of the render (missing shares, points and sigma of
    the stored GT, the neighbours fused, the renderer's agreement per neighbour) and of
    its accuracy (:func:`quality_statistics`)."""
    gt_depth, gt_sigma = images.gt["Z"], images.gt["S"]
    stats: dict[str, Any] = {
        "input_missing": float((images.depth_in <= 0).mean()),
        "gt_missing": float((gt_depth <= 0).mean()),
        "gt_mean_points": float(gt.count[0, 0].cpu().numpy().astype(np.float32).mean()),
        "gt_median_sigma_m": float(np.median(gt_sigma[gt_depth > 0])) if (gt_depth > 0).any() else float("nan"),
        "neighbours_fused": len(alignment.fused) - 1,
    }
    # neighbours the renderer left out: too few of their samples agree with the target's depth
    offsets_fused = [offsets[i] for i in alignment.fused]
    share = gt.agreement[0].cpu().numpy()
    stats["render_agreement"] = {f"{o:+d}": round(float(a), 4) for o, a in zip(offsets_fused, share) if np.isfinite(a)}
    # with tiles a frame is left out whole only below min_whole_frame_agreement
    whole = settings.min_whole_frame_agreement if settings.agreement_tile_px > 0 else settings.min_frame_agreement
    stats["render_left_out"] = [o for o, a in zip(offsets_fused, share) if np.isfinite(a) and a < whole and o != 0]
    if gt.disagreement is not None and float(gt.disagreement[0, 0].sum()) > 0:
        # share of the neighbours' compared samples that the agreement check kept
        stats["render_kept_share"] = round(float(gt.disagreement[0, 2].sum() / gt.disagreement[0, 0].sum()), 4)
    stats.update(quality_statistics(data, alignment, gt_depth, settings, left_out=gt.left_out))
    return stats


def draw_patches(images: StoredImages, fid: FrameSetId, settings: Settings) -> dict[str, np.ndarray]:
    """The patch crops of the stored images (:func:`depthgt.gt.patches.make_patches`),
    drawn with the frame set's own seed (the same crops whatever else the job builds)."""
    rng = np.random.default_rng(stable_seed(settings.seed, fid.dataset, fid.scene, fid.target, "patches"))
    return make_patches(
        images.depth_in,
        images.gt["Z"],
        images.rgb8,
        settings.patches,
        rng,
        truth_m=images.truth,
        gt_sigma_m=images.gt["S"],
    )


def write_images(out: FrameSetOutputs, images: StoredImages, patches: dict[str, np.ndarray]) -> None:
    """Write gt.exr, input.exr, rgb.webp and patches.npz (``patches``: the record of
    :func:`depthgt.gt.patches.patch_record`), each atomically."""
    write_atomic(out.gt, store.write_gt_exr, images.gt)
    write_atomic(out.input, store.write_input_exr, images.depth_in, images.truth)
    write_atomic(out.rgb, io.write_rgb_webp, images.rgb8)
    write_atomic(out.patches, save_npz, patches)


def poses_record(
    data: FrameSetData, alignment: Alignment, offsets: list[int], coverage: CoverageResult | None = None
) -> dict[str, Any]:
    """poses.json's content but the timings: the neighbours' poses keyed by offset, the
    registration's record, the source's poses when it has them, the added views'."""
    T_np = alignment.T_j_to_t.detach().cpu().numpy().astype(np.float64)
    doc: dict[str, Any] = {
        "T_j_to_t": {str(o): T_np[i].tolist() for i, o in enumerate(offsets[1:])},
        "registration": alignment.info,
    }
    if data.T_world_cam is not None:
        ref = poses_from_source(data).cpu().numpy()
        doc["T_j_to_t_reference"] = {str(o): ref[i].tolist() for i, o in enumerate(offsets[1:])}
    if coverage is not None:
        doc["coverage_T_j_to_t"] = {str(o): T for o, T in coverage.T_j_to_t.items()}
    return doc


def frameset_record(
    fid: FrameSetId,
    data: FrameSetData,
    alignment: Alignment,
    stats: dict,
    settings: Settings,
    coverage: CoverageResult | None = None,
) -> dict[str, Any]:
    """frameset.json's content: the frame set, its status, statistics with their units
    and the settings that decide it (the sections of :data:`depthgt.settings.STAGES`
    ``frameset``, less ``frameset.batch_size``: how jobs are cut, not what a frame set is)."""
    doc = {
        "format_version": store.FORMAT_VERSION,
        "dataset": fid.dataset,
        "scene": fid.scene,
        "target": fid.target,
        "members": fid.members,
        "offsets": fid.offsets,
        "frame_ids": data.frame_ids,
        "split": fid.split,
        "status": alignment.status,
        "reason": alignment.reason,
        "K": data.K.cpu().numpy().tolist(),
        "size_hw": list(settings.size_hw),
        "statistics": stats,
        "units": _units(stats),
        "settings": settings.doc(*STAGES["frameset"].top),
    }
    if coverage is not None:
        doc["coverage"] = coverage.record
    doc["settings"]["frameset"].pop("batch_size", None)
    return doc


def _units(stats: dict) -> dict[str, str]:
    """Unit of every statistic (nested error dicts share their metrics' units; a dict
    keyed by frame offset, such as ``render_agreement``, has its own unit)."""
    names = set()
    for key, value in stats.items():
        names.update(value if isinstance(value, dict) and key not in METRIC_UNITS else [key])
    return {k: METRIC_UNITS[k] for k in sorted(names)}
