"""The core's own floor for the wavelet kernel's two inner loops (issue 39): their instruction mixes alone, in
x86-64 assembly (AVX2), over data that stays in L1, timed by this thread's CPU time and stated in cycles at the
clock rate measured in the same run (a chain of dependent integer adds, one cycle each).

  - dense: per (term, 32-vertex block) of ``kernels/wavelet.c``'s register-blocked GEMV for RGB: 12 multiply-adds
    into 12 independent sums, with what each term adds to them one at a time (3 light broadcasts, 4 widening
    loads ``vpmovsxwd``, 4 conversions ``vcvtdq2ps``), and alternatives (light pre-broadcast as 3 plain loads; the
    widening by shifts/and of 32-bit lanes);
  - sparse: per 8-vertex block of the column-major pass: its address from an int32 offset table, its values
    (16-bit widened and converted, or float), three 32-byte read-modify-writes of the tile's scratch (load,
    multiply-add, store), the blocks visited in a sweep (stride 1), scattered (stride 37 of 144 blocks) or all
    the same block (stride 0: each read waits for the previous store: the chain); also 4-vertex blocks
    (128-bit), the stores alone and the loads alone.

These are floors of the loops' bodies (no loop control beyond a counter, no range set-up, no memory traffic
beyond L1): what the kernel's loops measure above them is what any rewrite of their code could win. Writes
reports/benchmarks/wavelet_floor_micro.md.

    .venv/bin/python benchmarks/bench_wavelet_floor_micro.py     (about 10 s; x86-64 only)
"""

from __future__ import annotations

import ctypes
import os
import platform
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import OUT  # noqa: E402

from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402

