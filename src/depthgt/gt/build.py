"""One frame set: load -> align -> render GT -> quality -> patches -> write.

:func:`process_frameset` reads like the algorithm; each step is a small function that
the tests call on their own. Outputs (docs/output-layout.md, every path given by the caller
in :class:`FrameSetOutputs`) are written atomically (:func:`depthgt.atomic.write_atomic`)
so that a killed job leaves no half file.
"""

from __future__ import annotations

import logging
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from depthgt import io
from depthgt.atomic import save_npz, write_atomic
from depthgt.device import resolve_device
from depthgt.framecache import FrameCache
from depthgt.gt import store
from depthgt.gt.coverage import CoverageResult, add_coverage_views
from depthgt.gt.patches import make_patches, patch_record
from depthgt.gt.planning import coverage_candidates, stable_seed
from depthgt.gt.render import Fusion, fuse
from depthgt.gt.render.fusion import fuse_sets, set_geometry
from depthgt.gt.render.settings import RenderSettings
from depthgt.metric_vocabulary import METRIC_UNITS, depth_errors
from depthgt.registration import Alignment, FrameSetData, align, align_many, load_frameset, poses_from_source
from depthgt.settings import STAGES, Settings
from depthgt.sources.base import Scene

__all__ = [
    "FrameSetOutputs",
    "quality_statistics",
    "FrameSetId",
    "StoredImages",
    "process_frameset",
    "process_framesets",
    "render_targets",
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

#: threads that finish a group of frame sets side by side on a GPU (statistics, patches, files)
FINISH_WORKERS = 8


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


def quality_statistics(
    data: FrameSetData,
    alignment: Alignment,
    gt_m: np.ndarray,
    settings: RenderSettings,
    fusion: Fusion | None = None,
) -> dict:
    """Depth errors of the GT (:func:`depthgt.metric_vocabulary.depth_errors`).

    With a clean truth: ``gt_vs_truth``, ``input_vs_truth`` and
    ``gt_vs_truth_input_valid`` (the fair accuracy comparison: only where the sensor has
    data). Without: ``leave_target_out``, the neighbours fused alone against the target's
    raw valid depth -- the only accuracy check possible on real data -- at the pixels
    where ``fusion`` (:func:`depthgt.gt.render.fuse` with ``leave_target_out``) rendered
    it; without that render it is rendered here.
    """
    depth_in = data.depth_m[0, 0].cpu().numpy().astype(np.float32)
    stats: dict[str, Any] = {}
    if data.truth_m is None:
        fused = alignment.fused
        if len(fused) > 1:
            if fusion is None or fusion.left_out is None:
                alone = fuse(data, alignment.T_j_to_t, settings, members=fused[1:])
                fusion = Fusion(alone.gt, alone.members, (), alone.gt, settings.leave_target_out_stride)
            stats["leave_target_out"] = depth_errors(fusion.left_out_depth(), fusion.on_lto_grid(depth_in))
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

    def add(self, name: str, shared: _StepClock, n: int) -> None:
        """Step ``name`` of ``shared`` (a step done for ``n`` frame sets at once), this
        set's even share; the clock restarts now."""
        self.wall_s[name] = round(shared.wall_s[name] / n, 4)
        self.cpu_s[name] = round(shared.cpu_s[name] / n, 4)
        self._wall, self._cpu = time.perf_counter(), time.process_time()


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
    cache: FrameCache | None = None,
) -> dict[str, Any]:
    """Build every output of one frame set and return frameset.json's content: read,
    align, render (with the coverage views when selected), statistics, patches, write
    (:func:`process_framesets` of one).

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
        cache: the batch job's per-frame results (:class:`~depthgt.framecache.FrameCache`:
            the registration's pyramid, the renderer's geometry), or None.
    """
    fid = FrameSetId(dataset, scene.name, target, list(members), split)
    return process_framesets(scene, [fid], [out], settings, encoder_state, [candidates], cache)[0]


