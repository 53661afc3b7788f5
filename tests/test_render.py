"""Tests of depthgt.gt.render: soft splat (gradients, occlusion, reference) and the GT renderer."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from render_reference import render_gt_reference, splat_soft_reference

from depthgt.errors import ConfigError
from depthgt.geometry import resize_depth_nearest, scale_intrinsics
from depthgt.gt.render import (
    GTRender,
    SoftSplat,
    cloud_in_target,
    composite_gt,
    estimate_noise_sigma_1m,
    rasterise_gt,
    render_gt,
    resampled_positions,
    splat_soft,
)
from depthgt.gt.render.agreement import frame_agreement
from depthgt.gt.render.compositor import _choose_surfaces
from depthgt.gt.render.rasteriser import rasterise_blocks
from depthgt.settings import RenderSettings


def _K(b: int, f: float, cx: float, cy: float, dtype=torch.float64) -> torch.Tensor:
    return torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1]], dtype=dtype).expand(b, 3, 3).clone()


def _unproject(uv: torch.Tensor, z: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """(N, 2) pixel positions and (N,) depths -> (N, 3) points for a (3, 3) K."""
    x = (uv[:, 0] - K[0, 2]) / K[0, 0] * z
    y = (uv[:, 1] - K[1, 2]) / K[1, 1] * z
    return torch.stack([x, y, z], dim=1)


# ------------------------------------------------------------------ splat_soft


def test_splat_single_point_footprint():
    K = _K(1, 10.0, 4.0, 4.0)
    p = _unproject(torch.tensor([[4.0, 4.0]], dtype=torch.float64), torch.tensor([2.0], dtype=torch.float64), K[0])
    out = splat_soft(p[None], torch.tensor([[[0.25, 0.75]]], dtype=torch.float64), K, (9, 9), radius_px=2.0)
    assert isinstance(out, SoftSplat)
    assert out.features.shape == (1, 2, 9, 9) and out.depth.shape == (1, 1, 9, 9) and out.weight.shape == (1, 1, 9, 9)
    assert out.weight[0, 0, 4, 4] == pytest.approx(1.0)
    assert out.weight[0, 0, 4, 5] == pytest.approx((1 - 1 / 4) ** 2)
    assert out.weight[0, 0, 4, 6] == 0  # exactly at the radius: weight falls to zero
    assert out.weight[0, 0, 5, 5] == pytest.approx((1 - 2 / 4) ** 2)
    covered = out.weight[0, 0] > 0
    assert int(covered.sum()) == 9  # pixel centres strictly within 2 px of (4, 4): 3x3 block
    assert torch.allclose(out.depth[0, 0][covered], torch.tensor(2.0, dtype=torch.float64))
    assert torch.allclose(out.features[0, 1][covered], torch.tensor(0.75, dtype=torch.float64))
    assert (out.depth[0, 0][~covered] == 0).all() and (out.features[0][:, ~covered] == 0).all()


def test_splat_occlusion_and_cap():
    K = _K(1, 10.0, 4.0, 4.0)
    uv = torch.tensor([[4.0, 4.0], [4.2, 4.1], [3.9, 4.0]], dtype=torch.float64)
    z = torch.tensor([1.0, 3.0, 1.02], dtype=torch.float64)
    p = _unproject(uv, z, K[0])[None]
    f = torch.tensor([[[1.0], [5.0], [1.0]]], dtype=torch.float64)
    out = splat_soft(p, f, K, (9, 9), radius_px=1.5)
    assert float(out.depth[0, 0, 4, 4]) < 1.03  # the point at 3 m is hidden behind the front ones
    assert float(out.features[0, 0, 4, 4]) == pytest.approx(1.0)
    # without the band, the cap alone (nearest in depth) still hides the farthest point
    out = splat_soft(p, f, K, (9, 9), radius_px=1.5, depth_band_rel=None, max_points=2)
    assert float(out.features[0, 0, 4, 4]) == pytest.approx(1.0)
    out = splat_soft(p, f, K, (9, 9), radius_px=1.5, depth_band_rel=None, max_points=3)
    assert float(out.features[0, 0, 4, 4]) > 1.5  # now it bleeds through, as documented


def test_splat_ignores_invalid_behind_and_outside():
    K = _K(1, 10.0, 4.0, 4.0)
    p = torch.tensor([[[0.0, 0.0, 2.0], [0.0, 0.0, -2.0], [50.0, 0.0, 1.0], [0.1, 0.1, 2.0]]], dtype=torch.float64)
    valid = torch.tensor([[True, True, True, False]])
    out = splat_soft(p, torch.ones(1, 4, 1, dtype=torch.float64), K, (9, 9), valid=valid, radius_px=1.0)
    assert int((out.weight > 0).sum()) == 1 and float(out.depth[0, 0, 4, 4]) == 2.0


def test_splat_matches_reference():
    g = torch.Generator().manual_seed(3)
    b, n, h, w = 2, 40, 12, 14
    K = _K(b, 12.0, 6.3, 5.8)
    uv = (
        torch.rand(b, n, 2, generator=g, dtype=torch.float64) * torch.tensor([w + 2.0, h + 2.0], dtype=torch.float64)
        - 1
    )
    z = 1.0 + torch.rand(b, n, generator=g, dtype=torch.float64) * 0.3
    p = torch.stack([_unproject(uv[i], z[i], K[i]) for i in range(b)])
    f = torch.rand(b, n, 3, generator=g, dtype=torch.float64)
    valid = torch.rand(b, n, generator=g) > 0.1
    out = splat_soft(p, f, K, (h, w), valid=valid, radius_px=1.7, max_points=3, depth_band_rel=0.1)
    for i in range(b):
        rf, rz, rw = splat_soft_reference(
            p[i].numpy(),
            f[i].numpy(),
            K[i].numpy(),
            (h, w),
            valid[i].numpy(),
            radius_px=1.7,
            max_points=3,
            depth_band_rel=0.1,
        )
        np.testing.assert_allclose(out.weight[i, 0].numpy(), rw, atol=1e-12)
        np.testing.assert_allclose(out.depth[i, 0].numpy(), rz, atol=1e-12)
        np.testing.assert_allclose(out.features[i].numpy(), rf, atol=1e-12)


def test_splat_gradcheck():
    K = _K(1, 8.0, 3.5, 3.0)
    uv = torch.tensor([[2.3, 2.7], [3.65, 3.25], [4.1, 2.15]], dtype=torch.float64)
    z = torch.tensor([1.0, 1.01, 1.02], dtype=torch.float64)
    p = _unproject(uv, z, K[0])[None].requires_grad_()
    f = torch.tensor([[[0.2, 0.9], [0.5, 0.1], [0.7, 0.4]]], dtype=torch.float64, requires_grad=True)

    def fn(p, f):
        out = splat_soft(p, f, K, (6, 7), radius_px=2.0, max_points=16)
        return out.features, out.depth, out.weight

    assert torch.autograd.gradcheck(fn, (p, f), eps=1e-6, atol=1e-6)
    fn(p, f)[1].sum().backward()
    assert p.grad is not None and p.grad.abs().sum() > 0


def test_splat_bad_shapes():
    K = _K(1, 10.0, 4.0, 4.0)
    with pytest.raises(ValueError, match="points_cam"):
        splat_soft(torch.zeros(1, 5, 2), torch.zeros(1, 5, 1), K, (9, 9))
    with pytest.raises(ValueError, match="features"):
        splat_soft(torch.zeros(1, 5, 3), torch.zeros(1, 4, 1), K, (9, 9))
    with pytest.raises(ValueError, match="K must be"):
        splat_soft(torch.zeros(2, 5, 3), torch.zeros(2, 5, 1), K, (9, 9))
    with pytest.raises(ValueError, match="valid"):
        splat_soft(torch.zeros(1, 5, 3), torch.zeros(1, 5, 1), K, (9, 9), valid=torch.ones(1, 5))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")
def test_splat_cuda_matches_cpu():
    g = torch.Generator().manual_seed(1)
    K = _K(1, 30.0, 16.0, 16.0, torch.float32)
    p = torch.rand(1, 500, 3, generator=g) * torch.tensor([1.0, 1.0, 1.0]) + torch.tensor([-0.5, -0.5, 1.0])
    f = torch.rand(1, 500, 3, generator=g)
    a = splat_soft(p, f, K, (32, 32))
    c = splat_soft(p.cuda(), f.cuda(), K.cuda(), (32, 32))
    assert c.depth.device.type == "cuda"
    assert torch.allclose(a.depth, c.depth.cpu(), atol=1e-5) and torch.allclose(a.features, c.features.cpu(), atol=1e-5)


# ------------------------------------------------------------------ render_gt


def _two_layer_cloud(seed: int, n_bg: int = 900, n_fg: int = 250):
    """Points of a tilted background plane and a nearer tilted patch, with normals, frame
    ids (4 frames) and per-point sigmas, at random sub-pixel positions of a 16x16 view
    (f = 14)."""
    g = torch.Generator().manual_seed(seed)
    K = _K(1, 14.0, 7.5, 7.5)
    uv_bg = torch.rand(n_bg, 2, generator=g, dtype=torch.float64) * 18 - 1
    uv_fg = torch.rand(n_fg, 2, generator=g, dtype=torch.float64) * torch.tensor([7.0, 9.0], dtype=torch.float64) + 4
    # a gap in the background right of the patch: an edge with nothing seen behind it
    gap = (uv_bg[:, 0] >= 11) & (uv_bg[:, 0] < 14) & (uv_bg[:, 1] >= 4) & (uv_bg[:, 1] < 13)
    uv_bg = uv_bg[~gap]
    pts, nrms = [], []
    for uv, n_plane, d in [(uv_bg, [0.3, -0.2, -1.0], -2.0), (uv_fg, [-0.4, 0.1, -1.0], -1.2)]:
        n_plane = torch.tensor(n_plane, dtype=torch.float64)
        n_plane = n_plane / n_plane.norm()
        ray = torch.stack(
            [(uv[:, 0] - 7.5) / 14.0, (uv[:, 1] - 7.5) / 14.0, torch.ones(len(uv), dtype=torch.float64)], 1
        )
        z = d / (ray @ n_plane)  # on the plane n.X = d
        pts.append(ray * z[:, None])
        nrms.append(n_plane.expand(len(uv), 3).clone())
    p = torch.cat(pts)[None]
    nrm = torch.cat(nrms)[None]
    nrm[0, torch.rand(len(nrm[0]), generator=g) < 0.2] = 0  # some points without a normal
    p = p + 0.002 * torch.randn(p.shape, generator=g, dtype=torch.float64)  # off-plane noise
    valid = torch.rand(1, p.shape[1], generator=g) > 0.05
    frame = torch.randint(0, 4, (1, p.shape[1]), generator=g)
    sigma = 0.002 + 0.001 * torch.rand(1, p.shape[1], generator=g, dtype=torch.float64)
    return p, nrm, valid, K, frame, sigma


def _compare_with_reference(p, nrm, valid, K, frame, sigma, st, src_hw, target_frame=None):
    out = render_gt(
        p, K, (16, 16), valid, st, normals_cam=nrm, sigma_m=sigma, frame=frame, src_hw=src_hw, target_frame=target_frame
    )
    assert isinstance(out, GTRender)
    rd, rw, rc, rs, ra = render_gt_reference(
        p[0].numpy(),
        K[0].numpy(),
        (16, 16),
        valid[0].numpy(),
        st,
        None if nrm is None else nrm[0].numpy(),
        None if sigma is None else sigma[0].numpy(),
        None if frame is None else frame[0].numpy(),
        src_hw,
        target_frame,
    )
    np.testing.assert_allclose(out.agreement[0].numpy(), ra, atol=1e-6)
    np.testing.assert_array_equal(out.count[0, 0].numpy(), rc)
    np.testing.assert_allclose(out.weight_sum[0, 0].numpy(), rw, atol=1e-12)
    np.testing.assert_allclose(out.depth[0, 0].numpy(), rd, atol=1e-10)
    np.testing.assert_allclose(out.sigma[0, 0].numpy(), rs, atol=1e-10, rtol=1e-8)
    return out, rd, rc, rs


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("src_hw", [None, (30, 40)])
@pytest.mark.parametrize("variant", ["default", "normals", "plain", "strict", "union", "resolve"])
def test_render_gt_matches_reference(seed, src_hw, variant):
    """The vectorised renderer against the plain loop oracle (tests/render_reference.py)."""
    p, nrm, valid, K, frame, sigma = _two_layer_cloud(seed)
    kw = {
        "default": {},
        "normals": dict(plane="normals"),
        "plain": dict(plane="none", drop_ambiguous=False),
        "strict": dict(extend_uncovered=False, min_frames=3, max_sigma_m=0.002),
        "union": dict(edge_vote=0.0),
        "resolve": dict(target_resolves_ambiguous=True),
    }[variant]
    st = RenderSettings(m=5, radius_px=1.3, min_points=2, **kw)
    if variant in ("strict", "resolve"):  # the target's own samples, right on some sample positions
        gu = (
            resampled_positions(src_hw[1], 16, dtype=torch.float64) if src_hw else torch.arange(16, dtype=torch.float64)
        )
        gv = (
            resampled_positions(src_hw[0], 16, dtype=torch.float64) if src_hw else torch.arange(16, dtype=torch.float64)
        )
        step = 3 if variant == "strict" else 1
        uv = torch.stack(torch.meshgrid(gu[::step], gv[::step], indexing="xy"), -1).reshape(-1, 2)
        if variant == "strict":  # a lone frame at 1.1 m
            z_on = torch.full((len(uv),), 1.1, dtype=torch.float64)
        else:  # the target sees the background plane everywhere (the patch's edge pixels are ambiguous);
            # off the positions by < 0.02 px, so that no two samples tie in distance to a position
            uv = uv + 0.02 * (
                torch.rand(uv.shape, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) - 0.5
            )
            n_bg = torch.tensor([0.3, -0.2, -1.0], dtype=torch.float64)
            ray = torch.stack(
                [(uv[:, 0] - 7.5) / 14.0, (uv[:, 1] - 7.5) / 14.0, torch.ones(len(uv), dtype=torch.float64)], 1
            )
            z_on = -2.0 / (ray @ (n_bg / n_bg.norm()))
        on = _unproject(uv, z_on, K[0])[None]
        p, nrm = torch.cat([p, on], 1), torch.cat([nrm, torch.zeros_like(on)], 1)
        valid = torch.cat([valid, torch.ones(1, on.shape[1], dtype=torch.bool)], 1)
        frame = torch.cat([frame, torch.full((1, on.shape[1]), 7)], 1)
        sigma = torch.cat([sigma, torch.full((1, on.shape[1]), 0.002, dtype=torch.float64)], 1)
    out, rd, rc, rs = _compare_with_reference(
        p, nrm, valid, K, frame, sigma, st, src_hw, target_frame=7 if variant in ("strict", "resolve") else None
    )
    if variant == "resolve":  # the target's samples decided pixels the default leaves empty
        plain = render_gt(
            p,
            K,
            (16, 16),
            valid,
            RenderSettings(m=5, radius_px=1.3, min_points=2),
            normals_cam=nrm,
            sigma_m=sigma,
            frame=frame,
            src_hw=src_hw,
            target_frame=7,
        )
        assert ((rd > 0) & (plain.depth[0, 0].numpy() == 0)).any()
        return
    # the case exercises both surfaces, the cap and min_points
    assert (rc == st.m).any() and (variant == "strict" or ((rc > 0) & (rc < st.min_points)).any())
    assert (rd > 1.5).any() and ((rd > 0) & (rd < 1.4)).any()
    assert (rs[rd > 0] > 0).all()
    if variant == "strict":  # max_sigma_m left out pixels that still have a sigma
        assert ((rd == 0) & (rs > 0.002)).any()
        # the lone target frame's surface at 1.1 m (in front of everything) wins where its
        # samples sit on the positions; its single sample is below min_points there
        assert (rc[::3, ::3] == 1).all() and (rd[::3, ::3] == 0).all()


@pytest.mark.parametrize("seed", [2, 3])
def test_render_gt_matches_reference_without_frames_and_sigmas(seed):
    p, nrm, valid, K, _, _ = _two_layer_cloud(seed)
    _compare_with_reference(p, None, valid, K, None, None, RenderSettings(m=7, noise_sigma_1m=0.004), None)


def test_render_gt_leaves_out_a_misregistered_frame():
    """A neighbour 5 cm off (misregistered) disagrees with the target's own depth and is
    left out; the correct neighbours stay (vectorised renderer vs the oracle)."""
    g = torch.Generator().manual_seed(5)
    h = w = 20
    K = _K(1, 20.0, 9.5, 9.5)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    plane = lambda uv: 2.0 + 0.01 * uv[:, 0] + 0.02 * uv[:, 1]  # noqa: E731 (depth of a slanted plane)
    uv_t = torch.stack([u.flatten(), v.flatten()], 1)
    pts, frames = [_unproject(uv_t, plane(uv_t), K[0])], [torch.zeros(h * w, dtype=torch.long)]
    for j in range(1, 5):
        uv = torch.rand(h * w, 2, generator=g, dtype=torch.float64) * (w - 1)
        z = plane(uv) + (0.05 if j == 4 else 0.0) + 0.002 * torch.randn(h * w, generator=g, dtype=torch.float64)
        pts.append(_unproject(uv, z, K[0]))
        frames.append(torch.full((h * w,), j))
    p, frame = torch.cat(pts)[None], torch.cat(frames)[None]
    st = RenderSettings(noise_sigma_1m=0.0012)
    out = render_gt(p, K, (h, w), settings=st, frame=frame, target_frame=0)
    rd, rw, rc, rs, ra = render_gt_reference(
        p[0].numpy(), K[0].numpy(), (h, w), None, st, frame=frame[0].numpy(), target_frame=0
    )
    np.testing.assert_allclose(out.agreement[0].numpy(), ra, atol=1e-6)
    np.testing.assert_allclose(out.depth[0, 0].numpy(), rd, atol=1e-5)
    np.testing.assert_array_equal(out.count[0, 0].numpy(), rc)
    assert np.isnan(ra[0]) and (ra[1:4] > 0.95).all() and ra[4] < 0.9
    truth = plane(uv_t).reshape(h, w)
    assert float((out.depth[0, 0] - truth).abs().mean()) < 0.002
    # without the check the off frame drags the GT towards itself
    off = render_gt(
        p,
        K,
        (h, w),
        settings=RenderSettings(noise_sigma_1m=0.0012, min_frame_agreement=0.0),
        frame=frame,
        target_frame=0,
    )
    assert float((off.depth[0, 0] - truth).abs().mean()) > 2 * float((out.depth[0, 0] - truth).abs().mean())


def test_render_gt_guard_hides_occluded_points():
    """Far points projecting right on a pixel's sample position must not bleed through
    a near surface that covers it, and a near surface to one side must not claim a
    pixel whose position sees the far one."""
    K = _K(1, 10.0, 4.0, 4.0)
    uv = torch.tensor([[4.0, 4.0], [4.02, 3.97], [3.6, 4.0], [4.4, 4.0], [4.0, 3.6], [4.0, 4.4]], dtype=torch.float64)
    z = torch.tensor([3.0, 3.0, 1.0, 1.0, 1.0, 1.0], dtype=torch.float64)
    frame = torch.tensor([[0, 1, 2, 3, 2, 3]])
    out = render_gt(_unproject(uv, z, K[0])[None], K, (9, 9), settings=RenderSettings(radius_px=1.0), frame=frame)
    assert float(out.depth[0, 0, 4, 4]) == pytest.approx(1.0) and int(out.count[0, 0, 4, 4]) == 4
    uv = torch.tensor([[4.0, 4.0], [4.2, 3.9], [3.8, 4.1], [4.7, 4.0], [4.75, 4.1]], dtype=torch.float64)
    z = torch.tensor([3.0, 3.0, 3.0, 1.0, 1.0], dtype=torch.float64)
    out = render_gt(
        _unproject(uv, z, K[0])[None],
        K,
        (9, 9),
        settings=RenderSettings(radius_px=1.0),
        frame=torch.tensor([[0, 1, 2, 1, 2]]),
    )
    assert float(out.depth[0, 0, 4, 4]) == pytest.approx(3.0, abs=1e-3)


def test_render_gt_needs_support_of_several_frames():
    """A lone frame's sample in front (an outlier) does not hide a surface that two
    frames see; min_frames=1 lets it."""
    K = _K(1, 10.0, 4.0, 4.0)
    uv = torch.tensor([[4.05, 4.0], [3.8, 4.1], [4.2, 3.9], [4.0, 4.2], [3.9, 3.8]], dtype=torch.float64)
    z = torch.tensor([1.0, 2.0, 2.0, 2.0, 2.0], dtype=torch.float64)
    p, frame = _unproject(uv, z, K[0])[None], torch.tensor([[0, 1, 2, 1, 2]])
    out = render_gt(p, K, (9, 9), settings=RenderSettings(radius_px=1.0), frame=frame)
    assert float(out.depth[0, 0, 4, 4]) == pytest.approx(2.0, abs=1e-3)
    out = render_gt(p, K, (9, 9), settings=RenderSettings(radius_px=1.0, min_frames=1), frame=frame)
    assert float(out.depth[0, 0, 4, 4]) == pytest.approx(1.0, abs=1e-3)


def test_render_gt_min_points_and_empty():
    K = _K(1, 10.0, 4.0, 4.0)
    p = _unproject(torch.tensor([[4.0, 4.0]], dtype=torch.float64), torch.tensor([2.0], dtype=torch.float64), K[0])[
        None
    ]
    out = render_gt(p, K, (9, 9), settings=RenderSettings(min_points=2))
    assert out.depth.abs().sum() == 0 and int(out.count[0, 0, 4, 4]) == 1 and float(out.weight_sum[0, 0, 4, 4]) == 1.0
    out = render_gt(torch.zeros(1, 0, 3, dtype=torch.float64), K, (9, 9))
    assert out.depth.shape == (1, 1, 9, 9) and out.depth.abs().sum() == 0 and out.sigma.abs().sum() == 0


def test_render_gt_gradients_reach_points():
    p, nrm, valid, K, frame, sigma = _two_layer_cloud(0, n_bg=200, n_fg=50)
    p = p.clone().requires_grad_()
    out = render_gt(p, K, (16, 16), valid, RenderSettings(), normals_cam=nrm, sigma_m=sigma, frame=frame)
    out.depth.sum().backward()
    assert torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0


def test_render_gt_gradcheck():
    """Analytic gradients of the plane fit match finite differences."""
    K = _K(1, 8.0, 3.5, 3.0)
    uv = torch.tensor([[2.3, 2.7], [3.35, 3.2], [2.8, 3.6], [3.1, 2.45]], dtype=torch.float64)
    z = torch.tensor([1.0, 1.01, 1.02, 1.005], dtype=torch.float64)
    p = _unproject(uv, z, K[0])[None].requires_grad_()
    n = torch.nn.functional.normalize(torch.tensor([[[0.1, -0.2, -1.0]]], dtype=torch.float64).expand(1, 4, 3), dim=-1)
    n = n.clone().requires_grad_()
    st = RenderSettings(radius_px=1.25, drop_ambiguous=False, extend_uncovered=False, min_frames=1, noise_sigma_1m=0.01)

    def fn(p, n):
        out = render_gt(p, K, (6, 7), settings=st, normals_cam=n)
        return out.depth, out.weight_sum

    assert torch.autograd.gradcheck(fn, (p, n), eps=1e-6, atol=1e-6)


def test_render_gt_bad_input():
    K = _K(1, 10.0, 4.0, 4.0)
    with pytest.raises(ValueError, match="normals_cam"):
        render_gt(torch.ones(1, 4, 3), K, (9, 9), normals_cam=torch.ones(1, 3, 3))
    with pytest.raises(ValueError, match="frame"):
        render_gt(torch.ones(1, 4, 3), K, (9, 9), frame=torch.zeros(1, 3, dtype=torch.long))
    with pytest.raises(ConfigError, match="render.plane"):
        RenderSettings(plane="spline")
    with pytest.raises(ConfigError, match="render.noise_sigma_1m"):
        RenderSettings(noise_sigma_1m=0)
    with pytest.raises(ValueError, match=r"\(B, N, 3\)"):
        render_gt(torch.ones(4, 3), K, (9, 9))


def test_rasterised_candidates_are_sorted_by_pixel_front_first():
    """The rasteriser's record: candidates by pixel, front first within a pixel, each
    within radius_px of its point's projection, with the shapes its docstring states."""
    p, nrm, valid, K, frame, sigma = _two_layer_cloud(4)
    st = RenderSettings(radius_px=1.3)
    c = rasterise_gt(p, K, (16, 16), st, valid=valid, normals_cam=nrm, sigma_m=sigma, frame=frame, src_hw=(32, 32))
    n_c = c.pixel.numel()
    assert n_c > p.shape[1] and c.size == (1, 16, 16) and c.n_frames == 4 and c.grad.shape == (p.shape[1], 2)
    assert all(t.shape == (n_c,) for t in (c.point, c.ox, c.oy, c.d2, c.iz, c.s, c.frame))
    assert (c.pixel.diff() >= 0).all()
    same = c.pixel[1:] == c.pixel[:-1]
    assert (c.iz[1:][same] <= c.iz[:-1][same]).all()  # front first within a pixel
    assert torch.equal(c.iz, 1.0 / p[0, c.point, 2]) and torch.equal(c.frame, frame[0, c.point])
    assert valid[0, c.point].all() and (c.d2 < st.radius_px**2).all() and torch.equal(c.d2, c.ox**2 + c.oy**2)
    assert torch.allclose(c.s, sigma[0, c.point] / p[0, c.point, 2] ** 2)


