"""Inverse lighting against Mitsuba 3 (issue 38): the light recovered from Mitsuba's images of
known geometry, per scene / views / image size / spp / silhouette mask / bounces, with the
well-posedness report's largest error gain and s_min/s_max (docs/inverse.md, "Against Mitsuba 3").

Images: ``validate.scenes.mitsuba_views`` (one-sided Lambertian, albedo 0.8, the light as an
``envmap`` hidden from the camera so alpha is coverage, box filter), pixels not wholly on the mesh
masked unless a row says otherwise; inverted through ``inverse.observe`` / ``design_matrix`` /
``fit_light`` (the path ``prt invert --unknown light`` takes) with a diffuse transfer of 1024 rays
per vertex. Light: ``studio`` at 3 bands lifted by a constant to be non-negative. Error: relative
L2 over the 27 coefficients.

    .venv/bin/python benchmarks/bench_inverse_mitsuba.py    # -> reports/benchmarks/inverse_mitsuba.md
"""
from __future__ import annotations

import math
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch import inverse  # noqa: E402
from prt_torch.lighting import load_light  # noqa: E402
from prt_torch.render.camera import Camera  # noqa: E402
from prt_torch.render.prt import PRTScene  # noqa: E402
from prt_torch.scene import load_scene  # noqa: E402
from prt_torch.transfer.diffuse import precompute_diffuse  # noqa: E402
from prt_torch.validate.lights import check_expressible, light_image  # noqa: E402
from prt_torch.validate.scenes import mitsuba_views  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

FOV = 40.0
ALBEDO = 0.8


def lifted_studio() -> torch.Tensor:
    L = load_light("studio", 3).clone()
    L[:, 0] += 1.25 * max(0.0, -float(light_image(L, 64).min())) / (0.5 / math.sqrt(math.pi))
    return L


def cameras(mesh, layout: str, W: int):
    if layout == "cube":
        cams = [Camera.fit(mesh, azimuth=45 + 90 * k, elevation=e, fov=FOV) for e in (35.26, -35.26) for k in range(4)]
    else:  # 'above': 8 views from 60° elevation
        cams = [Camera.fit(mesh, azimuth=10 + 45 * k, elevation=60, fov=FOV) for k in range(8)]
    return [inverse.CameraView(None, np.linalg.inv(c.view_matrix()), None, None, None, None, W, W,
                               angle_x=math.radians(FOV)).resolve(W, W) for c in cams]


def row(scene: str, layout: str, W: int, spp: int, bounces: int = 0, model_bounces: int | None = None,
        silhouettes: bool = False, face_normals: bool = False) -> dict:
    mesh = load_scene(scene, albedo=[ALBEDO] * 3)
    L = lifted_studio()
    mb = bounces if model_bounces is None else model_bounces
    T = precompute_diffuse(mesh, bands=3, samples=1024, shadows="always", fold_albedo=False, bounces=mb)
    views = cameras(mesh, layout, W)
    t0 = time.perf_counter()
    ims = mitsuba_views(mesh, views, check_expressible(L, "studio+", 64), spp=spp, max_depth=2 + bounces, seed=0,
                        face_normals=face_normals)
    t_mi = time.perf_counter() - t0
    masks = [np.ones(im.shape[:2], bool) if silhouettes else im[..., 3] > 0.999 for im in ims]
    obs = inverse.observe(mesh, views, [im[..., :3].astype(np.float64) for im in ims], masks)
    A = inverse.design_matrix(PRTScene(T), obs)
    fit = inverse.fit_light(A, obs.values)
    model = torch.einsum("cpn,cn->pc", A, L)
    err = fit.light - L
    _, s, Vh = torch.linalg.svd(A[0], full_matrices=False)
    return {"scene": scene, "layout": layout, "W": W, "spp": spp, "bounces": bounces, "model_bounces": mb,
            "mask": "silhouettes kept" if silhouettes else "coverage > 0.999", "normals": "face" if face_normals else "smooth",
            "pixels": obs.P, "error": float(err.norm() / L.norm()),
            "per_channel": [float(err[c].norm() / L[c].norm()) for c in range(3)],
            "sum_ratio": float(obs.values.sum() / model.sum()),
            "gain": max(b["gain"] for b in fit.report["bands"]), "smin": float(s[-1] / s[0]),
            "on_weakest": float((err @ Vh[-1]).norm() / err.norm()), "mitsuba_s": t_mi}


ROWS = [dict(scene="bumpy_sphere", layout="cube", W=48, spp=64),
        dict(scene="bumpy_sphere", layout="cube", W=48, spp=128),
        dict(scene="bumpy_sphere", layout="cube", W=32, spp=32),
        dict(scene="bumpy_sphere", layout="cube", W=48, spp=64, silhouettes=True),
        dict(scene="bumpy_sphere", layout="cube", W=48, spp=64, bounces=2),
        dict(scene="bumpy_sphere", layout="cube", W=48, spp=64, bounces=2, model_bounces=0),
        dict(scene="sphere_on_plane", layout="above", W=64, spp=64, face_normals=True),
        dict(scene="sphere_on_plane", layout="above", W=64, spp=512, face_normals=True),
        dict(scene="sphere_on_plane", layout="above", W=64, spp=64, face_normals=True, silhouettes=True)]


def main() -> None:
    t0 = time.perf_counter()
    rows = [row(**r) for r in ROWS]
    cpu = subprocess.run(["lscpu"], capture_output=True, text=True).stdout
    cpu = next((ln.split(":", 1)[1].strip() for ln in cpu.splitlines() if ln.startswith("Model name")), platform.processor())
    import mitsuba as mi

    md = ["# Inverse lighting against Mitsuba 3 (issue 38)", "",
          f"`benchmarks/bench_inverse_mitsuba.py`; {cpu}, {os.cpu_count()} cores, load average "
          f"{' / '.join(f'{x:.1f}' for x in os.getloadavg())} (shared with other jobs when > {os.cpu_count()}); "
          f"Mitsuba {mi.__version__} `scalar_rgb`; torch {torch.__version__}; {time.perf_counter() - t0:.0f} s in all.", "",
          (__doc__ or "").split("\n\n")[1].replace("\n", " "), "",
          "`cube`: 8 views from the corners of a cube around the mesh; `above`: 8 views from 60° elevation. "
          "`on weakest`: the share of the light error along the design's weakest singular direction "
          "(light from below for sphere_on_plane). `sum ratio`: Mitsuba / model pixel sum.", "",
          "| scene | views | size | spp | bounces (images / model) | mask | normals | pixels | error | per channel | sum ratio "
          "| max gain | s_min/s_max | on weakest |", "|" + "---|" * 14]
    for r in rows:
        md.append(f"| {r['scene']} | {r['layout']} | {r['W']}×{r['W']} | {r['spp']} | {r['bounces']} / {r['model_bounces']} | "
                  f"{r['mask']} | {r['normals']} | {r['pixels']} | {r['error']:.4f} | "
                  f"{' / '.join(f'{x:.4f}' for x in r['per_channel'])} | {r['sum_ratio']:.4f} | {r['gain']:.3g} | "
                  f"{r['smin']:.4f} | {r['on_weakest']:.3f} |")
    out = ROOT / "reports" / "benchmarks"
    out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(out / "inverse_mitsuba.md", "\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
