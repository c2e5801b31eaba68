"""CPU time of the harness's random-light PSNR (MRT eq. 11, ``harness.metrics.random_light_psnr``),
this checkout's against an earlier copy of ``metrics.py``, on the default benchmark's two signal
shapes, with the value against a float64 numpy evaluation of the same lights.

Shapes (P × n_out·n_in, lights): the main run's MRT matrices 10 242 × 64·16 with 128 lights (Gram
form), the Gaussian part's transport tables 10 242 × 42·384 with 128 lights (projection form:
fewer lights than inputs). x is a random float32 signal, x̂ = x + 1% noise (float32), as the harness
passes them (``codec.decode(enc).to(float32)``). Each side is called ``--repeats`` times, the two
alternating (before, after, before, ...) in one process; per call the process's CPU time (all
threads: ``time.process_time``) and wall time; the table gives medians. Reference: numpy float64,
Σ_p ‖Δ_p Lᵀ‖² by row blocks (independent of both implementations).

Run: .venv/bin/python benchmarks/bench_light_psnr.py --before /path/to/old/prt_torch/harness/metrics.py
     [--repeats 3] [--threads 2] [--out reports/benchmarks/light_psnr.md]
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: OpenMP's wait policy)

import argparse  # noqa: E402
import importlib.util  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from prt_torch.harness import metrics  # noqa: E402
from prt_torch.harness.timing import cpu_label  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402


def _load_before(path: str):
    spec = importlib.util.spec_from_file_location("metrics_before", path, submodule_search_locations=None)
    mod = importlib.util.module_from_spec(spec)
    mod.__package__ = "prt_torch.harness"  # its relative import (.timing) resolves to this checkout's
    spec.loader.exec_module(mod)
    return mod


def numpy_psnr(x: torch.Tensor, xh: torch.Tensor, n_in: int, n_lights: int, seed: int) -> float:
    """eq. 11 over the same lights, float64 numpy, by row blocks."""
    L = metrics.random_unit_vectors(n_lights, n_in, seed).numpy()
    acc = 0.0
    for i in range(0, x.shape[0], 256):
        d = x[i:i + 256].numpy().astype(np.float64) - xh[i:i + 256].numpy().astype(np.float64)
        acc += float(np.square(d.reshape(-1, n_in) @ L.T).sum())
    mse = acc / n_lights / x.shape[0]
    return 10 * math.log10(1 / mse)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", required=True, help="an earlier metrics.py to compare with")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    before = _load_before(a.before)
    g = torch.Generator().manual_seed(0)
    cases = [("main run: MRT 10 242 × 64·16, 128 lights (Gram form)", 10242, 64, 16, 128),
             ("Gaussian part: transport 10 242 × 42·384, 128 lights (projection form)", 10242, 42, 384, 128)]
    load0 = os.getloadavg()
    rows = []
    for name, P, n_out, n_in, nl in cases:
        x = torch.randn(P, n_out * n_in, generator=g)
        xh = x + 0.01 * torch.randn(P, n_out * n_in, generator=g)
        ref = numpy_psnr(x, xh, n_in, nl, 0)
        t = {"before": [], "after": []}
        vals = {}
        for _ in range(a.repeats):
            for side, fn in (("before", before.random_light_psnr), ("after", metrics.random_light_psnr)):
                c0, w0 = time.process_time(), time.perf_counter()
                vals[side] = fn(x, xh, n_in, nl, seed=0)
                t[side].append((time.process_time() - c0, time.perf_counter() - w0))
        med = {s: (statistics.median(c for c, _ in v), statistics.median(w for _, w in v)) for s, v in t.items()}
        rows.append((name, med, vals, ref))
        print(f"{name}: CPU s before {med['before'][0]:.2f} after {med['after'][0]:.2f} (x{med['after'][0] / med['before'][0]:.2f}), "
              f"wall {med['before'][1]:.2f} -> {med['after'][1]:.2f}; PSNR before {vals['before']:.9f} after {vals['after']:.9f} "
              f"numpy float64 {ref:.9f}", flush=True)
        del x, xh
    load1 = os.getloadavg()
    lines = [f"Machine: {cpu_label()}; torch threads {a.threads}; load average {load0[0]:.1f} -> {load1[0]:.1f} "
             f"(shared with other jobs when above 2); {a.repeats} calls per side, alternating, medians.", "",
             "| signal | CPU s before | CPU s after | after / before | wall s before → after | PSNR dB before | after | numpy float64 |",
             "|---|---:|---:|---:|---|---:|---:|---:|"]
    for name, med, vals, ref in rows:
        lines.append(f"| {name} | {med['before'][0]:.2f} | {med['after'][0]:.2f} | {med['after'][0] / med['before'][0]:.2f} | "
                     f"{med['before'][1]:.2f} → {med['after'][1]:.2f} | {vals['before']:.7f} | {vals['after']:.7f} | {ref:.7f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        atomic_write_text(Path(a.out), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
