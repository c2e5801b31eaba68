"""The wavelet kernel's 16-lane dense loop against a base revision's (issue 39): ``kernels/wavelet.c`` of the working
tree and of ``--base`` (a git revision; default 69385e0, main before the dense loop took two 32-vertex blocks in
lockstep) compiled as two libraries with this CPU's native flags (the ``wavelet`` library's; on an AVX-512 CPU the
``W16`` dense loop), both bound to one layout of one relighter, timed paired by one thread's CPU time
(``measure_paired(clock=time.thread_time)``: what other processes ran is in neither side). Rows: the studio and sky
lights (transport-weighted terms, RGB: CO = 3) at N = 1, 10, 30, 100, 300, 1000, 2000 and all, the whole call, and at N = 100,
300, 1000 the light's dense terms alone (the loop this work changes, with the set-up and the output pass). Every
output is compared bit for bit with the base build's (``maxdiff`` must be 0: each vertex's terms are added in the
same order) and with the float64 sums of the same stored values (``relight.wavelet_dense``).

Columns: the two medians, **base / test** (median of the per-repeat ratios, quartiles; > 1: the working tree
faster), the working tree's fraction of its streaming-read bound (``timing.read_bound_fn`` of
``WaveletRelighter.bytes_read`` plus the output, paired the same way), its ns per (dense term, 32-vertex block) for
the dense-alone rows (the call's time less the set-up and output, timed as a one-term call of a column no vertex
keeps, over nd x blocks), and with ``--avx2`` the working tree's ``PRT_TORCH_KERNEL_ISA=avx2`` build paired against
it (avx2 / test > 1: the 16-lane build faster). The kernel section's transfer: occluder_over_plane small (``--size medium|large``: the
sizes users relight), R = 32, K = 256, 16 bits, one thread. Writes reports/benchmarks/wavelet_dense16.md (the CPU, flags and load named).

    .venv/bin/python benchmarks/bench_wavelet_dense16.py [--base REV] [--avx2]        (about 2 minutes)
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
from bench_wavelet import BITS, KERNEL_SIZES, LIGHTS, OUT, load, size_choice  # noqa: E402
from bench_wavelet_isa import rl_bytes, bound_call, emit_report, kernel_build, kernel_source  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, read_bound_fn  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TERMS = (1, 10, 30, 100, 300, 1000, 2000)


def build(rev: str | None, zmm_min: int = 0):
    """The ``wavelet`` library compiled from revision ``rev``'s ``prt_torch/kernels/wavelet.c`` (None: the working
    tree's; ``zmm_min`` > 0: with ``#define ZMM_MIN zmm_min`` before it) with the library's own flags
    (bench_wavelet_isa.kernel_source / kernel_build); raises SystemExit with one line when the revision or the
    compiler fails."""
    text = kernel_source(rev, "bench_wavelet_dense16.py: --base")[0]
    if zmm_min:
        text = f"#define ZMM_MIN {zmm_min}LL\n" + text
    return kernel_build(text, "native", "bench_wavelet_dense16.py")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--base", default="69385e0", help="the git revision to pair against (default 69385e0)")
    ap.add_argument("--avx2", action="store_true", help="also pair the working tree's avx2 build (8-lane loop)")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--terms", default="", help="the whole-light rows' N, a comma list of integers >= 1 (default: "
                    + ", ".join(map(str, TERMS)) + " and all, with the dense-alone rows)")
    ap.add_argument("--base-zmm-min", type=int, default=0, help="compile the base with ZMM_MIN set (e.g. --base . "
                    "--base-zmm-min 1000000000: the working tree with every call on the 8-lane loop; 0: its own)")
    ap.add_argument("--write", default=str(OUT / "wavelet_dense16.md"), help="the report ('': print only)")
    ap.add_argument("--size", default=None, help="the kernel section's mesh (occluder_over_plane): " + ", ".join(KERNEL_SIZES)
                    + " (default small)")
    args = ap.parse_args()
    size = size_choice(args.size, "bench_wavelet_dense16.py")
    torch.set_num_threads(1)
    if args.base_zmm_min < 0:
        raise SystemExit(f"bench_wavelet_dense16.py: --base-zmm-min {args.base_zmm_min}; accepted: an integer >= 0 (0: the "
                         "kernel's own ZMM_MIN)")
    try:
        terms = tuple(int(x) for x in args.terms.split(",")) if args.terms else None
    except ValueError:
        terms = (0,)
    if terms is not None and min(terms) < 1:
        raise SystemExit(f"bench_wavelet_dense16.py: --terms {args.terms}; accepted: a comma list of integers >= 1")
    base, flags = build(args.base, args.base_zmm_min)
    test, _ = build(None)
    if not int(test.prt_wavelet_isa()) & 32:
        print("[dense16] warning: this build has no 16-lane dense loop (no AVX-512F): the pair compares 8-lane code",
              flush=True)
    avx2 = relight._wavelet_lib("avx2") if args.avx2 else None
    mesh = builtin("occluder_over_plane", size)
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="both")  # the row-major copy built: both builds read it
    ref_index, ref_vals = rl.reference_rows(0, rl.V)
    alb = rl.albedo[:, :3].double()
    nb = (rl.V + 31) // 32
    before = load()
    # the set-up and output pass alone: one term of a column no vertex keeps (as bench_wavelet_parts.py's 'output')
    empty = torch.nonzero(rl.cls == 0).flatten()[:1].contiguous()
    out0 = torch.empty(rl.V, 3)
    fixed = measure_paired(bound_call(rl, test, empty, torch.ones(3, 1), out0, 1),
                           bound_call(rl, base, empty, torch.ones(3, 1), out0, 1), repeats=args.repeats, warmup=1,
                           clock=time.thread_time).test.median if empty.numel() else 0.0
    rows = []
    cases = [(light, N, part) for light in ("studio", "sky (sun)") for N in (terms or TERMS + (rl.P,)) for part in ("all",)]
    cases += [(light, N, "dense") for light in ("studio", "sky (sun)") for N in (100, 300, 1000) if terms is None]
    for light, N, part in cases:
        li, lv, _ = rl.light(LIGHTS[light], N, "transport")
        lv = lv.to(torch.float32).contiguous()
        if part == "dense":
            keep = rl.dslot[li] >= 0
            li, lv = li[keep], lv[:, keep].contiguous()
        li = li.contiguous()
        nd = int((rl.dslot[li] >= 0).sum())
        o_t, o_b, o_a = torch.empty(rl.V, 3), torch.empty(rl.V, 3), torch.empty(rl.V, 3)
        f_t, f_b = bound_call(rl, test, li, lv, o_t, 1), bound_call(rl, base, li, lv, o_b, 1)
        f_t(), f_b()
        ref = relight.wavelet_dense(ref_vals.double(), ref_index, li, lv.double(), rl.P) * alb
        scale = float(ref.abs().max()) or 1.0
        err = float((o_t.double() - ref).abs().max()) / scale
        same = bool(torch.equal(o_t, o_b))
        p = measure_paired(f_t, f_b, repeats=args.repeats, warmup=1, clock=time.thread_time)
        bound = read_bound_fn(rl_bytes(rl, li), rl.V * 12)
        pb = measure_paired(f_t, bound, repeats=args.repeats, warmup=1, clock=time.thread_time)
        row = {"light": light, "N": N, "part": part, "terms": int(li.numel()), "nd": nd, "test_us": p.test.median * 1e6,
               "base_us": p.peer.median * 1e6, "ratio": p.speedup, "q": [p.ratio.q1, p.ratio.q3],
               "of_read": pb.speedup, "err": err, "same": same, "load": load()}
        if part == "dense" and nd:
            row["ns_tb"] = (p.test.median - fixed) * 1e9 / (nd * nb)
            row["ns_tb_base"] = (p.peer.median - fixed) * 1e9 / (nd * nb)
        if avx2 is not None:
            f_a = bound_call(rl, avx2, li, lv, o_a, 1)
            f_a()
            pa = measure_paired(f_t, f_a, repeats=args.repeats, warmup=1, clock=time.thread_time)
            row.update(avx2_us=pa.peer.median * 1e6, avx2_ratio=pa.speedup, avx2_q=[pa.ratio.q1, pa.ratio.q3],
                       avx2_same=bool(torch.equal(o_t, o_a)))
        rows.append(row)
        print(f"[dense16] {light} N={N} {part} ({row['terms']} terms, {nd} dense): test {row['test_us']:.1f} us, base "
              f"{row['base_us']:.1f} us, base/test {row['ratio']:.3f} [{row['q'][0]:.3f}, {row['q'][1]:.3f}], of read "
              f"bound {row['of_read']:.2f}, same bits {same}, err {err:.1e}"
              + (f", avx2/test {row['avx2_ratio']:.3f}" if avx2 is not None else "") + f", load {row['load']:.1f}",
              flush=True)
    after = load()
    L = ["# Wavelet kernel: the 16-lane dense loop, two 32-vertex blocks in lockstep (issue 39)\n",
         f"{cpu_label()}; load average {before:.1f} → {after:.1f} (a machine shared with other jobs: one thread's CPU "
         f"time, which their load does not enter). Two builds of `kernels/wavelet.c` with the wavelet library's flags "
         f"(`{flags}`): **test** the working tree's, **base** revision `{args.base}`'s"
         + (f" with `ZMM_MIN` {args.base_zmm_min} (every call with fewer (dense term, 32-vertex block) pairs on the "
            "8-lane loop)" if args.base_zmm_min else "") + f", both bound to one layout "
         f"(occluder_over_plane {size}, V = {rl.V}, R = 32, K = 256, {BITS}-bit, {rl.Pd} dense columns, {nb} blocks of "
         f"32 vertices, tiles of {rl.TV}; the row-major copy built), transport-weighted terms, RGB light (CO = 3), one "
         f"thread. Paired by the calling thread's CPU time (`measure_paired(clock=time.thread_time)`, {args.repeats} "
         "repeats): medians per call and **base / test**, the median of the per-repeat ratios [quartiles] (> 1: the "
         "working tree faster); *of read bound*: the test build against a streaming read of the transfer bytes it "
         "touches plus a fill of the output (`timing.read_bound_fn`, paired the same way); *same bits*: test and base "
         "outputs equal bit for bit; error: max |test − float64 sums of the stored values × factor| / max |reference|. "
         f"Dense-alone rows: ns per (dense term, 32-vertex block) after the set-up and output pass ({fixed * 1e6:.1f} µs, "
         "a one-term call of a column no vertex keeps)"
         + (". *avx2 / test*: the working tree's `PRT_TORCH_KERNEL_ISA=avx2` build (the 8-lane loop) paired against "
            "the test build the same way" if avx2 is not None else "")
         + f". Reproduce: `.venv/bin/python benchmarks/bench_wavelet_dense16.py --base {args.base}"
         + (f" --base-zmm-min {args.base_zmm_min}" if args.base_zmm_min else "") + (f" --terms {args.terms}" if args.terms else "")
         + (" --avx2" if avx2 is not None else "") + (f" --size {size}" if size != "small" else "") + "`.\n",
         "| light | N | terms | dense terms | base | test | **base / test** [quartiles] | test of read bound "
         "| ns / (term, block) base → test | same bits | error |" + (" avx2 / test [quartiles] |" if avx2 is not None else "")
         + " load |",
         "|---|---|---|---|---|---|---|---|---|---|---|" + ("---|" if avx2 is not None else "") + "---|"]
    for r in rows:
        terms = "all" if r["part"] == "all" else f"dense alone ({r['terms']})"
        tb = f"{r['ns_tb_base']:.2f} → {r['ns_tb']:.2f}" if "ns_tb" in r else ""
        a = (f" {r['avx2_ratio']:.2f} [{r['avx2_q'][0]:.2f}, {r['avx2_q'][1]:.2f}]"
             f"{'' if r['avx2_same'] else ' ≠ bits'} |" if avx2 is not None else "")
        L.append(f"| {r['light']} | {r['N']} | {terms} | {r['nd']} | {r['base_us']:.1f} µs | {r['test_us']:.1f} µs | "
                 f"**{r['ratio']:.3f}** [{r['q'][0]:.3f}, {r['q'][1]:.3f}] | {r['of_read']:.2f} | {tb} | "
                 f"{'yes' if r['same'] else '**no**'} | {r['err']:.1e} |{a} {r['load']:.1f} |")
    text = "\n".join(L) + "\n"
    emit_report(args.write, text, "dense16")
    if not all(r["same"] for r in rows):
        raise SystemExit("bench_wavelet_dense16.py: the test build's outputs differ from the base build's (see 'same bits')")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
