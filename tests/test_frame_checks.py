"""Frame validity is decided where frames are read: the scene index reads no frame, the
frame-set batches check each member frame once and record unusable ones; the scene
summaries and the dataset summary list every unusable frame and every frame set it
made skip, with the reason and the file; registration pretraining skips a drawn frame
set with an unusable frame and takes a spare."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import torch
from conftest import commands_in_background, count_synthetic_reads, depthgt_command, early, make_workdir

from depthgt.errors import FrameError
from depthgt.gt import store
from depthgt.jobs.common import open_source_scene
from depthgt.sources import synthetic

SYN = {"name": "syn", "kind": "synthetic", "split": "train", "options": {"n_frames": 16, "width": 80, "height": 60}}
SMALL = {
    "seed": 1,
    "device": "cpu",
    "resize": 32,
    "sources": [dict(SYN, scenes=["room_000"])],
    "frameset": {"neighbours": 1, "stride": 1, "target_step": 1, "batch_size": 4},
    "patches": {"count": 1, "size": 16, "max_missing": 1.0},
}


def test_the_index_reads_no_frame(tmp_path, monkeypatch):
    """run_scene_index never reads a frame, nor builds the synthetic room (whose frames
    only ray casting gives); it plans every target whose members share a split."""
    from depthgt.jobs.gt import run_scene_index

    def no_read(self, i):
        raise AssertionError(f"the index read frame {i}")

    def no_room(*args, **kwargs):
        raise AssertionError("the index built the synthetic room")

    monkeypatch.setattr(synthetic.SyntheticScene, "read", no_read)
    monkeypatch.setattr(synthetic, "generate_layout", no_room)
    monkeypatch.setattr(synthetic, "make_path", no_room)
    run_scene_index(
        dict(SYN, scenes=["room_000"]), "room_000", SMALL, str(tmp_path / "index.parquet"), str(tmp_path / "index.json")
    )
    table = pd.read_parquet(tmp_path / "index.parquet")
    meta = json.loads((tmp_path / "index.json").read_text())
    assert list(table["frame_id"]) == [f"{i:06d}" for i in range(16)]
    assert set(table.loc[table["is_target"], "frameset_status"]) == {"planned"}
    assert meta["framesets_planned"] == list(range(1, 15)) and meta["n_framesets_skipped"] == 0
    assert "n_valid_frames" not in meta and "valid" not in table.columns


def test_a_batch_reads_each_frame_once(tmp_path, monkeypatch):
    """Checking the members before building a frame set costs no extra read: every frame
    a batch uses is read from the source once, and batch.json lists each with its outcome."""
    from depthgt.jobs.gt import run_frameset_batch, run_scene_index

    source = dict(SYN, scenes=["room_000"])
    run_scene_index(source, "room_000", SMALL, str(tmp_path / "index.parquet"), str(tmp_path / "index.json"))
    reads = count_synthetic_reads(monkeypatch)
    shard = tmp_path / "000003-000010.zip"
    records = run_frameset_batch(source, "room_000", 3, 10, SMALL, str(tmp_path / "index.parquet"), str(shard))
    assert [r["target"] for r in records] == list(range(3, 11)) and {r["status"] for r in records} == {"ok"}
    assert sorted(reads) == list(range(2, 12))  # the members of targets 3..10, each once
    assert [(f["position"], f["valid"]) for f in store.read_batch_frames(shard)] == [(i, True) for i in range(2, 12)]


def _export_scannet(root, n_frames=12):
    """A ScanNet exported folder (color/N.jpg, depth/N.png in mm, pose/N.txt) holding
    the frames of a small synthetic room; returns the scene folder."""
    syn = open_source_scene(
        {"kind": "synthetic", "options": {"n_frames": n_frames, "width": 80, "height": 60}}, "room_000"
    )
    scene = root / "scene0000_00"
    for sub in ("color", "depth", "pose", "intrinsic"):
        (scene / sub).mkdir(parents=True)
    for i in range(n_frames):
        fr = syn.read(i)
        assert cv2.imwrite(str(scene / "color" / f"{i}.jpg"), cv2.cvtColor(fr.rgb, cv2.COLOR_RGB2BGR))
        assert cv2.imwrite(str(scene / "depth" / f"{i}.png"), np.round(fr.depth_m * 1000).astype(np.uint16))
        np.savetxt(scene / "pose" / f"{i}.txt", fr.T_world_cam)
    K4 = np.eye(4)
    K4[:3, :3] = syn.intrinsics
    np.savetxt(scene / "intrinsic" / "intrinsic_depth.txt", K4)
    return scene


def corrupt_png(path: Path) -> None:
    """Flip a byte of a PNG's image data: libpng fails on it and prints its own message."""
    data = bytearray(path.read_bytes())
    data[data.find(b"IDAT") + 10] ^= 0xFF
    path.write_bytes(bytes(data))


