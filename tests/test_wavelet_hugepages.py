"""The wavelet relighter's dense layout in memory advised for transparent huge pages (``io.hugepage_zeros``, issue 39:
a light's dense terms read scattered 64-byte lines, each a new 4 KB page past the L2). Checked against independent
measures: the kernel's address space (``/proc/self/maps``: the mapping exists while the tensor does and is gone once it
is dropped), zeros and alignment read back, the float64 dense sum over each vertex's kept coefficients
(``relight.wavelet_dense``), the same relighter on torch's buffer (``PRT_TORCH_HUGEPAGES=0``) bit for bit, the forced
fallback (mmap or madvise failing) and one clear line for a bad value of the switch."""
from __future__ import annotations

import gc
import mmap
import sys

import pytest
import torch

from prt_torch import io, relight
from prt_torch.relight import WaveletRelighter

from test_wavelet_isa import _transfer

HP = sys.platform.startswith("linux") and hasattr(mmap, "MADV_HUGEPAGE") and io._thp_mode() not in ("never",)
needs_hp = pytest.mark.skipif(not HP, reason="no transparent huge pages to advise here (not Linux, or THP never)")


def _mapping_of(ptr: int) -> tuple[int, int] | None:
    """The ``/proc/self/maps`` range holding address ``ptr``, or None."""
    with open("/proc/self/maps") as f:
        for line in f:
            a, b = (int(x, 16) for x in line.split()[0].split("-"))
            if a <= ptr < b:
                return a, b
    return None


