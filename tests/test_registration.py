"""Tests of the overfit registration (issue 3): small sizes, CPU, a few seconds each."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from depthgt.errors import ConfigError
from depthgt.eval.metrics import pose_errors
from depthgt.registration.correspondences import find_correspondences, knn2_both, sample_candidates
from depthgt.registration.encoder import build_encoder, candidate_points
from depthgt.registration.overfit import encode_at, register_frameset
from depthgt.registration.procrustes import procrustes_random_subsets, weighted_procrustes
from depthgt.registration.refine import adjoint, refine_poses
from depthgt.settings import REGISTRATION_PRESETS, RefineSettings, RegistrationSettings, registration_settings

SEVEN = Path(__file__).resolve().parents[2] / "shared/data/7scenes-kitchen"


# ----------------------------------------------------------------------------- helpers


def _raycast_room(T_world_cam: np.ndarray, K: np.ndarray, hw, textured=True, flat=False):
    """Depth (H, W) and colour (H, W, 3) of a textured box room with a cube inside
    (or, with ``flat``, a single uniform wall at z = 2 m) seen from ``T_world_cam``."""
    H, W = hw
    v, u = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u, float)], -1)
    d = rays @ T_world_cam[:3, :3].T
    o = T_world_cam[:3, 3]
    if flat:
        t = (2.0 - o[2]) / d[..., 2]
    else:
        lo, hi = np.array([-2.0, -1.5, -1.0]), np.array([2.0, 1.5, 4.0])
        with np.errstate(divide="ignore", invalid="ignore"):
            t_room = np.where(d > 0, (hi - o) / d, (lo - o) / d).min(-1)
            clo, chi = np.array([-0.6, 0.2, 1.8]), np.array([0.3, 1.5, 2.6])
            t1, t2 = (clo - o) / d, (chi - o) / d
            tmin = np.minimum(t1, t2).max(-1)
            tmax = np.maximum(t1, t2).min(-1)
        hit = (tmax >= tmin) & (tmin > 0)
        t = np.where(hit & (tmin < t_room), tmin, t_room)
    X = o + t[..., None] * d
    depth = (t * (d @ T_world_cam[:3, 2])).astype(np.float32)  # z in the camera
    if textured:
        rgb = np.stack(
            [
                0.5 + 0.2 * np.sin(5 * X[..., 0] + 3 * X[..., 2]) + 0.15 * np.sin(11 * X[..., 1] + 7 * X[..., 2]),
                0.5 + 0.2 * np.sin(7 * X[..., 1] - 4 * X[..., 0]) + 0.15 * np.cos(13 * X[..., 2] + 5 * X[..., 0]),
                0.5 + 0.25 * np.cos(6 * X[..., 2] + 9 * X[..., 1] - 2 * X[..., 0]),
            ],
            -1,
        )
    else:
        rgb = np.full(depth.shape + (3,), 0.6)
    return depth, np.clip(rgb, 0, 1).astype(np.float32)


def _rot(axis_angle):
    a = np.asarray(axis_angle, float)
    th = np.linalg.norm(a)
    if th == 0:
        return np.eye(3)
    k = a / th
    Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * Kx + (1 - math.cos(th)) * Kx @ Kx


def _frameset(
    offsets, hw=(64, 64), flat=False, textured=True, step_t=0.02, step_deg=1.0, noise_m=0.0, seed=0, holes=0.0
):
    """Synthetic frame set on a smooth trajectory (``holes``: share of depth pixels
    dropped at random, like a sensor's); returns rgb, depth, K, true T_j_to_t."""
    K = np.array([[0.9 * hw[1], 0, hw[1] / 2 - 0.5], [0, 0.9 * hw[1], hw[0] / 2 - 0.5], [0, 0, 1.0]])
    rng = np.random.default_rng(seed)
    poses = {}
    for o in offsets:
        T = np.eye(4)
        T[:3, :3] = _rot(np.radians(step_deg) * o * np.array([0.3, 1.0, 0.2]) / 1.06)
        T[:3, 3] = step_t * o * np.array([1.0, 0.3, 0.4])
        poses[o] = T
    rgbs, depths = [], []
    for o in offsets:
        dep, col = _raycast_room(poses[o], K, hw, textured=textured, flat=flat)
        if noise_m:
            dep = dep + rng.normal(0, noise_m, dep.shape).astype(np.float32) * dep**2
        if holes:
            dep[rng.random(dep.shape) < holes] = 0
        rgbs.append(col)
        depths.append(dep)
    rgb = torch.from_numpy(np.stack(rgbs)).permute(0, 3, 1, 2).contiguous()
    depth = torch.from_numpy(np.stack(depths))[:, None]
    T_true = np.stack([np.linalg.inv(poses[0]) @ poses[o] for o in offsets[1:]])
    return rgb, depth, torch.from_numpy(K).float(), T_true


def _random_T(gen, angle_deg=10.0, trans=0.2):
    axis = torch.randn(3, generator=gen, dtype=torch.float64)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.from_numpy(_rot((axis / axis.norm() * math.radians(angle_deg)).numpy()))
    T[:3, 3] = torch.randn(3, generator=gen, dtype=torch.float64) * trans
    return T


# ----------------------------------------------------------------------------- procrustes


def test_procrustes_recovers_known_transform_exactly():
    gen = torch.Generator().manual_seed(1)
    T = torch.stack([_random_T(gen), _random_T(gen, 40.0, 1.0)])
    p = torch.randn(2, 50, 3, generator=gen, dtype=torch.float64)
    q = p @ T[:, :3, :3].transpose(1, 2) + T[:, None, :3, 3]
    w = torch.rand(2, 50, generator=gen, dtype=torch.float64) + 0.1
    T_est = weighted_procrustes(p, q, w)
    assert torch.allclose(T_est, T, atol=1e-10)
    # zero weights on outliers: still exact
    q_bad = q.clone()
    q_bad[:, :10] += 5.0
    w2 = w.clone()
    w2[:, :10] = 0
    assert torch.allclose(weighted_procrustes(p, q_bad, w2), T, atol=1e-10)


def test_procrustes_fixes_reflections_and_random_subsets_pick_inliers():
    gen = torch.Generator().manual_seed(2)
    p = torch.randn(1, 60, 3, generator=gen, dtype=torch.float64)
    q = p.clone()
    q[..., 2] *= -1  # a mirror: the best rotation must still have det +1
    T = weighted_procrustes(p, q, torch.ones(1, 60, dtype=torch.float64))
    assert torch.linalg.det(T[0, :3, :3]).item() == pytest.approx(1.0, abs=1e-9)
    T_true = _random_T(gen)
    q = p @ T_true[:3, :3].T + T_true[:3, 3]
    T_r, res = procrustes_random_subsets(p, q, torch.ones(1, 60, dtype=torch.float64), 10, 0.2, gen)
    assert torch.allclose(T_r[0], T_true, atol=1e-9) and res.item() < 1e-18


def test_gradients_reach_the_encoder_through_the_weights():
    torch.manual_seed(0)
    rgb, depth, K, _ = _frameset([0, 2], hw=(24, 24))
    enc = build_encoder(n_blocks=1, channels=8, feat_dim=8, seed=0)
    gen = torch.Generator().manual_seed(0)
    idx, mask = sample_candidates(depth > 0, 200, gen)
    pts, f = candidate_points(depth, K.expand(2, 3, 3), idx), encode_at(enc, rgb, idx)
    corr = find_correspondences(pts[:1], f[:1], mask[:1], pts[1:], f[1:], mask[1:], top_k=30)
    assert corr.weights.shape == (1, 60) and (corr.weights >= 0).all() and (corr.weights <= 1).all()
    T, _ = procrustes_random_subsets(corr.points_src, corr.points_dst, corr.weights, 4, 0.5, gen)
    T[0, :3, 3].sum().backward()  # a scalar of the pose only: gradient must come via the weights
    grads = [p.grad for p in enc.parameters() if p.requires_grad]
    assert all(g is not None for g in grads)
    assert sum(float(g.abs().sum()) for g in grads) > 0


def test_the_compiled_two_nearest_are_topks_both_ways():
    """The CPU's one pass over each pair's similarities finds topk's two nearest along
    its rows and along its columns, for every valid candidate: with invalid candidates
    and groups of pairs cut at max_block. Where two candidates are equally near
    (candidates of one encoder cell share a feature) either is a nearest: there the
    values agree, and the indices wherever the top three values differ."""
    gen = torch.Generator().manual_seed(5)
    P, N, M, C = 5, 70, 90, 8
    f_a = torch.nn.functional.normalize(torch.randn(P, N, C, generator=gen), dim=-1)
    f_b = torch.nn.functional.normalize(torch.randn(P, M, C, generator=gen), dim=-1)
    f_b[:, 40:60] = f_b[:, 10:30]  # exact ties: each candidate 10-29 has a twin 30 later
    f_a[:, 50:65] = f_a[:, 5:20]
    mask_a = torch.rand(P, N, generator=gen) > 0.1
    mask_b = torch.rand(P, M, generator=gen) > 0.1
    mask_a[0] = True  # one pair without invalid candidates
    mask_b[0] = True
    sim = (f_a @ f_b.transpose(1, 2)).masked_fill(~(mask_a[:, :, None] & mask_b[:, None, :]), -4.0)
    for s_, valid in ((sim, mask_a), (sim.transpose(1, 2).contiguous(), mask_b)):
        top3 = s_.topk(3, dim=2).values
        distinct = (top3[..., 0] > top3[..., 1]) & (top3[..., 1] > top3[..., 2]) & valid
        assert int(distinct.sum()) > 0 and int((~distinct & valid).sum()) > 0  # both kinds present
    for block in (N * M, 2 * N * M, 1 << 25):
        ab, ba = knn2_both(f_a, f_b, mask_a, mask_b, max_block=block, compiled=True)
        assert ab.dtype == torch.int64 and ab.shape == (P, N, 2) and ba.shape == (P, M, 2)
        for s_, nn, valid in ((sim, ab, mask_a), (sim.transpose(1, 2).contiguous(), ba, mask_b)):
            ref = s_.topk(3, dim=2)
            assert torch.equal(s_.gather(2, nn)[valid], ref.values[..., :2][valid])  # the two largest
            v = ref.values
            distinct = (v[..., 0] > v[..., 1]) & (v[..., 1] > v[..., 2]) & valid
            assert torch.equal(nn[distinct], ref.indices[..., :2][distinct])
    # the tensor path (GPU): valid candidates first there too
    ab_t, ba_t = knn2_both(f_a, f_b, mask_a, mask_b, compiled=False)
    assert bool(mask_b.gather(1, ab_t[..., 0])[mask_a].all()) and bool(mask_a.gather(1, ba_t[..., 0])[mask_b].all())
    with pytest.raises(ValueError, match="float32 CPU features"):
        knn2_both(f_a.double(), f_b.double(), mask_a, mask_b, compiled=True)
    ab_64, _ = knn2_both(f_a.double(), f_b.double(), mask_a, mask_b)  # the default falls back to topk
    assert ab_64.shape == (P, N, 2)


def test_the_median_depth_is_torchs_median_of_the_valid_depths():
    """The refinement's median depth: torch.median's lower middle value of the valid
    depths (odd and even counts, float32 and float64), 1 m without any."""
    from depthgt.registration.refine import _median_depth

    gen = torch.Generator().manual_seed(2)
    counts = set()
    for n, dtype in ((4097, torch.float32), (4096, torch.float32), (1001, torch.float64)):
        d = 0.3 + 4.0 * torch.rand(1, 1, n, generator=gen, dtype=dtype)
        d[..., ::7] = 0.0  # invalid
        counts.add(int((d > 0).sum()) % 2)
        m = _median_depth(d)
        assert m.dtype == dtype and m.shape == () and torch.equal(m, d[d > 0].median())
    assert counts == {0, 1}  # odd and even counts of valid depths
    d = (0.3 + 4.0 * torch.rand(1, 1, 999, generator=gen)).to(torch.bfloat16)
    assert torch.equal(_median_depth(d), d.median())  # bfloat16: torch's own median
    assert float(_median_depth(torch.zeros(1, 1, 4, 4))) == 1.0


def test_weight_gradient_matches_finite_differences():
    gen = torch.Generator().manual_seed(3)
    p = torch.randn(1, 12, 3, generator=gen, dtype=torch.float64)
    q = p + 0.05 * torch.randn(1, 12, 3, generator=gen, dtype=torch.float64)
    w = (torch.rand(1, 12, generator=gen, dtype=torch.float64) + 0.2).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda ww: weighted_procrustes(p, q, ww)[:, :3, :], (w,))


