"""A scene that yields no frame set is named in the dataset summary with its reason."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
from conftest import commands_in_background, depthgt_command, early, in_background, make_workdir, synthetic_source
from sens_writer import write_sens

from depthgt.gt.assemble import FRAMESET_COLUMNS, scenes_without_framesets


def test_scenes_without_framesets_reasons():
    fs = pd.DataFrame(
        [
            {"dataset": "a", "scene": "ok", "status": "ok", "reason": ""},
            {"dataset": "a", "scene": "skipped", "status": "skipped", "reason": "invalid_frame: depth 3 empty"},
            {"dataset": "a", "scene": "skipped", "status": "skipped", "reason": "invalid_frame: depth 4 empty"},
            {"dataset": "a", "scene": "skipped", "status": "skipped", "reason": "split_guard"},
        ],
        columns=FRAMESET_COLUMNS,
    )
    metas = [
        {"dataset": "a", "scene": s, "n_frames": n, "problems": p, "source": {"root": "/data"}}
        for s, n, p in [
            ("ok", 20, []),
            ("skipped", 20, []),
            ("empty", 0, ["scene_too_short: 0 frames"]),
            ("short", 4, ["scene_too_short: 4 frames, a frame set needs 7"]),
            ("noposes", 20, ["/data/groundtruth.txt: not found"]),
        ]
    ]
    fs = pd.concat(
        [
            fs,
            pd.DataFrame(
                [{"dataset": "a", "scene": "noposes", "status": "skipped", "reason": "registration_failed: x"}]
            ),
        ],
        ignore_index=True,
    )
    got = {r["scene"]: r["reason"] for r in scenes_without_framesets(fs, metas)}
    assert got == {
        "skipped": "every frame set skipped: invalid_frame (2), split_guard (1)",
        "empty": "empty_scene: the source yields no frame (root /data)",
        "short": "scene_too_short: 4 frames, a frame set needs 7",
        "noposes": "every frame set skipped: registration_failed (1); the scene's problems: /data/groundtruth.txt: not found",
    }


def test_a_dataset_with_no_patch_kept_writes_empty_manifests_and_says_why(tmp_path):
    from depthgt.gt.assemble import FRAME_COLUMNS, PATCH_COLUMNS, DatasetOutputs, assemble

    tables = {}
    for name, cols in (
        ("fs", FRAMESET_COLUMNS),
        ("patches", PATCH_COLUMNS),
        ("quality", []),
        ("frames", FRAME_COLUMNS),
    ):
        tables[name] = tmp_path / f"{name}.parquet"
        pd.DataFrame(columns=cols).to_parquet(tables[name])
    index = tmp_path / "index.json"
    index.write_text(
        json.dumps(
            {
                "dataset": "k",
                "scene": "seq",
                "n_frames": 5,
                "problems": ["scene_too_short: 5 frames, a frame set needs 13"],
                "source": {"root": "/data"},
            }
        )
    )
    out = DatasetOutputs.in_dir(tmp_path / "out")
    summary = assemble([tables["fs"]], [tables["patches"]], [tables["quality"]], [tables["frames"]], [index], out)
    for split in ("train", "val", "test"):
        assert pd.read_parquet(getattr(out, split)).empty
    assert summary["scenes_without_framesets"] == [
        {"dataset": "k", "scene": "seq", "n_frames": 5, "reason": "scene_too_short: 5 frames, a frame set needs 13"}
    ]
    assert "scene_too_short" in out.summary_md.read_text()


@early()
def empty_sens_build(folder: Path):
    """A .sens whose header announces 0 frames beside a synthetic scene, built to ``dataset`` (an early run)."""
    data = folder / "data"
    data.mkdir()
    K = np.array([[60.0, 0, 40], [0, 60, 30], [0, 0, 1]])
    write_sens(
        data / "scene0000_00.sens",
        [np.zeros((60, 80, 3), np.uint8)],
        [np.zeros((60, 80), np.uint16)],
        [],
        K,
        K,
        num_frames=0,
    )
    config = {
        "seed": 0,
        "device": "cpu",
        "resize": 32,
        "sources": [
            {"name": "scan", "kind": "scannet", "root": str(data), "scenes": ["scene0000_00"], "split": "train"},
            {
                "name": "syn",
                "kind": "synthetic",
                "scenes": ["room_000"],
                "split": "train",
                "options": {"n_frames": 6, "width": 80, "height": 60},
            },
        ],
        "frameset": {"neighbours": 1, "stride": 1, "target_step": 1, "batch_size": 4},
        "patches": {"count": 1, "size": 16, "max_missing": 1.0},
    }
    return in_background(make_workdir(folder / "wd", config), "dataset")


@early()
def five_frames_build(folder: Path):
    """A source of 5 frames (a frame set needs 13): ``depthgt build dataset``, then again
    with a --configfile allowing an empty dataset, refused, then with --reconfigure. An
    early run."""
    config = {
        "seed": 0,
        "device": "cpu",
        "resize": 32,
        "sources": [synthetic_source("syn", ["room_000"], "train", 5, 80, 60)],
        "frameset": {"neighbours": 3, "stride": 2, "target_step": 1},
        "patches": {"count": 1, "size": 16, "max_missing": 1.0},
    }
    wd = make_workdir(folder / "wd", config)
    allow = folder / "allow.yaml"
    allow.write_text("dataset: {allow_empty: true}\n")
    build = ["build", "-d", str(wd), "--cores", "2", "dataset"]
    return commands_in_background(
        [
            depthgt_command(*build),
            depthgt_command(*build, "--configfile", str(allow)),
            depthgt_command(*build, "--configfile", str(allow), "--reconfigure"),
        ]
    )


def test_an_empty_dataset_fails_the_build_saying_why(five_frames_build):
    """A build that keeps nothing exits non-zero naming the scene and its reason, without
    a traceback; dataset.allow_empty: true (a config change, refused until
    --reconfigure) keeps the empty dataset and exits 0."""
    first, refused, allowed = five_frames_build
    out = first.stdout + first.stderr
    assert first.returncode != 0
    assert "the dataset is empty: no frame set was built (syn/room_000 (5 frames): scene_too_short" in out, out[-3000:]
    assert "dataset.allow_empty: true" in out and "Traceback" not in out
    # the run's summary, from the scene's table: nothing built, and why
    assert "depthgt: so far, in 1 of 1 scenes: 0 frame sets built" in first.stderr, first.stderr[-3000:]
    assert refused.returncode == 2 and "dataset.allow_empty: (unset) -> true" in refused.stderr, refused.stderr
    assert "--reconfigure" in refused.stderr and "Traceback" not in refused.stderr
    assert allowed.returncode == 0, allowed.stderr[-3000:]
    wd = Path(first.args[first.args.index("-d") + 1])
    summary = json.loads((wd / "results/dataset/summary.json").read_text())
    assert sum(summary["framesets"].values()) == 0
    assert "depthgt: 0 frame sets built (train 0, val 0, test 0)" in allowed.stderr
    assert f"{wd / 'results/dataset/summary.md'}" in allowed.stderr


def test_empty_sens_is_named_in_summary(empty_sens_build):
    """A .sens whose header announces 0 frames, beside a scene that builds."""
    wd = empty_sens_build
    data = wd.parent / "data"
    md = (wd / "results/dataset/summary.md").read_text()
    assert f"| scan | scene0000_00 | 0 | empty_scene: the source yields no frame (root {data}) |" in md, md
    summary = json.loads((wd / "results/dataset/summary.json").read_text())
    assert [r["scene"] for r in summary["scenes_without_framesets"]] == ["scene0000_00"]
    assert summary["framesets"]["train"] == 4  # the other scene is built
