"""Subsurface scattering transfer: the dipole diffusion BSSRDF (Jensen et al. 2001) spread over
the surface by the hierarchical evaluation of Jensen & Buhler 2002, in the SH basis of the
lighting (Sloan et al. 2003 §3.1, Fig. 9).

Model (Jensen, Marschner, Levoy & Hanrahan 2001, "A Practical Model for Subsurface Light
Transport", §2.4-2.5; all lengths in mm, coefficients in mm⁻¹):

    σ'_t = σ_a + σ'_s,   α' = σ'_s / σ'_t,   σ_tr = √(3 σ_a σ'_t)              (eq. 5-7)
    F_dr = −1.440/η² + 0.710/η + 0.668 + 0.0636 η,   A = (1 + F_dr)/(1 − F_dr)
    z_r = 1/σ'_t,   z_v = z_r (1 + 4A/3),   d_{r,v} = √(r² + z_{r,v}²)
    R_d(r) = α'/(4π) [ z_r (σ_tr d_r + 1) e^{−σ_tr d_r}/d_r³ + z_v (σ_tr d_v + 1) e^{−σ_tr d_v}/d_v³ ]   (eq. 4)
    ∫₀^∞ R_d(r) 2πr dr = (α'/2)(1 + e^{−(4/3)A√(3(1−α'))}) e^{−√(3(1−α'))}      (eq. 13)

and within radius ρ (the same antiderivative, used for a sample's own disk and the edge test):
``P(ρ) = (α'/2) Σ_{z∈{z_r,z_v}} (e^{−σ_tr z} − z e^{−σ_tr √(ρ²+z²)} / √(ρ²+z²))``.

The BSSRDF of the diffusion term is S_d = (1/π) F_t(η, ω_i) R_d(‖x_i − x_o‖) F_t(η, ω_o)
(Jensen 2001 eq. 5). Sloan 2003 makes it view-independent ("affects only the y_0 basis function
of exiting radiance"); here both Fresnel factors are replaced by their cosine-weighted mean over
the outside hemisphere, F_dt = 1 − F_dr,ext: exact for the entry under a uniform radiance field,
and the view-independent exit Sloan uses. Jensen's F_dr(η) (η > 1) is the *internal* diffuse
reflectance (≈ 0.44 at η = 1.3, total internal reflection included; it sets A); the outside's
follows from it by reciprocity of a diffuse field across the boundary (L_in = η² L_out):
F_dt = 1 − F_dr,ext = η² (1 − F_dr(η)) (0.94 at η = 1.3, 0.91 at 1.5). So, with E(x_i) the SH
transfer of *transferred irradiance* (E = π t of :mod:`~prt_torch.transfer.diffuse`, ρ = 1:
shadowed, optionally interreflected)

    L_o(x_o)[c] = (F_dt² / π) Σ_i R_d,c(‖x_i − x_o‖) A_i E(x_i)      (c = R, G, B)

— a diffuse transfer vector per channel, ``[V, 3, n²]``: under constant radiance 1 on a large
flat slab (E = π) the exit radiance is F_dt² · R_d (``fresnel=False``: R_d itself).

The sum over every sample (O(V²)) is :func:`scatter_brute`; :func:`scatter_hierarchical` is
Jensen & Buhler 2002 §3: an octree over the irradiance samples (per node: total area, the
area-weighted centroid, Σ A_i E_i, a bounding radius), and a node whose solid angle seen from
the receiver, ΔΩ = A_node / d², is below ``epsilon`` (and whose bounding sphere does not hold
the receiver) contributes R_d(d) Σ A_i E_i as one sample; other nodes are opened, and a leaf
that cannot be accepted is summed sample by sample. The tree is arrays (Morton order) and the
walk goes level by level over (receiver, node) pairs with masks — no per-vertex Python loop —
each level's accepted pairs gathering rows of the node/sample table and scattering them
(``index_add_``) to their receivers. When the vertices are sparser than the mean free path the
samples are points spread over the faces (:func:`surface_samples`, Jensen & Buhler 2002 §3.1:
samples denser than the mean free path), E interpolated from the vertices; the receivers are
always the vertices. A receiver's own sample is integrated over its own disk of area A_i (P(ρ_i), ρ_i =
√(A_i/π)), not evaluated at r = 0, and no sample weighs more than that: R_d is decreasing, so the
mean of R_d over a disk of area A_j is largest for the disk centred on the receiver, and the
weight of sample j is min(R_d(r), P(ρ_j)/A_j) · A_j (without the bound, two scan vertices a
hair apart each see the other's whole area at R_d(0), ~1/z_r² — bright specks on scanned meshes).

Presets: the measured materials of Jensen et al. 2001, Fig. 5 (σ'_s, σ_a in mm⁻¹ for R, G, B;
η = 1.3 for foods and skin, 1.5 for marble as published; the table's diffuse reflectance R_d
column is kept as ``published_rd`` and checked against eq. 13 in the tests).
"""
from __future__ import annotations

import dataclasses
import math
import time
import warnings
from typing import Any

import numpy as np
import torch

from .._checks import check_float, check_int
from ..scene import Mesh
from ..scene.mesh import edge_face_counts, face_areas
from .base import RunOptions

__all__ = [
    "Material", "PRESETS", "material_from_spec", "resolve_material", "published_rd", "fresnel_dr", "vertex_areas", "dipole_rd", "dipole_rd_within",
    "SampleTree", "scatter_brute", "scatter_hierarchical", "subsurface_term",
    "check_closed", "check_scale", "sub_state", "surface_samples", "DEFAULT_SPACING", "MAX_SAMPLES", "check_term_spec", "add_term", "DEFAULT_EPSILON",
    "sample_count", "scatter_bytes",
]

