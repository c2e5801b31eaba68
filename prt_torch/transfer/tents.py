"""The tent basis of matrix radiance transfer (Lehtinen & Kautz 2003): exit radiance in a
basis of M×M piecewise-bilinear "tent" functions on the hemisphere. The MRT precompute that
uses it is :mod:`prt_torch.transfer.mrt`.

Parameterisation (Lehtinen & Kautz §4.3; Shirley & Chiu 1997):

* square (a, b) ∈ [-1, 1]² → unit disk by the concentric map
  |a| > |b|: r = a, φ = (π/4) b/a;  otherwise: r = b, φ = π/2 - (π/4) a/b;  (u, v) = r(cos φ, sin φ)
* disk → hemisphere by the equal-area (Lambert azimuthal) lift
  (x, y, z) = (u sqrt(2 - r²), v sqrt(2 - r²), 1 - r²).
  Both maps are area preserving up to a constant: dω = (π/2) da db (the square's area 4 maps
  to the hemisphere's 2π).
* tents: grid nodes a_i = -1 + 2i/(M-1), i = 0..M-1 (same in b); basis function
  j = i_a·M + i_b is g_j(a, b) = hat_{i_a}(a) hat_{i_b}(b) with the 1-D hat functions of the
  grid. They form a partition of unity and only the four of the cell holding a direction are
  nonzero there ("four dot products per vertex", §4.4).

Matrices (all float64):

* G_jk = ∫_H g_j g_k dω (Gram, eq. 7) — by quadrature, and in closed form
  (π/2)(K ⊗ K) with K the 1-D hat mass matrix (:func:`tent_gram_exact`, a test reference).
* C_ji = ∫_H Y_i g_j dω (change of basis, eq. 7), ``[M², m²]``.
* Projection SH → tents: l^g = G⁻¹ C l (eq. 8).
* Error matrix E = A_m - Cᵀ G⁻¹ C (eq. 10), A_m the hemisphere Gram of SH (Sloan 2003
  §9.1), so ‖L_o - L_o^g‖²_H = lᵀ E l.
* Average PSNR (eq. 11): -10 log10 E{lᵀ E l} over uniformly random unit vectors l; the
  expectation is tr(E)/m² exactly, and :func:`average_psnr` also reports a sampled population.

Quadrature: the square is cut into grid cells and each cell into 4 triangles by its
diagonals. The concentric map's seams (the square's diagonals) run along cell diagonals,
so every triangle lies inside one smooth piece of the map, and the triangle whose vertex is
the square's centre (the pole, where the map is only Lipschitz) is integrated with a
Duffy-collapsed Gauss rule whose collapsed vertex is that centre — along rays from it the
map is smooth. Tent products are then integrated exactly and SH–tent products to ~1e-15.
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import torch

from .._checks import check_int
from ..sh import MAX_BANDS, eval_sh, hemisphere_gram

__all__ = [
    "MAX_TENTS",
    "square_to_disk",
    "disk_to_square",
    "square_to_hemisphere",
    "hemisphere_to_square",
    "tent_nodes",
    "tent_eval",
    "tent_taps",
    "tent_quadrature",
    "tent_gram",
    "tent_gram_exact",
    "change_of_basis",
    "sh_to_tent",
    "tent_project",
    "error_matrix",
    "average_psnr",
    "MRTBasis",
]

MAX_TENTS = 64
_QUARTER_PI = math.pi / 4


# ------------------------------------------------------------------------- maps
def square_to_disk(ab: torch.Tensor) -> torch.Tensor:
    """Shirley–Chiu concentric map ``[..., 2]`` (a, b) ∈ [-1,1]² → ``[..., 2]`` (u, v) on the unit disk."""
    a, b = ab[..., 0], ab[..., 1]
    first = a.abs() > b.abs()
    safe_a = torch.where(a == 0, torch.ones_like(a), a)
    safe_b = torch.where(b == 0, torch.ones_like(b), b)
    r = torch.where(first, a, b)
    phi = torch.where(first, _QUARTER_PI * b / safe_a, 2 * _QUARTER_PI - _QUARTER_PI * a / safe_b)
    phi = torch.where((a == 0) & (b == 0), torch.zeros_like(phi), phi)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi)], dim=-1)


def disk_to_square(uv: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`square_to_disk`: ``[..., 2]`` (u, v) → ``[..., 2]`` (a, b)."""
    u, v = uv[..., 0], uv[..., 1]
    R = torch.sqrt(u * u + v * v)
    first = u.abs() >= v.abs()
    # signed radius r (= a in the first region, b in the second); the point is r (cos φ, sin φ)
    r = torch.where(first, torch.sign(u) * R, torch.sign(v) * R)
    safe_r = torch.where(r == 0, torch.ones_like(r), r)
    phi = torch.atan2(v / safe_r, u / safe_r)
    a = torch.where(first, r, r * (2 * _QUARTER_PI - phi) / _QUARTER_PI)
    b = torch.where(first, r * phi / _QUARTER_PI, r)
    zero = R == 0
    return torch.stack([torch.where(zero, 0 * a, a), torch.where(zero, 0 * b, b)], dim=-1)


