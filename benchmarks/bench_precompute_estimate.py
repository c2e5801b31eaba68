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

``--scenes S [S ...]`` (the command-line section; nothing else is measured, the other tables are
kept from ``--out``'s .json): for each scene and each of ``--cli-kinds`` (diffuse and glossy with
one bounce under the default estimator 'auto', whose face probe the first chunks trace lazily, and
the default transport table), with the CLI's defaults otherwise, three child processes under
``/usr/bin/time -v``, in alternating order per repeat: ``prt precompute S ... --dry-run`` (its
printed total seconds and peak bytes; its own wall time is the probe's cost), the real ``prt
precompute S ...`` (its peak RSS, and the wall time of the command's ``main()`` after the imports,
timed inside the process), and a bare interpreter importing what the command imports (its RSS: the
baseline the estimate does not count). Compared: the estimate's total (mesh + rays + result) with
the real ``main()``'s wall time, and its peak with the real peak RSS less the baseline's.
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


#: the command-line section's kinds: a row label -> the ``prt precompute`` options (the CLI's defaults otherwise)
CLI_KINDS = {"diffuse_bounce": ["--kind", "diffuse", "--bounces", "1"],
             "glossy_bounce": ["--kind", "glossy", "--bounces", "1"],
             "transport": ["--kind", "transport"]}
#: what ``prt precompute`` imports before its mesh: the bare interpreter's baseline (start-up wall, RSS)
CLI_IMPORTS = "import prt_torch.cli, prt_torch.cli.precompute, prt_torch.transfer, prt_torch.scene, prt_torch.transfer.estimate"
_UNITS = {"B": 1, "KiB": 1 << 10, "MiB": 1 << 20, "GiB": 1 << 30, "TiB": 1 << 40}


def _bytes(text: str) -> int:
    """'821 MiB' (``io.format_bytes``) -> bytes."""
    num, unit = text.split()
    return int(float(num) * _UNITS[unit])


def _timed(cmd: list[str]) -> tuple[dict, str]:
    """Run ``cmd`` under ``/usr/bin/time -v``: ({wall, cpu (user + system), rss (peak, bytes)}, its stderr)."""
    import re
    import subprocess

    p = subprocess.run(["/usr/bin/time", "-v", *cmd], capture_output=True, text=True, cwd=ROOT)
    err = p.stderr
    if p.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} exited with {p.returncode}: {err.strip().splitlines()[-3:]}")
    wall = re.search(r"Elapsed \(wall clock\) time \(h:mm:ss or m:ss\): ([\d:.]+)", err).group(1).split(":")
    secs = sum(float(x) * 60 ** i for i, x in enumerate(reversed(wall)))
    cpu = sum(float(re.search(rf"{k} time \(seconds\): ([\d.]+)", err).group(1)) for k in ("User", "System"))
    rss = int(re.search(r"Maximum resident set size \(kbytes\): (\d+)", err).group(1)) * 1024
    return {"wall": secs, "cpu": cpu, "rss": rss}, err


def cli_row(scene: str, label: str, work: Path, order: int) -> dict:
    """One command-line comparison (module docstring, ``--scenes``) of ``scene`` and ``label``."""
    import re

    prt = str(Path(sys.executable).with_name("prt"))
    opts = [*CLI_KINDS[label], "--no-progress"]
    row: dict = {"scene": scene, "kind": label, "load": os.getloadavg()[0]}
    steps = ["base", "dry", "real"]
    for step in (steps if order % 2 == 0 else steps[::-1]):
        out = work / f"{label}_{step}.out"
        shutil.rmtree(out, ignore_errors=True) if out.is_dir() else out.unlink(missing_ok=True)
        if step == "base":
            row["base"], _ = _timed([sys.executable, "-c", CLI_IMPORTS])
        elif step == "dry":
            row["dry"], err = _timed([prt, "precompute", scene, *opts, "-o", str(out), "--dry-run"])
            lines = {ln.split()[0]: ln for ln in err.splitlines() if ln.startswith("  ")}
            row["vertices"] = int(re.search(r"(\d+) vertices", err).group(1))
            row["estimate_seconds"] = float(re.search(r"~([\d.]+) s", lines["peak"]).group(1))
            row["estimate_rays_seconds"] = float(re.search(r"~([\d.]+) s", lines["rays"]).group(1))
            row["estimate_peak"] = _bytes(" ".join(lines["peak"].split()[1:3]))
            row["estimate_note"] = lines["rays"].split("time from ")[-1].strip()
        else:  # the command's own main() after the imports, timed inside the process (the start-up's wall moves with the load)
            argv = ["precompute", scene, *opts, "-o", str(out)]
            code = (f"{CLI_IMPORTS}; import sys, time; from prt_torch.cli import main; t = time.perf_counter(); "
                    f"rc = main({argv!r}); sys.stderr.write(f'BENCH_WALL {{time.perf_counter() - t}}\\n'); sys.exit(rc)")
            row["real"], err = _timed([sys.executable, "-c", code])
            row["real_main_seconds"] = float(re.search(r"BENCH_WALL ([\d.e-]+)", err).group(1))
            m = re.search(r" in ([\d.]+) s\)", err)
            row["real_precompute_seconds"] = float(m.group(1)) if m else None
            shutil.rmtree(out, ignore_errors=True) if out.is_dir() else out.unlink(missing_ok=True)
    row["load_end"] = os.getloadavg()[0]
    row["real_seconds"] = row["real_main_seconds"]
    row["real_peak"] = row["real"]["rss"] - row["base"]["rss"]
    return row


