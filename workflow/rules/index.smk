# The scene index: every frame checked once (validity and reason), the scene's frame
# sets with their status.
# A plain rule: the frame sets are planned from cheap metadata (common.smk), not from it.
rule scene_index:
    input:
        # a .sens or folder source: the scene's data (a change re-runs the index)
        unpack(scene_data),
    output:
        table="results/scenes/{dataset}/{scene}/index.parquet",
        meta="results/scenes/{dataset}/{scene}/index.json",
    params:
        source=scene_source,
        config=INDEX_CONFIG,
    conda:
        ENV
    log:
        "logs/scenes/{dataset}/{scene}/index.log",
    benchmark:
        "benchmarks/scenes/{dataset}/{scene}/index.tsv"
    script:
        "../scripts/scene_index.py"
