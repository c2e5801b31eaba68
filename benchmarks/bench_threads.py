"""Which OpenMP configuration to default to: spinning threads (OpenMP's default),
``OMP_WAIT_POLICY=PASSIVE``, or one thread — measured on an idle machine and beside two busy
processes, on relighting kernels of the harness (CPCA with MRT taps, PCA without a view, the
uncompressed tap path, at 10k points) and one GEMM. Writes reports/benchmarks/threads.{md,json}.

    python benchmarks/bench_threads.py

Each configuration runs in its own process (the policy is read when OpenMP starts); every
figure is the median of 15 samples of 5 calls, with the second-worst sample as the tail.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CHILD = r"""
import json, time, torch
from prt_torch import codecs, relight
from prt_torch.codecs.synthetic import transfer_like
P, n_out, n_in = 10242, 64, 16
X = transfer_like(P, n_out, n_in, seed=0)
c = codecs.get("cpca", clusters=16, vectors=8, iterations=2); enc = c.fit_encode(X, matrix_shape=(n_out, n_in))
p = codecs.get("pca", vectors=8); enc2 = p.fit_encode(X, matrix_shape=(n_out, n_in))
g = torch.Generator().manual_seed(0)
L = torch.randn(n_in, 3, generator=g); idx = torch.randint(0, n_out - 3, (P, 1), generator=g) + torch.arange(4)[None]
w = torch.rand(P, 4, generator=g); Mx = X.view(P, n_out, n_in); B = torch.randn(1024, 8, generator=g)
fns = {"cpca_taps": lambda: c.relight(enc, L, view=(idx, w)), "pca_noview": lambda: p.relight(enc2, L),
       "uncompressed_taps": lambda: relight.apply_taps(Mx, L.T, idx, w), "gemm_10k_1024_8": lambda: X @ B}
out = {}
for k, f in fns.items():
    for _ in range(3): f()
    ts = []
    for _ in range(15):
        t = time.perf_counter(); [f() for _ in range(5)]; ts.append((time.perf_counter() - t) / 5)
    ts.sort(); out[k] = {"median_ms": ts[7] * 1e3, "tail_ms": ts[-2] * 1e3}
print(json.dumps(out))
"""

CONFIGS = {"spinning (default)": {}, "OMP_WAIT_POLICY=PASSIVE": {"OMP_WAIT_POLICY": "PASSIVE"},
           "OMP_NUM_THREADS=1": {"OMP_NUM_THREADS": "1"}}


def run_child(extra: dict) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OMP_NUM_THREADS")}
    env.update(extra)
    env["PYTHONPATH"] = str(ROOT)
    r = subprocess.run([sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=600)
    if r.returncode != 0:
        raise RuntimeError(r.stderr[-2000:])
    return json.loads(r.stdout.strip().splitlines()[-1])


def main() -> int:
    from prt_torch import io
    from prt_torch.harness.timing import machine_info

    res = {"machine": machine_info(), "runs": {}}
    for mode in ("idle", "two busy processes"):
        hogs = []
        if mode != "idle":
            hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
            time.sleep(1.0)
        try:
            res["runs"][mode] = {name: run_child(extra) for name, extra in CONFIGS.items()}
        finally:
            for h in hogs:
                h.kill()
    md = ["# OpenMP configuration: measured", "", "`python benchmarks/bench_threads.py`. Milliseconds per call (median / "
          "second-worst of 15 samples), each configuration in its own process, at 10k points.", "",
          "| machine | configuration | " + " | ".join(next(iter(next(iter(res["runs"].values())).values()))) + " |",
          "|---|---|" + "---|" * 4]
    for mode, by in res["runs"].items():
        for name, r in by.items():
            md.append(f"| {mode} | {name} | " + " | ".join(f"{v['median_ms']:.2f} / {v['tail_ms']:.2f}" for v in r.values()) + " |")
    md += ["", "Ratios PASSIVE / spinning (median): " + "; ".join(
        f"{mode}: " + ", ".join(f"{k} {by['OMP_WAIT_POLICY=PASSIVE'][k]['median_ms'] / by['spinning (default)'][k]['median_ms']:.2f}×"
                                for k in by["spinning (default)"]) for mode, by in res["runs"].items()) + ".",
           "", "Decision (prt_torch/__init__.py): spinning threads unless other processes already occupy ≥ 0.75 × the cores "
           "when prt_torch is imported, then PASSIVE; a user's own OMP_WAIT_POLICY always wins."]
    io.atomic_write_json(ROOT / "reports" / "benchmarks" / "threads.json", res)
    io.atomic_write_text(ROOT / "reports" / "benchmarks" / "threads.md", "\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
