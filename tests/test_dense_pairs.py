"""Dense views of 17-24 rows (three 8-row vectors per colour: CPCA 256×8 of 24×25 glossy transfer) pair two
consecutive visits of one cluster in one pass over its constants on every build: with AVX-512VL in one pass of 18
accumulators (``dense3v2_3``), with AVX2's 16 registers as vector groups 2 + 1 (issue 42 §4). Either way each point's
sums are ``dense3v``'s, so a point's bits must not depend on whether it was paired — i.e. on the visiting order, the
cluster sizes, the thread split or the call's point count — and must equal y_p · (M_p l) (Sloan 2003 §3.1, the exit
radiance of a dense view, with M_p the CPCA reconstruction of Sloan 2003 eq. (3)) from the decoded matrices in float64
to float32 rounding."""
from __future__ import annotations

import warnings

import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs import relight_kernels
from prt_torch.codecs.synthetic import transfer_like
from prt_torch.harness.timing import torch_threads

P = 251  # odd: thread ranges that are not multiples of 8, and a paired point at a range's end


def _lib():
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip(f"no compiled kernels: {relight_kernels.native_status()['detail']}")
    return lib


def _fit(name: str, params: dict, n_out: int, n_in: int = 5):
    X = transfer_like(P, n_out, n_in, seed=7, regions=10, noise=0.05 if name == "cpca_adaptive" else 0.0)
    c = codecs.get(name, **params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # short fits of tiny signals may not converge
        enc = c.fit_encode(X, matrix_shape=(n_out, n_in))
    return c, enc


def _uneven(c, enc):
    """The same codec with uneven clusters and an empty one: every point of cluster 0 moved to cluster 1, and two
    thirds of the rest to cluster 2 (labels only, weights kept: still a valid plain encoding, which decode follows)."""
    lab = enc.tensors["labels"]
    L = lab.long()
    L[L == 0] = 1
    L[torch.arange(P) % 3 != 0] = 2
    lab.copy_(L.to(lab.dtype))
    enc.cache.clear()


CODECS = [
    ("cpca_static", {"clusters": 5, "vectors": 3, "max_iter": 5}, None),
    ("cpca_static uneven, one empty", {"clusters": 5, "vectors": 3, "max_iter": 5}, _uneven),
    ("cpca_iterative", {"clusters": 4, "vectors": 4, "iterations": 2, "max_iter": 5}, None),
    ("cpca_adaptive", {"clusters": 6, "vectors": 2, "budget": 3.0, "max_vectors": 5, "iterations": 2, "adapt_iters": 2,
                       "max_iter": 5}, None),
    ("pca", {"vectors": 8}, None),  # one cluster: every consecutive visit pairs
    ("mrt_pca", {"vectors": 4}, None),  # no mean
]


@pytest.mark.parametrize("n_out", [17, 20, 23, 24])
@pytest.mark.parametrize("name,params,edit", CODECS, ids=[x[0] for x in CODECS])
def test_paired_dense_points_keep_their_bits(n_out, name, params, edit):
    lib = _lib()
    g = torch.Generator().manual_seed(n_out)
    c, enc = _fit(name.split()[0], params, n_out)
    if edit is not None:
        edit(c, enc)
    n = int(c.n_vectors_.max())
    codes = c._native_codes(enc, n)
    J = n + (1 if c.means_ is not None else 0)
    L = torch.randn(5, 3, generator=g)
    T = relight_kernels.constants(lib, c.means_, c.basis_, n, n_out, 5, L, "dense", nk=codes[4])
    ybuf = torch.full((P * n_out + 16,), float("nan"))  # NaN past the view: a read beyond its rows would show
    y = ybuf[:P * n_out].view(P, n_out)
    y.copy_(torch.randn(P, n_out, generator=g))
    labels = c.labels_of(enc) if c.K_ > 1 else torch.zeros(P, dtype=torch.long)

    def run(order=None, sub=None):
        cd, yy = codes, y
        if sub is not None:  # the first `sub` points alone
            cd = (None if codes[0] is None else codes[0][:sub], codes[1][:sub], codes[2],
                  None if codes[3] is None else codes[3][:sub], *codes[4:])
            yy = y[:sub]
        return relight_kernels.affine_dense(lib, T, J, n_out, 3, *cd, yy, order=order)[0]

    outs = []
    for threads in (1, 2, 3):
        with torch_threads(threads):
            outs.append(run())  # point order: pairs where neighbours share a cluster
            outs.append(run(torch.argsort(labels, stable=True).to(torch.int32)))  # cluster by cluster: nearly all paired
            outs.append(run(torch.randperm(P, generator=g).to(torch.int32)))
    base = outs[0].view(torch.int32)
    assert all(torch.equal(o.view(torch.int32), base) for o in outs[1:]), (name, n_out)
    if codes[3] is None:
        for sub in (1, 2, 9, 17):  # a point alone, a pair alone, ends of 8-point blocks
            assert torch.equal(run(sub=sub).view(torch.int32), base[:sub]), (name, n_out, sub)
    M = c.decode(enc).double().view(P, n_out, 5)
    ref = torch.einsum("po,poi,ic->pc", y.double(), M, L.double())
    scale = torch.einsum("po,poi,ic->pc", y.double().abs(), M.abs(), L.double().abs())
    assert bool(((outs[0].double() - ref).abs() <= 1e-5 * scale + 1e-6).all()), (name, n_out)


def test_a_cpca_relight_of_24_rows_is_the_same_at_one_and_two_threads_and_reports_its_path():
    """Through ``relight`` (cluster-sorted visiting, the plan, ``out=``) at the shape bench_relight measures, scaled
    down: 24 rows, 8 vectors, uneven clusters; 1 and 2 threads give the same bits, and the plan names the paired path
    (every build pairs 24-row RGB views of one cluster now) and, in AVX2 builds, its grouped loop."""
    _lib()
    c, enc = _fit("cpca_static", {"clusters": 6, "vectors": 8, "max_iter": 5}, 24, 25)
    _uneven(c, enc)
    light = torch.randn(25, 3, generator=torch.Generator().manual_seed(3))
    view = torch.randn(P, 24, generator=torch.Generator().manual_seed(4))
    got = []
    for threads in (1, 2):
        with torch_threads(threads):
            out = torch.empty(P, 3)
            for _ in range(3):  # the full call, then the armed fast path
                c.relight(enc, light, view=view, out=out)
            got.append(out.clone())
            kp = c.kernel_path(enc, view)
            assert kp["path"].startswith("dense: 8 lanes, RGB, two points per load"), (threads, kp)
            # the loop within the path: AVX2 builds without AVX-512 name the grouped pass (16 vector registers)
            assert ("vector groups 2 + 1" in kp["path"]) == (kp["isa"] == "avx2"), (threads, kp)
    assert torch.equal(got[0].view(torch.int32), got[1].view(torch.int32))
    M = c.decode(enc).double().view(P, 24, 25)
    ref = torch.einsum("po,poi,ic->pc", view.double(), M, light.double())
    scale = torch.einsum("po,poi,ic->pc", view.double().abs(), M.abs(), light.double().abs())
    assert bool(((got[0].double() - ref).abs() <= 1e-5 * scale + 1e-6).all())


@pytest.mark.parametrize("march", ["-mavx2"], ids=["avx2-without-fma"])
def test_paired_dense_points_keep_their_bits_in_other_builds(march, monkeypatch, tmp_path):
    """The same with the kernels built for 16 vector registers without FMA: each multiply-add rounded twice, so the
    groups' products and sums must be dense3v's one for one (the baseline ISA's build of the same loop is held to the
    float64 reference by test_relight_codecs' test_kernels_built_for_other_instruction_sets)."""
    import platform
    from pathlib import Path

    if march is not None:
        if platform.machine() not in ("x86_64", "AMD64"):
            pytest.skip("x86-64 only")
        try:
            if "avx2" not in Path("/proc/cpuinfo").read_text().split():
                pytest.skip("this CPU cannot run AVX2 code")
        except OSError:
            pass
    if relight_kernels.native() is None:
        pytest.skip("no compiled kernels")
    flags = [f for f in relight_kernels._FLAGS if f != "-march=native"] + ([march] if march else [])
    monkeypatch.setattr(relight_kernels, "_FLAGS", flags)
    monkeypatch.setattr(relight_kernels, "_state", {})
    monkeypatch.setenv("PRT_TORCH_CACHE", str(tmp_path))
    if relight_kernels.native() is None:
        pytest.fail(f"the kernels do not compile with {' '.join(flags)}: {relight_kernels.native_status()['detail']}")
    assert " ".join(flags) in relight_kernels.native_status()["detail"]
    for name, params, edit in (CODECS[1], CODECS[4]):
        test_paired_dense_points_keep_their_bits(24, name, params, edit)
