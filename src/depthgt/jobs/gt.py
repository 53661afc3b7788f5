"""Entry points of the workflow's jobs: plain arguments in, files out.

Each Snakemake script is two lines that call one of these with the paths and the
config sections of its rule, so every job can also be run and tested without
Snakemake.
"""

from __future__ import annotations

import json
import logging
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from depthgt import io

log = logging.getLogger("depthgt")


@contextmanager
def logging_to(path: str | Path | None, level: int = logging.INFO) -> Iterator[None]:
    """Send depthgt's log records (and warnings) to ``path`` for the duration."""
    if path is None:
        yield
        return
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    handler = logging.FileHandler(path, mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    root.addHandler(handler)
    old = root.level
    root.setLevel(level)
    logging.captureWarnings(True)
    try:
        yield
    except Exception:
        log.exception("job failed")
        raise
    finally:
        root.removeHandler(handler)
        root.setLevel(old)
        handler.close()


POSE_OPTIONAL_KINDS = ("scannet", "sevenscenes", "tum")


def open_source_scene(source: dict[str, Any], scene: str, need_poses: bool = True):
    """Open ``scene`` of a config source entry (name, kind, root, options).

    When the registration does not need the source's poses, real sources are opened
    with ``require_pose=False`` so that frames with non-finite poses (ScanNet has them)
    stay usable.
    """
    from depthgt.errors import ConfigError
    from depthgt.sources.base import open_scene

    options = dict(source.get("options") or {})
    if not need_poses and source["kind"] in POSE_OPTIONAL_KINDS:
        options.setdefault("require_pose", False)
    try:
        return open_scene(source["kind"], source.get("root"), scene, **options)
    except TypeError as err:
        raise ConfigError(f"config sources entry {source.get('name')!r} (kind {source['kind']}): bad options: {err}") from err


def run_scene_index(source: dict[str, Any], scene: str, config: dict[str, Any], out_parquet: str, out_json: str,
                    cache_dir: str | None = None) -> None:
    """Check every frame of a scene and write its index (parquet + json), and the
    frame cache at the working resolution into ``cache_dir`` when given."""
    from depthgt.gt.cache import FrameCacheWriter
    from depthgt.settings import build
    from depthgt.gt.framesets import FrameSetSettings, SplitSettings
    from depthgt.gt.index import build_index

    method = (config.get("registration") or {}).get("method", "given")
    sc = open_source_scene(source, scene, need_poses=(method == "given"))
    size = int(config.get("resize", 256))
    cache = FrameCacheWriter(cache_dir, len(sc), (size, size), sc.has_clean_depth) if cache_dir else None
    index = build_index(
        sc, source["name"], source.get("split", "auto"), need_poses=(method == "given"),
        fs_settings=build(FrameSetSettings, config.get("frameset"), "frameset"),
        split_settings=build(SplitSettings, config.get("split"), "split"),
        seed=int(config.get("seed", 0)), progress=True, cache=cache,
    )
    if cache is not None:
        cache.close()
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


def run_frameset(source: dict[str, Any], scene: str, target: int, config: dict[str, Any], index_parquet: str, out_dir: str,
                 encoder: str | None = None, cache_dir: str | None = None) -> None:
    """Build one frame set's outputs in ``out_dir`` (frames from ``cache_dir`` when given)."""
    import pandas as pd

    from depthgt.settings import job_settings
    from depthgt.gt.frameset import process_frameset

    table = pd.read_parquet(index_parquet)
    row = table[(table["position"] == target) & table["is_target"]]
    if row.empty or row.iloc[0]["frameset_status"] != "ok":
        raise ValueError(f"{index_parquet}: target {target} is not a runnable frame set of this scene")
    row = row.iloc[0]
    state = None
    if encoder:
        import torch

        state = torch.load(encoder, map_location="cpu", weights_only=True) or None  # {}: no pretraining
    settings = job_settings(config)
    if cache_dir:
        from depthgt.gt.cache import CachedScene

        scene_obj = CachedScene(Path(index_parquet).with_name("index.json"), table)
    else:
        scene_obj = open_source_scene(source, scene, need_poses=(settings.registration_method == "given"))
    doc = process_frameset(scene_obj, source["name"], target, [int(m) for m in row["members"]],
                           row["frameset_split"], out_dir, settings, encoder_state=state, cache_dir=cache_dir)
    log.info("frame set %s/%s/%06d: status %s, %d/%d patches kept, GT missing %.3f (input %.3f)", source["name"], scene,
             target, doc["status"], doc["statistics"]["patches_kept"], doc["statistics"]["patches_drawn"],
             doc["statistics"]["gt_missing"], doc["statistics"]["input_missing"])


def run_scene_summary(index_parquet: str, frameset_jsons: list[str], out_framesets: str, out_patches: str, out_quality: str) -> None:
    """Summarise a scene's frame sets, patches and GT quality into three parquet tables."""
    from depthgt.gt.assemble import summarize_scene

    fs, patches, quality = summarize_scene(index_parquet, [str(Path(p).parent) for p in frameset_jsons])
    fs.to_parquet(out_framesets, index=False)
    patches.to_parquet(out_patches, index=False)
    quality.to_parquet(out_quality, index=False)


def run_dataset(scene_framesets: list[str], out_dir: str) -> None:
    """Assemble the dataset manifests from the per-scene summaries."""
    from depthgt.gt.assemble import assemble

    summary = assemble([str(Path(p).parent) for p in scene_framesets], out_dir)
    log.info("dataset: %s pairs, %d frame sets skipped", summary["pairs"], len(summary["framesets_skipped"]))


def run_pretrain_registration(sources: dict[str, dict[str, Any]], index_jsons: list[str], config: dict[str, Any],
                              out_path: str) -> None:
    """Stream-only pretraining of the registration encoder on frame sets of the training
    split (no poses used), written as a torch ``state_dict``."""
    import torch

    from depthgt.settings import job_settings
    from depthgt.gt.framesets import stable_seed
    from depthgt.gt.frameset import load_frameset, resolve_device
    from depthgt.registration import make_settings, pretrain_encoder
    import pandas as pd

    settings = job_settings(config)
    reg = dict(settings.registration)
    pre = dict(reg.pop("pretrain", None) or {})
    n_sets, epochs = int(pre.get("framesets", 16)), int(pre.get("epochs", 1))
    device = resolve_device(settings.device)
    candidates = []
    for path in index_jsons:
        meta = json.loads(Path(path).read_text())
        table = pd.read_parquet(Path(path).with_name("index.parquet"))
        ok = table[table["is_target"] & (table["frameset_status"] == "ok") & (table["frameset_split"] == "train")]
        candidates += [(meta["dataset"], meta["scene"], [int(m) for m in r.members]) for r in ok.itertuples()]
    if not candidates:
        raise ValueError("pretrain_registration: no frame set of the train split to pretrain on "
                         "(set registration.pretrain.framesets: 0 to start from random weights)")
    rng = np.random.default_rng(stable_seed(settings.seed, "pretrain"))
    chosen = sorted(rng.choice(len(candidates), size=min(n_sets, len(candidates)), replace=False).tolist()) if n_sets else []
    framesets, scenes = [], {}
    for i in chosen:
        dataset, scene, members = candidates[i]
        if (dataset, scene) not in scenes:
            scenes[dataset, scene] = open_source_scene(sources[dataset], scene, need_poses=False)
        data = load_frameset(scenes[dataset, scene], members, settings.size_hw, need_poses=False, device=device)
        framesets.append((data.rgb, data.depth_m, data.K, [m - members[0] for m in members]))
    log.info("pretraining the registration encoder on %d frame sets, %d epoch(s)", len(framesets), epochs)
    state = pretrain_encoder(framesets, make_settings(**reg), epochs=epochs, seed=settings.seed) if framesets else {}
    Path(out_path).parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(out_path).with_suffix(".tmp")
    torch.save(state, tmp)
    tmp.replace(out_path)
