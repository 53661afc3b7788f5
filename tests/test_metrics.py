"""Metrics on hand-computed cases."""

import math

import numpy as np
import pytest
import torch

from depthgt.eval.metrics import (
    completeness,
    depth_metrics,
    ls_distance,
    mae,
    pose_errors,
    rmse,
    rotation_error_deg,
    ssim_depth,
    to_long,
    translation_error_cm,
)

torch.set_num_threads(1)

PRED = np.array([[1.0, 2.0], [0.0, 4.0]], dtype=np.float32)
REF = np.array([[1.0, 3.0], [2.0, 0.0]], dtype=np.float32)


def test_rmse_mae_completeness_hand_computed():
    # both valid: (0,0) err 0, (0,1) err 1
    assert rmse(PRED, REF) == pytest.approx(math.sqrt(0.5))
    assert mae(PRED, REF) == pytest.approx(0.5)
    # reference valid: errors 0, 1, 2 (missing prediction counts as 0 m)
    assert rmse(PRED, REF, fill=True) == pytest.approx(math.sqrt(5.0 / 3.0))
    assert mae(PRED, REF, fill=True) == pytest.approx(1.0)
    assert completeness(PRED, REF) == pytest.approx(2.0 / 3.0)


def test_metrics_accept_torch_and_reject_bad_shapes():
    t = torch.from_numpy(PRED)[None, None]
    assert rmse(t, torch.from_numpy(REF)[None, None]) == pytest.approx(math.sqrt(0.5))
    with pytest.raises(ValueError, match="differ in shape"):
        rmse(PRED, np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        rmse(np.zeros((2, 2, 2), np.float32), np.zeros((2, 2, 2), np.float32))
    assert math.isnan(rmse(np.zeros((2, 2), np.float32), REF))


def test_ssim_identical_and_constant_images():
    rng = np.random.default_rng(0)
    d = (1.0 + rng.random((24, 24))).astype(np.float32)
    assert ssim_depth(d, d) == pytest.approx(1.0, abs=1e-5)
    # constants 1 m and 2 m -> 0.1 and 0.2 after /10: zero variance, so
    # SSIM = (2 mu1 mu2 + C1) / (mu1^2 + mu2^2 + C1), C1 = 0.01^2
    a = np.full((24, 24), 1.0, np.float32)
    b = np.full((24, 24), 2.0, np.float32)
    expected = (2 * 0.1 * 0.2 + 1e-4) / (0.01 + 0.04 + 1e-4)
    assert ssim_depth(a, b) == pytest.approx(expected, rel=1e-4)


def test_ls_distance_step_edge():
    # pred has a unit step between columns 1 and 2, ref is flat: the max gradient
    # magnitude of pred is 1 in rows 0..2 of column 1 (row 3 has no lower
    # neighbour), so with a 5x5 window all 16 pixels see 1 -> L_S = 1; with 3x3
    # only columns 0..2 do -> 12/16.
    pred = np.zeros((4, 4), np.float32) + 1.0
    pred[:, 2:] = 2.0
    ref = np.ones((4, 4), np.float32)
    assert ls_distance(pred, ref) == pytest.approx(1.0, rel=1e-5)
    assert ls_distance(pred, ref, window=3) == pytest.approx(0.75, rel=1e-5)
    assert ls_distance(ref, ref) == pytest.approx(0.0, abs=1e-10)


def test_depth_metrics_keys_and_long_table():
    m = depth_metrics(PRED, REF)
    assert m["rmse_m"] == pytest.approx(math.sqrt(0.5))
    assert m["n_valid"] == 2
    assert math.isnan(m["ssim"])  # 2x2 is smaller than the 11x11 window
    df = to_long(m, dataset="d", scene="s", method="input")
    assert list(df.columns) == ["dataset", "scene", "method", "metric", "unit", "value"]
    assert df.set_index("metric").loc["rmse_m", "unit"] == "m"
    assert len(df) == len(m)


def _pose(angle_deg, t):
    a = math.radians(angle_deg)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = t
    return T


def test_pose_errors_hand_computed():
    T_ref = _pose(10.0, [1.0, 2.0, 3.0])
    T_est = _pose(40.0, [1.01, 2.02, 3.02])
    assert rotation_error_deg(T_est, T_ref) == pytest.approx(30.0)
    assert translation_error_cm(T_est, T_ref) == pytest.approx(3.0)
    batch = np.stack([T_est, T_ref])
    e = pose_errors(batch, np.stack([T_ref, T_ref]))
    assert e["rot_err_deg"] == pytest.approx(15.0)
    assert e["trans_err_cm"] == pytest.approx(1.5)
    with pytest.raises(ValueError, match="4, 4"):
        rotation_error_deg(np.eye(3), np.eye(4))
