"""Runs the Snakemake workflow on a tiny synthetic config (conftest.TINY, built once per
session) and checks the output layout, single-scene regeneration and bad config.
Resumption after kill -9 and the determinism of a second build: test_profiles.py."""

from __future__ import annotations

import copy
import json
import re
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from conftest import TINY, early, in_background, make_workdir, snakemake, synthetic_source

from depthgt.gt import store
from depthgt.io import read_exr

_NO_CUDA = "config key device: cuda was asked for but no CUDA device is available"
FRAMESET_FILES = ("gt.exr", "input.exr", "rgb.webp", "poses.json", "patches.npz", "frameset.json")


@pytest.fixture(scope="module")
def built(tiny_build) -> Path:
    return tiny_build


def test_layout(built):
    wd = built
    for dataset, scene in [("syn", "room_000"), ("syn", "room_001"), ("synval", "room_002"), ("syntest", "room_003")]:
        sdir = wd / "results/scenes" / dataset / scene
        assert (sdir / "index.parquet").exists() and (sdir / "index.json").exists()
        index = pd.read_parquet(sdir / "index.parquet")
        meta = json.loads((sdir / "index.json").read_text())
        assert len(index) == meta["n_frames"] and list(index["position"]) == list(range(meta["n_frames"]))
        assert "valid" not in index.columns  # the index reads no frame: the batches check them
        shards = sorted((wd / "results/framesets" / dataset / scene).glob("*.zip"))
        # TINY: 1 or 2 frame sets per scene (13 or 14 frames), one batch (batch_size 32): one shard
        targets = [6, 7][: meta["n_frames"] - 12]
        assert meta["framesets_planned"] == targets
        assert [p.name for p in shards] == [f"000006-{targets[-1]:06d}.zip"]
        batch = store.read_batch(shards[0])
        assert [r["target"] for r in batch] == targets and all(r["status"] == "ok" for r in batch)
        assert store.shard_targets(shards[0]) == targets
        # every member frame was read once by the batch and found usable
        frames = store.read_batch_frames(shards[0])
        members = sorted({m for r in batch for m in r["members"]})
        assert [f["position"] for f in frames] == members and all(f["valid"] and not f["reason"] for f in frames)
        scene_frames = pd.read_parquet(sdir / "frames.parquet")
        assert list(scene_frames["position"]) == members and scene_frames["valid"].all()
        for t in targets:
            loc = store.find_frameset(wd / "results", dataset, scene, t)
            assert loc == store.location(shards[0], t)
            with store.frameset_files(loc) as fdir:
                assert sorted(p.name for p in fdir.iterdir()) == sorted(FRAMESET_FILES)
                gt = read_exr(fdir / "gt.exr")
                inp = read_exr(fdir / "input.exr")
            assert set(gt) == {"Z", "S"} and gt["Z"].shape == (128, 128)
            # S: the GT's expected std (metres), positive wherever there is GT depth
            assert (gt["S"][gt["Z"] > 0] > 0).all() and np.isfinite(gt["S"]).all()
            assert {"Z", "T"} <= set(inp)
            doc = store.read_json(f"{loc}/frameset.json")
            assert doc["members"] == [t, t - 6, t - 4, t - 2, t + 2, t + 4, t + 6]
            assert doc["split"] == {"syn": "train", "synval": "val", "syntest": "test"}[dataset]
            poses = store.read_json(f"{loc}/poses.json")
            assert sorted(poses["T_j_to_t"], key=int) == ["-6", "-4", "-2", "2", "4", "6"]
            npz = store.read_patches_at(loc)
            assert npz["gt"].shape[1:] == (64, 64) and (npz["missing_gt"] < 0.15).all()
        # the scene's manifest points into the shard
        fs = pd.read_parquet(sdir / "framesets.parquet")
        assert set(fs.loc[fs["status"] == "ok", "frameset"]) == {
            store.location(f"results/framesets/{dataset}/{scene}/{shards[0].name}", t) for t in targets
        }
    for split in ("train", "val", "test"):
        m = pd.read_parquet(wd / f"results/dataset/{split}.parquet")
        assert len(m) > 0 and (m["split"] == split).all()
    summary = json.loads((wd / "results/dataset/summary.json").read_text())
    fs = pd.read_parquet(wd / "results/dataset/framesets.parquet")
    assert (
        summary["patches_kept"] + summary["patches_rejected"]
        == summary["patches_drawn"]
        == 6 * (fs["status"] == "ok").sum()
    )
    # the members of targets 6 and 7 (14 frames: 0..13) in syn's rooms, of target 6 alone (0, 2, .., 12) in the
    # others: every frame read once, none unusable
    assert summary["frames_read"] == 14 + 14 + 7 + 7 and summary["frames_skipped"] == []
    assert summary["framesets_skipped"] == []
    q = pd.read_csv(wd / "results/dataset/gt_quality.csv")
    assert {"gt", "input"} <= set(q["estimate"])
    # the frame cache is temporary: gone once every frame set is built
    assert not (wd / "results/scenes/syn/room_000/frames").exists()
    # every rule logged
    assert (wd / "logs/dataset.log").exists() and any((wd / "logs/framesets").rglob("*.log"))


