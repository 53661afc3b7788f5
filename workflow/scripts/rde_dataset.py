from depthgt.jobs.common import logging_to
from depthgt.jobs.enhance import run_rde_dataset

with logging_to(snakemake.log[0]):
    run_rde_dataset(list(snakemake.input.framesets), list(snakemake.input.patches), dict(snakemake.output.items()))
