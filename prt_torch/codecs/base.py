"""The codec interface, its parameter validation, the registry, and the on-disk layout.

A codec compresses a surface signal ``X [P, D]`` (Sloan 2003 §3.3: an n-dimensional signal
x_p at P surface points; D = n) and relights straight from the compressed form. In the
scikit-learn spirit a codec is configured in ``__init__`` (parameters validated there, before
any work), learns in ``fit`` (fitted state in attributes ending in ``_``) and then

* ``encode(X) -> Encoded``            per-point codes (weights, cluster indices, ...);
* ``decode(enc) -> [P, D] float32``    the approximation x̃_p;
* ``relight(enc, light, view=None)``  radiance from the compressed form (Sloan 2003 §6);
* ``storage(enc) -> dict``            Sloan's float count and the actual bytes;
* ``save(path, enc)`` / ``load(path)`` the project's format (prt_torch.io, no pickle).

The interface makes no assumption that a codec is linear: ``Encoded`` is a bag of named
tensors, ``linear`` says whether relighting commutes with decoding, and ``light_kind`` says
what ``relight`` takes as a light (``'sh'``: an SH coefficient matrix ``[n_in, C]``), so a
non-linear fit such as Green 2005's per-vertex sums of spherical Gaussians (lighting from a
prefiltered environment map) fits behind the same registry.

Registry: ``register(name)`` (a class decorator, optionally with fixed parameters — a
*preset*), ``get(name, **params)`` (unknown names, unknown parameters and invalid values are
refused here, before any work), ``available()``, ``describe(name)``.
"""
from __future__ import annotations

import dataclasses
import math
import os
import warnings
from pathlib import Path
from typing import Any, Callable

import torch

from .. import io
from .._checks import check_choice, check_finite, check_float, check_int, check_shape, describe as _describe

__all__ = [
    "Codec", "Encoded", "Param", "register", "get", "available", "describe", "load",
    "ConvergenceWarning", "ConvergenceError", "CODEC_FORMAT_VERSION",
    "p_int", "p_float", "p_choice", "p_bool",
]

#: Version of the codec file layout (docs/codecs.md). Readers accept versions <= this.
CODEC_FORMAT_VERSION = 1


class ConvergenceWarning(UserWarning):
    """An iterative fit stopped at its iteration limit before meeting its tolerance."""


class ConvergenceError(RuntimeError):
    """Raised instead of ConvergenceWarning when the codec was built with ``strict=True``."""


# ----------------------------------------------------------------------------------------
# parameters
# ----------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class Param:
    """One codec parameter: default, a checker ``(name, value) -> normalised value`` that
    raises ValueError/TypeError naming the parameter, and a one-line description."""

    default: Any
    check: Callable[[str, Any], Any]
    doc: str = ""


def p_int(lo: int | None = None, hi: int | None = None, allow_none: bool = False):
    def check(name, v):
        if v is None and allow_none:
            return None
        return check_int(name, v, lo, hi)
    return check


def p_float(lo: float | None = None, hi: float | None = None, lo_open: bool = False, allow_none: bool = False):
    def check(name, v):
        if v is None and allow_none:
            return None
        if isinstance(v, bool):
            raise TypeError(f"{name} must be a real number, got {_describe(v)}")
        return check_float(name, v, lo, hi, lo_open=lo_open)
    return check


def p_choice(*choices):
    def check(name, v):
        return check_choice(name, v, choices)
    return check


