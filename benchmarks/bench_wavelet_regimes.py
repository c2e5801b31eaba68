"""The wavelet kernel's dense-loop prefetch in three cache regimes (issue 39): which layouts should take the prefetch
across units (``kernels/wavelet.c``'s ``PF_FAR``, taken when the dense layout holds at least ``PFX_MIN`` bytes) when
the call does not find its lines in the L2.

Builds of the working tree's ``kernels/wavelet.c`` (this CPU's native build: on an AVX-512 CPU the 16-lane loop
whose prefetch these knobs move; ``-D`` overrides prepended to the source through ``bench_wavelet_isa.kernel_build``):
**base** (``PFX_MIN`` = 2 MB, the default before; the working tree's is now 0), **A/A** (the base built twice), ``PFX_MIN`` = 0 (the far path always),
512 KB, 1 MB, *never* (the within-unit prefetch ``PF_IN`` always), and ``PF_IN`` variants: the in-unit distance
``PF`` = 3 / 10 / 16 and ``PF_NEXT`` (the unit's last PF terms prefetch the next unit's first terms), these with the
base's ``PFX_MIN`` (at small they replace the in-unit loop the base runs; at medium the far path runs in every build). All bound to one
layout per size (occluder_over_plane small / medium: V = 2251 / 10585, dense layouts 1.1 / 5.2 MB against a 2 MB L2;
R = 32, K = 256, 16-bit), the studio and sky lights (transport-weighted terms, RGB) at N = 10, 30, 100, 300, 1000 and
all, one thread, timed by the calling thread's CPU time (``clock=time.thread_time``: the other processes' load enters
neither side), paired against the base in three regimes:

- **warm**: back-to-back calls (``timing.measure_paired``; samples of ≥ 20 ms of calls);
- **evicted**: each call preceded (untimed) by a streaming read of ``--evict-mb`` MB (default 3) of
  other data (``timing.measure_paired_cold`` without ``evict``: its junk read, here sized to just outgrow the L2):
  the call finds its lines in L3, as in a render loop doing other work between relights; a sample is ``--calls``
  (default 4) such calls, its time their mean;
- **cold**: each call preceded by a flush of everything the two sides touch from every cache level
  (``measure_paired_cold(evict=working_set(...))``): the lines from memory.

Each ``PFX_MIN`` build is also paired with the streaming read of the bytes the call touches plus a fill of the output
(``timing.read_bound_fn`` of ``WaveletRelighter.bytes_read``) in the same regime. Every build's output is compared
bit for bit with the base's. Writes reports/benchmarks/wavelet_regimes.md (and the rows as .json).

    .venv/bin/python benchmarks/bench_wavelet_regimes.py [--sizes small,medium] [--variants ...]   (about 7 minutes)
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
from bench_wavelet import BITS, OUT, kernel_lights, kernel_transfer, layout_info, load, size_choice  # noqa: E402
from bench_wavelet_isa import bound_call, emit_report, kernel_build, kernel_source  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import KERNEL_ISAS, cpu_isa  # noqa: E402
from prt_torch.harness.timing import (cpu_label, measure_paired, measure_paired_cold, read_bound_fn,  # noqa: E402
                                      working_set)

TERMS = (10, 30, 100, 300, 1000)
WHO = "bench_wavelet_regimes.py"
def regimes(evict_mb: list[float]) -> list[tuple[str, int | None]]:
    """``[(name, evict bytes)]``: warm, one evicted regime per ``evict_mb`` size (named ``evicted`` alone when there is
    one size, else ``evicted X MB``), cold."""
    ev = [(("evicted" if len(evict_mb) == 1 else f"evicted {m:g} MB"), int(m * 2**20)) for m in evict_mb]
    return [("warm", None), *ev, ("cold", None)]
#: the base every variant is paired against: PFX_MIN = 2 MB (the default before this benchmark; the working tree's
#: default is now 0, i.e. the ``pfx0`` variant), prepended whatever the tree's default
BASE = "#define PFX_MIN (2LL << 20)\n"
#: the 8-lane builds' base (--isa avx2, avx512-256): their dense loop without the prefetch across units, the code tuned
#: on the AMD Zen 3 (the default until the x8 variant measured here was made the default)
BASE_X8 = "#define PF_X8 0\n"
#: variant name -> the -D lines prepended to the source
VARIANTS = {
    "pfx0": "#define PFX_MIN 0LL\n",
    "pfx512k": "#define PFX_MIN (512LL << 10)\n",
    "pfx1m": "#define PFX_MIN (1LL << 20)\n",
    "never": "#define PFX_MIN (1LL << 62)\n",
    "pf3": "#define PF 3\n" + BASE,  # the in-unit variants with the base's PFX_MIN: at small they replace PF_IN
    "pf10": "#define PF 10\n" + BASE,
    "pf16": "#define PF 16\n" + BASE,
    "next": "#define PF_NEXT 1\n" + BASE,
    # the 8-lane loop (builds without W16: --isa avx2 or avx512-256) with the prefetch across units, on every layout
    "x8": "#define PF_X8 1\n#define PFX_MIN 0LL\n",
    "x8pfx12": "#define PF_X8 1\n#define PFX_MIN 0LL\n#define PFX 12\n",
    "x8pfx48": "#define PF_X8 1\n#define PFX_MIN 0LL\n#define PFX 48\n",
}
#: the variants that change only the 8-lane loop (PF_X8: a W16 build ignores them) and the builds running that loop
X8 = ("x8", "x8pfx12", "x8pfx48")
ISAS_8LANE = ("avx2", "avx512-256")
LABEL = {"base": "PFX_MIN 2 MB (base)", "aa": "A/A", "pfx0": "PFX_MIN 0 (far always)", "pfx512k": "PFX_MIN 512 KB",
         "pfx1m": "PFX_MIN 1 MB", "never": "PF_IN always", "pf3": "PF 3", "pf10": "PF 10", "pf16": "PF 16",
         "next": "PF_NEXT", "x8": "PF_X8 (PFX 24)", "x8pfx12": "PF_X8, PFX 12", "x8pfx48": "PF_X8, PFX 48"}
#: the builds also paired with the streaming read
BOUND = ("base", "pfx0", "pfx512k", "pfx1m", "x8")


def is_8lane(isa: str) -> bool:
    """Whether the build for ``isa`` runs the 8-lane dense loop: avx2 / avx512-256 (:data:`ISAS_8LANE`), or native on a
    CPU without AVX-512 (``_native.cpu_isa``: an AVX2-only CPU such as the AMD Zen 3, where native is the 8-lane build)."""
    return isa in ISAS_8LANE or (isa == "native" and cpu_isa() != "avx512")


def base_lines(isa: str) -> str:
    """The base build's prepended lines for ``isa``: :data:`BASE_X8` for the 8-lane builds, else :data:`BASE`."""
    return BASE_X8 if is_8lane(isa) else BASE


