"""What holds the wavelet kernel's 16-lane dense loop (``W16`` in ``kernels/wavelet.c``, AVX-512) above its pipes' floor
(issue 39): the loop alone over the real blocks and terms of one light, compiled here (16-bit values, CT = 1, RGB:
CO = 3), with one thing changed per variant, and the loop's instruction mix alone in assembly.

Loop variants (sums stored per block, no output; each compared with the one-block form's sums, bit for bit):
  - ``1 block``: the loop of 69385e0 (per term: a slot load and shift, a prefetch PF = 6 terms ahead, 3 light
    broadcasts, 2 widening loads ``vpmovsxwd`` + 2 conversions ``vcvtdq2ps`` + 6 FMAs into 6 zmm sums);
  - ``2 blocks``: blocks 2i and 2i + 1 in lockstep, the slot, address and broadcasts shared (the kernel's form now);
  - ``3 blocks`` and ``4 blocks`` in lockstep (18 / 24 zmm sums);
  - ``2 blocks, no prefetch``; ``2 blocks, prefetch across pairs`` (the last PF terms of a pair prefetch the next
    pair's first PF slots);
  - ``1 block, byte offsets``: the slots as byte offsets, the list padded by PF (no shift, no test per prefetch);
  - ``1 block, L1`` / ``2 blocks, L1``: every block reading block 0's (and 1's) values (16-31 KB: L1);
  - ``1 block, one light``: the broadcasts hoisted out of the loop (wrong sums: a probe of their cost).

Assembly mixes (L1-resident values, a moving address, sums zeroed and light values finite first: no assists; the
best of 5 runs of 2e6 iterations; cycles per iteration at the clock measured by a chain of dependent multiplies, which
the zmm licence may lower during the FMA loops: their cycles are then over-counted — 12 zmm FMAs, 6 cycles at two per
cycle, read ~6.4):
12 independent zmm FMAs; the W16 term (3 broadcasts, 2 widening loads, 2 conversions, 6 FMAs into 6 sums); the same
for two blocks (12 sums); the term with float values (2 plain loads: no widening or conversion); the 8-lane AVX2 term
(4 ymm widening loads, 4 conversions, 12 ymm FMAs).

Studio and sky (transport-weighted) at N = 100, 300, 1000; the kernel section's transfer (occluder_over_plane small,
R = 32, K = 256, 16 bits). Each variant paired against ``1 block`` (``measure_paired(clock=time.thread_time)``, 9
repeats of 50 passes): cycles per (term, 32-vertex block) at the measured clock and **1 block / variant** (> 1:
faster). Writes reports/benchmarks/wavelet_dense16_micro.md (CPU, load named). Needs AVX-512F (exits otherwise).

    .venv/bin/python benchmarks/bench_wavelet_dense16_micro.py     (about a minute)
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
from bench_wavelet import LIGHTS, OUT  # noqa: E402
from bench_wavelet_dense_micro import blocker_dense, dense_terms  # noqa: E402

from prt_torch._native import compile_library, cpu_isa  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

SRC = r"""#define _POSIX_C_SOURCE 199309L
#include <stdint.h>
#include <string.h>
#include <time.h>
#include <immintrin.h>
typedef int64_t i64;
typedef float v16f __attribute__((vector_size(64)));
static inline v16f ld16(const int16_t *p) { return (v16f)_mm512_cvtepi32_ps(_mm512_cvtepi16_epi32(_mm256_loadu_si256((const __m256i *)p))); }
static inline v16f bc16(const float *p) { return (v16f)_mm512_set1_ps(*p); }
#define PF 6
/* K blocks bs int16 apart from blk in lockstep over the terms ds [nd] (slots; lw [nd, 4]), sums [K, 3, 32];
 * pf: 0 no prefetch, 1 PF ahead, 2 also the next group's first PF slots (nxt: its first block, or NULL) */
