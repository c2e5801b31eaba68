"""benchmarks/bench_wavelet_groups.py's Haar bookkeeping checked against the transform itself: each
coefficient's node and support from ``lighting.haar.ihaar2d`` of a unit coefficient (the basis
function), and each grouping's members related as the benchmark's table says (siblings share one
support; pairs are neighbours in one band; a parent's four children tile its support)."""

from __future__ import annotations

import sys
from pathlib import Path

import torch

from prt_torch.lighting.haar import haar_levels, ihaar2d

ROOT = Path(__file__).resolve().parents[1]
R = 8


def _bench():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import bench_wavelet_groups
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    return bench_wavelet_groups


def _supports() -> torch.Tensor:
    """[6R², 6, R, R] bool: where each coefficient's basis function (the inverse transform of a unit
    coefficient, float64) is nonzero."""
    P = 6 * R * R
    e = torch.eye(P, dtype=torch.float64).reshape(P, 6, R, R)
    return ihaar2d(e).abs() > 1e-12


def test_positions_match_the_basis_functions():
    q = _bench().haar_positions(R)
    sup = _supports()
    lev = haar_levels(R)
    for c in range(6 * R * R):
        f, h, a, b = (int(q[k][c]) for k in ("f", "h", "a", "b"))
        s = sup[c]
        assert bool(s[f].any()) and not bool(s[torch.arange(6) != f].any())  # one face
        if h == 0:  # the scaling coefficient: the whole face
            assert bool(s[f].all()) and int(lev[c]) == 0
            continue
        w = R // h  # node (a, b) at half-width h covers a w x w block of texels
        blk = torch.zeros(R, R, dtype=torch.bool)
        blk[a * w:(a + 1) * w, b * w:(b + 1) * w] = True
        assert torch.equal(s[f], blk), c
        assert int(lev[c]) == h.bit_length()  # haar_levels: log2(h) + 1


def test_groupings_relate_their_members_as_stated():
    bench = _bench()
    q = bench.haar_positions(R)
    P = 6 * R * R
    sup = _supports()
    blk = torch.zeros(R, P, dtype=torch.bool)  # any 'block' matrix: only the siblings-2 choice reads it
    keys = bench.group_keys(R, blk)
    det = torch.nonzero(q["h"] > 0).flatten()

    def groups(name):
        k = keys[name][det]
        return [det[k == u] for u in torch.unique(k)]

    sib = groups("siblings 3")
    assert len(sib) == (P - 6) // 3 and all(g.numel() == 3 for g in sib)
    for g in sib:  # the three detail wavelets of one node: one support, three types
        assert all(torch.equal(sup[g[0]], sup[x]) for x in g[1:])
        assert sorted(int(q["typ"][x]) for x in g) == [0, 1, 2]
    for g in groups("siblings 2"):
        assert g.numel() in (1, 2) and len({int(q["typ"][x]) for x in g}) == g.numel()
        assert all(torch.equal(sup[g[0]], sup[x]) for x in g[1:])
    for g in groups("h-pair 2"):  # one band (face, level, type), one row, neighbouring columns
        assert g.numel() in (1, 2)
        for k in ("f", "h", "typ", "i"):
            assert len({int(q[k][x]) for x in g}) == 1
        if g.numel() == 2:
            assert abs(int(q["j"][g[0]]) - int(q["j"][g[1]])) == 1
    for g in groups("children 4"):  # the children of one parent in one band tile the parent's support
        h = int(q["h"][g[0]])
        if h == 1:
            assert g.numel() == 1
            continue
        assert g.numel() == 4 and len({int(q["typ"][x]) for x in g}) == 1
        union = sup[g].any(0)
        a, b = int(q["a"][g[0]]) // 2, int(q["b"][g[0]]) // 2
        parent = [c for c in det.tolist() if int(q["h"][c]) == h // 2 and int(q["a"][c]) == a and int(q["b"][c]) == b
                  and int(q["f"][c]) == int(q["f"][g[0]])]
        assert parent and torch.equal(union, sup[parent[0]])


def test_member_slots_number_each_group_in_column_order():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        from bench_wavelet_pass_micro import member_slots
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    g = torch.Generator().manual_seed(3)
    key = torch.randint(-1, 40, (500,), generator=g)
    slot = member_slots(key)
    seen: dict[int, int] = {}
    for c in range(key.numel()):  # brute force: the n-th column of a key (by index) gets slot n
        k = int(key[c])
        assert int(slot[c]) == seen.get(k, 0), c
        seen[k] = seen.get(k, 0) + 1
