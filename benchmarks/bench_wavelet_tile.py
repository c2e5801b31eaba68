"""The wavelet relighter's default tile (issue 39; ``WaveletRelighter._tile``): a relighter built for one thread (one
tile at ``--size`` small, V = 2251 <= 4096) against one built for two (two tiles: the default before the tile followed
the threads), both called at one thread, **across placements**: ``--placements`` K relighters of each, built in turn on
one transfer (a pad tensor of a different size allocated between builds), and every (one-tile i, two-tile j) pair of
calls timed paired by one thread's CPU time (``measure_paired(clock=time.thread_time)``, ``--repeats`` each, through
``WaveletRelighter.prepared``), K x K pairings per row; the control pairs one-tile relighters i != j with each other
(what two placements of one layout differ by). Per row: the median over the pairings of the paired ratio (> 1: one
tile faster) and their range. Why across placements: two relighters of one layout, each paired once, differ by up to
~3% warm and up to ~2x evicted at small (``bench_wavelet_scratch.py --base-tile 2272`` against ``--base-first``;
docs/wavelet_kernel_log.md "The tile follows the relighter's threads"), as much as the tile itself.

Lights: occluder_over_plane (``--size``), R = 32, K = 256, 16-bit values (section 7's kernel transfer), studio and sky,
transport-weighted terms, RGB, at N = 10, 30, 100, 300, 1000 (studio: 292 nonzero terms, so 300 only) and all; every
output compared bit for bit between the two layouts (each vertex's terms are added in the same order).
Writes reports/benchmarks/wavelet_tile18_placements.md (the CPU and load named).

    .venv/bin/python benchmarks/bench_wavelet_tile.py [--placements 4] [--repeats 9] [--size small]     (about a minute)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import LIGHTS, OUT, kernel_transfer, load, size_choice  # noqa: E402
from bench_wavelet_isa import emit_report  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired  # noqa: E402

WHO = "bench_wavelet_tile.py"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--placements", type=int, default=4, help="relighters of each layout (K; K x K pairings a row)")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--size", default="small", help="section 7's mesh size: small (default), medium, large")
    ap.add_argument("--pad", type=int, default=123457, help="floats of the pad tensor between builds (x the build's index)")
    ap.add_argument("--write", default=str(OUT / "wavelet_tile18_placements.md"), help="the report ('': print only)")
    args = ap.parse_args()
    args.size = size_choice(args.size, WHO)
    if args.placements < 2:
        raise SystemExit(f"{WHO}: --placements {args.placements}; accepted: at least 2 (the control pairs i != j)")
    if args.repeats < 3:
        raise SystemExit(f"{WHO}: --repeats {args.repeats}; accepted: at least 3")
    torch.set_num_threads(1)
    tr = kernel_transfer(args.size)
    ones, twos, pads = [], [], []
    for i in range(args.placements):
        ones.append(relight.WaveletRelighter(tr, threads=1))
        twos.append(relight.WaveletRelighter(tr, threads=2))
        pads.append(torch.empty(args.pad * (i + 1)))  # the next builds elsewhere in memory
    before = load()
    P, V = ones[0].P, ones[0].V
    rows = []
    for light in ("studio", "sky (sun)"):
        for N in (10, 30, 100, 300, 1000, P):
            if light == "studio" and N == 1000:  # its 292 nonzero terms: N = 300 already holds them all
                continue
            fns, outs = {}, {}
            for tag, group in (("1", ones), ("2", twos)):
                for i, r in enumerate(group):
                    r.threads = 1
                    li, lv, _ = r.light(LIGHTS[light], N, "transport")
                    outs[(tag, i)] = torch.empty(V, 3)
                    fns[(tag, i)] = r.prepared(li.contiguous(), lv.float().contiguous(), out=outs[(tag, i)])
            same = all(torch.equal(o, outs[("1", 0)]) for o in outs.values())
            rule, ctl = [], []
            for i in range(args.placements):
                for j in range(args.placements):
                    rule.append(measure_paired(fns[("1", i)], fns[("2", j)], repeats=args.repeats, warmup=1,
                                               clock=time.thread_time).speedup)
                    if i != j:
                        ctl.append(measure_paired(fns[("1", i)], fns[("1", j)], repeats=args.repeats, warmup=1,
                                                  clock=time.thread_time).speedup)
            t1 = measure_paired(fns[("1", 0)], fns[("2", 0)], repeats=args.repeats, warmup=1, clock=time.thread_time)
            rule.sort()
            ctl.sort()
            row = {"light": light, "N": N, "rule": rule, "control": ctl, "same": same, "load": load(),
                   "one_us": t1.test.median * 1e6, "two_us": t1.peer.median * 1e6}
            rows.append(row)
            print(f"[tile] {light} N={'all' if N == P else N}: one tile / two (median of {len(rule)}) "
                  f"{statistics.median(rule):.3f} [{rule[0]:.3f} .. {rule[-1]:.3f}], control "
                  f"{statistics.median(ctl):.3f} [{ctl[0]:.3f} .. {ctl[-1]:.3f}], same bits {same}, load {row['load']:.1f}",
                  flush=True)
    after = load()
    K = args.placements
    L = ["# Wavelet kernel: the default tile across placements (issue 39)\n",
         f"{cpu_label()}; load average {before:.1f} → {after:.1f} (a shared machine: one thread's CPU time, which the "
         f"others' load does not enter). occluder_over_plane {args.size} (V = {V}), R = 32, K = 256, 16-bit; the "
         f"relighter's kernel as built for this CPU ({relight.wavelet_kernel_path()['path']}). {K} relighters built for "
         f"one thread ({ones[0].NT} tile{'s' * (ones[0].NT > 1)} of {ones[0].TV} vertices) and {K} built for two "
         f"({twos[0].NT} tiles of {twos[0].TV}), called at one thread; **one / two**: the median over the {K * K} "
         f"pairings (one-tile i against two-tile j, {args.repeats} paired repeats each, median ratio) [min .. max] (> 1: "
         f"one tile faster); *control*: one-tile i against one-tile j ≠ i ({K * (K - 1)} pairings): two placements of "
         "one layout. *µs*: relighter 0 of each, one pairing. *bits*: every output of the two layouts equal. "
         f"Reproduce: `.venv/bin/python benchmarks/bench_wavelet_tile.py --placements {K} --repeats {args.repeats} "
         f"--size {args.size} --pad {args.pad}`.\n",
         "| light | N | one tile µs | two tiles µs | **one / two** [min .. max] | control [min .. max] | bits | load |",
         "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        a, c = r["rule"], r["control"]
        L.append(f"| {r['light']} | {'all' if r['N'] == P else r['N']} | {r['one_us']:.1f} | {r['two_us']:.1f} | "
                 f"**{statistics.median(a):.3f}** [{a[0]:.3f} .. {a[-1]:.3f}] | {statistics.median(c):.3f} "
                 f"[{c[0]:.3f} .. {c[-1]:.3f}] | {'same' if r['same'] else '**differ**'} | {r['load']:.1f} |")
    emit_report(args.write, "\n".join(L) + "\n", "tile",
                {"machine": {"cpu": cpu_label(), "load_before": before, "load_after": after}, "rows": rows,
                 "placements": K, "repeats": args.repeats, "size": args.size})


if __name__ == "__main__":
    main()
