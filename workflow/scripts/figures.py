from pathlib import Path

from depthgt.jobs.gt import logging_to
from depthgt.jobs.enhance import run_figures

with logging_to(snakemake.log[0]):
    curves = dict(zip(snakemake.params.models, snakemake.output.curves))
    logs = dict(zip(snakemake.params.models, snakemake.input.logs))
    preds = {m: str(Path(snakemake.input.evals[0]).parent / "predictions" / m) for m in snakemake.params.methods}
    run_figures(snakemake.input.framesets, preds, logs, snakemake.output.comparison, curves,
                split=snakemake.params.split, frames_per_scene=snakemake.params.frames_per_scene)