def _same_candidates(a, b) -> None:
    for name in ("pixel", "point", "ox", "oy", "d2", "iz", "s", "frame", "grad", "iz_point"):
        x, y = getattr(a, name), getattr(b, name)
        assert (x is None) == (y is None) and (x is None or (x.dtype == y.dtype and torch.equal(x, y))), name
    assert (a.size, a.n_frames, a.first_pixel, a.pixels) == (b.size, b.n_frames, b.first_pixel, b.pixels)


def test_the_compiled_rasteriser_finds_the_tensor_paths_candidates():
    """The CPU's compiled cells (a counting sort by pixel) against the tensor path a GPU
    runs, bit for bit: float32 and float64 points, pixel centres and resampled sample
    positions, two radii, two images stacked, points off the image and behind the
    camera, points at one depth (ties in a pixel), in blocks of rows and in one; with
    gradients wanted, the same values and the gradients reach the points."""
    p64, nrm, valid, K, frame, sigma = _two_layer_cloud(7)
    p64 = p64.clone()
    p64[0, :40, 2] = -1.0  # behind the camera
    p64[0, 100::4, 2] = float(p64[0, 99, 2])  # a quarter at one depth: ties within pixels
    ties = 0
    for dtype in (torch.float32, torch.float64):
        p = p64.to(dtype)
        for radius, src_hw in ((1.3, (32, 32)), (2.0, None), (1.25, (37, 29))):
            st = RenderSettings(radius_px=radius)
            kw = dict(valid=valid, normals_cam=nrm.to(dtype), sigma_m=sigma.to(dtype), frame=frame, src_hw=src_hw)
            for rows in (None, 5):
                got = rasterise_blocks(p, K.to(dtype), (16, 16), st, block_rows=rows, compiled=True, **kw)
                want = rasterise_blocks(p, K.to(dtype), (16, 16), st, block_rows=rows, compiled=False, **kw)
                assert len(got) == len(want) and sum(c.pixel.numel() for c in got) > p.shape[1]
                for a, b in zip(got, want):
                    _same_candidates(a, b)
                    same = a.pixel[1:] == a.pixel[:-1]
                    ties += int((same & (a.iz[1:] == a.iz[:-1])).sum())
    assert ties > 100  # equal depths in a pixel keep the points' order, as the tensors' stable sort
    # two images stacked (the batched layout), and an empty cloud
    p2 = torch.cat([p64, p64.flip(1)]).float()
    kw2 = dict(valid=valid.expand(2, -1), frame=frame.expand(2, -1), src_hw=(32, 32))
    K2 = K.expand(2, 3, 3).float()
    for rows in (None, 7):
        got = rasterise_blocks(p2, K2, (16, 16), RenderSettings(), block_rows=rows, compiled=True, **kw2)
        want = rasterise_blocks(p2, K2, (16, 16), RenderSettings(), block_rows=rows, compiled=False, **kw2)
        for a, b in zip(got, want, strict=True):
            _same_candidates(a, b)
    empty = rasterise_gt(p2[:, :0], K2, (16, 16), compiled=True)
    assert empty.pixel.numel() == 0 and empty.ox.dtype == torch.float32
    # with gradients: the same candidates, and d(sum of ox, oy, iz)/d(points) reaches them
    pg = p64.float().requires_grad_(True)
    got = rasterise_gt(pg, K.float(), (16, 16), compiled=True, valid=valid)
    want = rasterise_gt(pg.detach(), K.float(), (16, 16), compiled=False, valid=valid)
    _same_candidates(got._replace(ox=got.ox.detach(), oy=got.oy.detach(), d2=got.d2.detach(), iz=got.iz.detach()), want)
    (got.ox.sum() + got.oy.sum() + got.iz.sum()).backward()
    assert pg.grad is not None and pg.grad[0, got.point].abs().sum(1).gt(0).all()


