"""The wavelet kernel's dense loop with the prefetch across units against a base revision's (issue 39):
``kernels/wavelet.c`` of the working tree (the 16-lane loop's ``PF_FAR``: PFX = 24 (term, unit) steps ahead, into the
next block or pair of blocks, when the dense layout holds at least PFX_MIN: 2 MB when this was written, 0 — every
layout — since bench_wavelet_regimes.py) and of ``--base`` (default ``main``, which prefetched PF = 6 terms ahead
within a block only), both compiled with the wavelet library's flags and
bound to one layout, timed paired by one thread's CPU time (``measure_paired(clock=time.thread_time)``: what other
processes ran is in neither side), at each ``--sizes`` of occluder_over_plane (small / medium / large: V = 2251 /
10585 / 51335, dense layouts of 1.1 / 5.2 / 25 MB against the Xeon's 2 MB L2), the studio and sky lights
(transport-weighted terms, RGB) at N = 10, 30, 100, 300, 1000 and all.

Per build (``native``: on an AVX-512 CPU the 16-lane loop; ``avx2``: ``PRT_TORCH_KERNEL_ISA=avx2``, the 8-lane loop,
whose machine code the change this was written for left as it was) and row: **base / test** (median of the per-repeat ratios,
quartiles; > 1: the working tree faster), an A/A control (the base against a second build of itself), the test
build's fraction of a streaming read of the bytes it touches plus a fill of the output (``timing.read_bound_fn`` of
``WaveletRelighter.bytes_read``, paired the same way), the outputs bit for bit against the base's; for the avx2 build
also ``far``: the working tree built with ``PF_X8`` (the same prefetch in the 8-lane loop: off by default when
this was written, on since bench_wavelet_regimes.py --isa avx2, so ``far`` and ``test`` are now the same code) against the
base. Writes reports/benchmarks/wavelet_prefetch.md (the CPU, flags and load named).

    .venv/bin/python benchmarks/bench_wavelet_prefetch.py [--base REV] [--sizes small,medium,large]   (about 7 minutes)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, KERNEL_SIZES, OUT, kernel_lights, kernel_transfer, layout_info, load, size_choice  # noqa: E402
from bench_wavelet_isa import rl_bytes, bound_call, emit_report, kernel_build, kernel_source  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, read_bound_fn  # noqa: E402

TERMS = (10, 30, 100, 300, 1000)
WHO = "bench_wavelet_prefetch.py"


def builds(base_rev: str) -> dict:
    """``{isa: {name: library}}`` for isa native and avx2: ``test`` (the working tree), ``base`` (``base_rev``),
    ``aa`` (the base again, a second library: the A/A control) and, for avx2, ``far`` (the working tree with
    ``PF_X8``); ``flags`` the native build's flags."""
    btext, _ = kernel_source(base_rev, f"{WHO}: --base")
    ttext, _ = kernel_source(None, WHO)
    out = {}
    for isa in ("native", "avx2"):
        libs = {"test": kernel_build(ttext, isa, WHO)[0], "base": kernel_build(btext, isa, WHO)[0],
                "aa": kernel_build(btext, isa, WHO, tag="A/A control")[0]}
        if isa == "avx2":
            libs["far"] = kernel_build("#define PF_X8 1\n" + ttext, isa, WHO)[0]
        out[isa] = libs
    out["flags"] = kernel_build(ttext, "native", WHO)[1]
    return out


