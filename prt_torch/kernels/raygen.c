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

/* ---------------------------------------------------------------------------------------------
 * The qmc diffuse precompute's rays (issue 42): for k vertices, M directions each from a
 * Hammersley set (a_m, b_m) over the vertex's hemisphere, uniform in solid angle, Cranley–Patterson
 * rotated per vertex by (u1_v, u2_v) (Cranley & Patterson 1976; the per-vertex hashes are computed
 * by the caller from (seed, vertex id)):
 *     z = max((a_m + u1_v) mod 1, 1e-12),  φ = 2π((b_m + u2_v) mod 1),  r = sqrt(1 − z²)
 *     d = r cos φ · t_v + r sin φ · b_v + z · n_v     (rows (t, b, n) of the vertex frame F_v)
 * cos φ and sin φ by the angle sum from cos 2πb_m, sin 2πb_m (tabled once, cb, sb) and
 * cos 2πu2_v, sin 2πu2_v (cu, su, per vertex): the mod 1 of φ is a whole turn, so no libm call
 * per ray. Every step is a float64 operation in the order the numpy reference
 * (diffuse.DiffuseSampler.rays without the library) takes, compiled without FMA contraction
 * (-std=c99): the same bits.
 *     F float64 [k, 3, 3]; ov float32 [k, 3]; u1, cu, su float64 [k]; a, cb, sb float64 [M]
 *     -> O, D float32 [k·M, 3] (origin = ov[v]), Z float64 [k·M] (z = n_v · d, the cosine)
 * Rays are grouped by vertex: ray v·M + m.
 * cosine = 1: the bounce estimator's cosine-weighted set at hit points instead (diffuse.HitBounce,
 * Malley's method): with a = (a_m + u1_v) mod 1, r = sqrt(a), z = sqrt(max(1 − a, 1e-24)). */

#include <math.h>

static void qmc_range(i64 v0, i64 v1, i64 M, const double *F, const float *ov, const double *u1, const double *cu,
                      const double *su, const double *a, const double *cb, const double *sb, float *O, float *D,
                      double *Z, int cosine) {
    for (i64 v = v0; v < v1; v++) {
        const double *f = F + 9 * v;
        const double tx = f[0], ty = f[1], tz = f[2], bx = f[3], by = f[4], bz = f[5], nx = f[6], ny = f[7], nz = f[8];
        const double uu = u1[v], c = cu[v], s = su[v];
        const float ox = ov[3 * v], oy = ov[3 * v + 1], oz = ov[3 * v + 2];
        float *o = O + 3 * v * M, *d = D + 3 * v * M;
        double *zz = Z + v * M;
        for (i64 m = 0; m < M; m++) {
            double z = a[m] + uu, r;
            if (z >= 1.0) z -= 1.0;            /* exact for z in [1, 2) (Sterbenz): numpy's remainder */
            if (cosine == 1) {
                const double e = 1.0 - z;
                r = sqrt(z);
                z = sqrt(e > 1e-24 ? e : 1e-24);
            } else if (cosine == 2) {          /* the defensive mixture p(z) = 3/4 + z/2: z = 2a / (3/4 + sqrt(9/16 + a)) */
                z = (2.0 * z) / (0.75 + sqrt(0.5625 + z));
                if (!(z > 1e-12)) z = 1e-12;
                r = sqrt(1.0 - z * z);
            } else {
                if (!(z > 1e-12)) z = 1e-12;   /* np.maximum(z, 1e-12) */
                r = sqrt(1.0 - z * z);
            }
            const double x = r * (cb[m] * c - sb[m] * s), y = r * (sb[m] * c + cb[m] * s);
            d[3 * m] = (float)((x * tx + y * bx) + z * nx);
            d[3 * m + 1] = (float)((x * ty + y * by) + z * ny);
            d[3 * m + 2] = (float)((x * tz + y * bz) + z * nz);
            o[3 * m] = ox; o[3 * m + 1] = oy; o[3 * m + 2] = oz;
            zz[m] = z;
        }
    }
}

int prt_qmc_rays(i64 k, i64 M, const double *F, const float *ov, const double *u1, const double *cu, const double *su,
                 const double *a, const double *cb, const double *sb, float *O, float *D, double *Z, int cosine, int nthreads) {
    i64 nth = nthreads > 0 ? nthreads : 1;
    #pragma omp parallel for schedule(static, 1) num_threads(nth)
    for (i64 t = 0; t < nth; t++) qmc_range(k * t / nth, k * (t + 1) / nth, M, F, ov, u1, cu, su, a, cb, sb, O, D, Z, cosine);
    return 0;
}

