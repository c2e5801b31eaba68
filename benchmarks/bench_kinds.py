"""Benchmark (issue 42 part 2): glossy, MRT and transport-table precomputes against bare Embree on
their own rays plus the work they cannot avoid, paired in one run.

    .venv/bin/python benchmarks/bench_kinds.py [--scene bumpy_sphere:medium] [--pairs 2] [--kinds glossy mrt transport]

For each kind, every ray-casting call of one precompute is recorded (``RecordRays``) and replayed
bare on pre-started worker processes (the same count as the precompute uses), and the work the
kind cannot avoid is timed alone on the same chunk shapes:

* glossy / MRT: the per-vertex GEMMs — (before: ``W [k, N] @ YY``, the transferred-radiance sum; now left
  out, ``outer_sums`` runs over the selected entries only),
  the rotation into each vertex frame (``rotate_rows``) and ``left [n_out, n²] @ R_p T_p``;
  the bound is bare Embree + these GEMMs; the BRDF projection (once per run, ``brdf_seconds``) is
  reported beside it;
* transport: the BRDF evaluated on the (upper view, visible texel) pairs alone (the faster of one
  call per chunk and the precompute's blocks of pairs); the bound is bare Embree + that.

Then ``pairs`` times, interleaved: the precompute, the bare replay, the work alone. The pace is
bound / precompute (goal ≥ 0.5). Writes reports/benchmarks/kinds.{md,json} atomically.
"""
from __future__ import annotations

import argparse
import os
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from bench_transfer_diffuse import RecordRays  # noqa: E402

from prt_torch import io  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402
from prt_torch.scene import RayCaster, builtin, default_workers  # noqa: E402
from prt_torch.sh import rotation_blocks  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.glossy import check_frames, precompute_glossy, rotate_rows  # noqa: E402
from prt_torch.transfer.mrt import precompute_mrt  # noqa: E402
from prt_torch.transfer.transport import HORIZON_EPS, cube_directions, icosphere_directions, precompute_transport  # noqa: E402


def gemms_alone(mesh, tr, bands: int, samples: int) -> float:
    """Seconds of the glossy/MRT per-vertex GEMMs alone on the precompute's chunk shapes, on one torch thread
    as the precompute's chunks: rotate_rows and left @ R T (left of the output's shape). The T_p sums are left
    out: since they run over each vertex's selected entries only (``outer_sums``; before, ``W [k, N] @ YY``
    timed here whatever W held) their size depends on the estimator's selection, so the bound here is a
    floor and the pace a lower bound."""
    from prt_torch.executor import torch_threads

    F = check_frames(mesh)
    V, n_out, n2 = tr.data.shape
    chunk = tr.meta["chunk_size"]
    left = torch.randn(n_out, n2, dtype=torch.float64)
    g = torch.Generator().manual_seed(0)
    total = 0.0
    with torch_threads(1):
        for a in range(0, V, chunk):  # a loop over chunks, as the precompute's
            b = min(V, a + chunk)
            T = torch.randn(b - a, n2, n2, generator=g, dtype=torch.float64)
            blocks = rotation_blocks(F[a:b], bands)
            t = time.perf_counter()
            out = left @ rotate_rows(T, blocks)
            total += time.perf_counter() - t
            del out
    return total