#: default solid-angle threshold ΔΩ = A_node/d² of the hierarchy; measured against the O(V²)
#: sum on scan_blob (tests/test_subsurface.py, reports/benchmarks/subsurface.md): ≤ 1% relative error
DEFAULT_EPSILON = 0.05
#: irradiance samples at most this multiple of the smallest mean free path 1/σ'_t apart (a flat
#: slab's reflectance with samples on a grid this far apart: ≤ 0.5% low at 0.5, ≤ 1.5% at 1,
#: ~3-4% at 2, ~5% at 8 on marble, whole milk and skin1; a 50 mm sphere of skin2 with lattice
#: samples on its faces: 0.4-2.5% low at 1, 0.4-0.5% at 0.5, 2-19% at 2)
DEFAULT_SPACING = 1.0
#: the most irradiance samples a precompute spreads over the surface
MAX_SAMPLES = 2_000_000
_LEVELS = 10  # octree depth (1024 cells per axis at the finest level)

# Jensen, Marschner, Levoy & Hanrahan 2001, Fig. 5: σ'_s [mm⁻¹], σ_a [mm⁻¹], diffuse reflectance R_d (R, G, B), η
_TABLE = {
    "apple": ((2.29, 2.39, 1.97), (0.0030, 0.0034, 0.046), (0.85, 0.84, 0.53), 1.3),
    "chicken1": ((0.15, 0.21, 0.38), (0.015, 0.077, 0.19), (0.31, 0.15, 0.10), 1.3),
    "chicken2": ((0.19, 0.25, 0.32), (0.018, 0.088, 0.20), (0.32, 0.16, 0.10), 1.3),
    "cream": ((7.38, 5.47, 3.15), (0.0002, 0.0028, 0.0163), (0.98, 0.90, 0.73), 1.3),
    "ketchup": ((0.18, 0.07, 0.03), (0.061, 0.97, 1.45), (0.16, 0.01, 0.00), 1.3),
    "marble": ((2.19, 2.62, 3.00), (0.0021, 0.0041, 0.0071), (0.83, 0.79, 0.75), 1.5),
    "potato": ((0.68, 0.70, 0.55), (0.0024, 0.0090, 0.12), (0.77, 0.62, 0.21), 1.3),
    "skimmilk": ((0.70, 1.22, 1.90), (0.0014, 0.0025, 0.0142), (0.81, 0.81, 0.69), 1.3),
    "skin1": ((0.74, 0.88, 1.01), (0.032, 0.17, 0.48), (0.44, 0.22, 0.13), 1.3),
    "skin2": ((1.09, 1.59, 1.79), (0.013, 0.070, 0.145), (0.63, 0.44, 0.34), 1.3),
    "wholemilk": ((2.55, 3.21, 3.77), (0.0011, 0.0024, 0.014), (0.91, 0.88, 0.76), 1.3),
}
_ALIASES = {"skin": "skin1", "whole_milk": "wholemilk", "skim_milk": "skimmilk", "milk": "wholemilk"}


def fresnel_dr(eta: float) -> float:
    """F_dr(η): the diffuse Fresnel reflectance, Jensen 2001's fit (eq. after eq. 4; Egan &
    Hilgeman), for relative index η = n_inside / n_outside."""
    return -1.440 / eta ** 2 + 0.710 / eta + 0.668 + 0.0636 * eta


def _rgb(name: str, v: Any) -> tuple[float, float, float]:
    if isinstance(v, (int, float)) and not isinstance(v, bool):
        v = (v, v, v)
    try:
        t = tuple(float(x) for x in v)
    except (TypeError, ValueError):
        raise ValueError(f"{name}={v!r}; accepted: one number or three (R,G,B), each ≥ 0 and finite [mm⁻¹]") from None
    if len(t) != 3 or not all(math.isfinite(x) and x >= 0 for x in t):
        raise ValueError(f"{name}={v!r}; accepted: one number or three (R,G,B), each ≥ 0 and finite [mm⁻¹]")
    return t  # type: ignore[return-value]