SRC = r"""
#define _POSIX_C_SOURCE 199309L
#include <stdint.h>
#include <time.h>
static double now(void) { struct timespec a; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &a); return a.tv_sec + a.tv_nsec * 1e-9; }
static float acc[144 * 32] __attribute__((aligned(64)));
static float lt[64] __attribute__((aligned(64)));
static short vals[1 << 16] __attribute__((aligned(64)));
static int ofs[4096] __attribute__((aligned(64)));

double clock_ghz(void) {
    long m = 200000000, x = 0;
    const double t0 = now();
    __asm__ volatile("1: add $1, %0\n add $1, %0\n add $1, %0\n add $1, %0\n dec %1\n jnz 1b" : "+r"(x), "+r"(m));
    return 4.0 * 200000000 / (now() - t0) / 1e9;
}

#define F12 "vfmadd231ps %%ymm14,%%ymm15,%%ymm0\n vfmadd231ps %%ymm14,%%ymm15,%%ymm1\n vfmadd231ps %%ymm14,%%ymm15,%%ymm2\n" \
    "vfmadd231ps %%ymm14,%%ymm15,%%ymm3\n vfmadd231ps %%ymm14,%%ymm15,%%ymm4\n vfmadd231ps %%ymm14,%%ymm15,%%ymm5\n"          \
    "vfmadd231ps %%ymm14,%%ymm15,%%ymm6\n vfmadd231ps %%ymm14,%%ymm15,%%ymm7\n vfmadd231ps %%ymm14,%%ymm15,%%ymm8\n"          \
    "vfmadd231ps %%ymm14,%%ymm15,%%ymm9\n vfmadd231ps %%ymm14,%%ymm15,%%ymm10\n vfmadd231ps %%ymm14,%%ymm15,%%ymm11\n"
#define BC3 "vbroadcastss (%1),%%ymm12\n vbroadcastss 4(%1),%%ymm13\n vbroadcastss 8(%1),%%ymm12\n"
#define MV3 "vmovaps (%1),%%ymm12\n vmovaps 32(%1),%%ymm13\n vmovaps 64(%1),%%ymm12\n"
#define W4 "vpmovsxwd (%2),%%ymm12\n vcvtdq2ps %%ymm12,%%ymm12\n vpmovsxwd 16(%2),%%ymm13\n vcvtdq2ps %%ymm13,%%ymm13\n" \
    "vpmovsxwd 32(%2),%%ymm12\n vcvtdq2ps %%ymm12,%%ymm12\n vpmovsxwd 48(%2),%%ymm13\n vcvtdq2ps %%ymm13,%%ymm13\n"
#define SH4 "vmovdqa (%2),%%ymm12\n vpsrad $16,%%ymm12,%%ymm13\n vcvtdq2ps %%ymm13,%%ymm13\n vpslld $16,%%ymm12,%%ymm12\n"   \
    "vpsrad $16,%%ymm12,%%ymm12\n vcvtdq2ps %%ymm12,%%ymm12\n vmovdqa 32(%2),%%ymm12\n vpsrad $16,%%ymm12,%%ymm13\n"           \
    "vcvtdq2ps %%ymm13,%%ymm13\n vpslld $16,%%ymm12,%%ymm12\n vpsrad $16,%%ymm12,%%ymm12\n vcvtdq2ps %%ymm12,%%ymm12\n"
#define DENSE(NAME, EXTRA)                                                                                    \
double NAME(long n) {                                                                                        \
    const double t0 = now();                                                                                 \
    __asm__ volatile("2: " F12 EXTRA "dec %0\n jnz 2b" : "+r"(n) : "r"(lt), "r"(vals)                        \
                     : "xmm0", "xmm1", "xmm2", "xmm3", "xmm4", "xmm5", "xmm6", "xmm7", "xmm8", "xmm9", "xmm10", \
                       "xmm11", "xmm12", "xmm13", "memory");                                                  \
    return now() - t0;                                                                                       \
}
DENSE(d_fma, "")
DENSE(d_bc, BC3)
DENSE(d_cvt, "vcvtdq2ps %%ymm12,%%ymm13\n vcvtdq2ps %%ymm12,%%ymm13\n vcvtdq2ps %%ymm12,%%ymm13\n vcvtdq2ps %%ymm12,%%ymm13\n")
DENSE(d_pmov, "vpmovsxwd (%2),%%ymm12\n vpmovsxwd 16(%2),%%ymm13\n vpmovsxwd 32(%2),%%ymm12\n vpmovsxwd 48(%2),%%ymm13\n")
DENSE(d_w4, W4)
DENSE(d_kernel, W4 BC3)
DENSE(d_kernel_mv, W4 MV3)
DENSE(d_shifts, SH4 BC3)

/* per block: e (%1) counts 0..4095; address acc + ofs[e]; values at vals + 16 e (or + 8 e for 4-vertex blocks) */
#define ADDR "movslq (%4,%1,4),%%rax\n add %2,%%rax\n mov %1,%%rcx\n"
#define RMW3(R) "vmovups (%%rax),%%" R "3\n vfmadd231ps %%" R "0,%%" R "15,%%" R "3\n vmovups %%" R "3,(%%rax)\n"       \
    "vmovups 32(%%rax),%%" R "1\n vfmadd231ps %%" R "0,%%" R "14,%%" R "1\n vmovups %%" R "1,32(%%rax)\n"              \
    "vmovups 64(%%rax),%%" R "2\n vfmadd231ps %%" R "0,%%" R "13,%%" R "2\n vmovups %%" R "2,64(%%rax)\n"
#define SPARSE(NAME, BODY)                                                                                   \
double NAME(long n, int stride) {                                                                            \
    for (int i = 0; i < 4096; i++) ofs[i] = ((i * stride) % 144) * 128;                                      \
    long e = 0;                                                                                              \
    const double t0 = now();                                                                                 \
    __asm__ volatile("vbroadcastss (%5),%%ymm13\n vbroadcastss 4(%5),%%ymm14\n vbroadcastss 8(%5),%%ymm15\n"     \
                     "vxorps %%ymm0,%%ymm0,%%ymm0\n"                                                         \
                     "2: " BODY "inc %1\n and $4095,%1\n dec %0\n jnz 2b"                                     \
                     : "+r"(n), "+r"(e) : "r"(acc), "r"(vals), "r"(ofs), "r"(lt)                             \
                     : "rax", "rcx", "xmm0", "xmm1", "xmm2", "xmm3", "xmm13", "xmm14", "xmm15", "memory");      \
    return now() - t0;                                                                                       \
}
SPARSE(s_rmw, ADDR RMW3("ymm"))
SPARSE(s_kernel, ADDR "shl $4,%%rcx\n vpmovsxwd (%3,%%rcx),%%ymm0\n vcvtdq2ps %%ymm0,%%ymm0\n" RMW3("ymm"))
SPARSE(s_float, ADDR "shl $4,%%rcx\n vmovups (%3,%%rcx),%%ymm0\n" RMW3("ymm"))
SPARSE(s_w4, ADDR "shl $3,%%rcx\n vpmovsxwd (%3,%%rcx),%%xmm0\n vcvtdq2ps %%xmm0,%%xmm0\n" RMW3("xmm"))
SPARSE(s_loads, ADDR "shl $4,%%rcx\n vpmovsxwd (%3,%%rcx),%%ymm0\n vcvtdq2ps %%ymm0,%%ymm0\n"
       "vmovups (%%rax),%%ymm3\n vfmadd231ps %%ymm0,%%ymm15,%%ymm3\n vmovups 32(%%rax),%%ymm1\n vfmadd231ps %%ymm0,%%ymm14,%%ymm1\n"
       "vmovups 64(%%rax),%%ymm2\n vfmadd231ps %%ymm0,%%ymm13,%%ymm2\n")
SPARSE(s_stores, ADDR "shl $4,%%rcx\n vpmovsxwd (%3,%%rcx),%%ymm0\n vcvtdq2ps %%ymm0,%%ymm0\n"
       "vmulps %%ymm0,%%ymm15,%%ymm3\n vmovups %%ymm3,(%%rax)\n vmulps %%ymm0,%%ymm14,%%ymm1\n vmovups %%ymm1,32(%%rax)\n"
       "vmulps %%ymm0,%%ymm13,%%ymm2\n vmovups %%ymm2,64(%%rax)\n")
"""

