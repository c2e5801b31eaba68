"""Analytic lights in SH, ``[C, n²]`` float64 (C = 3 unless a colour of another length is given).

Normalisation (one rule for every light here, DirectXSH's in spirit): **``intensity`` is the
exit radiance of a white (albedo 1) Lambertian surface facing the light**, computed exactly
(not after band-limiting), with exit radiance = E/π for irradiance E.

* :func:`directional`: radiance π·I·δ(s - d), so E⊥ = π I and the facing white surface exits I.
  L_lm = π I y_lm(d). (DirectXSH's XMSHEvalDirectionalLight additionally divides by the
  band-limited cosine integral, e.g. 17/16 at 3 bands, so that its *truncated* irradiance
  exits 1; we keep the physical value, so our truncated 9-term irradiance at normal
  incidence is 17/16 I, the usual order-2 overshoot, within the 3/32 bound of Ramamoorthi
  2002 §4.3.1.)
* :func:`cap`: uniform radiance L_c over a cone of half-angle α about d. With ``intensity``,
  L_c = I / sin²(min(α, π/2)), since a facing surface receives E⊥ = π L_c sin²α; so a small cap
  tends to the directional light of the same intensity. Or give ``radiance`` L_c directly.
  Zonal coefficients in closed form (Legendre recurrence):
  h_0 = 2π N_0 (1 - cos α),  h_l = 2π N_l (P_{l-1}(cos α) - P_{l+1}(cos α)) / (2l+1),
  N_l = √((2l+1)/4π), rotated to d by f_lm = Λ_l h_l y_lm(d) (Sloan et al. 2005 notes).
* :func:`sky_gradient` / :func:`hemisphere`: radiance as a function of t = s·up:
  ``horizon + (zenith - horizon)·t`` for t ≥ 0, ``ground`` for t < 0; zonal coefficients by
  Gauss-Legendre on [-1, 0] and [0, 1] (exact: the pieces are polynomials).
* :func:`constant`: uniform radiance c: L_00 = 2√π c (= c · 4π · Y_00); a white Lambertian
  surface under it exits c.
Radiances in sky_gradient/hemisphere/constant are radiances (the same rule: a surface under
uniform radiance c exits c).
"""
from __future__ import annotations

import math
from typing import Any

import torch

from .._checks import check_float, check_int, describe
from ..sh import MAX_BANDS, eval_sh, rotate_zonal, zonal_project

__all__ = ["unit_direction", "directional", "cap", "cap_zonal", "sky_gradient", "hemisphere", "constant", "color"]


def color(value: Any, name: str = "intensity") -> torch.Tensor:
    """A colour ``[C]`` float64: a scalar -> RGB grey ``[3]``; a sequence -> as given."""
    t = torch.as_tensor(value, dtype=torch.float64)
    if t.ndim == 0:
        t = t.repeat(3)
    if t.ndim != 1 or t.numel() < 1 or not torch.isfinite(t).all():
        raise ValueError(f"{name}={describe(value)}; accepted: a finite number or a sequence of per-channel values")
    if bool((t < 0).any()):
        raise ValueError(f"{name}={describe(value)} is negative; accepted: radiance ≥ 0 per channel (as for image pixels)")
    return t


def _dir(direction: Any, name: str = "direction") -> torch.Tensor:
    d = torch.as_tensor(direction, dtype=torch.float64)
    if d.shape != (3,) or not torch.isfinite(d).all() or float(d.norm()) == 0:
        raise ValueError(f"{name}={describe(direction)}; accepted: a non-zero 3-vector (normalised here)")
    return d / d.norm()


def unit_direction(direction: Any, name: str = "direction") -> torch.Tensor:
    """``direction`` checked (a finite non-zero 3-vector) and normalised, ``[3]`` float64: the
    rule every light here applies to its direction (public for the cube rasteriser)."""
    return _dir(direction, name)


