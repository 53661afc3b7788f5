rule frameset:
    input:
        index="results/scenes/{dataset}/{scene}/index.parquet",
        cache="results/scenes/{dataset}/{scene}/frames",
        encoder=registration_encoder,
    output:
        gt="results/framesets/{dataset}/{scene}/{target}/gt.exr",
        input="results/framesets/{dataset}/{scene}/{target}/input.exr",
        rgb="results/framesets/{dataset}/{scene}/{target}/rgb.png",
        poses="results/framesets/{dataset}/{scene}/{target}/poses.json",
        patches="results/framesets/{dataset}/{scene}/{target}/patches.npz",
        meta="results/framesets/{dataset}/{scene}/{target}/frameset.json",
    params:
        source=source_of,
        config=FRAMESET_CONFIG,
    conda:
        ENV
    log:
        "logs/framesets/{dataset}/{scene}/{target}.log",
    benchmark:
        "benchmarks/framesets/{dataset}/{scene}/{target}.tsv"
    threads: 1
    resources:
        mem_mb=FRAMESET_MEM_MB,
        runtime=frameset_runtime_min(1),
        gpu=GPUS,
    script:
        "../scripts/frameset.py"


# Runs in the main Snakemake process on a cluster: its input is read from the scene's
# checkpoint, which a job started by a remote executor cannot resolve (Snakemake 9.27
# hands such a job the unresolved input "<TBD>").
localrules:
    scene_summary,


rule scene_summary:
    input:
        index="results/scenes/{dataset}/{scene}/index.parquet",
        framesets=frameset_jsons,
    output:
        framesets="results/scenes/{dataset}/{scene}/framesets.parquet",
        patches="results/scenes/{dataset}/{scene}/patches.parquet",
        quality="results/scenes/{dataset}/{scene}/quality.parquet",
    conda:
        ENV
    log:
        "logs/scenes/{dataset}/{scene}/summary.log",
    script:
        "../scripts/scene_summary.py"


rule framesets:
    input:
        scene_summaries("framesets"),
