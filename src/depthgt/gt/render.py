"""The GT renderer of paper eq. 5: the merged frame-set cloud fused into the target view.

It composes the shared rasteriser (:mod:`depthgt.rasterise`: every point paired with
the pixels whose sample positions lie within ``radius_px`` of its projection; the soft
splat of the registration, :mod:`depthgt.splatting`, uses it too) with its own
compositor: the candidates made front first (the points sorted by inverse depth) and
sorted once by pixel (a stable int32 sort), grouped into surfaces by gaps in inverse
depth scaled to the sensor's noise
(:mod:`depthgt.noise_law`), the visible surface picked by its support and its sampled
footprint, frames (or regions of them) that disagree with the target left out, and a
weighted plane fitted in inverse depth per pixel (closed-form 2x2 solves), with a
per-pixel confidence. No Python loop runs over points or pixels;
``tests/render_reference.py`` holds the plain loop versions (test oracles).

Measured (bench/bench_gt_protocol.py, evaluation set of 45 synthetic frame sets never
used for tuning, see bench/README.md): from the clean depth of the 6 neighbours
with exact poses the GT is within 0.95 mm MAE of the truth (grazing pixels 1.4 mm,
beyond 4 m 1.9 mm); from Kinect-noised depth its MAE is 0.26x the input's where both
have depth.

Layouts: points (B, N, 3) metres in the camera frame, intrinsics (B, 3, 3) at the
output resolution, images (B, C, H, W), depth (B, 1, H, W) metres with 0 = nothing."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from kornia.geometry.depth import depth_to_normals
from kornia.geometry.linalg import transform_points

from depthgt.device import plain_cpu_convolutions
from depthgt.geometry import backproject
from depthgt.noise_law import (KINECT_SIGMA_1M, Residuals, depth_sigma_m, estimate_noise_sigma_1m, noise_sigma_1m_from,
                               second_difference_residuals)
from depthgt.rasterise import candidates, check_points, front_to_back, rank_in_pixel, resampled_positions, sort_by_pixel
from depthgt.settings import RenderSettings
from depthgt.splatting import SoftSplat, splat_soft  # re-exported: the renderer's public names

__all__ = ["SoftSplat", "splat_soft", "GTRender", "render_gt", "TargetCloud", "cloud_in_target",
           "depth_sigma_m", "estimate_noise_sigma_1m", "resampled_positions", "KINECT_SIGMA_1M"]




# --------------------------------------------------------------------------- GT renderer (eq. 5)

#: a surface with a sample this close to a pixel's sample position covers it (px)
_HIT_PX = 0.05
#: scale of the error model in the confidence, calibrated on the tuning set of
#: bench/bench_gt_protocol.py so that the median |GT - truth| / sigma is 0.674, as for
#: Gaussian errors (the model alone overstates the typical error by ~1.9x)
_SIGMA_SCALE = 0.53
#: frame agreement: samples within this of a target sample are compared with it (px);
#: a frame is judged on at least this many comparisons
_NEAR_PX = 0.5
_MIN_COMPARED = 200
#: per-region agreement (``agreement_tile_px``): a tile is judged on the comparisons of
#: its 3x3 tile neighbourhood, when there are at least this many
_MIN_TILE_COMPARED = 50


class GTRender(NamedTuple):
    """Output of :func:`render_gt`.

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
    left_out: with ``leave_out_frame``, the render of the other frames alone (no
        agreement check; the leave-target-out check of real data; with
        ``leave_out_stride`` only at those pixels), else None. Its ``sigma`` is zero
        unless ``max_sigma_m`` needs it (the check uses the depth only).
    """

    depth: torch.Tensor
    weight_sum: torch.Tensor
    count: torch.Tensor
    sigma: torch.Tensor
    agreement: torch.Tensor
    disagreement: torch.Tensor | None = None
    left_out: "GTRender | None" = None


def _inverse_depth_planes(points_cam, normals_cam, K, st: RenderSettings) -> torch.Tensor:
    """(B*N, 2) screen-space gradient (d(1/z)/du, d(1/z)/dv) of each point's tangent plane.

    Plane n.X = n.p and X = z K^-1 [u, v, 1] give 1/z = (K^-T n) . [u, v, 1] / (n.p),
    affine in (u, v). Rows are zero (no correction) where the normal is missing, the
    plane is seen at a grazing angle, or the correction within R could exceed
    ``max_correction_rel``.
    """
    nrm = torch.nan_to_num(normals_cam, nan=0.0, posinf=0.0, neginf=0.0)
    d0 = (nrm * points_cam).sum(-1)  # (B, N) n.p
    kn = torch.einsum("bji,bnj->bni", torch.linalg.inv(K.to(torch.float64)).to(points_cam.dtype), nrm)  # K^-T n
    safe = torch.where(d0.abs() > 1e-12, d0, torch.ones_like(d0))
    grad = kn[..., :2] / safe[..., None]
    with torch.no_grad():
        cos = d0.abs() / (nrm.norm(dim=-1) * points_cam.norm(dim=-1)).clamp_min(1e-12)
        z = points_cam[..., 2]
        # |delta(1/z)| <= |grad| R; relative depth change ~ z |grad| R
        ok = (cos >= st.min_cos_incidence) & (z * grad.norm(dim=-1) * st.radius_px <= st.max_correction_rel)
    return (grad * ok[..., None]).reshape(-1, 2)


def _keep_m_nearest(pixel: torch.Tensor, d2: torch.Tensor, keep: torch.Tensor, m: int, r2: float, n_pix: int) -> torch.Tensor:
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
    boundary = torch.where(full.any(dim=1), full.to(torch.int8).argmax(dim=1), torch.full((n_pix,), nb, device=pixel.device))
    before = torch.where(boundary > 0, cum.gather(1, (boundary - 1).clamp_min(0)[:, None]).squeeze(1), torch.zeros_like(boundary))
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


def _choose_surfaces(pixel, iz, s_iz, frame, ox, oy, d2, n_pix: int, st: RenderSettings,
                     target_frame: int | None = None) -> _Surfaces:
    """Group each pixel's candidates into surfaces by gaps in inverse depth and pick the
    visible one (see :class:`RenderSettings`). All inputs (C,), detached, sorted by
    pixel and, within a pixel, by decreasing inverse depth (front first)."""
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
    behind = none.scatter_reduce(0, cl_pixel, torch.where(qualified & (idx > front.index_select(0, cl_pixel)), idx, n_cl), reduce="amin")
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
        r_cf = -torch.full((n_cl * n_frames,), float("inf"), dtype=ox.dtype, device=dev).scatter_reduce(0, cf, t, reduce="amin")
        r_sorted = r_cf.view(n_cl, n_frames).sort(dim=1, descending=True).values  # absent frames: -inf, last
        last = torch.full((n_pix * n_frames,), -1, dtype=torch.long, device=dev).scatter_reduce(
            0, pixel * n_frames + frame, cluster, reduce="amax").view(n_pix, n_frames)  # back-most cluster of each frame
        voters = (last.index_select(0, cl_pixel) >= idx[:, None]).sum(1)
        k = torch.ceil(st.edge_vote * voters.to(ox.dtype)).long().clamp(1, n_frames) - 1
        reach = torch.where(centred, reach, torch.minimum(reach, r_sorted.gather(1, k[:, None]).squeeze(1) + st.edge_vote_slack_px))
    d_near = torch.full((n_cl,), float("inf"), dtype=d2.dtype, device=dev).scatter_reduce(0, cluster, d2, reduce="amin")
    hit = d_near <= _HIT_PX**2  # a sample at the position itself (the target's own, typically)
    covered = (reach >= st.edge_margin_px) | hit
    fi, bi = front.clamp_max(n_cl - 1), behind.clamp_max(n_cl - 1)
    cov_f, cov_b = covered.index_select(0, fi), covered.index_select(0, bi)
    take_b = has_b & ~cov_f & (cov_b | (d_near.index_select(0, bi) < d_near.index_select(0, fi)))
    use = has_f & (cov_f | has_b | st.extend_uncovered)
    ambiguous = has_f & has_b & ~hit.index_select(0, fi) & ((reach.index_select(0, fi) - st.edge_margin_px).abs() < st.ambiguous_px)
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


def render_gt(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    valid: torch.Tensor | None = None,
    settings: RenderSettings = RenderSettings(),
    normals_cam: torch.Tensor | None = None,
    sigma_m: torch.Tensor | None = None,
    frame: torch.Tensor | None = None,
    src_hw: tuple[int, int] | None = None,
    target_frame: int | None = None,
    leave_out_frame: int | None = None,
    leave_out_sigma_m: torch.Tensor | None = None,
    leave_out_stride: int = 1,
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
        leave_out_frame: also render the cloud without this frame's points, and
            without the agreement check, into ``left_out`` (the leave-target-out
            render, sharing the projection and the sort with the main one).
        leave_out_sigma_m: (B, N) the points' sigmas for that second render (the noise
            estimated without the left-out frame), or None (``sigma_m``).
        leave_out_stride: that second render only at the pixels of every this-th row and
            column (others empty); each holds what the full render gives it (to float
            rounding: the weights' common scale is the median sigma of the kept samples).

    Returns:
        :class:`GTRender` (depth, weight_sum, count, sigma), each (B, 1, H, W).
    """
    valid = check_points(points_cam, K, valid, size_hw)
    b, n = points_cam.shape[:2]
    for name, t, shape in (("normals_cam", normals_cam, (b, n, 3)), ("sigma_m", sigma_m, (b, n)), ("frame", frame, (b, n)),
                           ("leave_out_sigma_m", leave_out_sigma_m, (b, n))):
        if t is not None and tuple(t.shape) != shape:
            raise ValueError(f"{name} must be {shape} to match points_cam {tuple(points_cam.shape)}, got {tuple(t.shape)}")
    st = settings
    h, w = int(size_hw[0]), int(size_hw[1])
    n_pix = b * h * w
    r2 = st.radius_px**2
    dev, dt = points_cam.device, points_cam.dtype
    grid = None
    if src_hw is not None:
        grid = (resampled_positions(int(src_hw[1]), w, dev, dt), resampled_positions(int(src_hw[0]), h, dev, dt))
    z_all = points_cam[..., 2].reshape(-1)
    iz_all = 1.0 / z_all.clamp_min(st.min_depth_m)
    with torch.no_grad():  # the candidates come front first: one sort of the points, not of the candidates
        by_depth = front_to_back(iz_all)
    cand, _ = candidates(points_cam, K, valid, (h, w), st.radius_px, st.min_depth_m, grid, point_order=by_depth)
    pixel = cand.pixel
    zeros_img = torch.zeros(b, 1, h, w, dtype=dt, device=dev)
    if pixel.numel() == 0:
        n_fr = 0 if frame is None else int(frame.max()) + 1 if frame.numel() else 0
        empty = GTRender(zeros_img, zeros_img.clone(), torch.zeros(b, 1, h, w, dtype=torch.int64, device=dev), zeros_img.clone(),
                         torch.full((b, n_fr), float("nan"), device=dev))
        return empty._replace(left_out=empty) if leave_out_frame is not None and frame is not None else empty
    with torch.no_grad():
        if sigma_m is None:
            sig_1m = KINECT_SIGMA_1M if st.noise_sigma_1m is None else st.noise_sigma_1m
            sz = depth_sigma_m(z_all.detach(), sig_1m, st.noise_sigma_abs_m)
        else:
            sz = sigma_m.detach().reshape(-1).to(dt)
        s_all = (sz * iz_all.detach() ** 2).clamp_min(1e-12)  # std in inverse depth
        s_all_lo = None
        if leave_out_sigma_m is not None:
            s_all_lo = (leave_out_sigma_m.detach().reshape(-1).to(dt) * iz_all.detach() ** 2).clamp_min(1e-12)
    grad = None if normals_cam is None else _inverse_depth_planes(points_cam, normals_cam, K, st)
    ox, oy = -cand.dx, -cand.dy  # projection minus sample position, px
    with torch.no_grad():
        pixel, order = sort_by_pixel(pixel)  # by pixel, front first (stable: the candidates' order)
    point = cand.point.index_select(0, order)
    ox, oy = ox.index_select(0, order), oy.index_select(0, order)
    d2 = ox * ox + oy * oy  # as the rasteriser computes it (dx^2 + dy^2, dx = -ox): bit for bit, cheaper than a gather
    iz, s = iz_all.index_select(0, point), s_all.index_select(0, point)
    fr = None if frame is None else frame.reshape(-1).index_select(0, point)
    pixel_all, d2_all, ox_all, oy_all, point_all, s_pre, fr_all = pixel, d2, ox, oy, point, s, fr
    agreement = torch.zeros(b, 0, device=dev)
    disagreement = None
    if fr is not None:
        n_fr = int(frame.max()) + 1
        agreement = torch.full((b, n_fr), float("nan"), device=dev)
        if target_frame is not None:
            with torch.no_grad():
                bad, agreement, disagreement = _frame_agreement(pixel, iz.detach(), s, fr, d2.detach(), b, n_fr, (h, w), st,
                                                                target_frame)
                if bad.any():  # a frame (or a region of it) that disagrees with the target stays out
                    ok = ~bad[_agreement_slot(pixel, fr, b, n_fr, (h, w), st.agreement_tile_px)]
                    sel = ok.nonzero().squeeze(1)
                    pixel, d2, ox, oy, point, iz, s, fr = (x.index_select(0, sel) for x in (pixel, d2, ox, oy, point, iz, s, fr))
    out = _estimate(pixel, d2, ox, oy, point, iz, s, fr, grad, (b, h, w), st, target_frame, agreement, disagreement)
    if leave_out_frame is not None and frame is not None:
        # the leave-target-out render (the neighbours alone, no agreement check) from the
        # same candidates: the projection, the sort and the clouds are shared
        with torch.no_grad():
            lo = fr_all != leave_out_frame
            if leave_out_stride > 1:  # only the pixels of every leave_out_stride-th row and column
                on_grid = torch.zeros(b, h, w, dtype=torch.bool, device=dev)
                on_grid[:, ::leave_out_stride, ::leave_out_stride] = True
                lo &= on_grid.reshape(-1).index_select(0, pixel_all)
            lo = lo.nonzero().squeeze(1)
        pixel_lo, d2_lo, ox_lo, oy_lo, point_lo, s_lo, fr_lo = (
            x.index_select(0, lo) for x in (pixel_all, d2_all, ox_all, oy_all, point_all, s_pre, fr_all))
        if s_all_lo is not None:  # the sigmas of the noise estimated without the left-out frame
            s_lo = s_all_lo.index_select(0, point_lo)
        left = _estimate(pixel_lo, d2_lo, ox_lo, oy_lo, point_lo, iz_all.index_select(0, point_lo), s_lo, fr_lo, grad,
                         (b, h, w), st, None, torch.full((b, agreement.shape[1]), float("nan"), device=dev), None,
                         with_sigma=False)
        out = out._replace(left_out=left)
    return out


