# Input functions and names the rules share (Snakemake's lint: functions apart from
# rules). Nothing heavy is imported here.
from depthgt import registry
from depthgt.sources.base import source_kind  # numpy only

# every rule's software environment (docs/development.md: --software-deployment-method conda)
ENV = "../envs/depthgt.yaml"


def train_scene_indices(wildcards=None):
    return [f"results/scenes/{d}/{s}/index.json" for d, s in SCENES]


def registration_encoder(wildcards):
    """The pretrained encoder when the registration method starts from it (overfit)."""
    if SETTINGS.registration.method_entry.pretrained_encoder:
        return "results/models/registration/encoder.pt"
    return []


MODELS = list(registry.learned())  # every trainable model of the registry (target `train`)
METHODS = list(SETTINGS.evaluation.methods)
EVALUATED_MODELS = SETTINGS.evaluation.models  # trained by the default target
KINDS = {name: src["kind"] for name, src in SOURCES.items()}
# sources whose kind has noise-free depth (synthetic data: evaluated against the truth)
HAS_TRUTH = {name: source_kind(kind).has_truth for name, kind in KINDS.items()}
MANIFESTS = {"depthgt": "results/dataset", "rde": "results/rde"}  # the GT a learned method trains on


# Real scenes whose frame sets may be evaluated (source split = evaluation.split, or
# auto): Table 2 scores them also against references no method was trained to imitate,
# built per scene by rule scene_references (depthgt.gt.references).
REFERENCE_SCENES = [(d, s) for d, s in SCENES if not HAS_TRUTH[d]
                    and SOURCES[d]["split"] in ("auto", SETTINGS.evaluation.split)]
REFERENCE_TABLES = [f"results/references/{d}/{s}/references.parquet" for d, s in REFERENCE_SCENES]

# Scenes with an RDE GT (a TSDF of the stream, one per scene by rde_scene): those RDE trains and
# validates on, the real scenes Table 2's TSDF reference needs, and synthetic test scenes
# only when evaluation.rde_synthetic_test asks (Table 1 rows; no method needs them).
RDE_SCENES = [(d, s) for d, s in SCENES if SOURCES[d]["split"] != SETTINGS.evaluation.split
              or not HAS_TRUTH[d] or SETTINGS.evaluation.rde_synthetic_test]


def train_config(wildcards):
    """The config sections that decide a model's training (its params: a change re-runs
    exactly this model; depthgt.settings.STAGES["train"]), the only config its job gets."""
    return stage_config(config, "train", model=registry.METHODS[wildcards.model].settings_key)


def model_priority(model):
    """A training's estimated length (depthgt.registry.training_priority), its job's
    priority: the longest trainings start first and every training before the
    evaluations; on 2 cores the default build's four trainings end near the longest one's
    lane (bench/README.md "The default build: time and memory")."""
    spec = registry.METHODS[model]
    return registry.training_priority(spec.builder, SETTINGS.enhance.models[model].epochs)


def train_priority(wildcards):
    """Rule train_model's priority (model_priority)."""
    return model_priority(wildcards.model)


def upstream_priority(trains_on):
    """The priority of the jobs that only the trainings on one GT (MANIFESTS) wait for:
    its training manifests, and for RDE's GT its scenes (rule rde_scene). Snakemake does not
    hand a job's priority on to the jobs it waits for: without this RDE's last scene and
    manifests waited behind the DDRNet training. One above the longest training on that GT,
    so that these short jobs go first when a training of equal priority is ready too."""
    trainings = [model_priority(m) for m, spec in registry.learned().items() if spec.trains_on == trains_on]
    return max(trainings) + 1 if trainings else 0


def train_manifests(wildcards):
    d = MANIFESTS[registry.METHODS[wildcards.model].trains_on]
    return {"train": f"{d}/train.parquet", "val": f"{d}/val.parquet"}


def method_inputs(wildcards):
    """The trained model of a learned method (none for input and filters)."""
    if registry.METHODS[wildcards.method].kind == "learned":
        return {"checkpoint": f"results/models/{wildcards.method}/best.pt"}
    return {}
