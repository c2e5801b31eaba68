"""Declared parameters: one vocabulary of constraints, and one ``key=value`` parser.

Every configurable object in prt_torch (codecs, transfer kinds, benchmark configs) declares its
parameters the way scikit-learn does (``sklearn/utils/_param_validation.py``): a mapping
``name -> list of constraints``, where a value is valid when *any* constraint accepts it::

    _parameter_constraints = {
        "clusters": [Interval(int, 1, None)],
        "budget": [Interval(float, 0, None), None],          # None is accepted as such
        "method": [Options("static", "iterative", "adaptive")],
        "strict": [Boolean()],
    }

:func:`validate_params` checks a dict of values against such a mapping and returns the
normalised values (ints as ``int``, reals as ``float``), raising ``ValueError`` (``TypeError``
for a wrong type) that names the object, the parameter, the value and what is accepted.
:func:`invalid_values` yields values each constraint list refuses: the invalid-parameter tests
are generated from it.

Text input (command-line overrides, ``--param NAME=VALUE``, ``--brdf-param``, light specs)
goes through :func:`parse_value` / :func:`parse_assignments` and nowhere else.
"""
from __future__ import annotations

import math
import numbers
import re
from typing import Any, Iterable

from ._checks import describe

__all__ = [
    "Interval", "Options", "Boolean", "Predicate", "Constraint",
    "check_param", "validate_params", "invalid_values", "describe_constraints",
    "parse_value", "parse_assignments", "check_kwargs",
]


class Constraint:
    """One accepted set of values: ``accepts(v)`` and a readable ``__str__``."""

    def accepts(self, value: Any) -> bool:  # pragma: no cover - interface
        raise NotImplementedError

    def normalise(self, value: Any) -> Any:
        return value

    def invalid(self) -> list[Any]:
        """A few values this constraint refuses (they may be accepted by a sibling constraint)."""
        return []


class Interval(Constraint):
    """Numbers of ``type`` (``int`` or ``float``; ``float`` also accepts ints) in an interval.

    ``closed``: 'both' (default), 'left', 'right' or 'neither'; ``None`` bounds are infinite.
    Booleans are never numbers here; floats must be finite.
    """

    def __init__(self, type: type, left: float | None, right: float | None, closed: str = "both"):
        if type not in (int, float):
            raise TypeError(f"Interval type must be int or float, got {type!r}")
        if closed not in ("both", "left", "right", "neither"):
            raise ValueError(f"closed={closed!r}; accepted: 'both', 'left', 'right', 'neither'")
        self.type, self.left, self.right, self.closed = type, left, right, closed

    def _is_type(self, v: Any) -> bool:
        if isinstance(v, bool):
            return False
        if self.type is int:
            return isinstance(v, numbers.Integral)
        return isinstance(v, numbers.Real) and math.isfinite(float(v))

    def accepts(self, v: Any) -> bool:
        if not self._is_type(v):
            return False
        lo_ok = self.left is None or (v >= self.left if self.closed in ("both", "left") else v > self.left)
        hi_ok = self.right is None or (v <= self.right if self.closed in ("both", "right") else v < self.right)
        return bool(lo_ok and hi_ok)

    def normalise(self, v: Any) -> Any:
        return int(v) if self.type is int else float(v)

    def invalid(self) -> list[Any]:
        out: list[Any] = ["1" if self.type is int else "0.5", True]
        if self.type is int:
            out.append(1.5)
        else:
            out.append(float("nan"))
        step = 1 if self.type is int else 1e-3
        if self.left is not None:
            out.append(self.left - step if self.closed in ("both", "left") else self.left)
        if self.right is not None:
            out.append(self.right + step if self.closed in ("both", "right") else self.right)
        return out

    def __str__(self) -> str:
        lb = "[" if self.closed in ("both", "left") and self.left is not None else "("
        rb = "]" if self.closed in ("both", "right") and self.right is not None else ")"
        lo = "-inf" if self.left is None else f"{self.left:g}"
        hi = "inf" if self.right is None else f"{self.right:g}"
        return f"{'an int' if self.type is int else 'a real number'} in {lb}{lo}, {hi}{rb}"


