"""Per-cluster PCA, batched over clusters (Sloan 2003 §4.1, "Per-Cluster PCA").

Input is the cluster-centred, weight-scaled signal in tile order (``segment.TileLayout``):
``Yt [NT, T, D]`` whose tile t holds rows ``sqrt(w_p)(x_p − x_0)`` of cluster
``tile_cluster[t]`` (zero rows pad the last tile of a cluster) — one such ``(layout, Yt)`` for
the whole signal, or one per chunk of rows (a :class:`TileSource`: a streamed fit never holds
the signal in tile order whole; every product below is a sum over the chunks, so the solvers
are the same for one chunk or many). For cluster k with residual
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
  CPCA relies on this). Cost per power step: two tile-GEMMs of width n + oversample (warm
  starts: n + min(oversample, WARM_OVERSAMPLE)). One cluster: plain GEMMs, no tiles.
* ``'krylov'`` — randomized block Krylov iteration (Musco & Musco 2015, "Randomized block Krylov
  methods for stronger and faster approximate singular value decomposition", Algorithm 2;
  Halko et al. 2011 §4.4 name the idea): the Rayleigh–Ritz step runs on the whole Krylov space
  ``[Q₀, (CᵀC)Q₀, …, (CᵀC)^q Q₀]`` (blocks of b = ⌈(n + oversample)/2⌉ columns, each made
  orthogonal to the earlier ones: block Lanczos with full re-orthogonalisation), not only on its
  last block. ``power_iters`` = q + 1 passes over the data, each applying CᵀC to one block of b
  columns: the same passes as ``'randomized'`` at about half its width. The Ritz matrix needs no
  extra pass: its block column j is Q_cᵀ (CᵀC Q_j), the product each pass computed anyway. On
  the default benchmark's 10 242 × 16 128 Gaussian-part tables (a slowly decaying spectrum) it
  reaches the float64 optimum's SE (ratio ≤ 1.00003 at n = 81 and 163) where the subspace
  iteration with 6 steps and 16 extra columns stops at 1.00027 / 1.00023, at under half its
  multiply-adds (reports/benchmarks/default_gaussian_10k/profile.md). Cold starts only: a warm
  refit (``init``, iterative CPCA) takes the ``'randomized'`` warm step, whose span keeps the
  warm basis.
"""
from __future__ import annotations

import torch

from .segment import TileLayout, tiles_accumulate, tiles_bmm

__all__ = ["cluster_pca", "total_variance", "orthonormalize", "TileSource"]


class TileSource:
    """The rows of every cluster as tiles, chunk by chunk: ``tiles()`` yields ``(layout, Yt)``
    per chunk of rows (``Yt [NT_c, T, D]``, the chunk's rows in its own tile layout); ``K``,
    ``D``, ``dtype``. The plain form holds one chunk: ``TileSource.single(layout, Yt)``."""

    def __init__(self, K: int, D: int, dtype: torch.dtype, tiles):
        self.K, self.D, self.dtype, self._tiles = K, D, dtype, tiles

    @classmethod
    def single(cls, layout: TileLayout, Yt: torch.Tensor) -> "TileSource":
        return cls(layout.K, Yt.shape[2], Yt.dtype, lambda: ((layout, Yt),))

    def tiles(self):
        return self._tiles()


def _over(src: TileSource, fn) -> torch.Tensor:
    """``Σ_chunks fn(layout, Yt)`` (the first chunk's result itself when there is one chunk)."""
    acc = None
    for lay, Yt in src.tiles():
        r = fn(lay, Yt)
        acc = r if acc is None else acc.add_(r)
    return acc


#: Random columns added to a warm basis (``init``): the warm basis and its power step carry the
#: subspace; more random columns cost a tile-GEMM column each and, on glossy transfer, did not
#: lower the iterative CPCA error (203.8 with 8, 202.9 with 2).
WARM_OVERSAMPLE = 2


