/* affine_dense.c: relighting with a dense view (Sloan 2003 §3.1, exit radiance o_p = y_p . e_p):
 *     o_p[c] = sum_r y_pr (T_k[0] + sum_i w_p^i T_k[1+i])[c, r]        out [P, C] float32
 * from the constants T [K, J, C, n_pad] (colour-major, rows padded from n_out to n_pad: prt_dense_pad)
 * and the view y [P, n_out] float32, folded in per point so no [P, n_out, C] intermediate exists:
 * J n_out C multiply-adds per point.
 *
 * Paths: DENSE1/DENSE3 (8 rows a vector, one or three colours), two points of one cluster per
 * load of T (dense3v2), and with AVX-512 16 rows a vector for 25-64 rows (MRT's 7x7 tents), with the
 * rows past the whole blocks from a per-call table (dense_tail_table [K, 3, rt, 16]). Returns 2 when
 * an output is not finite. */

#include "affine.h"

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
DENSE3V(1) DENSE3V(2) DENSE3V(3) DENSE3V(4) DENSE3V(5) DENSE3V(6)
#if defined(__AVX512VL__)  /* 32 vector registers hold the 3 NBS accumulators */
DENSE3V(7)
#else
/* dense3v for 7 vectors per colour (MRT's 7x7 tents: n_out 49) with 16 vector registers, which its 21
   accumulators overflow (spilled, each multiply-add also a load and a store of its accumulator): the vectors
   in groups of at most 4 (7 = 4 + 3), each group's accumulators summed over the terms in registers, then their terms
   of the dot added to r0..r2 in vector order (5 and 6 vectors, not measured, keep dense3v). Every accumulator and every dot term is dense3v's, formed by the same
   operations in the same order: the same bits. Measured on Zen 3 (AVX2 build, ab_kernels --only mrt --clock cpu, one
   thread, maxdiff 0): MRT-PCA 16 with a dense view 1.375x [1.363, 1.380]; groups of at most 3 (7 = 3 + 2 + 2) 0.89x:
   a group of 2 has 6 chains of J multiply-adds, too few to cover the FMA latency. */
static inline __attribute__((always_inline)) void dense3_group(const int GB, const int first, const float *T0, i64 n_pad, i64 F,
        int mean, const float *w, i64 cnt, const float *yc, v8 *r0, v8 *r1, v8 *r2) {
    const float *T1 = T0 + n_pad, *T2 = T0 + 2 * n_pad;
    v8 a0[4], a1[4], a2[4];
    for (int b = 0; b < GB; b++) {
        a0[b] = mean ? LD(T0 + 8 * b) : (v8){0};
        a1[b] = mean ? LD(T1 + 8 * b) : (v8){0};
        a2[b] = mean ? LD(T2 + 8 * b) : (v8){0};
    }
    i64 s = mean ? F : 0;
    for (i64 i = 0; i < cnt; i++, s += F) {
        float wi = w[i];
        for (int b = 0; b < GB; b++) {
            a0[b] += wi * LD(T0 + s + 8 * b);
            a1[b] += wi * LD(T1 + s + 8 * b);
            a2[b] += wi * LD(T2 + s + 8 * b);
        }
    }
    for (int b = 0; b < GB; b++) {
        v8 yb = LD(yc + 8 * b);
        IN_REG(yb);
        if (first && b == 0) {
            *r0 = a0[0] * yb; *r1 = a1[0] * yb; *r2 = a2[0] * yb;
        } else {
            *r0 += a0[b] * yb; *r1 += a1[b] * yb; *r2 += a2[b] * yb;
        }
    }
}
#define DENSE3VG(NBS, G1, G2, G3)                                                                \
static inline void dense3v_##NBS(const float *T0, i64 n_pad, i64 F, int mean, const float *w, i64 cnt, \
                                 const float *yc, v8 *rv) {                                      \
    v8 r0, r1, r2;                                                                               \
    dense3_group(G1, 1, T0, n_pad, F, mean, w, cnt, yc, &r0, &r1, &r2);                          \
    dense3_group(G2, 0, T0 + 8 * (G1), n_pad, F, mean, w, cnt, yc + 8 * (G1), &r0, &r1, &r2);     \
    if (G3) dense3_group(G3, 0, T0 + 8 * ((G1) + (G2)), n_pad, F, mean, w, cnt, yc + 8 * ((G1) + (G2)), &r0, &r1, &r2); \
    rv[0] = r0; rv[8] = r1; rv[16] = r2;                                                         \
}
DENSE3VG(7, 4, 3, 0)
#endif
/* 6 NBS accumulators + 3 T vectors + 2 weights in the vector registers: 32 with AVX-512VL, else 16 */
#if defined(__AVX512VL__)
#define MAXNBS2 3
#define PAIRS_NBT(nbt) 1
DENSE3V2(1) DENSE3V2(2) DENSE3V2(3)
#else
/* AVX2 (16 vector registers), 3 vectors per colour (n_out 17..24: CPCA 256x8 of 24x25 glossy transfer): dense3v2_3's 18
   accumulators overflow them, so the two points of one cluster run as groups of vectors per colour, blocks 0-1 (12
   accumulators, one T vector in a register at a time, 2 weights: 15 registers) then block 2 (6), each accumulator the
   same chain of multiply-adds over the terms and the dot terms added in vector order: dense3v's sums, the same bits. */
