"""A learned transfer codec: per-point latent codes and a shared decoder (an auto-decoder).

Each point p keeps a latent code z_p ∈ R^k; one small decoder, shared by all points (or one
last layer per cluster), maps it back to the signal (Park et al. 2019, DeepSDF §4, the
auto-decoder: codes and decoder optimised jointly, no encoder network):

    x̃_p = g_{k(p)}(z_p) = b_{k(p)} + W_{k(p)} h(z_p),     h(z) = [z, φ(z)] ∈ R^H        (1)

φ is a multilayer perceptron R^k → R^{H−k} (``depth`` hidden layers of ``width`` units, an
activation after every layer), shared by all clusters (``cluster_decoder='head'``) or one φ_k per
cluster (``'full'``: a whole decoder per CPCA cluster, h(z_p) = [z_p, φ_{k(p)}(z_p)]); W_k
``[D, H]`` and b_k ``[D]`` are the last, linear layer of cluster k (k(p) = 0 without clustering). Because the last layer is
linear, relighting keeps PRT's structure (Sloan 2003 §6): per light the constants W_k^T l
and b_k^T l (``[K, 1+H, n_out, C]``, like CPCA's per-cluster M_i l), per point the features
h(z_p) dotted with them. Once h(z_p) is computed and cached (``NeuralCodec.affine_form``),
relighting *is* CPCA relighting with H vectors: the same compiled kernels and plans
(``affine.AffineCodec.relight``), the same GLSL decoder (features as attributes, constants as
a uniform table).

Fitting (``fit``): the signal is centred and scaled by its RMS norm, codes and decoder are
initialised from PCA with k vectors (one cluster) or static CPCA (``clusters`` > 1; Sloan
2003 §4.1) — z_p the PCA weights, W's first k columns the PCA vectors, the rest zero — so
eq. (1) starts equal to PCA with k vectors; then Adam (codes updated per minibatch row,
``adam``) or full-batch L-BFGS (``lbfgs``) minimise the weighted squared error
Σ_p w_p ||x_p − x̃_p||² (the harness's error), minibatches in a seeded order; a held-out
subset of points trains its codes only and decides early stopping; a non-finite or rising
loss stops with the last good state and a warning; finally the last layer is solved exactly
by least squares on the (stored-precision) codes' features, and a result worse than the PCA
start on the training points is replaced by that start. ``encode`` of new data optimises
codes only: a least-squares start on the skip columns (each cluster's, the best cluster
chosen), then Adam steps, each point keeping its best code.

Stored: ``codes.z [P, k]`` (float32 or float16: ``code_dtype``), ``codes.labels [P]`` (K > 1),
the decoder's ``model.layer{i}.weight/bias`` (φ: ``[out, in]``, ``[out]``; one per cluster:
``[K, out, in]``, ``[K, out]``), ``model.head [K, H, D]`` (W_k^T) and
``model.bias [K, D]``. Run time (``storage``: ``runtime_bytes``): the cached features
``[P, H]`` float32 with the head — larger than the stored codes when H > k, the point of the
comparison in reports/benchmarks/neural.md.
"""
from __future__ import annotations

import contextlib
import math
import time
from typing import Any

import torch

from .. import io
from .._checks import check_finite
from ..params import Boolean, Interval, Options
from .affine import check_enc_origin, label_dtype, signal_key
from .cpca import CPCA, PCA, CPCAStatic
from .base import (Codec, Encoded, Relighter, array_type, check_matrix_shape, check_signal, check_weights,
                   encoding_state, grad_required, input_ref, register, squared_error_rows, typed, view_nbytes)
from .segment import from_tiles, tile_layout, tiles_accumulate, to_tiles

__all__ = ["NeuralCodec", "NeuralRelighter"]

_ACTIVATIONS = {
    "silu": torch.nn.functional.silu,
    "tanh": torch.tanh,
    "relu": torch.relu,
    "linear": lambda t: t,
}

#: a loss above this multiple of the best so far counts as divergence (with NaN / Inf)
DIVERGENCE_FACTOR = 4.0
#: training codes kept with the decoder (``model.code_samples``): the starts of ``encode`` for new data
CODE_SAMPLES = 256
#: elements of the [rows, D] temporaries of encoding new data, per chunk of points
CHUNK_ELEMENTS = 1 << 21
#: codes-only Adam steps of the held-out points per epoch (they follow the decoder)
HOLDOUT_STEPS = 3


