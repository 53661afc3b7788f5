from depthgt.jobs.common import logging_to
from depthgt.jobs.gt import run_training_manifests

with logging_to(snakemake.log[0]):
    run_training_manifests(list(snakemake.input.patches), dict(snakemake.output.items()))
