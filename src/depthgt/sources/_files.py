"""Helpers shared by the file-based adapters (ScanNet, 7-Scenes, TUM)."""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from depthgt.errors import FrameError, SourceError
from depthgt.io import probe_image_file, read_depth_png

log = logging.getLogger(__name__)


def require_root(root: str | Path | None, kind: str) -> Path:
    """The source's root folder; SourceError naming it when it is missing."""
    if root is None:
        raise SourceError(f"{kind} source needs a root folder (got None)")
    path = Path(root).expanduser()
    if not path.is_dir():
        rule = "" if path.is_absolute() else f" ({root} relative to the working directory {Path.cwd()})"
        what = "is not a folder" if path.exists() else "not found"
        raise SourceError(f"{path.absolute()}: {kind} root folder {what}{rule}")
    return path


def probe_depth_size(
    depth_paths: Sequence[Path], scene_path: Path, samples: int = 15
) -> tuple[tuple[int, int], str, list[str]]:
    """The scene's depth image size: the most common declared size (PNG headers only,
    nothing decoded) among up to ``samples`` depth images spread evenly over the scene.

    A single odd image, first or not, thus cannot decide the size of all the others;
    each image of another size later fails on its own (FrameError size_mismatch) with
    a message naming it and this majority size.

    Args:
        depth_paths: the scene's depth images in frame order.

    Returns:
        ``(H, W)``; how it is named in size-mismatch messages; scene-level problems
        (sampled images of differing sizes), empty when all agree.

    Raises:
        SourceError: none of the sampled depth images has a readable header.
    """
    n = len(depth_paths)
    picks = np.unique(np.linspace(0, n - 1, min(n, samples)).round().astype(np.int64)) if n else []
    sizes: Counter[tuple[int, int]] = Counter()
    for k in picks:
        try:
            sizes[probe_image_file(depth_paths[int(k)]).hw] += 1
        except FrameError as exc:
            log.warning("%s", exc)
    if not sizes:
        raise SourceError(
            f"{scene_path}: none of the {len(picks)} sampled depth images is readable, cannot tell the image size"
        )
    (h, w), count = sizes.most_common(1)[0]  # ties: the size met first
    total = sum(sizes.values())
    what = f"the scene's depth size (that of {count} of {total} sampled depth images)"
    problems = []
    if len(sizes) > 1:
        seen = ", ".join(f"{sw}x{sh} ({c})" for (sh, sw), c in sizes.most_common())
        problems.append(
            f"{scene_path}: depth images differ in size ({seen} of {total} sampled); the scene uses {w}x{h}, "
            "frames of another size are skipped as size_mismatch"
        )
        log.warning("%s", problems[-1])
    return (h, w), what, problems


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
        self._size_what = "expected depth size"

    def _set_size(self, probed: tuple[tuple[int, int], str, list[str]]) -> tuple[int, int]:
        hw, self._size_what, problems = probed
        self.problems.extend(problems)
        return hw

    def _read_depth(self, path: Path) -> np.ndarray:
        """(H, W) float32 metres of a depth image of the scene's size (checked on the
        PNG header before decoding; FrameError size_mismatch names the majority size)."""
        return read_depth_png(path, self.depth_scale, expected_hw=self.image_size, what=self._size_what)


class NumberedFrames(FileScene):
    """Mixin for scenes whose frames are numbered files (ScanNet exported, 7-Scenes):
    the subclass sets ``_ids`` (sorted int array of frame numbers), ``_depth`` (number ->
    depth image path), ``depth_scale`` and ``path``."""

    def _probe_size(self) -> tuple[int, int]:
        paths = [self._depth[int(n)] for n in self._ids if int(n) in self._depth]
        return self._set_size(probe_depth_size(paths, self.path))

    def __len__(self) -> int:
        return int(self._ids.size)

    def frame_id(self, i: int) -> str:
        return str(int(self._ids[i]))