@dataclasses.dataclass(frozen=True)
class Material:
    """A homogeneous scattering medium (Jensen 2001 §2.4): per channel (R, G, B) the absorption
    σ_a and reduced scattering σ'_s in mm⁻¹, and the relative index of refraction η > 0.
    Refused: negative, NaN/Inf, σ_a + σ'_s = 0 in a channel, η ≤ 0 (ValueError naming the value).

    Derived (``[3]`` float64 tensors): ``sigma_t`` σ'_t, ``alpha`` α', ``sigma_tr`` σ_tr, ``z_r``,
    ``z_v``; scalars ``F_dr``, ``F_dt``, ``A``; ``mean_free_path`` 1/σ'_t [mm]; :meth:`total_rd` (eq. 13).
    """

    sigma_a: tuple[float, float, float]
    sigma_s: tuple[float, float, float]
    eta: float = 1.3
    name: str = "custom"

    def __post_init__(self):
        object.__setattr__(self, "sigma_a", _rgb("sigma_a", self.sigma_a))
        object.__setattr__(self, "sigma_s", _rgb("sigma_s", self.sigma_s))
        eta = check_float("eta", self.eta)
        if not eta > 0:
            raise ValueError(f"eta={eta!r}; accepted: a relative index of refraction > 0 (1.3 skin/foods, 1.5 marble)")
        object.__setattr__(self, "eta", eta)
        if any(a + s <= 0 for a, s in zip(self.sigma_a, self.sigma_s)):
            raise ValueError(f"sigma_a={self.sigma_a} + sigma_s={self.sigma_s} is 0 in a channel; accepted: an extinction "
                             f"σ_a + σ'_s > 0 in every channel")

    @property
    def sigma_t(self) -> torch.Tensor:
        return torch.tensor(self.sigma_a, dtype=torch.float64) + torch.tensor(self.sigma_s, dtype=torch.float64)

    @property
    def alpha(self) -> torch.Tensor:
        return torch.tensor(self.sigma_s, dtype=torch.float64) / self.sigma_t

    @property
    def sigma_tr(self) -> torch.Tensor:
        return torch.sqrt(3.0 * torch.tensor(self.sigma_a, dtype=torch.float64) * self.sigma_t)

    @property
    def F_dr(self) -> float:
        return fresnel_dr(self.eta)

    @property
    def F_dt(self) -> float:
        """The outside's diffuse Fresnel transmittance η² (1 − F_dr(η)) (module docstring)."""
        return self.eta ** 2 * (1.0 - self.F_dr)

    @property
    def A(self) -> float:
        return (1.0 + self.F_dr) / (1.0 - self.F_dr)

    @property
    def z_r(self) -> torch.Tensor:
        return 1.0 / self.sigma_t

    @property
    def z_v(self) -> torch.Tensor:
        return self.z_r * (1.0 + 4.0 * self.A / 3.0)

    @property
    def mean_free_path(self) -> torch.Tensor:
        """``[3]`` 1/σ'_t in mm (the depth of the dipole's real source)."""
        return self.z_r

    def total_rd(self) -> torch.Tensor:
        """``[3]`` float64: the total diffuse reflectance of a semi-infinite slab, Jensen 2001 eq. 13,
        (α'/2)(1 + e^{−(4/3)A√(3(1−α'))}) e^{−√(3(1−α'))}."""
        s = torch.sqrt(3.0 * (1.0 - self.alpha))
        return 0.5 * self.alpha * (1.0 + torch.exp(-4.0 / 3.0 * self.A * s)) * torch.exp(-s)

    def describe(self) -> dict[str, Any]:
        """JSON-able record (coefficients, η and every derived quantity) for a transfer's meta."""
        r = lambda t: [float(x) for x in t]  # noqa: E731
        return {"name": self.name, "sigma_a_per_mm": list(self.sigma_a), "sigma_s_reduced_per_mm": list(self.sigma_s),
                "eta": self.eta, "sigma_tr_per_mm": r(self.sigma_tr), "alpha_prime": r(self.alpha), "z_r_mm": r(self.z_r),
                "z_v_mm": r(self.z_v), "F_dr": self.F_dr, "F_dt": self.F_dt, "A": self.A, "total_rd": r(self.total_rd())}


#: Jensen 2001 Fig. 5 materials by name; ``published_rd`` is the table's R_d column.
PRESETS: dict[str, Material] = {k: Material(sa, ss, eta, name=k) for k, (ss, sa, _rd, eta) in _TABLE.items()}
published_rd: dict[str, tuple[float, float, float]] = {k: v[2] for k, v in _TABLE.items()}


def material_from_spec(spec: Any) -> Material:
    """A :class:`Material` from a preset name (``PRESETS``; aliases skin, milk, whole_milk,
    skim_milk), a mapping ``{sigma_a: [R,G,B], sigma_s: [R,G,B], eta: E}`` (σ'_s, mm⁻¹) or a
    Material. Unknown names are refused naming the presets."""
    if isinstance(spec, Material):
        return spec
    if isinstance(spec, str):
        key = _ALIASES.get(spec.lower(), spec.lower())
        if key not in PRESETS:
            raise ValueError(f"material={spec!r} is not known; accepted: {sorted(PRESETS)} (aliases {sorted(_ALIASES)}) or "
                             f"{{sigma_a: [R,G,B], sigma_s: [R,G,B], eta: E}}")
        return PRESETS[key]
    if isinstance(spec, dict):
        extra = set(spec) - {"sigma_a", "sigma_s", "eta", "name"}
        if extra or not {"sigma_a", "sigma_s"} <= set(spec):
            raise ValueError(f"material={spec!r}; accepted: a preset name or {{sigma_a: [R,G,B], sigma_s: [R,G,B], eta: E}}")
        return Material(spec["sigma_a"], spec["sigma_s"], spec.get("eta", 1.3), name=str(spec.get("name", "custom")))
    raise TypeError(f"material must be a preset name, a mapping or a Material, got {type(spec).__name__}")


def resolve_material(material: Any = None, sigma_a: Any = None, sigma_s: Any = None, eta: Any = None) -> Material:
    """``material`` (a name, mapping or Material) or the coefficients one by one (``sigma_a``
    and ``sigma_s`` both, ``eta`` default 1.3) — not both; None of either: marble."""
    loose = {k: v for k, v in (("sigma_a", sigma_a), ("sigma_s", sigma_s), ("eta", eta)) if v is not None}
    if material is not None and loose:
        raise ValueError(f"material={material!r} and {sorted(loose)} given together; accepted: a material name (--material) "
                         f"or the coefficients (--sigma-a R,G,B --sigma-s R,G,B [--eta E]), not both")
    if material is not None:
        return material_from_spec(material)
    if not loose:
        return PRESETS["marble"]
    if sigma_a is None or sigma_s is None:
        raise ValueError(f"{sorted(loose)} given without {'sigma_s' if sigma_s is None else 'sigma_a'}; accepted: both "
                         f"sigma_a and sigma_s (R,G,B in mm⁻¹), eta optional (default 1.3)")
    return Material(sigma_a, sigma_s, 1.3 if eta is None else eta)


def dipole_rd(r: torch.Tensor, m: Material) -> torch.Tensor:
    """R_d(r) of the dipole, Jensen 2001 eq. 4: ``r`` ``[...]`` in mm (float32 or float64) →
    ``[..., 3]`` in mm⁻² (per channel), dtype of ``r``."""
    r2 = (r * r)[..., None]
    st, zr, zv, al = (t.to(r.dtype) for t in (m.sigma_tr, m.z_r, m.z_v, m.alpha))
    dr = torch.sqrt(r2 + zr * zr)
    dv = torch.sqrt(r2 + zv * zv)
    return al / (4 * math.pi) * (zr * (st * dr + 1) * torch.exp(-st * dr) / (dr * dr * dr)
                                  + zv * (st * dv + 1) * torch.exp(-st * dv) / (dv * dv * dv))


