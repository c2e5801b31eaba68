/* transport.c: the BRDF of the transport tables, fused with what surrounds it (library "transport", called by
 * prt_torch/transfer/transport_kernels.py for transport._chunk_transport; Green 2005 §1.2 eq. 1.2, issue 42 §2).
 *
 * A table holds, per vertex v, view j and cube texel p, T = f_r(wi, wo) W with W = V max(n . wi, 0) (eq. 1.2),
 * and where the lobe is narrower than the texels (transport.supersample_plan) the texel average
 * T = sum_s a_s f_r(wi_s, wo) max(n . wi_s, 0) over S x S sub-texels s of solid-angle shares a_s.
 *
 * prt_transport_points (the point pass): for k vertices, wi float64 [k, P, 3] and wo float64 [k, J, 3] (local
 *     directions: the rows of the vertex frame applied to the texel centres and the views), W float64 [k, P],
 *     later uint8 [k, J, P] or NULL (the pairs the averages write: skipped), the BRDF's parameters per vertex
 *     par float64 [k, 4] -> out [k, J * P] (float32, float64 or float16: out_dtype 0, 1, 2): every element of the
 *     k rows is written, f_r W on the pairs of an upper view (wo_z > 0) and a texel with W > 0 not in `later`,
 *     0 elsewhere. Per vertex the visible texels are gathered once (structure of arrays), then each upper view
 *     evaluates them in one block.
 * prt_transport_averages (the texel averages): n pairs (vertex iv, view jv, texel pv, sub-texel count sv), frames
 *     float64 [k, 3, 3] (rows t, b, n), the sub-texel sets packed: for each S, sd float64 [P, S^2, 3] directions
 *     and sw float64 [P, S^2] shares, starting at element soff[S] of sd (x3) and sw -> out[iv, jv * P + pv] =
 *     the average above. The sub-texels' local directions are rotated once per run of pairs with the same
 *     (vertex, texel, S) (the caller sorts them so), keeping only those above the horizon (f_r is 0 below).
 *
 * The BRDF (model, flags; transport_kernels.native_model): 0 Ashikhmin-Shirley 2000 eq. 4 (+ eq. 5's diffuse
 * term where rd != 0; flags bit 0 Fresnel, bit 1 diffuse), par = (nu, nv, rs, rd); 1 modified Phong, 2 Phong
 * in the reflection form (Ramamoorthi 2002 eq. 3.37: the lobe over cos theta_i), 3 normalised Blinn-Phong,
 * par = (s, ks, kd); 4 Lambertian, par = (kd). The formulas and their order of operations are prt_torch/brdf.py's
 * _eval; the power b^e is glibc's libmvec _ZGVdN4vv_pow 4 lanes at a time on the AVX2 path (lanes padded with
 * 1^1), libm's pow otherwise (the portable path): values within a few ulp of torch's (tests: relative 1e-12).
 * f_r is 0 where wi_z <= 0 or wo_z <= 0, as BRDF.eval. Threads (OpenMP, `nthreads`): vertices (points) or
 * ranges of pairs (averages); each output element is computed by one thread the same way whatever the count. */

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__AVX2__)
#include <immintrin.h>
__m256d _ZGVdN4vv_pow(__m256d x, __m256d y); /* glibc libmvec: pow, 4 doubles (AVX2) */
#endif

typedef int64_t i64;

#define NPAR 4
/* pairs per unit of the averages' dynamic schedule (a shared machine stalls a static split at its slowest thread) */
#define AVG_BLOCK 512
#define PI 3.14159265358979323846

int prt_transport_points(i64 k, i64 J, i64 P, const double *wi, const double *wo, const double *W, const uint8_t *later,
                         int model, int flags, const double *par, int out_dtype, void *out, int nthreads);
int prt_transport_averages(i64 n, const i64 *iv, const i64 *jv, const i64 *pv, const i64 *sv, i64 J, i64 P,
                           const double *frames, const double *wo, const double *sd, const double *sw, const i64 *soff,
                           int model, int flags, const double *par, int out_dtype, void *out, int nthreads);
int prt_transport_abi(void);

