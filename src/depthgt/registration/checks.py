"""The failure checks of a registered frame set, shared by every registration method:
per neighbour (:func:`check_neighbours`: too few confident matches, a pose jump, a
correction of the source's pose beyond its bounds, a low inlier fraction, a degenerate
alignment, a high residual, a non-finite pose) and for the whole set
(:func:`set_status`). The thresholds: :class:`~depthgt.settings.CheckSettings`
(``RegistrationSettings.checks``; docs/method.md "Registration checks")."""

from __future__ import annotations

import numpy as np
import torch

from depthgt.metric_vocabulary import pose_delta
from depthgt.registration.settings import CheckSettings

__all__ = ["check_neighbours", "set_status"]


def check_neighbours(
    T: torch.Tensor, n_corr: torch.Tensor | None, refined, s: CheckSettings, T_start: torch.Tensor | None = None
) -> tuple[list[str], list[str]]:
    """Status ("ok" | "failed") and reasons of every neighbour (see
    :class:`~depthgt.settings.CheckSettings`).

    Args:
        T: (F, 4, 4) final poses in the target camera; n_corr: (F,) confident matches
            (None: no correspondence step, e.g. refined source poses); refined: the
            :class:`~depthgt.registration.refine.RefineResult` or None.
        T_start: (F, 4, 4) poses the refinement started from when they are a source's
            (method ``refine``): the correction T_start^-1 T must stay within
            ``max_correction_m`` / ``max_correction_deg``, else the refinement diverged.
    """
    statuses, reasons = [], []
    dt, dr = pose_delta(T[1:])
    if T_start is not None:
        ct, cr = pose_delta(torch.linalg.inv(T_start[1:].to(T.dtype)) @ T[1:])
    for i in range(T.shape[0] - 1):
        why = []
        if n_corr is not None and int(n_corr[i + 1]) < s.min_confident:
            why.append(f"too_few_confident_correspondences({int(n_corr[i + 1])}<{s.min_confident})")
        if dt[i] > s.max_translation_m or dr[i] > s.max_rotation_deg:
            why.append(f"pose_jump({dt[i]:.3f}m,{dr[i]:.1f}deg)")
        if T_start is not None and not (ct[i] <= s.max_correction_m and cr[i] <= s.max_correction_deg):
            why.append(f"large_correction({ct[i] * 100:.2f}cm,{cr[i]:.2f}deg)")
        if refined is not None:
            fr = float(refined.inlier_fraction[i + 1])
            cond = float(refined.condition[i + 1])
            if fr < s.min_inlier_fraction:
                why.append(f"low_inlier_fraction({fr:.2f})")
            if not cond < s.max_condition:
                why.append(f"degenerate_alignment(condition={cond:.3g})")
            res = float(refined.residual_m[i + 1])
            res_sig = float(refined.residual_sigmas[i + 1]) if refined.residual_sigmas is not None else float("nan")
            # NaN: nothing associated (or no noise estimate: the metric bound alone)
            if not (res <= s.max_residual_m or (s.max_residual_sigmas > 0 and res_sig <= s.max_residual_sigmas)):
                why.append(f"high_residual({res * 100:.2f}cm,{res_sig:.2f}sigma)")
        if not torch.isfinite(T[i + 1]).all():
            why.append("non_finite_pose")
        statuses.append("failed" if why else "ok")
        reasons.append(";".join(why))
    return statuses, reasons


def set_status(statuses: list[str], loss_curve: list[float], s: CheckSettings) -> tuple[str, str]:
    """Status of the whole set: failed when too few neighbours registered or when the
    training loss ``loss_curve`` did not decrease (the overfit registration without
    refinement passes its loss; a method whose poses are refined passes [])."""
    n_ok, n = statuses.count("ok"), len(statuses)
    status, reason = "ok", ""
    if len(loss_curve) >= 4:
        k = max(1, len(loss_curve) // 4)
        if np.mean(loss_curve[-k:]) > np.mean(loss_curve[:k]):
            status, reason = "failed", "loss_not_decreasing"
    if n_ok < s.min_ok_fraction * n:
        status = "failed"
        reason = ";".join(x for x in [reason, f"only {n_ok} of {n} neighbours registered"] if x)
    return status, reason
