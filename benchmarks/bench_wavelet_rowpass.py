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
pass from ``row_min`` = 0.5 of them): where the two passes cross.

The kernel section's transfer (occluder_over_plane small, R = 32, K = 256, 16 bits). Writes
reports/benchmarks/wavelet_rowpass.md (the CPU, both builds, the flags and the load named).

    .venv/bin/python benchmarks/bench_wavelet_rowpass.py --crossover          (about 2 minutes)
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


def bound(fn, layout: torch.Tensor, f: torch.Tensor, li: torch.Tensor, lv: torch.Tensor, out: torch.Tensor):
    """``run()``: ``fn`` relighting ``li``/``lv`` into ``out`` on ``layout`` (one thread), as ``prepared`` does."""
    args = torch.tensor([layout.data_ptr(), li.numel(), li.data_ptr(), lv.data_ptr(), lv.shape[0], f.data_ptr(),
                         out.data_ptr(), 1], dtype=torch.int64)
    call = functools.partial(fn, args.data_ptr())
    held = (layout, f, li, lv, out, args)

    def run():
        st = call()
        if st:
            raise RuntimeError(f"the wavelet kernel returned {st}")
        return held[4]
    return run


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
    args = ap.parse_args()
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
              f"{rl.row_min} of the sparse blocks held. Outputs of the two passes differ in rounding only (each vertex's "
              "terms summed in another order): max |difference| / max |output|.\n",
              "| light | N | sparse blocks held | row-major | column-major | **column / row** [quartiles] | max diff | load |",
              "|---|---|---|---|---|---|---|---|"]
        for x in cross:
            L.append(f"| {x['light']} | {x['N']} | {x['held']:.3f} | {x['us'][0]:.1f} µs | {x['us'][1]:.1f} µs | "
                     f"**{x['ratio']:.3f}** [{x['q'][0]:.3f}, {x['q'][1]:.3f}] | {x['diff']:.1e} | {x['load']:.1f} |")
    text = "\n".join(L) + "\n"
    if args.write:
        Path(args.write).write_text(text)
        print(f"[rowpass] wrote {args.write}", flush=True)
    else:
        print(text)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
