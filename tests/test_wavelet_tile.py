"""The wavelet relighter's default tile (``WaveletRelighter._tile``): the vertices split between the threads the
relighter is built for (``threads``, or ``torch.get_num_threads()`` at construction), rounded up to whole 32-vertex
blocks, at most ``TILE_MAX`` (4096) — counted by hand here —; ``estimate_bytes`` plans the same tile; and a relighter
built for one thread (one tile at 2251 vertices) relights, at one and at two threads, as the float64 gather of the
same stored values (``relight.wavelet_dense``), as does one built for two (two tiles)."""

from __future__ import annotations

import pytest
import torch

from prt_torch import relight

from test_wavelet_isa import _transfer


@pytest.mark.parametrize(("V", "threads", "TV"), [
    (2251, 1, 2272), (2251, 2, 1152), (2251, 3, 768), (2251, 4, 576), (10585, 1, 4096), (10585, 2, 4096),
    (10585, 4, 2656), (51335, 1, 4096), (20, 1, 32), (20, 2, 32)])
def test_default_tile_follows_the_threads(V, threads, TV):
    W = relight.WaveletRelighter
    assert W._tile(V, None, threads) == TV
    assert W._tile(V, 96, threads) == 96  # an explicit tile wins
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        assert W._tile(V, None) == TV  # None: the torch threads now
    finally:
        torch.set_num_threads(old)


def test_one_tile_and_two_relight_the_float64_sum():
    tr = _transfer(torch.float32, 1)
    g = torch.Generator().manual_seed(11)
    rs = {th: relight.WaveletRelighter(tr, threads=th, arith="float") for th in (1, 2)}
    assert (rs[1].NT, rs[1].TV, rs[2].NT, rs[2].TV) == (1, 2272, 2, 1152)
    for N in (40, rs[1].P):
        li = torch.randperm(rs[1].P, generator=g)[:N]
        lv = torch.randn(3, N, generator=g)
        idx, vals = rs[1].reference_rows()
        ref = relight.wavelet_dense(vals.double(), idx, li, lv.double(), rs[1].P)
        for built, r in rs.items():
            for th in (1, 2):
                r.threads = th
                got = r(li, lv, albedo=False).double()
                assert (got - ref).abs().max() <= 1e-5 * float(ref.abs().max()) + 1e-6, (built, th, N)
