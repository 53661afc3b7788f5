from depthgt.jobs.common import logging_to
from depthgt.jobs.report import run_tables

with logging_to(snakemake.log[0]):
    run_tables(
        list(snakemake.input.evals),
        snakemake.input.framesets,
        snakemake.input.rde,
        snakemake.input.quality,
        snakemake.params.kinds,
        dict(snakemake.output.items()),
    )
