"""Paired A/B of two versions of the compiled relight kernels, on every codec and view mode.

    .venv/bin/python benchmarks/ab_kernels.py                        # HEAD vs the working tree
    .venv/bin/python benchmarks/ab_kernels.py --base 25850e2 --threads 1,2 --only cpca,vq
    .venv/bin/python benchmarks/ab_kernels.py --base HEAD~1 --test HEAD --shape default

Each version's C sources and compiler flags (the files ``prt_torch/kernels/*`` that
``_native.LIBRARIES['relight']`` lists, and its flags; before they moved there, the module's
string ``_SRC`` and ``_FLAGS``) come from a git revision or from the working tree (``--test .``,
the default). Both are compiled and cached by a hash of the source. The two
libraries are then swapped under the same ``codec.relight(..., out=)`` calls, and samples of each
are timed back to back in one process, in alternating order (``harness.timing.measure_paired``:
median of the per-repeat ratios, with their IQR). A machine that speeds up or slows down mid-run
therefore moves both sides of every ratio, and a change of a few per cent stays visible on a
shared machine.

Every comparison also reports ``maxdiff``, the largest absolute difference between the two
versions' results, which must be 0 for a change meant to keep the arithmetic.

Why a tool: code layout alone moves these kernels' speed. Adding a loop to one C function once
slowed another loop in it by 15–27%, so a kernel change needs every row checked, not only the
rows it targets.

The A/B is refused when the two revisions' Python differs outside how the sources are found
(``_SRC``/``_SOURCES``, ``_FLAGS``, ``_compile``; comments and docstrings may differ). The
Python side decides the constants' layouts and the arguments the kernels read, so mixing one
revision's Python with the other's C would compare different work.

``--accept-python-diff`` runs it anyway, for a revision whose Python differs in what the relight
calls do not use (the kernel-path reporting of issue 42 §4, a renamed helper): the difference is
printed (unparsed, without docstrings) for the record, and the ``maxdiff`` column is then the check
that both libraries did the same work. Entry points the working tree's Python loads and that
revision's sources lack (``prt_plan_path``, ``prt_isa``: path reporting only) are added to its
library as stubs returning 0, in a file of their own after its sources (compared on the Intel
Xeon: HEAD vs the Nov-24 kernels, reports/benchmarks/xeon_audit.md).

Shapes (``--shape``):
* ``relight``: ``bench_relight``'s 50 000-point settings (VQ 256, PCA 8, CPCA 256×8 static,
  iterative and adaptive; MRT-PCA 16; the Gaussian codec with 1 and 3 lobes), no view, dense
  view, and taps;
* ``diffuse``: ``bench_relight``'s diffuse rows: vectors, 50 000 points of 16 SH coefficients, an
  RGB result per point (VQ 256, PCA 8, CPCA 64×4, no view), 12 bytes out per point;
* ``default``: the default benchmark's shape, 10 242 points of a 64×16 MRT-like signal with 4
  tent taps and dense views (VQ 64, PCA 8, CPCA 16×4, MRT-PCA 8).

``--points N`` replaces the shape's point count (a quick check of the tool: tests/test_ab_kernels.py
runs it at 1000 points). Prints a markdown table; ``--out PATH`` also writes it (atomically).
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import ast  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch._native import kernel_isa  # noqa: E402
from prt_torch.codecs import relight_kernels  # noqa: E402
from prt_torch.codecs.synthetic import tent_taps_random, transfer_like  # noqa: E402
from prt_torch.harness.timing import machine_info, measure_paired  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_relight  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
MODULE = "prt_torch/codecs/relight_kernels.py"
NATIVE = "prt_torch/_native.py"
KERNELS = "prt_torch/kernels"


def git_text(rev: str, path: str) -> str:
    """A file of the repository at a git revision, or in the working tree (``rev == '.'``)."""
    if rev == ".":
        return (ROOT / path).read_text()
    r = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"ab_kernels: cannot read {path} at revision {rev!r}: {r.stderr.strip()}; "
                         "accepted: a git revision of this repository, or '.' for the working tree")
    return r.stdout


def module_text(rev: str) -> str:
    """The kernels module at a git revision, or in the working tree (``rev == '.'``)."""
    return git_text(rev, MODULE)


def _libraries(rev: str) -> dict:
    """``_native.LIBRARIES`` at ``rev`` (a literal dict: {name: (sources, flags)})."""
    for node in ast.parse(git_text(rev, NATIVE)).body:
        target = node.target if isinstance(node, ast.AnnAssign) else node.targets[0] if isinstance(node, ast.Assign) else None
        if isinstance(target, ast.Name) and target.id == "LIBRARIES":
            return ast.literal_eval(node.value)
    raise SystemExit(f"ab_kernels: {NATIVE} at {rev!r} has no literal LIBRARIES; accepted: a revision with the compiled kernels")


def split_source(text: str, rev: str) -> tuple[tuple[dict[str, str], list[str]], str]:
    """((the C sources ``{file name: text}``, the compiler flags), the rest of the module as code:
    its syntax tree without them, without ``_compile`` and the import of ``_native`` (how the sources
    are found), and without docstrings, so that comments and docs may differ). A revision from
    before the kernels moved to ``prt_torch/kernels/`` holds its source in the literal ``_SRC``: it
    is one file, ``relight.c``."""
    found = {}
    tree = ast.parse(text)
    body = []
    for node in tree.body:
        names = [t.id for t in getattr(node, "targets", []) if isinstance(t, ast.Name)] + \
            [e.id for t in getattr(node, "targets", []) if isinstance(t, ast.Tuple) for e in t.elts if isinstance(e, ast.Name)]
        if isinstance(node, ast.Assign) and set(names) & {"_SRC", "_FLAGS", "_SOURCES"}:
            if names in (["_SRC"], ["_FLAGS"]):
                found[names[0]] = ast.literal_eval(node.value)
            else:
                found["_SOURCES"] = True
        elif isinstance(node, ast.FunctionDef) and node.name == "_compile":
            continue
        elif isinstance(node, ast.ImportFrom) and node.module == "_native":
            continue
        else:
            body.append(node)
    if "_SRC" in found and "_FLAGS" in found:
        kernels = ({"relight.c": found["_SRC"]}, list(found["_FLAGS"]))
    elif "_SOURCES" in found:
        names, flags = _libraries(rev)["relight"]
        kernels = ({n: git_text(rev, f"{KERNELS}/{n}") for n in names}, list(flags))
    else:
        raise SystemExit(f"ab_kernels: {MODULE} at {rev!r} has neither a literal _SRC and _FLAGS nor _SOURCES; accepted: a revision "
                         "with the compiled kernels")
    tree.body = body
    for node in ast.walk(tree):
        b = getattr(node, "body", None)
        if isinstance(b, list) and b and isinstance(b[0], ast.Expr) and isinstance(b[0].value, ast.Constant) \
                and isinstance(b[0].value.value, str):
            node.body = b[1:] or [ast.Pass()]
    return kernels, ast.dump(tree)


STUBS = {"prt_plan_path": "int prt_plan_path(const long long *a) { (void)a; return 0; }",
         "prt_isa": "int prt_isa(void) { return 0; }"}


def with_stubs(kernels: tuple[dict[str, str], list[str]]) -> tuple[tuple[dict[str, str], list[str]], list[str]]:
    """``kernels`` with a file ``ab_stubs.c`` of the :data:`STUBS` its sources do not define (the entry
    points the working tree's Python loads that an older revision lacks), and the names added."""
    import re
    text = "\n".join(kernels[0].values())
    missing = [n for n in STUBS if not re.search(rf"\bint\s+{n}\s*\(", text)]
    if not missing:
        return kernels, []
    return ({**kernels[0], "ab_stubs.c": "/* ab_stubs.c: entry points of a later revision, stubs (ab_kernels) */\n"
             + "\n".join(STUBS[n] for n in missing) + "\n"}, kernels[1]), missing


def python_diff(rest: str, rest_here: str, rev: str) -> str:
    """The unified difference of two modules' code as ``split_source`` returns it (its syntax-tree dump,
    here unparsed back to Python, one statement a line)."""
    import difflib

    def code(dump: str) -> list[str]:
        return ast.unparse(ast.fix_missing_locations(eval(dump, vars(ast)))).splitlines(True)  # noqa: S307  (our own dump)
    return "".join(difflib.unified_diff(code(rest), code(rest_here), rev, "working tree", n=0))


def compile_source(kernels: tuple[dict[str, str], list[str]], label: str):
    """The kernels library compiled from ``(sources, flags)`` (``relight_kernels._compile``, cached
    by a hash of both)."""
    lib, why = relight_kernels._compile(*kernels)
    if lib is None:
        raise SystemExit(f"ab_kernels: the kernels of {label} did not compile: {why}")
    want = " ".join(list(kernels[1]) + list(kernel_isa()[1]))  # what _compile adds for PRT_TORCH_KERNEL_ISA included
    if f"({want})" not in why:  # built only by the fallback without -march=native: another ISA
        raise SystemExit(f"ab_kernels: the kernels of {label} compiled only with other flags than {want} "
                         f"({why}): the A/B would compare another instruction set; accepted: a source that compiles with "
                         "its flags (compile it by hand to see the error)")
    return lib


def cases(shape: str, only: list[str], cache: Path, points: int | None = None):
    """(label, codec, encoding, light, [(mode, view)]) for the chosen shape (``points``: instead of
    its point count, for a quick check of the tool itself)."""
    g = torch.Generator().manual_seed(0)
    if shape in ("relight", "diffuse"):  # bench_relight's settings; "diffuse": its vector rows only
        P = points or 50000
        sig = {"glossy": (transfer_like(P, 24, 25, seed=0), (24, 25)), "mrt": (transfer_like(P, 49, 25, seed=3), (49, 25)),
               "diffuse": (transfer_like(P, 1, 16, seed=5), None)}  # vectors: 16 SH coefficients, an RGB result [P, 3]
        views = {"glossy": [("none", None), ("dense", torch.randn(P, 24, generator=g))],
                 "mrt": [("none", None), ("dense", torch.randn(P, 49, generator=g)), ("taps", tent_taps_random(P, 7, seed=4))],
                 "diffuse": [("none", None)]}
        todo = [t for t in bench_relight.settings(False) if (t[3] == "diffuse") == (shape == "diffuse")]
        light = torch.randn(25, 3, generator=g)
    else:
        P = points or 10242
        sig = {"mrt": (transfer_like(P, 64, 16, seed=0), (64, 16))}
        views = {"mrt": [("taps", tent_taps_random(P, 8, seed=1)), ("dense", torch.randn(P, 64, generator=g))]}
        todo = [("vq 64", "vq", {"clusters": 64, "max_iter": 10}, "mrt"), ("pca 8", "pca", {"vectors": 8}, "mrt"),
                ("cpca 16x4", "cpca_static", {"clusters": 16, "vectors": 4, "max_iter": 10}, "mrt"),
                ("mrt_pca 8", "mrt_pca", {"vectors": 8}, "mrt")]
        light = torch.randn(16, 3, generator=g)
    for label, name, params, s in todo:
        if only and not any(o in label for o in only):
            continue
        X, ms = sig[s]
        c, enc, _ = bench_relight.fitted(name, params, X, ms, cache)
        yield label, c, enc, light[:ms[1] if ms else X.shape[1]], views[s]
    if shape == "relight":  # bench_relight's Gaussian rows: every stored view, and camera taps
        pe = bench_relight.prefilter_environment(light.T.contiguous().double(), res=16)
        for lobes in (1, 3):
            label = f"gaussian {lobes}"
            if only and not any(o in label for o in only):
                continue
            c, enc = bench_relight.gaussian_fitted(lobes, P)
            yield label, c, enc, pe, [("none", None), ("taps", bench_relight.gaussian_view(c, P))]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", default="HEAD", help="git revision of the reference kernels (default HEAD)")
    ap.add_argument("--test", default=".", help="git revision of the kernels under test, or '.' for the working tree (default)")
    ap.add_argument("--shape", choices=["relight", "default", "diffuse"], default="relight")
    ap.add_argument("--threads", default="1", help="comma list of thread counts (default 1)")
    ap.add_argument("--only", default="", help="comma list of substrings of codec labels (default: all)")
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--points", type=int, default=None, help="points per setting instead of the shape's (a quick check)")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "prt_bench_relight"))
    ap.add_argument("--out", default=None, help="also write the table to this file")
    ap.add_argument("--accept-python-diff", action="store_true",
                    help="run although a revision's module differs from the working tree's outside the kernel sources "
                         "(printed; maxdiff is the check); entry points it lacks get stubs (see the docstring)")
    ap.add_argument("--clock", choices=["wall", "cpu"], default="wall",
                    help="wall: time.perf_counter (default); cpu: the thread's CPU time (time.thread_time), one thread only: "
                         "on a shared machine the time other processes held the core is in neither side")
    args = ap.parse_args()
    threads = [int(t) for t in args.threads.split(",")]
    if any(t < 1 for t in threads):
        raise SystemExit(f"ab_kernels: --threads {args.threads!r}; accepted: positive integers, comma-separated")
    if args.clock == "cpu" and threads != [1]:
        raise SystemExit(f"ab_kernels: --clock cpu with --threads {args.threads!r}; accepted: --threads 1 (the CPU-time clock "
                         "counts the calling thread only)")
    for name in ("repeats", "points"):
        v = getattr(args, name)
        if v is not None and v < (3 if name == "repeats" else 64):
            raise SystemExit(f"ab_kernels: --{name} {v}; accepted: an integer >= {3 if name == 'repeats' else 64}")
    (src_a, rest_a), (src_b, rest_b) = (split_source(module_text(r), r) for r in (args.base, args.test))
    _, rest_here = split_source(module_text("."), ".")
    stubbed = {}
    for rev, rest in ((args.base, rest_a), (args.test, rest_b)):
        if rest != rest_here and args.accept_python_diff:
            print(f"note: {MODULE} at {rev!r} differs from the working tree's outside its kernel sources (accepted by "
                  f"--accept-python-diff; maxdiff is the check):\n{python_diff(rest, rest_here, rev)}", file=sys.stderr)
        elif rest != rest_here:  # this process runs the working tree's Python side
            raise SystemExit(f"ab_kernels: {MODULE} differs between {rev!r} and the working tree outside its kernel sources and flags "
                             "(layouts, wrappers): the kernels would not do the work they were written for; accepted: revisions "
                             "whose module differs from the working tree's in _SRC/_SOURCES, _FLAGS and _compile only")
    if src_a == src_b:
        print(f"note: {args.base!r} and {args.test!r} have the same kernel source and flags; the ratios measure only the noise", file=sys.stderr)
    if args.accept_python_diff:
        (src_a, stubbed[args.base]), (src_b, stubbed[args.test]) = with_stubs(src_a), with_stubs(src_b)
        for rev, names in stubbed.items():
            if names:
                print(f"note: {rev!r} lacks {', '.join(names)}: stubs returning 0 added (ab_stubs.c)", file=sys.stderr)
    lib_a, lib_b = compile_source(src_a, args.base), compile_source(src_b, args.test)
    relight_kernels.native()  # the process's own library, restored after each pair
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    only = [o for o in args.only.split(",") if o]
    lines = [f"# Kernel A/B: {args.base} (base) vs {args.test if args.test != '.' else 'working tree'} (test)", "",
             f"Machine: {machine_info().get('cpu')}; shape {args.shape}; paired, {args.repeats} repeats, "
             f"{'CPU time (time.thread_time)' if args.clock == 'cpu' else 'wall time'}; "
             "ratio = base time / test time (> 1: test faster), median [IQR]; kernels built for "
             f"PRT_TORCH_KERNEL_ISA={relight_kernels._state.get('isa_choice', 'native')}; load average at the start "
             f"{', '.join(f'{x:.2f}' for x in os.getloadavg())}.", "",
             "| codec | view | threads | base (ms) | test (ms) | ratio | maxdiff |", "|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    own = relight_kernels._state.get("lib")
    try:
        for label, c, enc, light, views in cases(args.shape, only, cache, args.points):
            for mode, view in views:
                buf = torch.empty_like(c.relight(enc, light, view=view))

                def on(lib):
                    def call():
                        relight_kernels._state["lib"] = lib
                        return c.relight(enc, light, view=view, out=buf)
                    return call

                fa, fb = on(lib_a), on(lib_b)
                ra, rb = fa().clone(), fb().clone()
                diff = float((ra - rb).abs().max()) if ra.numel() else 0.0
                for nt in threads:
                    torch.set_num_threads(nt)
                    p = measure_paired(fb, fa, repeats=args.repeats, warmup=2,
                                       clock=time.thread_time if args.clock == "cpu" else time.perf_counter)
                    row = (f"| {label} | {mode} | {nt} | {1e3 * p.peer.median:.3f} | {1e3 * p.test.median:.3f} | "
                           f"**{p.ratio.median:.3f}** [{p.ratio.q1:.3f}, {p.ratio.q3:.3f}] | {diff:.1e} |")
                    lines.append(row)
                    print(row, flush=True)
    finally:
        relight_kernels._state["lib"] = own
    lines += ["", f"Load average at the end: {', '.join(f'{x:.2f}' for x in os.getloadavg())}."]
    print(lines[-1], flush=True)
    if args.out:
        atomic_write_text(Path(args.out), "\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