def _estimate(pixel, d2, ox, oy, point, iz, s, fr, grad, bhw, st: RenderSettings, target_frame, agreement,
              disagreement, with_sigma: bool = True) -> GTRender:
    """Steps 2-5 of :func:`render_gt` on the candidates (C,) sorted by pixel, front first:
    surfaces, visibility, the m nearest samples, the plane fit and the confidence (with
    ``with_sigma`` or ``max_sigma_m``; else ``sigma`` is zero)."""
    b, h, w = bhw
    n_pix = b * h * w
    r2 = st.radius_px**2
    dt, dev = iz.dtype, iz.device
    zeros_img = torch.zeros(b, 1, h, w, dtype=dt, device=dev)
    if pixel.numel() == 0:
        return GTRender(zeros_img, zeros_img.clone(), torch.zeros(b, 1, h, w, dtype=torch.int64, device=dev), zeros_img.clone(),
                        agreement, disagreement)
    with torch.no_grad():
        surf = _choose_surfaces(pixel, iz.detach(), s, fr, ox.detach(), oy.detach(), d2.detach(), n_pix, st, target_frame)
        keep = _keep_m_nearest(pixel, d2, surf.keep, st.m, r2, n_pix)
        sub = keep.nonzero().squeeze(1)  # from here on, only the kept samples
    pixel, d2, iz, s, ox, oy, point = (x.index_select(0, sub) for x in (pixel, d2, iz, s, ox, oy, point))
    fr = None if fr is None else fr.index_select(0, sub)
    w_sp = torch.exp(-d2 / r2)
    s_ref = s.median() if s.numel() else torch.ones((), dtype=dt, device=dev)
    wt = w_sp * (s_ref / s) ** 2  # inverse-variance weights (scaled: only ratios matter)
    if grad is None or st.plane == "none":
        gx = gy = torch.zeros_like(iz)
    else:
        g = grad.index_select(0, point)
        gx, gy = g[:, 0], g[:, 1]
    sw, s_iz, s_x, s_y, s_gx, s_gy, wsum = _segment_sums(pixel, [wt, wt * iz, wt * ox, wt * oy, wt * gx, wt * gy, w_sp], n_pix)
    has = sw > 0
    sw_safe = torch.where(has, sw, torch.ones_like(sw))
    mean_iz, mean_x, mean_y, mean_gx, mean_gy = (v / sw_safe for v in (s_iz, s_x, s_y, s_gx, s_gy))
    cxo, cyo = ox - mean_x.index_select(0, pixel), oy - mean_y.index_select(0, pixel)  # offsets about the weighted centroid
    if st.plane == "fit":
        diz = iz - mean_iz.index_select(0, pixel)
        wx, wy = wt * cxo, wt * cyo
        cxx, cyy, cxy, cxz, cyz = (v / sw_safe for v in _segment_sums(pixel, [wx * cxo, wy * cyo, wx * cyo, wx * diz, wy * diz], n_pix))
        lam = st.slope_prior
        a11, a22, a12 = cxx + lam, cyy + lam, cxy
        v1, v2 = cxz + lam * mean_gx, cyz + lam * mean_gy
        det = a11 * a22 - a12 * a12
        ok = det > 1e-12
        det_safe = torch.where(ok, det, torch.ones_like(det))
        slope_x = torch.where(ok, (a22 * v1 - a12 * v2) / det_safe, torch.zeros_like(det))
        slope_y = torch.where(ok, (a11 * v2 - a12 * v1) / det_safe, torch.zeros_like(det))
        iz_hat = mean_iz - slope_x * mean_x - slope_y * mean_y  # the plane at the sample position
        resid = iz - (iz_hat.index_select(0, pixel) + slope_x.index_select(0, pixel) * ox + slope_y.index_select(0, pixel) * oy)
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
            sigma = _confidence(pixel, wt.detach(), s, resid.detach(), fr, depth.detach(), sw_safe.detach(), surf, n_pix,
                                (mean_x.detach(), mean_y.detach(), cxx.detach(), cyy.detach(), cxy.detach()), st)
            sigma = torch.where(good, sigma, torch.zeros_like(sigma))
        else:
            sigma = torch.zeros_like(depth.detach())
        if st.max_sigma_m is not None:
            good = good & (sigma <= st.max_sigma_m)
    depth = torch.where(good, depth, torch.zeros_like(depth))
    return GTRender(depth.reshape(b, 1, h, w), wsum.reshape(b, 1, h, w), count.reshape(b, 1, h, w), sigma.reshape(b, 1, h, w),
                    agreement, disagreement)


