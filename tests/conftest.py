"""Shared helpers of the tests: running the workflow on a config in a temporary workdir."""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]


def synthetic_source(name: str, scenes: list[str], split: str, n_frames: int, width: int, height: int) -> dict:
    """A ``sources`` entry of the synthetic kind."""
    return {
        "name": name,
        "kind": "synthetic",
        "scenes": scenes,
        "split": split,
        "options": {"n_frames": n_frames, "width": width, "height": height},
    }


# The tiny synthetic build that several test files read (tiny_build): two training
# rooms, a validation and a test room, one or two frame sets each.
TINY = {
    "seed": 3,
    "device": "cpu",
    "sources": [
        synthetic_source("syn", ["room_000", "room_001"], "train", 14, 320, 240),
        synthetic_source("synval", ["room_002"], "val", 13, 320, 240),
        synthetic_source("syntest", ["room_003"], "test", 13, 320, 240),
    ],
    "frameset": {"neighbours": 3, "stride": 2, "target_step": 1},
    "resize": 128,
    "patches": {"count": 6, "size": 64, "max_missing": 0.15, "filter_on": "gt"},
}


# The tiny enhancement build (tiny_report): a training, a validation and a test room at
# 160x120, the filter methods only (no training).
TINY_ENHANCE = {
    "seed": 1,
    "device": "cpu",
    "sources": [
        synthetic_source("syn", ["room_000"], "train", 10, 160, 120),
        synthetic_source("synval", ["room_002"], "val", 8, 160, 120),
        synthetic_source("syntest", ["room_003"], "test", 8, 160, 120),
    ],
    "frameset": {"neighbours": 1, "stride": 2, "target_step": 2},
    "resize": 64,
    "patches": {"count": 4, "size": 32, "max_missing": 0.2, "filter_on": "gt"},
    "enhance": {
        "train": {"epochs": 1, "batch_size": 4, "lr": 0.001, "max_batches_per_epoch": 2},
        "rde": {"voxel_m": 0.04, "frame_step": 1, "backend": "torch", "max_missing": 0.5},
    },
    "evaluation": {"methods": ["input", "rgf"], "figure_frames_per_scene": 1},
}


def snakemake(workdir: Path, *args: str, check: bool = True, **kw) -> subprocess.CompletedProcess:
    cmd = [
        sys.executable,
        "-m",
        "snakemake",
        "-s",
        str(REPO / "Snakefile"),
        "-d",
        str(workdir),
        "--cores",
        "2",
        "--rerun-incomplete",
        *args,
    ]
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env, **kw)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}")
    return proc


def make_workdir(path: Path, config: dict) -> Path:
    (path / "config").mkdir(parents=True)
    (path / "config" / "config.yaml").write_text(yaml.safe_dump(config))
    return path


def _normalised(name: str, data: bytes) -> bytes:
    """poses.json without its timings (wall-clock and CPU seconds); the dataset card
    without the checksums of the shards (their poses.json hold the timings)."""
    if name.endswith("poses.json"):
        doc = json.loads(data)
        doc.pop("timings_s", None)
        doc.pop("cpu_s", None)
        return json.dumps(doc, sort_keys=True).encode()
    if name == "card.json":
        doc = json.loads(data)
        doc["files"] = {k: v for k, v in doc["files"].items() if not k.endswith(".zip")}
        return json.dumps(doc, sort_keys=True).encode()
    return data


def digest_outputs(workdir: Path) -> dict[str, str]:
    """sha256 of every result file, and of every member of a zip archive (frame-set
    shards, RDE frames); poses.json without its timings. Temporary frame caches are not
    results."""
    out = {}
    for p in sorted((workdir / "results").rglob("*")):
        if not p.is_file() or p.parent.name == "frames":
            continue
        rel = str(p.relative_to(workdir))
        if p.suffix == ".zip":
            with zipfile.ZipFile(p) as z:
                for name in sorted(z.namelist()):
                    out[f"{rel}/{name}"] = hashlib.sha256(_normalised(name, z.read(name))).hexdigest()
            continue
        out[rel] = hashlib.sha256(_normalised(p.name, p.read_bytes())).hexdigest()
    return out


@pytest.fixture(scope="session")
def tiny_build(tmp_path_factory) -> Path:
    """TINY built to the ``dataset`` target once per test session, shared by the test
    files that only read it (test_workflow, test_data, test_profiles): a test that
    changes a build works on a copy or a build of its own."""
    wd = make_workdir(tmp_path_factory.mktemp("tiny"), TINY)
    snakemake(wd, "dataset")
    return wd


@pytest.fixture(scope="session")
def tiny_report(tmp_path_factory) -> Path:
    """TINY_ENHANCE built to the ``report`` target once per test session, shared by
    test_workflow_enhance (which reads it) and test_train_resume (which copies it)."""
    wd = make_workdir(tmp_path_factory.mktemp("tiny-report"), TINY_ENHANCE)
    snakemake(wd, "report")
    return wd


@pytest.fixture(scope="session", autouse=True)
def _started_early(request, tmp_path_factory):
    """A selected test module that defines ``start_early(tmp_path_factory)`` has it called
    at the session's start and the object it returns ``stop()``-ed at the end. test_slurm
    uses it: its runs spend most of their time waiting for the executor's job-state checks,
    so they are started before every other test and overlap with them."""
    modules = {getattr(item, "module", None) for item in request.session.items}  # doctests have none
    modules = {m for m in modules if hasattr(m, "start_early")}
    started = [m.start_early(tmp_path_factory) for m in sorted(modules, key=lambda m: m.__name__)]
    yield
    for s in started:
        s.stop()


@pytest.fixture(autouse=True)
def _torch_threads(request):
    """Torch's intra-op threads for each test: the module's ``TORCH_THREADS`` (default 2,
    the machine's cores). A module-level ``torch.set_num_threads`` would hold for the whole
    session from the last module collected; the modules whose in-process trainings ran
    several-fold slower with two threads beside other work (test_slurm's runs, a build) ask
    for one."""
    if "torch" in sys.modules:
        module = getattr(request.node, "module", None)  # a doctest has none
        sys.modules["torch"].set_num_threads(getattr(module, "TORCH_THREADS", 2))
    yield
