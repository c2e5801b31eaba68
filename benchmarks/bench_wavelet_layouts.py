"""The wavelet relighter's row-major copy held on first need (issue 39, ``WaveletRelighter(layouts=)``):
bytes held per vertex with both layouts (the old eager build) against the column-major layout alone
(``layouts='auto'`` until a light chooses the row-major pass), and the first-call cost of the lazy
build against a relight, paired, one thread, this thread's CPU time (``time.thread_time``).

Transfers: the kernel section's (occluder_over_plane small, K = 256, 16 bits) at R = 16 and 32, and a
coloured one (cornell_box small, one bounce: CT = 3, R = 16). Per
repeat (interleaved): the copy dropped and rebuilt (:meth:`WaveletRelighter._build_rows`) and, back to
back, relights of the sky light (the studio light before the zero-term rule) at N = all (the row-major
pass) and N = 100 (the column-major pass) through ``prepared`` (mean of 20 calls per sample); the ratio per repeat, median [quartiles].
And the whole first call at N = all (kernel status 3, the build, the call repeated) against a later one.

Writes reports/benchmarks/wavelet_layouts.md (CPU, kernel path and load average named).

    .venv/bin/python benchmarks/bench_wavelet_layouts.py
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import os  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, OUT, load  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

REPEATS = 15
CALLS = 20


def cpu(f, n: int = 1) -> float:
    t = time.thread_time()
    for _ in range(n):
        f()
    return (time.thread_time() - t) / n


def q(xs):
    s = sorted(xs)
    return statistics.median(s), s[len(s) // 4], s[(3 * len(s)) // 4]


def drop_rows(rl) -> None:
    rl.rptr = rl.rcol = rl.rvals = None
    if rl._native is not None:
        rl._layout[20:23] = 0


def row(scene: str, res: int, bounces: int = 0) -> dict:
    mesh = builtin(scene, "small")
    tr = precompute_wavelet(mesh, res, 256, BITS, shadows="always", bounces=bounces, hit_samples=8, run=RunOptions(workers=1))
    V = tr.mesh.num_vertices
    both = relight.WaveletRelighter(tr, threads=1, layouts="both")
    auto = relight.WaveletRelighter(tr, threads=1)
    if auto._kernel() is None:
        raise SystemExit("no native wavelet kernel here: the lazy build is the kernel's")
    # the sky: every term takes the row-major pass (the studio light's nonzero terms, 143-292 here, no longer do:
    # select_terms keeps no round-off term)
    li_all, lv_all, _ = auto.light("sky")
    li_100, lv_100, _ = auto.light("sky", terms=100)
    out = torch.empty(V, 3)
    run_100 = auto.prepared(li_100, lv_100, out)
    held_before = auto.held_bytes()
    assert auto.rptr is None  # N = 100 takes the column-major pass
    run_all = auto.prepared(li_all, lv_all, out)
    assert auto.rptr is not None  # N = all chose the row-major pass: built
    held_after, held_both = auto.held_bytes(), both.held_bytes()
    b, ra, r1, first = [], [], [], []
    for i in range(REPEATS):
        steps = [("b", lambda: (drop_rows(auto), cpu(auto._build_rows))[1]),
                 ("ra", lambda: cpu(run_all, CALLS)), ("r1", lambda: cpu(run_100, CALLS))]
        res_ = {}
        for k, f in (steps if i % 2 == 0 else steps[::-1]):
            res_[k] = f()
        b.append(res_["b"]), ra.append(res_["ra"]), r1.append(res_["r1"])
        drop_rows(auto)
        t_first = cpu(run_all)  # status 3, the build, the call again
        first.append((t_first, cpu(run_all, CALLS)))
    return {"scene": scene + (f", {bounces} bounce, coloured (CT = 3)" if bounces else ""), "res": res, "V": V,
            "NB": auto.NB, "before": held_before, "after": held_after, "both": held_both,
            "stored": tr.data[0].numel() * tr.data.element_size() + 2 * tr.data.shape[-1],
            "build_us": q([x * 1e6 for x in b]), "all_us": q([x * 1e6 for x in ra]), "n100_us": q([x * 1e6 for x in r1]),
            "build_over_all": q([x / y for x, y in zip(b, ra)]), "build_over_100": q([x / y for x, y in zip(b, r1)]),
            "first_over_later": q([x / y for x, y in first]), "load": load()}


def main() -> None:
    torch.set_num_threads(1)
    info = machine_info()
    la = [load()]
    rows = [row("occluder_over_plane", 16), row("occluder_over_plane", 32), row("cornell_box", 16, bounces=1)]
    la.append(load())
    L = ["# Wavelet relighter: the row-major copy on first need (`layouts`)\n",
         f"CPU: {info['cpu']} (family {info.get('cpu_family')} model {info.get('cpu_model')}), kernel path "
         f"{info.get('cpu_isa')} (kernels/wavelet.c at -march=native: {relight.wavelet_kernel_path()['path']}), one thread; load average "
         f"{min(la + [r['load'] for r in rows]):.1f}-{max(la + [r['load'] for r in rows]):.1f} on "
         f"{os.cpu_count()} cores (shared with other jobs: CPU time, `time.thread_time`, which other processes' "
         "load does not enter). Transfers: occluder_over_plane small (grey) and cornell_box small with one bounce "
         "(coloured walls: one transfer per colour, CT = 3; 8 hit samples), K = 256, 16 bits, "
         "the sky light (the studio light before the zero-term rule). "
         f"Reproduce: `.venv/bin/python benchmarks/bench_wavelet_layouts.py`.\n",
         "## Bytes held per vertex (`held_bytes() / V`)\n",
         "*before*: `layouts='both'` (what every relighter held before: the row-major copy built eagerly); *auto*: the "
         "default now, until a light chooses the row-major pass (after it, the same as both). *stored*: the transfer file's "
         "values + int16 indices per vertex, for scale.\n",
         "| scene | R | V | sparse blocks | stored | dense | column-major | row-major copy | other | **both (before)** | "
         "**auto, column-major only** | auto / both |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        V, bo, be = r["V"], r["both"], r["before"]
        L.append(f"| {r['scene']} | {r['res']} | {V} | {r['NB']} | {r['stored']} | {bo['dense'] / V:.0f} | {bo['column'] / V:.0f} | "
                 f"{bo['row'] / V:.0f} | {bo['other'] / V:.0f} | **{bo['total'] / V:.0f}** | **{be['total'] / V:.0f}** | "
                 f"{be['total'] / bo['total']:.2f} |")
    L += ["\n## First-call cost of the lazy build (one thread, CPU time, paired per repeat)\n",
          f"{REPEATS} repeats, each: the copy dropped and rebuilt (`_build_rows`), and back to back (order alternating) "
          f"relights through `prepared` at N = all (row-major pass) and N = 100 (column-major pass), mean of {CALLS} "
          "calls per sample; then the whole first call at N = all (kernel status 3, the build, the call again) against "
          "the mean of the next calls. Median [quartiles] of the per-repeat ratios.\n",
          "| scene | R | build | relight N = all | relight N = 100 | **build / relight N = all** | build / relight N = 100 | "
          "**first call / later call, N = all** | load |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        def f(k, u=""):
            m, a, b = r[k]
            return f"{m:.1f}{u} [{a:.1f}, {b:.1f}]" if u else f"{m:.1f} [{a:.1f}, {b:.1f}]"
        L.append(f"| {r['scene']} | {r['res']} | {f('build_us', ' µs')} | {f('all_us', ' µs')} | {f('n100_us', ' µs')} | "
                 f"**{f('build_over_all')}** | {f('build_over_100')} | **{f('first_over_later')}** | {r['load']:.1f} |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_layouts.md", "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
