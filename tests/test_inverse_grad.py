"""Differentiable relighting (issue 38): ``torch.autograd.gradcheck`` in float64 of every
uncompressed relight path, of every affine codec's ``relight`` with respect to the light (and
the view weights, and a codec's own tensors), of the Gaussian codec's relight with respect to its
prefiltered light (and through the prefilter to an SH light) and of the wavelet relighter with
respect to the light's kept coefficients, checked against finite differences (gradcheck's
independent numerical Jacobian). The fused C kernels are forward-only: when a gradient is
required the torch path takes over, with the kernels' forward values (float32 tolerance)."""
from __future__ import annotations

import warnings

import pytest
import torch

from prt_torch import codecs, relight
from prt_torch.codecs.relight_kernels import native
from prt_torch.sh import random_rotations


def _gc(f, *inputs):
    return torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-6, rtol=1e-4, fast_mode=True)


def test_uncompressed_relight_paths_gradcheck():
    g = torch.Generator().manual_seed(0)
    V, n = 4, 4
    L = torch.randn(3, n, dtype=torch.float64, generator=g, requires_grad=True)
    T = torch.randn(V, n, dtype=torch.float64, generator=g)
    T3 = torch.randn(V, 3, n, dtype=torch.float64, generator=g)
    alb = torch.rand(V, 3, dtype=torch.float64, generator=g)
    assert _gc(lambda l: relight.diffuse(T, l, alb), L)
    assert _gc(lambda l: relight.diffuse(T3, l), L)
    M = torch.randn(V, 3, n, dtype=torch.float64, generator=g, requires_grad=True)
    v = torch.nn.functional.normalize(torch.randn(V, 3, dtype=torch.float64, generator=g), dim=1)
    v[:, 2] = v[:, 2].abs()
    assert _gc(lambda l, m: relight.glossy(m, l, v), L, M)
    A = torch.randn(V, 16, n, dtype=torch.float64, generator=g, requires_grad=True)
    assert _gc(lambda l, a: relight.mrt(a, l, v), L, A)
    frames = random_rotations(V, seed=0)
    rb = relight.kautz_setup(frames, 2)
    B = torch.randn(4, n, dtype=torch.float64, generator=g, requires_grad=True)
    Tg = torch.randn(V, n, n, dtype=torch.float64, generator=g)
    assert _gc(lambda l, b: relight.kautz(Tg, rb, b, l, v), L, B)


def _fit(name, X, **kw):
    c = codecs.get(name, **{k: v for k, v in kw.items() if k != "matrix_shape"})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return c, c.fit_encode(X, matrix_shape=kw.get("matrix_shape"))


AFFINE = [("pca", dict(vectors=3)), ("vq", dict(clusters=4)), ("cpca", dict(clusters=3, vectors=2)),
          ("cpca_static", dict(clusters=3, vectors=2)), ("cpca_iterative", dict(clusters=3, vectors=2)),
          ("cpca_adaptive", dict(clusters=3, vectors=2)), ("neural", dict(latent=3, epochs=5))]


@pytest.mark.parametrize("name,kw", AFFINE, ids=[a for a, _ in AFFINE])
def test_affine_codec_relight_gradcheck_vectors(name, kw):
    torch.manual_seed(0)
    X = torch.randn(40, 9)
    try:
        c, enc = _fit(name, X, **kw)
    except (TypeError, ValueError) as e:  # a codec whose parameters differ: fit with its defaults scaled down
        if name != "neural":
            raise
        c, enc = _fit(name, X)
        del e
    L = torch.randn(9, 3, dtype=torch.float64, requires_grad=True)
    assert _gc(lambda l: c.relight(enc, l), L)
    # the forward value under autograd is the kernels' (float32) result to float32 rounding
    ref = c.relight(enc, L.detach().float())
    got = c.relight(enc, L).detach()
    assert torch.allclose(got.float(), ref, rtol=1e-4, atol=1e-4 * float(ref.abs().max()))
    assert got.dtype == torch.float64 and c.relight(enc, L).requires_grad


@pytest.mark.parametrize("name", ["mrt_pca", "cpca"])
def test_matrix_codecs_gradcheck_with_views(name):
    torch.manual_seed(1)
    P, M2, n = 10, 9, 4
    c, enc = _fit(name, torch.randn(P, M2 * n), vectors=3, matrix_shape=(M2, n), **({"clusters": 2} if name == "cpca" else {}))
    L = torch.randn(n, 3, dtype=torch.float64, requires_grad=True)
    taps = (torch.randint(0, M2, (P, 4)), torch.rand(P, 4, dtype=torch.float64))
    dense = torch.rand(P, M2, dtype=torch.float64, requires_grad=True)
    assert _gc(lambda l: c.relight(enc, l, taps), L)
    assert _gc(lambda l, y: c.relight(enc, l, y), L, dense)
    ref = c.relight(enc, L.detach().float(), (taps[0], taps[1].float()))
    assert torch.allclose(c.relight(enc, L, taps).detach().float(), ref, rtol=1e-4, atol=1e-5)


