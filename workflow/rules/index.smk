checkpoint scene_index:
    output:
        table="results/scenes/{dataset}/{scene}/index.parquet",
        meta="results/scenes/{dataset}/{scene}/index.json",
        # resized frames for the frame-set jobs; removed once every frame set is built
        cache=temp(directory("results/scenes/{dataset}/{scene}/frames")),
    params:
        source=source_of,
        config=INDEX_CONFIG,
    conda:
        ENV
    log:
        "logs/scenes/{dataset}/{scene}/index.log",
    benchmark:
        "benchmarks/scenes/{dataset}/{scene}/index.tsv"
    script:
        "../scripts/scene_index.py"
