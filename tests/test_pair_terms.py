"""The refinement's compiled residual terms (CPU) against the tensor path they replace
there (a GPU's path): the same points seen and associated, the same costs and normal
equations to float32 rounding, and the same refined poses on a real frame set."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import torch
from kornia.geometry.liegroup import Se3

from depthgt.jobs.common import open_source_scene
from depthgt.registration import load_frameset, poses_from_source
from depthgt.registration.pair_terms import kernel_maps, pair_terms
from depthgt.registration.refine import (
    Level,
    LevelSettings,
    RefineSet,
    _system,
    frame_pairs,
    refine_poses_many,
    target_residual_stats,
)
from depthgt.settings import FrameSetSettings, RefineSettings

KITCHEN = Path(__file__).resolve().parents[2] / "shared/data/7scenes-kitchen"


def _moved(T: torch.Tensor, seed: int, size: float) -> torch.Tensor:
    """T (F, 4, 4) with every frame but the target moved by a random twist of ``size``."""
    xi = (torch.rand(len(T), 6, generator=torch.Generator().manual_seed(seed), dtype=torch.float64) - 0.5) * size
    xi[0] = 0
    with torch.no_grad():  # kornia's Se3 holds its values as parameters
        return Se3.exp(xi).matrix() @ T


@pytest.fixture(scope="module")
def frameset():
    """A synthetic room's frame set (noisy depth, exact poses) at 96x128, float32 as the
    build loads it, with its poses in the target camera."""
    torch.set_num_threads(1)
    scene = open_source_scene({"kind": "synthetic", "options": {"n_frames": 13, "seed": 3}}, "room_000")
    d = load_frameset(scene, [6 + o for o in FrameSetSettings().offsets], (96, 128), True, torch.device("cpu"))
    return d, torch.cat([torch.eye(4, dtype=torch.float64)[None], poses_from_source(d)])


@pytest.mark.parametrize(
    "settings",
    [
        LevelSettings(geo_scale_m=0.01, photo_scale=0.03, photo_weight=0.3, robust="huber"),
        LevelSettings(geo_scale_m=0.005, photo_scale=0.03, photo_weight=0.0, robust="huber"),
        LevelSettings(geo_scale_m=0.01, photo_scale=0.05, photo_weight=1.0, robust="cauchy", geo_ref_depth_m=1.5),
    ],
    ids=["photometric", "geometric", "cauchy-disparity"],
)
@pytest.mark.parametrize("scale", [1, 2])
@pytest.mark.parametrize("holes", [False, True], ids=["", "holes"])
def test_the_compiled_terms_are_the_tensor_paths(frameset, settings, scale, holes):
    """At poses off by ~1 cm / 0.5 deg (points inside and beyond the gate, some off the
    image): the same points seen and associated (a point on a threshold may flip), the
    costs per point to float32 rounding, and every pair's cost sum, H and g within 1e-5
    of the tensors' (the compiled sums are float64 over float32 terms, the tensors'
    float32 products). With ``holes``, a quarter of every frame's depth missing in bands and a block
    (the compiled loops skip invalid points): nothing seen or costed there."""
    d, T = frameset
    if holes:
        depth = d.depth_m.clone()
        for f in range(depth.shape[0]):  # each frame its own bands, as a sensor's holes
            for c in range((f * 5) % 32, depth.shape[-1], 32):
                depth[f, :, :, c : c + 5] = 0
            depth[f, :, 20 + 3 * f : 50 + 3 * f, 10:60] = 0
        d = replace(d, depth_m=depth)
    level = Level(d.rgb, d.depth_m, d.K.float(), scale, 1)
    if holes:
        invalid = ~level.valid
        assert 0.2 < float(invalid.float().mean()) < 0.4
    pairs = frame_pairs(7, "all")
    T = _moved(T, seed=scale, size=0.02)
    gate = 0.05
    ref = _system(level, T, pairs, settings, gate, compiled=False)
    got = _system(level, T, pairs, settings, gate, compiled=True)
    n = got.vis.numel()
    assert got.vis.shape == ref.vis.shape and got.cost_pts.shape == ref.cost_pts.shape
    assert int(ref.vis.sum()) > n // (8 if holes else 4)
    assert int((ref.cost_pts > 0).sum()) > int(ref.inliers.sum())  # some seen beyond the gate
    flips = got.vis != ref.vis
    assert int(flips.sum()) <= max(2, n // 10_000)
    assert int((got.inliers - ref.inliers).abs().max()) <= 2
    same = ~flips & (got.cost_pts - ref.cost_pts).abs().le(1e-4 * (1 + ref.cost_pts.abs()))
    assert float(same.float().mean()) > 0.9995
    if holes:  # a source point's column in pair (a, b) is b's point: none seen where b has none
        cols = invalid[pairs[:, 1]].repeat(1, got.vis.shape[1] // invalid.shape[1])
        assert not bool(got.vis[cols].any()) and not bool(got.cost_pts[cols].any())
    # the sums, on the pairs without a point on a threshold: against the same terms in
    # float64 (the tensor path on float64 frames), the compiled float64 sums are at
    # least as close as the tensors' float32 products (which cancel to ~1e-4 in g)
    exact = _system(
        Level(d.rgb.double(), d.depth_m.double(), d.K.double(), scale, 1), T, pairs, settings, gate, compiled=False
    )
    steady = ~flips.any(1) & (got.inliers == ref.inliers) & (exact.inliers == ref.inliers)
    assert int(steady.sum()) >= len(pairs) // 2
    assert torch.allclose(got.pair_cost[steady], exact.pair_cost[steady], rtol=1e-5)
    # elsewhere a point on the gate moves its pair's cost by at most the gate's cost per term
    on_gate = (got.inliers - ref.inliers).abs() + flips.sum(1)
    gate_cost = float(ref.cost_pts.max())
    assert bool(((got.pair_cost - ref.pair_cost).abs() <= 1e-5 * ref.pair_cost + 2 * gate_cost * on_gate).all())
    for name in ("H_rel", "g_rel"):
        a, b, x = (getattr(sys_, name)[steady] for sys_ in (got, ref, exact))
        assert a.dtype == torch.float64
        scale_x = float(x.abs().max())
        assert float((a - x).abs().max()) <= max(2 * float((b - x).abs().max()), 1e-6 * scale_x), name
        assert float((a - x).abs().max()) <= 1e-4 * scale_x, name


def test_the_compiled_terms_take_the_cpu_only(frameset):
    d, _ = frameset
    level = Level(d.rgb, d.depth_m, d.K.float(), 2, 1)
    kw = dict(
        geo_scale_m=0.01, geo_ref_depth_m=0.0, gate=0.05, photo_weight=0.3, photo_scale=0.03, huber=True,
        gate_cost=0.5,
    )  # fmt: skip
    with pytest.raises(ValueError, match="CPU"):
        pair_terms(
            level.points.to("meta"), level.gray, level.valid, kernel_maps(level.geo, level.photo), level.K,
            torch.eye(4)[None].expand(1, 4, 4), torch.tensor([[0, 1]]), **kw,
        )  # fmt: skip
    with pytest.raises(ValueError, match="geo maps need 8 channels"):
        kernel_maps(level.geo[:, :7], level.photo)
    with pytest.raises(ValueError, match="differ in size"):
        kernel_maps(level.geo, level.photo[:1])


@pytest.mark.skipif(not KITCHEN.is_dir(), reason="../shared/data/7scenes-kitchen is absent")
def test_the_compiled_refinement_is_the_tensor_paths_on_a_real_frame_set():
    """A real Kinect frame set (7-Scenes, 256x256) refined from its KinectFusion poses
    moved by ~1 cm / 0.5 deg, with the build's settings and with the ``fast`` preset's:
    the compiled terms and the tensors reach the same poses within 1 um and 1 urad."""
    torch.set_num_threads(1)
    scene = open_source_scene({"kind": "sevenscenes", "root": str(KITCHEN)}, "7scenes-kitchen")
    offsets = list(FrameSetSettings().offsets)
    d = load_frameset(scene, [30 + o for o in offsets], (256, 256), True, torch.device("cpu"))
    T0 = _moved(torch.cat([torch.eye(4, dtype=torch.float64)[None], poses_from_source(d)]), seed=7, size=0.02)
    fast = replace(RefineSettings(), iters=(8, 5, 3), point_stride=(1, 2, 4), geo_ref_depth_m=1.5, photo_weight=1.0)
    for settings in (RefineSettings(), fast):
        out = [
            refine_poses_many([RefineSet(d.rgb, d.depth_m, T0, offsets)], d.K.float(), settings, compiled=c)[0]
            for c in (False, True)
        ]
        a, b = (o.T_f_to_t for o in out)
        assert float((a[:, :3, 3] - b[:, :3, 3]).abs().max()) < 1e-6
        assert float((a[:, :3, :3] - b[:, :3, :3]).abs().max()) < 1e-6
        assert float((a[1:, :3, 3] - T0[1:, :3, 3]).abs().max()) > 1e-3  # the refinement moved them


@pytest.mark.parametrize("sigma_1m", [None, 0.0015])
def test_the_compiled_residual_statistics_are_the_tensor_paths(frameset, sigma_1m):
    """The residual check's statistics (``refine.target_residual_stats``: each
    neighbour's median |point-to-plane residual| in the target and, with the sensor's
    noise, the median in sigmas) from the compiled residuals and from the tensors, at
    poses off by ~1 cm / 0.5 deg, with a block of depth missing: the same to float32
    rounding (a point exactly on the gate may flip)."""
    d, T = frameset
    depth = d.depth_m.clone()
    depth[:, :, 30:60, 20:70] = 0
    level = Level(d.rgb, depth, d.K.float(), 1, 1)
    pairs = frame_pairs(7, "target")
    pairs = pairs[pairs[:, 0] == 0]  # b's points into the target
    T = _moved(T, seed=5, size=0.02)
    ls = LevelSettings(geo_scale_m=0.005, photo_scale=0.03, photo_weight=0.0, robust="huber")
    got = target_residual_stats(level, T, pairs, ls, 0.03, 7, sigma_1m, compiled=True)
    ref = target_residual_stats(level, T, pairs, ls, 0.03, 7, sigma_1m, compiled=False)
    for a, b in zip(got, ref):
        assert a.shape == b.shape == (7,) and a.dtype == b.dtype == torch.float64
        assert torch.equal(torch.isnan(a), torch.isnan(b))
        if sigma_1m is None and a is got[1]:
            assert bool(torch.isnan(a[1:]).all())
            continue
        assert float(a[0]) == 0.0 and bool((a[1:] > 0).all())
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7), (a, b)
