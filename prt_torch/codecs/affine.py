"""The piecewise-affine model shared by VQ, PCA, CPCA and MRT-PCA (Sloan 2003 §3.3).

Every point p belongs to a cluster k(p) and is approximated as

    x̃_p = x_0^k + Σ_{i ≤ n_k} w_p^i x_i^k                      (Sloan 2003 §3.3)

VQ is the case n_k = 0, PCA the case of one cluster, CPCA the general case (n_k constant or,
adaptive, varying per cluster), MRT-PCA one cluster without a mean (Lehtinen & Kautz 2003
eq. (12)). Fitted state (float32): ``means_ [K, D]`` (x_0, absent for uncentred models),
``basis_ [K, n_max, D]`` (orthonormal rows x_i; rows i ≥ n_k are zero), ``n_vectors_ [K]``.

Encoded codes: ``labels [P]`` (uint8 / int16 / int32, the smallest that holds K; absent when
K = 1) and ``coeffs`` — ``[P, n']`` float32, or, when n_k varies, packed: the n_{k(p)}
weights of each point one after the other, in point order (meta ``packed: true``).

As one array (``transform``, ``inverse_transform``): ``[P, n_max]`` float32 weights, names
``<codec>0 .. <codec>{n_max-1}``; a codec with a ``clusters`` parameter (VQ, CPCA) puts the
cluster index k(p) first, as a float (exact up to 2^24 clusters), named ``<codec>_cluster``:
``[P, 1 + n_max]``. Weights past a point's n_k (adaptive CPCA) are zeros, and are ignored by
``inverse_transform``.

Relighting from the compressed form (Sloan 2003 §6, Lehtinen & Kautz 2003 eq. (13)): the
per-cluster constants ``M_i l`` (``[K, 1+n, n_out, C]``) are computed once per light, then
every point takes its weighted sum ``e_p = (M_0 l) + Σ_i w_p^i (M_i l)`` as one batched GEMM
over cluster tiles (``segment.tiles_bmm``), never decoding x̃_p. With a view, ``y(v_p)·e_p``
(dense ``[P, n_out]``) or the 4-tap tent sum of eq. (13) (``(idx, w)``).
"""
from __future__ import annotations

import math
import operator
import threading
import time
import weakref
from typing import Any

import torch

from .. import io
from .._checks import check_finite, tensor_version
from ..params import Boolean, Interval, Options
from .base import (Codec, Encoded, Relighter, array_type, as_array_type, check_light, check_matrix_shape, check_out,
                   check_signal, check_view, check_weights, encoding_state, grad_required, input_ref, squared_error_rows, typed,
                   typed_relighter, view_tensors)
from .chunks import CHUNK_BYTES, STREAM_BYTES, CentredRows, chunk_rows, row_chunks, row_sq_norms
from .chunks import centred as centred_signal
from .kmeans import CACHE_BLOCK_BYTES, linear, row_chunk
from .relight_kernels import constants_layout as kernel_layout
from .relight_kernels import fits as kernel_fits
from .relight_kernels import light_flagged, native, run_checked, run_plan
from .relight_kernels import plan as kernel_plan
from .segment import from_tiles, segment_matmul, tile_layout, tiles_bmm, to_tiles

#: relight visits points cluster by cluster (``AffineCodec._cluster_sorted_codes``) when one
#: cluster's constants take at least this many bytes: CPCA 256×8 on 24×25 matrices (2.6 KB per
#: cluster) relights 1.2-1.4× faster so, VQ 256 (288 B per cluster, the table L2-resident) 0.9×
#: (paired, 50k points, 1 and 2 threads; benchmarks/bench_relight.py)
SORT_MIN_CLUSTER_BYTES = 1024

__all__ = ["AffineCodec", "check_enc_origin", "label_dtype", "signal_key"]


def check_enc_origin(codec: Any, enc: Encoded) -> None:
    """Refuse ``enc`` unless it is an :class:`Encoded` of this fitted ``codec``'s name, signal
    dimension ``D_`` and cluster count ``K_`` (the affine codecs and the neural codec, whose
    relighting form is affine)."""
    codec._require_fitted()
    if not isinstance(enc, Encoded):
        raise TypeError(f"enc must be an Encoded (from encode/load), got {type(enc).__name__}")
    if enc.codec != codec.codec_name or enc.meta.get("dim") != codec.D_ or enc.meta.get("clusters") != codec.K_:
        raise ValueError(f"enc (codec {enc.codec!r}, dim {enc.meta.get('dim')}, clusters {enc.meta.get('clusters')}) "
                         f"was not produced by this codec ({codec.codec_name!r}, dim {codec.D_}, clusters {codec.K_})")


def _memo(enc: Encoded, name: Any, build, model: tuple = ()) -> Any:
    """``build()``, kept in ``enc.cache[name]`` while the codes are the same tensors at the same
    versions (each one's id, storage address and version: a replaced tensor or an in-place edit
    rebuilds it) and ``model`` (the codec's tensors the value also depends on, ``_model_tensors``) likewise. The
    entry holds those tensors, so their ids stay unique while it lives. For the per-encoding caches
    of relighting and ``decode`` (tile plan, weights, packed offsets, kernel plans)."""
    held = (*enc.tensors.values(), *model)
    state = encoding_state(enc, held)
    hit = enc.cache.get(name)
    if hit is None or hit[0] != state:
        hit = enc.cache[name] = (state, build(), held)
    return hit[1]


def label_dtype(K: int) -> torch.dtype:
    """Smallest integer dtype holding cluster indices 0..K-1 (uint8, int16 or int32)."""
    if K <= 256:
        return torch.uint8
    if K <= 32768:
        return torch.int16
    return torch.int32


