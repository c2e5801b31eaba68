"""Grouped sparse blocks for the wavelet kernel's column-major pass (issue 39's last item): how often
do the Haar columns a grouped layout would put side by side occur together — in the transfer's kept
coefficients and in a light's N-term selection — and how many blocks and bytes would the pass read?

The column-major pass (``kernels/wavelet.c``, ``WaveletRelighter``) does, per 8-vertex block of one
sparse column, one read-modify-write of the tile's scratch per output channel; a grouped layout would
store G columns' values per 8-vertex block (zeros where a vertex keeps fewer, 4 + 8·G·CT·b bytes)
and do G × C multiply-adds with ONE read-modify-write per channel. A light holding a group reads all
of its grouped blocks (the columns it does not hold with a zero light). Groupings of the cube's
non-standard 2-D Haar coefficients (course notes "PRT with Haar Wavelets"; index f·R² + i·R + j, the
layout of ``lighting.haar.haar2d``; a node (f, h, a, b) has three detail siblings (a, h+b), (h+a, b),
(h+a, h+b)):

  - ``siblings 3``: a node's three detail siblings;
  - ``siblings 2``: per node the two siblings whose 8-vertex blocks overlap most in the transfer, the third alone;
  - ``h-pair 2`` / ``v-pair 2``: horizontal (j, j^1) / vertical (i, i^1) neighbours in one band (level 1: unpaired);
  - ``children 4``: the four children of one parent in one band (2 × 2 neighbours);
  - ``parent+children 5``: those four and their parent.

Per light and N (transport-weighted selection, the default): the light's sparse terms, the groups
they touch and terms per group, the blocks the pass reads ungrouped and grouped, and the bytes
(16-bit values, CT = 1: 20 B per ungrouped block). Counts only: the kernel variants were timed side by
side (docs/wavelet_kernel_log.md "Issue 39, grouped sparse blocks"). Transfer: the kernel section's
(occluder_over_plane small, R = 32, K = 256, 16 bits).

    .venv/bin/python benchmarks/bench_wavelet_groups.py     (about 20 s)

Writes reports/benchmarks/wavelet_groups.md.
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

TERMS = (100, 300, 1000, 2000)


def haar_positions(res: int) -> dict[str, torch.Tensor]:
    """Per cube Haar coefficient (flat [6R²], ``lighting.haar.haar2d``'s layout): face, row i, column j, the
    level's half-width h (0 for the scaling coefficient), the node (a, b) = (i mod h, j mod h) and the
    detail type (0: (a, h+b), 1: (h+a, b), 2: (h+a, h+b)); int64."""
    c = torch.arange(6 * res * res)
    f, i, j = c // (res * res), (c % (res * res)) // res, c % res
    m = torch.maximum(i, j)
    h = torch.where(m > 0, 2 ** torch.floor(torch.log2(m.clamp(min=1).double())).long(), torch.zeros_like(m))
    hc = h.clamp(min=1)
    return {"f": f, "i": i, "j": j, "h": h, "a": i % hc, "b": j % hc, "typ": (i >= h).long() * 2 + (j >= h).long() - 1}


def group_keys(res: int, blk: torch.Tensor) -> dict[str, torch.Tensor]:
    """Group key per column for each grouping (columns with equal keys share grouped blocks); ``blk [nb8, P]``
    bool: the 8-vertex blocks each sparse column has values in (the 'siblings 2' choice)."""
    q = haar_positions(res)
    f, h, a, b, t, i, j = q["f"], q["h"], q["a"], q["b"], q["typ"], q["i"], q["j"]
    R2 = res * res
    P = 6 * R2
    node = f * R2 + h * h + a * h.clamp(min=1) + b  # unique per (face, level, node) for h > 0
    keys = {"siblings 3": node}
    # siblings 2: per node the pair of types whose blocks overlap most (shared blocks), the third alone
    cols = torch.arange(P)
    bl = blk.T.float()  # [P, nb8]
    by_node = {}
    for c in cols[h > 0].tolist():
        by_node.setdefault(int(node[c]), [None, None, None])[int(t[c])] = c
    k2 = node * 4
    for n, (c0, c1, c2) in by_node.items():
        ov = [float(bl[x] @ bl[y]) for x, y in ((c0, c1), (c0, c2), (c1, c2))]
        best = max(range(3), key=lambda z: ov[z])
        alone = (c2, c1, c0)[best]
        k2[alone] = n * 4 + 3
    keys["siblings 2"] = k2
    # pairs within one band: a band of level h >= 2 starts at a multiple of h in i and j, so (j, j^1) / (i, i^1) stay in
    # it; level 1's bands are one coefficient wide (their neighbours are siblings of another type): unpaired
    one = h <= 1
    keys["h-pair 2"] = torch.where(one, P + torch.arange(P), f * R2 + i * res + (j >> 1))
    keys["v-pair 2"] = torch.where(one, P + torch.arange(P), f * R2 + (i >> 1) * res + j)
    ch = (f * R2 + h * h + (a // 2) * h.clamp(min=1) + b // 2) * 3 + t
    keys["children 4"] = ch
    # parent + children: a child joins its parent's group (the parent of (f, h, a, b, t) is (f, h/2, a/2, b/2, t))
    par = torch.where(h >= 2, (f * R2 + (h // 2) * (h // 2) + (a // 2) * (h // 2).clamp(min=1) + b // 2) * 3 + t, -1)
    own = (f * R2 + h * h + a * h.clamp(min=1) + b) * 3 + t
    keys["parent+children 5"] = torch.where(h >= 2, par, own)  # level-1 details: their own key (the parent of level 2)
    return keys


def main() -> None:
    torch.set_num_threads(1)
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="column")
    P, V, res = rl.P, rl.V, rl.res
    sparse = rl.cls == 1
    keep = torch.zeros(V, P, dtype=torch.bool)
    keep.scatter_(1, rl.index, True)
    keep &= sparse[None]
    nb8 = -(-V // 8)  # 8-vertex blocks never straddle a tile (tiles are multiples of 32): per-block counts = the layout's
    vv, cc = torch.nonzero(keep, as_tuple=True)
    blk = torch.zeros(nb8, P, dtype=torch.bool)
    blk[vv // 8, cc] = True
    assert int(blk.sum()) == rl.NB, (int(blk.sum()), rl.NB)
    keys = group_keys(res, blk)
    b = rl.bvals.element_size()
    L = ["# Grouped sparse blocks for the wavelet kernel: co-occurrence, blocks and bytes (issue 39)\n",
         f"Transfer: occluder_over_plane small (V = {V}), R = {res}, K = 256, {BITS}-bit, {rl.Pd} dense columns, "
         f"{int(sparse.sum())} sparse columns holding {rl.NB} 8-vertex blocks. Reproduce: "
         "`.venv/bin/python benchmarks/bench_wavelet_groups.py` (counts only; timings in "
         "docs/wavelet_kernel_log.md \"Issue 39, grouped sparse blocks\").\n"]
    # the transfer's co-occurrence: of the kept sparse coefficients, the share whose vertex keeps 1 / 2 / 3 of the node's siblings
    node = keys["siblings 3"]
    un, inv = torch.unique(node[cc], return_inverse=True)
    cnt = torch.zeros(V, un.numel(), dtype=torch.long).index_put_((vv, inv), torch.ones_like(vv), accumulate=True)
    tot = int(cnt.sum())
    share = [int((cnt == k).sum()) * k / tot for k in (1, 2, 3)]
    L.append(f"**The transfer**: of its {tot} kept sparse coefficients, {share[0]:.0%} belong to a vertex that keeps one "
             f"of the node's three detail siblings, {share[1]:.0%} two, {share[2]:.0%} all three.\n")
    L.append("**Blocks of the whole layout** (grouped / ungrouped; bytes with 4 + 8·G·2 per grouped block against 20):\n")
    L.append("| grouping | G | grouped blocks | / ungrouped | bytes / ungrouped |")
    L.append("|---|---|---|---|---|")
    gb_mats = {}
    for name, key in keys.items():
        G = int(name.split()[-1])
        k = torch.where(sparse, key, -1)
        uk, gi = torch.unique(k, return_inverse=True)
        m = torch.zeros(nb8, uk.numel(), dtype=torch.long).index_add_(1, gi, blk.long())  # [nb8, groups] member blocks
        gb_mats[name] = (gi, m > 0, uk)
        ng = int((m > 0).sum())
        L.append(f"| {name} | {G} | {ng} | {ng / rl.NB:.2f} | {ng * (4 + 8 * G * b) / (rl.NB * (4 + 8 * b)):.2f} |")
    L.append("\n**Per light** (transport-weighted selection): the light's sparse terms, then per grouping the groups it "
             "touches, its terms per group, and the blocks (and bytes) the grouped pass reads against the ungrouped "
             "pass's:\n")
    L.append("| light | N | sparse terms | ungrouped blocks | " + " | ".join(
        f"{n}: groups, terms/group, blocks (bytes) / ungrouped" for n in keys) + " |")
    L.append("|---|---|---|---|" + "---|" * len(keys))
    for lname, spec in LIGHTS.items():
        for N in TERMS + (P,):
            li, _, _ = rl.light(spec, N, "transport")
            held = torch.zeros(P, dtype=torch.bool)
            held[li] = True
            held &= sparse
            ub = int(blk[:, held].sum())
            cells = []
            for name, (gi, gm, uk) in gb_mats.items():
                G = int(name.split()[-1])
                hg = torch.zeros(uk.numel(), dtype=torch.bool)
                hg[gi[held]] = True
                gbk = int(gm[:, hg].sum())
                ng = int(hg.sum())
                cells.append(f"{ng}, {int(held.sum()) / max(ng, 1):.2f}, {gbk / max(ub, 1):.2f} "
                             f"({gbk * (4 + 8 * G * b) / max(ub * (4 + 8 * b), 1):.2f})")
            L.append(f"| {lname} | {N} | {int(held.sum())} | {ub} | " + " | ".join(cells) + " |")
            print(L[-1], flush=True)
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_groups.md", "\n".join(L) + "\n")
    print(f"[wavelet_groups] wrote {OUT / 'wavelet_groups.md'}", flush=True)


if __name__ == "__main__":
    main()
