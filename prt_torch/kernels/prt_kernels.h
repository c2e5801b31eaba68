/* prt_kernels.h: the entry points of the relighting library (libprt "relight"), the ABI that
 * prt_torch/codecs/relight_kernels.py declares to ctypes (its _SIGNATURES) and calls.
 *
 * Every entry point returns an int (0: done; other values a flag the caller decodes: a non-finite
 * light, a non-finite output, a bad tap) and takes the thread count last. Tensors are passed as
 * pointers to contiguous float32 / int64 / int32 memory owned by torch; shapes are in each
 * definition's comment. The sources compiled together into the library are listed in
 * relight_kernels._SOURCES; each .c file compiles on its own (tests/test_kernel_sources.py builds
 * every one with -Wall -Wextra -Werror). */

#ifndef PRT_PRT_KERNELS_H
#define PRT_PRT_KERNELS_H
#include <stddef.h>
#include <stdlib.h>
#include <stdint.h>
#include <float.h>
#include <math.h>
#ifdef _OPENMP
#include <omp.h>
#endif
typedef int64_t i64;

int prt_constants(i64 K, i64 J, i64 Jmax, i64 n_in, i64 n_out, i64 n_pad, i64 C, const float *Mt, const float *L, float *out, i64 sk, i64 sj, i64 so, i64 sc, const i64 *nk, int mean, int nthreads);
int prt_constants_lanes(i64 K, i64 J, i64 Jmax, i64 n_in, i64 C, const float *Mv, const float *L, float *out, i64 sk, i64 sj, int nthreads);
int prt_rows_pad(i64 Fo, i64 J);
int prt_affine_rows(i64 P, i64 F, i64 Fo, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 J, float *out, const int32_t *order, int csort, int nthreads);
int prt_dense_pad(i64 n_out);
int prt_affine_dense(i64 K, i64 P, i64 n_out, i64 n_pad, i64 C, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 J, const float *y, float *out, const int32_t *order, int csort, int nthreads);
int prt_affine_taps(i64 P, i64 n_out, i64 C, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 Jp, i64 ntap, const i64 *idx, const float *g, float *out, const int32_t *order, int csort, int nthreads);
/* the point kernels' paths (prt_rows_path, prt_dense_path, prt_taps_path; prt_plan_path for a plan), as the kernels
   dispatch on them: relight_kernels.kernel_path names them (_PATH_NAMES there, in this order) */
enum { PRT_ROWS_VQ_COPY = 1, PRT_ROWS_SMALL_VQ_RGB8, PRT_ROWS_SMALL_VQ, PRT_ROWS_SMALL_K1_RGB8, PRT_ROWS_SMALL_FIXED,
       PRT_ROWS_SMALL_ONE, PRT_ROWS_W16, PRT_ROWS_W8_PAIRS, PRT_ROWS_W8,
       PRT_DENSE_VQ8, PRT_DENSE_W16, PRT_DENSE_RGB8_PAIRS, PRT_DENSE_RGB8, PRT_DENSE_COLOUR,
       PRT_TAPS_ONE_TERM, PRT_TAPS_RGB8, PRT_TAPS_GENERAL };
int prt_rows_path(i64 F, i64 Fo, i64 J, const void *lab, const float *W, const i64 *woff, const i64 *nk, i64 nuse, int mean, const int32_t *order);
int prt_dense_path(i64 n_out, i64 n_pad, i64 C, const float *W, int mean, const int32_t *order);
int prt_taps_path(i64 C, i64 Jp);
/* AVX2 builds without AVX-512 only: the loop within a path (0: the path's general one), as the kernels dispatch on it;
   prt_plan_path reports it as PRT_SUBPATH times it plus the path */
enum { PRT_SEQ_TAPS = 1, PRT_SEQ_TAPS_EXACT, PRT_SEQ_TAPS_K1_4, PRT_FIXED_U8_RGB = 1, PRT_PAIRS_GROUPS = 1, PRT_SUBPATH = 32 };
int prt_taps_seq_path(i64 C, i64 Jp, const void *lab, const float *W, const i64 *woff, const i64 *nk, i64 nuse, int mean, i64 ntap,
                      const int32_t *order);
int prt_fixed_rows_path(i64 Fo, int lab_kind, i64 wstride, i64 nuse, i64 J);
int prt_dense_pairs_path(i64 n_pad);
int prt_plan_path(const i64 *a);
int prt_isa(void);
int prt_relight_plan(const i64 *a, const float *L, float *T, float *out, const void *y0, const void *y1, int nthreads);
int prt_sg_lookup_sum_q(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss, const float *table, const float *quads, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads);
int prt_sg_lookup_sum(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss, const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads);
int prt_sg_prepare(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss, i64 r, i64 L, const float *ladder, int32_t *P, int nthreads);
int prt_sg_lookup_prepared(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss, const int32_t *P, const float *table, const float *quads, i64 r, i64 L, const float *ladder, float *out, int nthreads);
int prt_sg_taps(i64 V, i64 J, i64 N, i64 k, i64 fv, i64 fj, const float *w, const float *mu, const float *sigma, i64 sw, i64 sm, i64 ss, const i64 *idx, const float *av, const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads);
int prt_sg_taps_prepare(i64 V, i64 J, i64 N, i64 k, i64 fv, i64 fj, const float *w, const float *mu, const float *sigma, i64 sw, i64 sm, i64 ss, const i64 *idx, const float *av, i64 r, i64 L, const float *ladder, int32_t *P, float *tot, int nthreads);
int prt_sg_taps_prepared(i64 V, i64 J, i64 N, i64 k, i64 fv, i64 fj, const float *w, const float *mu, const float *sigma, i64 sw, i64 sm, i64 ss, const i64 *idx, const float *av, const int32_t *P, const float *tot, const float *table, i64 r, i64 L, const float *ladder, float *out, int nthreads);
#endif /* PRT_PRT_KERNELS_H */