def dipole_rd_within(rho: torch.Tensor, m: Material) -> torch.Tensor:
    """P(ρ) = ∫₀^ρ R_d(r) 2πr dr in closed form (module docstring): ``rho`` float64 ``[...]`` mm →
    ``[..., 3]``. P(∞) is :meth:`Material.total_rd` (Jensen 2001 eq. 13)."""
    r2 = (rho * rho)[..., None]
    st, zr, zv = m.sigma_tr, m.z_r, m.z_v
    dr = torch.sqrt(r2 + zr * zr)
    dv = torch.sqrt(r2 + zv * zv)
    return 0.5 * m.alpha * (torch.exp(-st * zr) - zr * torch.exp(-st * dr) / dr + torch.exp(-st * zv) - zv * torch.exp(-st * dv) / dv)


def vertex_areas(mesh: Mesh) -> torch.Tensor:
    """``[V]`` float64: a third of the area of each vertex's faces (the irradiance samples' A_i;
    they sum to the surface area)."""
    v = mesh.vertices.to(torch.float64).numpy()
    f = mesh.faces.numpy().astype(np.int64)
    a = face_areas(v, f) / 3.0
    return torch.from_numpy(np.bincount(f.reshape(-1), weights=np.repeat(a, 3), minlength=mesh.num_vertices))


# ----------------------------------------------------------------------------------------
# the O(V²) sum and the hierarchy
# ----------------------------------------------------------------------------------------

def _self_weight(areas: torch.Tensor, m: Material) -> torch.Tensor:
    """``[S, 3]``: a sample's weight on itself, P(√(A/π)) / A (R_d averaged over its own disk)."""
    rho = torch.sqrt(areas / math.pi)
    return dipole_rd_within(rho, m) / areas.clamp_min(1e-300)[:, None]


def scatter_brute(receivers: torch.Tensor, points: torch.Tensor, areas: torch.Tensor, values: torch.Tensor,
                  m: Material, receiver_ids: torch.Tensor | None = None, chunk: int = 1024) -> torch.Tensor:
    """The O(R·S) sum Σ_i R_d(‖x_i − x_o‖) A_i E_i (Jensen 2001 eq. 5 over the samples).

    Args:
        receivers: ``[R, 3]`` float64 points x_o (mm).
        points, areas, values: the samples: ``[S, 3]`` mm, ``[S]`` mm², ``[S, D]`` (E_i, any D).
        receiver_ids: ``[R]`` int64, the sample index of each receiver (its own disk is integrated:
            :func:`dipole_rd_within`), or -1 / None where the receiver is no sample.
        chunk: receivers per GEMM.
    Returns:
        ``[R, 3, D]`` float64.
    """
    x, p = receivers.to(torch.float64), points.to(torch.float64)
    aE = areas.to(torch.float64)[:, None] * values.to(torch.float64)  # [S, D]
    selfw = _self_weight(areas.to(torch.float64), m)  # [S, 3]
    out = torch.empty(x.shape[0], 3, aE.shape[1], dtype=torch.float64)
    p32 = p.to(torch.float32)
    for a in range(0, x.shape[0], chunk):  # chunks of receivers, each one batched GEMM
        xs = x[a:a + chunk]
        # distances directly (not |x|²+|y|²−2x·y, which loses the near field to cancellation), kernel in float32 as the hierarchy's
        K = dipole_rd(torch.cdist(xs.to(torch.float32), p32, compute_mode="donot_use_mm_for_euclid_dist"), m).to(torch.float64)
        K = torch.minimum(K, selfw[None])  # a sample nearer than its own radius: at most its disk's mean (module docstring)
        if receiver_ids is not None:
            rid = receiver_ids[a:a + chunk].to(torch.int64)
            ok = torch.nonzero(rid >= 0).squeeze(1)
            K[ok, rid[ok]] = selfw[rid[ok]]
        out[a:a + chunk] = torch.einsum("csk,sd->ckd", K, aE)
    return out


