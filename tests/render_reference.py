"""Plain, slow reference implementations of the renderers in :mod:`depthgt.gt.render`.

Test oracles only: Python loops over pixels and points, float64 numpy, written
directly from the rules stated in the docstrings of ``splat_soft`` and ``render_gt``
(and of ``RenderSettings``) without any of the vectorisation tricks (candidate
windows, composite-key sorts, scatter reductions, closed-form per-pixel solves).
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


def splat_soft_reference(
    points_cam, features, K, size_hw, valid=None, radius_px=2.0, max_points=16, depth_band_rel=0.05, min_depth=1e-3
):
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


def _resampled(n_src: int, n_dst: int) -> np.ndarray:
    """Position (output px) of the source pixel centre nearest to each output pixel centre."""
    i = np.clip(np.floor((np.arange(n_dst) + 0.5) * n_src / n_dst), 0, n_src - 1)
    return (i + 0.5) * n_dst / n_src - 0.5


def render_gt_reference(
    points_cam,
    K,
    size_hw,
    valid=None,
    settings=None,
    normals_cam=None,
    sigma_m=None,
    frame=None,
    src_hw=None,
    target_frame=None,
):
    """Loop version of ``render_gt`` for one image: points (N, 3), K (3, 3), normals (N, 3),
    sigma_m (N,), frame (N,), written from the rules of its docstring and of
    ``RenderSettings``.

    Returns depth, weight_sum, count, sigma as (H, W) float64 / float64 / int / float64
    arrays and the (J,) agreement share of every frame (NaN where not measured).
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
    gu = np.arange(w, dtype=np.float64) if src_hw is None else _resampled(src_hw[1], w)
    gv = np.arange(h, dtype=np.float64) if src_hw is None else _resampled(src_hw[0], h)
    # per-point inverse depth, its std, and the tangent-plane gradient of inverse depth
    iz = 1.0 / np.maximum(z, st.min_depth_m)
    if sigma_m is None:
        s1 = 0.0012 if st.noise_sigma_1m is None else st.noise_sigma_1m
        sz = np.sqrt(st.noise_sigma_abs_m**2 + (s1 * z * z) ** 2)
    else:
        sz = np.asarray(sigma_m, dtype=np.float64)
    s_iz = np.maximum(sz * iz * iz, 1e-12)
    grads = np.zeros((n, 2))
    if normals_cam is not None:
        N = np.nan_to_num(np.asarray(normals_cam, dtype=np.float64))
        for i in range(n):
            d0 = N[i] @ P[i]
            if abs(d0) <= 1e-12:
                continue
            g = (Kinv.T @ N[i])[:2] / d0
            cos = abs(d0) / max(np.linalg.norm(N[i]) * np.linalg.norm(P[i]), 1e-12)
            if cos >= st.min_cos_incidence and z[i] * np.linalg.norm(g) * R <= st.max_correction_rel:
                grads[i] = g

    def near(y, x):
        """Indices (ascending) of the points whose projection lies in the square of half
        side R around the sample position: a superset of those within R, so that the
        loops below apply the exact rules to a few points instead of all (only the
        number of points visited changes, not the result)."""
        with np.errstate(invalid="ignore"):
            inside = (np.abs(u - gu[x]) <= R * (1 + 1e-9)) & (np.abs(v - gv[y]) <= R * (1 + 1e-9))
        return np.flatnonzero(inside).tolist()

    def pixel_candidates(y, x, use):
        out = []
        for i in near(y, x):
            if not use[i] or not z[i] > st.min_depth_m:
                continue
            o = np.array([u[i] - gu[x], v[i] - gv[y]])  # projection minus sample position
            d2 = o @ o
            if d2 < R * R:
                out.append(dict(i=i, o=o, d2=d2, iz=iz[i], s=s_iz[i], f=i if frame is None else int(frame[i])))
        return out

    # frames that disagree with the target's own samples are left out
    n_fr = 0 if frame is None else int(np.max(frame)) + 1
    agreement = np.full(n_fr, np.nan)
    if target_frame is not None and frame is not None:
        # the target's own sample at each position
        t_iz, t_s = np.full((h, w), np.nan), np.zeros((h, w))
        cands_at = {}
        for y in range(h):
            for x in range(w):
                cands_at[y, x] = pixel_candidates(y, x, valid)
                tgt = [c for c in cands_at[y, x] if c["f"] == target_frame and c["d2"] <= 0.05**2]
                if tgt:
                    t_iz[y, x], t_s[y, x] = tgt[-1]["iz"], tgt[-1]["s"]  # (one target sample per position)
        # positions judged: a target sample, and (agreement_edge_px) no edge or hole of the
        # target within that many px (max - min of its inverse depth beyond the tolerance)
        e = st.agreement_edge_px
        judged_at = np.isfinite(t_iz)
        if e > 0:
            for y in range(h):
                for x in range(w):
                    if not judged_at[y, x]:
                        continue
                    win = t_iz[max(0, y - e) : y + e + 1, max(0, x - e) : x + e + 1]
                    tol = st.gap_sigmas * math.sqrt(2.0) * t_s[y, x] + st.gap_slope_rel * t_iz[y, x] * 2 * e
                    judged_at[y, x] = bool(np.isfinite(win).all()) and win.max() - win.min() <= tol
        tile = st.agreement_tile_px
        ty, tx = (-(-h // tile), -(-w // tile)) if tile > 0 else (1, 1)
        n_cmp_t, n_ok_t = np.zeros((n_fr, ty, tx)), np.zeros((n_fr, ty, tx))
        for y in range(h):
            for x in range(w):
                if not judged_at[y, x]:
                    continue
                for c in cands_at[y, x]:
                    if c["f"] != target_frame and c["d2"] <= 0.5**2:
                        tol = st.gap_sigmas * np.hypot(c["s"], t_s[y, x]) + st.gap_slope_rel * c["iz"] * math.sqrt(
                            c["d2"]
                        )
                        k = (c["f"], y // tile, x // tile) if tile > 0 else (c["f"], 0, 0)
                        n_cmp_t[k] += 1
                        n_ok_t[k] += abs(c["iz"] - t_iz[y, x]) <= tol
        n_cmp, n_ok = n_cmp_t.sum((1, 2)), n_ok_t.sum((1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            agreement = np.where(n_cmp >= 200, n_ok / np.maximum(n_cmp, 1), np.nan)  # judged on >= 200 samples
        bad = agreement < st.min_frame_agreement
        if tile > 0:
            # each tile judged on its 3x3 tile neighbourhood (>= 50 comparisons, else the
            # frame's decision); a frame below min_whole_frame_agreement is out everywhere
            bad_t = np.zeros((n_fr, ty, tx), bool)
            for f in range(n_fr):
                for i in range(ty):
                    for j in range(tx):
                        nc = n_cmp_t[f, max(0, i - 1) : i + 2, max(0, j - 1) : j + 2].sum()
                        no = n_ok_t[f, max(0, i - 1) : i + 2, max(0, j - 1) : j + 2].sum()
                        bad_t[f, i, j] = no < st.min_frame_agreement * nc if nc >= 50 else bad[f]
                bad_t[f] |= agreement[f] < st.min_whole_frame_agreement
        else:
            bad_t = bad[:, None, None]

        def dropped(i, y, x):  # a sample of a frame whose tile at this pixel disagrees
            return bool(bad_t[int(frame[i]), y // tile, x // tile] if tile > 0 else bad_t[int(frame[i]), 0, 0])
    else:

        def dropped(i, y, x):
            return False

    depth = np.zeros((h, w))
    wsum = np.zeros((h, w))
    count = np.zeros((h, w), int)
    sigma = np.zeros((h, w))
    for y in range(h):
        for x in range(w):
            cands = []
            for i in near(y, x):
                if not valid[i] or not z[i] > st.min_depth_m or dropped(i, y, x):
                    continue
                o = np.array([u[i] - gu[x], v[i] - gv[y]])  # projection minus sample position
                d2 = o @ o
                if d2 < R * R:
                    cands.append(dict(i=i, o=o, d2=d2, iz=iz[i], s=s_iz[i], f=i if frame is None else int(frame[i])))
            if not cands:
                continue
            # surfaces: gaps in inverse depth, front first
            cands = sorted(cands, key=lambda c: -c["iz"])
            clusters = [[cands[0]]]
            for a, b in zip(cands[:-1], cands[1:]):
                tol = st.gap_sigmas * np.hypot(a["s"], b["s"]) + st.gap_slope_rel * a["iz"] * np.linalg.norm(
                    a["o"] - b["o"]
                )
                if a["iz"] - b["iz"] > tol:
                    clusters.append([])
                clusters[-1].append(b)
            qualified = [
                len({c["f"] for c in cl}) >= st.min_frames
                or (
                    target_frame is not None
                    and frame is not None
                    and any(c["f"] == target_frame and c["d2"] <= 0.05**2 for c in cl)
                )
                for cl in clusters
            ]
            fi = qualified.index(True) if any(qualified) else 0
            bi = next((k for k in range(fi + 1, len(clusters)) if qualified[k]), None)

            def geometry(ci, clusters=clusters):  # called within this iteration only
                cl = clusters[ci]
                offs = np.array([c["o"] for c in cl])
                cen = offs.mean(0)
                norm = np.linalg.norm(cen)
                reach = np.inf if norm <= 1e-9 else -min(offs @ (cen / norm))
                if st.edge_vote > 0 and frame is not None and norm > 1e-9:
                    # each frame's own reach (-inf: a frame seen only behind this surface);
                    # the k-th largest (k = ceil(edge_vote x voters)) plus the slack
                    voters = {c["f"] for later in clusters[ci:] for c in later}
                    per_frame = sorted(
                        (
                            -min(np.array([c["o"] for c in cl if c["f"] == f]) @ (cen / norm))
                            if any(c["f"] == f for c in cl)
                            else -np.inf
                            for f in voters
                        ),
                        reverse=True,
                    )
                    k = min(max(math.ceil(st.edge_vote * len(per_frame)), 1), len(per_frame))
                    reach = min(reach, per_frame[k - 1] + st.edge_vote_slack_px)
                d_near = min(c["d2"] for c in cl)
                hit = d_near <= 0.05**2
                return reach, d_near, hit, (reach >= st.edge_margin_px) or hit

            reach_f, dn_f, hit_f, cov_f = geometry(fi)
            chosen = fi
            if bi is not None and not cov_f:
                _, dn_b, _, cov_b = geometry(bi)
                if cov_b or dn_b < dn_f:
                    chosen = bi
            ambiguous = bi is not None and not hit_f and abs(reach_f - st.edge_margin_px) < st.ambiguous_px
            if not (cov_f or bi is not None or st.extend_uncovered) or (ambiguous and st.drop_ambiguous):
                chosen = None
            if (
                st.target_resolves_ambiguous
                and target_frame is not None
                and frame is not None
                and (chosen is None or ambiguous)
            ):
                # the target's own sample at the position decides, on a surface of >= min_frames frames
                own = [
                    k
                    for k, cl in enumerate(clusters)
                    if any(c["f"] == target_frame and c["d2"] <= 0.05**2 for c in cl)
                    and len({c["f"] for c in cl}) >= st.min_frames
                ]
                if own:
                    chosen, ambiguous = own[0], False
            if chosen is None:
                continue
            kept = sorted(clusters[chosen], key=lambda c: c["d2"])[: st.m]  # stable: ties keep point order
            wsp = np.array([math.exp(-c["d2"] / (R * R)) for c in kept])
            s = np.array([c["s"] for c in kept])
            wt = wsp / s**2
            offs = np.array([c["o"] for c in kept])
            izs = np.array([c["iz"] for c in kept])
            g = np.array([grads[c["i"]] for c in kept])
            sw = wt.sum()
            mean_o = (wt[:, None] * offs).sum(0) / sw
            cen = offs - mean_o
            C = (wt[:, None, None] * cen[:, :, None] * cen[:, None, :]).sum(0) / sw
            if st.plane == "fit":
                lam = st.slope_prior
                A = C + lam * np.eye(2)
                b = (wt[:, None] * cen * (izs - (wt * izs).sum() / sw)[:, None]).sum(0) / sw + lam * (
                    wt[:, None] * g
                ).sum(0) / sw
                slope = np.linalg.solve(A, b) if np.linalg.det(A) > 1e-12 else np.zeros(2)
                iz_hat = (wt * izs).sum() / sw - slope @ mean_o
                resid = izs - (iz_hat + offs @ slope)
            elif st.plane == "normals":
                izc = izs - (g * offs).sum(1)
                iz_hat = (wt * izc).sum() / sw
                resid = izc - iz_hat
            else:
                iz_hat = (wt * izs).sum() / sw
                resid = izs - iz_hat
            count[y, x] = len(kept)
            wsum[y, x] = wsp.sum()
            if len(kept) < st.min_points or not iz_hat > 0:
                continue
            zz = 1.0 / iz_hat
            n_frames = len({c["f"] for c in kept})
            A = C + (st.slope_prior + 1e-6) * np.eye(2)
            extrap = mean_o @ np.linalg.solve(A, mean_o)
            var_iz = ((wt * s**2).sum() / sw + (wt * resid**2).sum() / sw) / max(n_frames, 1) * (1 + extrap)
            sig2 = 0.53**2 * zz**4 * var_iz  # 0.53: the documented calibration of the error model
            if ambiguous:
                iz_f = np.mean([c["iz"] for c in clusters[fi]])
                iz_b = np.mean([c["iz"] for c in clusters[bi]])
                sig2 += (0.5 * zz * zz * abs(iz_f - iz_b)) ** 2
            sigma[y, x] = math.sqrt(sig2)
            if st.max_sigma_m is not None and sigma[y, x] > st.max_sigma_m:
                continue
            depth[y, x] = zz
    return depth, wsum, count, sigma, agreement
