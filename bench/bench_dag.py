"""The factory at scale (issue 9): planning time and memory, files per frame set, CPU
time per frame set.

    python3 bench/bench_dag.py plan [--sizes 1000 10000 50000 250000]
    python3 bench/bench_dag.py files [--frames 80]
    python3 bench/bench_dag.py cpu [--scenes 2] [--old PATH]

``plan``: ``snakemake -n framesets`` on synthetic configs of about N frame sets (1,513
scenes x 1,650 frames at target_step 10 for 250k, ScanNet's size), nothing read or
rendered; wall time and peak RSS (``/usr/bin/time``), and the number of batch jobs the
plan lists. ``files``: a real build of two small scenes (``framesets`` and ``dataset``),
then every file under results/, logs/, benchmarks/ and .snakemake/metadata/ per frame
set. ``cpu``: CPU seconds (user + system of Snakemake and every job) of the frame-set
stage of the default config's first ``--scenes`` training scenes at batch_size 1 and the
default, and of a checkout of the old layout given by ``--old`` (for example ``git
worktree add /tmp/oldmain bb3884c``), per frame set built.
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import yaml

REPO = Path(__file__).resolve().parents[1]


def _write_config(wd: Path, config: dict) -> Path:
    (wd / "config").mkdir(parents=True, exist_ok=True)
    (wd / "config" / "config.yaml").write_text(yaml.safe_dump(config))
    return wd


def _snakemake(checkout: Path, wd: Path, *args: str, time_it: bool = False) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", "-s", str(checkout / "Snakefile"), "-d", str(wd), "--cores", "2", *args]
    if time_it:
        cmd = ["/usr/bin/time", "-f", "TIME %e s %M KiB", *cmd]
    env = dict(os.environ, PYTHONPATH=str(checkout / "src"), OMP_NUM_THREADS="1")
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"snakemake failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def plan(sizes: list[int]) -> None:
    print("| frame sets | scenes x frames | batch jobs | plan wall (s) | peak RSS (MiB) |")
    print("|---:|---|---:|---:|---:|")
    for size in sizes:
        # 1,650 frames at target_step 10: 164 frame sets per scene (reach 6)
        n_frames, step = 1650, 10
        per_scene = len(range(6, n_frames - 6, step))
        n_scenes = max(1, round(size / per_scene))
        config = {
            "sources": [
                {
                    "name": "scan",
                    "kind": "synthetic",
                    "split": "auto",
                    "scenes": [f"room_{i:04d}" for i in range(n_scenes)],
                    "options": {"n_frames": n_frames},
                }
            ],
            "frameset": {"target_step": step},
        }
        with tempfile.TemporaryDirectory() as tmp:
            wd = _write_config(Path(tmp), config)
            proc = _snakemake(REPO, wd, "framesets", "-n", "--quiet", "rules", time_it=True)
        out = proc.stdout + proc.stderr
        wall, rss = re.search(r"TIME ([\d.]+) s (\d+) KiB", out).groups()
        jobs = re.search(r"^frameset_batch\s+(\d+)$", out, re.M)
        print(
            f"| {n_scenes * per_scene:,} | {n_scenes:,} x {n_frames:,} | {int(jobs.group(1)) if jobs else 0:,} | "
            f"{float(wall):.1f} | {int(rss) / 1024:.0f} |",
            flush=True,
        )


def _small_config(n_frames: int, scenes: list[str], batch_size: int | None = None) -> dict:
    config = {
        "sources": [
            {
                "name": "syn",
                "kind": "synthetic",
                "split": "train",
                "scenes": scenes,
                "options": {"n_frames": n_frames, "width": 320, "height": 240},
            }
        ],
        "frameset": {"target_step": 1},
        "resize": 128,
        "patches": {"count": 6, "size": 64, "max_missing": 0.15},
    }
    if batch_size:
        config["frameset"]["batch_size"] = batch_size
    return config


def files(n_frames: int) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        wd = _write_config(Path(tmp), _small_config(n_frames, ["room_000", "room_001"]))
        _snakemake(REPO, wd, "dataset")
        n_fs = int((pd.read_parquet(wd / "results/dataset/framesets.parquet")["status"] == "ok").sum())
        counts = {
            d: sum(1 for p in (wd / d).rglob("*") if p.is_file())
            for d in ("results", "logs", "benchmarks", ".snakemake/metadata")
        }
    total = sum(counts.values())
    print(
        f"{n_fs} frame sets (2 scenes x {n_frames} frames, target_step 1, batch_size 32): files {counts}, "
        f"{total} in all = {total / n_fs:.2f} per frame set"
    )


def _cpu_of(checkout: Path, config: dict) -> tuple[float, int]:
    with tempfile.TemporaryDirectory() as tmp:
        wd = _write_config(Path(tmp), config)
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.time()
        _snakemake(checkout, wd, "framesets")
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        fs = pd.concat([pd.read_parquet(p) for p in (wd / "results/scenes").rglob("framesets.parquet")])
        n = int((fs["status"] == "ok").sum())
        print(f"  {checkout.name}: {n} frame sets, {cpu:.0f} s CPU, {time.time() - t0:.0f} s wall", flush=True)
        return cpu, n


def cpu(n_scenes: int, old: Path | None) -> None:
    default = yaml.safe_load((REPO / "config/config.yaml").read_text())
    src = dict(default["sources"][0], scenes=default["sources"][0]["scenes"][:n_scenes])
    config = dict(default, sources=[src])
    rows = []
    if old is not None:  # the old layout knows no batch_size
        c, n = _cpu_of(
            old, dict(config, frameset={k: v for k, v in config.get("frameset", {}).items() if k != "batch_size"})
        )
        rows.append(("old layout (one job per frame set)", c, n))
    for batch in (1, 32):
        c, n = _cpu_of(REPO, dict(config, frameset=dict(config.get("frameset", {}), batch_size=batch)))
        rows.append((f"batch_size {batch}", c, n))
    print("| layout | frame sets | CPU (s) | CPU per frame set (s) |")
    print("|---|---:|---:|---:|")
    for name, c, n in rows:
        print(f"| {name} | {n} | {c:.0f} | {c / n:.2f} |")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="what", required=True)
    a = sub.add_parser("plan")
    a.add_argument("--sizes", type=int, nargs="+", default=[1000, 10000, 50000, 250000])
    b = sub.add_parser("files")
    b.add_argument("--frames", type=int, default=80)
    c = sub.add_parser("cpu")
    c.add_argument("--scenes", type=int, default=2)
    c.add_argument("--old", type=Path, help="a checkout of the old layout")
    args = p.parse_args()
    if not shutil.which("/usr/bin/time") and args.what == "plan":
        raise SystemExit("plan needs /usr/bin/time (Debian package time)")
    print(f"$ python3 bench/bench_dag.py {' '.join(sys.argv[1:])}")
    if args.what == "plan":
        plan(args.sizes)
    elif args.what == "files":
        files(args.frames)
    else:
        cpu(args.scenes, args.old)


if __name__ == "__main__":
    main()
