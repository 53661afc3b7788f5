"""The enhancement/table/report rules on tiny configs.

* A tiny synthetic config without a real source and only the filter methods (no
  training): Tables 1, 3 and the GT-quality table are built, Table 2 says that no real
  source is configured, the figures and the HTML report are made.
* With the 7-Scenes fixture (skipped when ../shared/data/7scenes-kitchen is absent):
  the filters and LapDEN (trained for two steps); Table 2 is built from the real
  kitchen frames against its three references (depthgt's GT, the neighbours-only render,
  the TSDF GT), Table 3 from the synthetic test scene.
"""

from __future__ import annotations

import copy
import shutil
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
import yaml
from conftest import (
    TINY_ENHANCE,
    _failed,
    _snakemake_command,
    commands_in_background,
    earlier_run,
    early,
    in_background,
    jobs_table,
    make_workdir,
    snakemake,
)

from depthgt.gt import store

FIXTURE = Path(__file__).resolve().parents[2] / "shared/data/7scenes-kitchen"
TINY = TINY_ENHANCE


def _table(wd: Path, name: str) -> pd.DataFrame:
    return pd.read_csv(wd / "results/tables" / f"{name}.csv")


@pytest.fixture(scope="module")
def synthetic_only(tiny_report) -> Path:
    return tiny_report  # conftest: built once per session (test_train_resume starts from a copy)


def test_tables_without_real_source(synthetic_only):
    wd = synthetic_only
    t2 = _table(wd, "table2")
    assert list(t2.columns) == ["note"] and "no real source" in t2.iloc[0, 0]
    assert "no real source" in (wd / "results/tables/table2.md").read_text()
    t3 = _table(wd, "table3")
    assert list(t3["method"]) == ["Input (raw depth)", "RGF"] and set(t3["dataset"]) == {"syntest"}
    assert {"RMSE, filling (m)", "MAE, denoising (m)", "SSIM, filling (unitless)", "RMSE, filling (m) 95% low"} <= set(
        t3.columns
    )
    assert (t3["RMSE, filling (m)"] > 0).all() and (t3["RMSE, denoising (m)"] < 0.5).all()
    assert (t3["frames"] == t3["frames"].iloc[0]).all()  # every method on the same frames
    paired = _table(wd, "table3_paired")  # no LapDEN in this build: the note says so
    assert list(paired.columns) == ["note"] and "lapden" in paired.iloc[0, 0]
    t1 = _table(wd, "table1")
    assert set(t1["GT"]) == {"depthgt GT (local frame set)", "global reconstruction GT (TSDF)"}
    assert t1["SSIM (unitless)"].between(0, 1).all()
    tq = _table(wd, "table_gt_quality")
    assert {"depthgt GT (local frame set)", "global reconstruction GT (TSDF)", "input (raw depth)"} <= set(
        tq["estimate"]
    )
    md = (wd / "results/tables/table3.md").read_text()
    assert "RMSE, filling (m)" in md and "data_range 1" in md and "seed 0" in md


