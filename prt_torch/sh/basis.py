"""Real spherical harmonics in the graphics convention.

Convention (Ramamoorthi 2002, thesis eq. 4.5; ARCHITECTURE.md): no Condon-Shortley phase,

    Y00 = 0.282095,  Y1,-1 = 0.488603 y,  Y1,0 = 0.488603 z,  Y1,1 = 0.488603 x,

flat index ``k = l(l+1) + m``; ``bands`` n means l = 0..n-1 and n² coefficients.
In terms of the complex harmonics Y_l^m (with the Condon-Shortley phase, as in scipy):

    y_lm = √2 (-1)^m Re Y_l^m      (m > 0)
    y_l0 = Y_l^0
    y_lm = √2 (-1)^m Im Y_l^{|m|}  (m < 0)

Evaluation uses fully normalised associated-Legendre recurrences in z = cos θ and builds
sin^m θ cos(mφ), sin^m θ sin(mφ) as Re/Im of (x + i y)^m, so there are no factorials, no
atan2 and no singularity at the poles; float64 is accurate to ~1e-13 at 30 bands and beyond.
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch

from .._checks import check_int, check_unit_vectors

__all__ = [
    "num_coeffs",
    "sh_index",
    "lm_of",
    "band_of_coeffs",
    "eval_sh",
    "eval_zonal_basis",
    "MAX_BANDS",
]

#: Hard upper limit on ``bands`` accepted by the evaluators (memory, not accuracy, is the limit).
MAX_BANDS = 128
#: sphericart's float32 evaluation loses accuracy past this many bands (against float64:
#: ≤ 1e-5 absolute to 19 bands, 2.5e-2 at 20, NaN from 32 — benchmarks/bench_extremes.py);
#: beyond it ``backend='auto'`` uses this module's recurrences, which stay at ~1e-4 to 64 bands.
SPHERICART_FLOAT32_MAX_BANDS = 19


def num_coeffs(bands: int) -> int:
    """Number of SH coefficients for ``bands`` bands: bands²."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    return bands * bands


def sh_index(l: int, m: int) -> int:
    """Flat index of (l, m): l(l+1) + m."""
    l = check_int("l", l, 0)
    m = check_int("m", m, -l, l)
    return l * (l + 1) + m


def band_of_coeffs(n_coeffs: int, name: str = "coefficient count") -> int:
    """Inverse of :func:`num_coeffs`: the band count whose square is ``n_coeffs``."""
    b = math.isqrt(int(n_coeffs))
    if b * b != n_coeffs or b < 1:
        raise ValueError(f"{name}={n_coeffs} is not a square number of SH coefficients; accepted: 1, 4, 9, 16, 25, ...")
    return b


@lru_cache(maxsize=None)
def _lm_table(bands: int) -> tuple[torch.Tensor, torch.Tensor]:
    l = torch.cat([torch.full((2 * b + 1,), b, dtype=torch.long) for b in range(bands)])
    m = torch.cat([torch.arange(-b, b + 1, dtype=torch.long) for b in range(bands)])
    return l, m


