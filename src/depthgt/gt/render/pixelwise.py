"""The compositor pixel by pixel, compiled: the CPU's path of
:func:`~depthgt.gt.render.compositor.composite_gt` (steps 2-5 of
:func:`~depthgt.gt.render.compositor.render_gt`).

The tensor compositor works on every cluster of a block at once: it writes a dozen
per-candidate and per-cluster arrays, copies the candidates that the frame agreement or
the leave-target-out render leaves out, and sends the pixels with several surfaces
(5 % of them on the shared recordings) through two dozen more tensor operations. Here
each pixel's candidates are read once, into buffers that stay in the L1 cache: the ones
left out are skipped as they are read (no copy), then the pixel's surfaces, its choice,
the plane fit of the chosen surface and its confidence follow on those buffers.

Written by hand because no library composites per pixel with a rule like this one
(PyTorch3D's compositors take a fixed number of points per pixel and blend them), and as
tensors the steps cost ~50 ns per candidate against ~15 here. The float arithmetic is the
tensors' operation by operation where a decision depends on it (the clusters, the reach,
the edge vote, in the candidates' precision); the plane fit sums in float64, as
:func:`~depthgt.gt.render.compositor._plane_fit_chosen` does. The result is the tensor
compositor's to float32 rounding (tests/test_render.py, tests/test_batched.py).
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba import types
from numba.extending import overload

__all__ = ["composite_pixels", "hypot", "rendered_candidates", "within_gap_bound"]


def hypot(a, b):
    """sqrt(a^2 + b^2) as ``torch.hypot`` computes it, in compiled code (below)."""
    return math.hypot(a, b)


@overload(hypot, jit_options={"cache": True, "nogil": True})
def _hypot(a, b):  # pragma: no cover (compiled)
    """In float32, the square root of the sum of the squares in float64, rounded once to
    float32: torch's (and glibc's hypotf's) result on float32 candidates (6 M random
    pairs over six decades: every one), in half the time of ``math.hypot``, which numba
    takes through the overflow-safe double routine. Other types: ``math.hypot``."""
    if a == types.float32 and b == types.float32:

        def f32(a, b):
            x, y = np.float64(a), np.float64(b)
            return np.float32(math.sqrt(x * x + y * y))

        return f32
    return lambda a, b: math.hypot(a, b)


@numba.njit(cache=True, nogil=True, inline="always")
def within_gap_bound(step, s_a, s_b, iz_a, gap_sigmas, gap_slope_rel):  # pragma: no cover (compiled)
    """True when the inverse-depth ``step`` between two samples is within the gap
    tolerance ``gap_sigmas * hypot(s_a, s_b) + gap_slope_rel * iz_a * apart`` (apart >= 0)
    by a bound that needs neither square root: |step| <= gap_sigmas * (|s_a| + |s_b|) / 2.
    The mean of the two stds is at most hypot(s_a, s_b) / sqrt(2), so the bound stays
    ~29 % below the tolerance's first term whatever the rounding, and the second term is
    >= 0 (or +inf) for gap_slope_rel >= 0 and 0 <= iz_a < inf (checked here). False
    where it cannot tell (a NaN, a step beyond the bound): the caller then computes the
    tolerance. The same decisions to the bit, and most samples of one surface skip both
    square roots."""
    if not (gap_sigmas >= 0 and gap_slope_rel >= 0 and iz_a >= 0 and iz_a < np.inf):
        return False
    return abs(step) <= gap_sigmas * ((abs(s_a) + abs(s_b)) * 0.5)


@numba.njit(cache=True, nogil=True, inline="always")
def _popcount(x):  # pragma: no cover (compiled)
    """The set bits of a uint64."""
    m = 0
    while x:
        x &= x - np.uint64(1)
        m += 1
    return m


@numba.njit(cache=True, nogil=True, inline="always")
def _cluster_stats(lo, hi, ox, oy, iz, d2):  # pragma: no cover (compiled)
    """Mean offset (x, y), mean inverse depth and smallest d2 of the pixel's buffered
    candidates ``[lo, hi)``, in their precision (the tensors' sums and divisions)."""
    zero = ox.dtype.type(0.0)
    sx = sy = sz = zero
    dmin = ox.dtype.type(np.inf)
    for q in range(lo, hi):
        sx += ox[q]
        sy += oy[q]
        sz += iz[q]
        dmin = min(dmin, d2[q])
    cnt = ox.dtype.type(hi - lo)
    return sx / cnt, sy / cnt, sz / cnt, dmin


@numba.njit(cache=True, nogil=True, inline="always")
def _reach(lo, hi, ox, oy, frame, mx, my, later_frames, n_frames, consts, r_frame):  # pragma: no cover
    """How far the buffered cluster ``[lo, hi)`` reaches beyond the sample position, opposite
    its centroid (+inf when centred), with the edge vote: the reach of the
    ceil(edge_vote x voters)-th farthest frame plus the slack, voters the frames seen on
    this cluster or behind it (``later_frames``, a bit mask). ``r_frame``: (J,) scratch."""
    edge_vote, slack, use_vote = consts[0], consts[1], consts[2] > 0
    real = ox.dtype.type
    one, zero = real(1.0), real(0.0)
    norm = hypot(mx, my)
    centred = norm <= real(1e-9)
    inv = one / max(norm, real(1e-12))
    ex = one if centred else mx * inv
    ey = zero if centred else my * inv
    t_min = real(np.inf)
    for f in range(n_frames):
        r_frame[f] = real(-np.inf)
    for q in range(lo, hi):
        t = ox[q] * ex + oy[q] * ey
        t_min = min(t_min, t)
        if use_vote:
            r_frame[frame[q]] = max(r_frame[frame[q]], -t)
    if centred:
        return real(np.inf)
    reach = -t_min
    if use_vote:
        voters = _popcount(later_frames)
        kk = int(math.ceil(edge_vote * real(voters)))
        kk = min(max(kk, 1), n_frames) - 1
        r_sorted = np.sort(r_frame[:n_frames])[::-1]  # descending; absent frames -inf, last
        reach = min(reach, r_sorted[kk] + slack)
    return reach


@numba.njit(cache=True, nogil=True, inline="always")
def _choose(
    n_cl, cl_lo, cl_hi, masks, qualified, own_cl, ox, oy, iz, d2, frame, n_frames, vote, rule, r_frame
):  # pragma: no cover
    """The visible cluster of one pixel (the rule of
    :func:`~depthgt.gt.render.compositor._choose_among`): (chosen or -1, ambiguous,
    inverse-depth step to the surface behind)."""
    margin, ambiguous_px, hit2 = rule[0], rule[1], rule[2]
    drop_ambiguous, extend_uncovered, resolves = rule[3] > 0, rule[4] > 0, rule[5] > 0
    zero = ox.dtype.type(0.0)
    front = -1
    for c in range(n_cl):
        if qualified[c]:
            front = c
            break
    if front < 0:
        front = 0
    behind = -1
    for c in range(front + 1, n_cl):
        if qualified[c]:
            behind = c
            break
    has_b = behind >= 0
    mx_f, my_f, iz_f, dn_f = _cluster_stats(cl_lo[front], cl_hi[front], ox, oy, iz, d2)
    mx_b = my_b = iz_b = dn_b = zero
    if has_b:
        mx_b, my_b, iz_b, dn_b = _cluster_stats(cl_lo[behind], cl_hi[behind], ox, oy, iz, d2)
    later = np.uint64(0)  # frames on each cluster or behind it, from the back
    reach_f = reach_b = zero
    for c in range(n_cl - 1, front - 1, -1):
        later |= masks[c]
        if c == behind:
            reach_b = _reach(cl_lo[c], cl_hi[c], ox, oy, frame, mx_b, my_b, later, n_frames, vote, r_frame)
    reach_f = _reach(cl_lo[front], cl_hi[front], ox, oy, frame, mx_f, my_f, later, n_frames, vote, r_frame)
    hit_f = dn_f <= hit2
    cov_f = reach_f >= margin or hit_f
    take_b = False
    step = zero
    if has_b:
        cov_b = reach_b >= margin or dn_b <= hit2
        take_b = (not cov_f) and (cov_b or dn_b < dn_f)
        step = abs(iz_f - iz_b)
    use = cov_f or has_b or extend_uncovered
    ambiguous = has_b and not hit_f and abs(reach_f - margin) < ambiguous_px
    chosen = -1
    if use and not (ambiguous and drop_ambiguous):
        chosen = behind if take_b else front
    if resolves and own_cl >= 0 and (chosen < 0 or ambiguous):
        chosen = own_cl
        ambiguous = False
    return chosen, ambiguous and chosen >= 0, step


@numba.njit(cache=True, nogil=True, inline="always")
def _fit(q_lo, q_hi, lx, ly, lz, lw, lwt, sv, lp, grad, support, step_iz, ambiguous, fit):  # pragma: no cover
    """The weighted plane of the chosen cluster (the pixel's buffers ``[q_lo, q_hi)``:
    offsets, inverse depths, spatial and inverse-variance weights, stds, points) and its
    confidence: depth, weight sum and sigma. The sums in float64 in one pass, as raw
    moments about the cluster's first inverse depth
    (:func:`~depthgt.gt.render.compositor._plane_fit_chosen` takes three passes about
    the mean: the same results to float32 rounding)."""
    lam, min_points, sigma_scale, need_sigma, max_sigma = fit[0], fit[1], fit[2], fit[3] > 0, fit[4]
    n = q_hi - q_lo
    z0 = np.float64(lz[q_lo])
    sw = s_z = s_x = s_y = s_gx = s_gy = wsum = 0.0
    s_xx = s_yy = s_xy = s_xz = s_yz = s_zz = s_ss = 0.0
    for q in range(q_lo, q_hi):
        w_sp = lw[q]
        w = np.float64(lwt[q])
        x, y, z = np.float64(lx[q]), np.float64(ly[q]), np.float64(lz[q]) - z0
        wx, wy, wz = w * x, w * y, w * z
        sw += w
        s_x += wx
        s_y += wy
        s_z += wz
        s_gx += w * grad[lp[q], 0]
        s_gy += w * grad[lp[q], 1]
        wsum += np.float64(w_sp)
        s_xx += wx * x
        s_yy += wy * y
        s_xy += wx * y
        s_xz += wx * z
        s_yz += wy * z
        s_zz += wz * z
        s_ss += w * np.float64(sv[q]) * np.float64(sv[q])
    has = sw > 0
    sw_safe = sw if has else 1.0
    mean_z, mean_x, mean_y = s_z / sw_safe, s_x / sw_safe, s_y / sw_safe
    cxx = s_xx / sw_safe - mean_x * mean_x
    cyy = s_yy / sw_safe - mean_y * mean_y
    cxy = s_xy / sw_safe - mean_x * mean_y
    cxz = s_xz / sw_safe - mean_x * mean_z
    cyz = s_yz / sw_safe - mean_y * mean_z
    slope_x, slope_y = plane_slopes(cxx, cyy, cxy, cxz, cyz, lam, s_gx / sw_safe, s_gy / sw_safe)
    c0 = mean_z - slope_x * mean_x - slope_y * mean_y  # the plane at the sample position, less z0
    iz_hat = z0 + c0
    good = has and n >= min_points and iz_hat > 0
    d = 1.0 / iz_hat if good else 0.0
    sg = 0.0
    if need_sigma:
        model = s_ss / sw_safe
        # the weighted mean square of z - (c0 + slope_x x + slope_y y), from the moments
        res2 = (
            s_zz
            + c0 * c0 * sw
            + slope_x * slope_x * s_xx
            + slope_y * slope_y * s_yy
            - 2.0 * c0 * s_z
            - 2.0 * slope_x * s_xz
            - 2.0 * slope_y * s_yz
            + 2.0 * c0 * slope_x * s_x
            + 2.0 * c0 * slope_y * s_y
            + 2.0 * slope_x * slope_y * s_xy
        ) / sw_safe
        res2 = max(res2, 0.0)
        sigma2 = confidence(
            model, res2, cxx, cyy, cxy, lam, mean_x, mean_y, support, d, ambiguous, step_iz, sigma_scale
        )
        sg = math.sqrt(sigma2) if good else 0.0
        if max_sigma >= 0 and not sg <= max_sigma:
            d = 0.0
    return d, wsum, sg


@numba.njit(cache=True, nogil=True, inline="always")
def _buffers(cap, like):  # pragma: no cover (compiled)
    """A pixel's buffers for ``cap`` candidates: offsets, inverse depths, d2, stds and
    the two weights (``like``'s dtype), points and frames; per cluster its first and end
    candidate, support, frames' bit mask, whether it qualifies and holds the target's
    own sample."""
    real = like.dtype
    return (
        np.empty(cap, real),
        np.empty(cap, real),
        np.empty(cap, real),
        np.empty(cap, real),
        np.empty(cap, real),
        np.empty(cap, real),
        np.empty(cap, real),
        np.empty(cap, np.int64),
        np.empty(cap, np.int64),
        np.empty(cap, np.int64),
        np.empty(cap, np.int64),
        np.empty(cap, np.int64),
        np.empty(cap, np.uint64),
        np.empty(cap, np.bool_),
        np.empty(cap, np.bool_),
    )


@numba.njit(cache=True, nogil=True, inline="always")
def plane_slopes(cxx, cyy, cxy, cxz, cyz, lam, mean_gx, mean_gy):  # pragma: no cover (compiled)
    """The slopes (x, y) of the weighted plane in inverse depth from the samples'
    centred second moments, with the normals' prior ``lam`` towards their mean tangent
    slopes (0, 0 where the system is singular)."""
    a11, a22 = cxx + lam, cyy + lam
    v1, v2 = cxz + lam * mean_gx, cyz + lam * mean_gy
    det = a11 * a22 - cxy * cxy
    if det > 1e-12:
        return (a22 * v1 - cxy * v2) / det, (a11 * v2 - cxy * v1) / det
    return 0.0, 0.0


@numba.njit(cache=True, nogil=True, inline="always")
def confidence(
    model, res2, cxx, cyy, cxy, lam, mean_x, mean_y, support, d, ambiguous, step_iz, sigma_scale
):  # pragma: no cover
    """sigma^2 of a pixel's depth ``d`` (render_gt's step 5): the mean model variance and
    the fit's residual over the distinct frames, times one plus the extrapolation to the
    sample position, plus half the step to the surface behind on an ambiguous pixel."""
    b11, b22 = cxx + lam + 1e-6, cyy + lam + 1e-6
    det = max(b11 * b22 - cxy * cxy, 1e-12)
    extrap = (b22 * mean_x * mean_x - 2 * cxy * mean_x * mean_y + b11 * mean_y * mean_y) / det
    var_iz = (model + res2) / max(np.float64(support), 1.0) * (1.0 + extrap)
    z2 = d * d
    sigma2 = sigma_scale * sigma_scale * z2 * z2 * var_iz
    if ambiguous:
        sigma2 += (0.5 * z2 * step_iz) ** 2
    return sigma2


@numba.njit(cache=True, nogil=True, inline="always")
def _rendered(p, first_pixel, wanted, stride, h, w):  # pragma: no cover (compiled)
    """Whether the block's pixel ``p`` is composited: among the ``wanted`` (B*H*W,)
    (empty: all) and on every ``stride``-th row and column of its image."""
    if wanted.shape[0] > 0 and not wanted[first_pixel + p]:
        return False
    if stride > 1:
        q_img = (first_pixel + p) % (h * w)
        return (q_img // w) % stride == 0 and (q_img % w) % stride == 0
    return True


@numba.njit(cache=True, nogil=True, inline="always")
def _past_off_rows(pixel, i, first_pixel, stride, h, w):  # pragma: no cover (compiled)
    """The first candidate at or after ``i`` whose pixel is not on a row that a render at
    ``stride`` leaves out: ``i`` itself on a rendered row, else the first candidate of
    the next rendered row (a binary search in the sorted ``pixel``: the rows left out
    hold half the candidates at stride 2, none of them read)."""
    if stride <= 1:
        return i
    q = first_pixel + pixel[i]
    row = (q % (h * w)) // w
    if row % stride == 0:
        return i
    nxt = q - q % (h * w) + (row + stride - row % stride) * w  # the next rendered row (or image)
    return i + np.searchsorted(pixel[i:], nxt - first_pixel)


@numba.njit(cache=True, nogil=True, inline="always")
def _run(pixel, i, first_pixel, wanted, stride, h, w):  # pragma: no cover (compiled)
    """The next pixel's run of candidates from ``i`` on, past the rows a render at
    ``stride`` leaves out: its first and its end, and whether the pixel is composited
    (:func:`_rendered`); (C, C, False) past the last."""
    n = pixel.shape[0]
    i = _past_off_rows(pixel, i, first_pixel, stride, h, w)
    if i >= n:
        return n, n, False
    p = pixel[i]
    j = i + 1
    while j < n and pixel[j] == p:
        j += 1
    return i, j, _rendered(p, first_pixel, wanted, stride, h, w)


@numba.njit(cache=True, nogil=True)
def rendered_candidates(pixel, first_pixel, wanted, stride, h, w):  # pragma: no cover (compiled)
    """(C',) int64 the candidates of the pixels :func:`composite_pixels` composites
    (``pixel`` (C,) sorted, within the block from ``first_pixel``; ``wanted``, ``stride``,
    ``h``, ``w`` as there), in order: the weights of a leave-target-out render (a quarter
    of the pixels at stride 2) or of chosen pixels are computed for these only."""
    n = pixel.shape[0]
    out = np.empty(n, np.int64)
    m = 0
    i = 0
    while i < n:
        i, j, composited = _run(pixel, i, first_pixel, wanted, stride, h, w)
        if composited:
            for k in range(i, j):
                out[m] = k
                m += 1
        i = j
    return out[:m]


@numba.njit(cache=True, nogil=True)
def composite_pixels(
    pixel,
    point,
    ox,
    oy,
    d2,
    iz,
    s,
    frame,
    grad,
    s_point,
    w_spatial,
    w_inv,
    n_pix,
    leave_out,
    where,
    wanted,
    gaps,
    vote,
    rule,
    limits,
    fit,
):  # pragma: no cover (compiled)
    """Depth, weight sum, count and sigma (n_pix,) of a block's pixels, composited one
    pixel at a time, and whether a chosen surface kept more than ``m`` samples (then the
    caller composites the block with the tensors, which keep the m nearest).

    Candidates (C,): ``pixel`` within the block (sorted; front first within a pixel),
    ``point``, ``ox``, ``oy``, ``d2``, ``iz``, ``s``, ``frame`` (C,) int64 below 64;
    ``grad`` (N, 2) the points' tangent-plane gradients (zero rows: none); ``s_point``
    (N,) the points' std in inverse depth to use instead of ``s`` (empty: ``s``);
    ``w_spatial``, ``w_inv`` (C,) the candidates' weights exp(-d2 / R^2) and that times
    (s_ref / s)^2 (with ``s_point``'s stds where given), vectorised by the caller: the
    tensor compositor's float operations; with ``compact`` those of the composited
    pixels' candidates only (:func:`rendered_candidates`), in order.

    leave_out (int64): frame left out (-1: none), target frame (-1: none), stride of the
    pixels rendered (1: all), the block's first pixel, image height and width, frames
    J, the agreement's tiles per frame, whether the weights are compact; where: (bad
    (slots,) bool, table (B*H*W,) int64) the frame agreement's bad (image, frame, tile)
    slots and each pixel's image-and-tile part (empty: nothing left out); wanted:
    (B*H*W,) bool the pixels to composite (empty: all; the others stay empty). gaps:
    gap_sigmas, gap_slope_rel;
    vote: edge_vote, edge_vote_slack_px, whether to vote; rule: edge_margin_px,
    ambiguous_px, HIT_PX^2, drop_ambiguous, extend_uncovered, target_resolves_ambiguous
    (all in the candidates' precision); limits: m, min_frames;
    fit: slope_prior, min_points, sigma_scale, need_sigma, max_sigma_m (< 0: none).

    Long because the pixel loop gathers and clusters into a dozen buffers and hands
    them on; the choice and the fit are their own functions.
    """
    skip, target, stride, first_pixel, h, w, n_frames, n_t, compact = leave_out
    bad, table = where
    gap_sigmas, gap_slope_rel = gaps
    m_cap, min_frames = limits
    hit2 = rule[2]
    has_bad = bad.shape[0] > 0
    alt = s_point.shape[0] > 0
    real = iz.dtype.type
    depth = np.zeros(n_pix, iz.dtype)
    weight_sum = np.zeros(n_pix, iz.dtype)
    count = np.zeros(n_pix, np.int64)
    sigma = np.zeros(n_pix, iz.dtype)
    cap = 64
    lx, ly, lz, ld, sv, lw, lwt, lp, lf, cl_lo, cl_hi, support, masks, qualified, own = _buffers(cap, iz)
    r_frame = np.empty(64, iz.dtype)
    capped = False
    n = pixel.shape[0]
    i = 0
    q = 0  # the candidates of the pixels composited before this one
    while i < n:
        i, j, composited = _run(pixel, i, first_pixel, wanted, stride, h, w)
        if not composited:
            i = j
            continue
        p = pixel[i]
        at_w = q - i if compact else 0  # the weights of candidate k: w_spatial[k + at_w]
        q += j - i
        if j - i > cap:
            cap = 2 * (j - i)
            lx, ly, lz, ld, sv, lw, lwt, lp, lf, cl_lo, cl_hi, support, masks, qualified, own = _buffers(cap, iz)
        # the pixel's candidates, less those left out, into the buffers; its clusters
        row = table[first_pixel + p] if has_bad else 0
        m = 0
        n_cl = 0
        for k in range(i, j):
            f = frame[k]
            if f == skip or (has_bad and bad[row + f * n_t]):
                continue
            sk = s_point[point[k]] if alt else s[k]
            x, y, z = ox[k], oy[k], iz[k]
            new = m == 0
            if not new and not within_gap_bound(lz[m - 1] - z, sv[m - 1], sk, lz[m - 1], gap_sigmas, gap_slope_rel):
                apart = hypot(x - lx[m - 1], y - ly[m - 1])
                tol = gap_sigmas * hypot(sv[m - 1], sk) + gap_slope_rel * lz[m - 1] * apart
                new = (lz[m - 1] - z) > tol
            if new:
                if n_cl > 0:
                    cl_hi[n_cl - 1] = m
                cl_lo[n_cl] = m
                masks[n_cl] = np.uint64(0)
                own[n_cl] = False
                n_cl += 1
            masks[n_cl - 1] |= np.uint64(1) << np.uint64(f)
            if f == target and d2[k] <= hit2:
                own[n_cl - 1] = True  # the target's own sample at the position
            lx[m], ly[m], lz[m], ld[m], sv[m], lp[m], lf[m] = x, y, z, d2[k], sk, point[k], f
            lw[m], lwt[m] = w_spatial[k + at_w], w_inv[k + at_w]
            m += 1
        if m == 0:
            i = j
            continue
        cl_hi[n_cl - 1] = m
        own_cl = -1
        for c in range(n_cl):
            support[c] = _popcount(masks[c])
            qualified[c] = support[c] >= min_frames or own[c]
            if own[c] and support[c] >= min_frames:
                own_cl = c  # the last own sample's surface, as the tensors write it
        if n_cl == 1 and rule[4] > 0:
            chosen, ambiguous, step = 0, False, real(0.0)
        else:
            chosen, ambiguous, step = _choose(
                n_cl,
                cl_lo,
                cl_hi,
                masks,
                qualified,
                own_cl,
                lx,
                ly,
                lz,
                ld,
                lf,
                n_frames,
                vote,
                rule,
                r_frame,
            )
        if chosen < 0:
            i = j
            continue
        q_lo, q_hi = cl_lo[chosen], cl_hi[chosen]
        if q_hi - q_lo > m_cap:
            capped = True
            i = j
            continue
        d, wsum, sg = _fit(q_lo, q_hi, lx, ly, lz, lw, lwt, sv, lp, grad, support[chosen], step, ambiguous, fit)
        depth[p] = d
        weight_sum[p] = wsum
        count[p] = q_hi - q_lo
        sigma[p] = sg
        i = j
    return depth, weight_sum, count, sigma, capped