/* 2: float16 output compiled in (the compiler has _Float16), else 1 */
int prt_transport_abi(void) {
#if defined(__FLT16_MAX__)
    return 2;
#else
    return 1;
#endif
}

/* out[q] = b[q]^e[q], q < n (n a multiple of 4) */
static void pow_block(i64 n, const double *b, const double *e, double *o) {
    i64 q = 0;
#if defined(__AVX2__)
    for (; q + 4 <= n; q += 4) _mm256_storeu_pd(o + q, _ZGVdN4vv_pow(_mm256_loadu_pd(b + q), _mm256_loadu_pd(e + q)));
#endif
    for (; q < n; q++) o[q] = pow(b[q], e[q]);
}

static inline double pow5(double x) { double x2 = x * x; return x2 * x2 * x; }

/* per-thread scratch of a block of m lanes: power bases, exponents, two factors, the powers */
typedef struct { double *b, *e, *c1, *c2, *pw; } Scratch;

/* f[q] = f_r(w[q], o) for q < n, w given as wx, wy, wz (n4 = n rounded up to 4 lanes, all readable and finite) */
static void eval_block(int model, int flags, const double *p, i64 n, const double *restrict wx, const double *restrict wy,
                       const double *restrict wz, double ox, double oy, double oz, double *restrict f, const Scratch *s) {
    i64 n4 = (n + 3) & ~(i64)3;
    double *restrict B = s->b, *restrict E = s->e, *restrict C1 = s->c1, *restrict C2 = s->c2, *restrict PW = s->pw;
    if (model == 4) { /* Lambertian */
        for (i64 q = 0; q < n; q++) f[q] = (wz[q] > 0 && oz > 0) ? p[0] / PI : 0.0;
        return;
    }
    if (model == 0) { /* Ashikhmin-Shirley eq. 4 (+ eq. 5) */
        const double nu = p[0], nv = p[1], rs = p[2], rd = p[3];
        const double C = sqrt((nu + 1) * (nv + 1)) / (8 * PI), fr = (flags & 1) ? 1.0 : 0.0;
        for (i64 q = 0; q < n4; q++) {
            double hx = wx[q] + ox, hy = wy[q] + oy, hz = wz[q] + oz;
            double nr = sqrt(hx * hx + hy * hy + hz * hz);
            nr = nr > 1e-300 ? nr : 1e-300;
            hx = hx / nr; hy = hy / nr; hz = hz / nr;
            double hx2 = hx * hx, hy2 = hy * hy, hzc = hz < 0 ? 0 : (hz > 1 ? 1 : hz);
            double sin2 = hx2 + hy2;
            double ex = sin2 > 1e-30 ? (nu * hx2 + nv * hy2) / sin2 : nu;
            double kh = wx[q] * hx + wy[q] * hy + wz[q] * hz;
            kh = kh > 1e-300 ? kh : 1e-300;
            double mz = wz[q] > oz ? wz[q] : oz;
            mz = mz > 1e-300 ? mz : 1e-300;
            B[q] = hzc; E[q] = ex; C1[q] = kh * mz;
            C2[q] = rs + (1 - rs) * pow5(1 - kh) * fr; /* fr = 0: exactly rs */
        }
        pow_block(n4, B, E, PW);
        const int diff = (flags & 2) && rd != 0.0; /* rd = 0: the diffuse term is exactly 0 */
        const double co = oz < 0 ? 0 : (oz > 1 ? 1 : oz), D = 28 * rd / (23 * PI) * (1 - rs), Do = 1 - pow5(1 - co / 2);
        for (i64 q = 0; q < n; q++) {
            double v = C * PW[q] / C1[q] * C2[q];
            if (diff) {
                double ci = wz[q] < 0 ? 0 : (wz[q] > 1 ? 1 : wz[q]);
                v = v + D * (1 - pow5(1 - ci / 2)) * Do;
            }
            f[q] = (wz[q] > 0 && oz > 0) ? v : 0.0;
        }
        return;
    }
    /* Phong (1, 2) and Blinn-Phong (3): kd/pi + ks (s + c)/(c pi) x^s */
    const double sx = p[0], ks = p[1], kd = p[2];
    for (i64 q = 0; q < n4; q++) {
        double x;
        if (model == 3) {
            double hx = wx[q] + ox, hy = wy[q] + oy, hz = wz[q] + oz;
            double nr = sqrt(hx * hx + hy * hy + hz * hz);
            nr = nr > 1e-300 ? nr : 1e-300;
            x = hz / nr;
        } else {
            x = -ox * wx[q] + -oy * wy[q] + oz * wz[q]; /* reflect(wo) . wi */
        }
        B[q] = x > 0 ? x : 0; E[q] = sx;
    }
    pow_block(n4, B, E, PW);
    const double A = model == 3 ? ks * (sx + 8) / (8 * PI) : model == 1 ? ks * (sx + 2) / (2 * PI) : ks * (sx + 1) / (2 * PI);
    for (i64 q = 0; q < n; q++) {
        double v = model == 2 ? kd / PI + A * PW[q] / (wz[q] > 1e-300 ? wz[q] : 1e-300) : kd / PI + A * PW[q];
        f[q] = (wz[q] > 0 && oz > 0) ? v : 0.0;
    }
}

