/* guided.c: the bounce estimator's guided first-hit rays in one pass (issue 42; part of library
 * "raygen", called by prt_torch/transfer/ray_kernels.py: guided_rays_native).
 *
 * diffuse.HitBounce draws the M rays of a first hit on a guided face (estimator 'auto', a flat and
 * mostly blocked face) from a piecewise-constant density over Malley's square (a = sin²θ, b = φ/2π)
 * with Ga × Gb cells (diffuse.GUIDE_GRID), built from the face probe (HitBounce._build_guide; a
 * defensive mixture, Hesterberg 1995). For guided hit g (its ray block h = hits[g], face f = tri[g])
 * and point m of the Hammersley set (ta[m], tb[m]), Cranley–Patterson rotated by (u1[g], v2[g]):
 *     ua = (ta[m] + u1) mod 1,  ub = (tb[m] + v2) mod 1
 *     ring    ia = #{i < Ga-1 : cA[i] <= ua} (cA: the face's cumulative ring masses), lo = cA[ia-1] (0 at ia = 0)
 *             a  = (ia + clip((ua - lo) / (cA[ia] - lo), 0, 1 - 1e-12)) / Ga
 *     sector  the same with the conditional cumulative masses cB[ia, :] of that ring and ub -> b
 *     q = 1 / (Ga·Gb·P[ia, ib])   (the cosine density over the guided one: the ray's weight factor)
 *     r = sqrt(a), z = sqrt(max(1 - a, 1e-24)), φ = 2πb,  d = (r cos φ t + r sin φ b) + z n
 * (Malley's map in the face frame, rows (t, b, n) of F[f]) -> D[h·M + m] (float32), W[h·M + m] = q.
 * The inverse-CDF warp is monotone per coordinate, so the rotated set's stratification carries over.
 * Every step is the float64 operation the numpy reference takes (HitBounce._guided_rays and
 * _malley_dirs), in its order, without FMA contraction (the library's -ffp-contract=off); cos and
 * sin are libm's, which numpy's float64 cos/sin equal on x86-64 glibc (tests/test_guided_kernel.py
 * checks the bits against the numpy reference).
 *     hits, tri int64 [G]; u1, v2 float64 [G]; ta, tb float64 [M]; grow int64 [Fall] (the face's
 *     guide row, -1 where not guided); cA float64 [Gf, Ga]; cB, P float64 [Gf, Ga, Gb]; F float64 [Fall, 3, 3]
 *     -> D float32 [·, 3], W float64 [·] written at rows h·M + m only.
 * Returns 0, or 1 + g for a hit g whose face has no guide row (its rays are not written). */

#include <math.h>
#include <stdint.h>
typedef int64_t i64;

static double clip01(double t) {
    if (t < 0.0) t = 0.0;               /* np.clip(x, 0.0, 1.0 - 1e-12) */
    if (t > 1.0 - 1e-12) t = 1.0 - 1e-12;
    return t;
}

/* one coordinate's inverse CDF: cumulative masses c[0..G-1] (c[G-1] = 1), u in [0, 1) -> (cell, warped point) */
static double warp1(const double *c, int G, double u, int *cell) {
    int i = 0;
    for (int j = 0; j < G - 1; j++) i += c[j] <= u;
    if (i > G - 1) i = G - 1;
    const double lo = i > 0 ? c[i - 1] : 0.0;
    const double p = c[i] - lo;
    *cell = i;
    return ((double)i + clip01((u - lo) / p)) / (double)G;
}

static i64 guided_range(i64 g0, i64 g1, i64 M, const i64 *hits, const i64 *tri, const double *u1, const double *v2,
                        const double *ta, const double *tb, const i64 *grow, const double *cA, const double *cB,
                        const double *P, int Ga, int Gb, const double *F, float *D, double *W) {
    const double two_pi = 2.0 * 3.141592653589793;  /* 2 * math.pi */
    const double K = (double)(Ga * Gb);
    for (i64 g = g0; g < g1; g++) {
        const i64 f = tri[g], gr = grow[f];
        if (gr < 0) return 1 + g;
        const double *ca = cA + gr * Ga, *cb = cB + gr * Ga * Gb, *pm = P + gr * Ga * Gb;
        const double *fr = F + 9 * f;
        const double uu = u1[g], vv = v2[g];
        const i64 h = hits[g];
        for (i64 m = 0; m < M; m++) {
            const double ua = fmod(ta[m] + uu, 1.0), ub = fmod(tb[m] + vv, 1.0);  /* np.mod of values in [0, 2) */
            int ia, ib;
            const double a = warp1(ca, Ga, ua, &ia);
            const double b = warp1(cb + ia * Gb, Gb, ub, &ib);
            const double e = 1.0 - a;
            const double r = sqrt(a), z = sqrt(e > 1e-24 ? e : 1e-24);
            const double phi = two_pi * b;
            const double x = r * cos(phi), y = r * sin(phi);
            const i64 ray = h * M + m;
            D[3 * ray] = (float)((x * fr[0] + y * fr[3]) + z * fr[6]);
            D[3 * ray + 1] = (float)((x * fr[1] + y * fr[4]) + z * fr[7]);
            D[3 * ray + 2] = (float)((x * fr[2] + y * fr[5]) + z * fr[8]);
            W[ray] = 1.0 / (K * pm[ia * Gb + ib]);
        }
    }
    return 0;
}

i64 prt_guided_rays(i64 G, i64 M, const i64 *hits, const i64 *tri, const double *u1, const double *v2, const double *ta,
                    const double *tb, const i64 *grow, const double *cA, const double *cB, const double *P, int Ga, int Gb,
                    const double *F, float *D, double *W, int nthreads) {
    i64 nth = nthreads > 0 ? nthreads : 1, bad = 0;
    #pragma omp parallel for schedule(static, 1) num_threads(nth) reduction(max: bad)
    for (i64 t = 0; t < nth; t++) {
        const i64 e = guided_range(G * t / nth, G * (t + 1) / nth, M, hits, tri, u1, v2, ta, tb, grow, cA, cB, P, Ga, Gb,
                                   F, D, W);
        if (e > bad) bad = e;
    }
    return bad;
}
