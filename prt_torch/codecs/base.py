"""The codec interface, its parameters, the registry, and the on-disk layout.

A codec compresses a surface signal ``X [P, D]`` (Sloan 2003 §3.3: an n-dimensional signal
x_p at P surface points; D = n) and relights straight from the compressed form. A codec is a
scikit-learn estimator (``sklearn.base.BaseEstimator``): ``__init__`` only stores its keyword
parameters (``get_params``/``set_params``/``clone`` work), the accepted values are declared once
per class in ``_parameter_constraints`` (the vocabulary of :mod:`prt_torch.params`) and checked
by ``codecs.get`` and at the start of ``fit``; ``fit`` learns (fitted state in attributes ending
in ``_``) and returns the codec; ``score(X)`` is minus the mean per-point squared
reconstruction error. Then

* ``encode(X) -> Encoded``            per-point codes (weights, cluster indices, ...);
* ``decode(enc) -> [P, D] float32``    the approximation x̃_p;
* ``relight(enc, light, view=None)``  radiance from the compressed form (Sloan 2003 §6);
* ``transform(X) -> [P, F] float32``   the codes as one array (a scikit-learn transformer:
  ``inverse_transform``, ``fit_transform``, ``get_feature_names_out``; the columns per codec
  in docs/codecs.md);
* ``storage(enc) -> dict``            Sloan's float count and the actual bytes;
* ``save(path, enc)`` / ``load(path)`` the project's format (prt_torch.io, no pickle).

The interface makes no assumption that a codec is linear: ``Encoded`` is a bag of named
tensors, ``linear`` says whether relighting commutes with decoding, and ``light_kind`` says
what ``relight`` takes as a light (``'sh'``: an SH coefficient matrix ``[n_in, C]``), so a
non-linear fit such as Green 2005's per-vertex sums of spherical Gaussians (lighting from a
prefiltered environment map) fits behind the same registry.

Array types: a torch tensor in gives a tensor out, a numpy array (or any other array-like:
lists, memmaps) a numpy array, for ``transform`` and ``inverse_transform`` (the type of their
argument) and for ``decode`` and ``relight`` (the type of the data the encoding was made from,
``Encoded.array_type``). Results are float32 whatever the input's float dtype.

Registry: ``register(name)`` (a class decorator; with ``preset={...}`` it registers a small
subclass whose parameters are fixed to those values), ``get(name, **params)`` (unknown names,
unknown parameters and invalid values are refused here, before any work), ``available()``,
``describe(name)`` (defaults from ``__init__``, docs from the class's numpydoc "Parameters").
"""
from __future__ import annotations

import dataclasses
import inspect
import math
import os
import re
import warnings
import weakref
from pathlib import Path
from typing import Any

import numpy as np
import torch
from sklearn.base import BaseEstimator, TransformerMixin
from sklearn.exceptions import NotFittedError
from sklearn.utils import check_array

from .. import io
from .._checks import check_finite, check_finite_float32, check_shape, tensor_version, describe as _describe
from ..params import Options, validate_params

__all__ = [
    "Codec", "Encoded", "register", "get", "available", "describe", "load",
    "ConvergenceWarning", "ConvergenceError", "CODEC_FORMAT_VERSION",
]

#: Version of the codec file layout (docs/codecs.md). Readers accept versions <= this.
CODEC_FORMAT_VERSION = 1


class ConvergenceWarning(UserWarning):
    """An iterative fit stopped at its iteration limit before meeting its tolerance."""


class ConvergenceError(RuntimeError):
    """Raised instead of ConvergenceWarning when the codec was built with ``strict=True``."""


# ----------------------------------------------------------------------------------------
# encoded data
# ----------------------------------------------------------------------------------------

@dataclasses.dataclass
class Encoded:
    """The compressed form of a signal: per-point codes of one fitted codec.

    Attributes:
        codec: registry name of the codec that produced it.
        tensors: name -> tensor, the per-point data (e.g. ``labels [P]`` uint8/int16/int32,
            ``coeffs [P, n'] float32``); the per-cluster representatives live in the codec.
        meta: JSON-able facts (``points``, ``dim``, ``matrix_shape``, layout flags).
        array_type: ``'torch'`` or ``'numpy'``, the type of the data it was made from (``encode``
            of a tensor, or of a numpy array or other array-like; ``inverse_transform``'s codes):
            ``decode`` and ``relight`` return that type. Not saved: a loaded encoding is ``'torch'``.
    Relighting plans (tile layouts, kernel arguments; built once per encoding) are cached in
    ``cache`` and are never saved, pickled or copied.
    """

    codec: str
    tensors: dict[str, torch.Tensor]
    meta: dict[str, Any]
    cache: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False, compare=False)
    array_type: str = dataclasses.field(default="torch", compare=False)

    def __getstate__(self) -> dict:
        """Pickled and copied without ``cache``: its entries point into this process's tensors
        (``AffineCodec``'s kernel plans hold raw addresses) and are rebuilt on first use."""
        return {**self.__dict__, "cache": {}}

    @property
    def points(self) -> int:
        return int(self.meta["points"])

    @property
    def nbytes(self) -> int:
        return sum(t.numel() * t.element_size() for t in self.tensors.values())

    def __repr__(self) -> str:
        shapes = ", ".join(f"{k}={tuple(v.shape)}:{str(v.dtype).replace('torch.', '')}" for k, v in self.tensors.items())
        return f"Encoded(codec={self.codec!r}, points={self.meta.get('points')}, {shapes})"


# ----------------------------------------------------------------------------------------
# the interface
# ----------------------------------------------------------------------------------------

