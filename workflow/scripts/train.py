from pathlib import Path

from depthgt.jobs import logging_to
from depthgt.jobs_enhance import run_train

with logging_to(snakemake.log[0]):
    run_train(snakemake.params.settings, snakemake.input.train, snakemake.input.val,
              str(Path(snakemake.output.best).parent), threads=snakemake.threads)
