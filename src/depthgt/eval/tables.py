"""The paper's metric tables from tidy long tables (CSV + Markdown, units in headers).

Inputs are long tables (one row per dataset, scene, frame, method, reference, metric
with its unit and value: :data:`depthgt.eval.evaluate.EVAL_COLUMNS`). Every table
averages per-frame values over the frames of a group (the mean of per-frame RMSE, not
a pooled RMSE) and states its conventions in a caption written on top of the
Markdown file:

* ``table1``: SSIM and L_S between a GT and the input depth, for depthgt's GT and the
  global-reconstruction (TSDF) GT (paper Table 1).
* ``table2``: every method on held-out *real* frames against depthgt's GT (paper
  Table 2); when no real source is configured it holds one row saying so.
* ``table3``: every method on held-out *synthetic* frames against the true clean
  depth (paper Table 3's role), input with Kinect-style noise.
* ``table_gt_quality``: the GTs' own error against the truth (synthetic data).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd

from depthgt import registry
from depthgt.eval.metrics import ls_distance, ssim_depth, unit_of
from depthgt.gt import store
from depthgt.status import Status

__all__ = [
    "COLUMN_LABELS",
    "gt_vs_input_long",
    "rde_quality_long",
    "method_table",
    "table1",
    "table2",
    "table3",
    "table_gt_quality",
    "write_table",
    "TABLE1_CAPTION",
    "TABLE2_CAPTION",
    "TABLE3_CAPTION",
    "GT_QUALITY_CAPTION",
]

# metric -> column header with its unit
COLUMN_LABELS = {
    "ssim": "SSIM (unitless)",
    "rmse_m": "RMSE (m)",
    "mae_m": "MAE (m)",
    "rmse_missing_counted_m": "RMSE, missing counted (m)",
    "mae_missing_counted_m": "MAE, missing counted (m)",
    "completeness": "completeness (fraction)",
    "ls": "L_S (m^2/px^2)",
}
METHOD_METRICS = ["ssim", "rmse_m", "mae_m", "rmse_missing_counted_m", "mae_missing_counted_m", "completeness"]
QUALITY_METRICS = ["mae_m", "rmse_m", "mae_missing_counted_m", "rmse_missing_counted_m", "completeness"]
GT_LABELS = {"gt": "depthgt GT (local frame set)", "rde": "global reconstruction GT (TSDF)",
             "input": "input (raw depth)"}

_CONVENTIONS = (
    "RMSE and MAE in metres over pixels where the reference is valid and the prediction is valid; the "
    "'missing counted' variants count a missing prediction as predicting 0 m over all reference-valid pixels; "
    "completeness = share of reference-valid pixels the prediction covers. SSIM on depth/10 m with data_range 1, "
    "11x11 Gaussian window, sigma 1.5, averaged over pixels where both images are valid. Values are means over "
    "frames of per-frame values; 'frames' counts them."
)
TABLE1_CAPTION = (
    "Table 1: similarity of a GT to the input depth (paper Table 1): SSIM (depth/10 m, data_range 1, 11x11 Gaussian "
    "window, sigma 1.5) and L_S (paper eq. 6, 5x5 window, m^2/px^2), over pixels valid in both, mean over all runnable "
    "frame sets. depthgt's GT fuses the 7-frame local set; the global-reconstruction GT is a TSDF of the whole "
    "stream (global poses) ray-cast at each frame. Higher SSIM / lower L_S = closer in structure to the input."
)
TABLE2_CAPTION = ("Table 2 (real data): methods on held-out real test frames against depthgt's GT (the paper's "
                  "protocol). " + _CONVENTIONS)
TABLE3_CAPTION = ("Table 3 (synthetic data): methods on held-out synthetic test frames against the true clean depth; "
                  "the input carries Kinect-style noise. " + _CONVENTIONS)
GT_QUALITY_CAPTION = (
    "GT quality (synthetic data, what the paper could not measure): the error of each GT, and of the raw input, "
    "against the true clean depth, mean over frame sets. MAE/RMSE in metres over pixels valid in both; 'missing "
    "counted' counts an empty GT pixel as 0 m over all truth-valid pixels; completeness = share of truth-valid "
    "pixels the estimate covers."
)
NO_REAL_NOTE = "no real source (ScanNet, 7-Scenes, TUM) with held-out test frames is configured: Table 2 is empty"
NO_SYNTH_NOTE = "no synthetic source with held-out test frames and clean truth is configured: Table 3 is empty"


def gt_vs_input_long(framesets: pd.DataFrame, rde_framesets: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per-frame SSIM and L_S of each GT against the input (long table).

    Args:
        framesets: depthgt's frame-set table (``frameset``, ``status`` ...).
        rde_framesets: the RDE table (``frameset``, ``rde``: locations), or None.

    Returns:
        columns dataset, scene, target, gt (``gt`` | ``rde``), metric, unit, value.
    """
    jobs = []
    for rec in framesets[(framesets["status"] == Status.OK) & (framesets["frameset"] != "")].itertuples():
        jobs.append((rec.dataset, rec.scene, int(rec.target), "gt", rec.frameset, rec.frameset))
    if rde_framesets is not None and len(rde_framesets):
        for rec in rde_framesets[(rde_framesets["status"] == Status.OK) & (rde_framesets["rde"] != "")].itertuples():
            jobs.append((rec.dataset, rec.scene, int(rec.target), "rde", rec.rde, rec.frameset))
    rows = []
    for dataset, scene, target, which, gt_loc, fs_loc in jobs:
        gt = store.read_exr_member(f"{gt_loc}/gt.exr")["Z"]
        inp = store.read_exr_member(f"{fs_loc}/input.exr")["Z"]
        for metric, value in (("ssim", ssim_depth(gt, inp)), ("ls", ls_distance(gt, inp))):
            rows.append({"dataset": dataset, "scene": scene, "target": target, "gt": which, "metric": metric,
                         "unit": unit_of(metric), "value": float(value)})
    return pd.DataFrame(rows, columns=["dataset", "scene", "target", "gt", "metric", "unit", "value"])