class Codec(TransformerMixin, BaseEstimator):
    """Base class of every codec: a scikit-learn estimator and transformer.

    Subclasses write an explicit ``__init__`` with keyword parameters that only stores each
    argument as the attribute of the same name, document the parameters in a numpydoc
    "Parameters" section of the class docstring, declare the accepted values in
    ``_parameter_constraints`` (merged with the base class's: ``{**Base._parameter_constraints,
    ...}``) and implement the hooks below.

    Shapes: ``X [P, D]`` float32/float64 tensor or numpy array (stored and decoded as float32);
    ``weights [P]`` non-negative (per-point importance, e.g. vertex area; default all 1);
    ``matrix_shape = (n_out, n_in)`` when each row is a row-major n_out×n_in matrix (glossy M_p,
    MRT A_p). ``light``: ``[n_in, C]`` (n_in = D for vectors). ``view``: None, dense
    ``[P, n_out]`` weights (e.g. y(v_p), Sloan 2003 §6) or sparse taps ``(idx int64 [P, k],
    w [P, k])`` (Lehtinen & Kautz 2003 eq. (13)). ``relight`` returns ``[P, C]`` for vectors or
    with a view, ``[P, n_out, C]`` for matrices without one.

    As a transformer (generic here, on ``encode``/``decode``): ``transform(X)`` is the codes of
    ``X`` as one float32 array ``[P, F]`` whose columns :meth:`get_feature_names_out` names,
    ``inverse_transform(Z)`` decodes such an array (``inverse_transform(transform(X))`` equals
    ``decode(encode(X))``), ``fit_transform``. A codec provides the layout with three hooks:
    ``_code_columns()`` (the column names' suffixes), ``_codes_to_array(enc)`` and
    ``_codes_from_array(Z)``. Tensors in give tensors out, numpy arrays or other array-likes
    give numpy arrays (``Encoded.array_type`` for ``decode`` and ``relight``).
    """

    #: registry name, written into saved files and ``Encoded.codec`` (set by ``register``).
    codec_name: str = ""
    #: parameter name -> list of constraints (prt_torch.params); a value is valid when any accepts it.
    _parameter_constraints: dict[str, list] = {}
    #: parameters fixed by a preset name (``register(name, cls, preset=...)``).
    _fixed_params: dict[str, Any] = {}
    #: relight(enc, l) equals relighting decode(enc) (to float32 rounding).
    linear: bool = True
    #: what ``relight`` takes as a light: 'sh' = SH coefficient matrix [n_in, C].
    light_kind: str = "sh"

    # -- parameters ------------------------------------------------------------------
    @property
    def params(self) -> dict[str, Any]:
        """The parameters checked against ``_parameter_constraints`` and normalised (ints as
        int, reals as float); raises ValueError/TypeError naming an invalid one."""
        return validate_params(self._parameter_constraints, self.get_params(deep=False), where=self.codec_name)

    def _validate(self) -> dict[str, Any]:
        """``params`` plus the cross-parameter checks of ``_check_params``; run by
        ``codecs.get`` and at the start of ``fit``."""
        p = self.params
        self._check_params(p)
        return p

    def _check_params(self, p: dict[str, Any]) -> None:
        """Cross-parameter checks on the validated ``p`` (subclasses); raise ValueError naming them."""

    def check_data_shape(self, points: int, dim: int | None = None, matrix_shape: Any = None) -> None:
        """Refuse, before any data exists, parameters that data of ``points`` rows (and, when known,
        ``dim`` columns holding ``matrix_shape`` matrices) would refuse at ``fit``: what a dry run can
        know. ``dim=None``: only the point count is checked (clusters ≤ points)."""
        p = self._validate()
        k = p.get("clusters")
        if isinstance(k, int) and not isinstance(k, bool) and k > points:
            raise ValueError(f"{self.codec_name}: clusters={k} exceeds the number of points P={points}; accepted: 1..{points}")
        check = getattr(self, "_check_data", None)
        if dim is not None and check is not None:
            check(points, dim, check_matrix_shape(matrix_shape, dim))

    def __sklearn_is_fitted__(self) -> bool:
        return bool(getattr(self, "fitted_", False))

    def __sklearn_tags__(self):
        tags = super().__sklearn_tags__()
        tags.transformer_tags.preserves_dtype = ["float32"]  # codes and decodings are float32
        return tags

    # -- the interface -------------------------------------------------------------------
    def fit(self, X, y=None, weights=None, matrix_shape=None) -> "Codec":
        """Fit on ``X [P, D]`` (``y`` is ignored: scikit-learn convention). Returns self."""
        raise NotImplementedError

    def encode(self, X) -> Encoded:
        raise NotImplementedError

    def fit_encode(self, X, weights=None, matrix_shape=None) -> Encoded:
        """``fit`` then ``encode`` the same signal (the training encoding is reused, not recomputed)."""
        return self.fit(X, weights=weights, matrix_shape=matrix_shape).encode(X)

    def decode(self, enc: Encoded) -> torch.Tensor:
        raise NotImplementedError

    # -- scikit-learn transformer ------------------------------------------------------------
    def transform(self, X) -> Any:
        """The codes of ``X [P, D]`` as one array ``[P, F]`` float32 (``encode``, then the
        codec's layout; columns named by :meth:`get_feature_names_out`, docs/codecs.md): a
        tensor for a tensor ``X``, else a numpy array. The training signal's codes come from the
        fit without recomputation."""
        Z = self._codes_to_array(self.encode(X))
        return Z if isinstance(X, torch.Tensor) else Z.numpy()

    def fit_transform(self, X, y=None, **fit_params) -> Any:
        """``fit(X, y, **fit_params)`` then ``transform(X)`` (the training encoding, reused)."""
        return self.fit(X, y, **fit_params).transform(X)

    def inverse_transform(self, Z) -> Any:
        """The reconstruction ``[P, D]`` float32 from codes ``Z [P, F]`` in ``transform``'s
        layout (``decode`` of the encoding they describe): a tensor for a tensor ``Z``, else a
        numpy array. ``inverse_transform(transform(X))`` equals ``decode(encode(X))``."""
        self._require_fitted()
        kind = array_type(Z)
        Zt = check_signal("Z", Z, min_features=0)
        F = len(self._code_columns())
        if Zt.shape[1] != F:
            raise ValueError(f"Z has {Zt.shape[1]} columns; accepted: [P, {F}], the layout of transform "
                             f"({', '.join(self.get_feature_names_out()[:4])}{', ...' if F > 4 else ''})")
        enc = self._codes_from_array(Zt if Zt.dtype == torch.float32 else Zt.to(torch.float32))
        enc.array_type = kind
        return self.decode(enc)

    def get_feature_names_out(self, input_features=None) -> np.ndarray:
        """Names of ``transform``'s columns (object array of str), the registry name as prefix:
        ``pca0, pca1, ...``; clustered codecs ``cpca_cluster, cpca0, ...``. ``input_features``
        (names of X's D columns, or None) is only checked for its length."""
        self._require_fitted()
        if input_features is not None and len(input_features) != self.n_features_in_:
            raise ValueError(f"input_features has {len(input_features)} names; accepted: n_features_in_ = {self.n_features_in_}")
        return np.asarray([f"{self.codec_name}{c}" for c in self._code_columns()], dtype=object)

    def _code_columns(self) -> list[str]:
        """Suffixes of ``transform``'s column names (after the registry name), one per column."""
        raise NotImplementedError(f"codec {self.codec_name!r} has no array layout of its codes")

    def _codes_to_array(self, enc: Encoded) -> torch.Tensor:
        """``enc``'s codes as ``[P, F]`` float32 in the layout of ``_code_columns``."""
        raise NotImplementedError(f"codec {self.codec_name!r} has no array layout of its codes")

    def _codes_from_array(self, Z: torch.Tensor) -> Encoded:
        """The encoding that ``Z [P, F]`` float32 (``_codes_to_array``'s layout) describes;
        raise ValueError naming a value the layout cannot hold."""
        raise NotImplementedError(f"codec {self.codec_name!r} has no array layout of its codes")

    def _check_features(self, X: torch.Tensor) -> None:
        """``X``'s column count against the fit's (scikit-learn's wording, then ours)."""
        if X.shape[1] != self.n_features_in_:
            raise ValueError(f"X has {X.shape[1]} features, but {type(self).__name__} is expecting {self.n_features_in_} "
                             f"features as input (X has D={X.shape[1]}; this codec was fitted with D={self.n_features_in_})")

    def relight(self, enc: Encoded, light: torch.Tensor, view: Any = None, out: torch.Tensor | None = None) -> torch.Tensor:
        """Radiance straight from the compressed form for one light; ``out``: an optional result
        tensor (float32, contiguous, the result's shape) written in place and returned, so a render
        loop does not pay for a fresh allocation per frame (:func:`check_out`)."""
        raise NotImplementedError

    def relighter(self, enc: Encoded, view: Any = None, **kwargs: Any) -> "Relighter":
        """A prepared relighting of ``enc`` with ``view`` for a render loop: ``r = codec.relighter(enc,
        view)`` once, then ``r(light, out=buf)`` per light, the same result as ``relight(enc, light,
        view, out=buf, **kwargs)``. The encoding, the view and the options are checked once here
        (the view's values again by the kernels as they read them); a codec whose relight has a
        per-call cost worth saving (``AffineCodec``) skips the rest of the per-call checks."""
        self._require_fitted()
        return typed_relighter(Relighter(self, enc, view, kwargs))

    def score(self, X, y=None) -> float:
        """Minus the mean per-point squared reconstruction error, ``-(1/P) Σ_p ||x_p − x̃_p||²``
        (unweighted, float64) of ``X`` encoded by this fitted codec: higher is better, 0 is
        lossless. ``y`` is ignored. This is what ``GridSearchCV`` maximises by default."""
        X = check_signal("X", X)
        return -self.squared_error(X, self.encode(X)) / X.shape[0]

    def relight_bytes(self, enc: Encoded, view: Any = None) -> int:
        """The bytes a relight from ``enc`` with ``view`` must read once: the memory-bandwidth
        bound's byte count (``harness.timing.io_bound_fn``, with the output's bytes written). By
        default the stored bytes (model and codes, :meth:`storage`) and the view's; a codec whose
        view selects part of the codes (the Gaussian codec's taps) counts only that part."""
        return int(self.storage(enc)["bytes_total"]) + view_nbytes(view)

    def storage(self, enc: Encoded) -> dict[str, Any]:
        """Sizes: per-tensor bytes (model and codes), totals, raw float32 size, ratios.
        Subclasses add Sloan 2003's float count ``sloan_cost_floats``."""
        self._require_fitted()
        model, _ = self._state()
        by = {f"model.{k}": _nbytes(v) for k, v in model.items()}
        by.update({f"codes.{k}": _nbytes(v) for k, v in enc.tensors.items()})
        dtypes = {f"model.{k}": str(v.dtype).replace("torch.", "") for k, v in model.items()}
        dtypes.update({f"codes.{k}": str(v.dtype).replace("torch.", "") for k, v in enc.tensors.items()})
        P, D = enc.meta["points"], enc.meta["dim"]
        total = sum(by.values())
        raw = P * D * 4
        return {
            "codec": enc.codec, "points": P, "dim": D,
            "bytes": by, "dtypes": dtypes,
            "bytes_model": sum(v for k, v in by.items() if k.startswith("model.")),
            "bytes_codes": sum(v for k, v in by.items() if k.startswith("codes.")),
            "bytes_total": total, "bytes_per_point": total / max(P, 1),
            "raw_bytes": raw, "compression_ratio": raw / total if total else math.inf,
        }

    def squared_error(self, X, enc: Encoded, weights: torch.Tensor | None = None) -> float:
        """Σ_p w_p ||x_p − x̃_p||² (Sloan 2003 Table 1's "SE", weights default 1): rows' norms in
        the signal's dtype, their squares summed in float64."""
        return squared_error_rows(_as_tensor(X), _as_tensor(self.decode(enc)), weights)

    # -- persistence -------------------------------------------------------------------
    def _state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """Fitted model as (tensors, JSON-able meta)."""
        raise NotImplementedError

    def _set_state(self, tensors: dict[str, torch.Tensor], meta: dict[str, Any]) -> None:
        raise NotImplementedError

    def save(self, path: str | os.PathLike, enc: Encoded, overwrite: bool = False, extra_meta: dict | None = None) -> Path:
        """Write the fitted codec and ``enc`` to ``path`` (io kind ``codec/<name>``), atomically.
        Layout: docs/codecs.md."""
        self._require_fitted()
        if enc.codec != self.codec_name:
            raise ValueError(f"enc was produced by codec {enc.codec!r}, not by this {self.codec_name!r}")
        model, model_meta = self._state()
        tensors = {f"model.{k}": v for k, v in model.items()}
        tensors.update({f"codes.{k}": v for k, v in enc.tensors.items()})
        meta = {
            "codec": self.codec_name, "codec_class": type(self).__name__,
            "codec_format_version": CODEC_FORMAT_VERSION,
            "params": self.params, "model": model_meta, "encoded": enc.meta,
        }
        if extra_meta:
            meta["extra"] = extra_meta
        return io.save(path, tensors, kind=f"codec/{self.codec_name}", meta=meta, overwrite=overwrite)

    @classmethod
    def load(cls, path: str | os.PathLike) -> tuple["Codec", Encoded]:
        """Load ``(codec, enc)`` from a file written by ``save`` (any registered codec)."""
        return load(path)

    # -- helpers -----------------------------------------------------------------------
    def _require_fitted(self) -> None:
        if not getattr(self, "fitted_", False):  # NotFittedError is a ValueError (and an AttributeError)
            raise NotFittedError(f"codec {self.codec_name!r} is not fitted; call fit(X) first (or load a saved codec)")

    def _warn_or_raise(self, message: str) -> None:
        if getattr(self, "strict", False):
            raise ConvergenceError(message)
        warnings.warn(message, ConvergenceWarning, stacklevel=3)


