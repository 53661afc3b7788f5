"""Tests of the real-data adapters (ScanNet exported + .sens, 7-Scenes, TUM) on small
generated folders, the bad-input cases, and the real 7-Scenes fixture."""

from __future__ import annotations

import logging
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from depthgt.errors import FrameError, SourceError
from depthgt.sources import base, tum
from depthgt.sources.sens import SensFile

sys.path.insert(0, str(Path(__file__).resolve().parent))
from sens_writer import write_sens  # noqa: E402

FIXTURE_7SCENES = Path(__file__).resolve().parents[2] / "shared/data/7scenes-kitchen"

HD, WD = 24, 32  # depth size used by the generated data
K_DEPTH = np.array([[29.0, 0.0, 15.5], [0.0, 29.0, 11.5], [0.0, 0.0, 1.0]])


def _rgb(h, w, seed):
    rng = np.random.default_rng(seed)
    # 2x2 constant blocks: an area downscale by 2 reproduces the coarse image exactly
    coarse = rng.integers(0, 256, (h // 2, w // 2, 3), dtype=np.uint8)
    return np.repeat(np.repeat(coarse, 2, 0), 2, 1)


def _smooth_rgb(h, w, seed):
    """Smooth colour with distinct channels (JPEG keeps it within a few levels)."""
    y, x = np.mgrid[0:h, 0:w]
    r = 180 + 40 * x / w + seed
    g = 100 + 50 * y / h
    b = 30 + 20 * (x + y) / (h + w)
    return np.stack([r, g, b], -1).astype(np.uint8)


def _depth_raw(seed, h=HD, w=WD, hole=True):
    rng = np.random.default_rng(100 + seed)
    d = rng.integers(500, 4000, (h, w), dtype=np.uint16)
    if hole:
        d[:3, :4] = 0
    return d


def _pose(k):
    a = 0.1 * k
    T = np.eye(4)
    T[:3, :3] = [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]]
    T[:3, 3] = (0.25 * k, -0.5, 1.0)
    return T.astype(np.float32).astype(np.float64)  # exactly representable in .sens float32


def _write_bgr(path, rgb):
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


# ------------------------------------------------------------------ ScanNet exported


def make_exported(root: Path, name="scene0000_00", numbers=(0, 1, 5, 10), inf_pose=(), color_png=True):
    scene = root / name
    for k in numbers:
        ext = "png" if color_png else "jpg"  # png: lossless, so the test can compare exactly
        _write_bgr(scene / "color" / f"{k}.{ext}", _rgb(2 * HD, 2 * WD, k))
        (scene / "depth").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(scene / "depth" / f"{k}.png"), _depth_raw(k))
        (scene / "pose").mkdir(parents=True, exist_ok=True)
        T = np.full((4, 4), -np.inf) if k in inf_pose else _pose(k)
        np.savetxt(scene / "pose" / f"{k}.txt", T)
    (scene / "intrinsic").mkdir(parents=True, exist_ok=True)
    K4 = np.eye(4)
    K4[:3, :3] = K_DEPTH
    np.savetxt(scene / "intrinsic" / "intrinsic_depth.txt", K4)
    np.savetxt(scene / "intrinsic" / "intrinsic_color.txt", K4)
    return scene


def test_scannet_exported_reads_frames_with_gaps(tmp_path):
    make_exported(tmp_path)
    scene = base.open_scene("scannet", tmp_path, "scene0000_00")
    assert isinstance(scene, base.Scene)
    assert len(scene) == 4 and [scene.frame_id(i) for i in range(4)] == ["0", "1", "5", "10"]
    assert scene.image_size == (HD, WD) and scene.has_poses and not scene.has_clean_depth
    np.testing.assert_array_equal(scene.intrinsics, K_DEPTH)
    f = scene.read(2)  # frame number 5
    assert f.rgb.dtype == np.uint8 and f.rgb.shape == (HD, WD, 3)
    np.testing.assert_array_equal(f.rgb, _rgb(2 * HD, 2 * WD, 5)[::2, ::2])  # INTER_AREA of 2x2 blocks
    assert f.depth_m.dtype == np.float32
    np.testing.assert_allclose(f.depth_m, _depth_raw(5) / 1000.0, rtol=1e-6)
    assert (f.depth_m[:3, :4] == 0).all()
    np.testing.assert_allclose(f.T_world_cam, _pose(5), atol=1e-12)
    assert f.clean_depth_m is None


def test_scannet_exported_bad_inputs(tmp_path, caplog):
    scene_dir = make_exported(tmp_path, numbers=(0, 1, 2, 3, 4, 5), inf_pose=(2,))
    (scene_dir / "color" / "3.png").unlink()  # missing colour
    cv2.imwrite(str(scene_dir / "depth" / "4.png"), _depth_raw(4, h=HD + 2))  # depth of the wrong size
    _write_bgr(scene_dir / "color" / "5.png", _rgb(2 * WD, 2 * WD, 5))  # square colour: cannot be fitted
    cv2.imwrite(str(scene_dir / "depth" / "1.png"), np.zeros((HD, WD), np.uint16))  # empty depth
    scene = base.open_scene("scannet", tmp_path, "scene0000_00")
    scene.read(0)
    expected = {1: "empty_depth", 2: "nonfinite_pose", 3: "missing_file", 4: "size_mismatch", 5: "size_mismatch"}
    for i, reason in expected.items():
        with pytest.raises(FrameError) as e:
            scene.read(i)
        assert e.value.reason == reason, (i, str(e.value))
        assert "scene0000_00" in str(e.value)
    with pytest.raises(FrameError, match=r"color/3\.jpg"):
        scene.read(3)
    with pytest.raises(FrameError, match=r"depth/4\.png"):
        scene.read(4)
    # without required poses the -inf frame is usable, with no pose
    lax = base.open_scene("scannet", tmp_path, "scene0000_00", require_pose=False)
    assert lax.read(2).T_world_cam is None
    assert lax.read(0).T_world_cam is not None


