"""The GT compositor: the rasteriser's candidates -> surfaces, visibility, a weighted
plane per pixel and the confidence (steps 2-5 of :func:`render_gt`).

Per pixel the candidates come front first, so a surface (a run of candidates between
gaps in inverse depth) is a contiguous run, and the samples the estimate keeps are one
such run: the chosen surface. The compositor therefore works on surfaces ("clusters")
throughout: every sum of the estimate is a sum over each cluster's run, taken for every
cluster at once, and a pixel reads its chosen cluster's values (no copy of the kept
samples). Where a pixel keeps more than ``m`` samples the kept ones are copied out and
estimated on their own (:func:`_keep_m_nearest`).

On the CPU the candidates are composited in blocks of pixel rows (:data:`BLOCK_ROWS`):
a block's two dozen arrays stay in the cache between the steps, which takes a third of
the time of whole-image arrays on a 2 MB L2 cache; on a GPU the whole batch is one
block. The blocks are independent: every step is per pixel or per cluster.
"""

from __future__ import annotations

import math
import warnings
from typing import NamedTuple

import numba
import numpy as np
import torch

from depthgt.gt.render.agreement import agreement_slot, frame_agreement, slot_table
from depthgt.gt.render.pixelwise import composite_pixels, confidence, hypot, plane_slopes, rendered_candidates
from depthgt.gt.render.rasteriser import HIT_PX, RenderCandidates, inverse_depth_std, rasterise_gt
from depthgt.gt.render.settings import RenderSettings
from depthgt.rasterise import rank_in_pixel

__all__ = ["GTRender", "composite_gt", "render_gt", "BLOCK_ROWS"]

#: scale of the error model in the confidence, calibrated on the tuning set of
#: bench/bench_gt_protocol.py so that the median |GT - truth| / sigma is 0.674, as for
#: Gaussian errors (the model alone overstates the typical error by ~1.9x)
_SIGMA_SCALE = 0.53
#: the weights' common scale, 1/m: inverse-variance weights (s_ref / s)^2 with s the
#: samples' std in inverse depth (only ratios matter: a constant keeps them near 1)
_S_REF = 1e-3
#: pixel rows composited together on the CPU (~250 k candidates at 256 columns: a
#: block's arrays fit a 2 MB L2 cache); measured on 7-Scenes, bench/bench_render.py
BLOCK_ROWS = 32


class GTRender(NamedTuple):
    """Output of :func:`render_gt` (:func:`composite_gt`).

    depth: (B, 1, H, W) GT depth in metres, 0 = no GT.
    weight_sum: (B, 1, H, W) sum of the spatial weights exp(-d / R^2) of the kept samples.
    count: (B, 1, H, W) int64 number of kept samples.
    sigma: (B, 1, H, W) expected standard deviation of ``depth`` in metres (the
        per-pixel confidence; 0 where nothing was estimated).
    agreement: (B, J) share of each frame's samples that agree with the target's own
        depth (NaN where not judged: no ``target_frame``, the target itself, fewer than
        200 samples compared); frames below ``min_frame_agreement`` were left out (with
        ``agreement_tile_px``: their regions below it). (B, 0) without frame ids.
    disagreement: (B, 3, H, W) float per pixel, over the other frames' samples compared
        with the target's: compared, disagreeing, and kept by the agreement check (a
        diagnostic of where frames disagree); None when nothing was judged.
    """

    depth: torch.Tensor
    weight_sum: torch.Tensor
    count: torch.Tensor
    sigma: torch.Tensor
    agreement: torch.Tensor
    disagreement: torch.Tensor | None = None


class _Surfaces(NamedTuple):
    """The clusters of a block's candidates and each pixel's choice (:func:`_choose_surfaces`).

    cluster: (C,) long cluster of every candidate, numbered pixel by pixel, front to back.
    lengths: (K,) candidates per cluster (runs of ``cluster``); cl_pixel: (K,) their pixel.
    support: (K,) distinct frames per cluster (candidates, without frame ids).
    chosen: (P,) long the cluster each pixel takes, -1 for none.
    ambiguous: (P,) bool; step_iz: (P,) inverse-depth step between the front surface
        and the one behind it (0 where there is none).
    """

    cluster: torch.Tensor
    lengths: torch.Tensor
    cl_pixel: torch.Tensor
    support: torch.Tensor
    chosen: torch.Tensor
    ambiguous: torch.Tensor
    step_iz: torch.Tensor