def squared_error_rows(X: torch.Tensor, Xh: torch.Tensor, weights: torch.Tensor | None = None) -> float:
    """Σ_p w_p ||x_p − x̂_p||² of ``X, Xh [P, D]`` (weights ``[P]`` or None), by blocks of rows."""
    se = 0.0
    for i in range(0, X.shape[0], 8192):  # chunks bound the float64 temporaries
        xs, hs = X[i:i + 8192], Xh[i:i + 8192]
        # float32 operands: the difference is taken in float32 (exact within a factor of 2,
        # Sterbenz; else one rounding of the difference itself), its squares summed in float64
        d = (xs - hs) if xs.dtype == hs.dtype == torch.float32 else (xs.double() - hs.double())
        # each row's norm in d's dtype (float32: relative rounding ~1e-7; a float64-cast
        # reduction runs ~20x slower), the squares summed in float64
        r = torch.linalg.vector_norm(d, dim=1).double().square()
        if weights is not None:
            r = r * weights[i:i + 8192].double()
        se += float(r.sum())
    return se


def _nbytes(t: torch.Tensor) -> int:
    return t.numel() * t.element_size()


# ----------------------------------------------------------------------------------------
# input validation shared by codecs
# ----------------------------------------------------------------------------------------

def array_type(X: Any) -> str:
    """``'torch'`` for a tensor, else ``'numpy'`` (numpy arrays and other array-likes): the type
    a codec's results take (``Encoded.array_type``)."""
    return "torch" if isinstance(X, torch.Tensor) else "numpy"


