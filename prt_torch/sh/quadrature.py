"""Sphere quadratures and SH projection / reconstruction.

Every quadrature returns ``(dirs [N, 3], weights [N])`` with ``sum(weights) = 4π`` (or 2π for
a hemisphere), so projecting a sampled function is one GEMM:

    f_lm = Σ_i w_i f(s_i) y_lm(s_i)            (Ramamoorthi 2002, eq. 4.13)

* :func:`gauss_sphere` — Gauss-Legendre in z × uniform in φ: *exact* for band-limited
  integrands (products of SH up to ``bands`` each), used for orthonormality and Gram matrices.
* :func:`latlong_grid` — an equirectangular pixel grid with the exact solid angle of each
  pixel, Δφ (cos θ0 - cos θ1) (not the sin θ midpoint approximation, though the two agree to
  O(Δθ²)).
* :func:`stratified_sphere` — jittered stratified samples in (z, φ), equal weights,
  deterministic per seed (Monte Carlo).
* :func:`fibonacci_sphere` — low-discrepancy spiral points, equal weights.

Values are sample-first: ``values`` is ``[N, *C]`` (N samples, any channel shape C) and the
projected coefficients are ``[*C, n²]`` (coefficients last).
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch

from .._checks import check_float_dtype, check_int, check_shape
from .basis import band_of_coeffs, eval_sh

__all__ = [
    "gauss_sphere",
    "gauss_hemisphere",
    "latlong_grid",
    "stratified_square",
    "stratified_sphere",
    "fibonacci_sphere",
    "project",
    "project_callable",
    "reconstruct",
]


def _dirs_from_z_phi(z: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    s = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    return torch.stack([s * torch.cos(phi), s * torch.sin(phi), z], dim=-1)


def gauss_sphere(bands: int, dtype: torch.dtype = torch.float64, oversample: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Product quadrature exact for polynomials of degree ≤ 2·bands·oversample - 1 on S².

    Gauss-Legendre nodes in z (``bands·oversample + 1`` of them) × ``2·bands·oversample + 1``
    equally spaced φ. Exact for the product of any two SH of up to ``bands·oversample`` bands.

    Returns: dirs ``[N, 3]``, weights ``[N]`` (dtype ``dtype``), Σw = 4π.
    """
    bands = check_int("bands", bands, 1, 4096)
    oversample = check_int("oversample", oversample, 1, 64)
    L = bands * oversample
    nz, nphi = L + 1, 2 * L + 1
    zx, zw = np.polynomial.legendre.leggauss(nz)
    z = torch.tensor(zx, dtype=torch.float64).repeat_interleave(nphi)
    phi = (torch.arange(nphi, dtype=torch.float64) * (2 * math.pi / nphi)).repeat(nz)
    w = torch.tensor(zw, dtype=torch.float64).repeat_interleave(nphi) * (2 * math.pi / nphi)
    return _dirs_from_z_phi(z, phi).to(dtype), w.to(dtype)


