"""Hemispherical SH projection (Sloan et al. 2003, §3.2 and Appendix §9).

A function f defined on the upper hemisphere H = {z ≥ 0} (exit or transferred radiance in a
local frame) is projected onto SH in one of four ways. All start from its *zero-hemisphere*
projection  b_k = ∫_H f y_k  (the ordinary SH projection of f extended by 0 below H):

* ``"zero"``: c = b.
* ``"least_squares"``: c = A⁻¹ b with the Gram matrix  A_ik = ∫_H y_i y_k  (Appendix §9.1):
  the least-squares optimal fit on H; reproduces any band-limited function on H exactly.
* ``"odd"`` / ``"even"``: the SH projection of f reflected about z = 0 with a sign flip (odd)
  or without (even), Westin et al. 1992; c = D* b where D* doubles the basis functions of the
  matching z-parity and zeroes the others. y_lm(x, y, -z) = (-1)^(l+m) y_lm(x, y, z), so the
  even reflection keeps the l+m even functions and the odd reflection the l+m odd ones.

A is computed in float64 with a product Gauss rule that is exact for it (the integrands are
polynomials of degree ≤ 2(n-1)). A is nearly singular — at 5 bands its smallest singular
value is 6.59e-6 (Appendix §9.1) and its conditioning worsens quickly with bands — so the
inverse is taken through a symmetric eigendecomposition in float64, with an explicit
``rcond`` (eigenvalues below rcond·λ_max are treated as zero, giving the minimum-norm
pseudo-inverse) and/or dropping nearly redundant basis functions (``drop=[(1, 0)]``, the
paper's choice for non-square N_r × N_i transfer matrices).
"""
from __future__ import annotations

from functools import lru_cache
from typing import Iterable

import torch

from .._checks import check_choice, check_float, check_int
from .basis import MAX_BANDS, band_of_coeffs, eval_sh, lm_of
from .quadrature import gauss_hemisphere

__all__ = [
    "hemisphere_gram",
    "hemisphere_projector",
    "project_hemisphere",
    "projection_error",
    "redundancy_errors",
    "METHODS",
]

METHODS = ("zero", "least_squares", "odd", "even")


@lru_cache(maxsize=None)
def _gram(bands: int) -> torch.Tensor:
    dirs, w = gauss_hemisphere(bands, dtype=torch.float64, oversample=2)
    y = eval_sh(dirs, bands, check=False)
    A = (y * w[:, None]).T @ y
    return 0.5 * (A + A.T)


