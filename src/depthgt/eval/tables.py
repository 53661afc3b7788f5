"""The paper's metric tables from tidy long tables (CSV + Markdown, units in headers).

Inputs are long tables (one row per dataset, scene, frame, method, reference, metric
with its unit and value: :data:`depthgt.eval.evaluate.EVAL_COLUMNS`). Every table
averages per-frame values over the frames of a group (the mean of per-frame RMSE, not
a pooled RMSE) and states its conventions in a caption written on top of the
Markdown file:

* ``table1``: SSIM and L_S between a GT and the input depth, for depthgt's GT and the
  global-reconstruction (TSDF) GT (paper Table 1).
* ``table2``: every method on held-out *real* frames, one block (column
  ``reference``) per reference: depthgt's GT (paper Table 2's protocol), the
  neighbours-only render of the target and the global-reconstruction (TSDF) GT
  (:mod:`depthgt.gt.references`); when no real source is configured it holds one row
  saying so.
* ``table3``: every method on held-out *synthetic* frames against the true clean
  depth (paper Table 3's role), input with Kinect-style noise.
* ``table2_paired``, ``table3_paired``: LapDEN against every other method of those
  tables, the mean per-frame difference over the same frames.
* ``table_gt_quality``: the GTs' own error against the truth (synthetic data).

The method tables' columns each have one pixel set for every method
(:data:`METHOD_METRICS`): the *filling* task (every reference-valid pixel, a missing
prediction counted as predicting 0 m) and the *denoising* task (the pixels where the
raw input and the reference are both valid, missing predictions counted likewise).
Every mean comes with its 95 % percentile bootstrap interval over frames
(:mod:`depthgt.eval.bootstrap`: fixed seed, the same draws for every row of a dataset)
and the number of frames. In the CSV a metric's column holds the mean and the columns
``"<column> 95% low"``, ``"<column> 95% high"`` its interval; the Markdown writes
``mean [low, high]``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from depthgt import registry
from depthgt.eval.bootstrap import BOOTSTRAP_RESAMPLES, BOOTSTRAP_SEED, bootstrap_means
from depthgt.eval.metrics import ls_distance, ssim_depth, unit_of
from depthgt.gt import store
from depthgt.status import Status

__all__ = [
    "COLUMN_LABELS",
    "gt_vs_input_long",
    "rde_quality_long",
    "method_table",
    "paired_table",
    "table1",
    "table2",
    "table3",
    "table2_paired",
    "table3_paired",
    "table_gt_quality",
    "write_table",
    "markdown_view",
    "TABLE1_CAPTION",
    "TABLE2_CAPTION",
    "table2_caption",
    "references_in",
    "TABLE3_CAPTION",
    "TABLE2_PAIRED_CAPTION",
    "TABLE3_PAIRED_CAPTION",
    "GT_QUALITY_CAPTION",
    "PAIRED_BASE",
    "REAL_REFERENCES",
    "REFERENCE_LABELS",
    "LOW",
    "HIGH",
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
    "ssim_missing_counted": "SSIM, filling (unitless)",
    "rmse_input_valid_m": "RMSE, denoising (m)",
    "mae_input_valid_m": "MAE, denoising (m)",
}
# the method tables' columns: one pixel set per column, the same for every method
METHOD_LABELS = {
    "ssim_missing_counted": "SSIM, filling (unitless)",
    "rmse_missing_counted_m": "RMSE, filling (m)",
    "mae_missing_counted_m": "MAE, filling (m)",
    "rmse_input_valid_m": "RMSE, denoising (m)",
    "mae_input_valid_m": "MAE, denoising (m)",
    "completeness": "completeness (fraction)",
}
METHOD_METRICS = list(METHOD_LABELS)
LOW, HIGH = " 95% low", " 95% high"  # suffixes of an interval's columns
PAIRED_BASE = "lapden"  # the method the paired tables compare with every other
QUALITY_METRICS = ["mae_m", "rmse_m", "mae_missing_counted_m", "rmse_missing_counted_m", "completeness"]
GT_LABELS = {
    "gt": "depthgt GT (local frame set)",
    "rde": "global reconstruction GT (TSDF)",
    "input": "input (raw depth)",
}

_CONVENTIONS = (
    "Each column has one pixel set, the same for every method. Filling: every reference-valid pixel, a missing "
    "prediction counted as predicting 0 m (its error is the reference depth). Denoising: the pixels where the raw "
    "input and the reference are both valid, a missing prediction counted likewise. RMSE and MAE in metres, computed "
    "per image and then averaged over frames (the mean of per-frame values); completeness = share of reference-valid "
    "pixels the prediction covers. SSIM on depth/10 m with data_range 1, 11x11 Gaussian window, sigma 1.5 (kornia), "
    "a missing prediction entering the windows as 0 m, the SSIM map averaged over every reference-valid pixel. "
    f"Brackets: 95 % percentile bootstrap interval over frames ({BOOTSTRAP_RESAMPLES} resamples of the frames with "
    f"replacement, numpy default_rng seed {BOOTSTRAP_SEED}, the same resamples for every row of a dataset); 'frames' "
    "counts the frames averaged."
)
_PAIRED = (
    "Paired comparison: per frame, LapDEN's value minus the other method's on the same frame and pixel set, then the "
    "mean over the frames both have and its 95 % percentile bootstrap interval over those frames "
    f"({BOOTSTRAP_RESAMPLES} resamples, seed {BOOTSTRAP_SEED}). For RMSE and MAE a negative difference means LapDEN "
    "has the lower error, for SSIM and completeness a positive one that LapDEN scores higher; an interval that "
    "excludes 0 separates the two methods on these frames. Pixel sets, units and averaging as in the method table. "
)
# Table 2's references (real data), in the order of its blocks
REAL_REFERENCES = ("gt", "neighbours", "tsdf")
REFERENCE_LABELS = {"gt": "depthgt GT", "neighbours": "neighbours only", "tsdf": "TSDF GT"}
# what each reference of Table 2 is, for the captions (only the references a table holds are described)
REFERENCE_TEXT = {
    "gt": "'depthgt GT': the frame set's GT, the paper's protocol; it favours LapDEN, which was trained to "
    "reproduce depthgt's GT (of other scenes), and it fuses the target's own depth, so it also favours methods "
    "that keep the input. ",
    "neighbours": "'neighbours only': the frame set's fused neighbours rendered into the target with the build's "
    "poses, without the target's own depth (the leave-target-out check at every pixel): independent of the "
    "target's sensor noise, no method was trained on it; empty where no neighbour sees. ",
    "tsdf": "'TSDF GT': the global reconstruction of the whole recording ray-cast at the target (the GT RDE is "
    "trained on, of other scenes; it holds the target's depth among all the frames'), so it favours RDE as "
    "depthgt's GT favours LapDEN. ",
}
_COUNT = {0: "no reference", 1: "one reference", 2: "two references", 3: "three references"}


def _references_text(references: tuple[str, ...]) -> str:
    blocks = "One block per reference (column 'reference'). " if len(references) > 1 else ""
    return blocks + "".join(REFERENCE_TEXT[r] for r in references)


def references_in(table: pd.DataFrame) -> tuple[str, ...]:
    """The references of :data:`REAL_REFERENCES` a Table 2 (or its paired table) holds,
    from its ``reference`` column."""
    labels = set(table["reference"]) if "reference" in table else set()
    return tuple(r for r in REAL_REFERENCES if REFERENCE_LABELS[r] in labels)


def table2_caption(references: tuple[str, ...] = REAL_REFERENCES, paired: bool = False, base: str = "LapDEN") -> str:
    """Table 2's caption, describing exactly ``references`` (:func:`references_in`: the
    references the table holds; `depthgt evaluate` scores against depthgt's GT only
    where the build has no other)."""
    if paired:
        head = f"Table 2, paired (real data, {_COUNT[len(references)]} of Table 2): {base} minus every other method. "
        return head + _references_text(references) + _PAIRED.replace("LapDEN", base)
    head = f"Table 2 (real data): methods on held-out real test frames against {_COUNT[len(references)]}. "
    return head + _references_text(references) + _CONVENTIONS


TABLE1_CAPTION = (
    "Table 1: similarity of a GT to the input depth (paper Table 1): SSIM (depth/10 m, data_range 1, 11x11 Gaussian "
    "window, sigma 1.5) and L_S (paper eq. 6, 5x5 window, m^2/px^2), over pixels valid in both, mean over all runnable "
    "frame sets. depthgt's GT fuses the 7-frame local set; the global-reconstruction GT is a TSDF of the whole "
    "stream (global poses) ray-cast at each frame. Higher SSIM / lower L_S = closer in structure to the input."
)
TABLE2_CAPTION = table2_caption()
TABLE3_CAPTION = (
    "Table 3 (synthetic data): methods on held-out synthetic test frames against the true clean depth; "
    "the input carries Kinect-style noise. " + _CONVENTIONS
)
TABLE2_PAIRED_CAPTION = table2_caption(paired=True)
TABLE3_PAIRED_CAPTION = (
    "Table 3, paired (synthetic data, reference: the true clean depth): LapDEN minus every other method. " + _PAIRED
)
GT_QUALITY_CAPTION = (
    "GT quality (synthetic data, what the paper could not measure): the error of each GT, and of the raw input, "
    "against the true clean depth, mean over frame sets. MAE/RMSE in metres over pixels valid in both; 'missing "
    "counted' counts an empty GT pixel as 0 m over all truth-valid pixels; completeness = share of truth-valid "
    "pixels the estimate covers."
)
NO_REAL_NOTE = "no real source (ScanNet, 7-Scenes, TUM) with held-out test frames is configured: Table 2 is empty"
NO_SYNTH_NOTE = "no synthetic source with held-out test frames and clean truth is configured: Table 3 is empty"
NO_BASE_NOTE = f"no paired comparison: {PAIRED_BASE!r} and another method are not both evaluated on these frames"


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
            rows.append(
                {
                    "dataset": dataset,
                    "scene": scene,
                    "target": target,
                    "gt": which,
                    "metric": metric,
                    "unit": unit_of(metric),
                    "value": float(value),
                }
            )
    return pd.DataFrame(rows, columns=["dataset", "scene", "target", "gt", "metric", "unit", "value"])


def rde_quality_long(rde_framesets: pd.DataFrame) -> pd.DataFrame:
    """Per-scene mean error of the RDE GT against the truth, in gt_quality.csv's form
    (dataset, scene, estimate='rde', reference='truth', metric, unit, value)."""
    rows = []
    ok = (
        rde_framesets[(rde_framesets["status"] == Status.OK) & (rde_framesets["rde"] != "")]
        if len(rde_framesets)
        else rde_framesets
    )
    for rec in ok.itertuples():
        st = store.read_json(f"{rec.rde}/frameset.json")["statistics"]
        for metric, value in st.get("rde_vs_truth", {}).items():
            rows.append(
                {
                    "dataset": rec.dataset,
                    "scene": rec.scene,
                    "estimate": "rde",
                    "reference": "truth",
                    "metric": metric,
                    "unit": unit_of(metric),
                    "value": float(value),
                }
            )
    cols = ["dataset", "scene", "estimate", "reference", "metric", "unit", "value"]
    long = pd.DataFrame(rows, columns=cols)
    if long.empty:
        return long
    return long.groupby(cols[:-1], as_index=False)["value"].mean()


def _ordered(methods) -> list[str]:
    """Registry order (:data:`depthgt.registry.METHODS`), unregistered names last."""
    known = [m for m in registry.METHODS if m in set(methods)]
    return known + sorted(set(methods) - set(known))


def _frame_matrix(ev: pd.DataFrame, datasets: list[str], reference: str) -> pd.DataFrame | None:
    """Per-frame values of :data:`METHOD_METRICS` restricted to ``datasets`` and
    ``reference``: index (dataset, scene, target), columns (method, metric); None when
    nothing qualifies. Raises ValueError when a metric comes with several units."""
    if ev.empty or not datasets:
        return None
    sub = ev[ev["dataset"].isin(datasets) & (ev["reference"] == reference) & ev["metric"].isin(METHOD_METRICS)]
    if sub.empty:
        return None
    bad = sub.groupby(["metric"])["unit"].nunique()
    if (bad > 1).any():
        raise ValueError(f"evaluation table: metrics {list(bad[bad > 1].index)} come with several units")
    dup = sub.duplicated(["dataset", "scene", "target", "method", "metric"])
    if dup.any():
        first = sub[dup].iloc[0]
        raise ValueError(
            f"evaluation table: {int(dup.sum())} duplicate rows, e.g. {first['dataset']}/{first['scene']}/"
            f"{first['target']} {first['method']} {first['metric']} (a method evaluated twice?)"
        )
    return sub.pivot(index=["dataset", "scene", "target"], columns=["method", "metric"], values="value")


def _interval_columns(labels: list[str]) -> list[str]:
    return [c for label in labels for c in (label, label + LOW, label + HIGH)]


def _rows_with_intervals(values: pd.DataFrame, keys: list[tuple], resamples: int, seed: int) -> list[dict]:
    """One dict per key of ``keys`` (a method or a comparison) from ``values`` (frames x
    (key, metric)): the frames, the mean, low and high of each metric (all columns
    resampled with the same draws)."""
    cols = [(k, m) for k in keys for m in METHOD_METRICS]
    v = values.reindex(columns=pd.MultiIndex.from_tuples(cols)).to_numpy(dtype=np.float64)
    est = bootstrap_means(v, resamples=resamples, seed=seed)
    rows = []
    for i, _key in enumerate(keys):
        part = slice(i * len(METHOD_METRICS), (i + 1) * len(METHOD_METRICS))
        # the frames a row averages: those with any value (each column's own NaNs aside)
        row = {"frames": int(np.isfinite(v[:, part]).any(axis=1).sum())}
        for m, mean, lo, hi in zip(METHOD_METRICS, est.mean[part], est.low[part], est.high[part]):
            label = METHOD_LABELS[m]
            row.update({label: mean, label + LOW: lo, label + HIGH: hi})
        rows.append(row)
    return rows


def method_table(
    ev: pd.DataFrame,
    datasets: list[str],
    reference: str,
    note: str,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> pd.DataFrame:
    """Wide table (one row per dataset and method) of :data:`METHOD_METRICS` from an
    evaluation long table, restricted to ``datasets`` and ``reference``: the mean over
    frames of each metric with its bootstrap interval (columns ``label``, ``label +
    LOW``, ``label + HIGH``) and the frames; a one-row table holding ``note`` when
    nothing qualifies."""
    wide = _frame_matrix(ev, datasets, reference)
    if wide is None:
        return pd.DataFrame([{"note": note}])
    out = []
    for dataset in sorted(set(wide.index.get_level_values("dataset"))):
        part = wide.xs(dataset, level="dataset")
        methods = _ordered(set(part.columns.get_level_values("method")))
        for method, row in zip(methods, _rows_with_intervals(part, methods, resamples, seed)):
            out.append({"dataset": dataset, "method": registry.label(method), **row})
    cols = ["dataset", "method", "frames"] + _interval_columns(list(METHOD_LABELS.values()))
    return pd.DataFrame(out, columns=cols)


def paired_table(
    ev: pd.DataFrame,
    datasets: list[str],
    reference: str,
    note: str,
    base: str = PAIRED_BASE,
    resamples: int = BOOTSTRAP_RESAMPLES,
    seed: int = BOOTSTRAP_SEED,
) -> pd.DataFrame:
    """``base`` against every other method, per dataset: the mean over frames of the
    per-frame difference (base minus other) of each metric of :data:`METHOD_METRICS`,
    with its bootstrap interval over the frames both have (the draws of
    :func:`method_table`); ``note`` (or why no comparison exists) when nothing qualifies."""
    wide = _frame_matrix(ev, datasets, reference)
    if wide is None:
        return pd.DataFrame([{"note": note}])
    out = []
    for dataset in sorted(set(wide.index.get_level_values("dataset"))):
        part = wide.xs(dataset, level="dataset")
        methods = _ordered(set(part.columns.get_level_values("method")))
        if base not in methods:
            continue
        others = [m for m in methods if m != base]
        diffs = pd.concat({o: part[base] - part[o] for o in others}, axis=1) if others else None
        if diffs is None:
            continue
        for other, row in zip(others, _rows_with_intervals(diffs, others, resamples, seed)):
            out.append({"dataset": dataset, "comparison": f"{registry.label(base)} - {registry.label(other)}", **row})
    if not out:
        return pd.DataFrame([{"note": NO_BASE_NOTE}])
    cols = ["dataset", "comparison", "frames"] + _interval_columns(list(METHOD_LABELS.values()))
    return pd.DataFrame(out, columns=cols)


def _kind_datasets(ev: pd.DataFrame, kinds: Mapping[str, str], synthetic: bool) -> list[str]:
    names = sorted(set(ev["dataset"])) if not ev.empty else []
    return [d for d in names if (kinds.get(d) == "synthetic") == synthetic]


def _per_reference(build, ev: pd.DataFrame, datasets: list[str]) -> pd.DataFrame:
    """``build(ev, datasets, reference, note)`` for each of :data:`REAL_REFERENCES`
    that has values, stacked with a column ``reference`` (its label) after
    ``dataset``; the depthgt-GT table (or its note) when none has."""
    blocks = []
    for ref in REAL_REFERENCES:
        t = build(ev, datasets, ref, NO_REAL_NOTE)
        if "note" in t.columns:
            continue
        t.insert(1, "reference", REFERENCE_LABELS[ref])
        blocks.append(t)
    if not blocks:
        return build(ev, datasets, "gt", NO_REAL_NOTE)
    return pd.concat(blocks, ignore_index=True)


def table2(ev: pd.DataFrame, kinds: Mapping[str, str]) -> pd.DataFrame:
    """Paper Table 2: real test frames, one block per reference of
    :data:`REAL_REFERENCES` present (depthgt's GT, the neighbours-only render, the TSDF
    GT). ``kinds``: dataset -> source kind."""
    return _per_reference(method_table, ev, _kind_datasets(ev, kinds, synthetic=False))


def table3(ev: pd.DataFrame, kinds: Mapping[str, str]) -> pd.DataFrame:
    """Paper Table 3's role: synthetic test frames, reference = the clean truth."""
    return method_table(ev, _kind_datasets(ev, kinds, synthetic=True), "truth", NO_SYNTH_NOTE)


