"""Benchmark: rays/s of the whole diffuse precompute vs a bare embreex occlusion call on the same rays.

    .venv/bin/python benchmarks/bench_transfer_diffuse.py [--scene bumpy_sphere:large] [--samples 1024]
                                                          [--bounces 0 2] [--workers N] [--quick]

Measured in one run:
* the whole ``precompute_diffuse`` (probe, ray generation, Embree, masked GEMM, chunk bookkeeping,
  interreflection) -> rays/s;
* the bound: the same rays (regenerated chunk by chunk, not timed) traced by a bare
  ``EmbreeScene.run(..., query='OCCLUDED')`` in this process (1 core), and the same split over
  the worker processes the precompute uses (all cores);
* GIL: the bare call on two threads vs one thread (embreex holds the GIL if 2 threads ≤ 1 thread);
* peak resident memory of the precompute (this process, then the workers).

Writes reports/benchmarks/transfer_diffuse.{md,json} atomically.
"""
from __future__ import annotations

import argparse
import os
import platform
import resource
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch import io  # noqa: E402
from prt_torch.scene import RayCaster, builtin, default_workers  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.diffuse import DiffuseSampler, precompute_diffuse  # noqa: E402

warnings.filterwarnings("ignore", message="Sparse")


def regenerate_rays(mesh, caster, sampler, chunk_size):
    """The precompute's rays, chunk by chunk (same generator as the precompute)."""
    V = mesh.num_vertices
    for a in range(0, V, chunk_size):
        b = min(V, a + chunk_size)
        frames = mesh.frames()[a:b] if sampler.sampling == "cosine" else None
        _, _, o, d, _ = sampler.rays(mesh.vertices[a:b], mesh.normals[a:b], frames, caster.eps, ids=np.arange(a, b))
        yield np.ascontiguousarray(o), np.ascontiguousarray(d)


def bare_occlusion(mesh, caster, sampler, chunk_size, workers_caster=None):
    """Seconds spent in the bare Embree calls only (ray generation excluded) and the ray count."""
    t_total, rays = 0.0, 0
    for o, d in regenerate_rays(mesh, caster, sampler, chunk_size):
        t = time.perf_counter()
        if workers_caster is None:
            caster._scene.run(o, d, query="OCCLUDED")
        else:
            workers_caster.trace(o, d, "occluded")
        t_total += time.perf_counter() - t
        rays += o.shape[0]
    return t_total, rays


