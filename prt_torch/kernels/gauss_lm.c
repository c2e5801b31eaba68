/* gauss_lm.c: the Gaussian codec's fit (Green 2005 §2.2, eq. 2.2-2.6): the batched Levenberg-Marquardt loop of
 * prt_torch/codecs/gaussian/fit.py (_lm_loop) in one compiled pass per iteration and function.
 *
 * Per function f of a batch (row f of T [B, P]) with N lobes (log w a, log sigma ls, unit mean mu):
 *   term_kp = w_k c(lam_k) exp(lam_k (mu_k . w_p - 1)),  lam = sigma^-2,  c(lam) = lam / (2 pi (1 - e^-2lam))
 *   r_p = sum_k term_kp - T_p,   E = sum_p dw_p r_p^2                                   (eq. 2.3)
 *       + en (beta |mu - mu_tgt|^2 + gamma (sigma - sigma_tgt)^2)                     (eq. 2.4-2.5)
 *       + en delta sum_pairs sum_q max(-<dmu_x, dmu_s>, 0)^3                             (eq. 2.6)
 * The Gauss-Newton system in (log w, log sigma, u, v) per lobe from per-texel moments:
 *   JtJ_kl = A_k (sum_p dw_p term_k term_l (1, w)(1, w)^T) A_l^T,  Jtr_k = A_k sum_p dw_p term_k r_p (1, w)
 * (Problem.normal_equations' derivation), the view and spatial terms added to it as there, an active
 * set at the width/weight bounds, damping lm * diag(JtJ), one Cholesky solve (float64), the step
 * (means re-centred on the sphere) and its objective: accepted when it does not rise.
 *
 * Iteration structure as _lm_loop: each iteration (1) moves the zero functions to the minimiser of
 * their view terms alone (the neighbours' mean), (2) takes every active function's view targets from
 * the iterate at its start (block Jacobi), (3) makes one damped step per active function: up to `tries` trial
 * solves of its normal equations, each rejected trial retried at 5x the damping (Marquardt's inner loop; issue 42
 * §2: with one trial a third of the iterations of 3-lobe fits were spent on rejected steps). The texel
 * sums run in float32 over 8 lanes (AVX2 with -march=native; plain C otherwise), the 4N x 4N system
 * in float64. exp is a Cephes-style polynomial (relative error ~2e-7, as expf) so the loops
 * vectorise without libm. */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

#define LOG_W_MIN (-23.025850929940457) /* log 1e-10 (fit._LOG_W_MIN) */
#define MAXN 16                         /* codecs.gaussian.MAX_LOBES */
#define PI_D 3.14159265358979323846

static inline float fexp(float x) {
    float xc = x < -87.0f ? -87.0f : (x > 88.0f ? 88.0f : x);
    float n = floorf(xc * 1.44269504088896341f + 0.5f);
    float r = xc - n * 0.693359375f + n * 2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    union { int32_t i; float f; } e;
    e.i = ((int32_t)n + 127) << 23;
    return x < -87.0f ? 0.0f : p * e.f;
}

typedef struct {
    int64_t B, N, P, J, R, Q, npairs;
    const float *T, *dirs, *sa, *en, *sb;
    const int64_t *vn;
    const int32_t *pairs;
    double beta, gamma, delta, lsmin, lsmax, smin, smax, tol;
    int64_t tries;
} ctx_t;

static void tangents(const float *m, float *t1, float *t2) {
    /* fit.tangents: the axis of m's smallest |component|, t1 = m x axis normalised, t2 = m x t1 */
    float ax[3] = {0, 0, 0};
    int i = 0;
    float am = fabsf(m[0]);
    if (fabsf(m[1]) < am) { i = 1; am = fabsf(m[1]); }
    if (fabsf(m[2]) < am) i = 2;
    ax[i] = 1.0f;
    t1[0] = m[1] * ax[2] - m[2] * ax[1];
    t1[1] = m[2] * ax[0] - m[0] * ax[2];
    t1[2] = m[0] * ax[1] - m[1] * ax[0];
    float nn = sqrtf(t1[0] * t1[0] + t1[1] * t1[1] + t1[2] * t1[2]);
    nn = nn > 1e-12f ? nn : 1e-12f;
    t1[0] /= nn; t1[1] /= nn; t1[2] /= nn;
    t2[0] = m[1] * t1[2] - m[2] * t1[1];
    t2[1] = m[2] * t1[0] - m[0] * t1[2];
    t2[2] = m[0] * t1[1] - m[1] * t1[0];
}

