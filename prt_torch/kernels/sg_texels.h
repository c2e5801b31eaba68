/* sg_texels.h: prefiltered cube-map lookups of Gaussian lobes (Green 2005 eq. 2.7:
 * E_sigma(mu) = the environment convolved with a normalised Gaussian of width sigma, read at mu),
 * the primitives of sg_lookup.c.
 *
 * The pyramid (lighting.prefilter.PrefilteredEnvironment): table [L 6 r r, C] float32, L levels of
 * six r x r faces in OpenGL order, ladder [L] = log sigma_l increasing. A lookup finds the face and
 * texel of mu, reads the four texels bilinearly (clamped at the face's edges) on the two bracketing
 * levels, and blends linearly in log sigma (clamped to the ladder). sg_lookup is the scalar form; with
 * AVX-512 (SG16) 16 lookups run at once: addressing (sg_address16), texel pairs or the quad table
 * (PrefilteredEnvironment.quads: the 2x2 texels from each texel on, one 64-byte row), and RGB
 * stores. The same float32 operations as the torch formulation, the sums in another order. */

#ifndef PRT_SG_TEXELS_H
#define PRT_SG_TEXELS_H
#include "prt_kernels.h"

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

#if defined(__AVX512F__) && defined(__AVX512VL__) && !defined(PRT_NO_W16)  /* PRT_NO_W16: vec.h */
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
#endif /* PRT_SG_TEXELS_H */
