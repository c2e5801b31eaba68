"""Irradiance from SH lighting (Ramamoorthi 2002, ch. 4).

* eq. 4.8–4.10: E_lm = A_l L_lm, E(n) = Σ A_l L_lm y_lm(n), with A_l of eq. 4.11
  (:func:`prt_torch.sh.clamped_cosine_A`), for any number of bands.
* eq. 4.14–4.15: E(n) = ñᵀ M ñ with ñ = (x, y, z, 1) and the symmetric 4×4 matrix M built from
  the first 9 coefficients and c1..c5; eq. 4.16: the same expanded as a polynomial.
  The constants are computed from A_l and the SH normalisations of eq. 4.5 (c1 = A_2·0.546274,
  c2 = A_1·0.488603/2, c3 = 3 A_2·0.315392, c4 = A_0·0.282095, c5 = A_2·0.315392); they agree
  with the thesis' printed 0.429043, 0.511664, 0.743125, 0.886227, 0.247708.
* The order-2 (9-term) approximation errs at most 3/32 ≈ 9% of the total intensity for a
  directional source (§4.3.1), at the horizon n·d = 0.

Exit radiance of a Lambertian surface of albedo ρ: B = ρ E / π.
"""
from __future__ import annotations

import math
from typing import Any

import torch

from .._checks import check_shape, check_unit_vectors
from ..sh import band_of_coeffs, clamped_cosine_A, reconstruct

__all__ = ["irradiance_coeffs", "irradiance_constants", "irradiance_matrix", "irradiance",
           "irradiance_quadratic", "irradiance_polynomial", "irradiance_map"]

_K00 = 0.5 / math.sqrt(math.pi)
_K1 = math.sqrt(3 / (4 * math.pi))
_K2a = 0.5 * math.sqrt(15 / math.pi)   # xy, yz, xz
_K20 = 0.25 * math.sqrt(5 / math.pi)   # (3z² - 1)
_K22 = 0.25 * math.sqrt(15 / math.pi)  # (x² - y²)


def irradiance_coeffs(L: torch.Tensor) -> torch.Tensor:
    """E_lm = A_l L_lm (Ramamoorthi 2002, eq. 4.8–4.9), ``[..., n²] -> [..., n²]``, any bands."""
    bands = band_of_coeffs(L.shape[-1], "L.shape[-1]")
    A = clamped_cosine_A(bands)
    l = torch.repeat_interleave(torch.arange(bands), 2 * torch.arange(bands) + 1)
    return L * A[l].to(L.dtype)


def irradiance_constants() -> dict[str, float]:
    """c1..c5 of Ramamoorthi 2002 eq. 4.15, from A_l (eq. 4.12) and the y_lm constants (eq. 4.5)."""
    A = clamped_cosine_A(3).tolist()
    return {"c1": A[2] * _K22, "c2": A[1] * _K1 / 2, "c3": 3 * A[2] * _K20, "c4": A[0] * _K00, "c5": A[2] * _K20}


def irradiance_matrix(L: torch.Tensor) -> torch.Tensor:
    """The symmetric 4×4 matrices M of eq. 4.15, ``L [C, n² ≥ 9] -> [C, 4, 4]`` float64
    (only the first 9 coefficients are used). E(n) = ñᵀ M ñ, ñ = (x, y, z, 1) (eq. 4.14)."""
    if L.shape[-1] < 9:
        raise ValueError(f"L has {L.shape[-1]} coefficients; accepted: at least 9 (3 bands) for eq. 4.15")
    c = irradiance_constants()
    c1, c2, c3, c4, c5 = (c[k] for k in ("c1", "c2", "c3", "c4", "c5"))
    Lf = L.to(torch.float64)
    L00, L1m1, L10, L11, L2m2, L2m1, L20, L21, L22 = (Lf[..., i] for i in range(9))
    rows = [
        [c1 * L22, c1 * L2m2, c1 * L21, c2 * L11],
        [c1 * L2m2, -c1 * L22, c1 * L2m1, c2 * L1m1],
        [c1 * L21, c1 * L2m1, c3 * L20, c2 * L10],
        [c2 * L11, c2 * L1m1, c2 * L10, c4 * L00 - c5 * L20],
    ]
    return torch.stack([torch.stack(r, -1) for r in rows], -2)


def irradiance(L: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """E(n) = Σ_lm A_l L_lm y_lm(n) (eq. 4.10) for any bands: ``L [C, n²]``, ``normals [*S, 3]``
    -> ``[*S, C]`` (dtype promoted)."""
    check_unit_vectors("normals", normals)
    return reconstruct(irradiance_coeffs(L), normals)


def irradiance_quadratic(M: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """E(n) = ñᵀ M ñ (eq. 4.14): ``M [C, 4, 4]``, ``normals [*S, 3]`` -> ``[*S, C]`` float64."""
    check_shape("M", M, last=(4, 4))
    n = normals.to(torch.float64)
    nt = torch.cat([n, torch.ones_like(n[..., :1])], -1)  # [*S, 4]
    return torch.einsum("...i,cij,...j->...c", nt, M.to(torch.float64), nt)


def irradiance_polynomial(L: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
    """E(n) as the expanded polynomial of eq. 4.16: ``L [C, ≥9]``, ``normals [*S, 3]`` -> ``[*S, C]``."""
    c = irradiance_constants()
    Lf = L.to(torch.float64)
    n = normals.to(torch.float64)
    x, y, z = (n[..., i : i + 1] for i in range(3))
    g = lambda i: Lf[..., i]  # noqa: E731  [C]
    return (c["c1"] * g(8) * (x * x - y * y) + c["c3"] * g(6) * z * z + c["c4"] * g(0) - c["c5"] * g(6)
            + 2 * c["c1"] * (g(4) * x * y + g(7) * x * z + g(5) * y * z)
            + 2 * c["c2"] * (g(3) * x + g(1) * y + g(2) * z))


def irradiance_map(L: torch.Tensor, layout: str = "latlong", size: int = 64, rotation: Any = None, bands: int | None = None):
    """An irradiance environment map (E as a function of the normal, eq. 4.10) in any layout:
    returns an :class:`~prt_torch.lighting.environment.Environment` whose pixel value is E(n)
    for n = the pixel's world direction. ``bands`` truncates L first (default: all of L)."""
    from .environment import render_sh

    Lc = L if bands is None else L[..., : bands * bands]
    env = render_sh(irradiance_coeffs(Lc), layout, size, rotation, name="irradiance")
    env.meta["quantity"] = "irradiance"
    return env
