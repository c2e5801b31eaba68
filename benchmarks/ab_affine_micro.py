"""Paired A/B of two affine point kernels in a bare C harness (no Python in the timed loop).

    .venv/bin/python benchmarks/ab_affine_micro.py                  # HEAD vs the working tree
    .venv/bin/python benchmarks/ab_affine_micro.py --base 6cc67b3~1 --test HEAD --rounds 8

``benchmarks/ab_kernels.py`` times whole ``relight`` calls (Python, the constants, the kernel);
this times the point kernels alone, as ``benchmarks/ab_sg_micro.py`` does the Gaussian lookups:
each revision's kernel sources and flags (as ab_kernels reads them) are compiled with a small
``main`` into a program of its own, which calls, on one thread, with the same data for both:

* ``taps``: ``prt_affine_taps`` of MRT-PCA with 16 vectors (one cluster, no mean, constants
  ``[1, 49, 3, 16]``), four bilinear tent taps of a 7×7 grid per point (Lehtinen & Kautz 2003
  eq. (13)) — ``bench_relight``'s "mrt_pca 16 taps" row;
* ``rows``: ``prt_affine_rows`` of CPCA 64×4 of diffuse vectors (uint8 labels, weights rows of 4,
  constants ``[64, 5, 8]``, RGB rows of 3 floats) — its "cpca static 64x4 (diffuse)" row;
* ``dense``: ``prt_affine_dense`` of CPCA 256×8 with a dense view of 24 rows (Sloan 2003 §3.1; uint8 labels, weights
  rows of 8, constants ``[256, 9, 3, 24]``), visited cluster by cluster within blocks of 8192 points from codes stored
  in that order, the view rows and outputs scattered, as ``AffineCodec`` plans it — its "cpca static 256x8 dense" row;

each ``--points`` points (default 50 000, as bench_relight), timed by the thread's CPU time
(``CLOCK_THREAD_CPUTIME_ID``: the time other processes hold the core is not counted), the median
of ``--reps`` calls after one that warms the caches. The two programs run in alternation,
``--rounds`` times each; the report gives each side's median of the per-round medians in ns per
point, the median and range of the round-by-round ratios (base / test: > 1, test faster) and
whether the two results' checksums (a sum of the outputs' bits) agree — they must, for a change
meant to keep the arithmetic. The changes of issue 42 §4 on AMD Zen 3 (docs/codecs_log.md) were
found and measured with it (``--out reports/benchmarks/affine_micro.md``).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ab_kernels  # noqa: E402
import ab_sg_micro  # noqa: E402

from prt_torch.harness.timing import cpu_label, machine_info  # noqa: E402

MAIN = r"""
#define _POSIX_C_SOURCE 200112L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <stdint.h>
#include <time.h>
typedef int64_t i64;
int prt_affine_taps(i64 P, i64 n_out, i64 C, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff,
                    const i64 *nk, i64 nuse, int mean, const float *T, i64 Jp, i64 ntap, const i64 *idx, const float *g,
                    float *out, const int32_t *order, int csort, int nthreads);
int prt_affine_rows(i64 P, i64 F, i64 Fo, const void *lab, int lab_kind, const float *W, i64 wstride, const i64 *woff,
                    const i64 *nk, i64 nuse, int mean, const float *T, i64 J, float *out, const int32_t *order, int csort,
                    int nthreads);
int prt_affine_dense(i64 K, i64 P, i64 n_out, i64 n_pad, i64 C, const void *lab, int lab_kind, const float *W, i64 wstride,
                     const i64 *woff, const i64 *nk, i64 nuse, int mean, const float *T, i64 J, const float *y, float *out,
                     const int32_t *order, int csort, int nthreads);
