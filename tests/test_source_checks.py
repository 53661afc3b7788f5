"""Start-of-workflow checks of the sources: adapter options (torch-free, no data opened)
and scene identity (a scene twice, the same data under two sources or in two splits)."""

from __future__ import annotations

import inspect
import os
import subprocess
import sys
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import yaml

from depthgt.errors import ConfigError
from depthgt.sources import base

REPO = Path(__file__).resolve().parents[1]


# ------------------------------------------------------------------ options


@pytest.mark.parametrize("kind,options,message", [
    ("synthetic", {"n_frame": 10}, r"src\.options\.n_frame: unknown synthetic option; known options: cx, cy, family, fx"),
    ("synthetic", {"n_frames": 0}, r"src\.options\.n_frames: must be an integer in \[1, 1000000\], got 0"),
    ("synthetic", {"width": 100000}, r"src\.options\.width: must be an integer in \[32, 4096\], got 100000"),
    ("synthetic", {"noise": "yes"}, r"src\.options\.noise: must be true or false, got 'yes'"),
    ("synthetic", {"noise_sigma_disp_px": -1}, r"noise_sigma_disp_px: must be a number >= 0"),
    ("synthetic", {"noise_bogus": 1}, r"noise_bogus: unknown synthetic option"),
    ("scannet", {"depth_scale": 0}, r"depth_scale: must be a number > 0 \(raw depth units per metre\), got 0"),
    ("scannet", {"require_pose": 1}, r"require_pose: must be true or false, got 1"),
    ("scannet", {"intrinsics": [[1, 0], [0, 1]]}, r"intrinsics: must be a finite 3x3 \(or 4x4\) matrix"),
    ("scannet", {"max_dt": 0.1}, r"max_dt: unknown scannet option; known options: depth_scale, intrinsics, require_pose"),
    ("sevenscenes", {"intrinsics": [[585, 0, 320], [0, -585, 240], [0, 0, 1]]}, r"intrinsics: must be a finite 3x3"),
    ("tum", {"camera": "kinect2"}, r"camera: must be one of fr1, fr2, fr3, ros_default, got 'kinect2'"),
    ("tum", {"max_dt": float("nan")}, r"max_dt: must be a number >= 0, got nan"),
    ("tum", {"bogus": 1}, r"bogus: unknown tum option"),
    ("kinect9000", {}, r"src\.options: unknown source kind 'kinect9000'"),
    ("tum", [1, 2], r"src\.options: must be a mapping"),
])
def test_check_options_names_the_key(kind, options, message):
    with pytest.raises(ConfigError, match=message):
        base.check_options(kind, options, "src.options")


def test_check_options_accepts_valid_options():
    base.check_options("synthetic", {"n_frames": 48, "seed": 0, "width": 320, "height": 240, "fx": None,
                                     "noise": False, "noise_max_range_m": 4.0, "noise_round_mm": False}, "o")
    base.check_options("scannet", {"depth_scale": 1000, "require_pose": False, "intrinsics": np.eye(4).tolist()}, "o")
    base.check_options("sevenscenes", {"intrinsics": [[585, 0, 320], [0, 585, 240], [0, 0, 1]]}, "o")
    base.check_options("tum", {"max_dt": 0.02, "camera": "fr3", "depth_scale": 5000.0}, "o")
    base.check_options("tum", None, "o")


def test_option_names_match_the_adapters():
    """The torch-free option lists mirror the adapters (which import OpenCV or torch)."""
    from depthgt.sources import scannet, sevenscenes, synthetic, tum
    from depthgt.synth.noise import SENSOR_PROFILES, KinectNoise

    for kind, module in (("scannet", scannet), ("sevenscenes", sevenscenes), ("tum", tum)):
        params = list(inspect.signature(module.open_scene).parameters)[2:]
        assert base.option_names(kind) == sorted(params), kind
    assert base.SYNTHETIC_NOISE_FIELDS == tuple(f.name for f in fields(KinectNoise))
    assert base.SYNTHETIC_SENSORS == tuple(SENSOR_PROFILES) and base.SYNTHETIC_FAMILIES == synthetic.FAMILIES
    assert base.option_names("synthetic") == sorted(list(synthetic._DEFAULTS) + [f"noise_{n}" for n in base.SYNTHETIC_NOISE_FIELDS])
    assert synthetic._DEFAULTS["seed"] == base.SYNTHETIC_DEFAULT_SEED
    assert base.check_options("tum", {"camera": "fr2"}) is None and sorted(tum.CAMERAS) == ["fr1", "fr2", "fr3", "ros_default"]


def test_start_checks_import_neither_torch_nor_opencv():
    code = ("import sys; from depthgt.sources.base import check_options, check_scene_identity; "
            "check_options('synthetic', {'n_frames': 4}); check_options('tum', {'camera': 'fr1'}); "
            "check_scene_identity([{'name': 'a', 'kind': 'synthetic'}], {'a': ['room_000']}); "
            "heavy = [m for m in ('torch', 'cv2', 'kornia', 'OpenEXR', 'PIL') if m in sys.modules]; "
            "assert not heavy, heavy")
    subprocess.run([sys.executable, "-c", code], check=True, env=dict(os.environ, PYTHONPATH=str(REPO / "src")))


# ------------------------------------------------------------------ scene identity


