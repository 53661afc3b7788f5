"""Seconds per training step of each learned model of a build, on that build's own data,
and, side by side, against another checkout.

Runs each model's training job (:func:`depthgt.jobs.enhance.run_train`, what the workflow's
``train_model`` rule runs, with its process settings) for ``--epochs`` epochs capped at
``--steps`` steps each (the config's ``max_batches_per_epoch``), validating on the first
``--val-pairs`` pairs of the validation split (none with 0), with the settings the build's
config gives the model (``results/report/config.yaml``, else the checkout's
config/config.yaml), in a fresh process per model, and prints per model the CPU and wall
seconds per training step of the last epoch (the first reads the patches and warms up),
per validation batch, and the whole process's CPU seconds (start-up, reading, any
compilation included). ``--predict-frames N`` then scores the trained model on the first
N test frames with the evaluation's code (:func:`depthgt.eval.evaluate.evaluate_frames`:
reading, prediction, metrics) and prints its CPU seconds per frame. A build's training
cost is (training pairs / batch size) x epochs x seconds per step (docs/decisions.md,
"Threads per training on 2 cores").

CPU seconds are this process's own (``time.process_time``, one torch thread by default as
the 2-core build's trainings run): on a shared machine they move far less than wall
seconds, which count the time other processes hold the cores.

``--against CHECKOUT`` runs every model with ``CHECKOUT/src`` as well, in turn (this, other,
this, other, ... ``--repeats`` times per model), on the same data and settings, and prints
the ratio other / this of each pair (median, min, max): the speed-up of this checkout.

    python3 bench/bench_train_steps.py WORKDIR                          # every learned model
    python3 bench/bench_train_steps.py WORKDIR --models lapden --steps 20 --threads 2
    python3 bench/bench_train_steps.py WORKDIR --against /tmp/base --repeats 3 --predict-frames 10
    python3 bench/bench_train_steps.py WORKDIR --models lapden --predict-frames 5 --profile   # by op class

``--profile`` prints torch.profiler's account of the timed epoch, the last validation and
the evaluated frames: the share of each op class (convolutions forward and backward,
pooling and resampling, ...) and the top ops (the profiler slows them by ~10-20 %).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

if __name__ == "__main__" and "--src" in sys.argv:  # run another checkout's library (see --against)
    sys.path.insert(0, sys.argv[sys.argv.index("--src") + 1])

import pandas as pd
import yaml

from depthgt import registry
from depthgt.settings import stage_settings

REPO = Path(__file__).resolve().parents[1]


def _config(workdir: Path, src: Path) -> dict:
    built = workdir / "results/report/config.yaml"
    path = built if built.is_file() else src.parent / "config/config.yaml"
    return yaml.safe_load(path.read_text())


def _manifests(workdir: Path, model: str) -> tuple[Path, Path]:
    """The training and validation manifests the workflow gives ``model`` (the RDE GT's for RDE)."""
    root = workdir / ("results/rde" if registry.METHODS[model].trains_on == "rde" else "results/dataset")
    return (root / "train.parquet").resolve(), (root / "val.parquet").resolve()


def _cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def run_one(a: argparse.Namespace) -> dict:
    """One model's training job in this process, with the library on ``sys.path``; its timings."""
    import depthgt.enhance.train as tr
    from depthgt.jobs.enhance import run_train

    model = a.models[0]
    config = _config(a.workdir, Path(tr.__file__).resolve().parents[2])
    key = registry.METHODS[model].settings_key
    st = stage_settings(config, "train", model=key).train(model)
    capped = {"epochs": a.epochs, "max_batches_per_epoch": a.steps, "progress": False}
    enhance = config.setdefault("enhance", {})
    enhance["train"] = {**enhance.get("train", {}), **capped}
    enhance["models"][key] = {**enhance["models"][key], **capped}
    train_m, val_m = _manifests(a.workdir, model)
    timed: dict[str, list[tuple[float, float, int]]] = {"train": [], "val": []}

    def timing(fn, what):  # CPU and wall seconds of each call of the trainer's step functions
        def wrapped(*args, **kwargs):
            last = len(timed["train"]) == a.epochs - (what == "train")  # the timed (last) epoch
            with _profiled(a.profile and last, f"{model}: {what} epoch {len(timed[what])}"):
                c0, w0 = time.process_time(), time.perf_counter()
                out = fn(*args, **kwargs)
                timed[what].append((time.process_time() - c0, time.perf_counter() - w0, int(out["batches"])))
            return out

        return wrapped

    tr.train_epoch = timing(tr.train_epoch, "train")
    tr.evaluate = timing(tr.evaluate, "val")
    cwd = Path.cwd()
    row = {"model": model, "src": str(Path(tr.__file__).resolve().parents[2])}
    with tempfile.TemporaryDirectory() as tmp:
        val = None
        if a.val_pairs > 0:
            val = str(Path(tmp) / "val.parquet")
            pd.read_parquet(val_m).head(a.val_pairs).to_parquet(val, index=False)
        outputs = {k: str(Path(tmp) / f) for k, f in (("best", "best.pt"), ("last", "last.pt"), ("log", "log.csv"))}
        outputs["meta"] = str(Path(tmp) / "train.json")
        try:
            os.chdir(a.workdir)  # the manifests' locations are relative to the working directory
            run_train(model, config, str(train_m), val, outputs, threads=a.threads)
            if a.predict_frames:
                row.update(_predict(a, model, Path(outputs["best"])))
        finally:
            os.chdir(cwd)
    cpu, wall, n = timed["train"][-1]
    row.update(
        step_cpu=cpu / n,
        step_wall=wall / n,
        first_epoch_cpu=timed["train"][0][0],
        batch_size=st.batch_size,
        epochs=st.epochs,
        train_pairs=len(pd.read_parquet(train_m)),
        process_cpu=_cpu(),
    )
    if timed["val"]:
        cpu, wall, n = timed["val"][-1]
        row.update(val_batch_cpu=cpu / n, val_batch_wall=wall / n)
    return row


def _predict(a: argparse.Namespace, model: str, checkpoint: Path) -> dict:
    from depthgt.eval.evaluate import evaluate_frames, method_spec

    frames = pd.read_parquet(a.workdir / "results/dataset/framesets.parquet")
    if "split" in frames.columns:
        frames = frames[frames["split"] == "test"]
    if "status" in frames.columns:
        frames = frames[frames["status"] == "ok"]
    frames = frames[frames["frameset"] != ""].head(a.predict_frames)
    with _profiled(a.profile, f"{model}: evaluation of {len(frames)} test frames"):
        c0 = time.process_time()
        evaluate_frames(frames, {model: method_spec(model, checkpoint, device="cpu")}, split=None)
        cpu = time.process_time() - c0
    return {"predict_frame_cpu": cpu / max(len(frames), 1)}


#: torch.profiler's op names by class, for --profile's summary (the first pattern that matches)
OP_CLASSES = (
    ("convolution backward", ("convolution_backward",)),
    ("convolution forward", ("convolution", "conv2d")),
    ("pooling and resampling", ("pool", "upsample", "pad")),
    ("cross product and norms", ("cross", "norm")),
    ("copies and concatenation", ("copy_", "cat", "_to_copy", "clone", "contiguous", "stack")),
)


@contextmanager
def _profiled(on: bool, title: str):
    """torch.profiler over the block when ``on``: CPU seconds by op class and the top ops."""
    if not on:
        yield
        return
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        yield
    ops = [e for e in prof.key_averages() if e.key.startswith("aten::")]
    total = sum(e.self_cpu_time_total for e in ops) or 1.0
    classes: dict[str, float] = {}
    for e in ops:
        name = next((c for c, pats in OP_CLASSES if any(p in e.key for p in pats)), "other (pointwise, reductions)")
        classes[name] = classes.get(name, 0.0) + e.self_cpu_time_total
    print(f"--- profile, {title}: {total / 1e6:.2f} s of aten ops (self CPU, profiler overhead included)")
    for name, t in sorted(classes.items(), key=lambda kv: -kv[1]):
        print(f"  {name:32s} {100 * t / total:5.1f} %")
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=12), flush=True)


