"""Where the wavelet kernel's dense GEMV spends its time (issue 39, one thread): the dense terms' loop of
``kernels/wavelet.c`` (``dense_block``: per 32-vertex block its 3 x 4 vectors of RGB sums in registers over the
light's dense terms, CT = 1, 16-bit values, the kernel's prefetch 6 terms ahead) compiled here, over the real
blocks and terms of one light, with one thing changed per variant:

  - ``kernel form``: per term 4 widening loads (``vpmovsxwd``), 4 int -> float conversions, 12 multiply-adds;
  - ``prefetch across blocks``: the kernel form, its last PF terms prefetching the next block's first PF slots
    (the kernel stops prefetching there);
  - ``lean loop``: the kernel form with the slots as byte offsets (no shift per term) and the list padded by the
    prefetch distance (no test before each prefetch); ``lean, 2 terms a step``: the same, two terms per loop step;
  - ``shifts``: the block's 32 values stored as 16 32-bit lanes, lane i of the q-th vector holding vertex
    16q + i in its low half and 16q + 8 + i in its high half, one 32-byte load per 16 values; the high vertices
    sign-extended by one arithmetic shift right by 16, the low ones by a shift left and one right (three shifts per
    16 values instead of two ``vpmovsxwd``); the same values, so the same sums bit for bit (gcc keeps two
    converted vectors live here and spills one of the 12 sums: its rows measure that spill's store-load chain;
    the instruction mix without it: ``bench_wavelet_floor_micro.py``);
  - ``float``: the values stored as float32 (no conversion, twice the bytes; the floor of the multiply-adds,
    not a candidate: the kernel's bound would double with its bytes);
  - each also with every block reading the first block's values (``L1``: 8-16 KB, in L1), which takes the
    memory out: what is left is the core's.

Every variant's sums are compared with the kernel form's. Studio and sky (transport-weighted) at N terms
(default 1000); the kernel section's transfer (occluder_over_plane small, R = 32, K = 256, 16 bits). Each: the
median of 15 paired samples of 100 passes against the kernel form by this thread's CPU time. The clock rate is
measured (a chain of dependent 64-bit multiplies, 3 cycles each) to state ns as cycles. Writes reports/benchmarks/wavelet_dense_micro.md.

    .venv/bin/python benchmarks/bench_wavelet_dense_micro.py [--terms 1000 ...]     (about 20 s)
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
from bench_wavelet import BITS, LIGHTS, OUT, kernel_transfer  # noqa: E402
from bench_wavelet_pass_micro import C_PRELUDE  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import machine_info, measure_paired  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

SRC = "#define _POSIX_C_SOURCE 199309L\n" + C_PRELUDE + r"""#include <time.h>
typedef int64_t i64;
typedef int32_t v8i __attribute__((vector_size(32)));
typedef uint32_t v8u __attribute__((vector_size(32)));
#define PF 6
/* dense [nb, Pd, 32] (blocks bs apart: 0 reads block 0 for every block), ds [nd] slots, lw [nd, 4]; sums [nb, 3, 32]
 * mode 0: int16, kernel form; 1: int16 shifts (the lanes' pairs as above); 2: float32 values; 3, 4: lean loop (ds: byte
 * offsets, PF + 1 padded), one or two terms a step; 5: the kernel form, its last PF terms prefetching the next block's first slots */
