"""Spherical harmonic reflection maps (SHRM): Ramamoorthi 2002, chapter 5.

The reflected light field of a convex object of one isotropic BRDF under a distant environment,
as a function of the surface orientation and the view, with no per-vertex data:

    B(α, β, ω'o) = Σ_{p ≤ P_B} Σ_{|q| ≤ p} B_pq(α, β) y_pq(ω'o)                    (eq. 5.10)
    B_pq(α, β)   = Σ_{l ≤ F_B} Σ_m L_lm ρ_{l p |q|} D^l_mq(R_αβ)                   (eq. 5.9)
    B_lmpq       = L_lm ρ_{l p |q|}           (eq. 5.7 / 2.55 with Λ_l dropped, §5.6.2 step 2)

Frames and conventions (this module's, in the engine's real SH, graphics convention):

* (α, β) are the polar angles of the **axis** the BRDF is reparameterised by (§5.3.1): the
  reflected view R = 2(n·v)n - v for every model but the Lambertian, which keeps the normal.
  A map texel is the engine's ``latlong`` pixel (α = π(i+½)/H from +z, β = 2π(j+½)/W from +x
  towards +y).
* The local frame at (α, β) is R_αβ = Rz(β) Ry(α) (γ = 0, eq. 2.48): its columns are
  e'x = (cos α cos β, cos α sin β, -sin α), e'y = (-sin β, cos β, 0), e'z = the axis. ω'o (and
  ω'i) are the view (light) directions in that frame.
* D(R) is the engine's real rotation matrix, y(R s) = D(R) y(s) (:mod:`prt_torch.sh.rotation`),
  so the light in the local frame is D(R_αβ)ᵀ L, and B_pq = Σ_l ρ_{lp|q|} (D(R_αβ)ᵀ L)_lq.
* The BRDF transfer function ρ̂(ω'i, ω'o) = f_r cos θi of the reparameterised model is expanded
  as ρ̂ = Σ_{l,p,q} ρ_{l p |q|} y_lq(ω'i) y_pq(ω'o) (eq. 2.53 in real SH: isotropy couples only
  equal q, and the mirror symmetry makes the coefficient depend on |q|), with both ω'i and ω'o
  over the whole sphere (eq. 5.18). Radially symmetric models (Lambertian about n, Phong's
  reflection form about R) have ρ_l00 = √(4π) h_l from their zonal lobes (eq. 2.60, 3.37) and
  P_B = 0; the others are integrated by quadrature (eq. 5.22).

Orders: ``F_B`` and ``P_B`` are the thesis' maximum orders (l ≤ F_B, p ≤ P_B; bands = order + 1).
:func:`choose_orders` picks them from ε by eq. 5.18 (BRDF energy; §5.6.2: the smallest P at a
large F, then the smallest F), and reports the lighting error of eq. 5.16 and the conservative
residual bound of eq. 5.19 beside it.

Prefiltering (§5.6): :func:`prefilter_frequency` computes the maps B_pq(α, β) from L and ρ in
O(F_B P_B² S²) (eq. 5.23–5.24: a sum over l per row α, then a real Fourier series in β);
:func:`prefilter_angular` is the angular-space reference: for every output texel a sum of
L(ω) ρ̂ Ω over the light pixels inside the BRDF's cone (§5.6.3, O(W S_L²) per texel), vectorised
per map row. :func:`project_latlong` is step 1's separable SH transform of a lat-long light
(eq. 5.21). :class:`SHRM` holds the result, evaluates B for any normals and views (map lookup or
straight from the coefficients) and saves/loads it (``kind: "shrm"``).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from . import io
from ._checks import check_float, check_int, check_shape, check_unit_vectors
from .brdf import BRDF, from_spec as brdf_from_spec
from .transfer.transport import HORIZON_EPS
from .lighting import builtin_environment, list_builtin_environments, load_environment, load_light, parse_light_spec
from .sh import MAX_BANDS, band_factor, eval_sh, gauss_legendre, latlong_grid, lm_of, rotate, rotation_blocks

__all__ = [
    "SHRM",
    "ACCEPTED_BRDFS",
    "check_brdf",
    "is_radial",
    "rho_hat",
    "brdf_coefficients",
    "energy_table",
    "choose_orders",
    "light_energy",
    "residual_bound",
    "project_latlong",
    "latlong_angles",
    "prefilter_frequency",
    "prefilter_angular",
    "angular_cone",
    "local_frames",
    "reference_radiance",
    "estimate_memory",
    "build_shrm",
    "load_shrm",
    "DEFAULT_MAX_MEMORY",
    "CONVEX_PROBE_TOL",
]

ACCEPTED_BRDFS = ("isotropic BRDFs: lambertian, phong (either form), blinn_phong, microfacet, "
                  "ashikhmin_shirley with nu == nv, ward with ax == ay; one material (scalar parameters)")

#: Default bound (bytes) on the memory an SHRM computation may plan for (estimated before any work).
DEFAULT_MAX_MEMORY = 4 * 2**30

#: Largest orders :func:`choose_orders` tries before refusing an ε.
MAX_P = 16

#: Occluded fraction of the diffuse energy (``transfer.diffuse.probe_self_occlusion``) above which a
#: mesh counts as not convex for an SHRM, which ignores visibility (§5.3): warned about by ``prt render``
#: and the harness's convex section (the transfer precomputes' ``probe_tol``: a convex tessellation's
#: grazing rays stay below it).
CONVEX_PROBE_TOL = 1e-3


# ----------------------------------------------------------------------------------------
# BRDF side: the reparameterised transfer function and its coefficients ρ_lpq
# ----------------------------------------------------------------------------------------


def check_brdf(brdf: Any) -> BRDF:
    """The BRDF an SHRM accepts (a :class:`~prt_torch.brdf.BRDF` or a spec for ``brdf.from_spec``):
    isotropic (§5.3: the chapter covers isotropic BRDFs), one material. Raises ValueError naming
    the model, its parameters and what is accepted."""
    b = brdf_from_spec(brdf)
    if len(b.batch_shape) != 0:
        raise ValueError(f"brdf={b!r} has a batch of parameters {tuple(b.batch_shape)}; accepted: {ACCEPTED_BRDFS}")
    if not b.isotropic:
        raise ValueError(f"brdf={b!r} is anisotropic (an SHRM covers isotropic BRDFs only, Ramamoorthi 2002 §5.3); "
                         f"accepted: {ACCEPTED_BRDFS}")
    return b


def is_radial(brdf: BRDF) -> str | None:
    """The axis ("normal" or "reflection") when the cosine-weighted model is one radially symmetric
    lobe about it (Lambertian; Phong's reflection form with kd = 0), else None."""
    try:
        lobes = brdf.lobes(2)
    except ValueError:
        return None
    axes = {axis for axis, h in lobes if bool((h != 0).any())}
    return axes.pop() if len(axes) == 1 else None


def _profile(brdf: BRDF, cos_t: torch.Tensor) -> torch.Tensor:
    """Radially symmetric ρ̂ as a function of the cosine to its axis: ``[N] -> [N]`` float64
    (the model's full-sphere extension at wo = +z, whose reflection is +z)."""
    s = torch.sqrt((1 - cos_t * cos_t).clamp_min(0))
    wi = torch.stack([s, torch.zeros_like(s), cos_t], -1)
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand_as(wi)
    return brdf.extended(wi, wo).to(torch.float64)


def rho_hat(brdf: BRDF, wi: torch.Tensor, wo: torch.Tensor) -> torch.Tensor:
    """The reparameterised transfer function ρ̂(ω'i, ω'o) = f_r(wi, wo) max(n·wi, 0) with ω'i, ω'o
    in the frame of the BRDF's axis (§5.3.1).

    Radial models: the lobe profile of ω'i·z (no ω'o dependence). Others: the normal is the
    half vector of the axis and the view, n = (z + ω'o)/|z + ω'o| (R is v mirrored about n), and
    the model is evaluated in a frame whose third axis is n.

    Args: ``wi [..., 3]``, ``wo [..., 3]`` float64 unit vectors (broadcast). Returns ``[...]`` float64.
    """
    wi, wo = torch.broadcast_tensors(wi.to(torch.float64), wo.to(torch.float64))
    if is_radial(brdf):
        return _profile(brdf, wi[..., 2].clamp(-1, 1))
    n = wo + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    # tangent frame at n: t2 ⟂ (z, n) plane, t1 = t2 × n (right-handed: t1 × t2 = n)
    t2 = torch.cross(n, wo, dim=-1)
    bad = t2.norm(dim=-1, keepdim=True) < 1e-12  # wo along z: any tangent will do
    t2 = torch.where(bad, torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64).expand_as(t2), t2)
    t2 = t2 - (t2 * n).sum(-1, keepdim=True) * n
    t2 = t2 / t2.norm(dim=-1, keepdim=True)
    t1 = torch.cross(t2, n, dim=-1)

    def local(d):
        return torch.stack([(d * t1).sum(-1), (d * t2).sum(-1), (d * n).sum(-1)], -1)

    return brdf.cosine_weighted(local(wi), local(wo)).to(torch.float64)