def test_scannet_exported_scene_errors(tmp_path):
    scene_dir = make_exported(tmp_path, name="scene0001_00", numbers=(0,))
    make_exported(tmp_path, name="scene0002_00", numbers=(0,))
    (scene_dir / "intrinsic" / "intrinsic_depth.txt").unlink()
    with pytest.raises(SourceError, match="intrinsic_depth.txt"):
        base.open_scene("scannet", tmp_path, "scene0001_00")
    # the option overrides the missing file
    s = base.open_scene("scannet", tmp_path, "scene0001_00", intrinsics=K_DEPTH)
    assert s.read(0).depth_m.shape == (HD, WD)
    with pytest.raises(SourceError, match="scene0001_00, scene0002_00") as e:
        base.open_scene("scannet", tmp_path, "scene9999_00")
    assert "scene9999_00" in str(e.value)
    with pytest.raises(SourceError, match="not found"):
        base.open_scene("scannet", tmp_path / "nowhere", "scene0001_00")
    with pytest.raises(SourceError, match="known kinds"):
        base.open_scene("kinect9000", tmp_path, "scene0001_00")


# ------------------------------------------------------------------ .sens


def make_sens(path, n=5, inf_pose=(3,), color="jpeg", depth="zlib_ushort", **kw):
    make = _smooth_rgb if color == "jpeg" else _rgb
    rgbs = [make(2 * HD, 2 * WD, k) for k in range(n)]
    depths = [_depth_raw(k) for k in range(n)]
    poses = [np.full((4, 4), -np.inf) if k in inf_pose else _pose(k) for k in range(n)]
    K_color = K_DEPTH * np.array([[2, 1, 2], [1, 2, 2], [1, 1, 1]])
    write_sens(
        path,
        rgbs,
        depths,
        poses,
        K_color,
        K_DEPTH,
        depth_shift=1000.0,
        color_compression=color,
        depth_compression=depth,
        **kw,
    )
    return rgbs, depths, poses


def test_sens_round_trip(tmp_path):
    path = tmp_path / "scene0003_00.sens"
    rgbs, depths, poses = make_sens(path)
    sens = SensFile(path)
    assert len(sens) == 5 and sens.problems == []
    h = sens.header
    assert h.version == 4 and h.sensor_name == "test-sensor" and h.depth_shift == 1000.0
    assert h.color_hw == (2 * HD, 2 * WD) and h.depth_hw == (HD, WD)
    assert h.color_compression == "jpeg" and h.depth_compression == "zlib_ushort"
    np.testing.assert_allclose(h.intrinsic_depth[:3, :3], K_DEPTH, rtol=1e-6)
    np.testing.assert_array_equal(sens.timestamps_depth, np.arange(5) * 1000 + 1)
    for k in range(5):
        np.testing.assert_array_equal(sens.read_depth_raw(k), depths[k])
        np.testing.assert_allclose(sens.read_depth_m(k), depths[k] / 1000.0, rtol=1e-6)
        assert np.abs(sens.read_color(k).astype(int) - rgbs[k]).max() <= 6  # JPEG: approximate, RGB order
    np.testing.assert_array_equal(sens.poses[[0, 1, 2, 4]], np.stack([poses[k] for k in (0, 1, 2, 4)]))
    assert np.isneginf(sens.poses[3]).all()

    scene = base.open_scene("scannet", tmp_path, "scene0003_00")
    assert len(scene) == 5 and scene.image_size == (HD, WD) and scene.frame_id(4) == "4"
    np.testing.assert_allclose(scene.intrinsics, K_DEPTH, rtol=1e-6)
    f = scene.read(1)
    assert f.rgb.shape == (HD, WD, 3) and f.rgb.dtype == np.uint8
    np.testing.assert_allclose(f.depth_m, depths[1] / 1000.0, rtol=1e-6)
    np.testing.assert_array_equal(f.T_world_cam, poses[1])
    with pytest.raises(FrameError, match="scene0003_00.sens frame 3") as e:
        scene.read(3)
    assert e.value.reason == "nonfinite_pose"
    assert base.open_scene("scannet", tmp_path, "scene0003_00", require_pose=False).read(3).T_world_cam is None


@pytest.mark.parametrize("color,depth", [("png", "raw_ushort"), ("raw", "zlib_ushort")])
def test_sens_lossless_colour_and_raw_depth(tmp_path, color, depth):
    path = tmp_path / "s.sens"
    rgbs, depths, _ = make_sens(path, n=2, inf_pose=(), color=color, depth=depth)
    sens = SensFile(path)
    for k in range(2):
        np.testing.assert_array_equal(sens.read_color(k), rgbs[k])
        np.testing.assert_array_equal(sens.read_depth_raw(k), depths[k])


def test_sens_open_is_lazy(tmp_path, monkeypatch):
    path = tmp_path / "s.sens"
    make_sens(path)
    import depthgt.sources.sens as sens_mod

    def boom(*a, **k):
        raise AssertionError("decoded at open time")

    import depthgt.io as io_mod

    monkeypatch.setattr(io_mod.cv2, "imdecode", boom)
    monkeypatch.setattr(sens_mod, "decode_color", boom)
    monkeypatch.setattr(sens_mod.zlib, "decompressobj", boom)
    assert len(SensFile(path)) == 5


def test_sens_truncated_header(tmp_path):
    path = tmp_path / "s.sens"
    make_sens(path, n=1)
    data = path.read_bytes()
    header_bytes = SensFile(path).header.header_bytes
    for cut in (0, 3, 11, 40, header_bytes - 1):
        bad = tmp_path / f"cut{cut}.sens"
        bad.write_bytes(data[:cut])
        with pytest.raises(SourceError, match=f"cut{cut}.sens.*truncated"):
            SensFile(bad)
    bad = tmp_path / "ver.sens"
    bad.write_bytes(b"\x03\x00\x00\x00" + data[4:])
    with pytest.raises(SourceError, match="version 3"):
        SensFile(bad)
    pos = 4 + 8 + len("test-sensor") + 4 * 64 + 4  # depth_compression_type
    bad = tmp_path / "occi.sens"
    bad.write_bytes(data[:pos] + (2).to_bytes(4, "little") + data[pos + 4 :])
    with pytest.raises(SourceError, match="occi.sens: depth compression 'occi_ushort' is not supported"):
        SensFile(bad)


