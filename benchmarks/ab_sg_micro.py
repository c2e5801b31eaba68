"""Paired A/B of the Gaussian lookup kernels in a bare C harness (no Python in the timed loop).

    .venv/bin/python benchmarks/ab_sg_micro.py                  # HEAD vs the working tree
    .venv/bin/python benchmarks/ab_sg_micro.py --base HEAD~1 --test HEAD --rounds 6

``benchmarks/ab_kernels.py`` times whole ``relight`` calls at 50 000 vertices, where the
machine's memory traffic moves a Gaussian row by 10–30% between samples. This tool times the two
kernels themselves on cache-resident data, as a program of its own: each revision's C source
(the files of ``prt_torch/kernels/`` and their flags, as ab_kernels reads them) is compiled with a small
``main`` that calls ``prt_sg_lookup_sum`` (16 384 one-lobe lookups, the RGB 20-level 6×16×16
pyramid of ``prefilter_environment``'s defaults) and ``prt_sg_taps`` (2 048 vertices of 92 views,
3 taps) on one thread and prints the best of ``--reps`` calls. Kernels that read the lobes as
records ``[..., 5]`` (w, μ, σ; the codec's stored form since they exist) get the data that way
(``-DSTRIDED``, chosen from the source's signature), older ones as three arrays; kernels that take
the records' layout (``-DLAYOUT``: view-major records since 2026-11-24) get vertex-major records:
the same values, so the same checksums. The two programs run in
alternation, ``--rounds`` times each; the report gives each side's median of those best times,
the median and range of the round-by-round ratios (base / test: > 1, test faster), and whether
the two results' checksums agree (they must, for a change meant to keep the arithmetic). Run it
on a quiet machine: HEAD against itself reads 0.99–1.01, and a busy moment moves one round. It resolves 1–2% where the relight-level A/B
does not; the register-permute change to the width ladder was found and measured with it.
"""
from __future__ import annotations

import argparse
import re
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import ab_kernels  # noqa: E402