def test_a_render_with_points_added_takes_the_first_points_cells():
    """A render whose cloud begins with an earlier render's points (the coverage step's
    views added after the core's frames) finds only the new points' cells and merges
    them into the earlier ones: the candidates of rasterising the whole cloud, bit for
    bit, in float32 and float64, with new points at the same depths as earlier ones in
    a pixel (ties keep the points' order: the earlier render's first) and new sigmas for
    every point (the noise law moves with the views added)."""
    p64, nrm, valid, K, frame, sigma = _two_layer_cloud(11)
    n_first = 700
    p64 = p64.clone()
    p64[0, n_first::3, 2] = p64[0, : (p64.shape[1] - n_first + 2) // 3, 2]  # new points at earlier depths
    ties = 0
    for dtype in (torch.float32, torch.float64):
        p = p64.to(dtype)
        for radius, src_hw, rows in ((1.3, (32, 32), None), (2.0, None, 5)):
            st = RenderSettings(radius_px=radius)
            kw = dict(valid=valid, normals_cam=nrm.to(dtype), frame=frame, src_hw=src_hw)
            first = rasterise_blocks(p[:, :n_first], K.to(dtype), (16, 16), st, sigma_m=sigma[:, :n_first].to(dtype),
                                     **{**kw, "valid": valid[:, :n_first], "normals_cam": nrm[:, :n_first].to(dtype),
                                        "frame": frame[:, :n_first]})  # fmt: skip
            assert first[0].cells is not None and first[0].cells.n_points == n_first
            later = dict(kw, sigma_m=(1.5 * sigma).to(dtype), block_rows=rows)
            got = rasterise_blocks(p, K.to(dtype), (16, 16), st, prior=first[0].cells, **later)
            want = rasterise_blocks(p, K.to(dtype), (16, 16), st, **later)
            assert len(got) == len(want)
            for a, b in zip(got, want):
                _same_candidates(a, b)
                same = (a.pixel[1:] == a.pixel[:-1]) & (a.iz[1:] == a.iz[:-1])
                ties += int((same & (a.point[:-1] < n_first) & (a.point[1:] >= n_first)).sum())
            assert np.array_equal(got[0].cells.starts, want[0].cells.starts)
            assert np.array_equal(got[0].cells.point, want[0].cells.point)
    assert ties > 20  # an earlier point and a new one at one depth in a pixel, the earlier first
    with pytest.raises(ValueError, match="prior cells"):
        rasterise_blocks(p64[:, :600], K, (16, 16), RenderSettings(), prior=first[0].cells, valid=valid[:, :600])


def test_the_compiled_plane_fit_is_the_tensor_one_to_rounding():
    """The CPU's compiled plane fit of each pixel's chosen surface against the tensors'
    (the path of a GPU and of gradients): the same valid pixels and counts, depth, weight
    sum and confidence to float32 rounding; with the agreement, without a confidence,
    with ``max_sigma_m`` and without normals; other planes are refused."""
    p, nrm, valid, K, frame, sigma = _two_layer_cloud(11)
    for st, normals in (
        (RenderSettings(radius_px=1.3, min_points=2), nrm),
        (RenderSettings(radius_px=1.6, max_sigma_m=0.004), nrm),
        (RenderSettings(radius_px=1.3), None),
    ):
        kw = dict(valid=valid, normals_cam=normals, sigma_m=sigma, frame=frame, src_hw=(32, 32))
        cands = rasterise_gt(p, K, (16, 16), st, **kw)
        for target, with_sigma in ((0, True), (None, False)):
            got = composite_gt(cands, st, target_frame=target, with_sigma=with_sigma, compiled=True)
            want = composite_gt(cands, st, target_frame=target, with_sigma=with_sigma, compiled=False)
            assert torch.equal(got.depth > 0, want.depth > 0) and torch.equal(got.count, want.count)
            assert (got.depth > 0).sum() > 100
            for name in ("depth", "weight_sum", "sigma"):
                assert torch.allclose(getattr(got, name), getattr(want, name), rtol=1e-5, atol=1e-12), name
            assert torch.equal(got.agreement.nan_to_num(-1), want.agreement.nan_to_num(-1))
            assert (got.disagreement is None) == (want.disagreement is None)
            assert got.disagreement is None or torch.equal(got.disagreement, want.disagreement)
        with torch.no_grad():  # the compiled surfaces: the tensors' clusters, frames and choices
            for frames in (cands.frame, None):
                c = cands._replace(frame=frames, n_frames=cands.n_frames if frames is not None else 0)
                a = _choose_surfaces(c, st, 0 if frames is not None else None, 256, compiled=True)
                b = _choose_surfaces(c, st, 0 if frames is not None else None, 256, compiled=False)
                assert all(torch.equal(getattr(a, k), getattr(b, k)) for k in a._fields)
    with pytest.raises(ValueError, match="plane='fit'"):
        composite_gt(cands, RenderSettings(plane="none"), compiled=True)


def test_leave_one_frame_out_is_the_compositor_over_fewer_candidates():
    """The leave-target-out render (compositor over the candidates without frame 0, with
    their own sigmas) equals rendering the cloud without frame 0's points bit for bit;
    on a pixel grid (stride 3) the same at the grid's pixels (depth to float rounding)
    and empty elsewhere."""
    p, nrm, valid, K, frame, sigma = _two_layer_cloud(5)
    st = RenderSettings(m=6, radius_px=1.3, min_points=2)
    cands = rasterise_gt(p, K, (16, 16), st, valid=valid, normals_cam=nrm, sigma_m=sigma, frame=frame, src_hw=(32, 32))
    full = composite_gt(cands, st, target_frame=0)
    assert torch.equal(
        full.depth,
        render_gt(
            p, K, (16, 16), valid, st, normals_cam=nrm, sigma_m=sigma, frame=frame, src_hw=(32, 32), target_frame=0
        ).depth,
    )
    other_sigma = sigma * 1.7
    without = valid & (frame != 0)
    alone = render_gt(p, K, (16, 16), without, st, normals_cam=nrm, sigma_m=other_sigma, frame=frame, src_hw=(32, 32))
    for stride in (1, 3):
        left = composite_gt(cands.without_frame(0, stride=stride, sigma_m=other_sigma), st, with_sigma=False)
        assert not (left.sigma.any() or (left.disagreement is not None)) and torch.isnan(left.agreement).all()
        on = torch.zeros(16, 16, dtype=torch.bool)
        on[::stride, ::stride] = True
        for name in ("depth", "weight_sum", "count"):
            got, want = getattr(left, name)[0, 0], getattr(alone, name)[0, 0]
            assert not got[~on].any(), (name, stride)
            if stride == 1 or name != "depth":
                assert torch.equal(got[on], want[on]), (name, stride)
            else:  # the weights' common scale (the kept samples' median sigma) differs: float rounding
                assert torch.allclose(got[on], want[on], rtol=1e-12, atol=0)
        assert (left.depth > 0).sum() > 0.5 * on.sum()
        # the compositor's own leave-out (the CPU's compiled path skips the candidates as
        # it reads them; the tensors' copies them out): the same render
        for compiled in (None, False):
            own = composite_gt(
                cands, st, with_sigma=False, leave_out=0, stride=stride, sigma_m=other_sigma, compiled=compiled
            )
            assert torch.equal(own.count, left.count) and torch.equal(own.depth > 0, left.depth > 0)
            assert torch.allclose(own.depth, left.depth, rtol=1e-12, atol=0)
            assert torch.allclose(own.weight_sum, left.weight_sum, rtol=1e-12, atol=0)
    # its own sigmas matter: the weights move with them
    same_sigma = composite_gt(cands.without_frame(0), st, with_sigma=False)
    assert not torch.equal(same_sigma.depth, composite_gt(cands.without_frame(0, sigma_m=other_sigma**0.9), st).depth)
    with pytest.raises(ValueError, match="frame ids"):
        rasterise_gt(p, K, (16, 16), st).without_frame(0)
    with pytest.raises(ValueError, match="one sigma per point"):
        cands.without_frame(0, sigma_m=sigma[:, :10])
    for compiled in (None, False):
        with pytest.raises(ValueError, match="one sigma per point"):
            composite_gt(cands, st, leave_out=0, sigma_m=sigma[:, :10], compiled=compiled)
    with pytest.raises(ValueError, match="frame ids"):
        composite_gt(rasterise_gt(p, K, (16, 16), st), st, leave_out=0)
    empty = composite_gt(rasterise_gt(p[:, :0], K, (16, 16), st, frame=frame[:, :0]).without_frame(0), st)
    assert not empty.depth.any() and empty.agreement.shape == (1, 0)


def test_the_compositor_renders_the_wanted_pixels_only():
    """``pixels``: the wanted pixels get the full render's GT (compiled and tensors, with
    the agreement judging every pixel), the others stay empty; a wrong mask is refused."""
    p, nrm, valid, K, frame, sigma = _two_layer_cloud(7)
    st = RenderSettings(radius_px=1.3, min_points=2)
    cands = rasterise_gt(p, K, (16, 16), st, valid=valid, normals_cam=nrm, sigma_m=sigma, frame=frame, src_hw=(32, 32))
    wanted = torch.zeros(1, 16, 16, dtype=torch.bool)
    wanted[:, 3:9, 2:14] = True
    for compiled in (None, False):
        full = composite_gt(cands, st, target_frame=0, compiled=compiled)
        part = composite_gt(cands, st, target_frame=0, compiled=compiled, pixels=wanted)
        m = wanted[:, None]
        for name in ("depth", "weight_sum", "count", "sigma"):
            got, want = getattr(part, name), getattr(full, name)
            assert torch.equal(got[m], want[m]) and not got[~m].any(), (name, compiled)
        assert int((part.depth > 0).sum()) > 40
        assert torch.equal(part.agreement.nan_to_num(-1), full.agreement.nan_to_num(-1))
    with pytest.raises(ValueError, match="pixels must be a"):
        composite_gt(cands, st, pixels=wanted[0])


def test_front_to_back_sorts_by_decreasing_inverse_depth_exactly():
    """The bit-pattern sort equals a stable float sort, ties in index order, in each float type."""
    from depthgt.rasterise import front_to_back

    g = torch.Generator().manual_seed(3)
    for dtype in (torch.float32, torch.float64):
        iz = torch.rand(5000, generator=g, dtype=torch.float64).to(dtype) * 5 + 1e-4
        iz[::7] = iz[3]  # ties
        iz[1::11] = torch.nextafter(iz[3], torch.tensor(10.0, dtype=dtype))  # one ulp apart
        expected = torch.sort(-iz, stable=True).indices
        assert torch.equal(front_to_back(iz), expected)


def test_the_compiled_radix_sort_puts_the_visible_points_front_to_back():
    """The rasteriser's compiled byte radix sort of the visible points equals the stable
    float sort of them, ties (equal and one ulp apart) in index order, in float32 and
    float64, with invisible points left out; a set where every key shares its top bytes
    (the skipped passes), one point and none."""
    import numpy as np

    from depthgt.gt.render.rasteriser import _visible_front_to_back

    g = torch.Generator().manual_seed(5)
    for dtype, bits in ((torch.float32, np.uint32), (torch.float64, np.uint64)):
        for spread in (5.0, 1e-3):  # 1e-3: the keys share their top bytes
            iz = torch.rand(6000, generator=g, dtype=torch.float64).to(dtype) * spread + 0.5
            iz[::7] = iz[3]
            iz[1::11] = torch.nextafter(iz[3], torch.tensor(10.0, dtype=dtype))
            ok = torch.rand(6000, generator=g) > 0.3
            for n in (6000, 1, 0):
                pid = ok[:n].nonzero().squeeze(1)
                want = pid.index_select(0, torch.sort(-iz[:n][pid], stable=True).indices)
                got = _visible_front_to_back(ok[:n].numpy(), iz[:n].numpy().view(bits), np.iinfo(bits).max)
                assert np.array_equal(got, want.numpy()), (dtype, spread, n)


def test_the_gap_bound_never_passes_a_step_the_tolerance_fails():
    """``within_gap_bound`` (the surfaces' and the frame agreement's shortcut past the
    square roots) says "within" only where the full float32 tolerance agrees, in both
    forms (a new surface: step > tol; agreement: |step| <= tol), on steps at, below and
    above the bound, equal, zero, NaN and infinite stds, and inverse depths <= 0, NaN or
    infinite; and it decides a good share of the steps inside the tolerance."""
    import numba

    from depthgt.gt.render.pixelwise import hypot, within_gap_bound

    @numba.njit
    def both(step, sa, sb, iz, dx, dy, gs, gsr):
        within = within_gap_bound(step, sa, sb, iz, gs, gsr)
        tol = gs * hypot(sa, sb) + gsr * iz * hypot(dx, dy)
        return within, step > tol, abs(step) <= tol

    rng = np.random.default_rng(3)
    n = 4000
    f32 = np.float32
    sa = (10.0 ** rng.uniform(-6, 0, n)).astype(f32)
    sb = np.where(rng.random(n) < 0.3, sa, 10.0 ** rng.uniform(-6, 0, n)).astype(f32)
    sb[::17], sa[::23], sb[::29], sa[::31] = 0, np.nan, np.inf, -sa[::31]
    bound = f32(4.0) * ((np.abs(sa) + np.abs(sb)) * f32(0.5))
    with np.errstate(invalid="ignore"):  # inf x 0: a NaN step, wanted among the cases
        step = (bound * rng.choice([0.0, 0.5, 1.0, 1.0, 1.2, 1.5], n) * rng.choice([-1.0, 1.0], n)).astype(f32)
    iz = rng.uniform(0.1, 2.0, n).astype(f32)
    iz[::13], iz[::19], iz[::37] = -0.5, np.inf, np.nan
    d = rng.uniform(-1, 1, (n, 2)).astype(f32)
    decided = inside = 0
    for gs, gsr in ((4.0, 0.02), (4.0, 0.0), (0.0, 0.02), (4.0, -0.02)):
        for i in range(n):
            within, beyond, agrees = both(step[i], sa[i], sb[i], iz[i], d[i, 0], d[i, 1], f32(gs), f32(gsr))
            assert not within or (not beyond and agrees), (i, gs, gsr, step[i], sa[i], sb[i], iz[i])
            decided += within
            inside += agrees
    assert decided > 0.4 * inside, (decided, inside)


def test_cells_inside_unravels_as_nonzero():
    """The float64 unravelling of the flat nonzero gives nonzero's (slot, row, column) for
    every window size, including the last cells of many points."""
    from depthgt.rasterise import _cells_inside

    g = torch.Generator().manual_seed(5)
    for span in (1, 2, 3, 4, 5, 7):
        inside = torch.rand(20000, span, span, generator=g) < 0.4
        inside[-1] = True
        got = torch.stack(_cells_inside(inside), 1)
        assert torch.equal(got, inside.nonzero())


def test_candidates_are_every_point_pixel_pair_within_the_radius():
    """The soft splat's rasteriser against a plain enumeration: every valid point in front
    of the camera paired with each pixel centre strictly within the radius (two images:
    the pixel index counts the first image's pixels), point by point in their order."""
    from depthgt.rasterise import candidates

    g = torch.Generator().manual_seed(4)
    pts = torch.rand(2, 800, 3, generator=g, dtype=torch.float64) * torch.tensor(
        [2.0, 2.0, 3.0], dtype=torch.float64
    ) - torch.tensor([1.0, 1.0, -0.05], dtype=torch.float64)
    K = _K(2, 20.0, 15.5, 11.5)
    valid = torch.rand(2, 800, generator=g) > 0.1
    h, w, r = 24, 32, 1.25
    made, z = candidates(pts, K, valid, (h, w), radius_px=r, min_depth=0.1)
    expected = []
    for b in range(2):
        for i in range(800):
            x, y, d = (float(c) for c in pts[b, i])
            if not valid[b, i] or d <= 0.1:
                continue
            u, v = 20.0 * x / d + 15.5, 20.0 * y / d + 11.5
            for py in range(h):
                for px in range(w):
                    d2 = (px - u) ** 2 + (py - v) ** 2
                    if d2 < r * r:
                        expected.append((b * 800 + i, (b * h + py) * w + px, d2))
    got = list(zip(made.point.tolist(), made.pixel.tolist(), made.d2.tolist()))
    assert len(got) == len(expected) > 1000
    assert [(p, q) for p, q, _ in got] == [(p, q) for p, q, _ in sorted(expected, key=lambda e: e[0])]
    np.testing.assert_allclose([d for *_, d in got], [d for *_, d in sorted(expected, key=lambda e: e[0])], atol=1e-9)
    assert torch.equal(z, pts[..., 2].reshape(-1))


def test_resampled_positions_match_nearest_resize():
    """The sample positions are the source pixel centres that resize_depth_nearest takes."""
    src = torch.arange(480 * 640, dtype=torch.float32).reshape(1, 1, 480, 640)
    idx = resize_depth_nearest(src, (256, 256))[0, 0].long()
    row, col = idx // 640, idx % 640
    gu, gv = resampled_positions(640, 256, dtype=torch.float64), resampled_positions(480, 256, dtype=torch.float64)
    np.testing.assert_allclose(gu.numpy(), ((col[0].double() + 0.5) * 256 / 640 - 0.5).numpy())
    np.testing.assert_allclose(gv.numpy(), ((row[:, 0].double() + 0.5) * 256 / 480 - 0.5).numpy())
    assert (gu - torch.arange(256)).abs().max() < 0.5


def test_noise_estimate_follows_the_sensor():
    """sigma at 1 m from noisy depth alone: noise of known std in inverse depth on a slanted
    plane is recovered; clean depth gives ~0."""
    g = torch.Generator().manual_seed(0)
    v, u = torch.meshgrid(
        torch.arange(96.0, dtype=torch.float64), torch.arange(128.0, dtype=torch.float64), indexing="ij"
    )
    iz = 0.5 + 0.004 * u - 0.002 * v  # a plane, in inverse depth (1/m)
    for sigma in (0.001, 0.003):
        noisy = 1.0 / (iz + sigma * torch.randn(iz.shape, generator=g, dtype=torch.float64))
        est = estimate_noise_sigma_1m(noisy[None, None].repeat(3, 1, 1, 1))
        assert est == pytest.approx(sigma, rel=0.1)
    assert estimate_noise_sigma_1m((1.0 / iz)[None, None]) < 1e-6


def test_the_noise_law_of_any_frames_is_their_own_estimate():
    """``noise_sigma_1m_of`` (the k-th of the frames' sorted residuals, a compiled
    bisection on their bits) is exactly ``noise_sigma_1m_from`` of the same frames: every
    subset of four noisy frames (one with a hole, one quantised so that residuals tie),
    and the fallback below ``min_pixels``."""
    from itertools import combinations

    from depthgt.noise_law import (
        KINECT_SIGMA_1M,
        noise_sigma_1m_from,
        noise_sigma_1m_of,
        second_difference_residuals,
        sorted_residuals,
    )

    g = torch.Generator().manual_seed(3)
    v, u = torch.meshgrid(torch.arange(48.0), torch.arange(64.0), indexing="ij")
    iz = 0.5 + 0.004 * u - 0.002 * v
    depth = torch.stack([1.0 / (iz + s * torch.randn(iz.shape, generator=g)) for s in (0.001, 0.002, 0.003, 0.004)])
    depth[1, 10:30, 5:40] = 0  # a hole
    depth[2] = torch.round(depth[2] * 200) / 200  # quantised: equal residuals
    res = second_difference_residuals(depth[:, None])
    per_frame = sorted_residuals(res)
    for n in range(1, 5):
        for frames in combinations(range(4), n):
            want = noise_sigma_1m_from(second_difference_residuals(depth[list(frames), None]))
            assert noise_sigma_1m_of([per_frame[f] for f in frames]) == want, frames
    assert noise_sigma_1m_of(per_frame[:1], min_pixels=10**6) == KINECT_SIGMA_1M
    assert noise_sigma_1m_of([]) == KINECT_SIGMA_1M


# ------------------------------------------------------------------ surfaces at grazing angles, far range, thin


def _plane_frames(K, n_plane, d, poses, hw, noise_1m, seed):
    """Depth of the plane n.X = d (world = target camera) seen from ``poses`` (T_j_to_t),
    with Gaussian noise of std noise_1m * z^2 quantised like a disparity sensor."""
    g = torch.Generator().manual_seed(seed)
    h, w = hw
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    rays = torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], -1)
    out = []
    for T in poses:
        n_j = T[:3, :3].T @ n_plane  # the plane in frame j: n_j . X_j = d - n . t
        d_j = d - n_plane @ T[:3, 3]
        z = d_j / (rays @ n_j)
        iz = 1 / z + noise_1m * torch.randn(z.shape, generator=g, dtype=torch.float64)
        out.append(torch.where((z > 0) & (z < 20), 1 / iz, torch.zeros_like(z)))
    return torch.stack(out)[:, None].float()