static inline void store(void *out, int dt, i64 at, double v) {
    if (dt == 0) ((float *)out)[at] = (float)v;
    else if (dt == 1) ((double *)out)[at] = v;
#if defined(__FLT16_MAX__)
    else ((_Float16 *)out)[at] = (_Float16)v;
#endif
}

static int alloc_scratch(Scratch *s, double **more, int nmore, i64 m) {
    double *all = malloc(sizeof(double) * (size_t)m * (size_t)(5 + nmore));
    if (!all) return 1;
    s->b = all; s->e = all + m; s->c1 = all + 2 * m; s->c2 = all + 3 * m; s->pw = all + 4 * m;
    for (int t = 0; t < nmore; t++) more[t] = all + (5 + t) * m;
    return 0;
}

static int dtype_ok(int out_dtype) {
#if defined(__FLT16_MAX__)
    return out_dtype >= 0 && out_dtype <= 2;
#else
    return out_dtype == 0 || out_dtype == 1;
#endif
}

int prt_transport_points(i64 k, i64 J, i64 P, const double *wi, const double *wo, const double *W, const uint8_t *later,
                         int model, int flags, const double *par, int out_dtype, void *out, int nthreads) {
    if (!dtype_ok(out_dtype) || model < 0 || model > 4) return 1;
    int nth = nthreads > 0 ? nthreads : 1, err = 0;
    const size_t es = out_dtype == 0 ? 4 : out_dtype == 1 ? 8 : 2;
    #pragma omp parallel num_threads(nth) reduction(| : err)
    {
        i64 m = P + 4;
        Scratch s;
        double *a[11]; /* visible texels: x, y, z, W, index; one view's: x, y, z, W, index, f */
        if (alloc_scratch(&s, a, 11, m)) err = 1;
        else {
            double *vx = a[0], *vy = a[1], *vz = a[2], *vw = a[3], *fx = a[5], *fy = a[6], *fz = a[7], *fw = a[8], *f = a[10];
            i64 *vi = (i64 *)a[4], *fi = (i64 *)a[9];
            #pragma omp for schedule(dynamic, 1)
            for (i64 v = 0; v < k; v++) {
                memset((char *)out + (size_t)(v * J * P) * es, 0, (size_t)(J * P) * es);
                i64 nv = 0;
                for (i64 p = 0; p < P; p++) {
                    double w = W[v * P + p];
                    if (!(w > 0)) continue;
                    const double *d = wi + 3 * (v * P + p);
                    vx[nv] = d[0]; vy[nv] = d[1]; vz[nv] = d[2]; vw[nv] = w; vi[nv] = p; nv++;
                }
                for (i64 j = 0; j < J; j++) {
                    const double *o = wo + 3 * (v * J + j);
                    if (!(o[2] > 0) || !nv) continue;
                    const uint8_t *lt = later ? later + (v * J + j) * P : NULL;
                    double *ex = vx, *ey = vy, *ez = vz, *ew = vw;
                    const i64 *ei = vi;
                    i64 n = nv;
                    if (lt) { /* the view's pairs the averages write are skipped */
                        n = 0;
                        for (i64 q = 0; q < nv; q++) {
                            if (lt[vi[q]]) continue;
                            fx[n] = vx[q]; fy[n] = vy[q]; fz[n] = vz[q]; fw[n] = vw[q]; fi[n] = vi[q]; n++;
                        }
                        ex = fx; ey = fy; ez = fz; ew = fw; ei = fi;
                    }
                    for (i64 q = n; q < ((n + 3) & ~(i64)3); q++) { ex[q] = 0; ey[q] = 0; ez[q] = 1; }
                    eval_block(model, flags, par + NPAR * v, n, ex, ey, ez, o[0], o[1], o[2], f, &s);
                    i64 row = v * J * P + j * P;
                    for (i64 q = 0; q < n; q++) store(out, out_dtype, row + ei[q], f[q] * ew[q]);
                }
            }
            free(s.b);
        }
    }
    return err ? 2 : 0;
}

