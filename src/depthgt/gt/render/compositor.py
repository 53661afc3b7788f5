"""The GT compositor: candidates -> surfaces, visibility, the plane fit and the confidence."""

from __future__ import annotations

from typing import NamedTuple

import torch

from depthgt.gt.render.agreement import _agreement_slot, _frame_agreement
from depthgt.gt.render.rasteriser import _HIT_PX, RenderCandidates, rasterise_gt
from depthgt.gt.render.settings import RenderSettings
from depthgt.rasterise import rank_in_pixel

__all__ = ["GTRender", "composite_gt", "render_gt"]


#: scale of the error model in the confidence, calibrated on the tuning set of
#: bench/bench_gt_protocol.py so that the median |GT - truth| / sigma is 0.674, as for
#: Gaussian errors (the model alone overstates the typical error by ~1.9x)
_SIGMA_SCALE = 0.53


class GTRender(NamedTuple):
    """Output of :func:`render_gt` (:func:`composite_gt`).

    depth: (B, 1, H, W) GT depth in metres, 0 = no GT.
    weight_sum: (B, 1, H, W) sum of the spatial weights exp(-d / R^2) of the kept samples.
    count: (B, 1, H, W) int64 number of kept samples.
    sigma: (B, 1, H, W) expected standard deviation of ``depth`` in metres (the
        per-pixel confidence; 0 where nothing was estimated).
    agreement: (B, J) share of each frame's samples that agree with the target's own
        depth (NaN where not judged: no ``target_frame``, the target itself, fewer than
        200 samples compared); frames
        below ``min_frame_agreement`` were left out (with ``agreement_tile_px``: their
        regions below it). (B, 0) without frame ids.
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


def _keep_m_nearest(
    pixel: torch.Tensor, d2: torch.Tensor, keep: torch.Tensor, *, m: int, r2: float, n_pix: int
) -> torch.Tensor:
    """Restrict ``keep`` to the m kept candidates of smallest d2 in every pixel.

    Avoids sorting all candidates: a per-pixel histogram of d2 in ``nb`` bins finds the
    bin where the count reaches m; bins before it are kept whole and only the
    candidates of that boundary bin are ranked exactly (by :func:`segment_rank_keep`).
    """
    if pixel.numel() == 0 or int(torch.bincount(pixel, weights=keep.to(torch.float32), minlength=n_pix).max()) <= m:
        return keep  # no pixel holds more than m: nothing to cap
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


class _Surfaces(NamedTuple):
    """Per-candidate surface (cluster) ids and per-pixel choice of :func:`_choose_surfaces`.

    cluster: (C,) long cluster id of every candidate (clusters numbered pixel by
        pixel, front to back). keep: (C,) bool, candidate of the chosen surface.
    ambiguous: (P,) bool per pixel; step_iz: (P,) inverse-depth step between the front
        surface and the one behind (0 where there is none).
    """

    cluster: torch.Tensor
    keep: torch.Tensor
    ambiguous: torch.Tensor
    step_iz: torch.Tensor


def _segment_sums(index: torch.Tensor, values: list[torch.Tensor], n: int) -> list[torch.Tensor]:
    """(n,) sums of each (C,) tensor in ``values`` over the segments ``index`` (C,), which
    must be sorted (candidates by pixel, or clusters numbered in that order).

    On the CPU ``torch.segment_reduce`` over the run lengths (the same sums, bit for bit,
    ~40 % faster than ``index_add``); elsewhere one 1-D ``index_add`` each."""
    if index.device.type != "cpu":
        return [torch.zeros(n, dtype=v.dtype, device=v.device).index_add(0, index, v) for v in values]
    lengths = torch.bincount(index, minlength=n)
    return [torch.segment_reduce(v, "sum", lengths=lengths, unsafe=True) for v in values]


def _choose_surfaces(c: RenderCandidates, st: RenderSettings, target_frame: int | None = None) -> _Surfaces:
    """Group each pixel's candidates into surfaces by gaps in inverse depth and pick the
    visible one (see :class:`RenderSettings`), on the candidates ``c`` (sorted by pixel
    and, within a pixel, front first; used detached).

    Longer than most functions here: its steps (clusters, support, front and behind,
    reach, the choice) share a dozen per-cluster tensors, and passing them between
    smaller functions read worse than one function in the order of the rule."""
    pixel, frame, s_iz = c.pixel, c.frame, c.s
    iz, ox, oy, d2 = c.iz.detach(), c.ox.detach(), c.oy.detach(), c.d2.detach()
    n_pix = c.size[0] * c.size[1] * c.size[2]
    dev = pixel.device
    apart = torch.hypot(ox[1:] - ox[:-1], oy[1:] - oy[:-1])  # px
    tol = st.gap_sigmas * torch.hypot(s_iz[:-1], s_iz[1:]) + st.gap_slope_rel * iz[:-1] * apart
    new = torch.ones_like(pixel, dtype=torch.bool)
    new[1:] = (pixel[1:] != pixel[:-1]) | ((iz[:-1] - iz[1:]) > tol)
    cluster = torch.cumsum(new.to(torch.long), 0) - 1  # numbered pixel by pixel, front to back
    n_cl = int(cluster[-1]) + 1
    cl_pixel = pixel.index_select(0, new.nonzero().squeeze(1))  # (faster than pixel[new] on ~2 M candidates)
    # support: distinct frames (each point its own frame when no frame ids are given)
    if frame is None:
        support = torch.bincount(cluster, minlength=n_cl)
    else:
        n_frames = int(frame.max()) + 1
        present = torch.zeros(n_cl * n_frames, dtype=torch.bool, device=dev)
        present[cluster * n_frames + frame] = True
        support = present.view(n_cl, n_frames).sum(1)
    qualified = support >= st.min_frames
    if target_frame is not None and frame is not None:
        # the target's own sample at a pixel's position: that surface is seen there
        qualified[cluster.index_select(0, ((frame == target_frame) & (d2 <= _HIT_PX**2)).nonzero().squeeze(1))] = True
    idx = torch.arange(n_cl, device=dev)
    none = torch.full((n_pix,), n_cl, dtype=torch.long, device=dev)
    first_q = none.scatter_reduce(0, cl_pixel, torch.where(qualified, idx, n_cl), reduce="amin")
    first = none.scatter_reduce(0, cl_pixel, idx, reduce="amin")
    front = torch.where(first_q < n_cl, first_q, first)
    behind = none.scatter_reduce(
        0, cl_pixel, torch.where(qualified & (idx > front.index_select(0, cl_pixel)), idx, n_cl), reduce="amin"
    )
    has_f, has_b = front < n_cl, behind < n_cl
    # coverage: how far each surface's samples reach beyond the sample position,
    # measured opposite their centroid (negative: they all lie on one side)
    cnt = torch.bincount(cluster, minlength=n_cl).to(ox.dtype)
    mx, my, iz_cl = (v / cnt for v in _segment_sums(cluster, [ox, oy, iz], n_cl))
    norm = torch.hypot(mx, my)
    centred = norm <= 1e-9
    inv = 1.0 / norm.clamp_min(1e-12)
    ex = torch.where(centred, torch.ones_like(mx), mx * inv)
    ey = torch.where(centred, torch.zeros_like(my), my * inv)
    t = ox * ex.index_select(0, cluster) + oy * ey.index_select(0, cluster)
    t_min = torch.full((n_cl,), float("inf"), dtype=ox.dtype, device=dev).scatter_reduce(0, cluster, t, reduce="amin")
    reach = torch.where(centred, torch.full_like(t_min, float("inf")), -t_min)
    if st.edge_vote > 0 and frame is not None:
        # Each frame's own reach: the surface's edge is where ``edge_vote`` of its frames
        # reach (the median edge of frames whose edges jitter and fatten on a real
        # sensor), not where the farthest one does (their union, biased outwards). One
        # frame's samples lie ~1 px apart, so its reach falls short of its edge by up to
        # 1 px: ``edge_vote_slack_px`` (half of that) is added back.
        # The voters: the frames with samples on the surface or behind it at the pixel (a
        # frame that sees only what lies behind has its edge before the position).
        cf = cluster * n_frames + frame
        r_cf = -torch.full((n_cl * n_frames,), float("inf"), dtype=ox.dtype, device=dev).scatter_reduce(
            0, cf, t, reduce="amin"
        )
        r_sorted = r_cf.view(n_cl, n_frames).sort(dim=1, descending=True).values  # absent frames: -inf, last
        last = (
            torch.full((n_pix * n_frames,), -1, dtype=torch.long, device=dev)
            .scatter_reduce(0, pixel * n_frames + frame, cluster, reduce="amax")
            .view(n_pix, n_frames)
        )  # back-most cluster of each frame
        voters = (last.index_select(0, cl_pixel) >= idx[:, None]).sum(1)
        k = torch.ceil(st.edge_vote * voters.to(ox.dtype)).long().clamp(1, n_frames) - 1
        reach = torch.where(
            centred, reach, torch.minimum(reach, r_sorted.gather(1, k[:, None]).squeeze(1) + st.edge_vote_slack_px)
        )
    d_near = torch.full((n_cl,), float("inf"), dtype=d2.dtype, device=dev).scatter_reduce(0, cluster, d2, reduce="amin")
    hit = d_near <= _HIT_PX**2  # a sample at the position itself (the target's own, typically)
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
    if st.target_resolves_ambiguous and target_frame is not None and frame is not None:
        # the target's own sample at the position decides a pixel left undecided, on a
        # surface that other frames support too
        own = (frame == target_frame) & (d2 <= _HIT_PX**2)
        own_cl = cluster[own]
        own_cl = own_cl[support.index_select(0, own_cl) >= st.min_frames]
        px = cl_pixel.index_select(0, own_cl)
        undecided = (chosen.index_select(0, px) < 0) | ambiguous.index_select(0, px)
        own_cl, px = own_cl[undecided], px[undecided]
        chosen[px] = own_cl
        ambiguous[px] = False
    use = chosen >= 0
    keep = cluster == chosen.index_select(0, pixel)
    iz_f = iz_cl.index_select(0, fi)
    step = torch.where(has_b, (iz_f - iz_cl.index_select(0, bi)).abs(), torch.zeros_like(iz_f))
    return _Surfaces(cluster, keep, ambiguous & use, step)


def _empty_render(c: RenderCandidates, agreement: torch.Tensor, disagreement: torch.Tensor | None = None) -> GTRender:
    """The :class:`GTRender` of no candidates: zero depth, weights, counts and sigmas."""
    b, h, w = c.size
    zeros_img = torch.zeros(b, 1, h, w, dtype=c.iz_point.dtype, device=c.pixel.device)
    return GTRender(
        zeros_img,
        zeros_img.clone(),
        torch.zeros(b, 1, h, w, dtype=torch.int64, device=zeros_img.device),
        zeros_img.clone(),
        agreement,
        disagreement,
    )


def _estimate(
    c: RenderCandidates,
    st: RenderSettings,
    *,
    target_frame: int | None,
    agreement: torch.Tensor,
    disagreement: torch.Tensor | None,
    with_sigma: bool = True,
) -> GTRender:
    """Steps 2-5 of :func:`render_gt` on the candidates ``c``: surfaces,
    visibility, the m nearest samples, the plane fit and the confidence (with
    ``with_sigma`` or ``max_sigma_m``; else ``sigma`` is zero).

    Long because the plane fit and the confidence reuse the weighted sums of the same
    kept samples (a dozen per-pixel tensors); split, they would travel between functions
    as long argument lists.
    """
    if c.pixel.numel() == 0:  # every candidate left out by the agreement check
        return _empty_render(c, agreement, disagreement)
    b, h, w = c.size
    n_pix = b * h * w
    r2 = st.radius_px**2
    dt, dev = c.iz.dtype, c.iz.device
    with torch.no_grad():
        surf = _choose_surfaces(c, st, target_frame)
        keep = _keep_m_nearest(c.pixel, c.d2, surf.keep, m=st.m, r2=r2, n_pix=n_pix)
    kept = c.select(keep.nonzero().squeeze(1))  # from here on, only the kept samples
    pixel, d2, iz, s, ox, oy = kept.pixel, kept.d2, kept.iz, kept.s, kept.ox, kept.oy
    w_sp = torch.exp(-d2 / r2)
    s_ref = s.median() if s.numel() else torch.ones((), dtype=dt, device=dev)
    wt = w_sp * (s_ref / s) ** 2  # inverse-variance weights (scaled: only ratios matter)
    if c.grad is None or st.plane == "none":
        gx = gy = torch.zeros_like(iz)
    else:
        g = c.grad.index_select(0, kept.point)
        gx, gy = g[:, 0], g[:, 1]
    sw, s_iz, s_x, s_y, s_gx, s_gy, wsum = _segment_sums(
        pixel, [wt, wt * iz, wt * ox, wt * oy, wt * gx, wt * gy, w_sp], n_pix
    )
    has = sw > 0
    sw_safe = torch.where(has, sw, torch.ones_like(sw))
    mean_iz, mean_x, mean_y, mean_gx, mean_gy = (v / sw_safe for v in (s_iz, s_x, s_y, s_gx, s_gy))
    cxo, cyo = (
        ox - mean_x.index_select(0, pixel),
        oy - mean_y.index_select(0, pixel),
    )  # offsets about the weighted centroid
    if st.plane == "fit":
        diz = iz - mean_iz.index_select(0, pixel)
        wx, wy = wt * cxo, wt * cyo
        cxx, cyy, cxy, cxz, cyz = (
            v / sw_safe for v in _segment_sums(pixel, [wx * cxo, wy * cyo, wx * cyo, wx * diz, wy * diz], n_pix)
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
            iz_hat.index_select(0, pixel) + slope_x.index_select(0, pixel) * ox + slope_y.index_select(0, pixel) * oy
        )
    else:
        wx, wy = wt * cxo, wt * cyo
        cxx, cyy, cxy = (v / sw_safe for v in _segment_sums(pixel, [wx * cxo, wy * cyo, wx * cyo], n_pix))
        if st.plane == "normals":
            iz_c = iz - gx * ox - gy * oy  # each sample moved along its tangent plane to the position
            iz_hat = _segment_sums(pixel, [wt * iz_c], n_pix)[0] / sw_safe
            resid = iz_c - iz_hat.index_select(0, pixel)
        else:
            iz_hat = mean_iz
            resid = iz - iz_hat.index_select(0, pixel)
    count = torch.bincount(pixel, minlength=n_pix)
    good = has & (count >= st.min_points) & (iz_hat > 0)
    depth = torch.where(good, 1.0 / torch.where(good, iz_hat, torch.ones_like(iz_hat)), torch.zeros_like(iz_hat))
    with torch.no_grad():
        if with_sigma or st.max_sigma_m is not None:
            moments = (mean_x.detach(), mean_y.detach(), cxx.detach(), cyy.detach(), cxy.detach())
            sigma = _confidence(
                kept,
                st,
                wt=wt.detach(),
                resid=resid.detach(),
                depth=depth.detach(),
                sw=sw_safe.detach(),
                moments=moments,
                surf=surf,
            )
            sigma = torch.where(good, sigma, torch.zeros_like(sigma))
        else:
            sigma = torch.zeros_like(depth.detach())
        if st.max_sigma_m is not None:
            good = good & (sigma <= st.max_sigma_m)
    depth = torch.where(good, depth, torch.zeros_like(depth))
    return GTRender(
        depth.reshape(b, 1, h, w),
        wsum.reshape(b, 1, h, w),
        count.reshape(b, 1, h, w),
        sigma.reshape(b, 1, h, w),
        agreement,
        disagreement,
    )


def _confidence(
    kept: RenderCandidates,
    st: RenderSettings,
    *,
    wt: torch.Tensor,
    resid: torch.Tensor,
    depth: torch.Tensor,
    sw: torch.Tensor,
    moments: tuple[torch.Tensor, ...],
    surf: _Surfaces,
) -> torch.Tensor:
    """(P,) expected std of the fused depth in metres (see :func:`render_gt`, step 5) from
    the ``kept`` samples, their weights ``wt`` (C,) and plane-fit residuals ``resid`` (C,),
    the fused ``depth`` (P,), the weight sums ``sw`` (P,), the samples' weighted
    ``moments`` (mean offsets x, y and covariances xx, yy, xy about them, each (P,), px)
    and the ``surf`` choice."""
    pixel, s, fr = kept.pixel, kept.s, kept.frame
    n_pix = kept.size[0] * kept.size[1] * kept.size[2]
    dt = wt.dtype
    model, res2 = (v / sw for v in _segment_sums(pixel, [wt * s * s, wt * resid * resid], n_pix))
    # distinct frames among the kept samples (each point its own frame without frame ids)
    if fr is None:
        n_frames = torch.bincount(pixel, minlength=n_pix).to(dt)
    else:
        j = int(fr.max()) + 1
        present = torch.zeros(n_pix * j, dtype=torch.bool, device=wt.device)
        present[pixel * j + fr] = True
        n_frames = present.view(n_pix, j).sum(1).to(dt)
    mx, my, cxx, cyy, cxy = moments
    lam = st.slope_prior + 1e-6
    a11, a22, a12 = cxx + lam, cyy + lam, cxy
    det = (a11 * a22 - a12 * a12).clamp_min(1e-12)
    extrap = (a22 * mx * mx - 2 * a12 * mx * my + a11 * my * my) / det  # o^T C^-1 o
    var_iz = (model + res2) / n_frames.clamp_min(1.0) * (1.0 + extrap)
    z2 = depth * depth
    sigma2 = _SIGMA_SCALE**2 * z2 * z2 * var_iz
    step_m = z2 * surf.step_iz  # depth step to the surface behind (first order)
    sigma2 = sigma2 + torch.where(surf.ambiguous, (0.5 * step_m) ** 2, torch.zeros_like(sigma2))
    return torch.sqrt(sigma2)


def composite_gt(
    cands: RenderCandidates,
    settings: RenderSettings = RenderSettings(),
    *,
    target_frame: int | None = None,
    with_sigma: bool = True,
) -> GTRender:
    """Steps 2-5 of :func:`render_gt` on the rasteriser's candidates: with
    ``target_frame`` the frames (or regions) that disagree with the target's own depth
    are left out first (:attr:`GTRender.agreement`); then surfaces, visibility, the
    ``m`` nearest samples, the plane fit and the confidence (with ``with_sigma`` or
    ``max_sigma_m``, else ``sigma`` is zero).

    The leave-target-out render is this compositor over the same candidates without the
    target's (:meth:`RenderCandidates.without_frame`), no ``target_frame``.
    """
    st = settings
    b = cands.size[0]
    dev = cands.pixel.device
    agreement = torch.full((b, cands.n_frames), float("nan"), device=dev)
    if cands.pixel.numel() == 0:
        return _empty_render(cands, agreement)
    disagreement = None
    if cands.frame is not None and target_frame is not None:
        with torch.no_grad():
            bad, agreement, disagreement = _frame_agreement(cands, st, target_frame)
            if bad.any():  # a frame (or a region of it) that disagrees with the target stays out
                slot = _agreement_slot(
                    cands.pixel, cands.frame, size=cands.size, n_frames=cands.n_frames, tile_px=st.agreement_tile_px
                )
                cands = cands.select((~bad[slot]).nonzero().squeeze(1))
    return _estimate(
        cands, st, target_frame=target_frame, agreement=agreement, disagreement=disagreement, with_sigma=with_sigma
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

    Long for its docstring, the rule step by step; its code is 25 lines.
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
