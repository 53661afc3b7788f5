# Config validation, wildcard constraints and input functions. Nothing heavy is
# imported here: the DAG is built without torch, kornia or OpenEXR.
import json
from pathlib import Path

from snakemake.utils import validate

from depthgt.config import check_config

check_config(config, workflow.source_path("../schemas/config.schema.yaml"))
validate(config, schema="../schemas/config.schema.yaml", set_default=True)

from depthgt.sources.base import check_options, check_scene_identity  # numpy only

SOURCES = {}
for _i, _src in enumerate(config["sources"]):
    if _src["name"] in SOURCES:
        raise ValueError(f"config sources: the name {_src['name']!r} is used twice; names must be unique")
    check_options(_src["kind"], _src.get("options"), f"config sources[{_i}] ({_src['name']}).options")
    SOURCES[_src["name"]] = _src


def _scenes_of(src):
    if src["scenes"] == "all":
        from depthgt.sources.base import list_scenes

        return list_scenes(src["kind"], src.get("root"), **src.get("options", {}))
    return list(src["scenes"])


_SCENES_OF = {name: _scenes_of(src) for name, src in SOURCES.items()}
SCENES = [(name, scene) for name, scenes in _SCENES_OF.items() for scene in scenes]
check_scene_identity(list(SOURCES.values()), _SCENES_OF)  # a scene twice, or the same data twice / in two splits
for _name, _scene in SCENES:
    if _scene in (".", "..") or "/" in _scene:
        raise ValueError(f"config sources {_name!r}: scene name {_scene!r} cannot be a path component; "
                         "name the sequence folder (or use scenes: all)")


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


def scene_summaries(what="framesets"):
    return [f"results/scenes/{d}/{s}/{what}.parquet" for d, s in SCENES]


# The sections of the config that decide a stage's outputs; passed as params so that
# changing one re-runs exactly the jobs it affects (Snakemake's params rerun trigger).
INDEX_CONFIG = {k: config.get(k) for k in ("seed", "frameset", "split", "registration", "resize")}
FRAMESET_CONFIG = {k: config.get(k) for k in ("seed", "device", "frameset", "resize", "registration", "render", "patches")}
