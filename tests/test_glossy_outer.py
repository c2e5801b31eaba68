"""The glossy / MRT transferred-radiance sums over each vertex's entries (issue 42 §2,
``glossy.outer_sums``; compiled pass ``kernels/glossy.c`` via ``ray_kernels.outer_accumulate``).

T_p = c Σ_e y(s_e) r_eᵀ (Sloan et al. 2002 §4–5: r_e = y(s_e) for the visibility sum, the hit
point's transfer for the bounce term) used to be a dense ``[k, N]`` weight matrix times the whole
set's outer products (and a ``[k, N, n²]`` hit buffer times Y). Checked here:

* against that dense formula written out independently (scatter into zeros, einsum), for the
  visibility and the hit-transfer forms, compiled and torch paths, within float64 rounding;
* the compiled pass gives every vertex the same bits whatever the chunk (rows split anywhere) and
  the thread count, and the 4-entry blocks the same bits as one entry at a time (entry counts 0–9);
* a chunk's T_p from ``transferred_radiance`` (shadowed, 'plain', no bounce) against a brute-force
  per-vertex sum over the directions a separate Embree query finds visible;
* bad input refused in one line (unsorted rows; out-of-range directions or pointers before the C);
* a one-bounce glossy / MRT precompute gives the same bits in chunks of 37 and of 100 vertices.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from prt_torch.scene import RayCaster, builtin
from prt_torch.sh import eval_sh
from prt_torch.transfer import ray_kernels
from prt_torch.transfer.glossy import _Directions, outer_sums, transferred_radiance

needs_lib = pytest.mark.skipif(ray_kernels._lib() is None, reason="no C compiler: the torch path runs")


def _entries(k: int, N: int, n: int, per: int, seed: int, with_r: bool):
    """Random entries grouped by row (some rows empty), SH-like Y [N, n] and R [E, n]."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, per + 1, (k,), generator=g)
    counts[::5] = 0  # empty vertices
    rows = torch.repeat_interleave(torch.arange(k), counts)
    dirs = torch.randint(0, N, (rows.numel(),), generator=g)
    Y = torch.randn(N, n, generator=g, dtype=torch.float64)
    R = torch.randn(rows.numel(), n, generator=g, dtype=torch.float64) if with_r else None
    return rows, dirs, Y, R


def _dense(k: int, rows, dirs, Y, c: float, R):
    """The former dense form: weights scattered into [k, N] (or rows into [k, N, n]) and multiplied by the
    whole set. Duplicated (row, direction) pairs are summed first (index_put_ with accumulate)."""
    N, n = Y.shape
    if R is None:
        W = torch.zeros(k, N, dtype=torch.float64).index_put_((rows, dirs), torch.full((rows.numel(),), c, dtype=torch.float64),
                                                               accumulate=True)
        return torch.einsum("kN,Na,Nb->kab", W, Y, Y)
    A = torch.zeros(k, N, n, dtype=torch.float64).index_put_((rows, dirs), R, accumulate=True)
    return torch.einsum("Na,kNb->kab", Y * c, A)


@pytest.mark.parametrize("native", [True, False])
@pytest.mark.parametrize("with_r", [False, True])
def test_outer_sums_equal_the_dense_form(native, with_r, monkeypatch):
    if native and ray_kernels._lib() is None:
        pytest.skip("no C compiler")
    if not native:
        monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    k, N, n = 37, 96, 25
    rows, dirs, Y, R = _entries(k, N, n, 40, 1 + with_r, with_r)
    c = 4 * np.pi / N
    S = outer_sums(k, rows, dirs, Y, c, R)
    ref = _dense(k, rows, dirs, Y, c, R)
    assert S.shape == (k, n, n) and S.dtype == torch.float64
    scale = ref.abs().amax(dim=(1, 2), keepdim=True).clamp_min(1e-300)
    assert float(((S - ref).abs() / scale).max()) < 1e-13
    empty = torch.bincount(rows, minlength=k) == 0
    assert bool((S[empty] == 0).all())


