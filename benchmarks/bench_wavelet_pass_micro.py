"""Where the wavelet kernel's column-major sparse pass spends its time (issue 39): the pass alone, over
the real blocks of one light, in a small C loop compiled here (the loop of ``kernels/wavelet.c``'s
``sparse_tile`` for CT = 1, RGB, 16-bit values), with one thing changed per variant:

  - ``kernel form``: per (tile, term) range, per 8-vertex block one 8-value load, conversion and three
    32-byte read-modify-writes of the tile's scratch (the kernel's loop);
  - ``float values``: the values read from a float32 copy (no int16 -> float conversion);
  - ``flat``: one loop over all the light's blocks (no per-(tile, term) range set-up and exit), one light;
  - ``flat, sweep``: the same loop with the scratch addressed in a fixed sweep, not the blocks' offsets
    (consecutive terms no longer hit the same blocks);
  - ``3 RMW sweep``: three read-modify-writes per block on a sweep of the scratch, nothing else (the floor);
  - ``4-vertex blocks``: the 8-vertex blocks' halves that hold a value, each a 4-value load and conversion and
    three 16-byte read-modify-writes (at the 8-block's scratch, + 16 bytes for the second half);
  - grouped layouts (``bench_wavelet_groups.py``): ``h-pair 2`` and ``children 4`` — per grouped block G
    values, 3·G multiply-adds and one read-modify-write per channel.

Also counts, for studio and sky at N = 100 … all, the light's sparse blocks and bytes at 8, 4 and 2 vertices per
block (``width_counts``).

Studio light, transport-weighted, its sparse terms at N (default 1000); the kernel section's transfer
(occluder_over_plane small, R = 32, K = 256, 16 bits, tiles as the relighter's). Each variant: the best of
15 samples of 200 passes, this thread's CPU time. Counts blocks per variant; ns per (grouped) block and
µs per pass. Writes reports/benchmarks/wavelet_pass_micro.md.

    .venv/bin/python benchmarks/bench_wavelet_pass_micro.py [--terms 1000]     (about 20 s)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import ctypes  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT  # noqa: E402
from bench_wavelet_groups import group_keys  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

#: the C the micro-benchmarks of the wavelet kernel share (bench_wavelet_fused_micro, bench_wavelet_dense_micro):
#: includes, the 8-lane float and int16 vector types, unaligned load/store, a broadcast and the int16 widening
#: load as kernels/wavelet.c has them
C_PRELUDE = r"""
#include <stdint.h>
#include <string.h>
#ifdef __AVX2__
#include <immintrin.h>
#endif
#pragma GCC diagnostic ignored "-Wpsabi"
typedef float v8f __attribute__((vector_size(32)));
typedef int16_t v8s __attribute__((vector_size(16)));
static inline v8f ld8(const float *p) { v8f x; memcpy(&x, p, sizeof x); return x; }
static inline void st8(float *p, v8f x) { memcpy(p, &x, sizeof x); }
static inline v8f bc8(const float *p) { const float x = *p; return (v8f){x, x, x, x, x, x, x, x}; }
#ifdef __AVX2__
static inline v8f load8(const int16_t *p) { return _mm256_cvtepi32_ps(_mm256_cvtepi16_epi32(_mm_loadu_si128((const __m128i *)p))); }
#else
static inline v8f load8(const int16_t *p) { v8s x; memcpy(&x, p, sizeof x); return __builtin_convertvector(x, v8f); }
#endif
"""

SRC = C_PRELUDE + r"""/* rng [nr, 3]: tile, first block, end; lw [nr, G, 4]; bofs [NB] (128 bytes per scratch block); bv [NB, G, 8];
 * acc: one tile's scratch (TV/8 x 128 bytes), zeroed per tile; mode 0 int16 values, 1 float values bvf */
