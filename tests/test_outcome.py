"""The run's end-of-run summary from the scenes' tables (depthgt.jobs.outcome.summary_lines):
the lines of the dataset's own summary (depthgt.gt.assemble.summarise and console_summary
over the tables read whole), read with the columns it needs only."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from depthgt.gt.assemble import FRAME_COLUMNS, FRAMESET_COLUMNS, PATCH_COLUMNS, console_summary, summarise
from depthgt.jobs import outcome

SCENES = [("syn", "room_000"), ("syn", "room_001"), ("scan", "scene0000_00"), ("scan", "scene0001_00"), ("syn", "x")]


def _frameset_rows(dataset: str, scene: str, outcomes: list[tuple[str, str, str]]) -> pd.DataFrame:
    rows = []
    for i, (split, status, reason) in enumerate(outcomes):
        row = dict.fromkeys(FRAMESET_COLUMNS, 0.0)
        row.update(dataset=dataset, scene=scene, target=6 + i, frame_id=f"{6 + i:06d}", split=split)
        row.update(status=status, reason=reason, frameset=f"results/framesets/{dataset}/{scene}/a.zip/{6 + i:06d}")
        row.update(has_truth=dataset == "syn", patches_drawn=2, patches_kept=1, neighbours_left_out="")
        rows.append(row)
    return pd.DataFrame(rows, columns=FRAMESET_COLUMNS)


def _patch_rows(dataset: str, scene: str, kept: list[bool], split: str) -> pd.DataFrame:
    rows = [[dataset, scene, 6 + i // 2, split, i % 2, "f", 0, 0, 32, 0.1, 0.2, k] for i, k in enumerate(kept)]
    return pd.DataFrame(rows, columns=PATCH_COLUMNS)


def _frame_rows(dataset: str, scene: str, valid: list[bool]) -> pd.DataFrame:
    rows = [
        [dataset, scene, i, f"{i:06d}", v, "" if v else "unreadable", "" if v else f"color/{i}.jpg: truncated"]
        for i, v in enumerate(valid)
    ]
    return pd.DataFrame(rows, columns=FRAME_COLUMNS)


def _write_scene(results: Path, dataset: str, scene: str, fs, patches, frames, meta, extra: bool) -> None:
    folder = results / "scenes" / dataset / scene
    folder.mkdir(parents=True)
    if extra:  # a column the summary does not need, large: it must not be read
        fs = fs.assign(huge=[np.random.default_rng(0).bytes(200_000) for _ in range(len(fs))])
    fs.to_parquet(folder / "framesets.parquet", index=False)
    if patches is not None:
        patches.to_parquet(folder / "patches.parquet", index=False)
    if frames is not None:
        frames.to_parquet(folder / "frames.parquet", index=False)
    if meta is not None:
        (folder / "index.json").write_text(json.dumps({"dataset": dataset, "scene": scene, **meta}))


@pytest.fixture
def scene_tables(tmp_path):
    """Four summarised scenes of five (the fifth not summarised yet): built and skipped
    frame sets of every split with reasons that tie and that name a frame, a scene whose
    every frame set was skipped, an empty scene without patches or frames tables, unusable
    frames, kept and rejected patches."""
    results = tmp_path / "results"
    reasons = [
        ("train", "ok", ""),
        ("train", "skipped", "frame 5: unreadable (color/5.jpg: truncated)"),
        ("val", "ok", ""),
        ("train", "skipped", "split_guard: members in two splits"),
        ("test", "ok", ""),
        ("val", "failed", "registration_failed: 2 of 6 neighbours not registered"),
        ("train", "skipped", "frame 8: unreadable (color/8.jpg: truncated)"),
    ]
    _write_scene(
        results,
        "syn",
        "room_000",
        _frameset_rows("syn", "room_000", reasons),
        _patch_rows("syn", "room_000", [True, False, True, True], "train"),
        _frame_rows("syn", "room_000", [True, False, True, True, True, True, True, True, False]),
        {"n_frames": 9, "problems": []},
        extra=True,
    )
    skipped_all = [
        ("val", "skipped", "split_guard: members in two splits"),
        ("val", "skipped", "frame 2: nonfinite_pose (pose of frame 2)"),
        ("val", "skipped", "split_guard: members in two splits"),
    ]
    _write_scene(
        results,
        "syn",
        "room_001",
        _frameset_rows("syn", "room_001", skipped_all),
        _patch_rows("syn", "room_001", [], "val"),
        _frame_rows("syn", "room_001", [True, True, False]),
        {"n_frames": 12, "problems": ["short: 12 frames"]},
        extra=False,
    )
    _write_scene(
        results,
        "scan",
        "scene0000_00",
        _frameset_rows("scan", "scene0000_00", []),
        None,
        None,
        {"n_frames": 0, "problems": [], "source": {"root": "/data/scannet"}},
        extra=False,
    )
    more = [("test", "ok", ""), ("test", "skipped", "registration_failed: no neighbour"), ("test", "ok", "")]
    _write_scene(
        results,
        "scan",
        "scene0001_00",
        _frameset_rows("scan", "scene0001_00", more),
        _patch_rows("scan", "scene0001_00", [True, True, False, False, True, False], "test"),
        _frame_rows("scan", "scene0001_00", [True] * 7),
        {"n_frames": 7, "problems": []},
        extra=True,
    )
    return tmp_path


def _summary_of_whole_tables(workdir: Path) -> list[str]:
    """The lines the dataset's own summary makes of the scenes' tables, every column of
    every table read (what summary_lines did before it read columns)."""
    folders = [workdir / "results/scenes" / d / s for d, s in SCENES]
    folders = [f for f in folders if (f / "framesets.parquet").is_file()]

    def concat(name: str, columns: list[str]) -> pd.DataFrame:
        frames = [pd.read_parquet(f / name) for f in folders if (f / name).is_file()]
        frames = [f for f in frames if len(f)]
        return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame(columns=columns)

    metas = [json.loads((f / "index.json").read_text()) for f in folders]
    summary = summarise(
        concat("framesets.parquet", FRAMESET_COLUMNS),
        concat("patches.parquet", PATCH_COLUMNS),
        concat("frames.parquet", FRAME_COLUMNS),
        metas,
    )
    return console_summary(summary)


@pytest.mark.parametrize("failed", [False, True])
def test_the_summary_from_the_tables_says_what_the_whole_tables_say(scene_tables, failed):
    lines = outcome.summary_lines(scene_tables, SCENES, failed=failed)
    expected = _summary_of_whole_tables(scene_tables)
    expected[0] = expected[0].replace("depthgt: ", "depthgt: so far, in 4 of 5 scenes: ", 1)
    assert lines[: len(expected)] == expected
    assert len(lines) == len(expected) + (0 if failed else 1)
    # what the tables hold, in the lines (the figures the comparison above rests on)
    assert lines[0] == (
        "depthgt: so far, in 4 of 5 scenes: 5 frame sets built (train 1, val 1, test 3), 8 skipped; "
        "3 of 19 frames read unusable; 6 patch pairs kept (train 3, val 0, test 3), 4 rejected by the missing filter"
    )
    # the top reasons: the counts summed over the scenes, ties in the tag's order, the first frame set's example
    assert lines[1:4] == [
        "depthgt:   3 frame sets skipped for split_guard, e.g. syn/room_000/000009: split_guard: members in two splits",
        "depthgt:   2 frame sets skipped for an unusable frame (unreadable), e.g. syn/room_000/000007: "
        "frame 5: unreadable (color/5.jpg: truncated)",
        "depthgt:   2 frame sets skipped for registration_failed, e.g. syn/room_000/000011: "
        "registration_failed: 2 of 6 neighbours not registered",
    ]
    assert lines[4] == (
        "depthgt:   scene syn/room_001 has no frame set: every frame set skipped: split_guard (2), "
        "frame 2 (1); the scene's problems: short: 12 frames"
    )
    assert lines[5] == (
        "depthgt:   scene scan/scene0000_00 has no frame set: empty_scene: the source yields no frame "
        "(root /data/scannet)"
    )


def test_the_summary_reads_only_the_columns_it_needs(scene_tables, monkeypatch):
    """A ScanNet build's tables hold millions of rows: the summary reads the columns its
    lines need (not the statistics, nor a large column it does not use)."""
    calls = []
    read = pd.read_parquet

    def recording(path, *args, **kwargs):
        table = read(path, *args, **kwargs)
        calls.append((Path(path).name, kwargs.get("columns")))
        return table

    monkeypatch.setattr(pd, "read_parquet", recording)
    lines = outcome.summary_lines(scene_tables, SCENES, failed=True)
    assert lines[0].startswith("depthgt: so far, in 4 of 5 scenes: 5 frame sets built")
    assert calls and all(columns is not None for _, columns in calls), calls
    needed = {
        "framesets.parquet": {"dataset", "scene", "target", "split", "status", "reason"},
        "patches.parquet": {"split", "kept"},
        "frames.parquet": {"valid"},
    }
    for name, columns in calls:
        assert set(columns) <= needed[name], (name, columns)
    # one read of each table that exists: 4 frame-set tables, 3 patch and 3 frame tables
    assert (
        sorted(name for name, _ in calls)
        == ["frames.parquet"] * 3 + ["framesets.parquet"] * 4 + ["patches.parquet"] * 3
    )


def test_the_summary_reads_index_json_only_for_scenes_it_may_name(scene_tables, monkeypatch):
    """index.json (the scene's frame count and problems) is read for a scene without a
    built frame set only, and only until the three the console names are found."""
    read = Path.read_text
    names = []

    def recording(self, *args, **kwargs):
        if self.name == "index.json":
            names.append(self.parent.name)
        return read(self, *args, **kwargs)

    monkeypatch.setattr(Path, "read_text", recording)
    outcome.summary_lines(scene_tables, SCENES)
    assert names == ["room_001", "scene0000_00"]
