"""VQ, PCA, clustered PCA (static, iterative, adaptive) and MRT-PCA (Sloan 2003 §4; Lehtinen &
Kautz 2003 §6), all fitted into the piecewise-affine model of ``affine.py``.

* ``VQ``   — LBG/Lloyd with k-means++ seeding (Sloan 2003 §4.1, "VQ Clustering"): n' = 0.
* ``PCA``  — one affine subspace (Sloan 2003 §4.1 with one cluster); ``center=False`` gives
  the linear PCA of Lehtinen & Kautz 2003 eq. (12).
* ``CPCA`` — ``method='static'``: VQ then per-cluster PCA (Sloan 2003 §4.1);
  ``'iterative'``: Kambhatla–Leen / generalised LBG — classify each point to the cluster of
  least reconstruction error, refit each cluster's PCA, adding PCA vectors one at a time with
  ``iterations`` rounds per vector (Sloan 2003 §4.2); ``'adaptive'``: then redistribute PCA
  vectors among clusters by ranking D_i²/m_k within a budget of per-point weights
  (Sloan 2003 §4.3).
* ``MRTPCA`` — PCA directly on MRT matrices A_p, relit with the 4-tap eq. (13).

Speed (the fit is batched over clusters; no Python loop over clusters or points):
* the signal is kept in cluster-tile order during the fit (``segment``), so per-cluster
  means, scatter products and projections are batched GEMMs;
* per-cluster PCA is an exact batched eigensolve for small K·D³, else a warm-started block
  subspace iteration whose span contains the previous basis (so no refit increases error);
* k-means: Hamerly-bounded Lloyd and pruned k-means++ (``kmeans``);
* iterative stages before the last stop when a round gains less than ``stage_tol``; warm
  refits add 2 random columns to the warm basis (its power step carries the subspace);
* classification at the start of each vector stage is exact over all clusters (one GEMM
  against all representatives); the other rounds of that stage compare each point only
  with the ``candidates`` clusters its cluster's members found best in that exact pass
  (``candidates=0``: exact over all clusters every round). A point's own cluster is always a
  candidate, so a round never increases the error.
"""
from __future__ import annotations

import math

import torch

from .affine import AffineCodec, classify_all
from ..params import Boolean, Interval, Options
from .base import register
from .kmeans import kmeans_pp, lloyd, repair_empty, seed_space, segment_sums
from .chunks import CentredRows, row_sq_norms, spans
from .segment import choose_tile, from_tiles, tile_layout, tiles_bmm, to_tiles
from .subspace import TileSource, cluster_pca, total_variance

__all__ = ["VQ", "PCA", "CPCA", "CPCAStatic", "CPCAIterative", "CPCAAdaptive", "MRTPCA"]

_VQ_CONSTRAINTS = {
    "clusters": [Interval(int, 1, None)],
    "max_iter": [Interval(int, 1, None)],
    "tol": [Interval(float, 0, None)],
    "n_init": [Interval(int, 1, None)],
    "init": [Options("k-means++", "random")],
    "init_sample": [Interval(int, 1, None), None],
    "init_dims": [Interval(int, 1, None), None],
}
_PCA_CONSTRAINTS = {
    "vectors": [Interval(int, 0, None)],
    "solver": [Options("auto", "eigh", "svd", "randomized", "krylov")],
    "oversample": [Interval(int, 0, 256)],
    "power_iters": [Interval(int, 0, 50)],
}

# numpydoc entries shared by the class docstrings below (each class lists all its parameters)
_DOC_VQ = """
    clusters : int, default=64
        Number of clusters m_c.
    tol : float, default=1e-4
        Lloyd stops when the squared centre shift ≤ tol · mean per-dimension variance.
    n_init : int, default=1
        k-means restarts (different seeds); the lowest error is kept.
    init : {'k-means++', 'random'}, default='k-means++'
        Seeding of the cluster centres.
    init_sample : int or None, default=None
        k-means++ draws its seeds from a random subset of this many points (default
        32·clusters for ``vq``, 64·clusters for CPCA; all points when fewer; each seed costs one
        pass over the subset — faiss likewise trains on a subsample). ``vq`` at 32·clusters
        instead of 64·clusters: on the 24k × 600 scan glossy transfer (256 clusters) seeding
        0.2–0.4 s faster at one thread, final SE 1526.8 / 1519.2 instead of 1527.7 / 1521.2
        (seeds 1, 2); on the synthetic 50k × 625 3.225e4 instead of 3.150e4 (seed 1), faiss's
        3.99e4. CPCA keeps 64·clusters: one iterative fit on the glossy case took 77 s of CPU
        at 32·clusters against 46 s at 64·clusters (one run each, load 5; not investigated).
    init_dims : int or None, default=64 (vq), None (cpca)
        k-means++ measures distances in the top ``init_dims`` principal directions of its
        sample (``kmeans.seed_space``; the seeds are still data points, Lloyd then works in
        full dimension); None, or D ≤ 2·init_dims: full dimension. Each seed then reads
        init_dims instead of D floats per sampled point: on glossy transfer (50k × 600, 256
        clusters, 20 Lloyd iterations) seeding took 0.4 instead of 1.6 s, and the final SE was
        3510–3524 over seeds 1–3 (full-dimension seeds: 3498–3522 over seeds 0–2; faiss's
        random seeds: 3567–3583), i.e. within seeding luck (reports/benchmarks/encode.md)."""