def test_gt_beats_input_on_tiny_scenes(built):
    q = pd.read_csv(built / "results/dataset/gt_quality.csv")
    mean = q.groupby(["estimate", "metric"])["value"].mean()
    assert mean["gt", "completeness"] > mean["input", "completeness"]
    assert mean["gt", "mae_missing_counted_m"] < mean["input", "mae_missing_counted_m"]


def test_rerun_is_noop(built):
    """A finished build has nothing left to do. (A second build in another folder, killed
    and resumed, gives the same files: test_profiles.py.)"""
    proc = snakemake(built, "dataset", "-n")
    assert "Nothing to be done" in proc.stdout + proc.stderr


def test_single_scene_regeneration(built):
    target = "results/scenes/syn/room_001/framesets.parquet"
    proc = snakemake(built, "--forceall", target, "-n")
    text = proc.stdout + proc.stderr
    assert "room_001" in text and "room_000" not in text and "room_002" not in text


def test_bad_config_names_key(tmp_path):
    bad = dict(TINY, patches={"count": 6, "size": 64, "filter_on": "rgb"}, bogus=1)
    wd = make_workdir(tmp_path / "bad", bad)
    proc = snakemake(wd, "-n", check=False)
    assert proc.returncode != 0
    text = proc.stdout + proc.stderr
    assert "patches.filter_on" in text and "bogus" in text


CONFIG_CASES = [
    ("size", {"resize": 32}, "patches.size"),  # a patch larger than the working resolution
    ("reg", {"registration": {"method": "given", "n_blockz": 1}}, "registration.n_blockz"),  # whatever the method
    ("render_key", {"render": {"bogus": 1}}, "render.bogus"),
    ("render_m", {"render": {"m": 0}}, "render.m"),
    ("train", {"enhance": {"train": {"epoch": 3}}}, "enhance.train"),
    (
        "options",
        {
            "sources": [
                {
                    "name": "syn",
                    "kind": "synthetic",
                    "scenes": ["room_000"],
                    "split": "train",
                    "options": {"n_frames": 12, "n_frame": 3},
                }
            ]
        },
        "sources[syn].options.n_frame",
    ),
    ("count", {"patches": {"count": 1_000_000_000, "size": 64}}, "patches.count"),
]


@pytest.mark.parametrize("name, extra, key", CONFIG_CASES)
def test_settings_name_the_key(name, extra, key):
    """Issue 10's config cases fail naming the key, in the checks the workflow makes when
    it starts (workflow/rules/common.smk: every stage's settings, then what no single
    section decides). That the workflow makes them before any job:
    test_settings_are_checked_before_any_job."""
    from depthgt.errors import ConfigError
    from depthgt.settings import check_workflow, settings_from_config

    config = copy.deepcopy({**TINY, **extra})
    with pytest.raises(ConfigError, match=re.escape(key)):
        check_workflow(settings_from_config(config))


