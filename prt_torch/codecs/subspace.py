"""Per-cluster PCA, batched over clusters (Sloan 2003 §4.1, "Per-Cluster PCA").

Input is the cluster-centred, weight-scaled signal in tile order (``segment.TileLayout``):
``Yt [NT, T, D]`` whose tile t holds rows ``sqrt(w_p)(x_p − x_0)`` of cluster
``tile_cluster[t]`` (zero rows pad the last tile of a cluster). For cluster k with residual
matrix C_k (m_k × D, Sloan's C), the PCA vectors are the top right singular vectors of C_k
and the squared singular values D_i² are the squared error each removes:

    Σ_j ||x_pj − x̃_pj||² = Σ_{i>n'} D_i² = Σ_j ||x_pj − x_0||² − Σ_{i≤n'} D_i²   (Sloan 2003 §4.1)

Solvers (all return ``basis [K, n, D] float64`` with orthonormal rows, ``evals [K, n] float64``
= D_i² in decreasing order; vectors a cluster cannot support — rank < n — are zero rows with
D_i² = 0):

* ``'eigh'`` — Sloan's normal form: CᵀC (D×D) for clusters with m_k ≥ D, CCᵀ (m_k×m_k) for
  the others, whose right vectors follow as Vᵀ = D⁻¹UᵀC; batched ``torch.linalg.eigh``.
* ``'svd'`` — batched ``torch.linalg.svd`` of the zero-padded C_k (reference; memory K·m·D).
* ``'randomized'`` — block subspace iteration (Halko, Martinsson & Tropp 2011) with a
  Rayleigh–Ritz step, warm-started from a previous basis: the span always contains the warm
  basis, so the captured variance never decreases from one refit to the next (iterative
  CPCA relies on this). Cost per power step: two tile-GEMMs of width n + oversample.
"""
from __future__ import annotations

import torch

from .segment import tiles_accumulate, tiles_bmm

__all__ = ["cluster_pca", "total_variance"]


def total_variance(Yt: torch.Tensor, tile_cluster: torch.Tensor, K: int) -> torch.Tensor:
    """``Σ_{p∈k} ||y_p||²`` per cluster, float64 ``[K]``."""
    per_tile = Yt.square().sum((1, 2)).double()
    return torch.zeros(K, dtype=torch.float64).index_add_(0, tile_cluster, per_tile)


