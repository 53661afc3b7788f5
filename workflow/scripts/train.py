from pathlib import Path

from depthgt.jobs.common import logging_to
from depthgt.jobs.enhance import run_train

# the resume state and a copy of the log live beside the outputs but are not outputs:
# Snakemake deletes a killed job's outputs and log before it runs the job again
resume = Path(snakemake.output.best).parent / "resume"
with logging_to(snakemake.log[0], keep=resume / "job.log"):
    outputs = {
        "best": snakemake.output.best,
        "last": snakemake.output.last,
        "log": snakemake.output.log,
        "meta": snakemake.output.meta,
        "resume": str(resume),
    }
    run_train(
        snakemake.wildcards.model,
        snakemake.params.config,
        snakemake.input.train,
        snakemake.input.val,
        outputs,
        threads=snakemake.threads,
    )