def size_rows(size: str, libs: dict, repeats: int) -> tuple[dict, list[dict]]:
    """One size's layout (``{V, Pd, dense_mb}``) and its rows (each light and N, both builds)."""
    rl = relight.WaveletRelighter(kernel_transfer(size), threads=1, layouts="both")  # the row-major copy: every build reads it
    info = layout_info(rl, size)
    rows = []
    for light, N, li, lv in kernel_lights(rl, TERMS):
        bound = read_bound_fn(rl_bytes(rl, li), rl.V * 12)
        row = {"size": size, "light": light, "N": N, "nd": int((rl.dslot[li] >= 0).sum()),
               "mb": rl_bytes(rl, li) / 2**20}
        for isa in ("native", "avx2"):
            outs = {k: torch.empty(rl.V, 3) for k in libs[isa]}
            fn = {k: bound_call(rl, lib, li, lv, outs[k], 1) for k, lib in libs[isa].items()}
            for f in fn.values():
                f()
            r = {"same": all(torch.equal(outs[k], outs["base"]) for k in outs)}
            for k in [k for k in fn if k != "base"]:
                p = measure_paired(fn[k], fn["base"], repeats=repeats, warmup=1, clock=time.thread_time)
                r[k] = (p.speedup, p.ratio.q1, p.ratio.q3)
                if k == "test":
                    r["test_us"], r["base_us"] = p.test.median * 1e6, p.peer.median * 1e6
            pb = measure_paired(fn["test"], bound, repeats=repeats, warmup=1, clock=time.thread_time)
            r["of_read"] = pb.speedup
            row[isa] = r
        row["load"] = load()
        rows.append(row)
        n, a = row["native"], row["avx2"]
        print(f"[prefetch] {size} {light} N={N} nd={row['nd']}: native base/test {n['test'][0]:.3f} (A/A "
              f"{n['aa'][0]:.3f}) {n['test_us']:.1f} us, of read {n['of_read']:.2f}; avx2 base/test "
              f"{a['test'][0]:.3f} (A/A {a['aa'][0]:.3f}), far {a['far'][0]:.3f}, of read {a['of_read']:.2f}; same "
              f"{n['same'] and a['same']}, load {row['load']:.1f}", flush=True)
    return info, rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", default="main", help="the git revision to pair against (default main)")
    ap.add_argument("--sizes", default=",".join(KERNEL_SIZES), help="comma-separated: " + ", ".join(KERNEL_SIZES))
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--write", default=str(OUT / "wavelet_prefetch.md"), help="the report ('': print only)")
    args = ap.parse_args()
    sizes = [size_choice(s.strip(), WHO) for s in args.sizes.split(",")]
    if args.repeats < 3:
        raise SystemExit(f"{WHO}: --repeats {args.repeats}; accepted: an integer >= 3")
    torch.set_num_threads(1)
    libs = builds(args.base)
    flags = libs.pop("flags")
    before = load()
    infos, rows = [], []
    for s in sizes:
        info, r = size_rows(s, libs, args.repeats)
        infos.append(info)
        rows += r
    after = load()

    def q(t):
        return f"{t[0]:.2f} [{t[1]:.2f}, {t[2]:.2f}]"
    L = ["# Wavelet kernel: the dense loop's prefetch across blocks (issue 39)\n",
         f"{cpu_label()}; load average {before:.1f} → {after:.1f} (a machine shared with other jobs: one thread's CPU "
         f"time, which their load does not enter). Builds of `kernels/wavelet.c` with the wavelet library's flags "
         f"(`{flags}`; avx2: `PRT_TORCH_KERNEL_ISA=avx2`, `-mno-avx512f`): **test** the working tree's, **base** "
         f"revision `{args.base}`'s, **A/A** the base built twice; **far** (avx2 only) the working tree with `PF_X8 1` "
         "(the prefetch across blocks in the 8-lane loop; on by default since bench_wavelet_regimes.py --isa avx2). All bound to one layout per size "
         "(occluder_over_plane, R = 32, K = 256, "
         f"{BITS}-bit; " + "; ".join(f"{i['size']}: V = {i['V']}, {i['Pd']} dense columns, dense layout "
                                      f"{i['dense_mb']:.1f} MB" for i in infos)
         + "), transport-weighted terms, RGB light, one thread, paired by the calling thread's CPU time "
         f"(`measure_paired(clock=time.thread_time)`, {args.repeats} repeats): **base / test** etc. are medians of the "
         "per-repeat ratios [quartiles] (> 1: the first named build slower, i.e. test faster); *of read*: the test "
         "build against a streaming read of the bytes it touches (`WaveletRelighter.bytes_read`) plus a fill of the "
         "output (`timing.read_bound_fn`), paired the same way; *bits*: every build's output equal to the base's. "
         f"Reproduce: `.venv/bin/python benchmarks/bench_wavelet_prefetch.py --base {args.base} --sizes "
         f"{','.join(sizes)}`.\n",
         "| size | light | N | dense terms | MB read | native test | **native base / test** | native A/A | native test "
         "of read | avx2 test | avx2 base / test | avx2 A/A | **avx2 base / far** | avx2 test of read | bits | load |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n, a = r["native"], r["avx2"]
        L.append(f"| {r['size']} | {r['light']} | {r['N']} | {r['nd']} | {r['mb']:.2f} | {n['test_us']:.1f} µs | "
                 f"**{q(n['test'])}** | {q(n['aa'])} | {n['of_read']:.2f} | {a['test_us']:.1f} µs | {q(a['test'])} | "
                 f"{q(a['aa'])} | **{q(a['far'])}** | {a['of_read']:.2f} | "
                 f"{'same' if n['same'] and a['same'] else '**differ**'} | {r['load']:.1f} |")
    text = "\n".join(L) + "\n"
    emit_report(args.write, text, "prefetch")
    if not all(r["native"]["same"] and r["avx2"]["same"] for r in rows):
        raise SystemExit(f"{WHO}: a build's outputs differ from the base build's (see 'bits')")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
