"""`depthgt evaluate`'s library: a folder of predictions scored with the workflow's
protocol gives the workflow's tables (frame sets written by hand with a known truth)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from depthgt import io
from depthgt.cli import main
from depthgt.data.export import encode_png16
from depthgt.errors import DepthGTError
from depthgt.eval import predictions, tables
from depthgt.eval.evaluate import evaluate_frames


def _frame(rng, n=32):
    yy, xx = np.mgrid[0:n, 0:n]
    truth = (2.0 + 0.01 * xx + 0.005 * yy + 0.3 * (xx > n // 2)).astype(np.float32)
    noisy = truth + rng.normal(0.0, 0.02, truth.shape).astype(np.float32)
    noisy[rng.random(truth.shape) < 0.1] = 0.0
    gt = truth + rng.normal(0.0, 0.002, truth.shape).astype(np.float32)
    gt[:2] = 0.0
    return truth, noisy, gt, np.full((n, n, 3), 100, np.uint8)


@pytest.fixture()
def build(tmp_path):
    """A working directory with a results/dataset/framesets.parquet of 6 test frame
    sets (relative locations, as the workflow writes them) and one train frame set."""
    rng = np.random.default_rng(0)
    rows = []
    for i in range(7):
        loc = f"results/framesets/syn/room/{i:06d}"
        truth, noisy, gt, rgb = _frame(rng)
        io.write_exr(tmp_path / loc / "input.exr", {"Z": noisy, "T": truth})
        io.write_exr(tmp_path / loc / "gt.exr", {"Z": gt})
        io.write_rgb_webp(tmp_path / loc / "rgb.webp", rgb)
        rows.append(
            {
                "dataset": "syn",
                "scene": "room",
                "target": i,
                "frameset": loc,
                "status": "ok",
                "split": "test" if i < 6 else "train",
            }
        )
    (tmp_path / "results/dataset").mkdir(parents=True)
    pd.DataFrame(rows).to_parquet(tmp_path / "results/dataset/framesets.parquet")
    return tmp_path


def test_a_folder_of_predictions_reproduces_the_workflow_tables(build, tmp_path, monkeypatch):
    monkeypatch.chdir(build)  # the workflow's jobs run in the working directory
    methods = {"input": {"baseline": "input"}, "rgf": {"baseline": "rgf"}, "lapden": {"image": "gt"}}
    ev = evaluate_frames("results/dataset/framesets.parquet", methods, pred_dirs={"rgf": build / "pred_npy"})
    kinds = {"syn": "synthetic"}
    t3 = tables.table3(ev, kinds).set_index("method")
    # the RGF predictions, as a user would hand them in (EXR, channel Y)
    pred_dir = tmp_path / "mine"
    for npy in (build / "pred_npy").rglob("*.npy"):
        out = pred_dir / npy.relative_to(build / "pred_npy").with_suffix(".exr")
        io.write_exr(out, {"Y": np.load(npy)})
    assert len(list(pred_dir.rglob("*.exr"))) == 6  # the test frames only
    compare = [ev[ev["method"] == m] for m in ("input", "lapden")]
    written = predictions.evaluate_folder(
        pred_dir, tmp_path / "out", predictions.frames_from_results(build), method="mine", compare=compare
    )
    mine = pd.read_csv(written["table3"].with_suffix(".csv")).set_index("method")
    assert list(mine.index) == ["Input (raw depth)", "LapDEN (depthgt GT)", "mine"]
    cols = [c for c in t3.columns if c != "dataset"]
    pd.testing.assert_series_equal(mine.loc["mine", cols], t3.loc["RGF", cols], check_names=False, rtol=1e-12)
    md = written["table3"].read_text()
    rgf_cells = tables.markdown_view(tables.table3(ev, kinds)).set_index("method").loc["RGF"]
    assert rgf_cells[tables.METHOD_LABELS["mae_input_valid_m"]] in md  # the printed digits, interval included
    paired = pd.read_csv(written["table3_paired"].with_suffix(".csv")).set_index("comparison")
    assert list(paired.index) == ["mine - Input (raw depth)", "mine - LapDEN (depthgt GT)"]
    assert "mine minus" not in md and "mine's value" in written["table3_paired"].read_text()
    # the same predictions as 16-bit millimetre PNGs: within half a millimetre
    png_dir = tmp_path / "mine_png"
    for exr in pred_dir.rglob("*.exr"):
        out = png_dir / exr.relative_to(pred_dir).with_suffix(".png")
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_bytes(encode_png16(io.read_exr(exr)["Y"], 1000, str(out)))
    as_png = predictions.score_predictions(png_dir, predictions.frames_from_results(build), "png")
    as_exr = predictions.score_predictions(pred_dir, predictions.frames_from_results(build), "exr")
    mae = [f[f["metric"] == "mae_missing_counted_m"]["value"].to_numpy() for f in (as_png, as_exr)]
    assert np.abs(mae[0] - mae[1]).max() <= 0.0005


def test_the_command_and_bad_prediction_folders(build, tmp_path, capsys):
    pred = tmp_path / "p"
    rng = np.random.default_rng(1)
    for i in range(6):
        io.write_exr(pred / "syn" / "room" / f"{i:06d}.exr", {"Y": _frame(rng)[0]})  # the truth itself
    assert main(["evaluate", str(pred), "-d", str(build), "--out", str(tmp_path / "o")]) == 0
    t3 = pd.read_csv(tmp_path / "o" / "table3.csv").set_index("method")
    # a perfect prediction has no error against the truth on either mask
    assert t3.loc["p", tables.METHOD_LABELS["mae_missing_counted_m"]] == 0.0
    assert t3.loc["p", "frames"] == 6
    assert "no real source" in (tmp_path / "o" / "table2.md").read_text()
    # a frame without its prediction, a prediction of another size, two files for one frame
    (pred / "syn" / "room" / "000003.exr").unlink()
    with pytest.raises(DepthGTError, match="no prediction .*000003.exr or .*000003.png"):
        predictions.score_predictions(pred, predictions.frames_from_results(build), "p")
    io.write_exr(pred / "syn" / "room" / "000003.exr", {"Y": np.ones((16, 32), np.float32)})
    with pytest.raises(DepthGTError, match=r"000003.exr: prediction of shape \(16, 32\), the test frame is \(32, 32\)"):
        predictions.score_predictions(pred, predictions.frames_from_results(build), "p")
    io.write_exr(
        pred / "syn" / "room" / "000003.exr", {"R": np.ones((32, 32), np.float32), "G": np.ones((32, 32), np.float32)}
    )
    with pytest.raises(DepthGTError, match="one depth channel 'Y'"):
        predictions.score_predictions(pred, predictions.frames_from_results(build), "p")
    (pred / "syn" / "room" / "000003.png").write_bytes(b"")
    with pytest.raises(DepthGTError, match="two predictions"):
        predictions.score_predictions(pred, predictions.frames_from_results(build), "p")
    assert main(["evaluate", str(tmp_path / "nowhere"), "-d", str(build)]) == 2
    assert "no prediction folder" in capsys.readouterr().err
    ev = pd.DataFrame({"method": ["rgf"]})
    with pytest.raises(DepthGTError, match="'rgf' is a method of the build"):
        predictions.evaluate_folder(pred, tmp_path / "o2", predictions.frames_from_results(build), "rgf", [ev])
    with pytest.raises(DepthGTError, match="not a finished export"):
        predictions.frames_from_export(tmp_path)


def test_every_missing_prediction_is_named_before_scoring_and_bad_depths(build, tmp_path, caplog):
    pred = tmp_path / "p"
    rng = np.random.default_rng(2)
    truths = [_frame(rng)[0] for _ in range(6)]
    for i in (0, 2, 5):
        io.write_exr(pred / "syn" / "room" / f"{i:06d}.exr", {"Y": truths[i]})
    read = []
    frames = predictions.frames_from_results(build)
    frames_read = predictions.TestFrames(frames.ids, lambda i: read.append(i) or frames._read(i))
    with pytest.raises(DepthGTError, match=r"3 of the 6 test frames have no single prediction") as err:
        predictions.score_predictions(pred, frames_read, "p")
    assert all(f"{i:06d}.exr" in str(err.value) for i in (1, 3, 4)) and not read  # named at once, nothing read
    for i in (1, 3, 4):
        io.write_exr(pred / "syn" / "room" / f"{i:06d}.exr", {"Y": truths[i]})
    (pred / "syn" / "rooom").mkdir()
    (pred / "syn" / "rooom" / "000001.png").write_bytes(b"")
    (pred / "notes.txt").write_text("")
    # NaN and +inf count as missing, and say so; a negative depth is an error naming the file
    bad = truths[4].copy()
    bad[:4] = np.nan
    bad[4:6] = np.inf
    io.write_exr(pred / "syn" / "room" / "000004.exr", {"Y": bad})
    with caplog.at_level("WARNING", logger="depthgt.eval.predictions"):
        ev = predictions.score_predictions(pred, predictions.frames_from_results(build), "p")
    assert "1 predictions hold NaN or inf pixels" in caplog.text and "000004.exr (192 px)" in caplog.text
    assert "2 files of" in caplog.text and "notes.txt, syn/rooom/000001.png" in caplog.text
    comp = ev[(ev["metric"] == "completeness") & (ev["reference"] == "truth")].set_index("target")["value"]
    assert comp.loc[4] == pytest.approx(1 - 6 / 32) and comp.loc[3] == 1.0
    bad[:4] = -1.0
    io.write_exr(pred / "syn" / "room" / "000004.exr", {"Y": bad})
    with pytest.raises(DepthGTError, match=r"000004.exr: 128 pixels of negative depth"):
        predictions.score_predictions(pred, predictions.frames_from_results(build), "p")


def test_corrupt_export_metadata_is_named(tmp_path):
    (tmp_path / "index.parquet").write_bytes(b"not parquet")
    (tmp_path / "export.json").write_text("{broken")
    with pytest.raises(DepthGTError, match=r"export.json: not readable \(JSONDecodeError"):
        predictions.frames_from_export(tmp_path)
    (tmp_path / "export.json").write_text("[1, 2]")
    with pytest.raises(DepthGTError, match=r"export.json: an export of None"):
        predictions.frames_from_export(tmp_path)
    (tmp_path / "export.json").write_text('{"kind": "frames", "splits": ["test"]}')
    with pytest.raises(DepthGTError, match=r"index.parquet: not a readable parquet table"):
        predictions.frames_from_export(tmp_path)
