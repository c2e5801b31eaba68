"""The dense slot order (``WaveletRelighter(dense_order=...)``: ``'column'``, ``'weight'``, ``'level'``, or Haar columns
first in a given order): the slot map is a permutation of the same dense columns, each slot holds its column's stored
values (read here from the transfer itself), every order relights as the float64 gather of the same stored values
(``relight.wavelet_dense``; within the VNNI loop's stated bound where a call takes it) in each build this CPU runs,
``bytes_read`` and the held bytes do not change, and a bad value is refused in one line."""

from __future__ import annotations

import os

import pytest
import torch

from prt_torch import relight
from prt_torch.lighting.haar import haar_levels

from test_wavelet_isa import HAS_VNNI, _builds, _relight, _transfer, _within_vnni_bound

W = relight.WaveletRelighter
NATIVE = os.environ.get("PRT_TORCH_NATIVE", "1") != "0" and relight._wavelet_lib() is not None


def _tr(dtype=torch.int16):
    """The synthetic blocker-scene transfer (R = 8, P = 384) with its first 40 columns dense (K = 48)."""
    return _transfer(dtype, 1, res=8, K=48, dense=40)


def _orders(r):
    """Every kind of order: the names, and Haar columns (some sparse, some repeated-free, reversed)."""
    g = torch.Generator().manual_seed(5)
    return ["column", "weight", "level", torch.randperm(r.P, generator=g)[:60], torch.arange(r.P - 1, -1, -1)]


def test_slots_are_a_permutation_holding_each_columns_values():
    tr = _tr()
    base = W(tr, threads=1)
    assert base.Pd == 40
    idx, vals = base.reference_rows()
    for order in _orders(base):
        r = W(tr, threads=1, dense_order=order)
        assert r.Pd == base.Pd
        assert torch.equal(torch.sort(r.dcol).values, base.dcol)  # the same dense columns
        assert torch.equal((r.dslot >= 0), (base.dslot >= 0))
        assert torch.equal(r.dslot[r.dcol].long(), torch.arange(r.Pd))  # dcol is dslot's inverse
        assert torch.equal(torch.sort(r.dslot[r.dcol]).values.long(), torch.arange(r.Pd))
        # slot s holds column dcol[s]'s stored values, vertex by vertex (from the transfer's own rows)
        dense = r.dense[:, :, 0, :].permute(0, 2, 1).reshape(-1, r.Pd)[:r.V].double()  # [V, Pd]
        want = torch.zeros(r.V, r.Pd, dtype=torch.float64)
        hit = r.dslot[idx] >= 0
        rows = torch.arange(r.V)[:, None].expand_as(idx)
        want[rows[hit], r.dslot[idx][hit].long()] = vals[hit].double()
        assert torch.equal(dense, want), order if isinstance(order, str) else "columns"


def test_the_orders_are_the_ones_named():
    tr = _tr()
    base = W(tr, threads=1)
    w = W(tr, threads=1, dense_order="weight")
    assert bool((w.weights[w.dcol][:-1] >= w.weights[w.dcol][1:]).all())
    lev = haar_levels(base.res)
    lv = W(tr, threads=1, dense_order="level")
    assert bool((lev[lv.dcol][:-1] <= lev[lv.dcol][1:]).all())
    first = torch.tensor([300, 7, 3, 39, 100, 0])  # 300 and 100 are sparse: skipped
    c = W(tr, threads=1, dense_order=first)
    assert c.dcol[:4].tolist() == [7, 3, 39, 0]
    assert torch.equal(c.dcol[4:], base.dcol[~torch.isin(base.dcol, first)])  # the rest by column
    assert (base.dense_order, w.dense_order, c.dense_order) == ("column", "weight", "columns")


@pytest.mark.parametrize("order", ["abc", 3, [1.5, 2.0], [1, 1], [-1], [384], [[1, 2]]])
def test_bad_order_is_refused_in_one_line(order):
    with pytest.raises(ValueError, match=r"^dense_order=.*; accepted: one of \('column', 'weight', 'level'\) or a 1-D "
                                         r"tensor of distinct Haar columns in \[0, 384\)$"):
        W(_tr(), dense_order=order)


