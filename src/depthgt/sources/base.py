"""One interface for every RGB-D source, and the registry of adapters.

Every adapter opens one *scene* (a single continuous RGB-D stream) and exposes:

* ``len(scene)``: number of frames (frame positions ``0..len-1``);
* ``scene.intrinsics``: (3, 3) float64 pinhole matrix of the depth camera at
  ``scene.image_size``;
* ``scene.image_size``: ``(H, W)`` of the depth image (colour is brought to it);
* ``scene.has_poses``: whether ``read`` returns camera-to-world poses;
* ``scene.has_clean_depth``: whether ``read`` returns noise-free depth (synthetic);
* ``scene.frame_id(i)``: the source's own id for position ``i`` (file number,
  timestamp, ...), used in manifests;
* ``scene.read(i) -> Frame``: raises :class:`~depthgt.errors.FrameError` when the
  frame is unusable (the message names the file).

Adapters register themselves with :func:`register` and are imported lazily by
:func:`open_scene`, so that opening a 7-Scenes folder never imports the ``.sens``
reader and nothing heavy happens while Snakemake parses the workflow.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from depthgt.errors import FrameError, SourceError


@dataclass(frozen=True)
class Frame:
    """One RGB-D frame at the depth camera's resolution.

    Attributes:
        rgb: (H, W, 3) uint8 colour, RGB order, registered to the depth image as well
            as the source allows.
        depth_m: (H, W) float32 depth in metres, 0 = invalid.
        T_world_cam: (4, 4) float64 camera-to-world pose, or None when the source has
            no poses.
        clean_depth_m: (H, W) float32 noise-free depth in metres (0 = no surface), only
            for sources that know it (synthetic), else None.
    """

    rgb: np.ndarray
    depth_m: np.ndarray
    T_world_cam: np.ndarray | None = None
    clean_depth_m: np.ndarray | None = None


@runtime_checkable
class Scene(Protocol):
    """A single RGB-D stream; see the module docstring for the contract."""

    name: str
    intrinsics: np.ndarray
    image_size: tuple[int, int]
    has_poses: bool
    has_clean_depth: bool

    def __len__(self) -> int: ...

    def frame_id(self, i: int) -> str: ...

    def read(self, i: int) -> Frame: ...


# kind -> "module:function" that opens a scene: f(root, scene, **options) -> Scene
# and "module:function" that lists scenes: g(root, **options) -> list[str].
_ADAPTERS: dict[str, tuple[str, str]] = {
    "synthetic": ("depthgt.sources.synthetic:open_scene", "depthgt.sources.synthetic:list_scenes"),
    "scannet": ("depthgt.sources.scannet:open_scene", "depthgt.sources.scannet:list_scenes"),
    "sevenscenes": ("depthgt.sources.sevenscenes:open_scene", "depthgt.sources.sevenscenes:list_scenes"),
    "tum": ("depthgt.sources.tum:open_scene", "depthgt.sources.tum:list_scenes"),
}


def register(kind: str, opener: str, lister: str) -> None:
    """Register an adapter by dotted ``module:function`` paths (imported lazily)."""
    _ADAPTERS[kind] = (opener, lister)


def known_kinds() -> list[str]:
    return sorted(_ADAPTERS)


def _resolve(path: str) -> Callable[..., Any]:
    module, func = path.split(":")
    return getattr(importlib.import_module(module), func)


def _adapter(kind: str) -> tuple[str, str]:
    if kind not in _ADAPTERS:
        raise SourceError(f"unknown source kind {kind!r}; known kinds: {', '.join(known_kinds())}")
    return _ADAPTERS[kind]


def open_scene(kind: str, root: str | None, scene: str, **options: Any) -> Scene:
    """Open scene ``scene`` of a source of kind ``kind`` under ``root``.

    Raises:
        SourceError: unknown kind, unknown scene (the message lists the known ones),
            or a scene that cannot be opened.
    """
    return _resolve(_adapter(kind)[0])(root, scene, **options)


def list_scenes(kind: str, root: str | None, **options: Any) -> list[str]:
    """Names of the scenes a source holds, sorted."""
    return _resolve(_adapter(kind)[1])(root, **options)


def check_frame(frame: Frame, expected_hw: tuple[int, int], where: str, need_pose: bool) -> Frame:
    """Validate a frame read by an adapter; raise :class:`FrameError` naming ``where``.

    Checks shapes and dtypes, finite depth, a non-empty depth image and (when
    ``need_pose``) a finite, rigid pose.
    """
    h, w = expected_hw
    if frame.depth_m.shape != (h, w):
        raise FrameError(f"{where}: depth is {frame.depth_m.shape[1]}x{frame.depth_m.shape[0]}, expected {w}x{h}", "size_mismatch")
    if frame.rgb.shape != (h, w, 3):
        raise FrameError(f"{where}: colour has shape {frame.rgb.shape}, expected {(h, w, 3)}", "size_mismatch")
    if not np.isfinite(frame.depth_m).all():
        raise FrameError(f"{where}: depth holds non-finite values", "nonfinite_depth")
    if not (frame.depth_m > 0).any():
        raise FrameError(f"{where}: depth image is empty (no valid pixel)", "empty_depth")
    if need_pose:
        T = frame.T_world_cam
        if T is None:
            raise FrameError(f"{where}: no pose", "missing_pose")
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise FrameError(f"{where}: pose is not a finite 4x4 matrix", "nonfinite_pose")
        R = T[:3, :3]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-3 or abs(np.linalg.det(R) - 1) > 1e-3:
            raise FrameError(f"{where}: pose rotation is not orthonormal", "invalid_pose")
    return frame