static inline __attribute__((always_inline)) void dense3v2_group(const int GB, const int first, const float *T0, i64 n_pad,
        i64 F, int mean, const float *w, const float *u, i64 cnt, const float *yc, const float *zc, v8 *r0, v8 *r1, v8 *r2,
        v8 *q0, v8 *q1, v8 *q2) {
    const float *T1 = T0 + n_pad, *T2 = T0 + 2 * n_pad;
    v8 a0[2], a1[2], a2[2], c0[2], c1[2], c2[2];
    for (int b = 0; b < GB; b++) {
        a0[b] = c0[b] = mean ? LD(T0 + 8 * b) : (v8){0};
        a1[b] = c1[b] = mean ? LD(T1 + 8 * b) : (v8){0};
        a2[b] = c2[b] = mean ? LD(T2 + 8 * b) : (v8){0};
    }
    i64 s = mean ? F : 0;
    for (i64 i = 0; i < cnt; i++, s += F) {
        float wi = w[i], ui = u[i];
        for (int b = 0; b < GB; b++) {
            v8 t0 = LD(T0 + s + 8 * b);
            IN_REG(t0);
            a0[b] += wi * t0; c0[b] += ui * t0;
            v8 t1 = LD(T1 + s + 8 * b);
            IN_REG(t1);
            a1[b] += wi * t1; c1[b] += ui * t1;
            v8 t2 = LD(T2 + s + 8 * b);
            IN_REG(t2);
            a2[b] += wi * t2; c2[b] += ui * t2;
        }
    }
    for (int b = 0; b < GB; b++) {
        v8 yb = LD(yc + 8 * b), zb = LD(zc + 8 * b);
        IN_REG(yb); IN_REG(zb);
        if (first && b == 0) {
            *r0 = a0[0] * yb; *r1 = a1[0] * yb; *r2 = a2[0] * yb;
            *q0 = c0[0] * zb; *q1 = c1[0] * zb; *q2 = c2[0] * zb;
        } else {
            *r0 += a0[b] * yb; *r1 += a1[b] * yb; *r2 += a2[b] * yb;
            *q0 += c0[b] * zb; *q1 += c1[b] * zb; *q2 += c2[b] * zb;
        }
    }
}
static inline void dense3v2_3(const float *T0, i64 n_pad, i64 F, int mean, const float *w, const float *u, i64 cnt,
                              const float *yc, const float *zc, v8 *rv) {
    v8 r0, r1, r2, q0, q1, q2;
    dense3v2_group(2, 1, T0, n_pad, F, mean, w, u, cnt, yc, zc, &r0, &r1, &r2, &q0, &q1, &q2);
    dense3v2_group(1, 0, T0 + 16, n_pad, F, mean, w, u, cnt, yc + 16, zc + 16, &r0, &r1, &r2, &q0, &q1, &q2);
    rv[0] = r0; rv[8] = r1; rv[16] = r2; rv[1] = q0; rv[9] = q1; rv[17] = q2;
}
#define MAXNBS2 3
DENSE3V2(1)
#define PAIRS_NBT(nbt) ((nbt) != 2)  /* no dense3v2_2 here */
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
        /* -0.0f, not 0.0f: a pad row's product (a constant's +0 pad times this) is then -0, the additive identity
           (x + -0 = x for every x, -0 included), where +0 turned a point's -0 sum into +0 (MRT's 49 rows padded to
           56 on the 8-lane path); every other sum keeps its bits */
        for (i64 r = n_out; r < n_pad; r++) yb[r] = -0.0f;
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

