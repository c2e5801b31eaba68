"""Vector quantisation kernels: k-means++ seeding and LBG / Lloyd iterations (Sloan 2003 §4.1,
"VQ Clustering": Linde, Buzo & Gray 1980), with squared distances by GEMM.

All functions take ``X [P, D]`` (float32 or float64; distances are computed in that dtype,
sums of points accumulated in float64) and optional point weights ``w [P]`` float64.
Randomness comes only from the ``torch.Generator`` passed in, so results are deterministic
per seed.

Speed (issue 15): the cost of k-means is distance evaluations — one ``[P, D] @ [D, K]`` GEMM
per full assignment, one ``[P, D] @ [D, trials]`` pass per k-means++ centre. Both skip the
points the triangle inequality proves cannot change:

* ``lloyd`` keeps Hamerly's (2010) bounds per point — an upper bound ``u`` on the distance to
  its centre and a lower bound ``l`` on the distance to every other centre, loosened by the
  centre shifts each iteration — and evaluates distances only for the points with
  ``u > max(l, s_a)`` (``s_a``: half the distance from its centre to the nearest other
  centre): first ``u`` is tightened to the exact distance (one row each), then the rest get a
  full GEMM row against all centres — unless more than ``FULL_FRACTION`` of the points are
  uncertified (then one pass assigns all of them, cheaper than gathering them) or more than
  ``TIGHTEN_FRACTION`` (then the tightening, a gather per point, is skipped). On glossy
  transfer (50k × 600, 256 clusters) about half the points stay uncertified each iteration,
  and this cut Lloyd from 4.3 to 3.0 s. Each exact row also keeps the ``NEAR`` − 1 next-nearest
  centres with a lower bound each, loosened by that centre's own shift (Elkan 2003, Lemma 2,
  for the centres that actually bound the point); only the remaining centres share Hamerly's
  bound from the ``NEAR``-th-nearest distance, loosened by the largest shift. On the 24k × 600
  scan glossy transfer (256 clusters, one thread) this left 15–50% instead of 45–100% of the
  points uncertified and cut the 20 iterations from 1.70 to 1.19–1.26 s (NEAR = 3; NEAR = 5
  1.31–1.43 s: a top-5 per row block costs 5× a top-2). Cluster sums are updated incrementally from the points
  that changed cluster (float64). The labels are those of plain Lloyd (the skipped points
  provably keep their centre; bounds carry a margin for float32 rounding).
* ``kmeans_pp`` evaluates a candidate centre only for the points within twice their current
  distance of their nearest chosen centre (``||c − c_a|| ≥ 2 d(x, c_a)`` ⇒ ``d(x, c) ≥ d(x, c_a)``),
  gathered in one block; the seeds are those of the unpruned greedy k-means++.
"""
from __future__ import annotations

import math
import os
import time

import torch

from .chunks import row_chunks, row_sq_norms

__all__ = ["BLOCK_BYTES", "CACHE_BLOCK_BYTES", "row_chunk", "linear", "gemm_choice", "sq_dists", "assign", "kmeans_pp", "seed_space",
           "lloyd", "repair_empty", "segment_sums"]

#: Bytes of one [rows, K] distance block.
BLOCK_BYTES = 64 * 2**20
#: Bytes of a distance block that is reduced (min / top-k) right after its GEMM: small enough
#: to stay in the cache between the GEMM and the reduction (faiss's blocked assignment).
CACHE_BLOCK_BYTES = 4 * 2**20

#: Relative float32/float64 rounding margin of a GEMM squared distance ``xx − 2x·c + cc``: the
#: bounds of ``lloyd`` and ``kmeans_pp`` widen by ``_ROUND[dtype]·(||x||² + max ||c||²)``.
_ROUND = {torch.float32: 64 * 2.0 ** -24, torch.float64: 64 * 2.0 ** -53}
#: ``lloyd``: above this fraction of uncertified points an iteration assigns every point (no
#: gathers); above TIGHTEN_FRACTION the candidates get their full rows without Hamerly's
#: tightening pass (whose per-point gathers cost more than they prune at that rate).
FULL_FRACTION = 0.5
TIGHTEN_FRACTION = 0.1
#: ``lloyd``: each exact distance row keeps its ``NEAR`` nearest centres; the 2nd..NEAR-th keep
#: their own lower bounds, loosened by their own shifts (Elkan's per-centre bounds, 2003, for the
#: few centres that bound a point), the rest one Hamerly bound from the (NEAR+1)-th distance.
NEAR = 3


