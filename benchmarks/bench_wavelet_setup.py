"""Every microsecond of a wavelet relight call, by part (issue 39): ``kernels/wavelet.c`` compiled as cumulative probes —
the same source with a return (or an empty tile) inserted after each step of the call — each bound to the layout as
``WaveletRelighter.prepared`` binds the kernel (the packed entry point: one ctypes argument) and paired with the whole
kernel by one thread's CPU time (``measure_paired(clock=time.thread_time)``, median of the repeats); a part's time is
the difference of two consecutive probes' medians, so the parts add up to the call by construction.

Probes, in call order (each includes every step before it; the light's closing zeroing runs in every probe past
the gather, so the light table is zero again between calls, as the kernel leaves it):

  1. call: ``return 0`` on entry — Python's loop and the ``run()`` closure, ctypes, the packed entry point;
  2. + checks: the light's channel count, the index check over N, the grey-light test;
  3. + closing zeroing: the light table's N columns zeroed (what the kernel does at its end);
  4. + gather: the P marks cleared, the light gathered per column, the sparse blocks counted;
  5. + dense listing: the row/column choice and the dense terms listed (N > SMALL_N: the Pd slots' pass);
  6. + sparse listing: the sparse terms listed (N > SMALL_N: the scan of the P marks) — the set-up;
  7. + OpenMP region: the tile loop entered (one thread: ``if(nt > 1)`` false, still a libgomp region), the tiles'
     pointers formed, nothing done;
  8. + scratch zeroing: each tile's accumulators zeroed (column-major lights; the AVX-512 build's scratch is zero
     between calls: nothing, or the tile's marks set when the light marks no blocks — kernels/wavelet.c, SCRATCH_ZERO);
  9. + sparse pass: the column-major pass into the scratch (no dense block; the AVX-512 build then drops the marked
     blocks' accumulators unread, SCRATCH_DROP, so the scratch is zero again for the next call);
  10. + output pass: every dense block called with no dense term — the scratch's sums (or, row-major lights, none)
      times the factor, written once (the AVX-512 build: the marked blocks' sums added back and re-zeroed);
  11. + row-major pass: the same with the row-major entries (row-major lights only; a column-major light's probe 11
      is the same work as 10, so its difference is the probes' code-placement noise, reported as such);
  12. + dense terms: the whole kernel.

Floors per part: the dense terms' instruction floor (dense (term, 32-vertex block) steps × the loop's instruction mix
from L1 on this CPU — the 16-lane term 5.78 cycles, the 8-lane AVX2 term 8.31, ``wavelet_dense16_micro.md`` —, at
the clock measured here: a chain of dependent multiplies, ``bench_wavelet_floor_micro.clock_ghz``), and the same loop
re-run from the caches (probe ``dense twice``: each tile's dense blocks relit twice, the second pass right after the
first: its extra time; the sparse scratch added in the second pass only; likewise probe ``sparse twice``, 14: probe 9
with each tile's column-major pass run twice, its extra time the pass from the caches — timing only, the sums doubled),
the sparse pass's (the light's 8-vertex blocks × the column-major pass alone in a tight loop:
4.5 cycles per block for the AVX-512 build's three-per-step loop, 4.9 for the one-block loop, ``wavelet_colpass.md``),
the output's (its factors read and its values written, 24 V bytes, at the rate of the call's own streaming read:
``timing.read_bound_fn`` of the call's bytes, paired here; ``read_bound_fn`` of 24 V bytes alone is mostly torch's
fixed cost, ~4 µs); the set-up's floor in the issue's bound is zero (the bound counts transfer bytes and the output only).
The call against its bound: ``timing.read_bound_fn`` of :meth:`WaveletRelighter.bytes_read` + the output, paired.

Lights (transport-weighted): studio at N = 100 and 300 (its 292 nonzero terms: N = 300 … all relight the same), sky at
N = 100, 300, 1000 and all; the kernel section's transfer
(occluder_over_plane small, R = 32, K = 256, 16 bits). ``--isa``: the build (``native`` default; ``avx2`` the 8-lane
AVX2 code on an AVX-512 CPU); ``--source REV``: the kernel of a git revision (or a .c file) instead of the working
tree's. Writes the CPU's, build's and source's section of reports/benchmarks/wavelet_setup.md (a run
replaces its own section and keeps the others).

``--pair REV``: instead, the working tree's kernel paired with REV's (a git revision, or a .c file:
``bench_wavelet_isa.kernel_source``), both compiled with the same flags (``--isa``) and bound to one layout, one
thread's CPU time, studio and sky at N = 10, 100, 300, 1000, 2000 and all, with an A/A control (REV against a
second build of itself); every output compared bit for bit (a difference stops the run).

    .venv/bin/python benchmarks/bench_wavelet_setup.py [--isa native|avx2]     (about 2 minutes)
``--variant NAME`` (with ``--pair REV``): instead of the working tree, REV's kernel rewritten as one of
:data:`VARIANTS` (what was measured and not kept: the dense prefetch distance, the tiles reversed every other call,
the OpenMP region's pragma removed, its shared variables copied in).

    .venv/bin/python benchmarks/bench_wavelet_setup.py --pair main [--isa native|avx2]     (about a minute)
    .venv/bin/python benchmarks/bench_wavelet_setup.py --pair main --variant 'tiles reversed'

``--tsc A,B`` (x86): instead, the parts timed in place in one build — the working tree's kernel with ``rdtsc`` read
around each tile's sparse pass, each 32-vertex block's ``dense_block`` call (its dense terms, the scratch added back,
the output) and the tile loop (from the light's quantisation, VNNI_SETUP, to the tiles' end), and from the gather to
the call's end (Python and ctypes outside); in the DVNNI build also VNNI_SETUP's parts (``vnni_quantise``'s chunk
pass, its flush groups, its guard test with the int16 lights' write, and ``vnni_records``) — on two relighters of the
same transfer with tiles A and B (vertices), and an A/A control (a second relighter of tile A: placement); the calls
alternated A, B, B, A, ... (``--tsc-pairs`` pairs, 50 untimed first; ``--tsc-block K``: K timed calls of one
relighter, after an untimed one, then K of the other, the pairs taken in order), per pair the difference B − A of each
part in TSC ticks (median [quartiles]), converted to µs at the TSC's rate (measured against CLOCK_MONOTONIC). Wall
time inside the call: a pair preempted in between is in the quartiles, not the median. Alternated per call, two
relighters whose working sets outgrow the L2 together (at small, sky N >= 300: 1.1 MB of dense lines each) find their
lines in L2 or L3 by turns, and the differences are bimodal (quartiles of +-10 us): ``--tsc-block 100`` there. The
``rdtsc`` pairs themselves cost ~1 µs of a 13 µs call. Probes compiled as separate builds (above) charge a part with
whatever the next probe's code changes elsewhere (placement, and the caches' state the skipped work leaves); this
split times one build.

    .venv/bin/python benchmarks/bench_wavelet_setup.py --tsc 2272,1152 --lights studio:300,studio:100,sky:100
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import ctypes  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import LIGHTS, OUT, kernel_transfer, load, size_choice  # noqa: E402
from bench_wavelet_floor_micro import SRC as FLOOR_SRC  # noqa: E402
from bench_wavelet_isa import rl_bytes, bound_call, kernel_build, kernel_source  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, read_bound_fn  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

WHO = "bench_wavelet_setup.py"
#: the light table's closing zeroing, as the kernel ends (every probe past the gather runs it)
ZERO = "for (i64 n_ = 0; n_ < N; n_++) memset(L->lp + 4 * sel[n_], 0, 4 * sizeof(float));"
#: (line of kernels/wavelet.c, probe's statement inserted before it)
CUTS = (("    if (C < 1 || C > 4 || (CT == 3 && C != 1 && C != 3)) return 1;", "if (PROBE == 1) return 0;"),
        ("    const i64 CO = grey ? 1 : C > CT ? C : CT;", "if (PROBE == 2) return 0;"),
        ("    const i64 CO = grey ? 1 : C > CT ? C : CT;", "if (PROBE == 3) { " + ZERO + " return 0; }"),
        ("    const int rows = sb && L->NR", "if (PROBE == 4) { " + ZERO + " return 0; }"),
        ("    i64 *sw = wk + Pd;", "if (PROBE == 5) { " + ZERO + " return 0; }"),
        ("    const T *rvals = (const T *)L->rvals;", "if (PROBE == 6) { " + ZERO + " return 0; }"),
        ("        SCRATCH_ZERO", "if (PROBE == 7) continue;"),
        ("        if (CT == 3) { TILE_CASE(T, 3, 3, 3) }", "if (PROBE == 8) continue;"))
#: (text, replacement): probes 9-11 inside TILE_CASE, ``dense twice`` (PROBE 13) and ``sparse twice`` (PROBE 14)
SUBS = (("    for (i64 b = 0; b < nb; b++) {                                                                           \\",
         "    for (i64 b = 0; b < (PROBE == 9 || PROBE == 14 ? nb : 0); b++) { SCRATCH_DROP(b) } \\\n"
         "    for (int r_ = 0; r_ < (PROBE == 13 ? 2 : 1); r_++) for (i64 b = 0; b < (PROBE == 9 || PROBE == 14 ? 0 : nb); b++) { \\"),
        # sparse twice: probe 9 with each tile's column-major pass run twice, the second right after the first (its
        # sums doubled: timing only, the output is not compared)
        ("    if (ns && !rows) sparse_tile_##T(", "    for (int s_ = 0; s_ < (PROBE == 14 ? 2 : 1); s_++) if (ns && !rows) sparse_tile_##T("),
        ("        dense_block_##T(CT_, CO_, OC_, nd, wk,", "        dense_block_##T(CT_, CO_, OC_, PROBE == 10 || PROBE == 11 ? 0 : nd, wk,"),
        ("rows ? lp : NULL, nv,", "rows && PROBE != 10 ? lp : NULL, nv,"),
        # dense twice: the sparse scratch added in the second pass only (the AVX-512 build's add-back clears it)
        ("ACC_ARGS(b, ns && !rows)", "ACC_ARGS(b, ns && !rows && !(PROBE == 13 && r_ == 0))"))
PARTS = ("Python → C call", "checks (C, indices, grey)", "light table's closing zeroing", "gather (marks, light per column)",
         "dense listing", "sparse listing", "OpenMP region (1 thread) + tiles", "scratch zeroing", "sparse pass (column-major)",
         "output pass", "row-major pass", "dense terms")
#: instruction floors in cycles (module docstring): dense per (term, 32-vertex block), sparse per 8-vertex block
FLOORS = {True: (5.78, 4.5), False: (8.31, 4.9)}


#: the tile loop's pragma in kernels/wavelet.c, and the tile and 32-vertex-block loops' heads, as the variants find them
PRAGMA = '_Pragma("omp parallel for schedule(static) num_threads(nt) if(nt > 1)")'
TILES = "    for (i64 t = 0; t < NT; t++) {"
SHARED = "nd, ns, wk, lw, sw, sl, lp, rows, grey, CO, dense, bvals, rvals, f, out, L, V, TV, P, CT, Pd, NT"


def _tiles_reversed(text: str) -> str:
    """Every other call takes the tiles in reverse order (a static toggle: an experiment, not thread-safe across
    layouts), so that the tile relit last in the previous call, the most recently cached, is relit first."""
    text = text.replace("    " + PRAGMA, "    static int flip_st_; const int flip_ = (flip_st_ ^= 1); (void)flip_; \\\n    " + PRAGMA)
    return text.replace(TILES, "    for (i64 t_ = 0; t_ < NT; t_++) { const i64 t = flip_ ? NT - 1 - t_ : t_;")


#: name -> (what must be in the source, rewrite of the source) for ``--variant``
VARIANTS = {
    "dense prefetch 12": ("#define PF 6", lambda s: "#define PF 12\n" + s),
    "dense prefetch 24": ("#define PF 6", lambda s: "#define PF 24\n" + s),
    "dense prefetch 40": ("#define PF 6", lambda s: "#define PF 40\n" + s),
    "tiles reversed": (TILES, _tiles_reversed),
    "no OpenMP pragma": (PRAGMA, lambda s: s.replace("    " + PRAGMA + "                                 \\\n", "", 1)),
    "firstprivate": (PRAGMA, lambda s: s.replace(PRAGMA, PRAGMA[:-2] + f" firstprivate({SHARED})\")", 1)),
    # the column-major pass's knobs (kernels/wavelet.c: SP_PFR, SP_PFL, SP_PFS; AVX-512 builds only)
    "sparse range prefetch off": ("SP_RANGE_PF", lambda s: "#define SP_PFR 0\n" + s),
    "sparse range prefetch 1": ("SP_RANGE_PF", lambda s: "#define SP_PFR 1\n" + s),
    "sparse range prefetch 2": ("SP_RANGE_PF", lambda s: "#define SP_PFR 2\n" + s),
    "sparse range prefetch 4": ("SP_RANGE_PF", lambda s: "#define SP_PFR 4\n" + s),
    "sparse range prefetch 2, 4 lines": ("SP_RANGE_PF", lambda s: "#define SP_PFR 2\n#define SP_PFL 4\n" + s),
    "sparse range prefetch 2, bounds 6": ("SP_RANGE_PF", lambda s: "#define SP_PFT 6\n" + s),
    "sparse range prefetch 2, bounds 12": ("SP_RANGE_PF", lambda s: "#define SP_PFT 12\n" + s),
    "scratch prefetch": ("SP_SCRATCH_PF", lambda s: "#define SP_PFS 8\n" + s),
    "scratch prefetch always": ("SP_SCRATCH_PF", lambda s: "#define SP_PFS 0\n" + s),
    "scratch prefetch + range prefetch 2": ("SP_SCRATCH_PF", lambda s: "#define SP_PFS 8\n#define SP_PFR 2\n" + s),
}


def light_list(spec: str | None) -> list[tuple[str, int | None]]:
    """``--lights`` as ``[(light, N)]`` (N None: all terms); one ``SystemExit`` line naming the value when it is not
    a comma-separated list of LIGHT:N with LIGHT studio or sky and N a positive count or 'all'."""
    spec = spec or "studio:100,studio:300,sky:100,sky:300,sky:1000,sky:all"
    names, out = {"studio": "studio", "sky": "sky (sun)"}, []
    for item in spec.split(","):
        light, _, n = item.strip().partition(":")
        if light not in names or not (n == "all" or (n.isdigit() and int(n) > 0)):
            raise SystemExit(f"{WHO}: --lights {item.strip()!r}: not LIGHT:N; accepted: LIGHT studio or sky, N a positive "
                             "count or 'all', comma-separated (studio:300,sky:30)")
        out.append((names[light], None if n == "all" else int(n)))
    return out


def probe_source(text: str, k: int) -> str:
    """``text`` (kernels/wavelet.c) as probe ``k`` (1-11, 13: module docstring; 12: the kernel itself)."""
    for old, ins in CUTS:
        if old not in text:
            raise SystemExit(f"{WHO}: kernels/wavelet.c changed: the probe's line {old.strip()!r} is gone")
        # every occurrence: the term lists are a macro with one form per build (LIST_TERMS: the AVX-512 build's one scan,
        # the 8-lane builds' two passes), and the probe after the dense listing belongs in whichever is compiled
        text = text.replace(old, "    " + ins + " \\\n" + old)
    for old, new in SUBS:
        if old not in text:
            raise SystemExit(f"{WHO}: kernels/wavelet.c changed: the probe's text {old.strip()!r} is gone")
        text = text.replace(old, new, 1)
    return f"#define PROBE {k}\n" + text


def clock_ghz() -> float:
    """This core's clock by a chain of dependent multiplies (bench_wavelet_floor_micro's), GHz."""
    lib, how = compile_library("wavelet_floor_micro", FLOOR_SRC, ["-O2", "-shared", "-fPIC", "-std=c99"], {})
    if lib is None:
        raise SystemExit(f"{WHO}: no compiler: {how}")
    lib.clock_ghz.restype = ctypes.c_double
    return lib.clock_ghz()


def section(rows: list[dict], head: str) -> list[str]:
    L = [head, "| light | N | part | µs | of the call | floor µs | **of its floor** |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        n = "all" if r["N"] == r["P"] else r["N"]
        for name, us, fl in r["parts"]:
            of = f"**{fl / us:.2f}**" if fl and us > 0 else "—"
            L.append(f"| {r['light']} | {n} | {name} | {us:.2f} | {us / r['call']:.3f} | {fl:.1f} | {of} |" if fl else
                     f"| {r['light']} | {n} | {name} | {us:.2f} | {us / r['call']:.3f} | — | — |")
        L.append(f"| {r['light']} | {n} | **the call** | **{r['call']:.1f}** | 1 | read bound {r['read']:.1f} | "
                 f"**{r['read'] / r['call']:.2f}** |")
    return L


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--isa", default="native", help="the kernel build: native (default), avx2, avx512, avx512-256")
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--write", default=str(OUT / "wavelet_setup.md"), help="the report ('': print only)")
    ap.add_argument("--source", default=".", help="the kernel accounted: '.' the working tree, a git revision or a .c file")
    ap.add_argument("--pair", default=None, help="pair the working tree's kernel with this revision's (or .c file's)")
    ap.add_argument("--variant", default=None, help=f"with --pair: REV's kernel rewritten, one of {sorted(VARIANTS)}")
    ap.add_argument("--size", default=None, help="section 7's mesh size: small (default), medium, large")
    ap.add_argument("--tile", type=int, default=None, help="the layout's tile (vertices, a multiple of 32; default the "
                    "relighter's at one thread: the vertices up to 4096, WaveletRelighter._tile)")
    ap.add_argument("--lights", default=None, help="the probes' lights as LIGHT:N pairs, comma-separated (LIGHT studio or "
                    "sky, N a count or 'all'; default studio:100,studio:300,sky:100,sky:300,sky:1000,sky:all)")
    ap.add_argument("--tsc", default=None, help="A,B: the parts timed in place by rdtsc on relighters of tiles A and B "
                    "(vertices), calls alternated, with an A/A control (module docstring)")
    ap.add_argument("--tsc-pairs", type=int, default=3000, help="with --tsc: the pairs of calls per light")
    ap.add_argument("--tsc-block", type=int, default=1, help="with --tsc: calls of one relighter in a row before the "
                    "other's (1: alternated per call; more where the two relighters' working sets outgrow the L2 together)")
    args = ap.parse_args()
    args.size = size_choice(args.size, WHO)
    args.lights = light_list(args.lights)
    if args.tsc is not None:
        tl = args.tsc.split(",")
        if len(tl) != 2 or not all(x.strip().isdigit() and int(x) >= 32 and int(x) % 32 == 0 for x in tl):
            raise SystemExit(f"{WHO}: --tsc {args.tsc!r}; accepted: two tiles A,B, each a multiple of 32 (vertices)")
        if args.tsc_pairs < 10:
            raise SystemExit(f"{WHO}: --tsc-pairs {args.tsc_pairs}; accepted: at least 10")
        if args.tsc_block < 1:
            raise SystemExit(f"{WHO}: --tsc-block {args.tsc_block}; accepted: at least 1")
        return write(args.write, tsc_split(args, [int(x) for x in tl]))
    if args.tile is not None and (args.tile < 32 or args.tile % 32):
        raise SystemExit(f"{WHO}: --tile {args.tile}; accepted: a multiple of 32, at least 32")
    if args.variant is not None and (args.variant not in VARIANTS or not args.pair):
        raise SystemExit(f"{WHO}: --variant {args.variant!r}; accepted: one of {sorted(VARIANTS)}, with --pair REV")
    if args.pair:
        return write(args.write, pair(args))
    torch.set_num_threads(1)
    try:
        path = relight.wavelet_kernel_path(args.isa)
    except ValueError as e:
        raise SystemExit(f"{WHO}: --isa {args.isa!r}: {e}") from None
    src, label = kernel_source(args.source, f"{WHO} --source")
    libs = {k: kernel_build(probe_source(src, k), args.isa, WHO)[0] for k in (*range(1, 12), 13, 14)}
    libs[12] = kernel_build(src, args.isa, WHO)[0]
    w16 = bool(path.get("w16"))
    dense_cyc, sparse_cyc = FLOORS[w16]
    rl = relight.WaveletRelighter(kernel_transfer(args.size), threads=1, layouts="both", tile=args.tile)
    ghz = [clock_ghz()]
    before = load()
    rows = []
    for light, N in args.lights:
        N = rl.P if N is None else N
        if True:
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            lv = lv.to(torch.float32).contiguous()
            li = li.contiguous()
            out = torch.empty(rl.V, 3)
            calls = {k: bound_call(rl, lib, li, lv, out, 1) for k, lib in libs.items()}
            full = calls[12]
            full()
            ref = out.clone()
            calls[13]()
            if not torch.equal(out, ref):
                raise SystemExit(f"{WHO}: the 'dense twice' probe changed the output ({light}, N = {N})")
            d = rl.dslot[li] >= 0
            s = li[~d]
            s = s[rl.nnz[s] > 0]
            sb = int(rl.bcount[:, s].sum())
            rows_pass = rl._takes_rows(sb, rl.NB, rl._row_permille(rl.row_min, True))
            t, peers = {}, []
            for k in (*range(1, 12), 13, 14):
                p = measure_paired(calls[k], full, repeats=args.repeats, warmup=1, clock=time.thread_time)
                t[k] = p.test.median * 1e6
                peers.append(p.peer.median * 1e6)
            t[12] = sum(peers) / len(peers)
            rb = measure_paired(read_bound_fn(rl_bytes(rl, li), rl.V * 12), full, repeats=args.repeats, warmup=1,
                                clock=time.thread_time)
            g = ghz[0]
            steps = int(d.sum()) * rl.dense.shape[0]
            read_us = rb.test.median * 1e6
            rate = (rl_bytes(rl, li) + rl.V * 12) / read_us  # bytes per µs of the streaming read at this size
            floors = {9: 0.0 if rows_pass else sb * sparse_cyc / g / 1e3, 10: rl.V * 24 / rate,
                      11: rl.NB * 2.6 / g / 1e3 if rows_pass else 0.0, 12: steps * dense_cyc / g / 1e3}
            parts = [(PARTS[0], t[1], 0.0)]
            for k in range(2, 13):
                name = PARTS[k - 1]
                if k == 11 and not rows_pass:
                    name = "(no row-major pass: the probes' code-placement noise)"
                parts.append((name, t[k] - t[k - 1], floors.get(k, 0.0)))
            hot = t[13] - t[12]
            parts.append(("  the dense terms and the row-major pass re-run from the caches (dense twice)" if rows_pass else
                          "  the dense terms re-run from the caches (dense twice)", hot, floors[12] + floors[11]))
            if not rows_pass:
                parts.append(("  the sparse pass re-run from the caches (sparse twice)", t[14] - t[9], floors[9]))
            row = {"light": light, "N": N, "P": rl.P, "call": t[12], "read": read_us, "parts": parts,
                   "dense": int(d.sum()), "sparse": int(s.numel()), "blocks": sb, "rows": rows_pass, "load": load()}
            rows.append(row)
            print(f"[wavelet_setup] {light} N={N}: dense {row['dense']} sparse {row['sparse']} blocks {sb} call "
                  f"{t[12]:.1f} us, read bound {row['read']:.1f}; " +
                  ", ".join(f"{n} {u:.2f}" for n, u, _ in parts), flush=True)
    ghz.append(clock_ghz())
    after = load()
    counts = "; ".join(f"{r['light']} N = {'all' if r['N'] == r['P'] else r['N']}: {r['dense']} dense terms, {r['sparse']} "
                       f"sparse ({r['blocks']} blocks{', row-major' if r['rows'] else ''})" for r in rows)
    size = "" if args.size == "small" else f", {args.size} (V = {rl.V})"
    head = (f"## {cpu_label()}: the `{args.isa}` build, kernel {label}{size} ({path['path']})\n\n"
            f"Clock {ghz[0]:.2f} / {ghz[1]:.2f} GHz (before / after: dependent multiplies); one thread's CPU time, each probe "
            f"the median of {args.repeats} samples paired with the whole kernel; load average {before:.1f} → {after:.1f} "
            f"(a shared machine). Floors: dense {dense_cyc} cycles per (term, 32-vertex block), "
            f"sparse {sparse_cyc} per 8-vertex block (module docstring), row-major 2.6 per entry "
            "(`wavelet_rowpass.md`, assembly from L1), output: its 24 V bytes at the rate of the call's streaming read "
            f"(module docstring); **of its floor**: floor / part. Per light and N: {counts}.\n")
    write(args.write, "\n".join(section(rows, head)) + "\n")


def write(dest: str, text: str, title: str | None = None) -> None:
    """``text`` (a section: its first line, ``## ...``, names the CPU, the build and what it measures) into the report
    ``dest``, replacing the section of the same first line and keeping the others ('' : printed only); ``title``: the
    report's head when it is new (default: this benchmark's)."""
    if not dest:
        print(text)
        return
    dest = Path(dest)
    title = title or "# Wavelet kernel: every microsecond of a relight call, by part (issue 39)\n\n" \
            "Reproduce: `.venv/bin/python benchmarks/bench_wavelet_setup.py [--isa native|avx2] [--pair REV]` (module " \
            "docstring: the probes, the floors, the pairing). One section per CPU, build and measurement; a run replaces its own.\n"
    old = dest.read_text() if dest.exists() else title
    key = text.split("\n")[0]
    chunks = old.split("\n## ")
    kept = [c for c in chunks[1:] if ("## " + c).split("\n")[0] != key]
    atomic_write_text(dest, chunks[0].rstrip("\n") + "\n\n" + "".join("## " + c.rstrip("\n") + "\n\n" for c in kept) + text)
    print(f"[wavelet_setup] wrote {dest}", flush=True)


def pair(args) -> str:
    """The ``--pair`` section (module docstring)."""
    torch.set_num_threads(1)
    try:
        path = relight.wavelet_kernel_path(args.isa)
    except ValueError as e:
        raise SystemExit(f"{WHO}: --isa {args.isa!r}: {e}") from None
    tree, name = kernel_source(None, WHO)
    test = "tree"
    base, label = kernel_source(args.pair, f"{WHO} --pair")
    if args.variant:
        need, rewrite = VARIANTS[args.variant]
        if need not in base:
            raise SystemExit(f"{WHO}: --variant {args.variant!r} no longer applies to {label}'s kernel ({need.strip()!r} is gone)")
        tree, name = rewrite(base), f"{label} as '{args.variant}'"
    test = "variant" if args.variant else "tree"
    libs = {"tree": kernel_build(tree, args.isa, WHO)[0], "base": kernel_build(base, args.isa, WHO)[0],
            "A/A": kernel_build(base, args.isa, WHO, tag="A/A control")[0]}
    rl = relight.WaveletRelighter(kernel_transfer(args.size), threads=1, layouts="both", tile=args.tile)
    before = load()
    L = [f"## {cpu_label()}: the `{args.isa}` build, {name} against {label}\n",
         f"{path['path']}. Both kernels compiled with the library's flags and this build's, bound to one layout (the "
         "row-major copy built), called through the packed entry point as `WaveletRelighter.prepared` calls it; one "
         f"thread's CPU time, the median of {args.repeats} paired samples; **{label} / {test}** > 1: {name} faster "
         f"[quartiles]; A/A: {label} against a second build of itself. Every output equal bit for bit. Load average "
         "{load0:.1f} → {load1:.1f}.\n",
         f"| light | N | {label} µs | {test} µs | **{label} / {test}** [quartiles] | A/A [quartiles] | load |",
         "|---|---|---|---|---|---|---|"]
    for light in ("studio", "sky (sun)"):
        for N in (10, 100, 300, 1000, 2000, rl.P):
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            lv = lv.to(torch.float32).contiguous()
            li = li.contiguous()
            outs = {k: torch.empty(rl.V, 3) for k in libs}
            calls = {k: bound_call(rl, lib, li, lv, outs[k], 1) for k, lib in libs.items()}
            for k in calls:
                calls[k]()
            for k in ("tree", "A/A"):
                if not torch.equal(outs[k], outs["base"]):
                    raise SystemExit(f"{WHO}: {k} and {label} differ ({light}, N = {N}): "
                                     f"{float((outs[k] - outs['base']).abs().max()):.3e}")
            p = measure_paired(calls["tree"], calls["base"], repeats=args.repeats, warmup=1, clock=time.thread_time)
            a = measure_paired(calls["A/A"], calls["base"], repeats=args.repeats, warmup=1, clock=time.thread_time)
            L.append(f"| {light} | {'all' if N == rl.P else N} | {p.peer.median * 1e6:.1f} | {p.test.median * 1e6:.1f} | "
                     f"**{p.speedup:.3f}** [{p.ratio.q1:.3f}, {p.ratio.q3:.3f}] | {a.speedup:.3f} [{a.ratio.q1:.3f}, "
                     f"{a.ratio.q3:.3f}] | {load():.1f} |")
            print(f"[wavelet_setup] {L[-1]}", flush=True)
    L[1] = L[1].replace("{load0:.1f}", f"{before:.1f}").replace("{load1:.1f}", f"{load():.1f}")
    return "\n".join(L) + "\n"


#: (text of kernels/wavelet.c, replacement) for --tsc: rdtsc around the parts, summed per call into prt_tsc [16]:
#: 0 the dense blocks, 1 the sparse passes, 2 the tile loop (from VNNI_SETUP), 3 the gather to the end, 4 tile 0's
#: blocks 0-1 (its first unit), 5 its blocks 2-3; the DVNNI build's set-up (VNNI_SETUP): 6 vnni_quantise's call,
#: 7 vnni_records, and within vnni_quantise 8 its chunk pass (the chunks' sums, maxima, weights, the guard's norms),
#: 9 the flush groups (the budget's pass from the back, the merge, the groups' float32 scales and the guard's sums),
#: 10 the guard's test and the int16 lights written (builds without DVNNI: 6-10 stay 0)
TSC_SUBS = (
    ("#include <string.h>\n", "#include <string.h>\n#include <x86intrin.h>\nunsigned long long prt_tsc[16];\n"),
    ("        dense_block_##T(CT_, CO_, OC_, nd, wk,", "        { const unsigned long long t0_ = __rdtsc(); \\\n"
     "        dense_block_##T(CT_, CO_, OC_, nd, wk,"),
    ("                        out + OC_ * v0, nt_out);", "                        out + OC_ * v0, nt_out); "
     "{ const unsigned long long d_ = __rdtsc() - t0_; prt_tsc[0] += d_; if (v0 < 2 * BV) prt_tsc[4] += d_; "
     "else if (v0 < 4 * BV) prt_tsc[5] += d_; } } "),
    ("    if (ns && !rows) sparse_tile_##T(CT_, CO_, ns, sw, sl, tp, bofs, bv, acc MK_ARG);",
     "    { const unsigned long long t1_ = __rdtsc(); \\\n"
     "    if (ns && !rows) sparse_tile_##T(CT_, CO_, ns, sw, sl, tp, bofs, bv, acc MK_ARG); prt_tsc[1] += __rdtsc() - t1_; } "),
    ("    VNNI_SETUP(T) /* DVNNI", "    const unsigned long long t2_ = __rdtsc(); \\\n    VNNI_SETUP(T) /* DVNNI"),
    ("    for (i64 n = 0; n < N; n++) memset(lp + 4 * sel[n], 0, 4 * sizeof(float));                               \\\n"
     "    NT_OUT_FENCE", "    prt_tsc[2] += __rdtsc() - t2_; \\\n"
     "    for (i64 n = 0; n < N; n++) memset(lp + 4 * sel[n], 0, 4 * sizeof(float));                               \\\n"
     "    NT_OUT_FENCE"),
    ("    memset(mark, 0, (size_t)P);", "    const unsigned long long t3_ = __rdtsc(); \\\n    memset(mark, 0, (size_t)P);"),
    ("    NT_OUT_FENCE(nt_out);                                                                                    \\\n    return 0;",
     "    NT_OUT_FENCE(nt_out); prt_tsc[3] += __rdtsc() - t3_; \\\n    return 0;"))
#: --tsc's reads inside the DVNNI set-up (applied when the source has them: builds and revisions without DENSE_VNNI's
#: vnni_quantise leave 6-10 at 0)
TSC_VNNI = (
    ("            if (vnni_quantise(nd, lw, vq_,", "            const unsigned long long t6_ = __rdtsc(); \\\n"
     "            const int q6_ = vnni_quantise(nd, lw, vq_,"),
    ("L->dnorm ? L->dnorm[Pd] : 0.0)) { /* 0: the guard */ \\\n",
     "L->dnorm ? L->dnorm[Pd] : 0.0); prt_tsc[6] += __rdtsc() - t6_; \\\n            if (q6_) { /* 0: the guard */ \\\n"),
    ("                vnni_records(nd, wk, 2 * pstb_, nbk_ * pstb_ >= PFX_MIN);",
     "                const unsigned long long t7_ = __rdtsc(); \\\n"
     "                vnni_records(nd, wk, 2 * pstb_, nbk_ * pstb_ >= PFX_MIN); prt_tsc[7] += __rdtsc() - t7_;"),
    ("    const double *gn = VNNI_GUARD > 0 ? nm : NULL;", "    unsigned long long q_ = __rdtsc(), q1_;\n"
     "    const double *gn = VNNI_GUARD > 0 ? nm : NULL;"),
    ("    rest[3 * nc] = rest[3 * nc + 1] = rest[3 * nc + 2] = 0;",
     "    q1_ = __rdtsc(); prt_tsc[8] += q1_ - q_; q_ = q1_;\n    rest[3 * nc] = rest[3 * nc + 1] = rest[3 * nc + 2] = 0;"),
    ("    if (gn) /* the guard: sum_G", "    q1_ = __rdtsc(); prt_tsc[9] += q1_ - q_; q_ = q1_;\n    if (gn) /* the guard: sum_G"),
    ("    return 1;\n}\n/* the dense terms' slots ds", "    prt_tsc[10] += __rdtsc() - q_;\n    return 1;\n}\n/* the dense terms' slots ds"))
TSC_PARTS = ("set-up (gather → tile loop)", "sparse passes", "dense blocks (terms, add-back, output)", "tile loop",
             "the call (gather → end)", "tile 0's first unit (blocks 0-1)", "its second unit (blocks 2-3)",
             "VNNI set-up (vnni_quantise + vnni_records)", "  vnni_quantise's chunk pass", "  its flush groups",
             "  its guard test + int16 write", "  vnni_records", "tile loop − VNNI set-up")


def tsc_source(src: str) -> str:
    """``src`` (kernels/wavelet.c) with ``--tsc``'s ``rdtsc`` reads (:data:`TSC_SUBS`: the sums in ``prt_tsc``
    unsigned long long [8]); one ``SystemExit`` line when a text they go after is not in it exactly once."""
    for old, new in TSC_SUBS:
        if src.count(old) != 1:
            raise SystemExit(f"{WHO}: kernels/wavelet.c changed: --tsc's text {old.strip()[:60]!r} is not there once")
        src = src.replace(old, new)
    if "static __attribute__((noinline)) int vnni_quantise(" in src:
        for old, new in TSC_VNNI:
            if src.count(old) != 1:
                raise SystemExit(f"{WHO}: kernels/wavelet.c changed: --tsc's text {old.strip()[:60]!r} is not there once")
            src = src.replace(old, new)
    return src


def tsc_rate() -> float:
    """The TSC's ticks per µs, against CLOCK_MONOTONIC over 0.2 s."""
    src = ("#include <time.h>\n#include <x86intrin.h>\ndouble tsc_mhz(void) { struct timespec a, b; "
           "clock_gettime(CLOCK_MONOTONIC, &a); unsigned long long t0 = __rdtsc(); double ns; do { "
           "clock_gettime(CLOCK_MONOTONIC, &b); ns = (b.tv_sec - a.tv_sec) * 1e9 + (b.tv_nsec - a.tv_nsec); } "
           "while (ns < 2e8); return (double)(__rdtsc() - t0) / ns * 1e3; }\n")
    lib, how = compile_library("wavelet_tsc_rate", {"tsc.c": src}, ["-O2", "-shared", "-fPIC", "-std=gnu99"], {})
    if lib is None:
        raise SystemExit(f"{WHO}: no compiler: {how}")
    lib.tsc_mhz.restype = ctypes.c_double
    return lib.tsc_mhz()