#if defined(__AVX2__) && !defined(__AVX512F__)
/* the loop within PRT_DENSE_RGB8_PAIRS (PRT_PAIRS_GROUPS, prt_kernels.h, where two points of three vectors per colour run
   as vector groups 2 + 1: dense3v2_3 above; 0: one pass): prt_plan_path reports it (only in these builds) */
int prt_dense_pairs_path(i64 n_pad) { return n_pad / 8 == 3 ? PRT_PAIRS_GROUPS : 0; }
#endif

/* the path prt_affine_dense_range takes for these shapes and codes (PRT_DENSE_*, prt_kernels.h): the dispatch below
   reads it, and prt_plan_path reports it (a benchmark row names the kernel it ran). Points past the last whole block
   of 8 take the one-point form of the same path. */
int prt_dense_path(i64 n_out, i64 n_pad, i64 C, const float *W, int mean, const int32_t *order) {
    const i64 nbt = n_pad / 8;
    if (HAVE_W16 && C == 3 && W && nbt >= 4 && nbt <= 8) return PRT_DENSE_W16;
    if (C == 3 && nbt <= 7) {
        if (!W && mean && !order && n_out == n_pad) return PRT_DENSE_VQ8;
        return W && nbt <= MAXNBS2 && PAIRS_NBT(nbt) ? PRT_DENSE_RGB8_PAIRS : PRT_DENSE_RGB8;
    }
    return PRT_DENSE_COLOUR;
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
    const int path = prt_dense_path(n_out, n_pad, C, W, mean, order);
#if HAVE_W16
    /* weights (PCA, CPCA, MRT-PCA), RGB, 32 to 64 rows: 16 rows per vector (dense3w) for every point of the call */
    const int wide = path == PRT_DENSE_W16;
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
        if (path == PRT_DENSE_VQ8) q = vq_dense_range(q, p1, n_out, lab, lab_kind, T, J, y, out, &flag);
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
                if (path == PRT_DENSE_RGB8_PAIRS && l < 7
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
#if defined(__AVX512VL__)
                    case 2: dense3v2_2(Tk, n_pad, F, mean, w, u, cnt, yp, zp, R + l); break;
#endif
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
            /* the first chunk's sum assigned, the others added: 0.0f + -0 would be +0 (a -0 result lost at 64 rows on
               the 8-lane path, where 8 blocks take this loop); 0 + x = x otherwise, so every other sum keeps its bits */
            for (i64 c = 0; c < C; c++) {
                int nb0 = (int)(nbt < cs ? nbt : cs);
                o[c] = dense1(nb0, Tk + c * n_pad, F, mean, w, cnt, yp);
                for (i64 b0 = cs; b0 < nbt; b0 += cs) {
                    int nb = (int)(nbt - b0 < cs ? nbt - b0 : cs);
                    o[c] += dense1(nb, Tk + c * n_pad + 8 * b0, F, mean, w, cnt, yp + 8 * b0);
                }
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

