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
    assert proc.returncode == 2 and "none.yaml: file not found" in proc.stderr  # (JSON and YAML: test_buildconfig)


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


def test_extract_writes_files_standard_tools_read(built, tmp_path):
    """Depth and confidence as float32 EXR in metres (OpenEXR's own module, no depthgt
    code) and 16-bit PNG in millimetres (OpenCV), units in the names and units.json."""
    import json

    import cv2
    import numpy as np
    import OpenEXR

    from depthgt.gt.store import read_frameset

    proc = depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "fs"))
    names = sorted(Path(p).name for p in proc.stdout.split())
    depth = ["gt_depth", "gt_sigma", "input_depth", "truth_depth"]  # synthetic: the truth too
    assert names == sorted(
        [f"{d}_m.exr" for d in depth]
        + ["gt_depth_mm.png", "gt_sigma_100um.png", "input_depth_mm.png", "truth_depth_mm.png"]
        + ["rgb.png", "poses.json", "patches.npz", "frameset.json", "units.json"]
    )
    rec = read_frameset(built / "results", "syn", "room_001", 6)
    with OpenEXR.File(str(tmp_path / "fs" / "gt_depth_m.exr")) as f:
        assert list(f.channels()) == ["Y"] and not any(k.startswith("depthgt") for k in f.header())
        gt = f.channels()["Y"].pixels
    assert gt.dtype == np.float32 and np.array_equal(gt, rec.gt_m)  # metres, exactly the stored GT
    with OpenEXR.File(str(tmp_path / "fs" / "gt_sigma_m.exr")) as f:
        assert np.array_equal(f.channels()["Y"].pixels, rec.gt_sigma_m)
    mm = cv2.imread(str(tmp_path / "fs" / "gt_depth_mm.png"), cv2.IMREAD_UNCHANGED)
    assert mm.dtype == np.uint16 and np.abs(mm / 1000.0 - rec.gt_m).max() <= 0.0005 + 1e-7
    sigma = cv2.imread(str(tmp_path / "fs" / "gt_sigma_100um.png"), cv2.IMREAD_UNCHANGED)
    assert np.abs(sigma / 10000.0 - rec.gt_sigma_m).max() <= 0.00005 + 1e-7
    assert np.array_equal(cv2.imread(str(tmp_path / "fs" / "rgb.png"))[..., ::-1], rec.rgb)
    units = json.loads((tmp_path / "fs" / "units.json").read_text())["files"]
    assert units["gt_depth_m.exr"]["unit"] == "m" and units["gt_depth_mm.png"]["unit"] == "mm"
    assert units["gt_sigma_100um.png"]["metres_per_unit"] == 0.0001
    # --format png16 only; --raw: the shard's members as stored, read back by depthgt
    proc = depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "png"), "--format", "png16")
    assert not list((tmp_path / "png").glob("*.exr")) and (tmp_path / "png" / "gt_depth_mm.png").is_file()
    depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "raw"), "--raw")
    from depthgt.io import read_exr

    assert np.array_equal(read_exr(tmp_path / "raw" / "gt.exr")["Z"], rec.gt_m)
    # a folder holding such files is not overwritten without --force; bad folders are named
    (tmp_path / "fs" / "gt_depth_m.exr").write_bytes(b"mine")
    proc = depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "fs"), check=False)
    assert proc.returncode == 2 and "already holds gt_depth_m.exr" in proc.stderr and "--force" in proc.stderr
    assert (tmp_path / "fs" / "gt_depth_m.exr").read_bytes() == b"mine"
    depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "fs"), "--force")
    assert (tmp_path / "fs" / "gt_depth_m.exr").read_bytes() != b"mine"
    (tmp_path / "afile").write_text("")
    proc = depthgt("extract", "-d", str(built), "syn", "room_001", "6", str(tmp_path / "afile" / "x"), check=False)
    assert proc.returncode == 2 and "afile" in proc.stderr and "Traceback" not in proc.stderr
    proc = depthgt("extract", "-d", str(tmp_path / "nowhere"), "syn", "room_001", "6", str(tmp_path / "y"), check=False)
    assert proc.returncode == 2 and "holds no build" in proc.stderr
    proc = depthgt("show", "-d", str(built), "syn", "room_000", "6", "--out", str(tmp_path / "p.jpgx"), check=False)
    assert proc.returncode == 2 and "--out" in proc.stderr and "Traceback" not in proc.stderr