_GEMM: dict = {}


def _onednn_linear():
    """torch's oneDNN linear kernel (``torch.ops.mkldnn._linear_pointwise``), or None."""
    try:
        op = torch.ops.mkldnn._linear_pointwise
        x, w, b = torch.ones(8, 16), torch.ones(4, 16), torch.zeros(4)
        return op if torch.allclose(op(x, w, b, "none", [], ""), x @ w.T + b) else None
    except Exception:  # noqa: BLE001 - a build without oneDNN, or the op renamed: the addmm path
        return None


def gemm_choice() -> dict:
    """Which kernel :func:`linear` uses: ``{'backend': 'onednn'|'mkl', 'how': str, 'op'}``, measured once
    per process (about 0.1 s). torch's float32 ``addmm`` goes to MKL, whose sgemm on the AMD EPYC
    of our benchmarks ran the k-means assignment GEMM ([50k, 600] @ [600, 256] in 4096-row
    blocks) in 135 ms, where torch's oneDNN linear kernel — the same OpenMP threads, so no second
    thread pool to contend with — took 88 ms. ``PRT_TORCH_ONEDNN=0`` keeps MKL."""
    if not _GEMM:
        op = None if os.environ.get("PRT_TORCH_ONEDNN", "1").strip() == "0" else _onednn_linear()
        if op is None:
            _GEMM.update(backend="mkl", how="oneDNN linear unavailable or disabled (PRT_TORCH_ONEDNN=0)", op=None)
            return _GEMM
        g = torch.Generator().manual_seed(0)
        X, W, b = torch.randn(4096, 576, generator=g), torch.randn(256, 576, generator=g), torch.randn(256, generator=g)
        tm, to = [], []
        for i in range(6):  # interleaved; the first pair warms both up
            t0 = time.perf_counter()
            torch.addmm(b[None], X, W.T)
            t1 = time.perf_counter()
            op(X, W, b, "none", [], "")
            t2 = time.perf_counter()
            if i:
                tm.append(t1 - t0)
                to.append(t2 - t1)
        fast = min(tm) > 1.1 * min(to)
        _GEMM.update(backend="onednn" if fast else "mkl", op=op if fast else None,
                     how=f"measured: MKL addmm {min(tm) * 1e3:.2f} ms, oneDNN linear {min(to) * 1e3:.2f} ms for "
                         f"[4096, 576] @ [576, 256] float32 at {torch.get_num_threads()} threads")
    return _GEMM


