/* raygen.c: ray generation of the uniform-sampling diffuse precompute, in one pass (library "raygen",
 * called by prt_torch/transfer/ray_kernels.py).
 *
 * For a chunk of k vertices and N shared sample directions, the rays traced are the pairs (vertex v,
 * direction s) with n_v . s > 0, grouped by vertex in row-major order (PRT course notes 2005,
 * "Precomputation": only the upper hemisphere contributes to the transfer integral).
 *     cos float64 [k, N] = n_v . s;  ov float32 [k, 3] (origins, already offset);  dirs float32 [N, 3]
 *     -> I, J int64 [R] (vertex, direction), O, D float32 [R, 3] (origin, direction)
 * prt_count_up counts each vertex's rays, the caller takes the exclusive prefix sum (starts), and
 * prt_fill_up writes them: the same values in the same order as the numpy path (same bits). */

#include <stdint.h>
typedef int64_t i64;

/* counts[v] = #{s : cos[v, s] > 0} for v in [v0, v1) */
static void count_range(i64 v0, i64 v1, i64 N, const double *cos, i64 *counts) {
    for (i64 v = v0; v < v1; v++) {
        const double *c = cos + v * N;
        i64 n = 0;
        for (i64 s = 0; s < N; s++) n += c[s] > 0.0;
        counts[v] = n;
    }
}

/* the rays of vertices [v0, v1), from position r0: i = v, j = s, o = ov[v], d = dirs[s] */
static void fill_range(i64 v0, i64 v1, i64 r0, i64 N, const double *cos, const float *ov, const float *dirs,
                       i64 *I, i64 *J, float *O, float *D) {
    i64 r = r0;
    for (i64 v = v0; v < v1; v++) {
        const double *c = cos + v * N;
        float ox = ov[3 * v], oy = ov[3 * v + 1], oz = ov[3 * v + 2];
        for (i64 s = 0; s < N; s++) {
            if (!(c[s] > 0.0)) continue;
            I[r] = v; J[r] = s;
            O[3 * r] = ox; O[3 * r + 1] = oy; O[3 * r + 2] = oz;
            D[3 * r] = dirs[3 * s]; D[3 * r + 1] = dirs[3 * s + 1]; D[3 * r + 2] = dirs[3 * s + 2];
            r++;
        }
    }
}

int prt_count_up(i64 k, i64 N, const double *cos, i64 *counts, int nthreads) {
    i64 nth = nthreads > 0 ? nthreads : 1;
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++) count_range(k * t / nth, k * (t + 1) / nth, N, cos, counts);
    return 0;
}

/* starts[v] = where vertex v's rays begin (exclusive prefix sum of the counts) */
int prt_fill_up(i64 k, i64 N, const double *cos, const i64 *starts, const float *ov, const float *dirs, i64 *I, i64 *J,
                float *O, float *D, int nthreads) {
    i64 nth = nthreads > 0 ? nthreads : 1;
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++) {
        i64 v0 = k * t / nth, v1 = k * (t + 1) / nth;
        if (v0 < v1) fill_range(v0, v1, starts[v0], N, cos, ov, dirs, I, J, O, D);
    }
    return 0;
}
