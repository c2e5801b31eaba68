"""``relight.apply_taps`` by blocks of vertices (``TAPS_BLOCK_BYTES``): the same result as the
explicit per-vertex tap sum (float64, loops in the test only), across block boundaries and for
ragged last blocks; differentiable when autograd records; and no per-call first-touch page
faults of a whole-signal temporary (a subprocess with glibc's mmap threshold fixed, so that every
large block is mapped anew on each allocation: the single gather faults ~V·k·N_i·4/4096 pages
per call there, the blocked one at most its ``TAPS_BLOCK_BYTES`` buffer's)."""
import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from prt_torch import relight


def _case(V=37, R=9, N=11, k=3, C=2, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(V, R, N, generator=g, dtype=dtype)
    L = torch.randn(C, N, generator=g, dtype=dtype)
    idx = torch.randint(0, R, (V, k), generator=g)
    w = torch.rand(V, k, generator=g, dtype=dtype)
    return A, L, idx, w


def _explicit(A, L, idx, w):
    out = torch.zeros(A.shape[0], L.shape[0], dtype=torch.float64)
    for p in range(A.shape[0]):
        for j in range(idx.shape[1]):
            out[p] += w[p, j].double() * (A[p, idx[p, j]].double() @ L.double().T)
    return out


@pytest.mark.parametrize("block_vertices", [1, 5, 36, 37, 1000])
def test_blocks_equal_the_explicit_tap_sum(monkeypatch, block_vertices):
    A, L, idx, w = _case()
    k, N = idx.shape[1], A.shape[2]
    monkeypatch.setattr(relight, "TAPS_BLOCK_BYTES", block_vertices * k * N * A.element_size())
    out = relight.apply_taps(A, L, idx, w)
    assert out.shape == (37, 2) and out.dtype == torch.float64
    torch.testing.assert_close(out, _explicit(A, L, idx, w), rtol=0, atol=1e-12)
    out1 = relight.apply_taps(A, L[0], idx, w)  # a light [N_i]: one channel
    torch.testing.assert_close(out1[:, 0], out[:, 0], rtol=0, atol=1e-12)


def test_float32_blocks_within_rounding_and_grad(monkeypatch):
    A, L, idx, w = _case(V=300, R=7, N=40, k=4, C=3, seed=1, dtype=torch.float32)
    monkeypatch.setattr(relight, "TAPS_BLOCK_BYTES", 4096)  # 6 vertices a block: 50 blocks
    ref = _explicit(A, L, idx, w)
    out = relight.apply_taps(A, L, idx, w)
    scale = _explicit(A.abs(), L.abs(), idx, w)
    assert out.dtype == torch.float32 and ((out.double() - ref).abs() <= 1e-6 * scale + 1e-30).all()
    Lg = L.double().requires_grad_(True)
    A64 = A.double()
    relight.apply_taps(A64, Lg, idx, w.double()).sum().backward()  # recorded: the single differentiable gather
    # d/dL_c of Σ_p Σ_j w_pj (A_p,idx_pj · L_c) = Σ_p Σ_j w_pj A_p,idx_pj, the same for every channel
    want = (w.double()[:, :, None] * A64[torch.arange(300)[:, None], idx]).sum((0, 1))
    torch.testing.assert_close(Lg.grad, want.expand(3, -1), rtol=1e-12, atol=1e-12)


_FAULTS = textwrap.dedent("""
    import json, resource, sys, torch
    torch.set_num_threads(1)
    from prt_torch import relight
    V, R, N, k = 4096, 8, 384, 3  # the gather: V*k*N*4 = 18.9 MB, 4.5 blocks
    g = torch.Generator().manual_seed(0)
    A, L = torch.rand(V, R, N, generator=g), torch.rand(3, N, generator=g)
    idx, w = torch.randint(0, R, (V, k), generator=g), torch.rand(V, k, generator=g)
    if sys.argv[1] == "whole":
        relight.TAPS_BLOCK_BYTES = 1 << 62
    relight.apply_taps(A, L, idx, w)
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(4):
        relight.apply_taps(A, L, idx, w)
    print(json.dumps((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 4))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's MALLOC_MMAP_THRESHOLD_ and Linux's fault counts")
def test_no_first_touch_faults_of_a_whole_gather_per_call():
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MALLOC_MMAP_THRESHOLD_": str(128 * 1024)}
    faults = {}
    for mode in ("whole", "blocked"):
        r = subprocess.run([sys.executable, "-c", _FAULTS, mode], capture_output=True, text=True, env=env, timeout=300)
        assert r.returncode == 0, r.stderr[-2000:]
        faults[mode] = json.loads(r.stdout.strip().splitlines()[-1])
    gather_pages = 4096 * 3 * 384 * 4 / 4096
    assert faults["whole"] >= 0.9 * gather_pages, faults  # the mechanism the blocks remove: it is there
    # at most the block buffer (4 MiB: 1024 pages) and the [V·k, C] products
    assert faults["blocked"] <= relight.TAPS_BLOCK_BYTES / 4096 + 0.1 * gather_pages, faults
