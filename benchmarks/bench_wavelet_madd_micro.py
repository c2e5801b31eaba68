"""The wavelet kernel's dense part with integer multiply-adds (issue 39, one thread): the dense terms' loop of
``kernels/wavelet.c`` (``dense_block``: per 32-vertex block its 3 x 4 vectors of RGB sums in registers over the
light's dense terms, CT = 1, 16-bit values) against the same loop doing AVX2 ``vpmaddwd`` (16 int16 x int16
products, adjacent pairs added into 8 int32) on a light quantised to int16, over the real blocks and terms of one
light (Ng, Ramamoorthi & Hanrahan 2003 eq. 2; the dense part of ``WaveletRelighter``).

The peer, ``float`` (the kernel's form, ``bench_wavelet_dense_micro.py``'s ``dense_pass`` mode 0): per (term, 32-vertex
block) 4 widening loads, 4 int -> float conversions and 12 multiply-adds (FMA) into 12 float sums.

The integer loops take the light's dense terms (in slot order) two at a time (a, b); per 16 vertices the two terms'
rows are interleaved by ``vpunpcklwd`` / ``vpunpckhwd`` (each 32-bit lane then holds (T_a[v], T_b[v]); the in-lane
vertex order {0-3, 8-11} / {4-7, 12-15} is undone once at the output by ``vperm2f128``), one ``vpmaddwd`` per output
channel with the lane-broadcast (Lq_a[c], Lq_b[c]) and one ``vpaddd`` into int32 sums; at the end of each scale
group the int32 sums are converted, multiplied by the group's light scale and added to float sums. An odd last term
is paired with itself at light 0. Variants:

  - ``half``: intrinsics, 16 vertices (6 sums) at a time (the 32-vertex form in intrinsics: gcc hoists the second
    half's loads and spills the sums to the stack);
  - ``lean``: a whole 32-vertex block per pair in one asm body (12 int32 sums, the row and its two interleavings:
    15 registers), the light pre-broadcast in memory and read by each ``vpmaddwd`` as its memory operand, the pairs'
    slots as byte offsets padded for the prefetch (no test); ``row in register``: the second row loaded into a
    register instead of two memory operands; ``prefetch 2 PF``: the prefetch 12 terms ahead instead of 6;
    ``no prefetch``;
  - ``half, asm``: 16 vertices at a time in one asm body with the light broadcast into a register per channel
    (5 loads per pair-half instead of the whole-block form's 16 per pair);
  - each also with every block reading the first block's values (``L1``): the memory taken out.

Scale groups (``--groups``): ``all`` one group (one int32 -> float flush per block) or ``16`` consecutive terms;
``65535 rule``: s_g = max(sum_{k in g} |L_k| / (65538 - n_g / 2), max_{k in g} |L_k| / 32767), safe for any
|T| <= 32767 (32767 x 65538 < 2^31; the n_g / 2: the rounding's share, which the plain sum |L| / 65535 misses);
``column max``: s_g = max(sum_k tmax_k |L_k| / (2^31 - 1 - sum_k tmax_k / 2),
max_k |L_k| / 32767) with tmax_k the dense column's largest stored magnitude, safe for the stored values (and finer).
Lq = round(L / s_g), s_g rounded up to float32. The madd sums are checked against the float64 sums of the same stored
values within the stated bound |dB_v| <= sum_g (s_g / 2) sum_{k in g} |T_v,k| (+ float rounding), and the bound is
compared with the transfer's own 16-bit quantisation bound for the same terms, sum_k |L_k| / 2 (stored units).

Also the loops' instruction mixes alone (asm, data in L1): which operations share pipes on this CPU. Studio and sky
(transport-weighted) at N terms (default 1000); the kernel section's transfer (occluder_over_plane small, R = 32,
K = 256, 16 bits). Each: the median of 15 paired samples of ``reps`` passes against the float form by this thread's
CPU time. Writes reports/benchmarks/wavelet_madd_micro.md.

    .venv/bin/python benchmarks/bench_wavelet_madd_micro.py [--terms 1000 ...] [--runs 2]    (about 2 min; x86-64 AVX2)

``--vnni`` (a CPU with AVX-512 VNNI): the same idea on 16 lanes, ``vpdpwssd zmm`` (32 int16 products, adjacent pairs
added and accumulated into 16 int32 in one instruction: ``vpmaddwd`` + ``vpaddd`` in one), ``vnni_pass``: per pair of
dense terms and 32-vertex block 1 load, 2 unpacks (the second row their memory operand), 6 ``vpdpwssd`` (asm per
block: in intrinsics gcc copied each of the 12 sums through another register at every step); one block, or two in
lockstep as the kernel's W16 loop. Paired against the kernel's own 16-lane float loop (``bench_wavelet_dense16_micro``'s
``dense16_pass`` mode 1, the W16 pair), the light quantised by the column-maximum rule (one group, and groups of 16);
per size (``--sizes small medium``) the kernel's own call on the same light split (whole call and its streaming-read
bound, dense terms alone, set-up and output alone) and the whole call estimated with the dense loop at the measured
gain; the kernel's VNNI dense loop (``kernels/wavelet.c``'s W16 loop, the default on such a CPU since 2026-11-30)
paired with its opt-out (``arith='float'``, C | FDENSE) on the whole call (each size). Writes
reports/benchmarks/wavelet_madd_micro_vnni.md; ``--vnni --proto`` the whole-call rows alone, with the error bound
(``vnni_bound``), to reports/benchmarks/wavelet_vnni_default.md.

    .venv/bin/python benchmarks/bench_wavelet_madd_micro.py --vnni --sizes small medium --terms 10 30 100 300 1000 6144
    (about 7 min)
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
from bench_wavelet import BITS, LIGHTS, OUT, size_choice  # noqa: E402
from bench_wavelet_dense_micro import SRC as DENSE_SRC  # noqa: E402
from bench_wavelet_dense_micro import blocker_dense, dense_terms  # noqa: E402

from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import cpu_label, machine_info, measure_paired, read_bound_fn  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

# the dense micro-benchmark's source (C_PRELUDE, its float kernel form as dense_pass mode 0, clock_ghz) and the madd loop
SRC = DENSE_SRC + r"""
#ifdef __AVX2__
/* dense int16 [nb, Pd, 32] (blocks bs values apart), pab [np, 2] the pairs' slots, lq [np, 4] int32 per channel
 * (Lq_a in the low half, Lq_b in the high half), gp [ng + 1] each group's first pair, gs [ng, 4] its scale per channel;
 * sums [nb, 3, 32] in vertex order */
int madd_pass(const int16_t *dense, i64 bs, const i64 *pab, i64 np, const int32_t *lq, const i64 *gp, i64 ng,
              const float *gs, i64 nb, float *sums, i64 reps) {
    (void)np;
    for (i64 r_ = 0; r_ < reps; r_++)
        for (i64 b = 0; b < nb; b++) {
            const int16_t *blk = dense + b * bs;
            v8f fs[3][4];
            for (int c = 0; c < 3; c++) for (int k = 0; k < 4; k++) fs[c][k] = (v8f){0};
            for (i64 g = 0; g < ng; g++) {
                __m256i s[3][4];
                const i64 q0 = gp[g], q1 = gp[g + 1];
                for (int h = 0; h < 2; h++) { /* 16 vertices at a time: 6 sums, 3 lights, 4 temporaries, no spill */
                    __m256i s0 = _mm256_setzero_si256(), s1 = s0, s2 = s0, s3 = s0, s4 = s0, s5 = s0;
                    for (i64 q = q0; q < q1; q++) {
                        const int16_t *pa = blk + pab[2 * q] * 32 + 16 * h, *pb = blk + pab[2 * q + 1] * 32 + 16 * h;
                        if (h == 0 && q + PF / 2 < q1) {
                            __builtin_prefetch(blk + pab[2 * q + PF] * 32);
                            __builtin_prefetch(blk + pab[2 * q + PF + 1] * 32);
                        }
                        const __m256i x = _mm256_loadu_si256((const __m256i *)pa), y = _mm256_loadu_si256((const __m256i *)pb);
                        const __m256i lo = _mm256_unpacklo_epi16(x, y), hi = _mm256_unpackhi_epi16(x, y);
                        const __m256i l0 = _mm256_set1_epi32(lq[4 * q]), l1 = _mm256_set1_epi32(lq[4 * q + 1]),
                                      l2 = _mm256_set1_epi32(lq[4 * q + 2]);
                        s0 = _mm256_add_epi32(s0, _mm256_madd_epi16(lo, l0));
                        s1 = _mm256_add_epi32(s1, _mm256_madd_epi16(hi, l0));
                        s2 = _mm256_add_epi32(s2, _mm256_madd_epi16(lo, l1));
                        s3 = _mm256_add_epi32(s3, _mm256_madd_epi16(hi, l1));
                        s4 = _mm256_add_epi32(s4, _mm256_madd_epi16(lo, l2));
                        s5 = _mm256_add_epi32(s5, _mm256_madd_epi16(hi, l2));
                    }
                    s[0][2 * h] = s0; s[0][2 * h + 1] = s1; s[1][2 * h] = s2; s[1][2 * h + 1] = s3;
                    s[2][2 * h] = s4; s[2][2 * h + 1] = s5;
                }
                for (int c = 0; c < 3; c++) {
                    const v8f sc = bc8(gs + 4 * g + c);
                    for (int k = 0; k < 4; k++) fs[c][k] += (v8f)_mm256_cvtepi32_ps(s[c][k]) * sc;
                }
            }
            for (int c = 0; c < 3; c++)
                for (int h = 0; h < 2; h++) {
                    const __m256 lo = (__m256)fs[c][2 * h], hi = (__m256)fs[c][2 * h + 1];
                    _mm256_storeu_ps(sums + b * 96 + 32 * c + 16 * h, _mm256_permute2f128_ps(lo, hi, 0x20));
                    _mm256_storeu_ps(sums + b * 96 + 32 * c + 16 * h + 8, _mm256_permute2f128_ps(lo, hi, 0x31));
                }
        }
    return 0;
}
/* the lean form: a whole 32-vertex block per pair (12 int32 sums, the x rows and their two interleavings: 15
 * registers), the pair's light pre-broadcast in memory lb [np, 3, 8] int32 and read by each vpmaddwd as its memory
 * operand (an asm statement per multiply-add, so that the compiler cannot hold the 3 lights in registers and spill),
 * the pairs' slots as byte offsets pob [np + PF, 2] (padded: the prefetch needs no test) */
#define MADD(s, x, l) do { __m256i t_; __asm__("vpmaddwd %2, %1, %0" : "=x"(t_) : "x"(x), "m"(*(const __m256i *)(l))); \
    s = _mm256_add_epi32(s, t_); } while (0)
#define MADD_BODY(UNP)                                                                                      \
    __asm__("vmovdqu (%[pa]), %[x]\n\t" UNP("")                                                              \
            "vpmaddwd (%[l]), %[lo], %[x]\n\t vpaddd %[x], %[s00], %[s00]\n\t"                                 \
            "vpmaddwd (%[l]), %[hi], %[x]\n\t vpaddd %[x], %[s01], %[s01]\n\t"                                 \
            "vpmaddwd 32(%[l]), %[lo], %[x]\n\t vpaddd %[x], %[s10], %[s10]\n\t"                               \
            "vpmaddwd 32(%[l]), %[hi], %[x]\n\t vpaddd %[x], %[s11], %[s11]\n\t"                               \
            "vpmaddwd 64(%[l]), %[lo], %[x]\n\t vpaddd %[x], %[s20], %[s20]\n\t"                               \
            "vpmaddwd 64(%[l]), %[hi], %[x]\n\t vpaddd %[x], %[s21], %[s21]\n\t"                               \
            "vmovdqu 32(%[pa]), %[x]\n\t" UNP("32")                                                          \
            "vpmaddwd (%[l]), %[lo], %[x]\n\t vpaddd %[x], %[s02], %[s02]\n\t"                                 \
            "vpmaddwd (%[l]), %[hi], %[x]\n\t vpaddd %[x], %[s03], %[s03]\n\t"                                 \
            "vpmaddwd 32(%[l]), %[lo], %[x]\n\t vpaddd %[x], %[s12], %[s12]\n\t"                               \
            "vpmaddwd 32(%[l]), %[hi], %[x]\n\t vpaddd %[x], %[s13], %[s13]\n\t"                               \
            "vpmaddwd 64(%[l]), %[lo], %[x]\n\t vpaddd %[x], %[s22], %[s22]\n\t"                               \
            "vpmaddwd 64(%[l]), %[hi], %[x]\n\t vpaddd %[x], %[s23], %[s23]\n\t"                               \
            : [s00] "+x"(s00), [s01] "+x"(s01), [s02] "+x"(s02), [s03] "+x"(s03), [s10] "+x"(s10),            \
              [s11] "+x"(s11), [s12] "+x"(s12), [s13] "+x"(s13), [s20] "+x"(s20), [s21] "+x"(s21),            \
              [s22] "+x"(s22), [s23] "+x"(s23), [x] "=&x"(x), [lo] "=&x"(lo), [hi] "=&x"(hi)                 \
            : [pa] "r"(pa), [pb] "r"(pb), [l] "r"(l)                                                          \
            : "memory")
/* the second row's interleavings from memory operands, or from a register loaded first (one more register) */
#define UNP_MEM(o) "vpunpckhwd " o "(%[pb]), %[x], %[hi]\n\t vpunpcklwd " o "(%[pb]), %[x], %[lo]\n\t"
#define UNP_REG(o) "vmovdqu " o "(%[pb]), %[hi]\n\t vpunpcklwd %[hi], %[x], %[lo]\n\t vpunpckhwd %[hi], %[x], %[hi]\n\t"
/* mode bit 0: no prefetch; bit 1: the second row in a register; bit 2: the prefetch 2 PF terms ahead */
int madd_lean(const int16_t *dense, i64 bs, const i64 *pob, const int32_t *lb, const i64 *gp, i64 ng,
              const float *gs, i64 nb, float *sums, i64 reps, i64 mode) {
    for (i64 r_ = 0; r_ < reps; r_++)
        for (i64 b = 0; b < nb; b++) {
            const char *blk = (const char *)(dense + b * bs);
            v8f fs[3][4];
            for (int c = 0; c < 3; c++) for (int k = 0; k < 4; k++) fs[c][k] = (v8f){0};
            for (i64 g = 0; g < ng; g++) {
                __m256i s00 = _mm256_setzero_si256(), s01 = s00, s02 = s00, s03 = s00, s10 = s00, s11 = s00, s12 = s00,
                        s13 = s00, s20 = s00, s21 = s00, s22 = s00, s23 = s00;
                const i64 q1 = gp[g + 1];
                for (i64 q = gp[g]; q < q1; q++) {
                    const char *pa = blk + pob[2 * q], *pb = blk + pob[2 * q + 1];
                    if (!(mode & 1)) {
                        const i64 ahead = mode & 4 ? 2 * PF : PF;
                        __builtin_prefetch(blk + pob[2 * q + ahead]);
                        __builtin_prefetch(blk + pob[2 * q + ahead + 1]);
                    }
                    const int32_t *l = lb + 24 * q;
                    __m256i x, lo, hi;
                    if (mode & 2) MADD_BODY(UNP_REG); else MADD_BODY(UNP_MEM);
                }
                const __m256i si[3][4] = {{s00, s01, s02, s03}, {s10, s11, s12, s13}, {s20, s21, s22, s23}};
                for (int c = 0; c < 3; c++) {
                    const v8f sc = bc8(gs + 4 * g + c);
                    for (int k = 0; k < 4; k++) fs[c][k] += (v8f)_mm256_cvtepi32_ps(si[c][k]) * sc;
                }
            }
            for (int c = 0; c < 3; c++)
                for (int h = 0; h < 2; h++) {
                    const __m256 lo = (__m256)fs[c][2 * h], hi = (__m256)fs[c][2 * h + 1];
                    _mm256_storeu_ps(sums + b * 96 + 32 * c + 16 * h, _mm256_permute2f128_ps(lo, hi, 0x20));
                    _mm256_storeu_ps(sums + b * 96 + 32 * c + 16 * h + 8, _mm256_permute2f128_ps(lo, hi, 0x31));
                }
        }
    return 0;
}
/* 16 vertices at a time (the pairs' loop twice per block): 6 int32 sums, the light broadcast into a register
 * per channel from lq [np, 4] (3 broadcasts per pair-half instead of 12 light operands per pair: the whole-block
 * form's floor is its 16 loads per pair), the second row loaded into a register; pob as in madd_lean (2 PF padded) */
