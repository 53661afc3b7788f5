# Enhancement: the global-reconstruction GT (RDE), training of LapDEN and the learned
# baselines, and the evaluation of every method on the held-out test frame sets.

from depthgt import registry

ENHANCE = config.get("enhance", {})
MODELS = list(registry.learned())  # every trainable model of the registry (target `train`)
METHODS = list(SETTINGS.evaluation.methods)
EVALUATED_MODELS = SETTINGS.evaluation.models  # trained by the default target
KINDS = {name: src["kind"] for name, src in SOURCES.items()}
MANIFESTS = {"depthgt": "results/dataset", "rde": "results/rde"}  # the GT a learned method trains on


def train_config(wildcards):
    """The config sections that decide a model's training (its params: a change re-runs
    exactly this model); the job builds its TrainSettings from the whole config."""
    key = registry.METHODS[wildcards.model].settings_key
    models = ENHANCE.get("models", {})
    return {"seed": config.get("seed", 0), "device": config.get("device", "auto"),
            "enhance": {"train": ENHANCE.get("train", {}), "models": {key: models[key]} if key in models else {}}}


def train_manifests(wildcards):
    d = MANIFESTS[registry.METHODS[wildcards.model].trains_on]
    return {"train": f"{d}/train.parquet", "val": f"{d}/val.parquet"}


def method_inputs(wildcards):
    """The trained model of a learned method (none for input and filters)."""
    if registry.METHODS[wildcards.method].kind == "learned":
        return {"checkpoint": f"results/models/{wildcards.method}/best.pt"}
    return {}


rule rde_scene:
    input:
        framesets="results/scenes/{dataset}/{scene}/framesets.parquet",
        cache="results/scenes/{dataset}/{scene}/frames",
    output:
        frames=directory("results/rde/{dataset}/{scene}/frames"),
        framesets="results/rde/{dataset}/{scene}/framesets.parquet",
        patches="results/rde/{dataset}/{scene}/patches.parquet",
    params:
        source=source_of,
        config={"enhance": {"rde": ENHANCE.get("rde", {})}},
    log:
        "logs/rde/{dataset}/{scene}.log",
    benchmark:
        "benchmarks/rde/{dataset}/{scene}.tsv"
    threads: 1
    script:
        "../scripts/rde.py"


rule rde_dataset:
    input:
        framesets=[f"results/rde/{d}/{s}/framesets.parquet" for d, s in SCENES],
        patches=[f"results/rde/{d}/{s}/patches.parquet" for d, s in SCENES],
    output:
        train="results/rde/train.parquet",
        val="results/rde/val.parquet",
        test="results/rde/test.parquet",
        framesets="results/rde/framesets.parquet",
    log:
        "logs/rde/dataset.log",
    run:
        from depthgt.jobs.common import logging_to
        from depthgt.jobs.enhance import run_rde_dataset

        with logging_to(log[0]):
            run_rde_dataset(list(input.framesets), list(input.patches), dict(output.items()))


rule train_model:
    input:
        unpack(train_manifests),
    output:
        best="results/models/{model}/best.pt",
        last="results/models/{model}/last.pt",
        log="results/models/{model}/loss_log.csv",
        meta="results/models/{model}/train.json",
    params:
        config=train_config,
    wildcard_constraints:
        model="|".join(MODELS),
    log:
        "logs/train/{model}.log",
    benchmark:
        "benchmarks/train/{model}.tsv"
    threads: 2
    resources:
        gpu=GPUS,
    script:
        "../scripts/train.py"


rule train:
    input:
        expand("results/models/{model}/best.pt", model=MODELS),


rule evaluate_method:
    input:
        unpack(method_inputs),
        framesets="results/dataset/framesets.parquet",
    output:
        table="results/eval/{method}.parquet",
        predictions=directory("results/eval/predictions/{method}"),
    params:
        config={"device": config.get("device", "auto"), "evaluation": {"split": SETTINGS.evaluation.split}},
    wildcard_constraints:
        method="|".join(METHODS),
    log:
        "logs/eval/{method}.log",
    benchmark:
        "benchmarks/eval/{method}.tsv"
    threads: 1
    script:
        "../scripts/evaluate.py"
