"""Per-call cost of a render loop's relight (issue 42 §4: the per-call overhead of relight(out=) and the prepared call).

    .venv/bin/python benchmarks/bench_relight_call.py                 # writes reports/benchmarks/relight_call.md
    .venv/bin/python benchmarks/bench_relight_call.py --points 2000 --repeats 9 --out -   # print only
    PYTHONPATH=DIR .venv/bin/python benchmarks/bench_relight_call.py --out -   # another revision's package (git archive REV)

VQ 256 of diffuse vectors (``transfer_like(P, 1, 16)``, an RGB result per point, as ``bench_relight``'s
"vq 256 (diffuse)" row), CPCA 64×4 and PCA 8 of the same signal, no view; MRT-PCA 16 of
``transfer_like(P, 49, 25)`` with four tent taps of a 7×7 grid and with a dense view (bench_relight's
"mrt_pca 16" taps and dense rows); one thread. Each form is timed
against the same peer, **the bare kernel call**: ``prt_relight_plan`` through ctypes with the plan's
argument array, the light, a constants buffer, the view's addresses and the output (what any form of the call must run:
the per-light constants M_i l and the point kernel, Sloan 2003 §6). Paired in one process, order
alternating, by the thread's CPU time (``harness.timing.measure_paired(clock=time.thread_time)``: on a
shared machine, the time other processes held the core is in neither side); each figure is the
median of the per-repeat ratios form / bare [IQR] and the form's median µs per call. Forms:

* ``relight(enc, L, view, out=buf)`` — a render loop's call: from its third call into the same ``out``
  with the same view, the fast path armed in ``enc.cache`` (``affine.fast_rows``; with a view since
  this change, without one before);
* ``relight, full check`` — the same call with ``AffineCodec.FAST_OUTS + 1`` output buffers taken in
  turn, more than it keeps entries for, so every call checks in full (the cost every call paid
  before the fast path, plus noting the buffer);
* ``relighter(enc, view)(L, out=buf)`` — the prepared form (``AffineRelighter``, the same fast path).

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
from prt_torch.codecs.synthetic import tent_taps_random, transfer_like  # noqa: E402
from prt_torch.harness.timing import cpu_label, machine_info, measure_paired  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

SETTINGS = [("vq 256 (diffuse)", "vq", {"clusters": 256, "max_iter": 10}, "diffuse", "none"),
            ("cpca static 64x4 (diffuse)", "cpca_static", {"clusters": 64, "vectors": 4, "max_iter": 10}, "diffuse", "none"),
            ("pca 8 (diffuse)", "pca", {"vectors": 8}, "diffuse", "none"),
            ("mrt_pca 16", "mrt_pca", {"vectors": 16}, "mrt", "taps"),
            ("mrt_pca 16", "mrt_pca", {"vectors": 16}, "mrt", "dense")]


def rows(P: int, repeats: int, only: str = "") -> list[dict]:
    signals = {"diffuse": (transfer_like(P, 1, 16, seed=5), None), "mrt": (transfer_like(P, 49, 25, seed=3), (49, 25))}
    g = torch.Generator().manual_seed(0)
    lights = {"diffuse": torch.randn(16, 3, generator=g), "mrt": torch.randn(25, 3, generator=g)}
    views = {"none": None, "taps": tent_taps_random(P, 7, seed=4), "dense": torch.randn(P, 49, generator=g)}
    out, fits = [], {}
    for label, name, params, sig, mode in SETTINGS:
        if only not in f"{label} {mode}":
            continue
        X, ms = signals[sig]
        L, view = lights[sig], views[mode]
        if (label, P) not in fits:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                c = codecs.get(name, **params)
                c.fit(X[:min(P, 8000)], matrix_shape=ms)
            fits[(label, P)] = (c, c.encode(X))
        c, enc = fits[(label, P)]
        want = c.relight(enc, L, view)
        buf = torch.empty_like(want)
        turn = [torch.empty_like(want) for _ in range(c.FAST_OUTS + 1)]
        r = c.relighter(enc, view)
        for _ in range(3):
            r(L, out=buf)
            c.relight(enc, L, view, out=buf)
        # the bare call: the plan relight caches, a constants buffer of its layout, the view's addresses
        ntap = view[0].shape[1] if isinstance(view, tuple) else 0
        pl = c._kernel_plan(native(), enc, c._n_eff(None), "rows" if view is None else ("taps" if ntap else "dense"), 3, ntap)
        T = torch.zeros(pl.size)
        y0, y1 = (view[0].data_ptr(), view[1].data_ptr()) if ntap else ((view.data_ptr(), None) if view is not None else (None, None))
        fn, args, lp, op = native().prt_relight_plan, pl.args_ptr, L.data_ptr(), buf.data_ptr()
        fn(args, lp, T.data_ptr(), op, y0, y1, 1)
        if not torch.equal(buf, want):
            raise SystemExit(f"bench_relight_call: {label} {mode}: the bare call's result differs from relight's")
        Tp = T.data_ptr()
        bare = lambda: fn(args, lp, Tp, op, y0, y1, 1)  # noqa: E731

        def full_check():
            turn.append(turn.pop(0))
            c.relight(enc, L, view, out=turn[0])

        forms = {"relight(out=buf)": lambda: c.relight(enc, L, view, out=buf), "relight, full check": full_check,
                 "relighter(enc)(L, out=buf)": lambda: r(L, out=buf)}
        row = {"label": label, "view": mode, "points": P, "kernel_path": kernel_path(pl)["path"]}
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
    ap.add_argument("--only", default="", help="only the settings whose 'label view' contains this text")
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
    res = [r for P in counts for r in rows(P, args.repeats, args.only)]
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
             "| setting | view | points | kernel path | bare kernel call (µs) | relight(out=buf) | relight, full check (5 outputs in turn) "
             "| relighter(enc)(L, out=buf) |", "|---|---|---|---|---|---|---|---|"]
    for r in res:
        cells = [f"{r[k]['ratio']:.2f} [{r[k]['q'][0]:.2f}, {r[k]['q'][1]:.2f}] ({r[k]['us']:.1f} µs)"
                 for k in ("relight(out=buf)", "relight, full check", "relighter(enc)(L, out=buf)")]
        bare_us = r["relight(out=buf)"]["bare_us"]
        lines.append(f"| {r['label']} | {r['view']} | {r['points']} | {r['kernel_path']} | {bare_us:.1f} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out != "-":
        atomic_write_text(Path(args.out), text)
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
