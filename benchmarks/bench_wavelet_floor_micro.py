"""The core's own floor for the wavelet kernel's two inner loops (issue 39): their instruction mixes alone, in
x86-64 assembly (AVX2), over data that stays in L1, timed by this thread's CPU time and stated in cycles at the
clock rate measured in the same run (a chain of dependent 64-bit multiplies, 3 cycles each).

  - dense: per (term, 32-vertex block) of ``kernels/wavelet.c``'s register-blocked GEMV for RGB: 12 multiply-adds
    into 12 independent sums, with what each term adds to them one at a time (3 light broadcasts, 4 widening
    loads ``vpmovsxwd``, 4 conversions ``vcvtdq2ps``), and alternatives (light pre-broadcast as 3 plain loads; the
    widening by shifts/and of 32-bit lanes);
  - sparse: per 8-vertex block of the column-major pass: its address from an int32 offset table, its values
    (16-bit widened and converted, or float), three 32-byte read-modify-writes of the tile's scratch (load,
    multiply-add, store), the blocks visited in a sweep (stride 1), scattered (stride 37 of 144 blocks) or all
    the same block (stride 0: each read waits for the previous store: the chain); also 4-vertex blocks
    (128-bit), the stores alone and the loads alone;
  - both in one loop step (``bench_wavelet_fused_micro.py``'s question without its loop): a dense half step
    (16 vertices, 6 sums) and one sparse block, against each alone.

These are floors of the loops' bodies (no loop control beyond a counter, no range set-up, no memory traffic
beyond L1): what the kernel's loops measure above them is what any rewrite of their code could win.

Then the model: per light (studio, sky; transport-weighted) and N (100, 300, 1000: the column-major pass), the
kernel's work counted — dense (term, 32-vertex block) steps, the light's sparse 8-vertex blocks — times those
floors at the measured clock, plus the kernel's own set-up (timed alone: ``kernels/wavelet.c`` compiled here with
a return right after the light is gathered and its terms listed; also cut after each of its steps, the set-up by
step at N = 1000) and output pass (a one-term call of a column no
vertex keeps, less its set-up): the kernel's time if both loops ran at their instruction mixes' floor. Against
the kernel (its eight-argument entry point, the probes' form; ``WaveletRelighter.prepared`` packs them)
and its read-once/write-once bound (``timing.io_bound_fn``), paired by
one thread's CPU time (median of 15). Writes reports/benchmarks/wavelet_floor_micro.md.

    .venv/bin/python benchmarks/bench_wavelet_floor_micro.py     (about 30 s; x86-64 only)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import ctypes  # noqa: E402
import os  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet_isa import rl_bytes  # noqa: E402
from bench_wavelet import BITS, LIGHTS, OUT  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import KERNELS_DIR, LIBRARIES, compile_library  # noqa: E402
from prt_torch.harness.timing import io_bound_fn, machine_info, measure_paired  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

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
    long m = 30000000, x = 3;  /* multiplies: 3 cycles each (an add-immediate chain is folded at rename on recent Intel cores) */
    const double t0 = now();
    __asm__ volatile("1: imul %0, %0\n imul %0, %0\n imul %0, %0\n imul %0, %0\n dec %1\n jnz 1b" : "+r"(x), "+r"(m));
    return 12.0 * 30000000 / (now() - t0) / 1e9;
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

/* the two interleaved (bench_wavelet_fused_micro.py's question at the instruction level): a dense half step (16
 * vertices: 2 widening loads and conversions, 3 broadcasts, 6 multiply-adds into 6 sums) and one sparse block */
static short dvals[1 << 16] __attribute__((aligned(64)));
#define F6 "vfmadd231ps %%ymm4,%%ymm12,%%ymm0\n vfmadd231ps %%ymm4,%%ymm13,%%ymm1\n vfmadd231ps %%ymm4,%%ymm14,%%ymm2\n" \
    "vfmadd231ps %%ymm5,%%ymm12,%%ymm6\n vfmadd231ps %%ymm5,%%ymm13,%%ymm7\n vfmadd231ps %%ymm5,%%ymm14,%%ymm8\n"
#define DH "vpmovsxwd (%5),%%ymm4\n vcvtdq2ps %%ymm4,%%ymm4\n vpmovsxwd 16(%5),%%ymm5\n vcvtdq2ps %%ymm5,%%ymm5\n"     \
    "vbroadcastss (%3),%%ymm12\n vbroadcastss 4(%3),%%ymm13\n vbroadcastss 8(%3),%%ymm14\n" F6
#define DHV "mov %1,%%rdx\n shl $6,%%rdx\n and $65535,%%rdx\n vpmovsxwd (%5,%%rdx),%%ymm4\n vcvtdq2ps %%ymm4,%%ymm4\n" \
    "vpmovsxwd 16(%5,%%rdx),%%ymm5\n vcvtdq2ps %%ymm5,%%ymm5\n"                                                  \
    "vbroadcastss (%3),%%ymm12\n vbroadcastss 4(%3),%%ymm13\n vbroadcastss 8(%3),%%ymm14\n" F6
#define SBT "movslq (%4,%1,4),%%rax\n add %2,%%rax\n mov %1,%%rcx\n shl $4,%%rcx\n"
#define SBC "mov %1,%%rax\n imul $37,%%rax\n and $127,%%rax\n shl $7,%%rax\n add %2,%%rax\n mov %1,%%rcx\n shl $4,%%rcx\n"
#define SB "vpmovsxwd (%6,%%rcx),%%ymm15\n vcvtdq2ps %%ymm15,%%ymm15\n"                                              \
    "vmovups (%%rax),%%ymm3\n vfmadd231ps %%ymm15,%%ymm9,%%ymm3\n vmovups %%ymm3,(%%rax)\n"                            \
    "vmovups 32(%%rax),%%ymm3\n vfmadd231ps %%ymm15,%%ymm10,%%ymm3\n vmovups %%ymm3,32(%%rax)\n"                      \
    "vmovups 64(%%rax),%%ymm3\n vfmadd231ps %%ymm15,%%ymm11,%%ymm3\n vmovups %%ymm3,64(%%rax)\n"
#define MIX(NAME, BODY)                                                                                      \
double NAME(long n) {                                                                                        \
    for (int i = 0; i < 4096; i++) ofs[i] = ((i * 37) % 144) * 128;                                           \
    long e = 0;                                                                                              \
    const double t0 = now();                                                                                 \
    __asm__ volatile("vbroadcastss (%3),%%ymm9\n vbroadcastss 4(%3),%%ymm10\n vbroadcastss 8(%3),%%ymm11\n"      \
                     "2: " BODY "inc %1\n and $4095,%1\n dec %0\n jnz 2b"                                     \
                     : "+r"(n), "+r"(e) : "r"(acc), "r"(lt), "r"(ofs), "r"(dvals), "r"(vals)                 \
                     : "rax", "rcx", "rdx", "xmm0", "xmm1", "xmm2", "xmm3", "xmm4", "xmm5", "xmm6", "xmm7", "xmm8", \
                       "xmm9", "xmm10", "xmm11", "xmm12", "xmm13", "xmm14", "xmm15", "memory");              \
    return now() - t0;                                                                                       \
}
MIX(m_dense, DH)
MIX(m_sparse, SBT SB)
MIX(m_both, DH SBT SB)
MIX(m_both_computed, DH SBC SB)
MIX(m_both_varying, DHV SBT SB)
"""

