"""Every transfer kind by name: its precompute function, its parameter constraints and its
command-line options (as data; the parser is built in :mod:`prt_torch.cli.precompute`).

``prt precompute``, benchmark configs (``transfer: {type: mrt, bands: 4, M: 8, ...}``) and the
harness all go through :func:`get_kind`, so a parameter is named, defaulted and validated the
same way everywhere:

    >>> from prt_torch import transfer
    >>> k = transfer.get_kind("mrt")
    >>> k.validate({"bands": 4, "M": 8, "brdf": {"type": "phong", "s": 12}})  # refused before work
    >>> tr = k.precompute(mesh, k.resolve({"bands": 4, "M": 8}), run=transfer.RunOptions())

A parameter's default is the precompute function's; a kind accepts exactly the parameters
named in its ``constraints``. Typed values (the BRDF) are given as ``{type: MODEL, ...}``.
"""
from __future__ import annotations

import dataclasses
import inspect
from typing import Any, Callable

from ..brdf import MODELS as BRDF_MODELS, from_spec as brdf_from_spec
from ..params import Boolean, Interval, Options, Predicate, describe_constraints, validate_params
from .auto import AUTO, resolve_auto
from .base import RunOptions
from .diffuse import MAX_BOUNCES, MAX_DIFFUSE_BANDS, MAX_SAMPLES, precompute_diffuse
from .glossy import MAX_GLOSSY_BANDS, precompute_glossy
from .glossy import MAX_SAMPLES as MAX_GLOSSY_SAMPLES
from .mrt import precompute_mrt
from .tents import MAX_TENTS
from .subsurface import PRESETS as SSS_PRESETS
from .subsurface import check_term_spec, material_from_spec
from .subsurface_kind import precompute_subsurface
from .transport import MAX_CUBE_RES, precompute_transport
from .wavelet import BITS, MAX_WAVELET_TERMS, SAMPLINGS, SCALES, precompute_wavelet

__all__ = ["Arg", "TransferKind", "get_kind", "kinds", "register_kind"]

_NOTSET = object()


@dataclasses.dataclass(frozen=True)
class Arg:
    """One command-line option of a kind: ``flag`` sets parameter ``param``.

    ``values``: text → value table (e.g. ``--fold-albedo yes`` → True); ``const``: a flag
    without a value that sets ``param`` to ``const``; ``spec``: the option names the ``type`` of
    a typed object, with ``--<flag>-param NAME=VALUE`` for its parameters (the BRDF).
    """

    flag: str
    param: str
    help: str
    values: dict | None = None
    const: Any = _NOTSET
    spec: bool = False

    @property
    def is_switch(self) -> bool:
        return self.const is not _NOTSET


