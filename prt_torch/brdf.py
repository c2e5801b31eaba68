"""Reflectance models and their spherical-harmonic forms: zonal lobes and BRDF matrices.

Local shading frame everywhere: +z is the surface normal n, +x the tangent u, +y the bitangent
v (rows of ``Mesh.frames()``). ``wi`` is the direction *towards the light* (Lehtinen & Kautz's
l̂_ω), ``wo`` the direction *towards the viewer* (v̂_ω); both point away from the surface.

Models (all batched; every parameter may be a float or a tensor ``[*P]`` that broadcasts,
right-aligned as in torch, against the direction batch ``wi.shape[:-1]`` — pass ``[V, 1]``
parameters for ``[V, N, 3]`` directions, or call :meth:`BRDF.view`):

* :class:`Lambertian` — kd/π.
* :class:`Phong` — ``form="modified"`` (Lafortune & Willems 1994, energy-normalised):
  kd/π + ks (s+2)/(2π) max(r·wi, 0)^s; ``form="reflection"`` (Ramamoorthi 2002 §3.2.6,
  the Phong-like kernel of Sloan et al. 2002): the *cosine-weighted* BRDF is
  kd/π cos θi + ks (s+1)/(2π) max(r·wi, 0)^s, radially symmetric about the reflected view
  r = 2(n·wo)n - wo, with zonal coefficients from eq. 3.37 (:func:`prt_torch.sh.phong`).
* :class:`BlinnPhong` — kd/π + ks (s+8)/(8π) max(n·h, 0)^s (normalised Blinn-Phong).
* :class:`AshikhminShirley` — Ashikhmin & Shirley 2000, "An anisotropic Phong BRDF model",
  eq. 4 (specular, with Schlick's Fresnel F = Rs + (1-Rs)(1 - k·h)^5) and eq. 5 (coupled
  diffuse); N_u ≠ N_v gives anisotropy. The model both MRT and CPCA use.
* :class:`Ward` — Ward 1992 anisotropic Gaussian: ρd/π + ρs exp(-tan²θh (cos²φh/αx² +
  sin²φh/αy²)) / (4π αx αy sqrt(cos θi cos θo)).
* :class:`Microfacet` — Ramamoorthi 2002's simplified microfacet model, eq. 5.34: the
  cosine-weighted BRDF f_r cos θi = ks exp(-(θh/σ)²)/(4πσ²), θh = ∠(n, h).

:attr:`BRDF.isotropic` says whether a model (with its parameters) is isotropic: Ashikhmin–Shirley
with N_u ≠ N_v and Ward with αx ≠ αy are not.

SH forms:

* :meth:`BRDF.lobes` — zonal coefficients h_l of radially symmetric lobes (Lambertian about
  the normal, reflection-form Phong about the reflected view), :func:`zonal_matrix` their
  diagonal double projection.
* :func:`brdf_matrix` — the BRDF matrix B (m² × n²) by double projection of the
  cosine-weighted BRDF f*(wi, wo) = f_r(wi, wo) max(0, n·wi) (Lehtinen & Kautz 2003 eq. 2–4;
  Sloan 2003 §3.1 ``B_ij = ∫_H ∫_H y_i(v) y_j(s) B(v, s) s_z ds dv``) by float64 product Gauss
  quadrature over both hemispheres, with the hemispherical projections of Sloan 2003 eq. (1)
  (A⁻¹ B A⁻¹, least squares; optional drop of (1,0) for non-square N_r × N_i), the
  reflections of Westin et al. 1992, and an optional window on the high output bands.
* :func:`double_project` — the generic double projection of any kernel K(s, v).
"""
from __future__ import annotations

import math
from typing import Any, Callable, Iterable

import numpy as np
import torch

from .executor import torch_threads
from ._checks import check_choice, check_int, check_shape, check_float_dtype, describe
from .params import check_kwargs
from .sh import (
    MAX_BANDS,
    band_factor,
    clamped_cosine,
    eval_sh,
    gauss_hemisphere,
    gauss_sphere,
    hemisphere_projector,
    lm_of,
    phong as phong_zonal,
    window as sh_window,
)

__all__ = [
    "BRDF",
    "Lambertian",
    "Phong",
    "BlinnPhong",
    "AshikhminShirley",
    "Ward",
    "Microfacet",
    "MODELS",
    "make_brdf",
    "from_spec",
    "reflect",
    "zonal_matrix",
    "double_project",
    "double_project_isotropic",
    "brdf_matrix",
    "brdf_matrices",
    "unique_params",
    "split_hemisphere_rules",
    "PROJECTIONS",
]

PROJECTIONS = ("zero", "least_squares", "odd", "even", "sphere")


def reflect(wo: torch.Tensor) -> torch.Tensor:
    """Mirror direction about the local normal +z: r = 2(n·wo)n - wo = (-x, -y, z). ``[..., 3]``."""
    return torch.stack([-wo[..., 0], -wo[..., 1], wo[..., 2]], dim=-1)


def _param(name: str, value, lo: float | None = None, lo_open: bool = False, hi: float | None = None) -> torch.Tensor:
    """Parameter as a float64 tensor, validated elementwise (message names the parameter)."""
    if isinstance(value, bool):
        raise TypeError(f"{name} must be a real number or a float tensor, got {describe(value)}")
    try:
        t = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError, RuntimeError):
        raise TypeError(f"{name} must be a real number or a float tensor, got {describe(value)}") from None
    bad = ~torch.isfinite(t)
    if lo is not None:
        bad |= (t <= lo) if lo_open else (t < lo)
    if hi is not None:
        bad |= t > hi
    if bool(bad.any()):
        v = t[bad].flatten()[0].item()
        rng = ("(" if lo_open else "[") + (f"{lo:g}" if lo is not None else "-inf") + ", " + (f"{hi:g}]" if hi is not None else "inf)")
        where = "" if t.ndim == 0 else f" (first bad entry of {int(bad.sum())})"
        raise ValueError(f"{name}={v!r}{where} is out of range; accepted: finite values in {rng}")
    return t


