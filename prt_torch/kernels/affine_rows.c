/* affine_rows.c: relighting without a view (Sloan 2003 §6): per point p of cluster k,
 *     e_p = T_k[0] + sum_{i<n_k} w_p^i T_k[1+i]          out [P, n_out C] float32
 * from the constants T [K, J, F] (affine_constants.c; rows padded from Fo = n_out C to F floats).
 *
 * Paths: VQ (mean only: a row copy per point), one-vector rows (diffuse RGB: 8 points in the lanes),
 * the general 8-lane pass (NB accumulators per chunk, two consecutive points of one cluster sharing
 * each load of T), and with AVX-512 the 16-lane pass for rows of >= ROWS16_MIN floats (MRT's 49 x 3).
 * Every path gives a point the same FMA chain, so its bits do not depend on pairing, order or
 * threads. */

#include "affine.h"

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
#if defined(SHUF) && defined(__AVX2__) && defined(__FMA__)
/* the first m weights of a point's 8 (the rest read as 0, never touched in memory): AVX-512VL's masked load, or AVX's
   vmaskmovps with the mask as a vector of sign bits */
static inline __m256 load_first(const float *p, i64 m) {
#if defined(__AVX512VL__)
    return _mm256_maskz_loadu_ps((__mmask8)((1u << m) - 1u), p);
#else
    if (m == 8) return _mm256_loadu_ps(p);
    return _mm256_maskload_ps(p, _mm256_cmpgt_epi32(_mm256_set1_epi32((int)m), _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7)));
#endif
}
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
        v8 r[8];
        for (int j = 0; j < 8; j++) r[j] = (v8)load_first(wq + j * ws + i0, m);
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
/* the same 8 points as one 16-byte copy each (the row's 3 floats and a padding lane), in ascending order: each
   store's 4th float is the next point's first, overwritten by that point's store, so the 8th point's store ends
   inside the range only where a 9th point follows (the caller's q + 9 <= p1). A load and a store per point,
   no shuffles: the packed form above spends 8 inserts and 3 two-source permutes per 8 points (ab_kernels --shape
   diffuse --only vq, 1 thread: 1.11-1.12x, maxdiff 0; labels read a byte each or 8 at a time: the same). */
#define VQ_RGB16_U8 {                                                                                             \
        const uint8_t *l_ = (const uint8_t *)lab + q;                                                             \
        float *d_ = out + 3 * q;                                                                                  \
        for (int i_ = 0; i_ < 8; i_++) *(v4u *)(d_ + 3 * i_) = *(const v4u *)(T + (i64)l_[i_] * 8);               \
    }
#if defined(__SSE4_1__)
#include <smmintrin.h>
/* 4 VQ points, RGB, uint8 labels l4 (the low 4 bytes), rows 8 floats apart (J = 1), as 12 contiguous floats in three
   16-byte stores (d: the first point's output): a0 a1 a2 b0 | b1 b2 c0 c1 | c2 e0 e1 e2, each a row's first 4 floats
   combined by one insertps, one shufps, and a byte shift + insertps. Zen 3 (AVX2 build) stores one vector per cycle
   here, 16 or 32 bytes alike, so the store count bounds the loop: 6 stores per 8 points where VQ_RGB16_U8 issues 8
   (a quarter of them crossing a cache line). Measured (C microbenchmark, 50 000 points, one thread, CPU time, load
   3-4): 21.3 -> 16.8-17.4 us (bound: a 50 kB copy + a 600 kB fill, 9.8-11.3 us); 32-byte stores (three per 8 points)
   cost more in shuffles than they save (17.3-20.8 us), gathers 68 us, 32-byte loads of pre-rotated rows 16-22 us.
   No arithmetic: the output bits are the constants' bits. */
