"""How tight is tests/test_stream_codecs.py::test_fit_larger_than_the_memory_limit_from_the_file?

That test runs a CPCA fit in a subprocess under ``RLIMIT_DATA`` = (the warmed-up process's VmData)
+ a limit, once from ``np.load`` of the signal (must fail) and once from its memory map (must
pass). This script measures, for the same child code, the smallest limit at which each mode
passes: the mmap fit's data need (its peak VmData growth above the warmed-up process, as
Linux's data accounting sees it) and the load fit's need (the signal plus the same fit). Each
need is found by bisection in one warmed-up process: every probe is a ``fork`` whose child sets
the limit and runs the fit (copy-on-write: the same VmData base as the parent), to
``--resolution`` bytes. ``--runs`` fresh processes per mode; ``--busy N`` runs N ``while True:
pass`` processes beside them (started before, killed after) to see whether load moves the need.

``--mmap-threshold BYTES`` sets glibc's ``MALLOC_MMAP_THRESHOLD_`` in the children: a fixed
threshold turns off glibc's dynamic one (which, once a large block is freed, serves blocks up to
its size from the heap, where freed memory stays counted in VmData), so that VmData follows the
live allocations.

Run: .venv/bin/python benchmarks/bench_stream_memory_margin.py [--runs 10] [--busy 0] [--rows 98304]
     [--dim 128] [--chunk-mib 2] [--limit-mib 32] [--modes load,mmap] [--mmap-threshold 131072] [--max-mib 512]
Prints one line per run and a summary row; --report PATH appends the row to a markdown table
(reports/benchmarks/stream_memory_margin.md holds the runs behind the test's sizes).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch.harness.timing import cpu_label  # noqa: E402

CHILD = textwrap.dedent("""
    import json, os, resource, sys, numpy as np, torch
    torch.set_num_threads(1)
    from prt_torch import codecs
    path, mode, chunk, res, top = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4]), int(sys.argv[5])
    codecs.get("cpca", clusters=4, vectors=2, method="static").fit_encode(torch.randn(4096, 64))  # warm-up
    def vmdata():
        for line in open("/proc/self/status"):
            if line.startswith("VmData:"):
                return int(line.split()[1]) * 1024
    base = vmdata()
    def fits(limit):
        pid = os.fork()
        if pid == 0:
            ok = 1
            try:
                resource.setrlimit(resource.RLIMIT_DATA, (base + limit, resource.RLIM_INFINITY))
                X = np.load(path, mmap_mode="r") if mode == "mmap" else np.load(path)
                c = codecs.get("cpca", clusters=8, vectors=2, method="static", max_iter=5)
                c.chunk_bytes_ = chunk
                enc = c.fit(X).encode(X)
                ok = 0 if enc.points == X.shape[0] else 1
            except (MemoryError, RuntimeError):
                ok = 1
            os._exit(ok)
        return os.waitpid(pid, 0)[1] == 0
    lo, hi = 0, top  # fails at lo (nothing fits in 0 bytes), passes at hi (checked)
    assert fits(hi), f"the fit does not pass even {top} bytes above the warmed-up process"
    while hi - lo > res:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if fits(mid) else (mid, hi)
    print(json.dumps({"need": hi, "base": base}))
""")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--busy", type=int, default=0, help="busy-loop processes beside the runs")
    ap.add_argument("--rows", type=int, default=98304)
    ap.add_argument("--dim", type=int, default=128)
    ap.add_argument("--chunk-mib", type=float, default=2.0)
    ap.add_argument("--limit-mib", type=float, default=32.0, help="the test's limit, for the margins")
    ap.add_argument("--resolution-kib", type=int, default=256)
    ap.add_argument("--max-mib", type=int, default=512, help="the bisection's upper end (must pass)")
    ap.add_argument("--modes", default="load,mmap", help="which of load,mmap to measure")
    ap.add_argument("--mmap-threshold", type=int, default=0,
                    help="MALLOC_MMAP_THRESHOLD_ for the children (bytes; 0: glibc's default, dynamic threshold)")
    ap.add_argument("--report", type=Path, default=None)
    a = ap.parse_args(argv)
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if a.mmap_threshold:  # a fixed threshold: no dynamic raise, every block above it mapped and unmapped
        env["MALLOC_MMAP_THRESHOLD_"] = str(a.mmap_threshold)
    g = np.random.default_rng(0)
    P, D = a.rows, a.dim
    X = (g.standard_normal((P, D), dtype=np.float32) + 4 * g.integers(0, 8, P)[:, None].astype(np.float32))
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(a.busy)]
    needs: dict[str, list[int]] = {"load": [], "mmap": []}
    load0 = os.getloadavg()[0]
    t0 = time.time()
    try:
        with tempfile.TemporaryDirectory() as d:
            path = Path(d) / "big.npy"
            np.save(path, X)
            for i in range(a.runs):
                for mode in a.modes.split(","):
                    r = subprocess.run([sys.executable, "-c", CHILD, str(path), mode, str(int(a.chunk_mib * 2**20)),
                                        str(a.resolution_kib * 1024), str(a.max_mib * 2**20)], capture_output=True, text=True, env=env, cwd=ROOT)
                    if r.returncode != 0:
                        raise SystemExit(r.stderr[-2000:])
                    rec = json.loads(r.stdout.strip().splitlines()[-1])
                    needs[mode].append(rec["need"])
                    print(f"run {i} {mode}: needs {rec['need'] / 2**20:.2f} MiB above a base of {rec['base'] / 2**20:.1f} MiB",
                          flush=True)
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    load1 = os.getloadavg()[0]
    sig = X.nbytes / 2**20
    mm, ld = (np.array(needs[m] or [np.nan]) / 2**20 for m in ("mmap", "load"))
    lines = [
        f"| {P}x{D} float32 ({sig:.0f} MiB) | {a.mmap_threshold or 'default'} | {a.chunk_mib:g} | {a.busy} | {a.runs} | "
        f"{mm.min():.2f} / {mm.max():.2f} | "
        f"{ld.min():.2f} / {ld.max():.2f} | {a.limit_mib - mm.max():.1f} | {ld.min() - a.limit_mib:.1f} | "
        f"{load0:.1f} / {load1:.1f} | {time.time() - t0:.0f} s |"]
    head = ("| signal | MALLOC_MMAP_THRESHOLD_ | chunk MiB | busy procs | runs | mmap need min / max (MiB) | load need min / max (MiB) | "
            f"mmap margin at {a.limit_mib:g} MiB | load margin at {a.limit_mib:g} MiB | load avg before / after | wall |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    print(f"CPU {cpu_label()}; needs at {a.resolution_kib} KiB resolution")
    print(head)
    print(lines[0])
    if a.report:
        with open(a.report, "a") as f:
            f.write(lines[0] + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