MAIN = r"""
#include <stdio.h>
#include <stdlib.h>
#include <time.h>
#include <math.h>
#include <stdint.h>
typedef int64_t i64;
#ifdef LAYOUT  /* kernels that also read view-major records (the lobe index of (v, j) given): called vertex-major */
int prt_sg_lookup_sum(i64 G, i64 B, i64 fb, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss,
                      const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads);
int prt_sg_taps(i64 V, i64 J, i64 N, i64 k, i64 fv, i64 fj, const float *w, const float *mu, const float *sigma, i64 sw, i64 sm,
                i64 ss, const i64 *idx, const float *av, const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out,
                int nthreads);
#define STRIDED
#define G_ARGS(G) G, 1, 0
#define V_ARGS(V, J) V, J, 1, 3, J, 1
#else
#define G_ARGS(G) G
#define V_ARGS(V, J) V, J, 1, 3
#endif
#ifdef STRIDED  /* kernels that read lobe records [..., 5] (w, mu, sigma) in place: the codec's stored form */
#ifndef LAYOUT
int prt_sg_lookup_sum(i64 G, i64 N, const float *mu, const float *sigma, const float *w, i64 sw, i64 sm, i64 ss, const float *table,
                      i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads);
int prt_sg_taps(i64 V, i64 J, i64 N, i64 k, const float *w, const float *mu, const float *sigma, i64 sw, i64 sm, i64 ss,
                const i64 *idx, const float *av, const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads);
#endif
#define STRIDES , 5, 5, 5
#define W_AT(g) rec[5 * (g)]
#define MU_AT(g, c) rec[5 * (g) + 1 + (c)]
#define SG_AT(g) rec[5 * (g) + 4]
#else  /* separate arrays */
int prt_sg_lookup_sum(i64 G, i64 N, const float *mu, const float *sigma, const float *w, const float *table, i64 r, i64 L,
                      const float *ladder, i64 C, float *out, int nthreads);
int prt_sg_taps(i64 V, i64 J, i64 N, i64 k, const float *w, const float *mu, const float *sigma, const i64 *idx,
                const float *av, const float *table, i64 r, i64 L, const float *ladder, i64 C, float *out, int nthreads);
#define STRIDES
#define W_AT(g) w[g]
#define MU_AT(g, c) mu[3 * (g) + (c)]
#define SG_AT(g) sg[g]
#endif
static double now(void) { struct timespec t; clock_gettime(CLOCK_MONOTONIC, &t); return t.tv_sec + 1e-9 * t.tv_nsec; }
static unsigned long long s = 88172645463325252ULL;
static float rnd(void) { s ^= s << 13; s ^= s >> 7; s ^= s << 17; return (float)(s >> 40) / (float)(1ULL << 24); }
int main(int argc, char **argv) {
    i64 G = atol(argv[1]), V = atol(argv[2]); int reps = atoi(argv[3]);
    const i64 r = 16, L = 20, C = 3, J = 92, k = 3, M = G > V * J ? G : V * J;
    float *mu = malloc(M * 3 * 4), *sg = malloc(M * 4), *w = malloc(M * 4), *out = malloc((G > V ? G : V) * 3 * 4);
    float *rec = malloc(M * 5 * 4);
    float *table = malloc(L * 6 * r * r * C * 4), *a = malloc(V * k * 4), ladder[20];
    i64 *idx = malloc(V * k * 8);
    for (i64 i = 0; i < L * 6 * r * r * C; i++) table[i] = rnd();
    for (int l = 0; l < L; l++) ladder[l] = logf(0.02f) + l * (logf(4.0f) - logf(0.02f)) / (L - 1);
    for (i64 g = 0; g < M; g++) {
        float x = rnd() - 0.5f, y = rnd() - 0.5f, z = rnd() - 0.5f, n = sqrtf(x * x + y * y + z * z) + 1e-6f;
        MU_AT(g, 0) = x / n; MU_AT(g, 1) = y / n; MU_AT(g, 2) = z / n;
        SG_AT(g) = 0.05f + 1.5f * rnd(); W_AT(g) = rnd();
    }
    for (i64 v = 0; v < V; v++)
        for (i64 t = 0; t < k; t++) { idx[v * k + t] = (i64)(rnd() * (J - 1)); a[v * k + t] = rnd(); }
    for (int which = 0; which < 2; which++) {
        double best = 1e30, sum = 0;
        i64 n = which == 0 ? G : V;
        for (int q = 0; q <= reps; q++) {
            double t = now();
#ifdef STRIDED
            if (which == 0) prt_sg_lookup_sum(G_ARGS(G), 1, rec + 1, rec + 4, rec STRIDES, table, r, L, ladder, C, out, 1);
            else prt_sg_taps(V_ARGS(V, J), rec, rec + 1, rec + 4 STRIDES, idx, a, table, r, L, ladder, C, out, 1);
#else
            if (which == 0) prt_sg_lookup_sum(G, 1, mu, sg, w, table, r, L, ladder, C, out, 1);
            else prt_sg_taps(V, J, 1, k, w, mu, sg, idx, a, table, r, L, ladder, C, out, 1);
#endif
            t = now() - t;
            if (q > 0 && t < best) best = t;  /* the first call warms the caches */
        }
        for (i64 i = 0; i < n * 3; i++) sum += out[i];
        printf("%s %.4f %.9e\n", which == 0 ? "lookup" : "taps", best / n * 1e9, sum);
    }
    return 0;
}
"""


