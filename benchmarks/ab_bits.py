"""Same bits? Two revisions' relight kernels on every codec of tests/test_relight_codecs.py's CASES.

    .venv/bin/python benchmarks/ab_bits.py                         # HEAD vs the working tree
    .venv/bin/python benchmarks/ab_bits.py --base b1bf796 --march x86-64-v3

``ab_kernels.py`` times bench_relight's settings and reports their largest difference; this tool
covers the small, odd shapes the tests hold to the float64 reference (K = 1 and K > 1, with and
without a mean, packed codes, int16 labels, 8/16/24/49 rows, 1/3/5 colours, n_vectors prefixes,
dense views, tent taps and arbitrary taps) at 1 and 2 threads, and compares the results bit for
bit. Each side's sources and flags are read as ``ab_kernels`` reads them (the files in
``prt_torch/kernels/``, or before they moved the module's ``_SRC``); ``--march`` replaces
``-march=native`` on both sides (another instruction set's build). Exits 1 when any result differs.
"""
from __future__ import annotations

import argparse
import sys
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
sys.path.insert(0, str(ROOT / "tests"))
import ab_kernels  # noqa: E402
import test_relight_codecs as T  # noqa: E402

from prt_torch.codecs import relight_kernels  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="git revision of the reference kernels (default HEAD)")
    ap.add_argument("--test", default=".", help="git revision under test, or '.' for the working tree (default)")
    ap.add_argument("--march", default=None, help="build both with -march=MARCH instead of -march=native (e.g. x86-64-v3, x86-64)")
    args = ap.parse_args()
    libs = []
    for rev in (args.base, args.test):
        (src, flags), _ = ab_kernels.split_source(ab_kernels.module_text(rev), rev)
        if args.march:
            flags = [f for f in flags if f != "-march=native"] + [f"-march={args.march}"]
        lib, why = relight_kernels._compile(src, flags)
        if lib is None:
            raise SystemExit(f"ab_bits: the kernels of {rev!r} did not compile: {why}")
        libs.append(lib)
    own = relight_kernels.native()
    compared = differ = 0
    try:
        for label, name, params, ms, P, edit in T.CASES:
            n_out, n_in = ms
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                c, enc = T._fit(name, params, ms, P, edit)
            g, prefixes, views = T.case_inputs(c, P, n_out)
            for C, ns in ((3, prefixes), (1, [None]), (5, [None])):
                L = torch.randn(n_in, C, generator=g)
                for n in ns:
                    for view in views:
                        for nt in (1, 2):
                            torch.set_num_threads(nt)
                            outs = []
                            for lib in libs:
                                relight_kernels._state["lib"] = lib
                                enc.cache.clear()  # plans hold the library's layouts: rebuild per side
                                outs.append(c.relight(enc, L, view=view, n_vectors=n).clone())
                            compared += 1
                            if not torch.equal(outs[0].view(torch.int32), outs[1].view(torch.int32)):
                                differ += 1
                                print(f"differs: {label}, C={C}, n_vectors={n}, view={type(view).__name__}, threads={nt}, "
                                      f"max |diff| {float((outs[0] - outs[1]).abs().max()):.3e}")
    finally:
        relight_kernels._state["lib"] = own
    print(f"{args.base} vs {args.test}{f' (-march={args.march})' if args.march else ''}: {compared} results compared, "
          f"{differ} differ bit for bit")
    return 1 if differ else 0


if __name__ == "__main__":
    raise SystemExit(main())