def chunk_cost(scene: str, label: str) -> dict:
    """CPU seconds per chunk of a real run in the dry-run probe's chunks (``estimate.probe_chunk``), one worker, in
    this process: the mean of chunks 2-3 (what the probe scales to every vertex) over the mean of chunks 4 to the
    last whole one — above 1 where the first chunks pay for lazily built state, such as the bounce estimator's face
    probe, traced for the faces the first hits land on (``diffuse.HitBounce``)."""
    from prt_torch.scene import load_scene
    from prt_torch.transfer import RunOptions, get_kind
    from prt_torch.transfer.estimate import probe_chunk, real_chunk

    name, size = (scene.split(":") + ["small"])[:2]
    mesh = load_scene(name, size=size)
    kind = {"diffuse_bounce": "diffuse", "glossy_bounce": "glossy", "transport": "transport"}[label]
    params = {"bounces": 1} if kind != "transport" else {}
    k = get_kind(kind)
    kw, _ = k.resolve(params, None)
    V = mesh.num_vertices
    chunk = probe_chunk(V, real_chunk(kind, kw, None))
    marks = [time.process_time()]
    with tempfile.TemporaryDirectory() as d:
        run = RunOptions(workers=1, chunk_size=chunk, state_dir=d + "/s", progress=False,
                         callback=lambda i, n: marks.append(time.process_time()))
        if k.output == "directory":
            k.precompute(mesh, params, run=run, out=d + "/t")
        else:
            k.precompute(mesh, params, run=run)
    cpu = [b - a for a, b in zip(marks, marks[1:])]
    whole = V // chunk  # chunks of the full size
    rest = cpu[3:whole]
    return {"scene": scene, "kind": label, "vertices": V, "chunk": chunk, "chunks": len(cpu), "load": os.getloadavg()[0],
            "first": cpu[0], "probed": sum(cpu[1:3]) / 2, "rest": sum(rest) / len(rest) if rest else float("nan")}


