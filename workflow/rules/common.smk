# Config validation, wildcard constraints and input functions. Nothing heavy is
# imported here: the DAG is built without torch, kornia or OpenEXR.
import json
from pathlib import Path

from snakemake.utils import validate

from depthgt.settings import check_config, check_scene_name, settings_from_config
from depthgt.sources.base import check_scene_identity  # numpy only

check_config(config, workflow.source_path("../schemas/config.schema.yaml"))
validate(config, schema="../schemas/config.schema.yaml", set_default=True)
# Every stage's settings, checked before any job runs (unknown keys, values, bounds,
# patches.size <= resize, registration keys whatever the method); jobs rebuild theirs
# from the config sections their rule passes (depthgt.settings.settings_from_config).
SETTINGS = settings_from_config(config)

SOURCES = {src["name"]: src for src in config["sources"]}  # names checked unique by the settings


def _scenes_of(src):
    if src["scenes"] == "all":
        from depthgt.sources.base import list_scenes

        return list_scenes(src["kind"], src.get("root"), **src.get("options", {}))
    return list(src["scenes"])


_SCENES_OF = {name: _scenes_of(src) for name, src in SOURCES.items()}
SCENES = [(name, scene) for name, scenes in _SCENES_OF.items() for scene in scenes]
check_scene_identity(list(SOURCES.values()), _SCENES_OF)  # a scene twice, or the same data twice / in two splits
for _name, _scene in SCENES:
    check_scene_name(_scene, f"sources[{_name}].scenes")


wildcard_constraints:
    dataset="|".join(map(re.escape, SOURCES)) if SOURCES else "[^/]+",
    scene="[^/]+",
    target=r"\d{6}",


def source_of(wildcards):
    return SOURCES[wildcards.dataset]


def frameset_dirs(wildcards):
    """Output folders of the runnable frame sets of a scene (after its index exists)."""
    meta = checkpoints.scene_index.get(dataset=wildcards.dataset, scene=wildcards.scene).output.meta
    targets = json.loads(Path(meta).read_text())["framesets_ok"]
    return [f"results/framesets/{wildcards.dataset}/{wildcards.scene}/{t:06d}" for t in targets]


def frameset_jsons(wildcards):
    return [f"{d}/frameset.json" for d in frameset_dirs(wildcards)]


def scene_summaries(what="framesets", ext="parquet"):
    return [f"results/scenes/{d}/{s}/{what}.{ext}" for d, s in SCENES]


# The sections of the config that decide a stage's outputs; passed as params so that
# changing one re-runs exactly the jobs it affects (Snakemake's params rerun trigger).
# Jobs build their settings from the whole (validated) config, snakemake.config, with
# depthgt.settings.settings_from_config, and use only these sections of it.
INDEX_CONFIG = {k: config.get(k) for k in ("seed", "frameset", "split", "registration", "resize")}
FRAMESET_CONFIG = {k: config.get(k) for k in ("seed", "device", "frameset", "resize", "registration", "render", "patches")}
