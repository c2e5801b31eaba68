"""Benchmark: the whole-command cost of ``prt precompute`` with this checkout's code against another
revision's (issue 42 §1: any change to a default reports its cost paired against main).

    .venv/bin/python benchmarks/bench_precompute_cost.py --against /tmp/main_src [--pairs 3]
        [--label NAME -- ARGS...]  (several --label/ARGS groups separated by '+')

``--against DIR``: a source tree of the other revision (e.g. ``git archive main | tar -x -C DIR``);
its ``prt_torch`` is put first on ``PYTHONPATH`` of the 'against' runs, this checkout's on the
others, same interpreter and virtual environment. Each command runs once as a warm-up per side,
then ``--pairs`` alternated pairs (the order flipped every pair). Per run: wall time and the CPU
time of the whole process tree (user + system of the command and of its ray-casting workers,
``RUSAGE_CHILDREN``). Reported per command: the median of the pairs' ratios (this / against) with
[min, max], the CPU model and the load average around the runs (the machine may be shared:
ratios within a pair are what to read). Appends a section to reports/benchmarks/precompute_cost.md.
"""
from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch import io  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402


def one(src: Path, args: list[str], out: Path) -> tuple[float, float]:
    """(wall s, CPU s of the process tree) of ``prt precompute ARGS -o OUT`` with ``src``'s prt_torch."""
    env = dict(os.environ, PYTHONPATH=str(src), OMP_NUM_THREADS=os.environ.get("OMP_NUM_THREADS", "2"))
    code = ("import sys, prt_torch; from prt_torch.cli import main; "
            f"assert prt_torch.__file__.startswith({str(src)!r}), prt_torch.__file__; sys.exit(main(sys.argv[1:]))")
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", code, "precompute", *args, "--no-progress", "--overwrite", "-o", str(out)],
                       env=env, capture_output=True, text=True, cwd=out.parent)  # not the checkout: '' on sys.path
    wall = time.perf_counter() - t
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if p.returncode != 0:
        sys.exit(f"prt precompute {' '.join(args)} ({src}) failed: {p.stderr.strip().splitlines()[-1:]}")
    return wall, (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def main(argv=None):
    argv = sys.argv[1:] if argv is None else argv
    head, groups = (argv[:argv.index("--")], argv[argv.index("--") + 1:]) if "--" in argv else (argv, [])
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--against", required=True, help="source tree of the other revision (its prt_torch/ inside)")
    ap.add_argument("--pairs", type=int, default=3)
    ap.add_argument("--label", action="append", default=[], help="one per command group after '--' (groups split by '+')")
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "precompute_cost.md"))
    a = ap.parse_args(head)
    cmds, cur = [], []
    for x in groups + ["+"]:
        if x == "+":
            if cur:
                cmds.append(cur)
            cur = []
        else:
            cur.append(x)
    if len(a.label) != len(cmds):
        sys.exit(f"--label given {len(a.label)} times for {len(cmds)} commands; accepted: one label per command")
    against = Path(a.against).resolve()
    if not (against / "prt_torch" / "__init__.py").exists():
        sys.exit(f"--against {a.against}: no prt_torch/ package inside; accepted: a source tree of the other revision")
    cpu = machine_info()["cpu"]
    lines = []
    with tempfile.TemporaryDirectory() as tmp:
        for label, args in zip(a.label, cmds):
            load0 = os.getloadavg()[0]
            out = Path(tmp) / "o.prt"
            one(ROOT, args, out), one(against, args, out)  # warm-up: caches, compiled kernels
            ratios_w, ratios_c, rows = [], [], []
            for i in range(a.pairs):
                order = [ROOT, against] if i % 2 == 0 else [against, ROOT]
                res = {src: one(src, args, out) for src in order}
                w, c = res[ROOT], res[against]
                ratios_w.append(w[0] / c[0])
                ratios_c.append(w[1] / c[1])
                rows.append(f"{w[0]:.1f} / {c[0]:.1f} s wall, {w[1]:.1f} / {c[1]:.1f} s CPU")
                print(f"[cost] {label} pair {i}: {rows[-1]}", flush=True)
            load1 = os.getloadavg()[0]
            rw, rc = np.array(ratios_w), np.array(ratios_c)
            lines.append(f"| {label} | `prt precompute {' '.join(args)}` | **{np.median(rc):.2f}×** [{rc.min():.2f}, {rc.max():.2f}] | "
                         f"{np.median(rw):.2f}× [{rw.min():.2f}, {rw.max():.2f}] | {'; '.join(rows)} | {load0:.1f} / {load1:.1f} |")
            print(lines[-1], flush=True)
    out = Path(a.out)
    text = out.read_text() if out.exists() else ("# Whole-command cost of `prt precompute`, paired against another revision\n\n"
                                                 "Written by `benchmarks/bench_precompute_cost.py`: ratios this / other, median of "
                                                 "alternated pairs after a warm-up [min, max]; CPU time of the whole process tree.\n")
    sec = ["", f"## {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, against `{a.against}` ({a.pairs} pairs; CPU: {cpu})", "",
           "| change | command | CPU time ratio | wall ratio | pairs (this / other) | load before / after |",
           "|---|---|---:|---:|---|---|", *lines]
    with io.atomic_path(out) as tmpf:
        Path(tmpf).write_text(text.rstrip("\n") + "\n" + "\n".join(sec) + "\n")
    print(f"[cost] wrote {out}")


if __name__ == "__main__":
    main()
