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
import torch.nn.functional as F

from depthgt.gt.render.cloud import (
    FrameGeometry,
    cached_geometry,
    cloud_from_geometry,
    frame_geometry,
)
from depthgt.gt.render.compositor import BLOCK_ROWS, GTRender, composite_gt
from depthgt.gt.render.rasteriser import Cells, rasterise_blocks
from depthgt.gt.render.settings import RenderSettings
from depthgt.noise_law import depth_sigma_m, noise_sigma_1m_of
from depthgt.registration.frameset import FrameSetData

__all__ = [
    "Fusion",
    "SetGeometry",
    "fuse",
    "fuse_geometry",
    "fuse_sets",
    "set_geometry",
    "frames_left_out_whole",
    "whole_frame_threshold",
]


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
        cells: the compiled rasteriser's cells of the members' points
            (:class:`~depthgt.gt.render.rasteriser.Cells`; None on the tensor path): a
            render of these members with more frames after them takes them (``prior`` of
            :func:`fuse`).
    """

    gt: GTRender
    members: tuple[int, ...]
    frames_left_out: tuple[int, ...]
    left_out: GTRender | None = None
    lto_stride: int = 1
    cells: Cells | None = None

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
    geometry: FrameGeometry | None = None,
    pixels: torch.Tensor | None = None,
    prior: Cells | None = None,
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
        normals: (F, 3, H, W) :func:`depthgt.depth_ops.depth_normals` of all F members' raw depth
            when the caller has them (the registration's refinement computed them); used
            for the raw depth (no ``depth_m``) when they match it in shape and dtype.
        geometry: the :class:`~depthgt.gt.render.cloud.FrameGeometry` of all F members'
            raw depth when the caller has it, for the raw depth (no ``depth_m``); else
            taken from the batch job's frame cache (``data.cache``) or computed here.
        pixels: (H, W) bool, the target's pixels whose GT is wanted (None: all; the
            others are left empty, :func:`~depthgt.gt.render.compositor.composite_gt`);
            the frame agreement and the leave-target-out render see every pixel.
        prior: the :attr:`Fusion.cells` of a fusion of the first members of ``members``
            with the same poses, geometry and settings (the coverage step's core): their
            points' cells are taken, not found again (the same render).
    """
    one = set_geometry(data, T_j_to_t, members, depth_m=depth_m, normals=normals, geometry=geometry)
    return fuse_sets(
        [one],
        data.K,
        tuple(data.depth_m.shape[-2:]),
        settings,
        src_hw=data.src_hw,
        leave_target_out=leave_target_out,
        pixels=pixels,
        prior=prior,
    )[0]


class SetGeometry(NamedTuple):
    """One frame set as the fusion takes it: the fused members' ``geometry`` (J frames,
    the target first when it is fused), their poses ``T_j_to_t`` (J, 4, 4) in the target
    camera and their positions ``members`` in the frame set (0 = the target)."""

    geometry: FrameGeometry
    T_j_to_t: torch.Tensor
    members: tuple[int, ...]


def set_geometry(
    data: FrameSetData,
    T_j_to_t: torch.Tensor,
    members: slice | list[int] = slice(None),
    *,
    depth_m: torch.Tensor | None = None,
    normals: torch.Tensor | None = None,
    geometry: FrameGeometry | None = None,
) -> SetGeometry:
    """The :class:`SetGeometry` of the ``members`` of a frame set (arguments as
    :func:`fuse`): the raw depth's geometry from ``geometry``, else the batch job's frame
    cache (``data.cache``), else computed (with ``normals`` when they match the depth);
    ``depth_m`` computed as given."""
    n_all = data.depth_m.shape[0]
    chosen = list(range(n_all))[members] if isinstance(members, slice) else list(members)
    depth = data.depth_m if depth_m is None else depth_m
    if normals is not None and (
        depth_m is not None or normals.shape != (n_all, 3, *depth.shape[-2:]) or normals.dtype != depth.dtype
    ):
        normals = None
    if geometry is None and depth_m is None and data.cache is not None and data.positions is not None:
        geometry = cached_geometry(
            data.cache, data.positions, data.depth_m, data.K, src_hw=data.src_hw, normals=normals
        )
    if geometry is None or depth_m is not None:
        geometry = frame_geometry(depth, data.K[None].expand(n_all, 3, 3), src_hw=data.src_hw, normals=normals)
    eye = torch.eye(4, dtype=T_j_to_t.dtype, device=T_j_to_t.device)[None]
    T = torch.cat([eye, T_j_to_t], dim=0)
    return SetGeometry(geometry.take(chosen), T[chosen], tuple(chosen))


