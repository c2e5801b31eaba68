/* relight_plan.c: one relight from a plan (relight_kernels.plan, AffineCodec's per-encoding
 * cache): the constants (affine_constants.c), then the point kernel of the plan's kind (rows,
 * dense or taps), with the arguments that do not change between lights read from one int64 array
 * (PL_ fields; _PLAN_FIELDS on the Python side): one ctypes call per light. */

#include "prt_kernels.h"

/* One relight from a plan (relight_kernels.plan, AffineCodec's per-encoding cache): the per-cluster
   constants into T (prt_constants_lanes or prt_constants), then the per-point kernel (rows, dense or taps)
   — the arguments that do not change between lights read from a[] (PL_ fields, _PLAN_FIELDS in Python),
   one call where two ctypes calls of 11-19 converted arguments each cost about 4 us of a small relight.
   y0, y1: the view (dense: y [P, n_out] float32; taps: idx int64 [P, t], g float32 [P, t]). Returns
   16 (nothing computed past the check) if L holds a NaN or an infinity, else the point kernel's flag. */
enum { PL_KIND, PL_LANES, PL_K, PL_J, PL_JMAX, PL_NIN, PL_NOUT, PL_NPAD, PL_C, PL_MT, PL_SK, PL_SJ, PL_SO, PL_SC, PL_NKC,
       PL_MEAN, PL_P, PL_X, PL_FO, PL_LAB, PL_LABKIND, PL_W, PL_WSTRIDE, PL_WOFF, PL_NK, PL_NUSE, PL_ORDER, PL_CSORT,
       PL_NTAP, PL_N };
#define PL_PTR(i, T) ((T)(intptr_t)a[i])
int prt_relight_plan(const i64 *a, const float *L, float *T, float *out, const void *y0, const void *y1, int nthreads) {
    int bad = a[PL_LANES]
        ? prt_constants_lanes(a[PL_K], a[PL_J], a[PL_JMAX], a[PL_NIN], a[PL_C], PL_PTR(PL_MT, const float *), L, T, a[PL_SK],
                              a[PL_SJ], nthreads)
        : prt_constants(a[PL_K], a[PL_J], a[PL_JMAX], a[PL_NIN], a[PL_NOUT], a[PL_NPAD], a[PL_C], PL_PTR(PL_MT, const float *),
                        L, T, a[PL_SK], a[PL_SJ], a[PL_SO], a[PL_SC], PL_PTR(PL_NKC, const i64 *), (int)a[PL_MEAN], nthreads);
    if (bad) return 16;
    const void *lab = PL_PTR(PL_LAB, const void *);
    const float *W = PL_PTR(PL_W, const float *);
    const i64 *woff = PL_PTR(PL_WOFF, const i64 *), *nk = PL_PTR(PL_NK, const i64 *);
    const int32_t *order = PL_PTR(PL_ORDER, const int32_t *);
    const int lk = (int)a[PL_LABKIND], mean = (int)a[PL_MEAN], csort = (int)a[PL_CSORT];
    switch (a[PL_KIND]) {
    case 0:
        return prt_affine_rows(a[PL_P], a[PL_X], a[PL_FO], lab, lk, W, a[PL_WSTRIDE], woff, nk, a[PL_NUSE], mean, T, a[PL_J], out,
                               order, csort, nthreads);
    case 1:
        return prt_affine_dense(a[PL_K], a[PL_P], a[PL_FO], a[PL_X], a[PL_C], lab, lk, W, a[PL_WSTRIDE], woff, nk, a[PL_NUSE], mean, T,
                                a[PL_J], (const float *)y0, out, order, csort, nthreads);
    default:
        return prt_affine_taps(a[PL_P], a[PL_FO], a[PL_C], lab, lk, W, a[PL_WSTRIDE], woff, nk, a[PL_NUSE], mean, T, a[PL_X],
                               a[PL_NTAP], (const i64 *)y0, (const float *)y1, out, order, csort, nthreads);
    }
}


/* the point kernel a plan runs (PRT_ROWS_* / PRT_DENSE_* / PRT_TAPS_*), from the dispatch functions the kernels
   themselves switch on: what a benchmark row names as its kernel path */
int prt_plan_path(const i64 *a) {
    const void *lab = PL_PTR(PL_LAB, const void *);
    const float *W = PL_PTR(PL_W, const float *);
    const int32_t *order = PL_PTR(PL_ORDER, const int32_t *);
#if defined(__AVX2__) && !defined(__AVX512F__)  /* the loops within a path that only these builds have */
    if (a[PL_KIND] == 0) {
        const int path = prt_rows_path(a[PL_X], a[PL_FO], a[PL_J], lab, W, PL_PTR(PL_WOFF, const i64 *), PL_PTR(PL_NK, const i64 *),
                                       a[PL_NUSE], (int)a[PL_MEAN], order);
        return path == PRT_ROWS_SMALL_FIXED ? path + PRT_SUBPATH * prt_fixed_rows_path(a[PL_FO], (int)a[PL_LABKIND], a[PL_WSTRIDE],
                                                                                            a[PL_NUSE], a[PL_J]) : path;
    }
    if (a[PL_KIND] == 1) {
        const int path = prt_dense_path(a[PL_FO], a[PL_X], a[PL_C], W, (int)a[PL_MEAN], order);
        return path == PRT_DENSE_RGB8_PAIRS ? path + PRT_SUBPATH * prt_dense_pairs_path(a[PL_X]) : path;
    }
    if (a[PL_KIND] == 2) {
        const int path = prt_taps_path(a[PL_C], a[PL_X]);
        return path == PRT_TAPS_RGB8 ? path + PRT_SUBPATH * prt_taps_seq_path(a[PL_C], a[PL_X], lab, W, PL_PTR(PL_WOFF, const i64 *),
                                                                             PL_PTR(PL_NK, const i64 *), a[PL_NUSE], (int)a[PL_MEAN],
                                                                             a[PL_NTAP], order) : path;
    }
#endif
    switch (a[PL_KIND]) {
    case 0:
        return prt_rows_path(a[PL_X], a[PL_FO], a[PL_J], lab, W, PL_PTR(PL_WOFF, const i64 *), PL_PTR(PL_NK, const i64 *), a[PL_NUSE],
                             (int)a[PL_MEAN], order);
    case 1:
        return prt_dense_path(a[PL_FO], a[PL_X], a[PL_C], W, (int)a[PL_MEAN], order);
    default:
        return prt_taps_path(a[PL_C], a[PL_X]);
    }
}

/* the instruction sets this library was compiled for, as the kernels' #if branches see them (bits: 1 AVX, 2 AVX2,
   4 FMA, 8 AVX-512F, 16 AVX-512VL, 32 the 16-lane affine kernels built: vec.h's HAVE_W16, which is __AVX512F__; 64 the
   Gaussian codec's 16-lobe ones) */
int prt_isa(void) {
    int b = 0;
#if defined(__AVX__)
    b |= 1;
#endif
#if defined(__AVX2__)
    b |= 2;
#endif
#if defined(__FMA__)
    b |= 4;
#endif
#if defined(__AVX512F__)
    b |= 8;
#endif
#if defined(__AVX512F__) && !defined(PRT_NO_W16)
    b |= 32;  /* vec.h's HAVE_W16, the same condition */
#endif
#if defined(__AVX512VL__)
    b |= 16;
#endif
#if defined(__AVX512F__) && defined(__AVX512VL__) && !defined(PRT_NO_W16)
    b |= 64;  /* the Gaussian codec's 16-lobe kernels (sg_texels.h's SG16, the same condition) */
#endif
    return b;
}
