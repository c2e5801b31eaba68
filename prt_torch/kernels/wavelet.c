/* wavelet.c: all-frequency relighting, sparse Haar light x sparse Haar transfer (library "wavelet",
 * called by prt_torch/relight.py, WaveletRelighter; Ng, Ramamoorthi & Hanrahan 2003 eq. 2 and §6).
 *
 *     out[v, c] = f[v, c] * sum_n L[c, n] * T[v, sel[n]]
 *
 * over the light's N kept Haar terms (indices sel int64 [N], values lv float32 [C, N], C <= 4), with
 * T[v, j] the vertex's stored (quantised: int8 / int16, or float32) value of Haar coefficient j and
 * f [V, C] the per-vertex factor (the quantisation scale times the albedo) applied once at the end,
 * since every value of a vertex shares its scale.
 *
 * The transfer's columns (one per Haar coefficient j) are stored in one of two forms, chosen per
 * column when the relighter is built (whichever reads fewer bytes):
 *  - dense, for the columns most vertices keep (the coarse Haar levels: a vertex keeps every
 *    coarse coefficient of the faces above its horizon). dense [ceil(V/32), Pd, 32]: for each block
 *    of 32 vertices, the Pd dense columns' 32 values side by side (zeros where a vertex did not keep
 *    the coefficient), dslot[j] the column's slot (-1: sparse). A block keeps its sums in registers
 *    (C x 4 vectors of 8 floats) over every dense light term: one load and C multiply-adds per 8
 *    values, no index read, no scatter (a register-blocked GEMV).
 *  - sparse (CSC), the rest: column j holds (offs int32, vals) between colptr[j] and colptr[j+1],
 *    offs the byte offset 16 * row of the vertex's accumulator row, rows ascending (distinct), each column padded to a multiple of 4 entries with zero values on the
 *    dummy row V, scattered into acc [V + 1, 4] (16-byte rows). With AVX2 two entries of a column
 *    share one 8-lane multiply-add (in-lane shuffles), the portable path takes one 4-float row per
 *    entry.
 * Only the columns of the light's terms are read. The index check (0 <= sel < P) runs before any
 * work (returns 2); C outside 1..4 returns 1, N > P 3. One thread. Arguments: the layout (a struct, so
 * that a call passes seven arguments), the light and the output. */

#include <stdint.h>
#include <string.h>
/* Only static inline functions return vectors here; the ABI note GCC gives without AVX
 * (-Wpsabi) is about calls across libraries, which these never are (as in vec.h). */
#pragma GCC diagnostic ignored "-Wpsabi"
typedef int64_t i64;
typedef float v4f __attribute__((vector_size(16)));
typedef float v8f __attribute__((vector_size(32)));
typedef int16_t v8s __attribute__((vector_size(16)));
typedef int8_t v8b __attribute__((vector_size(8)));
#ifdef __AVX2__
#include <immintrin.h>
#endif
#define BV 32 /* vertices per dense block: C x 4 vectors of 8 sums */

#ifdef __AVX2__ /* one 8-lane widening load (gcc splits __builtin_convertvector of 16-bit lanes into halves) */
static inline v8f load8_i16(const int16_t *p) {
    return _mm256_cvtepi32_ps(_mm256_cvtepi16_epi32(_mm_loadu_si128((const __m128i *)p))); }
static inline v8f load8_i8(const int8_t *p) {
    return _mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(_mm_loadl_epi64((const __m128i *)p))); }
#else
static inline v8f load8_i16(const int16_t *p) { v8s x; memcpy(&x, p, sizeof x); return __builtin_convertvector(x, v8f); }
static inline v8f load8_i8(const int8_t *p) { v8b x; memcpy(&x, p, sizeof x); return __builtin_convertvector(x, v8f); }
#endif
static inline v8f load8_f32(const float *p) { v8f x; memcpy(&x, p, sizeof x); return x; }

