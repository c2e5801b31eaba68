"""Benchmark: Monte Carlo error of the glossy and MRT precomputes with one bounce (issue 42 §1),
the estimator before issue 42 against today's, every ray counted.

    .venv/bin/python benchmarks/bench_precompute_error_glossy.py [--scene cornell_box --size small --albedo 0.8]
        [--kinds glossy mrt] [--samples 256] [--every 8] [--seeds 2] [--ref-factor 64] [--ref-cache F.pt]

Glossy exit transfer M_p = B R_p T_p (Sloan 2003 §3.1; default BRDF, ``--bands`` in and out) and
MRT A_p = G⁻¹ C B R_p T_p (Lehtinen & Kautz 2003 eq. 9; ``--tents`` per side) on every
``--every``-th vertex (``vertices=``: the same rows the whole run computes), with ``bounces = 0``
(shadowed) and ``bounces = 1``: a blocked direction brings the diffuse exit radiance of the point
it hits, estimated there by :class:`~prt_torch.transfer.diffuse.HitBounce` (Sloan 2002 §5). Rows:

* ``plain (before issue 42)``: the visible sum at the vertex and the hits' plain sum with
  independent rotations;
* ``control (main's default)``: the control variate at the vertex (exact unshadowed T_p minus the
  blocked directions) and at every hit (unguided): the glossy/MRT default before this benchmark;
* ``auto (default)``: per vertex the control variate where at least half of its directions are
  open and the plain sum elsewhere; at the hits the diffuse default's 'auto' (per hit from the
  face probe, the mostly blocked flat faces' rays guided).

Error: relative RMS over every selected vertex and matrix entry, sqrt(Σ|X − X_ref|² / Σ|X_ref|²),
mean over ``--seeds`` seeds, against a reference of ``--ref-factor`` × the samples per vertex with
independent seeds: the mean of a 'control' run (hits 'control', unguided) and a 'plain' run, each
64× the rays, so that no row's own estimator makes it; their difference bounds its error — for the shadowed
transfer, the one-bounce total and its interreflected part (total − shadowed of the same seed).
Rays per vertex: every ray traced — the vertices' (``rays_traced``) and the hits' (intersect and
occluded, ``hit_rays_traced``) per selected vertex, plus the face probe of 'auto'
(``hit_choice_rays``, traced once per run over every face) per mesh vertex, what a whole run pays.

Writes the section ``## Glossy and MRT with one bounce`` of reports/benchmarks/precompute_error.md
(a scene's rows replace its earlier rows; the diffuse sections are kept) and
reports/benchmarks/precompute_error_glossy.json. Errors do not depend on the machine's load.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch import io  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.glossy import precompute_glossy  # noqa: E402
from prt_torch.transfer.mrt import precompute_mrt  # noqa: E402

REF_SEED = 1_000_003
#: (row name, estimator): the vertex's and the hits' (HitBounce reads the estimator of the same name)
METHODS = [("plain (before issue 42)", "plain"), ("control (main's default)", "control"), ("auto (default)", "auto")]
MARK = "## Glossy and MRT with one bounce"


def run(kind, mesh, args, samples, seed, estimator, bounces):
    """(data float64 [k, rows, n²], rays per vertex (module docstring)) of one precompute."""
    sub = torch.arange(0, mesh.num_vertices, args.every)
    kw = dict(samples=samples, seed=seed, shadows=True, bounces=bounces, vertices=sub, estimator=estimator,
              run=RunOptions(progress=False))
    if kind == "glossy":
        tr = precompute_glossy(mesh, bands=args.bands, bands_out=args.bands, **kw)
    else:
        tr = precompute_mrt(mesh, bands=args.bands, bands_out=args.bands, M=args.tents, **kw)
    m = tr.meta
    rays = (m["rays_traced"] + m.get("hit_rays_traced", 0)) / sub.numel() + m.get("hit_choice_rays", 0) / mesh.num_vertices
    return tr.data.to(torch.float64), rays


def rel(x, ref):
    return float(((x - ref) ** 2).sum().sqrt() / (ref ** 2).sum().sqrt())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="cornell_box")
    ap.add_argument("--size", default="small")
    ap.add_argument("--albedo", type=float, default=None, help="a grey albedo for every vertex (default: the scene's own)")
    ap.add_argument("--kinds", nargs="+", default=["glossy", "mrt"], choices=["glossy", "mrt"])
    ap.add_argument("--samples", type=int, default=256)
    ap.add_argument("--every", type=int, default=8)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--ref-factor", type=int, default=64)
    ap.add_argument("--bands", type=int, default=4)
    ap.add_argument("--tents", type=int, default=6)
    ap.add_argument("--ref-cache", default=None, help="a .pt file keeping the references between runs (same settings)")
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "precompute_error"))
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    mesh = builtin(args.scene, args.size, albedo=args.albedo)
    load0 = os.getloadavg()[0]
    ref_n = args.ref_factor * args.samples
    key = {"scene": args.scene, "size": args.size, "albedo": args.albedo, "bands": args.bands, "tents": args.tents,
           "ref_n": ref_n, "every": args.every, "mesh": mesh.content_hash()}
    cached = torch.load(args.ref_cache) if args.ref_cache and os.path.exists(args.ref_cache) else None
    refs = cached["refs"] if cached is not None and cached["key"] == key else {}
    V = mesh.num_vertices
    print(f"[glossy-err] {args.scene}:{args.size} {len(range(0, V, args.every))} of {V} vertices; reference {ref_n} "
          f"samples; load {load0:.1f}", flush=True)
    rows = []
    for kind in args.kinds:
        if kind not in refs:
            t0 = time.perf_counter()
            c0, _ = run(kind, mesh, args, ref_n, REF_SEED, "control", 0)
            c1, _ = run(kind, mesh, args, ref_n, REF_SEED, "control", 1)
            p0, _ = run(kind, mesh, args, ref_n, REF_SEED + 1, "plain", 0)
            p1, _ = run(kind, mesh, args, ref_n, REF_SEED + 1, "plain", 1)
            refs[kind] = {"ref0": (c0 + p0) / 2, "ref1": (c1 + p1) / 2, "self": rel(c1, p1), "seconds": time.perf_counter() - t0}
            if args.ref_cache:
                torch.save({"key": key, "refs": refs}, args.ref_cache)
            print(f"[glossy-err] {kind} reference in {refs[kind]['seconds']:.0f} s; its two halves differ by "
                  f"{refs[kind]['self']:.1e}", flush=True)
        ref0, ref1 = refs[kind]["ref0"], refs[kind]["ref1"]
        for name, est in METHODS:
            e0, e1, ei, r0s, r1s = [], [], [], [], []
            t0 = time.perf_counter()
            for s in range(args.seeds):
                d, ra = run(kind, mesh, args, args.samples, s, est, 0)
                t1, rb = run(kind, mesh, args, args.samples, s, est, 1)
                e0.append(rel(d, ref0))
                e1.append(rel(t1, ref1))
                ei.append(rel(t1 - d, ref1 - ref0))
                r0s.append(ra)
                r1s.append(rb)
            row = {"kind": kind, "method": name, "estimator": est, "samples": args.samples,
                   "rays_per_vertex": float(np.mean(r0s)), "rays_per_vertex_bounce1": float(np.mean(r1s)),
                   "err_direct": float(np.mean(e0)), "err_bounce1_total": float(np.mean(e1)),
                   "err_bounce1_inter": float(np.mean(ei)), "err_bounce1_total_seeds": e1,
                   "seconds": time.perf_counter() - t0, "reference_self_error": refs[kind]["self"]}
            rows.append(row)
            print(f"[glossy-err] {kind:6s} {name:30s} rays/v {row['rays_per_vertex']:6.0f} / {row['rays_per_vertex_bounce1']:6.0f}"
                  f"  shadowed {row['err_direct']:.4f}  1 bounce {row['err_bounce1_total']:.4f}  inter "
                  f"{row['err_bounce1_inter']:.4f}  ({row['seconds']:.0f} s)", flush=True)
    res = {"scene": f"{args.scene}:{args.size}", "albedo": args.albedo, "vertices": V, "every": args.every,
           "bands": args.bands, "tents": args.tents, "samples": args.samples, "reference_samples": ref_n,
"seeds": args.seeds, "rows": rows, "cpu": machine_info()["cpu"],
           "load": [load0, os.getloadavg()[0]], "ref_factor": args.ref_factor}
    out = Path(args.out)
    jpath = out.parent / (out.name + "_glossy.json")
    scenes = json.loads(jpath.read_text())["scenes"] if jpath.exists() else {}
    scenes[res["scene"]] = res
    with io.atomic_path(jpath) as tmp:
        Path(tmp).write_text(json.dumps({"scenes": scenes}, indent=1))
    md = out.with_suffix(".md")
    text = md.read_text() if md.exists() else ""
    head = text.split("\n" + MARK + "\n")[0].rstrip("\n")
    with io.atomic_path(md) as tmp:
        Path(tmp).write_text(head + "\n\n" + "\n".join(section(scenes)) + "\n")
    print(f"[glossy-err] wrote {md} and {jpath}")


def section(scenes: dict) -> list[str]:
    """The report's glossy/MRT section: one table per scene, ratios to the 'before' row."""
    lines = [MARK, "",
             "Written by `benchmarks/bench_precompute_error_glossy.py` (kept at the end of this report). Glossy exit "
             "transfer B R_p T_p and MRT G⁻¹C B R_p T_p, default BRDF, on every `every`-th vertex; relative RMS error "
             "over every entry against a reference of 64× the samples (other seeds: the mean of a control-variate run and a "
             "plain-sum run, hits unguided; the two halves' relative difference is given per kind). "
             "Rays per vertex: vertex + hit rays (intersect and occluded) + the face probe per mesh "
             "vertex. Ratios are to the estimator before issue 42 (plain at vertex and hits)."]
    for res in scenes.values():
        grey = f", grey albedo {res['albedo']}" if res.get("albedo") is not None else ""
        lines += ["", f"### `{res['scene']}`{grey}", "",
                  f"{len(range(0, res['vertices'], res['every']))} of {res['vertices']} vertices (every {res['every']}th), "
                  f"{res['bands']} bands in and out, MRT "
                  f"{res['tents']}×{res['tents']} tents, N = {res['samples']} sphere samples (about N/2 traced above the "
                  f"tangent plane), reference {res['reference_samples']} samples (8 rays per hit: 64× the rays); "
                  f"{res['seeds']} seeds per row. CPU: {res['cpu']}; load average before/after "
                  f"{res['load'][0]:.1f} / {res['load'][1]:.1f}.", "",
                  "| kind | estimator | rays / vertex (shadowed) | shadowed | ratio | rays / vertex, 1 bounce | 1 bounce: total "
                  "| ratio | per seed | interreflected part | ratio |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---|---:|---:|"]
        for x in res["rows"]:
            b = next(y for y in res["rows"] if y["kind"] == x["kind"] and y["estimator"] == "plain")
            seeds = " / ".join(f"{e:.4f}" for e in x["err_bounce1_total_seeds"])
            lines.append(
                f"| {x['kind']} | {x['method']} | {x['rays_per_vertex']:.0f} | {x['err_direct']:.4f} | "
                f"{x['err_direct'] / b['err_direct']:.2f} | {x['rays_per_vertex_bounce1']:.0f} | {x['err_bounce1_total']:.4f} | "
                f"{x['err_bounce1_total'] / b['err_bounce1_total']:.2f} | {seeds} | {x['err_bounce1_inter']:.4f} | "
                f"{x['err_bounce1_inter'] / b['err_bounce1_inter']:.2f} |")
        lines += ["", "Reference halves (control vs plain, one bounce) differ by " + ", ".join(
            f"{k} {v:.1e}" for k, v in {x["kind"]: x.get("reference_self_error", float("nan")) for x in res["rows"]}.items())
            + " (the mean's own error is about half of that)."]
        scene, size = res["scene"].split(":")
        alb = f" --albedo {res['albedo']}" if res.get("albedo") is not None else ""
        lines += ["", f"Reproduce: `.venv/bin/python benchmarks/bench_precompute_error_glossy.py --scene {scene} --size {size}"
                  f"{alb} --samples {res['samples']} --every {res['every']} --seeds {res['seeds']} --bands {res['bands']} "
                  f"--tents {res['tents']}`."]
    return lines


if __name__ == "__main__":
    main()
