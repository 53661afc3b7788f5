"""The source's poses as they are (``registration.method: given``): nothing is estimated,
every neighbour is kept."""

from __future__ import annotations

from depthgt.registration.frameset import FrameSetData, poses_from_source
from depthgt.registration.result import RegistrationResult
from depthgt.registration.settings import RegistrationSettings
from depthgt.status import Status

__all__ = ["register_given"]


def register_given(
    data: FrameSetData,
    offsets: list[int],
    settings: RegistrationSettings,
    *,
    seed: int = 0,
    encoder_state: dict | None = None,
) -> RegistrationResult:
    """The source's poses of the neighbours (:func:`poses_from_source`), all ok
    (:class:`~depthgt.registration.frameset.Registration`; ``settings``, ``seed`` and
    ``encoder_state`` are not used).

    Raises:
        FrameError: the source has no finite poses for the members ("missing_pose").
    """
    n = len(offsets) - 1
    return RegistrationResult(
        T_j_to_t=poses_from_source(data),
        offsets=list(offsets),
        neighbour_status=[Status.OK] * n,
        neighbour_reasons=[""] * n,
        status=Status.OK,
        reason="",
        n_correspondences=[0] * n,
        estimated=False,
    )