def table2_paired(ev: pd.DataFrame, kinds: Mapping[str, str]) -> pd.DataFrame:
    """Table 2's frames, LapDEN minus every other method (:func:`paired_table`), one
    block per reference."""
    return _per_reference(paired_table, ev, _kind_datasets(ev, kinds, synthetic=False))


def table3_paired(ev: pd.DataFrame, kinds: Mapping[str, str]) -> pd.DataFrame:
    """Table 3's frames and reference, LapDEN minus every other method (:func:`paired_table`)."""
    return paired_table(ev, _kind_datasets(ev, kinds, synthetic=True), "truth", NO_SYNTH_NOTE)


def table1(long: pd.DataFrame) -> pd.DataFrame:
    """Paper Table 1 from :func:`gt_vs_input_long`: one row per dataset and GT."""
    if long.empty:
        return pd.DataFrame([{"note": "no runnable frame set: Table 1 is empty"}])
    wide = long.pivot_table(index=["dataset", "gt"], columns="metric", values="value", aggfunc="mean")
    frames = (
        long.drop_duplicates(["dataset", "gt", "scene", "target"]).groupby(["dataset", "gt"]).size().rename("frames")
    )
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
    q = (
        pd.concat([quality, rde_quality], ignore_index=True)
        if rde_quality is not None and len(rde_quality)
        else quality
    )
    q = q[(q["reference"] == "truth") & q["metric"].isin(QUALITY_METRICS)] if len(q) else q
    if q.empty:
        return pd.DataFrame(
            [{"note": "no source with clean truth is configured: the GT's own error cannot be measured"}]
        )
    wide = q.pivot_table(index=["dataset", "estimate"], columns="metric", values="value", aggfunc="mean")
    scenes = q.groupby(["dataset", "estimate"])["scene"].nunique().rename("scenes")
    wide = wide.join(scenes).reset_index()
    order = {"gt": 0, "rde": 1, "input": 2}
    wide = wide.sort_values(
        ["dataset", "estimate"], key=lambda s: s.map(order).fillna(9) if s.name == "estimate" else s
    )
    wide["estimate"] = wide["estimate"].map(lambda g: GT_LABELS.get(g, g))
    wide = wide.rename(columns=COLUMN_LABELS)
    cols = ["dataset", "estimate", "scenes"] + [COLUMN_LABELS[m] for m in QUALITY_METRICS]
    for c in cols:
        if c not in wide.columns:
            wide[c] = np.nan
    return wide[cols].reset_index(drop=True)


