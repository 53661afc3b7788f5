# depthgt: ground-truth depth datasets from raw RGB-D video (see README.md).
from snakemake.utils import min_version

min_version("9.21")


configfile: "config/config.yaml"


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