static inline float sg_norm(float lam) {
    /* lighting.prefilter.sg_normaliser */
    if (lam < 1e-6f) return (float)(1.0 / (4.0 * PI_D)) * (1.0f + lam);
    return lam / ((float)(2.0 * PI_D) * (-expm1f(-2.0f * lam)));
}

/* term [N, P], r [P] of function f at (a, ls, mu); returns E (data + view + spatial terms). */
static double evaluate(const ctx_t *c, int64_t f, const float *a, const float *ls, const float *mu, const float *tm,
                       const float *ts, float *restrict term, float *restrict r, float *lam_out) {
    const int64_t N = c->N, P = c->P;
    const float *T = c->T + f * P, *dx = c->dirs, *dy = c->dirs + P, *dz = c->dirs + 2 * P, *sa = c->sa;
    for (int64_t k = 0; k < N; k++) {
        float lam = expf(-2.0f * ls[k]);
        float bias = a[k] + logf(sg_norm(lam)) - lam;
        float mx = mu[3 * k] * lam, my = mu[3 * k + 1] * lam, mz = mu[3 * k + 2] * lam;
        float *restrict tk = term + k * P;
#pragma omp simd
        for (int64_t p = 0; p < P; p++) tk[p] = fexp(mx * dx[p] + my * dy[p] + mz * dz[p] + bias);
        if (lam_out) lam_out[k] = lam;
    }
    float e = 0.0f;
    const float *restrict t0 = term;
#pragma omp simd
    for (int64_t p = 0; p < P; p++) r[p] = t0[p] - T[p];
    for (int64_t k = 1; k < N; k++) {
        const float *restrict tk = term + k * P;
#pragma omp simd
        for (int64_t p = 0; p < P; p++) r[p] += tk[p];
    }
#pragma omp simd reduction(+ : e)
    for (int64_t p = 0; p < P; p++) e += r[p] * r[p] * sa[p];
    double E = e;
    double en = c->en[f];
    if (c->beta > 0 && tm) {
        double vm = 0, vs = 0;
        for (int64_t k = 0; k < N; k++) {
            for (int i = 0; i < 3; i++) vm += ((double)mu[3 * k + i] - tm[3 * k + i]) * ((double)mu[3 * k + i] - tm[3 * k + i]);
            double s = expf(ls[k]) - ts[k];
            vs += s * s;
        }
        E += en * (c->beta * vm + c->gamma * vs);
    }
    if (c->delta > 0 && c->sb && c->npairs) {
        const float *sb = c->sb + f * c->npairs * c->Q * 3;
        double S = 0;
        for (int64_t n = 0; n < c->npairs; n++) {
            int i = c->pairs[2 * n], j = c->pairs[2 * n + 1];
            float dx[3] = {mu[3 * i] - mu[3 * j], mu[3 * i + 1] - mu[3 * j + 1], mu[3 * i + 2] - mu[3 * j + 2]};
            for (int64_t q = 0; q < c->Q; q++) {
                const float *b = sb + (n * c->Q + q) * 3;
                float v = -(dx[0] * b[0] + dx[1] * b[1] + dx[2] * b[2]);
                if (v > 0) S += (double)v * v * v;
            }
        }
        E += en * c->delta * S;
    }
    return E;
}

/* the view targets of function f (fit._lm_batch.targets): per lobe the mean over its R neighbouring
 * views of the nearest lobe's mean and width. */
