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
import sys

# the training, scoring and pairing are bench_train_variants' (this script's folder is on sys.path)
from bench_train_variants import add_run_arguments, run_from_args


def variant_name(sigma_ref: float | None) -> str:
    return "paper" if sigma_ref is None else f"sigma_ref_{sigma_ref * 1000:g}mm"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sigma-ref", type=float, nargs="*", default=[], help="metres; one weighted run each")
    add_run_arguments(
        ap, "/tmp/depthgt_bench_loss_weight", "another run's --out: pair this build's unweighted model with its own"
    )
    a = ap.parse_args(argv)
    print(f"command: python3 bench/bench_loss_weight.py {' '.join(sys.argv[1:] if argv is None else argv)}", flush=True)
    if not a.sigma_ref and not a.against:
        ap.error("nothing to compare: give --sigma-ref values, --against another run's --out, or both")
    if any(not (s > 0) for s in a.sigma_ref):
        ap.error(f"--sigma-ref values must be > 0 metres, got {a.sigma_ref}")
    # the paper's loss: the config's loss_params without a weight, whatever the config says
    variants = [(variant_name(None), {"loss_params.sigma_ref_m": None})]
    variants += [(variant_name(s), {"loss_params.sigma_ref_m": s}) for s in a.sigma_ref]
    return run_from_args(a, variants, "lapden", reference="paper")


if __name__ == "__main__":
    raise SystemExit(main())