@dataclasses.dataclass
class SampleTree:
    """An octree over irradiance samples as arrays (Jensen & Buhler 2002 §3.2), nodes of every
    level concatenated (root = 0), samples in Morton order.

    Attributes (N nodes, S samples): ``order`` ``[S]`` sample index of each sorted position;
    ``area`` ``[N]`` total area; ``centre`` ``[N, 3]`` area-weighted centroid; ``radius`` ``[N]``
    bounding radius about it; ``aE`` ``[N, D]`` Σ A_i E_i; ``child_start``/``child_count``
    ``[N]`` (global ids, count 0 for a leaf); ``first``/``count`` ``[N]`` its samples' range in
    sorted order; ``leaf`` ``[N]`` bool (≤ ``leaf_size`` samples or the finest level).
    """

    points: torch.Tensor
    areas: torch.Tensor
    values: torch.Tensor
    order: torch.Tensor
    area: torch.Tensor
    centre: torch.Tensor
    radius: torch.Tensor
    aE: torch.Tensor
    child_start: torch.Tensor
    child_count: torch.Tensor
    first: torch.Tensor
    count: torch.Tensor
    leaf: torch.Tensor

    @classmethod
    def build(cls, points: torch.Tensor, areas: torch.Tensor, values: torch.Tensor, leaf_size: int = 8,
              levels: int = _LEVELS) -> "SampleTree":
        """Build from ``points [S,3]``, ``areas [S]``, ``values [S, D]`` (float64): Morton codes
        at ``levels`` bits per axis, one ``unique_consecutive`` and a few scatters per level."""
        p = points.to(torch.float64)
        a = areas.to(torch.float64)
        E = values.to(torch.float64)
        S = p.shape[0]
        lo, hi = p.min(0).values, p.max(0).values
        cell = ((p - lo) / (hi - lo).max().clamp_min(1e-300) * ((1 << levels) - 1)).round().to(torch.int64)
        code = torch.zeros(S, dtype=torch.int64)
        for b in range(levels):  # interleave bits (levels iterations, each over all samples)
            for ax in range(3):
                code |= ((cell[:, ax] >> b) & 1) << (3 * b + ax)
        code, order = torch.sort(code, stable=True)
        ps, aw, aEs = p[order], a[order], a[order, None] * E[order]
        nodes_area, nodes_c, nodes_r, nodes_aE, firsts, counts, parents, level_of = [], [], [], [], [], [], [], []
        offset = 0
        prev_prefix, prev_n = None, 0
        for lev in range(levels + 1):
            prefix = code >> (3 * (levels - lev))
            uniq, inv, cnt = torch.unique_consecutive(prefix, return_inverse=True, return_counts=True)
            n = uniq.shape[0]
            ar = torch.zeros(n, dtype=torch.float64).index_add_(0, inv, aw)
            c = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, ps * aw[:, None]) / ar.clamp_min(1e-300)[:, None]
            zero_area = ar <= 0
            if zero_area.any():  # degenerate samples only: their plain mean
                cm = torch.zeros(n, 3, dtype=torch.float64).index_add_(0, inv, ps) / cnt[:, None]
                c[zero_area] = cm[zero_area]
            rad = torch.zeros(n, dtype=torch.float64).scatter_reduce_(0, inv, (ps - c[inv]).norm(dim=1), "amax")
            nodes_area.append(ar)
            nodes_c.append(c)
            nodes_r.append(rad)
            nodes_aE.append(torch.zeros(n, aEs.shape[1], dtype=torch.float64).index_add_(0, inv, aEs))
            firsts.append(torch.cumsum(cnt, 0) - cnt)
            counts.append(cnt)
            parents.append(None if prev_prefix is None else
                           torch.searchsorted(prev_prefix, uniq >> 3) + (offset - prev_n))  # global id of the parent
            level_of.append(torch.full((n,), lev, dtype=torch.int64))
            prev_prefix, prev_n = uniq, n
            offset += n
        N = offset
        count = torch.cat(counts)
        level = torch.cat(level_of)
        leaf = (count <= leaf_size) | (level == levels)
        child_count = torch.zeros(N, dtype=torch.int64)
        child_start = torch.zeros(N, dtype=torch.int64)
        start = counts[0].shape[0]
        for lev in range(1, levels + 1):  # children of level lev-1 are contiguous in level lev (Morton order)
            par = parents[lev]
            n = par.shape[0]
            up, cnt_c = torch.unique_consecutive(par, return_counts=True)
            child_count[up] = cnt_c
            child_start[up] = start + torch.cumsum(cnt_c, 0) - cnt_c
            start += n
        child_count[leaf] = 0
        return cls(points=p, areas=a, values=E, order=order, area=torch.cat(nodes_area), centre=torch.cat(nodes_c),
                   radius=torch.cat(nodes_r), aE=torch.cat(nodes_aE), child_start=child_start, child_count=child_count,
                   first=torch.cat(firsts), count=count, leaf=leaf)

    @property
    def num_nodes(self) -> int:
        return int(self.area.shape[0])


def scatter_hierarchical(receivers: torch.Tensor, tree: SampleTree, m: Material, epsilon: float = DEFAULT_EPSILON,
                         receiver_ids: torch.Tensor | None = None, stats: dict | None = None) -> torch.Tensor:
    """Σ_i R_d(‖x_i − x_o‖) A_i E_i by the hierarchy of Jensen & Buhler 2002 §3.3: ``[R, 3, D]``
    float64 for ``receivers [R, 3]`` (mm); see the module docstring. A node is accepted when
    ΔΩ = A_node / d² < ``epsilon`` and d exceeds its bounding radius (d: receiver to the node's
    area-weighted centroid); a rejected leaf is summed over its samples (own sample: its disk,
    as :func:`scatter_brute`). The walk is over (receiver, node) pairs, one level per step.
    ``stats`` (a dict) receives the pair counts: ``node_terms``, ``sample_terms``."""
    epsilon = check_float("epsilon", epsilon, 0.0, None, lo_open=True)
    x = receivers.to(torch.float32)  # the walk and the kernel in float32 (R_d to ~1e-7), the sums in float64
    R = x.shape[0]
    N = tree.num_nodes
    centre, radius, area = tree.centre.to(torch.float32), tree.radius.to(torch.float32), tree.area.to(torch.float32)
    spts = tree.points.to(torch.float32)
    sw_all = _self_weight(tree.areas, m)  # [S, 3] each sample's bound (its own disk's mean)
    rid_all = None if receiver_ids is None else receiver_ids.to(torch.int64)
    rows_l, cols_l, w_l = [], [], []
    r = torch.arange(R)
    nd = torch.zeros(R, dtype=torch.int64)
    n_node_terms = n_sample_terms = 0
    while r.numel():
        d = (x[r] - centre[nd]).norm(dim=1)
        acc = (area[nd] < epsilon * d * d) & (d > radius[nd])
        if acc.any():
            rows_l.append(r[acc])
            cols_l.append(nd[acc])
            w_l.append(dipole_rd(d[acc], m).to(torch.float64))
            n_node_terms += int(acc.sum())
        rest = ~acc
        lf = rest & tree.leaf[nd]
        if lf.any():  # leaves summed sample by sample
            rl, nl = r[lf], nd[lf]
            cnt = tree.count[nl]
            rr = torch.repeat_interleave(rl, cnt)
            pos = torch.repeat_interleave(tree.first[nl] - torch.cumsum(cnt, 0) + cnt, cnt) + torch.arange(int(cnt.sum()))
            s = tree.order[pos]
            sw = sw_all[s]  # [P, 3]
            w = torch.minimum(dipole_rd((x[rr] - spts[s]).norm(dim=1), m).to(torch.float64), sw)
            if rid_all is not None:
                own = rid_all[rr] == s
                w[own] = sw[own]
            w = w * tree.areas[s, None]
            rows_l.append(rr)
            cols_l.append(N + s)
            w_l.append(w)
            n_sample_terms += int(rr.numel())
        op = rest & ~tree.leaf[nd]
        r, nd = r[op], nd[op]
        cc = tree.child_count[nd]
        r = torch.repeat_interleave(r, cc)
        nd = torch.repeat_interleave(tree.child_start[nd] - torch.cumsum(cc, 0) + cc, cc) + torch.arange(int(cc.sum()))
    if stats is not None:
        stats["node_terms"] = stats.get("node_terms", 0) + n_node_terms
        stats["sample_terms"] = stats.get("sample_terms", 0) + n_sample_terms
    table = torch.cat([tree.aE, tree.values])  # [N + S, D]: Σ A E per node, E per sample (areas in the weights)
    D = table.shape[1]
    out = torch.zeros(R, 3, D, dtype=torch.float64)
    if not rows_l:
        return out
    for rows, cols, w in zip(rows_l, cols_l, w_l):  # per level: gather the table rows, scatter to the receivers
        g = table[cols]  # [P, D]
        for c in range(3):
            out[:, c].index_add_(0, rows, g * w[:, c:c + 1])
    return out


