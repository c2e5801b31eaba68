"""Fused CPU kernels for relighting straight from the compressed forms (Sloan 2003 §6; Green 2005).

Per point p of cluster k = k(p) with weights w_p (n_k of them) and per-cluster constants
``T_k = [M_0^k l, M_1^k l, ...]`` (computed once per light by ``AffineCodec.cluster_constants``):

* rows:  ``e_p = T_k[0] + Σ_{i<n_k} w_p^i T_k[1+i]``                 (no view, ``[P, n_out·C]``)
* dense: ``o_p = Σ_r y_pr e_{p,r}``                                     (Sloan 2003 §3.1, ``[P, C]``)
* taps:  ``o_p = Σ_t g_pt e_{p,idx_pt}``                                (Lehtinen & Kautz 2003 eq. (13))

One pass over the codes (labels, weights, view), the constants table staying in cache: the
view is folded in per point before anything of size n_out·C leaves the core, so a dense view
costs J·n_out·C multiply-adds per point and no ``[P, n_out, C]`` intermediate (Sloan 2003's
cost model). torch has no fused op for these small per-point contractions (a GEMM, gather or
``embedding_bag`` each leave an intermediate as large as the view behind), so they are a few
lines of C compiled on first use with the system C compiler (``cc``, OpenMP, about 2 s here),
cached on disk by a hash of the source, flags and CPU, and called through ctypes (the GIL is
released). Without a compiler — or with ``PRT_TORCH_NATIVE=0`` — :func:`native` returns None
and ``AffineCodec.relight`` uses its torch formulation, which gives the same results to
float32 rounding (tests run both).

Per light, ``AffineCodec.relight`` runs a :class:`Plan` of its encoding (:func:`plan`, built once
and cached; :func:`run_plan`): the arguments of the constants kernel and of the point kernel
that do not change between lights, as one int64 array, handed to ``prt_relight_plan`` — one
ctypes call, the same kernels as :func:`constants` followed by :func:`affine_rows`,
:func:`affine_dense` or :func:`affine_taps` (tests hold them to the same bits).

Codes as stored by ``AffineCodec`` (no copies): labels ``[P]`` uint8/int16/int32 (absent when
K = 1), weights ``[P, n_max]`` float32 (row stride n_max, the first n used) or packed (the
n_{k(p)} weights of each point one after the other; ``offsets int64 [P]`` where each starts,
``n_vectors int64 [K]``). Constants float32 contiguous: ``[K, J, n_out·C]`` (rows, dense) or
``[K, n_out, J·C]`` (taps), J = (1 if a mean) + n. Points may be visited in a given order
(CPCA: cluster by cluster within blocks, from codes stored in that order; ``AffineCodec``
chooses), and the result written into a given tensor (``out``). Without a view, and with an
RGB dense view of up to 24 rows (8 with 16 vector registers; two points within one block of 8),
two consecutive visits of one cluster with the same term count are combined in one pass over
``T_k`` (with a dense view each load kept in a register for both points' multiply-adds; each
point's sums in the same order: same bits). Compiled with ``-ffp-contract=fast``: each
``a += w·t`` is one fused multiply-add where the CPU has them (measured, paired: dense views
3–15% faster; results differ from separate rounding by float32 rounding only, and a point's
bits still do not depend on pairing, order or threads).

The Gaussian codec's relighting (Green 2005 eq. 2.7 and §2.3) runs here too: per lobe, the
prefiltered cube-map lookup (face, bilinear texels, linear in log σ between levels) and the
weighted sum over the lobes (:func:`sg_lookup_sum`); with view taps, the blend of the tapped
views' lobes as well (:func:`sg_taps`) — one pass per vertex instead of ~30 torch ops over
lobe-sized intermediates.
"""
from __future__ import annotations

import ctypes
import os
import threading
import weakref

import torch

from .._checks import check_finite_float32, tensor_version
from .._native import compile_library

__all__ = ["native", "native_status", "constants", "constants_layout", "model_t", "affine_rows", "affine_dense", "affine_taps",
           "plan", "run_plan", "Plan", "sg_lookup_sum", "sg_taps", "lobe_layout", "fits", "MAX_ROW"]

#: largest per-point row (n_out·C for dense views, J·C for taps) the kernels hold on the stack
MAX_ROW = 4096

