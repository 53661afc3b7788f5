"""Overfit-trained unsupervised registration of one local frame set (paper Sec. 3.2).

``register_frameset`` is the entry point (``register_overfit``, the method of the
table ``depthgt.registration.METHODS``, calls it on a
:class:`~depthgt.registration.frameset.FrameSetData`): the R&R encoder is trained
(Adam) on the single frame set with the consistency losses of every pair (eq. 4); the poses of the
neighbours in the target camera come from the weighted Procrustes of the last (or
best-loss) iteration; then, beyond the paper, far neighbours may be initialised by
chaining through nearer ones and all poses are refined jointly over SE(3)
(:mod:`depthgt.registration.refine`). Failures are flagged per neighbour and per set,
never silently kept.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from functools import cached_property

import torch
import torch.nn.functional as F

from depthgt.framecache import FrameCache
from depthgt.geometry import backproject
from depthgt.metric_vocabulary import pose_delta
from depthgt.registration.checks import check_neighbours, set_status
from depthgt.registration.correspondences import find_correspondences, sample_candidates
from depthgt.registration.encoder import build_encoder, candidate_points
from depthgt.registration.frameset import FrameSetData
from depthgt.registration.losses import correspondence_loss, default_render_fn, render_losses
from depthgt.registration.procrustes import procrustes_random_subsets
from depthgt.registration.refine import Level, LevelSettings, RefineResult, pair_mean_cost, refine_poses
from depthgt.registration.result import RegistrationResult
from depthgt.registration.settings import RegistrationSettings
from depthgt.shapes import check_shape

__all__ = ["register_overfit", "register_frameset", "pretrain_encoder", "frameset_loss"]

log = logging.getLogger(__name__)


# --------------------------------------------------------------------------- inputs


@dataclass
class _Frameset:
    rgb: torch.Tensor  # (F, 3, H, W)
    depth: torch.Tensor  # (F, 1, H, W)
    K: torch.Tensor  # (3, 3) the frame set's one camera
    cand_idx: torch.Tensor  # (F, n)
    cand_mask: torch.Tensor  # (F, n)
    pairs: torch.Tensor  # (P, 2) unordered (a, b), a < b
    render_stride: int  # the render losses' points: every render_stride-th pixel and row

    @cached_property
    def _render_samples(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(rpts (F, M, 3) render points, rrgb (F, M, 3), rmask (F, M)): made when the
        render losses first need them (never with ``iterations: 0``, as preset fast)."""
        Fn, _, H, W = self.depth.shape
        ys = torch.arange(0, H, self.render_stride, device=self.depth.device)
        xs = torch.arange(0, W, self.render_stride, device=self.depth.device)
        ridx = (ys[:, None] * W + xs[None, :]).reshape(-1)
        pts = backproject(self.depth, self.K.expand(Fn, 3, 3).to(self.depth.dtype))
        return (
            pts.index_select(1, ridx),
            self.rgb.flatten(2).index_select(2, ridx).transpose(1, 2),
            (self.depth > 0).flatten(1).index_select(1, ridx),
        )

    @property
    def rpts(self) -> torch.Tensor:
        return self._render_samples[0]

    @property
    def rrgb(self) -> torch.Tensor:
        return self._render_samples[1]

    @property
    def rmask(self) -> torch.Tensor:
        return self._render_samples[2]


def _check_inputs(rgb, depth_m, K, offsets):
    check_shape(depth_m, "F 1 H W", "depth_m", check_shape(rgb, "F 3 H W", "rgb"))
    check_shape(K, "3 3", "K (the frame set's one camera)")
    if len(offsets) != rgb.shape[0] or offsets[0] != 0:
        raise ValueError(f"offsets must have one entry per frame ({rgb.shape[0]}) with offsets[0] == 0, got {offsets}")
    if rgb.shape[0] < 2:
        raise ValueError("a frame set needs a target and at least one neighbour")
    if not torch.isfinite(depth_m).all():
        raise ValueError("depth_m holds non-finite values")


