"""The wavelet relighter's dense layout on transparent huge pages (issue 39): ``WaveletRelighter`` allocates
``dense [ceil(V/32), Pd, CT, 32]`` through ``io.hugepage_zeros`` (2 MiB pages advised from 2 MiB up;
``PRT_TORCH_HUGEPAGES=0``: torch's own buffer, 4 KB pages under the kernel's ``madvise`` THP mode). A light's dense
terms read a few scattered 64-byte lines in each block (a block spans Pd·CT·64 bytes, 15.6 KB at Pd = 244): past the
L2 each line is a new 4 KB page.

Three parts, each kept in reports/benchmarks/wavelet_hugepages.json (a part re-run replaces its own entry) and all
written to reports/benchmarks/wavelet_hugepages.md:

* ``pages``: at each ``--sizes`` of occluder_over_plane (:data:`bench_wavelet.KERNEL_SIZES`: V = 2251 / 10 585 /
  51 335; R = 32, K = 256, :data:`bench_wavelet.BITS`-bit, the row-major copy built) four relighters of one transfer in
  one process — **hp** (the default: dense on huge pages), **4k** (``PRT_TORCH_HUGEPAGES=0``), **4k′** (a second
  one: the A/A control) and **hp+sparse** (hp with the sparse blocks — ``bvals``, ``bofs`` — and the row-major copy —
  ``rvals``, ``rcol``, ``rptr`` — copied onto huge pages as well: measured, not kept) — bound to the kernel as
  ``WaveletRelighter.prepared`` binds it, the studio and sky lights (:data:`bench_wavelet.LIGHTS`, transport-weighted
  terms, RGB) at N = 10, 30, 100, 300, 1000 and all, each pair timed by one thread's CPU time
  (``measure_paired(clock=time.thread_time)``: the other jobs' load enters neither side); hp and 4k each against the
  streaming read of the bytes the light touches plus a fill of the output (``timing.read_bound_fn`` of
  ``bytes_read``); ``AnonHugePages`` (``/proc/self/smaps_rollup``) after each relighter is built; every output bit
  for bit against 4k's; the construction's CPU time (hp against 4k, paired).
* ``spread``: the large N = 10 and N = 100 rows (studio and sky) in ``--processes`` fresh processes each with and
  without huge pages (alternating), the transfer saved once and loaded by each: per process the median µs of a call
  and its fraction of the streaming read — the spread between processes; and one more fresh process's RSS and
  ``AnonHugePages`` across building and dropping three large relighters of each kind.
* ``prefetch``: the 16-lane dense loop's prefetch across units (kernels/wavelet.c ``PFX`` = 24 steps ahead, taken
  from ``PFX_MIN`` = 2 MB of layout) on the huge-page layout: builds with ``#define PFX 12 / 40 / 64`` and with
  ``PFX_MIN`` above the layout (the far prefetch off) prepended (``bench_wavelet_isa.kernel_build``, the wavelet
  library's flags, this CPU's native build) paired with the working tree's build on the same layout at medium and
  large, with an A/A control; the far prefetch off also on torch's buffer (what the prefetch is worth with 4 KB pages).
* ``avx2``: the AVX2 build (the 8-lane code an AVX2-only CPU runs, the AMD EPYC Zen 3's) on the hp, 4k and 4k′
  layouts at medium and large (``--prefetch-sizes``), paired as ``pages``: what the pages do to the code this change
  does not touch, on this Xeon (a proxy, not the Zen 3).

    .venv/bin/python benchmarks/bench_wavelet_hugepages.py [--parts pages,spread,prefetch,avx2] [--sizes small,medium,large]
    (about 10 minutes on a 2-core Xeon: pages 4, spread 2.5, prefetch 2, avx2 1.5)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import gc  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, KERNEL_SIZES, LIGHTS, OUT, STEADY_SPREAD, STEADY_TRIES, kernel_transfer, load, size_choice  # noqa: E402
from bench_wavelet_isa import bound_call, kernel_build, kernel_source  # noqa: E402

from prt_torch import io, relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, measure_paired, read_bound_fn  # noqa: E402
from prt_torch.transfer import Transfer  # noqa: E402

WHO = "bench_wavelet_hugepages.py"
TERMS = (10, 30, 100, 300, 1000)
PARTS = ("pages", "spread", "prefetch", "avx2")
AA = "4k'"  # the A/A control's relighter: a second one on torch's buffer
SPARSE = ("bvals", "bofs", "rvals", "rcol", "rptr")  # the arrays the hp+sparse variant copies onto huge pages
#: the prefetch variants: name -> the lines prepended to kernels/wavelet.c
VARIANTS = {"PFX 12": "#define PFX 12\n", "PFX 40": "#define PFX 40\n", "PFX 64": "#define PFX 64\n",
            "far off": "#define PFX_MIN (1LL << 62)\n"}


def proc_kb(field: str, path: str = "/proc/self/smaps_rollup") -> int:
    """A ``kB`` field of ``/proc/self/smaps_rollup`` (``AnonHugePages``, ``Rss``) or ``/proc/self/status``
    (``VmRSS``, ``VmHWM``); 0 where the file does not exist."""
    try:
        with open(path) as f:
            for line in f:
                if line.startswith(field + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return 0


def relighter(tr: Transfer, huge: bool, sparse: bool = False) -> relight.WaveletRelighter:
    """The relighter with ``PRT_TORCH_HUGEPAGES`` set for its construction (then restored); ``sparse``: the
    :data:`SPARSE` arrays copied onto huge pages too (the layout rebound on first use)."""
    prev = os.environ.get("PRT_TORCH_HUGEPAGES")
    os.environ["PRT_TORCH_HUGEPAGES"] = "1" if huge else "0"
    try:
        rl = relight.WaveletRelighter(tr, threads=1, layouts="both")
    finally:
        if prev is None:
            del os.environ["PRT_TORCH_HUGEPAGES"]
        else:
            os.environ["PRT_TORCH_HUGEPAGES"] = prev
    if sparse:
        for name in SPARSE:
            t = getattr(rl, name)
            h = io.hugepage_zeros(t.shape, t.dtype, huge=True)
            h.copy_(t)
            setattr(rl, name, h)
        rl._native = None  # the kernel's layout rebuilt with the new addresses
    return rl


def light_of(rl, light: str, N: int):
    li, lv, _ = rl.light(LIGHTS[light], N, "transport")
    return li.contiguous(), lv.to(torch.float32).contiguous()


def pair(a, b, repeats: int) -> dict:
    """``b``'s time over ``a``'s (> 1: ``a`` faster), median of the per-repeat ratios and quartiles, one thread's CPU
    time; the medians per call in µs; timed again while the ratios' relative quartile range exceeds
    :data:`bench_wavelet.STEADY_SPREAD`, up to :data:`bench_wavelet.STEADY_TRIES` times, the steadiest kept
    (``tries``), as the kernel section's rows."""
    best, tries = None, 0
    for tries in range(1, STEADY_TRIES + 1):
        p = measure_paired(a, b, repeats=repeats, warmup=1, clock=time.thread_time)
        if best is None or p.ratio.spread < best.ratio.spread:
            best = p
        if p.ratio.spread <= STEADY_SPREAD:
            break
    return {"r": best.speedup, "q": [best.ratio.q1, best.ratio.q3], "us": [best.test.median * 1e6, best.peer.median * 1e6],
            "tries": tries}