static void targets(const ctx_t *c, int64_t f, const float *ls, const float *mu, float *tm, float *ts) {
    const int64_t N = c->N, R = c->R, J = c->J;
    const int64_t base = (f / J) * J, view = f % J;
    const float *mf = mu + f * N * 3;
    for (int64_t k = 0; k < N; k++) { tm[3 * k] = tm[3 * k + 1] = tm[3 * k + 2] = 0.0f; ts[k] = 0.0f; }
    for (int64_t q = 0; q < R; q++) {
        int64_t g = base + c->vn[view * R + q];
        const float *mg = mu + g * N * 3;
        for (int64_t k = 0; k < N; k++) {
            int64_t best = 0;
            if (N > 1) {
                float bd = -INFINITY;
                for (int64_t m = 0; m < N; m++) {
                    float dd = mf[3 * k] * mg[3 * m] + mf[3 * k + 1] * mg[3 * m + 1] + mf[3 * k + 2] * mg[3 * m + 2];
                    if (dd > bd) { bd = dd; best = m; }
                }
            }
            tm[3 * k] += mg[3 * best]; tm[3 * k + 1] += mg[3 * best + 1]; tm[3 * k + 2] += mg[3 * best + 2];
            ts[k] += expf(ls[g * N + best]);
        }
    }
    for (int64_t k = 0; k < N; k++) { tm[3 * k] /= R; tm[3 * k + 1] /= R; tm[3 * k + 2] /= R; ts[k] /= R; }
}

