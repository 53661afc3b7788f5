"""The one fusion entry of the GT: a frame set's aligned members rendered into its
target view (paper eq. 5), and beside it the leave-target-out render of real data.

:func:`fuse` owns the renderer's steps: the members' cloud in the target camera
(:func:`~depthgt.gt.render.cloud.cloud_in_target`), the rasteriser
(:func:`~depthgt.gt.render.rasteriser.rasterise_gt`), the compositor with the frame
agreement (:func:`~depthgt.gt.render.compositor.composite_gt`) and the leave-target-out
render over the same candidates without the target's. Its result (:class:`Fusion`)
says which members the agreement left out whole and where the leave-target-out render
is valid, so no caller re-derives either.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch

from depthgt.gt.render.cloud import cloud_in_target
from depthgt.gt.render.compositor import GTRender, composite_gt
from depthgt.gt.render.rasteriser import rasterise_gt
from depthgt.gt.render.settings import RenderSettings
from depthgt.noise_law import depth_sigma_m, noise_sigma_1m_from, second_difference_residuals
from depthgt.registration.frameset import FrameSetData

__all__ = ["Fusion", "fuse", "frames_left_out_whole", "whole_frame_threshold"]


class Fusion(NamedTuple):
    """What :func:`fuse` made of one frame set.

    Attributes:
        gt: the GT render (B = 1).
        members: positions (in the frame set's members, 0 = the target) of the frames
            fused, in the render's frame order (frame j of ``gt.agreement`` is
            ``members[j]``).
        frames_left_out: the positions of ``members`` that the frame agreement left out
            whole (agreement below ``min_whole_frame_agreement``, or with whole-frame
            agreement below ``min_frame_agreement``).
        left_out: the leave-target-out render (the members without the target, the same
            candidates without the target's), or None; valid at the pixels of every
            ``lto_stride``-th row and column only (:meth:`on_lto_grid`). Its ``sigma``
            is zero unless ``max_sigma_m`` needs it.
        lto_stride: the stride of the pixels ``left_out`` was rendered at.
    """

    gt: GTRender
    members: tuple[int, ...]
    frames_left_out: tuple[int, ...]
    left_out: GTRender | None = None
    lto_stride: int = 1

    def on_lto_grid(self, image):
        """The pixels of ``image`` (..., H, W) (tensor or array) where ``left_out`` was
        rendered: every ``lto_stride``-th row and column."""
        k = self.lto_stride
        return image[..., ::k, ::k]

    def left_out_depth(self) -> np.ndarray | None:
        """(H', W') float32 the leave-target-out depth at its grid (:meth:`on_lto_grid`), or None."""
        if self.left_out is None:
            return None
        return self.on_lto_grid(self.left_out.depth[0, 0].detach().cpu().numpy().astype(np.float32))


def whole_frame_threshold(settings: RenderSettings) -> float:
    """The agreement with the target below which a frame is left out whole:
    ``min_whole_frame_agreement`` with agreement tiles, ``min_frame_agreement`` without."""
    return settings.min_whole_frame_agreement if settings.agreement_tile_px > 0 else settings.min_frame_agreement


def frames_left_out_whole(agreement: torch.Tensor, settings: RenderSettings) -> torch.Tensor:
    """(B, J) bool: frames whose agreement (B, J) with the target left them out whole
    (:func:`whole_frame_threshold`; NaN, not judged: kept)."""
    return torch.nan_to_num(agreement, nan=float("inf")) < whole_frame_threshold(settings)


def fuse(
    data: FrameSetData,
    T_j_to_t: torch.Tensor,
    settings: RenderSettings,
    depth_m: torch.Tensor | None = None,
    members: slice | list[int] = slice(None),
    leave_target_out: bool = False,
    normals: torch.Tensor | None = None,
) -> Fusion:
    """Render the aligned members into the target view (paper eq. 5).

    Args:
        data: the frame set (target first).
        T_j_to_t: (F-1, 4, 4) poses of the neighbours (the target's is the identity).
        depth_m: (F, 1, H, W) depth to fuse (default: the raw depth of the members).
        members: which members to use (``slice(1, None)`` leaves the target out; a
            list of positions, 0 = the target, keeps those).
        leave_target_out: with the target among the members and neighbours beside it,
            also render the neighbours alone (:attr:`Fusion.left_out`): the same result
            as fusing ``members`` without the target, at the pixels of every
            ``settings.leave_target_out_stride``-th row and column, sharing the clouds,
            the projection and the sort with the GT render.
        normals: (F, 3, H, W) kornia's ``depth_to_normals`` of all F members' raw depth
            when the caller has them (the registration's refinement computed them); used
            when every member is fused (a batch of other frames rounds the convolution
            differently, which the normalisation can amplify where the gradients
            vanish), for the raw depth (no ``depth_m``) and when they match it in shape
            and dtype.
    """
    depth = (data.depth_m if depth_m is None else depth_m)[members]
    n_all = data.depth_m.shape[0]
    chosen = list(range(n_all))[members] if isinstance(members, slice) else list(members)
    if normals is not None and (
        depth_m is not None
        or chosen != list(range(n_all))
        or normals.shape != (n_all, 3, *data.depth_m.shape[-2:])
        or normals.dtype != depth.dtype
        or normals.device != depth.device
    ):
        normals = None
    eye = torch.eye(4, dtype=T_j_to_t.dtype, device=T_j_to_t.device)[None]
    T = torch.cat([eye, T_j_to_t], dim=0)[members]
    K = data.K[None].expand(depth.shape[0], 3, 3)
    residuals = second_difference_residuals(depth, data.src_hw)  # the noise estimates and the normals' edge test
    cloud = cloud_in_target(
        depth,
        K,
        T,
        src_hw=data.src_hw,
        noise_sigma_1m=settings.noise_sigma_1m,
        noise_sigma_abs_m=settings.noise_sigma_abs_m,
        residuals=residuals,
        normals=normals,
    )
    h, w = data.depth_m.shape[-2:]
    with_target = bool(chosen) and chosen[0] == 0  # the target's own depth is fused, as frame 0 of the cloud
    cands = rasterise_gt(
        cloud.points,
        data.K[None].to(depth.dtype),
        (h, w),
        settings,
        valid=cloud.valid,
        normals_cam=cloud.normals,
        sigma_m=cloud.sigma_m,
        frame=cloud.frame,
        src_hw=data.src_hw,
    )
    gt = composite_gt(cands, settings, target_frame=0 if with_target else None)
    whole = frames_left_out_whole(gt.agreement, settings)[0].tolist() if gt.agreement.numel() else []
    left = tuple(chosen[j] for j, out in enumerate(whole) if out and j < len(chosen) and chosen[j] != 0)
    stride = settings.leave_target_out_stride
    if not (with_target and leave_target_out and len(chosen) > 1):
        return Fusion(gt, tuple(chosen), left, None, stride)
    left_out = _leave_target_out(cands, residuals, depth, settings, cloud.sigma_m.dtype)
    return Fusion(gt, tuple(chosen), left, left_out, stride)


def _leave_target_out(cands, residuals, depth: torch.Tensor, settings: RenderSettings, dtype) -> GTRender:
    """The neighbours alone (frames 1.. of ``cands``) at every ``leave_target_out_stride``-th
    pixel, with the noise law as fusing them alone estimates it (without the target's depth)."""
    lo_sigma = None
    if settings.noise_sigma_1m is None:
        sigma_1m = noise_sigma_1m_from(residuals, frames=slice(1, None))
        lo_sigma = torch.cat(
            [torch.zeros_like(depth[:1]), depth_sigma_m(depth[1:], sigma_1m, settings.noise_sigma_abs_m)]
        )
        lo_sigma = lo_sigma.reshape(1, -1).to(dtype)
    # the same compositor over the same candidates minus the target's
    neighbours = cands.without_frame(0, stride=settings.leave_target_out_stride, sigma_m=lo_sigma)
    return composite_gt(neighbours, settings, with_sigma=False)