def as_array_type(t: Any, kind: str) -> Any:
    """The tensor ``t`` as ``kind`` (``array_type``): itself, or a numpy view of it (no copy)."""
    return t.numpy() if kind == "numpy" and isinstance(t, torch.Tensor) else t


def typed(enc: Encoded, kind: str) -> Encoded:
    """``enc`` if its ``array_type`` is ``kind``, else a copy that shares its tensors, meta and
    cache (so relighting plans built for one serve both) with ``array_type = kind``."""
    return enc if enc.array_type == kind else dataclasses.replace(enc, array_type=kind)


def input_ref(X: Any):
    """A weak reference to ``X`` (what a codec keeps of its training signal, to know it again),
    or for an object that takes none (a list: converted afresh at every call, so never the same
    data again) a reference that is always dead."""
    try:
        return weakref.ref(X)
    except TypeError:
        return lambda: None


def _as_tensor(X: Any, name: str = "X", min_features: int = 1) -> Any:
    """numpy arrays and other array-likes (lists, memmaps; scikit-learn's ``check_array``: 2-D,
    dense, real, numeric; its messages for sparse, complex or 1-D input) become tensors, sharing
    memory where they can: float32 stays float32, other dtypes become float64. Tensors and
    None pass unchanged; the values are checked by the caller."""
    if isinstance(X, torch.Tensor) or X is None:
        return X
    X = check_array(X, accept_sparse=False, dtype=[np.float64, np.float32], order="C", ensure_all_finite=False,
                    ensure_min_samples=0, ensure_min_features=min_features, input_name=name)
    if not X.flags.writeable:  # read-only (a memmap): shared, never written (torch warns that it could be)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            return torch.from_numpy(X)
    return torch.from_numpy(X)


def check_signal(name: str, X: Any, min_features: int = 1) -> torch.Tensor:
    """``X`` must be a finite float tensor, numpy array or array-like [P, D] with P >= 1 and D >=
    ``min_features``; returned as a tensor (a numpy array's memory shared)."""
    X = _as_tensor(X, name, min_features)
    if not isinstance(X, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor or numpy array [P, D], got {_describe(X)}")
    check_shape(name, X, ndim=2)
    if X.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} has dtype {X.dtype}; accepted: torch.float32 or torch.float64")
    if X.shape[0] < 1 or X.shape[1] < min_features:
        raise ValueError(f"{name} has shape {tuple(X.shape)}; accepted: [P, D] with P >= 1 and D >= {min_features}")
    check_finite(name, X)
    return X


def check_weights(weights: Any, P: int) -> torch.Tensor | None:
    if weights is None:
        return None
    if not isinstance(weights, torch.Tensor):
        weights = torch.as_tensor(weights)
    if weights.shape != (P,):
        raise ValueError(f"weights has shape {tuple(weights.shape)}; accepted: [P] = [{P}], one per point")
    if not weights.is_floating_point():
        weights = weights.double()
    check_finite("weights", weights)
    if bool((weights < 0).any()):
        raise ValueError(f"weights has {int((weights < 0).sum())} negative value(s); accepted: weights >= 0")
    if float(weights.sum()) <= 0:
        raise ValueError("weights sum to 0; accepted: non-negative weights with a positive sum")
    return weights


def check_matrix_shape(matrix_shape: Any, D: int) -> tuple[int, int] | None:
    if matrix_shape is None:
        return None
    try:
        n_out, n_in = (int(v) for v in matrix_shape)
    except (TypeError, ValueError):
        raise ValueError(f"matrix_shape={_describe(matrix_shape)}; accepted: None or (n_out, n_in) with n_out*n_in = D = {D}") from None
    if n_out < 1 or n_in < 1 or n_out * n_in != D:
        raise ValueError(f"matrix_shape=({n_out}, {n_in}) does not fold D={D}; accepted: (n_out, n_in) with n_out*n_in = {D}")
    return n_out, n_in


