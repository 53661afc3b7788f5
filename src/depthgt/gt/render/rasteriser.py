"""The GT rasteriser: every (point, pixel) pair within the radius, sorted by pixel and,
within a pixel, front first (the candidates, :class:`RenderCandidates`).

It works in blocks of pixel rows (the images of a batch stacked): the points are sorted
front to back once and grouped by the rows they reach (a point within ``radius_px`` of
two blocks is in both), and each block's candidates are made in that order and sorted
by pixel on their own. A block's arrays stay in the cache between the steps and the
compositor takes them block by block (:func:`rasterise_blocks`); on a GPU the whole
batch is one block. :func:`rasterise_gt` concatenates the blocks.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numba
import numpy as np
import torch

from depthgt.geometry import project
from depthgt.gt.render.settings import RenderSettings
from depthgt.noise_law import KINECT_SIGMA_1M, depth_sigma_m
from depthgt.rasterise import _cells_inside, _footprint, check_points, front_to_back, resampled_positions
from depthgt.shapes import check_shape

__all__ = ["HIT_PX", "Cells", "RenderCandidates", "rasterise_blocks", "rasterise_gt"]

#: a surface with a sample this close to a pixel's sample position covers it (px)
HIT_PX = 0.05


class Cells(NamedTuple):
    """The compiled rasteriser's (point, pixel) pairs of one render (:func:`_front_first_cells`):
    ``starts`` (B*H*W + 1,) int64 each pixel's first pair, ``point`` (C,) int64 each pair's
    point, of a cloud whose first ``n_points`` points they cover. A later render of a
    cloud that begins with the same points in the same camera (the coverage step's render
    with views added) takes them (:func:`rasterise_blocks`' ``prior``) and finds the
    cells of its new points only."""

    starts: np.ndarray
    point: np.ndarray
    n_points: int


class RenderCandidates(NamedTuple):
    """The GT rasteriser's output (:func:`rasterise_gt`), the compositor's input
    (:func:`composite_gt`): every (point, pixel) pair whose projection lies strictly
    within ``radius_px`` of the pixel's sample position, sorted by pixel and, within a
    pixel, front first (decreasing inverse depth; ties in point order).

    Per candidate (C = their number):
        pixel: (C,) long index into the flattened (B*H*W) output pixels, ascending.
        point: (C,) long index into the flattened (B*N) points.
        ox, oy: (C,) the projection minus the pixel's sample position, px
            (differentiable w.r.t. the points).
        d2: (C,) ox^2 + oy^2, px^2 (differentiable).
        iz: (C,) the point's inverse depth 1/z, 1/m (differentiable).
        s: (C,) the point's expected std in inverse depth, 1/m (detached).
        frame: (C,) long frame index of the point, or None (no frame ids: each point
            counts as its own frame).
    Per point and per image:
        grad: (B*N, 2) screen-space gradient (d(1/z)/du, d(1/z)/dv) of each point's
            tangent plane (zero rows: no correction), or None (no normals).
        iz_point: (B*N,) inverse depth of every point, detached (other sigmas for the
            same candidates, :meth:`without_frame`).
        size: (B, H, W) of the output.
        n_frames: J = the largest frame id + 1 (0 without frame ids): the width of
            :attr:`GTRender.agreement`.
        first_pixel: the flat index of the block's first pixel (``pixel`` counts from
            it); n_pixels: the block's pixels (None: every pixel, B*H*W).
        cells: the compiled rasteriser's :class:`Cells` of the whole render (every
            block's), or None (the tensor path).
    """

    pixel: torch.Tensor
    point: torch.Tensor
    ox: torch.Tensor
    oy: torch.Tensor
    d2: torch.Tensor
    iz: torch.Tensor
    s: torch.Tensor
    frame: torch.Tensor | None
    grad: torch.Tensor | None
    iz_point: torch.Tensor
    size: tuple[int, int, int]
    n_frames: int
    first_pixel: int = 0
    n_pixels: int | None = None
    cells: Cells | None = None

    @property
    def pixels(self) -> int:
        """The pixels of this record (a block's, or all B*H*W)."""
        b, h, w = self.size
        return b * h * w if self.n_pixels is None else self.n_pixels

    def block(self, lo: int, hi: int, first_pixel: int, n_pixels: int) -> RenderCandidates:
        """The candidates ``lo:hi`` (views, no copy) as the block of the ``n_pixels``
        pixels from ``first_pixel`` on (their ``pixel`` counted from it)."""
        names = ("point", "ox", "oy", "d2", "iz", "s")
        picked = {k: getattr(self, k)[lo:hi] for k in names}
        shift = first_pixel - self.first_pixel
        pixel = self.pixel[lo:hi]
        return self._replace(
            **picked,
            pixel=pixel - shift if shift else pixel,
            frame=None if self.frame is None else self.frame[lo:hi],
            first_pixel=first_pixel,
            n_pixels=n_pixels,
        )

    def blocks(self, rows: int | None) -> list[RenderCandidates]:
        """This record cut into blocks of ``rows`` pixel rows (None or a block: itself)."""
        b, h, w = self.size
        if rows is None or self.n_pixels is not None or rows * w >= b * h * w:
            return [self]
        n_all = b * h * w
        edges = torch.arange(0, n_all + rows * w, rows * w, device=self.pixel.device).clamp_max(n_all)
        cut = torch.searchsorted(self.pixel, edges).tolist()
        p = edges.tolist()
        return [self.block(cut[i], cut[i + 1], p[i], p[i + 1] - p[i]) for i in range(len(p) - 1)]

    @staticmethod
    def concat(blocks: list[RenderCandidates]) -> RenderCandidates:
        """Blocks of consecutive pixels as one record of every pixel (pixels counted from 0)."""
        first = blocks[0]
        if len(blocks) == 1 and first.first_pixel == 0 and first.n_pixels is None:
            return first
        cat = {k: torch.cat([getattr(c, k) for c in blocks]) for k in ("point", "ox", "oy", "d2", "iz", "s")}
        frame = None if first.frame is None else torch.cat([c.frame for c in blocks])
        pixel = torch.cat([c.pixel + c.first_pixel for c in blocks])
        return first._replace(**cat, pixel=pixel, frame=frame, first_pixel=0, n_pixels=None)

    def select(self, index: torch.Tensor) -> RenderCandidates:
        """The candidates at ``index`` (C',) long (ascending keeps the sort); no
        :attr:`cells` (those are the whole render's)."""
        names = ("pixel", "point", "ox", "oy", "d2", "iz", "s")
        picked = {k: getattr(self, k).index_select(0, index) for k in names}
        frame = None if self.frame is None else self.frame.index_select(0, index)
        return self._replace(**picked, frame=frame, cells=None)

    def without_frame(self, frame: int, *, stride: int = 1, sigma_m: torch.Tensor | None = None) -> RenderCandidates:
        """The candidates of every frame but ``frame`` (the leave-target-out render's).

        Args:
            frame: the frame id to leave out (the candidates need frame ids).
            stride: keep only the pixels of every ``stride``-th row and column.
            sigma_m: (B, N) the points' depth sigmas in metres for these candidates
                (e.g. the noise law estimated without the left-out frame), or None
                (keep their sigmas).
        """
        if self.frame is None:
            raise ValueError("without_frame needs candidates with frame ids (render with frame=...)")
        b, h, w = self.size
        if sigma_m is not None and sigma_m.numel() != self.iz_point.numel():
            raise ValueError(
                f"sigma_m must hold one sigma per point ({self.iz_point.numel()}), got {tuple(sigma_m.shape)}"
            )
        with torch.no_grad():
            keep = self.frame != frame
            if stride > 1:
                on_grid = torch.zeros(b, h, w, dtype=torch.bool, device=self.pixel.device)
                on_grid[:, ::stride, ::stride] = True
                on_grid = on_grid.reshape(-1)[self.first_pixel : self.first_pixel + self.pixels]
                keep &= on_grid.index_select(0, self.pixel)
            out = self.select(keep.nonzero().squeeze(1))
            if sigma_m is not None:
                s_point = inverse_depth_std(sigma_m.detach().reshape(-1).to(self.iz_point.dtype), self.iz_point)
                out = out._replace(s=s_point.index_select(0, out.point))
        return out


def inverse_depth_std(sigma_m: torch.Tensor, iz: torch.Tensor) -> torch.Tensor:
    """(N,) std in inverse depth s = sigma_z / z^2 = sigma_z iz^2 (floored at 1e-12) of
    depth stds ``sigma_m`` (N,) metres at inverse depths ``iz`` (N,) 1/m."""
    return (sigma_m * iz**2).clamp_min(1e-12)


def _inverse_depth_planes(points_cam, normals_cam, K, st: RenderSettings) -> torch.Tensor:
    """(B*N, 2) screen-space gradient (d(1/z)/du, d(1/z)/dv) of each point's tangent plane.

    Plane n.X = n.p and X = z K^-1 [u, v, 1] give 1/z = (K^-T n) . [u, v, 1] / (n.p),
    affine in (u, v). Rows are zero (no correction) where the normal is missing, the
    plane is seen at a grazing angle, or the correction within R could exceed
    ``max_correction_rel``.
    """
    nrm = torch.nan_to_num(normals_cam, nan=0.0, posinf=0.0, neginf=0.0)
    # one plane per component ((B, N) each): a third of the time of the (B, N, 3) sums
    nx, ny, nz = nrm.unbind(-1)
    px, py, pz = points_cam.unbind(-1)
    d0 = nx * px + ny * py + nz * pz  # n.p
    ki = torch.linalg.inv(K.to(torch.float64)).to(points_cam.dtype)[..., None]  # (B, 3, 3, 1)
    kn_u = ki[:, 0, 0] * nx + ki[:, 1, 0] * ny + ki[:, 2, 0] * nz  # K^-T n, its first two components
    kn_v = ki[:, 0, 1] * nx + ki[:, 1, 1] * ny + ki[:, 2, 1] * nz
    safe = torch.where(d0.abs() > 1e-12, d0, torch.ones_like(d0))
    gu, gv = kn_u / safe, kn_v / safe
    with torch.no_grad():
        n_len = torch.sqrt(nx * nx + ny * ny + nz * nz)
        p_len = torch.sqrt(px * px + py * py + pz * pz)
        cos = d0.abs() / (n_len * p_len).clamp_min(1e-12)
        # |delta(1/z)| <= |grad| R; relative depth change ~ z |grad| R
        g_len = torch.sqrt(gu * gu + gv * gv)
        ok = ((cos >= st.min_cos_incidence) & (pz * g_len * st.radius_px <= st.max_correction_rel)).to(gu.dtype)
    return torch.stack([gu * ok, gv * ok], dim=-1).reshape(-1, 2)


@numba.njit(cache=True, nogil=True)
def _at_least(x, lo):  # pragma: no cover (compiled)
    """torch's clamp_min: NaN stays NaN."""
    return lo if x < lo else x


@numba.njit(cache=True, nogil=True)
def _points_in_view(points, normals, K, K_inv, valid, sigma, consts):  # pragma: no cover (compiled)
    """What the rasteriser needs of every point, in one compiled pass: uv (B*N, 2)
    projections (-inf behind the camera), inverse depth iz and its std s (B*N,), whether
    each is visible within the radius of the image (B*N,) bool, and its tangent plane's
    screen-space gradient (B*N, 2) (:func:`_inverse_depth_planes`; zeros without
    ``normals``, an empty array). The tensors' float arithmetic, operation by operation:
    the same values."""
    eps, u_lo, u_hi, v_lo, v_hi, min_cos, radius, max_corr, s_min, d_min, cl_min = consts
    b, n = points.shape[0], points.shape[1]
    uv = np.empty((b * n, 2), points.dtype)
    iz = np.empty(b * n, points.dtype)
    s = np.empty(b * n, points.dtype)
    ok = np.empty(b * n, np.bool_)
    grad = np.zeros((b * n, 2), points.dtype)
    with_planes = normals.shape[1] == n
    zero = points.dtype.type(0.0)
    one = points.dtype.type(1.0)
    for bi in range(b):
        k00, k01, k02, k11, k12 = K[bi, 0, 0], K[bi, 0, 1], K[bi, 0, 2], K[bi, 1, 1], K[bi, 1, 2]
        for j in range(n):
            i = bi * n + j
            px, py, pz = points[bi, j, 0], points[bi, j, 1], points[bi, j, 2]
            zs = _at_least(pz, eps)
            if pz > eps:
                u = k00 * px / zs + k01 * py / zs + k02
                v = k11 * py / zs + k12
            else:
                u = v = -np.inf
            uv[i, 0], uv[i, 1] = u, v
            q = one / _at_least(pz, eps)
            iz[i] = q
            s[i] = _at_least(sigma[bi, j] * (q * q), s_min)
            ok[i] = (
                valid[bi, j]
                and pz > eps
                and math.isfinite(u)
                and math.isfinite(v)
                and u > u_lo
                and u < u_hi
                and v > v_lo
                and v < v_hi
            )
            if not with_planes:
                continue
            nx, ny, nz = normals[bi, j, 0], normals[bi, j, 1], normals[bi, j, 2]
            nx = nx if math.isfinite(nx) else zero
            ny = ny if math.isfinite(ny) else zero
            nz = nz if math.isfinite(nz) else zero
            d0 = nx * px + ny * py + nz * pz
            kn_u = K_inv[bi, 0, 0] * nx + K_inv[bi, 1, 0] * ny + K_inv[bi, 2, 0] * nz
            kn_v = K_inv[bi, 0, 1] * nx + K_inv[bi, 1, 1] * ny + K_inv[bi, 2, 1] * nz
            safe = d0 if abs(d0) > d_min else one
            gu, gv = kn_u / safe, kn_v / safe
            n_len = math.sqrt(nx * nx + ny * ny + nz * nz)
            p_len = math.sqrt(px * px + py * py + pz * pz)
            cos = abs(d0) / _at_least(n_len * p_len, cl_min)
            g_len = math.sqrt(gu * gu + gv * gv)
            keep = one if (cos >= min_cos and pz * g_len * radius <= max_corr) else zero
            grad[i, 0], grad[i, 1] = gu * keep, gv * keep
    return uv, iz, s, ok, grad


class _Projected(NamedTuple):
    """The points as the rasteriser's blocks use them (:func:`_project`).

    uv: (B*N, 2) projections, px (differentiable); iz: (B*N,) inverse depth
    (differentiable); s: (B*N,) std in inverse depth (detached); frame: (B*N,) long or
    None; grad: (B*N, 2) or None (:func:`_inverse_depth_planes`); entries: the visible
    points' indices, block by block, front to back within a block; edges: the blocks'
    offsets into ``entries``; grid: the sample positions (columns (W,), rows (H,)) and
    their largest shift from the pixel centres; rows: pixel rows per block; visible:
    (B*N,) bool the points visible within the radius of the image.
    """

    uv: torch.Tensor
    iz: torch.Tensor
    s: torch.Tensor
    frame: torch.Tensor | None
    grad: torch.Tensor | None
    entries: torch.Tensor
    edges: list[int]
    grid: tuple[torch.Tensor, torch.Tensor, float]
    rows: int
    size: tuple[int, int, int]
    n_frames: int
    visible: torch.Tensor


def _sample_grid(size_hw, src_hw, device, dtype) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The pixels' sample positions (columns (W,), rows (H,)): their centres, or with
    ``src_hw`` the source pixels' (:func:`resampled_positions`), and the largest shift
    between the two (< 0.5 px)."""
    h, w = size_hw
    if src_hw is None:
        return torch.arange(w, device=device, dtype=dtype), torch.arange(h, device=device, dtype=dtype), 0.0
    gu = resampled_positions(int(src_hw[1]), w, device, dtype)
    gv = resampled_positions(int(src_hw[0]), h, device, dtype)
    shift = float(
        max(
            (gu - torch.arange(w, dtype=dtype, device=device)).abs().max(),
            (gv - torch.arange(h, dtype=dtype, device=device)).abs().max(),
        )
    )
    if shift >= 0.5:
        raise ValueError(f"sample positions must lie within 0.5 px of the pixel centres, got up to {shift:.3f}")
    return gu, gv, shift


def _project_compiled(points_cam, K, st: RenderSettings, valid, normals_cam, sigma_m, gu, gv):
    """:func:`_points_in_view` of the points (B, N, 3), their intrinsics (B, 3, 3),
    validity, normals (or None) and depth sigmas (B, N), on the sample grid (gu, gv):
    uv (B*N, 2), iz, s (B*N,), ok (B*N,) bool, planes (B*N, 2) (zeros without normals)."""
    dt = points_cam.dtype
    real = points_cam.detach().numpy().dtype.type  # a Python number meets a tensor in its dtype
    r = float(st.radius_px)
    # K^-1 as :func:`_inverse_depth_planes` takes it: in float64, then the points' dtype
    k_inv = torch.linalg.inv(K.to(torch.float64)).to(dt)
    normals = torch.zeros(points_cam.shape[0], 0, 3, dtype=dt) if normals_cam is None else normals_cam
    consts = (
        *(real(x) for x in (st.min_depth_m, float(gu[0]) - r, float(gu[-1]) + r, float(gv[0]) - r)),
        *(real(x) for x in (float(gv[-1]) + r, st.min_cos_incidence, st.radius_px, st.max_correction_rel)),
        *(real(x) for x in (1e-12, 1e-12, 1e-12)),
    )
    out = _points_in_view(
        *(t.detach().contiguous().numpy() for t in (points_cam, normals.to(dt), K.to(dt), k_inv, valid)),
        sigma_m.detach().to(dt).contiguous().numpy(),
        consts,
    )
    return tuple(torch.from_numpy(a) for a in out)


def _by_blocks(pid, v, bnh: tuple[int, int, int], rows: int, r: float, shift: float) -> tuple[torch.Tensor, list[int]]:
    """The visible points ``pid`` (front first) as entries of the blocks of ``rows`` pixel
    rows of the stacked images (B images of N points and H rows each, ``bnh``) that
    they reach, front first within a block, and the blocks' offsets into them; ``v``
    (B*N,) the points' rows."""
    b, n, h = bnh
    # every point in the blocks of its first and last candidate row (a point
    # reaches at most span rows: two blocks), front first within a block
    span = int(math.floor(2 * (r + shift))) + 1
    y0 = torch.ceil(v.index_select(0, pid) - r - shift).long()
    img = torch.div(pid, n, rounding_mode="floor") * h if b > 1 else 0
    k0 = torch.div(y0.clamp(0, h - 1) + img, rows, rounding_mode="floor")
    k1 = torch.div((y0 + span - 1).clamp(0, h - 1) + img, rows, rounding_mode="floor")
    twice = k1 != k0
    reps = 1 + twice.to(torch.long)
    entries = torch.repeat_interleave(pid, reps)
    block = torch.repeat_interleave(k0, reps)
    second = torch.cumsum(reps, 0) - 1  # the second entry of a point in two blocks
    block[second[twice]] = k1[twice]
    key = block.to(torch.int16 if block.numel() == 0 or int(block.max()) < 2**15 else torch.int32)
    order = torch.sort(key, stable=True).indices
    entries = entries.index_select(0, order)
    n_blocks = -(-(b * h) // rows)
    counts = torch.bincount(block, minlength=n_blocks)
    edges = [0, *torch.cumsum(counts, 0).tolist()]
    return entries, edges


def _project(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    st: RenderSettings,
    valid: torch.Tensor,
    normals_cam: torch.Tensor | None,
    sigma_m: torch.Tensor | None,
    frame: torch.Tensor | None,
    src_hw: tuple[int, int] | None,
    block_rows: int | None,
    compiled: bool = False,
    sort_from: int = 0,
) -> _Projected:
    """Project the points, order the visible ones front to back and group them by the
    blocks of ``block_rows`` pixel rows they reach (None: one block). ``compiled``: the
    projection, sigmas, visibility and planes in one compiled pass
    (:func:`_points_in_view`; CPU tensors with sigmas and no gradients) and the visible
    points put front to back by a compiled radix sort (:func:`_visible_front_to_back`;
    one block), the same values and order; ``sort_from``: the compiled sort's entries
    are the visible points from this index on only (the others' cells are known)."""
    b, n = points_cam.shape[:2]
    h, w = int(size_hw[0]), int(size_hw[1])
    dev, dt = points_cam.device, points_cam.dtype
    gu, gv, shift = _sample_grid((h, w), src_hw, dev, dt)
    r = float(st.radius_px)
    grads = torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in (points_cam, normals_cam, K))
    grad = None
    if compiled and sigma_m is not None and not grads:
        # compiled: the projection, the sigmas, the visibility and the tangent planes in
        # one pass over the points (:func:`_points_in_view`; the same values)
        uv_f, iz_all, s_all, ok, planes = _project_compiled(points_cam, K, st, valid, normals_cam, sigma_m, gu, gv)
        grad = None if normals_cam is None else planes
    else:
        uv, z = project(points_cam, K, eps=st.min_depth_m)
        uv_f, z_f = uv.reshape(-1, 2), z.reshape(-1)
        iz_all = 1.0 / z_f.clamp_min(st.min_depth_m)
        with torch.no_grad():
            if sigma_m is None:
                sig_1m = KINECT_SIGMA_1M if st.noise_sigma_1m is None else st.noise_sigma_1m
                sz = depth_sigma_m(z_f.detach(), sig_1m, st.noise_sigma_abs_m)
            else:
                sz = sigma_m.detach().reshape(-1).to(dt)
            s_all = inverse_depth_std(sz, iz_all.detach())
            u, v = uv_f[:, 0].detach(), uv_f[:, 1].detach()
            ok = valid.reshape(-1) & (z_f.detach() > st.min_depth_m) & torch.isfinite(u) & torch.isfinite(v)
            ok &= (u > float(gu[0]) - r) & (u < float(gu[-1]) + r) & (v > float(gv[0]) - r) & (v < float(gv[-1]) + r)
        if normals_cam is not None:
            grad = _inverse_depth_planes(points_cam, normals_cam, K, st)
    with torch.no_grad():
        v = uv_f[:, 1].detach()
        rows = b * h if block_rows is None else max(1, int(block_rows))
        bits = {torch.float32: np.uint32, torch.float64: np.uint64}.get(iz_all.dtype)
        if compiled and bits is not None and rows >= b * h:
            iz_bits = iz_all.detach().contiguous().numpy().view(bits)
            to_sort = ok.contiguous().numpy()
            if sort_from:
                to_sort = to_sort.copy()
                to_sort[:sort_from] = False
            pid = torch.from_numpy(_visible_front_to_back(to_sort, iz_bits, np.iinfo(bits).max))
        else:
            pid = ok.nonzero().squeeze(1)
            pid = pid.index_select(0, front_to_back(iz_all.detach().index_select(0, pid)))  # front first
        if rows >= b * h:
            entries, edges = pid, [0, pid.numel()]
        else:
            entries, edges = _by_blocks(pid, v, (b, n, h), rows, r, shift)
    n_frames = 0 if frame is None or frame.numel() == 0 else int(frame.max()) + 1
    fr = None if frame is None else frame.reshape(-1)
    grid = (gu, gv, shift)
    return _Projected(uv_f, iz_all, s_all, fr, grad, entries, edges, grid, rows, (b, h, w), n_frames, ok)


@numba.njit(cache=True, nogil=True)
def _visible_front_to_back(ok, bits, top):  # pragma: no cover (compiled)
    """(V,) int64 the visible points (``ok`` (P,) bool) front first: by the bit patterns
    ``bits`` (P,) of their inverse depths (unsigned, of the floats' width: positive
    floats order as their bits) decreasing, equal ones in index order; ``top`` the bits'
    largest value. :func:`~depthgt.rasterise.front_to_back`'s order of the visible
    points, by an LSD radix sort of bytes that skips the bytes every key shares: no
    library sorts float keys with their indices by radix on the CPU (torch sorts them by
    comparison; its integer sort of the same keys, with the ``nonzero`` and gathers
    around it, took 12 against 8 ms per 7-Scenes set)."""
    n_all = ok.shape[0]
    n_digits = bits.itemsize
    m = 0
    for i in range(n_all):
        m += 1 if ok[i] else 0
    keys = np.empty(m, bits.dtype)
    ids = np.empty(m, np.int64)
    j = 0
    for i in range(n_all):
        if ok[i]:
            keys[j] = top - bits[i]  # ascending keys: decreasing inverse depth
            ids[j] = i
            j += 1
    keys2 = np.empty(m, bits.dtype)
    ids2 = np.empty(m, np.int64)
    hist = np.zeros((n_digits, 257), np.int64)
    for j in range(m):
        k = keys[j]
        for d in range(n_digits):
            hist[d, ((k >> (8 * d)) & 255) + 1] += 1
    for d in range(n_digits):
        if m == 0 or hist[d, ((keys[0] >> (8 * d)) & 255) + 1] == m:
            continue  # every key has this byte
        at = hist[d]
        for q in range(256):
            at[q + 1] += at[q]
        for j in range(m):  # stable: equal bytes keep their order
            k = keys[j]
            q = (k >> (8 * d)) & 255
            t = at[q]
            keys2[t] = k
            ids2[t] = ids[j]
            at[q] = t + 1
        keys, keys2 = keys2, keys
        ids, ids2 = ids2, ids
    return ids


@numba.njit(cache=True, nogil=True)
def _front_first_cells(uv, ok, order, gu, gv, r, shift, r2, far, span, b, n, h, w):  # pragma: no cover
    """Every (point, pixel) pair whose sample position lies strictly within the radius of
    the point's projection, by pixel and, within a pixel, front first: ``starts`` (B H W
    + 1,) int64, the first pair of each pixel, and ``point`` (C,) int64, each pair's point.

    uv (P, 2): the projections (P = B N, ``n`` points per image); ok (P,) bool: the
    visible ones; order (V,): those front first (:func:`_visible_front_to_back`); gu (W,),
    gv (H,): the sample positions; r, shift: the radius and the largest shift of a sample
    position from its pixel centre; r2, far: the squared radius and the squared distance
    of a cell outside the image (in the points' precision); span: the footprint's side
    (:func:`~depthgt.rasterise._footprint`'s window, its float arithmetic).

    The same cells, in the same order, as :func:`_cells_sorted` (the same arithmetic), by
    a counting sort on the pixels in two passes: the cells found point by point in index
    order (a point's neighbours in memory are its neighbours in the image, so the
    counters stay in the cache), then each point's cells put into their pixels' next
    slots front first. Written by hand because no library rasterises every point within
    a radius into a pixel-sorted candidate list on the CPU (PyTorch3D's points
    rasteriser keeps the K nearest in depth and builds from source only), and as tensors
    the footprint test, its nonzero and the stable sort of ~2 M candidates per frame set
    took two thirds of the rasteriser.
    """
    n_all = uv.shape[0]
    n_pix = b * h * w
    starts = np.zeros(n_pix + 1, np.int64)
    dx2 = np.empty(span, uv.dtype)
    dy2 = np.empty(span, uv.dtype)
    cells = np.empty(order.shape[0] * span * span, np.int32)
    first = np.empty(n_all + 1, np.int64)  # each point's cells: cells[first[i]:first[i + 1]]
    zero = uv.dtype.type(0.0)
    m = 0
    for i in range(n_all):
        first[i] = m
        if not ok[i]:
            continue
        u, v = uv[i, 0], uv[i, 1]
        x0 = math.ceil(u - r - shift)
        y0 = math.ceil(v - r - shift)
        for j in range(span):  # the squared distances per column and row
            c = x0 + j
            d = gu[min(max(c, 0), w - 1)] - u
            dx2[j] = d * d + (far if (c < 0 or c >= w) else zero)
            c = y0 + j
            d = gv[min(max(c, 0), h - 1)] - v
            dy2[j] = d * d + (far if (c < 0 or c >= h) else zero)
        corner = ((i // n) * h + y0) * w + x0
        for jy in range(span):
            for jx in range(span):
                if dy2[jy] + dx2[jx] < r2:
                    p = corner + jy * w + jx
                    cells[m] = p
                    m += 1
                    starts[p + 1] += 1
    first[n_all] = m
    for p in range(n_pix):
        starts[p + 1] += starts[p]
    point = np.empty(starts[n_pix], np.int64)
    at = starts[:-1].copy()  # the next free slot of each pixel
    for k in range(order.shape[0]):
        i = order[k]
        for q in range(first[i], first[i + 1]):
            p = cells[q]
            point[at[p]] = i
            at[p] += 1
    return starts, point


@numba.njit(cache=True, nogil=True)
def _merged_cells(starts_a, point_a, starts_b, point_b, bits):  # pragma: no cover (compiled)
    """The cells of two renders of one cloud's points merged pixel by pixel: ``a``'s
    (:class:`Cells`) of its first points, ``b``'s of the others. Within a pixel front
    first as :func:`_front_first_cells` orders them: by the bit patterns ``bits`` of the
    points' inverse depths decreasing, equal ones in point order (a's points come
    first). A pass over the pairs, in place of finding and sorting the first points'
    cells again."""
    n_pix = starts_a.shape[0] - 1
    starts = np.empty(n_pix + 1, np.int64)
    point = np.empty(point_a.shape[0] + point_b.shape[0], np.int64)
    starts[0] = 0
    m = 0
    for p in range(n_pix):
        i, i_end = starts_a[p], starts_a[p + 1]
        j, j_end = starts_b[p], starts_b[p + 1]
        while i < i_end and j < j_end:
            if bits[point_b[j]] > bits[point_a[i]]:  # b's point in front
                point[m] = point_b[j]
                j += 1
            else:
                point[m] = point_a[i]
                i += 1
            m += 1
        while i < i_end:
            point[m] = point_a[i]
            i += 1
            m += 1
        while j < j_end:
            point[m] = point_b[j]
            j += 1
            m += 1
        starts[p + 1] = m
    return starts, point


@numba.njit(cache=True, nogil=True)
def _cell_values(starts, point, uv, iz, s, frame, gu, gv, h, w):  # pragma: no cover (compiled)
    """The candidates of :func:`_front_first_cells`' pairs in one pass over the pixels
    (row by row, so no division): pixel, ox, oy (the projection minus the sample
    position), d2 = ox^2 + oy^2, iz, s and frame (``frame`` empty: 0), as the tensor path
    computes them from the same values; the points' values read by point, so that a
    pixel's reads stay near the last pixel's."""
    n = point.shape[0]
    pixel = np.empty(n, np.int64)
    fr = np.empty(n, np.int64)
    ox = np.empty(n, uv.dtype)
    oy = np.empty(n, uv.dtype)
    d2 = np.empty(n, uv.dtype)
    izc = np.empty(n, uv.dtype)
    sc = np.empty(n, uv.dtype)
    with_frame = frame.shape[0] > 0
    for row in range((starts.shape[0] - 1) // w):
        y = gv[row % h]
        for c in range(w):
            p = row * w + c
            x = gu[c]
            for i in range(starts[p], starts[p + 1]):
                e = point[i]
                pixel[i] = p
                fr[i] = frame[e] if with_frame else 0
                dx = uv[e, 0] - x
                dy = uv[e, 1] - y
                ox[i] = dx
                oy[i] = dy
                d2[i] = dx * dx + dy * dy
                izc[i] = iz[e]
                sc[i] = s[e]
    return pixel, ox, oy, d2, izc, sc, fr


def _cells_sorted(u, v, x0, y0, off, ids, pr: _Projected, g_lo: int, g_hi: int, r: float):
    """:func:`_front_first_cells` as tensors (a GPU's path): (pixel within the block, entry,
    column, row of the stacked images) of every cell of the block's entries within ``r``,
    sorted by pixel and, within a pixel, in entry order."""
    b, h, w = pr.size
    n = pr.uv.shape[0] // b
    gu, gv, _ = pr.grid
    cols = x0[:, None] + off[None, :]
    rows = y0[:, None] + off[None, :]
    if b > 1:
        y0 = y0 + (torch.div(ids, n, rounding_mode="floor") * h - g_lo)  # the first row within the block
    else:
        y0 = y0 - g_lo
    # squared distances per axis; a column or row outside the image (or the block) gets
    # a huge one, so that the (P, span, span) sum below needs a single comparison
    far = 4.0 * r * r + 1.0
    dx2 = (gu[cols.clamp(0, w - 1)] - u[:, None]) ** 2 + ((cols < 0) | (cols >= w)) * far
    row_b = y0[:, None] + off[None, :]
    dy2 = (gv[rows.clamp(0, h - 1)] - v[:, None]) ** 2
    dy2 += ((rows < 0) | (rows >= h) | (row_b < 0) | (row_b >= g_hi - g_lo)) * far
    inside = (dy2[:, :, None] + dx2[:, None, :]) < r * r
    del dx2, dy2
    slot, oy, ox = _cells_inside(inside)
    del inside
    col = x0.index_select(0, slot) + ox
    row = y0.index_select(0, slot) + oy  # within the block
    pixel = row * w + col
    n_pix = (g_hi - g_lo) * w
    key = pixel.to(torch.int16) if n_pix < 2**15 else pixel.to(torch.int32)
    pixel, order = torch.sort(key, stable=True)  # by pixel, front first (stable: the entries' order)
    # the row of the stacked images (a gather: a third of the time of pixel // w)
    return pixel.long(), slot.index_select(0, order), col.index_select(0, order), row.index_select(0, order).add_(g_lo)


def _candidates(pr: _Projected, pixel, point, col, row, n_pix: int, first_pixel: int) -> RenderCandidates:
    """The candidates (pixel within the block, point, column and row of each, sorted)
    with their offsets, inverse depths, sigmas and frames as tensors (differentiable)."""
    gu, gv, _ = pr.grid
    # projection minus sample position, px (differentiable)
    ox = pr.uv[:, 0].index_select(0, point) - gu.index_select(0, col)
    oy = pr.uv[:, 1].index_select(0, point) - gv.index_select(0, row)
    return RenderCandidates(
        pixel,
        point,
        ox,
        oy,
        ox * ox + oy * oy,
        iz=pr.iz.index_select(0, point),
        s=pr.s.index_select(0, point),
        frame=None if pr.frame is None else pr.frame.index_select(0, point),
        grad=pr.grad,
        iz_point=pr.iz.detach(),
        size=pr.size,
        n_frames=pr.n_frames,
        first_pixel=first_pixel,
        n_pixels=n_pix,
    )


def _rasterise_block(pr: _Projected, k: int, radius_px: float) -> RenderCandidates:
    """The candidates of block ``k`` (its pixels counted from the block's first), its
    cells found as tensors (:func:`_cells_sorted`: a GPU's path, and the reference)."""
    b, h, w = pr.size
    r = float(radius_px)
    g_lo, g_hi = k * pr.rows, min((k + 1) * pr.rows, b * h)  # the block's rows of the stacked images
    with torch.no_grad():
        ids = pr.entries[pr.edges[k] : pr.edges[k + 1]]
        u = pr.uv[:, 0].detach().index_select(0, ids)
        v = pr.uv[:, 1].detach().index_select(0, ids)
        x0, y0, off = _footprint(u, v, r, pr.grid[2])
        pixel, slot, col, row = _cells_sorted(u, v, x0, y0, off, ids, pr, g_lo, g_hi, r)
        if b > 1:
            row = row % h
        point = ids.index_select(0, slot)
    return _candidates(pr, pixel, point, col, row, (g_hi - g_lo) * w, g_lo * w)


def _rasterise_compiled(pr: _Projected, radius_px: float, prior: Cells | None = None) -> RenderCandidates:
    """The candidates of every pixel, their cells found by :func:`_front_first_cells`
    (CPU tensors; the tensor path's candidates), their values by :func:`_cell_values`
    (with gradients wanted: as tensors). ``prior``: the cells of the first points, known
    (``pr.entries`` holds the others only): the others' cells are found and merged in."""
    b, h, w = pr.size
    gu, gv, shift = pr.grid
    r = float(radius_px)
    n_pix = b * h * w
    if n_pix >= 2**31:  # the kernel's cells are int32
        raise ValueError(f"too many pixels for one rasterisation: {n_pix}")
    uv = pr.uv.detach().contiguous().numpy()
    real = uv.dtype.type  # the tensors' precision
    visible = pr.visible.numpy()
    if prior is not None:
        visible = visible.copy()
        visible[: prior.n_points] = False
    starts, point = _front_first_cells(
        uv,
        visible,
        pr.entries.numpy(),
        gu.numpy(),
        gv.numpy(),
        real(r),
        real(shift),
        real(r * r),
        real(4.0 * r * r + 1.0),
        int(math.floor(2 * (r + shift))) + 1,  # as _footprint's
        b,
        pr.uv.shape[0] // b,
        h,
        w,
    )
    if prior is not None:
        bits = {np.dtype(np.float32): np.uint32, np.dtype(np.float64): np.uint64}[uv.dtype]
        iz_bits = pr.iz.detach().contiguous().numpy().view(bits)  # positive floats order as their bits
        starts, point = _merged_cells(prior.starts, prior.point, starts, point, iz_bits)
    cells = Cells(starts, point, pr.uv.shape[0])
    if not (torch.is_grad_enabled() and (pr.uv.requires_grad or pr.iz.requires_grad)):
        values = _cell_values(
            starts,
            point,
            uv,
            *(t.detach().contiguous().numpy() for t in (pr.iz, pr.s)),
            pr.frame.numpy() if pr.frame is not None else np.zeros(0, np.int64),
            gu.numpy(),
            gv.numpy(),
            h,
            w,
        )
        pixel, ox, oy, d2, iz, s, frame = (torch.from_numpy(a) for a in values)
        return RenderCandidates(
            pixel,
            torch.from_numpy(point),
            ox,
            oy,
            d2,
            iz=iz,
            s=s,
            frame=None if pr.frame is None else frame,
            grad=pr.grad,
            iz_point=pr.iz.detach(),
            size=pr.size,
            n_frames=pr.n_frames,
            cells=cells,
        )
    with torch.no_grad():
        pixel = torch.repeat_interleave(torch.arange(n_pix), torch.from_numpy(np.diff(starts)))
        col = pixel % w
        row = torch.div(pixel, w, rounding_mode="floor") % h
    return _candidates(pr, pixel, torch.from_numpy(point), col, row, None, 0)._replace(cells=cells)


def _check(points_cam, K, size_hw, valid, normals_cam, sigma_m, frame) -> torch.Tensor:
    valid = check_points(points_cam, K, valid, size_hw)
    sizes = {"B": points_cam.shape[0], "N": points_cam.shape[1]}
    for name, t, spec in (("normals_cam", normals_cam, "B N 3"), ("sigma_m", sigma_m, "B N"), ("frame", frame, "B N")):
        if t is not None:
            check_shape(t, spec, name, sizes)
    return valid


def rasterise_blocks(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    settings: RenderSettings = RenderSettings(),
    *,
    valid: torch.Tensor | None = None,
    normals_cam: torch.Tensor | None = None,
    sigma_m: torch.Tensor | None = None,
    frame: torch.Tensor | None = None,
    src_hw: tuple[int, int] | None = None,
    block_rows: int | None = None,
    compiled: bool | None = None,
    prior: Cells | None = None,
) -> list[RenderCandidates]:
    """Step 1 of :func:`~depthgt.gt.render.compositor.render_gt` in blocks of
    ``block_rows`` pixel rows of the stacked images (None: one block): each block's
    candidates with their inverse depths, sigmas and frames, sorted by pixel and front
    first. ``compiled``: the CPU's compiled cells (:func:`_front_first_cells`; default on the
    CPU) or the tensor path (a GPU's); the same candidates. ``prior``: the compiled
    cells (:attr:`RenderCandidates.cells`) of a render of these points' first
    ``prior.n_points`` -- the same points in the same camera, at this size and radius --
    so that only the others' cells are found (the compiled path; the tensor path
    finds them all); the same candidates. Other args: as :func:`rasterise_gt`."""
    valid = _check(points_cam, K, size_hw, valid, normals_cam, sigma_m, frame)
    if compiled is None:
        compiled = points_cam.device.type == "cpu"
    elif compiled and points_cam.device.type != "cpu":
        raise ValueError(f"the compiled rasteriser takes CPU tensors, got {points_cam.device.type}")
    if compiled:
        b, h, w = points_cam.shape[0], int(size_hw[0]), int(size_hw[1])
        if prior is not None and (prior.starts.shape[0] != b * h * w + 1 or prior.n_points > valid.numel()):
            raise ValueError(
                f"prior cells of {prior.starts.shape[0] - 1} pixels and {prior.n_points} points do not fit "
                f"a render of {b * h * w} pixels and {valid.numel()} points"
            )
        # every pixel at once (:func:`_front_first_cells`' counting sort needs no blocks: 12 %
        # faster on 7-Scenes than block by block), then cut into blocks (views)
        first = 0 if prior is None else prior.n_points
        pr = _project(points_cam, K, size_hw, settings, valid, normals_cam, sigma_m, frame, src_hw, None, True, first)
        return _rasterise_compiled(pr, settings.radius_px, prior).blocks(block_rows)
    pr = _project(points_cam, K, size_hw, settings, valid, normals_cam, sigma_m, frame, src_hw, block_rows)
    return [_rasterise_block(pr, k, settings.radius_px) for k in range(len(pr.edges) - 1)]


def rasterise_gt(
    points_cam: torch.Tensor,
    K: torch.Tensor,
    size_hw: tuple[int, int],
    settings: RenderSettings = RenderSettings(),
    *,
    valid: torch.Tensor | None = None,
    normals_cam: torch.Tensor | None = None,
    sigma_m: torch.Tensor | None = None,
    frame: torch.Tensor | None = None,
    src_hw: tuple[int, int] | None = None,
    compiled: bool | None = None,
) -> RenderCandidates:
    """Step 1 of :func:`~depthgt.gt.render.compositor.render_gt`: the candidates of every
    pixel, with their inverse depths, sigmas and frames, sorted by pixel and front first
    (:func:`rasterise_blocks`, the blocks concatenated).

    Args: as :func:`~depthgt.gt.render.compositor.render_gt`. Returns: :class:`RenderCandidates`.
    """
    blocks = rasterise_blocks(
        points_cam,
        K,
        size_hw,
        settings,
        valid=valid,
        normals_cam=normals_cam,
        sigma_m=sigma_m,
        frame=frame,
        src_hw=src_hw,
        block_rows=None,
        compiled=compiled,
    )
    return RenderCandidates.concat(blocks)
