"""The GT renderer of paper eq. 5: the merged frame-set cloud fused into the target view.

Two parts, as PyTorch3D's points renderer: a rasteriser, :func:`rasterise_gt` (the
shared point rasteriser of :mod:`depthgt.rasterise`, which the registration's soft
splat uses too: every point paired with the pixels whose sample positions lie within
``radius_px`` of its projection; the candidates made front first, the points sorted by
inverse depth, and sorted once by pixel, a stable int32 sort), whose output is a typed
record, :class:`RenderCandidates`; and a compositor, :func:`composite_gt`, that turns
candidates into a :class:`GTRender`: frames (or regions of them) that disagree with the
target left out, the candidates grouped into surfaces by gaps in inverse depth scaled
to the sensor's noise (:mod:`depthgt.noise_law`), the visible surface picked by its
support and its sampled footprint, and a weighted plane fitted in inverse depth per
pixel (closed-form 2x2 solves), with a per-pixel confidence. :func:`render_gt` is the
two in a row; the leave-target-out render is the same compositor over the same
candidates without the target's (:meth:`RenderCandidates.without_frame`). No Python loop runs over points or pixels;
``tests/render_reference.py`` holds the plain loop versions (test oracles).

Measured (bench/bench_gt_protocol.py, evaluation set of 45 synthetic frame sets never
used for tuning, see bench/README.md "GT on the synthetic evaluation set"): from the clean depth of the 6 neighbours
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
from depthgt.noise_law import (
    KINECT_SIGMA_1M,
    Residuals,
    depth_sigma_m,
    estimate_noise_sigma_1m,
    noise_sigma_1m_from,
    second_difference_residuals,
)
from depthgt.rasterise import candidates, check_points, front_to_back, rank_in_pixel, resampled_positions, sort_by_pixel
from depthgt.settings import RenderSettings
from depthgt.splatting import SoftSplat, splat_soft  # re-exported: the renderer's public names

__all__ = [
    "SoftSplat",
    "splat_soft",
    "GTRender",
    "RenderCandidates",
    "render_gt",
    "rasterise_gt",
    "composite_gt",
    "TargetCloud",
    "cloud_in_target",
    "depth_sigma_m",
    "estimate_noise_sigma_1m",
    "resampled_positions",
    "KINECT_SIGMA_1M",
]


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
    left_out: the render of the other frames alone, or None: the leave-target-out
        check of real data, set by :func:`depthgt.gt.build.fuse` (the same compositor
        over the same candidates without the target's,
        :meth:`RenderCandidates.without_frame`, no agreement check; only at the pixels
        of every ``leave_target_out_stride``-th row and column). Its ``sigma`` is zero
        unless ``max_sigma_m`` needs it (the check uses the depth only).
    """

    depth: torch.Tensor
    weight_sum: torch.Tensor
    count: torch.Tensor
    sigma: torch.Tensor
    agreement: torch.Tensor
    disagreement: torch.Tensor | None = None
    left_out: GTRender | None = None


