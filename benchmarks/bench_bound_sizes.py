"""The two read-once/write-once bounds of the kernel benchmarks against the bytes they move (issue 39): why the copy
bound (``timing.io_bound_fn``: a ``copy_`` of the bytes read and a ``fill_`` of the output) is slow from about 1 MB on a
CPU with 2 MB of L2 per core, where the streaming read (``timing.read_bound_fn``: an int64 sum of the same bytes) is
not — so a kernel at "1.4 of its copy bound" there has not beaten memory, its bound has left the cache.

Per size: the copy bound and the read bound as the benchmarks build them (buffers allocated once, reused), a bare
``copy_`` into a reused destination and one into a fresh destination every call (first-touch page faults, if that
were the cause: minor faults per call counted), each one thread's CPU time (``time.thread_time``, page faults are
system time of the thread, so they count), the median of 301 calls after 20 warm-up calls; GB/s of the bytes read.
The output filled is 27 012 bytes (the wavelet kernel section's V = 2251 x 3 float32).

    .venv/bin/python benchmarks/bench_bound_sizes.py     (about 20 s)

Writes reports/benchmarks/bound_sizes.md (the CPU, its cache sizes and the load named).
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import os  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch.harness.timing import cpu_label, io_bound_fn, read_bound_fn  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

OUT = Path(__file__).resolve().parents[1] / "reports" / "benchmarks"
SIZES_MB = (0.25, 0.5, 0.75, 1.0, 1.25, 1.5, 2.0, 3.0, 6.0)
OUTPUT_BYTES = 2251 * 3 * 4


def median_time(f, calls: int = 301, warmup: int = 20) -> float:
    for _ in range(warmup):
        f()
    ts = []
    for _ in range(calls):
        t0 = time.thread_time()
        f()
        ts.append(time.thread_time() - t0)
    ts.sort()
    return ts[len(ts) // 2]


def caches() -> str:
    """lscpu's cache lines (L1d, L2, L3), or '' where lscpu is missing."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
    except (OSError, subprocess.SubprocessError):
        return ""
    return "; ".join(" ".join(ln.split()) for ln in out.splitlines() if ln.strip().startswith(("L1d", "L2", "L3")))


def main() -> None:
    torch.set_num_threads(1)
    before = os.getloadavg()[0]
    rows = []
    for mb in SIZES_MB:
        n = int(mb * 1e6)
        src = torch.empty(n, dtype=torch.uint8).random_(0, 255)
        dst = torch.empty_like(src)
        t_copy = median_time(io_bound_fn(n, OUTPUT_BYTES))
        t_read = median_time(read_bound_fn(n, OUTPUT_BYTES))
        t_bare = median_time(lambda: dst.copy_(src))  # noqa: B023
        f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
        t_fresh = median_time(lambda: torch.empty_like(src).copy_(src), calls=101)  # noqa: B023
        faults = (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / 121
        rows.append((mb, t_copy, t_read, t_bare, t_fresh, faults))
        print(f"[bound_sizes] {mb} MB: copy bound {t_copy * 1e6:.1f} us, read bound {t_read * 1e6:.1f} us, bare copy "
              f"{t_bare * 1e6:.1f} us, fresh destination {t_fresh * 1e6:.1f} us ({faults:.0f} faults/call)", flush=True)
    after = os.getloadavg()[0]
    L = ["# The copy bound and the streaming-read bound against their size (issue 39)\n",
         f"{cpu_label()}; {caches()}; one thread's CPU time, median of 301 calls; load average {before:.1f} → {after:.1f} "
         "(a shared machine: other processes' use of the caches is not in the CPU time but in the misses it leaves). "
         "`timing.io_bound_fn` (the copy bound: `copy_` of the bytes + `fill_` of a 27 012-byte output) and "
         "`timing.read_bound_fn` (the streaming read: an int64 sum of the same bytes + the fill), as the kernel "
         "benchmarks build them (buffers allocated once); a bare `copy_` into a reused destination and into a fresh "
         "one per call (minor page faults per call). GB/s of the bytes read. Reproduce: "
         "`.venv/bin/python benchmarks/bench_bound_sizes.py`.\n",
         "| MB read | copy bound | GB/s | streaming read | GB/s | copy / read | bare copy | fresh destination | faults per call |",
         "|---|---|---|---|---|---|---|---|---|"]
    for mb, tc, tr, tb, tf, fl in rows:
        gb = lambda t: mb * 1e6 / t / 1e9  # noqa: E731, B023
        L.append(f"| {mb} | {tc * 1e6:.1f} µs | {gb(tc):.1f} | {tr * 1e6:.1f} µs | {gb(tr):.1f} | {tc / tr:.2f} | "
                 f"{tb * 1e6:.1f} µs | {tf * 1e6:.1f} µs | {fl:.0f} |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "bound_sizes.md", "\n".join(L) + "\n")
    print(f"[bound_sizes] wrote {OUT / 'bound_sizes.md'}", flush=True)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