#define GROUP(K)                                                                                              \
static inline __attribute__((always_inline)) void grp##K(const int16_t *blk, i64 bs, const i64 *ds, i64 nd,    \
        const float *lw, int pf, const int16_t *nxt, float *sums) {                                           \
    v16f z[K][3][2];                                                                                          \
    for (int k = 0; k < K; k++) for (int c = 0; c < 3; c++) for (int h = 0; h < 2; h++) z[k][c][h] = (v16f){0}; \
    for (i64 t = 0; t < nd; t++) {                                                                            \
        const i64 o = ds[t] * 32;                                                                             \
        if (pf && t + PF < nd) for (int k = 0; k < K; k++) __builtin_prefetch(blk + k * bs + ds[t + PF] * 32); \
        else if (pf == 2 && nxt) for (int k = 0; k < K; k++) __builtin_prefetch(nxt + k * bs + ds[t + PF - nd] * 32); \
        v16f l[3];                                                                                            \
        for (int c = 0; c < 3; c++) l[c] = bc16(lw + 4 * t + c);                                              \
        for (int h = 0; h < 2; h++)                                                                           \
            for (int k = 0; k < K; k++) {                                                                     \
                const v16f x = ld16(blk + k * bs + o + 16 * h);                                               \
                for (int c = 0; c < 3; c++) z[k][c][h] += x * l[c];                                           \
            }                                                                                                 \
    }                                                                                                         \
    for (int k = 0; k < K; k++) for (int c = 0; c < 3; c++) for (int h = 0; h < 2; h++)                       \
        memcpy(sums + 96 * k + 32 * c + 16 * h, &z[k][c][h], 64);                                             \
}
GROUP(1)
GROUP(2)
GROUP(3)
GROUP(4)
/* mode: 0 one block, 1 two, 2 three, 3 four in lockstep, 4 two without prefetch, 5 two prefetching across pairs,
 * 6 one block with byte offsets (bo [nd + PF]), 7 one block, one light (broadcasts hoisted); l1: every group reads
 * the first group's blocks */
int dense16_pass(const int16_t *dense, i64 Pd, const i64 *ds, const i64 *bo, i64 nd, const float *lw, i64 nb,
                 i64 mode, i64 l1, float *sums, i64 reps) {
    const i64 bs = Pd * 32, K = mode == 1 || mode == 4 || mode == 5 ? 2 : mode == 2 ? 3 : mode == 3 ? 4 : 1;
    for (i64 r_ = 0; r_ < reps; r_++) {
        i64 b = 0;
        for (; b + K <= nb; b += K) {
            const int16_t *blk = dense + (l1 ? 0 : b * bs), *nxt = b + 2 * K <= nb && !l1 ? blk + K * bs : NULL;
            float *s = sums + 96 * b;
            if (mode == 0) grp1(blk, bs, ds, nd, lw, 1, NULL, s);
            else if (mode == 1) grp2(blk, bs, ds, nd, lw, 1, NULL, s);
            else if (mode == 2) grp3(blk, bs, ds, nd, lw, 1, NULL, s);
            else if (mode == 3) grp4(blk, bs, ds, nd, lw, 1, NULL, s);
            else if (mode == 4) grp2(blk, bs, ds, nd, lw, 0, NULL, s);
            else if (mode == 5) grp2(blk, bs, ds, nd, lw, 2, nxt, s);
            else if (mode == 6) {
                const char *bb = (const char *)blk;
                v16f z[3][2];
                for (int c = 0; c < 3; c++) for (int h = 0; h < 2; h++) z[c][h] = (v16f){0};
                for (i64 t = 0; t < nd; t++) {
                    const int16_t *p = (const int16_t *)(bb + bo[t]);
                    __builtin_prefetch(bb + bo[t + PF]);
                    v16f l[3];
                    for (int c = 0; c < 3; c++) l[c] = bc16(lw + 4 * t + c);
                    for (int h = 0; h < 2; h++) { const v16f x = ld16(p + 16 * h); for (int c = 0; c < 3; c++) z[c][h] += x * l[c]; }
                }
                for (int c = 0; c < 3; c++) for (int h = 0; h < 2; h++) memcpy(s + 32 * c + 16 * h, &z[c][h], 64);
            } else {
                v16f z[3][2], l[3];
                for (int c = 0; c < 3; c++) { l[c] = bc16(lw + c); for (int h = 0; h < 2; h++) z[c][h] = (v16f){0}; }
                for (i64 t = 0; t < nd; t++) {
                    const int16_t *p = blk + ds[t] * 32;
                    if (t + PF < nd) __builtin_prefetch(blk + ds[t + PF] * 32);
                    for (int h = 0; h < 2; h++) { const v16f x = ld16(p + 16 * h); for (int c = 0; c < 3; c++) z[c][h] += x * l[c]; }
                }
                for (int c = 0; c < 3; c++) for (int h = 0; h < 2; h++) memcpy(s + 32 * c + 16 * h, &z[c][h], 64);
            }
        }
        for (; b < nb; b++) grp1(dense + (l1 ? 0 : b * bs), bs, ds, nd, lw, 1, NULL, sums + 96 * b);
    }
    return 0;
}

