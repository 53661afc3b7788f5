# Enhancement: the global-reconstruction GT (RDE), training of LapDEN and the learned
# baselines, and the evaluation of every method on the held-out test frame sets.

rule rde_scene:
    input:
        framesets="results/scenes/{dataset}/{scene}/framesets.parquet",
    output:
        frames="results/rde/{dataset}/{scene}/frames.zip",
        framesets="results/rde/{dataset}/{scene}/framesets.parquet",
        patches="results/rde/{dataset}/{scene}/patches.parquet",
    priority: upstream_priority("rde")
    params:
        source=source_of,
        config=RDE_CONFIG,
    conda:
        ENV
    log:
        "logs/rde/{dataset}/{scene}.log",
    benchmark:
        "benchmarks/rde/{dataset}/{scene}.tsv"
    threads: 1
    script:
        "../scripts/rde.py"


# RDE's training manifests from the scenes that can hold train or val frame sets only
# (as rule training_manifests): a test source added leaves the RDE training as it is.
rule rde_training_manifests:
    input:
        patches=[f"results/rde/{d}/{s}/patches.parquet" for d, s in RDE_SCENES if (d, s) in TRAINING_SCENES],
    output:
        train="results/rde/train.parquet",
        val="results/rde/val.parquet",
    priority: upstream_priority("rde")
    conda:
        ENV
    log:
        "logs/rde/training-manifests.log",
    script:
        "../scripts/rde_training_manifests.py"


rule rde_dataset:
    input:
        framesets=[f"results/rde/{d}/{s}/framesets.parquet" for d, s in RDE_SCENES],
        patches=[f"results/rde/{d}/{s}/patches.parquet" for d, s in RDE_SCENES],
    output:
        test="results/rde/test.parquet",
        framesets="results/rde/framesets.parquet",
    conda:
        ENV
    log:
        "logs/rde/dataset.log",
    script:
        "../scripts/rde_dataset.py"


rule scene_references:
    input:
        framesets="results/scenes/{dataset}/{scene}/framesets.parquet",
        rde="results/rde/{dataset}/{scene}/framesets.parquet",
    output:
        images="results/references/{dataset}/{scene}/references.npz",
        table="results/references/{dataset}/{scene}/references.parquet",
    params:
        source=source_of,
        config=REFERENCES_CONFIG,
    conda:
        ENV
    log:
        "logs/references/{dataset}/{scene}.log",
    benchmark:
        "benchmarks/references/{dataset}/{scene}.tsv"
    threads: 1
    script:
        "../scripts/references.py"


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
    conda:
        ENV
    log:
        "logs/train/{model}.log",
    benchmark:
        "benchmarks/train/{model}.tsv"
    threads: train_threads
    priority: train_priority
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
        references=REFERENCE_TABLES,
    output:
        table="results/eval/{method}.parquet",
        predictions=directory("results/eval/predictions/{method}"),
    params:
        config=EVALUATE_CONFIG,
    wildcard_constraints:
        method="|".join(METHODS),
    conda:
        ENV
    log:
        "logs/eval/{method}.log",
    benchmark:
        "benchmarks/eval/{method}.tsv"
    threads: 1
    resources:
        gpu=GPUS,  # learned methods run inference on the config's device
    script:
        "../scripts/evaluate.py"
