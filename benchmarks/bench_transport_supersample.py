"""Benchmark (issue 42 §2, "defaults that work together"): what the transport tables' texel averages
cost (``precompute_transport(supersample='auto')`` against point values, ``supersample=1``).

    .venv/bin/python benchmarks/bench_transport_supersample.py [--scene scan_blob] [--res 13]
        [--vertices 60] [--repeats 3] [--threads 2] [--against /tmp/ss_old] [--out reports/benchmarks/transport_supersample.md]

One chunk of the table (``transport._chunk_transport``: the shadow rays, the BRDF on the (upper view,
visible texel) pairs, and with 'auto' the texel averages of the grazing views) for ``--vertices``
vertices spread over the mesh, the default Ashikhmin–Shirley N = 40 and 92 views, in one thread, the
two forms alternating ``--repeats`` times in one process: this thread's CPU time (time.thread_time, so
the machine's load does not enter the ratio) and the pairs evaluated. The ray casting runs in this
thread too (``RayCaster(workers=1)``'s in-process path) and is the same in both. Prints and writes a
markdown table naming the CPU and the load.

A third form, 'auto' with the texel averages in ``--threads`` torch threads (``average_threads``, what
``precompute_transport`` uses: the process's threads, since no ray is cast while they run), is timed by
wall clock (its CPU time is spread over threads) next to the wall clock of the one-thread forms, and
checked bit for bit against the one-thread table. ``--against DIR``: a checkout of another revision
(``git archive main | tar -x -C DIR``) whose ``transport._chunk_transport`` is timed too with 'auto', one
thread, in this process (its transport.py loaded as a module of this package), and its table compared bit for bit.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch.brdf import AshikhminShirley  # noqa: E402
from prt_torch.scene import RayCaster, builtin  # noqa: E402
from prt_torch.transfer import transport as TT  # noqa: E402
from prt_torch.transfer.glossy import check_frames  # noqa: E402
from prt_torch.harness.timing import cpu_label as _cpu  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="scan_blob")
    ap.add_argument("--res", type=int, default=13)
    ap.add_argument("--vertices", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--against", default=None)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    mesh = builtin(a.scene)
    F = check_frames(mesh)
    brdf = AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0)
    views = TT.icosphere_directions(3)
    texels = TT.cube_directions(a.res)[0].reshape(-1, 3)
    idx = torch.arange(0, mesh.num_vertices, max(1, mesh.num_vertices // a.vertices))[:a.vertices]
    plan = TT.supersample_plan(brdf, a.res, "auto")
    subs = TT.sub_texel_sets(a.res, plan)
    load0 = os.getloadavg()
    forms = {"point": {}, "auto": {"plan": plan, "sub_texels": subs, "average_threads": 1},
             "threads": {"plan": plan, "sub_texels": subs, "average_threads": a.threads}}
    chunk = {k: TT._chunk_transport for k in forms}
    if a.against:
        import importlib.util

        spec = importlib.util.spec_from_file_location("prt_torch.transfer._against",
                                                      Path(a.against) / "prt_torch/transfer/transport.py")
        other = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(other)
        forms["against"] = {"plan": plan, "sub_texels": subs}
        chunk["against"] = other._chunk_transport
    t: dict[str, list[float]] = {k: [] for k in forms}
    w: dict[str, list[float]] = {k: [] for k in forms}
    out = {}
    with RayCaster(mesh, workers=1) as c:
        args = (c, brdf, mesh.vertices[idx], mesh.normals[idx], F[idx], texels, views, None, True, torch.float32)
        for _ in range(a.repeats):  # alternating: the forms see the same machine state
            for name, kw in forms.items():
                t0, w0 = time.thread_time(), time.perf_counter()
                out[name] = chunk[name](*args, **kw)
                t[name].append(time.thread_time() - t0)
                w[name].append(time.perf_counter() - w0)
    load1 = os.getloadavg()
    same = torch.equal(out["threads"], out["auto"])
    best = {k: min(v) for k, v in t.items()}
    wbest = {k: min(v) for k, v in w.items()}
    lines = [
        "# Transport tables: the cost of texel averages (issue 42 §2)",
        "",
        f"`benchmarks/bench_transport_supersample.py --scene {a.scene} --res {a.res} --vertices {a.vertices} --repeats {a.repeats} "
        f"--threads {a.threads}{' --against ' + a.against if a.against else ''}`"
        f" — CPU {_cpu()}, torch {torch.__version__}, one thread except the averages of the threads row,"
        f" load {load0[0]:.1f} → {load1[0]:.1f} (a shared machine: the"
        " figures are this thread's CPU time, paired and alternating in one process).",
        "",
        f"One table chunk of {len(idx)} vertices × {views.shape[0]} views × 6×{a.res}×{a.res} texels (default BRDF); 'auto': {plan['reason']}.",
        "",
        "| form | thread CPU s per chunk (each repeat) | best | ratio to point values | wall s (each repeat) | best wall | wall ratio |",
        "|---|---|---:|---:|---|---:|---:|",
    ]
    names = {"point": "point values (supersample 1)", "auto": "texel averages (supersample auto), one thread",
             "threads": f"texel averages, averages in {a.threads} threads", "against": f"texel averages, one thread, {a.against}'s code"}
    for k in forms:
        cpu = (f"{', '.join(f'{x:.3f}' for x in t[k])} | {best[k]:.3f} | {best[k] / best['point']:.2f}" if k != "threads"
               else "(spread over threads) | | ")
        lines.append(f"| {names[k]} | {cpu} | {', '.join(f'{x:.3f}' for x in w[k])} | {wbest[k]:.3f} | {wbest[k] / wbest['point']:.2f} |")
    lines += ["", f"The {a.threads}-thread table {'equals' if same else 'DIFFERS from'} the one-thread table bit for bit; "
              f"texel averages alone (best minus point values, wall): {wbest['auto'] - wbest['point']:.2f} s in one thread, "
              f"{wbest['threads'] - wbest['point']:.2f} s in {a.threads}."]
    if a.against:
        d = (out["against"].double() - out["auto"].double()).abs()
        same = "equals this one bit for bit" if torch.equal(out["against"], out["auto"]) else \
            f"differs from this one in {int((d > 0).sum())} values (largest {float(d.max()):.3g})"
        lines += ["", f"{a.against}'s table {same}; its whole chunk (its own point values and texel averages, one thread) "
                  f"{best['against']:.3f} s of thread CPU against {best['auto']:.3f} s here ({best['against'] / best['auto']:.2f}x); "
                  "the point-values row is this checkout's (compiled where the BRDF is one the C knows)."]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        atomic_write_text(Path(a.out), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
