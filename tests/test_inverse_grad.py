"""Differentiable relighting (issue 38): ``torch.autograd.gradcheck`` in float64 of every
uncompressed relight path and of every affine codec's ``relight`` with respect to the light (and
the view weights, and a codec's own tensors), checked against finite differences (gradcheck's
independent numerical Jacobian). The fused C kernels are forward-only: when a gradient is
required the torch path takes over, with the kernels' forward values."""
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
