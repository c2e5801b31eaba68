/* affine_taps.c: relighting with view taps (Lehtinen & Kautz 2003 eq. (13): the exit radiance at
 * a point is the tent-weighted sum of its few tapped rows):
 *     o_p[c] = sum_t g_pt e_p[idx_pt, c]                              out [P, C] float32
 * from the constants T [K, n_out, C, Jp] (J terms padded to Jp, a multiple of 8), taps idx int64
 * [P, t] and g float32 [P, t], t <= 64. A point's term weights [1 if mean, w_0 .. w_{n-1}, 0 ..]
 * are formed in registers (term_weights8) and dotted with each tapped row. Returns 1 when a tap
 * index is outside [0, n_out), 2 when an output is not finite. */

#include "affine.h"

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
/* one tap's row r (three colour rows Jp apart) times its weight gt into the NBJ x 3 accumulators */
#define TAP_ACC(NBJ, row, weight)                                                                \
    do {                                                                                         \
        const float *r = (row);                                                                  \
        float gt = (weight);                                                                     \
        for (int b = 0; b < NBJ; b++) {                                                          \
            a0[b] += gt * LD(r + 8 * b);                                                         \
            a1[b] += gt * LD(r + Jp + 8 * b);                                                    \
            a2[b] += gt * LD(r + 2 * Jp + 8 * b);                                                \
        }                                                                                        \
    } while (0)
#define TAPS3V(NBJ)                                                                              \
static inline void taps3v_##NBJ(const float *Tk, i64 R, i64 n_out, const i64 *ix, const float *gg, i64 ntap, i64 Jp, \
                                const float *wv, const float *w, i64 cnt, int mean, v8 *rv, int *flag) { \
    (void)w; (void)cnt; (void)mean;                                                              \
    v8 xw[NBJ];  /* the term weights, before the taps: the dot below then reads registers */     \
    for (int b = 0; b < NBJ; b++) xw[b] = TWV(b);                                                \
    v8 a0[NBJ], a1[NBJ], a2[NBJ];                                                                \
    for (int b = 0; b < NBJ; b++) { a0[b] = (v8){0}; a1[b] = (v8){0}; a2[b] = (v8){0}; }         \
    if (ntap == 4 && (uint64_t)ix[0] < (uint64_t)n_out && (uint64_t)ix[1] < (uint64_t)n_out      \
        && (uint64_t)ix[2] < (uint64_t)n_out && (uint64_t)ix[3] < (uint64_t)n_out) {               \
        /* four valid taps (MRT's bilinear tents): the loop below with its trip count known and no  \
           per-tap test, the same FMAs in the same order (same bits) */                           \
        for (int t = 0; t < 4; t++) {                                                            \
            TAP_ACC(NBJ, Tk + ix[t] * R, gg[t]);                                                 \
        }                                                                                        \
    } else                                                                                       \
    for (i64 t = 0; t < ntap; t++) {                                                             \
        i64 ri = ix[t];                                                                          \
        if ((uint64_t)ri >= (uint64_t)n_out) { *flag |= 1; continue; }  /* skipped, flagged */    \
        TAP_ACC(NBJ, Tk + ri * R, gg[t]);                                                        \
    }                                                                                            \
    v8 r0 = a0[0] * xw[0], r1 = a1[0] * xw[0], r2 = a2[0] * xw[0];                              \
    for (int b = 1; b < NBJ; b++) {                                                              \
        v8 x = xw[b];                                                                            \
        r0 += a0[b] * x; r1 += a1[b] * x; r2 += a2[b] * x;                                       \
    }                                                                                            \
    rv[0] = r0; rv[8] = r1; rv[16] = r2;                                                         \
}
TAPS3V(1) TAPS3V(2) TAPS3V(3) TAPS3V(4)
/* The RGB 8-point pass for points in order (no visiting order) with the terms' block count NBJ as a constant (AVX2
   builds without AVX-512): Jp = 8 NBJ and R = 3 Jp are then constants, so each tapped row's 3 NBJ vectors are
   addressed by immediate offsets from one pointer, where the general pass holds the runtime Jp's multiples in stack
   slots and reloads one per FMA; and the per-point bookkeeping of the general pass (the visiting order, the prefetches,
   the switch on Jp / 8, the weights' view) is decided once per range. Every point is taps3v_NBJ's: the same FMAs in
   the same order, so the same bits. PRT_SEQ_TAPS_EXACT: every point's term weights are its stored row (no mean, nuse = Jp, rows
   of weights, no per-cluster counts: MRT-PCA with 8, 16, 24 or 32 vectors), read by plain loads; else formed in
   registers (term_weights8); one cluster with four taps per point (MRT-PCA's tents) has a loop of its own, the tap
   count a constant (the four-valid-taps test then one branch) and no label to read. Measured on Zen 3 (C
   microbenchmark, MRT-PCA 16, 50 000 points of 7x7 tents, one thread, CPU time, bit-equal): the general pass 11.1-11.6
   ns per point; with Jp constant alone (in the general pass) 1.04x; this pass 8.6-8.9 ns (1.30-1.35x), with the
   one-cluster four-tap loop 7.5 ns (1.48x) - the same as a bare loop of the same FMAs without any checks (7.6 ns):
   about 22 cycles for 30 FMAs (24 for the taps, 6 for the dot) and 34 loads per point. Returns the flags; *qp: where
   it stopped (the last p1 - q < 8 points are the caller's). */
