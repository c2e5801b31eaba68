"""The taps kernel's RGB passes (``prt_torch/kernels/affine_taps.c``; Lehtinen & Kautz 2003
eq. (13): o_p[c] = Σ_t g_pt Σ_j wv_pj T[k_p, idx_pt, c, j], wv_p = [1 if mean, w_p, 0 ..]).

Points in order run ``taps_seq_NBJ`` on AVX2 builds without AVX-512 (the term blocks NBJ = Jp / 8
as a constant; the per-point bookkeeping decided once per range), points in a visiting order the
general 8-point pass, the last points of a thread's range one at a time. Every configuration the
dispatch tells apart — NBJ 1-4, weights that are exactly the stored row (MRT-PCA with 8·NBJ
vectors) or not (a mean, fewer vectors, packed per-cluster counts), no labels or uint8 / int16 /
int32 labels, four valid tent taps or not (an index outside [0, n_out), 3 or 6 taps), point
counts around the 8-point blocks, 1-3 threads — is held to a float64 evaluation of the equation
from the same constants (to float32 rounding) and to the visiting-order pass bit for bit (the same
FMAs in the same order), with the same flags: 1 for a tap outside the rows (skipped), 2 for a
non-finite output.
"""
from __future__ import annotations

import pytest
import torch

from prt_torch import codecs, relight
from prt_torch.codecs import relight_kernels
from prt_torch.codecs.synthetic import tent_taps_random, transfer_like
from prt_torch.harness.timing import torch_threads

N_OUT = 9  # a 3 x 3 tent grid


def _lib():
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    return lib


def _codes(P: int, K: int, n: int, lab_dtype, packed: bool, g: torch.Generator):
    """labels (None for K = 1), weights and the kernel's code arguments; packed: per-cluster term
    counts 1..n (nk) with each point's weights one after the other (woff)."""
    labels = None if K == 1 else torch.randint(0, K, (P,), generator=g).to(lab_dtype)
    lab = torch.zeros(P, dtype=torch.long) if labels is None else labels.long()
    if packed:
        nk = torch.randint(1, n + 1, (K,), generator=g)
        nk[0] = n
        cnt = nk[lab]
        woff = torch.zeros(P, dtype=torch.long)
        if P > 1:
            woff[1:] = torch.cumsum(cnt, 0)[:-1]
        W = torch.randn(max(int(cnt.sum()), 1), generator=g)
        dense = torch.zeros(P, n)
        for p in range(P):  # the reference's view of the packed rows (small P)
            dense[p, :cnt[p]] = W[woff[p]:woff[p] + cnt[p]]
        return labels, lab, dense, (W, 0, woff, nk, n)
    W = torch.randn(P, n, generator=g)
    return labels, lab, W, (W, n, None, None, n)


def _reference(T, lab, dense_w, mean, idx, gw):
    """o_p[c] in float64 from the constants and codes (taps outside the rows contribute nothing),
    and the same sum of absolute values (the float32 rounding scale)."""
    K, n_out, C, Jp = T.shape
    P, n = dense_w.shape
    wv = torch.zeros(P, Jp, dtype=torch.float64)
    if mean:
        wv[:, 0] = 1.0
    wv[:, int(mean):int(mean) + n] = dense_w.double()
    ok = (idx >= 0) & (idx < n_out)
    rows = T.double()[lab[:, None], idx.clamp(0, n_out - 1)]  # [P, t, C, Jp]
    gg = torch.where(ok, gw.double(), torch.zeros((), dtype=torch.float64))
    ref = torch.einsum("pt,ptcj,pj->pc", gg, rows, wv)
    scale = torch.einsum("pt,ptcj,pj->pc", gg.abs(), rows.abs(), wv.abs())
    return ref, scale


# (mean, vectors): Jp = 8 NBJ for NBJ = 1..4; "exact" rows (no mean, 8 NBJ vectors) read the stored weights in place
_TERMS = [(0, 8), (1, 5), (0, 16), (0, 15), (1, 16), (0, 24), (0, 32), (1, 30)]


@pytest.mark.parametrize("mean,n", _TERMS)
def test_rgb_taps_passes_against_float64_and_each_other(mean, n):
    lib = _lib()
    g = torch.Generator().manual_seed(100 * n + mean)
    for K, lab_dtype, packed in ((1, None, False), (5, torch.uint8, False), (300, torch.int16, False), (3, torch.int32, True)):
        J = mean + n
        Jp = (J + 7) // 8 * 8
        P = 251
        labels, lab, dense_w, (W, ws, woff, nk, nuse) = _codes(P, K, n, lab_dtype, packed, g)
        T = torch.zeros(K, N_OUT, 3, Jp)
        T[..., :J] = torch.randn(K, N_OUT, 3, J, generator=g)
        views = {"tents": tent_taps_random(P, 3, seed=n),
                 "three": (torch.randint(0, N_OUT, (P, 3), generator=g), torch.rand(P, 3, generator=g)),
                 "six": (torch.randint(0, N_OUT, (P, 6), generator=g), torch.randn(P, 6, generator=g))}
        bad = tent_taps_random(P, 3, seed=n + 1)
        bad[0][5, 2] = N_OUT  # one tap past the rows, one before them: skipped and flagged
        bad[0][200, 0] = -1
        views["bad"] = bad
        for vname, (idx, gw) in views.items():
            ref, scale = _reference(T, lab, dense_w, mean, idx, gw)
            for Pc in (1, 7, 8, 9, 17, 251):
                ic, gc = idx[:Pc].contiguous(), gw[:Pc].contiguous()
                codes = [None if labels is None else labels[:Pc], W if packed else W[:Pc], ws, woff, nk, nuse, mean]
                if packed:
                    codes[3] = woff[:Pc]
                expect_flag = 1 if vname == "bad" and Pc > 5 else 0
                outs = []
                for threads in ((1, 2, 3) if Pc == 251 else (1, 2)):
                    with torch_threads(threads):
                        out, flag = relight_kernels.affine_taps(lib, T, J, N_OUT, 3, *codes, ic, gc)
                    assert flag == expect_flag, (K, vname, Pc, threads, flag)
                    outs.append(out)
                with torch_threads(1):
                    ordered, oflag = relight_kernels.affine_taps(lib, T, J, N_OUT, 3, *codes, ic, gc,
                                                                 order=torch.arange(Pc, dtype=torch.int32))
                label = (mean, n, K, vname, Pc)
                assert oflag == expect_flag, label
                for o in outs:
                    assert torch.equal(o, ordered), label  # the same FMAs in the same order: the same bits
                err = (outs[0].double() - ref[:Pc]).abs()
                assert (err <= 2e-6 * scale[:Pc] + 1e-30).all(), (label, float((err / scale[:Pc]).max()))


