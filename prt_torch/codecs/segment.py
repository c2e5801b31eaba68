"""Segment ("per-cluster") matrix products as a few batched GEMMs: the tile layout.

CPCA needs, for every point p in cluster k(p), products with that cluster's matrices —
``y_p = x_p W_{k(p)}`` (projection onto a cluster's PCA vectors, Sloan 2003 §4.1; per-point
weights applied to per-cluster constants, Sloan 2003 §6) — and per-cluster accumulations
``S_k = Σ_{p∈k} x_pᵀ y_p`` (scatter products for the PCA). A gather of W per point would move
K·D·r floats per point, and a Python loop over clusters is banned on a hot path.

The tile layout cuts each cluster's points into tiles of ``T`` rows (the last one
zero-padded), so every tile belongs to one cluster. Tiles are stored *group-major*: group j
holds the j-th tile of every cluster that has more than j tiles, clusters in the order of
decreasing tile count (``corder``). The clusters of group j are therefore a prefix of
``corder``, so a segment product is one ``bmm`` per group against a *prefix view* of the
cluster matrices permuted once, ``W[corder][:c_j]`` — no per-tile copy of W. The number of
groups is the tile count of the largest cluster (a loop over tile rows, not clusters).
Padding costs at most ``K·(T−1)`` rows; ``choose_tile`` keeps it near a quarter of the
points at most. This is the CPU analogue of Sloan 2003 §6.2's per-cluster draw calls.

All functions are batch-first; dtypes follow the inputs (float32 or float64).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["TileLayout", "tile_layout", "choose_tile", "to_tiles", "from_tiles", "tiles_bmm", "tiles_accumulate",
           "segment_matmul"]


def choose_tile(P: int, K: int) -> int:
    """Tile height: a power of two near P/(2K), clamped to [8, 256]. Expected padding ≈ K·T/2 ≤ P/4."""
    target = max(1, P // max(1, 2 * K))
    t = 8
    while t * 2 <= target and t < 256:
        t *= 2
    return t


@dataclass
class TileLayout:
    """Items (points) of K clusters cut into tiles of ``T`` rows, stored group-major.

    Attributes:
        K, T, n: clusters, tile height, number of items.
        counts: ``int64 [K]`` items per cluster; ntiles: ``int64 [K]`` tiles per cluster.
        corder: ``int64 [K]`` clusters by decreasing tile count (stable); crank: its inverse.
        groups: list of ``(t0, t1)`` tile ranges; group j holds clusters ``corder[:t1-t0]``.
        tile_cluster: ``int64 [NT]`` cluster of each tile.
        pos: ``int64 [n]`` flat tile position (tile·T + slot) of each item.
        order: ``int64 [n]`` items by increasing ``pos``; pos_sorted = pos[order] (both computed
        on first use: no caller of the fit's per-chunk layouts needs them).
    """

    K: int
    T: int
    n: int
    counts: torch.Tensor
    ntiles: torch.Tensor
    corder: torch.Tensor
    crank: torch.Tensor
    groups: list
    group_start: torch.Tensor
    tile_cluster: torch.Tensor
    pos: torch.Tensor

    @property
    def order(self) -> torch.Tensor:
        if getattr(self, "_order", None) is None:
            self._order = torch.argsort(self.pos)
        return self._order

    @property
    def pos_sorted(self) -> torch.Tensor:
        return self.pos[self.order]

    @property
    def NT(self) -> int:
        return int(self.tile_cluster.numel())

    def cluster_rows(self, ks: torch.Tensor, R: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Flat tile rows of clusters ``ks`` as ``[len(ks), R]`` (R ≥ T·max ntiles[ks]) and a mask
        of the rows that belong to the cluster (padding rows of a last tile are zero anyway)."""
        r = torch.arange(R)
        j = r // self.T
        valid = j[None, :] < self.ntiles[ks][:, None]
        gs = self.group_start[j.clamp_max(self.group_start.numel() - 1)]
        tiles = gs[None, :] + self.crank[ks][:, None]
        rows = tiles * self.T + (r % self.T)[None, :]
        return torch.where(valid, rows, torch.zeros_like(rows)), valid


def tile_layout(labels: torch.Tensor, K: int, T: int | None = None) -> TileLayout:
    """Build the group-major tile layout of ``labels`` (``int [n]`` in [0, K)). Vectorised:
    sort, bincount, cumsum."""
    labels = labels.reshape(-1).long()
    n = labels.numel()
    if T is None:
        T = choose_tile(n, K)
    counts = torch.bincount(labels, minlength=K)
    ntiles = (counts + T - 1) // T
    corder = torch.argsort(ntiles, descending=True, stable=True)
    crank = torch.empty_like(corder)
    crank[corder] = torch.arange(K)
    G = int(ntiles.max()) if K else 0
    # clusters in group j: those with ntiles > j  ->  c_j = #{k: ntiles_k > j}
    c = torch.bincount(ntiles, minlength=G + 1).flip(0).cumsum(0).flip(0)[1:G + 1] if G else torch.zeros(0, dtype=torch.long)
    group_start = torch.cumsum(c, 0) - c
    gs, cl = group_start.tolist(), c.tolist()
    groups = [(gs[j], gs[j] + cl[j]) for j in range(G)]
    NT = int(c.sum())
    tile_cluster = torch.empty(NT, dtype=torch.long)
    if NT:
        jj = torch.repeat_interleave(torch.arange(G), c)
        tile_cluster[:] = corder[torch.arange(NT) - group_start[jj]]
    # a stable sort of the labels in the smallest integer type that holds K (the same
    # permutation; uint8 / int16 keys sort several times faster than int64)
    key = labels.to(torch.uint8 if K <= 256 else torch.int16 if K <= 32768 else torch.int32) if n else labels
    order0 = torch.argsort(key, stable=True)
    sl = labels[order0]
    cstart = torch.cumsum(counts, 0) - counts
    rank = torch.arange(n) - cstart[sl]
    j = rank // T
    tile = group_start[j] + crank[sl] if n else rank
    pos = torch.empty(n, dtype=torch.long)
    pos[order0] = tile * T + rank % T
    return TileLayout(K=K, T=T, n=n, counts=counts, ntiles=ntiles, corder=corder, crank=crank, groups=groups,
                      group_start=group_start, tile_cluster=tile_cluster, pos=pos)


def to_tiles(layout: TileLayout, Y: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """``Y [n, *F]`` (item order) -> ``[NT, T, *F]`` (tile order), zero-padded."""
    rows = layout.NT * layout.T
    if out is None:
        out = Y.new_zeros((rows, *Y.shape[1:]))
    else:
        out = out[:rows]
        out.zero_()
    out.index_copy_(0, layout.pos, Y)
    return out.view(layout.NT, layout.T, *Y.shape[1:])


def from_tiles(layout: TileLayout, Yt: torch.Tensor) -> torch.Tensor:
    """``[NT, T, *F]`` (tile order) -> ``[n, *F]`` (item order)."""
    return Yt.reshape(layout.NT * layout.T, *Yt.shape[2:]).index_select(0, layout.pos)


def tiles_bmm(layout: TileLayout, Yt: torch.Tensor, W: torch.Tensor, out: torch.Tensor | None = None) -> torch.Tensor:
    """``out[t] = Yt[t] @ W[tile_cluster[t]]``: ``Yt [NT, T, D]``, ``W [K, D, r]`` -> ``[NT, T, r]``.

    One ``bmm`` per tile group against a prefix view of ``W[corder]`` (W permuted once)."""
    NT, T, D = Yt.shape
    r = W.shape[2]
    Ws = W.to(Yt.dtype).index_select(0, layout.corder)
    if out is None:
        out = Yt.new_empty((NT, T, r))
    for t0, t1 in layout.groups:  # one bmm per tile row of the largest cluster
        torch.bmm(Yt[t0:t1], Ws[: t1 - t0], out=out[t0:t1])
    return out


def tiles_accumulate(layout: TileLayout, At: torch.Tensor, Bt: torch.Tensor, out_dtype=torch.float64) -> torch.Tensor:
    """``S[k] = Σ_{tiles t of k} A_tᵀ B_t``: ``At [NT, T, D]``, ``Bt [NT, T, r]`` -> ``[K, D, r]``.

    One ``baddbmm`` per tile group into a prefix view of the cluster-permuted sum (each group
    adds a few hundred products per cluster in the input dtype), then un-permuted."""
    D, r = At.shape[2], Bt.shape[2]
    Bt = Bt.to(At.dtype)
    Ss = torch.zeros((layout.K, D, r), dtype=At.dtype)
    for t0, t1 in layout.groups:  # one batched GEMM per tile row of the largest cluster
        c = t1 - t0
        Ss[:c].baddbmm_(At[t0:t1].transpose(1, 2), Bt[t0:t1])
    S = torch.empty((layout.K, D, r), dtype=out_dtype)
    S[layout.corder] = Ss.to(out_dtype)
    return S


def segment_matmul(layout: TileLayout, X: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    """``out[i] = X[i] @ W[k(i)]``: ``X [n, D]`` (item order), ``W [K, D, r]`` -> ``[n, r]``."""
    Xt = to_tiles(layout, X)
    return from_tiles(layout, tiles_bmm(layout, Xt, W))