#if defined(__AVX2__) && !defined(__AVX512F__)
#define TAPS_SEQ(NBJ)                                                                            \
static __attribute__((noinline)) int taps_seq_##NBJ(int seq, i64 *qp, i64 p1, i64 n_out, const void *lab, int lab_kind, \
        const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 ntap,    \
        const i64 *idx, const float *g, float *out) {                                           \
    enum { Jp = 8 * NBJ, R = 3 * Jp };                                                           \
    v8 Rv[24];                                                                                   \
    int flag = 0;                                                                                \
    i64 q = *qp;                                                                                 \
    if (seq == PRT_SEQ_TAPS_K1_4)                                                                \
        for (; q + 8 <= p1; q += 8) {  /* one cluster, four taps (MRT-PCA): constants at T */     \
            for (int l = 0; l < 8; l++) {                                                        \
                const i64 p = q + l;                                                             \
                const float *w = W + p * wstride;                                                \
                taps3v_##NBJ(T, R, n_out, idx + 4 * p, g + 4 * p, 4, Jp, w, w, Jp, 0, Rv + l, &flag); \
            }                                                                                    \
            const i64 pl[8] = {q, q + 1, q + 2, q + 3, q + 4, q + 5, q + 6, q + 7};              \
            flag |= store8_rgb(Rv, out, pl, 1);                                                  \
        }                                                                                        \
    else if (seq == PRT_SEQ_TAPS_EXACT)                                                           \
        for (; q + 8 <= p1; q += 8) {                                                            \
            for (int l = 0; l < 8; l++) {                                                        \
                const i64 p = q + l;                                                             \
                const float *Tk = T + lab_at(lab, lab_kind, p) * n_out * R, *w = W + p * wstride;    \
                taps3v_##NBJ(Tk, R, n_out, idx + p * ntap, g + p * ntap, ntap, Jp, w, w, Jp, 0, Rv + l, &flag); \
            }                                                                                    \
            const i64 pl[8] = {q, q + 1, q + 2, q + 3, q + 4, q + 5, q + 6, q + 7};              \
            flag |= store8_rgb(Rv, out, pl, 1);                                                  \
        }                                                                                        \
    else                                                                                         \
        for (; q + 8 <= p1; q += 8) {                                                            \
            for (int l = 0; l < 8; l++) {                                                        \
                const i64 p = q + l;                                                             \
                i64 k = lab_at(lab, lab_kind, p), cnt;                                           \
                const float *w = weights_of(W, wstride, woff, nk, nuse, k, p, &cnt);             \
                taps3v_##NBJ(T + k * n_out * R, R, n_out, idx + p * ntap, g + p * ntap, ntap, Jp, NULL, w, cnt, mean, \
                             Rv + l, &flag);                                                     \
            }                                                                                    \
            const i64 pl[8] = {q, q + 1, q + 2, q + 3, q + 4, q + 5, q + 6, q + 7};              \
            flag |= store8_rgb(Rv, out, pl, 1);                                                  \
        }                                                                                        \
    *qp = q;                                                                                     \
    return flag;                                                                                 \
}
#define HAVE_TAPS_SEQ 1
/* which of taps_seq's loops prt_affine_taps_range runs for these shapes and codes (PRT_SEQ_TAPS_*, prt_kernels.h; 0:
   none, the general pass): the dispatch switches on it and prt_plan_path reports it (only in these builds) */