def _tile_grid(hw: tuple[int, int], tile_px: int) -> tuple[int, int]:
    """(rows, columns) of the agreement tiles; (1, 1) when ``tile_px`` is 0 (whole frames)."""
    if tile_px <= 0:
        return 1, 1
    return -(-hw[0] // tile_px), -(-hw[1] // tile_px)


def _agreement_slot(pixel: torch.Tensor, fr: torch.Tensor, b: int, n_fr: int, hw: tuple[int, int], tile_px: int) -> torch.Tensor:
    """Index of each sample's (image, frame, tile) in the flat decisions of
    :func:`_frame_agreement`: ((image * J + frame) * tiles + tile), from a per-pixel
    table (one gather, no integer division per sample)."""
    h, w = hw
    ty, tx = _tile_grid(hw, tile_px)
    n_t = ty * tx
    img = torch.arange(b, device=pixel.device)[:, None, None]
    if tile_px <= 0:
        tile = torch.zeros(1, h, w, dtype=torch.long, device=pixel.device)
    else:
        tile = (torch.arange(h, device=pixel.device)[:, None] // tile_px) * tx + torch.arange(w, device=pixel.device)[None] // tile_px
    table = (img * (n_fr * n_t) + tile).reshape(-1)  # per pixel of the B images: image and tile part
    return table.index_select(0, pixel) + fr * n_t


def _frame_agreement(pixel, iz, s, fr, d2, b, n_fr, hw, st, target_frame):
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

    Returns:
        (B * J * tiles,) bool bad (frame, tile) slots (:func:`_agreement_slot`), (B, J)
        float share of agreeing samples per frame (NaN: fewer than ``_MIN_COMPARED``
        comparisons, e.g. the target itself) and the (B, 3, H, W) diagnostic counts of
        :class:`GTRender`.
    """
    h, w = hw
    h_w = h * w
    n_pix = b * h_w
    tgt = ((fr == target_frame) & (d2 <= _HIT_PX**2)).nonzero().squeeze(1)
    iz_t = torch.full((n_pix,), float("nan"), dtype=iz.dtype, device=iz.device)
    s_t = torch.zeros(n_pix, dtype=iz.dtype, device=iz.device)
    pix_t = pixel.index_select(0, tgt)
    iz_t[pix_t] = iz.index_select(0, tgt)
    s_t[pix_t] = s.index_select(0, tgt)
    judge = torch.isfinite(iz_t)
    if st.agreement_edge_px > 0:
        # Not judged next to a depth edge or a hole of the target: a real sensor's edges
        # are fattened and shift between frames by more than its noise law says, and
        # they would outvote the flat surfaces on which a misregistration shows.
        k, r = 2 * st.agreement_edge_px + 1, st.agreement_edge_px
        img = iz_t.reshape(b, 1, h, w)
        hi = F.max_pool2d(torch.nan_to_num(img, nan=float("inf")), k, stride=1, padding=r)
        lo = -F.max_pool2d(-torch.nan_to_num(img, nan=-float("inf")), k, stride=1, padding=r)
        tol = st.gap_sigmas * math.sqrt(2.0) * s_t.reshape(b, 1, h, w) + st.gap_slope_rel * img * (2 * r)
        judge &= ((hi - lo) <= tol).reshape(-1)
    near = (fr != target_frame) & (d2 <= _NEAR_PX**2) & judge.index_select(0, pixel)
    ni = near.nonzero().squeeze(1)
    p, f, s_n, iz_n, d2_n = (x.index_select(0, ni) for x in (pixel, fr, s, iz, d2))
    tol = st.gap_sigmas * torch.hypot(s_n, s_t.index_select(0, p)) + st.gap_slope_rel * iz_n * torch.sqrt(d2_n)
    agree = (iz_n - iz_t.index_select(0, p)).abs() <= tol
    slot = torch.div(p, h_w, rounding_mode="floor") * n_fr + f
    n_cmp = torch.bincount(slot, minlength=b * n_fr).reshape(b, n_fr)
    n_ok = torch.bincount(slot[agree], minlength=b * n_fr).reshape(b, n_fr)
    share = torch.where(n_cmp >= _MIN_COMPARED, n_ok / n_cmp.clamp_min(1), torch.full_like(n_cmp, float("nan"), dtype=torch.float32))
    bad = share < st.min_frame_agreement  # (NaN: not judged)
    if st.agreement_tile_px > 0:
        ty, tx = _tile_grid(hw, st.agreement_tile_px)
        tslot = _agreement_slot(p, f, b, n_fr, hw, st.agreement_tile_px)
        counts = torch.stack([torch.bincount(tslot, minlength=b * n_fr * ty * tx),
                              torch.bincount(tslot[agree], minlength=b * n_fr * ty * tx)]).to(torch.float32)
        # comparisons pooled over each tile's 3x3 neighbourhood (sums: average x 9)
        pooled = F.avg_pool2d(counts.reshape(2 * b * n_fr, 1, ty, tx), 3, stride=1, padding=1, count_include_pad=True) * 9
        n_cmp_t, n_ok_t = pooled.reshape(2, b, n_fr, ty, tx).round()
        judged = n_cmp_t >= _MIN_TILE_COMPARED
        bad_t = torch.where(judged, n_ok_t < st.min_frame_agreement * n_cmp_t, bad[..., None, None])
        bad = bad_t | (share < st.min_whole_frame_agreement)[..., None, None]
    kept = ~bad.reshape(-1)[_agreement_slot(p, f, b, n_fr, hw, st.agreement_tile_px)]
    diag = torch.stack([torch.bincount(p, minlength=n_pix), torch.bincount(p[~agree], minlength=n_pix),
                        torch.bincount(p[kept], minlength=n_pix)]).to(torch.float32)
    return bad.reshape(-1), share.to(torch.float32), diag.reshape(3, b, h, w).transpose(0, 1)


def _confidence(pixel, wt, s, resid, fr, depth, sw, surf: _Surfaces, n_pix, moments, st) -> torch.Tensor:
    """(P,) expected std of the fused depth in metres (see :func:`render_gt`, step 5)."""
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


def _backproject_resampled(depth_m: torch.Tensor, K: torch.Tensor, src_hw: tuple[int, int]) -> torch.Tensor:
    """Back-project (J, 1, H, W) depth made by nearest resizing from ``src_hw``, each pixel
    at the position of its source pixel centre: (J, H*W, 3) metres.

    Written by hand: kornia's depth_to_3d assumes the regular output pixel grid.
    """
    h, w = depth_m.shape[-2:]
    dev, dt = depth_m.device, depth_m.dtype
    v, u = torch.meshgrid(resampled_positions(src_hw[0], h, dev, dt), resampled_positions(src_hw[1], w, dev, dt), indexing="ij")
    z = depth_m[:, 0]
    fx, fy = K[:, 0, 0, None, None], K[:, 1, 1, None, None]
    cx, cy, s = K[:, 0, 2, None, None], K[:, 1, 2, None, None], K[:, 0, 1, None, None]
    y = (v - cy) / fy
    x = (u - cx - s * y) / fx
    return torch.stack([x * z, y * z, z], dim=-1).reshape(depth_m.shape[0], -1, 3)


def _smooth_3x3(res: Residuals, max_rel: float, sigma_1m: float, noise_sigmas: float = 6.0) -> torch.Tensor:
    """(J, 1, H, W) bool: the 3x3 neighbourhood is valid and holds no depth edge.

    An edge is a second difference of inverse depth (``res``, along x or y, zero on any
    plane however slanted) above ``max_rel`` x the inverse depth plus ``noise_sigmas``
    times its noise, anywhere in the 3x3 window."""
    bad = ~res.ok
    for r, both in zip(res.r, res.both):
        bad |= both & (r.abs() > max_rel * res.iz + noise_sigmas * sigma_1m)
    return F.max_pool2d(bad.to(torch.float32), 3, stride=1, padding=1) == 0


class TargetCloud(NamedTuple):
    """The frames of a frame set merged in the target camera (one batch element).

    points: (1, J*H*W, 3) metres; normals: (1, J*H*W, 3) unit normals (zeros where
    unknown); valid: (1, J*H*W) bool (valid depth); frame: (1, J*H*W) long index j of
    each point's frame; sigma_m: (1, J*H*W) expected std of each point's depth in
    metres (the z^2 law of :func:`depth_sigma_m` with the sensor's noise at 1 m).
    """

    points: torch.Tensor
    normals: torch.Tensor
    valid: torch.Tensor
    frame: torch.Tensor
    sigma_m: torch.Tensor


def cloud_in_target(
    depth_m: torch.Tensor,
    K: torch.Tensor,
    T_j_to_t: torch.Tensor,
    normal_max_jump_rel: float = 0.05,
    src_hw: tuple[int, int] | None = None,
    noise_sigma_1m: float | None = None,
    noise_sigma_abs_m: float = RenderSettings.noise_sigma_abs_m,
    residuals: Residuals | None = None,
    normals: torch.Tensor | None = None,
) -> TargetCloud:
    """Back-project J depth images and move their points and normals into the target camera.

    Normals come from :func:`kornia.geometry.depth.depth_to_normals`; they are set to
    zero (unknown) wherever the 3x3 neighbourhood holds an invalid pixel or a depth
    edge: a second difference of inverse depth above ``normal_max_jump_rel`` times the
    inverse depth (plus 6 sigma of the noise). Planes have none at any slant, so
    grazing surfaces keep their normals while edges lose them.

    Args:
        depth_m: (J, 1, H, W) depth in metres, 0 = invalid.
        K: (J, 3, 3) intrinsics of each frame at (H, W).
        T_j_to_t: (J, 4, 4) poses mapping points of frame j into the target camera.
        src_hw: when ``depth_m`` was made by :func:`depthgt.geometry.resize_depth_nearest`
            from images of size ``src_hw``, every pixel holds the depth of the source
            pixel nearest to its centre, up to 0.5 source pixels away; passing
            ``src_hw`` back-projects each depth at that source pixel's exact position
            (in output pixel units) instead of at the output pixel centre, which puts
            the points on the surface (it matters on slanted surfaces and at edges).
        noise_sigma_1m: the sensor's depth sigma at 1 m (metres); None estimates it
            from ``depth_m`` (:func:`estimate_noise_sigma_1m`).
        noise_sigma_abs_m: floor of every point's sigma (metres).
        residuals: :func:`depthgt.noise_law.second_difference_residuals` of ``depth_m``
            when the caller has them (they are computed here otherwise).
        normals: (J, 3, H, W) :func:`kornia.geometry.depth.depth_to_normals` of
            ``depth_m`` and ``K`` when the caller has them (the registration's
            refinement computes the same), else computed here.

    Returns:
        :class:`TargetCloud` with J*H*W points in row-major pixel order, frame by frame.
    """
    if depth_m.ndim != 4 or depth_m.shape[1] != 1:
        raise ValueError(f"depth_m must be (J, 1, H, W), got {tuple(depth_m.shape)}")
    j = depth_m.shape[0]
    if T_j_to_t.shape != (j, 4, 4):
        raise ValueError(f"T_j_to_t must be ({j}, 4, 4) to match depth_m, got {tuple(T_j_to_t.shape)}")
    dtype = depth_m.dtype
    K = K.to(dtype)
    T = T_j_to_t.to(dtype)
    if src_hw is None:
        pts_j = backproject(depth_m, K)
    else:
        pts_j = _backproject_resampled(depth_m, K, src_hw)
    pts = transform_points(T, pts_j)  # (J, HW, 3)
    res = second_difference_residuals(depth_m, src_hw) if residuals is None else residuals
    sigma_1m = noise_sigma_1m_from(res) if noise_sigma_1m is None else float(noise_sigma_1m)
    if normals is None:
        with plain_cpu_convolutions():  # 3x3 filters: ~3x faster than oneDNN's on one thread
            nrm = depth_to_normals(depth_m, K)  # (J, 3, H, W)
    elif normals.shape != (j, 3, *depth_m.shape[-2:]):
        raise ValueError(f"normals must be ({j}, 3, H, W) to match depth_m {tuple(depth_m.shape)}, got {tuple(normals.shape)}")
    else:
        nrm = normals
    flat = _smooth_3x3(res, normal_max_jump_rel, sigma_1m)
    nrm = torch.where(flat & torch.isfinite(nrm).all(dim=1, keepdim=True), nrm, torch.zeros_like(nrm))
    nrm = nrm.flatten(2).transpose(1, 2) @ T[:, :3, :3].transpose(1, 2)  # rotate into the target camera
    valid = (depth_m > 0).reshape(j, -1)
    sigma = depth_sigma_m(depth_m.reshape(j, -1), sigma_1m, noise_sigma_abs_m)  # each point's own sensor depth
    frame = torch.arange(j, device=depth_m.device)[:, None].expand(j, depth_m.shape[-2] * depth_m.shape[-1])
    return TargetCloud(pts.reshape(1, -1, 3), nrm.reshape(1, -1, 3), valid.reshape(1, -1), frame.reshape(1, -1),
                       sigma.reshape(1, -1))
