from depthgt.jobs.common import logging_to
from depthgt.jobs.gt import run_scene_index

with logging_to(snakemake.log[0]):
    run_scene_index(
        snakemake.params.source,
        snakemake.wildcards.scene,
        snakemake.params.config,
        snakemake.output.table,
        snakemake.output.meta,
    )
