"""Stage-by-stage cost of the default benchmark's Gaussian part (issue 42 part 2).

Runs the ``gaussian`` part of ``configs/default.yaml`` (or a size / codec list given here) through
the harness's own functions, one stage at a time, and records per stage: wall time, this process's
CPU time (user + system, with its ray-casting children), minor page faults, the resident set at
the end and its peak within the stage (``/proc/self/clear_refs`` resets the high-water mark), and
the load average before and after. Stages: mesh, transport table (precompute into a fresh cache
unless ``--cache`` holds it), evaluator and uncompressed references, then per codec setting its fit
(``fit_encode``), its error and PSNR pass (decode, per light and view) and its relighting timings
(``harness.run.time_setting``: the paired repeats, broken down by timing function).

Run: .venv/bin/python benchmarks/profile_gaussian_part.py --size medium [--codecs gaussian,pca]
     [--cache DIR] [--json out.json]
(about 5 min at size medium on 2 cores with every codec; the machine's load is printed).
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import shutil  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch.harness.config import expand_codecs, load_config, part_configs  # noqa: E402
from prt_torch.harness.evaluate import Evaluator  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402
from prt_torch.harness.run import (compute_transfer, evaluate_setting, load_mesh_within_budget,  # noqa: E402
                                   measure_uncompressed, setting_id, time_setting)

ROWS: list[dict] = []


def _rss_kib() -> tuple[int, int]:
    """(current, peak since the last reset) resident set of this process in KiB."""
    cur = peak = 0
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                cur = int(line.split()[1])
            elif line.startswith("VmHWM:"):
                peak = int(line.split()[1])
    return cur, peak


@contextlib.contextmanager
def stage(name: str):
    """Record one stage's wall, CPU (user/system, self + children), minor faults, RSS."""
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")  # reset VmHWM to the current RSS
    l0 = os.getloadavg()[0]
    s0, c0 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    yield
    wall = time.perf_counter() - t0
    s1, c1 = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    cur, peak = _rss_kib()
    row = {"stage": name, "wall_s": wall,
           "user_s": (s1.ru_utime - s0.ru_utime) + (c1.ru_utime - c0.ru_utime),
           "sys_s": (s1.ru_stime - s0.ru_stime) + (c1.ru_stime - c0.ru_stime),
           "minor_faults": (s1.ru_minflt - s0.ru_minflt) + (c1.ru_minflt - c0.ru_minflt),
           "rss_gib": cur / 2**20, "peak_rss_gib": peak / 2**20, "load": [l0, os.getloadavg()[0]]}
    ROWS.append(row)
    print(f"{name:55s} wall {wall:7.1f} s  user {row['user_s']:7.1f}  sys {row['sys_s']:6.1f}  "
          f"faults {row['minor_faults'] / 1e6:6.2f} M  rss {row['rss_gib']:.2f} (peak {row['peak_rss_gib']:.2f}) GiB  "
          f"load {l0:.1f}->{row['load'][1]:.1f}", flush=True)


def _trace_timing() -> dict:
    """Wrap the timing functions ``harness.run.time_setting`` calls so that each call's wall and
    CPU time are summed per function name (the relight-timing stage broken down)."""
    import prt_torch.harness.run as hr

    spent: dict = {}
    for name in ("measure_paired", "measure_paired_cold", "rate_policy"):
        fn = getattr(hr, name)

        def wrapped(*args, _fn=fn, _name=name, **kw):
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                return _fn(*args, **kw)
            finally:
                w, c, n = spent.get(_name, (0.0, 0.0, 0))
                spent[_name] = (w + time.perf_counter() - t0, c + time.process_time() - c0, n + 1)
        setattr(hr, name, wrapped)
    return spent


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="default")
    ap.add_argument("--size", default=None, help="the part's scene size (default: the config's)")
    ap.add_argument("--codecs", default=None, help="comma-separated codec types of the part to run (default: all)")
    ap.add_argument("--override", action="append", default=[], help="part codec override: INDEX.KEY=VALUE (YAML value)")
    ap.add_argument("--cache", default=None, help="cache directory (default: a fresh temporary one: the precompute is timed)")
    ap.add_argument("--no-timing", action="store_true", help="skip the relighting timings")
    ap.add_argument("--json", default=None)
    ap.add_argument("--resolve-factor", type=float, nargs="+", default=[None],
                    help="fit each Gaussian setting with its narrowest lobe at each of these texel spacings, paired in this run "
                         "(codecs.gaussian.fit.RESOLVE_FACTOR; default: the codec's)")
    ap.add_argument("--lm-variants", nargs="+", default=[None], metavar="MAX_ITER:TRIES",
                    help="fit each Gaussian setting with each of these LM budgets, paired in this run: max_iter and damped "
                         "solves per iteration (codecs.gaussian.fit.LM_TRIES), e.g. 20:1 30:5 (before / after issue 42 §2)")
    a = ap.parse_args(argv)
    cfg = load_config(a.config)
    scratch = [tempfile.mkdtemp(prefix="prof_part_")] + ([] if a.cache else [tempfile.mkdtemp(prefix="prof_cache_")])
    try:
        return _run(a, cfg, scratch)
    finally:
        for d in scratch:  # the run writes nothing there that is kept; a fresh cache would be the whole table
            shutil.rmtree(d, ignore_errors=True)