_SRC = r"""
#include <stddef.h>
#include <stdlib.h>
#include <stdint.h>
#include <float.h>
#include <math.h>
#ifdef _OPENMP
#include <omp.h>
#endif
typedef int64_t i64;
/* 8 floats, unaligned loads/stores (GCC/Clang vector extensions; split into SSE where no AVX) */
typedef float v8 __attribute__((vector_size(32), aligned(4)));

static inline i64 lab_at(const void *L, int kind, i64 p) {
    switch (kind) {
    case 1: return ((const uint8_t *)L)[p];
    case 2: return ((const int16_t *)L)[p];
    case 3: return ((const int32_t *)L)[p];
    default: return 0;
    }
}

/* where the weights of point p start; *cnt = how many are used (n_k capped at nuse) */
static inline const float *weights_of(const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse,
                                      i64 k, i64 p, i64 *cnt) {
    i64 c = nuse;
    if (nk && nk[k] < c) c = nk[k];
    *cnt = W ? c : 0;
    return W ? W + (woff ? woff[p] : p * wstride) : 0;
}

/* Points may be visited in cluster order (order != NULL: a permutation of 0..P-1 sorted by
   cluster), so that consecutive points read the same cluster's constants from L1; their codes,
   views and outputs are then scattered, and are prefetched PF_AHEAD points ahead. */
#define PF_AHEAD 16
#define PREFETCH_CODES(pp) do {                                                                  \
        if (lab) __builtin_prefetch((const char *)lab + (pp) * (lab_kind == 1 ? 1 : lab_kind == 2 ? 2 : 4)); \
        if (W) __builtin_prefetch(W + (woff ? woff[pp] : (pp) * wstride));                       \
    } while (0)
#define PREFETCH_ROW(ptr, n, rw) do {                                                            \
        const float *pr_ = (ptr);                                                                \
        for (i64 f_ = 0; f_ < (n); f_ += 16) __builtin_prefetch(pr_ + f_, rw);                   \
    } while (0)

typedef float v4 __attribute__((vector_size(16)));
typedef float v4u __attribute__((vector_size(16), aligned(4)));  /* unaligned loads of 4 floats */
#if defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 12)
#define SHUF(a, ...) __builtin_shufflevector(a, a, __VA_ARGS__)
/* ((a0 + a1) + (a2 + a3)) + ((a4 + a5) + (a6 + a7)): the association hsum8 uses for each of its
   8 sums, so a point's result does not depend on whether it was reduced alone or in a block of 8
   (nor, therefore, on how the points were split between threads) */
static inline float hsum(v8 a) {
    v4 s = SHUF(a, 0, 2, 4, 6) + SHUF(a, 1, 3, 5, 7);
    return (s[0] + s[1]) + (s[2] + s[3]);
}
/* lane i = the sum of a[i]'s lanes, for 8 vectors at once: three rounds of adding the even and
   odd lanes of neighbouring pairs (7 shuffle pairs for 8 sums, where 8 hsums take 24) */
#define EVEN2(a, b) __builtin_shufflevector(a, b, 0, 2, 4, 6, 8, 10, 12, 14)
#define ODD2(a, b) __builtin_shufflevector(a, b, 1, 3, 5, 7, 9, 11, 13, 15)
static inline v8 hsum8(const v8 *a) {
    v8 t0 = EVEN2(a[0], a[1]) + ODD2(a[0], a[1]), t1 = EVEN2(a[2], a[3]) + ODD2(a[2], a[3]);
    v8 t2 = EVEN2(a[4], a[5]) + ODD2(a[4], a[5]), t3 = EVEN2(a[6], a[7]) + ODD2(a[6], a[7]);
    v8 u0 = EVEN2(t0, t1) + ODD2(t0, t1), u1 = EVEN2(t2, t3) + ODD2(t2, t3);
    return EVEN2(u0, u1) + ODD2(u0, u1);
}
#else
static inline float hsum(v8 a) { return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7])); }
static inline v8 hsum8(const v8 *a) { v8 r; for (int i = 0; i < 8; i++) r[i] = hsum(a[i]); return r; }
#endif

#ifdef SHUF
/* d[3l + c] = a_c[l] for l < 8: three colour vectors interleaved into 24 floats (6 shuffles) */
static inline void interleave3(v8 a0, v8 a1, v8 a2, float *d) {
    v8 t0 = __builtin_shufflevector(a0, a1, 0, 8, 0, 1, 9, 0, 2, 10);
    v8 t1 = __builtin_shufflevector(a0, a1, 0, 3, 11, 0, 4, 12, 0, 5);
    v8 t2 = __builtin_shufflevector(a0, a1, 13, 0, 6, 14, 0, 7, 15, 0);
    *(v8 *)d = __builtin_shufflevector(t0, a2, 0, 1, 8, 3, 4, 9, 6, 7);
    *(v8 *)(d + 8) = __builtin_shufflevector(t1, a2, 10, 1, 2, 11, 4, 5, 12, 7);
    *(v8 *)(d + 16) = __builtin_shufflevector(t2, a2, 0, 13, 2, 3, 14, 5, 6, 15);
}

/* r[0..7] <- its 8x8 transpose (r[i][l] -> r[l][i]): unpack pairs, then quads, then halves */
static inline void transpose8(v8 *r) {
    v8 t[8], q[8];
    for (int i = 0; i < 8; i += 2) {
        t[i] = __builtin_shufflevector(r[i], r[i + 1], 0, 8, 1, 9, 4, 12, 5, 13);
        t[i + 1] = __builtin_shufflevector(r[i], r[i + 1], 2, 10, 3, 11, 6, 14, 7, 15);
    }
    for (int i = 0; i < 8; i += 4)
        for (int h = 0; h < 2; h++) {
            q[i + 2 * h] = __builtin_shufflevector(t[i + h], t[i + h + 2], 0, 1, 8, 9, 4, 5, 12, 13);
            q[i + 2 * h + 1] = __builtin_shufflevector(t[i + h], t[i + h + 2], 2, 3, 10, 11, 6, 7, 14, 15);
        }
    for (int i = 0; i < 4; i++) {
        r[i] = __builtin_shufflevector(q[i], q[i + 4], 0, 1, 2, 3, 8, 9, 10, 11);
        r[i + 4] = __builtin_shufflevector(q[i], q[i + 4], 4, 5, 6, 7, 12, 13, 14, 15);
    }
}
#endif

/* 8 RGB points: colour c of point l is the lane sum of R[8c + l]; written to out[3 pl[l] + c].
   Returns 2 if an output is not finite. */
static inline int store8_rgb(const v8 *R, float *out, const i64 *pl, int seq) {
    v8 s0 = hsum8(R), s1 = hsum8(R + 8), s2 = hsum8(R + 16);
    /* non-finite: |x| above FLT_MAX as bits (NaN and Inf), all 24 lanes at once */
    typedef int32_t v8i __attribute__((vector_size(32)));
    const v8i absmask = {0x7fffffff, 0x7fffffff, 0x7fffffff, 0x7fffffff, 0x7fffffff, 0x7fffffff, 0x7fffffff, 0x7fffffff};
    const v8i maxbits = {0x7f7fffff, 0x7f7fffff, 0x7f7fffff, 0x7f7fffff, 0x7f7fffff, 0x7f7fffff, 0x7f7fffff, 0x7f7fffff};
    v8i bad = (((v8i)s0 & absmask) > maxbits) | (((v8i)s1 & absmask) > maxbits) | (((v8i)s2 & absmask) > maxbits);
    int any = 0;
    for (int l = 0; l < 8; l++) any |= bad[l];
#ifdef SHUF
    if (seq) {  /* consecutive points (pl[l] = pl[0] + l): 24 contiguous floats, three vector stores */
        interleave3(s0, s1, s2, out + 3 * pl[0]);
        return any ? 2 : 0;
    }
#endif
    for (int l = 0; l < 8; l++) {
        float *op = out + 3 * pl[l];
        op[0] = s0[l]; op[1] = s1[l]; op[2] = s2[l];
    }
    return any ? 2 : 0;
}

static inline float dot(const float *a, const float *b, i64 n) {
    v8 acc = {0};
    i64 i = 0;
    for (; i + 8 <= n; i += 8) acc += *(const v8 *)(a + i) * *(const v8 *)(b + i);
    float s = hsum(acc);
    for (; i < n; i++) s += a[i] * b[i];
    return s;
}

#define LD(p) (*(const v8 *)(p))
#define ST(p, v) (*(v8 *)(p) = (v))
#if defined(__AVX__)
#include <immintrin.h>
#endif
/* FMA8: a + w x, one rounding where the CPU has FMA: written out, not left to contraction, which GCC applied in one
   loop of the one-vector rows pass (small_rows_range) and not in another (their bits differed); FMA8V: the same
   with w a vector */
static inline v8 splat8(float x) { return (v8){x, x, x, x, x, x, x, x}; }
#if defined(__FMA__)
#define FMA8(w, x, a) ((v8)_mm256_fmadd_ps(_mm256_set1_ps(w), (__m256)(x), (__m256)(a)))
#define FMA8V(w, x, a) ((v8)_mm256_fmadd_ps((__m256)(w), (__m256)(x), (__m256)(a)))
#elif defined(__ARM_FEATURE_FMA) || defined(__FP_FAST_FMAF)  /* FMA without __FMA__: written out lane by lane */
static inline v8 fma8v_(v8 w, v8 x, v8 a) { v8 r; for (int i = 0; i < 8; i++) r[i] = __builtin_fmaf(w[i], x[i], a[i]); return r; }
#define FMA8(w, x, a) fma8v_(splat8(w), (x), (a))
#define FMA8V(w, x, a) fma8v_((w), (x), (a))
#else  /* no FMA instruction: nothing to contract into */
#define FMA8(w, x, a) ((a) + (w) * (x))
#define FMA8V(w, x, a) ((a) + (w) * (x))
#endif
/* x stays in a register: a vector loaded once for several FMAs is not folded into each as a
   memory operand (GCC does that, loading it two or three times). Used where one load feeds
   several FMAs: the paired dense kernel (measured, paired: dense views of 24 rows 1.03-1.16x),
   the view in the dense dot (VQ dense 1.06-1.08x) and the model vector of the constants kernel
   (CPCA constants 1.09-1.29x). In the rows kernel it made CPCA 1.13x faster but PCA 0.72-0.87x at
   one thread (cause not established), so that one keeps the folded loads. No code is emitted;
   the baseline ISA (SSE halves) has no such register. */
#if defined(__AVX__)
#define IN_REG(x) __asm__("" : "+v"(x))
#else
#define IN_REG(x) (void)0
#endif

/* 16 floats per vector (AVX-512): the dense kernel's and the rows kernel's wide paths */
#if defined(__AVX512F__)
#define HAVE_W16 1
/* a 16-lane vector's two halves added, as 8 lanes (the dense kernel's per-colour dot, for hsum / store8_rgb) */
static inline v8 fold16(__m512 r) {
    return (v8)_mm256_add_ps(_mm512_castps512_ps256(r), _mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(r), 1)));
}
/* the first n lanes (0 <= n, all 16 from n = 16 on) */
static inline __mmask16 lanes16(i64 n) { return n >= 16 ? (__mmask16)0xFFFF : n <= 0 ? (__mmask16)0 : (__mmask16)((1u << n) - 1u); }
#else
#define HAVE_W16 0
#endif

/* a_b = (mean ? Tc[8b..] : 0) + sum_{i<cnt} w[i] Tc[(mean + i) F + 8b..], b < NB: NB independent
   accumulators (NB >= 8 keeps both FMA pipes busy) while the weights stream past. Named
   variables a0..a11, not an array: GCC keeps an array of vectors on the stack and copies it out
   in 64-byte moves that stall on store forwarding (measured: the VQ rows kernel ran at a third
   of a plain copy's speed); the `b < NB_` tests fold at compile time. */
#define EACH12(X) X(0) X(1) X(2) X(3) X(4) X(5) X(6) X(7) X(8) X(9) X(10) X(11)
#define ACC_INIT(b) v8 a##b = (b < NB_ && mean) ? LD(Tc + 8 * b) : (v8){0};
#define ACC_STEP(b) if (b < NB_) a##b += wi * LD(Tb + 8 * b);
#define ACCUMULATE(NB)                                                                           \
    enum { NB_ = NB };                                                                           \
    EACH12(ACC_INIT)                                                                             \
    const float *Tb = Tc + (mean ? F : 0);                                                       \
    for (i64 i = 0; i < cnt; i++, Tb += F) {                                                     \
        float wi = w[i];                                                                         \
        EACH12(ACC_STEP)                                                                         \
    }

/* rows: ec[8b..] = a_b */
#define ACC_STORE(b) if (b < NB_) ST(ec + 8 * b, a##b);
#define ROWS_CHUNK(NB)                                                                           \
static inline void rows_chunk_##NB(const float *Tc, i64 F, int mean, const float *w, i64 cnt, float *ec) { \
    ACCUMULATE(NB)                                                                               \
    EACH12(ACC_STORE)                                                                            \
}
#define CHUNKS(X) X(1) X(2) X(3) X(4) X(5) X(6) X(7) X(8) X(9) X(10) X(11) X(12)
CHUNKS(ROWS_CHUNK)
#define MAXNB 12
#define CASE_ROWS(NB) case NB: rows_chunk_##NB(Tc, F, mean, w, cnt, ec); break;

/* nv vectors in ceil(nv / 12) nearly equal chunks: the size of one */
static inline i64 chunk_size(i64 nv) { i64 n = (nv + MAXNB - 1) / MAXNB; return n ? (nv + n - 1) / n : 1; }

/* e[0:F] = (mean ? T[0] : 0) + sum_{i<cnt} w[i] T[mean + i]  (rows of F floats, stride F; F % 8 == 0) */
static inline __attribute__((always_inline)) void combine(i64 F, i64 cs, const float *T, int mean, const float *w, i64 cnt, float *e) {
    i64 nv = F / 8;  /* cs = chunk_size(nv), computed once per call by the caller (two divisions) */
    for (i64 b0 = 0; b0 < nv; b0 += cs) {
        int nb = (int)(nv - b0 < cs ? nv - b0 : cs);
        const float *Tc = T + 8 * b0;
        float *ec = e + 8 * b0;
        switch (nb) { CHUNKS(CASE_ROWS) default: break; }
    }
}

/* two points of one cluster with the same term count at once: one pass over T for both points'
   FMAs (GCC still loads each T vector twice, as memory operands; see IN_REG). Each point's sums are
   formed in the same order as by ACCUMULATE, so a point's result does not depend on whether it
   was paired. */
#define ACC2_INIT(b) v8 a##b = (b < NB_ && mean) ? LD(Tc + 8 * b) : (v8){0}; v8 c##b = a##b;
#define ACC2_STEP(b) if (b < NB_) { v8 t_ = LD(Tb + 8 * b); a##b += wi * t_; c##b += ui * t_; }
#define ACC2_STORE(b) if (b < NB_) { ST(ec + 8 * b, a##b); ST(fc + 8 * b, c##b); }
#define ROWS2_CHUNK(NB)                                                                          \
static inline void rows2_chunk_##NB(const float *Tc, i64 F, int mean, const float *w, const float *u, i64 cnt, \
                                    float *ec, float *fc) {                                      \
    enum { NB_ = NB };                                                                           \
    EACH12(ACC2_INIT)                                                                            \
    const float *Tb = Tc + (mean ? F : 0);                                                       \
    for (i64 i = 0; i < cnt; i++, Tb += F) {                                                     \
        float wi = w[i], ui = u[i];                                                              \
        EACH12(ACC2_STEP)                                                                        \
    }                                                                                            \
    EACH12(ACC2_STORE)                                                                           \
}
/* 2 NB accumulators + a T vector + 2 weights must fit the vector registers: 32 with AVX-512VL,
   else 16 */
#if defined(__AVX512VL__)
#define MAXNB2 12
#define CHUNKS2(X) CHUNKS(X)
#else
#define MAXNB2 6
#define CHUNKS2(X) X(1) X(2) X(3) X(4) X(5) X(6)
#endif
CHUNKS2(ROWS2_CHUNK)
#define CASE_ROWS2(NB) case NB: rows2_chunk_##NB(Tc, F, mean, w, u, cnt, ec, fc); break;
static inline i64 chunk_size2(i64 nv) { i64 n = (nv + MAXNB2 - 1) / MAXNB2; return n ? (nv + n - 1) / n : 1; }

/* combine for two points sharing T: e = T-combination with weights w, f = with weights u */
static inline __attribute__((always_inline)) void combine2(i64 F, i64 cs, const float *T, int mean, const float *w,
                                                           const float *u, i64 cnt, float *e, float *f) {
    i64 nv = F / 8;  /* cs = chunk_size2(nv) */
    for (i64 b0 = 0; b0 < nv; b0 += cs) {
        int nb = (int)(nv - b0 < cs ? nv - b0 : cs);
        const float *Tc = T + 8 * b0;
        float *ec = e + 8 * b0, *fc = f + 8 * b0;
        switch (nb) { CHUNKS2(CASE_ROWS2) default: break; }
    }
}

/* out[0:n] = e[0:n] */
static inline void copy_row(float *out, const float *e, i64 n) {
    i64 f = 0;
    for (; f + 8 <= n; f += 8) ST(out + f, LD(e + f));
    for (; f < n; f++) out[f] = e[f];
}

/* e[0:R] = sum_{t<n} g[t] rows[t][0:R] */
static inline void gather_sum(i64 R, const float *const *rows, const float *g, i64 n, float *e) {
    i64 f0 = 0;
    for (; f0 + 32 <= R; f0 += 32) {
        v8 a0 = {0}, a1 = {0}, a2 = {0}, a3 = {0};
        for (i64 t = 0; t < n; t++) {
            const float *r = rows[t] + f0;
            float gt = g[t];
            a0 += gt * *(const v8 *)r; a1 += gt * *(const v8 *)(r + 8); a2 += gt * *(const v8 *)(r + 16); a3 += gt * *(const v8 *)(r + 24);
        }
        *(v8 *)(e + f0) = a0; *(v8 *)(e + f0 + 8) = a1; *(v8 *)(e + f0 + 16) = a2; *(v8 *)(e + f0 + 24) = a3;
    }
    for (; f0 + 8 <= R; f0 += 8) {
        v8 a0 = {0};
        for (i64 t = 0; t < n; t++) a0 += g[t] * *(const v8 *)(rows[t] + f0);
        *(v8 *)(e + f0) = a0;
    }
    for (; f0 < R; f0++) {
        float a = 0.0f;
        for (i64 t = 0; t < n; t++) a += g[t] * rows[t][f0];
        e[f0] = a;
    }
}

/* RGB: G consecutive 8-output blocks of one representative at once (each L broadcast and loop
   step shared by the G blocks), even and odd terms in separate registers: A[3g + c] = block g,
   colour c. The same sums in the same order for every G. */
#define CG_DECL(g) v8 a##g##0 = {0}, a##g##1 = {0}, a##g##2 = {0}, b##g##0 = {0}, b##g##1 = {0}, b##g##2 = {0};
#define CG_STEP(g) if (g < G_) { v8 x = LD(s0 + 8 * g), z = LD(s1 + 8 * g); IN_REG(x); IN_REG(z);  \
        a##g##0 += x * l0; a##g##1 += x * l1; a##g##2 += x * l2; b##g##0 += z * m0; b##g##1 += z * m1; b##g##2 += z * m2; }
#define CG_TAIL(g) if (g < G_) { v8 x = LD(s0 + 8 * g); IN_REG(x); a##g##0 += x * l0; a##g##1 += x * l1; a##g##2 += x * l2; }
#define CG_OUT(g) if (g < G_) { A[3 * g] = a##g##0 + b##g##0; A[3 * g + 1] = a##g##1 + b##g##1; A[3 * g + 2] = a##g##2 + b##g##2; }
#define EACH3(X) X(0) X(1) X(2)
#define CONST_GROUP(G)                                                                           \
static inline void const_group_##G(const float *src, i64 n_in, i64 n_pad, const float *L, v8 *A) { \
    enum { G_ = G };                                                                             \
    EACH3(CG_DECL)                                                                               \
    i64 i = 0;                                                                                   \
    for (; i + 2 <= n_in; i += 2) {                                                              \
        const float *s0 = src + i * n_pad, *s1 = s0 + n_pad;                                     \
        float l0 = L[3 * i], l1 = L[3 * i + 1], l2 = L[3 * i + 2], m0 = L[3 * i + 3], m1 = L[3 * i + 4], m2 = L[3 * i + 5]; \
        EACH3(CG_STEP)                                                                           \
    }                                                                                            \
    if (i < n_in) {                                                                              \
        const float *s0 = src + i * n_pad;                                                       \
        float l0 = L[3 * i], l1 = L[3 * i + 1], l2 = L[3 * i + 2];                               \
        EACH3(CG_TAIL)                                                                           \
    }                                                                                            \
    EACH3(CG_OUT)                                                                                \
}
CONST_GROUP(1) CONST_GROUP(2) CONST_GROUP(3)
/* 2 G·3 accumulators + loads must fit the vector registers: 3 blocks with AVX-512VL (32), else 1 */
#if defined(__AVX512VL__)
#define CGMAX 3
#else
#define CGMAX 1
#endif

/* block ob (outputs 8 ob .. 8 ob + 7) of one representative's constants, a[c] per colour, into its layout */
static inline void store_block(float *dst, i64 ob, const v8 *a, i64 C, i64 n_out, i64 so, i64 sc) {
    if (so == 1 && ob * 8 + 8 <= n_out) {  /* colour-major layouts: 8 outputs in one store */
        for (i64 c = 0; c < C; c++) ST(dst + ob * 8 + c * sc, a[c]);
        return;
    }
#ifdef SHUF
    if (C == 3 && so == 3 && sc == 1 && ob * 8 + 8 <= n_out) {  /* rows layout, RGB: (o, c) interleaved */
        interleave3(a[0], a[1], a[2], dst + ob * 24);
        return;
    }
#endif
    for (i64 l = 0; l < 8 && ob * 8 + l < n_out; l++)
        for (i64 c = 0; c < C; c++) dst[(ob * 8 + l) * so + c * sc] = a[c][l];
}

/* Per-cluster constants T = M l (Sloan 2003 §6) from the model cached "column-major":
   Mt [K, Jmax, n_in, n_pad] (the representatives x_0, x_1.. of each cluster as n_out x n_in
   matrices, transposed, rows zero-padded to n_pad); L [n_in, C]. Writes
   out[k*sk + j*sj + o*so + c*sc] = sum_i Mt[k, j, i, o] L[i, c] for j < J, o < n_out: every
   layout a kernel below reads, directly. 8 outputs o per vector, L broadcast: no reductions.
   RGB: up to CGMAX blocks of 8 outputs per pass (measured, CPCA 256x8 at 24x25: 0.195 -> 0.145 ms).
   nk (optional, int64 [K]): cluster k's terms are only its first Jk = min(J, mean + nk[k]) (CPCA
   adaptive: n_k of up to n vectors), the only ones a kernel reads (taps: zeros beyond, since it
   reads 8 terms at a time); the rest of its rows are left as they were. */
static void constants_range(i64 k0, i64 k1, i64 J, i64 Jmax, i64 n_in, i64 n_out, i64 n_pad, i64 C, const float *Mt,
                            const float *L, float *out, i64 sk, i64 sj, i64 so, i64 sc, const i64 *nk, int mean) {
    i64 nb = n_pad / 8;
#define TERMS_OF(k) (nk && mean + nk[k] < J ? mean + nk[k] : J)
#ifdef SHUF
    if (C == 3 && sj == 1 && sc > 1 && sc % 8 == 0 && so == 3 * sc) {
        /* taps layout [K, n_out, 3, Jp]: a row's terms are contiguous, so compute 8 terms of a block
           of 8 outputs, transpose each colour's 8x8 and store whole vectors (element stores at
           stride 3 Jp: measured 2x slower). Same sums (const_group_1 per term and block). */
        for (i64 k = k0; k < k1; k++)
            for (i64 ob0 = 0; ob0 < nb; ob0 += CGMAX)
                for (i64 j0 = 0, Jk = TERMS_OF(k); j0 < J; j0 += 8) {
                    i64 G = nb - ob0 < CGMAX ? nb - ob0 : CGMAX;
                    v8 T3[3 * CGMAX][8];  /* [3 g + c][term] */
                    for (i64 jj = 0; jj < 8; jj++) {
                        v8 A[3 * CGMAX];
                        for (int x = 0; x < 3 * CGMAX; x++) A[x] = (v8){0};
                        const float *src = Mt + ((k * Jmax + j0 + jj) * n_in) * n_pad + ob0 * 8;
                        if (j0 + jj < Jk) {
                            switch (G) {
                            case 1: const_group_1(src, n_in, n_pad, L, A); break;
#if CGMAX >= 3
                            case 2: const_group_2(src, n_in, n_pad, L, A); break;
                            default: const_group_3(src, n_in, n_pad, L, A); break;
#endif
                            }
                        }
                        for (int x = 0; x < 3 * CGMAX; x++) T3[x][jj] = A[x];
                    }
                    for (i64 g = 0; g < G; g++)
                        for (int c = 0; c < 3; c++) {
                            v8 *t = T3[3 * g + c];
                            transpose8(t);
                            for (i64 l = 0; l < 8 && (ob0 + g) * 8 + l < n_out; l++)
                                ST(out + k * sk + ((ob0 + g) * 8 + l) * so + c * sc + j0, t[l]);
                        }
                }
        return;
    }
#endif
    for (i64 k = k0; k < k1; k++)
        for (i64 j = 0, Jk = TERMS_OF(k); j < Jk; j++) {
            const float *src = Mt + ((k * Jmax + j) * n_in) * n_pad;
            float *dst = out + k * sk + j * sj;
            if (C == 3) {
                for (i64 ob0 = 0; ob0 < nb; ob0 += CGMAX) {
                    v8 A[3 * CGMAX];
                    i64 G = nb - ob0 < CGMAX ? nb - ob0 : CGMAX;
                    switch (G) {
                    case 1: const_group_1(src + ob0 * 8, n_in, n_pad, L, A); break;
#if CGMAX >= 3
                    case 2: const_group_2(src + ob0 * 8, n_in, n_pad, L, A); break;
                    default: const_group_3(src + ob0 * 8, n_in, n_pad, L, A); break;
#endif
                    }
                    for (i64 g = 0; g < G; g++) store_block(dst, ob0 + g, A + 3 * g, 3, n_out, so, sc);
                }
                continue;
            }
            for (i64 ob = 0; ob < nb; ob++) {
                v8 a[16];
                for (i64 c = 0; c < C; c++) a[c] = (v8){0};
                for (i64 i = 0; i < n_in; i++) {
                    v8 x = LD(src + i * n_pad + ob * 8);
                    const float *li = L + i * C;
                    for (i64 c = 0; c < C; c++) a[c] += x * li[c];
                }
                store_block(dst, ob, a, C, n_out, so, sc);
            }
        }
    if (nk && sj == 1)  /* taps layout: zeros for the terms past a cluster's own (read, times zero weights) */
        for (i64 k = k0; k < k1; k++)
            for (i64 j = TERMS_OF(k); j < J; j++)
                for (i64 o = 0; o < n_out; o++)
                    for (i64 c = 0; c < C; c++) out[k * sk + j + o * so + c * sc] = 0.0f;
#undef TERMS_OF
}

/* returns 1 (and computes nothing) if the light L [n_in, C] holds a NaN or an infinity: the
   caller's check, here where L is read anyway (names the value only on that path) */
int prt_constants(i64 K, i64 J, i64 Jmax, i64 n_in, i64 n_out, i64 n_pad, i64 C, const float *Mt, const float *L,
                  float *out, i64 sk, i64 sj, i64 so, i64 sc, const i64 *nk, int mean, int nthreads) {
    int bad = 0;
    for (i64 i = 0; i < n_in * C; i++) bad |= !(fabsf(L[i]) <= FLT_MAX);
    if (bad) return 1;
    i64 nth = nthreads > 0 ? nthreads : 1;
    if (nth == 1) {  /* no parallel region: entering one, even of one thread, costs ~0.5 us (libgomp) */
        constants_range(0, K, J, Jmax, n_in, n_out, n_pad, C, Mt, L, out, sk, sj, so, sc, nk, mean);
        return 0;
    }
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++)
        constants_range(K * t / nth, K * (t + 1) / nth, J, Jmax, n_in, n_out, n_pad, C, Mt, L, out, sk, sj, so, sc, nk, mean);
    return 0;
}

/* n_out = 1 (vector codecs: VQ, PCA, CPCA of diffuse transfer), rows layout: 8 clusters in the lanes, from the model
   cached as Mv [ceil(K/8), Jmax, n_in, 8] (cluster 8b + l in lane l, zero past K), where the per-cluster pass above
   computes 8 lanes of which one is used. Cluster k's sums are the FMA chains of constants_range's RGB pass (even and
   odd terms apart, then added; other colour counts one chain): for RGB its values bit for bit, 8 clusters at a
   time; for other colour counts within float32 rounding of its per-cluster loop, whose contraction GCC decides. */
static void constants_lanes_range(i64 b0, i64 b1, i64 K, i64 J, i64 Jmax, i64 n_in, i64 C, const float *Mv,
                                  const float *L, float *out, i64 sk, i64 sj) {
    for (i64 b = b0; b < b1; b++)
        for (i64 j = 0; j < J; j++) {
            const float *src = Mv + (b * Jmax + j) * n_in * 8;
            if (C == 3) {  /* the three colours' chains at once, each as below (same bits): 6 independent chains
                              where one colour's two waited on the multiply-add latency (VQ 256 of 16: 3x) */
                v8 a0 = {0}, a1 = {0}, a2 = {0}, z0 = {0}, z1 = {0}, z2 = {0};
                i64 i = 0;
                for (; i + 2 <= n_in; i += 2) {
                    const v8 s = LD(src + 8 * i), t = LD(src + 8 * i + 8);
                    a0 = FMA8(L[3 * i], s, a0);
                    a1 = FMA8(L[3 * i + 1], s, a1);
                    a2 = FMA8(L[3 * i + 2], s, a2);
                    z0 = FMA8(L[3 * i + 3], t, z0);
                    z1 = FMA8(L[3 * i + 4], t, z1);
                    z2 = FMA8(L[3 * i + 5], t, z2);
                }
                for (; i < n_in; i++) {
                    const v8 s = LD(src + 8 * i);
                    a0 = FMA8(L[3 * i], s, a0);
                    a1 = FMA8(L[3 * i + 1], s, a1);
                    a2 = FMA8(L[3 * i + 2], s, a2);
                }
                a0 = a0 + z0;
                a1 = a1 + z1;
                a2 = a2 + z2;
                for (i64 l = 0; l < 8 && b * 8 + l < K; l++) {
                    float *o = out + (b * 8 + l) * sk + j * sj;
                    o[0] = a0[l];
                    o[1] = a1[l];
                    o[2] = a2[l];
                }
                continue;
            }
            for (i64 c = 0; c < C; c++) {
                v8 a = {0}, z = {0};
                i64 i = 0;
                if (C == 3)
                    for (; i + 2 <= n_in; i += 2) {
                        a = FMA8(L[3 * i + c], LD(src + 8 * i), a);
                        z = FMA8(L[3 * i + 3 + c], LD(src + 8 * i + 8), z);
                    }
                for (; i < n_in; i++) a = FMA8(L[i * C + c], LD(src + 8 * i), a);
                if (C == 3) a = a + z;
                for (i64 l = 0; l < 8 && b * 8 + l < K; l++) out[(b * 8 + l) * sk + j * sj + c] = a[l];
            }
        }
}

/* prt_constants for n_out = 1, rows layout, from Mv (above); returns 1 if L holds a NaN or an infinity */
int prt_constants_lanes(i64 K, i64 J, i64 Jmax, i64 n_in, i64 C, const float *Mv, const float *L, float *out,
                        i64 sk, i64 sj, int nthreads) {
    int bad = 0;
    for (i64 i = 0; i < n_in * C; i++) bad |= !(fabsf(L[i]) <= FLT_MAX);
    if (bad) return 1;
    i64 nb = (K + 7) / 8, nth = nthreads > 0 ? nthreads : 1;
    if (nb * J * n_in * C < 32768) nth = 1;  /* under ~10 us of work: a parallel region costs more than it saves
                                                (measured: VQ 256 of 16 coefficients 2.9 us at 1 thread, 4.5 at 2) */
    if (nth > nb) nth = nb > 0 ? nb : 1;
    if (nth == 1) {
        constants_lanes_range(0, nb, K, J, Jmax, n_in, C, Mv, L, out, sk, sj);
        return 0;
    }
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++)
        constants_lanes_range(nb * t / nth, nb * (t + 1) / nth, K, J, Jmax, n_in, C, Mv, L, out, sk, sj);
    return 0;
}

/* mean only (VQ), no view, rows unpadded (F == Fo, a multiple of 8), points in order: out[p] =
   T[lab_p], one plain row copy per point, the label kind fixed per loop. Without the general
   loop's per-point bookkeeping (weights, pairing test, chunk switch, order). */
#define VQ_ROWS_LOOP(TY)                                                                         \
    for (i64 p = p0; p < p1; p++) {                                                              \
        const float *s = T + (i64)((const TY *)lab)[p] * F;                                      \
        float *d = out + p * F;                                                                  \
        for (i64 f = 0; f < F; f += 8) ST(d + f, LD(s + f));                                     \
    }
static __attribute__((noinline)) void vq_rows_range(i64 p0, i64 p1, i64 F, const void *lab, int lab_kind, const float *T,
                                                    float *out) {
    switch (lab_kind) {
    case 1: VQ_ROWS_LOOP(uint8_t) break;
    case 2: VQ_ROWS_LOOP(int16_t) break;
    default: VQ_ROWS_LOOP(int32_t) break;
    }
}

/* v[0:n] to p, n <= 8 (a row of n_out C <= 8 floats: diffuse RGB, 3) */
#define ST_FO(p, v, n) do { v8 v_ = (v); if ((n) == 8) ST(p, v_); else for (i64 i_ = 0; i_ < (n); i_++) (p)[i_] = v_[i_]; } while (0)

/* no view, rows of one vector (F == 8, Fo <= 8: diffuse transfer, n_out C = 3), where the general
   pass spends its time on per-point bookkeeping: VQ copies the cluster's row, PCA (one cluster,
   RGB) takes 8 points in lanes (k1_rgb8), the rest one point at a time. Every path computes a
   point by the same FMA chain, so its bits depend on neither the path, the order nor the threads.
   Whole 8-float vectors are stored where rows are consecutive (the next points' stores overwrite
   the lanes past Fo) and the store ends inside the thread's range; otherwise Fo scalar stores
   (masked vector stores of consecutive 12-byte rows ran at a third of the speed on Zen 4). */
#if defined(SHUF) && defined(__AVX512VL__)
/* 8 consecutive points of one cluster (K = 1: PCA), RGB rows (Fo = 3), points in lanes: the 8
   points' weights transposed 8 at a time (r[i] = weight i of each point), then per colour c
   acc_c = T_0[c] + sum_i r[i] T_{1+i}[c] by the same FMA chain per point and colour as the
   one-point loop (same bits), written as 24 contiguous floats: paired, 4-5x the one-point loop,
   which waits on each point's chain of weight loads and multiply-adds. */
static inline void k1_rgb8(const float *Tk, int mean, const float *wq, i64 ws, i64 cnt, float *d) {
    v8 a0 = {0}, a1 = {0}, a2 = {0};
    if (mean) {  /* set, not added to zero: 0 + (-0) is +0, and the other paths keep the mean's -0 */
        a0 = (v8)_mm256_set1_ps(Tk[0]); a1 = (v8)_mm256_set1_ps(Tk[1]); a2 = (v8)_mm256_set1_ps(Tk[2]);
    }
    const float *b = Tk + (mean ? 8 : 0);
    for (i64 i0 = 0; i0 < cnt; i0 += 8) {
        i64 m = cnt - i0 < 8 ? cnt - i0 : 8;
        const __mmask8 mk = (__mmask8)((1u << m) - 1u);
        v8 r[8];
        for (int j = 0; j < 8; j++) r[j] = (v8)_mm256_maskz_loadu_ps(mk, wq + j * ws + i0);
        transpose8(r);
        for (i64 i = 0; i < m; i++) {
            const float *t = b + 8 * (i0 + i);
            a0 = (v8)_mm256_fmadd_ps((__m256)r[i], _mm256_set1_ps(t[0]), (__m256)a0);
            a1 = (v8)_mm256_fmadd_ps((__m256)r[i], _mm256_set1_ps(t[1]), (__m256)a1);
            a2 = (v8)_mm256_fmadd_ps((__m256)r[i], _mm256_set1_ps(t[2]), (__m256)a2);
        }
    }
    interleave3(a0, a1, a2, d);
}
#define HAVE_K1_RGB8 1
#else
#define HAVE_K1_RGB8 0
#endif
#ifdef SHUF
/* 8 VQ points, RGB: the first 3 floats of each cluster row, packed as 24 contiguous floats */
#define VQ_RGB8(TY) {                                                                                             \
        const TY *l_ = (const TY *)lab + q;                                                                       \
        v8 r01 = __builtin_shufflevector(*(const v4u *)(T + l_[0] * J * 8), *(const v4u *)(T + l_[1] * J * 8), 0, 1, 2, 3, 4, 5, 6, 7); \
        v8 r23 = __builtin_shufflevector(*(const v4u *)(T + l_[2] * J * 8), *(const v4u *)(T + l_[3] * J * 8), 0, 1, 2, 3, 4, 5, 6, 7); \
        v8 r45 = __builtin_shufflevector(*(const v4u *)(T + l_[4] * J * 8), *(const v4u *)(T + l_[5] * J * 8), 0, 1, 2, 3, 4, 5, 6, 7); \
        v8 r67 = __builtin_shufflevector(*(const v4u *)(T + l_[6] * J * 8), *(const v4u *)(T + l_[7] * J * 8), 0, 1, 2, 3, 4, 5, 6, 7); \
        float *d_ = out + 3 * q;                                                                                  \
        ST(d_, __builtin_shufflevector(r01, r23, 0, 1, 2, 4, 5, 6, 8, 9));                                        \
        ST(d_ + 8, __builtin_shufflevector(r23, r45, 2, 4, 5, 6, 8, 9, 10, 12));                                  \
        ST(d_ + 16, __builtin_shufflevector(r45, r67, 5, 6, 8, 9, 10, 12, 13, 14));                               \
    }
/* the same with uint8 labels read 8 at a time and rows 8 floats apart (J = 1): one load instead of eight, in a loop
   bound by its loads (ab_kernels --shape diffuse: 1.135x at 1 thread, 1.07x at 2) */
#define ROW_U8_(i) (*(const v4u *)(T + (i64)((l8 >> (8 * (i))) & 255) * 8))
#define VQ_RGB8_U8 {                                                                                              \
        uint64_t l8;                                                                                              \
        __builtin_memcpy(&l8, (const uint8_t *)lab + q, 8);                                                       \
        v8 r01 = __builtin_shufflevector(ROW_U8_(0), ROW_U8_(1), 0, 1, 2, 3, 4, 5, 6, 7);                         \
        v8 r23 = __builtin_shufflevector(ROW_U8_(2), ROW_U8_(3), 0, 1, 2, 3, 4, 5, 6, 7);                         \
        v8 r45 = __builtin_shufflevector(ROW_U8_(4), ROW_U8_(5), 0, 1, 2, 3, 4, 5, 6, 7);                         \
        v8 r67 = __builtin_shufflevector(ROW_U8_(6), ROW_U8_(7), 0, 1, 2, 3, 4, 5, 6, 7);                         \
        float *d_ = out + 3 * q;                                                                                  \
        ST(d_, __builtin_shufflevector(r01, r23, 0, 1, 2, 4, 5, 6, 8, 9));                                        \
        ST(d_ + 8, __builtin_shufflevector(r23, r45, 2, 4, 5, 6, 8, 9, 10, 12));                                  \
        ST(d_ + 16, __builtin_shufflevector(r45, r67, 5, 6, 8, 9, 10, 12, 13, 14));                               \
    }
#endif
/* points q.. in order, n terms each after the mean, weights in rows of stride ws, the label kind fixed: each
   point by the one-point chain a = T_k[0] + sum_i w_i T_k[1+i] below (same FMAs, same bits), specialised so that
   neither the label kind, nor the weights' addressing, nor the term count is decided per point. The point's first 8
   weights are one load (4 floats for up to 4 terms; lanes permuted where the CPU has AVX2), so the loop stops at
   the caller's `last`: where that load would end past the last weight the one-point chain reads (any row stride, 0
   included) or a whole-vector store past the range. Returns where it stopped. On builds without AVX2 the compiler may order a
   multiply-add's operands differently here and in the one-point loop: where both are NaN, the NaN's payload bits
   can then depend on the path (every result is the same otherwise). */
static inline __attribute__((always_inline)) i64 rows_fixed(i64 q, i64 last, i64 Fo, const void *lab, const int lab_kind,
        const float *W, i64 ws, const int n, const float *T, i64 J, float *out) {
    for (; q <= last; q++) {
        const float *t = T + lab_at(lab, lab_kind, q) * J * 8, *w = W + q * ws;
        v8 a = LD(t);
#if defined(__AVX2__)
        __m256 wv = n <= 4 ? _mm256_castps128_ps256(_mm_loadu_ps(w)) : _mm256_loadu_ps(w);
        IN_REG(wv);  /* one load: GCC otherwise folds it into every permute (n loads, 1.3x slower, bare C) */
        for (int i = 0; i < n; i++) a = FMA8V((v8)_mm256_permutevar8x32_ps(wv, _mm256_set1_epi32(i)), LD(t + 8 + 8 * i), a);
#else
        for (int i = 0; i < n; i++) a = FMA8(w[i], LD(t + 8 + 8 * i), a);
#endif
        ST(out + q * Fo, a);
    }
    return q;
}
/* rows_fixed with the term count and label kind as constants, one instantiation each, kept out of small_rows_range:
   there, the 32 copies cost the diffuse CPCA loop 8% (ab_kernels --shape diffuse: 1.08x at 1 thread, 1.07x at 2) */
static __attribute__((noinline)) i64 fixed_rows(i64 q, i64 last, i64 Fo, const void *lab, int lab_kind, const float *W,
                                               i64 wstride, i64 nuse, const float *T, i64 J, float *out) {
#define FIXED(n) switch (lab_kind) {                                                                                \
        case 0: q = rows_fixed(q, last, Fo, lab, 0, W, wstride, n, T, J, out); break;                        \
        case 1: q = rows_fixed(q, last, Fo, lab, 1, W, wstride, n, T, J, out); break;                        \
        case 2: q = rows_fixed(q, last, Fo, lab, 2, W, wstride, n, T, J, out); break;                        \
        default: q = rows_fixed(q, last, Fo, lab, 3, W, wstride, n, T, J, out); break;                       \
        }
        switch (nuse) {
        case 1: FIXED(1) break;
        case 2: FIXED(2) break;
        case 3: FIXED(3) break;
        case 4: FIXED(4) break;
        case 5: FIXED(5) break;
        case 6: FIXED(6) break;
        case 7: FIXED(7) break;
        default: FIXED(8) break;
        }
#undef FIXED
    return q;
}
static __attribute__((noinline)) void small_rows_range(const int32_t *order, int csort, i64 p0, i64 p1, i64 Fo, const void *lab,
        int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 J,
        float *out) {
    i64 q = p0;
#ifdef SHUF
    if (!W && !order && lab && mean && Fo == 3) {  /* VQ, RGB: 8 points' rows packed into 24 floats (3 stores where one
                                                     store per point crosses a cache line every other point; 2x, bare C) */
        switch (lab_kind) {
        case 1:
            if (J == 1)  /* rows 8 floats apart, as VQ_RGB8_U8 assumes */
                for (; q + 8 <= p1; q += 8) VQ_RGB8_U8
            for (; q + 8 <= p1; q += 8) VQ_RGB8(uint8_t)
            break;
        case 2: for (; q + 8 <= p1; q += 8) VQ_RGB8(int16_t) break;
        default: for (; q + 8 <= p1; q += 8) VQ_RGB8(int32_t) break;
        }
    }
#endif
    if (!W && !order && lab && mean) {  /* VQ: the row of the point's cluster; whole vectors in order as above while
                                          they end inside the range, the rest below */
        switch (lab_kind) {
        case 1: for (; q * Fo + 8 <= p1 * Fo; q++) ST(out + q * Fo, LD(T + ((const uint8_t *)lab)[q] * J * 8)); break;
        case 2: for (; q * Fo + 8 <= p1 * Fo; q++) ST(out + q * Fo, LD(T + ((const int16_t *)lab)[q] * J * 8)); break;
        default: for (; q * Fo + 8 <= p1 * Fo; q++) ST(out + q * Fo, LD(T + ((const int32_t *)lab)[q] * J * 8)); break;
        }
    }
#if HAVE_K1_RGB8
    if (!lab && !order && !woff && W && Fo == 3) {
        i64 cnt;
        weights_of(W, wstride, woff, nk, nuse, 0, 0, &cnt);
        for (; q + 8 <= p1; q += 8) k1_rgb8(T, mean, W + q * wstride, wstride, cnt, out + 3 * q);
    }
#endif
    /* the rest (CPCA, other row lengths, a visiting order, the tails): one point at a time. The out-of-order core
       overlaps consecutive points' chains; an 8-point pass, with a pointer per point, spilled them (CPCA 1.5x slower).
       Consecutive rows with whole-vector stores while they end inside the range, then Fo floats per point. */
    if (!order && W && !woff && !nk && mean && nuse >= 1 && nuse <= 8) {  /* CPCA, PCA: fixed term count, rows of weights */
        /* the last point whose load of wl weights ends within the range's last used one, (p1 - 1) ws + nuse (row
           stride 0: every point or none), and whose 8-float store ends within the range (computed here: inside
           rows_fixed the same bound made GCC's CPCA loop 1.7x slower) */
        const i64 wl = nuse <= 4 ? 4 : 8, last_o = p1 - (8 + Fo - 1) / Fo;
        const i64 last_w = wstride > 0 ? p1 - 1 - (wl - nuse + wstride - 1) / wstride : (wl <= nuse ? p1 - 1 : q - 1);
        const i64 last = last_o < last_w ? last_o : last_w;
        q = fixed_rows(q, last, Fo, lab, lab_kind, W, wstride, nuse, T, J, out);
    }
#define ONE_ROW(pc) i64 k = lab_at(lab, lab_kind, pc), cnt;                                                          \
        const float *w = weights_of(W, wstride, woff, nk, nuse, k, pc, &cnt), *t = T + k * J * 8, *b = t + (mean ? 8 : 0); \
        v8 a = mean ? LD(t) : (v8){0};                                                                             \
        for (i64 i = 0; i < cnt; i++) a = FMA8(w[i], LD(b + 8 * i), a);
    if (!order)
        for (; q * Fo + 8 <= p1 * Fo; q++) {
            ONE_ROW(q)
            ST(out + q * Fo, a);
        }
    for (; q < p1; q++) {
        i64 p = order ? order[q] : q;
        ONE_ROW(csort ? q : p)
        ST_FO(out + p * Fo, a, Fo);
    }
#undef ONE_ROW
}

/* the no-view kernels' visits (rows16_range, prt_affine_rows_range): visit q's point *p, prefetching the codes and the
   output row PF_AHEAD visits ahead in a visiting order; returns the codes' index (q where they are cluster-sorted) */
static inline __attribute__((always_inline)) i64 rows_visit(const int32_t *order, int csort, i64 q, i64 p1, const void *lab,
        int lab_kind, const float *W, i64 wstride, const i64 *woff, const float *out, i64 Fo, i64 *p) {
    *p = order ? order[q] : q;
    if (order && q + PF_AHEAD < p1) {
        i64 pp = order[q + PF_AHEAD];
        if (!csort) PREFETCH_CODES(pp);
        PREFETCH_ROW(out + pp * Fo, Fo, 1);
    }
    return csort ? q : *p;
}
/* the next visit (q + 1 < p1) when it is in cluster k with cnt terms (always for PCA; mostly for CPCA, visited cluster
   by cluster), to combine both at once: its weights, its point in *p2 (prefetching as rows_visit); else NULL */
static inline __attribute__((always_inline)) const float *rows_pair(const int32_t *order, int csort, i64 q, i64 p1, const void *lab,
        int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, i64 k, i64 cnt, const float *out,
        i64 Fo, i64 *p2) {
    i64 pc2 = rows_visit(order, csort, q + 1, p1, lab, lab_kind, W, wstride, woff, out, Fo, p2), cnt2;
    i64 k2 = lab_at(lab, lab_kind, pc2);
    const float *u = weights_of(W, wstride, woff, nk, nuse, k2, pc2, &cnt2);
    return k2 == k && cnt2 == cnt ? u : NULL;
}

/* no view, rows of many floats (MRT's 49 x 3 = 147) with weights, AVX-512: the rows layout padded
   to 16 floats (prt_rows_pad), e_p summed 16 floats per vector in chunks of up to 6 vectors, two
   points of one cluster per load of the constants, and written straight into the unpadded output
   rows under a mask (the 8-lane pass combines into a padded buffer, then copies it out). Each
   float is the same FMA chain as in the 8-lane pass, so the same bits. */
#define ROWS16_MIN 97  /* Fo from which the wide pass runs: for glossy 24 x 3 = 72 it was slower (PCA 8 at 50k points, 1 thread: 0.66 -> 0.75 ms) */
#if HAVE_W16
static inline __attribute__((always_inline)) void rows16_chunk(const int NBC, const int two, const float *Tc, i64 F, int mean,
        const float *w, const float *u, i64 cnt, float *o1, float *o2, i64 nrem) {
#define R16_INIT(k) __m512 a##k = _mm512_setzero_ps(), c##k = _mm512_setzero_ps();                              \
    if (k < NBC && mean) { a##k = _mm512_loadu_ps(Tc + 16 * k); c##k = a##k; }
#define R16_STEP(k) if (k < NBC) {                                                                              \
        __m512 t_ = _mm512_loadu_ps(Tb + 16 * k);                                                               \
        IN_REG(t_);                                                                                             \
        a##k = _mm512_fmadd_ps(wi, t_, a##k);                                                                   \
        if (two) c##k = _mm512_fmadd_ps(ui, t_, c##k);                                                          \
    }
#define R16_STORE(k) if (k < NBC) {                                                                             \
        __mmask16 m_ = lanes16(nrem - 16 * k);                                                                  \
        _mm512_mask_storeu_ps(o1 + 16 * k, m_, a##k);                                                           \
        if (two) _mm512_mask_storeu_ps(o2 + 16 * k, m_, c##k);                                                  \
    }
#define EACH6(X) X(0) X(1) X(2) X(3) X(4) X(5)
    EACH6(R16_INIT)
    const float *Tb = Tc + (mean ? F : 0);
    for (i64 i = 0; i < cnt; i++, Tb += F) {
        __m512 wi = _mm512_set1_ps(w[i]), ui = two ? _mm512_set1_ps(u[i]) : wi;
        EACH6(R16_STEP)
    }
    EACH6(R16_STORE)
#undef R16_INIT
#undef R16_STEP
#undef R16_STORE
#undef EACH6
}
#define R16_CASE(n) case n:                                                                                    \
        if (u) rows16_chunk(n, 1, Tc, F, mean, w, u, cnt, o1, o2c, nrem);                                          \
        else rows16_chunk(n, 0, Tc, F, mean, w, u, cnt, o1, o2c, nrem);                                            \
        break;
static void rows16_range(const int32_t *order, int csort, i64 p0, i64 p1, i64 F, i64 Fo, const void *lab, int lab_kind,
                         const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 J,
                         float *out) {
    const i64 nv = F / 16, nch = (nv + 5) / 6, cs = (nv + nch - 1) / nch;  /* nearly equal chunks of <= 6 vectors */
    for (i64 q = p0; q < p1; q++) {
        i64 p, pc = rows_visit(order, csort, q, p1, lab, lab_kind, W, wstride, woff, out, Fo, &p);
        i64 k = lab_at(lab, lab_kind, pc), cnt, p2;
        const float *w = weights_of(W, wstride, woff, nk, nuse, k, pc, &cnt), *u = NULL;
        const float *Tk = T + k * J * F;
        float *o2 = NULL;  /* the paired point's row */
        if (q + 1 < p1 && (u = rows_pair(order, csort, q, p1, lab, lab_kind, W, wstride, woff, nk, nuse, k, cnt, out, Fo, &p2))) {
            o2 = out + p2 * Fo;
            q++;
        }
        for (i64 b0 = 0; b0 < nv; b0 += cs) {
            const i64 nb = nv - b0 < cs ? nv - b0 : cs, nrem = Fo - 16 * b0;
            const float *Tc = Tk + 16 * b0;
            float *o1 = out + p * Fo + 16 * b0, *o2c = o2 ? o2 + 16 * b0 : NULL;
            switch (nb) { R16_CASE(1) R16_CASE(2) R16_CASE(3) R16_CASE(4) R16_CASE(5) default: R16_CASE(6) }
        }
    }
}
#undef R16_CASE
#endif
/* the row stride of the rows layout for rows of Fo floats and J terms: a multiple of 16 floats
   where the wide pass runs them (rows16_range), else of 8 */
int prt_rows_pad(i64 Fo, i64 J) {
    i64 f8 = (Fo + 7) / 8 * 8;
    return (int)(HAVE_W16 && J >= 2 && Fo >= ROWS16_MIN ? (Fo + 15) / 16 * 16 : f8);
}

/* no view: out[p, 0:Fo] = e_p; constants T [K, J, F], rows zero-padded from Fo to F floats */
static int prt_affine_rows_range(const int32_t *order, int csort, i64 p0, i64 p1, i64 P, i64 F, i64 Fo, const void *lab,
        int lab_kind, const float *W, i64 wstride, const i64 *woff,
                    const i64 *nk, i64 nuse, int mean, const float *T, i64 J, float *out) {
    (void)P;  /* the callers' point count: the range [p0, p1) is what is read */
    const i64 cs = chunk_size(F / 8), cs2 = chunk_size2(F / 8);
    float e[4096], f[4096];  /* rows padded from Fo to F: combined here, then copied */
    if (J == 1 && !W && mean && lab && !order && F == Fo) {  /* J == 1: no weights can also be an empty packed
                                                                   block (every point's n_k = 0) with J > 1 */
        vq_rows_range(p0, p1, F, lab, lab_kind, T, out);
        return 0;
    }
    if (F == 8) {
        small_rows_range(order, csort, p0, p1, Fo, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, J, out);
        return 0;
    }
#if HAVE_W16
    if (W && F % 16 == 0 && F == prt_rows_pad(Fo, J)) {
        rows16_range(order, csort, p0, p1, F, Fo, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, J, out);
        return 0;
    }
#endif
    for (i64 q = p0; q < p1; q++) {
        i64 p, pc = rows_visit(order, csort, q, p1, lab, lab_kind, W, wstride, woff, out, Fo, &p);
        i64 k = lab_at(lab, lab_kind, pc), cnt, p2;
        const float *w = weights_of(W, wstride, woff, nk, nuse, k, pc, &cnt), *u;
        const float *Tk = T + k * J * F;
        if (W && q + 1 < p1) {  /* the next visit in the same cluster with the same term count: both at once */
            if ((u = rows_pair(order, csort, q, p1, lab, lab_kind, W, wstride, woff, nk, nuse, k, cnt, out, Fo, &p2))) {
                if (F == Fo) {
                    combine2(F, cs2, Tk, mean, w, u, cnt, out + p * Fo, out + p2 * Fo);
                } else {
                    combine2(F, cs2, Tk, mean, w, u, cnt, e, f);
                    copy_row(out + p * Fo, e, Fo);
                    copy_row(out + p2 * Fo, f, Fo);
                }
                q++;
                continue;
            }
        }
        if (F == Fo) {
            combine(F, cs, Tk, mean, w, cnt, out + p * Fo);
        } else {
            combine(F, cs, Tk, mean, w, cnt, e);
            copy_row(out + p * Fo, e, Fo);
        }
    }
    return 0;
}

int prt_affine_rows(i64 P, i64 F, i64 Fo, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff,
        const i64 *nk, i64 nuse, int mean, const float *T, i64 J, float *out, const int32_t *order, int csort, int nthreads) {
    /* one contiguous range of points per thread; the range function sees every
       argument as a local (an OpenMP-outlined loop body reloads shared ones per point) */
    int flag = 0;
    i64 nth = nthreads > 0 ? nthreads : 1;
    /* one thread: no parallel region (as in prt_constants) */
    if (nth == 1) return prt_affine_rows_range(order, csort, 0, P, P, F, Fo, lab, lab_kind,
            W, wstride, woff, nk, nuse, mean, T, J, out);
    #pragma omp parallel for schedule(static, 1) num_threads(nth) reduction(|:flag)
    for (i64 t = 0; t < nth; t++) flag |= prt_affine_rows_range(order, csort, P * t / nth, P * (t + 1) / nth, P, F, Fo, lab, lab_kind,
            W, wstride, woff, nk, nuse, mean, T, J, out);
    return flag;
}

/* dense: sums y . e[c, o0 : o0 + 8 NBS] for one colour (DENSE1) or three (DENSE3), every index a
   compile-time constant so the accumulators stay in registers. Tc points at e-row (c, o0) of the
   mean term; colours are n_pad floats apart; yc at y[o0]. */
#define ACC_DOT(b) if (b >= 1 && b < NB_) r += a##b * LD(yc + 8 * b);
#define DENSE1(NBS)                                                                              \
static inline float dense1_##NBS(const float *Tc, i64 F, int mean, const float *w, i64 cnt, const float *yc) { \
    ACCUMULATE(NBS)                                                                              \
    v8 r = a0 * LD(yc);                                                                          \
    EACH12(ACC_DOT)                                                                              \
    return hsum(r);                                                                              \
}
/* RGB: the three colours' lane vectors of one point into rv[0], rv[8], rv[16] (so 8 points fill
   three hsum8 inputs); every index a compile-time constant, the accumulators in registers */
#define DENSE3V(NBS)                                                                             \
static inline void dense3v_##NBS(const float *T0, i64 n_pad, i64 F, int mean, const float *w, i64 cnt, \
                                 const float *yc, v8 *rv) {                                      \
    v8 a0[NBS], a1[NBS], a2[NBS];                                                                \
    const float *T1 = T0 + n_pad, *T2 = T0 + 2 * n_pad;                                          \
    for (int b = 0; b < NBS; b++) {                                                              \
        a0[b] = mean ? LD(T0 + 8 * b) : (v8){0};                                                 \
        a1[b] = mean ? LD(T1 + 8 * b) : (v8){0};                                                 \
        a2[b] = mean ? LD(T2 + 8 * b) : (v8){0};                                                 \
    }                                                                                            \
    i64 s = mean ? F : 0;                                                                        \
    for (i64 i = 0; i < cnt; i++, s += F) {                                                      \
        float wi = w[i];                                                                         \
        for (int b = 0; b < NBS; b++) {                                                          \
            a0[b] += wi * LD(T0 + s + 8 * b);                                                    \
            a1[b] += wi * LD(T1 + s + 8 * b);                                                    \
            a2[b] += wi * LD(T2 + s + 8 * b);                                                    \
        }                                                                                        \
    }                                                                                            \
    v8 y0 = LD(yc);                                                                              \
    IN_REG(y0);                                                                                  \
    v8 r0 = a0[0] * y0, r1 = a1[0] * y0, r2 = a2[0] * y0;                                        \
    for (int b = 1; b < NBS; b++) {                                                              \
        v8 yb = LD(yc + 8 * b);                                                                  \
        IN_REG(yb);                                                                              \
        r0 += a0[b] * yb; r1 += a1[b] * yb; r2 += a2[b] * yb;                                    \
    }                                                                                            \
    rv[0] = r0; rv[8] = r1; rv[16] = r2;                                                         \
}
/* one point: the three colours' sums straight into o (assigned: 0 + -0 would be +0, where store8_rgb keeps the
   -0 of a point reduced in a block of 8, and a point's bits would depend on the thread split) */
#define DENSE3(NBS)                                                                              \
static inline void dense3_##NBS(const float *T0, i64 n_pad, i64 F, int mean, const float *w, i64 cnt, \
                                const float *yc, float *o) {                                     \
    v8 rv[17];                                                                                   \
    dense3v_##NBS(T0, n_pad, F, mean, w, cnt, yc, rv);                                           \
    o[0] = hsum(rv[0]); o[1] = hsum(rv[8]); o[2] = hsum(rv[16]);                                 \
}
/* two points of one cluster with the same term count (weights w, u; views yc, zc): each T load
   feeds both points' FMAs; each point's sums in dense3v's order (the same bits, paired or not).
   Lane vectors to rv[0], rv[8], rv[16] (first point) and rv[1], rv[9], rv[17] (second). */
#define DENSE3V2(NBS)                                                                            \
static inline void dense3v2_##NBS(const float *T0, i64 n_pad, i64 F, int mean, const float *w, const float *u, \
                                  i64 cnt, const float *yc, const float *zc, v8 *rv) {           \
    v8 a0[NBS], a1[NBS], a2[NBS], c0[NBS], c1[NBS], c2[NBS];                                     \
    const float *T1 = T0 + n_pad, *T2 = T0 + 2 * n_pad;                                          \
    for (int b = 0; b < NBS; b++) {                                                              \
        a0[b] = c0[b] = mean ? LD(T0 + 8 * b) : (v8){0};                                         \
        a1[b] = c1[b] = mean ? LD(T1 + 8 * b) : (v8){0};                                         \
        a2[b] = c2[b] = mean ? LD(T2 + 8 * b) : (v8){0};                                         \
    }                                                                                            \
    i64 s = mean ? F : 0;                                                                        \
    for (i64 i = 0; i < cnt; i++, s += F) {                                                      \
        float wi = w[i], ui = u[i];                                                              \
        for (int b = 0; b < NBS; b++) {                                                          \
            v8 t0 = LD(T0 + s + 8 * b), t1 = LD(T1 + s + 8 * b), t2 = LD(T2 + s + 8 * b);        \
            IN_REG(t0); IN_REG(t1); IN_REG(t2);                                                  \
            a0[b] += wi * t0; a1[b] += wi * t1; a2[b] += wi * t2;                                \
            c0[b] += ui * t0; c1[b] += ui * t1; c2[b] += ui * t2;                                \
        }                                                                                        \
    }                                                                                            \
    v8 y0 = LD(yc), z0 = LD(zc);                                                                 \
    IN_REG(y0); IN_REG(z0);                                                                      \
    v8 r0 = a0[0] * y0, r1 = a1[0] * y0, r2 = a2[0] * y0;                                        \
    v8 q0 = c0[0] * z0, q1 = c1[0] * z0, q2 = c2[0] * z0;                                        \
    for (int b = 1; b < NBS; b++) {                                                              \
        v8 yb = LD(yc + 8 * b), zb = LD(zc + 8 * b);                                             \
        IN_REG(yb); IN_REG(zb);                                                                  \
        r0 += a0[b] * yb; r1 += a1[b] * yb; r2 += a2[b] * yb;                                    \
        q0 += c0[b] * zb; q1 += c1[b] * zb; q2 += c2[b] * zb;                                    \
    }                                                                                            \
    rv[0] = r0; rv[8] = r1; rv[16] = r2; rv[1] = q0; rv[9] = q1; rv[17] = q2;                    \
}
CHUNKS(DENSE1)
DENSE3V(1) DENSE3V(2) DENSE3V(3) DENSE3V(4) DENSE3V(5) DENSE3V(6) DENSE3V(7)
/* 6 NBS accumulators + 3 T vectors + 2 weights in the vector registers: 32 with AVX-512VL, else 16 */
#if defined(__AVX512VL__)
#define MAXNBS2 3
DENSE3V2(1) DENSE3V2(2) DENSE3V2(3)
#else
#define MAXNBS2 1
DENSE3V2(1)
#endif
DENSE3(1) DENSE3(2) DENSE3(3) DENSE3(4) DENSE3(5) DENSE3(6) DENSE3(7)
/* dense, RGB, 4 <= n_pad / 8 <= 8 (n_out 25..64: MRT's 7x7 tents), with AVX-512: dense3v's sums
   16 outputs per vector, NB = ceil(n_pad / 16) vectors per colour, the last one masked to ml's
   lanes (n_pad's last 8 when n_pad is an odd number of 8s: the next colour's row is not read),
   and the view row read in place, masked to its n_out floats (no zero-padded copy). Each colour's
   16-lane dot is folded to 8 lanes (low + high half) for store8_rgb / hsum, the same association
   whether a point is reduced alone, in a block of 8 or paired (dense3w2). Half the instructions of
   the 8-lane kernel, whose FMA loop ran at a third of the peak rate on an Intel Xeon. */
#if HAVE_W16
/* the last block under ml where M (a masked last block) is set: a zero-masking load costs an extra ALU uop
   on Intel, on the FMA ports (measured: the masked chunk's loop took 1.5x the unmasked one's time) */
#define MLD(b, p) (MK_ && b == NB_ - 1 ? _mm512_maskz_loadu_ps(ml, (p)) : _mm512_loadu_ps(p))
#define DENSE3W(NB, M)                                                                           \
static inline void dense3w_##NB##_##M(const float *T0, i64 n_pad, i64 F, int mean, const float *w, i64 cnt, \
                                      const float *yr, i64 n_out, __mmask16 ml, __m512 *r3) {    \
    enum { NB_ = NB, MK_ = M };                                                                  \
    __m512 a0[NB], a1[NB], a2[NB];                                                               \
    const float *T1 = T0 + n_pad, *T2 = T0 + 2 * n_pad;                                          \
    for (int b = 0; b < NB; b++) {                                                               \
        a0[b] = mean ? MLD(b, T0 + 16 * b) : _mm512_setzero_ps();                                \
        a1[b] = mean ? MLD(b, T1 + 16 * b) : _mm512_setzero_ps();                                \
        a2[b] = mean ? MLD(b, T2 + 16 * b) : _mm512_setzero_ps();                                \
    }                                                                                            \
    i64 s = mean ? F : 0;                                                                        \
    for (i64 i = 0; i < cnt; i++, s += F) {                                                      \
        __m512 wi = _mm512_set1_ps(w[i]);                                                        \
        for (int b = 0; b < NB; b++) {                                                           \
            a0[b] = _mm512_fmadd_ps(wi, MLD(b, T0 + s + 16 * b), a0[b]);                         \
            a1[b] = _mm512_fmadd_ps(wi, MLD(b, T1 + s + 16 * b), a1[b]);                         \
            a2[b] = _mm512_fmadd_ps(wi, MLD(b, T2 + s + 16 * b), a2[b]);                         \
        }                                                                                        \
    }                                                                                            \
    __m512 y0 = _mm512_maskz_loadu_ps(lanes16(n_out), yr);                                       \
    __m512 r0 = _mm512_mul_ps(a0[0], y0), r1 = _mm512_mul_ps(a1[0], y0), r2 = _mm512_mul_ps(a2[0], y0); \
    for (int b = 1; b < NB; b++) {                                                               \
        __m512 yb = _mm512_maskz_loadu_ps(lanes16(n_out - 16 * b), yr + 16 * b);                 \
        r0 = _mm512_fmadd_ps(a0[b], yb, r0); r1 = _mm512_fmadd_ps(a1[b], yb, r1); r2 = _mm512_fmadd_ps(a2[b], yb, r2); \
    }                                                                                            \
    r3[0] = r0; r3[1] = r1; r3[2] = r2;                                                          \
}
/* two points of one cluster (weights w, u; view rows yr, zr): each T load feeds both points' FMAs,
   each point's sums in dense3w's order. Blocks B0 .. B0 + NBC - 1 (NBC <= 2) of each colour, over
   every term, then their share of the dot, r (point 1) and q (point 2) running across the chunks:
   12 accumulators at a time, where all 4 blocks' 24 left GCC spilling in the loop (0.8x unpaired). */
static inline __attribute__((always_inline)) void dense3w2_chunk(const int B0, const int NBC, const int NB, const int MK_, const float *T0,
        i64 n_pad, i64 F, int mean, const float *w, const float *u, i64 cnt, const float *yr, const float *zr, i64 n_out,
        __mmask16 ml, __m512 *r, __m512 *q) {
    const int NB_ = NB;
    const float *T1 = T0 + n_pad, *T2 = T0 + 2 * n_pad;
    /* named accumulators (colour c, block B0 + k: a<c><k> point 1, c<c><k> point 2): GCC kept arrays of them on the stack */
#define W2_INIT(k) __m512 a0##k, a1##k, a2##k, c0##k, c1##k, c2##k;                                          \
    if (k < NBC) {                                                                                          \
        const int b = B0 + k;                                                                               \
        a0##k = c0##k = mean ? MLD(b, T0 + 16 * b) : _mm512_setzero_ps();                                   \
        a1##k = c1##k = mean ? MLD(b, T1 + 16 * b) : _mm512_setzero_ps();                                   \
        a2##k = c2##k = mean ? MLD(b, T2 + 16 * b) : _mm512_setzero_ps();                                   \
    } else a0##k = a1##k = a2##k = c0##k = c1##k = c2##k = _mm512_setzero_ps();
#define W2_STEP(k) if (k < NBC) {                                                                           \
        const int b = B0 + k;                                                                               \
        __m512 t0 = MLD(b, T0 + s + 16 * b), t1 = MLD(b, T1 + s + 16 * b), t2 = MLD(b, T2 + s + 16 * b);    \
        IN_REG(t0); IN_REG(t1); IN_REG(t2);                                                                 \
        a0##k = _mm512_fmadd_ps(wi, t0, a0##k); a1##k = _mm512_fmadd_ps(wi, t1, a1##k); a2##k = _mm512_fmadd_ps(wi, t2, a2##k); \
        c0##k = _mm512_fmadd_ps(ui, t0, c0##k); c1##k = _mm512_fmadd_ps(ui, t1, c1##k); c2##k = _mm512_fmadd_ps(ui, t2, c2##k); \
    }
#define W2_DOT(k) if (k < NBC) {                                                                            \
        const int b = B0 + k;                                                                               \
        __mmask16 mb = lanes16(n_out - 16 * b);                                                             \
        __m512 yb = _mm512_maskz_loadu_ps(mb, yr + 16 * b), zb = _mm512_maskz_loadu_ps(mb, zr + 16 * b);    \
        if (b == 0) {                                                                                       \
            r[0] = _mm512_mul_ps(a0##k, yb); r[1] = _mm512_mul_ps(a1##k, yb); r[2] = _mm512_mul_ps(a2##k, yb); \
            q[0] = _mm512_mul_ps(c0##k, zb); q[1] = _mm512_mul_ps(c1##k, zb); q[2] = _mm512_mul_ps(c2##k, zb); \
        } else {                                                                                            \
            r[0] = _mm512_fmadd_ps(a0##k, yb, r[0]); r[1] = _mm512_fmadd_ps(a1##k, yb, r[1]); r[2] = _mm512_fmadd_ps(a2##k, yb, r[2]); \
            q[0] = _mm512_fmadd_ps(c0##k, zb, q[0]); q[1] = _mm512_fmadd_ps(c1##k, zb, q[1]); q[2] = _mm512_fmadd_ps(c2##k, zb, q[2]); \
        }                                                                                                   \
    }
    W2_INIT(0) W2_INIT(1)
    i64 s = mean ? F : 0;
    for (i64 i = 0; i < cnt; i++, s += F) {
        __m512 wi = _mm512_set1_ps(w[i]), ui = _mm512_set1_ps(u[i]);
        W2_STEP(0) W2_STEP(1)
    }
    W2_DOT(0) W2_DOT(1)
#undef W2_INIT
#undef W2_STEP
#undef W2_DOT
}
#define DENSE3W2(NB, M)                                                                          \
static inline void dense3w2_##NB##_##M(const float *T0, i64 n_pad, i64 F, int mean, const float *w, const float *u, \
                                 i64 cnt, const float *yr, const float *zr, i64 n_out, __mmask16 ml, __m512 *r, __m512 *q) { \
    dense3w2_chunk(0, 2, NB, M, T0, n_pad, F, mean, w, u, cnt, yr, zr, n_out, ml, r, q);        \
    if (NB > 2) dense3w2_chunk(2, NB - 2, NB, M, T0, n_pad, F, mean, w, u, cnt, yr, zr, n_out, ml, r, q); \
}
DENSE3W(2, 0) DENSE3W(3, 0) DENSE3W(4, 0) DENSE3W2(2, 0) DENSE3W2(3, 0) DENSE3W2(4, 0)
DENSE3W(2, 1) DENSE3W(3, 1) DENSE3W(4, 1) DENSE3W2(2, 1) DENSE3W2(3, 1) DENSE3W2(4, 1)
#undef MLD
/* a point's term weights in lanes: [1 if mean, w_0 .. w_{cnt-1}, 0 ..] (mean + cnt <= 16) */
static inline __m512 term16(const float *w, i64 cnt, int mean) {
    __m512 v = w ? _mm512_maskz_expandloadu_ps((__mmask16)(lanes16(mean + cnt) & ~lanes16(mean)), w) : _mm512_setzero_ps();
    return mean ? _mm512_mask_mov_ps(v, (__mmask16)1, _mm512_set1_ps(1.0f)) : v;
}
/* the tail rows' share of a point's colour sums: r[c] += (y_o w) . tl[c, o] over the rt rows o past the
   nb 16-row blocks, terms in lanes (tl: the cluster's block of dense_tail's table), only in the lanes m of the
   point's terms: a cluster's rows past its own term count (CPCA adaptive) are left from earlier lights by the
   constants kernel, and a non-finite value there times a zero weight would be NaN */
static inline void dense_tail(__m512 *r, const float *tl, i64 rt, const float *yt, __m512 wv, __mmask16 m) {
    for (i64 o = 0; o < rt; o++) {
        __m512 vy = _mm512_mul_ps(_mm512_set1_ps(yt[o]), wv);
        r[0] = _mm512_mask3_fmadd_ps(vy, _mm512_loadu_ps(tl + 16 * o), r[0], m);
        r[1] = _mm512_mask3_fmadd_ps(vy, _mm512_loadu_ps(tl + 16 * (rt + o)), r[1], m);
        r[2] = _mm512_mask3_fmadd_ps(vy, _mm512_loadu_ps(tl + 16 * (2 * rt + o)), r[2], m);
    }
}
/* one point (as dense3w) or two of one cluster (as dense3w2, when u is not NULL) into rv: nb blocks of 16 rows,
   then, with a tail table (tl), its rt rows */
static inline void dense3w(i64 nb, const float *T0, i64 n_pad, i64 F, int mean, const float *w, const float *u, i64 cnt,
                           const float *yr, const float *zr, i64 n_out, __mmask16 ml, const float *tl, i64 rt, v8 *rv) {
    __m512 r[3], q[3] = {_mm512_setzero_ps(), _mm512_setzero_ps(), _mm512_setzero_ps()};  /* q: only with u */
#define W_CASE(n, m) case 2 * n + m:                                                                            \
        if (u) dense3w2_##n##_##m(T0, n_pad, F, mean, w, u, cnt, yr, zr, n_out, ml, r, q);                      \
        else dense3w_##n##_##m(T0, n_pad, F, mean, w, cnt, yr, n_out, ml, r);                                   \
        break;
    switch (2 * nb + (ml != (__mmask16)0xFFFF)) {
    W_CASE(2, 0) W_CASE(2, 1) W_CASE(3, 0) W_CASE(3, 1) W_CASE(4, 0) default: W_CASE(4, 1)
    }
#undef W_CASE
    if (tl) {
        const __mmask16 m = lanes16(mean + cnt);
        dense_tail(r, tl, rt, yr + 16 * nb, term16(w, cnt, mean), m);
        if (u) dense_tail(q, tl, rt, zr + 16 * nb, term16(u, cnt, mean), m);
    }
    rv[0] = fold16(r[0]); rv[8] = fold16(r[1]); rv[16] = fold16(r[2]);
    if (u) { rv[1] = fold16(q[0]); rv[9] = fold16(q[1]); rv[17] = fold16(q[2]); }
}
#endif
/* the colour stride (n_out rows zero-padded) the dense kernel should be given: a multiple of 16
   floats where its 16-lane kernel runs (25 to 64 rows, AVX-512), so that each colour's and each
   term's rows start on a 64-byte line (at a stride of 56 floats, the 16-float loads of every other
   row straddled two lines: the kernel ran at 0.6 of its aligned speed); else a multiple of 8 */
int prt_dense_pad(i64 n_out) {
    i64 n8 = (n_out + 7) / 8 * 8;
    return (int)(HAVE_W16 && n8 >= 32 && n8 <= 64 ? (n_out + 15) / 16 * 16 : n8);
}
#define CASE_DENSE1(NB) case NB: return dense1_##NB(Tc, F, mean, w, cnt, yc);

static inline float dense1(int nbs, const float *Tc, i64 F, int mean, const float *w, i64 cnt, const float *yc) {
    switch (nbs) { CHUNKS(CASE_DENSE1) default: return 0.0f; }
}

/* one visited point q (point p) of the dense kernel: prefetches PF_AHEAD visits ahead (visiting
   order), its weights (*w, *cnt) and view row (*yp: copied zero-padded into yb when n_out is not a
   multiple of 8, unless yb is NULL: the row itself) and cluster (*kp); returns its cluster's constants */
static inline const float *dense_point(const int32_t *order, int csort, i64 q, i64 p1, i64 p, i64 n_out, i64 n_pad, i64 F, i64 J,
                                       const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk,
                                       i64 nuse, const float *T, const float *y, float *yb, const float **w, i64 *cnt, const float **yp, i64 *kp) {
    i64 pc = csort ? q : p;
    if (order && q + PF_AHEAD < p1) {
        i64 pp = order[q + PF_AHEAD];
        if (!csort) PREFETCH_CODES(pp);
        PREFETCH_ROW(y + pp * n_out, n_out, 0);
    }
    i64 k = lab_at(lab, lab_kind, pc);
    *kp = k;
    *w = weights_of(W, wstride, woff, nk, nuse, k, pc, cnt);
    const float *yr = y + p * n_out;
    if (n_out != n_pad && yb) {
        for (i64 r = 0; r < n_out; r++) yb[r] = yr[r];
        for (i64 r = n_out; r < n_pad; r++) yb[r] = 0.0f;
        yr = yb;
    }
    *yp = yr;
    return T + k * J * F;
}

/* the mean-only RGB dense loop for NBS vectors per colour (vq_dense_range) */
#define VQ_DENSE_CASE(NBS)                                                                       \
    case NBS:                                                                                    \
        for (; q + 8 <= p1; q += 8) {                                                            \
            for (int l = 0; l < 8; l++) {                                                        \
                pl[l] = q + l;                                                                   \
                dense3v_##NBS(T + lab_at(lab, lab_kind, q + l) * J * F, n_pad, F, 1, 0, 0, y + (q + l) * n_out, R + l); \
            }                                                                                    \
            *flag |= store8_rgb(R, out, pl, 1);                                                  \
        }                                                                                        \
        break;
#define VQ_DENSE_CASES VQ_DENSE_CASE(1) VQ_DENSE_CASE(2) VQ_DENSE_CASE(3) VQ_DENSE_CASE(4) VQ_DENSE_CASE(5) VQ_DENSE_CASE(6) \
    VQ_DENSE_CASE(7)
/* mean only (VQ), RGB, n_out a multiple of 8 (<= 56), points in order: y_p . T_k per colour, view
   rows read in place, 8 points at a time from p0; returns where it stopped (the rest: the general
   loop). Without the general loop's per-point bookkeeping (weights, order, prefetch, padding, the
   switch on nbt), which costs as much as the arithmetic here (measured: 1.2x). Its own function,
   not inlined: inside prt_affine_dense_range it slowed the general loop by 15-27% (codegen). */
static __attribute__((noinline)) i64 vq_dense_range(i64 p0, i64 p1, i64 n_out, const void *lab, int lab_kind, const float *T,
                                                    i64 J, const float *y, float *out, int *flag) {
    const i64 n_pad = n_out, F = 3 * n_pad;
    v8 R[24];
    i64 pl[8], q = p0;
    switch (n_pad / 8) { VQ_DENSE_CASES default: break; }
    return q;
}

/* dense view: constants colour-major T [K, J, C, n_pad] (rows zero-padded from n_out to n_pad,
   a multiple of 8); out[p, c] = y_p . e_p[c], e_p accumulated in registers chunk by chunk and
   dotted with the view as it is formed (RGB with n_pad <= 56: all three colours in one pass, 8
   points reduced together; measured on MRT's 49 rows, 1.5x faster than colour by colour).
   The view row is copied into a zero-padded buffer when n_out is not a multiple of 8.
   Returns 2 if an output is not finite. */
static int prt_affine_dense_range(const int32_t *order, int csort, i64 p0, i64 p1, i64 P, i64 n_out, i64 n_pad, i64 C,
        const void *lab, int lab_kind, const float *W, i64 wstride,
                     const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 J,
                     const float *y, float *out, const float *tail, i64 rt) {
    (void)P;  /* the callers' point count: the range [p0, p1) is what is read */
    i64 F = n_pad * C, nbt = n_pad / 8, cs = chunk_size(nbt);
    int flag = 0;
    i64 q = p0;
#if HAVE_W16
    /* weights (PCA, CPCA, MRT-PCA), RGB, 32 to 64 rows: 16 rows per vector (dense3w) for every point of the call */
    const int wide = C == 3 && W && nbt >= 4 && nbt <= 8;
    /* blocks of 16 rows: all of them, the last under ml; or, with a tail table, the whole ones before the tail rows */
    const i64 nbw = tail ? n_out / 16 : (n_pad + 15) / 16;
    const __mmask16 ml = tail ? (__mmask16)0xFFFF : lanes16(n_pad - 16 * (nbw - 1));
#else
    const int wide = 0;
    (void)tail; (void)rt;
#endif
    if (C == 3 && (nbt <= 7 || wide)) {
        /* RGB: 8 points at a time, their 24 dot products reduced together */
        v8 R[24];
        float yb[56], zb[56];
        i64 pl[8];
        if (!W && mean && !order && n_out == n_pad) q = vq_dense_range(q, p1, n_out, lab, lab_kind, T, J, y, out, &flag);
        for (; q + 8 <= p1; q += 8) {
            for (int l = 0; l < 8; l++) {
                const float *w, *yp;
                i64 cnt;
                pl[l] = order ? order[q + l] : q + l;
                i64 k;
                const float *Tk = dense_point(order, csort, q + l, p1, pl[l], n_out, n_pad, F, J, lab, lab_kind, W, wstride, woff, nk,
                                              nuse, T, y, wide ? NULL : yb, &w, &cnt, &yp, &k);
#if HAVE_W16
                if (wide) {
                    const float *u = NULL, *zp = NULL;
                    i64 cnt2;
                    if (l < 7 && T + lab_at(lab, lab_kind, csort ? q + l + 1 : (order ? order[q + l + 1] : q + l + 1)) * J * F == Tk) {
                        pl[l + 1] = order ? order[q + l + 1] : q + l + 1;  /* the next visit, same cluster: both at once */
                        dense_point(order, csort, q + l + 1, p1, pl[l + 1], n_out, n_pad, F, J, lab, lab_kind, W, wstride, woff, nk, nuse,
                                    T, y, NULL, &u, &cnt2, &zp, &k);
                    }
                    dense3w(nbw, Tk, n_pad, F, mean, w, u, cnt, yp, zp, n_out, ml, tail ? tail + k * 3 * rt * 16 : NULL, rt, R + l);
                    if (u) l++;
                    continue;
                }
#endif
                if (W && nbt <= MAXNBS2 && l < 7
                    && T + lab_at(lab, lab_kind, csort ? q + l + 1 : (order ? order[q + l + 1] : q + l + 1)) * J * F == Tk) {
                    /* the next visit is in the same cluster (so the same term count): both at once */
                    const float *u, *zp;
                    i64 cnt2;
                    pl[l + 1] = order ? order[q + l + 1] : q + l + 1;
                    dense_point(order, csort, q + l + 1, p1, pl[l + 1], n_out, n_pad, F, J, lab, lab_kind, W, wstride, woff, nk, nuse, T, y,
                                zb, &u, &cnt2, &zp, &k);
                    switch (nbt) {
                    case 1: dense3v2_1(Tk, n_pad, F, mean, w, u, cnt, yp, zp, R + l); break;
#if MAXNBS2 >= 3
                    case 2: dense3v2_2(Tk, n_pad, F, mean, w, u, cnt, yp, zp, R + l); break;
                    default: dense3v2_3(Tk, n_pad, F, mean, w, u, cnt, yp, zp, R + l); break;
#endif
                    }
                    l++;
                    continue;
                }
                switch (nbt) {
                case 1: dense3v_1(Tk, n_pad, F, mean, w, cnt, yp, R + l); break;
                case 2: dense3v_2(Tk, n_pad, F, mean, w, cnt, yp, R + l); break;
                case 3: dense3v_3(Tk, n_pad, F, mean, w, cnt, yp, R + l); break;
                case 4: dense3v_4(Tk, n_pad, F, mean, w, cnt, yp, R + l); break;
                case 5: dense3v_5(Tk, n_pad, F, mean, w, cnt, yp, R + l); break;
                case 6: dense3v_6(Tk, n_pad, F, mean, w, cnt, yp, R + l); break;
                default: dense3v_7(Tk, n_pad, F, mean, w, cnt, yp, R + l); break;
                }
            }
            flag |= store8_rgb(R, out, pl, !order);
        }
    }
    for (; q < p1; q++) {
        i64 p = order ? order[q] : q, cnt;
        float yb[4096];
        float o[16];
        const float *w, *yp;
        i64 k;
        const float *Tk = dense_point(order, csort, q, p1, p, n_out, n_pad, F, J, lab, lab_kind, W, wstride, woff, nk, nuse, T, y,
                                      wide ? NULL : yb, &w, &cnt, &yp, &k);
        for (i64 c = 0; c < C; c++) o[c] = 0.0f;
#if HAVE_W16
        if (wide) {
            v8 rv[17];
            dense3w(nbw, Tk, n_pad, F, mean, w, NULL, cnt, yp, NULL, n_out, ml, tail ? tail + k * 3 * rt * 16 : NULL, rt, rv);
            o[0] = hsum(rv[0]); o[1] = hsum(rv[8]); o[2] = hsum(rv[16]);  /* assigned, as in dense3_N */
        } else
#endif
        if (C == 3 && nbt <= 7) {
            switch (nbt) {
            case 1: dense3_1(Tk, n_pad, F, mean, w, cnt, yp, o); break;
            case 2: dense3_2(Tk, n_pad, F, mean, w, cnt, yp, o); break;
            case 3: dense3_3(Tk, n_pad, F, mean, w, cnt, yp, o); break;
            case 4: dense3_4(Tk, n_pad, F, mean, w, cnt, yp, o); break;
            case 5: dense3_5(Tk, n_pad, F, mean, w, cnt, yp, o); break;
            case 6: dense3_6(Tk, n_pad, F, mean, w, cnt, yp, o); break;
            default: dense3_7(Tk, n_pad, F, mean, w, cnt, yp, o); break;
            }
        } else {
            for (i64 c = 0; c < C; c++)
                for (i64 b0 = 0; b0 < nbt; b0 += cs) {
                    int nb = (int)(nbt - b0 < cs ? nbt - b0 : cs);
                    o[c] += dense1(nb, Tk + c * n_pad + 8 * b0, F, mean, w, cnt, yp + 8 * b0);
                }
        }
        for (i64 c = 0; c < C; c++) {
            out[p * C + c] = o[c];
            if (!(fabsf(o[c]) <= FLT_MAX)) flag |= 2;
        }
    }
    return flag;
}

/* the tail table of dense3w (AVX-512, RGB, weights): for n_out = 16 m + rt rows, 1 <= rt <= 8, m >= 2, in a layout
   padded to 16 and at most 16 terms, the rt rows past the m whole blocks as [K, 3, rt, 16], terms in lanes (zero past
   J): a point's share of them is rt FMAs per colour (dense_tail), where a zero-padded 16-row block took J per colour
   (MRT's 49 = 3 x 16 + 1 rows: 16 terms x 3 colours x 4 blocks of FMAs -> x 3 blocks + 3). Returns NULL (no table: the
   padded block) where that does not apply, where the table would pass 64 KiB (K rt > 341: its 48 K rt copies are
   paid by every call, however few its points), or the allocation fails; else the table, to free. Decided by the
   shapes alone, never by the number of points, so a point's bits do not depend on the size of the call (with a
   threshold on P they did: a review's finding). */
static float *dense_tail_table(i64 K, i64 n_out, i64 n_pad, i64 C, const float *W, const float *T, i64 J, i64 *rt) {
    *rt = 0;
#if HAVE_W16
    i64 r = n_out % 16, F = n_pad * C;
    if (!(C == 3 && W && n_pad % 16 == 0 && n_pad >= 32 && n_pad <= 64 && n_out >= 32 && r >= 1 && r <= 8 && J <= 16 && K >= 1
          && K * r <= 341))
        return NULL;
    float *tab = (float *)malloc((size_t)(K * 3 * r * 16) * sizeof(float));
    if (!tab) return NULL;
    for (i64 k = 0; k < K; k++)
        for (i64 c = 0; c < 3; c++)
            for (i64 o = 0; o < r; o++) {
                float *d = tab + ((k * 3 + c) * r + o) * 16;
                for (i64 j = 0; j < 16; j++) d[j] = j < J ? T[k * J * F + j * F + c * n_pad + (n_out - r) + o] : 0.0f;
            }
    *rt = r;
    return tab;
#else
    (void)K; (void)n_out; (void)n_pad; (void)C; (void)W; (void)T; (void)J;
    return NULL;
#endif
}

int prt_affine_dense(i64 K, i64 P, i64 n_out, i64 n_pad, i64 C, const void *lab, int lab_kind, const float *W, i64 wstride,
        const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 J, const float *y, float *out,
        const int32_t *order, int csort, int nthreads) {
    /* one contiguous range of points per thread; the range function sees every
       argument as a local (an OpenMP-outlined loop body reloads shared ones per point) */
    int flag = 0;
    i64 nth = nthreads > 0 ? nthreads : 1, rt;
    float *tail = dense_tail_table(K, n_out, n_pad, C, W, T, J, &rt);
    /* one thread: no parallel region (as in prt_constants) */
    if (nth == 1) {
        flag = prt_affine_dense_range(order, csort, 0, P, P, n_out, n_pad, C, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, J, y,
                                      out, tail, rt);
    } else {
        #pragma omp parallel for schedule(static, 1) num_threads(nth) reduction(|:flag)
        for (i64 t = 0; t < nth; t++) flag |= prt_affine_dense_range(order, csort, P * t / nth, P * (t + 1) / nth, P, n_out, n_pad, C,
                lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, J, y, out, tail, rt);
    }
    free(tail);
    return flag;
}

#if defined(__AVX2__)
#include <immintrin.h>
/* terms [8b, 8b + 8) of a point's term weights [1 if mean, w_0 .. w_{cnt-1}, 0 ..], straight from
   the stored weights by a masked load (masked-out lanes are not read: no fault before w or past
   its end). Built by element stores instead (GCC makes them a memcpy and a memset per point), the
   kernel's vector load of the buffer waits for the stores to retire: measured, 40% of the taps
   kernel's time on CPCA 16x2 with 4 taps. */
static inline v8 term_weights8(const float *w, i64 cnt, int mean, i64 b) {
    i64 lo = 8 * b - mean;                      /* the weight index at lane 0 */
    i64 l0 = lo < 0 ? -lo : 0, l1 = cnt - lo;   /* lanes [l0, l1) hold weights */
    if (l1 > 8) l1 = 8;
    v8 v = (v8){0};
    if (w && l1 > l0) {
        const float *src = (const float *)((uintptr_t)w + (intptr_t)(4 * lo));
#if defined(__AVX512VL__)  /* a k-mask load: no mask vector to build (MRT-PCA 15 vectors with taps: 0.62 -> 0.60 ms) */
        v = (v8)_mm256_maskz_loadu_ps((__mmask8)(((1u << l1) - 1u) & ~((1u << l0) - 1u)), src);
#else
        const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7);
        __m256i m = _mm256_and_si256(_mm256_cmpgt_epi32(_mm256_set1_epi32((int)l1), lane),
                                     _mm256_cmpgt_epi32(lane, _mm256_set1_epi32((int)l0 - 1)));
        v = (v8)_mm256_maskload_ps(src, m);
#endif
    }
    if (mean && b == 0) v[0] = 1.0f;
    return v;
}
#endif

/* taps, RGB, Jp = 8 NBJ terms: s[c] = sum_t g_t T[k, idx_t, c, :] in registers (three colours x
   NBJ vectors), then out[c] = s[c] . wv (wv = [1 if mean, w_0 .. w_{cnt-1}, 0 ..]: read from wv, or
   with AVX2 where wv is NULL, formed in registers from the stored weights w, cnt, mean by
   term_weights8); the lane vectors of one point go to rv[0], rv[8], rv[16] (so 8 points fill three
   hsum8 inputs). In registers, not copied into a buffer per point: MRT-PCA 15 vectors, whose
   weights are not exactly 16 stored floats, relit 0.67 ms against 16 vectors' 0.575 (Intel Xeon,
   50 000 points, 1 thread). */
#if defined(__AVX2__)
#define TWV(b) (wv ? LD(wv + 8 * (b)) : term_weights8(w, cnt, mean, (b)))
#else
#define TWV(b) LD(wv + 8 * (b))
#endif
#define TAPS3V(NBJ)                                                                              \
static inline void taps3v_##NBJ(const float *Tk, i64 R, i64 n_out, const i64 *ix, const float *gg, i64 ntap, i64 Jp, \
                                const float *wv, const float *w, i64 cnt, int mean, v8 *rv, int *flag) { \
    (void)w; (void)cnt; (void)mean;                                                              \
    v8 xw[NBJ];  /* the term weights, before the taps: the dot below then reads registers */     \
    for (int b = 0; b < NBJ; b++) xw[b] = TWV(b);                                                \
    v8 a0[NBJ], a1[NBJ], a2[NBJ];                                                                \
    for (int b = 0; b < NBJ; b++) { a0[b] = (v8){0}; a1[b] = (v8){0}; a2[b] = (v8){0}; }         \
    for (i64 t = 0; t < ntap; t++) {                                                             \
        i64 ri = ix[t];                                                                          \
        if ((uint64_t)ri >= (uint64_t)n_out) { *flag |= 1; continue; }  /* skipped, flagged */    \
        const float *r = Tk + ri * R;                                                            \
        float gt = gg[t];                                                                        \
        for (int b = 0; b < NBJ; b++) {                                                          \
            a0[b] += gt * LD(r + 8 * b);                                                         \
            a1[b] += gt * LD(r + Jp + 8 * b);                                                    \
            a2[b] += gt * LD(r + 2 * Jp + 8 * b);                                                \
        }                                                                                        \
    }                                                                                            \
    v8 r0 = a0[0] * xw[0], r1 = a1[0] * xw[0], r2 = a2[0] * xw[0];                              \
    for (int b = 1; b < NBJ; b++) {                                                              \
        v8 x = xw[b];                                                                            \
        r0 += a0[b] * x; r1 += a1[b] * x; r2 += a2[b] * x;                                       \
    }                                                                                            \
    rv[0] = r0; rv[8] = r1; rv[16] = r2;                                                         \
}
TAPS3V(1) TAPS3V(2) TAPS3V(3) TAPS3V(4)
/* one point: the three colours' sums into o */
#define TAPS3(NBJ)                                                                               \
static inline void taps3_##NBJ(const float *Tk, i64 R, i64 n_out, const i64 *ix, const float *gg, i64 ntap, i64 Jp,     \
                               const float *wv, const float *w, i64 cnt, int mean, float *o, int *flag) { \
    v8 rv[17];                                                                                   \
    taps3v_##NBJ(Tk, R, n_out, ix, gg, ntap, Jp, wv, w, cnt, mean, rv, flag);                    \
    o[0] = hsum(rv[0]); o[1] = hsum(rv[8]); o[2] = hsum(rv[16]);                                 \
}
TAPS3(1) TAPS3(2) TAPS3(3) TAPS3(4)

/* one point's taps: its valid tapped rows of its cluster's constants (rows, gs; *flag |= 1 for a
   tap outside [0, n_out), which is skipped) and its term weights wv = [1 if mean, w.., 0..] (Jp);
   returns how many taps were kept */

/* a point's term weights *wv = [1 if mean, w.., 0..] (Jp floats: the stored weights themselves
   when they are exactly that, else copied into buf); returns its cluster's constants T_k */
static inline const float *taps_weights(i64 pc, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff,
                                        const i64 *nk, i64 nuse, int mean, const float *T, i64 Jp, i64 R, i64 n_out,
                                        float *buf, const float **wvp) {
    i64 k = lab_at(lab, lab_kind, pc), cnt;
    const float *w = weights_of(W, wstride, woff, nk, nuse, k, pc, &cnt);
    static const float mean_only[32] = {1.0f};  /* [1, 0, ..]: VQ, or no weights kept */
    if (!mean && cnt == Jp) {  /* e.g. MRT-PCA with 16 vectors: no copy */
        *wvp = w;
        return T + k * n_out * R;
    }
    if (mean && cnt == 0 && Jp <= 32) {
        *wvp = mean_only;
        return T + k * n_out * R;
    }
    float *wv = buf;
    *wvp = buf;
#if defined(__AVX2__)
    if (Jp <= 32) {  /* whole-vector stores, which the kernel's vector loads of wv forward from */
        for (i64 b = 0; b < Jp / 8; b++) ST(wv + 8 * b, term_weights8(w, cnt, mean, b));
        return T + k * n_out * R;
    }
#endif
    i64 j = 0;
    if (mean) wv[j++] = 1.0f;
    for (i64 i = 0; i < cnt; i++) wv[j++] = w[i];
    for (; j < Jp; j++) wv[j] = 0.0f;
    return T + k * n_out * R;
}

/* the RGB kernels' view of a point's terms (Jp <= 32): with AVX2 its stored weights (*w, *cnt) and *wvp = NULL, for
   taps3v to form [1 if mean, w.., 0..] in registers, or the stored row itself in *wvp where it is exactly that; else
   taps_weights' buffer or stored row in *wvp. Returns its
   cluster's constants T_k. */
static inline const float *taps_terms(i64 pc, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff,
                                      const i64 *nk, i64 nuse, int mean, const float *T, i64 Jp, i64 R, i64 n_out, float *buf,
                                      const float **wvp, const float **w, i64 *cnt) {
#if defined(__AVX2__)
    i64 k = lab_at(lab, lab_kind, pc);
    *w = weights_of(W, wstride, woff, nk, nuse, k, pc, cnt);
    *wvp = !mean && *cnt == Jp ? *w : NULL;  /* exactly the stored row (MRT-PCA with 8 or 16 vectors): plain loads */
    (void)buf;
    return T + k * n_out * R;
#else
    *w = NULL;
    *cnt = 0;
    return taps_weights(pc, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, Jp, R, n_out, buf, wvp);
#endif
}

static inline i64 taps_point(i64 p, i64 pc, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk,
                             i64 nuse, int mean, const float *T, i64 Jp, i64 R, i64 n_out, i64 ntap, const i64 *idx,
                             const float *g, const float **rows, float *gs, float *wv, int *flag) {
    const float *wq;
    const float *Tk = taps_weights(pc, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, Jp, R, n_out, wv, &wq);
    if (wq != wv)
        for (i64 j = 0; j < Jp; j++) wv[j] = wq[j];
    i64 nt = 0;
    for (i64 t = 0; t < ntap; t++) {
        i64 r = idx[p * ntap + t];
        if (r < 0 || r >= n_out) { *flag |= 1; continue; }
        rows[nt] = Tk + r * R;
        gs[nt++] = g[p * ntap + t];
    }
    return nt;
}

/* taps: constants T [K, n_out, C, Jp] (J terms zero-padded to Jp, a multiple of 8; Jp = 1 for one term);
   s = sum_t g[p, t] T[k, idx[p, t]] ([C, Jp]); out[p, c] = (mean ? s[c, 0] : 0) + w_p . s[c, mean:mean+cnt].
   Returns 1 if a tap index is outside [0, n_out) (that tap is skipped), 2 if an output is not finite. */
static int prt_affine_taps_range(const int32_t *order, int csort, i64 p0, i64 p1, i64 P, i64 n_out, i64 C, const void *lab,
        int lab_kind, const float *W, i64 wstride,
                    const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 Jp,
                    i64 ntap, const i64 *idx, const float *g, float *out) {
    (void)P;  /* the callers' point count: the range [p0, p1) is what is read */
    i64 R = Jp * C;
    int flag = 0;
    i64 q = p0;
    if (Jp == 1) {
        /* one term (VQ: the mean alone; or one vector, no mean), constants unpadded [K, n_out, C]:
           o_c = s_p sum_t g_t T[k, idx_t, c], s_p = 1 (mean) or w_p0 (RGB with four valid taps: the
           sum taken pairwise) */
        for (; q < p1; q++) {
            i64 p = order ? order[q] : q, pc = csort ? q : p, cnt;
            if (order && q + PF_AHEAD < p1) {
                i64 pp = order[q + PF_AHEAD];
                if (!csort) PREFETCH_CODES(pp);
                __builtin_prefetch(idx + pp * ntap);
                __builtin_prefetch(g + pp * ntap);
            }
            i64 k = lab_at(lab, lab_kind, pc);
            const float *w = weights_of(W, wstride, woff, nk, nuse, k, pc, &cnt);
            const float sp = mean ? 1.0f : (cnt ? w[0] : 0.0f);
            const float *Tk = T + k * n_out * C;
            const i64 *ix = idx + p * ntap;
            const float *gg = g + p * ntap;
            if (C == 3) {
                float o0 = 0.0f, o1 = 0.0f, o2 = 0.0f;
                if (ntap == 4 && (uint64_t)ix[0] < (uint64_t)n_out && (uint64_t)ix[1] < (uint64_t)n_out
                    && (uint64_t)ix[2] < (uint64_t)n_out && (uint64_t)ix[3] < (uint64_t)n_out) {
                    /* four valid taps (MRT's bilinear tents), summed pairwise: two short chains
                       instead of one of four (measured, VQ 64 at 10k vertices: 1.12-1.16x) */
                    const float *r0 = Tk + ix[0] * 3, *r1 = Tk + ix[1] * 3, *r2 = Tk + ix[2] * 3, *r3 = Tk + ix[3] * 3;
                    float g0 = gg[0], g1 = gg[1], g2 = gg[2], g3 = gg[3];
                    o0 = (g0 * r0[0] + g1 * r1[0]) + (g2 * r2[0] + g3 * r3[0]);
                    o1 = (g0 * r0[1] + g1 * r1[1]) + (g2 * r2[1] + g3 * r3[1]);
                    o2 = (g0 * r0[2] + g1 * r1[2]) + (g2 * r2[2] + g3 * r3[2]);
                } else {
                    for (i64 t = 0; t < ntap; t++) {
                        i64 ri = ix[t];
                        if ((uint64_t)ri >= (uint64_t)n_out) { flag |= 1; continue; }  /* skipped, flagged */
                        const float *r = Tk + ri * 3;
                        float gt = gg[t];
                        o0 += gt * r[0]; o1 += gt * r[1]; o2 += gt * r[2];
                    }
                }
                o0 *= sp; o1 *= sp; o2 *= sp;
                out[p * 3] = o0; out[p * 3 + 1] = o1; out[p * 3 + 2] = o2;
                if (!(fabsf(o0) <= FLT_MAX && fabsf(o1) <= FLT_MAX && fabsf(o2) <= FLT_MAX)) flag |= 2;
                continue;
            }
            float o[16] = {0};
            for (i64 t = 0; t < ntap; t++) {
                i64 ri = ix[t];
                if ((uint64_t)ri >= (uint64_t)n_out) { flag |= 1; continue; }
                const float *r = Tk + ri * C;
                float gt = gg[t];
                for (i64 c = 0; c < C; c++) o[c] += gt * r[c];
            }
            for (i64 c = 0; c < C; c++) {
                float v = o[c] * sp;
                out[p * C + c] = v;
                if (!(fabsf(v) <= FLT_MAX)) flag |= 2;
            }
        }
        return flag;
    }
    if (C == 3 && Jp / 8 <= 4) {
        /* RGB: 8 points at a time, their 24 dot products reduced together */
        v8 Rv[24];
        float wv[32];
        i64 pl[8];
        for (; q + 8 <= p1; q += 8) {
            for (int l = 0; l < 8; l++) {
                pl[l] = order ? order[q + l] : q + l;
                if (order && q + l + PF_AHEAD < p1) {
                    i64 pp = order[q + l + PF_AHEAD];
                    if (!csort) PREFETCH_CODES(pp);
                    __builtin_prefetch(idx + pp * ntap);
                    __builtin_prefetch(g + pp * ntap);
                }
                const float *wq, *w;
                i64 cnt;
                const float *Tk = taps_terms(csort ? q + l : pl[l], lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, Jp, R, n_out,
                                             wv, &wq, &w, &cnt);
                const i64 *ix = idx + pl[l] * ntap;
                const float *gg = g + pl[l] * ntap;
                switch (Jp / 8) {
                case 1: taps3v_1(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, Rv + l, &flag); break;
                case 2: taps3v_2(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, Rv + l, &flag); break;
                case 3: taps3v_3(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, Rv + l, &flag); break;
                default: taps3v_4(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, Rv + l, &flag); break;
                }
            }
            flag |= store8_rgb(Rv, out, pl, !order);
        }
    }
    for (; q < p1; q++) {
        i64 p = order ? order[q] : q;
        if (order && q + PF_AHEAD < p1) {
            i64 pp = order[q + PF_AHEAD];
            if (!csort) PREFETCH_CODES(pp);
            __builtin_prefetch(idx + pp * ntap);
            __builtin_prefetch(g + pp * ntap);
        }
        float s[4096];
        float wv[4096];
        float o[16];
        const float *rows[64];
        float gs[64];
        i64 nbj = Jp / 8;
        if (C == 3 && nbj <= 4) {
            const float *wq, *w;
            i64 cnt;
            const float *Tk = taps_terms(csort ? q : p, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, Jp, R, n_out, wv, &wq, &w,
                                         &cnt);
            const i64 *ix = idx + p * ntap;
            const float *gg = g + p * ntap;
            switch (nbj) {
            case 1: taps3_1(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, o, &flag); break;
            case 2: taps3_2(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, o, &flag); break;
            case 3: taps3_3(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, o, &flag); break;
            default: taps3_4(Tk, R, n_out, ix, gg, ntap, Jp, wq, w, cnt, mean, o, &flag); break;
            }
        } else {
            i64 nt = taps_point(p, csort ? q : p, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, Jp, R, n_out, ntap, idx, g, rows,
                                gs, wv, &flag);
            gather_sum(R, rows, gs, nt, s);
            for (i64 c = 0; c < C; c++) o[c] = dot(wv, s + c * Jp, Jp);
        }
        for (i64 c = 0; c < C; c++) {
            out[p * C + c] = o[c];
            if (!(fabsf(o[c]) <= FLT_MAX)) flag |= 2;
        }
    }
    return flag;
}

int prt_affine_taps(i64 P, i64 n_out, i64 C, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff,
        const i64 *nk, i64 nuse, int mean, const float *T, i64 Jp, i64 ntap, const i64 *idx, const float *g, float *out,
        const int32_t *order, int csort, int nthreads) {
    /* one contiguous range of points per thread; the range function sees every
       argument as a local (an OpenMP-outlined loop body reloads shared ones per point) */
    int flag = 0;
    i64 nth = nthreads > 0 ? nthreads : 1;
    /* one thread: no parallel region (as in prt_constants) */
    if (nth == 1) return prt_affine_taps_range(order, csort, 0, P, P, n_out, C, lab, lab_kind, W,
            wstride, woff, nk, nuse, mean, T, Jp, ntap, idx, g, out);
    #pragma omp parallel for schedule(static, 1) num_threads(nth) reduction(|:flag)
    for (i64 t = 0; t < nth; t++) flag |= prt_affine_taps_range(order, csort, P * t / nth, P * (t + 1) / nth, P, n_out, C, lab,
            lab_kind, W, wstride, woff, nk, nuse, mean, T, Jp, ntap, idx, g, out);
    return flag;
}

/* One relight from a plan (relight_kernels.plan, AffineCodec's per-encoding cache): the per-cluster
   constants into T (prt_constants_lanes or prt_constants), then the per-point kernel (rows, dense or taps)
   — the arguments that do not change between lights read from a[] (PL_ fields, _PLAN_FIELDS in Python),
   one call where two ctypes calls of 11-19 converted arguments each cost about 4 us of a small relight.
   y0, y1: the view (dense: y [P, n_out] float32; taps: idx int64 [P, t], g float32 [P, t]). Returns
   16 (nothing computed past the check) if L holds a NaN or an infinity, else the point kernel's flag. */
enum { PL_KIND, PL_LANES, PL_K, PL_J, PL_JMAX, PL_NIN, PL_NOUT, PL_NPAD, PL_C, PL_MT, PL_SK, PL_SJ, PL_SO, PL_SC, PL_NKC,
       PL_MEAN, PL_P, PL_X, PL_FO, PL_LAB, PL_LABKIND, PL_W, PL_WSTRIDE, PL_WOFF, PL_NK, PL_NUSE, PL_ORDER, PL_CSORT,
       PL_NTAP, PL_N };
#define PL_PTR(i, T) ((T)(intptr_t)a[i])
int prt_relight_plan(const i64 *a, const float *L, float *T, float *out, const void *y0, const void *y1, int nthreads) {
    int bad = a[PL_LANES]
        ? prt_constants_lanes(a[PL_K], a[PL_J], a[PL_JMAX], a[PL_NIN], a[PL_C], PL_PTR(PL_MT, const float *), L, T, a[PL_SK],
                              a[PL_SJ], nthreads)
        : prt_constants(a[PL_K], a[PL_J], a[PL_JMAX], a[PL_NIN], a[PL_NOUT], a[PL_NPAD], a[PL_C], PL_PTR(PL_MT, const float *),
                        L, T, a[PL_SK], a[PL_SJ], a[PL_SO], a[PL_SC], PL_PTR(PL_NKC, const i64 *), (int)a[PL_MEAN], nthreads);
    if (bad) return 16;
    const void *lab = PL_PTR(PL_LAB, const void *);
    const float *W = PL_PTR(PL_W, const float *);
    const i64 *woff = PL_PTR(PL_WOFF, const i64 *), *nk = PL_PTR(PL_NK, const i64 *);
    const int32_t *order = PL_PTR(PL_ORDER, const int32_t *);
    const int lk = (int)a[PL_LABKIND], mean = (int)a[PL_MEAN], csort = (int)a[PL_CSORT];
    switch (a[PL_KIND]) {
    case 0:
        return prt_affine_rows(a[PL_P], a[PL_X], a[PL_FO], lab, lk, W, a[PL_WSTRIDE], woff, nk, a[PL_NUSE], mean, T, a[PL_J], out,
                               order, csort, nthreads);
    case 1:
        return prt_affine_dense(a[PL_K], a[PL_P], a[PL_FO], a[PL_X], a[PL_C], lab, lk, W, a[PL_WSTRIDE], woff, nk, a[PL_NUSE], mean, T,
                                a[PL_J], (const float *)y0, out, order, csort, nthreads);
    default:
        return prt_affine_taps(a[PL_P], a[PL_FO], a[PL_C], lab, lk, W, a[PL_WSTRIDE], woff, nk, a[PL_NUSE], mean, T, a[PL_X],
                               a[PL_NTAP], (const i64 *)y0, (const float *)y1, out, order, csort, nthreads);
    }
}

/* Green 2005 eq. 2.7 from a prefiltered cube-map pyramid (``PrefilteredEnvironment.lookup``, fused):
   acc[c] += wl E_sigma(x, y, z)[c], E bilinear in the face (clamped at its edges) and linear in
   log sigma between the two bracketing levels (clamped to the ladder); OpenGL face order.
   table [L 6 r r, C]; ladder [L] = log sigma_l increasing. The same float32 operations as the
   torch formulation (the sums in another order). */
static inline void sg_lookup(float x, float y, float z, float sigma, float wl, const float *table, i64 r, i64 L,
                             const float *ladder, i64 C, float *acc) {
    const float half = (float)r * 0.5f;
    const i64 lvl = 6 * r * r, rmax = r > 1 ? r - 2 : 0;
    float ax = fabsf(x), ay = fabsf(y), az = fabsf(z), sc, tc, mm;
    i64 face;
    if (ax >= ay && ax >= az) { mm = ax; face = x < 0; sc = x >= 0 ? -z : z; tc = -y; }
    else if (ay >= az) { mm = ay; face = 2 + (y < 0); sc = x; tc = y >= 0 ? z : -z; }
    else { mm = az; face = 4 + (z < 0); sc = z >= 0 ? x : -x; tc = -y; }
    if (mm < 1e-30f) mm = 1e-30f;
    sc /= mm; tc /= mm;
    float s = (sc + 1) * half - 0.5f, t = (tc + 1) * half - 0.5f;
    s = s < 0 ? 0 : (s > r - 1 ? r - 1 : s);
    t = t < 0 ? 0 : (t > r - 1 ? r - 1 : t);
    float sf = floorf(s), tf = floorf(t);
    /* a NaN coordinate (a non-finite direction) fails every compare above: texel 0 of the face, whose
       lookup is NaN through fs, ft (converting NaN to an integer is undefined behaviour) */
    i64 s0 = sf >= 0 ? (i64)(sf > rmax ? rmax : sf) : 0, t0 = tf >= 0 ? (i64)(tf > rmax ? rmax : tf) : 0;
    float fs = s - (float)s0, ft = t - (float)t0;
    fs = fs < 0 ? 0 : (fs > 1 ? 1 : fs);
    ft = ft < 0 ? 0 : (ft > 1 ? 1 : ft);
    i64 s1 = s0 + 1 > r - 1 ? r - 1 : s0 + 1, t1 = t0 + 1 > r - 1 ? r - 1 : t0 + 1;
    float ls = logf(sigma < 1e-12f ? 1e-12f : sigma), a = 0.0f;
    i64 lo = 0, hi = 0;
    if (L > 1) {
        /* searchsorted (left): the first ladder entry >= ls, by a branch-free binary search */
        i64 b = 0, len = L;
        while (len > 1) {
            i64 h = len / 2;
            b = ladder[b + h - 1] < ls ? b + h : b;
            len -= h;
        }
        hi = b + (ladder[b] < ls);
        hi = hi < 1 ? 1 : (hi > L - 1 ? L - 1 : hi);
        lo = hi - 1;
        a = (ls - ladder[lo]) / (ladder[hi] - ladder[lo]);
        a = a < 0 ? 0 : (a > 1 ? 1 : a);
    }
    i64 base = (face * r + t0) * r + s0, ds = s1 - s0, dt = (t1 - t0) * r;
    i64 tex[4] = {base, base + ds, base + dt, base + dt + ds};
    float w4[4] = {(1 - ft) * (1 - fs), (1 - ft) * fs, ft * (1 - fs), ft * fs};
    if (C == 3) {  /* RGB: the sums in registers (an array would chain through the stack) */
        float r0 = 0, r1 = 0, r2 = 0;
        for (int i = 0; i < 8; i++) {
            const float *tr = table + (tex[i & 3] + (i < 4 ? lo : hi) * lvl) * 3;
            float wt = w4[i & 3] * (i < 4 ? 1 - a : a) * wl;
            r0 += wt * tr[0]; r1 += wt * tr[1]; r2 += wt * tr[2];
        }
        acc[0] += r0; acc[1] += r1; acc[2] += r2;
        return;
    }
    for (int i = 0; i < 8; i++) {
        const float *tr = table + (tex[i & 3] + (i < 4 ? lo : hi) * lvl) * C;
        float wt = w4[i & 3] * (i < 4 ? 1 - a : a) * wl;
        for (i64 c = 0; c < C; c++) acc[c] += wt * tr[c];
    }
}

#if defined(__AVX512F__) && defined(__AVX512VL__)
#include <immintrin.h>
/* 16 lookups at once (RGB tables), lane by lane the float32 operations of sg_lookup: the face, texel
   and level addressing in vector registers, the 8 texels x 3 channels by gathers. The log of the
   width is Cephes' logf (range reduction to [sqrt(1/2), sqrt(2)), a degree-8 polynomial: within
   about 1 ulp of logf; NaN and +Inf pass through as logf's). Table offsets are int32: the caller
   takes this path only for tables under 2^31 floats. */
static inline __m512 log16(__m512 x) {
    const __m512 one = _mm512_set1_ps(1.0f);
    __m512i xi = _mm512_castps_si512(x);
    __m512 e = _mm512_cvtepi32_ps(_mm512_sub_epi32(_mm512_srli_epi32(xi, 23), _mm512_set1_epi32(126)));
    __m512 m = _mm512_castsi512_ps(_mm512_or_si512(_mm512_and_si512(xi, _mm512_set1_epi32(0x807fffff)),
                                                   _mm512_set1_epi32(0x3f000000)));  /* [0.5, 1) */
    __mmask16 lo = _mm512_cmp_ps_mask(m, _mm512_set1_ps(0.707106781186547524f), _CMP_LT_OQ);
    e = _mm512_mask_sub_ps(e, lo, e, one);
    m = _mm512_sub_ps(_mm512_mask_add_ps(m, lo, m, m), one);
    __m512 z = _mm512_mul_ps(m, m);
    __m512 y = _mm512_set1_ps(7.0376836292E-2f);
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(-1.1514610310E-1f));
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(1.1676998740E-1f));
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(-1.2420140846E-1f));
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(1.4249322787E-1f));
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(-1.6668057665E-1f));
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(2.0000714765E-1f));
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(-2.4999993993E-1f));
    y = _mm512_fmadd_ps(y, m, _mm512_set1_ps(3.3333331174E-1f));
    y = _mm512_mul_ps(_mm512_mul_ps(y, m), z);
    y = _mm512_fmadd_ps(e, _mm512_set1_ps(-2.12194440e-4f), y);
    y = _mm512_fnmadd_ps(_mm512_set1_ps(0.5f), z, y);
    __m512 res = _mm512_fmadd_ps(e, _mm512_set1_ps(0.693359375f), _mm512_add_ps(m, y));
    __mmask16 fin = _mm512_cmp_ps_mask(x, _mm512_set1_ps(INFINITY), _CMP_LT_OQ);  /* NaN, +Inf: as given */
    return _mm512_mask_blend_ps(fin, x, res);
}

static inline __m512 clamp16(__m512 v, __m512 lo, __m512 hi) {  /* v < lo ? lo : (v > hi ? hi : v) */
    v = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(v, hi, _CMP_GT_OQ), v, hi);
    return _mm512_mask_blend_ps(_mm512_cmp_ps_mask(v, lo, _CMP_LT_OQ), v, lo);
}

/* acc{r,g,b} += wl E_sigma(x, y, z), 16 lanes; table [L 6 r r, 3], ladder [L] increasing */
/* a lookup's addressing (face, texel, level) and its texel reads, in two parts: sg_lookup16 runs both, a prepared
   relight (prt_sg_prepare, prt_sg_lookup_prepared) keeps the first's result per lobe. The texel index of lane l's
   first texel on the lower level i0 = base + lo 6 r^2, its flags (bit 0: the second texel column is one on, bit 1:
   the second row is, bit 2: the upper level is the next one), and the bilinear and level fractions fs, ft, a: the
   integers the eight texel indices are sums of, and the floats their weights are products of, so both paths give
   the same bits. */
static inline void sg_address16(__m512 x, __m512 y, __m512 z, __m512 sigma, i64 r, i64 L, const float *ladder,
                                const __m512 *lad, __m512i *i0_, __m512i *flags_, __m512 *fs_, __m512 *ft_, __m512 *a_) {
    const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f);
    const __m512 signbit = _mm512_set1_ps(-0.0f);
    __m512 ax = _mm512_andnot_ps(signbit, x), ay = _mm512_andnot_ps(signbit, y), az = _mm512_andnot_ps(signbit, z);
    __m512 nx = _mm512_xor_ps(x, signbit), ny = _mm512_xor_ps(y, signbit), nz = _mm512_xor_ps(z, signbit);
    __mmask16 mx = _mm512_cmp_ps_mask(ax, ay, _CMP_GE_OQ) & _mm512_cmp_ps_mask(ax, az, _CMP_GE_OQ);
    __mmask16 my = ~mx & _mm512_cmp_ps_mask(ay, az, _CMP_GE_OQ);
    __mmask16 xneg = _mm512_cmp_ps_mask(x, zero, _CMP_LT_OQ), yneg = _mm512_cmp_ps_mask(y, zero, _CMP_LT_OQ);
    __mmask16 zneg = _mm512_cmp_ps_mask(z, zero, _CMP_LT_OQ);
    __mmask16 xge = _mm512_cmp_ps_mask(x, zero, _CMP_GE_OQ), yge = _mm512_cmp_ps_mask(y, zero, _CMP_GE_OQ);
    __mmask16 zge = _mm512_cmp_ps_mask(z, zero, _CMP_GE_OQ);
    /* z face (the default), then y, then x overwrite their lanes */
    __m512 mm = az, sc = _mm512_mask_blend_ps(zge, nx, x), tc = ny;
    __m512i face = _mm512_mask_blend_epi32(zneg, _mm512_set1_epi32(4), _mm512_set1_epi32(5));
    mm = _mm512_mask_blend_ps(my, mm, ay);
    sc = _mm512_mask_blend_ps(my, sc, x);
    tc = _mm512_mask_blend_ps(my, tc, _mm512_mask_blend_ps(yge, nz, z));
    face = _mm512_mask_blend_epi32(my, face, _mm512_mask_blend_epi32(yneg, _mm512_set1_epi32(2), _mm512_set1_epi32(3)));
    mm = _mm512_mask_blend_ps(mx, mm, ax);
    sc = _mm512_mask_blend_ps(mx, sc, _mm512_mask_blend_ps(xge, z, nz));
    tc = _mm512_mask_blend_ps(mx, tc, ny);
    face = _mm512_mask_blend_epi32(mx, face, _mm512_mask_blend_epi32(xneg, _mm512_setzero_si512(), _mm512_set1_epi32(1)));
    mm = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(mm, _mm512_set1_ps(1e-30f), _CMP_LT_OQ), mm, _mm512_set1_ps(1e-30f));
    sc = _mm512_div_ps(sc, mm);
    tc = _mm512_div_ps(tc, mm);
    const __m512 half = _mm512_set1_ps((float)r * 0.5f), p5 = _mm512_set1_ps(0.5f), rm1 = _mm512_set1_ps((float)(r - 1));
    __m512 s = _mm512_fmsub_ps(_mm512_add_ps(sc, one), half, p5), t = _mm512_fmsub_ps(_mm512_add_ps(tc, one), half, p5);
    s = clamp16(s, zero, rm1);
    t = clamp16(t, zero, rm1);
    const __m512 rmax = _mm512_set1_ps((float)(r > 1 ? r - 2 : 0));
    __m512 sf = _mm512_roundscale_ps(s, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    __m512 tf = _mm512_roundscale_ps(t, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC);
    sf = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(sf, rmax, _CMP_GT_OQ), sf, rmax);
    tf = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(tf, rmax, _CMP_GT_OQ), tf, rmax);
    /* a NaN coordinate (a non-finite direction) survives the compare-and-blend clamps and converts
       to INT_MIN: the unsigned minimum puts it on a texel inside the face, so the lane reads the
       table and its result is NaN, as in the scalar loop, instead of reading 8 GiB before it */
    const __m512i rmaxi = _mm512_set1_epi32((int)(r > 1 ? r - 2 : 0));
    __m512i s0 = _mm512_min_epu32(_mm512_cvttps_epi32(sf), rmaxi), t0 = _mm512_min_epu32(_mm512_cvttps_epi32(tf), rmaxi);
    __m512 fs = clamp16(_mm512_sub_ps(s, sf), zero, one), ft = clamp16(_mm512_sub_ps(t, tf), zero, one);
    const __m512i ri = _mm512_set1_epi32((int)r), rm1i = _mm512_set1_epi32((int)(r - 1)), onei = _mm512_set1_epi32(1);
    __m512i ds = _mm512_sub_epi32(_mm512_min_epi32(_mm512_add_epi32(s0, onei), rm1i), s0);
    __m512i dt = _mm512_mullo_epi32(_mm512_sub_epi32(_mm512_min_epi32(_mm512_add_epi32(t0, onei), rm1i), t0), ri);
    __m512 ls = log16(_mm512_mask_blend_ps(_mm512_cmp_ps_mask(sigma, _mm512_set1_ps(1e-12f), _CMP_LT_OQ), sigma,
                                           _mm512_set1_ps(1e-12f)));
    __m512 a = zero;
    __m512i lo = _mm512_setzero_si512(), hi = lo;
    if (L > 1) {  /* searchsorted (left) = the number of ladder entries below ls */
        for (i64 l = 0; l < L; l++)
            hi = _mm512_mask_add_epi32(hi, _mm512_cmp_ps_mask(_mm512_set1_ps(ladder[l]), ls, _CMP_LT_OQ), hi, onei);
        hi = _mm512_min_epi32(_mm512_max_epi32(hi, onei), _mm512_set1_epi32((int)(L - 1)));
        lo = _mm512_sub_epi32(hi, onei);
        __m512 llo, lhi;
        if (L <= 32) {  /* the ladder in two registers: a permute, not a gather */
            llo = _mm512_permutex2var_ps(lad[0], lo, lad[1]);
            lhi = _mm512_permutex2var_ps(lad[0], hi, lad[1]);
        } else {
            llo = _mm512_i32gather_ps(lo, ladder, 4);
            lhi = _mm512_i32gather_ps(hi, ladder, 4);
        }
        a = clamp16(_mm512_div_ps(_mm512_sub_ps(ls, llo), _mm512_sub_ps(lhi, llo)), zero, one);
    }
    const __m512i lvl = _mm512_set1_epi32((int)(6 * r * r));
    __m512i base = _mm512_add_epi32(_mm512_mullo_epi32(_mm512_add_epi32(_mm512_mullo_epi32(face, ri), t0), ri), s0);
    *i0_ = _mm512_add_epi32(base, _mm512_mullo_epi32(lo, lvl));
    *flags_ = _mm512_or_epi32(_mm512_or_epi32(ds, _mm512_slli_epi32(_mm512_min_epi32(dt, onei), 1)),
                              _mm512_slli_epi32(_mm512_sub_epi32(hi, lo), 2));
    *fs_ = fs;
    *ft_ = ft;
    *a_ = a;
}
/* sg_texels16 where r > 1: per pair of texels p (row (t0, t1) = p & 1, level (lo, hi) = p >> 1) of lane l, the float
   offset ix[p][l] of the first texel in the table and the weights (wa, wb) at wp[p][2 l] */
static inline void sg_pairs16(const __m512i *tex, __m512i dl, const __m512 *w4, const __m512 *la, __m512 wl, int32_t ix[4][16],
                              float wp[4][32]) {
    const __m512i three = _mm512_set1_epi32(3);
    const __m512i lo8 = _mm512_set_epi32(23, 7, 22, 6, 21, 5, 20, 4, 19, 3, 18, 2, 17, 1, 16, 0);
    const __m512i hi8 = _mm512_add_epi32(lo8, _mm512_set1_epi32(8));
    for (int p = 0; p < 4; p++) {
        const __m512i t = tex[2 * (p & 1)];
        _mm512_store_si512(ix[p], _mm512_mullo_epi32(p < 2 ? t : _mm512_add_epi32(t, dl), three));
        const __m512 wa = _mm512_mul_ps(_mm512_mul_ps(w4[2 * (p & 1)], la[p >> 1]), wl);
        const __m512 wb = _mm512_mul_ps(_mm512_mul_ps(w4[2 * (p & 1) + 1], la[p >> 1]), wl);
        _mm512_store_ps(wp[p], _mm512_permutex2var_ps(wa, lo8, wb));
        _mm512_store_ps(wp[p] + 16, _mm512_permutex2var_ps(wa, hi8, wb));
    }
}
/* lane l's RGB (and a 4th float) from sg_pairs16's offsets and weights: one masked 6-float load per pair weighted
   [wa wa wa wb wb wb], the four multiply-adds in order, then the two texels' RGB added */
static inline __m128 sg_pair_sum(const float *table, int32_t ix[4][16], float wp[4][32], int l) {
    const __m256i spread = _mm256_set_epi32(1, 1, 1, 1, 1, 0, 0, 0), fold = _mm256_set_epi32(7, 7, 7, 7, 7, 5, 4, 3);
    __m256 s8 = _mm256_setzero_ps();
    for (int p = 0; p < 4; p++) {
        const __m256 w2 = _mm256_permutexvar_ps(spread, _mm256_castps128_ps256(_mm_castpd_ps(_mm_load_sd((const double *)(wp[p] + 2 * l)))));
        s8 = _mm256_fmadd_ps(w2, _mm256_maskz_loadu_ps(0x3f, table + ix[p][l]), s8);
    }
    return _mm_add_ps(_mm256_castps256_ps128(s8), _mm256_castps256_ps128(_mm256_permutexvar_ps(fold, s8)));
}
/* the texel indices, bilinear and level weights of sg_address16's lanes */
#define SG_TEXEL_SETUP                                                                                                      \
    const __m512 one = _mm512_set1_ps(1.0f);                                                                                \
    const __m512i onei = _mm512_set1_epi32(1);                                                                              \
    const __m512i ds = _mm512_and_si512(flags, onei);                                                                       \
    const __m512i dt = _mm512_mullo_epi32(_mm512_and_si512(_mm512_srli_epi32(flags, 1), onei), _mm512_set1_epi32((int)r));  \
    const __m512i dl = _mm512_mullo_epi32(_mm512_srli_epi32(flags, 2), _mm512_set1_epi32((int)(6 * r * r)));                \
    __m512i tex[4] = {i0, _mm512_add_epi32(i0, ds), _mm512_add_epi32(i0, dt), _mm512_add_epi32(_mm512_add_epi32(i0, dt), ds)}; \
    __m512 gs = _mm512_sub_ps(one, fs), gt = _mm512_sub_ps(one, ft);                                                        \
    __m512 w4[4] = {_mm512_mul_ps(gt, gs), _mm512_mul_ps(gt, fs), _mm512_mul_ps(ft, gs), _mm512_mul_ps(ft, fs)};            \
    __m512 la[2] = {_mm512_sub_ps(one, a), a};
/* sg_texels16's offsets and weights (r > 1) */
static inline void sg_pairs_of(__m512i i0, __m512i flags, __m512 fs, __m512 ft, __m512 a, __m512 wl, i64 r, int32_t ix[4][16],
                               float wp[4][32]) {
    SG_TEXEL_SETUP
    (void)tex[1]; (void)tex[3];
    sg_pairs16(tex, dl, w4, la, wl, ix, wp);
}
/* the eight texels of sg_address16's lanes, weighted by wl, added to acc (RGB) */
static inline void sg_texels16(__m512i i0, __m512i flags, __m512 fs, __m512 ft, __m512 a, __m512 wl, const float *table, i64 r,
                               __m128 *acc) {
    SG_TEXEL_SETUP
    const __m512i three = _mm512_set1_epi32(3);
    if (r > 1) {  /* the texel's neighbour along s is the next one (ds = 1): one masked 6-float load per pair of texels,
                     weighted [wa wa wa wb wb wb] (the two weights one 8-byte load, spread by a permute), where the
                     per-texel loop below took twice the loads and multiply-adds */
        int32_t ix[4][16] __attribute__((aligned(64)));
        float wp[4][32] __attribute__((aligned(64)));
        sg_pairs16(tex, dl, w4, la, wl, ix, wp);
        for (int l = 0; l < 16; l++) acc[l] = _mm_add_ps(acc[l], sg_pair_sum(table, ix, wp, l));
        return;
    }
    /* the 8 texels x 3 channels per lane: a masked 3-float load per texel (no gathers: Zen 4 and
       older cores gather at about one element per cycle) */
    int32_t ix[8][16] __attribute__((aligned(64)));
    float wt[8][16] __attribute__((aligned(64)));
    for (int i = 0; i < 8; i++) {
        _mm512_store_si512(ix[i], _mm512_mullo_epi32(i < 4 ? tex[i & 3] : _mm512_add_epi32(tex[i & 3], dl), three));
        _mm512_store_ps(wt[i], _mm512_mul_ps(_mm512_mul_ps(w4[i & 3], la[i >> 2]), wl));
    }
    for (int l = 0; l < 16; l++) {
        __m128 s4 = _mm_setzero_ps();
        for (int i = 0; i < 8; i++) s4 = _mm_fmadd_ps(_mm_set1_ps(wt[i][l]), _mm_maskz_loadu_ps(7, table + ix[i][l]), s4);
        acc[l] = _mm_add_ps(acc[l], s4);
    }
}
/* sg_texels16 from the quad table Q (PrefilteredEnvironment.quads): row i = the 2x2 texels from texel i on, (t, s),
   (t, s+1), (t+1, s), (t+1, s+1), RGB each, then 4 zeros: 16 floats, one 64-byte line, where the table's 8 texels
   of a lookup lie on four lines (two rows, two levels). Per lane two line loads (the lower and the upper level,
   dl floats apart), weighted by the level weights (1 - a) wl and a wl, then by the bilinear weights spread over
   the 12 floats, and the 12 summed to RGB by two permutes: 14 instructions a lane where sg_texels16 takes 27
   (measured, prepared every-view relighting at 50 000 x 92: 1.12x with one lobe, 1.15x with three). The products
   are those of sg_texels16; the sums run in another order (float32 rounding). */
/* sg_quads16's per-lane level weights l0, l1, row offsets ix and bilinear weights wq (lane l's (w00, w01, w10, w11)
   at 16 (l & 3) + 4 (l >> 2): a 4 x 16 transpose) */
typedef struct { float l0[16], l1[16]; int32_t ix[16]; float wq[80]; } __attribute__((aligned(64))) sg_quad_setup;
static inline void sg_quads_setup(__m512i i0, __m512 fs, __m512 ft, __m512 a, __m512 wl, sg_quad_setup *u) {
    const __m512 one = _mm512_set1_ps(1.0f);
    const __m512 gs = _mm512_sub_ps(one, fs), gt = _mm512_sub_ps(one, ft);
    const __m512 w00 = _mm512_mul_ps(gt, gs), w01 = _mm512_mul_ps(gt, fs), w10 = _mm512_mul_ps(ft, gs), w11 = _mm512_mul_ps(ft, fs);
    _mm512_store_ps(u->l0, _mm512_mul_ps(_mm512_sub_ps(one, a), wl));
    _mm512_store_ps(u->l1, _mm512_mul_ps(a, wl));
    _mm512_store_si512(u->ix, _mm512_slli_epi32(i0, 4));
    const __m512 t0 = _mm512_unpacklo_ps(w00, w01), t1 = _mm512_unpackhi_ps(w00, w01);
    const __m512 t2 = _mm512_unpacklo_ps(w10, w11), t3 = _mm512_unpackhi_ps(w10, w11);
    _mm512_store_ps(u->wq, _mm512_castpd_ps(_mm512_unpacklo_pd(_mm512_castps_pd(t0), _mm512_castps_pd(t2))));
    _mm512_store_ps(u->wq + 16, _mm512_castpd_ps(_mm512_unpackhi_pd(_mm512_castps_pd(t0), _mm512_castps_pd(t2))));
    _mm512_store_ps(u->wq + 32, _mm512_castpd_ps(_mm512_unpacklo_pd(_mm512_castps_pd(t1), _mm512_castps_pd(t3))));
    _mm512_store_ps(u->wq + 48, _mm512_castpd_ps(_mm512_unpackhi_pd(_mm512_castps_pd(t1), _mm512_castps_pd(t3))));
    _mm512_store_ps(u->wq + 64, _mm512_setzero_ps());
}
/* lane l's RGB (and a 4th float) from its two quad lines: weighted by the levels, times the bilinear weights spread
   over the 12 floats, then folded (the 4 zeros, times any weight, left out) */
static inline __m128 sg_quad_sum(const float *quads, i64 dl, const sg_quad_setup *u, int l) {
    const __m512i spread = _mm512_set_epi32(3, 3, 3, 3, 3, 3, 3, 2, 2, 2, 1, 1, 1, 0, 0, 0);
    const __m512i six = _mm512_set_epi32(15, 15, 15, 15, 15, 15, 15, 15, 15, 15, 11, 10, 9, 8, 7, 6);
    const __m256i three = _mm256_set_epi32(7, 7, 7, 7, 7, 5, 4, 3);
    const float *q = quads + u->ix[l];
    __m512 t = _mm512_mul_ps(_mm512_loadu_ps(q), _mm512_set1_ps(u->l0[l]));
    t = _mm512_fmadd_ps(_mm512_loadu_ps(q + dl), _mm512_set1_ps(u->l1[l]), t);
    t = _mm512_mul_ps(t, _mm512_permutexvar_ps(spread, _mm512_loadu_ps(u->wq + 16 * (l & 3) + 4 * (l >> 2))));
    t = _mm512_add_ps(t, _mm512_permutexvar_ps(six, t));
    const __m256 h = _mm512_castps512_ps256(t);
    return _mm256_castps256_ps128(_mm256_add_ps(h, _mm256_permutexvar_ps(three, h)));
}
static inline void sg_quads16(__m512i i0, __m512 fs, __m512 ft, __m512 a, __m512 wl, const float *quads, i64 dl, __m128 *acc) {
    sg_quad_setup u;
    sg_quads_setup(i0, fs, ft, a, wl, &u);
    for (int l = 0; l < 16; l++) acc[l] = _mm_add_ps(acc[l], sg_quad_sum(quads, dl, &u, l));
}

/* the lanes outer (N <= 4 lobes set up by sg_quads_setup or sg_pairs_of): lane l's lobes summed in a register, in
   order from zero as acc[l] in sg_quads16 or sg_texels16 (the same bits), times scale[l] (NULL: 1) as store16_rgb,
   written to o + 3 rs l. Measured, prepared every-view relighting at 50 000 x 92 (quads): 1.25x with one lobe, 1.15x
   with three; prepared taps (pairs): 1.21x with one. */
static inline void sg_lanes_quads(const sg_quad_setup *u, i64 N, const float *quads, i64 dl, float *o, i64 rs) {
    for (int l = 0; l < 16; l++) {
        __m128 acc = _mm_setzero_ps();
        for (i64 n = 0; n < N; n++) acc = _mm_add_ps(acc, sg_quad_sum(quads, dl, &u[n], l));
        float tt[4];
        _mm_storeu_ps(tt, acc);
        float *ol = o + 3 * rs * l;
        ol[0] = tt[0]; ol[1] = tt[1]; ol[2] = tt[2];
    }
}
static inline void sg_lanes_pairs(int32_t ix[][4][16], float wp[][4][32], i64 N, const float *table, const float *scale, float *o,
                                  i64 rs) {
    float st[52] __attribute__((aligned(64)));
    for (int l = 0; l < 16; l++) {
        __m128 acc = _mm_setzero_ps();
        for (i64 n = 0; n < N; n++) acc = _mm_add_ps(acc, sg_pair_sum(table, ix[n], wp[n], l));
        _mm_storeu_ps(st + 3 * l, scale ? _mm_mul_ps(acc, _mm_set1_ps(scale[l])) : acc);
    }
    if (rs == 1) {  /* 16 rows in a row: three lines */
        _mm512_storeu_ps(o, _mm512_load_ps(st));
        _mm512_storeu_ps(o + 16, _mm512_load_ps(st + 16));
        _mm512_storeu_ps(o + 32, _mm512_load_ps(st + 32));
    } else
        for (int l = 0; l < 16; l++) {
            float *ol = o + 3 * rs * l;
            ol[0] = st[3 * l]; ol[1] = st[3 * l + 1]; ol[2] = st[3 * l + 2];
        }
}

/* a block of 16 functions' results, 16 B RGB rows contiguous in out from o on (B > 1: every view of 16 vertices), staged
   in the thread's buffer and written with streaming stores where the result is large (SG_STREAM_BYTES): it is not read
   again before it leaves the caches, and a plain store reads each line first (measured, prepared every-view
   relighting at 50 000 x 92: 1.04x; with the records prefetched, 1.06x) */
#define SG_STAGE 8192
static inline float *sg_stage(float *stage, float *o, int nt) { return nt ? stage : o; }
static inline void sg_flush(const float *stage, float *o, i64 B, int nt) {
    if (nt)
        for (i64 i = 0; i < 48 * B; i += 16) _mm512_stream_ps(o + i, _mm512_load_ps(stage + i));
}
static inline void sg_lookup16(__m512 x, __m512 y, __m512 z, __m512 sigma, __m512 wl, const float *table, i64 r, i64 L,
                               const float *ladder, const __m512 *lad, __m128 *acc) {
    __m512i i0, flags;
    __m512 fs, ft, a;
    sg_address16(x, y, z, sigma, r, L, ladder, lad, &i0, &flags, &fs, &ft, &a);
    sg_texels16(i0, flags, fs, ft, a, wl, table, r, acc);
}

/* out[3 l + c] = acc[l][c] scale[l] for 16 lanes */
/* the first 32 ladder entries in two registers (zeros beyond L) */
static inline void ladder32(const float *ladder, i64 L, __m512 *lad) {
    float lt[32] = {0};
    for (i64 l = 0; l < L && l < 32; l++) lt[l] = ladder[l];
    lad[0] = _mm512_loadu_ps(lt);
    lad[1] = _mm512_loadu_ps(lt + 16);
}

/* elements ix (0..47) of the 48 floats a, b, c (16 each) */
static inline __m512 deint3(__m512 a, __m512 b, __m512 c, __m512i ix) {
    __m512 ab = _mm512_permutex2var_ps(a, ix, b);  /* ix < 32 */
    __m512 cc = _mm512_permutexvar_ps(_mm512_sub_epi32(ix, _mm512_set1_epi32(32)), c);
    return _mm512_mask_blend_ps(_mm512_cmpge_epi32_mask(ix, _mm512_set1_epi32(32)), ab, cc);
}

/* 5-way deinterleave of 80 floats r[0..4] (16 lobe records w, mu_x, mu_y, mu_z, sigma): field f of
   lane l is float p = 5 l + f, in register p / 16. One index vector p serves every permute (they
   read its low 5 or 4 bits): registers 0-1 for p < 32, 2-3 for p < 64, 4 beyond, as deint3 does. */
static inline __m512 deint5(const __m512 *r, int f) {
    const __m512i p = _mm512_add_epi32(_mm512_set_epi32(75, 70, 65, 60, 55, 50, 45, 40, 35, 30, 25, 20, 15, 10, 5, 0),
                                       _mm512_set1_epi32(f));
    __m512 o = _mm512_mask_blend_ps(_mm512_cmpge_epi32_mask(p, _mm512_set1_epi32(32)), _mm512_permutex2var_ps(r[0], p, r[1]),
                                    _mm512_permutex2var_ps(r[2], p, r[3]));
    return _mm512_mask_blend_ps(_mm512_cmpge_epi32_mask(p, _mm512_set1_epi32(64)), o, _mm512_permutexvar_ps(p, r[4]));
}

/* lane l's RGB (times scale[l] when given) to out[3 rs l + c] */
static inline void store16_rgb(float *out, i64 rs, const __m128 *acc, const float *scale) {
    for (int l = 0; l < 16; l++) {
        float t[4];
        _mm_storeu_ps(t, _mm_mul_ps(acc[l], _mm_set1_ps(scale ? scale[l] : 1.0f)));
        float *o = out + 3 * rs * l;
        o[0] = t[0]; o[1] = t[1]; o[2] = t[2];
    }
}
#define SG16 1
#endif

/* Lobe m's parameters: w[sw m], mu[sm m + c], sigma[ss m]. Separate arrays: (sw, sm, ss) = (1, 3, 1);
   records [..., 5] = (w, mu_x, mu_y, mu_z, sigma): (5, 5, 5) with mu = w + 1, sigma = w + 4, so a
   view's lobes are one run of 20 N bytes. */
#define IS_RECORD (sw == 5 && sm == 5 && ss == 5 && mu == w + 1 && sigma == w + 4)

/* out[a B + b, c] = sum_{n<N} w_m E_{sigma_m}(mu_m)[c], m = a N + b fb + n, for a in [g0, g1), b < B:
   functions (a, b) written in a-major order, their lobes consecutive in a. G functions in order: B = 1 (fb
   unused); the Gaussian codec's view-major records [J, V, N, 5]: (a, b) = (vertex, view), fb = V N. */
#ifdef SG16
/* lobe n of functions (g0 + l, b) for the 16 lanes l, mb = b fb (lobe m = (g0 + l) N + n + mb): its weight, mean and width */
static inline __attribute__((always_inline)) void sg_load16(i64 g0, i64 mb, i64 n, i64 N, const float *mu, const float *sigma,
        const float *w, i64 sw, i64 sm, i64 ss, int rec, int sep, __m512 *X, __m512 *Y, __m512 *Z, __m512 *S, __m512 *W) {
    if (N == 1 && rec) {  /* 16 consecutive records: 80 contiguous floats, deinterleaved by permutes */
        const float *p = w + 5 * (g0 + mb);
        __m512 q[5] = {_mm512_loadu_ps(p), _mm512_loadu_ps(p + 16), _mm512_loadu_ps(p + 32), _mm512_loadu_ps(p + 48),
                       _mm512_loadu_ps(p + 64)};
        *W = deint5(q, 0); *X = deint5(q, 1); *Y = deint5(q, 2); *Z = deint5(q, 3); *S = deint5(q, 4);
    } else if (N == 1 && sep) {  /* 16 consecutive lobes: mu is 48 contiguous floats, deinterleaved by permutes */
        const float *p = mu + 3 * (g0 + mb);
        __m512 a = _mm512_loadu_ps(p), b = _mm512_loadu_ps(p + 16), c = _mm512_loadu_ps(p + 32);
        const __m512i ix = _mm512_set_epi32(45, 42, 39, 36, 33, 30, 27, 24, 21, 18, 15, 12, 9, 6, 3, 0);
        *X = deint3(a, b, c, ix);
        *Y = deint3(a, b, c, _mm512_add_epi32(ix, _mm512_set1_epi32(1)));
        *Z = deint3(a, b, c, _mm512_add_epi32(ix, _mm512_set1_epi32(2)));
        *S = _mm512_loadu_ps(sigma + g0 + mb);
        *W = _mm512_loadu_ps(w + g0 + mb);
    } else {
        const __m512i lane = _mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
        __m512i m = _mm512_add_epi32(_mm512_mullo_epi32(_mm512_add_epi32(lane, _mm512_set1_epi32((int)g0)),
                                                        _mm512_set1_epi32((int)N)), _mm512_set1_epi32((int)(n + mb)));
        __m512i mm = _mm512_mullo_epi32(m, _mm512_set1_epi32((int)sm));
        *X = _mm512_i32gather_ps(mm, mu, 4); *Y = _mm512_i32gather_ps(mm, mu + 1, 4); *Z = _mm512_i32gather_ps(mm, mu + 2, 4);
        *S = _mm512_i32gather_ps(_mm512_mullo_epi32(m, _mm512_set1_epi32((int)ss)), sigma, 4);
        *W = _mm512_i32gather_ps(_mm512_mullo_epi32(m, _mm512_set1_epi32((int)sw)), w, 4);
    }
}
#endif
static inline __attribute__((always_inline)) void sg_range_(i64 g0, i64 g1, i64 B, i64 fb, i64 N, const float *mu,
        const float *sigma, const float *w, i64 sw, i64 sm, i64 ss, const float *table, const float *quads, i64 r, i64 L,
        const float *ladder, i64 C, int vec, int nt, float *out) {
#ifdef SG16
    if (vec) {  /* 16 functions at a time (lane l: function (g + l, b)), the rest below */
        __m512 lad[2];
        ladder32(ladder, L, lad);
        const int rec = IS_RECORD, sep = sw == 1 && sm == 3 && ss == 1;
        float stage[SG_STAGE] __attribute__((aligned(64)));
        for (; g0 + 16 <= g1; g0 += 16) {
          float *ob = sg_stage(stage, out + 3 * g0 * B, nt);
          for (i64 b = 0; b < B; b++) {  /* B > 1: the block's rows (16 B C floats) stay in L1 over its B functions */
            __m128 acc[16];
            const i64 mb = b * fb;
            for (int l = 0; l < 16; l++) acc[l] = _mm_setzero_ps();
            if (rec && B == 1 && g0 + 16 * 9 <= g1)  /* the records 8 blocks ahead (measured: the hardware prefetcher alone left
                                                        every-view lookups 0.84x as fast as from separate arrays; with this 0.98-1.01x) */
                for (i64 f = 0; f < 5 * N; f++) _mm_prefetch((const char *)(w + 5 * N * (g0 + 16 * 8) + 16 * f), _MM_HINT_T0);
            else if (rec && B > 1 && g0 + 32 <= g1)  /* B streams, one per b: the next block's records of this b */
                for (i64 f = 0; f < 5 * N; f++) _mm_prefetch((const char *)(w + 5 * (N * (g0 + 16) + mb) + 16 * f), _MM_HINT_T0);
            if (N <= 4 && (quads || r > 1)) {  /* the lanes outer (sg_lanes_quads, sg_lanes_pairs) */
                sg_quad_setup u[4] __attribute__((aligned(64)));
                int32_t ix[4][4][16] __attribute__((aligned(64)));
                float wp[4][4][32] __attribute__((aligned(64)));
                for (i64 n = 0; n < N; n++) {
                    __m512 X, Y, Z, S, W, fs, ft, a;
                    __m512i i0, flags;
                    sg_load16(g0, mb, n, N, mu, sigma, w, sw, sm, ss, rec, sep, &X, &Y, &Z, &S, &W);
                    sg_address16(X, Y, Z, S, r, L, ladder, lad, &i0, &flags, &fs, &ft, &a);
                    if (quads) sg_quads_setup(i0, fs, ft, a, W, &u[n]);
                    else sg_pairs_of(i0, flags, fs, ft, a, W, r, ix[n], wp[n]);
                }
                if (quads) sg_lanes_quads(u, N, quads, L > 1 ? 16 * 6 * r * r : 0, ob + 3 * b, B);
                else sg_lanes_pairs(ix, wp, N, table, NULL, ob + 3 * b, B);
                continue;
            }
            for (i64 n = 0; n < N; n++) {
                __m512 X, Y, Z, S, W;
                sg_load16(g0, mb, n, N, mu, sigma, w, sw, sm, ss, rec, sep, &X, &Y, &Z, &S, &W);
                if (quads) {
                    __m512i i0, flags;
                    __m512 fs, ft, a;
                    sg_address16(X, Y, Z, S, r, L, ladder, lad, &i0, &flags, &fs, &ft, &a);
                    sg_quads16(i0, fs, ft, a, W, quads, L > 1 ? 16 * 6 * r * r : 0, acc);
                } else
                    sg_lookup16(X, Y, Z, S, W, table, r, L, ladder, lad, acc);
            }
            store16_rgb(ob + 3 * b, B, acc, NULL);
          }
          sg_flush(stage, out + 3 * g0 * B, B, nt);
        }
        if (nt) _mm_sfence();
    }
#else
    (void)vec; (void)quads; (void)nt;
#endif
    for (i64 g = g0; g < g1; g++)
        for (i64 b = 0; b < B; b++) {
            float acc[16] = {0};
            for (i64 m = g * N + b * fb; m < g * N + b * fb + N; m++)
                sg_lookup(mu[sm * m], mu[sm * m + 1], mu[sm * m + 2], sigma[ss * m], w[sw * m], table, r, L, ladder, C, acc);
            for (i64 c = 0; c < C; c++) out[(g * B + b) * C + c] = acc[c];
        }
}

/* B = 1 compiled apart (measured in ab_sg_micro: the general loop cost one-lobe lookups in order 8%) */
static void sg_range(i64 g0, i64 g1, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm,
                     i64 ss, const float *table, const float *quads, i64 r, i64 L, const float *ladder, i64 C, int vec, int nt,
                     float *out) {
    if (B == 1) sg_range_(g0, g1, 1, 0, N, mu, sigma, w, sw, sm, ss, table, quads, r, L, ladder, C, vec, 0, out);
    else sg_range_(g0, g1, B, fb, N, mu, sigma, w, sw, sm, ss, table, quads, r, L, ladder, C, vec, nt, out);
}

/* the 16-lane path: RGB, and every gather offset (5 G N into the lobes, L 6 r r 3 into the table) in int32 */
static inline int sg_vec(i64 elems, i64 L, i64 r, i64 C) {
    return C == 3 && 5 * elems < ((i64)1 << 31) - 64 && L * 6 * r * r * 3 < ((i64)1 << 31) - 64;
}

/* G x B functions (sg_range), the G split between the threads */
/* thread t's functions: whole blocks of 16, the last thread also the tail, so that which lanes take the 16-lane
   lookup (whose logarithm differs from logf's by up to an ulp) depends on G only, not on the thread count */
#define SPLIT16(G, t, nth) (((G) / 16) * (t) / (nth) * 16)
#define SPLIT16_END(G, t, nth) ((t) + 1 == (nth) ? (G) : SPLIT16(G, (t) + 1, nth))
/* whether a block of 16 functions' rows go through sg_stage: every view (B > 1) of a result over SG_STREAM_BYTES, rows
   that fit the stage and start on 64-byte lines */
#define SG_STREAM_BYTES ((i64)16 << 20)
static inline int sg_nt(i64 G, i64 B, const float *out) {
#ifdef SG16
    return B > 1 && G * B * 12 >= SG_STREAM_BYTES && 48 * B <= SG_STAGE && ((uintptr_t)out & 63) == 0;  /* 48 B floats: whole lines */
#else
    (void)G; (void)B; (void)out;
    return 0;
#endif
}
/* whether sg_quads16 takes this pyramid: RGB, more than one texel per side, and its int32 float offsets (16 per row)
   within range (sg_vec bounds the table's 3 per row) */
static inline int sg_quads_fit(i64 L, i64 r, i64 C) {
    return C == 3 && r >= 2 && 16 * L * 6 * r * r < ((i64)1 << 31) - 64;
}
/* quads: NULL, or PrefilteredEnvironment.quads() of this table (C = 3, r > 1; read by sg_quads16) */
int prt_sg_lookup_sum_q(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss,
                        const float *table, const float *quads, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads) {
    i64 nth = nthreads > 0 ? nthreads : 1;
    int vec = sg_vec(G * B * N, L, r, C), nt = vec && sg_nt(G, B, out);
    if (!vec || !sg_quads_fit(L, r, C)) quads = NULL;
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++)
        sg_range(SPLIT16(G, t, nth), SPLIT16_END(G, t, nth), B, fb, N, mu, sigma, w, sw, sm, ss, table, quads, r, L, ladder, C,
                 vec, nt, out);
    return 0;
}
int prt_sg_lookup_sum(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss,
                      const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads) {
    return prt_sg_lookup_sum_q(G, B, fb, N, mu, sigma, w, sw, sm, ss, table, NULL, r, L, ladder, C, out, nthreads);
}

/* A prepared relight of every view (GaussianCodec.relighter): the addressing of each lobe of the whole blocks of 16
   functions (sg_address16: face, texel, level; a third of a lookup's time, and independent of the light's values)
   kept as P [G / 16, B, N, 5, 16] int32 (per lane: i0, then fs, ft, a, w as float bits: 20 bytes per lobe; the flags
   are 7 for every lane where the pyramid has more than one texel per side and more than one width), then per light
   only the texel reads (sg_texels16); the tail functions (G mod 16) look up from the records as sg_range does. Same
   arithmetic, so the same bits as prt_sg_lookup_sum. Return 1 (nothing done) without the 16-lane kernels, for a
   shape they do not take (sg_vec), or a pyramid of one texel per side or one width. */
#define PREP_AT(P, blk, b, n, B, N) ((P) + (((blk) * (B) + (b)) * (N) + (n)) * 80)
int prt_sg_prepare(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss,
                   i64 r, i64 L, const float *ladder, int32_t *P, int nthreads) {
#ifdef SG16
    if (!sg_vec(G * B * N, L, r, 3) || r < 2 || L < 2) return 1;
    i64 nth = nthreads > 0 ? nthreads : 1, nb = G / 16;
    const int rec = IS_RECORD, sep = sw == 1 && sm == 3 && ss == 1;
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++) {
        __m512 lad[2];
        ladder32(ladder, L, lad);
        for (i64 blk = nb * t / nth; blk < nb * (t + 1) / nth; blk++)
            for (i64 b = 0; b < B; b++)
                for (i64 n = 0; n < N; n++) {
                    __m512 X, Y, Z, S, W, fs, ft, a;
                    __m512i i0, flags;
                    sg_load16(16 * blk, b * fb, n, N, mu, sigma, w, sw, sm, ss, rec, sep, &X, &Y, &Z, &S, &W);
                    sg_address16(X, Y, Z, S, r, L, ladder, lad, &i0, &flags, &fs, &ft, &a);
                    int32_t *q = PREP_AT(P, blk, b, n, B, N);
                    (void)flags;  /* 7 in every lane (r > 1, L > 1) */
                    _mm512_storeu_si512(q, i0);
                    _mm512_storeu_ps(q + 16, fs);
                    _mm512_storeu_ps(q + 32, ft);
                    _mm512_storeu_ps(q + 48, a);
                    _mm512_storeu_ps(q + 64, W);
                }
    }
    return 0;
#else
    (void)G; (void)B; (void)fb; (void)N; (void)mu; (void)sigma; (void)w; (void)sw; (void)sm; (void)ss; (void)r; (void)L;
    (void)ladder; (void)P; (void)nthreads;
    return 1;
#endif
}
int prt_sg_lookup_prepared(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm,
                           i64 ss, const int32_t *P, const float *table, const float *quads, i64 r, i64 L, const float *ladder,
                           float *out, int nthreads) {
#ifdef SG16
    if (!sg_vec(G * B * N, L, r, 3) || r < 2 || L < 2) return 1;
    i64 nth = nthreads > 0 ? nthreads : 1, nb = G / 16;
    const __m512i flags = _mm512_set1_epi32(7);
    const int nt = sg_nt(G, B, out);
    if (!sg_quads_fit(L, r, 3)) quads = NULL;
    const i64 dl = 16 * 6 * r * r;
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++) {
        float stage[SG_STAGE] __attribute__((aligned(64)));
        for (i64 blk = nb * t / nth; blk < nb * (t + 1) / nth; blk++) {
            float *ob = sg_stage(stage, out + 3 * 16 * blk * B, nt);
            for (i64 b = 0; b < B; b++) {  /* B > 1: the block's rows (16 B C floats) stay in L1 over its B functions */
                if (quads && N <= 4) {  /* the lanes outer (sg_lanes_quads) */
                    sg_quad_setup u[4] __attribute__((aligned(64)));
                    const char *pf = (const char *)PREP_AT(P, blk, b, 0, B, N) + 8 * 320 * N;
                    for (i64 f = 0; f < 5 * N; f++) _mm_prefetch(pf + 64 * f, _MM_HINT_T0);
                    for (i64 n = 0; n < N; n++) {
                        const int32_t *q = PREP_AT(P, blk, b, n, B, N);
                        sg_quads_setup(_mm512_loadu_si512(q), _mm512_loadu_ps(q + 16), _mm512_loadu_ps(q + 32), _mm512_loadu_ps(q + 48),
                                       _mm512_loadu_ps(q + 64), &u[n]);
                    }
                    sg_lanes_quads(u, N, quads, dl, ob + 3 * b, B);
                    continue;
                }
                __m128 acc[16];
                for (int l = 0; l < 16; l++) acc[l] = _mm_setzero_ps();
                /* the addressing 8 functions ahead (measured: 1.05x over the hardware prefetcher alone) */
                const char *pf = (const char *)PREP_AT(P, blk, b, 0, B, N) + 8 * 320 * N;
                for (i64 f = 0; f < 5 * N; f++) _mm_prefetch(pf + 64 * f, _MM_HINT_T0);
                for (i64 n = 0; n < N; n++) {
                    const int32_t *q = PREP_AT(P, blk, b, n, B, N);
                    if (quads)
                        sg_quads16(_mm512_loadu_si512(q), _mm512_loadu_ps(q + 16), _mm512_loadu_ps(q + 32),
                                   _mm512_loadu_ps(q + 48), _mm512_loadu_ps(q + 64), quads, dl, acc);
                    else
                        sg_texels16(_mm512_loadu_si512(q), flags, _mm512_loadu_ps(q + 16), _mm512_loadu_ps(q + 32),
                                    _mm512_loadu_ps(q + 48), _mm512_loadu_ps(q + 64), table, r, acc);
                }
                store16_rgb(ob + 3 * b, B, acc, NULL);
            }
            sg_flush(stage, out + 3 * 16 * blk * B, B, nt);
        }
        if (nt) _mm_sfence();
        if (t + 1 == nth)  /* the tail: from the records, as sg_range's scalar loop */
            sg_range(16 * nb, G, B, fb, N, mu, sigma, w, sw, sm, ss, table, NULL, r, L, ladder, 3, 0, 0, out);
    }
    return 0;
#else
    (void)G; (void)B; (void)fb; (void)N; (void)mu; (void)sigma; (void)w; (void)sw; (void)sm; (void)ss; (void)P; (void)table;
    (void)quads; (void)r; (void)L; (void)ladder; (void)out; (void)nthreads;
    return 1;
#endif
}

/* Relighting with view taps (Green §2.3): per vertex v, the lobes of its k tapped views blended
   (weights and widths linearly, means as the normalised weighted sum; gaussian.blend_lobes) with
   a_t / sum(a), looked up, summed over the N lobes and scaled by sum(a). Lobe n of vertex v and view j
   has lobe index m = v fv + j fj + n (w[sw m], ...): (fv, fj) = (J N, N) vertex-major, (N, V N) for
   the view-major records [J, V, N, 5], where a camera's taps read a few runs along the vertices;
   idx [V, k] (in [0, J), checked by the caller), a [V, k]. */
/* 1 if a tap among taps [t0, t1) has an index outside [0, J) or a weight that is negative or not finite (Green
   2005 §2.3: the blend is convex), else 0: one branch-free pass */
static int taps_bad(i64 t0, i64 t1, const i64 *idx, const float *av, i64 J) {
    int bad = 0;
#ifdef SG16
    /* 16 taps a step, the rest below (the scalar loop alone was 14% of a three-tap relight at 50 000 vertices) */
    const __m512i Jv = _mm512_set1_epi64(J);
    const __m512 zero = _mm512_setzero_ps(), fmax = _mm512_set1_ps(FLT_MAX);
    __mmask16 b = 0;
    for (; t0 + 16 <= t1; t0 += 16) {
        const __m512 a = _mm512_loadu_ps(av + t0);
        b |= (__mmask16)(_mm512_cmpge_epu64_mask(_mm512_loadu_si512(idx + t0), Jv)
                         | _mm512_cmpge_epu64_mask(_mm512_loadu_si512(idx + t0 + 8), Jv))
             | (__mmask16)~(_mm512_cmp_ps_mask(a, zero, _CMP_GE_OQ) & _mm512_cmp_ps_mask(a, fmax, _CMP_LE_OQ));
    }
    bad = b != 0;
#endif
    for (i64 t = t0; t < t1; t++) bad |= ((uint64_t)idx[t] >= (uint64_t)J) | !(av[t] >= 0.0f && av[t] <= FLT_MAX);
    return bad;
}

/* P == NULL: relight vertices [v0, v1) into out. P != NULL (prt_sg_taps_prepare; v0 a multiple of 16): instead of the
   lookups, keep each whole block of 16 vertices' blended lobes' addressing at PREP_AT(P, v0 / 16, 0, n, 1, N) (as
   prt_sg_prepare's, the weight being the blended one) and their sum(a) at tot + v0; the tail is not prepared */
static inline __attribute__((always_inline)) void sg_taps_range_(i64 v0, i64 v1, i64 fv, i64 fj, i64 N, i64 k, const float *w,
        const float *mu, const float *sigma, i64 sw, i64 sm, i64 ss, const i64 *idx, const float *av, const float *table, i64 r,
        i64 L, const float *ladder, i64 C, int vec, float *out, int32_t *P, float *totp) {
#ifdef SG16
    if (vec && k <= 8) {  /* 16 vertices at a time (lane l: vertex v + l), the rest below */
        const int rec = IS_RECORD;
        __m512 lad[2];
        ladder32(ladder, L, lad);
        for (; v0 + 16 <= v1; v0 += 16) {
            int32_t mb[8][16];  /* per tap and lane: the lobe index v fv + idx fj of lobe 0 */
            float at[8][16];
            if (k == 3) {  /* the usual three taps: 48 indices and weights deinterleaved by permutes (the scalar loop below
                              took a fifth of the time; with the vector check of the taps, 1.26x at one lobe) */
                const i64 *ip = idx + 3 * v0;
                __m256i c[6];
                for (int i = 0; i < 6; i++) c[i] = _mm512_cvtepi64_epi32(_mm512_loadu_si512(ip + 8 * i));
                const __m512 z0 = _mm512_castsi512_ps(_mm512_inserti64x4(_mm512_castsi256_si512(c[0]), c[1], 1));
                const __m512 z1 = _mm512_castsi512_ps(_mm512_inserti64x4(_mm512_castsi256_si512(c[2]), c[3], 1));
                const __m512 z2 = _mm512_castsi512_ps(_mm512_inserti64x4(_mm512_castsi256_si512(c[4]), c[5], 1));
                const __m512 a0 = _mm512_loadu_ps(av + 3 * v0), a1 = _mm512_loadu_ps(av + 3 * v0 + 16), a2 = _mm512_loadu_ps(av + 3 * v0 + 32);
                const __m512i lane = _mm512_set_epi32(15, 14, 13, 12, 11, 10, 9, 8, 7, 6, 5, 4, 3, 2, 1, 0);
                const __m512i base = _mm512_mullo_epi32(_mm512_add_epi32(lane, _mm512_set1_epi32((int)v0)), _mm512_set1_epi32((int)fv));
                const __m512i ix = _mm512_set_epi32(45, 42, 39, 36, 33, 30, 27, 24, 21, 18, 15, 12, 9, 6, 3, 0);
                for (int t = 0; t < 3; t++) {
                    const __m512i it = _mm512_add_epi32(ix, _mm512_set1_epi32(t));
                    const __m512i id = _mm512_castps_si512(deint3(z0, z1, z2, it));
                    _mm512_storeu_si512(mb[t], _mm512_add_epi32(base, _mm512_mullo_epi32(id, _mm512_set1_epi32((int)fj))));
                    _mm512_storeu_ps(at[t], deint3(a0, a1, a2, it));
                }
            } else
            for (i64 t = 0; t < k; t++)
                for (int l = 0; l < 16; l++) {
                    mb[t][l] = (int32_t)((v0 + l) * fv + idx[(v0 + l) * k + t] * fj);
                    at[t][l] = av[(v0 + l) * k + t];
                }
            __m512 tot = _mm512_setzero_ps();
            for (i64 t = 0; t < k; t++) tot = _mm512_add_ps(tot, _mm512_loadu_ps(at[t]));
            const __m512 tiny = _mm512_set1_ps(1e-12f);
            __m512 inv = _mm512_div_ps(_mm512_set1_ps(1.0f),
                                       _mm512_mask_blend_ps(_mm512_cmp_ps_mask(tot, tiny, _CMP_GT_OQ), tiny, tot));
            __m128 acc[16];
            for (int l = 0; l < 16; l++) acc[l] = _mm_setzero_ps();
            float an[8][16] __attribute__((aligned(64)));
            for (i64 t = 0; t < k; t++) _mm512_store_ps(an[t], _mm512_mul_ps(_mm512_loadu_ps(at[t]), inv));
            /* two or three lobes: a view's records are one run of 5 N <= 15 floats, so each tap is one masked load and
               one multiply-add for all the lobes (the same per-float operations as one lobe at a time below: the same
               bits; measured, three lobes at 50 000 vertices: 1.14x), and lobe n's blended records go to blall[n] + 16
               (masked stores of its 5 floats; the 16 floats before it are room for the store's masked-off start) */
            float blall[3][16 * 5 + 32] __attribute__((aligned(64)));
            const int all = rec && N >= 2 && N <= 3;
            if (all) {
                const __mmask16 run = (__mmask16)((1u << (5 * N)) - 1);
#define BLEND_ALL(K) for (int l = 0; l < 16; l++) {                                                                     \
                    __m512 b = _mm512_setzero_ps();                                                                     \
                    for (i64 t = 0; t < (K); t++)                                                                       \
                        b = _mm512_fmadd_ps(_mm512_set1_ps(an[t][l]), _mm512_maskz_loadu_ps(run, w + 5 * (i64)mb[t][l]), b); \
                    for (i64 n = 0; n < N; n++)                                                                         \
                        _mm512_mask_storeu_ps(blall[n] + 16 + 5 * l - 5 * n, (__mmask16)(0x1fu << (5 * n)), b);         \
                }
                if (k == 3) BLEND_ALL(3)
                else BLEND_ALL(k)
#undef BLEND_ALL
            }
            for (i64 n = 0; n < N; n++) {
                __m512 wb = _mm512_setzero_ps(), sb = wb, mx = wb, my = wb, mz = wb;
                if (all) {
                    const float *bl = blall[n] + 16;
                    __m512 q[5] = {_mm512_load_ps(bl), _mm512_load_ps(bl + 16), _mm512_load_ps(bl + 32), _mm512_load_ps(bl + 48),
                                   _mm512_load_ps(bl + 64)};
                    wb = deint5(q, 0); mx = deint5(q, 1); my = deint5(q, 2); mz = deint5(q, 3); sb = deint5(q, 4);
                } else if (rec) {  /* records: per lane, the k tapped records (w, mu, sigma: 5 floats, one masked load each)
                               blended by the same multiply-adds as the gathers below, each 5 floats into a row of 16
                               blended records, deinterleaved as sg_range's (15 gathers of 16 per lobe cost more) */
                    float bl[16 * 5 + 8] __attribute__((aligned(64)));
#define BLEND_LANES(K) for (int l = 0; l < 16; l++) {                                                                   \
                        __m256 b = _mm256_setzero_ps();                                                                 \
                        for (i64 t = 0; t < (K); t++)                                                                   \
                            b = _mm256_fmadd_ps(_mm256_set1_ps(an[t][l]), _mm256_maskz_loadu_ps(0x1f, w + 5 * ((i64)mb[t][l] + n)), b); \
                        _mm256_storeu_ps(bl + 5 * l, b);                                                                \
                    }
                    if (k == 3) BLEND_LANES(3)  /* the usual three taps: unrolled (1.0x-1.1x) */
                    else BLEND_LANES(k)
#undef BLEND_LANES
                    __m512 q[5] = {_mm512_load_ps(bl), _mm512_load_ps(bl + 16), _mm512_load_ps(bl + 32), _mm512_load_ps(bl + 48),
                                   _mm512_load_ps(bl + 64)};
                    wb = deint5(q, 0); mx = deint5(q, 1); my = deint5(q, 2); mz = deint5(q, 3); sb = deint5(q, 4);
                } else
                for (i64 t = 0; t < k; t++) {
                    __m512 an_ = _mm512_load_ps(an[t]);
                    __m512i m = _mm512_add_epi32(_mm512_loadu_si512(mb[t]), _mm512_set1_epi32((int)n));
                    __m512i m3 = _mm512_mullo_epi32(m, _mm512_set1_epi32((int)sm));
                    wb = _mm512_fmadd_ps(an_, _mm512_i32gather_ps(_mm512_mullo_epi32(m, _mm512_set1_epi32((int)sw)), w, 4), wb);
                    sb = _mm512_fmadd_ps(an_, _mm512_i32gather_ps(_mm512_mullo_epi32(m, _mm512_set1_epi32((int)ss)), sigma, 4), sb);
                    mx = _mm512_fmadd_ps(an_, _mm512_i32gather_ps(m3, mu, 4), mx);
                    my = _mm512_fmadd_ps(an_, _mm512_i32gather_ps(m3, mu + 1, 4), my);
                    mz = _mm512_fmadd_ps(an_, _mm512_i32gather_ps(m3, mu + 2, 4), mz);
                }
                __m512 nm = _mm512_sqrt_ps(_mm512_fmadd_ps(mz, mz, _mm512_fmadd_ps(my, my, _mm512_mul_ps(mx, mx))));
                nm = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(nm, tiny, _CMP_GT_OQ), tiny, nm);
                const __m512 smin = _mm512_set1_ps(1e-6f);
                const __m512 X = _mm512_div_ps(mx, nm), Y = _mm512_div_ps(my, nm), Z = _mm512_div_ps(mz, nm);
                const __m512 S = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(sb, smin, _CMP_GT_OQ), smin, sb);
                if (P) {  /* sg_lookup16's first part, kept */
                    __m512i i0, flags;
                    __m512 fs, ft, a;
                    sg_address16(X, Y, Z, S, r, L, ladder, lad, &i0, &flags, &fs, &ft, &a);
                    (void)flags;  /* 7 in every lane (r > 1, L > 1) */
                    int32_t *q = PREP_AT(P, v0 / 16, 0, n, 1, N);
                    _mm512_storeu_si512(q, i0);
                    _mm512_storeu_ps(q + 16, fs);
                    _mm512_storeu_ps(q + 32, ft);
                    _mm512_storeu_ps(q + 48, a);
                    _mm512_storeu_ps(q + 64, wb);
                } else
                    sg_lookup16(X, Y, Z, S, wb, table, r, L, ladder, lad, acc);
            }
            if (P) {
                _mm512_storeu_ps(totp + v0, tot);
                continue;
            }
            float tt[16];
            _mm512_storeu_ps(tt, tot);
            store16_rgb(out + 3 * v0, 1, acc, tt);
        }
    }
#else
    (void)vec;
#endif
    if (P) return;
    for (i64 v = v0; v < v1; v++) {
        float acc[16] = {0}, tot = 0;
        for (i64 t = 0; t < k; t++) tot += av[v * k + t];
        float inv = 1.0f / (tot > 1e-12f ? tot : 1e-12f);
        for (i64 n = 0; n < N; n++) {
            float wb = 0, sb = 0, mx = 0, my = 0, mz = 0;
            for (i64 t = 0; t < k; t++) {
                float an = av[v * k + t] * inv;
                i64 m = v * fv + idx[v * k + t] * fj + n;
                wb += an * w[sw * m]; sb += an * sigma[ss * m];
                mx += an * mu[sm * m]; my += an * mu[sm * m + 1]; mz += an * mu[sm * m + 2];
            }
            float nm = sqrtf(mx * mx + my * my + mz * mz);
            nm = nm > 1e-12f ? nm : 1e-12f;
            sg_lookup(mx / nm, my / nm, mz / nm, sb > 1e-6f ? sb : 1e-6f, wb, table, r, L, ladder, C, acc);
        }
        for (i64 c = 0; c < C; c++) out[v * C + c] = acc[c] * tot;
    }
}
static void sg_taps_range(i64 v0, i64 v1, i64 fv, i64 fj, i64 N, i64 k, const float *w, const float *mu, const float *sigma,
                          i64 sw, i64 sm, i64 ss, const i64 *idx, const float *av, const float *table, i64 r, i64 L, const float *ladder,
                          i64 C, int vec, float *out) {
    sg_taps_range_(v0, v1, fv, fj, N, k, w, mu, sigma, sw, sm, ss, idx, av, table, r, L, ladder, C, vec, out, NULL, NULL);
}

/* returns 1, writing nothing, if a tap is bad (taps_bad): each thread checks its vertices' taps, then all compute
   only if none found one */
int prt_sg_taps(i64 V, i64 J, i64 N, i64 k, i64 fv, i64 fj, const float *w, const float *mu, const float *sigma, i64 sw, i64 sm, i64 ss,
                const i64 *idx, const float *av, const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads) {
    i64 nth = nthreads > 0 ? nthreads : 1;
    int vec = sg_vec(V * J * N, L, r, C), bad = 0;
    #pragma omp parallel num_threads(nth)
    {
#ifdef _OPENMP
        i64 t = omp_get_thread_num(), n = omp_get_num_threads();
#else
        i64 t = 0, n = 1;
        (void)nth;
#endif
        i64 v0 = SPLIT16(V, t, n), v1 = SPLIT16_END(V, t, n);  /* whole blocks of 16: bits independent of the thread count */
        if (taps_bad(v0 * k, v1 * k, idx, av, J)) {
            #pragma omp atomic write
            bad = 1;
        }
        #pragma omp barrier
        int any;
        #pragma omp atomic read
        any = bad;
        if (!any) sg_taps_range(v0, v1, fv, fj, N, k, w, mu, sigma, sw, sm, ss, idx, av, table, r, L, ladder, C, vec, out);
    }
    return bad;
}

/* A prepared relight with taps (GaussianCodec.relighter(enc, taps)): the blend and the addressing of each whole block of
   16 vertices' lobes (everything but the texel reads: they depend on the lobes, the taps and the pyramid's shape, not on
   the light's values) kept as P [V / 16, N, 5, 16] int32 (prt_sg_prepare's layout with B = 1, the blended weight in
   place of w) and tot [V / 16 * 16] = sum(a); per light only the texel reads, and the tail of fewer than 16 vertices
   from the records and taps as prt_sg_taps. The same arithmetic, so the same bits as prt_sg_taps. Returns 1 (nothing
   written) if a tap is bad (taps_bad; the prepare checks them all, each light the tail's, the only taps it reads), 2
   (nothing done) without the 16-lane kernels, for a shape they do not take (sg_vec, k > 8), or a pyramid of one texel
   per side or one width. */
int prt_sg_taps_prepare(i64 V, i64 J, i64 N, i64 k, i64 fv, i64 fj, const float *w, const float *mu, const float *sigma, i64 sw,
                        i64 sm, i64 ss, const i64 *idx, const float *av, i64 r, i64 L, const float *ladder, int32_t *P, float *tot,
                        int nthreads) {
#ifdef SG16
    if (!sg_vec(V * J * N, L, r, 3) || r < 2 || L < 2 || k > 8) return 2;
    i64 nth = nthreads > 0 ? nthreads : 1, nb = V / 16;
    int bad = 0;
    #pragma omp parallel num_threads(nth)
    {
#ifdef _OPENMP
        i64 t = omp_get_thread_num(), n = omp_get_num_threads();
#else
        i64 t = 0, n = 1;
#endif
        i64 v0 = SPLIT16(V, t, n), v1 = SPLIT16_END(V, t, n);
        if (taps_bad(v0 * k, v1 * k, idx, av, J)) {
            #pragma omp atomic write
            bad = 1;
        }
        #pragma omp barrier
        int any;
        #pragma omp atomic read
        any = bad;
        if (!any)
            sg_taps_range_(v0, v1 < 16 * nb ? v1 : 16 * nb, fv, fj, N, k, w, mu, sigma, sw, sm, ss, idx, av, NULL, r, L, ladder, 3,
                           1, NULL, P, tot);
    }
    return bad;
#else
    (void)V; (void)J; (void)N; (void)k; (void)fv; (void)fj; (void)w; (void)mu; (void)sigma; (void)sw; (void)sm; (void)ss;
    (void)idx; (void)av; (void)r; (void)L; (void)ladder; (void)P; (void)tot; (void)nthreads;
    return 2;
#endif
}
int prt_sg_taps_prepared(i64 V, i64 J, i64 N, i64 k, i64 fv, i64 fj, const float *w, const float *mu, const float *sigma, i64 sw,
                         i64 sm, i64 ss, const i64 *idx, const float *av, const int32_t *P, const float *tot, const float *table,
                         i64 r, i64 L, const float *ladder, float *out, int nthreads) {
#ifdef SG16
    if (!sg_vec(V * J * N, L, r, 3) || r < 2 || L < 2 || k > 8) return 2;
    i64 nth = nthreads > 0 ? nthreads : 1, nb = V / 16;
    if (taps_bad(16 * nb * k, V * k, idx, av, J)) return 1;
    const __m512i flags = _mm512_set1_epi32(7);
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++) {
        for (i64 blk = nb * t / nth; blk < nb * (t + 1) / nth; blk++) {
            if (N <= 4) {  /* the lanes outer (sg_lanes_pairs) */
                int32_t ix[4][4][16] __attribute__((aligned(64)));
                float wp[4][4][32] __attribute__((aligned(64)));
                for (i64 n = 0; n < N; n++) {
                    const int32_t *q = PREP_AT(P, blk, 0, n, 1, N);
                    sg_pairs_of(_mm512_loadu_si512(q), flags, _mm512_loadu_ps(q + 16), _mm512_loadu_ps(q + 32), _mm512_loadu_ps(q + 48),
                                _mm512_loadu_ps(q + 64), r, ix[n], wp[n]);
                }
                sg_lanes_pairs(ix, wp, N, table, tot + 16 * blk, out + 48 * blk, 1);
                continue;
            }
            __m128 acc[16];
            for (int l = 0; l < 16; l++) acc[l] = _mm_setzero_ps();
            for (i64 n = 0; n < N; n++) {
                const int32_t *q = PREP_AT(P, blk, 0, n, 1, N);
                sg_texels16(_mm512_loadu_si512(q), flags, _mm512_loadu_ps(q + 16), _mm512_loadu_ps(q + 32), _mm512_loadu_ps(q + 48),
                            _mm512_loadu_ps(q + 64), table, r, acc);
            }
            store16_rgb(out + 48 * blk, 1, acc, tot + 16 * blk);
        }
        if (t + 1 == nth)  /* the tail: from the records and taps, as prt_sg_taps's last thread */
            sg_taps_range(16 * nb, V, fv, fj, N, k, w, mu, sigma, sw, sm, ss, idx, av, table, r, L, ladder, 3, 1, out);
    }
    return 0;
#else
    (void)V; (void)J; (void)N; (void)k; (void)fv; (void)fj; (void)w; (void)mu; (void)sigma; (void)sw; (void)sm; (void)ss;
    (void)idx; (void)av; (void)P; (void)tot; (void)table; (void)r; (void)L; (void)ladder; (void)out; (void)nthreads;
    return 2;
#endif
}
"""

