"""Relighting straight from the compressed forms (``AffineCodec.relight``: the compiled kernels of
``codecs.relight_kernels`` and the torch path used without a C compiler) against decode-then-relight
through the uncompressed reference (``prt_torch.relight.apply_dense`` / ``apply_taps``, float64):
every codec family × view mode (none, dense, taps) × K = 1 / K > 1 × with / without a mean ×
n_vectors prefixes × per-cluster n_k (adaptive, packed codes) × label dtypes × colours."""
import itertools
import math
import re
import shutil
import warnings

from pathlib import Path

import pytest
import torch

from prt_torch import codecs, relight
from prt_torch.codecs import relight_kernels
from prt_torch.codecs.synthetic import tent_taps_random, transfer_like
from prt_torch.harness.timing import torch_threads

EPS = torch.finfo(torch.float32).eps


@pytest.fixture(params=["native", "torch"])
def path(request, monkeypatch):
    """Run a test through the compiled kernels and through the torch formulation."""
    if request.param == "torch":
        monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    elif relight_kernels.native() is None:
        pytest.skip(f"no compiled kernels: {relight_kernels.native_status()['detail']}")
    return request.param


def _without_mean(c, enc):
    """A fitted K > 1 codec made linear (x̃ = Σ w_i x_i, no x_0): decode and relight both read
    the same (labels, weights, basis), so they must still agree (the encoding's cached plans,
    built with the mean, are dropped)."""
    c.means_ = None
    enc.cache.clear()


# (label, codec, params, (n_out, n_in), P, edit)
CASES = [
    ("vq K>1", "vq", {"clusters": 7, "max_iter": 5}, (9, 4), 200, None),
    ("vq K=1", "vq", {"clusters": 1}, (9, 4), 100, None),
    ("vq int16 labels", "vq", {"clusters": 300, "max_iter": 2, "init": "random"}, (5, 3), 600, None),
    ("vq n_out=16", "vq", {"clusters": 7, "max_iter": 5}, (16, 4), 203, None),  # rows a multiple of 8: the mean-only dense loop
    ("pca mean", "pca", {"vectors": 5}, (9, 4), 200, None),
    ("pca no mean", "pca", {"vectors": 5, "center": False}, (9, 4), 200, None),
    ("cpca static", "cpca_static", {"clusters": 6, "vectors": 3, "max_iter": 5}, (9, 4), 250, None),
    # dense views pair two points of one cluster per pass: 3 blocks of 8 rows with AVX-512VL, 1 with 16 registers
    ("cpca static n_out=24", "cpca_static", {"clusters": 4, "vectors": 3, "max_iter": 5}, (24, 4), 230, None),
    ("pca n_out=8", "pca", {"vectors": 3}, (8, 4), 117, None),
    ("cpca iterative n_out=16", "cpca_iterative", {"clusters": 5, "vectors": 4, "iterations": 2, "max_iter": 5}, (16, 3), 250, None),
    ("cpca adaptive (packed)", "cpca_adaptive",  # n_k = 0..3 per cluster on this signal
     {"clusters": 8, "vectors": 2, "budget": 2.0, "max_vectors": 5, "iterations": 2, "adapt_iters": 2, "max_iter": 5}, (9, 4), 300,
     None),
    ("cpca no mean", "cpca_static", {"clusters": 6, "vectors": 3, "max_iter": 5}, (9, 4), 250, _without_mean),
    ("mrt_pca", "mrt_pca", {"vectors": 7}, (16, 9), 200, None),
    ("mrt_pca mean", "mrt_pca", {"vectors": 7, "center": True}, (16, 9), 200, None),
    ("mrt_pca n_out=49", "mrt_pca", {"vectors": 5}, (49, 4), 123, None),  # 7×7 tents: the 7-vector RGB path, a tail
    # 49 rows with clusters and packed weights: with AVX-512, the 16-lane dense (a tail row) and no-view paths
    ("cpca adaptive n_out=49 (packed)", "cpca_adaptive",
     {"clusters": 6, "vectors": 2, "budget": 3.0, "max_vectors": 5, "iterations": 2, "adapt_iters": 2, "max_iter": 5}, (49, 4), 300,
     None),
    ("mrt_pca 8 vectors", "mrt_pca", {"vectors": 8}, (16, 9), 150, None),  # taps read the 8 stored weights in place
]


