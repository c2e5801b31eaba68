"""prt_torch.brdf: reflectance models and BRDF matrices, against independent references
(Ramamoorthi 2002 A_l and eq. 3.37 by scipy quadrature, scalar re-implementations of the
published formulas, analytic least-squares projections)."""
import math

import numpy as np
import pytest
import torch
from scipy import integrate, special

from prt_torch import brdf as B
from prt_torch import sh

# Ramamoorthi 2002 eq. 4.11 values (A_0..A_4): π, 2π/3, π/4, 0, -π/24
A_PAPER = [math.pi, 2 * math.pi / 3, math.pi / 4, 0.0, -math.pi / 24]


def rand_dirs(n, seed, upper=True):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    if upper:
        d[:, 2] = d[:, 2].abs() + 1e-3
        d = d / d.norm(dim=-1, keepdim=True)
    return d


# --------------------------------------------------------------------- Lambertian
def test_lambertian_normal_parameterised_matrix_is_diagonal_A_l():
    """Double projection over S²×S² of the Lambertian kernel max(n·s,0)/π, exit radiance
    parameterised by the normal n, is diag(A_l/π) (Ramamoorthi & Hanrahan's irradiance map)."""
    K = lambda s, v: (v * s).sum(-1).clamp_min(0) / math.pi  # noqa: E731
    M = B.double_project(K, 5, 5, domain="sphere", quad_bands=36)[0]
    l, _ = sh.lm_of(5)
    want = torch.diag(torch.tensor(A_PAPER, dtype=torch.float64)[l] / math.pi)
    assert torch.allclose(M, want, atol=2e-4), (M - want).abs().max()
    # the analytic form agrees exactly
    lam = B.Lambertian(1.0)
    Z = B.zonal_matrix(lam.lobes(5)[0][1], about="normal")
    assert torch.allclose(Z, want, atol=1e-12)


def test_lambertian_zero_hemisphere_matrix_is_rank_one_with_A_l():
    """Local-frame B (zero hemisphere) of a Lambertian = a cᵀ: a_i = ∫_H y_i (view), c_j =
    (kd/π) ∫_H y_j s_z = kd A_l/(π Λ_l) for m = 0 (light)."""
    kd = 0.7
    Bm = B.brdf_matrix(B.Lambertian(kd), 4, 5, quad_bands=12)  # polynomial integrands: exact
    l_in, m_in = sh.lm_of(5)
    c = torch.zeros(25, dtype=torch.float64)
    for L in range(5):
        c[L * L + L] = kd * A_PAPER[L] / (math.pi * math.sqrt(4 * math.pi / (2 * L + 1)))
    a = torch.zeros(16, dtype=torch.float64)
    for L in range(4):  # ∫_H y_l0 = 2π N_l ∫_0^1 P_l(t) dt (scipy), m ≠ 0 integrate to 0 over φ
        val, _ = integrate.quad(lambda t: special.eval_legendre(L, t), 0, 1)
        a[L * L + L] = 2 * math.pi * math.sqrt((2 * L + 1) / (4 * math.pi)) * val
    assert torch.allclose(Bm, torch.outer(a, c), atol=1e-12)


def test_lambertian_least_squares_matrix_single_entry():
    """With Sloan 2003 eq. (1) on both sides the Lambertian B maps the LS coefficient of z to the
    constant: the only nonzero entry is (00, 10) = sqrt(4π)·sqrt(4π/3)·kd/π = 4 kd/√3."""
    kd = 0.6
    Bm = B.brdf_matrix(B.Lambertian(kd), 3, 3, projection="least_squares")
    want = torch.zeros(9, 9, dtype=torch.float64)
    want[0, 2] = 4 * kd / math.sqrt(3)
    assert torch.allclose(Bm, want, atol=1e-10)


# --------------------------------------------------------------------- Phong
@pytest.mark.parametrize("s", [4.0, 16.0])
def test_phong_zonal_coefficients_vs_quadrature(s):
    """Λ_l h_l of the normalised lobe (s+1)/(2π) max(t,0)^s (Ramamoorthi eq. 3.37) equals
    (s+1) ∫_0^1 t^s P_l(t) dt by scipy quadrature."""
    h = B.Phong(s, form="reflection").lobes(8)[1][1]
    f = h * sh.band_factor(8)
    ref = [(s + 1) * integrate.quad(lambda t: t**s * special.eval_legendre(L, t), 0, 1)[0] for L in range(8)]
    assert np.allclose(f.numpy(), ref, atol=1e-12)