@dataclasses.dataclass(frozen=True)
class TransferKind:
    """A transfer kind: ``precompute(mesh, **params, run=RunOptions)``, the ``constraints`` of
    its parameters (:mod:`prt_torch.params` vocabulary), its command-line ``args``, and where
    its result goes (``output``: 'file' — a Transfer — or 'directory' — streamed tables, whose
    precompute also takes the directory as its second argument)."""

    name: str
    function: Callable[..., Any]
    constraints: dict[str, list]
    args: tuple[Arg, ...]
    doc: str
    output: str = "file"

    def defaults(self) -> dict[str, Any]:
        """Default of every parameter (from the precompute function's signature)."""
        sig = inspect.signature(self.function).parameters
        return {k: sig[k].default for k in self.constraints}

    def validate(self, params: dict[str, Any], where: str | None = None) -> dict[str, Any]:
        """Check ``params`` (unknown names, types, ranges, typed objects, ``'auto'`` where a
        rule exists, ``energy`` — the fraction an ``'auto'`` choice keeps, in (0, 1]); returns
        them normalised. Raises ValueError/TypeError naming ``where`` (default: the kind)."""
        if not isinstance(params, dict):
            raise TypeError(f"{where or self.name}: parameters must be a mapping, got {type(params).__name__}")
        return validate_params({**self.constraints, "energy": _ENERGY}, params, where or f"transfer type {self.name!r}")

    def resolve(self, params: dict[str, Any], lights: list | None = None) -> tuple[dict[str, Any], dict[str, Any]]:
        """Keyword arguments for the precompute and the automatic decisions: validated, typed
        objects built (a BRDF spec becomes a BRDF), pairs as tuples, ``'auto'`` replaced by the
        value :func:`prt_torch.transfer.auto.resolve_auto` chooses from ``lights`` (SH
        ``[C, n²]`` tensors, the scene's lighting; None: a flat spectrum) and the BRDF."""
        p = self.validate(params)
        if p.get("brdf") is not None:
            p["brdf"] = brdf_from_spec(p["brdf"])
        if p.get("drop_out") is not None:
            p["drop_out"] = [tuple(d) for d in p["drop_out"]]
        max_bands = next((int(c.right) for c in self.constraints.get("bands", []) if isinstance(c, Interval)), 16)
        brdf = p.get("brdf") or (None if self.name == "diffuse" else _default_brdf())
        return resolve_auto(self.name, p, lights, brdf, max_bands)

    def precompute(self, mesh, params: dict[str, Any], run: RunOptions | None = None, out=None, lights: list | None = None):
        """Run the precompute on ``mesh`` with ``params`` (validated and resolved here, ``'auto'``
        chosen from ``lights``; the decisions land in ``meta['auto']``). 'directory' kinds write
        to ``out``; 'file' kinds return the :class:`Transfer`."""
        kw, decisions = self.resolve(params, lights)
        if self.output == "directory":
            if out is None:
                raise ValueError(f"transfer type {self.name!r} streams its tables to a directory; pass out=")
            table = self.function(mesh, out, **kw, run=run)
            if decisions and hasattr(table, "meta") and hasattr(table, "path"):  # the manifest keeps the decisions too
                from .. import io

                table.meta["auto"] = {**table.meta.get("auto", {}), **decisions}
                io.atomic_write_json(table.path / "manifest.json", table.meta)
            return table
        tr = self.function(mesh, **kw, run=run)
        if decisions:
            tr.meta["auto"] = decisions
        return tr

    def describe(self) -> dict[str, dict[str, Any]]:
        """``{param: {'default', 'accepted'}}`` for help texts and docs."""
        d = self.defaults()
        return {k: {"default": d[k], "accepted": describe_constraints(c)} for k, c in self.constraints.items()}


_KINDS: dict[str, TransferKind] = {}


def register_kind(kind: TransferKind, replace: bool = False) -> TransferKind:
    """Add ``kind`` to the registry (refused if the name is taken, unless ``replace``)."""
    if kind.name in _KINDS and not replace:
        raise ValueError(f"transfer type {kind.name!r} is already registered; pass replace=True")
    missing = set(kind.constraints) - set(inspect.signature(kind.function).parameters)
    if missing:
        raise ValueError(f"transfer type {kind.name!r}: constraints name {sorted(missing)}, which "
                         f"{kind.function.__name__} does not take")
    _KINDS[kind.name] = kind
    return kind


def kinds() -> list[str]:
    """Registered transfer kind names."""
    return list(_KINDS)


def get_kind(name: str) -> TransferKind:
    """The registered kind ``name``; unknown names are refused naming the accepted ones."""
    if name not in _KINDS:
        raise ValueError(f"transfer type {name!r} is not known; accepted: {kinds()}")
    return _KINDS[name]


# ----------------------------------------------------------------------------------------
# the kinds
# ----------------------------------------------------------------------------------------

def _is_brdf(v: Any) -> bool:
    brdf_from_spec(v)
    return True


def _is_pairs(v: Any) -> bool:
    return isinstance(v, (list, tuple)) and all(
        isinstance(d, (list, tuple)) and len(d) == 2 and all(isinstance(x, int) and not isinstance(x, bool) for x in d)
        for d in v)


