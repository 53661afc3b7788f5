# Config validation, wildcard constraints and input functions. Nothing heavy is
# imported here: the DAG is built without torch, kornia or OpenEXR.
import sys

from snakemake.exceptions import WorkflowError

from depthgt import runlock  # standard library only
from depthgt.device import check_device_available  # torch-free
from depthgt.gt.resources import frameset_mem_mb  # torch-free (the settings only)
from depthgt.settings import (  # torch-free
    check_scene_name,
    check_workflow,
    config_with_defaults,
    settings_from_config,
    stage_config,
)
from depthgt.sources.base import check_scene_identity, scene_file  # numpy only

# Every stage's settings, checked before any job runs: the one check of the config
# (unknown keys at any depth, types, choices, bounds, patches.size <= resize, registration
# keys whatever the method; every section's problem at once). Jobs rebuild theirs from the
# config sections their rule passes (STAGES below).
SETTINGS = settings_from_config(config)
check_workflow(SETTINGS)  # what no single section decides (a source at least; the encoder's pretraining)
# the defaults the rules' params and the recorded source entries hold (depthgt.settings.WRITTEN_DEFAULTS)
config.update(config_with_defaults(config))

SOURCES = {src["name"]: src for src in config["sources"]}  # names checked unique by the settings


def _scenes_of(src):
    if src["scenes"] == "all":
        from depthgt.sources.base import list_scenes

        found = list_scenes(src["kind"], src["root"], **src["options"])
        if not found:  # an empty folder, or one of another kind: nothing would be built, silently
            raise WorkflowError(
                f"sources[{src['name']}]: scenes: all finds no {src['kind']} scene under {os.path.abspath(src['root'] or '.')} "
                "(an empty folder, or data of another kind?)"
            )
        return found
    return list(src["scenes"])


_SCENES_OF = {name: _scenes_of(src) for name, src in SOURCES.items()}
SCENES = [(name, scene) for name, scenes in _SCENES_OF.items() for scene in scenes]
check_scene_identity(list(SOURCES.values()), _SCENES_OF)  # a scene twice, or the same data twice / in two splits
for _name, _scene in SCENES:
    check_scene_name(_scene, f"sources[{_name}].scenes")


wildcard_constraints:
    dataset="|".join(map(re.escape, SOURCES)) if SOURCES else "[^/]+",
    scene="[^/]+",
    first=r"\d{6}",
    last=r"\d{6}",


def source_of(wildcards):
    return SOURCES[wildcards.dataset]


def scene_source(wildcards):
    """What decides a scene's outputs of its source's entry (params): not the list of
    scenes, so that adding a scene to `scenes:` runs only that scene."""
    return {k: v for k, v in SOURCES[wildcards.dataset].items() if k != "scenes"}


def scene_data(wildcards):
    """The scene's one file, when its kind may hold a scene in one (ScanNet's .sens; an input:
    Snakemake then re-runs the index when the file changes); folder sources have too
    many files to list."""
    src = SOURCES[wildcards.dataset]
    path = scene_file(src["kind"], src["root"], wildcards.scene, **src["options"])
    return {"scene_file": path} if path else {}


# The plan: every scene's frame-set batches from its frame count (cheap metadata, see
# depthgt.sources.base.frame_count; nothing is read or rendered), so that the DAG is
# built in one pass for any number of frame sets. Which targets turn out skipped
# (invalid frames, split guard, a scene shorter than planned) the jobs record.
BATCH_SIZE = SETTINGS.frameset.batch_size


def _plan_batches():
    from depthgt.sources.base import frame_count

    plan = {}
    for name, scene in SCENES:
        src = SOURCES[name]
        n = frame_count(src["kind"], src["root"], scene, **src["options"])
        plan[name, scene] = SETTINGS.frameset.batches(n)
    return plan


BATCHES = _plan_batches()


