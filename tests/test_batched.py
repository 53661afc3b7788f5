"""The paths that keep a GPU busy, checked on the CPU against the one-set-at-a-time paths:
frame sets rendered together (one pass of the rasteriser and the compositor), refined
together (one residual evaluation for every set), and a batch's per-frame cache; and
the compositor in blocks of rows against one block."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import count_synthetic_reads, synthetic_source

from depthgt.framecache import FrameCache
from depthgt.gt.render import fuse
from depthgt.gt.render.cloud import cached_geometry, cloud_from_geometry, frame_geometry
from depthgt.gt.render.compositor import composite_gt
from depthgt.gt.render.fusion import SetGeometry, fuse_sets
from depthgt.gt.render.rasteriser import rasterise_blocks, rasterise_gt
from depthgt.jobs.common import open_source_scene
from depthgt.registration import load_frameset, poses_from_source
from depthgt.registration.local import refine_source_poses, refine_source_poses_many
from depthgt.settings import FrameSetSettings, RenderSettings, registration_settings

SIZE = (96, 128)
TARGETS = (6, 8, 9)


@pytest.fixture(scope="module")
def framesets():
    """Three frame sets of a synthetic room (noisy depth, exact poses) rendered at 160x120
    and read at 96x128 through one frame cache, as a batch job reads them."""
    options = {"n_frames": 18, "seed": 1, "width": 160, "height": 120}
    scene = open_source_scene({"kind": "synthetic", "options": options}, "room_000")
    offsets = FrameSetSettings().offsets
    cache = FrameCache(keep=16)
    return [
        load_frameset(scene, [t + o for o in offsets], SIZE, True, torch.device("cpu"), cache=cache) for t in TARGETS
    ], list(offsets)


def _sets(datas, members_of=lambda k: tuple(range(7))):
    out = []
    for k, d in enumerate(datas):
        members = members_of(k)
        g = frame_geometry(d.depth_m, d.K[None].expand(7, 3, 3), src_hw=d.src_hw)
        T = torch.cat([torch.eye(4, dtype=torch.float64)[None], poses_from_source(d)])
        out.append(SetGeometry(g.take(list(members)), T[list(members)], members))
    return out


def test_frame_sets_rendered_together_are_the_sets_rendered_one_by_one(framesets):
    datas, _ = framesets
    # the second set fuses a subset (a neighbour left out): the batch pads it
    sets = _sets(datas, lambda k: (0, 1, 3, 4, 6) if k == 1 else tuple(range(7)))
    first = datas[0]
    kw = dict(src_hw=first.src_hw, leave_target_out=True)
    one = fuse_sets(sets, first.K, SIZE, RenderSettings(), together=False, **kw)
    together = fuse_sets(sets, first.K, SIZE, RenderSettings(), together=True, **kw)
    for a, b in zip(one, together):
        assert a.members == b.members and a.frames_left_out == b.frames_left_out
        for name in ("depth", "weight_sum", "count", "sigma"):
            x, y = getattr(a.gt, name), getattr(b.gt, name)
            assert torch.equal(x > 0, y > 0), name
            assert torch.allclose(x.double(), y.double(), rtol=1e-5, atol=1e-6), name
        assert torch.allclose(a.gt.agreement.nan_to_num(-1), b.gt.agreement.nan_to_num(-1))
        assert torch.allclose(a.left_out.depth, b.left_out.depth, rtol=1e-5, atol=1e-6)
        assert (a.gt.depth > 0).float().mean() > 0.5  # a real render, not two empty ones


def test_a_render_in_blocks_of_rows_is_the_render_in_one_block(framesets):
    datas, _ = framesets
    one = _sets(datas[:1])[0]
    d = datas[0]
    from depthgt.gt.render.cloud import cloud_from_geometry

    cloud = cloud_from_geometry(one.geometry, one.T_j_to_t)
    kw = dict(valid=cloud.valid, normals_cam=cloud.normals, sigma_m=cloud.sigma_m, frame=cloud.frame, src_hw=d.src_hw)
    cands = rasterise_gt(cloud.points, d.K[None].float(), SIZE, RenderSettings(), **kw)
    whole = composite_gt(cands, RenderSettings(), target_frame=0, block_rows=None)
    for rows in (5, 32):
        blocks = composite_gt(cands, RenderSettings(), target_frame=0, block_rows=rows)
        for name in ("depth", "weight_sum", "count", "sigma"):
            x, y = getattr(whole, name), getattr(blocks, name)
            assert torch.equal(x > 0, y > 0) and torch.allclose(x.double(), y.double(), rtol=1e-6, atol=1e-7), name


def test_frame_sets_refined_together_are_the_sets_refined_one_by_one(framesets):
    datas, offsets = framesets
    settings = registration_settings({"method": "refine", "refine_settings": {"iters": [3, 2, 2]}})
    one = [
        refine_source_poses(d.rgb, d.depth_m, d.K, offsets, poses_from_source(d), settings, cache=d.cache,
                            positions=d.positions)
        for d in datas
    ]  # fmt: skip
    together = refine_source_poses_many(datas, offsets, settings)
    for a, b in zip(one, together):
        assert torch.allclose(a.T_j_to_t, b.T_j_to_t, atol=1e-9)
        assert a.neighbour_status == b.neighbour_status
        assert a.diagnostics["refine_cost_curve"] == pytest.approx(b.diagnostics["refine_cost_curve"], rel=1e-9)
        for key in ("inlier_fraction", "condition", "residual_m", "residual_sigmas"):
            assert a.diagnostics[key] == pytest.approx(b.diagnostics[key], rel=1e-6, abs=1e-12), key


def test_the_batch_cache_gives_each_frames_geometry_once_and_the_same_render(framesets):
    datas, _ = framesets
    d = datas[0]
    calls = []
    cache = FrameCache(keep=16)
    original = cache.get

    def counting(kind, positions, compute):
        return original(kind, positions, lambda todo: calls.append(list(todo)) or compute(todo))

    cache.get = counting
    for data in datas:
        cached_geometry(cache, data.positions, data.depth_m, data.K, src_hw=data.src_hw)
    assert sorted(p for c in calls for p in c) == sorted({p for data in datas for p in data.positions})
    # the cached geometry renders the same GT as the frame set's own
    own = fuse(d, poses_from_source(d), RenderSettings())
    mine = fuse(d, poses_from_source(d), RenderSettings(), geometry=cached_geometry(cache, d.positions, d.depth_m,
                                                                                     d.K, src_hw=d.src_hw))  # fmt: skip
    assert torch.equal(own.gt.depth > 0, mine.gt.depth > 0)
    assert torch.allclose(own.gt.depth, mine.gt.depth, rtol=1e-5, atol=1e-6)


def test_the_refinements_normals_enter_the_cache_as_the_renderers_own(framesets):
    """With ``refine`` the registration has kornia's normals of the members' raw depth:
    the batch cache takes them for frames not yet in it (no second normals pass), and
    they are the normals the renderer computes itself."""
    datas, offsets = framesets
    d = datas[0]
    settings = registration_settings({"method": "refine", "refine_settings": {"iters": [1, 1, 1]}})
    res = refine_source_poses(d.rgb, d.depth_m, d.K, offsets, poses_from_source(d), settings)
    own = frame_geometry(d.depth_m, d.K[None].expand(7, 3, 3), src_hw=d.src_hw)
    assert torch.equal(res.normals.flatten(2).transpose(1, 2).nan_to_num(7.0), own.normals.nan_to_num(7.0))
    marked = res.normals + 1.0  # distinguishable: the cache must keep what it is given
    g = cached_geometry(FrameCache(keep=16), d.positions, d.depth_m, d.K, src_hw=d.src_hw, normals=marked)
    assert torch.equal(g.normals, marked.flatten(2).transpose(1, 2))
    data = type(d)(**{**d.__dict__, "cache": FrameCache(keep=16)})
    fused = fuse(data, poses_from_source(d), RenderSettings(), normals=res.normals)
    plain = fuse(d, poses_from_source(d), RenderSettings())
    assert torch.equal(fused.gt.depth, plain.gt.depth)


def _count_evaluations(monkeypatch) -> list[int]:
    """The pairs of every residual evaluation of the refinement from now on (a list filled in place)."""
    import depthgt.registration.refine as refine

    rows: list[int] = []
    original = refine._system

    def counting(level, T, pairs, s, gate, compiled=None):
        rows.append(int(pairs.shape[0]))
        return original(level, T, pairs, s, gate, compiled)

    monkeypatch.setattr(refine, "_system", counting)
    return rows


def test_refining_together_evaluates_no_more_pairs_than_one_by_one(framesets, monkeypatch):
    """After an accepted step the sets' linearisation comes from the trial's evaluation:
    together, the residual evaluations cover no more pairs than set by set."""

    datas, offsets = framesets
    settings = registration_settings({"method": "refine", "refine_settings": {"iters": [3, 2, 2]}})
    rows = _count_evaluations(monkeypatch)
    for d in datas:
        refine_source_poses(d.rgb, d.depth_m, d.K, offsets, poses_from_source(d), settings)
    one_by_one, rows[:] = sum(rows), []
    refine_source_poses_many(datas, offsets, settings)
    assert 0 < sum(rows) <= one_by_one


def test_the_build_renders_a_group_as_it_renders_each_set(framesets):
    """render_targets' group path (a GPU's) run on the CPU, with the sets' fused members,
    the refinement's normals and the frame cache as the build passes them: the same GT
    as one set at a time."""
    from depthgt.gt.build import render_targets
    from depthgt.registration import Alignment

    datas, offsets = framesets
    settings = registration_settings({"method": "refine", "refine_settings": {"iters": [1, 1, 1]}})
    alignments = []
    for k, d in enumerate(datas):
        res = refine_source_poses(d.rgb, d.depth_m, d.K, offsets, poses_from_source(d), settings)
        fused = [0, 1, 2, 4, 5, 6] if k == 1 else list(range(7))  # a neighbour left out
        alignments.append(Alignment(res.T_j_to_t, fused, normals=res.normals))
    one = render_targets(datas, alignments, RenderSettings(), together=False)
    group = render_targets(datas, alignments, RenderSettings(), together=True)
    for a, b in zip(one, group):
        assert a.members == b.members and a.frames_left_out == b.frames_left_out
        assert torch.equal(a.gt.depth > 0, b.gt.depth > 0)
        assert torch.allclose(a.gt.depth.double(), b.gt.depth.double(), rtol=1e-5, atol=1e-6)
    assert one[1].members == (0, 1, 2, 4, 5, 6)


def test_a_trial_next_to_a_rejected_one_is_not_evaluated(framesets, monkeypatch):
    """After a rejected LM trial the damping grows, but its first steps barely move the
    trial: a trial within ``SAME_TRIAL`` (a micrometre) of the set's rejected one, or
    within ``SAME_TRIAL_SHARE`` of that step, is damped further without a residual
    evaluation. The poses stay those of evaluating every trial, set by set and together,
    with fewer evaluations; each rule saves some on these sets."""
    import depthgt.registration.refine as refine

    datas, offsets = framesets
    settings = registration_settings({"method": "refine"})
    calls = _count_evaluations(monkeypatch)

    def run():
        calls.clear()
        one = [refine_source_poses(d.rgb, d.depth_m, d.K, offsets, poses_from_source(d), settings) for d in datas]
        n_one = len(calls)
        calls.clear()
        group = refine_source_poses_many(datas, offsets, settings)
        return one, n_one, group, sum(calls)

    skipping = run()
    monkeypatch.setattr(refine, "SAME_TRIAL_SHARE", 0.0)  # within a micrometre only
    absolute = run()
    monkeypatch.setattr(refine, "SAME_TRIAL", 0.0)  # every trial evaluated
    every = run()
    for a, b, c in zip(skipping[0] + skipping[2], absolute[0] + absolute[2], every[0] + every[2]):
        assert torch.equal(a.T_j_to_t, c.T_j_to_t) and torch.equal(b.T_j_to_t, c.T_j_to_t)
    assert skipping[1] < absolute[1] < every[1], (skipping[1], absolute[1], every[1])  # evaluations, set by set
    assert skipping[3] < absolute[3] < every[3], (skipping[3], absolute[3], every[3])  # pairs evaluated, together


def test_refining_no_set_together_gives_no_result():
    from depthgt.registration.refine import refine_poses_many

    assert refine_poses_many([], torch.eye(3)) == []


KITCHEN = Path(__file__).resolve().parents[2] / "shared/data/7scenes-kitchen"


@pytest.mark.skipif(not KITCHEN.is_dir(), reason="../shared/data/7scenes-kitchen is absent")
def test_the_compiled_renderer_is_the_tensor_path_on_a_real_frame_set():
    """On a real Kinect frame set (7-Scenes, 640x480 to 256x256, KinectFusion poses) the
    CPU's compiled cloud is the tensors' to a float32 rounding with the same normals
    kept, its compiled cells give the tensor path's candidates bit for bit, block by
    block, and the compiled plane fit the tensors' GT to float32 rounding (under 5 um)."""
    torch.set_num_threads(1)
    scene = open_source_scene({"kind": "sevenscenes", "root": str(KITCHEN)}, "7scenes-kitchen")
    d = load_frameset(scene, [30 + o for o in FrameSetSettings().offsets], (256, 256), True, torch.device("cpu"))
    g = frame_geometry(d.depth_m, d.K[None].expand(7, 3, 3), src_hw=d.src_hw)
    T = torch.cat([torch.eye(4, dtype=torch.float64)[None], poses_from_source(d)])
    cloud = cloud_from_geometry(g, T)
    tensor_cloud = cloud_from_geometry(g, T, compiled=False)
    for name in ("valid", "frame", "sigma_m"):
        assert torch.equal(getattr(cloud, name), getattr(tensor_cloud, name)), name
    ok = cloud.valid[0]
    assert torch.allclose(cloud.points[0, ok], tensor_cloud.points[0, ok], rtol=3e-7, atol=1e-7)
    assert torch.equal(cloud.normals.abs().sum(-1) > 0, tensor_cloud.normals.abs().sum(-1) > 0)
    assert torch.allclose(cloud.normals, tensor_cloud.normals, atol=3e-7)
    assert 0.5 < float((cloud.normals.abs().sum(-1) > 0).float().mean()) < 1.0
    kw = dict(valid=cloud.valid, normals_cam=cloud.normals, sigma_m=cloud.sigma_m, frame=cloud.frame, src_hw=d.src_hw)
    K = d.K[None].float()
    got = rasterise_blocks(cloud.points, K, (256, 256), RenderSettings(), block_rows=32, compiled=True, **kw)
    want = rasterise_blocks(cloud.points, K, (256, 256), RenderSettings(), block_rows=32, compiled=False, **kw)
    assert len(got) == len(want) == 8 and sum(c.pixel.numel() for c in got) > 1_000_000
    for a, b in zip(got, want):
        for name in ("pixel", "point", "ox", "oy", "d2", "iz", "s", "frame"):
            assert torch.equal(getattr(a, name), getattr(b, name)), name
        assert (a.first_pixel, a.pixels) == (b.first_pixel, b.pixels)
    # the compiled surfaces are the tensors' (the same clusters, frames and choices)
    from depthgt.gt.render.compositor import _choose_surfaces

    with torch.no_grad():
        for blk in got:
            a = _choose_surfaces(blk, RenderSettings(), 0, blk.pixels, compiled=True)
            b = _choose_surfaces(blk, RenderSettings(), 0, blk.pixels, compiled=False)
            for name in a._fields:
                assert torch.equal(getattr(a, name), getattr(b, name)), name
    # and the compiled plane fit gives the tensors' GT to float32 rounding
    fit = composite_gt(got, RenderSettings(), target_frame=0, compiled=True)
    tensors = composite_gt(got, RenderSettings(), target_frame=0, compiled=False)
    assert torch.equal(fit.depth > 0, tensors.depth > 0) and torch.equal(fit.count, tensors.count)
    assert torch.equal(fit.agreement.nan_to_num(-1), tensors.agreement.nan_to_num(-1))
    assert torch.equal(fit.disagreement, tensors.disagreement)  # the agreement's scans: the same
    assert (fit.depth - tensors.depth).abs().max() < 5e-6 and (fit.depth > 0).float().mean() > 0.5
    assert torch.allclose(fit.sigma, tensors.sigma, rtol=1e-4, atol=1e-9)