def test_encoder_parameter_count_has_no_shared_layers():
    enc = build_encoder(n_blocks=2, channels=64, feat_dim=32)
    n = sum(p.numel() for p in enc.parameters())
    stem = 3 * 64 * 9 + 2 * 64
    block = 2 * (64 * 64 * 9 + 2 * 64)
    head = 64 * 32 + 2 * 32
    assert n == stem + 2 * block + head
    ids = [id(m) for m in enc.modules()]
    assert len(ids) == len(set(ids))


# ----------------------------------------------------------------------------- refinement


def test_adjoint_moves_a_twist_between_frames():
    from kornia.geometry.liegroup import Se3

    gen = torch.Generator().manual_seed(4)
    T = _random_T(gen)
    xi = torch.randn(1, 6, generator=gen, dtype=torch.float64) * 0.1
    lhs = T @ Se3.exp(xi).matrix()[0].double() @ torch.linalg.inv(T)
    rhs = Se3.exp((adjoint(T) @ xi[0])[None]).matrix()[0].double()
    assert torch.allclose(lhs, rhs, atol=1e-9)


def test_grouped_sampling_equals_one_map_per_pair():
    """The refinement samples each frame's map once for all pairs landing in it: the same
    values as sampling one map per pair, whether the pairs come in frame order with equal
    counts (the grid used as it is), interleaved, or unbalanced with unused frames."""
    import torch.nn.functional as F

    from depthgt.registration.refine import _sample_grouped

    g = torch.Generator().manual_seed(0)
    maps = torch.rand(7, 7, 32, 40, generator=g)
    grid = torch.rand(42, 300, 2, generator=g) * 2.4 - 1.2  # some beyond the border: zeros
    for a in (
        torch.arange(7).repeat_interleave(6),
        torch.arange(7).repeat(6),
        torch.tensor([0] * 6 + [1] * 3 + [3] * 3),
    ):
        gr = grid[: len(a)]
        one_by_one = torch.cat(
            [
                F.grid_sample(
                    maps[int(a[p])][None],
                    gr[p][None, :, None],
                    mode="bilinear",
                    padding_mode="zeros",
                    align_corners=False,
                )[..., 0]
                for p in range(len(a))
            ]
        )
        out = _sample_grouped(maps, gr, a)  # (G, C, m, N), pair p = g m + i
        assert out.shape[0] * out.shape[2] == len(a)
        assert torch.equal(out.permute(0, 2, 1, 3).reshape(len(a), 7, -1), one_by_one)


