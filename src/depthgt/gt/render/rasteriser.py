"""The GT rasteriser: every (point, pixel) pair within the radius, sorted by pixel and front first."""

from __future__ import annotations

from typing import NamedTuple

import torch

from depthgt.gt.render.settings import RenderSettings
from depthgt.noise_law import KINECT_SIGMA_1M, depth_sigma_m
from depthgt.rasterise import candidates, check_points, front_to_back, resampled_positions, sort_by_pixel

__all__ = ["RenderCandidates", "rasterise_gt"]


#: a surface with a sample this close to a pixel's sample position covers it (px)
_HIT_PX = 0.05


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

    def select(self, index: torch.Tensor) -> RenderCandidates:
        """The candidates at ``index`` (C',) long (ascending keeps the sort)."""
        names = ("pixel", "point", "ox", "oy", "d2", "iz", "s")
        picked = {k: getattr(self, k).index_select(0, index) for k in names}
        return self._replace(**picked, frame=None if self.frame is None else self.frame.index_select(0, index))

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
                keep &= on_grid.reshape(-1).index_select(0, self.pixel)
            out = self.select(keep.nonzero().squeeze(1))
            if sigma_m is not None:
                s_point = _inverse_depth_std(sigma_m.detach().reshape(-1).to(self.iz_point.dtype), self.iz_point)
                out = out._replace(s=s_point.index_select(0, out.point))
        return out


def _inverse_depth_std(sigma_m: torch.Tensor, iz: torch.Tensor) -> torch.Tensor:
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
    d0 = (nrm * points_cam).sum(-1)  # (B, N) n.p
    kn = torch.einsum("bji,bnj->bni", torch.linalg.inv(K.to(torch.float64)).to(points_cam.dtype), nrm)  # K^-T n
    safe = torch.where(d0.abs() > 1e-12, d0, torch.ones_like(d0))
    grad = kn[..., :2] / safe[..., None]
    with torch.no_grad():
        cos = d0.abs() / (nrm.norm(dim=-1) * points_cam.norm(dim=-1)).clamp_min(1e-12)
        z = points_cam[..., 2]
        # |delta(1/z)| <= |grad| R; relative depth change ~ z |grad| R
        ok = (cos >= st.min_cos_incidence) & (z * grad.norm(dim=-1) * st.radius_px <= st.max_correction_rel)
    return (grad * ok[..., None]).reshape(-1, 2)


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
) -> RenderCandidates:
    """Step 1 of :func:`render_gt`: the candidates of every pixel, with their inverse
    depths, sigmas and frames, sorted by pixel and front first (the points sorted by
    inverse depth once, :func:`depthgt.rasterise.front_to_back`, and the candidates made
    in that order, then one stable sort by pixel).

    Args: as :func:`render_gt`. Returns: :class:`RenderCandidates`.
    """
    valid = check_points(points_cam, K, valid, size_hw)
    b, n = points_cam.shape[:2]
    for name, t, shape in (
        ("normals_cam", normals_cam, (b, n, 3)),
        ("sigma_m", sigma_m, (b, n)),
        ("frame", frame, (b, n)),
    ):
        if t is not None and tuple(t.shape) != shape:
            raise ValueError(
                f"{name} must be {shape} to match points_cam {tuple(points_cam.shape)}, got {tuple(t.shape)}"
            )
    st = settings
    h, w = int(size_hw[0]), int(size_hw[1])
    dev, dt = points_cam.device, points_cam.dtype
    grid = None
    if src_hw is not None:
        grid = (resampled_positions(int(src_hw[1]), w, dev, dt), resampled_positions(int(src_hw[0]), h, dev, dt))
    z_all = points_cam[..., 2].reshape(-1)
    iz_all = 1.0 / z_all.clamp_min(st.min_depth_m)
    with torch.no_grad():  # the candidates come front first: one sort of the points, not of the candidates
        by_depth = front_to_back(iz_all)
    cand, _ = candidates(
        points_cam,
        K,
        valid,
        (h, w),
        radius_px=st.radius_px,
        min_depth=st.min_depth_m,
        grid_uv=grid,
        point_order=by_depth,
    )
    n_frames = 0 if frame is None or frame.numel() == 0 else int(frame.max()) + 1
    with torch.no_grad():
        if sigma_m is None:
            sig_1m = KINECT_SIGMA_1M if st.noise_sigma_1m is None else st.noise_sigma_1m
            sz = depth_sigma_m(z_all.detach(), sig_1m, st.noise_sigma_abs_m)
        else:
            sz = sigma_m.detach().reshape(-1).to(dt)
        s_all = _inverse_depth_std(sz, iz_all.detach())
    grad = None if normals_cam is None else _inverse_depth_planes(points_cam, normals_cam, K, st)
    with torch.no_grad():
        pixel, order = sort_by_pixel(cand.pixel)  # by pixel, front first (stable: the candidates' order)
    point = cand.point.index_select(0, order)
    # projection minus sample position, px
    ox, oy = (-cand.dx).index_select(0, order), (-cand.dy).index_select(0, order)
    d2 = ox * ox + oy * oy  # as the rasteriser computes it (dx^2 + dy^2, dx = -ox): bit for bit, cheaper than a gather
    fr = None if frame is None else frame.reshape(-1).index_select(0, point)
    return RenderCandidates(
        pixel,
        point,
        ox,
        oy,
        d2,
        iz=iz_all.index_select(0, point),
        s=s_all.index_select(0, point),
        frame=fr,
        grad=grad,
        iz_point=iz_all.detach(),
        size=(b, h, w),
        n_frames=n_frames,
    )
