"""The ``depthgt`` command on a tiny config: every subcommand, run for real."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from conftest import REPO, TINY, make_workdir

from depthgt.cli import scene_outputs

SUBCOMMANDS = ("build", "rebuild", "show", "extract", "report", "bench", "evaluate")


def depthgt(*args: str, check: bool = True, cwd: Path | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run(
        [sys.executable, "-m", "depthgt.cli", *args],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=dict(os.environ, OMP_NUM_THREADS="1"),
    )
    if check and proc.returncode != 0:
        raise AssertionError(
            f"depthgt {' '.join(args)} failed ({proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}"
        )
    return proc


@pytest.fixture(scope="module")
def built(tiny_build) -> Path:
    return tiny_build  # conftest: built once per session; read-only here (rebuild works on a copy)


def test_console_script_is_declared():
    text = (REPO / "pyproject.toml").read_text()
    assert 'depthgt = "depthgt.cli:main"' in text


@pytest.mark.parametrize("sub", SUBCOMMANDS)
def test_help_of_each_subcommand(sub):
    out = depthgt(sub, "--help").stdout
    assert out.startswith(f"usage: depthgt {sub}")


def test_build_dry_run_lists_jobs_and_builds_nothing(tmp_path):
    wd = make_workdir(tmp_path / "dry", TINY)
    proc = depthgt("build", "-d", str(wd), "--cores", "1", "--dry-run", "framesets")
    assert "scene_summary" in proc.stdout + proc.stderr
    assert not (wd / "results").exists()


def test_build_names_a_bad_config_key(tmp_path):
    wd = make_workdir(tmp_path / "bad", dict(TINY, resize=16))
    proc = depthgt("build", "-d", str(wd), "--cores", "1", "-n", check=False)
    assert proc.returncode != 0
    assert "resize" in proc.stdout + proc.stderr


def test_build_names_a_config_file_that_is_not_valid_yaml(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("seed: 0\nframeset: {neighbours: [3\n")
    proc = depthgt("build", "-d", str(tmp_path / "wd"), "-n", "--configfile", str(bad), check=False)
    assert proc.returncode == 2 and f"--configfile {bad}:3:1: not valid YAML" in proc.stderr
    proc = depthgt("build", "-d", str(tmp_path / "wd"), "-n", "--configfile", str(tmp_path / "none.yaml"), check=False)
    assert proc.returncode == 2 and "none.yaml: file not found" in proc.stderr
    # what Snakemake reads passes: JSON (tabs included) and YAML
    from depthgt.cli import _check_yaml_files

    (tmp_path / "tabs.json").write_text('{\n\t"seed": 1\n}')
    (tmp_path / "ok.yaml").write_text("seed: 1\n")
    _check_yaml_files([tmp_path / "tabs.json", tmp_path / "ok.yaml"])


def test_build_names_a_source_whose_scenes_all_finds_nothing(tmp_path):
    (tmp_path / "empty").mkdir()
    source = {"name": "mine", "kind": "sevenscenes", "root": str(tmp_path / "empty"), "scenes": "all", "split": "train"}
    wd = make_workdir(tmp_path / "wd", dict(TINY, sources=[*TINY["sources"], source]))
    proc = depthgt("build", "-d", str(wd), "--cores", "1", "-n", check=False)
    assert proc.returncode != 0
    assert "sources[mine]: scenes: all finds no sevenscenes scene under" in proc.stdout + proc.stderr


def test_show_prints_statistics_and_writes_a_panel(built, tmp_path):
    out = tmp_path / "panel.png"
    proc = depthgt("show", "-d", str(built), "syn", "room_000", "6", "--out", str(out))
    stats = dict(line.split(None, 1) for line in proc.stdout.splitlines() if line and not line.startswith("panel"))
    # the statistics of frameset.json, under its names
    assert float(stats["gt_missing"]) < float(stats["input_missing"]) + 0.05
    assert float(stats["gt_median_sigma_m"]) > 0
    # synthetic scenes know the truth: the GT is scored against it
    assert float(stats["gt_vs_truth.mae_m"]) < 0.05
    import cv2

    img = cv2.imread(str(out))
    assert img is not None and img.shape[1] > 4 * img.shape[0] / 1.5  # five panels side by side


def test_show_names_a_frame_set_that_was_not_built(built):
    proc = depthgt("show", "-d", str(built), "syn", "room_000", "999", check=False)
    assert proc.returncode == 2 and "not built" in proc.stderr and "000999" in proc.stderr


def test_extract_writes_the_frame_set_files(built, tmp_path):
    proc = depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "fs"))
    names = sorted(Path(p).name for p in proc.stdout.split())
    assert names == sorted(["gt.exr", "input.exr", "rgb.webp", "poses.json", "patches.npz", "frameset.json"])
    from depthgt.io import read_exr

    assert read_exr(tmp_path / "fs" / "gt.exr")["Z"].shape == (TINY["resize"],) * 2
    # a folder holding such files is not overwritten without --force; bad folders are named
    (tmp_path / "fs" / "gt.exr").write_bytes(b"mine")
    proc = depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "fs"), check=False)
    assert proc.returncode == 2 and "already holds gt.exr" in proc.stderr and "--force" in proc.stderr
    assert (tmp_path / "fs" / "gt.exr").read_bytes() == b"mine"
    depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "fs"), "--force")
    assert read_exr(tmp_path / "fs" / "gt.exr")["Z"].shape == (TINY["resize"],) * 2
    (tmp_path / "afile").write_text("")
    proc = depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "afile" / "x"), check=False)
    assert proc.returncode == 2 and "afile" in proc.stderr and "Traceback" not in proc.stderr
    proc = depthgt("extract", "-d", str(tmp_path / "nowhere"), "syn", "room_001", "6", str(tmp_path / "y"), check=False)
    assert proc.returncode == 2 and "holds no build" in proc.stderr
    proc = depthgt("show", "-d", str(built), "syn", "room_000", "6", "--out", str(tmp_path / "p.jpgx"), check=False)
    assert proc.returncode == 2 and "--out" in proc.stderr and "Traceback" not in proc.stderr


def test_rebuild_runs_only_that_scene(built, tmp_path):
    wd = tmp_path / "copy"
    shutil.copytree(built, wd, symlinks=True)  # with Snakemake's records and the files' times
    summary = wd / "results/scenes/syn/room_001/framesets.parquet"
    other = wd / "results/scenes/syn/room_000/framesets.parquet"
    before, before_other = summary.stat().st_mtime_ns, other.stat().st_mtime_ns
    depthgt("rebuild", "-d", str(wd), "--cores", "2", "syn", "room_001")
    assert summary.stat().st_mtime_ns > before
    assert other.stat().st_mtime_ns == before_other


def test_rebuild_names_an_unknown_scene(built):
    proc = depthgt("rebuild", "-d", str(built), "--cores", "1", "syn", "room_999", check=False)
    assert proc.returncode != 0
    assert "room_999" in proc.stdout + proc.stderr


def test_scene_outputs_matches_whole_folders_only():
    summary = (
        "output_file\tdate\nresults/scenes/syn/room_1/a\t-\nresults/scenes/syn/room_10/a\t-\n"
        "results/framesets/syn/room_1/000002/gt.exr\t-\nresults/syn/x\t-\n"
    )
    assert scene_outputs(summary, "syn", "room_1") == [
        "results/scenes/syn/room_1/a",
        "results/framesets/syn/room_1/000002/gt.exr",
    ]


def test_report_of_an_unfinished_build_says_what_to_run(built, tmp_path):
    # the report of a finished build is tested in test_workflow_enhance (it needs training)
    proc = depthgt("report", "-d", str(built), "--out", str(tmp_path / "r.html"), check=False)
    assert proc.returncode == 2 and "depthgt build" in proc.stderr
    proc = depthgt("report", "-d", str(tmp_path / "typo"), "--out", str(tmp_path / "r.html"), check=False)
    assert proc.returncode == 2 and "holds no build" in proc.stderr and not (tmp_path / "typo").exists()


def test_bench_runs_a_benchmark():
    proc = depthgt("bench", "bench_render", "--help")
    assert "usage" in proc.stdout.lower()


def test_bench_names_the_known_benchmarks():
    proc = depthgt("bench", "no_such_bench", check=False)
    assert proc.returncode == 2 and "bench_render" in proc.stderr
