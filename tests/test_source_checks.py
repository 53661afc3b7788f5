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


@pytest.mark.parametrize(
    "kind,options,message",
    [
        (
            "synthetic",
            {"n_frame": 10},
            r"src\.options\.n_frame: unknown synthetic option; known options: cx, cy, family, fx",
        ),
        ("synthetic", {"n_frames": 0}, r"src\.options\.n_frames: must be an integer in \[1, 1000000\], got 0"),
        ("synthetic", {"width": 100000}, r"src\.options\.width: must be an integer in \[32, 4096\], got 100000"),
        ("synthetic", {"noise": "yes"}, r"src\.options\.noise: must be true or false, got 'yes'"),
        ("synthetic", {"noise_sigma_disp_px": -1}, r"noise_sigma_disp_px: must be a number >= 0"),
        ("synthetic", {"noise_bogus": 1}, r"noise_bogus: unknown synthetic option"),
        ("scannet", {"depth_scale": 0}, r"depth_scale: must be a number > 0 \(raw depth units per metre\), got 0"),
        ("scannet", {"require_pose": 1}, r"require_pose: must be true or false, got 1"),
        ("scannet", {"intrinsics": [[1, 0], [0, 1]]}, r"intrinsics: must be a finite 3x3 \(or 4x4\) matrix"),
        (
            "scannet",
            {"max_dt": 0.1},
            r"max_dt: unknown scannet option; known options: depth_scale, intrinsics, require_pose",
        ),
        (
            "sevenscenes",
            {"intrinsics": [[585, 0, 320], [0, -585, 240], [0, 0, 1]]},
            r"intrinsics: must be a finite 3x3",
        ),
        ("tum", {"camera": "kinect2"}, r"camera: must be one of fr1, fr2, fr3, ros_default, got 'kinect2'"),
        ("tum", {"max_dt": float("nan")}, r"max_dt: must be a number >= 0, got nan"),
        ("tum", {"bogus": 1}, r"bogus: unknown tum option"),
        ("kinect9000", {}, r"src\.options: unknown source kind 'kinect9000'"),
        ("tum", [1, 2], r"src\.options: must be a mapping"),
    ],
)
def test_check_options_names_the_key(kind, options, message):
    with pytest.raises(ConfigError, match=message):
        base.check_options(kind, options, "src.options")


def test_check_options_accepts_valid_options():
    base.check_options(
        "synthetic",
        {
            "n_frames": 48,
            "seed": 0,
            "width": 320,
            "height": 240,
            "fx": None,
            "noise": False,
            "noise_max_range_m": 4.0,
            "noise_round_mm": False,
        },
        "o",
    )
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
    assert base.option_names("synthetic") == sorted(
        list(synthetic._DEFAULTS) + [f"noise_{n}" for n in base.SYNTHETIC_NOISE_FIELDS]
    )
    assert synthetic._DEFAULTS["seed"] == base.SYNTHETIC_DEFAULT_SEED
    assert base.check_options("tum", {"camera": "fr2"}) is None and sorted(tum.CAMERAS) == [
        "fr1",
        "fr2",
        "fr3",
        "ros_default",
    ]


def test_the_registry_holds_every_kind_once():
    """One entry per kind (sources.base.KINDS): every adapter module has the functions
    its entry promises; a kind whose poses are optional takes require_pose; only
    synthetic colour matches its depth by default, and only synthetic scenes know the
    noise-free depth (``has_truth``, what the scenes it opens say)."""
    import importlib

    assert base.known_kinds() == sorted(base.KINDS)
    for kind, entry in base.KINDS.items():
        module = importlib.import_module(entry.module)
        assert callable(module.open_scene) and callable(module.list_scenes), kind
        assert entry.single_file == hasattr(module, "scene_file"), kind
        params = inspect.signature(module.open_scene).parameters
        assert entry.poses_optional == ("require_pose" in params), kind
    assert {k for k, e in base.KINDS.items() if e.colour_matches_depth} == {"synthetic"}
    assert {k for k, e in base.KINDS.items() if e.single_file} == {"scannet"}
    assert base.KINDS["synthetic"].has_truth and not any(
        base.KINDS[k].has_truth for k in ("scannet", "sevenscenes", "tum")
    )
    scene = base.open_scene("synthetic", None, "room_000", n_frames=2, width=32, height=32)
    assert scene.has_clean_depth is base.KINDS["synthetic"].has_truth is True
    with pytest.raises(ValueError, match="poses_optional needs the option require_pose"):
        base.SourceKind("depthgt.sources.tum", {}, poses_optional=True)


