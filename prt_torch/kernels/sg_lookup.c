/* sg_lookup.c: the Gaussian codec's relighting (Green 2005 eq. 2.7 and §2.3), fused per vertex.
 *
 *     out[g, c] = sum_{n<N} w_n E_{sigma_n}(mu_n)[c]          (prt_sg_lookup_sum, one view per vertex)
 * with view taps (§2.3): the lobes of a vertex's k tapped views blended with weights a_t / sum(a)
 * (weights and widths linearly, means as the normalised weighted sum), looked up and scaled by
 * sum(a) (prt_sg_taps). Lobe m's parameters at w[sw m], mu[sm m + c], sigma[ss m]: separate arrays or
 * the codec's records [..., 5] = (w, mu_x, mu_y, mu_z, sigma). The _prepare / _prepared pairs keep the
 * light-independent part (the addressing, the blend) per vertex, so a new light costs only the
 * texel reads. Lookups from sg_texels.h. */

#include "sg_texels.h"


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
    (void)totp;  /* read by the 16-lane path only */
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
