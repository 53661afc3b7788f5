from depthgt.jobs.common import logging_to
from depthgt.jobs.gt import run_scene_references

with logging_to(snakemake.log[0]):
    run_scene_references(
        snakemake.params.source,
        snakemake.wildcards.scene,
        snakemake.input.framesets,
        snakemake.input.rde,
        snakemake.params.config,
        snakemake.output.images,
        snakemake.output.table,
    )