def test_levels_of_one_frame_set_share_their_maps():
    """A level built from the maps another level of the frame set computed (the chaining's
    and the refinement's at scale 2) equals one built from scratch, at its own stride."""
    from depthgt.registration.refine import Level

    g = torch.Generator().manual_seed(1)
    depth = 1.0 + torch.rand(3, 1, 32, 40, generator=g)
    depth[:, :, 5:9, 7:12] = 0
    rgb = torch.rand(3, 3, 32, 40, generator=g)
    K = torch.tensor([[30.0, 0, 20], [0, 30, 16], [0, 0, 1]])
    maps_of: dict = {}
    first = Level(rgb, depth, K, 2, 1, maps_of)
    shared = Level(rgb, depth, K, 2, 2, maps_of)
    fresh = Level(rgb, depth, K, 2, 2)
    assert shared.geo is first.geo and shared.photo is first.photo and list(maps_of) == [2]
    for name in ("geo", "photo", "points", "gray", "valid", "K", "median_depth"):
        assert torch.equal(getattr(shared, name), getattr(fresh, name)), name
    assert shared.hw == fresh.hw and first.points.shape[-1] == 4 * fresh.points.shape[-1]


def _perturbed_start(offsets):
    """A 64x64 frame set (:func:`_frameset`) with each neighbour's true pose moved by a
    random 1.5 deg and 1.5 cm: rgb, depth, K, the true poses, the moved start (F, 4, 4)."""
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64))
    gen = torch.Generator().manual_seed(5)
    T0 = torch.eye(4, dtype=torch.float64).repeat(len(offsets), 1, 1)
    T0[1:] = torch.from_numpy(T_true)
    for j in range(1, len(offsets)):
        T0[j] = _random_T(gen, 1.5, 0.015) @ T0[j]
    return rgb, depth, K, T_true, T0