def tsc_split(args, tiles: list[int]) -> str:
    """The ``--tsc`` section (module docstring)."""
    import platform
    import statistics

    if platform.machine() not in ("x86_64", "AMD64"):
        raise SystemExit(f"{WHO}: --tsc on {platform.machine()}; accepted: an x86-64 CPU (rdtsc)")
    torch.set_num_threads(1)
    src, label = kernel_source(args.source, f"{WHO} --source")
    lib = kernel_build(tsc_source(src), args.isa, WHO)[0]
    tsc = (ctypes.c_ulonglong * 16).in_dll(lib, "prt_tsc")
    mhz = tsc_rate()
    tr = kernel_transfer(args.size)
    rls = {"A": relight.WaveletRelighter(tr, threads=1, layouts="both", tile=tiles[0]),
           "B": relight.WaveletRelighter(tr, threads=1, layouts="both", tile=tiles[1]),
           "A'": relight.WaveletRelighter(tr, threads=1, layouts="both", tile=tiles[0])}
    before = load()
    nt = {k: r.NT for k, r in rls.items()}
    L = [f"## {cpu_label()}: the `{args.isa}` build, kernel {label}, the call's parts in place (rdtsc), tiles "
         f"{tiles[0]} against {tiles[1]}{'' if args.size == 'small' else ', ' + args.size}\n",
         f"One build with `rdtsc` around the parts (`--tsc`, module docstring); relighters A (tile {tiles[0]}: {nt['A']} "
         f"tile{'s' * (nt['A'] > 1)}), B (tile {tiles[1]}: {nt['B']} tiles) and A' (A's tile again: the A/A control) of one "
         f"transfer (V = {rls['A'].V}); {args.tsc_pairs} pairs per light and control, "
         + ("alternated per call" if args.tsc_block == 1 else f"in runs of {args.tsc_block} calls per relighter")
         + f"; µs at the TSC's "
         f"{mhz:.0f} MHz; **B − A**: the median of the per-pair differences [quartiles] (> 0: tile {tiles[0]} "
         "faster); A' − A the same for two relighters of one tile. Load average {load0:.1f} → {load1:.1f}.\n",
         "| light | N | part | A µs | B µs | **B − A µs** [quartiles] | A' − A µs [quartiles] |",
         "|---|---|---|---|---|---|---|"]
    for light, N in args.lights:
        N = rls["A"].P if N is None else N
        fns = {}
        for k, rl in rls.items():
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            li, lv = li.contiguous(), lv.to(torch.float32).contiguous()
            fns[k] = bound_call(rl, lib, li, lv, torch.empty(rl.V, 3), 1, per_vertex=True)

        def parts(fn):
            ctypes.memset(tsc, 0, 128)
            fn()
            v = list(tsc)
            return [v[3] - v[2], v[1], v[0], v[2], v[3], v[4], v[5], v[6] + v[7], v[8], v[9], v[10], v[7],
                    v[2] - v[6] - v[7]]

        diffs = {}
        for other in ("B", "A'"):
            for _ in range(50):
                fns["A"]()
                fns[other]()
            sa, so = [], []
            K = args.tsc_block
            for i in range(-(-args.tsc_pairs // K)):  # K calls of one relighter, then K of the other, in turn
                first, second = (("A", sa), (other, so)) if i % 2 == 0 else ((other, so), ("A", sa))
                for k, acc in (first, second):
                    fns[k]()  # untimed: the first call after the other relighter's
                    acc += [parts(fns[k]) for _ in range(K)]
            diffs[other] = (sa, so)
        for j, name in enumerate(TSC_PARTS):
            cols = []
            for other in ("B", "A'"):
                sa, so = diffs[other]
                d = sorted((b[j] - a[j]) / mhz for a, b in zip(sa, so))
                n = len(d)
                cols.append((statistics.median(a[j] for a in sa) / mhz, statistics.median(b[j] for b in so) / mhz,
                             d[n // 2], d[n // 4], d[3 * n // 4]))
            b, c = cols
            L.append(f"| {light} | {'all' if N == rls['A'].P else N} | {name} | {b[0]:.2f} | {b[1]:.2f} | "
                     f"**{b[2]:+.2f}** [{b[3]:+.2f}, {b[4]:+.2f}] | {c[2]:+.2f} [{c[3]:+.2f}, {c[4]:+.2f}] |")
            print(f"[wavelet_setup] {L[-1]}", flush=True)
    L[1] = L[1].replace("{load0:.1f}", f"{before:.1f}").replace("{load1:.1f}", f"{load():.1f}")
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
