"""Positivity of the recovered light (issue 38, Ramamoorthi 2002 eq. 6.24): when does constraining
the radiance to be ≥ 0 help, when does it hurt — the measurement behind ``prt invert --positive``
being off by default — and what it costs in solve time (ratio to the unconstrained solve, same
run).

A. A smooth physical light, exactly band-limited to the fitted bands: ((1 + d·ω)/2)^(n−1) (RGB
   1 / 0.8 / 0.6), zero at −d, ≥ 0 everywhere; pixels = the model's (design × truth), float64.
B. Physical lights with detail beyond the fitted bands (a 30° cap, the built-in ``sky`` and
   ``studio``) at 8 bands through 8-band transfer, fitted at 3 and 4 bands: the truth's n-band
   projection rings below 0, and that projection is what the images determine.

Error: relative L2 of the fitted coefficients against the truth's first n² (A: the whole truth).
PSNR: re-rendered vs input pixels.

    .venv/bin/python benchmarks/bench_inverse_positive.py   # -> reports/benchmarks/inverse_positive.md
"""
from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch import inverse  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402
from prt_torch.lighting import load_light  # noqa: E402
from prt_torch.render.camera import Camera  # noqa: E402
from prt_torch.render.prt import PRTScene  # noqa: E402
from prt_torch.scene import load_scene  # noqa: E402
from prt_torch.sh.zonal import rotate_zonal, zonal_project  # noqa: E402
from prt_torch.transfer.diffuse import precompute_diffuse  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

W, FOV, VIEWS = 32, 40.0, 6
SCENES = [("convex", "never"), ("bumpy_sphere", "auto"), ("occluder_over_plane", "always")]


def design(T):
    mesh = T.mesh
    cams = [Camera.fit(mesh, azimuth=10 + k * 360.0 / VIEWS, elevation=30.0, fov=FOV) for k in range(VIEWS)]
    views = [inverse.CameraView(None, np.linalg.inv(c.view_matrix()), None, None, None, None, W, W,
                                angle_x=math.radians(FOV)).resolve(W, W) for c in cams]
    obs = inverse.observe(mesh, views, [np.zeros((W, W, 3))] * VIEWS, [np.ones((W, W), bool)] * VIEWS)
    return inverse.design_matrix(PRTScene(T), obs)


def lobe(bands):
    d = torch.tensor([0.3, 0.2, 1.0], dtype=torch.float64)
    h = zonal_project(lambda t: ((1 + t) / 2) ** (bands - 1), bands, n=64)
    return torch.tensor([1.0, 0.8, 0.6], dtype=torch.float64)[:, None] * rotate_zonal(h, d / d.norm())[None]


def rel(X, L):
    return float((X - L).norm() / L.norm())


def timed(f):
    t = time.perf_counter()
    r = f()
    return r, time.perf_counter() - t


