"""Weighted Procrustes alignment of 3D correspondences (R&R's alignment step).

All functions are batched over pairs: points (B, N, 3) in metres, weights (B, N) >= 0.
Transforms are (B, 4, 4) and map ``points_src`` onto ``points_dst``
(``T_src_to_dst``). The SVD runs in float64 for accuracy and a stable gradient; the
result is cast back to the input dtype.
"""

from __future__ import annotations

import torch

from depthgt.shapes import check_shape

__all__ = ["weighted_procrustes", "weighted_residual", "procrustes_random_subsets"]


def _check(points_src: torch.Tensor, points_dst: torch.Tensor, weights: torch.Tensor) -> None:
    sizes = check_shape(points_src, "B N 3", "points_src")
    check_shape(points_dst, "B N 3", "points_dst", sizes)
    check_shape(weights, "B N", "weights", sizes)


def weighted_procrustes(
    points_src: torch.Tensor, points_dst: torch.Tensor, weights: torch.Tensor, eps: float = 1e-12
) -> torch.Tensor:
    """Rigid transform minimising ``sum_i w_i |R p_i + t - q_i|^2`` (Kabsch/Umeyama, no scale).

    Written by hand because kornia has no weighted, batched rigid Procrustes with a
    reflection fix; the SVD itself is torch's.

    Args:
        points_src: (B, N, 3) points p (metres).
        points_dst: (B, N, 3) corresponding points q.
        weights: (B, N) non-negative weights; a pair with all-zero weights returns
            the identity.

    Returns:
        (B, 4, 4) ``T_src_to_dst`` in the input dtype; differentiable with respect to
        all inputs.
    """
    _check(points_src, points_dst, weights)
    dtype = points_src.dtype
    p = points_src.double()
    q = points_dst.double()
    w = weights.double().clamp(min=0)
    wsum = w.sum(dim=1, keepdim=True)  # (B, 1)
    wn = w / wsum.clamp(min=eps)
    mu_p = (wn[..., None] * p).sum(dim=1)  # (B, 3)
    mu_q = (wn[..., None] * q).sum(dim=1)
    pc = p - mu_p[:, None]
    qc = q - mu_q[:, None]
    cov = torch.einsum("bn,bni,bnj->bij", wn, qc, pc)  # (B, 3, 3) = sum w q p^T
    # A tiny isotropic term keeps the SVD gradient finite for degenerate (planar,
    # collinear) sets without moving the optimum of well-posed ones.
    cov = cov + 1e-12 * torch.eye(3, dtype=cov.dtype, device=cov.device)
    U, _, Vh = torch.linalg.svd(cov)
    d = torch.sign(torch.linalg.det(U @ Vh))  # reflection fix
    d = torch.where(d == 0, torch.ones_like(d), d)
    D = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], dim=-1))
    R = U @ D @ Vh
    t = mu_q - (R @ mu_p[..., None])[..., 0]
    T = torch.eye(4, dtype=torch.float64, device=p.device).repeat(p.shape[0], 1, 1)
    T = torch.cat([torch.cat([R, t[..., None]], dim=2), T[:, 3:]], dim=1)
    ok = (wsum[:, 0] > eps)[:, None, None]
    T = torch.where(ok, T, torch.eye(4, dtype=torch.float64, device=p.device).expand_as(T))
    return T.to(dtype)


def weighted_residual(
    T_src_to_dst: torch.Tensor,
    points_src: torch.Tensor,
    points_dst: torch.Tensor,
    weights: torch.Tensor,
    eps: float = 1e-12,
) -> torch.Tensor:
    """Weighted mean squared residual ``sum w |T p - q|^2 / sum w`` per pair, (B,) in m^2."""
    _check(points_src, points_dst, weights)
    R = T_src_to_dst[:, :3, :3].to(points_src.dtype)
    t = T_src_to_dst[:, :3, 3].to(points_src.dtype)
    res = ((points_src @ R.transpose(1, 2) + t[:, None]) - points_dst).pow(2).sum(-1)
    return (weights * res).sum(1) / weights.sum(1).clamp(min=eps)


def procrustes_random_subsets(
    points_src: torch.Tensor,
    points_dst: torch.Tensor,
    weights: torch.Tensor,
    n_subsets: int = 10,
    fraction: float = 0.2,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """R&R's robust alignment: Procrustes on ``n_subsets`` random subsets of the
    correspondences, keep the transform with the lowest weighted residual over all
    correspondences. Gradients flow through the chosen transform only.

    Args:
        points_src, points_dst: (B, N, 3).
        weights: (B, N).
        n_subsets: number of random subsets (R&R: 10).
        fraction: subset size as a fraction of N (R&R: 0.2); at least 3 points.
        generator: CPU generator for the subset draw (determinism).

    Returns:
        T (B, 4, 4) chosen ``T_src_to_dst`` and its residual (B,) in m^2.
    """
    _check(points_src, points_dst, weights)
    B, N, _ = points_src.shape
    if n_subsets < 1 or not 0 < fraction <= 1:
        raise ValueError(f"need n_subsets >= 1 and 0 < fraction <= 1, got {n_subsets}, {fraction}")
    m = max(3, min(N, int(round(fraction * N))))
    # Random subset per (pair, trial): argsort of uniform noise, first m indices.
    noise = torch.rand(B, n_subsets, N, generator=generator)
    idx = noise.argsort(dim=-1)[..., :m].to(points_src.device)  # (B, S, m)
    flat = idx.reshape(B, n_subsets * m)

    def gather(x: torch.Tensor) -> torch.Tensor:
        if x.ndim == 3:
            g = torch.gather(x, 1, flat[..., None].expand(-1, -1, 3))
            return g.reshape(B * n_subsets, m, 3)
        return torch.gather(x, 1, flat).reshape(B * n_subsets, m)

    T_all = weighted_procrustes(gather(points_src), gather(points_dst), gather(weights))  # (B*S, 4, 4)
    rep = lambda x: x.repeat_interleave(n_subsets, dim=0)  # noqa: E731
    res = weighted_residual(T_all, rep(points_src), rep(points_dst), rep(weights)).reshape(B, n_subsets)
    best = res.detach().argmin(dim=1)
    T = T_all.reshape(B, n_subsets, 4, 4)[torch.arange(B, device=best.device), best]
    return T, res[torch.arange(B, device=best.device), best]
