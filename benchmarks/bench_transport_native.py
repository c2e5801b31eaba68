"""Benchmark and whole-table check (issue 42 §2): the transport table's compiled BRDF passes
(``transfer.transport_kernels``, ``kernels/transport.c``) against the torch path, chunk by chunk over a whole mesh.

    .venv/bin/python benchmarks/bench_transport_native.py [--scene bumpy_sphere:medium] [--every 1] [--dtype float64]
        [--out reports/benchmarks/transport_native.md]

Every ``--every``-th chunk of the default table (92 views, ``res: auto`` = 13 for the default Ashikhmin–Shirley N = 40,
texel averages; the real run's 89-vertex chunks) is computed twice in this process, one thread each: with the
compiled passes and with ``PRT_TORCH_NATIVE=0`` (torch), alternating which goes first, both in ``--dtype`` (float64:
the values before rounding to the stored float32). Per chunk: this thread's CPU time of each (``time.thread_time``;
the shadow rays run in this thread too, ``RayCaster(workers=1)``, the same in both), and the values' largest relative
difference. Prints and writes a markdown table: totals, the CPU ratio, and the largest difference over the whole
table, naming the CPU, its kernel path and the load.
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

from prt_torch._native import cpu_isa  # noqa: E402
from prt_torch.brdf import AshikhminShirley  # noqa: E402
from prt_torch.scene import RayCaster, builtin  # noqa: E402
from prt_torch.transfer import transport as TT  # noqa: E402
from prt_torch.transfer import transport_kernels as TK  # noqa: E402
from prt_torch.transfer.glossy import check_frames  # noqa: E402
from prt_torch.harness.timing import cpu_label as _cpu  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bumpy_sphere:medium")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    ok, how = TK.available()
    if not ok:
        raise SystemExit(f"no compiled transport kernel: {how}")
    mesh = builtin(a.scene)
    F = check_frames(mesh)
    brdf = AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0)
    res, _ = TT.choose_cube_res(brdf)
    views = TT.icosphere_directions(3)
    texels = TT.cube_directions(res)[0].reshape(-1, 3)
    J, P = views.shape[0], texels.shape[0]
    plan = TT.supersample_plan(brdf, res, "auto")
    subs = TT.sub_texel_sets(res, plan)
    chunk = int(max(1, min(4096, (8 << 20) // (J * P))))  # precompute_transport's default chunk
    dt = getattr(torch, a.dtype)
    V = mesh.num_vertices
    starts = list(range(0, V, chunk))[::a.every]
    load0 = os.getloadavg()
    cpu = {"native": 0.0, "torch": 0.0}
    worst, values, differ = 0.0, 0, 0
    with RayCaster(mesh, workers=1) as c:
        for n, s in enumerate(starts):
            e = min(V, s + chunk)
            args = (c, brdf, mesh.vertices[s:e], mesh.normals[s:e], F[s:e], texels, views, None, True, dt)
            out = {}
            for form in (("native", "torch") if n % 2 == 0 else ("torch", "native")):
                os.environ["PRT_TORCH_NATIVE"] = "1" if form == "native" else "0"
                t0 = time.thread_time()
                out[form] = TT._chunk_transport(*args, plan=plan, sub_texels=subs, average_threads=1)
                cpu[form] += time.thread_time() - t0
            x, y = out["torch"].double(), out["native"].double()
            d = (x - y).abs()
            nz = x != 0
            if not torch.equal(nz, y != 0):
                raise SystemExit(f"chunk at vertex {s}: the zero sets differ")
            values += x.numel()
            differ += int((d > 0).sum())
            worst = max(worst, float((d[nz] / x[nz].abs()).max()) if bool(nz.any()) else 0.0)
            if n % 20 == 0:
                print(f"chunk {n + 1}/{len(starts)}: native {cpu['native']:.1f} s, torch {cpu['torch']:.1f} s, "
                      f"max rel {worst:.3g}", flush=True)
    os.environ.pop("PRT_TORCH_NATIVE", None)
    load1 = os.getloadavg()
    lines = [
        "# Transport tables: the compiled BRDF passes against torch (issue 42 §2)",
        "",
        f"`benchmarks/bench_transport_native.py --scene {a.scene} --every {a.every} --dtype {a.dtype}` — CPU {_cpu()} "
        f"({cpu_isa()}: the kernel's {'AVX2 path, libmvec pow' if cpu_isa() in ('avx2', 'avx512') else 'portable path'}; "
        f"{how.rsplit(', ', 1)[0]}), torch {torch.__version__}, one thread, load {load0[0]:.1f} → {load1[0]:.1f} (a shared "
        "machine: the figures are this thread's CPU time, the two forms alternating chunk by chunk in one process).",
        "",
        f"{len(starts)} chunks of {chunk} vertices ({V} vertices, every {a.every}) × {J} views × 6×{res}×{res} texels, default "
        f"BRDF, texel averages ({plan['reason']}); each chunk's shadow rays are cast in this thread in both forms.",
        "",
        "| form | thread CPU s, all chunks | per chunk | ratio |",
        "|---|---:|---:|---:|",
        f"| torch (`PRT_TORCH_NATIVE=0`) | {cpu['torch']:.2f} | {cpu['torch'] / len(starts):.3f} | 1.00 |",
        f"| compiled (`kernels/transport.c`) | {cpu['native']:.2f} | {cpu['native'] / len(starts):.3f} | "
        f"{cpu['torch'] / cpu['native']:.2f}x faster |",
        "",
        f"Values ({a.dtype}): {values} in all, {differ} differ in some bit, the largest relative difference "
        f"{worst:.3g}; the same zeros.",
    ]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        Path(a.out).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