class RenderCandidates(NamedTuple):
    """The GT rasteriser's output (:func:`rasterise_gt`), the compositor's input
    (:func:`composite_gt`): every (point, pixel) pair whose projection lies strictly
    within ``radius_px`` of the pixel's sample position, sorted by pixel and, within a
    pixel, front first (decreasing inverse depth; ties in point order).

    Per candidate (C = their number):
        pixel: (C,) long index into the flattened (B*H*W) output pixels, ascending.
        point: (C,) long index into the flattened (B*N) points.
        ox, oy: (C,) the projection minus the pixel's sample position, px
            (differentiable w.r.t. the points).
        d2: (C,) ox^2 + oy^2, px^2 (differentiable).
        iz: (C,) the point's inverse depth 1/z, 1/m (differentiable).
        s: (C,) the point's expected std in inverse depth, 1/m (detached).
        frame: (C,) long frame index of the point, or None (no frame ids: each point
            counts as its own frame).
    Per point and per image:
        grad: (B*N, 2) screen-space gradient (d(1/z)/du, d(1/z)/dv) of each point's
            tangent plane (zero rows: no correction), or None (no normals).
        iz_point: (B*N,) inverse depth of every point, detached (other sigmas for the
            same candidates, :meth:`without_frame`).
        size: (B, H, W) of the output.
        n_frames: J = the largest frame id + 1 (0 without frame ids): the width of
            :attr:`GTRender.agreement`.
    """

    pixel: torch.Tensor
    point: torch.Tensor
    ox: torch.Tensor
    oy: torch.Tensor
    d2: torch.Tensor
    iz: torch.Tensor
    s: torch.Tensor
    frame: torch.Tensor | None
    grad: torch.Tensor | None
    iz_point: torch.Tensor
    size: tuple[int, int, int]
    n_frames: int

    def select(self, index: torch.Tensor) -> RenderCandidates:
        """The candidates at ``index`` (C',) long (ascending keeps the sort)."""
        names = ("pixel", "point", "ox", "oy", "d2", "iz", "s")
        picked = {k: getattr(self, k).index_select(0, index) for k in names}
        return self._replace(**picked, frame=None if self.frame is None else self.frame.index_select(0, index))

    def without_frame(self, frame: int, *, stride: int = 1, sigma_m: torch.Tensor | None = None) -> RenderCandidates:
        """The candidates of every frame but ``frame`` (the leave-target-out render's).

        Args:
            frame: the frame id to leave out (the candidates need frame ids).
            stride: keep only the pixels of every ``stride``-th row and column.
            sigma_m: (B, N) the points' depth sigmas in metres for these candidates
                (e.g. the noise law estimated without the left-out frame), or None
                (keep their sigmas).
        """
        if self.frame is None:
            raise ValueError("without_frame needs candidates with frame ids (render with frame=...)")
        b, h, w = self.size
        if sigma_m is not None and sigma_m.numel() != self.iz_point.numel():
            raise ValueError(
                f"sigma_m must hold one sigma per point ({self.iz_point.numel()}), got {tuple(sigma_m.shape)}"
            )
        with torch.no_grad():
            keep = self.frame != frame
            if stride > 1:
                on_grid = torch.zeros(b, h, w, dtype=torch.bool, device=self.pixel.device)
                on_grid[:, ::stride, ::stride] = True
                keep &= on_grid.reshape(-1).index_select(0, self.pixel)
            out = self.select(keep.nonzero().squeeze(1))
            if sigma_m is not None:
                s_point = _inverse_depth_std(sigma_m.detach().reshape(-1).to(self.iz_point.dtype), self.iz_point)
                out = out._replace(s=s_point.index_select(0, out.point))
        return out


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


def _inverse_depth_std(sigma_m: torch.Tensor, iz: torch.Tensor) -> torch.Tensor:
    """(N,) std in inverse depth s = sigma_z / z^2 = sigma_z iz^2 (floored at 1e-12) of
    depth stds ``sigma_m`` (N,) metres at inverse depths ``iz`` (N,) 1/m."""
    return (sigma_m * iz**2).clamp_min(1e-12)