static double now(void) { struct timespec a; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a); return a.tv_sec + a.tv_nsec * 1e-9; }
/* this thread's clock rate: a chain of dependent 64-bit multiplies (3 cycles each), GHz */
double clock_ghz(void) {
    double a = now(); i64 n = 30000000, x = 3;
    __asm__ volatile("1: imul %0, %0\n imul %0, %0\n imul %0, %0\n imul %0, %0\n dec %1\n jnz 1b" : "+r"(x), "+r"(n));
    return 3.6e8 / ((now() - a) * 1e9);
}
#define BODY_W16(OFS, A0, A1, A2, A3, A4, A5, X0, X1)                                                        \
    "vpmovsxwd " #OFS "(%1,%3),%%zmm" #X0 "\n vcvtdq2ps %%zmm" #X0 ",%%zmm" #X0 "\n"                           \
    "vfmadd231ps %%zmm" #X0 ",%%zmm20,%%zmm" #A0 "\n vfmadd231ps %%zmm" #X0 ",%%zmm21,%%zmm" #A1 "\n"          \
    "vfmadd231ps %%zmm" #X0 ",%%zmm22,%%zmm" #A2 "\n"                                                         \
    "vpmovsxwd " #OFS "+32(%1,%3),%%zmm" #X1 "\n vcvtdq2ps %%zmm" #X1 ",%%zmm" #X1 "\n"                        \
    "vfmadd231ps %%zmm" #X1 ",%%zmm20,%%zmm" #A3 "\n vfmadd231ps %%zmm" #X1 ",%%zmm21,%%zmm" #A4 "\n"          \
    "vfmadd231ps %%zmm" #X1 ",%%zmm22,%%zmm" #A5 "\n"
#define BCAST "vbroadcastss (%2),%%zmm20\n vbroadcastss 4(%2),%%zmm21\n vbroadcastss 8(%2),%%zmm22\n"
#define CLOB "xmm0", "xmm1", "xmm2", "xmm3", "xmm4", "xmm5", "xmm6", "xmm7", "xmm8", "xmm9", "xmm10", "xmm11", "xmm12", \
    "xmm13", "xmm14", "xmm15", "xmm16", "xmm17", "xmm18", "xmm19", "xmm20", "xmm21", "xmm22", "cc"
#define ZERO "vpxord %%xmm0,%%xmm0,%%xmm0\n vpxord %%xmm1,%%xmm1,%%xmm1\n vpxord %%xmm2,%%xmm2,%%xmm2\n"          \
    "vpxord %%xmm3,%%xmm3,%%xmm3\n vpxord %%xmm4,%%xmm4,%%xmm4\n vpxord %%xmm5,%%xmm5,%%xmm5\n vpxord %%xmm6,%%xmm6,%%xmm6\n"   \
    "vpxord %%xmm7,%%xmm7,%%xmm7\n vpxord %%xmm8,%%xmm8,%%xmm8\n vpxord %%xmm9,%%xmm9,%%xmm9\n vpxord %%xmm10,%%xmm10,%%xmm10\n" \
    "vpxord %%xmm11,%%xmm11,%%xmm11\n"
/* seconds per iteration of mix m over n iterations (buf: 16 KB of int16, lw: 4 floats); the address moves by 64
 * bytes per iteration within 8 KB (4 KB for the two-block mix, whose second block is 4 KB on) */
