"""Benchmark (issue 42 §2, "defaults that work together"): what the transport tables' texel averages
cost (``precompute_transport(supersample='auto')`` against point values, ``supersample=1``).

    .venv/bin/python benchmarks/bench_transport_supersample.py [--scene scan_blob] [--res 13]
        [--vertices 60] [--repeats 3] [--out reports/benchmarks/transport_supersample.md]

One chunk of the table (``transport._chunk_transport``: the shadow rays, the BRDF on the (upper view,
visible texel) pairs, and with 'auto' the texel averages of the grazing views) for ``--vertices``
vertices spread over the mesh, the default Ashikhmin–Shirley N = 40 and 92 views, in one thread, the
two forms alternating ``--repeats`` times in one process: this thread's CPU time (time.thread_time, so
the machine's load does not enter the ratio) and the pairs evaluated. The ray casting runs in this
thread too (``RayCaster(workers=1)``'s in-process path) and is the same in both. Prints and writes a
markdown table naming the CPU and the load.
"""
from __future__ import annotations

import argparse
import os
import platform
import subprocess
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


def _cpu() -> str:
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
        return next(ln.split(":", 1)[1].strip() for ln in out.splitlines() if ln.startswith("Model name"))
    except (OSError, StopIteration):
        return platform.processor() or "unknown"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="scan_blob")
    ap.add_argument("--res", type=int, default=13)
    ap.add_argument("--vertices", type=int, default=60)
    ap.add_argument("--repeats", type=int, default=3)
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
    t = {"point": [], "auto": []}
    with RayCaster(mesh, workers=1) as c:
        args = (c, brdf, mesh.vertices[idx], mesh.normals[idx], F[idx], texels, views, None, True, torch.float32)
        for _ in range(a.repeats):  # alternating: the two forms see the same machine state
            for name in ("point", "auto"):
                t0 = time.thread_time()
                TT._chunk_transport(*args, **({"plan": plan, "sub_texels": subs} if name == "auto" else {}))
                t[name].append(time.thread_time() - t0)
    load1 = os.getloadavg()
    best = {k: min(v) for k, v in t.items()}
    lines = [
        "# Transport tables: the cost of texel averages (issue 42 §2)",
        "",
        f"`benchmarks/bench_transport_supersample.py --scene {a.scene} --res {a.res} --vertices {a.vertices} --repeats {a.repeats}`"
        f" — CPU {_cpu()}, torch {torch.__version__}, one thread, load {load0[0]:.1f} → {load1[0]:.1f} (a shared machine: the"
        " figures are this thread's CPU time, paired and alternating in one process).",
        "",
        f"One table chunk of {len(idx)} vertices × {views.shape[0]} views × 6×{a.res}×{a.res} texels (default BRDF); 'auto': {plan['reason']}.",
        "",
        "| form | CPU s per chunk (each repeat) | best | ratio to point values |",
        "|---|---|---:|---:|",
    ]
    for k in ("point", "auto"):
        lines.append(f"| {'point values (supersample 1)' if k == 'point' else 'texel averages (supersample auto)'} | "
                     f"{', '.join(f'{x:.2f}' for x in t[k])} | {best[k]:.2f} | {best[k] / best['point']:.2f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        Path(a.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
