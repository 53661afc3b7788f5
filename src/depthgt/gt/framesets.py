"""Local frame sets: a target frame and its neighbours t +- k*stride (k = 1..n).

Paper defaults: 3 neighbours each side at stride 2 (frames t-6, t-4, t-2, t+2, t+4,
t+6). Frame sets are enumerated per scene from a per-frame validity table, and split
tags are assigned without leakage (no frame is used by frame sets of two splits).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass

import numpy as np

SPLITS = ("train", "val", "test")


@dataclass(frozen=True)
class FrameSetSettings:
    """How frame sets are formed.

    Attributes:
        neighbours: neighbours on each side of the target (paper: 3).
        stride: frames between consecutive neighbours (paper: 2).
        target_step: a target every ``target_step`` frames.
    """

    neighbours: int = 3
    stride: int = 2
    target_step: int = 1

    def __post_init__(self):
        for key in ("neighbours", "stride", "target_step"):
            if getattr(self, key) < 1:
                raise ValueError(f"frameset.{key} must be >= 1, got {getattr(self, key)}")

    @property
    def offsets(self) -> list[int]:
        """Offsets of the members, target first: [0, -n*s, ..., -s, s, ..., n*s]."""
        k = np.arange(1, self.neighbours + 1) * self.stride
        return [0, *(-k[::-1]).tolist(), *k.tolist()]

    @property
    def reach(self) -> int:
        return self.neighbours * self.stride


@dataclass(frozen=True)
class SplitSettings:
    """Split assignment.

    ``mode = "source"``: every frame set takes the split fixed for its source
    (``train``, ``val`` or ``test``). Sources marked ``auto`` are cut into blocks of
    ``block_frames`` consecutive frames; every ``round(1 / val_fraction)``-th block (with
    a phase drawn from the seed and the scene name) is validation, the rest training.
    A frame set whose members fall into blocks of different splits is skipped with the
    reason ``split_guard``, so no frame is shared between splits.
    """

    val_fraction: float = 0.1
    block_frames: int = 50

    def __post_init__(self):
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"split.val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.block_frames < 1:
            raise ValueError(f"split.block_frames must be >= 1, got {self.block_frames}")


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
    for t in range(settings.reach, n - settings.reach, settings.target_step):
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