static inline __attribute__((always_inline)) void vq_rgb4(const float *T, uint64_t l4, float *d) {
    const __m128 a = _mm_loadu_ps(T + (i64)(l4 & 255) * 8), b = _mm_loadu_ps(T + (i64)((l4 >> 8) & 255) * 8);
    const __m128 c = _mm_loadu_ps(T + (i64)((l4 >> 16) & 255) * 8), e = _mm_loadu_ps(T + (i64)((l4 >> 24) & 255) * 8);
    _mm_storeu_ps(d, _mm_insert_ps(a, b, 0x30));                                  /* b's lane 0 into lane 3 */
    _mm_storeu_ps(d + 4, _mm_shuffle_ps(b, c, _MM_SHUFFLE(1, 0, 2, 1)));          /* b1 b2 c0 c1 */
    _mm_storeu_ps(d + 8, _mm_insert_ps(_mm_castsi128_ps(_mm_slli_si128(_mm_castps_si128(e), 4)), c, 0x80));  /* c2 e0 e1 e2 */
}
/* 8 points from q: labels read 8 at a time */
#define VQ_RGB12_U8 {                                                                                             \
        uint64_t l8;                                                                                              \
        __builtin_memcpy(&l8, (const uint8_t *)lab + q, 8);                                                       \
        vq_rgb4(T, l8, out + 3 * q);                                                                              \
        vq_rgb4(T, l8 >> 32, out + 3 * q + 12);                                                                   \
    }
#endif
#endif
/* points q.. in order, n terms each after the mean, weights in rows of stride ws, the label kind fixed: each
   point by the one-point chain a = T_k[0] + sum_i w_i T_k[1+i] below (same FMAs, same operands, same bits),
   specialised so that neither the label kind, nor the weights' addressing, nor the term count is decided per point.
   Each group of 4 weights is one 16-byte load into both halves and each weight broadcast from it by an in-lane
   permute (vpermilps: either shuffle pipe, latency 1), the last n mod 4 by vbroadcastss, so no load reads past the
   point's n weights. Measured on Zen 3 (ab_kernels --shape diffuse --only cpca --clock cpu, CPCA 64x4, maxdiff 0):
   one load of 4/8 weights and a cross-lane vpermps per term (its permutes bounded the loop) -> vbroadcastss per term,
   1.30x; -> this, 1.19x more: the loop is bound by how many points are in flight, each waiting on its label, its
   constants' address and a chain of n multiply-adds, and fewer loads per point leave room for more points in the
   load queue. The loop stops at the caller's `last`, where a whole-vector store would end past the range. Returns
   where it stopped. */
#if defined(__AVX2__) && !defined(__AVX512F__)
/* whether rows_fixed (term count nuse) takes its 8-labels-per-load loop below (PRT_FIXED_U8_RGB, prt_kernels.h; 0: the
   one-point loop): the loop tests it, prt_plan_path reports it (only in these builds) */
