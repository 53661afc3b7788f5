"""The run's validated config (defaults filled in) as a report item."""

from pathlib import Path

import yaml

from depthgt.jobs.common import logging_to

with logging_to(snakemake.log[0]):
    out = Path(snakemake.output[0])
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(snakemake.params.config, sort_keys=False))