def _fit(name, params, ms, P, edit, seed=2):
    n_out, n_in = ms
    if name == "cpca_adaptive":  # a signal whose clusters differ in complexity: per-cluster n_k vary
        X = transfer_like(P, n_out, n_in, seed=1, regions=12, noise=0.05)
    else:
        X = transfer_like(P, n_out, n_in, seed=seed, regions=12)
    c = codecs.get(name, **params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # short fits of tiny signals may not converge
        enc = c.fit_encode(X, matrix_shape=ms)
    if edit is not None:
        edit(c, enc)
    return c, enc


def _reference(M, L, view):
    """Decode-then-relight through the uncompressed reference in float64, and the same with
    absolute values (the scale of float32 rounding)."""
    Md, Ld = M.double(), L.double()
    if view is None:
        return Md @ Ld, Md.abs() @ Ld.abs()
    if isinstance(view, tuple):
        idx, w = view
        return (relight.apply_taps(Md, Ld.T, idx, w.double()), relight.apply_taps(Md.abs(), Ld.abs().T, idx, w.double().abs()))
    return relight.apply_dense(Md, Ld.T, view.double()), relight.apply_dense(Md.abs(), Ld.abs().T, view.double().abs())


def _check(out, ref, scale, J, what):
    tol = 8 * (J + 8) * EPS * (scale + 1e-6 * float(scale.max()))
    assert out.dtype == torch.float32 and out.shape == ref.shape, (what, out.shape, ref.shape)
    err = (out.double() - ref).abs()
    assert bool((err <= tol).all()), (what, float(err.max()), float((err / tol).max()))


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_relight_equals_decode_then_reference(case, path):
    _check_case(case, path)


def case_inputs(c, P: int, n_out: int):
    """``(generator, n_vectors prefixes, views)`` a fitted CASES codec is relit with: no view, a dense
    view, tent taps where n_out is a square, 2 arbitrary taps (benchmarks/ab_bits.py uses the same)."""
    g = torch.Generator().manual_seed(5)
    nmax = c.basis_.shape[1]
    prefixes = sorted({None, 0, 1, max(0, nmax - 1)} - ({1} if nmax < 1 else set()), key=lambda v: -1 if v is None else v)
    side = math.isqrt(n_out)
    views = [None, torch.randn(P, n_out, generator=g)]
    if side * side == n_out:
        views.append(tent_taps_random(P, side, seed=3))
    views.append((torch.randint(0, n_out, (P, 2), generator=g), torch.randn(P, 2, generator=g)))  # 2 arbitrary taps
    return g, prefixes, views


def _check_case(case, path):
    """Every view mode, colour count and n_vectors prefix of one of CASES against the reference."""
    label, name, params, ms, P, edit = case
    n_out, n_in = ms
    c, enc = _fit(name, params, ms, P, edit)
    assert enc.meta["packed"] == ("packed" in label), label  # the packed layout is exercised
    nmax = c.basis_.shape[1]
    g, prefixes, views = case_inputs(c, P, n_out)
    for C, ns in ((3, prefixes), (1, [None]), (5, [None])):
        L = torch.randn(n_in, C, generator=g)
        for n in ns:
            M = c.decode(enc, n_vectors=n).view(P, n_out, n_in)
            J = (nmax if n is None else min(n, nmax)) + 1
            for view in views:
                out = c.relight(enc, L, view=view, n_vectors=n)
                ref, scale = _reference(M, L, view)
                _check(out, ref, scale, J * n_out, (label, path, C, n, None if view is None else type(view).__name__))


@pytest.mark.parametrize("march", ["-march=x86-64-v3", "-mavx2", None], ids=["avx2", "avx2-without-fma", "baseline"])
def test_kernels_built_for_other_instruction_sets(march, monkeypatch, tmp_path):
    """The kernels as built on machines unlike this one: AVX2 + FMA with 16 vector registers (the
    rows kernel pairs points in fewer accumulators there), AVX2 without FMA (once failed to
    compile: intrinsics without their header) and the compiler's baseline ISA (the
    fallback where -march=native is refused; 8-float vectors split in SSE halves), against the
    float64 reference, every view mode (the default build is the native path of the test above);
    the dense kernel's paired points: n_out = 8 with 16 registers, 24 with AVX-512VL."""
    import platform

    if march is not None and platform.machine() not in ("x86_64", "AMD64"):
        pytest.skip("x86-64 micro-architecture levels only")
    try:
        cpu_flags = set(Path("/proc/cpuinfo").read_text().split())
    except OSError:
        cpu_flags = None
    if march is not None and cpu_flags is not None and not {"avx2", "fma", "bmi2", "movbe"} <= cpu_flags:
        pytest.skip("this CPU cannot run AVX2 / x86-64-v3 code")
    compiles_here = relight_kernels.native() is not None  # this machine's own build
    flags = [f for f in relight_kernels._FLAGS if f != "-march=native"] + ([march] if march else [])
    monkeypatch.setattr(relight_kernels, "_FLAGS", flags)
    monkeypatch.setattr(relight_kernels, "_state", {})
    monkeypatch.setenv("PRT_TORCH_CACHE", str(tmp_path))
    if relight_kernels.native() is None:
        detail = relight_kernels.native_status()["detail"]
        if compiles_here:  # the same compiler builds -march=native: a failure here is the source's
            pytest.fail(f"the kernels do not compile with {' '.join(flags)}: {detail}")
        pytest.skip(f"no compiled kernels: {detail}")
    assert " ".join(flags) in relight_kernels.native_status()["detail"]
    for case in CASES:
        if case[0] in ("vq n_out=16", "pca mean", "pca n_out=8", "cpca static", "cpca static n_out=24", "cpca adaptive (packed)",
                       "mrt_pca n_out=49"):
            _check_case(case, "native " + (march or "baseline"))
    test_kernels_visit_points_in_any_order()  # and the same bits whichever order (so pairing) the points are visited in
    test_rows_of_one_vector_stay_in_their_rows()  # rows of <= 8 floats: scalar stores and FMA without AVX-512VL
    test_rows_of_one_vector_by_term_count_and_label_kind()  # weights broadcast by permutes (AVX2) or from memory
    if march == "-march=x86-64-v3":  # FMA: the constants' bits are the FMA chain's (without FMA products round apart)
        test_vector_constants_eight_clusters_per_vector()


@pytest.mark.parametrize("name, params", [("vq", {"clusters": 5}), ("pca", {"vectors": 3}),
                                          ("cpca_adaptive", {"clusters": 4, "vectors": 2, "budget": 2.0, "max_vectors": 4})])
def test_vector_codecs(name, params, path):
    """Vectors (no matrix_shape): ``[P, C]`` = x̃_p · l."""
    X = transfer_like(200, 1, 12, seed=4, regions=8)
    c = codecs.get(name, **params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(X)
    L = torch.randn(12, 3)
    ref = c.decode(enc).double() @ L.double()
    _check(c.relight(enc, L), ref, c.decode(enc).double().abs() @ L.double().abs(), 12 * 8, (name, path))
    with pytest.raises(ValueError, match="fitted on vectors"):
        c.relight(enc, L, view=torch.zeros(200, 1))


def test_view_dtypes_and_layouts(path):
    """float64 / non-contiguous views and int32 tap indices give the float32 view's result."""
    c, enc = _fit("cpca_static", {"clusters": 4, "vectors": 2}, (9, 4), 200, None)
    g = torch.Generator().manual_seed(1)
    L = torch.randn(4, 3, generator=g)
    y = torch.randn(200, 9, generator=g)
    base = c.relight(enc, L, view=y)
    assert torch.allclose(c.relight(enc, L, view=y.double()), base, rtol=1e-6, atol=1e-6)
    yt = torch.randn(9, 200, generator=g).T  # non-contiguous
    assert torch.allclose(c.relight(enc, L, view=yt), c.relight(enc, L, view=yt.contiguous()), rtol=1e-6, atol=1e-6)
    idx, w = tent_taps_random(200, 3, seed=2)
    assert torch.allclose(c.relight(enc, L, view=(idx.int(), w.double())), c.relight(enc, L, view=(idx, w)), rtol=1e-6, atol=1e-6)


def test_a_non_finite_view_value_in_any_lane_of_a_block_is_named():
    """The dense kernels reduce 8 points at a time and flag a non-finite result from all 8 lanes at
    once (store8_rgb: a lane mask of the 24 sums): a NaN or Inf in the view of any point of a block
    (each of its 8 lanes, blocks past the first, the tail) is refused naming that value, for VQ (its
    8-point loop: `dense: VQ, 8 lanes, 8 points`) and PCA."""
    L = torch.randn(9, 3)
    for name, params in (("vq", {"clusters": 5, "max_iter": 3}), ("pca", {"vectors": 3})):
        c, enc = _fit(name, params, (16, 9), 37, None)
        for p in (0, 3, 7, 8, 13, 31, 32, 36):
            for bad in (float("nan"), float("inf")):
                y = torch.randn(37, 16, generator=torch.Generator().manual_seed(p))
                y[p, 5] = bad
                with pytest.raises(ValueError, match=rf"view has 1 non-finite value\(s\).*index \({p}, 5\)"):
                    c.relight(enc, L, view=y)
        assert torch.isfinite(c.relight(enc, L, view=torch.randn(37, 16))).all()


def test_bad_views_are_refused_naming_the_value(path):
    c, enc = _fit("mrt_pca", {"vectors": 4}, (16, 9), 150, None)
    L = torch.randn(9, 3)
    y = torch.randn(150, 16)
    y[7, 3] = float("nan")
    with pytest.raises(ValueError, match=r"view has 1 non-finite value\(s\).*index \(7, 3\)"):
        c.relight(enc, L, view=y)
    y[7, 3] = float("inf")
    with pytest.raises(ValueError, match="view has 1 non-finite"):
        c.relight(enc, L, view=y)
    idx, w = tent_taps_random(150, 4, seed=1)
    vq, vq_enc = _fit("vq", {"clusters": 5, "max_iter": 3}, (16, 9), 150, None)  # one term: the kernel's scalar tap path
    for codec, e in ((c, enc), (vq, vq_enc)):
        bad = idx.clone()
        bad[3, 1] = 16
        with pytest.raises(ValueError, match=r"view tap indices span \[0, 16\]; accepted: \[0, n_out\) = \[0, 16\)"):
            codec.relight(e, L, view=(bad, w))
        bad[3, 1] = -1
        with pytest.raises(ValueError, match=r"view tap indices span \[-1, 15\]"):
            codec.relight(e, L, view=(bad, w))
    w2 = w.clone()
    w2[5, 0] = float("nan")
    with pytest.raises(ValueError, match=r"view weights has 1 non-finite value\(s\).*index \(5, 0\)"):
        c.relight(enc, L, view=(idx, w2))
    # finite data whose result overflows float32 is not an input error
    big = torch.full((150, 16), 3e38)
    out = c.relight(enc, L * 1e30, view=big)
    assert out.shape == (150, 3)


def test_bad_lights_are_refused_naming_the_value(path):
    """A NaN or Inf in the light is refused naming it, on every path: the compiled kernels check
    it as the constants kernel reads it, the torch path before it starts; every view mode, a
    float64 light, and the J = 0 shortcut (no mean, no vectors kept) that computes no constants."""
    c, enc = _fit("mrt_pca", {"vectors": 4}, (16, 9), 150, None)
    vq, vq_enc = _fit("vq", {"clusters": 5, "max_iter": 3}, (16, 9), 150, None)
    views = (None, torch.randn(150, 16), tent_taps_random(150, 4, seed=1))
    for dtype in (torch.float32, torch.float64):
        L = torch.randn(9, 3, dtype=dtype)
        L[4, 2] = float("nan")
        for codec, e in ((c, enc), (vq, vq_enc)):
            for view in views:
                with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*index \(4, 2\)"):
                    codec.relight(e, L, view=view)
        L[4, 2] = float("-inf")
        with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*index \(4, 2\)"):
            c.relight(enc, L, view=views[1], out=torch.empty(150, 3))
        with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*index \(4, 2\)"):
            c.relight(enc, L, n_vectors=0)  # mrt_pca keeps no mean: J = 0
    # finite as given, but beyond float32's range (relighting computes in float32)
    L = torch.randn(9, 3, dtype=torch.float64)
    L[4, 2] = 1e39
    for view in views:
        with pytest.raises(ValueError, match=r"light \(converted to float32.*has 1 non-finite.*index \(4, 2\)"):
            c.relight(enc, L, view=view)
    lib = relight_kernels.native()
    if lib is not None:  # the constants kernel names it too, and never returns a table it did not compute
        with pytest.raises(ValueError, match=r"light \(converted to float32.*index \(4, 2\)"):
            relight_kernels.constants(lib, c.means_, c.basis_, 4, 16, 9, L, "dense", scratch=True)


def test_mean_only_fast_path_needs_one_term():
    """CPCA adaptive whose encoded points all sit in clusters keeping no vectors (n_k = 0): the
    packed weights are empty (no weights pointer) although J = 1 + n > 1, so the VQ no-view loop
    (one term per cluster) must not take it; rows of 16·3 floats (a multiple of 8: that loop's
    shape) and 4·3 (padded), against decode-then-relight."""
    X = transfer_like(300, 16, 4, seed=1, regions=12, noise=0.05)
    c = codecs.get("cpca_adaptive", clusters=8, vectors=1, budget=1.0, max_vectors=2, iterations=2, adapt_iters=2, max_iter=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(X, matrix_shape=(16, 4))
    nk, lab = c.n_vectors_, c.labels_of(enc).long()
    assert bool((nk == 0).any()) and c.basis_.shape[1] >= 1, nk  # the case exists on this signal
    k = int((nk == 0).nonzero()[0, 0])
    e = c.encode(X[lab == k])
    assert e.tensors["coeffs"].numel() == 0 and e.points > 0
    g = torch.Generator().manual_seed(1)
    for C in (3, 1):
        L = torch.randn(4, C, generator=g)
        ref = c.decode(e).view(-1, 16, 4).double() @ L.double()
        assert torch.allclose(c.relight(e, L).double(), ref, atol=1e-5), C


def test_corrupt_codes_are_refused_before_any_kernel_reads_them():
    c, enc = _fit("cpca_static", {"clusters": 4, "vectors": 2}, (9, 4), 200, None)
    L = torch.randn(4, 3)
    bad = codecs.Encoded(enc.codec, dict(enc.tensors), dict(enc.meta))
    lab = bad.tensors["labels"].clone()
    lab[10] = 9  # cluster 9 of 4
    bad.tensors["labels"] = lab
    if relight_kernels.native() is not None:
        with pytest.raises(ValueError, match=r"enc labels .* span \[0, 9\]; accepted: \[200\] in \[0, 4\)"):
            c.relight(bad, L)
    packed = next(x for x in CASES if "packed" in x[0])
    ad, enc2 = _fit(*packed[1:])
    assert enc2.meta["packed"]
    short = codecs.Encoded(enc2.codec, {**enc2.tensors, "coeffs": enc2.tensors["coeffs"][:-3]}, dict(enc2.meta))
    if relight_kernels.native() is not None:
        with pytest.raises(ValueError, match=r"enc packed coeffs have shape \(\d+,\)"):
            ad.relight(short, L)


def test_model_edits_and_refits_are_seen():
    """The kernels read a per-model cache of the representatives: an in-place edit of the basis
    and a refit must both show up in the next relight."""
    c, enc = _fit("cpca_static", {"clusters": 4, "vectors": 2}, (9, 4), 200, None)
    L = torch.randn(4, 3)
    y = torch.randn(200, 9)
    c.relight(enc, L, view=y)
    with torch.no_grad():
        c.basis_.mul_(2.0)
        if c.means_ is not None:
            c.means_.mul_(2.0)
    M = c.decode(enc).view(200, 9, 4)
    ref, scale = _reference(M, L, y)
    _check(c.relight(enc, L, view=y), ref, scale, 3 * 9, "after in-place edit")
    X2 = transfer_like(200, 9, 4, seed=9, regions=5)
    enc2 = c.fit_encode(X2, matrix_shape=(9, 4))
    ref, scale = _reference(c.decode(enc2).view(200, 9, 4), L, y)
    _check(c.relight(enc2, L, view=y), ref, scale, 3 * 9, "after refit")


def test_kernel_constants_match_cluster_constants():
    """Every layout the constants kernel writes holds M_i^k l of ``cluster_constants``."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    c, enc = _fit("cpca_static", {"clusters": 5, "vectors": 3}, (9, 4), 300, None)
    wide, _ = _fit("cpca_static", {"clusters": 3, "vectors": 10}, (9, 4), 300, None)
    L = torch.randn(4, 3)
    for c, n in ((c, 3), (c, 1), (c, 0), (wide, 10)):  # J = 4, 2, 1 (the mean alone: taps unpadded), 11 (two blocks of 8 terms)
        ref = c.cluster_constants(L, n)  # [K, J, n_out, C]
        K, J, n_out, C = ref.shape
        rows = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 4, L, "rows")
        assert torch.allclose(rows[..., : n_out * C].reshape(K, J, n_out, C), ref, atol=1e-5)
        assert not rows[..., n_out * C:].any()
        dense = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 4, L, "dense")
        assert torch.allclose(dense[..., :n_out].permute(0, 1, 3, 2), ref, atol=1e-5) and not dense[..., n_out:].any()
        taps = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 4, L, "taps")
        assert torch.allclose(taps[..., :J].permute(0, 3, 1, 2), ref, atol=1e-5) and not taps[..., J:].any()
        assert taps.shape[-1] == (1 if J == 1 else 8 if J <= 8 else 16)
    # per-cluster term counts (CPCA adaptive's n_k): cluster k's first 1 + min(n, n_k) terms as
    # above; taps zero beyond them (read 8 at a time), whatever the buffer held before (a scratch
    # buffer filled with NaN first; RGB and one colour: both code paths of the kernel)
    c, n = wide, 10
    nk = torch.tensor([0, 4, 12], dtype=torch.int64)
    for C in (3, 1):
        Lc = L[:, :C].contiguous()
        ref = c.cluster_constants(Lc, n)
        K, J, n_out, _ = ref.shape
        for kind in ("rows", "dense", "taps"):
            full = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 4, Lc, kind)
            relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 4, Lc, kind, scratch=True).fill_(float("nan"))
            raw = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 4, Lc, kind, scratch=True, nk=nk)
            assert not torch.equal(raw, full), kind  # the terms no point reads were skipped
            got = {"rows": lambda t: t[..., : n_out * C].reshape(K, J, n_out, C), "dense": lambda t: t[..., :n_out].permute(0, 1, 3, 2),
                   "taps": lambda t: t[..., :J].permute(0, 3, 1, 2)}[kind](raw)
            for k in range(K):
                jk = 1 + min(n, int(nk[k]))
                assert torch.allclose(got[k, :jk], ref[k, :jk], atol=1e-5), (kind, C, k)
                if kind == "taps":
                    assert torch.equal(got[k, jk:], torch.zeros_like(got[k, jk:])), (C, k)
    with pytest.raises(ValueError, match=r"nk is torch.int32 \(3,\); accepted: contiguous int64 \[K\] = \[3\]"):
        relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 4, L, "taps", nk=nk.int())


def test_rows_of_one_vector_read_no_weight_past_the_last_used():
    """The fixed-term loop loads 4 or 8 weights per point at once; it stops where that load would
    pass the last weight the one-point chain reads, so weights ending right there (at a page the
    process may not read: a read past it is a crash) work for any row stride — 0 (one row for
    every point), below 4, 5-7, 8 and more — and give the float64 chain's values. The same for one
    cluster (PCA, RGB: 8 points in lanes, each point's first 8 weights one load, the rest masked)."""
    import ctypes
    import sys

    lib = relight_kernels.native()
    if lib is None or not sys.platform.startswith("linux"):
        pytest.skip("compiled kernels on Linux (mmap/mprotect guard page)")
    libc = ctypes.CDLL(None)
    libc.mmap.restype, libc.mmap.argtypes = ctypes.c_void_p, [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                                                              ctypes.c_int, ctypes.c_long]
    libc.mprotect.argtypes = [ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int]
    libc.munmap.argtypes = [ctypes.c_void_p, ctypes.c_size_t]
    page = 4096
    base = libc.mmap(None, 2 * page, 3, 0x22, -1, 0)  # PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS
    assert base not in (None, ctypes.c_void_p(-1).value) and libc.mprotect(base + page, page, 0) == 0
    g = torch.Generator().manual_seed(31)
    try:
        for (ws, nuse), K in itertools.product(((0, 4), (0, 8), (2, 2), (3, 3), (6, 5), (8, 8), (11, 2), (11, 7), (9, 9)), (3, 1)):
            for P, Fo in ((1, 3), (9, 3), (16, 3), (40, 3), (40, 8)):  # K = 1, Fo = 3: PCA's 8 points in lanes
                n = (P - 1) * ws + nuse  # the weights the chain reads, ending at the guard page
                W = torch.frombuffer((ctypes.c_float * n).from_address(base + page - 4 * n), dtype=torch.float32)
                W.copy_(torch.randn(n, generator=g))
                T = torch.randn(K, nuse + 1, 8, generator=g)
                T[..., Fo:] = 0.0
                labels = torch.randint(0, K, (P,), generator=g).to(torch.uint8) if K > 1 else None
                rows = torch.stack([W[p * ws:p * ws + nuse] for p in range(P)]).double()
                Td = T.double()[labels.long() if K > 1 else torch.zeros(P, dtype=torch.long)]
                ref = Td[:, 0, :Fo] + (rows[:, :, None] * Td[:, 1:, :Fo]).sum(1)
                for threads in (1, 2):
                    with torch_threads(threads):
                        got = relight_kernels.affine_rows(lib, T, nuse + 1, Fo, 1, labels, W, ws, None, None, nuse, True, P=P)
                    assert torch.allclose(got.double(), ref, atol=1e-5), (ws, nuse, P, Fo, threads)
    finally:
        libc.munmap(base, 2 * page)


def test_vector_constants_eight_clusters_per_vector():
    """Vectors (n_out = 1), layout 'rows': the constants kernel puts 8 clusters in a vector's
    lanes (``prt_constants_lanes``, model ``model_t(lanes=True)``). Against float64 M l for
    cluster counts around multiples of 8, 1/3/4 colours, with and without a mean, any prefix of
    the vectors, 1 and 2 threads (K = 1500: enough work for both); bit for bit the chain of fused
    multiply-adds over the SH index (RGB: even and odd indices in two chains, then added), as
    float64 steps rounded to float32 (exact products, one rounding per step), and zero padding."""

    def fma_chain(x, l, parts):  # x [K, J, n_in], l [n_in, C] -> [K, J, C] float32
        acc = [torch.zeros(x.shape[0], x.shape[1], l.shape[1], dtype=torch.float32) for _ in range(parts)]
        n2 = x.shape[2] - x.shape[2] % 2 if parts == 2 else 0
        for i in range(x.shape[2]):
            p = i % 2 if i < n2 else 0
            acc[p] = (x[:, :, i, None].double() * l[i].double() + acc[p].double()).float()
        return acc[0] if parts == 1 else acc[0] + acc[1]

    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(21)
    for K, n_in, nmax, mean in ((1, 16, 8, True), (5, 9, 3, True), (8, 16, 0, True), (9, 4, 2, False), (20, 16, 4, True),
                                (1500, 16, 3, True)):
        means = torch.randn(K, n_in, generator=g) if mean else None
        basis = torch.randn(K, nmax, n_in, generator=g)
        for C in (1, 3, 4):
            L = torch.randn(n_in, C, generator=g)
            for n in sorted({0, nmax // 2, nmax}):
                J = (1 if mean else 0) + n
                if J == 0:
                    continue
                reps = basis[:, :n] if means is None else torch.cat([means[:, None], basis[:, :n]], 1)  # [K, J, n_in]
                ref = reps.double() @ L.double()  # [K, J, C]
                chain = fma_chain(reps, L, 2 if C == 3 else 1)
                for threads in (1, 2):
                    with torch_threads(threads):
                        got = relight_kernels.constants(lib, means, basis, n, 1, n_in, L, "rows")
                    case = (K, n_in, n, mean, C, threads)
                    assert got.shape == (K, J, relight_kernels._pad8(C)), case
                    assert torch.allclose(got[..., :C].double(), ref, atol=1e-5 * n_in), case
                    assert not got[..., C:].any(), case
                    assert torch.equal(got[..., :C].view(torch.int32), chain.view(torch.int32)), case
    with pytest.raises(ValueError, match="lanes=True lays out vectors"):
        relight_kernels.model_t(None, torch.zeros(2, 1, 6), 2, 3, lanes=True)
    # one basis relit as vectors and as 1-row matrices with a view keeps both layouts (no rebuild per call)
    basis = torch.randn(5, 2, 4, generator=g)
    lanes, plain = relight_kernels.model_t(None, basis, 1, 4, lanes=True), relight_kernels.model_t(None, basis, 1, 4)
    assert relight_kernels.model_t(None, basis, 1, 4, lanes=True) is lanes and relight_kernels.model_t(None, basis, 1, 4) is plain
    basis.mul_(2.0)  # an in-place edit rebuilds both
    assert torch.equal(relight_kernels.model_t(None, basis, 1, 4, lanes=True), 2 * lanes)
    assert torch.equal(relight_kernels.model_t(None, basis, 1, 4), 2 * plain)


def test_native_status_reports_the_path(monkeypatch):
    st = relight_kernels.native_status()
    assert isinstance(st["native"], bool) and st["detail"]
    if shutil.which("cc") or shutil.which("gcc"):  # with a compiler the kernels must build (a failure is a bug, not a skip)
        assert st["native"], st["detail"]
    monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    assert relight_kernels.native() is None and relight_kernels.native_status() == {"native": False, "detail": "disabled by PRT_TORCH_NATIVE=0"}


def _kernel_case(P: int):
    """A small CPCA encoding (5 clusters × 3 vectors, 9×4 matrices) with its native codes,
    constants of every layout, a dense view and taps, for the kernel tests below."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    c, enc = _fit("cpca_static", {"clusters": 5, "vectors": 3, "max_iter": 5}, (9, 4), P, None)
    L = torch.randn(4, 3)
    T = {k: relight_kernels.constants(lib, c.means_, c.basis_, 3, 9, 4, L, k) for k in ("rows", "dense", "taps")}
    taps = (torch.randint(0, 9, (P, 4)), torch.rand(P, 4))
    return lib, c.labels_of(enc), c._native_codes(enc, 3), T, torch.randn(P, 9), taps


def test_kernels_visit_points_in_any_order():
    """The kernels' optional visiting order (a permutation, e.g. by cluster) changes nothing."""
    lib, labels, codes, T, y, taps = _kernel_case(250)
    order = torch.argsort(labels, stable=True).to(torch.int32)
    for o in (order, torch.randperm(250).to(torch.int32)):
        assert torch.equal(relight_kernels.affine_rows(lib, T["rows"], 4, 9, 3, *codes, P=250, order=o),
                           relight_kernels.affine_rows(lib, T["rows"], 4, 9, 3, *codes, P=250))
        assert torch.equal(relight_kernels.affine_dense(lib, T["dense"], 4, 9, 3, *codes, y, order=o)[0],
                           relight_kernels.affine_dense(lib, T["dense"], 4, 9, 3, *codes, y)[0])
        assert torch.equal(relight_kernels.affine_taps(lib, T["taps"], 4, 9, 3, *codes, *taps, order=o)[0],
                           relight_kernels.affine_taps(lib, T["taps"], 4, 9, 3, *codes, *taps)[0])
    with pytest.raises(ValueError, match="order must be a contiguous int32 permutation"):
        relight_kernels.affine_rows(lib, T["rows"], 4, 9, 3, *codes, P=250, order=order.long())
    # an order's range is checked once per tensor version: an in-place edit is checked again
    bad = order.clone()
    relight_kernels.affine_rows(lib, T["rows"], 4, 9, 3, *codes, P=250, order=bad)
    bad[7] = 250
    with pytest.raises(ValueError, match=r"order spans \[0, 250\]"):
        relight_kernels.affine_rows(lib, T["rows"], 4, 9, 3, *codes, P=250, order=bad)


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int16, torch.int32])
def test_mean_only_rows_gather_each_label_dtype(dtype):
    """VQ without a view (the mean-only rows loop, one per label dtype): out[p] = T[label_p],
    against plain indexing, for every label width the codecs store, 1 and 2 threads, and rows
    that are not a multiple of 8 floats (the general loop: padded rows copied)."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(3)
    P, K = 301, {torch.uint8: 200, torch.int16: 3000, torch.int32: 40000}[dtype]
    labels = torch.randint(0, K, (P,), generator=g).to(dtype)
    labels[:3] = torch.tensor([0, K - 1, K // 2]).to(dtype)
    for n_out, C in ((16, 3), (8, 1), (5, 3)):
        Fo = n_out * C
        F = (Fo + 7) // 8 * 8
        T = torch.randn(K, 1, F, generator=g)
        T[..., Fo:] = 0.0
        ref = T[labels.long(), 0, :Fo]
        for threads in (1, 2):
            with torch_threads(threads):
                got = relight_kernels.affine_rows(lib, T, 1, n_out, C, labels, None, 0, None, None, 0, 1, P=P)
            assert torch.equal(got, ref), (dtype, n_out, C, threads)


@pytest.mark.parametrize("dtype", [torch.uint8, torch.int16, torch.int32])
def test_diffuse_vq_rows_every_tail_and_split_write_only_their_floats(dtype):
    """Diffuse VQ without a view (n_out = 1, C = 3: rows of 3 floats from constants padded to 8),
    the point kernel that writes 4 points as three 16-byte stores without AVX-512, else packed 8 (uint8 labels, 8 labels read at a
    time) and the loops for the rest: out[p] = T[label_p, :3] bit for bit against plain indexing, for
    point counts that leave every tail length past groups of 4 and 8, split over 1-3 threads (ranges
    starting anywhere), and nothing written past the last point's 3 floats (a NaN-filled guard after
    them stays NaN; the constants' padding is filled with values that must not appear)."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(11)
    K = {torch.uint8: 256, torch.int16: 700, torch.int32: 5000}[dtype]
    T = torch.randn(K, 1, 8, generator=g)
    T[..., 3:] = 1e30  # padding: a kernel that wrote it out would put it in the next point's floats
    for P in [*range(0, 26), 31, 32, 33, 1001, 4099]:
        labels = torch.randint(0, K, (P,), generator=g).to(dtype)
        if P >= 2:
            labels[:2] = torch.tensor([K - 1, 0]).to(dtype)
        ref = T[labels.long(), 0, :3]
        for threads in (1, 2, 3):
            buf = torch.full((P * 3 + 16,), float("nan"))
            with torch_threads(threads):
                got = relight_kernels.affine_rows(lib, T, 1, 1, 3, labels, None, 0, None, None, 0, 1, P=P, out=buf[:P * 3])
            assert torch.equal(got.view(P, 3), ref), (dtype, P, threads)
            assert torch.isnan(buf[P * 3:]).all(), (dtype, P, threads)


def test_dense_and_taps_kernels_do_not_depend_on_the_thread_split():
    """The dense and taps kernels reduce RGB points 8 at a time (hsum8) and the rest one by one (hsum),
    with the same association: a point's result is the same whichever way the threads split
    the points (P = 251: ranges that are not multiples of 8), and equals the visiting-order path."""
    lib, _, codes, T, y, taps = _kernel_case(251)
    runs = {"dense": lambda **kw: relight_kernels.affine_dense(lib, T["dense"], 4, 9, 3, *codes, y, **kw)[0],
            "taps": lambda **kw: relight_kernels.affine_taps(lib, T["taps"], 4, 9, 3, *codes, *taps, **kw)[0]}
    for name, run in runs.items():
        outs = []
        for n in (1, 2, 3):
            with torch_threads(n):
                outs.append(run())
        ordered = run(order=torch.arange(251, dtype=torch.int32))
        assert all(torch.equal(o, outs[0]) for o in outs[1:]) and torch.equal(ordered, outs[0]), name


# per-cluster term counts 2-4 at 25-49 rows of 251 points: packed weights
_ADAPTIVE_49 = {"clusters": 6, "vectors": 2, "budget": 3.0, "max_vectors": 5, "iterations": 2, "adapt_iters": 2, "max_iter": 5}


def test_dense_kernel_of_25_to_64_rows_any_layout_split_and_order():
    """RGB dense views of 25-64 rows (MRT's 7x7 = 49 tents) with weights: where the kernels are
    built with AVX-512 they sum 16 rows per vector from a layout padded to 16 floats
    (``dense_pad``), rows past the whole blocks (49 = 3 x 16 + 1) from a table with the terms in
    lanes, the last vector masked in a layout padded to 8 only, and the view row read in place,
    masked to its n_out floats. Against y_p · (M_p l) in float64 from the decoded matrices (to
    float32 rounding), with and without a mean (CPCA, MRT-PCA), ranges of 1-3 threads (P = 251:
    the paired and single points at the ranges' ends) and a random visiting order: the same bits
    for each layout, and for a call of the first 17 points alone; NaNs after the view's last row,
    and in a packed cluster's rows past its own term count (which the constants kernel leaves from
    earlier lights), are never read."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(21)
    P = 251
    for n_out in (25, 40, 49, 64):
        pad = relight_kernels.dense_pad(n_out)
        assert pad % 8 == 0 and n_out <= pad <= n_out + 15, (n_out, pad)
        for name, params in (("cpca_static", {"clusters": 5, "vectors": 3, "max_iter": 5}), ("mrt_pca", {"vectors": 4}),
                             ("cpca_adaptive", _ADAPTIVE_49)):
            c, enc = _fit(name, params, (n_out, 6), P, None)
            n = int(c.n_vectors_.max())
            codes = c._native_codes(enc, n)
            L = torch.randn(6, 3, generator=g)
            ybuf = torch.full((P * n_out + 16,), float("nan"))  # NaN past the view: a read beyond its rows would show
            y = ybuf[:P * n_out].view(P, n_out)
            y.copy_(torch.randn(P, n_out, generator=g))
            J = n + (1 if c.means_ is not None else 0)
            T = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 6, L, "dense")
            assert T.shape[3] == pad, (n_out, T.shape)
            T8 = torch.zeros(*T.shape[:3], relight_kernels._pad8(n_out))  # the same constants padded to 8 floats only
            T8[..., :n_out] = T[..., :n_out]
            ref = torch.einsum("po,poi,ic->pc", y.double(), c.decode(enc).double().view(P, n_out, 6), L.double())
            scale = torch.einsum("po,poi,ic->pc", y.double().abs(), c.decode(enc).double().abs().view(P, n_out, 6), L.double().abs())
            for Tl in (T, T8):
                outs = []
                for threads in (1, 2, 3):
                    with torch_threads(threads):
                        outs.append(relight_kernels.affine_dense(lib, Tl, J, n_out, 3, *codes, y)[0])
                order = torch.randperm(P, generator=g).to(torch.int32)
                outs.append(relight_kernels.affine_dense(lib, Tl, J, n_out, 3, *codes, y, order=order)[0])
                case = (n_out, name, Tl.shape[3])
                assert all(torch.equal(o.view(torch.int32), outs[0].view(torch.int32)) for o in outs[1:]), case
                assert bool(((outs[0].double() - ref).abs() <= 1e-5 * scale + 1e-6).all()), case
                if codes[3] is None:  # a call of the first 17 points alone (no tail table: the tail rows gathered)
                    sub = (None if codes[0] is None else codes[0][:17], codes[1][:17], *codes[2:])
                    got = relight_kernels.affine_dense(lib, Tl, J, n_out, 3, *sub, y[:17])[0]
                    assert torch.equal(got.view(torch.int32), outs[0][:17].view(torch.int32)), case
                if codes[4] is not None:  # packed: cluster k's rows past its own J_k terms are never read (NaN there)
                    Tp = Tl.clone()
                    for k, nk in enumerate(codes[4].tolist()):
                        Tp[k, (1 if c.means_ is not None else 0) + nk:] = float("nan")
                    got = relight_kernels.affine_dense(lib, Tp, J, n_out, 3, *codes, y)[0]
                    assert torch.equal(got.view(torch.int32), outs[0].view(torch.int32)), case


def test_rows_kernel_padded_rows_at_any_thread_split():
    """Without a view, rows whose Fo floats are padded to F (a multiple of 8) are combined padded
    and copied out unpadded: against e_p = T_k0 + Σ_i w_i T_k,1+i in float64, for padding shorter
    and longer than a row (Fo = 27, 9, 3 floats in rows of 32, 16, 8; nothing may land in a
    neighbour's row), 1-3 threads (ranges not multiples of 2: the paired and single paths at
    their ends), and the same bits in point and visiting order."""
    lib, labels, codes, _, _, _ = _kernel_case(251)
    W = codes[1]
    g = torch.Generator().manual_seed(4)
    for Fo in (27, 9, 3):
        F = (Fo + 7) // 8 * 8
        T = torch.randn(5, 4, F, generator=g)
        T[..., Fo:] = 0.0
        Td = T.double()[labels.long()]  # [P, J, F]
        ref = (Td[:, 0] + (W.double()[:, :, None] * Td[:, 1:]).sum(1))[:, :Fo]
        outs = []
        for n in (1, 2, 3):
            with torch_threads(n):
                outs.append(relight_kernels.affine_rows(lib, T, 4, Fo, 1, *codes, P=251))
        ordered = relight_kernels.affine_rows(lib, T, 4, Fo, 1, *codes, P=251, order=torch.arange(251, dtype=torch.int32))
        assert all(torch.equal(o, outs[0]) for o in outs[1:]) and torch.equal(ordered, outs[0]), Fo
        assert torch.allclose(outs[0].double(), ref, atol=1e-5), Fo


def test_dense_kernel_keeps_the_sign_of_zero_at_any_split():
    """A result of -0.0 (a negative mean seen through an all-zero view row) stays -0.0 whether its
    point is reduced in a block of 8 or alone at a range's end (1-3 threads, 9 points): the single
    point's sums are assigned, not added to 0.0f, which turned -0 into +0 (the 8-lane and the
    16-lane kernels: 24, 40, 49 and 64 rows). On the 8-lane path (no AVX-512) 49 rows are padded to
    56 with a -0 view (a +0 pad row added +0 to every lane) and 64 rows (8 blocks, colour by colour)
    assign their first chunk's sum: both lost the sign for every point before (AMD EPYC Zen 3)."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(5)
    for n_out in (24, 40, 49, 64):
        T = -(torch.rand(1, 3, 3, relight_kernels.dense_pad(n_out), generator=g) + 0.1)
        T[..., n_out:] = 0.0
        codes = (None, torch.zeros(9, 2), 2, None, None, 2, 1)
        y = torch.zeros(9, n_out)
        for threads in (1, 2, 3):
            with torch_threads(threads):
                out = relight_kernels.affine_dense(lib, T, 3, n_out, 3, *codes, y)[0]
            assert bool(torch.signbit(out).all()) and bool((out == 0).all()), (n_out, threads)


def test_rows_kernel_of_long_rows_gives_the_eight_lane_bits():
    """Without a view, rows of >= 97 floats with weights (MRT's 49 x 3 = 147): where the kernels
    are built with AVX-512, the constants are laid out padded to 16 floats (``rows_pad``) and a
    point's row is summed 16 floats per vector, two points per load, and stored straight into
    the unpadded output under a mask. Each float is the same FMA chain, so the result equals the
    8-lane pass's (the same constants padded to 8 floats) bit for bit, and y_p = M_p l in float64
    to float32 rounding; for CPCA (a mean, clusters; static, and adaptive with packed weights of
    per-cluster term counts) and MRT-PCA (no mean, one cluster), 1-3 threads, a random visiting
    order; nothing written past the last row, every row written."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(23)
    P = 251
    for n_out in (33, 49):
        Fo = 3 * n_out
        for name, params in (("cpca_static", {"clusters": 5, "vectors": 3, "max_iter": 5}), ("mrt_pca", {"vectors": 5}),
                             ("cpca_adaptive", _ADAPTIVE_49)):
            c, enc = _fit(name, params, (n_out, 6), P, None)
            n = int(c.n_vectors_.max())
            codes = c._native_codes(enc, n)
            J = n + (1 if c.means_ is not None else 0)
            L = torch.randn(6, 3, generator=g)
            T = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 6, L, "rows")
            assert T.shape[2] == relight_kernels.rows_pad(Fo, J) and T.shape[2] % 8 == 0 and Fo <= T.shape[2] < Fo + 16
            T8 = torch.zeros(*T.shape[:2], relight_kernels._pad8(Fo))  # the same constants padded to 8 floats only
            T8[..., :Fo] = T[..., :Fo]
            ref = torch.einsum("poi,ic->poc", c.decode(enc).double().view(P, n_out, 6), L.double()).reshape(P, Fo)
            outs = []
            for threads in (1, 2, 3):
                for Tl, order in ((T, None), (T8, None), (T, torch.randperm(P, generator=g).to(torch.int32))):
                    buf = torch.full((P * Fo + 16,), float("nan"))
                    buf[P * Fo:] = 7.0
                    with torch_threads(threads):
                        relight_kernels.affine_rows(lib, Tl, J, n_out, 3, *codes, P=P, order=order, out=buf[:P * Fo])
                    assert bool((buf[P * Fo:] == 7.0).all()), (n_out, name, threads)
                    outs.append(buf[:P * Fo].view(P, Fo).clone())
            case = (n_out, name)
            assert all(torch.equal(o.view(torch.int32), outs[0].view(torch.int32)) for o in outs[1:]), case
            assert bool(((outs[0].double() - ref).abs() <= 1e-5 * (1 + ref.abs())).all()), case


def _rows_every_split(lib, T, J, Fo, codes, P, g, case) -> list:
    """``affine_rows`` of one-vector rows at 1-3 threads, in point order and in a random visiting
    order, each into a NaN-filled buffer with sentinels after the last row (checked untouched):
    the six results ``[P, Fo]``."""
    outs = []
    for n in (1, 2, 3):
        for order in (None, torch.randperm(P, generator=g).to(torch.int32)):
            buf = torch.full((P * Fo + 16,), float("nan"))
            buf[P * Fo:] = 7.0
            with torch_threads(n):
                relight_kernels.affine_rows(lib, T, J, Fo, 1, *codes, P=P, order=order, out=buf[:P * Fo])
            assert bool((buf[P * Fo:] == 7.0).all()), (case, n)
            outs.append(buf[:P * Fo].view(P, Fo).clone())
    return outs


def test_rows_of_one_vector_stay_in_their_rows():
    """Rows of Fo <= 8 floats (F = 8: diffuse RGB, Fo = 3) take the 8-points-per-pass kernel, VQ's
    and PCA's by whole-vector stores that overlap the next rows (each overwritten by the next
    point's): against the FMA chain e_p = T_k0 + w_0 T_k1 + ... in float64 (to float32 rounding),
    for VQ (labels, no weights), PCA (one cluster), CPCA (labels and weights), ranges of 1-3
    threads, with and without a visiting order, the same bits (compared as bits: PCA's first
    output is -0.0 throughout, which a chain started from +0 would turn into +0); nothing written
    past the last row (sentinels after it) and every row written (NaN-filled buffers)."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(12)
    for P in (1, 7, 9, 23, 250):
        for Fo in (1, 2, 3, 5, 8):
            for kind in ("vq", "pca", "cpca"):
                K, J = {"vq": (6, 1), "pca": (1, 4), "cpca": (5, 4)}[kind]
                T = torch.randn(K, J, 8, generator=g)
                T[..., Fo:] = 0.0
                labels = None if K == 1 else torch.randint(0, K, (P,), generator=g).to(torch.uint8)
                W = None if J == 1 else torch.randn(P, J - 1, generator=g)
                if kind == "pca":  # output 0 is -0.0 on the exact FMA chain: mean -0, terms w·(-0) = -0 (w >= 0)
                    T[0, :, 0] = -0.0
                    W = W.abs()
                codes = (labels, W, J - 1, None, None, J - 1, True)
                lab = torch.zeros(P, dtype=torch.long) if labels is None else labels.long()
                Td = T.double()[lab]  # [P, J, 8]
                ref = Td[:, 0, :Fo] + (0 if W is None else (W.double()[:, :, None] * Td[:, 1:, :Fo]).sum(1))
                outs = _rows_every_split(lib, T, J, Fo, codes, P, g, (P, Fo, kind))
                assert all(torch.equal(o.view(torch.int32), outs[0].view(torch.int32)) for o in outs[1:]), (P, Fo, kind)
                assert torch.allclose(outs[0].double(), ref, atol=1e-5), (P, Fo, kind)
                if kind == "pca":
                    assert bool(torch.signbit(outs[0][:, 0]).all()), (P, Fo)


def test_rows_of_one_vector_by_term_count_and_label_kind():
    """The one-vector rows pass specialises points in order by term count (1-8), label kind and
    row stride of the weights (loaded 8 at a time where the stride allows): every combination
    gives the bits of the generic one-point chain (the same points visited in a random order take
    it), for 1-3 threads, with weights rows wider than the terms used, and agrees with float64.
    AVX2 builds without AVX-512 run uint8 labels of RGB rows with weights rows of exactly the terms
    8 points per label load with 16-byte stores (P = 67: several blocks, then the one-point loop and
    the tail, at every thread split)."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    g = torch.Generator().manual_seed(13)
    for nuse in (1, 2, 4, 5, 8, 9):
        for extra in (0, 3):
            ws = nuse + extra
            for lab_dtype in (None, torch.uint8, torch.int16, torch.int32):
                for P, Fo in ((5, 3), (37, 3), (67, 3), (37, 1), (37, 8)):
                    K, J = (1 if lab_dtype is None else 7), nuse + 1
                    T = torch.randn(K, J, 8, generator=g)
                    T[..., Fo:] = 0.0
                    labels = None if lab_dtype is None else torch.randint(0, K, (P,), generator=g).to(lab_dtype)
                    W = torch.randn(P, ws, generator=g)
                    codes = (labels, W, ws, None, None, nuse, True)
                    lab = torch.zeros(P, dtype=torch.long) if labels is None else labels.long()
                    Td = T.double()[lab]
                    ref = Td[:, 0, :Fo] + (W.double()[:, :nuse, None] * Td[:, 1:, :Fo]).sum(1)
                    case = (nuse, ws, lab_dtype, P, Fo)
                    outs = _rows_every_split(lib, T, J, Fo, codes, P, g, case)
                    assert all(torch.equal(o.view(torch.int32), outs[0].view(torch.int32)) for o in outs[1:]), case
                    assert torch.allclose(outs[0].double(), ref, atol=1e-5), case


@pytest.mark.parametrize("name", ["cpca_static", "cpca_adaptive"])
def test_cluster_sorted_visiting_changes_nothing(name, monkeypatch):
    """Where a cluster's constants are large, ``relight`` visits points cluster by cluster from a
    cached cluster-sorted copy of the codes (plain and packed); the results equal the point-order
    kernels' bit for bit (same per-point arithmetic) for every view mode, any thread count, and
    an in-place edit of the codes is seen (the copy is rebuilt)."""
    from prt_torch.codecs import affine

    if relight_kernels.native() is None:
        pytest.skip("no compiled kernels")
    params, (n_out, n_in) = ({"clusters": 6, "vectors": 4, "max_iter": 5}, (16, 9))
    if name == "cpca_adaptive":
        params, (n_out, n_in) = next(x for x in CASES if "packed" in x[0])[2:4]
    c, enc = _fit(name, params, (n_out, n_in), 300, None)
    assert enc.meta["packed"] == (name == "cpca_adaptive")
    L = torch.randn(n_in, 3)
    views = {"none": None, "dense": torch.randn(300, n_out), "taps": (torch.randint(0, n_out, (300, 4)), torch.rand(300, 4))}

    def run(view):
        return c.relight(enc, L, view=view)

    for threads in (1, 2):
        with torch_threads(threads):
            for mode, view in views.items():
                monkeypatch.setattr(affine, "SORT_MIN_CLUSTER_BYTES", 0)
                sorted_out = run(view)
                assert "cluster_order" in enc.cache, mode
                monkeypatch.setattr(affine, "SORT_MIN_CLUSTER_BYTES", 1 << 60)
                assert torch.equal(sorted_out, run(view)), (mode, threads)
    labels = enc.tensors["labels"]
    labels[:50] = (labels[:50].long() + 1).remainder(c.K_).to(labels.dtype)  # an in-place edit of the codes
    if name == "cpca_adaptive":
        return  # packed weights follow the labels' n_k: an edit of labels alone is not a valid encoding
    monkeypatch.setattr(affine, "SORT_MIN_CLUSTER_BYTES", 0)
    edited = run(views["dense"])
    monkeypatch.setattr(affine, "SORT_MIN_CLUSTER_BYTES", 1 << 60)
    assert torch.equal(edited, run(views["dense"]))


@pytest.mark.parametrize("mode", ["none", "dense", "taps", "vector"])
def test_relight_into_out(mode, path):
    """``relight(..., out=)`` writes the same values into the given tensor and returns it; a wrong
    shape, dtype, a non-contiguous tensor or one aliasing the view is refused, naming what is accepted."""
    ms = None if mode == "vector" else (9, 4)
    c = codecs.get("cpca_static", clusters=4, vectors=2, max_iter=5)
    X = transfer_like(120, 9, 4, seed=5)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(X, matrix_shape=ms)
    L = torch.randn(36 if ms is None else 4, 3)
    view = {"none": None, "vector": None, "dense": torch.randn(120, 9),
            "taps": (torch.randint(0, 9, (120, 4)), torch.rand(120, 4))}[mode]
    ref = c.relight(enc, L, view=view)
    out = torch.full_like(ref, float("nan"))
    got = c.relight(enc, L, view=view, out=out)
    assert got is out and torch.equal(out, ref)
    with pytest.raises(ValueError, match=r"out has shape .*accepted: a contiguous float32 tensor of shape"):
        c.relight(enc, L, view=view, out=torch.empty(ref.shape[0] + 1, *ref.shape[1:]))
    with pytest.raises(ValueError, match="accepted: a contiguous float32"):
        c.relight(enc, L, view=view, out=ref.double())
    with pytest.raises(ValueError, match="not contiguous"):
        c.relight(enc, L, view=view, out=torch.empty(ref.shape[::-1]).permute(*range(ref.ndim - 1, -1, -1)))  # reversed strides
    with pytest.raises(TypeError, match="out must be None or a float32 tensor"):
        c.relight(enc, L, view=view, out=[0.0])
    if mode == "dense":
        with pytest.raises(ValueError, match="out shares memory with an input"):
            c.relight(enc, L, view=view, out=view.view(-1)[:360].view(120, 3))  # the view's own memory


def test_relight_from_concurrent_threads():
    """Relighting calls from several Python threads at once (the kernels release the GIL; each
    thread has its own constants scratch buffer) give the results of serial calls."""
    import threading

    c, enc = _fit("cpca_static", {"clusters": 6, "vectors": 3, "max_iter": 5}, (9, 4), 250, None)
    lights = [torch.randn(4, 3, generator=torch.Generator().manual_seed(i)) for i in range(6)]
    views = [None, torch.randn(250, 9), (torch.randint(0, 9, (250, 4)), torch.rand(250, 4))]
    want = {(i, v): c.relight(enc, L, view=views[v]) for i, L in enumerate(lights) for v in range(3)}
    got, errors = {}, []

    def work(i):
        try:
            for _ in range(20):
                for v in range(3):
                    got[(i, v)] = c.relight(enc, lights[i], view=views[v])
        except Exception as e:  # pragma: no cover - reported below
            errors.append(e)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(len(lights))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and all(torch.equal(got[k], want[k]) for k in want)


def _light_and_views(P: int, n_out: int, n_in: int, ms):
    """A light [n_in, 3] and the view modes of a codec fitted on vectors (``ms`` None: rows only) or
    on matrices (rows, dense [P, n_out], 4 taps), and the generator that drew them."""
    g = torch.Generator().manual_seed(4)
    L = torch.randn(n_in, 3, generator=g)
    views = {"rows": None}
    if ms:
        views.update({"dense": torch.randn(P, n_out, generator=g),
                      "taps": (torch.randint(0, n_out, (P, 4), generator=g), torch.rand(P, 4, generator=g))})
    return L, views, g


@pytest.mark.parametrize("name,params,ms", [("vq", {"clusters": 5}, None), ("cpca_static", {"clusters": 4, "vectors": 3}, (9, 4)),
                                            ("pca", {"vectors": 3}, (9, 4))])
def test_relight_plans_follow_the_encoding_and_the_model(name, params, ms, monkeypatch):
    """``relight`` runs a per-encoding plan (``relight_kernels.plan``: the kernels' arguments
    built once, one ``prt_relight_plan`` call per light). Its results equal the two kernels called
    one by one (``constants``, then ``affine_rows`` / ``affine_dense`` / ``affine_taps``) bit for
    bit, for every view mode; an in-place edit of the codes or of the model, a replaced codes
    tensor and a refit are each seen by the next relight (the plan is rebuilt) — and by ``decode``
    and the torch path, whose per-encoding caches (tile plan, padded weights) once kept the codes
    they were built from — and a non-finite light is refused naming the value after a plan exists."""
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    P = 150
    c, enc = _fit(name, params, ms or (1, 16), P, None) if ms else (None, None)
    if ms is None:
        c = codecs.get(name, **params)
        enc = c.fit_encode(transfer_like(P, 1, 16, seed=3))
    n_out, n_in = ms or (1, 16)
    L, views, g = _light_and_views(P, n_out, n_in, ms)

    def by_kernels(kind, view):  # the two kernels one by one, points in order
        codes = c._native_codes(enc, c._n_eff(None))
        J = (1 if c.means_ is not None else 0) + codes[5]
        T = relight_kernels.constants(lib, c.means_, c.basis_, codes[5], n_out, n_in, L, kind, nk=codes[4])
        if kind == "rows":
            return relight_kernels.affine_rows(lib, T, J, n_out, 3, *codes, P=P).view(c.relight(enc, L).shape)
        if kind == "dense":
            return relight_kernels.affine_dense(lib, T, J, n_out, 3, *codes, view)[0]
        return relight_kernels.affine_taps(lib, T, J, n_out, 3, *codes, *view)[0]

    def check(what):
        for kind, view in views.items():
            got = c.relight(enc, L, view=view)
            assert torch.equal(got, by_kernels(kind, view)), (what, kind)
            assert any(isinstance(k, tuple) and k[:3] == ("kernel_plan", c._n_eff(None), kind) for k in enc.cache), (what, kind)
            ref, scale = _reference(c.decode(enc).view(P, n_out, n_in), L, view)
            _check(got.view(ref.shape), ref, scale, 3 * n_out, (what, kind, "decode"))
            monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
            _check(c.relight(enc, L, view=view).view(ref.shape), ref, scale, 3 * n_out, (what, kind, "torch path"))
            monkeypatch.delenv("PRT_TORCH_NATIVE")

    check("first")
    before = c.relight(enc, L)
    W = enc.tensors.get("coeffs")
    if W is not None:
        W.mul_(-0.5)  # the codes edited in place
        check("coeffs edited")
    with torch.no_grad():
        c.basis_.mul_(1.5)  # the model edited in place
        if c.means_ is not None:
            c.means_.add_(0.25)
    check("model edited")
    assert not torch.equal(c.relight(enc, L), before)
    if "labels" in enc.tensors:
        lab = enc.tensors["labels"]
        enc.tensors["labels"] = (lab.long() + 1).remainder(c.K_).to(lab.dtype)  # a replaced tensor
        check("labels replaced")
    X2 = transfer_like(P, n_out, n_in, seed=8, regions=6)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(X2.view(P, -1), matrix_shape=ms)  # a refit (a new encoding too)
    check("refit")
    bad = L.clone()
    bad[2, 1] = float("nan")
    with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*\(2, 1\)"):
        c.relight(enc, bad, view=views.get("dense"))


def test_caches_follow_a_refit_a_second_codec_and_fresh_copies_of_the_codes(monkeypatch):
    """Every per-encoding cache is keyed by the codec's model too (``affine._memo``): after a refit
    that changes CPCA adaptive's per-cluster term counts, the old encoding is refused by its
    packed-size check instead of read past its coefficients; a second codec object (here without a
    mean) relighting and decoding an encoding another one has cached gets its own results; and
    non-contiguous codes edited in place — whose contiguous copy is a fresh tensor every call — are
    seen by the cluster-sorted copy of the codes, and labels corrupted in place are range-checked
    again. (Found by a review with AddressSanitizer.)"""
    import copy

    from prt_torch.codecs import affine

    L = torch.randn(4, 3, generator=torch.Generator().manual_seed(3))
    params = {"clusters": 8, "vectors": 2, "budget": 2.0, "max_vectors": 5, "iterations": 2, "adapt_iters": 2, "max_iter": 5}
    c = codecs.get("cpca_adaptive", **params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(transfer_like(300, 9, 4, seed=1, regions=12, noise=0.05), matrix_shape=(9, 4))
        c.relight(enc, L)
        c.decode(enc)
        for seed in range(2, 40):  # a refit whose per-cluster counts no longer add up to the stored weights
            c.fit(transfer_like(300, 9, 4, seed=seed, regions=12, noise=0.3), matrix_shape=(9, 4))
            if int(c.n_vectors_[c.labels_of(enc).long()].sum()) != enc.tensors["coeffs"].numel():
                break
        else:  # pragma: no cover - the search is deterministic
            pytest.fail("no refit changed the per-cluster counts")
    if relight_kernels.native() is not None:
        with pytest.raises(ValueError, match=r"enc packed coeffs have shape"):
            c.relight(enc, L)
    with pytest.raises((ValueError, RuntimeError)):
        c.decode(enc)

    P, ms = 250, (9, 4)
    c, enc = _fit("cpca_static", {"clusters": 6, "vectors": 3, "max_iter": 5}, ms, P, None)
    c.relight(enc, L)
    c.decode(enc)
    c2 = copy.deepcopy(c)
    c2.means_ = None  # a second codec object: the same basis, no mean
    want = c2.decode(copy.copy(enc))  # a copy carries no cache
    assert torch.equal(c2.decode(enc), want)
    monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    ref, scale = _reference(want.view(P, *ms), L, None)
    _check(c2.relight(enc, L), ref, scale, 3 * 9, "second codec, torch path")
    monkeypatch.delenv("PRT_TORCH_NATIVE")
    _check(c2.relight(enc, L), ref, scale, 3 * 9, "second codec, kernels")
    if relight_kernels.native() is not None:  # labels corrupted in place after plans exist: checked again, refused
        enc.tensors["labels"][5] = c.K_ + 3
        with pytest.raises(ValueError, match=r"enc labels have shape \(250,\) and span \[0, 9\]"):
            c.relight(enc, L)

    monkeypatch.setattr(affine, "SORT_MIN_CLUSTER_BYTES", 0)  # visit cluster by cluster, from a sorted copy
    c, enc = _fit("cpca_static", {"clusters": 4, "vectors": 3, "max_iter": 5}, (24, 4), 230, None)
    W = enc.tensors["coeffs"]
    enc.tensors["coeffs"] = Wt = torch.empty(W.shape[1], W.shape[0]).t().copy_(W)  # non-contiguous codes
    for i in range(6):
        ref, scale = _reference(c.decode(enc).view(230, 24, 4), L, None)
        _check(c.relight(enc, L), ref, scale, 3 * 24, f"edit {i}")
        assert "cluster_order" in enc.cache or relight_kernels.native() is None
        Wt.mul_(2.0)  # an in-place edit


@pytest.mark.parametrize("name,params,ms", [("vq", {"clusters": 5}, None), ("cpca_static", {"clusters": 4, "vectors": 3}, (9, 4)),
                                            ("cpca_adaptive", {"clusters": 4, "vectors": 2, "budget": 2.0, "max_vectors": 4,
                                                               "iterations": 2, "adapt_iters": 2, "max_iter": 5}, (9, 4))])
def test_relighter_gives_relights_bits_and_sees_every_change(name, params, ms, path, monkeypatch):
    """``codec.relighter(enc, view)`` then ``r(light, out=)`` per light (a render loop's form, which
    skips relight's per-call checks while nothing changed): the same bits as ``relight``, with and
    without ``out``, for every view mode, kernels or torch path; a view updated in place, codes and
    model edited in place, a replaced codes tensor, a refit (an old encoding then refused, as relight
    refuses it), another ``out``, another light shape and a float64 view (converted, so relit through
    ``relight``) are each seen by the next call; bad lights, a NaN written into the view and an
    ``out`` that overlaps the light are refused naming them."""
    P = 150
    n_out, n_in = ms or (1, 16)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get(name, **params)
        enc = c.fit_encode(transfer_like(P, n_out, n_in, seed=3, regions=6).view(P, -1), matrix_shape=ms)
    L, views, g = _light_and_views(P, n_out, n_in, ms)
    rs = {k: c.relighter(enc, v) for k, v in views.items()}
    bufs = {k: torch.empty_like(c.relight(enc, L, view=v)) for k, v in views.items()}

    last: dict = {}

    def check(what, light=L, e=None):
        for k, v in views.items():
            # first as the previous call was made (so that it may take the fast path) and before relight,
            # which would rebuild caches the relighter reads
            prev = last.get(k)
            got = rs[k](light, out=prev if prev is not None and prev.shape[-1] == light.shape[1] else None).clone()
            want = c.relight(e or enc, light, view=v)
            assert torch.equal(got, want), (what, k)
            buf = bufs[k] if bufs[k].shape == want.shape else torch.empty_like(want)
            for _ in range(2):  # the first call checks in full, the second takes the fast path
                assert torch.equal(rs[k](light), want), (what, k)
                assert rs[k](light, out=buf) is buf and torch.equal(buf, want), (what, k)
            last[k] = buf

    check("first")
    check("another light", torch.randn(n_in, 3, generator=g))
    check("two colours", torch.randn(n_in, 2, generator=g))
    if ms:
        views["dense"].mul_(-2.0)  # the view updated in place: read at each call
        views["taps"][1].mul_(0.5)
        check("view edited")
    W = enc.tensors.get("coeffs")
    if W is not None:
        W.mul_(-0.5)
        check("codes edited")
    with torch.no_grad():
        c.basis_.mul_(1.5)
        if c.means_ is not None:
            c.means_.add_(0.25)
    check("model edited")
    if "labels" in enc.tensors:
        lab = enc.tensors["labels"]
        enc.tensors["labels"] = (lab.long() + 1).remainder(c.K_).to(lab.dtype)
        check("labels replaced")
    bufs = {k: b.clone() for k, b in bufs.items()}  # other out tensors
    check("another out")
    if ms:
        v64 = views["dense"].double()
        r64 = c.relighter(enc, v64)
        assert torch.equal(r64(L), c.relight(enc, L, view=v64))
        v64.mul_(3.0)  # a converted view is relit through relight, so its edits are seen too
        assert torch.equal(r64(L), c.relight(enc, L, view=v64))
    for k in views:
        bad = L.clone()
        bad[2, 1] = float("nan")
        rs[k](L)
        with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*\(2, 1\)"):
            rs[k](bad)
        rs[k](L, out=bufs[k])  # the fast path into out (no view: straight to the kernel call)
        with pytest.raises(ValueError, match=r"light has 1 non-finite value\(s\).*\(2, 1\)"):
            rs[k](bad, out=bufs[k])
        with pytest.raises(ValueError, match=r"light has shape \(3, 3\); accepted"):
            rs[k](torch.randn(3, 3))
        with pytest.raises(TypeError, match="light must be a torch.Tensor"):
            rs[k]([[1.0, 2.0, 3.0]])
        rs[k](L, out=bufs[k])
        if k == "rows" and not ms:  # a light inside out (vectors: out [P, 3], the light [16, 3] fits in it)
            with pytest.raises(ValueError, match="out shares memory with an input"):
                rs[k](bufs[k][:16], out=bufs[k])
    if ms:
        views["dense"][7, 2] = float("nan")
        with pytest.raises(ValueError, match=r"view.*non-finite.*\(7, 2\)"):
            rs["dense"](L, out=bufs["dense"])
        views["dense"][7, 2] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c.fit(transfer_like(P, n_out, n_in, seed=8, regions=6).view(P, -1), matrix_shape=ms)  # a refit
    for k, v in views.items():
        try:
            want = c.relight(enc, L, view=v)
        except ValueError as e:  # the old encoding refused (CPCA adaptive: another packed size): by both
            with pytest.raises(ValueError, match=re.escape(str(e)[:40])):
                rs[k](L)
        else:
            assert torch.equal(rs[k](L), want), k
    enc2 = c.encode(transfer_like(P, n_out, n_in, seed=9, regions=6).view(P, -1))
    rs = {k: c.relighter(enc2, v) for k, v in views.items()}
    check("refit, new encoding", e=enc2)


def test_relighter_after_changes_behind_its_back_refuses_and_converts_as_relight():
    """What a review found in the relighter's fast path, each now as relight does: a refit to another
    matrix shape with the same D (the kernels' buffer sizes checked again: once a write past a stack
    buffer), a view whose storage is swapped to the output's (refused as overlapping), taps given as a
    list, an encoding whose meta no longer matches the codec (refused), and a view turned float64
    through ``.data`` (converted, as relight converts it)."""
    g = torch.Generator().manual_seed(21)
    c = codecs.get("pca", vectors=2)
    X = torch.randn(64, 300, generator=g)
    enc = c.fit_encode(X, matrix_shape=(60, 5))
    r = c.relighter(enc)
    r(torch.randn(5, 15, generator=g))
    c.fit(X, matrix_shape=(300, 1))  # D and K unchanged: enc is still accepted, n_out 60 -> 300
    L = torch.randn(1, 15, generator=g)
    assert torch.equal(r(L), c.relight(enc, L))

    P = 40
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get("cpca_static", clusters=4, vectors=3)
        enc = c.fit_encode(transfer_like(P, 3, 4, seed=2, regions=4).view(P, -1), matrix_shape=(3, 4))
    L = torch.randn(4, 3, generator=g)
    y, buf = torch.randn(P, 3, generator=g), torch.empty(P, 3)
    r = c.relighter(enc, y)
    r(L, out=buf)
    r(L, out=buf)
    y.data = buf  # the view now is the output
    with pytest.raises(ValueError, match="out shares memory with an input"):
        c.relight(enc, L, view=y, out=buf)
    with pytest.raises(ValueError, match="out shares memory with an input"):
        r(L, out=buf)
    idx, w = torch.randint(0, 3, (P, 4), generator=g), torch.rand(P, 4, generator=g)
    assert torch.equal(c.relighter(enc, [idx, w])(L), c.relight(enc, L, view=[idx, w]))
    y2 = torch.randn(P, 3, generator=g)
    r = c.relighter(enc, y2)
    r(L)
    y2.data = y2.data.double()
    assert torch.equal(r(L), c.relight(enc, L, view=y2))
    r(L)
    enc.meta["clusters"] = 99
    with pytest.raises(ValueError, match="was not produced by this codec"):
        c.relight(enc, L, view=y2)
    with pytest.raises(ValueError, match="was not produced by this codec"):
        r(L)


@pytest.mark.parametrize("name, params, key, cut", [("pca", {"vectors": 4}, "coeffs", lambda t: t[:, :3]),
                                                    ("vq", {"clusters": 16}, "labels", lambda t: t[: t.numel() // 2]),
                                                    ("cpca_static", {"clusters": 8, "vectors": 4}, "labels", lambda t: t[:100])])
def test_codes_narrowed_through_data_are_refused_by_relight_and_the_relighter(name, params, key, cut):
    """``t.data = t[:k]`` keeps the tensor's id, address and version: the per-encoding caches and
    the relighter's fast path, keyed on those alone, kept relighting the old codes (found by the
    review of the Gaussian relighter, helper-19). The key has the shape too now: both refuse the
    codes, naming them, as for codes of that shape given anew."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get(name, **params)
        enc = c.fit_encode(transfer_like(2000, 1, 16, seed=1))
    L = torch.randn(16, 3, generator=torch.Generator().manual_seed(2))
    r = c.relighter(enc)
    for _ in range(2):
        r(L), c.relight(enc, L)  # the caches made, the fast path armed
    t = enc.tensors[key]
    t.data = cut(t.data)
    for f in (lambda: c.relight(enc, L), lambda: r(L)):
        with pytest.raises(ValueError, match=f"enc {key} have shape"):
            f()


@pytest.mark.parametrize("name, params", [("vq", {"clusters": 8}), ("cpca_static", {"clusters": 4, "vectors": 3}),
                                          ("cpca_adaptive", {"clusters": 4, "vectors": 3})])
def test_models_and_encodings_made_under_inference_mode_relight(name, params):
    """Tensors made under ``torch.inference_mode`` track no version counter, which the per-encoding
    caches and the relighter's state key on (reading it raised): such an encoding relights, through
    ``relight`` and the relighter, in and out of inference mode, to the same values as one made
    normally (its caches are then rebuilt at each call instead of kept)."""
    X = transfer_like(600, 1, 16, seed=3)
    L = torch.randn(16, 3, generator=torch.Generator().manual_seed(1))
    c = codecs.get(name, max_iter=5, seed=0, **params)
    enc = c.fit(X).encode(X)
    want = c.relight(enc, L)
    with torch.inference_mode():
        c_i = codecs.get(name, max_iter=5, seed=0, **params)
        enc_i = c_i.fit(X).encode(X)
        r = c_i.relighter(enc_i)
        for got in (c_i.relight(enc_i, L), r(L), r(L)):
            assert torch.allclose(got, want, rtol=1e-5, atol=1e-5)
    assert torch.allclose(c_i.relight(enc_i, L), want, rtol=1e-5, atol=1e-5)


def test_tensors_off_the_cpu_are_refused_naming_them():
    """A light, a view or an out on another device (here 'meta': no memory at all) is refused by
    name before any kernel reads it — its address would be read as CPU memory (a meta light once
    crashed relight) — by relight and by the relighter's first and later calls."""
    P = 40
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get("cpca_static", clusters=4, vectors=3)
        enc = c.fit_encode(transfer_like(P, 3, 4, seed=2, regions=4).view(P, -1), matrix_shape=(3, 4))
    L, y, buf = torch.randn(4, 3), torch.randn(P, 3), torch.empty(P, 3)
    meta = lambda t: torch.empty(t.shape, dtype=t.dtype, device="meta")  # noqa: E731
    r = c.relighter(enc, y)
    r(L, out=buf)
    for call in (lambda: c.relight(enc, meta(L), view=y), lambda: r(meta(L), out=buf), lambda: r(meta(L))):
        with pytest.raises(ValueError, match="light is on device meta; accepted: a CPU tensor"):
            call()
    with pytest.raises(ValueError, match="view is on device meta"):
        c.relight(enc, L, view=meta(y))
    with pytest.raises(ValueError, match="view is on device meta"):
        c.relighter(enc, meta(y))
    with pytest.raises(ValueError, match="view taps is on device meta"):
        c.relight(enc, L, view=(meta(torch.zeros(P, 4, dtype=torch.long)), torch.rand(P, 4)))
    with pytest.raises(ValueError, match="out is on device meta"):
        c.relight(enc, L, view=y, out=meta(buf))
    with pytest.raises(ValueError, match="out is on device meta"):
        r(L, out=meta(buf))
