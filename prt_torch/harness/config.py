"""Benchmark configs: YAML files (shipped ones in prt_torch/configs/), command-line overrides,
sweeps, validation.

A config is a nested mapping (see prt_torch/configs/default.yaml, documented in docs/harness.md)::

    name: default                 # run name -> reports/<name>/
    seed: 0
    scene:    {name: bumpy_sphere, size: small}      # built-in name or a mesh file path
    transfer: {type: mrt, bands: 4, samples: 256, M: 8, brdf: {type: phong, s: 12}}
    lights:   [sky, studio, {type: directional, direction: [0.3, 0.2, 1], intensity: 3}]
    views:    {count: 3, elevation: 30.0}
    metrics:  {random_lights: 64, repeats: 5, warmup: 1}
    codecs:
      - {type: pca, vectors: [2, 4, 8]}             # lists expand into a grid
      - {type: cpca, clusters: [8, 32], vectors: [2, 4]}
    render:   {enabled: true, width: 256, height: 256}
    target:   {psnr: null, codec: pca, param: vectors, lo: 1, hi: 64}

Typed objects (transfer, codec, BRDF, analytic light) are mappings whose ``type`` key names
the type; the other keys are that type's parameters, validated by its registry
(``prt_torch.transfer.get_kind``, ``prt_torch.codecs.get``, ``prt_torch.brdf.from_spec``,
``prt_torch.lighting.load_light``). A light may also be a built-in name, a file or a spec
string (``"cap:direction=0.4,-0.3,1;half_angle_deg=20"``).

Overrides (``prt bench CONFIG key.sub=value ...``) are values parsed by
:func:`prt_torch.params.parse_value` set at a dotted path; ``codecs.0.clusters=[4,8]``
addresses the first codec entry. Every key must exist in the schema or be a parameter of the
typed object it is in: an unknown key or an invalid value fails here, before any work starts.

Sweeps: inside a codec entry, a list value expands into a grid over that parameter (the
Cartesian product over all list-valued parameters). Elsewhere a list where one value is
expected expands the whole run into one grid point per value (e.g. ``transfer.bands=[3,4]``).
"""
from __future__ import annotations

import copy
import itertools
import json
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from ..params import Boolean, Interval, Options, Predicate, check_param, parse_value

__all__ = ["DEFAULTS", "load_config", "apply_override", "expand_runs", "expand_codecs", "validate", "resolve_config_path", "config_hash",
           "part_configs", "PART_KEYS"]

#: The schema: every accepted key with its default. ``None`` defaults accept any type.
DEFAULTS: dict[str, Any] = {
    "name": "default",
    "seed": 0,
    "scene": {"name": "bumpy_sphere", "size": "small", "up": "z", "albedo": None},
    "transfer": {"type": "diffuse", "bands": 4, "samples": 256},  # + any parameter of that type
    "lights": ["sky", "studio"],
    "views": {"count": 3, "elevation": 30.0, "azimuth0": 20.0},
    "metrics": {"random_lights": 64, "repeats": 5, "warmup": 1, "max_memory_gb": 16.0, "cold_pairs": 9},
    "codecs": [],
    "render": {"enabled": True, "width": 256, "height": 256},
    "target": {"psnr": None, "codec": None, "param": None, "lo": 1, "hi": 64, "hi_clusters": 256, "metric": "psnr_lights_db",
               "by": "bytes"},
    "cache_dir": "cache",
    "output_dir": "reports",
    "validation": {"enabled": False, "vertices": 24, "spp": 256},  # engine vs Mitsuba 3 (prt_torch.validate)
    "ablation": None,  # a swept key (transfer.<param> or codecs.<i>.<param>): one combined report
    "ablation_reference": None,  # the value the others are compared with (default: the last)
    "parts": [],  # further benchmarks in the same report, each on its own scene/transfer (part_configs)
    # convex objects: SHRM vs unshadowed glossy PRT, same BRDF and light (harness.convex; shipped config 'convex')
    "convex": {"enabled": False, "meshes": ["sphere", "hull:bumpy_sphere"], "size": "small", "epsilons": [0.03, 0.01],
               "map_height": 64, "light_size": 64},
    # a wavelet transfer's all-frequency trade (harness.trade): its lights cut to N Haar terms against SH at n
    # bands projected from the same visibility, each against the exact result (every term)
    "trade": {"terms": [10, 30, 100, 300, 1000, 2000], "bands": [3, 4, 5, 6, 7, 8, 9, 10], "selection": "transport"},
    # a wavelet transfer's relighter (relight.WaveletRelighter): the dense terms' arithmetic, 'auto' (int16 VNNI dot
    # products on a CPU with AVX-512 VNNI where the call allows, else float32) or 'float' (the float32 loop everywhere)
    "wavelet": {"arith": "auto"},
}

