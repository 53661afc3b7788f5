"""Per-scene frame cache at the working resolution.

The scene index reads every frame once anyway (to check it); it also stores the
resized frames here, so that each frame-set job maps 7 frames from disk instead of
decoding (JPEG, zlib, ray casting) and resizing every frame again -- with the paper's
frame sets a frame belongs to up to 7 of them. Arrays are plain ``.npy`` files opened
with ``mmap_mode="r"``: a job touches only its members' pages.

Layout of ``{scene}/frames/``: ``depth.npy`` (N, H, W) float32 metres (0 = invalid or
unreadable frame), ``rgb.npy`` (N, H, W, 3) uint8, ``poses.npy`` (N, 4, 4) float64 (NaN
where unknown), ``truth.npy`` (N, H, W) float32 when the source knows the clean depth,
``valid.npy`` (N,) bool (the frame was cached), and ``scene.json``: the scene's name,
frame ids, intrinsics at the cached resolution and the size of the source images.

:class:`CachedScene` is the one reader: it serves the cached frames through the
:class:`~depthgt.sources.base.Scene` protocol, so that the frame-set job, the RDE GT
and any other consumer load frames with the same code whether they come from the
cache or from the source.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import torch

from depthgt import geometry
from depthgt.errors import FrameError
from depthgt.sources.base import Frame, Scene, check_frame

__all__ = ["resize_frame", "ResizedScene", "FrameCacheWriter", "CachedScene"]


def _depth_at(depth_m: np.ndarray, size_hw: tuple[int, int]) -> np.ndarray:
    d = torch.from_numpy(np.ascontiguousarray(depth_m, dtype=np.float32))[None, None]
    return geometry.resize_depth_nearest(d, size_hw)[0, 0].numpy()


def resize_frame(frame: Frame, size_hw: tuple[int, int]) -> Frame:
    """A frame at the working resolution: depth and truth nearest/valid-aware, colour
    area-averaged (uint8), pose unchanged."""
    rgb = torch.from_numpy(np.ascontiguousarray(frame.rgb)).permute(2, 0, 1)[None].float() / 255.0
    rgb = geometry.resize_rgb(rgb, size_hw)[0].permute(1, 2, 0).numpy()
    return Frame(rgb=(rgb * 255.0 + 0.5).astype(np.uint8), depth_m=_depth_at(frame.depth_m, size_hw),
                 T_world_cam=frame.T_world_cam,
                 clean_depth_m=_depth_at(frame.clean_depth_m, size_hw) if frame.clean_depth_m is not None else None)


class ResizedScene:
    """A source scene served at the working resolution, frame by frame (what the frame
    cache holds, without the cache): for jobs that read a scene's frames once, such as
    the RDE GT's TSDF, so that they see the frames the frame sets see."""

    def __init__(self, scene: Scene, size_hw: tuple[int, int]):
        self._scene = scene
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        self.name = scene.name
        self.image_size = self.size_hw
        self.source_size = tuple(int(x) for x in scene.image_size)
        self.intrinsics = geometry.scale_intrinsics(np.asarray(scene.intrinsics, dtype=np.float64), scene.image_size,
                                                    self.size_hw)
        self.has_poses = bool(scene.has_poses)
        self.has_clean_depth = bool(scene.has_clean_depth)

    def __len__(self) -> int:
        return len(self._scene)

    def frame_id(self, i: int) -> str:
        return self._scene.frame_id(i)

    def read(self, i: int) -> Frame:
        """Frame ``i`` resized (raises the source's FrameError for a bad frame)."""
        frame = self._scene.read(i)
        check_frame(frame, self._scene.image_size, f"{self.name} frame {self.frame_id(i)}", need_pose=False)
        return resize_frame(frame, self.size_hw)