def test_a_gpu_group_of_targets_apart_reads_each_frame_once(tmp_path, monkeypatch):
    """A batch job on a GPU holds a group of frame sets before it builds them: its caches
    keep every frame the group's sets cover, however far apart their targets are
    (``target_step``), so each frame is read once (a GPU's group here on the CPU; with
    2 x reach + 1 + the group frames kept, the group's first frames were read again)."""
    from depthgt.gt import batch
    from depthgt.jobs.gt import run_frameset_batch, run_scene_index

    monkeypatch.setattr(batch, "resolve_device", lambda device: torch.device("cuda"))
    monkeypatch.setattr(batch, "GPU_GROUP", 4)
    source = synthetic_source("syn", ["room_000"], "train", 30, 80, 60)
    config = {
        "seed": 1,
        "device": "cpu",
        "resize": 32,
        "sources": [source],
        "frameset": {"neighbours": 1, "stride": 1, "target_step": 3, "batch_size": 32},
        "patches": {"count": 1, "size": 16, "max_missing": 1.0},
        "registration": {"method": "given"},
    }
    index = tmp_path / "index.parquet"
    run_scene_index(source, "room_000", config, str(index), str(tmp_path / "index.json"))
    reads = count_synthetic_reads(monkeypatch)
    records = run_frameset_batch(source, "room_000", 1, 28, config, str(index), str(tmp_path / "000001-000028.zip"))
    assert sum(r["status"] == "ok" for r in records) >= 2 * batch.GPU_GROUP  # two groups at least
    assert sorted(reads) == sorted(set(reads))  # each frame read once