def directional(direction: Any, intensity: Any = 1.0, bands: int = 3) -> torch.Tensor:
    """Directional light towards ``direction`` (the direction light arrives *from*), ``[C, n²]``.

    L_lm = π I y_lm(d): a white Lambertian surface facing it exits radiance I (exact)."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    d = _dir(direction)
    return math.pi * color(intensity)[:, None] * eval_sh(d, bands)[None, :]


def _legendre(x: float, n: int) -> list[float]:
    p = [1.0, x]
    for l in range(1, n):  # three-term recurrence (l+1) P_{l+1} = (2l+1) x P_l - l P_{l-1}; O(bands)
        p.append(((2 * l + 1) * x * p[l] - l * p[l - 1]) / (l + 1))
    return p


def cap_zonal(half_angle: float, bands: int) -> torch.Tensor:
    """Zonal coefficients h_l ``[bands]`` float64 of the indicator of a cap of half-angle α about +z."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    a = check_float("half_angle", half_angle, 0.0, math.pi, lo_open=True)
    x = math.cos(a)
    p = _legendre(x, bands + 1)
    h = [2 * math.pi * math.sqrt(1 / (4 * math.pi)) * (1 - x)]
    for l in range(1, bands):
        h.append(2 * math.pi * math.sqrt((2 * l + 1) / (4 * math.pi)) * (p[l - 1] - p[l + 1]) / (2 * l + 1))
    return torch.tensor(h, dtype=torch.float64)


def cap(direction: Any, half_angle: float, intensity: Any = None, radiance: Any = None, bands: int = 3) -> torch.Tensor:
    """Spherical cap (disk / cone light) of half-angle ``half_angle`` (radians) about ``direction``.

    Exactly one of ``intensity`` (exit radiance of a facing white Lambertian surface; the cap's
    radiance is then I / sin²(min(α, π/2))) or ``radiance`` (the cap's uniform radiance).
    Returns ``[C, n²]`` float64."""
    if (intensity is None) == (radiance is None):
        raise ValueError("cap: give exactly one of intensity= (exit radiance of a facing white surface) or radiance=")
    d = _dir(direction)
    h = cap_zonal(half_angle, bands)
    if radiance is None:
        Lc = color(intensity) / math.sin(min(half_angle, math.pi / 2)) ** 2
    else:
        Lc = color(radiance, "radiance")
    return rotate_zonal(Lc[:, None] * h[None, :], d)


def sky_gradient(zenith: Any = (0.3, 0.5, 1.0), horizon: Any = (0.9, 0.9, 1.0), ground: Any = (0.2, 0.18, 0.15),
                 up: Any = (0.0, 0.0, 1.0), bands: int = 3) -> torch.Tensor:
    """Sky gradient: radiance horizon + (zenith - horizon)·t above the horizon (t = s·up ≥ 0),
    ``ground`` below. Returns ``[C, n²]`` float64 (colours broadcast to a common C)."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    z, hz, g = color(zenith, "zenith"), color(horizon, "horizon"), color(ground, "ground")
    z, hz, g = torch.broadcast_tensors(z, hz, g)
    n = max(16, bands + 2)
    one_up = zonal_project(lambda t: torch.ones_like(t), bands, lower=0.0, n=n)
    t_up = zonal_project(lambda t: t, bands, lower=0.0, n=n)
    one_all = zonal_project(lambda t: torch.ones_like(t), bands, lower=-1.0, n=n)
    h = hz[:, None] * one_up + (z - hz)[:, None] * t_up + g[:, None] * (one_all - one_up)
    return rotate_zonal(h, _dir(up, "up"))


def hemisphere(upper: Any = 1.0, lower: Any = 0.0, up: Any = (0.0, 0.0, 1.0), bands: int = 3) -> torch.Tensor:
    """Two-hemisphere light: uniform radiance ``upper`` where s·up > 0, ``lower`` below. ``[C, n²]``."""
    return sky_gradient(upper, upper, lower, up, bands)


def constant(value: Any = 1.0, bands: int = 3) -> torch.Tensor:
    """Uniform radiance ``value``: L_00 = 2√π c, all else 0. ``[C, n²]`` float64."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    c = color(value, "value")
    out = torch.zeros(c.numel(), bands * bands, dtype=torch.float64)
    out[:, 0] = 2 * math.sqrt(math.pi) * c
    return out