_FLAGS = ["-O3", "-march=native", "-ffp-contract=fast", "-fopenmp", "-shared", "-fPIC", "-std=c99"]
_lock = threading.Lock()
_state: dict = {}


def _compile() -> tuple[ctypes.CDLL | None, str]:
    """The library built from the module's current ``_SRC`` and ``_FLAGS`` (read at call time:
    ``benchmarks/ab_kernels.py`` swaps them to build another revision's kernels)."""
    i64, vp, ci = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int
    common = [vp, ci, vp, i64, vp, vp, i64, ci, vp, i64]
    return compile_library("relight", _SRC, _FLAGS, {
        "prt_affine_rows": [i64, i64, i64, *common, vp, vp, ci, ci],
        "prt_affine_dense": [i64, i64, i64, i64, i64, *common, vp, vp, vp, ci, ci],
        "prt_affine_taps": [i64, i64, i64, *common, i64, vp, vp, vp, vp, ci, ci],
        "prt_constants": [i64] * 7 + [vp, vp, vp] + [i64] * 4 + [vp, ci, ci],
        "prt_constants_lanes": [i64] * 5 + [vp, vp, vp] + [i64] * 2 + [ci],
        "prt_relight_plan": [vp, vp, vp, vp, vp, vp, ci],
        "prt_dense_pad": [i64],
        "prt_rows_pad": [i64, i64],
        "prt_sg_lookup_sum": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, i64, i64, vp, i64, vp, ci],
        "prt_sg_lookup_sum_q": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, i64, i64, vp, i64, vp, ci],
        "prt_sg_prepare": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, i64, i64, vp, vp, ci],
        "prt_sg_lookup_prepared": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, vp, i64, i64, vp, vp, ci],
        "prt_sg_taps": [i64, i64, i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, vp, i64, i64, vp, i64, vp, ci],
        "prt_sg_taps_prepare": [i64, i64, i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, i64, i64, vp, vp, vp, ci],
        "prt_sg_taps_prepared": [i64, i64, i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, vp, vp, vp, i64, i64, vp, vp, ci],
    })