def build(sources: dict[str, str], flags: list[str], work: Path, name: str, main: str = MAIN) -> Path:
    """An executable of the kernels ``sources`` (``{file name: C text}``; their compile flags, as a
    program) and ``main`` (default ``MAIN``; ``ab_affine_micro`` passes its own)."""
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise SystemExit("ab_sg_micro: no C compiler (cc or gcc) on PATH; accepted: a machine where the kernels compile")
    d = work / f"{name}-src"
    d.mkdir()
    for n, text in sources.items():
        (d / n).write_text(text)
    units = [n for n in sources if n.endswith(".c")]
    if len(units) > 1:  # one translation unit, as the library is built (_native._build)
        (d / "unity.c").write_text("".join(f'#include "{n}"\n' for n in units))
        units = ["unity.c"]
    units = [str(d / n) for n in units]
    src = "\n".join(sources.values())
    (work / "main.c").write_text(main)
    exe = work / name
    fl = [f for f in flags if f not in ("-shared", "-fPIC")]
    if re.search(r"int prt_sg_taps\([^)]*i64 fv, i64 fj", src):  # and view-major ones (given vertex-major data here)
        fl.append("-DLAYOUT")
    elif re.search(r"int prt_sg_taps\([^)]*i64 sw, i64 sm, i64 ss", src):  # the kernels read lobe records in place
        fl.append("-DSTRIDED")
    r = subprocess.run([cc, *fl, f"-I{d}", *units, str(work / "main.c"), "-o", str(exe), "-lm"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"ab_sg_micro: the kernels of {name} did not compile: {r.stderr.strip()[-800:]}")
    return exe


def run(exe: Path, *args: int) -> dict[str, tuple[float, str]]:
    """Run a built micro-benchmark program with its integer arguments; its lines ``kernel ns checksum``
    as {kernel: (ns, checksum)} (this program: lookups, vertices, reps; ab_affine_micro's: points, reps)."""
    out = subprocess.run([str(exe), *map(str, args)], capture_output=True, text=True, check=True).stdout
    return {m.group(1): (float(m.group(2)), m.group(3)) for m in re.finditer(r"^(\w+) (\S+) (\S+)$", out, re.M)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="git revision of the reference kernels (default HEAD)")
    ap.add_argument("--test", default=".", help="git revision under test, or '.' for the working tree (default)")
    ap.add_argument("--rounds", type=int, default=6, help="alternating runs of each program (default 6)")
    ap.add_argument("--reps", type=int, default=100, help="calls per run; its best is kept (default 100)")
    ap.add_argument("--lookups", type=int, default=16384)
    ap.add_argument("--vertices", type=int, default=2048)
    args = ap.parse_args()
    for name in ("rounds", "reps", "lookups", "vertices"):
        if getattr(args, name) < 1:
            raise SystemExit(f"ab_sg_micro: --{name} {getattr(args, name)}; accepted: a positive integer")
    (src_a, _), (src_b, _) = (ab_kernels.split_source(ab_kernels.module_text(r), r) for r in (args.base, args.test))
    with tempfile.TemporaryDirectory() as d:
        work = Path(d)
        exes = {"base": build(*src_a, work, "base")}
        if src_b == src_a:  # one program twice: the ratios measure the noise
            print(f"note: {args.base!r} and {args.test!r} have the same kernel source and flags", file=sys.stderr)
            exes["test"] = exes["base"]
        else:
            exes["test"] = build(*src_b, work, "test")
        times: dict[str, dict[str, list[float]]] = {"base": {}, "test": {}}
        sums: dict[str, dict[str, str]] = {"base": {}, "test": {}}
        for _ in range(args.rounds):
            for side in ("base", "test"):
                for kernel, (ns, cs) in run(exes[side], args.lookups, args.vertices, args.reps).items():
                    times[side].setdefault(kernel, []).append(ns)
                    sums[side][kernel] = cs
    print(f"# Gaussian kernels, bare C: {args.base} (base) vs {args.test if args.test != '.' else 'working tree'} (test)\n")
    print("| kernel | base (ns) | test (ns) | ratio (base / test) [range over rounds] | same result |\n|---|---|---|---|---|")
    for kernel, unit in (("lookup", "per lookup"), ("taps", "per vertex")):
        a, b = statistics.median(times["base"][kernel]), statistics.median(times["test"][kernel])
        per = [x / y for x, y in zip(times["base"][kernel], times["test"][kernel])]  # round by round, adjacent in time
        print(f"| {kernel} ({unit}) | {a:.2f} | {b:.2f} | **{statistics.median(per):.3f}** [{min(per):.3f}, {max(per):.3f}] | "
              f"{sums['base'][kernel] == sums['test'][kernel]} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
