from depthgt.jobs.common import logging_to
from depthgt.jobs.enhance import run_train

with logging_to(snakemake.log[0]):
    outputs = {"best": snakemake.output.best, "last": snakemake.output.last, "log": snakemake.output.log,
               "meta": snakemake.output.meta}
    run_train(snakemake.wildcards.model, snakemake.config, snakemake.input.train, snakemake.input.val, outputs,
              threads=snakemake.threads)