def _worker(a: argparse.Namespace, model: str, src: Path) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "row.json"
        cmd = [sys.executable, __file__, str(a.workdir), "--models", model, "--src", str(src), "--json", str(out)]
        for key in ("threads", "steps", "epochs", "val_pairs", "predict_frames"):
            cmd += [f"--{key.replace('_', '-')}", str(getattr(a, key))]
        cmd += ["--profile"] if a.profile else []
        env = {**os.environ, "PYTHONPATH": str(src)}
        subprocess.run(cmd, check=True, env=env, cwd=str(src.parent))
        return json.loads(out.read_text())


COLUMNS = ("step_cpu", "val_batch_cpu", "predict_frame_cpu", "process_cpu")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path, help="a build's working directory (results/dataset, results/report)")
    ap.add_argument("--models", nargs="+", default=list(registry.learned()))
    ap.add_argument("--threads", type=int, default=1, help="torch threads per training (the 2-core build's: 1)")
    ap.add_argument("--steps", type=int, default=10, help="training steps per epoch")
    ap.add_argument("--epochs", type=int, default=2, help="epochs; the last one is timed")
    ap.add_argument("--val-pairs", type=int, default=64, help="validation pairs per epoch (0: none)")
    ap.add_argument("--predict-frames", type=int, default=0, help="test frames scored with the trained model")
    ap.add_argument("--against", type=Path, help="another checkout, run in turn with this one")
    ap.add_argument("--repeats", type=int, default=1, help="runs per model (and checkout)")
    ap.add_argument(
        "--profile", action="store_true", help="torch.profiler tables of the timed epoch and the evaluation"
    )
    ap.add_argument("--src", type=Path, help=argparse.SUPPRESS)  # internal: one model in this process
    ap.add_argument("--json", type=Path, help=argparse.SUPPRESS)
    a = ap.parse_args()
    a.workdir = a.workdir.resolve()
    if a.src is not None:
        a.json.write_text(json.dumps(run_one(a)))
        return
    srcs = {"this": REPO / "src"} | ({"other": a.against.resolve() / "src"} if a.against else {})
    rows = []
    for rep in range(a.repeats):
        for model in a.models:
            for name, src in srcs.items():
                row = _worker(a, model, src)
                rows.append({"run": name, "repeat": rep, **row})
                print(json.dumps(rows[-1]), flush=True)
    df = pd.DataFrame(rows)
    print(f"\n{a.threads} thread(s), {a.steps} steps x {a.epochs} epochs (last timed), {a.repeats} repeat(s)")
    for model, d in df.groupby("model", sort=False):
        first = d.iloc[0]
        for name, r in d.groupby("run", sort=False):
            med = {c: statistics.median(r[c]) for c in COLUMNS if c in r and r[c].notna().all()}
            steps = math.ceil(first["train_pairs"] / first["batch_size"])
            print(
                f"{model} ({name}): "
                + ", ".join(f"{c} {v:.3f} s" for c, v in med.items())
                + f"; the config's {first['epochs']} epochs of {steps} steps: "
                f"{first['epochs'] * steps * med['step_cpu'] / 60:.1f} CPU min of training steps"
            )
        if a.against:
            this, other = d[d["run"] == "this"].reset_index(), d[d["run"] == "other"].reset_index()
            for c in COLUMNS:
                if c in d and d[c].notna().all():
                    ratio = other[c] / this[c]
                    print(
                        f"  {c} other / this: median {ratio.median():.2f} [{ratio.min():.2f}, {ratio.max():.2f}]"
                        f" over {len(ratio)} pair(s)"
                    )


if __name__ == "__main__":
    main()
