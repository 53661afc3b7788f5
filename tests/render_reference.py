"""Plain, slow reference implementations of the renderers in :mod:`depthgt.render`.

Test oracles only: Python loops over pixels and points, float64 numpy, written
directly from the rules stated in the docstrings of ``splat_soft`` and ``render_gt``
without any of the vectorisation tricks (candidate windows, partial sorts).
Use them on tiny images (e.g. 16x16) only.
"""

from __future__ import annotations

import math

import numpy as np


def _project(points_cam: np.ndarray, K: np.ndarray):
    """(N, 3) points, (3, 3) K -> u, v, z arrays (u, v = nan behind the camera)."""
    z = points_cam[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * points_cam[:, 0] / z + K[0, 1] * points_cam[:, 1] / z + K[0, 2]
        v = K[1, 1] * points_cam[:, 1] / z + K[1, 2]
    return u, v, z


def splat_soft_reference(points_cam, features, K, size_hw, valid=None, radius_px=2.0, max_points=16,
                         depth_band_rel=0.05, min_depth=1e-3):
    """Loop version of ``splat_soft`` for one image: points (N, 3), features (N, C), K (3, 3).

    Returns features (C, H, W), depth (H, W), weight (H, W) as float64 arrays.
    """
    points_cam = np.asarray(points_cam, dtype=np.float64)
    features = np.asarray(features, dtype=np.float64)
    h, w = size_hw
    n, c = features.shape
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    u, v, z = _project(points_cam, np.asarray(K, dtype=np.float64))
    out_f = np.zeros((c, h, w))
    out_z = np.zeros((h, w))
    out_w = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            cands = []  # (z, weight, index)
            for i in range(n):
                if not valid[i] or not z[i] > min_depth:
                    continue
                d2 = (x - u[i]) ** 2 + (y - v[i]) ** 2
                if d2 < radius_px**2:
                    cands.append((z[i], (1 - d2 / radius_px**2) ** 2, i))
            if not cands:
                continue
            if depth_band_rel is not None:
                z_front = min(cz for cz, _, _ in cands)
                cands = [cd for cd in cands if cd[0] <= z_front * (1 + depth_band_rel)]
            cands = sorted(cands, key=lambda cd: cd[0])[:max_points]
            ws = sum(cw for _, cw, _ in cands)
            out_w[y, x] = ws
            out_z[y, x] = sum(cw * cz for cz, cw, _ in cands) / ws
            out_f[:, y, x] = sum(cw * features[i] for _, cw, i in cands) / ws
    return out_f, out_z, out_w