#: Keys whose value is itself a list (so a list there is not a sweep).
LIST_KEYS = {"lights", "codecs", "parts", "convex.meshes", "convex.epsilons", "trade.terms", "trade.bands"}
#: Keys whose value is a typed object: its keys are the parameters of its ``type``, validated
#: by that type's registry rather than by this schema.
FREE_KEYS = {"transfer"}
#: Keys renamed when the one ``type`` vocabulary arrived: old name -> new name.
RENAMED = {"name": "type", "kind": "type", "model": "type"}


def builtin_configs() -> list[str]:
    """Names of the configs shipped with the package (``prt_torch/configs/*.yaml``)."""
    root = resources.files("prt_torch") / "configs"
    out = [p.name[:-5] for p in root.iterdir() if p.name.endswith(".yaml")]
    for sub in (p for p in root.iterdir() if p.is_dir() and not p.name.startswith("_")):
        out += [f"{sub.name}/{p.name[:-5]}" for p in sub.iterdir() if p.name.endswith(".yaml")]
    return sorted(out)


def resolve_config_path(name_or_path: str | None) -> Path:
    """A config file path, or the name of a config shipped with the package (without .yaml)."""
    if name_or_path is None:
        name_or_path = "default"
    p = Path(name_or_path)
    if p.is_file():
        return p
    if p.is_dir():
        raise ValueError(f"config {str(name_or_path)!r} is a directory; accepted: a YAML file path or one of {builtin_configs()}")
    cand = resources.files("prt_torch") / "configs" / f"{name_or_path}.yaml"
    if cand.is_file():
        return Path(str(cand))
    raise FileNotFoundError(f"config {str(name_or_path)!r} not found; accepted: a YAML file path or one of {builtin_configs()}")


def _drop_foreign_defaults(merged: dict, given: dict) -> dict:
    """A transfer of another type than the default's keeps only the default keys its type
    declares (e.g. 'transport' has no 'bands' or 'samples'); the file's own keys all stay."""
    from ..transfer import get_kind

    try:
        declared = set(get_kind(given["type"]).constraints)
    except (ValueError, KeyError, TypeError):
        return merged  # an unknown type is refused by validation, naming it
    return {k: v for k, v in merged.items() if k == "type" or k in given or k in declared}


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
        elif key in FREE_KEYS and isinstance(v, dict):  # typed object: the defaults, then the file's keys
            out[k] = {**copy.deepcopy(base[k]), **copy.deepcopy(v)}
            if key == "transfer" and v.get("type", base[k].get("type")) != base[k].get("type"):
                out[k] = _drop_foreign_defaults(out[k], v)
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
    if overrides:  # an override may have replaced a section: check its shape, fill its defaults
        cfg = _merge(DEFAULTS, cfg)
    cfg["_source"] = str(path)
    validate(cfg)
    return cfg


def apply_override(cfg: dict, text: str) -> dict:
    """Apply ``a.b.c=value`` (value parsed as YAML) to a copy of ``cfg``."""
    if "=" not in text:
        raise ValueError(f"override {text!r} is not of the form key.path=value")
    key, val = text.split("=", 1)
    try:
        value = parse_value(val)
    except ValueError as e:
        raise ValueError(f"override {text!r}: {e}") from None
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


def _is_albedo(v: Any) -> bool:
    vals = v if isinstance(v, list) else [v]
    return len(vals) in (1, 3) and all(isinstance(x, (int, float)) and not isinstance(x, bool) and 0 <= x <= 1 for x in vals)