def test_a_registered_kind_is_known_everywhere(tmp_path):
    """Adding a kind is its module and its entry: the settings, the option checks, the
    scene opener (lazily importing the module) and the job's poses rule follow."""
    from depthgt.jobs.common import open_source_scene
    from depthgt.settings import settings_from_config

    (tmp_path / "flatcam.py").write_text(
        "import numpy as np\n"
        "from depthgt.sources.base import Frame\n"
        "class Flat:\n"
        "    name, intrinsics, image_size = 'one', np.eye(3), (4, 4)\n"
        "    has_poses, has_clean_depth = True, False\n"
        "    def __init__(self, require_pose): self.require_pose = require_pose\n"
        "    def __len__(self): return 2\n"
        "    def frame_id(self, i): return str(i)\n"
        "    def read(self, i): return Frame(np.zeros((4, 4, 3), np.uint8), np.ones((4, 4), np.float32), np.eye(4))\n"
        "def open_scene(root, scene, require_pose=True): return Flat(require_pose)\n"
        "def list_scenes(root): return ['one']\n"
    )
    sys.path.insert(0, str(tmp_path))
    try:
        base.register(
            "flatcam",
            base.SourceKind(
                "flatcam",
                {"require_pose": base.OptionCheck("true or false", lambda v: isinstance(v, bool))},
                poses_optional=True,
            ),
        )
        src = {"name": "f", "kind": "flatcam", "scenes": ["one"], "options": {"require_pose": True}}
        assert settings_from_config({"sources": [src]}).sources[0].kind == "flatcam"
        with pytest.raises(ConfigError, match=r"sources\[f\]\.options\.bogus: unknown flatcam option"):
            settings_from_config({"sources": [{**src, "options": {"bogus": 1}}]})
        assert base.frame_count("flatcam", None, "one") == 2 and base.list_scenes("flatcam", None) == ["one"]
        scene = open_source_scene({**src, "options": {}}, "one", need_poses=False)
        assert scene.require_pose is False and scene.colour_matches_depth is False
        assert open_source_scene({**src, "colour_matches_depth": True}, "one").colour_matches_depth is True
    finally:
        base.KINDS.pop("flatcam", None)
        sys.path.remove(str(tmp_path))
        sys.modules.pop("flatcam", None)


@pytest.mark.parametrize("value,ok", [("auto", True), (True, True), (False, True), ("yes", False), (1, False)])
def test_colour_matches_depth_setting_names_the_key(value, ok):
    from depthgt.settings import settings_from_config

    config = {"sources": [{"name": "s", "kind": "scannet", "root": "/x", "colour_matches_depth": value}]}
    if ok:
        assert settings_from_config(config).sources[0].colour_matches_depth == value
    else:
        with pytest.raises(ConfigError, match=r"sources\[(s|0)\]\.colour_matches_depth: must be"):
            settings_from_config(config)


def test_start_checks_import_neither_torch_nor_opencv():
    code = (
        "import sys; from depthgt.sources.base import check_options, check_scene_identity; "
        "check_options('synthetic', {'n_frames': 4}); check_options('tum', {'camera': 'fr1'}); "
        "check_scene_identity([{'name': 'a', 'kind': 'synthetic'}], {'a': ['room_000']}); "
        "heavy = [m for m in ('torch', 'cv2', 'kornia', 'OpenEXR', 'PIL') if m in sys.modules]; "
        "assert not heavy, heavy"
    )
    subprocess.run([sys.executable, "-c", code], check=True, env=dict(os.environ, PYTHONPATH=str(REPO / "src")))


# ------------------------------------------------------------------ scene identity


def _src(name, kind="synthetic", split="train", root=None, **options):
    return {"name": name, "kind": kind, "root": root, "split": split, "options": options}


def test_scene_listed_twice_is_an_error():
    with pytest.raises(
        ConfigError,
        match=r"sources 'syn': scene 'room_000' is listed twice \(synthetic room 0 with seed "
        r"0\); every frame set would be built and counted twice",
    ):
        base.check_scene_identity([_src("syn")], {"syn": ["room_000", "room_001", "room_000"]})
    with pytest.raises(ConfigError, match=r"scenes 'room_000' and 'room_0000' are the same data"):
        base.check_scene_identity([_src("syn")], {"syn": ["room_000", "room_0000"]})


def test_same_synthetic_room_under_two_sources():
    srcs = [_src("a", split="train", n_frames=14), _src("b", split="test", n_frames=32)]
    with pytest.raises(
        ConfigError,
        match=r"sources 'a' \(split: train\) and 'b' \(split: test\) hold the same data, "
        r"scene 'room_001' \(synthetic room 1 with seed 0\): identical ground truth "
        r"would end up in two splits",
    ):
        base.check_scene_identity(srcs, {"a": ["room_000", "room_001"], "b": ["room_001"]})
    with pytest.raises(ConfigError, match=r"\(both split: test\) hold the same data.*counted twice"):
        base.check_scene_identity(
            [_src("a", split="test"), _src("b", split="test")], {"a": ["room_002"], "b": ["room_002"]}
        )
    with pytest.raises(ConfigError, match="two splits"):  # auto splits blocks per source: copies land in train and val
        base.check_scene_identity(
            [_src("a", split="auto"), _src("b", split="auto")], {"a": ["room_002"], "b": ["room_002"]}
        )
    # other rooms, or the same room number with another seed, are other data
    base.check_scene_identity(srcs, {"a": ["room_000"], "b": ["room_001"]})
    base.check_scene_identity(
        [_src("a", seed=0), _src("b", split="test", seed=1)], {"a": ["room_000"], "b": ["room_000"]}
    )


