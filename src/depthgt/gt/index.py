"""The scene index: every frame's validity (with the reason) and the scene's frame sets.

Written once per scene; the frame-set batch jobs read it to know which of their targets
are runnable (the workflow plans the batches from the frame count alone). Reading every
frame once is the price of never discovering a broken frame in the middle of a frame-set
job.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from depthgt.errors import FrameError
from depthgt.gt.framesets import FrameSetSettings, SplitSettings, block_splits, enumerate_framesets
from depthgt.sources.base import Scene, check_frame

log = logging.getLogger(__name__)


@dataclass
class SceneIndex:
    """Attributes:
        frames: one row per frame position: position, frame_id, valid, reason, split.
        framesets: one row per candidate target: target, members, split, status, reason.
        meta: intrinsics (3x3 list), image_size, counts, scene-level problems.
    """

    frames: pd.DataFrame
    framesets: pd.DataFrame
    meta: dict = field(default_factory=dict)

    def to_table(self) -> pd.DataFrame:
        """The index as one table (one row per frame, frame-set columns filled on targets)."""
        fs = self.framesets.rename(columns={"target": "position", "status": "frameset_status", "reason": "frameset_reason",
                                            "split": "frameset_split"})
        table = self.frames.merge(fs, on="position", how="left")
        table["is_target"] = table["frameset_status"].notna()
        table["frameset_status"] = table["frameset_status"].fillna("")
        table["frameset_reason"] = table["frameset_reason"].fillna("")
        table["frameset_split"] = table["frameset_split"].fillna("")
        table["members"] = [m if isinstance(m, list) else [] for m in table["members"]]
        return table


def build_index(scene: Scene, dataset: str, source_split: str, need_poses: bool, fs_settings: FrameSetSettings,
                split_settings: SplitSettings, seed: int, progress: bool = False) -> SceneIndex:
    """Check every frame of ``scene`` and enumerate its frame sets.

    Args:
        need_poses: frames without a finite pose are invalid (``registration.method: given``).
    """
    n = len(scene)
    valid = np.zeros(n, dtype=bool)
    reasons = [""] * n
    messages = [""] * n
    positions = range(n)
    if progress:
        from tqdm import tqdm

        positions = tqdm(positions, desc=f"index {dataset}/{scene.name}", unit="frame")
    for i in positions:
        try:
            frame = scene.read(i)
            check_frame(frame, scene.image_size, f"{dataset}/{scene.name} frame {scene.frame_id(i)}", need_pose=need_poses)
            valid[i] = True
        except FrameError as err:
            reasons[i] = err.reason
            messages[i] = str(err)
            log.warning("skipping frame: %s", err)
    splits = block_splits(n, source_split, split_settings, seed, dataset, scene.name)
    frames = pd.DataFrame({
        "position": np.arange(n),
        "frame_id": [scene.frame_id(i) for i in range(n)],
        "valid": valid,
        "reason": reasons,
        "message": messages,
        "split": splits.astype(str),
    })
    sets = enumerate_framesets(valid, [f"{r} ({m})" if r else "" for r, m in zip(reasons, messages)], splits, fs_settings)
    framesets = pd.DataFrame(sets, columns=["target", "members", "split", "status", "reason"])
    problems = list(getattr(scene, "problems", []))
    if n < 2 * fs_settings.reach + 1:
        problems.append(f"scene_too_short: {n} frames, a frame set needs {2 * fs_settings.reach + 1}")
    meta = {
        "dataset": dataset,
        "scene": scene.name,
        "n_frames": n,
        "n_valid_frames": int(valid.sum()),
        "image_size": list(scene.image_size),
        "intrinsics": np.asarray(scene.intrinsics, dtype=float).tolist(),
        "has_poses": bool(scene.has_poses),
        "has_clean_depth": bool(scene.has_clean_depth),
        "n_framesets": int((framesets["status"] == "ok").sum()) if len(framesets) else 0,
        "n_framesets_skipped": int((framesets["status"] != "ok").sum()) if len(framesets) else 0,
        "problems": problems,
    }
    return SceneIndex(frames=frames, framesets=framesets, meta=meta)


def select_pretraining_framesets(index_jsons: list[str], n: int, seed: int) -> list[tuple[str, str, list[int]]]:
    """``n`` runnable frame sets of the train split, drawn without replacement over all
    scenes (a fixed draw for a seed), for the registration encoder's pretraining.

    Args:
        index_jsons: the scenes' ``index.json`` (their ``index.parquet`` lies beside).

    Returns:
        (dataset, scene, member positions) of each chosen set, in index order.

    Raises:
        ValueError: no frame set of the train split exists.
    """
    import json
    from pathlib import Path

    from depthgt.gt.framesets import stable_seed

    candidates = []
    for path in index_jsons:
        meta = json.loads(Path(path).read_text())
        table = pd.read_parquet(Path(path).with_name("index.parquet"))
        ok = table[table["is_target"] & (table["frameset_status"] == "ok") & (table["frameset_split"] == "train")]
        candidates += [(meta["dataset"], meta["scene"], [int(m) for m in r.members]) for r in ok.itertuples()]
    if not candidates:
        raise ValueError("pretrain_registration: no frame set of the train split to pretrain on "
                         "(set registration.pretrain.framesets: 0 to start from random weights)")
    rng = np.random.default_rng(stable_seed(seed, "pretrain"))
    chosen = sorted(rng.choice(len(candidates), size=min(n, len(candidates)), replace=False).tolist()) if n else []
    return [candidates[i] for i in chosen]