def _is_index_list(v: Any) -> bool:
    import torch

    if isinstance(v, torch.Tensor):
        return v.ndim == 1 and not v.is_floating_point()
    return isinstance(v, (list, tuple)) and all(isinstance(x, int) and not isinstance(x, bool) for x in v)


def _is_directions(v: Any) -> bool:
    import torch

    t = torch.as_tensor(v, dtype=torch.float64)
    return t.ndim == 2 and t.shape[1] == 3 and bool(torch.isfinite(t).all())


_SEED = [Interval(int, 0, None)]
_AUTO = Options(AUTO)
_ENERGY = [Interval(float, 0, 1, closed="right")]


def _default_brdf():
    from ..brdf import AshikhminShirley

    return AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0)  # the glossy/MRT precompute default
_SHADOWS = [Options("auto", "always", "never")]
_BRDF = [Predicate(_is_brdf, "a BRDF model name or {type: MODEL, <param>: value} (models: "
                   + ", ".join(BRDF_MODELS) + ")"), None]
_WINDOW = [Options("hanning", "lanczos"), None]
_OPT_INT = [Interval(int, 1, None), None]
_VERTICES = [Predicate(_is_index_list, "a list of vertex indices"), None]

# options shared by several kinds (one flag each on the command line)
_SHARED_ARGS = {a.param: a for a in (
    Arg("--bands", "bands", "SH bands n of the lighting (n² coefficients)"),
    Arg("--samples", "samples", "Monte Carlo directions per vertex"),
    Arg("--bounces", "bounces", "interreflection bounces after the direct pass"),
    Arg("--seed", "seed", "direction-set seed"),
    Arg("--shadows", "shadows", "trace visibility: auto (probe self-occlusion first), always, never",
        values={"auto": "auto", "always": "always", "never": "never"}),
    Arg("--brdf", "brdf", "reflectance model (" + ", ".join(BRDF_MODELS) + "); "
        "its parameters with --brdf-param NAME=VALUE, e.g. s=32 ks=1 kd=0.2 (Phong), nu=40 nv=10 rs=0.05 (AS)", spec=True),
    Arg("--bands-out", "bands_out", "exit radiance SH bands m"),
    Arg("--window", "window", "window the exit-radiance bands against ringing",
        values={"hanning": "hanning", "lanczos": "lanczos"}),
    Arg("--window-width", "window_width", "window width in bands"),
    Arg("--estimator", "estimator", "auto (default): per vertex the control variate where at least half its directions "
        "are open, the plain sum elsewhere; control: the exact unshadowed T_p minus the sampled blocked part (exact "
        "where nothing is blocked); plain: the sum over visible rays",
        values={"auto": "auto", "control": "control", "plain": "plain"}),
    Arg("--quad-bands", "quad_bands", "BRDF double-projection quadrature size (default from the lobe's sharpness)"),
)}


def _args(*names: str) -> tuple[Arg, ...]:
    return tuple(_SHARED_ARGS[n] for n in names)


