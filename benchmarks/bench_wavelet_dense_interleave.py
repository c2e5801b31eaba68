"""A timing prototype, not a layout the relighter builds (issue 39, the dense slot order's next step): the dense layout
with ``--units`` (u: 2, 4, 8 or 16) consecutive 32-vertex blocks interleaved per term (``[ceil(V / (32 u)), Pd, u, 32]`` int16: a term's
line for block 2i + 1 beside block 2i's, so every term the call reads is a run of u adjacent lines, u x 64 bytes,
whatever the light), read by ``kernels/wavelet.c`` rewritten for it (substitutions: each block's address, the slots'
stride and the pair's second block beside the first; the VNNI loop's stride test and its records — one set per pair
position in the super-block of u blocks, each term's prefetch target PFX steps ahead in the pairs' real order, the
next pair's lines 128 bytes on or the next super-block's —; the float loop's far prefetch the same targets, one line
per block; a timing build for one thread: the pair's position in a global). Each row checks
the outputs equal the working tree's on the usual layout bit for bit (the same sums in the same order), for the VNNI
dense loop (the default; checked to differ from the float loop's, so the call took it) and the float loop (``C |
FDENSE``). Paired with the working tree's kernel on the usual layout, one thread's CPU time, warm and evicted (a 3 MB
read before each call), with an A/A (the usual layout against a second relighter of it), occluder_over_plane
``--sizes`` (``--size``: one, the earlier option; one tile: the relighter at one thread), ``--regimes``, studio
N = 10, 30, 100, all (292 kept) and sky N = 10, 30, 100, 300, 1000, all. Only the AVX-512 build's 16-lane loops take
the layout (the 8-lane builds are not timed here). Writes a section of reports/benchmarks/wavelet_dense_runs.md (``--write``; '' prints).

    .venv/bin/python benchmarks/bench_wavelet_dense_interleave.py --sizes small,medium,large --units 4
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
from bench_wavelet_dense_order import regimes_option  # noqa: E402
from bench_wavelet_isa import bound_call, kernel_build, kernel_source  # noqa: E402
from bench_wavelet_setup import write  # noqa: E402

from prt_torch import io, relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, measure_paired_cold  # noqa: E402

WHO = "bench_wavelet_dense_interleave.py"


HELPERS = r"""
/* the interleaved layout's prefetch targets (bench_wavelet_dense_interleave.py): a super-block of ILV_U blocks holds
 * ILV_U / 2 pairs, pair p's lines at 128 p bytes of each term row; the pair k pairs ahead of pair p of super-block s is
 * pair (p + k) % (ILV_U / 2) of super-block s + (p + k) / (ILV_U / 2): ilv_delta its offset in elements from pair p */
static inline i64 ilv_delta(i64 k) {
    const i64 U = ILV_U / 2, p = ilv_par;
    return (p + k) / U * ilv_us + (p + k) % U * 64 - p * 64;
}
/* the VNNI loop's records, one set per pair position p (ilv_rec + p nd): each term's row offset in bytes and its
 * prefetch target PFX steps ahead (in this pair's terms, then the next pairs'), from the pair's first block */