def process_framesets(
    scene: Scene,
    fids: list[FrameSetId],
    outs: list[FrameSetOutputs],
    settings: Settings,
    encoder_state: dict | None = None,
    candidates: list[list[int] | None] | None = None,
    cache: FrameCache | None = None,
) -> list[dict[str, Any]]:
    """Build the frame sets ``fids`` of one scene (outputs ``outs``, coverage candidates
    ``candidates`` per set; the rest as :func:`process_frameset`) and return their
    frameset.json contents. Each set is read and aligned on its own; their GTs are
    rendered together (:func:`render_targets`: in one pass on a GPU); then each set's
    coverage views, statistics, patches and files (on a GPU by :data:`FINISH_WORKERS`
    threads side by side). Every step's time is recorded per set in its poses.json (a
    shared render's time split evenly; the CPU seconds of steps done by threads side by
    side count every thread's)."""
    reg = settings.registration
    device = resolve_device(settings.device)
    candidates = candidates or [None] * len(fids)
    clocks = [_StepClock() for _ in fids]
    datas = []
    for fid, clock in zip(fids, clocks):
        datas.append(
            load_frameset(
                scene, fid.members, settings.size_hw, need_poses=reg.uses_source_poses, device=device, cache=cache
            )
        )
        clock.lap("load_resize")
    seeds = [stable_seed(settings.seed, fid.dataset, scene.name, fid.target) for fid in fids]
    together = _StepClock()
    if len(fids) == 1 or len({tuple(f.offsets) for f in fids}) > 1:
        alignments = [align(d, f.offsets, reg, s_, encoder_state) for d, f, s_ in zip(datas, fids, seeds)]
    else:
        alignments = align_many(datas, fids[0].offsets, reg, seeds, encoder_state)
    together.lap("align")
    for clock in clocks:
        clock.add("align", together, len(fids))
    shared = _StepClock()
    fusions = render_targets(datas, alignments, settings.render)
    shared.lap("render")
    for clock in clocks:
        clock.add("render", shared, len(fids))

    def finish(k: int) -> dict[str, Any]:
        out = FrameSetOutputs(*(Path(p) for p in outs[k]))
        return _finish_frameset(
            scene, fids[k], out, datas[k], alignments[k], fusions[k], settings, candidates[k], clocks[k]
        )

    # On a GPU the sets' statistics, patches and files (CPU work: EXR and WebP encoding,
    # most of it outside the GIL) are made by a few threads side by side, so the device
    # does not wait on them; with coverage the views are read through the scene's frame
    # cache, which is not shared between threads.
    workers = 1
    if device.type == "cuda" and settings.frameset.selection != "coverage":
        workers = min(FINISH_WORKERS, len(fids), os.cpu_count() or 1)
    if workers <= 1:
        return [finish(k) for k in range(len(fids))]
    with ThreadPoolExecutor(workers) as pool:
        return list(pool.map(finish, range(len(fids))))


def _finish_frameset(
    scene: Scene,
    fid: FrameSetId,
    out: FrameSetOutputs,
    data: FrameSetData,
    alignment: Alignment,
    fusion: Fusion,
    settings: Settings,
    candidates: list[int] | None,
    clock: _StepClock,
) -> dict[str, Any]:
    """A rendered frame set's coverage views (when selected), statistics, patches and files."""
    coverage = None
    if settings.frameset.selection == "coverage":
        coverage = cover(scene, fid, data, alignment, fusion, settings, candidates=candidates)
        fusion = coverage.render  # the core's GT where it has one, the added views' only where it has none
        clock.lap("coverage")
    images = stored_images(data, fusion, out)
    stats = frameset_statistics(data, alignment, fusion, images, fid.offsets, settings.render)
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


def render_targets(
    datas: list[FrameSetData],
    alignments: list[Alignment],
    settings: RenderSettings,
    together: bool | None = None,
) -> list[Fusion]:
    """:func:`render_target` of each frame set; the sets with their target fused rendered
    together (:func:`depthgt.gt.render.fusion.fuse_sets`, one pass) when they come from
    one camera at one size and ``together`` (default: on a GPU; the CPU renders set by
    set)."""
    if together is None:
        together = datas[0].depth_m.device.type != "cpu"
    if len(datas) == 1 or not together:
        return [render_target(d, a, settings) for d, a in zip(datas, alignments)]
    first = datas[0]
    same = all(
        d.src_hw == first.src_hw and d.depth_m.shape[1:] == first.depth_m.shape[1:] and torch.equal(d.K, first.K)
        for d in datas
    )
    if not same or any(a.fused[0] != 0 for a in alignments) or len({d.truth_m is None for d in datas}) > 1:
        return [render_target(d, a, settings) for d, a in zip(datas, alignments)]
    sets = [set_geometry(d, a.T_j_to_t, _members(d, a), normals=a.normals) for d, a in zip(datas, alignments)]
    # the leave-target-out render for real data only (as render_target does): the group's
    # sets all have a clean truth or none (checked above)
    return fuse_sets(
        sets,
        first.K,
        tuple(first.depth_m.shape[-2:]),
        settings,
        src_hw=first.src_hw,
        leave_target_out=first.truth_m is None,
        together=True,
    )