def _check_dirs(wi: torch.Tensor, wo: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    check_shape("wi", wi, last=(3,))
    check_shape("wo", wo, last=(3,))
    check_float_dtype("wi", wi)
    check_float_dtype("wo", wo)
    return wi, wo


def _broadcast_shapes(*shapes) -> torch.Size:
    """``torch.broadcast_shapes`` of plain integer shapes (NumPy's broadcasting rule), without its
    first-call import of ``torch.fx.experimental.symbolic_shapes`` and sympy (0.39 CPU s on this
    machine, torch 2.13: a fixed cost of every glossy/MRT precompute, issue 42). Raises as torch does,
    naming the shapes, when they do not broadcast."""
    n = max((len(s) for s in shapes), default=0)
    out = [1] * n
    for s in shapes:
        for k, d in enumerate(s, n - len(s)):
            d = int(d)
            if d != out[k] and d != 1:
                if out[k] != 1:
                    raise RuntimeError(f"shapes {[tuple(x) for x in shapes]} do not broadcast (axis {k}: {out[k]} vs {d})")
                out[k] = d
    return torch.Size(out)


class BRDF:
    """Base class of the batched reflectance models (see the module docstring for frames).

    Subclasses list their parameters in ``param_names`` and implement :meth:`_eval`.
    Attributes: one float64 tensor per parameter (shape ``[*P]`` or scalar).
    """

    name: str = "brdf"
    param_names: tuple[str, ...] = ()

    # -- parameters -------------------------------------------------------------------
    @property
    def params(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k) for k in self.param_names}

    @property
    def batch_shape(self) -> torch.Size:
        """Broadcast shape of all parameters (``torch.Size([])`` for a single material)."""
        return _broadcast_shapes(*(p.shape for p in self.params.values()))

    def _replace(self, **params) -> "BRDF":
        new = object.__new__(type(self))
        new.__dict__.update(self.__dict__)
        for k, v in params.items():
            setattr(new, k, v)
        return new

    def view(self, *shape: int) -> "BRDF":
        """Same model with every parameter broadcast to ``batch_shape`` and reshaped to ``shape``
        (e.g. ``brdf.view(-1, 1)`` to evaluate ``[P]`` materials against ``[P, N, 3]`` directions)."""
        bs = self.batch_shape
        return self._replace(**{k: v.expand(bs).reshape(*shape) for k, v in self.params.items()})

    def select(self, index: torch.Tensor) -> "BRDF":
        """Parameter sets ``index`` (int tensor) of a 1-D batch of materials."""
        bs = self.batch_shape
        if len(bs) != 1:
            raise ValueError(f"select needs a 1-D batch of parameters; this {self.name} has batch shape {tuple(bs)}")
        return self._replace(**{k: v.expand(bs)[index] for k, v in self.params.items()})

    def meta(self) -> dict:
        """JSON-able description: ``{"model": name, <param>: float or list}``."""
        out: dict = {"model": self.name}
        for k, v in self.params.items():
            out[k] = v.item() if v.ndim == 0 else v.tolist()
        out.update(self._extra_meta())
        return out

    def _extra_meta(self) -> dict:
        return {}

    def __repr__(self) -> str:
        items = ", ".join(f"{k}={v.item():g}" if v.ndim == 0 else f"{k}=tensor{tuple(v.shape)}" for k, v in self.params.items())
        extra = "".join(f", {k}={v!r}" for k, v in self._extra_meta().items())
        return f"{type(self).__name__}({items}{extra})"

    # -- evaluation -------------------------------------------------------------------
    def __call__(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        return self.eval(wi, wo)

    def eval(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """BRDF value f_r(wi, wo) for local unit directions ``wi, wo [..., 3]`` (float32/64).

        Returns ``broadcast(wi[..., 0], wo[..., 0], params)``-shaped values in the dtype of
        ``wi``; zero where either direction is below the surface (z ≤ 0).
        """
        _check_dirs(wi, wo)
        dtype = torch.promote_types(wi.dtype, wo.dtype)
        wi, wo = wi.to(dtype), wo.to(dtype)
        p = {k: v.to(dtype) for k, v in self.params.items()}
        f = self._eval(wi, wo, p)
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return torch.where(up, f, torch.zeros((), dtype=dtype))

    def cosine_weighted(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """The BRDF product function f*(wi, wo) = f_r(wi, wo) max(0, n·wi) (Lehtinen & Kautz
        2003, eq. 1), zero for wo below the surface. Shapes as :meth:`eval`."""
        return self.eval(wi, wo) * wi[..., 2].clamp_min(0)

    def extended(self, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
        """Full-sphere extension of f* used by ``brdf_matrix(projection="sphere")``; only
        models with a natural one (radially symmetric lobes) define it."""
        raise ValueError(
            f"the {self.name} model defines no full-sphere extension; accepted: projection in "
            "'zero', 'least_squares', 'odd', 'even' for this model"
        )

    def _eval(self, wi, wo, p) -> torch.Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def sharpness(self) -> float:
        """An equivalent Phong exponent of the sharpest lobe (≥ 0), used to size quadratures."""
        return 0.0

    #: The axis of the model's lobe: 'half' (a function of the half vector h: Blinn-Phong,
    #: Ashikhmin–Shirley, Ward, microfacet — narrower across the plane of incidence towards
    #: grazing views), 'reflection' (radially symmetric about the reflected view: Phong) or
    #: 'normal' (no view dependence: Lambertian). Sizes transport tables (``res: auto``); an
    #: unknown model is taken as 'half', the narrower.
    lobe_axis: str = "half"

    #: Whether the model's form depends on the azimuths only through φo − φi (a subclass says so;
    #: the default, False, keeps an unknown model off the isotropic paths).
    isotropic_form: bool = False

    @property
    def isotropic(self) -> bool:
        """True when f_r depends on the azimuths only through φo - φi for every parameter set
        (rotating the tangent frame changes nothing). :func:`brdf_matrix` then projects by
        :func:`double_project_isotropic`; a user model is taken as anisotropic unless its class
        sets ``isotropic_form = True``."""
        return self.isotropic_form

    def lobes(self, bands: int) -> list[tuple[str, torch.Tensor]]:
        """Radially symmetric lobes of the cosine-weighted BRDF as ``[(axis, h)]`` with
        ``axis`` in {"normal", "reflection"} and ``h [*P, bands]`` zonal coefficients
        (f* = Σ h(axis·wi)). Only for models that are sums of such lobes."""
        raise ValueError(
            f"the {self.name} model is not a sum of radially symmetric lobes; accepted: Lambertian, "
            "Phong(form='reflection')"
        )


class Lambertian(BRDF):
    """f_r = kd/π. ``kd`` ∈ [0, 1] (albedo), per material."""

    name = "lambertian"
    param_names = ("kd",)
    isotropic_form = True
    lobe_axis = "normal"

    def __init__(self, kd=1.0):
        self.kd = _param("kd", kd, 0.0, hi=1.0)

    def _eval(self, wi, wo, p):
        shape = _broadcast_shapes(wi.shape[:-1], wo.shape[:-1], p["kd"].shape)
        return (p["kd"] / math.pi).expand(shape)

    def extended(self, wi, wo):
        """kd/π max(wi_z, 0) for every wo on the sphere (view-independent)."""
        _check_dirs(wi, wo)
        shape = _broadcast_shapes(wi.shape[:-1], wo.shape[:-1], self.kd.shape)
        return (self.kd.to(wi.dtype) / math.pi * wi[..., 2].clamp_min(0)).expand(shape)

    def lobes(self, bands):
        """[("normal", kd/π · h_l(clamped cosine))] — Λ_l h_l = kd A_l / π (Ramamoorthi 2002 eq. 4.11)."""
        h = clamped_cosine(bands)
        return [("normal", self.kd[..., None] / math.pi * h)]


class Phong(BRDF):
    """Normalised Phong with exponent ``s ≥ 0``, specular ``ks`` and diffuse ``kd`` weights.

    ``form="modified"`` (default; Lafortune & Willems 1994): f_r = kd/π + ks (s+2)/(2π) max(r·wi, 0)^s.
    ``form="reflection"`` (Ramamoorthi 2002 §3.2.6, eq. 3.37): f_r cos θi =
    kd/π cos θi + ks (s+1)/(2π) max(r·wi, 0)^s — the lobe is radially symmetric about r, so its
    SH form is zonal (:meth:`lobes`); it is what Sloan et al. 2002 convolve with.
    """

    name = "phong"
    param_names = ("s", "ks", "kd")
    isotropic_form = True
    lobe_axis = "reflection"

    def __init__(self, s=32.0, ks=1.0, kd=0.0, form: str = "modified"):
        self.s = _param("s (Phong exponent)", s, 0.0)
        self.ks = _param("ks", ks, 0.0)
        self.kd = _param("kd", kd, 0.0, hi=1.0)
        self.form = check_choice("form", form, ["modified", "reflection"])

    def _extra_meta(self):
        return {"form": self.form}

    def _lobe(self, wi, wo, p):
        return torch.pow((reflect(wo) * wi).sum(-1).clamp_min(0), p["s"])

    def _eval(self, wi, wo, p):
        lobe = self._lobe(wi, wo, p)
        if self.form == "modified":
            return p["kd"] / math.pi + p["ks"] * (p["s"] + 2) / (2 * math.pi) * lobe
        cos_i = wi[..., 2].clamp_min(1e-300)
        return p["kd"] / math.pi + p["ks"] * (p["s"] + 1) / (2 * math.pi) * lobe / cos_i

    def cosine_weighted(self, wi, wo):
        if self.form == "modified":
            return super().cosine_weighted(wi, wo)
        _check_dirs(wi, wo)
        dtype = torch.promote_types(wi.dtype, wo.dtype)
        wi, wo = wi.to(dtype), wo.to(dtype)
        p = {k: v.to(dtype) for k, v in self.params.items()}
        f = p["kd"] / math.pi * wi[..., 2].clamp_min(0) + p["ks"] * (p["s"] + 1) / (2 * math.pi) * self._lobe(wi, wo, p)
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return torch.where(up, f, torch.zeros((), dtype=dtype))

    def extended(self, wi, wo):
        """Reflection form only: kd/π max(wi_z, 0) + ks (s+1)/(2π) max(r·wi, 0)^s for all wi, wo
        on the sphere — exactly the two zonal lobes of :meth:`lobes`."""
        if self.form != "reflection":
            return super().extended(wi, wo)
        _check_dirs(wi, wo)
        p = {k: v.to(wi.dtype) for k, v in self.params.items()}
        return p["kd"] / math.pi * wi[..., 2].clamp_min(0) + p["ks"] * (p["s"] + 1) / (2 * math.pi) * self._lobe(wi, wo, p)

    @property
    def sharpness(self):
        return float(self.s.max())

    def lobes(self, bands):
        """Reflection form: [("normal", kd/π h(clamped cosine)), ("reflection", ks h(Phong, eq. 3.37))]."""
        if self.form != "reflection":
            return super().lobes(bands)
        return [
            ("normal", self.kd[..., None] / math.pi * clamped_cosine(bands)),
            ("reflection", self.ks[..., None] * phong_zonal(self.s, bands)),
        ]


class BlinnPhong(BRDF):
    """f_r = kd/π + ks (s+8)/(8π) max(n·h, 0)^s with h = (wi + wo)/|wi + wo| (normalised Blinn-Phong)."""

    name = "blinn_phong"
    param_names = ("s", "ks", "kd")
    isotropic_form = True

    def __init__(self, s=64.0, ks=1.0, kd=0.0):
        self.s = _param("s (Blinn-Phong exponent)", s, 0.0)
        self.ks = _param("ks", ks, 0.0)
        self.kd = _param("kd", kd, 0.0, hi=1.0)

    def _eval(self, wi, wo, p):
        h = wi + wo
        h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        return p["kd"] / math.pi + p["ks"] * (p["s"] + 8) / (8 * math.pi) * torch.pow(h[..., 2].clamp_min(0), p["s"])

    @property
    def sharpness(self):
        return float(self.s.max()) / 4.0


class AshikhminShirley(BRDF):
    """Ashikhmin & Shirley 2000 anisotropic Phong BRDF.

    ρ_s = sqrt((N_u+1)(N_v+1))/(8π) · (n·h)^{(N_u (h·u)² + N_v (h·v)²)/(1-(h·n)²)}
          / ((h·k) max(n·k1, n·k2)) · F(k·h),   F(c) = Rs + (1-Rs)(1-c)^5      (eq. 4)
    ρ_d = 28 Rd/(23π) (1-Rs) (1-(1-n·k1/2)^5)(1-(1-n·k2/2)^5)                 (eq. 5)

    Parameters: ``nu, nv > 0`` (N_u along the tangent x, N_v along the bitangent y), ``rs``
    (specular reflectance at normal incidence) and ``rd`` (diffuse) in [0, 1]; ``fresnel=False``
    replaces F by the constant Rs; ``diffuse=False`` drops ρ_d.
    """

    name = "ashikhmin_shirley"
    param_names = ("nu", "nv", "rs", "rd")

    def __init__(self, nu=40.0, nv=None, rs=0.05, rd=0.0, fresnel: bool = True, diffuse: bool = True):
        self.nu = _param("nu (N_u)", nu, 0.0, lo_open=True)
        self.nv = _param("nv (N_v)", self.nu if nv is None else nv, 0.0, lo_open=True)
        self.rs = _param("rs", rs, 0.0, hi=1.0)
        self.rd = _param("rd", rd, 0.0, hi=1.0)
        self.fresnel = bool(fresnel)
        self.diffuse = bool(diffuse)

    def _extra_meta(self):
        return {"fresnel": self.fresnel, "diffuse": self.diffuse}

    def _eval(self, wi, wo, p):
        h = wi + wo
        h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        hx2, hy2, hz = h[..., 0] ** 2, h[..., 1] ** 2, h[..., 2].clamp(0, 1)
        sin2 = hx2 + hy2
        # exponent (N_u cos²φ_h + N_v sin²φ_h); at h = n (sin θ_h = 0) the power is 1 anyway
        expo = torch.where(sin2 > 1e-30, (p["nu"] * hx2 + p["nv"] * hy2) / sin2.clamp_min(1e-30), p["nu"] + 0 * sin2)
        kh = (wi * h).sum(-1).clamp_min(1e-300)
        denom = kh * torch.maximum(wi[..., 2], wo[..., 2]).clamp_min(1e-300)
        F = p["rs"] + (1 - p["rs"]) * (1 - kh) ** 5 if self.fresnel else p["rs"] + 0 * kh
        spec = torch.sqrt((p["nu"] + 1) * (p["nv"] + 1)) / (8 * math.pi) * torch.pow(hz, expo) / denom * F
        if not self.diffuse or (_broadcast_shapes(spec.shape, p["rd"].shape) == spec.shape and not bool(p["rd"].any())):
            return spec  # rd = 0 (the default): the diffuse term is exactly 0, spec + 0 = spec; not computed (issue 42 §2)
        ci, co = wi[..., 2].clamp(0, 1), wo[..., 2].clamp(0, 1)
        diff = 28 * p["rd"] / (23 * math.pi) * (1 - p["rs"]) * (1 - (1 - ci / 2) ** 5) * (1 - (1 - co / 2) ** 5)
        return spec + diff

    @property
    def sharpness(self):
        return float(torch.maximum(self.nu, self.nv).max()) / 4.0

    @property
    def isotropic(self) -> bool:
        """N_u = N_v everywhere."""
        return bool(torch.equal(*torch.broadcast_tensors(self.nu, self.nv)))


class Ward(BRDF):
    """Ward 1992 anisotropic Gaussian BRDF:
    f_r = ρd/π + ρs exp(-((h_x/αx)² + (h_y/αy)²)/h_z²) / (4π αx αy sqrt(cos θi cos θo)).
    ``ax, ay > 0`` are the roughnesses along tangent x and bitangent y; ``rs``, ``rd`` ≥ 0.
    """

    name = "ward"
    param_names = ("ax", "ay", "rs", "rd")

    def __init__(self, ax=0.2, ay=None, rs=0.05, rd=0.0):
        self.ax = _param("ax (Ward alpha_x)", ax, 0.0, lo_open=True)
        self.ay = _param("ay (Ward alpha_y)", self.ax if ay is None else ay, 0.0, lo_open=True)
        self.rs = _param("rs", rs, 0.0)
        self.rd = _param("rd", rd, 0.0, hi=1.0)

    def _eval(self, wi, wo, p):
        h = wi + wo
        h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        hz2 = (h[..., 2] ** 2).clamp_min(1e-300)
        e = -((h[..., 0] / p["ax"]) ** 2 + (h[..., 1] / p["ay"]) ** 2) / hz2
        cc = (wi[..., 2] * wo[..., 2]).clamp_min(1e-300)
        return p["rd"] / math.pi + p["rs"] * torch.exp(e) / (4 * math.pi * p["ax"] * p["ay"] * torch.sqrt(cc))

    @property
    def sharpness(self):
        a = float(torch.minimum(self.ax, self.ay).min())
        return 1.0 / (2.0 * a * a)

    @property
    def isotropic(self) -> bool:
        """αx = αy everywhere."""
        return bool(torch.equal(*torch.broadcast_tensors(self.ax, self.ay)))


class Microfacet(BRDF):
    """Ramamoorthi 2002's simplified microfacet model (eq. 5.34; eq. 3.42 without its 1/cos θo,
    Fresnel and shadowing): the cosine-weighted BRDF (the thesis' transfer function ρ̂)

        f_r cos θi = ks exp(-(θh/σ)²) / (4πσ²),   θh = arccos(n·h), h = (wi + wo)/|wi + wo|,

    so f_r = ks exp(-(θh/σ)²) / (4πσ² cos θi). ``sigma`` > 0 is the roughness in radians
    (about unit energy at normal exitance for small σ), ``ks`` ≥ 0 a scale. Isotropic.
    """

    name = "microfacet"
    param_names = ("sigma", "ks")
    isotropic_form = True

    def __init__(self, sigma=0.2, ks=1.0):
        self.sigma = _param("sigma (microfacet roughness)", sigma, 0.0, lo_open=True, hi=2.0)
        self.ks = _param("ks", ks, 0.0)

    def _lobe(self, wi, wo, p):
        h = wi + wo
        h = h / h.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        th = torch.arccos(h[..., 2].clamp(-1, 1))
        return p["ks"] * torch.exp(-((th / p["sigma"]) ** 2)) / (4 * math.pi * p["sigma"] ** 2)

    def _eval(self, wi, wo, p):
        return self._lobe(wi, wo, p) / wi[..., 2].clamp_min(1e-300)

    def cosine_weighted(self, wi, wo):
        """eq. 5.34 itself, zero where wi or wo is below the surface (no division by cos θi)."""
        _check_dirs(wi, wo)
        dtype = torch.promote_types(wi.dtype, wo.dtype)
        wi, wo = wi.to(dtype), wo.to(dtype)
        p = {k: v.to(dtype) for k, v in self.params.items()}
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return torch.where(up, self._lobe(wi, wo, p), torch.zeros((), dtype=dtype))

    @property
    def sharpness(self):
        """exp(-(θh/σ)²) with θh ≈ θ/2 about the reflected view is cos^s θ for s = 1/(2σ²)."""
        return 1.0 / (2.0 * float(self.sigma.min()) ** 2)


MODELS: dict[str, type[BRDF]] = {
    "lambertian": Lambertian,
    "phong": Phong,
    "blinn_phong": BlinnPhong,
    "ashikhmin_shirley": AshikhminShirley,
    "ward": Ward,
    "microfacet": Microfacet,
}
_ALIASES = {"as": "ashikhmin_shirley", "blinn": "blinn_phong", "blinnphong": "blinn_phong", "lambert": "lambertian", "diffuse": "lambertian"}


def make_brdf(model: str, **params) -> BRDF:
    """Build a model by name (``MODELS`` keys or aliases 'as', 'blinn', 'lambert', 'diffuse')
    from keyword parameters; ``make_brdf(**brdf.meta())`` round-trips (``meta`` has ``model``)."""
    key = _ALIASES.get(str(model).lower(), str(model).lower())
    cls = MODELS.get(key)
    if cls is None:
        raise ValueError(f"BRDF model={model!r} is not known; accepted: {sorted(MODELS)} (aliases {sorted(_ALIASES)})")
    check_kwargs(cls, params, f"BRDF model {key!r}")  # unknown or missing parameters named, with the accepted ones
    try:
        return cls(**params)
    except TypeError as e:
        raise ValueError(f"bad parameters for BRDF model {key!r}: {e}") from None


def from_spec(spec: Any) -> BRDF:
    """A BRDF from a config value: a :class:`BRDF` (returned as is), a model name
    (``'phong'``, default parameters) or a mapping ``{type: phong, s: 12, ...}`` — the ``type``
    key names the model, as for every typed object in configs."""
    if isinstance(spec, BRDF):
        return spec
    if isinstance(spec, str):
        return make_brdf(spec)
    if isinstance(spec, dict):
        d = dict(spec)
        model = d.pop("type", None)
        if model is None:
            raise ValueError(f"BRDF spec {spec!r} has no 'type'; accepted: {{type: MODEL, ...}} with MODEL in {sorted(MODELS)}")
        return make_brdf(model, **d)
    raise TypeError(f"BRDF spec {describe(spec)}; accepted: a BRDF, a model name, or {{type: MODEL, <param>: value}}")


# ----------------------------------------------------------------------------------------
# SH forms
# ----------------------------------------------------------------------------------------


def zonal_matrix(h: torch.Tensor, about: str = "reflection") -> torch.Tensor:
    """Diagonal double projection of a zonal lobe K(s, v) = Σ_l h_l Y_l0(axis(v)·s).

    By the addition theorem K = Σ_lm Λ_l h_l y_lm(axis(v)) y_lm(s), so projecting over v ∈ S²
    and s ∈ S² gives the diagonal matrix Λ_l h_l σ_lm with σ = 1 for ``about="normal"``
    (axis(v) = v: exit radiance parameterised by the lobe axis, e.g. the irradiance map
    E_lm/π = A_l L_lm/π, Ramamoorthi 2002 eq. 4.9–4.12) and σ = (-1)^m for
    ``about="reflection"`` (axis = reflect(v) = (-v_x, -v_y, v_z), since y_lm rotated by π
    about z is (-1)^m y_lm): the Phong kernel of Sloan et al. 2002.

    Args: h ``[*P, bands]``. Returns ``[*P, n², n²]`` float64.
    """
    check_choice("about", about, ["normal", "reflection"])
    bands = h.shape[-1]
    l, m = lm_of(bands)
    f = (h.to(torch.float64) * band_factor(bands))[..., l]
    if about == "reflection":
        f = f * torch.where(m % 2 == 0, 1.0, -1.0).to(torch.float64)
    return torch.diag_embed(f)


def _quad(domain: str, bands: int) -> tuple[torch.Tensor, torch.Tensor]:
    return (gauss_hemisphere if domain == "hemisphere" else gauss_sphere)(bands, dtype=torch.float64)


def _split_hemisphere_rule(z0: float, nz: int, nphi: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Product rule on z ≥ 0 with the z-interval split at z0: Gauss-Legendre (nz nodes each) on
    [0, z0] and [z0, 1] × nphi uniform φ. Returns (dirs [2·nz·nphi, 3], w), Σw = 2π."""
    d, w = split_hemisphere_rules(torch.tensor([float(z0)], dtype=torch.float64), nz, nphi)
    return d[0], w[0]


def split_hemisphere_rules(z0: torch.Tensor, nz: int, nphi: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`_split_hemisphere_rule` for every split point of ``z0 [R]`` float64 at once:
    (dirs ``[R, 2·nz·nphi, 3]``, w ``[R, 2·nz·nphi]``) float64, row r split at z0[r]. Public for
    integrands with a kink along z = z0 (Ashikhmin–Shirley's max(n·k1, n·k2) at z_i = z_o), e.g.
    the per-pixel rules of :func:`prt_torch.inverse.brdf_fit.slice_model`."""
    x, wz = (torch.from_numpy(a) for a in np.polynomial.legendre.leggauss(nz))
    zero, one = torch.zeros_like(z0), torch.ones_like(z0)
    lo, hi = torch.stack([zero, z0], 1), torch.stack([z0, one], 1)  # [R, 2] panels
    z = (lo[..., None] + (x + 1) * (hi - lo)[..., None] / 2).reshape(len(z0), -1)  # [R, 2nz]
    wzs = (wz * (hi - lo)[..., None] / 2).reshape(len(z0), -1)
    z = z.repeat_interleave(nphi, 1)
    w = wzs.repeat_interleave(nphi, 1) * (2 * math.pi / nphi)
    phi = (torch.arange(nphi, dtype=torch.float64) * (2 * math.pi / nphi)).repeat(2 * nz)
    s = torch.sqrt((1 - z * z).clamp_min(0))
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], -1), w


def double_project(
    kernel: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    bands_out: int,
    bands_in: int,
    *,
    domain: str = "hemisphere",
    quad_bands: int | None = None,
    batch: int = 1,
    split: bool = True,
    max_elems: int = 2**23,
) -> torch.Tensor:
    """Double SH projection B_ij = ∫∫ y_i(v) y_j(s) K(s, v) ds dv (Lehtinen & Kautz 2003 eq. 2–4).

    Args:
        kernel: ``K(s [Nv, Ns, 3], v [Nv, 1, 3]) -> [batch, Nv, Ns]`` (or ``[Nv, Ns]`` when
            batch = 1), float64; s is the light direction, v the view direction.
        bands_out, bands_in: m and n (rows m², columns n²).
        domain: ``"hemisphere"`` — both integrals over z ≥ 0 (zero-hemisphere projection,
            Sloan 2003 §3.1); ``"sphere"`` — both over S².
        quad_bands: product Gauss rule size L per direction ((L+1) z-nodes × (2L+1) φ-nodes);
            default 2·max(m, n) + 8.
        split: hemisphere only: split the light rule's z-interval at each view row's z
            (the views of the product rule share L+1 z values, so this is a loop over those
            rows). BRDFs with max(n·wi, n·wo) (Ashikhmin–Shirley) or min() have a kink along
            z_s = z_v; with the split every Gauss panel is smooth and the rule converges
            spectrally instead of as O(L⁻²).
        max_elems: bound on batch·Nv_chunk·Ns kernel values held at once (memory).
    Returns:
        ``[batch, m², n²]`` float64.
    """
    bands_out = check_int("bands_out", bands_out, 1, MAX_BANDS)
    bands_in = check_int("bands_in", bands_in, 1, MAX_BANDS)
    check_choice("domain", domain, ["hemisphere", "sphere"])
    L = quad_bands if quad_bands is not None else 2 * max(bands_out, bands_in) + 8
    L = check_int("quad_bands", L, 1, 1024)
    dirs, w = _quad(domain, L)
    N = dirs.shape[0]
    y_out = eval_sh(dirs, bands_out, check=False) * w[:, None]  # [Nv, m²] weighted
    out = torch.zeros(batch, bands_out**2, bands_in**2, dtype=torch.float64)

    def accumulate(vs: slice, s_dirs: torch.Tensor, s_w: torch.Tensor) -> None:
        y_in = eval_sh(s_dirs, bands_in, check=False) * s_w[:, None]  # [Ns, n²] weighted
        Ns = s_dirs.shape[0]
        idx = torch.arange(N)[vs]
        step = max(1, max_elems // max(1, batch * Ns))
        for a in range(0, len(idx), step):  # chunks bound memory (a handful of iterations)
            sel = idx[a : a + step]
            K = kernel(s_dirs[None, :, :], dirs[sel, None, :])
            if K.ndim == 2:
                K = K[None]
            K = K.expand(batch, K.shape[-2], K.shape[-1]).to(torch.float64)
            out.add_(torch.einsum("vi,bvj->bij", y_out[sel], K @ y_in))  # Σ_v y_i w_v Σ_s K w_s y_j

    if domain == "hemisphere" and split:
        nz, nphi = L + 1, 2 * L + 1
        # view rows of the product rule share z; one split light rule per row (L+1 iterations)
        for r in range(nz):
            z0 = float(dirs[r * nphi, 2])
            s_dirs, s_w = _split_hemisphere_rule(z0, (nz + 1) // 2 + 1, nphi)
            accumulate(slice(r * nphi, (r + 1) * nphi), s_dirs, s_w)
    else:
        accumulate(slice(0, N), dirs, w)
    return out


def double_project_isotropic(
    kernel: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    bands_out: int,
    bands_in: int,
    *,
    domain: str = "hemisphere",
    quad_bands: int | None = None,
    batch: int = 1,
    split: bool = True,
    max_elems: int = 2**23,
) -> torch.Tensor:
    """:func:`double_project` of a kernel that depends on the azimuths only through
    Δ = φ_s − φ_v (an isotropic BRDF): the same sum on the same nodes, with the view azimuth summed
    in closed form.

    For such a kernel the double projection is block-diagonal in the azimuthal index (Ramamoorthi
    2002 eq. 5.4–5.6: only y_lq(s), y_pq'(v) with |q| = |q'| survive). With y_{l,±k}(θ, φ) =
    K_lk(θ) cos(kφ) / sin(kφ) (K_lk(θ) = y_lk(θ, 0)) and the uniform φ grid of n_φ nodes shared
    by both rules, Σ_a c_i(φ_a) c_j(φ_a + Δ_d) is n_φ (k = 0), n_φ/2 cos(kΔ_d) (same sign of m),
    n_φ/2 sin(kΔ_d) (m_i = k, m_j = −k) or −n_φ/2 sin(kΔ_d) (m_i = −k, m_j = k), exactly for
    2k < n_φ. So the kernel is evaluated only at views of azimuth 0 — one per z row of the view
    rule instead of n_φ — and its Fourier sums over Δ give every entry:

        B_ij = Σ_r Σ_z w_r w_z K_i(z_r) K_j(z) Σ_d K(s(z, Δ_d), v(z_r, 0)) g_ij(Δ_d).

    n_φ = 2L+1 times fewer kernel evaluations than :func:`double_project`, whose result this
    equals to rounding (``tests/test_brdf_fast.py``: 1e-10 on every model). Arguments, kernel
    contract and return value ``[batch, m², n²]`` float64 as :func:`double_project`; the kernel
    must be isotropic (not checked here: :func:`brdf_matrix` uses it when ``brdf.isotropic``).
    Runs on one torch thread: its steps are small (measured on 2 cores: 0.05 s steady on one
    thread, 0.06–0.94 s on two, the default glossy matrix).
    """
    with torch_threads(1):
        return _double_project_isotropic(kernel, bands_out, bands_in, domain, quad_bands, batch, split, max_elems)


def _double_project_isotropic(kernel, bands_out, bands_in, domain, quad_bands, batch, split, max_elems) -> torch.Tensor:
    bands_out = check_int("bands_out", bands_out, 1, MAX_BANDS)
    bands_in = check_int("bands_in", bands_in, 1, MAX_BANDS)
    check_choice("domain", domain, ["hemisphere", "sphere"])
    L = quad_bands if quad_bands is not None else 2 * max(bands_out, bands_in) + 8
    L = check_int("quad_bands", L, 1, 1024)
    dirs, w = _quad(domain, L)
    nz, nphi = L + 1, 2 * L + 1
    zv, wv = dirs[::nphi, 2], w[::nphi]  # the view rule's z rows and node weights (2π/n_φ included)
    if domain == "hemisphere" and split:  # one split light rule per view row, as double_project's
        s_dirs, s_w = split_hemisphere_rules(zv, (nz + 1) // 2 + 1, nphi)  # [nz, Ns, 3], [nz, Ns]
    else:
        s_dirs, s_w = dirs[None].expand(nz, -1, -1), w[None].expand(nz, -1)
    Ns = s_dirs.shape[1]
    nzs = Ns // nphi
    sv = torch.sqrt((1 - zv * zv).clamp_min(0))
    v = torch.stack([sv, torch.zeros_like(sv), zv], -1)[:, None, :]  # [nz, 1, 3] views at φ = 0
    K = torch.empty(batch, nz, Ns, dtype=torch.float64)
    step = max(1, max_elems // max(1, batch * Ns))
    for a in range(0, nz, step):  # chunks of view rows bound memory (one iteration at default sizes)
        k = kernel(s_dirs[a : a + step], v[a : a + step])
        K[:, a : a + step] = (k[None] if k.ndim == 2 else k).to(torch.float64)
    kmax = min(bands_out, bands_in)  # orders k = 0..kmax-1 couple
    phi = s_dirs[0, :nphi]
    delta = torch.atan2(phi[:, 1], phi[:, 0])  # the light rule's azimuths Δ_d (view at 0)
    kk = torch.arange(kmax, dtype=torch.float64)
    C = K.reshape(batch, nz, nzs, nphi) @ torch.cos(delta[:, None] * kk)  # [b, nz, nzs, kmax]
    S = K.reshape(batch, nz, nzs, nphi) @ torch.sin(delta[:, None] * kk)
    # K_lk at the view rows and at each row's light z nodes (y_l|m| at φ = 0), node weights folded in
    lo, mo = lm_of(bands_out)
    li, mi = lm_of(bands_in)
    Yv = eval_sh(v[:, 0], bands_out, check=False)[:, lo * (lo + 1) + mo.abs()] * wv[:, None]  # [nz, m²]
    zs = s_dirs[:, ::nphi, 2]  # [nz, nzs]
    ss = torch.sqrt((1 - zs * zs).clamp_min(0))
    ds = torch.stack([ss, torch.zeros_like(ss), zs], -1)
    Ys = eval_sh(ds, bands_in, check=False)[..., li * (li + 1) + mi.abs()] * s_w[:, ::nphi, None]  # [nz, nzs, n²]
    out = torch.zeros(batch, bands_out**2, bands_in**2, dtype=torch.float64)
    for k in range(kmax):  # one block per azimuthal order (≤ 16 iterations)
        io = torch.nonzero(mo.abs() == k).flatten()
        ij = torch.nonzero(mi.abs() == k).flatten()
        c = torch.einsum("ri,rzj,brz->bij", Yv[:, io], Ys[:, :, ij], C[..., k])
        if k == 0:
            out[:, io[:, None], ij[None, :]] = nphi * c
            continue
        s = torch.einsum("ri,rzj,brz->bij", Yv[:, io], Ys[:, :, ij], S[..., k])
        pos_o, pos_i = (mo[io] > 0)[:, None], (mi[ij] > 0)[None, :]
        g = torch.where(pos_o == pos_i, c, torch.where(pos_o, s, -s))  # cos·cos, sin·sin: C; cos·sin: S; sin·cos: −S
        out[:, io[:, None], ij[None, :]] = (nphi / 2) * g
    return out


def brdf_matrix(
    brdf: BRDF,
    bands_out: int,
    bands_in: int | None = None,
    *,
    projection: str = "zero",
    drop_out: Iterable[tuple[int, int]] | None = None,
    rcond: float | None = None,
    window: str | torch.Tensor | None = None,
    window_width: int | None = None,
    quad_bands: int | None = None,
) -> torch.Tensor:
    """The BRDF matrix B (m² × n²; Lehtinen & Kautz 2003 eq. 4; Sloan 2003 §3.1).

    B_ij = ∫_H ∫_H y_i(v) y_j(s) f_r(s, v) s_z ds dv, by float64 product Gauss quadrature
    over both hemispheres (:func:`double_project`; for an isotropic model
    :func:`double_project_isotropic`, the same sum with the view azimuth done in closed form,
    Ramamoorthi 2002 eq. 5.4–5.6: 2L+1 times fewer BRDF evaluations), then a hemispherical projection on both
    sides (Sloan 2003 eq. (1), appendix §9): B ← P_out B P_in with P from
    :func:`prt_torch.sh.hemisphere_projector`. Applied to the *zero-hemisphere* coefficients
    b = R_p T_p L of transferred radiance, ``B @ b`` gives exit-radiance coefficients over
    the kept output functions: L_out(v) = Σ_i (B b)_i y_i(v).

    Args:
        brdf: a model; a batch of parameters ``[P]`` gives one matrix per material.
        bands_out: m (exit radiance bands); bands_in: n (lighting bands, default m).
        projection: ``"zero"`` (P = I, Sloan 2002 / Sloan 2003 §3.1), ``"least_squares"``
            (P = A⁻¹, Sloan 2003 eq. (1)), ``"odd"`` / ``"even"`` (Westin et al. 1992
            reflections), or ``"sphere"`` (double projection over S² × S² of the model's
            full-sphere extension, for radially symmetric lobes; no P).
        drop_out: least-squares only: output basis functions to leave out, e.g. ``[(1, 0)]``
            for Sloan's 24 × 25 matrices (Sloan 2003 §6.1). Rows follow :func:`output_index`.
        rcond: least-squares pseudo-inverse threshold (needed beyond ~6 bands).
        window: per-band attenuation of the *output* bands against ringing (Lehtinen &
            Kautz 2003 §7, windowing "in the higher-order SH bands"): a kind accepted by
            :func:`prt_torch.sh.window` ('hanning', 'lanczos', 'gaussian') or a ``[m]`` tensor.
        quad_bands: quadrature size (default from the model's sharpness: sharp lobes need
            more nodes; 2·max(m,n) + 4·sqrt(s) + 8).
    Returns:
        ``[*P, n_out, n²]`` float64 (n_out = m² - len(drop_out)).
    """
    bands_out = check_int("bands_out", bands_out, 1, MAX_BANDS)
    bands_in = bands_out if bands_in is None else check_int("bands_in", bands_in, 1, MAX_BANDS)
    check_choice("projection", projection, PROJECTIONS)
    if not isinstance(brdf, BRDF):
        raise TypeError(f"brdf must be a prt_torch.brdf.BRDF, got {describe(brdf)}")
    if drop_out and projection != "least_squares":
        raise ValueError(f"drop_out applies to projection='least_squares' only, got projection={projection!r}")
    if quad_bands is None:
        quad_bands = 2 * max(bands_out, bands_in) + int(math.ceil(4 * math.sqrt(brdf.sharpness))) + 8
    bshape = brdf.batch_shape
    P = int(torch.Size(bshape).numel())
    flat = brdf.view(P, 1, 1)
    domain = "sphere" if projection == "sphere" else "hemisphere"
    iso = brdf.isotropic  # f* depends on φ_s − φ_v only: the view azimuth summed in closed form
    # chunks of materials: each chunk is one batched double projection (P/8 iterations)
    Bs = []
    per = 8
    for a in range(0, P, per):
        sub = flat._replace(**{k: v[a : a + per] for k, v in flat.params.items()})
        f = sub.extended if projection == "sphere" else sub.cosine_weighted
        project = double_project_isotropic if iso else double_project  # same nodes, same sum (to rounding)
        Bs.append(project(lambda s, v, f=f: f(s, v), bands_out, bands_in, domain=domain,
                          quad_bands=quad_bands, batch=min(per, P - a)))
    B = torch.cat(Bs, 0)
    if projection not in ("zero", "sphere"):
        kw = dict(rcond=rcond) if projection == "least_squares" else {}
        P_out = hemisphere_projector(bands_out, projection, drop=drop_out, **kw)
        P_in = hemisphere_projector(bands_in, projection, **kw)
        B = P_out @ B @ P_in
    if window is not None:
        w = window if isinstance(window, torch.Tensor) else sh_window(bands_out, window, width=window_width)
        if w.shape != (bands_out,):
            raise ValueError(f"window has shape {tuple(w.shape)}; accepted: [{bands_out}] (one factor per output band)")
        l_idx = lm_of(bands_out)[0][output_index(bands_out, drop_out)]
        B = B * w.to(torch.float64)[l_idx][:, None]
    return B.reshape(*bshape, B.shape[-2], B.shape[-1])


def output_index(bands_out: int, drop_out: Iterable[tuple[int, int]] | None = None) -> torch.Tensor:
    """Flat SH indices of the rows of a BRDF / exit-transfer matrix (all m² unless dropped)."""
    n2 = bands_out * bands_out
    keep = torch.ones(n2, dtype=torch.bool)
    for l, m in drop_out or ():
        keep[l * (l + 1) + m] = False
    return torch.nonzero(keep).flatten()


__all__.append("output_index")


def unique_params(brdf: BRDF) -> tuple[BRDF, torch.Tensor]:
    """Deduplicate a 1-D batch of materials: returns (model with U unique parameter sets
    ``[U]``, inverse index ``[P]`` int64) so per-vertex matrices are built once per material."""
    bs = brdf.batch_shape
    if len(bs) == 0:
        return brdf.view(1), torch.zeros(1, dtype=torch.int64)
    if len(bs) != 1:
        raise ValueError(f"unique_params needs a 1-D batch of parameters, got batch shape {tuple(bs)}")
    stacked = torch.stack([v.expand(bs) for v in brdf.params.values()], dim=-1)
    uniq, inv = torch.unique(stacked, dim=0, return_inverse=True)
    return brdf._replace(**{k: uniq[:, i].contiguous() for i, k in enumerate(brdf.param_names)}), inv


def brdf_matrices(brdf: BRDF, bands_out: int, bands_in: int | None = None, max_materials: int = 4096, **kw) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-vertex BRDF matrices without duplication: ``(B [U, n_out, n²] float64, index [V])``
    with B_p = B[index[p]]. Refuses more than ``max_materials`` distinct parameter sets (each
    costs a full double projection); quantise spatially varying parameters first."""
    uniq, inv = unique_params(brdf)
    U = int(uniq.batch_shape.numel())
    if U > max_materials:
        raise ValueError(
            f"{U} distinct BRDF parameter sets would need {U} double projections; accepted: at most "
            f"max_materials={max_materials} (quantise the per-vertex parameters, e.g. to a palette)"
        )
    return brdf_matrix(uniq, bands_out, bands_in, **kw).reshape(U, -1, (bands_in or bands_out) ** 2), inv


__all__.append("brdf_matrices")
