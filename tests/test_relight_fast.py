"""``codec.relight(enc, light, out=buf)`` without a view: from its second call like the first it runs
the prepared form's fast path (``affine.fast_rows``, armed in ``enc.cache``). Checked against the
decoded signal times the light (Sloan 2003 §6: x̃_p · l, computed here in float64 from ``decode``,
independent of the kernels) and against the errors the full call gives, after every change the fast
path must see: another ``out``, another light shape, codes or model edited in place or replaced,
a refit, grad wanted, the kernels disabled, another thread, another codec of the same name."""
import gc
import threading
import warnings
import weakref

import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs.relight_kernels import native
from prt_torch.codecs.synthetic import transfer_like


def _fit(name: str = "vq", P: int = 2001, seed: int = 0, **kw):
    params = {"vq": {"clusters": 16, "max_iter": 5}, "pca": {"vectors": 4}, "cpca_static": {"clusters": 8, "vectors": 3,
                                                                                              "max_iter": 5}}[name]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get(name, seed=seed, **params)
        enc = c.fit_encode(transfer_like(P, 1, 16, seed=1), **kw)
    return c, enc


def _want(c, enc, L, n=None):
    return (c.decode(enc, n).double() @ L.double()).float()


def _armed(c, enc, out, n=None):
    f = enc.cache.get(("rows_fast", id(c), n), {}).get(id(out))
    return f is not None and len(f) > 2 and f[0]() is out


def _check(c, enc, L, out, n=None):
    assert c.relight(enc, L, out=out, n_vectors=n) is out
    torch.testing.assert_close(out, _want(c, enc, L, n), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("name", ["vq", "pca", "cpca_static"])
def test_relight_out_fast_path_same_bits_as_full_call(name):
    c, enc = _fit(name)
    g = torch.Generator().manual_seed(2)
    L, L2 = torch.randn(16, 3, generator=g), torch.randn(16, 3, generator=g)
    out = torch.full((enc.points, 3), float("nan"))
    _check(c, enc, L, out)
    assert not _armed(c, enc, out)  # the first full call into out only notes it
    _check(c, enc, L, out)
    assert native() is None or _armed(c, enc, out)
    for light in (L2, L, L2):  # fast path: the same bits as a fresh full call and as the prepared form
        _check(c, enc, light, out)
        assert torch.equal(out, c.relight(enc, light))
        assert torch.equal(out, c.relighter(enc)(light, out=torch.empty_like(out)))
    if name != "vq":  # n_vectors is part of the key
        _check(c, enc, L, out, n=1)
        _check(c, enc, L, out, n=1)
        _check(c, enc, L, out)


def test_relight_out_fast_path_sees_changes():
    c, enc = _fit("vq")
    g = torch.Generator().manual_seed(3)
    L = torch.randn(16, 3, generator=g)
    out = torch.empty(enc.points, 3)
    _check(c, enc, L, out)
    out2 = torch.empty(enc.points, 3)  # another out: checked in full, then the fast path for it
    _check(c, enc, L, out2)
    _check(c, enc, L, out2)
    _check(c, enc, L, out)
    for _ in range(3):  # double buffering: both outputs keep their entries
        _check(c, enc, L, out)
        _check(c, enc, L, out2)
    assert native() is None or (_armed(c, enc, out) and _armed(c, enc, out2))
    outs = [torch.empty(enc.points, 3) for _ in range(c.FAST_OUTS + 1)]  # more outputs than entries: the oldest dropped
    for _ in range(2):
        for o in outs:
            _check(c, enc, L, o)
    assert len(enc.cache[("rows_fast", id(c), None)]) <= c.FAST_OUTS
    fresh = [torch.empty(enc.points, 3) for _ in range(3)]  # a new out each call: noted, never armed
    for o in fresh:
        _check(c, enc, L, o)
        assert not _armed(c, enc, o)
    L4 = torch.randn(16, 4, generator=g)  # another light shape: out no longer fits -> the full call's error
    with pytest.raises(ValueError, match="out has shape"):
        c.relight(enc, L4, out=out)
    _check(c, enc, L, out)
    lab = enc.tensors["labels"]
    lab.data = (lab.data.long() + 5).remainder(c.K_).to(lab.dtype)  # same id and version, another address
    _check(c, enc, L, out)
    lab.mul_(0)  # edited in place
    _check(c, enc, L, out)
    with torch.no_grad():
        c.means_.mul_(-2.0)  # the model edited in place
    _check(c, enc, L, out)
    enc.tensors["labels"] = lab.clone()  # a replaced tensor
    _check(c, enc, L, out)
    got = []  # another thread: checked in full there (the armed constants buffer is this thread's)
    th = threading.Thread(target=lambda: got.append(c.relight(enc, L, out=out).clone()))
    th.start()
    th.join()
    torch.testing.assert_close(got[0], _want(c, enc, L), rtol=1e-5, atol=1e-5)
    _check(c, enc, L, out)
    bad = L.clone()
    bad[4, 2] = float("inf")
    with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*\(4, 2\)"):
        c.relight(enc, bad, out=out)
    with pytest.raises(ValueError, match="out shares memory"):  # a light inside out's storage
        big = torch.zeros(enc.points * 3 + 48)
        c.relight(enc, big[enc.points * 3:].view(16, 3), out=big[:enc.points * 3].view(enc.points, 3))
    _check(c, enc, L, out)
    with pytest.raises(ValueError, match="out= with a light"):  # grad wanted: refused as by the full call
        c.relight(enc, L.clone().requires_grad_(), out=out)
    _check(c, enc, L, out)
    c.means_.requires_grad_(True)  # a model tensor that wants grad (no version change): the full call's refusal
    try:
        with pytest.raises(ValueError, match="out= with a light"):
            c.relight(enc, L, out=out)
    finally:
        c.means_.requires_grad_(False)
    _check(c, enc, L, out)
    c2, enc2 = _fit("vq", seed=7)  # another codec of the same name and shapes relighting this encoding: its own model
    assert c2.relight(enc, L, out=out) is out
    torch.testing.assert_close(out, (c2.decode(enc).double() @ L.double()).float(), rtol=1e-5, atol=1e-5)
    _check(c, enc, L, out)
    c.fit(transfer_like(2001, 1, 16, seed=9))  # a refit: new model tensors
    enc = c.encode(transfer_like(2001, 1, 16, seed=1))
    _check(c, enc, L, out)
    _check(c, enc, L, out)


def test_relight_out_fast_path_off_without_kernels(monkeypatch):
    c, enc = _fit("vq")
    L = torch.randn(16, 3, generator=torch.Generator().manual_seed(4))
    out = torch.empty(enc.points, 3)
    _check(c, enc, L, out)
    _check(c, enc, L, out)
    monkeypatch.setenv("PRT_TORCH_NATIVE", "0")  # the torch formulation: float32 rounding of the kernels' sums
    calls = []
    orig = type(c)._relight_torch
    monkeypatch.setattr(type(c), "_relight_torch", lambda self, *a: calls.append(1) or orig(self, *a))
    _check(c, enc, L, out)
    assert calls


def test_relight_out_fast_entry_keeps_neither_encoding_nor_out():
    c, _ = _fit("vq")
    enc = c.encode(transfer_like(2001, 1, 16, seed=11))  # not the training encoding, which the codec keeps
    L = torch.randn(16, 3, generator=torch.Generator().manual_seed(5))
    out = torch.empty(enc.points, 3)
    _check(c, enc, L, out)
    _check(c, enc, L, out)
    we, wo = weakref.ref(enc), weakref.ref(out)
    del enc, out
    gc.collect()
    assert we() is None and wo() is None
