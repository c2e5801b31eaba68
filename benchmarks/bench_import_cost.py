"""Start-up import cost of the CLI beyond torch, and of scipy.spatial on the glossy/MRT bounce path.

Each variant is a fresh ``python -c`` process; its CPU time (user + system, ``RUSAGE_CHILDREN``) is
paired with the base variant's in the same round (order alternating), ``--pairs`` rounds; reported:
the median paired difference against the base, with [min, max], and the base's median. Variants:

* ``torch``: ``import torch`` (the base: every command needs it);
* ``cli``: ``import prt_torch.cli`` (the command table; subcommands are imported when the parser is built);
* ``help``: ``prt --help`` (``main(['--help'])``: every subcommand's parser, hence the transfer
  registry and the modules the subcommands import at their top);
* ``transfer``: ``import torch, prt_torch.transfer``;
* ``spatial``: ``import torch, prt_torch.transfer, scipy.spatial`` (what an estimator-'auto' bounce
  precompute adds for its k-NN of face centroids, ``transfer.diffuse.HitBounce._coplanar``).

Run: .venv/bin/python benchmarks/bench_import_cost.py [--pairs 6]
Prints a markdown table (CPU named, load average before and after).
"""
from __future__ import annotations

import argparse
import os
import resource
import statistics
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch.harness.timing import cpu_label  # noqa: E402

VARIANTS = {
    "torch": "import torch",
    "cli": "import torch, prt_torch.cli",
    "help": "import sys, torch; from prt_torch.cli import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n    pass",
    "transfer": "import torch, prt_torch.transfer",
    "spatial": "import torch, prt_torch.transfer, scipy.spatial",
}


def cpu(code: str) -> float:
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-c", code], check=True, stdout=subprocess.DEVNULL, cwd=ROOT)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=6)
    a = ap.parse_args(argv)
    load0 = os.getloadavg()[0]
    for code in VARIANTS.values():  # warm the page cache and the .pyc files once
        cpu(code)
    base: list[float] = []
    diffs: dict[str, list[float]] = {k: [] for k in VARIANTS if k != "torch"}
    for i in range(a.pairs):
        for k in diffs:
            if i % 2 == 0:
                b, t = cpu(VARIANTS["torch"]), cpu(VARIANTS[k])
            else:
                t, b = cpu(VARIANTS[k]), cpu(VARIANTS["torch"])
            base.append(b)
            diffs[k].append(t - b)
    print(f"CPU {cpu_label()}; {a.pairs} pairs per variant; load average {load0:.1f} before, {os.getloadavg()[0]:.1f} after; "
          f"`import torch` alone: {statistics.median(base):.3f} s CPU (median)\n")
    print("| variant | CPU s over `import torch`: median [min, max] |\n|---|---|")
    for k, d in diffs.items():
        print(f"| {k} | {statistics.median(d):.3f} [{min(d):.3f}, {max(d):.3f}] |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
