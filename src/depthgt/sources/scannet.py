"""ScanNet adapter: exported scene folders and raw ``.sens`` files.

``root`` is a folder of scenes. A scene ``<name>`` is, in this order of preference:

1. a folder ``root/<name>/`` in ScanNet's exported layout::

       color/N.jpg                   colour (1296x968 in ScanNet; .png also accepted)
       depth/N.png                   uint16 depth, millimetres (option ``depth_scale``)
       pose/N.txt                    4x4 camera-to-world ("-inf" rows where tracking was lost)
       intrinsic/intrinsic_depth.txt 4x4 depth intrinsics (the upper-left 3x3 is used)

   Frames are the numbers N found in ``color/`` or ``depth/`` (sorted numerically,
   gaps allowed); a number with a file missing in one folder is a frame that fails
   with ``FrameError("missing_file")`` so that it is recorded, not silently dropped.
   ``image_size`` is the most common size among depth images sampled over the scene
   (PNG headers; see :func:`depthgt.sources._files.probe_depth_size`).

2. a raw stream ``root/<name>.sens`` or ``root/<name>/<name>.sens`` (see
   :mod:`depthgt.sources.sens`); depth scale, sizes and intrinsics come from its
   header, frame ids are the frame positions in the file (the N of ScanNet's export).

Colour is resized to the depth resolution with ``cv2.INTER_AREA``. ScanNet's colour and
depth cameras are calibrated separately; at 640x480 their pinhole parameters agree to
about 1 pixel, which is the registration the exported data offers.

Options (``open_scene(root, scene, **options)``):
    depth_scale: raw depth units per metre for exported folders (default 1000).
    require_pose: when True (default) a frame whose pose is missing, non-finite or not
        rigid raises ``FrameError`` ("missing_file" / "nonfinite_pose" /
        "invalid_pose"); when False such a frame is returned with ``T_world_cam=None``
        (registration does not need it).
    intrinsics: (3, 3) matrix overriding the file's depth intrinsics.
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from depthgt.errors import SourceError
from depthgt.io import fit_rgb_to_depth, read_pose_txt, read_rgb
from depthgt.sources._files import NumberedFrames, require_root
from depthgt.sources.base import Frame, check_frame, usable_pose
from depthgt.sources.sens import SensFile, read_header

__all__ = ["ScanNetExportedScene", "ScanNetSensScene", "open_scene", "list_scenes", "frame_count", "scene_file"]

log = logging.getLogger(__name__)

_NUMBER = re.compile(r"^(\d+)$")


def _numbered(folder: Path, suffixes: tuple[str, ...]) -> dict[int, Path]:
    """``{N: path}`` for files ``N<suffix>`` in ``folder`` (first suffix wins)."""
    found: dict[int, Path] = {}
    if not folder.is_dir():
        return found
    for suffix in reversed(suffixes):
        for p in folder.glob(f"*{suffix}"):
            m = _NUMBER.match(p.name[: -len(suffix)])
            if m:
                found[int(m.group(1))] = p
    return found


def _check_intrinsics(K: np.ndarray, where: str) -> np.ndarray:
    K = np.asarray(K, dtype=np.float64)
    if K.shape in ((4, 4), (3, 4), (4, 3)):
        K = K[:3, :3]
    if K.shape != (3, 3) or not np.isfinite(K).all() or K[0, 0] <= 0 or K[1, 1] <= 0:
        raise SourceError(
            f"{where}: intrinsics must be a finite 3x3 matrix with positive focal lengths, got {K.tolist()}"
        )
    return K.copy()


def _finish(frame: Frame, hw: tuple[int, int], where: str, require_pose: bool) -> Frame:
    """Common validation: with ``require_pose`` False an unusable pose (non-finite, not
    rigid, bottom row not 0 0 0 1) becomes None."""
    if not require_pose and frame.T_world_cam is not None:
        frame = Frame(frame.rgb, frame.depth_m, usable_pose(frame.T_world_cam), frame.clean_depth_m)
    return check_frame(frame, hw, where, need_pose=require_pose)


class ScanNetExportedScene(NumberedFrames):
    """One scene in ScanNet's exported folder layout (see the module docstring)."""

    has_clean_depth = False

    def __init__(
        self,
        folder: str | Path,
        name: str,
        depth_scale: float = 1000.0,
        require_pose: bool = True,
        intrinsics: np.ndarray | None = None,
    ):
        self._init_files(folder, name, depth_scale, require_pose)
        k_file = self.path / "intrinsic" / "intrinsic_depth.txt"
        if intrinsics is not None:
            self.intrinsics = _check_intrinsics(intrinsics, f"{self.path} (option intrinsics)")
        elif k_file.is_file():
            try:
                values = np.loadtxt(k_file, dtype=np.float64)
            except ValueError as exc:
                raise SourceError(f"{k_file}: cannot parse intrinsics ({exc})") from exc
            self.intrinsics = _check_intrinsics(values, str(k_file))
        else:
            raise SourceError(f"{k_file}: missing depth intrinsics")
        self._color = _numbered(self.path / "color", (".jpg", ".png"))
        self._depth = _numbered(self.path / "depth", (".png",))
        self._pose = _numbered(self.path / "pose", (".txt",))
        self._ids = np.array(sorted(set(self._color) | set(self._depth)), dtype=np.int64)
        if self._ids.size == 0:
            raise SourceError(f"{self.path}: no frames (no color/N.jpg or depth/N.png)")
        self.has_poses = bool(self._pose)
        self.image_size = self._probe_size()

    def read(self, i: int) -> Frame:
        """Frame at position ``i``; raises FrameError naming the file at fault."""
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame position {i} out of range 0..{len(self) - 1}")
        n = int(self._ids[i])
        depth_path = self._depth.get(n, self.path / "depth" / f"{n}.png")
        color_path = self._color.get(n, self.path / "color" / f"{n}.jpg")
        depth_m = self._read_depth(depth_path)
        rgb = fit_rgb_to_depth(read_rgb(color_path), self.image_size, str(color_path))
        T = None
        if self.has_poses:
            pose_path = self._pose.get(n, self.path / "pose" / f"{n}.txt")
            if pose_path.is_file() or self.require_pose:
                T = read_pose_txt(pose_path)
        return _finish(
            Frame(rgb, depth_m, T), self.image_size, f"{self.path} frame {n}", self.require_pose and self.has_poses
        )