def builds(names: list[str], isa: str = "native") -> tuple[dict, str]:
    """``({name: library}, flags)``: base, aa and ``names`` (keys of VARIANTS), builds of the working tree for ``isa``
    (``_native.KERNEL_ISAS``: native, or avx2 / avx512-256 for the 8-lane loop, whose base is :data:`BASE_X8`)."""
    text, _ = kernel_source(None, WHO)
    b = base_lines(isa)
    libs = {"base": kernel_build(b + text, isa, WHO)[0], "aa": kernel_build(b + text, isa, WHO, tag="A/A control")[0]}
    for n in names:
        libs[n] = kernel_build(VARIANTS[n] + text, isa, WHO)[0]
    return libs, kernel_build(text, isa, WHO)[1]


def pair(regime: str, a, b, ws: list, repeats: int, evict_bytes: int | None, calls: int):
    """``a`` against ``b`` in ``regime`` (a name of :func:`regimes`; ``evict_bytes`` its junk read): the Paired
    (speedup = b / a, > 1: a faster)."""
    if regime == "warm":
        return measure_paired(a, b, repeats=repeats, warmup=1, clock=time.thread_time)
    if regime.startswith("evicted"):
        return measure_paired_cold(a, b, repeats=2 * repeats + 1, warmup=1, evict_bytes=evict_bytes,
                                   clock=time.thread_time, calls=calls)
    return measure_paired_cold(a, b, repeats=2 * repeats + 1, warmup=1, evict=ws, clock=time.thread_time, calls=calls)