def p_bool():
    def check(name, v):
        if not isinstance(v, bool):
            raise TypeError(f"{name} must be true or false, got {_describe(v)}")
        return v
    return check


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
    Relighting plans (tile layouts, built once per encoding) are cached in ``cache`` and are
    never saved.
    """

    codec: str
    tensors: dict[str, torch.Tensor]
    meta: dict[str, Any]
    cache: dict[str, Any] = dataclasses.field(default_factory=dict, repr=False, compare=False)

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

class Codec:
    """Base class of every codec; subclasses declare ``PARAMS`` and implement the hooks.

    Shapes: ``X [P, D]`` float32/float64 (stored and decoded as float32); ``weights [P]``
    non-negative (per-point importance, e.g. vertex area; default all 1); ``matrix_shape =
    (n_out, n_in)`` when each row is a row-major n_out×n_in matrix (glossy M_p, MRT A_p).
    ``light``: ``[n_in, C]`` (n_in = D for vectors). ``view``: None, dense ``[P, n_out]``
    weights (e.g. y(v_p), Sloan 2003 §6) or sparse taps ``(idx int64 [P, k], w [P, k])``
    (Lehtinen & Kautz 2003 eq. (13)). ``relight`` returns ``[P, C]`` for vectors or with a
    view, ``[P, n_out, C]`` for matrices without one.
    """

    #: name -> Param; the full set of accepted constructor parameters.
    PARAMS: dict[str, Param] = {}
    #: relight(enc, l) equals relighting decode(enc) (to float32 rounding).
    linear: bool = True
    #: what ``relight`` takes as a light: 'sh' = SH coefficient matrix [n_in, C].
    light_kind: str = "sh"

    def __init__(self, **params: Any):
        self.codec_name = getattr(self, "codec_name", None) or type(self).__name__.lower()
        self.params = self._validate(params)
        self._check_params()
        self.fitted_ = False

    # -- parameters ------------------------------------------------------------------
    @classmethod
    def _validate(cls, params: dict[str, Any], where: str | None = None) -> dict[str, Any]:
        where = where or cls.__name__
        unknown = sorted(set(params) - set(cls.PARAMS))
        if unknown:
            raise ValueError(
                f"unknown parameter(s) {unknown} for codec {where!r}; accepted: {sorted(cls.PARAMS)}"
            )
        out = {}
        for k, spec in cls.PARAMS.items():
            v = params.get(k, spec.default)
            out[k] = spec.check(k, v) if (k in params or v is not None) else v
        return out

    def _check_params(self) -> None:
        """Cross-parameter checks (subclasses); raise ValueError naming the parameters."""

    def get_params(self) -> dict[str, Any]:
        return dict(self.params)

    def __getattr__(self, name: str) -> Any:
        params = self.__dict__.get("params")
        if params is not None and name in params:
            return params[name]
        raise AttributeError(name)

    def __repr__(self) -> str:
        ps = ", ".join(f"{k}={v!r}" for k, v in self.params.items() if v != self.PARAMS[k].default)
        return f"{self.codec_name}({ps})"

    # -- the interface -------------------------------------------------------------------
    def fit(self, X: torch.Tensor, weights: torch.Tensor | None = None, matrix_shape=None) -> "Codec":
        raise NotImplementedError

    def encode(self, X: torch.Tensor) -> Encoded:
        raise NotImplementedError

    def fit_encode(self, X: torch.Tensor, weights: torch.Tensor | None = None, matrix_shape=None) -> Encoded:
        """``fit`` then ``encode`` the same signal (the training encoding is reused, not recomputed)."""
        return self.fit(X, weights=weights, matrix_shape=matrix_shape).encode(X)

    def decode(self, enc: Encoded) -> torch.Tensor:
        raise NotImplementedError

    def relight(self, enc: Encoded, light: torch.Tensor, view: Any = None) -> torch.Tensor:
        raise NotImplementedError

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

    def squared_error(self, X: torch.Tensor, enc: Encoded, weights: torch.Tensor | None = None) -> float:
        """Σ_p w_p ||x_p − x̃_p||² in float64 (Sloan 2003 Table 1's "SE", weights default 1)."""
        Xh = self.decode(enc)
        se = 0.0
        for i in range(0, X.shape[0], 8192):  # chunks bound the float64 temporaries
            r = (X[i:i + 8192].double() - Xh[i:i + 8192].double()).square().sum(1)
            if weights is not None:
                r = r * weights[i:i + 8192].double()
            se += float(r.sum())
        return se

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
        if not self.fitted_:
            raise ValueError(f"codec {self.codec_name!r} is not fitted; call fit(X) first (or load a saved codec)")

    def _warn_or_raise(self, message: str) -> None:
        if self.params.get("strict"):
            raise ConvergenceError(message)
        warnings.warn(message, ConvergenceWarning, stacklevel=3)


def _nbytes(t: torch.Tensor) -> int:
    return t.numel() * t.element_size()


# ----------------------------------------------------------------------------------------
# input validation shared by codecs
# ----------------------------------------------------------------------------------------

def check_signal(name: str, X: Any) -> torch.Tensor:
    """``X`` must be a finite float tensor [P, D] with P, D >= 1."""
    if not isinstance(X, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor [P, D], got {_describe(X)}")
    check_shape(name, X, ndim=2)
    if X.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} has dtype {X.dtype}; accepted: torch.float32 or torch.float64")
    if X.shape[0] < 1 or X.shape[1] < 1:
        raise ValueError(f"{name} has shape {tuple(X.shape)}; accepted: [P, D] with P >= 1 and D >= 1")
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


def check_light(light: Any, n_in: int) -> torch.Tensor:
    if not isinstance(light, torch.Tensor):
        raise TypeError(f"light must be a torch.Tensor [n_in, C] = [{n_in}, C], got {_describe(light)}")
    if light.ndim != 2 or light.shape[0] != n_in:
        raise ValueError(f"light has shape {tuple(light.shape)}; accepted: [n_in, C] = [{n_in}, C] (SH coefficients on rows, colours on columns)")
    if not light.is_floating_point():
        raise TypeError(f"light has dtype {light.dtype}; accepted: a float tensor")
    check_finite("light", light)
    return light.to(torch.float32)


def check_view(view: Any, P: int, n_out: int):
    """None, dense ``[P, n_out]`` or sparse taps ``(idx [P, k] int, w [P, k] float)``."""
    if view is None:
        return None
    if isinstance(view, (tuple, list)):
        if len(view) != 2:
            raise ValueError(f"view as a tuple must be (idx [P, k], w [P, k]); got {len(view)} items")
        idx, w = view
        if not isinstance(idx, torch.Tensor) or not isinstance(w, torch.Tensor):
            raise TypeError("view taps must be tensors (idx int64 [P, k], w float [P, k])")
        if idx.ndim != 2 or idx.shape[0] != P or w.shape != idx.shape:
            raise ValueError(f"view taps have shapes {tuple(idx.shape)}, {tuple(w.shape)}; accepted: idx [P, k], w [P, k] with P={P}")
        if idx.is_floating_point() or idx.dtype == torch.bool:
            raise TypeError(f"view tap indices have dtype {idx.dtype}; accepted: an integer dtype")
        idx = idx.long()
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= n_out):
            raise ValueError(f"view tap indices span [{int(idx.min())}, {int(idx.max())}]; accepted: [0, n_out) = [0, {n_out})")
        check_finite("view weights", w)
        return idx, w.to(torch.float32)
    if not isinstance(view, torch.Tensor):
        raise TypeError(f"view must be None, a tensor [P, n_out] or a tuple (idx, w); got {_describe(view)}")
    if view.shape != (P, n_out):
        raise ValueError(f"view has shape {tuple(view.shape)}; accepted: [P, n_out] = [{P}, {n_out}]")
    check_finite("view", view)
    return view.to(torch.float32)


