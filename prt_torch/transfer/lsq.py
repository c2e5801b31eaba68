"""Choosing the regularisation of the least-squares hemispherical projection from the error it
predicts for the samples actually used (Sloan 2003 eq. 1 and Appendix §9).

Glossy exit transfer with the least-squares projection is M_p = P_out B P_in R_p T_p with
P = A⁻¹ the inverse hemisphere Gram matrix on both sides. A is nearly singular (condition
3e12 at 10 bands), and T_p is a Monte Carlo estimate: its quadrature error is amplified by P_in
and P_out, so a setting that is exact for band-limited functions can be far off in practice
(10 bands, 1024 samples: tens of percent) although the condition number alone passes any fixed
threshold. What matters is the error *amplification given the sample count*, so it is measured
directly:

for an unoccluded vertex (T = A in its local frame) the engine's own estimate Â from the same
stratified direction set (rotated to a few normals) is pushed through the projection, and the
error of the exit-radiance operator is taken in the norm that matters — radiance over the
upper hemisphere, averaged over unit lighting vectors (Lehtinen & Kautz 2003 eq. 11 style):

    ε(rcond)² = tr(Eᵀ A_out E) / tr(Mᵀ A_out M),   E = P_out B P_in Â − M,   M = P_out* B

with M the exact-projection operator (the reference). :func:`choose_rcond` takes the rcond
(None = exact inverse) with the smallest ε: the exact inverse where amplification is harmless,
a pseudo-inverse where it is not.
"""
from __future__ import annotations

import math
from typing import Iterable

import torch

from ..brdf import BRDF, brdf_matrix
from ..sh import eval_sh, hemisphere_gram, hemisphere_projector
from ..sh.rotation import random_rotations
from .sampling import uniform_sphere

__all__ = ["RCOND_CANDIDATES", "projection_error", "choose_rcond"]

#: pseudo-inverse thresholds tried (None: the exact inverse, where it exists)
RCOND_CANDIDATES = (None, 1e-14, 1e-13, 1e-12, 1e-11, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3)


def _projector(bands: int, rcond: float | None, drop=None) -> torch.Tensor:
    try:
        return hemisphere_projector(bands, "least_squares", rcond=rcond, drop=drop)
    except ValueError:
        if rcond is not None:
            raise
        return hemisphere_projector(bands, "least_squares", rcond=1e-15, drop=drop)  # numerically the exact inverse


def projection_error(B_zero: torch.Tensor, bands_out: int, bands_in: int, samples: int, seed: int, rcond: float | None,
                     drop_out: Iterable[tuple[int, int]] | None = None, normals: int = 4,
                     directions: tuple[torch.Tensor, torch.Tensor] | None = None) -> float:
    """ε(rcond) of the module docstring for one material's zero-hemisphere BRDF matrix
    ``B_zero [m², n²]`` float64, with the engine's stratified set of ``samples`` directions
    (``seed``; or ``directions = (dirs [N, 3], weights [N])``) rotated to ``normals`` frames.
    Raises ValueError when ``rcond`` is None and the exact inverse does not exist."""
    drop = list(drop_out or [])
    P_in = hemisphere_projector(bands_in, "least_squares", rcond=rcond) if rcond is not None else _projector(bands_in, None)
    P_out = hemisphere_projector(bands_out, "least_squares", rcond=rcond, drop=drop) if rcond is not None \
        else _projector(bands_out, None, drop)
    keep = torch.ones(bands_out * bands_out, dtype=torch.bool)
    for l, m in drop:
        keep[l * (l + 1) + m] = False
    A_out = hemisphere_gram(bands_out)[keep][:, keep]
    M = _projector(bands_out, None, drop) @ B_zero  # the exact-projection exit operator (T = A: P_in A = I)
    ref = float(torch.trace(M.T @ A_out @ M))
    dirs, w = uniform_sphere(samples, seed) if directions is None else directions
    frames = [torch.eye(3, dtype=torch.float64)] + list(random_rotations(normals - 1, seed=seed + 17)) if normals > 1 else \
        [torch.eye(3, dtype=torch.float64)]
    G = P_out @ B_zero @ P_in
    err = 0.0
    for F in frames:  # a few frames: each one [N, n²] evaluation and one GEMM
        loc = dirs @ F.to(torch.float64).T
        up = loc[:, 2] > 0
        Y = eval_sh(loc[up], bands_in, check=False)
        T_hat = (Y * w[up, None]).T @ Y  # the engine's Monte Carlo T for an unoccluded vertex
        E = G @ T_hat - M
        err += float(torch.trace(E.T @ A_out @ E))
    return math.sqrt(err / len(frames) / max(ref, 1e-300))


def choose_rcond(brdf: BRDF, bands_out: int, bands_in: int, samples: int, seed: int = 0,
                 drop_out: Iterable[tuple[int, int]] | None = None, quad_bands: int | None = None,
                 B_zero: torch.Tensor | None = None) -> dict:
    """The rcond with the smallest predicted error (module docstring) for this BRDF, band counts
    and sample set. Returns ``{'rcond', 'predicted_error', 'exact_error' (None if the exact
    inverse does not exist), 'tried': {rcond: error}}``."""
    if B_zero is None:
        B_zero = brdf_matrix(brdf, bands_out, bands_in, projection="zero", quad_bands=quad_bands)
    B0 = B_zero.reshape(-1, B_zero.shape[-2], B_zero.shape[-1])[0].to(torch.float64)
    tried: dict = {}
    for rc in RCOND_CANDIDATES:
        try:
            tried[rc] = projection_error(B0, bands_out, bands_in, samples, seed, rc, drop_out)
        except ValueError:  # no exact inverse at this band count
            continue
    best = min(tried, key=lambda r: tried[r])
    return {"rcond": best, "predicted_error": tried[best], "exact_error": tried.get(None),
            "tried": {str(k): v for k, v in tried.items()}}
