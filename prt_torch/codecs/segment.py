"""Segment ("per-cluster") matrix products as a few batched GEMMs: the tile layout.

CPCA needs, for every point p in cluster k(p), products with that cluster's matrices —
``y_p = x_p W_{k(p)}`` (projection onto a cluster's PCA vectors, Sloan 2003 §4.1; per-cluster
constants applied to per-point weights, Sloan 2003 §6) — and the per-cluster accumulations
``S_k = Σ_{p∈k} x_pᵀ y_p`` (scatter matrices, subspace iteration). A gather of W per point
would move K·D·r floats per point; a Python loop over clusters is banned on a hot path.

The tile layout sorts points by cluster and cuts each cluster into tiles of ``T`` rows
(the last tile of a cluster zero-padded), so every tile belongs to exactly one cluster. A
segment product is then one ``torch.bmm`` over tiles, ``[NT, T, D] @ [NT, D, r]``, with the
cluster's matrix gathered once per *tile* (not per point). Padding costs at most ``K·(T-1)``
rows; ``choose_tile`` keeps it under about a quarter of the points. This is the CPU analogue of
Sloan 2003 §6.2's per-cluster draw calls (a chunk of geometry per cluster).

All functions take/return batch-first tensors; dtypes follow the inputs (float32 or float64).
Work is done in chunks of tiles to bound the temporary memory (a loop over a handful of
chunks, not over clusters).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["TileLayout", "tile_layout", "choose_tile", "segment_matmul", "segment_accumulate", "to_tiles", "from_tiles",
           "tiles_bmm", "tiles_accumulate"]

#: Bytes of temporaries one chunk of tiles may allocate (gathered rows + gathered matrices).
CHUNK_BYTES = 48 * 2**20


def choose_tile(P: int, K: int) -> int:
    """Tile height: a power of two near P/(2K), clamped to [8, 256]. Expected padding ≈ K·T/2 ≤ P/4."""
    target = max(1, P // max(1, 2 * K))
    t = 8
    while t * 2 <= target and t < 256:
        t *= 2
    return t


@dataclass
class TileLayout:
    """Points (or point/cluster pairs) sorted by cluster and cut into tiles of ``T`` rows.

    Attributes:
        K, T, n: clusters, tile height, number of items.
        counts: ``int64 [K]`` items per cluster.
        tile_cluster: ``int64 [NT]`` the cluster of each tile.
        order: ``int64 [n]`` items sorted by cluster (stable).
        pos_sorted: ``int64 [n]`` flat tile position (tile·T + slot) of ``order[i]``, increasing.
        pos: ``int64 [n]`` flat tile position of item i (``pos[order] = pos_sorted``).
        rows: ``int64 [n]`` or None — the row of the data matrix item i reads (pairs layouts).
    """

    K: int
    T: int
    n: int
    counts: torch.Tensor
    tile_cluster: torch.Tensor
    order: torch.Tensor
    pos_sorted: torch.Tensor
    pos: torch.Tensor
    rows: torch.Tensor | None = None

    @property
    def NT(self) -> int:
        return int(self.tile_cluster.numel())

    def chunks(self, row_bytes: int):
        """Yield ``(t0, t1, i0, i1)``: tile range [t0, t1) and the slice [i0, i1) of ``order``
        whose items live in those tiles, each chunk holding about CHUNK_BYTES of temporaries."""
        per_tile = max(1, self.T * max(1, row_bytes))
        step = max(1, CHUNK_BYTES // per_tile)
        bounds = torch.arange(0, self.NT + step, step).clamp_max(self.NT)
        item_bounds = torch.searchsorted(self.pos_sorted, bounds * self.T).tolist()
        b = bounds.tolist()
        for j in range(len(b) - 1):
            if b[j] < b[j + 1]:
                yield b[j], b[j + 1], item_bounds[j], item_bounds[j + 1]


def tile_layout(labels: torch.Tensor, K: int, T: int | None = None, rows: torch.Tensor | None = None) -> TileLayout:
    """Build the tile layout of ``labels`` (``int [n]`` in [0, K)).

    ``rows`` (``int64 [n]``, optional) maps each item to the data row it reads, for layouts
    over (point, candidate cluster) pairs. Fully vectorised: sort, bincount, cumsum.
    """
    labels = labels.reshape(-1).long()
    n = labels.numel()
    if T is None:
        T = choose_tile(n, K)
    counts = torch.bincount(labels, minlength=K)
    ntiles = (counts + T - 1) // T
    tile_start = torch.cumsum(ntiles, 0) - ntiles
    tile_cluster = torch.repeat_interleave(torch.arange(K), ntiles)
    order = torch.argsort(labels, stable=True)
    sl = labels[order]
    cstart = torch.cumsum(counts, 0) - counts
    rank = torch.arange(n) - cstart[sl]
    pos_sorted = (tile_start[sl] + rank // T) * T + rank % T
    pos = torch.empty_like(pos_sorted)
    pos[order] = pos_sorted
    return TileLayout(K=K, T=T, n=n, counts=counts, tile_cluster=tile_cluster, order=order,
                      pos_sorted=pos_sorted, pos=pos, rows=None if rows is None else rows.reshape(-1).long())


def _gather_rows(layout: TileLayout, X: torch.Tensor, i0: int, i1: int) -> torch.Tensor:
    idx = layout.order[i0:i1]
    if layout.rows is not None:
        idx = layout.rows[idx]
    return X.index_select(0, idx)


def to_tiles(layout: TileLayout, Y: torch.Tensor) -> torch.Tensor:
    """``Y [n, *F]`` (item order) -> ``[NT, T, *F]`` in tile order, zero-padded."""
    out = Y.new_zeros((layout.NT * layout.T, *Y.shape[1:]))
    out[layout.pos] = Y if layout.rows is None else Y[layout.rows]
    return out.view(layout.NT, layout.T, *Y.shape[1:])


def from_tiles(layout: TileLayout, Yt: torch.Tensor) -> torch.Tensor:
    """``[NT, T, *F]`` in tile order -> ``[n, *F]`` in item order."""
    return Yt.reshape(layout.NT * layout.T, *Yt.shape[2:]).index_select(0, layout.pos)


def segment_matmul(layout: TileLayout, X: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """``out[i] = X[row(i)] @ W[k(i)]``: ``X [P, D]``, ``W [K, D, r]`` -> ``[n, r]`` (item order).

    One ``bmm`` per chunk of tiles; W gathered per tile. dtype of X (W is cast to it).
    """
    D, r = X.shape[1], W.shape[2]
    W = W.to(X.dtype)
    out = X.new_empty((layout.n, r))
    if layout.n == 0:
        return out
    es = X.element_size()
    for t0, t1, i0, i1 in layout.chunks((D + r) * es + D * r * es // layout.T):
        nt = t1 - t0
        Xt = X.new_zeros((nt * layout.T, D))
        local = layout.pos_sorted[i0:i1] - t0 * layout.T
        Xt[local] = _gather_rows(layout, X, i0, i1)
        Yt = torch.bmm(Xt.view(nt, layout.T, D), W.index_select(0, layout.tile_cluster[t0:t1]))
        out[layout.order[i0:i1]] = Yt.view(nt * layout.T, r)[local]
    return out


def segment_accumulate(layout: TileLayout, X: torch.Tensor, Y: torch.Tensor, out_dtype=torch.float64) -> torch.Tensor:
    """``S[k] = Σ_{i∈k} X[row(i)]ᵀ Y[i]``: ``X [P, D]``, ``Y [n, r]`` (item order) -> ``[K, D, r]``.

    Per-tile products in the dtype of X (T ≤ 256 terms), accumulated over tiles in
    ``out_dtype`` (float64 by default) with ``index_add_``.
    """
    D, r = X.shape[1], Y.shape[1]
    S = torch.zeros((layout.K, D, r), dtype=out_dtype)
    if layout.n == 0:
        return S
    Y = Y.to(X.dtype)
    es = X.element_size()
    for t0, t1, i0, i1 in layout.chunks((D + r) * es + D * r * es // layout.T):
        nt = t1 - t0
        local = layout.pos_sorted[i0:i1] - t0 * layout.T
        Xt = X.new_zeros((nt * layout.T, D))
        Xt[local] = _gather_rows(layout, X, i0, i1)
        Yt = X.new_zeros((nt * layout.T, r))
        Yt[local] = Y.index_select(0, layout.order[i0:i1])
        St = torch.bmm(Xt.view(nt, layout.T, D).transpose(1, 2), Yt.view(nt, layout.T, r))
        S.index_add_(0, layout.tile_cluster[t0:t1], St.to(out_dtype))
    return S


def tiles_bmm(Yt: torch.Tensor, W: torch.Tensor, tile_cluster: torch.Tensor) -> torch.Tensor:
    """``[NT, T, D] @ W[tile_cluster]`` with ``W [K, D, r]`` -> ``[NT, T, r]``.

    For data already in tile order (the fit keeps its centred signal that way, so no per-point
    gather happens inside an iteration). W is gathered per tile, in chunks of tiles.
    """
    NT, T, D = Yt.shape
    r = W.shape[2]
    W = W.to(Yt.dtype)
    out = Yt.new_empty((NT, T, r))
    step = max(1, CHUNK_BYTES // max(1, (D * r + T * r) * Yt.element_size()))
    for t0 in range(0, NT, step):  # a handful of chunks, bounded memory
        t1 = min(NT, t0 + step)
        torch.bmm(Yt[t0:t1], W.index_select(0, tile_cluster[t0:t1]), out=out[t0:t1])
    return out


def tiles_accumulate(At: torch.Tensor, Bt: torch.Tensor, tile_cluster: torch.Tensor, K: int,
                     out_dtype=torch.float64) -> torch.Tensor:
    """``S[k] = Σ_{tiles of k} A_tᵀ B_t``: ``At [NT, T, D]``, ``Bt [NT, T, r]`` -> ``[K, D, r]``.

    Per-tile products in the input dtype, summed over tiles in ``out_dtype`` (index_add_).
    """
    NT, T, D = At.shape
    r = Bt.shape[2]
    S = torch.zeros((K, D, r), dtype=out_dtype)
    Bt = Bt.to(At.dtype)
    step = max(1, CHUNK_BYTES // max(1, D * r * At.element_size()))
    for t0 in range(0, NT, step):  # a handful of chunks, bounded memory
        t1 = min(NT, t0 + step)
        St = torch.bmm(At[t0:t1].transpose(1, 2), Bt[t0:t1])
        S.index_add_(0, tile_cluster[t0:t1], St.to(out_dtype))
    return S