/* Gauss-Newton normal equations of f at its current terms: JtJ [4N, 4N], Jtr [4N] (float64). */
static void normal_equations(const ctx_t *c, int64_t f, const float *ls, const float *mu, const float *tm, const float *ts,
                             const float *term, const float *r, const float *lam, double *JtJ, double *Jtr) {
    const int64_t N = c->N, P = c->P, n4 = 4 * N;
    const float *dx = c->dirs, *dy = c->dirs + c->P, *dz = c->dirs + 2 * c->P, *sa = c->sa;
    double A[MAXN][4][4], M[4][4], Mt[4][4];
    float t1[MAXN][3], t2[MAXN][3];
    for (int64_t k = 0; k < N; k++) {
        tangents(mu + 3 * k, t1[k], t2[k]);
        double x = lam[k];
        double dlogc = x < 1e-3 ? 1 - x / 3 : 1 / x - 2 / expm1(2 * x);
        memset(A[k], 0, sizeof(A[k]));
        A[k][0][0] = 1.0;
        A[k][1][0] = -2 * x * (dlogc - 1);
        for (int i = 0; i < 3; i++) {
            A[k][1][1 + i] = -2 * x * mu[3 * k + i];
            A[k][2][1 + i] = x * t1[k][i];
            A[k][3][1 + i] = x * t2[k][i];
        }
    }
    for (int64_t k = 0; k < N; k++) {
        const float *tk = term + k * P;
        /* Jtr_k = A_k sum_p dw term_k r (1, w) */
        float v0 = 0, v1 = 0, v2 = 0, v3 = 0;
#pragma omp simd reduction(+ : v0, v1, v2, v3)
        for (int64_t p = 0; p < P; p++) {
            float g = sa[p] * tk[p] * r[p];
            v0 += g; v1 += g * dx[p]; v2 += g * dy[p]; v3 += g * dz[p];
        }
        double v[4] = {v0, v1, v2, v3};
        for (int i = 0; i < 4; i++) {
            double s = 0;
            for (int j = 0; j < 4; j++) s += A[k][i][j] * v[j];
            Jtr[4 * k + i] = s;
        }
        for (int64_t l = k; l < N; l++) {
            const float *tl = term + l * P;
            float s0 = 0, sx = 0, sy = 0, sz = 0, sxx = 0, sxy = 0, sxz = 0, syy = 0, syz = 0, szz = 0;
#pragma omp simd reduction(+ : s0, sx, sy, sz, sxx, sxy, sxz, syy, syz, szz)
            for (int64_t p = 0; p < P; p++) {
                float w = sa[p] * tk[p] * tl[p];
                float x = dx[p], y = dy[p], z = dz[p];
                float wx = w * x, wy = w * y, wz = w * z;
                s0 += w; sx += wx; sy += wy; sz += wz;
                sxx += wx * x; sxy += wx * y; sxz += wx * z; syy += wy * y; syz += wy * z; szz += wz * z;
            }
            double m[4][4] = {{s0, sx, sy, sz}, {sx, sxx, sxy, sxz}, {sy, sxy, syy, syz}, {sz, sxz, syz, szz}};
            memcpy(M, m, sizeof(M));
            for (int i = 0; i < 4; i++)  /* Mt = M A_l^T */
                for (int j = 0; j < 4; j++) {
                    double s = 0;
                    for (int q = 0; q < 4; q++) s += M[i][q] * A[l][j][q];
                    Mt[i][j] = s;
                }
            for (int i = 0; i < 4; i++)
                for (int j = 0; j < 4; j++) {
                    double s = 0;
                    for (int q = 0; q < 4; q++) s += A[k][i][q] * Mt[q][j];
                    JtJ[(4 * k + i) * n4 + 4 * l + j] = s;
                    JtJ[(4 * l + j) * n4 + 4 * k + i] = s;
                }
        }
    }
    double en = c->en[f];
    if (c->beta > 0 && tm) {
        for (int64_t k = 0; k < N; k++) {
            int64_t iu = 4 * k + 2, iv = 4 * k + 3, is = 4 * k + 1;
            double dm[3] = {(double)mu[3 * k] - tm[3 * k], (double)mu[3 * k + 1] - tm[3 * k + 1], (double)mu[3 * k + 2] - tm[3 * k + 2]};
            JtJ[iu * n4 + iu] += c->beta * en;
            JtJ[iv * n4 + iv] += c->beta * en;
            Jtr[iu] += c->beta * en * (t1[k][0] * dm[0] + t1[k][1] * dm[1] + t1[k][2] * dm[2]);
            Jtr[iv] += c->beta * en * (t2[k][0] * dm[0] + t2[k][1] * dm[1] + t2[k][2] * dm[2]);
            double s = expf(ls[k]);
            JtJ[is * n4 + is] += c->gamma * en * s * s;
            Jtr[is] += c->gamma * en * s * (s - ts[k]);
        }
    }
    if (c->delta > 0 && c->sb && c->npairs) {
        const float *sb = c->sb + f * c->npairs * c->Q * 3;
        double sd = sqrt(c->delta);
        for (int64_t n = 0; n < c->npairs; n++) {
            int i = c->pairs[2 * n], j = c->pairs[2 * n + 1];
            float dx[3] = {mu[3 * i] - mu[3 * j], mu[3 * i + 1] - mu[3 * j + 1], mu[3 * i + 2] - mu[3 * j + 2]};
            int64_t ids[4] = {4 * i + 2, 4 * i + 3, 4 * j + 2, 4 * j + 3};
            for (int64_t q = 0; q < c->Q; q++) {
                const float *b = sb + (n * c->Q + q) * 3;
                float fv = -(dx[0] * b[0] + dx[1] * b[1] + dx[2] * b[2]);
                fv = fv > 0 ? fv : 0;
                double coef = 1.5 * sd * sqrt((double)fv), res = sd * pow((double)fv, 1.5);
                double g[4] = {-(t1[i][0] * b[0] + t1[i][1] * b[1] + t1[i][2] * b[2]) * coef,
                               -(t2[i][0] * b[0] + t2[i][1] * b[1] + t2[i][2] * b[2]) * coef,
                               (t1[j][0] * b[0] + t1[j][1] * b[1] + t1[j][2] * b[2]) * coef,
                               (t2[j][0] * b[0] + t2[j][1] * b[1] + t2[j][2] * b[2]) * coef};
                for (int u = 0; u < 4; u++) {
                    Jtr[ids[u]] += en * g[u] * res;
                    for (int w = 0; w < 4; w++) JtJ[ids[u] * n4 + ids[w]] += en * g[u] * g[w];
                }
            }
        }
    }
}

/* In-place Cholesky of the n x n SPD matrix A (lower), then solve A x = b into x; 0 when A is not
 * positive definite (torch.linalg.cholesky_ex's info != 0: the step is zero). */
