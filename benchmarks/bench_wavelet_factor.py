"""The wavelet kernel's per-vertex factor against a base revision's ``[V, 3]`` one (issue 39): ``kernels/wavelet.c``
of the working tree, called as ``WaveletRelighter`` calls it (``_kfactor``: on the blocker scene's grey albedo one
float per vertex, ``f [V + 4]``, ``C | F1``), and of ``--base`` (default ``main``: ``f [V, 3]``, 12 bytes per vertex),
both compiled with the wavelet library's flags and bound to one layout, timed paired by one thread's CPU time
(``measure_paired(clock=time.thread_time)``: what other processes ran is in neither side), at each ``--sizes`` of
occluder_over_plane (small / medium / large: V = 2251 / 10585 / 51335), the studio and sky lights
(transport-weighted terms, RGB) at N = 10, 30, 100, 300, 1000 and all, in the ``native`` build (on an AVX-512 CPU the
16-lane dense loop) and the ``avx2`` one (``PRT_TORCH_KERNEL_ISA=avx2``: the 8-lane code an AVX2-only CPU runs —
on this CPU a proxy for it, not a measurement of the AMD Zen 3 it was tuned on).

Per build and row: **base / test** (median of the per-repeat ratios, quartiles; > 1: the working tree faster), an A/A
control (the base against a second build of itself), each build against a streaming read of the bytes it touches plus
a fill of the output (``timing.read_bound_fn``) with the **new** byte count (``WaveletRelighter.bytes_read``: the
transfer's bytes and the factor the build reads — 4 (V + 4) bytes for the test, 12 V for the base) and with the **old**
one (``bytes_read(..., factor=False)``: no factor, the count of the reports before this one), the outputs bit for bit
against the base's. In the native build also **nt**: the working tree built with ``OUT_NT`` (the RGB output written by
streaming stores when it holds at least ``--nt-bytes``, default 512 KiB: the large size's 0.62 MB alone), against the
ordinary stores, alone and followed by a sum over the output (a reader right after the call). Writes
reports/benchmarks/wavelet_factor.md (the CPU, flags and load named).

    .venv/bin/python benchmarks/bench_wavelet_factor.py [--base REV] [--sizes small,medium,large]   (about 10 minutes)
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
from bench_wavelet_isa import bound_call, emit_report, kernel_build, kernel_source  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, read_bound_fn  # noqa: E402

TERMS = (10, 30, 100, 300, 1000)
WHO = "bench_wavelet_factor.py"


def builds(base_rev: str, nt_bytes: int) -> dict:
    """``{isa: {name: library}}`` for isa native and avx2: ``test`` (the working tree), ``base`` (``base_rev``), ``aa``
    (the base again: the A/A control) and, native only, ``nt`` (the working tree with ``OUT_NT`` = ``nt_bytes``)."""
    btext, _ = kernel_source(base_rev, f"{WHO}: --base")
    ttext, _ = kernel_source(None, WHO)
    out = {}
    for isa in ("native", "avx2"):
        libs = {"test": kernel_build(ttext, isa, WHO)[0], "base": kernel_build(btext, isa, WHO)[0],
                "aa": kernel_build(btext, isa, WHO, tag="A/A control")[0]}
        if isa == "native":
            libs["nt"] = kernel_build(f"#define OUT_NT {int(nt_bytes)}LL\n" + ttext, isa, WHO)[0]
        out[isa] = libs
    out["flags"] = kernel_build(ttext, "native", WHO)[1]
    return out


def paired(a, b, repeats: int) -> tuple[float, float, float]:
    """``b``'s time over ``a``'s, one thread's CPU time: (median of the per-repeat ratios, quartiles)."""
    p = measure_paired(a, b, repeats=repeats, warmup=1, clock=time.thread_time)
    return p.speedup, p.ratio.q1, p.ratio.q3


