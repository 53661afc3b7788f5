"""Plain, slow reference implementations of the renderers in :mod:`depthgt.gt.render`.

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


def render_gt_reference(points_cam, K, size_hw, valid=None, settings=None, normals_cam=None):
    """Loop version of ``render_gt`` for one image: points (N, 3), K (3, 3), normals (N, 3).

    ``settings`` is a ``depthgt.settings.RenderSettings``. Returns depth, weight_sum, count as (H, W)
    float64 / float64 / int arrays.
    """
    st = settings
    P = np.asarray(points_cam, dtype=np.float64)
    K = np.asarray(K, dtype=np.float64)
    Kinv = np.linalg.inv(K)
    h, w = size_hw
    n = len(P)
    valid = np.ones(n, bool) if valid is None else np.asarray(valid, bool)
    u, v, z = _project(P, K)
    R = st.radius_px
    use_planes = normals_cam is not None and st.plane_correction
    if use_planes:
        N = np.nan_to_num(np.asarray(normals_cam, dtype=np.float64))
    depth = np.zeros((h, w))
    wsum = np.zeros((h, w))
    count = np.zeros((h, w), int)
    for y in range(h):
        for x in range(w):
            cands = []  # dicts with d2, offset, z
            for i in range(n):
                if not valid[i] or not z[i] > st.min_depth_m:
                    continue
                d2 = (x - u[i]) ** 2 + (y - v[i]) ** 2
                if not d2 < R * R:
                    continue
                zc = z[i]
                if use_planes:
                    # the tangent plane n.X = n.p met by the ray through the pixel centre
                    nrm, p = N[i], P[i]
                    d0 = nrm @ p
                    cos = abs(d0) / max(np.linalg.norm(nrm) * np.linalg.norm(p), 1e-12)
                    grad = (Kinv.T @ nrm)[:2] / d0 if abs(d0) > 1e-12 else np.zeros(2)
                    if cos >= st.min_cos_incidence and z[i] * np.linalg.norm(grad) * R <= st.max_correction_rel:
                        ray = Kinv @ np.array([x, y, 1.0])
                        zc = d0 / (nrm @ ray)
                cands.append({"d2": d2, "off": np.array([x - u[i], y - v[i]]), "z": zc})
            if not cands:
                continue
            z_min = min(c["z"] for c in cands)
            band = lambda z0: z0 * (1 + st.rel_band) + st.abs_band_m  # noqa: E731
            front = [c for c in cands if c["z"] <= band(z_min)]
            behind = [c for c in cands if c["z"] > band(z_min)]
            centroid = np.linalg.norm(sum(c["off"] for c in front)) / len(front)
            z_ref = z_min
            if behind and st.ambiguous_band is not None:
                lo, hi = st.ambiguous_band
                if lo * R < centroid < hi * R:
                    continue  # an edge too close to the centre: left empty
            uncovered = centroid > st.coverage_frac * R  # F's samples sit on one side of the centre
            if uncovered and behind and st.compare_next_layer:
                z_b = min(c["z"] for c in behind)
                nxt = [c for c in behind if c["z"] <= band(z_b)]
                uncovered = centroid > np.linalg.norm(sum(c["off"] for c in nxt)) / len(nxt)
            if uncovered:
                if behind:
                    z_ref = min(c["z"] for c in behind)
                elif not st.extend_uncovered:
                    continue  # nothing seen there: the pixel stays empty
            layer = [c for c in cands if z_ref <= c["z"] <= band(z_ref)]
            layer = sorted(layer, key=lambda c: c["d2"])[: st.m]
            ws = [math.exp(-c["d2"] / (R * R)) for c in layer]
            count[y, x] = len(layer)
            wsum[y, x] = sum(ws)
            if len(layer) >= st.min_points and wsum[y, x] > 0:
                depth[y, x] = sum(wi * c["z"] for wi, c in zip(ws, layer)) / wsum[y, x]
    return depth, wsum, count
