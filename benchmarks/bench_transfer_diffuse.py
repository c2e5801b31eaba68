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
from prt_torch.harness.timing import machine_info  # noqa: E402
from prt_torch.scene import RayCaster, builtin, default_workers  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.diffuse import DiffuseSampler, precompute_diffuse  # noqa: E402

warnings.filterwarnings("ignore", message="Sparse")

#: which compiled path the rows used (kernels/raygen.c has one path, built with -march=native)
KERNEL_PATH = ("ray generation, choice and SH sums: kernels/raygen.c built -march=native, scalar code the compiler "
               "vectorises for the CPU at hand — AVX2 on this Zen 3 (family 25 model 1); raygen has no AVX-512-specific path")


def regenerate_rays(mesh, caster, sampler, chunk_size):
    """The precompute's rays, chunk by chunk (same generator as the precompute)."""
    V = mesh.num_vertices
    for a in range(0, V, chunk_size):
        b = min(V, a + chunk_size)
        frames = mesh.frames()[a:b] if sampler.sampling == "cosine" else None
        _, _, o, d, _ = sampler.rays(caster.local(mesh.vertices[a:b]), mesh.normals[a:b], frames, caster.eps, ids=np.arange(a, b))
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


class RecordRays:
    """``with RecordRays() as rec: <precompute>``: every ray-casting call of the block
    (query, origins, directions; copies) in ``rec.calls``; :meth:`replay` traces them again, bare,
    on a given caster and returns the seconds spent in its ``trace`` calls alone — the same number
    and kind of rays (occluded or intersect) in the same batches as the precompute traced."""

    def __enter__(self):
        self.calls = []
        self._orig = RayCaster._dispatch  # every query (trace, occluded, intersect) goes through it
        rec = self

        def dispatch(caster, query, o, d, tfar):
            if tfar is not None:
                raise ValueError("RecordRays replays rays without tfar; accepted: precomputes that trace to infinity")
            rec.calls.append((query, np.array(o, np.float32), np.array(d, np.float32)))
            return rec._orig(caster, query, o, d, tfar)

        RayCaster._dispatch = dispatch
        return self

    def __exit__(self, *exc):
        RayCaster._dispatch = self._orig

    @property
    def rays(self) -> dict:
        out = {}
        for q, o, _ in self.calls:
            out[q] = out.get(q, 0) + o.shape[0]
        return out

    def replay(self, caster) -> float:
        t_total = 0.0
        for q, o, d in self.calls:
            t = time.perf_counter()
            caster.trace(o, d, q)
            t_total += time.perf_counter() - t
        return t_total