def pages_part(sizes: list[str], repeats: int) -> dict:
    infos, rows = [], []
    for size in sizes:
        tr = kernel_transfer(size)
        ahp0 = proc_kb("AnonHugePages")
        rls, ahp = {}, {}
        for name, huge, sparse in (("hp", True, False), ("4k", False, False), (AA, False, False),
                                   ("hp+sparse", True, True)):
            rls[name] = relighter(tr, huge, sparse)
            ahp[name] = proc_kb("AnonHugePages") - ahp0 - sum(ahp.values())
        hp = rls["hp"]
        info = {"size": size, "V": hp.V, "Pd": hp.Pd, "held": hp.held_bytes(),
                "held_same": hp.held_bytes() == rls["4k"].held_bytes(), "anon_huge_kb": ahp,
                "backed": {k: [n for n in ("dense",) + SPARSE if io.hugepage_backed(getattr(r, n))] for k, r in rls.items()}}
        # the construction, hp against 4k (each a fresh relighter, dropped at once)
        info["build"] = pair(lambda: relighter(tr, True), lambda: relighter(tr, False), 3)
        infos.append(info)
        print(f"[hugepages] {size}: V = {hp.V}, dense {info['held']['dense'] / 2**20:.2f} MB, AnonHugePages kB {ahp}, "
              f"on huge pages {info['backed']}, build 4k/hp {info['build']['r']:.2f}", flush=True)
        for light in ("studio", "sky (sun)"):
            for N in TERMS + (hp.P,):
                li, lv = light_of(hp, light, N)
                outs = {k: torch.empty(hp.V, 3) for k in rls}
                fn = {k: rl.prepared(li, lv, outs[k]) for k, rl in rls.items()}
                for f in fn.values():
                    f()
                nbytes = hp.bytes_read(li)
                bound = read_bound_fn(nbytes, hp.V * 12)
                row = {"size": size, "light": light, "N": N, "nd": int((hp.dslot[li] >= 0).sum()), "mb": nbytes / 2**20,
                       "same": all(torch.equal(outs[k], outs["4k"]) for k in outs),
                       "hp": pair(fn["hp"], fn["4k"], repeats), "aa": pair(fn[AA], fn["4k"], repeats),
                       "sparse": pair(fn["hp+sparse"], fn["hp"], repeats),
                       "hp_read": pair(fn["hp"], bound, repeats), "4k_read": pair(fn["4k"], bound, repeats),
                       "load": load()}
                rows.append(row)
                print(f"[hugepages] {size} {light} N={N}: 4k/hp {row['hp']['r']:.3f} [{row['hp']['q'][0]:.2f}, "
                      f"{row['hp']['q'][1]:.2f}] ({row['hp']['us'][0]:.1f} / {row['hp']['us'][1]:.1f} us), A/A "
                      f"{row['aa']['r']:.3f}, hp/hp+sparse {row['sparse']['r']:.3f}, of read hp {row['hp_read']['r']:.2f} "
                      f"4k {row['4k_read']['r']:.2f}, same {row['same']}, load {row['load']:.1f}", flush=True)
        del rls, fn, hp
        gc.collect()
    return {"infos": infos, "rows": rows}


