rule dataset:
    input:
        scenes=scene_summaries("framesets"),
        patches=scene_summaries("patches"),
        quality=scene_summaries("quality"),
        frames=scene_summaries("frames"),
        indices=scene_summaries("index", "json"),
        shards=all_shards(),
    output:
        train="results/dataset/train.parquet",
        val="results/dataset/val.parquet",
        test="results/dataset/test.parquet",
        framesets="results/dataset/framesets.parquet",
        summary="results/dataset/summary.json",
        summary_md="results/dataset/summary.md",
        quality="results/dataset/gt_quality.csv",
        card="results/dataset/card.json",
        card_md="results/dataset/card.md",
    params:
        config=GT_CONFIG,
    conda:
        ENV
    log:
        "logs/dataset.log",
    benchmark:
        "benchmarks/dataset.tsv"
    script:
        "../scripts/dataset.py"
