from depthgt.jobs.common import logging_to
from depthgt.jobs.enhance import run_rde_training_manifests

with logging_to(snakemake.log[0]):
    run_rde_training_manifests(list(snakemake.input.patches), dict(snakemake.output.items()))
