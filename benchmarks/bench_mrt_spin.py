"""Benchmark (issue 42 §3 item 4): CPU over wall of the MRT precompute, by OpenMP wait policy, against
bare Embree on the same rays.

    .venv/bin/python benchmarks/bench_mrt_spin.py [--repeats 3] [--scene bumpy_sphere --size medium]
        [--out reports/benchmarks/mrt_spin.md]

Each repeat runs, in child processes and alternating the order,

* ``prt precompute SCENE --size SIZE --kind mrt`` (the defaults: 5 bands, M = 11, 1024 samples,
  ray-casting workers as the CLI chooses) with ``OMP_WAIT_POLICY`` unset (``prt_torch``'s import-time
  choice: spinning threads unless other processes hold the cores, the choice printed), ``ACTIVE``
  (threads spin while they wait) and ``PASSIVE`` (they sleep): wall seconds, CPU seconds of the whole process tree (user + system of
  the child and the workers it reaped: ``RUSAGE_CHILDREN``), and the precompute's own seconds (its
  ``rays in`` figure);
* bare Embree: the same rays (every ray-casting call of one MRT precompute recorded, ``RecordRays``)
  replayed on a ray caster with as many workers, its wall and CPU (this process and its workers,
  from ``/proc/<pid>/stat``).

CPU / wall above the bare rays' own CPU / wall is work the precompute adds (GEMMs, the BRDF, the
file) or waste (threads spinning while they wait). The machine is shared (2 cores): the load
average is recorded with each row.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def _tree_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


#: a child that imports torch before prt_torch: libgomp reads OMP_WAIT_POLICY when torch loads, so prt_torch's
#: import-time choice (PASSIVE on a busy machine) comes too late and the libgomp default (spin, then sleep) holds —
#: what a quiet machine runs, reproduced on a busy one
_TORCH_FIRST = "import sys; sys.path.insert(0, sys.argv.pop(1)); import torch; from prt_torch.cli import main; sys.exit(main(sys.argv[1:]))"


def cli_run(scene: str, size: str, policy: str | None, out: Path, code: str | None = None) -> dict:
    """``prt precompute --kind mrt`` in a child process: wall, the tree's CPU, the precompute's seconds.
    ``policy`` 'default': the libgomp default (torch imported first); ``code``: the tree whose
    ``prt_torch`` runs (default this one)."""
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy and policy != "default":
        env["OMP_WAIT_POLICY"] = policy
    args = ["precompute", scene, "--size", size, "--kind", "mrt", "-o", str(out), "--overwrite", "--no-progress"]
    if policy == "default" or code is not None:
        env["PYTHONPATH"] = str(code or ROOT)
        cmd = [sys.executable, "-c", _TORCH_FIRST, str(code or ROOT), *args]
    else:
        cmd = [sys.executable, "-m", "prt_torch", *args]
    load = os.getloadavg()[0]
    choice = None
    if not policy:  # what prt_torch's import-time rule chooses now (spinning unless other processes hold the cores)
        choice = subprocess.run([sys.executable, "-c", "import prt_torch; print(prt_torch.OMP_POLICY_CHOICE)"], env=env,
                                capture_output=True, text=True).stdout.strip()
    c0, t0 = _tree_cpu(), time.perf_counter()
    p = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - t0, _tree_cpu() - c0
    if p.returncode != 0:
        raise RuntimeError(p.stderr[-2000:])
    m = re.search(r"(\d+) rays in ([0-9.]+) s", p.stderr)
    label = (policy or f"unset: {choice}") + ("" if code is None else f" [{Path(code).name}]")
    return {"policy": label, "wall_s": wall, "cpu_s": cpu, "rays": int(m.group(1)) if m else None,
            "precompute_s": float(m.group(2)) if m else None, "load": load, "load_end": os.getloadavg()[0]}


def _proc_cpu(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def bare_child(scene: str, size: str) -> dict:
    """Record one MRT precompute's rays (in-process), then replay them bare on a caster with the CLI's workers."""
    import warnings

    warnings.simplefilter("ignore")
    from bench_transfer_diffuse import RecordRays

    from prt_torch.scene import RayCaster, load_scene
    from prt_torch.transfer import RunOptions, get_kind
    from prt_torch.transfer.glossy import default_chunk

    mesh = load_scene(scene, size=size)
    kw = get_kind("mrt").defaults()
    V = mesh.num_vertices
    rays = V * max(1, int(kw["samples"]) // 2)
    from prt_torch.scene import default_workers

    workers = default_workers() if rays >= 4_000_000 else 1  # the CLI's rule (glossy.run_exit_transfer)
    with RecordRays() as rec:
        get_kind("mrt").precompute(mesh, {}, run=RunOptions(workers=1, chunk_size=default_chunk(int(kw["samples"]))))
    out = []
    for _ in range(2):
        with RayCaster(mesh, workers=workers, offset=RunOptions.offset) as caster:
            caster.start()
            time.sleep(0.5)  # the workers built their scenes
            pids = [p.pid for p in (caster._pool or [])]
            c0 = time.process_time() + sum(_proc_cpu(p) for p in pids)
            t0 = time.perf_counter()
            rec.replay(caster)
            wall = time.perf_counter() - t0
            cpu = time.process_time() + sum(_proc_cpu(p) for p in pids) - c0
        out.append({"wall_s": wall, "cpu_s": cpu, "workers": workers, "rays": sum(rec.rays.values()), "load": os.getloadavg()[0]})
    return {"bare": out}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="bumpy_sphere")
    ap.add_argument("--size", default="medium")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--bare-child", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--before", default=None, metavar="REV",
                    help="also run the code of git revision REV (extracted to a temporary tree), libgomp default policy")
    ap.add_argument("--policies", nargs="+", default=["unset", "ACTIVE", "PASSIVE"],
                    help="arms: unset (prt_torch's import-time choice), default (libgomp's: torch imported first), ACTIVE, PASSIVE")
    ap.add_argument("--out", default=str(ROOT / "reports/benchmarks/mrt_spin.md"))
    args = ap.parse_args(argv)
    if args.bare_child:
        print("JSON " + json.dumps(bare_child(args.scene, args.size)))
        return 0
    if args.repeats < 1:
        print(f"bench_mrt_spin: --repeats {args.repeats}; accepted: 1 or more", file=sys.stderr)
        return 2
    from prt_torch import io
    from prt_torch.harness.timing import cpu_label, machine_info

    info = machine_info()
    info["command"] = "python benchmarks/bench_mrt_spin.py " + " ".join(argv if argv is not None else sys.argv[1:])
    rows, bare = [], []
    with tempfile.TemporaryDirectory(prefix="bench_mrt_spin_") as tmp:
        out = Path(tmp) / "x.prt"
        before = None
        if args.before:  # the earlier code, for a paired before/after under the libgomp default
            before = Path(tmp) / f"before-{args.before[:12]}"
            before.mkdir()
            arch = subprocess.run(["git", "-C", str(ROOT), "archive", args.before, "prt_torch"], capture_output=True, check=True)
            subprocess.run(["tar", "-x", "-C", str(before)], input=arch.stdout, check=True)
        arms = [(None if p == "unset" else p, None) for p in args.policies] + ([("default", str(before))] if before else [])
        cli_run(args.scene, args.size, "PASSIVE", out)  # warm-up: the file cache, kernels built
        if before:
            cli_run(args.scene, args.size, "default", out, str(before))
        for r in range(args.repeats):
            for pol, code in (arms if r % 2 == 0 else arms[::-1]):
                rows.append({"repeat": r, **cli_run(args.scene, args.size, pol, out, code)})
                print(rows[-1], flush=True)
            c0 = _tree_cpu()
            p = subprocess.run([sys.executable, __file__, "--bare-child", "--scene", args.scene, "--size", args.size],
                               capture_output=True, text=True, check=True)
            res = json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("JSON "))[5:])
            bare += [{"repeat": r, **b} for b in res["bare"]]
            print(res, f"child tree cpu {_tree_cpu() - c0:.1f}", flush=True)
    info["load_end"] = os.getloadavg()[0]
    L = ["# MRT precompute: CPU over wall by OpenMP wait policy, against bare Embree on its rays", "",
         f"Command: `{info['command'].strip()}`. CPU: {cpu_label(info)}, {info['cores']} cores; the machine was shared with "
         f"other jobs (load average at each row). `prt precompute {args.scene} --size {args.size} --kind mrt` (defaults: "
         "5 bands, M = 11, 1024 samples) in a child process; CPU = user + system of the child and the ray-casting workers "
         "it reaped. Bare = the same rays (recorded from one precompute) replayed on a caster with the CLI's workers; "
         "CPU = this process + its workers (/proc).", "",
         "| repeat | OMP_WAIT_POLICY | wall s | CPU s | CPU / wall | precompute s (its `rays in`) | load |",
         "|---:|---|---:|---:|---:|---:|---:|"]
    for r in rows:
        L.append(f"| {r['repeat']} | {r['policy']} | {r['wall_s']:.2f} | {r['cpu_s']:.2f} | {r['cpu_s'] / r['wall_s']:.2f} | "
                 f"{r['precompute_s']} | {r['load']:.1f}–{r['load_end']:.1f} |")
    L += ["", "| repeat | bare Embree: rays | workers | wall s | CPU s | CPU / wall | load |", "|---:|---:|---:|---:|---:|---:|---:|"]
    for b in bare:
        L.append(f"| {b['repeat']} | {b['rays']} | {b['workers']} | {b['wall_s']:.2f} | {b['cpu_s']:.2f} | "
                 f"{b['cpu_s'] / b['wall_s']:.2f} | {b['load']:.1f} |")
    for pol in sorted({r["policy"].split(":")[0] for r in rows}):
        sel = [r for r in rows if r["policy"].split(":")[0] == pol]
        if sel:
            med = sorted(r["cpu_s"] / r["wall_s"] for r in sel)[len(sel) // 2]
            L.append(f"\nMedian CPU / wall, OMP_WAIT_POLICY {pol}: {med:.2f}; median wall "
                     f"{sorted(r['wall_s'] for r in sel)[len(sel) // 2]:.2f} s, CPU {sorted(r['cpu_s'] for r in sel)[len(sel) // 2]:.2f} s.")
    outp = Path(args.out)
    outp.parent.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(outp, overwrite=True) as t:
        Path(t).write_text("\n".join(L) + "\n")
    io.atomic_write_json(outp.with_suffix(".json"), {"machine": info, "rows": rows, "bare": bare})
    print(f"wrote {outp}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
