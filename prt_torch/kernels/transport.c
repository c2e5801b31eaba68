/* transport.c: the BRDF of the transport tables, fused with what surrounds it (library "transport", called by
 * prt_torch/transfer/transport_kernels.py for transport._chunk_transport; Green 2005 §1.2 eq. 1.2, issue 42 §2).
 *
 * A table holds, per vertex v, view j and cube texel p, T = f_r(wi, wo) W with W = V max(n . wi, 0) (eq. 1.2),
 * and where the lobe is narrower than the texels (transport.supersample_plan) the texel average
 * T = sum_s a_s f_r(wi_s, wo) max(n . wi_s, 0) over S x S sub-texels s of solid-angle shares a_s.
 *
 * prt_transport_points (the point pass): for k vertices, wi float64 [k, P, 3] and wo float64 [k, J, 3] (local
 *     directions: the rows of the vertex frame applied to the texel centres and the views), W float64 [k, P],
 *     the horizon (a double: a view with wo_z <= horizon is below it), the na averaged pairs (ai, aj, ap
 *     int64: vertex, view, texel, in that lexicographic order; checked, 4 if not; the pairs the averages write,
 *     skipped by merging the sorted lists), the BRDF's parameters per vertex par float64 [k, 4]
 *     -> out [k, J * P] (float32, float64 or float16: out_dtype 0, 1, 2; float16 through float, as torch):
 *     every element of the k rows is written, f_r W on the pairs of an upper view (wo_z > horizon, the
 *     caller's transport.HORIZON_EPS: a view in the tangent plane, where Ward's 1/sqrt(cos theta_o) diverges,
 *     counts as below) and a texel with W > 0 not averaged, 0 elsewhere. Per vertex the visible texels are
 *     gathered once (structure of arrays), then each upper view evaluates them in one block.
 * prt_transport_averages (the texel averages): n pairs (vertex iv, view jv, texel pv, sub-texel count sv; any
 *     order), frames float64 [k, 3, 3] (rows t, b, n), the sub-texel sets packed: for each S, sd float64
 *     [P, S^2, 3] directions and sw float64 [P, S^2] shares, starting at element soff[S] of sd (x3) and sw
 *     -> out[iv, jv * P + pv] = the average above. The pairs are taken in (vertex, texel) order (a stable
 *     counting sort here), so each (vertex, texel)'s S x S sub-texels are rotated into its frame once per S
 *     for all its views (a cache per S), keeping only those above the horizon (f_r max(n . w, 0) is 0 below).
 *     Returns 3 for a pair out of range or an S without its set.
 *
 * The BRDF (model, flags; transport_kernels.native_model): 0 Ashikhmin-Shirley 2000 eq. 4 (+ eq. 5's diffuse
 * term where rd != 0; flags bit 0 Fresnel, bit 1 diffuse), par = (nu, nv, rs, rd); 1 modified Phong, 2 Phong
 * in the reflection form (Ramamoorthi 2002 eq. 3.37: the lobe over cos theta_i), 3 normalised Blinn-Phong,
 * par = (s, ks, kd); 4 Lambertian, par = (kd); 5 Ward 1992 (isotropic or anisotropic), par = (ax, ay, rs, rd); 6 Ramamoorthi
 * 2002's microfacet model (eq. 5.34 over cos theta_i, as brdf.Microfacet), par = (sigma, ks). The formulas and their order of operations are prt_torch/brdf.py's
 * _eval (the half vector normalised by one division and three products); the power b^N by repeated squaring
 * for an integer exponent N <= 1024 (isotropic Ashikhmin-Shirley, Phong, Blinn-Phong: ipow_block), else
 * glibc's libmvec _ZGVdN4vv_pow 4 lanes at a time on the AVX2 path (lanes padded with 1^1), libm's pow
 * otherwise (the portable path): values within a few ulp of torch's (tests: relative 1e-12; 6.6e-14 measured
 * over the whole 10k default table). Ward and microfacet normalise the half vector as torch does, bit for bit (torch
 * 2.13's CPU norm is sqrt(fma(z, z, fma(y, y, x x))), then three divisions), so their exponent -- and the microfacet's
 * theta_h = acos(h_z), ill-conditioned near the normal -- is torch's to the bit; exp (and acos) 4 lanes at a time from
 * libmvec on the AVX2 path (_ZGVdN4v_exp; _ZGVdN4v_acos from glibc 2.35, libm's acos before), libm's otherwise.
 * f_r is 0 where wi_z <= 0 or wo_z <= 0, as BRDF.eval. Threads (OpenMP, `nthreads`): vertices (points) or
 * ranges of pairs (averages); each output element is computed by one thread the same way whatever the count. */

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#if defined(__AVX2__)
#include <immintrin.h>
__m256d _ZGVdN4vv_pow(__m256d x, __m256d y); /* glibc libmvec: pow, 4 doubles (AVX2) */
__m256d _ZGVdN4v_exp(__m256d x);                /* exp, 4 doubles (glibc 2.22) */
#if defined(__GLIBC__) && (__GLIBC__ > 2 || (__GLIBC__ == 2 && __GLIBC_MINOR__ >= 35))
#define PRT_MVEC_ACOS 1
__m256d _ZGVdN4v_acos(__m256d x);               /* acos, 4 doubles (glibc 2.35) */
#endif
#endif

