from pathlib import Path

from depthgt.jobs.gt import logging_to
from depthgt.jobs.enhance import run_train

with logging_to(snakemake.log[0]):
    run_train(snakemake.params.settings, snakemake.input.train, snakemake.input.val,
              str(Path(snakemake.output.best).parent), threads=snakemake.threads)