# ----------------------------------------------------------------------------------------
# registry
# ----------------------------------------------------------------------------------------

_REGISTRY: dict[str, tuple[type, dict[str, Any], str]] = {}


def register(name: str, cls: type | None = None, *, preset: dict[str, Any] | None = None, doc: str = "",
             replace: bool = False):
    """Register codec class ``cls`` under ``name`` (usable as a decorator).

    ``preset`` fixes some parameters for this name (e.g. ``'cpca_iterative'`` = ``'cpca'``
    with ``method='iterative'``); passing a different value for them to ``get`` is refused.
    """
    if not isinstance(name, str) or not name or not name.replace("_", "").isalnum():
        raise ValueError(f"codec name {name!r}; accepted: a non-empty identifier such as 'cpca'")

    def deco(c: type) -> type:
        if not (isinstance(c, type) and issubclass(c, Codec)):
            raise TypeError(f"register({name!r}) needs a Codec subclass, got {c!r}")
        if name in _REGISTRY and not replace:
            raise ValueError(f"codec name {name!r} is already registered (to {_REGISTRY[name][0].__name__}); pass replace=True")
        p = dict(preset or {})
        c._validate(p, where=name)  # presets must themselves be valid
        _REGISTRY[name] = (c, p, doc or (c.__doc__ or "").strip().splitlines()[0] if (doc or c.__doc__) else "")
        return c

    return deco(cls) if cls is not None else deco