register_kind(TransferKind(
    name="diffuse", function=precompute_diffuse, doc="diffuse transfer vectors: unshadowed, shadowed, interreflected "
    "(Sloan 2002; course notes 2005)",
    constraints={
        "bands": [Interval(int, 1, MAX_DIFFUSE_BANDS), _AUTO], "samples": [Interval(int, 1, MAX_SAMPLES)],
        "bounces": [Interval(int, 0, MAX_BOUNCES)], "seed": _SEED, "sampling": [Options("qmc", "uniform", "cosine")],
        "estimator": [Options("auto", "control", "plain")], "shadows": _SHADOWS, "fold_albedo": [Boolean(), None],
        "bounce_tol": [Interval(float, 0, 1, closed="left")],
        "probe_tol": [Interval(float, 0, 1, closed="left")],
        "bounce_points": [Options("hits", "vertices")], "hit_samples": [Interval(int, 1, 1024), _AUTO],
        "hit_offset": [Interval(float, 0, 0.1)],
        "subsurface": [Predicate(lambda v: _is_sss_term(v), "{material: NAME or {sigma_a, sigma_s, eta}, scale: MM_PER_UNIT} "
                                 "(optional epsilon, fresnel, spacing)"), None],
    },
    args=_args("bands", "samples", "bounces", "seed", "shadows") + (
        Arg("--estimator", "estimator", "auto (default): per vertex the control variate where at least half its rays are "
            "open, the plain sum elsewhere (exact for open and for enclosed vertices); control: the exact unshadowed "
            "transfer minus the sampled blocked part; plain: the sum over visible rays",
            values={"auto": "auto", "control": "control", "plain": "plain"}),
        Arg("--sampling", "sampling", "direction set: a randomised Hammersley set over each vertex's hemisphere (qmc, "
            "default), one stratified sphere set for all vertices (uniform) or cosine-weighted per vertex (cosine)",
            values={"qmc": "qmc", "uniform": "uniform", "cosine": "cosine"}),
        Arg("--fold-albedo", "fold_albedo", "store [V,3,n²] with albedo folded (yes), [V,n²] without (no), or as needed (auto)",
            values={"auto": None, "yes": True, "no": False}),
        Arg("--bounce-tol", "bounce_tol", "stop adding bounces below this energy fraction"),
        Arg("--bounce-points", "bounce_points", "where a bounce takes the reflected light: at the hit point itself "
            "(hits; unbiased near sharp vertices) or interpolated from the hit face's vertices (vertices; faster)",
            values={"hits": "hits", "vertices": "vertices"}),
        Arg("--hit-samples", "hit_samples", "rays per bounce hit point (bounce_points=hits); auto (default): 4 under "
            "--estimator auto, 8 under control and plain"),
        Arg("--hit-offset", "hit_offset", "offset of the rays leaving a bounce hit point, as a fraction of the bounding-box "
            "diagonal (default 1e-6, floored at 16 float32 ulps; 1e-4 was the rule before issue 37)"),
    ),
))

_GLOSSY_COMMON = {
    "brdf": _BRDF, "window": _WINDOW, "window_width": _OPT_INT, "quad_bands": _OPT_INT,
    "samples": [Interval(int, 1, MAX_GLOSSY_SAMPLES)], "seed": _SEED,
    "shadows": [Boolean()] + _SHADOWS, "bounces": [Interval(int, 0, 16)], "vertices": _VERTICES,
    "estimator": [Options("auto", "control", "plain")],
}

register_kind(TransferKind(
    name="glossy", function=precompute_glossy, doc="glossy exit transfer M_p = B R_p T_p (Sloan 2003 §3.1) or "
    "transferred radiance T_p (Sloan 2002)",
    constraints={
        "bands": [Interval(int, 1, MAX_GLOSSY_BANDS), _AUTO], "bands_out": [Interval(int, 1, MAX_GLOSSY_BANDS), _AUTO, None],
        "exit": [Boolean()], "projection": [Options("zero", "least_squares", "odd", "even")],
        "drop_out": [Predicate(_is_pairs, "a list of (l, m) pairs"), None], "rcond": [Interval(float, 0, None), None],
        "subsurface": [Predicate(lambda v: _is_sss_term(v), "{material: NAME or {sigma_a, sigma_s, eta}, scale: MM_PER_UNIT} "
                                 "(optional epsilon, fresnel, spacing)"), None],
        **_GLOSSY_COMMON,
    },
    args=_args("bands", "bands_out", "brdf", "samples", "seed", "shadows", "bounces", "window", "window_width",
               "quad_bands", "estimator") + (
        Arg("--projection", "projection", "hemispherical SH projection of B (Sloan 2003 eq. 1)",
            values={k: k for k in ("zero", "least_squares", "odd", "even")}),
        Arg("--drop-10", "drop_out", "drop the (1,0) exit basis function: N_r = m²-1 (Sloan 2003 §6.1)", const=[[1, 0]]),
        Arg("--rcond", "rcond", "pseudo-inverse threshold of the least-squares projection beyond ~6 bands"),
        Arg("--transferred", "exit", "store the global transferred radiance T_p (Sloan 2002) instead of exit M_p",
            const=False),
    ),
))