def test_sens_truncated_frames(tmp_path, caplog):
    path = tmp_path / "scene0004_00.sens"
    make_sens(path, inf_pose=())
    full = SensFile(path)
    # cut inside frame 3's depth payload
    cut = int(full.depth_offsets[3]) + 5
    path.write_bytes(path.read_bytes()[:cut])
    with caplog.at_level(logging.WARNING):
        scene = base.open_scene("scannet", tmp_path, "scene0004_00")
    assert len(scene) == 3
    assert len(scene.problems) == 1 and "announces 5 frames, 3 found" in scene.problems[0]
    assert "scene0004_00.sens" in scene.problems[0]
    assert any("announces 5 frames, 3 found" in r.getMessage() for r in caplog.records)
    for i in range(3):
        scene.read(i)
    with pytest.raises(IndexError):
        scene.read(3)
    # cut inside a frame header
    path.write_bytes(path.read_bytes()[: int(full.color_offsets[1]) - 10])
    assert len(SensFile(path)) == 1


def test_sens_corrupt_payloads(tmp_path):
    path = tmp_path / "scene0005_00.sens"
    rgbs = [_rgb(2 * HD, 2 * WD, k) for k in range(3)]
    good = [cv2.imencode(".jpg", cv2.cvtColor(c, cv2.COLOR_RGB2BGR))[1].tobytes() for c in rgbs]
    payloads = [good[0], b"\xff\xd8\xff\xe0 this is not a jpeg" * 4, good[2]]
    write_sens(
        path,
        rgbs,
        [_depth_raw(k) for k in range(3)],
        [_pose(k) for k in range(3)],
        K_DEPTH,
        K_DEPTH,
        color_payloads=payloads,
    )
    scene = base.open_scene("scannet", tmp_path, "scene0005_00")
    scene.read(0)
    scene.read(2)
    with pytest.raises(FrameError, match="scene0005_00.sens frame 1 colour") as e:
        scene.read(1)
    assert e.value.reason == "unreadable"
    # corrupt the zlib stream of frame 2's depth in place
    sens = SensFile(path)
    data = bytearray(path.read_bytes())
    off = int(sens.depth_offsets[2])
    data[off : off + 8] = b"\x00" * 8
    path.write_bytes(bytes(data))
    with pytest.raises(FrameError, match="frame 2 depth.*zlib") as e:
        base.open_scene("scannet", tmp_path, "scene0005_00").read(2)
    assert e.value.reason == "unreadable"


def test_scannet_list_scenes_mixes_layouts(tmp_path):
    make_exported(tmp_path, name="scene0010_00", numbers=(0,))
    make_sens(tmp_path / "scene0011_00.sens", n=1, inf_pose=())
    (tmp_path / "scene0012_00").mkdir()
    make_sens(tmp_path / "scene0012_00" / "scene0012_00.sens", n=2, inf_pose=())
    (tmp_path / "notes").mkdir()
    assert base.list_scenes("scannet", tmp_path) == ["scene0010_00", "scene0011_00", "scene0012_00"]
    assert len(base.open_scene("scannet", tmp_path, "scene0012_00")) == 2
    # the one file of a scene (an input of its index): a .sens, not an exported folder
    assert base.scene_file("scannet", str(tmp_path), "scene0010_00") is None
    assert base.scene_file("scannet", str(tmp_path), "scene0011_00") == str(tmp_path / "scene0011_00.sens")
    assert base.scene_file("scannet", str(tmp_path), "scene0012_00") == str(
        tmp_path / "scene0012_00" / "scene0012_00.sens"
    )
    assert base.scene_file("sevenscenes", str(tmp_path), "scene0011_00") is None  # not a single-file kind


# ------------------------------------------------------------------ 7-Scenes


def make_7scenes_seq(folder: Path, n=3, color_ext="png", invalid=65535):
    folder.mkdir(parents=True, exist_ok=True)
    for k in range(n):
        _write_bgr(folder / f"frame-{k:06d}.color.{color_ext}", _rgb(HD, WD, k))
        d = _depth_raw(k, hole=False)
        d[:2, :2] = invalid
        d[2, 2] = 0
        cv2.imwrite(str(folder / f"frame-{k:06d}.depth.png"), d)
        np.savetxt(folder / f"frame-{k:06d}.pose.txt", _pose(k))
    return folder


def test_sevenscenes_sequence_layouts(tmp_path):
    make_7scenes_seq(tmp_path / "seq-01")
    make_7scenes_seq(tmp_path / "seq-02", n=2)
    assert base.list_scenes("sevenscenes", tmp_path) == ["seq-01", "seq-02"]
    s = base.open_scene("sevenscenes", tmp_path, "seq-01")
    assert len(s) == 3 and s.frame_id(2) == "2" and s.image_size == (HD, WD)
    np.testing.assert_array_equal(s.intrinsics, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])  # default
    f = s.read(1)
    assert (f.depth_m[:2, :2] == 0).all() and f.depth_m[2, 2] == 0  # 65535 and 0 are invalid
    np.testing.assert_allclose(f.depth_m[3:], _depth_raw(1, hole=False)[3:] / 1000.0, rtol=1e-6)
    np.testing.assert_array_equal(f.rgb, _rgb(HD, WD, 1))
    np.testing.assert_allclose(f.T_world_cam, _pose(1), atol=1e-12)
    # camera-intrinsics.txt in the root is used for its sequences; an option overrides it
    np.savetxt(tmp_path / "camera-intrinsics.txt", K_DEPTH)
    np.testing.assert_array_equal(base.open_scene("sevenscenes", tmp_path, "seq-02").intrinsics, K_DEPTH)
    K2 = K_DEPTH * 2
    K2[2, 2] = 1
    np.testing.assert_array_equal(base.open_scene("sevenscenes", tmp_path, "seq-02", intrinsics=K2).intrinsics, K2)
    # root being a sequence itself: "." or its folder name
    seq = tmp_path / "seq-01"
    assert base.list_scenes("sevenscenes", seq) == ["seq-01"]
    assert len(base.open_scene("sevenscenes", seq, ".")) == 3
    assert base.open_scene("sevenscenes", seq, "seq-01").name == "seq-01"
    with pytest.raises(SourceError, match="known scenes: seq-01, seq-02"):
        base.open_scene("sevenscenes", tmp_path, "seq-03")


