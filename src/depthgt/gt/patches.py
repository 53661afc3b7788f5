"""Random patch pairs cropped from a (input, GT) depth pair, with the missing filter.

Paper Sec. 4.1: 6 random 128x128 crops per 256x256 pair, kept when the missing ratio
is below 5 %. The paper does not say which image the ratio is measured on; the
default is the GT patch, configurable (``gt`` | ``input`` | ``both``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class PatchSettings:
    """Attributes:
        count: crops drawn per frame (paper: 6).
        size: square patch side in pixels (paper: 128).
        max_missing: a pair is kept when its missing ratio is strictly below this.
        filter_on: which image's missing ratio decides ("gt", "input" or "both").
    """

    count: int = 6
    size: int = 128
    max_missing: float = 0.05
    filter_on: str = "gt"

    def __post_init__(self):
        if self.filter_on not in ("gt", "input", "both"):
            raise ValueError(f"patches.filter_on must be gt, input or both, got {self.filter_on!r}")
        if self.count < 1 or self.size < 1:
            raise ValueError(f"patches.count and patches.size must be >= 1, got {self.count}, {self.size}")
        if not 0.0 < self.max_missing <= 1.0:
            raise ValueError(f"patches.max_missing must be in (0, 1], got {self.max_missing}")


def crop_boxes(hw: tuple[int, int], settings: PatchSettings, rng: np.random.Generator) -> np.ndarray:
    """(count, 4) int boxes (y0, x0, h, w) drawn uniformly inside an image of size ``hw``."""
    h, w = hw
    if settings.size > h or settings.size > w:
        raise ValueError(f"patch size {settings.size} does not fit in a {w}x{h} image")
    y0 = rng.integers(0, h - settings.size + 1, size=settings.count)
    x0 = rng.integers(0, w - settings.size + 1, size=settings.count)
    s = np.full(settings.count, settings.size)
    return np.stack([y0, x0, s, s], axis=1).astype(np.int64)


def crop(image: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """Stack of crops (P, size, size, ...) of ``image`` (H, W, ...) at ``boxes``.

    Vectorised gather: one fancy index instead of a loop over boxes.
    """
    size = int(boxes[0, 2]) if len(boxes) else 0
    ar = np.arange(size)
    rows = boxes[:, 0, None] + ar[None]  # (P, s)
    cols = boxes[:, 1, None] + ar[None]
    return image[rows[:, :, None], cols[:, None, :]]


def make_patches(input_m: np.ndarray, gt_m: np.ndarray, rgb: np.ndarray, settings: PatchSettings, rng: np.random.Generator,
                 truth_m: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Crop ``settings.count`` pairs and keep those that pass the missing filter.

    Args:
        input_m: (H, W) float32 raw depth (0 = missing).
        gt_m: (H, W) float32 GT depth (0 = missing).
        rgb: (H, W, 3) uint8 colour.
        truth_m: optional (H, W) clean depth (synthetic sources).

    Returns:
        Arrays ``input``, ``gt``, ``rgb``, ``boxes``, ``missing_input``, ``missing_gt``
        (and ``truth``) of the kept pairs, plus ``all_boxes``, ``all_missing_input``,
        ``all_missing_gt`` and ``kept`` (bool) for every drawn crop so that rejected
        crops are recorded, not lost.
    """
    if input_m.shape != gt_m.shape or rgb.shape[:2] != gt_m.shape:
        raise ValueError(f"input {input_m.shape}, gt {gt_m.shape} and rgb {rgb.shape} sizes differ")
    boxes = crop_boxes(gt_m.shape, settings, rng)
    p_in, p_gt = crop(input_m, boxes), crop(gt_m, boxes)
    miss_in = (p_in <= 0).mean(axis=(1, 2))
    miss_gt = (p_gt <= 0).mean(axis=(1, 2))
    if settings.filter_on == "gt":
        keep = miss_gt < settings.max_missing
    elif settings.filter_on == "input":
        keep = miss_in < settings.max_missing
    else:
        keep = (miss_gt < settings.max_missing) & (miss_in < settings.max_missing)
    out = {
        "input": p_in[keep].astype(np.float32),
        "gt": p_gt[keep].astype(np.float32),
        "rgb": crop(rgb, boxes)[keep].astype(np.uint8),
        "boxes": boxes[keep],
        "missing_input": miss_in[keep].astype(np.float32),
        "missing_gt": miss_gt[keep].astype(np.float32),
        "all_boxes": boxes,
        "all_missing_input": miss_in.astype(np.float32),
        "all_missing_gt": miss_gt.astype(np.float32),
        "kept": keep,
    }
    if truth_m is not None:
        out["truth"] = crop(truth_m, boxes)[keep].astype(np.float32)
    return out
