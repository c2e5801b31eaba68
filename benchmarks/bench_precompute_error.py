"""Benchmark: Monte Carlo error of the diffuse precompute against rays, for every direction set
and estimator (issue 42, part 1: "the same error with fewer rays").

    .venv/bin/python benchmarks/bench_precompute_error.py [--scene bumpy_sphere] [--size small]
        [--albedo A] [--samples 64 256 1024] [--seeds 2] [--ref-factor 64] [--bands 5] [--ref-cache F.pt]
        [--methods uniform:plain qmc:auto] [--equal-rays]

For each (sampling, estimator) in {uniform, qmc, cosine} × {plain, control} and each sample
count N, the precompute (``precompute_diffuse``, shadows traced, ρ kept out) runs with ``--seeds``
seeds; its relative RMS error, sqrt(Σ_v |t_v − t_ref,v|² / Σ_v |t_ref,v|²) over every vertex and
coefficient, is measured against a reference of ``--ref-factor`` × the largest N rays per vertex
with an independent seed, for

* the shadowed transfer (bounces = 0) and
* one bounce (bounces = 1, default hit-point estimator): the total, and the interreflected part
  alone (total − direct, each run's own direct part),

plotted against the rays traced per vertex (log–log, with a 1/√N line through the first point of
today's estimator). ``cosine`` traces N rays per vertex where the others trace about N/2, so it is
run at N/2 to compare at equal rays. The reference is computed twice (qmc+control and
uniform+plain, both at the reference size, other seeds): their difference bounds its own error.

``--equal-rays`` (issue 42 §1): after each default (qmc + auto) row, today's estimator again at the
perfect square N = k² whose one-bounce run traces about the default's rays (a whole k × k grid of
its jittered set), per seed; the headline gives the ratio at equal rays (corrected by √ of the small
remaining ray ratio) and, as a second reading, against today's N error scaled by 1/√rays.
``--methods`` re-runs only some rows and keeps the scene's others from the report.

Writes reports/benchmarks/precompute_error.{md,json,png} atomically, a section, a headline line and
a row of panels per scene: a run replaces its own scene's section and keeps the others' (the
report covers bumpy_sphere, the scan stand-in scan_blob, occluder_over_plane and a grey
cornell_box, each with its mean occluded fraction of t00). Errors do not depend on the
machine's load; the seconds column does (it is the whole precompute, for orientation only).
"""
from __future__ import annotations

import argparse
import json
import math
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
from prt_torch.transfer.diffuse import precompute_diffuse  # noqa: E402

TODAY = ("uniform", "plain")  # the estimator before issue 42
METHODS = [(s, e) for s in ("uniform", "cosine", "qmc") for e in ("plain", "control", "auto")]
REF_SEED = 1_000_003


def run(mesh, bands, samples, seed, sampling, estimator, bounces):
    """(total [V, n²] float64, seconds, rays per vertex): every ray traced — the vertices' own, the
    hit points' (intersect and occluded alike) and the hits' per-face probe (``hit_choice_rays``)."""
    n = samples // 2 if sampling == "cosine" else samples  # equal rays: cosine traces N, the others ~N/2
    t = time.perf_counter()
    tr = precompute_diffuse(mesh, bands, n, bounces, seed=seed, sampling=sampling, estimator=estimator, shadows="always",
                            fold_albedo=False, bounce_tol=0.0, run=RunOptions(progress=False))
    sec = time.perf_counter() - t
    total = tr.data.to(torch.float64)
    m = tr.meta
    return total, sec, (m["rays_traced"] + m.get("hit_rays_traced", 0) + m.get("hit_choice_rays", 0)) / mesh.num_vertices


