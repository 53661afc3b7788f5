"""Random patch pairs cropped from a (input, GT) depth pair, with the missing filter.

Paper Sec. 4.1: 6 random 128x128 crops per 256x256 pair, kept when the missing ratio
is below 5 %. The paper does not say which image the ratio is measured on; the
default is the GT patch, configurable (``gt`` | ``input`` | ``both``). With
``max_gt_sigma_m`` the GT's per-pixel confidence (the ``S`` channel of gt.exr, an
expected standard deviation in metres) joins the filter: GT pixels less certain than
that are left out of the patch (set to 0) and count as missing.
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
        max_gt_sigma_m: GT pixels whose expected std (metres) exceeds this are left out
            of the GT patch and count as missing; None (default) keeps every GT pixel.
    """

    count: int = 6
    size: int = 128
    max_missing: float = 0.05
    filter_on: str = "gt"
    max_gt_sigma_m: float | None = None

    def __post_init__(self):
        if self.filter_on not in ("gt", "input", "both"):
            raise ValueError(f"patches.filter_on must be gt, input or both, got {self.filter_on!r}")
        if self.count < 1 or self.size < 1:
            raise ValueError(f"patches.count and patches.size must be >= 1, got {self.count}, {self.size}")
        if not 0.0 < self.max_missing <= 1.0:
            raise ValueError(f"patches.max_missing must be in (0, 1], got {self.max_missing}")
        if self.max_gt_sigma_m is not None and not self.max_gt_sigma_m > 0:
            raise ValueError(f"patches.max_gt_sigma_m must be null or > 0, got {self.max_gt_sigma_m}")


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
                 truth_m: np.ndarray | None = None, gt_sigma_m: np.ndarray | None = None) -> dict[str, np.ndarray]:
    """Crop ``settings.count`` pairs and keep those that pass the missing filter.

    Args:
        input_m: (H, W) float32 raw depth (0 = missing).
        gt_m: (H, W) float32 GT depth (0 = missing).
        rgb: (H, W, 3) uint8 colour.
        truth_m: optional (H, W) clean depth (synthetic sources).
        gt_sigma_m: optional (H, W) expected std of the GT in metres (gt.exr's ``S``);
            needed when ``settings.max_gt_sigma_m`` is set.

    Returns:
        Arrays ``input``, ``gt``, ``rgb``, ``boxes``, ``missing_input``, ``missing_gt``
        (and ``truth``, ``gt_sigma``) of the kept pairs, plus ``all_boxes``,
        ``all_missing_input``, ``all_missing_gt`` and ``kept`` (bool) for every drawn
        crop so that rejected crops are recorded, not lost.
    """
    if input_m.shape != gt_m.shape or rgb.shape[:2] != gt_m.shape:
        raise ValueError(f"input {input_m.shape}, gt {gt_m.shape} and rgb {rgb.shape} sizes differ")
    if gt_sigma_m is not None and gt_sigma_m.shape != gt_m.shape:
        raise ValueError(f"gt_sigma_m {gt_sigma_m.shape} and gt {gt_m.shape} sizes differ")
    if settings.max_gt_sigma_m is not None:
        if gt_sigma_m is None:
            raise ValueError("patches.max_gt_sigma_m is set but no GT confidence (gt_sigma_m) was given")
        gt_m = np.where(gt_sigma_m <= settings.max_gt_sigma_m, gt_m, 0).astype(gt_m.dtype)
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
    if gt_sigma_m is not None:
        out["gt_sigma"] = crop(gt_sigma_m, boxes)[keep].astype(np.float32)
    return out