class Options(Constraint):
    """One of a fixed set of values (strings, or any hashable; compared with ==, type-exact)."""

    def __init__(self, *values: Any):
        if not values:
            raise ValueError("Options needs at least one value")
        self.values = tuple(values)

    def accepts(self, v: Any) -> bool:
        return any(type(v) is type(o) and v == o for o in self.values)

    def invalid(self) -> list[Any]:
        return ["not-an-option", 3.5]

    def __str__(self) -> str:
        return "one of " + ", ".join(repr(o) for o in self.values)


class Boolean(Constraint):
    """``True`` or ``False`` (not 0/1, not strings)."""

    def accepts(self, v: Any) -> bool:
        return isinstance(v, bool)

    def invalid(self) -> list[Any]:
        return [1, "yes"]

    def __str__(self) -> str:
        return "true or false"


class Predicate(Constraint):
    """Values for which ``test(value)`` is true (or does not raise); ``text`` says what they are,
    e.g. ``Predicate(lambda v: from_spec(v), "a BRDF or {type: MODEL, ...}")``."""

    def __init__(self, test, text: str, invalid: tuple = ("not-valid", 3.5)):
        self.test, self.text, self._invalid = test, text, list(invalid)

    def accepts(self, v: Any) -> bool:
        try:
            return self.test(v) is not False
        except (ValueError, TypeError, KeyError):
            return False

    def invalid(self) -> list[Any]:
        return self._invalid

    def __str__(self) -> str:
        return self.text


def _accepts(c: Any, v: Any) -> bool:
    return v is None if c is None else c.accepts(v)


def describe_constraints(constraints: Iterable[Any]) -> str:
    """'an int in [1, inf) or None' for a constraint list."""
    return " or ".join("None" if c is None else str(c) for c in constraints)


def check_param(name: str, value: Any, constraints: list[Any], where: str | None = None) -> Any:
    """The normalised ``value`` if any of ``constraints`` accepts it, else ValueError/TypeError
    naming ``where`` (the object), ``name``, the value and what is accepted."""
    for c in constraints:
        if _accepts(c, value):
            return None if c is None else c.normalise(value)
    prefix = f"{where}: " if where else ""
    numeric = [c for c in constraints if isinstance(c, Interval)]
    wrong_type = not any(c is not None and not isinstance(c, Interval) for c in constraints) and numeric and \
        not any(c._is_type(value) for c in numeric) and value is not None
    exc = TypeError if wrong_type else ValueError
    return _raise(exc, f"{prefix}{name}={describe(value)}; accepted: {describe_constraints(constraints)}")


def _raise(exc: type, message: str):
    raise exc(message)


def validate_params(constraints: dict[str, list[Any]], values: dict[str, Any], where: str | None = None,
                    allow_unknown: bool = False) -> dict[str, Any]:
    """Check every value against its constraint list; unknown names are refused (unless
    ``allow_unknown``). Returns the normalised values, in the order of ``values``."""
    if not allow_unknown:
        unknown = sorted(set(values) - set(constraints))
        if unknown:
            prefix = f"{where}: " if where else ""
            raise ValueError(f"{prefix}unknown parameter(s) {unknown}; accepted: {sorted(constraints)}")
    return {k: (check_param(k, v, constraints[k], where) if k in constraints else v) for k, v in values.items()}


def invalid_values(constraints: list[Any]) -> list[Any]:
    """Values refused by *every* constraint of the list (for generated invalid-parameter tests)."""
    cands: list[Any] = [object()]
    for c in constraints:
        if c is not None:
            cands += c.invalid()
    if None not in constraints:
        cands.append(None)
    out = []
    for v in cands:
        if not any(_accepts(c, v) for c in constraints) and not any(v is o for o in out):
            out.append(v)
    return out


