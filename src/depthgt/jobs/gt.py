"""Entry points of the GT jobs: scene index, frame set, scene summary, dataset, and the
registration encoder's pretraining.

Each Snakemake script calls one of these with its rule's paths (every output path
explicitly) and the config sections of its stage (:data:`depthgt.settings.STAGES`); the
job gets its settings from them (:func:`depthgt.settings.stage_settings`), calls one library function and writes
the outputs. Every job also runs and is tested without Snakemake.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from depthgt import io
from depthgt.atomic import work_dir, write_atomic
from depthgt.device import keep_freed_memory, resolve_device
from depthgt.errors import DepthGTError, FrameError
from depthgt.gt import store
from depthgt.gt.assemble import (
    DatasetOutputs,
    assemble,
    empty_dataset,
    empty_dataset_message,
    summarize_scene,
    write_manifests,
)
from depthgt.gt.card import build_card, write_card
from depthgt.gt.index import build_index, select_pretraining_framesets
from depthgt.jobs.common import open_source_scene
from depthgt.settings import STAGES, stage_settings
from depthgt.status import Status

__all__ = [
    "run_scene_references",
    "run_scene_index",
    "run_frameset_batch",
    "run_scene_summary",
    "run_dataset",
    "run_training_manifests",
    "run_pretrain_registration",
]

log = logging.getLogger("depthgt")


def run_scene_index(
    source: dict[str, Any], scene: str, config: Mapping[str, Any], out_parquet: str, out_json: str
) -> None:
    """List a scene's frames and frame sets from its metadata (no frame is read) and
    write its index (parquet + json); ``config``: the sections of stage ``index``
    (:data:`depthgt.settings.STAGES`; a whole config is narrowed to them)."""
    settings = stage_settings(config, "index")
    sc = open_source_scene(source, scene, need_poses=False)  # reads no frame: poses do not matter here
    index = build_index(
        sc,
        source["name"],
        source.get("split", "auto"),
        fs_settings=settings.frameset,
        split_settings=settings.split,
        seed=settings.seed,
    )
    meta = dict(index.meta)
    meta["framesets_planned"] = [
        int(t) for t in index.framesets.loc[index.framesets["status"] == Status.PLANNED, "target"]
    ]
    meta["source"] = source
    Path(out_parquet).parent.mkdir(parents=True, exist_ok=True)
    index.to_table().to_parquet(out_parquet, index=False)
    io.write_json(out_json, meta)
    log.info(
        "%s/%s: %d frames, %d frame sets planned (%d skipped)",
        source["name"],
        scene,
        meta["n_frames"],
        meta["n_framesets_planned"],
        meta["n_framesets_skipped"],
    )
    for p in meta["problems"]:
        log.warning("%s/%s: %s", source["name"], scene, p)


def run_frameset_batch(
    source: dict[str, Any],
    scene: str,
    first: int,
    last: int,
    config: Mapping[str, Any],
    index_parquet: str,
    out_shard: str,
    encoder: str | None = None,
) -> list[dict[str, Any]]:
    """Build the frame sets of targets ``first``..``last`` of a scene and write them as
    one shard (:func:`depthgt.gt.store.write_shard`): the scene opened once, its frames
    read once through the batch's frame cache (:class:`depthgt.gt.cache.ResizedScene`),
    the encoder loaded once, the sets built by :func:`depthgt.gt.batch.build_batch`
    (every candidate target recorded in ``batch.json``, with every frame read and its
    outcome).

    Returns:
        The frame-set records of ``batch.json``.
    """
    # heavy (torch): only the jobs that build frame sets need them
    from depthgt.gt.batch import build_batch, frames_kept
    from depthgt.gt.cache import ResizedScene

    keep_freed_memory()  # a process of its own: no page faults for every large tensor

    settings = stage_settings(config, "frameset")
    need_poses = settings.registration.uses_source_poses
    planned = [t for t in settings.frameset.targets(last + settings.frameset.reach + 1) if first <= t <= last]
    state = None
    if encoder:
        import torch  # heavy: only with a pretrained encoder

        state = torch.load(encoder, map_location="cpu", weights_only=True) or None  # {}: no pretraining
    scene_obj = ResizedScene(
        open_source_scene(source, scene, need_poses=need_poses),
        settings.size_hw,
        keep=frames_kept(settings),
        need_pose=need_poses,
    )
    with work_dir(out_shard) as tmp:
        records, built = build_batch(
            scene_obj, source["name"], planned, pd.read_parquet(index_parquet), settings, tmp, encoder_state=state
        )
        frames = [c.to_dict() for c in scene_obj.checks]
        store.write_shard(out_shard, built, records, frames=frames)
    n_bad = sum(not f["valid"] for f in frames)
    log.info("%s/%s %06d-%06d: %d frames read, %d unusable", source["name"], scene, first, last, len(frames), n_bad)
    return records


def run_scene_references(
    source: dict[str, Any],
    scene: str,
    scene_framesets: str,
    rde_framesets: str,
    config: Mapping[str, Any],
    out_npz: str,
    out_table: str,
) -> None:
    """The references of a real scene's ``evaluation.split`` frame sets that no method
    was trained to imitate (:func:`depthgt.gt.references.scene_references`): the
    neighbours-only render of each target with the build's poses, and the TSDF GT
    (from ``rde_framesets``). Writes ``out_npz`` and its table ``out_table``."""
    # heavy (torch): only this job needs them
    from depthgt.gt.cache import ResizedScene
    from depthgt.gt.references import scene_references

    settings = stage_settings(config, "references")
    sc = ResizedScene(
        open_source_scene(source, scene, need_poses=False), settings.size_hw, keep=2 * settings.frameset.reach + 2
    )
    table = scene_references(
        sc,
        pd.read_parquet(scene_framesets),
        pd.read_parquet(rde_framesets),
        settings.render,
        settings.size_hw,
        settings.evaluation.split,
        out_npz,
        device=resolve_device(settings.device),
    )
    Path(out_table).parent.mkdir(parents=True, exist_ok=True)
    table.to_parquet(out_table, index=False)
    log.info(
        "%s/%s: %d reference images of the %s frame sets", source["name"], scene, len(table), settings.evaluation.split
    )


def run_scene_summary(
    index_parquet: str, shards: list[str], out_framesets: str, out_patches: str, out_quality: str, out_frames: str
) -> None:
    """Summarise a scene's frame sets (from its shards), patches, GT quality and the
    frames its batches read into four parquet tables
    (:func:`depthgt.gt.assemble.summarize_scene`)."""
    tables = summarize_scene(index_parquet, shards)
    for table, path in zip(tables, (out_framesets, out_patches, out_quality, out_frames)):
        table.to_parquet(path, index=False)
    frames = tables[3]
    log.info("%d frame sets, %d frames read (%d unusable)", len(tables[0]), len(frames), int((~frames["valid"]).sum()))


def run_dataset(
    scene_framesets: list[str],
    scene_patches: list[str],
    scene_quality: list[str],
    scene_frames: list[str],
    index_jsons: list[str],
    outputs: Mapping[str, str],
    shards: list[str] | None = None,
    config: Mapping[str, Any] | None = None,
    manifests: list[str] | None = None,
    allow_empty: bool = False,
) -> None:
    """Assemble the dataset manifests from the per-scene summaries and write the dataset
    card (:mod:`depthgt.gt.card`).

    Args:
        outputs: the paths ``framesets``, ``summary``, ``summary_md``, ``quality``,
            ``card``, ``card_md`` and those of the manifests to write here, of ``train``,
            ``val``, ``test`` (:class:`depthgt.gt.assemble.DatasetOutputs`).
        shards: every frame-set shard of the build (checksummed in the card).
        manifests: manifests written by another job (:func:`run_training_manifests`),
            checksummed in the card.
        allow_empty: keep a dataset without any built frame set (config
            ``dataset.allow_empty``); otherwise such a dataset fails the job with a
            :class:`~depthgt.errors.DepthGTError` saying why, after the summary
            (Markdown) is written to the log.
        config: the config sections that decide the GT (stage ``dataset`` of
            :data:`depthgt.settings.STAGES`; their resolved settings, defaults filled in,
            are recorded in the card).

    Raises:
        DepthGTError: an empty dataset without ``allow_empty``.
    """
    out = DatasetOutputs(**{k: outputs.get(k) for k in DatasetOutputs._fields})
    summary = assemble(scene_framesets, scene_patches, scene_quality, scene_frames, index_jsons, out)
    if empty_dataset(summary) and not allow_empty:
        log.info("the dataset summary:\n%s", Path(out.summary_md).read_text())
        raise DepthGTError(empty_dataset_message(summary))
    log.info(
        "dataset: %s pairs, %d frame sets skipped, %d of %d frames read unusable",
        summary["pairs"],
        len(summary["framesets_skipped"]),
        len(summary["frames_skipped"]),
        summary["frames_read"],
    )
    results = Path(outputs["card"]).parent.parent
    card = build_card(
        results,
        summary,
        pd.read_parquet(out.framesets),
        pd.read_csv(out.quality),
        [json.loads(Path(p).read_text()) for p in index_jsons],
        stage_settings(config or {}, "dataset").doc(*STAGES["dataset"].top),
        [*(shards or []), *(p for p in out if p is not None), *(manifests or [])],
    )
    write_card(card, outputs["card"], outputs["card_md"])
    log.info(
        "dataset card: %d files checksummed (depthgt %s, commit %s)",
        len(card["files"]),
        card["depthgt"]["version"],
        card["depthgt"]["commit"],
    )


def run_training_manifests(scene_patches: list[str], outputs: Mapping[str, str]) -> None:
    """Write the ``train`` and ``val`` manifests (``outputs``: split -> path) from the
    patch tables of the scenes that can hold such frame sets (the sources not
    ``split: test``; :func:`depthgt.gt.assemble.write_manifests`)."""
    rows = write_manifests(scene_patches, dict(outputs))
    log.info("training manifests: %s patch pairs from %d scenes", rows, len(scene_patches))


def run_pretrain_registration(
    sources: Mapping[str, dict[str, Any]], index_jsons: list[str], config: Mapping[str, Any], out_path: str
) -> None:
    """Stream-only pretraining of the registration encoder on frame sets of the training
    split (no poses used), written as a torch ``state_dict``.

    The frame sets are drawn by :func:`depthgt.gt.index.select_pretraining_framesets`;
    one with an unusable frame (the index reads none) is skipped with a warning and the
    next spare of the draw takes its place.
    """
    # heavy (torch): only this job needs them
    import torch

    from depthgt.registration import load_frameset, pretrain_encoder

    settings = stage_settings(config, "pretrain")
    pre = settings.registration.pretrain
    device = resolve_device(settings.device)
    candidates = select_pretraining_framesets(index_jsons, pre.framesets, settings.seed)
    framesets, scenes, skipped = [], {}, 0
    for dataset, scene, members in candidates:
        if len(framesets) >= pre.framesets:
            break
        if (dataset, scene) not in scenes:
            scenes[dataset, scene] = open_source_scene(sources[dataset], scene, need_poses=False)
        try:
            data = load_frameset(scenes[dataset, scene], members, settings.size_hw, need_poses=False, device=device)
        except FrameError as err:
            skipped += 1
            log.warning(
                "pretraining: frame set %s/%s/%06d skipped, a frame is unusable: %s", dataset, scene, members[0], err
            )
            continue
        framesets.append((data.rgb, data.depth_m, data.K, [m - members[0] for m in members]))
    if len(framesets) < min(pre.framesets, len(candidates)):
        log.warning(
            "pretraining: only %d usable frame sets of the train split (%d asked for, %d skipped)",
            len(framesets),
            pre.framesets,
            skipped,
        )
    log.info("pretraining the registration encoder on %d frame sets, %d epoch(s)", len(framesets), pre.epochs)
    state = (
        pretrain_encoder(framesets, settings.registration, epochs=pre.epochs, seed=settings.seed) if framesets else {}
    )
    write_atomic(out_path, lambda tmp: torch.save(state, tmp))
