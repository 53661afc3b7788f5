"""The GT's confidence as a loss weight (issue 27 item 5), chosen on VALIDATION frames only.

    # a default build's dataset first (python3 -m snakemake --cores 2 dataset), then
    python3 bench/bench_loss_weight.py -d WORKDIR --sigma-ref 0.005 0.02 --threads 1
    python3 bench/bench_loss_weight.py -d WORKDIR --sigma-ref 0.01 --epochs 1 --max-batches 2 --max-frames 4  # tiny

LapDEN is trained on the build's GT patches (``results/dataset`` train/val, the config's
``enhance.train`` + ``enhance.models.lapden``, what the workflow's ``train_model`` rule
uses) once as the paper has it (every valid GT pixel alike) and once per ``--sigma-ref``
with ``loss_params.sigma_ref_m`` set (:func:`depthgt.enhance.losses.confidence_weight`:
each GT pixel's depth term weighted by ``sigma_ref^2 / (sigma_ref^2 + sigma^2)``), the
same seed, crops and order. Each run's ``best.pt`` is scored on the full frames of the
training source's ``val`` frame sets (never a test frame) against the clean truth with
Table 3's masks and per-frame means (:func:`depthgt.eval.tables.table3`), and every
weighted run is compared with the unweighted one frame by frame (mean difference and 95 %
bootstrap interval over the same frames, :func:`depthgt.eval.bootstrap.bootstrap_means`).

Rule, fixed before the runs: a weight becomes the default only if it lowers the
validation RMSE with the holes counted (Table 3's "RMSE, filling") with a paired interval
below zero and does not raise the MAE where the input is valid ("MAE, denoising") with an
interval above zero; of several such, the lowest RMSE. Otherwise the paper's loss stays.

``--against DIR`` pairs this run's unweighted model with another run's (``DIR``, an
``--out`` of this script on another build of the same training rooms and splits, e.g.
one with ``frameset.selection: coverage``: the GT's completeness as the lever) on the
same val frames: the paired table then gives every run of this build minus that one.

Writes ``--out``/runs.csv (Table 3's columns per run), ``--out``/paired.csv and prints
both. Checkpoints are kept under ``--out`` and reused (a finished run resumes at its end).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch
import yaml

from depthgt.device import resolve_device
from depthgt.enhance.train import TrainOutputs, train
from depthgt.eval import tables
from depthgt.eval.bootstrap import bootstrap_means
from depthgt.eval.evaluate import evaluate_frames, method_spec
from depthgt.settings import settings_from_config
from depthgt.status import Status

REPO = Path(__file__).resolve().parents[1]
# Table 3's columns compared frame by frame (per-frame metric of the long evaluation table)
PAIRED = {
    "rmse_missing_counted_m": "RMSE, filling",
    "mae_missing_counted_m": "MAE, filling",
    "rmse_input_valid_m": "RMSE, denoising",
    "mae_input_valid_m": "MAE, denoising",
}


def variant_name(sigma_ref: float | None) -> str:
    return "paper" if sigma_ref is None else f"sigma_ref_{sigma_ref * 1000:g}mm"


def per_frame(ev: pd.DataFrame) -> pd.DataFrame:
    """Per-frame values of the :data:`PAIRED` metrics against the truth (frames x metrics)."""
    ev = ev[(ev["reference"] == "truth") & ev["metric"].isin(list(PAIRED))]
    return ev.pivot_table(index=["dataset", "scene", "target"], columns="metric", values="value")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-d", "--workdir", required=True, help="a build with results/dataset (train, val, framesets)")
    ap.add_argument("--configfile", default=str(REPO / "config/config.yaml"), help="the build's config")
    ap.add_argument("--sigma-ref", type=float, nargs="*", default=[], help="metres; one weighted run each")
    ap.add_argument("--seed", type=int, default=None, help="training seed (default: the config's)")
    ap.add_argument("--epochs", type=int, default=None, help="override the config's epochs (tiny runs)")
    ap.add_argument("--max-batches", type=int, default=None, help="cap on training steps per epoch (tiny runs)")
    ap.add_argument("--max-frames", type=int, default=None, help="val frames per dataset (tiny runs; default all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default="/tmp/depthgt_bench_loss_weight")
    ap.add_argument(
        "--against", default=None, help="another run's --out: pair this build's unweighted model with its own"
    )
    a = ap.parse_args(argv)
    print(f"command: python3 bench/bench_loss_weight.py {' '.join(sys.argv[1:] if argv is None else argv)}", flush=True)
    if not a.sigma_ref and not a.against:
        ap.error("nothing to compare: give --sigma-ref values, --against another run's --out, or both")
    if any(not (s > 0) for s in a.sigma_ref):
        ap.error(f"--sigma-ref values must be > 0 metres, got {a.sigma_ref}")
    torch.set_num_threads(a.threads)
    device = str(resolve_device(a.device))
    settings = settings_from_config(yaml.safe_load(Path(a.configfile).read_text()))
    out = Path(a.out).resolve()
    os.chdir(a.workdir)  # the manifests' locations are relative to the build's folder
    kinds = {src.name: src.kind for src in settings.sources}
    auto = {src.name for src in settings.sources if src.split == "auto" and src.kind == "synthetic"}
    fs = pd.read_parquet("results/dataset/framesets.parquet")
    frames = fs[
        (fs["split"] == "val") & (fs["status"] == Status.OK) & (fs["frameset"] != "") & fs["dataset"].isin(auto)
    ]
    if a.max_frames:
        frames = frames.groupby("dataset", group_keys=False).head(a.max_frames)
    if frames.empty:
        print(f"{a.workdir}: no val frame sets of a synthetic split: auto source", file=sys.stderr)
        return 1

    base = settings.train("lapden")
    seed = base.seed if a.seed is None else a.seed
    rows, frame_values = [], {}
    for sigma_ref in [None, *a.sigma_ref]:
        name = variant_name(sigma_ref)
        params = {k: v for k, v in base.loss_params.items() if k != "sigma_ref_m"}
        if sigma_ref is not None:
            params["sigma_ref_m"] = sigma_ref
        ts = replace(
            base,
            seed=seed,
            loss_params=params,
            progress=False,
            device=device,
            epochs=a.epochs if a.epochs is not None else base.epochs,
            max_batches_per_epoch=a.max_batches if a.max_batches is not None else base.max_batches_per_epoch,
        )
        t0 = time.process_time()
        res = train(
            "results/dataset/train.parquet",
            "results/dataset/val.parquet",
            TrainOutputs.in_dir(out / name, resume=True),
            ts,
        )
        t_train = time.process_time() - t0
        ev = evaluate_frames(
            frames, {"lapden": method_spec("lapden", res["best"], device=device)}, references=("truth",), split="val"
        )
        ev.to_parquet(out / name / "frames.parquet", index=False)
        frame_values[name] = per_frame(ev)
        t3 = tables.table3(ev, kinds)
        t3.insert(1, "variant", name)
        t3.insert(2, "best_epoch", res["best_epoch"] + 1)
        rows.append(t3)
        print(
            f"{name}: best epoch {res['best_epoch'] + 1}, {len(frames)} val frames, train {t_train:.0f} CPU s, "
            f"RMSE filling {frame_values[name]['rmse_missing_counted_m'].mean() * 1000:.2f} mm",
            flush=True,
        )
    runs = pd.concat(rows, ignore_index=True)
    ref = frame_values["paper"]
    if a.against:
        other = per_frame(pd.read_parquet(Path(a.against).resolve() / "paper" / "frames.parquet"))
        if set(other.index) != set(ref.index):
            raise SystemExit(f"--against {a.against}: its val frames are not this build's ({len(other)} vs {len(ref)})")
        ref = other
    paired = []
    for name, v in frame_values.items():
        if name == "paper" and not a.against:
            continue
        diff = (v - ref).reindex(ref.index)
        row = {"variant": name, "frames": int(diff.notna().all(axis=1).sum())}
        for metric, label in PAIRED.items():
            m = bootstrap_means(diff[metric].to_numpy(dtype=np.float64) * 1000.0)
            row[f"{label} (mm)"] = f"{m.mean[0]:+.2f} [{m.low[0]:+.2f}, {m.high[0]:+.2f}]"
        paired.append(row)
    paired = pd.DataFrame(paired)
    out.mkdir(parents=True, exist_ok=True)
    runs.to_csv(out / "runs.csv", index=False)
    paired.to_csv(out / "paired.csv", index=False)
    print(f"\nVALIDATION ({len(frames)} val frame sets, full frames vs the clean truth, Table 3's masks):")
    print(tables.markdown_view(runs).to_markdown(index=False))
    base = f"--against {a.against}'s paper-loss model" if a.against else "paper"
    print(f"\neach minus {base}, per frame (95 % bootstrap over the val frames; negative = lower error):")
    print(paired.to_markdown(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
