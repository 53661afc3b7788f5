# depthgt: ground-truth depth datasets from raw RGB-D video (see README.md).
import os

from snakemake.utils import min_version

min_version("9.21")


# The config: the working directory's config/config.yaml when it holds one (a working
# directory of its own, `depthgt build -d DIR`), else the embedded default beside this
# file, wherever Snakemake is started: `-s path/to/Snakefile -d elsewhere --configfile
# mine.yaml` applies mine.yaml over the same defaults as in the checkout.
configfile: "config/config.yaml" if os.path.isfile("config/config.yaml") else os.path.join(workflow.basedir, "config/config.yaml")


include: "workflow/rules/common.smk"
include: "workflow/rules/inputs.smk"
include: "workflow/rules/index.smk"
include: "workflow/rules/registration.smk"
include: "workflow/rules/framesets.smk"
include: "workflow/rules/dataset.smk"
include: "workflow/rules/enhance.smk"
include: "workflow/rules/report.smk"


rule all:
    default_target: True
    input:
        rules.dataset.output,
        rules.report.input,
