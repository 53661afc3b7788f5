"""Figures: method comparison rows (paper Figs. 5-7), training curves and one frame set's panel.

matplotlib is imported lazily with the Agg backend (no display needed).
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path

import numpy as np
import pandas as pd

from depthgt.gt import store

__all__ = ["shared_depth_range", "comparison_figure", "training_curve", "frameset_panel"]


def _plt():
    import matplotlib  # heavy (and its backend must be chosen before pyplot): only for drawing

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(plt, fig, out_path: str | Path, dpi: int = 100) -> Path:
    """Lay out, write (creating the folder) and close a figure."""
    fig.tight_layout()
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def shared_depth_range(images: list[np.ndarray], lo_pct: float = 1.0, hi_pct: float = 99.0) -> tuple[float, float]:
    """(vmin, vmax) in metres from the valid (> 0) pixels of all images (percentiles,
    so that a few outliers do not flatten the colours); (0, 1) when none is valid."""
    vals = np.concatenate([np.asarray(im)[np.asarray(im) > 0].ravel() for im in images] + [np.empty(0, np.float32)])
    if vals.size == 0:
        return 0.0, 1.0
    lo, hi = np.percentile(vals, [lo_pct, hi_pct])
    return float(lo), float(max(hi, lo + 1e-3))


def comparison_figure(
    frames: pd.DataFrame, pred_dirs: Mapping[str, str | Path], out_path: str | Path, frames_per_scene: int = 2
) -> Path:
    """One row per test frame: RGB | input | each method | GT (| truth when known).

    Depth panels share one colour range per row (the row's valid depths, 1st-99th
    percentile), invalid pixels (0) black. Predictions are read from
    ``{pred_dirs[method]}/{dataset}/{scene}/{target:06d}.npy``.

    Args:
        frames: frame-set rows (dataset, scene, target, frameset) to choose from;
            up to ``frames_per_scene`` evenly spaced frames of each scene are shown.
    """
    plt = _plt()
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    picked = []
    for _, group in frames.sort_values(["dataset", "scene", "target"]).groupby(["dataset", "scene"], sort=False):
        idx = np.unique(np.linspace(0, len(group) - 1, min(frames_per_scene, len(group))).round().astype(int))
        picked.extend(group.iloc[idx].itertuples())
    methods = list(pred_dirs)
    if not picked:
        fig, ax = plt.subplots(figsize=(6, 1))
        ax.axis("off")
        ax.text(0.5, 0.5, "no test frame set", ha="center", va="center")
        fig.savefig(out, dpi=80)
        plt.close(fig)
        return out
    has_truth = any(store.read_frame_images(r.frameset).truth_m is not None for r in picked)
    titles = ["RGB", "input"] + methods + ["depthgt GT"] + (["truth"] if has_truth else [])
    n_cols = len(titles)
    fig, axes = plt.subplots(len(picked), n_cols, figsize=(1.9 * n_cols, 2.0 * len(picked) + 0.4), squeeze=False)
    cmap = plt.get_cmap("turbo").copy()
    cmap.set_bad("black")
    image = None
    for row, rec in enumerate(picked):
        fr = store.read_frame_images(rec.frameset)
        preds = []
        for m in methods:
            p = Path(pred_dirs[m]) / str(rec.dataset) / str(rec.scene) / f"{int(rec.target):06d}.npy"
            preds.append(np.load(p) if p.is_file() else np.zeros_like(fr.input_m))
        depths = [fr.input_m, *preds, fr.gt_m] + (
            [fr.truth_m if fr.truth_m is not None else np.zeros_like(fr.gt_m)] if has_truth else []
        )
        vmin, vmax = shared_depth_range(depths)
        axes[row, 0].imshow(fr.rgb)
        for col, d in enumerate(depths, start=1):
            image = axes[row, col].imshow(np.ma.masked_less_equal(d, 0), cmap=cmap, vmin=vmin, vmax=vmax)
        axes[row, 0].set_ylabel(f"{rec.dataset}/{rec.scene}\n{int(rec.target):06d}", fontsize=7)
        for col in range(n_cols):
            axes[row, col].set_xticks([])
            axes[row, col].set_yticks([])
            if row == 0:
                axes[row, col].set_title(titles[col], fontsize=8)
        fig.colorbar(image, ax=axes[row, -1], fraction=0.046, pad=0.04, label="m")
    fig.tight_layout()
    fig.savefig(out, dpi=100)
    plt.close(fig)
    return out


def training_curve(loss_log: str | Path, out_path: str | Path, title: str = "") -> Path:
    """Train and validation total loss per epoch from a ``loss_log.csv``."""
    plt = _plt()
    log = pd.read_csv(loss_log)
    if not {"epoch", "split", "total"} <= set(log.columns):
        raise ValueError(f"{loss_log}: needs columns epoch, split, total (has {list(log.columns)})")
    fig, ax = plt.subplots(figsize=(4.5, 3.0))
    for split, group in log.groupby("split"):
        ax.plot(group["epoch"], group["total"], marker="o", label=split)
    ax.set_xlabel("epoch")
    ax.set_ylabel("loss (total)")
    ax.set_yscale("log")
    ax.set_title(title)
    ax.legend()
    return _save(plt, fig, out_path)


def frameset_panel(rec, out_path: str | Path, title: str = "") -> Path:
    """One built frame set side by side: RGB | input | GT | confidence (| truth).

    Args:
        rec: a :class:`depthgt.gt.store.FrameSetRecord`.
        out_path: PNG path.

    Depth panels share one colour range (metres; missing depth in black); the confidence
    panel shows the GT's expected standard deviation in millimetres.
    """
    plt = _plt()
    depths = [("input", rec.input_m), ("GT", rec.gt_m)] + ([("truth", rec.truth_m)] if rec.truth_m is not None else [])
    vmin, vmax = shared_depth_range([d for _, d in depths])
    sigma_mm = np.where(rec.gt_m > 0, rec.gt_sigma_m * 1000.0, np.nan)
    n = 2 + len(depths)
    fig, axes = plt.subplots(1, n, figsize=(2.6 * n, 2.9))
    axes[0].imshow(rec.rgb)
    axes[0].set_title("RGB")
    cmap = plt.get_cmap("turbo").copy()
    cmap.set_bad("black")
    panels = [depths[0], depths[1], ("confidence: std (mm)", sigma_mm)] + depths[2:]
    for ax, (name, img) in zip(axes[1:], panels):
        if name.startswith("confidence"):
            finite = sigma_mm[np.isfinite(sigma_mm)]
            hi = float(np.percentile(finite, 99)) if finite.size else 1.0
            im = ax.imshow(np.ma.masked_invalid(img), cmap=cmap, vmin=0.0, vmax=max(hi, 1e-3))
            fig.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
        else:
            ax.imshow(np.ma.masked_less_equal(img, 0), cmap=cmap, vmin=vmin, vmax=vmax)
        ax.set_title(name)
    for ax in axes:
        ax.axis("off")
    if title:
        fig.suptitle(title)
    return _save(plt, fig, out_path)