def render_target(data: FrameSetData, alignment: Alignment, settings: RenderSettings) -> Fusion:
    """The GT of the target from the members the alignment fused
    (:func:`depthgt.gt.render.fuse`); without a clean truth also the leave-target-out
    render that :func:`quality_statistics` checks the GT with (real data)."""
    return fuse(
        data,
        alignment.T_j_to_t,
        settings,
        members=_members(data, alignment),
        leave_target_out=data.truth_m is None,
        normals=alignment.normals,
    )


def _members(data: FrameSetData, alignment: Alignment) -> list[int] | slice:
    """The members the alignment fused (every one: all of them)."""
    fused = alignment.fused
    return fused if len(fused) < data.depth_m.shape[0] else slice(None)


def cover(
    scene: Scene,
    fid: FrameSetId,
    data: FrameSetData,
    alignment: Alignment,
    core: Fusion,
    settings: Settings,
    candidates: list[int] | None = None,
) -> CoverageResult:
    """The GT with views added where ``core`` (the core's render) has none
    (:func:`depthgt.gt.coverage.add_coverage_views`, ``frameset.selection: coverage``).

    Args:
        candidates: the frames the added views may come from; None: every frame of the
            scene within ``frameset.coverage_span`` (the scene in one split).
    """
    if candidates is None:
        splits = np.full(len(scene), fid.split, dtype=object)
        candidates = coverage_candidates(splits, fid.target, fid.members, settings.frameset)
    return add_coverage_views(
        scene,
        fid.target,
        list(candidates),
        data,
        alignment,
        core,
        settings.frameset,
        settings.registration,
        settings.render,
        core_offsets=fid.offsets,
    )


def stored_images(data: FrameSetData, fusion: Fusion, out: FrameSetOutputs) -> StoredImages:
    """The target's GT (``fusion.gt``), raw depth, truth and colour as the shard stores
    them (:func:`depthgt.gt.store.stored_gt`, :func:`depthgt.gt.store.stored_input`)."""
    gt = fusion.gt
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
    fusion: Fusion,
    images: StoredImages,
    offsets: list[int],
    settings: RenderSettings,
) -> dict[str, Any]:
    """frameset.json's ``statistics`` of the render (missing shares, points and sigma of
    the stored GT, the neighbours fused, the renderer's agreement per neighbour) and of
    its accuracy (:func:`quality_statistics`)."""
    gt_depth, gt_sigma = images.gt["Z"], images.gt["S"]
    gt = fusion.gt
    stats: dict[str, Any] = {
        "input_missing": float((images.depth_in <= 0).mean()),
        "gt_missing": float((gt_depth <= 0).mean()),
        "gt_mean_points": float(gt.count[0, 0].cpu().numpy().astype(np.float32).mean()),
        "gt_median_sigma_m": float(np.median(gt_sigma[gt_depth > 0])) if (gt_depth > 0).any() else float("nan"),
        "neighbours_fused": len(alignment.fused) - 1,
    }
    # the renderer's agreement of each fused member with the target's depth, and the
    # neighbours it left out whole
    offsets_fused = [offsets[i] for i in fusion.members]
    share = gt.agreement[0].cpu().numpy()
    stats["render_agreement"] = {f"{o:+d}": round(float(a), 4) for o, a in zip(offsets_fused, share) if np.isfinite(a)}
    stats["render_left_out"] = [offsets[i] for i in fusion.frames_left_out]
    if gt.disagreement is not None and float(gt.disagreement[0, 0].sum()) > 0:
        # share of the neighbours' compared samples that the agreement check kept
        stats["render_kept_share"] = round(float(gt.disagreement[0, 2].sum() / gt.disagreement[0, 0].sum()), 4)
    stats.update(quality_statistics(data, alignment, gt_depth, settings, fusion))
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
