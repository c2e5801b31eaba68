"""A timing prototype, not a layout the relighter builds (issue 39, the dense slot order's next step): the dense layout
with ``--units`` consecutive 32-vertex blocks interleaved per term (``[ceil(V / (32 u)), Pd, u, 32]`` int16: a term's
line for block 2i + 1 beside block 2i's, so the 128-byte pair the adjacent-line prefetcher pulls is one term's 64
vertices, u = 2), read by ``kernels/wavelet.c`` rewritten for it (three substitutions: each block's address and the
slots' stride, the VNNI loop's stride test, the records' row offsets; u = 4 also the records' unit, which then points
the second pair's prefetches one row off: its figures are not the layout's). Only what the VNNI dense loop reads is
right (16-bit grey transfer, RGB light; the float loop's prefetch targets are not): each row checks that the call took
the VNNI loop and that the outputs equal the working tree's on the usual layout bit for bit (the same sums in the same
order). Paired with the working tree's kernel on the usual layout, one thread's CPU time, warm and evicted (a 3 MB read
before each call), occluder_over_plane ``--size`` (its tiles a multiple of 32 u vertices, or one tile).

    .venv/bin/python benchmarks/bench_wavelet_dense_interleave.py --size medium --units 2
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import LIGHTS, kernel_transfer, load, size_choice  # noqa: E402
from bench_wavelet_isa import bound_call, kernel_build, kernel_source  # noqa: E402

from prt_torch import io, relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, measure_paired_cold  # noqa: E402

WHO = "bench_wavelet_dense_interleave.py"


def interleaved_source(src: str, u: int) -> str:
    """``src`` (kernels/wavelet.c) reading the dense layout with ``u`` blocks interleaved per term (module docstring)."""
    subs = [("dense + v0 * Pd * CT_, BV * CT_, PAIR_ARGS(b, nb, Pd * BV * CT_)",
             f"dense + (v0 / {32 * u}) * Pd * {32 * u} + (v0 % {32 * u}), {u} * BV, PAIR_ARGS(b, nb, BV)"),
            ("#define VNNI_ON(T) vq && CO == 3 && CT == 1 && sizeof(T) == 2 && stride == BV",
             f"#define VNNI_ON(T) vq && CO == 3 && CT == 1 && sizeof(T) == 2 && stride == {u} * BV"),
            ("r[2 * t] = (int32_t)(sl * 64);", f"r[2 * t] = (int32_t)(sl * {64 * u});")]
    if u == 4:
        subs.append(("vnni_records(nd, wk, 2 * pstb_,", "vnni_records(nd, wk, 128,"))
    for a, b in subs:
        if src.count(a) != 1:
            raise SystemExit(f"{WHO}: kernels/wavelet.c changed: {a[:60]!r} is not there once")
        src = src.replace(a, b)
    return src


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="medium")
    ap.add_argument("--units", type=int, default=2, help="blocks interleaved per term: 2 or 4")
    args = ap.parse_args()
    size = size_choice(args.size, WHO)
    if args.units not in (2, 4):
        raise SystemExit(f"{WHO}: --units {args.units}; accepted: 2 or 4")
    u = args.units
    torch.set_num_threads(1)
    src, _ = kernel_source(None, WHO)
    ilib = kernel_build(interleaved_source(src, u), "native", WHO)[0]
    lib = kernel_build(src, "native", WHO)[0]
    tr = kernel_transfer(size)
    rl = relight.WaveletRelighter(tr, threads=1, layouts="both")
    ri = relight.WaveletRelighter(tr, threads=1, layouts="both")
    if not (rl.TV % (32 * u) == 0 or rl.NT == 1):
        raise SystemExit(f"{WHO}: the tile {rl.TV} is not a multiple of {32 * u} vertices")
    ri._kernel()
    nb, Pd = ri.dense.shape[0], ri.dense.shape[1]
    nbu = -(-nb // u)
    d = torch.zeros(nbu * u, Pd, 32, dtype=ri.dense.dtype)
    d[:nb] = ri.dense[:, :, 0, :]
    inter = io.hugepage_zeros((nbu, Pd, u, 32), ri.dense.dtype, huge=ri.huge_pages)
    inter.copy_(d.reshape(nbu, u, Pd, 32).permute(0, 2, 1, 3))
    ri._interleaved = inter  # kept alive with the relighter
    ri._layout[12] = inter.data_ptr()  # wavelet_layout's dense pointer
    print(f"{cpu_label()}: {size} V {rl.V} Pd {Pd} tile {rl.TV}, {u} blocks interleaved; load {load():.1f}", flush=True)
    for light, N in (("studio", 10), ("studio", 30), ("studio", 100), ("studio", rl.P), ("sky (sun)", 10),
                     ("sky (sun)", 30), ("sky (sun)", 100), ("sky (sun)", 300), ("sky (sun)", 1000)):
        li, lv, _ = rl.light(LIGHTS[light], N, "transport")
        li, lv = li.contiguous(), lv.to(torch.float32).contiguous()
        o1, o2, o3 = (torch.empty(rl.V, 3) for _ in range(3))
        f1 = bound_call(rl, lib, li, lv, o1, 1, per_vertex=True)
        f2 = bound_call(ri, ilib, li, lv, o2, 1, per_vertex=True)
        f3 = bound_call(rl, lib, li, lv, o3, 1, per_vertex=True, flags=relight.WaveletRelighter.FDENSE)
        for f in (f1, f2, f3):
            f()
        if not torch.equal(o1, o2) or torch.equal(o1, o3):
            raise SystemExit(f"{WHO}: {light} N = {N}: the interleaved call is not the VNNI loop's bits")
        p = measure_paired(f2, f1, repeats=11, warmup=2, clock=time.thread_time)
        e = measure_paired_cold(f2, f1, repeats=15, warmup=1, evict_bytes=3 << 20, clock=time.thread_time, calls=4)
        print(f"{light} N = {'all' if N == rl.P else N} (dense terms {int((rl.dslot[li] >= 0).sum())}): usual layout "
              f"{p.peer.median * 1e6:.1f} us; usual / interleaved warm {p.speedup:.3f} [{p.ratio.q1:.2f}, {p.ratio.q3:.2f}], "
              f"evicted {e.speedup:.3f} [{e.ratio.q1:.2f}, {e.ratio.q3:.2f}]; same bits; load {load():.1f}", flush=True)


if __name__ == "__main__":
    main()