@early()
def bad_frames_build(folder: Path):
    """A ScanNet export with a truncated JPEG (frame 5), a corrupt depth PNG (frame 6) and
    a non-finite pose (frame 8), built to ``dataset`` by ``depthgt build`` (an early run)."""
    scene = _export_scannet(folder / "data")
    jpg = scene / "color" / "5.jpg"
    jpg.write_bytes(jpg.read_bytes()[:-200])
    corrupt_png(scene / "depth" / "6.png")
    np.savetxt(scene / "pose" / "8.txt", np.full((4, 4), np.nan))
    config = dict(
        SMALL,
        sources=[
            {"name": "scan", "kind": "scannet", "root": str(scene.parent), "scenes": ["scene0000_00"], "split": "train"}
        ],
    )
    wd = make_workdir(folder / "wd", config)
    run = commands_in_background([depthgt_command("build", "-d", str(wd), "--cores", "2", "dataset")])
    return lambda: (wd, run()[0])


def test_a_bad_frame_found_by_the_batches_is_recorded(bad_frames_build):
    """A truncated JPEG (frame 5) and a non-finite pose (frame 8, registration given)
    are found by the batches that read them: batches of 4 targets overlap, so frame 5 is
    read by two of them and listed once; each frame set holding one is skipped with the
    frame's reason and file, in frames.parquet and in the dataset summary. A corrupt depth
    PNG (frame 6) is named with libpng's own words; the console shows depthgt's sentences
    naming the files (never a bare libpng message) and ends with the build's summary."""
    wd, proc = bad_frames_build
    assert proc.returncode == 0, proc.stderr[-4000:]
    sdir = wd / "results/scenes/scan/scene0000_00"
    index = pd.read_parquet(sdir / "index.parquet")
    assert set(index.loc[index["is_target"], "frameset_status"]) == {"planned"}  # the index did not know
    shards = sorted((wd / "results/framesets/scan/scene0000_00").glob("*.zip"))
    assert [p.name for p in shards] == ["000001-000004.zip", "000005-000008.zip", "000009-000010.zip"]
    seen_5 = [s.name for s in shards if any(f["position"] == 5 and not f["valid"] for f in store.read_batch_frames(s))]
    assert seen_5 == ["000001-000004.zip", "000005-000008.zip"]

    frames = pd.read_parquet(sdir / "frames.parquet").set_index("position")
    assert list(frames.index) == list(range(12))
    bad = frames[~frames["valid"]]
    assert list(bad.index) == [5, 6, 8] and list(bad["reason"]) == ["unreadable", "unreadable", "nonfinite_pose"]
    assert "scene0000_00/color/5.jpg: truncated JPEG" in bad.loc[5, "message"]
    assert "scene0000_00/depth/6.png: cannot decode PNG image (libpng error: IDAT:" in bad.loc[6, "message"]
    assert "scene0000_00 frame 8: pose is not a finite" in bad.loc[8, "message"]

    fs = pd.read_parquet(wd / "results/dataset/framesets.parquet").set_index("target")
    assert list(fs.index) == list(range(1, 11))
    skipped = fs[fs["status"] != "ok"]
    assert list(skipped.index) == [4, 5, 6, 7, 8, 9] and (skipped["status"] == "skipped").all()
    assert skipped.loc[4, "reason"] == f"frame 5: unreadable ({bad.loc[5, 'message']})"
    assert skipped.loc[8, "reason"] == f"frame 8: nonfinite_pose ({bad.loc[8, 'message']})"
    assert (fs.loc[[1, 2, 3, 10], "status"] == "ok").all() and (fs.loc[[1, 2, 3, 10], "frameset"] != "").all()

    summary = json.loads((wd / "results/dataset/summary.json").read_text())
    assert summary["frames_read"] == 12
    assert [(f["position"], f["frame_id"], f["reason"]) for f in summary["frames_skipped"]] == [
        (5, "5", "unreadable"),
        (6, "6", "unreadable"),
        (8, "8", "nonfinite_pose"),
    ]
    assert [r["target"] for r in summary["framesets_skipped"]] == [4, 5, 6, 7, 8, 9]
    md = (wd / "results/dataset/summary.md").read_text()
    assert "unusable (skipped): 3. Frame sets skipped: 6." in md
    # each frame's file or name and problem: in its row of the frames, and in each frame set it made skip
    assert (
        md.count("color/5.jpg: truncated JPEG") == 1 + 3
        and md.count("scene0000_00 frame 8: pose is not a finite") == 1 + 3
    )
    # the console: each skipped frame set in depthgt's words, no bare library message, then the summary
    console = proc.stderr
    assert not [line for line in console.splitlines() if line.startswith("libpng")], console[-4000:]
    assert "depthgt: warning: frame set scan/scene0000_00/000007 skipped: frame 6: unreadable" in console
    assert "depth/6.png: cannot decode PNG image (libpng error: IDAT:" in console
    assert "depthgt: 4 frame sets built (train 4, val 0, test 0), 6 skipped; 3 of 12 frames read unusable" in console, (
        console[-4000:]
    )
    assert (
        "depthgt:   4 frame sets skipped for an unusable frame (unreadable), e.g. scan/scene0000_00/000004: "
        "frame 5: unreadable (" in console
    )
    assert "depthgt:   2 frame sets skipped for an unusable frame (nonfinite_pose)" in console
    assert f"depthgt: every skipped frame and frame set with its reason: {wd / 'results/dataset/summary.md'}" in console