def _k_table(theta: torch.Tensor, F: int, P: int) -> torch.Tensor:
    """K_lq(θ) = y_lq(θ, φ = 0) for q = 0..min(l, P): ``[N, F+1, P+1]`` float64 (zero for q > l);
    y_l,±q(θ, φ) = K_lq(θ) cos(qφ) / sin(qφ)."""
    d = torch.stack([torch.sin(theta), torch.zeros_like(theta), torch.cos(theta)], -1)
    Y = eval_sh(d, F + 1, check=False)
    K = torch.zeros(theta.shape[0], F + 1, P + 1, dtype=torch.float64)
    for q in range(min(P, F) + 1):  # ≤ P+1 columns
        ls = torch.arange(q, F + 1)
        K[:, ls, q] = Y[:, ls * (ls + 1) + q]
    return K


def brdf_coefficients(brdf: Any, F: int, P: int, *, n_theta: int | None = None, n_phi: int = 96,
                      n_view: int | None = None) -> tuple[torch.Tensor, float]:
    """BRDF coefficients ρ_{l p q} (q ≥ 0) and the total energy ∫∫ ρ̂² (eq. 5.17 / 5.18).

    Radial models (:func:`is_radial`): ρ_l00 = √(4π) h_l from the model's zonal lobes (eq. 2.60;
    Phong eq. 3.37, Lambertian eq. 4.11); energy 4π · 2π ∫ ρ̂(t)² dt by Gauss–Legendre split at
    t = 0 and near the lobe. Others, by quadrature of eq. 5.22 in real SH:

        ρ_lpq = c_q ∫∫ K_lq(θi) K_pq(θo) ĝ_q(θi, θo) sin θi sin θo dθi dθo,
        ĝ_q = ∫_0^{2π} ρ̂(θi, θo, φ) cos qφ dφ,   c_0 = 2π, c_q = π (q > 0),

    with θi on two Gauss–Legendre panels ([0, a] around the lobe, [a, π]), cos θo Gauss–Legendre
    on [-1, 1] and φ = φi - φo uniform (exact for trigonometric polynomials).

    Args:
        brdf: an isotropic model (:func:`check_brdf`); F, P: maximum orders l ≤ F, p ≤ P.
    Returns:
        (ρ ``[F+1, P+1, P+1]`` float64 indexed [l, p, |q|] (zero where |q| > min(l, p)),
        total energy ∫∫ ρ̂(ω'i, ω'o)² dω'i dω'o over both spheres, a float).
    """
    brdf = check_brdf(brdf)
    F = check_int("F", F, 0, MAX_BANDS - 1)
    P = check_int("P", P, 0, MAX_BANDS - 1)
    rho = torch.zeros(F + 1, P + 1, P + 1, dtype=torch.float64)
    if is_radial(brdf):
        axis, h = [(a, h) for a, h in brdf.lobes(F + 1) if bool((h != 0).any())][0]
        rho[:, 0, 0] = math.sqrt(4 * math.pi) * h.to(torch.float64)
        width = 1.0 / math.sqrt(1.0 + brdf.sharpness)
        c0 = math.cos(min(math.pi / 2, 8 * width))
        t = torch.cat([gauss_legendre(256, -1.0, 0.0)[0], gauss_legendre(512, 0.0, c0)[0], gauss_legendre(512, c0, 1.0)[0]])
        w = torch.cat([gauss_legendre(256, -1.0, 0.0)[1], gauss_legendre(512, 0.0, c0)[1], gauss_legendre(512, c0, 1.0)[1]])
        total = 4 * math.pi * 2 * math.pi * float((w * _profile(brdf, t) ** 2).sum())
        return rho, total
    width = 1.0 / math.sqrt(1.0 + brdf.sharpness)
    a = min(math.pi / 2, 8 * width)
    n_t = n_theta or max(48, F + 24)
    t1, w1 = gauss_legendre(n_t, 0.0, a)
    t2, w2 = gauss_legendre(n_t, a, math.pi)
    ti = torch.cat([t1, t2])
    wi_w = torch.cat([w1, w2]) * torch.sin(ti)
    n_v = n_view or max(40, 2 * P + 24)
    co, wo_w = gauss_legendre(n_v, -1.0, 1.0)
    to = torch.arccos(co)
    phi = torch.arange(n_phi, dtype=torch.float64) * (2 * math.pi / n_phi)
    si = torch.sin(ti)[:, None, None]
    wi = torch.stack(torch.broadcast_tensors(si * torch.cos(phi), si * torch.sin(phi), torch.cos(ti)[:, None, None]), -1)
    so = torch.sin(to)
    wo = torch.stack([so, torch.zeros_like(so), co], -1)[None, :, None, :]  # [1, n_v, 1, 3]
    g = rho_hat(brdf, wi.expand(-1, n_v, -1, -1), wo)  # [n_i, n_v, n_phi]
    dphi = 2 * math.pi / n_phi
    q = torch.arange(P + 1, dtype=torch.float64)
    ghat = torch.einsum("iok,kq->ioq", g, torch.cos(phi[:, None] * q[None, :])) * dphi  # [n_i, n_v, P+1]
    Ki = _k_table(ti, F, P) * wi_w[:, None, None]
    Ko = _k_table(to, P, P) * wo_w[:, None, None]
    cq = torch.where(q == 0, 2 * math.pi, math.pi).to(torch.float64)
    rho = torch.einsum("ilq,opq,ioq->lpq", Ki, Ko, ghat) * cq
    total = float((g * g).sum(-1).mul(dphi * 2 * math.pi).mul(wi_w[:, None] * wo_w[None, :]).sum())
    return rho, total


def energy_table(rho: torch.Tensor) -> torch.Tensor:
    """Captured BRDF energy E[F, P] = Σ_{l ≤ F} Σ_{p ≤ P} Σ_{|q| ≤ min(l,p)} ρ_lpq² (eq. 5.18's left
    side; q and -q both counted): ``[F+1, P+1, P+1] -> [F+1, P+1]`` float64, cumulative in both."""
    mult = torch.ones(rho.shape[-1], dtype=torch.float64)
    mult[1:] = 2.0
    per = (rho.to(torch.float64) ** 2 * mult).sum(-1)  # [F+1, P+1]
    return per.cumsum(0).cumsum(1)


