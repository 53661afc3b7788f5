"""Losses of the depth-enhancement networks (LapDEN as in the paper, Sec. 3.3).

L = L_D(y_hat, y) + lambda_s * L_S(y_hat, y), summed over the pyramid levels:

* L_D: L1 on depth + L1 on the depth gradient + L1 on the surface normal (normals
  from depth and intrinsics, :func:`depthgt.depth_ops.depth_normals`: kornia's
  ``depth_to_normals`` without its slow convolution on CPU);
* L_S (paper eq. 6, :func:`depthgt.depth_ops.structure_loss`): mean over pixels p of
  ``(max_{q in W(p)} |grad y_hat_q| - max_{q in W(p)} |grad y_q|)^2``, W a 5x5
  window; the paper's change: the GT y replaces the raw input x; lambda_s = 5.

Optionally (``sigma_ref_m``, beyond the paper) the depth term is weighted per pixel by
the GT's confidence: ``w = sigma_ref^2 / (sigma_ref^2 + sigma^2)`` with ``sigma`` the
GT's expected std (gt.exr's ``S``, the batch's ``sigma``), so that GT pixels the
renderer is unsure of (few samples, surfaces split by the agreement check) pull less;
a weighted mean, so the term's scale does not change.

Optionally (``hole_weight``, beyond the paper) the depth term weights the GT pixels where
the raw input has no depth (the filling task) ``hole_weight`` times as much as those
where it has (the batch's ``input``), times the confidence weight when both are set.

Supervision only where the GT is valid (> 0): depth terms on valid GT pixels,
gradient terms on pixels whose forward neighbours are valid too, normal terms on
pixels whose 3x3 neighbourhood (the Sobel support of the normals) is valid.
Coarser levels are supervised with the GT average-pooled over its valid pixels and
the intrinsics rescaled to that level.

Every loss function takes ``(outputs, batch)``: ``outputs`` a list of depth maps
(B, 1, h, w) in metres, finest last; ``batch`` a dict with ``input`` (B,1,H,W) raw
depth, ``gt`` (B,1,H,W) GT depth (0 = none), ``K`` (B,3,3) intrinsics of the
(H, W) images, ``rgb`` (B,3,H,W) in [0,1]; and returns ``(total, terms)`` with
``terms`` a dict of floats for the loss log.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import torch

from depthgt.depth_ops import (
    depth_normals,
    forward_gradients,
    masked_avg_pool,
    masked_mean,
    structure_loss,
    window_max,
)
from depthgt.geometry import scale_intrinsics
from depthgt.shapes import check_shape

__all__ = [
    "LossConfig",
    "depth_l1",
    "confidence_weight",
    "gradient_l1",
    "normal_l1",
    "lapden_loss",
    "lapden_loss_from_params",
]


@dataclass(frozen=True)
class LossConfig:
    """Weights of the LapDEN loss.

    Attributes:
        w_depth, w_grad, w_normal: weights of the three L_D terms.
        lambda_s: weight of L_S (the paper: 5, the original LapDEN: 10).
        window: side of the max window of L_S (pixels, odd).
        scale_weights: weight of each pyramid level, coarse to fine.
        sigma_ref_m: None (the paper): every valid GT pixel counts alike in the depth
            term; metres: each is weighted by ``sigma_ref_m^2 / (sigma_ref_m^2 +
            sigma^2)`` (the batch must carry ``sigma``); coarser levels take the mean
            weight of their valid fine pixels.
        hole_weight: weight of the depth term on GT pixels where the input has no depth,
            relative to 1 where it has (1: the paper, every pixel alike).
    """

    w_depth: float = 1.0
    w_grad: float = 1.0
    w_normal: float = 1.0
    lambda_s: float = 5.0
    window: int = 5
    scale_weights: tuple[float, ...] = (1.0, 1.0, 1.0)
    sigma_ref_m: float | None = None
    hole_weight: float = 1.0

    def __post_init__(self):
        if self.sigma_ref_m is not None and not (math.isfinite(self.sigma_ref_m) and self.sigma_ref_m > 0):
            raise ValueError(f"loss_params.sigma_ref_m must be null or a finite number > 0, got {self.sigma_ref_m}")
        if isinstance(self.hole_weight, bool) or not (
            isinstance(self.hole_weight, (int, float)) and math.isfinite(self.hole_weight) and self.hole_weight > 0
        ):
            raise ValueError(f"loss_params.hole_weight must be a finite number > 0, got {self.hole_weight!r}")


def depth_l1(
    pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor, weight: torch.Tensor | None = None
) -> torch.Tensor:
    """Mean |pred - gt| (metres) over valid GT pixels, weighted by ``weight`` (B, 1, H,
    W) when given. pred, gt, valid: (B, 1, H, W)."""
    if weight is None:
        return masked_mean((pred - gt).abs(), valid)
    w = weight * valid.to(weight.dtype)
    return ((pred - gt).abs() * w).sum() / w.sum().clamp_min(1e-12)


def confidence_weight(sigma: torch.Tensor, sigma_ref_m: float) -> torch.Tensor:
    """``sigma_ref^2 / (sigma_ref^2 + sigma^2)``: 1 for a certain GT pixel, 1/2 at
    ``sigma == sigma_ref_m``. sigma: (B, 1, H, W) metres."""
    s2 = sigma_ref_m * sigma_ref_m
    return s2 / (s2 + sigma * sigma)


def gradient_l1(pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Mean L1 of the forward-difference gradient error, x and y terms averaged over
    their own valid pixels and summed. Inputs (B, 1, H, W); metres per pixel."""
    pgx, pgy, _, _ = forward_gradients(pred, valid)
    ggx, ggy, vx, vy = forward_gradients(gt, valid)
    return masked_mean((pgx - ggx).abs(), vx) + masked_mean((pgy - ggy).abs(), vy)


