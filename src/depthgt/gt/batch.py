"""A frame-set batch: a slice of one scene's targets, each built or recorded as skipped.

:func:`build_batch` is what a frame-set job does between reading its inputs and writing
its shard: every candidate target of the slice ends in one record of ``batch.json``
(built ``ok``/``failed``; ``skipped`` with its reason; ``not_in_scene`` for a truncated
scene), the frames are read through the batch's frame cache, and what depends on a
frame alone is computed once (:class:`~depthgt.framecache.FrameCache`). The buildable
sets go through :func:`~depthgt.gt.build.process_framesets` in groups: one set at a
time on the CPU, :data:`GPU_GROUP` at once on a GPU (their GTs rendered together).
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pandas as pd
from tqdm import tqdm

from depthgt.device import resolve_device
from depthgt.framecache import FrameCache
from depthgt.gt.build import FrameSetId, FrameSetOutputs, process_framesets
from depthgt.gt.cache import ResizedScene
from depthgt.gt.planning import coverage_candidates, member_problems
from depthgt.gt.resources import GPU_GROUP
from depthgt.settings import Settings
from depthgt.status import Status

__all__ = ["GPU_GROUP", "build_batch", "frames_kept"]

log = logging.getLogger("depthgt")

# GPU_GROUP, the frame sets built together on a GPU: defined in the torch-free
# depthgt.gt.resources, where the workflow sizes the batch job's memory by it


def frames_kept(settings: Settings) -> int:
    """How many frames a batch job keeps at hand: the positions a group of frame sets
    (:data:`GPU_GROUP` on a GPU, ``target_step`` apart) and their reach (the coverage span
    with coverage) cover, and the next frame coming in. A group's first set is built
    after its last set's members were read: with fewer frames kept its frames would be
    read, resized and their geometry computed again."""
    fs = settings.frameset
    span = max(fs.reach, fs.coverage_span) if fs.selection == "coverage" else fs.reach
    group = GPU_GROUP if resolve_device(settings.device).type == "cuda" else 1
    return 2 * span + 1 + (group - 1) * fs.target_step + 1


def _record(target: int, status: str, reason: str, members: list[int], split: str) -> dict[str, Any]:
    return {"target": target, "status": status, "reason": reason, "members": members, "split": split}


def build_batch(
    scene: ResizedScene,
    dataset: str,
    planned: list[int],
    index: pd.DataFrame,
    settings: Settings,
    out_dir: str | Path,
    encoder_state: dict | None = None,
) -> tuple[list[dict[str, Any]], dict[int, Path]]:
    """Build the frame sets of the targets ``planned`` (positions of ``scene``, in order)
    into ``out_dir``/``{target:06d}``.

    Before a planned target is built its member frames are read (through ``scene``,
    which checks each frame once); a frame set with an unusable member is skipped, its
    reason naming each such frame (:func:`~depthgt.gt.planning.member_problems`). With
    ``frameset.selection: coverage`` each target's candidate views come from the index's
    split tags (:func:`~depthgt.gt.planning.coverage_candidates`).

    Args:
        scene: the scene at the working resolution, its frames kept for the batch.
        index: the scene's index table (``position``, ``is_target``, ``members``,
            ``frameset_status``, ``frameset_reason``, ``frameset_split``, ``split``).

    Returns:
        the records of every target of ``planned`` (batch.json's), and the folders of
        the frame sets built, by target.

    Long because every candidate target ends in one of the records of batch.json (not in
    the scene, not planned, unusable members, built), each written where the loop
    decides it.
    """
    fs = settings.frameset
    rows = {int(r.position): r for r in index[index["is_target"]].itertuples()}
    splits = index.sort_values("position")["split"].to_numpy(dtype=object)  # the index's split of every frame
    group = GPU_GROUP if resolve_device(settings.device).type == "cuda" else 1
    cache = FrameCache(keep=frames_kept(settings))
    out_dir = Path(out_dir)
    records: dict[int, dict[str, Any]] = {}
    built: dict[int, Path] = {}
    waiting: list[tuple[FrameSetId, list[int]]] = []
    name = scene.name

    def flush() -> None:
        if not waiting:
            return
        fids = [f for f, _ in waiting]
        outs = [FrameSetOutputs.in_dir(out_dir / f"{f.target:06d}") for f in fids]
        docs = process_framesets(scene, fids, outs, settings, encoder_state, [c for _, c in waiting], cache)
        for fid, doc in zip(fids, docs):
            built[fid.target] = out_dir / f"{fid.target:06d}"
            records[fid.target] = _record(fid.target, doc["status"], doc["reason"], fid.members, fid.split)
            log.info(
                "frame set %s/%s/%06d: status %s, %d/%d patches kept, GT missing %.3f (input %.3f)",
                dataset,
                name,
                fid.target,
                doc["status"],
                doc["statistics"]["patches_kept"],
                doc["statistics"]["patches_drawn"],
                doc["statistics"]["gt_missing"],
                doc["statistics"]["input_missing"],
            )
        waiting.clear()

    desc = f"frame sets {dataset}/{name} {planned[0]:06d}-{planned[-1]:06d}" if planned else "frame sets"
    for target in tqdm(planned, desc=desc, unit="set"):
        row = rows.get(target)
        if row is None:
            reason = f"not_in_scene: the scene holds {len(index)} frames, fewer than planned for this target"
            records[target] = _record(target, Status.SKIPPED, reason, [], "")
            log.warning("%s/%s: target %d skipped: not in the scene (%d frames)", dataset, name, target, len(index))
            continue
        members = [int(m) for m in row.members]
        if row.frameset_status != Status.PLANNED:
            records[target] = _record(target, row.frameset_status, row.frameset_reason, members, row.frameset_split)
            continue
        checks = [scene.check(m) for m in members]
        bad = member_problems(members, {c.position: c.problem for c in checks if not c.valid})
        if bad:
            records[target] = _record(target, Status.SKIPPED, bad, members, row.frameset_split)
            log.warning("frame set %s/%s/%06d skipped: %s", dataset, name, target, bad)
            continue
        fid = FrameSetId(dataset, name, target, members, row.frameset_split)
        waiting.append((fid, coverage_candidates(splits, target, members, fs)))
        if len(waiting) >= group:
            flush()
    flush()
    return [records[t] for t in planned], built
