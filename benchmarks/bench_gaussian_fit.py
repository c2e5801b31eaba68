"""The Gaussian codec's fit (Green 2005 §2.2): the compiled Levenberg–Marquardt loop
(``codecs.gaussian.lm_native``, ``prt_torch/kernels/gauss_lm.c``) against the torch loop
(``PRT_TORCH_NATIVE=0``), paired in one process on the same tables.

Tables: a harness config's transport part (``--config default``: the default benchmark's Gaussian
part, Phong s = 12, 42 views, 6×8×8; ``--config gaussian``: prt bench gaussian's, Ashikhmin–Shirley
N = 40, 6×13×13), at ``--size`` (the scene level), through the harness's own cache
(``harness.run.compute_transfer``), the first ``--vertices`` vertices (faces among them kept, so
the flood fill and the spatial term run as in the full fit). For each lobe count the two loops
alternate ``--repeats`` times, each fit in one thread (``torch.set_num_threads(1)``), timed by
this thread's CPU time (``time.thread_time``: the machine is shared, the load is recorded); a fit
is ``GaussianCodec.fit`` — start, LM stages, restart, and its error statistics. Errors: the fit's
whole-table relative L2 and relative SE (Σ (T̃ − T)² / Σ T²), the per-function median and p90.

Run: .venv/bin/python benchmarks/bench_gaussian_fit.py --config default --size medium --vertices 2000 --lobes 1,2
Writes reports/benchmarks/gaussian_fit_<config>.md and .json (--out to change).
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.codecs.gaussian import lm_native  # noqa: E402
from prt_torch.harness.config import load_config, part_configs  # noqa: E402
from prt_torch.harness.evaluate import Evaluator  # noqa: E402
from prt_torch.harness.run import compute_transfer, load_mesh_within_budget  # noqa: E402
from prt_torch.harness.timing import cpu_label as _cpu  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def _tables(config: str, size: str | None, cache: str):
    cfg = load_config(config)
    cfg["cache_dir"] = cache
    sub = next(s for s in ([cfg] + part_configs(cfg)) if s.get("transfer", {}).get("type") == "transport")
    if size:
        sub["scene"]["size"] = int(size) if size.isdigit() else size
    mesh, _ = load_mesh_within_budget(sub)
    tr, _ = compute_transfer(sub, mesh, Path(cache), progress=False)
    return Evaluator(tr), sub


def _fit(X, ev, kw, lobes: int, native: bool) -> dict:
    os.environ["PRT_TORCH_NATIVE"] = "1" if native else "0"
    c = codecs.get("gaussian", lobes=lobes)
    t0, w0 = time.thread_time(), time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        c.fit(X, matrix_shape=ev.matrix_shape, **kw)
    cpu, wall = time.thread_time() - t0, time.perf_counter() - w0
    i = c.fit_info_
    return {"cpu_s": cpu, "wall_s": wall, "relative_l2": i["relative_l2"], "se_relative": i["se_relative"],
            "median": i["relative_l2_median"], "p90": i["relative_l2_p90"], "converged": i["converged_fraction"],
            "iterations": max(b["iterations"] for b in i["batches"]), "lm_loop": i["lm_loop"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="default")
    ap.add_argument("--size", default=None)
    ap.add_argument("--vertices", type=int, default=2000)
    ap.add_argument("--lobes", default="1,2")
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--cache", default=str(ROOT / "cache" / "bench_gaussian_fit"))
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if not lm_native.available():
        print(f"the compiled loop is not available here: {lm_native.why()}", file=sys.stderr)
        return 2
    torch.set_num_threads(1)
    load0 = os.getloadavg()
    ev, sub = _tables(a.config, a.size, a.cache)
    K = min(a.vertices, ev.V)
    X = ev.X[:K]
    kw = ev.fit_kwargs(codecs.get("gaussian"))
    f = kw["faces"]
    kw["faces"] = f[(f < K).all(1)]
    J, P = ev.matrix_shape
    rows = []
    for lobes in (int(x) for x in a.lobes.split(",")):
        runs = {True: [], False: []}
        for _ in range(a.repeats):
            for native in (True, False):  # alternating: both see the same load
                runs[native].append(_fit(X, ev, kw, lobes, native))
                print(f"lobes {lobes} {'compiled' if native else 'torch   '}: {runs[native][-1]}", flush=True)
        rows.append({"lobes": lobes, "compiled": runs[True], "torch": runs[False]})
    os.environ.pop("PRT_TORCH_NATIVE", None)
    load1 = os.getloadavg()
    res = {"config": a.config, "scene": sub["scene"], "vertices": K, "views": J, "texels": P, "cpu": _cpu(),
           "torch": torch.__version__, "kernel": lm_native.why(), "load_before": load0, "load_after": load1, "rows": rows,
           "argv": sys.argv[1:]}
    out = Path(a.out) if a.out else ROOT / "reports" / "benchmarks" / f"gaussian_fit_{a.config}"
    atomic_write_text(out.with_suffix(".json"), json.dumps(res, indent=1))
    atomic_write_text(out.with_suffix(".md"), _markdown(res))
    print(f"wrote {out.with_suffix('.md')}")
    return 0


def _markdown(r: dict) -> str:
    def best(runs, k):
        return min(x[k] for x in runs)

    lines = [f"# The Gaussian fit: compiled LM loop vs torch loop ({r['config']} tables)", "",
             f"Generated by `benchmarks/bench_gaussian_fit.py {' '.join(r['argv'])}`. Machine: {r['cpu']}; torch {r['torch']}, "
             f"one thread per fit. Load average {[round(x, 2) for x in r['load_before']]} before, "
             f"{[round(x, 2) for x in r['load_after']]} after (a shared machine: the CPU time of the fitting thread is the figure; "
             "the two loops alternate so both see the same load).", "",
             f"Tables: {r['scene']['name']} {r['scene'].get('size')}, the first {r['vertices']} vertices × {r['views']} views × "
             f"{r['texels']} texels. Compiled path: {r['kernel']}.", "",
             "| lobes | loop | CPU s (each run) | best CPU s | compiled / torch (best) | relative L2 | relative SE | median | p90 | converged |",
             "|---:|---|---|---:|---:|---:|---:|---:|---:|---:|"]
    for row in r["rows"]:
        tb = best(row["torch"], "cpu_s")
        for name in ("compiled", "torch"):
            runs = row[name]
            x = runs[-1]
            ratio = f"{best(runs, 'cpu_s') / tb:.2f}" if name == "compiled" else ""
            lines.append(f"| {row['lobes']} | {name} | {', '.join('%.2f' % y['cpu_s'] for y in runs)} | {best(runs, 'cpu_s'):.2f} | "
                         f"{ratio} | {x['relative_l2']:.5f} | {x['se_relative']:.6f} | {x['median']:.4f} | {x['p90']:.4f} | "
                         f"{x['converged']:.3f} |")
    lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    sys.exit(main())
