"""The refinement's residuals on the CPU, compiled: every pair's robust cost and normal
equations in one pass over its points.

:func:`depthgt.registration.refine._residuals_lazy` computes the same terms as tensors:
a dozen (pairs, points) planes, each written to memory and read back by the next step,
then the Jacobians (6 planes more) and their products. On one CPU thread that traffic,
not the arithmetic, sets its speed. Here each pair's points go through the warp, the
bilinear sample, the robust costs and the 6x6 normal equations in chunks of 256, each
phase over small planes that stay in the L1 cache (numba; no library fuses a warp, a
bilinear sample and a robust Gauss-Newton accumulation). The tensor path stays for GPUs
and is the reference the tests compare against: the same points associate, the costs
agree to float32 rounding, and the sums, which accumulate in float64 here,
to ~1e-5 of their largest entry.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch

__all__ = ["PairTerms", "pair_terms", "costs_seen_by_both", "kernel_maps", "point_residuals"]

#: the channels of a texel of the two maps the kernels sample (:class:`depthgt.registration.refine.Level`'s
#: ``geo`` and ``photo``, channels last): X (3), normals (3), normal validity and a 0 (8 floats, 32 bytes);
#: gray, its gradients (2) and a 0 (4 floats). The geometric term, a real recording's only one,
#: reads the first alone: a tap's channels lie in one aligned half of a cache line, where one
#: 40-byte texel of all ten crossed a line every second time (an evaluation 4-16 % faster
#: without the photometric term, as fast with it; docs/decisions.md "The refinement's
#: residuals compiled")
_GEO, _PHOTO = 8, 4
#: the sampled values (smp's rows): X (0-2), normals (3-5), gray (6), gx, gy (7, 8), validity (9)
_SAMPLED = 10


class PairTerms(NamedTuple):
    """Every pair's terms at one set of poses (:func:`pair_terms`).

    Attributes:
        cost_pts: (P, C N) float32 robust cost of every point that lands on a surface of
            the destination (the gate's cost beyond the gate), 0 elsewhere; C = 2 with
            the photometric term (geometric columns, then photometric), else 1.
        vis: (P, C N) bool, the points that land on a surface (likewise).
        pair_cost: (P,) float64 sums of ``cost_pts``; inliers: (P,) long, associated points.
        H_rel: (P, 6, 6), g_rel: (P, 6) float64 normal equations.
    """

    cost_pts: torch.Tensor
    vis: torch.Tensor
    pair_cost: torch.Tensor
    inliers: torch.Tensor
    H_rel: torch.Tensor
    g_rel: torch.Tensor


#: points per chunk: a chunk's planes (~40 x 4 bytes a point) stay in L1
_CHUNK = 256

# Rows of the chunk's planes. Each loop below writes one array (LLVM vectorises a loop
# only when it can rule out, in a few run-time checks, that its stores overlap its loads):
# pq: the warped points (qx, qy, qz, 1 / qz), their pixel (u, v), and ON: 1.0 where a
# valid source point in front of the camera lands within a pixel of the image
_ON = 6
# res: a term's scaled residuals (R), IRLS weights (W), costs (RHO); K: the geometric
# Jacobian's scale (1 / robust scale / |sampled normal|); SEEN (on a surface) and OK
# (associated), 1.0 or 0.0
_R, _W, _RHO, _K, _SEEN, _OK = 0, 1, 2, 3, 4, 5
# jw: the Jacobian rows d r / d (v, w) of the geometric (0-5) and photometric (6-11)
# terms, then each term's weight and weight x residual (0 unless associated)
_WG, _WRG, _WP, _WRP = 12, 13, 14, 15


@numba.njit(inline="always")
def _warp(points, b, start, m, pose, cam, h, w, pq):  # pragma: no cover (compiled)
    """b's valid points ``start`` .. ``start + m`` (:func:`_valid_first`) moved by
    ``pose`` (the 12 values of T_ab's rows) and projected (vectorised) into pq."""
    fx, fy, cx, cy = cam
    for i in range(m):
        n = start + i
        x, y, z = points[b, 0, n], points[b, 1, n], points[b, 2, n]
        qx = pose[0] * x + pose[1] * y + pose[2] * z + pose[3]
        qy = pose[4] * x + pose[5] * y + pose[6] * z + pose[7]
        qz = pose[8] * x + pose[9] * y + pose[10] * z + pose[11]
        zi = np.float32(1.0) / max(qz, np.float32(1e-6))
        u, v = fx * qx * zi + cx, fy * qy * zi + cy
        pq[0, i], pq[1, i], pq[2, i], pq[3, i], pq[4, i], pq[5, i] = qx, qy, qz, zi, u, v
        # beyond a pixel off the image grid_sample's taps are all padding (zeros)
        on = (qz > 1e-3) & (u > -1.0) & (u < w) & (v > -1.0) & (v < h)
        pq[_ON, i] = 1.0 if on else 0.0


@numba.njit(inline="always")
def _taps(texel0, h, w, m, pq, taps, tap_w):  # pragma: no cover (compiled)
    """Each point's four bilinear taps where ON, as grid_sample takes them (align_corners=False:
    pixel centres at integers; a tap off the image weighs 0, as its zero padding): their
    texels (``texel0`` + y w + x) into taps and their weights into tap_w (4, m); where not
    ON, weights 0 (vectorised, no branch)."""
    f32 = np.float32
    for i in range(m):
        on = pq[_ON, i] > 0
        u = pq[4, i] if on else f32(0.0)
        v = pq[5, i] if on else f32(0.0)
        x0, y0 = int(u + 1.0) - 1, int(v + 1.0) - 1  # floor (u, v > -1)
        ax, ay = u - x0, v - y0
        in_x0, in_x1, in_y0, in_y1 = x0 >= 0, x0 + 1 < w, y0 >= 0, y0 + 1 < h
        xa, xb, ya, yb = max(x0, 0), min(x0 + 1, w - 1), max(y0, 0), min(y0 + 1, h - 1)
        tap_w[0, i] = (1 - ax) * (1 - ay) if on & in_x0 & in_y0 else f32(0.0)
        tap_w[1, i] = ax * (1 - ay) if on & in_x1 & in_y0 else f32(0.0)
        tap_w[2, i] = (1 - ax) * ay if on & in_x0 & in_y1 else f32(0.0)
        tap_w[3, i] = ax * ay if on & in_x1 & in_y1 else f32(0.0)
        taps[0, i] = texel0 + ya * w + xa
        taps[1, i] = texel0 + ya * w + xb
        taps[2, i] = texel0 + yb * w + xa
        taps[3, i] = texel0 + yb * w + xb


@numba.njit(inline="always")
def _sample(geo, photo, texel0, h, w, m, pq, taps, tap_w, smp, with_photo):  # pragma: no cover (compiled)
    """The maps' channels bilinearly at (u, v) where ON into smp (10, m) (X, normals,
    gray, gx, gy, validity; zeros where not ON): the geometric texel's (``geo``) always,
    the photometric one's (``photo``) only with the photometric term, as nothing else reads
    them (without it, a real recording's default, an evaluation takes 12-16 % less time).
    Each texel's channels written out (a loop over a tuple of channels ran ~5 % slower)."""
    _taps(texel0, h, w, m, pq, taps, tap_w)
    for i in range(m):
        o0, o1, o2, o3 = taps[0, i] * _GEO, taps[1, i] * _GEO, taps[2, i] * _GEO, taps[3, i] * _GEO
        w0, w1, w2, w3 = tap_w[0, i], tap_w[1, i], tap_w[2, i], tap_w[3, i]
        for c in range(6):
            smp[c, i] = w0 * geo[o0 + c] + w1 * geo[o1 + c] + w2 * geo[o2 + c] + w3 * geo[o3 + c]
        smp[9, i] = w0 * geo[o0 + 6] + w1 * geo[o1 + 6] + w2 * geo[o2 + 6] + w3 * geo[o3 + 6]
    if with_photo:
        for i in range(m):
            o0, o1, o2, o3 = taps[0, i] * _PHOTO, taps[1, i] * _PHOTO, taps[2, i] * _PHOTO, taps[3, i] * _PHOTO
            w0, w1, w2, w3 = tap_w[0, i], tap_w[1, i], tap_w[2, i], tap_w[3, i]
            for c in range(3):
                smp[6 + c, i] = w0 * photo[o0 + c] + w1 * photo[o1 + c] + w2 * photo[o2 + c] + w3 * photo[o3 + c]


@numba.njit(inline="always")
def _geometric(pq, smp, m, ref_inv, gate, geo_scale, res):  # pragma: no cover (compiled)
    """The point-to-plane residuals (vectorised) into res: R, K, SEEN, OK."""
    f32 = np.float32
    for i in range(m):
        qx, qy, qz = pq[0, i], pq[1, i], pq[2, i]
        seen = (pq[_ON, i] > 0) & (smp[9, i] > 0.999)  # a pixel whose 3x3 neighbourhood is valid
        X2 = smp[2, i]
        n0, n1, n2 = smp[3, i], smp[4, i], smp[5, i]
        n_inv = f32(1.0) / np.sqrt(max(n0 * n0 + n1 * n1 + n2 * n2, f32(1e-12)))
        r_geo = (n0 * (qx - smp[0, i]) + n1 * (qy - smp[1, i]) + n2 * (qz - X2)) * n_inv
        # a disparity sensor's noise grows as z^2 beyond the reference depth: so do the
        # robust scale and the gate (ref_inv 0: constant)
        t = X2 * ref_inv
        sz = max(t * t, f32(1.0))
        gate_pt = gate * sz
        inv_geo = f32(1.0) / (geo_scale * sz)
        ok = seen & (abs(qz - X2) < gate_pt) & (abs(r_geo) < gate_pt)
        res[_R, i] = r_geo * inv_geo
        res[_K, i] = inv_geo * n_inv
        res[_SEEN, i] = 1.0 if seen else 0.0
        res[_OK, i] = 1.0 if ok else 0.0


@numba.njit(inline="always")
def _robust(res, m, huber):  # pragma: no cover (compiled)
    """IRLS weights W and costs RHO of the scaled residuals R (refine._robust's), one
    loop per kernel (Cauchy's log1p is a library call the other must not wait on)."""
    f32 = np.float32
    if huber:
        for i in range(m):
            a = abs(res[_R, i])
            k = min(a, f32(1.0))
            res[_W, i], res[_RHO, i] = f32(1.0) / max(a, f32(1.0)), (a - f32(0.5) * k) * k
    else:
        for i in range(m):
            a = abs(res[_R, i])
            res[_W, i], res[_RHO, i] = f32(1.0) / (f32(1.0) + a * a), f32(0.5) * np.log1p(a * a)


@numba.njit(inline="always")
def _costs(res, m, gate_cost, cost_out, vis_out, jw, w_row):  # pragma: no cover (compiled)
    """A term's costs (an associated point its robust cost, one seen beyond the gate the
    gate's cost, else 0) into cost_out and the points seen into vis_out (each m long);
    its weights and weight x residual into jw's rows ``w_row``, ``w_row + 1``. Returns
    the costs' sum (float64)."""
    f32 = np.float32
    total = 0.0
    for i in range(m):
        c = res[_RHO, i] if res[_OK, i] > 0 else (gate_cost if res[_SEEN, i] > 0 else f32(0.0))
        cost_out[i] = c
        total += c
    for i in range(m):
        vis_out[i] = res[_SEEN, i] > 0
    for i in range(m):
        ok = res[_OK, i] > 0
        jw[w_row, i] = res[_W, i] if ok else f32(0.0)
        jw[w_row + 1, i] = res[_W, i] * res[_R, i] if ok else f32(0.0)
    return total


@numba.njit(inline="always")
def _valid_first(points, src_gray, src_valid):  # pragma: no cover (compiled)
    """Each frame's valid points and their gray values moved to the front, in their order
    (F, 3, N), (F, N), with their columns (F, N) and counts (F,): the pairs' loops run
    over valid points only (a Kinect frame's holes are 10-30 % of its points; evaluating
    them cost as much as a valid point's terms). One pass, a small part of an evaluation."""
    F, N = src_valid.shape
    pts = np.empty((F, 3, N), np.float32)
    gray = np.empty((F, N), np.float32)
    cols = np.empty((F, N), np.int64)
    count = np.zeros(F, np.int64)
    for f in range(F):
        k = 0
        for n in range(N):
            if src_valid[f, n]:
                pts[f, 0, k], pts[f, 1, k], pts[f, 2, k] = points[f, 0, n], points[f, 1, n], points[f, 2, n]
                gray[f, k] = src_gray[f, n]
                cols[f, k] = n
                k += 1
        count[f] = k
    return pts, gray, cols, count


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _pair_terms_kernel(
    points, src_gray, src_valid, geo, photo_maps, h, w, pairs, T_ab, cam, scales, photo, huber,
    cost_pts, vis, pair_cost, inliers, H, g,
):  # fmt: skip  # pragma: no cover (compiled)
    """Long because a chunk's phases share its planes; each phase is a function or a
    short loop.

    points (F, 3, N) float32; src_gray (F, N); src_valid (F, N) bool; geo, photo_maps:
    the flat (F, h, w, 8) and (F, h, w, 4) float32 maps (:func:`kernel_maps`; channels
    last: a tap's channels are one read); pairs (P, 2) int64 (a, b): b's points into a's
    maps; T_ab (P, 12) float32, the rows of each relative pose; cam (fx, fy, cx, cy);
    scales (geo_scale_m, 1 / geo_ref_depth_m or 0, gate, sqrt(photo_weight) /
    photo_scale, gate cost). Writes cost_pts, vis (P, C N), pair_cost, inliers (P,), H
    (P, 6, 6) and g (P, 6).

    Each chunk of points runs in phases over small planes (warp, sample, residuals,
    costs, Jacobians, sums) rather than point by point: the element-wise phases
    vectorise, and a point's long chain of dependent steps no longer stalls the next.
    The sums reassociate (float64 over float32 terms; H's within a chunk of 256 points in
    float32): they round differently from the tensors' float32 products."""
    f32 = np.float32
    cam32 = (f32(cam[0]), f32(cam[1]), f32(cam[2]), f32(cam[3]))
    fx, fy = cam32[0], cam32[1]
    geo_scale, ref_inv, gate, wps = f32(scales[0]), f32(scales[1]), f32(scales[2]), f32(scales[3])
    gate_cost = f32(scales[4])
    n_pairs, N = pairs.shape[0], points.shape[2]
    pq = np.empty((7, _CHUNK), np.float32)
    taps = np.empty((4, _CHUNK), np.int64)  # the bilinear taps' texels
    tap_w = np.empty((4, _CHUNK), np.float32)  # and their weights
    smp = np.empty((_SAMPLED, _CHUNK), np.float32)
    res = np.empty((6, _CHUNK), np.float32)
    jw = np.zeros((16, _CHUNK), np.float32)  # the photometric rows stay 0 without the term
    c_chunk = np.empty(_CHUNK, np.float32)  # a term's costs and visibility before they
    v_chunk = np.empty(_CHUNK, np.bool_)  # go to their points' columns
    pts, gray, cols, count = _valid_first(points, src_gray, src_valid)
    cost_pts[:] = 0.0  # an invalid point: no cost, not seen
    vis[:] = False
    for p in range(n_pairs):
        a, b = pairs[p, 0], pairs[p, 1]
        texel0 = a * h * w
        acc = np.zeros(27)  # H's upper triangle row by row (21), then g (6)
        cost = 0.0
        n_in = 0
        for start in range(0, count[b], _CHUNK):
            m = min(_CHUNK, count[b] - start)
            _warp(pts, b, start, m, T_ab[p], cam32, h, w, pq)
            _sample(geo, photo_maps, texel0, h, w, m, pq, taps, tap_w, smp, photo)
            _geometric(pq, smp, m, ref_inv, gate, geo_scale, res)
            _robust(res, m, huber)
            cost += _costs(res, m, gate_cost, c_chunk, v_chunk, jw, _WG)
            for i in range(m):
                cost_pts[p, cols[b, start + i]] = c_chunk[i]
                vis[p, cols[b, start + i]] = v_chunk[i]
            for i in range(m):
                n_in += 1 if res[_OK, i] > 0 else 0
            for i in range(m):  # (n, q x n) / scale: d r / d (v, w), a left twist of T_ab
                qx, qy, qz, k, ok = pq[0, i], pq[1, i], pq[2, i], res[_K, i], res[_OK, i] > 0
                n0, n1, n2 = smp[3, i] * k, smp[4, i] * k, smp[5, i] * k
                jw[0, i] = n0 if ok else f32(0.0)
                jw[1, i] = n1 if ok else f32(0.0)
                jw[2, i] = n2 if ok else f32(0.0)
                jw[3, i] = qy * n2 - qz * n1 if ok else f32(0.0)
                jw[4, i] = qz * n0 - qx * n2 if ok else f32(0.0)
                jw[5, i] = qx * n1 - qy * n0 if ok else f32(0.0)
            if photo:
                for i in range(m):  # the intensity residuals (SEEN and OK are the geometric term's)
                    res[_R, i] = (smp[6, i] - gray[b, start + i]) * wps
                _robust(res, m, huber)
                cost += _costs(res, m, gate_cost, c_chunk, v_chunk, jw, _WP)
                for i in range(m):
                    cost_pts[p, N + cols[b, start + i]] = c_chunk[i]
                    vis[p, N + cols[b, start + i]] = v_chunk[i]
                for i in range(m):  # the image gradient chained with d(u, v)/dq of the projection
                    qx, qy, qz, zi, ok = pq[0, i], pq[1, i], pq[2, i], pq[3, i], res[_OK, i] > 0
                    gx, gy = smp[7, i] * fx * zi, smp[8, i] * fy * zi
                    gz = -(gx * qx + gy * qy) * zi
                    jw[6, i] = gx * wps if ok else f32(0.0)
                    jw[7, i] = gy * wps if ok else f32(0.0)
                    jw[8, i] = gz * wps if ok else f32(0.0)
                    jw[9, i] = (qy * gz - qz * gy) * wps if ok else f32(0.0)
                    jw[10, i] = (qz * gx - qx * gz) * wps if ok else f32(0.0)
                    jw[11, i] = (qx * gy - qy * gx) * wps if ok else f32(0.0)
            # the chunk's w J J^T and w J r (vectorised sums): J^T J's in float32 within
            # the chunk (16 lanes, no conversions: a tenth of the kernel's time), into
            # float64 across chunks; J^T r's in float64 (its terms cancel near the optimum)
            k = 0
            for r in range(6):
                for c in range(r, 6):
                    s = f32(0.0)
                    for i in range(m):
                        s += jw[_WG, i] * jw[r, i] * jw[c, i] + jw[_WP, i] * jw[6 + r, i] * jw[6 + c, i]
                    acc[k] += s
                    k += 1
            for r in range(6):
                s = 0.0
                for i in range(m):
                    s += jw[_WRG, i] * jw[r, i] + jw[_WRP, i] * jw[6 + r, i]
                acc[21 + r] += s
        pair_cost[p] = cost
        inliers[p] = n_in
        k = 0
        for r in range(6):
            for c in range(r, 6):
                H[p, r, c] = acc[k]
                H[p, c, r] = acc[k]
                k += 1
            g[p, r] = acc[21 + r]


def kernel_maps(geo: torch.Tensor, photo: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """A level's maps (:class:`~depthgt.registration.refine.Level`'s ``geo`` (F, 8, h, w)
    and ``photo`` (F, 4, h, w)) as the kernels read them: (F, h, w, 8) and (F, h, w, 4)
    float32 (no copy where the maps are float32 and channels last in memory)."""
    for name, maps, channels in (("geo", geo, _GEO), ("photo", photo, _PHOTO)):
        if maps.ndim != 4 or maps.shape[1] != channels:
            raise ValueError(f"pair_terms: the level's {name} maps need {channels} channels, got {tuple(maps.shape)}")
    if geo.shape[0] != photo.shape[0] or geo.shape[2:] != photo.shape[2:]:
        raise ValueError(f"pair_terms: geo {tuple(geo.shape)} and photo {tuple(photo.shape)} maps differ in size")
    return tuple(m.permute(0, 2, 3, 1).to(torch.float32).contiguous().numpy() for m in (geo, photo))


def _kernel_inputs(
    name: str,
    points: torch.Tensor,
    maps_hwc: tuple[np.ndarray, np.ndarray],
    K: torch.Tensor,
    T_ab: torch.Tensor,
    pairs: torch.Tensor,
) -> tuple:
    """The kernels' common arguments: the two flat maps, their (h, w), the pairs, the rows
    of each relative pose (P, 12) and the camera (fx, fy, cx, cy); raises unless the
    points are on the CPU."""
    if points.device.type != "cpu":
        raise ValueError(f"{name} runs on the CPU; the points are on {points.device.type}")
    Kd = K.to(torch.float64)
    return (
        maps_hwc[0].reshape(-1),
        maps_hwc[1].reshape(-1),
        maps_hwc[0].shape[1],
        maps_hwc[0].shape[2],
        pairs.to(torch.int64).contiguous().numpy(),
        T_ab[:, :3, :4].to(torch.float32).reshape(-1, 12).contiguous().numpy(),
        np.array([Kd[0, 0], Kd[1, 1], Kd[0, 2], Kd[1, 2]], np.float64),
    )


def pair_terms(
    points: torch.Tensor,
    gray: torch.Tensor,
    valid: torch.Tensor,
    maps_hwc: tuple[np.ndarray, np.ndarray],
    K: torch.Tensor,
    T_ab: torch.Tensor,
    pairs: torch.Tensor,
    *,
    geo_scale_m: float,
    geo_ref_depth_m: float,
    gate: float,
    photo_weight: float,
    photo_scale: float,
    huber: bool,
    gate_cost: float,
) -> PairTerms:
    """Every pair's terms (:class:`PairTerms`) at the relative poses ``T_ab`` (P, 4, 4):
    pair (a, b) = ``pairs[p]`` takes b's ``points`` (F, 3, N) (with their ``gray`` and
    ``valid`` (F, N)) into a's maps (``maps_hwc``, :func:`kernel_maps`) through the
    camera ``K`` (3, 3) of the maps' scale. The settings are
    :class:`~depthgt.registration.refine.LevelSettings`' with the association ``gate``
    (metres) and its cost. The normal equations come with the costs: in this pass they
    add about a fifth to its time. CPU tensors."""
    common = _kernel_inputs("pair_terms", points, maps_hwc, K, T_ab, pairs)
    n_pairs, N = pairs.shape[0], points.shape[2]
    photo = photo_weight > 0
    cols = 2 * N if photo else N
    cost_pts = np.empty((n_pairs, cols), np.float32)
    vis = np.empty((n_pairs, cols), np.bool_)
    pair_cost = np.empty(n_pairs, np.float64)
    inliers = np.empty(n_pairs, np.int64)
    H = np.empty((n_pairs, 6, 6), np.float64)
    g = np.empty((n_pairs, 6), np.float64)
    scales = np.array(
        [
            geo_scale_m,
            1.0 / geo_ref_depth_m if geo_ref_depth_m > 0 else 0.0,
            gate,
            math.sqrt(photo_weight) / photo_scale if photo else 0.0,
            gate_cost,
        ],
        np.float64,
    )
    _pair_terms_kernel(
        points.to(torch.float32).contiguous().numpy(),
        gray.to(torch.float32).contiguous().numpy(),
        valid.contiguous().numpy(),
        *common, scales, photo, huber,
        cost_pts, vis, pair_cost, inliers, H, g,
    )  # fmt: skip
    return PairTerms(
        torch.from_numpy(cost_pts),
        torch.from_numpy(vis),
        torch.from_numpy(pair_cost),
        torch.from_numpy(inliers),
        torch.from_numpy(H),
        torch.from_numpy(g),
    )


@numba.njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def _residuals_kernel(
    points, src_valid, geo, photo_maps, h, w, pairs, T_ab, cam, gate, ref_invs, r_geo, seen, ok,
):  # fmt: skip  # pragma: no cover (compiled)
    """Every point's point-to-plane residual (metres) into r_geo (P, N), whether it lands
    on a surface into seen (P, N), and whether it is associated into ok (R, P, N), with
    the gate growing beyond each reference depth of ``ref_invs`` (R,) (1 / metres; 0:
    constant): the phases of :func:`_pair_terms_kernel`, the same arithmetic, over every
    point (invalid ones: not seen)."""
    f32 = np.float32
    cam32 = (f32(cam[0]), f32(cam[1]), f32(cam[2]), f32(cam[3]))
    n_pairs, N = pairs.shape[0], points.shape[2]
    pq = np.empty((7, _CHUNK), np.float32)
    taps = np.empty((4, _CHUNK), np.int64)
    tap_w = np.empty((4, _CHUNK), np.float32)
    smp = np.empty((_SAMPLED, _CHUNK), np.float32)
    res = np.empty((6, _CHUNK), np.float32)
    for p in range(n_pairs):
        a, b = pairs[p, 0], pairs[p, 1]
        for start in range(0, N, _CHUNK):
            m = min(_CHUNK, N - start)
            _warp(points, b, start, m, T_ab[p], cam32, h, w, pq)
            for i in range(m):
                pq[_ON, i] = pq[_ON, i] if src_valid[b, start + i] else f32(0.0)
            _sample(geo, photo_maps, a * h * w, h, w, m, pq, taps, tap_w, smp, False)
            for k in range(ref_invs.shape[0]):
                # a robust scale of 1 (the residual unscaled), the gate with reference k
                _geometric(pq, smp, m, f32(ref_invs[k]), f32(gate), f32(1.0), res)
                for i in range(m):
                    ok[k, p, start + i] = res[_OK, i] > 0
            for i in range(m):
                seen[p, start + i] = res[_SEEN, i] > 0
            _geometric(pq, smp, m, f32(0.0), f32(gate), f32(1.0), res)
            for i in range(m):
                r_geo[p, start + i] = res[_R, i]


def point_residuals(
    points: torch.Tensor,
    valid: torch.Tensor,
    maps_hwc: tuple[np.ndarray, np.ndarray],
    K: torch.Tensor,
    T_ab: torch.Tensor,
    pairs: torch.Tensor,
    gate: float,
    ref_depths_m: list[float],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The point-to-plane residuals behind the refinement's residual statistics
    (:func:`depthgt.registration.refine.target_residual_stats`), compiled: for pair (a,
    b) = ``pairs[p]`` b's ``points`` (F, 3, N) (``valid`` (F, N)) warped by ``T_ab`` (P,
    4, 4) into a's maps (:func:`kernel_maps`) through ``K`` (3, 3). Returns r_geo (P, N)
    float32 metres, seen (P, N) bool (on a surface of a) and ok (R, P, N) bool (seen and
    within the association ``gate``, metres, grown as (z / ref)^2 beyond each of the R
    ``ref_depths_m``, 0: constant), as the tensor path (``refine._residuals_lazy``) finds
    them to float32 rounding. CPU tensors."""
    common = _kernel_inputs("point_residuals", points, maps_hwc, K, T_ab, pairs)
    n_pairs, N = pairs.shape[0], points.shape[2]
    r_geo = np.empty((n_pairs, N), np.float32)
    seen = np.empty((n_pairs, N), np.bool_)
    ok = np.empty((len(ref_depths_m), n_pairs, N), np.bool_)
    _residuals_kernel(
        points.to(torch.float32).contiguous().numpy(),
        valid.contiguous().numpy(),
        *common,
        float(gate),
        np.array([1.0 / r if r > 0 else 0.0 for r in ref_depths_m], np.float64),
        r_geo, seen, ok,
    )  # fmt: skip
    return torch.from_numpy(r_geo), torch.from_numpy(seen), torch.from_numpy(ok)


@numba.njit(cache=True, nogil=True)
def _costs_seen_by_both(old_cost, old_vis, rows, new_cost, new_vis, n_sets, c_old, c_new):  # pragma: no cover
    """Per set (its rows in turn, ``len(rows) / n_sets`` each): the float64 sums of the old
    and the new costs over the points visible in both (old's row ``rows[i]`` beside new's
    row i)."""
    per_set = rows.shape[0] // n_sets
    for k in range(n_sets):
        a = 0.0
        b = 0.0
        for i in range(k * per_set, (k + 1) * per_set):
            o = rows[i]
            for j in range(new_cost.shape[1]):
                if old_vis[o, j] and new_vis[i, j]:
                    a += old_cost[o, j]
                    b += new_cost[i, j]
        c_old[k] = a
        c_new[k] = b


def costs_seen_by_both(
    old_cost: torch.Tensor, old_vis: torch.Tensor, rows: torch.Tensor, new_cost: torch.Tensor, new_vis: torch.Tensor,
    n_sets: int,
) -> tuple[torch.Tensor, torch.Tensor]:  # fmt: skip
    """The Levenberg-Marquardt acceptance test's sums in one pass (CPU; the tensor path
    would make three (P, C N) temporaries): per set, the float64 sums (n_sets,) of the old
    costs ``old_cost[rows]`` and the new ``new_cost`` over the points that both ``old_vis[rows]``
    and ``new_vis`` see (:class:`PairTerms`' costs and visibility)."""
    c_old = np.empty(n_sets, np.float64)
    c_new = np.empty(n_sets, np.float64)
    _costs_seen_by_both(
        old_cost.contiguous().numpy(), old_vis.contiguous().numpy(), rows.to(torch.int64).contiguous().numpy(),
        new_cost.contiguous().numpy(), new_vis.contiguous().numpy(), n_sets, c_old, c_new,
    )  # fmt: skip
    return torch.from_numpy(c_old), torch.from_numpy(c_new)