def normal_l1(pred: torch.Tensor, gt: torch.Tensor, valid: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Mean over valid pixels of ||n_pred - n_gt||_1 (unit normals, :func:`depth_normals`).

    Args:
        pred, gt: (B, 1, H, W) metres; valid: (B, 1, H, W) bool; K: (B, 3, 3) at (H, W).
    """
    check_shape(K, "B 3 3", "K", {"B": pred.shape[0]})
    K = K.to(pred.dtype)
    n_pred = depth_normals(pred, K)
    n_gt = depth_normals(gt, K)
    # the Sobel support of the normal is 3x3: all of it must be valid GT
    v = valid.to(pred.dtype)
    v3 = 1.0 - window_max(1.0 - v, 3)
    return masked_mean((n_pred - n_gt).abs().sum(dim=1, keepdim=True), v3 > 0.5)


def _level_targets(gt: torch.Tensor, K: torch.Tensor, shape_hw: tuple[int, int], weight: torch.Tensor | None = None):
    H, W = gt.shape[-2:]
    factor = H // shape_hw[0]
    if factor * shape_hw[0] != H or factor * shape_hw[1] != W:
        raise ValueError(f"output size {shape_hw} is not an integer fraction of the GT size {(H, W)}")
    gt_l, valid_l = masked_avg_pool(gt, gt > 0, factor)
    K_l = scale_intrinsics(K, (H, W), shape_hw) if factor > 1 else K
    w_l = None if weight is None else masked_avg_pool(weight, gt > 0, factor)[0]
    return gt_l, valid_l, K_l, w_l


def lapden_loss(outputs: list[torch.Tensor], batch: dict, config: LossConfig = LossConfig()):
    """The paper's LapDEN loss summed over pyramid levels (see module docstring).

    Args:
        outputs: list of (B, 1, h_l, w_l) predictions, coarse to fine; finest at GT size.
        batch: dict with ``gt`` (B, 1, H, W) and ``K`` (B, 3, 3) (and ``sigma`` (B, 1,
            H, W) with ``config.sigma_ref_m``, ``input`` (B, 1, H, W) with
            ``config.hole_weight``).

    Returns:
        (total loss tensor, dict of float terms summed over levels: depth, grad,
        normal, structure, total).
    """
    if isinstance(outputs, torch.Tensor):
        outputs = [outputs]
    gt, K = batch["gt"], batch["K"]
    check_shape(gt, "B 1 H W", "batch['gt']")
    weights = config.scale_weights[-len(outputs) :]
    if len(weights) != len(outputs):
        raise ValueError(f"{len(outputs)} outputs but only {len(config.scale_weights)} scale_weights")
    weight = None
    if config.sigma_ref_m is not None:
        if "sigma" not in batch:
            raise ValueError(
                "loss_params.sigma_ref_m is set but the batch has no 'sigma' (the GT's expected std): "
                "train on a depthgt GT (gt.exr channel S), not on one without a confidence image"
            )
        weight = confidence_weight(batch["sigma"].to(gt.dtype), config.sigma_ref_m)
    if config.hole_weight != 1.0:
        if "input" not in batch:
            raise ValueError("loss_params.hole_weight is set but the batch has no 'input' (the raw depth)")
        holes = (batch["input"] <= 0).to(gt.dtype)
        hw = 1.0 + (float(config.hole_weight) - 1.0) * holes
        weight = hw if weight is None else weight * hw
    total = gt.new_zeros(())
    names = ("depth", "grad", "normal", "structure")
    level_terms = []
    for w_l, pred in zip(weights, outputs):
        gt_l, valid_l, K_l, cw_l = _level_targets(gt, K, tuple(pred.shape[-2:]), weight)
        t_d = depth_l1(pred, gt_l, valid_l, cw_l)
        t_g = gradient_l1(pred, gt_l, valid_l)
        t_n = normal_l1(pred, gt_l, valid_l, K_l)
        t_s = structure_loss(pred, gt_l, valid_l, config.window)
        level = config.w_depth * t_d + config.w_grad * t_g + config.w_normal * t_n + config.lambda_s * t_s
        total = total + w_l * level
        level_terms.append(torch.stack([t_d, t_g, t_n, t_s]))
    # read once at the end (one host read; the loss stays one traceable graph for torch.compile),
    # summed over the levels in Python as the float terms were
    values = torch.stack([*level_terms, total.expand(len(names))]).detach().tolist()
    terms = {k: sum(w_l * row[i] for w_l, row in zip(weights, values[:-1])) for i, k in enumerate(names)}
    terms["total"] = values[-1][0]
    return total, terms


def _loss_config(**params) -> LossConfig:
    if "scale_weights" in params:
        params = {**params, "scale_weights": tuple(params["scale_weights"])}
    unknown = sorted(set(params) - {f.name for f in fields(LossConfig)})
    if unknown:
        raise TypeError(f"unknown LapDEN loss parameters {unknown}; known: {[f.name for f in fields(LossConfig)]}")
    return LossConfig(**params)


def lapden_loss_from_params(outputs: list[torch.Tensor], batch: dict, **params):
    """:func:`lapden_loss` with the config's ``loss_params`` (:class:`LossConfig` fields)
    as keywords: the registry's loss of ``lapden`` (:data:`depthgt.registry.MODELS`)."""
    return lapden_loss(outputs, batch, _loss_config(**params))


#: the training checks ``loss_params`` with this before the first batch
lapden_loss_from_params.check_params = _loss_config