#define GROUPED(G)                                                                                          \
int pass_g##G(const int64_t *rng, int64_t nr, int64_t nt, const float *lw, const int32_t *bofs,              \
              const int16_t *bv, const float *bvf, int64_t mode, float *acc, int64_t nacc, int64_t reps) {  \
    for (int64_t r_ = 0; r_ < reps; r_++)                                                                   \
        for (int64_t t = 0; t < nt; t++) {                                                                  \
            memset(acc, 0, (size_t)nacc * sizeof(float));                                                   \
            for (int64_t r = 0; r < nr; r++) {                                                              \
                if (rng[3 * r] != t) continue;                                                              \
                v8f l[G][3];                                                                                \
                for (int g = 0; g < G; g++) for (int c = 0; c < 3; c++) l[g][c] = bc8(lw + (G * r + g) * 4 + c); \
                const int64_t e1 = rng[3 * r + 2];                                                          \
                for (int64_t e = rng[3 * r + 1]; e < e1; e++) {                                             \
                    float *a = (float *)((char *)acc + bofs[e]);                                            \
                    v8f w[G];                                                                               \
                    for (int g = 0; g < G; g++) w[g] = mode ? ld8(bvf + (G * e + g) * 8) : load8(bv + (G * e + g) * 8); \
                    for (int c = 0; c < 3; c++) {                                                           \
                        v8f s = w[0] * l[0][c];                                                             \
                        for (int g = 1; g < G; g++) s += w[g] * l[g][c];                                    \
                        st8(a + 8 * c, ld8(a + 8 * c) + s);                                                 \
                    }                                                                                       \
                }                                                                                           \
            }                                                                                               \
        }                                                                                                   \
    return 0;                                                                                               \
}
GROUPED(1)
GROUPED(2)
GROUPED(4)
/* 4-vertex blocks (issue 39 idea 1): per (tile, term) range, per 4-vertex block one 4-value load and conversion
 * and three 16-byte read-modify-writes of the same scratch (a 4-block at its 8-block's offset + 16 bytes for the
 * second half); bv4 [NB4, 4] int16, bofs4 [NB4] bytes; mode 1: the 4 values as a 64-bit load widened in one step */
int pass_w4(const int64_t *rng, int64_t nr, int64_t nt, const float *lw, const int32_t *bofs, const int16_t *bv,
            int64_t mode, float *acc, int64_t nacc, int64_t reps) {
    typedef float v4f __attribute__((vector_size(16)));
    for (int64_t r_ = 0; r_ < reps; r_++)
        for (int64_t t = 0; t < nt; t++) {
            memset(acc, 0, (size_t)nacc * sizeof(float));
            for (int64_t r = 0; r < nr; r++) {
                if (rng[3 * r] != t) continue;
                const float l0 = lw[4 * r], l1 = lw[4 * r + 1], l2 = lw[4 * r + 2];
                const v4f L0 = {l0, l0, l0, l0}, L1 = {l1, l1, l1, l1}, L2 = {l2, l2, l2, l2};
                const int64_t e1 = rng[3 * r + 2];
                for (int64_t e = rng[3 * r + 1]; e < e1; e++) {
                    float *a = (float *)((char *)acc + bofs[e]);
#ifdef __AVX2__
                    const v4f w = (v4f)_mm_cvtepi32_ps(_mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)(bv + 4 * e))));
#else
                    const v4f w = {bv[4 * e], bv[4 * e + 1], bv[4 * e + 2], bv[4 * e + 3]};
#endif
                    v4f x0, x1, x2;
                    memcpy(&x0, a, 16); memcpy(&x1, a + 8, 16); memcpy(&x2, a + 16, 16);
                    x0 += w * L0; x1 += w * L1; x2 += w * L2;
                    memcpy(a, &x0, 16); memcpy(a + 8, &x1, 16); memcpy(a + 16, &x2, 16);
                }
            }
        }
    (void)mode;
    return 0;
}
/* one loop over the flat list of the light's blocks (flat [nf], tile-major), one light; mode 0: the blocks'
 * offsets, 1: a sweep of the scratch (block k at k mod nblk), 2: the sweep with no value read (3 RMW only) */