def _prepare(rgb, depth_m, K, s: RegistrationSettings, gen: torch.Generator) -> _Frameset:
    Fn = depth_m.shape[0]
    cand_idx, cand_mask = sample_candidates(depth_m > 0, s.matching.n_candidates, gen)
    if s.training.pairs == "all":
        a, b = torch.triu_indices(Fn, Fn, offset=1)
    else:
        b = torch.arange(1, Fn)
        a = torch.zeros_like(b)
    pairs = torch.stack([a, b], 1).to(depth_m.device)
    return _Frameset(rgb, depth_m, K, cand_idx, cand_mask, pairs, s.training.render_stride)


# --------------------------------------------------------------------------- loss


def _cpu_has_native_bf16() -> bool:
    """True when the CPU has bf16 dot-product instructions (AVX512-BF16 or AMX-BF16),
    where oneDNN's bf16 convolutions are ~2x faster than fp32; elsewhere bf16 is
    emulated and slower. Linux only (/proc/cpuinfo); False when unknown."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return bool(flags & {"avx512_bf16", "amx_bf16"})
    except OSError:
        pass
    return False


def autocast_dtype(device: torch.device | str, precision: str) -> torch.dtype | None:
    """The autocast dtype of the encoder for ``precision`` on ``device`` (None = fp32)."""
    dev = torch.device(device)
    if precision == "fp32":
        return None
    if precision == "bf16":
        return torch.bfloat16
    if dev.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else None
    if dev.type == "cpu" and torch.backends.mkldnn.is_available() and _cpu_has_native_bf16():
        return torch.bfloat16
    return None


def encode_at(
    encoder: torch.nn.Module, rgb: torch.Tensor, index: torch.Tensor, precision: str = "fp32", stride: int = 1
) -> torch.Tensor:
    """Unit-length float32 features (B, N, C) of the pixels ``index`` (B, N) (flat,
    row-major) of ``rgb`` (B, 3, H, W), with the encoder's convolutions in the dtype
    :func:`autocast_dtype` picks (channels-last memory on CPU, the fast layout of
    oneDNN's convolutions). With ``stride`` > 1 the encoder sees ``rgb`` averaged over
    cells of ``stride`` x ``stride`` pixels (the last row and column of cells partial
    where H or W is not a multiple) and a pixel takes its cell's feature. Only the
    chosen pixels are gathered (in the map's own layout, without a copy of the whole
    map) and normalised."""
    dt = autocast_dtype(rgb.device, precision)
    W = rgb.shape[-1]
    if stride > 1:
        rgb = F.avg_pool2d(rgb, stride, ceil_mode=True, count_include_pad=False)
        w_cells = rgb.shape[-1]
        index = (index // W // stride) * w_cells + (index % W) // stride
    if rgb.device.type == "cpu":
        rgb = rgb.contiguous(memory_format=torch.channels_last)
    with torch.autocast(rgb.device.type, dtype=dt or torch.float32, enabled=dt is not None):
        feats = encoder(rgb)
    C = feats.shape[1]
    f = torch.gather(feats.flatten(2), 2, index[:, None].expand(-1, C, -1)).float()  # (B, C, N)
    return F.normalize(f, dim=1).transpose(1, 2)


def frameset_loss(
    encoder: torch.nn.Module,
    fs: _Frameset,
    s: RegistrationSettings,
    gen: torch.Generator,
    render_fn: Callable | None,
    with_render: bool = True,
):
    """Set-wide loss (eq. 4) and the pairwise Procrustes estimates.

    Returns:
        loss (scalar), T_b_to_a (P, 4, 4) for ``fs.pairs``, confident match counts (P,)
        and a dict of the mean loss terms.
    """
    Fn = fs.rgb.shape[0]
    f = encode_at(encoder, fs.rgb, fs.cand_idx, s.encoder.precision, s.encoder.encoder_stride)  # (F, n, C)
    Kb = fs.K.expand(Fn, 3, 3).to(fs.depth.dtype)
    pts = candidate_points(fs.depth, Kb, fs.cand_idx)
    a, b = fs.pairs[:, 0], fs.pairs[:, 1]
    # x.index_select(0, i) in place of x[i] (faster on CPU); the features keep their
    # (C, N)-planar layout, as x[i] keeps it, so that their normalisation in
    # find_correspondences reduces in the same order (bit-identical)
    sel = lambda x, i: x.index_select(0, i)  # noqa: E731
    fsel = lambda i: f.transpose(1, 2).index_select(0, i).transpose(1, 2)  # noqa: E731
    corr = find_correspondences(
        sel(pts, a),
        fsel(a),
        sel(fs.cand_mask, a),
        sel(pts, b),
        fsel(b),
        sel(fs.cand_mask, b),
        s.matching.top_k,
        s.matching.knn_block,
    )
    T_ba, _ = procrustes_random_subsets(
        corr.points_src, corr.points_dst, corr.weights, s.matching.n_subsets, s.matching.subset_fraction, gen
    )
    l_corr = correspondence_loss(T_ba, corr.points_src, corr.points_dst, corr.weights)
    n_conf = (corr.weights.detach() >= s.checks.confident_weight).sum(1)
    loss = s.training.w_corr * l_corr.sum()
    terms = {"corr": float(l_corr.detach().mean())}
    if with_render and (s.training.w_depth > 0 or s.training.w_photo > 0):
        T_ab = torch.linalg.inv(T_ba)
        # both directions: b rendered into a with T_ba, a rendered into b with T_ab
        src = torch.cat([b, a])
        dst = torch.cat([a, b])
        T = torch.cat([T_ba, T_ab])
        l_d, l_p = render_losses(
            fs.rpts[src],
            fs.rrgb[src],
            fs.rmask[src],
            T,
            fs.depth[dst],
            fs.rgb[dst],
            Kb[dst],
            render_fn,
            s.training.render_radius_px,
            s.training.render_max_points,
        )
        loss = loss + s.training.w_depth * l_d.sum() + s.training.w_photo * l_p.sum()
        terms["depth"] = float(l_d.detach().mean())
        terms["photo"] = float(l_p.detach().mean())
    return loss, T_ba, n_conf, terms


def _finite_grads(module: torch.nn.Module) -> bool:
    return all(bool(torch.isfinite(p.grad).all()) for p in module.parameters() if p.grad is not None)


def _target_poses(T_ba: torch.Tensor, pairs: torch.Tensor, Fn: int) -> torch.Tensor:
    """(F, 4, 4) T_f_to_t from the pairs (0, j) (target = a)."""
    T = torch.eye(4, dtype=torch.float64, device=T_ba.device).repeat(Fn, 1, 1)
    sel = pairs[:, 0] == 0
    T[pairs[sel, 1]] = T_ba[sel].detach().to(torch.float64)
    return T


def _pair_table(T_ba: torch.Tensor, pairs: torch.Tensor, Fn: int) -> dict[tuple[int, int], torch.Tensor]:
    """T_b_to_a for every available ordered pair (inverse added)."""
    out = {}
    for i, (a, b) in enumerate(pairs.tolist()):
        T = T_ba[i].detach().to(torch.float64)
        out[(a, b)] = T
        out[(b, a)] = torch.linalg.inv(T)
    return out


# --------------------------------------------------------------------------- chaining


def _chain(
    fs: _Frameset,
    T_init: torch.Tensor,
    table,
    offsets,
    s: RegistrationSettings,
    extra=None,
    maps_of=None,
    frames: tuple[FrameCache | None, tuple[int, ...] | None] = (None, None),
):
    """Choose per neighbour between the direct estimate and compositions through nearer
    neighbours (and an external initial guess) by their alignment cost into the target
    (robust point-to-plane + photometric cost at half resolution). ``frames``: the batch
    job's frame cache and the members' positions (each frame's maps once per batch)."""
    Fn = len(offsets)
    rs = s.refine_settings
    level = Level(fs.rgb, fs.depth, fs.K, 2, 1, maps_of, *frames)
    cands, owners, labels = [], [], []
    for j in range(1, Fn):
        options = [("direct", T_init[j]), ("identity", torch.eye(4, dtype=T_init.dtype, device=T_init.device))]
        for k in range(1, Fn):
            if k != j and abs(offsets[k]) < abs(offsets[j]) and offsets[k] * offsets[j] > 0 and (k, j) in table:
                options.append((f"via{offsets[k]:+d}", T_init[k] @ table[(k, j)]))
        if extra is not None:
            options.append(("init", extra[j]))
        for lab, T in options:
            cands.append(T)
            owners.append(j)
            labels.append(lab)
    T_c = torch.stack(cands)  # candidate T_j_to_t
    pairs = torch.stack([torch.zeros(len(owners), dtype=torch.long), torch.tensor(owners)], 1).to(fs.depth.device)
    # normal_system works on absolute poses T (F', 4, 4); build a virtual frame list:
    # reuse the real frames by pairing (0, j) with the candidate pose in place of T_j.
    Tv = torch.eye(4, dtype=torch.float64, device=fs.depth.device).repeat(len(owners) + 1, 1, 1)
    Tv[1:] = T_c
    vpairs = torch.stack([torch.zeros(len(owners), dtype=torch.long), torch.arange(1, len(owners) + 1)], 1)
    level.points = torch.cat([level.points[:1], level.points[pairs[:, 1]]])
    level.gray = torch.cat([level.gray[:1], level.gray[pairs[:, 1]]])
    level.valid = torch.cat([level.valid[:1], level.valid[pairs[:, 1]]])
    level.geo = torch.cat([level.geo[:1], level.geo[pairs[:, 1]]])
    level.photo = torch.cat([level.photo[:1], level.photo[pairs[:, 1]]])
    ls = LevelSettings(rs.geo_scale_m[-1], rs.photo_scale, rs.photo_weight, rs.robust, rs.geo_ref_depth_m)
    # Mean cost per point that lands on a surface of the target, not the sum: a sum
    # charges points that leave the view and so favours the candidate of the largest
    # overlap (the identity) over the right one. A candidate that sees less than a
    # quarter of the overlap of the best-overlapping one of its neighbour is not chosen
    # (not a half: next to the holes of real depth, a pose on the pixel grid such as the
    # identity sees up to twice the points of a sub-pixel one).
    cost, n_vis = pair_mean_cost(level, Tv, vpairs.to(fs.depth.device), ls, rs.max_dist_m[-1])
    T_out = T_init.clone()
    choice = {}
    owners_t = torch.tensor(owners)
    for j in range(1, Fn):
        idx = torch.nonzero(owners_t == j)[:, 0]
        c = torch.where(n_vis[idx] >= 0.25 * n_vis[idx].max(), cost[idx], torch.full_like(cost[idx], math.inf))
        best = idx[c.argmin()]
        T_out[j] = T_c[best]
        choice[int(offsets[j])] = labels[int(best)]
    return T_out, choice


# --------------------------------------------------------------------------- entry point


@dataclass
class _Overfit:
    """What the overfit training leaves: the loss per iteration, the per-iteration
    pose changes, the last iteration's target poses and the best-loss estimate."""

    loss_curve: list[float] = field(default_factory=list)
    pose_history: list[list[dict]] = field(default_factory=list)
    prev: torch.Tensor | None = None  # (F, 4, 4) T_f_to_t of the last iteration
    best: tuple = (math.inf, None, None)  # (loss, T_ba, n_conf)


def _pose_changes(T_before: torch.Tensor, T_after: torch.Tensor) -> list[dict]:
    """Per neighbour ``{"dt_m", "dr_deg"}``: the change of T_j_to_t between two estimates."""
    dt, dr = pose_delta(torch.linalg.inv(T_before[1:]) @ T_after[1:])
    return [{"dt_m": float(a), "dr_deg": float(b)} for a, b in zip(dt, dr)]


def _setup(rgb, depth_m, K, s: RegistrationSettings, encoder_state: dict | None, seed: int, render_fn: Callable | None):
    """Inputs on their dtypes, the frame set's fixed samples, the encoder (pretrained
    weights or a seeded initialisation) and the random generator."""
    if s.num_threads:
        torch.set_num_threads(s.num_threads)
    dev = rgb.device
    rgb, depth_m, K = rgb.float(), depth_m.float(), K.to(dev, torch.float32)
    if render_fn is None and (s.training.w_depth > 0 or s.training.w_photo > 0) and s.training.iterations > 0:
        render_fn = default_render_fn()
    gen = torch.Generator().manual_seed(seed)
    fs = _prepare(rgb, depth_m, K, s, gen)
    encoder = build_encoder(s.encoder.n_blocks, s.encoder.channels, s.encoder.feat_dim, seed=seed).to(dev)
    if encoder_state is not None:
        encoder.load_state_dict(encoder_state)
    if dev.type == "cpu":
        encoder = encoder.to(memory_format=torch.channels_last)
    encoder.train()
    return fs, encoder, gen, render_fn


def _overfit(
    encoder: torch.nn.Module, fs: _Frameset, s: RegistrationSettings, gen: torch.Generator, render_fn: Callable | None
) -> _Overfit:
    """The paper's overfit training of the encoder on the single frame set (Adam,
    ``s.training.iterations`` steps of the set-wide loss, eq. 4)."""
    Fn = fs.rgb.shape[0]
    opt = torch.optim.Adam(encoder.parameters(), lr=s.training.lr, weight_decay=s.training.weight_decay)
    trace = _Overfit()
    for _ in range(s.training.iterations):
        opt.zero_grad(set_to_none=True)
        loss, T_ba, n_conf, _terms = frameset_loss(encoder, fs, s, gen, render_fn)
        if not torch.isfinite(loss):
            log.warning("non-finite training loss; stopping the overfit training early")
            break
        loss.backward()
        if _finite_grads(encoder):
            opt.step()
        else:
            # e.g. an SVD with repeated singular values (no texture: all weights ~0)
            log.warning("non-finite gradient in the overfit training; step skipped")
        trace.loss_curve.append(float(loss.detach()))
        T_now = _target_poses(T_ba, fs.pairs, Fn)
        if trace.loss_curve[-1] < trace.best[0]:
            trace.best = (trace.loss_curve[-1], T_ba.detach(), n_conf)
        if trace.prev is not None:
            trace.pose_history.append(_pose_changes(trace.prev, T_now))
        trace.prev = T_now
    return trace


def _final_estimate(
    encoder: torch.nn.Module,
    fs: _Frameset,
    s: RegistrationSettings,
    gen: torch.Generator,
    render_fn: Callable | None,
    trace: _Overfit,
):
    """The paper's output poses from the trained encoder (or the best-loss iteration).

    Returns:
        (T_ba (P, 4, 4) of the pairs, T_paper (F, 4, 4) T_f_to_t, confident target-pair
        matches per frame (F,) long).
    """
    Fn = fs.rgb.shape[0]
    with torch.no_grad():
        _, T_ba, n_conf, _ = frameset_loss(encoder, fs, s, gen, render_fn, with_render=False)
    if s.training.pose_from == "best" and trace.best[1] is not None:
        T_ba, n_conf = trace.best[1], trace.best[2]
    T_paper = _target_poses(T_ba, fs.pairs, Fn)
    if trace.prev is not None:
        trace.pose_history.append(_pose_changes(trace.prev, T_paper))
    tsel = fs.pairs[:, 0] == 0
    n_corr = torch.zeros(Fn, dtype=torch.long)
    n_corr[fs.pairs[tsel, 1].cpu()] = n_conf[tsel].cpu()
    return T_ba, T_paper, n_corr


def _beyond_the_paper(
    fs: _Frameset,
    T_paper: torch.Tensor,
    T_ba: torch.Tensor,
    offsets: list[int],
    s: RegistrationSettings,
    extra: torch.Tensor | None,
    frames: tuple[FrameCache | None, tuple[int, ...] | None] = (None, None),
) -> tuple[torch.Tensor, RefineResult | None, dict, dict[str, float]]:
    """The steps beyond the paper on its poses ``T_paper`` (F, 4, 4): the chaining of far
    neighbours through nearer ones (``s.chaining``, or an initial guess ``extra``) and the
    joint SE(3) refinement (``s.refine``). ``frames``: the batch job's
    :class:`~depthgt.framecache.FrameCache` and the members' positions, or Nones: what
    depends on a frame alone (its pyramid, its noise residuals) is computed once per batch.

    Returns:
        T (F, 4, 4) the final poses, the refinement's
        :class:`~depthgt.registration.refine.RefineResult` (or None), the diagnostics of
        the two steps and their seconds.
    """
    diagnostics: dict = {}
    timings: dict[str, float] = {}
    T = T_paper
    maps_of: dict = {}  # the refinement pyramid's maps by scale, shared by the chaining and the refinement
    if s.chaining or extra is not None:
        t0 = time.perf_counter()
        with torch.no_grad():
            table = _pair_table(T_ba, fs.pairs, len(offsets)) if s.chaining else {}
            T, choice = _chain(fs, T, table, offsets, s, extra, maps_of, frames)
        diagnostics["chaining"] = choice
        timings["chaining"] = time.perf_counter() - t0
    refined = None
    if s.refine:
        t0 = time.perf_counter()
        with torch.no_grad():
            refined = refine_poses(fs.rgb, fs.depth, fs.K, T, s.refine_settings, offsets, maps_of, *frames)
        T = refined.T_f_to_t
        diagnostics.update(refined.diagnostics())
        timings["refine"] = time.perf_counter() - t0
    return T, refined, diagnostics, timings


def register_frameset(
    rgb: torch.Tensor,
    depth_m: torch.Tensor,
    K: torch.Tensor,
    offsets: list[int],
    settings: RegistrationSettings = RegistrationSettings(),
    encoder_state: dict | None = None,
    init_T_j_to_t: torch.Tensor | None = None,
    seed: int = 0,
    render_fn: Callable | None = None,
    cache: FrameCache | None = None,
    positions: tuple[int, ...] | None = None,
) -> RegistrationResult:
    """Register the neighbours of a local frame set to its target (frame 0).

    Steps: prepare the inputs and the encoder, overfit it on the set (paper), estimate
    the poses from it, chain far neighbours through nearer ones, refine jointly over
    SE(3) (beyond the paper), check every neighbour.

    Args:
        rgb: (F, 3, H, W) float colour in [0, 1] at the working resolution (256x256).
        depth_m: (F, 1, H, W) depth in metres, 0 = invalid.
        K: (3, 3) the frame set's one camera (every frame's intrinsics) at (H, W).
        offsets: frame offsets, ``offsets[0] == 0`` (the target), e.g. [0, -6, -4, -2, 2, 4, 6].
        settings: :class:`~depthgt.settings.RegistrationSettings` (presets:
            :func:`depthgt.settings.registration_settings`).
        encoder_state: pretrained encoder weights (:func:`pretrain_encoder`), else a
            random initialisation from ``seed``.
        init_T_j_to_t: (F-1, 4, 4) optional initial guess, used as one more candidate
            of the chaining step.
        seed: seed of the initialisation, candidate draw and random subsets.
        render_fn: differentiable splatting (default :func:`depthgt.splatting.splat_soft`).
        cache, positions: the batch job's :class:`~depthgt.framecache.FrameCache` and the
            frames' positions: per-frame maps and noise residuals once per batch.

    Returns:
        :class:`RegistrationResult`; the device of the computation is that of ``rgb``.
    """
    t_start = time.perf_counter()
    _check_inputs(rgb, depth_m, K, offsets)
    s = settings
    Fn = rgb.shape[0]
    if init_T_j_to_t is not None:
        check_shape(init_T_j_to_t, "J 4 4", "init_T_j_to_t", {"J": Fn - 1})
    dev = rgb.device
    fs, encoder, gen, render_fn = _setup(rgb, depth_m, K, s, encoder_state, seed, render_fn)
    timings: dict[str, float] = {}

    t0 = time.perf_counter()
    trace = _overfit(encoder, fs, s, gen, render_fn)
    timings["overfit"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    T_ba, T_paper, n_corr = _final_estimate(encoder, fs, s, gen, render_fn, trace)
    timings["estimate"] = time.perf_counter() - t0

    diagnostics: dict = {"poses_paper": T_paper[1:].cpu().numpy().tolist()}
    extra = None
    if init_T_j_to_t is not None:
        extra = torch.cat([torch.eye(4, dtype=torch.float64)[None], init_T_j_to_t.to(torch.float64).cpu()]).to(dev)
    T, refined, notes, seconds = _beyond_the_paper(fs, T_paper, T_ba, offsets, s, extra, (cache, positions))
    diagnostics.update(notes)
    timings.update(seconds)
    statuses, reasons = check_neighbours(T, n_corr, refined, s.checks)
    status, reason = set_status(statuses, [] if s.refine else trace.loss_curve, s.checks)
    timings["total"] = time.perf_counter() - t_start
    return RegistrationResult(
        T_j_to_t=T[1:].detach().cpu().to(torch.float64),
        offsets=list(offsets),
        neighbour_status=statuses,
        neighbour_reasons=reasons,
        status=status,
        reason=reason,
        loss_curve=trace.loss_curve,
        pose_history=trace.pose_history,
        n_correspondences=[int(x) for x in n_corr[1:]],
        timings=timings,
        diagnostics=diagnostics,
        normals=None if refined is None else refined.normals,
    )


def register_overfit(
    data: FrameSetData,
    offsets: list[int],
    settings: RegistrationSettings,
    *,
    seed: int = 0,
    encoder_state: dict | None = None,
) -> RegistrationResult:
    """:func:`register_frameset` of the members of one frame set (the source's poses,
    if any, are not used; :class:`~depthgt.registration.frameset.Registration`)."""
    return register_frameset(
        data.rgb,
        data.depth_m,
        data.K,
        offsets,
        settings,
        encoder_state=encoder_state,
        seed=seed,
        cache=data.cache,
        positions=data.positions,
    )


def pretrain_encoder(
    framesets: Iterable[tuple[torch.Tensor, torch.Tensor, torch.Tensor, list[int]]],
    settings: RegistrationSettings = RegistrationSettings(),
    epochs: int = 1,
    seed: int = 0,
    render_fn: Callable | None = None,
) -> dict:
    """Stream-only unsupervised pretraining of the encoder (no poses used).

    Args:
        framesets: (rgb (F, 3, H, W), depth_m (F, 1, H, W), K (3, 3) the set's one camera, offsets) tuples
            from the training scenes; re-iterated once per epoch (pass a list when
            ``epochs > 1``).
        settings: the registration settings (same encoder size and losses).
        epochs: passes over ``framesets``; one Adam step per frame set.

    Returns:
        The encoder's ``state_dict`` (CPU tensors).
    """
    s = settings
    gen = torch.Generator().manual_seed(seed)
    encoder = None
    opt = None
    steps = 0
    for _ in range(epochs):
        for rgb, depth_m, K, offsets in framesets:
            _check_inputs(rgb, depth_m, K, offsets)
            if encoder is None:
                encoder = build_encoder(s.encoder.n_blocks, s.encoder.channels, s.encoder.feat_dim, seed=seed).to(
                    rgb.device
                )
                if rgb.device.type == "cpu":
                    encoder = encoder.to(memory_format=torch.channels_last)
                encoder.train()
                opt = torch.optim.Adam(encoder.parameters(), lr=s.training.lr, weight_decay=s.training.weight_decay)
                if render_fn is None and (s.training.w_depth > 0 or s.training.w_photo > 0):
                    render_fn = default_render_fn()
            fs = _prepare(rgb.float(), depth_m.float(), K.to(rgb.device, torch.float32), s, gen)
            opt.zero_grad(set_to_none=True)
            loss, _, _, _ = frameset_loss(encoder, fs, s, gen, render_fn)
            if torch.isfinite(loss):
                loss.backward()
                if _finite_grads(encoder):
                    opt.step()
            steps += 1
    if encoder is None:
        raise ValueError("pretrain_encoder: no frame set given")
    log.info("pretrained the encoder for %d steps", steps)
    return {k: v.detach().cpu().contiguous() for k, v in encoder.state_dict().items()}
