"""Where the wavelet kernel's one-thread time goes (issue 39): a light's terms split into its parts, each
relit alone through the same kernel and paired with its own read-once/write-once bounds (the transfer bytes
that part reads, :meth:`WaveletRelighter.bytes_read`, plus the output): the copy bound
(``timing.io_bound_fn``) and the streaming read (``timing.read_bound_fn``).

Lights (transport-weighted): studio at N = 100 and 300 (its 292 nonzero terms: N = 300 ... all relight the same)
and sky at N = 100, 300, 1000, 2000 and all. Parts, per light and N (the kernel section's transfer:
occluder_over_plane small, R = 32, K = 256, 16 bits):
  - all: the light's N terms (the kernel section's row);
  - dense: its terms stored as dense columns alone (the register-blocked GEMV and the output pass);
  - sparse: its block-sparse terms alone (the column-major pass into the tiles' scratch, or the
    row-major pass when they hold >= row_min of the sparse blocks; then the output pass);
  - output: one term of a column no vertex keeps (the light's set-up and the output pass alone:
    the scratch's sums times the per-vertex factor, written once; bound: the output's fill).
Each part's time includes the set-up and the output pass, so parts do not add up to "all".

Every microsecond of a whole call by step (set-up, passes, output): bench_wavelet_setup.py.

Writes the section of this CPU and kernel build (the process's: ``PRT_TORCH_KERNEL_ISA``) of
reports/benchmarks/wavelet_parts.md, keeping the other sections (one thread; CPU, build and load average named).

    .venv/bin/python benchmarks/bench_wavelet_parts.py
    PRT_TORCH_KERNEL_ISA=avx2 .venv/bin/python benchmarks/bench_wavelet_parts.py     (the AVX2 build on an AVX-512 CPU)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT, load  # noqa: E402
from bench_wavelet_setup import write  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, io_bound_fn, measure, measure_paired, read_bound_fn  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402

#: (light, N): N None is every term
CASES = (("studio", 100), ("studio", 300), ("sky (sun)", 100), ("sky (sun)", 300), ("sky (sun)", 1000), ("sky (sun)", 2000),
         ("sky (sun)", None))
TITLE = ("# Wavelet kernel: one thread's time by part (issue 39)\n\n"
         "One section per CPU and kernel build; a run replaces its own. Reproduce: "
         "`.venv/bin/python benchmarks/bench_wavelet_parts.py` (and with `PRT_TORCH_KERNEL_ISA=avx2`).\n")


def part_row(rl, name: str, li: torch.Tensor, lv: torch.Tensor) -> dict:
    """One part: its kernel time (median), bytes (transfer + output) and fraction of its own bound (paired)."""
    out = torch.empty(rl.V, 3)
    nbytes = rl.bytes_read(li)
    f = rl.prepared(li, lv, out)
    bound = io_bound_fn(nbytes, rl.V * 12)
    p = measure_paired(f, bound, repeats=7, warmup=1, floor_pairs=40)
    t = measure(f, repeats=7, warmup=1).median
    # the same pair by this thread's CPU time (one thread: the kernel runs on the calling thread), the load-proof figure
    c = measure_paired(f, bound, repeats=15, warmup=1, clock=time.thread_time)
    r = measure_paired(f, read_bound_fn(nbytes, rl.V * 12), repeats=15, warmup=1, clock=time.thread_time)
    return {"part": name, "terms": int(li.numel()), "bytes": nbytes + rl.V * 12, "us": t * 1e6,
            "of_bound": p.speedup, "trusted": bool(p.contention.get("trusted")), "load": load(),
            "cpu_us": c.test.median * 1e6, "of_bound_cpu": c.speedup, "of_bound_cpu_q": [c.ratio.q1, c.ratio.q3],
            "of_read_cpu": r.speedup, "of_read_cpu_q": [r.ratio.q1, r.ratio.q3]}


def main() -> None:
    torch.set_num_threads(1)
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1)
    before = load()
    rows = []
    for light, N in CASES:
        N = N or rl.P
        li, lv, _ = rl.light(LIGHTS[light], N, "transport")
        lv = lv.to(torch.float32).contiguous()
        d = rl.dslot[li] >= 0
        s = li[~d]
        frac = int(rl.bcount[:, s[rl.nnz[s] > 0]].sum()) / max(1, rl.NB)
        for name, m in (("all", torch.ones_like(d)), ("dense", d), ("sparse", ~d)):
            r = part_row(rl, name, li[m].contiguous(), lv[:, m].contiguous())
            held = frac if name != "dense" else 0.0
            r.update(light=light, N=N, sparse_blocks=held, **{"pass": "dense only" if name == "dense" else
                                                               ("row-major" if held >= rl.row_min else "column-major")})
            rows.append(r)
            print(f"[wavelet_parts] {light} N={N} {r}", flush=True)
    empty = torch.nonzero(rl.cls == 0).flatten()[:1].contiguous()
    if empty.numel():
        r = part_row(rl, "output", empty, torch.ones(3, 1))
        r.update(light="—", N=1, sparse_blocks=0.0, **{"pass": "set-up + output"})
        rows.append(r)
        print(f"[wavelet_parts] {r}", flush=True)
    path = relight.wavelet_kernel_path()
    L = [f"## {cpu_label()}: the {path.get('isa')} build\n",
         f"One thread, the {path.get('isa')} build of `kernels/wavelet.c` ({path['path']}; `PRT_TORCH_KERNEL_ISA`="
         f"{os.environ.get('PRT_TORCH_KERNEL_ISA', 'native')}); load average "
         f"{before:.1f} → {load():.1f} (the machine shared with other jobs; ⚠: the wall-clock pairing flagged contention). "
         f"Occluder_over_plane small (V = {rl.V}), R = 32, K = 256, {BITS}-bit, {rl.Pd} dense columns, "
         f"tiles of {rl.TV}; transport-weighted terms. Each part relit alone through `WaveletRelighter.prepared`, paired "
         "with its own bounds: the copy bound (a copy of the transfer bytes it reads and a fill of the output, "
         "`timing.io_bound_fn`; wall clock, fastest tenth, and by CPU time) and the streaming read (`timing.read_bound_fn`: "
         "a sum over the same bytes and the fill; CPU time). Every part's time includes the per-light set-up and the output "
         "pass. **CPU time**: the thread's CPU time (`measure_paired(clock=time.thread_time)`, 15 repeats: median ratio "
         "[quartiles]), which the other processes' load does not enter. Every microsecond of the whole call by step: "
         "`wavelet_setup.md`.\n",
         "| light | N | part | terms | bytes read (+ output) | sparse blocks held / all | pass | time | of copy bound "
         "| CPU time | **of copy bound, CPU time** | **of streaming read, CPU time** | load |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        q, qr = r["of_bound_cpu_q"], r["of_read_cpu_q"]
        L.append(f"| {r['light']} | {'all' if r['N'] == rl.P else r['N']} | {r['part']} | {r['terms']} | {r['bytes']} | "
                 f"{r['sparse_blocks']:.2f} | {r['pass']} | {r['us']:.1f} µs | {r['of_bound']:.2f}{'' if r['trusted'] else ' ⚠'} | "
                 f"{r['cpu_us']:.1f} µs | **{r['of_bound_cpu']:.2f}** [{q[0]:.2f}, {q[1]:.2f}] | "
                 f"**{r['of_read_cpu']:.2f}** [{qr[0]:.2f}, {qr[1]:.2f}] | {r['load']:.1f} |")
    OUT.mkdir(parents=True, exist_ok=True)
    write(str(OUT / "wavelet_parts.md"), "\n".join(L) + "\n", TITLE)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