#: Accepted values of every scalar schema key (the prt_torch.params vocabulary, as codecs and
#: transfer kinds declare theirs). A list of accepted values at these keys is a sweep.
CONSTRAINTS: dict[str, list] = {
    "name": [Predicate(lambda v: isinstance(v, str) and v and "/" not in v, "a run name (no '/')")],
    "seed": [Interval(int, 0, None)],
    "scene.name": [Predicate(lambda v: isinstance(v, str) and v, "a built-in scene name or a mesh file path")],
    "scene.size": [Options("small", "medium", "large", "xl"), Interval(int, 12, 20_000_000)],
    "scene.up": [Options("z", "-z", "y", "-y", "x", "-x")],
    "scene.albedo": [Predicate(_is_albedo, "a reflectance in [0, 1] or [r, g, b]"), None],
    "views.count": [Interval(int, 1, 360)],
    "views.elevation": [Interval(float, -90, 90)],
    "views.azimuth0": [Interval(float, -360, 360)],
    "metrics.random_lights": [Interval(int, 1, None)],
    "metrics.repeats": [Interval(int, 1, None)],
    "metrics.warmup": [Interval(int, 0, None)],
    "metrics.cold_pairs": [Interval(int, 0, None)],
    "metrics.max_memory_gb": [Interval(float, 0, None, closed="neither")],
    "trade.selection": [Options("magnitude", "area", "transport")],
    "wavelet.arith": [Options("auto", "float")],
    "render.enabled": [Boolean()],
    "render.width": [Interval(int, 1, 8192)],
    "render.height": [Interval(int, 1, 8192)],
    "target.psnr": [Interval(float, 0, 1000, closed="neither"), None],
    "target.codec": [Predicate(lambda v: isinstance(v, str), "a codec name"), None],
    "target.param": [Predicate(lambda v: isinstance(v, str), "an integer size parameter of the codec"), None],
    "target.lo": [Interval(int, 0, None)],
    "target.hi": [Interval(int, 1, None)],
    "target.hi_clusters": [Interval(int, 1, None)],
    "target.by": [Options("bytes", "fps")],
    "target.metric": [Options("psnr_lights_db", "psnr_lights_min_db", "psnr_random_db", "psnr_random_closed_form_db")],
    "cache_dir": [Predicate(lambda v: isinstance(v, str) and v, "a directory path")],
    "output_dir": [Predicate(lambda v: isinstance(v, str) and v, "a directory path")],
    "validation.enabled": [Boolean(), Options("auto")],
    "validation.vertices": [Interval(int, 1, 10_000)],
    "validation.spp": [Interval(int, 1, 1 << 20)],
    "ablation": [Predicate(lambda v: isinstance(v, str) and v.startswith(("transfer.", "codecs.")),
                           "a swept key: transfer.<param> or codecs.<i>.<param>"), None],
    "ablation_reference": [Predicate(lambda v: isinstance(v, (str, int, float, bool)), "one of the ablation's values"), None],
    "convex.enabled": [Boolean()],
    "convex.size": [Options("small", "medium", "large")],
    "convex.map_height": [Interval(int, 4, 1024)],
    "convex.light_size": [Interval(int, 8, 1024)],
}


def _check_value(key: str, value: Any) -> None:
    """``value`` (or each value of a sweep list) against ``CONSTRAINTS[key]``."""
    cons = CONSTRAINTS[key]
    vals = value if isinstance(value, list) and not any(c is not None and c.accepts(value) for c in cons) else [value]
    for v in vals:
        try:
            check_param(key, v, cons, where="config key")
        except TypeError as e:  # a config value of the wrong type is a bad value of the config
            raise ValueError(str(e)) from None


def _renamed(entry: Any, where: str) -> None:
    """Refuse the keys the one ``type`` vocabulary replaced, saying what they are now."""
    if isinstance(entry, dict):
        for old, new in RENAMED.items():
            if old in entry:
                raise ValueError(f"config key '{where}.{old}' is now '{where}.{new}' (every typed object names its type "
                                 f"with 'type'), e.g. {{type: {entry[old]!r}, ...}}")


def transfer_types(cfg: dict) -> list[str]:
    """The transfer type(s) of a config (a list when ``transfer.type`` is swept)."""
    t = cfg["transfer"]["type"]
    return t if isinstance(t, list) else [t]


def _transfer_sweeps(cfg: dict) -> list[str]:
    """Parameters of ``transfer`` given as a list the parameter itself does not accept: sweeps."""
    from ..transfer import get_kind

    t = cfg["transfer"]
    out = []
    for k, v in t.items():
        if not isinstance(v, list):
            continue
        if k == "type":
            out.append(k)
            continue
        accepts_list = any(not isinstance(c, list) and c is not None and c.accepts(v)
                           for name in transfer_types(cfg) for c in get_kind(name).constraints.get(k, []))
        if not accepts_list:
            out.append(k)
    return out


