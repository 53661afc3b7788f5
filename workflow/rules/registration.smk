# Stream-only pretraining of the registration encoder (issue 3): used as the starting
# point of every frame set's overfit training when registration.method is overfit.


def train_scene_indices(wildcards=None):
    return [f"results/scenes/{d}/{s}/index.json" for d, s in SCENES]


rule pretrain_registration:
    input:
        indices=train_scene_indices,
    output:
        "results/models/registration/encoder.pt",
    params:
        sources=SOURCES,
        config=FRAMESET_CONFIG,
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


def registration_encoder(wildcards):
    """The pretrained encoder when frame sets are registered by the overfit method."""
    if SETTINGS.registration.method == "overfit":
        return "results/models/registration/encoder.pt"
    return []