def child(path: str, huge: bool, repeats: int) -> dict:
    """One fresh process's large rows: the transfer at ``path``, one relighter (huge pages or not), N = 10 and 100,
    studio and sky, each against the streaming read."""
    torch.set_num_threads(1)
    tr = Transfer.load(path)
    ahp0 = proc_kb("AnonHugePages")
    rl = relighter(tr, huge)
    out = {"huge": huge, "backed": io.hugepage_backed(rl.dense), "anon_huge_kb": proc_kb("AnonHugePages") - ahp0,
           "rows": []}
    for light in ("studio", "sky (sun)"):
        for N in (10, 100):
            li, lv = light_of(rl, light, N)
            o = torch.empty(rl.V, 3)
            run = rl.prepared(li, lv, o)
            p = pair(run, read_bound_fn(rl.bytes_read(li), rl.V * 12), repeats)
            out["rows"].append({"light": light, "N": N, "us": p["us"][0], "bound_us": p["us"][1], "of_read": p["r"],
                                "load": load()})
    return out


def rss_child(path: str) -> list[list]:
    """A fresh process's RSS (``VmRSS``) and ``AnonHugePages`` in kB across building three relighters of the
    transfer at ``path`` and dropping them: on torch's buffer, on huge pages, on torch's buffer again."""
    tr = Transfer.load(path)
    gc.collect()
    out = [["start", proc_kb("VmRSS", "/proc/self/status"), proc_kb("AnonHugePages")]]
    for huge in (False, True, False):
        held = [relighter(tr, huge) for _ in range(3)]
        out.append([f"3 {'hp' if huge else '4k'} built", proc_kb("VmRSS", "/proc/self/status"), proc_kb("AnonHugePages")])
        del held
        gc.collect()
        out.append(["dropped", proc_kb("VmRSS", "/proc/self/status"), proc_kb("AnonHugePages")])
    return out