def rasterise_gt(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    settings: RenderSettings = RenderSettings(),
    *,
    valid: torch.Tensor | None = None,
    normals_cam: torch.Tensor | None = None,
    sigma_m: torch.Tensor | None = None,
    frame: torch.Tensor | None = None,
    src_hw: tuple[int, int] | None = None,
) -> RenderCandidates:
    """Step 1 of :func:`render_gt`: the candidates of every pixel, with their inverse
    depths, sigmas and frames, sorted by pixel and front first (the points sorted by
    inverse depth once, :func:`depthgt.rasterise.front_to_back`, and the candidates made
    in that order, then one stable sort by pixel).

    Args: as :func:`render_gt`. Returns: :class:`RenderCandidates`.
    """
    valid = check_points(points_cam, K, valid, size_hw)
    b, n = points_cam.shape[:2]
    for name, t, shape in (
        ("normals_cam", normals_cam, (b, n, 3)),
        ("sigma_m", sigma_m, (b, n)),
        ("frame", frame, (b, n)),
    ):
        if t is not None and tuple(t.shape) != shape:
            raise ValueError(
                f"{name} must be {shape} to match points_cam {tuple(points_cam.shape)}, got {tuple(t.shape)}"
            )
    st = settings
    h, w = int(size_hw[0]), int(size_hw[1])
    dev, dt = points_cam.device, points_cam.dtype
    grid = None
    if src_hw is not None:
        grid = (resampled_positions(int(src_hw[1]), w, dev, dt), resampled_positions(int(src_hw[0]), h, dev, dt))
    z_all = points_cam[..., 2].reshape(-1)
    iz_all = 1.0 / z_all.clamp_min(st.min_depth_m)
    with torch.no_grad():  # the candidates come front first: one sort of the points, not of the candidates
        by_depth = front_to_back(iz_all)
    cand, _ = candidates(
        points_cam,
        K,
        valid,
        (h, w),
        radius_px=st.radius_px,
        min_depth=st.min_depth_m,
        grid_uv=grid,
        point_order=by_depth,
    )
    n_frames = 0 if frame is None or frame.numel() == 0 else int(frame.max()) + 1
    with torch.no_grad():
        if sigma_m is None:
            sig_1m = KINECT_SIGMA_1M if st.noise_sigma_1m is None else st.noise_sigma_1m
            sz = depth_sigma_m(z_all.detach(), sig_1m, st.noise_sigma_abs_m)
        else:
            sz = sigma_m.detach().reshape(-1).to(dt)
        s_all = _inverse_depth_std(sz, iz_all.detach())
    grad = None if normals_cam is None else _inverse_depth_planes(points_cam, normals_cam, K, st)
    with torch.no_grad():
        pixel, order = sort_by_pixel(cand.pixel)  # by pixel, front first (stable: the candidates' order)
    point = cand.point.index_select(0, order)
    # projection minus sample position, px
    ox, oy = (-cand.dx).index_select(0, order), (-cand.dy).index_select(0, order)
    d2 = ox * ox + oy * oy  # as the rasteriser computes it (dx^2 + dy^2, dx = -ox): bit for bit, cheaper than a gather
    fr = None if frame is None else frame.reshape(-1).index_select(0, point)
    return RenderCandidates(
        pixel,
        point,
        ox,
        oy,
        d2,
        iz=iz_all.index_select(0, point),
        s=s_all.index_select(0, point),
        frame=fr,
        grad=grad,
        iz_point=iz_all.detach(),
        size=(b, h, w),
        n_frames=n_frames,
    )


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
    leave-target-out render of :func:`depthgt.gt.build.fuse`) calls them itself.

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