def test_the_frame_cache_serves_threads_side_by_side():
    """A GPU's batch job finishes its frame sets in a few threads, which may read the
    batch's frame cache at once: every result is the frame's own and none of them
    fails, while the threads evict each other's frames (the computations yield the
    interpreter half way)."""
    import threading
    import time

    cache = FrameCache(keep=2)
    errors: list[BaseException] = []

    def square(todo: list[int]) -> list[int]:
        time.sleep(1e-4)  # another thread runs here
        return [p * p for p in todo]

    def work(seed: int) -> None:
        g = torch.Generator().manual_seed(seed)
        try:
            for _ in range(150):
                positions = torch.randint(0, 6, (3,), generator=g).tolist()
                assert cache.get("square", positions, square) == [p * p for p in positions]
        except BaseException as err:  # handed to the test's thread
            errors.append(err)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors[:3]


def test_the_kernel_warm_up_builds_its_frame_set(compiled_kernels):
    """The session's first early run (conftest ``compiled_kernels``, tests/warm_kernels.py)
    builds its frame set: the kernels it compiles are those a batch job runs."""
    import json

    (proc,) = compiled_kernels
    assert proc.returncode == 0, proc.stderr[-3000:]
    folder = Path(proc.args[-1]) / "frameset"
    assert json.loads((folder / "frameset.json").read_text())["status"] == "ok"
    assert (folder / "gt.exr").stat().st_size > 0
