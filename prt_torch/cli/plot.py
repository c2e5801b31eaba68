"""``prt plot RESULTS... -o DIR`` — draw any set of result files together."""
from __future__ import annotations

import argparse
from pathlib import Path


def register(sub) -> None:
    p = sub.add_parser("plot", help="rate–distortion and speed–accuracy plots of one or more results.json files")
    p.add_argument("results", nargs="+", help="results.json files or reports/<run>/ directories")
    p.add_argument("-o", "--output", default="reports/plots", help="output directory (default: reports/plots)")
    p.add_argument("--labels", nargs="*", default=None, help="one label per results file")
    p.add_argument("--overwrite", action="store_true", help="replace existing plots in the output directory")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ..harness.report import PLOT_FILES, load_results, plot_results
    from ..io import check_outputs

    out = Path(args.output)
    inputs = [r for r in args.results] + [Path(r) / "results.json" for r in args.results if Path(r).is_dir()]
    check_outputs({"-o/--output": [out / f for f in PLOT_FILES]}, {"RESULTS": inputs}, args.overwrite)  # before any work
    res = [load_results(r) for r in args.results]
    if args.labels is not None and len(args.labels) != len(res):
        raise ValueError(f"--labels has {len(args.labels)} entries for {len(res)} results files; accepted: one label per file")
    for p in plot_results(res, out, labels=args.labels):
        print(p)
    return 0
