"""Parameter validation shared by every module.

Every check raises ``ValueError`` (or ``TypeError`` for a wrong type) with a message that
names the argument, the value it got, and what would be accepted, in the scikit-learn spirit:
parameters are validated in one place, with one wording.
"""
from __future__ import annotations

import math
from typing import Any, Iterable

import torch

__all__ = [
    "check_int",
    "check_float",
    "check_choice",
    "check_finite",
    "check_finite_float32",
    "check_shape",
    "check_unit_vectors",
    "check_float_dtype",
    "describe",
    "tensor_version",
    "tensor_state",
]


def describe(value: Any) -> str:
    """Short, readable rendering of a value for an error message."""
    if isinstance(value, torch.Tensor):
        return f"tensor(shape={tuple(value.shape)}, dtype={value.dtype})"
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def check_int(name: str, value: Any, lo: int | None = None, hi: int | None = None) -> int:
    """Return ``value`` as an int, or raise naming ``name`` and the accepted range [lo, hi]."""
    if isinstance(value, bool) or not isinstance(value, (int,)) and not (
        hasattr(value, "__index__") and not isinstance(value, float)
    ):
        raise TypeError(f"{name} must be an integer, got {describe(value)}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        rng = f"[{lo if lo is not None else '-inf'}, {hi if hi is not None else 'inf'}]"
        raise ValueError(f"{name}={v} is out of range; accepted: integers in {rng}")
    return v


def check_float(
    name: str,
    value: Any,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
    hi_open: bool = False,
) -> float:
    """Return ``value`` as a finite float within the given (open or closed) bounds."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a real number, got {describe(value)}") from None
    bad = not math.isfinite(v)
    if lo is not None:
        bad |= v <= lo if lo_open else v < lo
    if hi is not None:
        bad |= v >= hi if hi_open else v > hi
    if bad:
        left = ("(" if lo_open else "[") + (f"{lo:g}" if lo is not None else "-inf")
        right = (f"{hi:g}" if hi is not None else "inf") + (")" if hi_open else "]")
        raise ValueError(f"{name}={v!r} is out of range; accepted: finite values in {left}, {right}")
    return v


def check_choice(name: str, value: Any, choices: Iterable[Any]) -> Any:
    """Return ``value`` if it is one of ``choices``, else raise listing them."""
    choices = list(choices)
    if value not in choices:
        raise ValueError(f"{name}={describe(value)} is not accepted; choose one of {choices}")
    return value


def check_finite(name: str, t: torch.Tensor) -> torch.Tensor:
    """Raise if ``t`` holds NaN or Inf, saying how many and where the first one is."""
    if t.is_floating_point() or t.is_complex():
        if t.numel() and t.is_floating_point():
            # fast path, one read-only pass in the tensor's own dtype: a NaN or Inf makes the sum
            # non-finite; a finite sum proves every value finite (an overflowing sum of finite
            # values falls through to the exact check below)
            if math.isfinite(float(t.sum())):
                return t
        bad = ~torch.isfinite(t)
        n = int(bad.sum())
        if n:
            first = tuple(int(i) for i in torch.nonzero(bad)[0])
            raise ValueError(
                f"{name} has {n} non-finite value(s) (NaN or Inf), first at index {first}; "
                "accepted: finite values only"
            )
    return t



def check_finite_float32(name: str, t: torch.Tensor, t32: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`check_finite` of ``t`` as given, then of its float32 conversion ``t32`` (computed
    here when not given): a finite float64 value beyond float32's range (±3.4e38) is refused
    too, for a computation in float32. Returns ``t32``."""
    check_finite(name, t)
    if t32 is None:
        t32 = t if t.dtype == torch.float32 else t.to(torch.float32)
    if t32 is not t:
        check_finite(f"{name} (converted to float32: a value beyond ±3.4e38 became Inf)", t32)
    return t32

def check_shape(name: str, t: torch.Tensor, *, ndim: int | None = None, last: tuple[int, ...] | None = None) -> torch.Tensor:
    """Check the number of dimensions and/or the trailing dimensions of ``t``."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {describe(t)}")
    if ndim is not None and t.ndim != ndim:
        raise ValueError(f"{name} has shape {tuple(t.shape)}; accepted: a {ndim}-D tensor")
    if last is not None and tuple(t.shape[t.ndim - len(last):]) != tuple(last):
        want = "[..., " + ", ".join(str(d) for d in last) + "]"
        raise ValueError(f"{name} has shape {tuple(t.shape)}; accepted: shape {want}")
    return t


def check_float_dtype(name: str, t: torch.Tensor) -> torch.Tensor:
    if t.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{name} has dtype {t.dtype}; accepted: torch.float32 or torch.float64")
    return t


def check_unit_vectors(name: str, dirs: torch.Tensor, tol: float | None = None) -> torch.Tensor:
    """Check ``dirs`` is a float tensor ``[..., 3]`` of finite unit vectors.

    ``tol`` is the accepted deviation of the norm from 1; by default 1e-4 in float32 and 1e-6
    in float64. Zero-length, NaN and non-unit vectors are refused with the index of the first.
    """
    check_shape(name, dirs, last=(3,))
    check_float_dtype(name, dirs)
    check_finite(name, dirs)
    if tol is None:
        tol = 1e-4 if dirs.dtype == torch.float32 else 1e-6
    if dirs.numel():
        dev = (dirs.norm(dim=-1) - 1.0).abs()
        worst = float(dev.max())
        if worst > tol:
            idx = tuple(int(i) for i in torch.nonzero(dev == dev.max())[0])
            norm = float(dirs.norm(dim=-1)[idx]) if idx else float(dirs.norm(dim=-1))
            raise ValueError(
                f"{name} must hold unit vectors; the vector at index {idx} has norm {norm:.6g} "
                f"(tolerance {tol:g}); accepted: |d| = 1, normalise with d / d.norm(dim=-1, keepdim=True)"
            )
    return dirs


def tensor_version(t: torch.Tensor) -> Any:
    """``t._version`` (bumped by every in-place edit), for cache keys; an inference tensor
    (``torch.inference_mode``) tracks none, so it gets a new object each call: a key holding it
    never matches, and whatever it keys is recomputed every time instead of raising. (Reading
    ``_version`` and catching an inference tensor's error costs 60 ns less than asking first.)"""
    try:
        return t._version
    except RuntimeError:  # "Inference tensors do not track version counter."
        if t.is_inference():
            return object()
        raise


def tensor_state(t: torch.Tensor) -> tuple:
    """What a cache keyed on a tensor must compare: its identity, address, shape, stride, dtype
    and version (:func:`tensor_version`). ``t.data = other`` keeps the identity and the version
    but not the address (0 on the meta device) or the shape; the caller holds ``t`` with the key,
    so its id cannot be reused by another tensor while the key lives. About 0.5 µs."""
    return (id(t), t.data_ptr(), t.shape, t.stride(), t.dtype, tensor_version(t))
