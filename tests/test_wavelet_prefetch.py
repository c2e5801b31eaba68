"""The 16-lane dense loop's prefetch across units (kernels/wavelet.c ``PF_FAR``: taken when the dense layout holds at
least ``PFX_MIN`` bytes, by default 0 — every layout —; built here with ``PFX_MIN`` 0 whatever the default): a
prefetch never changes what is summed, so the forced build gives the AVX2 build's bits (each vertex's terms in the same
order) and the float64 gather of the same stored values (``relight.wavelet_dense``) — with fewer dense terms than
``PFX`` (the target several units ahead), with more, tiles of odd block counts (the pair and the lone block), the
layout's last unit (the prefetch past its end), one and two threads."""

from __future__ import annotations

import ctypes
import os

import pytest
import torch

from prt_torch import _native, relight
from prt_torch._native import KERNEL_ISAS, KERNELS_DIR, LIBRARIES, compile_library

from test_wavelet_isa import _relight, _transfer

HAS_512 = _native.cpu_isa() == "avx512"
pytestmark = [pytest.mark.skipif(os.environ.get("PRT_TORCH_NATIVE", "1") == "0" or relight._wavelet_lib() is None,
                                 reason="no compiled wavelet kernel"),
              pytest.mark.skipif(not HAS_512, reason="no avx512f/avx512vl on this CPU: no 16-lane dense loop")]


def _forced():
    """The avx512 build of the working tree's wavelet.c with every layout taking the prefetch across units."""
    text = "#define PFX_MIN 0LL\n" + (KERNELS_DIR / "wavelet.c").read_text()
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    sig = [vp, i64, vp, vp, i64, vp, vp, i64]
    lib, how = compile_library("wavelet", {"wavelet.c": text}, list(LIBRARIES["wavelet"][1]) + list(KERNEL_ISAS["avx512"]),
                               {f"prt_wavelet_relight_{n}": sig for n in ("f32", "i8", "i16")})
    assert lib is not None, how
    return lib


@pytest.mark.parametrize("dtype", [torch.int16, torch.int8, torch.float32])
def test_prefetch_across_units_keeps_the_bits(dtype):
    forced, avx2 = _forced(), relight._wavelet_lib("avx2")
    g = torch.Generator().manual_seed(7)
    for CT, channels in ((1, (1, 3)), (3, (3,))):
        tr = _transfer(dtype, CT)
        for tile in (1152, 96):  # 36 and 3 blocks
            r = relight.WaveletRelighter(tr, threads=1, layouts="both", tile=tile)
            dense = torch.nonzero(r.dslot >= 0).flatten()
            other = torch.nonzero(r.dslot < 0).flatten()
            assert dense.numel() >= 10
            idx, vals = r.reference_rows()
            for C in channels:
                # 4 dense terms (PFX = 24: six units ahead), 10 dense + 30 others, every column
                for li in (dense[:4], torch.cat([dense[:10], other[torch.randperm(other.numel(), generator=g)[:30]]]), torch.arange(r.P)):
                    li = li.contiguous()
                    lv = torch.randn(C, li.numel(), generator=g)
                    L = lv.double().expand(max(C, CT), li.numel())
                    ref = (relight.wavelet_dense(vals.double(), idx, li, L, r.P) if CT == 1 else torch.cat(
                        [relight.wavelet_dense(vals[:, c].double(), idx, li, L[c:c + 1], r.P) for c in range(CT)], 1))
                    for threads in (1, 2):
                        a = _relight(r, forced, li, lv, threads, relight.float_dense_flag(forced))  # the float dense loop
                        b = _relight(r, avx2, li, lv, threads)
                        assert torch.equal(a, b), (dtype, CT, tile, C, li.numel(), threads)
                        err = float((a.double() - ref).abs().max())
                        assert err <= 1e-5 * float(ref.abs().max()) + 1e-6, (dtype, CT, tile, C, li.numel(), err)


def _build(pre: str):
    """The avx512 build of the working tree's wavelet.c with ``pre`` prepended (its entry points typed)."""
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    sig = [vp, i64, vp, vp, i64, vp, vp, i64]
    lib, how = compile_library("wavelet", {"wavelet.c": pre + (KERNELS_DIR / "wavelet.c").read_text()},
                               list(LIBRARIES["wavelet"][1]) + list(KERNEL_ISAS["avx512"]),
                               {f"prt_wavelet_relight_{n}": sig for n in ("f32", "i8", "i16")})
    assert lib is not None, how
    return lib


@pytest.mark.skipif(not {"avx512_vnni", "avx512bw"} <= _native._isa_flags(), reason="no AVX-512 VNNI on this CPU")
def test_vnni_records_keep_the_sums():
    """The VNNI dense loop's records (kernels/wavelet.c ``vnni_records``: each dense term's row offset and its prefetch
    target, written over the call's dense slots) in both prefetch forms — across units (``PFX_MIN`` 0) and within the
    unit (``PFX_MIN`` above every layout) — give the same bits (a prefetch never changes what is summed), within the
    loop's stated bound of the float64 gather of the same stored values (``bench_wavelet_madd_micro.vnni_bound``), and
    not the float loop's bits (the VNNI loop was taken): 4 and 5 dense terms (the prefetch target PFX = 24 steps, six
    units ahead, an odd last term alone), 9 (odd, one group), 10 dense + 30 others, every column (odd and even counts
    over several groups); the default tiles and tiles of 3 blocks (a pair and a lone block), one and two threads."""
    from test_wavelet_isa import _within_vnni_bound

    # the per-call guard off (VNNI_GUARD 0): these random lights on a random layout would often trip it (tested in
    # test_wavelet_madd_micro.py); here the VNNI loop's records are under test
    far, unit = _build("#define VNNI_GUARD 0\n#define PFX_MIN 0LL\n"), _build("#define VNNI_GUARD 0\n#define PFX_MIN (1LL << 62)\n")
    assert far.prt_wavelet_isa() & 64 and unit.prt_wavelet_isa() & 64
    g = torch.Generator().manual_seed(11)
    tr = _transfer(torch.int16, 1, dense=20)
    for tile in (None, 96):
        r = relight.WaveletRelighter(tr, threads=1, layouts="both", tile=tile)
        dense = torch.nonzero(r.dslot >= 0).flatten()
        other = torch.nonzero(r.dslot < 0).flatten()
        assert dense.numel() >= 17
        idx, vals = r.reference_rows()
        for li in (dense[:4], dense[:5], dense[:9], torch.cat([dense[:10], other[torch.randperm(other.numel(), generator=g)[:30]]]),
                   dense.flip(0), torch.arange(r.P)):
            li = li.contiguous()
            lv = torch.randn(3, li.numel(), generator=g)
            assert r._takes_vnni(li, lv, vnni=True, arith="auto")
            ref = relight.wavelet_dense(vals.double(), idx, li, lv.double(), r.P)
            for threads in (1, 2):
                a, b = _relight(r, far, li, lv, threads), _relight(r, unit, li, lv, threads)
                assert torch.equal(a, b), (tile, li.numel(), threads)
                assert _within_vnni_bound(r, a, ref, li, lv), (tile, li.numel(), threads)
                assert not torch.equal(a, _relight(r, far, li, lv, threads, relight.float_dense_flag(far))), (tile, li.numel())
