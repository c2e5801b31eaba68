"""The dense slot order (issue 39; ``WaveletRelighter(dense_order=...)``): relighters of one transfer whose dense slots
are numbered in different orders, each bound to the same kernel build (``--isa``: ``native`` default, ``avx2`` the 8-lane
code tuned on an AMD Zen 3), paired with the default order (``'column'``) by one thread's CPU time, with an A/A
control (a second relighter of the default order: placement), at each ``--sizes`` of occluder_over_plane (small /
medium / large: V = 2251 / 10585 / 51335; R = 32, K = 256, 16-bit values), the studio and sky lights (transport-weighted
terms, RGB, the relighter's per-vertex factor) at N = ``--terms`` and all, in two regimes:

- **warm**: back-to-back calls (``timing.measure_paired``);
- **evicted**: each call preceded (untimed) by a streaming read of ``--evict-mb`` MB (default 3) of other data
  (``timing.measure_paired_cold``'s junk read: the call's lines from L3); a sample is 4 such calls.

Orders (``--orders``): ``weight`` (descending transport weight), ``level`` (coarse Haar levels first) — both
light-independent —, ``own`` (the row's light's own transport-weighted ranking: a relighter built per light, so every N
of that light reads a prefix of each block's slots: the bound on what an order can give), ``both`` (the columns by
their better rank in the studio and the sky lights' rankings: one relighter for two lights). A layout change only: the
kernel is the same build on every side. The kernel's dense list is in column order on the AVX-512 build (N > 256) or
the light's order (N <= 256), slot order on the 8-lane builds (N > 256): where the list order is the same the outputs
are the same bits; each output's largest difference from the float64 sums of the stored values
(``relight.wavelet_dense``) relative to the output's largest value is reported for the default and the worst order.

Per row: column / order (the median of the per-repeat ratios [quartiles]; > 1: the order faster). Writes
reports/benchmarks/wavelet_dense_order.md's section for this CPU, build and sizes (``--write``; '' prints).

    .venv/bin/python benchmarks/bench_wavelet_dense_order.py [--sizes small,medium,large] [--isa native|avx2]
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import LIGHTS, OUT, kernel_transfer, load, size_choice  # noqa: E402
from bench_wavelet_isa import bound_call, kernel_build, kernel_source  # noqa: E402
from bench_wavelet_setup import write  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, measure_paired_cold  # noqa: E402

WHO = "bench_wavelet_dense_order.py"
ORDERS = ("weight", "level", "own", "both")
TERMS = (10, 30, 100, 300, 1000)
LIGHT_NAMES = ("studio", "sky (sun)")


def ranking(rl, light: str) -> torch.Tensor:
    """``light``'s transport-weighted ranking of every Haar column (int64 [P], the largest term first)."""
    return rl.light(LIGHTS[light], rl.P, "transport")[0]


def both_order(rl) -> torch.Tensor:
    """The Haar columns by their better rank in the studio and sky rankings (ties by column): int64 [P]."""
    rank = torch.full((rl.P,), rl.P, dtype=torch.int64)
    for light in LIGHT_NAMES:
        r = torch.full((rl.P,), rl.P, dtype=torch.int64)
        li = ranking(rl, light)
        r[li] = torch.arange(li.numel())
        rank = torch.minimum(rank, r)
    return torch.argsort(rank * rl.P + torch.arange(rl.P))


def regimes_option(text: str, who: str) -> list[str]:
    """``--regimes`` checked before any work: ``warm`` and/or ``evicted``, comma-separated, else one line naming
    ``who``, the option, the value and what is accepted (the dense-order, runs and interleave benchmarks)."""
    regimes = [g.strip() for g in text.split(",")]
    if not regimes or any(g not in ("warm", "evicted") for g in regimes):
        raise SystemExit(f"{who}: --regimes {text!r}; accepted: warm and/or evicted, comma-separated")
    return regimes


def pair(regime: str, a, b, repeats: int, evict_bytes: int) -> list[float]:
    """``a`` against ``b``: [median of b / a per repeat, q1, q3, a's median µs, b's median µs]."""
    if regime == "warm":
        p = measure_paired(a, b, repeats=repeats, warmup=1, clock=time.thread_time)
    else:
        p = measure_paired_cold(a, b, repeats=2 * repeats + 1, warmup=1, evict_bytes=evict_bytes, clock=time.thread_time,
                                calls=4)
    return [p.speedup, p.ratio.q1, p.ratio.q3, p.test.median * 1e6, p.peer.median * 1e6]


