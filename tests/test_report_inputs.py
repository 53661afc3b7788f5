"""depthgt report on a build whose files are damaged: one line naming the file, no traceback."""

import json
import shutil

import pandas as pd
import pytest

from depthgt.errors import DepthGTError
from depthgt.eval.report import write_report


def _build(tmp_path):
    """A minimal dataset-only build: one scene's frame-set table and the dataset summary."""
    results = tmp_path / "wd" / "results"
    (results / "framesets").mkdir(parents=True)
    scene = results / "scenes" / "syn" / "room_000"
    scene.mkdir(parents=True)
    pd.DataFrame({"dataset": ["syn"], "scene": ["room_000"], "target": [6], "status": ["ok"]}).to_parquet(
        scene / "framesets.parquet"
    )
    (results / "dataset").mkdir()
    summary = {
        "framesets": {"train": 1, "val": 0, "test": 0},
        "pairs": {"train": 6, "val": 0, "test": 0},
        "framesets_skipped": [],
        "frames_skipped": [],
        "frames_read": 7,
        "patches_rejected": 0,
        "scenes_without_framesets": [],
    }
    (results / "dataset" / "summary.json").write_text(json.dumps(summary))
    return tmp_path / "wd", summary


def test_report_of_a_sound_build_is_written(tmp_path):
    wd, _ = _build(tmp_path)
    out = write_report(wd, tmp_path / "report.html")
    assert "patch pairs" in out.read_text()


@pytest.mark.parametrize(
    "damage, named",
    [
        (lambda wd, s: (wd / "results/dataset/summary.json").write_text("{not json"), "summary.json"),
        (
            lambda wd, s: (wd / "results/dataset/summary.json").write_text(json.dumps({**s, "pairs": None})),
            "summary.json",
        ),
        (
            lambda wd, s: (wd / "results/scenes/syn/room_000/framesets.parquet").write_bytes(b"PAR1 torn"),
            "framesets.parquet",
        ),
        (lambda wd, s: (wd / "results/dataset/gt_quality.csv").write_text(""), "gt_quality.csv"),
    ],
)
def test_a_damaged_file_is_named_in_one_line(tmp_path, damage, named):
    wd, summary = _build(tmp_path)
    damage(wd, summary)
    with pytest.raises(DepthGTError, match=rf"{named}: cannot be read for the report"):
        write_report(wd, tmp_path / "report.html")
    shutil.rmtree(wd)