@needs_hp
@pytest.mark.parametrize("dtype", [torch.int16, torch.float32, torch.int8])
def test_hugepage_zeros_is_zero_aligned_and_unmapped_when_dropped(dtype):
    row = 244 * 32 * torch.empty((), dtype=dtype).element_size()
    shape = (io.HUGE_PAGE_BYTES // row + 3, 244, 32)  # a little over 2 MiB: the last huge page partly filled
    t = io.hugepage_zeros(shape, dtype)
    nbytes = t.numel() * t.element_size()
    assert t.shape == shape and t.dtype == dtype and t.is_contiguous() and nbytes >= io.HUGE_PAGE_BYTES
    assert t.data_ptr() % io.HUGE_PAGE_BYTES == 0 and io.hugepage_backed(t) and io.hugepage_backed(t[3:])
    assert int(torch.count_nonzero(t)) == 0
    a, b = _mapping_of(t.data_ptr())
    assert b - t.data_ptr() >= -(-nbytes // io.HUGE_PAGE_BYTES) * io.HUGE_PAGE_BYTES  # whole huge pages from the start
    t.fill_(3)
    view = t[1:2]
    ptr = view.data_ptr()
    del t
    gc.collect()
    assert _mapping_of(ptr) is not None and int(view[0, 0, 0]) == 3  # a view keeps the mapping alive
    del view
    gc.collect()
    assert _mapping_of(ptr) != (a, b)  # unmapped with the last view
    assert not io._HUGE_MAPS or all(k != ptr for k in io._HUGE_MAPS)


def test_hugepage_zeros_falls_back_to_torch(monkeypatch):
    """Below 2 MiB, switched off, or mmap / madvise failing: a plain zero tensor of the same shape and dtype."""
    big = (1024, 1024)  # 4 MiB of float32
    small = io.hugepage_zeros((10, 3), torch.float32)
    off = io.hugepage_zeros(big, torch.float32, huge=False)
    assert not io.hugepage_backed(small) and not io.hugepage_backed(off)
    monkeypatch.setenv("PRT_TORCH_HUGEPAGES", "0")
    assert not io.hugepage_backed(io.hugepage_zeros(big, torch.float32))
    monkeypatch.delenv("PRT_TORCH_HUGEPAGES")

    def fails(*a, **k):
        raise OSError(12, "Cannot allocate memory")
    monkeypatch.setattr(mmap, "mmap", fails)
    t = io.hugepage_zeros(big, torch.float32)
    assert t.shape == big and t.dtype == torch.float32 and int(torch.count_nonzero(t)) == 0 and not io.hugepage_backed(t)
    monkeypatch.undo()
    if hasattr(mmap, "MADV_HUGEPAGE"):
        monkeypatch.delattr(mmap, "MADV_HUGEPAGE")
        t = io.hugepage_zeros(big, torch.int16)
        assert t.shape == big and int(torch.count_nonzero(t)) == 0 and not io.hugepage_backed(t)


@pytest.mark.parametrize("value", ["yes", "2", "on", "true"])
def test_bad_switch_is_one_line(value, monkeypatch):
    monkeypatch.setenv("PRT_TORCH_HUGEPAGES", value)
    with pytest.raises(ValueError, match=rf"^PRT_TORCH_HUGEPAGES='{value}'; accepted: 1 .* or 0 ") as e:
        io.hugepage_zeros((4, 4), torch.float32)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="PRT_TORCH_HUGEPAGES"):
        WaveletRelighter(_transfer(torch.int16, 1))


@pytest.mark.parametrize("dtype,CT", [(torch.int16, 3), (torch.float32, 1)])
def test_relighter_on_huge_pages_equals_torch_buffer_and_dense_reference(dtype, CT, monkeypatch):
    """A layout of >= 2 MiB (71 blocks of 32 vertices: 160 dense columns of int16 RGB, 2.2 MB; 200 of float32 grey,
    1.8 MB ... 250 boosted, all 200 kept: 2.3 MB) relit from huge pages equals the same relighter on torch's buffer bit
    for bit and the float64 sums of the same stored values (the transfer's albedo is folded in: none applied); the
    torch path (``PRT_TORCH_NATIVE=0``) reads the same layout."""
    tr = _transfer(dtype, CT, res=8, K=200, dense=160 if CT == 3 else 250)
    g = torch.Generator().manual_seed(11)
    monkeypatch.setenv("PRT_TORCH_HUGEPAGES", "0")
    plain = WaveletRelighter(tr, threads=1, layouts="both")
    monkeypatch.setenv("PRT_TORCH_HUGEPAGES", "1")
    huge = WaveletRelighter(tr, threads=1, layouts="both")
    nbytes = huge.dense.numel() * huge.dense.element_size()
    assert nbytes >= io.HUGE_PAGE_BYTES and huge.Pd >= 150
    assert io.hugepage_backed(huge.dense) == HP and not io.hugepage_backed(plain.dense)
    assert huge.held_bytes() == plain.held_bytes() and torch.equal(huge.dense, plain.dense)
    idx, vals = huge.reference_rows()
    dense = torch.nonzero(huge.dslot >= 0).flatten()
    for li in (dense[:10], torch.randperm(huge.P, generator=g)[:120], torch.arange(huge.P)):
        li = li.contiguous()
        lv = torch.randn(3, li.numel(), generator=g)
        a, b = huge(li, lv), plain(li, lv)
        assert torch.equal(a, b)
        ref = (relight.wavelet_dense(vals.double(), idx, li, lv.double(), huge.P) if CT == 1 else torch.cat(
            [relight.wavelet_dense(vals[:, c].double(), idx, li, lv[c:c + 1].double(), huge.P) for c in range(CT)], 1))
        assert float((a.double() - ref).abs().max()) <= 1e-5 * float(ref.abs().max()) + 1e-6
        monkeypatch.setenv("PRT_TORCH_NATIVE", "0")  # the torch path reads the same layout
        assert torch.allclose(huge(li, lv), a, rtol=1e-5, atol=1e-5 * float(a.abs().max()))
        monkeypatch.delenv("PRT_TORCH_NATIVE")
    if HP:  # dropped with the relighter (its prepared closures, the kernel's bound layout and all): unmapped
        run = huge.prepared(dense[:10].contiguous(), torch.randn(3, 10, generator=g))
        run()
        ptr, span = huge.dense.data_ptr(), _mapping_of(huge.dense.data_ptr())
        del huge, run
        gc.collect()
        assert _mapping_of(ptr) != span


@needs_hp
def test_arena_packs_small_arrays_into_one_huge_page_mapping():
    """Arrays carved from one mapping (``/proc/self/maps``), each zero, contiguous and 64-byte aligned; ``take`` copies
    the values; what no longer fits (and every array of an arena with huge pages off) is torch's own buffer."""
    arena = io.HugePageArena(100_000)
    assert arena.capacity == io.HUGE_PAGE_BYTES and arena.buf.data_ptr() % io.HUGE_PAGE_BYTES == 0
    a = arena.zeros((3, 5), torch.int16)
    src = torch.arange(1000, dtype=torch.float32).reshape(10, 100)
    b = arena.take(src)
    c = arena.zeros((7,), torch.uint8)
    span = _mapping_of(arena.buf.data_ptr())
    for t in (a, b, c):
        assert io.hugepage_backed(t) and _mapping_of(t.data_ptr()) == span and t.data_ptr() % 64 == 0 and t.is_contiguous()
    assert int(torch.count_nonzero(a)) == 0 and int(torch.count_nonzero(c)) == 0
    assert torch.equal(b, src) and b.data_ptr() != src.data_ptr()
    assert c.data_ptr() >= b.data_ptr() + b.numel() * 4 and b.data_ptr() >= a.data_ptr() + a.numel() * 2
    big = torch.ones(io.HUGE_PAGE_BYTES // 4, dtype=torch.float32)  # 2 MiB: no longer fits
    assert arena.take(big) is big and not io.hugepage_backed(arena.zeros((io.HUGE_PAGE_BYTES,), torch.uint8))
    off = io.HugePageArena(100, huge=False)
    assert off.buf is None and off.capacity == 0 and not io.hugepage_backed(off.zeros((4,), torch.float32))
    assert off.take(src) is src


def test_read_bound_on_a_huge_page():
    """``read_bound_fn(huge=True)``: the bytes and the output in one huge-page mapping (torch's buffers where there
    are none); the 4 KB default in torch's; both read the same number of bytes."""
    from prt_torch.harness.timing import read_bound_fn

    for huge in (False, True):
        fn = read_bound_fn(300_000, 27_012, huge=huge)
        cells = dict(zip(fn.__code__.co_freevars, (c.cell_contents for c in fn.__closure__)))
        src, out = cells["src"], cells["out"]
        assert src.numel() * 8 == 300_000 and out.numel() == 27_012
        assert io.hugepage_backed(src) == io.hugepage_backed(out) == (huge and HP)
        fn()
        assert int((out == 1).sum()) == out.numel()



def test_read_bound_pick_keeps_one_candidate_and_checks_its_argument():
    """``pick=k``: one of k reads of the same size is kept (the others freed); a bad ``pick`` is one line."""
    from prt_torch.harness.timing import read_bound_fn

    fn = read_bound_fn(100_000, 1000, pick=3)
    cells = dict(zip(fn.__code__.co_freevars, (c.cell_contents for c in fn.__closure__)))
    assert cells["src"].numel() * 8 == 100_000 and cells["out"].numel() == 1000
    fn()
    with pytest.raises(ValueError, match="pick") as e:
        read_bound_fn(100, 10, pick=0)
    assert "\n" not in str(e.value)