def test_refinement_recovers_poses_from_a_perturbed_start():
    offsets = [0, -2, 2, 4]
    rgb, depth, K, T_true, T0 = _perturbed_start(offsets)
    r0, t0 = pose_errors(T0[1:], T_true)
    res = refine_poses(
        rgb,
        depth,
        K,
        T0,
        RefineSettings(
            scales=(2, 1), iters=(10, 10), point_stride=(1, 1), max_dist_m=(0.1, 0.05), geo_scale_m=(0.02, 0.005)
        ),
        offsets,
    )
    r1, t1 = pose_errors(res.T_f_to_t[1:], T_true)
    # 1.5 mm, not 0.5: at 64x64 the minimum of the robust cost of this scene lies ~1 mm
    # from the truth (bilinear intensity of a fine texture; the x translation is weakly
    # constrained by its geometry: a wall and a cube seen face-on). The refinement once
    # stopped nearer the truth here only because its start was a false minimum (started
    # at the truth it did not move at all; see the test with sensor holes below).
    assert np.median(r1) < 0.05 and np.median(t1) < 0.15, (r1, t1)
    assert np.median(r1) < 0.1 * np.median(r0) and np.median(t1) < 0.1 * np.median(t0), (r0, r1, t0, t1)
    assert res.final_cost.sum() < res.initial_cost.sum()


def test_coarse_scales_stop_at_their_own_step():
    # A scale before the finest ends after an accepted step under coarse_converged_step;
    # the finest still runs until no trial is accepted. With a bound of 1 m every coarse
    # scale takes one iteration (fewer in all than run to convergence at each scale, 0),
    # and the finest scale still brings the poses to the truth.
    offsets = [0, -2, 2, 4]
    rgb, depth, K, T_true, T0 = _perturbed_start(offsets)
    levels = dict(
        scales=(4, 2, 1), iters=(10, 10, 10), point_stride=(1, 1, 1), max_dist_m=(0.1, 0.05, 0.03),
        geo_scale_m=(0.02, 0.01, 0.005),
    )  # fmt: skip
    full = refine_poses(rgb, depth, K, T0, RefineSettings(**levels, coarse_converged_step=0.0), offsets)
    early = refine_poses(rgb, depth, K, T0, RefineSettings(**levels, coarse_converged_step=1.0), offsets)
    assert len(early.cost_curve) < len(full.cost_curve), (early.cost_curve, full.cost_curve)
    for res in (full, early):
        r, t = pose_errors(res.T_f_to_t[1:], T_true)
        assert np.median(r) < 0.05 and np.median(t) < 0.15, (r, t)
    with pytest.raises(ConfigError, match="refine_settings.coarse_converged_step"):
        RefineSettings(coarse_converged_step=-1.0)
    with pytest.raises(ConfigError, match="refine_settings.coarse_converged_step"):
        RefineSettings(coarse_converged_step=float("nan"))


def test_refinement_leaves_the_identity_start_with_sensor_holes():
    # Depth with holes (as every sensor's): at the identity start every warped point sits
    # on a pixel centre, and any motion lets some points fall off the view or next to a
    # hole. The LM test once charged those points as mismatches, so the start was a false
    # minimum: every step was refused and the poses stayed at the identity (errors
    # 1.5-2.4 deg, 1.1-2.2 cm here). Compared on the points seen at both poses, it converges.
    offsets = [0, -4, -2, 2, 4]
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64), step_t=0.005, step_deg=0.6, noise_m=0.0005, holes=0.1)
    T0 = torch.eye(4, dtype=torch.float64).repeat(len(offsets), 1, 1)
    r0, t0 = pose_errors(T0[1:], T_true)
    assert r0.max() > 2.0 and t0.max() > 2.0  # a real offset to recover
    res = refine_poses(
        rgb,
        depth,
        K,
        T0,
        RefineSettings(
            scales=(2, 1), iters=(10, 6), point_stride=(1, 1), max_dist_m=(0.1, 0.05), geo_scale_m=(0.02, 0.005)
        ),
        offsets,
    )
    r1, t1 = pose_errors(res.T_f_to_t[1:], T_true)
    assert r1.max() < 0.2 and t1.max() < 0.8, (r1, t1)
    assert np.all(r1 < 0.1 * r0) and np.all(t1 < 0.5 * t0), (r0, r1, t0, t1)


def test_chaining_keeps_the_right_pose_next_to_holes():
    # The chaining step scores candidate initialisations (direct, identity, via nearer
    # neighbours) by their mean cost per point that lands on the target, among those with
    # at least a quarter of the largest overlap: with sensor holes the identity (on the
    # pixel grid) sees ~2x the points of the right pose, which must still be chosen.
    from depthgt.registration.overfit import _chain, _prepare

    offsets = [0, -2, 2]
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64), step_t=0.01, step_deg=1.5, noise_m=0.0005, holes=0.1)
    s = RegistrationSettings.from_keys(dict(**FAST_TEST, iterations=0))
    fs = _prepare(rgb, depth, K, s, torch.Generator().manual_seed(0))
    T_init = torch.eye(4, dtype=torch.float64).repeat(3, 1, 1)
    T_init[1:] = torch.from_numpy(T_true)
    T_out, choice = _chain(fs, T_init, {}, offsets, s)
    assert choice == {-2: "direct", 2: "direct"}, choice


