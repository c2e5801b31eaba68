"""The wavelet kernel's builds paired on one CPU (issue 39): ``kernels/wavelet.c`` compiled as this CPU's
native build (on an AVX-512 CPU the dense loop on 16 lanes) and as ``PRT_TORCH_KERNEL_ISA=avx2``
(``-mno-avx512f``: the 8-lane AVX2 code an AVX2-only CPU runs), both bound to the same layout of the same
relighter, timed paired by one thread's CPU time (``measure_paired(clock=time.thread_time)``: the time other
processes held the core is in neither side), each N of the kernel section and both environments (studio, sky),
transport-weighted terms, and at N = 300 and 1000 (studio) the light's dense terms alone and its sparse terms alone
(what each build's loops change: the dense loop is the 16-lane one); every output compared with the other
build's and with the float64 sums of the same stored values (``relight.wavelet_dense`` on ``reference_rows``).
Two threads: the same pair by wall clock (fastest tenth of short samples), which the load moves.

The kernel section's transfer: occluder_over_plane small, R = 32, K = 256, 16 bits. ``--builds a,b``: the pair
(default ``native,avx2``; any of native, avx2, avx512, avx512-256 this CPU runs). Writes
reports/benchmarks/wavelet_isa.md (the CPU, both builds' paths and the load named).

    .venv/bin/python benchmarks/bench_wavelet_isa.py          (about a minute)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import ctypes  # noqa: E402
import functools  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT, TERMS, load  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import KERNEL_ISAS, LIBRARIES, compile_library, kernel_isa  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]


def kernel_source(spec: str | None, who: str) -> tuple[str, str]:
    """``(text, label)`` of ``prt_torch/kernels/wavelet.c``: ``spec`` None or ``.`` the working tree, a path ending
    in ``.c``, or a git revision of this repository (label: its short commit). One ``SystemExit`` line naming ``who``
    (the benchmark and its option), the value and what is accepted when it cannot be read. The benchmarks that pair
    two versions of the kernel on one layout (bench_wavelet_colpass / _rowpass / _dense16) read their sources here."""
    if spec in (None, "."):
        return (ROOT / "prt_torch/kernels/wavelet.c").read_text(), "working tree"
    accepted = "accepted: '.', a .c file, a git revision of this repository"
    if spec.endswith(".c"):
        try:
            return Path(spec).read_text(), spec
        except OSError as e:
            raise SystemExit(f"{who} {spec!r}: {e.strerror}; {accepted}") from None
    r = subprocess.run(["git", "-C", str(ROOT), "show", f"{spec}:prt_torch/kernels/wavelet.c"], capture_output=True, text=True)
    if r.returncode:
        raise SystemExit(f"{who} {spec!r}: {r.stderr.strip()}; {accepted}")
    short = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", spec], capture_output=True, text=True).stdout.strip()
    return r.stdout, short


def kernel_build(text: str, isa: str | None, who: str, tag: str = ""):
    """``(library, flags)``: ``text`` (a version of kernels/wavelet.c) compiled as the wavelet library with its own flags
    and ``isa``'s (``_native.KERNEL_ISAS``; None: this process's ``PRT_TORCH_KERNEL_ISA``), ``tag`` appended as a
    comment (a second build of the same code: an A/A control), every entry point typed; cached by the source's hash.
    One ``SystemExit`` line naming ``who`` when it does not compile."""
    flags = list(LIBRARIES["wavelet"][1]) + list(KERNEL_ISAS[isa] if isa is not None else kernel_isa()[1])
    if tag:
        text += f"\n/* {tag} */\n"
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    sig = [vp, i64, vp, vp, i64, vp, vp, i64]
    lib, how = compile_library("wavelet", {"wavelet.c": text}, flags, {
        "prt_wavelet_relight_f32": sig, "prt_wavelet_relight_i8": sig, "prt_wavelet_relight_i16": sig,
        "prt_wavelet_relight_f32_packed": [vp], "prt_wavelet_relight_i8_packed": [vp],
        "prt_wavelet_relight_i16_packed": [vp], "prt_wavelet_isa": []})
    if lib is None:
        raise SystemExit(f"{who}: the wavelet kernel did not compile: {how}")
    return lib, " ".join(flags)


def rl_bytes(rl, li: torch.Tensor) -> int:
    """The bytes a call through :func:`bound_call` (default form) reads: the transfer's
    (``WaveletRelighter.bytes_read(..., factor=False)``) and the ``[V, 3]`` factor it passes (12 bytes per vertex;
    ``bytes_read`` alone counts the relighter's own factor, one float per vertex on a grey albedo)."""
    return rl.bytes_read(li, factor=False) + rl.V * 12


def bound_call(rl, lib, li: torch.Tensor, lv: torch.Tensor, out: torch.Tensor, threads: int, per_vertex: bool = False,
               flags: int = 0):
    """``run()`` relighting ``li``/``lv`` into ``out`` through build ``lib`` on ``rl``'s layout (the packed entry point,
    as ``WaveletRelighter.prepared``); the tensors it addresses are kept alive by the closure. The factor as
    ``[V, CO]`` (``WaveletRelighter._factor``: what every build of the kernel reads), or with ``per_vertex`` in the
    relighter's kernel form (``_kfactor``: ``[V + 4]`` with ``C | F1`` where one per vertex will do; builds from
    0182f3f on). ``flags``: bits or-ed into C (``WaveletRelighter.FDENSE``: the float dense loop in a build with the
    VNNI loop; the builds without it refuse the bit, and the run raises)."""
    rl._kernel()  # the layout (self._layout) exists
    f, Ck = rl._kfactor(lv.shape[0], True) if per_vertex else (rl._factor(lv.shape[0], True), lv.shape[0])
    Ck |= flags
    name = {torch.int8: "i8", torch.int16: "i16"}.get(rl.bvals.dtype, "f32")
    args = torch.tensor([rl._layout.data_ptr(), li.numel(), li.data_ptr(), lv.data_ptr(), Ck, f.data_ptr(),
                         out.data_ptr(), threads], dtype=torch.int64)
    fn = functools.partial(getattr(lib, f"prt_wavelet_relight_{name}_packed"), args.data_ptr())
    held = (li, lv, f, out, args)

    def run():
        st = fn()
        if st:
            raise RuntimeError(f"prt_wavelet_relight_{name}_packed returned {st}")
        return held[3]
    return run


def emit_report(write: str | None, text: str, tag: str, payload: dict | None = None) -> None:
    """A benchmark's report: written to ``write`` (and ``payload`` as JSON beside it, ``.json``), each through a
    temporary file renamed into place (``io.atomic_write_text``), or printed when ``write`` is empty."""
    if write:
        atomic_write_text(write, text)
        if payload is not None:
            atomic_write_text(str(Path(write).with_suffix(".json")), json.dumps(payload, indent=1))
        print(f"[{tag}] wrote {write}", flush=True)
    else:
        print(text)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--builds", default="native,avx2", help="two kernel builds, test first: native, avx2, avx512, avx512-256")
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--write", default=str(OUT / "wavelet_isa.md"), help="the report ('' : print only)")
    args = ap.parse_args()
    builds = [b.strip() for b in args.builds.split(",")]
    if len(builds) != 2:
        raise SystemExit(f"bench_wavelet_isa.py: --builds {args.builds!r}; accepted: two builds, e.g. native,avx2")
    try:
        paths = [relight.wavelet_kernel_path(b) for b in builds]
    except ValueError as e:
        raise SystemExit(f"bench_wavelet_isa.py: --builds {args.builds!r}: {e}") from None
    libs = [relight._wavelet_lib(b) for b in builds]
    if any(lib is None for lib in libs):
        raise SystemExit(f"bench_wavelet_isa.py: a build did not compile: {paths}")
    torch.set_num_threads(1)
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="both")  # the row-major copy built: both builds read it
    ref_index, ref_vals = rl.reference_rows(0, rl.V)  # the values relit with (scale applied), float32
    alb = rl.albedo[:, :3].double()
    before = load()
    rows = []
    cases = [(light, N, "all") for light in ("studio", "sky (sun)") for N in TERMS + [rl.P]]
    cases[cases.index(("studio", 1000, "all")) + 1:1] = [("studio", N, part) for N in (300, 1000) for part in ("dense", "sparse")]
    for light, N, part in cases:
        li, lv, _ = rl.light(LIGHTS[light], N, "transport")
        lv = lv.to(torch.float32).contiguous()
        if part != "all":  # the light's dense (or sparse) terms alone
            keep = (rl.dslot[li] >= 0) == (part == "dense")
            li, lv = li[keep], lv[:, keep].contiguous()
        li = li.contiguous()
        outs = [torch.empty(rl.V, 3) for _ in builds]
        one = [bound_call(rl, lib, li, lv, o, 1) for lib, o in zip(libs, outs)]
        two = [bound_call(rl, lib, li, lv, o, 2) for lib, o in zip(libs, outs)]
        for f in one:
            f()
        ref = relight.wavelet_dense(ref_vals.double(), ref_index, li, lv.double(), rl.P) * alb
        scale = float(ref.abs().max()) or 1.0
        err = [float((o.double() - ref).abs().max()) / scale for o in outs]
        diff = float((outs[0] - outs[1]).abs().max()) / scale
        p1 = measure_paired(one[0], one[1], repeats=args.repeats, warmup=1, clock=time.thread_time)
        torch.set_num_threads(2)
        p2 = measure_paired(two[0], two[1], repeats=7, warmup=1, floor_pairs=40)
        torch.set_num_threads(1)
        row = {"light": light, "N": N, "part": part, "terms": int(li.numel()), "us": [p1.test.median * 1e6, p1.peer.median * 1e6],
               "ratio": p1.speedup, "q": [p1.ratio.q1, p1.ratio.q3], "ratio_2": p2.speedup, "trusted_2": bool(p2.contention.get("trusted")),
               "err": err, "diff": diff, "load": load()}
        rows.append(row)
        print(f"[wavelet_isa] {light} N={N} {part}: {builds[1]} {row['us'][1]:.1f} us, {builds[0]} {row['us'][0]:.1f} us, "
              f"{builds[1]}/{builds[0]} {row['ratio']:.3f} [{row['q'][0]:.3f}, {row['q'][1]:.3f}], 2 threads "
              f"{row['ratio_2']:.3f}, max |err|/max|ref| {err[0]:.1e} / {err[1]:.1e}, between builds {diff:.1e}, "
              f"load {row['load']:.1f}", flush=True)
    after = load()
    a, b = builds
    L = [f"# Wavelet kernel: the `{a}` and `{b}` builds paired (issue 39)\n",
         f"{cpu_label()}; load average {before:.1f} → {after:.1f} (the machine shared with other jobs). "
         f"Builds of `kernels/wavelet.c` (`PRT_TORCH_KERNEL_ISA`, `relight.wavelet_kernel_path`): **{a}**: {paths[0]['path']} "
         f"(`{paths[0]['flags']}`); **{b}**: {paths[1]['path']} (`{paths[1]['flags']}`). Both bound to one layout "
         f"(occluder_over_plane small, V = {rl.V}, R = 32, K = 256, {BITS}-bit, {rl.Pd} dense columns, tiles of {rl.TV}; "
         "the row-major copy built), transport-weighted terms, RGB light. **One thread**: paired by the calling thread's "
         f"CPU time (`measure_paired(clock=time.thread_time)`, {args.repeats} repeats): medians per call and the median "
         f"of the per-repeat ratios {b} / {a} [quartiles] (> 1: {a} faster). **Two threads**: the same pair by wall clock "
         "(fastest tenth of 40 pairs of short samples; ⚠: contention flagged). Error: max |output − float64 sums of the "
         "stored values × factor| / max |reference| (`relight.wavelet_dense`). Reproduce: "
         f"`.venv/bin/python benchmarks/bench_wavelet_isa.py --builds {a},{b}`.\n",
         f"| light | N | terms | {a} (1 thr CPU) | {b} (1 thr CPU) | **{b} / {a}, 1 thr** [quartiles] | {b} / {a}, 2 threads "
         f"| error {a} | error {b} | {a} vs {b} | load |",
         "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        terms = "all" if r["part"] == "all" else f"{r['part']} alone ({r['terms']})"
        L.append(f"| {r['light']} | {r['N']} | {terms} | {r['us'][0]:.1f} µs | {r['us'][1]:.1f} µs | **{r['ratio']:.2f}** "
                 f"[{r['q'][0]:.2f}, {r['q'][1]:.2f}] | {r['ratio_2']:.2f}{'' if r['trusted_2'] else ' ⚠'} | {r['err'][0]:.1e} | "
                 f"{r['err'][1]:.1e} | {r['diff']:.1e} | {r['load']:.1f} |")
    text = "\n".join(L) + "\n"
    if args.write:
        atomic_write_text(Path(args.write), text)
        print(f"[wavelet_isa] wrote {args.write}", flush=True)
    else:
        print(text)


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "2")
    main()
