# The scene index: the scene's frames and frame sets from its metadata (no frame is read;
# the frame-set batches check each frame as they read it), split tags and split guard.
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