static double now(void) { struct timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t); return t.tv_sec + 1e-9 * t.tv_nsec; }
static unsigned long long s = 88172645463325252ULL;
static float rnd(void) { s ^= s << 13; s ^= s >> 7; s ^= s << 17; return (float)(s >> 40) / (float)(1ULL << 24); }
static void *al(size_t n) { void *p = NULL; return posix_memalign(&p, 64, n) ? NULL : p; }  /* 64-byte aligned, as torch's */
static int cmpd(const void *a, const void *b) { double x = *(const double *)a, y = *(const double *)b; return (x > y) - (x < y); }
static const uint8_t *sort_lab;  /* visiting order: by block of 8192 points, then label, then point (a stable sort) */
static int by_block_label(const void *a, const void *b) {
    int32_t x = *(const int32_t *)a, y = *(const int32_t *)b;
    if (x / 8192 != y / 8192) return x / 8192 < y / 8192 ? -1 : 1;
    if (sort_lab[x] != sort_lab[y]) return sort_lab[x] < sort_lab[y] ? -1 : 1;
    return (x > y) - (x < y);
}
static unsigned long long bits(const float *o, i64 n) {
    unsigned long long h = 0; uint32_t u;
    for (i64 i = 0; i < n; i++) { memcpy(&u, o + i, 4); h = h * 1000003ULL + u; }
    return h;
}
int main(int argc, char **argv) {
    const i64 P = atol(argv[1]); const int reps = atoi(argv[2]);
    double *t = malloc((reps + 1) * sizeof(double));
    /* MRT-PCA 16: 49 rows x 3 colours x 16 terms, four tent taps of a 7x7 grid per point */
    const i64 n_out = 49, Jp = 16;
    float *T = al(n_out * 3 * Jp * 4), *W = al(P * 16 * 4), *g = malloc(P * 4 * 4);
    float *out = al(P * 3 * 4 + 64);
    i64 *idx = malloc(P * 4 * 8);
    for (i64 i = 0; i < n_out * 3 * Jp; i++) T[i] = rnd() - 0.5f;
    for (i64 i = 0; i < P * 16; i++) W[i] = rnd() - 0.5f;
    for (i64 p = 0; p < P; p++) {
        i64 x = (i64)(rnd() * 6), y = (i64)(rnd() * 6); float a = rnd(), b = rnd();
        idx[4 * p] = 7 * y + x; idx[4 * p + 1] = 7 * y + x + 1; idx[4 * p + 2] = 7 * y + x + 7; idx[4 * p + 3] = 7 * y + x + 8;
        g[4 * p] = (1 - a) * (1 - b); g[4 * p + 1] = a * (1 - b); g[4 * p + 2] = (1 - a) * b; g[4 * p + 3] = a * b;
    }
    for (int q = 0; q <= reps; q++) {
        double t0 = now();
        prt_affine_taps(P, n_out, 3, NULL, 0, W, 16, NULL, NULL, 16, 0, T, Jp, 4, idx, g, out, NULL, 0, 1);
        t[q] = now() - t0;
    }
    qsort(t + 1, reps, sizeof(double), cmpd);
    printf("taps %.4f %llu\n", t[1 + reps / 2] / P * 1e9, bits(out, P * 3));
    /* CPCA 64x4 of diffuse vectors: 64 clusters x 5 terms x 8 floats (RGB in the first 3), uint8 labels */
    const i64 K = 64, J = 5, n = 4;
    float *T2 = al(K * J * 8 * 4), *W2 = al(P * n * 4);
    uint8_t *lab = malloc(P);
    for (i64 i = 0; i < K * J * 8; i++) T2[i] = (i % 8) < 3 ? rnd() - 0.5f : 0.0f;
    for (i64 i = 0; i < P * n; i++) W2[i] = rnd() - 0.5f;
    for (i64 p = 0; p < P; p++) lab[p] = (uint8_t)(rnd() * K);
    for (int q = 0; q <= reps; q++) {
        double t0 = now();
        prt_affine_rows(P, 8, 3, lab, 1, W2, n, NULL, NULL, n, 1, T2, J, out, NULL, 0, 1);
        t[q] = now() - t0;
    }
    qsort(t + 1, reps, sizeof(double), cmpd);
    printf("rows %.4f %llu\n", t[1 + reps / 2] / P * 1e9, bits(out, P * 3));
    /* CPCA 256x8, dense view of 24 rows, RGB: constants [256, 9, 3, 24], codes stored in visiting order */
    const i64 K3 = 256, J3 = 9, n3 = 8, R3 = 24;
    float *T3 = al(K3 * J3 * 3 * R3 * 4), *W3 = al(P * n3 * 4), *y3 = al(P * R3 * 4), *o3 = al(P * 3 * 4);
    uint8_t *lab3 = malloc(P), *lab3s = malloc(P);
    int32_t *ord = malloc(P * 4);
    for (i64 i = 0; i < K3 * J3 * 3 * R3; i++) T3[i] = rnd() - 0.5f;
    for (i64 p = 0; p < P; p++) { lab3[p] = (uint8_t)(rnd() * K3); ord[p] = (int32_t)p; }
    for (i64 i = 0; i < P * R3; i++) y3[i] = rnd() - 0.5f;
    sort_lab = lab3;
    qsort(ord, P, 4, by_block_label);
    for (i64 q = 0; q < P; q++) {
        lab3s[q] = lab3[ord[q]];
        for (i64 i = 0; i < n3; i++) W3[q * n3 + i] = rnd() - 0.5f;
    }
    for (int q = 0; q <= reps; q++) {
        double t0 = now();
        prt_affine_dense(K3, P, R3, R3, 3, lab3s, 1, W3, n3, NULL, NULL, n3, 1, T3, J3, y3, o3, ord, 1, 1);
        t[q] = now() - t0;
    }
    qsort(t + 1, reps, sizeof(double), cmpd);
    printf("dense %.4f %llu\n", t[1 + reps / 2] / P * 1e9, bits(o3, P * 3));
    return 0;
}
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="git revision of the reference kernels (default HEAD)")
    ap.add_argument("--test", default=".", help="git revision under test, or '.' for the working tree (default)")
    ap.add_argument("--rounds", type=int, default=6, help="alternating runs of each program (default 6)")
    ap.add_argument("--reps", type=int, default=41, help="calls per run; their median is kept (default 41)")
    ap.add_argument("--points", type=int, default=50000)
    ap.add_argument("--out", default=None, help="also write the table to this file")
    args = ap.parse_args()
    for name in ("rounds", "reps", "points"):
        if getattr(args, name) < 1:
            raise SystemExit(f"ab_affine_micro: --{name} {getattr(args, name)}; accepted: a positive integer")
    load0 = os.getloadavg()[0]
    (src_a, _), (src_b, _) = (ab_kernels.split_source(ab_kernels.module_text(r), r) for r in (args.base, args.test))
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        exes = {"base": ab_sg_micro.build(*src_a, work, "base", main=MAIN)}
        if src_b == src_a:  # one program twice: the ratios measure the noise
            print(f"note: {args.base!r} and {args.test!r} have the same kernel source and flags", file=sys.stderr)
            exes["test"] = exes["base"]
        else:
            exes["test"] = ab_sg_micro.build(*src_b, work, "test", main=MAIN)
        times: dict[str, dict[str, list[float]]] = {"base": {}, "test": {}}
        sums: dict[str, dict[str, str]] = {"base": {}, "test": {}}
        for _ in range(args.rounds):
            for side in ("base", "test"):
                for kernel, (ns, cs) in ab_sg_micro.run(exes[side], args.points, args.reps).items():
                    times[side].setdefault(kernel, []).append(ns)
                    sums[side][kernel] = cs
    flags = " ".join(src_b[1])
    info = machine_info()
    lines = [f"# Affine point kernels, bare C: {args.base} (base) vs {args.test if args.test != '.' else 'working tree'} (test)\n",
             f"Reproduce: `.venv/bin/python benchmarks/ab_affine_micro.py {' '.join(sys.argv[1:])}`\n",
             f"{cpu_label(info)}, load average {load0:.1f} before, {os.getloadavg()[0]:.1f} after; {args.points} points, one "
             f"thread, CPU time (median of {args.reps} calls per run, {args.rounds} alternating runs per side); kernels compiled "
             f"with `{flags}`.\n",
             "| kernel | base (ns / point) | test (ns / point) | ratio (base / test) [range over rounds] | same result |",
             "|---|---|---|---|---|"]
    for kernel, label in (("taps", "taps: MRT-PCA 16, 4 tent taps"), ("rows", "rows: CPCA 64x4 diffuse, uint8 labels"),
                          ("dense", "dense: CPCA 256x8, 24-row view, cluster-sorted")):
        if kernel not in times["base"] or kernel not in times["test"]:  # a revision from before this kernel was measured
            continue
        a, b = statistics.median(times["base"][kernel]), statistics.median(times["test"][kernel])
        per = [x / y for x, y in zip(times["base"][kernel], times["test"][kernel])]  # round by round, adjacent in time
        lines.append(f"| {label} | {a:.3f} | {b:.3f} | **{statistics.median(per):.3f}** [{min(per):.3f}, {max(per):.3f}] | "
                     f"{sums['base'][kernel] == sums['test'][kernel]} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out:
        from prt_torch.io import atomic_write_text
        atomic_write_text(Path(args.out), text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