def rde_quality_long(rde_framesets: pd.DataFrame) -> pd.DataFrame:
    """Per-scene mean error of the RDE GT against the truth, in gt_quality.csv's form
    (dataset, scene, estimate='rde', reference='truth', metric, unit, value)."""
    rows = []
    ok = rde_framesets[(rde_framesets["status"] == Status.OK) & (rde_framesets["rde"] != "")] if len(rde_framesets) else rde_framesets
    for rec in ok.itertuples():
        st = store.read_json(f"{rec.rde}/frameset.json")["statistics"]
        for metric, value in st.get("rde_vs_truth", {}).items():
            rows.append({"dataset": rec.dataset, "scene": rec.scene, "estimate": "rde", "reference": "truth",
                         "metric": metric, "unit": unit_of(metric), "value": float(value)})
    cols = ["dataset", "scene", "estimate", "reference", "metric", "unit", "value"]
    long = pd.DataFrame(rows, columns=cols)
    if long.empty:
        return long
    return long.groupby(cols[:-1], as_index=False)["value"].mean()


def _ordered(methods) -> list[str]:
    """Registry order (:data:`depthgt.registry.METHODS`), unregistered names last."""
    known = [m for m in registry.METHODS if m in set(methods)]
    return known + sorted(set(methods) - set(known))


def method_table(ev: pd.DataFrame, datasets: list[str], reference: str, note: str) -> pd.DataFrame:
    """Wide table (one row per dataset and method) of :data:`METHOD_METRICS` from an
    evaluation long table, restricted to ``datasets`` and ``reference``; a one-row
    table holding ``note`` when nothing qualifies."""
    cols = ["dataset", "method", "frames"] + [COLUMN_LABELS[m] for m in METHOD_METRICS]
    if ev.empty or not datasets:
        return pd.DataFrame([{"note": note}])
    sub = ev[ev["dataset"].isin(datasets) & (ev["reference"] == reference) & ev["metric"].isin(METHOD_METRICS)]
    if sub.empty:
        return pd.DataFrame([{"note": note}])
    bad = sub.groupby(["metric"])["unit"].nunique()
    if (bad > 1).any():
        raise ValueError(f"evaluation table: metrics {list(bad[bad > 1].index)} come with several units")
    wide = sub.pivot_table(index=["dataset", "method"], columns="metric", values="value", aggfunc="mean")
    frames = sub.drop_duplicates(["dataset", "method", "scene", "target"]).groupby(["dataset", "method"]).size().rename("frames")
    wide = wide.join(frames).reset_index()
    wide["_order"] = wide["method"].map({m: i for i, m in enumerate(_ordered(wide["method"]))})
    wide = wide.sort_values(["dataset", "_order"]).drop(columns="_order")
    wide["method"] = wide["method"].map(registry.label)
    wide = wide.rename(columns=COLUMN_LABELS)
    for c in cols:
        if c not in wide.columns:
            wide[c] = np.nan
    return wide[cols].reset_index(drop=True)


