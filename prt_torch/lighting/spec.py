"""One entry point for "a light", by name, file or analytic spec: :func:`load_light`.

Accepted ``spec``:

* an :class:`Environment`;
* a built-in environment name (``list_builtin_environments()``: sky, sunset, studio, overcast);
* an analytic spec string ``kind`` or ``kind:key=value;key=value`` with kind in directional, cap,
  sky_gradient, hemisphere, constant and the keys of the function of that name in
  :mod:`prt_torch.lighting.analytic` (vectors as ``x,y,z``; ``half_angle_deg`` accepted for
  caps), e.g. ``directional:direction=0,0,1;intensity=2`` or
  ``cap:direction=1,0,1;half_angle_deg=10;intensity=1,0.8,0.6``;
* a dict ``{"type": kind, **kwargs}`` of the same;
* a file path, or a '{face}' pattern / list of six paths (see :func:`load_environment`);
* a ``.json`` file holding SH coefficients in the layout ``prt light --json`` prints (and ``prt
  invert`` writes): ``coeffs`` ``[C][n²]`` (C = 1 or 3), ``bands`` n, and ``convention`` (must be
  the graphics convention with +z up); asked for fewer bands it is truncated, for more it is
  zero-padded (an SH light of n bands is exactly that).
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import torch

from ..params import check_kwargs, parse_assignments
from . import analytic
from .builtin import BUILTIN_SIZE, builtin_environment, list_builtin_environments
from .environment import Environment, expand_window, load_environment, window_factors

__all__ = ["load_light", "parse_light_spec", "analytic_params", "ANALYTIC_KINDS", "load_light_json", "SH_CONVENTION"]

SH_CONVENTION = "real SH, graphics convention (no Condon-Shortley), index l(l+1)+m, +z up"


def load_light_json(path: str | os.PathLike, bands: int | None = None) -> torch.Tensor:
    """SH light ``[C, n²]`` float64 from a JSON file in ``prt light --json``'s layout (module doc);
    ``bands`` None keeps the file's. Refused, naming the file and key: not JSON, no ``coeffs``,
    a ``coeffs`` that is not ``[C][bands²]`` finite numbers with C in (1, 3), another convention."""
    import json

    p = Path(path)
    try:
        doc = json.loads(p.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"light {str(p)!r} is not JSON ({e}); accepted: the output of prt light --json or prt invert") from None
    if not isinstance(doc, dict) or "coeffs" not in doc:
        raise ValueError(f"light {str(p)!r} has no 'coeffs'; accepted: JSON with coeffs [C][n²], bands, convention "
                         "(prt light --json's layout)")
    conv = doc.get("convention", SH_CONVENTION)
    if conv != SH_CONVENTION:
        raise ValueError(f"light {str(p)!r}: convention={conv!r}; accepted: {SH_CONVENTION!r}")
    try:
        L = torch.tensor(doc["coeffs"], dtype=torch.float64)
    except (TypeError, ValueError):
        raise ValueError(f"light {str(p)!r}: coeffs is not a [C][n²] list of numbers") from None
    n = doc.get("bands")
    if L.ndim != 2 or L.shape[0] not in (1, 3) or not isinstance(n, int) or isinstance(n, bool) or n < 1 \
            or L.shape[1] != n * n or not torch.isfinite(L).all():
        raise ValueError(f"light {str(p)!r}: coeffs of shape {list(L.shape)} with bands={n!r}; accepted: finite [C][bands²], "
                         "C = 1 or 3")
    if bands is None or bands == n:
        return L
    out = torch.zeros(L.shape[0], bands * bands, dtype=torch.float64)
    k = min(bands, n) ** 2
    out[:, :k] = L[:, :k]
    return out

ANALYTIC_KINDS = {
    "directional": analytic.directional,
    "cap": analytic.cap,
    "sky_gradient": analytic.sky_gradient,
    "hemisphere": analytic.hemisphere,
    "constant": analytic.constant,
}


def parse_light_spec(spec: str) -> dict | None:
    """'kind:key=value;...' -> {'type': kind, key: value, ...} (values by
    :func:`prt_torch.params.parse_value`: numbers, ``x,y,z`` lists); None if ``spec`` is no
    analytic kind."""
    kind, _, rest = spec.partition(":")
    if kind not in ANALYTIC_KINDS:
        return None
    out: dict = {"type": kind}
    out.update(parse_assignments(rest, what=f"light spec {spec!r}: item", sep=";"))
    for k, v in out.items():
        if k != "type" and not (isinstance(v, (int, float)) and not isinstance(v, bool)
                                or isinstance(v, list) and all(isinstance(x, (int, float)) for x in v)):
            raise ValueError(f"light spec {spec!r}: {k}={v!r}; accepted: a number or comma-separated numbers")
    return out


def analytic_params(d: dict) -> tuple[str, dict]:
    """``(kind, keyword arguments)`` of an analytic light spec ``{'type': kind, ...}``: the kind
    checked against :data:`ANALYTIC_KINDS`, ``half_angle_deg`` turned into ``half_angle`` (radians)."""
    d = dict(d)
    kind = d.pop("type", None)
    if kind not in ANALYTIC_KINDS:
        raise ValueError(f"light type {kind!r}; accepted: {sorted(ANALYTIC_KINDS)}")
    if "half_angle_deg" in d:
        d["half_angle"] = math.radians(d.pop("half_angle_deg"))
    return kind, d


def _analytic(d: dict, bands: int) -> torch.Tensor:
    kind, d = analytic_params(d)
    # its parameters in the spec's words (half_angle_deg, not the radians the function takes)
    check_kwargs(ANALYTIC_KINDS[kind], d, f"light {kind!r}", hidden=("bands",), shown={"half_angle": "half_angle_deg"})
    try:
        return ANALYTIC_KINDS[kind](bands=bands, **d)
    except TypeError as e:  # a value of the wrong type (a list for a number)
        raise ValueError(f"light {kind!r}: {e}") from None


def check_light_path(spec: Any) -> None:
    """Raise one clear FileNotFoundError when ``spec`` (a str or path, after the built-in names and analytic specs
    were tried) names no existing file: the value and every accepted form (a '{face}' pattern is checked by the
    loader, face by face)."""
    if isinstance(spec, (str, os.PathLike)) and "{face}" not in str(spec) and not Path(spec).exists():
        raise FileNotFoundError(
            f"light {str(spec)!r} is neither an existing file, a built-in environment "
            f"({', '.join(list_builtin_environments())}) nor an analytic spec ({', '.join(ANALYTIC_KINDS)}, "
            "e.g. 'directional:direction=0,0,1;intensity=1')")


def load_light(spec: Any, bands: int = 3, window: Any = None, size: int = BUILTIN_SIZE, **load_kw) -> torch.Tensor:
    """SH lighting vector ``[C, n²]`` float64 for ``spec`` (see module doc).

    ``window`` is applied to every kind (off by default); ``size`` is the resolution of a
    built-in environment; ``load_kw`` (layout, rotation, up, clamp) go to :func:`load_environment`
    for files (``rotation`` also rotates built-ins)."""
    if isinstance(spec, Environment):
        return spec.project(bands, window)
    if isinstance(spec, dict):
        L = _analytic(spec, bands)
    elif isinstance(spec, str) and spec in list_builtin_environments():
        env = builtin_environment(spec, size=size, rotation=load_kw.get("rotation"))
        return env.project(bands, window)
    elif isinstance(spec, str) and parse_light_spec(spec) is not None:
        L = _analytic(parse_light_spec(spec), bands)
    elif isinstance(spec, (str, os.PathLike)) and str(spec).lower().endswith(".json") and Path(spec).is_file():
        L = load_light_json(spec, bands)
    elif isinstance(spec, (str, os.PathLike, list, tuple)):
        check_light_path(spec)
        return load_environment(spec, **load_kw).project(bands, window)
    else:
        raise TypeError(f"light spec of type {type(spec).__name__}; accepted: str, path, dict, Environment")
    w = window_factors(window, bands)
    return L if w is None else L * expand_window(w)
