"""Finished work is never redone (issue 9): staged targets, an added scene and a changed
setting run exactly the jobs they need; the batch size changes the files, not the GT."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import pandas as pd
import pytest
from conftest import digest_outputs, early, in_background, make_workdir, planned_jobs, snakemake, synthetic_source

SMALL = {
    "seed": 2,
    "device": "cpu",
    "sources": [synthetic_source("syn", ["room_000"], "train", 14, 160, 120)],
    "frameset": {"neighbours": 3, "stride": 2, "target_step": 1},
    "resize": 64,
    "patches": {"count": 2, "size": 32, "max_missing": 0.5, "filter_on": "gt"},
}


@pytest.fixture(scope="module")
def small_framesets(tmp_path_factory) -> Path:
    """SMALL built to the ``framesets`` target once for this file; tests that change it
    work on a copy (:func:`copy_build`)."""
    wd = make_workdir(tmp_path_factory.mktemp("small"), SMALL)
    snakemake(wd, "framesets")
    return wd


def copy_build(built: Path, dest: Path) -> Path:
    """A copy of a working directory with Snakemake's records (.snakemake/metadata) and
    the files' times, so that the copy is as up to date as the original."""
    shutil.copytree(built, dest, symlinks=True)
    return dest


def test_staged_targets_run_each_job_once(small_framesets, tmp_path):
    wd = copy_build(small_framesets, tmp_path / "staged")
    # the dataset needs no index, frame set or summary job again (the frame cache is gone)
    assert planned_jobs(wd, "dataset") == {"training_manifests": 1, "dataset": 1}
    snakemake(wd, "dataset")
    assert planned_jobs(wd, "dataset") == {}
    # nor does the RDE GT (it reads the source, not the temporary frame cache)
    jobs = planned_jobs(wd, "all")
    assert not {"scene_index", "frameset_batch", "scene_summary", "dataset"} & set(jobs), jobs
    assert jobs.get("rde_scene") == 1


def test_an_added_scene_runs_only_that_scene(small_framesets, tmp_path):
    wd = copy_build(small_framesets, tmp_path / "added")
    bigger = dict(SMALL, sources=[dict(SMALL["sources"][0], scenes=["room_000", "room_001"])])
    (wd / "config/config.yaml").unlink()
    make_workdir_config(wd, bigger)
    text = snakemake(wd, "-n", "framesets").stdout
    assert "scene=room_001" in text and "scene=room_000" not in text
    assert planned_jobs(wd, "framesets") == {"scene_index": 1, "frameset_batch": 1, "scene_summary": 1, "framesets": 1}


def test_a_registration_setting_reruns_frame_sets_not_the_index(small_framesets, tmp_path):
    wd = copy_build(small_framesets, tmp_path / "setting")
    make_workdir_config(wd, dict(SMALL, registration={"method": "given", "preset": "fast"}))
    jobs = planned_jobs(wd, "framesets")
    assert jobs.get("frameset_batch") == 1 and "scene_index" not in jobs, jobs


def test_a_test_source_added_to_a_finished_dataset_leaves_the_training_manifests(small_framesets, tmp_path):
    """New test data (a `split: test` source) runs its frame sets and the dataset again,
    not the job that writes the train and val manifests the trainings read (issue 42)."""
    wd = copy_build(small_framesets, tmp_path / "test-added")
    snakemake(wd, "dataset")
    train = wd / "results/dataset/train.parquet"
    before = train.stat().st_mtime_ns
    bigger = dict(SMALL, sources=[*SMALL["sources"], synthetic_source("mine", ["room_001"], "test", 14, 160, 120)])
    make_workdir_config(wd, bigger)
    jobs = planned_jobs(wd, "dataset")
    assert jobs == {"scene_index": 1, "frameset_batch": 1, "scene_summary": 1, "dataset": 1}, jobs
    assert "training_manifests" not in planned_jobs(wd, "train") and train.stat().st_mtime_ns == before


@early()
def one_per_batch_build(folder: Path):
    """SMALL with ``batch_size: 1``, built to ``framesets`` (an early run)."""
    return in_background(
        make_workdir(folder / "one", dict(SMALL, frameset=dict(SMALL["frameset"], batch_size=1))), "framesets"
    )


def test_batch_size_changes_the_files_not_the_frame_sets(small_framesets, one_per_batch_build):
    one = one_per_batch_build
    many = small_framesets  # the default batch size
    shards_one = sorted(p.name for p in (one / "results/framesets/syn/room_000").glob("*.zip"))
    shards_many = sorted(p.name for p in (many / "results/framesets/syn/room_000").glob("*.zip"))
    assert shards_one == ["000006-000006.zip", "000007-000007.zip"] and shards_many == ["000006-000007.zip"]

    def members(wd):  # every frame set's files, whatever shard holds them
        return {
            re.sub(r"\d{6}-\d{6}\.zip/", "", k): v
            for k, v in digest_outputs(wd).items()
            if "/framesets/" in k and not k.endswith("batch.json")
        }

    assert members(one) == members(many) and len(members(one)) == 2 * 6


def make_workdir_config(wd, config):
    import yaml

    (wd / "config" / "config.yaml").write_text(yaml.safe_dump(config))


@early()
def truncated_sens_build(folder: Path):
    """A .sens of 12 frames cut inside frame 8's record, built to ``dataset`` (an early run)."""
    import numpy as np
    from sens_writer import write_sens

    from depthgt.jobs.common import open_source_scene
    from depthgt.sources.sens import SensFile

    syn = open_source_scene({"kind": "synthetic", "options": {"n_frames": 12, "width": 80, "height": 60}}, "room_000")
    frames = [syn.read(i) for i in range(12)]
    sens = folder / "data" / "scene0000_00.sens"
    sens.parent.mkdir()
    K = np.asarray(syn.intrinsics)
    write_sens(
        sens,
        [f.rgb for f in frames],
        [np.round(f.depth_m * 1000).astype(np.uint16) for f in frames],
        [f.T_world_cam for f in frames],
        K,
        K,
    )
    cut = int(SensFile(sens).color_offsets[8]) - 10  # inside frame 8's record: 8 frames remain
    sens.write_bytes(sens.read_bytes()[:cut])
    config = {
        "seed": 0,
        "device": "cpu",
        "resize": 32,
        "sources": [
            {"name": "scan", "kind": "scannet", "root": str(sens.parent), "scenes": ["scene0000_00"], "split": "train"}
        ],
        "frameset": {"neighbours": 1, "stride": 1, "target_step": 1, "batch_size": 4},
        "patches": {"count": 1, "size": 16, "max_missing": 1.0},
    }
    return in_background(make_workdir(folder / "wd", config), "dataset")


def test_targets_a_truncated_sens_lacks_are_recorded(truncated_sens_build):
    """The plan takes the frame count from the .sens header; frames cut off by a
    truncated file become recorded skips, never silently missing frame sets."""
    wd = truncated_sens_build
    fs = pd.read_parquet(wd / "results/dataset/framesets.parquet").set_index("target")
    assert list(fs.index) == list(range(1, 11))  # planned from the header: 12 frames
    assert (fs.loc[1:6, "status"] == "ok").all()
    assert (fs.loc[7:10, "status"] == "skipped").all() and fs.loc[7:10, "reason"].str.startswith("not_in_scene").all()
    summary = (wd / "results/dataset/summary.md").read_text()
    assert "not_in_scene" in summary and "truncated .sens" in summary
