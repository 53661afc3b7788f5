"""Helpers shared by the file-based adapters (ScanNet, 7-Scenes, TUM)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Iterable

from depthgt.errors import FrameError, SourceError
from depthgt.io import read_depth_png

log = logging.getLogger(__name__)


def require_root(root: str | Path | None, kind: str) -> Path:
    """The source's root folder; SourceError naming it when it is missing."""
    if root is None:
        raise SourceError(f"{kind} source needs a root folder (got None)")
    path = Path(root)
    if not path.is_dir():
        raise SourceError(f"{path}: {kind} root folder not found")
    return path


def probe_depth_size(depth_paths: Iterable[Path], depth_scale: float, scene_path: Path, tries: int = 10) -> tuple[int, int]:
    """(H, W) of the first readable of the first ``tries`` depth images; later frames of
    another size fail on their own (FrameError size_mismatch)."""
    for i, p in enumerate(depth_paths):
        if i >= tries:
            break
        try:
            return tuple(read_depth_png(p, depth_scale).shape)  # type: ignore[return-value]
        except FrameError as exc:
            log.warning("%s", exc)
    raise SourceError(f"{scene_path}: none of the first depth images is readable, cannot tell the image size")


def list_sequences(path: Path, is_sequence) -> list[str]:
    """Sorted names of the sequence folders under ``path``, or ``[path's name]`` when
    ``path`` is itself a sequence (``is_sequence(folder) -> bool`` tells)."""
    if is_sequence(path):
        return [path.resolve().name]
    return sorted(p.name for p in path.iterdir() if p.is_dir() and is_sequence(p))


class FileScene:
    """Common set-up of the file-based scenes: path, name, depth scale (checked),
    whether poses are required, and the list of scene-level problems."""

    has_clean_depth = False

    def _init_files(self, folder: str | Path, name: str, depth_scale: float, require_pose: bool) -> None:
        self.path = Path(folder)
        self.name = name
        if not depth_scale > 0:
            raise SourceError(f"{self.path}: depth_scale must be > 0, got {depth_scale}")
        self.depth_scale = float(depth_scale)
        self.require_pose = bool(require_pose)
        self.problems: list[str] = []


class NumberedFrames(FileScene):
    """Mixin for scenes whose frames are numbered files (ScanNet exported, 7-Scenes):
    the subclass sets ``_ids`` (sorted int array of frame numbers), ``_depth`` (number ->
    depth image path), ``depth_scale`` and ``path``."""

    def _probe_size(self) -> tuple[int, int]:
        paths = [self._depth[int(n)] for n in self._ids[:10] if int(n) in self._depth]
        return probe_depth_size(paths, self.depth_scale, self.path)

    def __len__(self) -> int:
        return int(self._ids.size)

    def frame_id(self, i: int) -> str:
        return str(int(self._ids[i]))