class FrameCacheWriter:
    """Pre-allocated memory-mapped arrays filled frame by frame, renamed into place on
    :meth:`close` so that a killed index job leaves no half cache behind.

    Args:
        out_dir: the cache folder.
        scene: the source scene (its name, frame ids, intrinsics and image size go to
            ``scene.json``).
        size_hw: the working resolution (H, W).
    """

    def __init__(self, out_dir: str | Path, scene: Scene, size_hw: tuple[int, int]):
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        h, w = self.size_hw
        n_frames = len(scene)
        self._meta = {
            "scene": scene.name,
            "frame_ids": [scene.frame_id(i) for i in range(n_frames)],
            "image_size": list(self.size_hw),
            "source_size": [int(x) for x in scene.image_size],
            "intrinsics": geometry.scale_intrinsics(np.asarray(scene.intrinsics, dtype=np.float64), scene.image_size,
                                                    self.size_hw).tolist(),
            "has_poses": bool(scene.has_poses),
            "has_clean_depth": bool(scene.has_clean_depth),
        }
        self._arrays = {
            "depth": self._open("depth", (n_frames, h, w), np.float32),
            "rgb": self._open("rgb", (n_frames, h, w, 3), np.uint8),
            "poses": self._open("poses", (n_frames, 4, 4), np.float64),
            "valid": self._open("valid", (n_frames,), np.bool_),
        }
        self._arrays["poses"][:] = np.nan
        if scene.has_clean_depth:
            self._arrays["truth"] = self._open("truth", (n_frames, h, w), np.float32)

    def _open(self, name: str, shape: tuple[int, ...], dtype) -> np.memmap:
        arr = np.lib.format.open_memmap(self.out / f".{name}.tmp.npy", mode="w+", dtype=dtype, shape=shape)
        arr[...] = 0
        return arr

    def put(self, i: int, frame: Frame) -> None:
        """Resize and store frame ``i`` (:func:`resize_frame`)."""
        small = resize_frame(frame, self.size_hw)
        self._arrays["depth"][i] = small.depth_m
        self._arrays["rgb"][i] = small.rgb
        if small.T_world_cam is not None:
            self._arrays["poses"][i] = small.T_world_cam
        if "truth" in self._arrays and small.clean_depth_m is not None:
            self._arrays["truth"][i] = small.clean_depth_m
        self._arrays["valid"][i] = True

    def close(self) -> None:
        for name, arr in self._arrays.items():
            arr.flush()
            del arr
            os.replace(self.out / f".{name}.tmp.npy", self.out / f"{name}.npy")
        self._arrays = {}
        tmp = self.out / ".scene.tmp.json"
        tmp.write_text(json.dumps(self._meta))
        os.replace(tmp, self.out / "scene.json")


class CachedScene:
    """The frames of a scene's cache as a :class:`~depthgt.sources.base.Scene`.

    ``read(i)`` returns frame ``i`` at the cached (working) resolution; ``intrinsics``
    and ``image_size`` are those of the cached frames, ``source_size`` the size of the
    source images they were resized from (the GT renderer places the resized depth at
    its source pixel positions). Opening it never opens the source (which can be
    costly: a synthetic room builds its textures). Arrays are memory-mapped: a job
    touches only its frames' pages.
    """

    def __init__(self, cache_dir: str | Path):
        d = Path(cache_dir)
        meta_path = d / "scene.json"
        if not meta_path.is_file() or not (d / "depth.npy").is_file():
            raise FileNotFoundError(f"frame cache {d} is missing or incomplete (rebuild the scene index)")
        meta = json.loads(meta_path.read_text())
        self.dir = d
        self.name = meta["scene"]
        self.intrinsics = np.asarray(meta["intrinsics"], dtype=np.float64)
        self.image_size = tuple(int(x) for x in meta["image_size"])
        self.source_size = tuple(int(x) for x in meta["source_size"])
        self.has_poses = bool(meta["has_poses"])
        self.has_clean_depth = bool(meta["has_clean_depth"])
        self._ids = [str(x) for x in meta["frame_ids"]]
        self._arrays = {name: np.load(d / f"{name}.npy", mmap_mode="r")
                        for name in ("depth", "rgb", "poses", "valid", "truth") if (d / f"{name}.npy").is_file()}
        n = len(self._arrays["depth"])
        if len(self._ids) != n or any(len(a) != n for a in self._arrays.values()):
            raise ValueError(f"frame cache {d}: arrays and scene.json disagree on the number of frames")

    def __len__(self) -> int:
        return len(self._ids)

    def frame_id(self, i: int) -> str:
        return self._ids[int(i)]

    def read(self, i: int) -> Frame:
        """Frame ``i`` at the cached resolution (copies of the cached arrays).

        Raises:
            FrameError: the frame was not cached (it was invalid when the index was built).
        """
        i = int(i)
        if not 0 <= i < len(self):
            raise FrameError(f"{self.dir}: frame position {i} out of range (0..{len(self) - 1})", "out_of_range")
        if not bool(self._arrays["valid"][i]):
            raise FrameError(f"{self.dir}: frame {self.frame_id(i)} is not in the cache (invalid when the index was built)",
                             "not_cached")
        pose = np.array(self._arrays["poses"][i])
        truth = self._arrays.get("truth")
        return Frame(
            rgb=np.array(self._arrays["rgb"][i]),
            depth_m=np.array(self._arrays["depth"][i]),
            T_world_cam=pose if np.isfinite(pose).all() else None,
            clean_depth_m=np.array(truth[i]) if truth is not None else None,
        )


