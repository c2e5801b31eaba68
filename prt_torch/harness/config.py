"""Benchmark configs: YAML files in configs/, command-line overrides, sweeps, validation.

A config is a nested mapping (see configs/default.yaml, documented in docs/harness.md)::

    name: default                 # run name -> reports/<name>/
    seed: 0
    scene:    {name: bumpy_sphere, size: small}      # built-in name or a mesh file path
    transfer: {kind: mrt, bands: 4, samples: 256, ...}  # passed to the precompute of that kind
    lights:   [sky, studio, "directional:direction=0.3,0.2,1;intensity=3"]
    views:    {count: 3, elevation: 30.0}
    metrics:  {random_lights: 64, repeats: 5, warmup: 1, lights_for_timing: 1}
    codecs:
      - {name: pca, vectors: [2, 4, 8]}             # lists expand into a grid
      - {name: cpca, clusters: [8, 32], vectors: [2, 4]}
    render:   {enabled: true, width: 256, height: 256, best: 2}
    target:   {psnr: null, codec: pca, param: vectors, lo: 1, hi: 64}

Overrides (``prt bench CONFIG key.sub=value ...``) are YAML scalars/lists set at a dotted
path; ``codecs.0.clusters=[4,8]`` addresses the first codec entry. Every key must already exist
in the schema (or be a codec parameter, validated by the codec registry): an unknown key or
an invalid value fails here, before any work starts.

Sweeps: inside a codec entry, a list value expands into a grid over that parameter (the
Cartesian product over all list-valued parameters). Scalar schema keys elsewhere also accept
a list, which expands the whole run into one grid point per value (e.g. ``transfer.bands=[3,4]``).
"""
from __future__ import annotations

import copy
import itertools
import json
from pathlib import Path
from typing import Any

import yaml

__all__ = ["DEFAULTS", "load_config", "apply_override", "expand_runs", "expand_codecs", "validate", "resolve_config_path", "config_hash"]

#: The schema: every accepted key with its default. ``None`` defaults accept any type.
DEFAULTS: dict[str, Any] = {
    "name": "default",
    "seed": 0,
    "scene": {"name": "bumpy_sphere", "size": "small", "up": "z", "albedo": None},
    "transfer": {
        "kind": "diffuse",
        "bands": 4,
        "samples": 256,
        "bounces": 0,
        "shadows": "auto",
        "params": {},  # extra keyword arguments of the kind's precompute (BRDF, M, ...)
    },
    "lights": ["sky", "studio"],
    "views": {"count": 3, "elevation": 30.0, "azimuth0": 20.0},
    "metrics": {"random_lights": 64, "repeats": 5, "warmup": 1, "max_memory_gb": 16.0},
    "codecs": [],
    "render": {"enabled": True, "width": 256, "height": 256, "best": 2},
    "target": {"psnr": None, "codec": None, "param": None, "lo": 1, "hi": 64, "metric": "psnr_lights_db"},
    "cache_dir": "cache",
    "output_dir": "reports",
}

#: Keys whose value is itself a list (so a list there is not a sweep).
LIST_KEYS = {"lights", "codecs"}
#: Keys whose value is a free-form mapping (not validated key by key here).
FREE_KEYS = {"transfer.params"}


def resolve_config_path(name_or_path: str | None) -> Path:
    """A config file path, or the name of one in the repository's configs/ (without .yaml)."""
    root = Path(__file__).resolve().parents[2] / "configs"
    if name_or_path is None:
        name_or_path = "default"
    p = Path(name_or_path)
    if p.is_file():
        return p
    cand = root / f"{name_or_path}.yaml"
    if cand.is_file():
        return cand
    avail = sorted(q.stem for q in root.glob("*.yaml")) if root.is_dir() else []
    raise FileNotFoundError(f"config {str(name_or_path)!r} not found; accepted: a YAML file path or one of {avail}")


def _merge(base: dict, upd: dict, path: str = "") -> dict:
    out = copy.deepcopy(base)
    for k, v in upd.items():
        key = f"{path}{k}"
        if k not in base:
            raise ValueError(f"unknown config key {key!r}; accepted keys here: {sorted(base)}")
        if isinstance(base[k], dict) and key not in FREE_KEYS:
            if not isinstance(v, dict):
                raise ValueError(f"config key {key!r} must be a mapping, got {v!r}")
            out[k] = _merge(base[k], v, key + ".")
        else:
            out[k] = copy.deepcopy(v)
    return out


