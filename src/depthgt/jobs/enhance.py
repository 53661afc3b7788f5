"""Entry points of the enhancement jobs: training of a registry model and the RDE
(global-reconstruction) GT of a scene and of the dataset.

Each Snakemake script calls one of these with its rule's paths (every output path
explicitly) and the config sections of its stage (:data:`depthgt.settings.STAGES`);
nothing heavy (torch) is imported at module level.
"""

from __future__ import annotations

import logging
import shutil
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import pandas as pd

from depthgt import registry
from depthgt.jobs.common import open_source_scene
from depthgt.settings import stage_settings

__all__ = ["run_train", "run_rde_scene", "run_rde_dataset", "run_rde_training_manifests"]

log = logging.getLogger("depthgt")


def run_train(
    model: str,
    config: Mapping[str, Any],
    train_manifest: str,
    val_manifest: str | None,
    outputs: Mapping[str, str],
    threads: int = 1,
) -> dict:
    """Train the registry model ``model`` (its :class:`~depthgt.settings.TrainSettings`
    from the config sections of stage ``train``, :data:`depthgt.settings.STAGES`).

    Args:
        outputs: the paths ``best``, ``last``, ``log``, ``meta`` and optionally
            ``resume`` (:class:`depthgt.enhance.train.TrainOutputs`): a killed training
            continues from the last finished epoch kept in ``resume``, which is removed
            once the training has finished.
    """
    import torch  # heavy: imported by the job, not by the workflow

    from depthgt.device import keep_freed_memory
    from depthgt.enhance.train import TrainOutputs, train

    keep_freed_memory()  # a process of its own: no page faults for each step's activations
    torch.set_num_threads(max(1, int(threads)))
    st = stage_settings(config, "train", model=registry.METHODS[model].settings_key).train(model)
    out = TrainOutputs(**{k: Path(outputs[k]) for k in TrainOutputs._fields if outputs.get(k) is not None})
    result = train(train_manifest, val_manifest, out, st)
    log.info(
        "trained %s (%s) -> %s: best epoch %d (val %.5f), %d epochs run",
        model,
        st.model,
        out.best,
        result["best_epoch"],
        result["best_val"],
        result["epochs_run"],
    )
    if out.resume is not None:
        shutil.rmtree(out.resume, ignore_errors=True)
    return result


def run_rde_scene(
    source: dict[str, Any],
    scene: str,
    scene_framesets: str,
    config: Mapping[str, Any],
    out_shard: str,
    out_framesets: str,
    out_patches: str,
) -> None:
    """RDE GT of every frame set of one scene (:func:`depthgt.gt.rde.rde_scene`) into the
    shard ``out_shard``, and its two tables. Frames come from the source at the working
    resolution (:class:`depthgt.gt.cache.ResizedScene`), the frames the frame sets saw.
    """
    # heavy (torch): only this job needs them
    from depthgt.gt.cache import ResizedScene
    from depthgt.gt.rde import rde_scene

    all_settings = stage_settings(config, "rde")
    sc = ResizedScene(open_source_scene(source, scene, need_poses=True), all_settings.size_hw)
    fs, patches = rde_scene(sc, pd.read_parquet(scene_framesets), all_settings.enhance.rde, out_shard)
    for table, path in ((fs, out_framesets), (patches, out_patches)):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        table.to_parquet(path, index=False)


def run_rde_dataset(scene_framesets: list[str], scene_patches: list[str], outputs: Mapping[str, str]) -> None:
    """Concatenate the scenes' RDE tables.

    Args:
        outputs: the path ``framesets`` and those of the splits' manifests to write here
            (of ``train``, ``val``, ``test``: kept patches per split; the workflow writes
            train and val in a job of their own, :func:`run_rde_training_manifests`).
    """
    from depthgt.gt.rde import rde_dataset  # heavy: the module imports torch

    fs, splits = rde_dataset([pd.read_parquet(p) for p in scene_framesets], [pd.read_parquet(p) for p in scene_patches])
    for path in outputs.values():
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    fs.to_parquet(outputs["framesets"], index=False)
    for split, table in splits.items():
        if split in outputs:
            table.to_parquet(outputs[split], index=False)
    log.info("RDE GT: %d frame sets, patches %s", len(fs), {s: len(t) for s, t in splits.items() if s in outputs})


def run_rde_training_manifests(scene_patches: list[str], outputs: Mapping[str, str]) -> None:
    """The RDE GT's ``train`` and ``val`` manifests (``outputs``: split -> path) from the
    patch tables of the scenes that can hold such frame sets (the sources not
    ``split: test``), as :func:`run_rde_dataset` writes them."""
    from depthgt.gt.rde import rde_dataset  # heavy: the module imports torch

    _, splits = rde_dataset([], [pd.read_parquet(p) for p in scene_patches])
    for split, path in outputs.items():
        Path(path).parent.mkdir(parents=True, exist_ok=True)
        splits[split].to_parquet(path, index=False)
    log.info("RDE training manifests: %s patch pairs", {s: len(splits[s]) for s in outputs})