def _lattice(k: int) -> torch.Tensor:
    """``[k², 3]`` float64 barycentrics of the centroids of a triangle's k² sub-triangles (the
    regular subdivision: k(k+1)/2 upright, k(k−1)/2 inverted), each of area A/k²."""
    i, j = torch.meshgrid(torch.arange(k), torch.arange(k), indexing="ij")
    i, j = i.reshape(-1).double(), j.reshape(-1).double()
    up = (i + j) <= k - 1
    dn = (i + j) <= k - 2
    u = torch.cat([(i[up] + 1 / 3) / k, (i[dn] + 2 / 3) / k])
    v = torch.cat([(j[up] + 1 / 3) / k, (j[dn] + 2 / 3) / k])
    return torch.stack([1 - u - v, u, v], 1)


def _subdivisions(mesh: Mesh, spacing: float, max_samples: int) -> tuple[torch.Tensor, torch.Tensor, bool]:
    """:func:`surface_samples`' subdivision of each face: (k_f ``[F]`` int64, face areas ``[F]``
    float64, whether the budget coarsened them)."""
    fa = torch.from_numpy(face_areas(mesh.vertices.to(torch.float64).numpy(), mesh.faces.to(torch.int64).numpy()))
    k = torch.ceil(torch.sqrt(fa) / spacing).clamp_min(1).to(torch.int64)
    capped = False
    while int((k * k).sum()) > max_samples and int(k.max()) > 1:  # coarsen uniformly until within the budget
        k = torch.ceil(k.double() * 0.9).to(torch.int64).clamp_min(1) - (k > 1).to(torch.int64) * (k > 2).to(torch.int64)
        capped = True
    return k, fa, capped


def _on_vertices(mesh: Mesh, m: "Material", scale: float, spacing: float) -> tuple[bool, float, torch.Tensor]:
    """Whether the vertices are dense enough to be the irradiance samples (their mean spacing at
    most ``spacing`` × the smallest mean free path, :func:`subsurface_term`), that target spacing
    in mm, and the vertex areas in mm²."""
    target = spacing * float(m.z_r.min())  # mm between irradiance samples
    varea = vertex_areas(mesh) * scale * scale
    return float(varea.sum()) / mesh.num_vertices <= target * target, target, varea


def sample_count(mesh: Mesh, material: Any, scale: float, spacing: float = DEFAULT_SPACING,
                 max_samples: int = MAX_SAMPLES) -> int:
    """How many irradiance samples :func:`subsurface_term` takes on ``mesh`` (the vertices, or
    :func:`surface_samples`' lattice), without building them: what the dry run sizes the
    hierarchy by (:func:`scatter_bytes`)."""
    m = material_from_spec(material)
    dense, target, _ = _on_vertices(mesh, m, scale, spacing)
    if dense:
        return mesh.num_vertices
    k, _, _ = _subdivisions(mesh, target / scale, max_samples)
    return int((k * k).sum())


def scatter_bytes(V: int, S: int, D: int, levels: int = _LEVELS) -> int:
    """Bytes the scatter pass holds in memory whole (:func:`subsurface_term`; every receiver may
    read any sample, so these are not streamed): the irradiance of the V vertices twice (float64
    ``[V, D]``: the input's copy and E = π t), the S samples (points, areas, values, Morton codes and
    order, and the build's sorted copies: 2 × (32 + 8D) + 40 bytes each) and the hierarchy's nodes
    (81 + 8D bytes each), counted at their upper bound Σ_l min(S, 8^l) over its ``levels`` + 1 levels."""
    nodes = sum(min(int(S), 8 ** lev) for lev in range(levels + 1))
    return int(2 * 8 * D * V + S * (2 * (32 + 8 * D) + 40) + nodes * (81 + 8 * D))


def surface_samples(mesh: Mesh, values: torch.Tensor, spacing: float, max_samples: int = 1_000_000,
                    seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, dict]:
    """Irradiance sample points over the surface about ``spacing`` apart (mesh units): each face
    is subdivided regularly into k_f² sub-triangles, k_f = ⌈√(A_f) / spacing⌉ (scaled down to at
    most ``max_samples`` in all), one sample at each sub-triangle's centroid with its area
    A_f / k_f² and the barycentric interpolation of the vertices' ``values [V, D]`` — a
    deterministic lattice (random points leave Poisson noise in the near field, which R_d
    weighs most). ``seed`` is unused (kept for the fingerprint). Returns points ``[S, 3]``, areas
    ``[S]``, values ``[S, D]`` (float64) and ``{'where', 'count', 'spacing', 'capped'}``."""
    v = mesh.vertices.to(torch.float64)
    f = mesh.faces.to(torch.int64)
    k, fa, capped = _subdivisions(mesh, spacing, max_samples)
    vals = values.to(torch.float64)
    pts_l, area_l, val_l = [], [], []
    for kk in torch.unique(k).tolist():  # one batch per subdivision level (a handful)
        sel = torch.nonzero(k == kk).squeeze(1)
        b = _lattice(int(kk))  # [k², 3]
        tri = f[sel]  # [F_k, 3]
        pts_l.append(torch.einsum("sj,fjd->fsd", b, v[tri]).reshape(-1, 3))
        val_l.append(torch.einsum("sj,fjd->fsd", b, vals[tri]).reshape(-1, vals.shape[1]))
        area_l.append((fa[sel] / (kk * kk))[:, None].expand(-1, b.shape[0]).reshape(-1))
    pts, areas, out = torch.cat(pts_l), torch.cat(area_l), torch.cat(val_l)
    S = int(pts.shape[0])
    return pts, areas, out, {"where": "surface", "count": S, "spacing": math.sqrt(float(fa.sum()) / S), "capped": capped}


