"""Tests of prt_torch.sh against independent references: scipy's complex harmonics, exact
quadrature, the thesis' printed constants (Ramamoorthi 2002) and Sloan 2003's appendix numbers."""
import math

import numpy as np
import pytest
import torch
from scipy.special import sph_harm_y

from prt_torch import sh


def unit(n, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return (d / d.norm(dim=-1, keepdim=True)).to(dtype)


def scipy_real_sh(dirs: np.ndarray, bands: int) -> np.ndarray:
    """Real graphics-convention SH from scipy's complex Y_l^m (which has the Condon-Shortley phase)."""
    x, y, z = dirs.T
    theta, phi = np.arccos(np.clip(z, -1, 1)), np.arctan2(y, x)
    out = np.zeros((dirs.shape[0], bands * bands))
    for l in range(bands):
        for m in range(-l, l + 1):
            c = sph_harm_y(l, abs(m), theta, phi)
            k = l * (l + 1) + m
            if m > 0:
                out[:, k] = math.sqrt(2) * (-1) ** m * c.real
            elif m < 0:
                out[:, k] = math.sqrt(2) * (-1) ** m * c.imag
            else:
                out[:, k] = c.real
    return out


# ---------------------------------------------------------------- basis

@pytest.mark.parametrize("backend", ["torch", "sphericart"])
def test_basis_matches_scipy_at_30_bands(backend):
    d = unit(400, seed=1)
    d = torch.cat([d, torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0]], dtype=torch.float64)])
    ours = sh.eval_sh(d, 31, backend=backend).numpy()
    ref = scipy_real_sh(d.numpy(), 31)
    assert np.abs(ours - ref).max() < 1e-10


def test_backends_agree_float32_and_float64():
    d = unit(1000, seed=2)
    for dtype, tol in [(torch.float64, 1e-12), (torch.float32, 2e-5)]:
        a = sh.eval_sh(d.to(dtype), 16, backend="torch")
        b = sh.eval_sh(d.to(dtype), 16, backend="sphericart")
        ref = sh.eval_sh(d, 16, backend="torch")
        assert a.dtype == b.dtype == dtype
        assert (a.double() - ref).abs().max() < tol
        assert (b.double() - ref).abs().max() < tol


def test_batched_leading_shape():
    d = unit(60, seed=3).reshape(3, 4, 5, 3)
    y = sh.eval_sh(d, 6)
    assert y.shape == (3, 4, 5, 36)
    assert torch.allclose(y.reshape(-1, 36), sh.eval_sh(d.reshape(-1, 3), 6))


def test_constants_of_eq_4_5():
    d = unit(50, seed=4)
    x, y, z = d.T
    Y = sh.eval_sh(d, 3)
    expect = torch.stack([
        torch.full_like(x, 0.282095),
        0.488603 * y, 0.488603 * z, 0.488603 * x,
        1.092548 * x * y, 1.092548 * y * z, 0.315392 * (3 * z * z - 1), 1.092548 * x * z,
        0.546274 * (x * x - y * y),
    ], dim=-1)
    assert (Y - expect).abs().max() < 2e-6  # the thesis prints 6 decimals


def test_orthonormality_by_exact_quadrature_30_bands():
    dirs, w = sh.gauss_sphere(30)
    Y = sh.eval_sh(dirs, 30)
    G = (Y * w[:, None]).T @ Y
    assert (G - torch.eye(900, dtype=torch.float64)).abs().max() < 1e-11


def test_zonal_basis_is_m0_column():
    d = unit(30, seed=5)
    full = sh.eval_sh(d, 8)
    zon = sh.eval_zonal_basis(d[:, 2], 8)
    idx = [l * (l + 1) for l in range(8)]
    assert torch.allclose(zon, full[:, idx], atol=1e-13)


# ---------------------------------------------------------------- quadrature / projection

def test_quadrature_weights_and_constant_projection():
    for dirs, w in [sh.gauss_sphere(8), sh.stratified_sphere(1000, 3), sh.fibonacci_sphere(1000)]:
        assert math.isclose(float(w.sum()), 4 * math.pi, rel_tol=1e-12)
    dirs, w = sh.latlong_grid(64, 128)
    assert math.isclose(float(w.sum()), 4 * math.pi, rel_tol=1e-12)
    c = sh.project(torch.ones(dirs.shape[:2]).reshape(-1), dirs.reshape(-1, 3), w.reshape(-1), 4)
    assert abs(float(c[0]) - 2 * math.sqrt(math.pi)) < 1e-12
    assert c[1:].abs().max() < 1e-3  # lat-long resolution error


