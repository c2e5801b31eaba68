/* affine_constants.c: the per-cluster constants of a light (Sloan 2003 §6: M_i^k l, one
 * matrix-vector product per representative and cluster, once per light).
 *
 * In:  the model Mt, "column-major" [K, Jmax, n_in, n_pad] float32 (relight_kernels.model_t; J terms:
 *      the mean, if any, then the basis vectors), or for n_out = 1 with 8 clusters in the lanes (Mv);
 *      the light L [n_in, C] float32.
 * Out: T in the layout the point kernel reads (relight_kernels.constants_layout: rows and dense
 *      [K, J, C, n_pad] colour-major, taps [K, n_out, C, Jp]), element (k, j, o, c) at
 *      k sk + j sj + o so + c sc. Returns 1, computing nothing, when L holds a NaN or an infinity. */

#include "affine.h"

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

