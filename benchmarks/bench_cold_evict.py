"""Does flushing a timed call's own data make it as cold as reading junk through the caches?

``harness.timing.measure_paired_cold`` times each call "from cold caches": its inputs and outputs in
memory, not in any cache. It used to evict by reading 4× the last-level cache (at least 64 MiB) before
every timed call — 128 MiB on the AMD EPYC Zen 3 of earlier sessions, 1920 MiB on a VM whose sysfs lists a
480 MiB L3 — and now flushes exactly the tensors the two sides touch (``evict=working_set(...)``:
``harness.timing.flush_caches``, CLFLUSHOPT / CLFLUSH per line then a fence, ``prt_torch/kernels/cacheflush.c``).

Part 1, the check: for each working-set size (default 256 KiB, 4 MiB, 64 MiB) a float32 buffer is read once
(``buf.sum()``, one thread, timed by the thread's CPU time — a stall on memory is CPU time of the thread;
other processes' time is not) in three conditions, interleaved per repeat with the order rotated:
(a) warm: right after an untimed read of the same buffer; (b) after the junk read (``measure_paired_cold``'s
fallback: 4× the last-level cache, at least 64 MiB, read at the process's thread count, as there); (c) after
the flush of the buffer; (d) a 64-byte read after the junk read: what (b) pays that is not the buffer's data
(the junk read evicts the code, the interpreter's and torch's state and the page tables too). Per repeat the
ratios b/a, c/a, b/c and (b − d)/c; their medians and quartiles. (b − d) and (c) should agree and both exceed
(a) where the buffer fits in the cache.

Part 2, the cost of each eviction per call (wall clock, as the suite and ``prt bench`` pay it): the junk read,
its one-time allocation and fill, and the flush of each size.

Part 3 (``--no-default`` skips it): one setting of the default ``prt bench`` (its mrt transfer of the
bumpy_sphere, 10 242 vertices, cached in ``cache/``; CPCA 16 clusters × 8 vectors by default, ``--setting``),
its cold bound fraction measured as ``harness.run.time_setting`` measures it (the prepared relighter into a
reused result against ``io_bound_fn`` of its bytes, ``metrics.cold_pairs`` = 9 single-call pairs), with the
flush and with the junk read, in alternating rounds (``--rounds``): the two columns should agree.

Run: .venv/bin/python benchmarks/bench_cold_evict.py [--repeats 21] [--sizes 256K,4M,64M] [--rounds 3]
Writes reports/benchmarks/cold_evict.md and cold_evict.json.
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch import codecs, io  # noqa: E402
from prt_torch.harness import timing  # noqa: E402
from prt_torch.harness.timing import (cpu_label, flush_caches, flush_method, io_bound_fn, last_level_cache_bytes,  # noqa: E402
                                      machine_info, measure_paired_cold, torch_threads, working_set)

OUT = ROOT / "reports" / "benchmarks"


def parse_size(s: str) -> int:
    s = s.strip().upper()
    mult = {"K": 1 << 10, "M": 1 << 20, "G": 1 << 30}.get(s[-1:], 1)
    digits = s.rstrip("KMG")
    if not digits.isdigit() or int(digits) <= 0:
        raise SystemExit(f"bench_cold_evict: --sizes item {s!r}; accepted: positive sizes like 256K, 4M, 64M")
    return int(digits) * mult


def quart(xs: list[float]) -> dict:
    xs = sorted(xs)
    q = statistics.quantiles(xs, n=4) if len(xs) >= 2 else [xs[0]] * 3
    return {"median": statistics.median(xs), "q1": q[0], "q3": q[2], "n": len(xs)}


def fmt_q(d: dict, scale: float = 1.0, digits: int = 2) -> str:
    return f"{d['median'] * scale:.{digits}f} [{d['q1'] * scale:.{digits}f}–{d['q3'] * scale:.{digits}f}]"


def check_reads(sizes: list[int], repeats: int, junk_bytes: int) -> list[dict]:
    """Part 1 and the flush's part of part 2: per size, the timed read in the three conditions and the
    evictions' costs."""
    junk = timing._junk(junk_bytes)  # measure_paired_cold's own buffer (allocated once)
    rows = []
    for nbytes in sizes:
        buf = torch.rand(nbytes // 4)
        tiny = torch.rand(16)

        def read(x=buf):
            with torch_threads(1):
                t0 = time.thread_time()
                x.sum()
                return time.thread_time() - t0

        def prep(cond):  # the untimed step before the timed read; returns its wall and process CPU time
            t0, c0 = time.perf_counter(), time.process_time()
            if cond == "warm":
                with torch_threads(1):
                    buf.sum()
            elif cond in ("junk", "junk64"):
                junk.sum()
            else:
                flush_caches([buf])
            return time.perf_counter() - t0, time.process_time() - c0

        # junk64: a 64-byte read after the junk read — the part of (b) that is not the buffer's data: the code,
        # the interpreter's and torch's state and the page tables the junk read evicts too
        conds = ("warm", "junk", "flush", "junk64")
        t = {c: [] for c in conds}
        cost = {c: [] for c in conds}
        for c in conds:  # one untimed round
            prep(c)
            read(tiny if c == "junk64" else buf)
        for i in range(repeats):
            order = conds[i % 4:] + conds[:i % 4]
            for c in (order if i % 2 == 0 else order[::-1]):
                cost[c].append(prep(c))
                t[c].append(read(tiny if c == "junk64" else buf))
        row = {"bytes": nbytes, "read_s": {c: quart(t[c]) for c in conds},
               "junk_over_warm": quart([b / a for a, b in zip(t["warm"], t["junk"])]),
               "flush_over_warm": quart([b / a for a, b in zip(t["warm"], t["flush"])]),
               "junk_over_flush": quart([a / b for a, b in zip(t["junk"], t["flush"])]),
               # the junk read's data part: (b) less the same repeat's 64-byte call after a junk read, over (c)
               "junk_data_over_flush": quart([(a - z) / b for a, z, b in zip(t["junk"], t["junk64"], t["flush"])]),
               "evict_wall_s": {"junk read": quart([w for w, _ in cost["junk"]]), "flush": quart([w for w, _ in cost["flush"]])},
               "evict_cpu_s": {"junk read": quart([c for _, c in cost["junk"]]), "flush": quart([c for _, c in cost["flush"]])}}
        rows.append(row)
        print(f"{nbytes >> 10} KiB: read warm {fmt_q(row['read_s']['warm'], 1e6, 1)} us, junk {fmt_q(row['read_s']['junk'], 1e6, 1)}, "
              f"flush {fmt_q(row['read_s']['flush'], 1e6, 1)}, 64 B after junk {fmt_q(row['read_s']['junk64'], 1e6, 1)}; "
              f"junk/flush {fmt_q(row['junk_over_flush'])}, (junk - 64 B)/flush {fmt_q(row['junk_data_over_flush'])}; "
              f"evict: junk {fmt_q(row['evict_wall_s']['junk read'], 1e3)} ms, flush {fmt_q(row['evict_wall_s']['flush'], 1e3, 3)} ms",
              flush=True)
    return rows


def default_setting(setting: dict, rounds: int, pairs: int, log=print) -> dict:
    """Part 3: one default-config setting's cold bound fraction by both evictions, alternating rounds."""
    from prt_torch.harness.config import load_config
    from prt_torch.harness.evaluate import Evaluator
    from prt_torch.harness.run import compute_transfer, load_mesh_within_budget

    cfg = load_config("default", [f"cache_dir={ROOT / 'cache'}"])
    mesh, _ = load_mesh_within_budget(cfg)
    t0 = time.perf_counter()
    tr, tinfo = compute_transfer(cfg, mesh, Path(cfg["cache_dir"]), progress=False)
    log(f"transfer {tuple(tr.data.shape)} ({tinfo['cache']}, {time.perf_counter() - t0:.1f} s)")
    ev = Evaluator(tr)
    lights, _, views = ev.config_views(cfg)
    params = dict(setting)
    codec = codecs.get(params.pop("type"), **params)
    enc = codec.fit_encode(ev.X, matrix_shape=ev.matrix_shape, **ev.fit_kwargs(codec))
    # as harness.run.time_setting: the prepared relighter into a reused result against its own bound
    L0, v0 = ev.codec_light(codec, lights[0]), views[0]
    buf = torch.empty_like(codec.relight(enc, L0, view=v0))
    prepared = codec.relighter(enc, v0)

    def relit_into():
        return prepared(L0, out=buf)

    read_bytes, out_bytes = codec.relight_bytes(enc, v0), ev.V * L0.shape[-1] * 4
    bound = io_bound_fn(read_bytes, out_bytes)
    for _ in range(3):
        relit_into()
        bound()
    ws = working_set(relit_into, bound)
    out = {"setting": setting, "vertices": ev.V, "bound_bytes": {"read": read_bytes, "written": out_bytes}, "pairs": pairs}
    # as prt bench times it (the process's threads, wall clock), and in one thread by its CPU time (what the
    # machine's load cannot stretch)
    for mode in ("threads", "one thread"):
        runs = {"flush": [], "junk read": []}
        for r in range(rounds):
            for way in (("flush", "junk read") if r % 2 == 0 else ("junk read", "flush")):
                t0 = time.perf_counter()
                kw = {"repeats": pairs, "evict": ws if way == "flush" else None}
                if mode == "one thread":
                    with torch_threads(1):
                        p = measure_paired_cold(relit_into, bound, clock=time.thread_time, **kw)
                else:
                    p = measure_paired_cold(relit_into, bound, **kw)
                wall = time.perf_counter() - t0
                runs[way].append({"fraction_cold": p.speedup, "q1": p.ratio.q1, "q3": p.ratio.q3, "relight_s": p.test.median,
                                  "bound_s": p.peer.median, "eviction": p.eviction, "wall_s": wall,
                                  "load_average_1min": p.contention["load_average_1min"]})
                log(f"{mode} round {r} {way}: cold fraction {p.speedup:.3f} [{p.ratio.q1:.3f}-{p.ratio.q3:.3f}], relight "
                    f"{p.test.median * 1e3:.3f} ms, bound {p.peer.median * 1e3:.3f} ms, evict {p.eviction['bytes'] / 2**20:.1f} "
                    f"MiB {p.eviction['median_s'] * 1e3:.2f} ms/call, {wall:.1f} s")
        out[mode] = {"runs": runs, "ratio_of_fractions": [a["fraction_cold"] / b["fraction_cold"]
                                                          for a, b in zip(runs["flush"], runs["junk read"])]}
    out["flushed_bytes"] = out["threads"]["runs"]["flush"][0]["eviction"]["bytes"]
    return out


def report(res: dict) -> str:
    m = res["machine"]
    mib = 1 << 20
    lines = [
        "# Cold-cache timing: flushing the timed call's data vs reading junk through the caches",
        "",
        f"CPU: {cpu_label(m)}; {m['cores']} cores; sysfs's largest cache {res['llc_bytes'] / mib:.0f} MiB, so the junk read is "
        f"{res['junk_bytes'] / mib:.0f} MiB; flush method `{res['flush_method']}`. Load average (1 min) "
        f"{res['load_before']:.1f} before, {res['load_after']:.1f} after (2 cores shared with other engineers' runs). "
        f"torch {m['torch']}. Generated by `benchmarks/bench_cold_evict.py` (its docstring says what is measured).",
        "",
        "## 1. One read of a buffer: warm, after the junk read, after the flush",
        "",
        f"`buf.sum()` of float32, one thread, this thread's CPU time (µs), median [quartiles] of {res['repeats']} repeats, the "
        "conditions interleaved per repeat (order rotated); ratios per repeat. **64 B after junk**: a read of a 16-float "
        "tensor after the junk read, the part of the junk condition that is not the buffer's data (the junk read also "
        "evicts the code, the interpreter's and torch's state and the page tables a call walks); **(junk − 64 B) / "
        "flush** ≈ 1: the two evictions leave the data equally cold.",
        "",
        "| working set | warm µs | after junk read µs | after flush µs | 64 B after junk µs | junk / warm | flush / warm | "
        "junk / flush | (junk − 64 B) / flush |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in res["reads"]:
        lines.append(f"| {r['bytes'] / 1024:.0f} KiB | {fmt_q(r['read_s']['warm'], 1e6, 1)} | {fmt_q(r['read_s']['junk'], 1e6, 1)} | "
                     f"{fmt_q(r['read_s']['flush'], 1e6, 1)} | {fmt_q(r['read_s']['junk64'], 1e6, 1)} | {fmt_q(r['junk_over_warm'])} | "
                     f"{fmt_q(r['flush_over_warm'])} | {fmt_q(r['junk_over_flush'])} | {fmt_q(r['junk_data_over_flush'])} |")
    lines += ["", "## 2. What each eviction costs per call (ms)", "",
              f"The junk buffer's allocation and fill, once per process now (per `measure_paired_cold` call before): "
              f"{res['junk_alloc_s'] * 1e3:.0f} ms wall. Wall clock (what the suite and `prt bench` wait) and the process's CPU "
              f"time (the junk read runs at the process's {res['machine']['torch_threads']} threads, the flush in one).", "",
              "| working set | junk read wall | flush wall | junk / flush (wall) | junk read CPU | flush CPU |",
              "|---|---|---|---|---|---|"]
    for r in res["reads"]:
        j, f = r["evict_wall_s"]["junk read"], r["evict_wall_s"]["flush"]
        jc, fc = r["evict_cpu_s"]["junk read"], r["evict_cpu_s"]["flush"]
        lines.append(f"| {r['bytes'] / 1024:.0f} KiB | {fmt_q(j, 1e3, 1)} | {fmt_q(f, 1e3, 3)} | {j['median'] / f['median']:.0f}× | "
                     f"{fmt_q(jc, 1e3, 1)} | {fmt_q(fc, 1e3, 3)} |")
    d = res.get("default")
    if d:
        lines += ["", "## 3. One default `prt bench` setting's cold column, both ways", "",
                  f"Setting {d['setting']} on the default config's mrt transfer ({d['vertices']} vertices); bound: "
                  f"{d['bound_bytes']['read']} B read, {d['bound_bytes']['written']} B written; the flush evicts "
                  f"{d['flushed_bytes']} B per call (working_set of the prepared relighter and the bound: the codec's model and "
                  f"plans, the encoding, the light, the output, the bound's buffers). {d['pairs']} single-call pairs per "
                  f"measurement (`metrics.cold_pairs`' default), rounds alternating which eviction goes first; as `prt bench` "
                  f"times it (**threads**: the process's {res['machine']['torch_threads']} threads, wall clock) and in **one "
                  f"thread** by its CPU time (`measure_paired_cold(clock=time.thread_time)`).", "",
                  "| timing | round | eviction | cold fraction [IQR] | relight ms | bound ms | eviction per call ms | "
                  "measurement wall s | load |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for mode in ("threads", "one thread"):
            runs = d[mode]["runs"]
            for i in range(len(runs["flush"])):
                for way in ("flush", "junk read"):
                    x = runs[way][i]
                    lines.append(f"| {mode} | {i} | {x['eviction']['method']} | {x['fraction_cold']:.3f} [{x['q1']:.3f}–{x['q3']:.3f}] | "
                                 f"{x['relight_s'] * 1e3:.3f} | {x['bound_s'] * 1e3:.3f} | {x['eviction']['median_s'] * 1e3:.2f} | "
                                 f"{x['wall_s']:.1f} | {x['load_average_1min']:.1f} |")
        for mode in ("threads", "one thread"):
            rr = d[mode]["ratio_of_fractions"]
            lines += ["", f"{mode}: flush / junk fraction per round {', '.join(f'{x:.3f}' for x in rr)} "
                          f"(median {statistics.median(rr):.3f})."]
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--sizes", default="256K,4M,64M")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--pairs", type=int, default=9)
    ap.add_argument("--setting", default="cpca:clusters=16,vectors=8", help="TYPE:key=value,... of the default config's codecs")
    ap.add_argument("--no-default", action="store_true", help="skip part 3 (the default config's transfer and one setting)")
    ap.add_argument("--no-write", action="store_true", help="print only")
    a = ap.parse_args(argv)
    if flush_method() is None:
        raise SystemExit(f"bench_cold_evict: no cache-flush helper here ({timing._FLUSH.get('why')})")
    sizes = [parse_size(s) for s in a.sizes.split(",")]
    t, _, kv = a.setting.partition(":")
    setting = {"type": t, **{k: int(v) for k, v in (p.split("=") for p in kv.split(",") if p)}}
    load_before = os.getloadavg()[0]
    junk_bytes = max(64 * 1024 ** 2, 4 * last_level_cache_bytes())
    timing.release_eviction_buffer()
    t0 = time.perf_counter()
    timing._junk(junk_bytes)
    junk_alloc = time.perf_counter() - t0
    res = {"machine": machine_info(), "llc_bytes": last_level_cache_bytes(), "junk_bytes": junk_bytes, "flush_method": flush_method(),
           "repeats": a.repeats, "load_before": load_before, "junk_alloc_s": junk_alloc}
    print(f"{cpu_label(res['machine'])}; junk {junk_bytes >> 20} MiB allocated in {junk_alloc:.2f} s; load {load_before:.1f}", flush=True)
    res["reads"] = check_reads(sizes, a.repeats, junk_bytes)
    if not a.no_default:
        res["default"] = default_setting(setting, a.rounds, a.pairs)
    res["load_after"] = os.getloadavg()[0]
    md = report(res)
    print(md)
    if not a.no_write:
        io.atomic_write_json(OUT / "cold_evict.json", res)
        io.atomic_write_text(OUT / "cold_evict.md", md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
