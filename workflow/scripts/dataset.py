from depthgt.jobs.common import logging_to
from depthgt.jobs.gt import run_dataset

with logging_to(snakemake.log[0]):
    run_dataset(
        list(snakemake.input.scenes),
        list(snakemake.input.patches),
        list(snakemake.input.quality),
        list(snakemake.input.frames),
        list(snakemake.input.indices),
        dict(snakemake.output.items()),
        shards=list(snakemake.input.shards),
        config=snakemake.params.config,
        manifests=list(snakemake.input.manifests),
        allow_empty=snakemake.params.allow_empty,
    )