double mix(i64 m, const void *buf, const float *lw, i64 n) {
    const i64 n0 = n;
    i64 off = 0;
    static float fbuf[4096]; /* the float mix's values: 1.0 (the int16 buffer read as floats would be denormal) */
    if (m == 3) { for (int i = 0; i < 4096; i++) fbuf[i] = 1.0f; buf = fbuf; }
    __asm__ volatile(ZERO "vbroadcastss (%0),%%zmm20\n vbroadcastss 4(%0),%%zmm21\n vbroadcastss 8(%0),%%zmm22\n"
                     :: "r"(lw) : CLOB); /* finite sums and light values: no assists */
    double t = now();
    if (m == 0)
        __asm__ volatile("1:\n"
            "vfmadd231ps %%zmm20,%%zmm21,%%zmm0\n vfmadd231ps %%zmm20,%%zmm21,%%zmm1\n vfmadd231ps %%zmm20,%%zmm21,%%zmm2\n"
            "vfmadd231ps %%zmm20,%%zmm21,%%zmm3\n vfmadd231ps %%zmm20,%%zmm21,%%zmm4\n vfmadd231ps %%zmm20,%%zmm21,%%zmm5\n"
            "vfmadd231ps %%zmm20,%%zmm21,%%zmm6\n vfmadd231ps %%zmm20,%%zmm21,%%zmm7\n vfmadd231ps %%zmm20,%%zmm21,%%zmm8\n"
            "vfmadd231ps %%zmm20,%%zmm21,%%zmm9\n vfmadd231ps %%zmm20,%%zmm21,%%zmm10\n vfmadd231ps %%zmm20,%%zmm21,%%zmm11\n"
            "dec %0\n jnz 1b\n" : "+r"(n) : "r"(buf), "r"(lw), "r"(off) : CLOB);
    else if (m == 1)
        __asm__ volatile("1:\n" BCAST BODY_W16(0, 0, 1, 2, 3, 4, 5, 16, 17) "add $64,%3\n and $8191,%3\n dec %0\n jnz 1b\n"
            : "+r"(n), "+r"(buf), "+r"(lw), "+r"(off) :: CLOB);
    else if (m == 2)
        __asm__ volatile("1:\n" BCAST BODY_W16(0, 0, 1, 2, 3, 4, 5, 16, 17) BODY_W16(4096, 6, 7, 8, 9, 10, 11, 18, 19)
            "add $64,%3\n and $4095,%3\n dec %0\n jnz 1b\n" : "+r"(n), "+r"(buf), "+r"(lw), "+r"(off) :: CLOB);
    else if (m == 3)
        __asm__ volatile("1:\n" BCAST "vmovups (%1,%3),%%zmm16\n"
            "vfmadd231ps %%zmm16,%%zmm20,%%zmm0\n vfmadd231ps %%zmm16,%%zmm21,%%zmm1\n vfmadd231ps %%zmm16,%%zmm22,%%zmm2\n"
            "vmovups 64(%1,%3),%%zmm17\n"
            "vfmadd231ps %%zmm17,%%zmm20,%%zmm3\n vfmadd231ps %%zmm17,%%zmm21,%%zmm4\n vfmadd231ps %%zmm17,%%zmm22,%%zmm5\n"
            "add $128,%3\n and $8191,%3\n dec %0\n jnz 1b\n" : "+r"(n), "+r"(buf), "+r"(lw), "+r"(off) :: CLOB);
    else
        __asm__ volatile("1:\n vbroadcastss (%2),%%ymm13\n vbroadcastss 4(%2),%%ymm14\n vbroadcastss 8(%2),%%ymm15\n"
#define Q8(OFS, A0, A1, A2) "vpmovsxwd " #OFS "(%1,%3),%%ymm12\n vcvtdq2ps %%ymm12,%%ymm12\n" \
            "vfmadd231ps %%ymm12,%%ymm13,%%ymm" #A0 "\n vfmadd231ps %%ymm12,%%ymm14,%%ymm" #A1 "\n vfmadd231ps %%ymm12,%%ymm15,%%ymm" #A2 "\n"
            Q8(0, 0, 1, 2) Q8(16, 3, 4, 5) Q8(32, 6, 7, 8) Q8(48, 9, 10, 11)
            "add $64,%3\n and $8191,%3\n dec %0\n jnz 1b\n" : "+r"(n), "+r"(buf), "+r"(lw), "+r"(off) :: CLOB);
    return (now() - t) / (double)(n0 ? n0 : 1);
}
"""

VARIANTS = (("2 blocks (the kernel's form)", 1, 0), ("3 blocks", 2, 0), ("4 blocks", 3, 0), ("2 blocks, no prefetch", 4, 0),
            ("2 blocks, prefetch across pairs", 5, 0), ("1 block, byte offsets", 6, 0), ("1 block, L1", 0, 1),
            ("2 blocks, L1", 1, 1), ("1 block, one light (probe)", 7, 0))
MIXES = ("12 zmm FMAs alone", "the W16 term, 1 block (10 p0/p5 uops)", "the W16 term, 2 blocks (per block)",
         "the term on float values (no widening/conversion)", "the 8-lane AVX2 term (ymm)")


def build_library(who: str):
    """This micro-benchmark's library (compiled once, cached; its functions' argument types set): ``dense16_pass``
    (the 16-lane float loop in its variants; mode 1 the kernel's W16 form, two blocks in lockstep), ``mix`` and
    ``clock_ghz``. Raises SystemExit naming ``who`` without a compiler."""
    lib, how = compile_library("wavelet_dense16_micro", SRC, ["-O3", "-march=native", "-ffp-contract=fast", "-shared",
                                                              "-fPIC", "-std=c99"], {})
    if lib is None:
        raise SystemExit(f"{who}: no compiler: {how}")
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    lib.dense16_pass.argtypes = [vp, i64, vp, vp, i64, vp, i64, i64, i64, vp, i64]
    lib.clock_ghz.restype = ctypes.c_double
    lib.mix.argtypes = [i64, vp, vp, i64]
    lib.mix.restype = ctypes.c_double
    return lib


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--terms", type=int, nargs="+", default=[100, 300, 1000])
    ap.add_argument("--reps", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    if cpu_isa() != "avx512":
        raise SystemExit(f"bench_wavelet_dense16_micro.py: this CPU has {cpu_isa()}; accepted: an AVX-512 CPU (the 16-lane loop)")
    torch.set_num_threads(1)
    lib = build_library("bench_wavelet_dense16_micro.py")
    rl, nb, Pd, d16 = blocker_dense()
    ghz = lib.clock_ghz()
    load0 = os.getloadavg()[0]
    buf = torch.ones(8192, dtype=torch.int16)
    lw1 = torch.tensor([1.0, 0.5, 0.25, 0.0])
    mixes = []
    for m, label in enumerate(MIXES):
        best = min(lib.mix(m, buf.data_ptr(), lw1.data_ptr(), 2_000_000) for _ in range(5))
        mixes.append((label, best * ghz * 1e9 / (2 if m == 2 else 1)))
        print(f"[dense16_micro] mix {label}: {mixes[-1][1]:.2f} cycles", flush=True)
    rows = []
    for light in ("studio", "sky (sun)"):
        for N in args.terms:
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            ds, lw = dense_terms(rl, li, lv)
            nd = ds.numel()
            bo = torch.cat([ds, ds[-1:].expand(6)]) * 64
            sums = torch.zeros(nb, 3, 32)

            def call(mode, l1=0, reps=1):
                return lib.dense16_pass(d16.data_ptr(), Pd, ds.data_ptr(), bo.data_ptr(), nd, lw.data_ptr(), nb, mode, l1,
                                        sums.data_ptr(), reps)

            call(0)
            ref = sums.clone()
            for _, mode, l1 in VARIANTS:
                if mode != 7 and not l1:
                    call(mode, l1)
                    assert torch.equal(sums, ref), (light, N, mode)
            for label, mode, l1 in VARIANTS:
                p = measure_paired(lambda m=mode, x=l1: call(m, x, args.reps), lambda: call(0, 0, args.reps),
                                   repeats=args.repeats, warmup=1, clock=time.thread_time)
                one = p.peer.median / args.reps
                cyc = p.test.median / args.reps * 1e9 * ghz / (nd * nb)
                rows.append({"light": light, "N": N, "nd": nd, "variant": label, "cyc": cyc,
                             "one": one * 1e9 * ghz / (nd * nb), "ratio": p.speedup, "q": [p.ratio.q1, p.ratio.q3]})
                print(f"[dense16_micro] {light} N={N} nd={nd} {label}: {cyc:.2f} cycles/(term, block), 1 block "
                      f"{rows[-1]['one']:.2f}, 1 block/this {p.speedup:.3f}", flush=True)
    L = ["# Wavelet kernel: the 16-lane dense loop alone (issue 39)\n",
         f"{cpu_label()} at {ghz:.2f} GHz (a chain of dependent multiplies), one thread, `-O3 -march=native` (AVX-512); "
         f"load average {load0:.1f} → {os.getloadavg()[0]:.1f} (a shared machine: this thread's CPU time). The kernel "
         f"section's transfer (V = {rl.V}, R = 32, K = 256, 16-bit, {Pd} dense columns, {nb} blocks of 32 vertices), "
         "CT = 1, RGB (CO = 3). Variants and mixes in the module docstring. Reproduce: "
         "`.venv/bin/python benchmarks/bench_wavelet_dense16_micro.py`.\n",
         "## The instruction mix alone (assembly, L1-resident values)\n",
         "| mix | cycles per iteration (per block for 2 blocks) |", "|---|---|"]
    L += [f"| {label} | {c:.2f} |" for label, c in mixes]
    L += ["", "## The loop on the real layout\n",
          f"Each variant paired with `1 block` (the loop of 69385e0) by this thread's CPU time ({args.repeats} repeats of "
          f"{args.reps} passes over every block): cycles per (term, 32-vertex block) and **1 block / variant** "
          "[quartiles] (> 1: the variant faster).\n",
          "| light | N | dense terms | variant | cycles per (term, block) | 1 block: cycles | **1 block / variant** [quartiles] |",
          "|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['light']} | {r['N']} | {r['nd']} | {r['variant']} | {r['cyc']:.2f} | {r['one']:.2f} | "
                 f"**{r['ratio']:.3f}** [{r['q'][0]:.3f}, {r['q'][1]:.3f}] |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_dense16_micro.md", "\n".join(L) + "\n")
    print(f"[dense16_micro] wrote {OUT / 'wavelet_dense16_micro.md'}", flush=True)


if __name__ == "__main__":
    main()
