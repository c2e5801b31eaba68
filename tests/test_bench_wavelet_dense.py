"""benchmarks/bench_wavelet_dense_order.py, bench_wavelet_dense_runs.py and bench_wavelet_dense_interleave.py (issue 39,
the dense slot order and the runs of adjacent lines): the placements they time are what their docstrings say — each a
permutation of the dense columns, a light's columns in runs of r with gaps of g (or aligned groups), the two lights'
common order by each column's better rank (checked against a plain Python sort) — and the interleaved kernel's text
substitutions still apply to today's kernels/wavelet.c for every unit count, so the prototype cannot rot silently."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def runs(bench_module):
    return bench_module("bench_wavelet_dense_runs")


def _positions(order: list[int], cols: list[int]) -> list[int]:
    where = {c: i for i, c in enumerate(order)}
    return sorted(where[c] for c in cols)


@pytest.mark.parametrize("r, g", [(2, 2), (4, 4), (4, 12), (8, 8), (3, 1)])
def test_runs_of_r_separated_by_g(runs, r, g):
    dcols = torch.arange(0, 400, 3)  # 134 dense columns, not contiguous Haar indices
    gen = torch.Generator().manual_seed(1)
    light = dcols[torch.randperm(dcols.numel(), generator=gen)[:23]]  # the light's dense columns, in its own order
    order, used = runs.runs_order(dcols, light, r, g)
    o = order.tolist()
    assert sorted(o) == dcols.tolist()  # a permutation of the dense columns
    pos = _positions(o, light.tolist())
    assert pos[0] == 0  # the first run starts the block
    k = -(-len(pos) // r)
    gap = int(used)
    assert 1 <= gap <= g
    for i, p in enumerate(pos):  # run i // r starts at (i // r) (r + gap)
        assert p == (i // r) * (r + gap) + i % r, (i, p)
    assert [o[p] for p in pos[:r]] == light[:r].tolist()  # each run keeps the light's order
    assert len(set(p // (r + gap) for p in pos)) == k


def test_scattered_runs_sit_in_aligned_groups(runs):
    dcols = torch.arange(64)
    light = torch.tensor([5, 9, 40, 41, 63, 2, 17])
    order, used = runs.runs_order(dcols, light, 4, None)
    assert used == "s" and sorted(order.tolist()) == list(range(64))
    pos = _positions(order.tolist(), light.tolist())
    groups = {p // 4 for p in pos}
    assert len(groups) == 2  # ceil(7 / 4) aligned groups of 4, filled front to back
    assert sum(1 for p in pos if p // 4 == min(groups)) == 4


def test_both_order_is_each_columns_better_rank(bench_module, monkeypatch):
    bo = bench_module("bench_wavelet_dense_order")
    P = 40
    gen = torch.Generator().manual_seed(2)
    ranks = {name: torch.randperm(P, generator=gen) for name in bo.LIGHT_NAMES}
    monkeypatch.setattr(bo, "ranking", lambda rl, light: ranks[light])

    class RL:
        pass

    rl = RL()
    rl.P = P
    got = bo.both_order(rl).tolist()
    best = {c: min(ranks[n].tolist().index(c) for n in bo.LIGHT_NAMES) for c in range(P)}
    assert got == sorted(range(P), key=lambda c: (best[c], c))


@pytest.mark.parametrize("u", [2, 4, 8, 16])
def test_interleaved_kernel_text_applies_to_todays_kernel(bench_module, u):
    bi = bench_module("bench_wavelet_dense_interleave")
    src = (ROOT / "prt_torch" / "kernels" / "wavelet.c").read_text()
    out = bi.interleaved_source(src, u)  # SystemExit naming the missing text if wavelet.c moved under it
    assert f"#define ILV_U {u}" in out and f"stride == {u} * BV" in out and out.count("ilv_records(nd, wk);") == 1


@pytest.mark.parametrize("script", ["bench_wavelet_dense_order", "bench_wavelet_dense_runs", "bench_wavelet_dense_interleave"])
def test_bad_regimes_is_one_line_before_any_build(bench_module, monkeypatch, script):
    import sys

    m = bench_module(script)

    def no_work(*a, **k):
        raise AssertionError("a kernel was built before the options were checked")

    monkeypatch.setattr(m, "kernel_build", no_work)
    monkeypatch.setattr(sys, "argv", [f"{script}.py", "--sizes", "small", "--regimes", "warm,hot"])
    with pytest.raises(SystemExit) as e:
        m.main()
    msg = str(e.value.code)
    assert msg == f"{script}.py: --regimes 'warm,hot'; accepted: warm and/or evicted, comma-separated"
