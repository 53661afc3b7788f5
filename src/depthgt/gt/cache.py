"""A scene's frames at the working resolution, read once per job.

:class:`ResizedScene` serves a source scene through the
:class:`~depthgt.sources.base.Scene` protocol at the working resolution and keeps the
frames it read last in memory: a batch of frame sets shares most of its frames (with the
paper's frame sets a frame belongs to up to 7 of them), so each is decoded (JPEG, zlib,
ray casting) and resized once per batch. It also remembers whether each frame it was
asked for is usable (:meth:`ResizedScene.check`): the batch jobs decide frame validity
as they read, so a bad frame is read once and every frame set holding it is skipped
with its reason. Nothing is written to disk: a cache of the
frames of every scene would hold ~0.7 MB per frame at 256x256, terabytes for ScanNet,
and a temporary one would force re-reading a scene whenever a later job needs it.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from depthgt import geometry
from depthgt.errors import FrameError
from depthgt.sources.base import Frame, Scene, check_frame, pose_problem

__all__ = ["resize_frame", "FrameCheck", "ResizedScene"]

log = logging.getLogger(__name__)


def _depth_at(depth_m: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    d = torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32))[None, None]
    return geometry.resize_depth_nearest(d, size_hw)[0, 0].numpy()


def resize_frame(frame: Frame, size_hw: tuple[int, int]) -> Frame:
    """A frame at the working resolution: depth and truth nearest/valid-aware, colour
    area-averaged (uint8), pose unchanged."""
    rgb = torch.from_numpy(np.ascontiguousarray(frame.rgb)).permute(2, 0, 1)[None].float() / 255.0
    rgb = geometry.resize_rgb(rgb, size_hw)[0].permute(1, 2, 0).numpy()
    return Frame(
        rgb=(rgb * 255.0 + 0.5).astype(np.uint8),
        depth_m=_depth_at(frame.depth_m, size_hw),
        T_world_cam=frame.T_world_cam,
        clean_depth_m=_depth_at(frame.clean_depth_m, size_hw) if frame.clean_depth_m is not None else None,
    )


@dataclass(frozen=True)
class FrameCheck:
    """Whether one frame could be used, as found when it was read.

    Attributes:
        position: the frame's position in the scene.
        frame_id: the source's id of the frame.
        valid: the frame read fine (and, where poses are needed, has a usable pose).
        reason: the :class:`~depthgt.errors.FrameError` reason tag ("" when valid).
        message: the error's message, naming the file at fault ("" when valid).
    """

    position: int
    frame_id: str
    valid: bool
    reason: str = ""
    message: str = ""

    @property
    def problem(self) -> str:
        """``"<reason> (<message>)"``, how a skipped frame set names this frame's problem."""
        return f"{self.reason} ({self.message})" if not self.valid else ""

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


class ResizedScene:
    """A source scene served at the working resolution (:func:`resize_frame`), the last
    ``keep`` frames read kept in memory. The frame-set batches and the RDE GT read their
    frames through it, so that both see the same frames.

    ``image_size`` and ``intrinsics`` are those of the resized frames, ``source_size``
    the size of the source images (the GT renderer places the resized depth at its
    source pixel positions). With ``need_pose`` a frame without a usable pose
    (:func:`~depthgt.sources.base.pose_problem`) is unusable too.

    Every frame's outcome is remembered for the object's life (:meth:`check`,
    :attr:`checks`): an unusable frame is read once, its error raised again on every
    later read.
    """

    def __init__(self, scene: Scene, size_hw: tuple[int, int], keep: int = 64, need_pose: bool = False):
        self._scene = scene
        self._keep = int(keep)
        self._frames: OrderedDict[int, Frame] = OrderedDict()
        self._checks: dict[int, FrameCheck] = {}
        self.need_pose = bool(need_pose)
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        self.name = scene.name
        self.image_size = self.size_hw
        self.source_size = tuple(int(x) for x in scene.image_size)
        self.intrinsics = geometry.scale_intrinsics(
            np.asarray(scene.intrinsics, dtype=np.float64), scene.image_size, self.size_hw
        )
        self.has_poses = bool(scene.has_poses)
        self.has_clean_depth = bool(scene.has_clean_depth)
        self.colour_matches_depth = bool(getattr(scene, "colour_matches_depth", True))

    def __len__(self) -> int:
        return len(self._scene)

    def frame_id(self, i: int) -> str:
        return self._scene.frame_id(i)

    def read(self, i: int) -> Frame:
        """Frame ``i`` resized (raises the source's FrameError for a bad frame)."""
        i = int(i)
        known = self._checks.get(i)
        if known is not None and not known.valid:
            raise FrameError(known.message, known.reason)
        if i in self._frames:
            self._frames.move_to_end(i)
            return self._frames[i]
        where = f"{self.name} frame {self.frame_id(i)}"
        try:
            frame = self._scene.read(i)
            check_frame(frame, self._scene.image_size, where, need_pose=False)
            problem = pose_problem(frame.T_world_cam) if self.need_pose else None
            if problem is not None:
                raise FrameError(f"{where}: {problem[1]}", problem[0])
        except FrameError as err:
            log.warning("unusable frame: %s", err)
            self._checks[i] = FrameCheck(i, self.frame_id(i), False, err.reason, str(err))
            raise
        self._checks[i] = FrameCheck(i, self.frame_id(i), True)
        small = resize_frame(frame, self.size_hw)
        self._frames[i] = small
        while len(self._frames) > self._keep:
            self._frames.popitem(last=False)
        return small

    def check(self, i: int) -> FrameCheck:
        """Whether frame ``i`` is usable: read once (into the window) on the first call,
        the outcome remembered."""
        i = int(i)
        if i not in self._checks:
            try:
                self.read(i)
            except FrameError:
                pass
        return self._checks[i]

    @property
    def checks(self) -> list[FrameCheck]:
        """The outcome of every frame read so far, by position."""
        return [self._checks[i] for i in sorted(self._checks)]