def size_rows(size: str, libs: dict, repeats: int) -> tuple[dict, list[dict]]:
    """One size's layout (``{V, Pd, dense_mb}``) and its rows (each light and N, both builds)."""
    rl = relight.WaveletRelighter(kernel_transfer(size), threads=1, layouts="both")  # the row-major copy: every build reads it
    info = {**layout_info(rl, size), "form": relight.WaveletRelighter._factor_form(rl.albedo[:, :3], rl.CT, 3), "fb": rl.factor_bytes(3)}
    rows = []
    for light, N, li, lv in kernel_lights(rl, TERMS):
        old = rl.bytes_read(li, factor=False)
        new = {"test": rl.bytes_read(li), "base": old + 12 * rl.V}
        bounds = {"old": read_bound_fn(old, rl.V * 12), "test": read_bound_fn(new["test"], rl.V * 12),
                  "base": read_bound_fn(new["base"], rl.V * 12)}
        row = {"size": size, "light": light, "N": N, "nd": int((rl.dslot[li] >= 0).sum()), "mb_old": old / 2**20,
               "mb_test": new["test"] / 2**20, "mb_base": new["base"] / 2**20}
        for isa in ("native", "avx2"):
            outs = {k: torch.empty(rl.V, 3) for k in libs[isa]}
            fn = {k: bound_call(rl, lib, li, lv, outs[k], 1, per_vertex=k in ("test", "nt")) for k, lib in libs[isa].items()}
            for f in fn.values():
                f()
            r = {"same": all(torch.equal(outs[k], outs["base"]) for k in outs)}
            p = measure_paired(fn["test"], fn["base"], repeats=repeats, warmup=1, clock=time.thread_time)
            r["test"] = (p.speedup, p.ratio.q1, p.ratio.q3)
            r["test_us"], r["base_us"] = p.test.median * 1e6, p.peer.median * 1e6
            r["aa"] = paired(fn["aa"], fn["base"], repeats)
            for k in ("test", "base"):
                r[f"{k}_read_new"] = paired(fn[k], bounds[k], repeats)[0]
                r[f"{k}_read_old"] = paired(fn[k], bounds["old"], repeats)[0]
            if "nt" in fn:
                o = outs["nt"]
                r["nt"] = paired(fn["nt"], fn["test"], repeats)
                r["nt_sum"] = paired(lambda: fn["nt"]().sum(), lambda: fn["test"]().sum(), repeats)
                r["nt_same"] = torch.equal(o, outs["test"])
            row[isa] = r
        row["load"] = load()
        rows.append(row)
        n, a = row["native"], row["avx2"]
        print(f"[factor] {size} {light} N={N} nd={row['nd']}: native base/test {n['test'][0]:.3f} (A/A {n['aa'][0]:.3f}) "
              f"{n['test_us']:.1f} us, of read new {n['test_read_new']:.2f} old {n['test_read_old']:.2f} (base "
              f"{n['base_read_new']:.2f} / {n['base_read_old']:.2f}), nt {n['nt'][0]:.3f} +sum {n['nt_sum'][0]:.3f}; "
              f"avx2 base/test {a['test'][0]:.3f} (A/A {a['aa'][0]:.3f}); same {n['same'] and a['same']}, "
              f"load {row['load']:.1f}", flush=True)
    return info, rows


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", default="main", help="the git revision to pair against (default main)")
    ap.add_argument("--sizes", default=",".join(KERNEL_SIZES), help="comma-separated: " + ", ".join(KERNEL_SIZES))
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--nt-bytes", type=int, default=1 << 19, help="OUT_NT: streaming stores from this output size")
    ap.add_argument("--write", default=str(OUT / "wavelet_factor.md"), help="the report ('': print only)")
    args = ap.parse_args()
    sizes = [size_choice(s.strip(), WHO) for s in args.sizes.split(",")]
    if args.repeats < 3:
        raise SystemExit(f"{WHO}: --repeats {args.repeats}; accepted: an integer >= 3")
    if args.nt_bytes < 0:
        raise SystemExit(f"{WHO}: --nt-bytes {args.nt_bytes}; accepted: an integer >= 0")
    torch.set_num_threads(1)
    libs = builds(args.base, args.nt_bytes)
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
    L = ["# Wavelet kernel: one factor per vertex, and the output's stores (issue 39)\n",
         f"{cpu_label()}; load average {before:.1f} → {after:.1f} (a machine shared with other jobs: one thread's CPU "
         f"time, which their load does not enter). Builds of `kernels/wavelet.c` with the wavelet library's flags "
         f"(`{flags}`; avx2: `PRT_TORCH_KERNEL_ISA=avx2`, `-mno-avx512f`, on this CPU a proxy for an AVX2-only one): "
         f"**test** the working tree's, called with the relighter's factor (`WaveletRelighter._kfactor`: the blocker "
         f"scene's albedo is grey, form `{infos[0]['form']}`: one float per vertex, `f [V + 4]`), **base** revision "
         f"`{args.base}`'s with `f [V, 3]` (12 bytes per vertex), **A/A** the base built twice. All bound to one layout "
         "per size (occluder_over_plane, R = 32, K = 256, "
         f"{BITS}-bit; " + "; ".join(f"{i['size']}: V = {i['V']}, {i['Pd']} dense columns, dense layout "
                                      f"{i['dense_mb']:.1f} MB, factor {i['fb'] / 2**20:.2f} MB (base {12 * i['V'] / 2**20:.2f})"
                                      for i in infos)
         + "), transport-weighted terms, RGB light, one thread, paired by the calling thread's CPU time "
         f"(`measure_paired(clock=time.thread_time)`, {args.repeats} repeats): **base / test** and A/A are medians of "
         "the per-repeat ratios [quartiles] (> 1: test faster). *of read*: the build against a streaming read "
         "(`timing.read_bound_fn`) of the bytes it touches plus a fill of the output, paired the same way: **new** — the "
         "byte count from this change on (`WaveletRelighter.bytes_read` counts the factor the kernel reads: the test's "
         "4 (V + 4) bytes, the base's 12 V) —, **old** — the count before (`bytes_read(..., factor=False)`, as in "
         "reports/benchmarks/wavelet.md section 7 and wavelet_prefetch.md before it: the transfer's bytes alone); a "
         "row of those reports compares with the *old* columns only. **nt** (native): the working tree built with "
         f"`OUT_NT` = {args.nt_bytes} bytes (the RGB output by streaming stores from that size: at large only) against "
         "the test build, **test / nt** alone and with a sum over the output right after the call (> 1: streaming "
         "faster). *bits*: every build's output equal to the base's. Reproduce: "
         f"`.venv/bin/python benchmarks/bench_wavelet_factor.py --base {args.base} --sizes {','.join(sizes)}`.\n",
         "| size | light | N | dense terms | MB read old / test new / base new | native test | **native base / test** | "
         "native A/A | native of read new: test / base | of read old: test / base | test / nt | test / nt, + sum of out | "
         "avx2 test | **avx2 base / test** | avx2 A/A | avx2 of read new: test / base | of read old: test / base | bits | load |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        n, a = r["native"], r["avx2"]
        L.append(f"| {r['size']} | {r['light']} | {r['N']} | {r['nd']} | {r['mb_old']:.2f} / {r['mb_test']:.2f} / "
                 f"{r['mb_base']:.2f} | {n['test_us']:.1f} µs | **{q(n['test'])}** | {q(n['aa'])} | "
                 f"{n['test_read_new']:.2f} / {n['base_read_new']:.2f} | {n['test_read_old']:.2f} / {n['base_read_old']:.2f} | "
                 f"{q(n['nt'])} | {q(n['nt_sum'])} | {a['test_us']:.1f} µs | **{q(a['test'])}** | {q(a['aa'])} | "
                 f"{a['test_read_new']:.2f} / {a['base_read_new']:.2f} | {a['test_read_old']:.2f} / {a['base_read_old']:.2f} | "
                 f"{'same' if n['same'] and a['same'] and n['nt_same'] else '**differ**'} | {r['load']:.1f} |")
    text = "\n".join(L) + "\n"
    emit_report(args.write, text, "factor")
    if not all(r["native"]["same"] and r["avx2"]["same"] and r["native"]["nt_same"] for r in rows):
        raise SystemExit(f"{WHO}: a build's outputs differ from the base build's (see 'bits')")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