def scene_shards(wildcards):
    """The shards of a scene's frame-set batches."""
    return [f"results/framesets/{wildcards.dataset}/{wildcards.scene}/{a:06d}-{b:06d}.zip"
            for a, b in BATCHES[wildcards.dataset, wildcards.scene]]


def all_shards():
    """Every frame-set shard of the build (checksummed in the dataset card)."""
    return [f"results/framesets/{d}/{s}/{a:06d}-{b:06d}.zip" for d, s in SCENES for a, b in BATCHES[d, s]]


def scene_summaries(what="framesets", ext="parquet", scenes=None):
    return [f"results/scenes/{d}/{s}/{what}.{ext}" for d, s in (SCENES if scenes is None else scenes)]


# The scenes whose frame sets may be in the train or val split: those of every source
# but the `split: test` ones (their own job writes the training manifests, rule
# training_manifests: a test source added or changed leaves the trainings as they are).
TRAINING_SCENES = [(d, s) for d, s in SCENES if SETTINGS.source(d).split != "test"]


# The sections of the config that decide a stage's outputs (depthgt.settings.STAGES, the
# one table of them): passed as the rules' `config` params, so that changing one re-runs
# exactly the jobs it affects (Snakemake's params rerun trigger), and the only config the
# jobs get (workflow/scripts pass snakemake.params.config; a job narrows whatever it gets
# to its stage's sections, depthgt.settings.stage_settings).
INDEX_CONFIG = stage_config(config, "index")
FRAMESET_CONFIG = stage_config(config, "frameset")
PRETRAIN_CONFIG = stage_config(config, "pretrain")
GT_CONFIG = stage_config(config, "dataset")  # what the dataset card records as the settings that decided the GT
RDE_CONFIG = stage_config(config, "rde")
EVALUATE_CONFIG = stage_config(config, "evaluate")
REFERENCES_CONFIG = stage_config(config, "references")


# Per-job resources. The rules declare them so that every executor sees one request:
# the SLURM executor (profiles/slurm) turns threads, mem_mb, runtime (minutes) and gpu
# into sbatch --cpus-per-task, --mem, -t and --gpus; the local executor limits by them
# only where --resources names them. A job that runs torch on the config's `device` asks
# for one GPU when that is cuda (auto and cpu ask for none).
GPUS = 1 if config["device"] == "cuda" else 0