def test_bytes_read_and_held_bytes_do_not_change():
    tr = _tr()
    base = W(tr, threads=1)
    g = torch.Generator().manual_seed(2)
    lights = [torch.randperm(base.P, generator=g)[:n] for n in (5, 40, 200, base.P)]
    for order in _orders(base):
        r = W(tr, threads=1, dense_order=order)
        for li in lights:
            assert r.bytes_read(li) == base.bytes_read(li)
            assert r.touched(li) == base.touched(li)
        assert r.held_bytes() == base.held_bytes()


@pytest.mark.skipif(not NATIVE, reason="no compiled wavelet kernel")
@pytest.mark.parametrize("isa", _builds())
@pytest.mark.parametrize("dtype", [torch.float32, torch.int16])
def test_every_order_relights_the_float64_sum(isa, dtype):
    """Each build, each order, N = 40 (the light's own listing) and all terms (the marks' scan), one and two threads:
    float32 values within 1e-5 of the float64 sum; 16-bit values within the VNNI loop's stated bound where the call
    takes it (native and avx512 builds on a VNNI CPU, RGB light), else within 1e-5."""
    lib = relight._wavelet_lib(isa)
    tr = _tr(dtype)
    base = W(tr, threads=1)
    idx, vals = base.reference_rows()
    g = torch.Generator().manual_seed(9)
    vnni_build = HAS_VNNI and isa in ("native", "avx512")
    for order in _orders(base):
        r = W(tr, threads=1, dense_order=order, layouts="both")  # the row-major copy held (the kernel's pass for N = all)
        for N in (40, r.P):
            li = torch.randperm(r.P, generator=g)[:N]
            lv = torch.rand(3, N, generator=g)
            ref = relight.wavelet_dense(vals.double(), idx, li, lv.double(), r.P)
            vnni = vnni_build and r._takes_vnni(li, lv, vnni=True)
            for th in (1, 2):
                got = _relight(r, lib, li, lv, th).double()
                if vnni:
                    assert _within_vnni_bound(r, got, ref, li, lv), (isa, order, N, th)
                else:
                    assert (got - ref).abs().max() <= 1e-5 * float(ref.abs().max()) + 1e-6, (isa, order, N, th)


def test_torch_path_follows_the_slots():
    """The torch formulation (``_sums``: no compiler) reads the same slots: float64 sums equal the reference's."""
    tr = _tr(torch.float32)
    base = W(tr, threads=1)
    idx, vals = base.reference_rows()
    g = torch.Generator().manual_seed(4)
    li = torch.randperm(base.P, generator=g)[:100]
    lv = torch.randn(3, 100, generator=g)
    ref = relight.wavelet_dense(vals.double(), idx, li, lv.double(), base.P)
    for order in _orders(base):
        r = W(tr, threads=1, dense_order=order)
        assert torch.allclose(r._sums(li, lv.double(), torch.float64), ref, rtol=0, atol=1e-9)


def test_reorder_in_place_gives_the_built_layout():
    """``reorder_dense`` gives the tensors a relighter built with that order holds (after the kernel's layout exists:
    its column maxima and norms permuted too), in the same buffers, so a prepared call bound before it still relights
    as the float64 gather of the stored values."""
    tr = _tr()
    r = W(tr, threads=1, layouts="both")
    idx, vals = r.reference_rows()
    g = torch.Generator().manual_seed(6)
    li = torch.randperm(r.P, generator=g)[:120]
    lv = torch.rand(3, 120, generator=g)
    ref = relight.wavelet_dense(vals.double(), idx, li, lv.double(), r.P)
    run = r.prepared(li, lv, albedo=False)
    ptrs = [t.data_ptr() for t in (r.dense, r.dslot, r.dcol)]
    for order in [*_orders(r), "column"]:
        r.reorder_dense(order)
        want = W(tr, threads=1, dense_order=order)
        want._kernel()
        for k in ("dense", "dslot", "dcol", "_dtmax", "_dnorm"):
            a, b = getattr(r, k), getattr(want, k)
            assert (a is None) == (b is None), k
            if a is not None:
                assert torch.equal(a, b), k
        assert [t.data_ptr() for t in (r.dense, r.dslot, r.dcol)] == ptrs
        got = run().double()
        if r._native is not None and r._takes_vnni(li, lv):
            assert _within_vnni_bound(r, got, ref, li, lv), order if isinstance(order, str) else "columns"
        else:
            assert (got - ref).abs().max() <= 1e-5 * float(ref.abs().max()) + 1e-6
    with pytest.raises(ValueError, match=r"^dense_order='x'; accepted"):
        r.reorder_dense("x")
