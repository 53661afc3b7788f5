"""Local refinement of a source's poses on the frame set (``registration.method: refine``).

Poses from another system -- a global reconstruction (ScanNet, 7-Scenes) or motion
capture (TUM) -- are right globally and misaligned locally: a small error of the
calibration between the tracker and the camera, the time between the pose and the
depth image, drift that a global optimisation spread over the scene. The joint SE(3)
refinement of :mod:`depthgt.registration.refine` (the consistency terms of every pair
of the set, paper eq. 4) starts from them; the paper's thesis in its cheapest form, with
no encoder and no correspondence search. Every neighbour goes through the checks of the
overfit registration (inliers, condition, residual against the frame set's own noise)
and a bound on the correction: one that moved further than ``max_correction_m`` /
``max_correction_deg`` from its source pose diverged and is left out.
"""

from __future__ import annotations

import time

import torch

from depthgt.framecache import FrameCache
from depthgt.registration.checks import check_neighbours, set_status
from depthgt.registration.frameset import FrameSetData, poses_from_source
from depthgt.registration.refine import RefineResult, RefineSet, refine_poses, refine_poses_many
from depthgt.registration.result import RegistrationResult
from depthgt.registration.settings import RegistrationSettings
from depthgt.shapes import check_shape

__all__ = ["register_refine", "refine_source_poses", "refine_source_poses_many"]


def register_refine(
    data: FrameSetData,
    offsets: list[int],
    settings: RegistrationSettings,
    *,
    seed: int = 0,
    encoder_state: dict | None = None,
) -> RegistrationResult:
    """The source's poses of the neighbours refined on the frame set
    (:func:`refine_source_poses`; :class:`~depthgt.registration.frameset.Registration`,
    deterministic: ``seed`` and ``encoder_state`` are not used).

    Raises:
        FrameError: the source has no finite poses for the members ("missing_pose").
    """
    return refine_source_poses(
        data.rgb,
        data.depth_m,
        data.K,
        offsets,
        poses_from_source(data),
        settings,
        cache=data.cache,
        positions=data.positions,
    )


def refine_source_poses(
    rgb: torch.Tensor,
    depth_m: torch.Tensor,
    K: torch.Tensor,
    offsets: list[int],
    T_j_to_t: torch.Tensor,
    settings: RegistrationSettings = RegistrationSettings(method="refine"),
    *,
    cache: FrameCache | None = None,
    positions: tuple[int, ...] | None = None,
) -> RegistrationResult:
    """Refine the source's poses of the neighbours of one frame set.

    Args:
        rgb: (F, 3, H, W) colour in [0, 1]; depth_m: (F, 1, H, W) metres, 0 = invalid;
            K: (3, 3) the frame set's one camera at (H, W) (the target first in each).
        offsets: frame offsets, ``offsets[0] == 0``.
        T_j_to_t: (F-1, 4, 4) the source's poses of the neighbours in the target camera.
        settings: its ``refine_settings`` and ``checks``.
        cache, positions: the batch job's per-frame results and the frames' positions
            (:func:`~depthgt.registration.refine.refine_poses`), or None.

    Returns:
        :class:`~depthgt.registration.result.RegistrationResult` (no correspondences,
        no loss curve); ``diagnostics`` holds the correction per neighbour.
    """
    t_start = time.perf_counter()
    T_start = _start(depth_m, offsets, T_j_to_t)
    refined = refine_poses(
        rgb, depth_m, K.to(depth_m.dtype), T_start, settings.refine_settings, offsets, cache=cache, positions=positions
    )
    return _result(refined, T_start, offsets, settings, time.perf_counter() - t_start)


def refine_source_poses_many(
    datas: list[FrameSetData], offsets: list[int], settings: RegistrationSettings
) -> list[RegistrationResult]:
    """:func:`register_refine` of several frame sets of one camera (the same members'
    shape and ``offsets``) refined together
    (:func:`~depthgt.registration.refine.refine_poses_many`: one residual evaluation for
    all of them, what keeps a GPU busy); each result as the set's own refinement gives.

    Raises:
        FrameError: a set's source has no finite poses for its members ("missing_pose").
    """
    t_start = time.perf_counter()
    starts = [_start(d.depth_m, offsets, poses_from_source(d)) for d in datas]
    sets = [RefineSet(d.rgb, d.depth_m, T, list(offsets), d.positions) for d, T in zip(datas, starts)]
    first = datas[0]
    refined = refine_poses_many(sets, first.K.to(first.depth_m.dtype), settings.refine_settings, first.cache)
    seconds = (time.perf_counter() - t_start) / len(datas)
    return [_result(r, T, offsets, settings, seconds) for r, T in zip(refined, starts)]


def _start(depth_m: torch.Tensor, offsets: list[int], T_j_to_t: torch.Tensor) -> torch.Tensor:
    """(F, 4, 4) float64 poses to start from (the target's the identity), inputs checked."""
    Fn = check_shape(depth_m, "F 1 H W", "depth_m")["F"]
    if Fn < 2:
        raise ValueError(f"depth_m must be (F >= 2, 1, H, W): a target and a neighbour, got {tuple(depth_m.shape)}")
    if len(offsets) != Fn or offsets[0] != 0:
        raise ValueError(f"offsets must list {Fn} offsets with the target's 0 first, got {offsets}")
    check_shape(T_j_to_t, "J 4 4", "T_j_to_t", {"J": Fn - 1})
    if not torch.isfinite(T_j_to_t).all():
        raise ValueError("T_j_to_t must be finite")
    dev = depth_m.device
    eye = torch.eye(4, dtype=torch.float64, device=dev)[None]
    T_start = torch.cat([eye, T_j_to_t.to(dev, torch.float64)])
    return T_start


def _result(
    refined: RefineResult, T_start: torch.Tensor, offsets: list[int], settings: RegistrationSettings, seconds: float
) -> RegistrationResult:
    """The refinement's :class:`RegistrationResult`: the neighbour checks against the
    start (a correction beyond the bounds diverged) and the diagnostics."""
    Fn = T_start.shape[0]
    T = refined.T_f_to_t
    statuses, reasons = check_neighbours(T, None, refined, settings.checks, T_start=T_start)
    status, reason = set_status(statuses, [], settings.checks)
    correction = torch.linalg.inv(T_start[1:]) @ T[1:]
    diagnostics = {**refined.diagnostics(), "correction_translation_m": correction[:, :3, 3].norm(dim=1).cpu().tolist()}
    return RegistrationResult(
        T_j_to_t=T[1:].detach().cpu().to(torch.float64),
        offsets=list(offsets),
        neighbour_status=statuses,
        neighbour_reasons=reasons,
        status=status,
        reason=reason,
        n_correspondences=[0] * (Fn - 1),
        timings={"refine": seconds, "total": seconds},
        diagnostics=diagnostics,
        normals=refined.normals,
    )