def train_threads(wildcards):
    """Threads of one training (the train_model rule), a quarter of --cores, one at least, two
    at most. The four trainings (LapDEN, RDE, DDRNet, SDD) are small networks on 128x128
    patches: on 2 cores two side by side on one thread each took the default build from
    ~80 to 69 min (docs/decisions.md "Threads per training on 2 cores"), and with 8 cores or
    more each gets the two threads it always had. Without a
    core count (a cluster run without --cores): two."""
    try:
        cores = workflow.cores
    except WorkflowError:
        return 2
    return max(1, min(2, cores // 4))

# Frame sets: the memory and CPU time one frame set of the registration method costs
# (its entry's JobCost, depthgt.registration.methods: measured peak RSS and CPU time,
# declared with headroom). A job that handles several frame sets in turn needs the memory
# of one and the time of all. frameset.selection coverage: the batch keeps the span's frames
# and the candidates' clouds; measured 1.7 GB peak RSS (7-Scenes, given and refine,
# bench_pipeline.py --selection coverage): 4000 MB at least.
# On a GPU a batch builds GPU_GROUP (16) frame sets together, and the host holds the
# group's frames and outputs: with device cuda or auto (a GPU wherever the job's node has
# one) the memory is one set's plus the other 15 sets' frames and outputs, a bound from the
# data's sizes (depthgt.gt.resources.group_host_mb: 2 x neighbours + 1 + target_step
# frames at 48 bytes a pixel and the outputs at 64, 488 MB at 256x256 with 3 neighbours
# each side and a target every 2 frames; given on cuda: 2488 MB). Not measured: a GPU batch job's peak RSS, and the CUDA runtime's own
# host memory, which the one-set figure's headroom has to hold. device cpu: one set's.
_JOB = SETTINGS.registration.job_cost
FRAMESET_MEM_MB = frameset_mem_mb(SETTINGS)
FRAMESET_CPU_S = _JOB.cpu_s


def frameset_runtime_min(n_framesets=1):
    """SLURM time limit (minutes) of a job that builds n frame sets: 10 minutes for
    start-up (Python, torch, Snakemake) plus FRAMESET_CPU_S per frame set."""
    return 10 + -(-n_framesets * FRAMESET_CPU_S // 60)


# One run per working directory (depthgt.runlock): the main process of a real run takes
# .snakemake/depthgt-run.lock before its first job and gives it back at the end; a second
# live run stops here with a message naming the first, a lock left by a killed run is
# taken over. Snakemake calls these handlers only in the main process of a run that
# executes jobs: not for --dry-run, --list or --summary, and not in the jobs it spawns
# (--no-hooks), which therefore neither take nor wait for the lock.
# device: cuda on a machine without CUDA stops a local run before its first job
# (torch-free check). It runs in `onstart` because the executor is known only there
# (while this file is parsed a SLURM run still looks local); on a cluster the submitting
# node may have no GPU, there each job checks before any work (depthgt.device).
# The run's config is remembered once its jobs are about to start (depthgt.buildconfig):
# later commands in this working directory run with it without --configfile; a config
# that cannot be written (a full disk) stops the run there, in one line.
# Before the first job the planned frame sets must fit on the results file system
# (depthgt.gt.space: the format's measured bytes per frame set x the frame sets whose
# shard is not built yet; config dataset.check_space: false warns only). At the end the
# run prints its summary (frame sets built and skipped with the top reasons, frames
# unusable, patch pairs kept, where summary.md is) and, when it failed, one line for a
# full disk or a job over its memory (depthgt.jobs.outcome).
def _space_plan():
    from depthgt.gt.space import PlannedShard

    step = SETTINGS.frameset.target_step
    return [
        PlannedShard(f"results/framesets/{d}/{s}/{a:06d}-{b:06d}.zip", (b - a) // step + 1, HAS_TRUTH[d])
        for d, s in SCENES
        for a, b in BATCHES[d, s]
    ]




def _end_of_run(log, failed):
    from depthgt.jobs.outcome import end_of_run_lines

    mem = {}
    for r in workflow.rules:  # the memory each rule declares (a snakemake Resource; a function has no value)
        try:
            value = getattr(r.resources.get("mem_mb"), "value", r.resources.get("mem_mb"))
        except Exception:
            continue
        if isinstance(value, int):
            mem[r.name] = value
    try:
        lines = end_of_run_lines(".", SCENES, _space_plan(), SETTINGS.resize, log, mem, failed=failed)
    except Exception as err:  # the summary must not hide the run's own outcome
        lines = [f"depthgt: (no summary: {type(err).__name__}: {err})"]
    for line in lines:
        print(line, file=sys.stderr)


onstart:
    runlock.acquire()
    try:
        if workflow.local_exec:
            check_device_available(SETTINGS.device)
        from depthgt.gt.space import check_space

        warning = check_space(".", _space_plan(), SETTINGS.resize, refuse=SETTINGS.dataset.check_space)
        if warning:
            print(warning, file=sys.stderr)
        buildconfig.remember(".", CONFIG_LAYERS)  # a full disk: one line naming the file
    except Exception as err:
        # one line, before any job: Snakemake would add its traceback of this handler
        runlock.release()
        print(f"depthgt: error: {err}", file=sys.stderr)
        raise SystemExit(1) from None


onsuccess:
    runlock.release()
    _end_of_run(log, failed=False)


onerror:
    runlock.release()
    _end_of_run(log, failed=True)
