"""The wavelet kernel's column-major sparse pass (``SPARSE_TILE`` in ``kernels/wavelet.c``; issue 39): what bounds
it, and the kernel with it changed paired against a base revision's kernel.

Part 1, **the pass alone** (a small C loop compiled here, AVX-512 CPUs only: some variants use zmm), over the real
blocks of one light — per (tile, term) range of the light's sparse terms, per 8-vertex block one offset load, one
8-value int16 load widened and converted, and three 32-byte read-modify-writes of the tile's scratch (CT = 1, RGB) —
with one thing changed per variant, each its own function (64-byte aligned, so code placement moves them less),
timed interleaved, one thread's CPU time:

  - ``kernel``: the base kernel's loop, one block per step;
  - diagnostics (not the same work, what each removal saves): ``no stores`` (the three sums OR-ed into registers,
    no latency chain), ``no scratch loads`` (stores only), ``no offset loads`` (block e at scratch block e mod 64),
    ``no value loads`` (a light value as the block's values), ``stores elsewhere`` (read the scratch, write a second
    one: no store-to-load chain through the scratch), ``fixed 12`` (every range exactly 12 blocks from its first:
    a loop exit that always predicts; per-block time over 12 × ranges), ``ranges only`` (the per-range set-up, no
    block);
  - forms (the same sums, bit for bit): ``2 / step``, ``3 / step``, ``4 / step`` (offsets and values of the step's
    blocks loaded first, then their read-modify-writes in block order, the rest one at a time), ``2 / step, tail
    to a dummy`` (odd counts: the second block's writes to a stack buffer, no remainder branch), ``16 lanes``
    (channels 0–1 of a block as one zmm read-modify-write, channel 2 a ymm), ``16 lanes, 2 / step``.

Part 2, **the kernel**: ``kernels/wavelet.c`` of the working tree and of ``--base`` (default ``main``), both compiled
with the wavelet library's flags (+ ``--isa``'s), bound to one layout (``bench_wavelet_isa.bound_call``), paired by
one thread's CPU time (``measure_paired(clock=time.thread_time)``, median of per-repeat ratios base / test
[quartiles], > 1: the working tree faster); studio and sky, transport-weighted terms, N = 100, 300, 1000, 2000, all,
and the light's sparse terms alone at N = 100, 300, 1000 (the column-major pass, set-up and output pass included).
Every output compared bit for bit between the two builds. The working tree's kernel also paired with the streaming
read bound of its bytes (``timing.read_bound_fn(WaveletRelighter.bytes_read(li), 12 V)``).

Part 3, **where a call of the sparse terms alone goes**: timing-only builds of the working tree's kernel cut after the
set-up (the light gathered, its terms listed) and without the column-major pass, each paired with the whole
call (studio and sky, N = 300 and 1000).

The transfer: occluder_over_plane small (V = 2251), R = 32, K = 256, 16 bits, tiles as the relighter's. Writes
reports/benchmarks/wavelet_colpass.md (the CPU, the builds and the load named).

    .venv/bin/python benchmarks/bench_wavelet_colpass.py [--base main] [--isa native|avx2] [--skip-micro]   (~2 min)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import ctypes  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT, load  # noqa: E402
from bench_wavelet_dense_micro import SRC as DENSE_SRC  # noqa: E402
from bench_wavelet_isa import rl_bytes, bound_call, kernel_build, kernel_source  # noqa: E402
from bench_wavelet_pass_micro import C_PRELUDE, grouped  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import compile_library, cpu_isa  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, read_bound_fn  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent

#: the pass alone: one function per variant (rng [nr, 3]: tile, first block, end; lw [nr, 4]; bofs [NB] bytes;
#: bv [NB, 8] int16; acc: one tile's scratch, zeroed per tile; acc2: a second one)
MICRO = C_PRELUDE + r"""
#include <immintrin.h>
typedef float v16f __attribute__((vector_size(64)));
static inline v16f ld16(const float *p) { v16f x; memcpy(&x, p, sizeof x); return x; }
static inline void st16(float *p, v16f x) { memcpy(p, &x, sizeof x); }
/* the block's 8 values in both halves of a zmm (one 16-byte broadcast load, one widening, one conversion) */
static inline v16f load8x2(const int16_t *p) {
    return (v16f)_mm512_cvtepi32_ps(_mm512_cvtepi16_epi32(_mm256_broadcastsi128_si256(_mm_loadu_si128((const __m128i *)p)))); }