/* Which traced rays an estimator reads (diffuse.DiffuseSampler, issue 42), for rays grouped by
 * vertex in blocks of M with weights w·z (z float64 [k·M], hit uint8 [k·M], 1 = blocked):
 *     mode 0 'auto':    open_v = Σ_m w z_m [not hit] >= 0.5 Σ_m w z_m (sums in ray order, as
 *                       np.bincount takes them); read the blocked rays of open vertices and the
 *                       visible rays of the others
 *     mode 1 'control': the blocked rays;   mode 2 'plain': the visible rays
 * -> open_v uint8 [k], sel int64 [≤ k·M] (ray indices, ascending), count[0] = how many. */
int prt_select_rays(i64 k, i64 M, const double *Z, const uint8_t *hit, double w, int mode, uint8_t *open_v, i64 *sel,
                    i64 *count) {
    i64 n = 0;
    for (i64 v = 0; v < k; v++) {
        const double *z = Z + v * M;
        const uint8_t *h = hit + v * M;
        uint8_t open = mode == 1;
        if (mode == 0) {
            double wo = 0.0, wa = 0.0;
            for (i64 m = 0; m < M; m++) {
                const double wz = w * z[m];
                wa += wz;
                wo += h[m] ? 0.0 : wz;
            }
            open = wo >= 0.5 * wa;
        }
        open_v[v] = open;
        for (i64 m = 0; m < M; m++) {
            sel[n] = v * M + m;
            n += (h[m] != 0) == open;
        }
    }
    count[0] = n;
    return 0;
}

/* The estimators' sum over their rays, by vertex, with the SH values computed on the fly:
 *     S[sel_r / M, :] += w · z_r · y(d_r)     for r in [0, nsel)   (z NULL: z_r = 1)
 * d_r = D[sel_r] (float32 directions, normalised in float64 as sphericart does), y the real SH of
 * `bands` bands in the graphics convention (Ramamoorthi 2002 eq. 4.5, no Condon–Shortley phase,
 * flat index l(l+1)+m): y_lm = K_lm Q_l^|m|(z) · {√2 Re (x+iy)^m, m > 0; 1, m = 0; √2 Im (x+iy)^|m|,
 * m < 0}, with Q_l^m = P_l^m / sin^m θ by the recurrence Q_m^m = (2m−1)!!, Q_{m+1}^m = (2m+1) z Q_m^m,
 * (l−m) Q_l^m = (2l−1) z Q_{l−1}^m − (l+m−1) Q_{l−2}^m; K float64 [bands²] holds K_lm (with the √2
 * for m ≠ 0) by flat index. sel ascending or not; rays grouped by vertex in blocks of M.
 * S float64 [k, bands²] is accumulated into (the caller zeroes it). bands in [1, 32]. */
int prt_sh_accumulate(i64 nsel, const i64 *sel, i64 M, const float *D, const double *Z, double w, int bands,
                      const double *K, double *S) {
    double cs[32], sn[32];
    const i64 n2 = (i64)bands * bands;
    if (bands < 1 || bands > 32) return 1;
    for (i64 r = 0; r < nsel; r++) {
        const i64 ray = sel[r];
        const double x0 = D[3 * ray], y0 = D[3 * ray + 1], z0 = D[3 * ray + 2];
        const double inv = 1.0 / sqrt(x0 * x0 + y0 * y0 + z0 * z0);  /* float32 rounding leaves |d| 1 ± 1e-7 */
        const double x = x0 * inv, y = y0 * inv, z = z0 * inv;
        const double wt = Z ? w * Z[ray] : w;
        double *s = S + (ray / M) * n2;
        cs[0] = 1.0; sn[0] = 0.0;
        for (int m = 1; m < bands; m++) {
            cs[m] = x * cs[m - 1] - y * sn[m - 1];
            sn[m] = x * sn[m - 1] + y * cs[m - 1];
        }
        double qmm = 1.0;  /* Q_m^m = (2m-1)!! */
        for (int m = 0; m < bands; m++) {
            if (m > 0) qmm *= (double)(2 * m - 1);
            double q2 = 0.0, q1 = 0.0;  /* Q_{l-2}^m, Q_{l-1}^m */
            for (int l = m; l < bands; l++) {
                double q;
                if (l == m) q = qmm;
                else if (l == m + 1) q = (double)(2 * m + 1) * z * qmm;
                else q = ((double)(2 * l - 1) * z * q1 - (double)(l + m - 1) * q2) / (double)(l - m);
                q2 = q1; q1 = q;
                const i64 c = (i64)l * (l + 1);
                const double a = wt * q;
                if (m == 0) {
                    s[c] += a * K[c];
                } else {
                    s[c + m] += a * K[c + m] * cs[m];
                    s[c - m] += a * K[c - m] * sn[m];
                }
            }
        }
    }
    return 0;
}