static int chol_solve(double *A, int64_t n, const double *b, double *x) {
    for (int64_t j = 0; j < n; j++) {
        double s = A[j * n + j];
        for (int64_t k = 0; k < j; k++) s -= A[j * n + k] * A[j * n + k];
        if (!(s > 0)) return 0;
        double l = sqrt(s);
        A[j * n + j] = l;
        for (int64_t i = j + 1; i < n; i++) {
            double t = A[i * n + j];
            for (int64_t k = 0; k < j; k++) t -= A[i * n + k] * A[j * n + k];
            A[i * n + j] = t / l;
        }
    }
    for (int64_t i = 0; i < n; i++) {
        double t = b[i];
        for (int64_t k = 0; k < i; k++) t -= A[i * n + k] * x[k];
        x[i] = t / A[i * n + i];
    }
    for (int64_t i = n - 1; i >= 0; i--) {
        double t = x[i];
        for (int64_t k = i + 1; k < n; k++) t -= A[k * n + i] * x[k];
        x[i] = t / A[i * n + i];
    }
    return 1;
}

/* One damped step of function f (from _lm_loop's body); updates a, ls, mu, lm, conv of f. */
static void lm_step(const ctx_t *c, int64_t f, float *a_all, float *ls_all, float *mu_all, double *lm_all, uint8_t *conv,
                    const float *tm, const float *ts, float *term, float *r, double *JtJ, double *Jtr, double *step, double *Afac) {
    const int64_t N = c->N, n4 = 4 * N;
    float *a = a_all + f * N, *ls = ls_all + f * N, *mu = mu_all + f * N * 3;
    float lam[MAXN];
    double E0 = evaluate(c, f, a, ls, mu, tm, ts, term, r, lam);
    normal_equations(c, f, ls, mu, tm, ts, term, r, lam, JtJ, Jtr);
    /* active set: a width or weight at its bound whose gradient points outward is frozen */
    const float lsmin = (float)c->lsmin, lsmax = (float)c->lsmax, amin = (float)LOG_W_MIN;
    for (int64_t k = 0; k < N; k++) {
        int fz[2];
        fz[1] = (ls[k] <= lsmin + 1e-6f && Jtr[4 * k + 1] > 0) || (ls[k] >= lsmax - 1e-6f && Jtr[4 * k + 1] < 0);
        fz[0] = a[k] <= amin + 1e-6f && Jtr[4 * k] > 0;
        for (int q = 0; q < 2; q++) {
            if (!fz[q]) continue;
            int64_t i = 4 * k + q;
            for (int64_t j = 0; j < n4; j++) JtJ[i * n4 + j] = JtJ[j * n4 + i] = 0.0;
            JtJ[i * n4 + i] = 1.0;
            Jtr[i] = 0.0;
        }
    }
    double dmax = 0, lmf = lm_all[f];
    for (int64_t i = 0; i < n4; i++) dmax = JtJ[i * n4 + i] > dmax ? JtJ[i * n4 + i] : dmax;
    double jit = 1e-12 * (1 + dmax);
    double mrhs[4 * MAXN];
    for (int64_t i = 0; i < n4; i++) mrhs[i] = -Jtr[i];
    /* up to c->tries damped solves of the same system (Marquardt's inner loop): a rejected trial is retried
     * at 5x the damping without re-forming JtJ, so an iteration ends with an accepted step unless all fail */
    double E1 = INFINITY, smax = 0;
    int acc = 0;
    float a2[MAXN], ls2[MAXN], mu2[3 * MAXN];
    for (int64_t t = 0; t < c->tries; t++) {
        if (t) lmf = lmf * 5 > 1e12 ? 1e12 : lmf * 5;
        memcpy(Afac, JtJ, sizeof(double) * n4 * n4);
        for (int64_t i = 0; i < n4; i++) Afac[i * n4 + i] += lmf * JtJ[i * n4 + i] + jit;
        if (!chol_solve(Afac, n4, mrhs, step))
            for (int64_t i = 0; i < n4; i++) step[i] = 0.0;
        smax = 0;
        for (int64_t i = 0; i < n4; i++) {
            step[i] = step[i] < -2.0 ? -2.0 : (step[i] > 2.0 ? 2.0 : step[i]);
            smax = fabs(step[i]) > smax ? fabs(step[i]) : smax;
        }
        for (int64_t k = 0; k < N; k++) {
            float t1[3], t2[3];
            tangents(mu + 3 * k, t1, t2);
            float d0 = (float)step[4 * k], d1 = (float)step[4 * k + 1], d2 = (float)step[4 * k + 2], d3 = (float)step[4 * k + 3];
            float av = a[k] + d0, lv = ls[k] + d1;
            a2[k] = av < amin ? amin : (av > 60.0f ? 60.0f : av);
            ls2[k] = lv < lsmin ? lsmin : (lv > lsmax ? lsmax : lv);
            float m[3], nn = 0;
            for (int i = 0; i < 3; i++) { m[i] = mu[3 * k + i] + d2 * t1[i] + d3 * t2[i]; nn += m[i] * m[i]; }
            nn = sqrtf(nn);
            nn = nn > 1e-12f ? nn : 1e-12f;
            for (int i = 0; i < 3; i++) mu2[3 * k + i] = m[i] / nn;
        }
        E1 = evaluate(c, f, a2, ls2, mu2, tm, ts, term, r, NULL);
        acc = E1 <= E0 && isfinite(E1);
        if (acc || lmf >= 1e12) break;
    }
    if (acc) {
        memcpy(a, a2, N * sizeof(float));
        memcpy(ls, ls2, N * sizeof(float));
        memcpy(mu, mu2, 3 * N * sizeof(float));
    }
    lmf = acc ? lmf / 3 : lmf * 5;
    lmf = lmf < 1e-9 ? 1e-9 : (lmf > 1e12 ? 1e12 : lmf);
    lm_all[f] = lmf;
    int small = fabs(E0 - E1) <= c->tol * fabs(E0) + 1e-14 || smax < 1e-4;
    conv[f] = (acc && small) || lmf >= 1e12 || E0 <= 1e-14;
}