def rel(x, ref):
    return float(((x - ref) ** 2).sum().sqrt() / (ref ** 2).sum().sqrt())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="bumpy_sphere")
    ap.add_argument("--size", default="small")
    ap.add_argument("--samples", type=int, nargs="+", default=[64, 256, 1024])
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--ref-factor", type=int, default=64)
    ap.add_argument("--bands", type=int, default=5)
    ap.add_argument("--albedo", type=float, default=None,
                    help="a grey albedo for every vertex (a coloured scene such as cornell_box: fold_albedo=False "
                         "with bounces needs a grey one); default: the scene's own")
    ap.add_argument("--ref-cache", default=None, help="a .pt file keeping the references between runs (same settings)")
    ap.add_argument("--equal-rays", action="store_true",
                    help="also run today's estimator at the N whose one-bounce run traces the default's rays (per seed)")
    ap.add_argument("--methods", nargs="+", default=None, metavar="SAMPLING:ESTIMATOR",
                    help="run only these rows (e.g. uniform:plain qmc:auto); the scene's other rows are kept from the report")
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "precompute_error"))
    args = ap.parse_args(argv)
    torch.set_num_threads(max(1, os.cpu_count() or 1))
    mesh = builtin(args.scene, args.size, albedo=args.albedo)
    V = mesh.num_vertices
    load0 = os.getloadavg()[0]
    ref_n = args.ref_factor * max(args.samples)
    print(f"[bench] {args.scene}:{args.size} V={V}; reference {ref_n} samples (x{args.ref_factor})", flush=True)
    t0 = time.perf_counter()
    key = {"scene": args.scene, "size": args.size, "albedo": args.albedo, "bands": args.bands, "ref_n": ref_n, "mesh": mesh.content_hash()}
    cached = torch.load(args.ref_cache) if args.ref_cache and os.path.exists(args.ref_cache) else None
    if cached is not None and cached["key"] == key:
        ref0, ref0_check, ref1, t_ref = cached["ref0"], cached["ref0_check"], cached["ref1"], cached["seconds"]
    else:
        ref0, _, _ = run(mesh, args.bands, ref_n, REF_SEED, "qmc", "control", 0)
        ref0_check, _, _ = run(mesh, args.bands, ref_n, REF_SEED + 1, "uniform", "plain", 0)
        ref1, _, _ = run(mesh, args.bands, ref_n, REF_SEED, "qmc", "control", 1)
        t_ref = time.perf_counter() - t0
        if args.ref_cache:
            torch.save({"key": key, "ref0": ref0, "ref0_check": ref0_check, "ref1": ref1, "seconds": t_ref}, args.ref_cache)
    ref_inter = ref1 - ref0
    ref_self = rel(ref0_check, ref0)
    print(f"[bench] references in {t_ref:.0f} s; qmc+control vs uniform+plain reference: {ref_self:.2e}", flush=True)
    frac = 1 - ref0[:, 0] / precompute_diffuse(mesh, args.bands, 16, shadows="never", fold_albedo=False).data.to(torch.float64)[:, 0]
    occl = float(frac.mean())  # each vertex's occluded fraction of t00 (cosine-weighted), by the reference
    occl_q = [float(x) for x in torch.quantile(frac, torch.tensor([0.1, 0.5, 0.9], dtype=torch.float64))]
    rows = []
    methods = METHODS if args.methods is None else [tuple(m.split(":")) for m in args.methods]
    bad = [m for m in methods if m not in METHODS]
    if bad:
        sys.exit(f"--methods {':'.join(bad[0])}: accepted: {' '.join(s + ':' + e for s, e in METHODS)}")
    for sampling, estimator in methods:
        for N in args.samples:
            e0, e1, ei, rays, rays1, secs = [], [], [], [], [], []
            for s in range(args.seeds):
                d, sec0, r = run(mesh, args.bands, N, s, sampling, estimator, 0)
                t1, sec1, r1 = run(mesh, args.bands, N, s, sampling, estimator, 1)
                rays1.append(r1)
                e0.append(rel(d, ref0))
                e1.append(rel(t1, ref1))
                ei.append(rel(t1 - d, ref_inter))
                rays.append(r)
                secs.append(sec0)
            row = {"sampling": sampling, "estimator": estimator, "samples": N, "rays_per_vertex": float(np.mean(rays)),
                   "rays_per_vertex_bounce1": float(np.mean(rays1)),
                   "err_direct": float(np.mean(e0)), "err_bounce1_total": float(np.mean(e1)),
                   "err_bounce1_inter": float(np.mean(ei)), "seconds_direct": float(np.mean(secs)),
                   "err_direct_seeds": e0, "err_bounce1_total_seeds": e1}
            rows.append(row)
            print(f"[bench] {sampling:8s} {estimator:8s} N={N:5d} rays/v={row['rays_per_vertex']:7.1f} "
                  f"direct {row['err_direct']:.4f} 1-bounce {row['err_bounce1_total']:.4f} "
                  f"inter {row['err_bounce1_inter']:.4f} (rays/v {row['rays_per_vertex_bounce1']:.0f})", flush=True)
            today = next((x for x in rows if (x["sampling"], x["estimator"]) == TODAY and x["samples"] == N), None)
            if args.equal_rays and (sampling, estimator) == ("qmc", "auto") and today is not None:
                # today's estimator at about the default's rays (both scale with N): N a perfect square, where its
                # jittered sphere set is a whole k × k grid (other N leave strata out and read worse than 1/√N);
                # the small difference in rays left is corrected by √(rays ratio)
                k = max(1, int(round(math.sqrt(N * row["rays_per_vertex_bounce1"] / today["rays_per_vertex_bounce1"]))))
                n_eq = k * k
                eq = [run(mesh, args.bands, n_eq, s, *TODAY, 1) for s in range(args.seeds)]
                r_eq = float(np.mean([x[2] for x in eq]))
                row["equal_rays_today"] = {"samples": n_eq, "rays_per_vertex_bounce1": r_eq,
                                           "err_bounce1_total_seeds": [rel(x[0], ref1) for x in eq]}
                q = np.array(e1) / np.array(row["equal_rays_today"]["err_bounce1_total_seeds"])
                q = q * math.sqrt(row["rays_per_vertex_bounce1"] / r_eq)
                print(f"[bench]   today at N={n_eq} (rays/v {row['equal_rays_today']['rays_per_vertex_bounce1']:.0f}): "
                      f"one bounce {np.mean(row['equal_rays_today']['err_bounce1_total_seeds']):.4f}; the default's ratio per "
                      f"seed {' / '.join(f'{x:.3f}' for x in q)}", flush=True)
    load1 = os.getloadavg()[0]
    res = {"scene": f"{args.scene}:{args.size}", "albedo": args.albedo, "vertices": V, "bands": args.bands, "reference_samples": ref_n,
           "reference_seconds": t_ref, "reference_self_error": ref_self, "occluded_fraction_t00": occl,
           "occluded_quantiles_t00": occl_q, "seeds": args.seeds, "rows": rows, "cpu": machine_info()["cpu"],
           "load": [load0, load1], "samples": sorted(args.samples), "ref_factor": args.ref_factor}
    out = Path(args.out)
    scenes = load_scenes(out.with_suffix(".json"))
    old = scenes.get(res["scene"])
    if args.methods is not None and old is not None:  # the rows not re-run are kept (same references: --ref-cache)
        ran = {(x["sampling"], x["estimator"], x["samples"]) for x in rows}
        kept = [x for x in old["rows"] if (x["sampling"], x["estimator"], x["samples"]) not in ran]
        res["rows"] = sorted(kept + rows, key=lambda x: (METHODS.index((x["sampling"], x["estimator"])), x["samples"]))
        res["samples"] = sorted({x["samples"] for x in res["rows"]})
    scenes[res["scene"]] = res  # this scene's section replaced, the others kept
    write(scenes, out)