def load_config(name_or_path: str | None = None, overrides: list[str] | None = None) -> dict:
    """Load a config (defaults ← file ← overrides) and validate it. Raises before any work."""
    path = resolve_config_path(name_or_path)
    try:
        raw = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as e:
        raise ValueError(f"config {str(path)!r} is not valid YAML: {e}") from None
    if not isinstance(raw, dict):
        raise ValueError(f"config {str(path)!r} must be a mapping at the top level, got {type(raw).__name__}")
    cfg = _merge(DEFAULTS, raw)
    for ov in overrides or []:
        cfg = apply_override(cfg, ov)
    cfg["_source"] = str(path)
    validate(cfg)
    return cfg


def apply_override(cfg: dict, text: str) -> dict:
    """Apply ``a.b.c=value`` (value parsed as YAML) to a copy of ``cfg``."""
    if "=" not in text:
        raise ValueError(f"override {text!r} is not of the form key.path=value")
    key, val = text.split("=", 1)
    try:
        value = yaml.safe_load(val)
    except yaml.YAMLError as e:
        raise ValueError(f"override {text!r}: value is not valid YAML ({e})") from None
    parts = key.strip().split(".")
    cfg = copy.deepcopy(cfg)
    node: Any = cfg
    schema: Any = DEFAULTS
    for i, p in enumerate(parts):
        last = i == len(parts) - 1
        here = ".".join(parts[: i + 1])
        if isinstance(node, list):
            try:
                idx = int(p)
                node[idx]
            except (ValueError, IndexError):
                raise ValueError(f"override {text!r}: {here!r} is not a valid index into a list of {len(node)}") from None
            if last:
                node[idx] = value
            else:
                node = node[idx]
                schema = None
            continue
        if not isinstance(node, dict):
            raise ValueError(f"override {text!r}: {'.'.join(parts[:i])!r} is not a mapping")
        in_free = any(here.startswith(f + ".") for f in FREE_KEYS) or schema is None
        if p not in node and not in_free:
            accepted = sorted(k for k in node if not k.startswith("_"))
            raise ValueError(f"override {text!r}: unknown key {here!r}; accepted: {accepted}")
        if last:
            node[p] = value
        else:
            node = node.setdefault(p, {})
            schema = schema.get(p) if isinstance(schema, dict) else None
    return cfg


def _check_type(key: str, value: Any, default: Any) -> None:
    if default is None or value is None:
        return
    kinds = {bool: (bool,), int: (int,), float: (int, float), str: (str,)}
    want = kinds.get(type(default))
    if want is None:
        return
    vals = value if isinstance(value, list) else [value]
    for v in vals:
        if isinstance(v, bool) and type(default) is not bool:
            raise ValueError(f"config key {key!r} = {v!r}: expected {type(default).__name__}")
        if not isinstance(v, want):
            raise ValueError(f"config key {key!r} = {v!r}: expected {type(default).__name__}" + (" (or a list of them, a sweep)" if key not in LIST_KEYS else ""))