@pytest.mark.parametrize(
    "argv, expected",
    [
        (["export", "-d", "wd", "--kind", "frames", "--split", "test", "DEST"], {"dest": "DEST", "split": ["test"]}),
        (
            ["export", "DEST", "--split", "test", "--split", "val", "-d", "wd"],
            {"dest": "DEST", "split": ["test", "val"]},
        ),
        (
            ["rebuild", "-d", "wd", "--configfile", "c.yaml", "synthetic", "room_001"],
            {"configfile": ["c.yaml"], "dataset": "synthetic", "scene": "room_001"},
        ),
        (
            ["build", "dataset", "--configfile", "a.yaml", "-n", "--configfile", "b.yaml", "framesets"],
            {"configfile": ["a.yaml", "b.yaml"], "targets": ["dataset", "framesets"], "dry_run": True},
        ),
        (["show", "syn", "--out", "p.png", "room_000", "6"], {"scene": "room_000", "target": 6, "out": "p.png"}),
    ],
)
def test_options_and_positionals_in_any_order(argv, expected):
    from depthgt.cli import parse_args

    args = parse_args(argv)
    assert {k: getattr(args, k) for k in expected} == expected


def test_a_list_option_takes_one_value_and_says_so():
    proc = depthgt("export", "-d", "wd", "--split", "test", "train", "DEST", check=False)
    assert proc.returncode == 2
    assert "unrecognized arguments: DEST" in proc.stderr and "repeat --configfile or --split" in proc.stderr


def test_export_with_options_before_the_destination(built, tmp_path):
    import pandas as pd

    dest = tmp_path / "export"
    depthgt("export", "-d", str(built), "--kind", "frames", "--split", "test", str(dest))
    index = pd.read_parquet(dest / "index.parquet")
    assert set(index["split"]) == {"test"} and len(index) == 1  # the test room's one frame set
    assert (dest / index["gt"].iloc[0]).is_file()


def test_a_directory_built_with_a_configfile_remembers_it(tmp_path):
    """The issue's trap: a directory built with --configfile, then commands without it.
    They run with the build's config (nothing new planned, the scene's own shard); a
    --configfile that changes a key is refused naming it (by depthgt and by a plain
    Snakemake run) until --reconfigure applies it."""
    import yaml
    from conftest import snakemake

    mine = tmp_path / "mine.yaml"
    mine.write_text(yaml.safe_dump(TINY))
    wd = tmp_path / "wd"  # no config/config.yaml: the embedded default (20 rooms) is the base
    index = "results/scenes/syn/room_000/index.json"
    depthgt("build", "-d", str(wd), "--cores", "1", index, "--configfile", str(mine))
    assert yaml.safe_load((wd / "results/config/overrides.yaml").read_text()) == TINY
    from depthgt.buildconfig import merge

    default = yaml.safe_load((REPO / "config/config.yaml").read_text())
    assert yaml.safe_load((wd / "results/config/config.yaml").read_text()) == merge(default, TINY)  # no defaults added
    proc = depthgt("build", "-d", str(wd), "-n", index)
    assert "Nothing to be done" in proc.stdout + proc.stderr
    proc = depthgt("rebuild", "-d", str(wd), "-n", "--cores", "1", "syn", "room_000")
    shards = {line.strip() for line in (proc.stdout + proc.stderr).split() if line.endswith(".zip")}
    assert shards == {"results/framesets/syn/room_000/000006-000007.zip"}, proc.stdout[-3000:]
    other = tmp_path / "other.yaml"
    other.write_text("seed: 9\n")
    proc = depthgt("build", "-d", str(wd), "-n", "--configfile", str(other), index, check=False)
    assert proc.returncode == 2 and "seed: 3 -> 9" in proc.stderr and "Traceback" not in proc.stderr
    proc = snakemake(wd, "-n", index, "--configfile", str(other), check=False)
    said = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "seed: 3 -> 9" in said and "DEPTHGT_RECONFIGURE=1" in said
    proc = depthgt("build", "-d", str(wd), "-n", "--reconfigure", "--configfile", str(other), index)
    assert "scene_index" in proc.stdout  # the seed decides the index: planned again


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