class ScanNetSensScene:
    """One scene stored as a raw ScanNet ``.sens`` file, read lazily."""

    has_clean_depth = False
    has_poses = True

    def __init__(self, path: str | Path, name: str, require_pose: bool = True, intrinsics: np.ndarray | None = None):
        self.path = Path(path)
        self.name = name
        self.require_pose = bool(require_pose)
        self.sens = SensFile(self.path)
        self.problems = list(self.sens.problems)
        self.image_size = self.sens.header.depth_hw
        where = f"{self.path} (option intrinsics)" if intrinsics is not None else f"{self.path} header intrinsic_depth"
        self.intrinsics = _check_intrinsics(
            self.sens.header.intrinsic_depth if intrinsics is None else intrinsics, where
        )

    def __len__(self) -> int:
        return len(self.sens)

    def frame_id(self, i: int) -> str:
        if not 0 <= i < len(self):
            raise IndexError(f"{self.path}: frame position {i} out of range 0..{len(self) - 1}")
        return str(int(i))

    def read(self, i: int) -> Frame:
        """Frame ``i`` of the file; raises FrameError naming the file and frame."""
        depth_m = self.sens.read_depth_m(i)
        where = f"{self.path} frame {i}"
        rgb = fit_rgb_to_depth(self.sens.read_color(i), self.image_size, f"{where} colour")
        T = self.sens.poses[i].copy()
        return _finish(Frame(rgb, depth_m, T), self.image_size, where, self.require_pose)


def _root(root: str | Path | None) -> Path:
    return require_root(root, "scannet")


def _is_exported(folder: Path) -> bool:
    return (folder / "depth").is_dir() or (folder / "color").is_dir()


def list_scenes(root: str | Path | None, **options) -> list[str]:
    """Sorted names of the scenes under ``root``: exported scene folders, folders
    holding ``<name>/<name>.sens`` and files ``<name>.sens``."""
    path = _root(root)
    names: set[str] = set()
    for p in path.iterdir():
        if p.is_dir() and (_is_exported(p) or (p / f"{p.name}.sens").is_file()):
            names.add(p.name)
        elif p.is_file() and p.suffix == ".sens":
            names.add(p.stem)
    return sorted(names)


def scene_file(root: str | Path | None, scene: str, **options) -> Path | None:
    """The ``.sens`` file that holds ``scene``, or None when the scene is an exported
    folder (preferred, as by :func:`open_scene`) or not found."""
    path = _root(root)
    folder = path / scene
    if folder.is_dir() and _is_exported(folder):
        return None
    for sens in (folder / f"{scene}.sens", path / f"{scene}.sens"):
        if sens.is_file():
            return sens
    return None


def frame_count(root: str | Path | None, scene: str, **options) -> int:
    """Frames of a scene: the ``.sens`` header's count (no frame record is read), or
    the exported folder's frames (a directory listing)."""
    sens = scene_file(root, scene)
    if sens is not None:
        return int(read_header(sens).num_frames)
    return len(open_scene(root, scene, **options))


def open_scene(
    root: str | Path | None,
    scene: str,
    depth_scale: float = 1000.0,
    require_pose: bool = True,
    intrinsics: np.ndarray | None = None,
):
    """Open ScanNet scene ``scene`` under ``root`` (exported folder preferred over
    ``.sens``).

    Raises:
        SourceError: root or scene not found (the message lists the known scenes),
            missing intrinsics, truncated ``.sens`` header.
    """
    path = _root(root)
    folder = path / scene
    if folder.is_dir() and _is_exported(folder):
        return ScanNetExportedScene(
            folder, scene, depth_scale=depth_scale, require_pose=require_pose, intrinsics=intrinsics
        )
    for sens in (folder / f"{scene}.sens", path / f"{scene}.sens"):
        if sens.is_file():
            return ScanNetSensScene(sens, scene, require_pose=require_pose, intrinsics=intrinsics)
    known = list_scenes(path)
    raise SourceError(f"{path}: unknown scannet scene {scene!r}; known scenes: {', '.join(known) or '(none)'}")
