"""Vector quantisation kernels: k-means++ seeding and LBG / Lloyd iterations (Sloan 2003 §4.1,
"VQ Clustering": Linde, Buzo & Gray 1980), with squared distances by GEMM.

All functions take ``X [P, D]`` (float32 or float64; distances are computed in that dtype,
sums of points accumulated in float64) and optional point weights ``w [P]`` float64.
Randomness comes only from the ``torch.Generator`` passed in, so results are deterministic
per seed.
"""
from __future__ import annotations

import math

import torch

__all__ = ["row_chunk", "sq_dists", "assign", "kmeans_pp", "lloyd", "repair_empty", "segment_sums"]

#: Bytes of one [rows, K] distance block.
BLOCK_BYTES = 64 * 2**20


def row_chunk(cols: int, itemsize: int = 4) -> int:
    """Rows per chunk so that a [rows, cols] temporary stays near BLOCK_BYTES."""
    return max(256, BLOCK_BYTES // max(1, cols * itemsize))


def sq_dists(X: torch.Tensor, C: torch.Tensor, xx: torch.Tensor | None = None, cc: torch.Tensor | None = None) -> torch.Tensor:
    """``||x_p − c_k||²`` = ||x||² − 2 x·c + ||c||² by one GEMM: ``[P, D], [K, D] -> [P, K]`` (≥ 0)."""
    if xx is None:
        xx = X.square().sum(1)
    if cc is None:
        cc = C.square().sum(1)
    d = torch.addmm(cc[None, :].to(X.dtype), X, C.to(X.dtype).T, beta=1.0, alpha=-2.0)
    d += xx[:, None]
    return d.clamp_min_(0)


def assign(X: torch.Tensor, C: torch.Tensor, xx: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Nearest centre of every point: ``(labels int64 [P], d2 [P])`` (chunked GEMM distances)."""
    P = X.shape[0]
    if xx is None:
        xx = X.square().sum(1)
    C = C.to(X.dtype)
    cc = C.square().sum(1)
    labels = torch.empty(P, dtype=torch.long)
    d2 = torch.empty(P, dtype=X.dtype)
    step = row_chunk(C.shape[0], X.element_size())
    for i in range(0, P, step):  # chunks bound the [rows, K] block
        d = sq_dists(X[i:i + step], C, xx[i:i + step], cc)
        m = d.min(1)
        labels[i:i + step] = m.indices
        d2[i:i + step] = m.values
    return labels, d2


def segment_sums(X: torch.Tensor, labels: torch.Tensor, K: int, w: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-cluster weighted sums ``[K, D]`` and weights ``[K]``, returned as float64.

    Summed with ``index_add_`` in the dtype of X (a cluster's few hundred float32 terms lose
    about 1e-6 relative), then promoted; no float64 copy of X is made.
    """
    D = X.shape[1]
    sums = torch.zeros(K, D, dtype=X.dtype)
    if w is None:
        sums.index_add_(0, labels, X)
        ws = torch.bincount(labels, minlength=K).double()
    else:
        wx = w.to(X.dtype)
        step = row_chunk(D, X.element_size())
        for i in range(0, X.shape[0], step):  # chunks bound the weighted temporary
            sums.index_add_(0, labels[i:i + step], X[i:i + step] * wx[i:i + step, None])
        ws = torch.bincount(labels, weights=w, minlength=K).double()
    return sums.double(), ws


def repair_empty(labels: torch.Tensor, err: torch.Tensor, K: int, w: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Give every empty cluster one point: the points with the largest (weighted) error,
    taken from clusters that keep at least one other member. Returns (labels, err, repaired).

    The moved point's error becomes 0 (it is its new cluster's only member), so the total error
    does not increase. Vectorised: one topk, no loop over clusters.
    """
    counts = torch.bincount(labels, minlength=K)
    empty = torch.nonzero(counts == 0).flatten()
    e = int(empty.numel())
    if e == 0:
        return labels, err, 0
    score = err.double() * (w if w is not None else 1.0)
    score = torch.where(counts[labels] > 1, score, torch.full_like(score, -1.0))
    e = min(e, int((counts[labels] > 1).sum()))
    if e == 0:
        return labels, err, 0
    top = torch.topk(score, e).indices
    labels = labels.clone()
    err = err.clone()
    labels[top] = empty[:e]
    err[top] = 0
    return labels, err, e


def kmeans_pp(X: torch.Tensor, K: int, gen: torch.Generator, w: torch.Tensor | None = None,
              trials: int | None = None, xx: torch.Tensor | None = None) -> torch.Tensor:
    """Greedy k-means++ seeding (Arthur & Vassilvitskii 2007; scikit-learn's greedy variant):
    each new centre is the best of ``trials`` (default 2 + ⌊ln K⌋) candidates drawn with
    probability ∝ w·D². Returns the indices ``int64 [K]`` of the chosen points.

    The loop over the K centres is sequential by definition of the method; each step is one
    GEMM over all points (``[P, D] @ [D, trials]``).
    """
    P = X.shape[0]
    if trials is None:
        trials = 2 + int(math.log(K)) if K > 1 else 1
    if xx is None:
        xx = X.square().sum(1)
    wd = torch.ones(P, dtype=torch.float64) if w is None else w.double()
    chosen = torch.empty(K, dtype=torch.long)
    chosen[0] = torch.multinomial(wd / wd.sum(), 1, generator=gen)[0]
    d2 = sq_dists(X, X[chosen[0]][None], xx, xx[chosen[0]][None]).flatten().double()
    for i in range(1, K):
        p = wd * d2
        s = float(p.sum())
        if not s > 0:  # every point coincides with a centre (duplicates): any point will do
            p = wd.clone()
            s = float(p.sum())
        cand = torch.multinomial(p / s, trials, replacement=True, generator=gen)
        dc = sq_dists(X, X[cand], xx, xx[cand]).double()  # [P, trials]
        new = torch.minimum(d2[:, None], dc)
        best = int(torch.argmin((wd[:, None] * new).sum(0)))
        d2 = new[:, best].contiguous()
        chosen[i] = cand[best]
    return chosen


def lloyd(X: torch.Tensor, C0: torch.Tensor, max_iter: int, tol: float, w: torch.Tensor | None = None,
          xx: torch.Tensor | None = None) -> dict:
    """LBG / Lloyd iterations from centres ``C0 [K, D]`` (Sloan 2003 §4.1).

    Each iteration: classify every point to its nearest centre (GEMM distances), give empty
    clusters the worst-approximated points (``repair_empty``), move centres to the weighted
    means. Converged when no label changes, or when the total squared centre shift is
    ≤ tol · mean per-dimension variance of X (scikit-learn's criterion). A final
    classification makes labels consistent with the returned centres.

    Returns dict: ``centers [K, D] float64``, ``labels int64 [P]``, ``d2 [P]`` (X dtype),
    ``inertia`` (Σ w d2, float64), ``n_iter``, ``converged``, ``repaired`` (total moves).
    """
    K = C0.shape[0]
    if xx is None:
        xx = X.square().sum(1)
    wd = None if w is None else w.double()
    mean_var = float(_weighted_var(X, wd).mean())
    tol_abs = tol * mean_var
    C = C0.double().clone()
    prev = None
    converged = False
    repaired = 0
    it = 0
    for it in range(1, max_iter + 1):
        labels, d2 = assign(X, C, xx)
        labels, d2, r = repair_empty(labels, d2, K, wd)
        repaired += r
        if prev is not None and r == 0 and torch.equal(labels, prev):
            converged = True
            break
        sums, ws = segment_sums(X, labels, K, wd)
        newC = torch.where(ws[:, None] > 0, sums / ws.clamp_min(1e-300)[:, None], C)
        shift = float((newC - C).square().sum())
        C = newC
        prev = labels
        if shift <= tol_abs:
            converged = True
            break
    labels, d2 = assign(X, C, xx)
    labels, d2, r = repair_empty(labels, d2, K, wd)
    if r:  # moved points become their clusters' centres
        sums, ws = segment_sums(X, labels, K, wd)
        C = torch.where(ws[:, None] > 0, sums / ws.clamp_min(1e-300)[:, None], C)
        repaired += r
    inertia = float((d2.double() * (wd if wd is not None else 1.0)).sum())
    return {"centers": C, "labels": labels, "d2": d2, "inertia": inertia, "n_iter": it,
            "converged": converged, "repaired": repaired}


def _weighted_var(X: torch.Tensor, w: torch.Tensor | None) -> torch.Tensor:
    """Per-dimension (weighted) variance of X, float64 ``[D]`` (chunked)."""
    P, D = X.shape
    s1 = torch.zeros(D, dtype=torch.float64)
    s2 = torch.zeros(D, dtype=torch.float64)
    tot = float(w.sum()) if w is not None else float(P)
    step = row_chunk(D, 8)
    for i in range(0, P, step):
        xs = X[i:i + step].double()
        ww = w[i:i + step, None] if w is not None else 1.0
        s1 += (xs * ww).sum(0)
        s2 += (xs.square() * ww).sum(0)
    m = s1 / tot
    return (s2 / tot - m.square()).clamp_min(0)