int prt_taps_seq_path(i64 C, i64 Jp, const void *lab, const float *W, const i64 *woff, const i64 *nk, i64 nuse, int mean, i64 ntap,
                      const int32_t *order) {
    if (order || C != 3 || Jp < 8 || Jp / 8 > 4) return 0;
    if (W && !woff && !nk && !mean && nuse == Jp) return !lab && ntap == 4 ? PRT_SEQ_TAPS_K1_4 : PRT_SEQ_TAPS_EXACT;
    return PRT_SEQ_TAPS;
}
#else
#define HAVE_TAPS_SEQ 0
#endif

/* one point: the three colours' sums into o */
#define TAPS3(NBJ)                                                                               \
static inline void taps3_##NBJ(const float *Tk, i64 R, i64 n_out, const i64 *ix, const float *gg, i64 ntap, i64 Jp,     \
                               const float *wv, const float *w, i64 cnt, int mean, float *o, int *flag) { \
    v8 rv[17];                                                                                   \
    taps3v_##NBJ(Tk, R, n_out, ix, gg, ntap, Jp, wv, w, cnt, mean, rv, flag);                    \
    o[0] = hsum(rv[0]); o[1] = hsum(rv[8]); o[2] = hsum(rv[16]);                                 \
}
TAPS3(1) TAPS3(2) TAPS3(3) TAPS3(4)
#if HAVE_TAPS_SEQ
TAPS_SEQ(1) TAPS_SEQ(2) TAPS_SEQ(3) TAPS_SEQ(4)
#endif

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

/* the path prt_affine_taps_range takes (PRT_TAPS_*, prt_kernels.h): one term (VQ), RGB with up to 32 terms (8 points
   reduced together), or the general loop; the dispatch below reads it, prt_plan_path reports it */
int prt_taps_path(i64 C, i64 Jp) {
    if (Jp == 1) return PRT_TAPS_ONE_TERM;
    return C == 3 && Jp / 8 <= 4 ? PRT_TAPS_RGB8 : PRT_TAPS_GENERAL;
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
    const int path = prt_taps_path(C, Jp);
    if (path == PRT_TAPS_ONE_TERM) {
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
    if (path == PRT_TAPS_RGB8) {
        /* RGB: 8 points at a time, their 24 dot products reduced together */
        v8 Rv[24];
        float wv[32];
        i64 pl[8];
#if HAVE_TAPS_SEQ
        const int seq = prt_taps_seq_path(C, Jp, lab, W, woff, nk, nuse, mean, ntap, order);
        if (seq) {
            switch (Jp / 8) {
            case 1: flag |= taps_seq_1(seq, &q, p1, n_out, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, ntap, idx, g, out); break;
            case 2: flag |= taps_seq_2(seq, &q, p1, n_out, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, ntap, idx, g, out); break;
            case 3: flag |= taps_seq_3(seq, &q, p1, n_out, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, ntap, idx, g, out); break;
            default: flag |= taps_seq_4(seq, &q, p1, n_out, lab, lab_kind, W, wstride, woff, nk, nuse, mean, T, ntap, idx, g, out); break;
            }
        }
#endif
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

