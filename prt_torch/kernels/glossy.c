/* glossy.c: the glossy / MRT transferred-radiance sums per vertex (issue 42 §2; part of library
 * "raygen", called by prt_torch/transfer/ray_kernels.py: outer_accumulate).
 *
 * T_p, the shadowed (and interreflected) transferred radiance of Sloan et al. 2002 §4–5 (Sloan 2003
 * §3.1), is a Monte Carlo sum over one shared sphere set {s_j} with weight c = 4π/N:
 *     T_p += c · Σ_{e in p} y(s_{dir[e]}) r_eᵀ,   r_e = y(s_{dir[e]}) (visibility sum) or R[e] (the
 * diffuse transfer of the point a blocked direction hits, the bounce term), over only the entries of
 * vertex p: its (direction, hit) pairs, grouped by vertex (rows ptr[p] .. ptr[p+1]-1). The former
 * torch form scattered the entries into dense [k, N] / [k, N, n] buffers (half of them below the
 * tangent plane, the rest mostly zero under the 'auto' estimator) and multiplied them by the whole
 * set; here each entry is one rank-1 update of the vertex's n × n block, which stays in L1.
 *     k vertices, n = bands², ptr int64 [k+1] (ptr[0] = 0, nondecreasing), dir int64 [E] in [0, N),
 *     Y float64 [N, n] (the set's SH values), R float64 [E, n] or NULL, T float64 [k, n, n] (added to).
 * Entries are added one after another in their order (blocks of four entries read each row of T
 * once, the additions still in entry order), so a vertex's T_p has the same bits for any chunking and
 * any thread count (vertices are split across OpenMP threads, never one vertex's entries). The
 * library's -ffp-contract=off keeps each update a product then a sum. */

#include <stdint.h>
typedef int64_t i64;

static void outer_vertex(i64 n, i64 e0, i64 e1, const i64 *restrict dir, const double *restrict Y,
                         const double *restrict R, double c, double *restrict t) {
    i64 e = e0;
    for (; e + 4 <= e1; e += 4) {
        const double *y0 = Y + dir[e] * n, *y1 = Y + dir[e + 1] * n, *y2 = Y + dir[e + 2] * n, *y3 = Y + dir[e + 3] * n;
        const double *r0 = R ? R + e * n : y0, *r1 = R ? R + (e + 1) * n : y1;
        const double *r2 = R ? R + (e + 2) * n : y2, *r3 = R ? R + (e + 3) * n : y3;
        for (i64 a = 0; a < n; a++) {
            const double a0 = c * y0[a], a1 = c * y1[a], a2 = c * y2[a], a3 = c * y3[a];
            double *restrict ta = t + a * n;
            for (i64 b = 0; b < n; b++) ta[b] = (((ta[b] + a0 * r0[b]) + a1 * r1[b]) + a2 * r2[b]) + a3 * r3[b];
        }
    }
    for (; e < e1; e++) {
        const double *y = Y + dir[e] * n, *r = R ? R + e * n : y;
        for (i64 a = 0; a < n; a++) {
            const double ya = c * y[a];
            double *restrict ta = t + a * n;
            for (i64 b = 0; b < n; b++) ta[b] = ta[b] + ya * r[b];
        }
    }
}

void prt_outer_accumulate(i64 k, i64 n, const i64 *ptr, const i64 *dir, const double *Y, const double *R, double c,
                          double *T, int threads) {
#pragma omp parallel for schedule(dynamic, 8) num_threads(threads > 0 ? threads : 1)
    for (i64 p = 0; p < k; p++) outer_vertex(n, ptr[p], ptr[p + 1], dir, Y, R, c, T + p * n * n);
}
