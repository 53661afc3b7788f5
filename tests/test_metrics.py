"""Metrics on hand-computed cases: one depth-error vocabulary, one pose error."""

import math

import numpy as np
import pytest
import torch

from depthgt.eval.metrics import (
    DEPTH_ERRORS,
    METRIC_UNITS,
    PoseErrors,
    depth_errors,
    depth_metrics,
    input_valid_errors,
    ls_distance,
    pose_delta,
    pose_errors,
    ssim_depth,
    to_long,
)

PRED = np.array([[1.0, 2.0], [0.0, 4.0]], dtype=np.float32)
REF = np.array([[1.0, 3.0], [2.0, 0.0]], dtype=np.float32)


def test_depth_errors_hand_computed():
    e = depth_errors(PRED, REF)
    # both valid: (0,0) err 0, (0,1) err 1
    assert e["rmse_m"] == pytest.approx(math.sqrt(0.5))
    assert e["mae_m"] == pytest.approx(0.5)
    # reference valid: errors 0, 1, 2 (missing prediction counts as 0 m)
    assert e["rmse_missing_counted_m"] == pytest.approx(math.sqrt(5.0 / 3.0))
    assert e["mae_missing_counted_m"] == pytest.approx(1.0)
    assert e["completeness"] == pytest.approx(2.0 / 3.0)
    assert e["n_reference_px"] == 3 and e["n_both_px"] == 2
    assert list(e) == list(DEPTH_ERRORS)


def test_depth_errors_second_case_and_mask():
    ref = np.array([[1.0, 2.0], [3.0, 0.0]], np.float32)
    est = np.array([[1.1, 0.0], [2.8, 5.0]], np.float32)
    s = depth_errors(est, ref)
    assert s["mae_m"] == pytest.approx((0.1 + 0.2) / 2, abs=1e-6)
    assert s["rmse_m"] == pytest.approx(np.sqrt((0.01 + 0.04) / 2), abs=1e-6)
    assert s["mae_missing_counted_m"] == pytest.approx((0.1 + 2.0 + 0.2) / 3, abs=1e-6)
    masked = depth_errors(est, ref, mask=np.array([[True, False], [False, False]]))
    assert masked["n_reference_px"] == 1 and masked["mae_m"] == pytest.approx(0.1, abs=1e-6)


def test_depth_errors_accept_torch_and_reject_bad_shapes():
    t = torch.from_numpy(PRED)[None, None]
    assert depth_errors(t, torch.from_numpy(REF)[None, None])["rmse_m"] == pytest.approx(math.sqrt(0.5))
    with pytest.raises(ValueError, match="differ in shape"):
        depth_errors(PRED, np.zeros((3, 3), np.float32))
    with pytest.raises(ValueError, match=r"\(H, W\)"):
        depth_errors(np.zeros((2, 2, 2), np.float32), np.zeros((2, 2, 2), np.float32))
    assert math.isnan(depth_errors(np.zeros((2, 2), np.float32), REF)["rmse_m"])
    nan_est = PRED.copy()
    nan_est[0, 1] = np.nan  # non-finite = missing
    assert depth_errors(nan_est, REF)["n_both_px"] == 1


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


def test_fixed_masks_do_not_depend_on_the_method():
    """The denoising errors and the counted SSIM use one pixel set whatever the
    estimate covers; the both-valid values move with the estimate's holes."""
    rng = np.random.default_rng(1)
    ref = (2.0 + 0.1 * rng.random((24, 24))).astype(np.float32)
    inp = ref + 0.01
    inp[:4] = 0.0  # 96 input holes
    full = ref + 0.02  # fills every pixel, 2 cm off
    sparse = full.copy()
    sparse[10:14] = 0.0  # leaves 96 input-valid pixels empty
    a, b = input_valid_errors(full, ref, inp), input_valid_errors(sparse, ref, inp)
    assert a["n_input_valid_px"] == b["n_input_valid_px"] == 24 * 20
    assert a["mae_input_valid_m"] == pytest.approx(0.02, abs=1e-6)
    # the 96 empty pixels count with their reference depth (~2.05 m)
    expected = (0.02 * 384 + ref[10:14].astype(np.float64).sum()) / 480
    assert b["mae_input_valid_m"] == pytest.approx(expected, rel=1e-5)
    assert depth_errors(sparse, ref)["mae_m"] == pytest.approx(0.02, abs=1e-6)  # both-valid: blind to the hole
    assert ssim_depth(sparse, ref, missing_counted=True) < ssim_depth(sparse, ref) - 0.1
    assert ssim_depth(full, ref, missing_counted=True) == pytest.approx(ssim_depth(full, ref), abs=1e-7)
    m = depth_metrics(sparse, ref, inp)
    assert m["mae_input_valid_m"] == pytest.approx(b["mae_input_valid_m"]) and "ssim_missing_counted" in m
    assert "mae_input_valid_m" not in depth_metrics(sparse, ref)  # no input, no denoising mask
    with pytest.raises(ValueError, match="differ in shape"):
        input_valid_errors(full, ref, inp[:4])


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


def test_depth_metrics_keys_units_and_long_table():
    m = depth_metrics(PRED, REF)
    assert m["rmse_m"] == pytest.approx(math.sqrt(0.5))
    assert m["n_both_px"] == 2
    assert math.isnan(m["ssim"])  # 2x2 is smaller than the 11x11 window
    assert set(m) <= set(METRIC_UNITS)  # every metric has its unit
    assert all(METRIC_UNITS[k] == "m" for k in m if k.endswith("_m"))  # units in the names agree with the table
    df = to_long(m, dataset="d", scene="s", method="input")
    assert list(df.columns) == ["dataset", "scene", "method", "metric", "unit", "value"]
    assert df.set_index("metric").loc["rmse_m", "unit"] == "m"
    assert len(df) == len(m)
    with pytest.raises(KeyError, match="no unit"):
        to_long({"mae_valid": 1.0})


def _pose(angle_deg, t):
    a = math.radians(angle_deg)
    T = np.eye(4)
    T[:2, :2] = [[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]]
    T[:3, 3] = t
    return T


def test_pose_errors_hand_computed():
    T_ref = _pose(10.0, [1.0, 2.0, 3.0])
    T_est = _pose(40.0, [1.01, 2.02, 3.02])
    e = pose_errors(T_est, T_ref)
    assert isinstance(e, PoseErrors)
    assert float(e.rot_err_deg) == pytest.approx(30.0)
    assert float(e.trans_err_cm) == pytest.approx(3.0)
    batch = np.stack([T_est, T_ref])
    r, t = pose_errors(torch.from_numpy(batch), np.stack([T_ref, T_ref]))  # torch in, unpacks as a pair
    assert r.shape == (2,) and r[1] == pytest.approx(0.0, abs=1e-6)
    assert pose_errors(batch, np.stack([T_ref, T_ref])).mean() == pytest.approx(
        {"rot_err_deg": 15.0, "trans_err_cm": 1.5}
    )
    dt, dr = pose_delta(_pose(90.0, [0.0, 3.0, 4.0]))
    assert float(dt) == pytest.approx(5.0) and float(dr) == pytest.approx(90.0)
    with pytest.raises(ValueError, match="4, 4"):
        pose_errors(np.eye(3), np.eye(4))