int prt_transport_averages(i64 n, const i64 *iv, const i64 *jv, const i64 *pv, const i64 *sv, i64 J, i64 P,
                           const double *frames, const double *wo, const double *sd, const double *sw, const i64 *soff,
                           int model, int flags, const double *par, int out_dtype, void *out, int nthreads) {
    if (!dtype_ok(out_dtype) || model < 0 || model > 4) return 1;
    for (i64 q = 0; q < n; q++)
        if (sv[q] < 1 || sv[q] > 8 || soff[sv[q]] < 0) return 3;
    int nth = nthreads > 0 ? nthreads : 1, err = 0;
    #pragma omp parallel num_threads(nth) reduction(| : err)
    {
        Scratch s;
        double *a[5]; /* the kept sub-texels: x, y, z, share; f */
        if (alloc_scratch(&s, a, 5, 68)) err = 1;
        else {
            double *x = a[0], *y = a[1], *z = a[2], *w = a[3], *f = a[4];
            #pragma omp for schedule(dynamic, 1)
            for (i64 blk = 0; blk < (n + AVG_BLOCK - 1) / AVG_BLOCK; blk++) {
            i64 q1 = (blk + 1) * AVG_BLOCK < n ? (blk + 1) * AVG_BLOCK : n, li = -1, lp = -1, lS = -1, m = 0;
            for (i64 q = blk * AVG_BLOCK; q < q1; q++) {
                i64 i = iv[q], p = pv[q], S = sv[q], S2 = S * S;
                if (i != li || p != lp || S != lS) { /* rotate this (vertex, texel)'s sub-texels into its frame */
                    const double *F = frames + 9 * i, *d = sd + 3 * (soff[S] + p * S2), *a_s = sw + soff[S] + p * S2;
                    m = 0;
                    for (i64 u = 0; u < S2; u++) {
                        double dx = d[3 * u], dy = d[3 * u + 1], dz = d[3 * u + 2];
                        double lz = F[6] * dx + F[7] * dy + F[8] * dz;
                        if (!(lz > 0)) continue; /* below the horizon: f_r max(n . w, 0) = 0 */
                        x[m] = F[0] * dx + F[1] * dy + F[2] * dz; y[m] = F[3] * dx + F[4] * dy + F[5] * dz; z[m] = lz;
                        w[m] = a_s[u]; m++;
                    }
                    for (i64 u = m; u < ((m + 3) & ~(i64)3); u++) { x[u] = 0; y[u] = 0; z[u] = 1; }
                    li = i; lp = p; lS = S;
                }
                const double *o = wo + 3 * (i * J + jv[q]);
                double acc = 0.0;
                if (m) {
                    eval_block(model, flags, par + NPAR * i, m, x, y, z, o[0], o[1], o[2], f, &s);
                    for (i64 u = 0; u < m; u++) acc += f[u] * z[u] * w[u];
                }
                store(out, out_dtype, i * J * P + jv[q] * P + p, acc);
            }
            }
            free(s.b);
        }
    }
    return err ? 2 : 0;
}