static inline v8f lo(v16f x) { return (v8f)_mm512_castps512_ps256((__m512)x); }
#define RMW(a, w) { st8(a, ld8(a) + (w) * l0); st8((a) + 8, ld8((a) + 8) + (w) * l1); st8((a) + 16, ld8((a) + 16) + (w) * l2); }
#define ZRMW(a, w) { st16(a, ld16(a) + (w) * l01); st8((a) + 16, ld8((a) + 16) + lo(w) * l2); }
#define BLK(k) float *a##k = (float *)((char *)acc + bofs[e + k]); const v8f w##k = load8(bv + 8 * (e + k));
#define PIN(p) __asm__("" : "+r"(p))
#define OR8(s, x) s = (v8f)_mm256_or_ps((__m256)s, (__m256)(x))
#define FN(NAME, ...)                                                                                        \
__attribute__((noinline, aligned(64))) int NAME(const int64_t *rng, int64_t nr, int64_t nt, const float *lw,  \
        const int32_t *bofs, const int16_t *bv, float *acc, float *acc2, int64_t nacc, int64_t NB, int64_t reps) { \
    float dummy[32] __attribute__((aligned(64))) = {0};                                                      \
    v8f keep = {0};                                                                                          \
    for (int64_t r_ = 0; r_ < reps; r_++) {                                                                  \
        int64_t r = 0;                                                                                       \
        for (int64_t t = 0; t < nt; t++) {                                                                   \
            memset(acc, 0, (size_t)nacc * sizeof(float));                                                    \
            for (; r < nr && rng[3 * r] == t; r++) {                                                         \
                const v8f l0 = bc8(lw + 4 * r), l1 = bc8(lw + 4 * r + 1), l2 = bc8(lw + 4 * r + 2);          \
                const v16f l01 = (v16f)_mm512_insertf32x8(_mm512_castps256_ps512((__m256)l0), (__m256)l1, 1); \
                int64_t e = rng[3 * r + 1]; const int64_t e1 = rng[3 * r + 2];                               \
                (void)l01; (void)e1; (void)acc2; (void)NB;                                                   \
                __VA_ARGS__                                                                                  \
            }                                                                                                \
        }                                                                                                    \
    }                                                                                                        \
    __asm__ volatile("" :: "r"(dummy), "x"(keep) : "memory");                                                \
    return 0;                                                                                                \
}
FN(v_kernel, for (; e < e1; e++) { BLK(0) RMW(a0, w0) })
FN(v_nostore, v8f s0 = {0}, s1 = {0}, s2 = {0};
    for (; e < e1; e++) { BLK(0) OR8(s0, ld8(a0) + w0 * l0); OR8(s1, ld8(a0 + 8) + w0 * l1); OR8(s2, ld8(a0 + 16) + w0 * l2); }
    keep += s0 + s1 + s2;)
FN(v_noload, for (; e < e1; e++) { BLK(0) st8(a0, w0 * l0); st8(a0 + 8, w0 * l1); st8(a0 + 16, w0 * l2); })
FN(v_noofs, for (; e < e1; e++) { float *a0 = acc + 32 * (e & 63); const v8f w0 = load8(bv + 8 * e); RMW(a0, w0) })
FN(v_noval, for (; e < e1; e++) { float *a0 = (float *)((char *)acc + bofs[e]); RMW(a0, l2) })
FN(v_elsewhere, for (; e < e1; e++) {
        const float *a = (const float *)((const char *)acc + bofs[e]); float *b = (float *)((char *)acc2 + bofs[e]);
        const v8f w = load8(bv + 8 * e);
        st8(b, ld8(a) + w * l0); st8(b + 8, ld8(a + 8) + w * l1); st8(b + 16, ld8(a + 16) + w * l2); })