def _no_empty_lists(node: Any, path: str) -> None:
    """A list where a sweep may stand must not be empty (a sweep of nothing runs nothing)."""
    if isinstance(node, dict):
        for k, v in node.items():
            _no_empty_lists(v, f"{path}{k}.")
    elif isinstance(node, list):
        if not node and path.rstrip(".") not in ("transfer.drop_out", "transfer.vertices", "parts"):
            raise ValueError(f"config key {path.rstrip('.')!r} is an empty list; accepted: a value, or a non-empty list (a sweep)")
        for i, v in enumerate(node):
            _no_empty_lists(v, f"{path}{i}.")


#: What a part of a benchmark may set (each replaces the parent's section, filled from DEFAULTS);
#: what it does not set (seed, lights, views, metrics, render, cache, codecs) is the parent's.
PART_KEYS = {"scene", "transfer", "codecs", "lights", "views", "metrics", "render", "validation"}


def part_configs(cfg: dict) -> list[dict]:
    """The configs of ``cfg['parts']``: further benchmarks reported with this one, each with its
    own scene and transfer (e.g. a codec family that needs another transfer kind, on a smaller
    scene). Entry: ``{name: ID, note: TEXT, <PART_KEYS>...}``; the part runs into
    ``<output_dir>/<name>/parts/<ID>/`` with the parent's seed, lights, views, metrics, cache
    and codecs unless it sets them. Raises ValueError naming the entry."""
    out = []
    seen = set()
    for i, part in enumerate(cfg.get("parts") or []):
        where = f"config key 'parts.{i}'"
        field = f"config key 'parts.{i}.{{}}'".format
        if not isinstance(part, dict):
            raise ValueError(f"{where} = {part!r}; accepted: a mapping {{name: ID, note: TEXT, {', '.join(sorted(PART_KEYS))}}}")
        name = part.get("name")
        if not isinstance(name, str) or not name or "/" in name or name in seen:
            raise ValueError(f"{field('name')} = {name!r}; accepted: a unique run name without '/'")
        seen.add(name)
        if not isinstance(part.get("note", ""), str):
            raise ValueError(f"{field('note')} = {part['note']!r}; accepted: a sentence saying what differs from the main run")
        extra = set(part) - PART_KEYS - {"name", "note"}
        if extra:
            raise ValueError(f"{where} sets {sorted(extra)}; accepted keys in a part: name, note, {', '.join(sorted(PART_KEYS))}")
        raw = {k: copy.deepcopy(cfg[k]) for k in ("seed", "lights", "views", "metrics", "render", "validation", "cache_dir", "codecs")}
        raw.update({k: copy.deepcopy(v) for k, v in part.items() if k in PART_KEYS})
        raw["name"] = name
        raw["output_dir"] = str(Path(cfg["output_dir"]) / str(cfg["name"]) / "parts")
        try:
            sub = _merge(DEFAULTS, raw)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        sub["_source"] = cfg.get("_source")
        sub["_part"] = {"of": cfg["name"], "note": part.get("note", "")}
        out.append(sub)
    return out