def gil_probe(caster, o, d):
    """Seconds for one thread on all rays vs two threads on halves."""
    sc = caster._scene
    t = time.perf_counter()
    sc.run(o, d, query="OCCLUDED")
    one = time.perf_counter() - t
    halves = [(np.ascontiguousarray(o[k::2]), np.ascontiguousarray(d[k::2])) for k in range(2)]
    th = [threading.Thread(target=sc.run, args=h, kwargs={"query": "OCCLUDED"}) for h in halves]
    t = time.perf_counter()
    for x in th:
        x.start()
    for x in th:
        x.join()
    two = time.perf_counter() - t
    return one, two


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bumpy_sphere:large")
    ap.add_argument("--samples", type=int, default=1024)
    ap.add_argument("--bands", type=int, default=5)
    ap.add_argument("--bounces", type=int, nargs="+", default=[0, 2])
    ap.add_argument("--sampling", default="qmc", choices=["qmc", "uniform", "cosine"],
                    help="the precompute's direction set (the bare call traces the same rays)")
    ap.add_argument("--estimator", default="control", choices=["control", "plain"])
    ap.add_argument("--workers", type=int, default=None, help="default: all cores")
    ap.add_argument("--quick", action="store_true", help="bumpy_sphere:medium, 256 samples (smoke run)")
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "transfer_diffuse"))
    ap.add_argument("--pairs", type=int, default=3,
                    help="paired repeats: the bounces=0 precompute and the bare call on the workers, back to back")
    args = ap.parse_args(argv)
    if args.quick:
        args.scene, args.samples = "bumpy_sphere:medium", 256
    workers = args.workers or default_workers()
    mesh = builtin(args.scene)
    sampler = DiffuseSampler(args.bands, args.samples, 0, args.sampling, args.estimator)
    kw = {"sampling": args.sampling, "estimator": args.estimator}
    load0 = os.getloadavg()
    runs = []
    for B in args.bounces:
        rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        t = time.perf_counter()
        tr = precompute_diffuse(mesh, args.bands, args.samples, B, seed=0, shadows="always",
                                run=RunOptions(workers=workers), **kw)
        wall = time.perf_counter() - t
        rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
        child = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        runs.append({"bounces": B, "seconds": wall, "rays": tr.meta["rays_traced"],
                     "rays_per_s": tr.meta["rays_traced"] / wall, "bounces_used": tr.meta["bounces_used"],
                     "query": "intersect (first hit, for bounces)" if B > 0 else "occluded",
                     "peak_rss_mib_main": rss / 1024, "peak_rss_mib_main_before": rss0 / 1024,
                     "peak_rss_mib_worker": child / 1024, "chunk_size": tr.meta["chunk_size"]})
        print(f"precompute bounces={B}: {wall:.2f} s, {runs[-1]['rays_per_s'] / 1e6:.2f} Mrays/s", flush=True)
    chunk = runs[0]["chunk_size"]
    caster = RayCaster(mesh, workers=1)
    bare_t, bare_rays = bare_occlusion(mesh, caster, sampler, chunk)
    with RayCaster(mesh, workers=workers, min_parallel_rays=1) as wc:
        wc.trace(np.zeros((4, 3), np.float32), np.ones((4, 3), np.float32) / np.sqrt(3), "occluded")  # start workers
        bare_w_t, _ = bare_occlusion(mesh, caster, sampler, chunk, workers_caster=wc)
        # paired repeats: precompute (bounces 0) then the bare call on the same workers, back to
        # back, so a machine whose load changes slows both sides of each ratio
        pairs = []
        for _ in range(args.pairs):
            t = time.perf_counter()
            precompute_diffuse(mesh, args.bands, args.samples, 0, seed=0, shadows="always", run=RunOptions(workers=workers), **kw)
            tp = time.perf_counter() - t
            tb, _ = bare_occlusion(mesh, caster, sampler, chunk, workers_caster=wc)
            pairs.append({"precompute_s": tp, "bare_workers_s": tb, "ratio": tb / tp, "load": os.getloadavg()[0]})
            print(f"pair: precompute {tp:.2f} s, bare on workers {tb:.2f} s, ratio {tb / tp:.2f}", flush=True)
    ratios = sorted(p["ratio"] for p in pairs)
    paired = {"pairs": pairs, "median_ratio": ratios[len(ratios) // 2] if ratios else None}
    o, d = next(regenerate_rays(mesh, caster, sampler, chunk))
    gil_one, gil_two = gil_probe(caster, o, d)
    bare_rps = bare_rays / bare_t
    bare_w_rps = bare_rays / bare_w_t
    load1 = os.getloadavg()
    for r in runs:
        r["ratio_to_bare_1core"] = r["rays_per_s"] / bare_rps
        r["ratio_to_bare_workers"] = r["rays_per_s"] / bare_w_rps
    result = {
        "benchmark": "transfer_diffuse",
        "scene": args.scene, "vertices": mesh.num_vertices, "faces": mesh.num_faces, "samples": args.samples,
        "bands": args.bands, "workers": workers, "cpu_count": os.cpu_count(), "loadavg_before": load0,
        "loadavg_after": load1, "python": platform.python_version(), "torch": torch.__version__,
        "bare_embree_occluded": {"rays": bare_rays, "seconds_1core": bare_t, "rays_per_s_1core": bare_rps,
                                 "seconds_workers": bare_w_t, "rays_per_s_workers": bare_w_rps},
        "gil": {"rays": int(o.shape[0]), "one_thread_s": gil_one, "two_threads_s": gil_two,
                "two_thread_speedup": gil_one / gil_two,
                "verdict": "embreex holds the GIL (threads do not scale); processes used" if gil_one / gil_two < 1.3
                else "threads scale"},
        "runs": runs,
        "paired": paired,
    }
    out = Path(args.out)
    io.atomic_write_json(out.with_suffix(".json"), result)
    lines = [
        "# Diffuse transfer precompute vs bare Embree",
        "",
        f"Scene `{args.scene}`: {mesh.num_vertices} vertices, {mesh.num_faces} faces; {args.samples} samples "
        f"(sampling `{args.sampling}`, estimator `{args.estimator}`; about half that many rays traced per vertex), "
        f"bands {args.bands}; {workers} ray-casting",
        f"processes on {os.cpu_count()} cores. Load average before/after: {load0[0]:.1f} / {load1[0]:.1f}",
        "(other jobs shared the machine; the ratios below are taken in the same run).",
        "",
        "| run | rays | seconds | Mrays/s | ratio to bare 1-core | ratio to bare on workers | peak RSS main / worker (MiB) |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for r in runs:
        lines.append(f"| precompute, bounces={r['bounces']} ({r['query']}) | {r['rays']} | {r['seconds']:.2f} | "
                     f"{r['rays_per_s'] / 1e6:.2f} | {r['ratio_to_bare_1core']:.2f} | {r['ratio_to_bare_workers']:.2f} | "
                     f"{r['peak_rss_mib_main']:.0f} / {r['peak_rss_mib_worker']:.0f} |")
    lines += [
        f"| bare `EmbreeScene.run(OCCLUDED)`, 1 core | {bare_rays} | {bare_t:.2f} | {bare_rps / 1e6:.2f} | 1.00 | | |",
        f"| bare occluded split over {workers} processes | {bare_rays} | {bare_w_t:.2f} | {bare_w_rps / 1e6:.2f} | "
        f"{bare_w_rps / bare_rps:.2f} | 1.00 | |",
        "",
        f"Paired (bounces=0 precompute, then the bare occluded call on the same {workers} worker processes, back to back, "
        f"{len(pairs)} times): rate ratio precompute / bare = median **{paired['median_ratio']:.2f}** "
        f"({', '.join('%.2f' % p['ratio'] for p in pairs)}; goal ≥ 0.8).",
        "",
        f"GIL: the bare call on {o.shape[0]} rays takes {gil_one:.3f} s on one thread and {gil_two:.3f} s on two threads "
        f"(speedup {gil_one / gil_two:.2f}): {result['gil']['verdict']}.",
        "",
        "Bare timings count only the Embree calls (the same rays are regenerated outside the timer); the",
        "precompute timings count everything (probe-free here: shadows='always'; ray generation, Embree,",
        "GEMM, chunking, and for bounces the first-hit query, sparse bounce matrix and bounce products).",
        "Peak RSS is the process high-water mark (ru_maxrss) after each run.",
        "",
        "Reproduce: `.venv/bin/python benchmarks/bench_transfer_diffuse.py`.",
    ]
    io.atomic_write_text(out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