FN(v_fixed12, for (int k = 0; k < 12; k++, e++) { if (e >= NB) break; BLK(0) RMW(a0, w0) })
FN(v_ranges, keep += l0 + l1 + l2;)
FN(v_u2, for (; e + 1 < e1; e += 2) { BLK(0) BLK(1) RMW(a0, w0) RMW(a1, w1) }
    for (; e < e1; e++) { BLK(0) RMW(a0, w0) })
FN(v_u3, for (; e + 2 < e1; e += 3) { BLK(0) BLK(1) BLK(2) RMW(a0, w0) RMW(a1, w1) RMW(a2, w2) }
    for (; e < e1; e++) { BLK(0) RMW(a0, w0) })
FN(v_u3dummy, for (; e < e1; e += 3) { /* the step's missing blocks (1-2 at a range's end) to a stack buffer */
        const int h1 = e + 1 < e1, h2 = e + 2 < e1;
        float *a0 = (float *)((char *)acc + bofs[e]);
        float *a1 = h1 ? (float *)((char *)acc + bofs[e + 1]) : dummy, *a2 = h2 ? (float *)((char *)acc + bofs[e + 2]) : dummy;
        const v8f w0 = load8(bv + 8 * e), w1 = load8(bv + 8 * (h1 ? e + 1 : e)), w2 = load8(bv + 8 * (h2 ? e + 2 : e));
        RMW(a0, w0) RMW(a1, w1) RMW(a2, w2) })
FN(v_u3pin, for (; e + 2 < e1; e += 3) { BLK(0) BLK(1) BLK(2) PIN(a0); PIN(a1); PIN(a2); RMW(a0, w0) RMW(a1, w1) RMW(a2, w2) }
    for (; e < e1; e++) { BLK(0) PIN(a0); RMW(a0, w0) })
FN(v_u3pf, if (r + 2 < nr) { const int64_t n = rng[3 * r + 7]; /* the range after next: its first lines */
        __builtin_prefetch(bv + 8 * n); __builtin_prefetch(bv + 8 * n + 32); __builtin_prefetch(bofs + n); }
    for (; e + 2 < e1; e += 3) { BLK(0) BLK(1) BLK(2) PIN(a0); PIN(a1); PIN(a2); RMW(a0, w0) RMW(a1, w1) RMW(a2, w2) }
    for (; e < e1; e++) { BLK(0) PIN(a0); RMW(a0, w0) })
FN(v_u4, for (; e + 3 < e1; e += 4) { BLK(0) BLK(1) BLK(2) BLK(3) RMW(a0, w0) RMW(a1, w1) RMW(a2, w2) RMW(a3, w3) }
    for (; e < e1; e++) { BLK(0) RMW(a0, w0) })
FN(v_u2dummy, for (; e < e1; e += 2) {
        const int h = e + 1 < e1;
        float *a = (float *)((char *)acc + bofs[e]), *b = h ? (float *)((char *)acc + bofs[e + 1]) : dummy;
        const v8f w = load8(bv + 8 * e), x = load8(h ? bv + 8 * e + 8 : bv + 8 * e);
        RMW(a, w) RMW(b, x) })
FN(v_z1, for (; e < e1; e++) { float *a = (float *)((char *)acc + bofs[e]); const v16f w = load8x2(bv + 8 * e); ZRMW(a, w) })
FN(v_z2, for (; e + 1 < e1; e += 2) {
        float *a = (float *)((char *)acc + bofs[e]), *b = (float *)((char *)acc + bofs[e + 1]);
        const v16f w = load8x2(bv + 8 * e), x = load8x2(bv + 8 * e + 8); ZRMW(a, w) ZRMW(b, x) }
    for (; e < e1; e++) { float *a = (float *)((char *)acc + bofs[e]); const v16f w = load8x2(bv + 8 * e); ZRMW(a, w) })
