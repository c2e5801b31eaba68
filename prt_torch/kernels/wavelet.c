/* wavelet.c: all-frequency relighting, sparse Haar light x sparse Haar transfer (library "wavelet",
 * called by prt_torch/relight.py, WaveletRelighter; Ng, Ramamoorthi & Hanrahan 2003 eq. 2 and §6).
 *
 * The transfer is a CSC matrix over the 6R^2 Haar coefficients of the cube: column j holds the
 * vertices whose kept coefficients include j, as (rows int32 [E], vals [E]) between colptr[j] and
 * colptr[j+1] (rows ascending, each vertex at most once per column). A light is its N kept terms:
 * indices sel int64 [N] and values lv float32 [N, C]. Exit radiance, with a per-vertex factor
 * f [V, C] (the quantisation scale times the albedo) applied once at the end, since every value of
 * a vertex shares its scale:
 *     out[v, c] = f[v, c] * sum_n sum_{e in column sel[n], rows[e] = v} vals[e] * lv[n, c]
 * Only the columns of the light's N terms are read: the work is sum_n nnz(column sel[n]).
 * vals are float32, int8 or int16 (the stored quantised values, Ng §6).
 *
 * Layout of the work: for C <= 4 the sums live in a scratch acc [V, 4] (16-byte rows), so one
 * entry is one 4-float load, one multiply-add and one store (a grey transfer times an RGB light);
 * entries are taken four at a time (distinct rows within a column: independent updates). The
 * scratch is the caller's, zeroed here; out [V, C] is written once at the end. One thread. */

#include <stdint.h>
#include <string.h>
typedef int64_t i64;
typedef float v4f __attribute__((vector_size(16)));

#define WAVELET_KERNEL(NAME, T)                                                                          \
int NAME(i64 N, const i64 *sel, const float *lv, i64 C, const i64 *colptr, const int32_t *rows,           \
         const T *vals, i64 V, const float *f, float *out, float *acc) {                                  \
    if (C > 4) return 1;                                                                                \
    memset(acc, 0, (size_t)(V * 4) * sizeof(float));                                                    \
    v4f *a = (v4f *)acc;                                                                                \
    for (i64 n = 0; n < N; n++) {                                                                       \
        const i64 j = sel[n];                                                                           \
        v4f l = {0.0f, 0.0f, 0.0f, 0.0f};                                                               \
        for (i64 c = 0; c < C; c++) l[c] = lv[C * n + c];                                               \
        i64 e = colptr[j];                                                                              \
        const i64 e1 = colptr[j + 1];                                                                   \
        for (; e + 4 <= e1; e += 4) {                                                                   \
            const int32_t r0 = rows[e], r1 = rows[e + 1], r2 = rows[e + 2], r3 = rows[e + 3];          \
            const float w0 = (float)vals[e], w1 = (float)vals[e + 1];                                   \
            const float w2 = (float)vals[e + 2], w3 = (float)vals[e + 3];                               \
            v4f x0 = a[r0], x1 = a[r1], x2 = a[r2], x3 = a[r3];                                         \
            a[r0] = x0 + w0 * l; a[r1] = x1 + w1 * l; a[r2] = x2 + w2 * l; a[r3] = x3 + w3 * l;         \
        }                                                                                               \
        for (; e < e1; e++) a[rows[e]] += (float)vals[e] * l;                                           \
    }                                                                                                   \
    for (i64 v = 0; v < V; v++)                                                                         \
        for (i64 c = 0; c < C; c++) out[C * v + c] = acc[4 * v + c] * f[C * v + c];                     \
    return 0;                                                                                           \
}

WAVELET_KERNEL(prt_wavelet_relight_f32, float)
WAVELET_KERNEL(prt_wavelet_relight_i8, int8_t)
WAVELET_KERNEL(prt_wavelet_relight_i16, int16_t)