def _kind_datasets(ev: pd.DataFrame, kinds: Mapping[str, str], synthetic: bool) -> list[str]:
    names = sorted(set(ev["dataset"])) if not ev.empty else []
    return [d for d in names if (kinds.get(d) == "synthetic") == synthetic]


def table2(ev: pd.DataFrame, kinds: Mapping[str, str]) -> pd.DataFrame:
    """Paper Table 2: real test frames, reference = depthgt's GT. ``kinds``: dataset -> source kind."""
    return method_table(ev, _kind_datasets(ev, kinds, synthetic=False), "gt", NO_REAL_NOTE)


def table3(ev: pd.DataFrame, kinds: Mapping[str, str]) -> pd.DataFrame:
    """Paper Table 3's role: synthetic test frames, reference = the clean truth."""
    return method_table(ev, _kind_datasets(ev, kinds, synthetic=True), "truth", NO_SYNTH_NOTE)


def table1(long: pd.DataFrame) -> pd.DataFrame:
    """Paper Table 1 from :func:`gt_vs_input_long`: one row per dataset and GT."""
    if long.empty:
        return pd.DataFrame([{"note": "no runnable frame set: Table 1 is empty"}])
    wide = long.pivot_table(index=["dataset", "gt"], columns="metric", values="value", aggfunc="mean")
    frames = long.drop_duplicates(["dataset", "gt", "scene", "target"]).groupby(["dataset", "gt"]).size().rename("frames")
    wide = wide.join(frames).reset_index()
    wide["gt"] = wide["gt"].map(lambda g: GT_LABELS.get(g, g))
    wide = wide.rename(columns={"gt": "GT", **COLUMN_LABELS})
    return wide[["dataset", "GT", "frames", COLUMN_LABELS["ssim"], COLUMN_LABELS["ls"]]]


def table_gt_quality(quality: pd.DataFrame, rde_quality: pd.DataFrame | None = None) -> pd.DataFrame:
    """The GTs' (and the input's) error against the truth, per dataset.

    Args:
        quality: ``gt_quality.csv`` (dataset, scene, estimate, reference, metric, unit, value; per-scene means).
        rde_quality: :func:`rde_quality_long` (same columns), or None.
    """
    q = pd.concat([quality, rde_quality], ignore_index=True) if rde_quality is not None and len(rde_quality) else quality
    q = q[(q["reference"] == "truth") & q["metric"].isin(QUALITY_METRICS)] if len(q) else q
    if q.empty:
        return pd.DataFrame([{"note": "no source with clean truth is configured: the GT's own error cannot be measured"}])
    wide = q.pivot_table(index=["dataset", "estimate"], columns="metric", values="value", aggfunc="mean")
    scenes = q.groupby(["dataset", "estimate"])["scene"].nunique().rename("scenes")
    wide = wide.join(scenes).reset_index()
    order = {"gt": 0, "rde": 1, "input": 2}
    wide = wide.sort_values(["dataset", "estimate"], key=lambda s: s.map(order).fillna(9) if s.name == "estimate" else s)
    wide["estimate"] = wide["estimate"].map(lambda g: GT_LABELS.get(g, g))
    wide = wide.rename(columns=COLUMN_LABELS)
    cols = ["dataset", "estimate", "scenes"] + [COLUMN_LABELS[m] for m in QUALITY_METRICS]
    for c in cols:
        if c not in wide.columns:
            wide[c] = np.nan
    return wide[cols].reset_index(drop=True)


def write_table(table: pd.DataFrame, csv_path: str | Path, md_path: str | Path, caption: str,
                digits: int = 4) -> tuple[Path, Path]:
    """Write ``csv_path`` (full precision) and ``md_path`` (caption, then the table with
    ``digits`` significant digits). Returns both paths."""
    csv_path, md_path = Path(csv_path), Path(md_path)
    for p in (csv_path, md_path):
        p.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(csv_path, index=False)
    md = table.to_markdown(index=False, floatfmt=f".{digits}g")
    md_path.write_text(f"{caption}\n\n{md}\n")
    return csv_path, md_path
