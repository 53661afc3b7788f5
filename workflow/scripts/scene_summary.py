from depthgt.jobs.common import logging_to
from depthgt.jobs.gt import run_scene_summary

with logging_to(snakemake.log[0]):
    run_scene_summary(
        snakemake.input.index,
        list(snakemake.input.shards),
        snakemake.output.framesets,
        snakemake.output.patches,
        snakemake.output.quality,
        snakemake.output.frames,
    )