/* one block of BV vertices over the nd dense terms; C a constant after inlining */
#define DENSE_BLOCK(T, LOAD)                                                                                 \
static inline __attribute__((always_inline)) void dense_block_##T(const int C, i64 nd, const i64 *ds,        \
        const float *lw, const T *blk, const float *acc, i64 nv, const float *f, float *out) {               \
    v8f a[4][4];                                                                                             \
    for (int c = 0; c < 4; c++) for (int k = 0; k < 4; k++) a[c][k] = (v8f){0};                             \
    for (i64 t = 0; t < nd; t++) {                                                                           \
        const T *p = blk + ds[t] * BV;                                                                       \
        const v8f x0 = LOAD(p), x1 = LOAD(p + 8), x2 = LOAD(p + 16), x3 = LOAD(p + 24);                      \
        for (int c = 0; c < C; c++) {                                                                        \
            const float l = lw[4 * t + c];                                                                   \
            a[c][0] += x0 * l; a[c][1] += x1 * l; a[c][2] += x2 * l; a[c][3] += x3 * l;                      \
        }                                                                                                    \
    }                                                                                                        \
    float sums[4 * BV] __attribute__((aligned(32)));                                                         \
    for (int c = 0; c < C; c++) for (int k = 0; k < 4; k++) memcpy(sums + c * BV + 8 * k, &a[c][k], 32);    \
    if (acc)                                                                                                 \
        for (i64 v = 0; v < nv; v++)                                                                         \
            for (int c = 0; c < C; c++) out[C * v + c] = (sums[c * BV + v] + acc[4 * v + c]) * f[C * v + c];  \
    else                                                                                                     \
        for (i64 v = 0; v < nv; v++)                                                                         \
            for (int c = 0; c < C; c++) out[C * v + c] = sums[c * BV + v] * f[C * v + c];                    \
}
DENSE_BLOCK(float, load8_f32)
DENSE_BLOCK(int8_t, load8_i8)
DENSE_BLOCK(int16_t, load8_i16)

#ifdef __AVX2__
static inline __m128 w4_float(const float *p) { return _mm_loadu_ps(p); }
static inline __m128 w4_int16_t(const int16_t *p) {
    return _mm_cvtepi32_ps(_mm_cvtepi16_epi32(_mm_loadl_epi64((const __m128i *)p))); }
static inline __m128 w4_int8_t(const int8_t *p) { int32_t x; memcpy(&x, p, 4);
    return _mm_cvtepi32_ps(_mm_cvtepi8_epi32(_mm_cvtsi32_si128(x))); }
#define PAIR(K, IMM) {                                                                                       \
    float *p0 = (float *)((char *)acc + offs[e + K]), *p1 = (float *)((char *)acc + offs[e + 2 + K]);        \
    __m256 x = _mm256_loadu2_m128(p1, p0);                                                                   \
    x = _mm256_fmadd_ps(_mm256_shuffle_ps(w, w, IMM), l2, x);                                                \
    _mm_store_ps(p0, _mm256_castps256_ps128(x)); _mm_store_ps(p1, _mm256_extractf128_ps(x, 1)); }
/* entries in groups of four (each column padded with zero values on the dummy row V): entries k and
 * k+2 share one 8-lane multiply-add, w = [w0 w1 w2 w3 | w2 w3 w0 w1] broadcast in-lane */
#define SCATTER(T)                                                                                           \
static void scatter_##T(i64 ns, const i64 *ss, const float *lw, const i64 *colptr, const int32_t *offs,      \
                        const T *vals, float *acc) {                                                         \
    for (i64 t = 0; t < ns; t++) {                                                                           \
        const __m128 l = _mm_loadu_ps(lw + 4 * t);                                                           \
        const __m256 l2 = _mm256_set_m128(l, l);                                                             \
        const i64 e1 = colptr[ss[t] + 1];                                                                    \
        for (i64 e = colptr[ss[t]]; e < e1; e += 4) {                                                        \
            const __m128 w4 = w4_##T(vals + e);                                                              \
            const __m256 w = _mm256_set_m128(_mm_shuffle_ps(w4, w4, 0x4E), w4);                              \
            PAIR(0, 0x00) PAIR(1, 0x55)                                                                      \
        }                                                                                                    \
    }                                                                                                        \
}
#else /* portable: one 16-byte row per entry */
#define SCATTER(T)                                                                                           \
static void scatter_##T(i64 ns, const i64 *ss, const float *lw, const i64 *colptr, const int32_t *offs,      \
                        const T *vals, float *acc) {                                                         \
    v4f *a = (v4f *)acc;                                                                                     \
    for (i64 t = 0; t < ns; t++) {                                                                           \
        v4f l; memcpy(&l, lw + 4 * t, sizeof l);                                                             \
        for (i64 e = colptr[ss[t]]; e < colptr[ss[t] + 1]; e++) a[offs[e] >> 4] += (float)vals[e] * l;            \
    }                                                                                                        \
}
#endif
SCATTER(float)
SCATTER(int8_t)
SCATTER(int16_t)

/* the transfer's layout and the scratch, built once per transfer (relight.py: an int64 tensor of
 * these eleven fields in this order; pointers as integers) */