typedef int64_t i64;

#define NPAR 4
/* pairs per unit of the averages' dynamic schedule (a shared machine stalls a static split at its slowest thread) */
#define AVG_BLOCK 512
#define PI 3.14159265358979323846

int prt_transport_points(i64 k, i64 J, i64 P, const double *wi, const double *wo, const double *W, double horizon, i64 na,
                         const i64 *ai, const i64 *aj, const i64 *ap, int model, int flags, const double *par, int out_dtype,
                         void *out, int nthreads);
int prt_transport_averages(i64 n, const i64 *iv, const i64 *jv, const i64 *pv, const i64 *sv, i64 k, i64 J, i64 P,
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

/* out[q] = exp(x[q]), q < n (n a multiple of 4) */
static void exp_block(i64 n, const double *x, double *o) {
    i64 q = 0;
#if defined(__AVX2__)
    for (; q + 4 <= n; q += 4) _mm256_storeu_pd(o + q, _ZGVdN4v_exp(_mm256_loadu_pd(x + q)));
#endif
    for (; q < n; q++) o[q] = exp(x[q]);
}

/* out[q] = acos(x[q]), q < n (n a multiple of 4) */
static void acos_block(i64 n, const double *x, double *o) {
    i64 q = 0;
#if defined(__AVX2__) && defined(PRT_MVEC_ACOS)
    for (; q + 4 <= n; q += 4) _mm256_storeu_pd(o + q, _ZGVdN4v_acos(_mm256_loadu_pd(x + q)));
#endif
    for (; q < n; q++) o[q] = acos(x[q]);
}

/* the half vector normalised as torch's h / h.norm(dim=-1).clamp_min(1e-300), bit for bit (the norm as torch 2.13's
 * CPU kernel: sqrt(fma(z, z, fma(y, y, x x))); three divisions) */
static inline void half_torch(double ix, double iy, double iz, double ox, double oy, double oz, double *h) {
    double hx = ix + ox, hy = iy + oy, hz = iz + oz;
    double nr = sqrt(fma(hz, hz, fma(hy, hy, hx * hx)));
    nr = nr > 1e-300 ? nr : 1e-300;
    h[0] = hx / nr; h[1] = hy / nr; h[2] = hz / nr;
}

/* o[q] = b[q]^N, q < n, for an integer N in [0, IPOW_MAX] by repeated squaring (per tile of 64 lanes a loop per bit, each
 * over the tile: vectorised). Squaring doubles a relative error, so x^N carries up to ~N/2 + log2 N ulp: 1.1e-13 at
 * N = 1024, 4e-15 at the default N = 40, within the 1e-12 the tests hold the kernel to; a fraction of pow's cost */
#define IPOW_MAX 1024
static void ipow_block(i64 n, const double *restrict b, i64 N, double *restrict o) {
    double x[64];
    for (i64 q0 = 0; q0 < n; q0 += 64) {
        i64 c = n - q0 < 64 ? n - q0 : 64;
        double *restrict r = o + q0;
        for (i64 q = 0; q < c; q++) { r[q] = 1.0; x[q] = b[q0 + q]; }
        for (i64 e = N; e; e >>= 1) {
            if (e & 1) for (i64 q = 0; q < c; q++) r[q] = r[q] * x[q];
            if (e > 1) for (i64 q = 0; q < c; q++) x[q] = x[q] * x[q];
        }
    }
}

/* the exponent as an integer N for ipow_block, or -1 */
static inline i64 int_exponent(double e) { return (e >= 0 && e <= IPOW_MAX && e == (double)(i64)e) ? (i64)e : -1; }

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
    if (model == 5) { /* Ward 1992: rd/pi + rs exp(-((hx/ax)^2 + (hy/ay)^2) / hz^2) / (4 pi ax ay sqrt(cos_i cos_o)) */
        const double ax = p[0], ay = p[1], rs = p[2], dp = p[3] / PI, c0 = 4 * PI * ax * ay; /* torch's ((4 pi) ax) ay */
        for (i64 q = 0; q < n4; q++) {
            double h[3];
            half_torch(wx[q], wy[q], wz[q], ox, oy, oz, h);
            double hz2 = h[2] * h[2];
            hz2 = hz2 > 1e-300 ? hz2 : 1e-300;
            double a = h[0] / ax, b = h[1] / ay;
            B[q] = -(a * a + b * b) / hz2;
            double cc = wz[q] * oz;
            C1[q] = c0 * sqrt(cc > 1e-300 ? cc : 1e-300);
        }
        exp_block(n4, B, PW);
        for (i64 q = 0; q < n; q++) {
            double v = dp + rs * PW[q] / C1[q];
            f[q] = (wz[q] > 0 && oz > 0) ? v : 0.0;
        }
        return;
    }
    if (model == 6) { /* microfacet (Ramamoorthi 2002 eq. 5.34): ks exp(-(theta_h/sigma)^2) / (4 pi sigma^2) / cos_i */
        const double sg = p[0], ks = p[1], c0 = 4 * PI * (sg * sg); /* torch's (4 pi) sigma**2 */
        for (i64 q = 0; q < n4; q++) {
            double h[3];
            half_torch(wx[q], wy[q], wz[q], ox, oy, oz, h);
            B[q] = h[2] < -1 ? -1 : (h[2] > 1 ? 1 : h[2]);
        }
        acos_block(n4, B, E);
        for (i64 q = 0; q < n4; q++) {
            double t = E[q] / sg;
            B[q] = -(t * t);
        }
        exp_block(n4, B, PW);
        for (i64 q = 0; q < n; q++) {
            double v = ks * PW[q] / c0 / (wz[q] > 1e-300 ? wz[q] : 1e-300);
            f[q] = (wz[q] > 0 && oz > 0) ? v : 0.0;
        }
        return;
    }
    if (model == 0) { /* Ashikhmin-Shirley eq. 4 (+ eq. 5) */
        const double nu = p[0], nv = p[1], rs = p[2], rd = p[3];
        const double C = sqrt((nu + 1) * (nv + 1)) / (8 * PI), fr = (flags & 1) ? 1.0 : 0.0;
        for (i64 q = 0; q < n4; q++) {
            double hx = wx[q] + ox, hy = wy[q] + oy, hz = wz[q] + oz;
            double nr = sqrt(hx * hx + hy * hy + hz * hz);
            double r = 1.0 / (nr > 1e-300 ? nr : 1e-300); /* one division, three products: h within an ulp of h / |h| */
            hx = hx * r; hy = hy * r; hz = hz * r;
            double kh = wx[q] * hx + wy[q] * hy + wz[q] * hz;
            kh = kh > 1e-300 ? kh : 1e-300;
            double mz = wz[q] > oz ? wz[q] : oz;
            mz = mz > 1e-300 ? mz : 1e-300;
            B[q] = hz < 0 ? 0 : (hz > 1 ? 1 : hz);
            C1[q] = kh * mz;
            C2[q] = rs + (1 - rs) * pow5(1 - kh) * fr; /* fr = 0: exactly rs */
        }
        i64 N = nu == nv ? int_exponent(nu) : -1; /* isotropic: the exponent is nu wherever sin(theta_h) > 0 (to an ulp) */
        if (N >= 0) ipow_block(n4, B, N, PW);
        else {
            for (i64 q = 0; q < n4; q++) { /* (N_u cos^2 phi_h + N_v sin^2 phi_h), as brdf.py, h normalised as above */
                double hx = wx[q] + ox, hy = wy[q] + oy, hz = wz[q] + oz;
                double nr = sqrt(hx * hx + hy * hy + hz * hz);
                double r = 1.0 / (nr > 1e-300 ? nr : 1e-300);
                double hx2 = (hx * r) * (hx * r), hy2 = (hy * r) * (hy * r), sin2 = hx2 + hy2;
                E[q] = sin2 > 1e-30 ? (nu * hx2 + nv * hy2) / sin2 : nu;
            }
            pow_block(n4, B, E, PW);
        }
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
    i64 N = int_exponent(sx);
    if (N >= 0) ipow_block(n4, B, N, PW); else pow_block(n4, B, E, PW);
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
    else ((_Float16 *)out)[at] = (_Float16)(float)v; /* through float, as torch's .to(float16) of a float64 */
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

/* the first index in [a, b) of the ascending x with x[q] >= v */
static i64 lower_bound(const i64 *x, i64 a, i64 b, i64 v) {
    while (a < b) {
        i64 mid = a + (b - a) / 2;
        if (x[mid] < v) a = mid + 1; else b = mid;
    }
    return a;
}

int prt_transport_points(i64 k, i64 J, i64 P, const double *wi, const double *wo, const double *W, double horizon, i64 na,
                         const i64 *ai, const i64 *aj, const i64 *ap, int model, int flags, const double *par, int out_dtype,
                         void *out, int nthreads) {
    if (!dtype_ok(out_dtype) || model < 0 || model > 6) return 1;
    for (i64 q = 0; q < na; q++) { /* the averaged pairs: in range and in (vertex, view, texel) order */
        if (ai[q] < 0 || ai[q] >= k || aj[q] < 0 || aj[q] >= J || ap[q] < 0 || ap[q] >= P) return 3;
        if (q && (ai[q] < ai[q - 1] || (ai[q] == ai[q - 1] && (aj[q] < aj[q - 1] || (aj[q] == aj[q - 1] && ap[q] <= ap[q - 1])))))
            return 4;
    }
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
                i64 qa = lower_bound(ai, 0, na, v), qe = lower_bound(ai, qa, na, v + 1); /* this vertex's averaged pairs */
                for (i64 j = 0; j < J; j++) {
                    const double *o = wo + 3 * (v * J + j);
                    while (qa < qe && aj[qa] < j) qa++;
                    if (!(o[2] > horizon) || !nv) continue; /* at or below the horizon (transport.HORIZON_EPS): zeros */
                    double *ex = vx, *ey = vy, *ez = vz, *ew = vw;
                    const i64 *ei = vi;
                    i64 n = nv;
                    if (qa < qe && aj[qa] == j) { /* the view's pairs the averages write are skipped (both lists ascend) */
                        n = 0;
                        for (i64 q = 0; q < nv; q++) {
                            while (qa < qe && aj[qa] == j && ap[qa] < vi[q]) qa++;
                            if (qa < qe && aj[qa] == j && ap[qa] == vi[q]) continue;
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

int prt_transport_averages(i64 n, const i64 *iv, const i64 *jv, const i64 *pv, const i64 *sv, i64 k, i64 J, i64 P,
                           const double *frames, const double *wo, const double *sd, const double *sw, const i64 *soff,
                           int model, int flags, const double *par, int out_dtype, void *out, int nthreads) {
    if (!dtype_ok(out_dtype) || model < 0 || model > 6) return 1;
    for (i64 q = 0; q < n; q++) {
        if (sv[q] < 1 || sv[q] > 8 || soff[sv[q]] < 0) return 3;
        if (iv[q] < 0 || iv[q] >= k || jv[q] < 0 || jv[q] >= J || pv[q] < 0 || pv[q] >= P) return 3;
    }
    /* the pairs in (vertex, texel) order (a stable counting sort): each one's sub-texels are rotated once for its views */
    i64 *order = malloc(sizeof(i64) * (size_t)(n + k * P + 1));
    if (!order) return 2;
    i64 *start = order + n;
    memset(start, 0, sizeof(i64) * (size_t)(k * P + 1));
    for (i64 q = 0; q < n; q++) start[iv[q] * P + pv[q] + 1]++;
    for (i64 c = 0; c < k * P; c++) start[c + 1] += start[c];
    for (i64 q = 0; q < n; q++) order[start[iv[q] * P + pv[q]]++] = q;
    int nth = nthreads > 0 ? nthreads : 1, err = 0;
    #pragma omp parallel num_threads(nth) reduction(| : err)
    {
        Scratch s;
        double *a[1 + 4 * 9]; /* f; per S, the kept sub-texels of the last (vertex, texel): x, y, z, share */
        if (alloc_scratch(&s, a, 1 + 4 * 9, 68)) err = 1;
        else {
            double *f = a[0];
            #pragma omp for schedule(dynamic, 1)
            for (i64 blk = 0; blk < (n + AVG_BLOCK - 1) / AVG_BLOCK; blk++) {
                i64 q1 = (blk + 1) * AVG_BLOCK < n ? (blk + 1) * AVG_BLOCK : n, key[9], m[9];
                for (int S = 0; S < 9; S++) key[S] = -1;
                for (i64 r = blk * AVG_BLOCK; r < q1; r++) {
                    i64 q = order[r], i = iv[q], p = pv[q], S = sv[q], S2 = S * S;
                    double *x = a[1 + 4 * S], *y = a[2 + 4 * S], *z = a[3 + 4 * S], *w = a[4 + 4 * S];
                    if (key[S] != i * P + p) { /* rotate this (vertex, texel)'s S x S sub-texels into its frame */
                        const double *F = frames + 9 * i, *d = sd + 3 * (soff[S] + p * S2), *a_s = sw + soff[S] + p * S2;
                        i64 c = 0;
                        for (i64 u = 0; u < S2; u++) {
                            double dx = d[3 * u], dy = d[3 * u + 1], dz = d[3 * u + 2];
                            double lz = F[6] * dx + F[7] * dy + F[8] * dz;
                            if (!(lz > 0)) continue; /* below the horizon: f_r max(n . w, 0) = 0 */
                            x[c] = F[0] * dx + F[1] * dy + F[2] * dz; y[c] = F[3] * dx + F[4] * dy + F[5] * dz; z[c] = lz;
                            w[c] = a_s[u]; c++;
                        }
                        for (i64 u = c; u < ((c + 3) & ~(i64)3); u++) { x[u] = 0; y[u] = 0; z[u] = 1; }
                        key[S] = i * P + p; m[S] = c;
                    }
                    const double *o = wo + 3 * (i * J + jv[q]);
                    double acc = 0.0;
                    if (m[S]) {
                        eval_block(model, flags, par + NPAR * i, m[S], x, y, z, o[0], o[1], o[2], f, &s);
                        for (i64 u = 0; u < m[S]; u++) acc += f[u] * z[u] * w[u];
                    }
                    store(out, out_dtype, i * J * P + jv[q] * P + p, acc);
                }
            }
            free(s.b);
        }
    }
    free(order);
    return err ? 2 : 0;
}
