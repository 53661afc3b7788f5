from depthgt.jobs.gt import logging_to
from depthgt.jobs.enhance import run_evaluate

with logging_to(snakemake.log[0]):
    run_evaluate(snakemake.wildcards.method, snakemake.params.method, snakemake.input.framesets, snakemake.output.table,
                 snakemake.output.predictions, split=snakemake.params.split, threads=snakemake.threads)
