# depthgt: ground-truth depth datasets from raw RGB-D video (see README.md).
import copy
import os
import sys

from snakemake.utils import min_version

min_version("9.21")


# The config: the working directory's config/config.yaml when it holds one (a working
# directory of its own, `depthgt build -d DIR`), else the embedded default beside this
# file, wherever Snakemake is started: `-s path/to/Snakefile -d elsewhere --configfile
# mine.yaml` applies mine.yaml over the same defaults as in the checkout. Over it go the
# --configfile files the build ran with before (results/config/overrides.yaml, written
# by the first real run) and this run's; a run whose --configfile changes keys of an
# existing build stops, naming them, unless DEPTHGT_RECONFIGURE=1 (depthgt.buildconfig).
# A --configfile with a top-level key that is no config key stops the run too, naming
# the keys (when most are such: most likely a target written after --configfile, which
# takes every value up to the next option).
configfile: "config/config.yaml" if os.path.isfile("config/config.yaml") else os.path.join(workflow.basedir, "config/config.yaml")


from depthgt import buildconfig  # standard library and PyYAML only
from depthgt.settings import TOP_LEVEL_KEYS  # torch-free

CONFIG_LAYERS = buildconfig.layered_config(
    ".",
    os.path.join(workflow.basedir, "config/config.yaml"),
    workflow.config_settings.configfiles,
    dict(workflow.config_settings.config),
    # jobs Snakemake spawns run with the config their main run remembered
    reconfigure=None if workflow.is_main_process else True,
    config_keys=TOP_LEVEL_KEYS,
)
config.clear()
config.update(copy.deepcopy(CONFIG_LAYERS.config))  # validation fills in defaults: not into what is remembered
if workflow.is_main_process and CONFIG_LAYERS.notice():
    print(CONFIG_LAYERS.notice(), file=sys.stderr)


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