def test_phong_sphere_matrix_matches_analytic_zonal():
    """Reflection-form Phong extended to S²×S²: B is diag((-1)^m f_l) with f_l from eq. 3.37."""
    s = 24.0
    ph = B.Phong(s, ks=1.0, kd=0.0, form="reflection")
    Bm = B.brdf_matrix(ph, 5, 5, projection="sphere", quad_bands=40)
    l, m = sh.lm_of(5)
    f = torch.tensor([(s + 1) * integrate.quad(lambda t: t**s * special.eval_legendre(L, t), 0, 1)[0] for L in range(5)],
                     dtype=torch.float64)
    want = torch.diag(f[l] * torch.where(m % 2 == 0, 1.0, -1.0).double())
    assert torch.allclose(Bm, want, atol=1e-6), (Bm - want).abs().max()


def test_brdf_matrix_quadrature_converges():
    br = B.Phong(16.0, kd=0.2)
    a = B.brdf_matrix(br, 3, 3)
    b = B.brdf_matrix(br, 3, 3, quad_bands=44)
    assert (a - b).abs().max() / b.abs().max() < 1e-3


# --------------------------------------------------------------------- models vs scalar formulas
def _as_scalar(k1, k2, nu, nv, rs, rd):
    """Ashikhmin & Shirley 2000 eq. 4–5, scalar, written from the paper."""
    h = k1 + k2
    h = h / np.linalg.norm(h)
    kh = float(k1 @ h)
    F = rs + (1 - rs) * (1 - kh) ** 5
    e = (nu * h[0] ** 2 + nv * h[1] ** 2) / (1 - h[2] ** 2)
    spec = math.sqrt((nu + 1) * (nv + 1)) / (8 * math.pi) * h[2] ** e / (kh * max(k1[2], k2[2])) * F
    diff = 28 * rd / (23 * math.pi) * (1 - rs) * (1 - (1 - k1[2] / 2) ** 5) * (1 - (1 - k2[2] / 2) ** 5)
    return spec + diff


def _ward_scalar(wi, wo, ax, ay, rs, rd):
    h = wi + wo
    h = h / np.linalg.norm(h)
    e = -((h[0] / ax) ** 2 + (h[1] / ay) ** 2) / h[2] ** 2
    return rd / math.pi + rs * math.exp(e) / (4 * math.pi * ax * ay * math.sqrt(wi[2] * wo[2]))


def test_ashikhmin_shirley_and_ward_match_published_formulas():
    wi, wo = rand_dirs(20, 1), rand_dirs(20, 2)
    asb = B.AshikhminShirley(40.0, 10.0, rs=0.05, rd=0.3)
    got = asb(wi, wo)
    ref = [_as_scalar(wi[i].numpy(), wo[i].numpy(), 40, 10, 0.05, 0.3) for i in range(20)]
    assert np.allclose(got.numpy(), ref, rtol=1e-10)
    w = B.Ward(0.15, 0.4, rs=0.1, rd=0.2)
    ref = [_ward_scalar(wi[i].numpy(), wo[i].numpy(), 0.15, 0.4, 0.1, 0.2) for i in range(20)]
    assert np.allclose(w(wi, wo).numpy(), ref, rtol=1e-10)


@pytest.mark.parametrize("model", [B.Lambertian(0.5), B.Phong(20.0, kd=0.1), B.BlinnPhong(30.0, kd=0.1),
                                   B.AshikhminShirley(30.0, 5.0, rd=0.2), B.Ward(0.2, 0.3, rd=0.1)])
def test_reciprocity_and_zero_below_horizon(model):
    wi, wo = rand_dirs(50, 3), rand_dirs(50, 4)
    if not isinstance(model, B.Phong):  # Phong's r·wi is symmetric too
        pass
    assert torch.allclose(model(wi, wo), model(wo, wi), rtol=1e-12)
    below = wi.clone()
    below[:, 2] = -below[:, 2]
    assert (model(below, wo) == 0).all() and (model.cosine_weighted(below, wo) == 0).all()


