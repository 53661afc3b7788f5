from depthgt.jobs.common import logging_to
from depthgt.jobs.report import run_evaluate

with logging_to(snakemake.log[0]):
    run_evaluate(
        snakemake.wildcards.method,
        snakemake.params.config,
        snakemake.input.framesets,
        snakemake.output.table,
        snakemake.output.predictions,
        checkpoint=snakemake.input.get("checkpoint"),
        threads=snakemake.threads,
        reference_tables=list(snakemake.input.references),
    )