def paired_bounces(mesh, args, workers, wc, pairs: int, bounces: int):
    """Issue 42 part 2 (2): diffuse with bounces (hit-point estimator, the defaults) against bare
    Embree on exactly its rays: the first-hit (intersect) primary rays and every hit point's
    secondary rays (intersect below the last level, occluded at it), recorded from one run and
    replayed on the same worker processes; interleaved ``pairs`` times."""
    kw = {"sampling": args.sampling, "estimator": args.estimator}
    with RecordRays() as rec:
        tr = precompute_diffuse(mesh, args.bands, args.samples, bounces, seed=0, shadows="always",
                                run=RunOptions(workers=workers), **kw)
    rows = []
    for _ in range(pairs):
        t = time.perf_counter()
        precompute_diffuse(mesh, args.bands, args.samples, bounces, seed=0, shadows="always", run=RunOptions(workers=workers), **kw)
        tp = time.perf_counter() - t
        tb = rec.replay(wc)
        rows.append({"precompute_s": tp, "bare_s": tb, "pace": tb / tp, "load": os.getloadavg()[0]})
        print(f"bounces={bounces} pair: precompute {tp:.2f} s, bare replay {tb:.2f} s, pace {tb / tp:.2f}", flush=True)
    paces = sorted(r["pace"] for r in rows)
    res = {"bounces": bounces, "bounces_used": tr.meta["bounces_used"], "rays": rec.rays, "calls": len(rec.calls),
           "rows": rows, "median_pace": paces[len(paces) // 2]}
    rec.calls.clear()
    return res


def paired_defaults(mesh, args, workers, wc, caster, pairs: int):
    """Issue 42 part 2 (1): the default (qmc + auto) against bare Embree on its own rays and
    against the former default (uniform + plain), interleaved in one run: each repeat times the
    qmc + auto precompute, the bare occluded call on the same rays (same worker processes), the
    uniform + plain precompute and the bare call on its rays, back to back."""
    confs = [("qmc", "auto"), ("uniform", "plain")]
    samplers = {c: DiffuseSampler(args.bands, args.samples, 0, *c) for c in confs}
    chunks = {}
    for c in confs:  # the precompute's own chunk size (same rays per chunk as it traces)
        tr = precompute_diffuse(mesh, args.bands, args.samples, 0, seed=0, shadows="always",
                                run=RunOptions(workers=workers), sampling=c[0], estimator=c[1])
        chunks[c] = (tr.meta["chunk_size"], tr.meta["rays_traced"])
    rows = []
    for _ in range(pairs):
        row = {"load": os.getloadavg()[0]}
        for c in confs:
            t = time.perf_counter()
            precompute_diffuse(mesh, args.bands, args.samples, 0, seed=0, shadows="always", run=RunOptions(workers=workers),
                               sampling=c[0], estimator=c[1])
            row[f"{c[0]}+{c[1]}"] = time.perf_counter() - t
            row[f"bare {c[0]}"], _ = bare_occlusion(mesh, caster, samplers[c], chunks[c][0], workers_caster=wc)
        rows.append(row)
        print("defaults pair:", {k: round(v, 3) for k, v in row.items()}, flush=True)

    def med(f):
        v = sorted(f(r) for r in rows)
        return v[len(v) // 2]

    return {
        "rays": {f"{c[0]}+{c[1]}": chunks[c][1] for c in confs},
        "rows": rows,
        "pace_default_vs_bare": med(lambda r: r["bare qmc"] / r["qmc+auto"]),
        "pace_former_vs_bare": med(lambda r: r["bare uniform"] / r["uniform+plain"]),
        "time_default_over_former": med(lambda r: r["qmc+auto"] / r["uniform+plain"]),
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="bumpy_sphere:large")
    ap.add_argument("--samples", type=int, default=1024)
    ap.add_argument("--bands", type=int, default=5)
    ap.add_argument("--bounces", type=int, nargs="+", default=[0])
    ap.add_argument("--sampling", default="qmc", choices=["qmc", "uniform", "cosine"],
                    help="the precompute's direction set (the bare call traces the same rays)")
    ap.add_argument("--estimator", default="auto", choices=["auto", "control", "plain"])
    ap.add_argument("--workers", type=int, default=None, help="default: all cores")
    ap.add_argument("--quick", action="store_true", help="bumpy_sphere:medium, 256 samples (smoke run)")
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "transfer_diffuse"))
    ap.add_argument("--bounce-pairs", type=int, nargs="*", default=[1, 2],
                    help="bounce counts whose precompute is paired with a bare replay of all its rays (none: skip)")
    ap.add_argument("--no-defaults", action="store_true",
                    help="skip the paired default (qmc + auto) vs bare vs former default (uniform + plain) section")
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
        defaults = None if args.no_defaults else paired_defaults(mesh, args, workers, wc, caster, args.pairs)
        bounce_pairs = [paired_bounces(mesh, args, workers, wc, args.pairs, B) for B in args.bounce_pairs]
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
        "cpu": machine_info()["cpu"],
        "defaults": defaults,
        "bounce_pairs": bounce_pairs,
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
    ]
    if defaults is not None:
        rs = defaults["rows"]
        lines += [
            "## The default (qmc + auto) against bare Embree and against the former default (uniform + plain)",
            "",
            f"Interleaved in one run, {len(rs)} times: the qmc + auto precompute, the bare occluded call on its rays, the "
            f"uniform + plain precompute, the bare call on its rays (the same {workers} worker processes; bare counts the "
            f"Embree calls only). Rays: qmc + auto {defaults['rays']['qmc+auto']}, uniform + plain "
            f"{defaults['rays']['uniform+plain']}. CPU: {result['cpu']} ({KERNEL_PATH}); load average at each repeat: "
            f"{', '.join('%.1f' % r['load'] for r in rs)}.",
            "",
            "| repeat | qmc + auto s | bare on its rays s | pace (bare / precompute) | uniform + plain s | bare on its rays s | pace "
            "| qmc + auto / uniform + plain time |",
            "|---:|---:|---:|---:|---:|---:|---:|---:|",
        ]
        for n, r in enumerate(rs, 1):
            lines.append(f"| {n} | {r['qmc+auto']:.2f} | {r['bare qmc']:.2f} | {r['bare qmc'] / r['qmc+auto']:.2f} | "
                         f"{r['uniform+plain']:.2f} | {r['bare uniform']:.2f} | {r['bare uniform'] / r['uniform+plain']:.2f} | "
                         f"{r['qmc+auto'] / r['uniform+plain']:.2f} |")
        lines += [
            "",
            f"Medians: the default runs at **{defaults['pace_default_vs_bare']:.2f}×** bare Embree's pace on its rays "
            f"(time {1 / defaults['pace_default_vs_bare']:.2f}× bare; goal ≤ ~1.1×), the former default at "
            f"{defaults['pace_former_vs_bare']:.2f}×; the default takes **{defaults['time_default_over_former']:.2f}×** the "
            "former default's time (1.98× before its directions, choice and SH sum were compiled).",
            "",
        ]
    if bounce_pairs:
        lines += [
            "## Diffuse with bounces (hit-point estimator) against bare Embree on all its rays",
            "",
            "Every `trace` call of one precompute (the primary rays' first-hit queries and each hit point's secondary rays: "
            "intersect below the last level, occluded at it) recorded, then replayed bare on the same "
            f"{workers} worker processes, interleaved with the precompute {args.pairs} times (bare counts its `trace` calls only; "
            f"load average at each repeat in the last column). CPU: {result['cpu']} ({KERNEL_PATH}).",
            "",
            "| bounces (used) | rays intersect / occluded | trace calls | precompute s | bare replay s | pace (bare / precompute) | load |",
            "|---|---:|---:|---:|---:|---:|---:|",
        ]
        for bp in bounce_pairs:
            for r in bp["rows"]:
                lines.append(f"| {bp['bounces']} ({bp['bounces_used']}) | {bp['rays'].get('intersect', 0)} / "
                             f"{bp['rays'].get('occluded', 0)} | {bp['calls']} | {r['precompute_s']:.2f} | {r['bare_s']:.2f} | "
                             f"{r['pace']:.2f} | {r['load']:.1f} |")
        lines += ["", "Median pace: " + ", ".join(f"bounces={bp['bounces']} **{bp['median_pace']:.2f}**" for bp in bounce_pairs)
                  + " (goal ≥ 0.5).", ""]
    lines += [
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
