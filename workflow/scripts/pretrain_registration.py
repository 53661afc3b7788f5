import torch

from depthgt.jobs.common import logging_to
from depthgt.jobs.gt import run_pretrain_registration

torch.set_num_threads(snakemake.threads)
with logging_to(snakemake.log[0]):
    run_pretrain_registration(
        snakemake.params.sources, list(snakemake.input.indices), snakemake.params.config, snakemake.output[0]
    )
