"""What every registration method gets: the members of one frame set at the working
resolution (:class:`FrameSetData`, read by :func:`depthgt.gt.build.load_frameset`), and
the one signature of the methods (:class:`Registration`; the table of them:
:data:`depthgt.registration.METHODS`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from depthgt.errors import FrameError
from depthgt.registration.result import RegistrationResult
from depthgt.settings import RegistrationSettings

__all__ = ["FrameSetData", "Registration", "poses_from_source"]


@dataclass
class FrameSetData:
    """The members of one frame set at the working resolution (target first).

    Attributes:
        rgb: (F, 3, H, W) float in [0, 1].
        depth_m: (F, 1, H, W) raw depth, 0 = invalid.
        K: (3, 3) float64 intrinsics at (H, W).
        T_world_cam: (F, 4, 4) float64 camera-to-world poses, or None.
        truth_m: (F, 1, H, W) clean depth when the source knows it, else None.
        frame_ids: the source's ids of the members.
        src_hw: (H, W) of the source's depth images before resizing.
        colour_matches_depth: the source's colour is taken by the depth's camera at the
            depth's instant (``Scene.colour_matches_depth``).
    """

    rgb: torch.Tensor
    depth_m: torch.Tensor
    K: torch.Tensor
    T_world_cam: torch.Tensor | None
    truth_m: torch.Tensor | None
    frame_ids: list[str]
    src_hw: tuple[int, int] | None = None
    colour_matches_depth: bool = True


def poses_from_source(data: FrameSetData) -> torch.Tensor:
    """``T_j_to_t`` (F-1, 4, 4) float64 of each neighbour from the source's poses.

    Raises:
        FrameError: the source has no poses for the members, or some are non-finite.
    """
    if data.T_world_cam is None:
        raise FrameError(
            "registration.method 'given' needs poses, but this source provides none or some are non-finite",
            "missing_pose",
        )
    T = data.T_world_cam
    return torch.linalg.inv(T[:1]) @ T[1:]


class Registration(Protocol):
    """A registration method: the neighbours of one frame set in its target's camera.

    Args:
        data: the members, target first.
        offsets: their frame offsets (``offsets[0] == 0``).
        settings: the registration settings (the method reads its parts).
        seed: seed of the method's random choices (initialisation, candidates, subsets).
        encoder_state: pretrained encoder weights (the overfit registration), or None.
    """

    def __call__(
        self,
        data: FrameSetData,
        offsets: list[int],
        settings: RegistrationSettings,
        *,
        seed: int = 0,
        encoder_state: dict | None = None,
    ) -> RegistrationResult: ...