register_kind(TransferKind(
    name="mrt", function=precompute_mrt, doc="matrix radiance transfer A_p = G⁻¹ C B R_p T_p in an M×M tent basis "
    "(Lehtinen & Kautz 2003)",
    constraints={
        "bands": [Interval(int, 1, MAX_GLOSSY_BANDS), _AUTO], "bands_out": [Interval(int, 1, MAX_GLOSSY_BANDS), _AUTO],
        "M": [Interval(int, 2, MAX_TENTS), _AUTO], **_GLOSSY_COMMON,
    },
    args=_args("bands", "bands_out", "brdf", "samples", "seed", "shadows", "bounces", "window", "window_width",
               "quad_bands", "estimator") + (
        Arg("--tents", "M", "M, the M×M tent basis over the hemisphere"),
    ),
))

register_kind(TransferKind(
    name="transport", function=precompute_transport, output="directory",
    doc="tabulated direct transport functions on cube maps for a set of views (Green 2005 §2.2.1), streamed to a directory",
    constraints={
        "brdf": _BRDF, "views": [Interval(int, 1, 16), Predicate(_is_directions, "view directions [J, 3]")],
        "res": [Interval(int, 1, MAX_CUBE_RES), _AUTO], "dtype": [Options("float32", "float16")],
        "supersample": [Interval(int, 1, 8), _AUTO],
        "shadows": [Boolean()] + _SHADOWS,
        "max_chunks": _OPT_INT,
    },
    args=_args("brdf", "shadows") + (
        Arg("--views", "views", "icosphere frequency of the view set (3 -> 92 views)"),
        Arg("--cube-res", "res", "cube-map face resolution r (6 r² texels), or auto (default): the smallest r where the "
            "BRDF's narrowest lobe spans 2 texel spacings (the reason in the manifest's auto.res)"),
        Arg("--transport-dtype", "dtype", "stored precision", values={"float32": "float32", "float16": "float16"}),
        Arg("--supersample", "supersample", "s x s sub-texels per texel. transport: texel averages where the BRDF's lobe is "
            "narrower than the texels (grazing views; auto, the default: 4; 1: point values at texel centres; the reason in the "
            "manifest's supersample); wavelet: sub-texel rays per texel (1: texel centres)"),
    ),
))



def _is_power_of_two(v: Any) -> bool:
    return isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 128 and not v & (v - 1)


register_kind(TransferKind(
    name="wavelet", function=precompute_wavelet,
    doc="all-frequency shadowed diffuse transfer as sparse Haar wavelets on a 6xRxR cube (Ng et al. 2003)",
    constraints={
        "res": [Predicate(_is_power_of_two, "a power of two in [1, 128]"), _AUTO],
        "terms": [Interval(int, 1, MAX_WAVELET_TERMS)], "bits": [Options(*BITS)], "scales": [Options(*SCALES)],
        "threshold": [Interval(float, 0, 1, closed="left")], "supersample": [Interval(int, 1, 16)],
        "sampling": [Options(*SAMPLINGS)], "bounces": [Interval(int, 0, 8)], "hit_samples": [Interval(int, 1, 4096)],
        "hit_offset": [Interval(float, 0, 0.1)],
        "shadows": [Boolean()] + _SHADOWS, "probe_tol": [Interval(float, 0, 1, closed="left")], "seed": _SEED,
    },
    args=_args("shadows", "seed", "bounces") + (
        Arg("--hit-samples", "hit_samples", "rays per bounce hit point (cosine-weighted; a quarter per further bounce)"),
        Arg("--hit-offset", "hit_offset", "offset of the rays leaving a bounce hit point, as a fraction of the bounding-box "
            "diagonal (default 1e-6, floored at 16 float32 ulps)"),
        Arg("--res", "res", "cube face resolution R, a power of two (6 R² texels), or auto (from the lights' energy "
            "above each wavelet level)"),
        Arg("--terms", "terms", "Haar coefficients kept per vertex (the largest), K <= 6 R²"),
        Arg("--bits", "bits", "stored precision of the kept values: 8 or 16 (integers with float32 scales) or 32 (float)"),
        Arg("--scales", "scales", "the integers' scales: level (one per vertex and Haar level; default) or vertex (one per vertex)"),
        Arg("--threshold", "threshold", "drop kept coefficients below this fraction of the vertex's largest"),
        Arg("--supersample", "supersample", "s x s sub-texel rays per texel (1: texel centres)"),
        Arg("--texel-sampling", "sampling", "grid (sub-texel centres) or jittered (one random point per sub-texel and "
            "vertex, unbiased; seeded by --seed)", values={"grid": "grid", "jittered": "jittered"}),
    ),
))