# ----------------------------------------------------------------------------------------
# text -> values: the one key=value parser
# ----------------------------------------------------------------------------------------

def check_kwargs(fn: Any, kwargs: dict[str, Any], what: str, hidden: Iterable[str] = (),
                 shown: dict[str, str] | None = None) -> None:
    """Refuse keyword arguments ``fn`` does not take, or a required one missing, before calling it,
    naming them in the words a user typed (not Python's ``f() got an unexpected keyword argument``).
    ``what``: how the message starts (e.g. ``"light spec 'directional:foo=1'"``); ``hidden``:
    parameters filled in by the caller (left out of the list of accepted ones); ``shown``: how to
    name a parameter the user writes differently (e.g. ``{'half_angle': 'half_angle_deg'}``)."""
    import inspect

    shown = shown or {}
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):  # a builtin without a signature: let the call decide
        return
    ps = sig.parameters
    if any(p.kind is p.VAR_KEYWORD for p in ps.values()):
        return
    names = [n for n, p in ps.items() if n not in hidden and n != "self" and p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]
    accepted = ", ".join(shown.get(n, n) + (" (required)" if ps[n].default is inspect.Parameter.empty else "") for n in names)
    unknown = [k for k in kwargs if k not in ps or k in hidden]
    if unknown:
        raise ValueError(f"{what}: unknown parameter {', '.join(repr(shown.get(k, k)) for k in unknown)}; accepted: {accepted}")
    missing = [n for n in names if ps[n].default is inspect.Parameter.empty and n not in kwargs]
    if missing:
        raise ValueError(f"{what}: needs {', '.join(repr(shown.get(n, n)) for n in missing)}; accepted: {accepted}")


#: a number in exponent notation without the '.' YAML 1.1 (PyYAML) needs to read it as a float: 1e-3, 2E6, -5e+2
_EXPONENT_FLOAT = re.compile(r"[-+]?(?:\d+\.?\d*|\.\d+)[eE][-+]?\d+")


def parse_value(text: str) -> Any:
    """A value typed as text: YAML scalars and lists (``3``, ``0.5``, ``true``, ``null``,
    ``[2, 4]``, ``phong``), numbers in exponent notation ``1e-3`` (a float; YAML 1.1 reads it as text)
    and comma-separated numbers ``0.3,0.2,1`` (a list of floats)."""
    import yaml

    s = text.strip()
    try:
        v = yaml.safe_load(s) if s else None
    except yaml.YAMLError as e:
        raise ValueError(f"value {text!r} is not valid YAML ({str(e).splitlines()[0]})") from None
    if isinstance(v, str) and _EXPONENT_FLOAT.fullmatch(v):  # '1e-3': a string to YAML 1.1 (it wants '1.0e-3')
        return float(v)
    if isinstance(v, str) and "," in v and not v.startswith(("{", "[")):
        parts = [p.strip() for p in v.split(",") if p.strip()]
        try:
            return [float(p) for p in parts]
        except ValueError:
            return v
    return v


def parse_assignments(items: str | Iterable[str], what: str = "parameter", sep: str = ";") -> dict[str, Any]:
    """``'a=1;b=x'`` or ``['a=1', 'b=x']`` → ``{'a': 1, 'b': 'x'}`` (values by :func:`parse_value`).

    ``what`` names the source in errors (e.g. ``'--param'``, ``"light spec 'cap:...'"``)."""
    if isinstance(items, str):
        items = [s for s in items.split(sep)]
    out: dict[str, Any] = {}
    for it in items:
        it = it.strip()
        if not it:
            continue
        key, eq, val = it.partition("=")
        if not eq or not key.strip():
            raise ValueError(f"{what} {it!r}; accepted: key=value items (e.g. vectors=8)")
        out[key.strip()] = parse_value(val)
    return out