def grad_required(*tensors: Any) -> bool:
    """Whether autograd must see a result computed from ``tensors``: grad mode is on and one of them
    (tensors only; None and arrays ignored) requires grad. The fused C kernels are forward-only, so
    a codec's ``relight`` takes its torch path then (docs/inverse.md "Differentiable relighting")."""
    return torch.is_grad_enabled() and any(isinstance(t, torch.Tensor) and t.requires_grad for t in tensors)


def check_light(light: Any, n_in: int, values: bool = True) -> torch.Tensor:
    """``light [n_in, C]`` as relighting reads it (float32): NaN/Inf refused naming the value, and
    so is a value beyond float32's range (relighting computes in float32). ``values=False``
    checks only its type and shape, for a caller whose kernel checks the float32 values
    (``relight_kernels.constants`` raises as this does)."""
    if isinstance(light, np.ndarray):
        light = torch.from_numpy(light)
    if not isinstance(light, torch.Tensor):
        raise TypeError(f"light must be a torch.Tensor or numpy array [n_in, C] = [{n_in}, C], got {_describe(light)}")
    check_cpu("light", light)
    if light.ndim != 2 or light.shape[0] != n_in:
        raise ValueError(f"light has shape {tuple(light.shape)}; accepted: [n_in, C] = [{n_in}, C] (SH coefficients on rows, colours on columns)")
    if not light.is_floating_point():
        raise TypeError(f"light has dtype {light.dtype}; accepted: a float tensor")
    L = light if light.dtype == torch.float32 else light.to(torch.float32)
    if values:
        check_finite_float32("light", light, L)
    return L


def check_view(view: Any, P: int, n_out: int, values: bool = True):
    """None, dense ``[P, n_out]`` or sparse taps ``(idx [P, k] int, w [P, k] float)``; returns the
    view as relighting reads it (float32 weights, int64 indices).

    ``values=True`` also checks the values — finite weights, tap indices in [0, n_out) — in one
    fused reduction each (a sum that is non-finite only if some weight is, then the full check
    that names it; ``aminmax`` of the indices), so the check reads the view once.
    ``values=False`` checks only types and shapes, for a caller whose kernel flags bad values
    itself and calls this again with ``values=True`` to raise the error naming them."""
    if view is None:
        return None
    if isinstance(view, (tuple, list)):
        if len(view) != 2:
            raise ValueError(f"view as a tuple must be (idx [P, k], w [P, k]); got {len(view)} items")
        idx, w = view
        if not isinstance(idx, torch.Tensor) or not isinstance(w, torch.Tensor):
            idx, w = view_tensors(view)  # numpy taps as tensors sharing their memory (tensors pay nothing here)
            if not isinstance(idx, torch.Tensor) or not isinstance(w, torch.Tensor):
                raise TypeError("view taps must be tensors or numpy arrays (idx int64 [P, k], w float [P, k])")
        check_cpu("view taps", idx, w)
        if idx.ndim != 2 or idx.shape[0] != P or w.shape != idx.shape:
            raise ValueError(f"view taps have shapes {tuple(idx.shape)}, {tuple(w.shape)}; accepted: idx [P, k], w [P, k] with P={P}")
        if idx.is_floating_point() or idx.dtype == torch.bool:
            raise TypeError(f"view tap indices have dtype {idx.dtype}; accepted: an integer dtype")
        idx = idx if idx.dtype == torch.int64 else idx.long()
        if values:
            if idx.numel():
                lo, hi = (int(x) for x in torch.aminmax(idx))
                if lo < 0 or hi >= n_out:
                    raise ValueError(f"view tap indices span [{lo}, {hi}]; accepted: [0, n_out) = [0, {n_out})")
            _check_finite_fast("view weights", w)
        return idx, (w if w.dtype == torch.float32 else w.to(torch.float32))
    if isinstance(view, np.ndarray):
        view = torch.from_numpy(view)
    if not isinstance(view, torch.Tensor):
        raise TypeError(f"view must be None, a tensor or numpy array [P, n_out] or a tuple (idx, w); got {_describe(view)}")
    check_cpu("view", view)
    if view.shape != (P, n_out):
        raise ValueError(f"view has shape {tuple(view.shape)}; accepted: [P, n_out] = [{P}, {n_out}]")
    if values:
        _check_finite_fast("view", view)
    return view if view.dtype == torch.float32 else view.to(torch.float32)


def view_tensors(view: Any) -> Any:
    """``view`` with numpy arrays as tensors sharing their memory (a tuple of taps stays a
    tuple); anything else unchanged, for ``check_view`` to judge."""
    if isinstance(view, np.ndarray):
        return torch.from_numpy(view)
    if isinstance(view, (tuple, list)):
        for t in view:  # (a loop, not any() over a generator: this runs at every relight with taps)
            if isinstance(t, np.ndarray):
                return tuple(torch.from_numpy(u) if isinstance(u, np.ndarray) else u for u in view)
    return view


def view_nbytes(view: Any) -> int:
    """Bytes of a view: None, a tensor or array, or a tuple/list of them (taps)."""
    if view is None:
        return 0
    if isinstance(view, (tuple, list)):
        return sum(view_nbytes(t) for t in view)
    if isinstance(view, torch.Tensor):
        return int(view.numel() * view.element_size())
    return int(getattr(view, "nbytes", 0))  # numpy arrays


def check_out(out: Any, shape: tuple[int, ...], *inputs: Any) -> torch.Tensor | None:
    """None, or ``out`` as ``relight`` writes into it: a contiguous float32 tensor of exactly
    ``shape`` that shares no memory with ``inputs`` (tensors or tuples of tensors the result is
    computed from, e.g. the view: writing one while reading it would corrupt the result)."""
    if out is None:
        return None
    if not isinstance(out, torch.Tensor):
        raise TypeError(f"out must be None or a float32 tensor {list(shape)}; got {_describe(out)}")
    check_cpu("out", out)
    if tuple(out.shape) != tuple(shape) or out.dtype != torch.float32 or not out.is_contiguous():
        raise ValueError(f"out has shape {tuple(out.shape)}, dtype {out.dtype}{'' if out.is_contiguous() else ', not contiguous'}; "
                         f"accepted: a contiguous float32 tensor of shape {list(shape)}")
    mine = out.untyped_storage().data_ptr()
    for t in inputs:
        for x in (t if isinstance(t, (tuple, list)) else (t,)):
            if isinstance(x, torch.Tensor) and x.numel() and x.untyped_storage().data_ptr() == mine:
                raise ValueError("out shares memory with an input of relight (the view or the light); accepted: a separate tensor")
    return out


