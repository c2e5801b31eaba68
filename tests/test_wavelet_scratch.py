"""The wavelet kernel's sparse scratch in the AVX-512 build (``kernels/wavelet.c``: ``zacc`` / ``tmark``, zero between
calls, a touched map instead of a memset per tile): consecutive calls with different lights and sparse sets — each
build in turn on one layout, the AVX2 build (which zeroes its own ``acc``) between them —, one and two threads, tiles
of 3 and 36 32-vertex blocks and the default (one tile of 71 at one thread), relight as the float64 gather of the
same stored values (``relight.wavelet_dense``: a
stale accumulator would add a previous light's terms), give the AVX2 build's bits, and leave ``zacc`` and ``tmark``
zero; so do the calls that return 1 (a channel count not accepted), 2 (an index out of range) and 3 (the row-major
pass chosen before its copy exists), and the row-major pass (no scratch)."""

from __future__ import annotations

import os

import pytest
import torch

from prt_torch import _native, relight

from test_wavelet_isa import _relight, _transfer

pytestmark = pytest.mark.skipif(os.environ.get("PRT_TORCH_NATIVE", "1") == "0" or relight._wavelet_lib() is None,
                                reason="no compiled wavelet kernel")

HAS_512 = _native.cpu_isa() == "avx512"
HAS_AVX2 = _native.cpu_isa() in ("avx2", "avx512")


def _builds() -> list[str]:
    return ["native"] + (["avx2"] if HAS_AVX2 and HAS_512 else [])


def _reference(r, li, lv) -> torch.Tensor:
    idx, vals = r.reference_rows()
    return relight.wavelet_dense(vals.double(), idx, li, lv.double(), r.P)


def _clean(r) -> bool:
    return not bool(r._zacc.any()) and not bool(r._tmark.any())


@pytest.mark.parametrize("tile", [96, 1152, None])
def test_consecutive_lights_each_build_scratch_zero_between_calls(tile):
    tr = _transfer(torch.int16, 1)
    r = relight.WaveletRelighter(tr, threads=1, layouts="column", tile=tile)  # column-major pass at every N
    g = torch.Generator().manual_seed(7)
    sparse = torch.nonzero((r.dslot < 0) & (r.cls > 0)).flatten()
    dense = torch.nonzero(r.dslot >= 0).flatten()
    lights = []
    for N in (40, 3, 200, 1, r.P, 17):
        if N == 1:
            li = sparse[torch.randint(sparse.numel(), (1,), generator=g)]  # one sparse term alone: few blocks touched
        elif N == 3:
            li = torch.cat([dense[:2], sparse[-1:]])
        else:
            li = torch.randperm(r.P, generator=g)[:N]
        lights.append((li.contiguous(), torch.randn(3, li.numel(), generator=g)))
    for threads in (1, 2):
        for k, (li, lv) in enumerate(lights):
            ref = _reference(r, li, lv)
            outs = {}
            for isa in _builds() if k % 2 == 0 else list(reversed(_builds())):  # each build last in turn
                lib = relight._wavelet_lib(isa)
                _relight(r, lib, li, lv, threads)  # the default (the VNNI dense loop where it applies): scratch zero too
                assert _clean(r), (tile, threads, k, isa)
                outs[isa] = _relight(r, lib, li, lv, threads, relight.float_dense_flag(lib))  # the float loop's bits
                err = float((outs[isa].double() - ref).abs().max())
                assert err <= 1e-5 * float(ref.abs().max()) + 1e-6, (tile, threads, k, isa, err)
                assert _clean(r), (tile, threads, k, isa)
            if "avx2" in outs:
                assert torch.equal(outs["native"], outs["avx2"]), (tile, threads, k)


