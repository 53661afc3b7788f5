"""Frame agreement: which frames, or regions of frames, disagree with the target's own depth."""

from __future__ import annotations

import math

import numba
import numpy as np
import torch
import torch.nn.functional as F

from depthgt.depth_ops import window_max
from depthgt.gt.render.pixelwise import hypot, within_gap_bound
from depthgt.gt.render.rasteriser import HIT_PX, RenderCandidates
from depthgt.gt.render.settings import RenderSettings

__all__ = ["frame_agreement", "agreement_slot", "slot_table"]

#: frame agreement: samples within this of a target sample are compared with it (px);
#: a frame is judged on at least this many comparisons
_NEAR_PX = 0.5

_MIN_COMPARED = 200

#: per-region agreement (``agreement_tile_px``): a tile is judged on the comparisons of
#: its 3x3 tile neighbourhood, when there are at least this many
_MIN_TILE_COMPARED = 50


def _tile_grid(hw: tuple[int, int], tile_px: int) -> tuple[int, int]:
    """(rows, columns) of the agreement tiles; (1, 1) when ``tile_px`` is 0 (whole frames)."""
    if tile_px <= 0:
        return 1, 1
    return -(-hw[0] // tile_px), -(-hw[1] // tile_px)


def agreement_slot(
    pixel: torch.Tensor, fr: torch.Tensor, *, size: tuple[int, int, int], n_frames: int, tile_px: int
) -> torch.Tensor:
    """Index of each sample's (image, frame, tile) in the flat decisions of
    :func:`frame_agreement`: ((image * J + frame) * tiles + tile), from a per-pixel
    table (one gather, no integer division per sample). ``pixel``, ``fr``: (C,) long;
    ``size``: (B, H, W); ``n_frames``: J."""
    ty, tx = _tile_grid(size[1:], tile_px)
    table = slot_table(size, n_frames, tile_px, pixel.device)  # per pixel of the B images: image and tile part
    return table.index_select(0, pixel) + fr * (ty * tx)


@numba.njit(cache=True, nogil=True)
def _target_samples(pixel, frame, d2, iz, s, target, hit2, iz_t, s_t):  # pragma: no cover (compiled)
    """The target's own samples at the pixels' positions (frame ``target``, d2 <= hit2)
    written into ``iz_t``, ``s_t`` (the block's pixels, counted from its first)."""
    for i in range(pixel.shape[0]):
        if frame[i] == target and d2[i] <= hit2:
            iz_t[pixel[i]] = iz[i]
            s_t[pixel[i]] = s[i]


@numba.njit(cache=True, nogil=True)
def _near_samples(
    pixel, frame, d2, iz, s, judge, iz_t, s_t, target, near2, gap_sigmas, gap_slope_rel
):  # pragma: no cover
    """The other frames' samples within ``near2`` (px^2) of a judged target sample:
    their pixels (of the block), frames and whether each agrees with the target's
    sample (the tensors' float arithmetic: the same decisions)."""
    n = pixel.shape[0]
    p_out = np.empty(n, np.int64)
    f_out = np.empty(n, np.int64)
    agree = np.empty(n, np.bool_)
    m = 0
    for i in range(n):
        p = pixel[i]
        if frame[i] != target and d2[i] <= near2 and judge[p]:
            step = iz[i] - iz_t[p]
            ok = within_gap_bound(step, s[i], s_t[p], iz[i], gap_sigmas, gap_slope_rel)
            if not ok:
                tol = gap_sigmas * hypot(s[i], s_t[p]) + gap_slope_rel * iz[i] * math.sqrt(d2[i])
                ok = abs(step) <= tol
            p_out[m] = p
            f_out[m] = frame[i]
            agree[m] = ok
            m += 1
    return p_out[:m].copy(), f_out[:m].copy(), agree[:m].copy()


@numba.njit(cache=True, nogil=True)
def _count_comparisons(pixel, frame, agree, table, n_t, h_w, n_fr, n_slots, n_pix):  # pragma: no cover
    """The comparisons of :func:`_near_samples` counted in one pass: per (image, frame)
    compared and agreeing (B*J,), per (image, frame, tile) the same (``n_slots``; ``table``
    (n_pix,) the image-and-tile part of :func:`agreement_slot`, ``n_t`` tiles per
    frame), per pixel compared and disagreeing (n_pix,); the bincounts of the tensor
    path, in int64."""
    n_img = n_pix // h_w
    cmp_f = np.zeros(n_img * n_fr, np.int64)
    ok_f = np.zeros(n_img * n_fr, np.int64)
    cmp_t = np.zeros(n_slots, np.int64)
    ok_t = np.zeros(n_slots, np.int64)
    seen = np.zeros(n_pix, np.int64)
    differ = np.zeros(n_pix, np.int64)
    for i in range(pixel.shape[0]):
        p, f = pixel[i], frame[i]
        fs = (p // h_w) * n_fr + f
        ts = table[p] + f * n_t
        cmp_f[fs] += 1
        cmp_t[ts] += 1
        seen[p] += 1
        if agree[i]:
            ok_f[fs] += 1
            ok_t[ts] += 1
        else:
            differ[p] += 1
    return cmp_f, ok_f, cmp_t, ok_t, seen, differ


@numba.njit(cache=True, nogil=True)
def _count_kept(pixel, frame, table, n_t, bad, n_pix):  # pragma: no cover (compiled)
    """Per pixel (n_pix,) int64 the comparisons whose (image, frame, tile) slot is not
    ``bad`` (the diagnostic's third count)."""
    kept = np.zeros(n_pix, np.int64)
    for i in range(pixel.shape[0]):
        p = pixel[i]
        if not bad[table[p] + frame[i] * n_t]:
            kept[p] += 1
    return kept


def slot_table(size: tuple[int, int, int], n_frames: int, tile_px: int, device: torch.device) -> torch.Tensor:
    """(B*H*W,) long: each pixel's image-and-tile part of :func:`agreement_slot`."""
    b, h, w = size
    ty, tx = _tile_grid((h, w), tile_px)
    img = torch.arange(b, device=device)[:, None, None]
    if tile_px <= 0:
        tile = torch.zeros(1, h, w, dtype=torch.long, device=device)
    else:
        tile = (torch.arange(h, device=device)[:, None] // tile_px) * tx + torch.arange(w, device=device)[
            None
        ] // tile_px
    return (img * (n_frames * ty * tx) + tile).reshape(-1)


def _target_depth(
    blocks: list[RenderCandidates], target_frame: int, n_pix: int, *, compiled: bool
) -> tuple[torch.Tensor, torch.Tensor]:
    """(n_pix,) the target's own sample at each pixel's position (inverse depth, NaN
    where none, and its std): its candidates within ``HIT_PX``."""
    c = blocks[0]
    dt, dev = c.iz_point.dtype, c.iz_point.device
    iz_t = torch.full((n_pix,), float("nan"), dtype=dt, device=dev)
    s_t = torch.zeros(n_pix, dtype=dt, device=dev)
    for blk in blocks:
        if compiled:
            p0, p1 = blk.first_pixel, blk.first_pixel + blk.pixels
            cols = (blk.pixel, blk.frame, blk.d2.detach(), blk.iz.detach(), blk.s)
            hit2 = iz_t.numpy().dtype.type(HIT_PX**2)  # a Python number meets a tensor in its dtype
            _target_samples(*(t.numpy() for t in cols), target_frame, hit2, *(t[p0:p1].numpy() for t in (iz_t, s_t)))
            continue
        tgt = ((blk.frame == target_frame) & (blk.d2.detach() <= HIT_PX**2)).nonzero().squeeze(1)
        pix_t = blk.pixel.index_select(0, tgt) + blk.first_pixel
        iz_t[pix_t] = blk.iz.detach().index_select(0, tgt)
        s_t[pix_t] = blk.s.index_select(0, tgt)
    return iz_t, s_t


def _near_comparisons(
    blocks: list[RenderCandidates],
    st: RenderSettings,
    target_frame: int,
    judge: torch.Tensor,
    iz_t: torch.Tensor,
    s_t: torch.Tensor,
    *,
    compiled: bool,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The other frames' samples within ``_NEAR_PX`` of a judged target sample: their
    pixels, frames and whether each agrees with the target's sample (C',)."""
    near_p, near_f, near_agree = [], [], []
    for blk in blocks:
        if compiled:
            p0, p1 = blk.first_pixel, blk.first_pixel + blk.pixels
            real = iz_t.numpy().dtype.type  # a Python number meets a tensor in its dtype
            p, f, ok = (
                torch.from_numpy(a)
                for a in _near_samples(
                    *(t.numpy() for t in (blk.pixel, blk.frame, blk.d2.detach(), blk.iz.detach(), blk.s)),
                    *(t[p0:p1].numpy() for t in (judge, iz_t, s_t)),
                    target_frame,
                    *(real(x) for x in (_NEAR_PX**2, st.gap_sigmas, st.gap_slope_rel)),
                )
            )
            near_p.append(p + p0 if p0 else p)
            near_f.append(f)
            near_agree.append(ok)
            continue
        fr, d2 = blk.frame, blk.d2.detach()
        pixel = blk.pixel + blk.first_pixel if blk.first_pixel else blk.pixel
        near = (fr != target_frame) & (d2 <= _NEAR_PX**2) & judge.index_select(0, pixel)
        ni = near.nonzero().squeeze(1)
        p, f, s_n, iz_n, d2_n = (x.index_select(0, ni) for x in (pixel, fr, blk.s, blk.iz.detach(), d2))
        tol = st.gap_sigmas * torch.hypot(s_n, s_t.index_select(0, p)) + st.gap_slope_rel * iz_n * torch.sqrt(d2_n)
        near_p.append(p)
        near_f.append(f)
        near_agree.append((iz_n - iz_t.index_select(0, p)).abs() <= tol)
    return torch.cat(near_p), torch.cat(near_f), torch.cat(near_agree)


def frame_agreement(
    blocks: list[RenderCandidates], st: RenderSettings, target_frame: int, *, compiled: bool | None = None
):
    """Which frames, or regions of frames, disagree with the target's own depth (a
    misregistered neighbour; a region that a rigid pose does not explain: lens
    distortion at the border, a moving object).

    Samples of the other frames within ``_NEAR_PX`` of a pixel where the target has its
    own sample are compared with it in inverse depth, with the gap tolerance of
    :func:`_choose_surfaces`, except within ``agreement_edge_px`` of a depth edge or a
    hole of the target (max - min of its inverse depth there beyond the tolerance of
    two samples plus the slope allowance). Whole frames (``agreement_tile_px`` 0): a frame whose share
    of agreeing samples is below ``min_frame_agreement`` (with at least
    ``_MIN_COMPARED`` samples compared) is bad. Tiles of ``agreement_tile_px``: each
    tile of each frame is judged on the comparisons of its 3x3 tile neighbourhood (at
    least ``_MIN_TILE_COMPARED``; fewer: the whole frame's decision), bad below
    ``min_frame_agreement``; a frame whose whole share is below
    ``min_whole_frame_agreement`` is bad everywhere (misregistered).

    Args:
        blocks: the rasteriser's candidates, in blocks of pixels (or one record).
        compiled: scan the candidates compiled (:func:`_target_samples`,
            :func:`_near_samples`; default: on the CPU) or as tensors; the same result.

    Returns:
        (B * J * tiles,) bool bad (frame, tile) slots (:func:`agreement_slot`), (B, J)
        float share of agreeing samples per frame (NaN: fewer than ``_MIN_COMPARED``
        comparisons, e.g. the target itself) and the (B, 3, H, W) diagnostic counts of
        :class:`GTRender`.

    Long for its docstring (the rule and its thresholds).
    """
    c = blocks[0]
    b, h, w = c.size
    hw, n_fr = (h, w), c.n_frames
    h_w = h * w
    n_pix = b * h_w
    # on the CPU the two scans over the candidates are compiled (the same values)
    compiled = c.iz_point.device.type == "cpu" if compiled is None else compiled
    if compiled and c.iz_point.device.type != "cpu":
        raise ValueError(f"the compiled frame agreement takes CPU tensors, got {c.iz_point.device.type}")
    iz_t, s_t = _target_depth(blocks, target_frame, n_pix, compiled=compiled)
    judge = torch.isfinite(iz_t)
    if st.agreement_edge_px > 0:
        # Not judged next to a depth edge or a hole of the target: a real sensor's edges
        # are fattened and shift between frames by more than its noise law says, and
        # they would outvote the flat surfaces on which a misregistration shows.
        k, r = 2 * st.agreement_edge_px + 1, st.agreement_edge_px
        img = iz_t.reshape(b, 1, h, w)
        hi = window_max(torch.nan_to_num(img, nan=float("inf")), k)  # max_pool2d's values
        lo = -window_max(-torch.nan_to_num(img, nan=-float("inf")), k)
        tol = st.gap_sigmas * math.sqrt(2.0) * s_t.reshape(b, 1, h, w) + st.gap_slope_rel * img * (2 * r)
        judge &= ((hi - lo) <= tol).reshape(-1)
    p, f, agree = _near_comparisons(blocks, st, target_frame, judge, iz_t, s_t, compiled=compiled)
    ty, tx = _tile_grid(hw, st.agreement_tile_px)
    n_slots = b * n_fr * ty * tx
    if compiled:  # the counts in one pass over the comparisons (the same integers)
        table = slot_table(c.size, n_fr, st.agreement_tile_px, p.device)
        n_cmp, n_ok, cmp_t, ok_t, seen, differ = (
            torch.from_numpy(a)
            for a in _count_comparisons(
                p.numpy(), f.numpy(), agree.numpy(), table.numpy(), ty * tx, h_w, n_fr, n_slots, n_pix
            )
        )
        n_cmp, n_ok = n_cmp.reshape(b, n_fr), n_ok.reshape(b, n_fr)
    else:
        slot = torch.div(p, h_w, rounding_mode="floor") * n_fr + f
        n_cmp = torch.bincount(slot, minlength=b * n_fr).reshape(b, n_fr)
        n_ok = torch.bincount(slot[agree], minlength=b * n_fr).reshape(b, n_fr)
        tslot = agreement_slot(p, f, size=c.size, n_frames=n_fr, tile_px=st.agreement_tile_px)
        cmp_t, ok_t = torch.bincount(tslot, minlength=n_slots), torch.bincount(tslot[agree], minlength=n_slots)
    share = torch.where(
        n_cmp >= _MIN_COMPARED, n_ok / n_cmp.clamp_min(1), torch.full_like(n_cmp, float("nan"), dtype=torch.float32)
    )
    bad = share < st.min_frame_agreement  # (NaN: not judged)
    if st.agreement_tile_px > 0:
        counts = torch.stack([cmp_t, ok_t]).to(torch.float32)
        # comparisons pooled over each tile's 3x3 neighbourhood (sums: average x 9)
        pooled = (
            F.avg_pool2d(counts.reshape(2 * b * n_fr, 1, ty, tx), 3, stride=1, padding=1, count_include_pad=True) * 9
        )
        n_cmp_t, n_ok_t = pooled.reshape(2, b, n_fr, ty, tx).round()
        judged = n_cmp_t >= _MIN_TILE_COMPARED
        bad_t = torch.where(judged, n_ok_t < st.min_frame_agreement * n_cmp_t, bad[..., None, None])
        bad = bad_t | (share < st.min_whole_frame_agreement)[..., None, None]
    if compiled:
        kept = torch.from_numpy(
            _count_kept(p.numpy(), f.numpy(), table.numpy(), ty * tx, bad.reshape(-1).contiguous().numpy(), n_pix)
        )
        diag = torch.stack([seen, differ, kept]).to(torch.float32)
    else:
        kept = ~bad.reshape(-1)[tslot]
        diag = torch.stack(
            [
                torch.bincount(p, minlength=n_pix),
                torch.bincount(p[~agree], minlength=n_pix),
                torch.bincount(p[kept], minlength=n_pix),
            ]
        ).to(torch.float32)
    return bad.reshape(-1), share.to(torch.float32), diag.reshape(3, b, h, w).transpose(0, 1)
