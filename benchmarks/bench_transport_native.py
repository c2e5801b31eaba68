"""Benchmark and whole-table check (issue 42 §2): the transport table's compiled BRDF passes
(``transfer.transport_kernels``, ``kernels/transport.c``) against the torch path, chunk by chunk over a whole mesh,
for one or several BRDFs.

    .venv/bin/python benchmarks/bench_transport_native.py [--scene bumpy_sphere:medium] [--every 1] [--dtype float64]
        [--brdf as ward ward:ax=0.3,ay=0.1 microfacet ...] [--out reports/benchmarks/transport_native.md]

Each ``--brdf`` is a model name of ``brdf.make_brdf`` (its default parameters; ``as``: the tables' default
Ashikhmin–Shirley N = 40) with ``:k=v,...`` parameters. For each, every ``--every``-th chunk of its table (92 views,
``res: auto`` from that BRDF, texel averages where its lobe is narrower than the texels; the real run's chunk size) is
computed twice in this process, one thread each: with the compiled passes and with ``PRT_TORCH_NATIVE=0`` (torch),
alternating which goes first, both in ``--dtype`` (float64: the values before rounding to the stored float32). Per
chunk: this thread's CPU time of each (``time.thread_time``; the shadow rays run in this thread too,
``RayCaster(workers=1)``, the same in both), and the values' largest relative difference (float64 subnormals, below
2^-1022, against 2^-1022). Prints and writes a markdown table, one row per BRDF: totals, the CPU ratio, and the
largest difference over the whole table, naming the CPU, its kernel path and the load.
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
from prt_torch.brdf import make_brdf  # noqa: E402
from prt_torch.scene import RayCaster, builtin  # noqa: E402
from prt_torch.transfer import transport as TT  # noqa: E402
from prt_torch.transfer import transport_kernels as TK  # noqa: E402
from prt_torch.transfer.glossy import check_frames  # noqa: E402
from prt_torch.harness.timing import cpu_label as _cpu  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402


def parse_brdf(spec: str):
    """``name`` or ``name:k=v,k=v`` -> (the BRDF, its label)."""
    name, _, rest = spec.partition(":")
    kw = {}
    for kv in (x for x in rest.split(",") if x):
        k, eq, v = kv.partition("=")
        try:
            kw[k] = float(v) if eq and k else float("x")
        except ValueError:
            raise ValueError(f"parameter {kv!r}; accepted: k=v with v a number, e.g. ward:ax=0.3,ay=0.1") from None
    return make_brdf(name, **kw), spec


def one_brdf(mesh, F, brdf, every: int, dt) -> dict:
    """Every ``every``-th chunk of ``brdf``'s default table both ways, alternating; totals and differences."""
    res, _ = TT.choose_cube_res(brdf)
    views = TT.icosphere_directions(3)
    texels = TT.cube_directions(res)[0].reshape(-1, 3)
    J, P = views.shape[0], texels.shape[0]
    plan = TT.supersample_plan(brdf, res, "auto")
    subs = None if plan is None else TT.sub_texel_sets(res, plan)
    chunk = int(max(1, min(4096, (8 << 20) // (J * P))))  # precompute_transport's default chunk
    V = mesh.num_vertices
    starts = list(range(0, V, chunk))[::every]
    cpu = {"native": 0.0, "torch": 0.0}
    worst, values, differ, nonzero = 0.0, 0, 0, 0
    tiny = torch.finfo(torch.float64).tiny
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
                raise SystemExit(f"{brdf!r}, chunk at vertex {s}: the zero sets differ")
            values += x.numel()
            nonzero += int(nz.sum())
            differ += int((d > 0).sum())
            worst = max(worst, float((d[nz] / x[nz].abs().clamp_min(tiny)).max()) if bool(nz.any()) else 0.0)
            if n % 20 == 0:
                print(f"{brdf!r} chunk {n + 1}/{len(starts)}: native {cpu['native']:.1f} s, torch {cpu['torch']:.1f} s, "
                      f"max rel {worst:.3g}", flush=True)
    os.environ.pop("PRT_TORCH_NATIVE", None)
    return {"res": res, "J": J, "chunk": chunk, "chunks": len(starts), "V": V, "cpu": cpu, "worst": worst, "values": values,
            "differ": differ, "nonzero": nonzero, "plan": "point values only" if plan is None else plan["reason"]}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bumpy_sphere:medium")
    ap.add_argument("--every", type=int, default=1)
    ap.add_argument("--dtype", default="float64", choices=["float64", "float32"])
    ap.add_argument("--brdf", nargs="+", default=["as"], help="model[:k=v,...] (brdf.make_brdf), one row each")
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    if a.every < 1:
        ap.error(f"--every {a.every}; accepted: an integer >= 1 (every n-th chunk)")
    brdfs = []
    for b in a.brdf:  # bad input named before any work (status 2, no traceback)
        try:
            brdfs.append(parse_brdf(b))
        except (ValueError, TypeError) as e:
            ap.error(f"--brdf {b!r}: {e}")
    torch.set_num_threads(1)
    ok, how = TK.available()
    if not ok:
        raise SystemExit(f"no compiled transport kernel: {how}")
    mesh = builtin(a.scene)
    F = check_frames(mesh)
    dt = getattr(torch, a.dtype)
    load0 = os.getloadavg()
    rows = [(label, brdf, one_brdf(mesh, F, brdf, a.every, dt)) for brdf, label in brdfs]
    load1 = os.getloadavg()
    isa = cpu_isa()
    lines = [
        "# Transport tables: the compiled BRDF passes against torch (issue 42 §2)",
        "",
        f"`benchmarks/bench_transport_native.py --scene {a.scene} --every {a.every} --dtype {a.dtype} --brdf {' '.join(a.brdf)}` "
        f"— CPU {_cpu()} ({isa}: the kernel's {'AVX2 path, libmvec pow/exp/acos' if isa in ('avx2', 'avx512') else 'portable path'}; "
        f"{how.rsplit(', ', 1)[0]}), torch {torch.__version__}, one thread, load {load0[0]:.1f} → {load1[0]:.1f} (a shared "
        "machine: the figures are this thread's CPU time, the two forms alternating chunk by chunk in one process).",
        "",
        f"Per BRDF: its default table on {a.scene} ({rows[0][2]['V']} vertices, every {a.every}-th chunk of the real run's) × "
        f"{rows[0][2]['J']} views × 6×r×r texels at its `res: auto`, with its texel averages; each chunk's shadow rays are "
        "cast in this thread in both forms (the same in both).",
        "",
        "| BRDF | r | chunks × vertices | torch CPU s (`PRT_TORCH_NATIVE=0`) | compiled CPU s | per chunk: torch / compiled | "
        "ratio | values (non-zero) | differ in some bit | largest relative difference |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for label, brdf, r in rows:
        c = r["cpu"]
        lines.append(f"| `{label}` = {brdf!r} | {r['res']} | {r['chunks']} × {r['chunk']} | {c['torch']:.2f} | {c['native']:.2f} | "
                     f"{c['torch'] / r['chunks']:.3f} / {c['native'] / r['chunks']:.3f} | **{c['torch'] / c['native']:.2f}×** | "
                     f"{r['values']} ({r['nonzero']}) | {r['differ']} | {r['worst']:.3g} |")
    lines += ["", "The zero sets are the same in every row (checked per chunk). Texel averages per BRDF:", ""]
    lines += [f"- `{label}`: {r['plan']}" for label, _, r in rows]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        atomic_write_text(Path(a.out), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
