/* affine.h: what the affine kernels (affine_constants.c, affine_rows.c, affine_dense.c,
 * affine_taps.c) share: reading a point's codes and the accumulation chains of the rows pass.
 *
 * Codes as AffineCodec stores them: labels [P] uint8/int16/int32 (lab_kind 1/2/3; none when K = 1),
 * weights [P, n_max] float32 (row stride n_max, the first n used) or packed (the n_k weights of
 * each point one after the other, woff int64 [P] where each starts, nk int64 [K]). Points may be
 * visited in cluster order and are then prefetched PF_AHEAD visits ahead.
 *
 * The chains compute, per point p of cluster k with weights w_p (Sloan 2003 §6, eq. (6)'s run-time
 * form): e_p = T_k[0] + sum_{i<n_k} w_p^i T_k[1+i], rows of F floats, in NB <= 12 named
 * accumulators per chunk (combine), or for two points of one cluster at once (combine2). */

#ifndef PRT_AFFINE_H
#define PRT_AFFINE_H
#include "vec.h"


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
#define ACC2_STEP(b) if (b < NB_) { v8 t_ = LD(Tb + 8 * b); IN_REG(t_); a##b += wi * t_; c##b += ui * t_; }
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

#endif /* PRT_AFFINE_H */
