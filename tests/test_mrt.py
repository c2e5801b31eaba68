"""Matrix radiance transfer basis (Lehtinen & Kautz 2003 §4.3, §5, appendix A), against
closed forms, finite-difference Jacobians, exact SH hemisphere integrals and an independent
midpoint-rule sampling of the projection error."""
import math

import pytest
import torch

from prt_torch import sh
from prt_torch.transfer import tents as mrt


def test_concentric_map_round_trip_and_area_preservation():
    g = torch.Generator().manual_seed(0)
    ab = torch.rand(500, 2, generator=g, dtype=torch.float64) * 2 - 1
    d = mrt.square_to_hemisphere(ab)
    assert torch.allclose(d.norm(dim=-1), torch.ones(500, dtype=torch.float64), atol=1e-14)
    assert (d[:, 2] >= 0).all()
    assert torch.allclose(mrt.hemisphere_to_square(d), ab, atol=1e-12)
    # |∂d/∂a × ∂d/∂b| = π/2 everywhere (area preserving), by central differences
    h = 1e-6
    ab = ab * 0.98
    da = (mrt.square_to_hemisphere(ab + torch.tensor([h, 0.0])) - mrt.square_to_hemisphere(ab - torch.tensor([h, 0.0]))) / (2 * h)
    db = (mrt.square_to_hemisphere(ab + torch.tensor([0.0, h])) - mrt.square_to_hemisphere(ab - torch.tensor([0.0, h]))) / (2 * h)
    jac = torch.cross(da, db, dim=-1).norm(dim=-1)
    away = (ab[:, 0].abs() - ab[:, 1].abs()).abs() > 1e-3  # off the map's seams
    assert torch.allclose(jac[away], torch.full_like(jac[away], math.pi / 2), rtol=1e-6)


@pytest.mark.parametrize("M", [2, 3, 8, 11])
def test_gram_matrix_matches_closed_form(M):
    G = mrt.tent_gram(M)
    assert torch.allclose(G, mrt.tent_gram_exact(M), atol=1e-14)
    assert abs(float(G.sum()) - 2 * math.pi) < 1e-12  # partition of unity: Σ_jk G_jk = |H|
    b = mrt.MRTBasis(M, 3)
    assert 1.0 < b.cond_G_ < 40.0  # K⊗K: cond(K)² with cond(K) ≤ ~6 at any M


@pytest.mark.parametrize("M", [3, 11])
def test_change_of_basis_partition_of_unity(M):
    """Σ_j C_ji = ∫_H Y_i (tents sum to one), vs the exact Gauss hemisphere rule."""
    C = mrt.change_of_basis(M, 8)
    dirs, w = sh.gauss_hemisphere(16)
    ref = (sh.eval_sh(dirs, 8) * w[:, None]).sum(0)
    assert torch.allclose(C.sum(0), ref, atol=1e-11)


def test_projection_reproduces_tent_span_exactly():
    M = 7
    g = torch.Generator().manual_seed(1)
    c = torch.randn(M * M, generator=g, dtype=torch.float64)
    got = mrt.tent_project(lambda d: mrt.tent_eval(c.expand(d.shape[0], -1), d), M)
    assert torch.allclose(got, c, atol=1e-11)
    # the constant Y00 is in the span: G⁻¹ C e_00 = Y00 everywhere, and E e_00 = 0
    P = mrt.sh_to_tent(M, 4)
    assert torch.allclose(P[:, 0], torch.full((M * M,), 0.5 / math.sqrt(math.pi), dtype=torch.float64), atol=1e-12)
    assert float(mrt.error_matrix(M, 4)[0].abs().max()) < 1e-12