def main() -> None:
    t0 = time.time()
    out = ROOT / "reports" / "benchmarks"
    out.mkdir(parents=True, exist_ok=True)
    A8 = {}
    for name, sh in SCENES:
        A8[name] = design(precompute_diffuse(load_scene(name), bands=8, samples=128, shadows=sh, fold_albedo=False))
    g = torch.Generator().manual_seed(0)
    rowsA, rowsB, times = [], [], []
    for name, _ in SCENES:
        for bands in (4, 6):
            A = A8[name][..., :bands * bands]
            L = lobe(bands)
            b = torch.einsum("cpn,cn->pc", A, L)
            for noise in (0.0, 0.01):
                bb = b + noise * float(b.std()) * torch.randn(b.shape, generator=g, dtype=torch.float64)
                u, tu = timed(lambda: inverse.fit_light(A, bb))
                p, tp = timed(lambda: inverse.fit_light(A, bb, positive=True))
                times.append(tp / tu)
                rowsA.append((name, bands, noise, u.report["recoverable_bands"], min(u.positivity["unconstrained"]["min_relative"]),
                              rel(u.light, L), rel(p.light, L), min(p.positivity["result"]["min_relative"]), tu, tp))
        for spec, label in [("cap:direction=0.3,0.2,1;half_angle_deg=30;intensity=3", "cap 30°"), ("sky", "sky"),
                            ("studio", "studio")]:
            L8 = load_light(spec, 8)
            b = torch.einsum("cpn,cn->pc", A8[name], L8)
            for bands in (3, 4):
                A = A8[name][..., :bands * bands]
                Lt = L8[:, :bands * bands]
                u, tu = timed(lambda: inverse.fit_light(A, b))
                p, tp = timed(lambda: inverse.fit_light(A, b, positive=True))
                times.append(tp / tu)
                rowsB.append((name, label, bands, min(inverse.negativity(Lt)["min_relative"]),
                              rel(u.light, Lt), rel(p.light, Lt), inverse.psnr(u.predicted, b), inverse.psnr(p.predicted, b)))
    info = machine_info()
    md = ["# Positivity of the recovered light (issue 38, eq. 6.24)", "",
          f"`benchmarks/bench_inverse_positive.py`; {info['cpu']}, {info['cores']} cores, {info['torch_threads']} torch threads, "
          f"load average {os.getloadavg()[0]:.1f} (the machine was shared with other jobs); torch {info['torch']}; "
          f"{time.time() - t0:.0f} s in all. {VIEWS} views {W}x{W} at 30° elevation, diffuse transfer 128 rays/vertex, "
          "pixels = design × truth in float64.", "",
          "## A. A smooth physical light, band-limited to the fitted bands: ((1 + d·ω)/2)^(n−1)", "",
          "| scene | bands | noise | recoverable bands | unconstrained min / mean abs | error unconstrained | error positive | "
          "positive min / mean abs | solve s (unc. / pos.) |",
          "|---|---|---|---|---|---|---|---|---|"]
    for r in rowsA:
        md.append(f"| `{r[0]}` | {r[1]} | {r[2]:.0%} | {r[3]} | {r[4]:.3f} | {r[5]:.2e} | **{r[6]:.2e}** | {r[7]:.1e} | "
                  f"{r[8]:.2f} / {r[9]:.2f} |")
    md += ["", "## B. Physical lights with detail beyond the fitted bands (8-band truth and transfer, fit at 3 / 4 bands)", "",
           "| scene | light | bands | truth's n-band projection min / mean abs | error unconstrained | error positive | "
           "PSNR unconstrained | PSNR positive |", "|---|---|---|---|---|---|---|---|"]
    for r in rowsB:
        md.append(f"| `{r[0]}` | {r[1]} | {r[2]} | {r[3]:.2f} | {r[4]:.3f} | {r[5]:.3f} | {r[6]:.1f} dB | {r[7]:.1f} dB |")
    md += ["", f"Solve time, positive / unconstrained (same run, 3 channels): median {float(np.median(times)):.1f}×, "
           f"max {max(times):.1f}× (the NNLS's active-set loop; the unconstrained solve is one SVD per channel plus the "
           "GCV search).", "",
           "**Reading.** Where the light is smooth and non-negative and the images filter bands away (A, `convex`: "
           "band 3 and 5 vanish for a convex Lambertian object), the unconstrained estimate dips below zero and the "
           "constraint cuts the error several-fold; where the images determine every band, both agree noise-free, and with 1% noise the "
           "constraint still helps (e.g. `bumpy_sphere` 4 bands 1.2% → 0.8%). But a real "
           "light has detail beyond any fitted band count, and its n-band projection — what the images determine — "
           "is itself negative (B: down to −1.4 × the mean |radiance|); constraining the fit to ≥ 0 then moves it away "
           "from that projection (at 3 bands on `convex` / `bumpy_sphere`, which the images determine: error 3–9% → "
           "28–44%) and lowers the re-render PSNR in every row (by 2–19 dB). Hence `--positive` is "
           "opt-in: use it when the light is known to be smooth at the fitted bands or when bands are filtered away "
           "(`recoverable_bands` shorter than `--bands`)."]
    atomic_write_text(out / "inverse_positive.md", "\n".join(md) + "\n")
    print("\n".join(md))


if __name__ == "__main__":
    main()
