"""The armed fast path with a view (issue 42 §4): ``relight(enc, light, view, out=buf)`` from its second
full call with the same view tensors into the same ``out``, and ``codec.relighter(enc, view)(light,
out=buf)`` from its first (``affine.arm_rows`` / ``affine.fast_rows``). Checked against a reference
independent of the kernels — the decoded matrices times the light in float64, then the dense view's
dot (Sloan 2003 §3.1) or the four tent taps (Lehtinen & Kautz 2003 eq. (13)) — at point counts that
leave every tail of the 8-point loops, at one and two threads, and against the errors the full call
gives after every change the fast path must see: another view, a view swapped behind its back
(``.data``), a bad view value, a view wanting grad, a wrong ``out``."""
import warnings

import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs.relight_kernels import native
from prt_torch.codecs.synthetic import tent_taps_random, transfer_like

M = 5  # 5×5 tents: n_out = 25


def _fit(name: str, P: int):
    params = {"mrt_pca": {"vectors": 3}, "cpca_static": {"clusters": 4, "vectors": 2, "max_iter": 5}}[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get(name, seed=0, **params)
        X = transfer_like(max(P, 64), M * M, 9, seed=1)
        c.fit(X, matrix_shape=(M * M, 9))
        enc = c.encode(X[:P])
    return c, enc


def _want(c, enc, L, view):
    """float64: e_p = M_p l from the decoded matrices, then the view (independent of the kernels)."""
    P = enc.points
    e = c.decode(enc).double().view(P, M * M, 9) @ L.double()  # [P, n_out, C]
    if isinstance(view, tuple):
        idx, g = view
        return (e.gather(1, idx[:, :, None].expand(-1, -1, e.shape[2])) * g.double()[:, :, None]).sum(1).float()
    return torch.einsum("po,poc->pc", view.double(), e).float()


def _views(P: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    return {"dense": torch.randn(P, M * M, generator=g), "taps": tent_taps_random(P, M, seed=seed)}


def _armed(c, enc, out):
    f = enc.cache.get(("rows_fast", id(c), None), {}).get(id(out))
    return f is not None and len(f) > 2 and f[0]() is out


@pytest.mark.parametrize("name", ["mrt_pca", "cpca_static"])
@pytest.mark.parametrize("P", [9, 1001])
@pytest.mark.parametrize("threads", [1, 2])
def test_fast_path_with_views_equals_reference_and_full_call(name, P, threads):
    c, enc = _fit(name, P)
    g = torch.Generator().manual_seed(P)
    lights = [torch.randn(9, 3, generator=g) for _ in range(3)]
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for kind, view in _views(P, 3).items():
            out = torch.full((P, 3), float("nan"))
            r, rout = c.relighter(enc, view), torch.full((P, 3), float("nan"))
            for i, L in enumerate(lights + lights):
                assert c.relight(enc, L, view, out=out) is out
                assert r(L, out=rout) is rout
                want = _want(c, enc, L, view)
                torch.testing.assert_close(out, want, rtol=1e-4, atol=1e-4)
                full = c.relight(enc, L, view)  # a fresh full call (no out): the same bits
                assert torch.equal(out, full) and torch.equal(rout, full), (kind, i)
                if i >= 1 and native() is not None:
                    assert _armed(c, enc, out), kind  # the second full call into out armed it
                    assert r._fast is not None, kind
    finally:
        torch.set_num_threads(old)


@pytest.mark.parametrize("kind", ["dense", "taps"])
def test_fast_path_with_a_view_sees_changes(kind):
    c, enc = _fit("cpca_static", 203)
    P = enc.points
    L = torch.randn(9, 3, generator=torch.Generator().manual_seed(1))
    view = _views(P, 4)[kind]
    other = _views(P, 5)[kind]
    out = torch.empty(P, 3)
    for _ in range(3):
        c.relight(enc, L, view, out=out)
    assert native() is None or _armed(c, enc, out)
    # another view into the same out: checked in full (the right result), then its own entry
    torch.testing.assert_close(c.relight(enc, L, other, out=out), _want(c, enc, L, other), rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(c.relight(enc, L, view, out=out), _want(c, enc, L, view), rtol=1e-4, atol=1e-4)
    for _ in range(2):
        c.relight(enc, L, view, out=out)
    # alternating views each call: noted, never armed, always right
    for i in range(4):
        v = view if i % 2 else other
        torch.testing.assert_close(c.relight(enc, L, v, out=out), _want(c, enc, L, v), rtol=1e-4, atol=1e-4)
        assert not _armed(c, enc, out)
    for _ in range(2):
        c.relight(enc, L, view, out=out)
    assert native() is None or _armed(c, enc, out)
    # the view's values edited in place: read by the fast path (the kernels read them each call)
    w = view if kind == "dense" else view[1]
    with torch.no_grad():
        w.mul_(-1.5)
    torch.testing.assert_close(c.relight(enc, L, view, out=out), _want(c, enc, L, view), rtol=1e-4, atol=1e-4)
    # the view's tensor swapped behind its back (same object and version, another address): checked in full
    w.data = w.data.flip(0).contiguous()
    torch.testing.assert_close(c.relight(enc, L, view, out=out), _want(c, enc, L, view), rtol=1e-4, atol=1e-4)
    for _ in range(2):
        c.relight(enc, L, view, out=out)
    # a bad value in the view: the kernel flags it, and the error names it as the full call's does
    bad = w.clone()
    if kind == "dense":
        with torch.no_grad():
            w[7, 3] = float("nan")
        with pytest.raises(ValueError, match=r"view has 1 non-finite value\(s\).*index \(7, 3\)"):
            c.relight(enc, L, view, out=out)
    else:
        idx = view[0]
        keep = idx[5, 1].item()
        idx[5, 1] = M * M + 3  # out of range: flagged by the taps kernel
        with pytest.raises(ValueError, match=r"view tap indices span"):
            c.relight(enc, L, view, out=out)
        idx[5, 1] = keep
    with torch.no_grad():
        w.copy_(bad)
    torch.testing.assert_close(c.relight(enc, L, view, out=out), _want(c, enc, L, view), rtol=1e-4, atol=1e-4)
    # the view wanting grad: refused as the full call refuses out= under autograd
    w.requires_grad_(True)
    try:
        with pytest.raises(ValueError, match="out= with a light, view or codec tensor that requires grad"):
            c.relight(enc, L, view, out=out)
    finally:
        w.requires_grad_(False)
    torch.testing.assert_close(c.relight(enc, L, view, out=out), _want(c, enc, L, view), rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("kind", ["none", "dense", "taps"])
def test_wrong_out_after_arming_gives_the_full_calls_error(kind):
    c, enc = _fit("mrt_pca", 77)
    P = enc.points
    L = torch.randn(9, 3, generator=torch.Generator().manual_seed(2))
    view = None if kind == "none" else _views(P, 6)[kind]
    shape = (P, M * M, 3) if view is None else (P, 3)
    out = torch.empty(shape)
    r = c.relighter(enc, view)
    for _ in range(3):
        c.relight(enc, L, view, out=out)
        r(L, out=out)
    assert native() is None or (_armed(c, enc, out) and r._fast is not None)
    bad_outs = {"out has shape": torch.empty(P + 1, *shape[1:]),
                r"out has shape .*torch.float64": torch.empty(shape, dtype=torch.float64),
                "not contiguous": torch.empty(*reversed(shape)).transpose(0, -1),
                "out is on device meta": torch.empty(shape, device="meta")}
    for msg, o in bad_outs.items():
        for call in (lambda: c.relight(enc, L, view, out=o), lambda: r(L, out=o)):
            with pytest.raises(ValueError, match=msg):
                call()
    # the armed out still takes the fast path, with the right result
    want = (c.decode(enc).double().view(P, M * M, 9) @ L.double()).float() if view is None else _want(c, enc, L, view)
    torch.testing.assert_close(c.relight(enc, L, view, out=out), want, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(r(L, out=out), want, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("P", [3, 17, 1001])
def test_no_view_rows_split_between_threads_same_bits(P):
    """MRT-style rows without a view (n_out·C = 75 floats, padded to 80: combined two points per pass,
    then copied out) split into one contiguous range per thread (bench_relight_split's question): odd
    point counts put the boundary inside a pair; two threads give the bits of one, and both the
    float64 decoded reference, through the armed fast path as through the full call."""
    c, enc = _fit("mrt_pca", P)
    L = torch.randn(9, 3, generator=torch.Generator().manual_seed(7))
    want = (c.decode(enc).double().view(P, M * M, 9) @ L.double()).float()
    got = {}
    old = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            out = torch.full((P, M * M, 3), float("nan"))
            for _ in range(3):  # full, full (arms), fast
                c.relight(enc, L, out=out)
            got[threads] = out.clone()
            torch.testing.assert_close(out, want, rtol=1e-4, atol=1e-4)
    finally:
        torch.set_num_threads(old)
    assert torch.equal(got[1], got[2])