def check_cpu(name: str, *ts: torch.Tensor) -> None:
    """Refuse tensors not in CPU memory: relighting runs on the CPU, and the compiled kernels read
    their addresses (a meta or GPU tensor's would be read as CPU memory: a crash)."""
    for t in ts:
        if not t.is_cpu:
            raise ValueError(f"{name} is on device {t.device}; accepted: a CPU tensor (relighting runs on the CPU: .cpu())")


def encoding_state(enc: Encoded, held: tuple) -> list:
    """The point count of ``enc`` and each of ``held``'s tensors' id, address, shape and version
    (None for None): what a cache derived from them is keyed by (``affine._memo``, the relighters).
    Equal states mean the same tensors, unedited, while the cache holds them (so their ids are not
    reused); the shape sees ``t.data = t[:k]``, which keeps the address and the version (a change
    of strides alone through ``.data``, e.g. a square transpose, is not seen: the kernels then read
    the same storage as before)."""
    state = [enc.meta.get("points")]
    for t in held:  # (a loop: ~1 µs here, against 2 for a generator into a tuple)
        if t is None:
            state.append(None)
            continue
        try:  # tensor_version, inline (a call per tensor is ~10% of this)
            v = t._version
        except RuntimeError:
            v = tensor_version(t)
        state += (id(t), t.data_ptr(), t.shape, v)
    return state


class Relighter:
    """``codec.relight(enc, light, view, out=out, **kwargs)`` with ``enc``, ``view`` and ``kwargs``
    bound (:meth:`Codec.relighter`): call it with a light (and an optional ``out``) per frame.
    The view may be updated in place between calls (its values are read, and checked, at each
    call); a replaced view needs a new relighter."""

    __slots__ = ("codec", "enc", "view", "kwargs")

    def __init__(self, codec: Codec, enc: Encoded, view: Any, kwargs: dict[str, Any]):
        self.codec, self.enc, self.view, self.kwargs = codec, enc, view, kwargs

    def __call__(self, light: Any, out: torch.Tensor | None = None) -> torch.Tensor:
        return self.codec.relight(self.enc, light, self.view, out=out, **self.kwargs)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({type(self.codec).__name__}, {self.enc!r}, view={type(self.view).__name__})"


class NumpyRelighter(Relighter):
    """A relighter of an encoding made from numpy data (``Encoded.array_type``): the tensor
    relighter ``inner``'s results as numpy arrays (views of the tensors, no copy); a numpy light
    is handed on as a tensor sharing its memory. With ``out``, ``out`` itself is returned."""

    __slots__ = ("inner",)

    def __init__(self, inner: Relighter):
        super().__init__(inner.codec, inner.enc, inner.view, inner.kwargs)
        self.inner = inner

    def __call__(self, light: Any, out: torch.Tensor | None = None) -> Any:
        res = self.inner(torch.from_numpy(light) if isinstance(light, np.ndarray) else light, out)
        return res if out is not None else as_array_type(res, "numpy")


def typed_relighter(r: Relighter) -> Relighter:
    """``r``, or for an encoding made from numpy data a :class:`NumpyRelighter` around it."""
    return r if r.enc.array_type == "torch" else NumpyRelighter(r)


def _check_finite_fast(name: str, t: torch.Tensor) -> None:
    """``check_finite`` at the cost of one sum: NaN/Inf anywhere make the sum non-finite; only
    then (or on a float overflow of the sum) the full check runs and names the first bad value."""
    if t.is_floating_point() and t.numel() and not math.isfinite(float(t.sum(dtype=torch.float64 if t.dtype == torch.float64 else torch.float32))):
        check_finite(name, t)


# ----------------------------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------------------------

_REGISTRY: dict[str, tuple[type, str]] = {}


class _Fixed(Options):
    """The one value a preset name fixes; refusals say which name fixes it and where to go."""

    def __init__(self, value: Any, param: str, name: str, base: type):
        super().__init__(value)
        self.param, self.name, self.base = param, name, base
        self.others = [v for c in base._parameter_constraints.get(param, []) if isinstance(c, Options)
                       for v in c.values if v != value]

    def invalid(self) -> list[Any]:
        return self.others + super().invalid()

    def __str__(self) -> str:
        v = self.values[0]
        return (f"{v!r} only (codec {self.name!r} fixes {self.param}={v!r}; "
                f"use codec {self.base.codec_name!r} to choose {self.param})")


def _preset_class(base: type, name: str, fixed: dict[str, Any], doc: str) -> type:
    """A subclass of ``base`` whose ``codec_name`` is ``name`` and whose parameters ``fixed``
    default to (and accept only) the given values, so ``clone`` keeps the name."""
    sig = inspect.signature(base.__init__)
    unknown = sorted(set(fixed) - set(sig.parameters) - {"self"})
    if unknown:
        raise ValueError(f"preset of codec {name!r} fixes unknown parameter(s) {unknown}; "
                         f"accepted: {sorted(base._parameter_constraints)}")
    base_init = base.__init__

    def __init__(self, **params):
        base_init(self, **{**fixed, **params})

    __init__.__signature__ = sig.replace(parameters=[
        p.replace(default=fixed[p.name]) if p.name in fixed else p for p in sig.parameters.values()])
    clsname = base.__name__ + "".join(str(v).title().replace("_", "") for v in fixed.values())
    cls = type(clsname, (base,), {
        "__init__": __init__, "__doc__": doc or base.__doc__, "__module__": base.__module__,
        "__qualname__": clsname, "codec_name": name, "_fixed_params": dict(fixed),
        "_parameter_constraints": {**base._parameter_constraints,
                                   **{k: [_Fixed(v, k, name, base)] for k, v in fixed.items()}},
    })
    __init__.__qualname__ = f"{clsname}.__init__"
    validate_params(cls._parameter_constraints, fixed, where=name)  # presets must themselves be valid
    return cls