def spread_part(processes: int, repeats: int) -> dict:
    runs = []
    with tempfile.TemporaryDirectory() as d:
        path = str(Path(d) / "large.prt")
        kernel_transfer("large").save(path)
        r = subprocess.run([sys.executable, __file__, "--child", path, "--rss"], capture_output=True, text=True)
        if r.returncode:
            raise SystemExit(f"{WHO}: the RSS child process failed: {r.stderr.strip().splitlines()[-1:]}")
        rss = json.loads(r.stdout.strip().splitlines()[-1])
        print(f"[hugepages] RSS, AnonHugePages kB: {rss}", flush=True)
        for i in range(processes):
            for huge in (True, False):
                r = subprocess.run([sys.executable, __file__, "--child", path, "--huge", "1" if huge else "0",
                                    "--repeats", str(repeats)], capture_output=True, text=True)
                if r.returncode:
                    raise SystemExit(f"{WHO}: a child process failed: {r.stderr.strip().splitlines()[-1:]}")
                res = json.loads(r.stdout.strip().splitlines()[-1])
                res["process"] = i
                runs.append(res)
                print(f"[hugepages] spread process {i} {'hp' if huge else '4k'}: " + ", ".join(
                    f"{x['light']} N={x['N']} {x['us']:.1f} us ({x['of_read']:.2f} of read)" for x in res["rows"]), flush=True)
    return {"runs": runs, "rss_kb": rss}


def prefetch_part(sizes: list[str], repeats: int) -> dict:
    text, _ = kernel_source(None, WHO)
    libs = {"ref": kernel_build(text, "native", WHO)[0], "A/A": kernel_build(text, "native", WHO, tag="A/A control")[0]}
    libs.update({k: kernel_build(v + text, "native", WHO)[0] for k, v in VARIANTS.items()})
    rows = []
    for size in sizes:
        tr = kernel_transfer(size)
        layouts = {"hp": relighter(tr, True), "4k": relighter(tr, False)}
        for light in ("studio", "sky (sun)"):
            for N in TERMS + (layouts["hp"].P,):
                li, lv = light_of(layouts["hp"], light, N)
                row = {"size": size, "light": light, "N": N, "load": load(), "same": True}
                for lay, rl in layouts.items():
                    names = ["A/A", *VARIANTS] if lay == "hp" else ["far off"]
                    outs = {k: torch.empty(rl.V, 3) for k in ["ref", *names]}
                    fn = {k: bound_call(rl, libs[k], li, lv, outs[k], 1) for k in outs}
                    for f in fn.values():
                        f()
                    row["same"] &= all(torch.equal(o, outs["ref"]) for o in outs.values())
                    for k in names:
                        row[f"{lay} {k}"] = pair(fn[k], fn["ref"], repeats)
                rows.append(row)
                print(f"[hugepages] prefetch {size} {light} N={N}: " + ", ".join(
                    f"{k} {v['r']:.3f}" for k, v in row.items() if isinstance(v, dict)) + f", same {row['same']}", flush=True)
        del layouts
        gc.collect()
    return {"rows": rows, "variants": VARIANTS}


