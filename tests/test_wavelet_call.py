"""``WaveletRelighter.prepared`` calls the kernel through its packed entry points (``prt_wavelet_relight_*_packed``:
the eight arguments in one int64 array, kernels/wavelet.c): for every stored dtype (int8, int16, float32), grey and
coloured lights, both sparse passes, the prepared run equals the float64 gather of the same stored values
(``relight.wavelet_dense``), survives a garbage collection (the packed array is held by the closure), follows the light
changed in place, and still refuses an index out of range in one line."""

from __future__ import annotations

import gc
import os

import pytest
import torch

from prt_torch import relight
from prt_torch.scene import builtin
from prt_torch.transfer import Transfer

pytestmark = pytest.mark.skipif(os.environ.get("PRT_TORCH_NATIVE", "1") == "0" or relight._wavelet_lib() is None,
                                reason="no compiled wavelet kernel")


@pytest.mark.parametrize("dtype", [torch.int8, torch.int16, torch.float32])
def test_prepared_packed_call_equals_the_dense_reference(dtype):
    scene = builtin("occluder_over_plane", "small")
    g = torch.Generator().manual_seed(7)
    V, res, K = scene.num_vertices, 8, 24
    P = 6 * res * res
    index = (torch.rand(V, P, generator=g) * torch.where(torch.arange(P) < 16, 50.0, 1.0)).topk(K, dim=1).indices
    q = torch.randn(V, K, generator=g) if dtype == torch.float32 else torch.randint(-100, 101, (V, K), generator=g).to(dtype)
    tr = Transfer("wavelet", q, scene, {"res": res, "terms": K}, aux={"index": index.to(torch.int16), "scale": torch.ones(V)})
    r = relight.WaveletRelighter(tr, threads=1)
    assert 0 < r.Pd < P  # both column forms in play
    for C, N in ((3, 40), (1, P), (3, P), (4, 9)):  # column-major and (N = P) row-major passes, grey, RGB, 4 channels
        li = torch.randperm(P, generator=g)[:N]
        lv = torch.randn(C, N, generator=g)
        out = torch.empty(V, C)
        run = r.prepared(li, lv, out, albedo=False)
        gc.collect()  # the packed arguments must outlive this scope's temporaries
        assert run() is out
        ref = relight.wavelet_dense(q.double(), index, li, lv.double(), P)
        vnni = r._takes_vnni(li, lv)  # the default's int16 VNNI dense loop (AVX-512 VNNI CPUs): its stated bound
        assert _close(r, out, ref, li, lv, vnni), (dtype, C, N)
        lv.mul_(-0.5)  # changed in place: the next run relights the new values
        run()
        ref = relight.wavelet_dense(q.double(), index, li, lv.double(), P)
        assert _close(r, out, ref, li, lv, vnni), (dtype, C, N, "in place")
    li[0] = P
    with pytest.raises(ValueError, match=f"accepted: 0..{P - 1}"):
        run()


def _close(r, out, ref, li, lv, vnni: bool) -> bool:
    """``out`` (no albedo) as the float64 reference ``ref``: within the VNNI loop's stated bound where the call takes it,
    else to float32 rounding."""
    if vnni:
        from test_wavelet_isa import _within_vnni_bound

        return _within_vnni_bound(r, out, ref, li, lv)
    return bool((out.double() - ref).abs().max() <= 1e-5 * ref.abs().max() + 1e-6)


@pytest.mark.parametrize("res", [2, 8])
def test_small_light_listing_with_repeated_columns_equals_the_reference(res):
    """kernels/wavelet.c lists up to SMALL_N = 256 light terms from the light itself (unsorted, a column listed twice
    listed once with its values added) instead of passes over the dense slots and the marks; around that size (N = 1,
    5, 40, 256, 257, 400) and where N reaches P − Pd (R = 2: P = 24, the guard that keeps the lists' writes inside the
    scratch), a light with repeated columns (dense and sparse) relights as the float64 gather of the summed light."""
    scene = builtin("occluder_over_plane", "small")
    g = torch.Generator().manual_seed(res)
    V, K = scene.num_vertices, 12 if res == 2 else 24
    P = 6 * res * res
    index = (torch.rand(V, P, generator=g) * torch.where(torch.arange(P) < 8, 50.0, 1.0)).topk(K, dim=1).indices
    q = torch.randint(-32767, 32768, (V, K), generator=g).to(torch.int16)
    tr = Transfer("wavelet", q, scene, {"res": res, "terms": K}, aux={"index": index.to(torch.int16), "scale": torch.ones(V)})
    # the float dense loop (this test is about the listing) and dense_min 1/3 (the bytes rule): at R = 2 the rare columns
    # are kept by ~25% of the vertices, which the VNNI build's default (0.2) would store dense too; the test needs both forms
    r = relight.WaveletRelighter(tr, threads=1, arith="float", dense_min=1 / 3)
    assert 0 < r.Pd < P
    for N in (1, 5, 40, 256, 257, 400):
        li = torch.randint(0, P, (N,), generator=g)  # repeats: every column of R = 2 several times
        li[: N // 2] = li[N // 2: 2 * (N // 2)]  # and at least N / 2 repeated columns at R = 8
        for C in (1, 3):
            lv = torch.randn(C, N, generator=g)
            Lsum = torch.zeros(C, P, dtype=torch.float64).index_add_(1, li, lv.double())
            ref = relight.wavelet_dense(q.double(), index, torch.arange(P), Lsum, P)
            for got in (r(li, lv, albedo=False), r.prepared(li, lv, albedo=False)()):
                assert (got.double() - ref).abs().max() <= 1e-5 * ref.abs().max() + 1e-6, (res, N, C)
        assert bool((r._lp == 0).all())  # the light table is zero again between calls
