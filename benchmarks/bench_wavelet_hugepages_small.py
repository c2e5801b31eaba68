"""The small layout and the streaming-read bound on 2 MiB pages (issue 39, section 7's small rows).

At small (occluder_over_plane, V = 2251, R = 32, K = 256, :data:`bench_wavelet.BITS`-bit) the dense layout (1.18 MB)
is below :data:`io.HUGE_PAGE_BYTES`, so before this change every array the kernel reads lay in torch's 4 KB pages,
and so does the bound's buffer (``timing.read_bound_fn``). Where 4 KB pages land decides the L2 sets they use and
their TLB entries: the hypothesis is that this makes both times depend on the process. Parts (each kept in
reports/benchmarks/wavelet_hugepages_small.json, a part re-run replaces its own entry; all written to
reports/benchmarks/wavelet_hugepages_small.md):

* ``bound``: in ``--processes`` fresh processes, the streaming read (``read_bound_fn``: an int64 sum of the bytes and
  a fill of V·12 output bytes) of each ``--mb`` size on 4 KB pages (torch's buffer) against the same read in one
  huge-page mapping (``read_bound_fn(huge=True)``: :class:`io.HugePageArena`), three fresh buffer pairs per process,
  each pair timed by one thread's CPU time (``measure_paired(clock=time.thread_time)``): the medians per buffer, the
  spread across processes.
* ``buffers``: in each of ``--processes`` fresh processes, ``--buffers`` huge-page reads and as many 4 KB reads of each
  ``--mb`` size held at once (distinct pages), each timed (its median µs paired with the first 4 KB one): whether a
  2 MiB page's read is the same whichever page it got, and whether the same pages come back in the next process.
* ``pairs``: in one process, the small relighter with every array its kernel reads on huge pages (**hp**:
  :func:`arena_relighter`, the variant measured — relight.py keeps torch's buffers below 2 MiB) against **4k**
  (the default at small: torch's buffers), with A/A controls (**4k′** a second
  4 KB relighter, **hp′** a second huge-page one), studio N = 10 / 30 / 100 / all (292 kept) and sky N = 10 / 30 / 100 /
  300 / 1000 / 2000 / all (transport-weighted, RGB, one thread): warm back to back (4k / hp, > 1: huge pages faster)
  and, as section 7, each against the streaming read (``bench_wavelet.steady_pair``: the median of the per-repeat
  ratios, the criterion) on 4 KB pages and on a huge page; outputs bit for bit against 4k's.
* ``fresh``: in ``--processes`` fresh processes each with huge pages and without (alternating), the transfer saved
  once: the fourth row (studio all) and sky N = 1000 (and N = 300) against both reads.
* ``relighters``: ``--buffers`` huge-page and as many 4 KB relighters held in one process, the same rows on each: the
  call's spread from placement alone.
* ``corunner``: the rows alone, beside an L2-thrashing process time-sliced on the same CPU, alone again.
* ``drift``: one process, one 4 KB relighter and one read per row built once (placement fixed), each row paired with
  its read every ``--interval`` seconds for ``--minutes``: how call, read and fraction move with the machine over time.

    .venv/bin/python benchmarks/bench_wavelet_hugepages_small.py [--parts bound,buffers,pairs,fresh,relighters,drift]
        [--processes 6] [--mb 0.3,1.5] [--buffers 8] [--minutes 20 --interval 30]
    (about 8 minutes on a 2-core Xeon: bound 0.5, buffers 1, pairs 3, fresh 2.5)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import OUT, kernel_transfer, load, steady_pair  # noqa: E402
from bench_wavelet_hugepages import light_of, pair, proc_kb, relighter  # noqa: E402

from prt_torch import io  # noqa: E402
from prt_torch.harness.timing import cpu_label, read_bound_fn  # noqa: E402
from prt_torch.transfer import Transfer  # noqa: E402

WHO = "bench_wavelet_hugepages_small.py"
PARTS = ("bound", "buffers", "pairs", "fresh", "relighters", "drift", "corunner")
ROWS = {"studio": (10, 30, 100, None), "sky (sun)": (10, 30, 100, 300, 1000, 2000, None)}  # None: all terms
FRESH_ROWS = (("studio", None), ("sky (sun)", 300), ("sky (sun)", 1000))
OUT_BYTES = 2251 * 12  # the small mesh's RGB output, float32
PICK = 8  # bound: read_bound_fn(pick=PICK), the median-time one of PICK fresh 4 KB reads
#: the arrays the kernel reads that :func:`arena_relighter` moves onto huge pages (scratch and per-column tables first,
#: then the layout, the row-major copy; the factor and ``_dtmax`` after the first call binds the kernel)
ARENA_ARRAYS = ("_acc", "_zacc", "_tmark", "_wk", "_lw", "_lp", "_mark", "cls", "dslot", "dcol", "_cblk", "tbase",
                "tptr", "bofs", "bvals", "dense", "rptr", "rcol", "rvals")


def arena_relighter(tr: Transfer, huge: bool = True):
    """The relighter (``layouts='both'``, one thread) with every array its kernel reads — :data:`ARENA_ARRAYS`, the
    factor for an RGB light with the albedo, ``_dtmax`` — copied into one :class:`io.HugePageArena` (whole 2 MiB pages:
    4 MiB for the small layout's 3.3 MB) and the kernel rebound to them; ``huge`` False: the plain 4 KB relighter
    (``PRT_TORCH_HUGEPAGES=0``). The variant measured here against the default (not kept in relight.py)."""
    rl = relighter(tr, False)
    rl._kfactor(3, True)  # the RGB light's factor, cached, and the kernel bound (_dtmax): both variants hold the same
    rl._kernel()
    if not huge:
        return rl
    sizes = [getattr(rl, n).numel() * getattr(rl, n).element_size() for n in ARENA_ARRAYS]
    sizes += [f.numel() * 4 for f, _ in rl._f.values()] + [4 * max(rl.Pd, 1)]
    arena = io.HugePageArena(sum(-(-b // 64) * 64 + 64 for b in sizes))
    for n in ARENA_ARRAYS:
        setattr(rl, n, arena.take(getattr(rl, n)))
    rl._f = {k: (arena.take(f), c) for k, (f, c) in rl._f.items()}
    rl._native = None
    rl._kernel()  # the layout rebuilt with the new addresses; _dtmax is its last field
    rl._dtmax = arena.take(rl._dtmax)
    if rl._dtmax is not None:
        rl._layout[-1] = rl._dtmax.data_ptr()
    rl._arena = arena
    return rl


def buffers_child(mb: float, k: int, repeats: int) -> dict:
    """``k`` huge-page reads and ``k`` 4 KB reads of ``mb`` MB, all held at once (distinct pages), each timed against
    the first 4 KB one by one thread's CPU time: the median µs of each."""
    torch.set_num_threads(1)
    n = int(mb * 1e6)
    hp = [read_bound_fn(n, OUT_BYTES, huge=True) for _ in range(k)]
    fk = [read_bound_fn(n, OUT_BYTES) for _ in range(k)]
    out = {"hp": [], "4k": []}
    for i in range(k):
        for name, fs in (("hp", hp), ("4k", fk)):
            out[name].append(pair(fs[i], fk[0], repeats)["us"][0])
    return out


def buffers_part(processes: int, mbs: list[float], k: int, repeats: int) -> dict:
    runs = []
    for i in range(processes):
        for mb in mbs:
            r = subprocess.run([sys.executable, __file__, "--child", "buffers", "--mb", str(mb), "--buffers", str(k),
                                "--repeats", str(repeats)], capture_output=True, text=True)
            if r.returncode:
                raise SystemExit(f"{WHO}: a child process failed: {r.stderr.strip().splitlines()[-1:]}")
            res = json.loads(r.stdout.strip().splitlines()[-1])
            res.update(process=i, mb=mb, load=load())
            runs.append(res)
            print(f"[hp-small] buffers process {i} {mb} MB: hp " + " ".join(f"{x:.1f}" for x in res["hp"]) + "; 4k "
                  + " ".join(f"{x:.1f}" for x in res["4k"]), flush=True)
    return {"runs": runs, "mb": mbs, "buffers": k}


def bound_child(mbs: list[float], repeats: int) -> dict:
    """One fresh process: per size three fresh (huge-page, 4 KB, 4 KB median of :data:`PICK`) read triples, the first two
    paired with each other and the third with the second by one thread's CPU time."""
    torch.set_num_threads(1)
    out = {"rows": [], "anon_huge_kb": []}
    for mb in mbs:
        n = int(mb * 1e6)
        for i in range(3):
            a0 = proc_kb("AnonHugePages")
            hp = read_bound_fn(n, OUT_BYTES, huge=True)
            grown = proc_kb("AnonHugePages") - a0
            fk = read_bound_fn(n, OUT_BYTES)
            pk = read_bound_fn(n, OUT_BYTES, pick=PICK)
            p = pair(hp, fk, repeats)
            out["rows"].append({"mb": mb, "buf": i, "hp_us": p["us"][0], "4k_us": p["us"][1], "r": p["r"], "q": p["q"],
                                "pick_us": pair(pk, fk, repeats)["us"][0]})
            out["anon_huge_kb"].append(grown)
            del hp, fk, pk
    return out


def bound_part(processes: int, mbs: list[float], repeats: int) -> dict:
    runs = []
    for i in range(processes):
        r = subprocess.run([sys.executable, __file__, "--child", "bound", "--mb", ",".join(map(str, mbs)),
                            "--repeats", str(repeats)], capture_output=True, text=True)
        if r.returncode:
            raise SystemExit(f"{WHO}: a child process failed: {r.stderr.strip().splitlines()[-1:]}")
        res = json.loads(r.stdout.strip().splitlines()[-1])
        res["process"], res["load"] = i, load()
        runs.append(res)
        print(f"[hp-small] bound process {i}: " + ", ".join(f"{x['mb']} MB hp {x['hp_us']:.1f} / 4k {x['4k_us']:.1f} / "
                                                          f"pick {x['pick_us']:.1f} us"
                                                          for x in res["rows"]) + f", AnonHugePages +{res['anon_huge_kb']} kB", flush=True)
    return {"runs": runs, "mb": mbs}


def pairs_part(repeats: int) -> dict:
    tr = kernel_transfer("small")
    rls = {k: arena_relighter(tr, k.startswith("hp")) for k in ("hp", "4k", "4k'", "hp'")}
    hp = rls["hp"]
    info = {"V": hp.V, "held": hp.held_bytes(), "held_same": hp.held_bytes() == rls["4k"].held_bytes(),
            "arena": {k: (r._arena.capacity, r._arena.used) if hasattr(r, "_arena") else None for k, r in rls.items()},
            "backed": {k: sorted(n for n in ARENA_ARRAYS + ("_dtmax",) if io.hugepage_backed(getattr(r, n)))
                       for k, r in rls.items()}}
    print(f"[hp-small] V = {hp.V}, held {info['held']['total'] / 2**20:.2f} MB, arena {info['arena']}", flush=True)
    rows = []
    for light, Ns in ROWS.items():
        for N in Ns:
            N = hp.P if N is None else N
            li, lv = light_of(hp, light, N)
            outs = {k: torch.empty(hp.V, 3) for k in rls}
            fn = {k: r.prepared(li, lv, outs[k]) for k, r in rls.items()}
            for f in fn.values():
                f()
            nbytes = hp.bytes_read(li)
            b4, bh = read_bound_fn(nbytes, hp.V * 12), read_bound_fn(nbytes, hp.V * 12, huge=True)
            row = {"light": light, "N": N, "kept": int(li.numel()), "mb": nbytes / 1e6, "load": load(),
                   "same": all(torch.equal(o, outs["4k"]) for o in outs.values()),
                   "hp": pair(fn["hp"], fn["4k"], repeats), "aa4k": pair(fn["4k'"], fn["4k"], repeats),
                   "aahp": pair(fn["hp'"], fn["hp"], repeats)}
            for k in ("hp", "4k"):
                for bn, b in (("read", b4), ("hread", bh)):
                    p, tries = steady_pair(fn[k], b)
                    row[f"{k}_{bn}"] = {"r": p.ratio.median, "q": [p.ratio.q1, p.ratio.q3], "floor": p.speedup,
                                        "us": [p.test.median * 1e6, p.peer.median * 1e6], "tries": tries}
            rows.append(row)
            print(f"[hp-small] {light} N={N}: 4k/hp {row['hp']['r']:.3f} [{row['hp']['q'][0]:.2f}, {row['hp']['q'][1]:.2f}] "
                  f"({row['hp']['us'][0]:.1f} / {row['hp']['us'][1]:.1f} us), A/A 4k {row['aa4k']['r']:.3f} hp "
                  f"{row['aahp']['r']:.3f}; of read hp {row['hp_read']['r']:.2f} / {row['hp_hread']['r']:.2f}, 4k "
                  f"{row['4k_read']['r']:.2f} / {row['4k_hread']['r']:.2f} (read {row['hp_read']['us'][1]:.1f}, hread "
                  f"{row['hp_hread']['us'][1]:.1f} us), same {row['same']}, load {row['load']:.1f}", flush=True)
    return {"info": info, "rows": rows}


def relighters_part(k: int, repeats: int) -> dict:
    """``k`` huge-page and ``k`` 4 KB relighters of one transfer held at once (distinct pages), the fourth row and sky
    N = 300 / 1000 on each timed paired with the first 4 KB one (one thread's CPU time): the call's spread by
    placement alone (the same code, the same virtual offsets within a 2 MiB page for the huge-page ones)."""
    tr = kernel_transfer("small")
    rls = {"hp": [arena_relighter(tr, True) for _ in range(k)], "4k": [arena_relighter(tr, False) for _ in range(k)]}
    ref = rls["4k"][0]
    rows = []
    for light, N in FRESH_ROWS:
        N = ref.P if N is None else N
        li, lv = light_of(ref, light, N)
        o = torch.empty(ref.V, 3)
        f0 = ref.prepared(li, lv, o)
        row = {"light": light, "N": N, "load": load()}
        for name, rs in rls.items():
            outs = [torch.empty(ref.V, 3) for _ in rs]
            fs = [r.prepared(li, lv, x) for r, x in zip(rs, outs)]
            row["same"] = row.get("same", True) and all(torch.equal(x, o) for x in outs)
            row[name] = [pair(f, f0, repeats)["us"][0] for f in fs]
        rows.append(row)
        print(f"[hp-small] relighters {light} N={N}: hp " + " ".join(f"{x:.1f}" for x in row["hp"]) + "; 4k "
              + " ".join(f"{x:.1f}" for x in row["4k"]) + f", same {row['same']}", flush=True)
    return {"rows": rows, "relighters": k}


def drift_part(minutes: float, interval: float) -> dict:
    """One process, one 4 KB relighter and one read per row (:data:`FRESH_ROWS`, the reads built once: the same pages
    throughout), each row paired with its read (``steady_pair``) every ``interval`` seconds for ``minutes``: how the
    call, the read and the fraction move with the machine's state over time, placement held fixed."""
    tr = kernel_transfer("small")
    rl = arena_relighter(tr, False)
    cases = []
    for light, N in FRESH_ROWS:
        N = rl.P if N is None else N
        li, lv = light_of(rl, light, N)
        o = torch.empty(rl.V, 3)
        cases.append((light, N, rl.prepared(li, lv, o), read_bound_fn(rl.bytes_read(li), rl.V * 12)))
    samples = []
    t_end = time.time() + minutes * 60
    while True:
        t0 = time.time()
        for light, N, run, rb in cases:
            p, _ = steady_pair(run, rb)
            samples.append({"t": t0, "light": light, "N": N, "call_us": p.test.median * 1e6, "read_us": p.peer.median * 1e6,
                            "r": p.ratio.median, "load": load()})
        print(f"[hp-small] drift {time.strftime('%H:%M:%S', time.gmtime(t0))}: " + ", ".join(
            f"{x['light']} N={x['N']} {x['call_us']:.1f}/{x['read_us']:.1f} us {x['r']:.2f}" for x in samples[-len(cases):])
            + f", load {samples[-1]['load']:.1f}", flush=True)
        if time.time() + interval > t_end:
            break
        time.sleep(max(0.0, interval - (time.time() - t0)))
    return {"samples": samples, "minutes": minutes, "interval": interval}


#: corunner: a process that reads 64 MB over and over (evicting the L2 of the CPU it runs on)
THRASH = "import numpy as np, os\nos.sched_setaffinity(0, {CPU})\na = np.ones(64 << 17)\nwhile True:\n    a.sum()\n"


def corunner_part() -> dict:
    """This process pinned to one CPU; :data:`FRESH_ROWS` paired with their reads (``steady_pair``) alone, then with an
    L2-thrashing process pinned to the same CPU (time-sliced with this one: it evicts the L2 between slices), then
    alone again: whether another process's cache use, which one thread's CPU time does not remove, moves the fraction."""
    cpu = min(os.sched_getaffinity(0))
    os.sched_setaffinity(0, {cpu})
    tr = kernel_transfer("small")
    rl = arena_relighter(tr, False)
    cases = []
    for light, N in FRESH_ROWS:
        N = rl.P if N is None else N
        li, lv = light_of(rl, light, N)
        o = torch.empty(rl.V, 3)
        cases.append((light, N, rl.prepared(li, lv, o), read_bound_fn(rl.bytes_read(li), rl.V * 12)))
    rows = []

    def sweep(phase: str) -> None:
        for light, N, run, rb in cases:
            p, _ = steady_pair(run, rb)
            rows.append({"phase": phase, "light": light, "N": N, "call_us": p.test.median * 1e6,
                         "read_us": p.peer.median * 1e6, "r": p.ratio.median, "load": load()})
            print(f"[hp-small] corunner {phase}: {light} N={N} {rows[-1]['call_us']:.1f} / {rows[-1]['read_us']:.1f} us, "
                  f"{rows[-1]['r']:.2f}", flush=True)

    sweep("alone")
    th = subprocess.Popen([sys.executable, "-c", THRASH.replace("CPU", str(cpu))])
    try:
        time.sleep(0.5)
        sweep("co-runner")
    finally:
        th.kill()
        th.wait()
    sweep("alone again")
    return {"rows": rows, "cpu": cpu}


def fresh_child(path: str, huge: bool) -> dict:
    torch.set_num_threads(1)
    tr = Transfer.load(path)
    a0 = proc_kb("AnonHugePages")
    rl = arena_relighter(tr, huge)
    out = {"huge": huge, "arena": io.hugepage_backed(rl.dense),
           "anon_huge_kb": proc_kb("AnonHugePages") - a0, "rows": []}
    for light, N in FRESH_ROWS:
        N = rl.P if N is None else N
        li, lv = light_of(rl, light, N)
        o = torch.empty(rl.V, 3)
        run = rl.prepared(li, lv, o)
        nbytes = rl.bytes_read(li)
        row = {"light": light, "N": N, "mb": nbytes / 1e6, "load": load()}
        for bn, huge_read in (("read", False), ("hread", True)):
            p, tries = steady_pair(run, read_bound_fn(nbytes, rl.V * 12, huge=huge_read))
            row[bn] = {"r": p.ratio.median, "us": [p.test.median * 1e6, p.peer.median * 1e6], "tries": tries}
        out["rows"].append(row)
    return out


def fresh_part(processes: int) -> dict:
    runs = []
    with tempfile.TemporaryDirectory() as d:
        path = str(Path(d) / "small.prt")
        kernel_transfer("small").save(path)
        for i in range(processes):
            for huge in (True, False):
                r = subprocess.run([sys.executable, __file__, "--child", "fresh", "--path", path, "--huge", "1" if huge else "0"],
                                   capture_output=True, text=True)
                if r.returncode:
                    raise SystemExit(f"{WHO}: a child process failed: {r.stderr.strip().splitlines()[-1:]}")
                res = json.loads(r.stdout.strip().splitlines()[-1])
                res["process"] = i
                runs.append(res)
                print(f"[hp-small] fresh {i} {'hp' if huge else '4k'}: " + ", ".join(
                    f"{x['light']} N={x['N']} {x['read']['us'][0]:.1f} us, of read {x['read']['r']:.2f} "
                    f"({x['read']['us'][1]:.1f}) / hread {x['hread']['r']:.2f} ({x['hread']['us'][1]:.1f})"
                    for x in res["rows"]), flush=True)
    return {"runs": runs}


def rng(xs: list[float], fmt: str = ".1f") -> str:
    xs = sorted(xs)
    if not xs:
        return "–"
    return f"{xs[0]:{fmt}}–{xs[-1]:{fmt}} (median {statistics.median(xs):{fmt}}, max/min {xs[-1] / xs[0]:.2f})"


def q(p: dict) -> str:
    return f"{p['r']:.2f} [{p['q'][0]:.2f}, {p['q'][1]:.2f}]"


def summary(res: dict) -> list[str]:
    """The figures the findings rest on, computed from the parts present."""
    L = ["## Summary (computed from the parts below)\n"]
    bf = res.get("buffers")
    if bf:
        for mb in bf["mb"]:
            runs = [r for r in bf["runs"] if r["mb"] == mb]
            for k in ("hp", "4k"):
                xs = [x for r in runs for x in r[k]]
                meds = [statistics.median(r[k]) for r in runs]
                L.append(f"- read of {mb} MB, {'one 2 MiB page each' if k == 'hp' else '4 KB pages'}: {len(xs)} buffers "
                         f"in {len(runs)} processes {min(xs):.1f}–{max(xs):.1f} µs (max/min {max(xs) / min(xs):.2f}); "
                         f"the per-process median of its {bf['buffers']} buffers {min(meds):.1f}–{max(meds):.1f} µs")
    p = res.get("pairs")
    if p:
        rows = p["rows"]
        for key, name in (("hp", "4k / hp (huge-page relighter against the default)"), ("aa4k", "A/A 4k′ / 4k"),
                          ("aahp", "A/A hp′ / hp")):
            xs = [r[key]["r"] for r in rows]
            L.append(f"- {name}, warm, {len(xs)} rows: {min(xs):.3f}–{max(xs):.3f}")
        L.append(f"- outputs bit for bit: {all(r['same'] for r in rows)}")
    f = res.get("fresh")
    if f:
        for light, N in FRESH_ROWS:
            for huge in (True, False):
                xs = [x for run in f["runs"] if run["huge"] == huge for x in run["rows"]
                      if x["light"] == light and (x["N"] == N or (N is None and x["N"] > 2000))]
                if xs:
                    L.append(f"- fresh processes, {light} N = {'all' if N is None else N}, {'hp' if huge else '4k'} "
                             f"relighter: of the 4 KB read {min(x['read']['r'] for x in xs):.2f}–{max(x['read']['r'] for x in xs):.2f}"
                             f", of the huge-page read {min(x['hread']['r'] for x in xs):.2f}–{max(x['hread']['r'] for x in xs):.2f}"
                             f"; call {min(x['read']['us'][0] for x in xs):.1f}–{max(x['read']['us'][0] for x in xs):.1f} µs")
    rs = res.get("relighters")
    if rs:
        for r in rs["rows"]:
            L.append(f"- {len(r['hp'])} + {len(r['4k'])} relighters held at once, {r['light']} N = {r['N']}: hp "
                     f"{min(r['hp']):.1f}–{max(r['hp']):.1f} µs, 4k {min(r['4k']):.1f}–{max(r['4k']):.1f} µs")
    d = res.get("drift")
    if d:
        for light, N in FRESH_ROWS:
            xs = [x for x in d["samples"] if x["light"] == light and (x["N"] == N or (N is None and x["N"] > 2000))]
            if xs:
                L.append(f"- over {d['minutes']:.0f} minutes in one process, {light} N = {'all' if N is None else N}: call "
                         f"{min(x['call_us'] for x in xs):.1f}–{max(x['call_us'] for x in xs):.1f} µs, read "
                         f"{min(x['read_us'] for x in xs):.1f}–{max(x['read_us'] for x in xs):.1f} µs, of read "
                         f"{min(x['r'] for x in xs):.2f}–{max(x['r'] for x in xs):.2f} ({len(xs)} samples)")
    return L + [""]


def write_md(res: dict, path: str) -> None:
    L = ["# The small wavelet layout and the streaming-read bound on 2 MiB pages (issue 39)\n",
         "Section 7's small rows (occluder_over_plane, V = 2251, R = 32, K = 256, 16-bit, RGB light, one thread, the "
         "AVX-512 build). Before: the small relighter's arrays (dense layout 1.18 MB < 2 MiB) and the bound's buffer "
         "in torch's 4 KB pages. Measured here: the same relighter with every array its kernel reads copied into one "
         "`io.HugePageArena` (a mapping advised `MADV_HUGEPAGE`, whole 2 MiB pages: the benchmark's `arena_relighter`, "
         "not kept in relight.py), and the streaming read from one (`timing.read_bound_fn(huge=True)`). Reproduce: `.venv/bin/python "
         "benchmarks/bench_wavelet_hugepages_small.py --parts bound --processes 6` (0.3 and 1.5 MB), `--parts buffers "
         "--processes 4 --mb 0.42,1.53` (the fourth row's and sky N = 1000's bytes), `--parts pairs`, `--parts fresh "
         "--processes 4`, `--parts relighters --buffers 6`, `--parts drift --minutes 40 --interval 60`, `--parts corunner` (figures in "
         "`wavelet_hugepages_small.json`). One thread's CPU "
         "time throughout (`measure_paired(clock=time.thread_time)`): the other jobs' load enters neither side, but "
         "their traffic in the shared caches does.\n"]
    L += summary(res)
    bf = res.get("buffers")
    if bf:
        m = bf["machine"]
        L += ["## Reads on distinct pages, held at once\n",
              f"{m['cpu']}; THP `{m['thp']}`; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. Per fresh process and "
              f"size, {bf['buffers']} huge-page reads (`read_bound_fn(huge=True)`, each its own 2 MiB page) and "
              f"{bf['buffers']} 4 KB reads held at once, each timed by one thread's CPU time (its median µs; "
              f"{m['repeats']} repeats, paired with the first 4 KB read): the µs per buffer in allocation order.\n",
              "| process | MB | huge page, µs per buffer | min–max | 4 KB, µs per buffer | min–max |", "|---|---|---|---|---|---|"]
        for run in bf["runs"]:
            L.append(f"| {run['process']} | {run['mb']} | {' '.join(f'{x:.1f}' for x in run['hp'])} | "
                     f"{min(run['hp']):.1f}–{max(run['hp']):.1f} | {' '.join(f'{x:.1f}' for x in run['4k'])} | "
                     f"{min(run['4k']):.1f}–{max(run['4k']):.1f} |")
        L.append("")
    b = res.get("bound")
    if b:
        m = b["machine"]
        L += ["## The streaming read in fresh processes\n",
              f"{m['cpu']}; THP `{m['thp']}`; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. "
              f"{len(b['runs'])} fresh processes; in each, per size three fresh buffer pairs (the huge-page read, "
              "`read_bound_fn(huge=True)`, and the 4 KB read, `read_bound_fn`), each pair timed by one thread's CPU "
              f"time ({m['repeats']} repeats, `measure_paired(clock=time.thread_time)`): the median µs of a call per "
              "buffer. *across processes*: each process's first buffer; *all buffers*: every buffer of every process; "
              f"*median of {PICK}*: `read_bound_fn(pick={PICK})` (the median-time one of {PICK} fresh 4 KB reads, chosen at "
              "construction; absent in runs before it existed).\n",
              "| MB | 4 KB: first buffer per process | 4 KB: all buffers | huge page: first buffer per process | "
              f"huge page: all buffers | 4k / hp per pair | 4 KB median of {PICK}: all |", "|---|---|---|---|---|---|---|"]
        for mb in b["mb"]:
            xs = [x for run in b["runs"] for x in run["rows"] if x["mb"] == mb]
            first = [x for x in xs if x["buf"] == 0]
            L.append(f"| {mb} | {rng([x['4k_us'] for x in first])} | {rng([x['4k_us'] for x in xs])} | "
                     f"{rng([x['hp_us'] for x in first])} | {rng([x['hp_us'] for x in xs])} | "
                     f"{rng([x['r'] for x in xs], '.2f')} | {rng([x['pick_us'] for x in xs if 'pick_us' in x])} |")
        L += ["", f"Per process (µs, 4k / hp / median of {PICK} per buffer): " + "; ".join(
            f"p{run['process']}: " + ", ".join(f"{x['mb']} MB {x['4k_us']:.1f}/{x['hp_us']:.1f}"
                                               + (f"/{x['pick_us']:.1f}" if "pick_us" in x else "") for x in run["rows"])
            for run in b["runs"]),
            "", f"AnonHugePages growth per huge-page read (kB): {sorted({k for run in b['runs'] for k in run['anon_huge_kb']})}.\n"]
    p = res.get("pairs")
    if p:
        m, i = p["machine"], p["info"]
        L += ["## hp against 4k in one process (paired)\n",
              f"{m['cpu']}; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. Held {i['held']['total'] / 2**20:.2f} MB "
              f"(the same for hp and 4k: {i['held_same']}); arenas (capacity, used bytes): {i['arena']}; on huge pages: "
              f"hp {len(i['backed']['hp'])} arrays, 4k {len(i['backed']['4k'])}. **4k / hp**: the 4 KB relighter's time "
              "over the huge-page one's, warm back to back (> 1: huge pages faster), the median of the per-repeat ratios "
              "of one thread's CPU time [quartiles]; A/A: 4k′ over 4k and hp′ over hp. *of read*: section 7's fraction "
              "(`steady_pair`: the median of the per-repeat ratios, the call alternating with the read) against the 4 KB "
              "read / the huge-page read.\n",
              "| light | N | kept | MB read | hp µs | 4k µs | **4k / hp** | A/A 4k | A/A hp | **hp of read** (4 KB / huge) | "
              "4k of read (4 KB / huge) | read µs (4 KB / huge) | bits | load |",
              "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in p["rows"]:
            L.append(f"| {r['light']} | {r['N']} | {r['kept']} | {r['mb']:.2f} | {r['hp']['us'][0]:.1f} | {r['hp']['us'][1]:.1f} | "
                     f"**{q(r['hp'])}** | {q(r['aa4k'])} | {q(r['aahp'])} | **{r['hp_read']['r']:.2f}** / "
                     f"{r['hp_hread']['r']:.2f} | {r['4k_read']['r']:.2f} / {r['4k_hread']['r']:.2f} | "
                     f"{r['hp_read']['us'][1]:.1f} / {r['hp_hread']['us'][1]:.1f} | {'same' if r['same'] else '**differ**'} | "
                     f"{r['load']:.1f} |")
        L.append("")
    rs = res.get("relighters")
    if rs:
        m = rs["machine"]
        L += ["## Relighters on distinct pages, held at once\n",
              f"{m['cpu']}; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. {rs['relighters']} huge-page relighters "
              f"(`arena_relighter`) and {rs['relighters']} 4 KB ones of the small transfer held in one process, each row "
              "timed on each (its median µs of a call, one thread's CPU time, paired with the first 4 KB one): the call's "
              "spread from placement alone (outputs bit for bit the first one's).\n",
              "| light | N | huge page, µs per relighter | min–max | 4 KB, µs per relighter | min–max | bits |",
              "|---|---|---|---|---|---|---|"]
        for r in rs["rows"]:
            L.append(f"| {r['light']} | {r['N']} | {' '.join(f'{x:.1f}' for x in r['hp'])} | {min(r['hp']):.1f}–{max(r['hp']):.1f} | "
                     f"{' '.join(f'{x:.1f}' for x in r['4k'])} | {min(r['4k']):.1f}–{max(r['4k']):.1f} | "
                     f"{'same' if r['same'] else '**differ**'} |")
        L.append("")
    d = res.get("drift")
    if d:
        m = d["machine"]
        L += ["## Over time: one process, the same pages\n",
              f"{m['cpu']}; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. One 4 KB relighter and one read per row "
              f"(built once), each row paired with its read (`steady_pair`, one thread's CPU time) every {d['interval']:.0f} s "
              f"for {d['minutes']:.0f} minutes: the call's µs, the read's µs and the fraction (min–max over the samples).\n",
              "| light | N | samples | call µs | read µs | **of read** |", "|---|---|---|---|---|---|"]
        for light, N in FRESH_ROWS:
            xs = [x for x in d["samples"] if x["light"] == light and (x["N"] == N or (N is None and x["N"] > 2000))]
            L.append(f"| {light} | {'all' if N is None else N} | {len(xs)} | {rng([x['call_us'] for x in xs])} | "
                     f"{rng([x['read_us'] for x in xs])} | {rng([x['r'] for x in xs], '.2f')} |")
        L += ["", "Per sample (UTC; call / read µs, fraction; load): " + "; ".join(
            f"{time.strftime('%H:%M', time.gmtime(x['t']))} {x['light'].split()[0]} {x['N']} "
            f"{x['call_us']:.1f}/{x['read_us']:.1f} {x['r']:.2f} ({x['load']:.1f})" for x in d["samples"]), ""]
    c = res.get("corunner")
    if c:
        m = c["machine"]
        L += ["## An L2-thrashing co-runner on the same CPU\n",
              f"{m['cpu']}; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. This process pinned to CPU {c['cpu']}; each "
              "row paired with its read (`steady_pair`, one thread's CPU time) alone, then with a process reading 64 MB "
              "in a loop pinned to the same CPU (the two time-slice: it evicts the L2 between this process's slices; its "
              "time is not in this thread's CPU time), then alone again: call / read µs (of the read).\n",
              "| light | N | alone | co-runner | alone again |", "|---|---|---|---|---|"]
        for light, N in FRESH_ROWS:
            cells = []
            for ph in ("alone", "co-runner", "alone again"):
                x = next((x for x in c["rows"] if x["phase"] == ph and x["light"] == light
                          and (x["N"] == N or (N is None and x["N"] > 2000))), None)
                cells.append(f"{x['call_us']:.1f} / {x['read_us']:.1f} ({x['r']:.2f})" if x else "–")
            L.append(f"| {light} | {'all' if N is None else N} | " + " | ".join(cells) + " |")
        L.append("")
    f = res.get("fresh")
    if f:
        m = f["machine"]
        L += ["## Fresh processes: the fourth row and sky N = 300 / 1000 against both reads\n",
              f"{m['cpu']}; load average {m['load'][0]:.1f} → {m['load'][1]:.1f}. The small transfer saved once; "
              f"{m['processes']} fresh processes with huge pages (hp) and {m['processes']} without (4k), alternating, each "
              "building one relighter and pairing each row with the 4 KB read and with the huge-page read (`steady_pair`, "
              "one thread's CPU time): µs of a call, the read's µs and the fraction, min–max over the processes.\n",
              "| light | N | pages | call µs | 4 KB read µs | **of 4 KB read** | huge read µs | **of huge read** |",
              "|---|---|---|---|---|---|---|---|"]
        for light, N in FRESH_ROWS:
            for huge in (True, False):
                xs = [x for run in f["runs"] if run["huge"] == huge for x in run["rows"]
                      if x["light"] == light and (N is None or x["N"] == N) and (N is not None or x["N"] > 2000)]
                L.append(f"| {light} | {'all' if N is None else N} | {'hp' if huge else '4k'} | "
                         f"{rng([x['read']['us'][0] for x in xs])} | {rng([x['read']['us'][1] for x in xs])} | "
                         f"{rng([x['read']['r'] for x in xs], '.2f')} | {rng([x['hread']['us'][1] for x in xs])} | "
                         f"{rng([x['hread']['r'] for x in xs], '.2f')} |")
        L.append("")
    io.atomic_write_text(path, "\n".join(L))


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--parts", default=",".join(PARTS), help="comma-separated: " + ", ".join(PARTS))
    ap.add_argument("--processes", type=int, default=6, help="bound, fresh: fresh processes (per kind)")
    ap.add_argument("--mb", default="0.3,1.5", help="bound: comma-separated read sizes in MB (1e6 bytes)")
    ap.add_argument("--repeats", type=int, default=11)
    ap.add_argument("--buffers", type=int, default=8, help="buffers: reads of each kind held at once per process")
    ap.add_argument("--minutes", type=float, default=20.0, help="drift: how long")
    ap.add_argument("--interval", type=float, default=30.0, help="drift: seconds between samples")
    ap.add_argument("--write", default=str(OUT / "wavelet_hugepages_small.md"), help="the report")
    ap.add_argument("--render", action="store_true", help="only rewrite the report from its JSON")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--path", help=argparse.SUPPRESS)
    ap.add_argument("--huge", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.repeats < 3:
        raise SystemExit(f"{WHO}: --repeats {args.repeats}; accepted: an integer >= 3")
    if args.buffers < 1:
        raise SystemExit(f"{WHO}: --buffers {args.buffers}; accepted: an integer >= 1")
    if not (args.minutes > 0 and args.interval > 0):
        raise SystemExit(f"{WHO}: --minutes {args.minutes} --interval {args.interval}; accepted: positive numbers")
    try:
        mbs = [float(x) for x in args.mb.split(",") if x.strip()]
    except ValueError:
        mbs = []
    if not mbs or any(x <= 0 for x in mbs):
        raise SystemExit(f"{WHO}: --mb {args.mb!r}; accepted: a comma list of positive sizes in MB")
    if args.child == "bound":
        print(json.dumps(bound_child(mbs, args.repeats)))
        return
    if args.child == "buffers":
        print(json.dumps(buffers_child(mbs[0], args.buffers, args.repeats)))
        return
    if args.child == "fresh":
        print(json.dumps(fresh_child(args.path, args.huge == "1")))
        return
    jpath = Path(args.write).with_suffix(".json")
    if args.render:
        write_md(json.loads(jpath.read_text()), args.write)
        return
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    if not parts or any(p not in PARTS for p in parts):
        raise SystemExit(f"{WHO}: --parts {args.parts!r}; accepted: a comma list of {', '.join(PARTS)}")
    if args.processes < 2:
        raise SystemExit(f"{WHO}: --processes {args.processes}; accepted: an integer >= 2")
    io.huge_pages_enabled()  # a bad PRT_TORCH_HUGEPAGES: one line before any work
    torch.set_num_threads(1)
    res = json.loads(jpath.read_text()) if jpath.exists() else {}
    bad = 0
    for part in parts:
        before = load()
        r = (bound_part(args.processes, mbs, args.repeats) if part == "bound" else pairs_part(args.repeats)
             if part == "pairs" else fresh_part(args.processes) if part == "fresh"
             else relighters_part(args.buffers, args.repeats) if part == "relighters"
             else drift_part(args.minutes, args.interval) if part == "drift"
             else corunner_part() if part == "corunner"
             else buffers_part(args.processes, [x for x in mbs], args.buffers, args.repeats))
        r["machine"] = {"cpu": cpu_label(), "thp": io._thp_mode(), "load": [before, load()], "repeats": args.repeats,
                        "processes": args.processes}
        res[part] = r
        bad += sum(not x["same"] for x in r.get("rows", []) if "same" in x)
        io.atomic_write_json(jpath, res)
        write_md(res, args.write)
        print(f"[hp-small] wrote {args.write} ({part})", flush=True)
    if bad:
        raise SystemExit(f"{WHO}: outputs differ between relighters in {bad} rows (see 'bits')")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