def register(name: str, cls: type | None = None, *, preset: dict[str, Any] | None = None, doc: str = "",
             replace: bool = False):
    """Register codec class ``cls`` under ``name`` (usable as a decorator); returns the class.

    The class's ``codec_name`` becomes ``name`` (a class may be registered under one name).
    ``preset`` registers instead a generated subclass that fixes some parameters (e.g.
    ``'cpca_iterative'`` = ``'cpca'`` with ``method='iterative'``, class ``CPCAIterative``) and
    returns it; passing a different value for them is refused.
    """
    if not isinstance(name, str) or not name or not name.replace("_", "").isalnum():
        raise ValueError(f"codec name {name!r}; accepted: a non-empty identifier such as 'cpca'")

    def deco(c: type) -> type:
        if not (isinstance(c, type) and issubclass(c, Codec)):
            raise TypeError(f"register({name!r}) needs a Codec subclass, got {c!r}")
        if name in _REGISTRY and not replace:
            raise ValueError(f"codec name {name!r} is already registered (to {_REGISTRY[name][0].__name__}); pass replace=True")
        if preset:
            c = _preset_class(c, name, dict(preset), doc)
        elif c.__dict__.get("codec_name", name) != name:
            raise ValueError(f"class {c.__name__} is registered as {c.codec_name!r}; register a subclass "
                             f"(or a preset) under {name!r}")
        c.codec_name = name
        _REGISTRY[name] = (c, doc or " ".join(inspect.cleandoc(c.__doc__ or "").split("\n\n")[0].split()))
        return c

    return deco(cls) if cls is not None else deco


def available() -> list[str]:
    """Registered codec names, sorted."""
    return sorted(_REGISTRY)


def _lookup(name: str) -> tuple[type, str]:
    if name not in _REGISTRY:
        raise ValueError(f"unknown codec {name!r}; accepted: {available()}")
    return _REGISTRY[name]


def get(name: str, **params: Any) -> Codec:
    """A new, unfitted codec ``name`` configured with ``params``.

    Unknown names, unknown parameters and invalid values raise ValueError/TypeError naming
    them and what is accepted — before any work.
    """
    cls, _ = _lookup(name)
    validate_params(cls._parameter_constraints, params, where=name)  # unknown names before construction
    codec = cls(**params)
    codec._validate()
    return codec


def _param_docs(cls: type) -> dict[str, str]:
    """Parameter -> one-line description, from the numpydoc "Parameters" sections of ``cls``
    and its bases (the most derived class wins)."""
    out: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        doc = inspect.cleandoc(klass.__dict__.get("__doc__") or "")
        m = re.search(r"^Parameters\n-+\n(.*?)(?=^\S[^\n]*\n-+\n|\Z)", doc, re.S | re.M)
        if not m:
            continue
        for entry in re.split(r"\n(?=\S)", m.group(1).strip()):
            head, _, body = entry.partition("\n")
            for p in head.split(":")[0].split(","):
                out[p.strip()] = " ".join(body.split())
    return out


def describe(name: str) -> dict[str, Any]:
    """``{'name', 'class', 'doc', 'preset', 'params': {param: {'default', 'doc', 'fixed'}}}`` for
    ``name``: defaults from ``__init__``, docs from the class docstring's "Parameters"."""
    cls, doc = _lookup(name)
    docs = _param_docs(cls)
    sig = inspect.signature(cls.__init__)
    return {
        "name": name, "class": cls.__name__, "doc": doc, "preset": dict(cls._fixed_params),
        "params": {k: {"default": p.default, "doc": docs.get(k, ""), "fixed": k in cls._fixed_params}
                   for k, p in sig.parameters.items() if k != "self"},
    }


def check_codec_file(path: Path, meta: dict, shapes: dict[str, list[int]]) -> None:
    """Consistency of a codec file (``io.register_check('codec/')``; metadata against shapes, the
    tensors are not read): the kind against the codec named inside, the codes' rows against
    ``encoded.points``, the model's dimension against ``encoded.dim``, the cluster count of the
    model's metadata against its basis and means and the encoding's, the vectors per cluster
    against the basis. Raises ValueError naming the file and the disagreement (:func:`check_codec_values`
    is the value-level half)."""
    enc = meta.get("encoded") or {}
    P, D = enc.get("points"), enc.get("dim")
    kind, name = str(meta.get("kind", "")), meta.get("codec")
    if name is not None and kind != f"codec/{name}":
        raise ValueError(f"{str(path)!r} is labelled kind={kind} but holds codec {name!r}; accepted: a file written by "
                         "Codec.save (kind codec/<its codec>)")
    problems = []
    model = meta.get("model") or {}
    K = model.get("clusters")
    for tname in ("model.basis", "model.means", "model.n_vectors"):
        sh = shapes.get(tname)
        if isinstance(K, int) and sh and sh[0] != K:
            problems.append(f"model.clusters={K} but {tname} has {sh[0]} rows")
    if isinstance(K, int) and isinstance(enc.get("clusters"), int) and enc["clusters"] != K:
        problems.append(f"encoded.clusters={enc['clusters']} but model.clusters={K}")
    if isinstance(model.get("dim"), int) and isinstance(D, int) and model["dim"] != D:
        problems.append(f"encoded.dim={D} but model.dim={model['dim']}")
    basis = shapes.get("model.basis")
    if basis is not None and len(basis) != 3:
        problems.append(f"model.basis has shape {basis}; accepted: [clusters, vectors, dim]")
    n_max = enc.get("n_max")
    if basis is not None and len(basis) == 3 and isinstance(n_max, int) and n_max > basis[1]:
        problems.append(f"encoded.n_max={n_max} but model.basis holds {basis[1]} vectors per cluster")
    lab = shapes.get("codes.labels")
    if isinstance(P, int) and lab is not None and lab[0] != P:
        problems.append(f"encoded.points={P} but codes.labels has {lab[0]} rows")
    co = shapes.get("codes.coeffs")
    if isinstance(P, int) and co is not None and len(co) == 2 and not enc.get("packed") and co[0] != P:
        problems.append(f"encoded.points={P} but codes.coeffs has {co[0]} rows")
    for name in ("model.means", "model.basis"):
        sh = shapes.get(name)
        if isinstance(D, int) and sh is not None and sh[-1] != D:
            problems.append(f"encoded.dim={D} but {name} has {sh[-1]} columns")
    ms = enc.get("matrix_shape")
    if isinstance(D, int) and ms and ms[0] * ms[1] != D:
        problems.append(f"matrix_shape {ms} does not fold dim={D}")
    if problems:
        raise ValueError(f"{str(path)!r} is inconsistent: {'; '.join(problems)}")


