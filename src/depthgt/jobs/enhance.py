"""Entry points of the enhancement workflow's jobs (train, RDE GT, evaluate, tables, figures).

Each Snakemake script calls one of these with its paths and config sections, so every
job also runs and is tested without Snakemake. Nothing heavy is imported at module
level.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from depthgt import io

__all__ = [
    "run_train",
    "run_rde_scene",
    "run_rde_dataset",
    "run_evaluate",
    "run_tables",
    "run_figures",
]

log = logging.getLogger("depthgt")

RDE_FRAMESET_COLUMNS = ["dataset", "scene", "target", "split", "status", "reason", "frameset_dir", "rde_dir", "has_truth",
                        "patches_kept", "rde_missing", "backend"]
RDE_PATCH_COLUMNS = ["dataset", "scene", "target", "split", "patch", "path"]


# --------------------------------------------------------------------------- training


def run_train(settings: dict[str, Any], train_manifest: str, val_manifest: str | None, out_dir: str, threads: int = 1) -> dict:
    """Train one model (settings: a TrainSettings mapping) and write ``out_dir``."""
    import torch

    from depthgt.enhance.train import settings_from_dict, train

    torch.set_num_threads(max(1, int(threads)))
    st = settings_from_dict(settings)
    result = train(train_manifest, val_manifest, out_dir, st)
    log.info("trained %s -> %s: best epoch %d (val %.5f), %d epochs run", st.model, out_dir, result["best_epoch"],
             result["best_val"], result["epochs_run"])
    return result


# --------------------------------------------------------------------------- RDE global-reconstruction GT


def _stream(source: dict, scene: str, cache_dir: str | None, K_work: np.ndarray, step: int, targets: list[int]):
    """Depth, colour and poses of the stream for the TSDF, plus the targets' poses.

    Uses the scene's frame cache (``frames/`` written by the scene index: every frame at
    the working resolution, whose intrinsics are ``K_work``) when given and present;
    else reads the source at full resolution.

    Returns:
        (depths list, rgbs list, K (3, 3), poses list, {target: T_world_cam or None}).
    """
    cache = Path(cache_dir) if cache_dir else None
    if cache is not None and (cache / "depth.npy").is_file() and (cache / "poses.npy").is_file():
        depth = np.load(cache / "depth.npy", mmap_mode="r")
        rgb = np.load(cache / "rgb.npy", mmap_mode="r") if (cache / "rgb.npy").is_file() else None
        poses = np.load(cache / "poses.npy")
        keep = [i for i in range(0, len(depth), step) if np.isfinite(poses[i]).all() and (depth[i] > 0).any()]
        target_poses = {t: (poses[t] if t < len(poses) and np.isfinite(poses[t]).all() else None) for t in targets}
        log.info("%s/%s: TSDF input from the frame cache %s", source["name"], scene, cache)
        return ([np.asarray(depth[i]) for i in keep], [np.asarray(rgb[i]) for i in keep] if rgb is not None else None,
                np.asarray(K_work, dtype=np.float64), [poses[i] for i in keep], target_poses)

    from depthgt.errors import FrameError
    from depthgt.jobs.gt import open_source_scene

    sc = open_source_scene(source, scene, need_poses=True)
    fuse_ids = set(range(0, len(sc), step))
    depths, rgbs, poses, target_poses = [], [], [], {}
    for i in sorted(fuse_ids | set(targets)):
        try:
            fr = sc.read(i)
        except FrameError as err:
            log.info("%s/%s frame %d not used for the TSDF: %s", source["name"], scene, i, err)
            if i in targets:
                target_poses[i] = None
            continue
        T = fr.T_world_cam
        ok = T is not None and np.isfinite(T).all()
        if i in targets:
            target_poses[i] = T if ok else None
        if i in fuse_ids and ok and (fr.depth_m > 0).any():
            depths.append(fr.depth_m)
            rgbs.append(fr.rgb)
            poses.append(T)
    return depths, rgbs, np.asarray(sc.intrinsics, dtype=np.float64), poses, target_poses


def run_rde_scene(source: dict[str, Any], scene: str, scene_framesets: str, rde_config: dict[str, Any], out_dir: str,
                  out_framesets: str, out_patches: str, frame_cache: str | None = None) -> None:
    """Global-reconstruction GT of every frame set of one scene.

    Fuses the scene's stream (every ``rde.frame_step``-th frame, source poses) into a
    TSDF, renders it at each runnable frame set's target (256x256 K of its
    frameset.json) and writes ``{out_dir}/{target:06d}/``: ``gt.exr`` (Z), ``patches.npz``
    (the frame set's drawn crop boxes applied to (input, RDE GT, rgb), kept when the
    RDE GT misses < ``rde.max_missing``) and ``frameset.json`` (K, split, statistics).
    Two tables list the frame sets and the kept patches.
    """
    import pandas as pd

    from depthgt.eval.evaluate import load_frame
    from depthgt.gt.patches import crop
    from depthgt.quality import error_stats
    from depthgt.gt.rde import reconstruct_and_render, tsdf_settings_from_dict

    settings = tsdf_settings_from_dict(rde_config)
    fs = pd.read_parquet(scene_framesets)
    ok = fs[(fs["status"] == "ok") & (fs["frameset_dir"] != "")]
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows, patch_rows = [], []
    if ok.empty:
        log.info("%s/%s: no runnable frame set, no RDE GT", source["name"], scene)
    else:
        targets = [int(t) for t in ok["target"]]
        docs = {int(r.target): json.loads((Path(r.frameset_dir) / "frameset.json").read_text()) for r in ok.itertuples()}
        K_work = np.asarray(next(iter(docs.values()))["K"], dtype=np.float64)
        depths, rgbs, K, poses, target_poses = _stream(source, scene, frame_cache, K_work, settings.frame_step, targets)
        frames = {int(r.target): load_frame(r.frameset_dir) for r in ok.itertuples()}
        render_targets = [t for t in targets if target_poses.get(t) is not None]
        hw = next(iter(frames.values()))["input"].shape
        if not depths:
            raise ValueError(f"{source['name']}/{scene}: no frame with depth and a finite pose for the TSDF")
        rendered, backend = reconstruct_and_render(
            depths, rgbs, K, poses, [np.asarray(docs[t]["K"], dtype=np.float64) for t in render_targets],
            [target_poses[t] for t in render_targets], hw, settings)
        log.info("%s/%s: TSDF of %d frames (%s backend), %d targets rendered", source["name"], scene, len(depths), backend,
                 len(render_targets))
        by_target = dict(zip(render_targets, rendered))
        for r in ok.itertuples():
            t = int(r.target)
            row = {"dataset": r.dataset, "scene": r.scene, "target": t, "split": r.split, "status": "ok", "reason": "",
                   "frameset_dir": r.frameset_dir, "rde_dir": "", "has_truth": bool(r.has_truth), "patches_kept": 0,
                   "rde_missing": np.nan, "backend": backend}
            if t not in by_target:
                row.update(status="skipped", reason="no finite global pose for the target")
                rows.append(row)
                continue
            d = out / f"{t:06d}"
            d.mkdir(parents=True, exist_ok=True)
            gt, fr = by_target[t], frames[t]
            io.write_exr(d / "gt.exr", {"Z": gt})
            with np.load(Path(r.frameset_dir) / "patches.npz") as npz:
                boxes = npz["all_boxes"]
            p_gt = crop(gt, boxes)
            miss = (p_gt <= 0).mean(axis=(1, 2))
            keep = miss < settings.max_missing
            arrays = {"input": crop(fr["input"], boxes)[keep], "gt": p_gt[keep].astype(np.float32),
                      "rgb": crop(fr["rgb"], boxes)[keep], "boxes": boxes[keep], "missing_gt": miss[keep].astype(np.float32),
                      "all_boxes": boxes, "kept": keep}
            np.savez_compressed(d / "patches.npz", **arrays)
            stats = {"rde_missing": float((gt <= 0).mean()), "patches_kept": int(keep.sum()), "patches_drawn": int(len(keep))}
            if fr["truth"] is not None:
                stats["rde_vs_truth"] = error_stats(gt, fr["truth"])
            io.write_json(d / "frameset.json", {"dataset": r.dataset, "scene": r.scene, "target": t, "split": r.split,
                                                "K": docs[t]["K"], "backend": backend, "settings": rde_config or {},
                                                "statistics": stats})
            row.update(rde_dir=str(d), patches_kept=int(keep.sum()), rde_missing=stats["rde_missing"])
            rows.append(row)
            for j in range(int(keep.sum())):
                patch_rows.append({"dataset": r.dataset, "scene": r.scene, "target": t, "split": r.split, "patch": j,
                                   "path": str(d / "patches.npz")})
    Path(out_framesets).parent.mkdir(parents=True, exist_ok=True)
    pd.DataFrame(rows, columns=RDE_FRAMESET_COLUMNS).to_parquet(out_framesets, index=False)
    pd.DataFrame(patch_rows, columns=RDE_PATCH_COLUMNS).to_parquet(out_patches, index=False)


def run_rde_dataset(scene_framesets: list[str], scene_patches: list[str], out_dir: str) -> None:
    """Concatenate the scenes' RDE tables into ``{train,val,test}.parquet`` and ``framesets.parquet``."""
    import pandas as pd

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fs = [pd.read_parquet(p) for p in scene_framesets]
    fs = pd.concat(fs, ignore_index=True) if fs else pd.DataFrame(columns=RDE_FRAMESET_COLUMNS)
    fs.to_parquet(out / "framesets.parquet", index=False)
    pt = [pd.read_parquet(p) for p in scene_patches]
    pt = pd.concat(pt, ignore_index=True) if pt else pd.DataFrame(columns=RDE_PATCH_COLUMNS)
    for split in ("train", "val", "test"):
        pt[pt["split"] == split].reset_index(drop=True).to_parquet(out / f"{split}.parquet", index=False)
    log.info("RDE GT: %d frame sets, patches %s", len(fs), pt["split"].value_counts().to_dict())