def avx2_part(sizes: list[str], repeats: int) -> dict:
    """The 8-lane AVX2 build (``PRT_TORCH_KERNEL_ISA=avx2``'s code, compiled here; the Zen 3's kernel, whose code
    this change leaves alone — on this Xeon a proxy, not proof) on the same three layouts: hp against 4k and the A/A."""
    lib = kernel_build(kernel_source(None, WHO)[0], "avx2", WHO)[0]
    rows = []
    for size in sizes:
        tr = kernel_transfer(size)
        rls = {"hp": relighter(tr, True), "4k": relighter(tr, False), AA: relighter(tr, False)}
        for light in ("studio", "sky (sun)"):
            for N in TERMS + (rls["hp"].P,):
                li, lv = light_of(rls["hp"], light, N)
                outs = {k: torch.empty(rls["hp"].V, 3) for k in rls}
                fn = {k: bound_call(rl, lib, li, lv, outs[k], 1) for k, rl in rls.items()}
                for f in fn.values():
                    f()
                row = {"size": size, "light": light, "N": N, "same": all(torch.equal(o, outs["4k"]) for o in outs.values()),
                       "hp": pair(fn["hp"], fn["4k"], repeats), "aa": pair(fn[AA], fn["4k"], repeats), "load": load()}
                rows.append(row)
                print(f"[hugepages] avx2 {size} {light} N={N}: 4k/hp {row['hp']['r']:.3f}, A/A {row['aa']['r']:.3f}, "
                      f"same {row['same']}", flush=True)
        del rls
        gc.collect()
    return {"rows": rows}


def q(p: dict) -> str:
    return f"{p['r']:.2f} [{p['q'][0]:.2f}, {p['q'][1]:.2f}]"


def spread_stats(xs: list[float]) -> str:
    xs = sorted(xs)
    return f"{xs[0]:.3g}–{xs[-1]:.3g} ({(xs[-1] / xs[0] - 1) * 100:.0f}%)" if xs else "–"


def runs_load(part: dict) -> str:
    """The load average before → after each run that a part's rows come from, with its sizes and repeats."""
    return "; ".join(f"{m['load'][0]:.1f} → {m['load'][1]:.1f} ({', '.join(m.get('sizes', []))}, {m['repeats']} repeats)"
                     for m in part.get("sessions", [part["machine"]]))


