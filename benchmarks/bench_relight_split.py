"""Where two threads lose on a large relight: the split, the memory system or the load (issue 42 §4).

    .venv/bin/python benchmarks/bench_relight_split.py              # writes reports/benchmarks/relight_split.md
    .venv/bin/python benchmarks/bench_relight_split.py --out -      # print only
    .venv/bin/python benchmarks/bench_relight_split.py --rows cpca_static:dense,cpca_iterative:dense --out -

The point kernels (``prt_affine_rows``, ``prt_affine_dense``) split the visited points into one contiguous range per
thread (``schedule(static, 1)`` over the thread count: thread t visits positions [P·t/n, P·(t+1)/n) of the visiting
order — for CPCA 256×8 the cluster-sorted order, clusters in blocks of 8192 points), so a two-thread call can lose to
one thread in four ways, each measured here on ``bench_relight``'s rows (``--rows``, codec:view; the fits are
``bench_relight``'s own, from its cache when there: MRT-PCA 16 of ``transfer_like(50 000, 49, 25)``, Lehtinen & Kautz
2003 eq. (13) without the taps; CPCA 256×8 static and iterative of ``transfer_like(50 000, 24, 25)``, Sloan 2003 §6's
per-point pass, without a view or with a dense one, Sloan 2003 §3.1) and on the bound (``harness.timing.io_bound_fn``:
a copy of the bytes read and a fill of the bytes written):

* **the split** — the work each thread's range gets (points; multiply-adds, J·n_out·C per point, plus n_out·C with a
  dense view; cluster runs, i.e. loads of a cluster's constants, and consecutive visits of one cluster, which the
  kernels combine two at a time) and the two ranges timed alone, one thread each, by the thread's CPU time and paired:
  exactly the ranges of a two-thread call (the plan's codes and visiting order from the range's first position), so
  the two calls together write the whole call's bits (checked); a ratio far from 1 means one thread waits for the
  other at the end of the region;
* **false sharing** — the output bytes both threads write: the one 64-byte line holding the boundary point's row, if
  its row is not line-aligned (computed, not timed; with a cluster-sorted order the boundary is a visit, and the two
  threads' rows interleave within the block it falls in, so this counts only the point order's case);
* **the memory system** — the whole call at one and at two threads, wall clock, interleaved, each the fastest of
  ``--samples`` calls (the fastest call is one no other process interrupted): two threads' best against one thread's
  best, next to the bound's own two-thread speed-up (the copy and fill share the same memory);
* **the load** — the same calls' medians, and the involuntary context switches and load average while they ran: on 2
  cores shared with other jobs, a spinning OpenMP region (``prt_torch.OMP_POLICY_CHOICE``) stalls whenever another
  process holds one of the cores, which stretches the median and not the best.
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_relight  # noqa: E402  (its settings, signals and cached fits: the rows measured here are its rows)

from prt_torch.codecs.relight_kernels import _PLAN_FIELDS, kernel_path, native, run_plan  # noqa: E402
from prt_torch.codecs.synthetic import transfer_like  # noqa: E402
from prt_torch.harness.timing import cpu_label, io_bound_fn, machine_info, measure_paired, torch_threads  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

P = 50000
ROWS = "mrt_pca:none,cpca_static:none,cpca_iterative:none,cpca_static:dense,cpca_iterative:dense"
_F = {f: i for i, f in enumerate(_PLAN_FIELDS)}


def interleaved(fns: dict, samples: int) -> dict:
    """Each of ``fns`` called ``samples`` times in rotation (wall clock): per name, the fastest call and the median
    (ms), with the involuntary context switches per second and the load average over the whole run."""
    ts: dict[str, list[float]] = {k: [] for k in fns}
    r0, w0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    for _ in range(samples):
        for k, (threads, fn) in fns.items():
            with torch_threads(threads):
                t0 = time.perf_counter()
                fn()
                ts[k].append(time.perf_counter() - t0)
    wall = time.perf_counter() - w0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    out = {k: {"best_ms": 1e3 * min(v), "median_ms": 1e3 * statistics.median(v)} for k, v in ts.items()}
    out["switches_per_s"] = (r1.ru_nivcsw - r0.ru_nivcsw) / wall
    out["load"] = os.getloadavg()[0]
    return out


def fitted(name: str, cache: Path) -> tuple:
    """bench_relight's fit of codec ``name`` (its 50 000-point setting; cached there), the signal and its label."""
    label, _, params, sig = next(s for s in bench_relight.settings(False) if s[1] == name and "diffuse" not in s[0])
    X, ms = (transfer_like(P, 49, 25, seed=3), (49, 25)) if sig == "mrt" else (transfer_like(P, 24, 25, seed=0), (24, 25))
    c, enc, _ = bench_relight.fitted(name, params, X, ms, cache)
    return label, c, enc


