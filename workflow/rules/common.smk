# Config validation, wildcard constraints and input functions. Nothing heavy is
# imported here: the DAG is built without torch, kornia or OpenEXR.
import json
from pathlib import Path

from snakemake.utils import validate

from depthgt.device import check_device_available  # torch-free
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


# Per-job resources. The rules declare them so that every executor sees one request:
# the SLURM executor (profiles/slurm) turns threads, mem_mb, runtime (minutes) and gpu
# into sbatch --cpus-per-task, --mem, -t and --gpus; the local executor limits by them
# only where --resources names them. A job that runs torch on the config's `device` asks
# for one GPU when that is cuda (auto and cpu ask for none).
GPUS = 1 if config["device"] == "cuda" else 0
# Frame sets: peak RSS (benchmarks/*.tsv, max_rss) and CPU time on one core, measured at
# 256x256: given poses 0.6 GB / 5 s (7-Scenes), overfit fast 0.7 GB / 9 s, overfit paper
# 5.9 GB / 830 s (issue 9); declared with headroom. A job that handles several frame sets
# in turn needs the memory of one and the time of all.
_REG = config["registration"]
_OVERFIT_PAPER = _REG.get("method") == "overfit" and _REG.get("preset") != "fast"
FRAMESET_MEM_MB = 8000 if _OVERFIT_PAPER else 2000
FRAMESET_CPU_S = 1800 if _OVERFIT_PAPER else 60


def frameset_runtime_min(n_framesets=1):
    """SLURM time limit (minutes) of a job that builds n frame sets: 10 minutes for
    start-up (Python, torch, Snakemake) plus FRAMESET_CPU_S per frame set."""
    return 10 + -(-n_framesets * FRAMESET_CPU_S // 60)


# device: cuda on a machine without CUDA stops a local run before its first job
# (torch-free check). It runs in `onstart` because the executor is known only there
# (while this file is parsed a SLURM run still looks local); on a cluster the submitting
# node may have no GPU, there each job checks before any work (depthgt.device).
onstart:
    if workflow.local_exec:
        check_device_available(SETTINGS.device)
