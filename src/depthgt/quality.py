"""Error of a depth image against a reference depth (GT quality, leave-target-out).

Conventions: depth in metres, 0 = missing. Three numbers answer different questions:

* ``mae_valid``/``rmse_valid``: over pixels where both the estimate and the reference
  are valid: is the estimate accurate where it has data?
* ``mae_missing_counted``: over pixels where the reference is valid, a missing
  estimate counting as predicting 0 (its error is the reference depth): accuracy and
  completeness in one number.
* ``completeness``: fraction of reference-valid pixels that the estimate covers.
"""

from __future__ import annotations

import numpy as np


def error_stats(estimate_m: np.ndarray, reference_m: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float]:
    """Error statistics of ``estimate_m`` against ``reference_m`` (both (H, W) metres).

    Args:
        mask: optional (H, W) bool restricting the pixels considered.

    Returns:
        dict with mae_valid, rmse_valid, mae_missing_counted, rmse_missing_counted,
        completeness (all metres or fractions), n_reference, n_both (pixel counts).
    """
    if estimate_m.shape != reference_m.shape:
        raise ValueError(f"estimate {estimate_m.shape} and reference {reference_m.shape} differ in shape")
    ref_ok = reference_m > 0
    if mask is not None:
        ref_ok &= mask
    est_ok = estimate_m > 0
    both = ref_ok & est_ok
    n_ref, n_both = int(ref_ok.sum()), int(both.sum())
    nan = float("nan")
    err = np.abs(estimate_m.astype(np.float64) - reference_m)
    err_counted = np.where(est_ok, err, reference_m.astype(np.float64))[ref_ok]
    return {
        "mae_valid": float(err[both].mean()) if n_both else nan,
        "rmse_valid": float(np.sqrt((err[both] ** 2).mean())) if n_both else nan,
        "mae_missing_counted": float(err_counted.mean()) if n_ref else nan,
        "rmse_missing_counted": float(np.sqrt((err_counted**2).mean())) if n_ref else nan,
        "completeness": n_both / n_ref if n_ref else nan,
        "n_reference": n_ref,
        "n_both": n_both,
    }