try:  # CPython's os.environ keeps its values in a dict of encoded keys: a lookup there costs 0.05 µs per
    # relight, os.environ.get 0.7 µs (its KeyError path when the variable is unset); both see os.environ's updates
    _ENV, _ENV_KEY, _ENV_OFF = os.environ._data, os.environ.encodekey("PRT_TORCH_NATIVE"), os.environ.encodevalue("0")
except AttributeError:  # pragma: no cover  (another Python)
    _ENV = None


def _disabled() -> bool:
    """``PRT_TORCH_NATIVE=0`` in the environment (read at every call: tests and benchmarks set it)."""
    if _ENV is not None:
        return _ENV.get(_ENV_KEY) == _ENV_OFF
    return os.environ.get("PRT_TORCH_NATIVE", "1") == "0"  # pragma: no cover


def native() -> ctypes.CDLL | None:
    """The compiled kernels (compiled on the first call of a process, then cached on disk), or
    None: no C compiler, a failed compile, or ``PRT_TORCH_NATIVE=0``."""
    if _disabled():
        return None
    if "lib" not in _state:
        with _lock:
            if "lib" not in _state:
                _state["lib"], _state["why"] = _compile()
    return _state["lib"]


def native_status() -> dict:
    """``{'native': bool, 'detail': str}``: whether relighting uses the compiled kernels and why (not)."""
    if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return {"native": False, "detail": "disabled by PRT_TORCH_NATIVE=0"}
    lib = native()
    return {"native": lib is not None, "detail": _state.get("why", "")}


