"""What every registration method gets: the members of one frame set at the working
resolution (:class:`FrameSetData`, read by :func:`load_frameset`), and
the one signature of the methods (:class:`Registration`; the table of them:
:data:`depthgt.registration.METHODS`)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import torch

from depthgt import geometry
from depthgt.errors import FrameError
from depthgt.framecache import FrameCache
from depthgt.registration.result import RegistrationResult
from depthgt.registration.settings import RegistrationSettings
from depthgt.sources.base import Scene, check_frame

__all__ = ["FrameSetData", "Registration", "load_depth", "load_frameset", "load_poses", "poses_from_source"]


@dataclass
class FrameSetData:
    """The members of one frame set at the working resolution (target first).

    Attributes:
        rgb: (F, 3, H, W) float in [0, 1].
        depth_m: (F, 1, H, W) raw depth, 0 = invalid.
        K: (3, 3) float64 intrinsics at (H, W): the frame set's one camera, every
            member's (a function taking several images' intrinsics takes them (F, 3, 3):
            ``K.expand(F, 3, 3)``; docs/development.md "Shapes and intrinsics").
        T_world_cam: (F, 4, 4) float64 camera-to-world poses, or None.
        truth_m: (F, 1, H, W) clean depth when the source knows it, else None.
        frame_ids: the source's ids of the members.
        src_hw: (H, W) of the source's depth images before resizing.
        colour_matches_depth: the source's colour is taken by the depth's camera at the
            depth's instant (``Scene.colour_matches_depth``).
        positions: the members' positions in their scene, or None.
        cache: the batch job's :class:`~depthgt.framecache.FrameCache` of per-frame
            results (keyed by ``positions``), or None.
    """

    rgb: torch.Tensor
    depth_m: torch.Tensor
    K: torch.Tensor
    T_world_cam: torch.Tensor | None
    truth_m: torch.Tensor | None
    frame_ids: list[str]
    src_hw: tuple[int, int] | None = None
    colour_matches_depth: bool = True
    positions: tuple[int, ...] | None = None
    cache: FrameCache | None = None


def load_frameset(
    scene: Scene,
    members: list[int],
    size_hw: tuple[int, int],
    need_poses: bool,
    device: torch.device,
    cache: FrameCache | None = None,
) -> FrameSetData:
    """Read the member frames of any :class:`~depthgt.sources.base.Scene` and bring them
    to ``size_hw`` (depth nearest/valid-aware, colour area-averaged, intrinsics scaled).

    A scene whose frames already have the working size (a
    :class:`depthgt.gt.cache.ResizedScene`) is not resized again; it tells the size of
    the images it was resized from by ``source_size``.

    ``cache``: the batch job's per-frame results (:class:`~depthgt.framecache.FrameCache`),
    kept with the frame set with the members' positions.

    Raises:
        FrameError: a member frame is unusable (the batch job checks the members
            before it builds a frame set, and records such a set as skipped).
    """
    frames = _checked(scene, members, need_poses)
    size_hw = (int(size_hw[0]), int(size_hw[1]))
    same = tuple(scene.image_size) == size_hw

    def depth_at_size(arrays: list[np.ndarray]) -> torch.Tensor:
        return _depth_at_size(arrays, scene, size_hw, device)

    rgb = torch.from_numpy(np.stack([f.rgb for f in frames])).permute(0, 3, 1, 2).to(device).float() / 255.0
    truth = None
    if all(f.clean_depth_m is not None for f in frames):
        truth = depth_at_size([f.clean_depth_m for f in frames])
    poses = None
    if all(f.T_world_cam is not None for f in frames) and all(np.isfinite(f.T_world_cam).all() for f in frames):
        poses = torch.from_numpy(np.stack([f.T_world_cam for f in frames])).to(device)
    K = np.asarray(scene.intrinsics, dtype=np.float64)
    if not same:
        K = geometry.scale_intrinsics(K, scene.image_size, size_hw)
    return FrameSetData(
        rgb=rgb if same else geometry.resize_rgb(rgb, size_hw),
        depth_m=depth_at_size([f.depth_m for f in frames]),
        K=torch.as_tensor(K, device=device),
        T_world_cam=poses,
        truth_m=truth,
        frame_ids=[scene.frame_id(m) for m in members],
        src_hw=tuple(getattr(scene, "source_size", scene.image_size)),
        colour_matches_depth=bool(getattr(scene, "colour_matches_depth", True)),  # test doubles may not say
        positions=tuple(int(m) for m in members),
        cache=cache,
    )


def load_depth(scene: Scene, members: list[int], size_hw: tuple[int, int], device: torch.device) -> torch.Tensor:
    """The raw depth (F, 1, H, W) of the ``members`` at ``size_hw``, as
    :func:`load_frameset` reads and resizes it, without their colour (coverage's
    candidates: their colour is read for the few views added)."""
    frames = _checked(scene, members, need_poses=False)
    return _depth_at_size([f.depth_m for f in frames], scene, (int(size_hw[0]), int(size_hw[1])), device)


def load_poses(scene: Scene, members: list[int], device: torch.device) -> torch.Tensor:
    """The source's poses (F, 4, 4) of the ``members``, as :func:`load_frameset` reads
    them, without their images (the frames checked as it checks them).

    Raises:
        FrameError: a member is unusable or has no usable pose."""
    frames = _checked(scene, members, need_poses=True)
    return torch.from_numpy(np.stack([f.T_world_cam for f in frames])).to(device)


def _checked(scene: Scene, members: list[int], need_poses: bool) -> list:
    return [
        check_frame(scene.read(m), scene.image_size, f"{scene.name} frame {scene.frame_id(m)}", need_pose=need_poses)
        for m in members
    ]


def _depth_at_size(
    arrays: list[np.ndarray], scene: Scene, size_hw: tuple[int, int], device: torch.device
) -> torch.Tensor:
    d = torch.from_numpy(np.stack(arrays))[:, None].to(device)
    return d if tuple(scene.image_size) == size_hw else geometry.resize_depth_nearest(d, size_hw)


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