def test_residual_size_separates_aligned_from_settled_off_poses():
    # the statistic behind the high_residual check: median point-to-plane residual of
    # each neighbour in the target, at the true poses and 3 cm (+0.3 deg) off them
    offsets = [0, -2, 2, 4]
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64), noise_m=0.0005)
    no_iters = RefineSettings(scales=(1,), iters=(0,), point_stride=(1,), max_dist_m=(0.05,), geo_scale_m=(0.005,))
    T = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    T[1:] = torch.from_numpy(T_true)
    aligned = refine_poses(rgb, depth, K, T, no_iters, offsets).residual_m
    gen = torch.Generator().manual_seed(3)
    T_off = T.clone()
    for j in range(1, 4):
        dT = _random_T(gen, 0.3, 0.0)
        dT[:3, 3] = torch.tensor([0.03, -0.01, 0.02], dtype=torch.float64) * (1 if j % 2 else -1)
        T_off[j] = dT @ T[j]
    off = refine_poses(rgb, depth, K, T_off, no_iters, offsets).residual_m
    assert aligned[0] == 0 and off[0] == 0
    assert aligned[1:].max() < 0.004, aligned
    assert off[1:].min() > 2 * aligned[1:].max(), (aligned, off)
    assert off[1:].min() > RegistrationSettings().checks.max_residual_m, off


def test_high_residual_neighbours_are_flagged_not_kept():
    offsets = [0, -2, 2]
    rgb, depth, K, _ = _frameset(offsets, hw=(48, 48))
    # a bound below any real residual: every neighbour must fail with the reason named
    s = RegistrationSettings.from_keys(
        dict(
            **FAST_TEST,
            iterations=0,
            max_residual_m=1e-6,
            max_residual_sigmas=1e-6,
            refine_settings=RefineSettings(
                scales=(1,), iters=(3,), point_stride=(1,), max_dist_m=(0.05,), geo_scale_m=(0.005,)
            ),
        )
    )
    res = register_frameset(rgb, depth, K, offsets, s, seed=0)
    assert res.status == "failed" and res.neighbour_status == ["failed", "failed"]
    assert all("high_residual" in r for r in res.neighbour_reasons), res.neighbour_reasons
    assert len(res.diagnostics["residual_m"]) == 2


def test_residual_check_adapts_to_the_sensor_noise():
    # a noisy, coarse_stereo-like sensor (3 mm at 1 m, z^2 law; the room is 1.7-4.3 m
    # deep): the correctly registered neighbours' median point-to-plane residual is above
    # the fixed 8 mm bound calibrated on Kinect noise, but within the noise the frame set
    # shows; a neighbour 2 deg off is still caught
    from depthgt.registration.checks import check_neighbours

    offsets = [0, -2, 2, 4]
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64), noise_m=0.003)
    rs = RefineSettings(scales=(1,), iters=(0,), point_stride=(1,), max_dist_m=(0.05,), geo_scale_m=(0.005,))
    T = torch.eye(4, dtype=torch.float64).repeat(4, 1, 1)
    T[1:] = torch.from_numpy(T_true)
    dT = torch.eye(4, dtype=torch.float64)
    dT[:3, :3] = torch.from_numpy(_rot(np.radians(2.0) * np.array([1.0, 0.0, 0.0])))
    T[3] = dT @ T[3]
    refined = refine_poses(rgb, depth, K, T, rs, offsets)
    assert 0.0025 < refined.noise_sigma_1m < 0.0035, refined.noise_sigma_1m
    s = RegistrationSettings.from_keys(dict(**FAST_TEST, refine_settings=rs))
    assert (refined.residual_m[1:] > s.checks.max_residual_m).all(), (
        refined.residual_m
    )  # the fixed bound fails them all
    n_corr = torch.full((4,), 1000)
    fixed = s.with_keys(max_residual_sigmas=0.0)
    statuses, reasons = check_neighbours(refined.T_f_to_t, n_corr, refined, fixed.checks)
    assert statuses == ["failed", "failed", "failed"], reasons
    statuses, reasons = check_neighbours(refined.T_f_to_t, n_corr, refined, s.checks)
    assert statuses == ["ok", "ok", "failed"], (reasons, refined.residual_sigmas)
    assert "high_residual" in reasons[2] and "sigma" in reasons[2]
    assert refined.residual_sigmas[1:3].max() < 0.8 and refined.residual_sigmas[3] > 1.2, refined.residual_sigmas


def test_bf16_encoder_matches_fp32_features():
    from depthgt.registration.overfit import autocast_dtype

    assert autocast_dtype("cpu", "fp32") is None and autocast_dtype("cpu", "bf16") is torch.bfloat16
    enc = build_encoder(1, 16, 16, seed=0).eval()
    rgb = _frameset([0, 2], hw=(32, 32))[0][:1]
    every = torch.arange(32 * 32)[None]  # every pixel
    f32 = encode_at(enc, rgb, every, "fp32")
    f16 = encode_at(enc, rgb, every, "bf16")
    assert f16.dtype == torch.float32 and f16.shape == f32.shape == (1, 32 * 32, 16)
    assert torch.allclose(f32.norm(dim=2), torch.ones(1, 32 * 32), atol=1e-5)
    cos = (f32 * f16).sum(2)  # unit features: bf16 keeps them pointing the same way
    assert cos.min() > 0.99, cos.min()


