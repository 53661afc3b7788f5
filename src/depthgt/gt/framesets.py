"""Local frame sets: a target frame and its neighbours t +- k*stride (k = 1..n).

Paper defaults: 3 neighbours each side at stride 2 (frames t-6, t-4, t-2, t+2, t+4,
t+6). Frame sets are enumerated per scene from a per-frame validity table, and split
tags are assigned without leakage (no frame is used by frame sets of two splits).
"""

from __future__ import annotations

import hashlib

import numpy as np

from depthgt.settings import SPLITS, FrameSetSettings, SplitSettings

__all__ = ["stable_seed", "block_splits", "enumerate_framesets"]


def stable_seed(*parts: object) -> int:
    """A 63-bit seed from any printable parts; stable across runs and machines
    (Python's ``hash`` is salted per process, so it cannot be used)."""
    digest = hashlib.sha256("\x1f".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def block_splits(n_frames: int, source_split: str, settings: SplitSettings, seed: int, dataset: str, scene: str) -> np.ndarray:
    """Split tag of every frame position (array of str, length ``n_frames``)."""
    if source_split in SPLITS:
        return np.full(n_frames, source_split, dtype=object)
    if source_split != "auto":
        raise ValueError(f"split must be one of {SPLITS + ('auto',)}, got {source_split!r}")
    tags = np.full(n_frames, "train", dtype=object)
    if settings.val_fraction <= 0:
        return tags
    period = max(1, round(1.0 / settings.val_fraction))
    phase = stable_seed(seed, dataset, scene, "split") % period
    block = np.arange(n_frames) // settings.block_frames
    tags[(block % period) == phase] = "val"
    return tags


def enumerate_framesets(valid: np.ndarray, reasons: list[str], splits: np.ndarray, settings: FrameSetSettings) -> list[dict]:
    """Frame sets of a scene with their status.

    Args:
        valid: (N,) bool, usable frames.
        reasons: (N,) reason of each invalid frame ("" when valid).
        splits: (N,) split tag of each frame (see :func:`block_splits`).
        settings: offsets and target step.

    Returns:
        One dict per candidate target (every ``target_step`` frames whose members all
        lie inside the scene): ``target``, ``members`` (positions, target first),
        ``split``, ``status`` ("ok" | "skipped") and ``reason`` (why skipped, naming the
        offending member frames).
    """
    n = len(valid)
    offsets = np.asarray(settings.offsets)
    out = []
    for t in settings.targets(n):
        members = (t + offsets).tolist()
        bad = [m for m in members if not valid[m]]
        status, reason = "ok", ""
        if bad:
            status = "skipped"
            reason = "; ".join(f"frame {m}: {reasons[m]}" for m in bad)
        elif len({splits[m] for m in members}) > 1:
            status, reason = "skipped", "split_guard: members span two splits"
        out.append({"target": t, "members": members, "split": splits[t], "status": status, "reason": reason})
    return out