def cli_table(rows: list[dict]) -> list[str]:
    """The command-line section of the report."""
    if not rows:
        return []
    L = ["", "## The command line: `prt precompute S ... --dry-run` against `prt precompute S ...`", "",
         "Each row: three child processes under `/usr/bin/time -v`, order alternating per repeat (`--scenes`, module "
         "docstring): the dry run, the real command (CLI defaults: 1024 samples, 5 bands; diffuse and glossy with "
         "`--bounces 1` under the default estimator 'auto', whose per-face probe the chunks trace as their hits land; "
         "transport: the default 92-view 6×8×8 table, written to a directory), and a bare interpreter doing the "
         "command's imports (the baseline RSS, which the estimate does not count). time: the estimate's total "
         "(mesh + rays + result) against the real command's `main()` after its imports (wall, timed in the "
         "process); peak: the estimate's peak against the real peak RSS less the baseline's. dry run = the dry "
         "run's own wall time (imports + mesh + probe). Before commit 186c70c the peak read low for glossy with a "
         "bounce (183 MiB against 530–560 measured on the Cornell box, 185 against 404–418 on scan_blob: the chunk's "
         "[k, N, n²] interreflection buffer and the hits' [H, n²] exit transfers were not counted) and for transport (222 against "
         "230–250: the second, in-flight chunk buffer), and 2.6–4.1× high for diffuse with a bounce (798–834 MiB against "
         "205–340: per-ray SH values the compiled qmc pass never holds); before 19c5de8 a glossy run of exactly three "
         "chunks (2154 vertices in 1024s) had its 106-vertex last chunk counted as a whole one (0.72–0.97).", "",
         "| scene | vertices | kind | estimate s | real s (main() wall) | time est / real | estimate peak | "
         "real peak (RSS − baseline) | peak est / real | dry run wall s | probe | load |",
         "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|---|---:|"]
    mb = 1 << 20
    order = list(dict.fromkeys(r["scene"] for r in rows))
    for r in sorted(rows, key=lambda r: (order.index(r["scene"]), list(CLI_KINDS).index(r["kind"]), r.get("repeat", 0))):
        note = r["estimate_note"]
        probe = ("whole run" if "whole run" in note else
                 note.split("per chunk of ")[1].split(" vertices")[0] + "-vertex chunks" if "per chunk of" in note else note[:40])
        L.append(f"| {r['scene']} | {r['vertices']} | {r['kind']} | {r['estimate_seconds']:.1f} | {r['real_seconds']:.2f} | "
                 f"{r['estimate_seconds'] / r['real_seconds']:.2f} | {r['estimate_peak'] / mb:.0f} MiB | "
                 f"{r['real_peak'] / mb:.0f} MiB | {r['estimate_peak'] / r['real_peak']:.2f} | {r['dry']['wall']:.1f} | "
                 f"{probe} | {r['load']:.1f}–{r['load_end']:.1f} |")
    return L


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
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="measure only the command-line section (dry run against the real command under /usr/bin/time -v) "
                         "on these scenes; the other tables are kept from --out's .json")
    ap.add_argument("--cli-kinds", nargs="+", default=list(CLI_KINDS), choices=sorted(CLI_KINDS))
    ap.add_argument("--chunk-cost", action="store_true",
                    help="with --scenes: instead of the command-line rows, the CPU per chunk of real runs in the probe's "
                         "chunks, chunks 2-3 (the probe's) against the later ones (what the first chunks' lazily traced "
                         "face probe adds)")
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
    rows, chunks, cli, costs = [], [], [], []
    cli_command = info["command"]
    if args.render_only or args.scenes:  # the tables again from --out's .json (after a change of the table's layout)
        args.merge, args.kinds, args.no_chunks, args.no_policy = True, [], True, True
    if args.scenes:
        if not Path("/usr/bin/time").exists():
            print("bench_precompute_estimate: --scenes needs /usr/bin/time (GNU time, its -v peak RSS); accepted: a machine "
                  "with it (apt-get install time)", file=sys.stderr)
            return 2
        with tempfile.TemporaryDirectory(prefix="bench_estimate_cli_") as tmp:
            for scene in (args.scenes if args.chunk_cost else []):
                for label in args.cli_kinds:
                    costs.append({**chunk_cost(scene, label), "command": info["command"].strip()})
                    print(costs[-1], flush=True)
            for scene in ([] if args.chunk_cost else args.scenes):
                for label in args.cli_kinds:
                    for r in range(args.repeats):
                        cli.append({**cli_row(scene, label, Path(tmp), r), "repeat": r})
                        c = cli[-1]
                        print(f"{scene} {label} #{r}: estimate {c['estimate_seconds']:.3g} s / {c['estimate_peak'] >> 20} MiB, "
                              f"real {c['real_seconds']:.3g} s / {c['real_peak'] >> 20} MiB, load {c['load']:.1f}", flush=True)
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
        cli_command = info["command"] if args.scenes else old.get("cli_command", "")
        if args.chunk_cost:
            costs = [r for r in old.get("chunk_cost", []) if r["scene"] not in args.scenes or r["kind"] not in args.cli_kinds] + costs
            cli_command = old.get("cli_command", "")
        else:
            costs = old.get("chunk_cost", [])
        if args.scenes and not args.chunk_cost:  # the rows of the other scenes (or kinds) kept, with the command that measured them
            kept = [r for r in old.get("cli", []) if r["scene"] not in args.scenes or r["kind"] not in args.cli_kinds]
            cli_command = "; ".join(x for x in (old.get("cli_command", "") if kept else "", cli_command) if x)
            cli = kept + cli
        cli = cli or old.get("cli", [])
        if args.scenes:
            info = old.get("machine", info)
        elif args.render_only:
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
    if cli:
        L += cli_table(cli)
        L += ["", f"Commands: `{cli_command.strip()}`; CPU: {cpu_label(info)}, {info['cores']} "
              f"cores; the machine was shared with other jobs (load average at each row)."]
    if costs:
        L += ["", "CPU per chunk of real runs in the dry-run probe's chunks (`--scenes S --chunk-cost`, one worker, one "
              "process): the probe scales the mean of chunks 2–3 to every vertex; the first chunks also trace the "
              "bounce estimator's face probe for the faces their hits land on, which later chunks mostly find done. "
              "probed / later = how high that makes the probe's per-chunk figure.", "",
              "| scene | vertices | kind | chunk | chunks | first (set-up) CPU s | chunks 2–3 mean CPU s | later chunks "
              "mean CPU s | probed / later | load |", "|---|---:|---|---:|---:|---:|---:|---:|---:|---:|"]
        for r in costs:
            L.append(f"| {r['scene']} | {r['vertices']} | {r['kind']} | {r['chunk']} | {r['chunks']} | {r['first']:.2f} | "
                     f"{r['probed']:.3f} | {r['rest']:.3f} | {r['probed'] / r['rest']:.2f} | {r['load']:.1f} |")
        L += ["", "Command: " + "; ".join(f"`{c}`" for c in dict.fromkeys(r.get("command", "") for r in costs) if c)
              + f"; CPU: {cpu_label(info)}; the machine was shared with other jobs (load average at each row)."]
    out.parent.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(out, overwrite=True) as t:
        Path(t).write_text("\n".join(L) + "\n")
    io.atomic_write_json(out.with_suffix(".json"), {"machine": info, "args": vars(args), "rows": rows, "chunks": chunks, "policies": policies,
                                                "cli": cli, "cli_command": cli_command, "chunk_cost": costs})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
