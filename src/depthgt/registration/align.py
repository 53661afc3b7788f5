"""A frame set's alignment: the neighbours' poses in the target camera by the method
``registration.method`` names (:data:`depthgt.registration.methods.METHODS`), with the
photometric rule of :func:`photometric_for`, and which members enter the GT."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import torch

from depthgt.registration import methods
from depthgt.registration.frameset import FrameSetData
from depthgt.registration.result import RegistrationResult
from depthgt.registration.settings import RegistrationSettings
from depthgt.status import Status

__all__ = ["Alignment", "align", "align_many", "photometric_for"]


@dataclass
class Alignment:
    """The neighbours' poses in the target camera and what enters the GT.

    Attributes:
        T_j_to_t: (F-1, 4, 4) float64.
        fused: positions of the members rendered into the GT (0 = the target).
        status, reason: "ok" | "failed" and why.
        info: the registration record written to poses.json.
        normals: (F, 3, H, W) the members' normals as the registration's refinement
            computed them (the renderer's own, reused), or None.
    """

    T_j_to_t: torch.Tensor
    fused: list[int]
    status: str = Status.OK
    reason: str = ""
    info: dict | None = None
    normals: torch.Tensor | None = None


def align(
    data: FrameSetData, offsets: list[int], settings: RegistrationSettings, seed: int, encoder_state: dict | None = None
) -> Alignment:
    """Poses of the neighbours in the target camera by the method ``settings.method``
    names in :data:`depthgt.registration.methods.METHODS` (the source's, the source's refined
    on the set, or the overfit registration's), with the photometric rule of
    :func:`photometric_for`. A neighbour that did not register never enters the GT;
    with ``on_failure: exclude`` the set fails.

    Args:
        offsets: frame offsets of the members, ``offsets[0] == 0``.
        seed: seed of the registration (initialisation, candidates, subsets).
    """
    settings = photometric_for(settings, data.colour_matches_depth)
    register = methods.METHODS[settings.method]  # looked up at call time so tests can replace it
    result = register(data, offsets, settings, seed=seed, encoder_state=encoder_state)
    return _alignment(data, offsets, settings, result)


def align_many(
    datas: list[FrameSetData],
    offsets: list[int],
    settings: RegistrationSettings,
    seeds: list[int],
    encoder_state: dict | None = None,
) -> list[Alignment]:
    """:func:`align` of several frame sets of one camera (the same members' shape and
    ``offsets``; ``seeds`` one each). On a GPU, a method that registers sets together
    (its :class:`~depthgt.registration.methods.RegistrationMethod` names ``together``) does so for all of them at once;
    otherwise each is aligned on its own. The same alignments either way, up to the
    rounding of the batched products."""
    entry = methods.METHODS[settings.method]
    first = datas[0]
    if (
        entry.together is None
        or len(datas) < 2
        or first.depth_m.device.type == "cpu"
        or len({photometric_for(settings, d.colour_matches_depth) for d in datas}) > 1
        or any(d.depth_m.shape != first.depth_m.shape or not torch.equal(d.K, first.K) for d in datas)
    ):
        return [align(d, offsets, settings, seed, encoder_state) for d, seed in zip(datas, seeds)]
    settings = photometric_for(settings, first.colour_matches_depth)
    results = entry.register_together(datas, offsets, settings)
    return [_alignment(d, offsets, settings, r) for d, r in zip(datas, results)]


def _alignment(
    data: FrameSetData, offsets: list[int], settings: RegistrationSettings, result: RegistrationResult
) -> Alignment:
    """The :class:`Alignment` of a registration's result: the members that enter the GT
    (the target and every neighbour registered), the status (``on_failure: exclude``
    fails the set for any neighbour not registered) and the record for poses.json."""
    T_j_to_t = torch.as_tensor(result.T_j_to_t, dtype=torch.float64, device=data.depth_m.device)
    status, reason = result.status, result.reason
    failed = [o for o, st in zip(offsets[1:], result.neighbour_status) if st != Status.OK]
    if failed and status == Status.OK and settings.on_failure == "exclude":
        status, reason = Status.FAILED, f"neighbours_not_registered(offsets {','.join(f'{o:+d}' for o in failed)})"
    fused = [0] + [i + 1 for i, st in enumerate(result.neighbour_status) if st == Status.OK]
    info: dict[str, Any] = {"method": settings.method}
    if result.estimated:
        info["photometric_weight"] = settings.refine_settings.photo_weight
        info.update(result.to_dict())
        info["fused_offsets"] = [offsets[i] for i in fused]
    return Alignment(T_j_to_t, fused, status, reason, info, result.normals)


def photometric_for(settings: RegistrationSettings, colour_matches_depth: bool) -> RegistrationSettings:
    """The registration settings with the refinement's photometric term off where
    ``registration.photometric`` says so: ``off``, or ``auto`` on a source whose colour
    is not the depth's camera at the depth's instant (on the TUM tuning frames the term
    biased the refined poses: residuals in units of the noise, median 1.33 with it and
    0.99 without, docs/decisions.md "The photometric term")."""
    if settings.photometric == "on" or (settings.photometric == "auto" and colour_matches_depth):
        return settings
    return replace(settings, refine_settings=replace(settings.refine_settings, photo_weight=0.0))