int pass_flat(const int64_t *flat, const int64_t *ftile_end, int64_t nt, const int32_t *bofs, const int16_t *bv,
              int64_t mode, float *acc, int64_t nacc, int64_t reps) {
    const v8f l0 = bc8(&(float){0.5f}), l1 = bc8(&(float){0.25f}), l2 = bc8(&(float){0.125f});
    const int64_t nblk = nacc / 32;
    for (int64_t r_ = 0; r_ < reps; r_++) {
        int64_t k = 0;
        for (int64_t t = 0; t < nt; t++) {
            memset(acc, 0, (size_t)nacc * sizeof(float));
            int64_t sw = 0;
            for (; k < ftile_end[t]; k++) {
                const int64_t e = flat[k];
                float *a = mode ? acc + 32 * sw : (float *)((char *)acc + bofs[e]);
                sw = sw + 1 == nblk ? 0 : sw + 1;
                const v8f w = mode == 2 ? l2 : load8(bv + 8 * e);
                st8(a, ld8(a) + w * l0); st8(a + 8, ld8(a + 8) + w * l1); st8(a + 16, ld8(a + 16) + w * l2);
            }
        }
    }
    return 0;
}
"""


def member_slots(key: torch.Tensor) -> torch.Tensor:
    """Each column's slot in its group (0 .. G-1, by column index within equal keys)."""
    P = key.numel()
    order = torch.argsort(key * (P + 1) + torch.arange(P))
    k = key[order]
    first = torch.ones(P, dtype=torch.bool)
    first[1:] = k[1:] != k[:-1]
    start = torch.cummax(torch.where(first, torch.arange(P), 0), 0).values
    slot = torch.empty(P, dtype=torch.int64)
    slot[order] = torch.arange(P) - start
    return slot