@pytest.mark.parametrize("incidence_deg,distance_m", [(80.0, 3.0), (72.0, 6.0)])
def test_slanted_far_plane_stays_one_surface(incidence_deg, distance_m):
    """A floor seen at a grazing angle at several metres, with Kinect-like noise: a fixed
    relative depth band (the old guard: 2% + 1 cm) splits its samples into layers;
    the geometric grouping keeps it whole and accurate."""
    K = torch.tensor([[120.0, 0, 47.5], [0, 120.0, 47.5], [0, 0, 1]], dtype=torch.float64)
    a = np.radians(incidence_deg)
    n_plane = torch.tensor([0.0, -np.sin(a), -np.cos(a)], dtype=torch.float64)  # seen from above, tilted away
    d = -distance_m * np.cos(a)  # the ray through the centre meets it at distance_m
    poses = []
    for k in (-3, -2, -1, 0, 1, 2, 3):
        T = torch.eye(4, dtype=torch.float64)
        T[:3, 3] = torch.tensor([0.01 * k, 0.004 * k, 0.006 * k])
        poses.append(T)
    poses = torch.stack(poses)
    depth = _plane_frames(K, n_plane, d, poses, (96, 96), 0.0012, 0)
    exact = _plane_frames(K, n_plane, d, poses[3:4], (96, 96), 0.0, 0)[0, 0]
    cloud = cloud_in_target(depth, K.float().expand(7, 3, 3), poses.float())
    out = render_gt(
        cloud.points,
        K.float()[None],
        (96, 96),
        cloud.valid,
        RenderSettings(),
        normals_cam=cloud.normals,
        sigma_m=cloud.sigma_m,
        frame=cloud.frame,
    )
    gt = out.depth[0, 0]
    ok = exact > 0
    assert float((gt[ok] > 0).float().mean()) > 0.97
    err_gt = (gt - exact).abs()[ok & (gt > 0)].mean()
    err_in = (depth[3, 0] - exact).abs()[ok & (depth[3, 0] > 0)].mean()
    assert err_gt < 0.5 * err_in
    # the noise estimate found the sensor's law: sigma of the samples ~ 1.2e-3 z^2
    assert float(cloud.sigma_m[0, depth.flatten() > 0].max()) > 0.5 * 0.0012 * float(exact.max()) ** 2


