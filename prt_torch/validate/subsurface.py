"""The subsurface transfer (dipole + hierarchy, :mod:`prt_torch.transfer.subsurface`) against
Mitsuba 3's volumetric path tracer (issue 41).

Scene: a sphere of radius ``radius`` mm holding a homogeneous medium (σ_a, σ_s = σ'_s with the
isotropic phase function, so σ'_s = σ_s) inside a smooth dielectric boundary of relative index
η, under an SH-band-limited environment (Mitsuba ``envmap`` from :func:`lights.light_image`),
path traced by ``volpath`` (no depth limit, Russian roulette: unbiased). Multiple *and* single
scattering and the exact directional Fresnel terms are in Mitsuba; the dipole has multiple
scattering only, view-independent Fresnel (F_dt) and a Euclidean R_d over a curved surface: the
ratio measures the approximation's known error (Jensen 2001 §4 reports the dipole within ~10-20%
of Monte Carlo for α' near 1).

What is compared: the projected integral of exit radiance seen by an orthographic camera from
direction d, I(d) = ∫ L_o(x, d) max(n·d, 0) dA (image sum × pixel area). Mitsuba's surface
reflection of the environment is removed by rendering the same sphere with an absorbing interior
(σ_s = 0, σ_a = 10³ mm⁻¹: nothing transmitted comes back) and subtracting. The engine's I(d) is
Σ_v A_v L_v max(n_v·d, 0) over its vertices (L_v = data[v] · l).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from .._checks import check_float, check_int
from ..scene import geodesic_sphere, make_mesh
from ..transfer.subsurface import Material, material_from_spec, vertex_areas
from ..transfer.subsurface_kind import precompute_subsurface
from .lights import check_expressible
from .scenes import require_mitsuba

__all__ = ["mitsuba_sphere_views", "engine_sphere_views", "compare_sphere"]


def _ortho(mi, d: np.ndarray, half: float, res: int, spp: int, seed: int) -> dict:
    up = (0.0, 1.0, 0.0) if abs(d[1]) < 0.9 else (1.0, 0.0, 0.0)
    eye = d * (4 * half)
    T = mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(*eye), target=mi.ScalarPoint3f(0, 0, 0), up=mi.ScalarVector3f(*up))
    return {"type": "orthographic", "to_world": T @ mi.ScalarTransform4f().scale(mi.ScalarVector3f(half, half, 1.0)),
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
            "sampler": {"type": "independent", "sample_count": int(spp), "seed": int(seed)}}


def mitsuba_sphere_views(radius: float, material: Material, light: torch.Tensor, views: np.ndarray, res: int = 32,
                         spp: int = 32, seed: int = 0) -> np.ndarray:
    """``[J, 3]`` float64: Mitsuba's I(d) (module docstring) for ``views [J, 3]`` unit directions,
    the subsurface part (the absorbing sphere's render subtracted)."""
    mi = require_mitsuba()
    img = check_expressible(light, "light")
    half = 1.05 * radius
    m = material

    def medium(absorbing: bool) -> dict:
        if absorbing:
            return {"type": "homogeneous", "sigma_t": 1.0, "scale": 1e3, "albedo": 0.0}
        st = [a + s for a, s in zip(m.sigma_a, m.sigma_s)]
        if max(st) - min(st) > 1e-12:  # a grey medium here (RGB σ_t would need a volume texture)
            raise ValueError(f"material {m.name!r}: the Mitsuba sphere takes a grey medium (equal σ_a + σ'_s in R, G, B); "
                             f"got σ_t = {st}")
        return {"type": "homogeneous", "sigma_t": 1.0, "scale": float(st[0]),
                "albedo": {"type": "rgb", "value": [s / t for s, t in zip(m.sigma_s, st)]}, "phase": {"type": "isotropic"}}

    out = np.zeros((len(views), 3))
    pix = (2 * half / res) ** 2
    for absorbing, sign in ((False, 1.0), (True, -1.0)):
        for j, d in enumerate(np.asarray(views, np.float64)):
            scene = mi.load_dict({
                "type": "scene", "integrator": {"type": "volpath", "max_depth": -1},
                "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(img, np.float32))},
                "ball": {"type": "sphere", "center": [0, 0, 0], "radius": float(radius), "interior": medium(absorbing),
                         "bsdf": {"type": "dielectric", "int_ior": float(m.eta), "ext_ior": 1.0}},
                "sensor": _ortho(mi, d / np.linalg.norm(d), half, res, spp, seed + j)})
            im = np.asarray(mi.render(scene, spp=int(spp), seed=int(seed + 7 * j + (100 if absorbing else 0))), np.float64)
            # the environment behind the sphere is the same in both renders: it cancels in the difference
            out[j] += sign * im.reshape(-1, 3).sum(0) * pix
    return out


def engine_sphere_views(radius: float, material: Material, light: torch.Tensor, views: np.ndarray, subdiv: int = 24,
                        **kw: Any) -> tuple[np.ndarray, dict]:
    """The engine's I(d) ``[J, 3]`` for the same sphere (a geodesic mesh of ``subdiv``, in mm:
    scale 1) and its transfer's meta."""
    v, f = geodesic_sphere(subdiv)
    mesh = make_mesh(np.asarray(v) * radius, f, name="sss_sphere")
    n2 = int(light.shape[-1])
    tr = precompute_subsurface(mesh, material, scale=1.0, bands=int(round(math.sqrt(n2))), shadows="never", **kw)
    L = (tr.data.double() * light.double().reshape(1, 1, -1)).sum(-1)  # [V, 3]
    A = vertex_areas(mesh)
    nrm = mesh.normals.double()
    d = torch.as_tensor(np.asarray(views, np.float64))
    w = (nrm @ (d / d.norm(dim=1, keepdim=True)).T).clamp_min(0) * A[:, None]  # [V, J]
    return (w.T @ L).numpy(), tr.meta


def compare_sphere(material: Any = None, radius: float = 20.0, light: torch.Tensor | None = None, res: int = 32,
                   spp: int = 32, seed: int = 0) -> dict:
    """Engine / Mitsuba ratios of I(d) from above (+z), the side (+x) and below (−z) under
    ``light`` (default: radiance 1 + 0.8 z, 2 bands: brighter above). ``material`` default: σ_a
    = 0.05, σ'_s = 1.0 mm⁻¹ (α' = 0.95, mean free path 0.95 mm), η = 1.3 in a 20 mm sphere.
    Returns ``{'views', 'engine', 'mitsuba', 'ratio' [J, 3], 'material'}``."""
    m = Material((0.05,) * 3, (1.0,) * 3, 1.3, name="test_medium") if material is None else material_from_spec(material)
    radius = check_float("radius", radius, 0.0, None, lo_open=True)
    check_int("res", res, 4)
    check_int("spp", spp, 1)
    if light is None:
        light = torch.zeros(1, 4, dtype=torch.float64)
        light[0, 0] = 2 * math.sqrt(math.pi)
        light[0, 2] = 0.8 * math.sqrt(4 * math.pi / 3)
    views = np.array([[0, 0, 1.0], [1.0, 0, 0], [0, 0, -1.0]])
    eng, _ = engine_sphere_views(radius, m, light, views)
    mit = mitsuba_sphere_views(radius, m, light, views, res=res, spp=spp, seed=seed)
    return {"views": views.tolist(), "engine": eng, "mitsuba": mit, "ratio": eng / mit, "material": m.describe()}