def test_same_folder_under_two_sources(tmp_path):
    """Resolved root + scene: a sequence as its own root ("." or its name), via its parent,
    or through a symbolic link is the same data, whatever the kind."""
    seq = tmp_path / "data" / "seq-01"
    seq.mkdir(parents=True)
    (tmp_path / "link").symlink_to(tmp_path / "data")
    keys = {
        base.scene_data_key("sevenscenes", tmp_path / "data", "seq-01"),
        base.scene_data_key("sevenscenes", seq, "."),
        base.scene_data_key("sevenscenes", seq, "seq-01"),
        base.scene_data_key("tum", tmp_path / "link", "seq-01"),
    }
    assert keys == {("files", str(seq.resolve()))}
    (tmp_path / "data" / "scene0000_00.sens").write_bytes(b"")
    assert base.scene_data_key("scannet", tmp_path / "link", "scene0000_00") == (
        "files",
        str((tmp_path / "data" / "scene0000_00.sens").resolve()),
    )
    srcs = [
        _src("real", "sevenscenes", "test", root=str(seq)),
        _src("again", "sevenscenes", "train", root=str(tmp_path / "link")),
    ]
    with pytest.raises(
        ConfigError,
        match=rf"sources 'real' \(split: test\) and 'again' \(split: train\) hold the same "
        rf"data, scenes '.' and 'seq-01' \({seq.resolve()}\): identical ground truth",
    ):
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
    dup = [
        {"name": "syn", "kind": "synthetic", "scenes": ["room_000", "room_000"], "split": "train"},
        {"name": "held", "kind": "synthetic", "scenes": ["room_001"], "split": "train"},
        {"name": "heldout", "kind": "synthetic", "scenes": ["room_001"], "split": "test"},
    ]
    proc = _dry_run(tmp_path / "dup", dup)
    text = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "ConfigError" in text
    assert "sources 'syn': scene 'room_000' is listed twice" in text
    assert "sources 'held' (split: train) and 'heldout' (split: test) hold the same data" in text
    bogus = [{"name": "syn", "kind": "synthetic", "scenes": ["room_000"], "options": {"n_frames": 8, "bogus": 1}}]
    proc = _dry_run(tmp_path / "opt", bogus)
    assert proc.returncode != 0
    assert "config key sources[syn].options.bogus: unknown synthetic option" in proc.stdout + proc.stderr


def test_a_kind_registered_outside_depthgt_passes_the_workflow_checks(tmp_path):
    """A kind defined outside depthgt (its module registers it, imported by the user's
    own Snakefile before it includes depthgt's) passes every check the workflow makes
    when it starts, and its scenes are planned: a dry run lists their frame-set batches."""
    (tmp_path / "flatcam.py").write_text(
        "import numpy as np\n"
        "from depthgt.sources import base\n"
        "class Flat:\n"
        "    name, intrinsics, image_size = 'one', np.eye(3), (4, 4)\n"
        "    has_poses, has_clean_depth, colour_matches_depth = True, False, False\n"
        "    def __len__(self): return 20\n"
        "    def frame_id(self, i): return str(i)\n"
        "    def read(self, i): raise NotImplementedError\n"
        "def open_scene(root, scene): return Flat()\n"
        "def list_scenes(root): return ['one']\n"
        "base.register('flatcam', base.SourceKind('flatcam', {}))\n"
    )
    (tmp_path / "Snakefile").write_text(
        f"import sys\nsys.path.insert(0, {str(tmp_path)!r})\nimport flatcam  # registers the kind\n\n"
        f"include: {str(REPO / 'Snakefile')!r}\n"
    )
    (tmp_path / "config").mkdir()
    source = {"name": "flat", "kind": "flatcam", "root": str(tmp_path), "scenes": "all", "split": "test"}
    (tmp_path / "config/config.yaml").write_text(yaml.safe_dump({"sources": [source], "device": "cpu"}))
    cmd = [sys.executable, "-m", "snakemake", "-s", str(tmp_path / "Snakefile"), "-d", str(tmp_path)]
    proc = subprocess.run(
        [*cmd, "-n", "--cores", "1", "framesets"],
        capture_output=True,
        text=True,
        env=dict(os.environ, PYTHONPATH=str(REPO / "src")),
    )
    assert proc.returncode == 0, (proc.stdout + proc.stderr)[-3000:]
    assert "results/framesets/flat/one/000006-000013.zip" in proc.stdout