def test_render_gt_edge_where_most_frames_put_it():
    """A real sensor fattens and jitters depth edges differently in every frame: a
    foreground plane at 1.5 m whose edge (truth: between columns 24 and 25) three of seven
    frames extend by 1-3 px, in front of a wall at 4 m. The GT's edge is where most frames
    put it (``edge_vote``), not at the farthest frame's (the union, ``edge_vote=0``)."""
    h = w = 48
    K = torch.tensor([[60.0, 0, 23.5], [0, 60.0, 23.5], [0, 0, 1]], dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    fattened_px = [0, 2, 0, 0, 3, 0, 1]
    x_edge = (24.5 - 23.5) / 60.0 * 1.5  # world x of the edge on the plane z = 1.5
    frames, poses = [], []
    for k, fat in zip(range(-3, 4), fattened_px):
        T = torch.eye(4, dtype=torch.float64)
        T[0, 3] = 0.01 * k  # camera k at x = 0.01 k: sub-pixel parallax between the frames
        x_world = (u - K[0, 2]) / K[0, 0] * 1.5 + 0.01 * k
        fg = x_world < x_edge + fat * 1.5 / 60.0
        frames.append(torch.where(fg, torch.full_like(u, 1.5), torch.full_like(u, 4.0)))
        poses.append(T)
    depth, poses = torch.stack(frames)[:, None].float(), torch.stack(poses).float()
    cloud = cloud_in_target(depth, K.float().expand(7, 3, 3), poses)

    def gt(**kw):
        return render_gt(
            cloud.points,
            K.float()[None],
            (h, w),
            cloud.valid,
            RenderSettings(**kw),
            normals_cam=cloud.normals,
            sigma_m=cloud.sigma_m,
            frame=cloud.frame,
        ).depth[0, 0]

    voted, union = gt(), gt(edge_vote=0.0)
    assert torch.allclose(voted[:, 4:25], torch.tensor(1.5), atol=1e-3)  # the foreground up to its true edge
    assert not ((voted[:, 25:30] > 0) & (voted[:, 25:30] < 2)).any()  # and not beyond it
    assert float((voted[:, 25:44] > 0).float().mean()) > 0.9  # the wall behind is there
    assert float(((union[:, 25:28] > 0) & (union[:, 25:28] < 2)).float().mean()) > 0.5  # the union fattens it


def test_thin_pole_seen_by_several_frames_is_kept():
    """A pole 2 px wide 1.5 m in front of a wall at 4 m, seen by 7 frames with small
    baselines: every pixel of the pole gets the pole's depth."""
    h = w = 48
    K = torch.tensor([[60.0, 0, 23.5], [0, 60.0, 23.5], [0, 0, 1]], dtype=torch.float64)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    frames, poses = [], []
    half = 1.0 / 60.0 * 1.5  # 1 px at 1.5 m: the pole is 2 px wide
    for k in range(-3, 4):
        T = torch.eye(4, dtype=torch.float64)
        T[0, 3] = 0.01 * k
        x_ray = (u - K[0, 2]) / K[0, 0]
        # camera j at x = 0.01 k: the pole (|x| < half at z = 1.5) is at x_j = -0.01 k
        pole = (x_ray * 1.5 + 0.01 * k).abs() < half
        frames.append(torch.where(pole, torch.full_like(u, 1.5), torch.full_like(u, 4.0)))
        poses.append(T)
    depth, poses = torch.stack(frames)[:, None].float(), torch.stack(poses).float()
    cloud = cloud_in_target(depth, K.float().expand(7, 3, 3), poses)
    gt = render_gt(
        cloud.points,
        K.float()[None],
        (h, w),
        cloud.valid,
        RenderSettings(),
        normals_cam=cloud.normals,
        sigma_m=cloud.sigma_m,
        frame=cloud.frame,
    ).depth[0, 0]
    target_pole = depth[3, 0] < 2
    assert int(target_pole.sum()) == 2 * h
    assert torch.allclose(gt[target_pole], torch.tensor(1.5), atol=1e-3)
    assert float(((gt[~target_pole] - 4.0).abs() > 1e-3).float().mean()) < 0.03


# ------------------------------------------------------------------ acceptance on an analytic scene


def _rot(yaw: float, pitch: float) -> np.ndarray:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    return np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]]) @ np.array([[1, 0, 0], [0, cp, -sp], [0, sp, cp]])