int madd_half(const int16_t *dense, i64 bs, const i64 *pob, const int32_t *lq, const i64 *gp, i64 ng,
              const float *gs, i64 nb, float *sums, i64 reps) {
    for (i64 r_ = 0; r_ < reps; r_++)
        for (i64 b = 0; b < nb; b++) {
            const char *blk = (const char *)(dense + b * bs);
            v8f fs[3][4];
            for (int c = 0; c < 3; c++) for (int k = 0; k < 4; k++) fs[c][k] = (v8f){0};
            for (i64 g = 0; g < ng; g++) {
                __m256i si[3][4];
                const i64 q0 = gp[g], q1 = gp[g + 1];
                for (int h = 0; h < 2; h++) {
                    __m256i s0 = _mm256_setzero_si256(), s1 = s0, s2 = s0, s3 = s0, s4 = s0, s5 = s0;
                    for (i64 q = q0; q < q1; q++) {
                        const char *pa = blk + pob[2 * q] + 32 * h, *pb = blk + pob[2 * q + 1] + 32 * h;
                        if (h == 0) {
                            __builtin_prefetch(blk + pob[2 * q + 2 * PF]);
                            __builtin_prefetch(blk + pob[2 * q + 2 * PF + 1]);
                        }
                        const int32_t *l = lq + 4 * q;
                        __m256i x, lo, hi, lc;
                        __asm__("vmovdqu (%[pa]), %[x]\n\t vmovdqu (%[pb]), %[hi]\n\t"
                                "vpunpcklwd %[hi], %[x], %[lo]\n\t vpunpckhwd %[hi], %[x], %[hi]\n\t"
                                "vpbroadcastd (%[l]), %[lc]\n\t"
                                "vpmaddwd %[lc], %[lo], %[x]\n\t vpaddd %[x], %[s0], %[s0]\n\t"
                                "vpmaddwd %[lc], %[hi], %[x]\n\t vpaddd %[x], %[s1], %[s1]\n\t"
                                "vpbroadcastd 4(%[l]), %[lc]\n\t"
                                "vpmaddwd %[lc], %[lo], %[x]\n\t vpaddd %[x], %[s2], %[s2]\n\t"
                                "vpmaddwd %[lc], %[hi], %[x]\n\t vpaddd %[x], %[s3], %[s3]\n\t"
                                "vpbroadcastd 8(%[l]), %[lc]\n\t"
                                "vpmaddwd %[lc], %[lo], %[x]\n\t vpaddd %[x], %[s4], %[s4]\n\t"
                                "vpmaddwd %[lc], %[hi], %[x]\n\t vpaddd %[x], %[s5], %[s5]\n\t"
                                : [s0] "+x"(s0), [s1] "+x"(s1), [s2] "+x"(s2), [s3] "+x"(s3), [s4] "+x"(s4), [s5] "+x"(s5),
                                  [x] "=&x"(x), [lo] "=&x"(lo), [hi] "=&x"(hi), [lc] "=&x"(lc)
                                : [pa] "r"(pa), [pb] "r"(pb), [l] "r"(l)
                                : "memory");
                    }
                    si[0][2 * h] = s0; si[0][2 * h + 1] = s1; si[1][2 * h] = s2; si[1][2 * h + 1] = s3;
                    si[2][2 * h] = s4; si[2][2 * h + 1] = s5;
                }
                for (int c = 0; c < 3; c++) {
                    const v8f sc = bc8(gs + 4 * g + c);
                    for (int k = 0; k < 4; k++) fs[c][k] += (v8f)_mm256_cvtepi32_ps(si[c][k]) * sc;
                }
            }
            for (int c = 0; c < 3; c++)
                for (int h = 0; h < 2; h++) {
                    const __m256 lo = (__m256)fs[c][2 * h], hi = (__m256)fs[c][2 * h + 1];
                    _mm256_storeu_ps(sums + b * 96 + 32 * c + 16 * h, _mm256_permute2f128_ps(lo, hi, 0x20));
                    _mm256_storeu_ps(sums + b * 96 + 32 * c + 16 * h + 8, _mm256_permute2f128_ps(lo, hi, 0x31));
                }
        }
    return 0;
}
/* a grey light (one output channel, CO = 1: a C = 1 light, or an RGB one with equal channels): the float loop as the
 * kernel's dense_block (per term 1 broadcast, 4 widening loads and conversions, 4 FMAs into 4 sums; lw [nd, 4]) and the
 * integer one (per pair 4 loads, 4 unpacks, 4 vpmaddwd with the broadcast pair light lq [np, 4] channel 0, 4 vpaddd:
 * 9 registers, intrinsics suffice); sums [nb, 32] */
int grey_float(const int16_t *dense, i64 bs, const i64 *ds, i64 nd, const float *lw, i64 nb, float *sums, i64 reps) {
    for (i64 r_ = 0; r_ < reps; r_++)
        for (i64 b = 0; b < nb; b++) {
            const int16_t *blk = dense + b * bs;
            v8f a[4] = {{0}, {0}, {0}, {0}};
            for (i64 t = 0; t < nd; t++) {
                const int16_t *p = blk + ds[t] * 32;
                if (t + PF < nd) __builtin_prefetch(blk + ds[t + PF] * 32);
                const v8f l = bc8(lw + 4 * t);
                for (int k = 0; k < 4; k++) a[k] += load8(p + 8 * k) * l;
            }
            for (int k = 0; k < 4; k++) st8(sums + b * 32 + 8 * k, a[k]);
        }
    return 0;
}
int grey_madd(const int16_t *dense, i64 bs, const i64 *pob, const int32_t *lq, const i64 *gp, i64 ng, const float *gs,
              i64 nb, float *sums, i64 reps) {
    for (i64 r_ = 0; r_ < reps; r_++)
        for (i64 b = 0; b < nb; b++) {
            const char *blk = (const char *)(dense + b * bs);
            v8f fs[4] = {{0}, {0}, {0}, {0}};
            for (i64 g = 0; g < ng; g++) {
                __m256i s0 = _mm256_setzero_si256(), s1 = s0, s2 = s0, s3 = s0;
                const i64 q1 = gp[g + 1];
                for (i64 q = gp[g]; q < q1; q++) {
                    const char *pa = blk + pob[2 * q], *pb = blk + pob[2 * q + 1];
                    __builtin_prefetch(blk + pob[2 * q + 2 * PF]);
                    __builtin_prefetch(blk + pob[2 * q + 2 * PF + 1]);
                    const __m256i l = _mm256_set1_epi32(lq[4 * q]);
                    __m256i x = _mm256_loadu_si256((const __m256i *)pa), y = _mm256_loadu_si256((const __m256i *)pb);
                    s0 = _mm256_add_epi32(s0, _mm256_madd_epi16(_mm256_unpacklo_epi16(x, y), l));
                    s1 = _mm256_add_epi32(s1, _mm256_madd_epi16(_mm256_unpackhi_epi16(x, y), l));
                    x = _mm256_loadu_si256((const __m256i *)(pa + 32)); y = _mm256_loadu_si256((const __m256i *)(pb + 32));
                    s2 = _mm256_add_epi32(s2, _mm256_madd_epi16(_mm256_unpacklo_epi16(x, y), l));
                    s3 = _mm256_add_epi32(s3, _mm256_madd_epi16(_mm256_unpackhi_epi16(x, y), l));
                }
                const v8f sc = bc8(gs + 4 * g);
                fs[0] += (v8f)_mm256_cvtepi32_ps(s0) * sc; fs[1] += (v8f)_mm256_cvtepi32_ps(s1) * sc;
                fs[2] += (v8f)_mm256_cvtepi32_ps(s2) * sc; fs[3] += (v8f)_mm256_cvtepi32_ps(s3) * sc;
            }
            for (int h = 0; h < 2; h++) {
                _mm256_storeu_ps(sums + b * 32 + 16 * h, _mm256_permute2f128_ps((__m256)fs[2 * h], (__m256)fs[2 * h + 1], 0x20));
                _mm256_storeu_ps(sums + b * 32 + 16 * h + 8, _mm256_permute2f128_ps((__m256)fs[2 * h], (__m256)fs[2 * h + 1], 0x31));
            }
        }
    return 0;
}
#else /* no AVX2: the integer loops are not built (status -1) */
int madd_pass(void) { return -1; }
int madd_lean(void) { return -1; }
int madd_half(void) { return -1; }
int grey_float(void) { return -1; }
int grey_madd(void) { return -1; }
#endif
/* the loops' instruction mixes alone (x86-64 asm, data in L1, n iterations; this thread's CPU time in s): what = 0: the
 * madd pair body (2 terms x 32 vertices: 4 loads, 4 unpacks, 12 vpmaddwd with the light from memory, 12 vpaddd); 1: the
 * float term body (3 light broadcasts, 4 widening loads, 4 conversions, 12 FMAs); 2..7: 12 independent FMAs, 12 vpmaddwd,
 * 6 FMAs + 6 vpmaddwd, 6 vpmaddwd + 6 unpacks, 6 FMAs + 6 conversions, 12 vpaddd (which operations share pipes) */
#if defined(__x86_64__) && defined(__AVX2__)
static int16_t fl_d[2048] __attribute__((aligned(64)));
static int32_t fl_l[32] __attribute__((aligned(64)));
#define FL_HALF(o, a, b, c, d, e, f) "vmovdqu " o "(%1), %%ymm13\n vmovdqu " o "(%2), %%ymm15\n"                   \
    "vpunpcklwd %%ymm15, %%ymm13, %%ymm14\n vpunpckhwd %%ymm15, %%ymm13, %%ymm15\n"                                \
    "vpmaddwd (%3), %%ymm14, %%ymm13\n vpaddd %%ymm13, %%ymm" a ", %%ymm" a "\n vpmaddwd (%3), %%ymm15, %%ymm13\n"    \
    "vpaddd %%ymm13, %%ymm" b ", %%ymm" b "\n vpmaddwd 32(%3), %%ymm14, %%ymm13\n vpaddd %%ymm13, %%ymm" c ", %%ymm" c "\n" \
    "vpmaddwd 32(%3), %%ymm15, %%ymm13\n vpaddd %%ymm13, %%ymm" d ", %%ymm" d "\n vpmaddwd 64(%3), %%ymm14, %%ymm13\n" \
    "vpaddd %%ymm13, %%ymm" e ", %%ymm" e "\n vpmaddwd 64(%3), %%ymm15, %%ymm13\n vpaddd %%ymm13, %%ymm" f ", %%ymm" f "\n"
#define FL_W(o, a, b, c) "vpmovsxwd " o "(%1), %%ymm15\n vcvtdq2ps %%ymm15, %%ymm15\n vfmadd231ps %%ymm15, %%ymm12, %%ymm" a "\n" \
    "vfmadd231ps %%ymm15, %%ymm13, %%ymm" b "\n vfmadd231ps %%ymm15, %%ymm14, %%ymm" c "\n"
#define FL_R(op, r) op " %%ymm14, %%ymm15, %%ymm" r "\n"
#define FL_C(r) "vcvtdq2ps %%ymm14, %%ymm" r "\n"
#define FL6(op, a, b, c, d, e, f) FL_R(op, a) FL_R(op, b) FL_R(op, c) FL_R(op, d) FL_R(op, e) FL_R(op, f)
double floor_loop(i64 what, long n) {
    struct timespec a, b;
    const int16_t *pa = fl_d, *pb = fl_d + 1024;
    const int32_t *l = fl_l;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a);
#define FL_RUN(body) __asm__ volatile("1:\n" body "dec %0\n jnz 1b" : "+r"(n) : "r"(pa), "r"(pb), "r"(l) : "memory")
    switch (what) {
    case 0: FL_RUN(FL_HALF("", "0", "1", "2", "3", "4", "5") FL_HALF("32", "6", "7", "8", "9", "10", "11")); break;
    case 1: FL_RUN("vbroadcastss (%3), %%ymm12\n vbroadcastss 4(%3), %%ymm13\n vbroadcastss 8(%3), %%ymm14\n"
                   FL_W("", "0", "1", "2") FL_W("16", "3", "4", "5") FL_W("32", "6", "7", "8") FL_W("48", "9", "10", "11")); break;
    case 2: FL_RUN(FL6("vfmadd231ps", "0", "1", "2", "3", "4", "5") FL6("vfmadd231ps", "6", "7", "8", "9", "10", "11")); break;
    case 3: FL_RUN(FL6("vpmaddwd", "0", "1", "2", "3", "4", "5") FL6("vpmaddwd", "6", "7", "8", "9", "10", "11")); break;
    case 4: FL_RUN(FL6("vfmadd231ps", "0", "1", "2", "3", "4", "5") FL6("vpmaddwd", "6", "7", "8", "9", "10", "11")); break;
    case 5: FL_RUN(FL6("vpmaddwd", "0", "1", "2", "3", "4", "5") FL6("vpunpcklwd", "6", "7", "8", "9", "10", "11")); break;
    case 6: FL_RUN(FL6("vfmadd231ps", "0", "1", "2", "3", "4", "5") FL_C("6") FL_C("7") FL_C("8") FL_C("9") FL_C("10") FL_C("11")); break;
    default: FL_RUN(FL6("vpaddd", "0", "1", "2", "3", "4", "5") FL6("vpaddd", "6", "7", "8", "9", "10", "11")); break;
    }
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &b);
    return (double)(b.tv_sec - a.tv_sec) + 1e-9 * (double)(b.tv_nsec - a.tv_nsec);
}
#else
double floor_loop(i64 what, long n) { (void)what; (void)n; return -1.0; }
#endif
/* AVX-512 VNNI (vpdpwssd zmm: 32 int16 x int16 products, adjacent pairs added into 16 int32 and accumulated, one
 * instruction): the pair loop on 16 lanes. Per pair of dense terms (a, b) and 32-vertex block: the two 64-byte rows
 * (one zmm each) interleaved by vpunpcklwd / vpunpckhwd (in 128-bit lanes: lo holds vertices {0-3, 8-11, 16-19,
 * 24-27}, hi {4-7, 12-15, 20-23, 28-31} as (T_a[v], T_b[v]) dword pairs), one vpdpwssd per interleaving and
 * channel with the broadcast pair light (Lq_a[c], Lq_b[c]) (lq [np, 4] int32, pack()'s): CO x 2 = 6 int32 sums per
 * block; at the end of each scale group (gp [ng + 1] first pairs, gs [ng, 4] scales) converted, scaled and added to
 * 6 float sums; the vertex order restored once per block (vpermt2ps). mode bit 0: two blocks (2i, 2i + 1) in
 * lockstep, as the kernel's W16 float loop (the pair's light broadcasts and offsets shared; 12 int32 sums; an odd
 * last block alone); bit 1: no prefetch. The prefetch: both rows of the pair PF / 2 pairs ahead (PF terms) in each
 * block (pob [np + 7, 2] byte offsets, padded). bs: the blocks' stride in int16 (0: every block reads block 0's
 * values, L1). sums [nb, 3, 32] float32, vertex order. Returns -1 where the build has no AVX-512 VNNI. */