MIX = (("m_dense", "a dense half step alone (6 sums: each one multiply-add per step, the 4-cycle latency)"),
       ("m_sparse", "a sparse block alone (address from the offset table)"),
       ("m_both", "**both in one step** (address from the table)"),
       ("m_both_computed", "both, the sparse address computed (no load)"),
       ("m_both_varying", "both, the dense values from a moving address"))

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
    for name, _ in DENSE + MIX:
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
    mix = {name: min(getattr(lib, name)(n) for _ in range(3)) for name, _ in MIX}
    ghz.append(lib.clock_ghz())
    f = sum(ghz) / 2
    m = machine_info()
    L = ["# Wavelet kernel: the core's floor for its two inner loops (issue 39)\n",
         f"{m['cpu']}, clock {ghz[0]:.2f} / {ghz[1]:.2f} GHz (measured before / after: dependent multiplies), one "
         f"thread, AVX2 (this benchmark's own 8-lane code on every CPU; this CPU: {m.get('cpu_isa')});"
         f" load average {load0:.1f} → {os.getloadavg()[0]:.1f} (shared "
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
    L += ["\n## A dense half step and a sparse block in one loop step (the fused form's question)\n",
          "| mix | cycles per step |", "|---|---|"]
    for name, label in MIX:
        L.append(f"| {label} | {mix[name] * f * 1e9 / n:.2f} |")
    L += model(f, dense["d_kernel"] * f * 1e9 / n, sparse[("s_kernel", 37)] * f * 1e9 / n)
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_floor_micro.md", "\n".join(L) + "\n")
    print("\n".join(L))


#: the set-up probes' cut points in kernels/wavelet.c (a return inserted before each line), cumulative
SETUP_CUTS = (("call, checks (index, grey light), the light's closing zeroing", "    unsigned char *mark = L->mark;"),
              ("+ marks cleared, light gathered per column", "    const int rows = sb && L->NR"),
              ("+ dense terms listed", "    i64 *sw = wk + Pd;"),
              ("+ sparse terms listed: the set-up", "    const T *rvals = (const T *)L->rvals;"))


def setup_probe(marker: str):
    """``kernels/wavelet.c`` compiled with a return inserted before the line ``marker`` (one of
    :data:`SETUP_CUTS`: what the kernel does before the tiles, up to there; the light table zeroed again as the
    kernel does at its end): the i16 entry point, or None without a compiler."""
    names, flags = LIBRARIES["wavelet"]
    src = (KERNELS_DIR / names[0]).read_text()
    if marker not in src:
        raise SystemExit(f"bench_wavelet_floor_micro: kernels/wavelet.c changed: the set-up probe's cut {marker.strip()!r} "
                         "is gone")
    cut = "    { float *lp_ = L->lp; for (i64 n = 0; n < N; n++) memset(lp_ + 4 * sel[n], 0, 4 * sizeof(float)); return 0; } \\\n"
    lib, how = compile_library("wavelet_setup_probe", src.replace(marker, cut + marker, 1), list(flags), {})
    if lib is None:
        return None
    fn = lib.prt_wavelet_relight_i16
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    fn.argtypes = [vp, i64, vp, vp, i64, vp, vp, i64]
    return fn


def model(ghz: float, dense_cyc: float, sparse_cyc: float) -> list[str]:
    """The floor model's table (module docstring)."""
    torch.set_num_threads(1)
    probes = [setup_probe(m) for _, m in SETUP_CUTS]
    probe = probes[-1]
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1)
    nb = rl.dense.shape[0]
    out = torch.empty(rl.V, 3)
    f3 = rl._factor(3, True)
    rl.prepared(torch.zeros(1, dtype=torch.int64), torch.ones(3, 1), out)()  # binds the layout
    lay = rl._layout.data_ptr()

    def setup(li, lv, fn=None):
        fn = fn or probe
        return lambda: fn(lay, li.numel(), li.data_ptr(), lv.data_ptr(), 3, f3.data_ptr(), out.data_ptr(), 1)

    def cpu(fn, peer):
        p = measure_paired(fn, peer, repeats=15, warmup=1, clock=time.thread_time)
        return p.test.median * 1e6, p.peer.median * 1e6

    empty = torch.nonzero(rl.cls == 0).flatten()[:1].contiguous()
    one = torch.ones(3, 1)
    # the kernel through its eight-argument entry point, the probes' form (prepared packs its arguments: ~0.8 us less
    # per call, benchmarks/bench_wavelet_call.py), so that the two sides differ only by the work after the cut
    kern8 = rl._native.func
    out_call, out_setup = cpu(setup(empty, one, kern8), setup(empty, one))
    load0 = os.getloadavg()[0]
    L = ["\n## The kernel against its loops' floor (R = 32, K = 256, 16-bit, V = %d, one thread)\n" % rl.V,
         f"Dense steps × {dense_cyc:.2f} cycles (the kernel's mix above) + sparse blocks × {sparse_cyc:.2f} (the "
         f"kernel's block, scattered) at {ghz:.2f} GHz, + the set-up timed alone + the output pass ({out_call - out_setup:.1f} µs: "
         f"a one-term call {out_call:.1f} µs less its set-up {out_setup:.1f} µs); load average {load0:.1f}. The kernel "
         "and its bound paired by CPU time; **bound / floor**: the fraction of its bound the kernel would reach at "
         "its loops' floor.\n",
         "| light | N | dense steps | sparse blocks | kernel µs | bound µs | kernel of bound | set-up µs | floor µs "
         "| **bound / floor** | kernel / floor |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for light in ("studio", "sky (sun)"):
        for N in (100, 300, 1000):
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            lv = lv.to(torch.float32).contiguous()
            d = rl.dslot[li] >= 0
            s = li[~d]
            sb = int(rl.bcount[:, s[rl.nnz[s] > 0]].sum())
            if sb >= rl.row_min * rl.NB:
                continue  # the row-major pass: not this model's
            rl.prepared(li, lv, out)()
            call = setup(li, lv, kern8)
            k_us, b_us = cpu(call, io_bound_fn(rl_bytes(rl, li), rl.V * 12))
            s_us, _ = cpu(setup(li, lv), call)
            steps = int(d.sum()) * nb
            floor = (steps * dense_cyc + sb * sparse_cyc) / ghz / 1e3 + s_us + (out_call - out_setup)
            L.append(f"| {light} | {N} | {steps} | {sb} | {k_us:.1f} | {b_us:.1f} | {b_us / k_us:.2f} | {s_us:.1f} | "
                     f"{floor:.1f} | **{b_us / floor:.2f}** | {k_us / floor:.2f} |")
            print(L[-1], flush=True)
    L += ["\n### The set-up by step (cumulative, µs; one thread's CPU time, median of 15)\n",
          "| light | N | " + " | ".join(label for label, _ in SETUP_CUTS) + " |", "|---|---|" + "---|" * len(SETUP_CUTS)]
    for light, N in (("one term", 1), ("studio", 1000), ("sky (sun)", 1000)):
        if N == 1:
            li, lv = empty, one
        else:
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            lv = lv.to(torch.float32).contiguous()
        rl.prepared(li, lv, out)()
        call = setup(li, lv, kern8)
        L.append(f"| {light} | {N} | " + " | ".join(f"{cpu(setup(li, lv, fn), call)[0]:.2f}" for fn in probes) + " |")
        print(L[-1], flush=True)
    return L


if __name__ == "__main__":
    main()
