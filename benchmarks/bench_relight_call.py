"""Per-call cost of a small relight without a view (issue 42 §4: the unprepared relight's per-call overhead).

    .venv/bin/python benchmarks/bench_relight_call.py                 # writes reports/benchmarks/relight_call.md
    .venv/bin/python benchmarks/bench_relight_call.py --points 2000 --repeats 9 --out -   # print only

VQ 256 of diffuse vectors (``transfer_like(P, 1, 16)``, an RGB result per point, as ``bench_relight``'s
"vq 256 (diffuse)" row), CPCA 64×4 and PCA 8 of the same signal, one thread. Each form is timed
against the same peer, **the bare kernel call**: ``prt_relight_plan`` through ctypes with the plan's
argument array, the light, a constants buffer and the output (what any form of the call must run:
the per-light constants M_i l and the point kernel, Sloan 2003 §6). Paired in one process, order
alternating, by the thread's CPU time (``harness.timing.measure_paired(clock=time.thread_time)``: on a
shared machine, the time other processes held the core is in neither side); each figure is the
median of the per-repeat ratios form / bare [IQR] and the form's median µs per call. Forms:

* ``relight(enc, L, out=buf)`` — a render loop's call: from its second call like the first, the
  fast path armed in ``enc.cache`` (``affine.fast_rows``);
* ``relight, full check`` — the same call with ``AffineCodec.FAST_OUTS + 1`` output buffers taken in
  turn, more than it keeps entries for, so every call checks in full (the cost every call paid
  before the fast path, plus noting the buffer);
* ``relighter(enc)(L, out=buf)`` — the prepared form (``AffineRelighter``, the same fast path).

The ratio minus 1 is the Python share of a call, over the kernel's own time.
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.codecs.relight_kernels import kernel_path, native  # noqa: E402
from prt_torch.codecs.synthetic import transfer_like  # noqa: E402
from prt_torch.harness.timing import cpu_label, machine_info, measure_paired  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

SETTINGS = [("vq 256 (diffuse)", "vq", {"clusters": 256, "max_iter": 10}),
            ("cpca static 64x4 (diffuse)", "cpca_static", {"clusters": 64, "vectors": 4, "max_iter": 10}),
            ("pca 8 (diffuse)", "pca", {"vectors": 8})]


def rows(P: int, repeats: int) -> list[dict]:
    X = transfer_like(P, 1, 16, seed=5)
    L = torch.randn(16, 3, generator=torch.Generator().manual_seed(0))
    out = []
    for label, name, params in SETTINGS:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            c = codecs.get(name, **params)
            c.fit(X[:min(P, 8000)])
        enc = c.encode(X)
        buf = torch.empty(P, 3)
        turn = [torch.empty(P, 3) for _ in range(c.FAST_OUTS + 1)]
        r = c.relighter(enc)
        for _ in range(3):
            r(L, out=buf)
            c.relight(enc, L, out=buf)
        f = r._fast  # the armed prepared call: the ctypes function, the plan's arguments, its constants buffer
        if f is None:
            raise SystemExit("bench_relight_call: the prepared call did not arm its fast path (no compiled kernels?)")
        fn, args, T, lp, op = f[10], f[11], f[13], L.data_ptr(), buf.data_ptr()
        want = c.relight(enc, L)
        fn(args, lp, T, op, None, None, 1)
        if not torch.equal(buf, want):
            raise SystemExit(f"bench_relight_call: {label}: the bare call's result differs from relight's")
        bare = lambda: fn(args, lp, T, op, None, None, 1)  # noqa: E731

        def full_check():
            turn.append(turn.pop(0))
            c.relight(enc, L, out=turn[0])

        forms = {"relight(out=buf)": lambda: c.relight(enc, L, out=buf), "relight, full check": full_check,
                 "relighter(enc)(L, out=buf)": lambda: r(L, out=buf)}
        row = {"label": label, "points": P, "kernel_path": kernel_path(c._kernel_plan(native(), enc, c._n_eff(None), "rows", 3, 0))["path"]}
        for name_, fn_ in forms.items():
            m = measure_paired(fn_, bare, repeats=repeats, warmup=2, clock=time.thread_time)
            row[name_] = {"ratio": 1.0 / m.ratio.median, "q": [1.0 / m.ratio.q3, 1.0 / m.ratio.q1],
                          "us": 1e6 * m.test.median, "bare_us": 1e6 * m.peer.median}
        out.append(row)
        print(row, flush=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", default="50000,2000", help="comma list of point counts (default 50000,2000)")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--out", default="reports/benchmarks/relight_call.md", help="report path, or - to print only")
    args = ap.parse_args()
    try:
        counts = [int(p) for p in args.points.split(",")]
        if not counts or min(counts) < 8:
            raise ValueError
    except ValueError:
        print(f"bench_relight_call: --points {args.points!r}; accepted: a comma list of integers >= 8", file=sys.stderr)
        return 2
    if native() is None:
        print("bench_relight_call: the compiled kernels are not available (PRT_TORCH_NATIVE=0 or no C compiler); "
              "accepted: a build with them", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    load0 = os.getloadavg()
    res = [r for P in counts for r in rows(P, args.repeats)]
    load1 = os.getloadavg()
    mi = machine_info()
    kp = kernel_path()
    lines = ["# Per-call cost of a small relight without a view", "",
             "Reproduce: `.venv/bin/python benchmarks/bench_relight_call.py` (the script's docstring defines the forms and the peer).", "",
             f"Machine: {cpu_label(mi)}, {kp.get('isa', '?')} build of the kernels (`{kp.get('flags', '')}`), one thread, "
             f"CPU time (time.thread_time). Load average before {tuple(round(x, 2) for x in load0)}, "
             f"after {tuple(round(x, 2) for x in load1)} (2 cores, shared with other jobs: CPU time keeps their time out of "
             "either side, not their use of the shared caches).", "",
             "Each cell: the form's CPU time per call over the bare kernel call's, paired, median [IQR]; then the form's µs per call "
             "(the bare call's in its own column).", "",
             "| setting | points | kernel path | bare kernel call (µs) | relight(out=buf) | relight, full check (5 outputs in turn) "
             "| relighter(enc)(L, out=buf) |", "|---|---|---|---|---|---|---|"]
    for r in res:
        cells = [f"{r[k]['ratio']:.2f} [{r[k]['q'][0]:.2f}, {r[k]['q'][1]:.2f}] ({r[k]['us']:.1f} µs)"
                 for k in ("relight(out=buf)", "relight, full check", "relighter(enc)(L, out=buf)")]
        lines.append(f"| {r['label']} | {r['points']} | {r['kernel_path']} | {r['relight(out=buf)']['bare_us']:.1f} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out != "-":
        atomic_write_text(Path(args.out), text)
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
