"""Local frame sets: a target frame and its neighbours t +- k*stride (k = 1..n).

Paper defaults: 3 neighbours each side at stride 2 (frames t-6, t-4, t-2, t+2, t+4,
t+6). Frame sets are enumerated per scene from its frame count and split tags, which
are assigned without leakage (no frame is used by frame sets of two splits). Whether
the member frames are usable is known only once they are read: the frame-set batch
jobs decide it (:func:`member_problems` words the skip reason).
"""

from __future__ import annotations

import hashlib
from collections.abc import Mapping, Sequence

import numpy as np

from depthgt.gt.settings import SPLITS, FrameSetSettings, SplitSettings
from depthgt.status import Status

__all__ = ["stable_seed", "block_splits", "enumerate_framesets", "coverage_candidates", "member_problems"]


def stable_seed(*parts: object) -> int:
    """A 63-bit seed from any printable parts; stable across runs and machines
    (Python's ``hash`` is salted per process, so it cannot be used)."""
    digest = hashlib.sha256("\x1f".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def block_splits(
    n_frames: int, source_split: str, settings: SplitSettings, seed: int, dataset: str, scene: str
) -> np.ndarray:
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


def enumerate_framesets(splits: np.ndarray, settings: FrameSetSettings) -> list[dict]:
    """Frame sets of a scene with their status, before any frame is read.

    Args:
        splits: (N,) split tag of each frame position (see :func:`block_splits`).
        settings: offsets and target step.

    Returns:
        One dict per candidate target (every ``target_step`` frames whose members all
        lie inside the scene): ``target``, ``members`` (positions, target first),
        ``split``, ``status`` and ``reason``. Status ``"planned"``: to be built once its
        member frames read fine (the batch job checks them); ``"skipped"`` with reason
        ``split_guard``: its members span two splits.

    >>> sets = enumerate_framesets(np.array(["train"] * 13 + ["val"] * 2, dtype=object), FrameSetSettings(target_step=1))
    >>> [(s["target"], str(s["status"])) for s in sets]
    [(6, 'planned'), (7, 'skipped'), (8, 'skipped')]
    """
    n = len(splits)
    offsets = np.asarray(settings.offsets)
    out = []
    for t in settings.targets(n):
        members = (t + offsets).tolist()
        status, reason = Status.PLANNED, ""
        if len({splits[m] for m in members}) > 1:
            status, reason = Status.SKIPPED, "split_guard: members span two splits"
        out.append({"target": t, "members": members, "split": splits[t], "status": status, "reason": reason})
    return out


def coverage_candidates(
    splits: np.ndarray, target: int, members: Sequence[int], settings: FrameSetSettings
) -> list[int]:
    """Frames that ``frameset.selection: coverage`` may add to a frame set (none with
    ``window``): within +-``coverage_span`` of the target, inside the scene, not a
    member, and of the target's split (the split guard holds for added views too: a
    frame of another split is never a candidate, so no frame set spans two splits).

    Args:
        splits: (N,) split tag of each frame position (:func:`block_splits`).
        target, members: the planned frame set (members target first).

    >>> tags = np.array(["train"] * 10 + ["val"] * 5, dtype=object)
    >>> coverage_candidates(tags, 7, [7, 5, 9], FrameSetSettings(neighbours=1, selection="coverage", coverage_span=4))
    [3, 4, 6, 8]
    """
    if settings.selection != "coverage":
        return []
    n = len(splits)
    pos = np.arange(max(0, target - settings.coverage_span), min(n, target + settings.coverage_span + 1))
    pos = pos[~np.isin(pos, np.asarray(members)) & (splits[pos] == splits[target])]
    return pos.tolist()


def member_problems(members: Sequence[int], problems: Mapping[int, str]) -> str:
    """Why a frame set is skipped for its unusable member frames ("" when none is).

    Args:
        members: the frame set's member positions, target first.
        problems: position -> what is wrong with that frame (``"<reason> (<message>)"``,
            the message naming the file), for the frames found unusable.

    Returns:
        ``"frame <position>: <problem>"`` of each unusable member in member order,
        joined by ``"; "``.

    >>> member_problems([7, 1, 3, 5, 9, 11, 13], {9: "nonfinite_pose (frame 9: pose is not finite)", 2: "unreadable (x)"})
    'frame 9: nonfinite_pose (frame 9: pose is not finite)'
    """
    return "; ".join(f"frame {m}: {problems[m]}" for m in members if m in problems)
