"""Reading the built frame sets back: the one reader of the frame-set outputs.

Everything that reads a frame set's outputs after it was built (a person inspecting
it, the ``depthgt show`` command, extraction to plain files) goes through
:func:`read_frameset`, so that the on-disk layout can change in one place.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from depthgt import io
from depthgt.errors import DepthGTError

__all__ = ["FrameSetRecord", "frameset_dir", "read_frameset", "extract_frameset"]


@dataclass
class FrameSetRecord:
    """The outputs of one built frame set.

    Attributes:
        gt_m: (H, W) float32 GT depth in metres (0 = none).
        gt_sigma_m: (H, W) float32 expected standard deviation of the GT in metres.
        gt_weight: (H, W) float32 weight sum of the fused samples.
        gt_count: (H, W) float32 number of fused samples.
        input_m: (H, W) float32 resized raw target depth (0 = none).
        truth_m: (H, W) float32 clean depth (synthetic sources) or None.
        rgb: (H, W, 3) uint8 target colour.
        poses: poses.json's content.
        meta: frameset.json's content (split, frame ids, K, statistics, status).
        patches: patches.npz's arrays.
    """

    gt_m: np.ndarray
    gt_sigma_m: np.ndarray
    gt_weight: np.ndarray
    gt_count: np.ndarray
    input_m: np.ndarray
    truth_m: np.ndarray | None
    rgb: np.ndarray
    poses: dict[str, Any]
    meta: dict[str, Any]
    patches: dict[str, np.ndarray]


def frameset_dir(results: str | Path, dataset: str, scene: str, target: int) -> Path:
    """The folder of one frame set's outputs under the results folder."""
    return Path(results) / "framesets" / dataset / scene / f"{int(target):06d}"


def read_frameset(results: str | Path, dataset: str, scene: str, target: int) -> FrameSetRecord:
    """Read one built frame set.

    Raises:
        DepthGTError: the frame set was not built (the message names the path).
    """
    d = frameset_dir(results, dataset, scene, target)
    if not (d / "frameset.json").is_file():
        raise DepthGTError(f"frame set {dataset}/{scene}/{int(target):06d} not built: no {d / 'frameset.json'}")
    gt = io.read_exr(d / "gt.exr")
    inp = io.read_exr(d / "input.exr")
    with np.load(d / "patches.npz") as z:
        patches = {k: z[k] for k in z.files}
    return FrameSetRecord(
        gt_m=gt["Z"], gt_sigma_m=gt.get("S", np.zeros_like(gt["Z"])), gt_weight=gt["W"], gt_count=gt["N"],
        input_m=inp["Z"], truth_m=inp.get("T"), rgb=io.read_rgb(d / "rgb.png"),
        poses=json.loads((d / "poses.json").read_text()), meta=json.loads((d / "frameset.json").read_text()),
        patches=patches)


def extract_frameset(results: str | Path, dataset: str, scene: str, target: int, dest: str | Path) -> list[Path]:
    """Copy one built frame set's files (gt.exr, input.exr, rgb.png, poses.json,
    patches.npz, frameset.json) into ``dest``; returns the written paths."""
    d = frameset_dir(results, dataset, scene, target)
    read_frameset(results, dataset, scene, target)  # checks it was built
    dest = Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    written = []
    for name in ("gt.exr", "input.exr", "rgb.png", "poses.json", "patches.npz", "frameset.json"):
        shutil.copyfile(d / name, dest / name)
        written.append(dest / name)
    return written