typedef struct {
    i64 P, Pd, V;               /* Haar coefficients 6R^2, dense columns, vertices */
    const i64 *colptr;          /* [P+1] the sparse columns (dense ones empty) */
    const int32_t *offs;        /* [E] byte offsets 16 * row */
    const void *vals;           /* [E] stored values of the sparse columns */
    const i64 *dslot;           /* [P] the column's dense slot, or -1 */
    const void *dense;          /* [ceil(V/32), Pd, 32] stored values of the dense columns */
    float *acc;                 /* scratch [V + 1, 4] */
    i64 *wk;                    /* scratch [P] */
    float *lw;                  /* scratch [P, 4] */
    float *ld;                  /* scratch [Pd, 4]: the light of each dense slot */
    unsigned char *mk;          /* scratch [Pd]: the slot is one of the light's terms */
} wavelet_layout;

#define WAVELET_KERNEL(NAME, T)                                                                              \
int NAME(const wavelet_layout *L, i64 N, const i64 *sel, const float *lv, i64 C, const float *f, float *out) { \
    const i64 P = L->P, Pd = L->Pd, V = L->V;                                                                \
    const i64 *colptr = L->colptr, *dslot = L->dslot;                                                        \
    const int32_t *offs = L->offs;                                                                           \
    const T *vals = (const T *)L->vals, *dense = (const T *)L->dense;                                        \
    float *acc = L->acc, *lw = L->lw;                                                                        \
    i64 *wk = L->wk;                                                                                         \
    if (N > P) return 3;                                                                                     \
    if (C < 1 || C > 4) return 1;                                                                            \
    for (i64 n = 0; n < N; n++) if (sel[n] < 0 || sel[n] >= P) return 2;                                    \
    /* the dense terms in slot order (each block's values are then read front to back; a column listed twice    \
     * adds its light values), the sparse terms from the back of wk / lw */                                  \
    float *ld = L->ld;                                                                                       \
    unsigned char *mk = L->mk;                                                                               \
    memset(ld, 0, (size_t)(Pd * 4) * sizeof(float));                                                         \
    memset(mk, 0, (size_t)Pd);                                                                               \
    i64 ns = 0;                                                                                              \
    for (i64 n = 0; n < N; n++) {                                                                            \
        const i64 j = sel[n], s = dslot[j];                                                                  \
        if (s >= 0) {                                                                                        \
            mk[s] = 1;                                                                                       \
            for (int c = 0; c < C; c++) ld[4 * s + c] += lv[c * N + n];                                      \
        } else {                                                                                             \
            const i64 t = N - 1 - ns++;                                                                      \
            wk[t] = j;                                                                                       \
            for (int c = 0; c < 4; c++) lw[4 * t + c] = c < C ? lv[c * N + n] : 0.0f;                        \
        }                                                                                                    \
    }                                                                                                        \
    i64 nd = 0;                                                                                              \
    for (i64 s = 0; s < Pd; s++)                                                                             \
        if (mk[s]) {                                                                                         \
            wk[nd] = s;                                                                                      \
            for (int c = 0; c < 4; c++) lw[4 * nd + c] = ld[4 * s + c];                                      \
            nd++;                                                                                            \
        }                                                                                                    \
    if (ns) {                                                                                                \
        memset(acc, 0, (size_t)((V + 1) * 4) * sizeof(float));                                                     \
        scatter_##T(ns, wk + N - ns, lw + 4 * (N - ns), colptr, offs, vals, acc);                            \
    }                                                                                                        \
    const float *sa = ns ? acc : NULL;                                                                       \
    for (i64 v0 = 0; v0 < V; v0 += BV) {                                                                     \
        const T *blk = dense + v0 * Pd;                                                                      \
        const i64 nv = V - v0 < BV ? V - v0 : BV;                                                            \
        const float *a = sa ? sa + 4 * v0 : NULL, *fv = f + C * v0;                                          \
        float *o = out + C * v0;                                                                             \
        switch (C) {                                                                                         \
            case 1: dense_block_##T(1, nd, wk, lw, blk, a, nv, fv, o); break;                                \
            case 2: dense_block_##T(2, nd, wk, lw, blk, a, nv, fv, o); break;                                \
            case 3: dense_block_##T(3, nd, wk, lw, blk, a, nv, fv, o); break;                                \
            default: dense_block_##T(4, nd, wk, lw, blk, a, nv, fv, o); break;                               \
        }                                                                                                    \
    }                                                                                                        \
    return 0;                                                                                                \
}

WAVELET_KERNEL(prt_wavelet_relight_f32, float)
WAVELET_KERNEL(prt_wavelet_relight_i8, int8_t)
WAVELET_KERNEL(prt_wavelet_relight_i16, int16_t)
