"""The wavelet kernel's sparse scratch and output pass (issue 39): ``kernels/wavelet.c`` of the working tree — in the
AVX-512 build (W16) a scratch zero between calls with a touched map (``zacc`` / ``tmark``: the column-major pass marks
each 32-vertex block it adds to, a dense block adds its accumulators back and stores zeros over them only when
marked; no memset of the whole scratch per tile, no add-back of untouched blocks) — against ``--base`` (default
``main``: a memset of each tile's scratch, every block's four accumulators added back), both compiled with the
wavelet library's flags for this CPU (``native``) and bound to one layout, timed paired by one thread's CPU time
(``measure_paired(clock=time.thread_time)``: what other processes ran is in neither side), at each ``--sizes`` of
occluder_over_plane (small / medium / large: V = 2251 / 10585 / 51335), the studio and sky lights (transport-weighted
terms, RGB, the relighter's per-vertex factor) at N = ``--terms`` and all, in two regimes:

- **warm**: back-to-back calls (``timing.measure_paired``);
- **evicted**: each call preceded (untimed) by a streaming read of ``--evict-mb`` MB (default 3) of other data
  (``timing.measure_paired_cold``'s junk read): the call's lines from L3, as in a render loop doing other work between
  relights; a sample is ``--calls`` (default 4) such calls;
- **2 threads** (``--two-threads``): back-to-back calls at two threads (the tiles split between them), paired by wall
  clock (``time.perf_counter``: the other thread's work is not in one thread's CPU time; the machine's load is), no
  fraction of the read bound (a one-thread figure).

Builds: **test** (the working tree), **base**, **A/A** (the base built twice: the pairing's noise) and the measurement
knobs in ``--variants`` (the working tree with ``-D`` lines prepended): ``touch8`` (``TOUCH8``: a mark per 8-vertex
block instead of per 32), ``outpf`` (``OUT_PFW``: each dense block prefetches its output lines for writing before its
dense terms), ``rho0`` / ``rho2`` (``VNNI_RHO`` 0 / 2: no relative budget — with ``b0``, ``rho0+b0``, the VNNI
loop's fixed 16-term flush groups — / a budget of 2x the 16-term groups' bound), ``cm`` (``VNNI_L2`` 0: grp17's
flush groups, weighed by the columns' maxima), ``b0`` / ``b5`` / ``b75`` / ``b9`` (``VNNI_BETA`` 0 / 0.5 / 0.75 / 0.9:
the flush groups' absolute budget, a fraction of the transfer's own 16-bit L2 bound; 0: none), ``l2`` (``VNNI_L2`` 1:
vnb18's L2 flush groups), ``noguard`` (``VNNI_GUARD`` 0: no per-call guard, the VNNI loop whatever its bound), and the others in
``VARIANTS``. Per row: base / variant (median of the per-repeat ratios,
quartiles; > 1: the variant faster), and the
test and base builds against the streaming read of the bytes the call touches plus a fill of the output
(``timing.read_bound_fn`` of ``WaveletRelighter.bytes_read``; section 7's criterion) in the same regime. Every
build's output is compared bit for bit with the base's.

The **output pass** alone: a call with no light term (N = 0: no dense term, no scratch; each dense block's zero sums
times the factor, interleaved and written once) against a plain fill of the output's bytes (``read_bound_fn(0,
12 V)``: the bound's own output part), warm, for test and base.

``--vnni``: every build compiled with ``#define DENSE_VNNI 1`` prepended (the dense loop on integer dot products where
the CPU has AVX-512 VNNI; kernels/wavelet.c), so the pairing measures the rest of the call beside that loop.
``--base-dense-min X``: the base and A/A builds bound to a relighter of their own on the same transfer, built with
``dense_min`` X (``1/3``, the bytes rule main's relighter used for 16-bit values, is written ``third``), while the test
build and the variants take the working tree's default layout (``WaveletRelighter.default_dense_min``): the pairing
then measures a layout change with the kernel change; each side's fraction of the streaming read is of its own
layout's bytes, and every output is compared with the float64 sums of the stored values (``relight.wavelet_dense``)
as well as bit for bit with the build of its own layout (test for the variants). ``--base-tile X|half`` likewise: the
base and A/A builds on a relighter built with tile X (``half``: the default before the tile followed the relighter's
threads, half the vertices up to 4096), the test build on the working tree's default at one thread
(``WaveletRelighter._tile``): with ``--base`` at the same kernel source, the pairing measures the tile alone.

The AVX2 build (``PRT_TORCH_KERNEL_ISA=avx2``, the code tuned on an AMD Zen 3) is not paired here: its machine code is
the base's byte for byte (``--check-avx2`` compares the two builds' .text with objcopy, and stops if they differ).
Writes reports/benchmarks/wavelet_scratch.md (the CPU, flags and load named) and the rows as .json.

    .venv/bin/python benchmarks/bench_wavelet_scratch.py [--base REV] [--sizes small,medium,large] [--variants touch8,outpf]
        [--vnni] [--base-dense-min third] [--base-tile half]
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, KERNEL_SIZES, OUT, kernel_lights, kernel_transfer, layout_info, load, size_choice, steady_pair  # noqa: E402
from bench_wavelet_isa import bound_call, emit_report, kernel_build, kernel_source  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import KERNEL_ISAS, LIBRARIES  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, measure_paired_cold, read_bound_fn  # noqa: E402

TERMS = (10, 30, 100, 300, 1000)
WHO = "bench_wavelet_scratch.py"
REGIMES = ("warm", "evicted")
#: the two-thread regime (--two-threads): warm, wall clock
TWO = "2 threads"
#: variant name -> the -D lines prepended to the working tree's source
VARIANTS = {"touch8": "#define TOUCH8 1\n", "outpf": "#define OUT_PFW 1\n", "markall": "#define TOUCH_X (1LL << 40)\n",
            "marknone": "#define TOUCH_X (-1LL)\n", "outz0": "#define OUT_Z 0\n", "outz2": "#define OUT_Z 2\n",
            "pfx12": "#define PFX 12\n", "pfx48": "#define PFX 48\n", "pfx96": "#define PFX 96\n",
            "g32": "#define VNNI_G 32\n", "g4096": "#define VNNI_G 4096\n",
            "sprf0": "#define SP_PFR 0\n", "sprf4l": "#define SP_PFL 4\n",
            "rho0": "#define VNNI_RHO 0\n", "rho2": "#define VNNI_RHO 2.0\n",
            "cm": "#define VNNI_L2 0\n", "b0": "#define VNNI_BETA 0\n", "b5": "#define VNNI_BETA 0.5\n", "b75": "#define VNNI_BETA 0.75\n",
            "b9": "#define VNNI_BETA 0.9\n", "l2": "#define VNNI_L2 1\n", "noguard": "#define VNNI_GUARD 0\n"}
#: the -D line ``--vnni`` prepends to every build
VNNI = "#define DENSE_VNNI 1\n"


def builds(base_rev: str, names: list[str], vnni: bool = False) -> tuple[dict, str]:
    """``({name: library}, flags)``: test, base, aa and ``names`` (keys of VARIANTS), native builds (``vnni``: each
    with :data:`VNNI` prepended)."""
    pre = VNNI if vnni else ""
    btext, _ = kernel_source(base_rev, f"{WHO}: --base")
    ttext, _ = kernel_source(None, WHO)
    btext, ttext = pre + btext, pre + ttext
    libs = {"test": kernel_build(ttext, "native", WHO)[0], "base": kernel_build(btext, "native", WHO)[0],
            "aa": kernel_build(btext, "native", WHO, tag="A/A control")[0]}
    for n in names:  # a name: variants joined by '+'
        libs[n] = kernel_build("".join(VARIANTS[v] for v in n.split("+")) + ttext, "native", WHO)[0]
    return libs, kernel_build(ttext, "native", WHO)[1]


def avx2_text_same(base_rev: str) -> bool:
    """Whether the AVX2 builds of the working tree's and ``base_rev``'s kernel have the same .text, byte for byte
    (gcc with the wavelet library's flags and ``-mno-avx512f``, objcopy)."""
    flags = [f for f in LIBRARIES["wavelet"][1]] + list(KERNEL_ISAS["avx2"])
    texts = []
    with tempfile.TemporaryDirectory() as d:
        for i, (src, _) in enumerate((kernel_source(None, WHO), kernel_source(base_rev, f"{WHO}: --base"))):
            c, so, t = (Path(d) / f"k{i}.{e}" for e in ("c", "so", "text"))
            c.write_text(src)
            subprocess.run(["gcc", *flags, str(c), "-o", str(so)], check=True)
            subprocess.run(["objcopy", "-O", "binary", "--only-section=.text", str(so), str(t)], check=True)
            texts.append(t.read_bytes())
    return texts[0] == texts[1]


def pair(regime: str, a, b, repeats: int, evict_bytes: int, calls: int):
    """``a`` against ``b`` in ``regime``: (median of b / a per repeat, q1, q3, a's median µs, b's median µs)."""
    if regime == "warm":
        p = measure_paired(a, b, repeats=repeats, warmup=1, clock=time.thread_time)
    elif regime == TWO:
        p = measure_paired(a, b, repeats=repeats, warmup=1, clock=time.perf_counter)
    else:
        p = measure_paired_cold(a, b, repeats=2 * repeats + 1, warmup=1, evict_bytes=evict_bytes, clock=time.thread_time,
                                calls=calls)
    return [p.speedup, p.ratio.q1, p.ratio.q3, p.test.median * 1e6, p.peer.median * 1e6]


def size_rows(size: str, libs: dict, terms, repeats: int, evict_bytes: int, calls: int, s7=(),
              base_dmin: float | None = None, regimes=REGIMES, base_tile: str | None = None,
              base_first: bool = False) -> tuple[dict, list[dict]]:
    tr = kernel_transfer(size)
    # the test build's layout: the relighter's default for that build (its prt_wavelet_isa bits: w16, vnni), which may
    # not be this process's own build (--vnni)
    bits = int(libs["test"].prt_wavelet_isa())
    rec = {"w16": bool(bits & 32), "vnni": bool(bits & 64)}
    dmin = relight.WaveletRelighter.default_dense_min(BITS // 8, rec)
    # the base and A/A builds' layout: the same relighter, or (--base-dense-min, --base-tile) one of its own, built
    # after the test's or (base_first: the placement's control, --base-first) before it
    btile = None if base_tile is None else (relight.WaveletRelighter._tile(tr.mesh.num_vertices, None, 2)
                                            if base_tile == "half" else int(base_tile))
    own = base_dmin is not None or btile is not None

    def base_rl():
        return relight.WaveletRelighter(tr, threads=1, layouts="both", dense_min=dmin if base_dmin is None else base_dmin,
                                        tile=btile)
    rlb = base_rl() if own and base_first else None
    rl = relight.WaveletRelighter(tr, threads=1, layouts="both", dense_min=dmin)
    rlb = rl if not own else rlb if rlb is not None else base_rl()
    lay = {k: rlb if k in ("base", "aa") else rl for k in libs}
    info = layout_info(rl, size)
    info["Pd_base"] = rlb.Pd
    info["tiles"], info["tiles_base"] = [rl.NT, rl.TV], [rlb.NT, rlb.TV]
    ref_index, ref_vals = rl.reference_rows(0, rl.V)
    # the output pass alone: no light term, against a fill of the output
    e_li, e_lv = torch.zeros(0, dtype=torch.int64), torch.zeros(3, 0)
    fill = read_bound_fn(0, rl.V * 12)
    info["output"] = {}
    for k in [k for k in libs if k != "aa"]:
        fn = bound_call(lay[k], libs[k], e_li, e_lv, torch.empty(rl.V, 3), 1, per_vertex=True)
        fn()
        info["output"][k] = pair("warm", fn, fill, repeats, evict_bytes, calls)
    print(f"[scratch] {size} output pass (N = 0) / fill: test {1 / info['output']['test'][0]:.2f}x the fill's time "
          f"({info['output']['test'][3]:.1f} vs {info['output']['test'][4]:.1f} us), base "
          f"{1 / info['output']['base'][0]:.2f}x" + "".join(f", {k} {1 / v[0]:.2f}x" for k, v in info["output"].items()
                                                             if k not in ("test", "base")), flush=True)
    rows = []
    for light, N, li, lv in kernel_lights(rl, terms):
        nbytes, nbytes_b = rl.bytes_read(li), rlb.bytes_read(li)
        bound = read_bound_fn(nbytes, rl.V * 12)
        bound_b = bound if rlb is rl else read_bound_fn(nbytes_b, rl.V * 12)
        outs = {k: torch.empty(rl.V, 3) for k in libs}
        fn = {k: bound_call(lay[k], lib, li, lv, outs[k], 1, per_vertex=True) for k, lib in libs.items()}
        for f in fn.values():
            f()
        outs2 = {k: torch.empty(rl.V, 3) for k in libs}
        fn2 = {k: bound_call(lay[k], lib, li, lv, outs2[k], 2, per_vertex=True) for k, lib in libs.items()}
        for f in fn2.values():
            f()
        ref = relight.wavelet_dense(ref_vals.double(), ref_index, li, lv.double(), rl.P) * rl.albedo[:, :3].double()
        scale = float(ref.abs().max()) or 1.0
        err = {k: float((o.double() - ref).abs().max()) / scale for k, o in outs.items()}
        d = rl.dslot[li] >= 0
        s = li[~d]
        s = s[rl.nnz[s] > 0]
        db = rlb.dslot[li] >= 0
        row = {"size": size, "light": light, "N": N, "nd": int(d.sum()), "sb": int(rl.bcount[:, s].sum()),
               "nd_base": int(db.sum()),
               "rows": bool(rl._takes_rows(int(rl.bcount[:, s].sum()), rl.NB, rl._row_permille(rl.row_min, True))),
               "mb": nbytes / 2**20, "mb_base": nbytes_b / 2**20, "err": err,
               # bit for bit with the build of the same layout: base for A/A, test for the variants (one layout: base)
               "same": {k: bool(torch.equal(outs[k], outs["base" if lay[k] is rlb else "test"])
                                and (TWO not in regimes or torch.equal(outs2[k], outs[k]))) for k in outs},
               "load0": load()}
        for regime in regimes:
            r = {}
            f_ = fn2 if regime == TWO else fn
            for k in [k for k in fn if k != "base"]:
                r[k] = pair(regime, f_[k], f_["base"], repeats, evict_bytes, calls)
            if regime == TWO:
                row[regime] = r
                continue
            for k in ("test", "base"):
                r["read_" + k] = pair(regime, fn[k], bound if k == "test" else bound_b, repeats, evict_bytes, calls)
            row[regime] = r
        if N in s7:  # section 7's figure: bench_wavelet.kernel_rows' of_read_bound_cpu_1 (steady_pair, median ratio)
            row["s7"] = {k: steady_pair(fn[k], bound if k == "test" else bound_b)[0].ratio.median for k in ("test", "base")}
        row["load1"] = load()
        rows.append(row)
        msg = "; ".join(f"{g} base {row[g]['test'][4]:.1f} us, "
                        + (f"of read test {row[g]['read_test'][0]:.2f} base {row[g]['read_base'][0]:.2f}, " if g != TWO else "")
                        + ", ".join(f"{k} {row[g][k][0]:.3f}" for k in fn if k != "base")
                        for g in regimes)
        s7m = f"; section 7 of read test {row['s7']['test']:.2f} base {row['s7']['base']:.2f}" if "s7" in row else ""
        print(f"[scratch] {size} {light} N={N} nd={row['nd']} sparse blocks {row['sb']}{' (row-major)' if row['rows'] else ''}: "
              f"{msg}{s7m}; same {all(row['same'].values())}, load {row['load1']:.1f}", flush=True)
    return info, rows


def report(infos: list[dict], rows: list[dict], flags: str, args, before: float, after: float, names: list[str],
           avx2_same: bool | None) -> str:
    def q(t):
        return f"{t[0]:.2f} [{t[1]:.2f}, {t[2]:.2f}]"
    cols = ["test", "aa", *names]
    own = args.base_dense_min is not None or args.base_tile is not None  # the base on a layout of its own
    lay = ("" if args.base_dense_min is None else
           f" The base and A/A builds on a layout of their own, `dense_min` {args.base_dense_min:.4g} (dense columns: "
           + "; ".join(f"{i['size']} {i['Pd_base']}" for i in infos) + "); test and variants on the working tree's default "
           "(`WaveletRelighter.default_dense_min`); each side's *of read* of its own layout's bytes; *error*: max |output − "
           "float64 sums of the stored values| / max |reference| (`relight.wavelet_dense`), test / base.")
    if args.base_tile is not None:
        lay += (f" The base and A/A builds on a layout of their own, tile `{args.base_tile}` (tiles × vertices: "
                + "; ".join(f"{i['size']} {i['tiles_base'][0]} × {i['tiles_base'][1]}" for i in infos)
                + "); test and variants on the working tree's default (`WaveletRelighter._tile` at one thread: "
                + "; ".join(f"{i['size']} {i['tiles'][0]} × {i['tiles'][1]}" for i in infos)
                + "); each side's *of read* of its own layout's bytes.")
    vn = " Every build with `#define DENSE_VNNI 1` prepended (`--vnni`: the dense loop on integer dot products)." if args.vnni else ""
    L = [f"# Wavelet kernel: {args.title} (issue 39)\n",
         f"{cpu_label()}; load average {before:.1f} → {after:.1f} (a machine shared with other jobs: one thread's CPU "
         f"time, which their load does not enter). Native builds of `kernels/wavelet.c` with the wavelet library's flags "
         f"(`{flags}`: on this CPU the AVX-512 build, W16): **test** the working tree's ({args.test_about}), "
         f"**base** revision `{args.base}`'s ({args.base_about}), **A/A** the base built twice" + "".join(
             f", **{n}** the working tree with `{'; '.join(VARIANTS[v].strip() for v in n.split('+'))}`" for n in names)
         + ". All bound to " + ("one layout" if args.base_dense_min is None else "the test's layout (base and A/A: below)")
         + " per size (occluder_over_plane, R = 32, K = 256, "
         f"{BITS}-bit; " + "; ".join(f"{i['size']}: V = {i['V']}, {i['Pd']} dense columns, dense layout "
                                      f"{i['dense_mb']:.1f} MB" for i in infos)
         + "), transport-weighted terms, RGB light, the relighter's per-vertex factor, one thread, paired by the calling "
         f"thread's CPU time ({args.repeats} repeats): **warm** back-to-back calls, **evicted** each call after a "
         f"{args.evict_mb:g} MB streaming read of other data ({args.calls} calls a sample). Columns *base / x*: medians of the "
         "per-repeat ratios [quartiles] (> 1: x faster than the base; each variant is paired with the base, so variant "
         "against test is the ratio of their columns). *of read*: the build against a streaming read "
         "of the bytes it touches plus a fill of the output (`timing.read_bound_fn` of `WaveletRelighter.bytes_read`, "
         "section 7's criterion), paired in the same regime (> 0.5: the issue's goal). *sparse blocks*: the light's "
         "sparse 8-vertex blocks (*rows*: the row-major pass, no scratch). *bits*: every build's output equal to the "
         "base's. The AVX2 build (`PRT_TORCH_KERNEL_ISA=avx2`) is not paired: "
         + ("its .text is the base's byte for byte (gcc + objcopy, `--check-avx2`)." if avx2_same else
            "not checked in this run (`--check-avx2`)." if avx2_same is None else "**its .text differs from the base's**.")
         + f" Reproduce: `.venv/bin/python benchmarks/bench_wavelet_scratch.py --base {args.base} --sizes "
         f"{args.sizes} --terms {args.terms} --s7-terms {args.s7_terms} --repeats {args.repeats} --variants '{','.join(names)}'"
         f"{' --check-avx2' if args.check_avx2 else ''}{' --vnni' if args.vnni else ''}{' --two-threads' if args.two_threads else ''}"
         f"{'' if args.base_dense_min is None else ' --base-dense-min ' + args.base_dense_min_text}"
         f"{'' if args.base_tile is None else ' --base-tile ' + args.base_tile}{' --base-first' if args.base_first else ''}`."
         f"{vn}{lay}{' The base relighter built before the test one (`--base-first`).' if args.base_first else ''}\n",
         "## The output pass alone\n",
         "A call with no light term (N = 0: each dense block's zero sums times the factor, interleaved and written once; "
         "the call's fixed cost, ~0.5 µs, included) against a fill of the output's 12 V bytes (`read_bound_fn(0, 12 V)`), "
         "warm.\n",
         "| size | V | test µs | fill µs | test / fill | base / fill |" + "".join(f" {n} / fill |" for n in names),
         "|---|---|---|---|---|---|" + "---|" * len(names)]
    for i in infos:
        t, b = i["output"]["test"], i["output"]["base"]
        L.append(f"| {i['size']} | {i['V']} | {t[3]:.1f} | {t[4]:.1f} | {1 / t[0]:.2f} | {1 / b[0]:.2f} |"
                 + "".join(f" {1 / i['output'][n][0]:.2f} |" for n in names))
    s7rows = [r for r in rows if "s7" in r]
    if s7rows:
        L += ["\n## Section 7's fraction of the streaming read\n",
              "As `bench_wavelet.py --only kernel` computes it (`bench_wavelet.steady_pair` of the call and "
              "`read_bound_fn(bytes_read, 12 V)`: median of 15 per-repeat ratios by one thread's CPU time, re-timed while they "
              "spread), for the test and the base build " + ("on the same layout" if not own else
                                                             "each on its own layout and of its bytes") + ", warm.\n",
              "| size | light | N | test | base | load |", "|---|---|---|---|---|---|"]
        for r in s7rows:
            L.append(f"| {r['size']} | {r['light']} | {r['N']} | **{r['s7']['test']:.2f}** | {r['s7']['base']:.2f} | {r['load1']:.1f} |")
    for regime in [g for g in REGIMES + (TWO,) if g in rows[0]] if rows else ():
        L += [f"\n## {regime}\n",
              "| size | light | N | dense terms | sparse blocks | MB read | base µs | test µs | "
              + " | ".join(f"**base / {k}**" if k == "test" else f"base / {k}" for k in cols)
              + " | of read: test / base | bits |" + (" error test / base |" if own else "")
              + " load |",
              "|---|---|---|---|---|---|---|---|" + "---|" * len(cols) + "---|---|---|"
              + ("---|" if own else "")]
        for r in rows:
            g = r[regime]
            two = own
            nd = f"{r['nd']} ({r['nd_base']})" if two else f"{r['nd']}"
            mb = f"{r['mb']:.2f} ({r['mb_base']:.2f})" if two else f"{r['mb']:.2f}"
            L.append(f"| {r['size']} | {r['light']} | {r['N']} | {nd} | {r['sb']}{' rows' if r['rows'] else ''} | "
                     f"{mb} | {g['test'][4]:.1f} | {g['test'][3]:.1f} | "
                     + " | ".join(q(g[k]) for k in cols)
                     + (f" | {g['read_test'][0]:.2f} / {g['read_base'][0]:.2f} | " if regime != TWO else " | — | ")
                     + f"{'same' if all(r['same'].values()) else '**differ**'} |"
                     + (f" {r['err']['test']:.1e} / {r['err']['base']:.1e} |" if two else "") + f" {r['load1']:.1f} |")
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", default="main", help="the git revision to pair against (default main)")
    ap.add_argument("--sizes", default=",".join(KERNEL_SIZES), help="comma-separated: " + ", ".join(KERNEL_SIZES))
    ap.add_argument("--terms", default=",".join(map(str, TERMS)), help="comma-separated N (all terms always added)")
    ap.add_argument("--variants", default="touch8,outpf", help="comma-separated: " + ", ".join(VARIANTS) + ", or several joined by '+' ('': none)")
    ap.add_argument("--s7-terms", default="30", help="the N whose rows also get section 7's fraction of the streaming read "
                    "(bench_wavelet.steady_pair: 15 repeats, median ratio), test and base ('': none)")
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--evict-mb", type=float, default=3.0)
    ap.add_argument("--calls", type=int, default=4)
    ap.add_argument("--check-avx2", action="store_true", help="compare the AVX2 builds' .text (gcc, objcopy)")
    ap.add_argument("--two-threads", action="store_true", help="also pair every build at two threads by wall clock")
    ap.add_argument("--write", default=str(OUT / "wavelet_scratch.md"), help="the report ('': print only)")
    ap.add_argument("--vnni", action="store_true", help="every build with #define DENSE_VNNI 1 prepended")
    ap.add_argument("--base-dense-min", default=None, help="the base and A/A builds on a relighter built with this "
                    "dense_min (a number, or 'third': 1/3, main's 16-bit default); default: the same layout as the test")
    ap.add_argument("--base-tile", default=None, help="the base and A/A builds on a relighter built with this tile "
                    "(vertices, a multiple of 32, or 'half': the default before the tile followed the threads, half the "
                    "vertices up to 4096); default: the same layout as the test")
    ap.add_argument("--base-first", action="store_true", help="with --base-tile or --base-dense-min: the base's relighter "
                    "built before the test's (a control of the two relighters' placement in memory)")
    ap.add_argument("--title", default="the sparse scratch zero between calls, and the output pass",
                    help="the report's title (what the working tree changes)")
    ap.add_argument("--test-about", default="the scratch zero between calls, a touched map per 32-vertex block; the RGB "
                    "interleave by one insert and two `vpermt2ps`, `OUT_Z` 1", help="the report's words for the test build")
    ap.add_argument("--base-about", default="a memset of each tile's scratch, every block's accumulators added back",
                    help="the report's words for the base build")
    args = ap.parse_args()
    args.base_dense_min_text = args.base_dense_min
    if args.base_dense_min is not None:
        try:
            args.base_dense_min = 1 / 3 if args.base_dense_min == "third" else float(args.base_dense_min)
        except ValueError:
            raise SystemExit(f"{WHO}: --base-dense-min {args.base_dense_min!r}; accepted: a number > 0, or 'third'") from None
        if not args.base_dense_min > 0:
            raise SystemExit(f"{WHO}: --base-dense-min {args.base_dense_min_text!r}; accepted: a number > 0, or 'third'")
    if args.base_tile is not None and args.base_tile != "half" and not (args.base_tile.isdigit() and int(args.base_tile) > 0
                                                                         and int(args.base_tile) % 32 == 0):
        raise SystemExit(f"{WHO}: --base-tile {args.base_tile!r}; accepted: a positive multiple of 32, or 'half'")
    if args.base_first and args.base_tile is None and args.base_dense_min is None:
        raise SystemExit(f"{WHO}: --base-first without a layout of the base's own; accepted: with --base-tile or "
                         "--base-dense-min")
    sizes = [size_choice(s.strip(), WHO) for s in args.sizes.split(",")]
    names = [n.strip() for n in args.variants.split(",") if n.strip()]
    for n in names:
        if not all(v in VARIANTS for v in n.split("+")):
            raise SystemExit(f"{WHO}: --variants {n!r}; accepted: a comma-separated list of {', '.join(VARIANTS)} (or several joined by '+')")
    try:
        terms = tuple(int(t) for t in args.terms.split(",") if t.strip())
    except ValueError:
        raise SystemExit(f"{WHO}: --terms {args.terms!r}; accepted: comma-separated integers >= 1") from None
    if not terms or min(terms) < 1:
        raise SystemExit(f"{WHO}: --terms {args.terms!r}; accepted: comma-separated integers >= 1")
    try:
        s7 = tuple(int(t) for t in args.s7_terms.split(",") if t.strip())
    except ValueError:
        raise SystemExit(f"{WHO}: --s7-terms {args.s7_terms!r}; accepted: comma-separated integers (of --terms)") from None
    if args.repeats < 3:
        raise SystemExit(f"{WHO}: --repeats {args.repeats}; accepted: an integer >= 3")
    if args.calls < 1:
        raise SystemExit(f"{WHO}: --calls {args.calls}; accepted: an integer >= 1")
    if not args.evict_mb > 0:
        raise SystemExit(f"{WHO}: --evict-mb {args.evict_mb}; accepted: a number > 0")
    torch.set_num_threads(1)
    avx2_same = avx2_text_same(args.base) if args.check_avx2 else None
    if avx2_same is False:
        raise SystemExit(f"{WHO}: the AVX2 build's .text differs from {args.base}'s: pair it (bench_wavelet_isa.py)")
    libs, flags = builds(args.base, names, args.vnni)
    before = load()
    infos, rows = [], []
    for s in sizes:
        info, r = size_rows(s, libs, terms, args.repeats, int(args.evict_mb * 2**20), args.calls, s7, args.base_dense_min,
                            REGIMES + ((TWO,) if args.two_threads else ()), args.base_tile, args.base_first)
        infos.append(info)
        rows += r
    after = load()
    text = report(infos, rows, flags, args, before, after, names, avx2_same)
    emit_report(args.write, text, "scratch", {"infos": infos, "rows": rows})
    if not all(all(r["same"].values()) for r in rows):
        raise SystemExit(f"{WHO}: a build's outputs differ from the base build's (see 'bits')")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
