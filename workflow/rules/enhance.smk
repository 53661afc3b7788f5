# Enhancement: the global-reconstruction GT (RDE), training of LapDEN and the learned
# baselines, and the evaluation of every method on the held-out test frame sets.

ENHANCE = config.get("enhance", {})
EVALUATION = config.get("evaluation", {})
MODELS = ["lapden", "ddrnet", "sdd", "rde"]
METHODS = list(EVALUATION.get("methods", ["input", "rgf", "jf", "ddrnet", "sdd", "rde", "lapden"]))
EVALUATED_MODELS = [m for m in MODELS if m in METHODS]  # trained by the default target
KINDS = {name: src["kind"] for name, src in SOURCES.items()}


def train_params(wildcards):
    """TrainSettings mapping of a model (checked by the job; no torch import here):
    enhance.train overridden by enhance.models[model]; RDE uses LapDEN's entry."""
    key = "lapden" if wildcards.model == "rde" else wildcards.model
    return {"seed": int(config.get("seed", 0)), "device": config.get("device", "auto"), "progress": False,
            "model_params": {}, **ENHANCE.get("train", {}), **ENHANCE.get("models", {}).get(key, {"model": key})}


def train_manifests(wildcards):
    if wildcards.model == "rde":
        return {"train": "results/rde/train.parquet", "val": "results/rde/val.parquet"}
    return {"train": "results/dataset/train.parquet", "val": "results/dataset/val.parquet"}


def method_spec(wildcards):
    """Evaluation method of depthgt.enhance.evaluate: a filter baseline or a checkpoint."""
    if wildcards.method in MODELS:
        return {"baseline": "learned", "params": {"checkpoint": f"results/models/{wildcards.method}/best.pt"}}
    return {"baseline": wildcards.method}


def method_inputs(wildcards):
    if wildcards.method in MODELS:
        return [f"results/models/{wildcards.method}/best.pt"]
    return []


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
        rde=ENHANCE.get("rde", {}),
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
        from depthgt.jobs import logging_to
        from depthgt.jobs_enhance import run_rde_dataset

        with logging_to(log[0]):
            run_rde_dataset(list(input.framesets), list(input.patches), str(Path(output.train).parent))


rule train_model:
    input:
        unpack(train_manifests),
    output:
        best="results/models/{model}/best.pt",
        last="results/models/{model}/last.pt",
        log="results/models/{model}/loss_log.csv",
        meta="results/models/{model}/train.json",
    params:
        settings=train_params,
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
        framesets="results/dataset/framesets.parquet",
        models=method_inputs,
    output:
        table="results/eval/{method}.parquet",
        predictions=directory("results/eval/predictions/{method}"),
    params:
        method=method_spec,
        split=EVALUATION.get("split", "test"),
    wildcard_constraints:
        method="|".join(METHODS),
    log:
        "logs/eval/{method}.log",
    benchmark:
        "benchmarks/eval/{method}.tsv"
    threads: 1
    script:
        "../scripts/evaluate.py"
