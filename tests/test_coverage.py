"""frameset.selection: coverage -- views added where the paper's window sees nothing.

The scene: a wall at z = 2 m and a plate (x in [-0.2, 0], |y| <= 0.3, z = 1 m) in front
of it, seen by a camera sliding along x (1 cm and 0.3 deg of yaw per frame) with a
structured-light projector 20 cm to its right. The plate's projector shadow on the wall
is a strip the camera sees but cannot measure (~6 px wide); the window's neighbours
(+-6 cm) share part of it, frames further left see past the plate into all of it. Everything is ray cast, so
the strip and the wall's depth are known exactly.
"""

from __future__ import annotations

import json
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from conftest import count_synthetic_reads

from depthgt import io
from depthgt.errors import ConfigError
from depthgt.gt import store
from depthgt.gt.build import FrameSetOutputs, process_frameset
from depthgt.gt.coverage import choose_views, fill_maps, view_limits
from depthgt.gt.planning import block_splits, coverage_candidates, enumerate_framesets
from depthgt.jobs.gt import run_frameset_batch, run_scene_index
from depthgt.registration.overfit import RegistrationResult
from depthgt.settings import FrameSetSettings, SplitSettings, settings_from_config
from depthgt.sources.base import Frame

HW = (64, 64)
N_FRAMES, TARGET = 41, 20
STEP_M, YAW_DEG = 0.01, 0.3
WALL_Z, PLATE_Z, PLATE_X, PLATE_Y = 2.0, 1.0, (-0.2, 0.0), 0.3
PROJECTOR_M = 0.2  # a wide baseline: the shadow spans ~6 px at 64x64


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _on_plate(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return (x >= PLATE_X[0]) & (x <= PLATE_X[1]) & (np.abs(y) <= PLATE_Y)


class OccluderScene:
    """The wall-and-plate scene (module docstring); every frame ray cast at 64x64."""

    name, image_size, has_poses, has_clean_depth, colour_matches_depth = "occluder", HW, True, True, True
    intrinsics = np.array([[60.0, 0, 31.5], [0, 60.0, 31.5], [0, 0, 1]])

    def __len__(self) -> int:
        return N_FRAMES

    def frame_id(self, i: int) -> str:
        return f"{i:03d}"

    def pose(self, i: int) -> np.ndarray:
        T = np.eye(4)
        T[:3, :3] = _rot_y((i - TARGET) * YAW_DEG)
        T[0, 3] = (i - TARGET) * STEP_M
        return T

    def read(self, i: int) -> Frame:
        T = self.pose(i)
        v, u = np.mgrid[0 : HW[0], 0 : HW[1]].astype(np.float64)
        rays = np.stack([u, v, np.ones_like(u)], -1) @ np.linalg.inv(self.intrinsics).T @ T[:3, :3].T  # world dirs
        c = T[:3, 3]
        s_plate = (PLATE_Z - c[2]) / rays[..., 2]
        p_plate = c + s_plate[..., None] * rays
        hit_plate = _on_plate(p_plate[..., 0], p_plate[..., 1])
        s = np.where(hit_plate, s_plate, (WALL_Z - c[2]) / rays[..., 2])
        p = c + s[..., None] * rays
        clean = ((p - c) @ T[:3, :3])[..., 2].astype(np.float32)  # z in the camera
        q = c + T[:3, :3] @ np.array([PROJECTOR_M, 0.0, 0.0])  # the projector
        t_q = (PLATE_Z - q[2]) / (p[..., 2] - q[2])
        x_q = q + t_q[..., None] * (p - q)
        shadow = ~hit_plate & _on_plate(x_q[..., 0], x_q[..., 1])
        depth = np.where(shadow, 0.0, clean).astype(np.float32)
        grey = (np.floor(p[..., 0] * 20) + np.floor(p[..., 1] * 20)) % 2 * 120 + 60  # a checker on the surfaces
        rgb = np.repeat(grey[..., None], 3, axis=-1).astype(np.uint8)
        return Frame(rgb, depth, T, clean)


def _settings(selection: str, **frameset):
    return settings_from_config(
        {
            "resize": 64,
            "patches": {"size": 32},
            "frameset": {"selection": selection, "coverage_span": 30, "coverage_views": 2, **frameset},
            "registration": {"method": "given"},
        }
    )


def _build(tmp_path, name: str, settings, candidates=None) -> tuple[dict, dict, dict]:
    scene = OccluderScene()
    members = [TARGET + o for o in settings.frameset.offsets]
    out = FrameSetOutputs.in_dir(tmp_path / name)
    doc = process_frameset(scene, "synthetic", TARGET, members, "train", out, settings, candidates=candidates)
    assert json.loads(out.meta.read_text()) == json.loads(json.dumps(doc))
    return doc, io.read_exr(out.gt), json.loads(out.poses.read_text())


@pytest.fixture(scope="module")
def window(tmp_path_factory):
    return _build(tmp_path_factory.mktemp("window"), "w", _settings("window"))


def test_scene_shadow_is_what_the_window_misses(window):
    frame = OccluderScene().read(TARGET)
    strip = (frame.depth_m == 0) & (frame.clean_depth_m > 0)
    assert 60 < strip.sum() < 600  # the projector's shadow: the target cannot measure it
    doc, gt, _ = window
    assert "coverage" not in doc
    # the window's neighbours (+-6 frames, 6 cm) see only part of it
    assert (strip & (gt["Z"] == 0)).sum() >= 60


def test_coverage_fills_the_occluded_pixels_and_keeps_the_core(window, tmp_path):
    _, gt_w, poses_w = window
    doc, gt, poses = _build(tmp_path, "c", _settings("coverage", coverage_max_angle_deg=20.0))
    frame = OccluderScene().read(TARGET)
    strip = (frame.depth_m == 0) & (frame.clean_depth_m > 0)
    cov = doc["coverage"]
    added = [v for v in cov["added"] if v["status"] == "ok"]
    assert added and all(v["offset"] < -6 for v in added)  # from the left, past the plate
    # the occluded pixels are filled, with the wall's depth
    filled = strip & (gt_w["Z"] == 0) & (gt["Z"] > 0)
    assert filled.sum() >= 0.9 * (strip & (gt_w["Z"] == 0)).sum()
    assert np.abs(gt["Z"][filled] - frame.clean_depth_m[filled]).max() < 0.01
    # every pixel the core decides is the core's, bit for bit (all channels)
    core = gt_w["Z"] > 0
    for ch in ("Z", "S"):
        assert np.array_equal(gt[ch][core], gt_w[ch][core]), ch
    assert cov["filled_px"] == int(((gt["Z"] > 0) & ~core).sum()) > 0
    assert doc["statistics"]["gt_missing"] < cov["gt_missing_core"]
    assert poses["T_j_to_t"] == poses_w["T_j_to_t"]
    assert set(poses["coverage_T_j_to_t"]) == {str(v["offset"]) for v in added}
    assert all(v["planned_fill_px"] >= 50 and v["reason"] == "" for v in added)


def test_the_render_with_views_added_takes_the_cores_cells(tmp_path, monkeypatch):
    """The render of the core's members and the views added finds the views' cells only
    and takes the core render's (its points come first, with the same poses): the same
    GT, statistics and records as finding them all."""
    from depthgt.gt import coverage

    real = coverage.fuse
    priors = []

    def recording(*args, **kw):
        priors.append(kw.get("prior"))
        return real(*args, **kw)

    settings = _settings("coverage", coverage_max_angle_deg=20.0)
    monkeypatch.setattr(coverage, "fuse", recording)
    doc, gt, _ = _build(tmp_path, "taken", settings)
    assert priors and all(p is not None and p.n_points == 7 * 64 * 64 for p in priors)
    monkeypatch.setattr(coverage, "fuse", lambda *args, **kw: real(*args, **{**kw, "prior": None}))
    doc_all, gt_all, _ = _build(tmp_path, "found", settings)
    assert [v for v in doc["coverage"]["added"] if v["status"] == "ok"]
    assert doc["coverage"] == doc_all["coverage"] and doc["statistics"] == doc_all["statistics"]
    assert gt.keys() == gt_all.keys() and all(np.array_equal(gt[k], gt_all[k]) for k in gt)


def test_views_beyond_the_angle_limit_are_not_added(window, tmp_path):
    wide, _, _ = _build(tmp_path, "wide", _settings("coverage", coverage_max_angle_deg=20.0))
    # (no hole margin: within 4 deg a view sees only a sliver of the shadow, next to its own)
    narrow_settings = _settings(
        "coverage", coverage_max_angle_deg=4.0, coverage_min_fill_px=5, coverage_mixed_margin_px=0
    )
    narrow, _, _ = _build(tmp_path, "narrow", narrow_settings)
    # the limit binds: without it, the best views are turned further than 4 deg
    assert max(v["angle_deg"] for v in wide["coverage"]["added"]) > 4.0
    assert narrow["coverage"]["beyond_limits"] > 0
    assert narrow["coverage"]["added"] and all(v["angle_deg"] <= 4.0 for v in narrow["coverage"]["added"])
    assert all(abs(v["offset"]) <= 4.0 / YAW_DEG for v in narrow["coverage"]["added"])
    wide_far = {v["offset"] for v in wide["coverage"]["added"] if v["angle_deg"] > 4.0}
    assert wide_far and not wide_far & {v["offset"] for v in narrow["coverage"]["added"]}


class FlyingPixelScene(OccluderScene):
    """The occluder scene with a sensor's mixed samples: the wall's samples beside the
    shadow (4-neighbours) lie halfway between the plate and the wall (flying pixels)."""

    def read(self, i: int) -> Frame:
        f = super().read(i)
        hole = f.depth_m == 0
        beside = np.zeros_like(hole)
        beside[:, 1:] |= hole[:, :-1]
        beside[:, :-1] |= hole[:, 1:]
        beside[1:] |= hole[:-1]
        beside[:-1] |= hole[1:]
        depth = np.where(beside & (f.depth_m > 0), np.float32((PLATE_Z + WALL_Z) / 2), f.depth_m)
        return Frame(f.rgb, depth, f.T_world_cam, f.clean_depth_m)


def test_added_views_fill_nothing_beside_their_own_holes(tmp_path):
    """The mixed samples beside an added view's shadow would fill the target's empty
    pixels with a depth between plate and wall (nothing in the core outvotes them there); with
    ``coverage_mixed_margin_px`` 1 they fill nothing and what is filled is the wall."""
    truth = FlyingPixelScene().read(TARGET).clean_depth_m

    def gt(name: str, settings) -> tuple[dict, np.ndarray]:
        out = FrameSetOutputs.in_dir(tmp_path / name)
        members = [TARGET + o for o in settings.frameset.offsets]
        doc = process_frameset(FlyingPixelScene(), "synthetic", TARGET, members, "train", out, settings)
        return doc, io.read_exr(out.gt)["Z"]

    window = gt("window", _settings("window"))[1] > 0
    errors = {}
    for margin in (0, 1):
        doc, z = gt(f"m{margin}", _settings("coverage", coverage_max_angle_deg=20.0, coverage_mixed_margin_px=margin))
        filled = (z > 0) & ~window
        assert doc["coverage"]["filled_px"] == int(filled.sum()) > 0
        errors[margin] = np.abs(z[filled] - truth[filled])
    assert (errors[0] > 0.4).sum() >= 30  # the flying pixels' depth where the wall is
    assert errors[1].size >= 30 and errors[1].max() < 0.01


def test_split_guard_holds_for_added_views(tmp_path):
    tags = block_splits(N_FRAMES, "auto", SplitSettings(val_fraction=0.5, block_frames=16), 0, "d", "occluder")
    fs = FrameSetSettings(selection="coverage", coverage_span=30)
    planned = [s for s in enumerate_framesets(tags, fs) if s["status"] == "planned"]
    assert planned and len(set(tags)) == 2
    for s in planned:
        cands = coverage_candidates(tags, s["target"], s["members"], fs)
        assert cands and {tags[c] for c in cands} == {s["split"]}
        assert not set(cands) & set(s["members"])
        # every frame of the target's split within the span is a candidate, no other
        span = range(max(0, s["target"] - 30), min(N_FRAMES, s["target"] + 31))
        assert cands == [c for c in span if tags[c] == s["split"] and c not in s["members"]]
    assert coverage_candidates(tags, planned[0]["target"], planned[0]["members"], FrameSetSettings()) == []
    # end to end: the best views (far left) lie in another split, so they are never added
    tags = np.array(["val"] * 4 + ["train"] * (N_FRAMES - 4), dtype=object)
    members = [TARGET + o for o in FrameSetSettings().offsets]
    settings = _settings("coverage", coverage_max_angle_deg=20.0, coverage_min_fill_px=5)
    doc, _, _ = _build(tmp_path, "split", settings, coverage_candidates(tags, TARGET, members, settings.frameset))
    added = [TARGET + v["offset"] for v in doc["coverage"]["added"]]
    assert added and all(tags[a] == "train" for a in added) and doc["coverage"]["candidates"] == 40 - 4 - 6
    assert -20 in [v["offset"] for v in _build(tmp_path, "nosplit", settings)[0]["coverage"]["added"]]


def test_failing_added_view_left_out_with_its_reason(window, tmp_path, monkeypatch):
    """With ``refine``, an added view whose refinement fails the neighbour checks is not
    fused: the GT is the window's, the view is recorded with the registration's reason."""
    from depthgt import registration
    from depthgt.registration import local

    real = local.register_refine  # the entry registration.METHODS["refine"] calls
    calls = []

    def refine(data, offsets, settings, **kwargs):
        calls.append(list(offsets))
        if len(calls) == 1:  # the core: refined for real
            return real(data, offsets, settings, **kwargs)
        n = len(offsets) - 1
        return RegistrationResult(
            registration.poses_from_source(data).cpu(),
            list(offsets),
            ["failed"] * n,
            ["residual 9.0 noise sigmas > 3"] * n,
            "ok",
            "",
            n_correspondences=[0] * n,
        )

    monkeypatch.setattr(local, "register_refine", refine)
    settings = settings_from_config(
        {
            "resize": 64,
            "patches": {"size": 32},
            "registration": {"method": "refine"},
            "frameset": {"selection": "coverage", "coverage_views": 2, "coverage_max_angle_deg": 20.0},
        }
    )
    doc, gt, poses = _build(tmp_path, "fail", settings)
    added = doc["coverage"]["added"]
    assert len(calls) == 2 and calls[1][0] == 0 and calls[1][1:] == [v["offset"] for v in added]
    assert added and all(v["status"] == "failed" and v["reason"] == "residual 9.0 noise sigmas > 3" for v in added)
    assert "filled_px" not in doc["coverage"] and poses["coverage_T_j_to_t"] == {}
    monkeypatch.setattr(local, "register_refine", real)
    settings_w = settings_from_config({"resize": 64, "patches": {"size": 32}, "registration": {"method": "refine"}})
    _, gt_w, _ = _build(tmp_path, "fail_w", settings_w)
    for ch in ("Z", "S"):
        assert np.array_equal(gt[ch], gt_w[ch]), ch


def test_selection_parts():
    T = torch.eye(4, dtype=torch.float64).repeat(2, 1, 1)
    T[1, :3, :3] = torch.from_numpy(_rot_y(30.0))
    T[1, 0, 3] = 0.3
    base, angle = view_limits(T)
    assert torch.allclose(base, torch.tensor([0.0, 0.3], dtype=torch.float64))
    assert torch.allclose(angle, torch.tensor([0.0, 30.0], dtype=torch.float64))
    # a fronto-parallel plane seen from the target's own pose fills exactly the empty pixels
    depth = torch.full((1, 1, 8, 8), 2.0)
    empty = torch.zeros(8, 8, dtype=torch.bool)
    empty[2:4, 3:6] = True
    K = torch.tensor([[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]], dtype=torch.float64)
    fill = fill_maps(depth, K, T[:1], empty)
    assert torch.equal(fill[0].reshape(8, 8), empty)
    depth[0, 0, 2, 3] = 0  # invalid depth fills nothing
    assert int(fill_maps(depth, K, T[:1], empty).sum()) == 5
    with pytest.raises(ValueError, match=r"T_c_to_t must be \(C=1, 4, 4\), got \(2, 4, 4\)"):
        fill_maps(depth, K, T, empty)
    with pytest.raises(ValueError, match=r"K \(the frame set's one camera\) must be \(3, 3\), got \(1, 3, 3\)"):
        fill_maps(depth, K[None], T[:1], empty)
    assert choose_views(torch.zeros(3, 5, dtype=torch.bool), 2, 1) == []


KITCHEN = Path(__file__).resolve().parents[2] / "shared" / "data" / "7scenes-kitchen"


@pytest.mark.skipif(not KITCHEN.is_dir(), reason="../shared/data/7scenes-kitchen is absent")
def test_the_compiled_fill_maps_are_the_tensors():
    """On real Kinect frames (7-Scenes, 256x256, KinectFusion poses, candidates up to 20
    frames away) the CPU's compiled fill maps mark the tensor path's pixels, but for a
    point whose rounded pixel flips with the rotation's summation order (2 of ~160k)."""
    from depthgt.jobs.common import open_source_scene
    from depthgt.registration import load_frameset

    scene = open_source_scene({"kind": "sevenscenes", "root": str(KITCHEN)}, "7scenes-kitchen")
    d = load_frameset(scene, [30, 10, 14, 18, 42, 46, 50], (256, 256), True, torch.device("cpu"))
    T = torch.linalg.inv(d.T_world_cam[:1]) @ d.T_world_cam[1:]
    empty = torch.zeros(256, 256, dtype=torch.bool)
    empty[::3] = True  # a third of the rows, as if the core had left them empty
    empty[:, 100:160] = True
    got = fill_maps(d.depth_m[1:], d.K, T, empty)
    want = fill_maps(d.depth_m[1:], d.K, T, empty, compiled=False)
    assert int(want.sum()) > 100_000 and int((got != want).sum()) <= 1e-4 * int(want.sum())


def test_coverage_settings_name_their_key():
    for key, value in (
        ("selection", "best"),
        ("coverage_span", 0),
        ("coverage_views", -1),
        ("coverage_max_baseline_m", 0.0),
        ("coverage_max_angle_deg", 200.0),
        ("coverage_min_fill_px", 0),
        ("coverage_mixed_margin_px", -1),
        ("coverage_mixed_margin_px", 1.5),
        ("coverage_mixed_jump_rel", -0.1),
    ):
        with pytest.raises(ConfigError, match=f"frameset.{key}"):
            settings_from_config({"frameset": {key: value}})


@pytest.mark.parametrize("method", ["given", "overfit"])
def test_batch_job_adds_views_of_the_targets_split_reading_each_frame_once(tmp_path, monkeypatch, method):
    """The batch job: candidates from the index's split tags (``split: auto`` blocks), the
    wider span's frames read once per batch (the frame cache keeps them), added views
    recorded in each frame set's frameset.json and their frames in batch.json; with
    ``overfit`` (the core's poses from the scene here) the views come from the chain."""
    if method == "overfit":
        from depthgt.registration import overfit

        monkeypatch.setattr(overfit, "register_overfit", _true_overfit)
    source = {
        "name": "syn",
        "kind": "synthetic",
        "split": "auto",
        "scenes": ["room_000"],
        "options": {"n_frames": 24, "width": 80, "height": 60},
    }
    config = {
        "seed": 1,
        "device": "cpu",
        "resize": 32,
        "sources": [source],
        "split": {"val_fraction": 0.5, "block_frames": 8},
        "frameset": {
            "neighbours": 1,
            "stride": 1,
            "batch_size": 32,
            "selection": "coverage",
            "coverage_span": 6,
            "coverage_views": 2,
            "coverage_min_fill_px": 1,
            "coverage_mixed_margin_px": 0,  # at 32x32 the rooms' every sample is beside a jump
            "coverage_max_angle_deg": 90.0,
            "coverage_max_baseline_m": 5.0,
        },
        "patches": {"count": 1, "size": 16, "max_missing": 1.0},
        "registration": {"method": method},
    }
    run_scene_index(source, "room_000", config, str(tmp_path / "index.parquet"), str(tmp_path / "index.json"))
    table = pd.read_parquet(tmp_path / "index.parquet")
    tags = dict(zip(table["position"].astype(int), table["split"]))
    reads = count_synthetic_reads(monkeypatch)
    last = 22 if method == "given" else 12  # the chain refines ~10 pairs per frame set: fewer targets
    shard = tmp_path / f"000001-{last:06d}.zip"
    records = run_frameset_batch(source, "room_000", 1, last, config, str(tmp_path / "index.parquet"), str(shard))
    built = [r for r in records if r["status"] == "ok"]
    assert built and any(r["reason"].startswith("split_guard") for r in records)
    assert sorted(reads) == sorted(set(reads))  # each frame read once, candidates included
    added_any = False
    with zipfile.ZipFile(shard) as z:
        for r in built:
            doc = json.loads(z.read(f"{r['target']:06d}/frameset.json"))
            added = [r["target"] + v["offset"] for v in doc["coverage"]["added"]]
            added_any |= bool(added)
            assert all(tags[a] == tags[r["target"]] for a in added), (r["target"], added)
            assert all(abs(a - r["target"]) <= 6 and a not in r["members"] for a in added)
            if method == "overfit":  # every added view was reached by a link that held
                chained = {x["offset"] for x in doc["coverage"]["chain"]["links"] if x["status"] == "ok"}
                assert {v["offset"] for v in doc["coverage"]["added"]} <= chained
    assert added_any
    assert {f["position"] for f in store.read_batch_frames(shard)} == set(reads)


def _true_overfit(data, offsets, settings, **kwargs):
    """The overfit registration's place in these tests: the scene's exact poses of the
    core (the chain beyond the core is what is tested, with the real refinement)."""
    T = torch.linalg.inv(data.T_world_cam[:1]) @ data.T_world_cam[1:]
    n = len(offsets) - 1
    return RegistrationResult(T.cpu(), list(offsets), ["ok"] * n, [""] * n, "ok", "", n_correspondences=[0] * n)


def _overfit_settings(**frameset):
    return settings_from_config(
        {
            "resize": 64,
            "patches": {"size": 32},
            "frameset": {"selection": "coverage", "coverage_span": 30, "coverage_views": 2, **frameset},
            "registration": {"method": "overfit"},
        }
    )


def test_overfit_chains_the_added_views_through_the_core(window, tmp_path, monkeypatch):
    """Without the source's poses (``overfit``) the candidates' poses come from a chain
    through the core's members: the chained poses match the scene's, the added views
    fill the shadow as with ``given`` poses, and the core's pixels stay the window's."""
    from depthgt.registration import overfit

    monkeypatch.setattr(overfit, "register_overfit", _true_overfit)
    _, gt_w, _ = window
    doc, gt, poses = _build(tmp_path, "ofc", _overfit_settings(coverage_max_angle_deg=20.0))
    cov = doc["coverage"]
    chain = cov["chain"]
    assert chain["step"] == 2 and chain["stopped"] == {}
    # each side walks outwards from the outermost core member at the core's stride
    left = [link for link in chain["links"] if link["offset"] < 0]
    assert [(x["from"], x["offset"]) for x in left[:2]] == [(-6, -8), (-8, -10)]
    assert all(x["status"] == "ok" for x in chain["links"]) and {x["offset"] for x in chain["links"]} >= {-20, 14}
    added = [v for v in cov["added"] if v["status"] == "ok"]
    assert added and all(v["offset"] < -6 and v["offset"] % 2 == 0 for v in added)
    scene = OccluderScene()
    for o, T in poses["coverage_T_j_to_t"].items():  # within a third of a pixel at the wall (1 px = 33 mm)
        truth = np.linalg.inv(scene.pose(TARGET)) @ scene.pose(TARGET + int(o))
        assert np.abs(np.asarray(T)[:3, 3] - truth[:3, 3]).max() < 0.01, o
        assert np.abs(np.asarray(T)[:3, :3] - truth[:3, :3]).max() < 2e-3, o
    frame = scene.read(TARGET)
    strip = (frame.depth_m == 0) & (frame.clean_depth_m > 0) & (gt_w["Z"] == 0)
    filled = strip & (gt["Z"] > 0)
    assert filled.sum() >= 0.9 * strip.sum()
    assert np.abs(gt["Z"][filled] - frame.clean_depth_m[filled]).max() < 0.01
    core = gt_w["Z"] > 0
    for ch in ("Z", "S"):
        assert np.array_equal(gt[ch][core], gt_w[ch][core]), ch


def test_overfit_chain_stops_at_a_failing_link(tmp_path, monkeypatch):
    """A link that fails its checks ends the chain on its side: nothing beyond it is
    chosen or fused, and the record says where and why."""
    from depthgt.gt import coverage
    from depthgt.registration import overfit

    monkeypatch.setattr(overfit, "register_overfit", _true_overfit)
    real = coverage.refine_source_poses

    def refine(rgb, depth_m, K, offsets, T_start, settings):
        res = real(rgb, depth_m, K, offsets, T_start, settings)
        if len(offsets) == 2 and torch.allclose(depth_m[1], broken):  # the link into frame -12
            res.neighbour_status, res.neighbour_reasons = ["failed"], ["residual 9.0 noise sigmas > 3"]
        return res

    broken = torch.nn.functional.interpolate(  # frame TARGET-12 at the working size, as the chain gets it
        torch.from_numpy(OccluderScene().read(TARGET - 12).depth_m)[None, None], size=HW, mode="nearest"
    )[0]
    monkeypatch.setattr(coverage, "refine_source_poses", refine)
    doc, _, poses = _build(tmp_path, "stop", _overfit_settings(coverage_max_angle_deg=20.0))
    chain = doc["coverage"]["chain"]
    assert chain["stopped"] == {"-": "link -10 -> -12: residual 9.0 noise sigmas > 3"}
    assert min(x["offset"] for x in chain["links"]) == -12
    assert all(v["offset"] > -12 for v in doc["coverage"]["added"])
    assert all(int(o) > -12 for o in poses["coverage_T_j_to_t"])


@pytest.mark.parametrize("method", ["given", "refine"])
def test_batch_cache_gives_the_same_coverage_as_none(tmp_path, method):
    """With the batch job's frame cache the core's geometry comes from the window's
    render, each candidate's mixed samples are found once, and the added views'
    refinement pyramids come from (and stay in) the cache: the same GT (to float32
    rounding of the per-frame results) and the same record as without a cache."""
    from depthgt.framecache import FrameCache

    settings = _settings("coverage", coverage_max_angle_deg=20.0)
    settings = replace(settings, registration=replace(settings.registration, method=method))
    doc, gt, poses = _build(tmp_path, "none", settings)
    scene = OccluderScene()
    cache = FrameCache(keep=2 * settings.frameset.coverage_span + 2)
    docs = {}
    for target in (TARGET - 1, TARGET):  # the second set reuses the first's frames
        members = [target + o for o in settings.frameset.offsets]
        out = FrameSetOutputs.in_dir(tmp_path / f"cached{target}")
        docs[target] = process_frameset(scene, "synthetic", target, members, "train", out, settings, cache=cache)
    gt_c = io.read_exr(FrameSetOutputs.in_dir(tmp_path / f"cached{TARGET}").gt)
    assert docs[TARGET]["coverage"] == doc["coverage"]
    assert np.array_equal(gt_c["Z"] > 0, gt["Z"] > 0)
    assert np.abs(gt_c["Z"] - gt["Z"]).max() < 1e-6
    kinds = {k for frame in cache._frames.values() for k in frame}
    assert any(k.startswith("coverage.without_mixed") for k in kinds) and any(
        k.startswith("render.geometry") for k in kinds
    )
    added = [TARGET + v["offset"] for v in doc["coverage"]["added"]]
    assert added and all(("refine.level1" in cache._frames[p]) == (method == "refine") for p in added)


def test_mixed_samples_equal_max_pool_windows():
    """mixed_samples' running-maximum windows give max_pool2d's values (the rule as first written)."""
    import torch.nn.functional as F

    from depthgt.gt.coverage import mixed_samples

    g = torch.Generator().manual_seed(3)
    d = torch.rand(3, 1, 40, 50, generator=g) + 0.5
    d[torch.rand(d.shape, generator=g) < 0.1] = 0.0
    d[:, :, 10:20, 5:30] += 1.0  # jumps
    for margin, jump in ((1, 0.0), (2, 0.03), (3, 0.1)):
        valid, k = d > 0, 2 * margin + 1
        ref = F.max_pool2d((~valid).float(), k, stride=1, padding=margin) > 0
        hi = F.max_pool2d(torch.where(valid, d, 0.0), k, stride=1, padding=margin)
        lo = -F.max_pool2d(torch.where(valid, -d, -float("inf")), k, stride=1, padding=margin)
        if jump > 0:
            ref |= hi - lo > jump * d
        assert torch.equal(mixed_samples(d, margin, jump), valid & ref)


def test_no_candidate_gives_empty_fill_maps():
    """No candidate left (none within the limits, none the chain reached): empty maps and
    no view chosen, not a failed reshape of 0 elements."""
    from depthgt import geometry

    K = torch.tensor([[8.0, 0, 3.5], [0, 8.0, 3.5], [0, 0, 1]])
    none = torch.zeros(0, 1, 6, 8)
    assert geometry.backproject(none, K[None].expand(0, 3, 3)).shape == (0, 48, 3)
    fill = fill_maps(none, K, torch.zeros(0, 4, 4), torch.ones(6, 8, dtype=torch.bool))
    assert fill.shape == (0, 48) and fill.dtype == torch.bool
    assert choose_views(fill, 4, 1) == []


def _failing_links(monkeypatch):
    """Every link of the overfit chain fails its checks (the core registered as the scene's poses)."""
    from depthgt.gt import coverage
    from depthgt.registration import overfit

    monkeypatch.setattr(overfit, "register_overfit", _true_overfit)
    real = coverage.refine_source_poses

    def refine(rgb, depth_m, K, offsets, T_start, settings):
        res = real(rgb, depth_m, K, offsets, T_start, settings)
        res.neighbour_status, res.neighbour_reasons = ["failed"], ["large_correction(9.00cm,1.00deg)"]
        return res

    monkeypatch.setattr(coverage, "refine_source_poses", refine)


@pytest.mark.parametrize("why", ["beyond_limits", "not_chained"])
def test_no_candidate_left_keeps_the_core(window, tmp_path, monkeypatch, why):
    """Candidates there are, but none is left to add (all beyond the baseline limit, or,
    with ``overfit``, the chain stopped at its first link on both sides): the frame set
    is built with no view added, its GT the window's bit for bit, and the record says why."""
    if why == "beyond_limits":
        settings = _settings("coverage", coverage_max_baseline_m=0.001)  # every candidate is >= 1 cm away
    else:
        _failing_links(monkeypatch)
        settings = _overfit_settings(coverage_max_angle_deg=20.0)
    doc, gt, poses = _build(tmp_path, why, settings)
    cov = doc["coverage"]
    assert cov["candidates"] == 40 - 6 and cov["unusable"] == {}
    assert cov[why] == cov["candidates"] and cov["added"] == [] and "filled_px" not in cov
    if why == "not_chained":
        assert cov["chain"]["stopped"] == {
            "-": "link -6 -> -8: large_correction(9.00cm,1.00deg)",
            "+": "link +6 -> +8: large_correction(9.00cm,1.00deg)",
        }
    assert poses["coverage_T_j_to_t"] == {}
    _, gt_w, poses_w = window
    for ch in ("Z", "S"):
        assert np.array_equal(gt[ch], gt_w[ch]), ch
    assert poses["T_j_to_t"] == poses_w["T_j_to_t"]


def test_default_synthetic_scene_overfit_fast_coverage_builds(tmp_path):
    """The frame set that crashed (``RuntimeError: cannot reshape tensor of 0 elements``):
    the default config's first synthetic room, target 7, ``overfit`` with the ``fast``
    preset and ``selection: coverage``. When this test was written its chain failed its
    first link on the + side (a large correction) and had no grid frame to walk to on the
    - side, so no candidate was reached (test_no_candidate_left_keeps_the_core holds that
    case whatever the refinement does); it must build either way."""
    import yaml

    from depthgt.gt.cache import ResizedScene
    from depthgt.jobs.common import open_source_scene

    config = yaml.safe_load((Path(__file__).resolve().parents[1] / "config/config.yaml").read_text())
    source = config["sources"][0]
    config.update(
        device="cpu",
        sources=[source],
        frameset={**config.get("frameset", {}), "selection": "coverage"},
        registration={"method": "overfit", "preset": "fast"},
    )
    settings = settings_from_config(config)
    fs = settings.frameset
    keep = 2 * max(fs.reach, fs.coverage_span) + 2  # as the batch job keeps the frames
    scene = ResizedScene(open_source_scene(source, source["scenes"][0], need_poses=False), settings.size_hw, keep=keep)
    target = 7
    out = FrameSetOutputs.in_dir(tmp_path / "fs")
    members = [target + o for o in settings.frameset.offsets]
    doc = process_frameset(scene, source["name"], target, members, "train", out, settings)
    cov = doc["coverage"]
    chained = {x["offset"] for x in cov["chain"]["links"] if x["status"] == "ok"}
    assert doc["status"] == "ok" and out.gt.exists()
    assert {v["offset"] for v in cov["added"]} <= chained
    assert ("filled_px" in cov) == any(v["status"] == "ok" for v in cov["added"])