def validate(cfg: dict) -> None:
    """Types of schema keys; codec names and parameters (through the codec registry); the
    scene, light and transfer kind names. Raises ValueError naming the key."""

    def walk(node: dict, schema: dict, path: str):
        for k, d in schema.items():
            key = f"{path}{k}"
            if k not in node:
                continue
            if isinstance(d, dict) and key not in FREE_KEYS:
                walk(node[k], d, key + ".")
            elif key not in LIST_KEYS and key not in FREE_KEYS:
                _check_type(key, node[k], d)

    walk(cfg, DEFAULTS, "")
    from ..transfer import KINDS

    kinds = cfg["transfer"]["kind"] if isinstance(cfg["transfer"]["kind"], list) else [cfg["transfer"]["kind"]]
    for k in kinds:
        if k not in KINDS:
            raise ValueError(f"config key 'transfer.kind' = {k!r}; accepted: {list(KINDS)}")
    params = cfg["transfer"].get("params") or {}
    if not isinstance(params, dict):
        raise ValueError(f"config key 'transfer.params' must be a mapping, got {params!r}")
    import inspect

    from .run import _build_params, _precompute_fn

    for k in kinds:
        accepted = set(inspect.signature(_precompute_fn(k)).parameters) - {"mesh", "progress", "bands", "samples", "seed"}
        for key in params:
            if key not in accepted:
                raise ValueError(f"config key 'transfer.params.{key}' is not a parameter of the {k} precompute; accepted: {sorted(accepted)}")
    if isinstance(params.get("brdf"), dict):

        try:
            _build_params({"brdf": params["brdf"]})
        except (ValueError, TypeError) as e:
            raise ValueError(f"config key 'transfer.params.brdf': {e}") from None
    if not isinstance(cfg["lights"], list) or not cfg["lights"]:
        raise ValueError(f"config key 'lights' must be a non-empty list, got {cfg['lights']!r}")
    if not isinstance(cfg["codecs"], list) or not cfg["codecs"]:
        raise ValueError("config key 'codecs' must be a non-empty list of codec settings, e.g. [{name: pca, vectors: [4, 8]}]")
    from .. import codecs

    for i, entry in enumerate(cfg["codecs"]):
        if not isinstance(entry, dict) or "name" not in entry:
            raise ValueError(f"config key 'codecs.{i}' must be a mapping with a 'name', got {entry!r}")
        for params in expand_codecs([entry]):
            p = dict(params)
            name = p.pop("name")
            try:
                codecs.get(name, **p)  # validates name and parameters, no work
            except (ValueError, TypeError) as e:
                raise ValueError(f"config key 'codecs.{i}': {e}") from None
    t = cfg["target"]
    if t.get("psnr") is not None:
        if not t.get("codec") or not t.get("param"):
            raise ValueError("config key 'target': a psnr target needs 'codec' and 'param' (the size parameter to search)")
    from ..scene import list_builtins

    scene_names = cfg["scene"]["name"] if isinstance(cfg["scene"]["name"], list) else [cfg["scene"]["name"]]
    for s in scene_names:
        if s not in list_builtins() and not Path(str(s)).is_file():
            raise FileNotFoundError(f"config key 'scene.name' = {s!r}: not a built-in scene ({list_builtins()}) nor an existing mesh file")


def expand_codecs(entries: list[dict]) -> list[dict]:
    """Each codec entry with list-valued parameters becomes the grid of its settings (in order)."""
    out = []
    for e in entries:
        keys = [k for k, v in e.items() if isinstance(v, list) and k != "name"]
        if not keys:
            out.append(dict(e))
            continue
        for combo in itertools.product(*(e[k] for k in keys)):
            d = dict(e)
            d.update(zip(keys, combo))
            out.append(d)
    return out


def _sweep_paths(node: Any, schema: Any, path: str) -> list[str]:
    out = []
    if isinstance(schema, dict) and isinstance(node, dict):
        for k, d in schema.items():
            key = f"{path}{k}"
            if k not in node or key in LIST_KEYS or key in FREE_KEYS:
                continue
            if isinstance(d, dict):
                out += _sweep_paths(node[k], d, key + ".")
            elif isinstance(node[k], list):
                out.append(key)
    return out


def expand_runs(cfg: dict) -> list[dict]:
    """Expand list values at scalar schema keys into one config per grid point."""
    paths = _sweep_paths(cfg, DEFAULTS, "")
    if not paths:
        return [cfg]

    def get(c, p):
        for k in p.split("."):
            c = c[k]
        return c

    def put(c, p, v):
        ks = p.split(".")
        for k in ks[:-1]:
            c = c[k]
        c[ks[-1]] = v

    runs = []
    for combo in itertools.product(*(get(cfg, p) for p in paths)):
        c = copy.deepcopy(cfg)
        for p, v in zip(paths, combo):
            put(c, p, v)
        c["name"] = cfg["name"] + "-" + "-".join(f"{p.split('.')[-1]}{v}" for p, v in zip(paths, combo))
        runs.append(c)
    return runs


def config_hash(obj: Any) -> str:
    """Stable short hash of a JSON-able object (settings, transfer parameters)."""
    import hashlib

    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]