"""

#: (function, label, same sums as the kernel, blocks counted as 12 per range)
VARIANTS = [("v_kernel", "kernel: 1 block / step", True, False),
            ("v_nostore", "no stores", False, False), ("v_noload", "no scratch loads", False, False),
            ("v_noofs", "no offset loads", False, False), ("v_noval", "no value loads", False, False),
            ("v_elsewhere", "stores elsewhere", False, False), ("v_fixed12", "fixed 12 per range", False, True),
            ("v_ranges", "ranges only", False, False),
            ("v_u2", "2 / step", True, False), ("v_u3", "3 / step", True, False), ("v_u4", "4 / step", True, False),
            ("v_u3dummy", "3 / step, tail to a dummy", True, False),
            ("v_u3pf", "3 / step, pinned, prefetch 2 ranges ahead", True, False), ("v_u3pin", "**3 / step, address pinned** (kept)", True, False),
            ("v_u2dummy", "2 / step, tail to a dummy", True, False), ("v_z1", "16 lanes", True, False),
            ("v_z2", "16 lanes, 2 / step", True, False)]


def ghz() -> float:
    """This thread's clock rate (GHz): ``bench_wavelet_dense_micro``'s ``clock_ghz`` (a chain of dependent 64-bit
    multiplies, 3 cycles each; a chain of adds is folded at rename on recent Intel cores)."""
    lib, how = compile_library("wavelet_dense_micro", DENSE_SRC, ["-O3", "-march=native", "-ffp-contract=fast", "-shared",
                                                                  "-fPIC", "-std=c99"], {})
    if lib is None:
        return float("nan")
    lib.clock_ghz.restype = ctypes.c_double
    return max(lib.clock_ghz() for _ in range(3))


def micro(rl, lights, terms, repeats: int = 15, reps: int = 100) -> tuple[list[str], float]:
    """Part 1's table rows: per light and N, each variant's median µs per pass [quartiles], cycles per block and
    kernel / variant (medians of the interleaved samples)."""
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    names = [v[0] for v in VARIANTS]
    lib, how = compile_library("wavelet_colpass_micro", MICRO, ["-O3", "-march=native", "-ffp-contract=fast", "-shared", "-fPIC",
                                                                 "-std=c99"], {n: [vp, i64, i64, vp, vp, vp, vp, vp, i64, i64, i64] for n in names})
    if lib is None:
        raise SystemExit(f"bench_wavelet_colpass: the micro-benchmark did not compile: {how}")
    hz = ghz()
    nacc = rl.TV // 8 * 32
    raw = torch.zeros(2 * nacc + 16)
    accp = (raw.data_ptr() + 63) // 64 * 64
    acc2p = accp + nacc * 4
    L = ["| light | N | ranges (empty) | blocks | variant | µs per pass [quartiles] | cycles per block | **kernel / variant** | sums |",
         "|---|---|---|---|---|---|---|---|---|"]
    for light in lights:
        for N in terms:
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            rng, gl, bofs, vals = grouped(rl, torch.arange(rl.P), 1, li, lv)
            vals = vals.reshape(-1, 8).contiguous()
            NB = vals.shape[0]
            nblk = int((rng[:, 2] - rng[:, 1]).sum())
            args = (rng.data_ptr(), rng.shape[0], rl.NT, gl.data_ptr(), bofs.data_ptr(), vals.data_ptr(), accp, acc2p, nacc, NB)
            sums = {}
            for n in names:
                getattr(lib, n)(*args, 2)
                sums[n] = torch.frombuffer((ctypes.c_float * nacc).from_address(accp), dtype=torch.float32).clone()
            res = {n: [] for n in names}
            for rep in range(repeats):
                for n in (names if rep % 2 else names[::-1]):
                    f = getattr(lib, n)
                    t0 = time.thread_time()
                    f(*args, reps)
                    res[n].append((time.thread_time() - t0) / reps * 1e6)
            kernel_blk = sorted(res["v_kernel"])[repeats // 2] / max(nblk, 1)
            for n, label, same, fixed in VARIANTS:
                s = sorted(res[n])
                nb = rng.shape[0] * 12 if fixed else nblk
                per = s[len(s) // 2] / max(nb, 1)  # µs per block (fixed 12: per block of its own count)
                cyc = "—" if n == "v_ranges" else f"{per * 1e3 * hz:.2f}"
                ratio = "—" if n == "v_ranges" else f"{kernel_blk / per:.3f}"
                eq = ("equal" if torch.equal(sums[n], sums["v_kernel"]) else "**differ**") if same else "—"
                L.append(f"| {light} | {N} | {rng.shape[0]} ({int((rng[:, 2] == rng[:, 1]).sum())}) | {nblk} | {label} | "
                         f"{s[len(s) // 2]:.1f} [{s[len(s) // 4]:.1f}, {s[3 * len(s) // 4]:.1f}] | {cyc} | {ratio} | {eq} |")
                print(f"[colpass micro] {light} N={N} {label}: {s[len(s) // 2]:.2f} us, {cyc} cyc/blk, kernel/this {ratio} {eq}",
                      flush=True)
    return L, hz


def kernel_lib(rev: str | None, isa: str, tag: str = "", cut: str = ""):
    """``kernels/wavelet.c`` at git revision ``rev`` (None: the working tree) compiled with the wavelet library's flags
    and ``isa``'s (``_native.KERNEL_ISAS``), ``tag`` appended as a comment (a second build of the same code: the A/A
    control); ``cut``: ``setup`` returns after the light is gathered and its terms listed, ``nopass`` skips the
    column-major pass (timing-only builds: where a call's time goes); returns (library, commit or 'working tree', flags)
    (bench_wavelet_isa.kernel_source / kernel_build)."""
    src, what = kernel_source(rev, "bench_wavelet_colpass: --base")
    if cut:
        at = {"setup": ("    const T *rvals = (const T *)L->rvals;",
                        "    if (1) { for (i64 n = 0; n < N; n++) memset(lp + 4 * sel[n], 0, 4 * sizeof(float)); return 0; } \\\n"
                        "    const T *rvals = (const T *)L->rvals;"),
              "nopass": ("    if (ns && !rows) sparse_tile_##T(", "    if (0) sparse_tile_##T(")}[cut]
        if at[0] not in src:
            raise SystemExit(f"bench_wavelet_colpass: --cut {cut}: the kernel's text changed ({at[0]!r} not found)")
        src = src.replace(at[0], at[1], 1) + f"\n/* cut: {cut} */\n"
    lib, flags = kernel_build(src, isa, "bench_wavelet_colpass", tag)
    return lib, what, flags


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", default="main", help="the git revision whose kernels/wavelet.c is the peer (default main)")
    ap.add_argument("--isa", default="native", choices=["native", "avx2", "avx512-256"],
                    help="both builds' PRT_TORCH_KERNEL_ISA flags (avx2: the 8-lane path, a proxy for an AVX2 CPU)")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--skip-micro", action="store_true", help="part 2 only")
    ap.add_argument("--write", default=None, help="the report (default reports/benchmarks/wavelet_colpass.md, "
                                                    "wavelet_colpass_<isa>.md for another --isa; '' : print only)")
    args = ap.parse_args()
    if args.write is None:
        args.write = str(OUT / ("wavelet_colpass.md" if args.isa == "native" else f"wavelet_colpass_{args.isa}.md"))
    torch.set_num_threads(1)
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="both")
    before = load()
    text = ["# Wavelet kernel: the column-major sparse pass (issue 39)\n",
            f"{cpu_label()}; load average {before:.1f} at the start (the machine shared with other jobs; every time is one "
            f"thread's CPU time, which the other processes' load does not enter). The transfer: occluder_over_plane small "
            f"(V = {rl.V}), R = 32, K = 256, {BITS}-bit, {rl.Pd} dense columns, {rl.NB} sparse 8-vertex blocks, tiles of "
            f"{rl.TV}; transport-weighted terms. Reproduce: `.venv/bin/python benchmarks/bench_wavelet_colpass.py"
            f"{'' if args.isa == 'native' else ' --isa ' + args.isa}` (module docstring: what each variant is).\n"]
    if not args.skip_micro and cpu_isa() == "avx512":
        rows, hz = micro(rl, ("studio", "sky (sun)"), (300, 1000))
        text += ["## The pass alone, by variant\n",
                 f"The light's sparse terms' blocks, the kernel's loop for CT = 1, RGB, 16-bit values (`-O3 -march=native`); "
                 f"each variant's median of 15 interleaved samples of 100 passes [quartiles]; cycles at {hz:.2f} GHz (a chain of dependent "
                 f"multiplies, same thread); **kernel / variant**: the kernel's time per block over the variant's (> 1: the variant faster; "
                 f"`fixed 12`: per block of its own 12 × ranges); sums: the last tile's "
                 f"scratch against the kernel's, bit for bit (— : not the same work). Load {load():.1f} at its end.\n"] + rows + [""]
    test, twhat, tflags = kernel_lib(None, args.isa)
    base, bwhat, _ = kernel_lib(args.base, args.isa)
    control, _, _ = kernel_lib(args.base, args.isa, "the A/A control: a second build of the base")
    cases = []
    for light in ("studio", "sky (sun)"):
        for N in (100, 300, 1000, 2000, rl.P):
            cases.append((light, N, "all"))
        for N in (100, 300, 1000):
            cases.append((light, N, "sparse"))
    rows = []
    for light, N, part in cases:
        li, lv, _ = rl.light(LIGHTS[light], N, "transport")
        lv = lv.to(torch.float32).contiguous()
        if part == "sparse":  # the light's sparse terms alone
            keep = rl.dslot[li] < 0
            li, lv = li[keep], lv[:, keep].contiguous()
        li = li.contiguous()
        outs = [torch.empty(rl.V, 3), torch.empty(rl.V, 3), torch.empty(rl.V, 3)]
        ft, fb = bound_call(rl, test, li, lv, outs[0], 1), bound_call(rl, base, li, lv, outs[1], 1)
        fc = bound_call(rl, control, li, lv, outs[2], 1)
        ft()
        fb()
        fc()
        same = torch.equal(outs[0], outs[1]) and torch.equal(outs[2], outs[1])
        p = measure_paired(ft, fb, repeats=args.repeats, warmup=1, clock=time.thread_time)
        pc = measure_paired(fc, fb, repeats=args.repeats, warmup=1, clock=time.thread_time)
        rb = measure_paired(ft, read_bound_fn(rl_bytes(rl, li), rl.V * 12), repeats=args.repeats, warmup=1, clock=time.thread_time)
        sb = int(rl._cblk[li[rl.cls[li] == 1]].sum())  # the sparse blocks of its sparse terms
        row = dict(light=light, N=N, part=part, terms=int(li.numel()), sblocks=sb, test=p.test.median * 1e6,
                   base=p.peer.median * 1e6, ratio=p.speedup, q=(p.ratio.q1, p.ratio.q3), of_read=rb.speedup, control=pc.speedup,
                   same=same, load=load())
        rows.append(row)
        print(f"[colpass] {light} N={N} {part}: test {row['test']:.1f} us, base {row['base']:.1f} us, base/test "
              f"{row['ratio']:.3f} [{row['q'][0]:.3f}, {row['q'][1]:.3f}], control {row['control']:.3f}, of read bound {row['of_read']:.2f}, "
              f"bit-identical {same}, load {row['load']:.1f}", flush=True)
    text += [f"## The kernel against {args.base}'s\n",
             f"**test**: the working tree's `kernels/wavelet.c`; **base**: {args.base} ({bwhat}); both `{tflags}`, bound to "
             f"one layout (the row-major copy built: N = 2000 and all take the row-major pass, whose blocks this change does "
             f"not touch). One thread, paired by its CPU time (`measure_paired(clock=time.thread_time)`, {args.repeats} "
             f"repeats): medians per call and **base / test**, the median of the per-repeat ratios [quartiles] (> 1: the "
             f"working tree faster); **control**: a second build of the base (the same code, a comment appended) paired with the "
             f"base the same way (the same machine code in a second library: the pairing's own noise; the row-major "
             f"rows N = 2000 and all, whose source is untouched but whose code moved inside the same function, show what "
             f"placement alone moves). Of read bound: the test kernel paired the same way with a streaming read of "
             f"`WaveletRelighter.bytes_read` of its terms and a fill of the output (`timing.read_bound_fn`). Outputs "
             f"compared bit for bit.\n",
             "| light | N | terms | sparse blocks | test µs | base µs | **base / test** [quartiles] | control | test of read bound "
             "| bit-identical | load |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        terms = f"all {r['terms']}" if r["part"] == "all" else f"sparse alone {r['terms']}"
        text.append(f"| {r['light']} | {'all' if r['N'] == rl.P else r['N']} | {terms} | {r['sblocks']} | {r['test']:.1f} | "
                    f"{r['base']:.1f} | **{r['ratio']:.3f}** [{r['q'][0]:.3f}, {r['q'][1]:.3f}] | {r['control']:.3f} | {r['of_read']:.2f} | "
                    f"{'yes' if r['same'] else '**no**'} | {r['load']:.1f} |")
    text += ["\n## Where a call of the light's sparse terms alone goes (the working tree's kernel)\n",
             "The same call through timing-only builds of the working tree's kernel: **set-up** returns after the checks, "
             "the light's gathering and its terms' listing (the light's columns zeroed again); **no pass** skips the "
             "column-major pass (the tiles' scratch zeroed and the dense blocks' output pass kept); each paired with the "
             "whole call by one thread's CPU time (medians). pass = whole − no pass.\n",
             "| light | N | sparse terms | sparse blocks | whole µs | set-up µs | + scratch and output µs | pass µs | pass ns per "
             "block |", "|---|---|---|---|---|---|---|---|---|"]
    cuts = {c: kernel_lib(None, args.isa, cut=c)[0] for c in ("setup", "nopass")}
    for light in ("studio", "sky (sun)"):
        for N in (300, 1000):
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            keep = rl.dslot[li] < 0
            li, lv = li[keep].contiguous(), lv.to(torch.float32)[:, keep].contiguous()
            out = torch.empty(rl.V, 3)
            whole = bound_call(rl, test, li, lv, out, 1)
            us = {}
            for c, lib in cuts.items():
                f = bound_call(rl, lib, li, lv, out, 1)
                p = measure_paired(f, whole, repeats=args.repeats, warmup=1, clock=time.thread_time)
                us[c], us["whole"] = p.test.median * 1e6, p.peer.median * 1e6
            sb = int(rl._cblk[li[rl.cls[li] == 1]].sum())
            ps = us["whole"] - us["nopass"]
            text.append(f"| {light} | {N} | {li.numel()} | {sb} | {us['whole']:.1f} | {us['setup']:.1f} | "
                        f"{us['nopass'] - us['setup']:.1f} | {ps:.1f} | {ps * 1e3 / max(sb, 1):.2f} |")
            print(f"[colpass split] {text[-1]}", flush=True)
    text.append(f"\nLoad average {before:.1f} → {load():.1f}.")
    out = "\n".join(text) + "\n"
    if args.write:
        atomic_write_text(Path(args.write), out)
        print(f"[colpass] wrote {args.write}", flush=True)
    else:
        print(out)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    main()