def light_energy(light: Any, F: int) -> tuple[torch.Tensor, float]:
    """Lighting energy captured per order (eq. 5.15–5.16): for an environment (an object with
    ``image`` and ``solid_angles()``, e.g. :class:`~prt_torch.lighting.Environment`), the total is
    ∫ L² dω from its pixels and the coefficients come from its projection; for SH coefficients
    ``[C, n²]`` the total is the energy of the given coefficients (exact for band-limited lights).

    Returns (cumulative captured energy ``[F+1]`` float64, summed over channels, total ∫ L²)."""
    F = check_int("F", F, 0, MAX_BANDS - 1)
    if hasattr(light, "image") and hasattr(light, "solid_angles"):
        img = light.image.to(torch.float64)
        total = float((img * img * light.solid_angles()[..., None]).sum())
        L = light.project(F + 1)
    else:
        L = torch.as_tensor(light, dtype=torch.float64)
        total = float((L * L).sum())
        if L.shape[-1] < (F + 1) ** 2:
            L = torch.nn.functional.pad(L, (0, (F + 1) ** 2 - L.shape[-1]))
        L = L[..., : (F + 1) ** 2]
    l, _ = lm_of(F + 1)
    per = torch.zeros(F + 1, dtype=torch.float64).index_add_(0, l, (L * L).reshape(-1, L.shape[-1]).sum(0))
    return per.cumsum(0), total


def residual_bound(rho: torch.Tensor, rho_total: float, L: torch.Tensor, light_total: float, F: int, P: int) -> float:
    """Conservative error estimate of eq. 5.19 for orders (F, P):

        B_res = Λ²_{F+1} (ε_L L_tot)(ε_ρ ρ_tot),   ε_B ≤ B_res / (Σ_{l ≤ F} Λ_l² |L_lm ρ_lpq|² + B_res)

    with ε_L, ε_ρ the lighting and BRDF errors at (F, P). The thesis prints Λ_{F+1}; here the
    energies are of the coefficients Λ_l L_lm ρ_lpq of eq. 2.55, so Λ enters squared on both sides.
    ``L [C, ≥ (F+1)²]``. Returns ε_B (float)."""
    l, _ = lm_of(F + 1)
    Lf = L.to(torch.float64)
    Lf = torch.nn.functional.pad(Lf, (0, max(0, (F + 1) ** 2 - Lf.shape[-1])))[..., : (F + 1) ** 2]
    lam2 = band_factor(F + 2) ** 2
    E = energy_table(rho[: F + 1, : P + 1, : P + 1])
    eps_rho = max(0.0, 1 - float(E[F, P]) / rho_total) if rho_total > 0 else 0.0
    lcap = float((Lf * Lf).sum())
    eps_L = max(0.0, 1 - lcap / light_total) if light_total > 0 else 0.0
    mult = torch.ones(P + 1, dtype=torch.float64)
    mult[1:] = 2.0
    rho2 = (rho[: F + 1, : P + 1, : P + 1] ** 2 * mult).sum((1, 2))  # [F+1] Σ_pq ρ_lpq² per l (q ≤ l)
    cap = float(((Lf * Lf).sum(0) * (lam2[l] * rho2[l])).sum())
    res = float(lam2[F + 1]) * (eps_L * light_total) * (eps_rho * rho_total)
    return res / (cap + res) if cap + res > 0 else 0.0


def choose_orders(brdf: Any, epsilon: float, light: Any = None, *, F_max: int | None = None,
                  P_max: int = 6) -> tuple[int, int, dict]:
    """Orders (F_B, P_B) keeping 1 - ε of the BRDF energy (eq. 5.18; eq. 5.17 for radial models).

    §5.6.2: with the coefficients to large (F_max, P_max), the smallest P for which the energy at
    F_max reaches (1 - ε) ∫∫ρ̂², then the smallest F at that P. F_max starts from the lobe's
    sharpness and P_max at 6; both grow (to 127 and :data:`MAX_P`) until the energy is reached.
    When ``light`` is given (an environment or SH coefficients), the returned ``info`` also has
    the lighting error ε_L at F_B (eq. 5.16), the min-of-errors estimate min(ε_L, ε_ρ) and the
    residual bound of eq. 5.19 — the thesis' two accuracy estimates.

    Returns (F_B, P_B, info) with info: ``energy`` (1 - ε_ρ at the orders), ``eps_rho``,
    ``energy_by_P`` (fraction at F_max for P = 0..P_max), ``F_max``, ``P_max``, ``reason`` and,
    with a light, ``eps_light``, ``eps_min``, ``eps_bound``.
    """
    eps = check_float("epsilon", epsilon, 0.0, 1.0, lo_open=True, hi_open=True)
    brdf = check_brdf(brdf)
    radial = is_radial(brdf)
    F_cap = MAX_BANDS - 1
    F_try = F_max or min(F_cap, int(math.ceil(6 * math.sqrt(1.0 + brdf.sharpness))) + 8)
    P_try = 0 if radial else check_int("P_max", P_max, 0, MAX_P)
    while True:
        rho, total = brdf_coefficients(brdf, F_try, P_try)
        E = energy_table(rho) / total
        ok_P = torch.nonzero(E[-1] >= 1 - eps)
        if ok_P.numel():
            break
        if F_try >= F_cap and (radial or P_try >= MAX_P):
            raise ValueError(
                f"epsilon={eps:g} needs more than orders F={F_cap}, P={0 if radial else MAX_P} for {brdf!r} "
                f"(they keep {float(E[-1, -1]):.6f} of the BRDF energy); accepted: a larger epsilon")
        # grow the order whose step gains more (the last order along each axis)
        gain_F = float(E[-1, -1] - E[max(0, F_try - 4), -1])
        gain_P = float(E[-1, -1] - E[-1, -2]) if E.shape[1] > 1 else 0.0
        if not radial and P_try < MAX_P and (gain_P >= gain_F or F_try >= F_cap):
            P_try = min(MAX_P, P_try + 2)
        else:
            F_try = min(F_cap, int(F_try * 1.5) + 2)
    P_B = int(ok_P[0])
    F_B = int(torch.nonzero(E[:, P_B] >= 1 - eps)[0])
    info: dict = {
        "epsilon": eps,
        "energy": float(E[F_B, P_B]),
        "eps_rho": 1 - float(E[F_B, P_B]),
        "energy_by_P": [float(v) for v in E[-1]],
        "F_max": F_try,
        "P_max": int(E.shape[1] - 1),
        "radial": radial,
        "axis": radial or "reflection",
        "rule": "eq. 5.17" if radial else "eq. 5.18",
    }
    why = (f"F_B={F_B}, P_B={P_B}: " + (
        f"radially symmetric about the {radial} (P_B = 0); smallest F keeping {1 - eps:g} of the BRDF energy "
        f"(eq. 5.17): {info['energy']:.4f}" if radial else
        f"smallest P keeping {1 - eps:g} of the BRDF energy at F={F_try} (eq. 5.18: "
        + ", ".join(f"P={p}: {v:.4f}" for p, v in enumerate(info["energy_by_P"])) + f"), then smallest F at that P: "
        f"{info['energy']:.4f}"))
    if light is not None:
        cum, ltot = light_energy(light, F_B)
        eps_L = max(0.0, 1 - float(cum[F_B]) / ltot) if ltot > 0 else 0.0
        Lc = light.project(F_B + 1) if hasattr(light, "project") else torch.as_tensor(light, dtype=torch.float64)
        info["eps_light"] = eps_L
        info["eps_min"] = min(eps_L, info["eps_rho"])
        info["eps_bound"] = residual_bound(rho, total, Lc, ltot, F_B, P_B)
        why += (f"; lighting error at F_B (eq. 5.16) {eps_L:.4f}, min-of-errors estimate {info['eps_min']:.4f}, "
                f"residual bound (eq. 5.19) {info['eps_bound']:.4f}")
    info["reason"] = why
    return F_B, P_B, info


