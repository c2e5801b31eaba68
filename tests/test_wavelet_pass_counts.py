"""benchmarks/bench_wavelet_pass_micro.py's layout counts (issue 39: narrower sparse blocks, columns dense
inside a 32-vertex block) checked against a brute-force count from the transfer itself: every (column, vertex)
the transfer keeps with a nonzero stored value in a sparse column, grouped by W consecutive vertices — not
from the relighter's blocks, which the benchmark re-cuts. At N = all the studio light holds only its nonzero Haar
terms (59 of 384 at R = 8), so the light's mask is checked too (it indexed pairs by their 32-vertex block instead
of their column, unseen while N = all held every column)."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

from prt_torch import relight
from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions
from prt_torch.transfer.wavelet import precompute_wavelet

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import bench_wavelet_pass_micro
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return bench_wavelet_pass_micro


@pytest.fixture(scope="module")
def rl():
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 8, 32, 16, shadows="always", run=RunOptions(workers=1))
    return relight.WaveletRelighter(tr, threads=1, layouts="column")


def _pairs(rl) -> tuple[torch.Tensor, torch.Tensor]:
    """(column, vertex) of every nonzero stored value in a sparse column, from the transfer's index and data."""
    index = rl.transfer.aux["index"].long()
    data = rl.transfer.data if rl.transfer.data.ndim == 2 else rl.transfer.data[:, 0]
    v, k = torch.nonzero(data != 0, as_tuple=True)
    col = index[v, k]
    keep = rl.cls[col] == 1
    return col[keep], v[keep]


def _held(rl, N: int) -> torch.Tensor:
    """``[P]`` bool: the studio light's N kept terms (at N = all its nonzero ones only: 59 of 384 at R = 8)."""
    li, _, _ = rl.light("studio", N, "transport")
    h = torch.zeros(rl.P, dtype=torch.bool)
    h[li] = True
    return h


def test_width_counts_against_brute_force(rl):
    col, v = _pairs(rl)
    h = _held(rl, rl.P)
    assert 0 < int(h.sum()) < rl.P and bool(h[col].any())
    col, v = col[h[col]], v[h[col]]  # the pairs of the light's columns
    rows = _bench().width_counts(rl, lights=("studio",), terms=(None,))  # N = all: the light's nonzero terms held
    cells = [c.strip() for c in rows[-1].strip("|").split("|")]
    assert int(cells[2]) == col.numel()  # sparse coefficients
    for W, at in ((8, 3), (4, 5), (2, 7)):
        n = torch.unique(col * (rl.V + 8) + v // W).numel()
        assert int(cells[at].split()[0]) == n, (W, cells[at], n)
        assert int(cells[at + 1]) == n * (4 + W * rl.bvals.element_size())
    assert int(rl.bcount[:, h & (rl.cls == 1)].sum()) == int(cells[3].split()[0])  # 8-vertex blocks: the relighter's own


def test_local_dense_counts_against_brute_force(rl):
    col, v = _pairs(rl)
    cnt8 = torch.unique(col * (rl.V + 8) + v // 8)  # the (column, 8-vertex block) pairs
    c, b8 = cnt8 // (rl.V + 8), cnt8 % (rl.V + 8)
    u, k = torch.unique(c * (rl.V + 8) + b8 // 4, return_counts=True)  # per (column, 32-vertex block): its 8-blocks
    h = _held(rl, rl.P)[u // (rl.V + 8)]  # the pair's column is one of the light's (N = all: its nonzero terms)
    assert 0 < int(h.sum()) < h.numel()
    rows = _bench().local_dense_counts(rl, lights=("studio",), terms=(rl.P,))
    for line in rows[2:]:
        cells = [x.strip() for x in line.strip("|").split("|")]
        kmin, pairs, held, blocks = int(cells[2]), int(cells[3]), int(cells[4]), int(cells[5])
        assert pairs == int((k >= kmin).sum())
        assert held == int(((k >= kmin) & h).sum())
        assert blocks == int(k[(k >= kmin) & h].sum())