int dense_pass(const void *dense, i64 bs, const i64 *ds, i64 nd, const float *lw, i64 nb, i64 mode, float *sums, i64 reps) {
    for (i64 r_ = 0; r_ < reps; r_++)
        for (i64 b = 0; b < nb; b++) {
            v8f a[3][4];
            for (int c = 0; c < 3; c++) for (int k = 0; k < 4; k++) a[c][k] = (v8f){0};
            if (mode == 0 || mode == 5) {
                const int16_t *blk = (const int16_t *)dense + b * bs;
                for (i64 t = 0; t < nd; t++) {
                    const int16_t *p = blk + ds[t] * 32;
                    if (t + PF < nd) __builtin_prefetch(blk + ds[t + PF] * 32);
                    else if (mode == 5 && b + 1 < nb) __builtin_prefetch(blk + bs + ds[t + PF - nd] * 32);
                    v8f l[3];
                    for (int c = 0; c < 3; c++) l[c] = bc8(lw + 4 * t + c);
                    for (int k = 0; k < 4; k++) {
                        const v8f x = load8(p + 8 * k);
                        for (int c = 0; c < 3; c++) a[c][k] += x * l[c];
                    }
                }
            } else if (mode == 1) {
                const int16_t *blk = (const int16_t *)dense + b * bs;
                for (i64 t = 0; t < nd; t++) {
                    const int16_t *p = blk + ds[t] * 32;
                    if (t + PF < nd) __builtin_prefetch(blk + ds[t + PF] * 32);
                    v8f l[3];
                    for (int c = 0; c < 3; c++) l[c] = bc8(lw + 4 * t + c);
                    for (int q = 0; q < 2; q++) {
                        v8i w;
                        memcpy(&w, p + 16 * q, sizeof w);
                        const v8f x0 = __builtin_convertvector((v8i)((v8u)w << 16) >> 16, v8f), x1 = __builtin_convertvector(w >> 16, v8f);
                        for (int c = 0; c < 3; c++) { a[c][2 * q] += x0 * l[c]; a[c][2 * q + 1] += x1 * l[c]; }
                    }
                }
            } else if (mode == 3 || mode == 4) { /* lean loop: byte offsets (ds3 [nd + PF], the last repeated PF times) */
                const char *blk = (const char *)dense + b * bs * 2;
                if (mode == 4) {
                    i64 t = 0;
                    for (; t + 1 < nd; t += 2) { /* two terms per step */
                        const int16_t *p = (const int16_t *)(blk + ds[t]), *p1 = (const int16_t *)(blk + ds[t + 1]);
                        __builtin_prefetch(blk + ds[t + PF]);
                        __builtin_prefetch(blk + ds[t + 1 + PF]);
                        for (int h = 0; h < 2; h++) {
                            const int16_t *q = h ? p1 : p;
                            v8f l[3];
                            for (int c = 0; c < 3; c++) l[c] = bc8(lw + 4 * (t + h) + c);
                            for (int k = 0; k < 4; k++) {
                                const v8f x = load8(q + 8 * k);
                                for (int c = 0; c < 3; c++) a[c][k] += x * l[c];
                            }
                        }
                    }
                    if (t < nd) {
                        const int16_t *p = (const int16_t *)(blk + ds[t]);
                        v8f l[3];
                        for (int c = 0; c < 3; c++) l[c] = bc8(lw + 4 * t + c);
                        for (int k = 0; k < 4; k++) {
                            const v8f x = load8(p + 8 * k);
                            for (int c = 0; c < 3; c++) a[c][k] += x * l[c];
                        }
                    }
                } else
                for (i64 t = 0; t < nd; t++) {
                    const int16_t *p = (const int16_t *)(blk + ds[t]);
                    __builtin_prefetch(blk + ds[t + PF]);
                    v8f l[3];
                    for (int c = 0; c < 3; c++) l[c] = bc8(lw + 4 * t + c);
                    for (int k = 0; k < 4; k++) {
                        const v8f x = load8(p + 8 * k);
                        for (int c = 0; c < 3; c++) a[c][k] += x * l[c];
                    }
                }
            } else {
                const float *blk = (const float *)dense + b * bs;
                for (i64 t = 0; t < nd; t++) {
                    const float *p = blk + ds[t] * 32;
                    if (t + PF < nd) { __builtin_prefetch(blk + ds[t + PF] * 32); __builtin_prefetch(blk + ds[t + PF] * 32 + 16); }
                    v8f l[3];
                    for (int c = 0; c < 3; c++) l[c] = bc8(lw + 4 * t + c);
                    for (int k = 0; k < 4; k++) {
                        const v8f x = ld8(p + 8 * k);
                        for (int c = 0; c < 3; c++) a[c][k] += x * l[c];
                    }
                }
            }
            for (int c = 0; c < 3; c++) for (int k = 0; k < 4; k++) st8(sums + b * 96 + 32 * c + 8 * k, a[c][k]);
        }
    return 0;
}
/* this thread's clock rate: a chain of dependent 64-bit multiplies (3 cycles each on AMD Zen 3 and recent Intel cores;
 * a chain of adds of an immediate, used before, is folded at rename on recent Intel cores: 13.4 GHz on a Xeon), per ns */
