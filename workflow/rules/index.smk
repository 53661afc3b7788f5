checkpoint scene_index:
    output:
        table="results/scenes/{dataset}/{scene}/index.parquet",
        meta="results/scenes/{dataset}/{scene}/index.json",
    params:
        source=source_of,
        config=INDEX_CONFIG,
    log:
        "logs/scenes/{dataset}/{scene}/index.log",
    benchmark:
        "benchmarks/scenes/{dataset}/{scene}/index.tsv"
    script:
        "../scripts/scene_index.py"