static inline void ilv_records(i64 nd, const i64 *wk) {
    const i64 U = ILV_U / 2, keep = ilv_par;
    for (i64 p = 0; p < U; p++) {
        int32_t *r = (int32_t *)(ilv_rec + p * nd);
        ilv_par = p;
        for (i64 t = 0; t < nd; t++) {
            const i64 tt = t + PFX, k = tt / nd;
            r[2 * t] = (int32_t)(wk[t] * 64 * ILV_U);
            r[2 * t + 1] = (int32_t)(2 * ilv_delta(k) + wk[tt % nd] * 64 * ILV_U);
        }
    }
    ilv_par = keep;
}
"""


def interleaved_source(src: str, u: int) -> str:
    """``src`` (kernels/wavelet.c) reading the dense layout with ``u`` blocks interleaved per term (module docstring)."""
    vnni = "(const int32_t *)ds, (const int32_t *)lw"
    subs = [("dense + v0 * Pd * CT_, BV * CT_, PAIR_ARGS(b, nb, Pd * BV * CT_)",
             f"dense + (v0 / {32 * u}) * Pd * {32 * u} + (v0 % {32 * u}), {u} * BV, "
             f"PAIR_ARGS(b, nb, (ilv_us = {u} * Pd * BV, ilv_par = v0 / 64 % {u // 2}, BV))"),
            ("#define VNNI_ON(T) vq && CO == 3 && CT == 1 && sizeof(T) == 2 && stride == BV",
             HELPERS + f"#define VNNI_ON(T) vq && CO == 3 && CT == 1 && sizeof(T) == 2 && stride == {u} * BV"),
            (f"1, nd, {vnni}", "1, nd, (const int32_t *)(ilv_rec + ilv_par * nd), (const int32_t *)lw"),
            (f"0, nd, {vnni}", "0, nd, (const int32_t *)(ilv_rec + ilv_par * nd), (const int32_t *)lw"),
            ("vnni_records(nd, wk, 2 * pstb_, nbk_ * pstb_ >= PFX_MIN);", "ilv_records(nd, wk);"),
            ("(PFX / nd + 1) * 2 * pstb_ + Pd * 64", f"(PFX / nd + 1) * {u} * pstb_ + Pd * {64 * u}"),
            # the float loop's far prefetch: the same targets (ilv_delta), one line per target and block
            ("    i64 pt_ = PFX, po_ = 0;                                                                                  \\\n"
             "    if (pt_ >= nd) { const i64 u_ = pt_ / nd; pt_ -= u_ * nd; po_ = u_ * (us); }",
             "    i64 pt_ = PFX % nd, pk_ = PFX / nd, po_ = ilv_delta(pk_); (void)(us);"),
            ("if (++pt_ == nd) { pt_ = 0; po_ += (us); }", "if (++pt_ == nd) { pt_ = 0; po_ = ilv_delta(++pk_); }"),
            ("        for (i64 q = 0; q < stride * (i64)sizeof(T); q += 64) {                                              \\\n"
             "            __builtin_prefetch((const char *)(a_ + q));",
             "        for (i64 q = 0; q < BV * CT * (i64)sizeof(T); q += 64) {                                             \\\n"
             "            __builtin_prefetch((const char *)(a_ + q));")]
    for a, b in subs:
        if src.count(a) != 1:
            raise SystemExit(f"{WHO}: kernels/wavelet.c changed: {a[:60]!r} is not there once")
        src = src.replace(a, b)
    return (f"#include <stdint.h>\n#define ILV_U {u}\nstatic int64_t ilv_us, ilv_par; /* the super-block's elements (u x Pd x "
            "BV) and the pair's position in it, set at each block's call (one thread) */\n"
            f"static int64_t ilv_rec[{u // 2} * 8192]; /* the records per pair position (the VNNI loop) */\n" + src)


def interleaved(rl, u: int) -> None:
    """``rl``'s dense layout replaced (for the kernel only: ``_layout``'s dense pointer) by its copy with ``u`` blocks
    interleaved per term, ``[ceil(nb / u), Pd, u, 32]`` int16 (the blocks past the last zero), kept on ``rl``."""
    rl._kernel()
    nb, Pd = rl.dense.shape[0], rl.dense.shape[1]
    nbu = -(-nb // u)
    d = torch.zeros(nbu * u, Pd, 32, dtype=rl.dense.dtype)
    d[:nb] = rl.dense[:, :, 0, :]
    inter = io.hugepage_zeros((nbu, Pd, u, 32), rl.dense.dtype, huge=rl.huge_pages)
    inter.copy_(d.reshape(nbu, u, Pd, 32).permute(0, 2, 1, 3))
    rl._interleaved = inter  # kept alive with the relighter
    rl._layout[12] = inter.data_ptr()  # wavelet_layout's dense pointer


def size_rows(size: str, u: int, lib, ilib, regimes, repeats: int) -> list[str]:
    tr = kernel_transfer(size)
    rl, aa, ri = (relight.WaveletRelighter(tr, threads=1, layouts="both") for _ in range(3))
    if not (rl.TV % (32 * u) == 0 or rl.NT == 1):
        raise SystemExit(f"{WHO}: the tile {rl.TV} is not a multiple of {32 * u} vertices")
    interleaved(ri, u)
    print(f"[interleave] {cpu_label()}: {size} V {rl.V} Pd {rl.Pd} tile {rl.TV}, {u} blocks interleaved; load "
          f"{load():.1f}", flush=True)
    lines = []
    for light, N in (("studio", 10), ("studio", 30), ("studio", 100), ("studio", rl.P), ("sky (sun)", 10),
                     ("sky (sun)", 30), ("sky (sun)", 100), ("sky (sun)", 300), ("sky (sun)", 1000),
                     ("sky (sun)", rl.P)):
        li, lv, _ = rl.light(LIGHTS[light], N, "transport")
        li, lv = li.contiguous(), lv.to(torch.float32).contiguous()
        nd = int((rl.dslot[li] >= 0).sum())
        vnni = None
        for loop, fl in (("VNNI", 0), ("float", relight.WaveletRelighter.FDENSE)):
            o1, o2, o3 = (torch.empty(rl.V, 3) for _ in range(3))
            f1 = bound_call(rl, lib, li, lv, o1, 1, per_vertex=True, flags=fl)
            f2 = bound_call(ri, ilib, li, lv, o2, 1, per_vertex=True, flags=fl)
            f3 = bound_call(aa, lib, li, lv, o3, 1, per_vertex=True, flags=fl)
            for f in (f1, f2, f3):
                f()
            if not (torch.equal(o1, o2) and torch.equal(o1, o3)):
                raise SystemExit(f"{WHO}: {light} N = {N} {loop}: the interleaved call is not the usual layout's bits")
            if fl and torch.equal(o1, vnni):
                raise SystemExit(f"{WHO}: {light} N = {N}: the default call did not take the VNNI loop")
            vnni = o1
            for g in regimes:
                if g == "warm":
                    p = measure_paired(f2, f1, repeats=repeats, warmup=2, clock=time.thread_time)
                    a = measure_paired(f3, f1, repeats=repeats, warmup=2, clock=time.thread_time)
                else:
                    p, a = (measure_paired_cold(f, f1, repeats=2 * repeats - 1, warmup=1, evict_bytes=3 << 20,
                                                clock=time.thread_time, calls=4) for f in (f2, f3))
                n = "all" if N == rl.P else str(N)
                line = (f"| {size} | {light} | {n} | {nd} | {loop} | {g} | {p.peer.median * 1e6:.1f} | "
                        f"**{p.speedup:.3f}** [{p.ratio.q1:.2f}, {p.ratio.q3:.2f}] | {a.speedup:.3f} "
                        f"[{a.ratio.q1:.2f}, {a.ratio.q3:.2f}] | {load():.1f} |")
                lines.append(line)
                print(f"[interleave] {line}", flush=True)
    return lines


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--sizes", default="small,medium,large", help="occluder_over_plane sizes, comma-separated")
    ap.add_argument("--size", default=None, help="one size (the earlier option; --sizes wins when both)")
    ap.add_argument("--units", type=int, default=2, help="blocks interleaved per term: 2, 4, 8 or 16")
    ap.add_argument("--regimes", default="warm,evicted", help="warm and/or evicted")
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--write", default=str(OUT / "wavelet_dense_runs.md"), help="the report ('': print only)")
    args = ap.parse_args()
    raw = args.size if args.size and "--sizes" not in sys.argv else args.sizes
    sizes = [size_choice(s.strip(), WHO) for s in raw.split(",")]
    if args.units not in (2, 4, 8, 16):
        raise SystemExit(f"{WHO}: --units {args.units}; accepted: 2, 4, 8 or 16")
    regimes = regimes_option(args.regimes, WHO)
    u = args.units
    torch.set_num_threads(1)
    src, label = kernel_source(None, WHO)
    ilib = kernel_build(interleaved_source(src, u), "native", WHO)[0]
    lib, flags = kernel_build(src, "native", WHO)
    before = load()
    lines = []
    for s in sizes:
        lines += size_rows(s, u, lib, ilib, regimes, args.repeats)
    head = (f"## {cpu_label()}: {u} blocks interleaved per term (timing prototype), the `native` build, sizes "
            f"{', '.join(sizes)}\n\n"
            f"Kernel {label} ({flags}) and its copy for the interleaved layout (`{WHO}`: `[ceil(V / {32 * u}), Pd, {u}, "
            f"32]` int16); one thread's CPU time, the median of {args.repeats} paired repeats (evicted: "
            f"{2 * args.repeats - 1}, each sample 4 calls after a 3 MB read) [quartiles]; **usual / interleaved** > 1: "
            f"the interleaved layout faster; A/A: the usual layout against a second relighter of it. Loop: the VNNI "
            f"dense loop (the default) or the float loop (`C | FDENSE`); every row's outputs the usual layout's bits "
            f"(checked). Load average {before:.1f} → {load():.1f}. Reproduce: `.venv/bin/python benchmarks/{WHO} "
            f"--sizes {','.join(sizes)} --units {u} --regimes {args.regimes}`.\n\n"
            "| size | light | N | dense terms | loop | regime | usual µs | **usual / interleaved** | A/A | load |\n"
            + "|---" * 10 + "|")
    write(args.write, head + "\n" + "\n".join(lines) + "\n",
          title="# Wavelet kernel: how long a run of adjacent dense lines must be (issue 39)\n\nReproduce: "
                "`.venv/bin/python benchmarks/bench_wavelet_dense_runs.py` and `bench_wavelet_dense_interleave.py` "
                "(module docstrings). One section per CPU, build, sizes and regimes; a run replaces its own.\n")


if __name__ == "__main__":
    main()