_LAB_KIND = {torch.uint8: 1, torch.int16: 2, torch.int32: 3}


def _ptr(t: torch.Tensor | None):
    return None if t is None else t.data_ptr()


def _codes(labels, W, wstride, woff, nk, nuse, mean):
    """The common argument block: labels (None: K = 1), weights ``W`` (None: no weights), row
    stride or per-point offsets ``woff int64 [P]`` with ``nk int64 [K]`` (packed), n used, mean."""
    kind = 0
    if labels is not None:
        kind = _LAB_KIND.get(labels.dtype, 0)
        if not kind:
            raise TypeError(f"labels have dtype {labels.dtype}; accepted: uint8, int16, int32")
        if not labels.is_contiguous():
            raise ValueError(f"labels must be contiguous; got {labels.dtype}, strides {labels.stride()}")
    for name, t, dt in (("weights", W, torch.float32), ("offsets", woff, torch.int64), ("n_vectors", nk, torch.int64)):
        if t is not None and (t.dtype != dt or not t.is_contiguous()):
            raise ValueError(f"{name} must be contiguous {dt}; got {t.dtype}, strides {t.stride()}")
    return [labels.data_ptr() if kind else None, kind, _ptr(W), int(wstride), _ptr(woff), _ptr(nk), int(nuse), int(bool(mean))]


