"""Depth-enhancement baselines behind one interface (paper Sec. 4.3).

Every baseline is a function ``f(depth_m, rgb, **params) -> (H, W) float32``:
``depth_m`` (H, W) float32 metres (0 = invalid), ``rgb`` (H, W, 3) uint8; the output
is depth in metres, 0 where the method leaves a pixel undefined. They are registered
by name in :data:`BASELINES`; :func:`run_baseline` checks the inputs and calls one.

* ``input``: the raw depth unchanged (the reference row of the tables).
* ``rgf``: rolling guidance filter (Zhang et al. ECCV 2014): a Gaussian-smoothed
  initial guidance, then joint bilateral iterations of the input guided by the last
  result, with OpenCV's filters (``cv2.GaussianBlur``, opencv-contrib's
  ``cv2.ximgproc.jointBilateralFilter``). Not ``cv2.ximgproc.rollingGuidanceFilter``
  itself: its first iteration guides with the input instead of the Gaussian-smoothed
  image (a bilateral filter that keeps the small structures the method removes), and
  it averages invalid (0 m) depth into its neighbours. Here invalid pixels are
  excluded by normalised convolution: the filter of (depth * valid, valid) as two
  channels with the same guidance, hence the same weights, divided.
* ``jf``: mutual-structure joint filtering (Shen et al. ICCV 2015), see :func:`jf`:
  written by hand because no maintained library has it (OpenCV's ``ximgproc`` has the
  one-way guided and joint filters, not the coupled two-way model); its box filters
  are kornia's.
* ``learned``: a network checkpoint written by :func:`depthgt.enhance.train.train`
  (LapDEN, RDE = LapDEN on another GT, DDRNet, SDD); ``checkpoint=`` is required.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
import torch
from kornia.color import rgb_to_grayscale

from depthgt.depth_ops import valid_avg_pool
from depthgt.enhance.train import load_model, predict_depth
from depthgt.shapes import check_shape

__all__ = ["BASELINES", "register_baseline", "run_baseline", "identity", "rgf", "jf", "learned", "box_fill"]

BASELINES: dict[str, Callable[..., np.ndarray]] = {}


def register_baseline(name: str):
    """Decorator registering ``f(depth_m, rgb, **params) -> (H, W) float32`` as ``name``."""

    def deco(fn):
        if name in BASELINES:
            raise ValueError(f"baseline {name!r} registered twice")
        BASELINES[name] = fn
        return fn

    return deco


def _check_inputs(depth_m: np.ndarray, rgb: np.ndarray | None) -> tuple[np.ndarray, np.ndarray | None]:
    d = np.asarray(depth_m)
    sizes = check_shape(d, "H W", "depth_m")
    d = np.nan_to_num(d.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    d[d < 0] = 0.0
    if rgb is not None:
        rgb = np.asarray(rgb)
        check_shape(rgb, "H W 3", "rgb", sizes)
    return d, rgb


def run_baseline(name: str, depth_m: np.ndarray, rgb: np.ndarray | None, **params) -> np.ndarray:
    """Run the baseline ``name`` on one frame; returns (H, W) float32 metres."""
    if name not in BASELINES:
        raise ValueError(f"unknown baseline {name!r}; known: {sorted(BASELINES)}")
    d, rgb = _check_inputs(depth_m, rgb)
    out = BASELINES[name](d, rgb, **params)
    out = np.asarray(out, dtype=np.float32)
    if out.shape != d.shape:
        raise RuntimeError(f"baseline {name!r} returned {out.shape}, expected {d.shape}")
    return out


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))[None, None]


@register_baseline("input")
def identity(depth_m: np.ndarray, rgb: np.ndarray | None = None) -> np.ndarray:
    """The raw depth, unchanged."""
    return np.asarray(depth_m, dtype=np.float32).copy()


def box_fill(depth: torch.Tensor, valid: torch.Tensor, kernel: int = 5, max_iter: int = 1000) -> torch.Tensor:
    """Fill holes by repeated normalised box filtering (:func:`depthgt.depth_ops.valid_avg_pool`
    with stride 1; each pass grows the filled
    region by ``kernel // 2`` pixels; valid pixels are kept).

    Args:
        depth: (B, 1, H, W); valid: (B, 1, H, W) bool.

    Returns:
        (B, 1, H, W), every pixel filled unless an image has no valid pixel.
    """
    d = torch.where(valid, depth, torch.zeros_like(depth))
    w = valid.to(depth.dtype)
    for _ in range(max_iter):
        if bool((w > 0).all()):
            break
        mean, ok = valid_avg_pool(d, w, kernel, stride=1, padding=kernel // 2, count_include_pad=False)
        new = (w == 0) & ok
        d = torch.where(new, mean, d)
        w = torch.where(new, torch.ones_like(w), w)
    return d


@register_baseline("rgf")
def rgf(
    depth_m: np.ndarray, rgb: np.ndarray | None = None, sigma_s: float = 3.0, sigma_r: float = 0.05, iterations: int = 4
) -> np.ndarray:
    """Rolling guidance filter of depth with invalid pixels excluded (OpenCV filters).

    Args:
        depth_m: (H, W) metres, 0 = invalid. rgb: unused (RGF guides with itself).
        sigma_s: spatial sigma (pixels); the kernel is 2*ceil(2*sigma_s)+1 wide.
        sigma_r: range sigma (metres).
        iterations: joint bilateral iterations after the Gaussian guidance.

    Returns:
        (H, W) float32 metres; holes are filled where a valid pixel lies within the
        kernel, 0 elsewhere.
    """
    if sigma_s <= 0 or sigma_r <= 0 or iterations < 0:
        raise ValueError(
            f"rgf: sigma_s, sigma_r must be > 0 and iterations >= 0, got {sigma_s}, {sigma_r}, {iterations}"
        )
    d = np.ascontiguousarray(depth_m, dtype=np.float32)
    valid = (d > 0).astype(np.float32)
    k = 2 * math.ceil(2 * sigma_s) + 1
    # (depth * valid, valid, 0): one filter call gives numerator and denominator with the same weights
    stack = np.ascontiguousarray(np.stack([d * valid, valid, np.zeros_like(d)], axis=-1))

    def normalised(filtered: np.ndarray) -> np.ndarray:
        num, den = filtered[..., 0], filtered[..., 1]
        return np.where(den > 1e-6, num / np.maximum(den, 1e-12), 0.0).astype(np.float32)

    J = normalised(cv2.GaussianBlur(stack, (k, k), sigma_s, sigmaY=sigma_s, borderType=cv2.BORDER_REFLECT_101))
    for _ in range(iterations):
        J = normalised(
            cv2.ximgproc.jointBilateralFilter(J, stack, k, sigma_r, sigma_s, borderType=cv2.BORDER_REFLECT_101)
        )
    return J


@register_baseline("jf")
def jf(
    depth_m: np.ndarray,
    rgb: np.ndarray,
    r: int = 3,
    eps_I: float = 1e-4,
    eps_G: float = 5e-4,
    lambda_I: float = 1.0,
    lambda_G: float = 30.0,
    iterations: int = 20,
) -> np.ndarray:
    """Mutual-structure joint filtering of depth I with the grey image G.

    The energy (Shen et al. 2015) couples I and G by local linear models in every
    (2r+1)^2 window k in both directions, with fidelity to the inputs I0, G0::

        E = sum_k sum_{i in w_k} [(a_k I_i + b_k - G_i)^2 + (c_k G_i + e_k - I_i)^2]
            + eps_I sum_k a_k^2 + eps_G sum_k c_k^2
            + lambda_I sum_i (I_i - I0_i)^2 + lambda_G sum_i (G_i - G0_i)^2

    solved by alternation: with I, G fixed, (a, b) and (c, e) are guided-filter
    regressions (OpenCV's box filter, in float64); with them fixed, the normal equations of each pixel
    are a 2x2 linear system in (I_i, G_i) whose coefficients are window averages of
    a^2, a, a b, ... (the structure term is averaged over the windows that cover a
    pixel, so lambda weighs against 1). Depth is scaled by its maximum to [0, 1] so
    that the authors' eps apply; holes are pre-filled by normalised box filtering and
    carry no fidelity term (lambda_I = 0 there).

    Args:
        depth_m: (H, W) metres; rgb: (H, W, 3) uint8.
        r, eps_I, eps_G, lambda_I, lambda_G, iterations: the authors' RGB-D values
        by default.

    Returns:
        (H, W) float32 metres, every pixel filled (0 only if the input is empty).
    """
    if rgb is None:
        raise ValueError("jf needs the rgb image as guidance")
    d = _t(depth_m)
    valid = d > 0
    if not valid.any():
        return np.zeros_like(depth_m, dtype=np.float32)
    scale = float(d[valid].max())
    # float64: the alternation amplifies rounding (in float32, 20 iterations of kornia's box blur
    # end up to 16 cm from the float64 result on a 256x256 frame, OpenCV's 1.3 mm)
    I0 = box_fill(d / scale, valid)[0, 0].numpy().astype(np.float64)
    G0 = rgb_to_grayscale(torch.from_numpy(np.ascontiguousarray(rgb)).permute(2, 0, 1)[None].float() / 255.0)
    G0 = G0[0, 0].numpy().astype(np.float64)
    lam_I = lambda_I * valid[0, 0].numpy().astype(np.float64)
    k = 2 * r + 1

    def box(x):  # OpenCV's mean filter (reflect-101 border as kornia's "reflect"): ~5x faster on one thread
        return cv2.boxFilter(x, -1, (k, k), normalize=True, borderType=cv2.BORDER_REFLECT_101)

    I, G = I0.copy(), G0.copy()  # noqa: E741 (the paper's names: I the depth, G the guide)
    for _ in range(iterations):
        mI, mG = box(I), box(G)
        cov = box(I * G) - mI * mG
        var_I = np.maximum(box(I * I) - mI * mI, 0.0)
        var_G = np.maximum(box(G * G) - mG * mG, 0.0)
        a = cov / (var_I + eps_I)  # G ~ a I + b
        b = mG - a * mI
        c = cov / (var_G + eps_G)  # I ~ c G + e
        e = mI - c * mG
        A, AA, AB = box(a), box(a * a), box(a * b)
        C, CC, CE = box(c), box(c * c), box(c * e)
        B, E = box(b), box(e)
        # [p11 p12; p12 p22] [I; G] = [q1; q2]
        p11 = AA + 1.0 + lam_I
        p22 = 1.0 + CC + lambda_G
        p12 = -(A + C)
        q1 = -AB + E + lam_I * I0
        q2 = B - CE + lambda_G * G0
        det = p11 * p22 - p12 * p12
        I = (p22 * q1 - p12 * q2) / det  # noqa: E741
        G = (p11 * q2 - p12 * q1) / det
    return np.maximum(I * scale, 0.0).astype(np.float32)


@lru_cache(maxsize=8)
def _cached_model(checkpoint: str, device: str):
    return load_model(checkpoint, device)


@register_baseline("learned")
def learned(
    depth_m: np.ndarray, rgb: np.ndarray | None = None, checkpoint: str | Path | None = None, device: str = "cpu"
) -> np.ndarray:
    """Enhance with a trained network checkpoint (LapDEN, RDE, DDRNet, SDD).

    Args:
        depth_m: (H, W) metres; rgb: unused (the networks take depth only).
        checkpoint: a ``best.pt``/``last.pt`` written by ``train``.
        device: where to run it.
    """
    if checkpoint is None:
        raise ValueError("learned baseline needs checkpoint=<path to best.pt>")
    model = _cached_model(str(Path(checkpoint).resolve()), device)
    return predict_depth(model, depth_m)
