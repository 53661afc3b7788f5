"""Tests of the harder synthetic family (``varied_NNN``), the sensor profiles and the
exact per-pixel geometry (incidence, thin structures) the GT protocol scores by."""

from __future__ import annotations

import numpy as np
import pytest

from depthgt.errors import ConfigError, SourceError
from depthgt.sources.base import list_scenes, open_scene
from depthgt.synth.noise import SENSOR_PROFILES, infrared_return, kinect_noise, sensor_profile
from depthgt.synth.scene import Primitive
from depthgt.synth.spaces import generate_space_layout

SMALL = dict(width=160, height=120, n_frames=12)


@pytest.fixture(scope="module")
def varied():
    return [open_scene("synthetic", None, f"varied_{k:03d}", seed=3, **SMALL) for k in range(4)]


def test_names_list_and_errors():
    assert list_scenes("synthetic", None, family="varied", n_scenes=2) == ["varied_000", "varied_001"]
    assert list_scenes("synthetic", None) == ["room_000", "room_001", "room_002"]
    with pytest.raises(SourceError, match="varied_000"):
        open_scene("synthetic", None, "variedroom_1")
    with pytest.raises(ConfigError, match="sensor"):
        open_scene("synthetic", None, "varied_000", sensor="kinect_v9", **SMALL)
    with pytest.raises(ConfigError, match="family"):
        list_scenes("synthetic", None, family="castle")


def test_deterministic_and_distinct_from_rooms(varied):
    again = open_scene("synthetic", None, "varied_001", seed=3, **SMALL)
    a, b = varied[1].read(7), again.read(7)
    for x, y in (
        (a.rgb, b.rgb),
        (a.depth_m, b.depth_m),
        (a.clean_depth_m, b.clean_depth_m),
        (a.T_world_cam, b.T_world_cam),
    ):
        np.testing.assert_array_equal(x, y)
    room = open_scene("synthetic", None, "room_001", seed=3, **SMALL)
    assert not np.allclose(room.layout.size, varied[1].layout.size)


