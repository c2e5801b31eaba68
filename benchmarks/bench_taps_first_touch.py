"""Why the default benchmark's Gaussian part had a bimodal "× the uncompressed rate" (45× or 95× for
cpca 16×7 between runs with unchanged code), and the measurement once ``relight.apply_taps`` is blocked.

The part's uncompressed peer (``Evaluator.uncompressed`` → ``relight.apply_taps``) gathered every
vertex's three tapped view rows at once: a fresh ``V·3·384`` float32 temporary (47 MB at 10 242
vertices) every call. Above glibc's largest dynamic mmap threshold (32 MiB), such a block is
served from the heap only when the heap happens to hold a free chunk that large (it depends on
what the process allocated and freed before: the fits of the other settings), else it is mapped
anew and first-touch page-faulted every call (~11.5 k minor faults). Which of the two a run got
decided the peer's one-thread time (24.6 vs 49.5 ms in the baseline's runs); the codec side
allocates nothing that large. ``apply_taps`` now gathers by blocks of ``relight.TAPS_BLOCK_BYTES``
into one reused buffer: the peer's time no longer depends on the allocator's state.

Each allocator state runs in its own process (glibc reads ``MALLOC_*`` at start-up):
``default`` (whatever the process's history gives), ``mmap`` (``MALLOC_MMAP_THRESHOLD_=131072``
fixed: every block ≥ 128 KiB mapped anew and unmapped on free: the slow mode, forced) and
``heap`` (``MALLOC_MMAP_THRESHOLD_=2**30``, ``MALLOC_TRIM_THRESHOLD_=2**32``: everything reused
from the heap: the fast mode, forced). In each: (1) the peer alone, the whole gather (before:
``TAPS_BLOCK_BYTES`` set above the gather's size) paired with the blocked one (after), one thread,
each sample in the thread's CPU time (``time.thread_time``: page faults are system time of the
thread, so they count), with minor page faults per call; (2) the harness's own speed-up column
(``harness.run.time_setting``, as ``prt bench`` measures it) for the part's settings given, before
and after, in the same process.

Run: .venv/bin/python benchmarks/bench_taps_first_touch.py [--settings cpca:16:7] [--states default,mmap,heap]
     [--size medium] [--cache cache/bench_taps_first_touch]
     .venv/bin/python benchmarks/bench_taps_first_touch.py --shapes 10242:64:16:4,10242:42:384:3   (the peer alone)
Writes reports/benchmarks/taps_first_touch.{md,json} (the transport table is cached under --cache).
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402


ROOT = Path(__file__).resolve().parents[1]
STATES = {"default": {}, "mmap": {"MALLOC_MMAP_THRESHOLD_": str(128 * 1024)},
          "heap": {"MALLOC_MMAP_THRESHOLD_": str(2**30), "MALLOC_TRIM_THRESHOLD_": str(2**32)}}
WHOLE = 1 << 62  # TAPS_BLOCK_BYTES above any gather: apply_taps's single gather (the code before)


def _faults_per_call(fn, calls: int = 5) -> float:
    fn()
    f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    for _ in range(calls):
        fn()
    return (resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0) / calls


def child(a) -> dict:
    from prt_torch import relight
    from prt_torch.harness.config import expand_codecs, load_config, part_configs
    from prt_torch.harness.evaluate import Evaluator
    from prt_torch.harness.run import compute_transfer, evaluate_setting, load_mesh_within_budget, measure_uncompressed, time_setting
    from prt_torch.harness.timing import measure_paired, torch_threads

    cfg = load_config("default")
    cfg["output_dir"] = tempfile.mkdtemp(prefix="taps_ft_")
    cfg["cache_dir"] = str(a.cache)
    sub = [s for s in part_configs(cfg) if s["name"] == "gaussian"][0]
    if a.size:
        sub["scene"]["size"] = a.size
    mesh, _ = load_mesh_within_budget(sub)
    tr, _ = compute_transfer(sub, mesh, Path(sub["cache_dir"]), progress=False)
    ev = Evaluator(tr)
    lights, _, views = ev.config_views(sub)
    refs, _ = measure_uncompressed(ev, lights, views, sub["metrics"])
    blocked = relight.TAPS_BLOCK_BYTES

    def peer(block):
        def f():
            relight.TAPS_BLOCK_BYTES = block
            return ev.uncompressed(lights[0], views[0])
        return f

    out = {"state": a.child, "vertices": ev.V, "table": list(tr.data.shape), "load": [os.getloadavg()[0]]}
    with torch_threads(1):
        p = measure_paired(peer(blocked), peer(WHOLE), repeats=15, warmup=2, clock=time.thread_time)
        out["peer"] = {"whole_s": p.peer.median, "blocked_s": p.test.median, "whole_over_blocked": p.ratio.median,
                       "ratio_q1": p.ratio.q1, "ratio_q3": p.ratio.q3,
                       "whole_faults_per_call": _faults_per_call(peer(WHOLE)),
                       "blocked_faults_per_call": _faults_per_call(peer(blocked))}
        out["peer"]["max_abs_diff"] = float((peer(WHOLE)() - peer(blocked)()).abs().max())
    out["settings"] = []
    want = [tuple(s.split(":")) for s in a.settings.split(",")]
    for s in expand_codecs(sub["codecs"]):
        key = (s["type"],) + tuple(str(s[k]) for k in ("clusters", "vectors", "lobes") if k in s)
        if key not in want:
            continue
        rec, codec, enc = evaluate_setting(ev, s, lights, views, sub, refs, timed=False)
        row = {"setting": ":".join(key)}
        for name, block in (("before", WHOLE), ("after", blocked), ("before again", WHOLE), ("after again", blocked)):
            relight.TAPS_BLOCK_BYTES = block
            r = time_setting(ev, codec, enc, lights, views, sub)
            row[name] = {"speedup_vs_uncompressed": r["speedup_vs_uncompressed"],
                         "peer_s": r["speedup_floor"]["peer_s"], "codec_s": r["speedup_floor"]["test_s"]}
        relight.TAPS_BLOCK_BYTES = blocked
        out["settings"].append(row)
    out["load"].append(os.getloadavg()[0])
    return out


def shapes(spec: str) -> list[str]:
    """The peer alone on random tables of given shapes (``V:R:N:k``, comma-separated), blocked vs whole,
    paired in this process (one thread, thread CPU time; floor of 40 short pairs as the harness)."""
    from prt_torch import relight
    from prt_torch.harness.timing import measure_paired, torch_threads

    out = []
    g = torch.Generator().manual_seed(0)
    for item in spec.split(","):
        V, R, N, k = (int(x) for x in item.split(":"))
        A, L = torch.rand(V, R, N, generator=g), torch.rand(3, N, generator=g)
        idx, w = torch.randint(0, R, (V, k), generator=g), torch.rand(V, k, generator=g)

        def f(block, A=A, L=L, idx=idx, w=w):
            def run():
                relight.TAPS_BLOCK_BYTES = block
                return relight.apply_taps(A, L, idx, w)
            return run
        blocked = relight.TAPS_BLOCK_BYTES
        with torch_threads(1):
            p = measure_paired(f(blocked), f(WHOLE), repeats=21, warmup=3, clock=time.thread_time, floor_pairs=40)
        relight.TAPS_BLOCK_BYTES = blocked
        out.append(f"| {V}×{R}×{N}, {k} taps | {p.peer.median * 1e3:.3f} | {p.test.median * 1e3:.3f} | {p.ratio.median:.3f} "
                   f"({p.ratio.q1:.3f}–{p.ratio.q3:.3f}) | {p.speedup:.3f} | {os.getloadavg()[0]:.1f} |")
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--settings", default="cpca:16:7", help="the part's settings, type:clusters:vectors or gaussian:lobes")
    ap.add_argument("--states", default="default,mmap,heap")
    ap.add_argument("--size", default=None)
    ap.add_argument("--cache", type=Path, default=ROOT / "cache" / "bench_taps_first_touch")
    ap.add_argument("--out", type=Path, default=ROOT / "reports" / "benchmarks" / "taps_first_touch")
    ap.add_argument("--shapes", default=None, metavar="V:R:N:k,...",
                    help="only the peer alone on random tables of these shapes in this process (default allocator), printed "
                         "as table rows: e.g. 10242:64:16:4 (the default MRT run's peer), 10242:42:384:3 (the Gaussian part's)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.shapes:
        print("| table, taps | whole ms | blocked ms | whole / blocked (q1–q3) | floor ratio | load |\n|---|---|---|---|---|---|")
        print("\n".join(shapes(a.shapes)))
        return 0
    if a.child:
        print(json.dumps(child(a)))
        return 0
    from prt_torch import io
    from prt_torch.harness.timing import cpu_label, machine_info

    info = machine_info()
    runs = []
    load0 = os.getloadavg()
    for st in a.states.split(","):
        env = {**os.environ, **STATES[st]}
        cmd = [sys.executable, __file__, "--child", st, "--settings", a.settings, "--cache", str(a.cache)]
        if a.size:
            cmd += ["--size", a.size]
        r = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=ROOT)
        if r.returncode != 0:
            sys.exit(r.stderr[-3000:])
        runs.append(json.loads(r.stdout.strip().splitlines()[-1]))
        print(json.dumps(runs[-1]), flush=True)
    load1 = os.getloadavg()
    lines = ["# The Gaussian part's uncompressed peer: first-touch page faults (`benchmarks/bench_taps_first_touch.py`)", "",
             f"CPU {cpu_label(info)} (the kernels' AVX2 paths; no AVX-512 here), {info['cores']} cores shared with other "
             f"engineers' jobs: load average {load0[0]:.1f} before, {load1[0]:.1f} after. Table "
             f"{runs[0]['table']} float32 (the default config's Gaussian part, {runs[0]['vertices']} vertices), "
             "first light and view. One torch thread, every sample in the thread's CPU time (`time.thread_time`, "
             "which counts the page faults' system time), interleaved pairs in one process per allocator state.", "",
             "## The peer alone: whole gather (before) vs blocked (after)", "",
             "| allocator state | whole gather ms | blocked ms | whole / blocked (q1–q3) | minor faults per call whole / blocked | max abs diff |",
             "|---|---|---|---|---|---|"]
    for r in runs:
        p = r["peer"]
        lines.append(f"| {r['state']} | {p['whole_s'] * 1e3:.1f} | {p['blocked_s'] * 1e3:.1f} | {p['whole_over_blocked']:.2f} "
                     f"({p['ratio_q1']:.2f}–{p['ratio_q3']:.2f}) | {p['whole_faults_per_call']:.0f} / {p['blocked_faults_per_call']:.0f} | "
                     f"{p['max_abs_diff']:.1e} |")
    lines += ["", "## The harness's speed-up column (`harness.run.time_setting`, as `prt bench` times it)", "",
              "| allocator state | setting | before: × uncompressed (peer ms / codec ms) | after | before, again | after, again |",
              "|---|---|---|---|---|---|"]
    for r in runs:
        for s in r["settings"]:
            cell = lambda x: f"{x['speedup_vs_uncompressed']:.1f}× ({x['peer_s'] * 1e3:.1f} / {x['codec_s'] * 1e3:.2f})"  # noqa: E731
            lines.append(f"| {r['state']} | {s['setting']} | {cell(s['before'])} | {cell(s['after'])} | "
                         f"{cell(s['before again'])} | {cell(s['after again'])} |")
    lines.append("")
    a.out.parent.mkdir(parents=True, exist_ok=True)
    io.atomic_write_text(a.out.with_suffix(".md"), "\n".join(lines))
    io.atomic_write_text(a.out.with_suffix(".json"), json.dumps({"runs": runs, "machine": info, "load": [load0, load1]}, indent=1))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
