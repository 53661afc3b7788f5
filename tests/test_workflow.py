"""Runs the Snakemake workflow on a tiny synthetic config and checks the output layout,
resumption after kill -9, determinism, single-scene regeneration and bad config."""

from __future__ import annotations

import hashlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from depthgt.io import read_exr

REPO = Path(__file__).resolve().parents[1]
FRAMESET_FILES = ("gt.exr", "input.exr", "rgb.png", "poses.json", "patches.npz", "frameset.json")

TINY = {
    "seed": 3,
    "device": "cpu",
    "sources": [
        {"name": "syn", "kind": "synthetic", "scenes": ["room_000", "room_001"], "split": "train",
         "options": {"n_frames": 14, "width": 320, "height": 240}},
        {"name": "synval", "kind": "synthetic", "scenes": ["room_002"], "split": "val",
         "options": {"n_frames": 13, "width": 320, "height": 240}},
        {"name": "syntest", "kind": "synthetic", "scenes": ["room_003"], "split": "test",
         "options": {"n_frames": 13, "width": 320, "height": 240}},
    ],
    "frameset": {"neighbours": 3, "stride": 2, "target_step": 1},
    "resize": 128,
    "patches": {"count": 6, "size": 64, "max_missing": 0.15, "filter_on": "gt"},
}


def snakemake(workdir: Path, *args: str, check: bool = True, **kw) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(workdir), "--cores", "2",
           "--rerun-incomplete", *args]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, **kw)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}")
    return proc


def make_workdir(path: Path, config: dict) -> Path:
    (path / "config").mkdir(parents=True)
    (path / "config" / "config.yaml").write_text(yaml.safe_dump(config))
    return path


def digest_outputs(workdir: Path) -> dict[str, str]:
    """sha256 of every result file; poses.json without its timings (wall-clock); the
    temporary frame caches are not results."""
    out = {}
    for p in sorted((workdir / "results").rglob("*")):
        if not p.is_file() or p.parent.name == "frames":
            continue
        data = p.read_bytes()
        if p.name == "poses.json":
            doc = json.loads(data)
            doc.pop("timings_s", None)
            data = json.dumps(doc, sort_keys=True).encode()
        out[str(p.relative_to(workdir))] = hashlib.sha256(data).hexdigest()
    return out


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> Path:
    wd = make_workdir(tmp_path_factory.mktemp("wf"), TINY)
    snakemake(wd, "dataset")
    return wd


def test_layout(built):
    wd = built
    for dataset, scene in [("syn", "room_000"), ("syn", "room_001"), ("synval", "room_002"), ("syntest", "room_003")]:
        sdir = wd / "results/scenes" / dataset / scene
        assert (sdir / "index.parquet").exists() and (sdir / "index.json").exists()
        index = pd.read_parquet(sdir / "index.parquet")
        meta = json.loads((sdir / "index.json").read_text())
        assert len(index) == meta["n_frames"]
        for t in meta["framesets_ok"]:
            fdir = wd / "results/framesets" / dataset / scene / f"{t:06d}"
            for name in FRAMESET_FILES:
                assert (fdir / name).exists(), fdir / name
            gt = read_exr(fdir / "gt.exr")
            assert set(gt) == {"Z", "W", "N", "S"} and gt["Z"].shape == (128, 128)
            # S: the GT's expected std (metres), positive wherever there is GT depth
            assert (gt["S"][gt["Z"] > 0] > 0).all() and np.isfinite(gt["S"]).all()
            inp = read_exr(fdir / "input.exr")
            assert {"Z", "T"} <= set(inp)
            doc = json.loads((fdir / "frameset.json").read_text())
            assert doc["members"] == [t, t - 6, t - 4, t - 2, t + 2, t + 4, t + 6]
            assert doc["split"] == {"syn": "train", "synval": "val", "syntest": "test"}[dataset]
            poses = json.loads((fdir / "poses.json").read_text())
            assert sorted(poses["T_j_to_t"], key=int) == ["-6", "-4", "-2", "2", "4", "6"]
            with np.load(fdir / "patches.npz") as npz:
                assert npz["gt"].shape[1:] == (64, 64) and (npz["missing_gt"] < 0.15).all()
    for split in ("train", "val", "test"):
        m = pd.read_parquet(wd / f"results/dataset/{split}.parquet")
        assert len(m) > 0 and (m["split"] == split).all()
    summary = json.loads((wd / "results/dataset/summary.json").read_text())
    fs = pd.read_parquet(wd / "results/dataset/framesets.parquet")
    assert summary["patches_kept"] + summary["patches_rejected"] == summary["patches_drawn"] == 6 * (fs["status"] == "ok").sum()
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
    assert mean["gt", "mae_missing_counted"] < mean["input", "mae_missing_counted"]


def test_rerun_is_noop_and_deterministic(built, tmp_path):
    proc = snakemake(built, "dataset", "-n")
    assert "Nothing to be done" in proc.stdout + proc.stderr
    wd2 = make_workdir(tmp_path / "again", TINY)
    snakemake(wd2, "dataset")
    assert digest_outputs(wd2) == digest_outputs(built)


def test_kill9_resume_gives_identical_outputs(built, tmp_path):
    wd = make_workdir(tmp_path / "killed", TINY)
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(wd), "--cores", "2", "dataset"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    deadline = time.time() + 300
    while time.time() < deadline and len(list((wd / "results").rglob("frameset.json"))) < 2:
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()
    assert not (wd / "results/dataset/summary.json").exists(), "the build finished before it could be killed"
    snakemake(wd, "--unlock")  # a kill -9 leaves Snakemake's lock behind (README: resuming)
    snakemake(wd, "dataset")
    assert digest_outputs(wd) == digest_outputs(built)


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


def test_unknown_scene_is_clear(tmp_path):
    cfg = dict(TINY, sources=[{"name": "x", "kind": "synthetic", "scenes": ["kitchen"], "split": "train"}])
    wd = make_workdir(tmp_path / "unk", cfg)
    proc = snakemake(wd, "dataset", check=False)
    assert proc.returncode != 0
    assert "kitchen" in (proc.stdout + proc.stderr) + "".join(p.read_text() for p in (wd / "logs").rglob("*.log"))


def test_overfit_registration_in_workflow(tmp_path):
    """registration.method overfit: pretraining rule, then every frame set registered
    without the source's poses; estimated poses close to the reference ones."""
    cfg = {
        "seed": 0, "device": "cpu",
        "sources": [{"name": "syn", "kind": "synthetic", "scenes": ["room_000"], "split": "train",
                     "options": {"n_frames": 13, "width": 320, "height": 240}}],
        "registration": {"method": "overfit", "preset": "fast", "pretrain": {"framesets": 1}},
        "resize": 128, "patches": {"count": 2, "size": 64},
    }
    wd = make_workdir(tmp_path / "reg", cfg)
    snakemake(wd, "dataset")
    assert (wd / "results/models/registration/encoder.pt").exists()
    poses = json.loads((wd / "results/framesets/syn/room_000/000006/poses.json").read_text())
    assert poses["registration"]["method"] == "overfit" and poses["registration"]["status"] == "ok"
    for off, T in poses["T_j_to_t"].items():
        T, ref = np.array(T), np.array(poses["T_j_to_t_reference"][off])
        assert np.linalg.norm(T[:3, 3] - ref[:3, 3]) < 0.01  # metres
        cos = (np.trace(T[:3, :3] @ ref[:3, :3].T) - 1) / 2
        assert np.degrees(np.arccos(np.clip(cos, -1, 1))) < 0.5
