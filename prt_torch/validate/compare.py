"""What the diffuse and the glossy comparison share (docs/validate.md): the sampled vertices, the
engine/Mitsuba ratio of luminance summed over them with its 1σ noise (Mitsuba's per-vertex errors
independent, the engine's measured on its summed error where replica seeds give it), the rms
relative difference, and the report as text.
"""
from __future__ import annotations

import math
from typing import Any

import torch

from .._checks import check_int
from ..scene import Mesh

__all__ = ["LUMA", "sample_vertices", "ratio", "rms_rel", "class_lines", "format_report"]

#: Rec. 709 luminance weights of an RGB radiance
LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


def sample_vertices(mesh: Mesh, n: int, seed: int = 0) -> torch.Tensor:
    """``n`` distinct vertex indices (sorted), uniformly at random with ``seed``."""
    n = check_int("vertices", n, 1)
    g = torch.Generator().manual_seed(int(seed) + 104729)
    return torch.randperm(mesh.num_vertices, generator=g)[: min(n, mesh.num_vertices)].sort().values


def ratio(e: torch.Tensor, e_se: torch.Tensor, m: torch.Tensor, m_se: torch.Tensor, e_sum_se: float | None = None) -> dict[str, float]:
    """Engine/Mitsuba ratio of sums (luminance over the vertices) with its 1σ noise: Mitsuba's
    per-vertex errors are independent (quadrature); the engine's sum error is ``e_sum_se`` when
    measured (replica seeds), else the quadrature of ``e_se``."""
    lum = lambda x: x @ LUMA  # noqa: E731
    lum_se = lambda x: ((x ** 2) @ (LUMA ** 2)).sqrt()  # noqa: E731
    E, M = float(lum(e).sum()), float(lum(m).sum())
    sE = float(lum_se(e_se).pow(2).sum().sqrt()) if e_sum_se is None else float(e_sum_se)
    sM = float(lum_se(m_se).pow(2).sum().sqrt())
    if M <= 0:
        return {"engine": E, "mitsuba": M, "ratio": float("nan"), "ratio_se": float("nan"), "engine_se": sE, "mitsuba_se": sM}
    r = E / M
    rse = abs(r) * math.sqrt((sE / E) ** 2 + (sM / M) ** 2) if E != 0 else sE / M
    return {"engine": E, "mitsuba": M, "ratio": r, "ratio_se": rse, "engine_se": sE, "mitsuba_se": sM,
            "z": (r - 1.0) / rse if rse > 0 else float("inf")}


def rms_rel(e: torch.Tensor, m: torch.Tensor) -> float:
    lum_e, lum_m = e @ LUMA, m @ LUMA
    return float(((lum_e - lum_m).pow(2).mean().sqrt()) / lum_m.abs().mean().clamp_min(1e-300))


def class_lines(rep: dict[str, Any]) -> list[str]:
    """The report's per-class lines (``rep['classes']``, :func:`prt_torch.validate.diffuse.class_report`):
    the mesh's hard features counted, then each vertex class's count and its direct and
    interreflected engine/Mitsuba ratios ± 1σ."""
    if "classes" not in rep:
        return []
    f = rep.get("mesh_features", {})
    out = [f"  mesh: {f.get('boundary_edges', 0)} boundary edges, {f.get('nonmanifold_edges', 0)} non-manifold edges; "
           "vertex classes (in the mesh / compared):"]
    for name, c in rep["classes"].items():
        s = f"    {name:<12} {c['mesh']:>6} / {c['sampled']:<4}"
        for part in ("direct", "inter"):
            if part in c:
                r = c[part]
                s += (f"  {part} {r['ratio']:.4f} ± {r['ratio_se']:.4f}" if math.isfinite(r["ratio"])
                      else f"  {part} — (Mitsuba's sum {r['mitsuba']:.3g})")
        out.append(s)
    return out


def format_report(rep: dict[str, Any]) -> str:
    """A few lines of text: each part's engine/Mitsuba ratio with its noise."""
    def line(label: str, r: dict) -> str:
        return (f"  {label:<22} engine/mitsuba = {r['ratio']:.4f} ± {r['ratio_se']:.4f} (1σ)   "
                f"engine {r['engine']:.5g} ± {r['engine_se']:.2g}, mitsuba {r['mitsuba']:.5g} ± {r['mitsuba_se']:.2g}")

    if rep.get("kind") == "glossy":
        b = rep["brdf"] or {}
        bs = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in b.items() if k != "model")
        return "\n".join([
            f"{rep['scene']}: {rep['vertices']} vertices, glossy {b.get('model')}({bs}), {rep['bands']}->{rep['bands_out']} bands "
            f"({rep['projection']}), views within {rep['view_deg']:g}° of the normal, light {rep['light']}, Mitsuba {rep['spp']} spp, "
            f"engine {rep['samples']} directions, no scale fit",
            line("direct (SH transfer)", rep["direct"]) + f"   rms rel {rep['direct_rms_rel']:.4f}",
            line("BRDF unprojected", rep["direct_unprojected"]),
            f"  {'SH truncation bias':<22} {rep['sh_truncation']:+.4f} of Mitsuba (direct; engine's rays, dense set of {rep['dense']})"]
            + ([line("interreflected", rep["inter"]), line("total", rep["total"])] if "inter" in rep else []))
    out = [f"{rep['scene']}: {rep['vertices']} vertices ({rep['sharp_vertices']} sharp ≥ {rep['sharp_deg']:g}°), "
           f"bounces {rep['bounces']}, light {rep['light']} ({rep['light_source']}), Mitsuba {rep['spp']} spp, "
           f"engine {rep['samples']} directions, no scale fit"]
    if rep.get("direct") is not None:  # a wavelet transfer with bounces is compared in total only
        out.append(line("direct", rep["direct"]) + f"   rms rel {rep['direct_rms_rel']:.4f}")
    for k, label in (("inter", "interreflected"), ("inter_sharp", "interreflected, sharp"), ("inter_smooth", "interreflected, rest")):
        if k in rep:
            out.append(line(label, rep[k]))
    out.append(line("total", rep["total"]))
    out += class_lines(rep)
    if "codec" in rep:
        out.append(line("codec total", rep["codec"]["total"]))
        if "inter" in rep["codec"]:
            out.append(line("codec interreflected", rep["codec"]["inter"]))
    if "sh_truncation" in rep:
        out.append(line("SH light / image light", rep["sh_truncation"]))
    return "\n".join(out)