def test_the_encoder_at_a_stride_gives_each_pixel_its_cells_feature():
    """``encoder_stride`` 2: the encoder sees the image averaged over 2 x 2 cells (the last
    row and column of cells partial on an odd size) and every pixel of a cell gets the
    cell's feature, exactly as encoding the averaged image at the cells."""
    import torch.nn.functional as F

    enc = build_encoder(1, 8, 8, seed=0).train()  # batch statistics, as the fast preset runs
    gen = torch.Generator().manual_seed(0)
    rgb = torch.rand(2, 3, 31, 30, generator=gen)
    every = torch.arange(31 * 30).expand(2, -1)
    f = encode_at(enc, rgb, every, "fp32", stride=2)
    cells = F.avg_pool2d(rgb, 2, ceil_mode=True, count_include_pad=False)
    assert cells.shape[-2:] == (16, 15)
    assert torch.allclose(cells[0, :, -1, -1], rgb[0, :, 30, 28:30].mean(-1))  # a partial cell: its 2 pixels
    y, x = every // 30, every % 30
    want = encode_at(enc, cells, (y // 2) * 15 + x // 2, "fp32")
    assert f.shape == (2, 31 * 30, 8) and torch.equal(f, want)
    assert torch.equal(f[:, 0], f[:, 31]) and not torch.equal(f[:, 0], f[:, 2])  # (0, 0) and (1, 1) share a cell
    with pytest.raises(ConfigError, match="registration.encoder_stride"):
        registration_settings({"encoder_stride": 0})


# ----------------------------------------------------------------------------- the frame set


FAST_TEST = dict(n_blocks=1, channels=16, feat_dim=16, n_candidates=600, top_k=60, render_stride=1)


def test_overfit_training_reduces_the_pose_error():
    offsets = [0, -2, 2]
    rgb, depth, K, T_true = _frameset(offsets, hw=(48, 48), step_t=0.03, step_deg=2.0)
    s = RegistrationSettings.from_keys(dict(**FAST_TEST, iterations=25, lr=1e-3, chaining=False, refine=False))
    res = register_frameset(rgb, depth, K, offsets, s, seed=0)
    T0 = torch.tensor(res.diagnostics["poses_paper"])
    assert len(res.loss_curve) == 25 and len(res.pose_history) == 25
    s0 = RegistrationSettings.from_keys(dict(**FAST_TEST, iterations=0, chaining=False, refine=False))
    res0 = register_frameset(rgb, depth, K, offsets, s0, seed=0)
    r_before, t_before = pose_errors(res0.T_j_to_t, T_true)
    r_after, t_after = pose_errors(T0, T_true)
    assert r_after.mean() + t_after.mean() < r_before.mean() + t_before.mean(), (r_before, t_before, r_after, t_after)
    assert np.mean(res.loss_curve[-3:]) < np.mean(res.loss_curve[:3])


def test_full_pipeline_reaches_millimetre_accuracy_and_writes_json():
    import json

    offsets = [0, -4, -2, 2, 4]
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64), step_t=0.01, step_deg=0.7)
    s = RegistrationSettings.from_keys(
        dict(
            **FAST_TEST,
            iterations=3,
            refine_settings=RefineSettings(
                scales=(2, 1), iters=(10, 8), point_stride=(1, 1), max_dist_m=(0.1, 0.05), geo_scale_m=(0.02, 0.005)
            ),
        )
    )
    res = register_frameset(rgb, depth, K, offsets, s, seed=0)
    r, t = pose_errors(res.T_j_to_t, T_true)
    assert np.median(r) < 0.05 and np.median(t) < 0.1, (r, t, res.neighbour_reasons)
    assert res.status == "ok" and res.neighbour_status == ["ok"] * 4
    d = json.loads(res.to_json())
    assert [n["offset"] for n in d["neighbours"]] == offsets[1:]
    assert set(d["timings_s"]) >= {"overfit", "refine", "total"}


def test_pretrained_encoder_state_changes_and_loads():
    from depthgt.registration.overfit import pretrain_encoder

    offsets = [0, -2, 2]
    rgb, depth, K, _ = _frameset(offsets, hw=(32, 32))
    s = RegistrationSettings.from_keys(
        {**FAST_TEST, "n_candidates": 300, "lr": 1e-2, "chaining": False, "refine": False}
    )
    state = pretrain_encoder([(rgb, depth, K, offsets)], s, epochs=2, seed=0)
    fresh = build_encoder(s.encoder.n_blocks, s.encoder.channels, s.encoder.feat_dim, seed=0).state_dict()
    assert set(state) == set(fresh)
    assert any(not torch.equal(state[k], fresh[k]) for k in state if state[k].is_floating_point())
    res = register_frameset(rgb, depth, K, offsets, s.with_keys(iterations=1), encoder_state=state)
    assert res.T_j_to_t.shape == (2, 4, 4)


def test_textureless_flat_wall_is_flagged():
    offsets = [0, -2, 2]
    rgb, depth, K, _ = _frameset(offsets, hw=(48, 48), flat=True, textured=False)
    s = RegistrationSettings.from_keys(
        dict(
            **FAST_TEST,
            iterations=2,
            refine_settings=RefineSettings(
                scales=(2, 1), iters=(5, 5), point_stride=(1, 1), max_dist_m=(0.1, 0.05), geo_scale_m=(0.02, 0.005)
            ),
        )
    )
    res = register_frameset(rgb, depth, K, offsets, s, seed=0)
    assert res.status == "failed"
    assert res.neighbour_status == ["failed", "failed"]
    assert all("degenerate" in r or "confident" in r for r in res.neighbour_reasons)


