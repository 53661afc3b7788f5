"""Entry points of the GT jobs: scene index, frame set, scene summary, dataset, and the
registration encoder's pretraining.

Each Snakemake script calls one of these with its rule's paths (every output path
explicitly) and config sections; the job gets its settings from
:func:`depthgt.settings.settings_from_config`, calls one library function and writes
the outputs. Every job also runs and is tested without Snakemake.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

from depthgt import io
from depthgt.jobs.common import open_source_scene

__all__ = ["run_scene_index", "run_frameset_batch", "run_scene_summary", "run_dataset", "run_pretrain_registration"]

log = logging.getLogger("depthgt")


def run_scene_index(source: dict[str, Any], scene: str, config: Mapping[str, Any], out_parquet: str,
                    out_json: str) -> None:
    """Check every frame of a scene and write its index (parquet + json)."""
    from depthgt.gt.index import build_index
    from depthgt.settings import settings_from_config

    settings = settings_from_config(config)
    need_poses = settings.registration.method == "given"
    sc = open_source_scene(source, scene, need_poses=need_poses)
    index = build_index(sc, source["name"], source.get("split", "auto"), need_poses=need_poses,
                        fs_settings=settings.frameset, split_settings=settings.split, seed=settings.seed, progress=True)
    meta = dict(index.meta)
    meta["framesets_ok"] = [int(t) for t in index.framesets.loc[index.framesets["status"] == "ok", "target"]]
    meta["source"] = source
    Path(out_parquet).parent.mkdir(parents=True, exist_ok=True)
    index.to_table().to_parquet(out_parquet, index=False)
    io.write_json(out_json, meta)
    log.info("%s/%s: %d frames (%d valid), %d frame sets (%d skipped)", source["name"], scene, meta["n_frames"],
             meta["n_valid_frames"], meta["n_framesets"], meta["n_framesets_skipped"])
    for p in meta["problems"]:
        log.warning("%s/%s: %s", source["name"], scene, p)


def run_frameset_batch(source: dict[str, Any], scene: str, first: int, last: int, config: Mapping[str, Any],
                       index_parquet: str, out_shard: str, encoder: str | None = None) -> list[dict[str, Any]]:
    """Build the frame sets of targets ``first``..``last`` of a scene in turn and write
    them as one shard (:func:`depthgt.gt.store.write_shard`); the encoder and the scene
    are loaded once.

    Every candidate target of the slice gets a record in the shard's ``batch.json``:
    ``ok`` when built, else ``skipped`` with the index's reason (invalid member frames,
    split guard) or ``not_in_scene`` when the scene holds fewer frames than planned (a
    truncated file). Frames are read from the source once per batch, at the working
    resolution (:class:`depthgt.gt.cache.ResizedScene`).

    Returns:
        The records of ``batch.json``.
    """
    import tempfile

    import pandas as pd
    from tqdm import tqdm

    from depthgt.gt import store
    from depthgt.gt.frameset import FrameSetOutputs, process_frameset
    from depthgt.settings import settings_from_config

    settings = settings_from_config(config)
    planned = [t for t in settings.frameset.targets(last + settings.frameset.reach + 1) if first <= t <= last]
    table = pd.read_parquet(index_parquet)
    rows = {int(r.position): r for r in table[table["is_target"]].itertuples()}
    state = None
    if encoder:
        import torch

        state = torch.load(encoder, map_location="cpu", weights_only=True) or None  # {}: no pretraining
    from depthgt.gt.cache import ResizedScene

    scene_obj = ResizedScene(open_source_scene(source, scene, need_poses=(settings.registration.method == "given")),
                             settings.size_hw, keep=2 * settings.frameset.reach + 2)
    records: list[dict[str, Any]] = []
    built: dict[int, Path] = {}
    with tempfile.TemporaryDirectory(prefix=".batch-", dir=Path(out_shard).parent) as tmp:
        for target in tqdm(planned, desc=f"frame sets {source['name']}/{scene} {first:06d}-{last:06d}", unit="set"):
            row = rows.get(target)
            if row is None:
                records.append({"target": target, "status": "skipped", "reason": "not_in_scene: the scene holds "
                                f"{len(table)} frames, fewer than planned for this target", "members": [], "split": ""})
                log.warning("%s/%s: target %d skipped: not in the scene (%d frames)", source["name"], scene, target,
                            len(table))
                continue
            members = [int(m) for m in row.members]
            if row.frameset_status != "ok":
                records.append({"target": target, "status": row.frameset_status, "reason": row.frameset_reason,
                                "members": members, "split": row.frameset_split})
                continue
            out = FrameSetOutputs.in_dir(Path(tmp) / f"{target:06d}")
            doc = process_frameset(scene_obj, source["name"], target, members, row.frameset_split, out, settings,
                                   encoder_state=state)
            built[target] = Path(tmp) / f"{target:06d}"
            records.append({"target": target, "status": doc["status"], "reason": doc["reason"], "members": members,
                            "split": row.frameset_split})
            log.info("frame set %s/%s/%06d: status %s, %d/%d patches kept, GT missing %.3f (input %.3f)",
                     source["name"], scene, target, doc["status"], doc["statistics"]["patches_kept"],
                     doc["statistics"]["patches_drawn"], doc["statistics"]["gt_missing"],
                     doc["statistics"]["input_missing"])
        store.write_shard(out_shard, built, records)
    return records


def run_scene_summary(index_parquet: str, shards: list[str], out_framesets: str, out_patches: str,
                      out_quality: str) -> None:
    """Summarise a scene's frame sets (from its shards), patches and GT quality into
    three parquet tables."""
    from depthgt.gt.assemble import summarize_scene

    fs, patches, quality = summarize_scene(index_parquet, shards)
    fs.to_parquet(out_framesets, index=False)
    patches.to_parquet(out_patches, index=False)
    quality.to_parquet(out_quality, index=False)


def run_dataset(scene_framesets: list[str], scene_patches: list[str], scene_quality: list[str], index_jsons: list[str],
                outputs: Mapping[str, str]) -> None:
    """Assemble the dataset manifests from the per-scene summaries.

    Args:
        outputs: the paths ``train``, ``val``, ``test``, ``framesets``, ``summary``,
            ``summary_md``, ``quality`` (:class:`depthgt.gt.assemble.DatasetOutputs`).
    """
    from depthgt.gt.assemble import DatasetOutputs, assemble

    out = DatasetOutputs(**{k: outputs[k] for k in DatasetOutputs._fields})
    summary = assemble(scene_framesets, scene_patches, scene_quality, index_jsons, out)
    log.info("dataset: %s pairs, %d frame sets skipped", summary["pairs"], len(summary["framesets_skipped"]))


def run_pretrain_registration(sources: Mapping[str, dict[str, Any]], index_jsons: list[str], config: Mapping[str, Any],
                              out_path: str) -> None:
    """Stream-only pretraining of the registration encoder on frame sets of the training
    split (no poses used), written as a torch ``state_dict``."""
    import torch

    from depthgt.atomic import write_atomic
    from depthgt.device import resolve_device
    from depthgt.gt.frameset import load_frameset
    from depthgt.gt.index import select_pretraining_framesets
    from depthgt.registration import pretrain_encoder
    from depthgt.settings import settings_from_config

    settings = settings_from_config(config)
    pre = settings.registration.pretrain
    device = resolve_device(settings.device)
    chosen = select_pretraining_framesets(index_jsons, pre.framesets, settings.seed)
    framesets, scenes = [], {}
    for dataset, scene, members in chosen:
        if (dataset, scene) not in scenes:
            scenes[dataset, scene] = open_source_scene(sources[dataset], scene, need_poses=False)
        data = load_frameset(scenes[dataset, scene], members, settings.size_hw, need_poses=False, device=device)
        framesets.append((data.rgb, data.depth_m, data.K, [m - members[0] for m in members]))
    log.info("pretraining the registration encoder on %d frame sets, %d epoch(s)", len(framesets), pre.epochs)
    state = pretrain_encoder(framesets, settings.registration, epochs=pre.epochs, seed=settings.seed) if framesets else {}
    write_atomic(out_path, lambda tmp: torch.save(state, tmp))