def _cluster_affine(x: torch.Tensor, labels: torch.Tensor | None, layout, w_t: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """b_k + x W_k per point: ``x [N, a]``, ``w_t [K, a, o]`` (W_k^T), ``b [K, o]``, cluster ``labels [N]``
    and their ``layout`` (``segment.tile_layout``; None with K = 1) -> ``[N, o]``: one GEMM, or one
    batched GEMM per tile group (differentiable: index_copy, bmm, index_select)."""
    K = w_t.shape[0]
    if K == 1 or labels is None:
        return torch.addmm(b[0], x, w_t[0])
    xt = to_tiles(layout, x)
    Ws = w_t.index_select(0, layout.corder)
    parts = [torch.bmm(xt[t0:t1], Ws[: t1 - t0]) for t0, t1 in layout.groups]  # one bmm per tile row
    out = from_tiles(layout, torch.cat(parts, 0) if parts else xt.new_zeros(0, layout.T, w_t.shape[2]))
    return out + b[labels]


def _phi_features(z: torch.Tensor, labels: torch.Tensor | None, layers: list, act, layout=None) -> torch.Tensor:
    """h(z) = [z, φ(z)] ``[N, H]`` (eq. (1)) in z's dtype: ``layers`` [(weight, bias)] of φ, each
    ``weight [o, a]``, ``bias [o]`` (one φ for every point) or ``[K, o, a]``, ``[K, o]`` (one φ per
    cluster, ``cluster_decoder='full'``: point p through φ_{k(p)}, ``labels [N]`` required)."""
    if not layers:
        return z
    a = z
    for w, b in layers:
        w, b = w.to(z.dtype), b.to(z.dtype)
        if w.ndim == 2:
            a = act(torch.nn.functional.linear(a, w, b))
        else:
            if layout is None:
                layout = tile_layout(labels, w.shape[0])
            a = act(_cluster_affine(a, labels, layout, w.transpose(1, 2), b))
    return torch.cat([z, a], 1)


@register("neural")
class NeuralCodec(Codec):
    """Learned auto-decoder codec: a latent code per point and a shared MLP decoder whose last layer is linear (relit as PCA with H vectors).

    Parameters
    ----------
    latent : int, default=4
        Latent code size k per point (the stored floats per point).
    features : int, default=16
        Feature size H of h(z) = [z, φ(z)] (H ≥ k; the relight cost is that of PCA with H vectors).
    width : int, default=32
        Hidden width of the MLP φ.
    depth : int, default=2
        Hidden layers of φ (0: one layer k → H−k).
    activation : {'silu', 'tanh', 'relu', 'linear'}, default='silu'
        Activation after each layer of φ; 'linear' makes h, and the codec, linear in z.
    clusters : int, default=1
        One last layer (W_k, b_k) per cluster of a static CPCA of the signal (Sloan 2003 §4.1).
    cluster_decoder : {'head', 'full'}, default='head'
        With ``clusters`` > 1: 'head' shares φ and gives each cluster its own last layer; 'full' gives each
        cluster a whole decoder of its own (φ_k and W_k, b_k: K times φ's weights stored).
    optimizer : {'adam', 'lbfgs'}, default='adam'
        Adam on minibatches (codes updated per row) or full-batch L-BFGS (strong Wolfe line search).
    lr : float, default=0.003
        Learning rate (Adam), or initial step (L-BFGS), in the units of the signal scaled to unit RMS norm.
    epochs : int, default=300
        Most passes over the training points (L-BFGS: outer steps of 20 iterations).
    batch_size : int, default=512
        Points per Adam minibatch (in a fixed order drawn from ``seed`` each epoch).
    patience : int, default=20
        Early stopping: epochs without a lower held-out loss before stopping.
    holdout : float, default=0.1
        Fraction of the points held out of the decoder's training (their codes still fitted) to decide early stopping; 0: the training loss decides.
    encode_iters : int, default=100
        Codes-only Adam steps when encoding new data with a fitted decoder.
    code_dtype : {'float32', 'float16'}, default='float32'
        Storage of the codes; float16 codes are rounded before the last layer's final least-squares solve.
    init : {'pca', 'random'}, default='pca'
        Start from PCA / static CPCA with k vectors (never worse than it), or from small random codes.
    fit_dtype : {'float32', 'float64'}, default='float32'
        Working precision of the fit.
    progress : bool, default=False
        Show a progress bar with the loss during the fit.
    seed : int, default=0
        Seed of the decoder's initial weights, the held-out draw and the minibatch order.
    strict : bool, default=False
        Raise ConvergenceError instead of warning when the training diverges.
    """

    _parameter_constraints = {
        "latent": [Interval(int, 1, 256)],
        "features": [Interval(int, 1, 1024)],
        "width": [Interval(int, 1, 4096)],
        "depth": [Interval(int, 0, 16)],
        "activation": [Options(*_ACTIVATIONS)],
        "clusters": [Interval(int, 1, None)],
        "cluster_decoder": [Options("head", "full")],
        "optimizer": [Options("adam", "lbfgs")],
        "lr": [Interval(float, 0, 10, closed="right")],
        "epochs": [Interval(int, 1, 100000)],
        "batch_size": [Interval(int, 1, None)],
        "patience": [Interval(int, 1, None)],
        "holdout": [Interval(float, 0, 0.5)],
        "encode_iters": [Interval(int, 0, 100000)],
        "code_dtype": [Options("float32", "float16")],
        "init": [Options("pca", "random")],
        "fit_dtype": [Options("float32", "float64")],
        "progress": [Boolean()],
        "seed": [Interval(int, 0, None)],
        "strict": [Boolean()],
    }

    def __init__(self, *, latent=4, features=16, width=32, depth=2, activation="silu", clusters=1, cluster_decoder="head", optimizer="adam",
                 lr=0.003, epochs=300, batch_size=512, patience=20, holdout=0.1, encode_iters=100, code_dtype="float32",
                 init="pca", fit_dtype="float32", progress=False, seed=0, strict=False):
        self.latent = latent
        self.features = features
        self.width = width
        self.depth = depth
        self.activation = activation
        self.clusters = clusters
        self.cluster_decoder = cluster_decoder
        self.optimizer = optimizer
        self.lr = lr
        self.epochs = epochs
        self.batch_size = batch_size
        self.patience = patience
        self.holdout = holdout
        self.encode_iters = encode_iters
        self.code_dtype = code_dtype
        self.init = init
        self.fit_dtype = fit_dtype
        self.progress = progress
        self.seed = seed
        self.strict = strict

    def _check_params(self, p: dict[str, Any]) -> None:
        if p["features"] < p["latent"]:
            raise ValueError(f"{self.codec_name}: features={p['features']} is below latent={p['latent']}; accepted: "
                             f"features >= latent (h(z) = [z, φ(z)] keeps the code as its first k features)")

    def _check_data(self, P: int, D: int, matrix_shape) -> None:
        k = self.params["latent"]
        if k >= D:
            raise ValueError(f"{self.codec_name}: latent={k} must be < D={D} (n_features = {D}); accepted: 1..{D - 1} "
                             "(the codes start as the weights of PCA with k vectors)")

    def __getstate__(self):
        return {k: v for k, v in super().__getstate__().items() if k not in ("_train", "_affine")}

    # ------------------------------------------------------------------ the decoder
    @property
    def _act(self):
        return _ACTIVATIONS[self.params_["activation"]]

    def _features(self, z: torch.Tensor, labels: torch.Tensor | None = None) -> torch.Tensor:
        """h(z) = [z, φ(z)] ``[N, H]`` in z's dtype (eq. (1)) of the fitted φ; ``labels [N]``: the
        points' clusters (needed with one φ per cluster, ``cluster_decoder='full'``)."""
        return _phi_features(z, labels, self.layers_, self._act)

    def _head(self, F: torch.Tensor, labels: torch.Tensor | None, head: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        """b_k + W_k h ``[N, D]`` for features ``F [N, H]``, cluster ``labels [N]`` (None: K = 1),
        ``head [K, H, D]``, ``bias [K, D]``: one GEMM, or with clusters the tile layout's batched
        GEMMs (``segment``; differentiable: index_copy, bmm, index_select)."""
        K = head.shape[0]
        return _cluster_affine(F, labels, None if K == 1 or labels is None else tile_layout(labels, K), head, bias)

    # ------------------------------------------------------------------ fit
    def fit(self, X, y=None, weights=None, matrix_shape=None) -> "NeuralCodec":
        """Fit codes and decoder on ``X [P, D]`` (float32/64, finite), optional ``weights [P]`` ≥ 0
        and ``matrix_shape``; ``y`` ignored. All checks before any work. Returns self."""
        p = self._validate()
        X_in, X = X, check_signal("X", X)
        P, D = X.shape
        w = check_weights(weights, P)
        ms = check_matrix_shape(matrix_shape, D)
        self._check_data(P, D, ms)
        if p["clusters"] > P:
            raise ValueError(f"{self.codec_name}: clusters={p['clusters']} exceeds the number of points P={P}; accepted: 1..{P}")
        t0 = time.perf_counter()
        self.params_ = p
        dt = torch.float64 if p["fit_dtype"] == "float64" else torch.float32
        with _seeded(p["seed"]):
            trainer = _Trainer(self, X, w, dt)
            state, info = trainer.run()
            del trainer.Y  # the scaled table: not needed past the fit
        cdt = torch.float16 if p["code_dtype"] == "float16" else torch.float32
        self.K_, self.D_, self.matrix_shape_ = int(state["head"].shape[0]), D, ms
        self.n_features_in_ = D
        self.layers_ = [(a.to(torch.float32).contiguous(), b.to(torch.float32).contiguous()) for a, b in state["layers"]]
        self.head_ = state["head"].to(torch.float32).contiguous()
        self.bias_ = state["bias"].to(torch.float32).contiguous()
        z_stored = state["z"].to(cdt)
        g = torch.Generator().manual_seed(p["seed"] + 2)
        pick = torch.randperm(P, generator=g)[:CODE_SAMPLES].sort().values
        self.code_samples_ = z_stored[pick].to(torch.float32).contiguous()
        self.code_sample_labels_ = (state["labels"][pick] if state["labels"] is not None
                                    else torch.zeros(pick.numel(), dtype=torch.long)).to(torch.int32).contiguous()
        self.fitted_ = True
        enc = self._make_encoded(z_stored, state["labels"])
        enc.array_type = array_type(X_in)
        self._train = (signal_key(X), input_ref(X_in), enc)
        info["seconds"] = time.perf_counter() - t0
        info["se"] = self.squared_error(X, enc, w)
        info["se_relative"] = info["se"] / max(trainer.energy, 1e-300)
        self.fit_info_ = info
        self.n_iter_ = int(info["epochs"])
        return self

    # ------------------------------------------------------------------ codes
    def _make_encoded(self, z: torch.Tensor, labels: torch.Tensor | None) -> Encoded:
        P = z.shape[0]
        tensors = {"z": z.contiguous()}
        if self.K_ > 1:
            tensors["labels"] = labels.to(label_dtype(self.K_)).contiguous()
        meta = {"points": P, "dim": self.D_, "clusters": self.K_, "latent": int(z.shape[1]),
                "features": int(self.head_.shape[1]), "code_dtype": str(z.dtype).replace("torch.", ""),
                "matrix_shape": list(self.matrix_shape_) if self.matrix_shape_ else None}
        return Encoded(codec=self.codec_name, tensors=tensors, meta=meta)

    def _check_enc(self, enc: Encoded) -> None:
        check_enc_origin(self, enc)
        z = enc.tensors.get("z")
        k = self.latent_size
        if z is None or z.ndim != 2 or z.shape != (enc.points, k) or not z.is_floating_point():
            raise ValueError(f"enc codes z have shape {None if z is None else tuple(z.shape)}; accepted: [{enc.points}, {k}] float")
        if self.K_ > 1:
            lab = enc.tensors.get("labels")
            if lab is None or lab.shape != (enc.points,):
                raise ValueError(f"enc labels have shape {None if lab is None else tuple(lab.shape)}; accepted: [{enc.points}]")

    @property
    def latent_size(self) -> int:
        """k, the code size of the fitted model."""
        return int(self.head_.shape[1]) - (int(self.layers_[-1][0].shape[-2]) if self.layers_ else 0)

    def labels_of(self, enc: Encoded) -> torch.Tensor:
        """Cluster index of every point, ``int64 [P]`` (zeros without clusters)."""
        if "labels" in enc.tensors:
            return enc.tensors["labels"].long()
        return torch.zeros(enc.points, dtype=torch.long)

    def features_of(self, enc: Encoded) -> torch.Tensor:
        """The cached features h(z_p) ``[P, H]`` float32 (eq. (1)), computed once per encoding and
        kept in ``enc.cache`` while the codes and the decoder are the same tensors at the same
        versions (``base.encoding_state``)."""
        return self.affine_form(enc)[1].tensors["coeffs"]

    def affine_form(self, enc: Encoded) -> tuple[Codec, Encoded]:
        """``(affine codec, encoding)``: eq. (1) after caching h(z_p), as the piecewise-affine
        model of ``affine.py`` — a ``pca`` (K = 1) or ``cpca`` codec with means b_k and H vectors
        W_k^T (not orthonormal), coefficients h(z_p) ``[P, H]`` float32 and ``enc``'s labels.
        Relighting, its plans and kernels, and the GLSL decoder run on it (Sloan 2003 §6). Cached:
        the codec while the decoder's tensors are unchanged, the encoding in ``enc.cache``."""
        self._check_enc(enc)
        model = self._model_tensors()
        aff = getattr(self, "_affine", None)
        mstate = encoding_state(enc, model)[1:]
        if aff is None or aff[0] != mstate:
            inner = PCA(vectors=int(self.head_.shape[1])) if self.K_ == 1 else CPCA(clusters=self.K_, vectors=int(self.head_.shape[1]))
            inner.means_, inner.basis_ = self.bias_, self.head_
            inner.n_vectors_ = torch.full((self.K_,), int(self.head_.shape[1]), dtype=torch.long)
            inner.K_, inner.D_, inner.matrix_shape_ = self.K_, self.D_, self.matrix_shape_
            inner.n_features_in_, inner.fitted_ = self.D_, True
            inner.fit_info_ = {"from": "neural.affine_form"}
            aff = self._affine = (mstate, inner, model)
        inner = aff[1]
        held = (*enc.tensors.values(), *model)
        state = encoding_state(enc, held)
        hit = enc.cache.get("neural_affine")
        if hit is None or hit[0] != state or hit[1][0] is not inner:
            z = enc.tensors["z"]
            check_finite("enc codes z", z)
            F = torch.empty(enc.points, int(self.head_.shape[1]), dtype=torch.float32)
            with torch.no_grad():
                lab = self.labels_of(enc) if self.K_ > 1 else None
                for i in range(0, enc.points, 65536):  # chunks bound φ's temporaries
                    F[i:i + 65536] = self._features(z[i:i + 65536].to(torch.float32), None if lab is None else lab[i:i + 65536])
            tensors = {"coeffs": F}
            if self.K_ > 1:
                tensors["labels"] = enc.tensors["labels"]
            aenc = Encoded(codec=inner.codec_name, tensors=tensors, array_type=enc.array_type,
                           meta={"points": enc.points, "dim": self.D_, "clusters": self.K_, "n_max": int(self.head_.shape[1]),
                                 "packed": False, "centered": True,
                                 "matrix_shape": list(self.matrix_shape_) if self.matrix_shape_ else None})
            hit = enc.cache["neural_affine"] = (state, (inner, aenc), held)
        inner, aenc = hit[1]
        return inner, typed(aenc, enc.array_type)

    def _model_tensors(self) -> tuple:
        """The decoder's tensors (what relighting's cached features depend on)."""
        return (self.head_, self.bias_, *(t for pair in self.layers_ for t in pair))

    # ------------------------------------------------------------------ encode / decode
    def encode(self, X) -> Encoded:
        """Codes of ``X [P, D]`` for the fitted decoder: the training signal's from the fit; other
        data by codes-only optimisation (a least-squares start on each cluster's skip columns,
        the cluster of least error, then ``encode_iters`` Adam steps, each point keeping its best)."""
        self._require_fitted()
        kind = array_type(X)
        X = check_signal("X", X)
        self._check_features(X)
        train = getattr(self, "_train", None)
        if train is not None and train[0] == signal_key(X) and train[1]() is not None:
            return typed(train[2], kind)
        p = self.params
        with _seeded(p["seed"]):
            z, labels = self._encode_codes(X.to(torch.float32), p)
        enc = self._make_encoded(z.to(torch.float16 if p["code_dtype"] == "float16" else torch.float32), labels)
        enc.array_type = kind
        return enc

    def _encode_codes(self, X: torch.Tensor, p: dict) -> tuple[torch.Tensor, torch.Tensor | None]:
        k = self.latent_size
        head, bias = self.head_.double(), self.bias_.double()
        S = head[:, :k]  # [K, k, D]: the skip columns W_k[:, :k]^T
        P = X.shape[0]
        # least squares per cluster: z = (S S^T)^-1 S (x - b)
        G = S @ S.transpose(1, 2)
        G = G + 1e-12 * G.diagonal(dim1=1, dim2=2).sum(-1).clamp_min(1e-30)[:, None, None] * torch.eye(k, dtype=torch.float64)
        A = torch.linalg.solve(G, S)  # [K, k, D]
        z = torch.empty(P, k, dtype=torch.float32)
        labels = torch.zeros(P, dtype=torch.long) if self.K_ > 1 else None
        step = max(1, (1 << 22) // max(1, self.K_ * self.D_))
        for i in range(0, P, step):  # chunks bound the [rows, K, D] residuals
            xb = X[i:i + step].double()
            zk = torch.einsum("kjd,pkd->pkj", A, xb[:, None] - bias[None])  # [rows, K, k]
            if self.K_ == 1:
                z[i:i + step] = zk[:, 0].float()
                continue
            r = xb[:, None] - bias[None] - torch.einsum("pkj,kjd->pkd", zk, S)
            best = r.square().sum(-1).argmin(1)
            labels[i:i + step] = best
            z[i:i + step] = zk[torch.arange(best.numel()), best].float()
        # the stored training codes as starts too: each point's nearest decoded sample, where it is
        # nearer than the least-squares start (the decoder is not convex in z)
        zs, ls = self.code_samples_, self.code_sample_labels_.long()
        rows = max(1, CHUNK_ELEMENTS // self.D_)
        if zs.numel():
            with torch.no_grad():
                Xs = self._head(self._features(zs, ls if self.K_ > 1 else None), ls if self.K_ > 1 else None, self.head_,
                                self.bias_).double()
                ss = Xs.square().sum(1)
                for i in range(0, P, rows):  # chunks bound the [rows, D] decodes
                    xb, zb = X[i:i + rows].double(), z[i:i + rows]
                    lb = None if labels is None else labels[i:i + rows]
                    e0 = (xb - self._head(self._features(zb, lb), lb, self.head_, self.bias_).double()).square().sum(1)
                    ds, js = (xb.square().sum(1)[:, None] - 2 * xb @ Xs.T + ss[None]).clamp_min(0).min(1)
                    use = ds < e0
                    zb[use] = zs[js[use]]
                    if lb is not None:
                        lb[use] = ls[js[use]]
        iters = p["encode_iters"]
        if iters:
            for i in range(0, P, rows):  # per chunk of points (each point's steps are its own)
                z[i:i + rows] = self._refine_codes(X[i:i + rows], z[i:i + rows], None if labels is None else labels[i:i + rows],
                                                   iters, p["lr"])
        return z, labels

    def _refine_codes(self, X: torch.Tensor, z: torch.Tensor, labels, iters: int, lr: float) -> torch.Tensor:
        """Codes-only Adam on ``||x − g(z)||²`` per point (decoder fixed), each point keeping the
        best code seen (never worse than ``z``). Batched over all points; the loss is in units of
        the fit's scale (``fit_info_['scale']``), so ``lr`` means what it means in the fit."""
        scale = float(self.fit_info_.get("scale", 1.0)) if isinstance(getattr(self, "fit_info_", None), dict) else 1.0
        scale = scale if scale > 0 else 1.0
        head, bias = self.head_, self.bias_
        zc = (z / scale).clone().requires_grad_(True)  # (codes in the scaled units the fit used for steps)
        opt = _Adam([zc], lr)
        best = z.clone()
        best_err = None
        for t in range(1, iters + 2):
            zz = zc * scale
            err = (X - self._head(self._features(zz, labels), labels, head, bias)).square().sum(1)
            with torch.no_grad():
                e = err.detach()
                if best_err is None:
                    best_err = e.clone()
                else:
                    better = e < best_err
                    best[better] = zz.detach()[better]
                    best_err = torch.where(better, e, best_err)
            if t == iters + 1:
                break
            zc.grad, = torch.autograd.grad(err.sum() / scale ** 2, zc)
            opt.step()
        return best

    def decode(self, enc: Encoded) -> Any:
        """x̃_p ``[P, D]`` float32 by eq. (1) from the codes (the decoder's forward pass, not the
        cached features); a tensor, or a numpy array for an encoding of numpy data. When the codes
        or the decoder's tensors require grad: the same pass under autograd, differentiable, in
        their promoted dtype (a tensor)."""
        self._check_enc(enc)
        z = enc.tensors["z"]
        labels = self.labels_of(enc) if self.K_ > 1 else None
        dec = [self.head_, self.bias_, *[t for pair in self.layers_ for t in pair]]
        if grad_required(z, *dec):  # under autograd: the same forward pass, in the promoted dtype, not chunked
            dt = torch.promote_types(torch.float32, z.dtype)
            for t in dec:
                dt = torch.promote_types(dt, t.dtype)
            F = self._features(z.to(dt), labels)
            return self._head(F, labels, self.head_.to(dt), self.bias_.to(dt))
        out = torch.empty(enc.points, self.D_, dtype=torch.float32)
        with torch.no_grad():
            for i in range(0, enc.points, 16384):
                lb = None if labels is None else labels[i:i + 16384]
                out[i:i + 16384] = self._head(self._features(z[i:i + 16384].to(torch.float32), lb), lb, self.head_, self.bias_)
        return out.numpy() if enc.array_type == "numpy" else out

    def squared_error(self, X, enc: Encoded, weights: torch.Tensor | None = None) -> float:
        """Σ_p w_p ||x_p − x̃_p||² (``Codec.squared_error``'s arithmetic: ``squared_error_rows``) of
        ``X [P, D]``, x̃ decoded by eq. (1) in blocks of about :data:`CHUNK_ELEMENTS` values — no
        decoded ``[P, D]`` copy (661 MB at 10 242 × 16 128). Under autograd: ``Codec.squared_error``."""
        self._check_enc(enc)
        if grad_required(enc.tensors["z"], *self._model_tensors()):
            return super().squared_error(X, enc, weights)
        X = torch.as_tensor(X)
        z = enc.tensors["z"]
        labels = self.labels_of(enc) if self.K_ > 1 else None
        rows = max(1, CHUNK_ELEMENTS // max(1, self.D_))
        se = 0.0
        with torch.no_grad():
            for i in range(0, enc.points, rows):
                lb = None if labels is None else labels[i:i + rows]
                xh = self._head(self._features(z[i:i + rows].to(torch.float32), lb), lb, self.head_, self.bias_)
                se += squared_error_rows(X[i:i + rows], xh, None if weights is None else weights[i:i + rows])
        return se

    # ------------------------------------------------------------------ transform layout
    def _code_columns(self) -> list[str]:
        self._require_fitted()
        return ["_cluster"] + [str(i) for i in range(self.latent_size)]

    def _codes_to_array(self, enc: Encoded) -> torch.Tensor:
        """``[P, 1 + k]`` float32: the cluster index as a float, then the code z_p."""
        self._check_enc(enc)
        return torch.cat([self.labels_of(enc).to(torch.float32)[:, None], enc.tensors["z"].to(torch.float32)], 1)

    def _codes_from_array(self, Z: torch.Tensor) -> Encoded:
        lab = Z[:, 0]
        bad = (lab != lab.round()) | (lab < 0) | (lab >= self.K_)
        if bool(bad.any()):
            i = int(torch.nonzero(bad)[0])
            raise ValueError(f"Z[{i}, 0] = {float(lab[i])!r} is not a cluster index; accepted: integers in [0, {self.K_})")
        cdt = torch.float16 if self.params["code_dtype"] == "float16" else torch.float32
        return self._make_encoded(Z[:, 1:].to(cdt).contiguous(), lab.long())

    # ------------------------------------------------------------------ relight
    def relight(self, enc: Encoded, light: Any, view: Any = None, out: torch.Tensor | None = None) -> Any:
        """Radiance from the cached features (Sloan 2003 §6 with W_k^T l as the per-cluster
        constants): ``AffineCodec.relight`` of :meth:`affine_form` — the same shapes, views,
        ``out`` and kernels as PCA (K = 1) or CPCA with H vectors. ``light [n_in, C]``; returns
        ``[P, C]`` (vectors, or with a view) or ``[P, n_out, C]``."""
        inner, aenc = self.affine_form(enc)
        return inner.relight(aenc, light, view, out=out)

    def relighter(self, enc: Encoded, view: Any = None) -> "NeuralRelighter":
        """A prepared relighting for a render loop: the features cached once, then the affine
        relighter of :meth:`affine_form` per light (rebuilt when the codes or the decoder change)."""
        self._check_enc(enc)
        return NeuralRelighter(self, enc, view)

    # ------------------------------------------------------------------ storage
    def storage(self, enc: Encoded) -> dict[str, Any]:
        """Stored bytes (``bytes_total``: the codes, in ``code_dtype``, and the decoder's weights)
        and, apart, the run-time bytes of relighting from the cached features (``runtime_bytes``:
        h(z_p) ``[P, H]`` float32, the head and biases, the labels) — Sloan 2003 §4.1's float count
        of the stored form (``sloan_cost_floats``: P k + the decoder's floats)."""
        self._check_enc(enc)
        out = super().storage(enc)
        P, D = enc.points, self.D_
        H, k = int(self.head_.shape[1]), self.latent_size
        n_out = self.matrix_shape_[0] if self.matrix_shape_ else 1
        feat = P * H * 4
        lab = enc.tensors["labels"].numel() * enc.tensors["labels"].element_size() if "labels" in enc.tensors else 0
        runtime = feat + (self.head_.numel() + self.bias_.numel()) * 4 + lab
        dec_floats = sum(t.numel() for t in self._model_tensors()) + self.code_samples_.numel()
        out.update({
            "clusters": self.K_, "latent": k, "features": H, "code_dtype": str(enc.tensors["z"].dtype).replace("torch.", ""),
            "decoder_floats": dec_floats,
            "runtime_bytes": runtime, "runtime_bytes_per_point": runtime / max(P, 1), "runtime_feature_bytes": feat,
            "sloan_cost_floats": P * k + dec_floats, "sloan_per_point_floats": P * k, "sloan_per_cluster_floats": dec_floats,
            "sloan_ratio": P * D / max(1, P * k + dec_floats),
            "relight_macs_per_point_per_channel": float((H + 1) * n_out),
        })
        return out

    def relight_bytes(self, enc: Encoded, view: Any = None) -> int:
        """What a relight reads: the run-time form (cached features, head, biases, labels), not
        the stored codes, and the view's bytes."""
        return int(self.storage(enc)["runtime_bytes"]) + view_nbytes(view)

    # ------------------------------------------------------------------ persistence
    def _state(self):
        tensors = {"head": self.head_, "bias": self.bias_, "code_samples": self.code_samples_,
                   "code_sample_labels": self.code_sample_labels_}
        for i, (a, b) in enumerate(self.layers_):
            tensors[f"layer{i}.weight"], tensors[f"layer{i}.bias"] = a, b
        meta = {"clusters": self.K_, "dim": self.D_, "latent": self.latent_size, "features": int(self.head_.shape[1]),
                "layers": len(self.layers_), "matrix_shape": list(self.matrix_shape_) if self.matrix_shape_ else None,
                "fit_info": io.jsonable(getattr(self, "fit_info_", {}))}
        return tensors, meta

    def _set_state(self, tensors, meta):
        try:
            self.head_ = tensors["head"].to(torch.float32).contiguous()
            self.bias_ = tensors["bias"].to(torch.float32).contiguous()
            self.code_samples_ = tensors["code_samples"].to(torch.float32).contiguous()
            self.code_sample_labels_ = tensors["code_sample_labels"].to(torch.int32).contiguous()
            self.layers_ = [(tensors[f"layer{i}.weight"].to(torch.float32).contiguous(),
                             tensors[f"layer{i}.bias"].to(torch.float32).contiguous()) for i in range(int(meta["layers"]))]
            self.K_, self.D_ = int(meta["clusters"]), int(meta["dim"])
        except KeyError as e:
            raise ValueError(f"codec file lacks {e}; it was not written by the neural codec's save") from None
        ms = meta.get("matrix_shape")
        self.matrix_shape_ = tuple(ms) if ms else None
        self.n_features_in_ = self.D_
        self.fit_info_ = meta.get("fit_info", {})
        self.params_ = self.params
        if any(w.ndim == 3 and (w.shape[0] != self.K_ or b.shape[0] != self.K_) for w, b in self.layers_):
            raise ValueError(f"codec file: a per-cluster layer of φ has {tuple(self.layers_[0][0].shape)} weights, not one per "
                             f"cluster of clusters={self.K_}")
        if self.head_.shape[0] != self.K_ or self.head_.shape[2] != self.D_ or self.bias_.shape != (self.K_, self.D_):
            raise ValueError(f"codec file: head {tuple(self.head_.shape)} / bias {tuple(self.bias_.shape)} do not match "
                             f"clusters={self.K_}, dim={self.D_}")


class NeuralRelighter(Relighter):
    """``NeuralCodec.relighter``: the affine relighter of the cached features (``affine_form``),
    rebuilt when the codes or the decoder are edited or replaced (their ``encoding_state``,
    ~1 µs a call); then the prepared PCA/CPCA relight (``AffineRelighter``): the same bits as
    ``relight``."""

    __slots__ = ("_inner", "_state")

    def __init__(self, codec: NeuralCodec, enc: Encoded, view: Any):
        super().__init__(codec, enc, view, {})
        self._state = None
        self._inner = None
        self._prepare()

    def _prepare(self):
        inner, aenc = self.codec.affine_form(self.enc)
        self._inner = inner.relighter(aenc, self.view)
        self._state = encoding_state(self.enc, (*self.enc.tensors.values(), *self.codec._model_tensors()))

    def __call__(self, light: Any, out: torch.Tensor | None = None) -> Any:
        if encoding_state(self.enc, (*self.enc.tensors.values(), *self.codec._model_tensors())) != self._state:
            self._prepare()
        return self._inner(light, out)


# ----------------------------------------------------------------------------------------
# training
# ----------------------------------------------------------------------------------------

@contextlib.contextmanager
def _seeded(seed: int):
    """Torch's global generator seeded with ``seed`` inside (the layers' default initialisation
    draws from it), restored after: the fit is a function of its seed, and the caller's random
    stream is not disturbed."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(seed))
        yield


def _centred_moments(X: torch.Tensor, w: torch.Tensor | None) -> tuple[torch.Tensor, float, float]:
    """``(x̄ [D] float64, Σ_p ||x_p − x̄||², Σ_p w_p ||x_p − x̄||²)`` of ``X [P, D]`` (float32/64) with
    the weighted mean x̄ (``w [P]`` ≥ 0 or None: the plain mean, and the two sums are equal), in
    float64 by row blocks of :data:`CHUNK_ELEMENTS`: no float64 copy of X (at 10 242 × 16 128 a
    1.3 GB copy and two more temporaries of its size, 7.8 M page faults in the default benchmark's
    Gaussian part). The first sum is the scale of :class:`_Trainer`, the second the denominator of
    ``se_relative``."""
    P, D = X.shape
    rows = max(1, CHUNK_ELEMENTS // max(1, D))
    wd = None if w is None else w.double()
    mu = torch.zeros(D, dtype=torch.float64)
    for i in range(0, P, rows):
        xb = X[i:i + rows].double()
        mu += xb.sum(0) if wd is None else (xb * wd[i:i + rows, None]).sum(0)
    mu /= P if wd is None else wd.sum()
    ss = ssw = 0.0
    for i in range(0, P, rows):
        r = (X[i:i + rows].double() - mu).square_().sum(1)
        ss += float(r.sum())
        ssw += float(r.sum()) if wd is None else float((r * wd[i:i + rows]).sum())
    return mu, ss, ssw


class _Trainer:
    """One fit of eq. (1): PCA start, Adam / L-BFGS with held-out early stopping and divergence
    detection, the last layer's least-squares solve, the never-worse-than-PCA guard. All in the
    scaled signal Y = (X − μ)/s (s the RMS norm of X − μ), mapped back at the end."""

    def __init__(self, codec: NeuralCodec, X: torch.Tensor, w, dt: torch.dtype):
        self.codec, self.p, self.dt = codec, codec.params_, dt
        P, D = X.shape
        self.P, self.D = P, D
        wd = None if w is None else (w.double() / w.double().mean())
        self.w = None if wd is None else wd.to(dt)
        # x̄, the RMS norm s of x − x̄ and Σ w ||x − x̄||² (se_relative's denominator) by row blocks in
        # float64, then Y = (X − x̄)/s block by block: each value as the whole-table float64 expression
        # gives it, without a float64 copy of the table
        self.mu, ss, self.energy = _centred_moments(X, w)
        s = math.sqrt(ss / P)
        self.scale = s if s > 0 else 1.0
        self.Y = torch.empty(P, D, dtype=dt)
        rows = max(1, CHUNK_ELEMENTS // max(1, D))
        for i in range(0, P, rows):
            self.Y[i:i + rows] = (X[i:i + rows].double() - self.mu) / self.scale
        self.info: dict[str, Any] = {"scale": self.scale, "fit_dtype": str(dt).replace("torch.", ""), "optimizer": self.p["optimizer"]}

    # -- the model's tensors as a list of leaves
    def _init(self):
        p, P, D, dt = self.p, self.P, self.D, self.dt
        k, H, K = p["latent"], p["features"], p["clusters"]
        Y = self.Y
        # the start on Y itself, in the fit's dtype: a float32 table larger than 2^23 values is fitted in
        # float32 passes with float64 accumulation (AffineCodec.fit's ``auto``; streamed by row chunks above
        # chunks.STREAM_BYTES, Krylov on wide rows: subspace.py), smaller ones in float64 as before. Was
        # ``Y.double()`` always: a float64 copy of the whole table (1.3 GB at 10 242 × 16 128) and its passes
        start_dtype = "float64" if dt == torch.float64 else "auto"
        if K == 1:
            pc = PCA(vectors=k, seed=p["seed"], fit_dtype=start_dtype)
        else:
            pc = CPCAStatic(clusters=K, vectors=k, seed=p["seed"], fit_dtype=start_dtype)
        with _quiet():
            enc = pc.fit_encode(Y, weights=None if self.w is None else self.w.double())
        labels = pc.labels_of(enc) if K > 1 else None
        Kf = pc.K_
        basis = pc.basis_.double()  # [K, k, D]
        means = pc.means_.double() if pc.means_ is not None else torch.zeros(Kf, D, dtype=torch.float64)
        z = pc.coeffs_of(enc).double()[:, :k]
        if z.shape[1] < k:
            z = torch.cat([z, torch.zeros(P, k - z.shape[1], dtype=torch.float64)], 1)
            basis = torch.cat([basis, torch.zeros(Kf, k - basis.shape[1], D, dtype=torch.float64)], 1)
        head = torch.zeros(Kf, H, D, dtype=torch.float64)
        if p["init"] == "pca":
            head[:, :k] = basis
        else:
            g = torch.Generator().manual_seed(p["seed"] + 1)
            z = 0.1 * torch.randn(P, k, generator=g, dtype=torch.float64)
            head[:, :k] = torch.randn(Kf, k, D, generator=g, dtype=torch.float64) / math.sqrt(D)
        layers = []
        if H > k:
            dims = [k] + [p["width"]] * p["depth"] + [H - k]
            per = Kf if (p["cluster_decoder"] == "full" and Kf > 1) else 0  # one φ per cluster: [K, o, a] weights
            for a, b in zip(dims[:-1], dims[1:]):
                lins = [torch.nn.Linear(a, b, dtype=torch.float64) for _ in range(max(1, per))]  # default init, seeded
                wgt = torch.stack([lin.weight.detach() for lin in lins]) if per else lins[0].weight.detach().clone()
                bia = torch.stack([lin.bias.detach() for lin in lins]) if per else lins[0].bias.detach().clone()
                layers.append((wgt, bia))
        self.labels = labels
        self.K = Kf
        return {"z": z.to(dt), "head": head.to(dt), "bias": means.to(dt), "layers": [(a.to(dt), b.to(dt)) for a, b in layers]}

    def _pred(self, st, idx=None, z=None):
        z = st["z"] if z is None else z
        zb = z if idx is None or z is not st["z"] else z[idx]
        lab = None if self.labels is None else (self.labels if idx is None else self.labels[idx])
        layout = None if lab is None else tile_layout(lab, self.K)  # one layout for φ_k and the last layer
        F = _phi_features(zb, lab, st["layers"], _ACTIVATIONS[self.p["activation"]], layout)
        return _cluster_affine(F, lab, layout, st["head"], st["bias"])

    def _loss_rows(self, st, idx=None, z=None) -> torch.Tensor:
        """Per-row weighted squared error of the scaled signal (rows ``idx``, or all)."""
        Y = self.Y if idx is None else self.Y[idx]
        r = (Y - self._pred(st, idx, z)).square().sum(1)
        if self.w is not None:
            r = r * (self.w if idx is None else self.w[idx])
        return r

    def loss_sum(self, st, idx: torch.Tensor | None = None) -> float:
        """Σ of :meth:`_loss_rows` over rows ``idx`` (all: None), float64, without gradients, by
        blocks of about :data:`CHUNK_ELEMENTS` values (at D = 16 128: 130 rows; the former 16 384-row
        blocks made three table-sized float32 temporaries — the rows, the prediction, the residual)."""
        n = self.P if idx is None else idx.numel()
        rows = max(1, min(16384, CHUNK_ELEMENTS // max(1, self.D)))
        s = 0.0
        with torch.no_grad():
            for i in range(0, n, rows):
                part = torch.arange(i, min(n, i + rows)) if idx is None else idx[i:i + rows]
                s += float(self._loss_rows(st, part).double().sum())
        return s

    def full_loss(self, st) -> float:
        return self.loss_sum(st) / self.P

    @staticmethod
    def _clone(st):
        return {"z": st["z"].detach().clone(), "head": st["head"].detach().clone(), "bias": st["bias"].detach().clone(),
                "layers": [(a.detach().clone(), b.detach().clone()) for a, b in st["layers"]]}

    def run(self):
        p = self.p
        st = self._init()
        init = self._clone(st)
        init_loss = self.full_loss(st)
        self.info.update({"pca_loss": init_loss, "init": p["init"]})
        P = self.P
        gen = torch.Generator().manual_seed(p["seed"])
        n_hold = int(P * p["holdout"]) if P >= 10 else 0
        perm = torch.randperm(P, generator=gen)
        hold, train = perm[:n_hold].sort().values, perm[n_hold:].sort().values
        self.info.update({"holdout_points": n_hold, "train_points": int(train.numel())})
        if p["optimizer"] == "adam":
            best, stop, hist = self._adam(st, train, hold, gen)
        else:
            best, stop, hist = self._lbfgs(st, train, hold)
        self.info.update(stop)
        self.info["history"] = hist
        st = best
        # codes stored in their dtype, then the last layer solved exactly on those codes' features
        cdt = torch.float16 if p["code_dtype"] == "float16" else torch.float32
        for s_ in (st, init):
            s_["z"] = (s_["z"] * self.scale).to(cdt).to(self.dt) / self.scale
        init_loss16 = self.full_loss(init)
        before = self.full_loss(st)
        solved = self._solve_head(st)
        after = self.full_loss(solved) if solved is not None else math.inf
        if after <= before:
            st = solved
        final = min(before, after)
        self.info.update({"loss_before_head_solve": before, "loss_after_head_solve": after, "train_loss": final,
                          "pca_loss_stored_codes": init_loss16})
        kept_pca = not (final <= init_loss16)  # (NaN: kept as well)
        if kept_pca:
            st = init
            self.info["train_loss"] = init_loss16
        self.info["kept_pca_start"] = kept_pca
        # back to the signal's units: x = μ + s (b + W h(z)), z in units of s
        s = self.scale
        k = self.p["latent"]
        head = st["head"].double() * s
        head[:, :k] = st["head"][:, :k].double()  # the skip rows act on z in the signal's units already
        out = {"z": (st["z"].double() * s), "head": head,
               "bias": st["bias"].double() * s + self.mu[None],
               "layers": [(a.double() / s if i == 0 else a.double(), b.double()) for i, (a, b) in enumerate(st["layers"])],
               "labels": self.labels}
        return out, self.info

    # -- the last layer by least squares
    def _solve_head(self, st):
        """W_k, b_k minimising Σ_{p∈k} w_p ||y_p − b_k − W_k h(z_p)||² given the features (float64
        normal equations per cluster, accumulated over the tile layout; a tiny ridge for
        rank-deficient features, e.g. constant data)."""
        with torch.no_grad():
            H1 = st["head"].shape[1] + 1
            G = torch.zeros(self.K, H1, H1, dtype=torch.float64)
            R = torch.zeros(self.K, H1, self.D, dtype=torch.float64)
            lab_all = self.labels if self.labels is not None else torch.zeros(self.P, dtype=torch.long)
            rows = max(1, CHUNK_ELEMENTS // self.D)
            for i in range(0, self.P, rows):  # chunks of points bound the float64 [rows, D] copies
                z = st["z"][i:i + rows]
                lab_c = lab_all[i:i + rows] if self.labels is not None else None
                F = torch.cat([torch.ones(z.shape[0], 1, dtype=torch.float64), self._feat({**st, "z": z}, lab_c).double()], 1)
                Y = self.Y[i:i + rows].double()
                if self.w is not None:
                    sw = self.w[i:i + rows].double().sqrt()[:, None]
                    F, Y = F * sw, Y * sw
                layout = tile_layout(lab_all[i:i + rows], self.K)
                Ft = to_tiles(layout, F)
                G += tiles_accumulate(layout, Ft, Ft)
                R += tiles_accumulate(layout, Ft, to_tiles(layout, Y))
            tr = G.diagonal(dim1=1, dim2=2).sum(-1).clamp_min(1e-300)
            G = G + (1e-10 * tr)[:, None, None] * torch.eye(G.shape[1], dtype=torch.float64)
            try:
                sol = torch.linalg.solve(G, R)  # [K, 1+H, D]
            except RuntimeError:
                return None
            if not bool(torch.isfinite(sol).all()):
                return None
            out = self._clone(st)
            out["bias"], out["head"] = sol[:, 0].to(self.dt), sol[:, 1:].to(self.dt).contiguous()
            return out

    def _feat(self, st, labels):
        """h(z) of the state's codes ``st['z']`` with their clusters ``labels`` (None: K = 1)."""
        return _phi_features(st["z"], labels, st["layers"], _ACTIVATIONS[self.p["activation"]])

    # -- Adam on minibatches
    def _adam(self, st, train, hold, gen):
        p = self.p
        lr = p["lr"]
        dec = [st["head"], st["bias"], *[t for pair in st["layers"] for t in pair]]
        es = _EarlyStop(self, st, train, hold, "epoch", dec)
        opt = _Adam(dec, lr)
        z = st["z"]
        zopt = _Adam([z], lr, rows=True)  # Adam on the rows of each minibatch (each row its own step count)
        B = min(p["batch_size"], max(1, train.numel()))
        nt = train.numel()
        try:
            for ep in range(1, p["epochs"] + 1):
                order = train[torch.randperm(nt, generator=gen)]
                tot = 0.0
                diverged = None
                for i in range(0, nt, B):
                    idx = order[i:i + B]
                    zb = z[idx].detach().requires_grad_(True)
                    loss = self._loss_rows(st, idx, zb).sum() / idx.numel()
                    lv = float(loss.detach())
                    if not math.isfinite(lv):
                        diverged = f"the loss became {lv} at epoch {ep}"
                        break
                    tot += lv * idx.numel()
                    for t in dec:
                        t.grad = None
                    loss.backward()
                    opt.step()
                    with torch.no_grad():
                        zopt.step_rows(idx, zb.grad)
                if es.epoch(st, ep, tot / max(1, nt), diverged):
                    break
        finally:
            es.close()
        return es.result()

    def _hold_steps(self, st, hold):
        """Codes-only Adam steps of the held-out points (the decoder fixed): they follow the
        decoder without training it (DeepSDF §4's inference, a few steps per epoch)."""
        if not hold.numel():
            return
        z = st["z"]
        if getattr(self, "_hold_opt", None) is None:
            self._hold_opt = _Adam([z], self.p["lr"], rows=True)
        dec = [st["head"], st["bias"], *[t for pair in st["layers"] for t in pair]]
        req = [t.requires_grad for t in dec]
        for t in dec:
            t.requires_grad_(False)
        try:
            for _ in range(HOLDOUT_STEPS):
                zb = z[hold].detach().requires_grad_(True)
                loss = self._loss_rows(st, hold, zb).sum() / hold.numel()
                g, = torch.autograd.grad(loss, zb)
                self._hold_opt.step_rows(hold, g)
        finally:
            for t, r in zip(dec, req):
                t.requires_grad_(r)

    def _hold_loss(self, st, hold) -> float:
        return self.loss_sum(st, hold) / max(1, hold.numel())

    # -- full-batch L-BFGS
    def _lbfgs(self, st, train, hold):
        p = self.p
        z = st["z"]
        zt = z[train].clone().requires_grad_(True)
        dec = [st["head"], st["bias"], *[t for pair in st["layers"] for t in pair]]
        es = _EarlyStop(self, st, train, hold, "step", dec)
        opt = torch.optim.LBFGS([zt, *dec], lr=p["lr"], max_iter=20, history_size=20, line_search_fn="strong_wolfe",
                                tolerance_grad=0.0, tolerance_change=0.0)
        nt = train.numel()

        def closure():
            opt.zero_grad(set_to_none=True)
            loss = self._loss_rows(st, train, zt).sum() / nt
            loss.backward()
            return loss

        try:
            for ep in range(1, p["epochs"] + 1):
                train_loss = float(opt.step(closure).detach())
                with torch.no_grad():
                    z[train] = zt.detach()
                if es.epoch(st, ep, train_loss, None):
                    break
        finally:
            es.close()
        return es.result()


class _EarlyStop:
    """The per-epoch bookkeeping both optimisers of :class:`_Trainer` share: divergence (a non-finite
    loss, or a training loss above ``DIVERGENCE_FACTOR`` × the best so far, the PCA start's
    included) → stop with the last good state and a warning; the criterion (the held-out points'
    loss after their codes-only steps, or the training loss without a holdout); the best state, the
    patience count, the history ``[[train, criterion], ...]`` and the progress bar. ``unit``:
    'epoch' (Adam) or 'step' (L-BFGS), as the messages say; ``dec``: the decoder's tensors, which
    require gradients from here until :meth:`close`."""

    def __init__(self, tr: "_Trainer", st: dict, train: torch.Tensor, hold: torch.Tensor, unit: str, dec: list):
        self.tr, self.hold, self.unit, self.dec = tr, hold, unit, dec
        for t in dec:
            t.requires_grad_(True)
        self.crit_hold = hold.numel() > 0
        self.best_crit = tr._hold_loss(st, hold) if self.crit_hold else tr.full_loss(st)
        self.best = tr._clone(st)
        self.best_train = tr.loss_sum(st, train) / max(1, train.numel())  # the start's (PCA)
        self.best_epoch, self.bad, self.stop, self.hist = 0, 0, {"stopped": "max_epochs"}, []
        self.bar = _bar(tr.p["progress"], tr.p["epochs"])

    def epoch(self, st: dict, ep: int, train_loss: float, diverged: str | None) -> bool:
        """After epoch ``ep`` (training loss ``train_loss``; ``diverged``: a reason found during it):
        the divergence checks, the held-out codes' steps and criterion, the best state and patience.
        Returns True when the fit stops (diverged or out of patience)."""
        u, p = self.unit, self.tr.p
        if diverged is None and not math.isfinite(train_loss):
            diverged = f"the loss became {train_loss} at {u} {ep}"
        elif diverged is None and train_loss > DIVERGENCE_FACTOR * max(self.best_train, 1e-30):
            diverged = (f"the training loss rose to {train_loss:.4g} at {u} {ep}, above {DIVERGENCE_FACTOR:g}x "
                        f"its best {self.best_train:.4g}")
        crit = train_loss
        if diverged is None:
            self.best_train = min(self.best_train, train_loss)
            if self.crit_hold:
                self.tr._hold_steps(st, self.hold)
                crit = self.tr._hold_loss(st, self.hold)
            if not math.isfinite(crit):
                diverged = f"the held-out loss became {crit} at {u} {ep}"
        if diverged is not None:
            self.stop = {"stopped": "diverged", "diverged": diverged}
            self.tr.codec._warn_or_raise(
                f"{self.tr.codec.codec_name}: training diverged ({diverged}; lr={p['lr']:g}); kept the last good state "
                f"({u} {self.best_epoch}); accepted: a smaller lr (e.g. {p['lr'] / 10:g})")
            return True
        self.hist.append([train_loss, crit])
        self.bar.update(1)
        self.bar.set_postfix(loss=f"{train_loss:.3e}", holdout=f"{crit:.3e}" if self.crit_hold else "-")
        if crit < self.best_crit * (1 - 1e-7):
            self.best_crit, self.best_epoch, self.bad = crit, ep, 0
            self.best = self.tr._clone(st)
            return False
        self.bad += 1
        if self.bad >= p["patience"]:
            self.stop = {"stopped": "early_stop"}
            return True
        return False

    def close(self) -> None:
        """The bar closed, the decoder's tensors back to no gradient."""
        self.bar.close()
        for t in self.dec:
            t.requires_grad_(False)

    def result(self) -> tuple[dict, dict, list]:
        """``(best state, stop record, history)``."""
        stop = dict(self.stop, epochs=len(self.hist), best_epoch=self.best_epoch, best_criterion=self.best_crit,
                    criterion="holdout" if self.crit_hold else "train")
        return self.best, stop, self.hist


class _Adam:
    """Adam (Kingma & Ba 2015, Algorithm 1) on a list of tensors updated in place, without
    ``torch.optim`` (whose first use imports torch's compiler stack: ~5 s). ``rows=True``: one
    tensor whose rows are updated only when present in a minibatch, each row with its own step
    count (lazy Adam for the per-point codes of an auto-decoder)."""

    def __init__(self, params: list, lr: float, rows: bool = False, betas=(0.9, 0.999), eps: float = 1e-8):
        self.params, self.lr, self.b1, self.b2, self.eps = params, lr, betas[0], betas[1], eps
        self.m = [torch.zeros_like(t) for t in params]
        self.v = [torch.zeros_like(t) for t in params]
        self.t = torch.zeros(params[0].shape[0], 1, dtype=params[0].dtype) if rows else 0

    @torch.no_grad()
    def step(self) -> None:
        self.t += 1
        c1, c2 = 1 - self.b1 ** self.t, 1 - self.b2 ** self.t
        for x, m, v in zip(self.params, self.m, self.v):
            if x.grad is None:
                continue
            g = x.grad
            m.mul_(self.b1).add_(g, alpha=1 - self.b1)
            v.mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
            x.sub_(self.lr * (m / c1) / ((v / c2).sqrt_() + self.eps))

    @torch.no_grad()
    def step_rows(self, idx: torch.Tensor, g: torch.Tensor) -> None:
        x, m, v, t = self.params[0], self.m[0], self.v[0], self.t
        t[idx] += 1
        mi = m[idx].mul_(self.b1).add_(g, alpha=1 - self.b1)
        vi = v[idx].mul_(self.b2).addcmul_(g, g, value=1 - self.b2)
        m[idx], v[idx] = mi, vi
        ti = t[idx]
        x[idx] = x[idx] - self.lr * (mi / (1 - self.b1 ** ti)) / ((vi / (1 - self.b2 ** ti)).sqrt_() + self.eps)


def _bar(enabled: bool, total: int):
    """A tqdm progress bar with the loss (or a silent stand-in)."""
    if enabled:
        from tqdm import tqdm

        return tqdm(total=total, desc="neural fit", unit="epoch", leave=False)

    class _Null:
        def update(self, n):
            pass

        def set_postfix(self, **kw):
            pass

        def close(self):
            pass

    return _Null()


@contextlib.contextmanager
def _quiet():
    """The PCA/CPCA start's convergence warnings are not this fit's (its own info records them)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        yield