def validate(cfg: dict) -> None:
    """Types of schema keys; the transfer, codec and light specs through their registries; the
    scene; the parts (each validated as a config of its own). Raises ValueError naming the key,
    before any work."""
    # a wavelet transfer is relit sparse as it is (no SH codec takes it): its run may have no codecs
    wavelet = isinstance(cfg.get("transfer"), dict) and cfg["transfer"].get("type") == "wavelet"
    _no_empty_lists({k: v for k, v in cfg.items() if not k.startswith("_") and not (wavelet and k == "codecs")}, "")

    def walk(node: dict, schema: dict, path: str):
        for k, d in schema.items():
            key = f"{path}{k}"
            if k not in node:
                continue
            if isinstance(d, dict) and key not in FREE_KEYS:
                walk(node[k], d, key + ".")
            elif key not in LIST_KEYS and key not in FREE_KEYS:
                _check_value(key, node[k])

    walk(cfg, DEFAULTS, "")
    for key, hi in (("terms", None), ("bands", 32)):  # lists, not sweeps
        v = cfg.get("trade", {}).get(key)
        if v is not None and not (isinstance(v, list) and v and all(isinstance(x, int) and not isinstance(x, bool) and x >= 1
                                                                      and (hi is None or x <= hi) for x in v)):
            raise ValueError(f"config key 'trade.{key}' = {v!r}; accepted: a non-empty list of integers >= 1"
                             + (f" and <= {hi}" if hi else ""))
    _validate_ablation(cfg)
    _validate_transfer(cfg)
    _validate_lights(cfg["lights"])
    if not (wavelet and cfg["codecs"] == []):
        _validate_codecs(cfg["codecs"])
    if (cfg.get("convex") or {}).get("enabled") is True:
        from .convex import check_convex

        check_convex(cfg)
    t = cfg["target"]
    if t["lo"] > t["hi"]:
        raise ValueError(f"config key 'target': lo={t['lo']} > hi={t['hi']}; accepted: lo <= hi")
    if t.get("psnr") is not None and t.get("codec"):
        if not t.get("param"):
            raise ValueError("config key 'target': a target codec needs 'param' (its size parameter to search); "
                             "leave 'codec' empty to search every codec family of the config")
        from .. import codecs

        try:
            codecs.get(t["codec"], **{t["param"]: int(t["lo"])})
        except (ValueError, TypeError) as e:
            raise ValueError(f"config key 'target': {e}") from None
    from ..io import check_writable

    check_writable(Path(cfg["output_dir"]) / str(cfg["name"]), "config key 'output_dir'", directory=True)
    check_writable(cfg["cache_dir"], "config key 'cache_dir'", directory=True)
    from ..scene import check_scene

    scene_names = cfg["scene"]["name"] if isinstance(cfg["scene"]["name"], list) else [cfg["scene"]["name"]]
    for s in scene_names:  # the one rule for naming a mesh (NAME, NAME:SIZE or a file), scene.size the default size
        check_scene(s, size=cfg["scene"]["size"], param="config key 'scene.name' =")
    for i, sub in enumerate(part_configs(cfg)):
        try:
            validate(sub)
        except (ValueError, FileNotFoundError) as e:
            raise type(e)(f"config key 'parts.{i}' ({sub['name']}): {e}") from None


def _validate_ablation(cfg: dict) -> None:
    key = cfg.get("ablation")
    if not key:
        return
    node: Any = cfg
    try:
        for k in key.split("."):
            node = node[int(k)] if isinstance(node, list) else node[k]
    except (KeyError, IndexError, ValueError, TypeError):
        raise ValueError(f"config key 'ablation' = {key!r} names no key of this config; accepted: a key holding the "
                         "list of values to sweep, e.g. transfer.bands or codecs.0.method") from None
    if not isinstance(node, list) or len(node) < 2:
        raise ValueError(f"config key 'ablation' = {key!r}: {key} = {node!r}; accepted: a list of at least two values")
    ref = cfg.get("ablation_reference")
    if ref is not None and ref not in node:
        raise ValueError(f"config key 'ablation_reference' = {ref!r}; accepted: one of {node}")


def _validate_transfer(cfg: dict) -> None:
    from ..transfer import get_kind
    from ..transfer.auto import energy_choices
    from .evaluate import KINDS

    t = cfg["transfer"]
    if not isinstance(t, dict):
        raise ValueError(f"config key 'transfer' must be a mapping {{type: KIND, ...}}, got {t!r}")
    _renamed(t, "transfer")
    if "params" in t:
        raise ValueError("config key 'transfer.params' is gone: write the parameters of the transfer type directly under "
                         "'transfer' (e.g. transfer: {type: mrt, M: 8, brdf: {type: phong, s: 12}})")
    sweeps = set(_transfer_sweeps(cfg))
    for name in transfer_types(cfg):
        if name not in KINDS:
            raise ValueError(f"config key 'transfer.type' = {name!r}; accepted: {list(KINDS)} (the types the harness relights)")
        kind = get_kind(name)
        params = {k: v for k, v in t.items() if k != "type"}
        energy_read = False
        for combo in itertools.product(*[(params[k] if k in sweeps else [params[k]]) for k in params]):
            try:
                p = kind.validate(dict(zip(params, combo)), where=f"config key 'transfer' (type {name})")
            except (ValueError, TypeError) as e:
                raise ValueError(str(e)) from None
            energy_read = energy_read or bool(energy_choices(name, p))
        if "energy" in params and not energy_read:
            _refuse_energy(cfg, kind, params)