def test_anisotropy_follows_tangent():
    """N_u along x: swapping N_u, N_v equals rotating both directions by 90° about the normal."""
    wi, wo = rand_dirs(30, 5), rand_dirs(30, 6)
    rot = lambda d: torch.stack([-d[:, 1], d[:, 0], d[:, 2]], -1)  # noqa: E731
    a = B.AshikhminShirley(40.0, 5.0)(wi, wo)
    b = B.AshikhminShirley(5.0, 40.0)(rot(wi), rot(wo))
    assert torch.allclose(a, b, rtol=1e-10)
    assert not torch.allclose(a, B.AshikhminShirley(40.0, 5.0)(rot(wi), rot(wo)), rtol=1e-3)


# --------------------------------------------------------------------- matrix options
def test_non_square_drop_and_window():
    asb = B.AshikhminShirley(10.0, 10.0, rd=0.2)
    z = B.brdf_matrix(asb, 5, 5, quad_bands=16)
    full = sh.hemisphere_projector(5) @ z @ sh.hemisphere_projector(5)
    dropped = sh.hemisphere_projector(5, drop=[(1, 0)]) @ z @ sh.hemisphere_projector(5)
    got = B.brdf_matrix(asb, 5, 5, projection="least_squares", drop_out=[(1, 0)], quad_bands=16)
    assert got.shape == (24, 25) and torch.allclose(got, dropped)
    assert B.output_index(5, [(1, 0)]).tolist() == [0, 1] + list(range(3, 25))
    assert not torch.allclose(full[[0, 1] + list(range(3, 25))], dropped, atol=1e-6)
    # zero-hemisphere: windowing scales row band l by w_l
    w = sh.window(5, "hanning")
    zw = B.brdf_matrix(asb, 5, 5, window="hanning", quad_bands=16)
    l, _ = sh.lm_of(5)
    assert torch.allclose(zw, z * w[l][:, None])


def test_spatially_varying_parameters_and_dedup():
    s = torch.tensor([8.0, 16.0, 8.0])
    br = B.Phong(s, kd=0.1)
    Ms = B.brdf_matrix(br, 3, 3, quad_bands=12)
    assert Ms.shape == (3, 9, 9)
    assert torch.allclose(Ms[1], B.brdf_matrix(B.Phong(16.0, kd=0.1), 3, 3, quad_bands=12))
    U, idx = B.brdf_matrices(br, 3, 3, quad_bands=12)
    assert U.shape[0] == 2 and torch.allclose(U[idx], Ms)
    # per-vertex evaluation broadcasts [V,1] parameters against [V,N,3] directions
    wi, wo = rand_dirs(12, 7).reshape(3, 4, 3), rand_dirs(12, 8).reshape(3, 4, 3)
    f = br.view(3, 1)(wi, wo)
    assert torch.allclose(f[2], B.Phong(8.0, kd=0.1)(wi[2], wo[2]))


# --------------------------------------------------------------------- bad input
def test_bad_parameters_are_refused():
    with pytest.raises(ValueError, match="Phong exponent"):
        B.Phong(-1.0)
    with pytest.raises(ValueError, match="N_u"):
        B.AshikhminShirley(0.0, 10.0)
    with pytest.raises(ValueError, match="N_v"):
        B.AshikhminShirley(10.0, torch.tensor([5.0, -2.0]))
    with pytest.raises(ValueError, match="alpha"):
        B.Ward(0.0)
    with pytest.raises(ValueError, match="kd"):
        B.Lambertian(1.5)
    with pytest.raises(ValueError, match="not known"):
        B.make_brdf("cook_torrance")
    with pytest.raises(ValueError, match="bands_out"):
        B.brdf_matrix(B.Lambertian(), 0)
    with pytest.raises(ValueError, match="full-sphere"):
        B.brdf_matrix(B.AshikhminShirley(), 3, projection="sphere")
    with pytest.raises(ValueError, match="drop_out"):
        B.brdf_matrix(B.Lambertian(), 3, projection="zero", drop_out=[(1, 0)])
    assert B.make_brdf(**B.AshikhminShirley(40.0, 10.0).meta()).meta() == B.AshikhminShirley(40.0, 10.0).meta()
