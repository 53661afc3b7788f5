from pathlib import Path

from depthgt.jobs.gt import logging_to, run_dataset

with logging_to(snakemake.log[0]):
    run_dataset(list(snakemake.input.scenes), str(Path(snakemake.output.train).parent))
