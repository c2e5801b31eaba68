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


@pytest.mark.filterwarnings("ignore:WaveletRelighter built for threads=1")  # called at two on purpose
@pytest.mark.parametrize("dtype", [torch.float32, torch.int16])
def test_one_tile_and_two_relight_the_float64_sum(dtype):
    """float32 values (the float loop): within 1e-5 of the float64 sum; 16-bit values on the default arithmetic (the
    VNNI loop where this build has it, RGB light, CT = 1): within the loop's stated bound
    (``bench_wavelet_madd_micro.vnni_bound``), else within 1e-5; one tile and two, at one and two threads, the same
    bits (each vertex's terms in the same order)."""
    from test_wavelet_isa import _within_vnni_bound

    tr = _transfer(dtype, 1)
    g = torch.Generator().manual_seed(11)
    rs = {th: relight.WaveletRelighter(tr, threads=th) for th in (1, 2)}
    assert (rs[1].NT, rs[1].TV, rs[2].NT, rs[2].TV) == (1, 2272, 2, 1152)
    vnni = dtype == torch.int16 and rs[1].kernel_path()["dense"] == "int16 vnni"
    for N in (40, rs[1].P):
        li = torch.randperm(rs[1].P, generator=g)[:N]
        lv = torch.rand(3, N, generator=g) if vnni else torch.randn(3, N, generator=g)
        idx, vals = rs[1].reference_rows()
        ref = relight.wavelet_dense(vals.double(), idx, li, lv.double(), rs[1].P)
        outs = []
        for built, r in rs.items():
            for th in (1, 2):
                r.threads = th
                got = r(li, lv, albedo=False).double()
                outs.append(got)
                if vnni:
                    assert _within_vnni_bound(r, got, ref, li, lv), (built, th, N)
                else:
                    assert (got - ref).abs().max() <= 1e-5 * float(ref.abs().max()) + 1e-6, (built, th, N)
        # each vertex's terms are added in the same order whatever the tiles: the same bits
        assert all(torch.equal(o, outs[0]) for o in outs[1:]), N

def test_two_threads_build_mains_tile():
    """A relighter built for two threads keeps the default tile before the rule (half the vertices rounded up to 32,
    at most 4096 — written out here by hand), so its layout and its two-thread calls are unchanged."""
    W = relight.WaveletRelighter
    for V in [*range(1, 300), 2251, 8191, 8192, 8193, 10585, 51335]:
        half = -(-V // 2)
        assert W._tile(V, None, 2) == min(4096, max(32, -(-half // 32) * 32)), V
    tr = _transfer(torch.int16, 1)
    a, b = W(tr, threads=2), W(tr, threads=1, tile=1152)
    assert (a.NT, a.TV) == (2, 1152)
    for k in ("tptr", "tbase", "bofs", "bvals", "dense", "dslot"):
        assert torch.equal(getattr(a, k), getattr(b, k)), k


def test_more_threads_than_built_for_warns_once():
    """A relighter whose default tile was built for one thread, called at two (its one tile on one thread), warns
    once — by ``__call__`` and by ``prepared`` —, naming the threads it was built for; built for two and called at
    one, or with an explicit tile, it does not."""
    import warnings

    tr = _transfer(torch.int16, 1)
    r = relight.WaveletRelighter(tr, threads=1)
    if r._kernel() is None:
        pytest.skip("no C kernel (no compiler or PRT_TORCH_NATIVE=0): the torch path has no tiles")
    li = torch.arange(40)
    lv = torch.rand(3, 40, generator=torch.Generator().manual_seed(2))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r(li, lv)  # at the threads it was built for: silent
    r.threads = 2
    with pytest.warns(RuntimeWarning, match=r"built for threads=1 \(1 tile of 2272 vertices\) called at 2 threads"):
        r(li, lv)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r(li, lv)  # once per relighter
        r.prepared(li, lv)()
        for built, tile, th in ((2, None, 1), (1, 1152, 2), (2, None, 2)):
            q = relight.WaveletRelighter(tr, threads=built, tile=tile)
            q.threads = th
            q(li, lv)
            q.prepared(li, lv)()
    q = relight.WaveletRelighter(tr, threads=1)
    q.threads = 2
    with pytest.warns(RuntimeWarning, match="called at 2 threads"):
        q.prepared(li, lv)  # the preparation checks (its __call__ warns first: once)


def test_estimate_bytes_plans_the_threads_tile(tmp_path):
    """``estimate_bytes(threads=)`` counts the tile a relighter built for those threads holds: its column-major part
    (the sparse blocks and each tile's column pointers) equals the relighter's, for one thread and for two (which
    differ by the second tile's pointers)."""
    tr = _transfer(torch.int16, 1)
    path = tmp_path / "t.prt"
    tr.save(path)
    col = {}
    for th in (1, 2):
        est = relight.WaveletRelighter.estimate_bytes(path, threads=th, layouts="column")
        col[th] = relight.WaveletRelighter(tr, threads=th, layouts="column").held_bytes()["column"]
        assert est["column"] == col[th], th
    assert col[2] - col[1] == 4 * (6 * 8 * 8 + 1) + 8  # one more tile: its int32 pointers tptr [P + 1], int64 tbase