def test_project_reconstruct_round_trip_and_channels():
    g = torch.Generator().manual_seed(0)
    coeffs = torch.randn(3, 36, generator=g, dtype=torch.float64)
    back = sh.project_callable(lambda d: sh.reconstruct(coeffs, d), 6)
    assert back.shape == (3, 36)
    assert (back - coeffs).abs().max() < 1e-12


def test_stratified_monte_carlo_converges_and_is_deterministic():
    def f(d):
        return torch.exp(d[:, 0]) + d[:, 2] ** 2
    exact = sh.project_callable(f, 3, oversample=8)
    a = sh.project_callable(f, 3, quadrature="stratified", n=40000, seed=7)
    b = sh.project_callable(f, 3, quadrature="stratified", n=40000, seed=7)
    assert torch.equal(a, b)
    assert (a - exact).abs().max() < 5e-3


# ---------------------------------------------------------------- rotation

@pytest.mark.parametrize("bands", [2, 3, 5, 8, 10])
def test_rotation_properties(bands):
    R = sh.random_rotations(6, seed=bands)
    D = sh.rotation_matrix(R, bands)
    eye = torch.eye(bands * bands, dtype=torch.float64)
    assert (D @ D.transpose(-1, -2) - eye).abs().max() < 1e-12
    R2 = sh.random_rotations(6, seed=100 + bands)
    D12 = sh.rotation_matrix(R @ R2, bands)
    assert (D12 - D @ sh.rotation_matrix(R2, bands)).abs().max() < 1e-12
    s = unit(6, seed=bands)
    lhs = sh.eval_sh((R @ s[:, :, None])[..., 0], bands)
    rhs = (D @ sh.eval_sh(s, bands)[:, :, None])[..., 0]
    assert (lhs - rhs).abs().max() < 1e-12
    # rotate a function: g(s) = f(Rᵀ s) has coefficients D(R) c
    c = torch.randn(6, bands * bands, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    g = sh.rotate(c, R)
    v = unit(6, seed=50 + bands)
    f_at = (sh.eval_sh((R.transpose(1, 2) @ v[:, :, None])[..., 0], bands) * c).sum(-1)
    g_at = (sh.eval_sh(v, bands) * g).sum(-1)
    assert (f_at - g_at).abs().max() < 1e-11


def test_rotation_against_quadrature_projection_peer():
    """D(R)_ij = ∫ y_i(R s) y_j(s) ds computed by exact quadrature: an independent construction."""
    R = sh.random_rotations(2, seed=9)
    dirs, w = sh.gauss_sphere(7, oversample=2)
    Yrs = sh.eval_sh(torch.einsum("bij,nj->bni", R, dirs), 7)
    Ys = sh.eval_sh(dirs, 7)
    D_quad = torch.einsum("bni,n,nj->bij", Yrs, w, Ys)
    assert (D_quad - sh.rotation_matrix(R, 7)).abs().max() < 1e-12


def test_rotation_float32_and_bad_rotations():
    R = sh.random_rotations(100, seed=0)
    d64 = sh.rotation_matrix(R, 6)
    d32 = sh.rotation_matrix(R.float(), 6)
    assert d32.dtype == torch.float32 and (d32.double() - d64).abs().max() < 1e-5
    with pytest.raises(ValueError, match="proper rotations"):
        sh.rotation_blocks(torch.diag(torch.tensor([1.0, 1.0, -1.0])), 3)
    with pytest.raises(ValueError, match="proper rotations"):
        sh.rotation_blocks(2 * torch.eye(3), 3)


# ---------------------------------------------------------------- zonal harmonics

def test_clamped_cosine_A_matches_eq_4_12_and_quadrature():
    A = sh.clamped_cosine_A(7)
    paper = [3.141593, 2.094395, 0.785398, 0.0, -0.130900, 0.0, 0.049087]
    assert np.allclose(A.numpy(), paper, atol=1e-6)
    quad = sh.zonal_project(lambda t: t, 20, lower=0.0, n=64) * sh.band_factor(20)
    assert (quad - sh.clamped_cosine_A(20)).abs().max() < 1e-13


def test_irradiance_constants_c1_to_c5_of_eq_4_15():
    A = sh.clamped_cosine_A(3)
    # basis normalisations read off our own basis: Y22 at +x, Y20 at +z, etc.
    Y = sh.eval_sh(torch.tensor([[1.0, 0, 0], [0, 0, 1.0]], dtype=torch.float64), 3)
    k22 = float(Y[0, 8])            # 0.546274 (x² - y²)
    k1 = float(Y[0, 3])             # 0.488603 x
    k20 = float(Y[1, 6]) / 2        # 0.315392 (3z² - 1) at z=1 -> 2·0.315392
    k00 = float(Y[0, 0])
    c = [A[2] * k22, A[1] * k1 / 2, 3 * A[2] * k20, A[0] * k00, A[2] * k20]
    paper = [0.429043, 0.511664, 0.743125, 0.886227, 0.247708]
    assert np.allclose([float(v) for v in c], paper, atol=1e-6)


@pytest.mark.parametrize("s", [0.0, 1.0, 7.5, 32.0, 500.0])
def test_phong_eq_3_37_against_quadrature(s):
    bands = 12
    def lobe(t):
        return (s + 1) / (2 * math.pi) * t.clamp_min(0) ** s
    quad = sh.zonal_project(lobe, bands, lower=0.0, n=300)
    assert (sh.phong(s, bands) - quad).abs().max() < 1e-10
    # unit energy: Λ_0 h_0 = 1
    assert math.isclose(float(sh.phong(s, 1)[0] * sh.band_factor(1)[0]), 1.0)


def test_phong_spatially_varying_shape():
    h = sh.phong(torch.tensor([[1.0, 10.0], [100.0, 3.0]]), 5)
    assert h.shape == (2, 2, 5)
    assert torch.allclose(h[1, 0], sh.phong(100.0, 5))


def test_microfacet_eq_3_51_approximates_exact_lobe():
    errs = []
    for sigma in (0.02, 0.05, 0.1, 0.2):
        approx = sh.microfacet(sigma, 12) * sh.band_factor(12)
        exact = sh.microfacet(sigma, 12, exact=True) * sh.band_factor(12)
        # eq. 3.51 is an asymptotic approximation: its error vanishes linearly with σ
        errs.append(float((approx - exact).abs().max()))
        assert errs[-1] < 0.5 * sigma, (sigma, errs[-1])
        # lobe energy: 1 - (2/3)σ² + O(σ⁴) (sin θ ≈ θ - θ³/6 under the Gaussian, E[θ²] = 4σ²)
        assert abs(float(exact[0]) - (1 - 2 * sigma**2 / 3)) < 2 * sigma**4
    assert errs == sorted(errs)


def test_rotate_zonal_and_funk_hecke_convolution_vs_brute_force():
    """Irradiance ∫ L(s) max(n·s, 0) ds by brute-force quadrature equals the SH convolution
    with the clamped cosine evaluated at n (Funk–Hecke), and rotate_zonal projects the
    rotated kernel exactly."""
    g = torch.Generator().manual_seed(5)
    L = torch.randn(25, generator=g, dtype=torch.float64)
    normals = unit(5, seed=6)
    dirs, w = sh.gauss_hemisphere(40)  # hemisphere about +z, rotated per normal below
    E_brute = []
    for n in normals:  # 5 normals: a tiny loop in a test
        # frame with n as z
        t = torch.linalg.svd(n[None, :]).Vh[1:]  # two vectors orthogonal to n
        F = torch.cat([t, n[None]], 0)
        if torch.linalg.det(F) < 0:
            F[0] = -F[0]
        world = dirs @ F  # local -> world
        E_brute.append(float((sh.reconstruct(L, world) * dirs[:, 2] * w).sum()))
    E_sh = sh.reconstruct(sh.convolve(L, sh.clamped_cosine(5)), normals)
    assert np.allclose(E_sh.numpy(), E_brute, atol=1e-10)
    # rotate_zonal = projection of max(n·s, 0)^3 about n
    h = sh.zonal_project(lambda t: t.clamp_min(0) ** 3, 6, lower=0.0, n=64)
    f = sh.rotate_zonal(h, normals[:1])
    proj = sh.project_callable(lambda d: (d @ normals[0]).clamp_min(0) ** 3, 6, oversample=8)
    assert (f[0] - proj).abs().max() < 1e-3  # kink at the horizon limits the Gauss rule


def test_windows():
    w = sh.window(5, "hanning")
    assert math.isclose(float(w[0]), 1.0) and float(w[-1]) > 0 and torch.all(w[1:] < w[:-1])
    assert torch.allclose(sh.window(6, "gaussian", sigma=0.1), torch.exp(-(0.1 * torch.arange(6.0, dtype=torch.float64)) ** 2))
    assert torch.equal(sh.window(4, "none"), torch.ones(4, dtype=torch.float64))
    lz = sh.window(6, "lanczos")
    assert math.isclose(float(lz[3]), math.sin(math.pi * 0.5) / (math.pi * 0.5))


# ---------------------------------------------------------------- band selection (eq. 5.15–5.17)

def test_bands_for_energy():
    c = torch.zeros(2, 36, dtype=torch.float64)
    for l, e in enumerate([50.0, 30.0, 15.0, 4.0, 0.9, 0.1]):
        c[0, l * l] = math.sqrt(e)  # channel 0 carries all energy
    assert sh.bands_for_energy(c, 0.10) == 3   # 95 % >= 90 %
    assert sh.bands_for_energy(c, 0.02) == 4   # 99 %
    assert sh.bands_for_energy(c, 0.0005) == 6
    # against the energy of a non-band-limited original (eq. 5.16): total larger than the coefficients hold
    with pytest.raises(ValueError, match="keep only"):
        sh.bands_for_energy(c, 0.01, total_energy=200.0)
    # zonal (eq. 5.17): Phong lobe needs more bands as s grows
    n10 = sh.bands_for_energy(sh.phong(10.0, 40), 0.01, zonal=True)
    n100 = sh.bands_for_energy(sh.phong(100.0, 40), 0.01, zonal=True)
    assert n10 < n100


# ---------------------------------------------------------------- hemispherical projection (Sloan 2003 §9)

def test_sloan_appendix_numbers():
    s = torch.linalg.svdvals(sh.hemisphere_gram(5))
    assert abs(float(s[-1]) - 6.59e-6) < 0.01e-6
    assert abs(float(s[-2]) - 3.10e-4) < 0.01e-4
    r = sh.redundancy_errors(5)
    assert int(r.argmin()) == sh.sh_index(1, 0) and abs(float(r.min()) - 1.48e-5) < 0.01e-5
    # (method, basis bands) -> (worst, average) as printed, each to half a unit of its last digit
    cases = [
        (("zero", None), (0.125, 0.0005), (0.0402, 0.00005)),
        (("odd", 8), (0.145, 0.0005), (0.044, 0.0005)),
        (("even", 7), (0.022, 0.0005), (0.0036, 0.00005)),
        (("even", 5), (0.193, 0.0005), (0.030, 0.0005)),
    ]
    for (method, basis), (worst, tw), (avg, ta) in cases:
        w, a = sh.projection_error(5, method, basis)
        assert abs(w - worst) <= tw, (method, basis, w)
        assert abs(a - avg) <= ta, (method, basis, a)
    w, a = sh.projection_error(5, "least_squares")
    assert w < 1e-15


def test_least_squares_projection_against_numpy_lstsq():
    """Fit a non-band-limited hemispherical function by least squares on dense samples with
    numpy (independent), compare with A⁻¹ b."""
    bands = 4
    def f(d):
        return torch.exp(2 * d[:, 0]) * d[:, 2] + 0.3
    dirs, w = sh.gauss_hemisphere(bands, oversample=12)
    b = sh.project(f(dirs), dirs, w, bands)
    c = sh.project_hemisphere(b, "least_squares")
    Y = sh.eval_sh(dirs, bands).numpy() * np.sqrt(w.numpy())[:, None]
    ref, *_ = np.linalg.lstsq(Y, f(dirs).numpy() * np.sqrt(w.numpy()), rcond=None)
    assert np.abs(c.numpy() - ref).max() < 1e-8


def test_least_squares_reproduces_band_limited_on_hemisphere_and_drop():
    g = torch.Generator().manual_seed(3)
    c = torch.randn(4, 25, generator=g, dtype=torch.float64)
    b = c @ sh.hemisphere_gram(5).T  # zero-hemisphere projection of c restricted to H
    assert (sh.project_hemisphere(b, "least_squares") - c).abs().max() < 1e-8
    # dropping (1,0): 24 coefficients, error over H bounded by the redundancy error
    P = sh.hemisphere_projector(5, drop=[(1, 0)])
    assert P.shape == (24, 25)
    keep = [k for k in range(25) if k != 2]
    c24 = b @ P.T
    A = sh.hemisphere_gram(5)
    full = torch.zeros(4, 25, dtype=torch.float64)
    full[:, keep] = c24
    err = torch.einsum("bi,ij,bj->b", full - c, A, full - c)
    assert torch.all(err <= (c[:, 2] ** 2) * 1.48e-5 * 1.01 + 1e-12)


def test_near_singular_gram_is_handled_explicitly():
    with pytest.raises(ValueError, match="numerically singular"):
        sh.hemisphere_projector(14, "least_squares")
    P = sh.hemisphere_projector(14, "least_squares", rcond=1e-12)
    assert torch.isfinite(P).all()
    # reflection projections: doubling of the matching z-parity
    P = sh.hemisphere_projector(3, "even")
    l, m = sh.lm_of(3)
    assert torch.equal(torch.diagonal(P), 2.0 * ((l + m) % 2 == 0).double())


# ---------------------------------------------------------------- bad input

@pytest.mark.parametrize(
    "dirs, match",
    [
        (torch.tensor([[1.0, 1.0, 0.0]]), "unit vectors"),
        (torch.tensor([[0.0, 0.0, 0.0]]), "unit vectors"),
        (torch.tensor([[float("nan"), 0.0, 1.0]]), "non-finite"),
        (torch.ones(4, 2), r"shape \[\.\.\., 3\]"),
    ],
)
def test_bad_directions(dirs, match):
    with pytest.raises(ValueError, match=match) as e:
        sh.eval_sh(dirs, 3)
    assert "dirs" in str(e.value)


def test_bad_bands_and_shapes():
    d = unit(3)
    with pytest.raises(ValueError, match="bands=0"):
        sh.eval_sh(d, 0)
    with pytest.raises(TypeError, match="bands"):
        sh.eval_sh(d, 2.5)
    with pytest.raises(ValueError, match="values has shape"):
        sh.project(torch.ones(4), d, torch.ones(3), 2)
    with pytest.raises(ValueError, match="not a square number"):
        sh.reconstruct(torch.ones(5), d)
    with pytest.raises(ValueError, match="Phong exponent"):
        sh.phong(-1.0, 3)
    with pytest.raises(ValueError, match="drop contains"):
        sh.hemisphere_projector(3, drop=[(3, 0)])
    with pytest.raises(TypeError, match="dtype"):
        sh.eval_sh(torch.tensor([[0, 0, 1]]), 2)


def test_float32_sh_stays_accurate_at_high_bands():
    """Found by benchmarks/bench_extremes.py: sphericart in float32 is wrong from 20 bands (NaN
    from 32); the auto backend must not use it there. Reference: scipy's spherical harmonics
    in the real graphics convention, float64."""
    import numpy as np
    from scipy.special import sph_harm_y

    g = torch.Generator().manual_seed(3)
    d = torch.randn(64, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    theta, phi = torch.arccos(d[:, 2]).numpy(), torch.atan2(d[:, 1], d[:, 0]).numpy()
    for bands in (20, 32, 64):
        l, m = bands - 1, -(bands // 3)
        c = sph_harm_y(l, abs(m), theta, phi)
        ref = np.sqrt(2) * (-1) ** m * c.imag
        y = sh.eval_sh(d.float(), bands)[:, l * (l + 1) + m].double().numpy()
        assert np.isfinite(y).all() and np.abs(y - ref).max() < 1e-4 * max(1.0, np.abs(ref).max())
    with pytest.raises(ValueError, match="sphericart"):
        sh.eval_sh(d.float(), 24, backend="sphericart")