DENSE = (("d_fma", "12 multiply-adds alone"), ("d_bc", "+ 3 light broadcasts (vbroadcastss m32)"),
         ("d_cvt", "+ 4 conversions alone (vcvtdq2ps)"), ("d_pmov", "+ 4 widening loads alone (vpmovsxwd m128)"),
         ("d_w4", "+ 4 widening loads and 4 conversions"),
         ("d_kernel", "**the kernel's mix**: + widening, conversions, 3 broadcasts"),
         ("d_kernel_mv", "the kernel's mix, light pre-broadcast (3 plain 32-byte loads)"),
         ("d_shifts", "widening by shifts of 32-bit lanes (2 loads, 6 shifts, 4 conversions) + 3 broadcasts"))
SPARSE = (("s_rmw", "3 read-modify-writes, address from the offset table"),
          ("s_kernel", "**the kernel's block**: + 8 values widened and converted"),
          ("s_float", "+ 8 float values (no conversion)"), ("s_w4", "4-vertex block: 4 values, 128-bit read-modify-writes"),
          ("s_loads", "the kernel's block without its 3 stores"), ("s_stores", "the kernel's block without its 3 scratch loads"))


def main() -> None:
    if platform.machine() not in ("x86_64", "AMD64"):
        raise SystemExit(f"bench_wavelet_floor_micro: x86-64 assembly; this machine is {platform.machine()}")
    lib, how = compile_library("wavelet_floor_micro", SRC, ["-O2", "-shared", "-fPIC", "-std=c99"], {})
    if lib is None:
        raise SystemExit(f"bench_wavelet_floor_micro: no compiler: {how}")
    for name, _ in DENSE:
        getattr(lib, name).restype = ctypes.c_double
        getattr(lib, name).argtypes = [ctypes.c_long]
    for name, _ in SPARSE:
        getattr(lib, name).restype = ctypes.c_double
        getattr(lib, name).argtypes = [ctypes.c_long, ctypes.c_int]
    lib.clock_ghz.restype = ctypes.c_double
    load0 = os.getloadavg()[0]
    n = 20_000_000
    ghz = [lib.clock_ghz()]
    dense = {name: min(getattr(lib, name)(n) for _ in range(3)) for name, _ in DENSE}
    sparse = {(name, s): min(getattr(lib, name)(n, s) for _ in range(3)) for name, _ in SPARSE for s in (1, 37, 0)}
    ghz.append(lib.clock_ghz())
    f = sum(ghz) / 2
    m = machine_info()
    L = ["# Wavelet kernel: the core's floor for its two inner loops (issue 39)\n",
         f"{m['cpu']}, clock {ghz[0]:.2f} / {ghz[1]:.2f} GHz (measured before / after: dependent integer adds), one "
         f"thread, AVX2 (no AVX-512 on this CPU); load average {load0:.1f} → {os.getloadavg()[0]:.1f} (shared "
         "machine; this thread's CPU time, the best of 3 runs of 2·10^7 iterations). The loops' instruction mixes "
         "alone, in assembly, on L1-resident data (module docstring). Reproduce: "
         "`.venv/bin/python benchmarks/bench_wavelet_floor_micro.py`.\n",
         "## Dense GEMV: per (term, 32-vertex block), RGB\n",
         "| mix | cycles |", "|---|---|"]
    for name, label in DENSE:
        L.append(f"| {label} | {dense[name] * f * 1e9 / n:.2f} |")
    L += ["\n## Sparse column-major pass: per 8-vertex block, RGB\n",
          "| mix | sweep (stride 1) | scattered (stride 37) | one block (stride 0: store → load chain) |",
          "|---|---|---|---|"]
    for name, label in SPARSE:
        L.append(f"| {label} | " + " | ".join(f"{sparse[(name, s)] * f * 1e9 / n:.2f}" for s in (1, 37, 0)) + " |")
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "wavelet_floor_micro.md").write_text("\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
