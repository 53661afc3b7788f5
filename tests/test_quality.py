import numpy as np
import pytest

from depthgt.quality import error_stats


def test_error_stats_hand_computed():
    ref = np.array([[1.0, 2.0], [3.0, 0.0]], np.float32)
    est = np.array([[1.1, 0.0], [2.8, 5.0]], np.float32)
    s = error_stats(est, ref)
    # reference-valid pixels: (0,0), (0,1), (1,0); estimate valid on (0,0), (1,0)
    assert s["n_reference"] == 3 and s["n_both"] == 2
    assert s["mae_valid"] == pytest.approx((0.1 + 0.2) / 2, abs=1e-6)
    assert s["rmse_valid"] == pytest.approx(np.sqrt((0.01 + 0.04) / 2), abs=1e-6)
    assert s["mae_missing_counted"] == pytest.approx((0.1 + 2.0 + 0.2) / 3, abs=1e-6)
    assert s["completeness"] == pytest.approx(2 / 3)


def test_error_stats_shape_mismatch():
    with pytest.raises(ValueError, match="differ"):
        error_stats(np.zeros((2, 2)), np.zeros((3, 2)))