def hemisphere_gram(bands: int) -> torch.Tensor:
    """A_ik = ∫_H y_i y_k ds over z ≥ 0 (Sloan 2003, Appendix §9.1), ``[n², n²]`` float64."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    return _gram(bands).clone()


def _kept_indices(bands: int, drop: Iterable[tuple[int, int]] | None) -> torch.Tensor:
    n2 = bands * bands
    keep = torch.ones(n2, dtype=torch.bool)
    for lm in drop or ():
        l, m = (int(v) for v in lm)
        if not (0 <= l < bands and -l <= m <= l):
            raise ValueError(f"drop contains (l, m)=({l}, {m}), which is not a basis function of {bands} bands; accepted: 0 ≤ l < {bands}, |m| ≤ l")
        keep[l * (l + 1) + m] = False
    return torch.nonzero(keep).flatten()


def hemisphere_projector(
    bands: int,
    method: str = "least_squares",
    rcond: float | None = None,
    drop: Iterable[tuple[int, int]] | None = None,
) -> torch.Tensor:
    """Matrix P mapping a zero-hemisphere projection b ``[n²]`` to coefficients c = P b.

    Args:
        bands: n. method: one of :data:`METHODS`.
        rcond: least-squares only; eigenvalues of A below ``rcond·λ_max`` are discarded
            (pseudo-inverse). None: exact inverse, refused if A (or its kept block) is
            numerically singular (condition number > 1e13); then pass rcond or drop.
        drop: least-squares only; (l, m) basis functions to leave out (e.g. ``[(1, 0)]``).
            The result then has fewer rows.
    Returns:
        ``[n_out, n²]`` float64, n_out = n² - len(drop). Columns of dropped functions are zero
        (their b is not needed); rows are the kept functions in flat-index order.
    """
    bands = check_int("bands", bands, 1, MAX_BANDS)
    check_choice("method", method, METHODS)
    n2 = bands * bands
    if method != "least_squares":
        if rcond is not None or drop:
            raise ValueError(f"rcond and drop apply to method='least_squares' only, got method={method!r}")
        if method == "zero":
            return torch.eye(n2, dtype=torch.float64)
        l, m = lm_of(bands)
        parity_even = (l + m) % 2 == 0
        keep = parity_even if method == "even" else ~parity_even
        return torch.diag(2.0 * keep.to(torch.float64))
    keep = _kept_indices(bands, drop)
    A = _gram(bands)[keep][:, keep]
    evals, evecs = torch.linalg.eigh(A)
    lam_max = float(evals[-1])
    if rcond is None:
        cond = lam_max / max(float(evals[0]), 1e-300)
        if cond > 1e13:
            raise ValueError(
                f"the hemisphere Gram matrix at bands={bands} is numerically singular (condition number {cond:.3g}); "
                "accepted: pass rcond (e.g. 1e-10) for a pseudo-inverse, or drop=[(1, 0)], or use fewer bands"
            )
        inv_evals = 1.0 / evals
    else:
        rcond = check_float("rcond", rcond, 0.0, 1.0, lo_open=True)
        inv_evals = torch.where(evals > rcond * lam_max, 1.0 / evals, torch.zeros_like(evals))
    Ainv = (evecs * inv_evals) @ evecs.T
    P = torch.zeros(len(keep), n2, dtype=torch.float64)
    P[:, keep] = 0.5 * (Ainv + Ainv.T)
    return P


def project_hemisphere(
    b: torch.Tensor,
    method: str = "least_squares",
    rcond: float | None = None,
    drop: Iterable[tuple[int, int]] | None = None,
) -> torch.Tensor:
    """Apply a hemispherical projection to zero-hemisphere coefficients.

    Args:
        b: ``[..., n²]`` zero-hemisphere projections (b_k = ∫_H f y_k).
    Returns:
        ``[..., n_out]`` coefficients in the dtype of ``b`` (the product is formed in float64).
    """
    bands = band_of_coeffs(b.shape[-1], "b.shape[-1]")
    P = hemisphere_projector(bands, method, rcond, drop)
    return (b.to(torch.float64) @ P.T).to(b.dtype)


def projection_error(signal_bands: int, method: str, basis_bands: int | None = None,
                     rcond: float | None = None) -> tuple[float, float]:
    """Worst- and average-case squared error over H of a hemispherical projection
    (Sloan 2003, Appendix §9.2), over all unit-length signals of ``signal_bands`` bands.

    The signal c (n_s² coefficients, zero-padded to the basis) is restricted to H, projected
    (b = A c, then ĉ = P b with the method's projector P at ``basis_bands``), and the error
    ∫_H (ĉ·y - c·y)² = cᵀ (PA - I)ᵀ A (PA - I) c = cᵀ Q c. Worst case is the largest
    eigenvalue of the signal block of Q, average the mean eigenvalue.

    Paper values: zero-hemisphere 0.125 / 0.0402 (5 bands); odd reflection 0.145 / 0.044
    (signal 5, basis 8); even reflection 0.022 / 0.0036 (basis 7), 0.193 / 0.030 (basis 5).
    """
    signal_bands = check_int("signal_bands", signal_bands, 1, MAX_BANDS)
    basis_bands = signal_bands if basis_bands is None else check_int("basis_bands", basis_bands, signal_bands, MAX_BANDS)
    A = _gram(basis_bands)
    P = hemisphere_projector(basis_bands, method, rcond=rcond if method == "least_squares" else None)
    E = P @ A - torch.eye(basis_bands**2, dtype=torch.float64)
    Q = E.T @ A @ E
    ns = signal_bands**2
    ev = torch.linalg.eigvalsh(0.5 * (Q[:ns, :ns] + Q[:ns, :ns].T))
    return float(ev.max()), float(ev.mean())


def redundancy_errors(bands: int) -> torch.Tensor:
    """For each basis function k, the least squared error over H of approximating y_k by a
    combination of the others: A_kk - A_k,¬k A_¬k,¬k⁻¹ A_¬k,k = 1 / (A⁻¹)_kk (a Schur complement).

    Sloan 2003 §9.1: at 5 bands the minimum, 1.48e-5, is at l=1, m=0. Returns ``[n²]`` float64.
    """
    bands = check_int("bands", bands, 1, MAX_BANDS)
    A = _gram(bands)
    evals, evecs = torch.linalg.eigh(A)
    diag_inv = (evecs * evecs / evals).sum(-1)
    return 1.0 / diag_inv