def linear(X: torch.Tensor, W: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``X [m, D] @ W[n, D]ᵀ + b [n]`` -> ``[m, n]`` in X's dtype, by the faster GEMM of this
    machine (:func:`gemm_choice`: oneDNN's linear for large contiguous float32 products, else
    ``addmm`` — oneDNN builds a kernel per new shape, which small products of varying shape,
    as k-means++'s, would pay every call)."""
    op = gemm_choice()["op"] if X.shape[0] * W.shape[0] * X.shape[1] >= 2**24 else None
    if op is not None and X.dtype == W.dtype == b.dtype == torch.float32 and X.is_contiguous() and W.is_contiguous():
        return op(X, W, b, "none", [], "")
    return torch.addmm(b[None, :], X, W.T)


def row_chunk(cols: int, itemsize: int = 4, block_bytes: int = BLOCK_BYTES) -> int:
    """Rows per chunk so that a [rows, cols] temporary stays near ``block_bytes``."""
    return max(256, block_bytes // max(1, cols * itemsize))


def sq_dists(X: torch.Tensor, C: torch.Tensor, xx: torch.Tensor | None = None, cc: torch.Tensor | None = None) -> torch.Tensor:
    """``||x_p − c_k||²`` = ||x||² − 2 x·c + ||c||² by one GEMM: ``[P, D], [K, D] -> [P, K]`` (≥ 0)."""
    if xx is None:
        xx = X.square().sum(1)
    if cc is None:
        cc = C.square().sum(1)
    d = linear(X, (-2.0 * C.to(X.dtype)).contiguous(), cc.to(X.dtype))
    d += xx[:, None]
    return d.clamp_min_(0)


def assign(X: torch.Tensor, C: torch.Tensor, xx: torch.Tensor | None = None,
           second: bool = False) -> tuple[torch.Tensor, ...]:
    """Nearest centre of every point: ``(labels int64 [P], d2 [P])``, and with ``second`` the
    squared distance to the second-nearest centre ``d2nd [P]`` (inf when K = 1); dtype of X.

    Row blocks of one GEMM each, ``||c||² − 2 x·c`` (``linear``: GEMM with bias), then a row min (top-2 with
    ``second``); ``||x||²`` is added to the K-wide block's minimum only (faiss's order)."""
    P = X.shape[0]
    if xx is None:
        xx = row_sq_norms(X)
    C = C.to(X.dtype)
    K = C.shape[0]
    cc = C.square().sum(1)
    Cm2 = (-2.0 * C).contiguous()  # ||c||² − 2 x·c: one GEMM with bias per block (linear)
    labels = torch.empty(P, dtype=torch.long)
    d2 = torch.empty(P, dtype=X.dtype)
    d2b = torch.full((P,), math.inf, dtype=X.dtype) if second else None
    step = min(row_chunk(K, X.element_size(), CACHE_BLOCK_BYTES), getattr(X, "rows", P) or 1)  # a streamed signal: ≤ its chunks
    for i in range(0, P, step):  # chunks bound the [rows, K] block
        d = linear(X[i:i + step].contiguous(), Cm2, cc)
        if second and K > 1:
            v, j = torch.topk(d, 2, dim=1, largest=False)
            labels[i:i + step] = j[:, 0]
            d2[i:i + step] = v[:, 0]
            d2b[i:i + step] = v[:, 1]
        else:
            m = d.min(1)
            labels[i:i + step] = m.indices
            d2[i:i + step] = m.values
    d2 += xx
    d2.clamp_min_(0)
    if second:
        d2b += xx
        d2b.clamp_min_(0)
        return labels, d2, d2b
    return labels, d2


def _assign_near(X: torch.Tensor, C: torch.Tensor, xx: torch.Tensor, m: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``m`` nearest centres of every point, ascending: ``(ids int64 [P, m], d2 [P, m])``
    (X's dtype; columns past K are ``inf``). :func:`assign`'s row blocks, a top-m per block."""
    P, K = X.shape[0], C.shape[0]
    C = C.to(X.dtype)
    cc = C.square().sum(1)
    Cm2 = (-2.0 * C).contiguous()
    k = min(m, K)
    ids = torch.zeros(P, m, dtype=torch.long)
    d2 = torch.full((P, m), math.inf, dtype=X.dtype)
    step = min(row_chunk(K, X.element_size(), CACHE_BLOCK_BYTES), getattr(X, "rows", P) or 1)
    for i in range(0, P, step):
        v, j = torch.topk(linear(X[i:i + step].contiguous(), Cm2, cc), k, dim=1, largest=False)
        ids[i:i + step, :k] = j
        d2[i:i + step, :k] = v
    d2[:, :k] += xx[:, None]
    return ids, d2.clamp_min_(0)


def segment_sums(X: torch.Tensor, labels: torch.Tensor, K: int, w: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-cluster weighted sums ``[K, D]`` and weights ``[K]``, returned as float64.

    Summed with ``index_add_`` in the dtype of X (a cluster's few hundred float32 terms lose
    about 1e-6 relative), then promoted; no float64 copy of X is made. X is a tensor or a
    ``chunks.CentredRows``; read by row blocks in point order (``index_add_`` adds the rows in
    index order, so the sums are those of one call over all rows).
    """
    D = X.shape[1]
    sums = torch.zeros(K, D, dtype=X.dtype)
    step = getattr(X, "rows", None) or (X.shape[0] if w is None else row_chunk(D, X.element_size()))
    wx = None if w is None else w.to(X.dtype)
    for i, j, x in row_chunks(X, step):  # chunks bound the (centred, weighted) temporary
        sums.index_add_(0, labels[i:j], x if wx is None else x * wx[i:j, None])
    ws = torch.bincount(labels, minlength=K).double() if w is None else torch.bincount(labels, weights=w, minlength=K).double()
    return sums.double(), ws


def repair_empty(labels: torch.Tensor, err: torch.Tensor, K: int, w: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Give every empty cluster one point: the points with the largest (weighted) error,
    taken from clusters that keep at least one other member. Returns (labels, err, repaired).

    The moved point's error becomes 0 (it is its new cluster's only member), so the total error
    does not increase. Vectorised: one topk, no loop over clusters.
    """
    labels, err, moved = _repair(labels, err, K, w)
    return labels, err, int(moved.numel())


def _repair(labels, err, K, w):
    """``repair_empty`` that also returns the indices of the moved points ``int64 [e]``."""
    none = torch.zeros(0, dtype=torch.long)
    counts = torch.bincount(labels, minlength=K)
    empty = torch.nonzero(counts == 0).flatten()
    e = int(empty.numel())
    if e == 0:
        return labels, err, none
    score = err.double() * (w if w is not None else 1.0)
    score = torch.where(counts[labels] > 1, score, torch.full_like(score, -1.0))
    e = min(e, int((counts[labels] > 1).sum()))
    if e == 0:
        return labels, err, none
    top = torch.topk(score, e).indices
    labels = labels.clone()
    err = err.clone()
    labels[top] = empty[:e]
    err[top] = 0
    return labels, err, top


def kmeans_pp(X: torch.Tensor, K: int, gen: torch.Generator, w: torch.Tensor | None = None,
              trials: int | None = None, xx: torch.Tensor | None = None) -> torch.Tensor:
    """Greedy k-means++ seeding (Arthur & Vassilvitskii 2007; scikit-learn's greedy variant):
    each new centre is the best of ``trials`` (default 2 + ⌊ln K⌋) candidates drawn with
    probability ∝ w·D². Returns the indices ``int64 [K]`` of the chosen points.

    The loop over the K centres is sequential by definition of the method; each step is one
    GEMM ``[S, D] @ [D, trials]`` over the points S that a candidate can move: those whose
    distance to their nearest chosen centre exceeds half that centre's distance to a
    candidate (the others provably keep their D²; module docstring).
    """
    P = X.shape[0]
    if trials is None:
        trials = 2 + int(math.log(K)) if K > 1 else 1
    if xx is None:
        xx = row_sq_norms(X)
    wd = torch.ones(P, dtype=torch.float64) if w is None else w.double()
    chosen = torch.empty(K, dtype=torch.long)
    chosen[0] = torch.multinomial(wd / wd.sum(), 1, generator=gen)[0]
    d2 = sq_dists(X, X[chosen[0]][None], xx, xx[chosen[0]][None]).flatten().double()
    near = torch.zeros(P, dtype=torch.long)  # index into chosen of each point's nearest centre
    Csel = torch.empty(K, X.shape[1], dtype=X.dtype)  # the chosen centres and their norms, in order
    ccsel = torch.empty(K, dtype=xx.dtype)
    Csel[0], ccsel[0] = X[chosen[0]], xx[chosen[0]]
    # rounding margin of a GEMM squared distance (both sides of the pruning test)
    margin = 2 * _ROUND.get(X.dtype, _ROUND[torch.float32]) * (xx.double() + float(xx.max()))
    for i in range(1, K):
        p = wd * d2
        s = float(p.sum())
        if not s > 0:  # every point coincides with a centre (duplicates): any point will do
            p = wd.clone()
            s = float(p.sum())
        cand = torch.multinomial(p / s, trials, replacement=True, generator=gen)
        # ||c_near − cand||² ≥ 4 d2 (with rounding margin): the candidate cannot come closer
        Xcand = X.index_select(0, cand)
        cc = sq_dists(Csel[:i], Xcand, ccsel[:i], xx[cand]).min(1).values.double()  # [i]: nearest candidate
        need = cc[near] < 4.0 * (d2 + 2 * margin)
        S = torch.nonzero(need).flatten()
        if S.numel() > P // 2:  # most points: no gather
            S = None
        XS, xxS = (X, xx) if S is None else (X.index_select(0, S), xx[S])
        dS, wS = (d2, wd) if S is None else (d2[S], wd[S])
        dc = sq_dists(XS, Xcand, xxS, xx[cand]).double()  # [|S|, trials]
        new = torch.minimum(dS[:, None], dc)
        best = int(torch.argmin((wS[:, None] * new).sum(0)))
        moved = dc[:, best] < dS
        if S is None:
            d2 = new[:, best].contiguous()
            near[moved] = i
        else:
            d2[S] = new[:, best]
            near[S[moved]] = i
        chosen[i] = cand[best]
        Csel[i] = Xcand[best]
        ccsel[i] = xx[cand[best]]
    return chosen


def seed_space(X: torch.Tensor, dims: int | None, gen: torch.Generator, power_iters: int = 2) -> torch.Tensor:
    """``X [m, D]`` in (an estimate of) its top-``dims`` principal subspace: ``X Q`` ``[m, dims]``
    (X's dtype), Q ``[D, dims]`` orthonormal from a randomized range finder (Halko et al. 2011,
    Alg. 4.3: a Gaussian start and ``power_iters`` steps of XᵀX); X itself when ``dims`` is
    None or D ≤ 2·dims. Where k-means++ seeds: distances between points of a signal whose
    energy sits in few directions (transfer) are kept to within the discarded energy, and each
    seed reads dims instead of D floats per point."""
    D = X.shape[1]
    if dims is None or D <= 2 * dims:
        return X
    Q = torch.randn(D, dims, generator=gen, dtype=torch.float64).to(X.dtype)
    for _ in range(max(1, power_iters)):
        Q = torch.linalg.qr(X.T @ (X @ Q)).Q
    return X @ Q


def lloyd(X: torch.Tensor, C0: torch.Tensor, max_iter: int, tol: float, w: torch.Tensor | None = None,
          xx: torch.Tensor | None = None) -> dict:
    """LBG / Lloyd iterations from centres ``C0 [K, D]`` (Sloan 2003 §4.1).

    Each iteration: classify every point to its nearest centre (GEMM distances, only for the
    points Hamerly's bounds cannot certify — module docstring), give empty clusters the
    worst-approximated points (``repair_empty``), move centres to the weighted means.
    Converged when no label changes, or when the total squared centre shift is ≤ tol · mean
    per-dimension variance of X (scikit-learn's criterion). A final classification makes
    labels consistent with the returned centres.

    Returns dict: ``centers [K, D] float64``, ``labels int64 [P]``, ``d2 [P]`` (X dtype),
    ``inertia`` (Σ w d2, float64), ``n_iter``, ``converged``, ``repaired`` (total moves),
    ``distance_rows`` (full K-wide distance rows evaluated, in units of P: plain Lloyd
    evaluates n_iter + 1).
    """
    K = C0.shape[0]
    P = X.shape[0]
    if xx is None:
        xx = row_sq_norms(X)
    wd = None if w is None else w.double()
    C = C0.double().clone()
    eps = _ROUND.get(X.dtype, _ROUND[torch.float32])
    # gathers of uncertified points: this many of assign's row blocks at a time (about 16 MiB)
    gather_blocks = max(1, (16 * 2**20) // max(1, row_chunk(K, X.element_size(), CACHE_BLOCK_BYTES) * X.shape[1] * X.element_size()))
    xx64 = xx.double()
    rows = 0

    def full(idx):
        """Exact labels and bounds of points ``idx`` (None: all) against all centres: ``(labels,
        u, near ids [n, NEAR-1], their lower bounds, the rest's lower bound)``. The points
        ``idx`` are gathered by blocks of ``assign``'s own row blocks (the same GEMMs as one
        gather, without a copy of up to half the signal)."""
        nonlocal rows
        if idx is None:
            ids, d2 = _assign_near(X, C, xx, NEAR + 1)
        else:
            n = idx.numel()
            ids, d2 = torch.empty(n, NEAR + 1, dtype=torch.long), torch.empty(n, NEAR + 1, dtype=X.dtype)
            step = row_chunk(K, X.element_size(), CACHE_BLOCK_BYTES) * max(1, gather_blocks)
            step = min(step, getattr(X, "rows", step) or 1)
            for i in range(0, n, step):
                sel = idx[i:i + step]
                ids[i:i + step], d2[i:i + step] = _assign_near(X.index_select(0, sel), C, xx[sel], NEAR + 1)
        m = (eps * ((xx64 if idx is None else xx64[idx]) + float(C.square().sum(1).max())))[:, None]
        rows += P if idx is None else idx.numel()
        d2 = d2.double()
        lo = (d2[:, 1:] - m).clamp_min(0).sqrt()
        return ids[:, 0], (d2[:, 0] + m[:, 0]).sqrt(), ids[:, 1:NEAR], lo[:, :NEAR - 1], lo[:, NEAR - 1]

    labels, u, nid, nlow, low = full(None)
    labels, moved = _repair_exact(X, C, labels, K, wd)
    repaired = int(moved.numel())
    u[moved] = math.inf  # moved points: bounds unknown, recomputed next iteration
    low[moved] = 0
    nlow[moved] = 0
    sums, ws = segment_sums(X, labels, K, wd)
    # mean per-dimension variance of X from the sums (scikit-learn's tol scale)
    tot = float(ws.sum())
    mean_var = max(0.0, (float((xx64 * (wd if wd is not None else 1.0)).sum()) / tot
                         - float((sums.sum(0) / tot).square().sum())) / X.shape[1])
    tol_abs = tol * mean_var
    changes, r = P, repaired
    converged = False
    it = 1
    while True:
        if it > 1 and changes == 0 and r == 0:
            converged = True
            break
        newC = torch.where(ws[:, None] > 0, sums / ws.clamp_min(1e-300)[:, None], C)
        delta = (newC - C).square().sum(1)
        shift = float(delta.sum())
        C = newC
        if shift <= tol_abs:
            converged = True
        labels, u, nid, nlow, low, sums, ws, changes, r = _bounded_step(X, xx, C, labels, u, nid, nlow, low, delta.sqrt(),
                                                                        sums, ws, wd, full, eps, xx64)
        repaired += r
        if converged or it == max_iter:
            break
        it += 1
    if r:  # moved points become their clusters' centres
        C = torch.where(ws[:, None] > 0, sums / ws.clamp_min(1e-300)[:, None], C)
    d2 = _residuals(X, C, labels)
    inertia = float((d2.double() * (wd if wd is not None else 1.0)).sum())
    return {"centers": C, "labels": labels, "d2": d2, "inertia": inertia, "n_iter": it,
            "converged": converged, "repaired": repaired, "distance_rows": rows / max(P, 1)}


def _residuals(X: torch.Tensor, C: torch.Tensor, labels: torch.Tensor, idx: torch.Tensor | None = None) -> torch.Tensor:
    """``||x_p − c_{labels_p}||²`` in X's dtype from the differences themselves (not the GEMM
    expansion), for all points or those in ``idx``; chunked. ``[P]`` or ``[len(idx)]``."""
    Cx = C.to(X.dtype)
    n = X.shape[0] if idx is None else idx.numel()
    out = torch.empty(n, dtype=X.dtype)
    step = min(row_chunk(X.shape[1], X.element_size()), getattr(X, "rows", n) or 1)  # a streamed signal: its chunks
    for i in range(0, n, step):  # chunks bound the [rows, D] difference
        if idx is None:
            xs, lab = X[i:i + step], labels[i:i + step]
        else:
            rows = idx[i:i + step]
            xs, lab = X.index_select(0, rows), labels.index_select(0, rows)
        r = Cx.index_select(0, lab).sub_(xs)
        out[i:i + step] = r.square_().sum(1)
    return out


def _repair_exact(X, C, labels, K, wd):
    """``repair_empty`` on exact errors, computed only when a cluster is empty. Returns
    (labels, indices of the moved points)."""
    if int(torch.bincount(labels, minlength=K).min()) > 0:
        return labels, torch.zeros(0, dtype=torch.long)
    labels, _, moved = _repair(labels, _residuals(X, C, labels), K, wd)
    return labels, moved


def _bounded_step(X, xx, C, labels, u, nid, nlow, low, delta, sums, ws, wd, full, eps, xx64):
    """One bounded assignment after the centres moved by ``delta [K]`` (float64), with the
    incremental update of the cluster sums. Bounds per point (all float64): ``u [P]`` on the
    distance to its centre; ``nlow [P, NEAR-1]`` on the distances to the centres ``nid`` that
    were next-nearest at its last exact row, each loosened by that centre's own shift (Elkan
    2003, Lemma 2 restricted to those centres); ``low [P]`` on every other centre, loosened by
    the largest shift of a centre other than its own (Hamerly 2010). A point keeps its label
    when ``u ≤ max(s_a, min(nlow, low))``. Returns the new (labels, u, nid, nlow, low, sums,
    ws, changes, repaired)."""
    K = C.shape[0]
    u = u + delta[labels]
    if K > 1:
        top2 = torch.topk(delta, 2)
        low = (low - torch.where(labels == top2.indices[0], top2.values[1], top2.values[0])).clamp_min(0)
        nlow = (nlow - delta[nid]).clamp_min(0)
        G = C @ C.T
        cc = G.diagonal()
        cd = (cc[:, None] + cc[None, :] - 2 * G).clamp_min(0)
        cd.fill_diagonal_(math.inf)
        s = 0.5 * cd.min(1).values.sqrt()
        bound = torch.maximum(s[labels], torch.minimum(low, nlow.min(1).values))
    else:
        bound = torch.full_like(u, math.inf)
    idx = torch.nonzero(u > bound).flatten()
    new_labels = labels
    P = X.shape[0]
    if idx.numel() > FULL_FRACTION * P:
        # most points uncertified: one exact pass over all of them costs less than gathering
        # them (measured on glossy transfer, reports/benchmarks/encode.md)
        lab, u, nid, nlow, low = full(None)
        new_labels = lab
        idx = idx[:0]
    elif 0 < idx.numel() <= TIGHTEN_FRACTION * P:
        # few candidates: tighten u to the exact distance to the own centre (one row per point);
        # with more, this gather per point would cost more than it prunes
        e2 = _residuals(X, C, labels, idx).double()
        ut = (e2 * (1 + 1e-5) + eps * (xx64[idx] + float(C.square().sum(1).max()))).sqrt()
        u[idx] = ut
        idx = idx[ut > bound[idx]]
    if idx.numel():
        lab, ua, na, nla, la = full(idx)
        new_labels = labels.clone()
        new_labels[idx] = lab
        u[idx] = ua
        nid = nid.clone()
        nid[idx] = na
        nlow[idx] = nla
        low[idx] = la
    ch = torch.nonzero(new_labels != labels).flatten()
    new_labels, moved = _repair_exact(X, C, new_labels, K, wd)
    if moved.numel():
        u[moved] = math.inf
        low[moved] = 0
        nlow[moved] = 0
        ch = torch.unique(torch.cat([ch, moved]))
    if ch.numel():
        old, new = labels[ch], new_labels[ch]
        wc = wd[ch] if wd is not None else torch.ones(ch.numel(), dtype=torch.float64)
        # the moved points' rows in float64, by blocks (all adds, then all subtractions: the
        # order of one call over all of them)
        step = min(row_chunk(X.shape[1], 8), getattr(X, "rows", P) or 1)
        sums = sums.clone()
        for sign in (1.0, -1.0):
            for i in range(0, ch.numel(), step):
                xs = X.index_select(0, ch[i:i + step]).double()
                if wd is not None:
                    xs = xs * wc[i:i + step, None]
                sums.index_add_(0, (new if sign > 0 else old)[i:i + step], xs, alpha=sign)
        ws = ws.index_add(0, new, wc).index_add_(0, old, wc, alpha=-1.0)
        ws = torch.where(torch.bincount(new_labels, minlength=K) > 0, ws, torch.zeros_like(ws))
    return new_labels, u, nid, nlow, low, sums, ws, int((new_labels != labels).sum()), int(moved.numel())