def test_evaluate_command_reproduces_table3(synthetic_only, tmp_path):
    """`depthgt evaluate` on RGF's saved predictions, with the references of an EXR
    export of the test frames, prints Table 3's RGF row digit for digit."""
    import numpy as np

    from depthgt import io

    wd = synthetic_only
    cli = [sys.executable, "-m", "depthgt.cli"]
    exp = tmp_path / "export"
    proc = subprocess.run(
        [*cli, "export", str(exp), "-d", str(wd), "--format", "exr", "--kind", "frames", "--split", "test"],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    preds = tmp_path / "rgf"
    for npy in (wd / "results/eval/predictions/rgf").rglob("*.npy"):
        io.write_exr(
            preds / npy.relative_to(wd / "results/eval/predictions/rgf").with_suffix(".exr"), {"Y": np.load(npy)}
        )
    proc = subprocess.run(
        [*cli, "evaluate", str(preds), "-d", str(wd), "--export", str(exp), "--out", str(tmp_path / "out")],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]

    def cells(md):  # the printed cells of the RGF row (the column widths differ with the rows beside it)
        return [[c.strip() for c in line.split("|")] for line in md.read_text().splitlines() if "| RGF " in line]

    row = cells(wd / "results/tables/table3.md")
    assert len(row) == 1 and cells(tmp_path / "out/table3.md") == row


def test_rde_gt_and_figures(synthetic_only):
    wd = synthetic_only
    rde = pd.read_parquet(wd / "results/rde/framesets.parquet")
    fs = pd.read_parquet(wd / "results/dataset/framesets.parquet")
    # the RDE GT of the scenes RDE trains and validates on; not of the synthetic test room,
    # which no method needs (evaluation.rde_synthetic_test off)
    assert set(rde["dataset"]) == {"syn", "synval"} and not (wd / "results/rde/syntest").exists()
    trained_on = fs[fs["dataset"].isin(["syn", "synval"]) & (fs["status"] == "ok")]
    assert len(rde) == len(trained_on) and (rde["status"] == "ok").all()
    assert (rde["rde_missing"] < 0.5).all()
    loc = rde.iloc[0]["rde"]  # a location in the scene's RDE shard, relative to the working directory
    doc = store.read_json(f"{loc if Path(loc).is_absolute() else wd / loc}/frameset.json")
    # a TSDF of the whole (noisy) stream lies within a few cm of the clean truth
    assert doc["statistics"]["rde_vs_truth"]["mae_m"] < 0.05 and doc["units"]["mae_m"] == "m"
    for png in ("comparison.png",):
        assert (wd / "results/figures" / png).stat().st_size > 1000


def test_rde_synthetic_test_adds_the_test_rooms_rde_gt(tmp_path):
    """evaluation.rde_synthetic_test: the DAG gains the test room's RDE GT job (without it,
    test_rde_gt_and_figures finds none)."""
    import re

    cfg = copy.deepcopy(TINY)
    cfg["evaluation"]["rde_synthetic_test"] = True
    text = snakemake(make_workdir(tmp_path, cfg), "-n", "tables").stdout
    assert set(re.findall(r"results/rde/(\w+)/room_\d+/framesets.parquet", text)) == {"syn", "synval", "syntest"}


def test_trainings_start_longest_first(tmp_path):
    """Rule train_model's priority is the training's estimated length (epochs x the model's
    pair_cpu_ms): on 2 cores the longest training (SDD in the default config) starts first
    and every training comes before the evaluations (priority 0), the jobs only its GT's
    trainings wait for one above; the epochs in the config move it (LapDEN at 90 epochs goes
    first)."""
    import re

    from depthgt import registry

    def priorities(cfg):
        wd = make_workdir(tmp_path / str(len(list(tmp_path.iterdir()))), cfg)
        text = snakemake(wd, "-n", "--cores", "2", "tables").stdout
        jobs = {}
        for block in text.split("\nrule ")[1:]:
            rule = block.split(":", 1)[0]
            wildcards = re.search(r"^    wildcards: (.*)$", block, re.M)
            prio = re.search(r"^    priority: (\d+)$", block, re.M)
            jobs[rule, wildcards and wildcards.group(1)] = int(prio.group(1)) if prio else 0
        return jobs

    cfg = yaml.safe_load((Path(__file__).resolve().parents[1] / "config/config.yaml").read_text())
    jobs = priorities(cfg)
    train = {w.removeprefix("model="): p for (r, w), p in jobs.items() if r == "train_model"}
    assert set(train) == {"lapden", "rde", "ddrnet", "sdd"}
    assert train["sdd"] > train["lapden"] == train["rde"] > train["ddrnet"] > 0
    assert train["sdd"] == registry.training_priority("sdd", 45)
    # what only the trainings on one GT wait for carries their priority, one above
    # (Snakemake does not pass it on): their manifests, and RDE's scenes
    assert jobs["training_manifests", None] == train["sdd"] + 1
    assert jobs["rde_training_manifests", None] == train["rde"] + 1
    rde_scenes = [p for (r, _), p in jobs.items() if r == "rde_scene"]
    assert len(rde_scenes) == 8 and set(rde_scenes) == {train["rde"] + 1}
    upstream = ("train_model", "training_manifests", "rde_training_manifests", "rde_scene")
    assert all(p == 0 for (r, _), p in jobs.items() if r not in upstream)
    assert sum(r == "evaluate_method" for r, _ in jobs) == 7

    cfg["enhance"]["models"]["lapden"]["epochs"] = 90
    train = {w.removeprefix("model="): p for (r, w), p in priorities(cfg).items() if r == "train_model"}
    assert train["lapden"] == train["rde"] > train["sdd"]


def test_html_report(synthetic_only):
    wd = synthetic_only
    snakemake(wd, "--report", str(wd / "report.html"))
    assert (wd / "report.html").stat().st_size > 10_000


def test_depthgt_report_command(synthetic_only, tmp_path):
    """`depthgt report` on a finished build writes the same kind of report."""
    out = tmp_path / "r.html"
    proc = subprocess.run(
        [sys.executable, "-m", "depthgt.cli", "report", "-d", str(synthetic_only), "--out", str(out)],
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert out.stat().st_size > 10_000


@early()
def kitchen_tables(folder: Path):
    """The session's enhancement build (``tiny_report``, a copy) with the kitchen's first 20
    frames added as a test source and JF and LapDEN (trained for two steps) as methods:
    LapDEN trained before the new test data comes, then a dry run of ``tables`` (its job
    table) and the run. An early run after ``tiny_report`` in the workflow lane; returns
    the working directory and the dry run's jobs (rule -> count)."""
    if not FIXTURE.is_dir():
        return lambda: None
    kitchen = folder / "first-20" / FIXTURE.name
    kitchen.mkdir(parents=True)
    for f in FIXTURE.iterdir():
        if not f.name.startswith("frame-") or int(f.name[6:12]) < 20:
            (kitchen / f.name).symlink_to(f)
    cfg = copy.deepcopy(TINY)
    cfg["evaluation"]["methods"] = ["input", "rgf", "jf", "lapden"]
    # one's own real recordings as a test source
    real = copy.deepcopy(cfg)
    real["sources"].append(
        {"name": "kitchen", "kind": "sevenscenes", "root": str(kitchen), "scenes": "all", "split": "test"}
    )
    wd = folder / "build"

    def run() -> tuple[Path, dict[str, int]]:
        shutil.copytree(earlier_run("tiny_report"), wd, symlinks=True)
        (wd / "config/config.yaml").write_text(yaml.safe_dump(cfg))
        in_background(wd, "results/models/lapden/best.pt")()
        (wd / "config/config.yaml").write_text(yaml.safe_dump(real))
        (dry,) = commands_in_background([_snakemake_command(wd, "-n", "tables")])()
        if dry.returncode != 0:
            raise _failed(dry)
        in_background(wd, "tables")()
        return wd, jobs_table(dry.stdout)

    return run


@pytest.mark.skipif(not FIXTURE.is_dir(), reason="../shared/data/7scenes-kitchen is absent")
def test_table2_from_7scenes_fixture(tiny_report, kitchen_tables):
    """The kitchen's first 20 frames as a test source of the enhancement build
    (``kitchen_tables``): the kitchen's frame sets, references and predictions, the model
    and the tables are what runs."""
    wd, jobs = kitchen_tables
    # its frame sets, the test manifest, the RDE and references they need, evaluation and
    # tables run; no training, and no job that writes a training manifest (issue 42)
    assert not {"train_model", "training_manifests", "rde_training_manifests"} & set(jobs), jobs
    assert jobs["frameset_batch"] >= 1 and jobs["dataset"] == 1 and jobs["rde_dataset"] == 1, jobs
    t2 = _table(wd, "table2")
    # one block per reference: depthgt's GT, the neighbours-only render, the TSDF GT
    refs = ["depthgt GT", "neighbours only", "TSDF GT"]
    assert set(t2["dataset"]) == {"kitchen"} and list(t2["reference"]) == [r for r in refs for _ in range(4)]
    assert t2["RMSE, filling (m)"].notna().all() and t2["MAE, denoising (m)"].notna().all()
    filters = t2[t2["method"].isin(["Input (raw depth)", "RGF", "JF"])]
    assert len(filters) == 9 and (filters["RMSE, denoising (m)"] < 0.5).all()  # the models had two training steps only
    # the raw input against the neighbours-only render: a real error (the render never saw the target's depth)
    inp = t2[t2["method"] == "Input (raw depth)"].set_index("reference")
    assert 0.002 < inp.loc["neighbours only", "MAE, denoising (m)"] < 0.02
    assert inp.loc["neighbours only", "MAE, denoising (m)"] > inp.loc["depthgt GT", "MAE, denoising (m)"]
    paired = _table(wd, "table2_paired")
    assert set(paired["dataset"]) == {"kitchen"} and len(paired) == 9  # LapDEN against input, RGF, JF per reference
    assert list(paired["reference"]) == [r for r in refs for _ in range(3)]
    assert (paired["frames"] == t2["frames"].iloc[0]).all()
    refs_table = pd.read_parquet(wd / "results/references/kitchen/7scenes-kitchen/references.parquet")
    assert set(refs_table["reference"]) == {"neighbours", "tsdf"}
    assert len(refs_table) == 2 * t2["frames"].iloc[0]
    t3 = _table(wd, "table3")
    assert set(t3["dataset"]) == {"syntest"} and len(t3) == 4
    t1 = _table(wd, "table1")
    assert {"kitchen", "syntest"} <= set(t1["dataset"])


def _plane_stream(n=7, hw=48):
    """Noisy views of the slanted plane z_world = 2 + 0.1 x_world from cameras shifted along x."""
    import numpy as np

    f, c = 45.0, (hw - 1) / 2
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    v, u = np.mgrid[0:hw, 0:hw].astype(np.float64)
    dx = (u - c) / f

    def pose(tx):
        T = np.eye(4)
        T[0, 3] = tx
        return T

    def depth(T):  # ray x = tx + z dx meets the plane: z = 2 + 0.1 (tx + z dx)
        return ((2 + 0.1 * T[0, 3]) / (1 - 0.1 * dx)).astype(np.float32)

    poses = [pose(t) for t in np.linspace(-0.2, 0.2, n)]
    rng = np.random.default_rng(0)
    depths = [depth(T) + rng.normal(0, 0.01, (hw, hw)).astype(np.float32) for T in poses]
    return K, poses, depths, pose(0.05), depth(pose(0.05))


@pytest.mark.parametrize("backend", ["torch", "open3d"])
def test_rde_tsdf_renders_a_plane(backend):
    import numpy as np

    from depthgt.gt.rde import open3d_available, reconstruct_and_render
    from depthgt.settings import RDESettings

    if backend == "open3d" and not open3d_available():
        pytest.skip("Open3D is not installed (optional extra)")
    K, poses, depths, T_new, truth = _plane_stream()
    out, used = reconstruct_and_render(
        depths, None, K, poses, [K], [T_new], truth.shape, RDESettings(voxel_m=0.01, max_depth_m=4.0, backend=backend)
    )
    assert used == backend
    valid = out[0] > 0
    assert valid.mean() > 0.95
    err = np.abs(out[0] - truth)[valid]
    assert err.mean() < 0.005, err.mean()  # 1 cm noise (MAE ~8 mm) averaged over 7 views -> a few mm


def test_rde_settings_errors():
    from depthgt.errors import ConfigError
    from depthgt.settings import RDESettings, settings_from_config

    with pytest.raises(ConfigError, match="enhance.rde.backend"):
        RDESettings(backend="pcl")
    with pytest.raises(ConfigError, match="unknown config key.*enhance.rde.voxel"):
        settings_from_config({"enhance": {"rde": {"voxel": 0.02}}})
