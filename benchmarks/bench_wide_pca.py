"""PCA and CPCA fits on the default benchmark's Gaussian-part transport tables (wide rows: 42 views ×
6×8×8 = 16 128 values per vertex), against the float64 optimum (issue 42 part 2, third pass).

For each PCA setting and solver: the fit's SE over the optimum's (total variance minus the top-n
eigenvalues of the centred Gram matrix ``Y Yᵀ``, float64 ``eigvalsh``: exact, independent of the
codec's solvers), its CPU time (``getrusage``, self) and wall time; for each CPCA setting, static
and/or iterative, the SE and times. All fits of one run share the machine's load (printed).

Run: .venv/bin/python benchmarks/bench_wide_pca.py --size medium --vectors 81,163 \\
         [--solvers krylov,randomized] [--cpca 16x7:static,16x7:iterative] [--cache cache/prof]
(size medium = 10 242 vertices: the Gram matrix and its eigenvalues take about 2 min on 2 cores.)
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.harness.config import load_config, part_configs  # noqa: E402
from prt_torch.harness.evaluate import Evaluator  # noqa: E402
from prt_torch.harness.run import compute_transfer, load_mesh_within_budget  # noqa: E402
from prt_torch.harness.timing import cpu_label  # noqa: E402


def table(size: str, cache: str) -> torch.Tensor:
    """The part's transport table ``[P, 16128]`` float32 at scene ``size`` (the harness's functions)."""
    cfg = load_config("default")
    cfg["output_dir"], cfg["cache_dir"] = tempfile.mkdtemp(prefix="wide_pca_"), cache
    sub = [s for s in part_configs(cfg) if s["name"] == "gaussian"][0]
    sub["scene"]["size"] = int(size) if size.isdigit() else size
    mesh, _ = load_mesh_within_budget(sub)
    tr, _ = compute_transfer(sub, mesh, Path(cache), progress=False)
    return Evaluator(tr).X


def spectrum(X: torch.Tensor, block: int = 2048) -> tuple[float, torch.Tensor]:
    """(total variance, eigenvalues descending) of the centred rows, float64, via the P×P Gram matrix."""
    mu = X.double().mean(0)
    P = X.shape[0]
    G = torch.zeros(P, P, dtype=torch.float64)
    rows = [(i, min(P, i + block)) for i in range(0, P, block)]
    for a, (i0, i1) in enumerate(rows):
        xa = X[i0:i1].double() - mu
        for j0, j1 in rows[a:]:
            g = xa @ (X[j0:j1].double() - mu).T
            G[i0:i1, j0:j1] = g
            G[j0:j1, i0:i1] = g.T
    return float(torch.diagonal(G).sum()), torch.linalg.eigvalsh(G).flip(0)


def timed_fit(codec, X):
    r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
    codec.fit(X)
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    return codec, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime), time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", default="2562")
    ap.add_argument("--vectors", default="28,57", help="PCA settings (comma-separated n')")
    ap.add_argument("--solvers", default="krylov,randomized")
    ap.add_argument("--cpca", default="", help="CPCA settings KxN:method, comma-separated (e.g. 16x7:static)")
    ap.add_argument("--cache", default="cache/prof")
    a = ap.parse_args(argv)
    X = table(a.size, a.cache)
    print(f"table {tuple(X.shape)} {X.dtype}; CPU: {cpu_label()}; load {os.getloadavg()}; torch threads {torch.get_num_threads()}",
          flush=True)
    t0 = time.perf_counter()
    tv, lam = spectrum(X)
    print(f"float64 optimum: total variance {tv:.6g}, {time.perf_counter() - t0:.0f} s", flush=True)
    print("| setting | solver | SE | SE / optimum | fit CPU s | fit wall s | load |\n|---|---|---:|---:|---:|---:|---|")
    for n in [int(v) for v in a.vectors.split(",") if v]:
        opt = tv - float(lam[:n].sum())
        for solver in a.solvers.split(","):
            c, cpu, wall = timed_fit(codecs.get("pca", vectors=n, solver=solver), X)
            print(f"| pca {n} | {c.fit_info_['solver']} | {c.fit_info_['se']:.6g} | {c.fit_info_['se'] / opt:.7f} | "
                  f"{cpu:.1f} | {wall:.1f} | {os.getloadavg()[0]:.1f} |", flush=True)
    for spec in [s for s in a.cpca.split(",") if s]:
        kn, method = spec.split(":")
        K, n = (int(v) for v in kn.split("x"))
        c, cpu, wall = timed_fit(codecs.get("cpca", clusters=K, vectors=n, method=method), X)
        print(f"| cpca {K}x{n} {method} | {c.fit_info_['solver']} | {c.fit_info_['se']:.6g} | "
              f"{c.fit_info_['se'] / tv:.5f} of the total variance | {cpu:.1f} | {wall:.1f} | {os.getloadavg()[0]:.1f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