# ----------------------------------------------------------------------------------------
# checks of the mesh and the length scale
# ----------------------------------------------------------------------------------------

def check_closed(mesh: Mesh) -> str | None:
    """None for a closed mesh; else a one-line warning naming where it is open (boundary edges,
    how many, and the bounding box of their vertices): the diffusion assumes a closed surface."""
    edges, cnt = edge_face_counts(mesh.faces.numpy(), mesh.num_vertices)
    b = edges[cnt == 1]
    if b.shape[0] == 0:
        return None
    vs = mesh.vertices.numpy()[np.unique(b)]
    lo, hi = vs.min(0), vs.max(0)
    fmt = lambda v: "(" + ", ".join(f"{x:.3g}" for x in v) + ")"  # noqa: E731
    return (f"mesh {mesh.name!r} is open: {b.shape[0]} boundary edges ({np.unique(b).shape[0]} vertices) within "
            f"{fmt(lo)}-{fmt(hi)}; the diffusion assumes a closed surface (light leaves through the holes unaccounted)")


def check_scale(mesh: Mesh, m: Material, scale: float) -> str | None:
    """None when the mean free path 1/σ'_t is within [size/1000, size] of the object (its
    bounding-box diagonal times ``scale`` mm); else a one-line warning with the numbers."""
    size = mesh.bbox_diagonal() * scale
    mfp = m.mean_free_path
    lo, hi = float(mfp.min()), float(mfp.max())
    if lo < size / 1000:
        return (f"material {m.name!r} at scale {scale:g} mm per unit: mean free path {lo:.3g} mm is below a thousandth of "
                f"the object ({size:.4g} mm): the subsurface term is a tiny blur (is the scale right?)")
    if hi > size:
        return (f"material {m.name!r} at scale {scale:g} mm per unit: mean free path {hi:.3g} mm exceeds the object "
                f"({size:.4g} mm): the diffusion approximation does not hold (is the scale right?)")
    return None


# ----------------------------------------------------------------------------------------
# the transfer
# ----------------------------------------------------------------------------------------

