"""The frame-set storage format (issue 29): the GT depth in fixed point and its sigma on
a logarithmic grid, each at a stated precision, the input depth and colour kept exact,
patches stored as boxes and cut on read, and the format version that refuses shards of
an older format by name."""

from __future__ import annotations

import json
import zipfile

import numpy as np
import pandas as pd
import pytest

from depthgt import io
from depthgt.atomic import save_npz
from depthgt.data import GTDataset
from depthgt.errors import DepthGTError, FrameError
from depthgt.gt import store
from depthgt.gt.build import OUTPUT_FILES
from depthgt.gt.card import verify
from depthgt.gt.patches import crop_pairs, cut_patches, patch_record


def _scene(rng, hw=(40, 48)):
    yy, xx = np.mgrid[0 : hw[0], 0 : hw[1]]
    gt = (1.2 + 0.013 * xx + 0.007 * yy + rng.normal(0, 0.001, hw)).astype(np.float32)
    gt[rng.random(hw) < 0.02] = 0
    sigma = np.where(gt > 0, rng.uniform(0.0005, 0.002, hw), 0).astype(np.float32)
    sigma[:16, :16] = 0.05  # an uncertain corner: max_gt_sigma_m rejects crops there
    raw_mm = np.round(gt * 1000 + rng.normal(0, 3, hw)).astype(np.uint16)
    raw_mm[rng.random(hw) < 0.1] = 0
    inp = raw_mm.astype(np.float32) / np.float32(1000)  # as io.read_depth_png converts millimetres
    truth = (1.2 + 0.013 * xx + 0.007 * yy).astype(np.float32)
    rgb = rng.integers(0, 256, (*hw, 3), dtype=np.uint8)
    return gt, sigma, inp, truth, rgb


def test_gt_exr_round_trip_within_the_stated_precision(tmp_path):
    rng = np.random.default_rng(0)
    gt, sigma, *_ = _scene(rng)
    gt[0, :8] = np.linspace(0.2, 10.0, 8)  # the range the issue names: 0-10 m
    sigma[0, :8] = np.geomspace(2e-4, 0.2, 8)  # real sigmas span 0.3 mm to 0.14 m
    chans = {"Z": gt, "S": sigma}
    store.write_gt_exr(tmp_path / "a.exr", chans)
    store.write_gt_exr(tmp_path / "b.exr", dict(reversed(list(chans.items()))))
    assert (tmp_path / "a.exr").read_bytes() == (tmp_path / "b.exr").read_bytes()  # deterministic
    back = io.read_exr(tmp_path / "a.exr")
    assert sorted(back) == ["S", "Z"] and all(v.dtype == np.float32 for v in back.values())
    # Z: half a unit of 2^-14 m (30.5 um) at most
    assert np.abs(back["Z"].astype(np.float64) - gt).max() <= 0.5 / store.GT_UNITS["Z"] * (1 + 1e-6)
    # S: 4.4 % of its value at most, at every magnitude; no sigma becomes 0 or appears
    steps, smallest = store.GT_LOG_GRID["S"]
    rel = np.abs(back["S"][sigma > 0].astype(np.float64) / sigma[sigma > 0] - 1)
    assert rel.max() <= 2 ** (0.5 / steps) - 1 + 1e-6 and 2 ** (0.5 / steps) - 1 < 0.045
    assert ((back["S"] > 0) == (sigma > 0)).all()
    assert ((back["Z"] > 0) == (gt > 0)).all()  # no depth turned into "missing" or back
    # what the build uses is what a reader gets, bit for bit; writing it again changes nothing
    stored = store.stored_gt(chans)
    for name in chans:
        np.testing.assert_array_equal(back[name], stored[name])
    store.write_gt_exr(tmp_path / "c.exr", stored)
    assert (tmp_path / "c.exr").read_bytes() == (tmp_path / "a.exr").read_bytes()
    # the precision the issue asks for: 10x finer than the smallest median sigma seen (0.6 mm) over 0-10 m
    assert 0.5 / store.GT_UNITS["Z"] <= 0.06e-3
    far = store.stored_gt({"Z": np.array([[10.0, 9.99997]], np.float32)})["Z"]
    assert np.abs(far - np.array([[10.0, 9.99997]])).max() <= 0.5 / store.GT_UNITS["Z"]
    # the GT holds no other channel (format 2's N and W are gone)
    with pytest.raises(ValueError, match=r"unknown GT channels \['N', 'W'\]"):
        store.write_gt_exr(tmp_path / "c.exr", {**chans, "N": gt, "W": gt})


