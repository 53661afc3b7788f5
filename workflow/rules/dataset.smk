# The training manifests have a job of their own, whose inputs are the scenes of the
# sources that can hold train or val frame sets (TRAINING_SCENES: split auto, train, val):
# adding or changing a `split: test` source leaves them, and the trainings that read
# them, untouched (the dataset job below re-runs, with the test manifest, the tables
# and the card).
rule training_manifests:
    input:
        patches=scene_summaries("patches", scenes=TRAINING_SCENES),
    output:
        train="results/dataset/train.parquet",
        val="results/dataset/val.parquet",
    priority: upstream_priority("depthgt")
    conda:
        ENV
    log:
        "logs/dataset-training.log",
    script:
        "../scripts/training_manifests.py"


rule dataset:
    input:
        manifests=rules.training_manifests.output,
        scenes=scene_summaries("framesets"),
        patches=scene_summaries("patches"),
        quality=scene_summaries("quality"),
        frames=scene_summaries("frames"),
        indices=scene_summaries("index", "json"),
        shards=all_shards(),
    output:
        test="results/dataset/test.parquet",
        framesets="results/dataset/framesets.parquet",
        summary="results/dataset/summary.json",
        summary_md="results/dataset/summary.md",
        quality="results/dataset/gt_quality.csv",
        card="results/dataset/card.json",
        card_md="results/dataset/card.md",
    params:
        config=GT_CONFIG,
        allow_empty=SETTINGS.dataset.allow_empty,
    conda:
        ENV
    log:
        "logs/dataset.log",
    benchmark:
        "benchmarks/dataset.tsv"
    script:
        "../scripts/dataset.py"
