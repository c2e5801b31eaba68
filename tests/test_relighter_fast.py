"""The prepared relighting's no-view form, ``r = codec.relighter(enc)`` then ``r(light, out=buf)``
(``affine.fast_rows``) and the diffuse VQ point kernel it runs (one 16-byte copy per point):
checked against the decoded signal times the light (Sloan 2003 §6: x̃_p · l, computed here in float64
from ``decode``, independent of the kernels), across point counts that leave every tail length, at one
and two threads, from another thread, and after changes the fast path must see."""
import threading
import warnings

import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs.relight_kernels import native
from prt_torch.codecs.synthetic import transfer_like


def _fit(P: int, K: int = 32):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get("vq", clusters=K, max_iter=5, seed=0)
        enc = c.fit_encode(transfer_like(P, 1, 16, seed=1))
    return c, enc


def _want(c, enc, L):
    return (c.decode(enc).double() @ L.double()).float()


@pytest.mark.parametrize("P", [1, 7, 8, 9, 16, 17, 1001, 4099])
@pytest.mark.parametrize("threads", [1, 2])
def test_vq_diffuse_prepared_equals_decoded_times_light(P, threads):
    c, enc = _fit(max(P, 40))
    if P < 40:  # fewer points than clusters: relight the first P codes
        enc = c.encode(transfer_like(P, 1, 16, seed=2))
    L = torch.randn(16, 3, generator=torch.Generator().manual_seed(P))
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        r, out = c.relighter(enc), torch.full((P, 3), float("nan"))
        for _ in range(3):  # the full call, then the fast path
            assert r(L, out=out) is out
            torch.testing.assert_close(out, _want(c, enc, L), rtol=1e-5, atol=1e-5)
            assert torch.equal(out, c.relight(enc, L))
    finally:
        torch.set_num_threads(old)


def test_fast_path_is_armed_and_sees_changes_made_behind_its_back():
    c, enc = _fit(3001)
    g = torch.Generator().manual_seed(3)
    L, L2 = torch.randn(16, 3, generator=g), torch.randn(16, 3, generator=g)
    out = torch.empty(3001, 3)
    r = c.relighter(enc)
    r(L, out=out)
    if native() is not None:
        assert r._fast is not None  # armed by the full call
    for light in (L, L2, L):  # another light of the same shape: still the fast path
        assert r(light, out=out) is out
        torch.testing.assert_close(out, _want(c, enc, light), rtol=1e-5, atol=1e-5)
        assert native() is None or r._fast is not None
    lab = enc.tensors["labels"]  # other codes through .data: same id and version, another address
    lab.data = (lab.data.long() + 5).remainder(c.K_).to(lab.dtype)
    torch.testing.assert_close(r(L, out=out), _want(c, enc, L), rtol=1e-5, atol=1e-5)
    lab.mul_(0)  # edited in place: a new version
    torch.testing.assert_close(r(L, out=out), _want(c, enc, L), rtol=1e-5, atol=1e-5)
    with torch.no_grad():
        c.means_.mul_(-2.0)  # the model edited in place
    r(L, out=out)
    torch.testing.assert_close(r(L, out=out), _want(c, enc, L), rtol=1e-5, atol=1e-5)
    got = []  # from another thread: checked in full there (the armed constants buffer is this thread's)
    th = threading.Thread(target=lambda: got.append(r(L2, out=out).clone()))
    th.start()
    th.join()
    torch.testing.assert_close(got[0], _want(c, enc, L2), rtol=1e-5, atol=1e-5)
    bad = L.clone()
    bad[4, 2] = float("inf")
    r(L, out=out)
    with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*\(4, 2\)"):
        r(bad, out=out)
    Lg = L.clone().requires_grad_()
    with pytest.raises(ValueError, match="out= with a light"):
        r(Lg, out=out)
    y = r(Lg)  # no out: autograd's path, d/dl of sum(x̃_p · l) = sum_p x̃_p
    y.sum().backward()
    torch.testing.assert_close(Lg.grad, c.decode(enc).sum(0)[:, None].expand(16, 3), rtol=1e-4, atol=1e-3)