double clock_ghz(void) {
    struct timespec a, b;
    i64 n = 30000000, x = 3;
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a);
#if defined(__x86_64__)
    __asm__ volatile("1: imul %0, %0\n imul %0, %0\n imul %0, %0\n imul %0, %0\n dec %1\n jnz 1b" : "+r"(x), "+r"(n));
#else
    return 0.0;
#endif
    clock_gettime(CLOCK_THREAD_CPUTIME_ID, &b);
    return 3.6e8 / ((double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec));
}
"""


def blocker_dense(size: str = "small") -> tuple["relight.WaveletRelighter", int, int, torch.Tensor]:
    """The micro-benchmarks' layout: the blocker scene (occluder_over_plane, ``size``: small by default) at R = 32,
    K = 256, 16-bit, its one-thread column-major relighter ``rl``, its ``nb`` 32-vertex blocks and ``Pd`` dense
    columns, and the dense values ``d16`` int16 [nb, Pd, 32]. The relighter's dense loop is the float one
    (``arith='float'``: these micro-benchmarks pair loops against the kernel's float loop; on an AVX-512 VNNI CPU the
    default is the VNNI loop)."""
    rl = relight.WaveletRelighter(kernel_transfer(size), threads=1, layouts="column", arith="float")
    assert rl.CT == 1 and rl.dense.dtype == torch.int16
    nb, Pd = rl.dense.shape[0], rl.dense.shape[1]
    return rl, nb, Pd, rl.dense.reshape(nb, Pd, 32)


def dense_terms(rl: "relight.WaveletRelighter", li: torch.Tensor, lv: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """A light's dense terms as the kernel lists them: ``ds`` int64 [nd] their dense slots in slot order and
    ``lw`` float32 [nd, 4] their light (channels 0..C-1, the rest zero), from the light's Haar terms ``li``
    int64 [N] and values ``lv`` [C, N] (``WaveletRelighter.light``)."""
    d = rl.dslot[li] >= 0
    order = torch.argsort(rl.dslot[li[d]].long())
    ds = rl.dslot[li[d]].long()[order].contiguous()
    lw = torch.zeros(ds.numel(), 4)
    lw[:, :lv.shape[0]] = lv[:, d].T.float()[order]
    return ds, lw


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--terms", type=int, nargs="+", default=[1000])
    ap.add_argument("--reps", type=int, default=100)
    args = ap.parse_args()
    torch.set_num_threads(1)
    lib, how = compile_library("wavelet_dense_micro", SRC, ["-O3", "-march=native", "-ffp-contract=fast", "-shared",
                                                            "-fPIC", "-std=c99"], {})
    if lib is None:
        raise SystemExit(f"bench_wavelet_dense_micro: no compiler: {how}")
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    lib.dense_pass.argtypes = [vp, i64, vp, i64, vp, i64, i64, vp, i64]
    lib.clock_ghz.restype = ctypes.c_double
    rl, nb, Pd, d16 = blocker_dense()
    # shifts: lane i of 32-bit vector q = (vertex 16q + i) | (vertex 16q + 8 + i) << 16
    perm = torch.tensor([16 * q + h * 8 + i for q in range(2) for i in range(8) for h in range(2)])
    dsa = d16[:, :, perm].contiguous()
    dfl = d16.float().contiguous()
    ghz = lib.clock_ghz()
    load0 = os.getloadavg()[0]
    rows = []
    for light in ("studio", "sky (sun)"):
        for N in args.terms:
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            ds, lw = dense_terms(rl, li, lv)
            nd = ds.numel()
            sums = torch.zeros(nb, 3, 32)

            ds3 = torch.cat([ds, ds[-1:].expand(7)]) * 64  # byte offsets, the last repeated PF + 1 = 7 times

            def call(mode, l1=False, reps=1):
                arr, light_w = ((d16, lw), (dsa, lw), (dfl, lw), (d16, lw), (d16, lw), (d16, lw))[mode]
                return lib.dense_pass(arr.data_ptr(), 0 if l1 else Pd * 32, (ds3 if mode in (3, 4) else ds).data_ptr(), nd,
                                      light_w.data_ptr(), nb, mode, sums.data_ptr(), reps)

            ref = {}
            for l1 in (False, True):
                call(0, l1)
                ref[l1] = sums.clone()
                for mode in (1, 2, 3, 4, 5):
                    call(mode, l1)
                    assert torch.equal(sums, ref[l1]) or mode == 2 and torch.allclose(sums, ref[l1], rtol=1e-5, atol=1e-3), \
                        (mode, l1, float((sums - ref[l1]).abs().max()))
            res = {"light": light, "N": N, "nd": nd, "tb": nd * nb}
            for label, mode, l1 in (("kernel form, L1", 0, True), ("prefetch across blocks", 5, False),
                                    ("lean loop", 3, False), ("lean loop, L1", 3, True),
                                    ("lean, 2 terms a step", 4, False), ("lean, 2 terms a step, L1", 4, True),
                                    ("shifts", 1, False), ("shifts, L1", 1, True),
                                    ("float", 2, False), ("float, L1", 2, True)):
                p = measure_paired(lambda m=mode, x=l1: call(m, x, args.reps), lambda: call(0, False, args.reps), repeats=15,
                                   warmup=1, clock=time.thread_time)
                res["kernel form"] = p.peer.median / args.reps * 1e6
                res[label] = p.test.median / args.reps * 1e6
                res[label + " ratio"] = p.speedup
                print(f"[dense_micro] {light} N={N} nd={nd} {label}: {res[label]:.1f} us, kernel form "
                      f"{res['kernel form']:.1f} us, kernel form/this {p.speedup:.3f}", flush=True)
            rows.append(res)
    m = machine_info()
    L = ["# Wavelet kernel: the dense GEMV alone (issue 39)\n",
         f"{m['cpu']} at {ghz:.2f} GHz (measured: a chain of dependent multiplies), one thread, `-O3 -march=native` "
         f"(this benchmark's own 8-lane AVX2 code on every CPU; this CPU: {m.get('cpu_isa')});"
         f" load average {load0:.1f} → {os.getloadavg()[0]:.1f} (shared machine; "
         f"this thread's CPU time). The kernel section's transfer (V = {rl.V}, R = 32, K = 256, {BITS}-bit, "
         f"{Pd} dense columns, {nb} blocks of 32 vertices); CT = 1, RGB. µs per pass over every block (sums stored, "
         "no output), the median of 15 paired samples of "
         f"{args.reps} passes against the kernel form on the real layout; **kernel form / variant** > 1: the variant "
         "is faster; cycles per (term, 32-vertex block) at the measured clock (the multiply-adds' floor: 12 on two "
         "pipes, 6 cycles). Variants in the module docstring. Reproduce: "
         "`.venv/bin/python benchmarks/bench_wavelet_dense_micro.py`.\n",
         "| light | N | dense terms | variant | µs per pass | cycles per term and block | **kernel form / variant** |",
         "|---|---|---|---|---|---|---|"]
    for r in rows:
        for label in ("kernel form", "kernel form, L1", "prefetch across blocks", "lean loop", "lean loop, L1",
                      "lean, 2 terms a step",
                      "lean, 2 terms a step, L1", "shifts", "shifts, L1", "float",
                      "float, L1"):
            cyc = r[label] * 1e3 * ghz / r["tb"]
            ratio = "1.00" if label == "kernel form" else f"{r[label + ' ratio']:.2f}"
            L.append(f"| {r['light']} | {r['N']} | {r['nd']} | {label} | {r[label]:.1f} | {cyc:.1f} | **{ratio}** |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_dense_micro.md", "\n".join(L) + "\n")
    print(f"[dense_micro] wrote {OUT / 'wavelet_dense_micro.md'}", flush=True)


if __name__ == "__main__":
    main()