def test_report_of_a_dataset_only_build_without_pygments(built, tmp_path):
    """`depthgt report` after the main install (no pygments) on a build without trained
    models: the summary, the GT-quality table, per source the frame sets to look at first
    as panels with their commands; --configfile as for build."""
    out = tmp_path / "r.html"
    code = "import sys; sys.modules['pygments'] = None; from depthgt.cli import main; sys.exit(main(sys.argv[1:]))"
    proc = subprocess.run(
        [sys.executable, "-c", code, "report", "-d", str(built), "--out", str(out)], capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    page = out.read_text()
    assert "<h2>Dataset</h2>" in page and "6 frame sets built (train 4, val 1, test 1)" in page
    assert "<h2>GT quality" in page and "truth@input_valid" in page and "(&#x27;syn&#x27;" not in page
    assert "Frame sets to look at first" in page and page.count("data:image/png;base64,") >= 3
    for source in ("syn", "synval", "syntest"):
        assert f"<h3>{source}</h3>" in page
    assert f"depthgt extract -d {built} syn room_" in page and f"depthgt rebuild -d {built} syn room_" in page
    assert "No tables yet" in page
    seed = tmp_path / "seed.yaml"
    seed.write_text("seed: 11\n")
    proc = depthgt("report", "-d", str(built), "--configfile", str(seed), "--out", str(out), check=False)
    assert proc.returncode == 2 and "seed: 3 -> 11" in proc.stderr
    proc = depthgt("report", "-d", str(tmp_path / "typo"), "--out", str(tmp_path / "r.html"), check=False)
    assert proc.returncode == 2 and "holds no build" in proc.stderr and not (tmp_path / "typo").exists()


def test_bench_runs_a_benchmark():
    proc = depthgt("bench", "bench_render", "--help")
    assert "usage" in proc.stdout.lower()


def test_bench_names_the_known_benchmarks():
    proc = depthgt("bench", "no_such_bench", check=False)
    assert proc.returncode == 2 and "bench_render" in proc.stderr


def _remembered_workdir(path: Path) -> Path:
    """A working directory on TINY whose config is remembered, with a results/framesets
    folder (what `depthgt report` asks of a build); nothing built."""
    from depthgt import buildconfig

    wd = make_workdir(path, TINY)
    (wd / "results" / "framesets").mkdir(parents=True)
    buildconfig.remember(wd, buildconfig.layered_config(wd, wd / "config/config.yaml", check_sources=False))
    return wd


def test_the_reports_refusal_of_a_changed_config_names_what_the_report_takes(tmp_path):
    """`depthgt report --configfile` changing a key of the build: refused in one line
    that does not offer the --reconfigure the report lacks, but the build command that
    applies the change, and leaving --configfile out."""
    wd = _remembered_workdir(tmp_path / "wd")
    seed = tmp_path / "seed.yaml"
    seed.write_text("seed: 11\n")
    proc = depthgt("report", "-d", str(wd), "--configfile", str(seed), "--out", str(tmp_path / "r.html"), check=False)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    (line,) = proc.stderr.splitlines()
    assert line.startswith(f"depthgt: error: --configfile would change the config the build in {wd} was made with")
    assert "seed: 3 -> 11" in line
    assert "depthgt report shows the build as it was made and takes no --reconfigure" in line
    assert f"(depthgt build -d {wd} --reconfigure --configfile {seed};" in line
    assert "pass --reconfigure" not in line and not (tmp_path / "r.html").exists()
    proc = depthgt("report", "--reconfigure", "-d", str(wd), check=False)  # the option the message no longer offers
    assert proc.returncode == 2 and "unrecognized arguments: --reconfigure" in proc.stderr


def test_build_refuses_a_config_file_given_as_a_target(tmp_path):
    """`depthgt build --configfile a.yaml b.yaml`: depthgt's --configfile takes one file,
    so b.yaml would be a target (no rule builds it) and left out of the config: refused
    in one line, with the command line meant, before Snakemake starts."""
    wd = make_workdir(tmp_path / "wd", TINY)
    (tmp_path / "a.yaml").write_text("seed: 4\n")
    (tmp_path / "b.yaml").write_text("resize: 96\n")
    proc = depthgt("build", "-d", str(wd), "-n", "--configfile", "a.yaml", "b.yaml", check=False, cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.splitlines() == [
        f"depthgt: error: target b.yaml is a config file ({tmp_path / 'b.yaml'}), not an output of the workflow: "
        "depthgt's --configfile takes one file, repeat it for several (--configfile a.yaml --configfile b.yaml); "
        "targets are rules or files under results/"
    ]


def test_targets_that_are_not_config_files_are_left_to_snakemake(tmp_path):
    """A rule, an output under results/ (a YAML the workflow writes), a YAML file that
    does not exist or holds no mapping: no refusal (Snakemake builds or names them)."""
    import argparse

    from depthgt.cli import check_targets
    from depthgt.errors import DepthGTError

    wd = make_workdir(tmp_path / "wd", TINY)
    (wd / "results" / "report").mkdir(parents=True)
    (wd / "results" / "report" / "config.yaml").write_text("seed: 3\n")
    (wd / "list.yaml").write_text("- 1\n")
    targets = ["dataset", "results/report/config.yaml", "missing.yaml", "list.yaml"]
    check_targets(argparse.Namespace(directory=str(wd), targets=targets, configfile=None))
    with pytest.raises(DepthGTError, match="target config/config.yaml is a config file"):
        check_targets(argparse.Namespace(directory=str(wd), targets=["config/config.yaml"], configfile=None))


def test_plain_snakemake_names_a_target_it_read_as_a_config_file(tmp_path):
    """`snakemake --configfile mine.yaml results/.../index.json`: Snakemake's --configfile
    takes every value up to the next option, so the existing index (a JSON mapping) is
    read as a second config file and the default target planned: stopped in one line
    naming it and where targets go."""
    from conftest import snakemake

    wd = make_workdir(tmp_path / "wd", TINY)
    index = wd / "results" / "scenes" / "syn" / "room_000" / "index.json"
    index.parent.mkdir(parents=True)
    index.write_text('{"dataset": "syn", "scene": "room_000", "n_frames": 14, "problems": []}')
    (tmp_path / "mine.yaml").write_text("seed: 3\n")
    proc = snakemake(wd, "-n", "--configfile", str(tmp_path / "mine.yaml"), str(index), check=False)
    said = proc.stdout + proc.stderr
    assert proc.returncode != 0 and "Job stats" not in said
    assert f"--configfile {index}: unknown config key(s) scene, n_frames, problems (allowed: " in said
    assert "Is it a target? Snakemake reads every value after --configfile" in said


def test_a_config_that_cannot_be_remembered_stops_the_run_before_its_jobs_in_one_line(tmp_path):
    """The run's config cannot be written (here a file where results/config goes; a full
    disk alike, test_buildconfig): the run stops in `onstart`, before any job, with one
    line naming the file, and gives the working directory's lock back."""
    wd = make_workdir(tmp_path / "wd", TINY)
    (wd / "results").mkdir()
    (wd / "results" / "config").write_text("")
    index = "results/scenes/syn/room_000/index.json"
    proc = depthgt("build", "-d", str(wd), "--cores", "1", index, check=False)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr, proc.stderr[-3000:]
    lines = [line for line in proc.stderr.splitlines() if line.startswith("depthgt: error:")]
    assert len(lines) == 1 and lines[0].startswith(
        f"depthgt: error: cannot remember the run's config in {wd / 'results/config/overrides.yaml'}: File exists: "
        f"{wd / 'results/config'} ("
    )
    assert lines[0].endswith("MB free on its file system); fix that and run again")
    assert not (wd / index).exists() and not (wd / ".snakemake" / "depthgt-run.lock").exists()
