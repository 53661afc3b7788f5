"""Issue 2 acceptance on the default synthetic scenes with the source's (exact) poses:
the GT beats the raw Kinect-style input against the clean truth, in completeness and in
accuracy where the input has data; the GT's confidence (sigma) tracks its actual error."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pandas as pd
import pytest
import torch

from depthgt.eval.metrics import depth_errors
from depthgt.gt.render import fuse
from depthgt.jobs.common import open_source_scene
from depthgt.registration import load_frameset, poses_from_source
from depthgt.settings import FrameSetSettings, RenderSettings


@pytest.fixture(scope="module")
def framesets():
    out = []
    offsets = FrameSetSettings().offsets
    for room, n in (("room_000", 48), ("room_100", 32)):  # a default training room, the former test room
        scene = open_source_scene({"kind": "synthetic", "options": {"n_frames": n, "seed": 0}}, room)
        for t in (9, 20):
            data = load_frameset(scene, [t + o for o in offsets], (256, 256), True, torch.device("cpu"))
            out.append((data, poses_from_source(data)))
    return out


@pytest.fixture(scope="module")
def rendered(framesets):
    """The default GT of every frame set (GTRender), rendered once for the module."""
    return [fuse(data, T, RenderSettings()).gt for data, T in framesets]


def test_gt_beats_input_against_truth(framesets, rendered):
    ratios_counted, ratios_valid, completeness = [], [], []
    for (data, _T), out in zip(framesets, rendered):
        gt = out.depth[0, 0].numpy()
        inp = data.depth_m[0, 0].numpy()
        truth = data.truth_m[0, 0].numpy()
        g, i = depth_errors(gt, truth), depth_errors(inp, truth)
        g_at_input = depth_errors(gt, truth, mask=inp > 0)
        ratios_counted.append(g["mae_missing_counted_m"] / i["mae_missing_counted_m"])
        ratios_valid.append(g_at_input["mae_m"] / i["mae_m"])
        completeness.append(g["completeness"])
    assert np.mean(completeness) >= 0.97
    assert np.mean(ratios_counted) <= 0.40
    assert np.mean(ratios_valid) <= 0.80


def test_leave_target_out_uses_neighbours_only(framesets, rendered):
    data, T = framesets[0]
    full = rendered[0].depth[0, 0].numpy()
    lto = fuse(data, T, RenderSettings(), members=slice(1, None)).gt.depth[0, 0].numpy()
    truth = data.truth_m[0, 0].numpy()
    s = depth_errors(lto, truth)
    assert s["completeness"] > 0.9 and s["mae_m"] < 0.01
    # removing the target changes the result (the target contributes to the full GT)
    assert not np.array_equal(full, lto)


@pytest.mark.parametrize("members", [slice(None), [0, 1, 2, 4, 6]])
def test_leave_target_out_beside_the_gt_is_the_same_render(framesets, members):
    """fuse(leave_target_out=True) renders the neighbours alone from the GT's candidates:
    the same depth, weights and counts as fusing them on their own (noise law
    estimated without the target), no sigma (the check needs the depth only) unless
    max_sigma_m asks for it, and the GT itself unchanged."""
    data, T = framesets[1]
    st = RenderSettings(leave_target_out_stride=1)
    both = fuse(data, T, st, members=members, leave_target_out=True)
    alone = fuse(data, T, st, members=slice(1, None) if isinstance(members, slice) else members[1:]).gt
    gt = fuse(data, T, st, members=members)
    assert both.left_out is not None and gt.left_out is None
    for a, b in ((both.gt, gt.gt), (both.left_out, alone)):
        for name in ("depth", "weight_sum", "count", "sigma")[: 4 if a is both.gt else 3]:
            assert torch.equal(getattr(a, name), getattr(b, name)), name
    assert not both.left_out.sigma.any()
    capped = replace(st, max_sigma_m=0.004)  # sigma decides which pixels stay: estimated, and the same
    c_both, c_alone = (
        fuse(data, T, capped, members=m, leave_target_out=lto)
        for m, lto in ((members, True), (slice(1, None) if isinstance(members, slice) else members[1:], False))
    )
    for name in ("depth", "sigma"):
        assert torch.equal(getattr(c_both.left_out, name), getattr(c_alone.gt, name)), name
    assert c_both.left_out.sigma.any() and (c_both.left_out.depth > 0).sum() < (both.left_out.depth > 0).sum()
    assert (both.left_out.depth > 0).float().mean() > 0.8
    # without neighbours there is nothing to leave the target out of
    assert fuse(data, T, st, members=[0], leave_target_out=True).left_out is None
    # every 2nd pixel of every 2nd row (the default): exactly those of the full render
    sparse = fuse(data, T, RenderSettings(), members=members, leave_target_out=True).left_out
    # (the weights' common scale, the median sigma of the kept samples, differs: rounding only)
    a, b = sparse.depth[..., ::2, ::2], alone.depth[..., ::2, ::2]
    assert torch.equal(a > 0, b > 0) and torch.allclose(a, b, rtol=1e-6, atol=0)
    assert not sparse.depth[..., 1::2, :].any() and not sparse.depth[..., :, 1::2].any()


def test_confidence_tracks_actual_error(framesets, rendered):
    """sigma (gt.exr channel S) against the known truth: larger where the GT is worse,
    about calibrated, and leaving out the least certain pixels cuts the error."""
    errs, sigmas = [], []
    for (data, _T), out in zip(framesets, rendered):
        gt, sigma = out.depth[0, 0].numpy(), out.sigma[0, 0].numpy()
        truth = data.truth_m[0, 0].numpy()
        m = (gt > 0) & (truth > 0)
        assert (sigma[gt > 0] > 0).all() and (sigma[out.count[0, 0].numpy() == 0] == 0).all()
        errs.append(np.abs(gt - truth)[m])
        sigmas.append(sigma[m])
    e, s = np.concatenate(errs), np.concatenate(sigmas)
    # Spearman's rank correlation: Pearson's of the (average) ranks; pandas' own
    # method="spearman" needs scipy, which the package does not depend on
    assert pd.Series(s).rank().corr(pd.Series(e).rank()) > 0.4
    assert 0.5 < (e <= s).mean() < 0.9 and (e <= 3 * s).mean() > 0.9
    confident = s <= np.quantile(s, 0.8)
    assert e[confident].mean() < 0.5 * e.mean()
    # the render option leaves those pixels out of the GT
    data, T = framesets[0]
    thr = float(np.quantile(s, 0.8))
    full = rendered[0].depth[0, 0].numpy()
    cut = fuse(data, T, RenderSettings(max_sigma_m=thr)).gt
    assert 0 < (cut.depth[0, 0].numpy() > 0).sum() < (full > 0).sum()
    assert (cut.sigma[0, 0].numpy()[cut.depth[0, 0].numpy() > 0] <= thr).all()


def test_gt_reuses_the_refinements_normals_unchanged(framesets):
    """The refinement's full-resolution normals (kornia's, of the same depth) go on to the
    renderer instead of being computed again: the GT and the leave-target-out render
    are bit for bit those of the renderer's own normals, for every member or a subset
    (the normals of all members are computed together either way)."""
    from depthgt.registration import align
    from depthgt.settings import registration_settings

    data, _ = framesets[0]
    settings = registration_settings({"method": "refine", "refine_settings": {"iters": [1, 1, 1]}})
    alignment = align(data, list(FrameSetSettings().offsets), settings, seed=0)
    assert alignment.normals is not None and alignment.normals.shape == (7, 3, 256, 256)
    for members in (slice(None), [0, 1, 2, 4, 6]):
        reused = fuse(
            data,
            alignment.T_j_to_t,
            RenderSettings(),
            members=members,
            leave_target_out=True,
            normals=alignment.normals,
        )
        own = fuse(data, alignment.T_j_to_t, RenderSettings(), members=members, leave_target_out=True)
        for name in ("depth", "weight_sum", "count", "sigma"):
            assert torch.equal(getattr(reused.gt, name), getattr(own.gt, name)), name
        assert torch.equal(reused.left_out.depth, own.left_out.depth)
        # they are what the renderer uses: zero normals (no plane correction) change the GT
        zero = fuse(
            data, alignment.T_j_to_t, RenderSettings(), members=members, normals=torch.zeros_like(alignment.normals)
        )
        assert not torch.equal(zero.gt.depth, own.gt.depth)
    # normals that do not match the depth are not used (a depth other than the raw one)
    other = fuse(data, alignment.T_j_to_t, RenderSettings(), depth_m=data.depth_m * 1.01, normals=alignment.normals)
    alone = fuse(data, alignment.T_j_to_t, RenderSettings(), depth_m=data.depth_m * 1.01)
    assert torch.equal(other.gt.depth, alone.gt.depth)