/* The whole loop (fit._lm_loop's contract): a, ls [B, N], mu [B, N, 3] float32 updated in place; conv [B]
 * (1 = converged or not optimised; updated), z [B] (1 = zero function), T [B, P], dirs [3, P] (x, y, z rows), sa [P],
 * en [B] (sum_p dw T^2), vn [J, R] int64 view neighbours (R = 0: no view terms), sb [B, npairs, Q, 3]
 * or NULL, pairs [npairs, 2] int32. Returns the iterations run (as _lm_loop's `it`); -1: bad sizes, -2: out of memory. */
int prt_gauss_lm_loop(int64_t B, int64_t N, int64_t P, int64_t J, int64_t R, int64_t Q, int64_t npairs, const float *T,
                          const float *dirs, const float *sa, const float *en, const int64_t *vn, const float *sb,
                          const int32_t *pairs, double beta, double gamma, double delta, double lsmin, double lsmax,
                          double smin, double smax, double tol, int64_t max_iter, int64_t tries, float *a, float *ls, float *mu,
                          uint8_t *conv, const uint8_t *z, int nthreads) {
    if (N < 1 || N > MAXN || P < 1 || B < 1 || tries < 1) return -1;
    ctx_t c = {B, N, P, J, R, Q, npairs, T, dirs, sa, en, sb, vn, pairs, beta, gamma, delta, lsmin, lsmax, smin, smax, tol, tries};
    const int views = beta > 0 && R > 0;
    float *tm = malloc(sizeof(float) * B * N * 3), *ts = malloc(sizeof(float) * B * N);
    double *lm = malloc(sizeof(double) * B);
    int64_t *act = malloc(sizeof(int64_t) * B), *zi = malloc(sizeof(int64_t) * B);
    nthreads = nthreads < 1 ? 1 : nthreads;
    const int64_t n4 = 4 * N, fper = (N + 1) * P, dper = 2 * n4 * n4 + 2 * n4;
    float *fscr = malloc(sizeof(float) * fper * nthreads);
    double *dscr = malloc(sizeof(double) * dper * nthreads);
    if (!tm || !ts || !lm || !act || !zi || !fscr || !dscr) {
        free(tm); free(ts); free(lm); free(act); free(zi); free(fscr); free(dscr);
        return -2;
    }
    int64_t nz = 0;
    for (int64_t f = 0; f < B; f++) { lm[f] = 1e-3; if (z[f]) zi[nz++] = f; }
    int64_t it = 0;
    for (it = 1; it <= max_iter; it++) {
        if (views && nz) {  /* zero functions: the minimiser of M + V alone (eq. 2.4-2.5), all from the same iterate */
#pragma omp parallel for num_threads(nthreads) schedule(static)
            for (int64_t i = 0; i < nz; i++) targets(&c, zi[i], ls, mu, tm + zi[i] * N * 3, ts + zi[i] * N);
#pragma omp parallel for num_threads(nthreads) schedule(static)
            for (int64_t i = 0; i < nz; i++) {
                int64_t f = zi[i];
                for (int64_t k = 0; k < N; k++) {
                    float *m = tm + (f * N + k) * 3;
                    float nn = sqrtf(m[0] * m[0] + m[1] * m[1] + m[2] * m[2]);
                    nn = nn > 1e-12f ? nn : 1e-12f;
                    for (int q = 0; q < 3; q++) mu[(f * N + k) * 3 + q] = m[q] / nn;
                    float s = ts[f * N + k];
                    s = s < (float)smin ? (float)smin : (s > (float)smax ? (float)smax : s);
                    ls[f * N + k] = logf(s);
                }
            }
        }
        int64_t na = 0;
        for (int64_t f = 0; f < B; f++) if (!conv[f]) act[na++] = f;
        if (na == 0) break;
        if (views) {
#pragma omp parallel for num_threads(nthreads) schedule(static)
            for (int64_t i = 0; i < na; i++) targets(&c, act[i], ls, mu, tm + act[i] * N * 3, ts + act[i] * N);
        }
#pragma omp parallel for num_threads(nthreads) schedule(dynamic, 16)
        for (int64_t i = 0; i < na; i++) {
            int64_t f = act[i], th = 0;
#ifdef _OPENMP
            th = omp_get_thread_num();
#endif
            float *term = fscr + th * fper;
            double *work = dscr + th * dper;
            lm_step(&c, f, a, ls, mu, lm, conv, views ? tm + f * N * 3 : NULL, views ? ts + f * N : NULL, term, term + N * P,
                    work, work + n4 * n4, work + n4 * n4 + n4, work + n4 * n4 + 2 * n4);
        }
    }
    if (it > max_iter) it = max_iter;
    free(tm); free(ts); free(lm); free(act); free(zi); free(fscr); free(dscr);
    return (int)it;
}