def test_error_matrix_equals_sampled_projection_error():
    """lᵀ E l (eq. 10) vs ∫_H (L_o - L_o^g)² by an independent midpoint rule on the square."""
    M, m = 5, 5
    E = mrt.error_matrix(M, m)
    P = mrt.sh_to_tent(M, m)
    n = 500
    x = (torch.arange(n, dtype=torch.float64) + 0.5) * (2.0 / n) - 1
    ab = torch.stack(torch.meshgrid(x, x, indexing="ij"), -1).reshape(-1, 2)
    d = mrt.square_to_hemisphere(ab)
    w = (math.pi / 2) * (2.0 / n) ** 2
    y = sh.eval_sh(d, m)
    g = torch.Generator().manual_seed(2)
    for _ in range(3):
        l = torch.randn(m * m, generator=g, dtype=torch.float64)
        l = l / l.norm()
        f = y @ l
        fg = mrt.tent_eval((P @ l).expand(d.shape[0], -1), d)
        sampled = float(((f - fg) ** 2).sum() * w)
        assert abs(sampled - float(l @ E @ l)) < 2e-3 * sampled + 1e-7


def test_psnr_trend_of_figure_2():
    """PSNR rises with M and falls with m (Lehtinen & Kautz Fig. 2); the sampled population of
    1000 agrees with the exact expectation tr(E)/m²."""
    by_M = [mrt.average_psnr(M, 5)["psnr"] for M in (3, 5, 7, 9, 11)]
    assert all(b > a for a, b in zip(by_M, by_M[1:]))
    by_m = [mrt.average_psnr(11, m)["psnr"] for m in (3, 5, 8)]
    assert all(b < a for a, b in zip(by_m, by_m[1:]))
    r = mrt.average_psnr(11, 5, population=1000)
    assert abs(r["psnr"] - r["psnr_sampled"]) < 0.5


def test_four_taps_match_dense_evaluation():
    M = 6
    g = torch.Generator().manual_seed(3)
    d = torch.randn(200, 3, generator=g, dtype=torch.float64)
    d[:, 2] = d[:, 2].abs()
    d = d / d.norm(dim=-1, keepdim=True)
    idx, w = mrt.tent_taps(d, M)
    assert torch.allclose(w.sum(-1), torch.ones(200, dtype=torch.float64)) and (w >= 0).all()
    dense = mrt._tents_at_square(mrt.hemisphere_to_square(d), M)
    sparse = torch.zeros_like(dense).scatter_add_(1, idx, w)
    assert torch.allclose(dense, sparse, atol=1e-12)


def test_bad_sizes_are_refused():
    with pytest.raises(ValueError, match="M"):
        mrt.MRTBasis(1, 5)
    with pytest.raises(ValueError, match="M"):
        mrt.MRTBasis(200, 5)
    with pytest.raises(ValueError, match="bands"):
        mrt.MRTBasis(5, 0)


@pytest.mark.parametrize("M", [2, 5, 11])
def test_sparse_tent_quadrature_equals_the_dense_sums(M):
    """G and C from each point's four nonzero tents (issue 42 §2: the MRT precompute's fixed cost) equal the
    dense quadrature sums (g W)ᵀ g and (g W)ᵀ y written out here to float64 rounding; the taps carry the dense
    tent values bit for bit (every other tent is 0 at the point)."""
    X, W = mrt.tent_quadrature(M)
    g = mrt._tents_at_square(X, M)
    idx, val = mrt._square_taps(X, M)
    assert torch.equal(torch.zeros_like(g).scatter_add_(1, idx, val), g)
    assert int((g > 0).sum(1).max()) <= 4
    G = (g * W[:, None]).T @ g
    # float64 rounding of a GEMM over the quadrature points: its blocking (so its error) is the BLAS's per CPU —
    # 1.11e-15 = 5 ulps of 0.698 on an Intel Xeon (AVX-512), under 1e-15 on an AMD Zen 3: 32 ulps of the largest entry
    assert float((mrt.tent_gram(M) - 0.5 * (G + G.T)).abs().max()) < 32 * torch.finfo(torch.float64).eps * float(G.abs().max())
    y = sh.eval_sh(mrt.square_to_hemisphere(X), 6)
    assert float((mrt.change_of_basis(M, 6) - (g * W[:, None]).T @ y).abs().max()) < 1e-14
