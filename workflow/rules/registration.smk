# Stream-only pretraining of the registration encoder (issue 3): used as the starting
# point of every frame set's overfit training when registration.method is overfit.


rule pretrain_registration:
    input:
        indices=train_scene_indices,
    output:
        "results/models/registration/encoder.pt",
    params:
        sources=SOURCES,
        config=PRETRAIN_CONFIG,
    conda:
        ENV
    log:
        "logs/models/pretrain_registration.log",
    benchmark:
        "benchmarks/models/pretrain_registration.tsv"
    threads: 2
    resources:
        mem_mb=4000,  # measured 2.2 GB peak RSS (preset paper and fast, 256x256)
        gpu=GPUS,
    script:
        "../scripts/pretrain_registration.py"
