from pathlib import Path

from depthgt.jobs.gt import logging_to
from depthgt.jobs.enhance import run_tables

with logging_to(snakemake.log[0]):
    run_tables(list(snakemake.input.evals), snakemake.input.framesets, snakemake.input.rde, snakemake.input.quality,
               snakemake.params.kinds, str(Path(snakemake.output.table1).parent))