def write_md(res: dict, path: str) -> None:
    L = ["# Wavelet relighter: the dense layout on transparent huge pages (issue 39)\n",
         "`WaveletRelighter` allocates its dense layout (`dense [ceil(V/32), Pd, CT, 32]`) through `io.hugepage_zeros`: "
         "a private anonymous mapping rounded to 2 MiB and advised `MADV_HUGEPAGE` when it holds at least 2 MiB (on "
         "Linux, THP mode not `never`), else torch's buffer; `PRT_TORCH_HUGEPAGES=0` turns it off. The layout is "
         "written in place (no copy). Reproduce: `.venv/bin/python benchmarks/bench_wavelet_hugepages.py [--parts "
         "pages,spread,prefetch]`; each part's figures are in `wavelet_hugepages.json`.\n"]
    pg = res.get("pages")
    if pg:
        m = pg["machine"]
        L += ["## Huge pages against 4 KB pages, paired in one process\n",
              f"{m['cpu']}; THP mode `{m['thp']}`; load average {runs_load(pg)} (the machine "
              "shared with other jobs: one thread's CPU time, which their load does not enter). occluder_over_plane, "
              f"R = 32, K = 256, {BITS}-bit, the row-major copy built, transport-weighted terms, RGB light, one thread. "
              f"**4k / hp**: the torch-buffer relighter's time over the huge-page relighter's (> 1: huge pages "
              f"faster), the median of the per-repeat ratios of one thread's CPU time "
              "(`measure_paired(clock=time.thread_time)`) [quartiles], each pairing timed again (up to 3 times, the steadiest kept) "
              "while its quartiles spread more than 0.2 of the median; **A/A**: a second torch-buffer relighter over "
              "the first; **hp / hp+sparse**: hp over hp with the sparse blocks and the row-major copy on huge pages "
              "too (> 1: the copy faster); *of read*: against a streaming read of the bytes the light touches "
              "(`WaveletRelighter.bytes_read`) plus a fill of the output (`timing.read_bound_fn`), paired the same "
              "way; *bits*: every relighter's output equal to 4k's.\n",
              "*AnonHugePages* below: the process's growth while each relighter was built; numpy advises huge pages "
              "for its own arrays of 4 MB or more (checked: an 8 MB numpy array got 6144 kB), so a figure may hold "
              "memory besides the layout — the 4k relighters' layouts are in torch's buffer (`io.hugepage_backed` "
              "false) whatever the column says.\n",
              "| size | V | dense MB | held MB (total; the same for hp and 4k) | AnonHugePages kB after building hp / 4k / "
              "4k′ / hp+sparse | on huge pages in hp+sparse | build, 4k / hp (CPU time, 3 paired) |",
              "|---|---|---|---|---|---|---|"]
        for i in pg["infos"]:
            a = i["anon_huge_kb"]
            L.append(f"| {i['size']} | {i['V']} | {i['held']['dense'] / 2**20:.2f} | {i['held']['total'] / 2**20:.2f}"
                     f"{'' if i['held_same'] else ' (**differs from 4k**)'} | {a['hp']} / {a['4k']} / {a[AA]} / "
                     f"{a['hp+sparse']} | {', '.join(i['backed']['hp+sparse']) or 'none'} | {q(i['build'])} |")
        L += ["", "| size | light | N | dense terms | MB read | hp | 4k | **4k / hp** | A/A | hp / hp+sparse | "
              "**hp of read** | 4k of read | bits | load |", "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in pg["rows"]:
            L.append(f"| {r['size']} | {r['light']} | {r['N']} | {r['nd']} | {r['mb']:.2f} | {r['hp']['us'][0]:.1f} µs | "
                     f"{r['hp']['us'][1]:.1f} µs | **{q(r['hp'])}** | {q(r['aa'])} | {q(r['sparse'])} | "
                     f"**{r['hp_read']['r']:.2f}** | {r['4k_read']['r']:.2f} | "
                     f"{'same' if r['same'] else '**differ**'} | {r['load']:.1f} |")
        L.append("")
    sp = res.get("spread")
    if sp:
        m = sp["machine"]
        L += ["## Process to process: the large rows in fresh processes\n",
              f"{m['cpu']}; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. The large transfer saved once; "
              f"{m['processes']} fresh processes with huge pages (hp) and {m['processes']} without (4k), alternating, "
              "each building one relighter and timing the rows against the streaming read (one thread's CPU time, "
              f"{m['repeats']} repeats): per process the median µs of a call and its fraction of the read; *spread*: "
              "min–max over the processes (max / min − 1).\n",
              "| light | N | pages | µs per process | the read's µs per process | fraction of the read per process | "
              "µs spread | the read's spread | of-read spread |",
              "|---|---|---|---|---|---|---|---|---|"]
        for light in ("studio", "sky (sun)"):
            for N in (10, 100):
                for huge in (True, False):
                    xs = [x for run in sp["runs"] if run["huge"] == huge for x in run["rows"]
                          if x["light"] == light and x["N"] == N]
                    us = ", ".join(f"{x['us']:.1f}" for x in xs)
                    bu = ", ".join(f"{x['bound_us']:.1f}" for x in xs)
                    fr = ", ".join(f"{x['of_read']:.2f}" for x in xs)
                    L.append(f"| {light} | {N} | {'hp' if huge else '4k'} | {us} | {bu} | {fr} | "
                             f"{spread_stats([x['us'] for x in xs])} | {spread_stats([x['bound_us'] for x in xs])} | "
                             f"{spread_stats([x['of_read'] for x in xs])} |")
        if "rss_kb" in sp:
            L += ["", "Memory across building and dropping three large relighters in a fresh process (the transfer "
                  "loaded first; kB): " + " → ".join(f"{t} VmRSS {a}, AnonHugePages {b}" for t, a, b in sp["rss_kb"])
                  + ". The huge-page mappings are unmapped with their relighter; torch's buffers go back to the "
                  "allocator, which keeps them for the next allocation."]
        kb = sorted({run["anon_huge_kb"] for run in sp["runs"] if run["huge"]})
        L += ["", f"AnonHugePages after the build, hp processes: {', '.join(map(str, kb))} kB; 4k processes: "
              f"{', '.join(sorted({str(run['anon_huge_kb']) for run in sp['runs'] if not run['huge']}))} kB.\n"]
    pf = res.get("prefetch")
    if pf:
        m = pf["machine"]
        names = list(pf["variants"])
        L += ["## The far prefetch's distance on the huge-page layout\n",
              f"{m['cpu']}; load average {runs_load(pf)}. `kernels/wavelet.c` built with the "
              f"wavelet library's flags (`{m['flags']}`) as it is (**ref**: PFX = 24, PFX_MIN = 2 MB) and with "
              + ", ".join(f"**{k}** (`{v.strip()}`)" for k, v in pf["variants"].items())
              + " prepended, bound to one layout (`bench_wavelet_isa.bound_call`); each paired with ref by one thread's "
              f"CPU time ({m['repeats']} repeats): ref / variant (> 1: the variant faster) [quartiles]; **A/A** ref "
              "built twice. On the huge-page layout (hp) every variant; on torch's buffer (4k) the far prefetch off.\n",
              "| size | light | N | hp A/A | " + " | ".join(f"hp {k}" for k in names) + " | 4k far off | bits | load |",
              "|---|---|---|---|" + "---|" * len(names) + "---|---|---|"]
        for r in pf["rows"]:
            L.append(f"| {r['size']} | {r['light']} | {r['N']} | {q(r['hp A/A'])} | "
                     + " | ".join(q(r[f"hp {k}"]) for k in names) + f" | {q(r['4k far off'])} | "
                     f"{'same' if r['same'] else '**differ**'} | {r['load']:.1f} |")
        L.append("")
    av = res.get("avx2")
    if av:
        m = av["machine"]
        L += ["## The AVX2 build on the same layouts (a proxy for the AMD EPYC Zen 3)\n",
              f"{m['cpu']}; load average {runs_load(av)}. The 8-lane AVX2 kernel (`PRT_TORCH_KERNEL_ISA=avx2`'s code, "
              "the code the Zen 3 runs; this change leaves it alone and moves only its data) bound to the hp, 4k and 4k′ "
              "relighters, paired as above: **4k / hp**, **A/A** 4k′ over 4k. On this Xeon, not on the Zen 3 (whose "
              "TLBs differ: not measured).\n",
              "| size | light | N | **4k / hp** | A/A | bits | load |", "|---|---|---|---|---|---|---|"]
        for r in av["rows"]:
            L.append(f"| {r['size']} | {r['light']} | {r['N']} | **{q(r['hp'])}** | {q(r['aa'])} | "
                     f"{'same' if r['same'] else '**differ**'} | {r['load']:.1f} |")
        L.append("")
    io.atomic_write_text(path, "\n".join(L))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--parts", default=",".join(PARTS), help="comma-separated: " + ", ".join(PARTS))
    ap.add_argument("--sizes", default=",".join(KERNEL_SIZES), help="pages: comma-separated " + ", ".join(KERNEL_SIZES))
    ap.add_argument("--prefetch-sizes", default="medium,large", help="prefetch and avx2: comma-separated sizes")
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--processes", type=int, default=3, help="spread: fresh processes per kind")
    ap.add_argument("--write", default=str(OUT / "wavelet_hugepages.md"), help="the report ('': print the JSON only)")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--huge", help=argparse.SUPPRESS)
    ap.add_argument("--rss", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--render", action="store_true", help="only rewrite the report from wavelet_hugepages.json")
    args = ap.parse_args()
    if args.repeats < 3:
        raise SystemExit(f"{WHO}: --repeats {args.repeats}; accepted: an integer >= 3")
    if args.child:
        print(json.dumps(rss_child(args.child) if args.rss else child(args.child, args.huge == "1", args.repeats)))
        return
    if args.render:
        jpath = Path(args.write or OUT / "wavelet_hugepages.md").with_suffix(".json")
        write_md(json.loads(jpath.read_text()), args.write or str(OUT / "wavelet_hugepages.md"))
        return
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    bad = [p for p in parts if p not in PARTS]
    if bad or not parts:
        raise SystemExit(f"{WHO}: --parts {args.parts!r}; accepted: a comma list of {', '.join(PARTS)}")
    if args.processes < 2:
        raise SystemExit(f"{WHO}: --processes {args.processes}; accepted: an integer >= 2")
    sizes = [size_choice(s.strip(), WHO) for s in args.sizes.split(",")]
    psizes = [size_choice(s.strip(), WHO) for s in args.prefetch_sizes.split(",")]
    io.huge_pages_enabled()  # a bad PRT_TORCH_HUGEPAGES: one line before any work
    torch.set_num_threads(1)
    jpath = Path(args.write or OUT / "wavelet_hugepages.md").with_suffix(".json")
    res = json.loads(jpath.read_text()) if jpath.exists() else {}
    for part in parts:
        before = load()
        if part == "pages":
            r = pages_part(sizes, args.repeats)
        elif part == "spread":
            r = spread_part(args.processes, args.repeats)
        elif part == "prefetch":
            r = prefetch_part(psizes, args.repeats)
        else:
            r = avx2_part(psizes, args.repeats)
        r["machine"] = {"cpu": cpu_label(), "thp": io._thp_mode(), "load": [before, load()], "repeats": args.repeats,
                        "processes": args.processes,
                        "flags": kernel_build(kernel_source(None, WHO)[0], "native", WHO)[1] if part == "prefetch" else ""}
        r["machine"]["sizes"] = sizes if part == "pages" else psizes if part in ("prefetch", "avx2") else ["large"]
        r["sessions"] = [r["machine"]]
        if part in ("pages", "prefetch", "avx2") and part in res:  # a run of some sizes replaces those sizes' rows only
            done = set(r["machine"]["sizes"])
            for key in ("rows", "infos"):
                if key in r:
                    kept = [x for x in res[part][key] if x["size"] not in done]
                    r[key] = sorted(kept + r[key], key=lambda x: KERNEL_SIZES.index(x["size"]))
            kept = []
            for m in res[part].get("sessions", [res[part]["machine"]]):
                left = [z for z in m.get("sizes", KERNEL_SIZES) if z not in done]  # the sizes its rows still hold
                if left:
                    kept.append(m | {"sizes": left})
            r["sessions"] = kept + r["sessions"]
        res[part] = r
        if args.write:
            io.atomic_write_json(jpath, res)
            write_md(res, args.write)
            print(f"[hugepages] wrote {args.write} ({part})", flush=True)
    if not args.write:
        print(json.dumps(res, indent=1))
    bad = [r for p in ("pages", "prefetch", "avx2") if p in parts for r in res[p]["rows"] if not r["same"]]
    if bad:
        raise SystemExit(f"{WHO}: outputs differ between relighters or builds in {len(bad)} rows (see 'bits')")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