def grouped(rl, key: torch.Tensor, G: int, li: torch.Tensor, lv: torch.Tensor):
    """The light's (tile, group) ranges of a layout grouping the sparse columns by ``key`` ([P]; G columns a group,
    slot by column order): rng [nr, 3], light [nr, G, 4], bofs [NGB], values [NGB, G, 8] int16."""
    P, V, TV, NT = rl.P, rl.V, rl.TV, rl.NT
    sparse = rl.cls == 1
    k = torch.where(sparse, key, -1)
    uk, grp = torch.unique(k, return_inverse=True)
    NG = uk.numel()
    slot = member_slots(k)
    assert int(slot[sparse].max()) < G
    col_b = torch.repeat_interleave(torch.arange(P).repeat(NT), rl.bcount.reshape(-1).long())
    tile_b = torch.repeat_interleave(torch.arange(NT), rl.bcount.sum(1).long())
    nb8 = -(-V // 8)
    blk_b = tile_b * (TV // 8) + (rl.bofs.long() >> 7)
    gk = (tile_b * NG + grp[col_b]) * nb8 + blk_b
    ug, inv = torch.unique(gk, return_inverse=True)
    vals = torch.zeros(ug.numel(), G, 8, dtype=rl.bvals.dtype)
    vals[inv, slot[col_b]] = rl.bvals[:, 0]
    gblk, gtile, gg = ug % nb8, ug // nb8 // NG, (ug // nb8) % NG
    bofs = ((gblk - gtile * (TV // 8)) * 128).to(torch.int32)
    cnt = torch.bincount(gtile * NG + gg, minlength=NT * NG).reshape(NT, NG)
    start = (torch.cumsum(cnt.reshape(-1), 0) - cnt.reshape(-1)).reshape(NT, NG)
    held = sparse[li]
    gl = torch.zeros(NG, G, 4)
    gl[grp[li[held]], slot[li[held]], :3] += lv[:, held].T.float()
    gh = torch.unique(grp[li[held]])
    t = torch.arange(NT).repeat_interleave(gh.numel())
    g = gh.repeat(NT)
    rng = torch.stack([t, start[t, g], start[t, g] + cnt[t, g]], 1).contiguous()
    return rng, gl[g].contiguous(), bofs.contiguous(), vals.contiguous()


def width_counts(rl, lights=("studio", "sky (sun)"), terms=(100, 300, 1000, 2000, None)) -> list[str]:
    """Counts (no timing) for narrower sparse blocks: per light and N, the light's sparse coefficients, and its
    sparse blocks, their fill and their bytes (int32 offset + W stored values each) at W = 8 (the kernel's), 4 and
    2 vertices per block — a W-block kept where any of its vertices holds a value (the 8-blocks' halves, quarters)."""
    b = rl.bvals.element_size()
    col_b = torch.repeat_interleave(torch.arange(rl.P).repeat(rl.NT), rl.bcount.reshape(-1).long())
    nz = rl.bvals[:, 0] != 0  # [NB, 8] (CT = 1)
    L = ["| light | N | sparse coefficients | 8-vertex blocks (fill) | bytes | 4-vertex blocks (fill) | bytes | "
         "2-vertex blocks (fill) | bytes | 4 / 8: blocks, bytes |", "|---|---|---|---|---|---|---|---|---|---|"]
    for light in lights:
        for N in terms:
            li, _, _ = rl.light(LIGHTS[light], N or rl.P, "transport")
            held = torch.zeros(rl.P, dtype=torch.bool)
            held[li[rl.cls[li] == 1]] = True
            m = held[col_b]
            c = int(nz[m].sum())
            row = f"| {light} | {N or 'all'} | {c} |"
            nw = {}
            for W in (8, 4, 2):
                nw[W] = int(nz[m].reshape(-1, 8 // W, W).any(2).sum())
                row += f" {nw[W]} ({c / max(nw[W] * W, 1):.2f}) | {nw[W] * (4 + W * b)} |"
            L.append(row + f" {nw[4] / max(nw[8], 1):.2f}×, {nw[4] * (4 + 4 * b) / max(nw[8] * (4 + 8 * b), 1):.2f}× |")
    return L


def rank_counts(rl, lights=("studio", "sky (sun)"), terms=(300, 1000, 2000)) -> list[str]:
    """Counts (issue 39 idea 2, a static order): would a fixed order of the sparse columns put a light's held columns
    first? Per key (the column's transport weight, its kept count nnz, its Haar index), the columns sorted by it and
    the prefixes holding 25 / 50 / 75% of all sparse blocks: the share of the light's held sparse blocks inside
    each. Equal shares: the key does not concentrate a light's columns (a row-major pass over such a prefix plus a
    column-major pass over the rest would read as much as now)."""
    cb = rl._cblk.long()
    sparse = rl.cls == 1
    keys = {"weight": -rl.weights, "nnz": -rl.nnz.double(), "Haar index": torch.arange(rl.P, dtype=torch.float64)}
    L = ["| key | light | N | held in the 25% prefix | 50% | 75% |", "|---|---|---|---|---|---|"]
    for name, k in keys.items():
        order = torch.argsort(torch.where(sparse, k, torch.tensor(float("inf"), dtype=k.dtype)), stable=True)
        cum = torch.cumsum(cb[order], 0).double() / max(int(cb[sparse].sum()), 1)
        for light in lights:
            for N in terms:
                li, _, _ = rl.light(LIGHTS[light], N, "transport")
                held = torch.zeros(rl.P, dtype=torch.bool)
                held[li] = True
                hb = torch.where(held & sparse, cb, 0)[order].double()
                hc = torch.cumsum(hb, 0) / max(float(hb.sum()), 1.0)
                shares = [float(hc[int(torch.searchsorted(cum, torch.tensor(q, dtype=torch.float64)))]) for q in (.25, .5, .75)]
                L.append(f"| {name} | {light} | {N} | " + " | ".join(f"{x:.2f}" for x in shares) + " |")
    return L


def regroup_counts(rl, lights=("studio", "sky (sun)"), terms=(300, 1000, 2000)) -> list[str]:
    """Counts: the vertices of each 32-vertex block regrouped into its four 8-vertex blocks (greedy: a seed with the
    most sparse columns, then the 7 vertices adding the fewest new columns), which would need only a permutation
    inside each dense block's outputs: the light's sparse 8-vertex blocks against the mesh's own order."""
    V, P = rl.V, rl.P
    index = rl.index
    vals = rl.values if rl.values.ndim == 2 else rl.values[:, 0]
    keep = torch.zeros(V, P, dtype=torch.bool)
    rows = torch.arange(V)[:, None].expand_as(index)
    keep[rows[vals != 0], index[vals != 0]] = True
    keep &= (rl.cls == 1)[None]
    perm = []
    for b0 in range(0, V, 32):
        M = keep[b0:b0 + 32]
        left = list(range(M.shape[0]))
        while left:
            seed = max(left, key=lambda i: int(M[i].sum()))
            grp, u = [seed], M[seed].clone()
            left.remove(seed)
            while len(grp) < 8 and left:
                cand = torch.tensor(left)
                j = int(cand[int(torch.argmin((M[cand] & ~u[None]).sum(1)))])
                grp.append(j)
                left.remove(j)
                u |= M[j]
            perm += [b0 + i for i in grp]
    perm = torch.tensor(perm)

    def blocks(order, cols):
        Mc = keep[order][:, cols]
        Mc = torch.cat([Mc, torch.zeros((-Mc.shape[0]) % 8, Mc.shape[1], dtype=torch.bool)])
        return int(Mc.reshape(-1, 8, Mc.shape[1]).any(1).sum())

    L = ["| light | N | sparse blocks, mesh order | regrouped | regrouped / mesh order |", "|---|---|---|---|---|"]
    for light in lights:
        for N in terms:
            li, _, _ = rl.light(LIGHTS[light], N, "transport")
            cols = li[rl.cls[li] == 1]
            a, r = blocks(torch.arange(V), cols), blocks(perm, cols)
            L.append(f"| {light} | {N} | {a} | {r} | {r / max(a, 1):.3f} |")
    return L


def local_dense_counts(rl, lights=("studio", "sky (sun)"), terms=(300, 1000, 2000), dense_cyc=6.8, block_cyc=4.8,
                       ghz=3.2) -> list[str]:
    """Counts and a cost model: (32-vertex block, column) pairs whose column has k >= 2, 3 or 4 non-empty 8-vertex
    blocks there, stored as one 32-value entry of the block, read row-major (every such entry, the light looked up per
    column, zero where the light does not hold it: no read-modify-write) at about a dense step's cost
    (``dense_cyc`` + the look-up: ~7.5 cycles), against the column-major pass over the light's blocks of those pairs
    (``block_cyc`` cycles each; floors of ``bench_wavelet_floor_micro.py``)."""
    P, NT, TV = rl.P, rl.NT, rl.TV
    col_b = torch.repeat_interleave(torch.arange(P).repeat(NT), rl.bcount.reshape(-1).long())
    tile_b = torch.repeat_interleave(torch.arange(NT), rl.bcount.sum(1).long())
    blk32 = (tile_b * (TV // 8) + (rl.bofs.long() >> 7)) // 4
    uk, cnt = torch.unique(blk32 * P + col_b, return_counts=True)
    L = ["| light | N | k ≥ | pairs | of them held | their held 8-vertex blocks | column-major µs | row-major entries µs |",
         "|---|---|---|---|---|---|---|---|"]
    for light in lights:
        for N in terms:
            li, _, _ = rl.light(LIGHTS[light], N, "transport")
            held = torch.zeros(P, dtype=torch.bool)
            held[li] = True
            hp = held[uk % P]  # the pair's column (uk = 32-vertex block · P + column)
            for kmin in (2, 3, 4):
                sel = cnt >= kmin
                hb = int(cnt[sel & hp].sum())
                L.append(f"| {light} | {N} | {kmin} | {int(sel.sum())} | {int((sel & hp).sum())} | {hb} | "
                         f"{block_cyc * hb / ghz / 1e3:.1f} | {(dense_cyc + 0.7) * int(sel.sum()) / ghz / 1e3:.1f} |")
    return L


def best_us(fn, reps: int) -> float:
    fn(1)
    best = float("inf")
    for _ in range(15):
        t0 = time.thread_time()
        fn(reps)
        best = min(best, (time.thread_time() - t0) / reps)
    return best * 1e6


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--terms", type=int, default=1000)
    args = ap.parse_args()
    torch.set_num_threads(1)
    lib, how = compile_library("wavelet_pass_micro", SRC, ["-O3", "-march=native", "-ffp-contract=fast", "-shared", "-fPIC",
                                                           "-std=c99"], {})
    if lib is None:
        raise SystemExit(f"bench_wavelet_pass_micro: no compiler: {how}")
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    for name in ("pass_g1", "pass_g2", "pass_g4"):
        getattr(lib, name).argtypes = [vp, i64, i64, vp, vp, vp, vp, i64, vp, i64, i64]
    lib.pass_flat.argtypes = [vp, vp, i64, vp, vp, i64, vp, i64, i64]
    lib.pass_w4.argtypes = [vp, i64, i64, vp, vp, vp, i64, vp, i64, i64]
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="column")
    li, lv, _ = rl.light(LIGHTS["studio"], args.terms, "transport")
    acc = torch.zeros(rl.TV // 8 * 32)
    nacc = acc.numel()
    rows, sums = [], []
    load0 = os.getloadavg()[0]

    def run_grouped(label, G, key, mode=0):
        rng, gl, bofs, vals = grouped(rl, key, G, li, lv)
        valf = vals.float().contiguous()
        nblk = int((rng[:, 2] - rng[:, 1]).sum())
        fn = getattr(lib, f"pass_g{G}")
        def call(r):
            return fn(rng.data_ptr(), rng.shape[0], rl.NT, gl.data_ptr(), bofs.data_ptr(), vals.data_ptr(),
                      valf.data_ptr(), mode, acc.data_ptr(), nacc, r)
        us = best_us(call, 200)
        call(1)  # the last tile's sums: every grouped variant computes the kernel form's (compared below)
        sums.append(acc.clone())
        err = float((sums[-1] - sums[0]).abs().max()) / max(float(sums[0].abs().max()), 1e-30)
        assert err < 1e-5, (label, err)
        rows.append((label, G, rng.shape[0], int((rng[:, 2] == rng[:, 1]).sum()), nblk, us))
        print(f"[pass_micro] {rows[-1]}", flush=True)
        return rng

    single = torch.arange(rl.P)
    rng = run_grouped("kernel form", 1, single)
    run_grouped("float values", 1, single, mode=1)
    flat = torch.cat([torch.arange(int(a), int(b)) for _, a, b in rng.tolist()]) if rng.numel() else torch.zeros(0, dtype=torch.int64)
    tile_end = torch.cumsum(torch.bincount(rng[:, 0], weights=(rng[:, 2] - rng[:, 1]).double(), minlength=rl.NT), 0).long()
    for label, mode in (("flat", 0), ("flat, sweep", 1), ("3 RMW sweep", 2)):
        us = best_us(lambda r: lib.pass_flat(flat.data_ptr(), tile_end.data_ptr(), rl.NT, rl.bofs.data_ptr(),
                                             rl.bvals.data_ptr(), mode, acc.data_ptr(), nacc, r), 200)
        rows.append((label, 1, 0, 0, flat.numel(), us))
        print(f"[pass_micro] {rows[-1]}", flush=True)
    # 4-vertex blocks: each 8-vertex block's halves that hold a value, at the 8-block's scratch offset + 16 bytes per half
    half = (rl.bvals[:, 0].reshape(-1, 2, 4) != 0).any(2)  # [NB, 2]
    keep = half.reshape(-1)
    bofs4 = (rl.bofs.long()[:, None] + torch.tensor([0, 16])).reshape(-1)[keep].to(torch.int32).contiguous()
    bv4 = rl.bvals[:, 0].reshape(-1, 4)[keep].contiguous()
    c4 = torch.zeros(rl.NB + 1, dtype=torch.int64)
    c4[1:] = torch.cumsum(half.sum(1), 0)
    rng4 = torch.stack([rng[:, 0], c4[rng[:, 1]], c4[rng[:, 2]]], 1).contiguous()
    lw1 = grouped(rl, single, 1, li, lv)[1]
    us = best_us(lambda r: lib.pass_w4(rng4.data_ptr(), rng4.shape[0], rl.NT, lw1.data_ptr(), bofs4.data_ptr(),
                                       bv4.data_ptr(), 0, acc.data_ptr(), nacc, r), 200)
    lib.pass_w4(rng4.data_ptr(), rng4.shape[0], rl.NT, lw1.data_ptr(), bofs4.data_ptr(), bv4.data_ptr(), 0,
                acc.data_ptr(), nacc, 1)
    err = float((acc - sums[0]).abs().max()) / max(float(sums[0].abs().max()), 1e-30)
    assert err < 1e-5, ("4-vertex blocks", err)
    rows.append(("4-vertex blocks", 1, rng4.shape[0], int((rng4[:, 2] == rng4[:, 1]).sum()),
                 int((rng4[:, 2] - rng4[:, 1]).sum()), us))
    print(f"[pass_micro] {rows[-1]}", flush=True)
    # the grouped layouts' keys need the blocks of each column only for 'siblings 2' (not timed): any matrix
    keys = group_keys(rl.res, torch.zeros(1, rl.P, dtype=torch.bool))
    run_grouped("h-pair 2", 2, keys["h-pair 2"])
    run_grouped("children 4", 4, keys["children 4"])
    m = machine_info()
    base = rows[0][5]
    L = ["# Wavelet kernel: the column-major sparse pass alone (issue 39)\n",
         f"{m['cpu']}, one thread, `-O3 -march=native` (this benchmark's own 8-lane code; "
         f"this CPU: {m.get('cpu_isa')}); load average {load0:.1f} → {os.getloadavg()[0]:.1f} (shared machine; "
         "this thread's CPU time, best of 15 samples of 200 passes). Studio light, transport-weighted, "
         f"N = {args.terms}: its sparse terms' blocks in the blocker scene's layout (V = {rl.V}, R = 32, K = 256, "
         f"{BITS}-bit, tiles of {rl.TV}). The pass of `kernels/wavelet.c` (CT = 1, RGB) with one thing changed per "
         "row (module docstring). Reproduce: `.venv/bin/python benchmarks/bench_wavelet_pass_micro.py`.\n",
         "| variant | G | (tile, term) ranges | of them empty | blocks | µs per pass | ns per block | / kernel form |",
         "|---|---|---|---|---|---|---|---|"]
    for label, G, nr, ne, nb, us in rows:
        L.append(f"| {label} | {G} | {nr or '—'} | {ne if nr else '—'} | {nb} | {us:.1f} | {us * 1e3 / max(nb, 1):.2f} | "
                 f"{us / base:.2f} |")
    L += ["\n## Narrower sparse blocks: counts (issue 39 idea 1)\n",
          "The kernel's layout's sparse blocks re-cut at 4 and 2 vertices (a block kept where any of its vertices holds "
          f"a value); bytes: int32 offset + W {BITS}-bit values per block. The pass over 4-vertex blocks is timed "
          "above (`4-vertex blocks`: 128-bit read-modify-writes at the 8-block's scratch + 16 bytes for the second "
          "half).\n"] + width_counts(rl)
    L += ["\n## A static column order: counts (issue 39 idea 2)\n", rank_counts.__doc__.split("\n\n")[0].replace("\n   ", "") + "\n"]
    L += rank_counts(rl)
    L += ["\n## Vertices regrouped inside each 32-vertex block: counts\n",
          regroup_counts.__doc__.replace("\n   ", "") + "\n"] + regroup_counts(rl)
    L += ["\n## Columns dense inside a 32-vertex block: counts and a cost model\n",
          local_dense_counts.__doc__.replace("\n   ", "") + "\n"] + local_dense_counts(rl)
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_pass_micro.md", "\n".join(L) + "\n")
    print(f"[pass_micro] wrote {OUT / 'wavelet_pass_micro.md'}", flush=True)


if __name__ == "__main__":
    main()