def _value(v: torch.Tensor | tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """A value of :meth:`_Runs.sums`: a tensor, or the product of a pair."""
    return v[0] * v[1] if isinstance(v, tuple) else v


class _Runs:
    """Sums and minima of per-candidate values over consecutive runs (clusters, or a
    pixel's kept samples): ``index`` (C,) the run of each element, sorted, ``lengths``
    (K,) each run's size (empty runs allowed).

    On the CPU the sums are one product with a sparse (K, C) matrix of ones in CSR form
    (MKL's sparse kernels: ~5x faster than ``torch.segment_reduce`` at a quarter million
    candidates, the same sums); elsewhere one ``index_add`` each. Differentiable."""

    def __init__(self, index: torch.Tensor, lengths: torch.Tensor) -> None:
        self.index, self.lengths = index, lengths
        self._csr: dict[torch.dtype, torch.Tensor] = {}

    def _matrix(self, dtype: torch.dtype) -> torch.Tensor:
        m = self._csr.get(dtype)
        if m is None:
            n = self.index.numel()
            crow = torch.zeros(self.lengths.numel() + 1, dtype=torch.long, device=self.index.device)
            torch.cumsum(self.lengths, 0, out=crow[1:])
            cols = torch.arange(n, device=self.index.device)
            with warnings.catch_warnings():  # "sparse CSR support is in beta": the product is all it is used for
                warnings.simplefilter("ignore", UserWarning)
                m = torch.sparse_csr_tensor(crow, cols, torch.ones(n, dtype=dtype), size=(self.lengths.numel(), n))
            self._csr[dtype] = m
        return m

    def sums(self, values: list[torch.Tensor | tuple[torch.Tensor, torch.Tensor]]) -> list[torch.Tensor]:
        """(K,) sums of each (C,) tensor of ``values``; a pair ``(a, b)`` stands for the
        product ``a * b``."""
        if self.index.device.type != "cpu" or self.index.numel() == 0:
            n = self.lengths.numel()
            return [
                torch.zeros(n, dtype=v.dtype, device=v.device).index_add(0, self.index, v) for v in map(_value, values)
            ]
        parts = [t for v in values for t in (v if isinstance(v, tuple) else (v,))]
        first = parts[0]
        if torch.is_grad_enabled() and any(t.requires_grad for t in parts):
            stacked = torch.stack([_value(v) for v in values])  # (k, C), rows contiguous
        else:
            # each product written into its row: no temporary per value and no stack copy
            # (the same values; out= takes no tensors that need gradients)
            stacked = torch.empty(len(values), first.numel(), dtype=first.dtype, device=first.device)
            for row, v in zip(stacked, values):
                if isinstance(v, tuple):
                    torch.mul(v[0], v[1], out=row)
                else:
                    row.copy_(v)
        return list((stacked @ self._matrix(stacked.dtype).t()).unbind(0))

    def minimum(self, v: torch.Tensor) -> torch.Tensor:
        """(K,) minimum of ``v`` (C,) over each run (+inf for an empty one)."""
        if self.index.device.type != "cpu":
            full = torch.full((self.lengths.numel(),), float("inf"), dtype=v.dtype, device=v.device)
            return full.scatter_reduce(0, self.index, v, reduce="amin")
        return torch.segment_reduce(v, "min", lengths=self.lengths, unsafe=True, initial=float("inf"))


def _clusters(c: RenderCandidates, st: RenderSettings) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Each pixel's candidates grouped into surfaces by gaps in inverse depth: the
    cluster of every candidate (C,) (numbered pixel by pixel, front to back), each
    cluster's first candidate (K,) and size (K,)."""
    pixel, s_iz = c.pixel, c.s
    iz, ox, oy = c.iz.detach(), c.ox.detach(), c.oy.detach()
    dev, n_c = pixel.device, pixel.numel()
    apart = torch.hypot(ox[1:] - ox[:-1], oy[1:] - oy[:-1])  # px
    tol = st.gap_sigmas * torch.hypot(s_iz[:-1], s_iz[1:]) + st.gap_slope_rel * iz[:-1] * apart
    new = torch.ones(n_c, dtype=torch.bool, device=dev)
    new[1:] = (pixel[1:] != pixel[:-1]) | ((iz[:-1] - iz[1:]) > tol)
    starts = new.nonzero().squeeze(1)
    cluster = torch.cumsum(new, 0) - 1
    lengths = torch.diff(starts, append=torch.tensor([n_c], device=dev))
    return cluster, starts, lengths


@numba.njit(cache=True, nogil=True)
def _cluster_runs(pixel, iz, s, ox, oy, frame, gap_sigmas, gap_slope_rel):  # pragma: no cover (compiled)
    """:func:`_clusters` in one compiled pass, with each cluster's distinct frames: the
    cluster of every candidate (C,), each cluster's first candidate, size and frames (K,)
    (``frame`` (C,) int64 below 64, or empty: each candidate counts as a frame). The same
    float arithmetic as the tensors' (hypot included: the same clusters)."""
    n = pixel.shape[0]
    cluster = np.empty(n, np.int64)
    starts = np.empty(n, np.int64)
    k = -1
    for i in range(n):
        new = i == 0 or pixel[i] != pixel[i - 1]
        if not new:
            apart = hypot(ox[i] - ox[i - 1], oy[i] - oy[i - 1])
            tol = gap_sigmas * hypot(s[i - 1], s[i]) + gap_slope_rel * iz[i - 1] * apart
            new = (iz[i - 1] - iz[i]) > tol
        if new:
            k += 1
            starts[k] = i
        cluster[i] = k
    n_cl = k + 1
    lengths = np.empty(n_cl, np.int64)
    support = np.empty(n_cl, np.int64)
    for j in range(n_cl):
        end = starts[j + 1] if j + 1 < n_cl else n
        lengths[j] = end - starts[j]
        if frame.shape[0] == 0:
            support[j] = lengths[j]
            continue
        seen = np.uint64(0)
        for i in range(starts[j], end):
            seen |= np.uint64(1) << np.uint64(frame[i])
        m = 0
        while seen:
            seen &= seen - np.uint64(1)
            m += 1
        support[j] = m
    return cluster, starts[:n_cl].copy(), lengths, support


def _clusters_compiled(c: RenderCandidates, st: RenderSettings) -> tuple[torch.Tensor, ...]:
    """:func:`_clusters` and each cluster's distinct frames (its candidates without frame
    ids), compiled (:func:`_cluster_runs`; frame ids below 64)."""
    frame = torch.zeros(0, dtype=torch.long) if c.frame is None else c.frame
    out = _cluster_runs(
        *(t.detach().numpy() for t in (c.pixel, c.iz, c.s, c.ox, c.oy)),
        frame.numpy(),
        # the tensors' precision: a Python number times a tensor is taken in its dtype
        *(c.iz.detach().numpy().dtype.type(x) for x in (st.gap_sigmas, st.gap_slope_rel)),
    )
    return tuple(torch.from_numpy(a) for a in out)


def _choose_surfaces(
    c: RenderCandidates,
    st: RenderSettings,
    target_frame: int | None,
    n_pix: int,
    *,
    need_support: bool = True,
    compiled: bool = False,
) -> _Surfaces:
    """Group each pixel's candidates into surfaces by gaps in inverse depth and pick the
    visible one (the rule: :func:`render_gt`, steps 2-3), on the candidates ``c`` of a
    block of ``n_pix`` pixels (``c.pixel`` local, sorted; within a pixel front first;
    used detached). ``need_support``: count each cluster's frames (the confidence needs
    them) even where the choice does not.

    A pixel with one surface takes it (with ``extend_uncovered``, whatever its reach):
    only the pixels with several (5 % of them on the shared recordings) go through the
    surfaces' support, reach and the edge vote (:func:`_choose_among`). ``compiled``: the
    clusters and their frames in one compiled pass (:func:`_cluster_runs`; CPU, frame
    ids below 64), the same values."""
    frame = c.frame
    n_frames = c.n_frames or (int(frame.max()) + 1 if frame is not None and frame.numel() else 0)
    present = None
    cluster, starts, lengths, support = (
        _clusters_compiled(c, st) if compiled and n_frames <= 64 else (*_clusters(c, st), None)
    )
    n_cl = starts.numel()
    dev = cluster.device
    cl_pixel = c.pixel.index_select(0, starts)
    per_pixel = torch.bincount(cl_pixel, minlength=n_pix)
    first = torch.cumsum(per_pixel, 0) - per_pixel  # each pixel's first cluster (its only one, mostly)
    multi = per_pixel > 1
    several = bool(multi.any()) or not st.extend_uncovered
    if support is None:
        support = lengths
        if frame is not None and (need_support or several):
            present = torch.zeros(n_cl * n_frames, dtype=torch.bool, device=dev)
            present[cluster * n_frames + frame] = True
            present = present.view(n_cl, n_frames)
            support = present.sum(1)
    has = per_pixel > 0
    chosen = torch.where(has, first, -1)
    ambiguous = torch.zeros(n_pix, dtype=torch.bool, device=dev)
    step = torch.zeros(n_pix, dtype=c.iz.dtype, device=dev)
    if several:
        # the candidates of the pixels with several surfaces (every pixel without
        # extend_uncovered: one surface may not reach the position)
        pick = multi if st.extend_uncovered else has
        sub_cl = pick.index_select(0, cl_pixel)
        cl_ids = sub_cl.nonzero().squeeze(1)
        idx = sub_cl.index_select(0, cluster).nonzero().squeeze(1)
        sub = c.select(idx)
        local = (torch.cumsum(sub_cl, 0) - 1).index_select(0, cluster.index_select(0, idx))
        sub_present = None if present is None else present.index_select(0, cl_ids)
        if present is None and frame is not None:  # compiled: the frames of these clusters only
            sub_present = torch.zeros(cl_ids.numel() * n_frames, dtype=torch.bool, device=dev)
            sub_present[local * n_frames + sub.frame] = True
            sub_present = sub_present.view(cl_ids.numel(), n_frames)
        ch, amb, stp = _choose_among(
            sub,
            st,
            target_frame,
            n_pix,
            cluster=local,
            lengths=lengths.index_select(0, cl_ids),
            cl_pixel=cl_pixel.index_select(0, cl_ids),
            support=support.index_select(0, cl_ids),
            present=sub_present,
            n_frames=n_frames,
        )
        px = pick.nonzero().squeeze(1)
        ch = ch.index_select(0, px)
        chosen[px] = torch.where(ch >= 0, cl_ids.index_select(0, ch.clamp_min(0)), -1)
        ambiguous[px] = amb.index_select(0, px)
        step[px] = stp.index_select(0, px)
    return _Surfaces(cluster, lengths, cl_pixel, support, chosen, ambiguous & (chosen >= 0), step)


def _choose_among(
    c: RenderCandidates,
    st: RenderSettings,
    target_frame: int | None,
    n_pix: int,
    *,
    cluster: torch.Tensor,
    lengths: torch.Tensor,
    cl_pixel: torch.Tensor,
    support: torch.Tensor,
    present: torch.Tensor | None,
    n_frames: int,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The visible surface of each pixel (:func:`render_gt`, steps 2-3) among the clusters
    ``cluster`` (C,) of the candidates ``c`` (``lengths``, ``cl_pixel``, ``support`` and
    ``present`` (K, J) per cluster): per pixel (n_pix,) the chosen cluster (-1: none),
    whether it is ambiguous, and the inverse-depth step to the surface behind.

    Long because its steps (support, front and behind, reach, the edge vote, the choice)
    share a dozen per-cluster tensors; passing them between smaller functions read worse
    than one function in the order of the rule."""
    frame, d2 = c.frame, c.d2.detach()
    iz, ox, oy = c.iz.detach(), c.ox.detach(), c.oy.detach()
    dev = cluster.device
    n_cl = lengths.numel()
    runs = _Runs(cluster, lengths)
    idx = torch.arange(n_cl, device=dev)
    qualified = support >= st.min_frames
    own = None
    if target_frame is not None and frame is not None:
        # the target's own sample at a pixel's position: that surface is seen there
        own = ((frame == target_frame) & (d2 <= HIT_PX**2)).nonzero().squeeze(1)
        qualified[cluster.index_select(0, own)] = True
    none = torch.full((n_pix,), n_cl, dtype=torch.long, device=dev)
    first_q = none.scatter_reduce(0, cl_pixel, torch.where(qualified, idx, n_cl), reduce="amin")
    first = none.scatter_reduce(0, cl_pixel, idx, reduce="amin")
    front = torch.where(first_q < n_cl, first_q, first)
    behind = none.scatter_reduce(
        0, cl_pixel, torch.where(qualified & (idx > front.index_select(0, cl_pixel)), idx, n_cl), reduce="amin"
    )
    has_f, has_b = front < n_cl, behind < n_cl
    # reach: how far each surface's samples go beyond the sample position, measured
    # opposite their centroid (negative: they all lie on one side)
    cnt = lengths.to(ox.dtype)
    mx, my, iz_cl = (v / cnt for v in runs.sums([ox, oy, iz]))
    norm = torch.hypot(mx, my)
    centred = norm <= 1e-9
    inv = 1.0 / norm.clamp_min(1e-12)
    ex = torch.where(centred, torch.ones_like(mx), mx * inv)
    ey = torch.where(centred, torch.zeros_like(my), my * inv)
    t = ox * ex.index_select(0, cluster) + oy * ey.index_select(0, cluster)
    reach = torch.where(centred, torch.full_like(mx, float("inf")), -runs.minimum(t))
    if st.edge_vote > 0 and frame is not None and present is not None:
        # Each frame's own reach: the surface's edge is where ``edge_vote`` of its frames
        # reach (the median edge of frames whose edges jitter and fatten on a real
        # sensor), not where the farthest one does (their union, biased outwards). One
        # frame's samples lie ~1 px apart, so its reach falls short of its edge by up to
        # 1 px: ``edge_vote_slack_px`` (half of that) is added back.
        # The voters: the frames with samples on the surface or behind it at the pixel (a
        # frame that sees only what lies behind has its edge before the position).
        r_cf = -torch.full((n_cl * n_frames,), float("inf"), dtype=ox.dtype, device=dev).scatter_reduce(
            0, cluster * n_frames + frame, t, reduce="amin"
        )
        r_sorted = r_cf.view(n_cl, n_frames).sort(dim=1, descending=True).values  # absent frames: -inf, last
        # frames with a sample on this cluster or one behind it at the pixel: the
        # clusters' presence counted from the back, less the count from the next pixel on
        from_back = present.flip(0).to(torch.int32).cumsum(0).flip(0)
        next_pixel = torch.searchsorted(cl_pixel, cl_pixel, right=True)
        beyond = torch.cat([from_back, torch.zeros_like(from_back[:1])]).index_select(0, next_pixel)
        voters = ((from_back - beyond) > 0).sum(1)
        k = torch.ceil(st.edge_vote * voters.to(ox.dtype)).long().clamp(1, n_frames) - 1
        reach = torch.where(
            centred, reach, torch.minimum(reach, r_sorted.gather(1, k[:, None]).squeeze(1) + st.edge_vote_slack_px)
        )
    d_near = runs.minimum(d2)
    hit = d_near <= HIT_PX**2  # a sample at the position itself (the target's own, typically)
    covered = (reach >= st.edge_margin_px) | hit
    fi, bi = front.clamp_max(n_cl - 1), behind.clamp_max(n_cl - 1)
    cov_f, cov_b = covered.index_select(0, fi), covered.index_select(0, bi)
    take_b = has_b & ~cov_f & (cov_b | (d_near.index_select(0, bi) < d_near.index_select(0, fi)))
    use = has_f & (cov_f | has_b | st.extend_uncovered)
    ambiguous = (
        has_f
        & has_b
        & ~hit.index_select(0, fi)
        & ((reach.index_select(0, fi) - st.edge_margin_px).abs() < st.ambiguous_px)
    )
    chosen = torch.where(use & ~(ambiguous & st.drop_ambiguous), torch.where(take_b, bi, fi), torch.full_like(fi, -1))
    if st.target_resolves_ambiguous and own is not None:
        # the target's own sample at the position decides a pixel left undecided, on a
        # surface that other frames support too
        own_cl = cluster.index_select(0, own)
        own_cl = own_cl[support.index_select(0, own_cl) >= st.min_frames]
        px = cl_pixel.index_select(0, own_cl)
        undecided = (chosen.index_select(0, px) < 0) | ambiguous.index_select(0, px)
        own_cl, px = own_cl[undecided], px[undecided]
        chosen[px] = own_cl
        ambiguous[px] = False
    iz_f = iz_cl.index_select(0, fi)
    step = torch.where(has_b, (iz_f - iz_cl.index_select(0, bi)).abs(), torch.zeros_like(iz_f))
    return chosen, ambiguous, step


def _keep_m_nearest(
    pixel: torch.Tensor, d2: torch.Tensor, keep: torch.Tensor, *, m: int, r2: float, n_pix: int
) -> torch.Tensor:
    """Restrict ``keep`` to the m kept candidates of smallest d2 in every pixel.

    Avoids sorting all candidates: a per-pixel histogram of d2 in ``nb`` bins finds the
    bin where the count reaches m; bins before it are kept whole and only the
    candidates of that boundary bin are ranked exactly (by :func:`rank_in_pixel`).
    """
    nb = 32
    dd = d2.detach()
    bins = (dd * (nb / r2)).long().clamp_(0, nb - 1)
    hist = torch.zeros(n_pix * nb, dtype=torch.int32, device=pixel.device)
    hist.index_add_(0, pixel * nb + bins, keep.to(torch.int32))
    cum = hist.view(n_pix, nb).cumsum(dim=1)
    full = cum >= m
    # first bin reaching m (nb = none: every kept candidate stays)
    boundary = torch.where(
        full.any(dim=1), full.to(torch.int8).argmax(dim=1), torch.full((n_pix,), nb, device=pixel.device)
    )
    before = torch.where(
        boundary > 0, cum.gather(1, (boundary - 1).clamp_min(0)[:, None]).squeeze(1), torch.zeros_like(boundary)
    )
    bnd = boundary.index_select(0, pixel)
    out = keep & (bins <= bnd)
    at_bnd = (out & (bins == bnd)).nonzero().squeeze(1)
    if at_bnd.numel():
        rank = rank_in_pixel(pixel.index_select(0, at_bnd), dd.index_select(0, at_bnd))
        out[at_bnd[rank >= (m - before)[pixel.index_select(0, at_bnd)]]] = False
    return out


class _Estimate(NamedTuple):
    """Per segment (a cluster, or a pixel's kept samples): depth, weight sum, count, sigma."""

    depth: torch.Tensor
    weight_sum: torch.Tensor
    count: torch.Tensor
    sigma: torch.Tensor | None


def _weights(d2: torch.Tensor, s: torch.Tensor, st: RenderSettings) -> tuple[torch.Tensor, torch.Tensor]:
    """Each candidate's spatial weight exp(-d2 / R^2) and its inverse-variance weight (the
    spatial one times (s_ref / s)^2: scaled, only ratios matter), (C,) each."""
    w_sp = torch.exp(-d2 / st.radius_px**2)
    return w_sp, w_sp * (_S_REF / s) ** 2


def _estimate(
    c: RenderCandidates,
    seg: torch.Tensor,
    lengths: torch.Tensor,
    n_frames: torch.Tensor,
    st: RenderSettings,
    *,
    with_sigma: bool,
    step_iz: torch.Tensor | None = None,
    ambiguous: torch.Tensor | None = None,
) -> _Estimate:
    """Step 4-5 of :func:`render_gt` for every segment of the candidates ``c``: the
    segments are the runs of ``seg`` (C,) sorted, ``lengths`` (S,) their sizes,
    ``n_frames`` (S,) their distinct frames; ``step_iz``, ``ambiguous`` (S,) the step to
    the surface behind and whether the segment's pixel is ambiguous (the confidence).

    Long because the plane fit and the confidence reuse the weighted sums of the same
    samples (a dozen per-segment tensors); split, they would travel between functions
    as long argument lists.
    """
    iz, s, ox, oy = c.iz, c.s, c.ox, c.oy
    w_sp, wt = _weights(c.d2, s, st)
    if c.grad is None or st.plane == "none":
        gx = gy = torch.zeros_like(iz)
    else:
        g = c.grad.index_select(0, c.point)
        gx, gy = g[:, 0], g[:, 1]
    runs = _Runs(seg, lengths)
    sw, s_iz, s_x, s_y, s_gx, s_gy, wsum = runs.sums([wt, (wt, iz), (wt, ox), (wt, oy), (wt, gx), (wt, gy), w_sp])
    has = sw > 0
    sw_safe = torch.where(has, sw, torch.ones_like(sw))
    mean_iz, mean_x, mean_y, mean_gx, mean_gy = (v / sw_safe for v in (s_iz, s_x, s_y, s_gx, s_gy))
    cxo = ox - mean_x.index_select(0, seg)  # offsets about the weighted centroid
    cyo = oy - mean_y.index_select(0, seg)
    wx, wy = wt * cxo, wt * cyo
    if st.plane == "fit":
        diz = iz - mean_iz.index_select(0, seg)
        cxx, cyy, cxy, cxz, cyz = (
            v / sw_safe for v in runs.sums([(wx, cxo), (wy, cyo), (wx, cyo), (wx, diz), (wy, diz)])
        )
        lam = st.slope_prior
        a11, a22, a12 = cxx + lam, cyy + lam, cxy
        v1, v2 = cxz + lam * mean_gx, cyz + lam * mean_gy
        det = a11 * a22 - a12 * a12
        ok = det > 1e-12
        det_safe = torch.where(ok, det, torch.ones_like(det))
        slope_x = torch.where(ok, (a22 * v1 - a12 * v2) / det_safe, torch.zeros_like(det))
        slope_y = torch.where(ok, (a11 * v2 - a12 * v1) / det_safe, torch.zeros_like(det))
        iz_hat = mean_iz - slope_x * mean_x - slope_y * mean_y  # the plane at the sample position
        resid = iz - (
            iz_hat.index_select(0, seg) + slope_x.index_select(0, seg) * ox + slope_y.index_select(0, seg) * oy
        )
    else:
        cxx, cyy, cxy = (v / sw_safe for v in runs.sums([(wx, cxo), (wy, cyo), (wx, cyo)]))
        if st.plane == "normals":
            iz_c = iz - gx * ox - gy * oy  # each sample moved along its tangent plane to the position
            iz_hat = runs.sums([(wt, iz_c)])[0] / sw_safe
            resid = iz_c - iz_hat.index_select(0, seg)
        else:
            iz_hat = mean_iz
            resid = iz - iz_hat.index_select(0, seg)
    good = has & (lengths >= st.min_points) & (iz_hat > 0)
    depth = torch.where(good, 1.0 / torch.where(good, iz_hat, torch.ones_like(iz_hat)), torch.zeros_like(iz_hat))
    sigma = None
    if with_sigma or st.max_sigma_m is not None:
        with torch.no_grad():
            wt_d, resid_d = wt.detach(), resid.detach()
            model, res2 = (v / sw_safe.detach() for v in runs.sums([(wt_d * s, s), (wt_d * resid_d, resid_d)]))
            lam = st.slope_prior + 1e-6
            mx, my = mean_x.detach(), mean_y.detach()
            a11, a22, a12 = cxx.detach() + lam, cyy.detach() + lam, cxy.detach()
            det = (a11 * a22 - a12 * a12).clamp_min(1e-12)
            extrap = (a22 * mx * mx - 2 * a12 * mx * my + a11 * my * my) / det  # o^T C^-1 o
            var_iz = (model + res2) / n_frames.to(model.dtype).clamp_min(1.0) * (1.0 + extrap)
            z2 = depth.detach() * depth.detach()
            sigma2 = _SIGMA_SCALE**2 * z2 * z2 * var_iz
            if step_iz is not None and ambiguous is not None:
                step_m = z2 * step_iz  # depth step to the surface behind (first order)
                sigma2 = sigma2 + torch.where(ambiguous, (0.5 * step_m) ** 2, torch.zeros_like(sigma2))
            sigma = torch.where(good, torch.sqrt(sigma2), torch.zeros_like(sigma2))
        if st.max_sigma_m is not None:
            depth = torch.where(sigma <= st.max_sigma_m, depth, torch.zeros_like(depth))
    return _Estimate(depth, wsum, lengths, sigma)


@numba.njit(cache=True, nogil=True)
def _plane_fit_chosen(
    chosen, cl_start, lengths, support, step_iz, ambiguous, w_spatial, w, iz, s, ox, oy, point, grad, consts
):  # pragma: no cover (compiled)
    """:func:`_estimate` with ``plane="fit"`` for each pixel's chosen cluster only, in
    one compiled pass per cluster (its candidates in the cache), without gradients:
    depth, weight sum, count and sigma per pixel (0 where ``chosen`` is -1).

    chosen (P,) int64 the cluster of each pixel or -1; cl_start, lengths, support (K,)
    each cluster's first candidate, size and frames; step_iz, ambiguous (P,); the
    candidates' spatial weights exp(-d2 / R^2) and inverse-variance weights (as the
    tensors compute them, vectorised), iz, s, ox, oy (C,) and point (C,) int64; grad (N,
    2) the points' tangent-plane gradients (zero rows: none); consts: slope_prior,
    min_points, sigma_scale, need_sigma, max_sigma_m (< 0: none).

    The same estimate as the tensors' (the weighted plane in inverse depth with the
    normals' slope prior, the confidence) with the sums taken in float64 one cluster at
    a time: the results agree to float32 rounding (tests/test_render.py). Written by hand
    because the tensor form materialises a dozen per-candidate products and takes every
    cluster's sums, where a pixel keeps one cluster: no library fuses a segmented
    weighted least-squares fit.

    Long because a cluster's three passes (the sums, the plane, the confidence) share a
    dozen scalars; split, they would travel as long argument lists.
    """
    lam, min_points, sigma_scale, need_sigma, max_sigma = consts
    n_pix = chosen.shape[0]
    depth = np.zeros(n_pix, iz.dtype)
    weight_sum = np.zeros(n_pix, iz.dtype)
    count = np.zeros(n_pix, np.int64)
    sigma = np.zeros(n_pix, iz.dtype)
    wts = np.empty(lengths.max() if lengths.shape[0] else 0, np.float64)  # a cluster's weights
    for px in range(n_pix):
        k = chosen[px]
        if k < 0:
            continue
        lo = cl_start[k]
        n = lengths[k]
        sw = s_iz = s_x = s_y = s_gx = s_gy = wsum = 0.0
        for i in range(lo, lo + n):
            w_sp = np.float64(w_spatial[i])
            wt = np.float64(w[i])
            wts[i - lo] = wt
            sw += wt
            s_iz += wt * iz[i]
            s_x += wt * ox[i]
            s_y += wt * oy[i]
            s_gx += wt * grad[point[i], 0]
            s_gy += wt * grad[point[i], 1]
            wsum += w_sp
        has = sw > 0
        sw_safe = sw if has else 1.0
        mean_iz, mean_x, mean_y = s_iz / sw_safe, s_x / sw_safe, s_y / sw_safe
        cxx = cyy = cxy = cxz = cyz = 0.0
        for i in range(lo, lo + n):
            wt = wts[i - lo]
            cxo, cyo, diz = ox[i] - mean_x, oy[i] - mean_y, iz[i] - mean_iz
            cxx += wt * cxo * cxo
            cyy += wt * cyo * cyo
            cxy += wt * cxo * cyo
            cxz += wt * cxo * diz
            cyz += wt * cyo * diz
        cxx, cyy, cxy, cxz, cyz = cxx / sw_safe, cyy / sw_safe, cxy / sw_safe, cxz / sw_safe, cyz / sw_safe
        slope_x, slope_y = plane_slopes(cxx, cyy, cxy, cxz, cyz, lam, s_gx / sw_safe, s_gy / sw_safe)
        iz_hat = mean_iz - slope_x * mean_x - slope_y * mean_y  # the plane at the sample position
        good = has and n >= min_points and iz_hat > 0
        d = 1.0 / iz_hat if good else 0.0
        sg = 0.0
        if need_sigma:
            model = res2 = 0.0
            for i in range(lo, lo + n):
                wt = wts[i - lo]
                resid = iz[i] - (iz_hat + slope_x * ox[i] + slope_y * oy[i])
                model += wt * s[i] * s[i]
                res2 += wt * resid * resid
            model, res2 = model / sw_safe, res2 / sw_safe
            sigma2 = confidence(
                model, res2, cxx, cyy, cxy, lam, mean_x, mean_y, support[k], d, ambiguous[px], step_iz[px], sigma_scale
            )
            sg = math.sqrt(sigma2) if good else 0.0
            if max_sigma >= 0 and not sg <= max_sigma:
                d = 0.0
        depth[px] = d
        weight_sum[px] = wsum
        count[px] = n
        sigma[px] = sg
    return depth, weight_sum, count, sigma


def _fit_chosen(
    c: RenderCandidates, surf: _Surfaces, st: RenderSettings, *, with_sigma: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_composite_block`'s result from each pixel's chosen cluster, compiled
    (:func:`_plane_fit_chosen`): depth, weight sum, count and sigma (zeros without
    ``with_sigma`` or ``max_sigma_m``)."""
    dt = c.iz.dtype
    need_sigma = with_sigma or st.max_sigma_m is not None
    consts = (
        float(st.slope_prior),
        int(st.min_points),
        _SIGMA_SCALE,
        need_sigma,
        -1.0 if st.max_sigma_m is None else float(st.max_sigma_m),
    )
    grad = c.grad if c.grad is not None else torch.zeros(c.iz_point.numel(), 2, dtype=dt)
    cl_start = torch.cumsum(surf.lengths, 0) - surf.lengths
    w_sp, wt = _weights(c.d2.detach(), c.s, st)
    out = _plane_fit_chosen(
        *(t.numpy() for t in (surf.chosen, cl_start, surf.lengths, surf.support, surf.step_iz, surf.ambiguous)),
        *(t.detach().numpy() for t in (w_sp, wt, c.iz, c.s, c.ox, c.oy, c.point, grad.to(dt).contiguous())),
        consts,
    )
    depth, weight_sum, count, sigma = (torch.from_numpy(a) for a in out)
    return depth, weight_sum, count, sigma if need_sigma else torch.zeros_like(sigma)


def _composite_block(
    c: RenderCandidates,
    st: RenderSettings,
    *,
    n_pix: int,
    target_frame: int | None,
    with_sigma: bool,
    compiled: bool | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Depth, weight sum, count and sigma (each (n_pix,)) of the pixels of one block:
    ``c.pixel`` local to the block (0 .. n_pix - 1), sorted, front first; ``compiled``:
    as :func:`composite_gt`."""
    dev, dt = c.iz.device, c.iz.dtype
    zeros = torch.zeros(n_pix, dtype=dt, device=dev)
    if c.pixel.numel() == 0:
        return zeros, zeros.clone(), torch.zeros(n_pix, dtype=torch.long, device=dev), zeros.clone()
    if compiled is None:
        grads = torch.is_grad_enabled() and any(
            t is not None and t.requires_grad for t in (c.ox, c.oy, c.d2, c.iz, c.s, c.grad)
        )
        compiled = st.plane == "fit" and dev.type == "cpu" and not grads
    elif compiled and (st.plane != "fit" or dev.type != "cpu"):
        raise ValueError(f"the compiled plane fit takes plane='fit' on the CPU, got {st.plane!r} on {dev.type}")
    with torch.no_grad():
        surf = _choose_surfaces(
            c, st, target_frame, n_pix, need_support=with_sigma or st.max_sigma_m is not None, compiled=compiled
        )
        chosen = surf.chosen
        use = chosen >= 0
        ch = chosen.clamp_min(0)
        kept_count = torch.where(use, surf.lengths.index_select(0, ch), torch.zeros_like(ch))
        capped = int(kept_count.max()) > st.m
    if compiled and not capped:
        return _fit_chosen(c, surf, st, with_sigma=with_sigma)
    if not capped:
        # the kept samples of a pixel are its chosen cluster's run: estimate every cluster
        est = _estimate(
            c,
            surf.cluster,
            surf.lengths,
            surf.support,
            st,
            with_sigma=with_sigma,
            step_iz=surf.step_iz.index_select(0, surf.cl_pixel),
            ambiguous=surf.ambiguous.index_select(0, surf.cl_pixel),
        )
        pick = ch
    else:
        # a pixel keeps more than m: the m nearest of its chosen cluster, copied out
        with torch.no_grad():
            keep = surf.cluster == chosen.index_select(0, c.pixel)
            keep = _keep_m_nearest(c.pixel, c.d2, keep, m=st.m, r2=st.radius_px**2, n_pix=n_pix)
            kept = c.select(keep.nonzero().squeeze(1))
            lengths = torch.bincount(kept.pixel, minlength=n_pix)
            if kept.frame is None:
                n_frames = lengths
            else:
                j = kept.n_frames or int(kept.frame.max()) + 1
                present = torch.zeros(n_pix * j, dtype=torch.bool, device=dev)
                present[kept.pixel * j + kept.frame] = True
                n_frames = present.view(n_pix, j).sum(1)
        est = _estimate(
            kept,
            kept.pixel,
            lengths,
            n_frames,
            st,
            with_sigma=with_sigma,
            step_iz=surf.step_iz,
            ambiguous=surf.ambiguous,
        )
        pick = torch.arange(n_pix, device=dev)

    def at(v: torch.Tensor) -> torch.Tensor:
        return torch.where(use, v.index_select(0, pick), 0)

    sigma = zeros if est.sigma is None else at(est.sigma)
    return at(est.depth), at(est.weight_sum), at(est.count), sigma


def _pixelwise_weights(
    c: RenderCandidates, st: RenderSettings, s_point: torch.Tensor | None, wanted: np.ndarray | None, stride: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_weights` of the candidates :func:`_pixelwise_block` composites, with the
    points' stds ``s_point`` where given: all of them (``wanted`` None), or compactly
    those of the ``wanted`` pixels (empty: all) on every ``stride``-th row and column
    (:func:`~depthgt.gt.render.pixelwise.rendered_candidates`; a leave-target-out render
    at stride 2 needs a quarter). Vectorised (torch's SIMD ``exp``, the same value at any
    position of an array): the tensor compositor's float operations."""
    d2, s_c = c.d2.detach(), c.s
    if wanted is not None:
        b, h, w = c.size
        sel = torch.from_numpy(rendered_candidates(c.pixel.numpy(), int(c.first_pixel), wanted, int(stride), h, w))
        d2 = d2.index_select(0, sel)
        s_c = s_c.index_select(0, sel) if s_point is None else s_point.index_select(0, c.point.index_select(0, sel))
    elif s_point is not None:
        s_c = s_point.index_select(0, c.point)
    return tuple(t.numpy() for t in _weights(d2, s_c, st))


def _pixelwise_block(
    c: RenderCandidates,
    st: RenderSettings,
    *,
    target_frame: int | None,
    with_sigma: bool,
    bad: torch.Tensor | None,
    table: torch.Tensor | None,
    n_tiles: int,
    leave_out: int | None,
    stride: int,
    s_point: torch.Tensor | None,
    wanted: torch.Tensor | None,
) -> tuple[torch.Tensor, ...] | None:
    """:func:`_composite_block`'s result for one block by the compiled pixel-by-pixel
    compositor (:func:`~depthgt.gt.render.pixelwise.composite_pixels`), skipping the
    candidates in ``bad`` agreement slots (``table``: each pixel's image-and-tile part),
    of frame ``leave_out`` and off the pixels of every ``stride``-th row and column, with
    the points' inverse-depth stds ``s_point`` instead of the candidates' (None: theirs),
    at the ``wanted`` pixels (B*H*W,) only (None: all); None when a chosen surface keeps
    more than ``m`` samples."""
    b, h, w = c.size
    n_pix = c.pixels
    if c.pixel.numel() == 0:
        zeros = torch.zeros(n_pix, dtype=c.iz.dtype)
        return zeros, zeros.clone(), torch.zeros(n_pix, dtype=torch.long), zeros.clone()
    real = c.iz.detach().numpy().dtype.type  # a Python number meets a tensor in its dtype
    empty_i, empty_b = np.zeros(0, np.int64), np.zeros(0, np.bool_)
    grad = c.grad if c.grad is not None else torch.zeros(c.iz_point.numel(), 2, dtype=c.iz.dtype)
    n_frames = c.n_frames or int(c.frame.max()) + 1
    none = np.zeros(0, c.iz.detach().numpy().dtype)
    # the weights vectorised (torch's SIMD exp), the leave-target-out render's with its
    # own stds: the float operations of the tensor compositor over the same candidates,
    # so that it is the render of the neighbours alone to the bit
    compact = stride > 1 or wanted is not None
    wanted_np = empty_b if wanted is None else wanted.numpy()
    w_sp, wt = _pixelwise_weights(c, st, s_point, wanted_np if compact else None, stride)
    depth, wsum, count, sigma, capped = composite_pixels(
        *(t.detach().numpy() for t in (c.pixel, c.point, c.ox, c.oy, c.d2, c.iz, c.s, c.frame)),
        grad.detach().to(c.iz.dtype).contiguous().numpy(),
        s_point.numpy() if s_point is not None else none,
        w_sp,
        wt,
        n_pix,
        (
            -1 if leave_out is None else int(leave_out),
            -1 if target_frame is None else int(target_frame),
            int(stride),
            int(c.first_pixel),
            h,
            w,
            n_frames,
            n_tiles,
            1 if compact else 0,
        ),
        (empty_b, empty_i) if bad is None else (bad.numpy(), table.numpy()),
        wanted_np,
        (real(st.gap_sigmas), real(st.gap_slope_rel)),
        (real(st.edge_vote), real(st.edge_vote_slack_px), 1 if st.edge_vote > 0 else 0),
        (
            real(st.edge_margin_px),
            real(st.ambiguous_px),
            real(HIT_PX**2),
            real(1 if st.drop_ambiguous else 0),
            real(1 if st.extend_uncovered else 0),
            real(1 if st.target_resolves_ambiguous else 0),
        ),
        (int(st.m), int(st.min_frames)),
        (
            float(st.slope_prior),
            int(st.min_points),
            _SIGMA_SCALE,
            1 if (with_sigma or st.max_sigma_m is not None) else 0,
            -1.0 if st.max_sigma_m is None else float(st.max_sigma_m),
        ),
    )
    if capped:
        return None
    return tuple(torch.from_numpy(a) for a in (depth, wsum, count, sigma))


def composite_gt(
    cands: RenderCandidates | list[RenderCandidates],
    settings: RenderSettings = RenderSettings(),
    *,
    target_frame: int | None = None,
    with_sigma: bool = True,
    block_rows: int | None = BLOCK_ROWS,
    compiled: bool | None = None,
    leave_out: int | None = None,
    stride: int = 1,
    sigma_m: torch.Tensor | None = None,
    pixels: torch.Tensor | None = None,
) -> GTRender:
    """Steps 2-5 of :func:`render_gt` on the rasteriser's candidates (one record, or the
    blocks of :func:`~depthgt.gt.render.rasteriser.rasterise_blocks` covering every
    pixel in order): with ``target_frame`` the frames (or regions) that disagree with
    the target's own depth are left out first (:attr:`GTRender.agreement`); then
    surfaces, visibility, the ``m`` nearest samples, the plane fit and the confidence
    (with ``with_sigma`` or ``max_sigma_m``, else ``sigma`` is zero). One record is
    composited in blocks of ``block_rows`` pixel rows on the CPU (None: all at once,
    as on a GPU). ``compiled``: the frame agreement's scans, the surfaces
    (:func:`_cluster_runs`) and the plane fit of the chosen ones
    (:func:`_plane_fit_chosen`) compiled (default: on the CPU, the last two with
    ``plane="fit"`` and no gradients wanted) or as tensors; the same GT to float32
    rounding.

    The leave-target-out render is this compositor over the same candidates without the
    target's: ``leave_out`` the target's frame id, ``stride`` (the pixels of every
    stride-th row and column only, the others empty) and ``sigma_m`` (B, N) the points'
    depth sigmas for it (None: the candidates'), no ``target_frame``; the same result as
    compositing :meth:`RenderCandidates.without_frame` (which the tensor path does; the
    compiled one skips those candidates as it reads them).

    ``pixels``: (B, H, W) bool, the pixels whose GT is wanted (None: all); the others are
    left empty (the compiled path skips them; the frame agreement still judges every
    pixel).

    On the CPU (``compiled``, plane "fit", frame ids below 64, no gradients wanted) each
    block is composited pixel by pixel, compiled
    (:func:`~depthgt.gt.render.pixelwise.composite_pixels`; a block where a surface keeps
    more than ``m`` samples goes the tensors' way); the same GT to float32 rounding.

    Long because it routes each block to the compiled compositor or the tensors with the
    agreement's bad regions, the leave-out and the pixel mask, which both paths take
    differently; every step is a function of its own.
    """
    st = settings
    if isinstance(cands, RenderCandidates):
        cands = cands.blocks(block_rows if cands.iz_point.device.type == "cpu" else None)
    first = cands[0]
    b, h, w = first.size
    dev, dt = first.iz_point.device, first.iz_point.dtype
    if leave_out is not None and first.frame is None:
        raise ValueError("leave_out needs candidates with frame ids (render with frame=...)")
    grads = torch.is_grad_enabled() and any(
        t is not None and t.requires_grad for c in cands for t in (c.ox, c.oy, c.d2, c.iz, c.s, c.grad)
    )
    n_frames = first.n_frames or max(
        (int(c.frame.max()) + 1 for c in cands if c.frame is not None and c.frame.numel()), default=0
    )
    pixelwise = (
        compiled is not False
        and dev.type == "cpu"
        and st.plane == "fit"
        and first.frame is not None
        and n_frames <= 64
        and not grads
    )
    s_point = None
    if pixelwise and sigma_m is not None:
        if sigma_m.numel() != first.iz_point.numel():
            raise ValueError(
                f"sigma_m must hold one sigma per point ({first.iz_point.numel()}), got {tuple(sigma_m.shape)}"
            )
        s_point = inverse_depth_std(sigma_m.detach().reshape(-1).to(dt), first.iz_point).contiguous()
    elif leave_out is not None:
        cands = [c.without_frame(leave_out, stride=stride, sigma_m=sigma_m) for c in cands]
        leave_out, stride = None, 1
    agreement = torch.full((b, first.n_frames), float("nan"), device=dev)
    disagreement = bad = None
    if first.frame is not None and target_frame is not None and any(c.pixel.numel() for c in cands):
        with torch.no_grad():
            bad, agreement, disagreement = frame_agreement(cands, st, target_frame, compiled=compiled)
            bad = bad if bool(bad.any()) else None
    wanted = None
    if pixels is not None:
        if tuple(pixels.shape) != (b, h, w) or pixels.dtype != torch.bool:
            raise ValueError(f"pixels must be a ({b}, {h}, {w}) bool mask, got {tuple(pixels.shape)} {pixels.dtype}")
        wanted = pixels.reshape(-1).contiguous()
    table = n_tiles = None
    if pixelwise and bad is not None:
        table = slot_table(first.size, first.n_frames, st.agreement_tile_px, dev)
        n_tiles = bad.numel() // (b * first.n_frames)
    parts = []
    for blk in cands:
        if pixelwise:
            with torch.no_grad():
                out = _pixelwise_block(
                    blk,
                    st,
                    target_frame=target_frame,
                    with_sigma=with_sigma,
                    bad=bad,
                    table=table,
                    n_tiles=n_tiles or 1,
                    leave_out=leave_out,
                    stride=stride,
                    s_point=s_point,
                    wanted=wanted,
                )
            if out is not None:
                parts.append(out)
                continue
            if leave_out is not None:  # the tensors' way: the candidates without the frame, copied
                blk = blk.without_frame(leave_out, stride=stride, sigma_m=sigma_m)
        if bad is not None:  # a frame (or a region of it) that disagrees with the target stays out
            with torch.no_grad():
                pixel = blk.pixel + blk.first_pixel if blk.first_pixel else blk.pixel
                slot = agreement_slot(
                    pixel, blk.frame, size=blk.size, n_frames=blk.n_frames, tile_px=st.agreement_tile_px
                )
                blk = blk.select((~bad[slot]).nonzero().squeeze(1))
        parts.append(
            _composite_block(
                blk, st, n_pix=blk.pixels, target_frame=target_frame, with_sigma=with_sigma, compiled=compiled
            )
        )
    depth, wsum, count, sigma = (parts[0][i] if len(parts) == 1 else torch.cat([p[i] for p in parts]) for i in range(4))
    if wanted is not None:  # the tensors' path composited every pixel: the unwanted left empty
        depth, wsum, count, sigma = (torch.where(wanted, v, torch.zeros_like(v)) for v in (depth, wsum, count, sigma))
    return GTRender(
        depth.reshape(b, 1, h, w).to(dt),
        wsum.reshape(b, 1, h, w),
        count.reshape(b, 1, h, w),
        sigma.reshape(b, 1, h, w),
        agreement,
        disagreement,
    )


def render_gt(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    valid: torch.Tensor | None = None,
    settings: RenderSettings = RenderSettings(),
    *,
    normals_cam: torch.Tensor | None = None,
    sigma_m: torch.Tensor | None = None,
    frame: torch.Tensor | None = None,
    src_hw: tuple[int, int] | None = None,
    target_frame: int | None = None,
) -> GTRender:
    """GT depth from a merged point cloud (paper eq. 5 with a geometric surface choice).

    For every pixel, at its sample position (the pixel centre; with ``src_hw`` the
    position of the source pixel that the nearest resize of the input takes it from,
    so that GT, input and a resized truth describe the same point):

    1. candidates: the points projecting strictly within R = ``radius_px``; each has
       its inverse depth iz, its expected std in inverse depth s = sigma_z / z^2
       (``sigma_m``, else the settings' z^2 law) and its frame;
    2. surfaces: the candidates sorted by iz split wherever consecutive ones differ by
       more than ``gap_sigmas`` x sqrt(s1^2 + s2^2) (+ ``gap_slope_rel`` x iz x their
       distance in px); the front surface F is the nearest one with samples of
       ``min_frames`` frames or the target's own sample at the position (else the
       nearest), B the next such surface behind it;
    3. visibility: F takes the pixel when its samples reach ``edge_margin_px`` beyond
       the sample position (opposite their centroid; with frame ids, as far as
       ``edge_vote`` of the frames that see it or what lies behind it reach, each
       frame's reach plus ``edge_vote_slack_px``); else B when it does, or when
       neither does, the one with the nearer sample; with no B, F when
       ``extend_uncovered``. Ambiguous pixels (F's edge within ``ambiguous_px`` of the
       margin, B present) are left empty with ``drop_ambiguous``;
    4. estimate: the m samples of the chosen surface nearest to the position, weights
       w = exp(-d / R^2) / s^2; inverse depth at the position from a weighted plane fit
       (``plane``), depth = 1 / iz;
    5. confidence: sigma = c z^2 sqrt((mean s^2 + residual^2) / n_frames x (1 +
       extrapolation)) in metres (c = 0.53, calibrated on the tuning set), n_frames the distinct frames among the kept samples
       (samples of one frame share its correlated noise), residual the weighted RMS
       of the plane fit, extrapolation o^T C^-1 o (o the samples' mean offset, C their
       covariance, both in px); ambiguous pixels add half the step to B in quadrature.
       ``max_sigma_m`` drops pixels above it.

    Differentiable w.r.t. ``points_cam`` and ``normals_cam`` through the weights and
    the plane fit; the selection is piecewise constant. Vectorised: one stable sort of
    the candidates, scatter reductions, a closed-form 2x2 solve per pixel.

    Composed of parts, as PyTorch3D's points renderer: the rasteriser
    :func:`rasterise_gt` (step 1, a :class:`RenderCandidates` record) and the compositor
    :func:`composite_gt` (steps 2-5); a caller that renders the same cloud twice (the
    leave-target-out render of :func:`depthgt.gt.render.fuse`) calls them itself.

    Args:
        points_cam: (B, N, 3) points in metres in the target camera (the caller
            concatenates the frames of the frame set, see :func:`cloud_in_target`).
        K: (B, 3, 3) target intrinsics at ``size_hw``.
        size_hw: output (H, W).
        valid: (B, N) bool or None (all valid).
        settings: :class:`RenderSettings`.
        normals_cam: (B, N, 3) unit normals in the target camera, or None; zero or
            non-finite rows mean "no normal".
        sigma_m: (B, N) expected std of each point's depth in metres, or None (the
            settings' law with ``noise_sigma_1m``, :data:`KINECT_SIGMA_1M` if None).
        frame: (B, N) long frame index of each point (0..J-1), or None (each point
            counts as its own frame for ``min_frames`` and the confidence).
        src_hw: (H, W) of the images the output's sample positions come from (see
            :func:`resampled_positions`); None = pixel centres.
        target_frame: the ``frame`` index of the target view's own depth, if fused: a
            surface with a target sample within 0.05 px of a pixel's position is seen
            there, so it qualifies as front surface whatever ``min_frames`` says (a
            thin pole that only the target caught stays).
    Returns:
        :class:`GTRender` (depth, weight_sum, count, sigma), each (B, 1, H, W).

    Long for its docstring, the rule step by step; its code is 12 lines.
    """
    cands = rasterise_gt(
        points_cam,
        K,
        size_hw,
        settings,
        valid=valid,
        normals_cam=normals_cam,
        sigma_m=sigma_m,
        frame=frame,
        src_hw=src_hw,
    )
    return composite_gt(cands, settings, target_frame=target_frame)