#if defined(__AVX512F__) && defined(__AVX512BW__) && defined(__AVX512VNNI__)
/* one pair's body in one block (asm: in intrinsics gcc copied each of the 12 sums through another register at every
 * step, 24 moves per pair): the first row loaded, the second as the unpacks' memory operand, 6 vpdpwssd with the
 * pair's three broadcast lights (registers, shared by the two blocks) */
#define VN_BLOCK(k, pa, pb)                                                                                    \
    __asm__("vmovdqu64 (%[pa_]), %[x]\n\t vpunpckhwd (%[pb_]), %[x], %[hi]\n\t vpunpcklwd (%[pb_]), %[x], %[x]\n\t" \
            "vpdpwssd %[l0], %[x], %[s00]\n\t vpdpwssd %[l0], %[hi], %[s01]\n\t"                                \
            "vpdpwssd %[l1], %[x], %[s10]\n\t vpdpwssd %[l1], %[hi], %[s11]\n\t"                                \
            "vpdpwssd %[l2], %[x], %[s20]\n\t vpdpwssd %[l2], %[hi], %[s21]\n\t"                                \
            : [s00] "+v"(s##k##00), [s01] "+v"(s##k##01), [s10] "+v"(s##k##10), [s11] "+v"(s##k##11),            \
              [s20] "+v"(s##k##20), [s21] "+v"(s##k##21), [x] "=&v"(x), [hi] "=&v"(hi)                          \
            : [pa_] "r"(pa), [pb_] "r"(pb), [l0] "v"(l0), [l1] "v"(l1), [l2] "v"(l2) : "memory")
static inline __attribute__((always_inline)) void vnni_unit(const char *blk, i64 bsb, const int two, const int pf,
        const i64 *pob, const int32_t *lq, const i64 *gp, i64 ng, const float *gs, float *sums) {
    __m512 fs[2][3][2];
    for (int k = 0; k < 2; k++) for (int c = 0; c < 3; c++) for (int h = 0; h < 2; h++) fs[k][c][h] = _mm512_setzero_ps();
    for (i64 g = 0; g < ng; g++) {
        __m512i s000 = _mm512_setzero_si512(), s001 = s000, s010 = s000, s011 = s000, s020 = s000, s021 = s000,
                s100 = s000, s101 = s000, s110 = s000, s111 = s000, s120 = s000, s121 = s000;
        const i64 q1 = gp[g + 1];
        for (i64 q = gp[g]; q < q1; q++) {
            const char *pa = blk + pob[2 * q], *pb = blk + pob[2 * q + 1];
            if (pf) {
                __builtin_prefetch(blk + pob[2 * q + PF]);
                __builtin_prefetch(blk + pob[2 * q + PF + 1]);
                if (two) { __builtin_prefetch(blk + bsb + pob[2 * q + PF]); __builtin_prefetch(blk + bsb + pob[2 * q + PF + 1]); }
            }
            const __m512i l0 = _mm512_set1_epi32(lq[4 * q]), l1 = _mm512_set1_epi32(lq[4 * q + 1]),
                          l2 = _mm512_set1_epi32(lq[4 * q + 2]);
            __m512i x, hi;
            VN_BLOCK(0, pa, pb);
            if (two) VN_BLOCK(1, pa + bsb, pb + bsb);
        }
        const __m512i si[2][3][2] = {{{s000, s001}, {s010, s011}, {s020, s021}}, {{s100, s101}, {s110, s111}, {s120, s121}}};
        for (int c = 0; c < 3; c++) {
            const __m512 sc = _mm512_set1_ps(gs[4 * g + c]);
            for (int k = 0; k < 1 + two; k++) for (int h = 0; h < 2; h++)
                fs[k][c][h] = _mm512_fmadd_ps(_mm512_cvtepi32_ps(si[k][c][h]), sc, fs[k][c][h]);
        }
    }
    /* lane 4j + r of lo: vertex 8j + r; of hi: vertex 8j + 4 + r (r < 4) */
    const __m512i i0 = _mm512_setr_epi32(0, 1, 2, 3, 16, 17, 18, 19, 4, 5, 6, 7, 20, 21, 22, 23),
                  i1 = _mm512_setr_epi32(8, 9, 10, 11, 24, 25, 26, 27, 12, 13, 14, 15, 28, 29, 30, 31);
    for (int k = 0; k < 1 + two; k++)
        for (int c = 0; c < 3; c++) {
            _mm512_storeu_ps(sums + 96 * k + 32 * c, _mm512_permutex2var_ps(fs[k][c][0], i0, fs[k][c][1]));
            _mm512_storeu_ps(sums + 96 * k + 32 * c + 16, _mm512_permutex2var_ps(fs[k][c][0], i1, fs[k][c][1]));
        }
}
#define VN_PASS(PFON)                                                                                          \
    for (i64 r_ = 0; r_ < reps; r_++) {                                                                        \
        i64 b = 0;                                                                                             \
        if (two)                                                                                               \
            for (; b + 2 <= nb; b += 2)                                                                        \
                vnni_unit((const char *)dense + b * bsb, bsb, 1, PFON, pob, lq, gp, ng, gs, sums + 96 * b);    \
        for (; b < nb; b++) vnni_unit((const char *)dense + b * bsb, bsb, 0, PFON, pob, lq, gp, ng, gs, sums + 96 * b); \
    }
int vnni_pass(const int16_t *dense, i64 bs, const i64 *pob, const int32_t *lq, const i64 *gp, i64 ng, const float *gs,
              i64 nb, float *sums, i64 reps, i64 mode) {
    const int two = mode & 1;
    const i64 bsb = bs * (i64)sizeof(int16_t);
    if (mode & 2) { VN_PASS(0) } else { VN_PASS(1) }
    return 0;
}
/* the VNNI pair body's mixes alone (asm, data in L1, as floor_loop): what = 0: one block (2 terms x 32 vertices: a
 * load, 2 unpacks with the second row as memory operand, 6 vpdpwssd with the light as an embedded broadcast {1to16});
 * 1: two blocks, the 3 lights broadcast into registers once (per block: the same); 2: 12 independent vpdpwssd zmm;
 * 3: 12 independent vfmadd231ps zmm (the float loop's multiply-adds, same clock); 4: 6 vpdpwssd + 6 vpunpcklwd zmm */
#define VN_CLOB "xmm0", "xmm1", "xmm2", "xmm3", "xmm4", "xmm5", "xmm6", "xmm7", "xmm8", "xmm9", "xmm10", "xmm11", \
    "xmm16", "xmm17", "xmm18", "xmm20", "xmm21", "xmm22", "memory"
#define VN12(op) op " %%zmm20,%%zmm21,%%zmm0\n " op " %%zmm20,%%zmm21,%%zmm1\n " op " %%zmm20,%%zmm21,%%zmm2\n "    \
    op " %%zmm20,%%zmm21,%%zmm3\n " op " %%zmm20,%%zmm21,%%zmm4\n " op " %%zmm20,%%zmm21,%%zmm5\n "                   \
    op " %%zmm20,%%zmm21,%%zmm6\n " op " %%zmm20,%%zmm21,%%zmm7\n " op " %%zmm20,%%zmm21,%%zmm8\n "                   \
    op " %%zmm20,%%zmm21,%%zmm9\n " op " %%zmm20,%%zmm21,%%zmm10\n " op " %%zmm20,%%zmm21,%%zmm11\n"
#define VN_BLK(o, a, b, c, d, e, f) "vmovdqu64 " o "(%1),%%zmm16\n vpunpcklwd " o "+64(%1),%%zmm16,%%zmm17\n"      \
    "vpunpckhwd " o "+64(%1),%%zmm16,%%zmm18\n"                                                                    \
    "vpdpwssd %%zmm20,%%zmm17,%%zmm" a "\n vpdpwssd %%zmm21,%%zmm17,%%zmm" b "\n vpdpwssd %%zmm22,%%zmm17,%%zmm" c "\n" \
    "vpdpwssd %%zmm20,%%zmm18,%%zmm" d "\n vpdpwssd %%zmm21,%%zmm18,%%zmm" e "\n vpdpwssd %%zmm22,%%zmm18,%%zmm" f "\n"
double vnni_floor(i64 what, long n) {
    struct timespec a, b;
    const int16_t *pa = fl_d;
    const int32_t *l = fl_l;
    __asm__ volatile("vpxord %%xmm20,%%xmm20,%%xmm20\n vpxord %%xmm21,%%xmm21,%%xmm21\n vpxord %%xmm22,%%xmm22,%%xmm22\n"
                     ::: "xmm20", "xmm21", "xmm22");
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a);
#define VN_RUN(body) __asm__ volatile("1:\n" body "dec %0\n jnz 1b" : "+r"(n) : "r"(pa), "r"(l) : VN_CLOB)
    switch (what) {
    case 0: VN_RUN("vmovdqu64 (%1),%%zmm16\n vpunpcklwd 64(%1),%%zmm16,%%zmm17\n vpunpckhwd 64(%1),%%zmm16,%%zmm18\n"
                   "vpdpwssd (%2)%{1to16%},%%zmm17,%%zmm0\n vpdpwssd 4(%2)%{1to16%},%%zmm17,%%zmm1\n"
                   "vpdpwssd 8(%2)%{1to16%},%%zmm17,%%zmm2\n vpdpwssd (%2)%{1to16%},%%zmm18,%%zmm3\n"
                   "vpdpwssd 4(%2)%{1to16%},%%zmm18,%%zmm4\n vpdpwssd 8(%2)%{1to16%},%%zmm18,%%zmm5\n"
                   "vmovdqu64 128(%1),%%zmm16\n vpunpcklwd 192(%1),%%zmm16,%%zmm17\n vpunpckhwd 192(%1),%%zmm16,%%zmm18\n"
                   "vpdpwssd (%2)%{1to16%},%%zmm17,%%zmm6\n vpdpwssd 4(%2)%{1to16%},%%zmm17,%%zmm7\n"
                   "vpdpwssd 8(%2)%{1to16%},%%zmm17,%%zmm8\n vpdpwssd (%2)%{1to16%},%%zmm18,%%zmm9\n"
                   "vpdpwssd 4(%2)%{1to16%},%%zmm18,%%zmm10\n vpdpwssd 8(%2)%{1to16%},%%zmm18,%%zmm11\n"); break;
    case 1: VN_RUN("vpbroadcastd (%2),%%zmm20\n vpbroadcastd 4(%2),%%zmm21\n vpbroadcastd 8(%2),%%zmm22\n"
                   VN_BLK("0", "0", "1", "2", "3", "4", "5") VN_BLK("2048", "6", "7", "8", "9", "10", "11")); break;
    case 2: VN_RUN(VN12("vpdpwssd")); break;
    case 3: VN_RUN(VN12("vfmadd231ps")); break;
    default: VN_RUN("vpdpwssd %%zmm20,%%zmm21,%%zmm0\n vpdpwssd %%zmm20,%%zmm21,%%zmm1\n vpdpwssd %%zmm20,%%zmm21,%%zmm2\n"
                    "vpdpwssd %%zmm20,%%zmm21,%%zmm3\n vpdpwssd %%zmm20,%%zmm21,%%zmm4\n vpdpwssd %%zmm20,%%zmm21,%%zmm5\n"
                    "vpunpcklwd %%zmm20,%%zmm21,%%zmm6\n vpunpcklwd %%zmm20,%%zmm21,%%zmm7\n vpunpcklwd %%zmm20,%%zmm21,%%zmm8\n"
                    "vpunpcklwd %%zmm20,%%zmm21,%%zmm9\n vpunpcklwd %%zmm20,%%zmm21,%%zmm10\n vpunpcklwd %%zmm20,%%zmm21,%%zmm11\n"); break;
    }
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &b);
    return (double)(b.tv_sec - a.tv_sec) + 1e-9 * (double)(b.tv_nsec - a.tv_nsec);
}
#else
int vnni_pass(void) { return -1; }
double vnni_floor(i64 what, long n) { (void)what; (void)n; return -1.0; }
#endif
"""


LEAN = {"lean": 0, "lean, no prefetch": 1, "lean, row in register": 2, "lean, row in register, prefetch 2 PF": 6}
VARIANTS = ("half", *LEAN, "half, asm")
#: the AVX-512 VNNI loops (``vnni_pass``'s mode): one block, two blocks in lockstep (the kernel's W16 form), and
#: two without the prefetch; status -1 where the build has no AVX-512 VNNI
VNNI = {"vnni, 1 block": 0, "vnni, 2 blocks": 1, "vnni, 2 blocks, no prefetch": 3}
VNNI_FLOORS = ("VNNI pair body, 1 block (2 terms x 32 vertices: 1 load, 2 unpacks, 6 vpdpwssd {1to16}; x2)",
               "VNNI pair body, 2 blocks (3 broadcasts, per block 1 load, 2 unpacks, 6 vpdpwssd)", "12 vpdpwssd zmm",
               "12 vfmadd231ps zmm", "6 vpdpwssd + 6 vpunpcklwd zmm")


FLOORS = ("madd pair body (2 terms x 32 vertices; per term: half)", "float term body (1 term x 32 vertices)",
          "12 FMA", "12 vpmaddwd", "6 FMA + 6 vpmaddwd", "6 vpmaddwd + 6 vpunpcklwd", "6 FMA + 6 vcvtdq2ps", "12 vpaddd")


#: the kernel's flush groups (``kernels/wavelet.c``'s VNNI_G, VNNI_RHO, VNNI_L2, VNNI_BETA): chunks of 16 dense terms,
#: merged while the call's column-maximum bound stays within 1.25 x the 16-term groups' (grp17's rule, the default:
#: VNNI_L2 0); with VNNI_L2 (vnb18's knob) the L2 bound (the columns' norms of scale x T) within 1.25 x the 16-term
#: groups' or 0.75 x the transfer's own 16-bit bound, whichever is larger (:func:`vnni_groups`). VNNI_GUARD (vg18): the
#: call takes the float loop when its L2 bound exceeds VNNI_GUARD x the transfer's own (:func:`vnni_guard`)
VNNI_G, VNNI_RHO, VNNI_BETA, VNNI_L2, VNNI_GUARD = 16, 1.25, 0.75, False, 1.0


def vnni_groups(lw: torch.Tensor, tmax: torch.Tensor, rho: float = VNNI_RHO, chunk: int = VNNI_G,
                norms: torch.Tensor | None = None, nscale: float = 0.0, beta: float = VNNI_BETA) -> torch.Tensor:
    """The VNNI loop's flush groups for one call, found from the light and the columns' maxima and norms
    (``kernels/wavelet.c``'s rule, recomputed here): ``lw`` [nd, 3] the dense terms' light in the kernel's order,
    ``tmax`` [nd] their columns' largest stored magnitudes (the scales), ``norms`` [nd] float64 their columns' L2
    norms over the vertices of scale x T and ``nscale`` the scale's own L2 norm (the kernel's rule since vnb18; None:
    grp17's, the columns' maxima as weights, no absolute budget). Chunks of ``chunk`` consecutive terms, merged left
    to right while, for every channel c, done_c + s_G,c W_G + rest_c <= budget_c, with W a run's weight (the sum of
    its norms; grp17: of its tmax), s its scale by :func:`quantise_light`'s column-maximum rule, done the closed
    groups' s W, rest the later chunks' as groups of ``chunk``, and budget_c = max(rho x B16_c, beta x nscale x
    sum_k |L_k,c|) (B16_c = sum over the chunks g of s_g,c W_g; the second term with ``norms`` only). With the norms,
    sum_G (s_G,c / 2) W_G bounds the output's L2 error over the vertices (triangle inequality; the albedo aside) and
    nscale sum_k |L_k,c| / 2 is the transfer's own 16-bit bound in the same terms. The same float64 sums in the same
    order as the kernel (a chunk's sums term by term, a run's its chunks' in order, sum |L| term by term; B16 summed
    from the back), so the same groups. Returns each term's group, int64 [nd]."""
    nd = lw.shape[0]
    a = lw.double().abs().tolist()
    tm = [float(x) for x in tmax.tolist()]
    nm = None if norms is None else [float(x) for x in norms.double().tolist()]
    nc = (nd + chunk - 1) // chunk
    cs, cm, ch, cw = [], [], [], []
    la = [0.0] * 3
    for i in range(nc):
        su, mx, half, wt = [0.0] * 3, [0.0] * 3, 0.0, 0.0
        for t in range(i * chunk, min((i + 1) * chunk, nd)):
            half += tm[t] / 2
            wt += tm[t] if nm is None else nm[t]
            for c in range(3):
                su[c] += a[t][c] * tm[t]
                mx[c] = max(mx[c], a[t][c])
                la[c] += a[t][c]
        cs.append(su), cm.append(mx), ch.append(half), cw.append(wt)

    def rule(su, mx, half):
        return [max(su[c] / (2147483647.0 - half), mx[c] / 32767.0) for c in range(3)]

    rest = [[0.0] * 3 for _ in range(nc + 1)]
    for i in range(nc - 1, -1, -1):
        sc = rule(cs[i], cm[i], ch[i])
        rest[i] = [rest[i + 1][c] + sc[c] * cw[i] for c in range(3)]
    bud = [max(rho * rest[0][c], beta * nscale * la[c] if nm is not None else 0.0) for c in range(3)]
    grp, g, done, cur = [], -1, [0.0] * 3, [0.0] * 3
    gs = gm = None
    gh = gw = 0.0
    for i in range(nc):
        n = min((i + 1) * chunk, nd) - i * chunk
        if i > 0:
            s2 = [gs[c] + cs[i][c] for c in range(3)]
            m2 = [max(gm[c], cm[i][c]) for c in range(3)]
            h2, w2 = gh + ch[i], gw + cw[i]
            sc = rule(s2, m2, h2)
            if all(done[c] + sc[c] * w2 + rest[i + 1][c] <= bud[c] for c in range(3)):
                gs, gm, gh, gw, cur = s2, m2, h2, w2, [sc[c] * w2 for c in range(3)]
                grp += [g] * n
                continue
            done = [done[c] + cur[c] for c in range(3)]
        g += 1
        gs, gm, gh, gw = list(cs[i]), list(cm[i]), ch[i], cw[i]
        sc = rule(gs, gm, gh)
        cur = [sc[c] * gw for c in range(3)]
        grp += [g] * n
    return torch.tensor(grp, dtype=torch.int64)


