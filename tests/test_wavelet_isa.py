"""The wavelet kernel's builds (``PRT_TORCH_KERNEL_ISA``: native, avx2, avx512, avx512-256; ``relight._wavelet_lib``):
each build this CPU runs relights one layout — every stored dtype, grey and coloured transfers, 1-4 light channels,
the column-major and row-major sparse passes, one and two threads, a vertex count that is not a multiple of the
32-vertex block — as the float64 gather of the same stored values (``relight.wavelet_dense``), and names its path
(``wavelet_kernel_path``: the 16-lane dense loop in the AVX-512 build alone). The AVX-512 builds are skipped on a
CPU without avx512f and avx512vl (where they are refused in one line); the environment variable is honoured.

On a CPU with AVX-512 VNNI the native and avx512 builds sum the dense terms of the calls that allow it (16-bit values,
a grey transfer, an RGB light with unequal channels, enough dense work: ``WaveletRelighter._takes_vnni``) by int16 dot
products, the default since 2026-11-30: those calls are checked within the VNNI loop's stated bound
(``bench_wavelet_madd_micro.vnni_bound``), every other call — and every call with the opt-out, C | FDENSE — gives the
float loop's bits, the AVX2 build's; the AVX2 build (a CPU without VNNI) refuses the bit and keeps the float loop, and a
library cached on a VNNI CPU is not loaded where the CPU's flags lack VNNI."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from prt_torch import _native, relight
from prt_torch.scene import builtin
from prt_torch.transfer import Transfer

pytestmark = pytest.mark.skipif(os.environ.get("PRT_TORCH_NATIVE", "1") == "0" or relight._wavelet_lib() is None,
                                reason="no compiled wavelet kernel")

HAS_512 = _native.cpu_isa() == "avx512"
HAS_AVX2 = _native.cpu_isa() in ("avx2", "avx512")
HAS_VNNI = HAS_512 and {"avx512_vnni", "avx512bw"} <= _native._isa_flags()
FDENSE = relight.WaveletRelighter.FDENSE


def _bench():
    """benchmarks/bench_wavelet_madd_micro.py (``vnni_bound``: the VNNI loop's stated bound, found independently)."""
    root = str(Path(__file__).resolve().parents[1] / "benchmarks")
    sys.path.insert(0, root)
    try:
        return __import__("bench_wavelet_madd_micro")
    finally:
        sys.path.remove(root)


def _transfer(dtype, CT: int, res: int = 8, K: int = 24, seed: int = 3, dense: int = 16) -> Transfer:
    """A synthetic wavelet transfer on the 2251-vertex blocker scene (2251 = 70 x 32 + 11): the first ``dense``
    columns kept by most vertices (dense), the rest sparse."""
    scene = builtin("occluder_over_plane", "small")
    g = torch.Generator().manual_seed(seed)
    V, P = scene.num_vertices, 6 * res * res
    index = (torch.rand(V, P, generator=g) * torch.where(torch.arange(P) < dense, 50.0, 1.0)).topk(K, dim=1).indices
    shape = (V, K) if CT == 1 else (V, CT, K)
    q = (torch.randn(*shape, generator=g) if dtype == torch.float32
         else torch.randint(-100 if dtype == torch.int8 else -30000, 101 if dtype == torch.int8 else 30001, shape,
                            generator=g).to(dtype))
    return Transfer("wavelet", q, scene, {"res": res, "terms": K, "albedo_folded": True},
                    aux={"index": index.to(torch.int16), "scale": torch.ones(V) if CT == 1 else torch.ones(V, CT)})


def _relight(r, lib, li, lv, threads: int, flags: int = 0) -> torch.Tensor:
    """``r``'s layout relit by build ``lib`` (its plain entry point), no albedo; ``flags`` or-ed into C (FDENSE: the
    float dense loop)."""
    r._kernel()
    name = {torch.int8: "i8", torch.int16: "i16"}.get(r.bvals.dtype, "f32")
    f = r._factor(lv.shape[0], False)
    out = torch.empty(r.V, f.shape[1])
    st = getattr(lib, f"prt_wavelet_relight_{name}")(r._layout.data_ptr(), li.numel(), li.data_ptr(), lv.data_ptr(),
                                                     lv.shape[0] | flags, f.data_ptr(), out.data_ptr(), threads)
    assert st == 0, st
    return out


def _within_vnni_bound(r, got, ref, li, lv, albedo: bool = False) -> bool:
    """``got`` (a VNNI call, the albedo applied or not) within the VNNI loop's stated bound of the float64 reference
    ``ref`` [V, 3] (``bench_wavelet_madd_micro.vnni_bound``)."""
    b = _bench().vnni_bound(r, li, lv, albedo=albedo)
    return bool(((got.double() - ref).abs() <= b["bound"] + b["slack"] + 1e-6).all())


def _guard(r, li, lv) -> bool:
    """Whether kernels/wavelet.c's per-call guard sends this VNNI-eligible call to the float loop (its L2 bound above the
    transfer's own: ``bench_wavelet_madd_micro.vnni_bound``'s ``guard``, recomputed from brute-force norms)."""
    return bool(_bench().vnni_bound(r, li, lv)["guard"])


def _builds() -> list:
    out = [pytest.param("native", id="native")]
    out.append(pytest.param("avx2", id="avx2", marks=pytest.mark.skipif(not HAS_AVX2, reason="no AVX2 on this CPU")))
    for b in ("avx512", "avx512-256"):
        out.append(pytest.param(b, id=b, marks=pytest.mark.skipif(not HAS_512, reason="no avx512f/avx512vl on this CPU")))
    return out


@pytest.mark.parametrize("isa", _builds())
def test_each_build_equals_the_dense_reference(isa):
    lib = relight._wavelet_lib(isa)
    assert lib is not None
    path = relight.wavelet_kernel_path(isa)
    assert path["backend"] == "native" and path["isa_choice"] == isa
    assert path["w16"] == (isa == "avx512" or (isa == "native" and HAS_512)), path
    assert path["vnni"] == (path["w16"] and HAS_VNNI), path
    assert path["dense"] == ("int16 vnni" if path["vnni"] else "float"), path
    assert relight.wavelet_kernel_path(isa, arith="float")["dense"] == "float"
    if isa == "avx2":
        assert path["isa"] == "avx2" and "8 lanes" in path["path"]
    vnni_calls = 0
    g = torch.Generator().manual_seed(11)
    for dtype in (torch.int8, torch.int16, torch.float32):
        for CT, channels in ((1, (1, 2, 3, 4)), (3, (1, 3))):
            tr = _transfer(dtype, CT)
            r = relight.WaveletRelighter(tr, threads=1, layouts="both")
            assert 0 < r.Pd < r.P
            idx, vals = r.reference_rows()
            for C in channels:
                for N in (30, r.P):  # column-major scratch pass; every column: the row-major pass
                    li = torch.randperm(r.P, generator=g)[:N].contiguous()
                    lv = torch.randn(C, N, generator=g)
                    L = lv.double().expand(max(C, CT), N)  # a grey light on a coloured transfer: its channel for all three
                    ref = (relight.wavelet_dense(vals.double(), idx, li, L, r.P) if CT == 1 else torch.cat(
                        [relight.wavelet_dense(vals[:, c].double(), idx, li, L[c:c + 1], r.P) for c in range(CT)], 1))
                    vnni = r._takes_vnni(li, lv, vnni=path["vnni"], arith="auto")
                    vnni_calls += vnni
                    for threads in (1, 2):
                        for flags in ((0, FDENSE) if path["vnni"] else (0,)):
                            got = _relight(r, lib, li, lv, threads, flags).double()
                            if vnni and not flags:  # the VNNI loop: its stated bound
                                assert _within_vnni_bound(r, got, ref, li, lv), (isa, dtype, CT, C, N, threads)
                                continue
                            err = float((got - ref).abs().max())
                            assert err <= 1e-5 * float(ref.abs().max()) + 1e-6, (isa, dtype, CT, C, N, threads, flags, err)
    assert (vnni_calls > 0) == path["vnni"], vnni_calls


@pytest.mark.skipif(not HAS_512, reason="no avx512f/avx512vl on this CPU: one build only")
@pytest.mark.parametrize("dtype", [torch.int16, torch.int8, torch.float32])
def test_builds_agree_bit_for_bit(dtype):
    """The 16-lane dense loop adds each vertex's terms in the order the 8-lane one does (one multiply-add per term and
    lane), also when it takes two 32-vertex blocks in lockstep (blocks 2i and 2i + 1 of a tile; the last block of a
    tile with an odd count alone), and when a light with little dense work takes the 8-lane loop (2 dense terms x 71
    blocks < ZMM_MIN), and when the AVX-512 row-major pass walks two 8-vertex blocks in lockstep, each in its own entry
    order (N = every column: blocks holding 0 to 72 entries, about half an odd count: unequal lockstep partners and
    odd tails), and the column-major pass takes three blocks per step: the AVX-512 and AVX2 builds give the same
    bits — every stored dtype, a grey transfer with 1-4
    light channels and a grey RGB light (one sum per vertex), a coloured transfer, tiles of 36 and of 3 blocks (2251
    vertices = 70 blocks + 11: odd counts, a partial last block), one and two threads."""
    g = torch.Generator().manual_seed(5)
    guarded = 0
    for CT, channels in ((1, (1, 2, 3, 4, "grey")), (3, (1, 3))):
        tr = _transfer(dtype, CT)
        for tile in (1152, 96):  # 36 and 3 blocks (one thread's default is one tile: test_wavelet_tile.py)
            r = relight.WaveletRelighter(tr, threads=1, layouts="both", tile=tile)
            dense = torch.nonzero(r.dslot >= 0).flatten()
            sparse = torch.nonzero((r.dslot < 0) & (r.cls > 0)).flatten()
            for C in channels:
                for N in (3, 40, r.P):
                    li = (torch.cat([dense[:2], sparse[:1]]) if N == 3 else torch.randperm(r.P, generator=g)[:N]).contiguous()
                    lv = torch.randn(1, N, generator=g).expand(3, N).contiguous() if C == "grey" else torch.randn(C, N, generator=g)
                    vnni = r._takes_vnni(li, lv, vnni=HAS_VNNI, arith="auto")
                    if vnni and _guard(r, li, lv):  # the per-call guard: the float loop, the float bits
                        vnni, guarded = False, guarded + 1
                    for threads in (1, 2):
                        a = _relight(r, relight._wavelet_lib("avx512"), li, lv, threads)
                        b = _relight(r, relight._wavelet_lib("avx2"), li, lv, threads)
                        if vnni:  # the VNNI loop (AVX-512 VNNI CPUs): not the float bits, within its bound; opted out: the bits
                            assert not torch.equal(a, b), (dtype, CT, tile, C, N, threads)
                            if threads == 1:
                                idx, vals = r.reference_rows()
                                ref = relight.wavelet_dense(vals.double(), idx, li, lv.double(), r.P)
                                assert _within_vnni_bound(r, a, ref, li, lv), (dtype, CT, tile, C, N)
                            a = _relight(r, relight._wavelet_lib("avx512"), li, lv, threads, FDENSE)
                        elif HAS_VNNI:  # the opt-out changes nothing where the VNNI loop is not taken
                            assert torch.equal(a, _relight(r, relight._wavelet_lib("avx512"), li, lv, threads, FDENSE))
                        assert torch.equal(a, b), (dtype, CT, tile, C, N, threads, vnni)


def test_avx512_request_refused_in_one_line_without_it():
    if HAS_512:
        pytest.skip("this CPU has AVX-512: the request is accepted (test_each_build_equals_the_dense_reference)")
    with pytest.raises(ValueError) as e:
        relight._wavelet_lib("avx512")
    assert "\n" not in str(e.value) and "PRT_TORCH_KERNEL_ISA='avx512'" in str(e.value) and "accepted here: native" in str(e.value)


@pytest.mark.skipif(not HAS_AVX2, reason="no AVX2 on this CPU")
def test_environment_variable_selects_the_build():
    env = {k: v for k, v in os.environ.items() if k != "PRT_TORCH_NATIVE"}
    env["PRT_TORCH_KERNEL_ISA"] = "avx2"
    r = subprocess.run([sys.executable, "-c", "import json; from prt_torch import relight; "
                        "print(json.dumps(relight.wavelet_kernel_path()))"], capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    p = json.loads(r.stdout.strip().splitlines()[-1])
    assert p["isa"] == "avx2" and p["isa_choice"] == "avx2" and not p["w16"] and "-mno-avx512f" in p["flags"], p
    assert not p["vnni"] and p["dense"] == "float", p  # a CPU without VNNI (the AVX2 build): the float loop


def test_the_opt_out_bit_and_arith_values():
    """C | FDENSE (512), also with C | F1: accepted by a build with the VNNI loop (the float loop), refused (status 1, nothing written) by
    the builds without it; any other bit above F1 refused by every build; ``arith`` / ``wavelet_kernel_path(arith=)``
    refuse another value in one line naming it; ``arith='float'`` passes the bit only to a build with the VNNI loop."""
    tr = _transfer(torch.int16, 1)
    r = relight.WaveletRelighter(tr, threads=1, arith="float")
    li = torch.arange(40)
    lv = torch.randn(3, 40, generator=torch.Generator().manual_seed(1))
    builds = ["native"] + (["avx2"] if HAS_AVX2 else []) + (["avx512", "avx512-256"] if HAS_512 else [])
    for isa in builds:
        lib = relight._wavelet_lib(isa)
        vnni = relight.wavelet_kernel_path(isa)["vnni"]
        name = "prt_wavelet_relight_i16"
        r._kernel()
        f = r._factor(3, False)
        for C, ok in ((3 | FDENSE, vnni), (3 | FDENSE | 256, vnni), (3 | 1024, False), (3 | 2048 | FDENSE, False)):
            out = torch.full((r.V, 3), 7.0)
            st = getattr(lib, name)(r._layout.data_ptr(), 40, li.data_ptr(), lv.data_ptr(), C, f.data_ptr(), out.data_ptr(), 1)
            assert (st == 0) == ok, (isa, C, st)
            if not ok:
                assert st == 1 and bool((out == 7.0).all()), (isa, C, st)
    assert r._fd == (FDENSE if relight.wavelet_kernel_path()["vnni"] else 0)
    for bad in ("int16", "Float", None, 1):
        with pytest.raises(ValueError) as e:
            relight.WaveletRelighter(tr, arith=bad)
        assert "\n" not in str(e.value) and f"arith={bad!r}" in str(e.value) and "'auto'" in str(e.value)
        with pytest.raises(ValueError):
            relight.wavelet_kernel_path(arith=bad)


@pytest.mark.skipif("avx512_vnni" not in _native._cpu_id(), reason="this CPU has no AVX-512 VNNI")
def test_a_library_cached_on_a_vnni_cpu_is_not_loaded_without_vnni(tmp_path, monkeypatch):
    """The run-time cache keys a library by the CPU's model name and flags line (``_native._cpu_id``): the wavelet
    library this CPU built (with the VNNI loop) is found again here, but not by a process whose CPU lacks avx512_vnni
    (the flags line without it: another key), which compiles its own (here a compiler that refuses, so none)."""
    relight._wavelet_lib()  # the cached build of this CPU exists
    import shutil

    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    fake = tmp_path / "cc"
    fake.write_text(f'#!/bin/sh\nif [ "$1" = --version ]; then exec {cc} --version; fi\nexit 1\n')
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    monkeypatch.setenv("PRT_TORCH_PREBUILT", "0")
    names, flags = _native.LIBRARIES["wavelet"]
    sig = {"prt_wavelet_isa": []}
    lib, how = _native.compile_library("wavelet", _native.kernel_sources(names), list(flags), sig)
    assert lib is not None and int(lib.prt_wavelet_isa()) & 64, how  # found in the cache: the VNNI loop
    cpu = _native._cpu_id()
    monkeypatch.setattr(_native, "_cpu_id", lambda: cpu.replace(" avx512_vnni", ""))
    lib, how = _native.compile_library("wavelet", _native.kernel_sources(names), list(flags), sig)
    assert lib is None and "compiling the wavelet kernels failed" in how, how


@pytest.mark.parametrize("res", [4, 8])
def test_term_lists_from_the_marks(res):
    """Lights of more than SMALL_N terms, or of at least P - Pd (the kernel's LIST_TERMS: the AVX-512 build lists the
    dense and sparse terms from one scan of the P marks, 64 per step — P = 96 at R = 4 ends in a partial step —, the
    8-lane builds by the Pd slots and 8 marks per step), repeated columns among them, the column-major pass (layouts
    'column') and the row-major one, one and two threads, one tile and tiles of 160 vertices (15: an odd count):
    each build equals the float64 sum of the stored values (within the VNNI loop's bound where the call takes it),
    and the native build the AVX2 build's bits where both take the float loop."""
    native, avx2 = relight._wavelet_lib("native"), relight._wavelet_lib("avx2") if HAS_AVX2 else None
    vnni_on = relight.wavelet_kernel_path("native")["vnni"]
    g = torch.Generator().manual_seed(7)
    tr = _transfer(torch.int16, 1, res=res, K=24 if res == 8 else 12, dense=16 if res == 8 else 6)
    for layouts, tile in (("column", None), ("column", 160), ("both", None)):
        r = relight.WaveletRelighter(tr, threads=1, layouts=layouts, tile=tile)
        idx, vals = r.reference_rows()
        assert 0 < r.Pd < r.P
        for N in (r.P - r.Pd, r.P, 300):  # 300: > SMALL_N, drawn with repeats
            li = torch.randint(0, r.P, (N,), generator=g) if N == 300 else torch.randperm(r.P, generator=g)[:N]
            li = li.contiguous()
            for C in (1, 3):
                lv = torch.randn(C, N, generator=g)
                L = torch.zeros(C, r.P, dtype=torch.float64).index_add_(1, li, lv.double())  # a repeated column adds
                ref = relight.wavelet_dense(vals.double(), idx, torch.arange(r.P), L, r.P)
                vnni = r._takes_vnni(li, lv, vnni=vnni_on, arith="auto")
                for threads in (1, 2):
                    got = _relight(r, native, li, lv, threads)
                    if vnni:
                        assert _within_vnni_bound(r, got, ref, li, lv), (res, layouts, tile, N, C, threads)
                        got = _relight(r, native, li, lv, threads, FDENSE)
                    err = float((got.double() - ref).abs().max())
                    assert err <= 1e-5 * float(ref.abs().max()) + 1e-6, (res, layouts, tile, N, C, threads, err)
                    if avx2 is not None:
                        assert torch.equal(got, _relight(r, avx2, li, lv, threads)), (res, layouts, tile, N, C, threads)


def test_sparse_range_prefetch_at_few_and_many_terms():
    """The AVX-512 build's column-major pass prefetches each term's range SP_PFR (2) terms ahead, the term index
    clamped to the light's last sparse term (kernels/wavelet.c, SP_RANGE_PF): lights of sparse terms only — 1, 2 and 3
    of them (fewer than, as many as, and one more than the distance), every sparse column in descending order (ranges
    walked backwards through the tile's entries), one tile and 15 (the last tile's entries end the array) — each equal
    to the float64 sum of the stored values, and to the AVX2 build's bits (no prefetch there; the prefetch changes no
    sum)."""
    native, avx2 = relight._wavelet_lib("native"), relight._wavelet_lib("avx2") if HAS_AVX2 else None
    g = torch.Generator().manual_seed(11)
    tr = _transfer(torch.int16, 1)
    for tile in (None, 160):
        r = relight.WaveletRelighter(tr, threads=1, layouts="column", tile=tile)
        idx, vals = r.reference_rows()
        sparse = torch.nonzero((r.dslot < 0) & (r.nnz > 0)).flatten()
        assert sparse.numel() > 3
        for li in (sparse[:1], sparse[5:7], sparse[-3:], sparse.flip(0)):
            li = li.contiguous()
            for C in (1, 3):
                lv = torch.randn(C, li.numel(), generator=g)
                L = torch.zeros(C, r.P, dtype=torch.float64).index_add_(1, li, lv.double())
                ref = relight.wavelet_dense(vals.double(), idx, torch.arange(r.P), L, r.P)
                for threads in (1, 2):
                    got = _relight(r, native, li, lv, threads)
                    err = float((got.double() - ref).abs().max())
                    assert err <= 1e-5 * float(ref.abs().max()) + 1e-6, (tile, li.numel(), C, threads, err)
                    if avx2 is not None:
                        assert torch.equal(got, _relight(r, avx2, li, lv, threads)), (tile, li.numel(), C, threads)
