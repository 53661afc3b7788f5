"""Table builders on hand-made long tables: values, units in headers, the notes when a
table cannot be built, and the CSV + Markdown writer."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from depthgt import io, registry
from depthgt.eval import tables
from depthgt.eval.evaluate import EVAL_COLUMNS


def _ev(rows):
    return pd.DataFrame([dict(zip(EVAL_COLUMNS, r)) for r in rows], columns=EVAL_COLUMNS)


def _eval_table():
    rows = []
    # synthetic: two frames, two methods, both references
    for target, (inp, lap) in enumerate([(0.04, 0.01), (0.06, 0.03)]):
        for method, v in (("input", inp), ("lapden", lap)):
            for ref in ("gt", "truth"):
                rows.append(("syn", "room", target, method, ref, "rmse_m", "m", v))
                rows.append(("syn", "room", target, method, ref, "mae_m", "m", v / 2))
                rows.append(("syn", "room", target, method, ref, "ssim", "1", 1 - v))
    # a real source: only the GT reference
    rows.append(("kitchen", ".", 0, "input", "gt", "rmse_m", "m", 0.02))
    rows.append(("kitchen", ".", 0, "jf", "gt", "rmse_m", "m", 0.015))
    return _ev(rows)


KINDS = {"syn": "synthetic", "kitchen": "sevenscenes"}


def test_table3_means_over_frames_and_method_order():
    t3 = tables.table3(_eval_table(), KINDS)
    assert list(t3["method"]) == [registry.label("input"), registry.label("lapden")]
    assert "RMSE (m)" in t3.columns and "MAE (m)" in t3.columns and "SSIM (unitless)" in t3.columns
    row = t3.set_index("method").loc[registry.label("lapden")]
    assert row["RMSE (m)"] == pytest.approx(0.02)  # mean of 0.01 and 0.03
    assert row["MAE (m)"] == pytest.approx(0.01)
    assert row["SSIM (unitless)"] == pytest.approx(0.98)
    assert row["frames"] == 2
    assert np.isnan(row["completeness (fraction)"])  # metric absent -> NaN column, not a crash
    assert set(t3["dataset"]) == {"syn"}  # the real source does not enter Table 3


def test_table2_real_only_and_note_without_real_source():
    t2 = tables.table2(_eval_table(), KINDS)
    assert set(t2["dataset"]) == {"kitchen"}
    assert t2.set_index("method").loc["JF", "RMSE (m)"] == pytest.approx(0.015)
    only_synthetic = tables.table2(_eval_table(), {"syn": "synthetic", "kitchen": "synthetic"})
    assert list(only_synthetic.columns) == ["note"] and "no real source" in only_synthetic.iloc[0, 0]
    assert "note" in tables.table3(_ev([]), KINDS).columns


def test_conflicting_units_raise():
    ev = _ev([("syn", "r", 0, "input", "truth", "rmse_m", "m", 0.1), ("syn", "r", 1, "input", "truth", "rmse_m", "mm", 100.0)])
    with pytest.raises(ValueError, match="units"):
        tables.table3(ev, KINDS)


def test_table1_and_gt_quality():
    long = pd.DataFrame([
        ("syn", "room", 0, "gt", "ssim", "1", 0.9), ("syn", "room", 1, "gt", "ssim", "1", 0.8),
        ("syn", "room", 0, "gt", "ls", "m^2/px^2", 1e-4), ("syn", "room", 0, "rde", "ssim", "1", 0.7),
        ("syn", "room", 0, "rde", "ls", "m^2/px^2", 3e-4), ("syn", "room2", 0, "gt", "ssim", "1", 0.85),
    ], columns=["dataset", "scene", "target", "gt", "metric", "unit", "value"])
    t1 = tables.table1(long).set_index("GT")
    assert t1.loc[tables.GT_LABELS["gt"], "SSIM (unitless)"] == pytest.approx(0.85)  # (0.9 + 0.8 + 0.85) / 3
    assert t1.loc[tables.GT_LABELS["rde"], "L_S (m^2/px^2)"] == pytest.approx(3e-4)
    assert t1.loc[tables.GT_LABELS["gt"], "frames"] == 3  # frames of two scenes with the same target number
    q = pd.DataFrame([
        ("syn", "a", "gt", "truth", "mae_m", "m", 0.002), ("syn", "b", "gt", "truth", "mae_m", "m", 0.004),
        ("syn", "a", "input", "truth", "mae_m", "m", 0.02),
        ("kitchen", ".", "leave_target_out", "target_raw", "mae_m", "m", 0.01),
    ], columns=["dataset", "scene", "estimate", "reference", "metric", "unit", "value"])
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
    rde = pd.DataFrame([{"dataset": "syn", "scene": "r", "target": 0, "status": "ok", "frameset": str(tmp_path / "fs"),
                         "rde": str(tmp_path / "rde")}])
    long = tables.gt_vs_input_long(fs, rde).set_index(["gt", "metric"])["value"]
    assert long[("rde", "ssim")] == pytest.approx(1.0, abs=1e-6)  # identical to the input
    assert long[("rde", "ls")] == pytest.approx(0.0, abs=1e-12)
    assert long[("gt", "ssim")] < 1.0 and long[("gt", "ls")] > 0  # a slanted ramp added


def test_write_table(tmp_path):
    t = pd.DataFrame({"method": ["a"], "RMSE (m)": [0.0123456]})
    csv, md = tables.write_table(t, tmp_path / "sub" / "t.csv", tmp_path / "other" / "t.md", "Caption: conventions.")
    assert pd.read_csv(csv)["RMSE (m)"][0] == pytest.approx(0.0123456)
    text = md.read_text()
    assert text.startswith("Caption: conventions.") and "RMSE (m)" in text and "0.01235" in text