def test_refused_calls_and_the_row_major_pass_leave_the_scratch_zero():
    tr = _transfer(torch.int16, 1)
    r = relight.WaveletRelighter(tr, threads=1, layouts="auto", tile=96)  # no row-major copy yet
    lib = relight._wavelet_lib()
    g = torch.Generator().manual_seed(9)
    li = torch.randperm(r.P, generator=g)[:40].contiguous()
    lv = torch.randn(3, 40, generator=g)
    r._kernel()
    f = r._factor(3, False)
    out = torch.empty(r.V, 3)
    call = lib.prt_wavelet_relight_i16

    fd = relight.float_dense_flag(lib)  # the float dense loop (the reference's tolerance is float32 rounding)

    def st(li_, lv_, C):
        return call(r._layout.data_ptr(), li_.numel(), li_.data_ptr(), lv_.data_ptr(), C | (fd if C == 3 else 0), f.data_ptr(),
                    out.data_ptr(), 1)

    assert st(li, lv, 3) == 0 and _clean(r)
    assert st(li, lv, 5) == 1 and _clean(r)  # C not accepted
    bad = li.clone()
    bad[-1] = r.P
    assert st(bad, lv, 3) == 2 and _clean(r)  # an index out of range
    allc = torch.arange(r.P)
    lva = torch.randn(3, r.P, generator=g)
    assert st(allc, lva, 3) == 3 and _clean(r)  # every column: the row-major pass, its copy not built
    r._build_rows()
    assert st(allc, lva, 3) == 0 and _clean(r)  # the row-major pass: no scratch
    ref = _reference(r, allc, lva)
    assert float((out.double() - ref).abs().max()) <= 1e-5 * float(ref.abs().max()) + 1e-6
    assert st(li, lv, 3) == 0 and _clean(r)
    ref = _reference(r, li, lv)
    assert float((out.double() - ref).abs().max()) <= 1e-5 * float(ref.abs().max()) + 1e-6


def test_held_bytes_count_the_scratch_as_estimated():
    tr = _transfer(torch.int16, 1)
    r = relight.WaveletRelighter(tr, threads=1, tile=96)
    assert r._zacc.shape == r._acc.shape and r._tmark.shape == r._acc.shape[:2] and _clean(r)
    assert r.held_bytes()["other"] >= r._acc.numel() * 8 + r._tmark.numel()


@pytest.mark.skipif(not (HAS_512 and HAS_AVX2), reason="one build only on this CPU")
def test_per_vertex_factor_output_same_bits_in_both_builds():
    """The AVX-512 build's RGB interleave (OUT_Z: an insert and two vpermt2ps per 8 vertices) moves data only: with the
    relighter's per-vertex factor (``_kfactor``: ``f [V + 4]``, ``C | F1``; put_rgb8) and with ``f [V, 3]``
    (store_rgb8), grey and coloured output multipliers, its outputs are the AVX2 build's bit for bit."""
    tr = _transfer(torch.int16, 1)
    r = relight.WaveletRelighter(tr, threads=1, layouts="column", tile=96)
    r._kernel()
    g = torch.Generator().manual_seed(13)
    li = torch.randperm(r.P, generator=g)[:60].contiguous()
    lv = torch.randn(3, 60, generator=g)
    f1 = torch.rand(r.V + 4, generator=g) + 0.5
    fc = f1.clone()
    fc[r.V:r.V + 3] = torch.tensor([0.7, 1.0, 1.3])  # a uniform coloured albedo's multipliers (fm 2)
    fv = torch.rand(r.V, 3, generator=g) + 0.5  # f [V, 3]
    outs = {}
    for isa in ("native", "avx2"):
        lib = relight._wavelet_lib(isa)
        for name, f, C in (("f1", f1, 3 | r.F1), ("fc", fc, 3 | r.F1), ("fv", fv.contiguous(), 3)):
            out = torch.empty(r.V, 3)
            C |= relight.float_dense_flag(lib)  # the float dense loop: the AVX2 build's bits
            assert lib.prt_wavelet_relight_i16(r._layout.data_ptr(), 60, li.data_ptr(), lv.data_ptr(), C, f.data_ptr(),
                                               out.data_ptr(), 1) == 0
            outs[isa, name] = out
    for name in ("f1", "fc", "fv"):
        assert torch.equal(outs["native", name], outs["avx2", name]), name
    assert not torch.equal(outs["native", "f1"], outs["native", "fc"])
