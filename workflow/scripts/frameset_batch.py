import torch

from depthgt.jobs.common import logging_to
from depthgt.jobs.gt import run_frameset_batch

# one job per core: torch would otherwise start a thread per core in every job
torch.set_num_threads(snakemake.threads)
with logging_to(snakemake.log[0]):
    run_frameset_batch(
        snakemake.params.source,
        snakemake.wildcards.scene,
        int(snakemake.wildcards.first),
        int(snakemake.wildcards.last),
        snakemake.params.config,
        snakemake.input.index,
        snakemake.output.shard,
        encoder=snakemake.input.encoder or None,
    )