@pytest.mark.parametrize("name, extra, key", [CONFIG_CASES[0], ("cuda", {"device": "cuda"}, _NO_CUDA)])
def test_settings_are_checked_before_any_job(tmp_path, name, extra, key):
    """The workflow stops before any job, naming the key: a check across sections
    (patches.size against resize) and device: cuda without a GPU."""
    from depthgt.device import cuda_device_count

    wd = make_workdir(tmp_path / name, {**TINY, **extra})
    if name == "cuda":
        if cuda_device_count() > 0:  # a machine with a GPU: device: cuda is fine
            assert snakemake(wd, "-n", check=False).returncode == 0
            return
        # checked once the executor is known (a SLURM run submits from a node without a
        # GPU): a real local run, stopped before its first job
        proc = snakemake(wd, check=False)
    else:
        proc = snakemake(wd, "-n", check=False)
    assert proc.returncode != 0 and key in proc.stdout + proc.stderr, (proc.stdout + proc.stderr)[-2000:]
    assert not (wd / "results").exists() and not (wd / "logs").exists()


def test_unknown_scene_is_clear(tmp_path):
    cfg = dict(TINY, sources=[{"name": "x", "kind": "synthetic", "scenes": ["kitchen"], "split": "train"}])
    wd = make_workdir(tmp_path / "unk", cfg)
    proc = snakemake(wd, "dataset", check=False)
    assert proc.returncode != 0
    assert "kitchen" in (proc.stdout + proc.stderr) + "".join(p.read_text() for p in (wd / "logs").rglob("*.log"))


@early()
def overfit_build(folder: Path):
    """TINY's first room built to ``dataset`` with the overfit registration (an early run)."""
    cfg = {
        "seed": 0,
        "device": "cpu",
        "sources": [synthetic_source("syn", ["room_000"], "train", 13, 320, 240)],
        "registration": {"method": "overfit", "preset": "fast", "pretrain": {"framesets": 1}},
        "resize": 128,
        "patches": {"count": 2, "size": 64},
    }
    return in_background(make_workdir(folder / "reg", cfg), "dataset")


def test_overfit_registration_in_workflow(overfit_build):
    """registration.method overfit: pretraining rule, then every frame set registered
    without the source's poses; estimated poses close to the reference ones."""
    wd = overfit_build
    assert (wd / "results/models/registration/encoder.pt").exists()
    poses = store.read_json(f"{store.find_frameset(wd / 'results', 'syn', 'room_000', 6)}/poses.json")
    assert poses["registration"]["method"] == "overfit" and poses["registration"]["status"] == "ok"
    for off, T in poses["T_j_to_t"].items():
        T, ref = np.array(T), np.array(poses["T_j_to_t_reference"][off])
        assert np.linalg.norm(T[:3, 3] - ref[:3, 3]) < 0.01  # metres
        cos = (np.trace(T[:3, :3] @ ref[:3, :3].T) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 0.5


def test_store_reads_and_extracts_a_frameset(built, tmp_path):
    """depthgt.gt.store gives one built frame set's arrays and copies its files out."""
    from depthgt.errors import DepthGTError
    from depthgt.gt.store import extract_frameset, read_frameset

    meta = json.loads((built / "results/scenes/syn/room_000/index.json").read_text())
    target = meta["framesets_planned"][0]
    rec = read_frameset(built / "results", "syn", "room_000", target)
    assert rec.gt_m.shape == rec.input_m.shape == rec.gt_sigma_m.shape == rec.rgb.shape[:2] == (128, 128)
    assert rec.truth_m is not None and rec.meta["target"] == target and rec.patches["kept"].dtype == bool
    assert (rec.gt_sigma_m[rec.gt_m > 0] > 0).all()
    written = extract_frameset(built / "results", "syn", "room_000", target, tmp_path / "one")
    assert sorted(p.name for p in written) == sorted(FRAMESET_FILES)
    np.testing.assert_array_equal(read_exr(tmp_path / "one" / "gt.exr")["Z"], rec.gt_m)
    with pytest.raises(DepthGTError, match="not built"):
        read_frameset(built / "results", "syn", "room_000", 999_999)