def sub_plan(pl, q0: int, q1: int) -> tuple[torch.Tensor, int]:
    """The plan's argument array for visits [q0, q1) alone — the codes and the visiting order from position q0 (a
    cluster-sorted plan stores its codes in visiting order), P = q1 - q0 — and the row the output and view start at:
    0 with a visiting order (it holds whole-call point indices), else q0."""
    a = pl.args.clone()
    order, labels, W, woff = pl.keep[5], pl.keep[1], pl.keep[2], pl.keep[3]
    sorted_codes = bool(a[_F["csort"]]) or order is None
    if not sorted_codes:
        raise ValueError("sub_plan: codes in point order with a visiting order; accepted: sorted codes or no order")
    a[_F["P"]] = q1 - q0
    if labels is not None:
        a[_F["lab"]] += q0 * labels.element_size()
    if woff is not None:
        a[_F["woff"]] += q0 * 8
    elif W is not None:
        a[_F["W"]] += q0 * int(a[_F["wstride"]]) * 4
    if order is not None:
        a[_F["order"]] += q0 * 4
    return a, 0 if order is not None else q0


def work(c, pl, q0: int, q1: int, view: str) -> dict:
    """The work of visits [q0, q1): points, multiply-adds, cluster runs and consecutive same-cluster visits."""
    labels = pl.keep[1]
    n_out = c.matrix_shape_[0]
    nk = c.n_vectors_.long()
    lab = labels[q0:q1].long() if labels is not None else torch.zeros(q1 - q0, dtype=torch.long)
    J = nk[lab] + (1 if c.means_ is not None else 0)
    macs = int((J * n_out * 3).sum()) + (n_out * 3 * (q1 - q0) if view == "dense" else 0)
    same = lab[1:] == lab[:-1]
    return {"points": q1 - q0, "macs": macs, "runs": int((~same).sum()) + 1, "same_next": int(same.sum())}


