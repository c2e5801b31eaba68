"""The issue-39 benchmarks that compile ``kernels/wavelet.c`` rewritten (bench_wavelet_setup_variants.py: the
sparse listing from a bitmap of the marks; bench_wavelet_floor_micro.py: the kernel cut after each set-up step)
still apply to the kernel's source, and keep its contract: the variant relights as the dense reference
(``relight.wavelet_dense``, a gather per kept coefficient) does, and a cut build leaves the layout's light table
zero (the kernel's invariant between calls), so the real kernel called after it still matches the reference."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest
import torch

from prt_torch import relight
from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions
from prt_torch.transfer.wavelet import precompute_wavelet

ROOT = Path(__file__).resolve().parents[1]

pytestmark = pytest.mark.skipif(os.environ.get("PRT_TORCH_NATIVE", "1") == "0" or relight._wavelet_lib() is None,
                                reason="no compiled wavelet kernel")


def _bench(name: str):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        return __import__(name)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


@pytest.fixture(scope="module")
def rl():
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 8, 32, 16, shadows="always", run=RunOptions(workers=1))
    # the float dense loop (arith='float'; the probes' calls pass C | FDENSE too): these tests are about the probes,
    # checked to float32 rounding of the reference
    return relight.WaveletRelighter(tr, threads=1, arith="float")


def _reference(rl, li, lv):
    return relight.wavelet_dense(rl.values.double(), rl.index, li, lv, rl.P) * rl.albedo[:, :3].double()


def _args(rl, li, lv, out):
    rl.prepared(li, lv, out)()  # binds the layout (and builds the row-major copy when this light takes it)
    return (rl._layout.data_ptr(), li.numel(), li.data_ptr(), lv.data_ptr(), 3 | relight.float_dense_flag(relight._wavelet_lib()),
            rl._factor(3, True).data_ptr(), out.data_ptr(), 1)


@pytest.mark.parametrize("N", [10, 100, None])
def test_setup_variant_relights_as_the_reference(rl, N):
    fn = _bench("bench_wavelet_setup_variants").variant("bitmap listing")
    li, lv, _ = rl.light("studio", N or rl.P, "transport")
    lv = lv.to(torch.float32).contiguous()
    out = torch.empty(rl.V, 3)
    args = _args(rl, li, lv, out)
    out.fill_(float("nan"))
    assert fn(*args) == 0
    assert torch.allclose(out.double(), _reference(rl, li, lv), rtol=1e-5, atol=1e-6)


def test_setup_probes_leave_the_light_table_zero(rl):
    fm = _bench("bench_wavelet_floor_micro")
    li, lv, _ = rl.light("studio", 100, "transport")
    lv = lv.to(torch.float32).contiguous()
    out = torch.empty(rl.V, 3)
    args = _args(rl, li, lv, out)
    for _, marker in fm.SETUP_CUTS:
        probe = fm.setup_probe(marker)
        assert probe(*args) == 0
        assert not bool(rl._lp.any()), marker  # the kernel's light per column: zero between calls
        rl(li, lv, out=out)
        assert torch.allclose(out.double(), _reference(rl, li, lv), rtol=1e-5, atol=1e-6), marker


@pytest.mark.parametrize("k", [3, 7, 10, 13])
def test_call_probes_apply_and_leave_the_light_table_zero(rl, k):
    """bench_wavelet_setup.py's probes (the kernel cut after a step of the call, or with its dense blocks relit twice)
    still apply to the kernel's source, return 0 and leave the light table zero; the ``dense twice`` probe (13)
    relights as the reference does (the second pass writes the same outputs)."""
    bs = _bench("bench_wavelet_setup")
    src, _ = _bench("bench_wavelet_isa").kernel_source(None, "test")
    lib, _ = _bench("bench_wavelet_isa").kernel_build(bs.probe_source(src, k), None, "test")
    li, lv, _ = rl.light("studio", 100, "transport")
    lv = lv.to(torch.float32).contiguous()
    out = torch.empty(rl.V, 3)
    args = _args(rl, li, lv, out)
    out.fill_(float("nan"))
    assert lib.prt_wavelet_relight_i16(*args) == 0
    assert not bool(rl._lp.any()), k
    if k == 13:
        assert torch.allclose(out.double(), _reference(rl, li, lv), rtol=1e-5, atol=1e-6)
    rl(li, lv, out=out)
    assert torch.allclose(out.double(), _reference(rl, li, lv), rtol=1e-5, atol=1e-6), k


def test_call_variants_apply_to_the_kernel_source(monkeypatch):
    """bench_wavelet_setup.py's --variant rewrites (what was measured and not kept) still find their text in the
    kernel's source and change it; a variant name not listed is refused in one line naming it."""
    bs = _bench("bench_wavelet_setup")
    src = (ROOT / "prt_torch/kernels/wavelet.c").read_text()
    for name, (need, rewrite) in bs.VARIANTS.items():
        assert need in src, name
        assert rewrite(src) != src, name
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_setup.py", "--pair", "main", "--variant", "nonsense", "--write", ""])
    with pytest.raises(SystemExit, match="--variant 'nonsense'; accepted: one of"):
        bs.main()


