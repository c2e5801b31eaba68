"""How tight are tests/test_stream_outputs.py's two memory-limited tests (24 MiB ``RLIMIT_DATA`` above
the warmed-up process, 40 MiB MRT results / transfers)? For each, the smallest limit at which its
streamed child passes ("need"), by bisection over fresh processes running the test's own child
script (imported from the test module), to ``--resolution-kib``; ``--runs`` bisections each.
The in-memory side needs the 40 MiB array at least (one mapped block): it cannot pass under 24 MiB.

Run: .venv/bin/python benchmarks/bench_stream_outputs_margin.py [--runs 5] [--mmap-threshold BYTES]
Prints one line per run and a summary (CPU, load average).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

from prt_torch.harness.timing import cpu_label  # noqa: E402


def passes(code: str, args: list[str], env: dict) -> bool:
    r = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, cwd=ROOT)
    if r.returncode != 0:
        raise SystemExit(r.stderr[-2000:])
    return json.loads(r.stdout.strip().splitlines()[-1])["ok"]


def need(code: str, make_args, env: dict, res: int, top: int) -> int:
    lo, hi = 0, top
    if not passes(code, make_args(hi), env):
        raise SystemExit(f"the streamed child does not pass at {top} bytes")
    while hi - lo > res:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if passes(code, make_args(mid), env) else (mid, hi)
    return hi


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--resolution-kib", type=int, default=512)
    ap.add_argument("--max-mib", type=int, default=48)
    ap.add_argument("--mmap-threshold", type=int, default=0)
    a = ap.parse_args(argv)
    import test_stream_outputs as T

    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions, get_kind

    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    if a.mmap_threshold:
        env["MALLOC_MMAP_THRESHOLD_"] = str(a.mmap_threshold)
    load0 = os.getloadavg()[0]
    out: dict[str, list[float]] = {"precompute": [], "relight": []}
    with tempfile.TemporaryDirectory() as d:
        d = Path(d)
        tr = get_kind("mrt").precompute(builtin("bumpy_sphere:10242"), dict(T.MRT, M=8, bands=4, samples=8, shadows="never"),
                                        run=RunOptions(chunk_size=4096))
        tr.save(d / "m.prt")
        count = iter(range(10**9))
        for i in range(a.runs):
            n = need(T._LIMITED_PRECOMPUTE, lambda lim: [str(d / f"p{next(count)}.prt"), "stream", str(lim)], env,
                     a.resolution_kib * 1024, a.max_mib * 2**20)
            out["precompute"].append(n / 2**20)
            n = need(T._LIMITED_RELIGHT, lambda lim: [str(d / "m.prt"), str(d / f"r{next(count)}.npy"), "stream", str(lim)], env,
                     a.resolution_kib * 1024, a.max_mib * 2**20)
            out["relight"].append(n / 2**20)
            print(f"run {i}: precompute stream needs {out['precompute'][-1]:.2f} MiB, relight stream {out['relight'][-1]:.2f} MiB",
                  flush=True)
    print(f"CPU {cpu_label()}; load average {load0:.1f} before, {os.getloadavg()[0]:.1f} after; "
          f"MALLOC_MMAP_THRESHOLD_ {a.mmap_threshold or 'default'}; resolution {a.resolution_kib} KiB")
    for k, v in out.items():
        print(f"{k}: need {min(v):.2f}-{max(v):.2f} MiB over {len(v)} runs; margin at the test's 24 MiB: {24 - max(v):.2f} MiB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