_DOC_PCA = """
    solver : {'auto', 'eigh', 'svd', 'randomized', 'krylov'}, default='auto'
        eigh: Sloan 2003 §4.1 normal form (CᵀC or CCᵀ by shape); svd; randomized: subspace
        iteration; krylov: randomized block Krylov (Musco & Musco 2015; ``subspace``); auto:
        eigh when K·D³ is small, else randomized (one-cluster PCA of wide rows, P < 4D: krylov
        where it would be randomized — the same passes over the data at half the width, at the
        optimum's error on slowly decaying spectra).
    oversample : int in [0, 256], default=8
        Extra random columns of a cold randomized start (warm starts: at most 2); krylov:
        blocks of ⌈(n' + oversample)/2⌉ columns.
    power_iters : int in [0, 50], default=3
        Power steps of a cold randomized start (warm starts use 1); krylov: passes over the
        data (Krylov blocks)."""
#: One global subspace (pca, mrt_pca): 6 power steps with 16 extra columns reach scikit-learn's
#: randomized-PCA error (7 iterations, 10 extra columns) — n' = 8 on 50k × 625 synthetic transfer:
#: SE 300156.24 vs scikit-learn's 300156.28 (3 steps, 8 columns: 300562.59), in 0.75 s against its
#: 1.0 s; glossy 50k × 600: 10435.84 vs 10435.85 (reports/benchmarks/encode.md)
_PCA_POWER_ITERS = 6
_PCA_OVERSAMPLE = 16
_DOC_PCA_GLOBAL = (_DOC_PCA.replace("power_iters : int in [0, 50], default=3", f"power_iters : int in [0, 50], default={_PCA_POWER_ITERS}")
                   .replace("oversample : int in [0, 256], default=8", f"oversample : int in [0, 256], default={_PCA_OVERSAMPLE}"))
_DOC_COMMON = """
    seed : int, default=0
        Random seed (k-means++ draws, random subspace starts); results are deterministic per seed.
    fit_dtype : {'auto', 'float32', 'float64'}, default='auto'
        Working precision of the fit; auto: float64 when P·D ≤ 2^23, else float32 (sums in float64).
    strict : bool, default=False
        Raise ConvergenceError instead of warning when an iteration limit is hit."""


def _doc(summary: str, *entries: str) -> str:
    """A numpydoc class docstring: ``summary`` then a "Parameters" section of ``entries``."""
    return summary + "\n\n    Parameters\n    ----------" + "".join(entries) + "\n    "


# ----------------------------------------------------------------------------------------
# fit machinery
# ----------------------------------------------------------------------------------------

class _Tiles:
    """One chunk of rows ``[i, j)`` of the centred signal in cluster-tile order: its layout, the
    rows ``Xt [NT, T, D]``, the sqrt weights ``swt [NT, T]`` (zero on padding rows) and the flat
    padding rows."""

    def __init__(self, i: int, j: int, labels: torch.Tensor, x: torch.Tensor, sw: torch.Tensor | None, K: int, T: int,
                 raw: torch.Tensor):
        self.i, self.j = i, j
        lay = tile_layout(labels, K, T)
        self.layout, self.tc = lay, lay.tile_cluster
        if K == 1 and j - i == T:  # one cluster, a chunk of exactly one tile: the rows themselves, no copy
            self.Xt = x.view(1, T, x.shape[1])
        else:
            self.Xt = to_tiles(lay, x, out=raw)
        self.swt = to_tiles(lay, torch.ones(j - i, dtype=x.dtype) if sw is None else sw)
        used = torch.zeros(lay.NT * T, dtype=torch.bool)
        used[lay.pos] = True
        self.pad_rows = torch.nonzero(~used).flatten()
        self.xxt = None