/* The objective E [B], JtJ [B, 4N, 4N] and Jtr [B, 4N] (float64) of each function at the given
 * parameters and view targets (tm [B, N, 3], ts [B, N], or NULL: no view terms), before any active
 * set or damping: the quantities each step of prt_gauss_lm_loop solves with (tests compare them with
 * fit.Problem and with finite differences). Arguments as prt_gauss_lm_loop's. Returns 0; -1 bad sizes,
 * -2 out of memory. */
int prt_gauss_normal_equations(int64_t B, int64_t N, int64_t P, int64_t Q, int64_t npairs, const float *T, const float *dirs,
                               const float *sa, const float *en, const float *sb, const int32_t *pairs, double beta, double gamma,
                               double delta, const float *a, const float *ls, const float *mu, const float *tm, const float *ts,
                               double *E, double *JtJ, double *Jtr) {
    if (N < 1 || N > MAXN || P < 1 || B < 0) return -1;
    ctx_t c = {B, N, P, 1, 0, Q, npairs, T, dirs, sa, en, sb, NULL, pairs, beta, gamma, delta, 0, 0, 0, 0, 0, 1};
    float *term = malloc(sizeof(float) * (N + 1) * P);
    if (!term) return -2;
    const int64_t n4 = 4 * N;
    for (int64_t f = 0; f < B; f++) {
        float lam[MAXN];
        const float *tmf = tm ? tm + f * N * 3 : NULL, *tsf = tm ? ts + f * N : NULL;
        E[f] = evaluate(&c, f, a + f * N, ls + f * N, mu + f * N * 3, tmf, tsf, term, term + N * P, lam);
        normal_equations(&c, f, ls + f * N, mu + f * N * 3, tmf, tsf, term, term + N * P, lam, JtJ + f * n4 * n4, Jtr + f * n4);
    }
    free(term);
    return 0;
}