def gauss_hemisphere(bands: int, dtype: torch.dtype = torch.float64, oversample: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """As :func:`gauss_sphere` but over the upper hemisphere z ≥ 0 (Σw = 2π).

    Exact for polynomials in (x, y, z) of degree ≤ 2·bands·oversample - 1 restricted to z ≥ 0,
    e.g. products of SH or a clamped cosine lobe times SH.
    """
    bands = check_int("bands", bands, 1, 4096)
    oversample = check_int("oversample", oversample, 1, 64)
    L = bands * oversample
    nz, nphi = L + 1, 2 * L + 1
    zx, zw = np.polynomial.legendre.leggauss(nz)
    z = torch.tensor(0.5 * (zx + 1.0), dtype=torch.float64).repeat_interleave(nphi)
    w = torch.tensor(0.5 * zw, dtype=torch.float64).repeat_interleave(nphi) * (2 * math.pi / nphi)
    phi = (torch.arange(nphi, dtype=torch.float64) * (2 * math.pi / nphi)).repeat(nz)
    return _dirs_from_z_phi(z, phi).to(dtype), w.to(dtype)


def latlong_grid(height: int, width: int, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixel-centre directions and exact solid angles of an equirectangular grid.

    Row i covers θ ∈ [iπ/H, (i+1)π/H] (θ from +z, row 0 at the top = +z), column j covers
    φ ∈ [2πj/W, 2π(j+1)/W] with φ measured from +x towards +y. This is the mathematical
    (θ, φ) grid; image layouts with their own orientation live in ``prt_torch.lighting``.

    Returns: dirs ``[H, W, 3]``, weights ``[H, W]`` with Σw = 4π exactly.
    """
    height = check_int("height", height, 1)
    width = check_int("width", width, 1)
    t0 = torch.arange(height, dtype=torch.float64) * (math.pi / height)
    t1 = t0 + math.pi / height
    tc = t0 + 0.5 * math.pi / height
    phi = (torch.arange(width, dtype=torch.float64) + 0.5) * (2 * math.pi / width)
    solid = (torch.cos(t0) - torch.cos(t1)) * (2 * math.pi / width)  # [H]
    z = torch.cos(tc)[:, None].expand(height, width)
    ph = phi[None, :].expand(height, width)
    dirs = _dirs_from_z_phi(z, ph)
    w = solid[:, None].expand(height, width).clone()
    return dirs.to(dtype), w.to(dtype)


def stratified_square(n: int, seed: int = 0) -> torch.Tensor:
    """``n`` jittered stratified points in the unit square ``[n, 2]`` float64.

    Strata form a ⌊√n⌋-by-⌊n/⌊√n⌋⌋ grid; samples beyond a full grid are uniform.
    Deterministic for a given ``seed``. The sphere and hemisphere samplers map these.
    """
    n = check_int("n", n, 1)
    g = torch.Generator().manual_seed(int(seed))
    rows = max(1, math.isqrt(n))
    cols = n // rows
    full = rows * cols
    u = torch.rand(n, 2, generator=g, dtype=torch.float64)
    i = torch.arange(full, dtype=torch.float64)
    out = u.clone()
    out[:full, 0] = (torch.div(i, cols, rounding_mode="floor") + u[:full, 0]) / rows
    out[:full, 1] = (torch.remainder(i, cols) + u[:full, 1]) / cols
    return out


def stratified_sphere(n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` jittered stratified directions, uniform on the sphere, equal weights 4π/n.

    :func:`stratified_square` mapped equal-area to the sphere (z = 1 - 2a, φ = 2πb).
    Deterministic for a given ``seed``.
    """
    n = check_int("n", n, 1)
    ab = stratified_square(n, seed)
    dirs = _dirs_from_z_phi(1.0 - 2.0 * ab[:, 0], 2 * math.pi * ab[:, 1])
    return dirs.to(dtype), torch.full((n,), 4 * math.pi / n, dtype=dtype)


def fibonacci_sphere(n: int, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` spherical-Fibonacci directions (low discrepancy), equal weights 4π/n."""
    n = check_int("n", n, 1)
    i = torch.arange(n, dtype=torch.float64)
    z = 1.0 - (2.0 * i + 1.0) / n
    phi = torch.remainder(i * (math.pi * (3.0 - math.sqrt(5.0))), 2 * math.pi)
    return _dirs_from_z_phi(z, phi).to(dtype), torch.full((n,), 4 * math.pi / n, dtype=dtype)


def project(values: torch.Tensor, dirs: torch.Tensor, weights: torch.Tensor, bands: int) -> torch.Tensor:
    """Project samples of a spherical function onto SH: f_lm = Σ_i w_i f(s_i) y_lm(s_i).

    Args:
        values: ``[N, *C]`` samples (any channel shape C, e.g. ``[N]`` or ``[N, 3]`` RGB).
        dirs: ``[N, 3]`` unit directions. weights: ``[N]`` quadrature weights (solid angles).
        bands: number of bands n.
    Returns:
        ``[*C, n²]`` coefficients, dtype of ``values`` promoted with ``dirs``.
    """
    check_shape("dirs", dirs, ndim=2, last=(3,))
    check_float_dtype("dirs", dirs)
    n = dirs.shape[0]
    if values.shape[:1] != (n,):
        raise ValueError(f"values has shape {tuple(values.shape)} but dirs has {n} samples; accepted: values [N, *C] with N = {n}")
    if weights.shape != (n,):
        raise ValueError(f"weights has shape {tuple(weights.shape)}; accepted: [N] with N = {n}")
    dtype = torch.promote_types(values.dtype, dirs.dtype)
    y = eval_sh(dirs.to(dtype), bands) * weights.to(dtype)[:, None]  # [N, n²]
    flat = values.to(dtype).reshape(n, -1)  # [N, prod C]
    out = flat.T @ y  # [prod C, n²]
    return out.reshape(*values.shape[1:], y.shape[1])


def project_callable(
    f: Callable[[torch.Tensor], torch.Tensor],
    bands: int,
    quadrature: str = "gauss",
    n: int | None = None,
    oversample: int = 4,
    seed: int = 0,
    dtype: torch.dtype = torch.float64,
) -> torch.Tensor:
    """Project a callable ``f(dirs [N, 3]) -> [N, *C]`` onto ``bands`` bands.

    ``quadrature``: ``"gauss"`` (product Gauss rule, ``oversample``·bands bands exact — right
    for smooth functions), ``"stratified"`` (``n`` jittered samples, seed) or ``"fibonacci"``.
    Returns ``[*C, n²]``.
    """
    if quadrature == "gauss":
        dirs, w = gauss_sphere(bands, dtype=dtype, oversample=oversample)
    elif quadrature in ("stratified", "fibonacci"):
        if n is None:
            raise ValueError(f"quadrature={quadrature!r} needs n (sample count); accepted: a positive integer")
        dirs, w = stratified_sphere(n, seed, dtype) if quadrature == "stratified" else fibonacci_sphere(n, dtype)
    else:
        raise ValueError(f"quadrature={quadrature!r}; accepted: 'gauss', 'stratified', 'fibonacci'")
    return project(f(dirs), dirs, w, bands)


def reconstruct(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate an SH expansion at directions.

    Args:
        coeffs: ``[*C, n²]`` coefficients. dirs: ``[*S, 3]`` unit directions.
    Returns:
        ``[*S, *C]`` values (sample shape first, as :func:`project` takes them).
    """
    bands = band_of_coeffs(coeffs.shape[-1], "coeffs.shape[-1]")
    dtype = torch.promote_types(coeffs.dtype, dirs.dtype)
    y = eval_sh(dirs.to(dtype), bands)  # [*S, n²]
    c = coeffs.to(dtype).reshape(-1, coeffs.shape[-1])  # [prod C, n²]
    out = y.reshape(-1, y.shape[-1]) @ c.T  # [prod S, prod C]
    return out.reshape(*dirs.shape[:-1], *coeffs.shape[:-1])