def size_rows(size: str, libs: dict, repeats: int, regs: list, calls: int, terms) -> tuple[dict, list[dict]]:
    rl = relight.WaveletRelighter(kernel_transfer(size), threads=1, layouts="both")
    info = layout_info(rl, size)
    rows = []
    for light, N, li, lv in kernel_lights(rl, terms):
        nbytes = rl.bytes_read(li)
        bound = read_bound_fn(nbytes, rl.V * 12)
        nd = int((rl.dslot[li] >= 0).sum())
        outs = {k: torch.empty(rl.V, 3) for k in libs}
        fn = {k: bound_call(rl, lib, li, lv, outs[k], 1) for k, lib in libs.items()}
        for f in fn.values():
            f()
        row = {"size": size, "light": light, "N": N, "nd": nd, "mb": nbytes / 2**20,
               "touched_dense_kb": nd * ((rl.V + 31) // 32) * 64 * rl.dense.shape[2] / 1024,
               "same": {k: bool(torch.equal(outs[k], outs["base"])) for k in outs}, "load0": load()}
        for regime, evict_bytes in regs:
            r = {}
            for k in [k for k in fn if k != "base"]:
                p = pair(regime, fn[k], fn["base"], working_set(rl, fn[k], fn["base"]), repeats, evict_bytes, calls)
                r[k] = [p.speedup, p.ratio.q1, p.ratio.q3, p.test.median * 1e6]
                r["base_us"] = p.peer.median * 1e6
                if p.eviction:
                    r["eviction"] = {"method": p.eviction["method"], "mb": p.eviction["bytes"] / 2**20}
            for k in [k for k in BOUND if k in fn]:
                p = pair(regime, fn[k], bound, working_set(rl, fn[k], bound), repeats, evict_bytes, calls)
                r["read_" + k] = [p.speedup, p.ratio.q1, p.ratio.q3, p.peer.median * 1e6]
            row[regime] = r
        row["load1"] = load()
        rows.append(row)
        msg = "; ".join(f"{g} base {row[g]['base_us']:.1f} us of read {row[g]['read_base'][0]:.2f}, " + ", ".join(
            f"{k} {row[g][k][0]:.3f}" for k in row[g] if k not in ("base_us", "eviction") and not k.startswith("read_"))
            for g, _ in regs)
        print(f"[regimes] {size} {light} N={N} nd={nd}: {msg}; same {all(row['same'].values())}, load "
              f"{row['load1']:.1f}", flush=True)
    return info, rows


def defines(k: str, isa: str = "native") -> str:
    """Build ``k``'s prepended lines, on one line."""
    return "; ".join(VARIANTS.get(k, base_lines(isa)).strip().splitlines())


def label(k: str, isa: str) -> str:
    """Build ``k``'s name in the report: the base of an 8-lane build is its default code (no PF_X8)."""
    return "PF_X8 0 (base)" if k == "base" and is_8lane(isa) else LABEL[k]


def report(infos: list[dict], rows: list[dict], flags: str, args, before: float, after: float, names: list[str],
           regs: list) -> str:
    def q(t):
        return f"{t[0]:.2f} [{t[1]:.2f}, {t[2]:.2f}]"
    isa = args.isa
    ev = [(g, b) for g, b in regs if b is not None]
    base = ("the base: the 8-lane loop without the prefetch across units, its code tuned on the AMD Zen 3"
            if is_8lane(isa) else "")
    L = [f"# Wavelet kernel: the dense loop's prefetch in {len(regs)} cache regimes, {isa} build (issue 39)\n",
         f"{cpu_label()}; load average {before:.1f} → {after:.1f} (a machine shared with other jobs: one thread's CPU "
         f"time, which their load does not enter). Builds of the working tree's `kernels/wavelet.c` for "
         f"`PRT_TORCH_KERNEL_ISA={isa}` with the wavelet library's flags (`{flags}`), `-D` overrides prepended"
         + (f" ({base})" if base else "") + ": "
         + ", ".join(f"**{label(k, isa)}**" + (f" (`{defines(k, isa)}`)" if k != "aa" else "") for k in ["base", "aa"] + names)
         + ". All bound to one layout per size (occluder_over_plane, R = 32, K = 256, "
         f"{BITS}-bit; " + "; ".join(f"{i['size']}: V = {i['V']}, {i['Pd']} dense columns, dense layout "
                                      f"{i['dense_mb']:.1f} MB" for i in infos)
         + "), transport-weighted terms, RGB light, one thread, paired by the calling thread's CPU time. Regimes: "
         f"**warm** back-to-back calls (`measure_paired`, {args.repeats} repeats of ≥ 20 ms samples); "
         + "; ".join(f"**{g}** each call after an untimed streaming read of {b / 2**20:g} MB of other data" for g, b in ev)
         + f" (`measure_paired_cold`'s junk read; {2 * args.repeats + 1} repeats, a sample {args.calls} such calls; a read "
         "smaller than the L2 leaves the rest of the L2 to the previous call's lines: 1.5 MB of a 2 MB L2 leaves ~512 KB, "
         "the L2 of an AMD Zen 3 core); **cold** each call after a flush "
         f"of everything both sides touch (`measure_paired_cold(evict=working_set(...), calls={args.calls})`: the layout, "
         f"its row-major copy and scratch, light, factor, output; {2 * args.repeats + 1} repeats). Ratios: base / variant, the "
         "median of the per-repeat ratios [quartiles] (> 1: the variant faster); *of read*: the build against a "
         "streaming read of the bytes it touches plus a fill of the output (`timing.read_bound_fn`) in the same regime "
         "(> 0.5: the issue's criterion met). *dense KB*: the light's dense lines (nd terms × blocks × 64 B × CT). "
         f"Reproduce: `.venv/bin/python benchmarks/bench_wavelet_regimes.py --isa {isa} --sizes {args.sizes} --variants "
         f"{','.join(names)} --evict-mb {args.evict_mb} --calls {args.calls} --repeats {args.repeats}`.\n"]
    for regime, _ in regs:
        L += [f"\n## {regime}\n",
              "| size | light | N | dense terms | dense KB | MB read | base µs | base of read | "
              + " | ".join(f"base / {label(k, isa)}" for k in ["aa"] + names) + " | "
              + " | ".join(f"{LABEL[k]} of read" for k in BOUND if k != "base" and k in ["aa"] + names) + " | bits | load |",
              "|---" * (11 + len(names) + len([k for k in BOUND if k != "base" and k in names])) + "|"]
        for r in rows:
            g = r[regime]
            L.append(f"| {r['size']} | {r['light']} | {r['N']} | {r['nd']} | {r['touched_dense_kb']:.0f} | {r['mb']:.2f} | "
                     f"{g['base_us']:.1f} | {g['read_base'][0]:.2f} | " + " | ".join(q(g[k]) for k in ["aa"] + names) + " | "
                     + " | ".join(f"{g['read_' + k][0]:.2f}" for k in BOUND if k != "base" and k in names)
                     + f" | {'same' if all(r['same'].values()) else '**differ**'} | {r['load1']:.1f} |")
    return "\n".join(L) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--isa", default="native", help="the builds' PRT_TORCH_KERNEL_ISA: " + ", ".join(KERNEL_ISAS)
                    + f" ({', '.join(ISAS_8LANE)}, and native on a CPU without AVX-512: the 8-lane loop, variants {', '.join(X8)})")
    ap.add_argument("--sizes", default="small,medium", help="comma-separated: small, medium, large")
    ap.add_argument("--variants", default=None, help="comma-separated, of: " + ", ".join(VARIANTS) + " (default: all "
                    "that change the --isa build's loop)")
    ap.add_argument("--terms", default=",".join(map(str, TERMS)), help="light terms N (all is always added)")
    ap.add_argument("--repeats", type=int, default=11, help="warm repeats (evicted, cold: 3x as many single calls)")
    ap.add_argument("--calls", type=int, default=4, help="evicted, cold: calls per sample, each after its eviction")
    ap.add_argument("--evict-mb", default="3", help="the evicted regimes' streaming reads, MB, comma-separated (default "
                    "3; 1.5 leaves ~512 KB of a 2 MB L2 to the previous call)")
    ap.add_argument("--write", default=None, help="the report ('': print only; default reports/benchmarks/"
                    "wavelet_regimes.md, for another --isa wavelet_regimes_ISA.md)")
    args = ap.parse_args()
    if args.isa not in KERNEL_ISAS:
        raise SystemExit(f"{WHO}: --isa {args.isa!r}; accepted: one of " + ", ".join(KERNEL_ISAS))
    sizes = [size_choice(s.strip(), WHO) for s in args.sizes.split(",")]
    lane8 = is_8lane(args.isa)
    own = [k for k in VARIANTS if (k in X8) == lane8]  # the variants that change this build's dense loop
    names = own if args.variants is None else [v.strip() for v in args.variants.split(",") if v.strip()]
    bad = [v for v in names if v not in VARIANTS]
    if bad:
        raise SystemExit(f"{WHO}: --variants {bad[0]!r}; accepted: a comma-separated list of " + ", ".join(VARIANTS))
    other = [v for v in names if v not in own]
    if other:
        raise SystemExit(f"{WHO}: --variants {other[0]!r} with --isa {args.isa}: it leaves that build's dense loop as the "
                         f"base's; accepted with --isa {args.isa}: " + ", ".join(own))
    if args.calls < 1:
        raise SystemExit(f"{WHO}: --calls {args.calls}; accepted: an integer >= 1")
    if args.repeats < 3:
        raise SystemExit(f"{WHO}: --repeats {args.repeats}; accepted: an integer >= 3")
    try:
        evict_mb = [float(m) for m in args.evict_mb.split(",") if m.strip()]
    except ValueError:
        evict_mb = []
    if not evict_mb or not all(0.5 <= m <= 64 for m in evict_mb) or len(set(evict_mb)) < len(evict_mb):
        raise SystemExit(f"{WHO}: --evict-mb {args.evict_mb!r}; accepted: comma-separated distinct sizes 0.5 to 64 (MB)")
    regs = regimes(evict_mb)
    if args.write is None:
        args.write = str(OUT / ("wavelet_regimes.md" if args.isa == "native" else f"wavelet_regimes_{args.isa}.md"))
    try:
        terms = [int(t) for t in args.terms.split(",") if t.strip()]
    except ValueError:
        raise SystemExit(f"{WHO}: --terms {args.terms!r}; accepted: comma-separated integers >= 1") from None
    if not terms or min(terms) < 1:
        raise SystemExit(f"{WHO}: --terms {args.terms!r}; accepted: comma-separated integers >= 1")
    torch.set_num_threads(1)
    libs, flags = builds(names, args.isa)
    before = load()
    infos, rows = [], []
    for s in sizes:
        info, r = size_rows(s, libs, args.repeats, regs, args.calls, terms)
        infos.append(info)
        rows += r
    after = load()
    text = report(infos, rows, flags, args, before, after, names, regs)
    emit_report(args.write, text, "regimes",
                {"cpu": cpu_label(), "isa": args.isa, "flags": flags, "load": [before, after], "infos": infos, "rows": rows,
                 "variants": {k: VARIANTS.get(k, base_lines(args.isa)) for k in ["base", "aa"] + names}})
    if not all(all(r["same"].values()) for r in rows):
        raise SystemExit(f"{WHO}: a build's outputs differ from the base build's (see 'bits')")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
