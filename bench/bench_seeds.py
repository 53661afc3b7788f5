"""Seed spread of the learned rows of Table 3 (issue 27 item 6): LapDEN and RDE trained with
several seeds on one build's dataset, each scored on the build's test frames with Table 3's
protocol, and the spread over seeds of every Table 3 number.

    # the default build first (python3 -m snakemake --cores 2 dataset results/rde/train.parquet), then
    python3 bench/bench_seeds.py -d WORKDIR                       # seeds 0 1 2, the config's epochs
    python3 bench/bench_seeds.py -d WORKDIR --configfile CFG --seeds 0 1 2 --epochs 1 --max-batches 2 --max-frames 4
    python3 bench/bench_seeds.py -d WORKDIR --device cuda --jobs 6   # a GPU machine: the six runs side by side

For each model and seed: :func:`depthgt.enhance.train.train` with the config's training
settings of the model (``enhance.train`` + ``enhance.models``, what the workflow's
``train_model`` rule uses) and only ``seed`` changed (the initialisation and the order
of the patches; the dataset, its crops and splits stay the build's), on the build's
manifests (``results/dataset`` for LapDEN, ``results/rde`` for RDE), ``best.pt`` at the
lowest validation loss; then :func:`depthgt.eval.evaluate.evaluate_frames` on the
``evaluation.split`` frame sets of the synthetic sources against the clean truth and
:func:`depthgt.eval.tables.table3` (the same masks, per-frame means, bootstrap
intervals). Trained checkpoints are kept under ``--out`` and reused (a finished run
resumes to its end at once).

``--jobs N`` runs the (model, seed) runs as N processes side by side (each ``--threads``
threads, its own ``--out``/MODEL-seedS folder) and merges their rows; ``--device cuda``
trains and runs the models on the GPU (the training's numbers then differ from a CPU
run's by the GPU's float rounding and kernels, not by the protocol).

Writes ``--out``/per_seed.csv (Table 3's rows, one per model and seed) and
``--out``/spread.csv|md: per model and column, the mean over seeds, the sample standard
deviation, min, max and max - min of the per-seed means (and of the interval bounds).
Nothing here is a test: the spread is what it is.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import torch
import yaml

from depthgt import registry
from depthgt.device import resolve_device
from depthgt.enhance.train import TrainOutputs, train
from depthgt.eval import tables
from depthgt.eval.evaluate import evaluate_frames, method_spec
from depthgt.settings import settings_from_config
from depthgt.status import Status

REPO = Path(__file__).resolve().parents[1]
MANIFESTS = {"depthgt": "results/dataset", "rde": "results/rde"}


def test_frames(framesets: Path, split: str, synthetic: set[str], max_frames: int | None) -> pd.DataFrame:
    """The ``split`` frame sets (status ok) of the synthetic datasets, the first
    ``max_frames`` per dataset when given."""
    t = pd.read_parquet(framesets)
    t = t[(t["split"] == split) & (t["status"] == Status.OK) & (t["frameset"] != "") & t["dataset"].isin(synthetic)]
    if max_frames:
        t = t.groupby("dataset", group_keys=False).head(max_frames)
    return t


def spread(per_seed: pd.DataFrame) -> pd.DataFrame:
    """Per dataset and method, for every numeric column of Table 3: mean, sd (ddof 1),
    min, max and range over the seeds (long: dataset, method, column, seeds, ...)."""
    value_cols = [c for c in per_seed.columns if c not in ("dataset", "method", "seed", "frames")]
    rows = []
    for (dataset, method), g in per_seed.groupby(["dataset", "method"], sort=False):
        for c in value_cols:
            v = g[c].astype(float)
            rows.append(
                {
                    "dataset": dataset,
                    "method": method,
                    "column": c,
                    "seeds": len(v),
                    "mean": v.mean(),
                    "sd": v.std(ddof=1) if len(v) > 1 else float("nan"),
                    "min": v.min(),
                    "max": v.max(),
                    "range": v.max() - v.min(),
                }
            )
    return pd.DataFrame(rows)


def write_spread(per_seed: pd.DataFrame, out: Path, caption: str) -> None:
    """per_seed.csv, spread.csv and spread.md (the means' rows) under ``out``; prints the table."""
    out.mkdir(parents=True, exist_ok=True)
    per_seed.to_csv(out / "per_seed.csv", index=False)
    sp = spread(per_seed)
    sp.to_csv(out / "spread.csv", index=False)
    means = sp[~sp["column"].str.endswith((tables.LOW, tables.HIGH))]
    (out / "spread.md").write_text(caption + "\n\n" + means.to_markdown(index=False, floatfmt=".4g") + "\n")
    print((out / "spread.md").read_text())


def run_parallel(args, out: Path) -> pd.DataFrame:
    """Each (model, seed) as its own process of this script, ``args.jobs`` at a time; their
    per_seed.csv rows in the order of ``args.models`` x ``args.seeds``. A failed run stops
    the bench with its command and exit status (its log is its folder's log.txt)."""
    common = ["-d", str(Path(args.workdir).resolve()), "--configfile", str(Path(args.configfile).resolve())]
    common += ["--threads", str(args.threads), "--device", args.device]
    for flag, value in (
        ("--epochs", args.epochs),
        ("--max-batches", args.max_batches),
        ("--max-frames", args.max_frames),
    ):
        if value is not None:
            common += [flag, str(value)]
    runs = [(m, s) for m in args.models for s in args.seeds]
    pending, running, done = list(runs), [], {}
    while pending or running:
        while pending and len(running) < args.jobs:
            m, s = pending.pop(0)
            d = out / f"{m}-seed{s}"
            d.mkdir(parents=True, exist_ok=True)
            cmd = [sys.executable, __file__, *common, "--models", m, "--seeds", str(s), "--out", str(d)]
            log = (d / "log.txt").open("w")
            running.append(((m, s), d, cmd, subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT), log))
        time.sleep(1.0)
        for item in list(running):
            key, d, cmd, proc, log = item
            if proc.poll() is None:
                continue
            log.close()
            running.remove(item)
            if proc.returncode != 0:
                for *_, p, lg in running:
                    p.kill()
                    lg.close()
                raise SystemExit(f"{' '.join(cmd)} exited with {proc.returncode}; see {d / 'log.txt'}")
            lines = (d / "log.txt").read_text().splitlines()
            print(next((ln for ln in lines if ln.startswith(f"{key[0]} seed {key[1]}:")), lines[-1]), flush=True)
            done[key] = pd.read_csv(d / "per_seed.csv")
    return pd.concat([done[k] for k in runs], ignore_index=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "-d",
        "--workdir",
        required=True,
        help="a build with results/dataset, results/rde (train/val) and results/dataset/framesets.parquet",
    )
    ap.add_argument("--configfile", default=str(REPO / "config/config.yaml"), help="the build's config")
    ap.add_argument("--models", nargs="+", default=["lapden", "rde"])
    ap.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    ap.add_argument("--epochs", type=int, default=None, help="override every model's epochs (tiny runs)")
    ap.add_argument("--max-batches", type=int, default=None, help="cap on training steps per epoch (tiny runs)")
    ap.add_argument("--max-frames", type=int, default=None, help="test frames per dataset (tiny runs; default all)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads per run")
    ap.add_argument("--device", default="cpu", help="cpu, cuda or auto: where the models train and run")
    ap.add_argument("--jobs", type=int, default=1, help="(model, seed) runs side by side, one process each")
    ap.add_argument("--out", default="/tmp/depthgt_bench_seeds")
    args = ap.parse_args(argv)
    device = str(resolve_device(args.device))
    caption = (
        f"Seed spread of Table 3 ({', '.join(args.models)}; seeds {args.seeds}; device {device}; "
        f"epochs {args.epochs or 'the config'}): per column the mean over seeds of the per-seed means, their "
        "sample sd, min, max and range (interval bounds in spread.csv)."
    )
    if args.jobs > 1:
        per_seed = run_parallel(args, Path(args.out).resolve())
        n = int(per_seed["frames"].iloc[0])
        write_spread(per_seed, Path(args.out).resolve(), caption.replace("; device", f"; {n} test frames; device"))
        return 0

    torch.set_num_threads(args.threads)
    config = yaml.safe_load(Path(args.configfile).read_text())
    settings = settings_from_config(config)
    out = Path(args.out).resolve()
    os.chdir(args.workdir)  # the manifests' locations are relative to the build's folder
    kinds = {src.name: src.kind for src in settings.sources}
    frames = test_frames(
        Path("results/dataset/framesets.parquet"),
        settings.evaluation.split,
        {d for d, k in kinds.items() if k == "synthetic"},
        args.max_frames,
    )
    if frames.empty:
        print(f"{args.workdir}: no {settings.evaluation.split} frame sets of a synthetic source", file=sys.stderr)
        return 1
    rows = []
    for model in args.models:
        d = MANIFESTS[registry.METHODS[model].trains_on]
        base = settings.train(model)
        for seed in args.seeds:
            ts = replace(
                base,
                seed=seed,
                progress=False,
                device=device,
                epochs=args.epochs if args.epochs is not None else base.epochs,
                max_batches_per_epoch=args.max_batches if args.max_batches is not None else base.max_batches_per_epoch,
            )
            run = out / model / f"seed{seed}"
            t0 = time.process_time()
            res = train(f"{d}/train.parquet", f"{d}/val.parquet", TrainOutputs.in_dir(run, resume=True), ts)
            t_train = time.process_time() - t0
            ev = evaluate_frames(
                frames,
                {model: method_spec(model, res["best"], device=device)},
                references=("truth",),
                split=settings.evaluation.split,
            )
            t3 = tables.table3(ev, kinds)
            t3.insert(2, "seed", seed)
            rows.append(t3)
            print(
                f"{model} seed {seed}: best epoch {res['best_epoch']}, {len(frames)} test frames, "
                f"train {t_train:.0f} CPU s, RMSE filling {t3[tables.METHOD_LABELS['rmse_missing_counted_m']].iloc[0]:.5f} m",
                flush=True,
            )
    write_spread(
        pd.concat(rows, ignore_index=True), out, caption.replace("; device", f"; {len(frames)} test frames; device")
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
