# Frame sets in batches: one job builds a contiguous slice of one scene's targets
# (frameset.batch_size) and writes one shard (depthgt.gt.store); the frame set stays
# the unit of the manifests (column `frameset`: <shard>/<target>).
rule frameset_batch:
    input:
        index="results/scenes/{dataset}/{scene}/index.parquet",
        encoder=registration_encoder,
    output:
        shard="results/framesets/{dataset}/{scene}/{first}-{last}.zip",
    params:
        source=scene_source,
        config=FRAMESET_CONFIG,
    conda:
        ENV
    log:
        "logs/framesets/{dataset}/{scene}/{first}-{last}.log",
    benchmark:
        "benchmarks/framesets/{dataset}/{scene}/{first}-{last}.tsv"
    threads: 1
    resources:
        mem_mb=FRAMESET_MEM_MB,
        runtime=frameset_runtime_min(BATCH_SIZE),
        gpu=GPUS,
    script:
        "../scripts/frameset_batch.py"


rule scene_summary:
    input:
        index="results/scenes/{dataset}/{scene}/index.parquet",
        shards=scene_shards,
    output:
        framesets="results/scenes/{dataset}/{scene}/framesets.parquet",
        patches="results/scenes/{dataset}/{scene}/patches.parquet",
        quality="results/scenes/{dataset}/{scene}/quality.parquet",
        frames="results/scenes/{dataset}/{scene}/frames.parquet",
    conda:
        ENV
    log:
        "logs/scenes/{dataset}/{scene}/summary.log",
    script:
        "../scripts/scene_summary.py"


rule framesets:
    input:
        scene_summaries("framesets"),
