"""Issue 2 acceptance on the default synthetic scenes with the source's (exact) poses:
the GT beats the raw Kinect-style input against the clean truth, in completeness and in
accuracy where the input has data."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from depthgt.eval.metrics import depth_errors
from depthgt.gt.frameset import fuse, load_frameset, poses_from_source
from depthgt.jobs.common import open_source_scene
from depthgt.settings import FrameSetSettings, RenderSettings


@pytest.fixture(scope="module")
def framesets():
    torch.set_num_threads(2)
    out = []
    offsets = FrameSetSettings().offsets
    for room, n in (("room_000", 48), ("room_100", 32)):  # the default config's train and test rooms
        scene = open_source_scene({"kind": "synthetic", "options": {"n_frames": n, "seed": 0}}, room)
        for t in (9, 20):
            data = load_frameset(scene, [t + o for o in offsets], (256, 256), True, torch.device("cpu"))
            out.append((data, poses_from_source(data)))
    return out


def test_gt_beats_input_against_truth(framesets):
    ratios_counted, ratios_valid, completeness = [], [], []
    for data, T in framesets:
        gt = fuse(data, T, RenderSettings()).depth[0, 0].numpy()
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


def test_leave_target_out_uses_neighbours_only(framesets):
    data, T = framesets[0]
    lto = fuse(data, T, RenderSettings(), members=slice(1, None)).depth[0, 0].numpy()
    truth = data.truth_m[0, 0].numpy()
    s = depth_errors(lto, truth)
    assert s["completeness"] > 0.9 and s["mae_m"] < 0.01
    # removing the target changes the result (the target contributes to the full GT)
    full = fuse(data, T, RenderSettings()).depth[0, 0].numpy()
    assert not np.array_equal(full, lto)
