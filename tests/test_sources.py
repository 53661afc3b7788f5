"""Tests of the real-data adapters (ScanNet exported + .sens, 7-Scenes, TUM) on small
generated folders, the bad-input cases, and the real 7-Scenes fixture."""

from __future__ import annotations

import logging
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from depthgt.errors import FrameError, SourceError
from depthgt.sources import base
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
    write_sens(path, rgbs, depths, poses, K_color, K_DEPTH, depth_shift=1000.0,
               color_compression=color, depth_compression=depth, **kw)
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
    bad.write_bytes(data[:pos] + (2).to_bytes(4, "little") + data[pos + 4:])
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
    write_sens(path, rgbs, [_depth_raw(k) for k in range(3)], [_pose(k) for k in range(3)],
               K_DEPTH, K_DEPTH, color_payloads=payloads)
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
    data[off: off + 8] = b"\x00" * 8
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
    s = base.open_scene("tum", tmp_path, "rgbd_dataset_freiburg2_xyz")
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