def test_gradient_wrt_codec_tensors():
    """The affine codecs' own tensors (basis, means, per-point weights) are differentiable too."""
    torch.manual_seed(2)
    c, enc = _fit("pca", torch.randn(25, 9), vectors=3)
    c.basis_ = c.basis_.double().requires_grad_(True)
    c.means_ = c.means_.double().requires_grad_(True)
    L = torch.randn(9, 2, dtype=torch.float64)
    assert _gc(lambda b, m: (setattr(c, "basis_", b), setattr(c, "means_", m), c.relight(enc, L))[-1], c.basis_, c.means_)


@pytest.mark.parametrize("name,kw", AFFINE[:6] + [("mrt_pca", dict(vectors=3))], ids=[a for a, _ in AFFINE[:6]] + ["mrt_pca"])
def test_affine_decode_gradcheck_wrt_codec_tensors(name, kw):
    """``decode`` under autograd (issue 38: "affine decode too"): with respect to the means, the
    basis and the per-point weights, against finite differences; its value is the tiled forward's
    (float32 tolerance)."""
    torch.manual_seed(5)
    ms = (4, 9) if name == "mrt_pca" else None
    c, enc = _fit(name, torch.randn(30, 36 if ms else 9), **kw, matrix_shape=ms)
    ref = c.decode(enc)
    names = ["basis_"] + (["means_"] if c.means_ is not None else [])  # (mrt_pca: no mean)
    tensors = [getattr(c, k).double().requires_grad_(True) for k in names]
    if "coeffs" in enc.tensors:
        names.append("coeffs")
        tensors.append(enc.tensors["coeffs"].double().requires_grad_(True))

    def f(*ts):
        for k, t in zip(names, ts):
            if k == "coeffs":
                enc.tensors["coeffs"] = t
            else:
                setattr(c, k, t)
        return c.decode(enc)

    assert _gc(f, *tensors)
    got = f(*tensors)
    assert got.requires_grad and got.dtype == torch.float64
    assert torch.allclose(got.detach().float(), ref, rtol=1e-5, atol=1e-5 * float(ref.abs().max()))


@pytest.mark.parametrize("kw", [dict(latent=3, epochs=5), dict(latent=3, epochs=5, clusters=2)], ids=["K1", "K2"])
def test_neural_decode_gradcheck(kw):
    """The neural codec's ``decode`` (eq. (1): head of [z, φ(z)]) under autograd, with respect to
    the codes and the linear head, against finite differences; the value is the no-grad pass's."""
    torch.manual_seed(6)
    try:
        c, enc = _fit("neural", torch.randn(30, 9), **kw)
    except (TypeError, ValueError):  # parameter names of another version: its defaults
        c, enc = _fit("neural", torch.randn(30, 9))
    ref = c.decode(enc)
    z = enc.tensors["z"].double().requires_grad_(True)
    head = c.head_.double().requires_grad_(True)
    bias = c.bias_.double().requires_grad_(True)

    def f(zz, h, b):
        enc.tensors["z"], c.head_, c.bias_ = zz, h, b
        return c.decode(enc)

    assert _gc(f, z, head, bias)
    assert f(z, head, bias).dtype == torch.float64
    # the value: the same pass as the no-grad one (float32 tensors that require grad: the same bits; float64 differs
    # by the float32 pass's rounding, amplified here by a 5-epoch head with weights ~6e3)
    got = f(*(t.detach().float().requires_grad_(True) for t in (z, head, bias)))
    assert got.requires_grad and torch.allclose(got.detach(), ref, rtol=1e-6, atol=1e-7 * float(ref.abs().max()))


def test_relighter_falls_back_to_autograd_path():
    """A prepared relighter (the render loop form, straight to the kernels) takes the torch path when
    the light requires grad, and its gradient is the analytic one: ∂Σ out / ∂l = Σ_p e_p (PCA:
    column sums of the decoded matrix, an independent closed form)."""
    torch.manual_seed(3)
    X = torch.randn(30, 9)
    c, enc = _fit("pca", X, vectors=5)
    r = c.relighter(enc)
    L = torch.randn(9, 1, dtype=torch.float64, requires_grad=True)
    r(L).sum().backward()
    Xhat = c.decode(enc).to(torch.float64)  # [P, 9], relight = Xhat @ L
    assert torch.allclose(L.grad[:, 0], Xhat.sum(0), rtol=1e-5, atol=1e-5)
    if native() is not None:  # and without grad the relighter still answers from the kernels, same values
        with torch.no_grad():
            assert torch.allclose(r(L.detach().float()), (Xhat @ L.detach()).float(), atol=1e-4)


