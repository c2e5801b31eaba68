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

/* The glossy kind's monochrome bounce (diffuse.HitBounce.exit_transfer with channel weights): a coloured hit
 * brings ρ_c x_c per channel c, made one transfer by the Rec. 709 luminance weights w (glossy matrices are shared
 * by the light's colour channels):
 *     out[h, b] = ((ρ_h0 x_h0[b]) w0 + (ρ_h1 x_h1[b]) w1) + (ρ_h2 x_h2[b]) w2,
 * the products and sums in exactly the order of the torch steps it replaces (mul, mul_, add_; -ffp-contract=off),
 * so the same bits, in one pass instead of eight over [H, n] temporaries.
 *     rho float64 [H, 3]; x float64 [H, C, n] with channel c read from min(c, C - 1) (C = 1: one exit transfer for
 *     the three albedos, one bounce); w float64 [3]; out float64 [H, n]. */
void prt_luma_mix(i64 H, i64 n, i64 C, const double *rho, const double *x, const double *w, double *out) {
    const double w0 = w[0], w1 = w[1], w2 = w[2];
    const i64 c1 = C > 1 ? 1 : 0, c2 = C > 2 ? 2 : C - 1;
    for (i64 h = 0; h < H; h++) {
        const double r0 = rho[3 * h], r1 = rho[3 * h + 1], r2 = rho[3 * h + 2];
        const double *x0 = x + h * C * n, *x1 = x0 + c1 * n, *x2 = x0 + c2 * n;
        double *o = out + h * n;
        for (i64 b = 0; b < n; b++) o[b] = ((r0 * x0[b]) * w0 + (r1 * x1[b]) * w1) + (r2 * x2[b]) * w2;
    }
}
