"""The wavelet kernel's row-major sparse pass (issue 39): two versions of ``kernels/wavelet.c`` compiled side by side
(``--base``, default the kernel before the row-pass change, against ``--test``, default the working tree: a git
revision, ``.``, or a path to a ``.c`` file), both bound to one layout of one relighter (the row-major copy built),
timed paired by one thread's CPU time (``measure_paired(clock=time.thread_time)``: the time other processes held the
core is in neither side), every output compared bit for bit between the two.

Rows: studio and sky (transport-weighted) at N = 100, 300, 1000, 2000 and all, each whole light, and the light's
sparse terms alone at N = 2000 and all (the row-major pass, the set-up and the output pass; no dense terms) — the
part this change is about, also as ns and cycles per row-major entry (the clock measured in the run by
``bench_wavelet_floor_micro``'s chain of dependent multiplies). ``--crossover``: the test build alone, each light at
N = 300 … all with the pass forced both ways (the layout's ``row_permille`` 0 / 1001), column-major time over
row-major time against the share of the sparse blocks the light's sparse terms hold (the kernel takes the row-major
pass from ``row_min`` of them: the build's default, ``WaveletRelighter.default_row_min``): where the two passes cross.
``--sweep`` (one build per run: this process's ``PRT_TORCH_KERNEL_ISA``) sweeps that share with synthetic lights on
larger scenes too and writes JSONs; ``--summarise`` turns them into reports/benchmarks/wavelet_rowmin.md (the
crossovers per build, what each threshold costs).

The kernel section's transfer (occluder_over_plane small, R = 32, K = 256, 16 bits). Writes
reports/benchmarks/wavelet_rowpass.md (the CPU, both builds, the flags and the load named).

    .venv/bin/python benchmarks/bench_wavelet_rowpass.py --crossover          (about 2 minutes)
    .venv/bin/python benchmarks/bench_wavelet_rowpass.py --sweep --write DIR/x.md   (2-7 minutes; then --summarise DIR/*.json)
    PRT_TORCH_KERNEL_ISA=avx2 .venv/bin/python benchmarks/bench_wavelet_rowpass.py --write ''   (the AVX2 build)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import ctypes  # noqa: E402
import functools  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT, load  # noqa: E402
from bench_wavelet_floor_micro import SRC as CLOCK_SRC  # noqa: E402
from bench_wavelet_isa import kernel_build, kernel_source  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
#: the kernel before the row-major pass's change (main at 69385e0)
BASE = "69385e0"
TERMS = (100, 300, 1000, 2000)
CROSS = (300, 500, 700, 850, 1000, 1200, 1500, 2000)


def build(text: str, tag: str):
    """The i16 packed entry point of ``text`` compiled with the wavelet library's flags and this process's
    ``PRT_TORCH_KERNEL_ISA`` (bench_wavelet_isa.kernel_build; cached by the source's hash), its flags and the build's
    ``prt_wavelet_isa`` bits."""
    lib, flags = kernel_build(text, None, f"bench_wavelet_rowpass ({tag})")
    return lib.prt_wavelet_relight_i16_packed, flags, int(lib.prt_wavelet_isa())


def bound(fn, layout: torch.Tensor, f: torch.Tensor, li: torch.Tensor, lv: torch.Tensor, out: torch.Tensor,
          threads: int = 1):
    """``run()``: ``fn`` relighting ``li``/``lv`` into ``out`` on ``layout`` (``threads`` threads), as ``prepared``
    does."""
    args = torch.tensor([layout.data_ptr(), li.numel(), li.data_ptr(), lv.data_ptr(), lv.shape[0], f.data_ptr(),
                         out.data_ptr(), threads], dtype=torch.int64)
    call = functools.partial(fn, args.data_ptr())
    held = (layout, f, li, lv, out, args)

    def run():
        st = call()
        if st:
            raise RuntimeError(f"the wavelet kernel returned {st}")
        return held[4]
    return run


#: ``--sweep``'s real lights (transport-weighted terms at N = CROSS and all): overcast is grey (three equal channels:
#: the kernel's one-sum path)
REAL = {"sky (sun)": LIGHTS["sky (sun)"], "overcast": "overcast", "cap 40°": LIGHTS["cap 40°"], "studio": LIGHTS["studio"]}
#: ``--sweep``: the shares of the sparse blocks held that the synthetic lights aim at (each the first N terms of its
#: order reaching the share; the share reached is reported)
SWEEP = tuple(round(0.40 + 0.025 * i, 3) for i in range(17))  # 0.400 ... 0.800


def synthetic_light(rl, order: str, share: float, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor, float]:
    """A synthetic RGB light on ``rl``'s columns whose sparse terms hold about ``share`` of the sparse blocks: the
    first N of the columns some vertex keeps, in ``order`` — ``'transport'`` (descending transport weight, as a
    uniform light's transport-weighted selection: coarse levels first) or ``'random'`` (every dense column, then the
    sparse ones in a fixed random order: features spread over the levels) —, N the smallest reaching ``share``.
    Values uniform in [0.2, 1) per channel (seeded). → ``(li [N] int64, lv [3, N] float32, share held)``."""
    cols = torch.nonzero(rl.nnz > 0).flatten()
    if order == "transport":
        cols = cols[torch.argsort(rl.weights[cols], descending=True, stable=True)]
    elif order == "random":
        g = torch.Generator().manual_seed(seed)
        dense, sparse = cols[rl.dslot[cols] >= 0], cols[rl.dslot[cols] < 0]
        cols = torch.cat([dense, sparse[torch.randperm(sparse.numel(), generator=g)]])
    else:
        raise ValueError(f"synthetic_light: order={order!r}; accepted: 'transport', 'random'")
    blocks = torch.where(rl.dslot[cols] < 0, rl._cblk[cols].long(), 0)
    held = torch.cumsum(blocks, 0) / max(rl.NB, 1)
    N = min(int(torch.searchsorted(held, torch.tensor([share], dtype=held.dtype))[0]) + 1, cols.numel())
    g = torch.Generator().manual_seed(seed + 1)
    lv = (0.2 + 0.8 * torch.rand(3, N, generator=g)).to(torch.float32)
    return cols[:N].contiguous(), lv.contiguous(), float(held[N - 1])


def sweep(args) -> None:
    """``--sweep``: the working tree's kernel, built for this process's ``PRT_TORCH_KERNEL_ISA``, on each
    ``--scenes`` size of occluder_over_plane (``--res`` R, default 32, ``--K`` terms per vertex, default 256,
    16-bit), synthetic lights (:func:`synthetic_light`, both orders) at the :data:`SWEEP` shares and the :data:`REAL`
    lights at N = 300 ... all, each with the pass forced row-major and column-major (``row_permille`` 0 / 1001) on
    copies of one layout, paired: one thread by its CPU time, or ``--threads`` 2 by wall time (the floor of short
    samples). Writes a JSON of the rows (``--write``'s name, its suffix ``.<isa>.t<threads>.json``; the report is
    ``--summarise``'s)."""
    import json

    from prt_torch.harness.timing import torch_threads

    text, label = kernel_source(".", "bench_wavelet_rowpass: --sweep")
    fn, flags, bits = build(text, "sweep")
    isa = relight.wavelet_kernel_path()
    before = load()
    rows = []
    for size in args.scenes.split(","):
        mesh = builtin("occluder_over_plane", size)
        t0 = time.perf_counter()
        tr = precompute_wavelet(mesh, args.res, args.K, BITS, shadows="always", run=RunOptions(workers=1))
        rl = relight.WaveletRelighter(tr, threads=args.threads, layouts="both")
        size = size if (args.res, args.K) == (32, 256) else f"{size} R{args.res} K{args.K}"
        rl._kernel()
        print(f"[rowmin] {size}: V = {rl.V}, {rl.Pd} dense columns, {rl.NB} sparse blocks, tiles of {rl.TV} "
              f"({time.perf_counter() - t0:.0f} s to build)", flush=True)
        f = rl._factor(3, True)
        lay_row, lay_col = rl._layout.clone(), rl._layout.clone()
        lay_row[24], lay_col[24] = 0, 1001  # row_permille: the row-major pass for any light, never
        cases = [(o, s) for o in ("transport", "random") for s in SWEEP]
        cases += [(light, N) for light in REAL for N in CROSS + (rl.P,)]
        seen = set()
        for name, x in cases:
            if name in ("transport", "random"):
                li, lv, held = synthetic_light(rl, name, x)
            else:
                li, lv, _ = rl.light(REAL[name], x, "transport")
                li, lv = li.contiguous(), lv.to(torch.float32).contiguous()
                if (name, li.numel()) in seen:  # fewer nonzero terms than N: timed once
                    continue
                seen.add((name, li.numel()))
                s = li[rl.dslot[li] < 0]
                held = int(rl.bcount[:, s[rl.nnz[s] > 0]].sum()) / rl.NB
            outs = [torch.empty(rl.V, 3), torch.empty(rl.V, 3)]
            r, c = bound(fn, lay_row, f, li, lv, outs[0], args.threads), bound(fn, lay_col, f, li, lv, outs[1], args.threads)
            r(), c()
            with torch_threads(args.threads):
                if args.threads == 1:
                    p = measure_paired(r, c, repeats=args.repeats, warmup=1, clock=time.thread_time)
                else:
                    p = measure_paired(r, c, repeats=args.repeats, warmup=1, floor_pairs=40, floor_max_pairs=160)
            diff = float((outs[0] - outs[1]).abs().max()) / (float(outs[1].abs().max()) or 1.0)
            rows.append({"scene": size, "V": rl.V, "NB": rl.NB, "light": name, "N": int(li.numel()), "held": held,
                         "us": [p.test.median * 1e6, p.peer.median * 1e6], "ratio": p.speedup,
                         "q": [p.ratio.q1, p.ratio.q3], "diff": diff, "load": load()})
            x = rows[-1]
            print(f"[rowmin] {size} {name} N={x['N']} held {held:.3f}: row {x['us'][0]:.1f} us, column "
                  f"{x['us'][1]:.1f} us, column/row {x['ratio']:.3f} [{x['q'][0]:.3f}, {x['q'][1]:.3f}], "
                  f"max|diff|/max {diff:.1e}, load {x['load']:.1f}", flush=True)
    after = load()
    run = {"cpu": cpu_label(), "build": isa, "flags": flags, "bits": bits, "threads": args.threads,
           "repeats": args.repeats, "load": [before, after], "rows": rows}
    if args.write:
        atomic_write_text(Path(args.write).with_suffix(f".{isa.get('isa')}.t{args.threads}.json"), json.dumps(run, indent=1))
    print(json.dumps({k: v for k, v in run.items() if k != "rows"}), flush=True)


#: ``--summarise``: the thresholds whose cost is tabulated
THRESHOLDS = (0.50, 0.55, 0.58, 0.60, 0.62, 0.64, 0.66, 0.70)


def _fit_crossover(pts: list[tuple[float, float]]) -> float | None:
    """The share where a least-squares line through ``(held, column / row)`` points (held 0.45 ... 0.80) reaches 1;
    None with fewer than three points or a flat line."""
    pts = [(h, r) for h, r in pts if 0.45 <= h <= 0.80]
    if len(pts) < 3:
        return None
    n = len(pts)
    mx, my = sum(h for h, _ in pts) / n, sum(r for _, r in pts) / n
    sxx = sum((h - mx) ** 2 for h, _ in pts)
    a = sum((h - mx) * (r - my) for h, r in pts) / sxx if sxx else 0.0
    return None if a <= 0 else mx + (1 - my) / a


def summarise(paths: list[str], write: str) -> None:
    """``--summarise``: the ``--sweep`` runs' JSONs (several per build: repeated runs) → the report. Per build, thread
    count, scene and light family: the median over runs of column / row at each share held, the crossover of a line
    fitted to those medians (shares 0.45-0.80) and the spread of the per-run fits; per build, what each threshold
    costs the lights measured at shares 0.40-0.80 (the pass a threshold sends a light to, over the faster: mean and
    worst)."""
    import json
    import statistics

    runs = [json.loads(Path(p).read_text()) for p in paths]
    groups: dict = {}
    for i, run in enumerate(runs):
        b = (run["build"].get("isa"), bool(run["build"].get("w16")), run["threads"])
        for r in run["rows"]:
            fam = r["light"]
            key = (b, r["scene"], fam)
            groups.setdefault(key, {}).setdefault((r["N"], round(r["held"], 3)), []).append((i, r["ratio"]))
    builds = sorted({k[0] for k in groups}, key=lambda b: (b[2], not b[1]))
    L = ["# Wavelet kernel: where the row-major sparse pass pays, per kernel build (issue 39)\n"]
    cpus = sorted({r["cpu"] for r in runs})
    loads = [x for r in runs for x in r["load"]]
    L.append(f"{'; '.join(cpus)}; {len(runs)} runs of `benchmarks/bench_wavelet_rowpass.py --sweep` (load average "
             f"{min(loads):.1f}-{max(loads):.1f} at their starts and ends: the machine shared with other jobs). Each run: "
             "the working tree's `kernels/wavelet.c` in one build (`PRT_TORCH_KERNEL_ISA` unset: the AVX-512 build with "
             "the 16-lane code, W16; `=avx2`: the AVX2 code, a proxy on this CPU for the AMD Zen 3 it was tuned on, not "
             "the Zen 3 itself), on occluder_over_plane at R = 32, K = 256, 16-bit values (small: V = 2251, 43 228 "
             "sparse 8-vertex blocks, 0.87 MB row-major copy, L2-resident with the dense part; medium: V = 10 585, "
             "148 328 blocks, 3.0 MB; large: V = 51 335, 556 687 blocks, 11.2 MB: beyond the 2 MB L2), each light relit "
             "with the pass forced row-major and column-major (`row_permille` 0 / 1001 on copies of one layout), paired: "
             "one thread by its CPU time (`measure_paired(clock=time.thread_time)`), two threads by wall time (the "
             "fastest tenth of short samples). *column / row* > 1: the row-major pass is faster. Lights: *transport* "
             "(synthetic: the columns some vertex keeps in descending transport weight, coarse levels first — a "
             "uniform light's transport-weighted selection — up to the share), *random* (synthetic: every dense "
             "column, then sparse columns in a random order: more, smaller columns per share), and the real sky (sun), "
             "overcast (grey: the kernel's one-sum path) at N = 300 ... all (transport-weighted); the same at R = 16, "
             "K = 64 where named (R16 K64). *crossover*: where a line fitted to column / row against the share held "
             "(0.45-0.80) reaches 1 — the medians over runs, and each run's own. Reproduce (one run per build; the "
             "JSONs beside this report, reports/benchmarks/wavelet_rowmin/): `.venv/bin/python "
             "benchmarks/bench_wavelet_rowpass.py --sweep --scenes small,medium,large --repeats 21 --write DIR/x.md`, "
             "the same with `PRT_TORCH_KERNEL_ISA=avx2`, with `--threads 2`, with `--res 16 --K 64`; then "
             "`--summarise DIR*/*.json`.\n")
    for b in builds:
        isa, w16, th = b
        L.append(f"## {isa} build{' (W16)' if w16 else ''}, {th} thread{'s' if th > 1 else ''}\n")
        L.append("| scene | lights | crossover (fit to the medians) | per-run fits | column / row at shares held (median "
                 "over runs) |")
        L.append("|---|---|---|---|---|")
        costs: dict = {}  # scene -> threshold -> the losses of its lights
        for (bb, scene, fam), pts in sorted(groups.items(), key=lambda kv: (kv[0][1] != "small", kv[0][1], kv[0][2])):
            if bb != b:
                continue
            med = sorted((h, statistics.median(x[1] for x in v)) for (_, h), v in pts.items())
            if not any(0.40 <= h <= 0.80 for h, _ in med):
                continue
            nrun = len({x[0] for v in pts.values() for x in v})
            fits = [_fit_crossover([(h, x[1]) for (_, h), v in pts.items() for x in v if x[0] == i])
                    for i in sorted({x[0] for v in pts.values() for x in v})]
            out = sum(1 for f in fits if f is None or not 0.35 <= f <= 0.90)  # flat or noisy: no crossover in range
            fits = [f for f in fits if f is not None and 0.35 <= f <= 0.90]
            x0 = _fit_crossover(med)
            x0 = x0 if x0 is not None and 0.35 <= x0 <= 0.90 else None
            shown = ", ".join(f"{h:.3f}: {r:.3f}" for h, r in med if 0.40 <= h <= 0.80)
            L.append(f"| {scene} | {fam} ({nrun} runs) | {f'**{x0:.3f}**' if x0 is not None else '—'} | "
                     f"{f'{min(fits):.3f}-{max(fits):.3f}' if fits else '—'}{f' ({out} outside 0.35-0.90)' if out else ''} | "
                     f"{shown} |")
            for h, r in med:
                if 0.40 <= h <= 0.80:
                    for t in THRESHOLDS:
                        loss = max(0.0, 1 / r - 1) if h >= t else max(0.0, r - 1)
                        costs.setdefault(scene, {}).setdefault(t, []).append(loss)
                        costs.setdefault("all", {}).setdefault(t, []).append(loss)
        L += ["", "What a threshold costs: each light above at shares 0.40-0.80 sent to the pass the threshold chooses, "
              "its time over the faster pass's (medians over runs) less 1: the mean over the lights, and in brackets "
              "the worst:\n", "| scene | " + " | ".join(f"row_min {t:.2f}" for t in THRESHOLDS) + " |",
              "|---|" + "---|" * len(THRESHOLDS)]
        for scene in sorted(costs, key=lambda x: (x == "all", x.split()[0] != "small", x)):
            c = costs[scene]
            L.append(f"| {scene} | " + " | ".join(f"{100 * sum(c[t]) / len(c[t]):.1f}% ({100 * max(c[t]):.0f}%)"
                                                  for t in THRESHOLDS) + " |")
        L.append("")
    text = "\n".join(L) + "\n"
    if write:
        atomic_write_text(write, text)
        print(f"[rowmin] wrote {write}", flush=True)
    print(text)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", default=BASE, help="the kernel to pair against: a git revision, '.', or a .c file")
    ap.add_argument("--test", default=".", help="the kernel measured: '.', a git revision or a .c file")
    ap.add_argument("--ls", type=int, default=0, help="compile the test kernel with ROW_LS (8-vertex blocks in lockstep "
                    "on the AVX-512 build: 1, 2 or 4; 0: its default)")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--crossover", action="store_true", help="also the two passes forced on the test build")
    ap.add_argument("--quick", action="store_true", help="N = 1000, 2000, all and the sparse rows only")
    ap.add_argument("--write", default=str(OUT / "wavelet_rowpass.md"), help="the report ('' : print only)")
    ap.add_argument("--sweep", action="store_true", help="the crossover only, the working tree's kernel in this "
                    "process's build: synthetic lights sweeping the share of sparse blocks held and the real lights, "
                    "on --scenes (writes --write, default reports/benchmarks/wavelet_rowmin.md, with a JSON)")
    ap.add_argument("--scenes", default="small,medium", help="--sweep: occluder_over_plane sizes, comma-separated")
    ap.add_argument("--threads", type=int, default=1, help="--sweep: the kernel's threads (1: CPU time; 2: wall time)")
    ap.add_argument("--res", type=int, default=32, help="--sweep: the transfer's cube face size R")
    ap.add_argument("--K", type=int, default=256, help="--sweep: the transfer's terms kept per vertex")
    ap.add_argument("--summarise", nargs="+", metavar="JSON", help="the report from --sweep runs' JSONs (written to "
                    "--write, default reports/benchmarks/wavelet_rowmin.md)")
    args = ap.parse_args()
    if args.summarise:
        if args.write == str(OUT / "wavelet_rowpass.md"):
            args.write = str(OUT / "wavelet_rowmin.md")
        return summarise(args.summarise, args.write)
    if args.sweep:
        if args.threads not in (1, 2):
            raise SystemExit(f"bench_wavelet_rowpass: --threads {args.threads}; accepted: 1 or 2")
        if args.write == str(OUT / "wavelet_rowpass.md"):
            args.write = str(OUT / "wavelet_rowmin.md")
        return sweep(args)
    if args.repeats < 3:
        raise SystemExit(f"bench_wavelet_rowpass: --repeats {args.repeats}; accepted: an integer >= 3")
    if args.ls not in (0, 1, 2, 4):
        raise SystemExit(f"bench_wavelet_rowpass: --ls {args.ls}; accepted: 1, 2, 4 (0: the kernel's default)")
    (ttext, tlabel), (btext, blabel) = (kernel_source(x, f"bench_wavelet_rowpass: --{o}") for o, x in (("test", args.test), ("base", args.base)))
    if args.ls:
        ttext, tlabel = f"#define ROW_LS {args.ls}\n" + ttext, f"{tlabel} with ROW_LS {args.ls}"
    (tfn, flags, bits), (bfn, _, _) = build(ttext, "test"), build(btext, "base")
    clk = compile_library("wavelet_floor_micro", CLOCK_SRC, ["-O2", "-shared", "-fPIC", "-std=c99"], {})[0]
    clk.clock_ghz.restype = ctypes.c_double
    torch.set_num_threads(1)
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="both")
    rl._kernel()
    layout = rl._layout
    f = rl._factor(3, True)
    ghz = [clk.clock_ghz()]
    before = load()
    rows = []
    terms = (1000, 2000) if args.quick else TERMS
    cases = [(light, N, part) for light in ("studio", "sky (sun)") for N in terms + (rl.P,) for part in ("all", "sparse")
             if part == "all" and not args.quick or part == "sparse" and N >= 2000]
    cases.insert(0, ("studio", 1, "pass"))
    lay_row = layout.clone()
    lay_row[24] = 0  # row_permille 0: the row-major pass for any light holding a sparse block
    for light, N, part in cases:
        if part == "pass":  # one sparse term, the row-major pass forced: every entry read, (almost) no set-up
            li, lv, _ = rl.light(LIGHTS[light], 64, "transport")
            first = int(torch.nonzero((rl.dslot[li] < 0) & (rl.nnz[li] > 0))[0])
            li, lv = li[first:first + 1], lv[:, first:first + 1].to(torch.float32).contiguous()
        else:
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            lv = lv.to(torch.float32).contiguous()
        if part == "sparse":
            keep = rl.dslot[li] < 0
            li, lv = li[keep], lv[:, keep].contiguous()
        li = li.contiguous()
        s = li[rl.dslot[li] < 0]
        held = int(rl.bcount[:, s[rl.nnz[s] > 0]].sum()) / rl.NB
        outs = [torch.empty(rl.V, 3), torch.empty(rl.V, 3)]
        lay = lay_row if part == "pass" else layout
        t, b = bound(tfn, lay, f, li, lv, outs[0]), bound(bfn, lay, f, li, lv, outs[1])
        t(), b()
        same = bool(torch.equal(outs[0], outs[1]))
        p = measure_paired(t, b, repeats=args.repeats, warmup=1, clock=time.thread_time)
        row = {"light": light, "N": N, "part": part, "terms": int(li.numel()), "held": held,
               "pass": "row" if held >= rl.row_min or part == "pass" else "column", "us": [p.test.median * 1e6, p.peer.median * 1e6],
               "ratio": p.speedup, "q": [p.ratio.q1, p.ratio.q3], "same": same, "load": load()}
        rows.append(row)
        print(f"[rowpass] {light} N={N} {part} ({row['pass']}-major, held {held:.2f}): base {row['us'][1]:.1f} us, "
              f"test {row['us'][0]:.1f} us, base/test {row['ratio']:.3f} [{row['q'][0]:.3f}, {row['q'][1]:.3f}], "
              f"bit-identical {same}, load {row['load']:.1f}", flush=True)
    cross = []
    if args.crossover:
        lay_row, lay_col = layout.clone(), layout.clone()
        lay_row[24], lay_col[24] = 0, 1001  # row_permille: the row-major pass for any light, never
        for light in ("studio", "sky (sun)"):
            for N in CROSS + (rl.P,):
                li, lv, _ = rl.light(LIGHTS[light], N, "transport")
                lv = lv.to(torch.float32).contiguous()
                s = li[rl.dslot[li] < 0]
                held = int(rl.bcount[:, s[rl.nnz[s] > 0]].sum()) / rl.NB
                outs = [torch.empty(rl.V, 3), torch.empty(rl.V, 3)]
                r, c = bound(tfn, lay_row, f, li, lv, outs[0]), bound(tfn, lay_col, f, li, lv, outs[1])
                r(), c()
                p = measure_paired(r, c, repeats=args.repeats, warmup=1, clock=time.thread_time)
                scale = float(outs[1].abs().max()) or 1.0
                diff = float((outs[0] - outs[1]).abs().max()) / scale
                cross.append({"light": light, "N": N, "held": held, "us": [p.test.median * 1e6, p.peer.median * 1e6],
                              "ratio": p.speedup, "q": [p.ratio.q1, p.ratio.q3], "diff": diff, "load": load()})
                x = cross[-1]
                print(f"[rowpass] crossover {light} N={N} held {held:.3f}: row {x['us'][0]:.1f} us, column "
                      f"{x['us'][1]:.1f} us, column/row {x['ratio']:.3f} [{x['q'][0]:.3f}, {x['q'][1]:.3f}], "
                      f"max|diff|/max {diff:.1e}, load {x['load']:.1f}", flush=True)
    ghz.append(clk.clock_ghz())
    after = load()
    g = sum(ghz) / 2
    L = ["# Wavelet kernel: the row-major sparse pass, paired against the kernel before (issue 39)\n",
         f"{cpu_label()}; clock {ghz[0]:.2f} / {ghz[1]:.2f} GHz (before / after, a chain of dependent multiplies); "
         f"load average {before:.1f} → {after:.1f} (the machine shared with other jobs). Both kernels compiled here with "
         f"`{flags}` (`PRT_TORCH_KERNEL_ISA`={os.environ.get('PRT_TORCH_KERNEL_ISA', 'unset')}; the build's "
         f"`prt_wavelet_isa` bits {bits}: {'the dense loop on 16 lanes (W16)' if bits & 32 else 'no W16'}), bound to one "
         f"layout (occluder_over_plane small, V = {rl.V}, R = 32, K = 256, {BITS}-bit, {rl.Pd} dense columns, "
         f"{rl.NB} sparse 8-vertex blocks = row-major entries, tiles of {rl.TV}; the row-major copy built). "
         f"**test**: {tlabel}; **base**: {blabel}. One thread, paired by its CPU time "
         f"(`measure_paired(clock=time.thread_time)`, {args.repeats} repeats): medians per call and the median of the "
         "per-repeat ratios base / test [quartiles] (> 1: test faster); *same bits*: the two outputs equal bit for bit. "
         "*sparse*: the light's sparse terms alone (no dense terms: the pass, the set-up and the output). Reproduce: "
         f"`.venv/bin/python benchmarks/bench_wavelet_rowpass.py --base {args.base} --test {args.test}"
         f"{f' --ls {args.ls}' if args.ls else ''}{f' --repeats {args.repeats}' if args.repeats != 15 else ''}"
         f"{' --crossover' if args.crossover else ''}`.\n",
         "| light | N | terms | sparse blocks held | pass | test | base | **base / test** [quartiles] | test ns (cycles) per "
         "entry (the call / entries) | same bits | load |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        per = (f"{r['us'][0] * 1e3 / rl.NB:.2f} ({r['us'][0] * 1e3 / rl.NB * g:.1f})"
               if r["part"] in ("sparse", "pass") and r["pass"] == "row" else "")
        L.append(f"| {r['light']} | {r['N']} | {dict(sparse='sparse ', all='').get(r['part'], 'row pass alone: ')}{r['terms']} | {r['held']:.2f} | "
                 f"{r['pass']} | {r['us'][0]:.1f} µs | {r['us'][1]:.1f} µs | **{r['ratio']:.3f}** [{r['q'][0]:.3f}, "
                 f"{r['q'][1]:.3f}] | {per} | {'yes' if r['same'] else '**no**'} | {r['load']:.1f} |")
    if cross:
        L += ["", "**Crossover** (the test build alone): each light with the pass forced row-major (`row_permille` 0) and "
              "column-major (1001) on copies of the one layout, paired by CPU time as above; column / row > 1: the "
              "row-major pass is faster. The kernel takes the row-major pass from `row_min` = "
              f"{rl.row_min} of the sparse blocks held (this build's default, `WaveletRelighter.default_row_min`; "
              "the sweep over shares, scenes and builds: wavelet_rowmin.md). Outputs of the two passes differ in rounding only (each vertex's "
              "terms summed in another order): max |difference| / max |output|.\n",
              "| light | N | sparse blocks held | row-major | column-major | **column / row** [quartiles] | max diff | load |",
              "|---|---|---|---|---|---|---|---|"]
        for x in cross:
            L.append(f"| {x['light']} | {x['N']} | {x['held']:.3f} | {x['us'][0]:.1f} µs | {x['us'][1]:.1f} µs | "
                     f"**{x['ratio']:.3f}** [{x['q'][0]:.3f}, {x['q'][1]:.3f}] | {x['diff']:.1e} | {x['load']:.1f} |")
    text = "\n".join(L) + "\n"
    if args.write:
        atomic_write_text(args.write, text)
        print(f"[rowpass] wrote {args.write}", flush=True)
    else:
        print(text)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
