"""Convex objects: a spherical harmonic reflection map (Ramamoorthi 2002 ch. 5) against unshadowed
glossy PRT (Sloan 2003 §3.1, exit matrices M_p = B R_p T_p) for the same BRDF and light, on a
sphere and on the convex hull of a scan-like mesh (the built-in bumpy_sphere's hull).

For every mesh: each method's per-vertex radiance towards one camera eye against a brute-force
reference (per vertex, Σ over the environment's pixels of L(ω) f_r max(n·ω, 0) Ω in the vertex's
tangent frame — the full-resolution light, no SH), as PSNR over the vertices facing the eye;
bytes (the SHRM file, per object; the exit matrices, per vertex, float32); precompute time; and
per-frame time (radiance of every vertex for a new view), the last as an interleaved paired ratio.

Run: .venv/bin/python benchmarks/bench_shrm_convex.py [--quick]   (about 2 minutes)
Writes reports/benchmarks/shrm_convex.md and shrm_convex.json.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import trimesh

from prt_torch import relight
from prt_torch import shrm as S
from prt_torch.brdf import Microfacet
from prt_torch.harness.metrics import psnr_vs_reference
from prt_torch.harness.timing import machine_info, measure_paired
from prt_torch.io import atomic_write_json, atomic_write_text
from prt_torch.lighting import builtin_environment
from prt_torch.scene import builtin, load_mesh
from prt_torch.scene.builtins import geodesic_sphere
from prt_torch.transfer import precompute_glossy

OUT = Path(__file__).resolve().parent.parent / "reports" / "benchmarks"


def _mesh_from(v: np.ndarray, f: np.ndarray, name: str):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / f"{name}.ply"
        trimesh.Trimesh(v, f, process=False).export(p)
        m = load_mesh(p)
    m.name = name
    return m


def meshes(quick: bool):
    v, f = geodesic_sphere(8 if quick else 16)
    sphere = _mesh_from(np.asarray(v), np.asarray(f), "sphere")
    bumpy = builtin("bumpy_sphere", size="small" if quick else "medium")
    hull = trimesh.Trimesh(bumpy.vertices.numpy(), bumpy.faces.numpy(), process=False).convex_hull
    return [sphere, _mesh_from(np.asarray(hull.vertices), np.asarray(hull.faces), "bumpy_sphere_hull")]


def reference(brdf, env, mesh, eye) -> tuple[torch.Tensor, torch.Tensor]:
    """Brute force per vertex over the environment's pixels (``shrm.reference_radiance``):
    ``([V, C] radiance, [V] facing mask)``."""
    dirs = env.directions().reshape(-1, 3)
    Lw = env.image.reshape(-1, env.channels).to(torch.float64) * env.solid_angles().reshape(-1)[:, None]
    v = eye[None] - mesh.vertices
    v = v / v.norm(dim=-1, keepdim=True)
    facing = (v * mesh.normals).sum(-1) > 0.02
    n = mesh.normals / mesh.normals.norm(dim=-1, keepdim=True)
    return S.reference_radiance(brdf, dirs, Lw, n, v), facing


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t_start = time.perf_counter()
    brdf = Microfacet(0.3)
    env = builtin_environment("studio", size=64)
    bands = 6 if args.quick else 8
    samples = 1024 if args.quick else 4096
    epsilons = (0.03, 0.01)
    rows = []
    for mesh in meshes(args.quick):
        eye = torch.tensor([3.0, -2.0, 2.5], dtype=torch.float64) + mesh.vertices.mean(0)
        ref, facing = reference(brdf, env, mesh, eye)
        views = eye[None] - mesh.vertices
        views = views / views.norm(dim=-1, keepdim=True)
        # glossy PRT, unshadowed (tangent-plane cut only), same BRDF and light
        t0 = time.perf_counter()
        g = precompute_glossy(mesh, bands, bands, brdf=brdf, shadows="never", samples=samples, seed=0)
        t_prt = time.perf_counter() - t0
        M = g.data.to(torch.float32)
        L = env.project(bands).to(torch.float32)
        out_index = g.meta.get("out_index")
        vl = relight.local_view(mesh.frames(), mesh.vertices, eye).to(torch.float32)
        rad_prt = relight.glossy(M, L, vl, out_index).to(torch.float64)
        prt = {"bands": bands, "bands_out": bands, "samples": samples, "psnr_db": psnr_vs_reference(ref, rad_prt, facing),
               "bytes": int(M.numel() * 4), "bytes_per_vertex": M.numel() * 4 / mesh.vertices.shape[0], "precompute_s": t_prt}
        shrms = []
        for eps in epsilons:  # SHRM: orders from ε, maps 64 x 128
            t0 = time.perf_counter()
            m = S.build_shrm(brdf, env, epsilon=eps, height=64)
            t_shrm = time.perf_counter() - t0
            with tempfile.TemporaryDirectory() as d:
                shrm_bytes = m.save(Path(d) / "m.prt").stat().st_size
            rad_shrm = m.radiance(mesh.normals, views, "map")
            pr = measure_paired(lambda: m.radiance(mesh.normals, views, "map"),
                                lambda: relight.glossy(M, L, vl, out_index), repeats=5, warmup=1)
            shrms.append({"epsilon": eps, "F_B": m.F_B, "P_B": m.P_B, "energy": m.meta["energy"],
                          "psnr_db": psnr_vs_reference(ref, rad_shrm, facing), "bytes": int(shrm_bytes),
                          "bytes_per_vertex": shrm_bytes / mesh.vertices.shape[0], "precompute_s": t_shrm,
                          "frame_s": pr.test.median, "prt_frame_s": pr.peer.median,
                          "frame_ratio_prt_over_shrm": pr.ratio.median, "trusted": bool(pr.contention.get("trusted", False)),
                          "vs_prt_psnr_db": psnr_vs_reference(rad_prt, rad_shrm, facing)})
        prt["frame_s"] = shrms[0]["prt_frame_s"]
        row = {"mesh": mesh.name, "vertices": int(mesh.vertices.shape[0]), "facing": int(facing.sum()), "shrm": shrms,
               "prt": prt}
        rows.append(row)
        print(f"  {mesh.name}: SHRM {[round(x['psnr_db'], 1) for x in shrms]} dB, PRT {prt['psnr_db']:.1f} dB", file=sys.stderr)
    res = {"quick": args.quick, "machine": machine_info(), "brdf": brdf.meta(), "light": "studio (64x128 lat-long)",
           "epsilons": list(epsilons), "rows": rows, "wall_s": time.perf_counter() - t_start}
    lines = [
        "# Convex objects: SHRM vs unshadowed glossy PRT",
        "",
        f"Microfacet σ = 0.3 (eq. 5.34) under the built-in `studio` environment (64×128 lat-long), one camera eye; "
        f"reference: per vertex, Σ over the environment's pixels of L f_r max(n·ω, 0) Ω (no SH). SHRM: orders from "
        f"ε = {' and '.join(str(e) for e in epsilons)} (eq. 5.18), 64×128 maps, radiance by map lookup. "
        f"PRT: `precompute_glossy` with {bands} light and "
        f"exit bands, {samples} directions, shadows never (a convex object has none), relit by `relight.glossy`. "
        f"CPU {res['machine'].get('cpu')}, 1 torch thread, load {res['machine'].get('load_average_1min', float('nan')):.2f}; "
        f"ran {res['wall_s']:.0f} s" + (" (--quick)" if args.quick else "") + ".",
        "",
        "| mesh | vertices (facing) | method | orders / bands | PSNR vs reference | bytes | bytes / vertex | precompute (s) "
        "| per frame (ms) |",
        "|---|---:|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        p_ = r["prt"]
        for k, s_ in enumerate(r["shrm"]):
            lines.append(f"| {r['mesh'] if k == 0 else ''} | {str(r['vertices']) + ' (' + str(r['facing']) + ')' if k == 0 else ''} | "
                         f"SHRM ε = {s_['epsilon']} | F_B={s_['F_B']}, P_B={s_['P_B']} | {s_['psnr_db']:.1f} dB | {s_['bytes']} | "
                         f"{s_['bytes_per_vertex']:.0f} | {s_['precompute_s']:.2f} | {1e3 * s_['frame_s']:.2f} |")
        lines.append(f"| | | glossy PRT | n = m = {p_['bands']} | {p_['psnr_db']:.1f} dB | {p_['bytes']} | "
                     f"{p_['bytes_per_vertex']:.0f} | {p_['precompute_s']:.2f} | {1e3 * p_['frame_s']:.2f} |")
    lines += ["", "Per-frame ratio (PRT time / SHRM time, interleaved pairs, median; ⚠ contention seen): "
              + "; ".join(f"{r['mesh']} " + ", ".join(f"ε {x['epsilon']}: {x['frame_ratio_prt_over_shrm']:.2f}×"
                                                      + ("" if x["trusted"] else " ⚠") for x in r["shrm"]) for r in rows)
              + ". SHRM vs PRT between themselves: " + "; ".join(
                  f"{r['mesh']} " + ", ".join(f"ε {x['epsilon']}: {x['vs_prt_psnr_db']:.1f} dB" for x in r["shrm"]) for r in rows)
              + ".", "",
              "The SHRM is one set of maps for any convex object under that light (its bytes do not grow with the "
              "mesh); PRT stores a matrix per vertex but relights under any light of its bands without recomputation.",
              ""]
    OUT.mkdir(parents=True, exist_ok=True)
    name = "shrm_convex_quick" if args.quick else "shrm_convex"
    atomic_write_json(OUT / f"{name}.json", res)
    atomic_write_text(OUT / f"{name}.md", "\n".join(lines))
    print(f"wrote {OUT / (name + '.md')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