def fuse_geometry(
    geometry: FrameGeometry,
    T_j_to_t: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    settings: RenderSettings,
    *,
    members: tuple[int, ...],
    src_hw: tuple[int, int] | None = None,
    leave_target_out: bool = False,
    block_rows: int | None = BLOCK_ROWS,
) -> Fusion:
    """:func:`fuse` on the frames' geometry: ``geometry`` (J frames, the fused members in
    order), their poses ``T_j_to_t`` (J, 4, 4) in the target camera, the intrinsics
    ``K`` (3, 3) at ``size_hw``; ``members`` the frames' positions in the frame set (0 =
    the target); the CPU renders in blocks of ``block_rows`` pixel rows."""
    one = SetGeometry(geometry, T_j_to_t, tuple(members))
    return fuse_sets([one], K, size_hw, settings, src_hw=src_hw, leave_target_out=leave_target_out, rows=block_rows)[0]


def fuse_sets(
    sets: list[SetGeometry],
    K: torch.Tensor,
    size_hw: tuple[int, int],
    settings: RenderSettings,
    *,
    src_hw: tuple[int, int] | None = None,
    leave_target_out: bool = False,
    together: bool | None = None,
    rows: int | None = BLOCK_ROWS,
    pixels: torch.Tensor | None = None,
    prior: Cells | None = None,
) -> list[Fusion]:
    """The :class:`Fusion` of each frame set of ``sets`` (one scene's: the intrinsics
    ``K`` (3, 3) at ``size_hw``, source size ``src_hw``).

    ``together``: render the sets as one batch, their images stacked, in one pass of the
    rasteriser and the compositor (what keeps a GPU busy); default: on a GPU. Otherwise
    (the CPU) set by set, each in blocks of ``rows`` pixel rows (cache-sized). Both give
    the same renders up to the rounding of the batched products. ``pixels``: (H, W) bool,
    of one set, the pixels whose GT is wanted (:func:`fuse`); ``prior``: of one set, the
    cells of its first members' points (:func:`fuse`)."""
    dev = sets[0].geometry.points.device
    if together is None:
        together = dev.type != "cpu"
    if (pixels is not None or prior is not None) and len(sets) != 1:
        raise ValueError(f"pixels and prior cells are one frame set's, got {len(sets)} sets")
    if not together or len(sets) == 1 or any(not s.members or s.members[0] != 0 for s in sets):
        cpu_rows = rows if dev.type == "cpu" else None
        return [_fuse_one(s, K, size_hw, settings, src_hw, leave_target_out, cpu_rows, pixels, prior) for s in sets]
    return _fuse_together(sets, K, size_hw, settings, src_hw, leave_target_out)


def _left_whole(agreement: torch.Tensor, members: tuple[int, ...], st: RenderSettings) -> tuple[int, ...]:
    """The members (positions) that the agreement (J,) of their frame set left out whole."""
    whole = frames_left_out_whole(agreement[None], st)[0].tolist() if agreement.numel() else []
    return tuple(members[j] for j, out in enumerate(whole) if out and j < len(members) and members[j] != 0)


def _lto_sigma(geometry: FrameGeometry, st: RenderSettings) -> torch.Tensor | None:
    """(1, J*H*W) the points' depth sigmas with the noise law estimated from the
    neighbours alone (frames 1..), the target's 0; None with a fixed ``noise_sigma_1m``."""
    if st.noise_sigma_1m is not None:
        return None
    sigma_1m = noise_sigma_1m_of(geometry.residuals[1:])
    return torch.cat(
        [torch.zeros_like(geometry.depth[:1]), depth_sigma_m(geometry.depth[1:], sigma_1m, st.noise_sigma_abs_m)]
    ).reshape(1, -1)


