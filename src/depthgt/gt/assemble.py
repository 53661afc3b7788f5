"""Per-scene summaries and the dataset manifests.

* :func:`summarize_scene` turns a scene's index and its frame-set shards into three
  tidy tables: one row per frame set (skipped ones included, with reasons), one row
  per drawn patch (kept or rejected, with missing ratios) and the GT quality; and a
  fourth: one row per frame the batches read, whether it was usable and why not.
* :func:`assemble` concatenates the scenes into ``{train,val,test}.parquet`` (one row
  per kept patch pair), ``framesets.parquet`` (one row per frame set, for full-frame
  evaluation), a summary (every skipped frame and frame set with its reason) and the
  GT quality table (units from :data:`depthgt.metric_vocabulary.METRIC_UNITS`).
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pandas as pd

from depthgt.gt import store
from depthgt.gt.settings import SPLITS
from depthgt.metric_vocabulary import unit_of
from depthgt.status import Status

FRAMESET_COLUMNS = [
    "dataset",
    "scene",
    "target",
    "frame_id",
    "split",
    "status",
    "reason",
    "frameset",
    "has_truth",
    "patches_drawn",
    "patches_kept",
    "input_missing",
    "gt_missing",
    "gt_median_sigma_m",
    "neighbours_left_out",
    "leave_target_out_mae_m",
]
# (estimate, frameset.json statistics key, reference) of the GT quality table
QUALITY_KEYS = (
    ("gt", "gt_vs_truth", "truth"),
    ("input", "input_vs_truth", "truth"),
    ("gt", "gt_vs_truth_input_valid", "truth@input_valid"),
    ("leave_target_out", "leave_target_out", "target_raw"),
)
# the frames the frame-set batches read (depthgt.gt.cache.FrameCheck): message names the file at fault
FRAME_COLUMNS = ["dataset", "scene", "position", "frame_id", "valid", "reason", "message"]
# frameset: the frame set's location (depthgt.gt.store); its patches are <frameset>/patches.npz
PATCH_COLUMNS = [
    "dataset",
    "scene",
    "target",
    "split",
    "patch",
    "frameset",
    "y0",
    "x0",
    "size",
    "missing_input",
    "missing_gt",
    "kept",
]


def read_index(index_parquet: str | Path) -> tuple[pd.DataFrame, dict]:
    """The scene index table and its metadata (``index.json`` beside it)."""
    table = pd.read_parquet(index_parquet)
    meta = json.loads((Path(index_parquet).with_name("index.json")).read_text())
    return table, meta


def summarize_scene(
    index_parquet: str | Path, shards: list[str | Path]
) -> tuple[pd.DataFrame, pd.DataFrame, pd.DataFrame, pd.DataFrame]:
    """Tables of one scene: frame sets, patches, GT quality (tidy long form) and frames.

    Args:
        shards: the scene's frame-set shards (:mod:`depthgt.gt.store`).

    Every target of the index appears in the frame-set table with the outcome its batch
    recorded: built (the statistics of its frameset.json and its location) or skipped
    with the reason (the index's split guard, unusable member frames); targets a batch
    planned beyond the frames the scene holds appear as recorded there. The frame table
    holds every frame a batch read (:data:`FRAME_COLUMNS`), once: batches overlap by
    the frame sets' reach and read the frames there each.

    Raises:
        FileNotFoundError: a target of the index that no shard given records.

    Long because the rows of its four tables are written out column by column
    (:data:`FRAMESET_COLUMNS`, :data:`PATCH_COLUMNS`, the quality and frame columns) in
    one pass over the shards.
    """
    table, meta = read_index(index_parquet)
    dataset, scene = meta["dataset"], meta["scene"]
    rows, patch_rows, quality = [], [], []
    by_target: dict[int, str] = {}
    batch_records: dict[int, dict] = {}
    frames: dict[int, dict] = {}
    for shard in shards:
        for rec in store.read_batch(shard):
            batch_records[int(rec["target"])] = rec
        for fr in store.read_batch_frames(shard):
            frames.setdefault(int(fr["position"]), fr)
        by_target.update({t: store.location(shard, t) for t in store.shard_targets(shard)})
    index_targets = set()
    for rec in table[table["is_target"]].itertuples():
        target = int(rec.position)
        index_targets.add(target)
        batch = batch_records.get(target)
        if batch is None:
            raise FileNotFoundError(
                f"{dataset}/{scene}: frame set {target} is in the index but no shard given records it"
            )
        row = {
            "dataset": dataset,
            "scene": scene,
            "target": target,
            "frame_id": rec.frame_id,
            "split": rec.frameset_split,
            "status": batch["status"],
            "reason": batch["reason"],
            "frameset": "",
            "has_truth": False,
            "patches_drawn": 0,
            "patches_kept": 0,
            "input_missing": np.nan,
            "gt_missing": np.nan,
            "gt_median_sigma_m": np.nan,
            "neighbours_left_out": np.nan,
            "leave_target_out_mae_m": np.nan,
        }
        loc = by_target.get(target)
        if loc is not None:
            doc = store.read_json(f"{loc}/frameset.json")
            st = doc["statistics"]
            row.update(
                status=doc["status"],
                reason=doc["reason"],
                frameset=loc,
                has_truth="gt_vs_truth" in st,
                patches_drawn=st["patches_drawn"],
                patches_kept=st["patches_kept"],
                input_missing=st["input_missing"],
                gt_missing=st["gt_missing"],
                gt_median_sigma_m=st.get("gt_median_sigma_m", np.nan),
                neighbours_left_out=neighbours_left_out(doc),
                leave_target_out_mae_m=float(st.get("leave_target_out", {}).get("mae_m", np.nan)),
            )
            npz = store.read_npz(f"{loc}/patches.npz")
            kept, boxes = npz["kept"], npz["all_boxes"]
            miss_in, miss_gt = npz["all_missing_input"], npz["all_missing_gt"]
            kept_index = np.cumsum(kept) - 1
            for i in range(len(kept)):
                patch_rows.append(
                    {
                        "dataset": dataset,
                        "scene": scene,
                        "target": target,
                        "split": doc["split"],
                        "patch": int(kept_index[i]) if kept[i] else -1,
                        "frameset": loc,
                        "y0": int(boxes[i, 0]),
                        "x0": int(boxes[i, 1]),
                        "size": int(boxes[i, 2]),
                        "missing_input": float(miss_in[i]),
                        "missing_gt": float(miss_gt[i]),
                        "kept": bool(kept[i]),
                    }
                )
            for estimate, key, reference in QUALITY_KEYS:
                if key not in st:
                    continue
                for metric, value in st[key].items():
                    quality.append(
                        {
                            "dataset": dataset,
                            "scene": scene,
                            "target": target,
                            "split": doc["split"],
                            "estimate": estimate,
                            "reference": reference,
                            "metric": metric,
                            "unit": unit_of(metric),
                            "value": float(value),
                        }
                    )
        rows.append(row)
    # targets a batch job planned but the scene does not hold (fewer frames than planned)
    for target in sorted(set(batch_records) - index_targets):
        rec = batch_records[target]
        rows.append(
            {
                "dataset": dataset,
                "scene": scene,
                "target": target,
                "frame_id": "",
                "split": rec.get("split", ""),
                "status": rec["status"],
                "reason": rec["reason"],
                "frameset": "",
                "has_truth": False,
                "patches_drawn": 0,
                "patches_kept": 0,
                "input_missing": np.nan,
                "gt_missing": np.nan,
                "gt_median_sigma_m": np.nan,
                "neighbours_left_out": np.nan,
                "leave_target_out_mae_m": np.nan,
            }
        )
    frame_rows = [
        {
            "dataset": dataset,
            "scene": scene,
            "position": p,
            "frame_id": str(frames[p]["frame_id"]),
            "valid": bool(frames[p]["valid"]),
            "reason": frames[p]["reason"],
            "message": frames[p]["message"],
        }
        for p in sorted(frames)
    ]
    return (
        pd.DataFrame(rows, columns=FRAMESET_COLUMNS),
        pd.DataFrame(patch_rows, columns=PATCH_COLUMNS),
        pd.DataFrame(
            quality, columns=["dataset", "scene", "target", "split", "estimate", "reference", "metric", "unit", "value"]
        ),
        pd.DataFrame(frame_rows, columns=FRAME_COLUMNS),
    )


def neighbours_left_out(doc: dict) -> float:
    """How many of a built frame set's neighbours its GT does not use: those the
    registration did not fuse and those the renderer left out (``frameset.json``'s
    ``members``, ``statistics.neighbours_fused`` and ``render_left_out``)."""
    st = doc.get("statistics", {})
    if "neighbours_fused" not in st or "members" not in doc:
        return float("nan")
    return float(len(doc["members"]) - 1 - int(st["neighbours_fused"]) + len(st.get("render_left_out", [])))


class DatasetOutputs(NamedTuple):
    """The files of the dataset assembly (``results/dataset/`` in the workflow); a
    manifest given as None is not written (the workflow writes ``train`` and ``val`` in a
    job of their own, :func:`write_manifests`: adding a test source leaves them, and the
    trainings that read them, untouched)."""

    train: Path | None
    val: Path | None
    test: Path | None
    framesets: Path
    summary: Path
    summary_md: Path
    quality: Path

    @classmethod
    def in_dir(cls, out_dir: str | Path) -> DatasetOutputs:
        d = Path(out_dir)
        return cls(
            d / "train.parquet",
            d / "val.parquet",
            d / "test.parquet",
            d / "framesets.parquet",
            d / "summary.json",
            d / "summary.md",
            d / "gt_quality.csv",
        )


def assemble(
    scene_framesets: list[str | Path],
    scene_patches: list[str | Path],
    scene_quality: list[str | Path],
    scene_frames: list[str | Path],
    index_jsons: list[str | Path],
    out: DatasetOutputs,
) -> dict:
    """Write the dataset manifests from the per-scene summaries.

    Args:
        scene_framesets, scene_patches, scene_quality, scene_frames: the per-scene
            tables of :func:`summarize_scene` (parquet paths).
        index_jsons: the scenes' ``index.json`` (scene problems).
        out: the output paths (:class:`DatasetOutputs`).

    Returns:
        The summary dict (also written as summary.json/.md): pairs and frame sets per
        split, patch counts, every skipped frame set (``framesets_skipped``: dataset,
        scene, target, reason), the frames the batches read (``frames_read``) and every
        one of them found unusable (``frames_skipped``: dataset, scene, position,
        frame_id, reason, message), scene problems, and every scene that contributes
        no frame set with the reason (``scenes_without_framesets``: an empty scene, one
        too short, or one whose every frame set was skipped).
    """
    out = DatasetOutputs(*(None if p is None else Path(p) for p in out))
    for p in out:
        if p is not None:
            p.parent.mkdir(parents=True, exist_ok=True)
    fs = _concat([Path(p) for p in scene_framesets], FRAMESET_COLUMNS)
    patches = _concat([Path(p) for p in scene_patches], PATCH_COLUMNS)
    quality = _concat([Path(p) for p in scene_quality], None)
    frames = _concat([Path(p) for p in scene_frames], FRAME_COLUMNS)
    metas = [json.loads(Path(p).read_text()) for p in index_jsons]

    kept = kept_patches(patches)
    for split in SPLITS:
        if getattr(out, split) is not None:
            kept[kept["split"] == split].reset_index(drop=True).to_parquet(getattr(out, split), index=False)
    fs.to_parquet(out.framesets, index=False)

    if len(quality):
        per_scene = quality.groupby(["dataset", "scene", "estimate", "reference", "metric", "unit"], as_index=False)[
            "value"
        ].mean()
    else:
        per_scene = pd.DataFrame(columns=["dataset", "scene", "estimate", "reference", "metric", "unit", "value"])
    per_scene.to_csv(out.quality, index=False)

    summary = summarise(fs, patches, frames, metas)
    out.summary.write_text(json.dumps(summary, indent=2, sort_keys=True) + "\n")
    out.summary_md.write_text(_summary_md(summary, per_scene))
    return summary


def summarise(fs: pd.DataFrame, patches: pd.DataFrame, frames: pd.DataFrame, metas: list[dict]) -> dict:
    """The summary of :func:`assemble` from the concatenated tables of the scenes (frame
    sets, patches, frames read) and their ``index.json`` documents."""
    kept = kept_patches(patches)
    return {
        "pairs": {s: int((kept["split"] == s).sum()) for s in SPLITS},
        "patches_drawn": int(len(patches)),
        "patches_kept": int(len(kept)),
        "patches_rejected": int(len(patches) - len(kept)),
        "framesets": {s: int(((fs["split"] == s) & (fs["status"] == Status.OK)).sum()) for s in SPLITS},
        "framesets_skipped": [
            {"dataset": r.dataset, "scene": r.scene, "target": int(r.target), "reason": r.reason}
            for r in fs[fs["status"] != Status.OK].itertuples()
        ],
        "scene_problems": [
            {"dataset": m["dataset"], "scene": m["scene"], "problem": p} for m in metas for p in m["problems"]
        ],
        "scenes_without_framesets": scenes_without_framesets(fs, metas),
        "frames_read": int(len(frames)),
        "frames_skipped": [
            {
                "dataset": r.dataset,
                "scene": r.scene,
                "position": int(r.position),
                "frame_id": str(r.frame_id),
                "reason": r.reason,
                "message": r.message,
            }
            for r in frames[~frames["valid"].astype(bool)].itertuples()
        ],
    }


def kept_patches(patches: pd.DataFrame) -> pd.DataFrame:
    """The kept rows of a patch table (the manifests' rows)."""
    # astype: a build that kept nothing has an empty object column, which would select columns
    return patches[patches["kept"].astype(bool)].reset_index(drop=True)


def write_manifests(scene_patches: list[str | Path], out: dict[str, str | Path]) -> dict[str, int]:
    """Write the manifests of the splits in ``out`` (split -> path; one row per kept
    patch pair, as :func:`assemble` writes them) from the per-scene patch tables, in the
    order given. Returns the rows per split."""
    unknown = sorted(set(out) - set(SPLITS))
    if unknown:
        raise ValueError(f"no split {unknown}; the splits are {', '.join(SPLITS)}")
    kept = kept_patches(_concat([Path(p) for p in scene_patches], PATCH_COLUMNS))
    rows = {}
    for split, path in out.items():
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        table = kept[kept["split"] == split].reset_index(drop=True)
        table.to_parquet(path, index=False)
        rows[split] = len(table)
    return rows


def scenes_without_framesets(fs: pd.DataFrame, metas: list[dict]) -> list[dict]:
    """Every scene of ``metas`` (index.json) with no built frame set in ``fs``, with the
    reason: ``empty_scene`` (the source yields no frame), the scene's problems (too
    short, ...), or the reasons its frame sets were skipped (counted)."""
    out = []
    for m in metas:
        rows = fs[(fs["dataset"] == m["dataset"]) & (fs["scene"] == m["scene"])]
        if (rows["status"] == "ok").any():
            continue
        if int(m["n_frames"]) == 0:
            root = (m.get("source") or {}).get("root")
            reason = "empty_scene: the source yields no frame" + (f" (root {root})" if root else "")
        elif len(rows):  # the frame sets' own reasons first; the scene's problems beside them
            counts = rows["reason"].astype(str).str.split(":").str[0].value_counts()
            reason = "every frame set skipped: " + ", ".join(f"{k} ({v})" for k, v in counts.items())
            if m["problems"]:
                reason += "; the scene's problems: " + "; ".join(m["problems"])
        elif m["problems"]:
            reason = "; ".join(m["problems"])
        else:
            reason = "no frame set planned"
        out.append({"dataset": m["dataset"], "scene": m["scene"], "n_frames": int(m["n_frames"]), "reason": reason})
    return out


def _concat(paths: list[Path], columns: list[str] | None) -> pd.DataFrame:
    frames = [pd.read_parquet(p) for p in paths]
    frames = [f for f in frames if len(f)]
    if not frames:
        return pd.DataFrame(columns=columns or [])
    return pd.concat(frames, ignore_index=True)


def _summary_md(summary: dict, quality: pd.DataFrame) -> str:
    lines = ["# Dataset summary", "", "| split | frame sets | patch pairs |", "|---|---:|---:|"]
    for s in SPLITS:
        lines.append(f"| {s} | {summary['framesets'][s]} | {summary['pairs'][s]} |")
    lines += [
        "",
        f"Patches drawn: {summary['patches_drawn']}, kept: {summary['patches_kept']}, "
        f"rejected by the missing filter: {summary['patches_rejected']}.",
        f"Frames read by the frame-set batches: {summary['frames_read']}, unusable (skipped): "
        f"{len(summary['frames_skipped'])}. Frame sets skipped: {len(summary['framesets_skipped'])}.",
        "",
    ]
    if summary["frames_skipped"]:
        lines += ["| dataset | scene | frame | id | reason | message |", "|---|---|---:|---|---|---|"]
        lines += [
            f"| {r['dataset']} | {r['scene']} | {r['position']} | {r['frame_id']} | {r['reason']} | "
            f"{_cell(r['message'])} |"
            for r in summary["frames_skipped"]
        ]
        lines.append("")
    if summary["framesets_skipped"]:
        lines += ["| dataset | scene | target | reason |", "|---|---|---:|---|"]
        lines += [
            f"| {r['dataset']} | {r['scene']} | {r['target']} | {_cell(r['reason'])} |"
            for r in summary["framesets_skipped"]
        ]
        lines.append("")
    if summary["scenes_without_framesets"]:
        lines += ["Scenes without a frame set:", "", "| dataset | scene | frames | reason |", "|---|---|---:|---|"]
        lines += [
            f"| {r['dataset']} | {r['scene']} | {r['n_frames']} | {_cell(r['reason'])} |"
            for r in summary["scenes_without_framesets"]
        ]
        lines.append("")
    if summary["scene_problems"]:
        lines += (
            ["Scene problems:", ""]
            + [f"- {p['dataset']}/{p['scene']}: {p['problem']}" for p in summary["scene_problems"]]
            + [""]
        )
    if len(quality):
        table = quality[quality["metric"].isin(["mae_m", "mae_missing_counted_m", "rmse_m", "completeness"])]
        wide = table.pivot_table(
            index=["dataset", "estimate", "reference"], columns="metric", values="value", aggfunc="mean"
        )
        lines += [
            "## GT quality (mean over scenes; metres, completeness as a fraction)",
            "",
            wide.round(4).reset_index().to_markdown(index=False),
            "",
        ]
    return "\n".join(lines)


def empty_dataset(summary: dict) -> bool:
    """Whether a summary (:func:`assemble`) holds no built frame set in any split."""
    return sum(summary["framesets"].values()) == 0


def reason_tag(reason: str) -> str:
    """The kind of a skip reason: its tag before the first ``:``; for a member frame that
    was unusable (``frame 5: unreadable (...)``), that frame's reason.

    >>> reason_tag("frame 5: unreadable (x.png: truncated)"), reason_tag("split_guard: members in two splits")
    ('an unusable frame (unreadable)', 'split_guard')
    """
    m = re.match(r"frame \d+: (\w+)", reason)
    if m:
        return f"an unusable frame ({m.group(1)})"
    return reason.split(":")[0].strip() or "unknown"


def reason_counts(records: list[dict], top: int = 3) -> list[tuple[str, int, dict]]:
    """The most common reasons (the tag before the first ``:``) of skipped records, each
    with its count and its first record (an example), most common first."""
    counts: dict[str, list] = {}
    for r in records:
        counts.setdefault(reason_tag(str(r.get("reason", ""))), [0, r])[0] += 1
    ranked = sorted(counts.items(), key=lambda kv: (-kv[1][0], kv[0]))
    return [(tag, n, first) for tag, (n, first) in ranked[:top]]


def empty_dataset_message(summary: dict) -> str:
    """Why a dataset holds no frame set, in one paragraph: the scenes without one and
    their reasons, and how to keep an empty dataset anyway."""
    scenes = summary.get("scenes_without_framesets", [])
    why = "; ".join(f"{r['dataset']}/{r['scene']} ({r['n_frames']} frames): {r['reason']}" for r in scenes[:5])
    if len(scenes) > 5:
        why += f"; and {len(scenes) - 5} more scenes"
    return (
        "the dataset is empty: no frame set was built"
        + (f" ({why})" if why else "")
        + ". Every skipped frame and frame set is listed in the summary above (and in this log). "
        "Fix the sources or the settings, or set dataset.allow_empty: true to keep an empty dataset"
    )


def console_summary(summary: dict, summary_md: str | Path | None = None) -> list[str]:
    """The lines a build prints at its end: frame sets built and skipped with the top
    reasons (one example each, naming the file), frames unusable, patch pairs kept, and
    where the full summary is (:func:`console_lines` of the summary's counts)."""
    skipped = summary["framesets_skipped"]
    return console_lines(
        summary["framesets"],
        len(skipped),
        reason_counts(skipped),
        len(summary["frames_skipped"]),
        summary["frames_read"],
        summary["pairs"],
        summary["patches_rejected"],
        summary.get("scenes_without_framesets", []),
        summary_md,
    )


def console_lines(
    framesets: dict[str, int],
    n_skipped: int,
    top_reasons: list[tuple[str, int, dict]],
    frames_unusable: int,
    frames_read: int,
    pairs: dict[str, int],
    patches_rejected: int,
    scenes_without_framesets: list[dict],
    summary_md: str | Path | None = None,
) -> list[str]:
    """The lines of :func:`console_summary` from the counts alone, for a caller that
    counts the scenes' tables without building the summary's per-frame-set records.

    Args:
        framesets, pairs: built frame sets and kept patch pairs per split.
        top_reasons: the top skip reasons as :func:`reason_counts` gives them.
        scenes_without_framesets: the first of them at least (three are printed).
    """
    fs = framesets
    lines = [
        f"depthgt: {sum(fs.values())} frame sets built ("
        + ", ".join(f"{s} {fs[s]}" for s in SPLITS)
        + f"), {n_skipped} skipped; {frames_unusable} of {frames_read} frames read "
        f"unusable; {sum(pairs.values())} patch pairs kept ("
        + ", ".join(f"{s} {pairs[s]}" for s in SPLITS)
        + f"), {patches_rejected} rejected by the missing filter"
    ]
    for tag, n, first in top_reasons:
        example = f"{first['dataset']}/{first['scene']}/{int(first['target']):06d}: {first['reason']}"
        if len(example) > 300:
            example = example[:297] + "..."
        lines.append(f"depthgt:   {n} frame sets skipped for {tag}, e.g. {example}")
    for r in scenes_without_framesets[:3]:
        lines.append(f"depthgt:   scene {r['dataset']}/{r['scene']} has no frame set: {r['reason']}")
    if summary_md is not None:
        lines.append(f"depthgt: every skipped frame and frame set with its reason: {Path(summary_md).absolute()}")
    return lines


def _cell(text: str) -> str:
    """``text`` fit for a markdown table cell (a ``|`` would end the cell)."""
    return str(text).replace("|", "\\|").replace("\n", " ")