def test_log_grid_keeps_a_constant_relative_step(tmp_path):
    values = np.array([[0.0, 1e-9, 2.0**-20, 3e-4, 6e-4, 1.4e-3, 0.02, 0.5, 7.0]], np.float32)
    codes = io.log_quantised(values, 8, 2.0**-20)
    assert codes.dtype == np.uint32 and codes[0, 0] == 0 and codes[0, 1] == codes[0, 2] == 1
    back = io.from_log_quantised(codes, 8, 2.0**-20)
    assert back[0, 0] == 0 and back[0, 1] == np.float32(2.0**-20)  # below the smallest value: stored as it
    rel = np.abs(back[0, 2:].astype(np.float64) / values[0, 2:] - 1)
    assert rel.max() <= 2 ** (1 / 16) - 1 + 1e-6
    # one more code is one step of 2^(1/8): a constant relative step at every magnitude
    assert np.allclose(io.from_log_quantised(codes + 1, 8, 2.0**-20)[0, 1:] / back[0, 1:], 2 ** (1 / 8))
    np.testing.assert_array_equal(io.on_log_grid(back, 8, 2.0**-20), back)  # stored values are on the grid
    with pytest.raises(ValueError, match=r"s.exr channel S: value -0.001 at pixel \(0, 1\)"):
        io.write_exr(tmp_path / "s.exr", {"S": np.array([[0.0, -0.001]], np.float32)}, log_grid={"S": (8, 1e-6)})
    with pytest.raises(ValueError, match="also fixed point"):
        io.write_exr(tmp_path / "s.exr", {"S": values}, fixed={"S": 10}, log_grid={"S": (8, 1e-6)})
    with pytest.raises(ValueError, match="whole steps per octave"):
        io.log_quantised(values, 0, 1e-6)


