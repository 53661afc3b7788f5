from depthgt.jobs.common import logging_to
from depthgt.jobs.report import run_figures

with logging_to(snakemake.log[0]):
    curves = dict(zip(snakemake.params.models, snakemake.output.curves))
    logs = dict(zip(snakemake.params.models, snakemake.input.logs))
    preds = dict(zip(snakemake.params.methods, snakemake.input.predictions))
    run_figures(
        snakemake.input.framesets,
        preds,
        logs,
        snakemake.output.comparison,
        curves,
        split=snakemake.params.split,
        frames_per_scene=snakemake.params.frames_per_scene,
    )
