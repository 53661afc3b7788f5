"""Training settings of one learned model compared on VALIDATION frames only (issue 27).

    # a default build's dataset first (python3 -m snakemake --cores 2 dataset), then
    python3 bench/bench_train_variants.py -d WORKDIR --model sdd \\
        --variant cosine10:lr_schedule=cosine,epochs=10 --threads 1
    python3 bench/bench_train_variants.py -d WORKDIR --model lapden \\
        --variant w5mm:loss_params.sigma_ref_m=0.005 --epochs 1 --max-batches 2 --max-frames 4   # tiny

The model (``--model``: lapden, ddrnet or sdd) is trained on the build's GT patches
(``results/dataset`` train/val, the config's ``enhance.train`` + ``enhance.models.MODEL``,
what the workflow's ``train_model`` rule uses) once with the config's settings (the
variant ``default``) and once per ``--variant NAME:KEY=VALUE,...`` (TrainSettings fields,
``loss_params.X`` / ``model_params.X`` for one key of those mappings; values read as
YAML), the same seed unless a variant sets its own. Each run's ``best.pt`` is scored on
the full frames of the training source's ``val`` frame sets (never a test frame) against
the clean truth with Table 3's masks and per-frame means (:func:`depthgt.eval.tables.table3`),
and every variant is compared with ``default`` frame by frame (mean difference and 95 %
bootstrap interval over the same frames, :func:`depthgt.eval.bootstrap.bootstrap_means`).

The score a choice is made on (``--score``'s default): RMSE with the holes counted
(Table 3's "RMSE, filling") for the models that fill holes (LapDEN, SDD), RMSE where the
input is valid ("RMSE, denoising") for DDRNet, which keeps the input's holes (the rule of
bench/bench_enhance_protocol.py, which chose the current epochs).

``--against DIR`` pairs this run's ``default`` model with another run's (``DIR``, an
``--out`` of this script on another build of the same training rooms and splits, e.g.
one with ``frameset.selection: coverage``) on the same val frames: the paired table then
gives every run of this build minus that one.

Writes ``--out``/runs.csv (Table 3's columns per run, with training CPU seconds and
steps), ``--out``/paired.csv and prints both. Runs are kept under ``--out``/NAME and
reused (a finished run resumes at its end).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import fields, replace
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
from depthgt.settings import TrainSettings, settings_from_config
from depthgt.status import Status

REPO = Path(__file__).resolve().parents[1]
# Table 3's columns compared frame by frame (per-frame metric of the long evaluation table)
PAIRED = {
    "rmse_missing_counted_m": "RMSE, filling",
    "mae_missing_counted_m": "MAE, filling",
    "rmse_input_valid_m": "RMSE, denoising",
    "mae_input_valid_m": "MAE, denoising",
}
SCORE = {"lapden": "rmse_missing_counted_m", "sdd": "rmse_missing_counted_m", "ddrnet": "rmse_input_valid_m"}


def per_frame(ev: pd.DataFrame) -> pd.DataFrame:
    """Per-frame values of the :data:`PAIRED` metrics against the truth (frames x metrics)."""
    ev = ev[(ev["reference"] == "truth") & ev["metric"].isin(list(PAIRED))]
    return ev.pivot_table(index=["dataset", "scene", "target"], columns="metric", values="value")


def parse_variant(text: str) -> tuple[str, dict]:
    """``NAME:KEY=VALUE,KEY=VALUE`` -> (NAME, {KEY: VALUE}); values read as YAML."""
    name, sep, body = text.partition(":")
    if not name or not sep or name == "default":
        raise argparse.ArgumentTypeError(f"--variant {text!r}: expected NAME:KEY=VALUE,... with NAME not 'default'")
    overrides = {}
    for item in filter(None, body.split(",")):
        key, eq, value = item.partition("=")
        if not eq:
            raise argparse.ArgumentTypeError(f"--variant {text!r}: {item!r} is not KEY=VALUE")
        overrides[key.strip()] = yaml.safe_load(value)
    return name, overrides


def apply_overrides(base: TrainSettings, overrides: dict) -> TrainSettings:
    """``base`` with TrainSettings fields (and ``loss_params.X``/``model_params.X`` keys) replaced."""
    names = {f.name for f in fields(TrainSettings)}
    changes: dict = {}
    for key, value in overrides.items():
        head, dot, sub = key.partition(".")
        if head not in names or (dot and head not in ("loss_params", "model_params")):
            raise SystemExit(f"variant key {key!r}: not a TrainSettings field (or loss_params.X / model_params.X)")
        if dot:
            mapping = dict(changes.get(head, getattr(base, head)))
            if value is None:
                mapping.pop(sub, None)
            else:
                mapping[sub] = value
            changes[head] = mapping
        else:
            changes[head] = value
    return replace(base, **changes)


def val_frames(settings, max_frames: int | None) -> tuple[pd.DataFrame, dict]:
    """The OK val frame sets of the synthetic ``split: auto`` sources of the build in the
    working directory, and the sources' kinds (Table 3's rows)."""
    kinds = {src.name: src.kind for src in settings.sources}
    auto = {src.name for src in settings.sources if src.split == "auto" and src.kind == "synthetic"}
    fs = pd.read_parquet("results/dataset/framesets.parquet")
    frames = fs[
        (fs["split"] == "val") & (fs["status"] == Status.OK) & (fs["frameset"] != "") & fs["dataset"].isin(auto)
    ]
    if max_frames:
        frames = frames.groupby("dataset", group_keys=False).head(max_frames)
    return frames, kinds


def run_variants(
    variants: list[tuple[str, dict]],
    *,
    model: str,
    workdir: str,
    configfile: str,
    out: Path,
    seed: int | None = None,
    epochs: int | None = None,
    max_batches: int | None = None,
    max_frames: int | None = None,
    device: str = "cpu",
    against: str | None = None,
    reference: str = "default",
    score: str | None = None,
) -> int:
    """Train and score every ``(name, overrides)`` of ``variants`` (the first is the
    reference, normally ``("default", {})``), print and write runs.csv and paired.csv."""
    settings = settings_from_config(yaml.safe_load(Path(configfile).read_text()))
    out = Path(out).resolve()
    device = str(resolve_device(device))
    os.chdir(workdir)  # the manifests' locations are relative to the build's folder
    frames, kinds = val_frames(settings, max_frames)
    if frames.empty:
        print(f"{workdir}: no val frame sets of a synthetic split: auto source", file=sys.stderr)
        return 1
    base = settings.train(model)
    base = replace(
        base,
        seed=base.seed if seed is None else seed,
        progress=False,
        device=device,
        epochs=base.epochs if epochs is None else epochs,
        max_batches_per_epoch=base.max_batches_per_epoch if max_batches is None else max_batches,
    )
    score = score or SCORE.get(model, "rmse_missing_counted_m")
    rows, frame_values = [], {}
    for name, overrides in variants:
        ts = apply_overrides(base, overrides)
        t0 = time.process_time()
        res = train(
            "results/dataset/train.parquet",
            "results/dataset/val.parquet",
            TrainOutputs.in_dir(out / name, resume=True),
            ts,
        )
        t_train = time.process_time() - t0
        log = pd.read_csv(res["log"])
        steps = int(log.loc[log["split"] == "train", "batches"].sum())
        ev = evaluate_frames(
            frames, {model: method_spec(model, res["best"], device=device)}, references=("truth",), split="val"
        )
        ev.to_parquet(out / name / "frames.parquet", index=False)
        frame_values[name] = per_frame(ev)
        t3 = tables.table3(ev, kinds)
        t3.insert(1, "variant", name)
        t3.insert(2, "epochs", ts.epochs)
        t3.insert(3, "lr_schedule", ts.lr_schedule)
        t3.insert(4, "best_epoch", res["best_epoch"] + 1)
        t3.insert(5, "train_steps", steps)
        rows.append(t3)
        print(
            f"{name}: {ts.epochs} epochs ({ts.lr_schedule}), best epoch {res['best_epoch'] + 1}, {steps} steps, "
            f"{len(frames)} val frames, train {t_train:.0f} CPU s (this call; 0 when reused), "
            f"{PAIRED.get(score, score)} {frame_values[name][score].mean() * 1000:.2f} mm",
            flush=True,
        )
    runs = pd.concat(rows, ignore_index=True)
    ref = frame_values[reference]
    if against:
        other = per_frame(pd.read_parquet(Path(against).resolve() / reference / "frames.parquet"))
        if set(other.index) != set(ref.index):
            raise SystemExit(f"--against {against}: its val frames are not this build's ({len(other)} vs {len(ref)})")
        ref = other
    paired = []
    for name, v in frame_values.items():
        if name == reference and not against:
            continue
        diff = (v - ref).reindex(ref.index)
        row = {"variant": name, "frames": int(diff.notna().all(axis=1).sum())}
        for metric, label in PAIRED.items():
            m = bootstrap_means(diff[metric].to_numpy(dtype=np.float64) * 1000.0)
            row[f"{label} (mm)"] = f"{m.mean[0]:+.2f} [{m.low[0]:+.2f}, {m.high[0]:+.2f}]"
        rel = (v[score].mean() - ref[score].mean()) / ref[score].mean()
        row[f"{PAIRED.get(score, score)}, relative"] = f"{rel * 100:+.2f} %"
        paired.append(row)
    paired = pd.DataFrame(paired)
    out.mkdir(parents=True, exist_ok=True)
    runs.to_csv(out / "runs.csv", index=False)
    paired.to_csv(out / "paired.csv", index=False)
    print(f"\nVALIDATION ({model}, {len(frames)} val frame sets, full frames vs the clean truth, Table 3's masks):")
    print(tables.markdown_view(runs).to_markdown(index=False))
    who = f"--against {against}'s {reference} model" if against else reference
    print(f"\neach minus {who}, per frame (95 % bootstrap over the val frames; negative = lower error):")
    print(paired.to_markdown(index=False))
    return 0


def add_run_arguments(ap: argparse.ArgumentParser, out: str | None, against: str) -> None:
    """The arguments every variant bench takes (this one and bench_loss_weight.py)."""
    ap.add_argument("-d", "--workdir", required=True, help="a build with results/dataset (train, val, framesets)")
    ap.add_argument("--configfile", default=str(REPO / "config/config.yaml"), help="the build's config")
    ap.add_argument("--seed", type=int, default=None, help="training seed (default: the config's)")
    ap.add_argument("--epochs", type=int, default=None, help="override the config's epochs for every run")
    ap.add_argument("--max-batches", type=int, default=None, help="cap on training steps per epoch (tiny runs)")
    ap.add_argument("--max-frames", type=int, default=None, help="val frames per dataset (tiny runs; default all)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=out, help="where the runs are kept")
    ap.add_argument("--against", default=None, help=against)


def run_from_args(a: argparse.Namespace, variants: list[tuple[str, dict]], model: str, **kw) -> int:
    """:func:`run_variants` with the arguments of :func:`add_run_arguments`."""
    torch.set_num_threads(a.threads)
    return run_variants(
        variants,
        model=model,
        workdir=a.workdir,
        configfile=a.configfile,
        out=Path(a.out),
        seed=a.seed,
        epochs=a.epochs,
        max_batches=a.max_batches,
        max_frames=a.max_frames,
        device=a.device,
        against=a.against,
        **kw,
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", default="lapden", choices=sorted(SCORE), help="the model trained")
    ap.add_argument(
        "--variant", type=parse_variant, nargs="*", default=[], help="NAME:KEY=VALUE,... (several after one --variant)"
    )
    ap.add_argument("--score", choices=list(PAIRED), default=None, help="the score the relative column reports")
    add_run_arguments(ap, None, "another run's --out: pair this build's default model with its own")
    a = ap.parse_args(argv)
    print(
        f"command: python3 bench/bench_train_variants.py {' '.join(sys.argv[1:] if argv is None else argv)}", flush=True
    )
    if not a.variant and not a.against:
        ap.error("nothing to compare: give --variant values, --against another run's --out, or both")
    a.out = a.out or f"/tmp/depthgt_bench_train_variants/{a.model}"
    return run_from_args(a, [("default", {}), *a.variant], a.model, score=a.score)


if __name__ == "__main__":
    raise SystemExit(main())