def _src(name, kind="synthetic", split="train", root=None, **options):
    return {"name": name, "kind": kind, "root": root, "split": split, "options": options}


def test_scene_listed_twice_is_an_error():
    with pytest.raises(ConfigError, match=r"sources 'syn': scene 'room_000' is listed twice \(synthetic room 0 with seed "
                                          r"0\); every frame set would be built and counted twice"):
        base.check_scene_identity([_src("syn")], {"syn": ["room_000", "room_001", "room_000"]})
    with pytest.raises(ConfigError, match=r"scenes 'room_000' and 'room_0000' are the same data"):
        base.check_scene_identity([_src("syn")], {"syn": ["room_000", "room_0000"]})


def test_same_synthetic_room_under_two_sources():
    srcs = [_src("a", split="train", n_frames=14), _src("b", split="test", n_frames=32)]
    with pytest.raises(ConfigError, match=r"sources 'a' \(split: train\) and 'b' \(split: test\) hold the same data, "
                                          r"scene 'room_001' \(synthetic room 1 with seed 0\): identical ground truth "
                                          r"would end up in two splits"):
        base.check_scene_identity(srcs, {"a": ["room_000", "room_001"], "b": ["room_001"]})
    with pytest.raises(ConfigError, match=r"\(both split: test\) hold the same data.*counted twice"):
        base.check_scene_identity([_src("a", split="test"), _src("b", split="test")], {"a": ["room_002"], "b": ["room_002"]})
    with pytest.raises(ConfigError, match="two splits"):  # auto splits blocks per source: copies land in train and val
        base.check_scene_identity([_src("a", split="auto"), _src("b", split="auto")], {"a": ["room_002"], "b": ["room_002"]})
    # other rooms, or the same room number with another seed, are other data
    base.check_scene_identity(srcs, {"a": ["room_000"], "b": ["room_001"]})
    base.check_scene_identity([_src("a", seed=0), _src("b", split="test", seed=1)], {"a": ["room_000"], "b": ["room_000"]})


def test_same_folder_under_two_sources(tmp_path):
    """Resolved root + scene: a sequence as its own root ("." or its name), via its parent,
    or through a symbolic link is the same data, whatever the kind."""
    seq = tmp_path / "data" / "seq-01"
    seq.mkdir(parents=True)
    (tmp_path / "link").symlink_to(tmp_path / "data")
    keys = {base.scene_data_key("sevenscenes", tmp_path / "data", "seq-01"),
            base.scene_data_key("sevenscenes", seq, "."),
            base.scene_data_key("sevenscenes", seq, "seq-01"),
            base.scene_data_key("tum", tmp_path / "link", "seq-01")}
    assert keys == {("files", str(seq.resolve()))}
    (tmp_path / "data" / "scene0000_00.sens").write_bytes(b"")
    assert base.scene_data_key("scannet", tmp_path / "link", "scene0000_00") == \
        ("files", str((tmp_path / "data" / "scene0000_00.sens").resolve()))
    srcs = [_src("real", "sevenscenes", "test", root=str(seq)), _src("again", "sevenscenes", "train", root=str(tmp_path / "link"))]
    with pytest.raises(ConfigError, match=rf"sources 'real' \(split: test\) and 'again' \(split: train\) hold the same "
                                          rf"data, scenes '.' and 'seq-01' \({seq.resolve()}\): identical ground truth"):
        base.check_scene_identity(srcs, {"real": ["."], "again": ["seq-01"]})
    (tmp_path / "data" / "seq-02").mkdir()
    base.check_scene_identity(srcs, {"real": ["."], "again": ["seq-02"]})


# ------------------------------------------------------------------ in the workflow


def _dry_run(tmp_path, sources) -> subprocess.CompletedProcess:
    (tmp_path / "config").mkdir(parents=True)
    (tmp_path / "config" / "config.yaml").write_text(yaml.safe_dump({"sources": sources, "device": "cpu"}))
    cmd = [sys.executable, "-m", "snakemake", "-s", str(REPO / "Snakefile"), "-d", str(tmp_path), "-n", "--cores", "1"]
    return subprocess.run(cmd, capture_output=True, text=True, env=dict(os.environ, PYTHONPATH=str(REPO / "src")))


def test_workflow_stops_before_any_job(tmp_path):
    """`snakemake -n` refuses a duplicated scene, the same data in two splits and an
    unknown option, naming each (one run per case would cost a parse each)."""
    dup = [{"name": "syn", "kind": "synthetic", "scenes": ["room_000", "room_000"], "split": "train"},
           {"name": "held", "kind": "synthetic", "scenes": ["room_001"], "split": "train"},
           {"name": "heldout", "kind": "synthetic", "scenes": ["room_001"], "split": "test"}]
    proc = _dry_run(tmp_path / "dup", dup)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "ConfigError" in text
    assert "sources 'syn': scene 'room_000' is listed twice" in text
    assert "sources 'held' (split: train) and 'heldout' (split: test) hold the same data" in text
    bogus = [{"name": "syn", "kind": "synthetic", "scenes": ["room_000"], "options": {"n_frames": 8, "bogus": 1}}]
    proc = _dry_run(tmp_path / "opt", bogus)
    assert proc.returncode != 0
    assert "config key sources[syn].options.bogus: unknown synthetic option" in proc.stdout + proc.stderr