def available() -> list[str]:
    """Registered codec names, sorted."""
    return sorted(_REGISTRY)


def _lookup(name: str) -> tuple[type, dict[str, Any], str]:
    if name not in _REGISTRY:
        raise ValueError(f"unknown codec {name!r}; accepted: {available()}")
    return _REGISTRY[name]


def get(name: str, **params: Any) -> Codec:
    """A new, unfitted codec ``name`` configured with ``params``.

    Unknown names, unknown parameters and invalid values raise ValueError/TypeError naming
    them and what is accepted — before any work.
    """
    cls, preset, _ = _lookup(name)
    for k, v in preset.items():
        if k in params and params[k] != v:
            raise ValueError(f"{k}={params[k]!r} conflicts with codec {name!r}, which fixes {k}={v!r}; "
                             f"use the general codec name to choose {k}")
    merged = {**params, **preset}
    try:
        cls._validate(merged, where=name)
    except (ValueError, TypeError) as e:
        raise type(e)(str(e)) from None
    obj = cls.__new__(cls)
    obj.codec_name = name
    Codec.__init__(obj, **merged)
    return obj


def describe(name: str) -> dict[str, Any]:
    """``{'name', 'class', 'doc', 'params': {param: {'default', 'doc'}}, 'preset'}`` for ``name``."""
    cls, preset, doc = _lookup(name)
    return {
        "name": name, "class": cls.__name__, "doc": doc, "preset": dict(preset),
        "params": {k: {"default": preset.get(k, p.default), "doc": p.doc, "fixed": k in preset}
                   for k, p in cls.PARAMS.items()},
    }


def load(path: str | os.PathLike) -> tuple[Codec, Encoded]:
    """Load ``(codec, enc)`` from a codec file (``Codec.save``); layout in docs/codecs.md."""
    tensors, meta = io.load(path, expect_kind="codec/")
    version = meta.get("codec_format_version")
    if not isinstance(version, int) or version > CODEC_FORMAT_VERSION:
        raise ValueError(f"{str(path)!r} has codec_format_version={version!r}; this prt_torch reads 1..{CODEC_FORMAT_VERSION}")
    name = meta.get("codec")
    if name not in _REGISTRY:
        raise ValueError(f"{str(path)!r} holds codec {name!r}, which is not registered here; accepted: {available()}")
    codec = get(name, **meta.get("params", {}))
    model = {k[len("model."):]: v for k, v in tensors.items() if k.startswith("model.")}
    codes = {k[len("codes."):]: v for k, v in tensors.items() if k.startswith("codes.")}
    codec._set_state(model, meta.get("model", {}))
    codec.fitted_ = True
    return codec, Encoded(codec=name, tensors=codes, meta=meta.get("encoded", {}))