def test_sevenscenes_bad_frames(tmp_path):
    seq = make_7scenes_seq(tmp_path / "seq-01", n=4, color_ext="jpg")
    (seq / "frame-000001.color.jpg").unlink()
    (seq / "frame-000002.pose.txt").write_text("nan " * 16)
    cv2.imwrite(str(seq / "frame-000003.depth.png"), _depth_raw(3, h=HD // 2, w=WD // 2))
    s = base.open_scene("sevenscenes", tmp_path, "seq-01")
    assert s.read(0).rgb.shape == (HD, WD, 3)
    with pytest.raises(FrameError, match="frame-000001.color.png") as e:
        s.read(1)
    assert e.value.reason == "missing_file"
    with pytest.raises(FrameError, match="seq-01 frame 2") as e:
        s.read(2)
    assert e.value.reason == "nonfinite_pose"
    with pytest.raises(FrameError, match="frame-000003.depth.png.*16x12") as e:
        s.read(3)
    assert e.value.reason == "size_mismatch"


@pytest.mark.fixture7
@pytest.mark.skipif(not FIXTURE_7SCENES.is_dir(), reason="../shared/data/7scenes-kitchen absent")
def test_sevenscenes_kitchen_fixture():
    assert base.list_scenes("sevenscenes", FIXTURE_7SCENES) == ["7scenes-kitchen"]
    s = base.open_scene("sevenscenes", FIXTURE_7SCENES, ".")
    assert len(s) == 60 and s.image_size == (480, 640) and s.has_poses
    assert s.frame_id(0) == "0" and s.frame_id(59) == "59"
    np.testing.assert_allclose(s.intrinsics, [[585, 0, 320], [0, 585, 240], [0, 0, 1]])
    holes, t = [], []
    for i in range(0, 60, 3):
        f = s.read(i)
        assert f.rgb.shape == (480, 640, 3) and f.depth_m.dtype == np.float32
        holes.append((f.depth_m == 0).mean())
        valid = f.depth_m[f.depth_m > 0]
        assert 0.3 < valid.min() and valid.max() < 5.0
        t.append(f.T_world_cam[:3, 3])
    assert 0.08 <= np.mean(holes) <= 0.11
    steps = np.linalg.norm(np.diff(np.array(t), axis=0), axis=1)  # 3 frames apart
    assert np.median(steps) < 0.05  # slow hand-held motion: a few mm per frame


# ------------------------------------------------------------------ TUM


def make_tum(folder: Path, n=5):
    """Depth at 30 Hz; colour 10 ms later except for frame 3 (50 ms); groundtruth at
    100 Hz but with a gap around frame 4."""
    (folder / "rgb").mkdir(parents=True)
    (folder / "depth").mkdir()
    t0 = 1305031102.0
    t_depth = t0 + np.arange(n) / 30.0
    t_rgb = t_depth + 0.01
    if n > 3:
        t_rgb[3] += 0.04
    d_lines, c_lines = ["# depth maps", "# timestamp filename"], ["# color images"]
    for k in range(n):
        dname, cname = f"depth/{t_depth[k]:.6f}.png", f"rgb/{t_rgb[k]:.6f}.png"
        cv2.imwrite(str(folder / dname), _depth_raw(k) * 5)  # 5000 per metre
        _write_bgr(folder / cname, _rgb(HD, WD, k))
        d_lines.append(f"{t_depth[k]:.6f} {dname}")
        c_lines.append(f"{t_rgb[k]:.6f} {cname}")
    (folder / "depth.txt").write_text("\n".join(d_lines) + "\n")
    (folder / "rgb.txt").write_text("\n".join(c_lines) + "\n")
    t_gt = np.arange(t0 - 0.05, t_depth[-1] + 0.05, 0.01)
    if n > 4:
        t_gt = t_gt[np.abs(t_gt - t_depth[4]) > 0.035]
    angle = 0.5 * (t_gt - t0)  # rotation about z
    rows = ["# ground truth trajectory", "# timestamp tx ty tz qx qy qz qw"]
    for t, a in zip(t_gt, angle):
        rows.append(f"{t:.4f} {t - t0:.4f} 0.5 1.5 0 0 {np.sin(a / 2):.9f} {np.cos(a / 2):.9f}")
    (folder / "groundtruth.txt").write_text("\n".join(rows) + "\n")
    return t_depth


def test_tum_association_and_poses(tmp_path):
    t_depth = make_tum(tmp_path / "rgbd_dataset_freiburg2_xyz")
    make_tum(tmp_path / "rgbd_dataset_freiburg3_office")
    assert base.list_scenes("tum", tmp_path) == ["rgbd_dataset_freiburg2_xyz", "rgbd_dataset_freiburg3_office"]
    # the raw images and the nearest pose (undistortion and interpolation: tests below)
    s = base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg2_xyz", undistort=False, interpolate_poses=False)
    assert len(s) == 5 and s.image_size == (HD, WD) and s.has_poses
    assert s.frame_id(2) == f"{t_depth[2]:.6f}"
    np.testing.assert_allclose(s.intrinsics, [[520.9, 0, 325.1], [0, 521.0, 249.7], [0, 0, 1]])
    assert base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg3_office").intrinsics[0, 0] == 535.4
    assert base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg2_xyz", camera="fr1").intrinsics[1, 1] == 516.5
    f = s.read(2)
    np.testing.assert_allclose(f.depth_m, _depth_raw(2) / 1000.0, rtol=1e-6)
    np.testing.assert_array_equal(f.rgb, _rgb(HD, WD, 2))
    # nearest groundtruth sample is within 5 ms: pose of the sample at round(t, 2)
    t_gt = np.round(t_depth[2] - t_depth[0] + 0.05, 2) - 0.05
    a = 0.5 * t_gt
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    np.testing.assert_allclose(f.T_world_cam[:3, :3], R, atol=1e-6)
    np.testing.assert_allclose(f.T_world_cam[:3, 3], [t_gt, 0.5, 1.5], atol=1e-4)
    with pytest.raises(FrameError, match="no colour image within") as e:
        s.read(3)  # colour 50 ms away
    assert e.value.reason == "no_association"
    with pytest.raises(FrameError, match="no ground-truth pose") as e:
        s.read(4)  # groundtruth gap
    assert e.value.reason == "no_association"
    lax = base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg2_xyz", require_pose=False)
    assert lax.read(4).T_world_cam is None
    loose = base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg2_xyz", max_dt=0.06)
    assert loose.read(3).rgb.shape == (HD, WD, 3)  # within the looser max_dt
    assert loose.read(4).T_world_cam is not None


def test_tum_pose_interpolated_at_depth_time(tmp_path):
    """The trajectory turns at 0.5 rad/s and moves at 1 m/s: the pose at the depth
    timestamp, interpolated between the 100 Hz rows, is exact (the nearest row is up to
    5 ms = 5 mm off); a depth frame in a gap of the trajectory keeps failing."""
    t_depth = make_tum(tmp_path / "rgbd_dataset_freiburg2_xyz")
    s = base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg2_xyz")
    for i in (0, 1, 2):
        dt = t_depth[i] - t_depth[0]
        a = 0.5 * dt
        T = s.read(i).T_world_cam
        np.testing.assert_allclose(
            T[:3, :3], [[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]], atol=1e-6
        )
        np.testing.assert_allclose(T[:3, 3], [dt, 0.5, 1.5], atol=2e-5)  # rows are written to 0.1 mm
    nearest = base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg2_xyz", interpolate_poses=False)
    assert abs(nearest.read(1).T_world_cam[0, 3] - (t_depth[1] - t_depth[0])) > 1e-3
    with pytest.raises(FrameError, match="no ground-truth pose"):
        s.read(4)


def test_tum_undistortion_known_truth(tmp_path):
    """Depth whose value is a known function of the undistorted (pinhole) direction,
    written through fr1's lens distortion: undistorted, every pixel holds the value of
    its pinhole direction (within the nearest-pixel step); colour likewise."""
    seq = tmp_path / "rgbd_dataset_freiburg1_xyz"
    make_tum(seq, n=3)
    fx, fy, cx, cy = tum.CAMERAS["fr1"]
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
    D = np.array(tum.DISTORTION["fr1"])
    h, w = 480, 640  # the camera's own size (the small colour images are scaled up to it)
    vd, ud = np.mgrid[0:h, 0:w].astype(np.float64)
    und = cv2.undistortPoints(np.stack([ud, vd], -1).reshape(-1, 1, 2), K, D).reshape(h, w, 2)

    def value(x, y):
        return 1.0 + 0.5 * x + 0.25 * y  # metres, of the pinhole direction (x, y)

    raw = np.round(value(und[..., 0], und[..., 1]) * 5000).astype(np.uint16)
    for name in sorted((seq / "depth").iterdir()):
        cv2.imwrite(str(name), raw)
    s = base.open_scene("tum", tmp_path, seq.name)
    assert s.camera == "fr1" and s.distortion is not None
    d = s.read(0).depth_m
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    want = value((u - cx) / fx, (v - cy) / fy)
    ok = d > 0
    assert ok.mean() > 0.8  # the border that the lens did not see stays empty
    step = 0.5 * (0.5 / fx + 0.25 / fy) + 1.0 / 5000  # half a pixel of the value's gradient + the PNG step
    assert np.abs(d[ok] - want[ok]).max() <= step * 1.01
    raw_scene = base.open_scene("tum", tmp_path, seq.name, undistort=False)
    assert np.abs(raw_scene.read(0).depth_m - want).max() > 20 * step  # the distortion is real
    assert base.open_scene("tum", tmp_path, seq.name, camera="ros_default").distortion is None
    with pytest.raises(SourceError, match="option distortion"):
        base.open_scene("tum", tmp_path, seq.name, distortion=[0.1, 0.2])


def test_tum_bad_inputs(tmp_path):
    seq = tmp_path / "rgbd_dataset_freiburg1_desk"
    t_depth = make_tum(seq)
    (seq / f"depth/{t_depth[1]:.6f}.png").unlink()
    s = base.open_scene("tum", tmp_path, seq.name)
    with pytest.raises(FrameError, match=f"{t_depth[1]:.6f}.png") as e:
        s.read(1)
    assert e.value.reason == "missing_file"
    with pytest.raises(SourceError, match="known scenes: rgbd_dataset_freiburg1_desk"):
        base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg1_xyz")
    with pytest.raises(SourceError, match="unknown TUM camera"):
        base.open_scene("tum", tmp_path, seq.name, camera="kinect2")
    (seq / "depth.txt").write_text("1.0 a b\n")
    with pytest.raises(SourceError, match="depth.txt: line 1 has 3 fields"):
        base.open_scene("tum", tmp_path, seq.name)
    # a sequence folder as the root itself
    seq2 = tmp_path / "other" / "rgbd_dataset_freiburg3_x"
    make_tum(seq2, n=2)
    assert base.list_scenes("tum", seq2) == ["rgbd_dataset_freiburg3_x"]
    assert len(base.open_scene("tum", seq2, ".")) == 2


# ------------------------------------------------------------------ hostile .sens input

from fuzz_harness import N_SENS_FRAMES, crafted_sens_kwargs, write_base_sens, zlib_bomb  # noqa: E402


def _crafted_sens(tmp_path, name, param=0):
    from fuzz_harness import _patch_sens

    kw = crafted_sens_kwargs(name, param)
    patch = kw.pop("patch", None)
    write_base_sens(tmp_path / "scene0100_00.sens", **kw)
    if patch:
        _patch_sens(tmp_path / "scene0100_00.sens", patch)
    return base.open_scene("scannet", tmp_path, "scene0100_00")


@pytest.mark.parametrize(
    "name,param,frame,reason,message",
    [
        ("sens_empty_colour_payload", 0, 2, "unreadable", "frame 2 colour: empty payload"),
        ("sens_jpeg_declares_60000x60000", 0, 2, "unreadable", "frame 2 colour: .*absurd size"),
        ("sens_jpeg_declares_40000x26000", 0, 2, "unreadable", "frame 2 colour: .*absurd size"),
        ("sens_jpeg_declares_16000x16000", 0, 2, "unreadable", "frame 2 colour: .*absurd size"),
        (
            "sens_jpeg_declares_8000x6000",
            0,
            2,
            "unreadable",
            "frame 2 colour: JPEG header declares 8000x6000 pixels, beyond",
        ),
        (
            "sens_jpeg_declares_256x192",
            0,
            2,
            "size_mismatch",
            "frame 2 colour: JPEG is 256x192, expected colour size is 128x96",
        ),
        ("sens_jpeg_truncated_half", 0, 2, "unreadable", "frame 2 colour: truncated JPEG"),
        ("sens_png_truncated_half", 0, 2, "unreadable", "frame 2 colour: truncated PNG"),
        ("sens_png16_colour", 0, 2, "unreadable", "frame 2 colour: colour must be 8-bit grey or RGB, decoded uint16"),
        ("sens_rgba_colour", 0, 2, "unreadable", "frame 2 colour: colour must be 8-bit grey or RGB, the PNG is 'RGBA'"),
        ("sens_tiff_colour", 0, 2, "unreadable", "frame 2 colour: not a readable JPEG or PNG"),
        ("sens_png_in_jpeg_file", 0, 2, "unreadable", "frame 2 colour: colour payload is PNG, expected JPEG"),
        (
            "sens_zlib_bomb",
            64 << 20,
            1,
            "unreadable",
            "frame 1 depth: payload of .* more than a frame of this size can take",
        ),
        ("sens_zlib_bomb", 6 << 20, 1, "unreadable", "frame 1 depth: zlib payload inflates beyond the 6144 bytes"),
        ("sens_pose_bottom_row_0000", 0, 3, "invalid_pose", "frame 3: pose's bottom row is 0 0 0 0, expected 0 0 0 1"),
        ("sens_pose_bottom_row_0002", 0, 3, "invalid_pose", "frame 3: pose's bottom row is 0 0 0 2, expected 0 0 0 1"),
        ("sens_pose_reflection", 0, 3, "invalid_pose", "frame 3: pose rotation has determinant -1"),
    ],
)
def test_sens_hostile_frame_is_a_recorded_skip(tmp_path, name, param, frame, reason, message):
    """Each crafted case of issue 10 fails as its own frame, naming file and frame; the
    other frames of the file read normally."""
    scene = _crafted_sens(tmp_path, name, param)
    assert len(scene) == N_SENS_FRAMES and scene.problems == []
    with pytest.raises(FrameError, match=f"scene0100_00.sens {message}") as e:
        scene.read(frame)
    assert e.value.reason == reason
    for i in set(range(N_SENS_FRAMES)) - {frame}:
        scene.read(i)


def test_sens_grey_colour_is_expanded(tmp_path):
    scene = _crafted_sens(tmp_path, "sens_grey_colour")
    rgb = scene.read(2).rgb
    assert rgb.shape == (48, 64, 3) and (rgb[..., 0] == rgb[..., 1]).all() and (rgb[..., 1] == rgb[..., 2]).all()


def test_sens_pose_checks_when_poses_are_optional(tmp_path):
    """require_pose: false drops an unusable pose (the frame stays usable without it)."""
    write_base_sens(tmp_path / "scene0101_00.sens", **crafted_sens_kwargs("sens_pose_bottom_row_0000"))
    lax = base.open_scene("scannet", tmp_path, "scene0101_00", require_pose=False)
    assert lax.read(3).T_world_cam is None and lax.read(2).T_world_cam is not None


def test_inflate_is_bounded_by_the_image_size():
    """A zlib bomb inflates no further than the h*w*2 bytes of a depth image."""
    import tracemalloc
    import zlib

    from depthgt.sources.sens import _inflate_bounded

    bomb = zlib_bomb(256 << 20)  # 256 MiB of zeros in ~260 KB
    tracemalloc.start()
    try:
        with pytest.raises(FrameError, match="inflates beyond the 614400 bytes") as e:
            _inflate_bounded(bomb, 640 * 480 * 2, "f frame 0 depth")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert e.value.reason == "unreadable" and peak < 2 * 614400 + 2 * len(bomb)
    good = zlib.compress(bytes(range(256)) * 6)
    assert _inflate_bounded(good, 1536, "f") == bytes(range(256)) * 6
    assert _inflate_bounded(good + b"junk", 1536, "f") == bytes(range(256)) * 6  # bytes after the stream: ignored
    with pytest.raises(FrameError, match="truncated zlib payload"):
        _inflate_bounded(good[:-6], 1536, "f")
    with pytest.raises(FrameError, match="corrupt zlib payload"):
        _inflate_bounded(b"\x00" * 8 + good, 1536, "f")


@pytest.mark.parametrize(
    "name,problem",
    [
        (
            "sens_lowered_frame_count",
            r"unexpected bytes after the 4 announced frames \(it holds 2 more frame record\(s\)",
        ),
        (
            "sens_garbage_after_frames",
            r"1160 unexpected bytes after the 6 announced frames \(it is not a valid IMU block\)",
        ),
        ("sens_frame_count_2^64-1", r"truncated .sens: header announces 18446744073709551615 frames, 6 found"),
        (
            "sens_colour_size_2^63",
            r"truncated .sens: header announces 6 frames, 2 found \(frame 2 payload ends at byte",
        ),
    ],
)
def test_sens_frames_never_vanish_unrecorded(tmp_path, name, problem):
    """Data after the announced frames must be the IMU block; otherwise (a frame count
    lowered by corruption) the frames it holds are recorded as a scene problem."""
    scene = _crafted_sens(tmp_path, name)
    assert len(scene.problems) == 1 and re.search(problem, scene.problems[0]), scene.problems
    assert "scene0100_00.sens" in scene.problems[0]


def test_sens_imu_block_or_nothing_is_clean(tmp_path):
    for imu in (None, 0, 3):
        write_base_sens(tmp_path / f"s{imu}.sens", imu_frames=imu)
        sens = SensFile(tmp_path / f"s{imu}.sens")
        assert len(sens) == N_SENS_FRAMES and sens.problems == [], imu


@pytest.mark.parametrize(
    "name,message",
    [
        ("sens_header_colour_60000x60000", r"corrupt .sens header \(colour 60000x60000"),
        ("sens_name_length_2^60", r"corrupt .sens header \(sensor name length 1152921504606846976\)"),
    ],
)
def test_sens_absurd_header_is_a_source_error(tmp_path, name, message):
    with pytest.raises(SourceError, match=f"scene0100_00.sens: {message}"):
        _crafted_sens(tmp_path, name)


# ------------------------------------------------------------------ pose and size checks


def test_pose_problem_cases():
    T = _pose(3)
    assert base.pose_problem(T) is None and base.usable_pose(T) is T
    noisy = T.copy()
    noisy[:3, :3] += 1.5e-4 * np.random.default_rng(0).standard_normal((3, 3))  # 7-Scenes-sized rounding: accepted
    assert base.pose_problem(noisy) is None
    cases = {
        "bottom row is 0 0 0 0": (3, slice(None), (0, 0, 0, 0)),
        "bottom row is 0 0 0 2": (3, slice(None), (0, 0, 0, 2)),
        "bottom row is 0 0.1 0 1": (3, 1, 0.1),
        "determinant -1": (slice(0, 3), 2, -T[:3, 2]),
        r"not orthonormal \(max \|R R\^T - I\| = 0.0201": (slice(0, 3), slice(0, 3), 1.01 * T[:3, :3]),
    }
    for msg, (rows, cols, value) in cases.items():
        bad = T.copy()
        bad[rows, cols] = value
        reason, text = base.pose_problem(bad)
        assert reason == "invalid_pose" and re.search(msg, text), (msg, text)
        assert base.usable_pose(bad) is None
        frame = base.Frame(np.zeros((2, 2, 3), np.uint8), np.ones((2, 2), np.float32), bad)
        with pytest.raises(FrameError, match=f"f7: .*{msg}") as e:
            base.check_frame(frame, (2, 2), "f7", need_pose=True)
        assert e.value.reason == "invalid_pose"
        base.check_frame(frame, (2, 2), "f7", need_pose=False)  # not needed: not checked
    assert base.pose_problem(np.full((4, 4), np.nan))[0] == "nonfinite_pose"
    assert base.pose_problem(np.eye(3))[0] == "invalid_pose"
    assert base.pose_problem(None)[0] == "missing_pose"


def test_first_depth_of_another_size_does_not_decide(tmp_path):
    """The scene's size is the majority of the sampled depth images: one odd first
    image is the one rejected, and the message names it and the majority size."""
    scene_dir = make_exported(tmp_path, numbers=(0, 1, 2, 3, 4))
    cv2.imwrite(str(scene_dir / "depth" / "0.png"), _depth_raw(0, h=HD // 2, w=WD // 2))
    scene = base.open_scene("scannet", tmp_path, "scene0000_00")
    assert scene.image_size == (HD, WD)
    assert len(scene.problems) == 1 and "32x24 (4), 16x12 (1)" in scene.problems[0]
    with pytest.raises(
        FrameError,
        match=r"depth/0\.png: PNG is 16x12, the scene's depth size \(that of 4 of 5 sampled "
        r"depth images\) is 32x24",
    ) as e:
        scene.read(0)
    assert e.value.reason == "size_mismatch"
    for i in range(1, 5):
        assert scene.read(i).depth_m.shape == (HD, WD)


# ------------------------------------------------------------------ TUM lists


def test_tum_unsorted_and_repeated_lists_are_cleaned_and_recorded(tmp_path, caplog):
    seq = tmp_path / "rgbd_dataset_freiburg1_room"
    t_depth = make_tum(seq)
    lines = (seq / "depth.txt").read_text().splitlines()
    header, rows = lines[:2], lines[2:]
    # out of order (line 5 before line 4) and frame 1 listed twice
    (seq / "depth.txt").write_text("\n".join(header + [rows[0], rows[2], rows[1], rows[1], rows[3], rows[4]]) + "\n")
    with caplog.at_level(logging.WARNING):
        s = base.open_scene("tum", tmp_path, seq.name)
    assert [s.frame_id(i) for i in range(len(s))] == [f"{t:.6f}" for t in t_depth]  # sorted, each image once
    assert len(s.problems) == 2
    assert re.search(r"depth.txt: 1 entries out of time order \(first at line 5\); sorted", s.problems[0])
    assert re.search(
        r"depth.txt: 1 repeated entries dropped \(same timestamp or file; first: line 6 repeats line 5\)", s.problems[1]
    )
    assert sum("repeated entries dropped" in r.getMessage() for r in caplog.records) == 1


def test_tum_without_poses_or_colour_list_records_the_file(tmp_path):
    seq = tmp_path / "rgbd_dataset_freiburg1_room"
    make_tum(seq)
    (seq / "groundtruth.txt").unlink()
    (seq / "rgb.txt").write_text("# colour images\n")
    s = base.open_scene("tum", tmp_path, seq.name, require_pose=False)
    assert not s.has_poses
    assert any(p.startswith(f"{seq / 'groundtruth.txt'}: not found") for p in s.problems)
    assert any(p.startswith(f"{seq / 'rgb.txt'}: no colour frames listed") for p in s.problems)


@pytest.mark.parametrize(
    "file,value", [("depth.txt", "nan"), ("depth.txt", "inf"), ("rgb.txt", "-inf"), ("groundtruth.txt", "nan")]
)
def test_tum_nonfinite_timestamp_is_a_source_error(tmp_path, file, value):
    """A NaN timestamp would be paired with any image (NaN > max_dt is False)."""
    seq = tmp_path / "rgbd_dataset_freiburg1_room"
    make_tum(seq)
    lines = (seq / file).read_text().splitlines()
    k = next(i for i, line in enumerate(lines) if not line.startswith("#")) + 1  # second data line
    fields = lines[k].split()
    lines[k] = " ".join([value] + fields[1:])
    (seq / file).write_text("\n".join(lines) + "\n")
    with pytest.raises(SourceError, match=rf"{file}: line {k + 1}: timestamp '{value}' is not finite"):
        base.open_scene("tum", tmp_path, seq.name)


def test_tum_nonfinite_pose_value_is_a_frame_problem(tmp_path):
    seq = tmp_path / "rgbd_dataset_freiburg1_room"
    t_depth = make_tum(seq)
    lines = (seq / "groundtruth.txt").read_text().splitlines()
    rows = [np.array(line.split(), dtype=float) for line in lines[2:]]
    k = int(np.argmin([abs(r[0] - t_depth[2]) for r in rows]))
    fields = lines[2 + k].split()
    fields[4] = "nan"
    lines[2 + k] = " ".join(fields)
    (seq / "groundtruth.txt").write_text("\n".join(lines) + "\n")
    s = base.open_scene("tum", tmp_path, seq.name)
    with pytest.raises(FrameError) as e:
        s.read(2)
    assert e.value.reason == "nonfinite_pose"
    s.read(1)


def test_frame_count_comes_from_metadata(tmp_path, monkeypatch):
    """The workflow plans from frame_count: equal to the opened scene's length, without
    reading a frame (synthetic: without building the room; .sens: the header)."""
    make_exported(tmp_path / "scannet", "scene0000_00")
    make_sens(tmp_path / "scannet" / "scene0002_00.sens", n=5, inf_pose=())
    make_7scenes_seq(tmp_path / "7s" / "seq-01", n=3)
    make_tum(tmp_path / "tum" / "rgbd_dataset_freiburg1_xyz")
    for kind, root, scene in (
        ("scannet", tmp_path / "scannet", "scene0000_00"),
        ("scannet", tmp_path / "scannet", "scene0002_00"),
        ("sevenscenes", tmp_path / "7s", "seq-01"),
        ("tum", tmp_path / "tum", "rgbd_dataset_freiburg1_xyz"),
    ):
        assert base.frame_count(kind, root, scene) == len(base.open_scene(kind, root, scene)), (kind, scene)
    from depthgt.sources import synthetic

    def no_build(*args, **kwargs):
        raise AssertionError("frame_count built the synthetic room")

    monkeypatch.setattr(synthetic.SyntheticScene, "__init__", no_build)
    assert base.frame_count("synthetic", None, "room_004", n_frames=17) == 17
    assert base.frame_count("synthetic", None, "room_004") == 40
    # a truncated .sens: the header's count (the jobs record the frames that are not there)
    path = tmp_path / "scannet" / "scene0002_00.sens"
    full = SensFile(path)
    path.write_bytes(path.read_bytes()[: int(full.depth_offsets[3]) + 5])
    monkeypatch.undo()
    assert base.frame_count("scannet", tmp_path / "scannet", "scene0002_00") == 5
    assert len(base.open_scene("scannet", tmp_path / "scannet", "scene0002_00")) == 3


def test_colour_matches_depth_from_the_registry_and_the_config(tmp_path):
    """The registration's photometric refinement term (``photometric: auto``) is used only
    where colour is the depth's camera at the depth's instant: every opened scene carries
    its kind's flag (synthetic only), a config source overrides it (synthetic data in
    ScanNet's layout), and the frame-set loader sees the override."""
    from depthgt.gt.cache import ResizedScene
    from depthgt.jobs.common import open_source_scene
    from depthgt.registration import photometric_for
    from depthgt.settings import RegistrationSettings

    make_exported(tmp_path / "scannet")
    make_7scenes_seq(tmp_path / "seven" / "seq-01")
    make_tum(tmp_path / "tum" / "rgbd_dataset_freiburg1_xyz")
    scenes = {
        "scannet": ("scene0000_00", tmp_path / "scannet"),
        "sevenscenes": ("seq-01", tmp_path / "seven"),
        "tum": ("rgbd_dataset_freiburg1_xyz", tmp_path / "tum"),
    }
    for kind, (name, root) in scenes.items():
        assert base.open_scene(kind, str(root), name).colour_matches_depth is False, kind
    assert base.open_scene("synthetic", None, "room_000", n_frames=2, width=64, height=48).colour_matches_depth is True
    src = {"name": "s", "kind": "scannet", "root": str(tmp_path / "scannet")}
    assert open_source_scene(src, "scene0000_00").colour_matches_depth is False
    assert open_source_scene({**src, "colour_matches_depth": "auto"}, "scene0000_00").colour_matches_depth is False
    matched = ResizedScene(open_source_scene({**src, "colour_matches_depth": True}, "scene0000_00"), (16, 16))
    assert matched.colour_matches_depth is True
    auto = RegistrationSettings(photometric="auto")
    assert photometric_for(auto, matched.colour_matches_depth).refine_settings.photo_weight > 0
    assert photometric_for(auto, False).refine_settings.photo_weight == 0
    syn = {"name": "y", "kind": "synthetic", "options": {"n_frames": 2, "width": 64, "height": 48}}
    assert open_source_scene({**syn, "colour_matches_depth": False}, "room_000").colour_matches_depth is False
