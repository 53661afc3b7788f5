from depthgt.jobs.common import logging_to
from depthgt.jobs.enhance import run_rde_scene

with logging_to(snakemake.log[0]):
    run_rde_scene(
        snakemake.params.source,
        snakemake.wildcards.scene,
        snakemake.input.framesets,
        snakemake.params.config,
        snakemake.output.frames,
        snakemake.output.framesets,
        snakemake.output.patches,
    )