def _pad8(n: int) -> int:
    return (n + 7) // 8 * 8


_MODEL_T: dict[tuple, tuple] = {}  # (id(basis), lanes) -> (weak reference to basis, key, Mt); dropped when basis dies


def model_t(means: torch.Tensor | None, basis: torch.Tensor, n_out: int, n_in: int, lanes: bool = False) -> torch.Tensor:
    """The representatives as the constants kernel reads them: ``[K, Jmax, n_in, n_pad]``
    float32 (x_0 first when ``means`` is given, then the basis rows; each n_out×n_in matrix
    transposed, n_out zero-padded to a multiple of 8); ``lanes=True`` (n_out = 1 only):
    ``[ceil(K/8), Jmax, n_in, 8]``, cluster 8b + l in lane l of block b (zero past K), as
    ``prt_constants_lanes`` reads them. Built once per model and kept while ``basis`` lives, one
    entry per basis and layout (keyed by the tensor and its version: refits and in-place edits
    rebuild; a codec of n_out = 1 relit with and without a view keeps both layouts)."""
    key = (tensor_version(basis), None if means is None else (id(means), tensor_version(means)), n_out, n_in, lanes)
    slot = (id(basis), bool(lanes))
    hit = _MODEL_T.get(slot)
    if hit is not None and hit[0]() is basis and hit[1] == key:
        return hit[2]
    K = basis.shape[0]
    reps = basis.reshape(K, -1, n_out, n_in)
    if means is not None:
        reps = torch.cat([means.reshape(K, 1, n_out, n_in), reps], 1)
    if lanes:
        if n_out != 1:
            raise ValueError(f"model_t: lanes=True lays out vectors (n_out = 1); got n_out = {n_out}")
        Mt = torch.zeros(_pad8(K), reps.shape[1], n_in, dtype=torch.float32)
        Mt[:K] = reps[:, :, 0]
        Mt = Mt.view(-1, 8, reps.shape[1], n_in).permute(0, 2, 3, 1).contiguous()
    else:
        Mt = torch.zeros(K, reps.shape[1], n_in, _pad8(n_out), dtype=torch.float32)
        Mt[..., :n_out] = reps.transpose(2, 3)
    if hit is None or hit[0]() is not basis:
        weakref.finalize(basis, _MODEL_T.pop, slot, None)
    _MODEL_T[slot] = (weakref.ref(basis), key, Mt)
    return Mt