def test_spaces_sizes_intrinsics_and_motion(varied):
    sizes = np.stack([generate_space_layout(np.random.default_rng(k), texture_size=64).size for k in range(30)])
    assert sizes[:, :2].max() <= 9.0 and sizes[:, :2].min() >= 1.8 and sizes[:, :2].max(1).min() >= 3.0
    assert (sizes[:, :2].max(1) > 7.0).mean() > 0.25  # long rooms and corridors: far walls at 5-8 m
    for s in varied:
        fx = s.intrinsics[0, 0] * 640 / 160
        assert 450 <= fx <= 600 and abs(s.intrinsics[1, 1] / s.intrinsics[0, 0] - 1) < 0.011
        poses = np.stack([s.pose(i) for i in range(12)])
        steps = np.linalg.inv(poses[:-1]) @ poses[1:]
        assert np.linalg.norm(steps[:, :3, 3], axis=1).max() < 0.015
        rot = np.degrees(np.arccos(np.clip((np.trace(steps[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
        assert rot.max() < 3.0
    assert len({round(s.intrinsics[0, 0], 3) for s in varied}) == len(varied)


def test_hard_cases_in_view(varied):
    """Far range, grazing floors/ceilings, thin structures and sensor dropouts all occur."""
    far, grazing, thin, holes = [], [], [], []
    for s in varied:
        for i in (0, 11):
            f = s.read(i)
            view = s.exact_view(i)
            np.testing.assert_array_equal(view.depth_m, f.clean_depth_m)  # same ray cast at the scene's own K
            far.append((f.clean_depth_m > 5.0).mean())
            grazing.append((view.cos_incidence < np.cos(np.radians(65))).mean())
            thin.append(view.thin.mean())
            holes.append((f.depth_m == 0).mean())
    assert max(far) > 0.1 and np.mean(grazing) > 0.1 and max(thin) > 0.005
    assert 0.03 < np.mean(holes) < 0.4


def test_exact_view_at_working_resolution(varied):
    s = varied[0]
    K = s.intrinsics.copy()
    K[:2] *= 0.5
    K[0, 2], K[1, 2] = (s.intrinsics[0, 2] + 0.5) * 0.5 - 0.5, (s.intrinsics[1, 2] + 0.5) * 0.5 - 0.5
    view = s.exact_view(4, K, (60, 80))
    full = s.exact_view(4)
    assert view.depth_m.shape == view.cos_incidence.shape == view.thin.shape == (60, 80)
    # pixel centres of the half-size image fall between the full image's: depths agree on smooth parts
    assert np.median(np.abs(view.depth_m - full.depth_m[::2, ::2])) < 0.05
    assert ((view.cos_incidence >= 0) & (view.cos_incidence <= 1.0001)).all()


def test_thin_primitives():
    pole = Primitive("cylinder", np.zeros(3), np.array([0.01, 0.01, 0.8]), 0)
    leg = Primitive("box", np.zeros(3), np.array([0.012, 0.012, 0.3]), 0)
    board = Primitive("box", np.zeros(3), np.array([0.4, 0.012, 0.03]), 0)  # thin in one direction only
    drum = Primitive("cylinder", np.zeros(3), np.array([0.2, 0.2, 0.3]), 0)
    assert pole.thin and leg.thin and not board.thin and not drum.thin


def test_sensor_profiles_differ_in_noise_law():
    K = np.array([[585.0, 0, 319.5], [0, 585.0, 239.5], [0, 0, 1]])
    depth = np.full((48, 64), 4.0, np.float32) + np.linspace(0, 0.4, 64, dtype=np.float32)[None]
    kin, coarse = SENSOR_PROFILES["kinect_v1"], SENSOR_PROFILES["coarse_stereo"]
    quiet = dict(border_right_px=0, blob_fraction=0, round_mm=False, max_range_m=9.0)
    a = kinect_noise(depth, K, np.random.default_rng(0), sensor_profile("kinect_v1", **quiet))
    b = kinect_noise(depth, K, np.random.default_rng(0), sensor_profile("coarse_stereo", **quiet))
    # depth levels: disparity multiples of the profile's step (at 64 px width, 10x finer than at 640)
    for out, prof in ((a, kin), (b, coarse)):
        disp = 585.0 * prof.baseline_m / out[out > 0]
        step = prof.disparity_step_px * 64 / 640
        np.testing.assert_allclose(disp / step, np.round(disp / step), atol=1e-2)
    # the coarse profile's far-range levels are ~2.2x the Kinect's
    ratio = (coarse.disparity_step_px / coarse.baseline_m) / (kin.disparity_step_px / kin.baseline_m)
    assert 2.0 < ratio < 2.5
    assert np.abs(b - depth)[b > 0].mean() > 1.5 * np.abs(a - depth)[a > 0].mean()
    assert coarse.shadow_grow_px > kin.shadow_grow_px and coarse.sigma_disp_falloff == 0 < kin.sigma_disp_falloff
    with pytest.raises(ValueError, match="unknown sensor profile"):
        sensor_profile("tof")


def test_glossy_return():
    cos = np.array([[0.1, 0.5, 0.9, 0.99]], np.float32)
    ones = np.ones_like(cos)
    matte = infrared_return(0.5 * ones, ones, 0 * ones, cos)
    glossy = infrared_return(0.5 * ones, ones, 0.8 * ones, cos)
    np.testing.assert_allclose(matte, 0.5)
    assert glossy[0, 0] < 0.15 and glossy[0, 0] < glossy[0, 1] < glossy[0, 2]  # little return at oblique angles
    assert glossy[0, 3] == 0  # saturated head-on


def test_varied_depth_uses_profile(varied):
    s = open_scene("synthetic", None, "varied_001", seed=3, sensor="coarse_stereo", **SMALL)
    assert s.noise_settings.disparity_step_px == SENSOR_PROFILES["coarse_stereo"].disparity_step_px
    assert s.noise_settings.max_range_m == 8.0  # the family's range
    np.testing.assert_array_equal(s.read(3).clean_depth_m, varied[1].read(3).clean_depth_m)
    assert not np.array_equal(s.read(3).depth_m, varied[1].read(3).depth_m)
    assert (
        open_scene("synthetic", None, "varied_001", seed=3, noise_max_range_m=5.0, **SMALL).noise_settings.max_range_m
        == 5.0
    )
