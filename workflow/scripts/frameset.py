from pathlib import Path

import torch

from depthgt.jobs.gt import logging_to, run_frameset

# one job per core: torch would otherwise start a thread per core in every job
torch.set_num_threads(snakemake.threads)
with logging_to(snakemake.log[0]):
    run_frameset(snakemake.params.source, snakemake.wildcards.scene, int(snakemake.wildcards.target),
                 snakemake.params.config, snakemake.input.index, str(Path(snakemake.output.meta).parent),
                 encoder=snakemake.input.encoder or None, cache_dir=snakemake.input.cache)