def _refuse_energy(cfg: dict, kind, params: dict) -> None:
    """``transfer.energy`` that no ``'auto'`` choice of the run keeps (:func:`prt_torch.transfer.auto.energy_choices`,
    over every combination of a sweep): one line naming the config file, the key, its value and what would keep it —
    the refusal ``prt precompute --energy`` gives (cli/precompute.py ``_check_energy_used``). The config's ``lights``
    have no such case: the harness relights with them whatever the transfer's parameters are."""
    from ..transfer.auto import energy_choices

    where = f"config {cfg.get('_source') or cfg.get('name')!r}: key 'transfer.energy' = {params['energy']!r} has no effect"
    names = []  # the type's parameters whose 'auto' keeps the energy
    for param in kind.constraints:
        try:
            if energy_choices(kind.name, kind.validate({param: "auto"})):
                names.append(param)
        except (ValueError, TypeError):
            pass
    if not names:
        raise ValueError(f"{where} on transfer type {kind.name!r}: no 'auto' choice of this type keeps a fraction of the "
                         "energy; accepted: no transfer.energy")
    given = [f"transfer.{n} = {params[n]!r}" for n in names if n in params]
    now = (f"with {', '.join(given)}" if given
           else f"with the default transfer.{names[0]} = {kind.defaults().get(names[0])!r}")
    raise ValueError(f"{where} {now}: no 'auto' choice in this run keeps it; accepted: "
                     f"{' / '.join(f'transfer.{n}: auto' for n in names)} with transfer.energy, or no transfer.energy")


def _validate_lights(lights: Any) -> None:
    from ..lighting import load_light

    if not isinstance(lights, list) or not lights:
        raise ValueError(f"config key 'lights' must be a non-empty list, got {lights!r}")
    from ..lighting import list_builtin_environments

    for i, spec in enumerate(lights):
        _renamed(spec, f"lights.{i}")
        if isinstance(spec, str) and ":" not in spec and spec not in list_builtin_environments() and "{face}" not in spec \
                and not Path(spec).is_file():
            raise FileNotFoundError(f"config key 'lights.{i}' = {spec!r}: not a built-in environment "
                                    f"({', '.join(list_builtin_environments())}), an analytic spec or an existing image file")
        if isinstance(spec, dict) or (isinstance(spec, str) and ":" in spec and not Path(spec).exists()):
            try:
                load_light(spec, bands=1)  # analytic: cheap; refuses bad types and parameters
            except (ValueError, TypeError, FileNotFoundError) as e:
                raise ValueError(f"config key 'lights.{i}': {e}") from None


def _validate_codecs(entries: Any) -> None:
    from .. import codecs

    if not isinstance(entries, list) or not entries:
        raise ValueError("config key 'codecs' must be a non-empty list of codec settings, e.g. [{type: pca, vectors: [4, 8]}]")
    for i, entry in enumerate(entries):
        _renamed(entry, f"codecs.{i}")
        if not isinstance(entry, dict) or "type" not in entry:
            raise ValueError(f"config key 'codecs.{i}' must be a mapping with a 'type', got {entry!r}")
        if not isinstance(entry["type"], str):
            raise ValueError(f"config key 'codecs.{i}.type' = {entry['type']!r}; accepted: one codec name "
                             f"({', '.join(codecs.available())}) — list several codecs as separate entries")
        for params in expand_codecs([entry]):
            p = dict(params)
            name = p.pop("type")
            try:
                codecs.get(name, **p)  # validates name and parameters, no work
            except (ValueError, TypeError) as e:
                raise ValueError(f"config key 'codecs.{i}': {e}") from None


def expand_codecs(entries: list[dict]) -> list[dict]:
    """Each codec entry with list-valued parameters becomes the grid of its settings (in order)."""
    out = []
    for e in entries:
        keys = [k for k, v in e.items() if isinstance(v, list) and k != "type"]
        if not keys:
            out.append(dict(e))
            continue
        for combo in itertools.product(*(e[k] for k in keys)):
            d = dict(e)
            d.update(zip(keys, combo))
            out.append(d)
    return out


def _sweep_paths(node: Any, schema: Any, path: str) -> list[str]:
    """Dotted paths of list values that expand a run into a grid (see module docstring)."""
    out = []
    if isinstance(schema, dict) and isinstance(node, dict):
        for k, d in schema.items():
            key = f"{path}{k}"
            if k not in node or key in LIST_KEYS:
                continue
            if key == "transfer":
                out += [f"transfer.{p}" for p in _transfer_sweeps(node)]
            elif isinstance(d, dict):
                out += _sweep_paths(node[k], d, key + ".")
            elif isinstance(node[k], list):
                out.append(key)
    return out


def expand_runs(cfg: dict) -> list[dict]:
    """Expand list values at scalar schema keys into one config per grid point."""
    paths = [p for p in _sweep_paths(cfg, DEFAULTS, "") if p != cfg.get("ablation")]
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