# ----------------------------------------------------------------------------------------
# Lighting side and the two prefilters
# ----------------------------------------------------------------------------------------


def latlong_angles(height: int, width: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre polar angles of the engine's ``latlong`` grid: α = π(i+½)/H ``[H]`` and
    β = 2π(j+½)/W ``[W]``, float64."""
    height = check_int("height", height, 1)
    width = check_int("width", width, 1)
    a = (torch.arange(height, dtype=torch.float64) + 0.5) * (math.pi / height)
    b = (torch.arange(width, dtype=torch.float64) + 0.5) * (2 * math.pi / width)
    return a, b


def _trig(beta: torch.Tensor, F: int) -> torch.Tensor:
    """Real Fourier basis in β: rows [1, cos β, sin β, cos 2β, sin 2β, ...], ``[2F+1, W]``."""
    k = torch.arange(1, F + 1, dtype=torch.float64)[:, None]
    c, s = torch.cos(k * beta[None]), torch.sin(k * beta[None])
    rows = torch.stack([c, s], 1).reshape(2 * F, beta.shape[0])  # F = 0: none (the constant row alone)
    return torch.cat([torch.ones(1, beta.shape[0], dtype=torch.float64), rows])


def _m_slots(F: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat SH index of (l, m) in a padded [F+1, 2F+1] (l, m + F) layout and its validity mask."""
    l = torch.arange(F + 1)[:, None]
    m = torch.arange(-F, F + 1)[None, :]
    ok = m.abs() <= l
    return torch.where(ok, l * (l + 1) + m, torch.zeros_like(l * m)), ok


def project_latlong(image: torch.Tensor, bands: int) -> torch.Tensor:
    """SH coefficients of a lat-long image by the separable transform of eq. 5.21, O(F S²):
    a real Fourier sum over φ per row, then a sum over rows against K_lm(θ) (pixel-centre values
    times the exact pixel solid angles Δφ (cos θ0 - cos θ1), as ``Environment.project``).

    Args: ``image [H, W, C]`` (engine ``latlong`` grid, any W), bands n. Returns ``[C, n²]`` float64.
    """
    check_shape("image", image, ndim=3)
    bands = check_int("bands", bands, 1, MAX_BANDS)
    H, W, C = image.shape
    F = bands - 1
    theta, phi = latlong_angles(H, W)
    wrow = latlong_grid(H, W)[1][:, 0]  # [H] solid angle of a pixel in each row
    tr = _trig(phi, F)  # [2F+1, W]
    Lm = torch.einsum("hwc,kw->chk", image.to(torch.float64), tr) * wrow[None, :, None]  # [C, H, 2F+1]
    K = _k_table(theta, F, F)  # [H, l, |m|], y_l,±m = K cos / sin
    l_all, m_all = lm_of(bands)
    # harmonic row of each (l, m): m = 0 -> 0, m > 0 -> cos mφ (2m-1), m < 0 -> sin |m|φ (2|m|)
    hrow = torch.where(m_all == 0, 0, torch.where(m_all > 0, 2 * m_all - 1, 2 * (-m_all)))
    Kf = K[:, l_all, m_all.abs()]  # [H, n²]
    return torch.einsum("chn,hn->cn", Lm[:, :, hrow], Kf)


def _rho_matrix(rho: torch.Tensor, F: int, P: int) -> torch.Tensor:
    """M[(l, m), (p, q)] = ρ_{l p |q|} if m = q (and |q| ≤ min(l, p)), else 0: ``[(F+1)², (P+1)²]``
    float64, so that B_pq = Σ_lm M (Dᵀ L)_lm."""
    lF, mF = lm_of(F + 1)
    lP, mP = lm_of(P + 1)
    same = (mF[:, None] == mP[None, :]) & (mF[:, None].abs() <= torch.minimum(lF[:, None], lP[None, :]))
    vals = rho[: F + 1, : P + 1][lF[:, None], lP[None, :], mP.abs()[None, :]]
    return torch.where(same, vals.to(torch.float64), torch.zeros((), dtype=torch.float64))


def _ry(alpha: torch.Tensor) -> torch.Tensor:
    """Rotations about +y by α: ``[N] -> [N, 3, 3]`` float64 (maps +z to (sin α, 0, cos α))."""
    c, s = torch.cos(alpha), torch.sin(alpha)
    z, o = torch.zeros_like(alpha), torch.ones_like(alpha)
    return torch.stack([torch.stack([c, z, s], -1), torch.stack([z, o, z], -1), torch.stack([-s, z, c], -1)], -2)


def prefilter_frequency(L: torch.Tensor, rho: torch.Tensor, F: int, P: int, height: int, width: int | None = None,
                        row_chunk: int = 32) -> torch.Tensor:
    """Frequency-space prefiltering, steps 2–3 of §5.6.2: the local SHRM maps B_pq(α, β).

    With R_αβ = Rz(β) Ry(α), (D(R_αβ)ᵀ L)_lq = Σ_m d^l_mq(α) G_lm(β) where G(β) = D(Rz β)ᵀ L is,
    per band, L_lm cos(|m|β) + sgn(m) L_l,-m sin(|m|β) (L_l0 for m = 0). So (eq. 5.23–5.24):

        Y_kpq(α) = Σ_l ρ_{lp|q|} Σ_{m = ±k} d^l_mq(α) L'_lm        O(F_B² P_B²) per row  (eq. 5.24a)
        B_pq(α, β) = Σ_k Y_kpq(α) · [1, cos kβ, sin kβ]           O(F_B P_B²) per texel (eq. 5.24b)

    d^l(α) are the engine's rotation blocks of Ry(α) (:func:`prt_torch.sh.rotation_blocks`),
    built ``row_chunk`` rows at a time; for P = 0 only column q = 0 is needed, d^l_m0(α) =
    Λ_l y_lm(α, 0) (eq. 2.35), and no blocks are built.

    Args:
        L: ``[C, ≥ (F+1)²]`` light coefficients (truncated to F); rho: ``[≥ F+1, ≥ P+1, ≥ P+1]``.
        height, width: output lat-long grid (width defaults to 2·height, the engine's layout).
    Returns:
        maps ``[C, (P+1)², H, W]`` float64: B_pq at the texel centres (:func:`latlong_angles`).
    """
    F = check_int("F", F, 0, MAX_BANDS - 1)
    P = check_int("P", P, 0, MAX_BANDS - 1)
    height = check_int("height", height, 1)
    width = 2 * height if width is None else check_int("width", width, 1)
    nF, nP = (F + 1) ** 2, (P + 1) ** 2
    if L.shape[-1] < nF:
        raise ValueError(f"L has {L.shape[-1]} coefficients; accepted: at least (F+1)² = {nF} for F={F}")
    Lf = L[..., :nF].to(torch.float64)
    C = Lf.shape[0]
    alpha, beta = latlong_angles(height, width)
    idx, ok = _m_slots(F)
    okf = ok.to(torch.float64)
    Lpad = Lf[:, idx] * okf  # [C, F+1, 2F+1] (l, m+F)
    # L' per harmonic: cos part uses L_lm at slot m; sin part uses sgn(m) L_l,-m at slot m
    sgn = torch.sign(torch.arange(-F, F + 1, dtype=torch.float64))
    Lsin = Lpad.flip(-1) * sgn  # slot m holds sgn(m) L_l,-m
    rho = rho.to(torch.float64)
    lP, mP = lm_of(P + 1)
    Ys = []
    for a0 in range(0, height, row_chunk):  # chunks of rows bound the rotation blocks' memory
        al = alpha[a0 : a0 + row_chunk]
        h = al.shape[0]
        if P == 0:
            d_al = torch.stack([torch.sin(al), torch.zeros_like(al), torch.cos(al)], -1)
            lF, _ = lm_of(F + 1)
            col = eval_sh(d_al, F + 1, check=False) * band_factor(F + 1)[lF]  # d^l_m0(α) [h, nF]
            A = (col * rho[lF, 0, 0])[:, :, None]  # [h, nF, 1]: d^l_m0(α) ρ_l00
        else:
            blocks = rotation_blocks(_ry(al), F + 1)
            # A[α, (l, m), (p, q)] = d^l_{m q}(α) ρ_{l p |q|}  (q ≤ min(l, p))
            A = torch.zeros(h, nF, nP, dtype=torch.float64)
            for l, blk in enumerate(blocks):  # one batched gather per band (F+1 iterations)
                rows = torch.arange(l * l, (l + 1) ** 2)
                qs = mP.clamp(-l, l) + l
                r_l = torch.where(mP.abs() <= torch.clamp(lP, max=l), rho[l, lP.clamp(max=rho.shape[1] - 1), mP.abs()],
                                  torch.zeros((), dtype=torch.float64))
                A[:, rows, :] = blk[:, :, qs].to(torch.float64) * r_l
        Apad = A[:, idx, :] * okf[None, :, :, None]  # [h, F+1, 2F+1, nP]
        Yc = torch.einsum("clm,hlmj->hcmj", Lpad, Apad)  # per slot m: Σ_l
        Ysn = torch.einsum("clm,hlmj->hcmj", Lsin, Apad)
        # harmonic k: cos part Σ_{m=±k} Yc, sin part Σ_{m=±k} Ysn
        Y = torch.zeros(h, C, 2 * F + 1, nP, dtype=torch.float64)
        Y[:, :, 0] = Yc[:, :, F]
        if F > 0:
            Y[:, :, 1::2] = Yc[:, :, F + 1 :] + Yc[:, :, :F].flip(2)
            Y[:, :, 2::2] = Ysn[:, :, F + 1 :] + Ysn[:, :, :F].flip(2)
        Ys.append(Y)
    Y = torch.cat(Ys)  # [H, C, 2F+1, nP]
    tr = _trig(beta, F)  # [2F+1, W]
    maps = torch.einsum("hckj,kw->cjhw", Y, tr)
    return maps


def local_frames(axis_dirs: torch.Tensor) -> torch.Tensor:
    """Frames R_αβ = Rz(β) Ry(α) of axis directions: ``[..., 3] -> [..., 3, 3]`` float64 whose
    columns are e'x, e'y, e'z = the axis (module docstring); β = atan2(y, x), so the pole gets β = 0."""
    d = axis_dirs.to(torch.float64)
    alpha = torch.arccos(d[..., 2].clamp(-1, 1))
    beta = torch.atan2(d[..., 1], d[..., 0])
    ca, sa, cb, sb = torch.cos(alpha), torch.sin(alpha), torch.cos(beta), torch.sin(beta)
    ex = torch.stack([ca * cb, ca * sb, -sa], -1)
    ey = torch.stack([-sb, cb, torch.zeros_like(sb)], -1)
    ez = torch.stack([sa * cb, sa * sb, ca], -1)
    return torch.stack([ex, ey, ez], -1)


def angular_cone(brdf: BRDF, epsilon: float) -> float:
    """Half-angle θ* about the axis holding 1 - ε of the lobe (§5.6.4, eq. 5.30). Phong reflection
    form: cos θ* = ε^{1/(s+1)}; microfacet: θh ≤ σ√(-ln ε) with θh ≥ θ'i/2 to first order (eq. 3.52),
    so θ* = 2σ√(-ln ε); every other model: the whole sphere (π)."""
    eps = check_float("epsilon", epsilon, 0.0, 1.0, lo_open=True, hi_open=True)
    name = brdf.name
    if name == "phong" and is_radial(brdf) == "reflection":
        return math.acos(eps ** (1.0 / (float(brdf.s) + 1.0)))
    if name == "microfacet":
        return min(math.pi, 2 * float(brdf.sigma) * math.sqrt(-math.log(eps)))
    return math.pi


def prefilter_angular(image: torch.Tensor, brdf: Any, height: int, views: torch.Tensor | None = None, *,
                      cone: float = math.pi) -> torch.Tensor:
    """Angular-space prefiltering (§5.6.3): per output texel the integral of L(ω) ρ̂(ω'i, ω'o) over
    the light pixels inside the cone θ'i ≤ ``cone`` about the texel's axis, for each local view.

        B(α, β; ω'o) = Σ_{pixels a, b: θ'i ≤ θ*} L_ab ρ̂(R_αβᵀ ω_ab, ω'o) Ω_ab,   O(W S_L²) per texel.

    On a lat-long grid whose output width equals the light's width, shifting β by one column
    shifts the light by one column, so each output row has one table of taps (light row, column
    offset, weight per view), and the row is a gathered sum over taps for all its columns at once:
    the loop is over output rows only (H iterations), every other axis batched.

    Args:
        image: light ``[H_L, W, C]`` on the engine's lat-long grid (pixel-centre radiance).
        brdf: an isotropic model; ``views`` ``[V, 3]`` local view directions ω'o (default: one
            view along the axis, the only one radial models need).
        height: output rows (the output width is the light's W).
        cone: half-angle of the truncation (:func:`angular_cone`); π integrates every pixel.
    Returns:
        ``[V, C, height, W]`` float64 explicit reflection maps.
    """
    brdf = check_brdf(brdf)
    check_shape("image", image, ndim=3)
    HL, W, C = image.shape
    height = check_int("height", height, 1)
    views = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64) if views is None else views.to(torch.float64)
    check_shape("views", views, ndim=2, last=(3,))
    V = views.shape[0]
    dirs, om = latlong_grid(HL, W)  # pixel centres [HL, W, 3], exact solid angles
    omega = om[:, 0]
    alpha, beta = latlong_angles(height, W)
    Lflat = image.to(torch.float64).reshape(HL * W, C)
    cos_cone = math.cos(cone)
    cols = torch.arange(W)
    out = torch.zeros(V, C, height, W, dtype=torch.float64)
    radial = is_radial(brdf) is not None
    for i in range(height):  # one tap table per output row; everything else is batched
        R = local_frames(torch.stack([torch.sin(alpha[i]) * torch.cos(beta[0]), torch.sin(alpha[i]) * torch.sin(beta[0]),
                                      torch.cos(alpha[i])]))
        loc = dirs @ R  # [HL, W, 3] local ω'i for output column 0
        sel = loc[..., 2] >= cos_cone
        a_idx, b_idx = torch.nonzero(sel, as_tuple=True)
        if a_idx.numel() == 0:
            continue
        wi = loc[a_idx, b_idx]  # [T, 3]
        if radial:
            k = rho_hat(brdf, wi, views[:1].expand_as(wi))[:, None].expand(-1, V)
        else:
            k = rho_hat(brdf, wi[:, None, :], views[None, :, :])  # [T, V]
        k = k * omega[a_idx][:, None]
        # light column for output column j: b + j (the light pixel at column b for j = 0)
        gidx = a_idx[:, None] * W + (b_idx[:, None] + cols[None, :]) % W  # [T, W]
        vals = Lflat[gidx]  # [T, W, C]
        out[:, :, i, :] = torch.einsum("tv,twc->vcw", k, vals)
    return out


