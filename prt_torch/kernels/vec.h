/* vec.h: the vector helpers of the affine kernels: 8-float vectors (v8, GCC/Clang vector
 * extensions: AVX where the CPU has it, SSE halves otherwise) and, with AVX-512, 16-float ones.
 *
 * Horizontal sums in one fixed association (hsum, hsum8: a point's bits do not depend on whether it
 * was reduced alone or in a block of 8, so not on the thread split), RGB interleave / 8x8 transpose
 * for storing 8 points' colours, FMA8 (a + w x with one rounding where the CPU has FMA, written
 * out rather than left to -ffp-contract), IN_REG (keep a loaded vector in a register), and the
 * 16-lane fold and lane masks (HAVE_W16). */
/* Only static inline functions return vectors here; the ABI note GCC gives without AVX
 * (-Wpsabi) is about calls across libraries, which these never are. */
#pragma GCC diagnostic ignored "-Wpsabi"

#ifndef PRT_VEC_H
#define PRT_VEC_H
#include "prt_kernels.h"
#if defined(__AVX__)
#include <immintrin.h>
#endif

/* 8 floats, unaligned loads/stores (GCC/Clang vector extensions; split into SSE where no AVX) */
typedef float v8 __attribute__((vector_size(32), aligned(4)));

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
/* lane i = the sum of a[i]'s lanes, for 8 vectors at once: three rounds of adding the even and odd lanes of
   neighbouring pairs (7 shuffle pairs for 8 sums, where 8 hsums take 24), each sum with the same operands in the
   same order as hsum's. The pairs are taken within 128-bit halves (vshufps) and the halves exchanged once at the
   end: round 1 leaves [a(01) a(23) b(01) b(23) | a(45) a(67) b(45) b(67)] per pair, round 2
   [a(0123) b(0123) c(0123) d(0123) | a(4567) ...], round 3 adds the halves, lane i = a_i(0123) + a_i(4567). Taking
   the even and odd lanes across the halves instead (a 16-lane pattern) made AVX2 code of vpermd from the stack:
   measured on Zen 3 (ab_kernels --shape relight --clock cpu, one thread, maxdiff 0) VQ with a dense view 1.60x
   faster this way, PCA 8 dense 1.20x, CPCA 256x8 dense 1.12x, MRT-PCA taps 1.24x. */
#define EVENL(a, b) __builtin_shufflevector(a, b, 0, 2, 8, 10, 4, 6, 12, 14)
#define ODDL(a, b) __builtin_shufflevector(a, b, 1, 3, 9, 11, 5, 7, 13, 15)
static inline v8 hsum8(const v8 *a) {
    v8 h01 = EVENL(a[0], a[1]) + ODDL(a[0], a[1]), h23 = EVENL(a[2], a[3]) + ODDL(a[2], a[3]);
    v8 h45 = EVENL(a[4], a[5]) + ODDL(a[4], a[5]), h67 = EVENL(a[6], a[7]) + ODDL(a[6], a[7]);
    v8 g0 = EVENL(h01, h23) + ODDL(h01, h23), g1 = EVENL(h45, h67) + ODDL(h45, h67);
    return __builtin_shufflevector(g0, g1, 0, 1, 2, 3, 8, 9, 10, 11) + __builtin_shufflevector(g0, g1, 4, 5, 6, 7, 12, 13, 14, 15);
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
#if defined(__AVX__)
    any = _mm256_movemask_ps((__m256)bad);  /* the lanes' sign bits (every lane is 0 or -1): one instruction */
#else
    for (int l = 0; l < 8; l++) any |= bad[l];
#endif
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

/* 16 floats per vector (AVX-512): the dense kernel's and the rows kernel's wide paths; off with PRT_NO_W16
   (PRT_TORCH_KERNEL_ISA=avx512-256: AVX-512VL's 32 registers and k-masks on 8-float vectors, no 512-bit kernels) */
#if defined(__AVX512F__) && !defined(PRT_NO_W16)
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
#endif /* PRT_VEC_H */