io.register_check("codec/", check_codec_file)


def check_codec_values(path: Any, tensors: dict[str, torch.Tensor], meta: dict) -> None:
    """The value-level half of a codec file's consistency check, run by every command that reads
    one (:func:`load`: ``prt render --codec-file``, ``prt validate --codec-file``, ``prt bench``'s
    records; ``prt info``), after :func:`check_codec_file` (metadata against shapes), as
    ``transfer.check_transfer_values`` is for transfer files: every floating tensor finite and
    within ±``transfer.MAX_ABS_TRANSFER`` (``model.*`` ``[K, n, D]``/``[K, D]``, ``codes.coeffs``
    ``[P, n]``), cluster labels (``codes.labels [P]``, any integer dtype) within 0..clusters-1,
    vectors per cluster (``model.n_vectors [K]``) within 0..the basis's vectors. Raises ValueError
    naming the file, the tensor and what is wrong."""
    from ..transfer.base import MAX_ABS_TRANSFER

    name = str(path)
    for k, t in tensors.items():
        if not t.is_floating_point() or not t.numel():
            continue
        bad = ~torch.isfinite(t)
        if bool(bad.any()):
            i = tuple(int(v) for v in torch.nonzero(bad)[0])
            raise ValueError(f"{name!r}: {k} holds {int(bad.sum())} non-finite value(s), first at {i}; accepted: finite values "
                             "(the file is corrupt)")
        top = float(t.abs().max())
        if top > MAX_ABS_TRANSFER:
            raise ValueError(f"{name!r}: {k} reaches |{top:.3g}|, beyond ±{MAX_ABS_TRANSFER:g} (float32 products would overflow); "
                             "accepted: values of physical scale (the file is corrupt)")
    K = (meta.get("model") or {}).get("clusters")
    lab = tensors.get("codes.labels")
    if lab is not None and isinstance(K, int) and lab.numel():
        lo, hi = int(lab.min()), int(lab.max())
        if lo < 0 or hi >= K:
            raise ValueError(f"{name!r}: codes.labels name clusters {lo}..{hi}; accepted: 0..{K - 1} (model.clusters={K}; "
                             "the file is corrupt)")
    nv, basis = tensors.get("model.n_vectors"), tensors.get("model.basis")
    if nv is not None and basis is not None and basis.ndim == 3 and nv.numel():
        lo, hi = int(nv.min()), int(nv.max())
        if lo < 0 or hi > basis.shape[1]:
            raise ValueError(f"{name!r}: model.n_vectors holds {lo}..{hi}; accepted: 0..{basis.shape[1]} (the basis's vectors "
                             "per cluster; the file is corrupt)")


def check_codec_matches(source: str, codec: "Codec", enc: Encoded, meta: dict | None, *, mesh_hash: str | None,
                        points: int, dim: int, matrix_shape: tuple[int, int] | None, n_in: int, kind: str) -> None:
    """Refuse a codec file that does not belong to a transfer (one check for ``prt render`` and
    ``prt validate``): the mesh it was compressed from (``extra.mesh_hash``, when the file records
    it), the points it encodes against the transfer's vertices ``points``, the signal dimension
    against ``dim`` (= n_out·n_in), the matrix shape (``[n_out, n_in]``, None for grey diffuse
    vectors of ``n_in``). Raises ValueError starting with ``source``."""
    got = ((meta or {}).get("extra") or {}).get("mesh_hash")
    if got is not None and mesh_hash is not None and got != mesh_hash:
        raise ValueError(f"{source} was compressed from a mesh with hash {got}, but the transfer's mesh has hash {mesh_hash}: "
                         "the codec file does not belong to this transfer; accepted: prt compress output of this transfer file")
    P = int(enc.meta.get("points", -1))
    if P != points:
        raise ValueError(f"{source} encodes {P} points but the transfer has {points} vertices: the codec file does not belong "
                         "to this transfer; accepted: prt compress output of this transfer file")
    D = getattr(codec, "D_", None)
    if D != dim:
        raise ValueError(f"{source} has signal dimension {D} but the transfer's rows have {dim}: the codec file does not "
                         "belong to this transfer; accepted: prt compress output of this transfer file")
    ms = getattr(codec, "matrix_shape_", None)
    if matrix_shape is None and ms not in (None, (1, n_in)):
        raise ValueError(f"{source} was fitted on matrices {tuple(ms)} but the transfer holds vectors of {n_in}")
    if matrix_shape is not None and ms is not None and tuple(ms) != tuple(matrix_shape):
        raise ValueError(f"{source} has matrix shape {tuple(ms)} but the transfer's is {tuple(matrix_shape)}")
    if matrix_shape is not None and ms is None:
        raise ValueError(f"{source} was fitted on vectors (no matrix_shape) but the {kind} transfer holds "
                         f"{tuple(matrix_shape)} matrices; accepted: prt compress of this transfer file (it keeps the matrix shape)")


def load(path: str | os.PathLike) -> tuple[Codec, Encoded]:
    """Load ``(codec, enc)`` from a codec file (``Codec.save``); layout in docs/codecs.md."""
    tensors, meta = io.load(path, expect_kind="codec/")
    check_codec_values(path, tensors, meta)
    version = meta.get("codec_format_version")
    if not isinstance(version, int) or version > CODEC_FORMAT_VERSION:
        raise ValueError(f"{str(path)!r} has codec_format_version={version!r}; this prt_torch reads 1..{CODEC_FORMAT_VERSION}")
    name = meta.get("codec")
    if name not in _REGISTRY:
        raise ValueError(f"{str(path)!r} holds codec {name!r}, which is not registered here; accepted: {available()}")
    model = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    codes = {k[len("codes."):]: v for k, v in tensors.items() if k.startswith("codes.")}
    try:  # the parameters and the model state it records, refused naming the file (not a raw KeyError)
        codec = get(name, **(meta.get("params") or {}))
        codec._set_state(model, meta.get("model") or {})
    except KeyError as e:
        raise ValueError(f"{str(path)!r} lacks {e} of codec {name!r}; accepted: a file written by Codec.save") from None
    except (ValueError, TypeError) as e:
        raise ValueError(f"{str(path)!r}: {e}") from None
    codec.fitted_ = True
    return codec, Encoded(codec=name, tensors=codes, meta=meta.get("encoded", {}))