def _fuse_one(
    one: SetGeometry,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    st: RenderSettings,
    src_hw: tuple[int, int] | None,
    leave_target_out: bool,
    rows: int | None,
    pixels: torch.Tensor | None = None,
    prior: Cells | None = None,
) -> Fusion:
    members = one.members
    cloud = cloud_from_geometry(
        one.geometry, one.T_j_to_t, noise_sigma_1m=st.noise_sigma_1m, noise_sigma_abs_m=st.noise_sigma_abs_m
    )
    with_target = bool(members) and members[0] == 0  # the target's own depth is fused, as frame 0 of the cloud
    blocks = rasterise_blocks(
        cloud.points,
        K[None].to(cloud.points.dtype),
        size_hw,
        st,
        valid=cloud.valid,
        normals_cam=cloud.normals,
        sigma_m=cloud.sigma_m,
        frame=cloud.frame,
        src_hw=src_hw,
        block_rows=rows,
        prior=prior,
    )
    gt = composite_gt(
        blocks, st, target_frame=0 if with_target else None, pixels=None if pixels is None else pixels[None]
    )
    left = _left_whole(gt.agreement[0], members, st)
    stride = st.leave_target_out_stride
    cells = blocks[0].cells
    if not (with_target and leave_target_out and len(members) > 1):
        return Fusion(gt, tuple(members), left, None, stride, cells)
    # the leave-target-out render: the same compositor over the same candidates minus the
    # target's, with the noise law as fusing the neighbours alone estimates it
    lo_sigma = _lto_sigma(one.geometry, st)
    left_out = composite_gt(blocks, st, with_sigma=False, leave_out=0, stride=stride, sigma_m=lo_sigma)
    return Fusion(gt, tuple(members), left, left_out, stride, cells)


def _fuse_together(
    sets: list[SetGeometry],
    K: torch.Tensor,
    size_hw: tuple[int, int],
    st: RenderSettings,
    src_hw: tuple[int, int] | None,
    leave_target_out: bool,
) -> list[Fusion]:
    """The sets (each with its target fused) as one batch: clouds padded to the largest
    set's frames with invalid points, stacked, rasterised and composited at once."""
    n_img = len(sets)
    j_max = max(len(s.members) for s in sets)
    hw = sets[0].geometry.depth.shape[1]
    parts, lo = [], []
    for one in sets:
        c = cloud_from_geometry(
            one.geometry, one.T_j_to_t, noise_sigma_1m=st.noise_sigma_1m, noise_sigma_abs_m=st.noise_sigma_abs_m
        )
        pad = (j_max - len(one.members)) * hw
        frame = torch.arange(j_max, device=c.points.device).repeat_interleave(hw)[None]
        parts.append(
            (
                F.pad(c.points, (0, 0, 0, pad)),
                F.pad(c.normals, (0, 0, 0, pad)),
                F.pad(c.valid, (0, pad)),
                frame,
                F.pad(c.sigma_m, (0, pad), value=1.0),
            )
        )
        s = _lto_sigma(one.geometry, st) if leave_target_out and len(one.members) > 1 else None
        lo.append(None if s is None else F.pad(s, (0, pad), value=1.0))
    points, normals, valid, frame, sigma = (torch.cat([p[k] for p in parts]) for k in range(5))
    blocks = rasterise_blocks(
        points,
        K[None].expand(n_img, 3, 3).to(points.dtype),
        size_hw,
        st,
        valid=valid,
        normals_cam=normals,
        sigma_m=sigma,
        frame=frame,
        src_hw=src_hw,
        block_rows=None,
    )
    gt = composite_gt(blocks, st, target_frame=0)
    lto = None
    stride = st.leave_target_out_stride
    with_lto = [leave_target_out and len(s.members) > 1 for s in sets]
    if any(with_lto):
        lo_sigma = None
        if st.noise_sigma_1m is None:
            lo_sigma = torch.cat([s if s is not None else torch.ones_like(sigma[:1]) for s in lo])
        lto = composite_gt(blocks, st, with_sigma=False, leave_out=0, stride=stride, sigma_m=lo_sigma)
    out = []
    for k, one in enumerate(sets):
        j = len(one.members)
        mine = GTRender(
            *(t[k : k + 1] for t in gt[:4]),
            gt.agreement[k : k + 1, :j],
            None if gt.disagreement is None else gt.disagreement[k : k + 1],
        )
        left_out = None
        if with_lto[k]:
            left_out = GTRender(*(t[k : k + 1] for t in lto[:4]), lto.agreement[k : k + 1, :0], None)
        out.append(Fusion(mine, one.members, _left_whole(mine.agreement[0], one.members, st), left_out, stride))
    return out