def measure_row(name: str, view: str, args, cache: Path, light: torch.Tensor) -> dict:
    lib = native()
    label, c, enc = fitted(name, cache)
    n_out, n_in = c.matrix_shape_
    Ls = light[:n_in]
    kind = "rows" if view == "none" else "dense"
    y = torch.randn(P, n_out, generator=torch.Generator().manual_seed(1)) if view == "dense" else None
    with torch_threads(2):
        pl = c._kernel_plan(lib, enc, c._n_eff(None), kind, 3, 0)
        path = kernel_path(pl)
    shape = (P, n_out, 3) if view == "none" else (P, 3)
    buf = torch.empty(shape)
    whole = c.relight(enc, Ls, view=y)
    h = P // 2  # the two threads' ranges of visits: [0, P/2) and [P/2, P)
    subs = [sub_plan(pl, 0, h), sub_plan(pl, h, P)]
    Lc = Ls.contiguous()
    y0 = None if y is None else y.data_ptr()
    from prt_torch.codecs.relight_kernels import _scratch
    T = _scratch(pl.kind, pl.size)
    orow = buf[0].numel() * 4  # bytes per output row (and per view row: y [P, n_out] float32)
    calls = [lambda a=a, r=r: lib.prt_relight_plan(a.data_ptr(), Lc.data_ptr(), T.data_ptr(), buf.data_ptr() + r * orow,
                                                   None if y0 is None else y0 + r * n_out * 4, None, 1) for a, r in subs]
    buf.fill_(float("nan"))
    for f in calls:
        f()
    if not torch.equal(buf.view(torch.int32), whole.view(torch.int32)):
        raise SystemExit(f"bench_relight_split: {label} {view}: the two thread ranges relit alone differ from the whole call")
    with torch_threads(1):
        split = measure_paired(calls[0], calls[1], repeats=args.repeats, warmup=2, clock=time.thread_time)
    r = c.relighter(enc, y)
    bound = io_bound_fn(c.relight_bytes(enc, y), buf.numel() * 4)
    for nt in (1, 2):
        with torch_threads(nt):
            for _ in range(3):
                r(Ls, out=buf)
                bound()
    fns = {"relight, 1 thread": (1, lambda: r(Ls, out=buf)), "relight, 2 threads": (2, lambda: r(Ls, out=buf)),
           "bound, 1 thread": (1, bound), "bound, 2 threads": (2, bound)}
    t = interleaved(fns, args.samples)
    row = shape[-1] * (n_out if view == "none" else 1) * 4
    run_plan(lib, pl, Lc, y, out=buf)  # (leave buf as a whole call wrote it)
    return {"label": f"{label}, {view}", "path": path, "work": [work(c, pl, 0, h, view), work(c, pl, h, P, view)],
            "split": split, "t": t, "row_bytes": row, "sorted": pl.keep[5] is not None}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", default=ROWS, help=f"codec:view pairs, comma-separated (default {ROWS}); codecs: mrt_pca, "
                    "cpca_static, cpca_iterative, cpca_adaptive; views: none, dense")
    ap.add_argument("--samples", type=int, default=40, help="calls of each form, in rotation (default 40)")
    ap.add_argument("--repeats", type=int, default=15, help="pairs of the halves' CPU-time comparison (default 15)")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "prt_bench_relight"))
    ap.add_argument("--out", default="reports/benchmarks/relight_split.md", help="report path, or - to print only")
    args = ap.parse_args()
    if args.samples < 3 or args.repeats < 3:
        print(f"bench_relight_split: --samples {args.samples}, --repeats {args.repeats}; accepted: integers >= 3", file=sys.stderr)
        return 2
    rows = []
    for item in args.rows.split(","):
        name, _, view = item.strip().partition(":")
        if name not in ("mrt_pca", "cpca_static", "cpca_iterative", "cpca_adaptive") or view not in ("none", "dense"):
            print(f"bench_relight_split: --rows item {item!r}; accepted: codec:view with codec mrt_pca, cpca_static, "
                  "cpca_iterative or cpca_adaptive and view none or dense", file=sys.stderr)
            return 2
        rows.append((name, view))
    if native() is None:
        print("bench_relight_split: the compiled kernels are not available (PRT_TORCH_NATIVE=0 or no C compiler); "
              "accepted: a build with them", file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    light = torch.randn(25, 3, generator=torch.Generator().manual_seed(0))
    res = [measure_row(name, view, args, cache, light) for name, view in rows]
    load1 = os.getloadavg()
    mi = machine_info()
    p0 = res[0]["path"]
    L = ["# Two threads on a large relight: the split, the memory system or the load", "",
         "Reproduce: `.venv/bin/python benchmarks/bench_relight_split.py` (the script's docstring defines each measurement; "
         f"`--rows {args.rows}`).", "",
         f"Machine: {cpu_label(mi)}, {os.cpu_count()} cores, {p0.get('isa', '?')} build (`{p0.get('flags', '')}`); OpenMP: "
         f"{prt_torch.OMP_POLICY_CHOICE}. Load average before {tuple(round(x, 2) for x in load0)}, after "
         f"{tuple(round(x, 2) for x in load1)}. {P} points; ranges: the two threads' visits [0, {P // 2}) and "
         f"[{P // 2}, {P}).", "",
         "| measurement | " + " | ".join(r["label"] for r in res) + " |", "|---|" + "---|" * len(res)]

    def line(name, fn):
        L.append(f"| {name} | " + " | ".join(fn(r) for r in res) + " |")

    line("point kernel (CPU · kernel path)", lambda r: f"`{r['path'].get('path')}`")
    line("work: points, first / second range", lambda r: f"{r['work'][0]['points']:,} / {r['work'][1]['points']:,}")
    line("work: multiply-adds, first / second", lambda r: f"{r['work'][0]['macs'] / 1e6:.2f} M / {r['work'][1]['macs'] / 1e6:.2f} M")
    line("work: cluster runs (constants loads), first / second", lambda r: f"{r['work'][0]['runs']:,} / {r['work'][1]['runs']:,}")
    line("work: visits followed by one of the same cluster, first / second",
         lambda r: f"{r['work'][0]['same_next']:,} / {r['work'][1]['same_next']:,}")
    line("the split: first range / second, 1 thread each, CPU time, paired",
         lambda r: f"{1 / r['split'].ratio.median:.3f} [{1 / r['split'].ratio.q3:.3f}, {1 / r['split'].ratio.q1:.3f}] "
                   f"({1e3 * r['split'].test.median:.2f} / {1e3 * r['split'].peer.median:.2f} ms)")
    line("false sharing: output lines both threads write (point order)",
         lambda r: "— (cluster-sorted visits: rows interleave within a block)" if r["sorted"] else
         f"{0 if (P // 2 * r['row_bytes']) % 64 == 0 else 1} of {P * r['row_bytes'] // 64:,}")
    tt = lambda r, k, s: r["t"][k][s]  # noqa: E731
    for k in ("relight, 1 thread", "relight, 2 threads", "bound, 1 thread", "bound, 2 threads"):
        line(f"{k}: best / median of {args.samples} (ms)", lambda r, k=k: f"{tt(r, k, 'best_ms'):.3f} / {tt(r, k, 'median_ms'):.3f}")
    for what in ("relight", "bound"):
        line(f"{what} speed-up, 2 threads over 1: best / median",
             lambda r, w=what: f"{tt(r, w + ', 1 thread', 'best_ms') / tt(r, w + ', 2 threads', 'best_ms'):.2f}× / "
                               f"{tt(r, w + ', 1 thread', 'median_ms') / tt(r, w + ', 2 threads', 'median_ms'):.2f}×")
    line("fraction of the bound at 2 threads: best / median",
         lambda r: f"{tt(r, 'bound, 2 threads', 'best_ms') / tt(r, 'relight, 2 threads', 'best_ms'):.2f} / "
                   f"{tt(r, 'bound, 2 threads', 'median_ms') / tt(r, 'relight, 2 threads', 'median_ms'):.2f}")
    line("involuntary context switches per second; load average at the end",
         lambda r: f"{r['t']['switches_per_s']:.0f}; {r['t']['load']:.1f}")
    text = "\n".join(L) + "\n"
    print(text)
    if args.out != "-":
        atomic_write_text(Path(args.out), text)
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