def dense_pad(n_out: int) -> int:
    """The dense layout's colour stride for ``n_out`` rows: what the compiled kernels ask for
    (``prt_dense_pad``: 16-float lines for their 16-lane kernel), else ``n_out`` padded to 8."""
    lib = native()
    return int(lib.prt_dense_pad(n_out)) if lib is not None else _pad8(n_out)


def rows_pad(Fo: int, J: int) -> int:
    """The rows layout's row stride for rows of ``Fo`` floats and ``J`` terms: what the compiled
    kernels ask for (``prt_rows_pad``: 16-float lines for their wide pass), else ``Fo`` padded to 8."""
    lib = native()
    return int(lib.prt_rows_pad(Fo, J)) if lib is not None else _pad8(Fo)


#: where element (k, j, o, c) of the constants sits, per layout: (sizes of the padded tensor, strides k, j, o, c)
def constants_layout(kind: str, K: int, J: int, n_out: int, C: int) -> tuple[tuple, tuple]:
    if kind == "rows":  # [K, J, F8]: a point's row e_p in output order (o, c) (F8: rows_pad)
        F = rows_pad(n_out * C, J)
        return (K, J, F), (J * F, F, C, 1)
    if kind == "dense":  # [K, J, C, n8]: colour-major, each colour a dot with the view (n8: dense_pad)
        n8 = dense_pad(n_out)
        return (K, J, C, n8), (J * C * n8, C * n8, 1, n8)
    Jp = 1 if J == 1 else _pad8(J)  # taps: [K, n_out, C, J8]: a tapped row holds every term of every colour (one term: unpadded)
    return (K, n_out, C, Jp), (n_out * C * Jp, 1, C * Jp, Jp)


_WORKSPACE = threading.local()  # per thread: {(kind, size): constants buffer} (see constants(scratch=True))


def _model_args(means, basis, n: int, n_out: int, n_in: int, C: int, kind: str, nk: torch.Tensor | None) -> tuple:
    """The constants kernel's view of the model (shared by :func:`constants` and :func:`plan`):
    ``(lanes, Mt, K, J, Jmax, size, strides)`` — the layout's padded sizes and (k, j, o, c)
    strides (:func:`constants_layout`); ``nk`` checked."""
    lanes = n_out == 1 and kind == "rows"  # vectors: 8 clusters per vector (prt_constants_lanes)
    Mt = model_t(means, basis, n_out, n_in, lanes)
    K, Jmax = basis.shape[0], Mt.shape[1]
    if nk is not None and (nk.dtype != torch.int64 or nk.shape != (K,) or not nk.is_contiguous()):
        raise ValueError(f"constants: nk is {nk.dtype} {tuple(nk.shape)}{'' if nk.is_contiguous() else ', not contiguous'}; "
                         f"accepted: contiguous int64 [K] = [{K}] (the kernel indexes it per cluster)")
    J = (1 if means is not None else 0) + n
    size, strides = constants_layout(kind, K, J, n_out, C)
    return lanes, Mt, K, J, Jmax, size, strides


def _scratch(kind: str, size: tuple) -> torch.Tensor:
    """This thread's constants buffer of layout ``kind`` and padded ``size``, reused by its next
    call (zeroed once, when made: the kernels overwrite all but the padding)."""
    bufs = getattr(_WORKSPACE, "bufs", None)
    if bufs is None:
        bufs = _WORKSPACE.bufs = {}
    out = bufs.get((kind, size))
    if out is None:
        bufs.clear()  # one buffer per thread: the latest layout
        out = bufs[(kind, size)] = torch.zeros(size, dtype=torch.float32)
    return out


def _light_flagged(L: torch.Tensor, Lc: torch.Tensor) -> None:
    """Raise naming the light's first non-finite value (as given, else as converted to float32:
    a float64 value beyond its range), after a kernel flagged the float32 light it read."""
    check_finite_float32("light", L, Lc)
    raise RuntimeError("prt_constants flagged the light but no value of it is NaN or Inf")  # pragma: no cover


def constants(lib, means, basis, n: int, n_out: int, n_in: int, L: torch.Tensor, kind: str, scratch: bool = False,
              nk: torch.Tensor | None = None) -> torch.Tensor:
    """Per-cluster constants M_i^k l (Sloan 2003 §6) for ``light L [n_in, C]`` float32, the
    first ``n`` basis rows (and the mean), laid out for kernel ``kind`` ('rows', 'dense',
    'taps'), zero-padded; one pass over the model (:func:`model_t`). A light holding NaN or
    Inf, or a value beyond float32's range, raises ``ValueError`` naming the first one (the
    kernel checks the float32 light as it reads it). ``scratch=True`` writes into this thread's
    buffer of that layout, reused by its next call (its padding zeroed once, the rest
    overwritten): for a caller that uses the result before calling again, as
    ``AffineCodec.relight`` does — no allocation and no zeroing per light. ``nk`` (contiguous
    int64 ``[K]``, optional: the vectors each cluster keeps, CPCA adaptive): the kernels read
    cluster k's first (mean) + min(n, nk[k]) terms only; the rest of its rows are undefined
    ('rows', 'dense': vectors, whose constants take 8 clusters at a time, compute them all) or
    zero ('taps')."""
    C = L.shape[1]
    lanes, Mt, K, J, Jmax, size, (sk, sj, so, sc) = _model_args(means, basis, n, n_out, n_in, C, kind, nk)
    out = _scratch(kind, size) if scratch else torch.zeros(size, dtype=torch.float32)
    Lc = _as(L, torch.float32)
    if lanes:  # every term of every cluster: the rows past a cluster's n_k are never read
        bad = lib.prt_constants_lanes(K, J, Jmax, n_in, C, Mt.data_ptr(), Lc.data_ptr(), out.data_ptr(), sk, sj,
                                      torch.get_num_threads())
    else:
        bad = lib.prt_constants(K, J, Jmax, n_in, n_out, Mt.shape[3], C, Mt.data_ptr(), Lc.data_ptr(), out.data_ptr(),
                                sk, sj, so, sc, _ptr(nk), int(means is not None), torch.get_num_threads())
    if bad:
        _light_flagged(L, Lc)
    return out


#: ``prt_relight_plan``'s argument array, in its PL_ order (the C enum)
_PLAN_FIELDS = ("kind", "lanes", "K", "J", "Jmax", "n_in", "n_out", "n_pad", "C", "Mt", "sk", "sj", "so", "sc", "nk_c", "mean",
                "P", "x", "Fo", "lab", "lab_kind", "W", "wstride", "woff", "nk", "nuse", "order", "csort", "ntap")


class Plan:
    """One encoding's relighting, ready to run per light (:func:`plan`, :func:`run_plan`): the
    kernels' arguments that do not change between lights, as one int64 array, and the tensors
    they point into (kept alive with it)."""

    __slots__ = ("args", "args_ptr", "keep", "kind", "size", "n_in", "C", "P", "n_out", "ntap", "shape", "numel")


def plan(lib, means, basis, n: int, n_out: int, n_in: int, C: int, kind: str, labels, W, wstride, woff, nk, nuse, mean,
         P: int, order: torch.Tensor | None = None, codes_sorted: bool = False, ntap: int = 0) -> Plan:
    """A :class:`Plan` of one relighting — :func:`constants` (into this thread's scratch buffer)
    then :func:`affine_rows`, :func:`affine_dense` or :func:`affine_taps` (``kind``; ``ntap``
    taps per point), with the same arguments and checks, run by :func:`run_plan` in one ctypes
    call (``prt_relight_plan``): the same kernels, so the same bits. For a caller that relights
    one encoding under many lights (``AffineCodec`` caches one per encoding): the two calls'
    argument conversion and checks, ~10 µs of a small relight, are paid once."""
    lanes, Mt, K, J, Jmax, size, (sk, sj, so, sc) = _model_args(means, basis, n, n_out, n_in, C, kind, nk)
    code = _codes(labels, W, wstride, woff, nk, nuse, mean)
    if kind == "rows":
        x, Fo = size[2], n_out * C
    elif kind in ("dense", "taps"):
        x, Fo = size[3], n_out
    else:
        raise ValueError(f"plan: kind {kind!r}; accepted: 'rows', 'dense', 'taps'")
    if kind == "taps" and not 1 <= ntap <= 64:
        raise ValueError(f"plan: {ntap} taps per point; accepted: 1..64")
    vals = {"kind": {"rows": 0, "dense": 1, "taps": 2}[kind], "lanes": int(lanes), "K": K, "J": J, "Jmax": Jmax, "n_in": n_in,
            "n_out": n_out, "n_pad": Mt.shape[3] if not lanes else 8, "C": C, "Mt": Mt.data_ptr(), "sk": sk, "sj": sj, "so": so,
            "sc": sc, "nk_c": _ptr(nk) or 0, "mean": int(means is not None), "P": P, "x": x, "Fo": Fo,
            "lab": code[0] or 0, "lab_kind": code[1], "W": code[2] or 0, "wstride": code[3], "woff": code[4] or 0,
            "nk": code[5] or 0, "nuse": code[6], "order": _order(order, P) or 0, "csort": _csort(order, codes_sorted),
            "ntap": ntap}
    pl = Plan()
    pl.args = torch.tensor([vals[f] for f in _PLAN_FIELDS], dtype=torch.int64)
    pl.args_ptr = pl.args.data_ptr()
    pl.keep = (Mt, labels, W, woff, nk, order)
    pl.kind, pl.size, pl.n_in, pl.C, pl.P, pl.n_out, pl.ntap = kind, size, n_in, C, P, n_out, ntap
    pl.shape = (P, Fo) if kind == "rows" else (P, C)
    pl.numel = P * pl.shape[1]
    return pl


