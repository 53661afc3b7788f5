"""Microsoft 7-Scenes adapter.

A sequence folder holds, per frame XXXXXX (six digits)::

    frame-XXXXXX.color.png | .color.jpg   640x480 colour (not registered to depth: a
                                          second Kinect camera, roughly aligned)
    frame-XXXXXX.depth.png                uint16 millimetres, 65535 or 0 = invalid
    frame-XXXXXX.pose.txt                 4x4 camera-to-world (KinectFusion)

``root`` is either a folder of sequence folders (``seq-01``, ...), whose names are the
scenes, or a sequence folder itself, whose scene is named ``"."`` or after the folder
(``list_scenes`` returns the folder name).

Intrinsics: ``camera-intrinsics.txt`` (3x3) in the sequence folder or in ``root``;
else the 7-Scenes published depth camera, fx = fy = 585, cx = 320, cy = 240 at 640x480
(:data:`DEFAULT_INTRINSICS`); the option ``intrinsics`` overrides both.

Options: ``intrinsics`` (3x3), ``depth_scale`` (default 1000 raw units per metre),
``require_pose`` (default True; as in :mod:`depthgt.sources.scannet`).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from depthgt.errors import SourceError
from depthgt.io import fit_rgb_to_depth, read_pose_txt, read_rgb
from depthgt.sources._files import NumberedFrames, list_sequences, require_root
from depthgt.sources.base import Frame, check_frame, usable_pose

__all__ = ["DEFAULT_INTRINSICS", "SevenScenesScene", "open_scene", "list_scenes"]

log = logging.getLogger(__name__)

#: 7-Scenes depth camera (dataset documentation), at 640x480.
DEFAULT_INTRINSICS = np.array([[585.0, 0.0, 320.0], [0.0, 585.0, 240.0], [0.0, 0.0, 1.0]])
INVALID_RAW = 65535  # 7-Scenes marks missing depth with 65535 (and sometimes 0)

_FRAME = re.compile(r"^frame-(\d+)\.(color|depth|pose)\.(png|jpg|txt)$")


def _scan(folder: Path) -> dict[str, dict[int, Path]]:
    """``{"color"|"depth"|"pose": {frame number: path}}`` (colour: .png before .jpg)."""
    out: dict[str, dict[int, Path]] = {"color": {}, "depth": {}, "pose": {}}
    for p in sorted(folder.iterdir(), key=lambda q: q.name.endswith(".png")):  # .png last: it wins
        m = _FRAME.match(p.name)
        if m:
            kind, ext = m.group(2), m.group(3)
            if (kind, ext) in {("color", "png"), ("color", "jpg"), ("depth", "png"), ("pose", "txt")}:
                out[kind][int(m.group(1))] = p
    return out


def _is_sequence(folder: Path) -> bool:
    return any(folder.glob("frame-*.depth.png"))


class SevenScenesScene(NumberedFrames):
    """One 7-Scenes sequence folder (see the module docstring)."""

    has_clean_depth = False

    def __init__(
        self,
        folder: str | Path,
        name: str,
        intrinsics: np.ndarray | None = None,
        depth_scale: float = 1000.0,
        require_pose: bool = True,
        intrinsics_search: tuple[Path, ...] = (),
    ):
        self._init_files(folder, name, depth_scale, require_pose)
        self.intrinsics = self._intrinsics(intrinsics, (self.path, *intrinsics_search))
        files = _scan(self.path)
        self._color, self._depth, self._pose = files["color"], files["depth"], files["pose"]
        self._ids = np.array(sorted(set(self._color) | set(self._depth)), dtype=np.int64)
        if self._ids.size == 0:
            raise SourceError(f"{self.path}: no 7-Scenes frames (frame-XXXXXX.depth.png)")
        self.has_poses = bool(self._pose)
        self.image_size = self._probe_size()

    def _intrinsics(self, override, folders) -> np.ndarray:
        if override is not None:
            K, where = np.asarray(override, dtype=np.float64), f"{self.path} (option intrinsics)"
        else:
            files = [f / "camera-intrinsics.txt" for f in folders if (f / "camera-intrinsics.txt").is_file()]
            if files:
                where = str(files[0])
                try:
                    K = np.loadtxt(files[0], dtype=np.float64)
                except ValueError as exc:
                    raise SourceError(f"{where}: cannot parse intrinsics ({exc})") from exc
            else:
                log.info(
                    "%s: no camera-intrinsics.txt, using the 7-Scenes default fx=fy=585, cx=320, cy=240", self.path
                )
                K, where = DEFAULT_INTRINSICS, "7-Scenes default"
        if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise SourceError(
                f"{where}: intrinsics must be a finite 3x3 matrix with positive focal lengths, got {K.tolist()}"
            )
        return K.copy()

    def _file(self, table: dict[int, Path], n: int, suffix: str) -> Path:
        return table.get(n, self.path / f"frame-{n:06d}.{suffix}")

    def read(self, i: int) -> Frame:
        """Frame at position ``i``; raises FrameError naming the file at fault."""
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame position {i} out of range 0..{len(self) - 1}")
        n = int(self._ids[i])
        depth_path = self._file(self._depth, n, "depth.png")
        depth_m = self._read_depth(depth_path)
        depth_m[depth_m >= np.float32((INVALID_RAW - 0.5) / self.depth_scale)] = (
            0.0  # half a unit below: no float rounding issue
        )
        color_path = self._file(self._color, n, "color.png")
        rgb = fit_rgb_to_depth(read_rgb(color_path), self.image_size, str(color_path))
        T = None
        need_pose = self.require_pose and self.has_poses
        if self.has_poses:
            pose_path = self._file(self._pose, n, "pose.txt")
            if pose_path.is_file() or need_pose:
                T = read_pose_txt(pose_path)
            if not need_pose:
                T = usable_pose(T)
        return check_frame(Frame(rgb, depth_m, T), self.image_size, f"{self.path} frame {n}", need_pose)


def _root(root: str | Path | None) -> Path:
    return require_root(root, "sevenscenes")


def list_scenes(root: str | Path | None, **options) -> list[str]:
    """Sorted sequence names under ``root``, or ``[root's folder name]`` when ``root``
    is itself a sequence."""
    return list_sequences(_root(root), _is_sequence)


def open_scene(
    root: str | Path | None,
    scene: str,
    intrinsics: np.ndarray | None = None,
    depth_scale: float = 1000.0,
    require_pose: bool = True,
) -> SevenScenesScene:
    """Open 7-Scenes sequence ``scene`` under ``root`` (``"."`` or the folder's own
    name when ``root`` is a sequence).

    Raises:
        SourceError: root or scene not found (the message lists the known scenes),
            unparsable intrinsics.
    """
    path = _root(root)
    opts = dict(intrinsics=intrinsics, depth_scale=depth_scale, require_pose=require_pose)
    if _is_sequence(path) and scene in (".", path.resolve().name):
        return SevenScenesScene(path, path.resolve().name, **opts)
    folder = path / scene
    if scene not in (".", "") and folder.is_dir() and _is_sequence(folder):
        return SevenScenesScene(folder, scene, intrinsics_search=(path,), **opts)
    known = list_scenes(path)
    raise SourceError(f"{path}: unknown sevenscenes scene {scene!r}; known scenes: {', '.join(known) or '(none)'}")