def test_settings_presets_and_bad_inputs():
    fast = registration_settings({"preset": "fast"})
    assert fast.encoder.n_blocks <= registration_settings({"preset": "paper"}).encoder.n_blocks
    assert set(REGISTRATION_PRESETS) >= {"paper", "fast"}
    # a nested override merges with the preset's refinement values
    tuned = registration_settings({"preset": "fast", "refine_settings": {"iters": [4, 4, 2]}})
    assert (
        tuned.refine_settings.iters == (4, 4, 2)
        and tuned.refine_settings.point_stride == fast.refine_settings.point_stride
    )
    from depthgt.errors import ConfigError

    with pytest.raises(ConfigError, match="registration.nonsense"):
        registration_settings({"preset": "paper", "nonsense": 1})
    with pytest.raises(ValueError, match="offsets"):
        register_frameset(torch.rand(2, 3, 8, 8), torch.ones(2, 1, 8, 8), torch.eye(3), [1, 0])
    with pytest.raises(ValueError, match="depth_m"):
        register_frameset(torch.rand(2, 3, 8, 8), torch.ones(2, 1, 8, 9), torch.eye(3), [0, 1])


@pytest.mark.fixture7
@pytest.mark.skipif(not SEVEN.is_dir(), reason="../shared/data/7scenes-kitchen is absent")
def test_real_kinect_frameset_matches_reference_poses():
    import cv2

    from depthgt.geometry import resize_depth_nearest, resize_rgb, scale_intrinsics

    offsets, target, hw = [0, -2, 2], 20, (128, 128)
    rgbs, deps, poses = [], [], []
    for o in offsets:
        stem = SEVEN / f"frame-{target + o:06d}"
        bgr = cv2.imread(str(stem) + ".color.jpg", cv2.IMREAD_COLOR)
        rgbs.append(torch.from_numpy(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)).permute(2, 0, 1).float() / 255)
        deps.append(
            torch.from_numpy(cv2.imread(str(stem) + ".depth.png", cv2.IMREAD_UNCHANGED).astype(np.float32))[None] / 1000
        )
        poses.append(np.loadtxt(str(stem) + ".pose.txt"))
    depth = resize_depth_nearest(torch.stack(deps), hw)
    depth[depth > 60] = 0  # 65.535 m marks missing depth in 7-Scenes
    rgb = resize_rgb(torch.stack(rgbs), hw)
    K = torch.from_numpy(scale_intrinsics(np.loadtxt(SEVEN / "camera-intrinsics.txt"), (480, 640), hw)).float()
    T_ref = np.stack([np.linalg.inv(poses[0]) @ p for p in poses[1:]])
    s = registration_settings(
        {
            "preset": "fast",
            "refine_settings": RefineSettings(
                scales=(2, 1), iters=(8, 5), point_stride=(1, 2), max_dist_m=(0.1, 0.05), geo_scale_m=(0.02, 0.005)
            ),
        }
    )
    res = register_frameset(rgb, depth, K, offsets, s, seed=0)
    r, t = pose_errors(res.T_j_to_t, T_ref)
    # the reference (KinectFusion) itself is good to about 0.1-0.2 deg / 0.3-0.5 cm here
    assert res.status == "ok" and r.max() < 0.5 and t.max() < 1.0, (r, t)


# ----------------------------------------------------------------------------- source poses refined (method refine)


def test_refine_source_poses_ends_closer_to_the_truth():
    """Given poses 1 deg / 1.5 cm off (a tracker's local error): refined on the frame set
    they end far closer to the truth, every neighbour passes its checks, and a
    correction beyond the bound fails the neighbour instead of being kept."""
    from depthgt.registration.local import refine_source_poses

    offsets = [0, -4, -2, 2, 4]
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64), noise_m=0.001, seed=2)
    gen = torch.Generator().manual_seed(11)
    T_given = torch.from_numpy(T_true).clone()
    for j in range(len(T_given)):
        T_given[j] = _random_T(gen, 1.0, 0.015) @ T_given[j]
    s = registration_settings(
        {
            "method": "refine",
            "refine_settings": {
                "scales": (2, 1),
                "iters": (10, 10),
                "point_stride": (1, 1),
                "max_dist_m": (0.1, 0.05),
                "geo_scale_m": (0.02, 0.005),
            },
        }
    )
    res = refine_source_poses(rgb, depth, K, offsets, T_given, s)
    r0, t0 = pose_errors(T_given, T_true)
    r1, t1 = pose_errors(res.T_j_to_t, T_true)
    assert res.status == "ok" and res.neighbour_status == ["ok"] * 4, res.neighbour_reasons
    # every neighbour ends closer, rotation to a twentieth; translation to the few mm that
    # are this 64x64 scene's floor (see test_refinement_recovers_poses_from_a_perturbed_start)
    assert (r1 < 0.1 * r0).all() and (t1 < 0.5 * t0).all() and t1.max() < 0.5, (r0, r1, t0, t1)
    tight = s.with_keys(max_correction_m=0.002)
    res = refine_source_poses(rgb, depth, K, offsets, T_given, tight)
    assert all(st == "failed" for st in res.neighbour_status)
    assert all("large_correction" in why for why in res.neighbour_reasons)
    with pytest.raises(ValueError, match="T_j_to_t"):
        refine_source_poses(rgb, depth, K, offsets, T_given[:2], s)


