"""BRDF fits beyond Phong (issue 38, Ramamoorthi 2002 §6.4.2): accuracy of the per-pixel hemisphere
rule of ``inverse.brdf_fit.slice_model`` (uniform azimuths vs azimuths graded towards the mirror
azimuth) against a 120 000-direction brute-force quadrature of the BRDF formulas written out in
``tests/test_inverse_brdf.py`` (numpy, world directions), for Ashikhmin–Shirley n = 60 and the
microfacet σ = 0.2 of eq. 5.34, on ``convex`` (4 views, 100 pixels, the 8-band cap + sky light of
the tests).

    .venv/bin/python benchmarks/bench_inverse_brdf.py      # -> reports/benchmarks/inverse_brdf.md
"""
from __future__ import annotations

import os
import platform
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

import test_inverse_brdf as T  # noqa: E402  (the independent brute force and formulas of the tests)

from prt_torch.brdf import AshikhminShirley, Lambertian, Microfacet  # noqa: E402
from prt_torch.inverse import brdf_fit  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402


def main() -> None:
    mesh = T.load_scene("convex")
    L = T._light()
    obs = T._observe(mesh, n_views=4, W=24, max_pixels=100)
    cases = [("ashikhmin-shirley n=60, rs=0.3", T._ashikhmin_shirley(60.0, 60.0, 0.3, 0.0),
              lambda sm: sm.render(AshikhminShirley(nu=60.0, rs=0.3, rd=0.0))),
             ("microfacet sigma=0.2 + kd 0.5", T._microfacet(0.5, 1.0, 0.2),
              lambda sm: sm.render(Microfacet(0.2, 1.0)) + 0.5 * sm.render(Lambertian(1.0)))]
    rows = []
    for name, ref_f, model in cases:
        ref = T._brute_force(mesh, obs, L, ref_f, n_dirs=120000)
        for Lq in (8, 12, 16, 24):
            for grade in (0.0, 0.9):
                sm = brdf_fit.slice_model(mesh, obs, L, visibility=False, quad_bands=Lq, grade=grade)
                m = model(sm)
                e = (m - ref).norm(dim=1) / ref.norm(dim=1)
                rows.append((name, Lq, int(sm.wi.shape[1]), "graded 0.9" if grade else "uniform",
                             float((m - ref).norm() / ref.norm()), float(e.max()), float(sm.wo[int(e.argmax()), 2])))
    cpu = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), platform.processor())
    out = ["# BRDF fit rule accuracy (`benchmarks/bench_inverse_brdf.py`)\n",
           f"CPU: {cpu}; load average {os.getloadavg()[0]:.1f} (shared machine). Model (engine classes on the per-pixel rule) "
           "vs brute force (120 000 Fibonacci world directions, the tests' numpy formulas; its own error ~6e-5).\n",
           "| BRDF | L | directions per pixel | azimuths | rel. error (all pixels) | worst pixel | its z_o |",
           "|---|---|---|---|---|---|---|"]
    out += [f"| {a} | {b} | {c} | {d} | {e:.2e} | {f:.2e} | {g:.3f} |" for a, b, c, d, e, f, g in rows]
    dst = ROOT / "reports" / "benchmarks" / "inverse_brdf.md"
    atomic_write_text(dst, "\n".join(out) + "\n")
    print("\n".join(out))


if __name__ == "__main__":
    main()