def reference_radiance(brdf: Any, dirs: torch.Tensor, light: torch.Tensor, normals: torch.Tensor, views: torch.Tensor,
                       chunk: int = 64) -> torch.Tensor:
    """Angular-space reference for a convex surface point (eq. 5.1 with no visibility): per point,
    Σ_k light_k f_r(ω_k, v) max(n·ω_k, 0) over a quadrature of the sphere, in a tangent frame of the
    point's normal (any: the model is isotropic) — the BRDF's own definition, nothing of the SHRM.

    Args:
        brdf: an isotropic model; dirs: ``[Q, 3]`` quadrature directions; light: ``[Q, C]`` radiance
            times quadrature weight (e.g. an environment's pixels times their solid angles);
        normals: ``[N, 3]`` unit; views: ``[N, 3]`` or ``[3]`` unit, towards the viewer.
    Returns: ``[N, C]`` float64 (``chunk`` points at a time).
    """
    brdf = check_brdf(brdf)
    n = normals.to(torch.float64)
    v = (views.expand_as(normals) if views.ndim == 1 else views).to(torch.float64)
    helper = torch.tensor([0.31, 0.17, 0.93], dtype=torch.float64).expand_as(n)
    t = torch.linalg.cross(n, helper)
    t = t / t.norm(dim=-1, keepdim=True)
    fr = torch.stack([t, torch.linalg.cross(n, t), n], -2)  # rows: tangent, bitangent, normal
    d = dirs.to(torch.float64)
    Lw = light.to(torch.float64)
    out = torch.zeros(n.shape[0], Lw.shape[1], dtype=torch.float64)
    for a in range(0, n.shape[0], chunk):  # chunks bound the [chunk, Q] kernel
        f_ = fr[a : a + chunk]
        wi = torch.einsum("vij,qj->vqi", f_, d)
        wo = torch.einsum("vij,vj->vi", f_, v[a : a + chunk])[:, None, :].expand_as(wi)
        out[a : a + chunk] = brdf.cosine_weighted(wi, wo) @ Lw
    return out