def test_non_finite_outputs_are_flagged_on_every_pass():
    """An output that overflows float32 is written (as ±inf) and flags 2, in the 8-point blocks and
    in the one-by-one tail alike."""
    lib = _lib()
    g = torch.Generator().manual_seed(7)
    P = 20
    T = torch.randn(1, N_OUT, 3, 16, generator=g)
    W = torch.randn(P, 16, generator=g)
    idx, gw = tent_taps_random(P, 3, seed=1)
    for p in (3, 18):  # in a block of 8 / in the tail
        gg = gw.clone()
        gg[p] = 3e38
        for order in (None, torch.arange(P, dtype=torch.int32)):
            out, flag = relight_kernels.affine_taps(lib, T, 16, N_OUT, 3, None, W, 16, None, None, 16, 0, idx, gg, order=order)
            assert flag == 2 and not torch.isfinite(out[p]).all() and torch.isfinite(out[torch.arange(P) != p]).all(), (p, order)


@pytest.mark.parametrize("vectors", [16, 15])
def test_mrt_pca_taps_match_the_uncompressed_reference(vectors):
    """MRT-PCA with 16 vectors (the stored weights are each point's whole term row) and 15 (formed
    in registers), 7x7 tents (Lehtinen & Kautz eq. (13)) at 1 and 2 threads: `relight` with taps
    against `relight.apply_taps` of the decoded matrices in float64, to float32 rounding."""
    _lib()
    P = 1003  # not a multiple of 8 per thread
    X = transfer_like(P, 49, 25, seed=5)
    c = codecs.get("mrt_pca", vectors=vectors)
    c.fit(X, matrix_shape=(49, 25))
    enc = c.encode(X)
    L = torch.randn(25, 3, generator=torch.Generator().manual_seed(3))
    idx, w = tent_taps_random(P, 7, seed=4)
    M = c.decode(enc).double().view(P, 49, 25)
    ref = relight.apply_taps(M, L.double().T, idx, w.double())
    scale = relight.apply_taps(M.abs(), L.double().abs().T, idx, w.double().abs())
    outs = []
    for threads in (1, 2):
        with torch_threads(threads):
            outs.append(c.relight(enc, L, view=(idx, w)))
    assert torch.equal(outs[0], outs[1])
    assert ((outs[0].double() - ref).abs() <= 2e-6 * scale).all()


def test_kernel_path_names_the_loop_within_the_path():
    """``kernel_path`` reports the loop the dispatch takes within a path, from the kernels' own test
    (``prt_taps_seq_path``, ``prt_fixed_rows_path`` via ``prt_plan_path``): on an AVX2 build without
    AVX-512, MRT-PCA 16 with 4 taps the one-cluster four-tap loop, with 3 taps the in-order one,
    CPCA of diffuse vectors with uint8 labels the 8-labels-per-load loop; an AVX-512 build none."""
    lib = _lib()
    from prt_torch.codecs.relight_kernels import kernel_path

    avx2_only = kernel_path()["isa"] == "avx2"
    X = transfer_like(300, 49, 25, seed=0)
    c = codecs.get("mrt_pca", vectors=16)
    enc = c.fit_encode(X, matrix_shape=(49, 25))
    four = c.kernel_path(enc, tent_taps_random(300, 7, seed=0))["path"]
    three = c.kernel_path(enc, (torch.zeros(300, 3, dtype=torch.long), torch.rand(300, 3)))["path"]
    Xd = transfer_like(300, 1, 16, seed=1).reshape(300, 16)
    cd = codecs.get("cpca_static", clusters=4, vectors=4)
    encd = cd.fit_encode(Xd)
    rows = cd.kernel_path(encd)["path"]
    assert four.startswith("taps: RGB, 8 points") and three.startswith("taps: RGB, 8 points"), (four, three)
    assert rows.startswith("rows/1 vector: fixed term count"), rows
    if avx2_only and lib.prt_isa() & 4:  # AVX2 with FMA, no AVX-512
        assert four.endswith("(points in order, one cluster, 4 taps)"), four
        assert three.endswith("(points in order, constant strides, weight rows in place)"), three
        assert rows.endswith("(uint8 labels, RGB: 8 labels per load, 16-byte stores)"), rows
    elif kernel_path()["isa"] == "avx512":
        assert "(" not in four.split("8 points")[1] or four.endswith("(8 lanes)"), four
        assert rows == "rows/1 vector: fixed term count (weights broadcast)", rows