def size_rows(size: str, lib, orders, terms, repeats: int, evict_bytes: int, regimes) -> list[str]:
    tr = kernel_transfer(size)

    def make(order="column"):
        return relight.WaveletRelighter(tr, threads=1, layouts="both", dense_order=order)
    base, aa = make(), make()
    rls = {"A/A": {n: aa for n in LIGHT_NAMES}}
    for o in orders:
        if o == "own":
            rls[o] = {n: make(ranking(base, n)) for n in LIGHT_NAMES}
        elif o == "both":
            r = make(both_order(base))
            rls[o] = {n: r for n in LIGHT_NAMES}
        else:
            r = make(o)
            rls[o] = {n: r for n in LIGHT_NAMES}
    ref_index, ref_vals = base.reference_rows(0, base.V)
    lines = []
    for light in LIGHT_NAMES:
        for N in tuple(terms) + (base.P,):
            li, lv, _ = base.light(LIGHTS[light], N, "transport")
            li, lv = li.contiguous(), lv.to(torch.float32).contiguous()
            out = torch.empty(base.V, 3)
            fb = bound_call(base, lib, li, lv, out, 1, per_vertex=True)
            fb()
            ref = relight.wavelet_dense(ref_vals.double(), ref_index, li, lv.double(), base.P) * base.albedo[:, :3].double()
            sc = float(ref.abs().max()) or 1.0
            err = {"column": float((out.double() - ref).abs().max()) / sc}
            nd = int((base.dslot[li] >= 0).sum())
            cells = {}
            for name, per in rls.items():
                rl = per[light]
                o2 = torch.empty(base.V, 3)
                fn = bound_call(rl, lib, li, lv, o2, 1, per_vertex=True)
                fn()
                err[name] = float((o2.double() - ref).abs().max()) / sc
                cells[name] = {g: pair(g, fn, fb, repeats, evict_bytes) for g in regimes}
            n = "all" if N == base.P else str(N)
            worst = max(v for k, v in err.items() if k != "column")
            for g in regimes:
                row = (f"| {size} | {light} | {n} | {nd} | {g} | {cells['A/A'][g][4]:.1f} | "
                       + " | ".join(f"**{cells[k][g][0]:.3f}** [{cells[k][g][1]:.2f}, {cells[k][g][2]:.2f}]"
                                    for k in rls if k != "A/A")
                       + f" | {cells['A/A'][g][0]:.3f} [{cells['A/A'][g][1]:.2f}, {cells['A/A'][g][2]:.2f}] | "
                       f"{err['column']:.1e} / {worst:.1e} | {load():.1f} |")
                lines.append(row)
                print(f"[dense_order] {row}", flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="small,medium,large", help="occluder_over_plane sizes, comma-separated")
    ap.add_argument("--isa", default="native", help="the kernel build: native (default), avx2, avx512, avx512-256")
    ap.add_argument("--orders", default=",".join(ORDERS), help=f"the orders paired with 'column': some of {ORDERS}")
    ap.add_argument("--terms", default=",".join(map(str, TERMS)), help="N per light (all terms always added)")
    ap.add_argument("--regimes", default="warm,evicted", help="warm and/or evicted")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--evict-mb", type=float, default=3.0)
    ap.add_argument("--write", default=str(OUT / "wavelet_dense_order.md"), help="the report ('': print only)")
    args = ap.parse_args()
    sizes = [size_choice(s.strip(), WHO) for s in args.sizes.split(",")]
    orders = [o.strip() for o in args.orders.split(",") if o.strip()]
    bad = [o for o in orders if o not in ORDERS]
    if bad or not orders:
        raise SystemExit(f"{WHO}: --orders {args.orders!r}; accepted: some of {', '.join(ORDERS)}, comma-separated")
    regimes = regimes_option(args.regimes, WHO)
    try:
        terms = tuple(int(t) for t in args.terms.split(","))
    except ValueError:
        raise SystemExit(f"{WHO}: --terms {args.terms!r}; accepted: positive integers, comma-separated") from None
    if any(t < 1 for t in terms):
        raise SystemExit(f"{WHO}: --terms {args.terms!r}; accepted: positive integers, comma-separated")
    torch.set_num_threads(1)
    src, label = kernel_source(None, WHO)
    lib, flags = kernel_build(src, args.isa, WHO)
    before = load()
    lines = []
    for s in sizes:
        lines += size_rows(s, lib, orders, terms, args.repeats, int(args.evict_mb * 2**20), regimes)
    head = (f"## {cpu_label()}: the `{args.isa}` build, sizes {', '.join(sizes)}\n\n"
            f"Kernel {label} ({flags}); one thread's CPU time, the median of {args.repeats} paired repeats (evicted: "
            f"{2 * args.repeats + 1}, each sample 4 calls after a {args.evict_mb:g} MB read); **column / order** > 1: the "
            f"order faster [quartiles]; A/A: column against a second relighter of the same order. err: the largest "
            f"difference from the float64 sums relative to the output's largest value, column / the worst other. Load "
            f"average {before:.1f} → {load():.1f}. Reproduce: `.venv/bin/python benchmarks/{WHO} --sizes {args.sizes} "
            f"--isa {args.isa} --orders {args.orders}`.\n\n"
            f"| size | light | N | dense terms | regime | column µs | "
            + " | ".join(f"**column / {o}**" for o in orders) + " | A/A | err | load |\n"
            + "|---" * (9 + len(orders)) + "|")
    write(args.write, head + "\n" + "\n".join(lines) + "\n",
          title="# Wavelet kernel: the dense slot order (issue 39)\n\nReproduce: `.venv/bin/python benchmarks/"
                f"{WHO}` (module docstring). One section per CPU, build and sizes; a run replaces its own.\n")


if __name__ == "__main__":
    main()