class AffineCodec(Codec):
    """Shared encode / decode / relight / storage / persistence of piecewise-affine codecs.

    Subclasses implement ``_check_data(P, D, matrix_shape)`` (data-dependent parameter checks,
    run before any work) and ``_fit_model(Xc, w, gen) -> dict`` returning ``labels int64 [P]``,
    ``means [K, D] float64`` (in the centred coordinates of Xc, or None), ``basis
    [K, n_max, D] float64``, ``n_vectors int64 [K]`` and ``info`` (dict).
    """

    centered: bool = True  # fit an affine (mean + vectors) model; False: linear (no mean)
    _parameter_constraints: dict[str, list] = {
        "seed": [Interval(int, 0, None)],
        "fit_dtype": [Options("auto", "float32", "float64")],
        "strict": [Boolean()],
    }

    def __getstate__(self):
        # the cached training encoding (a weak reference to the training X) is not state
        return {k: v for k, v in super().__getstate__().items() if k != "_train"}

    # ----------------------------------------------------------------- fit
    def _check_data(self, P: int, D: int, matrix_shape) -> None:
        pass

    def _fit_model(self, Xc: torch.Tensor, w: torch.Tensor | None, gen: torch.Generator) -> dict:
        raise NotImplementedError

    def _fit_dtype(self, P: int, D: int, choice: str) -> torch.dtype:
        if choice == "float64" or (choice == "auto" and P * D <= 2**23):
            return torch.float64
        return torch.float32

    def fit(self, X, y=None, weights=None, matrix_shape=None) -> "AffineCodec":
        """Fit on ``X [P, D]`` (float32/64 tensor or numpy array, finite), optional ``weights
        [P]`` ≥ 0 (by keyword) and ``matrix_shape=(n_out, n_in)``; ``y`` is ignored
        (scikit-learn convention). Parameters are validated first (``_parameter_constraints``,
        then ``_check_params``); all parameter/data checks happen before any work. Returns self."""
        p = self._validate()
        X_in, X = X, check_signal("X", X)
        P, D = X.shape
        w = check_weights(weights, P)
        ms = check_matrix_shape(matrix_shape, D)
        self._check_data(P, D, ms)
        t0 = time.perf_counter()
        dtype = self._fit_dtype(P, D, p.get("fit_dtype", "auto"))
        centred = bool(p.get("center", self.centered))
        step = row_chunk(D, 8)
        offset = torch.zeros(D, dtype=torch.float64)
        if centred:
            if w is None:  # column sums of row blocks in X's dtype (fast), the blocks' sums in float64
                for i in range(0, P, 1024):
                    offset += X[i:i + 1024].sum(0).double()
                offset /= P
            else:
                for i in range(0, P, step):  # chunks bound the float64 temporary
                    offset += (X[i:i + step].double() * w[i:i + step, None].double()).sum(0)
                offset /= float(w.sum())
        # the centred signal: a copy when it fits one chunk, else read by chunks and centred on
        # the fly (chunks.CentredRows; float32 in a float32 fit: X − offset rounded once to
        # float32, else via float64), so the fit holds the signal once (issue 42 part 3)
        Xc = centred_signal(X, offset, dtype, chunk_bytes=self._chunk_bytes(), stream_bytes=self._stream_bytes(),
                            stream=_mapped(X_in))
        w64 = None if w is None else w.double()
        gen = torch.Generator().manual_seed(int(p.get("seed", 0)))
        res = self._fit_model(Xc, w64, gen)
        labels = res["labels"].long()
        K = int(res["basis"].shape[0])
        basis = res["basis"]
        nvec = res["n_vectors"].long()
        for name, t in (("means", res["means"]), ("basis", basis)):
            if t is not None and not bool(torch.isfinite(t).all()):
                raise RuntimeError(f"codec {self.codec_name!r}: the fit produced non-finite {name}; "
                                   "the signal may be too badly scaled for float32 (try fit_dtype='float64')")
        self.K_, self.D_, self.matrix_shape_ = K, D, ms
        self.n_features_in_ = D  # scikit-learn convention
        self.means_ = (res["means"] + offset).to(torch.float32) if centred else None
        self.basis_ = basis.to(torch.float32)
        self.n_vectors_ = nvec
        self.fitted_ = True
        # training encoding, with the fit's float64 model (coefficients = B_k (x_p - x_0^k))
        coeffs = self._project(Xc, labels, res["means"], basis, dtype)
        enc = self._make_encoded(labels, coeffs)
        enc.array_type = array_type(X_in)
        # the training encoding, returned by encode(X) while X (the object passed in) is alive
        self._train = (signal_key(X), input_ref(X_in), enc)
        info = dict(res.get("info", {}))
        info["seconds"] = time.perf_counter() - t0
        info["fit_dtype"] = str(dtype).replace("torch.", "")
        info["se"] = self.squared_error(X, enc, w)
        info["se_relative"] = info["se"] / max(1e-300, float(_total_energy(Xc, w, centred)))
        self.fit_info_ = info
        return self

    def _chunk_bytes(self) -> int:
        """Signal bytes per chunk of a streamed fit or encode (``chunks.CHUNK_BYTES``; an
        instance attribute ``chunk_bytes_`` overrides it)."""
        return int(getattr(self, "chunk_bytes_", CHUNK_BYTES))

    def _stream_bytes(self) -> int:
        """Signals larger than this are fitted and encoded by chunks (``chunks.STREAM_BYTES``; an
        instance attribute ``stream_bytes_`` overrides it: 0 streams every signal). A
        memory-mapped numpy input is always streamed."""
        return int(getattr(self, "stream_bytes_", STREAM_BYTES))

    def _project(self, Xc, labels, means, basis, dtype) -> torch.Tensor:
        """Per-point weights w_p = B_k (x_p − x_0^k) ``[P, n_max]`` float32, masked by n_k;
        ``Xc`` a tensor or ``chunks.CentredRows`` (projected chunk by chunk)."""
        P = Xc.shape[0]
        K, nmax, D = basis.shape
        if nmax == 0:
            return torch.zeros(P, 0, dtype=torch.float32)
        Bt = basis.transpose(1, 2).to(dtype)  # [K, D, n]
        mb = None if means is None else torch.einsum("knd,kd->kn", basis, means).to(dtype)
        out = torch.empty(P, nmax, dtype=torch.float32)
        for i, j, x in row_chunks(Xc, getattr(Xc, "rows", None)):
            lab = labels[i:j]
            if K == 1:
                c = x @ Bt[0]
            else:
                c = segment_matmul(tile_layout(lab, K), x, Bt)
            if mb is not None:
                c -= mb[lab] if K > 1 else mb[0]
            mask = torch.arange(nmax)[None, :] < self.n_vectors_[lab][:, None]
            torch.mul(c.to(torch.float32), mask, out=out[i:j])
        return out

    # ----------------------------------------------------------------- codes
    @property
    def uniform_(self) -> bool:
        return bool((self.n_vectors_ == self.n_vectors_.max()).all()) if self.n_vectors_.numel() else True

    def _make_encoded(self, labels: torch.Tensor, coeffs: torch.Tensor) -> Encoded:
        P = labels.numel()
        tensors = {}
        if self.K_ > 1:
            tensors["labels"] = labels.to(label_dtype(self.K_))
        nmax = self.basis_.shape[1]
        packed = False
        if nmax > 0:
            if self.uniform_:
                tensors["coeffs"] = coeffs.contiguous()
            else:
                mask = torch.arange(nmax)[None, :] < self.n_vectors_[labels][:, None]
                tensors["coeffs"] = coeffs[mask].contiguous()
                packed = True
        meta = {"points": P, "dim": self.D_, "clusters": self.K_, "n_max": nmax, "packed": packed,
                "matrix_shape": list(self.matrix_shape_) if self.matrix_shape_ else None,
                "centered": self.means_ is not None}
        return Encoded(codec=self.codec_name, tensors=tensors, meta=meta)

    def _check_enc(self, enc: Encoded) -> None:
        check_enc_origin(self, enc)

    def labels_of(self, enc: Encoded) -> torch.Tensor:
        """Cluster index of every point, ``int64 [P]``."""
        if "labels" in enc.tensors:
            return enc.tensors["labels"].long()
        return torch.zeros(enc.points, dtype=torch.long)

    def coeffs_of(self, enc: Encoded) -> torch.Tensor:
        """Per-point weights ``[P, n_max] float32`` (zero beyond each point's n_k)."""
        nmax = self.basis_.shape[1]
        P = enc.points
        if nmax == 0:
            return torch.zeros(P, 0, dtype=torch.float32)
        c = enc.tensors["coeffs"]
        if not enc.meta.get("packed"):
            return c

        def build():
            mask = torch.arange(nmax)[None, :] < self.n_vectors_[self.labels_of(enc)][:, None]
            full = torch.zeros(P, nmax, dtype=torch.float32)
            full[mask] = c
            return full

        return _memo(enc, "coeffs_padded", build, model=self._model_tensors())

    # ----------------------------------------------------------------- encode
    def encode(self, X: torch.Tensor) -> Encoded:
        """Codes of ``X [P, D]``: each point to the cluster of least reconstruction error
        (Sloan 2003 §4.2), weights by projection onto that cluster's vectors (§4.1). The
        training signal's encoding is returned from the fit without recomputation (a copy
        sharing its tensors where X is the same data as another type: ``Encoded.array_type``)."""
        self._require_fitted()
        kind = array_type(X)
        X_in, X = X, check_signal("X", X)
        self._check_features(X)
        train = getattr(self, "_train", None)
        if train is not None and train[0] == signal_key(X) and train[1]() is not None:
            return typed(train[2], kind)
        dtype = torch.float64 if X.dtype == torch.float64 else torch.float32
        off = self.means_.double().mean(0) if self.means_ is not None else torch.zeros(self.D_, dtype=torch.float64)
        Xc = centred_signal(X, off, dtype, chunk_bytes=self._chunk_bytes(), via64=True, stream_bytes=self._stream_bytes(),
                            stream=_mapped(X_in))  # read by chunks when large
        means = None if self.means_ is None else (self.means_.double() - off)
        basis = self.basis_.double()
        labels = self._classify(Xc, means, basis)
        enc = self._make_encoded(labels, self._project(Xc, labels, means, basis, dtype))
        enc.array_type = kind
        return enc

    # ----------------------------------------------------------------- codes as one array
    @property
    def _clustered(self) -> bool:
        """Whether ``transform`` has a cluster column: the codec has a ``clusters`` parameter
        (VQ, CPCA; a fixed layout per codec, whatever K the fit found)."""
        return "clusters" in self.get_params(deep=False)

    def _code_columns(self) -> list[str]:
        self._require_fitted()
        return (["_cluster"] if self._clustered else []) + [str(i) for i in range(self.basis_.shape[1])]

    def _codes_to_array(self, enc: Encoded) -> torch.Tensor:
        """``[P, (1 +) n_max]`` float32: (the cluster index as a float,) the weights padded to n_max."""
        self._check_enc(enc)
        W = self.coeffs_of(enc)
        if not self._clustered:
            return W
        return torch.cat([self.labels_of(enc).to(torch.float32)[:, None], W], 1)

    def _codes_from_array(self, Z: torch.Tensor) -> Encoded:
        """The encoding of ``Z`` (``_codes_to_array``'s layout): cluster indices must be integers
        in [0, K); weights past a point's n_k are dropped."""
        if not self._clustered:
            return self._make_encoded(torch.zeros(Z.shape[0], dtype=torch.long), Z.contiguous())
        lab = Z[:, 0]
        bad = (lab != lab.round()) | (lab < 0) | (lab >= self.K_)
        if bool(bad.any()):
            i = int(torch.nonzero(bad)[0])
            raise ValueError(f"Z[{i}, 0] = {float(lab[i])!r} is not a cluster index; accepted: integers in [0, {self.K_})")
        return self._make_encoded(lab.long(), Z[:, 1:].contiguous())

    def _classify(self, Xc, means, basis) -> torch.Tensor:
        """argmin_k ||x − x_0^k||² − Σ_i ((x − x_0^k)·x_i^k)² over all clusters (Sloan 2003 §4.2),
        by chunked GEMM against all representatives."""
        P = Xc.shape[0]
        K = basis.shape[0]
        if K == 1:
            return torch.zeros(P, dtype=torch.long)
        return classify_all(Xc, row_sq_norms(Xc), means, basis)[0]

    # ----------------------------------------------------------------- decode
    def _n_eff(self, n_vectors) -> int:
        nmax = self.basis_.shape[1]
        if n_vectors is None:
            return nmax
        if isinstance(n_vectors, bool) or not isinstance(n_vectors, int) or n_vectors < 0:
            raise ValueError(f"n_vectors={n_vectors!r}; accepted: None or an integer in [0, {nmax}] (a prefix of the PCA vectors)")
        return min(int(n_vectors), nmax)

    def decode(self, enc: Encoded, n_vectors: int | None = None) -> torch.Tensor:
        """x̃_p ``[P, D] float32`` (Sloan 2003 §3.3); ``n_vectors`` keeps only a prefix of each
        cluster's PCA vectors (run-time quality knob, Lehtinen & Kautz 2003 §6). A tensor, or a
        numpy array for an encoding of numpy data (``Encoded.array_type``). When the codec's
        tensors (means, basis) or the encoding's (per-point weights) require grad: ``_decode_grad``,
        differentiable, in their promoted dtype."""
        self._check_enc(enc)
        n = self._n_eff(n_vectors)
        if grad_required(*enc.tensors.values(), *self._model_tensors()):
            return self._decode_grad(enc, n)
        reps = self._representatives(n)  # [K, J, D]
        W = self._weights1(enc, n)  # [P, J]
        K = self.K_
        if K == 1:
            out = W @ reps[0]
        elif reps.shape[1] == 1 and self.means_ is not None:
            out = reps[:, 0][self.labels_of(enc)]
        else:
            plan = self._plan(enc)
            out = from_tiles(plan["layout"], tiles_bmm(plan["layout"], plan["W1t"][..., : reps.shape[1]], reps))
        return as_array_type(out, enc.array_type)

    def _decode_grad(self, enc: Encoded, n: int) -> torch.Tensor:
        """``decode`` under autograd (the tiled batched GEMM writes into buffers, which autograd
        cannot follow, and caches the weights): x̃_p = x_0^k + Σ_i w_p^i x_i^k (Sloan 2003 §3.3)
        gathered per point in the promoted dtype of the means, basis and weights (float64 for
        gradcheck), with no cache. → ``[P, D]``."""
        c = self.coeffs_of(enc)[:, :n]
        B = self.basis_[:, :n]
        dt = torch.promote_types(torch.promote_types(B.dtype, c.dtype), torch.float32)
        if self.means_ is not None:
            dt = torch.promote_types(dt, self.means_.dtype)
        reps = torch.cat([self.means_.to(dt)[:, None], B.to(dt)], 1) if self.means_ is not None else B.to(dt)  # [K, J, D]
        W = torch.cat([torch.ones(c.shape[0], 1, dtype=dt), c.to(dt)], 1) if self.means_ is not None else c.to(dt)  # [P, J]
        if self.K_ == 1:
            return W @ reps[0]
        return torch.einsum("pj,pjd->pd", W, reps[self.labels_of(enc)])

    def squared_error(self, X, enc: Encoded, weights: torch.Tensor | None = None) -> float:
        """Σ_p w_p ||x_p − x̃_p||² (Sloan 2003 Table 1's "SE"); a signal larger than one chunk
        (``chunks.CHUNK_BYTES``) is decoded chunk by chunk (no decoded ``[P, D]`` copy, no cached
        relighting plan), with the arithmetic of ``Codec.squared_error``."""
        if not isinstance(X, torch.Tensor) or X.shape[0] * X.shape[1] * 4 <= min(self._stream_bytes(), 4 * self._chunk_bytes()):
            return super().squared_error(X, enc, weights)
        self._check_enc(enc)
        P, D = X.shape
        n = self.basis_.shape[1]
        reps = self._representatives(n)  # [K, J, D]
        labels, C = self.labels_of(enc), self.coeffs_of(enc)
        se = 0.0
        rows = chunk_rows(D, 4, self._chunk_bytes())
        for i in range(0, P, rows):
            lab, c = labels[i:i + rows], C[i:i + rows, :n]
            W1 = torch.cat([torch.ones(c.shape[0], 1), c], 1) if self.means_ is not None else c
            xh = W1 @ reps[0] if self.K_ == 1 else segment_matmul(tile_layout(lab, self.K_), W1.contiguous(), reps)
            se += squared_error_rows(X[i:i + rows], xh, None if weights is None else weights[i:i + rows])
        return se

    def _representatives(self, n: int) -> torch.Tensor:
        """``[K, J, D] float32``: (x_0,) x_1..x_n — J = n+1 with a mean, n without."""
        B = self.basis_[:, :n]
        if self.means_ is None:
            return B
        return torch.cat([self.means_[:, None], B], 1)

    def _weights1(self, enc: Encoded, n: int) -> torch.Tensor:
        """``[P, J]``: (1,) w_p^1..w_p^n (cached while the codes are the same: ``_memo``)."""

        def build():
            c = self.coeffs_of(enc)[:, :n]
            if self.means_ is not None:
                c = torch.cat([torch.ones(c.shape[0], 1), c], 1)
            return c.contiguous()

        return _memo(enc, ("W1", n), build, model=self._model_tensors())

    def _plan(self, enc: Encoded) -> dict:
        """Tile layout of the points by cluster and the weights in tile order, built once per
        encoding (the CPU counterpart of uploading per-cluster vertex buffers) and rebuilt when
        its codes change (a replaced tensor or an in-place edit: ``_memo``)."""

        def build():
            layout = tile_layout(self.labels_of(enc), self.K_)
            return {"layout": layout, "W1t": to_tiles(layout, self._weights1(enc, self.basis_.shape[1])).contiguous()}

        return _memo(enc, "plan", build, model=self._model_tensors())

    # ----------------------------------------------------------------- relight
    def cluster_constants(self, light: torch.Tensor, n: int | None = None) -> torch.Tensor:
        """Per-cluster constants M_i l (Sloan 2003 §6): ``[K, J, n_out, C] float32`` for a light
        ``[n_in, C]`` (J = n+1 with the mean term M_0 l, n without). One GEMM over the mean rows
        and one over the basis rows, read in place (no copy of the K·J·D model)."""
        self._require_fitted()
        n_out, n_in = self.matrix_shape_ or (1, self.D_)
        L = check_light(light, n_in)
        n = self._n_eff(n)
        K, C = self.K_, L.shape[1]
        parts = []
        if self.means_ is not None:
            parts.append((self.means_.reshape(K * n_out, n_in) @ L).view(K, 1, n_out, C))
        if n:
            nmax = self.basis_.shape[1]  # one GEMM over the whole stored basis (a view), then the first n
            parts.append((self.basis_.reshape(K * nmax * n_out, n_in) @ L).view(K, nmax, n_out, C)[:, :n])
        if not parts:
            return torch.zeros(K, 0, n_out, C)
        return parts[0].contiguous() if len(parts) == 1 else torch.cat(parts, 1)

    def relight(self, enc: Encoded, light: torch.Tensor, view: Any = None, n_vectors: int | None = None,
                out: torch.Tensor | None = None) -> torch.Tensor:
        """Radiance straight from the compressed form (Sloan 2003 §6; Lehtinen & Kautz 2003 eq. (13)).

        Per light, the per-cluster constants M_i l (``cluster_constants``); per point, one pass
        over its codes: ``e_p = M_0 l + Σ_i w_p^i M_i l`` and, with a view, ``y(v_p)·e_p`` (dense)
        or the tent sum of eq. (13) (taps) folded in before any ``[P, n_out, C]`` exists — the
        fused kernels of ``relight_kernels`` where a C compiler is available, else the torch
        formulation below (same results to float32 rounding).

        Args:
            light: ``[n_in, C]`` SH light (n_in = D for vector signals).
            view: None; dense ``[P, n_out]`` (e.g. y(v_p) in the local frame); or taps
                ``(idx int64 [P, k], w [P, k])`` (MRT tent basis, k = 4).
            n_vectors: use only the first n PCA vectors of each cluster (None: all).
            out: None, or the result tensor to write (contiguous float32 of the result's shape;
                ``base.check_out``): a render loop reusing one avoids a fresh allocation per frame
                — without a view ``[P, n_out, C]`` is large, and its first-touch page faults are a
                large share of the call (reports/benchmarks/relight.md, "new output").
        Returns: ``[P, C]`` float32 (vectors, or matrices with a view), else ``[P, n_out, C]``
        (``out`` when given); a tensor, or a numpy array for an encoding of numpy data
        (``Encoded.array_type``; the light and the view may be numpy arrays too).

        With ``out``, from the third call into the same ``out`` with the same view tensors (a float32
        contiguous light of the same shape, the codes, the model and the view's tensors unchanged
        but for the view's values) a call runs the prepared form's fast path (``fast_rows``, armed
        in ``enc.cache`` by the second full call into that ``out``, up to ``FAST_OUTS`` outputs:
        ~5 µs of checks instead of ~15-25, the same bits), so a render loop of ``relight(enc,
        light, view, out=buf)`` costs about what ``relighter(enc, view)(light, out=buf)`` does
        (benchmarks/bench_relight_call.py).
        """
        if out is not None and type(light) is torch.Tensor and (n_vectors is None or type(n_vectors) is int):
            fs = enc.cache.get(("rows_fast", id(self), n_vectors)) if isinstance(enc, Encoded) else None
            f = fs.get(id(out)) if fs is not None else None
            if f is not None and len(f) > 2 and f[0]() is out:
                res = fast_rows(self, enc, light, out, f, view)
                if res is not None:
                    return res
        self._check_enc(enc)
        P = enc.points
        n_out, n_in = self.matrix_shape_ or (1, self.D_)
        if self.matrix_shape_ is None and view is not None:
            raise ValueError("view was given but this codec was fitted on vectors (no matrix_shape); accepted: view=None")
        n = self._n_eff(n_vectors)
        if torch.is_grad_enabled() and grad_required(light, *(view if isinstance(view, tuple) else (view,)), *enc.tensors.values(),
                                                     *self._model_tensors()):
            if out is not None:
                raise ValueError("out= with a light, view or codec tensor that requires grad; accepted: out=None (autograd "
                                 "cannot write into a reused buffer)")
            return self._relight_grad(enc, light, view, n)
        lib = native()
        # with the kernels, structure only: a float32 light's values are checked by the constants
        # kernel and the view's inside the point kernels (a flag); only a bad call pays for the
        # full check that names the value (another dtype is checked here, as given and as float32)
        L = check_light(light, n_in, values=lib is None or getattr(light, "dtype", None) != torch.float32)
        if out is not None:
            C = L.shape[1]
            shape = (P, C) if view is not None or self.matrix_shape_ is None else (P, n_out, C)
            out = check_out(out, shape, view, light)
        if lib is not None:
            v = check_view(view, P, n_out, values=False) if self.matrix_shape_ is not None else None
            got = self._relight_native(lib, enc, L, v, n, out)
            if got is not None:
                res, flag = got
                if flag:
                    check_view(view, P, n_out)  # raises with the offending value; else the data overflowed
                if out is not None and L is light and light.is_contiguous() and (
                        view is None or v is view or (type(v) is tuple and v[0] is view[0] and v[1] is view[1])):  # as given
                    self._arm_rows(lib, enc, n, n_vectors, light, out, v)
                return res if out is not None or enc.array_type == "torch" else res.numpy()
            check_finite("light", L)  # the torch formulation below
        view = check_view(view, P, n_out) if self.matrix_shape_ is not None else None
        res = self._relight_torch(enc, light, view, n)
        return as_array_type(res, enc.array_type) if out is None else out.copy_(res)

    #: outputs per encoding, codec and n_vectors whose relight(out=) calls keep a fast-path entry (double or triple
    #: buffering: each buffer its own entry); the oldest is dropped beyond
    FAST_OUTS = 4

    def _arm_rows(self, lib, enc: Encoded, n: int, n_vectors: Any, light: torch.Tensor, out: torch.Tensor,
                  view: Any = None) -> None:
        """After a full ``relight(enc, light, view, out=out)`` that ran the kernels on the view as
        given (``view``: None, or the checked dense view or taps, the same tensors the caller
        passed): the entry of ``fast_rows`` for the next such call into ``out`` (``arm_rows``),
        kept in ``enc.cache`` under this codec and ``n_vectors`` (the value as given: the key of the
        call), one per output tensor (up to ``FAST_OUTS``: a double-buffered loop keeps both). The
        first full call into an ``out`` only notes it (a weak reference and the view's tensors'
        ids), the second with the same view arms it: a call into a new tensor each time, or with
        another view each time, pays no arming. Held there, not on the codec: an entry holds the
        codes', the model's and the view's tensors, never the encoding or ``out``."""
        if not (n_vectors is None or type(n_vectors) is int) or n + (self.means_ is not None) == 0:
            return
        key = ("rows_fast", id(self), n_vectors)
        fs = enc.cache.get(key)
        if fs is None:
            fs = enc.cache[key] = {}
        vids = None if view is None else ((id(view[0]), id(view[1])) if type(view) is tuple else id(view))
        slot = fs.get(id(out))
        if slot is None or slot[1] != vids or slot[0]() is not out:  # the first full call into this out (with this view)
            fs.pop(id(out), None)
            while len(fs) >= self.FAST_OUTS:  # (pop with a default: another thread may drop the same entry)
                fs.pop(next(iter(fs), None), None)
            fs[id(out)] = (weakref.ref(out), vids)
            return
        ntap = view[0].shape[1] if isinstance(view, tuple) else 0
        kind = "rows" if view is None else ("taps" if ntap else "dense")
        f = arm_rows(lib, self._kernel_plan(lib, enc, n, kind, light.shape[1], ntap), light, out,
                     (*enc.tensors.values(), *self._model_tensors()), view)
        if f is None:
            fs.pop(id(out), None)
        else:
            fs[id(out)] = f

    def relighter(self, enc: Encoded, view: Any = None, n_vectors: int | None = None) -> "AffineRelighter":
        """A prepared relighting (``base.Relighter``): ``r = codec.relighter(enc, view)``, then
        ``r(light, out=buf)`` per light, the same bits as ``relight(enc, light, view, n_vectors,
        out=buf)``. Everything ``relight`` checks per call is checked here once (the view's values
        in full); per call only the light's type and shape, ``out`` (in full when it is another
        tensor than the last call's), and whether the codes and the model are the same tensors at
        the same versions, then one kernel call: ~4 µs less per light than ``relight``, what a
        small relight costs (reports/benchmarks/relight.md, "prepared")."""
        return typed_relighter(AffineRelighter(self, enc, view, n_vectors))

    def _relight_grad(self, enc: Encoded, light, view, n: int) -> torch.Tensor:
        """``relight`` under autograd (the fused C kernels are forward-only): the same sums in torch,
        in the light's dtype (float64 for ``torch.autograd.gradcheck``), differentiable with respect
        to the light, the view weights and the codec's tensors (means, basis, per-point weights).
        Sloan 2003 §6: e_p = M_0^k l + Σ_i w_p^i M_i^k l; with a view y(v_p)·e_p or eq. (13)'s taps."""
        n_out, n_in = self.matrix_shape_ or (1, self.D_)
        L = torch.as_tensor(light)
        if L.ndim != 2 or L.shape[0] != n_in or not L.is_floating_point():
            check_light(light, n_in)  # raises with the accepted shape
        dt = torch.promote_types(L.dtype, torch.float32)
        L = L.to(dt)
        K, C, P = self.K_, L.shape[1], enc.points
        parts = []
        if self.means_ is not None:
            parts.append((self.means_.to(dt).reshape(K * n_out, n_in) @ L).view(K, 1, n_out, C))
        if n:
            nb = self.basis_[:, :n].to(dt)
            parts.append((nb.reshape(K * n * n_out, n_in) @ L).view(K, n, n_out, C))
        if not parts:
            return torch.zeros(P, C, dtype=dt) if view is not None or self.matrix_shape_ is None else torch.zeros(P, n_out, C, dtype=dt)
        consts = torch.cat(parts, 1)  # [K, J, n_out, C]
        c = self.coeffs_of(enc)[:, :n].to(dt)
        W = torch.cat([torch.ones(P, 1, dtype=dt), c], 1) if self.means_ is not None else c  # [P, J]
        if isinstance(view, tuple):
            idx, g = view
            return _taps_relight(consts, W, (torch.as_tensor(idx).long(), torch.as_tensor(g).to(dt)),
                                 None if K == 1 else self.labels_of(enc))
        e = torch.einsum("pj,pjoc->poc", W, consts[self.labels_of(enc)] if K > 1 else consts[0].expand(P, *consts.shape[1:]))
        if view is None:
            return e[:, 0] if self.matrix_shape_ is None else e
        return torch.einsum("po,poc->pc", torch.as_tensor(view).to(dt), e)

    def _relight_torch(self, enc: Encoded, light, view, n: int) -> torch.Tensor:
        """The torch formulation of ``relight`` (no compiled kernels), on a checked view."""
        P = enc.points
        n_out = self.matrix_shape_[0] if self.matrix_shape_ else 1
        consts = self.cluster_constants(light, n)  # [K, J, n_out, C]
        K, J, _, C = consts.shape
        W = self._weights1(enc, n)  # [P, J]
        if J == 0:  # no mean and no vectors kept: x̃ = 0
            return torch.zeros(P, C) if view is not None or self.matrix_shape_ is None else torch.zeros(P, n_out, C)
        if isinstance(view, tuple):
            # sparse view (MRT tents): gather only the k tapped rows of each point's cluster
            # constants (one fused gather-sum), then J multiply-adds per colour
            return _taps_relight(consts, W, view, None if K == 1 else self.labels_of(enc))
        F = n_out * C
        if K == 1:
            out = W @ consts[0].reshape(J, F)
        elif J == 1 and self.means_ is not None:
            out = consts[:, 0].reshape(K, F)[self.labels_of(enc)]
        else:
            plan = self._plan(enc)
            out_t = tiles_bmm(plan["layout"], plan["W1t"][..., :J], consts.reshape(K, J, F))
            out = from_tiles(plan["layout"], out_t)
        out = out.view(P, n_out, C)
        if view is None:
            return out[:, 0] if self.matrix_shape_ is None else out
        return torch.einsum("po,poc->pc", view, out)

    def _relight_native(self, lib, enc: Encoded, L: torch.Tensor, view, n: int, out: torch.Tensor | None = None):
        """The fused-kernel path of ``relight``: ``(out, flag)``, or None where the kernels' buffers
        are too small (``relight_kernels.fits``). Per light, the constants straight into the
        layout the kernel reads (one pass over the model); per point, one pass over the codes,
        writing into ``out`` (checked by ``relight``) when given; ``L`` is the checked light."""
        n_out, n_in = self.matrix_shape_ or (1, self.D_)
        C = L.shape[1]
        J = (1 if self.means_ is not None else 0) + n
        if J == 0:  # no mean and no vectors kept: x̃ = 0 (the light's and view's values still checked)
            check_finite("light", L)
            check_view(view, enc.points, n_out)
            if out is not None:
                return out.zero_(), 0
            return (torch.zeros(enc.points, C) if view is not None or self.matrix_shape_ is None
                    else torch.zeros(enc.points, n_out, C)), 0
        ntap = view[0].shape[1] if isinstance(view, tuple) else 0
        if not kernel_fits(J, n_out, C) or ntap > 64:
            return None
        kind = "rows" if view is None else ("taps" if isinstance(view, tuple) else "dense")
        res, flag = run_plan(lib, self._kernel_plan(lib, enc, n, kind, C, ntap), L, view, out)
        if view is None:
            return (res if out is not None or self.matrix_shape_ is None else res.view(-1, n_out, C)), 0
        return res, flag

    def kernel_path(self, enc: Encoded, view=None, C: int = 3, n_vectors: int | None = None) -> dict:
        """Which code ``relight(enc, light [n_in, C], view)`` runs (``relight_kernels.kernel_path``:
        backend, the compiled instruction set, threads and the point kernel of this encoding's
        plan — the one ``relight`` builds and caches), for benchmarks to name per row (issue 42 §4).
        Its shapes alone decide it, so no light is needed."""
        from .relight_kernels import kernel_path

        lib = native()
        n = self._n_eff(n_vectors)
        n_out = (self.matrix_shape_ or (1, self.D_))[0]
        J = (1 if self.means_ is not None else 0) + n
        ntap = view[0].shape[1] if isinstance(view, tuple) else 0
        if lib is None or J == 0 or not kernel_fits(J, n_out, C) or ntap > 64:
            info = kernel_path()
            if lib is not None:
                info.update(backend="torch", path="torch formulation (shapes past the kernels' buffers, or no terms)")
            return info
        kind = "rows" if view is None else ("taps" if isinstance(view, tuple) else "dense")
        return kernel_path(self._kernel_plan(lib, enc, n, kind, C, ntap))

    def _kernel_plan(self, lib, enc: Encoded, n: int, kind: str, C: int, ntap: int):
        """This encoding's ``relight_kernels.Plan`` for ``n`` vectors, view ``kind``, C colours
        and ``ntap`` taps, built once and cached in ``enc.cache`` while the model and the codes
        are the same tensors at the same versions (a refit, an in-place edit or a replaced
        tensor rebuilds it; the plan holds them, so their ids stay unique while it lives)."""
        key = ("kernel_plan", n, kind, C, ntap, SORT_MIN_CLUSTER_BYTES)  # (the module's threshold: benchmarks and tests set it)
        return _memo(enc, key, lambda: self._build_kernel_plan(lib, enc, n, kind, C, ntap), model=self._model_tensors())

    def _build_kernel_plan(self, lib, enc: Encoded, n: int, kind: str, C: int, ntap: int):
        basis, means = self.basis_, self.means_
        n_out, n_in = self.matrix_shape_ or (1, self.D_)
        codes = self._native_codes(enc, n)
        # Where a cluster's constants are large (CPCA: J·n_out·C floats, 2.6 KB at 9×24×3), points
        # are visited cluster by cluster within blocks, from a cluster-sorted copy of the codes
        # (Sloan 2003 §6: per-cluster work over cluster-sorted storage), so T_k is read from L1
        # instead of L2 for every point; only the view rows and outputs are scattered, within a
        # block. Same arithmetic per point, so the same results bit for bit.
        order = None
        J = (1 if means is not None else 0) + n
        if codes[0] is not None and kernel_layout(kind, self.K_, J, n_out, C)[1][0] * 4 >= SORT_MIN_CLUSTER_BYTES:
            order, codes = self._cluster_sorted_codes(enc, codes)
        # per cluster only the terms its points read (n_k: CPCA adaptive)
        return kernel_plan(lib, means, basis, n, n_out, n_in, C, kind, *codes, P=enc.points, order=order,
                           codes_sorted=order is not None, ntap=ntap)

    def _model_tensors(self) -> tuple:
        """The fitted model's tensors every per-encoding cache depends on (``_memo``'s ``model``):
        a refit replaces them, an in-place edit bumps their versions, and a codec without a mean
        (``means_`` None) keys apart from one with it — each rebuilds the caches (per-cluster
        term counts decide packed offsets and padded weights; the mean decides the weights' ones)."""
        return (self.basis_, self.means_, self.n_vectors_)

    def _cluster_sorted_codes(self, enc: Encoded, codes: tuple) -> tuple[torch.Tensor, tuple]:
        """The visiting order ``int32 [P]`` — points sorted by cluster within consecutive blocks of
        B = clamp(32 K, 2048, 16384) points (stable: point order within a cluster) — and the codes
        (``_native_codes``' tuple) stored in that order; built once per encoding and cached
        (a second copy of the labels and weights: the CPU counterpart of Sloan's per-cluster vertex
        buffers). A block keeps the scattered view rows and outputs close together; 32 points per
        cluster and block on average amortise loading T_k (measured: benchmarks/bench_relight.py)."""
        labels, W, wstride, woff, nk, n, mean = codes

        def build():  # from the codes as read now (a stored tensor's contiguous() may be a fresh copy: _memo keys the stored ones)
            P, K = enc.points, self.K_
            B = min(max(32 * K, 2048), 16384)
            order = torch.argsort(torch.arange(P) // B * K + labels.long(), stable=True)
            lab_s = labels[order].contiguous()
            if W is None:
                W_s, woff_s = None, None
            elif woff is None:
                W_s, woff_s = W[order].contiguous(), None
            else:  # packed: each point's n_k weights, re-packed in the new order
                cnt = nk[lab_s.long()]
                woff_s = (torch.cumsum(cnt, 0) - cnt).contiguous()
                src = torch.repeat_interleave(woff[order] - woff_s, cnt) + torch.arange(int(cnt.sum()))
                W_s = W[src].contiguous()
            return order.to(torch.int32).contiguous(), lab_s, W_s, woff_s

        order, lab_s, W_s, woff_s = _memo(enc, "cluster_order", build, model=self._model_tensors())
        return order, (lab_s, W_s, wstride, woff_s, nk, n, mean)

    def _native_codes(self, enc: Encoded, n: int) -> tuple:
        """The codes as the kernels read them, in place: ``(labels or None, weights or None, row
        stride, packed offsets or None, n_k or None, n, has_mean)``. Labels are range-checked
        and packed offsets built once per encoding (cached); the kernels index with them."""
        labels = enc.tensors.get("labels") if self.K_ > 1 else None
        if labels is not None:
            stored = labels

            def checked():  # once per encoding and model (_memo): the range check, and a dtype the kernels read
                lab = stored if stored.dtype in (torch.uint8, torch.int16, torch.int32) else stored.to(
                    torch.int32 if self.K_ > 32768 else torch.int16)
                lab = lab.contiguous()
                lo, hi = torch.aminmax(lab.to(torch.int32)) if lab.numel() else (torch.tensor(0), torch.tensor(0))
                if lab.shape != (enc.points,) or int(lo) < 0 or int(hi) >= self.K_:
                    raise ValueError(f"enc labels have shape {tuple(lab.shape)} and span [{int(lo)}, {int(hi)}]; "
                                     f"accepted: [{enc.points}] in [0, {self.K_})")
                return lab

            labels = _memo(enc, "labels_checked", checked, model=self._model_tensors())
        nmax = self.basis_.shape[1]
        mean = self.means_ is not None
        if n == 0 or nmax == 0:
            return labels, None, 0, None, None, 0, mean
        c = enc.tensors["coeffs"]
        if not enc.meta.get("packed"):
            if c.shape != (enc.points, nmax) or c.dtype != torch.float32:
                raise ValueError(f"enc coeffs have shape {tuple(c.shape)} ({c.dtype}); accepted: [{enc.points}, {nmax}] float32")
            return labels, c.contiguous(), nmax, None, None, n, mean

        def offsets():  # per encoding, rebuilt when its codes change
            counts = self.n_vectors_[self.labels_of(enc)]
            if c.ndim != 1 or int(counts.sum()) != c.numel() or c.dtype != torch.float32:
                raise ValueError(f"enc packed coeffs have shape {tuple(c.shape)} ({c.dtype}); accepted: "
                                 f"[{int(counts.sum())}] float32 (Σ_p n_k(p))")
            return (torch.cumsum(counts, 0) - counts).contiguous()

        return (labels, c.contiguous(), 0, _memo(enc, "coeff_offsets", offsets, model=self._model_tensors()),
                self.n_vectors_.contiguous(), n, mean)

    # ----------------------------------------------------------------- storage
    def storage(self, enc: Encoded) -> dict[str, Any]:
        """Actual bytes (``Codec.storage``) plus Sloan 2003 §4.1's float count
        ``m_p n' + m_c (n'+1) n`` — generalised to per-cluster n_k as Σ_p n_{k(p)} + Σ_k (n_k+1) n
        (n_k n without a mean); cluster indices are not floats and are counted only in bytes."""
        self._check_enc(enc)
        out = super().storage(enc)
        P, D = enc.points, self.D_
        lab = self.labels_of(enc)
        nk = self.n_vectors_
        per_point = int(nk[lab].sum())
        per_cluster = int(((nk + (1 if self.means_ is not None else 0)) * D).sum())
        cost = per_point + per_cluster
        out.update({
            "clusters": self.K_, "vectors_max": int(self.basis_.shape[1]),
            "vectors_mean_per_point": per_point / max(P, 1),
            "sloan_cost_floats": cost, "sloan_per_point_floats": per_point, "sloan_per_cluster_floats": per_cluster,
            "sloan_ratio": P * D / cost if cost else math.inf,
            "relight_macs_per_point_per_channel": self._relight_cost(per_point / max(P, 1) + (1 if self.means_ is not None else 0)),
        })
        return out

    def _relight_cost(self, terms: float) -> float:
        """Multiply-adds per point per colour channel of the per-point stage (Sloan 2003 §6:
        n'+1 per output; ×n_out for matrices without a view), for ``terms`` = n'+1 terms per point
        on average (per-cluster n_k: the mean over the points, not the largest n_k)."""
        n_out = self.matrix_shape_[0] if self.matrix_shape_ else 1
        return float(terms * n_out)

    # ----------------------------------------------------------------- persistence
    def _state(self):
        tensors = {"basis": self.basis_.contiguous(), "n_vectors": self.n_vectors_.to(torch.int32)}
        if self.means_ is not None:
            tensors["means"] = self.means_.contiguous()
        meta = {"clusters": self.K_, "dim": self.D_, "centered": self.means_ is not None,
                "matrix_shape": list(self.matrix_shape_) if self.matrix_shape_ else None,
                "fit_info": io.jsonable(getattr(self, "fit_info_", {}))}
        return tensors, meta

    def _set_state(self, tensors, meta):
        try:
            self.basis_ = tensors["basis"].to(torch.float32)
            self.n_vectors_ = tensors["n_vectors"].long()
            self.means_ = tensors["means"].to(torch.float32) if meta.get("centered") else None
            self.K_, self.D_ = int(meta["clusters"]), int(meta["dim"])
            self.n_features_in_ = self.D_
        except KeyError as e:
            raise ValueError(f"codec file lacks {e}; it was not written by this codec's save") from None
        ms = meta.get("matrix_shape")
        self.matrix_shape_ = tuple(ms) if ms else None
        self.fit_info_ = meta.get("fit_info", {})
        if self.basis_.shape[0] != self.K_ or self.basis_.shape[2] != self.D_:
            raise ValueError(f"codec file: basis has shape {tuple(self.basis_.shape)}, expected [{self.K_}, n, {self.D_}]")


# ----------------------------------------------------------------------------------------
# kernels used by relight and by the fits
# ----------------------------------------------------------------------------------------

def _taps_relight(consts: torch.Tensor, W: torch.Tensor, view: tuple, labels: torch.Tensor | None = None) -> torch.Tensor:
    """Lehtinen & Kautz 2003 eq. (13), per cluster: ``Σ_{j∈taps} g_j(v) Σ_i w_{p,i} (M_i^{k(p)} l)_j``.

    ``consts [K, J, n_out, C]`` = M_i^k·l computed once per light (Sloan 2003 §6); ``W [P, J]``;
    taps ``(idx [P, t], g [P, t])``; ``labels [P]`` the cluster of each point (None: K = 1).
    Per point: the t tapped rows of its cluster's constants, weighted by g (one fused
    gather-and-sum over a ``[K·n_out, J·C]`` table, ``embedding_bag``), then J multiply-adds per
    colour with the point's weights — t·J·C loads and J·C multiply-adds, whatever n_out.
    Returns ``[P, C]``.
    """
    idx, g = view
    K, J, n_out, C = consts.shape
    table = consts.permute(0, 2, 1, 3).reshape(K * n_out, J * C).contiguous()  # row (k, o): (M_i^k l)_o for all i
    rows = idx if labels is None else labels[:, None] * n_out + idx
    s = torch.nn.functional.embedding_bag(rows, table, per_sample_weights=g, mode="sum").view(-1, J, C)
    return torch.einsum("pj,pjc->pc", W, s)


def classify_all(Xc: torch.Tensor, xx: torch.Tensor, means: torch.Tensor | None, basis: torch.Tensor,
                 top: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """Reconstruction error of every point in every cluster (Sloan 2003 §4.2):

        e_k(x) = ||x − x_0^k||² − Σ_i ((x − x_0^k)·x_i^k)²

    by one GEMM against all representatives per block of points, with the constant terms as
    the GEMM's bias (``addmm``): columns ``[−2 x_0^k, x_i^k]`` and bias ``[||x_0^k||², −x_i^k·x_0^k]``
    give ``−2 x·x_0 + ||x_0||²`` and the projections ``(x − x_0)·x_i`` directly; ``||x||²`` is
    added to the minimum only. Blocks of ``[rows, K(1+n)]`` sized to stay in cache.
    ``Xc [P, D]``, ``xx [P]`` = ``||x_p||²`` (Xc's dtype), ``means [K, D]`` or None,
    ``basis [K, n, D]`` (float64). Returns ``(labels int64 [P], e_min [P], top_k int64 [P, top]
    or None)``.
    """
    P, D = Xc.shape
    K, n, _ = basis.shape
    dt = Xc.dtype
    if means is None:
        means = torch.zeros(K, D, dtype=torch.float64)
    W = torch.cat([-2.0 * means[:, None], basis], 1).to(dt).reshape(K * (1 + n), D)
    bias = torch.cat([means.square().sum(1)[:, None], -torch.einsum("knd,kd->kn", basis, means)], 1)
    bias = bias.to(dt).reshape(1, K * (1 + n))
    labels = torch.empty(P, dtype=torch.long)
    emin = torch.empty(P, dtype=dt)
    # fewer clusters than candidates; the smallest integer type that holds K (int64 would be
    # 8·top bytes per point, more than a transfer signal of 16 floats)
    tops = torch.empty(P, min(top, K), dtype=label_dtype(K)) if top else None
    step = min(P, row_chunk(K * (1 + n), Xc.element_size(), CACHE_BLOCK_BYTES), getattr(Xc, "rows", P) or 1)
    W = W.contiguous()
    bias = bias.reshape(-1)
    for i in range(0, P, step):  # blocks bound the [rows, K(1+n)] temporary
        G = linear(Xc[i:i + step].contiguous(), W, bias).view(-1, K, 1 + n)  # GEMM with bias (kmeans.linear)
        if n:
            e = G[..., 0] - G[..., 1:].square_().sum(-1)
        else:
            e = G[..., 0]
        if top:
            v, j = torch.topk(e, min(top, K), dim=1, largest=False)
            tops[i:i + step] = j
            labels[i:i + step] = j[:, 0]
            emin[i:i + step] = v[:, 0]
        else:
            m = e.min(1)
            labels[i:i + step] = m.indices
            emin[i:i + step] = m.values
    emin += xx
    return labels, emin.clamp_min_(0), tops


def _mapped(X: Any) -> bool:
    """Whether ``X`` is a numpy memory map (or a view of one): a signal kept on disk, streamed."""
    import numpy as np

    while isinstance(X, np.ndarray):
        if isinstance(X, np.memmap):
            return True
        X = X.base
    return False


def _total_energy(Xc, w, centred: bool) -> float:
    """Σ_p w_p ||x_p||², rows' norms in Xc's dtype, their squares summed in float64 (the
    denominator of ``se_relative`` only); Xc a tensor or ``chunks.CentredRows``."""
    if w is None:
        return float(row_sq_norms(Xc, norm=True).double().sum()) if isinstance(Xc, CentredRows) else \
            float(torch.linalg.vector_norm(Xc, dim=1).double().square().sum())
    s = 0.0
    for i, j, x in row_chunks(Xc, 8192):
        r = x.double().square().sum(1) * w[i:j]
        s += float(r.sum())
    return s


def signal_key(X: torch.Tensor) -> tuple:
    """What identifies a signal tensor as the same data again (address, shape, dtype, version,
    strides): the key of a codec's cached training encoding (``encode`` of the training X)."""
    return (X.data_ptr(), tuple(X.shape), X.dtype, tensor_version(X), tuple(X.stride()))


class AffineRelighter(Relighter):
    """``AffineCodec.relighter``: ``relight`` with the encoding, the view and ``n_vectors`` bound
    and checked once (the view's values too). A call takes the fast path when everything the last
    full call checked is unchanged: a float32 contiguous light of the same shape, the same ``out``
    at the same address, shape and contiguity, the view's tensors at the same addresses, the
    encoding still this codec's (``_check_enc``) and its codes and the model the same tensors at
    the same versions (``encoding_state``); then only the light's and the view's values are
    checked, by the kernels as they read them (a flagged one raises naming it, as ``relight``
    does). Otherwise a full call: ``relight``'s checks of the view's structure, ``out`` and the
    kernels' buffer sizes, the cached kernel plan (``_kernel_plan``: rebuilt after an edit, a
    replaced tensor or a refit), or ``relight`` itself where it would convert the light or the
    view or not use the kernels."""

    __slots__ = ("_hot", "_fast")  # _fast: arm_rows' tuple

    def __init__(self, codec: AffineCodec, enc: Encoded, view: Any = None, n_vectors: int | None = None):
        codec._check_enc(enc)
        n_out = codec.matrix_shape_[0] if codec.matrix_shape_ else 1
        if codec.matrix_shape_ is None and view is not None:
            raise ValueError("view was given but this codec was fitted on vectors (no matrix_shape); accepted: view=None")
        codec._n_eff(n_vectors)  # refused here, not at the first light
        if codec.matrix_shape_ is not None:
            check_view(view, enc.points, n_out)  # the values too, once
        view = view_tensors(view)  # numpy arrays as tensors sharing their memory (edits in place are seen)
        super().__init__(codec, enc, tuple(view) if isinstance(view, list) else view, {"n_vectors": n_vectors})
        # the last full call's checked setting: (light shape, out, out's address and shape, the view's
        # addresses, encoding_state of the codes and model, plan, n_out, result shape, held tensors)
        self._hot: tuple | None = None
        # the render loop's form, r(light, out=buf), prepared at its first full call (arm_rows; with a view too): the
        # ctypes function, the plan's argument array, the view's addresses, a constants buffer of this relighter's own
        # and what the call checks against (see fast_rows)
        self._fast: tuple | None = None

    def _view_ptrs(self) -> tuple:
        v = self.view
        return () if v is None else ((v[0].data_ptr(), v[1].data_ptr()) if isinstance(v, tuple) else (v.data_ptr(),))

    def __call__(self, light: Any, out: torch.Tensor | None = None) -> torch.Tensor:
        f = self._fast
        if f is not None and type(light) is torch.Tensor and f[0]() is out:
            res = fast_rows(self.codec, self.enc, light, out, f, self.view)
            if res is not None:
                return res
        self._fast = None
        codec, enc, view = self.codec, self.enc, self.view
        if grad_required(light):  # the kernels are forward-only: relight's autograd path
            return codec.relight(enc, light, view, out=out, **self.kwargs)
        lib = native()
        hot = self._hot
        if (hot is not None and lib is not None and type(light) is torch.Tensor and light.dtype == torch.float32
                and light.shape == hot[0] and light.is_contiguous() and light.is_cpu and out is hot[1]
                and (out is None or (out.data_ptr() == hot[2] and out.shape == hot[3] and out.is_contiguous()
                                     and light.untyped_storage().data_ptr() != out.untyped_storage().data_ptr()))
                and self._view_ptrs() == hot[4]):
            codec._check_enc(enc)
            held = (*enc.tensors.values(), *codec._model_tensors())
            if encoding_state(enc, held) == hot[5]:
                if view is None and out is not None:  # everything run_plan checks is checked above
                    run_checked(lib, hot[6], light, light, None, None, out)
                    return out
                res, flag = run_plan(lib, hot[6], light, view, out)
                if flag:
                    check_view(view, enc.points, hot[7])  # raises with the offending value
                return res if out is not None or hot[8] is None else res.view(hot[8])
        self._hot = None
        if (lib is None or type(light) is not torch.Tensor or light.dtype != torch.float32 or light.ndim != 2 or not light.is_contiguous()
                or not light.is_cpu):
            return codec.relight(enc, light, view, out=out, **self.kwargs)
        codec._check_enc(enc)  # (a refit to another shape or cluster count)
        n_out, n_in = codec.matrix_shape_ or (1, codec.D_)
        n, C, P = codec._n_eff(self.kwargs["n_vectors"]), light.shape[1], enc.points
        J = (1 if codec.means_ is not None else 0) + n
        if codec.matrix_shape_ is not None:
            checked = check_view(view, P, n_out, values=False)  # relight's refusals of a resized or retyped view
            if (checked is not view) if not isinstance(view, tuple) else any(a is not b for a, b in zip(checked, view)):
                return codec.relight(enc, light, view, out=out, **self.kwargs)  # converted: relight converts per call
        ntap = view[0].shape[1] if isinstance(view, tuple) else 0
        if light.shape[0] != n_in or J == 0 or not kernel_fits(J, n_out, C) or ntap > 64:
            return codec.relight(enc, light, view, out=out, **self.kwargs)
        shape = (P, n_out, C) if view is None and codec.matrix_shape_ is not None else None
        if out is not None:
            check_out(out, shape or (P, C), view, light)
        vptrs = self._view_ptrs()
        kind = "rows" if view is None else ("taps" if ntap else "dense")
        pl = codec._kernel_plan(lib, enc, n, kind, C, ntap)
        res, flag = run_plan(lib, pl, light, view, out)
        if flag and view is not None:
            check_view(view, P, n_out)  # raises with the offending value
        held = (*enc.tensors.values(), *codec._model_tensors())
        self._hot = (light.shape, out, None if out is None else out.data_ptr(), None if out is None else out.shape, vptrs,
                     encoding_state(enc, held), pl, n_out, shape, held)
        if out is not None:
            self._fast = arm_rows(lib, pl, light, out, held, view)
        return res if out is not None or shape is None else res.view(shape)


def _view_parts(view: Any) -> tuple:
    """The view's tensors as a tuple: () for None, (y,) for a dense view, (idx, w) for taps."""
    return () if view is None else (tuple(view) if isinstance(view, (tuple, list)) else (view,))


def arm_rows(lib, pl, light: torch.Tensor, out: torch.Tensor, held: tuple, view: Any = None) -> tuple | None:
    """The render loop's form, ``relight(enc, light, view, out=buf)`` or ``r(light, out=buf)``,
    prepared after a full call into ``out`` that ran plan ``pl`` under ``light`` (float32,
    contiguous) and ``view`` (None for a plan of kind 'rows'; the dense view or the taps as the
    kernels read them, for 'dense' and 'taps'): everything :func:`fast_rows` would otherwise look
    up (the ctypes function, the plan's argument address, the view's addresses, a constants buffer
    ``T`` of the plan's layout owned by this entry and the thread that armed it, so no other call
    replaces it under us) and what it compares against (a weak reference to ``out``, its address,
    shape and storage, the light's shape, the point count, per held tensor — the codes and the
    model — the tensor itself, its address, shape and version: ``encoding_state``'s key without
    rebuilding it; and per view tensor the tensor, its address, shape and dtype). None where a held
    tensor tracks no version (inference mode), or the view is not what the plan's kernel reads in
    place (dense float32 ``[P, n_out]``, taps int64 and float32 ``[P, t]``, contiguous): every call
    then checks in full. Holds no reference to the encoding or ``out``, so it may live in
    ``enc.cache`` (``AffineCodec.relight``)."""
    try:
        meta = tuple((t, t.data_ptr(), t.shape, t._version) for t in held if t is not None)
    except RuntimeError:
        return None
    vts = _view_parts(view)
    want = {"rows": (), "dense": ((torch.float32, (pl.P, pl.n_out)),),
            "taps": ((torch.int64, (pl.P, pl.ntap)), (torch.float32, (pl.P, pl.ntap)))}[pl.kind]
    if len(vts) != len(want) or any(not isinstance(t, torch.Tensor) or t.dtype != dt or t.shape != sh or not t.is_contiguous()
                                    or not t.is_cpu for t, (dt, sh) in zip(vts, want)):
        return None
    vmeta = tuple((t, t.data_ptr(), t.shape, t.dtype) for t in vts)
    y = [m[1] for m in vmeta] + [None, None]
    T = torch.zeros(pl.size, dtype=torch.float32)
    return (weakref.ref(out), threading.get_ident(), lib, light.shape, out.data_ptr(), out.shape, out.untyped_storage().data_ptr(),
            pl.P, held, meta, lib.prt_relight_plan, pl.args_ptr, T, T.data_ptr(), pl, vts, vmeta, y[0], y[1])


def fast_rows(codec: AffineCodec, enc: Encoded, light: torch.Tensor, out: torch.Tensor, f: tuple, view: Any = None) -> torch.Tensor | None:
    """``relight(enc, light, view, out=out)``, as armed by :func:`arm_rows` (the caller has checked
    ``f[0]() is out`` and ``type(light) is torch.Tensor``): ``out``, or None where anything the full
    call checked changed (the caller then checks in full). Per call: the light a CPU float32
    contiguous tensor of the armed shape not in ``out``'s storage, no grad wanted (of the light,
    the view, the codes or the model); ``out`` at the same address, shape and storage, contiguous;
    the kernels still enabled; the encoding still this codec's (``_check_enc``) with the same point
    count; its codes and the model the same tensors at the same addresses, shapes and versions;
    the view the armed tensors (or None for none) at the same addresses, shapes and dtypes,
    contiguous; then the one kernel call (``prt_relight_plan``: Sloan 2003 §6's constants M_i l,
    then e_p per point and, with a view, y(v_p)·e_p or Lehtinen & Kautz 2003 eq. (13)'s taps), whose
    light check raises naming a non-finite value, as ``relight`` does, and whose view flag raises
    naming the offending view value (``check_view``). ~4-6 µs of Python (reports/benchmarks/relight_call.md)."""
    if (light.requires_grad and torch.is_grad_enabled()) or native() is not f[2] or light.dtype != torch.float32 \
            or light.shape != f[3] or not light.is_contiguous() or not light.is_cpu or out.data_ptr() != f[4] \
            or out.shape != f[5] or not out.is_contiguous() or light.untyped_storage().data_ptr() == f[6] \
            or threading.get_ident() != f[1] or enc.meta.get("points") != f[7]:
        return None
    vts = f[15]
    if vts:
        if view is None or len(parts := _view_parts(view)) != len(vts) or not all(map(operator.is_, parts, vts)):
            return None
        grad = torch.is_grad_enabled()
        for t, ptr, shape, dt in f[16]:
            if t.data_ptr() != ptr or t.shape != shape or t.dtype != dt or not t.is_contiguous() or (grad and t.requires_grad):
                return None
    elif view is not None:
        return None
    codec._check_enc(enc)
    held = (*enc.tensors.values(), *codec._model_tensors())
    if len(held) != len(f[8]) or not all(map(operator.is_, held, f[8])):
        return None
    for t, ptr, shape, v in f[9]:
        if t._version != v or t.data_ptr() != ptr or t.shape != shape or t.requires_grad:
            return None
    flag = f[10](f[11], light.data_ptr(), f[13], f[4], f[17], f[18], torch.get_num_threads())
    if flag & 16:
        light_flagged(light, light)
    if flag and vts:
        check_view(view, f[7], f[14].n_out)  # raises with the offending value; else the data overflowed (as relight)
    return out