def test_tsc_build_relights_as_the_reference(rl, monkeypatch):
    """bench_wavelet_setup.py --tsc: its rdtsc reads apply once each to the kernel's source, the build relights as the
    reference does (timing only), and its sums nest — the dense blocks and sparse passes within the tile loop, the tile
    loop and the set-up within the call, tile 0's first two units within the dense blocks; bad --tsc values are refused
    in one line naming them."""
    import ctypes

    bs = _bench("bench_wavelet_setup")
    src, _ = _bench("bench_wavelet_isa").kernel_source(None, "test")
    lib, _ = _bench("bench_wavelet_isa").kernel_build(bs.tsc_source(src), None, "test")
    tsc = (ctypes.c_ulonglong * 16).in_dll(lib, "prt_tsc")
    li, lv, _ = rl.light("studio", 300, "transport")
    lv = lv.to(torch.float32).contiguous()
    out = torch.empty(rl.V, 3)
    args = _args(rl, li, lv, out)
    out.fill_(float("nan"))
    ctypes.memset(tsc, 0, 128)
    assert lib.prt_wavelet_relight_i16(*args) == 0
    assert torch.allclose(out.double(), _reference(rl, li, lv), rtol=1e-5, atol=1e-6)
    dense, sparse, loop, call, u0, u1, quant, rec, chunks, groups, write = (int(tsc[k]) for k in range(11))
    assert 0 < dense + sparse <= loop < call and 0 < u0 + u1 <= dense and sparse > 0, list(tsc)
    # the DVNNI build's set-up (VNNI_SETUP) within the tile loop, vnni_quantise's three passes within its call; builds
    # and calls without it: all five zero
    assert quant + rec + dense + sparse <= loop and chunks + groups + write <= quant, list(tsc)
    assert (quant > 0) == (rec > 0) and (chunks > 0) == (quant > 0), list(tsc)
    # the same call without C | FDENSE: the DVNNI build quantises the light (the VNNI loop, or the guard's float loop)
    ctypes.memset(tsc, 0, 128)
    assert lib.prt_wavelet_relight_i16(args[0], args[1], args[2], args[3], 3, *args[5:]) == 0
    dense, sparse, loop, call, u0, u1, quant, rec, chunks, groups, write = (int(tsc[k]) for k in range(11))
    assert quant + rec + dense + sparse <= loop < call and chunks + groups + write <= quant, list(tsc)
    if int(lib.prt_wavelet_isa()) & 64:
        assert quant > 0 and chunks > 0, list(tsc)
    for bad in ("2272", "2272,100", "a,b"):
        monkeypatch.setattr(sys, "argv", ["bench_wavelet_setup.py", "--tsc", bad, "--write", ""])
        with pytest.raises(SystemExit, match=f"--tsc '{bad}'; accepted: two tiles A,B"):
            bs.main()