def lm_of(bands: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``(l, m)`` of every flat index for ``bands`` bands: two long tensors ``[bands²]``."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    l, m = _lm_table(bands)
    return l.clone(), m.clone()


@lru_cache(maxsize=None)
def _recurrence_coeffs(bands: int) -> tuple[list[list[float]], list[list[float]], list[float], list[float]]:
    """Coefficients of the normalised associated-Legendre recurrences (float64 Python floats).

    With q_l^m = K_lm P_l^m(z) / (1 - z²)^{m/2} (no Condon-Shortley phase):
      q_0^0 = 1/sqrt(4π);  q_m^m = q_{m-1}^{m-1} sqrt((2m+1)/(2m))
      q_{m+1}^m = sqrt(2m+3) z q_m^m
      q_l^m = a_lm (z q_{l-1}^m - b_lm q_{l-2}^m),
        a_lm = sqrt((4l²-1)/(l²-m²)),  b_lm = sqrt(((l-1)²-m²)/(4(l-1)²-1)).
    """
    a = [[0.0] * (l + 1) for l in range(bands)]
    b = [[0.0] * (l + 1) for l in range(bands)]
    for l in range(2, bands):
        for m in range(0, l - 1):
            a[l][m] = math.sqrt((4.0 * l * l - 1.0) / (l * l - m * m))
            b[l][m] = math.sqrt(((l - 1.0) ** 2 - m * m) / (4.0 * (l - 1.0) ** 2 - 1.0))
    diag = [1.0 / math.sqrt(4.0 * math.pi)]
    for m in range(1, bands):
        diag.append(diag[-1] * math.sqrt((2.0 * m + 1.0) / (2.0 * m)))
    sub = [math.sqrt(2.0 * m + 3.0) for m in range(bands)]
    return a, b, diag, sub


def _legendre_q(z: torch.Tensor, bands: int) -> list[torch.Tensor]:
    """q_l^m for m = 0..l as a list over l of tensors ``[l+1, N]`` (same dtype as z).

    Layout is m-major (rows contiguous over the N points) so every recurrence step is a
    contiguous vector operation. The loop is over bands only.
    """
    a, b, diag, sub = _recurrence_coeffs(bands)
    dtype, dev = z.dtype, z.device
    out: list[torch.Tensor] = []
    for l in range(bands):
        q = torch.empty(l + 1, z.shape[0], dtype=dtype, device=dev)
        if l >= 2:
            av = torch.tensor(a[l][: l - 1], dtype=dtype, device=dev)[:, None]
            bv = torch.tensor(b[l][: l - 1], dtype=dtype, device=dev)[:, None]
            torch.mul(out[l - 1][: l - 1], z, out=q[: l - 1])
            q[: l - 1].sub_(bv * out[l - 2][: l - 1]).mul_(av)
        if l >= 1:
            torch.mul(out[l - 1][l - 1], z, out=q[l - 1]).mul_(sub[l - 1])
        q[l] = diag[l]
        out.append(q)
    return out


@lru_cache(maxsize=None)
def _sphericart_calculator(lmax: int):
    """sphericart's calculator for ``lmax``, first run at the most threads this process may use.

    sphericart-torch 2.0.4 sizes its per-thread buffers at the first ``compute``: created inside
    ``torch_threads(1)`` (a precompute's chunk or BRDF setup) and used later with two OpenMP
    threads, it wrote past them — heap corruption, seen as 'double free or corruption' in a later
    LAPACK call (2 cores, 10 bands). Warming it at max(cores, current threads) avoids that."""
    import os

    import sphericart.torch as sct  # optional compiled backend

    from ..executor import torch_threads

    calc = sct.SphericalHarmonics(lmax)
    with torch_threads(max(os.cpu_count() or 1, torch.get_num_threads())):
        calc.compute(torch.tensor([[0.0, 0.0, 1.0]] * 64, dtype=torch.float64))
    return calc


def _have_sphericart() -> bool:
    try:
        import sphericart.torch  # noqa: F401
    except Exception:  # ImportError, or a binary incompatible with this torch
        return False
    return True


BACKENDS = ("auto", "torch", "sphericart")


@lru_cache(maxsize=None)
def _have_sphericart_cached() -> bool:
    return _have_sphericart()


def eval_sh(dirs: torch.Tensor, bands: int, check: bool = True, backend: str = "auto") -> torch.Tensor:
    """Evaluate all real SH up to ``bands`` bands at unit directions.

    Args:
        dirs: ``[..., 3]`` float32 or float64 unit vectors (x, y, z) in the world frame.
        bands: number of bands n ≥ 1 (l = 0..n-1).
        check: validate ``dirs`` (unit length, finite). Turn off only on hot paths whose
            directions are unit by construction.
        backend: ``"torch"`` — the normalised recurrences of this module (pure torch, any
            device, autograd); ``"sphericart"`` — sphericart-torch's compiled kernels, which
            use the same convention (measured agreement ≤ 8e-14 at 31 bands in float64) and
            are 1.5–14× faster on CPU (reports/benchmarks/sh.md); ``"auto"`` — sphericart
            for CPU tensors without autograd when it is installed, else torch.

    Returns:
        ``[..., n²]`` tensor of the same dtype and device, flat index l(l+1)+m.
    """
    bands = check_int("bands", bands, 1, MAX_BANDS)
    if backend not in BACKENDS:
        raise ValueError(f"backend={backend!r}; accepted: {list(BACKENDS)}")
    if check:
        check_unit_vectors("dirs", dirs)
    f32_unsafe = dirs.dtype != torch.float64 and bands > SPHERICART_FLOAT32_MAX_BANDS
    if backend == "sphericart" and f32_unsafe:
        raise ValueError(f"backend='sphericart' in {dirs.dtype} is wrong beyond {SPHERICART_FLOAT32_MAX_BANDS} bands "
                         f"(measured: 2.5e-2 absolute error at 20 bands, NaN from 32); got bands={bands}; accepted: "
                         "float64 directions, backend='torch', or fewer bands")
    if backend == "sphericart" or (
        backend == "auto" and not f32_unsafe and dirs.device.type == "cpu" and not dirs.requires_grad
        and _have_sphericart_cached()
    ):
        flat = dirs.reshape(-1, 3)
        if flat.shape[0] == 0:
            return dirs.new_empty(*dirs.shape[:-1], bands * bands)
        y = _sphericart_calculator(bands - 1).compute(flat.contiguous())
        return y.reshape(*dirs.shape[:-1], bands * bands)
    lead = dirs.shape[:-1]
    d = dirs.reshape(-1, 3).T.contiguous()  # [3, N]
    n = d.shape[1]
    x, y, z = d[0], d[1], d[2]
    out = torch.empty(bands * bands, n, dtype=d.dtype, device=d.device)
    q = _legendre_q(z, bands)
    # √2 C_m = √2 Re (x+iy)^m = √2 sin^m θ cos mφ ; √2 S_m likewise with Im.
    cs = torch.empty(bands, n, dtype=d.dtype, device=d.device)
    sn = torch.empty(bands, n, dtype=d.dtype, device=d.device)
    cs[0] = math.sqrt(2.0)
    sn[0] = 0.0
    for m in range(1, bands):  # loop over bands only
        cs[m] = x * cs[m - 1] - y * sn[m - 1]
        sn[m] = x * sn[m - 1] + y * cs[m - 1]
    for l in range(bands):
        c = l * (l + 1)
        out[c] = q[l][0]
        if l:
            torch.mul(q[l][1:], cs[1 : l + 1], out=out[c + 1 : c + l + 1])
            # m < 0 stored in reverse order: index c-|m|
            out[c - l : c].copy_((q[l][1:] * sn[1 : l + 1]).flip(0))
    return out.T.reshape(*lead, bands * bands)


def eval_zonal_basis(cos_theta: torch.Tensor, bands: int) -> torch.Tensor:
    """Zonal harmonics Y_l0 at cos θ for l = 0..bands-1.

    Args:
        cos_theta: ``[...]`` float tensor with values in [-1, 1].
    Returns:
        ``[..., bands]`` tensor, Y_l0(θ) = sqrt((2l+1)/4π) P_l(cos θ).
    """
    bands = check_int("bands", bands, 1, MAX_BANDS)
    if not isinstance(cos_theta, torch.Tensor) or not cos_theta.is_floating_point():
        raise TypeError(f"cos_theta must be a float tensor, got {type(cos_theta).__name__}")
    if cos_theta.numel() and (cos_theta.abs().max() > 1 + 1e-6 or not torch.isfinite(cos_theta).all()):
        raise ValueError(f"cos_theta has values outside [-1, 1] (max |value| {float(cos_theta.abs().max()):.6g}); accepted: cosines in [-1, 1]")
    lead = cos_theta.shape
    q = _legendre_q(cos_theta.reshape(-1), bands)
    return torch.stack([ql[0] for ql in q], dim=-1).reshape(*lead, bands)
