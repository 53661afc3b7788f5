"""Feature-space correspondences between two feature-carrying point clouds (R&R).

For a pair (a, b) every candidate point of b looks up its two nearest neighbours among
the candidates of a in feature space (and vice versa); the ratio test gives the weight
``w = 1 - d1 / d2`` and the ``top_k`` most confident matches of each direction are
kept. The nearest-neighbour search runs without gradient on the similarity matrix of
each pair, in groups of pairs of bounded size: on the CPU one compiled pass over each
matrix finds both directions' two nearest; elsewhere ``topk`` runs along the rows of the
matrix and of its transpose (one product each, so that both searches run along
contiguous rows). The kept distances are recomputed with gradient so that the weights
are differentiable with respect to the features.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
import torch
import torch.nn.functional as F

from depthgt.shapes import check_shape

__all__ = ["Correspondences", "sample_candidates", "knn2_both", "ratio_weights", "find_correspondences"]


class Correspondences(NamedTuple):
    """Matches of a batch of pairs; both directions concatenated (2 * top_k rows).

    Attributes:
        points_src: (P, K, 3) points of frame b (metres, b's camera).
        points_dst: (P, K, 3) matched points of frame a (metres, a's camera).
        weights: (P, K) ratio-test weights in [0, 1], 0 for padding.
    """

    points_src: torch.Tensor
    points_dst: torch.Tensor
    weights: torch.Tensor


def sample_candidates(
    valid: torch.Tensor, n: int, generator: torch.Generator | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Draw up to ``n`` valid pixels per frame, uniformly without replacement.

    Args:
        valid: (F, 1, H, W) bool mask of valid depth.
        n: candidates per frame.
        generator: CPU generator (deterministic draw for a given seed).

    Returns:
        index (F, n) long flat pixel indices and mask (F, n) bool, False where a frame
        has fewer than ``n`` valid pixels (those slots hold invalid pixels).
    """
    check_shape(valid, "F 1 H W", "valid")
    flat = valid.flatten(1)
    n = min(n, flat.shape[1])
    score = torch.rand(flat.shape, generator=generator).to(flat.device) + flat.float() * 2.0
    index = score.topk(n, dim=1).indices
    return index, torch.gather(flat, 1, index)


def knn2_both(
    f_a: torch.Tensor,
    f_b: torch.Tensor,
    mask_a: torch.Tensor,
    mask_b: torch.Tensor,
    max_block: int = 1 << 25,
    compiled: bool | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Two nearest neighbours in both directions from the similarity matrix of each pair.

    Features must be L2-normalised, so that the Euclidean ranking equals the ranking
    by dot product (``|x - y|^2 = 2 - 2 x.y``): one batched matmul per group of pairs,
    then :func:`_top2_both` over it (CPU, float32), or ``topk`` along its rows and along
    those of the transposed product. Pairs are processed in groups holding at most
    ``max_block`` similarities (memory bound), without gradient.

    Args:
        f_a: (P, N, C) and f_b: (P, M, C) unit features.
        mask_a: (P, N), mask_b: (P, M) bool validity (invalid entries are never
            returned while valid ones exist).
        compiled: the compiled search (default: for float32 CPU features and N, M >= 2)
            or ``topk`` (False): the same indices, but for equally near candidates.

    Returns:
        nn_b_of_a (P, N, 2) indices into M and nn_a_of_b (P, M, 2) indices into N.
    """
    P, N, _ = f_a.shape
    M = f_b.shape[1]
    # groups of at most max_block similarities, and (speed: the matrices stay in cache)
    # at most _CACHE_BLOCK unless a single pair is larger; the grouping changes no value
    g = max(1, min(max_block, _CACHE_BLOCK) // max(1, N * M))
    can_compile = f_a.device.type == f_b.device.type == "cpu" and f_a.dtype == f_b.dtype == torch.float32
    if compiled is None:
        compiled = can_compile and min(N, M) >= 2
    elif compiled and not (can_compile and min(N, M) >= 2):
        raise ValueError(
            f"knn2_both: the compiled search needs float32 CPU features and N, M >= 2, got {f_a.dtype} / "
            f"{f_b.dtype} on {f_a.device.type} / {f_b.device.type}, N={N}, M={M}"
        )
    if compiled:
        nn_ab = np.empty((P, N, 2), np.int64)
        nn_ba = np.empty((P, M, 2), np.int64)
    out_ab, out_ba = [], []
    with torch.no_grad():
        for s in range(0, P, g):
            fa, fb = f_a[s : s + g], f_b[s : s + g]
            sim = fa @ fb.transpose(1, 2)  # (g, N, M)
            ma, mb = mask_a[s : s + g], mask_b[s : s + g]
            bad = None if bool(ma.all() and mb.all()) else ~(ma[:, :, None] & mb[:, None, :])
            if bad is not None:
                sim.masked_fill_(bad, -4.0)
            if compiled:
                _top2_both(sim.contiguous().numpy(), nn_ab[s : s + g], nn_ba[s : s + g])
                continue
            # the other direction from its own product (the same dot products), so that
            # both top-2 searches run along contiguous rows: 3x faster than along columns
            sim_t = fb @ fa.transpose(1, 2)  # (g, M, N)
            if bad is not None:
                sim_t.masked_fill_(bad.transpose(1, 2), -4.0)
            out_ab.append(sim.topk(2, dim=2).indices)
            out_ba.append(sim_t.topk(2, dim=2).indices)
    if compiled:
        return torch.from_numpy(nn_ab), torch.from_numpy(nn_ba)
    return torch.cat(out_ab), torch.cat(out_ba)


@numba.njit(cache=True, nogil=True)
def _top2_both(sim, nn_ab, nn_ba):  # pragma: no cover (compiled)
    """The two largest entries of every row and every column of each (N, M) matrix of
    ``sim`` (G, N, M), in one pass over it: their column indices into ``nn_ab`` (G, N, 2)
    and their row indices into ``nn_ba`` (G, M, 2), the largest first; among equal values
    the later index first (``topk`` orders equal values as its partial sort meets them:
    either is a nearest). Otherwise ``topk``'s indices along the rows of ``sim`` and of its
    transpose, without the transpose's product and with one pass in place of two. Written by hand:
    no library gives both directions' two nearest from one matrix (21 pairs of 1,024
    candidates, one thread: 62 against 150-280 ms for the two products and two ``topk``).
    The row's pair is a scalar running maximum (its branches are rarely taken, so
    predicted); the columns' pairs are arrays updated along the row."""
    n_g, N, M = sim.shape
    neg = -np.inf
    cb1 = np.empty(M, sim.dtype)  # each column's largest and second value, and their rows
    cb2 = np.empty(M, sim.dtype)
    ci1 = np.zeros(M, np.int64)
    ci2 = np.zeros(M, np.int64)
    for p in range(n_g):
        cb1[:] = neg
        cb2[:] = neg
        ci1[:] = 0
        ci2[:] = 0
        for i in range(N):
            b1 = neg
            b2 = neg
            j1 = 0
            j2 = 0
            for j in range(M):
                v = sim[p, i, j]
                if v >= b2:
                    if v >= b1:
                        b2, j2, b1, j1 = b1, j1, v, j
                    else:
                        b2, j2 = v, j
                if v >= cb2[j]:
                    if v >= cb1[j]:
                        cb2[j], ci2[j], cb1[j], ci1[j] = cb1[j], ci1[j], v, i
                    else:
                        cb2[j], ci2[j] = v, i
            nn_ab[p, i, 0] = j1
            nn_ab[p, i, 1] = j2
        for j in range(M):
            nn_ba[p, j, 0] = ci1[j]
            nn_ba[p, j, 1] = ci2[j]


_CACHE_BLOCK = 1 << 22  # similarities per matmul group for speed (16 MB of float32)


def ratio_weights(f_query: torch.Tensor, f_ref: torch.Tensor, nn_idx: torch.Tensor, eps: float = 1e-8) -> torch.Tensor:
    """``w = 1 - d1 / d2`` from the two neighbours ``nn_idx`` (P, N, 2); differentiable, (P, N)."""
    C = f_ref.shape[-1]
    g = torch.gather(f_ref, 1, nn_idx.flatten(1)[..., None].expand(-1, -1, C)).reshape(*nn_idx.shape, C)
    d = (g - f_query[:, :, None]).pow(2).sum(-1).add(eps).sqrt()  # (P, N, 2)
    return (1.0 - d[..., 0] / d[..., 1].clamp(min=eps)).clamp(min=0.0)


def _one_direction(pts_q, f_q, m_q, pts_r, f_r, nn_idx, top_k):
    w = ratio_weights(f_q, f_r, nn_idx) * m_q.to(f_q.dtype)
    k = min(top_k, w.shape[1])
    sel = w.detach().topk(k, dim=1).indices  # (P, k)
    w_k = torch.gather(w, 1, sel)
    q_k = torch.gather(pts_q, 1, sel[..., None].expand(-1, -1, 3))
    r_idx = torch.gather(nn_idx[..., 0], 1, sel)
    r_k = torch.gather(pts_r, 1, r_idx[..., None].expand(-1, -1, 3))
    return q_k, r_k, w_k


def find_correspondences(
    points_a: torch.Tensor,
    feats_a: torch.Tensor,
    mask_a: torch.Tensor,
    points_b: torch.Tensor,
    feats_b: torch.Tensor,
    mask_b: torch.Tensor,
    top_k: int = 200,
    max_block: int = 1 << 25,
) -> Correspondences:
    """Bidirectional ratio-test matches between frames b (source) and a (destination).

    Args:
        points_a, points_b: (P, N, 3) candidate points in their own cameras (metres).
        feats_a, feats_b: (P, N, C) their features (L2-normalised here and compared by
            Euclidean distance).
        mask_a, mask_b: (P, N) bool validity of the candidates.
        top_k: matches kept per direction (R&R: 200).
        max_block: similarities per matmul block (memory bound).

    Returns:
        :class:`Correspondences` with ``points_src`` in b and ``points_dst`` in a, so
        that Procrustes on them estimates ``T_b_to_a``.
    """
    check_shape(points_a, "P N D", "points_a")
    check_shape(points_b, "P N D", "points_b")
    feat_dim = check_shape(feats_a, "P N C", "feats_a")["C"]
    check_shape(feats_b, "P N C", "feats_b", {"C": feat_dim})  # P and N may differ from a's
    feats_a = F.normalize(feats_a, dim=-1)
    feats_b = F.normalize(feats_b, dim=-1)
    nn_b_of_a, nn_a_of_b = knn2_both(feats_a, feats_b, mask_a, mask_b, max_block)
    b_q, a_r, w_ba = _one_direction(points_b, feats_b, mask_b, points_a, feats_a, nn_a_of_b, top_k)
    a_q, b_r, w_ab = _one_direction(points_a, feats_a, mask_a, points_b, feats_b, nn_b_of_a, top_k)
    return Correspondences(torch.cat([b_q, b_r], 1), torch.cat([a_r, a_q], 1), torch.cat([w_ba, w_ab], 1))
