"""Where an SHRM's error lives: by the angle between the view and the surface (Ramamoorthi 2002
ch. 5; issue 40's noticed "error at grazing views" and "negative radiance from ringing").

Random surface points (normal, view above the surface) under the built-in `studio` environment
(64×128 lat-long, nonnegative), each point's reflected radiance against the brute-force reference
(``shrm.reference_radiance``: Σ over the environment's pixels of L f_r max(n·ω, 0) Ω; no SH): the
relative RMS error of the SHRM's map radiance per band of n·v (within 5°, 5–15°, 15–30° and more
than 30° above grazing), for the orders ε picks (eq. 5.18) and for larger P_B at the same F_B; the
total relative squared error (what ε predicts, averaged over every view of the sphere); the
points with negative radiance and their n·v; and the same error with the radiance clamped at 0
(``SHRM.radiance(clamp=True)``, what ``prt render`` shows). Beside clamping, the alternative
against ringing: windows (``sh.window``, Lanczos σ-factors and Hanning) on ρ_lpq over l and/or p
before prefiltering, measured the same way.

Run: .venv/bin/python benchmarks/bench_shrm_grazing.py [--points N]   (about 2 minutes)
Writes reports/benchmarks/shrm_grazing.md and shrm_grazing.json.
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import torch

from prt_torch import shrm as S
from prt_torch.brdf import BlinnPhong, Microfacet
from prt_torch.harness.timing import machine_info
from prt_torch.io import atomic_write_json, atomic_write_text
from prt_torch.lighting import builtin_environment
from prt_torch.sh import window

OUT = Path(__file__).resolve().parent.parent / "reports" / "benchmarks"
#: bands of n·v: within 5°, 5–15°, 15–30°, more than 30° above grazing
BANDS = [(0.02, math.sin(math.radians(5))), (math.sin(math.radians(5)), math.sin(math.radians(15))),
         (math.sin(math.radians(15)), math.sin(math.radians(30))), (math.sin(math.radians(30)), 1.0 + 1e-9)]
WINDOWS = [("none", "none"), ("none", "lanczos"), ("lanczos", "none"), ("lanczos", "lanczos"), ("hanning", "hanning")]
CASES = [  # (BRDF, label, [None: orders from ε] or (F_B, P_B))
    (Microfacet(0.3), "microfacet σ = 0.3", [0.03, 0.01, (7, 4), (7, 6), (11, 8), (16, 8), (16, 12)]),
    (BlinnPhong(16.0), "Blinn-Phong s = 16", [0.03, 0.01, (8, 4), (12, 8)]),
]


def points(n: int, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    nn = torch.randn(n, 3, generator=g, dtype=torch.float64)
    nn = nn / nn.norm(dim=-1, keepdim=True)
    v = torch.randn(n, 3, generator=g, dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    c = (nn * v).sum(-1)
    v = torch.where((c < 0)[:, None], -v, v)
    c = c.abs()
    keep = c > BANDS[0][0]
    return nn[keep], v[keep], c[keep]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=3000)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    t_start = time.perf_counter()
    env = builtin_environment("studio", size=64)
    dirs = env.directions().reshape(-1, 3).to(torch.float64)
    Lw = env.image.reshape(-1, 3).to(torch.float64) * env.solid_angles().reshape(-1, 1).to(torch.float64)
    n, v, c = points(args.points)
    counts = [int(((c >= lo) & (c < hi)).sum()) for lo, hi in BANDS]
    results = []
    for brdf, label, settings in CASES:
        ref = S.reference_radiance(brdf, dirs, Lw, n, v)
        for st in settings:
            m = S.build_shrm(brdf, env, epsilon=st if isinstance(st, float) else None,
                             orders=None if isinstance(st, float) else st, height=64)
            rad = m.radiance(n, v, "map")
            cl = rad.clamp_min(0)

            def rel(x, sel):
                return float(((x[sel] - ref[sel]) ** 2).sum() / (ref[sel] ** 2).sum())

            every = torch.ones_like(c, dtype=torch.bool)
            neg = (rad < 0).any(-1)
            results.append({
                "brdf": label, "setting": st if isinstance(st, float) else list(st), "F_B": m.F_B, "P_B": m.P_B,
                "energy": float(m.meta["energy"]),
                "rel_rms_by_band": [math.sqrt(rel(rad, (c >= lo) & (c < hi))) for lo, hi in BANDS],
                "rel_sq": rel(rad, every), "rel_sq_clamped": rel(cl, every),
                "negative_points": int(neg.sum()), "min_radiance": float(rad.min()), "peak": float(ref.max()),
                "negative_nv_median": float(c[neg].median()) if neg.any() else None,
            })
            r = results[-1]
            print(f"  {label} {st}: ({m.F_B}, {m.P_B}) rel RMS by band "
                  + ", ".join(f"{x:.3f}" for x in r["rel_rms_by_band"]), file=sys.stderr)
    windowed = []  # windows on rho over l (F_B + 1 bands) and p (P_B + 1 bands), microfacet at eps's orders
    brdf = CASES[0][0]
    ref = S.reference_radiance(brdf, dirs, Lw, n, v)
    every = torch.ones_like(c, dtype=torch.bool)
    for eps in (0.03, 0.01):
        base = S.build_shrm(brdf, env, epsilon=eps, height=None)
        for wl, wp in WINDOWS:
            rho = base.rho * window(base.F_B + 1, wl)[:, None, None] * window(base.P_B + 1, wp)[None, :, None]
            m = S.SHRM(base.light, rho, base.F_B, base.P_B, base.axis).prefilter(64)
            rad = m.radiance(n, v, "map")
            windowed.append({"epsilon": eps, "F_B": m.F_B, "P_B": m.P_B, "window_l": wl, "window_p": wp,
                             "rel_rms_by_band": [math.sqrt(float(((rad[s_] - ref[s_]) ** 2).sum() / (ref[s_] ** 2).sum()))
                                                 for s_ in ((c >= lo) & (c < hi) for lo, hi in BANDS)],
                             "rel_sq": float(((rad - ref) ** 2).sum() / (ref ** 2).sum()),
                             "negative_points": int((rad < 0).any(-1).sum()), "min_radiance": float(rad.min())})
    machine = machine_info()
    res = {"points": int(c.numel()), "band_counts": counts, "results": results, "windowed": windowed, "machine": machine,
           "wall_s": time.perf_counter() - t_start}
    lines = [
        "# SHRM error by view angle, negative radiance and clamping", "",
        f"`benchmarks/bench_shrm_grazing.py` — {res['points']} random surface points (normal, view above the surface) under "
        "the built-in `studio` environment (64×128 lat-long); reference: Σ over its pixels of L f_r max(n·ω, 0) Ω "
        "(`shrm.reference_radiance`, no SH). SHRM: 64×128 maps, radiance by map lookup. Relative RMS error per band of the "
        f"view's elevation above the surface (points per band: {', '.join(map(str, counts))}); rel. sq. = Σ|B − ref|² / Σ ref² "
        "over all points; clamped: the same with B clamped at 0. "
        f"CPU {machine.get('cpu')}, load {machine.get('load_average_1min', float('nan')):.1f}; ran {res['wall_s']:.0f} s.", "",
        "| BRDF | ε or orders | F_B, P_B | energy kept | rel. RMS < 5° | 5–15° | 15–30° | > 30° | rel. sq. (all) "
        "| clamped | points < 0 | min (peak) | median n·v of those < 0 |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in results:
        st = f"ε = {r['setting']}" if isinstance(r["setting"], float) else f"orders {tuple(r['setting'])}"
        med = "" if r["negative_nv_median"] is None else f"{r['negative_nv_median']:.2f}"
        lines.append(f"| {r['brdf']} | {st} | {r['F_B']}, {r['P_B']} | {r['energy']:.4f} | "
                     + " | ".join(f"{x:.3f}" for x in r["rel_rms_by_band"])
                     + f" | {r['rel_sq']:.4f} | {r['rel_sq_clamped']:.4f} | {r['negative_points']} | "
                       f"{r['min_radiance']:.3f} ({r['peak']:.2f}) | {med} |")
    lines += [
        "",
        "Reading: the error is concentrated at grazing views. ε (eq. 5.18) bounds the BRDF energy lost averaged over "
        "every outgoing direction ω'o of the sphere, and the lost part sits where the horizon cuts the reparameterised "
        "lobe — near-grazing views, where ρ̂(ω'i, ω'o) changes fastest with ω'o — so a few per cent of energy is a "
        "relative error of order 1 within 5° of grazing. Raising P_B at the same F_B reduces it slowly; the total "
        "relative squared error stays near ε (the light is not band-limited, so it may exceed ε slightly). On a "
        "rendered sphere the band within 5° of the silhouette covers about sin²5° ≈ 0.8% of the disc's area "
        "(orthographic view), the band within 15° about 6.7%. Negative radiance: the truncated series rings below 0 "
        "where the true radiance is small; clamping at 0 (what `prt render` does by default, `--no-clamp` keeps the "
        "series) can only move a value towards a nonnegative truth and lowers the error a little.",
        "",
        "## Windows instead of clamping", "",
        "Microfacet σ = 0.3 at the orders ε picks; ρ_lpq multiplied by `sh.window` over l (F_B + 1 bands) and over p "
        "(P_B + 1 bands) before the frequency-space prefilter, the same points and reference.", "",
        "| ε (orders) | window in l | window in p | rel. RMS < 5° | 5–15° | 15–30° | > 30° | rel. sq. (all) | points < 0 "
        "| min |",
        "|---|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for w in windowed:
        lines.append(f"| {w['epsilon']} ({w['F_B']}, {w['P_B']}) | {w['window_l']} | {w['window_p']} | "
                     + " | ".join(f"{x:.3f}" for x in w["rel_rms_by_band"])
                     + f" | {w['rel_sq']:.4f} | {w['negative_points']} | {w['min_radiance']:.3f} |")
    lines += [
        "",
        "Windows remove the ringing (Lanczos in both l and p: almost no negative points) but blur the lobe: the "
        "total error grows two- to threefold; only a window in l alone lowers the error within 5° of grazing (1.04 to 0.85 "
        "at ε = 0.03), at the cost of more than doubling it above 30°, and a window in p makes grazing worse. "
        "Clamping keeps the series' accuracy and removes every negative value, so `prt render` clamps and "
        "no window is offered.",
        "",
    ]
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_json(OUT / "shrm_grazing.json", res)
    atomic_write_text(OUT / "shrm_grazing.md", "\n".join(lines))
    print(f"wrote {OUT / 'shrm_grazing.md'}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
