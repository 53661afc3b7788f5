"""Table builders on hand-made long tables: values, units in headers, the notes when a
table cannot be built, and the CSV + Markdown writer."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from depthgt import io, registry
from depthgt.eval import tables
from depthgt.eval.bootstrap import bootstrap_means
from depthgt.eval.evaluate import EVAL_COLUMNS


def _ev(rows):
    return pd.DataFrame([dict(zip(EVAL_COLUMNS, r)) for r in rows], columns=EVAL_COLUMNS)


UNITS = {"ssim_missing_counted": "1", "completeness": "fraction"}


def _eval_table():
    rows = []
    # synthetic: two frames, two methods, both references
    for target, (inp, lap) in enumerate([(0.04, 0.01), (0.06, 0.03)]):
        for method, v in (("input", inp), ("lapden", lap)):
            for ref in ("gt", "truth"):
                rows.append(("syn", "room", target, method, ref, "rmse_missing_counted_m", "m", v))
                rows.append(("syn", "room", target, method, ref, "mae_input_valid_m", "m", v / 2))
                rows.append(("syn", "room", target, method, ref, "ssim_missing_counted", "1", 1 - v))
                rows.append(("syn", "room", target, method, ref, "rmse_m", "m", 9.0))  # not a table column
    # a real source: only the GT reference
    rows.append(("kitchen", ".", 0, "input", "gt", "rmse_missing_counted_m", "m", 0.02))
    rows.append(("kitchen", ".", 0, "jf", "gt", "rmse_missing_counted_m", "m", 0.015))
    return _ev(rows)


KINDS = {"syn": "synthetic", "kitchen": "sevenscenes"}
RMSE, MAE_D, SSIM = (
    tables.METHOD_LABELS[m] for m in ("rmse_missing_counted_m", "mae_input_valid_m", "ssim_missing_counted")
)


def test_table3_means_over_frames_intervals_and_method_order():
    t3 = tables.table3(_eval_table(), KINDS)
    assert list(t3["method"]) == [registry.label("input"), registry.label("lapden")]
    assert {RMSE, RMSE + tables.LOW, RMSE + tables.HIGH, MAE_D, SSIM} <= set(t3.columns)
    assert "RMSE (m)" not in t3.columns  # no column whose pixel set depends on the method
    row = t3.set_index("method").loc[registry.label("lapden")]
    assert row[RMSE] == pytest.approx(0.02)  # mean of 0.01 and 0.03
    assert row[MAE_D] == pytest.approx(0.01)
    assert row[SSIM] == pytest.approx(0.98)
    # two frames: every resample's mean is 0.01, 0.02 or 0.03
    assert 0.01 - 1e-12 <= row[RMSE + tables.LOW] <= 0.02 <= row[RMSE + tables.HIGH] <= 0.03 + 1e-12
    assert row["frames"] == 2
    assert np.isnan(row[tables.METHOD_LABELS["completeness"]])  # metric absent -> NaN column, not a crash
    assert set(t3["dataset"]) == {"syn"}  # the real source does not enter Table 3


def _noisy_frames(n=60, seed=3):
    """Per-frame errors that vary a lot between frames (hard and easy frames) while
    LapDEN is better than RGF by exactly 2 mm on every frame."""
    rng = np.random.default_rng(seed)
    hard = rng.uniform(0.01, 0.05, n)
    rows = []
    for t in range(n):
        for method, v in (("lapden", hard[t]), ("rgf", hard[t] + 0.002), ("input", hard[t] + rng.normal(0, 0.01))):
            for metric in tables.METHOD_METRICS:
                rows.append(("syn", "room", t, method, "truth", metric, UNITS.get(metric, "m"), v))
    return _ev(rows)


def test_paired_table_separates_what_the_method_table_cannot():
    ev = _noisy_frames()
    t3 = tables.table3(ev, KINDS).set_index("method")
    lap, rgf = t3.loc[registry.label("lapden")], t3.loc[registry.label("rgf")]
    # the unpaired intervals overlap: the frames' spread hides a 2 mm difference
    assert lap[RMSE + tables.HIGH] > rgf[RMSE + tables.LOW]
    paired = tables.table3_paired(ev, KINDS).set_index("comparison")
    key = f"{registry.label('lapden')} - {registry.label('rgf')}"
    assert list(paired.index) == [f"{registry.label('lapden')} - {registry.label('input')}", key]
    row = paired.loc[key]
    assert row["frames"] == 60
    assert row[RMSE] == pytest.approx(-0.002)
    assert row[RMSE + tables.LOW] == pytest.approx(-0.002) and row[RMSE + tables.HIGH] == pytest.approx(-0.002)
    inp = paired.loc[f"{registry.label('lapden')} - {registry.label('input')}"]
    assert inp[RMSE + tables.LOW] < inp[RMSE] < inp[RMSE + tables.HIGH]
    # no LapDEN: a note, not a crash
    note = tables.table3_paired(ev[ev["method"] != "lapden"], KINDS)
    assert list(note.columns) == ["note"] and "lapden" in note.iloc[0, 0]
    assert "note" in tables.table2_paired(ev, KINDS).columns


def test_bootstrap_against_a_plain_loop_and_normal_theory():
    rng = np.random.default_rng(7)
    v = rng.normal(1.0, 0.5, (400, 2))
    v[5, 1] = np.nan
    est = bootstrap_means(v, resamples=500, seed=11)
    # plain reference: the same draws, one resample at a time
    idx = np.random.default_rng(11).integers(0, 400, size=(500, 400))
    loop = np.array([np.nanmean(v[i], axis=0) for i in idx])
    np.testing.assert_allclose(est.low, np.percentile(loop, 2.5, axis=0), rtol=1e-12)
    np.testing.assert_allclose(est.high, np.percentile(loop, 97.5, axis=0), rtol=1e-12)
    np.testing.assert_allclose(est.mean, np.nanmean(v, axis=0), rtol=1e-12)
    assert est.frames.tolist() == [400, 399]
    # about the normal interval mean +- 1.96 sd / sqrt(n)
    half = (est.high - est.low) / 2
    assert half == pytest.approx(1.96 * np.nanstd(v, axis=0) / np.sqrt(400), rel=0.15)
    # the seed is fixed: the same numbers again
    again = bootstrap_means(v, resamples=500, seed=11)
    np.testing.assert_array_equal(est.low, again.low)
    assert np.isnan(bootstrap_means(np.full((3, 1), np.nan)).mean[0])
    with pytest.raises(ValueError, match="n_frames, k"):
        bootstrap_means(np.zeros((2, 2, 2)))


def test_table2_real_only_and_note_without_real_source():
    t2 = tables.table2(_eval_table(), KINDS)
    assert set(t2["dataset"]) == {"kitchen"}
    assert t2.set_index("method").loc["JF", RMSE] == pytest.approx(0.015)
    only_synthetic = tables.table2(_eval_table(), {"syn": "synthetic", "kitchen": "synthetic"})
    assert list(only_synthetic.columns) == ["note"] and "no real source" in only_synthetic.iloc[0, 0]
    assert "note" in tables.table3(_ev([]), KINDS).columns


def test_table2_one_block_per_reference():
    """Real frames scored against depthgt's GT, the neighbours-only render and the TSDF
    GT: one block each (column ``reference``, Table 2's order), each with its own means,
    intervals and paired differences; a reference without values has no block."""
    rows = []
    for target in range(3):
        for ref, (inp, lap) in (
            ("tsdf", (0.05, 0.04)),
            ("gt", (0.02, 0.01)),
            ("neighbours", (0.03, 0.02 + 0.001 * target)),
        ):
            for method, v in (("input", inp), ("lapden", lap)):
                rows.append(("kitchen", ".", target, method, ref, "rmse_missing_counted_m", "m", v))
    t2 = tables.table2(_ev(rows), KINDS)
    assert list(t2["reference"]) == ["depthgt GT"] * 2 + ["neighbours only"] * 2 + ["TSDF GT"] * 2
    by = t2.set_index(["reference", "method"])[RMSE]
    assert by["neighbours only", registry.label("lapden")] == pytest.approx(0.021)
    assert by["TSDF GT", registry.label("input")] == pytest.approx(0.05)
    assert (t2["frames"] == 3).all()
    paired = tables.table2_paired(_ev(rows), KINDS)
    assert list(paired["reference"]) == ["depthgt GT", "neighbours only", "TSDF GT"]
    assert paired.set_index("reference").loc["neighbours only", RMSE] == pytest.approx(-0.009)
    only_gt = tables.table2(_ev([r for r in rows if r[4] == "gt"]), KINDS)
    assert list(only_gt["reference"]) == ["depthgt GT"] * 2
    assert "neighbours only" in tables.TABLE2_CAPTION and "favours" in tables.TABLE2_PAIRED_CAPTION
    # a caption describes the references its table holds (depthgt evaluate on a build with depthgt's GT only)
    only_gt = pd.DataFrame({"reference": ["depthgt GT", "depthgt GT"]})
    caption = tables.table2_caption(tables.references_in(only_gt))
    assert caption.startswith("Table 2 (real data): methods on held-out real test frames against one reference. ")
    assert "'depthgt GT'" in caption and "TSDF" not in caption and "neighbours only" not in caption
    assert "three references" in tables.TABLE2_CAPTION and "One block per reference" in tables.TABLE2_CAPTION


def test_conflicting_units_and_duplicates_raise():
    ev = _ev(
        [
            ("syn", "r", 0, "input", "truth", "rmse_missing_counted_m", "m", 0.1),
            ("syn", "r", 1, "input", "truth", "rmse_missing_counted_m", "mm", 100.0),
        ]
    )
    with pytest.raises(ValueError, match="units"):
        tables.table3(ev, KINDS)
    ev = _ev([("syn", "r", 0, "input", "truth", "rmse_missing_counted_m", "m", 0.1)] * 2)
    with pytest.raises(ValueError, match="duplicate rows, e.g. syn/r/0 input"):
        tables.table3(ev, KINDS)


def test_table1_and_gt_quality():
    long = pd.DataFrame(
        [
            ("syn", "room", 0, "gt", "ssim", "1", 0.9),
            ("syn", "room", 1, "gt", "ssim", "1", 0.8),
            ("syn", "room", 0, "gt", "ls", "m^2/px^2", 1e-4),
            ("syn", "room", 0, "rde", "ssim", "1", 0.7),
            ("syn", "room", 0, "rde", "ls", "m^2/px^2", 3e-4),
            ("syn", "room2", 0, "gt", "ssim", "1", 0.85),
        ],
        columns=["dataset", "scene", "target", "gt", "metric", "unit", "value"],
    )
    t1 = tables.table1(long).set_index("GT")
    assert t1.loc[tables.GT_LABELS["gt"], "SSIM (unitless)"] == pytest.approx(0.85)  # (0.9 + 0.8 + 0.85) / 3
    assert t1.loc[tables.GT_LABELS["rde"], "L_S (m^2/px^2)"] == pytest.approx(3e-4)
    assert t1.loc[tables.GT_LABELS["gt"], "frames"] == 3  # frames of two scenes with the same target number
    q = pd.DataFrame(
        [
            ("syn", "a", "gt", "truth", "mae_m", "m", 0.002),
            ("syn", "b", "gt", "truth", "mae_m", "m", 0.004),
            ("syn", "a", "input", "truth", "mae_m", "m", 0.02),
            ("kitchen", ".", "leave_target_out", "target_raw", "mae_m", "m", 0.01),
        ],
        columns=["dataset", "scene", "estimate", "reference", "metric", "unit", "value"],
    )
    rq = pd.DataFrame([("syn", "a", "rde", "truth", "mae_m", "m", 0.008)], columns=q.columns)
    tq = tables.table_gt_quality(q, rq)
    assert list(tq["estimate"]) == [tables.GT_LABELS["gt"], tables.GT_LABELS["rde"], tables.GT_LABELS["input"]]
    assert tq["MAE (m)"].tolist() == pytest.approx([0.003, 0.008, 0.02])
    assert "note" in tables.table_gt_quality(q[q["dataset"] == "kitchen"]).columns


def test_gt_vs_input_long_reads_frame_sets(tmp_path):
    inp = np.full((32, 32), 2.0, np.float32)
    inp[:4] = 0.0
    gt = inp + 0.01 * np.arange(32, dtype=np.float32)[None]
    gt[:4] = 2.0
    for d, z in (("fs", gt), ("rde", inp)):
        (tmp_path / d).mkdir()
        io.write_exr(tmp_path / d / "gt.exr", {"Z": z})
    io.write_exr(tmp_path / "fs" / "input.exr", {"Z": inp})
    fs = pd.DataFrame([{"dataset": "syn", "scene": "r", "target": 0, "status": "ok", "frameset": str(tmp_path / "fs")}])
    rde = pd.DataFrame(
        [
            {
                "dataset": "syn",
                "scene": "r",
                "target": 0,
                "status": "ok",
                "frameset": str(tmp_path / "fs"),
                "rde": str(tmp_path / "rde"),
            }
        ]
    )
    long = tables.gt_vs_input_long(fs, rde).set_index(["gt", "metric"])["value"]
    assert long[("rde", "ssim")] == pytest.approx(1.0, abs=1e-6)  # identical to the input
    assert long[("rde", "ls")] == pytest.approx(0.0, abs=1e-12)
    assert long[("gt", "ssim")] < 1.0 and long[("gt", "ls")] > 0  # a slanted ramp added


def test_write_table(tmp_path):
    t = pd.DataFrame(
        {
            "method": ["a", "b"],
            "RMSE (m)": [0.0123456, np.nan],
            "RMSE (m)" + tables.LOW: [0.011, np.nan],
            "RMSE (m)" + tables.HIGH: [0.01351, np.nan],
            "frames": [3, 0],
        }
    )
    csv, md = tables.write_table(t, tmp_path / "sub" / "t.csv", tmp_path / "other" / "t.md", "Caption: conventions.")
    back = pd.read_csv(csv)
    assert back["RMSE (m)"][0] == pytest.approx(0.0123456) and back["RMSE (m)" + tables.HIGH][0] == pytest.approx(
        0.01351
    )
    text = md.read_text()
    assert text.startswith("Caption: conventions.") and "RMSE (m)" in text and "0.01235 [0.011, 0.01351]" in text
    assert "95% low" not in text and "n/a" in text