def test_colour_is_stored_lossless_as_webp(tmp_path):
    rng = np.random.default_rng(4)
    rgb = rng.integers(0, 256, (40, 48, 3), dtype=np.uint8)
    rgb[:10] = 0  # flat and noisy regions
    io.write_rgb_webp(tmp_path / "c.webp", rgb)
    data = (tmp_path / "c.webp").read_bytes()
    assert data[:4] == b"RIFF" and data[8:12] == b"WEBP"
    np.testing.assert_array_equal(io.decode_color(data, "c.webp", formats=("WEBP",)), rgb)
    with pytest.raises(FrameError, match="c.webp: not a readable JPEG or PNG or WEBP image"):
        io.decode_color(data[: len(data) // 2], "c.webp", formats=("WEBP",))
    with pytest.raises(FrameError, match="not a readable JPEG or PNG"):  # sources still take JPEG and PNG only
        io.decode_color(data, "c.webp")
    assert OUTPUT_FILES == store.FRAMESET_FILES and store.RGB_MEMBER in OUTPUT_FILES  # the build writes rgb.webp


def test_fixed_point_refuses_values_it_cannot_hold(tmp_path):
    with pytest.raises(ValueError, match=r"gt.exr channel Z.*pixel \(0, 1\)"):
        store.stored_gt({"Z": np.array([[1.0, -1.0]], np.float32)}, "gt.exr")
    with pytest.raises(ValueError, match="unknown GT channels"):
        store.stored_gt({"Q": np.zeros((2, 2), np.float32)})
    with pytest.raises(ValueError, match="not among the channels"):
        io.write_exr(tmp_path / "x.exr", {"Z": np.zeros((2, 2), np.float32)}, fixed={"S": 10})


@pytest.mark.parametrize("units", [1000, 5000, None])
def test_input_depth_stays_exact(tmp_path, units):
    rng = np.random.default_rng(1)
    if units is None:  # no sensor grid (a simulated sensor): float32, as it is
        depth = rng.uniform(0.4, 6.0, (30, 20)).astype(np.float32)
    else:
        depth = rng.integers(0, 40000, (30, 20)).astype(np.float32) / np.float32(units)
    truth = rng.uniform(0.4, 6.0, (30, 20)).astype(np.float32)
    store.write_input_exr(tmp_path / "input.exr", depth, truth)
    back = io.read_exr(tmp_path / "input.exr")
    np.testing.assert_array_equal(back["Z"], depth)
    assert np.abs(back["T"].astype(np.float64) - truth).max() <= 0.5 / store.TRUTH_UNITS
    np.testing.assert_array_equal(back["T"], store.stored_input(depth, truth)[1])
    import OpenEXR

    with OpenEXR.File(str(tmp_path / "input.exr")) as f:
        table = json.loads(f.header()[io.FIXED_POINT_ATTRIBUTE])
    assert table.get("Z") == units and table["T"] == store.TRUTH_UNITS


@pytest.mark.parametrize("max_gt_sigma_m", [None, 0.01])
def test_patches_cut_on_read_are_the_built_crops(max_gt_sigma_m):
    rng = np.random.default_rng(2)
    gt, sigma, inp, truth, rgb = _scene(rng)
    boxes = np.array([[0, 0, 16, 16], [10, 20, 16, 16], [24, 32, 16, 16], [5, 5, 16, 16]])
    built = crop_pairs(inp, gt, rgb, boxes, 0.05, "gt", truth_m=truth, gt_sigma_m=sigma, max_gt_sigma_m=max_gt_sigma_m)
    assert built["kept"].sum() == (len(boxes) if max_gt_sigma_m is None else 2)
    record = patch_record(built, max_gt_sigma_m)
    assert not set(record) & {"input", "gt", "rgb", "truth", "gt_sigma"}  # boxes, not crops
    cut = cut_patches(record, inp, gt, rgb, truth_m=truth, gt_sigma_m=sigma)
    assert sorted(cut) == sorted(built)
    for k in built:
        assert cut[k].dtype == built[k].dtype and cut[k].shape == built[k].shape, k
        np.testing.assert_array_equal(cut[k], built[k], err_msg=k)
    none_kept = crop_pairs(inp, gt, rgb, boxes, 0.0)  # nothing passes: shapes as crop_pairs gives them
    cut = cut_patches(patch_record(none_kept), inp, gt, rgb)
    assert all(cut[k].shape == none_kept[k].shape for k in none_kept)
    with pytest.raises(ValueError, match="p.npz: .*no truth image"):
        cut_patches(record, inp, gt, rgb, gt_sigma_m=sigma, where="p.npz")


def _v1_shard(path, gt, inp, rgb, boxes):
    """A shard as depthgt wrote it before format versions (commit ef0c22c): float32
    EXRs, the crops in patches.npz, no version in the comment or batch.json."""
    d = path.parent / "v1"
    d.mkdir(parents=True)
    io.write_exr(d / "gt.exr", {"Z": gt, "S": np.full_like(gt, 0.001), "N": np.ones_like(gt), "W": np.ones_like(gt)})
    io.write_exr(d / "input.exr", {"Z": inp})
    io.write_rgb_png(d / "rgb.png", rgb)
    save_npz(d / "patches.npz", crop_pairs(inp, gt, rgb, boxes, 0.05))
    (d / "frameset.json").write_text(json.dumps({"K": np.eye(3).tolist(), "target": 6}))
    (d / "poses.json").write_text("{}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with zipfile.ZipFile(path, "w") as z:
        for f in sorted(d.iterdir()):
            z.writestr(f"000006/{f.name}", f.read_bytes())
        z.writestr("batch.json", json.dumps({"framesets": [{"target": 6, "status": "ok", "reason": ""}]}))
    return d


def test_an_old_format_shard_is_refused_by_name(tmp_path):
    rng = np.random.default_rng(3)
    gt, _, inp, _, rgb = _scene(rng)
    shard = tmp_path / "results/framesets/syn/room_0/000006-000006.zip"
    folder = _v1_shard(shard, gt, inp, rgb, np.array([[0, 0, 16, 16]]))
    loc = store.location(shard, 6)
    want = (
        rf"{shard} is in frame-set format version 1; this depthgt reads version {store.FORMAT_VERSION} only.*"
        "`depthgt rebuild syn room_0`"
    )
    for read in (
        store.read_frameset_at,
        store.read_patches_at,
        store.read_frame_images,
        store.read_batch,
        lambda loc: store.read_json(f"{loc}/frameset.json"),
    ):
        with pytest.raises(DepthGTError, match=want):
            read(loc if read is not store.read_batch else shard)
    with pytest.raises(DepthGTError, match=want):
        GTDataset.from_manifest(pd.DataFrame({"frameset": [loc], "patch": [0]}))[0]
    # a frame-set folder of the old format: its crops are not taken for a patch record
    with pytest.raises(DepthGTError, match=rf"{folder}/patches.npz is in frame-set format version 1"):
        store.read_patches_at(folder)
    # a shard of this format records its version in the comment and in batch.json
    new = store.write_shard(tmp_path / "results/framesets/syn/room_0/000008-000008.zip", {}, [])
    with zipfile.ZipFile(new) as z:
        assert store.shard_format_version(z) == store.FORMAT_VERSION
    assert json.loads(store.member_bytes(f"{new}/batch.json"))["format_version"] == store.FORMAT_VERSION
    assert store.rebuild_command(tmp_path / "results/rde/syn/room_0/frames.zip").startswith("rm ")


def _v2_frameset(d, gt, sigma, inp, rgb, boxes):
    """A frame-set folder as format 2 wrote it (commit 50bd960): gt.exr with Z at
    2^-15 m, S at 2^-14 m, N and W; rgb.png; the same patch record."""
    d.mkdir(parents=True)
    ones = np.ones_like(gt)
    io.write_exr(
        d / "gt.exr",
        {"Z": gt, "S": sigma, "N": ones, "W": ones},
        fixed={"Z": 2**15, "S": 2**14, "N": 1, "W": 16},
        compression="htj2k",
    )
    store.write_input_exr(d / "input.exr", inp)
    io.write_rgb_png(d / "rgb.png", rgb)
    save_npz(d / "patches.npz", patch_record(crop_pairs(inp, gt, rgb, boxes, 0.05)))
    (d / "frameset.json").write_text(json.dumps({"K": np.eye(3).tolist(), "target": 6, "format_version": 2}))
    (d / "poses.json").write_text("{}")
    return d


def test_a_format_2_shard_or_folder_is_refused_by_name(tmp_path):
    rng = np.random.default_rng(5)
    gt, sigma, inp, _, rgb = _scene(rng)
    folder = _v2_frameset(tmp_path / "v2" / "000006", gt, sigma, inp, rgb, np.array([[0, 0, 16, 16]]))
    shard = tmp_path / "results/framesets/syn/room_0/000006-000006.zip"
    shard.parent.mkdir(parents=True)
    with zipfile.ZipFile(shard, "w") as z:  # what format 2's write_shard wrote
        z.comment = b"depthgt frame-set shard, format version 2"
        for f in sorted(folder.iterdir()):
            z.writestr(f"000006/{f.name}", f.read_bytes())
        z.writestr("batch.json", json.dumps({"format_version": 2, "framesets": [{"target": 6, "status": "ok"}]}))
    loc = store.location(shard, 6)
    want = rf"{shard} is in frame-set format version 2; this depthgt reads version 3 only.*`depthgt rebuild syn room_0`"
    readers = (store.read_frameset_at, store.read_patches_at, store.read_frame_images)
    for read in readers:
        with pytest.raises(DepthGTError, match=want):
            read(loc)
    with pytest.raises(DepthGTError, match=want):
        GTDataset.from_manifest(pd.DataFrame({"frameset": [loc], "patch": [0]}))[0]
    # an extracted folder of format 2: refused by name too, not read as format 3
    for read in readers:
        with pytest.raises(DepthGTError, match=rf"frame-set folder {folder} is in frame-set format version 2"):
            read(folder)


def test_verify_names_a_card_of_an_older_format(tmp_path):
    card = tmp_path / "results/dataset/card.json"
    card.parent.mkdir(parents=True)
    card.write_text(json.dumps({"files": {}}))  # a card from before format versions
    report = verify(tmp_path)
    assert not report.ok and "format version 1" in report.problems[0] and "depthgt rebuild" in report.problems[0]
    card.write_text(json.dumps({"files": {}, "format_version": 2}))  # format 2: N, W and rgb.png
    report = verify(tmp_path)
    assert not report.ok and "format version 2, this depthgt reads version 3" in report.problems[0]
    card.write_text(json.dumps({"files": {}, "format_version": store.FORMAT_VERSION}))
    assert verify(tmp_path).ok