def _is_sss_term(v: Any) -> bool:
    check_term_spec(v)
    return True


def _is_material(v: Any) -> bool:
    material_from_spec(v)
    return True


def _is_rgb(v: Any) -> bool:
    import math

    vals = [v] if isinstance(v, (int, float)) and not isinstance(v, bool) else v
    return (isinstance(vals, (list, tuple)) and len(vals) in (1, 3)
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x >= 0 for x in vals))


_MATERIAL = [Predicate(_is_material, f"a measured material of Jensen et al. 2001 ({', '.join(sorted(SSS_PRESETS))}) or "
                       "{sigma_a: [R,G,B], sigma_s: [R,G,B], eta: E} (mm^-1)"), None]
_RGB = [Predicate(_is_rgb, "R,G,B (or one number), each finite and >= 0, in mm^-1"), None]

register_kind(TransferKind(
    name="subsurface", function=precompute_subsurface,
    doc="subsurface scattering term alone (dipole of Jensen 2001, hierarchy of Jensen & Buhler 2002, SH lighting as "
    "Sloan 2003 §3.1): diffuse transfer [V,3,n²], colour folded",
    constraints={
        "material": _MATERIAL, "scale": [Interval(float, 0, None, closed="neither")],
        "bands": [Interval(int, 1, MAX_DIFFUSE_BANDS)], "samples": [Interval(int, 1, MAX_SAMPLES)],
        "bounces": [Interval(int, 0, MAX_BOUNCES)], "seed": _SEED, "shadows": _SHADOWS,
        "sigma_a": _RGB, "sigma_s": _RGB, "eta": [Interval(float, 0, None, closed="neither"), None],
        "epsilon": [Interval(float, 0, None, closed="neither")], "fresnel": [Boolean()],
        "method": [Options("hierarchical", "brute")], "spacing": [Interval(float, 0, None, closed="neither")],
    },
    args=_args("bands", "samples", "bounces", "seed", "shadows") + (
        Arg("--material", "material", f"measured material (Jensen et al. 2001): {', '.join(sorted(SSS_PRESETS))}"),
        Arg("--sigma-a", "sigma_a", "absorption coefficient R,G,B in mm^-1 (with --sigma-s; instead of --material)"),
        Arg("--sigma-s", "sigma_s", "reduced scattering coefficient sigma_s' R,G,B in mm^-1 (with --sigma-a)"),
        Arg("--eta", "eta", "relative index of refraction (with --sigma-a/--sigma-s; default 1.3)"),
        Arg("--scale", "scale", "mm per mesh unit: the mesh's units decide how far light travels under the surface"),
        Arg("--epsilon", "epsilon", "the hierarchy's solid-angle threshold A/d^2 (default 0.05: <= 1% from the O(V^2) sum)"),
        Arg("--sss-method", "method", "hierarchical (Jensen & Buhler 2002, default) or brute (the O(V^2) sum)",
            values={"hierarchical": "hierarchical", "brute": "brute"}),
        Arg("--spacing", "spacing", "irradiance samples at most this many smallest mean free paths apart (default 1)"),
        Arg("--no-fresnel", "fresnel", "leave out the Fresnel transmittance F_dt at entry and exit", const=False),
    ),
))
