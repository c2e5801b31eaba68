"""How long a run of adjacent dense lines must be (issue 39, after "The dense slot order"): a light's dense columns
placed in the dense slots (``WaveletRelighter(dense_order=<columns>)``: a layout change only, the kernel the same build)
in **runs of r adjacent slots separated by gaps of g** other dense columns (``--runs``: r; ``--gaps``: g as multiples of
r, ``1`` and ``3`` by default, or ``s``: scattered, the runs in aligned groups of r drawn at random), so each 32-vertex
block's lines that the call reads come in runs of r × 64 bytes. Each
placement paired by one thread's CPU time with the default order (``'column'``: the light's columns where they fall)
and with the contiguous placement (the light's columns in slots 0..n-1, its own ranking: the bound on what an order
gives), with an A/A control (a second ``'column'`` relighter), at each ``--sizes`` of occluder_over_plane (R = 32, K =
256, 16-bit values, the kernel's ``--isa`` build: ``native`` default), for studio 292 kept (N = all), studio N = 100
and sky N = 100 (``--lights``; transport-weighted terms, RGB, the relighter's per-vertex factor).

Placement: the light's n dense columns in its ranking order, r of them, then g of the other dense columns (by column),
repeated; g = 3r where it fits, else the largest even gap the other columns allow (the row says the gap used: ``g``).
The placements are made on one relighter in place (``reorder_dense``), so every placement shares one allocation.
Warm: back-to-back calls (``timing.measure_paired``); evicted (``--regimes``): each call after a 3 MB streaming read
(a sample 4 calls). The outputs are the same bits for every placement in the AVX-512 build (its dense list is the
light's order for N <= 256 and column order above: not the slots'), checked per row.

``--read-strides``: rows of the contiguous placement read in another time order (the light's terms taken with that
stride, N <= 256 rows: the same lines, each step that many slots from the last; the sums' order changes, so the outputs
are checked within 1e-3 of the output's largest value) — whether the runs' gain needs their lines read one after another
(``--fdense``: every call on the float dense loop, whose cost does not depend on the terms' order as the VNNI loop's
flush groups do).

Per row: column / runs and contiguous / runs (the median of the per-repeat ratios [quartiles]; > 1: the runs faster),
and **share** = (column / runs - 1) / (column / contiguous - 1), the part of the contiguous gain the runs recover.
Writes reports/benchmarks/wavelet_dense_runs.md's section for this CPU, build and sizes (``--write``; '' prints).

    .venv/bin/python benchmarks/bench_wavelet_dense_runs.py [--sizes medium,large] [--runs 2,4,8,16,32] [--gaps 1,3]
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import LIGHTS, OUT, kernel_transfer, load, size_choice  # noqa: E402
from bench_wavelet_dense_order import pair, ranking, regimes_option  # noqa: E402
from bench_wavelet_isa import bound_call, kernel_build, kernel_source  # noqa: E402
from bench_wavelet_setup import write  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label  # noqa: E402

WHO = "bench_wavelet_dense_runs.py"
ROWS = {"studio all": ("studio", None), "studio 100": ("studio", 100), "sky 100": ("sky (sun)", 100)}


def runs_order(dcols: torch.Tensor, light_cols: torch.Tensor, r: int, g: int | None) -> tuple[torch.Tensor, str]:
    """The dense columns ``dcols [Pd]`` (int64) in slot order: ``light_cols [n]`` (dense, in the light's order) in runs of
    ``r`` separated by ``g`` of the others (by column), ``g`` lowered to the largest gap the others fill evenly; ``g``
    None (scattered): the runs in ceil(n / r) of the Pd // r aligned groups of r slots drawn at random (seed 0; adjacent
    draws merge, as a layout interleaving r blocks per term would merge a light's adjacent columns) → (int64 ``[Pd]``,
    the gap used, or 's')."""
    lc = light_cols.tolist()
    inl = set(lc)
    others = [c for c in sorted(dcols.tolist()) if c not in inl]
    if g is None:
        k = -(-len(lc) // r)
        pick = set(torch.randperm(len(dcols) // r, generator=torch.Generator().manual_seed(0))[:k].tolist())
        out, i, j = [], 0, 0
        for grp in range(-(-len(dcols) // r)):
            for _ in range(r):
                if grp in pick and i < len(lc):
                    out.append(lc[i])
                    i += 1
                elif j < len(others):
                    out.append(others[j])
                    j += 1
        out += lc[i:] + others[j:]
        assert sorted(out) == sorted(dcols.tolist())
        return torch.tensor(out, dtype=torch.int64), "s"
    k = -(-len(lc) // r)  # runs
    if k > 1:
        g = min(g, len(others) // (k - 1))
    out, i, j = [], 0, 0
    while i < len(lc):
        out += lc[i:i + r]
        i += r
        if i < len(lc):
            out += others[j:j + g]
            j += g
    out += others[j:]
    assert sorted(out) == sorted(dcols.tolist())
    return torch.tensor(out, dtype=torch.int64), str(g)


def size_rows(size: str, lib, runs, gaps, rows, repeats: int, evict_bytes: int, regimes, strides=(),
              flags: int = 0) -> list[str]:
    tr = kernel_transfer(size)

    def make():
        return relight.WaveletRelighter(tr, threads=1, layouts="both")
    base, aa, own, test = make(), make(), make(), make()
    dcols = torch.sort(base.dcol).values
    print(f"[dense_runs] {size}: V {base.V}, Pd {base.Pd}; load {load():.1f}", flush=True)
    lines = []
    for row in rows:
        light, N = ROWS[row]
        N = N or base.P
        li, lv, _ = base.light(LIGHTS[light], N, "transport")
        li, lv = li.contiguous(), lv.to(torch.float32).contiguous()
        lcols = li[base.dslot[li] >= 0]  # the light's dense columns, in its order
        n = int(lcols.numel())
        own.reorder_dense(ranking(base, light))
        outs = {k: torch.empty(base.V, 3) for k in ("column", "aa", "own", "test")}
        fc = bound_call(base, lib, li, lv, outs["column"], 1, per_vertex=True, flags=flags)
        fa = bound_call(aa, lib, li, lv, outs["aa"], 1, per_vertex=True, flags=flags)
        fo = bound_call(own, lib, li, lv, outs["own"], 1, per_vertex=True, flags=flags)
        ft = bound_call(test, lib, li, lv, outs["test"], 1, per_vertex=True, flags=flags)
        for f in (fc, fa, fo):
            f()
        same = torch.equal(outs["column"], outs["own"]) and torch.equal(outs["column"], outs["aa"])
        cells = {g: {"A/A": pair(g, fa, fc, repeats, evict_bytes), "own": pair(g, fo, fc, repeats, evict_bytes)}
                 for g in regimes}
        n_label = "all (292 kept)" if N == base.P else str(N)
        for g in regimes:
            a, o = cells[g]["A/A"], cells[g]["own"]
            line = (f"| {size} | {light} | {n_label} | {n} | {g} | contiguous | – | {a[4]:.1f} | **{o[0]:.3f}** "
                    f"[{o[1]:.2f}, {o[2]:.2f}] | 1 | 1 | {a[0]:.3f} [{a[1]:.2f}, {a[2]:.2f}] | {load():.1f} |")
            lines.append(line)
            print(f"[dense_runs] {line}", flush=True)

        def emit(f, r_label, g_label) -> None:
            """One report row per regime: ``f`` paired with the column layout (fc) and the contiguous one (fo)."""
            for g in regimes:
                c = pair(g, f, fc, repeats, evict_bytes)
                o = pair(g, f, fo, repeats, evict_bytes)
                gain = cells[g]["own"][0] - 1
                share = (c[0] - 1) / gain if abs(gain) > 0.03 else float("nan")
                line = (f"| {size} | {light} | {n_label} | {n} | {g} | {r_label} | {g_label} | {c[4]:.1f} | "
                        f"**{c[0]:.3f}** [{c[1]:.2f}, {c[2]:.2f}] | {o[0]:.3f} [{o[1]:.2f}, {o[2]:.2f}] | {share:.2f} | "
                        f"{cells[g]['A/A'][0]:.3f} | {load():.1f} |")
                lines.append(line)
                print(f"[dense_runs] {line}", flush=True)

        for r in runs:
            for gm in gaps:
                order, gap = runs_order(dcols, lcols, r, None if gm == "s" else int(gm) * r)
                test.reorder_dense(order)
                ft()
                same = same and torch.equal(outs["column"], outs["test"])
                emit(ft, r, gap)
        for st in strides if N <= 256 else ():
            # the contiguous placement read in another time order: the light's terms taken with stride st (the same
            # lines; each step st slots from the last, as a layout that interleaves blocks spreads a term's lines over
            # the pairs' steps); the sums' order changes, so the outputs are checked against the float64 sums' scale
            perm = torch.cat([torch.arange(k, li.numel(), st) for k in range(st)])
            lp, vp = li[perm].contiguous(), lv[:, perm].contiguous()
            op = torch.empty(base.V, 3)
            fp = bound_call(own, lib, lp, vp, op, 1, per_vertex=True, flags=flags)
            fp()
            if float((op - outs["column"]).abs().max()) > 1e-3 * float(outs["column"].abs().max()):
                raise SystemExit(f"{WHO}: {size} {row}: the strided read's outputs differ beyond rounding")
            emit(fp, f"contiguous, read stride {st}", "–")
        if not same:
            raise SystemExit(f"{WHO}: {size} {row}: a placement changed the outputs' bits")
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="medium,large", help="occluder_over_plane sizes, comma-separated")
    ap.add_argument("--isa", default="native", help="the kernel build: native (default), avx2, avx512, avx512-256")
    ap.add_argument("--runs", default="2,4,8,16,32", help="run lengths r (slots), comma-separated")
    ap.add_argument("--gaps", default="1,3", help="gaps as multiples of r, comma-separated")
    ap.add_argument("--read-strides", default="", help="rows of the contiguous placement read with the light's terms "
                    "taken at these strides (N <= 256 rows only), comma-separated; '' none")
    ap.add_argument("--no-runs", action="store_true", help="no runs rows (with --read-strides: those rows only)")
    ap.add_argument("--fdense", action="store_true", help="every call on the float dense loop (C | FDENSE)")
    ap.add_argument("--lights", default=",".join(ROWS), help=f"rows: some of {tuple(ROWS)}")
    ap.add_argument("--regimes", default="warm", help="warm and/or evicted")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--evict-mb", type=float, default=3.0)
    ap.add_argument("--write", default=str(OUT / "wavelet_dense_runs.md"), help="the report ('': print only)")
    args = ap.parse_args()
    sizes = [size_choice(s.strip(), WHO) for s in args.sizes.split(",")]
    try:
        runs = [int(t) for t in args.runs.split(",")]
        gaps = [t.strip() if t.strip() == "s" else int(t) for t in args.gaps.split(",")]
    except ValueError:
        raise SystemExit(f"{WHO}: --runs {args.runs!r} / --gaps {args.gaps!r}; accepted: positive integers (gaps: or "
                         "s, scattered), comma-separated") from None
    if any(t < 1 for t in runs) or any(t != "s" and t < 1 for t in gaps):
        raise SystemExit(f"{WHO}: --runs {args.runs!r} / --gaps {args.gaps!r}; accepted: positive integers (gaps: or "
                         "s, scattered), comma-separated")
    try:
        strides = [int(t) for t in args.read_strides.split(",") if t.strip()]
    except ValueError:
        raise SystemExit(f"{WHO}: --read-strides {args.read_strides!r}; accepted: integers >= 2, comma-separated") from None
    if any(t < 2 for t in strides):
        raise SystemExit(f"{WHO}: --read-strides {args.read_strides!r}; accepted: integers >= 2, comma-separated")
    if args.no_runs:
        runs = []
    rows = [s.strip() for s in args.lights.split(",")]
    if any(s not in ROWS for s in rows):
        raise SystemExit(f"{WHO}: --lights {args.lights!r}; accepted: some of {', '.join(ROWS)}, comma-separated")
    regimes = regimes_option(args.regimes, WHO)
    torch.set_num_threads(1)
    src, label = kernel_source(None, WHO)
    lib, flags = kernel_build(src, args.isa, WHO)
    before = load()
    lines = []
    for s in sizes:
        lines += size_rows(s, lib, runs, gaps, rows, args.repeats, int(args.evict_mb * 2**20), regimes, strides,
                           relight.WaveletRelighter.FDENSE if args.fdense else 0)
    head = (f"## {cpu_label()}: the `{args.isa}` build, sizes {', '.join(sizes)}, regimes {', '.join(regimes)}"
            + (f", read strides {args.read_strides}" if strides else "") + (", no runs" if args.no_runs else "")
            + (", the float dense loop" if args.fdense else "") + "\n\n"
            f"Kernel {label} ({flags}); one thread's CPU time, the median of {args.repeats} paired repeats (evicted: "
            f"{2 * args.repeats + 1}, each sample 4 calls after a {args.evict_mb:g} MB read) [quartiles]; > 1: the runs "
            f"faster. r: run length (slots of 64 bytes per 32-vertex block), g: the gap used (other dense columns "
            f"between runs; s: scattered, the runs in aligned groups of r slots drawn at random, adjacent draws "
            f"merged); share: (column / runs − 1) / (column / contiguous − 1), blank (nan) where the contiguous "
            f"gain is under 3%. A/A: column against a second column relighter. The outputs are the same bits in every "
            f"placement (checked). Load average {before:.1f} → {load():.1f}. Reproduce: `.venv/bin/python benchmarks/"
            f"{WHO} --sizes {args.sizes} --isa {args.isa} --runs {args.runs} --gaps {args.gaps} --regimes "
            f"{args.regimes}" + (f" --read-strides {args.read_strides}" if strides else "")
            + (" --no-runs" if args.no_runs else "") + (" --fdense" if args.fdense else "") + "`.\n\n"
            "| size | light | N | dense terms | regime | r | g | column µs | **column / runs** | contiguous / runs | "
            "share | A/A | load |\n" + "|---" * 13 + "|")
    write(args.write, head + "\n" + "\n".join(lines) + "\n",
          title="# Wavelet kernel: how long a run of adjacent dense lines must be (issue 39)\n\nReproduce: "
                f"`.venv/bin/python benchmarks/{WHO}` (module docstring). One section per CPU, build, sizes and "
                "regimes; a run replaces its own.\n")


if __name__ == "__main__":
    main()
