"""The wavelet kernel's call cost in a render loop (issue 39, the set-up's fixed part; one thread):
``WaveletRelighter.prepared``'s ``run()`` with the kernel's eight arguments passed through ctypes at every call
(``functools.partial`` of the eight-argument entry point: the form before) against the same kernel with its arguments
packed once into an int64 array (``prt_wavelet_relight_*_packed``: one pointer to convert per call, the form now),
paired by this thread's CPU time; both run the same kernel on the same light into the same output, so the
difference is the call. Also a trivial C function (returns at once) with eight and with one argument: the ctypes
conversion alone. The kernel section's transfer (occluder_over_plane small, R = 32, K = 256, 16 bits), the studio
light at N = 1 (a column no vertex keeps: set-up and output only), 10, 100, 1000 and all terms.

Writes reports/benchmarks/wavelet_call.md (CPU, path and load average named).

    .venv/bin/python benchmarks/bench_wavelet_call.py     (about 30 s)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import ctypes  # noqa: E402
import functools  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, OUT  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import machine_info, measure_paired  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

TRIVIAL = r"""
#include <stdint.h>
int call8(const void *a, int64_t b, const void *c, const void *d, int64_t e, const void *f, void *g, int64_t h) {
    (void)a; (void)c; (void)d; (void)f; (void)g; return (int)(b + e + h) & 0; }
int call1(const int64_t *a) { return (int)a[1] & 0; }
"""


def eight_argument_run(rl, li: torch.Tensor, lv: torch.Tensor, out: torch.Tensor):
    """``prepared``'s run() as it was: the eight-argument kernel through ``functools.partial`` (converted per call)."""
    f = rl._factor(lv.shape[0], True)
    call = functools.partial(rl._kernel(), li.numel(), li.data_ptr(), lv.data_ptr(), lv.shape[0], f.data_ptr(),
                             out.data_ptr(), 1)
    held = (li, lv, f, out)

    def run():
        st = call()
        if st != 0:
            rl._check_indices(held[0])
        return out
    return run


def main() -> None:
    torch.set_num_threads(1)
    reps = 200
    lib, how = compile_library("wavelet_call_trivial", TRIVIAL, ["-O2", "-shared", "-fPIC", "-std=c99"], {})
    if lib is None:
        raise SystemExit(f"bench_wavelet_call: no compiler: {how}")
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    lib.call8.argtypes, lib.call1.argtypes = [vp, i64, vp, vp, i64, vp, vp, i64], [vp]
    packed = torch.zeros(8, dtype=torch.int64)
    c8 = functools.partial(lib.call8, 1 << 20, 1000, 1 << 20, 1 << 20, 3, 1 << 20, 1 << 20, 1)
    c1 = functools.partial(lib.call1, packed.data_ptr())

    def loop(fn):
        def f():
            for _ in range(reps):
                fn()
        return f

    tr = precompute_wavelet(builtin("occluder_over_plane", "small"), 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="both")
    if rl._kernel() is None:
        raise SystemExit("bench_wavelet_call: no compiled wavelet kernel")
    load0 = os.getloadavg()[0]
    rows = []
    p = measure_paired(loop(c1), loop(c8), repeats=15, warmup=1, clock=time.thread_time)
    rows.append({"what": "trivial C function, 1 argument vs 8", "N": "–", "before": p.peer.median / reps * 1e6,
                 "now": p.test.median / reps * 1e6, "ratio": p.speedup, "q": (p.ratio.q1, p.ratio.q3)})
    empty = torch.nonzero(rl.cls == 0).flatten()[:1]
    for N in (1, 10, 100, 1000, rl.P):
        if N == 1:
            li, lv = empty.clone(), torch.ones(3, 1)
        else:
            li, lv, _ = rl.light("studio", N, "transport")
            lv = lv.to(torch.float32).contiguous()
        out = torch.empty(rl.V, 3)
        new = rl.prepared(li, lv, out)
        old = eight_argument_run(rl, li, lv, out)
        ref = old().clone()
        assert torch.equal(new(), ref)  # the same kernel, the same output
        p = measure_paired(loop(new), loop(old), repeats=15, warmup=1, clock=time.thread_time)
        rows.append({"what": "kernel through prepared: packed vs eight arguments", "N": N if N != 1 else "1 (empty column)",
                     "before": p.peer.median / reps * 1e6, "now": p.test.median / reps * 1e6, "ratio": p.speedup,
                     "q": (p.ratio.q1, p.ratio.q3)})
        print(f"[wavelet_call] {rows[-1]}", flush=True)
    m = machine_info()
    L = ["# Wavelet kernel: the cost of the call (issue 39)\n",
         f"{m['cpu']}, one thread (the kernel's {relight.wavelet_kernel_path().get('isa')} build: {relight.wavelet_kernel_path()['path']}),"
         f" load average {load0:.1f} → "
         f"{os.getloadavg()[0]:.1f} (shared machine; this thread's CPU time). `WaveletRelighter.prepared`'s run() with the "
         "kernel's arguments packed once into an int64 array (one pointer converted by ctypes per call: the form now) "
         "against the eight-argument entry point through `functools.partial` (the form before), the same kernel on the "
         f"same light and output (outputs equal bit for bit); µs per call, the median of 15 paired samples of {reps} calls; "
         "**before / now** > 1: packing is faster [quartiles of the per-sample ratios]. The kernel section's transfer "
         f"(V = {rl.V}, R = 32, K = 256, {BITS}-bit), studio light. Reproduce: `.venv/bin/python benchmarks/bench_wavelet_call.py`.\n",
         "| what | N | before (µs per call) | now (µs per call) | saved (µs) | **before / now** [quartiles] |", "|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['what']} | {r['N']} | {r['before']:.2f} | {r['now']:.2f} | {r['before'] - r['now']:.2f} | "
                 f"**{r['ratio']:.3f}** [{r['q'][0]:.3f}, {r['q'][1]:.3f}] |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_call.md", "\n".join(L) + "\n")
    print(f"[wavelet_call] wrote {OUT / 'wavelet_call.md'}", flush=True)


if __name__ == "__main__":
    main()
