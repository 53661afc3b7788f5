"""Per-scene frame cache at the working resolution.

The scene index reads every frame once anyway (to check it); it also stores the
resized frames here, so that each frame-set job maps 7 frames from disk instead of
decoding (JPEG, zlib, ray casting) and resizing every frame again -- with the paper's
frame sets a frame belongs to up to 7 of them. Arrays are plain ``.npy`` files opened
with ``mmap_mode="r"``: a job touches only its members' pages.

Layout of ``{scene}/frames/``: ``depth.npy`` (N, H, W) float32 metres (0 = invalid or
unreadable frame), ``rgb.npy`` (N, H, W, 3) uint8, ``poses.npy`` (N, 4, 4) float64 (NaN
where unknown), ``truth.npy`` (N, H, W) float32 when the source knows the clean depth.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import torch

from depthgt import geometry
from depthgt.sources.base import Frame


class FrameCacheWriter:
    """Pre-allocated memory-mapped arrays filled frame by frame, renamed into place on
    :meth:`close` so that a killed index job leaves no half cache behind."""

    def __init__(self, out_dir: str | Path, n_frames: int, size_hw: tuple[int, int], with_truth: bool):
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.size_hw = (int(size_hw[0]), int(size_hw[1]))
        h, w = self.size_hw
        self._arrays = {
            "depth": self._open("depth", (n_frames, h, w), np.float32),
            "rgb": self._open("rgb", (n_frames, h, w, 3), np.uint8),
            "poses": self._open("poses", (n_frames, 4, 4), np.float64),
        }
        self._arrays["poses"][:] = np.nan
        if with_truth:
            self._arrays["truth"] = self._open("truth", (n_frames, h, w), np.float32)

    def _open(self, name: str, shape: tuple[int, ...], dtype) -> np.memmap:
        arr = np.lib.format.open_memmap(self.out / f".{name}.tmp.npy", mode="w+", dtype=dtype, shape=shape)
        arr[...] = 0
        return arr

    def put(self, i: int, frame: Frame) -> None:
        """Resize and store frame ``i`` (depth nearest/valid-aware, colour area-averaged)."""
        depth = torch.from_numpy(np.ascontiguousarray(frame.depth_m, dtype=np.float32))[None, None]
        self._arrays["depth"][i] = geometry.resize_depth_nearest(depth, self.size_hw)[0, 0].numpy()
        rgb = torch.from_numpy(np.ascontiguousarray(frame.rgb)).permute(2, 0, 1)[None].float() / 255.0
        rgb = geometry.resize_rgb(rgb, self.size_hw)[0].permute(1, 2, 0).numpy()
        self._arrays["rgb"][i] = (rgb * 255.0 + 0.5).astype(np.uint8)
        if frame.T_world_cam is not None:
            self._arrays["poses"][i] = frame.T_world_cam
        if "truth" in self._arrays and frame.clean_depth_m is not None:
            truth = torch.from_numpy(np.ascontiguousarray(frame.clean_depth_m, dtype=np.float32))[None, None]
            self._arrays["truth"][i] = geometry.resize_depth_nearest(truth, self.size_hw)[0, 0].numpy()

    def close(self) -> None:
        for name, arr in self._arrays.items():
            arr.flush()
            del arr
            os.replace(self.out / f".{name}.tmp.npy", self.out / f"{name}.npy")
        self._arrays = {}


def read_cached(cache_dir: str | Path, members: list[int]) -> dict[str, np.ndarray]:
    """The members' arrays from a cache: depth (F, H, W), rgb (F, H, W, 3), poses (F, 4, 4)
    and truth (F, H, W) when cached."""
    d = Path(cache_dir)
    if not (d / "depth.npy").exists():
        raise FileNotFoundError(f"frame cache {d} is missing (rebuild the scene index)")
    out = {}
    for name in ("depth", "rgb", "poses", "truth"):
        p = d / f"{name}.npy"
        if p.exists():
            out[name] = np.ascontiguousarray(np.load(p, mmap_mode="r")[members])
    return out


class CachedScene:
    """What a frame-set job needs of a scene whose frames are cached: name, intrinsics
    and size of the source images, and frame ids -- from the scene index, without
    opening the source (opening can be costly: a synthetic room builds its textures)."""

    has_poses = False
    has_clean_depth = False

    def __init__(self, index_json: str | Path, index_table):
        import json

        meta = json.loads(Path(index_json).read_text())
        self.name = meta["scene"]
        self.intrinsics = np.asarray(meta["intrinsics"], dtype=np.float64)
        self.image_size = tuple(meta["image_size"])
        self.has_poses = bool(meta["has_poses"])
        self.has_clean_depth = bool(meta["has_clean_depth"])
        self._ids = dict(zip(index_table["position"].astype(int), index_table["frame_id"].astype(str)))

    def __len__(self) -> int:
        return len(self._ids)

    def frame_id(self, i: int) -> str:
        return self._ids[int(i)]

    def read(self, i: int):
        raise NotImplementedError("CachedScene serves cached frames only; open the source to read frames")