def _analytic_depth(T_world_cam: np.ndarray, K: np.ndarray, hw: tuple[int, int]) -> np.ndarray:
    """Exact z-depth (H, W) of a room corner: a wall tilted by 25 degrees at ~3 m, a floor
    (slanted in view), a side wall, and a box yawed by 30 degrees in front (OpenCV axes)."""
    h, w = hw
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d_cam = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)  # z = 1: t is depth
    d = d_cam @ T_world_cam[:3, :3].T
    c = T_world_cam[:3, 3]
    t = np.full((h, w), np.inf)
    a = np.deg2rad(25)
    with np.errstate(divide="ignore", invalid="ignore"):
        for n, off in [((np.sin(a), 0, -np.cos(a)), -3.0), ((0, -1, 0), -0.9), ((1, 0, 0), -1.6)]:
            n = np.asarray(n, np.float64)
            tp = (off - n @ c) / (d @ n)
            t = np.where((tp > 0.05) & (tp < t), tp, t)
        Rb = _rot(np.deg2rad(30), 0.0)
        cb, db = (c - np.array([-0.15, 0.05, 1.9])) @ Rb, d @ Rb
        t1, t2 = (np.array([-0.3, -0.3, -0.2]) - cb) / db, (np.array([0.3, 0.3, 0.2]) - cb) / db
    tn, tf = np.minimum(t1, t2).max(-1), np.maximum(t1, t2).min(-1)
    t = np.where((tn <= tf) & (tn > 0.05) & (tn < t), tn, t)
    return np.where(np.isfinite(t), t, 0).astype(np.float32)