def kernel_groups(lw: torch.Tensor, tmax: torch.Tensor, norms: torch.Tensor, nscale: float) -> torch.Tensor:
    """The kernel's flush groups for one call (:func:`vnni_groups` by its default rule: grp17's column maxima, or the L2
    rule where :data:`VNNI_L2`), each term's group int64 [nd]."""
    return vnni_groups(lw, tmax, norms=norms, nscale=nscale) if VNNI_L2 else vnni_groups(lw, tmax)


def vnni_guard(lw: torch.Tensor, grp, tmax: torch.Tensor, norms: torch.Tensor, nscale: float,
               guard: float = VNNI_GUARD) -> tuple[bool, float]:
    """``kernels/wavelet.c``'s per-call guard (vg18), recomputed: for the dense terms' light ``lw`` [nd, 3] in the
    kernel's order, their flush groups ``grp`` (each term's group int64 [nd], or a group size), columns' maxima ``tmax``
    [nd] and L2 norms of scale x T ``norms`` [nd] float64 (``nscale`` the scale's own norm), the call's L2 bound
    sum_G s_G,c sum_{k in G} norms_k (:func:`quantise_light`'s float32 scales) against the transfer's own
    nscale sum_k |L_k,c| (both without the common 1/2), per channel with light. Returns ``(trips, ratio)``: whether
    the call takes the float loop (ratio > ``guard`` in some channel; ``guard`` 0: never) and the largest channel's
    ratio."""
    _, s, g = quantise_light(lw, grp, tmax)
    W = torch.zeros(s.shape[0], dtype=torch.float64).index_add_(0, g, norms.double())
    vb = (s.double() * W[:, None]).sum(0)
    own = nscale * lw.double().abs().sum(0)
    lit = own > 0
    ratio = float((vb[lit] / own[lit]).max()) if bool(lit.any()) else 0.0
    return bool(guard > 0 and ratio > guard), ratio


def dense_norms(rl) -> torch.Tensor:
    """The dense columns' L2 norms over the vertices of scale x T, float64 [Pd], and the scale's, by brute force over
    ``rl.dense`` and ``rl.scale`` (a grey transfer; not the layout's ``dnorm``): ``(norms, nscale)``."""
    T = rl.dense[:, :rl.Pd, 0, :].permute(1, 0, 2).reshape(rl.Pd, -1)[:, :rl.V].double()  # [Pd, V]
    sv = rl.scale[:, 0].double()
    return (T * sv).norm(dim=1), float(sv.norm())


def quantise_light(lw: torch.Tensor, group, tmax: torch.Tensor | None):
    """The dense terms' light lw [nd, 3] float32 quantised per group of ``group`` consecutive terms and channel:
    Lq int32 [nd, 3], the groups' scales s float32 [ng, 3] and each term's group int64 [nd]. The scale keeps every
    int32 sum of Tq Lq in range, rounding included (|Lq_k| <= |L_k| / s + 1/2): with the columns' largest stored
    magnitudes tmax [nd] ("column max"), s_g = max(sum_k tmax_k |L_k| / (2^31 - 1 - sum_k tmax_k / 2),
    max_k |L_k| / 32767); without (None: any |T| <= 32767, "65535 rule"), s_g = max(sum |L| / (65538 - n_g / 2),
    max |L| / 32767), n_g the group's terms — the brief's sum |L| / 65535 lets the rounding carry sum |Lq| to
    65535 + n_g / 2, past the 65538 = floor((2^31 - 1) / 32767) that |T| = 32767 allows
    (tests/test_wavelet_madd_micro.py found it). Rounded up to float32, so that q s_g is the dequantised light
    exactly and |q s_g - L| <= s_g / 2. ``group``: an int (consecutive terms a group) or each term's group int64 [nd]
    (:func:`vnni_groups`)."""
    nd = lw.shape[0]
    grp = group if isinstance(group, torch.Tensor) else torch.arange(nd) // group
    ng = int(grp[-1]) + 1 if nd else 0
    a = lw.double().abs()
    smax = torch.zeros(ng, 3, dtype=torch.float64).scatter_reduce_(0, grp[:, None].expand(-1, 3), a, "amax")
    if tmax is None:
        ssum = torch.zeros(ng, 3, dtype=torch.float64).index_add_(0, grp, a)
        cnt = torch.bincount(grp, minlength=ng).to(torch.float64)[:, None]
        s = torch.maximum(ssum / (65538 - cnt / 2), smax / 32767)
    else:
        tm = tmax.double()[:, None]
        ssum = torch.zeros(ng, 3, dtype=torch.float64).index_add_(0, grp, a * tm)
        half = torch.zeros(ng, dtype=torch.float64).index_add_(0, grp, tm[:, 0] / 2)
        s = torch.maximum(ssum / (2.0 ** 31 - 1 - half[:, None]), smax / 32767)
    s = torch.where(s > 0, s, torch.full_like(s, 2.0 ** -126))  # a group without light: q = 0, no error, no bound
    s32 = s.float()
    s32 = torch.where(s32.double() < s, torch.nextafter(s32, torch.full_like(s32, float("inf"))), s32)
    q = torch.round(lw.double() / s32.double()[grp]).to(torch.int32)
    return q, s32, grp


CONFIGS = {"all, 65535 rule": (4096, False), "all, column max": (4096, True), "16, column max": (16, True)}


def build_library():
    """The micro-benchmark's library (compiled once, cached), its functions' argument types set; None without a compiler."""
    lib, _ = compile_library("wavelet_madd_micro", SRC, ["-O3", "-march=native", "-ffp-contract=fast", "-shared",
                                                          "-fPIC", "-std=c99"], {})
    if lib is None:
        return None
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    lib.dense_pass.argtypes = [vp, i64, vp, i64, vp, i64, i64, vp, i64]
    lib.madd_pass.argtypes = [vp, i64, vp, i64, vp, vp, i64, vp, i64, vp, i64]
    lib.madd_lean.argtypes = [vp, i64, vp, vp, vp, i64, vp, i64, vp, i64, i64]
    lib.madd_half.argtypes = [vp, i64, vp, vp, vp, i64, vp, i64, vp, i64]
    lib.grey_float.argtypes = [vp, i64, vp, i64, vp, i64, vp, i64]
    lib.grey_madd.argtypes = [vp, i64, vp, vp, vp, i64, vp, i64, vp, i64]
    lib.clock_ghz.restype = ctypes.c_double
    lib.floor_loop.argtypes = [i64, ctypes.c_long]
    lib.floor_loop.restype = ctypes.c_double
    lib.vnni_pass.argtypes = [vp, i64, vp, vp, vp, i64, vp, i64, vp, i64, i64]
    lib.vnni_floor.argtypes = [i64, ctypes.c_long]
    lib.vnni_floor.restype = ctypes.c_double
    return lib


def float_pf_library(pf: int):
    """The float loop (``dense_pass`` mode 0) compiled with its prefetch ``pf`` terms ahead instead of the kernel's 6."""
    lib, _ = compile_library(f"wavelet_madd_micro_pf{pf}", SRC.replace("#define PF 6", f"#define PF {pf}"),
                             ["-O3", "-march=native", "-ffp-contract=fast", "-shared", "-fPIC", "-std=c99"], {})
    if lib is not None:
        i64, vp = ctypes.c_int64, ctypes.c_void_p
        lib.dense_pass.argtypes = [vp, i64, vp, i64, vp, i64, i64, vp, i64]
    return lib