def _tile_grid(hw: tuple[int, int], tile_px: int) -> tuple[int, int]:
    """(rows, columns) of the agreement tiles; (1, 1) when ``tile_px`` is 0 (whole frames)."""
    if tile_px <= 0:
        return 1, 1
    return -(-hw[0] // tile_px), -(-hw[1] // tile_px)


def _agreement_slot(
    pixel: torch.Tensor, fr: torch.Tensor, *, size: tuple[int, int, int], n_frames: int, tile_px: int
) -> torch.Tensor:
    """Index of each sample's (image, frame, tile) in the flat decisions of
    :func:`_frame_agreement`: ((image * J + frame) * tiles + tile), from a per-pixel
    table (one gather, no integer division per sample). ``pixel``, ``fr``: (C,) long;
    ``size``: (B, H, W); ``n_frames``: J."""
    b, h, w = size
    hw, n_fr = (h, w), n_frames
    ty, tx = _tile_grid(hw, tile_px)
    n_t = ty * tx
    img = torch.arange(b, device=pixel.device)[:, None, None]
    if tile_px <= 0:
        tile = torch.zeros(1, h, w, dtype=torch.long, device=pixel.device)
    else:
        tile = (torch.arange(h, device=pixel.device)[:, None] // tile_px) * tx + torch.arange(w, device=pixel.device)[
            None
        ] // tile_px
    table = (img * (n_fr * n_t) + tile).reshape(-1)  # per pixel of the B images: image and tile part
    return table.index_select(0, pixel) + fr * n_t


def _frame_agreement(c: RenderCandidates, st: RenderSettings, target_frame: int):
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

    Long for its docstring (the rule and its thresholds); its code is 61 lines.
    """
    pixel, s, fr, iz, d2 = c.pixel, c.s, c.frame, c.iz.detach(), c.d2.detach()
    b, h, w = c.size
    hw, n_fr = (h, w), c.n_frames
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
    share = torch.where(
        n_cmp >= _MIN_COMPARED, n_ok / n_cmp.clamp_min(1), torch.full_like(n_cmp, float("nan"), dtype=torch.float32)
    )
    bad = share < st.min_frame_agreement  # (NaN: not judged)
    if st.agreement_tile_px > 0:
        ty, tx = _tile_grid(hw, st.agreement_tile_px)
        tslot = _agreement_slot(p, f, size=c.size, n_frames=n_fr, tile_px=st.agreement_tile_px)
        counts = torch.stack(
            [
                torch.bincount(tslot, minlength=b * n_fr * ty * tx),
                torch.bincount(tslot[agree], minlength=b * n_fr * ty * tx),
            ]
        ).to(torch.float32)
        # comparisons pooled over each tile's 3x3 neighbourhood (sums: average x 9)
        pooled = (
            F.avg_pool2d(counts.reshape(2 * b * n_fr, 1, ty, tx), 3, stride=1, padding=1, count_include_pad=True) * 9
        )
        n_cmp_t, n_ok_t = pooled.reshape(2, b, n_fr, ty, tx).round()
        judged = n_cmp_t >= _MIN_TILE_COMPARED
        bad_t = torch.where(judged, n_ok_t < st.min_frame_agreement * n_cmp_t, bad[..., None, None])
        bad = bad_t | (share < st.min_whole_frame_agreement)[..., None, None]
    kept = ~bad.reshape(-1)[_agreement_slot(p, f, size=c.size, n_frames=n_fr, tile_px=st.agreement_tile_px)]
    diag = torch.stack(
        [
            torch.bincount(p, minlength=n_pix),
            torch.bincount(p[~agree], minlength=n_pix),
            torch.bincount(p[kept], minlength=n_pix),
        ]
    ).to(torch.float32)
    return bad.reshape(-1), share.to(torch.float32), diag.reshape(3, b, h, w).transpose(0, 1)


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


def _backproject_resampled(depth_m: torch.Tensor, K: torch.Tensor, src_hw: tuple[int, int]) -> torch.Tensor:
    """Back-project (J, 1, H, W) depth made by nearest resizing from ``src_hw``, each pixel
    at the position of its source pixel centre: (J, H*W, 3) metres.

    Written by hand: kornia's depth_to_3d assumes the regular output pixel grid.
    """
    h, w = depth_m.shape[-2:]
    dev, dt = depth_m.device, depth_m.dtype
    v, u = torch.meshgrid(
        resampled_positions(src_hw[0], h, dev, dt), resampled_positions(src_hw[1], w, dev, dt), indexing="ij"
    )
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
    *,
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
        raise ValueError(
            f"normals must be ({j}, 3, H, W) to match depth_m {tuple(depth_m.shape)}, got {tuple(normals.shape)}"
        )
    else:
        nrm = normals
    flat = _smooth_3x3(res, normal_max_jump_rel, sigma_1m)
    nrm = torch.where(flat & torch.isfinite(nrm).all(dim=1, keepdim=True), nrm, torch.zeros_like(nrm))
    nrm = nrm.flatten(2).transpose(1, 2) @ T[:, :3, :3].transpose(1, 2)  # rotate into the target camera
    valid = (depth_m > 0).reshape(j, -1)
    sigma = depth_sigma_m(depth_m.reshape(j, -1), sigma_1m, noise_sigma_abs_m)  # each point's own sensor depth
    frame = torch.arange(j, device=depth_m.device)[:, None].expand(j, depth_m.shape[-2] * depth_m.shape[-1])
    return TargetCloud(
        pts.reshape(1, -1, 3), nrm.reshape(1, -1, 3), valid.reshape(1, -1), frame.reshape(1, -1), sigma.reshape(1, -1)
    )