def markdown_view(table: pd.DataFrame, digits: int = 4) -> pd.DataFrame:
    """The table as the Markdown shows it: a column with interval columns (``LOW``,
    ``HIGH``) becomes one text column ``mean [low, high]`` with ``digits`` significant
    digits; other columns are left as they are."""
    out = table.copy()
    for col in list(table.columns):
        if col + LOW in table.columns and col + HIGH in table.columns:

            def cell(mean, lo, hi):
                if not np.isfinite(mean):
                    return "n/a"
                return f"{mean:.{digits}g} [{lo:.{digits}g}, {hi:.{digits}g}]"

            out[col] = [cell(*t) for t in zip(table[col], table[col + LOW], table[col + HIGH])]
            out = out.drop(columns=[col + LOW, col + HIGH])
    return out


def write_table(
    table: pd.DataFrame, csv_path: str | Path, md_path: str | Path, caption: str, digits: int = 4
) -> tuple[Path, Path]:
    """Write ``csv_path`` (full precision) and ``md_path`` (caption, then the table with
    ``digits`` significant digits, intervals as ``mean [low, high]``: :func:`markdown_view`).
    Returns both paths."""
    csv_path, md_path = Path(csv_path), Path(md_path)
    for p in (csv_path, md_path):
        p.parent.mkdir(parents=True, exist_ok=True)
    table.to_csv(csv_path, index=False)
    md = markdown_view(table, digits).to_markdown(index=False, floatfmt=f".{digits}g")
    md_path.write_text(f"{caption}\n\n{md}\n")
    return csv_path, md_path