def brdf_alone(mesh, brdf, views: int, res: int, chunk: int) -> tuple[float, float, float | None]:
    """Seconds of the transport table's BRDF evaluations alone, on the pairs (upper view, texel
    above the tangent plane) of each chunk — the visible ones are fewer, so this is an upper floor.
    Timed three ways: the whole chunk in one torch call, in blocks of ``transport.PAIR_BLOCK`` pairs on one
    torch thread, and the compiled point pass (``transport_kernels.points``, one thread, into a float32
    table as the precompute's; None without the library); the bound uses the fastest."""
    from prt_torch.executor import torch_threads
    from prt_torch.transfer import transport_kernels as TK
    from prt_torch.transfer.transport import PAIR_BLOCK

    texels, _ = cube_directions(res)
    texels = texels.reshape(-1, 3)
    vd = icosphere_directions(views)
    F = check_frames(mesh)
    whole = blocked = 0.0
    compiled = None
    for a in range(0, mesh.num_vertices, chunk):  # a loop over chunks, as the precompute's
        b = min(mesh.num_vertices, a + chunk)
        wi = torch.einsum("kab,pb->kpa", F[a:b], texels)
        wo = torch.einsum("kab,jb->kja", F[a:b], vd)
        iv, jv, pv = torch.nonzero((wo[:, :, None, 2] > HORIZON_EPS) & (wi[:, None, :, 2] > 0), as_tuple=True)
        x, y = wi[iv, pv], wo[iv, jv]
        t = time.perf_counter()
        brdf.eval(x, y)
        whole += time.perf_counter() - t
        t = time.perf_counter()
        with torch_threads(1):
            for s in range(0, x.shape[0], PAIR_BLOCK):  # blocks of pairs, as the precompute's
                brdf.eval(x[s:s + PAIR_BLOCK], y[s:s + PAIR_BLOCK])
        blocked += time.perf_counter() - t
        model = TK.native_model(brdf, b - a) if TK.available()[0] else None
        if model is not None:
            T = torch.empty(b - a, vd.shape[0] * texels.shape[0], dtype=torch.float32)
            W = (wi[..., 2] > 0).to(torch.float64)
            t = time.perf_counter()
            TK.points(T, wi, wo, W, None, model, threads=1, horizon=HORIZON_EPS)
            compiled = (compiled or 0.0) + time.perf_counter() - t
    return whole, blocked, compiled


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bumpy_sphere:medium")
    ap.add_argument("--samples", type=int, default=1024)
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--kinds", nargs="+", default=["glossy", "mrt", "transport"], choices=["glossy", "mrt", "transport"])
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "kinds"))
    args = ap.parse_args(argv)
    mesh = builtin(args.scene)
    workers = default_workers()
    info = machine_info()
    tmp = Path(tempfile.mkdtemp(prefix="bench_kinds_"))
    from prt_torch.brdf import AshikhminShirley

    def run(kind):
        run_opts = RunOptions(workers=workers)
        if kind == "glossy":
            return precompute_glossy(mesh, 5, 5, samples=args.samples, run=run_opts)
        if kind == "mrt":
            return precompute_mrt(mesh, 5, 8, 11, samples=args.samples, run=run_opts)
        shutil.rmtree(tmp / "t", ignore_errors=True)
        return precompute_transport(mesh, tmp / "t", views=3, res=8, supersample=1, run=run_opts)  # point values: the bound's pairs

    results = []
    try:
        with RayCaster(mesh, workers=workers, min_parallel_rays=1) as wc:
            for kind in args.kinds:
                with RecordRays() as rec:
                    tr = run(kind)
                rows = []
                for _ in range(args.pairs):
                    t = time.perf_counter()
                    tr = run(kind)
                    tp = time.perf_counter() - t
                    tb = rec.replay(wc)
                    if kind == "transport":
                        whole, blocked, compiled = brdf_alone(mesh, AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0), 3, 8,
                                                              tr.meta["chunk_size"])
                        work, setup = min(x for x in (whole, blocked, compiled) if x is not None), 0.0
                        extra = {"work_whole_s": whole, "work_blocked_s": blocked, "work_compiled_s": compiled}
                    else:
                        work = gemms_alone(mesh, tr, 5, args.samples)
                        setup = float(tr.meta.get("brdf_seconds", 0.0))
                        extra = {}
                    rows.append({**extra, "precompute_s": tp, "bare_s": tb, "work_s": work, "setup_s": setup,
                                 "pace": (tb + work) / tp, "pace_without_setup": (tb + work) / max(tp - setup, 1e-9),
                                 "load": os.getloadavg()[0]})
                    print(kind, {k: round(v, 3) for k, v in rows[-1].items()}, flush=True)
                results.append({"kind": kind, "rays": rec.rays, "calls": len(rec.calls), "rows": rows,
                                "median_pace": statistics.median(r["pace"] for r in rows), "vertices": mesh.num_vertices,
                                "shape": list(tr.data.shape) if kind != "transport" else [mesh.num_vertices, 92, 6, 8, 8]})
                rec.calls.clear()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    res = {"benchmark": "kinds", "scene": args.scene, "samples": args.samples, "workers": workers, "machine": info,
           "results": results}
    out = Path(args.out)
    io.atomic_write_json(out.with_suffix(".json"), res)
    work_name = {"glossy": "GEMMs alone", "mrt": "GEMMs alone", "transport": "BRDF on the pairs alone"}
    lines = [
        "# Glossy, MRT and transport tables against bare Embree plus their unavoidable work (issue 42 part 2)",
        "",
        f"Scene `{args.scene}` ({mesh.num_vertices} vertices), {args.samples} samples (glossy 5→5 bands, MRT 5 bands → 8, "
        f"11×11 tents; transport: 92 views, 6×8×8 texels; default BRDF, shadows traced); {workers} ray-casting processes. "
        f"CPU: {info['cpu']} (Zen 3, AVX2; no kernel of this benchmark has an AVX-512 path); the machine was shared with "
        "other jobs (load average per repeat in the last column), so only ratios taken in the same repeat are compared.",
        "",
        "Bare: every ray-casting call of one precompute recorded and replayed bare on the same number of pre-started "
        "worker processes. Work alone: what the kind cannot avoid, timed alone on the same chunk shapes (glossy/MRT: "
        "the rotation into each vertex frame and `left @ R_p T_p` on one torch thread (the T_p sums, `W @ YY` before, left "
        "out: `outer_sums` runs over the selected entries only, so the bound is a floor); "
        "transport: the BRDF on every (upper view, "
        "texel above the tangent plane) pair, "
        "the fastest of one torch call per chunk, blocks of `PAIR_BLOCK` pairs on one torch thread and the compiled point "
        "pass `transport_kernels.points` on one thread; the transport precompute here stores point values, `supersample=1`, "
        "the pairs of that bound). "
        "Pace = (bare + work alone) / precompute (goal ≥ 0.5); the glossy/MRT "
        "precompute includes its once-per-run BRDF projection (column setup), the last pace column leaves it out.",
        "",
        "| kind | rays (occluded / intersect) | precompute s | setup s | bare Embree s | work alone s | pace | pace without setup | load |",
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        for row in r["rows"]:
            lines.append(f"| {r['kind']} | {r['rays'].get('occluded', 0)} / {r['rays'].get('intersect', 0)} | "
                         f"{row['precompute_s']:.2f} | {row['setup_s']:.2f} | {row['bare_s']:.2f} | {row['work_s']:.2f} | "
                         f"{row['pace']:.2f} | {row['pace_without_setup']:.2f} | {row['load']:.1f} |")
    lines += ["", "Median pace over the repeats: " + ", ".join(f"{r['kind']} **{r['median_pace']:.2f}**" for r in results) + ".", "",
              f"Work alone is {', '.join(f'{k}: {v}' for k, v in work_name.items())} (the transport's pairs include the "
              "texels blocked from the vertex, which the precompute skips: a floor a few per cent high here).", "",
              "Reproduce: `.venv/bin/python benchmarks/bench_kinds.py`."]
    io.atomic_write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