def pack(ds: torch.Tensor, q: torch.Tensor, s: torch.Tensor, group: int) -> dict:
    """The integer loops' arguments for the dense slots ``ds [nd]`` (slot order) and their quantised light ``q [nd, 3]``
    int32 with scales ``s [ng, 3]`` float32 (:func:`quantise_light` with ``group`` terms a group, even): the pairs'
    slots ``pab [np, 2]`` (an odd last term paired with itself at light 0), their byte offsets ``pob`` (padded by
    2 PF + 2 entries for the prefetch), the pairs' light ``lq [np, 4]`` int32 ((Lq_a & 0xFFFF) | Lq_b << 16 per
    channel) and pre-broadcast ``lb [np, 3, 8]``, each group's first pair ``gp [ng + 1]`` and scales ``gs [ng, 4]``."""
    nd = ds.numel()
    pa, qq = ds.long(), q
    if nd % 2:
        pa = torch.cat([pa, pa[-1:]])
        qq = torch.cat([qq, torch.zeros(1, 3, dtype=torch.int32)])
    np_ = pa.numel() // 2
    ng = s.shape[0]
    lq = torch.zeros(np_, 4, dtype=torch.int32)
    lq[:, :3] = (qq[0::2] & 0xFFFF) | (qq[1::2] << 16)
    gs = torch.zeros(ng, 4)
    gs[:, :3] = s
    return {"np": np_, "ng": ng, "pab": pa.contiguous(), "pob": torch.cat([pa, pa[-2:].repeat(7)]) * 64, "lq": lq,
            "lb": lq[:, :3, None].expand(np_, 3, 8).contiguous(),
            "gp": torch.tensor([min(g * group // 2, np_) for g in range(ng)] + [np_], dtype=torch.int64), "gs": gs}


def madd_call(lib, variant: str, d16: torch.Tensor, k: dict, out: torch.Tensor, l1: bool = False, reps: int = 1) -> int:
    """One call of an integer loop over the dense blocks ``d16 [nb, Pd, 32]`` int16 with :func:`pack`'s arguments ``k``:
    the sums (light scale applied, no factor) into ``out [nb, 3, 32]`` float32, vertex order; ``l1``: every block reads
    the first block's values. Returns the loop's status (-1: no AVX2 build; for the VNNI loops, no AVX-512 VNNI)."""
    nb, Pd = d16.shape[0], d16.shape[1]
    bs = 0 if l1 else Pd * 32
    if variant in VNNI:
        return lib.vnni_pass(d16.data_ptr(), bs, k["pob"].data_ptr(), k["lq"].data_ptr(), k["gp"].data_ptr(), k["ng"],
                             k["gs"].data_ptr(), nb, out.data_ptr(), reps, VNNI[variant])
    if variant == "half, asm":
        return lib.madd_half(d16.data_ptr(), bs, k["pob"].data_ptr(), k["lq"].data_ptr(), k["gp"].data_ptr(), k["ng"],
                             k["gs"].data_ptr(), nb, out.data_ptr(), reps)
    if variant == "half":
        return lib.madd_pass(d16.data_ptr(), bs, k["pab"].data_ptr(), k["np"], k["lq"].data_ptr(), k["gp"].data_ptr(),
                             k["ng"], k["gs"].data_ptr(), nb, out.data_ptr(), reps)
    return lib.madd_lean(d16.data_ptr(), bs, k["pob"].data_ptr(), k["lb"].data_ptr(), k["gp"].data_ptr(), k["ng"],
                         k["gs"].data_ptr(), nb, out.data_ptr(), reps, LEAN[variant])


def vnni_main(args, lib) -> None:
    """The AVX-512 VNNI rows (``--vnni``): per size, light and N, the VNNI loops against the kernel's 16-lane float
    dense loop (``bench_wavelet_dense16_micro``'s ``dense16_pass`` mode 1: the kernel's W16 pair, two blocks in
    lockstep) on the same dense terms, paired by one thread's CPU time; the errors against the float64 sums of the same
    stored values and against the transfer's own quantisation bound; the kernel itself on the same light (whole call,
    dense terms alone, set-up and output alone, its streaming-read bound) and what the whole call would become with
    the dense loop at the measured gain. Writes reports/benchmarks/wavelet_madd_micro_vnni.md."""
    from bench_wavelet import rel
    from bench_wavelet_dense16_micro import build_library as dense16_library

    if lib.vnni_floor(0, 1) < 0:
        raise SystemExit("bench_wavelet_madd_micro.py: --vnni: this build has no AVX-512 VNNI (accepted: a CPU with "
                         "avx512_vnni, e.g. Intel Xeon Ice Lake or later)")
    f16 = dense16_library("bench_wavelet_madd_micro.py")
    ghz = max(lib.clock_ghz() for _ in range(5))
    loads = [os.getloadavg()[0]]
    floors = {}
    for what, label in enumerate(VNNI_FLOORS):
        floors[label] = min(lib.vnni_floor(what, 2_000_000) for _ in range(9)) * ghz * 1e9 / 2_000_000
        print(f"[madd_micro vnni] floor {label}: {floors[label]:.2f} cycles", flush=True)
    groups = ("all, column max", "16, column max")
    rows, protos = [], []
    for size in args.sizes:
        rl, nb, Pd, d16 = blocker_dense(size)
        tmax = d16.abs().amax(dim=(0, 2)).to(torch.int64)
        assert int(d16.abs().max()) <= 32767, "stored values outside +-32767"
        reps = max(5, args.reps * 71 // nb)
        fac = rl._factor(3, True).double()  # [V, 3] the kernel's per-vertex factor (quantisation scale x albedo)
        empty = torch.nonzero(rl.cls == 0).flatten()[:1].contiguous()
        out0 = torch.empty(rl.V, 3)
        f_fixed = rl.prepared(empty, torch.ones(3, 1), out0)
        for light in ("studio", "sky (sun)"):
            li_a, lv_a, _ = rl.light(LIGHTS[light], rl.P, "transport")
            out_all = rl.prepared(li_a, lv_a.float(), torch.empty(rl.V, 3))().clone().double()
            for N in args.terms:
                N = min(N, rl.P)
                li, lv, _ = rl.light(LIGHTS[light], N, "transport")
                lv = lv.float().contiguous()
                ds, lw = dense_terms(rl, li, lv)
                nd = ds.numel()
                res = {"size": size, "V": rl.V, "nb": nb, "light": light, "N": "all" if N == rl.P else N,
                       "terms": int(li.numel()), "nd": nd, "tb": nd * nb}
                # the kernel: the whole call, its dense terms alone, the set-up and output alone, the streaming read
                out_n = torch.empty(rl.V, 3)
                f_all = rl.prepared(li, lv, out_n)
                d = rl.dslot[li] >= 0
                f_dense = rl.prepared(li[d].contiguous(), lv[:, d].contiguous(), torch.empty(rl.V, 3))
                f_all()
                pr = measure_paired(f_all, read_bound_fn(rl.bytes_read(li), rl.V * 12), repeats=15, warmup=1,
                                    clock=time.thread_time)
                pd = measure_paired(f_dense, f_fixed, repeats=15, warmup=1, clock=time.thread_time)
                res.update(call=pr.test.median, read=pr.peer.median, of_read=pr.speedup, dense_call=pd.test.median,
                           fixed=pd.peer.median, dense_net=pd.test.median - pd.peer.median,
                           trunc=rel(out_n, out_all))
                # the float pair loop (the kernel's W16 form) and the float64 sums of the stored values
                fsums = torch.zeros(nb, 3, 32)
                bo = torch.cat([ds, ds[-1:].expand(6)]) * 64

                def fcall(l1=0, reps=1):
                    return f16.dense16_pass(d16.data_ptr(), Pd, ds.data_ptr(), bo.data_ptr(), nd, lw.data_ptr(), nb, 1, l1,
                                            fsums.data_ptr(), reps)

                fcall()
                tv = d16[:, ds, :].double()  # [nb, nd, 32]
                exact = torch.einsum("bkv,kc->bcv", tv, lw[:, :3].double())
                res["float err"] = float(((fsums.double() - exact).abs() / exact.abs().clamp_min(1e-30)).median())
                tbound = lw[:, :3].double().abs().sum(0)[None, :, None] / 2
                msums = torch.zeros(nb, 3, 32)
                for G in groups:
                    G2, _ = CONFIGS[G]
                    q, sc, grp = quantise_light(lw[:, :3], G2, tmax[ds])
                    k = pack(ds, q, sc, G2)
                    bound = torch.einsum("bkv,kc->bcv", tv.abs(), sc.double()[grp] / 2)
                    slack = 1e-6 * exact.abs() + 1e-6 * torch.einsum("bkv,kc->bcv", tv.abs(), lw[:, :3].double().abs())
                    for variant in VNNI:
                        assert madd_call(lib, variant, d16, k, msums) == 0
                        err = (msums.double() - exact).abs()
                        key = f"{variant} G{G}"
                        res[key + " ok"] = bool((err <= bound + slack).all())
                        res[key + " err"] = float((err / exact.abs().clamp_min(1e-30)).median())
                        res[key + " vs transfer"] = float((bound / tbound).median())
                        # the output's error from the dense sums alone: relative L2 over vertices and channels
                        dv = (msums.double() - exact).permute(0, 2, 1).reshape(-1, 3)[:rl.V] * fac
                        res[key + " out err"] = float(dv.norm() / out_n.double().norm())
                        res[key + " out bound"] = float(((bound.permute(0, 2, 1).reshape(-1, 3)[:rl.V] * fac).norm()
                                                         / out_n.double().norm()))
                        res[key + " out transfer bound"] = float(((tbound.expand_as(bound).permute(0, 2, 1)
                                                                   .reshape(-1, 3)[:rl.V] * fac).norm() / out_n.double().norm()))
                        for l1 in (False, True):
                            p = measure_paired(lambda x=l1, v=variant, k=k: madd_call(lib, v, d16, k, msums, x, reps),
                                               lambda x=l1: fcall(int(x), reps), repeats=15, warmup=1, clock=time.thread_time)
                            kk = key + (" L1" if l1 else "")
                            res[kk] = p.test.median / reps
                            res[kk + " float"] = p.peer.median / reps
                            res[kk + " ratio"] = p.speedup
                            res[kk + " q"] = [p.ratio.q1, p.ratio.q3]
                        print(f"[madd_micro vnni] {size} {light} N={res['N']} nd={nd} {key}: vnni {res[key] * 1e6:.1f} us, "
                              f"float pair {res[key + ' float'] * 1e6:.1f} us, float/vnni {res[key + ' ratio']:.3f} "
                              f"(L1 {res[key + ' L1 ratio']:.3f}); within bound {res[key + ' ok']}; bound/transfer's "
                              f"{res[key + ' vs transfer']:.2f}; output err {res[key + ' out err']:.1e} "
                              f"(truncation {res['trunc']:.1e}); load {os.getloadavg()[0]:.1f}", flush=True)
                print(f"[madd_micro vnni] {size} {light} N={res['N']}: kernel call {res['call'] * 1e6:.1f} us, of read "
                      f"{res['of_read']:.2f}, dense alone {res['dense_call'] * 1e6:.1f} us, set-up+output "
                      f"{res['fixed'] * 1e6:.1f} us", flush=True)
                rows.append(res)
        loads.append(os.getloadavg()[0])
        protos += [dict(r, size=size, V=rl.V) for r in proto_rows(rl, fac, args)]
    write_vnni(rows, floors, ghz, loads, args, protos)


def kernel_dense_order(rl, li: torch.Tensor, lv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The light's dense terms in the order ``kernels/wavelet.c`` lists them (the order the DENSE_VNNI prototype's
    groups follow): ``ds`` int64 [nd] slots, ``lw`` float32 [nd, 3] their light. Few terms (N <= SMALL_N = 256 and
    N < P - Pd): the light's own order; else column order (the AVX-512 build's listing, LIST_TERMS: the marks scanned
    by column — the only build with the VNNI loop; slot order, ``dense_terms``, where the relighter's ``dense_order`` is
    'column', its default)."""
    d = rl.dslot[li] >= 0
    if li.numel() <= 256 and li.numel() < rl.P - rl.Pd:
        return rl.dslot[li[d]].long().contiguous(), lv[:, d].T.float().contiguous()
    order = torch.argsort(li[d])
    return rl.dslot[li[d]].long()[order].contiguous(), lv[:, d].T.float()[order].contiguous()


def vnni_bound(rl, li: torch.Tensor, lv: torch.Tensor, fac: torch.Tensor | None = None, albedo: bool = True,
               groups=None) -> dict:
    """The VNNI dense loop's stated error bound for one call on ``rl``'s layout (a 16-bit grey transfer, the light
    ``li`` int64 [N], ``lv`` float32 [3, N]), per vertex and channel, float64 [V, 3], from quantities found here
    independently of the kernel: the light's dense terms in the kernel's order (:func:`kernel_dense_order`), each dense
    column's largest stored magnitude by brute force over ``rl.dense`` (not the layout's ``dtmax``), the groups' steps
    s_g by :func:`quantise_light`'s column-maximum rule in the kernel's flush groups (:func:`kernel_groups`: chunks of 16
    terms merged within 1.25 x the 16-term groups' column-max bound, grp17's rule; with :data:`VNNI_L2` the L2 rule on the
    columns' norms by brute force, :func:`dense_norms`); ``fac`` [V, 3] the factor (default the
    relighter's, ``_factor(3, albedo)``; ``albedo``: the output with the albedo applied, as the call's; ``groups``: each
    term's group int64 [nd] or a group size instead of the kernel's). Returns
    ``bound`` f_v Σ_g (s_g,c / 2) Σ_{k∈g} |T_v,k| (the dense terms' quantised light), ``slack`` 1e-5 f_v Σ_k
    |T_v,k| |L_k,c| over all N terms (float32 rounding of the whole call, dense and sparse: ~100 roundings of 6e-8
    each at most), ``tbound`` the transfer's own 16-bit quantisation bound for the same dense terms
    f_v Σ_k |L_k,c| / 2, ``nd`` the dense terms and ``groups``; per channel float64 [3]: ``l2`` the output's L2 error
    bound over the vertices Σ_g (s_g,c / 2) Σ_{k∈g} ||f_c ⊙ T_:,k||_2, ``l2_transfer`` the transfer's own in the same
    terms ||f_c||_2 Σ_k |L_k,c| / 2, ``slack_l2`` the rounding slack's L2 norm; ``guard`` whether the kernel's per-call
    guard sends the call to the float loop with these groups (:func:`vnni_guard` on the brute-force norms: then the
    call's output is the float loop's, ``bound`` does not apply) and ``guard_ratio`` its ratio."""
    if fac is None:
        fac = rl._factor(3, albedo).double()
    nb = rl.dense.shape[0]
    d16 = rl.dense.reshape(nb, rl.Pd, 32)
    ds, lw = kernel_dense_order(rl, li, lv)
    tmax = d16.to(torch.int32).abs().amax(dim=(0, 2))  # [Pd] brute force
    nrm, ns = dense_norms(rl)  # [Pd] brute force
    if groups is None:
        groups = kernel_groups(lw, tmax[ds], nrm[ds], ns) if ds.numel() else 16
    _, sc, grp = quantise_light(lw, groups, tmax[ds])
    trips, gratio = vnni_guard(lw, grp, tmax[ds], nrm[ds], ns) if ds.numel() else (False, 0.0)
    tk = d16[:, ds, :].double().abs()  # [nb, nd, 32] |T_v,k| over the dense terms
    bound = torch.einsum("bkv,kc->bvc", tk, sc.double()[grp] / 2).reshape(-1, 3)[:rl.V] * fac
    ref_index, ref_vals = rl.reference_rows(0, rl.V)  # dequantised: the scale applied, so times the albedo only
    from prt_torch import relight

    mag = relight.wavelet_dense(ref_vals.double().abs(), ref_index, li, lv.double().abs(), rl.P)
    if albedo:
        mag = mag * rl.albedo[:, :3].double()
    # the L2 bound over the vertices per channel (triangle inequality over the columns) and the transfer's own
    tf = torch.stack([(d16[:, ds, :].double().permute(1, 0, 2).reshape(ds.numel(), -1)[:, :rl.V] * fac[:, c]).norm(dim=1)
                      for c in range(3)], 1)  # [nd, 3] ||f_c (.) T_:,k||
    return {"bound": bound, "slack": 1e-5 * mag, "tbound": lw.double().abs().sum(0)[None, :] / 2 * fac, "nd": int(ds.numel()),
            "groups": int(grp[-1]) + 1 if ds.numel() else 0, "l2": (sc.double()[grp] / 2 * tf).sum(0),
            "l2_transfer": fac.norm(dim=0) * lw.double().abs().sum(0) / 2, "slack_l2": 1e-5 * mag.norm(dim=0),
            "guard": trips, "guard_ratio": gratio}


def proto_rows(rl, fac: torch.Tensor, args) -> list:
    """The VNNI dense loop, the default of ``kernels/wavelet.c``'s AVX-512 build on a CPU with AVX-512 VNNI (the W16
    dense loop on ``vpdpwssd``, the light quantised per call by the column-maximum rule in groups of 16 dense terms, on
    the layout's column maxima), against the opt-out (``WaveletRelighter(arith='float')``: the call's C | FDENSE, the
    float loop) on ``rl``'s layout, the same library (this process's build), the whole call paired by one thread's CPU
    time, each against its streaming-read bound; both outputs against the float64 reference of the same stored values
    (``relight.wavelet_dense`` of ``reference_rows``, times the albedo), the default within its stated bound per vertex
    (:func:`vnni_bound`), beside the transfer's own 16-bit quantisation bound for the same dense terms."""
    from bench_wavelet import rel
    from bench_wavelet_isa import bound_call

    from prt_torch import relight

    lib = relight._wavelet_lib()
    path = relight.wavelet_kernel_path()
    if lib is None or not path.get("vnni"):
        raise SystemExit(f"bench_wavelet_madd_micro.py --vnni --proto: this process's wavelet build has no VNNI dense loop "
                         f"({path.get('path')}, PRT_TORCH_KERNEL_ISA {path.get('isa_choice')!r}); accepted: the native or "
                         "avx512 build on a CPU with AVX-512 VNNI")
    ref_index, ref_vals = rl.reference_rows(0, rl.V)
    alb = rl.albedo[:, :3].double()
    out = []
    for light in ("studio", "sky (sun)"):
        li_a, lv_a, _ = rl.light(LIGHTS[light], rl.P, "transport")
        o_all = torch.empty(rl.V, 3)
        bound_call(rl, lib, li_a, lv_a.float().contiguous(), o_all, 1, True, flags=rl.FDENSE)()
        out_all = o_all.double()
        for N in args.terms:
            N = min(N, rl.P)
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            lv = lv.float().contiguous()
            o_b, o_v = torch.empty(rl.V, 3), torch.empty(rl.V, 3)
            rl.prepared(li, lv, o_b)()  # builds the row-major copy where the light needs it
            f_b = bound_call(rl, lib, li, lv, o_b, 1, True, flags=rl.FDENSE)
            f_v = bound_call(rl, lib, li, lv, o_v, 1, True)
            f_b(), f_v()
            exact = relight.wavelet_dense(ref_vals.double(), ref_index, li, lv.double(), rl.P) * alb
            b = vnni_bound(rl, li, lv, fac)
            ok = bool(((o_v.double() - exact).abs() <= b["bound"] + b["slack"]).all())
            p = measure_paired(f_v, f_b, repeats=15, warmup=1, clock=time.thread_time)
            read = read_bound_fn(rl.bytes_read(li), rl.V * 12)
            rv = measure_paired(f_v, read, repeats=15, warmup=1, clock=time.thread_time)
            rb = measure_paired(f_b, read, repeats=15, warmup=1, clock=time.thread_time)
            en = exact.norm()
            r = {"light": light, "N": "all" if N == rl.P else N, "nd": b["nd"], "groups": b["groups"],
                 "vnni": p.test.median, "float": p.peer.median, "ratio": p.speedup, "q": [p.ratio.q1, p.ratio.q3],
                 "of_read": rv.speedup, "of_read_float": rb.speedup, "err": rel(o_v, exact), "err_float": rel(o_b, exact),
                 "bound": float(b["bound"].norm() / en), "tbound": float(b["tbound"].norm() / en),
                 "trunc": rel(o_b, out_all), "ok": ok, "load": os.getloadavg()[0], "dense": path["dense"]}
            print(f"[madd_micro vnni] default {light} N={r['N']}: vnni {r['vnni'] * 1e6:.1f} us, float {r['float'] * 1e6:.1f} us, "
                  f"float/vnni {r['ratio']:.3f}; of read {r['of_read_float']:.2f} -> {r['of_read']:.2f}; err {r['err']:.1e} "
                  f"(float {r['err_float']:.1e}, bound {r['bound']:.1e}, transfer's {r['tbound']:.1e}, truncation "
                  f"{r['trunc']:.1e}), within bound {ok}; load {r['load']:.1f}", flush=True)
            out.append(r)
    return out


def group_rows(size: str, terms) -> list:
    """The flush groups and the error they carry per row (``--vnni --groups-table``): on the blocker scene at ``size``
    (R = 32, K = 256, 16-bit; the default relighter, so the VNNI loop of this process's build), studio and sky at each N
    of ``terms`` and all, the groups of fixed 16-term chunks, of grp17's column-maximum rule (:func:`vnni_groups`
    without norms: the kernel's default) and of vnb18's L2 rule (``-DVNNI_L2=1``; with brute-force norms,
    :func:`dense_norms`); per grouping the stated
    bound as a fraction of the transfer's own 16-bit bound, per vertex in rel. L2 (``vnni_bound``'s ``bound`` against
    ``tbound``, over V x 3) and in the L2 terms the rule uses (``l2`` against ``l2_transfer``, the largest channel); the
    default call's error (rel. L2 against the float64 sum of the same stored values), every vertex within the per-vertex
    bound and the L2 error within the L2 bound (per channel), for the kernel's groups; and the per-call guard's ratio
    (:func:`vnni_guard`: above 1 the call takes the float loop)."""
    from bench_wavelet import kernel_transfer

    from prt_torch import relight

    rl = relight.WaveletRelighter(kernel_transfer(size), threads=1, layouts="column")
    if not rl._takes_vnni(*rl.light(LIGHTS["studio"], 300, "transport")[:2]):
        raise SystemExit("bench_wavelet_madd_micro.py --groups-table: this process's wavelet build has no VNNI dense loop; "
                         "accepted: the native or avx512 build on a CPU with AVX-512 VNNI")
    nb = rl.dense.shape[0]
    tmax = rl.dense.reshape(nb, rl.Pd, 32).to(torch.int32).abs().amax(dim=(0, 2))
    nrm, ns = dense_norms(rl)
    ref_index, ref_vals = rl.reference_rows(0, rl.V)
    rows = []
    for light in ("studio", "sky (sun)"):
        for N in tuple(terms) + (rl.P,):
            li, lv, _ = rl.light(LIGHTS[light], min(N, rl.P), "transport")
            lv = lv.float().contiguous()
            ds, lw = kernel_dense_order(rl, li, lv)
            exact = relight.wavelet_dense(ref_vals.double(), ref_index, li, lv.double(), rl.P) * rl.albedo[:, :3].double()
            out = rl(li, lv).double()
            r = {"size": size, "V": rl.V, "light": light, "N": "all" if N >= rl.P else N, "nd": int(ds.numel()),
                 "err": float((out - exact).norm() / exact.norm())}
            for name, g in (("16", 16), ("cm", vnni_groups(lw, tmax[ds])),
                            ("l2", vnni_groups(lw, tmax[ds], norms=nrm[ds], nscale=ns))):
                b = vnni_bound(rl, li, lv, groups=g)
                r[name] = {"groups": b["groups"], "pv": float(b["bound"].norm() / b["tbound"].norm()),
                           "l2": float((b["l2"] / b["l2_transfer"]).max())}
                if name == ("l2" if VNNI_L2 else "cm"):  # the kernel's groups: its output within their bounds
                    r["within"] = bool(((out - exact).abs() <= b["bound"] + b["slack"]).all())
                    r["within_l2"] = bool(((out - exact).norm(dim=0) <= b["l2"] + b["slack_l2"]).all())
                    r["guard"], r["guard_ratio"] = b["guard"], b["guard_ratio"]  # the per-call guard (vg18)
            print(f"[groups] {size} {light} N={r['N']} nd={r['nd']}: groups 16 / cm / l2 {r['16']['groups']} / "
                  f"{r['cm']['groups']} / {r['l2']['groups']}, bound of the transfer's (per vertex) {r['16']['pv']:.2f} / "
                  f"{r['cm']['pv']:.2f} / {r['l2']['pv']:.2f}, (L2) {r['16']['l2']:.2f} / {r['cm']['l2']:.2f} / "
                  f"{r['l2']['l2']:.2f}; err {r['err']:.1e}; within {r['within']} / {r['within_l2']}; guard "
                  f"{r['guard_ratio']:.2f}{' (float loop)' if r['guard'] else ''}", flush=True)
            rows.append(r)
    return rows


def write_groups(rows: list, loads: list, args) -> None:
    """``--groups-table``'s report: reports/benchmarks/wavelet_vnni_l2groups_error.md (and .json)."""
    import json

    L = ["# Wavelet kernel: the VNNI loop's flush groups and the error they carry (issue 39)", "",
         f"{cpu_label()}; load average {min(loads):.1f}-{max(loads):.1f}. Blocker scene (occluder_over_plane, R = 32, "
         "K = 256, 16-bit grey transfer, albedo 0.8), studio and sky, transport-weighted terms, RGB, the default "
         "relighter (this process's wavelet build: the VNNI dense loop, VNNI_RHO "
         f"{VNNI_RHO}, VNNI_BETA {VNNI_BETA}). Per row the groups of fixed 16-term chunks, of grp17's column-maximum rule "
         "(`cm`: the kernel's default since vg18) and of vnb18's L2 rule (`l2`, `-DVNNI_L2=1`: chunks merged while the "
         "call's L2 bound stays within max(1.25 x the "
         "16-term groups', VNNI_BETA x the transfer's own 16-bit bound)), recomputed by `vnni_groups` from brute-force "
         "column maxima and norms; the stated bound as a fraction of the transfer's own 16-bit bound, **per vertex** "
         "(rel. L2 over V x 3 of `vnni_bound`'s f_v Σ_g (s_g,c / 2) Σ_{k∈g} |T_v,k| against f_v Σ_k |L_k,c| / 2: the "
         "figure the VNNI default rests on) and **L2** (the rule's own terms: Σ_g (s_g,c / 2) Σ_{k∈g} ||f_c ⊙ T_:,k||_2 "
         "against ||f_c||_2 Σ_k |L_k,c| / 2, the largest channel); the default call's error (rel. L2 against the "
         "float64 sum of the same stored values, `relight.wavelet_dense` of `reference_rows` times the albedo); "
         "*within* (the kernel's groups): every vertex within the per-vertex bound / every channel's L2 error within "
         "the L2 bound; *guard*: the per-call guard's ratio (`vnni_guard`; above 1: the float loop, the bounds moot). "
         f"Reproduce: `.venv/bin/python benchmarks/bench_wavelet_madd_micro.py --vnni --groups-table --sizes "
         f"{' '.join(args.sizes)}`.", "",
         "| size | light | N | dense terms | groups 16 / cm / **l2** | bound / transfer's, per vertex: 16 / cm / **l2** | "
         "L2: 16 / cm / **l2** | error (rel. L2) | within | guard |", "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['size']} | {r['light']} | {r['N']} | {r['nd']} | {r['16']['groups']} / {r['cm']['groups']} / "
                 f"**{r['l2']['groups']}** | {r['16']['pv']:.2f} / {r['cm']['pv']:.2f} / **{r['l2']['pv']:.2f}** | "
                 f"{r['16']['l2']:.2f} / {r['cm']['l2']:.2f} / **{r['l2']['l2']:.2f}** | {r['err']:.1e} | "
                 f"{'✓' if r['within'] else '✗'} / {'✓' if r['within_l2'] else '✗'} | {r['guard_ratio']:.2f}"
                 f"{' float' if r['guard'] else ''} |")
    path = OUT / "wavelet_vnni_l2groups_error.md"
    atomic_write_text(path, "\n".join(L) + "\n")
    atomic_write_text(path.with_suffix(".json"), json.dumps(rows, indent=1))
    print(f"[groups] wrote {path}")


def hdr_lights(rl, N: int = 300) -> dict:
    """Two high-dynamic-range lights as (indices [N'], values [3, N'] float32, sun-only values or None): the sky with a
    sun — one cube texel, in the direction (0.3, 0.2, 1) over the blocker, at 1e4 x the sky's mean radiance — cut to
    its N most important terms (transport-weighted), and the sky's N terms with one dense term in the middle of the
    first group of 16 (in the kernel's order) scaled by 1e4 (one huge term among small ones: the group's step is
    set by it)."""
    from prt_torch.lighting.haar import cube_geometry, cube_light, haar2d, select_terms

    sky, _ = cube_light("sky", rl.res)  # [3, 6, R, R] float64
    d, _ = cube_geometry(rl.res)
    s = torch.tensor([0.3, 0.2, 1.0], dtype=torch.float64)
    t = int((d.reshape(-1, 3) @ (s / s.norm())).argmax())
    sun = torch.zeros_like(sky).reshape(3, -1)
    sun[:, t] = 1e4 * float(sky.mean())
    sun = sun.reshape(sky.shape)
    H = haar2d(sky + sun).reshape(3, -1)
    li, lv = select_terms(H, N, "transport", rl.weights)
    Hs = haar2d(sun).reshape(3, -1)
    out = {"sky + sun 1e4": (li, lv.float().contiguous(), Hs[:, li].float().contiguous())}
    li2, lv2, _ = rl.light("sky", N, "transport")
    lv2 = lv2.float().clone()
    ds = rl.dslot[li2]
    dense_pos = torch.nonzero(ds >= 0).flatten()
    if N > 256 or N >= rl.P - rl.Pd:  # the kernel's order: slot order
        dense_pos = dense_pos[torch.argsort(ds[dense_pos])]
    k = int(dense_pos[min(5, dense_pos.numel() - 1)])
    lv2[:, k] *= 1e4
    out["one term x 1e4"] = (li2, lv2.contiguous(), None)
    return out


def pervertex_rows(size: str, args) -> list:
    """The VNNI default's error per vertex (``--pervertex``): on the kernel section's transfer at ``size`` (R = 32,
    K = 256, 16-bit) and the same precompute stored as float32 (bits 32: the stored transfer's own error beside it),
    under studio and sky at N = 100 and all, and :func:`hdr_lights`, the relative error per vertex (norm over channels
    over the float64 gather of the same stored values, vertices above 1e-3 of the brightest; for the sun light also
    the vertices the sun does not reach, its own contribution under 1e-3 of its largest) of the default, the opt-out
    and the stored 16-bit transfer against the float32 one."""
    from bench_wavelet import kernel_transfer

    from prt_torch import relight
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions
    from prt_torch.transfer.wavelet import precompute_wavelet

    tr16 = kernel_transfer(size)
    tr32 = precompute_wavelet(builtin("occluder_over_plane", size), 32, 256, 32, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr16, threads=1, layouts="column")
    fl = relight.WaveletRelighter(tr16, threads=1, layouts="column", arith="float")
    r32 = relight.WaveletRelighter(tr32, threads=1, layouts="column")
    idx16, vals16 = rl.reference_rows(0, rl.V)
    idx32, vals32 = r32.reference_rows(0, r32.V)
    alb = rl.albedo[:, :3].double()

    def exact(idx, vals, li, lv):
        return relight.wavelet_dense(vals.double(), idx, li, lv.double(), rl.P) * alb

    lights = {}
    for name in ("studio", "sky (sun)"):
        for N in (100, rl.P):
            li, lv, _ = rl.light(LIGHTS[name], N, "transport")
            lights[f"{name}, N = {'all' if N == rl.P else N}"] = (li, lv.float().contiguous(), None)
    lights.update({f"{k}, N = 300": v for k, v in hdr_lights(rl).items()})
    rows = []
    for name, (li, lv, sun) in lights.items():
        out, opt = rl(li, lv).double(), fl(li, lv).double()
        ex, e32 = exact(idx16, vals16, li, lv), exact(idx32, vals32, li, lv)
        n = ex.norm(dim=1)
        masks = {"above 1e-3 of the brightest": n > 1e-3 * n.max()}
        if sun is not None:
            s = exact(idx16, vals16, li, sun).norm(dim=1)
            masks["sun-shadowed"] = (s <= 1e-3 * s.max()) & (n > 0)
        for what, m in masks.items():
            def q(x, m=m):
                r = x.norm(dim=1)[m] / n[m]
                return [float(r.median()), float(r.quantile(0.99)), float(r.max())]
            rows.append({"size": size, "V": rl.V, "light": name, "vertices": what, "count": int(m.sum()),
                         "vnni": q(out - ex), "float": q(opt - ex), "stored": q(ex - e32),
                         "bound": q(vnni_bound(rl, li, lv)["bound"]), "takes_vnni": rl._takes_vnni(li, lv)})
            r = rows[-1]
            print(f"[madd_micro vnni] per vertex {size} {name} ({what}, {r['count']}): vnni {r['vnni'][0]:.1e} / "
                  f"{r['vnni'][2]:.1e}, float {r['float'][0]:.1e} / {r['float'][2]:.1e}, stored 16-bit {r['stored'][0]:.1e} / "
                  f"{r['stored'][2]:.1e} (median / max)", flush=True)
    return rows


def write_pervertex(rows: list, loads: list, args) -> None:
    """reports/benchmarks/wavelet_vnni_pervertex.md (+ .json): :func:`pervertex_rows`."""
    from bench_wavelet_isa import emit_report

    from prt_torch import relight

    path = relight.wavelet_kernel_path()
    L = ["# Wavelet kernel: the VNNI default's error per vertex (issue 39)\n",
         f"{cpu_label()}; build: {path.get('path')} (dense {path.get('dense')}); load {' → '.join(f'{x:.1f}' for x in loads)}. "
         f"Reproduce: `.venv/bin/python benchmarks/bench_wavelet_madd_micro.py --vnni --pervertex --sizes {' '.join(args.sizes)}`.\n",
         "Blocker scene, R = 32, K = 256; the relighter's default (**vnni**: the int16 VNNI dense loop where the call "
         "takes it), its opt-out (**float**, `arith='float'`), each against the float64 gather of the same stored "
         "16-bit values; **stored**: that float64 gather against the same precompute stored as float32 (bits 32), the "
         "error the stored transfer already carries; **bound**: the VNNI loop's stated bound (`vnni_bound`). Relative "
         "error per vertex (norm over RGB / the vertex's norm), median / 99th percentile / max over the vertices named. "
         "Lights: transport-weighted terms; *sky + sun 1e4*: one cube texel toward (0.3, 0.2, 1) at 1e4× the sky's "
         "mean radiance added to the sky; *one term x 1e4*: the sky's N terms with the 6th dense term (kernel order) "
         "× 1e4 (`hdr_lights`).\n",
         "| size (V) | light | vertices | count | vnni | float | stored | bound |", "|---|---|---|---|---|---|---|---|"]
    f = lambda x: " / ".join(f"{v:.1e}" for v in x)  # noqa: E731
    for r in rows:
        L.append(f"| {r['size']} ({r['V']}) | {r['light']} | {r['vertices']} | {r['count']} | {f(r['vnni'])} | "
                 f"{f(r['float'])} | {f(r['stored'])} | {f(r['bound'])} |")
    emit_report(str(OUT / "wavelet_vnni_pervertex.md"), "\n".join(L) + "\n", "madd_micro vnni", {"rows": rows, "loads": loads})


def write_proto(protos: list, loads: list, args) -> None:
    """reports/benchmarks/wavelet_vnni_default.md: the VNNI default's whole-call rows against the opt-out (``--vnni
    --proto``; the prototype's report before it became the default: wavelet_vnni_proto.md)."""
    from bench_wavelet_isa import emit_report

    from prt_torch import relight

    path = relight.wavelet_kernel_path()
    L = ["# Wavelet kernel: the VNNI dense loop by default against the opt-out, the whole call (issue 39)\n",
         f"{cpu_label()}, one thread, this thread's CPU time (`time.thread_time`; the others' load does not enter it); "
         f"load average {' → '.join(f'{x:.1f}' for x in loads)} (shared machine). Blocker scene `occluder_over_plane`, "
         "R = 32, K = 256, 16-bit values, CT = 1, RGB light (CO = 3), transport-weighted terms. Reproduce: "
         f"`.venv/bin/python benchmarks/bench_wavelet_madd_micro.py --vnni --proto --sizes {' '.join(args.sizes)} "
         f"--terms {' '.join(map(str, args.terms))}`.\n",
         f"`kernels/wavelet.c` as this process builds it ({path.get('path')}; flags `{path.get('flags')}`), one library "
         "bound to one layout (`bench_wavelet_isa.bound_call`, the per-vertex factor), called two ways: **vnni** the "
         "default (the W16 dense loop on `vpdpwssd`; the dense light quantised per call by the *column-maximum rule* in "
         "groups of 16 dense terms — Σ_k tmax_k |Lq_k| ≤ 2³¹ − 1 per group and channel, tmax the layout's per-column "
         "largest stored magnitude — and one flush per group: int32 → float, times the group's scale, added), "
         "**float** the opt-out (`WaveletRelighter(arith='float')`: C | FDENSE, the float loop's bits), paired by one "
         "thread's CPU time (15 repeats; **float / vnni** > 1: the default faster [quartiles]), each against the "
         "streaming read (`read_bound_fn` of the bytes the call reads plus the output: section 7's criterion; each "
         "fraction from its own pairing). "
         "Errors, relative L2 over vertices and channels against the **float64 reference** of the same stored values "
         "(`relight.wavelet_dense` of `reference_rows`, times the albedo): *err vnni*, *err float* (the opt-out: "
         "float32 rounding only), *bound* the stated bound f_v Σ_g (s_g/2) Σ_{k∈g} |T_v,k| "
         "(`vnni_bound`: `quantise_light`'s scales on brute-force column maxima; every vertex within it, float "
         "rounding slack included: ✓), *transfer's* the transfer's own 16-bit "
         "quantisation bound for the same dense terms f_v Σ_k |L_k| / 2, *truncation* the opt-out's output at N "
         "against all terms.\n",
         "| size (V) | light | N | dense terms (groups) | vnni µs | float µs | **float / vnni** [quartiles] | of read: "
         "float → **vnni** | err vnni | err float | bound | transfer's | truncation | within | load |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in protos:
        L.append(f"| {r['size']} ({r['V']}) | {r['light']} | {r['N']} | {r['nd']} ({r['groups']}) | {r['vnni'] * 1e6:.1f} | "
                 f"{r['float'] * 1e6:.1f} | **{r['ratio']:.2f}** [{r['q'][0]:.2f}, {r['q'][1]:.2f}] | "
                 f"{r['of_read_float']:.2f} → **{r['of_read']:.2f}** | {r['err']:.1e} | {r['err_float']:.1e} | "
                 f"{r['bound']:.1e} | {r['tbound']:.1e} | {r['trunc']:.1e} | {'✓' if r['ok'] else '✗'} | {r['load']:.1f} |")
    emit_report(str(OUT / "wavelet_vnni_default.md"), "\n".join(L) + "\n", "madd_micro vnni", {"rows": protos, "loads": loads})


def write_vnni(rows: list, floors: dict, ghz: float, loads: list, args, protos: list) -> None:
    """reports/benchmarks/wavelet_madd_micro_vnni.md from :func:`vnni_main`'s rows."""
    m = machine_info()
    best = "vnni, 2 blocks G" + "all, column max"
    L = ["# Wavelet kernel: the dense part with AVX-512 VNNI integer dot products (issue 39)\n",
         f"{cpu_label()} at {ghz:.2f} GHz (a chain of dependent multiplies, the fastest of five; the zmm loops may run "
         f"slower, so their cycles are over-counted by a few %), one thread, `-O3 -march=native`; load average "
         f"{' → '.join(f'{x:.1f}' for x in loads)} (shared machine; this thread's CPU time, which the others' load does "
         "not enter). The kernel section's transfer (occluder_over_plane, R = 32, K = 256, 16-bit, CT = 1), RGB light "
         "(CO = 3), transport-weighted terms. Reproduce: `.venv/bin/python benchmarks/bench_wavelet_madd_micro.py --vnni"
         + (f" --sizes {' '.join(args.sizes)}" if args.sizes != ["small"] else "") + "`.\n",
         "**The loops** (`bench_wavelet_madd_micro.py`'s `vnni_pass`, sums stored per block, no output): per pair of "
         "dense terms (a, b) and 32-vertex block the two 64-byte rows interleaved by `vpunpcklwd`/`vpunpckhwd` (zmm), "
         "one `vpdpwssd zmm` per interleaving and channel with the broadcast pair light (Lq_a[c], Lq_b[c]): 6 int32 sums "
         "per block; per scale group converted, scaled, added to float sums; the vertex order restored once per block. "
         "`2 blocks`: blocks 2i and 2i + 1 in lockstep as the kernel's W16 loop (the pair's offsets and broadcasts "
         "shared); the prefetch PF = 6 terms ahead in each block as the peer's. **The peer**: the kernel's 16-lane float "
         "loop, two blocks in lockstep (`bench_wavelet_dense16_micro.py`'s `dense16_pass` mode 1, the W16 pair: per "
         "term and block 2 widening loads, 2 conversions, 6 FMAs), the same terms, paired by this thread's CPU time "
         "(median of 15 samples of several passes over every block; **float / vnni** > 1: VNNI faster, [quartiles]); "
         "cycles per (dense term, 32-vertex block) at the measured clock. `L1`: every block reads the first block's (or "
         "pair's) values. The light: int16 per group and channel by `quantise_light`'s column-maximum rule (Σ_k "
         "tmax_k |Lq_k| ≤ 2³¹ − 1: no int32 sum overflows for the stored values), G `all` one group, `16` groups of 16 "
         "consecutive dense terms.\n",
         "**Errors**: *rel. err* the median over vertices and channels of |vnni − exact| / |exact| of the dense sums "
         "(exact: float64 sums of the same stored values; every vertex within the stated bound Σ_g (s_g/2) "
         "Σ_{k∈g} |T_v,k|: ✓); *bound / transfer's*: the median of that bound over the transfer's own 16-bit "
         "quantisation bound for the same terms, Σ_k |L_k| / 2 (stored units); *output err*: the relative L2 over "
         "vertices and channels of the dense sums' error × the per-vertex factor against the kernel's output at this N "
         "(bench_wavelet's `rel`), beside the same of the two bounds and the **N-term truncation error** (the kernel's "
         "output at N against all terms, relative L2).\n",
         "## The instruction mixes alone (asm, data in L1, min of 9 × 2M iterations)\n",
         "| mix | cycles per iteration | per (term, 32-vertex block) |", "|---|---|---|"]
    L += [f"| {k} | {v:.2f} | {f'{v / 4:.2f}' if k.startswith('VNNI') else ''} |" for k, v in floors.items()]
    L += ["", "The kernel's float term alone (`bench_wavelet_dense16_micro.py`, the W16 term: 3 broadcasts, 2 widening "
          "loads, 2 conversions, 6 FMAs): 5.7-5.8 cycles per (term, block) at the same clock (the kernel's header).", "",
          "## The loops on the real layout\n",
          "| size (V) | light | N | dense terms | variant | G | vnni µs | float pair µs | cycles/(term, block) vnni / float | "
          "**float / vnni** [quartiles] | L1: **float / vnni** | rel. err | bound / transfer's | output err | output bound "
          "| transfer's output bound | truncation err | within bound |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for v in VNNI:
            for G in ("all, column max", "16, column max"):
                k = f"{v} G{G}"
                cv, cf = (r[k] * 1e9 * ghz / r["tb"], r[k + " float"] * 1e9 * ghz / r["tb"]) if r["tb"] else (0, 0)
                L.append(f"| {r['size']} ({r['V']}) | {r['light']} | {r['N']} | {r['nd']} | {v} | {G.split(',')[0]} | "
                         f"{r[k] * 1e6:.1f} | {r[k + ' float'] * 1e6:.1f} | {cv:.2f} / {cf:.2f} | **{r[k + ' ratio']:.2f}** "
                         f"[{r[k + ' q'][0]:.2f}, {r[k + ' q'][1]:.2f}] | **{r[k + ' L1 ratio']:.2f}** | {r[k + ' err']:.1e} | "
                         f"{r[k + ' vs transfer']:.2f} | {r[k + ' out err']:.1e} | {r[k + ' out bound']:.1e} | "
                         f"{r[k + ' out transfer bound']:.1e} | {r['trunc']:.1e} | {'✓' if r[k + ' ok'] else '✗'} |")
    L += ["", "## What the whole call would become\n",
          "The kernel itself on the same light (`WaveletRelighter.prepared`, this thread's CPU time, 15 paired repeats): "
          "the whole call against its streaming-read bound (`timing.read_bound_fn` of `bytes_read` plus the output: "
          "section 7's criterion), its dense terms alone against the set-up and output alone (a one-term call of a "
          "column no vertex keeps): *dense net* the difference, the dense loop's time in the call. **Estimate**: the call "
          f"with the dense net divided by the micro-benchmark's paired gain of `{best}` (the quantisation of the light "
          "per call not counted: a pass over the dense terms, ~1 µs), and its fraction of the same bound.\n",
          "| size | light | N | dense terms | call µs | of read | dense alone µs | set-up + output µs | dense net µs | "
          "kernel ns/(term, block) | vnni ns/(term, block) | gain (paired, micro) | **estimated call µs** | "
          "**estimated of read** |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        gain = r[best + " ratio"]
        net = max(r["dense_net"], 0.0)
        est = r["call"] - net + net / gain
        kn = net * 1e9 / r["tb"] if r["tb"] else 0.0
        vn = r[best] * 1e9 / r["tb"] if r["tb"] else 0.0
        L.append(f"| {r['size']} | {r['light']} | {r['N']} | {r['nd']} | {r['call'] * 1e6:.1f} | {r['of_read']:.2f} | "
                 f"{r['dense_call'] * 1e6:.1f} | {r['fixed'] * 1e6:.1f} | {net * 1e6:.1f} | {kn:.2f} | {vn:.2f} | "
                 f"{gain:.2f} | **{est * 1e6:.1f}** | **{r['read'] / est:.2f}** |")
    if protos:
        L += ["", "## The kernel prototype (`-DDENSE_VNNI`), the whole call\n",
              "`kernels/wavelet.c` built twice from the working tree with the wavelet library's flags (native: the W16 "
              "loop): **vnni** with `#define DENSE_VNNI` (the W16 dense loop on `vpdpwssd`, the light quantised per call "
              "by the *65535 rule*, one group, the float loop's prefetch), **float** the default; both bound to "
              "the layout (`bench_wavelet_isa.bound_call`, the per-vertex factor), paired by one thread's CPU time "
              "(15 repeats; **float / vnni** > 1: the prototype faster [quartiles]), each against the streaming read "
              "(`read_bound_fn`: section 7's criterion). *err*: relative L2 of vnni − float over the float output; "
              "*bound*: the same of the stated per-vertex bound f_v (s/2) Σ_k |T_v,k| (every vertex within it: ✓); "
              "*truncation*: the float output at N against all terms. Each fraction of the read comes from its own pairing "
              "(under load they move by ±0.1 between pairings, e.g. medium studio N = 10 0.99 → 0.82 against a paired "
              "1.16×): **float / vnni** is the paired figure.\n",
              "| size (V) | light | N | dense terms | vnni µs | float µs | **float / vnni** [quartiles] | of read: float → "
              "**vnni** | err | bound | truncation | within | load |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in protos:
            L.append(f"| {r['size']} ({r['V']}) | {r['light']} | {r['N']} | {r['nd']} | {r['vnni'] * 1e6:.1f} | {r['float'] * 1e6:.1f} | "
                     f"**{r['ratio']:.2f}** [{r['q'][0]:.2f}, {r['q'][1]:.2f}] | {r['of_read_float']:.2f} → "
                     f"**{r['of_read']:.2f}** | {r['err']:.1e} | {r['bound']:.1e} | {r['trunc']:.1e} | "
                     f"{'✓' if r['ok'] else '✗'} | {r['load']:.1f} |")
    OUT.mkdir(parents=True, exist_ok=True)
    path = OUT / "wavelet_madd_micro_vnni.md"
    atomic_write_text(path, "\n".join(L) + "\n")
    print(f"[madd_micro vnni] wrote {path} ({m['cpu']})", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vnni", action="store_true", help="the AVX-512 VNNI rows only (wavelet_madd_micro_vnni.md)")
    ap.add_argument("--proto", action="store_true", help="--vnni: the whole-call rows only "
                    "(the VNNI default against the opt-out: reports/benchmarks/wavelet_vnni_default.md)")
    ap.add_argument("--pervertex", action="store_true", help="--vnni: the default's error per vertex beside the opt-out's "
                    "and the stored transfer's own, incl. HDR lights (reports/benchmarks/wavelet_vnni_pervertex.md)")
    ap.add_argument("--groups-table", action="store_true", help="--vnni: the flush groups (16-term, grp17's column-max "
                    "rule, the kernel's L2 rule) and the error and bounds they carry per row "
                    "(reports/benchmarks/wavelet_vnni_l2groups_error.md)")
    ap.add_argument("--sizes", nargs="+", default=["small"], help="--vnni: the kernel section's sizes (small, medium, large)")
    ap.add_argument("--terms", type=int, nargs="+", default=[300, 1000, 6144])
    ap.add_argument("--grey", nargs="*", default=["cap 20°", "cap 40°"], choices=list(LIGHTS),
                    help="lights relit grey (their first channel; CO = 1)")
    ap.add_argument("--pf", type=int, nargs="*", default=[12, 18, 24], help="the float loop's prefetch distances to pair")
    ap.add_argument("--groups", nargs="+", default=list(CONFIGS), choices=list(CONFIGS))
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--runs", type=int, default=2)
    ap.add_argument("--variants", nargs="+", default=[v for v in VARIANTS if v != "lean, no prefetch"], choices=VARIANTS)
    args = ap.parse_args()
    for size in args.sizes:
        size_choice(size, "bench_wavelet_madd_micro.py")
    if min(args.terms) < 1:
        raise SystemExit(f"bench_wavelet_madd_micro.py: --terms {' '.join(map(str, args.terms))}; accepted: integers >= 1")
    torch.set_num_threads(1)
    lib = build_library()
    if lib is None:
        raise SystemExit("bench_wavelet_madd_micro: no compiler")
    if args.vnni and args.groups_table:
        loads, rows = [os.getloadavg()[0]], []
        for size in args.sizes:
            rows += group_rows(size, (10, 30, 100, 300, 1000))
            loads.append(os.getloadavg()[0])
        write_groups(rows, loads, args)
        return
    if args.vnni and args.pervertex:
        loads, rows = [os.getloadavg()[0]], []
        for size in args.sizes:
            rows += pervertex_rows(size, args)
            loads.append(os.getloadavg()[0])
        write_pervertex(rows, loads, args)
        return
    if args.vnni and args.proto:
        loads, protos = [os.getloadavg()[0]], []
        for size in args.sizes:
            rl = blocker_dense(size)[0]
            protos += [dict(r, size=size, V=rl.V) for r in proto_rows(rl, rl._factor(3, True).double(), args)]
            loads.append(os.getloadavg()[0])
        write_proto(protos, loads, args)
        return
    if args.vnni:
        vnni_main(args, lib)
        return
    rl, nb, Pd, d16 = blocker_dense()
    tmax = d16.abs().amax(dim=(0, 2)).to(torch.int64)  # [Pd] each dense column's largest stored magnitude
    assert int(d16.abs().max()) <= 32767 and int(d16.min()) >= -32767, "stored values outside +-32767"
    pf_libs = {pf: float_pf_library(pf) for pf in args.pf}
    ghz = max(lib.clock_ghz() for _ in range(5))  # the least disturbed of five (the core is shared)
    loads = [os.getloadavg()[0]]
    floors = {}
    for what, label in enumerate(FLOORS):
        t = min(lib.floor_loop(what, 2_000_000) for _ in range(9))
        floors[label] = t * ghz * 1e9 / 2_000_000
        print(f"[madd_micro] floor {label}: {floors[label]:.2f} cycles", flush=True)
    rows, grey_rows = [], []
    for run in range(args.runs):
        for light in ("studio", "sky (sun)"):
            for N in args.terms:
                li, lv, _ = rl.light(LIGHTS[light], N, "transport")
                ds, lw = dense_terms(rl, li, lv)
                nd = ds.numel()
                sums = torch.zeros(nb, 3, 32)
                msums = torch.zeros(nb, 3, 32)
                lib.dense_pass(d16.data_ptr(), Pd * 32, ds.data_ptr(), nd, lw.data_ptr(), nb, 0, sums.data_ptr(), 1)
                ref = sums.clone()
                # the float64 dense sums of the stored values, for the bound
                tv = d16[:, ds, :].double()  # [nb, nd, 32]
                exact = torch.einsum("bkv,kc->bcv", tv, lw[:, :3].double())
                res = {"light": light, "N": N, "nd": nd, "tb": nd * nb, "run": run}
                for pf in args.pf:  # the float loop alone: a longer prefetch distance against the kernel's
                    pl = pf_libs[pf]
                    p = measure_paired(lambda pl=pl: pl.dense_pass(d16.data_ptr(), Pd * 32, ds.data_ptr(), nd, lw.data_ptr(), nb, 0,
                                                                   sums.data_ptr(), args.reps),
                                       lambda: lib.dense_pass(d16.data_ptr(), Pd * 32, ds.data_ptr(), nd, lw.data_ptr(), nb, 0,
                                                              sums.data_ptr(), args.reps),
                                       repeats=15, warmup=1, clock=time.thread_time)
                    res[f"pf{pf}"] = p.speedup
                    print(f"[madd_micro] run {run} {light} N={N} float loop, prefetch {pf} terms ahead: PF 6 / PF {pf} "
                          f"{p.speedup:.3f}", flush=True)
                for G in args.groups:
                    G2, use_tmax = CONFIGS[G]
                    q, s, grp = quantise_light(lw[:, :3], G2, tmax[ds] if use_tmax else None)
                    k = pack(ds, q, s, G2)
                    ng = k["ng"]
                    # the stated bound: sum_g (s_g / 2) sum_k |Tq_v,k|; the transfer's own 16-bit bound: sum_k |L_k| / 2
                    bound = torch.einsum("bkv,kc->bcv", tv.abs(), s.double()[grp] / 2)
                    tbound = lw[:, :3].double().abs().sum(0)[None, :, None] / 2

                    def mcall(variant, l1=False, reps=1, k=k):
                        return madd_call(lib, variant, d16, k, msums, l1, reps)

                    slack = 1e-6 * exact.abs() + 1e-6 * torch.einsum("bkv,kc->bcv", tv.abs(), lw[:, :3].double().abs())
                    res["float err"] = float((ref.double() - exact).abs().max())
                    for variant in args.variants:
                        if mcall(variant) != 0:
                            raise SystemExit("bench_wavelet_madd_micro: no AVX2 on this machine")
                        err = (msums.double() - exact).abs()
                        key0 = f"{variant} G{G}"
                        res[key0 + " ok"] = bool((err <= bound + slack).all())
                        res[key0 + " err"] = float((err / exact.abs().clamp_min(1e-30)).median())
                        res[key0 + " bound"] = float((bound / exact.abs().clamp_min(1e-30)).median())
                        res[key0 + " groups"] = ng
                        res[key0 + " vs transfer"] = float((bound / tbound).median())
                        for l1 in (False, True):
                            p = measure_paired(lambda x=l1, v=variant: mcall(v, x, args.reps),
                                               lambda x=l1: lib.dense_pass(d16.data_ptr(), 0 if x else Pd * 32, ds.data_ptr(),
                                                                           nd, lw.data_ptr(), nb, 0, sums.data_ptr(), args.reps),
                                               repeats=15, warmup=1, clock=time.thread_time)
                            key = key0 + (" L1" if l1 else "")
                            res[key + " float"] = p.peer.median / args.reps * 1e6
                            res[key] = p.test.median / args.reps * 1e6
                            res[key + " ratio"] = p.speedup
                            print(f"[madd_micro] run {run} {light} N={N} nd={nd} {key}: madd {res[key]:.1f} us, float "
                                  f"{res[key + ' float']:.1f} us, float/madd {p.speedup:.3f}; within bound "
                                  f"{res[key0 + ' ok']}", flush=True)
                rows.append(res)
        for light in args.grey:  # a grey light: one output channel (CO = 1)
            for N in args.terms:
                li, lv, _ = rl.light(LIGHTS[light], N, "transport")
                ds, lw = dense_terms(rl, li, lv[:1])
                nd = ds.numel()
                L1c = lw[:, 0].clone()
                gsum = torch.zeros(nb, 32)
                msum = torch.zeros(nb, 32)
                tv = d16[:, ds, :].double()
                exact = torch.einsum("bkv,k->bv", tv, L1c.double())
                res = {"light": light, "N": N, "nd": nd, "tb": nd * nb, "run": run}
                for G in ("all, column max", "16, column max"):
                    G2, _ = CONFIGS[G]
                    q, sc, grp = quantise_light(L1c[:, None].expand(nd, 3), G2, tmax[ds])
                    k = pack(ds, q, sc, G2)
                    bound = torch.einsum("bkv,k->bv", tv.abs(), sc.double()[grp, 0] / 2)
                    slack = 1e-6 * torch.einsum("bkv,k->bv", tv.abs(), L1c.double().abs()) + 1e-30

                    def gm(l1=False, reps=1, k=k):
                        return lib.grey_madd(d16.data_ptr(), 0 if l1 else Pd * 32, k["pob"].data_ptr(), k["lq"].data_ptr(),
                                             k["gp"].data_ptr(), k["ng"], k["gs"].data_ptr(), nb, msum.data_ptr(), reps)

                    def gf(l1=False, reps=1):
                        return lib.grey_float(d16.data_ptr(), 0 if l1 else Pd * 32, ds.data_ptr(), nd, lw.data_ptr(), nb,
                                              gsum.data_ptr(), reps)

                    if gm() != 0:
                        raise SystemExit("bench_wavelet_madd_micro: no AVX2 on this machine")
                    res[G + " ok"] = bool(((msum.double() - exact).abs() <= bound + slack).all())
                    res[G + " vs transfer"] = float((bound / (L1c.double().abs().sum() / 2)).median())
                    for l1 in (False, True):
                        p = measure_paired(lambda x=l1, f=gm: f(x, args.reps), lambda x=l1: gf(x, args.reps), repeats=15,
                                           warmup=1, clock=time.thread_time)
                        key = G + (" L1" if l1 else "")
                        res[key] = p.test.median / args.reps * 1e6
                        res[key + " float"] = p.peer.median / args.reps * 1e6
                        res[key + " ratio"] = p.speedup
                        print(f"[madd_micro] run {run} grey {light} N={N} nd={nd} {key}: madd {res[key]:.1f} us, float "
                              f"{res[key + ' float']:.1f} us, float/madd {p.speedup:.3f}; within bound {res[G + ' ok']}",
                              flush=True)
                grey_rows.append(res)
        loads.append(os.getloadavg()[0])
    m = machine_info()
    L = ["# Wavelet kernel: the dense part with integer multiply-adds (issue 39)\n",
         f"{m['cpu']} at {ghz:.2f} GHz (measured: a chain of dependent multiplies, the fastest of five), one thread, `-O3 -march=native` "
         f"(AVX2 path: `vpmaddwd`, this benchmark's own 8-lane code on every CPU; this CPU: {m.get('cpu_isa')});"
         f" load average {' → '.join(f'{x:.1f}' for x in loads)} "
         "(shared machine; this thread's CPU time). The kernel section's transfer "
         f"(V = {rl.V}, R = 32, K = 256, {BITS}-bit, {Pd} dense columns, {nb} blocks of 32 vertices); CT = 1, RGB. "
         "µs per pass over every block (sums stored, no output), the median of 15 paired samples of "
         f"{args.reps} passes against the float form (the kernel's dense loop) in the same run; **float / madd** > 1: "
         "the integer loop is faster; cycles per (term, 32-vertex block) at the measured clock. `L1`: every block "
         "reads the first block's values (the memory taken out). G: the light's scale groups — `all`: one group (one "
         "int32 -> float flush per block), `16`: groups of 16 consecutive dense terms; `65535 rule`: "
         "s_g = max(sum |L| / (65538 - n_g / 2), max |L| / 32767) (safe for any |T| <= 32767, rounding included: the "
         "brief's sum |L| / 65535 is not, by up to n_g / 2 in sum |Lq|), `column max`: "
         "s_g = max(sum tmax_k |L_k| / (2^31 - 1 - sum tmax_k / 2), max |L| / 32767) with tmax_k the dense column's "
         "largest stored magnitude (safe for the stored values). "
         "`bound / transfer's bound`: the median over vertices and channels of the stated bound over the transfer's own "
         "16-bit quantisation bound for the same terms, sum_k |L_k| / 2 (in stored units: each stored value is within "
         "half a step of the unquantised one). "
         "Error: the median over vertices and channels of |madd − exact| / |exact| and of the stated bound "
         "sum_g (s_g/2) sum_k |T_v,k| over |exact| (exact: float64 sums of the same stored values); every vertex within "
         "the bound: ✓. Reproduce: `.venv/bin/python benchmarks/bench_wavelet_madd_micro.py`.\n",
         "| run | light | N | dense terms | variant | G | groups | madd µs | float µs | cycles/term/block madd / float | "
         "**float / madd** | L1: **float / madd** | median rel. error | median rel. bound | bound / transfer's bound | within bound |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        for v in args.variants:
            for G in args.groups:
                k = f"{v} G{G}"
                cm = r[k] * 1e3 * ghz / r["tb"]
                cf = r[k + " float"] * 1e3 * ghz / r["tb"]
                L.append(f"| {r['run']} | {r['light']} | {r['N']} | {r['nd']} | {v} | {G} | {r[k + ' groups']} | {r[k]:.1f} | "
                         f"{r[k + ' float']:.1f} | {cm:.1f} / {cf:.1f} | **{r[k + ' ratio']:.2f}** | **{r[k + ' L1 ratio']:.2f}** | "
                         f"{r[k + ' err']:.1e} | {r[k + ' bound']:.1e} | {r[k + ' vs transfer']:.2f} | {'✓' if r[k + ' ok'] else '✗'} |")
    if grey_rows:
        L += ["", "A grey light (one output channel, CO = 1; the light's first channel): the kernel's float loop (per term 1 "
              "broadcast, 4 widening loads and conversions, 4 FMAs) against the integer loop (per pair 4 loads, 4 unpacks, "
              "4 `vpmaddwd`, 4 `vpaddd`; intrinsics, no spill), scale groups from the column maxima, paired the same way.", "",
              "| run | light | N | dense terms | G | madd µs | float µs | cycles/term/block madd / float | **float / madd** | "
              "L1: **float / madd** | bound / transfer's bound | within bound |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in grey_rows:
            for G in ("all, column max", "16, column max"):
                L.append(f"| {r['run']} | {r['light']} | {r['N']} | {r['nd']} | {G} | {r[G]:.1f} | {r[G + ' float']:.1f} | "
                         f"{r[G] * 1e3 * ghz / r['tb']:.1f} / {r[G + ' float'] * 1e3 * ghz / r['tb']:.1f} | "
                         f"**{r[G + ' ratio']:.2f}** | **{r[G + ' L1 ratio']:.2f}** | {r[G + ' vs transfer']:.2f} | "
                         f"{'✓' if r[G + ' ok'] else '✗'} |")
    if args.pf:
        L += ["", "The float loop alone (the kernel's form) with its prefetch further ahead than the kernel's 6 terms, paired "
              "against it in the same run (one thread CPU time, median of 15 × reps passes): **PF 6 / PF x** > 1: the longer "
              "distance is faster.", "",
              "| run | light | N | dense terms | " + " | ".join(f"**PF 6 / PF {pf}**" for pf in args.pf) + " |",
              "|---|---|---|---|" + "---|" * len(args.pf)]
        L += [f"| {r['run']} | {r['light']} | {r['N']} | {r['nd']} | " + " | ".join(f"{r[f'pf{pf}']:.3f}" for pf in args.pf)
              + " |" for r in rows]
    L += ["", "The loops' instruction mixes alone (x86-64 asm, data in L1, independent sums; min of 9 × 2M iterations, "
          "cycles per iteration at the measured clock): which operations share pipes on this CPU.", "",
          "| instruction mix | cycles |", "|---|---|"]
    L += [f"| {k} | {v:.2f} |" for k, v in floors.items()]
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_madd_micro.md", "\n".join(L) + "\n")
    print(f"[madd_micro] wrote {OUT / 'wavelet_madd_micro.md'}", flush=True)


if __name__ == "__main__":
    main()