# ----------------------------------------------------------------------------------------
# The SHRM object
# ----------------------------------------------------------------------------------------


def estimate_memory(F: int, P: int, height: int, width: int, channels: int = 3, row_chunk: int = 32) -> int:
    """Bytes an SHRM computation plans for (float64 working set), estimated before any work:
    the maps (C (P+1)² H W), the per-row sums (H C (2F+1) (P+1)²), one chunk of rotation
    blocks and padded row matrices (row_chunk · (F+1)(2F+1)(P+1)² and Σ(2l+1)²), the BRDF
    quadrature grid and the lighting's Fourier rows."""
    nP = (P + 1) ** 2
    maps = channels * nP * height * width * 8 * 2  # the einsum output and the float32/64 copies
    rows = height * channels * (2 * F + 1) * nP * 8 * 3
    chunk = min(row_chunk, height) * ((F + 1) * (2 * F + 1) * nP * 8 * 2
                                      + sum((2 * l + 1) ** 2 for l in range(F + 1)) * 8 * (2 if P else 0)
                                      + channels * (2 * F + 1) * nP * 8 * 2)
    quad = 2 * max(48, F + 24) * max(40, 2 * P + 24) * 96 * 8 * 12
    return int(maps + rows + chunk + quad)


@dataclass
class SHRM:
    """A spherical harmonic reflection map (Ramamoorthi 2002 §5.4).

    Attributes:
        light: ``[C, (F_B+1)²]`` float64 SH coefficients L_lm of the environment.
        rho: ``[F_B+1, P_B+1, P_B+1]`` float64 BRDF coefficients ρ_{l p |q|}.
        F_B, P_B: maximum orders (l ≤ F_B, p ≤ P_B; P_B may exceed F_B, ρ_lpq needs |q| ≤ min(l, p)).
        axis: ``"reflection"`` (R = 2(n·v)n - v) or ``"normal"`` (Lambertian).
        maps: ``[C, (P_B+1)², H, W]`` float32 local SHRM B_pq(α, β) on the lat-long grid, or None.
        meta: JSON-able provenance (brdf, light, ε, energy, reason, timings).
    """

    light: torch.Tensor
    rho: torch.Tensor
    F_B: int
    P_B: int
    axis: str = "reflection"
    maps: torch.Tensor | None = None
    meta: dict = field(default_factory=dict)

    def __post_init__(self):
        """The light to exactly (F_B+1)² coefficients (missing bands are zero)."""
        L = torch.as_tensor(self.light, dtype=torch.float64)
        nF = (self.F_B + 1) ** 2
        self.light = torch.nn.functional.pad(L, (0, max(0, nF - L.shape[-1])))[..., :nF]

    @property
    def coefficients(self) -> torch.Tensor:
        """B_lmpq = L_lm ρ_{l p |q|} (eq. 5.7 without Λ_l, §5.6.2 step 2): ``[C, (F_B+1)², (P_B+1)²]``
        float64, zero where q ≠ m or |q| > min(l, p)."""
        M = _rho_matrix(self.rho, self.F_B, self.P_B)
        return self.light[:, : (self.F_B + 1) ** 2, None].to(torch.float64) * M[None]

    def prefilter(self, height: int = 64, width: int | None = None) -> "SHRM":
        """Compute the maps by :func:`prefilter_frequency` (stored float32); returns self."""
        self.maps = prefilter_frequency(self.light, self.rho, self.F_B, self.P_B, height, width).to(torch.float32)
        return self

    def explicit_maps(self, views: torch.Tensor) -> torch.Tensor:
        """Explicit reflection maps for local views ω'o (eq. 5.10 at fixed ω'o, O(P_B²) per texel):
        ``views [V, 3]`` -> ``[V, C, H, W]`` (dtype of the maps)."""
        if self.maps is None:
            raise ValueError("this SHRM has no maps; accepted: call prefilter(height) first")
        check_unit_vectors("views", views)
        y = eval_sh(views.to(self.maps.dtype), self.P_B + 1)  # [V, nP]
        return torch.einsum("vj,cjhw->vchw", y, self.maps)

    def axes(self, normals: torch.Tensor, views: torch.Tensor) -> torch.Tensor:
        """The parameterising axis per point: R = 2(n·v)n - v, or n for ``axis == "normal"``."""
        if self.axis == "normal":
            return normals
        return 2 * (normals * views).sum(-1, keepdim=True) * normals - views

    def view_terms(self, normals: torch.Tensor, views: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """What a point's view contributes (eq. 5.3, 5.10): its axis (R or n, unit), its frame
        R_αβ (:func:`local_frames`) and the SH weights y_pq(ω'o) of ω'o = R_αβᵀ v, zero where the
        point faces away (n·v ≤ ``transport.HORIZON_EPS``, as the glossy PRT relights: a view in the tangent
        plane, at float64 rounding of either sign, counts as away). ``normals [N, 3]``, ``views [N, 3]`` or ``[3]`` ->
        (``[N, 3]``, ``[N, 3, 3]``, ``[N, (P_B+1)²]``) float64."""
        check_unit_vectors("normals", normals)
        views = views.expand_as(normals) if views.ndim == 1 else views
        check_unit_vectors("views", views)
        n = normals.to(torch.float64)
        v = views.to(torch.float64)
        ax = self.axes(n, v)
        ax = ax / ax.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        Rf = local_frames(ax)  # [N, 3, 3], columns e'x, e'y, e'z
        wo = (v[:, :, None] * Rf).sum(1)  # ω'o = Rᵀ v  [N, 3]
        wo = wo / wo.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        y = eval_sh(wo, self.P_B + 1, check=False)  # [N, nP]
        facing = (n * v).sum(-1) > HORIZON_EPS  # as the glossy PRT it is compared with (relight._above)
        return ax, Rf, torch.where(facing[:, None], y, torch.zeros((), dtype=torch.float64))

    def radiance(self, normals: torch.Tensor, views: torch.Tensor, method: str = "map", chunk: int = 1024,
                 clamp: bool = False) -> torch.Tensor:
        """Reflected radiance B for surface normals and view directions (eq. 5.10, 5.3).

        ω'o = R_αβᵀ v in the frame of the point's axis (:meth:`view_terms`), then
        B = Σ_pq B_pq(α, β) y_pq(ω'o) with B_pq either bilinearly interpolated from the maps
        (``method="map"``: the rendering path, wrap-around in β) or summed from the coefficients
        (``method="coeffs"``: eq. 5.9 with the rotation blocks of each point's frame, exact up to
        the orders; ``chunk`` points at a time). Points facing away (n·v ≤ ``transport.HORIZON_EPS``) get 0.

        ``clamp``: max(B, 0). The truncated series rings below zero where the true radiance is
        small (studio light, microfacet σ = 0.3: 17% of random surface points at ε = 0.03, down to
        −0.17 for a peak of 4.5; reports/benchmarks/shrm_grazing.md); radiance is never negative,
        so the clamped value is never farther from the true one than the series (its squared error
        there fell 1–3% in that measurement). The renderer clamps by default; the series itself,
        unclamped, is what the ε of eq. 5.18 bounds.

        Args: ``normals [N, 3]``, ``views [N, 3]`` or ``[3]`` (towards the viewer), unit, float.
        Returns: ``[N, C]`` in the dtype of ``normals`` (float64 computation).
        """
        if method not in ("map", "coeffs"):
            raise ValueError(f"method={method!r}; accepted: 'map', 'coeffs'")
        ax, Rf, y = self.view_terms(normals, views)
        if method == "map":
            Bpq = self._lookup(ax)
        else:
            M = _rho_matrix(self.rho, self.F_B, self.P_B)
            Lf = self.light[:, : (self.F_B + 1) ** 2].to(torch.float64)
            parts = []
            for s0 in range(0, ax.shape[0], chunk):  # bounded memory: blocks are O(F³) per point
                Fr = Rf[s0 : s0 + chunk].transpose(1, 2)  # rows e'x, e'y, e'z: D(Rᵀ) L = local light
                G = rotate(Lf[None], Fr[:, None])  # [n, C, nF]
                parts.append(G @ M)
            Bpq = torch.cat(parts) if parts else torch.zeros(0, Lf.shape[0], M.shape[1], dtype=torch.float64)
        out = (Bpq * y[:, None, :]).sum(-1)
        return (out.clamp_min(0) if clamp else out).to(normals.dtype)

    def global_maps(self) -> torch.Tensor:
        """The global SHRM B̂_pq(α, β) (eq. 5.11–5.14), for a distant viewer: at every texel the local
        coefficients B_p turned into the world frame, B̂_p = D^p(R_αβ) B_p — eq. 5.14's
        Σ_s D^p_sq(−α) e^{−iqβ} B_ps in the engine's real SH, since y(R_αβᵀ v) = D(R_αβ)ᵀ y(v) — so
        that B = Σ_pq B̂_pq(α, β) y_pq(v) with the world view v itself (eq. 5.11).
        Returns ``[C, (P_B+1)², H, W]`` float32 (float64 rotation)."""
        if self.maps is None:
            raise ValueError("this SHRM has no maps; accepted: call prefilter(height) first")
        C, nP, H, W = self.maps.shape
        a, b = latlong_angles(H, W)
        ax = torch.stack([torch.sin(a)[:, None] * torch.cos(b)[None], torch.sin(a)[:, None] * torch.sin(b)[None],
                          torch.cos(a)[:, None].expand(H, W)], -1)  # texel-centre axes [H, W, 3]
        Rf = local_frames(ax)  # [H, W, 3, 3], columns e'x, e'y, e'z: R_αβ
        B = self.maps.to(torch.float64).permute(2, 3, 0, 1)  # [H, W, C, nP]
        return rotate(B, Rf[:, :, None]).permute(2, 3, 0, 1).to(torch.float32)

    def reflection_map(self, view: torch.Tensor, global_maps: torch.Tensor | None = None) -> torch.Tensor:
        """The dynamic reflection map of one distant view (eq. 5.11, §5.7.5): Σ_pq B̂_pq(α, β) y_pq(v)
        at every texel, ``[C, H, W]`` float32 — a point with normal n then reflects B at the texel of
        its axis R = 2(n·v)n − v (:meth:`radiance_distant`). ``view [3]`` unit, towards the viewer;
        ``global_maps`` from :meth:`global_maps` (computed when None)."""
        check_unit_vectors("view", view.reshape(1, 3))
        G = self.global_maps() if global_maps is None else global_maps
        y = eval_sh(view.reshape(1, 3).to(torch.float64), self.P_B + 1)[0]
        return torch.einsum("j,cjhw->chw", y, G.to(torch.float64)).to(torch.float32)

    def radiance_distant(self, normals: torch.Tensor, view: torch.Tensor, reflection_map: torch.Tensor | None = None,
                         clamp: bool = False) -> torch.Tensor:
        """Reflected radiance for a distant viewer (one view ``[3]`` for every point) from the
        reflection map of that view (:meth:`reflection_map`, eq. 5.11): a bilinear lookup at each
        point's axis (R, or n for a Lambertian SHRM), 0 where n·v ≤ ``transport.HORIZON_EPS``, ``clamp`` as in :meth:`radiance`.
        ``normals [N, 3]`` unit -> ``[N, C]`` in the dtype of ``normals``."""
        check_unit_vectors("normals", normals)
        v = view.reshape(1, 3).to(torch.float64)
        n = normals.to(torch.float64)
        E = self.reflection_map(view) if reflection_map is None else reflection_map
        ax = self.axes(n, v.expand_as(n))
        ax = ax / ax.norm(dim=-1, keepdim=True).clamp_min(1e-300)
        out = self._lookup(ax, E[:, None])[..., 0]
        out = torch.where(((n * v).sum(-1) > HORIZON_EPS)[:, None], out, torch.zeros((), dtype=torch.float64))
        return (out.clamp_min(0) if clamp else out).to(normals.dtype)

    def _lookup(self, dirs: torch.Tensor, maps: torch.Tensor | None = None) -> torch.Tensor:
        """Bilinear lookup of ``maps`` (default: the SHRM's, ``[C, nP, H, W]``) at axis directions
        ``[N, 3]`` -> ``[N, C, nP]`` float64."""
        if maps is None and self.maps is None:
            raise ValueError("method='map' needs maps; accepted: call prefilter(height) first, or method='coeffs'")
        maps = self.maps if maps is None else maps
        C, nP, H, W = maps.shape
        alpha = torch.arccos(dirs[:, 2].clamp(-1, 1))
        beta = torch.remainder(torch.atan2(dirs[:, 1], dirs[:, 0]), 2 * math.pi)
        fy = (alpha * (H / math.pi) - 0.5).clamp(0, H - 1)
        fx = beta * (W / (2 * math.pi)) - 0.5
        y0 = fy.floor().long().clamp(max=H - 1)
        y1 = (y0 + 1).clamp(max=H - 1)
        x0f = fx.floor()
        x0 = torch.remainder(x0f.long(), W)
        x1 = torch.remainder(x0 + 1, W)
        ty = (fy - y0.to(fy.dtype))[:, None, None]
        tx = (fx - x0f)[:, None, None]
        m = maps.to(torch.float64).permute(2, 3, 0, 1)  # [H, W, C, nP]
        return ((1 - ty) * ((1 - tx) * m[y0, x0] + tx * m[y0, x1]) + ty * ((1 - tx) * m[y1, x0] + tx * m[y1, x1]))

    # -- files ---------------------------------------------------------------------------
    def save(self, path, overwrite: bool = False):
        """Write a ``.prt`` file (``kind: "shrm"``; tensors ``light``, ``rho`` and ``maps`` when
        present; atomic, :func:`prt_torch.io.save`). Returns the path."""
        tensors = {"light": self.light.to(torch.float64), "rho": self.rho.to(torch.float64)}
        if self.maps is not None:
            tensors["maps"] = self.maps.to(torch.float32)
        meta = dict(self.meta, F_B=self.F_B, P_B=self.P_B, axis=self.axis,
                    convention="Ramamoorthi 2002 ch. 5 (local SHRM, eq. 5.9-5.10); real SH, graphics convention, "
                               "index l(l+1)+m; maps on the latlong grid, frame R = Rz(beta) Ry(alpha)")
        return io.save(path, tensors, kind="shrm", meta=meta, overwrite=overwrite)


def _resolve_light(light: Any) -> Any:
    """A built-in environment name or an image file -> its Environment (pixels give eq. 5.15's
    total); analytic specs (str or dict), environments and coefficient tensors pass through."""
    if isinstance(light, str) and light in list_builtin_environments():
        return builtin_environment(light)
    if isinstance(light, (str, os.PathLike)) and (not isinstance(light, str) or parse_light_spec(light) is None):
        if "{face}" not in str(light) and not Path(light).exists():
            raise FileNotFoundError(
                f"light {str(light)!r} is neither an existing file, a built-in environment "
                f"({', '.join(list_builtin_environments())}) nor an analytic spec (e.g. 'directional:direction=0,0,1')")
        return load_environment(light)
    return light


def load_shrm(path) -> SHRM:
    """Read a file written by :meth:`SHRM.save`."""
    t, meta = io.load(path, expect_kind="shrm")
    m = {k: v for k, v in meta.items() if k not in ("format", "format_version", "kind", "F_B", "P_B", "axis", "convention")}
    return SHRM(t["light"], t["rho"], int(meta["F_B"]), int(meta["P_B"]), meta.get("axis", "reflection"), t.get("maps"), m)


def build_shrm(brdf: Any, light: Any, *, epsilon: float | None = 0.03, orders: tuple[int, int] | None = None,
               height: int | None = 64, width: int | None = None, max_memory: int = DEFAULT_MAX_MEMORY) -> SHRM:
    """An SHRM for a BRDF and a light, orders from ε (``epsilon``, eq. 5.16–5.19) or given.

    Args:
        brdf: isotropic model or spec (:func:`check_brdf`).
        light: SH coefficients ``[C, n²]`` (missing bands count as zero), an ``Environment``
            (projected to F_B by its own quadrature; its pixels give ε_L), a built-in environment
            name or image file (loaded as an Environment), or an analytic spec (``lighting.load_light``
            at F_B + 1 bands; no ε_L, its total is not known).
        epsilon: in (0, 1): orders by :func:`choose_orders`; ignored when ``orders`` is given.
        orders: ``(F_B, P_B)`` explicitly (meta reason says so).
        height, width: map grid (lat-long; width default 2·height), or height None for no maps.
        max_memory: refuse, before any work, plans above this many bytes (:func:`estimate_memory`).
    Returns:
        :class:`SHRM` with maps (float32) unless ``height`` is None.
    """
    brdf = check_brdf(brdf)
    light = _resolve_light(light)
    analytic = isinstance(light, (str, dict))
    C = 3
    if analytic:
        C = load_light(light, 1).shape[0]
    elif not hasattr(light, "project"):
        lt = torch.as_tensor(light, dtype=torch.float64)
        check_shape("light", lt, ndim=2)
        C = lt.shape[0]
    else:
        C = light.channels
    if height is not None:
        height = check_int("height", height, 1, 8192)
        width = 2 * height if width is None else check_int("width", width, 1, 16384)
    if orders is not None:
        if not (isinstance(orders, (tuple, list)) and len(orders) == 2):
            raise ValueError(f"orders={orders!r}; accepted: a pair (F_B, P_B) of integers in [0, {MAX_BANDS - 1}]")
        F_B = check_int("orders F_B", orders[0], 0, MAX_BANDS - 1)
        P_B = check_int("orders P_B", orders[1], 0, MAX_BANDS - 1)
        if is_radial(brdf):
            P_B = 0
        need = estimate_memory(F_B, P_B, height or 1, width or 1, C)
        if need > max_memory:
            raise ValueError(
                f"orders=({F_B}, {P_B}) at a {height}x{width} map need about {need / 2**30:.2f} GiB (estimated before any "
                f"work); accepted: at most max_memory={max_memory / 2**30:.2f} GiB: smaller orders or a smaller map")
        rho, total = brdf_coefficients(brdf, F_B, P_B)
        E = energy_table(rho)
        info = {"energy": float(E[F_B, P_B]) / total if total > 0 else 1.0, "axis": is_radial(brdf) or "reflection",
                "reason": f"F_B={F_B}, P_B={P_B}: given"}
        info["eps_rho"] = 1 - info["energy"]
    else:
        if epsilon is None:
            raise ValueError("give epsilon in (0, 1) or orders=(F_B, P_B)")
        eps = check_float("epsilon", epsilon, 0.0, 1.0, lo_open=True, hi_open=True)
        F_B, P_B, info = choose_orders(brdf, eps, None if analytic else light)
        need = estimate_memory(F_B, P_B, height or 1, width or 1, C)
        if need > max_memory:
            raise ValueError(
                f"epsilon={eps:g} gives orders ({F_B}, {P_B}) that at a {height}x{width} map need about "
                f"{need / 2**30:.2f} GiB; accepted: at most max_memory={max_memory / 2**30:.2f} GiB: a larger epsilon "
                "or a smaller map")
        rho, _ = brdf_coefficients(brdf, F_B, P_B)
    if analytic:
        L = load_light(light, F_B + 1)
    elif hasattr(light, "project"):
        L = light.project(F_B + 1)
    else:
        L = torch.as_tensor(light, dtype=torch.float64)
        nF = (F_B + 1) ** 2
        L = torch.nn.functional.pad(L, (0, max(0, nF - L.shape[-1])))[:, :nF]
    meta = {"brdf": brdf.meta(), "epsilon": None if orders is not None else float(epsilon),
            **{k: v for k, v in info.items() if k not in ("axis",)}}
    out = SHRM(L, rho, F_B, P_B, info["axis"], None, meta)
    if height is not None:
        out.prefilter(height, width)
    return out