@pytest.fixture(scope="module")
def analytic_frameset():
    """7 frames (target index 3) at 640x480 with exact poses, their 256x256 versions and
    the exact depth at the 256x256 pixel centres of the target."""
    K = np.array([[525.0, 0, 319.5], [0, 525.0, 239.5], [0, 0, 1]])
    Ts = []
    for k in range(-3, 4):  # neighbours t -+ 2, 4, 6 of a slow hand-held motion
        T = np.eye(4)
        T[:3, :3] = _rot(np.deg2rad(0.6 * k), np.deg2rad(0.3 * k))
        T[:3, 3] = [0.012 * k, 0.004 * k, -0.006 * k]
        Ts.append(T)
    Ts = np.stack(Ts)
    depth = torch.from_numpy(np.stack([_analytic_depth(T, K, (480, 640)) for T in Ts]))[:, None]
    K256 = scale_intrinsics(torch.tensor(K), (480, 640), (256, 256))
    exact = torch.from_numpy(_analytic_depth(Ts[3], K256.numpy(), (256, 256)))
    T_j_to_t = torch.from_numpy(np.linalg.inv(Ts[3])[None] @ Ts)
    return resize_depth_nearest(depth, (256, 256)), K256.float(), T_j_to_t.float(), exact


def _render_frames(clean256, K256, T_j_to_t, frames, src_hw=(480, 640), noise=0.0, settings=RenderSettings()):
    d = clean256[frames]
    if noise:
        g = torch.Generator().manual_seed(0)
        d = d * (1 + noise * d * torch.randn(d.shape, generator=g))  # sigma = noise * z^2 (Kinect-like)
    cloud = cloud_in_target(d, K256.expand(len(frames), 3, 3), T_j_to_t[frames], src_hw=src_hw)
    return render_gt(
        cloud.points,
        K256[None],
        (256, 256),
        cloud.valid,
        settings,
        normals_cam=cloud.normals,
        sigma_m=cloud.sigma_m,
        frame=cloud.frame,
        src_hw=src_hw,
    ).depth[0, 0]


def _mae_mm(a: torch.Tensor, b: torch.Tensor) -> float:
    m = (a > 0) & (b > 0)
    return float((a - b).abs()[m].mean()) * 1000


def test_render_gt_reproduces_clean_target(analytic_frameset):
    """Acceptance: the 6 neighbours (t -+ 2, 4, 6) with exact poses reproduce the clean target."""
    clean, K, T, exact = analytic_frameset
    neighbours = [0, 1, 2, 4, 5, 6]
    gt = _render_frames(clean, K, T, neighbours)
    assert float((gt > 0).float().mean()) > 0.985
    # the GT estimates the depth at the input's sample positions: the nearest-resized
    # clean target is the exact depth there
    assert _mae_mm(gt, clean[3, 0]) <= 1.0
    # without src_hw the sample positions are the 256x256 pixel centres
    centre = _render_frames(clean, K, T, neighbours, src_hw=None)
    assert _mae_mm(centre, exact) <= 1.5
    assert _mae_mm(clean[3, 0], exact) > 1.0  # (the two sample grids differ: for comparison)
    # naive splat: every point within R averaged, no surface choice, no plane fit
    naive = RenderSettings(gap_sigmas=1e9, gap_slope_rel=0.0, plane="none", drop_ambiguous=False, min_frames=1)
    assert _mae_mm(_render_frames(clean, K, T, neighbours, settings=naive), clean[3, 0]) > 3 * _mae_mm(gt, clean[3, 0])


def test_render_gt_with_target_and_noise(analytic_frameset):
    clean, K, T, exact = analytic_frameset
    assert _mae_mm(_render_frames(clean, K, T, list(range(7))), clean[3, 0]) <= 1.0
    # Kinect-like noise (sigma 6 mm at 2 m): the GT stays well below the input's noise
    noisy_in = clean[3, 0] * (
        1 + 0.0015 * clean[3, 0] * torch.randn(clean[3, 0].shape, generator=torch.Generator().manual_seed(1))
    )
    gt = _render_frames(clean, K, T, list(range(7)), noise=0.0015)
    assert _mae_mm(gt, clean[3, 0]) < 0.5 * _mae_mm(noisy_in, clean[3, 0])


