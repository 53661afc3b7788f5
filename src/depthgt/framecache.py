"""What a batch job computes once per frame and keeps while its frame sets use it.

A batch of consecutive frame sets shares each frame with up to six others (the paper's
window), and what depends on a frame alone -- the refinement's image pyramid, the
renderer's back-projected points, normals and noise residuals -- is the same in every
set that holds it. :class:`FrameCache` keeps such results by frame position and kind,
the most recently used frames first, so that each is computed once per batch. A leaf
module (the standard library only): the registration and the GT renderer both use it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

__all__ = ["FrameCache"]

T = TypeVar("T")


class FrameCache:
    """Per-frame results keyed by (kind, frame position), the frames used last kept.

    Args:
        keep: how many frames to keep results for (a batch job keeps the frames of its
            frame sets' reach: twice the reach plus the frame coming in).

    Safe to share between threads (a GPU's batch job finishes its sets in a few): a
    call holds the cache until it returns, its computation included.

    >>> cache = FrameCache(keep=2)
    >>> calls = []
    >>> square = lambda todo: calls.append(todo) or [p * p for p in todo]
    >>> cache.get("square", [3, 4], square), cache.get("square", [4, 5], square), calls
    ([9, 16], [16, 25], [[3, 4], [5]])
    """

    def __init__(self, keep: int = 64) -> None:
        self._keep = max(1, int(keep))
        self._frames: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._lock = threading.RLock()  # re-entrant: a computation may read other kinds

    def get(self, kind: str, positions: Sequence[int], compute: Callable[[list[int]], Sequence[T]]) -> list[T]:
        """The results of ``kind`` for the frames at ``positions``, in that order; those
        not kept yet come from one call ``compute(missing positions)``, which returns
        one result per position it is given."""
        with self._lock:
            return self._get(kind, positions, compute)

    def _get(self, kind: str, positions: Sequence[int], compute: Callable[[list[int]], Sequence[T]]) -> list[T]:
        missing = [p for p in dict.fromkeys(positions) if kind not in self._frames.get(p, {})]
        if missing:
            results = list(compute(missing))
            if len(results) != len(missing):
                raise ValueError(f"{kind}: {len(results)} results for {len(missing)} frames")
            for p, r in zip(missing, results):
                self._frames.setdefault(p, {})[kind] = r
        out = []
        for p in positions:
            self._frames.move_to_end(p)
            out.append(self._frames[p][kind])
        while len(self._frames) > max(self._keep, len(set(positions))):
            self._frames.popitem(last=False)
        return out
