"""Where two threads lose on a large relight without a view (issue 42 §4: "mrt_pca 16 none, 2 threads: 0.43").

    .venv/bin/python benchmarks/bench_relight_split.py              # writes reports/benchmarks/relight_split.md
    .venv/bin/python benchmarks/bench_relight_split.py --out -      # print only

``prt_affine_rows`` splits the points into one contiguous range per thread (``schedule(static, 1)`` over the
thread count: thread t relights points [P·t/n, P·(t+1)/n)), so a two-thread call can lose to one thread in
four ways, each measured here on ``bench_relight``'s row (MRT-PCA 16 of ``transfer_like(50 000, 49, 25)``
without a view: 147 floats, 588 bytes, written per point; Lehtinen & Kautz 2003 eq. (13) without the view's
taps, Sloan 2003 §6's per-point pass) and on the bound (``harness.timing.io_bound_fn``: a copy of the bytes
read and a fill of the bytes written):

* **the split** — the two threads' ranges timed alone, one thread each, by the thread's CPU time and paired
  (the second half's codes encoded on their own: the same per-point work); a ratio far from 1 means one
  thread waits for the other at the end of the region;
* **false sharing** — the output bytes both threads write: the one 64-byte line holding the boundary row's
  first bytes, if the boundary is not line-aligned (computed, not timed);
* **the memory system** — the whole call at one and at two threads, wall clock, interleaved, each the fastest
  of ``--samples`` calls (the fastest call is one no other process interrupted): two threads' best against
  one thread's best, next to the bound's own two-thread speed-up (the copy and fill share the same memory);
* **the load** — the same calls' medians, and the involuntary context switches and load average while they
  ran: on 2 cores shared with other jobs, a spinning OpenMP region (``prt_torch.OMP_POLICY_CHOICE``) stalls
  whenever another process holds one of the cores, which stretches the median and not the best.
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import glob  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.codecs.relight_kernels import kernel_path, native  # noqa: E402
from prt_torch.codecs.synthetic import transfer_like  # noqa: E402
from prt_torch.harness.timing import cpu_label, io_bound_fn, machine_info, measure_paired, torch_threads  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

P, FIT = 50000, 8000


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


def fitted(cache: Path) -> tuple:
    """bench_relight's MRT-PCA 16 (its cached fit when there is one), and the signal."""
    A = transfer_like(P, 49, 25, seed=3)
    for path in sorted(glob.glob(str(cache / "mrt_pca-*.prt"))):
        c, enc = codecs.load(path)
        if enc.points == P and c.matrix_shape_ == (49, 25):
            return c, enc, A
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c = codecs.get("mrt_pca", vectors=16).fit(A[:FIT], matrix_shape=(49, 25))
    return c, c.encode(A), A


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=40, help="calls of each form, in rotation (default 40)")
    ap.add_argument("--repeats", type=int, default=15, help="pairs of the halves' CPU-time comparison (default 15)")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "prt_bench_relight"))
    ap.add_argument("--out", default="reports/benchmarks/relight_split.md", help="report path, or - to print only")
    args = ap.parse_args()
    if args.samples < 3 or args.repeats < 3:
        print(f"bench_relight_split: --samples {args.samples}, --repeats {args.repeats}; accepted: integers >= 3", file=sys.stderr)
        return 2
    if native() is None:
        print("bench_relight_split: the compiled kernels are not available (PRT_TORCH_NATIVE=0 or no C compiler); "
              "accepted: a build with them", file=sys.stderr)
        return 2
    load0 = os.getloadavg()
    c, enc, A = fitted(Path(args.cache))
    light = torch.randn(25, 3, generator=torch.Generator().manual_seed(0))
    h = P // 2  # the two threads' ranges: [0, P/2) and [P/2, P)
    halves = [c.encode(A[:h]), c.encode(A[h:])]
    bufs = [torch.empty(h, 49, 3), torch.empty(P - h, 49, 3)]
    with torch_threads(1):
        rs = [c.relighter(e) for e in halves]
        for r, b in zip(rs, bufs):
            r(light, out=b)
        split = measure_paired(lambda: rs[0](light, out=bufs[0]), lambda: rs[1](light, out=bufs[1]), repeats=args.repeats,
                               warmup=2, clock=time.thread_time)
        whole_ref = c.relight(enc, light)
        if not (torch.equal(torch.cat([c.relight(halves[0], light), c.relight(halves[1], light)]), whole_ref)):
            print("bench_relight_split: the halves relit alone differ from the whole call", file=sys.stderr)
            return 1
    buf = torch.empty(P, 49, 3)
    r = c.relighter(enc)
    bound = io_bound_fn(c.relight_bytes(enc, None), buf.numel() * 4)
    for nt in (1, 2):
        with torch_threads(nt):
            for _ in range(3):
                r(light, out=buf)
                bound()
    fns = {"relight, 1 thread": (1, lambda: r(light, out=buf)), "relight, 2 threads": (2, lambda: r(light, out=buf)),
           "bound, 1 thread": (1, bound), "bound, 2 threads": (2, bound)}
    t = interleaved(fns, args.samples)
    with torch_threads(2):
        path = kernel_path(c._kernel_plan(native(), enc, c._n_eff(None), "rows", 3, 0))
    row = 49 * 3 * 4
    boundary = h * row
    shared_lines = 0 if boundary % 64 == 0 else 1
    load1 = os.getloadavg()
    mi = machine_info()
    best = lambda k: t[k]["best_ms"]  # noqa: E731
    med = lambda k: t[k]["median_ms"]  # noqa: E731
    lines = [
        "# Two threads on a large relight without a view: the split, the memory system or the load",
        "",
        "Reproduce: `.venv/bin/python benchmarks/bench_relight_split.py` (the script's docstring defines each measurement).",
        "",
        f"Machine: {cpu_label(mi)}, {os.cpu_count()} cores, {path.get('isa', '?')} build (`{path.get('flags', '')}`), point kernel "
        f"`{path.get('path')}`; OpenMP: {prt_torch.OMP_POLICY_CHOICE}. Load average before {tuple(round(x, 2) for x in load0)}, "
        f"after {tuple(round(x, 2) for x in load1)}. MRT-PCA 16, {P} points of 49×3 floats out ({P * row / 1e6:.1f} MB written "
        f"per call), no view.",
        "",
        "| measurement | figure |",
        "|---|---|",
        f"| the split: first half / second half, 1 thread each, CPU time, paired | {1 / split.ratio.median:.3f} "
        f"[{1 / split.ratio.q3:.3f}, {1 / split.ratio.q1:.3f}] ({1e3 * split.test.median:.2f} / {1e3 * split.peer.median:.2f} ms) |",
        f"| false sharing: output lines both threads write | {shared_lines} of {P * row // 64:,} (boundary row at byte "
        f"{boundary:,}, {boundary % 64} into its line) |",
        f"| relight, 1 thread: best / median of {args.samples} (ms) | {best('relight, 1 thread'):.3f} / {med('relight, 1 thread'):.3f} |",
        f"| relight, 2 threads: best / median (ms) | {best('relight, 2 threads'):.3f} / {med('relight, 2 threads'):.3f} |",
        f"| relight speed-up, 2 threads over 1: best / median | {best('relight, 1 thread') / best('relight, 2 threads'):.2f}× / "
        f"{med('relight, 1 thread') / med('relight, 2 threads'):.2f}× |",
        f"| bound, 1 thread: best / median (ms) | {best('bound, 1 thread'):.3f} / {med('bound, 1 thread'):.3f} |",
        f"| bound, 2 threads: best / median (ms) | {best('bound, 2 threads'):.3f} / {med('bound, 2 threads'):.3f} |",
        f"| bound speed-up, 2 threads over 1: best / median | {best('bound, 1 thread') / best('bound, 2 threads'):.2f}× / "
        f"{med('bound, 1 thread') / med('bound, 2 threads'):.2f}× |",
        f"| fraction of the bound at 2 threads: best / median | {best('bound, 2 threads') / best('relight, 2 threads'):.2f} / "
        f"{med('bound, 2 threads') / med('relight, 2 threads'):.2f} |",
        f"| involuntary context switches per second; load average at the end | {t['switches_per_s']:.0f}; {t['load']:.1f} |",
        "",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if args.out != "-":
        atomic_write_text(Path(args.out), text)
        print("wrote", args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