# ------------------------------------------------------------------ acceptance on the synthetic source


def test_render_gt_on_synthetic_room():
    """The 6 neighbours' clean depth of a synthetic room frame set, exact poses, 256x256."""
    from depthgt.sources.base import open_scene

    scene = open_scene("synthetic", None, "room_000", n_frames=20)
    ids = [2, 4, 6, 8, 10, 12, 14]  # target 8, neighbours -+ 2, 4, 6
    frames = [scene.read(i) for i in ids]
    hw = scene.image_size
    K = scale_intrinsics(torch.tensor(scene.intrinsics), hw, (256, 256)).float()
    clean = resize_depth_nearest(torch.from_numpy(np.stack([f.clean_depth_m for f in frames]))[:, None], (256, 256))
    Ts = np.stack([f.T_world_cam for f in frames])
    T = torch.from_numpy(np.linalg.inv(Ts[3])[None] @ Ts).float()
    nb = [0, 1, 2, 4, 5, 6]
    cloud = cloud_in_target(clean[nb], K.expand(6, 3, 3), T[nb], src_hw=hw)

    def render(st):
        return render_gt(
            cloud.points,
            K[None],
            (256, 256),
            cloud.valid,
            st,
            normals_cam=cloud.normals,
            sigma_m=cloud.sigma_m,
            frame=cloud.frame,
            src_hw=hw,
        ).depth[0, 0]

    gt = render(RenderSettings())
    assert float((gt > 0).float().mean()) > 0.97  # edge pixels of undecidable side are left empty
    assert _mae_mm(gt, clean[3, 0]) <= 1.0  # against the truth at the sample positions
    # keeping the ambiguous edge pixels fills them in at a clear cost in accuracy
    full = render(RenderSettings(drop_ambiguous=False))
    assert float((full > 0).float().mean()) > float((gt > 0).float().mean())
    assert _mae_mm(full, clean[3, 0]) > 1.5 * _mae_mm(gt, clean[3, 0])


def _plane_seen_with_offsets(offsets_m, region_off, h=24, w=24, seed=7):
    """A slanted plane seen by a target (frame 0, a sample at every pixel centre) and
    neighbours with random sample positions; neighbour j's depth is off by
    ``offsets_m[j-1]`` where ``region_off(u, v)`` holds (everywhere when it is None)."""
    g = torch.Generator().manual_seed(seed)
    K = _K(1, 24.0, (w - 1) / 2, (h - 1) / 2)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    plane = lambda uv: 2.0 + 0.01 * uv[:, 0] + 0.02 * uv[:, 1]  # noqa: E731
    uv_t = torch.stack([u.flatten(), v.flatten()], 1)
    pts, frames = [_unproject(uv_t, plane(uv_t), K[0])], [torch.zeros(h * w, dtype=torch.long)]
    for j, off in enumerate(offsets_m, 1):
        uv = torch.rand(2 * h * w, 2, generator=g, dtype=torch.float64) * torch.tensor(
            [w - 1.0, h - 1.0], dtype=torch.float64
        )
        where = (
            torch.ones(len(uv), dtype=torch.bool) if region_off is None or j != 3 else region_off(uv[:, 0], uv[:, 1])
        )
        z = plane(uv) + off * where + 0.002 * torch.randn(len(uv), generator=g, dtype=torch.float64)
        pts.append(_unproject(uv, z, K[0]))
        frames.append(torch.full((len(uv),), j))
    return torch.cat(pts)[None], torch.cat(frames)[None], K, plane(uv_t).reshape(h, w)


def test_render_gt_keeps_a_frame_where_it_agrees():
    """Frame 3 is right on the left two thirds of the image and 15 cm off on the right (a
    moving object, distortion at the border); frame 4 is 15 cm off everywhere (at 2-2.7 m
    the tolerance is about 5 cm). Judged per
    tile, frame 3 contributes where it agrees and nowhere else, frame 4 stays out whole;
    judged per frame, frame 3 is lost whole. Vectorised renderer vs the loop oracle."""
    p, frame, K, truth = _plane_seen_with_offsets([0.0, 0.0, 0.15, 0.15], lambda u, v: u >= 16)
    h, w = truth.shape
    tiles = RenderSettings(noise_sigma_1m=0.0012, agreement_tile_px=8, min_whole_frame_agreement=0.5)
    whole = replace(tiles, agreement_tile_px=0)
    out = render_gt(p, K, (h, w), settings=tiles, frame=frame, target_frame=0)
    rd, rw, rc, rs, ra = render_gt_reference(
        p[0].numpy(), K[0].numpy(), (h, w), None, tiles, frame=frame[0].numpy(), target_frame=0
    )
    np.testing.assert_allclose(out.agreement[0].numpy(), ra, atol=1e-6)
    np.testing.assert_array_equal(out.count[0, 0].numpy(), rc)
    np.testing.assert_allclose(out.depth[0, 0].numpy(), rd, atol=1e-5)
    assert 0.5 < ra[3] < 0.9 and ra[4] < 0.1
    err = (out.depth[0, 0] - truth).abs()
    assert float(err.max()) < 0.01  # neither the off region of frame 3 nor frame 4 reached the GT
    per_frame = render_gt(p, K, (h, w), settings=whole, frame=frame, target_frame=0)
    assert int(out.count.sum()) > int(per_frame.count.sum())  # frame 3's good part is kept
    kept = out.disagreement[0, 2].sum() / out.disagreement[0, 0].sum()
    kept_whole = per_frame.disagreement[0, 2].sum() / per_frame.disagreement[0, 0].sum()
    assert kept > kept_whole
    # the check is still a check: with tiles but no whole-frame floor frame 4 stays out too
    floorless = render_gt(
        p, K, (h, w), settings=replace(tiles, min_whole_frame_agreement=0.0), frame=frame, target_frame=0
    )
    assert float((floorless.depth[0, 0] - truth).abs().max()) < 0.01


def test_the_compiled_frame_agreement_counts_as_the_tensors():
    """The CPU's compiled scans and counts of the frame agreement against the tensor path
    (a GPU's) on a scene where a frame is off in a region and another everywhere: the
    same bad (frame, tile) slots, shares and diagnostic counts, per tile and per frame,
    in one block and in blocks of 8 rows."""
    p, frame, K, truth = _plane_seen_with_offsets([0.0, 0.0, 0.15, 0.15], lambda u, v: u >= 16)
    h, w = truth.shape
    tiles = RenderSettings(noise_sigma_1m=0.0012, agreement_tile_px=8, min_whole_frame_agreement=0.5)
    for st in (tiles, replace(tiles, agreement_tile_px=0)):
        for rows in (None, 8):
            blocks = rasterise_blocks(p, K, (h, w), st, frame=frame, block_rows=rows)
            bad, share, diag = frame_agreement(blocks, st, 0, compiled=True)
            want = frame_agreement(blocks, st, 0, compiled=False)
            assert torch.equal(bad, want[0]) and bool(bad.any())
            assert torch.equal(share.nan_to_num(-1), want[1].nan_to_num(-1))
            assert torch.equal(diag, want[2]) and float(diag[:, 2].sum()) < float(diag[:, 0].sum())


def test_render_gt_agreement_ignores_target_edges():
    """Next to a depth step of the target, neighbours' samples of the other side are not
    compared (a real sensor's edges move between frames); away from it they are."""
    h = w = 24
    K = _K(1, 24.0, 11.5, 11.5)
    v, u = torch.meshgrid(torch.arange(h, dtype=torch.float64), torch.arange(w, dtype=torch.float64), indexing="ij")
    step = lambda uv: torch.where(uv[:, 0] < 12, 1.5, 2.5)  # noqa: E731
    uv_t = torch.stack([u.flatten(), v.flatten()], 1)
    g = torch.Generator().manual_seed(3)
    pts, frames = [_unproject(uv_t, step(uv_t), K[0])], [torch.zeros(h * w, dtype=torch.long)]
    for j in (1, 2):
        uv = torch.rand(2 * h * w, 2, generator=g, dtype=torch.float64) * (w - 1)
        pts.append(_unproject(uv, step(uv - torch.tensor([1.5, 0.0], dtype=torch.float64)), K[0]))  # edge 1.5 px off
        frames.append(torch.full((len(uv),), j))
    p, frame = torch.cat(pts)[None], torch.cat(frames)[None]
    for e in (0, 2):
        st = RenderSettings(noise_sigma_1m=0.0012, agreement_edge_px=e)
        out = render_gt(p, K, (h, w), settings=st, frame=frame, target_frame=0)
        _, _, rc, _, ra = render_gt_reference(
            p[0].numpy(), K[0].numpy(), (h, w), None, st, frame=frame[0].numpy(), target_frame=0
        )
        np.testing.assert_allclose(out.agreement[0].numpy(), ra, atol=1e-6)
        np.testing.assert_array_equal(out.count[0, 0].numpy(), rc)
        if e == 0:
            assert (ra[1:] < 0.95).all()  # the shifted edge outvotes the flat parts
        else:
            assert (ra[1:] > 0.99).all()