def square_to_hemisphere(ab: torch.Tensor) -> torch.Tensor:
    """Area-preserving map ``[..., 2]`` → unit directions ``[..., 3]`` with z ≥ 0 (dω = π/2 da db)."""
    uv = square_to_disk(ab)
    r2 = (uv * uv).sum(-1).clamp(max=1.0)
    s = torch.sqrt(2.0 - r2)
    return torch.stack([uv[..., 0] * s, uv[..., 1] * s, 1.0 - r2], dim=-1)


def hemisphere_to_square(d: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`square_to_hemisphere` for ``[..., 3]`` unit directions; directions
    below the horizon are first clamped onto it (z = 0). Returns ``[..., 2]`` in [-1, 1]²."""
    z = d[..., 2].clamp(0.0, 1.0)
    xy = d[..., :2]
    n = xy.norm(dim=-1, keepdim=True)
    # re-normalise (x, y) so that points below the horizon land on the rim
    target = torch.sqrt((1.0 - z * z).clamp_min(0.0))[..., None]
    xy = torch.where(n > 0, xy / n.clamp_min(1e-300) * target, xy)
    uv = xy / torch.sqrt(1.0 + z)[..., None]
    return disk_to_square(uv).clamp(-1.0, 1.0)


# ------------------------------------------------------------------------- tents
def tent_nodes(M: int) -> torch.Tensor:
    """Grid node coordinates ``[M]`` float64 in [-1, 1]."""
    M = check_int("M", M, 2, MAX_TENTS)
    return torch.linspace(-1.0, 1.0, M, dtype=torch.float64)


def _hat_taps(x: torch.Tensor, M: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Cell index i0 ∈ [0, M-2] and fractional position t ∈ [0, 1] of x ∈ [-1, 1]."""
    g = (x + 1.0) * (0.5 * (M - 1))
    i0 = torch.clamp(torch.floor(g), 0, M - 2)
    return i0.to(torch.int64), (g - i0).clamp(0.0, 1.0)


def tent_taps(dirs: torch.Tensor, M: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The four nonzero tents at each direction (Lehtinen & Kautz 2003 eq. 13: s, t, r, o).

    Args: dirs ``[..., 3]`` local directions (z ≥ 0; below-horizon ones are clamped to the rim).
    Returns: (index ``[..., 4]`` int64 into the M² basis, weight ``[..., 4]`` in dirs' dtype),
    weights ≥ 0 summing to 1.
    """
    M = check_int("M", M, 2, MAX_TENTS)
    ab = hemisphere_to_square(dirs)
    ia, ta = _hat_taps(ab[..., 0], M)
    ib, tb = _hat_taps(ab[..., 1], M)
    idx = torch.stack([ia * M + ib, ia * M + ib + 1, (ia + 1) * M + ib, (ia + 1) * M + ib + 1], dim=-1)
    w = torch.stack([(1 - ta) * (1 - tb), (1 - ta) * tb, ta * (1 - tb), ta * tb], dim=-1)
    return idx, w.to(dirs.dtype)


def _tents_at_square(ab: torch.Tensor, M: int) -> torch.Tensor:
    """All M² tent values at square points ``[N, 2]`` → ``[N, M²]`` (dense; for quadrature)."""
    nodes = tent_nodes(M).to(ab.dtype)
    h = 2.0 / (M - 1)
    ha = (1.0 - (ab[:, 0:1] - nodes[None]).abs() / h).clamp_min(0)  # [N, M]
    hb = (1.0 - (ab[:, 1:2] - nodes[None]).abs() / h).clamp_min(0)
    return (ha[:, :, None] * hb[:, None, :]).reshape(ab.shape[0], M * M)


def tent_eval(coeffs: torch.Tensor, dirs: torch.Tensor) -> torch.Tensor:
    """Evaluate tent expansions Σ_j c_j g_j(d) (Lehtinen & Kautz eq. 9).

    Args: coeffs ``[*B, M²]``; dirs ``[*B, 3]`` (same leading shape, one direction per expansion)
    Returns ``[*B]``.
    """
    M = int(round(math.sqrt(coeffs.shape[-1])))
    if M * M != coeffs.shape[-1]:
        raise ValueError(f"coeffs has {coeffs.shape[-1]} entries per expansion; accepted: M² for an integer M ≥ 2")
    idx, w = tent_taps(dirs, M)
    return (torch.gather(coeffs, -1, idx) * w.to(coeffs.dtype)).sum(-1)


@lru_cache(maxsize=None)
def _tri_rule(q: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Duffy-collapsed Gauss rule on the reference triangle (P0 collapsed):
    point = P0 + ξ (P1 - P0) + ξ η (P2 - P1), weight ∝ ξ. Returns (ξη [q², 2], w [q²])
    with Σw = 1/2 (the reference triangle's area)."""
    x, w = np.polynomial.legendre.leggauss(q)
    x, w = (x + 1) / 2, w / 2
    xi, eta = np.meshgrid(x, x, indexing="ij")
    wi, we = np.meshgrid(w, w, indexing="ij")
    pts = torch.tensor(np.stack([xi.ravel(), eta.ravel()], -1), dtype=torch.float64)
    ww = torch.tensor((wi * we * xi).ravel(), dtype=torch.float64)
    return pts, ww


@lru_cache(maxsize=None)
def _tent_quadrature(M: int, q: int) -> tuple[torch.Tensor, torch.Tensor]:
    nodes = tent_nodes(M)
    i = torch.arange(M - 1)
    a0, b0 = torch.meshgrid(nodes[i], nodes[i], indexing="ij")
    a0, b0 = a0.reshape(-1), b0.reshape(-1)
    h = 2.0 / (M - 1)
    corners = torch.stack(
        [torch.stack([a0, b0], -1), torch.stack([a0 + h, b0], -1), torch.stack([a0 + h, b0 + h], -1), torch.stack([a0, b0 + h], -1)], 1
    )  # [cells, 4, 2] counter-clockwise
    centre = corners.mean(1)  # [cells, 2]
    tris = []
    for k in range(4):  # 4 triangles per cell: (centre, corner k, corner k+1)
        tris.append(torch.stack([centre, corners[:, k], corners[:, (k + 1) % 4]], 1))
    T = torch.cat(tris, 0)  # [4·cells, 3, 2]
    # collapse at the vertex nearest the square's centre (the pole, where the map is only Lipschitz)
    first = T.norm(dim=-1).argmin(dim=1)
    order = torch.stack([first, (first + 1) % 3, (first + 2) % 3], 1)
    T = torch.gather(T, 1, order[:, :, None].expand(-1, -1, 2))
    P0, P1, P2 = T[:, 0], T[:, 1], T[:, 2]
    pts, w = _tri_rule(q)
    xi, eta = pts[:, 0], pts[:, 1]
    X = P0[:, None] + xi[None, :, None] * (P1 - P0)[:, None] + (xi * eta)[None, :, None] * (P2 - P1)[:, None]
    area2 = ((P1 - P0)[:, 0] * (P2 - P0)[:, 1] - (P1 - P0)[:, 1] * (P2 - P0)[:, 0]).abs()  # 2·area
    W = area2[:, None] * w[None, :] * (math.pi / 2)  # dω = π/2 da db
    return X.reshape(-1, 2), W.reshape(-1)


def tent_quadrature(M: int, q: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Quadrature adapted to the M×M tent grid: (square points ``[N, 2]``, solid-angle weights
    ``[N]``), float64, Σw = 2π; N = 4 (M-1)² q². Exact for tent products (degree ≤ 4 per triangle)."""
    M = check_int("M", M, 2, MAX_TENTS)
    q = max(8, -(-32 // (M - 1))) if q is None else check_int("q", q, 2, 64)
    X, W = _tent_quadrature(M, q)
    return X.clone(), W.clone()


def _square_taps(ab: torch.Tensor, M: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The (at most) four nonzero tents at square points ``[N, 2]``: (index ``[N, 4]`` int64 into the M²
    basis, value ``[N, 4]`` float64), each value the bits :func:`_tents_at_square` gives that tent (the
    same hat formula at the two nodes around each coordinate; the other hats are 0 there)."""
    nodes = tent_nodes(M).to(ab.dtype)
    h = 2.0 / (M - 1)
    taps = []
    for c in (0, 1):
        i0, _ = _hat_taps(ab[:, c], M)
        i = torch.stack([i0, i0 + 1], -1)  # [N, 2] the nodes around the coordinate
        taps.append((i, (1.0 - (ab[:, c:c + 1] - nodes[i]).abs() / h).clamp_min(0)))
    (ia, ha), (ib, hb) = taps
    idx = (ia[:, :, None] * M + ib[:, None, :]).reshape(-1, 4)
    return idx, (ha[:, :, None] * hb[:, None, :]).reshape(-1, 4)


def tent_gram(M: int, q: int | None = None) -> torch.Tensor:
    """G_jk = ∫_H g_j g_k dω (Lehtinen & Kautz eq. 7) by quadrature, ``[M², M²]`` float64. Each point
    adds its 4 × 4 nonzero products (g_j W) g_k (:func:`_square_taps`) instead of a dense ``[N, M²]``
    GEMM (issue 42 §2: the MRT precompute's fixed cost; the same terms, summed in another order)."""
    X, W = tent_quadrature(M, q)
    idx, g = _square_taps(X, M)
    gw = g * W[:, None]
    G = torch.zeros(M * M * M * M, dtype=torch.float64)
    G.index_add_(0, (idx[:, :, None] * (M * M) + idx[:, None, :]).reshape(-1), (gw[:, :, None] * g[:, None, :]).reshape(-1))
    G = G.reshape(M * M, M * M)
    return 0.5 * (G + G.T)


def tent_gram_exact(M: int) -> torch.Tensor:
    """Closed form of G: (π/2) K ⊗ K with K the 1-D mass matrix of hats of spacing h = 2/(M-1)
    (diagonal 2h/3, h/3 at the two ends, off-diagonal h/6) — valid because the map is
    area-preserving with constant Jacobian π/2. ``[M², M²]`` float64."""
    M = check_int("M", M, 2, MAX_TENTS)
    h = 2.0 / (M - 1)
    K = torch.diag(torch.full((M,), 2 * h / 3, dtype=torch.float64))
    K[0, 0] = K[-1, -1] = h / 3
    i = torch.arange(M - 1)
    K[i, i + 1] = K[i + 1, i] = h / 6
    return (math.pi / 2) * torch.kron(K, K)


def change_of_basis(M: int, bands: int, q: int | None = None) -> torch.Tensor:
    """C_ji = ∫_H Y_i g_j dω (Lehtinen & Kautz eq. 7), ``[M², m²]`` float64 (m = bands)."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    X, W = tent_quadrature(M, q)
    idx, g = _square_taps(X, M)  # the 4 nonzero tents per point, not the dense [N, M²]
    y = eval_sh(square_to_hemisphere(X), bands, check=False)
    gw = g * W[:, None]
    C = torch.zeros(M * M, bands * bands, dtype=torch.float64)
    for t in range(4):  # the four taps (not a loop over points)
        C.index_add_(0, idx[:, t], gw[:, t:t + 1] * y)
    return C


def tent_project(fn, M: int, q: int | None = None) -> torch.Tensor:
    """Orthogonal projection of a hemispherical function onto the tents (Lehtinen & Kautz
    appendix A): coefficients G⁻¹ ⟨g, f⟩. ``fn(dirs [N, 3]) -> [N, *C]``; returns ``[*C, M²]``."""
    X, W = tent_quadrature(M, q)
    g = _tents_at_square(X, M)
    f = fn(square_to_hemisphere(X)).to(torch.float64)
    b = (g * W[:, None]).T @ f.reshape(f.shape[0], -1)  # [M², prod C]
    G = tent_gram(M, q)
    c = torch.linalg.solve(G, b)
    return c.T.reshape(*f.shape[1:], M * M)


def sh_to_tent(M: int, bands: int, q: int | None = None) -> torch.Tensor:
    """The projection matrix G⁻¹ C (Lehtinen & Kautz eq. 8), ``[M², m²]`` float64."""
    G = tent_gram(M, q)
    C = change_of_basis(M, bands, q)
    return torch.linalg.solve(G, C)


def error_matrix(M: int, bands: int, q: int | None = None) -> torch.Tensor:
    """E = A_m - Cᵀ G⁻¹ C (Lehtinen & Kautz eq. 10): ‖L_o - L_o^g‖²_H = lᵀ E l for the SH
    expansion l (m² coefficients) of exit radiance. ``[m², m²]`` float64, symmetric PSD."""
    G = tent_gram(M, q)
    C = change_of_basis(M, bands, q)
    E = hemisphere_gram(bands) - C.T @ torch.linalg.solve(G, C)
    return 0.5 * (E + E.T)


def average_psnr(M: int, bands: int, population: int = 1000, seed: int = 0, q: int | None = None) -> dict:
    """Average PSNR of the tent projection of random SH expansions (Lehtinen & Kautz eq. 11).

    PSNR = -10 log10 E{‖L_o - L_o^g‖²} (peak 1) with l uniform on the unit sphere of R^{m²}.
    Returns ``{"psnr": from the exact expectation tr(E)/m², "psnr_sampled": from the mean
    error of ``population`` random vectors (as the paper's populations of 1000),
    "mean_error", "max_error" (largest eigenvalue of E, the worst unit vector)}``.
    """
    E = error_matrix(M, bands, q)
    n2 = bands * bands
    mean = float(torch.trace(E)) / n2
    g = torch.Generator().manual_seed(int(seed))
    l = torch.randn(population, n2, generator=g, dtype=torch.float64)
    l = l / l.norm(dim=1, keepdim=True)
    err = ((l @ E) * l).sum(1)
    return {
        "M": M,
        "bands": bands,
        "psnr": -10 * math.log10(max(mean, 1e-300)),
        "psnr_sampled": -10 * math.log10(max(float(err.mean()), 1e-300)),
        "mean_error": mean,
        "max_error": float(torch.linalg.eigvalsh(E).max()),
    }


class MRTBasis:
    """The M×M tent basis with its matrices for exit radiance of ``bands`` (m) SH bands.

    Attributes (float64): ``G_`` [M², M²], ``C_`` [M², m²], ``P_`` = G⁻¹ C [M², m²],
    ``cond_G_`` (2-norm condition number of G), ``E_`` [m², m²] (eq. 10).
    """

    def __init__(self, M: int = 11, bands: int = 5, q: int | None = None):
        self.M = check_int("M (tents per side)", M, 2, MAX_TENTS)
        self.bands = check_int("bands", bands, 1, MAX_BANDS)
        self.q = None if q is None else check_int("q", q, 2, 64)
        self.G_ = tent_gram(self.M, self.q)
        self.C_ = change_of_basis(self.M, self.bands, self.q)
        self.P_ = torch.linalg.solve(self.G_, self.C_)
        ev = torch.linalg.eigvalsh(self.G_)
        self.cond_G_ = float(ev[-1] / ev[0])
        E = hemisphere_gram(self.bands) - self.C_.T @ self.P_
        self.E_ = 0.5 * (E + E.T)

    def __repr__(self) -> str:
        return f"MRTBasis(M={self.M}, bands={self.bands}, cond_G={self.cond_G_:.3g})"