# --------------------------------------------------------------------------- evaluation


def run_evaluate(name: str, method: dict, framesets: str, out_table: str, pred_dir: str | None = None,
                 split: str = "test", threads: int = 1) -> None:
    """Run one method on the ``split`` frame sets; score against depthgt's GT and, where
    present, the clean truth. Writes a tidy long table (parquet, see
    :data:`depthgt.eval.evaluate.EVAL_COLUMNS`)."""
    import pandas as pd
    import torch

    from depthgt.eval.evaluate import EVAL_COLUMNS, load_frame, run_method
    from depthgt.eval.metrics import METRIC_UNITS, depth_metrics

    torch.set_num_threads(max(1, int(threads)))
    table = pd.read_parquet(framesets)
    if split is not None:
        table = table[table["split"] == split]
    table = table[(table["status"] == "ok") & (table["frameset_dir"] != "")]
    rows = []
    for rec in table.itertuples():
        frame = load_frame(rec.frameset_dir)
        pred = run_method(method, frame)
        if pred_dir is not None:
            p = Path(pred_dir) / str(rec.dataset) / str(rec.scene) / f"{int(rec.target):06d}.npy"
            p.parent.mkdir(parents=True, exist_ok=True)
            np.save(p, pred.astype(np.float32))
        for reference in ("gt", "truth"):
            if frame[reference] is None:
                continue
            for metric, value in depth_metrics(pred, frame[reference]).items():
                rows.append({"dataset": rec.dataset, "scene": rec.scene, "target": int(rec.target), "method": name,
                             "reference": reference, "metric": metric, "unit": METRIC_UNITS.get(metric, ""),
                             "value": float(value)})
    out = pd.DataFrame(rows, columns=EVAL_COLUMNS)
    Path(out_table).parent.mkdir(parents=True, exist_ok=True)
    out.to_parquet(out_table, index=False)
    log.info("evaluated %s on %d %s frame sets", name, len(table), split)


