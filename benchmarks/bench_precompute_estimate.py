"""Benchmark: ``prt precompute --dry-run``'s time estimate against the real run (issue 42, part 3).

    .venv/bin/python benchmarks/bench_precompute_estimate.py [--sizes 10000 100000] [--kinds diffuse mrt]
        [--repeats 2] [--out reports/benchmarks/precompute_estimate.md]

On ``bumpy_sphere:<size>`` with ``bench_scale.py``'s settings (diffuse: 4 bands, 64 samples, shadows
traced; MRT: 3 bands, M = 4, Phong s = 12, 32 samples), one worker, in this one process: after a
warm-up run on a 642-vertex mesh, each repeat times, back to back and each from a freshly built
mesh (what a mesh computes lazily is paid by each step, as by a fresh ``prt precompute``),

* ``estimate``: :func:`prt_torch.transfer.estimate.estimate` with its probe as ``--dry-run`` runs
  it (the probe's own chunk: :func:`~prt_torch.transfer.estimate.probe_chunk`), its wall time
  (the probe's cost) and the seconds it predicts (rays + result stages);
* ``estimate @1024``: the same with ``probe_vertices=1024`` (the chunk of the probe before);
* ``real``: the precompute (chunks saved to a state directory, as ``prt precompute``) + its save
  to a file: what ``bench_scale.py`` measures; wall and process CPU seconds.

The order of the three alternates between repeats (the load drifts). Reported per kind, size and
repeat: estimate / real for both probes, and the probe's cost as a share of the real run. The
machine is shared (2 cores): the load average is recorded with each row; every figure is wall
time, which the load moves — the estimate is a wall-time prediction under the load of the moment.
Then the cause: per chunk size, µs per vertex (wall, the chunk thread's CPU, the process's CPU)
over chunks 2–5; and for MRT the same at 1024 and 8192 vertices per chunk in two child
processes, ``OMP_WAIT_POLICY=ACTIVE`` (spinning, what ``prt_torch`` keeps on a quiet machine) and
``PASSIVE``. Writes ``--out`` (.md) and the same numbers as .json beside it, atomically.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PARAMS = {"diffuse": {"bands": 4, "samples": 64, "shadows": "always"},
          "mrt": {"bands": 3, "M": 4, "samples": 32, "shadows": "always", "brdf": {"type": "phong", "s": 12.0}},
          # the kinds that streamed last (issue 42 part 3, the rest): a row label -> (kind, parameters)
          "diffuse_bounce": {"kind": "diffuse", "bands": 4, "samples": 64, "bounces": 1, "shadows": "always"},
          "subsurface": {"kind": "subsurface", "bands": 3, "samples": 64, "material": "skin1", "scale": 10.0,
                         "shadows": "always"},
          "wavelet": {"kind": "wavelet", "res": 16, "terms": 64, "shadows": "always"},
          "transport": {"kind": "transport", "views": 1, "res": 8, "shadows": True}}


def kind_of(label: str) -> tuple[str, dict]:
    """(transfer kind, its parameters) of a row label of :data:`PARAMS`."""
    p = dict(PARAMS[label])
    return p.pop("kind", label), p


def real_run(label: str, mesh, work: Path) -> dict:
    """The precompute as ``prt precompute`` runs it (state directory) + the save, timed (transport:
    its table streamed to the directory, which is its output)."""
    import warnings

    from prt_torch.transfer import RunOptions, get_kind

    kind, params = kind_of(label)
    state, out = work / f"{label}.prt.state", work / f"{label}.prt"
    k = get_kind(kind)
    t, c = time.perf_counter(), time.process_time()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the subsurface scale/holes notes
        if k.output == "directory":
            tr = k.precompute(mesh, params, run=RunOptions(workers=1, state_dir=state, progress=False), out=state)
            chunk = int(tr.meta["chunk_size"])
        else:
            tr = k.precompute(mesh, params, run=RunOptions(workers=1, state_dir=state, progress=False))
            tr.save(out, overwrite=True)
            chunk = int(tr.meta.get("chunk_size", 0))
    res = {"real_seconds": time.perf_counter() - t, "real_cpu_seconds": time.process_time() - c, "chunk_size": chunk}
    del tr
    if out.exists():
        out.unlink()
    shutil.rmtree(state, ignore_errors=True)
    return res


def per_chunk(label: str, mesh, chunk: int, n: int = 5) -> dict:
    """Per-vertex wall, this thread's and the process's CPU µs and minor page faults per vertex of chunks 2..n of a run
    in chunks of ``chunk`` (no state directory; the first chunk, with the set-up, left out)."""
    import resource

    from prt_torch.transfer import RunOptions, get_kind
    from prt_torch.transfer.base import ChunkInterrupt

    V, marks = mesh.num_vertices, []

    def cb(i: int, n_chunks: int) -> None:
        marks.append((min(V, (i + 1) * chunk) - i * chunk, time.perf_counter(), time.thread_time(), time.process_time(),
                      resource.getrusage(resource.RUSAGE_SELF).ru_minflt))
        if len(marks) >= n:
            raise ChunkInterrupt("enough")

    kind, params = kind_of(label)
    try:
        get_kind(kind).precompute(mesh, params, run=RunOptions(workers=1, chunk_size=chunk, callback=cb, progress=False))
    except ChunkInterrupt:
        pass
    if len(marks) < 2:
        return {"chunk": chunk, "chunks_timed": 0}
    nv = sum(m[0] for m in marks[1:])
    return {"chunk": chunk, "chunks_timed": len(marks) - 1, "wall_us_per_vertex": 1e6 * (marks[-1][1] - marks[0][1]) / nv,
            "cpu_us_per_vertex": 1e6 * (marks[-1][2] - marks[0][2]) / nv,
            "process_cpu_us_per_vertex": 1e6 * (marks[-1][3] - marks[0][3]) / nv, "faults_per_vertex": (marks[-1][4] - marks[0][4]) / nv}


def estimated(label: str, mesh, probe_vertices: int | None) -> dict:
    """The dry run's estimate (its probe), timed; ``first_pass_seconds``: the estimate of the first
    pass alone (what the probe said before it timed a subsurface scatter)."""
    import warnings

    from prt_torch.transfer import RunOptions, get_kind
    from prt_torch.transfer.estimate import estimate

    kind, params = kind_of(label)
    t = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        e = estimate(get_kind(kind), mesh, params, RunOptions(workers=1, state_dir=Path(tempfile.gettempdir()) / "x"),
                     probe=True, probe_vertices=probe_vertices, mesh_seconds=0.0)
    note = e.stages[1]["note"].split("time from ")[-1]
    passes = e.stages[1].get("passes") or []
    return {"seconds": e.seconds, "probe_wall_seconds": time.perf_counter() - t, "note": note,
            "first_pass_seconds": passes[0]["seconds"] if passes else e.seconds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000])
    ap.add_argument("--kinds", nargs="+", default=["diffuse", "mrt"], choices=sorted(PARAMS))
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--policy-size", type=int, default=100_000,
                    help="the mesh of the OpenMP wait-policy table (MRT, 1024- and real-chunk runs in child processes)")
    ap.add_argument("--policy-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=str(ROOT / "reports/benchmarks/precompute_estimate.md"))
    ap.add_argument("--merge", action="store_true",
                    help="keep the rows, per-chunk and policy tables of the kinds not measured now from --out's .json")
    ap.add_argument("--no-chunks", action="store_true", help="skip the per-chunk-size table")
    ap.add_argument("--render-only", action="store_true", help="measure nothing: write --out again from its .json")
    ap.add_argument("--no-policy", action="store_true", help="skip the OpenMP wait-policy table")
    ap.add_argument("--max-real", type=float, default=120.0,
                    help="skip the larger sizes of a kind once its real run took longer than this (seconds)")
    args = ap.parse_args(argv)
    if args.repeats < 1:
        print(f"bench_precompute_estimate: --repeats {args.repeats}; accepted: 1 or more", file=sys.stderr)
        return 2
    if args.policy_child:  # a child with OMP_WAIT_POLICY set by the parent: per-chunk figures as JSON on stdout
        import json

        import prt_torch
        from prt_torch.scene import load_scene

        mesh = load_scene(f"bumpy_sphere:{args.policy_size}")
        res = [{"policy": prt_torch.OMP_POLICY_CHOICE, "kind": args.policy_child, "vertices": mesh.num_vertices,
                "load": os.getloadavg()[0], **per_chunk(args.policy_child, mesh, c)} for c in (1024, 8192, 1024, 8192)]
        print("JSON " + json.dumps(res))
        return 0
    from prt_torch import io
    from prt_torch.harness.timing import cpu_label, machine_info
    from prt_torch.scene import load_scene

    info = machine_info()
    info["command"] = "python benchmarks/bench_precompute_estimate.py " + " ".join(argv if argv is not None else sys.argv[1:])
    rows, chunks = [], []
    if args.render_only:  # the tables again from --out's .json (after a change of the table's layout)
        args.merge, args.kinds, args.no_chunks, args.no_policy = True, [], True, True
    with tempfile.TemporaryDirectory(prefix="bench_estimate_") as tmp:
        work = Path(tmp)
        small = load_scene("bumpy_sphere:642") if args.kinds else None
        for kind in args.kinds:  # warm-up: imports, kernels, first-use allocations
            real_run(kind, small, work)
        too_long: set[str] = set()
        for size in (args.sizes if args.kinds else []):
            V = load_scene(f"bumpy_sphere:{size}").num_vertices
            for kind in args.kinds:
                if kind in too_long:
                    print(f"{kind} {V}: skipped (its real run took over --max-real {args.max_real:g} s at a smaller size)")
                    continue
                for r in range(args.repeats):
                    row = {"kind": kind, "vertices": V, "repeat": r, "load": os.getloadavg()[0]}
                    steps = ["estimate", "estimate_1024", "real"]
                    for step in (steps if r % 2 == 0 else steps[::-1]):
                        mesh = load_scene(f"bumpy_sphere:{size}")  # each step from a fresh mesh (its lazy caches: the step's own)
                        if step == "real":
                            row.update(real_run(kind, mesh, work))
                        else:
                            e = estimated(kind, mesh, None if step == "estimate" else 1024)
                            row.update({f"{step}_{k}": v for k, v in e.items()})
                    row["load_end"] = os.getloadavg()[0]
                    rows.append(row)
                    if size == min(args.sizes) and row["real_seconds"] * max(args.sizes) / size > args.max_real:
                        too_long.add(kind)  # the largest size would take longer than --max-real (time linear in V)
                    print(f"{kind} {V} #{r}: estimate {row['estimate_seconds']:.3g} s, @1024 "
                          f"{row['estimate_1024_seconds']:.3g} s, real {row['real_seconds']:.3g} s "
                          f"(cpu {row['real_cpu_seconds']:.3g}), probe {row['estimate_probe_wall_seconds']:.3g} s, "
                          f"load {row['load']:.1f}", flush=True)
        from prt_torch.transfer.estimate import probe_chunk

        for size in ([] if args.no_chunks else args.sizes):
            mesh = load_scene(f"bumpy_sphere:{size}")
            for kind in args.kinds:
                real = next(r["chunk_size"] for r in rows if r["kind"] == kind and r["vertices"] == mesh.num_vertices)
                for c in sorted({256, 1024, probe_chunk(mesh.num_vertices, real), real}):
                    chunks.append({"kind": kind, "vertices": mesh.num_vertices, "real_chunk": real, "load": os.getloadavg()[0],
                                   **per_chunk(kind, mesh, c)})
                    print(chunks[-1], flush=True)
    policies = []
    import json
    import subprocess

    for pol in (() if args.no_policy else ("ACTIVE", "PASSIVE")):  # torch's OpenMP threads spinning or sleeping
        p = subprocess.run([sys.executable, __file__, "--policy-child", "mrt", "--policy-size", str(args.policy_size)],
                           env={**os.environ, "OMP_WAIT_POLICY": pol}, capture_output=True, text=True, check=True)
        policies += json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("JSON "))[5:])
    info["load_end"] = os.getloadavg()[0]
    out = Path(args.out)
    if args.merge and out.with_suffix(".json").exists():  # the other kinds' rows (and tables not measured now) kept
        import json

        old = json.loads(out.with_suffix(".json").read_text())
        keep = [r for r in old.get("rows", []) if r["kind"] not in args.kinds]
        rows = keep + rows
        chunks = chunks or old.get("chunks", [])
        policies = policies or old.get("policies", [])
        if args.render_only:
            info = old.get("machine", info)
        else:
            info["earlier_runs"] = old.get("machine", {}).get("earlier_runs", []) + [old.get("machine", {})]
    L = ["# `prt precompute --dry-run`: time estimate against the real run", "",
         f"Command: `{info['command'].strip()}`. CPU: {cpu_label(info)}, {info['cores']} cores, OpenMP wait policy: {info.get('omp_wait_policy')}; "
         f"the machine was shared "
         f"with other jobs (load average at each row). Scene `bumpy_sphere:<vertices>`; diffuse 4 bands, 64 samples "
         f"(32 rays per vertex), shadows traced; MRT 3 bands, M = 4, Phong s = 12, 32 samples; one worker."
         + "".join(f" Earlier rows: `{m.get('command', '').strip()}` (load {m.get('load_end', float('nan')):.1f} at its end)."
                   for m in info.get("earlier_runs", []) if m.get("command"))
         + " Rows added by issue 42 part 3 (the rest): diffuse_bounce = diffuse with 1 bounce (hit-point estimator, "
         "8 rays per hit); subsurface = the subsurface kind, skin1 at 10 mm per unit, 3 bands, 64 samples (its "
         "irradiance pass, then the scatter over the receivers); wavelet = res 16, 64 terms, 8 bits; transport = "
         "12 views (icosphere 1) × 6×8×8 texels, streamed to a directory.", "",
         "estimate = `transfer.estimate.estimate(..., probe=True)` (rays + result stages, as `--dry-run` prints them); "
         "real = the precompute with its state directory + the save (`bench_scale.py`'s measured figure), wall "
         "seconds, back to back in one process (order alternating per repeat). probe = the estimate's own wall time "
         "(set-up + three chunks + a 32 MiB write) as a share of the real run. `@1024` = the same probe with "
         "1024-vertex chunks (the probe's chunk before; wavelet and transport probed 1024-vertex chunks whatever their "
         "own). first pass / real = the estimate of the first pass alone (subsurface: what the probe said before it "
         "timed the scatter).", "",
         "| kind | vertices | real chunk | probe chunk | real s (CPU s) | estimate s | estimate / real | @1024 / real "
         "| first pass / real | probe / real | load |", "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        note = r["estimate_note"]
        k = note.split("per chunk of ")[1].split(" ")[0] if "per chunk of" in note else "whole run"
        fp = r.get("estimate_first_pass_seconds")  # shown for the runs of several passes (subsurface)
        fp = f"{fp / r['real_seconds']:.2f}" if fp is not None and kind_of(r["kind"])[0] == "subsurface" else "–"
        L.append(f"| {r['kind']} | {r['vertices']} | {r['chunk_size']} | {k} | {r['real_seconds']:.3g} ({r['real_cpu_seconds']:.3g}) "
                 f"| {r['estimate_seconds']:.3g} | {r['estimate_seconds'] / r['real_seconds']:.2f} | "
                 f"{r['estimate_1024_seconds'] / r['real_seconds']:.2f} | "
                 f"{fp} | "
                 f"{r['estimate_probe_wall_seconds'] / r['real_seconds']:.2f} "
                 f"| {r['load']:.1f}–{r['load_end']:.1f} |")
    L += ["", "Per chunk size (the cause): µs per vertex (wall; CPU of the thread running the chunk; CPU of the whole "
          "process, every thread) and minor page faults per vertex over "
          "chunks 2–5 of a run in chunks of that size (no state directory; the first chunk, with the set-up, left out):",
          "", "| kind | vertices | chunk | chunks timed | wall µs / vertex | thread CPU µs / vertex | process CPU µs / vertex "
          "| faults / vertex | load |",
          "|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in chunks:
        if r["chunks_timed"]:
            L.append(f"| {r['kind']} | {r['vertices']} | {r['chunk']}{' (real)' if r['chunk'] == r['real_chunk'] else ''} | "
                     f"{r['chunks_timed']} | {r['wall_us_per_vertex']:.1f} | {r['cpu_us_per_vertex']:.1f} | {r['process_cpu_us_per_vertex']:.1f} | "
                     f"{r['faults_per_vertex']:.2f} | {r['load']:.1f} |")
    L += ["", "The per-chunk fixed cost by OpenMP wait policy (MRT, each policy in a child process of its own, "
          "`OMP_WAIT_POLICY` set; two runs per chunk size, chunks 2–5 each):", "",
          "| policy | vertices | chunk | wall µs / vertex | thread CPU µs / vertex | process CPU µs / vertex | load |",
          "|---|---:|---:|---:|---:|---:|---:|"]
    for r in policies:
        if r["chunks_timed"]:
            L.append(f"| {r['policy']} | {r['vertices']} | {r['chunk']} | {r['wall_us_per_vertex']:.1f} | "
                     f"{r['cpu_us_per_vertex']:.1f} | {r['process_cpu_us_per_vertex']:.1f} | {r['load']:.1f} |")
    out.parent.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(out, overwrite=True) as t:
        Path(t).write_text("\n".join(L) + "\n")
    io.atomic_write_json(out.with_suffix(".json"), {"machine": info, "args": vars(args), "rows": rows, "chunks": chunks, "policies": policies})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