/* Peaks and moments (fit._init_lobes with one lobe; Green §2.2's initialisation): for each function
 * f of R [B, P] (float32, >= 0 where it matters) the lobe at the centroid of the contiguous
 * half-maximum cap around its largest texel: c_out = the largest cos to the peak among texels below
 * half the peak (-1 if none), the cap = texels with cos > c_out, c_in = their smallest cos (1 if
 * none); sigma = sqrt((1 - (c_in + c_out) / 2) / ln 2) within [smin, smax] (1 - cos = ln2 sigma^2 at
 * half maximum), mu = the cap's first moment sum dw max(R, 0) w normalised (the peak direction if it
 * vanishes), w = max(peak, 0) / max(exp(lam (mu . w_peak - 1)), 1/2) / c(lam). dirs [3, P] as
 * prt_gauss_lm_loop's. Writes w [B], mu [B, 3], sigma [B]. Returns 0, or -1 for bad sizes. */
int prt_gauss_peaks(int64_t B, int64_t P, const float *R, const float *dirs, const float *sa, double smin, double smax, float *w,
                    float *mu, float *sigma, int nthreads) {
    if (B < 0 || P < 1) return -1;
    const float *dx = dirs, *dy = dirs + P, *dz = dirs + 2 * P;
    nthreads = nthreads < 1 ? 1 : nthreads;
#pragma omp parallel for num_threads(nthreads) schedule(static)
    for (int64_t f = 0; f < B; f++) {
        const float *r = R + f * P;
        int64_t p = 0;
        float peak = r[0];
        for (int64_t q = 1; q < P; q++)
            if (r[q] > peak) { peak = r[q]; p = q; }
        const float px = dx[p], py = dy[p], pz = dz[p], half = 0.5f * peak;
        float c_out = -1.0f;
        for (int64_t q = 0; q < P; q++) {
            float c = px * dx[q] + py * dy[q] + pz * dz[q];
            if (!(r[q] >= half) && c > c_out) c_out = c;
        }
        float c_in = 1.0f, cx = 0, cy = 0, cz = 0;
        for (int64_t q = 0; q < P; q++) {
            float c = px * dx[q] + py * dy[q] + pz * dz[q];
            if (c > c_out + 1e-6f) {
                if (c < c_in) c_in = c;
                float v = (r[q] > 0 ? r[q] : 0.0f) * sa[q];
                cx += v * dx[q]; cy += v * dy[q]; cz += v * dz[q];
            }
        }
        float omc = 0.5f * ((1 - c_out) + (1 - c_in));
        float s = sqrtf(omc / 0.69314718055994531f);
        s = s < (float)smin ? (float)smin : (s > (float)smax ? (float)smax : s);
        float cn = sqrtf(cx * cx + cy * cy + cz * cz), m[3];
        if (cn > 1e-30f) { m[0] = cx / cn; m[1] = cy / cn; m[2] = cz / cn; }
        else { m[0] = px; m[1] = py; m[2] = pz; }
        float lam = 1.0f / (s * s);
        float off = expf(lam * (m[0] * px + m[1] * py + m[2] * pz - 1.0f));
        off = off > 0.5f ? off : 0.5f;
        w[f] = (peak > 0 ? peak : 0.0f) / off / sg_norm(lam);
        mu[3 * f] = m[0]; mu[3 * f + 1] = m[1]; mu[3 * f + 2] = m[2];
        sigma[f] = s;
    }
    return 0;
}
