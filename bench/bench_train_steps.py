"""Seconds per training step of each learned model of a build, on that build's own data.

Trains each model for one epoch capped at ``--steps`` steps (``train()`` with ``epochs: 1``,
``max_batches_per_epoch: --steps``, no validation) from the build's training manifest,
with the settings its config gives the model (``results/report/config.yaml``), and prints
the seconds per step and per full epoch of the training split. A build's training cost is
(training pairs / batch size) x epochs x seconds per step (docs/decisions.md, "Threads
per training on 2 cores").

    python3 bench/bench_train_steps.py WORKDIR                       # every learned model, 2 threads
    python3 bench/bench_train_steps.py WORKDIR --models lapden rde --threads 1 --steps 20
"""

from __future__ import annotations

import argparse
import math
import os
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import pandas as pd
import torch
import yaml

from depthgt import registry
from depthgt.enhance.train import TrainOutputs, train
from depthgt.settings import stage_settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("workdir", type=Path, help="a build's working directory (results/dataset, results/report)")
    ap.add_argument("--models", nargs="+", default=list(registry.learned()))
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=10, help="training steps timed per model")
    args = ap.parse_args()
    config = yaml.safe_load((args.workdir / "results/report/config.yaml").read_text())
    manifest = (args.workdir / "results/dataset/train.parquet").resolve()
    pairs = len(pd.read_parquet(manifest))
    torch.set_num_threads(args.threads)
    print(f"{pairs} training pairs, {args.threads} threads, {args.steps} steps per model")
    for model in args.models:
        st = stage_settings(config, "train", model=registry.METHODS[model].settings_key).train(model)
        epochs = st.epochs
        st = replace(st, epochs=1, max_batches_per_epoch=args.steps)
        cwd = Path.cwd()
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            try:
                os.chdir(args.workdir)  # the manifests' locations are relative to the working directory
                train(manifest, None, TrainOutputs.in_dir(Path(tmp)), st)
            finally:
                os.chdir(cwd)
            wall = time.perf_counter() - start
            log = pd.read_csv(Path(tmp) / "loss_log.csv")
        step_s = float(log["seconds"].iloc[-1]) / args.steps
        steps = math.ceil(pairs / st.batch_size)
        print(
            f"{model}: batch {st.batch_size}, {step_s:.3f} s per step ({wall:.1f} s wall with set-up); "
            f"epoch of {steps} steps {steps * step_s:.0f} s; the config's {epochs} epochs "
            f"{epochs * steps * step_s / 60:.1f} min"
        )


if __name__ == "__main__":
    main()