def run_plan(lib, pl: Plan, L: torch.Tensor, view=None, out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """Relight under ``L [n_in, C]`` by plan ``pl``: ``(result, flag)`` as the kernel of its kind
    returns them (rows: ``[P, n_out·C]``; dense, taps: ``[P, C]``; into ``out`` when given).
    ``view``: dense ``y [P, n_out]`` float32, taps ``(idx int64 [P, t], g float32 [P, t])``, or
    None (rows). A non-finite light raises naming the value, as :func:`constants` does."""
    Lc = _as(L, torch.float32)
    if Lc.shape != (pl.n_in, pl.C):
        raise ValueError(f"run_plan: light {tuple(Lc.shape)}; accepted: [{pl.n_in}, {pl.C}] (the plan's)")
    y0 = y1 = None
    if pl.kind == "dense":
        if view.dtype != torch.float32 or view.shape != (pl.P, pl.n_out):
            raise ValueError(f"run_plan: dense view {view.dtype} {tuple(view.shape)}; accepted: float32 [{pl.P}, {pl.n_out}]")
        view = view if view.is_contiguous() else view.contiguous()
        y0 = view.data_ptr()
    elif pl.kind == "taps":
        idx, g = view
        if idx.dtype != torch.int64 or g.dtype != torch.float32 or idx.shape != (pl.P, pl.ntap) or g.shape != idx.shape:
            raise ValueError(f"run_plan: taps {idx.dtype} {tuple(idx.shape)}, {g.dtype} {tuple(g.shape)}; accepted: int64 and "
                             f"float32 [{pl.P}, {pl.ntap}]")
        idx, g = _as(idx, torch.int64), _as(g, torch.float32)
        y0, y1 = idx.data_ptr(), g.data_ptr()
    elif view is not None:
        raise ValueError("run_plan: a view for a plan of kind 'rows'; accepted: None")
    out = _out(out, pl.numel, pl.shape)
    return out, run_checked(lib, pl, L, Lc, y0, y1, out)


def run_checked(lib, pl: Plan, L: torch.Tensor, Lc: torch.Tensor, y0, y1, out: torch.Tensor) -> int:
    """The kernel call of :func:`run_plan`, after its checks (``Lc``: the light as float32
    contiguous ``[n_in, C]``; ``y0``, ``y1``: the view's addresses; ``out``: contiguous float32 of
    the plan's size) — for a caller that has checked them (``AffineRelighter``'s fast path):
    the kernels' flag, after raising for a flagged light."""
    T = _scratch(pl.kind, pl.size)
    flag = lib.prt_relight_plan(pl.args_ptr, Lc.data_ptr(), T.data_ptr(), out.data_ptr(), y0, y1, torch.get_num_threads())
    if flag & 16:
        _light_flagged(L, Lc)
    return int(flag)


_ORDERS_CHECKED: dict[int, tuple] = {}  # id(order) -> (weak reference, version): range already checked


def _order(order, P: int):
    """The visiting order: None (point order) or a permutation ``int32 [P]`` (cluster order).
    Its range is checked once per tensor and version (a cached order is reused every call)."""
    if order is None:
        return None
    if order.dtype != torch.int32 or order.shape != (P,) or not order.is_contiguous():
        raise ValueError(f"order must be a contiguous int32 permutation [{P}]; got {order.dtype} {tuple(order.shape)}")
    hit = _ORDERS_CHECKED.get(id(order))
    if hit is None or hit[0]() is not order or hit[1] != tensor_version(order):
        lo, hi = (int(x) for x in torch.aminmax(order)) if P else (0, -1)
        if P and (lo < 0 or hi >= P):
            raise ValueError(f"order spans [{lo}, {hi}]; accepted: a permutation of 0..{P - 1}")
        if hit is None or hit[0]() is not order:
            weakref.finalize(order, _ORDERS_CHECKED.pop, id(order), None)
        _ORDERS_CHECKED[id(order)] = (weakref.ref(order), tensor_version(order))
    return order.data_ptr()


def _as(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``t`` as a contiguous tensor of ``dtype``: itself when it already is (a ``.to()`` and a
    ``.contiguous()`` cost about a microsecond each even when they copy nothing)."""
    return t if t.dtype == dtype and t.is_contiguous() else t.to(dtype).contiguous()


def _pyramid(fn: str, table: torch.Tensor, ladder: torch.Tensor, res: int) -> None:
    """Refuse, before a kernel reads them, a pyramid whose rows are not ``L·6·r·r`` for the
    ladder's L levels and resolution r, or a table or ladder off the CPU: the kernels size their
    reads from the ladder and r (a light's own check can be got around by assigning through
    ``.data``; this one is at the call, in O(1)). A quad table is checked against the table by
    :func:`_quads_ptr`."""
    off = [(n, t.device) for n, t in (("table", table), ("ladder", ladder)) if t.device.type != "cpu"]
    if off:
        raise ValueError(f"{fn}: the pyramid's {off[0][0]} is on {off[0][1]}; accepted: CPU tensors")
    rows = ladder.numel() * 6 * int(res) * int(res)
    if table.dim() != 2 or table.shape[0] != rows:
        raise ValueError(f"{fn}: a pyramid table {tuple(table.shape)} for {ladder.numel()} levels of 6×{res}×{res}; "
                         f"accepted: {rows} rows (levels · 6 · res²)")


def _out(out: torch.Tensor | None, numel: int, shape: tuple) -> torch.Tensor:
    """The kernels' result tensor: ``out`` (contiguous float32 with ``numel`` elements, any shape
    of them) or a new ``[shape]``."""
    if out is None:
        return torch.empty(shape, dtype=torch.float32)
    if out.dtype != torch.float32 or not out.is_contiguous() or out.numel() != numel:
        raise ValueError(f"out must be contiguous float32 with {numel} elements; got {out.dtype} {tuple(out.shape)}")
    return out


def _csort(order, codes_sorted: bool) -> int:
    """1 when the codes are stored in visiting order (the q-th point visited reads the q-th code
    and writes output row ``order[q]``), 0 when they are in point order."""
    if codes_sorted and order is None:
        raise ValueError("codes_sorted=True needs an order (the permutation the codes were sorted by)")
    return int(bool(codes_sorted))


def affine_rows(lib, T: torch.Tensor, J: int, n_out: int, C: int, labels, W, wstride, woff, nk, nuse, mean, P: int,
                order: torch.Tensor | None = None, codes_sorted: bool = False, out: torch.Tensor | None = None) -> torch.Tensor:
    """No view: ``e_p`` for every point, ``[P, n_out·C] float32`` (into ``out``, contiguous
    float32 of P·n_out·C elements, when given), from the constants ``T`` of layout 'rows';
    ``order`` (a permutation ``int32 [P]``, e.g. by cluster) is the order the points are visited
    in (None: 0..P-1); ``codes_sorted``: the codes are stored in that order."""
    Fo = n_out * C
    if Fo > T.shape[2]:
        raise ValueError(f"affine_rows: rows of n_out·C = {Fo} floats from constants of {T.shape[2]}; accepted: n_out·C <= T.shape[2]")
    out = _out(out, P * Fo, (P, Fo))
    lib.prt_affine_rows(P, T.shape[2], Fo, *_codes(labels, W, wstride, woff, nk, nuse, mean), T.data_ptr(), J,
                        out.data_ptr(), _order(order, P), _csort(order, codes_sorted), torch.get_num_threads())
    return out


def affine_dense(lib, T: torch.Tensor, J: int, n_out: int, C: int, labels, W, wstride, woff, nk, nuse, mean,
                 y: torch.Tensor, order: torch.Tensor | None = None, codes_sorted: bool = False,
                 out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """Dense view ``y [P, n_out]`` float32 contiguous: ``[P, C]`` from the constants ``T`` of
    layout 'dense', and a flag (2: a non-finite output)."""
    if not y.is_contiguous() or y.dtype != torch.float32 or y.shape[1] != n_out:
        raise ValueError(f"affine_dense: the view must be contiguous float32 [P, {n_out}]")
    P = y.shape[0]
    out = _out(out, P * C, (P, C))
    flag = lib.prt_affine_dense(T.shape[0], P, n_out, T.shape[3], C, *_codes(labels, W, wstride, woff, nk, nuse, mean), T.data_ptr(), J,
                                y.data_ptr(), out.data_ptr(), _order(order, P), _csort(order, codes_sorted), torch.get_num_threads())
    return out, int(flag)


def affine_taps(lib, T: torch.Tensor, J: int, n_out: int, C: int, labels, W, wstride, woff, nk, nuse, mean,
                idx: torch.Tensor, g: torch.Tensor, order: torch.Tensor | None = None,
                codes_sorted: bool = False, out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """Taps ``(idx int64 [P, t], g float32 [P, t])`` contiguous, t ≤ 64: ``[P, C]`` from the
    constants ``T`` of layout 'taps', and a flag (1: a tap index outside [0, n_out); 2: a
    non-finite output)."""
    if idx.dtype != torch.int64 or g.dtype != torch.float32 or not idx.is_contiguous() or not g.is_contiguous() or idx.shape[1] > 64:
        raise ValueError("affine_taps: taps must be contiguous (idx int64, g float32), at most 64 per point")
    P, t = idx.shape
    out = _out(out, P * C, (P, C))
    flag = lib.prt_affine_taps(P, n_out, C, *_codes(labels, W, wstride, woff, nk, nuse, mean), T.data_ptr(), T.shape[3],
                               t, idx.data_ptr(), g.data_ptr(), out.data_ptr(), _order(order, P), _csort(order, codes_sorted),
                               torch.get_num_threads())
    return out, int(flag)


def _strides_are(t: torch.Tensor, shape: tuple, step: int) -> bool:
    """``t``'s strides are those of a contiguous ``shape`` times ``step`` (size-1 axes ignored)."""
    want = step
    for size, stride in zip(reversed(shape), reversed(t.stride()[:len(shape)])):
        if size > 1 and stride != want:
            return False
        want *= size
    return True


def lobe_layout(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor) -> tuple:
    """``(w, mu, sigma, sw, sm, ss, fb)`` for the kernels: lobe m's parameters at ``w[sw·m]``,
    ``mu[sm·m + c]``, ``sigma[ss·m]``. Views of one record array ``rec [..., 5]`` = (w, μx, μy,
    μz, σ) (``rec[..., 0]``, ``rec[..., 1:4]``, ``rec[..., 4]``, as the Gaussian codec stores its
    lobes) are read in place, strides (5, 5, 5); anything else as contiguous float32 arrays,
    strides (1, 3, 1). ``fb``: 0 where the lobes are in the order of ``w [..., N]``'s elements
    (m = g·N + n for function g); ``V·N`` for ``w [V, J, N]`` viewing view-major records
    ``[J, V, N, 5]`` permuted (the Gaussian codec's ``lobes_by_view``): m = v·N + j·V·N + n."""
    if w.dtype == torch.float32 and mu.data_ptr() == w.data_ptr() + 4 and sigma.data_ptr() == w.data_ptr() + 16:
        st, step = [], 5  # the views rec[..., 0], rec[..., 1:4], rec[..., 4] of a contiguous rec [..., 5]: exact strides
        for d in reversed(w.shape):
            st.append(step)
            step *= d
        st = tuple(reversed(st))
        if w.ndim == 3:  # or of a view-major rec [J, V, N, 5] permuted to [V, J, N, 5]
            V, J, N = w.shape
            vm = (5 * N, 5 * V * N, 5)
            if (V > 1 and J > 1 and w.stride() == vm and sigma.stride() == vm and mu.stride() == (*vm, 1)
                    and mu.dtype == sigma.dtype == torch.float32 and mu.shape == (*w.shape, 3) and sigma.shape == w.shape):
                return w, mu, sigma, 5, 5, 5, V * N
        if (w.stride() == st and sigma.stride() == st and mu.stride() == (*st, 1) and mu.dtype == sigma.dtype == torch.float32
                and mu.shape == (*w.shape, 3) and sigma.shape == w.shape):
            return w, mu, sigma, 5, 5, 5, 0
    if tuple(mu.shape) != (*w.shape, 3) or tuple(sigma.shape) != tuple(w.shape):  # the kernels read w.numel() lobes of each
        raise ValueError(f"lobes: mu {tuple(mu.shape)} and sigma {tuple(sigma.shape)} do not match w {tuple(w.shape)}; "
                         f"accepted: mu {(*w.shape, 3)}, sigma {tuple(w.shape)}")
    shape = tuple(w.shape)
    if (all(t.dtype == torch.float32 for t in (w, mu, sigma)) and tuple(mu.shape) == (*shape, 3) and tuple(sigma.shape) == shape
            and mu.data_ptr() == w.data_ptr() + 4 and sigma.data_ptr() == w.data_ptr() + 16 and mu.stride(-1) == 1
            and _strides_are(w, shape, 5) and _strides_are(sigma, shape, 5) and _strides_are(mu, shape, 5)):
        return w, mu, sigma, 5, 5, 5, 0
    return _as(w, torch.float32), _as(mu, torch.float32), _as(sigma, torch.float32), 1, 3, 1, 0


#: the quad table (``PrefilteredEnvironment.quads``) is read where a relight makes at least this many lookups per
#: table row (its build, 64 bytes a row, then costs under 2%) and it holds at most SG_QUADS_MAX_BYTES (beyond, its
#: lines fall out of the L2 that the table's 12 bytes a texel stay in)
SG_QUADS_MIN_LOOKUPS_PER_ROW = 16
SG_QUADS_MAX_BYTES = 8 << 20


def sg_quads_worth(rows: int, channels: int, res: int, lookups: int) -> bool:
    """Whether ``lookups`` lobe lookups in an RGB pyramid of ``rows`` texels (``L·6·r·r``) and
    resolution ``res`` should read its quad table (:func:`sg_lookup_sum`'s ``quads``)."""
    return (channels == 3 and res >= 2 and rows * 64 <= SG_QUADS_MAX_BYTES
            and lookups >= SG_QUADS_MIN_LOOKUPS_PER_ROW * rows)


def sg_lookup_sum(lib, table: torch.Tensor, log_sigmas: torch.Tensor, res: int, mu: torch.Tensor, sigma: torch.Tensor,
                  w: torch.Tensor, out: torch.Tensor | None = None, layout: tuple | None = None,
                  quads: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over the last axis of ``w [..., N]`` of w · E_σ(μ) (Green 2005 eq. 2.7) from a prefiltered
    pyramid ``table [L·6·r·r, C]`` float32 (``PrefilteredEnvironment.table``) with ladder
    ``log_sigmas [L]``: ``mu [..., N, 3]``, ``sigma [..., N]`` → ``[..., C]`` float32, one fused
    pass per lobe (the torch formulation builds ~30 lobe-sized intermediates). The three may be
    views of one record array ``[..., N, 5]``, or of view-major records ``[J, V, N, 5]`` permuted
    to ``[V, J, N, 5]`` (read in place, :func:`lobe_layout`; the latter a block of 16 vertices
    at a time, every view of each, its rows of the result staying in L1), or any tensors of
    those shapes (else ``ValueError``). ``out``: an optional contiguous float32 result
    ``[..., C]`` (checked by the caller), written and returned. ``layout``: ``lobe_layout(w, mu,
    sigma)`` where the caller keeps it (the Gaussian codec, per encoding: ~2 µs a call).
    ``quads``: ``PrefilteredEnvironment.quads()`` of this table ``[L·6·r·r, 16]`` float32, or
    None: with it, RGB lookups in blocks of 16 read one 64-byte line per level (the 2×2 texels)
    instead of four (the same products, summed in another order: float32 rounding); worth its
    build where :func:`sg_quads_worth`."""
    C = table.shape[1]
    if C > 16:
        raise ValueError(f"sg_lookup_sum: {C} channels; accepted: at most 16")
    lead, N, G, A, B, lay = _sg_args(w, mu, sigma, layout)
    w, mu, sigma, sw, sm, ss, fb = lay
    _pyramid("sg_lookup_sum", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    given = out
    out = _out(out, G * C, (G, C))
    q = _quads_ptr(quads, table)
    lib.prt_sg_lookup_sum_q(A, B, fb, N, mu.data_ptr(), sigma.data_ptr(), w.data_ptr(), sw, sm, ss, table.data_ptr(), q, int(res),
                            ladder.numel(), ladder.data_ptr(), C, out.data_ptr(), torch.get_num_threads())
    return given if given is not None else out.reshape(*lead, C)


def _quads_ptr(quads: torch.Tensor | None, table: torch.Tensor) -> int | None:
    """The address of a quad table of ``table`` for the kernels (None: read the table itself)."""
    if quads is None:
        return None
    if quads.dtype != torch.float32 or not quads.is_contiguous() or quads.shape != (table.shape[0], 16) or table.shape[1] != 3 \
            or quads.device.type != "cpu":
        raise ValueError(f"quads: {quads.dtype} {tuple(quads.shape)} on {quads.device} for a table {tuple(table.shape)}; accepted: "
                         f"contiguous float32 [{table.shape[0]}, 16] on the CPU, of an RGB table (PrefilteredEnvironment.quads())")
    return quads.data_ptr()


def _sg_args(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, layout: tuple | None) -> tuple:
    """``(lead, N, G, A, B, layout)`` of lobes ``w [..., N]``: G functions, which the kernels take
    as A × B (view-major records: A vertices in blocks of 16, every one of the B views of each; else
    G × 1), and the lobes' :func:`lobe_layout`."""
    lead, N = tuple(w.shape[:-1]), w.shape[-1]
    G = w.numel() // max(N, 1)
    lay = layout or lobe_layout(w, mu, sigma)
    A, B = (lay[0].shape[0], lay[0].shape[1]) if lay[6] else (G, 1)
    return lead, N, G, A, B, lay


def sg_prepare(lib, log_sigmas: torch.Tensor, res: int, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
               layout: tuple | None = None) -> torch.Tensor | None:
    """The addressing of every lobe in the pyramid of resolution ``res`` and width ladder
    ``log_sigmas`` (face, texel, level and their fractions: ``prt_sg_prepare``, the part of a
    lookup that does not depend on the light's values), for :func:`sg_lookup_prepared`:
    ``int32 [⌊A/16⌋·B·N·80]`` (20 bytes per lobe), or None where the 16-lane kernels do not take
    this shape (no AVX-512, sizes past their int32 indices, a pyramid of one texel per side or
    one width: relight as usual)."""
    _, N, _, A, B, (w, mu, sigma, sw, sm, ss, fb) = _sg_args(w, mu, sigma, layout)
    ladder = _as(log_sigmas, torch.float32)
    P = torch.empty((A // 16) * B * N * 80, dtype=torch.int32)
    if lib.prt_sg_prepare(A, B, fb, N, mu.data_ptr(), sigma.data_ptr(), w.data_ptr(), sw, sm, ss, int(res), ladder.numel(),
                          ladder.data_ptr(), P.data_ptr(), torch.get_num_threads()):
        return None
    return P


def sg_lookup_prepared(lib, prepared: torch.Tensor, table: torch.Tensor, log_sigmas: torch.Tensor, res: int, w: torch.Tensor,
                       mu: torch.Tensor, sigma: torch.Tensor, out: torch.Tensor | None = None,
                       layout: tuple | None = None, quads: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`sg_lookup_sum` of RGB lights (``table [L·6·r·r, 3]``) from :func:`sg_prepare`'s
    addressing of these lobes for this ``res`` and ``log_sigmas`` (the caller keeps it valid: the
    same lobes, unchanged): per lobe only the 8 texel reads, the tail of fewer than 16 functions
    from the records. The same bits as :func:`sg_lookup_sum` with the same ``quads``."""
    lead, N, G, A, B, (w, mu, sigma, sw, sm, ss, fb) = _sg_args(w, mu, sigma, layout)
    if table.shape[1] != 3 or prepared.numel() != (A // 16) * B * N * 80:
        raise ValueError(f"sg_lookup_prepared: table {tuple(table.shape)}, prepared {prepared.numel()} values; accepted: "
                         f"[rows, 3] and {(A // 16) * B * N * 80} (sg_prepare of these lobes)")
    _pyramid("sg_lookup_prepared", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    given = out
    out = _out(out, G * 3, (G, 3))
    if lib.prt_sg_lookup_prepared(A, B, fb, N, mu.data_ptr(), sigma.data_ptr(), w.data_ptr(), sw, sm, ss, prepared.data_ptr(),
                                  table.data_ptr(), _quads_ptr(quads, table), int(res), ladder.numel(), ladder.data_ptr(),
                                  out.data_ptr(), torch.get_num_threads()):
        raise RuntimeError("prt_sg_lookup_prepared refused a shape sg_prepare took")  # pragma: no cover
    return given if given is not None else out.reshape(*lead, 3)


def sg_taps(lib, table: torch.Tensor, log_sigmas: torch.Tensor, res: int, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
            idx: torch.Tensor, a: torch.Tensor, out: torch.Tensor | None = None, layout: tuple | None = None) -> torch.Tensor:
    """Gaussian relighting with view taps (Green 2005 §2.3, eq. 2.7), fused per vertex: the lobes
    of the tapped views blended with ``a / Σa`` (``gaussian.blend_lobes``), looked up in the
    pyramid (as :func:`sg_lookup_sum`), summed over the lobes and scaled by Σa. ``w [V, J, N]``,
    ``mu [V, J, N, 3]``, ``sigma [V, J, N]`` (views of the codec's records are read in place,
    :func:`lobe_layout`: view-major ``lobes_by_view [J, V, N, 5]``, where a camera's taps, a few
    views shared by neighbouring vertices, read a few runs along the vertices; or vertex-major
    ``lobes [V, J, N, 5]``, three runs of 20·N bytes per vertex), ``idx int64 [V, k]``,
    ``a [V, k]`` → ``([V, C]`` float32 (into ``out`` when given, checked by the caller), flag``):
    flag 1, with nothing computed or written, when a tap has an index outside [0, J) or a
    negative or non-finite weight (one pass over the taps in the kernel, where torch's checks
    took four; the caller raises naming it). ``layout``: as for :func:`sg_lookup_sum`."""
    C = table.shape[1]
    if C > 16:
        raise ValueError(f"sg_taps: {C} channels; accepted: at most 16")
    args, _held = _taps_args(w, mu, sigma, idx, a, layout)
    _pyramid("sg_taps", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    out = _out(out, args[0] * C, (args[0], C))
    flag = lib.prt_sg_taps(*args, table.data_ptr(), int(res), ladder.numel(), ladder.data_ptr(), C, out.data_ptr(),
                           torch.get_num_threads())
    return out, int(flag)


def _taps_args(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, idx: torch.Tensor, a: torch.Tensor, layout: tuple | None):
    """``prt_sg_taps*``'s shape and lobe arguments ``[V, J, N, k, fv, fj, w, mu, sigma, sw, sm, ss, idx, a]``
    (pointers for the tensors) and the tensors they point into (kept alive by the caller)."""
    V, J, N = w.shape
    k = idx.shape[1]
    w, mu, sigma, sw, sm, ss, fb = layout or lobe_layout(w, mu, sigma)
    fv, fj = (N, fb) if fb else (J * N, N)  # lobe index of (v, j, 0): view-major records, else in order
    a, idx = _as(a, torch.float32), _as(idx, torch.int64)
    held = (w, mu, sigma, idx, a)
    return [V, J, N, k, fv, fj, w.data_ptr(), mu.data_ptr(), sigma.data_ptr(), sw, sm, ss, idx.data_ptr(), a.data_ptr()], held


def sg_taps_prepare(lib, log_sigmas: torch.Tensor, res: int, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
                    idx: torch.Tensor, a: torch.Tensor, layout: tuple | None = None) -> tuple:
    """The part of :func:`sg_taps` that does not depend on the light's values, for
    :func:`sg_taps_prepared`: each whole block of 16 vertices' lobes blended across the taps
    (``prt_sg_taps_prepare``), normalised and addressed in the pyramid of resolution ``res`` and
    width ladder ``log_sigmas`` (face, texel, level and their fractions, as :func:`sg_prepare`).
    Arguments as :func:`sg_taps`. → ``(prepared, flag)``: prepared = ``(P int32 [⌊V/16⌋·N·80],
    tot float32 [⌊V/16⌋·16], the kernels' lobe and taps arguments, the tensors they point into)``,
    20 bytes per blended lobe and Σa per vertex; ``(None, 0)`` where the 16-lane kernels do not
    take this shape (no AVX-512, sizes past their int32 indices, more than 8 taps, a pyramid of
    one texel per side or one width); ``(None, 1)`` with a bad tap (as :func:`sg_taps`' flag)."""
    args, held = _taps_args(w, mu, sigma, idx, a, layout)
    V, N = args[0], args[2]
    ladder = _as(log_sigmas, torch.float32)
    P = torch.empty((V // 16) * N * 80, dtype=torch.int32)
    tot = torch.empty((V // 16) * 16, dtype=torch.float32)
    flag = lib.prt_sg_taps_prepare(*args, int(res), ladder.numel(), ladder.data_ptr(), P.data_ptr(), tot.data_ptr(),
                                   torch.get_num_threads())
    if flag == 2:
        return None, 0
    return (None, 1) if flag else ((P, tot, tuple(args), held), 0)


def sg_taps_prepared(lib, prepared: tuple, table: torch.Tensor, log_sigmas: torch.Tensor, res: int,
                     out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """:func:`sg_taps` of RGB lights (``table [L·6·r·r, 3]``) from :func:`sg_taps_prepare`'s
    blend and addressing of its lobes and taps for this ``res`` and ``log_sigmas`` (the caller
    keeps it valid: the same lobes and taps, unchanged, and the same ``res`` and ladder): per
    blended lobe only the 8 texel reads, the tail of fewer than 16 vertices from the records and
    taps. The same bits as :func:`sg_taps`. → ``([V, 3]`` float32, flag``)``: flag 1, nothing
    written, when a tap of the tail (the only taps read) is bad."""
    out, call = sg_taps_prepared_call(prepared, table, log_sigmas, res, out)
    flag = lib.prt_sg_taps_prepared(*call, torch.get_num_threads())
    if flag == 2:
        raise RuntimeError("prt_sg_taps_prepared refused a shape sg_taps_prepare took")  # pragma: no cover
    return out, int(flag)


def sg_taps_prepared_call(prepared: tuple, table: torch.Tensor, log_sigmas: torch.Tensor, res: int,
                          out: torch.Tensor | None = None) -> tuple[torch.Tensor, tuple]:
    """:func:`sg_taps_prepared`'s checks, then ``(out, the arguments of prt_sg_taps_prepared but
    the thread count)``: what a caller that keeps ``prepared``, the pyramid and ``out`` unchanged
    (``GaussianRelighter``'s fast path) may pass again without the checks."""
    P, tot, args, _held = prepared
    V, N = args[0], args[2]
    if (table.shape[1] != 3 or P.numel() != (V // 16) * N * 80 or tot.numel() != (V // 16) * 16 or P.dtype != torch.int32
            or tot.dtype != torch.float32 or not (P.is_contiguous() and tot.is_contiguous())):
        raise ValueError(f"sg_taps_prepared: table {tuple(table.shape)}, prepared {P.numel()} and {tot.numel()} values; accepted: "
                         f"[rows, 3], {(V // 16) * N * 80} int32 and {(V // 16) * 16} float32 (sg_taps_prepare of these lobes and taps)")
    _pyramid("sg_taps_prepared", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    out = _out(out, V * 3, (V, 3))
    return out, (*args, P.data_ptr(), tot.data_ptr(), table.data_ptr(), int(res), ladder.numel(), ladder.data_ptr(), out.data_ptr())


def fits(J: int, n_out: int, C: int) -> bool:
    """Whether the kernels' per-point buffers hold these sizes (else the torch path is used)."""
    return C <= 16 and max(_pad8(n_out * C), C * _pad8(n_out), C * _pad8(J)) <= MAX_ROW  # taps with J = 1: C floats