def _run(a, cfg: dict, scratch: list[str]) -> int:
    import yaml

    cfg["output_dir"] = scratch[0]
    cfg["cache_dir"] = a.cache or scratch[1]
    sub = [s for s in part_configs(cfg) if s["name"] == "gaussian"][0]
    if a.size:
        sub["scene"]["size"] = int(a.size) if a.size.isdigit() else a.size
    for o in a.override:
        k, v = o.split("=", 1)
        i, key = k.split(".", 1)
        sub["codecs"][int(i)][key] = yaml.safe_load(v)
    want = set(a.codecs.split(",")) if a.codecs else None
    spent = _trace_timing()
    print(f"load {os.getloadavg()}, torch threads {torch.get_num_threads()}, OMP_WAIT_POLICY={os.environ.get('OMP_WAIT_POLICY')}")
    with stage("mesh"):
        mesh, _ = load_mesh_within_budget(sub)
    with stage(f"transport table ({mesh.num_vertices} vertices)"):
        tr, tinfo = compute_transfer(sub, mesh, Path(sub["cache_dir"]), progress=False)
    print(f"  table {tuple(tr.data.shape)} {tr.data.dtype} ({tinfo['cache']})")
    with stage("evaluator + uncompressed references"):
        ev = Evaluator(tr)
        lights, _, views = ev.config_views(sub)
        refs, unc = measure_uncompressed(ev, lights, views, sub["metrics"])
    records = []
    from prt_torch.codecs.gaussian import fit as gfit

    rf0, tries0 = gfit.RESOLVE_FACTOR, gfit.LM_TRIES
    settings = [(s, rf, lv) for s in expand_codecs(sub["codecs"])
                for rf in (a.resolve_factor if s["type"] == "gaussian" else [None])
                for lv in (a.lm_variants if s["type"] == "gaussian" else [None])]
    for s, rf, lv in settings:
        if want and s["type"] not in want:
            continue
        gfit.RESOLVE_FACTOR = rf0 if rf is None else rf
        gfit.LM_TRIES = tries0
        if lv is not None:
            mi, tr_ = (int(x) for x in lv.split(":"))
            s = {**s, "max_iter": mi}
            gfit.LM_TRIES = tr_
        sid = (setting_id(s) + ("" if rf is None else f" (resolve factor {rf:g})")
               + ("" if lv is None else f" (max_iter {s['max_iter']}, {gfit.LM_TRIES} tries)"))
        t0 = time.perf_counter()
        with stage(f"{sid}: fit + error/PSNR"):
            rec, codec, enc = evaluate_setting(ev, s, lights, views, sub, refs, timed=False)
        ROWS[-1]["encode_s"] = rec["encode_s"]
        print(f"  encode {rec['encode_s']:.1f} s (error/PSNR {time.perf_counter() - t0 - rec['encode_s']:.1f} s), "
              f"{rec['bytes_per_vertex']:.1f} B/vertex, PSNR lights {rec['psnr_lights_db']:.2f} dB, rel SE {rec['relative_se']:.4f}")
        if not a.no_timing:
            spent.clear()
            with stage(f"{sid}: relight timings"):
                rec.update(time_setting(ev, codec, enc, lights, views, sub))
            ROWS[-1]["timing_calls"] = {k: {"wall_s": w, "cpu_s": c, "calls": n} for k, (w, c, n) in spent.items()}
            print("  " + ", ".join(f"{k} x{n}: {w:.1f} s wall, {c:.1f} s CPU" for k, (w, c, n) in spent.items()))
        records.append({k: rec.get(k) for k in ("setting_id", "encode_s", "bytes_per_vertex", "psnr_lights_db", "relative_se",
                                                "speedup_vs_uncompressed")} | {"resolve_factor": gfit.RESOLVE_FACTOR, "lm_tries": gfit.LM_TRIES,
                                                                                "max_iter": s.get("max_iter")})
        del codec, enc
    gfit.RESOLVE_FACTOR, gfit.LM_TRIES = rf0, tries0
    tot = {k: sum(r[k] for r in ROWS) for k in ("wall_s", "user_s", "sys_s", "minor_faults")}
    peak = max(r["peak_rss_gib"] for r in ROWS)
    print(f"total: wall {tot['wall_s']:.1f} s, CPU {tot['user_s'] + tot['sys_s']:.1f} s ({tot['user_s']:.1f} user + "
          f"{tot['sys_s']:.1f} sys), {tot['minor_faults'] / 1e6:.2f} M minor faults, peak RSS {peak:.2f} GiB; load {os.getloadavg()}")
    if a.json:
        atomic_write_text(Path(a.json), json.dumps({"stages": ROWS, "records": records, "total": tot, "peak_rss_gib": peak,
                                            "argv": sys.argv[1:]}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
