"""Tests of depthgt.io: image, EXR, JSON and pose helpers, including bad input."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from depthgt.errors import FrameError
from depthgt.io import read_depth_png, read_exr, read_pose_txt, read_rgb, write_exr, write_json, write_rgb_png

sys.path.insert(0, str(Path(__file__).resolve().parent))


def test_read_depth_png_scales_to_metres(tmp_path):
    raw = np.array([[0, 1000, 2500], [65535, 1, 5000]], dtype=np.uint16)
    cv2.imwrite(str(tmp_path / "d.png"), raw)
    d = read_depth_png(tmp_path / "d.png", 1000.0)
    assert d.dtype == np.float32 and d.shape == (2, 3)
    np.testing.assert_allclose(d, raw.astype(np.float64) / 1000.0, rtol=1e-6)
    assert d[0, 0] == 0
    d5 = read_depth_png(tmp_path / "d.png", 5000.0)
    assert d5[1, 2] == pytest.approx(1.0)


def test_read_depth_png_errors_name_the_path(tmp_path):
    with pytest.raises(FrameError, match="nope.png") as e:
        read_depth_png(tmp_path / "nope.png", 1000.0)
    assert e.value.reason == "missing_file"
    (tmp_path / "junk.png").write_bytes(b"not a png at all")
    with pytest.raises(FrameError, match="junk.png") as e:
        read_depth_png(tmp_path / "junk.png", 1000.0)
    assert e.value.reason == "unreadable"
    cv2.imwrite(str(tmp_path / "u8.png"), np.full((4, 4), 7, np.uint8))
    with pytest.raises(FrameError, match="uint16") as e:
        read_depth_png(tmp_path / "u8.png", 1000.0)
    assert e.value.reason == "unreadable"
    with pytest.raises(ValueError):
        read_depth_png(tmp_path / "u8.png", 0.0)


def test_rgb_png_round_trip_keeps_channel_order(tmp_path):
    rgb = np.zeros((5, 7, 3), np.uint8)
    rgb[..., 0] = 200  # pure red must stay in channel 0
    rgb[2, 3] = (1, 2, 3)
    write_rgb_png(tmp_path / "sub" / "c.png", rgb)
    back = read_rgb(tmp_path / "sub" / "c.png")
    assert back.dtype == np.uint8
    np.testing.assert_array_equal(back, rgb)
    # cv2 on disk is BGR: red is the last channel there
    assert cv2.imread(str(tmp_path / "sub" / "c.png"))[0, 0, 2] == 200


def test_rgb_errors(tmp_path):
    with pytest.raises(FrameError, match="missing.jpg") as e:
        read_rgb(tmp_path / "missing.jpg")
    assert e.value.reason == "missing_file"
    (tmp_path / "bad.jpg").write_bytes(b"\xff\xd8\xff garbage")
    with pytest.raises(FrameError, match="bad.jpg") as e:
        read_rgb(tmp_path / "bad.jpg")
    assert e.value.reason == "unreadable"
    with pytest.raises(ValueError, match=r"rgb must be \(H, W, 3\), got \(4, 4\)"):
        write_rgb_png(tmp_path / "x.png", np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match=r"\(H, W, 3\) uint8, got float32"):
        write_rgb_png(tmp_path / "x.png", np.zeros((4, 4, 3), np.float32))


def test_exr_round_trip_and_deterministic_bytes(tmp_path):
    rng = np.random.default_rng(0)
    z = rng.uniform(0.5, 4.0, (6, 9)).astype(np.float32)
    z[0, :3] = 0
    w = rng.uniform(0, 1, (6, 9)).astype(np.float32)
    write_exr(tmp_path / "a.exr", {"Z": z, "W": w})
    write_exr(tmp_path / "b.exr", {"W": w, "Z": z})  # channel order must not matter
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()
    back = read_exr(tmp_path / "a.exr")
    assert sorted(back) == ["W", "Z"]
    assert back["Z"].dtype == np.float32 and back["Z"].shape == (6, 9)
    np.testing.assert_array_equal(back["Z"], z)
    np.testing.assert_array_equal(back["W"], w)


def test_exr_errors(tmp_path):
    with pytest.raises(ValueError, match="no channel"):
        write_exr(tmp_path / "e.exr", {})
    with pytest.raises(ValueError, match="'Z'.*float32"):
        write_exr(tmp_path / "e.exr", {"Z": np.zeros((3, 3), np.float64)})
    with pytest.raises(ValueError, match="differ in shape"):
        write_exr(tmp_path / "e.exr", {"Z": np.zeros((3, 3), np.float32), "W": np.zeros((3, 4), np.float32)})
    with pytest.raises(FrameError, match="none.exr") as e:
        read_exr(tmp_path / "none.exr")
    assert e.value.reason == "missing_file"
    (tmp_path / "bad.exr").write_bytes(b"definitely not exr")
    with pytest.raises(FrameError, match="bad.exr") as e:
        read_exr(tmp_path / "bad.exr")
    assert e.value.reason == "unreadable"


def test_write_json_sorted_and_numpy(tmp_path):
    write_json(tmp_path / "j" / "a.json", {"b": np.float32(1.5), "a": np.arange(3), "c": {"z": 1, "y": np.int64(2)}})
    text = (tmp_path / "j" / "a.json").read_text()
    assert text.index('"a"') < text.index('"b"') < text.index('"c"')
    assert text.index('"y"') < text.index('"z"')
    assert json.loads(text) == {"a": [0, 1, 2], "b": 1.5, "c": {"y": 2, "z": 1}}
    with pytest.raises(TypeError, match="a.json"):
        write_json(tmp_path / "j" / "a.json", {"x": object()})


def test_read_pose_txt(tmp_path):
    T = np.eye(4)
    T[:3, 3] = (0.1, -2.0, 3.25)
    np.savetxt(tmp_path / "p.txt", T)
    np.testing.assert_array_equal(read_pose_txt(tmp_path / "p.txt"), T)
    assert read_pose_txt(tmp_path / "p.txt").dtype == np.float64
    (tmp_path / "inf.txt").write_text("\n".join(["-inf -inf -inf -inf"] * 4))
    assert np.isneginf(read_pose_txt(tmp_path / "inf.txt")).all()
    (tmp_path / "short.txt").write_text("1 0 0\n0 1 0\n0 0 1\n")
    with pytest.raises(FrameError, match="9 numbers") as e:
        read_pose_txt(tmp_path / "short.txt")
    assert e.value.reason == "unreadable"
    (tmp_path / "text.txt").write_text("a b c d\n" * 4)
    with pytest.raises(FrameError, match="text.txt"):
        read_pose_txt(tmp_path / "text.txt")
    with pytest.raises(FrameError, match="absent.txt") as e:
        read_pose_txt(tmp_path / "absent.txt")
    assert e.value.reason == "missing_file"


def test_fit_rgb_to_depth_area_downscale_and_aspect_check():
    from depthgt.io import fit_rgb_to_depth

    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (8, 12, 3), dtype=np.uint8)
    assert fit_rgb_to_depth(rgb, (8, 12), "x") is rgb  # same size: untouched
    out = fit_rgb_to_depth(rgb, (4, 6), "x")
    block_mean = rgb.reshape(4, 2, 6, 2, 3).astype(float).mean((1, 3))  # area average of 2x2 blocks
    assert out.dtype == np.uint8 and out.shape == (4, 6, 3)
    assert np.abs(out - block_mean).max() <= 0.5 + 1e-9
    # ScanNet's 1296x968 colour vs 640x480 depth differ by 0.4% in aspect: accepted
    assert fit_rgb_to_depth(np.zeros((968, 1296, 3), np.uint8), (480, 640), "x").shape == (480, 640, 3)
    with pytest.raises(FrameError, match=r"c\.jpg: colour 12x12 cannot be fitted to depth 12x8") as e:
        fit_rgb_to_depth(np.zeros((12, 12, 3), np.uint8), (8, 12), "c.jpg")
    assert e.value.reason == "size_mismatch"


# ------------------------------------------------------------------ untrusted images


def _enc(img, ext):
    ok, buf = cv2.imencode(ext, img)
    assert ok
    return buf.tobytes()


def _textured(h=48, w=64):
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([(3 * x) % 256, (5 * y) % 256, (x * y) % 256], -1).astype(np.uint8)


def test_declared_size_is_checked_before_decoding(tmp_path, monkeypatch):
    """Headers claiming huge images are rejected from the header alone: the decoder is
    never called (it would allocate w*h*3 bytes first)."""
    from fuzz_harness import jpeg_with_size, png_with_size

    import depthgt.io as io_mod

    def no_decode(*a, **k):
        raise AssertionError("decoded")

    monkeypatch.setattr(io_mod.cv2, "imdecode", no_decode)
    jpg, png = _enc(_textured(), ".jpg"), _enc(np.zeros((48, 64), np.uint16), ".png")
    for w, h in ((60000, 60000), (40000, 26000), (16000, 16000), (8000, 6000)):
        (tmp_path / "c.jpg").write_bytes(jpeg_with_size(jpg, w, h))
        with pytest.raises(FrameError, match=r"c\.jpg: .*(absurd size|beyond the limit)") as e:
            read_rgb(tmp_path / "c.jpg")
        assert e.value.reason == "unreadable"
        (tmp_path / "d.png").write_bytes(png_with_size(png, w, h))
        with pytest.raises(FrameError, match=r"d\.png: .*(absurd size|beyond the limit)"):
            read_depth_png(tmp_path / "d.png", 1000.0)
    # a plausible size that is not the scene's: size_mismatch, still without decoding
    (tmp_path / "d.png").write_bytes(png_with_size(png, 640, 480))
    with pytest.raises(FrameError, match=r"d\.png: PNG is 640x480, the scene's size is 64x48") as e:
        read_depth_png(tmp_path / "d.png", 1000.0, expected_hw=(48, 64), what="the scene's size")
    assert e.value.reason == "size_mismatch"


def test_truncated_empty_and_mistyped_images(tmp_path):
    rgb = _textured()
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    jpg, png = _enc(bgr, ".jpg"), _enc(bgr, ".png")
    cases = {
        "half.jpg": (jpg[: len(jpg) // 2], "truncated JPEG"),  # libjpeg would decode it with grey rows
        "half.png": (png[: len(png) // 2], "truncated PNG"),
        "empty.jpg": (b"", "empty"),
        "rgb16.png": (_enc(bgr.astype(np.uint16) * 257, ".png"), "8-bit grey or RGB, decoded uint16"),
        "rgba.png": (_enc(np.dstack([bgr, bgr[..., :1]]), ".png"), "8-bit grey or RGB, the PNG is 'RGBA'"),
        "grey16.png": (_enc(np.zeros((48, 64), np.uint16), ".png"), "8-bit grey or RGB, the PNG is 'I;16'"),
        "tiff.png": (_enc(bgr, ".tiff"), "not a readable JPEG or PNG"),
    }
    for name, (data, msg) in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(FrameError, match=msg) as e:
            read_rgb(tmp_path / name)
        assert e.value.reason == "unreadable" and name in str(e.value), name
    # JPEG padded with zeros after its end marker and 8-bit grey are fine
    (tmp_path / "pad.jpg").write_bytes(jpg + b"\x00" * 7)
    np.testing.assert_array_equal(
        read_rgb(tmp_path / "pad.jpg"), cv2.cvtColor(cv2.imdecode(np.frombuffer(jpg, np.uint8), 1), cv2.COLOR_BGR2RGB)
    )
    (tmp_path / "grey.png").write_bytes(_enc(rgb[..., 1], ".png"))
    np.testing.assert_array_equal(read_rgb(tmp_path / "grey.png"), np.repeat(rgb[..., 1:2], 3, axis=2))
    # depth: truncated, 8-bit and JPEG are unreadable
    d = _enc((np.arange(48 * 64).reshape(48, 64) % 5000).astype(np.uint16), ".png")
    for name, data, msg in (("cut.png", d[:-20], "truncated PNG"), ("jpg.png", jpg, "16-bit PNG, got JPEG")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(FrameError, match=msg):
            read_depth_png(tmp_path / name, 1000.0)


def test_save_npz_round_trip_at_exactly_the_path(tmp_path):
    """Every array comes back from numpy.load with its dtype and shape, at a name without
    ``.npz``; deflated (smaller than the arrays), with no time of writing in the bytes."""
    from depthgt.atomic import save_npz

    arrays = {
        "gt": np.linspace(0.5, 4.0, 2 * 128 * 128, dtype=np.float32).reshape(2, 128, 128),
        "rgb": np.full((2, 8, 8, 3), 7, np.uint8),
        "kept": np.array([True, False]),
        "boxes": np.arange(8).reshape(2, 4),
    }
    path = tmp_path / "patches.tmp"
    save_npz(path, arrays)
    with np.load(path) as z:
        assert sorted(z.files) == sorted(arrays)
        for name, value in arrays.items():
            assert z[name].dtype == value.dtype and np.array_equal(z[name], value)
    assert path.stat().st_size < sum(a.nbytes for a in arrays.values()) / 2
    import zipfile

    with zipfile.ZipFile(path) as zf:  # no time of writing in the bytes
        assert {m.date_time for m in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}


def test_write_atomic_leaves_no_temporary_file_when_the_write_or_the_rename_fails(tmp_path, monkeypatch):
    """A full disk in the writer, or a rename that fails, leaves neither a temporary file
    nor a changed target; the error comes through as it was."""
    import errno
    import os

    from depthgt.atomic import write_atomic

    target = tmp_path / "out" / "config.yaml"
    write_atomic(target, Path.write_text, "old\n")

    def enospc(path: Path, text: str) -> None:
        path.write_text(text[:2])
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    with pytest.raises(OSError, match="No space left on device"):
        write_atomic(target, enospc, "new\n")
    assert [p.name for p in target.parent.iterdir()] == ["config.yaml"] and target.read_text() == "old\n"

    def refused(src, dst):
        raise OSError(errno.ENOSPC, "No space left on device", str(dst))

    monkeypatch.setattr(os, "replace", refused)
    with pytest.raises(OSError, match="No space left on device"):
        write_atomic(target, Path.write_text, "new\n")
    monkeypatch.undo()
    assert [p.name for p in target.parent.iterdir()] == ["config.yaml"] and target.read_text() == "old\n"