def test_pretraining_skips_a_frame_set_with_an_unusable_frame(tmp_path, monkeypatch, caplog):
    """A drawn frame set holding an unreadable frame is skipped with a warning and the
    first spare of the draw replaces it; pretraining gets the usable sets it asked for."""
    from depthgt import registration
    from depthgt.gt.index import select_pretraining_framesets
    from depthgt.jobs.gt import run_pretrain_registration, run_scene_index
    from depthgt.registration import load_frameset

    config = dict(SMALL, registration={"method": "overfit", "preset": "fast", "pretrain": {"framesets": 3}})
    index_json = tmp_path / "index.json"
    run_scene_index(
        dict(SYN, scenes=["room_000"]), "room_000", config, str(tmp_path / "index.parquet"), str(index_json)
    )
    candidates = select_pretraining_framesets([str(index_json)], 3, config["seed"])
    assert len(candidates) == 14
    bad_frame = candidates[1][2][0]  # the target of the second drawn set
    usable = [c for c in candidates if bad_frame not in c[2]][:3]
    assert usable[:1] == candidates[:1] and usable[2] not in candidates[:3]  # a spare fills in

    real_read = synthetic.SyntheticScene.read

    def read(self, i):
        if i == bad_frame:
            raise FrameError(f"synthetic {self.name}: frame {i} unreadable (test)", "unreadable")
        return real_read(self, i)

    monkeypatch.setattr(synthetic.SyntheticScene, "read", read)
    seen = []

    def fake_pretrain(framesets, settings, epochs, seed):
        seen.extend(framesets)
        return {}

    monkeypatch.setattr(registration, "pretrain_encoder", fake_pretrain)
    with caplog.at_level(logging.WARNING, logger="depthgt"):
        run_pretrain_registration({"syn": SYN}, [str(index_json)], config, str(tmp_path / "encoder.pt"))
    assert (tmp_path / "encoder.pt").exists()
    assert any(
        "skipped, a frame is unusable" in r.getMessage() and f"frame {bad_frame} unreadable" in r.getMessage()
        for r in caplog.records
    )
    scene = open_source_scene(dict(SYN), "room_000", need_poses=False)
    assert len(seen) == 3
    for (_, _, members), (rgb, depth, _K, offsets) in zip(usable, seen):
        want = load_frameset(scene, members, (32, 32), need_poses=False, device=torch.device("cpu"))
        assert offsets == [m - members[0] for m in members]
        assert torch.equal(depth, want.depth_m) and torch.equal(rgb, want.rgb)


@pytest.mark.parametrize("need_pose", [False, True])
def test_resized_scene_reads_a_bad_frame_once(need_pose):
    """ResizedScene.check: each frame's outcome is remembered; an unusable frame is not
    read again, its error raised again on read; with need_pose a bad pose is unusable."""
    from depthgt.gt.cache import ResizedScene

    class Scene:
        name, image_size, has_poses, has_clean_depth = "s", (8, 8), True, False
        intrinsics = np.array([[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]])

        def __init__(self):
            self.reads = []

        def __len__(self):
            return 4

        def frame_id(self, i):
            return f"f{i}"

        def read(self, i):
            from depthgt.sources.base import Frame

            self.reads.append(i)
            if i == 1:
                raise FrameError("s/depth/1.png: unreadable", "unreadable")
            T = np.full((4, 4), np.inf) if i == 2 else np.eye(4)
            return Frame(np.zeros((8, 8, 3), np.uint8), np.ones((8, 8), np.float32), T)

    src = Scene()
    small = ResizedScene(src, (4, 4), need_pose=need_pose)
    outcomes = [small.check(i) for i in (0, 1, 2, 1, 0, 2)]
    assert src.reads == [0, 1, 2]
    assert [c.valid for c in small.checks] == [True, False, not need_pose]
    assert outcomes[1].reason == "unreadable" and outcomes[1].problem == "unreadable (s/depth/1.png: unreadable)"
    with pytest.raises(FrameError, match="depth/1.png"):
        small.read(1)
    assert src.reads == [0, 1, 2]
    if need_pose:
        assert small.checks[2].reason == "nonfinite_pose" and "s frame f2" in small.checks[2].message