def test_align_refine_uses_source_poses_and_photometric_rule():
    """``align`` with method refine starts from the source's poses; the photometric term
    is left out for a source whose colour is not the depth's camera at its instant."""
    from depthgt.registration import FrameSetData, align, photometric_for

    offsets = [0, -2, 2]
    rgb, depth, K, T_true = _frameset(offsets, hw=(64, 64), seed=4)
    poses = torch.cat([torch.eye(4, dtype=torch.float64)[None], torch.from_numpy(T_true)])  # world = target camera
    data = FrameSetData(
        rgb=rgb,
        depth_m=depth,
        K=K.double(),
        T_world_cam=poses,
        truth_m=None,
        frame_ids=["a", "b", "c"],
        colour_matches_depth=False,
    )
    s = registration_settings(
        {
            "method": "refine",
            "refine_settings": {
                "scales": (2, 1),
                "iters": (6, 6),
                "point_stride": (1, 1),
                "max_dist_m": (0.1, 0.05),
                "geo_scale_m": (0.02, 0.005),
            },
        }
    )
    al = align(data, offsets, s, seed=0)
    assert al.status == "ok" and al.fused == [0, 1, 2] and al.info["photometric_weight"] == 0.0
    r, t = pose_errors(al.T_j_to_t, T_true)
    assert r.max() < 0.1 and t.max() < 0.2, (r, t)
    assert photometric_for(s, True).refine_settings.photo_weight == s.refine_settings.photo_weight > 0
    assert photometric_for(dataclasses.replace(s, photometric="on"), False).refine_settings.photo_weight > 0
    assert photometric_for(dataclasses.replace(s, photometric="off"), True).refine_settings.photo_weight == 0


def test_every_method_is_one_entry_of_the_table(monkeypatch):
    """The methods share one signature and are entries of registration.METHODS by the
    config's name, each with what it needs (the source's poses, the pretrained encoder)
    and costs; ``align`` calls the entry with the frame set, its offsets, the settings,
    the seed and the encoder state, and applies ``on_failure`` to what it returns;
    ``given`` is the source's poses, every neighbour ok, nothing estimated (poses.json
    records the method alone)."""
    import importlib

    from depthgt import registration
    from depthgt.errors import FrameError
    from depthgt.registration import FrameSetData, align, overfit
    from depthgt.registration.methods import RegistrationMethod
    from depthgt.registration.result import RegistrationResult

    assert all(isinstance(m, RegistrationMethod) and m.name == name for name, m in registration.METHODS.items())
    for m in registration.METHODS.values():
        module, function = m.register.split(":")
        assert callable(getattr(importlib.import_module(module), function)), m
        assert set(m.preset_cost) <= set(REGISTRATION_PRESETS), m
    given_, refine_, overfit_ = (registration.METHODS[n] for n in ("given", "refine", "overfit"))
    assert given_.uses_source_poses and refine_.uses_source_poses and not overfit_.uses_source_poses
    assert overfit_.pretrained_encoder and not given_.pretrained_encoder and not refine_.pretrained_encoder
    assert overfit_.job_cost("paper").mem_mb > overfit_.job_cost("fast").mem_mb == given_.job_cost("paper").mem_mb
    assert RegistrationSettings(method="overfit").uses_source_poses is False
    with pytest.raises(ConfigError, match=r"registration.method: must be one of given, refine, .*got 'no_such'"):
        RegistrationSettings(method="no_such")
    offsets = [0, -2, 2]
    gen = torch.Generator().manual_seed(0)
    T_world = torch.stack([_random_T(gen, 5.0, 0.1) for _ in offsets])
    data = FrameSetData(
        rgb=torch.rand(3, 3, 8, 8, generator=gen),
        depth_m=torch.ones(3, 1, 8, 8),
        K=torch.eye(3, dtype=torch.float64),
        T_world_cam=T_world,
        truth_m=None,
        frame_ids=["a", "b", "c"],
    )
    given = registration.METHODS["given"](data, offsets, RegistrationSettings())
    assert torch.equal(given.T_j_to_t, torch.linalg.inv(T_world[:1]) @ T_world[1:])
    assert given.neighbour_status == ["ok", "ok"] and given.status == "ok" and not given.estimated
    al = align(data, offsets, RegistrationSettings(), seed=0)
    assert al.info == {"method": "given"} and al.fused == [0, 1, 2] and torch.equal(al.T_j_to_t, given.T_j_to_t)
    for method in ("given", "refine"):  # both start from the source's poses
        with pytest.raises(FrameError, match="needs poses"):
            registration.METHODS[method](dataclasses.replace(data, T_world_cam=None), offsets, RegistrationSettings())

    calls = []

    def fake(data, offsets, settings, *, seed=0, encoder_state=None):
        calls.append((list(offsets), settings.method, seed, encoder_state))
        return RegistrationResult(
            given.T_j_to_t, list(offsets), ["failed", "ok"], ["pose_jump", ""], "ok", "", [], [], [1, 2]
        )

    monkeypatch.setattr(overfit, "register_overfit", fake)
    settings = RegistrationSettings(method="overfit", on_failure="exclude")
    al = align(data, offsets, settings, seed=7, encoder_state={"w": 1})
    assert calls == [(offsets, "overfit", 7, {"w": 1})]
    assert al.status == "failed" and al.reason == "neighbours_not_registered(offsets -2)" and al.fused == [0, 2]
    assert al.info["fused_offsets"] == [0, 2] and al.info["neighbours"][0]["reason"] == "pose_jump"