@needs_lib
@pytest.mark.parametrize("with_r", [False, True])
def test_compiled_sums_same_bits_for_any_chunk_and_threads(with_r):
    k, N, n = 41, 64, 16
    rows, dirs, Y, R = _entries(k, N, n, 9, 7 + with_r, with_r)  # 0..9 entries: every remainder of the 4-entry blocks
    c = 0.3
    full = outer_sums(k, rows, dirs, Y, c, R)
    for a, b in [(0, 1), (3, 20), (20, 41), (40, 41)]:  # rows split anywhere
        m = (rows >= a) & (rows < b)
        part = outer_sums(b - a, rows[m] - a, dirs[m], Y, c, None if R is None else R[m])
        assert torch.equal(part, full[a:b])
    ptr = np.zeros(k + 1, np.int64)
    ptr[1:] = np.cumsum(np.bincount(rows.numpy(), minlength=k))
    two = np.zeros((k, n, n))
    assert ray_kernels.outer_accumulate(two, ptr, dirs.numpy(), Y.numpy(), c, None if R is None else R.numpy(), threads=2)
    assert np.array_equal(two, full.numpy())
    one = np.zeros((k, n, n))  # one entry at a time, in order: the 4-entry blocks add in the same order
    for p in range(k):
        for e in range(ptr[p], ptr[p + 1]):
            y = Y[dirs[e]].numpy()
            r = y if R is None else R[e].numpy()
            one[p] = one[p] + (c * y)[:, None] * r[None, :]
    assert np.array_equal(one, full.numpy())


