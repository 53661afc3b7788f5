"""The scene index: a scene's frames (position, source id, split tag) and its frame sets.

Written once per scene from the scene's metadata (frame count, frame ids, intrinsics,
scene-level problems): no frame is read. The split tags, the split guard and a scene too
short for any frame set are decided here; whether a frame is usable (a readable file, a
finite pose, some valid depth) is not known until it is read, and the frame-set batch
jobs read every member frame anyway: they decide it and record it (``batch.json`` of
each shard, then the scene's ``frames.parquet`` and the dataset summary). A frame set
the index lists as ``planned`` is built, or skipped there with the reason naming its
unusable member frames.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from depthgt.gt.planning import FrameSetSettings, SplitSettings, block_splits, enumerate_framesets, stable_seed
from depthgt.sources.base import Scene
from depthgt.status import Status

log = logging.getLogger(__name__)

#: What the index says about the frames' own validity (index.json ``frame_checks``).
FRAME_CHECKS = (
    "not in the index: each frame is checked when a frame-set batch reads it "
    "(batch.json of the shards, results/scenes/<dataset>/<scene>/frames.parquet)"
)


@dataclass
class SceneIndex:
    """Attributes:
    frames: one row per frame position: position, frame_id, split.
    framesets: one row per candidate target: target, members, split, status
        ("planned" | "skipped"), reason.
    meta: intrinsics (3x3 list), image_size, counts, scene-level problems.
    """

    frames: pd.DataFrame
    framesets: pd.DataFrame
    meta: dict = field(default_factory=dict)

    def to_table(self) -> pd.DataFrame:
        """The index as one table (one row per frame, frame-set columns filled on targets)."""
        fs = self.framesets.rename(
            columns={
                "target": "position",
                "status": "frameset_status",
                "reason": "frameset_reason",
                "split": "frameset_split",
            }
        )
        table = self.frames.merge(fs, on="position", how="left")
        table["is_target"] = table["frameset_status"].notna()
        table["frameset_status"] = table["frameset_status"].fillna("")
        table["frameset_reason"] = table["frameset_reason"].fillna("")
        table["frameset_split"] = table["frameset_split"].fillna("")
        table["members"] = [m if isinstance(m, list) else [] for m in table["members"]]
        return table


def build_index(
    scene: Scene,
    dataset: str,
    source_split: str,
    fs_settings: FrameSetSettings,
    split_settings: SplitSettings,
    seed: int,
) -> SceneIndex:
    """List the frames of ``scene`` and enumerate its frame sets, reading no frame.

    Uses ``len(scene)``, ``scene.frame_id``, the intrinsics and image size, and the
    scene's ``problems`` (what its adapter found when opening it).
    """
    n = len(scene)
    splits = block_splits(n, source_split, split_settings, seed, dataset, scene.name)
    frames = pd.DataFrame(
        {
            "position": np.arange(n),
            "frame_id": [scene.frame_id(i) for i in range(n)],
            "split": splits.astype(str),
        }
    )
    sets = enumerate_framesets(splits, fs_settings)
    framesets = pd.DataFrame(sets, columns=["target", "members", "split", "status", "reason"])
    problems = list(getattr(scene, "problems", []))
    if n < 2 * fs_settings.reach + 1:
        problems.append(f"scene_too_short: {n} frames, a frame set needs {2 * fs_settings.reach + 1}")
    meta = {
        "dataset": dataset,
        "scene": scene.name,
        "n_frames": n,
        "frame_checks": FRAME_CHECKS,
        "image_size": list(scene.image_size),
        "intrinsics": np.asarray(scene.intrinsics, dtype=float).tolist(),
        "has_poses": bool(scene.has_poses),
        "has_clean_depth": bool(scene.has_clean_depth),
        "n_framesets_planned": int((framesets["status"] == Status.PLANNED).sum()) if len(framesets) else 0,
        "n_framesets_skipped": int((framesets["status"] != Status.PLANNED).sum()) if len(framesets) else 0,
        "problems": problems,
    }
    return SceneIndex(frames=frames, framesets=framesets, meta=meta)


def select_pretraining_framesets(index_jsons: list[str], n: int, seed: int) -> list[tuple[str, str, list[int]]]:
    """Planned frame sets of the train split for the registration encoder's pretraining,
    in order of preference: ``n`` drawn without replacement over all scenes (a fixed
    draw for a seed), then every other one in a random order of the same seed.

    The index reads no frame, so a chosen frame set may hold an unusable frame: the
    caller takes the first ``n`` that read fine and skips the others (the spares that
    follow the draw replace them).

    Args:
        index_jsons: the scenes' ``index.json`` (their ``index.parquet`` lies beside).

    Returns:
        (dataset, scene, member positions) of every candidate: the first ``min(n, len)``
        are the draw (in index order), the rest the spares.

    Raises:
        ValueError: no frame set of the train split exists.
    """
    candidates = []
    for path in index_jsons:
        meta = json.loads(Path(path).read_text())
        table = pd.read_parquet(Path(path).with_name("index.parquet"))
        ok = table[
            table["is_target"] & (table["frameset_status"] == Status.PLANNED) & (table["frameset_split"] == "train")
        ]
        candidates += [(meta["dataset"], meta["scene"], [int(m) for m in r.members]) for r in ok.itertuples()]
    if not candidates:
        raise ValueError(
            "pretrain_registration: no frame set of the train split to pretrain on "
            "(set registration.pretrain.framesets: 0 to start from random weights)"
        )
    rng = np.random.default_rng(stable_seed(seed, "pretrain"))
    chosen = sorted(rng.choice(len(candidates), size=min(n, len(candidates)), replace=False).tolist()) if n else []
    taken = set(chosen)
    spares = [i for i in range(len(candidates)) if i not in taken]
    spares = [spares[k] for k in rng.permutation(len(spares))]
    return [candidates[i] for i in chosen + spares]
