"""The hand-written derivatives of :mod:`depthgt.registration.refine` against central
finite differences in float64.

The residuals' closed-form Jacobians are exact where the destination is locally a plane
(the point-to-plane residual does not change when the warped point slides along the
surface) and its intensity is locally linear (the Sobel gradient is then the true
gradient and bilinear sampling is exact): the scene here is a tilted plane with an
intensity ramp, so the finite differences of the full residual function, sampling
included, are the truth they must equal. A wrong sign or a missing term (e.g. the
rotation part ``q x n``, the ``-z`` term of the projection's derivative, the adjoint
chaining of the joint system) moves them far beyond the tolerance.
"""

from __future__ import annotations

import pytest
import torch
from kornia.geometry.liegroup import Se3

from depthgt.registration.refine import (
    Level,
    LevelSettings,
    _assemble,
    _residuals,
    _robust,
    adjoint,
    frame_pairs,
    normal_system,
    se3_exp,
)

H = W = 32
K = torch.tensor([[30.0, 0.0, 15.5], [0.0, 32.0, 16.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
STEP = 1e-6  # central differences in float64: error ~ STEP^2 * (3rd derivative), rounding ~ 1e-16 / STEP


def _hat(xi: torch.Tensor) -> torch.Tensor:
    """4x4 matrix of a twist (v, w): the oracle's own exponential map is torch's matrix_exp."""
    v, w = xi[:3], xi[3:]
    z = torch.zeros((), dtype=xi.dtype)
    return torch.stack(
        [
            torch.stack([z, -w[2], w[1], v[0]]),
            torch.stack([w[2], z, -w[0], v[1]]),
            torch.stack([-w[1], w[0], z, v[2]]),
            torch.stack([z, z, z, z]),
        ]
    )


def _exp(xi: torch.Tensor) -> torch.Tensor:
    return torch.linalg.matrix_exp(_hat(xi))


def _pose(xi) -> torch.Tensor:
    return _exp(torch.tensor(xi, dtype=torch.float64))


# camera-to-world poses of three frames (frame 0 the target) looking at one tilted plane
T_WORLD = torch.stack(
    [
        _pose([0, 0, 0, 0, 0, 0]),
        _pose([0.04, -0.02, 0.01, 0.02, -0.03, 0.01]),
        _pose([-0.03, 0.03, -0.02, -0.01, 0.02, -0.02]),
    ]
)
PLANE_N = torch.tensor([0.15, -0.2, 1.0], dtype=torch.float64)
PLANE_N = PLANE_N / PLANE_N.norm()
PLANE_D = 1.6  # n . X = d in the world (metres)


def _plane_frames() -> tuple[torch.Tensor, torch.Tensor]:
    """rgb (F, 3, H, W) with a per-frame linear intensity ramp and depth (F, 1, H, W) of
    the plane seen by each camera, float64."""
    v, u = torch.meshgrid(torch.arange(H, dtype=torch.float64), torch.arange(W, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)])  # (3, H, W), z = 1
    depth, rgb = [], []
    for f, T in enumerate(T_WORLD):
        n_c = T[:3, :3].T @ PLANE_N
        d_c = PLANE_D - PLANE_N @ T[:3, 3]
        depth.append(d_c / torch.einsum("c,chw->hw", n_c, rays))
        gray = 0.3 + (0.006 + 0.002 * f) * u - (0.004 - 0.001 * f) * v  # linear in the pixel coordinates
        rgb.append(gray.expand(3, H, W))
    return torch.stack(rgb), torch.stack(depth)[:, None]


@pytest.fixture(scope="module")
def level() -> Level:
    rgb, depth = _plane_frames()
    assert (depth > 0.5).all() and 0.05 < float(rgb.min()) and float(rgb.max()) < 0.95
    return Level(rgb, depth, K, scale=1, stride=1)


def _true_T_ab(pairs: torch.Tensor) -> torch.Tensor:
    return torch.linalg.inv(T_WORLD[pairs[:, 0]]) @ T_WORLD[pairs[:, 1]]


def _start(pairs: torch.Tensor) -> torch.Tensor:
    """Relative poses near the truth (residuals not zero): a small left perturbation."""
    g = torch.Generator().manual_seed(3)
    xi = (torch.rand(len(pairs), 6, generator=g, dtype=torch.float64) - 0.5) * torch.tensor(
        [0.01] * 3 + [0.005] * 3, dtype=torch.float64
    )
    return torch.stack([_exp(x) for x in xi]) @ _true_T_ab(pairs)


def _interior(level: Level, T_ab: torch.Tensor, pairs: torch.Tensor, margin: float = 2.5) -> torch.Tensor:
    """(P, N) points that land at least ``margin`` px inside the destination (its Sobel
    gradient and normals are one-sided at the border)."""
    p = level.points.index_select(0, pairs[:, 1])
    q = T_ab[:, :3, :3] @ p + T_ab[:, :3, 3:]
    u = K[0, 0] * q[:, 0] / q[:, 2] + K[0, 2]
    v = K[1, 1] * q[:, 1] / q[:, 2] + K[1, 2]
    return (u > margin) & (u < W - 1 - margin) & (v > margin) & (v < H - 1 - margin)


def _fd_jacobian(
    level: Level,
    T_ab: torch.Tensor,
    pairs: torch.Tensor,
    s: LevelSettings,
    gate: float,
    scale: torch.Tensor | float = 1.0,
) -> torch.Tensor:
    """(P, 6, M) central differences of the residuals w.r.t. a left twist of each T_ab;
    ``scale`` multiplies the unscaled geometric residual (held fixed, as the IRLS does)."""
    cols = []
    for k in range(6):
        e = torch.zeros(6, dtype=torch.float64)
        e[k] = STEP
        plus, minus = _exp(e) @ T_ab, _exp(-e) @ T_ab
        if s.photo_weight > 0:
            rp, rm = _residuals(level, plus, pairs, s, gate)[0], _residuals(level, minus, pairs, s, gate)[0]
        else:  # the unscaled point-to-plane residual, times its scale held fixed
            rp, rm = (
                _residuals(level, plus, pairs, s, gate)[4] * scale,
                _residuals(level, minus, pairs, s, gate)[4] * scale,
            )
        cols.append((rp - rm) / (2 * STEP))
    return torch.stack(cols, 1)


def _close(J: torch.Tensor, J_fd: torch.Tensor, mask: torch.Tensor) -> None:
    m = mask[:, None, :].expand_as(J)
    assert int(mask.sum()) > 200, "too few points to compare"
    err = (J - J_fd).abs()[m].max()
    ref = J_fd.abs()[m].max()
    assert float(err) <= 1e-5 * float(ref), f"max |J - J_fd| = {float(err):.3g} (max |J_fd| = {float(ref):.3g})"


def test_point_to_plane_jacobian_matches_finite_differences(level):
    pairs = frame_pairs(3, "all")
    T_ab = _start(pairs)
    s = LevelSettings(geo_scale_m=0.01, photo_scale=0.03, photo_weight=0.0, robust="huber")
    r, J, valid, _, _ = _residuals(level, T_ab, pairs, s, gate=0.05)
    assert J.shape == (len(pairs), 6, level.points.shape[-1])
    J_fd = _fd_jacobian(level, T_ab, pairs, s, 0.05, scale=1.0 / s.geo_scale_m)
    _close(J, J_fd, valid & _interior(level, T_ab, pairs))
    # the rotation columns are not small here: a test of the translation block alone would miss q x n
    assert float(J[:, 3:].abs().max()) > 0.5 * float(J[:, :3].abs().max())


def test_point_to_plane_jacobian_with_the_depth_dependent_scale(level):
    """geo_ref_depth_m > 0: the robust scale grows as (z / ref)^2 per point and is a
    weight of the residual, held fixed by the Jacobian (IRLS), like the finite
    differences of the unscaled residual times the same scale."""
    pairs = frame_pairs(3, "target")
    T_ab = _start(pairs)
    s = LevelSettings(geo_scale_m=0.01, photo_scale=0.03, photo_weight=0.0, robust="cauchy", geo_ref_depth_m=1.2)
    r, J, valid, _, r_geo = _residuals(level, T_ab, pairs, s, gate=0.05)
    scale = r / r_geo.where(r_geo.abs() > 1e-12, torch.ones_like(r_geo))  # 1 / (geo_scale_m * (z / ref)^2)
    assert float(scale.min()) < 0.99 / s.geo_scale_m, "the plane must reach beyond geo_ref_depth_m"
    J_fd = _fd_jacobian(level, T_ab, pairs, s, 0.05, scale=scale)
    _close(J, J_fd, valid & _interior(level, T_ab, pairs) & (r_geo.abs() > 1e-12))


def test_photometric_jacobian_matches_finite_differences(level):
    pairs = frame_pairs(3, "all")
    T_ab = _start(pairs)
    s = LevelSettings(geo_scale_m=0.01, photo_scale=0.03, photo_weight=0.5, robust="huber")
    r, J, valid, _, _ = _residuals(level, T_ab, pairs, s, gate=0.05)
    n = level.points.shape[-1]
    assert J.shape == (len(pairs), 6, 2 * n)
    J_fd = _fd_jacobian(level, T_ab, pairs, s, 0.05)
    inside = _interior(level, T_ab, pairs)
    _close(J, J_fd, valid & torch.cat([inside, inside], 1))
    # the photometric half has its own, non-zero derivative (not a copy of the geometric one)
    assert float(J[:, :, n:].abs().max()) > 0.1


def test_adjoint_matches_the_conjugated_exponential():
    """T exp(xi) T^-1 = exp(Ad_T xi), with the oracle's own exponential (matrix_exp) and
    kornia's Se3.exp (what refine_poses applies) agreeing on the twist order (v, w)."""
    g = torch.Generator().manual_seed(1)
    for _ in range(4):
        T = _exp((torch.rand(6, generator=g, dtype=torch.float64) - 0.5) * 2)
        xi = (torch.rand(6, generator=g, dtype=torch.float64) - 0.5) * 0.2
        lhs = T @ _exp(xi) @ torch.linalg.inv(T)
        assert torch.allclose(lhs, _exp(adjoint(T) @ xi), atol=1e-12)
        assert torch.allclose(Se3.exp(xi[None]).matrix()[0].to(torch.float64), _exp(xi), atol=1e-12)


def test_the_refinements_exponential_is_kornias():
    """``se3_exp`` (what refine_poses applies to each trial's step) is kornia's
    ``Se3.exp(xi).matrix()`` to float64 rounding, for twists from 0.3 down to 1e-9 (the
    small-angle range of kornia's series) and zero, each component on its own and all
    together."""
    g = torch.Generator().manual_seed(2)
    for scale in (0.3, 1e-3, 1e-6, 1e-9, 0.0):
        xi = (torch.rand(12, 6, generator=g, dtype=torch.float64) - 0.5) * 2 * scale
        xi[:6] = torch.eye(6, dtype=torch.float64) * scale  # one component at a time
        with torch.no_grad():
            want = Se3.exp(xi).matrix().to(torch.float64)
        got = se3_exp(xi)
        assert got.dtype == torch.float64 and got.shape == (12, 4, 4)
        assert float((got - want).abs().max()) <= 1e-15, scale
        assert torch.equal(got[:, 3], torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(12, 4))


@pytest.mark.parametrize("photo_weight", [0.0, 0.5])
def test_joint_normal_system_matches_finite_differences(level, photo_weight):
    """The per-pair systems chained through the adjoint into the frames' system
    (``normal_system`` + ``_assemble``, as refine_poses solves it): its gradient g equals
    the finite differences of the IRLS cost 1/2 sum w r^2 (weights and association held
    at the current poses) w.r.t. a left twist of each frame's pose T_f <- exp(d_f) T_f,
    and H equals J^T W J of the finite-difference J."""
    n_frames = 3
    pairs = frame_pairs(n_frames, "all")
    g_ = torch.Generator().manual_seed(5)
    T = torch.stack(
        [torch.eye(4, dtype=torch.float64)]
        + [
            _exp((torch.rand(6, generator=g_, dtype=torch.float64) - 0.5) * 0.01)
            @ torch.linalg.inv(T_WORLD[0])
            @ T_WORLD[f]
            for f in range(1, n_frames)
        ]
    )
    s = LevelSettings(geo_scale_m=0.01, photo_scale=0.03, photo_weight=photo_weight, robust="huber")
    gate = 0.05

    def residuals(T_frames):
        T_ab = torch.linalg.inv(T_frames[pairs[:, 0]]) @ T_frames[pairs[:, 1]]
        return _residuals(level, T_ab, pairs, s, gate)

    r0, J_rel, valid, _, _ = residuals(T)
    w, _ = _robust(r0, s.robust)
    # normal_system is J^T W r and J^T W J of these Jacobians with the IRLS weights
    H_all, g_all, _, _, Tinv = normal_system(level, T, pairs, s, gate)
    Jw = J_rel * (w * valid)[:, None]
    assert torch.allclose(H_all, Jw @ J_rel.transpose(1, 2), rtol=1e-12, atol=1e-9)
    assert torch.allclose(g_all, (Jw @ r0[..., None])[..., 0], rtol=1e-12, atol=1e-9)
    # the joint system of the points landing inside the destinations (their one-sided
    # border gradients are not the plane's), chained by _assemble as refine_poses does
    W = w * valid * _keep(level, T, pairs, photo_weight > 0)
    H_rel = (J_rel * W[:, None]) @ J_rel.transpose(1, 2)
    g_rel = ((J_rel * W[:, None]) @ r0[..., None])[..., 0]
    H, g = _assemble(H_rel, g_rel, Tinv, pairs, n_frames)

    J_fd = torch.zeros(len(pairs), r0.shape[1], n_frames, 6, dtype=torch.float64)
    for f in range(n_frames):
        for k in range(6):
            e = torch.zeros(6, dtype=torch.float64)
            e[k] = STEP
            Tp, Tm = T.clone(), T.clone()
            Tp[f], Tm[f] = _exp(e) @ T[f], _exp(-e) @ T[f]
            J_fd[:, :, f, k] = (residuals(Tp)[0] - residuals(Tm)[0]) / (2 * STEP)
    J_fd = J_fd.reshape(len(pairs), r0.shape[1], n_frames * 6)
    g_fd = torch.einsum("pm,pmk->k", W * r0, J_fd).reshape(n_frames, 6)
    H_fd = torch.einsum("pmi,pm,pmj->ij", J_fd, W, J_fd).reshape(n_frames, 6, n_frames, 6).permute(0, 2, 1, 3)
    assert float(g_fd.abs().max()) > 1.0 and float(H_fd.abs().max()) > 1.0
    assert torch.allclose(g, g_fd, rtol=1e-5, atol=1e-5 * float(g_fd.abs().max()))
    assert torch.allclose(H, H_fd, rtol=1e-5, atol=1e-5 * float(H_fd.abs().max()))


def _keep(level: Level, T: torch.Tensor, pairs: torch.Tensor, photometric: bool) -> torch.Tensor:
    T_ab = torch.linalg.inv(T[pairs[:, 0]]) @ T[pairs[:, 1]]
    inside = _interior(level, T_ab, pairs)
    return torch.cat([inside, inside], 1) if photometric else inside