def load_scenes(path: Path) -> dict:
    """The scenes already in the report's JSON, by name (a file of one scene, the format before
    sections per scene, is read as that one section)."""
    if not path.exists():
        return {}
    old = json.loads(path.read_text())
    return {old["scene"]: old} if "rows" in old else old["scenes"]


def by(rows, sampling, estimator, key):
    """(rays per vertex, errors, N) of one method's rows; the one-bounce errors against every ray
    of the one-bounce run (vertex, hit and probe rays) where the rows record them."""
    r = [x for x in rows if x["sampling"] == sampling and x["estimator"] == estimator]
    xk = "rays_per_vertex_bounce1" if key != "err_direct" and all("rays_per_vertex_bounce1" in x for x in r) else "rays_per_vertex"
    return np.array([x[xk] for x in r]), np.array([x[key] for x in r]), [x["samples"] for x in r]


def write(scenes: dict, out: Path):
    """reports/benchmarks/precompute_error.{md,json,png}: a section, a headline line and a row of
    three panels per scene."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.parent.mkdir(parents=True, exist_ok=True)
    keys = [("err_direct", "shadowed (bounces = 0)"), ("err_bounce1_total", "one bounce: total"),
            ("err_bounce1_inter", "one bounce: interreflected part")]
    fig, axes = plt.subplots(len(scenes), 3, figsize=(15, 4.6 * len(scenes)), squeeze=False)
    for row_axes, res in zip(axes, scenes.values()):
        rows = res["rows"]
        for ax, (key, title) in zip(row_axes, keys):
            for sampling, estimator in METHODS:
                x, y, _ = by(rows, sampling, estimator, key)
                if len(x):
                    ax.loglog(x, y, {"control": "o-", "auto": "^-", "plain": "s--"}[estimator], label=f"{sampling} + {estimator}")
            x, y, _ = by(rows, *TODAY, key)
            if len(x):  # a report of some rows only (--methods into a new --out) has no line to draw
                ax.loglog(x, y[0] * np.sqrt(x[0] / x), "k:", lw=1, label="1/√N")
            ax.set_xlabel("rays traced per vertex" + ("" if key == "err_direct" else " (vertex + hit + probe rays)"))
            ax.set_ylabel("relative RMS error vs reference")
            ax.set_title(f"{res['scene']}: {title}", fontsize=10)
            ax.grid(True, which="both", alpha=0.3)
        row_axes[0].legend(fontsize=7)
    fig.suptitle("error vs rays, per scene (rows)")
    fig.tight_layout()
    with io.atomic_path(out.with_suffix(".png")) as tmp:
        fig.savefig(tmp, format="png", dpi=60)
    plt.close(fig)

    lines = [
        "# Precompute error vs rays: direction sets and the control variate (issue 42, part 1)",
        "",
        "Error = relative RMS over every vertex and coefficient, sqrt(Σ|t − t_ref|² / Σ|t_ref|²), mean over seeds, "
        "against a reference of 64× the largest N's samples per vertex (qmc + control, an independent seed; the same "
        "size with uniform + plain and another seed differs from it by the figure given per scene, which bounds its "
        "own error). Cosine runs at N/2 samples so that every row traces about the same rays. The occluded fraction "
        "of a vertex is 1 − t00(shadowed reference) / t00(unshadowed): the cosine-weighted share of its hemisphere "
        "that shadowing removes. Errors do not depend on the machine's load; the seconds column does (for "
        "orientation only).",
        "",
        "![error vs rays](precompute_error.png)",
        "",
        "Headlines at the default N = 1024 (the default qmc + auto against today's uniform + plain; goal ≤ 0.5×):",
        "",
    ]
    for res in scenes.values():
        h = headline(res)
        if h:
            lines.append(f"- `{res['scene']}` ({100 * res['occluded_fraction_t00']:.1f}% occluded on average): {h}")
    for res in scenes.values():
        lines += section(res)
    md = out.with_suffix(".md")
    glossy_mark = "\n## Glossy and MRT with one bounce\n"  # bench_precompute_error_glossy.py's section: kept
    old_md = md.read_text() if md.exists() else ""
    tail = glossy_mark + old_md.split(glossy_mark, 1)[1] if glossy_mark in old_md else ""
    with io.atomic_path(md) as tmp:
        Path(tmp).write_text("\n".join(lines) + "\n" + tail)
    with io.atomic_path(out.with_suffix(".json")) as tmp:
        Path(tmp).write_text(json.dumps({"scenes": scenes}, indent=1))
    print(f"[bench] wrote {out.with_suffix('.md')}")


def headline(res) -> str | None:
    rows = res["rows"]
    t = next((x for x in rows if (x["sampling"], x["estimator"]) == TODAY and x["samples"] == 1024), None)
    d = next((x for x in rows if (x["sampling"], x["estimator"]) == ("qmc", "auto") and x["samples"] == 1024), None)
    if t is None or d is None:
        return None
    h = (f"**{d['err_direct'] / t['err_direct']:.2f}×** today's error for the shadowed transfer and "
         f"**{d['err_bounce1_total'] / t['err_bounce1_total']:.2f}×** for the total with one bounce "
         f"({d['err_bounce1_inter'] / t['err_bounce1_inter']:.2f}× for the interreflected part alone")
    if "rays_per_vertex_bounce1" in d and "rays_per_vertex_bounce1" in t:
        h += f"; one-bounce rays per vertex {d['rays_per_vertex_bounce1']:.0f} vs {t['rays_per_vertex_bounce1']:.0f}"
    h += ")"
    eq = d.get("equal_rays_today")
    if eq:
        q = np.array(d["err_bounce1_total_seeds"]) / np.array(eq["err_bounce1_total_seeds"])
        q = q * math.sqrt(d["rays_per_vertex_bounce1"] / eq["rays_per_vertex_bounce1"])  # the rays made equal
        c = np.array(d["err_bounce1_total_seeds"]) / (t["err_bounce1_total"] * math.sqrt(
            t["rays_per_vertex_bounce1"] / d["rays_per_vertex_bounce1"]))
        h += (f"; with one bounce at equal rays (today at N = {eq['samples']}, {eq['rays_per_vertex_bounce1']:.0f} rays per "
              f"vertex against the default's {d['rays_per_vertex_bounce1']:.0f}, scaled by √ of their ratio): "
              f"**{q.mean():.2f}×**, per seed {q.min():.2f}–{q.max():.2f} ({len(q)} seeds); today's N = {t['samples']} error "
              f"scaled by 1/√rays instead: {c.mean():.2f}×, per seed {c.min():.2f}–{c.max():.2f}")
    return h


def seeds_note(res) -> str:
    """How many seeds each row averages: the last run's count for its rows (they keep per-seed
    errors), 2 for rows kept from an earlier run (``--methods``), which did not record them."""
    rows = res["rows"]
    new = sorted({len(x["err_direct_seeds"]) for x in rows if "err_direct_seeds" in x})
    if not new or len(new) == 1 and all("err_direct_seeds" in x for x in rows):
        return f"{res['seeds']} seeds per row"
    return (f"{'/'.join(map(str, new))} seeds per row for the rows re-run last (those with an equal-rays or per-seed "
            "record in the JSON), 2 for the rows kept from the earlier run")


def section(res) -> list[str]:
    rows = res["rows"]
    q = res.get("occluded_quantiles_t00")
    qs = f" (10/50/90th percentile over vertices: {q[0]:.2f} / {q[1]:.2f} / {q[2]:.2f})" if q else ""
    grey = f", grey albedo {res['albedo']}" if res.get("albedo") is not None else ""
    lines = [
        "", f"## `{res['scene']}`", "",
        f"{res['vertices']} vertices, {res['bands']} bands{grey}; shadowing removes {100 * res['occluded_fraction_t00']:.1f}% "
        f"of t00 on average{qs}. Reference: {res['reference_samples']} samples per vertex "
        f"({res['reference_seconds']:.0f} s); the uniform + plain reference differs from it by "
        f"{res['reference_self_error']:.1e}. {seeds_note(res)}. CPU: {res['cpu']}; load average "
        f"before/after: {res['load'][0]:.1f} / {res['load'][1]:.1f}.",
        "",
        "| sampling | estimator | N | rays / vertex | shadowed | ratio to today | rays / vertex, 1 bounce | 1 bounce: total | ratio "
        "| interreflected part | ratio | s (shadowed) |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    today = {x["samples"]: x for x in rows if (x["sampling"], x["estimator"]) == TODAY}
    for x in rows:
        t = today[x["samples"]]
        rays1 = f"{x['rays_per_vertex_bounce1']:.0f}" if "rays_per_vertex_bounce1" in x else "–"
        lines.append(
            f"| {x['sampling']} | {x['estimator']} | {x['samples']} | {x['rays_per_vertex']:.0f} | {x['err_direct']:.4f} | "
            f"{x['err_direct'] / t['err_direct']:.2f} | {rays1} | {x['err_bounce1_total']:.4f} | "
            f"{x['err_bounce1_total'] / t['err_bounce1_total']:.2f} | {x['err_bounce1_inter']:.4f} | "
            f"{x['err_bounce1_inter'] / t['err_bounce1_inter']:.2f} | {x['seconds_direct']:.2f} |")
    h = headline(res)
    if h:
        lines += ["", f"At N = 1024 the default (qmc + auto) has {h}; goal ≤ 0.5×."]
    scene, size = res["scene"].split(":")
    alb = f" --albedo {res['albedo']}" if res.get("albedo") is not None else ""
    lines += ["", f"Reproduce: `.venv/bin/python benchmarks/bench_precompute_error.py --scene {scene} --size {size}{alb} "
              f"--seeds {res['seeds']} --ref-factor {res.get('ref_factor', 64)} "
              f"--samples {' '.join(str(n) for n in sorted(today))}` (`--ref-cache F.pt` keeps the references "
              "between runs; the other scenes' sections are kept)."]
    return lines


if __name__ == "__main__":
    main()