def test_out_with_grad_is_refused():
    c, enc = _fit("pca", torch.randn(20, 9), vectors=2)
    L = torch.randn(9, 3, dtype=torch.float64, requires_grad=True)
    with pytest.raises(ValueError, match="requires grad"):
        c.relight(enc, L, out=torch.empty(20, 3))


# ------------------------------------------------------------------------------------ Gaussian codec
@pytest.fixture(scope="module")
def gaussian():
    """A Gaussian codec fitted to mixtures of known lobes (the test_gaussian construction), with an
    SH diffuse part, on a 4×4-texel cube per view; 5 vertices × 12 views."""
    from prt_torch.codecs.gaussian import mixture
    from prt_torch.lighting.prefilter import cube_map_directions

    d, _ = cube_map_directions(4)
    d = d.reshape(-1, 3)
    g = torch.Generator().manual_seed(2)
    V, J, N = 5, 12, 2
    mu = torch.nn.functional.normalize(torch.randn(V * J, N, 3, dtype=torch.float64, generator=g), dim=-1)
    sg = torch.empty(V * J, N, dtype=torch.float64).uniform_(0.25, 0.8, generator=g)
    w = torch.empty(V * J, N, dtype=torch.float64).uniform_(0.5, 1.5, generator=g)
    T = mixture(d, w, mu, sg).reshape(V, J * d.shape[0]).float()
    c = codecs.get("gaussian", lobes=N, diffuse_bands=2, max_iter=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(T, matrix_shape=(J, d.shape[0]))
    return c, enc, V, J


def _taps(V, J):
    j = torch.arange(V) % J
    return torch.stack([j, (j + 1) % J, (j + 2) % J], 1), torch.tensor([[0.5, 0.3, 0.2]] * V)


@pytest.mark.parametrize("view", ["all", "taps"])
def test_gaussian_codec_gradcheck_through_the_prefilter(gaussian, view):
    """d relight / d SH light through ``prefilter_environment`` (linear: float64 filter when the
    light requires grad) and the torch trilinear lookups; every stored view, and view taps."""
    from prt_torch.lighting.prefilter import prefilter_environment

    c, enc, V, J = gaussian
    v = None if view == "all" else _taps(V, J)
    L = torch.randn(3, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(4), requires_grad=True)
    L0 = L.detach().clone()
    L0[:, 0] += 3.0  # a positive light

    def f(l):
        return c.relight(enc, prefilter_environment(L0 + l, res=4, levels=5), view=v)

    assert _gc(f, L)


def test_gaussian_relight_surface_gradcheck(gaussian):
    """Surface points (Green §2.3: lobes blended across views and the triangle's vertices), with
    respect to the SH light through the prefilter; the value equals the kernels' path's."""
    from prt_torch.lighting.prefilter import prefilter_environment

    c, enc, V, J = gaussian
    g = torch.Generator().manual_seed(7)
    faces = torch.tensor([[0, 1, 2], [2, 3, 4]])
    fi = torch.tensor([0, 1, 1])
    bary = torch.rand(3, 3, generator=g)
    bary = bary / bary.sum(1, keepdim=True)
    dirs = torch.nn.functional.normalize(torch.randn(3, 3, generator=g), dim=1)
    L0 = load_light_sh().double()

    def f(l):
        return c.relight_surface(enc, prefilter_environment(l, res=4, levels=5), faces, fi, bary, dirs)

    L = L0.clone().requires_grad_(True)
    assert _gc(f, L)
    ref = c.relight_surface(enc, prefilter_environment(L0, res=4, levels=5), faces, fi, bary, dirs)
    assert torch.allclose(f(L).detach().float(), ref, rtol=1e-4, atol=1e-5 * float(ref.abs().max()))


def test_gaussian_codec_gradcheck_wrt_levels_and_sh(gaussian):
    """With respect to the pyramid itself (levels) and the SH coefficients of the diffuse part."""
    from prt_torch.lighting.prefilter import PrefilteredEnvironment, prefilter_environment

    c, enc, V, J = gaussian
    pe = prefilter_environment(load_light_sh(), res=4, levels=5)
    lv = pe.levels.double().clone().requires_grad_(True)
    sh = pe.sh.double().clone().requires_grad_(True)
    assert _gc(lambda a, b: c.relight(enc, PrefilteredEnvironment(a, pe.sigmas, pe.cube, b), view=_taps(V, J)), lv, sh)


def load_light_sh():
    from prt_torch.lighting import load_light

    return load_light("sky", 2).float()


def test_gaussian_grad_path_value_equals_the_kernels(gaussian):
    """The grad path's forward (torch lookups, float64 levels) equals the fused kernels' (float32,
    no grad) to float32 rounding, every view and taps; ``out=`` is refused under autograd."""
    from prt_torch.lighting.prefilter import prefilter_environment

    c, enc, V, J = gaussian
    L = load_light_sh().double()
    ref_pe = prefilter_environment(L, res=4, levels=5)
    grad_pe = prefilter_environment(L.clone().requires_grad_(True), res=4, levels=5)
    assert grad_pe.levels.dtype == torch.float64 and grad_pe.levels.requires_grad
    for v in (None, _taps(V, J)):
        ref = c.relight(enc, ref_pe, view=v)
        got = c.relight(enc, grad_pe, view=v)
        assert got.requires_grad and got.dtype == torch.float64
        assert torch.allclose(got.detach().float(), ref, rtol=1e-4, atol=1e-5 * float(ref.abs().max()))
    with pytest.raises(ValueError, match="require grad"):
        c.relight(enc, grad_pe, out=torch.empty(V, J, 3))
    r = c.relighter(enc, _taps(V, J))  # the prepared relighter takes the torch path too
    assert r(grad_pe).requires_grad


# ------------------------------------------------------------------------------------ wavelet relighter
@pytest.fixture(scope="module")
def wavelet():
    from prt_torch.scene import builtin
    from prt_torch.transfer.wavelet import precompute_wavelet

    tr = precompute_wavelet(builtin("occluder_over_plane", "small"), res=4, terms=40, bits=8, shadows="always")
    # the float dense loop (arith='float'): these tests compare the grad path (float64) with the kernel to float32
    # rounding; the default's int16 VNNI loop (AVX-512 VNNI CPUs) is checked against its own bound in test_wavelet_isa.py
    return tr, relight.WaveletRelighter(tr, arith="float")


def test_wavelet_relighter_gradcheck(wavelet):
    """d relight / d (kept light coefficients) for a fixed term selection (dense and sparse
    columns both read), against finite differences; the gradient of Σ out is also the dense
    reference's closed form Σ_v albedo_vc T̂_v,n (``wavelet_dense`` of unit lights)."""
    tr, r = wavelet
    li, lv, _ = r.light("studio", terms=30, selection="magnitude")
    assert bool((r.dslot[li] >= 0).any()) and bool((r.dslot[li] < 0).any())
    x = lv.double().clone().requires_grad_(True)
    assert _gc(lambda v: r(li, v), x)
    r(li, x).sum().backward()
    alb = tr.mesh.albedo[:, :3].double()
    eye = torch.eye(li.numel(), dtype=torch.float64)
    cols = torch.stack([relight.wavelet_dense(r.values.double(), r.index, li, eye[k][None].expand(3, -1), r.P) for k in
                        range(li.numel())], -1)  # [V, 3, N]: d out[v, c] / d lv[c, k]
    assert torch.allclose(x.grad, (cols * alb[:, :, None]).sum(0), rtol=1e-6, atol=1e-9)


def test_wavelet_grad_path_value_equals_the_kernel(wavelet):
    tr, r = wavelet
    li, lv, _ = r.light("sky", terms=50)
    ref = r(li, lv.float())
    got = r(li, lv.double().requires_grad_(True))
    assert got.requires_grad and got.dtype == torch.float64
    assert torch.allclose(got.detach().float(), ref, rtol=1e-4, atol=1e-5 * float(ref.abs().max()))
    with pytest.raises(ValueError, match="require grad"):
        r(li, lv.double().requires_grad_(True), out=torch.empty(r.V, 3))


def test_wavelet_grad_path_on_a_coloured_transfer():
    """A coloured (interreflected, [V, 3, K]) wavelet transfer: the grad path's value equals the C
    kernel's for a grey and an RGB light, gradcheck passes, and a 2-channel light is refused."""
    from prt_torch.scene import builtin
    from prt_torch.transfer.wavelet import precompute_wavelet

    tr = precompute_wavelet(builtin("cornell_box", "small"), res=4, terms=40, bits=16, bounces=1, hit_samples=4)
    r = relight.WaveletRelighter(tr)
    assert r.CT == 3
    li, lv, _ = r.light("studio", terms=30, selection="magnitude")
    for L in (lv[:1], lv):  # grey, RGB
        ref = r(li, L.float())
        got = r(li, L.double().requires_grad_(True))
        assert got.shape == ref.shape == (r.V, 3)
        assert torch.allclose(got.detach().float(), ref, rtol=1e-4, atol=1e-5 * float(ref.abs().max()))
    x = lv.double().clone().requires_grad_(True)
    assert _gc(lambda v: r(li, v), x)
    with pytest.raises(ValueError, match="colour channels"):
        r(li, lv[:2].double().requires_grad_(True))