# --------------------------------------------------------------------------- tables and figures


def run_tables(eval_tables: list[str], framesets: str, rde_framesets: str, gt_quality: str, kinds: dict[str, str],
               out_dir: str) -> None:
    """Tables 1-3 and the GT-quality table as CSV + Markdown in ``out_dir``."""
    import pandas as pd

    from depthgt.eval import tables

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    evals = [pd.read_parquet(p) for p in eval_tables]
    ev = pd.concat(evals, ignore_index=True) if evals else pd.DataFrame()
    t1 = tables.gt_vs_input_long(pd.read_parquet(framesets), pd.read_parquet(rde_framesets))
    tables.write_table(tables.table1(t1), out / "table1", tables.TABLE1_CAPTION)
    tables.write_table(tables.table2(ev, kinds), out / "table2", tables.TABLE2_CAPTION)
    tables.write_table(tables.table3(ev, kinds), out / "table3", tables.TABLE3_CAPTION)
    q = pd.read_csv(gt_quality)
    rq = tables.rde_quality_long(pd.read_parquet(rde_framesets))
    tables.write_table(tables.table_gt_quality(q, rq), out / "table_gt_quality", tables.GT_QUALITY_CAPTION)


def run_figures(framesets: str, pred_dirs: dict[str, str], loss_logs: dict[str, str], out_comparison: str,
                out_curves: dict[str, str], split: str = "test", frames_per_scene: int = 2) -> None:
    """The comparison figure (rows: up to ``frames_per_scene`` test frames of each test
    scene) and one training-curve plot per model (``out_curves``: model -> png)."""
    import pandas as pd

    from depthgt.eval import figures

    table = pd.read_parquet(framesets)
    table = table[(table["split"] == split) & (table["status"] == "ok") & (table["frameset_dir"] != "")]
    figures.comparison_figure(table, pred_dirs, out_comparison, frames_per_scene)
    for name, path in loss_logs.items():
        figures.training_curve(path, out_curves[name], title=name)