def subsurface_term(mesh: Mesh, irradiance_transfer: torch.Tensor, material: Any, scale: float, *,
                    epsilon: float = DEFAULT_EPSILON, fresnel: bool = True, method: str = "hierarchical",
                    spacing: float = DEFAULT_SPACING, max_samples: int = MAX_SAMPLES, seed: int = 0,
                    run: RunOptions | None = None, meta: dict | None = None,
                    dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """The subsurface exit transfer ``[V, 3, n²]`` (module docstring's L_o; float64, or ``dtype``)
    from the per-vertex diffuse transfer t (ρ = 1, ``[V, n²]``: E = π t) of the same mesh.

    Memory: the irradiance samples and their hierarchy are held whole (every receiver may read
    any sample: about three float64 copies of ``[S, n²]``); the receivers' rows are copied into
    :meth:`RunOptions.result_rows` as each chunk finishes — in a file beside ``run.state_dir``
    when larger than the streaming threshold — and converted to ``dtype`` there (elementwise:
    the bits of ``L.to(dtype)`` on the whole result).

    Irradiance samples (Jensen & Buhler 2002 §3.1: denser than the mean free path): the vertices
    when their mean spacing is below ``spacing`` × the smallest 1/σ'_t, else
    :func:`surface_samples` at that spacing (at most ``max_samples``; warned when capped), E
    interpolated from the vertices. The receivers are the vertices.

    ``scale``: mm per mesh unit. ``method``: 'hierarchical' (Jensen & Buhler 2002) or 'brute'
    (the O(V²) sum). Receivers run in ``run`` chunks (resumable, any executor). ``meta``
    receives the material, checks, timings and the hierarchy's pair counts."""
    m = material_from_spec(material)
    scale = check_float("scale", scale, 0.0, None, lo_open=True)
    if method not in ("hierarchical", "brute"):
        raise ValueError(f"method={method!r}; accepted: 'hierarchical' or 'brute'")
    run = RunOptions() if run is None else run
    meta = {} if meta is None else meta
    spacing = check_float("spacing", spacing, 0.0, None, lo_open=True)
    max_samples = check_int("max_samples", max_samples, 1)
    t0 = time.perf_counter()
    V = mesh.num_vertices
    T = torch.as_tensor(irradiance_transfer, dtype=torch.float64).reshape(V, -1)
    T_sum, D = float(T.abs().sum()), int(T.shape[1])  # the fingerprint's
    recv = mesh.vertices.to(torch.float64) * scale
    E_v = math.pi * T
    del T  # one copy of the irradiance held (the input may be a file-backed map: read once here)
    dense, target, varea = _on_vertices(mesh, m, scale, spacing)
    if dense:  # the vertices are dense enough: they are the samples
        pts, areas, E, ids = recv, varea, E_v, torch.arange(V)
        meta["samples"] = {"where": "vertices", "count": V, "spacing_mm": math.sqrt(float(varea.sum()) / V)}
    else:
        pts, areas, E, info = surface_samples(mesh, E_v, target / scale, max_samples, seed)
        pts, areas, ids = pts * scale, areas * scale * scale, None
        meta["samples"] = info | {"spacing_mm": info["spacing"] * scale}
        if info["capped"]:
            warnings.warn(f"subsurface: {info['count']} irradiance samples (max_samples) are {info['spacing'] * scale:.3g} mm "
                          f"apart, above the {target:.3g} mm asked ({spacing:g} x the smallest mean free path "
                          f"{float(m.z_r.min()):.3g} mm): the near field is under-resolved (a few % dark)", stacklevel=3)
    fdt = m.F_dt if fresnel else 1.0
    tree = SampleTree.build(pts, areas, E) if method == "hierarchical" else None

    def compute(a: int, b: int) -> dict[str, torch.Tensor]:
        rid = None if ids is None else ids[a:b]
        st = {"node_terms": 0, "sample_terms": (b - a) * int(pts.shape[0])}
        if tree is None:
            out = scatter_brute(recv[a:b], pts, areas, E, m, receiver_ids=rid)
        else:
            st["sample_terms"] = 0
            out = scatter_hierarchical(recv[a:b], tree, m, epsilon, receiver_ids=rid, stats=st)
        # the pair counts travel with the chunk (a Ray task's side effects would not come back)
        return {"L": out * (fdt * fdt / math.pi), "terms": torch.tensor([st["node_terms"], st["sample_terms"]])}

    fp = {"kind": "subsurface", "mesh": mesh.content_hash(), "material": m.describe(), "scale": scale, "epsilon": epsilon,
          "fresnel": fresnel, "method": method, "spacing": spacing, "max_samples": max_samples, "seed": seed,
          "T": T_sum, "shape": [V, D]}
    L = run.result_rows((V, 3, D), dtype, name="subsurface")
    terms = torch.zeros(2, dtype=torch.int64)

    def sink(a: int, b: int, c: dict[str, torch.Tensor]) -> None:  # each chunk copied in as it finishes
        L[a:b] = c["L"]
        terms.add_(c["terms"])

    run.run_chunks(V, run.chunks(2048), compute, fingerprint=fp, desc="subsurface", sink=sink)
    stats = {"node_terms": int(terms[0]), "sample_terms": int(terms[1])}
    meta.update({"material": m.describe(), "scale_mm_per_unit": scale, "epsilon": epsilon, "method": method,
                 "fresnel": f"F_dt = eta^2 (1 - F_dr) = {m.F_dt:.4f} at entry and exit (view-independent, Sloan 2003 §3.1)" if fresnel else "none",
                 "seconds_scatter": time.perf_counter() - t0,
                 "tree_nodes": tree.num_nodes if tree is not None else 0, **stats})
    return L


def check_term_spec(spec: Any, where: str = "subsurface") -> dict[str, Any]:
    """The ``subsurface: {material: NAME | {sigma_a, sigma_s, eta}, scale: MM_PER_UNIT, epsilon:
    ..., fresnel: ...}`` term of the diffuse and glossy kinds, validated: ``{material: Material,
    scale, epsilon, fresnel}``. Unknown keys, a missing scale or material are refused."""
    if not isinstance(spec, dict):
        raise ValueError(f"{where}={spec!r}; accepted: {{material: NAME, scale: MM_PER_UNIT}} (optional epsilon, fresnel, spacing)")
    extra = set(spec) - {"material", "scale", "epsilon", "fresnel", "spacing"}
    if extra or "scale" not in spec or "material" not in spec:
        raise ValueError(f"{where}={spec!r}; accepted: {{material: NAME or {{sigma_a, sigma_s, eta}}, scale: MM_PER_UNIT}} "
                         f"(optional epsilon, fresnel, spacing)" + (f"; unknown keys {sorted(extra)}" if extra else ""))
    fresnel = spec.get("fresnel", True)
    if not isinstance(fresnel, bool):
        raise ValueError(f"{where}.fresnel={fresnel!r}; accepted: true or false")
    return {"material": material_from_spec(spec["material"]),
            "scale": check_float(f"{where}.scale", spec["scale"], 0.0, None, lo_open=True),
            "epsilon": check_float(f"{where}.epsilon", spec.get("epsilon", DEFAULT_EPSILON), 0.0, None, lo_open=True),
            "spacing": check_float(f"{where}.spacing", spec.get("spacing", DEFAULT_SPACING), 0.0, None, lo_open=True),
            "fresnel": fresnel}


def add_term(mesh: Mesh, spec: Any, transfer: torch.Tensor, run: RunOptions, meta: dict) -> torch.Tensor:
    """The subsurface term of ``spec`` (:func:`check_term_spec`) for a diffuse precompute whose
    transfer (ρ kept out, ``[V, n²]`` or ``[V, C, n²]``: E = π t, channels averaged) is
    ``transfer``; warns about holes and the scale; returns ``[V, 3, n²]`` float64 and records
    ``meta['subsurface']``."""
    sp = check_term_spec(spec)
    for w in (check_closed(mesh), check_scale(mesh, sp["material"], sp["scale"])):
        if w:
            warnings.warn(w, stacklevel=3)
    t = transfer.to(torch.float64)
    t = t.mean(1) if t.ndim == 3 else t
    sub: dict[str, Any] = {}
    L = subsurface_term(mesh, t, sp["material"], sp["scale"], epsilon=sp["epsilon"], fresnel=sp["fresnel"],
                        spacing=sp["spacing"], run=dataclasses.replace(run, state_dir=sub_state(run, "subsurface")), meta=sub)
    meta["subsurface"] = sub
    return L


def sub_state(run: RunOptions, name: str):
    """The state directory of one pass of a two-pass precompute (under ``run.state_dir``)."""
    if run.state_dir is None:
        return None
    import os

    return os.path.join(os.fspath(run.state_dir), name)