def test_transferred_radiance_equals_a_brute_force_visibility_sum():
    """'plain' without bounces: T_p = (4π/N) Σ_{s: n·s > 0, visible} y(s) y(s)ᵀ, the visible directions found by a
    separate Embree query per vertex (origins offset along the normal by the caster's epsilon)."""
    mesh = builtin("occluder_over_plane", "small")
    vids = torch.arange(0, mesh.num_vertices, max(1, mesh.num_vertices // 12))
    P, Nrm = mesh.vertices[vids].double(), mesh.normals[vids].double()
    dirs = _Directions(3, 128, 5)
    with RayCaster(mesh, workers=1) as caster:
        T, rays = transferred_radiance(caster, P, Nrm, dirs, estimator="plain")
        ref = torch.zeros(len(vids), 9, 9, dtype=torch.float64)
        shadowed = 0
        for r in range(len(vids)):  # per vertex, on purpose: the independent reference
            up = torch.nonzero(dirs.dirs @ Nrm[r] > 0).flatten()
            o = (caster.local(P[r]) + caster.eps * Nrm[r]).expand(up.numel(), 3).numpy().astype(np.float32)
            vis = ~torch.from_numpy(caster.trace(o, dirs.dirs32[up.numpy()], "occluded"))
            y = eval_sh(dirs.dirs[up[vis]], 3)
            ref[r] = dirs.weight * y.T @ y
            shadowed += int(not bool(vis.all()))
    assert rays == int((Nrm @ dirs.dirs.T > 0).sum())
    assert shadowed >= 2  # some of these vertices are shadowed: the visibility matters
    assert float((T - ref).abs().max()) < 1e-12 * float(ref.abs().max())


def test_bad_input_is_refused_in_one_line():
    Y = torch.randn(8, 4, dtype=torch.float64)
    with pytest.raises(ValueError, match="outer_sums: rows must be nondecreasing"):
        outer_sums(3, torch.tensor([1, 0]), torch.tensor([0, 1]), Y, 1.0)
    with pytest.raises(ValueError, match=r"rows must be nondecreasing in \[0, 3\)"):
        outer_sums(3, torch.tensor([0, 3]), torch.tensor([0, 1]), Y, 1.0)
    if ray_kernels._lib() is None:
        return
    T = np.zeros((2, 4, 4))
    with pytest.raises(ValueError, match=r"directions in \[0, 9\]; accepted: .*\[0, 8\)"):
        ray_kernels.outer_accumulate(T, np.array([0, 1, 2]), np.array([0, 9]), Y.numpy(), 1.0)
    with pytest.raises(ValueError, match="accepted: ptr 0 .. E nondecreasing"):
        ray_kernels.outer_accumulate(T, np.array([0, 2, 1]), np.array([0, 1]), Y.numpy(), 1.0)
    with pytest.raises(ValueError, match="accepted: contiguous float64"):
        ray_kernels.outer_accumulate(np.zeros((2, 4, 4), np.float32), np.array([0, 1, 2]), np.array([0, 1]), Y.numpy(), 1.0)


@pytest.mark.parametrize("kind", ["glossy", "mrt"])
def test_one_bounce_precompute_same_bits_for_any_chunk_size(kind):
    """Each vertex's T_p, its hits' transfer and its rotation do not depend on which chunk it falls in: a one-bounce
    glossy/MRT precompute in chunks of 37 and of 100 vertices writes the same float32 matrices."""
    from prt_torch.transfer import RunOptions
    from prt_torch.transfer.glossy import precompute_glossy
    from prt_torch.transfer.mrt import precompute_mrt

    f = precompute_glossy if kind == "glossy" else precompute_mrt
    mesh = builtin("cornell_box", "small", albedo=0.8)
    vids = torch.arange(0, mesh.num_vertices, 13)
    a = f(mesh, 3, samples=64, bounces=1, vertices=vids, run=RunOptions(chunk_size=37))
    b = f(mesh, 3, samples=64, bounces=1, vertices=vids, run=RunOptions(chunk_size=100))
    assert a.meta["hit_rays_traced"] == b.meta["hit_rays_traced"] > 0
    assert torch.equal(a.data, b.data)


def test_csr_rows_equal_scipy_row_slices():
    """``diffuse._csr_rows`` (the coplanar pools' rows without scipy.sparse) against scipy's own CSR row slicing:
    the same columns row after row, each row's start, empty rows and repeated rows included."""
    import scipy.sparse

    from prt_torch.transfer.diffuse import _csr_rows

    g = np.random.default_rng(3)
    dense = (g.random((40, 30)) < 0.2) & (g.random((40, 1)) < 0.8)  # some rows empty
    m = scipy.sparse.csr_matrix(dense.astype(np.int8))
    indptr, indices = m.indptr.astype(np.int64), m.indices.astype(np.int32)
    rows = np.array([5, 0, 5, 39, 17, 2], np.int64)
    cols, seg = _csr_rows(indptr, indices, rows)
    sub = m[rows]
    assert np.array_equal(cols, sub.indices) and np.array_equal(seg, sub.indptr[:-1])
    e, s = _csr_rows(indptr, indices, np.zeros(0, np.int64))
    assert e.size == 0 and s.size == 0


@needs_lib
@pytest.mark.parametrize("C", [1, 3])
def test_luma_mix_same_bits_as_the_torch_steps(C):
    """``ray_kernels.luma_mix`` (the glossy bounce's luminance mix of a coloured hit, one pass) against the torch
    steps it replaces in ``HitBounce.exit_transfer`` — mul, mul_, add_ in their order —: the same bits; x with one
    channel (one bounce: one transfer for the three albedos) or one per channel."""
    g = torch.Generator().manual_seed(C)
    H, n = 1000, 25
    x = torch.randn(H, C, n, generator=g, dtype=torch.float64)
    rho = torch.rand(H, 3, generator=g, dtype=torch.float64)
    w = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)
    xs = [x[:, min(c, C - 1)] for c in range(3)]
    ref = torch.mul(rho[:, 0:1], xs[0]).mul_(w[0])
    t = torch.mul(rho[:, 1:2], xs[1]).mul_(w[1])
    ref.add_(t).add_(torch.mul(rho[:, 2:3], xs[2], out=t).mul_(w[2]))
    out = np.empty((H, n))
    assert ray_kernels.luma_mix(out, rho.numpy(), x.numpy(), w.numpy())
    assert np.array_equal(out, ref.numpy())
    with pytest.raises(ValueError, match="luma_mix: .*accepted: contiguous float64"):
        ray_kernels.luma_mix(np.empty((H, n), np.float32), rho.numpy(), x.numpy(), w.numpy())