def _bmm(layout: TileLayout, Yt: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """``tiles_bmm``; one cluster (global PCA): a single GEMM over all rows ``[NT·T, D] @ [D, r]``."""
    if layout.K != 1:
        return tiles_bmm(layout, Yt, W)
    NT, T, D = Yt.shape
    return (Yt.reshape(NT * T, D) @ W[0].to(Yt.dtype)).view(NT, T, -1)


def _accumulate(layout: TileLayout, At: torch.Tensor, Bt: torch.Tensor) -> torch.Tensor:
    """``tiles_accumulate`` (float64 ``[K, D, r]``); one cluster: a single GEMM ``Aᵀ B``."""
    if layout.K != 1:
        return tiles_accumulate(layout, At, Bt)
    D, r = At.shape[2], Bt.shape[2]
    return (At.reshape(-1, D).T @ Bt.reshape(-1, r).to(At.dtype)).double()[None]


def total_variance(layout: TileLayout, Yt: torch.Tensor) -> torch.Tensor:
    """``Σ_{p∈k} ||y_p||²`` per cluster, float64 ``[K]`` (no temporary of Yt's size)."""
    per_tile = torch.linalg.vector_norm(Yt, dim=(1, 2)).double().square()
    return torch.zeros(layout.K, dtype=torch.float64).index_add_(0, layout.tile_cluster, per_tile)


def _rows_of(src: TileSource, ks: torch.Tensor) -> tuple[torch.Tensor, int]:
    """The rows of clusters ``ks`` from every chunk, ``[len(ks), R, D]`` float64 (zero rows where
    a cluster has fewer), and R. For the few small clusters of the normal form and the SVD."""
    parts = []
    for lay, Yt in src.tiles():
        NT, T, D = Yt.shape
        R = int(lay.ntiles[ks].max()) * T
        if R:
            rows, valid = lay.cluster_rows(ks, R)
            parts.append(Yt.reshape(NT * T, D)[rows].double() * valid[..., None])
    Cb = parts[0] if len(parts) == 1 else torch.cat(parts, 1)
    return Cb, int(Cb.shape[1])


def orthonormalize(A: torch.Tensor, passes: int = 2) -> torch.Tensor:
    """Orthonormal columns spanning ``A [K, D, r]`` (float64), batched: Q = A V Λ^{-1/2} from the
    eigen-decomposition of the small Gram AᵀA, twice for accuracy ("eigen-QR", like CholeskyQR2
    but tolerant of rank deficiency: directions with no energy become zero columns). Used
    instead of Householder QR, whose batched CPU path is far slower for these shapes."""
    Q = A
    for _ in range(passes):
        G = Q.transpose(1, 2) @ Q
        lam, V = torch.linalg.eigh(0.5 * (G + G.transpose(1, 2)))
        tol = lam[:, -1:].clamp_min(1e-300) * (G.shape[-1] * torch.finfo(torch.float64).eps * 64)
        ok = lam > tol
        scale = torch.where(ok, lam.clamp_min(1e-300).rsqrt(), torch.zeros_like(lam))
        Q = Q @ (V * scale[:, None, :])
    return Q


def _test_block(gen: torch.Generator, K: int, D: int, r: int, cache: dict | None) -> torch.Tensor:
    """Gaussian test block ``[K, D, r]`` float64, drawn once per shape per ``cache`` (one fit):
    later warm-started refits reuse it (the warm basis carries the subspace; fresh draws add
    nothing and are not free). Deterministic per seed."""
    if cache is None:
        return torch.randn(K, D, r, generator=gen, dtype=torch.float64)
    key = ("test_block", K, D, r)
    if key not in cache:
        cache[key] = torch.randn(K, D, r, generator=gen, dtype=torch.float64)
    return cache[key]


def _top(evals: torch.Tensor, evecs: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """eigh output (ascending) -> top-n (descending) values [K, n] and vectors [K, D|m, n]."""
    return evals[..., -n:].flip(-1).clamp_min(0), evecs[..., -n:].flip(-1)


def _eigh_normal_form(src, n, counts):
    K, D = src.K, src.D
    basis = torch.zeros(K, n, D, dtype=torch.float64)
    evals = torch.zeros(K, n, dtype=torch.float64)
    if n == 0:
        return basis, evals
    big = counts >= D
    # clusters with m_k >= D: C^T C (D x D), eigenvectors = PCA vectors (Sloan 2003 §4.1)
    ka = torch.nonzero(big).flatten()
    if ka.numel():
        S = _over(src, lambda lay, Yt: _accumulate(lay, Yt, Yt))[ka]
        lam, V = torch.linalg.eigh(0.5 * (S + S.transpose(1, 2)))
        lam, V = _top(lam, V, n)
        basis[ka] = V.transpose(1, 2)
        evals[ka] = lam
    # clusters with 0 < m_k < D: C C^T (m_k x m_k); right vectors V^T = D^-1 U^T C
    kb = torch.nonzero((~big) & (counts > 0)).flatten()
    if kb.numel():
        Cb, R = _rows_of(src, kb)
        G = Cb @ Cb.transpose(1, 2)
        lam, U = torch.linalg.eigh(0.5 * (G + G.transpose(1, 2)))
        nb = min(n, R)
        lam, U = _top(lam, U, nb)
        ok = lam > lam[:, :1].clamp_min(1e-300) * (R * torch.finfo(torch.float64).eps * 16)
        sig = torch.where(ok, lam, torch.ones_like(lam)).sqrt()
        V = (Cb.transpose(1, 2) @ U) / sig[:, None, :] * ok[:, None, :]
        basis[kb, :nb] = V.transpose(1, 2)
        evals[kb, :nb] = lam * ok
    return basis, evals


def _svd(src, n, counts):
    K, D = src.K, src.D
    basis = torch.zeros(K, n, D, dtype=torch.float64)
    evals = torch.zeros(K, n, dtype=torch.float64)
    ks = torch.nonzero(counts > 0).flatten()
    if n == 0 or ks.numel() == 0:
        return basis, evals
    Cb, R = _rows_of(src, ks)
    _, S, Vh = torch.linalg.svd(Cb, full_matrices=False)
    nb = min(n, S.shape[1])
    ok = S[:, :nb] > S[:, :1].clamp_min(1e-300) * (max(R, D) * torch.finfo(torch.float64).eps * 4)
    basis[ks, :nb] = Vh[:, :nb] * ok[..., None]
    evals[ks, :nb] = S[:, :nb].square() * ok
    return basis, evals


def _drop_empty(basis: torch.Tensor, evals: torch.Tensor, D: int, dtype: torch.dtype) -> None:
    """Zero (in place) the vectors whose D_i² is within the rounding of the products that
    estimated it: ≤ λ₁ · 16 √D · eps(dtype) — fewer points than vectors, or zero columns.
    (The bound was λ₁ · 16 D · eps: 3% of λ₁ in float32 at D = 16 128, which dropped real
    directions of a slowly decaying spectrum — the default benchmark's Gaussian-part tables have
    λ₈₁/λ₁ = 0.039, λ₁₆₃/λ₁ = 0.0069: PCA at 163 vectors kept about 80 and had 2.6× the optimum's SE.)"""
    small = evals <= evals[:, :1].clamp_min(1e-300) * (D ** 0.5 * torch.finfo(dtype).eps * 16)
    basis[small] = 0
    evals[small] = 0


def _randomized(src, n, gen, init, oversample, power_iters, cache):
    K, D = src.K, src.D
    basis = torch.zeros(K, n, D, dtype=torch.float64)
    evals = torch.zeros(K, n, dtype=torch.float64)
    if n == 0:
        return basis, evals
    warm = None
    if init is not None and init.shape[1] > 0:
        warm = init[:, : min(init.shape[1], n)].double().transpose(1, 2)  # [K, D, n0]
        oversample = min(oversample, WARM_OVERSAMPLE)
    r = min(D, n + oversample)
    n_rand = r if warm is None else max(0, r - warm.shape[2])
    g = _test_block(gen, K, D, n_rand, cache)
    if warm is None:
        Q = orthonormalize(g)
        for _ in range(max(1, power_iters)):  # power steps (each: 2 tile-GEMMs + a small orth)
            Q = orthonormalize(_apply(src, Q))
    else:
        # one power step on [warm, random], then Rayleigh-Ritz on span([warm, S [warm, random]]):
        # the warm basis stays in the span, so the captured variance cannot drop
        Q0 = torch.cat([warm, g], 2)
        SQ = _apply(src, Q0)
        Q = orthonormalize(torch.cat([warm, SQ], 2)[..., :D])
    H = _over(src, lambda lay, Yt: (lambda Z: _accumulate(lay, Z, Z))(_bmm(lay, Yt, Q)))  # (YQ)ᵀ(YQ) per cluster
    lam, U = torch.linalg.eigh(0.5 * (H + H.transpose(1, 2)))
    nb = min(n, lam.shape[1])
    lam, U = _top(lam, U, nb)
    basis[:, :nb] = (Q @ U).transpose(1, 2)
    evals[:, :nb] = lam
    # fewer points than vectors, or zero columns: drop directions without variance
    _drop_empty(basis, evals, D, src.dtype)
    return basis, evals


def _krylov(src, n, gen, oversample, power_iters, cache):
    """Randomized block Krylov (Musco & Musco 2015, Algorithm 2) with full re-orthogonalisation:
    ``power_iters`` passes ``W_j = Σ y yᵀ Q_j`` (``_apply``), blocks ``Q_j [K, D, b]`` float64,
    then Rayleigh–Ritz on ``Q_c = [Q_0 … Q_q]`` with ``H = Q_cᵀ [W_0 … W_q]`` ``[K, m, m]``."""
    K, D = src.K, src.D
    basis = torch.zeros(K, n, D, dtype=torch.float64)
    evals = torch.zeros(K, n, dtype=torch.float64)
    if n == 0:
        return basis, evals
    b = min(D, max(1, -(-(n + oversample) // 2)))
    Q = orthonormalize(_test_block(gen, K, D, b, cache))
    Qs, Ws = [], []
    for i in range(max(1, power_iters)):
        W = _apply(src, Q)  # C^T C Q_i, one pass over the data
        Qs.append(Q)
        Ws.append(W)
        if i + 1 == max(1, power_iters) or b * (i + 1) >= D:
            break
        Qc = torch.cat(Qs, 2)
        V = W
        for _ in range(2):  # block Gram-Schmidt against the Krylov space so far, twice
            V = V - Qc @ (Qc.transpose(1, 2) @ V)
        Q = orthonormalize(V)
    Qc, Wc = torch.cat(Qs, 2), torch.cat(Ws, 2)
    H = Qc.transpose(1, 2) @ Wc  # Q_c^T C^T C Q_c, symmetric up to rounding
    lam, U = torch.linalg.eigh(0.5 * (H + H.transpose(1, 2)))
    nb = min(n, lam.shape[1])
    lam, U = _top(lam, U, nb)
    basis[:, :nb] = (Qc @ U).transpose(1, 2)
    evals[:, :nb] = lam
    _drop_empty(basis, evals, D, src.dtype)
    return basis, evals


def _apply(src: TileSource, Q: torch.Tensor) -> torch.Tensor:
    """``Σ_{p∈k} y_p y_pᵀ Q_k`` = ``C_kᵀ (C_k Q_k)`` per cluster ``[K, D, r]`` float64: one pass over the chunks."""
    return _over(src, lambda lay, Yt: _accumulate(lay, Yt, _bmm(lay, Yt, Q)))


def cluster_pca(layout, Yt: torch.Tensor | None, n: int, solver: str, gen: torch.Generator | None = None,
                init: torch.Tensor | None = None, oversample: int = 8, power_iters: int = 3,
                cache: dict | None = None, counts: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Top-``n`` PCA vectors of every cluster: ``(basis [K, n, D], evals [K, n])`` float64.

    Args:
        layout: the tile layout of the clusters and Yt: ``[NT, T, D]`` centred,
            sqrt(weight)-scaled rows in that tile order (float32/64; padding rows zero); or a
            :class:`TileSource` (chunks of rows, each in its own layout) with ``Yt`` None and
            ``counts [K]`` the points per cluster.
        solver: 'eigh' | 'svd' | 'randomized' | 'krylov' (see module docstring).
        init: ``[K, n0, D]`` warm-start basis for 'randomized' and 'krylov' (its span is kept: both
            take the randomized warm step).
        cache: a dict owned by one fit, to reuse the random test block across refits.
    """
    if isinstance(layout, TileSource):
        src = layout
    else:
        src, counts = TileSource.single(layout, Yt), layout.counts
    if solver == "eigh":
        return _eigh_normal_form(src, n, counts)
    if solver == "svd":
        return _svd(src, n, counts)
    if solver == "randomized":
        if gen is None:
            gen = torch.Generator().manual_seed(0)
        return _randomized(src, n, gen, init, oversample, power_iters, cache)
    if solver == "krylov":
        if gen is None:
            gen = torch.Generator().manual_seed(0)
        if init is not None and init.shape[1] > 0:  # a warm refit (iterative CPCA): the randomized warm
            return _randomized(src, n, gen, init, oversample, power_iters, cache)  # step keeps the warm span
        return _krylov(src, n, gen, oversample, power_iters, cache)
    raise ValueError(f"solver={solver!r}; accepted: 'eigh', 'svd', 'randomized', 'krylov'")