class _Work:
    """The centred signal with the current cluster labels, read in cluster-tile order chunk by
    chunk (``chunks``): a signal of one chunk (``Xc`` a tensor) keeps its tiles between passes,
    as the whole fit used to; a streamed one (``Xc`` a ``chunks.CentredRows``) rebuilds each
    chunk's tiles in two reused buffers of one chunk's size per pass, so the signal is held
    once (by the caller, or on disk) plus O(chunk) work memory (issue 42 part 3). Per point it
    keeps the labels, ``||x||²`` and, weighted, ``sqrt(w)``."""

    def __init__(self, Xc, w: torch.Tensor | None, K: int, centred: bool = True):
        self.X, self.w, self.K, self.centred = Xc, w, K, centred
        self.P, self.D = Xc.shape
        self.dt = Xc.dtype
        self.streamed = isinstance(Xc, CentredRows)
        self.spans = spans(self.P, Xc.rows) if self.streamed else [(0, self.P)]
        n = self.spans[0][1] - self.spans[0][0]  # rows of the largest chunk
        # one cluster: a chunk is one tile (256-row tiles padded a 260-row chunk of a streamed
        # 16 128-wide signal to 512 rows: twice the GEMM work of every pass)
        self.T = choose_tile(n, K) if K > 1 else n
        self._xx = None  # ||x_p||², computed when a classification first needs it (not by PCA)
        self.sw = None if w is None else w.sqrt().to(self.dt)
        rows = n + K * (self.T - 1) if K > 1 else n
        self._raw = torch.empty(rows, self.D, dtype=self.dt)
        self._y = torch.empty(rows, self.D, dtype=self.dt)
        self.labels = None
        self._one = None  # the one chunk's tiles (a signal of one chunk)
        self.cache: dict = {}

    def set_labels(self, labels: torch.Tensor) -> None:
        self.labels = labels
        self.counts = torch.bincount(labels, minlength=self.K)
        # one chunk (a small signal, or a streamed one within one chunk): its tiles are kept
        # between passes (at most one chunk's size)
        self._one = self._tiles(0, self.P) if len(self.spans) == 1 else None

    def _tiles(self, i: int, j: int) -> _Tiles:
        x = self.X if not self.streamed else self.X[i:j]
        return _Tiles(i, j, self.labels[i:j], x, None if self.sw is None else self.sw[i:j], self.K, self.T, self._raw)

    def chunks(self):
        """The chunks of rows in tile order, in row order (one cached chunk, or built afresh)."""
        if self._one is not None:
            yield self._one
            return
        for i, j in self.spans:
            yield self._tiles(i, j)

    @property
    def xx(self) -> torch.Tensor:
        """``||x_p||²`` ``[P]`` (X's dtype), computed once on first use."""
        if self._xx is None:
            self._xx = row_sq_norms(self.X, norm=True)
        return self._xx

    def means(self) -> torch.Tensor:
        """Weighted cluster means [K, D] float64 (x_0, Sloan 2003 §4.1); empty clusters: 0.
        Streamed: ``kmeans.segment_sums`` of the rows as read (no tile order needed)."""
        if self._one is None:
            sums, ws = segment_sums(self.X, self.labels, self.K, self.w)
            return sums / ws.clamp_min(1e-300)[:, None]
        sums = torch.zeros(self.K, self.D, dtype=torch.float64)
        ws = torch.zeros(self.K, dtype=torch.float64)
        for c in self.chunks():
            w2 = c.swt.square()
            if self.sw is None:  # padding rows are zero: a plain per-tile sum
                s = c.Xt.sum(1).double()
            else:
                s = torch.bmm(w2[:, None, :], c.Xt).squeeze(1).double()
            sums.index_add_(0, c.tc, s)
            ws.index_add_(0, c.tc, w2.sum(1).double())
        return sums / ws.clamp_min(1e-300)[:, None]

    def _centred_tiles(self, c: _Tiles, means: torch.Tensor | None) -> torch.Tensor:
        """``Yt = sqrt(w) (x − x_0)`` of chunk ``c`` in its tile order, zero on padding rows (in
        the reused work buffer)."""
        Yt = self._y[: c.Xt.shape[0] * self.T].view_as(c.Xt)
        if means is not None:
            torch.sub(c.Xt, means.to(self.dt)[c.tc][:, None, :], out=Yt)
            if self.sw is None:
                Yt.view(-1, self.D).index_fill_(0, c.pad_rows, 0)
            else:
                Yt *= c.swt[..., None]
        else:
            Yt.copy_(c.Xt)
            if self.sw is not None:
                Yt *= c.swt[..., None]
        return Yt

    def refit(self, n: int, solver: str, gen, init=None, oversample=8, power_iters=3, alloc=None) -> dict:
        """Means, top-n PCA vectors and squared error of the current clusters (Sloan 2003 §4.1)."""
        means = self.means() if self.centred else None
        pi = power_iters if init is None or init.shape[1] == 0 else 1
        if self._one is not None:  # one chunk: its centred tiles once, for every product
            Yt = self._centred_tiles(self._one, means)
            basis, evals = cluster_pca(self._one.layout, Yt, n, solver, gen=gen, init=init,
                                       oversample=oversample, power_iters=pi, cache=self.cache)
            tv = total_variance(self._one.layout, Yt)
        else:  # streamed: every product is a pass over the chunks, each centred when read
            tvs = []

            def tiles():  # one pass; its per-cluster Σ||y||² noted on the way (the last pass's is kept)
                tv = torch.zeros(self.K, dtype=torch.float64)
                for c in self.chunks():
                    Yt = self._centred_tiles(c, means)
                    yield c.layout, Yt
                    tv += total_variance(c.layout, Yt)
                tvs.append(tv)

            src = TileSource(self.K, self.D, self.dt, tiles)
            basis, evals = cluster_pca(src, None, n, solver, gen=gen, init=init, oversample=oversample,
                                       power_iters=pi, cache=self.cache, counts=self.counts)
            if not tvs:  # no pass ran (n = 0)
                list(tiles())
            tv = tvs[-1]
        return {"labels": self.labels, "means": means, "basis": basis, "evals": evals, "tv": tv,
                "n_vectors": torch.full((self.K,), n, dtype=torch.long), "se": float(tv.sum() - evals.sum())}

    def classify_candidates(self, st: dict, cand: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Least reconstruction error among each cluster's candidate clusters ``cand [K, L]``
        (own cluster first), in tile order: one tile-GEMM against the candidates' stacked
        representatives ``[−2 x_0, x_i]`` with the constants ``[||x_0||², −x_i·x_0]`` added after
        (as ``classify_all``), chunk by chunk. Returns (labels [P], e_min [P])."""
        means, basis = st["means"], st["basis"]
        K, n, D = basis.shape
        L = cand.shape[1]
        if means is None:
            means = torch.zeros(K, D, dtype=torch.float64)
        Wall = torch.cat([-2.0 * means[:, None], basis], 1).to(self.dt)  # [K, 1+n, D]
        # [K, D, L(1+n)] made contiguous once: tiles_bmm permutes it per chunk, and a strided gather of
        # 16 x 16 128 x 64 floats per 260-row chunk of wide rows cost more than the chunk's GEMM
        Wc = Wall[cand].reshape(K, L * (1 + n), D).transpose(1, 2).contiguous()
        bias = torch.cat([means.square().sum(1)[:, None], -torch.einsum("knd,kd->kn", basis, means)], 1)
        bc = bias[cand].reshape(K, L * (1 + n)).to(self.dt)  # [K, L(1+n)]
        labels = torch.empty(self.P, dtype=torch.long)
        emin = torch.empty(self.P, dtype=self.dt)
        for c in self.chunks():
            if c.xxt is None:
                c.xxt = to_tiles(c.layout, self.xx[c.i:c.j])
            E = tiles_bmm(c.layout, c.Xt, Wc)
            E += bc[c.tc][:, None, :]
            E = E.view(*c.Xt.shape[:2], L, 1 + n)
            e = E[..., 0] - E[..., 1:].square_().sum(-1) if n else E[..., 0]
            m = e.min(-1)
            lab_t = torch.gather(cand[c.tc][:, None, :].expand(-1, self.T, -1), 2, m.indices[..., None]).squeeze(-1)
            labels[c.i:c.j] = from_tiles(c.layout, lab_t[..., None]).squeeze(-1)
            emin[c.i:c.j] = from_tiles(c.layout, (m.values + c.xxt).clamp_min(0)[..., None]).squeeze(-1)
        return labels, emin


def _candidate_sets(labels: torch.Tensor, top: torch.Tensor, K: int, L: int) -> torch.Tensor:
    """Per-cluster candidates ``[K, L]``: the cluster itself, then the clusters most often among
    its members' ``top`` choices (one bincount over (cluster, choice) pairs)."""
    L = min(L, K)
    cnt = torch.zeros(K * K, dtype=torch.float64)
    step = 1 << 18
    for i in range(0, labels.numel(), step):  # blocks bound the [rows, L] int64 pairs
        pairs = (labels[i:i + step, None] * K + top[i:i + step].long()).flatten()
        cnt += torch.bincount(pairs, minlength=K * K).double()
    cnt = cnt.view(K, K)
    cnt[torch.arange(K), torch.arange(K)] = math.inf
    return torch.topk(cnt, L, dim=1).indices


def _allocate(evals: torch.Tensor, counts: torch.Tensor, budget: float) -> torch.Tensor:
    """Sloan 2003 §4.3: rank PCA vectors of all clusters by D_i²/m_k (error reduction per
    stored weight), add them in decreasing order while Σ_k m_k n_k ≤ budget. ``[K]`` int64."""
    K, nmax = evals.shape
    m = counts.double().clamp_min(1)[:, None]
    gain = torch.where((counts[:, None] > 0) & (evals > 0), evals / m, torch.full_like(evals, -1.0))
    flat = gain.flatten()
    order = torch.argsort(flat, descending=True, stable=True)
    useful = flat[order] > 0
    cost = counts.double()[order // nmax]
    take = (torch.cumsum(cost, 0) <= budget + 1e-9) & useful
    take = take & (torch.cumsum((~take).long(), 0) == 0)  # a prefix of the ranking
    return torch.bincount(order[take] // nmax, minlength=K)


def _mask_basis(st: dict, nvec: torch.Tensor) -> dict:
    nmax = st["basis"].shape[1]
    keep = torch.arange(nmax)[None, :] < nvec[:, None]
    out = dict(st)
    out["basis"] = st["basis"] * keep[..., None]
    out["n_vectors"] = nvec
    out["se"] = float(st["tv"].sum() - (st["evals"] * keep).sum())
    return out


# ----------------------------------------------------------------------------------------
# codecs
# ----------------------------------------------------------------------------------------

class _VQMixin:
    #: k-means++'s default sample: this many points per cluster (``init_sample=None``)
    _init_per_cluster = 64

    @property
    def n_iter_(self) -> int:
        """LBG/Lloyd iterations of the fit's clustering (CPCA: of its initial VQ), as scikit-learn's
        ``KMeans.n_iter_``; ``fit_info_['lloyd_iterations']``."""
        try:
            return int(self.fit_info_["lloyd_iterations"])
        except (AttributeError, KeyError):
            raise AttributeError(f"{type(self).__name__} has no n_iter_ before a fit") from None

    def _run_vq(self, Xc, w, gen, K, final):
        """LBG from k-means++ (or random) seeds; ``final``: the clustering is the codec's result,
        so stopping at max_iter warns (CPCA records it in fit_info_ and warns only if strict)."""
        p = self.params
        xx = row_sq_norms(Xc)
        best = None
        for r in range(p["n_init"]):  # restarts: a handful, each a full batched fit
            if p["init"] == "k-means++":
                m = p["init_sample"] or self._init_per_cluster * K
                d = p.get("init_dims")
                if m < Xc.shape[0]:
                    sub = torch.randperm(Xc.shape[0], generator=gen)[:m]
                    Z = seed_space(Xc.index_select(0, sub), d, gen)
                    idx = sub[kmeans_pp(Z, K, gen, None if w is None else w[sub], xx=xx[sub] if Z.shape[1] == Xc.shape[1] else None)]
                else:  # all points are candidates (at most init_sample of them): held whole here
                    Z = seed_space(Xc.materialize() if isinstance(Xc, CentredRows) else Xc, d, gen)
                    idx = kmeans_pp(Z, K, gen, w, xx=xx if Z.shape[1] == Xc.shape[1] else None)
            else:
                pw = torch.ones(Xc.shape[0], dtype=torch.float64) if w is None else w.double()
                idx = torch.multinomial(pw / pw.sum(), K, replacement=False, generator=gen)
            res = lloyd(Xc, Xc.index_select(0, idx), p["max_iter"], p["tol"], w, xx)
            if best is None or res["inertia"] < best["inertia"]:
                best = res
        if not best["converged"] and (final or p["strict"]):
            self._warn_or_raise(
                f"codec {self.codec_name!r}: LBG/Lloyd did not converge in max_iter={p['max_iter']} "
                f"iterations (tol={p['tol']}); the clustering is usable but not a fixed point — "
                "raise max_iter or tol")
        return best


@register("vq")
class VQ(_VQMixin, AffineCodec):
    _init_per_cluster = 32
    __doc__ = _doc("""Vector quantisation (LBG with k-means++ seeding): n' = 0 (Sloan 2003 §4.1).""", _DOC_VQ, """
    max_iter : int, default=50
        LBG/Lloyd iteration limit (Sloan 2003 used 20).""", _DOC_COMMON)

    codec_name = "vq"
    _parameter_constraints = {**AffineCodec._parameter_constraints, **_VQ_CONSTRAINTS}

    def __init__(self, *, clusters=64, max_iter=50, tol=1e-4, n_init=1, init="k-means++", init_sample=None,
                 init_dims=64, seed=0, fit_dtype="auto", strict=False):
        self.clusters = clusters
        self.max_iter = max_iter
        self.tol = tol
        self.n_init = n_init
        self.init = init
        self.init_sample = init_sample
        self.init_dims = init_dims
        self.seed = seed
        self.fit_dtype = fit_dtype
        self.strict = strict

    def _check_data(self, P, D, ms):
        K = self.params["clusters"]
        if K > P:
            raise ValueError(f"clusters={K} exceeds the number of points P={P} (n_samples = {P}); accepted: 1..{P}")

    def _fit_model(self, Xc, w, gen):
        K = self.params["clusters"]
        r = self._run_vq(Xc, w, gen, K, final=True)
        return {"labels": r["labels"], "means": r["centers"], "basis": torch.zeros(K, 0, Xc.shape[1], dtype=torch.float64),
                "n_vectors": torch.zeros(K, dtype=torch.long),
                "info": {"inertia": r["inertia"], "lloyd_iterations": r["n_iter"], "converged": r["converged"],
                         "empty_repairs": r["repaired"]}}


def _resolve_solver(solver: str, K: int, D: int, limit: float) -> str:
    if solver != "auto":
        return solver
    return "eigh" if K * D ** 3 <= limit else "randomized"


@register("pca")
class PCA(AffineCodec):
    __doc__ = _doc("""One global affine subspace: mean + n' PCA vectors (Sloan 2003 §4.1 with m_c = 1).""", """
    vectors : int, default=8
        PCA vectors n'.
    center : bool, default=True
        Subtract the mean (affine PCA); false: linear PCA as Lehtinen & Kautz 2003 eq. (12).""",
                   _DOC_PCA_GLOBAL, _DOC_COMMON)

    codec_name = "pca"
    _parameter_constraints = {**AffineCodec._parameter_constraints, **_PCA_CONSTRAINTS, "center": [Boolean()]}

    def __init__(self, *, vectors=8, center=True, solver="auto", oversample=_PCA_OVERSAMPLE, power_iters=_PCA_POWER_ITERS,
                 seed=0, fit_dtype="auto", strict=False):
        self.vectors = vectors
        self.center = center
        self.solver = solver
        self.oversample = oversample
        self.power_iters = power_iters
        self.seed = seed
        self.fit_dtype = fit_dtype
        self.strict = strict

    def _check_data(self, P, D, ms):
        p = self.params
        n = p["vectors"]
        hi = D if not p["center"] else D - 1
        if n > hi:
            raise ValueError(f"vectors={n} must be < D={D} (n_features = {D}; n' < n, Sloan 2003 §3.3)" if p["center"]
                             else f"vectors={n} exceeds D={D} (n_features = {D}); accepted: 0..{D}")

    def _fit_model(self, Xc, w, gen):
        P, D = Xc.shape
        p = self.params
        n = p["vectors"]
        solver = p["solver"]
        if solver == "auto":  # big signals: subspace iteration by GEMMs over the data, not the D×D scatter
            big = P * D > 2**23 and P >= 4 * D and n + p["oversample"] <= D // 4
            solver = "randomized" if big else _resolve_solver("auto", 1, D, 4e8)
            # wide rows (P < 4D, e.g. 10 242 × 16 128 transport tables): block Krylov, the same passes at
            # half the width (subspace.py); tall signals keep the subspace iteration (there the passes are
            # bound by reading the rows, not by the GEMM width: 50 000 × 625, n' = 2-16, no faster)
            solver = "krylov" if solver == "randomized" and P < 4 * D else solver
        work = _Work(Xc, w, 1, centred=p["center"])
        work.set_labels(torch.zeros(P, dtype=torch.long))
        st = work.refit(n, solver, gen, oversample=p["oversample"], power_iters=p["power_iters"])
        means = st["means"]
        return {"labels": work.labels, "means": means, "basis": st["basis"], "n_vectors": st["n_vectors"],
                "info": {"solver": solver, "eigenvalues": st["evals"][0].tolist(), "se_model": st["se"],
                         "total_variance": float(st["tv"].sum())}}


@register("cpca")
class CPCA(_VQMixin, AffineCodec):
    __doc__ = _doc("""Clustered PCA: per-cluster affine subspaces (Sloan 2003 §3.3–4.3).""", _DOC_VQ, """
    max_iter : int, default=20
        LBG iterations of the initial VQ (Sloan 2003 §4.1 used 20).
    vectors : int, default=8
        PCA vectors n' per cluster (adaptive: the mean per point, see budget).""", _DOC_PCA, """
    method : {'static', 'iterative', 'adaptive'}, default='iterative'
        static (§4.1), iterative (§4.2) or adaptive (§4.3).
    iterations : int, default=10
        Classify/refit rounds per added PCA vector (Sloan 2003: 10-20).
    candidates : int, default=8
        Clusters compared per point between exact passes (0: all, every round).
    stage_tol : float, default=1e-2
        Iterative: a stage before the last ends once a round lowers the SE by less than this
        fraction (0: always ``iterations`` rounds); the last stage runs ``iterations`` rounds.
        Measured at 256 clusters × 8 vectors (reports/benchmarks/encode.md): 1e-2 against 5e-3
        took 23.0 instead of 30.3 s on glossy transfer (50k × 600) for SE 201.75 instead of
        202.94, and 24.8 instead of 28.3 s on 50k × 625 synthetic transfer at the same SE.
    budget : float or None, default=None
        Adaptive: mean per-point PCA weights Σ m_k n_k / P (default: vectors).
    max_vectors : int or None, default=None
        Adaptive: most PCA vectors one cluster may take (default: 2·vectors, < D).
    adapt_iters : int, default=5
        Adaptive: classify/refit/redistribute rounds (Sloan 2003 §4.3).""", _DOC_COMMON)

    codec_name = "cpca"
    _parameter_constraints = {
        **AffineCodec._parameter_constraints, **_VQ_CONSTRAINTS, **_PCA_CONSTRAINTS,
        "method": [Options("static", "iterative", "adaptive")],
        "iterations": [Interval(int, 1, None)],
        "candidates": [Interval(int, 0, None)],
        "stage_tol": [Interval(float, 0, None)],
        "budget": [Interval(float, 0, None), None],
        "max_vectors": [Interval(int, 1, None), None],
        "adapt_iters": [Interval(int, 1, None)],
    }

    def __init__(self, *, clusters=64, max_iter=20, tol=1e-4, n_init=1, init="k-means++", init_sample=None, init_dims=None,
                 vectors=8, solver="auto", oversample=8, power_iters=3, method="iterative", iterations=10,
                 candidates=8, stage_tol=1e-2, budget=None, max_vectors=None, adapt_iters=5, seed=0, fit_dtype="auto",
                 strict=False):
        self.clusters = clusters
        self.max_iter = max_iter
        self.tol = tol
        self.n_init = n_init
        self.init = init
        self.init_sample = init_sample
        self.init_dims = init_dims
        self.vectors = vectors
        self.solver = solver
        self.oversample = oversample
        self.power_iters = power_iters
        self.method = method
        self.iterations = iterations
        self.candidates = candidates
        self.stage_tol = stage_tol
        self.budget = budget
        self.max_vectors = max_vectors
        self.adapt_iters = adapt_iters
        self.seed = seed
        self.fit_dtype = fit_dtype
        self.strict = strict

    def _check_params(self, p):
        if p["method"] != "adaptive":
            for k in ("budget", "max_vectors"):
                if p[k] is not None:
                    raise ValueError(f"{k}={p[k]!r} applies only to method='adaptive' (method={p['method']!r})")
        else:
            mv = p["max_vectors"] if p["max_vectors"] is not None else max(1, 2 * p["vectors"])
            b = p["budget"] if p["budget"] is not None else float(p["vectors"])
            if b > mv:
                raise ValueError(f"budget={b} mean weights per point cannot be met with max_vectors={mv} per cluster; "
                                 f"accepted: budget <= max_vectors")

    def _check_data(self, P, D, ms):
        p = self.params
        if p["clusters"] > P:
            raise ValueError(f"clusters={p['clusters']} exceeds the number of points P={P} (n_samples = {P}); accepted: 1..{P}")
        if p["vectors"] >= D:
            raise ValueError(f"vectors={p['vectors']} must be < D={D} (n_features = {D}; n' < n, Sloan 2003 §3.3); accepted: 0..{D - 1}")
        if p["method"] == "adaptive":
            mv = p["max_vectors"] if p["max_vectors"] is not None else min(D - 1, max(1, 2 * p["vectors"]))
            if mv >= D:
                raise ValueError(f"max_vectors={mv} must be < D={D}; accepted: 1..{D - 1}")
            b = p["budget"] if p["budget"] is not None else float(p["vectors"])
            if b > mv:
                raise ValueError(f"budget={b} mean weights per point cannot be met: at most max_vectors={mv} "
                                 f"vectors per cluster (D={D}); accepted: budget <= {mv}")

    def _fit_model(self, Xc, w, gen):
        p = self.params
        P, D = Xc.shape
        K, n = p["clusters"], p["vectors"]
        method = p["method"]
        limit = 4e8 if method == "static" else 5e7
        solver = _resolve_solver(p["solver"], K, D, limit)
        kw = {"oversample": p["oversample"], "power_iters": p["power_iters"]}
        info = {"solver": solver, "method": method}
        vq = self._run_vq(Xc, w, gen, K, final=False)
        info.update(lloyd_iterations=vq["n_iter"], vq_converged=vq["converged"], vq_se=vq["inertia"])
        work = _Work(Xc, w, K)
        work.set_labels(vq["labels"])
        static = work.refit(n, solver, gen, **kw)
        info["static_se"] = static["se"]
        best = static
        if method in ("iterative", "adaptive") and n > 0:
            best = self._iterative(work, vq, static, solver, gen, kw, info)
        if method == "adaptive":
            best = self._adaptive(work, best, solver, gen, kw, info, D)
        info["se_model"] = best["se"]
        info["n_vectors_hist"] = torch.bincount(best["n_vectors"]).tolist()
        return {"labels": best["labels"], "means": best["means"], "basis": best["basis"],
                "n_vectors": best["n_vectors"], "info": info}

    # -- Sloan 2003 §4.2 ------------------------------------------------------------------
    def _rounds(self, work, st, n, solver, gen, kw, rounds, L, cand=None, rtol=0.0):
        """Generalised LBG rounds at fixed n: [classify, refit] × rounds. The first
        classification is exact over all clusters unless candidate sets ``cand [K, L]`` are
        given; later ones are among the candidate sets (L > 0) built from that exact pass.
        Stops when no label changes, or (``rtol`` > 0) when a round lowers the SE by less than
        ``rtol`` of it. Returns the best state, the label changes per round and the
        candidate sets."""
        changes = []
        best = st
        for r in range(rounds):
            if cand is None:
                labels, emin, top = classify_all(work.X, work.xx, st["means"], st["basis"], top=L if L else 0)
            else:
                labels, emin = work.classify_candidates(st, cand)
            labels, emin, _ = repair_empty(labels, emin, work.K, work.w)
            ch = int((labels != work.labels).sum())
            changes.append(ch)
            if ch == 0:
                break
            work.set_labels(labels)
            if L and cand is None:
                cand = _candidate_sets(labels, top, work.K, L)
            prev = st["se"]
            st = work.refit(n, solver, gen, init=st["basis"], **kw)
            if st["se"] < best["se"]:
                best = st
            if prev - st["se"] < rtol * prev:  # the stage has stalled
                break
        return best, changes, cand

    def _iterative(self, work, vq, static, solver, gen, kw, info):
        """Sloan 2003 §4.2: PCA vectors added one at a time, ``iterations`` rounds per vector.

        Speed: the stages before the last stop once a round gains less than ``stage_tol``
        (they steer the clusters away from poor local minima; the last stage decides the
        error); and when the incremental path reaches n vectors with more error than the
        static fit, the last stage continues from the static fit instead of running a second
        full last stage afterwards (the rounds never increase error, so the result is never
        worse than static). Each stage starts with an exact classification over all clusters
        (candidate sets carried across stages cost 2% of SE on glossy transfer)."""
        p = self.params
        n, L = p["vectors"], p["candidates"]
        st = {"labels": vq["labels"], "basis": torch.zeros(work.K, 0, work.D, dtype=torch.float64)}
        stages = []
        work.set_labels(vq["labels"])
        for j in range(1, n + 1):  # add PCA vectors one at a time (Sloan 2003 §4.2)
            st = work.refit(j, solver, gen, init=st["basis"], **kw)
            last = j == n
            if last and st["se"] > static["se"]:
                info["restarted_from_static"] = {"incremental_se": st["se"], "static_se": static["se"]}
                work.set_labels(static["labels"])
                st = static
            st, changes, _ = self._rounds(work, st, j, solver, gen, kw, p["iterations"], L,
                                          rtol=0.0 if last else p["stage_tol"])
            if not torch.equal(work.labels, st["labels"]):
                work.set_labels(st["labels"])
            stages.append({"vectors": j, "se": st["se"], "changes": changes})
        info["stages"] = stages
        info["iterative_se"] = st["se"]
        return st

    # -- Sloan 2003 §4.3 ------------------------------------------------------------------
    def _adaptive(self, work, st, solver, gen, kw, info, D):
        p = self.params
        n = p["vectors"]
        nmax = p["max_vectors"] if p["max_vectors"] is not None else min(D - 1, max(1, 2 * n))
        budget = (p["budget"] if p["budget"] is not None else float(n)) * work.P
        if not torch.equal(work.labels, st["labels"]):
            work.set_labels(st["labels"])
        best = st
        if int((st["n_vectors"] * work.counts).sum()) > budget + 1e-9:
            best = {**st, "se": math.inf}  # the uniform start is over this budget
        alloc = lambda s: _allocate(s["evals"], work.counts, budget)  # noqa: E731
        cur = st
        hist = []
        for a in range(p["adapt_iters"]):  # classify -> refit -> redistribute (Sloan 2003 §4.3)
            full = work.refit(nmax, solver, gen, init=cur["basis"], **kw)
            cur = _mask_basis(full, alloc(full))
            hist.append(cur["se"])
            if cur["se"] < best["se"]:
                best = cur
            labels, emin, _ = classify_all(work.X, work.xx, cur["means"], cur["basis"])
            labels, emin, _ = repair_empty(labels, emin, work.K, work.w)
            if torch.equal(labels, work.labels):
                break
            work.set_labels(labels)
        else:
            full = work.refit(nmax, solver, gen, init=cur["basis"], **kw)
            cur = _mask_basis(full, alloc(full))
            hist.append(cur["se"])
            if cur["se"] < best["se"]:
                best = cur
        if best["basis"].shape[1] < nmax:  # the iterative start won: pad its basis to n_max
            pad = torch.zeros(work.K, nmax - best["basis"].shape[1], work.D, dtype=torch.float64)
            best = {**best, "basis": torch.cat([best["basis"], pad], 1)}
        info["adaptive_se"] = hist
        info["budget_weights"] = budget
        info["used_weights"] = int((best["n_vectors"] * torch.bincount(best["labels"], minlength=work.K)).sum())
        return best


# presets: subclasses CPCAStatic, CPCAIterative, CPCAAdaptive with ``method`` fixed (they keep
# their registry name through sklearn.base.clone)
CPCAStatic = register("cpca_static", CPCA, preset={"method": "static"}, doc="CPCA, VQ then per-cluster PCA (Sloan 2003 §4.1)")
CPCAIterative = register("cpca_iterative", CPCA, preset={"method": "iterative"}, doc="CPCA, iterative (Sloan 2003 §4.2)")
CPCAAdaptive = register("cpca_adaptive", CPCA, preset={"method": "adaptive"}, doc="CPCA, adaptive n' per cluster (Sloan 2003 §4.3)")


@register("mrt_pca")
class MRTPCA(PCA):
    __doc__ = _doc("""PCA on matrix radiance transfer A_p (Lehtinen & Kautz 2003 §6, eq. (12)); relight with the
    4-tap eq. (13), K (``n_vectors``) adjustable at run time as a prefix.""", """
    vectors : int, default=25
        Principal components K (Lehtinen & Kautz 2003 used 10-50).
    center : bool, default=False
        Subtract the mean matrix first (eq. (12) has none).""", _DOC_PCA_GLOBAL, _DOC_COMMON)

    codec_name = "mrt_pca"
    _parameter_constraints = {**PCA._parameter_constraints, "vectors": [Interval(int, 1, None)]}

    def __init__(self, *, vectors=25, center=False, solver="auto", oversample=_PCA_OVERSAMPLE, power_iters=_PCA_POWER_ITERS,
                 seed=0, fit_dtype="auto", strict=False):
        super().__init__(vectors=vectors, center=center, solver=solver, oversample=oversample,
                         power_iters=power_iters, seed=seed, fit_dtype=fit_dtype, strict=strict)

    def _check_data(self, P, D, ms):
        if ms is None:
            raise ValueError("mrt_pca needs matrix_shape=(M*M, n_in) (each row an MRT matrix A_p, Lehtinen & Kautz 2003 §6)")
        super()._check_data(P, D, ms)

    def _relight_cost(self, terms: float) -> float:
        """4K multiply-adds per colour per vertex with the tent basis (eq. (13)); 4(K+1) with a mean
        (``terms`` = K, or K+1)."""
        return 4.0 * terms