int prt_fixed_rows_path(i64 Fo, int lab_kind, i64 wstride, i64 nuse, i64 J) {
#if defined(__FMA__)
    return lab_kind == 1 && Fo == 3 && wstride == nuse && J == nuse + 1 ? PRT_FIXED_U8_RGB : 0;
#else
    (void)Fo; (void)lab_kind; (void)wstride; (void)nuse; (void)J;
    return 0;
#endif
}
#endif
/* one point's chain: T_k[0] + sum_i w_i T_k[1+i] (t: T_k, w: its n weights) */
static inline __attribute__((always_inline)) v8 fixed_chain(const float *t, const float *w, const int n) {
    v8 a = LD(t);
#if defined(__AVX__) && defined(__FMA__)
    int i = 0;
    for (; i + 4 <= n; i += 4) {  /* 4 weights, one load into both halves; each broadcast by an in-lane permute */
        const __m256 w4 = _mm256_broadcast_ps((const __m128 *)(w + i));
        a = FMA8V((v8)_mm256_permute_ps(w4, 0x00), LD(t + 8 + 8 * i), a);
        a = FMA8V((v8)_mm256_permute_ps(w4, 0x55), LD(t + 16 + 8 * i), a);
        a = FMA8V((v8)_mm256_permute_ps(w4, 0xAA), LD(t + 24 + 8 * i), a);
        a = FMA8V((v8)_mm256_permute_ps(w4, 0xFF), LD(t + 32 + 8 * i), a);
    }
    for (; i < n; i++) a = FMA8(w[i], LD(t + 8 + 8 * i), a);
#else
    for (int i = 0; i < n; i++) a = FMA8(w[i], LD(t + 8 + 8 * i), a);
#endif
    return a;
}
static inline __attribute__((always_inline)) i64 rows_fixed(i64 q, i64 last, i64 Fo, const void *lab, const int lab_kind,
        const float *W, i64 ws, const int n, const float *T, i64 J, float *out) {
#if defined(__AVX2__) && defined(__FMA__) && !defined(__AVX512F__)
    /* AVX2 builds without AVX-512, uint8 labels, RGB rows, weights rows of the n terms: 8 labels per load and one
       16-byte store per point (its 4th float overwritten by the next point's, as the 32-byte store's 5 are), strides
       as constants. The loop is bound by its loads and stores: on Zen 3 (C microbenchmark, CPCA 64x4, 50 000 points,
       one thread, CPU time) its 7 loads and a 32-byte store per point took as long without the multiply-adds (1.31
       against 1.34 ns per point), and the multiply-adds without the constants' loads 1.12; this takes 7/8 of a load
       and 16 bytes of store per point off: 1.38 -> 1.25-1.27 ns (1.09-1.10x; the label loads alone 1.05x, the store
       alone 1.04x). Not kept: two points per vector (one in each half, their 4 weights one 32-byte load, rows
       blended or inserted: 0.95-0.99x, no fewer loads), pairs of points in one 32-byte store (0.94x), 4-lane
       arithmetic (1.00x). The same chain per point (fixed_chain), so the same bits. */
    if (prt_fixed_rows_path(Fo, lab_kind, ws, n, J))  /* RGB rows, weights rows of n, n terms: constant strides */
        for (; q + 7 <= last; q += 8) {
            uint64_t l8;
            __builtin_memcpy(&l8, (const uint8_t *)lab + q, 8);
            const float *w = W + q * n;
            float *o = out + q * 3;
            for (int l = 0; l < 8; l++)
                _mm_storeu_ps(o + 3 * l, _mm256_castps256_ps128((__m256)fixed_chain(T + (i64)((l8 >> (8 * l)) & 255) * (n + 1) * 8,
                                                                                   w + n * l, n)));
        }
#endif
    for (; q <= last; q++) {
        const v8 a = fixed_chain(T + lab_at(lab, lab_kind, q) * J * 8, W + q * ws, n);
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
/* the path prt_affine_rows_range takes for these shapes and codes (PRT_ROWS_*, prt_kernels.h): the dispatch below
   switches on it, and prt_plan_path reports it, so a benchmark row names the kernel it ran (not one guessed from the
   CPU's flags). Decided by the shapes and codes alone, never by the number of points. */
int prt_rows_path(i64 F, i64 Fo, i64 J, const void *lab, const float *W, const i64 *woff, const i64 *nk, i64 nuse, int mean,
                  const int32_t *order) {
    if (J == 1 && !W && mean && lab && !order && F == Fo) return PRT_ROWS_VQ_COPY;  /* J == 1: no weights can also be an
                                                                                     empty packed block with J > 1 */
    if (F == 8) {
#ifdef SHUF
        if (!W && !order && lab && mean && Fo == 3) return PRT_ROWS_SMALL_VQ_RGB8;
#endif
        if (!W && !order && lab && mean) return PRT_ROWS_SMALL_VQ;
        if (HAVE_K1_RGB8 && !lab && !order && !woff && W && Fo == 3) return PRT_ROWS_SMALL_K1_RGB8;
        if (!order && W && !woff && !nk && mean && nuse >= 1 && nuse <= 8) return PRT_ROWS_SMALL_FIXED;
        return PRT_ROWS_SMALL_ONE;
    }
    if (HAVE_W16 && W && F % 16 == 0 && F == prt_rows_pad(Fo, J)) return PRT_ROWS_W16;
    return W ? PRT_ROWS_W8_PAIRS : PRT_ROWS_W8;
}
static __attribute__((noinline)) void small_rows_range(int path, const int32_t *order, int csort, i64 p0, i64 p1, i64 Fo,
        const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, int mean,
        const float *T, i64 J, float *out) {
    i64 q = p0;
#ifdef SHUF
    if (path == PRT_ROWS_SMALL_VQ_RGB8) {  /* VQ, RGB: 8 points' rows packed into 24 floats (3 stores where one
                                                     store per point crosses a cache line every other point; 2x, bare C) */
        switch (lab_kind) {
        case 1:
#if !defined(__AVX512F__)
            /* AVX-512 builds keep VQ_RGB8_U8 (the Intel Xeon of reports/benchmarks/xeon_audit.md: ab_kernels --shape diffuse
               --only vq --clock cpu, one thread, maxdiff 0: VQ_RGB16_U8 0.83x [0.77, 0.87] of it; these two loops were
               measured faster on Zen 3, AVX2 only, and are unchanged there) */
#if defined(__SSE4_1__)
            if (J == 1)  /* rows 8 floats apart, as VQ_RGB12_U8 assumes; stores end at the 8th point's last float */
                for (; q + 8 <= p1; q += 8) VQ_RGB12_U8
#endif
            if (J == 1)  /* rows 8 floats apart, as VQ_RGB16_U8 / VQ_RGB8_U8 assume */
                for (; q + 9 <= p1; q += 8) VQ_RGB16_U8
#endif
            if (J == 1)
                for (; q + 8 <= p1; q += 8) VQ_RGB8_U8
            for (; q + 8 <= p1; q += 8) VQ_RGB8(uint8_t)
            break;
        case 2: for (; q + 8 <= p1; q += 8) VQ_RGB8(int16_t) break;
        default: for (; q + 8 <= p1; q += 8) VQ_RGB8(int32_t) break;
        }
    }
#endif
    if (path == PRT_ROWS_SMALL_VQ_RGB8 || path == PRT_ROWS_SMALL_VQ) {  /* VQ: the row of the point's cluster; whole vectors in order as above while
                                          they end inside the range, the rest below */
        switch (lab_kind) {
        case 1: for (; q * Fo + 8 <= p1 * Fo; q++) ST(out + q * Fo, LD(T + ((const uint8_t *)lab)[q] * J * 8)); break;
        case 2: for (; q * Fo + 8 <= p1 * Fo; q++) ST(out + q * Fo, LD(T + ((const int16_t *)lab)[q] * J * 8)); break;
        default: for (; q * Fo + 8 <= p1 * Fo; q++) ST(out + q * Fo, LD(T + ((const int32_t *)lab)[q] * J * 8)); break;
        }
    }
#if HAVE_K1_RGB8
    if (path == PRT_ROWS_SMALL_K1_RGB8) {
        i64 cnt;
        weights_of(W, wstride, woff, nk, nuse, 0, 0, &cnt);
        for (; q + 8 <= p1; q += 8) k1_rgb8(T, mean, W + q * wstride, wstride, cnt, out + 3 * q);
    }
#endif
    /* the rest (CPCA, other row lengths, a visiting order, the tails): one point at a time. The out-of-order core
       overlaps consecutive points' chains; an 8-point pass, with a pointer per point, spilled them (CPCA 1.5x slower).
       Consecutive rows with whole-vector stores while they end inside the range, then Fo floats per point. */
    if (path == PRT_ROWS_SMALL_FIXED) {  /* CPCA, PCA: fixed term count, rows of weights */
        /* the last point whose 8-float store ends within the range (computed here: inside rows_fixed the same bound
           made GCC's CPCA loop 1.7x slower); the weights read are the point's own nuse */
        q = fixed_rows(q, p1 - (8 + Fo - 1) / Fo, Fo, lab, lab_kind, W, wstride, nuse, T, J, out);
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
    const int path = prt_rows_path(F, Fo, J, lab, W, woff, nk, nuse, mean, order);
    if (path == PRT_ROWS_VQ_COPY) {
        vq_rows_range(p0, p1, F, lab, lab_kind, T, out);
        return 0;
    }
    if (F == 8) {
        small_rows_range(path, order, csort, p0, p1, Fo, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, J, out);
        return 0;
    }
#if HAVE_W16
    if (path == PRT_ROWS_W16) {
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