def _top(evals: torch.Tensor, evecs: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """eigh output (ascending) -> top-n (descending) values [K, n] and vectors [K, D|m, n]."""
    return evals[..., -n:].flip(-1).clamp_min(0), evecs[..., -n:].flip(-1)


def _eigh_normal_form(Yt, tile_cluster, counts, n, T):
    NT, _, D = Yt.shape
    K = counts.numel()
    basis = torch.zeros(K, n, D, dtype=torch.float64)
    evals = torch.zeros(K, n, dtype=torch.float64)
    if n == 0:
        return basis, evals
    big = counts >= D
    # clusters with m_k >= D: C^T C (D x D)
    ka = torch.nonzero(big).flatten()
    if ka.numel():
        tmask = big[tile_cluster]
        remap = torch.full((K,), -1, dtype=torch.long)
        remap[ka] = torch.arange(ka.numel())
        S = tiles_accumulate(Yt[tmask], Yt[tmask], remap[tile_cluster[tmask]], ka.numel())
        S = 0.5 * (S + S.transpose(1, 2))
        lam, V = torch.linalg.eigh(S)
        lam, V = _top(lam, V, n)
        basis[ka] = V.transpose(1, 2)
        evals[ka] = lam
    # clusters with 0 < m_k < D: C C^T (m_k x m_k), padded to the largest such cluster
    kb = torch.nonzero((~big) & (counts > 0)).flatten()
    if kb.numel():
        ntiles = (counts + T - 1) // T
        tstart = torch.cumsum(ntiles, 0) - ntiles
        R = int(ntiles[kb].max()) * T
        rows = tstart[kb, None] * T + torch.arange(R)[None, :]  # [Kb, R] flat rows of each cluster
        valid = torch.arange(R)[None, :] < (ntiles[kb] * T)[:, None]
        flat = Yt.reshape(NT * T, D)
        Cb = flat[rows.clamp_max(NT * T - 1)].double() * valid[..., None]
        G = Cb @ Cb.transpose(1, 2)
        G = 0.5 * (G + G.transpose(1, 2))
        lam, U = torch.linalg.eigh(G)
        nb = min(n, R)
        lam, U = _top(lam, U, nb)
        sig = lam.sqrt()
        ok = lam > lam[:, :1].clamp_min(1e-300) * (R * torch.finfo(torch.float64).eps * 16)
        V = (Cb.transpose(1, 2) @ U) / torch.where(ok, sig, torch.ones_like(sig))[:, None, :]
        V = V * ok[:, None, :]
        basis[kb, :nb] = V.transpose(1, 2)
        evals[kb, :nb] = lam * ok
    return basis, evals


def _svd(Yt, tile_cluster, counts, n, T):
    NT, _, D = Yt.shape
    K = counts.numel()
    basis = torch.zeros(K, n, D, dtype=torch.float64)
    evals = torch.zeros(K, n, dtype=torch.float64)
    ks = torch.nonzero(counts > 0).flatten()
    if n == 0 or ks.numel() == 0:
        return basis, evals
    ntiles = (counts + T - 1) // T
    tstart = torch.cumsum(ntiles, 0) - ntiles
    R = int(ntiles[ks].max()) * T
    rows = tstart[ks, None] * T + torch.arange(R)[None, :]
    valid = torch.arange(R)[None, :] < (ntiles[ks] * T)[:, None]
    Cb = Yt.reshape(NT * T, D)[rows.clamp_max(NT * T - 1)].double() * valid[..., None]
    _, S, Vh = torch.linalg.svd(Cb, full_matrices=False)
    nb = min(n, S.shape[1])
    lam = S[:, :nb].square()
    ok = S[:, :nb] > S[:, :1].clamp_min(1e-300) * (max(R, D) * torch.finfo(torch.float64).eps * 4)
    basis[ks, :nb] = Vh[:, :nb] * ok[..., None]
    evals[ks, :nb] = lam * ok
    return basis, evals


def _randomized(Yt, tile_cluster, counts, n, gen, init, oversample, power_iters):
    NT, T, D = Yt.shape
    K = counts.numel()
    basis = torch.zeros(K, n, D, dtype=torch.float64)
    evals = torch.zeros(K, n, dtype=torch.float64)
    if n == 0:
        return basis, evals
    r = min(D, n + oversample)
    warm = None
    if init is not None and init.shape[1] > 0:
        warm = init[:, : min(init.shape[1], n)].double().transpose(1, 2)  # [K, D, n0]
    g = torch.randn(K, D, r, generator=gen, dtype=torch.float64)
    Q = g if warm is None else torch.cat([warm, g[..., : max(0, r - warm.shape[2])]], 2)
    Q = torch.linalg.qr(Q).Q
    for _ in range(power_iters):  # a few power steps (each: 2 tile-GEMMs)
        Z = tiles_bmm(Yt, Q, tile_cluster)
        Q = torch.linalg.qr(tiles_accumulate(Yt, Z, tile_cluster, K)).Q
    if warm is not None:
        Q = torch.linalg.qr(torch.cat([warm, Q], 2)[..., :D]).Q
    Z = tiles_bmm(Yt, Q, tile_cluster)
    H = tiles_accumulate(Z, Z, tile_cluster, K)
    H = 0.5 * (H + H.transpose(1, 2))
    lam, U = torch.linalg.eigh(H)
    nb = min(n, lam.shape[1])
    lam, U = _top(lam, U, nb)
    V = Q @ U  # [K, D, nb]
    basis[:, :nb] = V.transpose(1, 2)
    evals[:, :nb] = lam
    # a cluster with fewer points than vectors: drop directions with (numerically) zero variance
    small = evals <= evals[:, :1].clamp_min(1e-300) * (D * torch.finfo(Yt.dtype).eps * 16)
    basis[small] = 0
    evals[small] = 0
    return basis, evals


def cluster_pca(Yt: torch.Tensor, tile_cluster: torch.Tensor, counts: torch.Tensor, n: int, solver: str,
                gen: torch.Generator | None = None, init: torch.Tensor | None = None,
                oversample: int = 8, power_iters: int = 4) -> tuple[torch.Tensor, torch.Tensor]:
    """Top-``n`` PCA vectors of every cluster: ``(basis [K, n, D], evals [K, n])`` float64.

    Args:
        Yt: ``[NT, T, D]`` centred, sqrt(weight)-scaled rows in tile order (float32/64).
        tile_cluster: ``int64 [NT]``; counts: ``int64 [K]`` points per cluster.
        solver: 'eigh' | 'svd' | 'randomized' (see module docstring).
        init: ``[K, n0, D]`` warm-start basis for 'randomized' (its span is kept).
    """
    T = Yt.shape[1]
    if solver == "eigh":
        return _eigh_normal_form(Yt, tile_cluster, counts, n, T)
    if solver == "svd":
        return _svd(Yt, tile_cluster, counts, n, T)
    if solver == "randomized":
        if gen is None:
            gen = torch.Generator().manual_seed(0)
        return _randomized(Yt, tile_cluster, counts, n, gen, init, oversample, power_iters)
    raise ValueError(f"solver={solver!r}; accepted: 'eigh', 'svd', 'randomized'")
