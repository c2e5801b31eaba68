"""Tabulated transport functions T_{x,ω_o}(ω_i) on cube maps (Green 2005, §1.2 eq. 1.2 and §2.2.1).

For a vertex x, a global view direction ω_o and a light direction ω_i (all pointing away from
the surface), direct glossy transport with visibility is

    T_{x,ω_o}(ω_i) = f_r(ω_i, ω_o) V_x(ω_i) max(n_x·ω_i, 0)                 (Green eq. 1.2)

and exit radiance is L_o(x, ω_o) = ∫ T_{x,ω_o}(ω_i) L_i(ω_i) dω_i (eq. 1.1), here the sum over
cube-map texels of T · L · Δω. Green tabulates T for the 92 views of a subdivided icosahedron
(frequency 3: 10·3² + 2 = 92) on small cube maps (e.g. 6×8×8) per vertex. At 50k vertices,
92 views and 6×8×8 texels this is 7 GB in float32, so the table is **streamed** to a directory:

    <out>/manifest.json        kind "transfer/transport", meta (views, res, brdf, chunks, ...)
    <out>/views.prt            the view directions [J, 3] and texel solid angles [6, r, r]
    <out>/mesh.prt             the mesh arrays (as Transfer.save stores them)
    <out>/chunk_000000.prt ... data [k, J, 6, r, r] (float32 or float16) for vertices start..stop-1,
                               and visibility [k, ⌈6r²/8⌉] uint8: each texel's V_p as packed bits (issue 42 §2;
                               :func:`pack_visibility`; absent in tables written before — :func:`texel_visibility`)

Chunks are written atomically and skipped when present, so an interrupted run resumes.
T is zero for views below the vertex's tangent plane (cos θ_o ≤ :data:`HORIZON_EPS`: a view lying in it, where
Ward's 1/√cos θ_o diverges, counts as below) and for occluded or below-horizon texels.
Where the BRDF's lobe is narrower than the texels (grazing views of a half-vector lobe, near the
mirror direction) a texel holds T's average over the texel instead of its centre value, so that
Σ_p T Δω stays the integral a relighting needs (:func:`supersample_plan`, issue 42 §2; the default
``supersample='auto'``, 1 for centre values everywhere).

Cube-map convention (OpenGL order +x, -x, +y, -y, +z, -z; texel (row t, column s) centre at
sc = 2(s+½)/r - 1, tc = 2(t+½)/r - 1):
+x: (1, -tc, -sc)  -x: (-1, -tc, sc)  +y: (sc, 1, tc)  -y: (sc, -1, -tc)  +z: (sc, -tc, 1)  -z: (-sc, -tc, -1).
Texel solid angles are exact (the cube-face area integral, Σ = 4π).
"""
from __future__ import annotations

import collections
import json
import math
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any, Iterator

import torch

from .. import io
from .._checks import check_choice, check_int, describe
from ..brdf import BRDF, AshikhminShirley
from ..executor import LocalExecutor, TaskFailure, torch_threads
from ..scene import Mesh, RayCaster
from .base import RunOptions
from . import transport_kernels
from .glossy import check_frames, decide_shadows

__all__ = ["check_disk_space", "pack_visibility", "unpack_visibility", "texel_visibility",
    "choose_cube_res", "lobe_width", "texel_spacing", "supersample_plan", "sub_texel_sets", "view_sub",
    "icosphere_directions",
    "cube_directions",
    "precompute_transport",
    "TransportTable",
    "transport_radiance",
    "MAX_CUBE_RES",
    "HORIZON_EPS",
]

MAX_CUBE_RES = 64
#: a view with cos θ_o = n·ω_o ≤ HORIZON_EPS counts as below the vertex's tangent plane: its transport function
#: is zero (Green 2005 eq. 1.2 has f_r(ω_i, ω_o) = 0 below it). Ward's 1/√(cos θ_i cos θ_o) (Ward 1992's anisotropic
#: Gaussian, brdf.Ward) diverges at the horizon, and a view lying exactly in a tangent plane (geodesic meshes with icosphere views:
#: systematic) comes out of the float64 frame rotation at |cos θ_o| ~ 1e-17 .. 1e-15 with either sign, where the
#: table held ~1e7 (e.g. 5.9e6 at 1.1e-16). 1e-9 is six orders above that rounding noise and ~5.7e-8 degrees above
#: the horizon, where a surface's projected area (∝ cos θ_o) leaves nothing to see; Ward's factor there is at most
#: 3.2e4 times its normal-view value. The compiled pass (``kernels/transport.c``), the harness's exact reference
#: and its view taps use this same constant; it is in a table's fingerprint.
HORIZON_EPS = 1e-9
#: torch threads in a transport chunk's own work (the BRDF on the pairs): the other core runs the
#: ray-casting workers (measured in reports/benchmarks/kinds.md); the texel averages, cast no ray, use all (``average_threads``)
CHUNK_THREADS = 1


def icosphere_directions(frequency: int = 3) -> torch.Tensor:
    """Vertices of a geodesic icosphere of the given frequency, ``[10 f² + 2, 3]`` float64 unit
    vectors (f = 3: Green's 92 view directions)."""
    from ..scene import geodesic_sphere

    frequency = check_int("frequency", frequency, 1, 64)
    v, _ = geodesic_sphere(frequency)
    v = torch.from_numpy(v).to(torch.float64)
    return v / v.norm(dim=-1, keepdim=True)


def cube_directions(res: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Texel-centre directions ``[6, r, r, 3]`` and exact solid angles ``[6, r, r]`` (float64)
    of a cube map in the module's convention."""
    return _cube_directions(check_int("res", res, 1, MAX_CUBE_RES))


def _cube_directions(res: int) -> tuple[torch.Tensor, torch.Tensor]:
    """:func:`cube_directions` without the bound on ``res`` (sub-texels and references)."""
    c = (torch.arange(res, dtype=torch.float64) + 0.5) * (2.0 / res) - 1.0
    tc, sc = torch.meshgrid(c, c, indexing="ij")  # rows t, columns s
    one = torch.ones_like(sc)
    faces = [
        (one, -tc, -sc), (-one, -tc, sc), (sc, one, tc), (sc, -one, -tc), (sc, -tc, one), (-sc, -tc, -one),
    ]
    d = torch.stack([torch.stack(f, -1) for f in faces])
    d = d / d.norm(dim=-1, keepdim=True)
    e = torch.linspace(-1.0, 1.0, res + 1, dtype=torch.float64)
    x0, x1 = e[:-1][None, :], e[1:][None, :]
    y0, y1 = e[:-1][:, None], e[1:][:, None]
    area = lambda x, y: torch.atan2(x * y, torch.sqrt(x * x + y * y + 1.0))  # noqa: E731
    sa = area(x1, y1) - area(x0, y1) - area(x1, y0) + area(x0, y0)  # [r, r]
    return d, sa[None].expand(6, res, res).clone()


#: ``res: auto`` (the default): the narrowest lobe's ±σ spans at least this many texel spacings
AUTO_TEXELS_PER_LOBE = 2.0
#: ``res: auto``: half-vector lobes are taken at this view angle from the normal (their width across
#: the plane of incidence shrinks by cos θ_o towards grazing; views beyond it keep narrower lobes)
AUTO_GRAZING_DEG = 60.0
#: the range ``res: auto`` chooses from (below: Green's 6×8×8 indirect tables are already coarse;
#: above: 10k vertices × 92 views would be tens of GB)
AUTO_MIN_RES, AUTO_MAX_RES = 8, 32


def texel_spacing(res: int) -> float:
    """h(r) = √(largest texel solid angle) of a 6×r×r cube map (≈ 2/r rad, at a face centre): the
    spacing the Gaussian fit's narrowest lobe is measured in (``codecs.gaussian.resolvable_sigma``
    = 0.35 h)."""
    return math.sqrt(float(cube_directions(res)[1].max()))


def lobe_width(brdf: BRDF | None) -> tuple[float, str]:
    """The angular standard deviation σ (radians) of the narrowest lobe of ``brdf``'s transport
    functions T(ω_i) = f_r V max(n·ω_i, 0) over the light direction, and a one-line reason.

    A lobe of equivalent Phong exponent s (``BRDF.sharpness``: cos^s θ ≈ exp(−sθ²/2)) has
    σ = 1/√s about its axis: Phong s → 1/√s; Blinn-Phong and Ashikhmin–Shirley exponent N
    (sharpness N/4) → 2/√N; Ramamoorthi's microfacet roughness σ_m (sharpness 1/(2σ_m²)) → √2 σ_m.
    A lobe about the half vector h (``BRDF.lobe_axis == 'half'``) maps to the light direction
    with dω_i = 4 (ω_o·h) dω_h, so across the plane of incidence it narrows by ω_o·h = cos θ_o
    in the mirror configuration: it is taken at θ_o = :data:`AUTO_GRAZING_DEG`. A model without a
    lobe (sharpness 0: Lambertian) has only the clamped cosine, σ = ∞."""
    from ..brdf import AshikhminShirley

    brdf = AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0) if brdf is None else brdf
    s = float(brdf.sharpness)
    if s <= 0:
        return math.inf, f"{brdf.name}: no lobe (only the clamped cosine)"
    sigma = 1.0 / math.sqrt(s)
    why = f"{brdf.name}: equivalent Phong exponent {s:g}, lobe sigma = 1/sqrt(s) = {sigma:.3f} rad"
    if getattr(brdf, "lobe_axis", "half") == "half":
        c = math.cos(math.radians(AUTO_GRAZING_DEG))
        sigma *= c
        why += (f" about the half vector, x cos({AUTO_GRAZING_DEG:g} deg) = {sigma:.3f} rad across the plane of incidence "
                f"at a view {AUTO_GRAZING_DEG:g} deg from the normal")
    return sigma, why


def choose_cube_res(brdf: BRDF | None, texels: float = AUTO_TEXELS_PER_LOBE, min_res: int = AUTO_MIN_RES,
                    max_res: int = AUTO_MAX_RES) -> tuple[int, dict[str, Any]]:
    """``res: auto``: the smallest cube face resolution r in [min_res, max_res] at which the
    narrowest lobe of ``brdf`` (:func:`lobe_width`, σ) spans ``texels`` texel spacings over ±σ,
    2σ ≥ texels · h(r) (:func:`texel_spacing`) — Green 2005 §2.2.1 tabulates direct glossy
    transport on finer cube maps than the 6×8×8 of smooth indirect terms for this reason, and the
    Gaussian fit cannot place a lobe narrower than 0.35 h. Returns (r, decision) with the decision
    ``{'value', 'lobe_sigma', 'texel_spacing', 'texels_per_lobe', 'reason'}`` (what the manifest's
    ``auto.res`` records); ``max_res`` with the reason when even that is short."""
    texels = float(texels)
    if not texels > 0:
        raise ValueError(f"texels={texels!r}; accepted: a positive number of texel spacings per lobe")
    sigma, why = lobe_width(brdf)
    r = int(min_res)
    while r < max_res and 2 * sigma < texels * texel_spacing(r):
        r += 1
    h = texel_spacing(r)
    ok = 2 * sigma >= texels * h
    reason = (f"smallest r in [{min_res}, {max_res}] where the narrowest lobe's 2 sigma spans >= {texels:g} texel spacings "
              f"h(r) = sqrt(largest texel solid angle) ({why}): 2 sigma / h = {2 * sigma / h:.2f} at r = {r}"
              if ok else
              f"r = {max_res}, the largest res: auto chooses, where the narrowest lobe's 2 sigma spans {2 * sigma / h:.2f} < "
              f"{texels:g} texel spacings ({why}): pass --cube-res up to {MAX_CUBE_RES} for more")
    return r, {"value": r, "lobe_sigma": sigma, "texel_spacing": h, "texels_per_lobe": 2 * sigma / h, "reason": reason}


#: texel averages (issue 42 §2), ``supersample='auto'``: sub-texels per texel side where a view's lobe
#: is narrower than the texels, chosen per view so that the sub-texel spacing h/S resolves the lobe
#: across the plane of incidence (2σ cos θ_o ≥ AUTO_TEXELS_PER_LOBE · h/S), from 2 up to this many
AUTO_SUPERSAMPLE = 8
#: the cap about the mirror direction averaged: the lobe's in-plane σ times this, plus 0.75 texel
#: spacings (a half-vector lobe at 3σ is (cos 3σ_h)^N ≈ e^−4.5 of its peak)
SUPERSAMPLE_CAP_SIGMAS = 3.0


def supersample_plan(brdf: BRDF | None, res: int, supersample: int | str = "auto") -> dict[str, Any] | None:
    """Where a table of ``brdf`` at face resolution ``res`` holds texel averages instead of point
    values (issue 42 §2): ``None`` (point values everywhere: no lobe, ``supersample`` 1, or a lobe
    the texel centres resolve at every view), else ``{'sub', 'adaptive', 'cos_view', 'cos_cap', 'reason'}``.

    A point value of a lobe narrower than the texel spacing is aliased: the texel centres hit or miss
    it, and Σ_p T Δω (what relighting from the table computes, Green 2005 eq. 1.1) no longer
    approximates ∫ T dω. A half-vector lobe (``BRDF.lobe_axis == 'half'``) narrows across the plane
    of incidence by cos θ_o (:func:`lobe_width`), so beyond the view angle where its 2σ cos θ_o spans
    fewer than :data:`AUTO_TEXELS_PER_LOBE` texel spacings h(r) — local view z < ``cos_view`` =
    AUTO_TEXELS_PER_LOBE · h / (2σ) — each texel within the lobe's cap about the mirror direction
    (angle < 3σ + 0.75 h: ``cos_cap``) gets the average of f_r max(n·ω, 0) over S × S sub-texels
    (weighted by their exact solid angles) times the texel's visibility: S = ``supersample``, or with
    'auto' (``adaptive``) per view the smallest S in [2, :data:`AUTO_SUPERSAMPLE`] at which the
    sub-texels resolve the lobe, S ≥ cos_view / cos θ_o (:func:`view_sub`). A lobe about
    the reflected view (Phong) has the same width at every view: averaged at all views when r does
    not resolve it (a ``--cube-res`` below ``res: auto``'s), else not at all."""
    adaptive = isinstance(supersample, str) and supersample == "auto"
    if adaptive:
        sub = AUTO_SUPERSAMPLE
    elif isinstance(supersample, bool) or not isinstance(supersample, int):
        raise ValueError(f"supersample={supersample!r}; accepted: 'auto' or an integer in [1, 8] (1: point values)")
    else:
        sub = check_int("supersample", supersample, 1, 8)
    brdf = AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0) if brdf is None else brdf
    s = float(brdf.sharpness)
    if sub == 1 or s <= 0:
        return None
    sigma = 1.0 / math.sqrt(s)
    h = texel_spacing(res)
    c_view = ratio = AUTO_TEXELS_PER_LOBE * h / (2 * sigma)
    half = getattr(brdf, "lobe_axis", "half") == "half"
    if not half and c_view <= 1.0:
        return None
    c_view = min(c_view, 1.0 + 1e-9)
    rho = min(math.pi, SUPERSAMPLE_CAP_SIGMAS * sigma + 0.75 * h)
    deg = math.degrees(math.acos(min(1.0, c_view)))
    how = f"2x2 to {sub}x{sub} sub-texels (per view, as the lobe narrows)" if adaptive else f"{sub}x{sub} sub-texels"
    return {"sub": sub, "adaptive": adaptive, "half": half, "ratio": ratio, "cos_view": c_view, "cos_cap": math.cos(rho),
            "reason": f"texel averages over {how} for views more than {deg:.1f} deg from the normal (the lobe's "
                      f"2 sigma cos(theta_o) spans < {AUTO_TEXELS_PER_LOBE:g} texel spacings there; sigma = {sigma:.3f} rad, "
                      f"h = {h:.3f} rad) on texels within {math.degrees(rho):.0f} deg of the mirror direction; point values elsewhere"}


def sub_texel_sets(res: int, plan: dict[str, Any]) -> dict[int, tuple[torch.Tensor, torch.Tensor]]:
    """{S: :func:`_sub_texels` (res, S)} for every S the ``plan`` may use (2 … sub when adaptive)."""
    sizes = range(2, int(plan["sub"]) + 1) if plan.get("adaptive") else [int(plan["sub"])]
    return {S: _sub_texels(res, S) for S in sizes}


def view_sub(plan: dict[str, Any], cos_o: torch.Tensor) -> torch.Tensor:
    """Sub-texels per side for views at ``cos_o`` (local z, any shape) under ``plan``
    (:func:`supersample_plan`): its ``sub``, or when ``adaptive`` ⌈ratio / cos θ_o⌉ for a half-vector
    lobe (ratio = AUTO_TEXELS_PER_LOBE · h / 2σ; the lobe narrows by cos θ_o), ⌈ratio⌉ for a lobe about
    the reflected view, in [2, sub] (int64)."""
    if not plan.get("adaptive"):
        return torch.full(cos_o.shape, int(plan["sub"]), dtype=torch.long)
    need = plan["ratio"] / cos_o.clamp_min(1e-6) if plan.get("half", True) else torch.full_like(cos_o, plan["ratio"])
    return torch.ceil(need - 1e-9).clamp(2, int(plan["sub"])).long()


def _sub_texels(res: int, sub: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Sub-texel directions ``[P, sub², 3]`` and their shares of the texel's solid angle ``[P, sub²]``
    (float64; texel p in the module's order, its sub-texels those of the ``res·sub`` cube map)."""
    d, sa = _cube_directions(res * sub)
    d = d.reshape(6, res, sub, res, sub, 3).permute(0, 1, 3, 2, 4, 5).reshape(6 * res * res, sub * sub, 3)
    sa = sa.reshape(6, res, sub, res, sub).permute(0, 1, 3, 2, 4).reshape(6 * res * res, sub * sub)
    return d.contiguous(), (sa / sa.sum(1, keepdim=True)).contiguous()


#: (view, texel) pairs per BRDF block of a transport chunk (issue 42): the block's float64
#: temporaries stay a few MB (heap reused from block to block, in cache) where one evaluation
#: over the whole chunk's ~2M pairs made tens of fresh 16–48 MB arrays — page faults that were
#: ~40% of a chunk's time
PAIR_BLOCK = 1 << 16


def _chunk_transport(caster, brdf, points, normals, frames, texels, views, mat_index, shadows,
                     dtype: torch.dtype = torch.float64, out: torch.Tensor | None = None,
                     plan: dict[str, Any] | None = None,
                     sub_texels: dict[int, tuple[torch.Tensor, torch.Tensor]] | None = None,
                     average_threads: int | None = None, visibility: torch.Tensor | None = None) -> torch.Tensor:
    """T for k vertices: ``[k, J, P]`` (P = 6r² texels) in ``dtype`` (the values computed in
    float64 and rounded once: the stored dtype is written directly), Green 2005 eq. 1.2.

    T is zero for a view below the vertex's tangent plane (f_r is zero there; cos θ_o ≤ :data:`HORIZON_EPS`
    counts as below, so a view lying in the plane gives zeros, not Ward's divergence) and for a texel
    below it or blocked (W = V max(n·ω_i, 0) is), so the BRDF is evaluated only on the pairs of
    an upper view and a visible texel — about a quarter of k·J·P (issue 42: the BRDF evaluation
    is the table's cost, not the ~P/2 rays per vertex). The pairs are taken a block of vertices
    at a time (at most :data:`PAIR_BLOCK` pairs, at least one vertex) and scattered into their
    rows, so every temporary is block-sized. ``out``: a buffer of at least ``k·J·P`` elements of
    ``dtype`` to write into (zeroed here; the chunk loop reuses one), else a new one.

    ``plan`` (:func:`supersample_plan`) with ``sub_texels`` ({S: :func:`_sub_texels`: ``[P, S², 3]``
    directions and ``[P, S²]`` solid-angle shares} for every S the plan uses): the pairs of a view beyond ``cos_view`` and a
    texel within the cap about its mirror direction hold V_p Σ_s a_s f_r(ω_s, ω_o) max(n·ω_s, 0),
    the texel average (V_p: one ray per texel, toward its centre, or toward its highest sub-texel
    when the centre is below the horizon and a sub-texel is not); their centre values are not
    evaluated (:func:`_averaged_pairs` before the point pairs). ``average_threads``: torch threads
    for those averages (None: the caller's count); :func:`precompute_transport` passes the process's
    count, since no ray is cast while they run (the rest of the chunk runs in :data:`CHUNK_THREADS`,
    the other cores being the ray-casting workers'). The values do not depend on it (elementwise
    work and a per-pair sum: tested).

    ``visibility``: a bool ``[k, P]`` tensor to fill with each texel's visibility V_p as the table uses
    it (independent of the view): its ray unblocked and some of it above the tangent plane (the texel
    centre, or with ``plan`` some sub-texel) — what the harness's exact-view reference reads
    (:func:`texel_visibility`, ``TransportTable.visibility``)."""
    cos = normals @ texels.T  # [k, P]
    W = cos.clamp_min(0)
    vis_any = None
    if plan is not None:
        sd = sub_texels[max(sub_texels)][0]  # the finest sub-texels decide the straddling texels
        cmax = torch.empty(normals.shape[0], sd.shape[0], dtype=sd.dtype)
        amax = torch.empty(normals.shape[0], sd.shape[0], dtype=torch.long)
        step = max(1, (4 << 20) // (8 * sd.shape[0] * sd.shape[1]))  # vertex blocks: [b, P, S²] temporaries of ~4 MB, not one
        for v0 in range(0, normals.shape[0], step):  # of k·P·S² (~46 MB fresh per chunk: page faults, issue 42 §2)
            torch.max(torch.einsum("kc,psc->kps", normals[v0:v0 + step], sd), -1, out=(cmax[v0:v0 + step], amax[v0:v0 + step]))
        vis_any = cmax > 0  # some sub-texel above the horizon (visibility below)
    if shadows:
        i, j = torch.nonzero(cos > 0, as_tuple=True)
        if i.numel():
            occ = caster.occluded(points[i], texels[j], normals=normals[i])
            W[i[occ], j[occ]] = 0.0
            if vis_any is not None:
                vis_any[i[occ], j[occ]] = False
        if vis_any is not None:  # straddling texels: centre below the horizon, a sub-texel above it
            i, j = torch.nonzero(vis_any & (cos <= 0), as_tuple=True)
            if i.numel():
                occ = caster.occluded(points[i], sd[j, amax[i, j]], normals=normals[i])
                vis_any[i[occ], j[occ]] = False
    if visibility is not None:
        visibility.copy_(W > 0 if vis_any is None else vis_any | (W > 0))
    wi = torch.einsum("kab,pb->kpa", frames, texels)  # [k, P, 3] local light directions
    wo = torch.einsum("kab,jb->kja", frames, views)  # [k, J, 3] local views
    k, J, P = wo.shape[0], wo.shape[1], wi.shape[1]
    if out is None:
        T = torch.zeros(k, J * P, dtype=dtype)
    else:
        if out.dtype != dtype or out.numel() < k * J * P:
            raise ValueError(f"out holds {out.numel()} {out.dtype} values; accepted: at least {k * J * P} of {dtype}")
        T = out.view(-1)[:k * J * P].view(k, J * P)
    # the pairs where T can be non-zero: view above the tangent plane (wo_z > HORIZON_EPS) and W > 0
    up, vis = wo[:, :, 2] > HORIZON_EPS, W > 0  # [k, J], [k, P]
    pairs, later = None, None
    if plan is not None:  # the averaged pairs: their centre values would be overwritten, so not evaluated
        pairs = _averaged_pairs(normals, wo, vis_any, views, plan, texels)
    threads = average_threads or torch.get_num_threads()
    native = transport_kernels.native_model(brdf, k, mat_index) if k else None
    if native is not None and transport_kernels.points(T, wi, wo, W, pairs, native, threads, horizon=HORIZON_EPS):  # compiled: the same pairs
        if plan is not None:
            _average_texels(T, brdf, frames, wo, pairs, mat_index, plan, sub_texels, dtype, native=native, threads=threads)
        return T.view(k, J, P)
    T.zero_()
    if pairs is not None:
        later = torch.zeros(k, J, P, dtype=torch.bool).index_put_(pairs, torch.ones((), dtype=torch.bool))
    per_vertex = int((up.sum(1) * vis.sum(1)).max()) if k else 0
    step = max(1, PAIR_BLOCK // max(1, per_vertex))
    for v0 in range(0, k, step):  # blocks of vertices (block-sized temporaries), not a loop per vertex
        v1 = min(k, v0 + step)
        mask = up[v0:v1, :, None] & vis[v0:v1, None, :]  # [b, J, P]
        if later is not None:
            mask &= ~later[v0:v1]
        iv, jv, pv = torch.nonzero(mask, as_tuple=True)
        if not iv.numel():
            continue
        iv += v0
        b = brdf if mat_index is None else brdf.select(mat_index[iv])
        f = b.eval(wi[iv, pv], wo[iv, jv])  # [N]
        T[v0:v1].masked_scatter_(mask.view(v1 - v0, J * P), (f * W[iv, pv]).to(dtype))
    if plan is not None:
        with torch_threads(threads):
            _average_texels(T, brdf, frames, wo, pairs, mat_index, plan, sub_texels, dtype)
    return T.view(k, J, P)


def _averaged_pairs(normals, wo, vis_any, views, plan, texels) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The (vertex, view, texel) index triples (int64 ``[n]`` each) that ``plan`` averages: a view above
    the tangent plane (cos θ_o > :data:`HORIZON_EPS`) and below ``cos_view`` (local z of ``wo [k, J, 3]``), a texel within the cap
    about its mirror direction (cos > ``cos_cap``) with some sub-texel visible (``vis_any [k, P]``)."""
    mirror = 2 * (normals @ views.T)[..., None] * normals[:, None, :] - views[None]  # [k, J, 3] world mirror directions
    graze = (wo[:, :, 2] > HORIZON_EPS) & (wo[:, :, 2] < plan["cos_view"])  # [k, J]
    iv, jv = torch.nonzero(graze, as_tuple=True)
    near = (mirror[iv, jv] @ texels.T > plan["cos_cap"]) & vis_any[iv]  # [n, P]
    q, pv = torch.nonzero(near, as_tuple=True)
    return iv[q], jv[q], pv


def _average_texels(T, brdf, frames, wo, pairs, mat_index, plan, sub_texels, dtype, native=None, threads: int = 1) -> None:
    """Overwrite the ``pairs`` ``plan`` averages (:func:`_averaged_pairs`) in ``T [k, J·P]`` with their
    texel averages, in blocks of about :data:`PAIR_BLOCK` (pair, sub-texel) evaluations.

    The work per (vertex, texel) that no view changes is done once: the sub-texels' local directions
    ``[U, S², 3]`` (float64; one rotation per distinct (vertex, texel) of a sub-texel count, where a
    texel near the mirror direction of ~7 grazing views was rotated once per view), gathered per pair.
    The BRDF takes the pair's view ``[n, 1, 3]`` broadcast against its sub-texels ``[n, S², 3]`` (no
    repeated copies). Both leave every value as it was: the same rotation of the same inputs and an
    elementwise BRDF on the same operands."""
    P = T.shape[1] // wo.shape[1]
    iv, jv, pv = pairs
    if not iv.numel():
        return
    subs = view_sub(plan, wo[iv, jv, 2])
    if native is not None and transport_kernels.averages(T, frames, wo, pairs, subs, sub_texels, native, threads):
        return
    for S in subs.unique().tolist():  # one pass per sub-texel count (at most 7), not per view
        sd, sw = sub_texels[S]
        S2 = S * S
        m = subs == S
        ivs, jvs, pvs = iv[m], jv[m], pv[m]
        key, inv = torch.unique(ivs * P + pvs, return_inverse=True)  # distinct (vertex, texel) of this S
        ui, up = key // P, key % P
        step = max(1, PAIR_BLOCK // S2)
        wiu = torch.empty(key.numel(), S2, 3, dtype=sd.dtype)
        for a in range(0, key.numel(), step):  # blocks of (vertex, texel): [n, S², 3] local sub-texel directions
            wiu[a:a + step] = torch.einsum("nab,nsb->nsa", frames[ui[a:a + step]], sd[up[a:a + step]])
        for a in range(0, ivs.numel(), step):  # blocks of pairs (block-sized temporaries), not a loop per pair
            i, j, p = ivs[a:a + step], jvs[a:a + step], pvs[a:a + step]
            wi = wiu[inv[a:a + step]]  # [n, S², 3]
            b = brdf if mat_index is None else brdf.select(mat_index[i]).view(-1, 1)
            f = b.eval(wi, wo[i, j][:, None, :])  # [n, S²]
            T[i, j * P + p] = (f * wi[..., 2].clamp_min(0) * sw[p]).sum(1).to(dtype)


def pack_visibility(vis: torch.Tensor) -> torch.Tensor:
    """Texel visibility ``[k, P]`` bool → packed bits ``[k, ⌈P/8⌉]`` uint8 (texel p at bit p % 8 of byte
    p // 8, little bit order): what a transport chunk file stores as ``visibility`` (P/8 bytes a vertex:
    127 at 6×13×13, against J·P·4 = 170 kB of tables at 42 views)."""
    import numpy as np

    return torch.from_numpy(np.packbits(vis.numpy(), axis=1, bitorder="little"))


def unpack_visibility(bits: torch.Tensor, P: int) -> torch.Tensor:
    """:func:`pack_visibility`'s inverse: ``[k, ⌈P/8⌉]`` uint8 → ``[k, P]`` bool."""
    import numpy as np

    return torch.from_numpy(np.unpackbits(bits.numpy(), axis=1, count=P, bitorder="little").astype(bool))


def texel_visibility(mesh: Mesh, res: int, *, plan: dict[str, Any] | None = None, shadows: bool = True,
                     offset: float = 1e-4, workers: int | None = 1, vertices: torch.Tensor | None = None) -> torch.Tensor:
    """The texel visibility V_p ``[k, P]`` bool (P = 6 res²) of a transport table of ``mesh``, traced now: the
    rays :func:`precompute_transport` casts (one per texel with its centre above the tangent plane, and with a
    supersample ``plan`` — the manifest's — one toward the highest sub-texel of a texel whose centre is below it
    and a sub-texel above), from the same origins (``offset``, as the manifest's fingerprint has it), so the
    bits of the chunk files' ``visibility``. For tables written before it was stored (the harness's exact-view
    reference falls back to this). ``vertices``: int64 indices (default all), in chunks of 4096."""
    res = check_int("res", res, 1, MAX_CUBE_RES)
    from ..brdf import Lambertian

    idx = torch.arange(mesh.num_vertices) if vertices is None else torch.as_tensor(vertices, dtype=torch.long).reshape(-1)
    if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= mesh.num_vertices):
        raise ValueError(f"vertices holds indices in [{int(idx.min())}, {int(idx.max())}]; accepted: vertex indices in "
                         f"[0, {mesh.num_vertices})")
    if not isinstance(shadows, bool):
        raise ValueError(f"shadows={shadows!r}; accepted: True or False (the table's manifest 'shadows')")
    texels = cube_directions(res)[0].reshape(-1, 3)
    plan = None if plan is None or int(plan.get("sub", 1)) <= 1 else plan
    subs = None if plan is None else sub_texel_sets(res, plan)
    F = check_frames(mesh)
    out = torch.zeros(idx.numel(), texels.shape[0], dtype=torch.bool)
    caster = RayCaster(mesh, workers=workers, offset=offset) if shadows else None
    up = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)  # one view: the BRDF pass is incidental (Lambertian)
    try:
        for a in range(0, idx.numel(), 4096):
            i = idx[a:a + 4096]
            _chunk_transport(caster, Lambertian(), mesh.vertices[i], mesh.normals[i], F[i], texels, up, None, bool(shadows),
                             torch.float32, plan=plan, sub_texels=subs, visibility=out[a:a + 4096])
    finally:
        if caster is not None:
            caster.close()
    return out


def check_disk_space(out: str | Path, V: int, views: torch.Tensor | int, res: int, dtype: str) -> int:
    """The bytes the tables of ``V`` vertices will take (``V·J·6r²`` values of ``dtype``), refused with
    ValueError (before any work) when the disk holding ``out`` has less free space than that plus
    5%. Returns the estimate."""
    J = (10 * int(views) ** 2 + 2) if isinstance(views, int) else int(torch.as_tensor(views).shape[0])
    need = int(V) * J * 6 * int(res) ** 2 * (4 if dtype == "float32" else 2)
    have = sum(f.stat().st_size for f in Path(out).glob("*.prt")) if Path(out).is_dir() else 0  # chunks kept for a resume
    io.check_disk_space(out, need, f"transport tables of {V} vertices x {J} views x 6x{res}x{res} texels ({dtype})",
                        "fewer views, a smaller res, dtype float16, a smaller mesh, or an output on a disk with room", have)
    return need


def precompute_transport(
    mesh: Mesh,
    out: str | Path,
    *,
    brdf: BRDF | None = None,
    views: torch.Tensor | int = 3,
    res: int | str = "auto",
    supersample: int | str = "auto",
    dtype: str = "float32",
    shadows: bool | str = True,
    overwrite: bool = False,
    max_chunks: int | None = None,
    run: RunOptions | None = None,
) -> "TransportTable":
    """Stream direct glossy transport tables (Green 2005 §2.2.1) for every vertex to ``out``.

    Args:
        brdf: reflectance (default isotropic Ashikhmin–Shirley N = 40); per-vertex ``[V]``
            parameters are allowed.
        views: global view directions ``[J, 3]``, or an icosphere frequency (3 → Green's 92).
        res: cube-map face resolution r (6 r² texels per table), or 'auto' (default): the smallest
            r at which the BRDF's narrowest lobe spans two texel spacings (:func:`choose_cube_res`;
            the choice and its reason in ``manifest['auto']['res']``).
        supersample: sub-texels per texel side of the texel averages stored where the BRDF's lobe
            is narrower than the texels (:func:`supersample_plan`: grazing views of a half-vector
            lobe, near its mirror direction), 'auto' (default), an integer S in [1, 8] or 1 (point values everywhere,
            the tables before issue 42 §2); 'auto': 2 to 8 per view as the lobe narrows; the plan and
            its reason in ``manifest['supersample']``.
        dtype: stored precision, 'float32' or 'float16'.
        overwrite: remove an existing ``out`` first. Otherwise an existing ``out`` is refused
            unless ``run.resume`` (keep the chunk files already there, same fingerprint, and
            compute the rest): ``out`` is this kind's resumable state.
        run: :class:`RunOptions` — ``chunk_size`` (vertices per chunk file, default ~64 MB of
            float64 work per chunk), ``workers``, ``offset``, ``resume``, ``progress``,
            ``callback(chunk, n_chunks)`` after each chunk written.
        max_chunks: stop after this many new chunks (for measuring a subset; the table is then
            incomplete and says so in ``manifest['complete']``).
    Returns:
        :class:`TransportTable` over ``out``.
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a prt_torch.scene.Mesh, got {describe(mesh)}")
    run = RunOptions() if run is None else run
    brdf = AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0) if brdf is None else brdf
    if not isinstance(brdf, BRDF):
        raise TypeError(f"brdf must be a prt_torch.brdf.BRDF, got {describe(brdf)}")
    auto: dict[str, Any] = {}
    if isinstance(res, str) and res == "auto":
        res, auto["res"] = choose_cube_res(brdf)
    elif isinstance(res, str) or isinstance(res, bool) or not isinstance(res, int):
        raise ValueError(f"res={res!r}; accepted: an integer in [1, {MAX_CUBE_RES}] or 'auto'")
    res = check_int("res", res, 1, MAX_CUBE_RES)
    plan = supersample_plan(brdf, res, supersample)
    check_choice("dtype", dtype, ["float32", "float16"])
    offset, resume = run.offset, run.resume
    check_disk_space(out, mesh.num_vertices, views, res, dtype)  # an absurd table is refused before any ray
    shadows, shadow_meta = decide_shadows(mesh, shadows, 0, run)
    V = mesh.num_vertices
    bs = brdf.batch_shape
    mat_index = None
    if len(bs) == 1 and bs[0] == V and V > 1:
        mat_index = torch.arange(V)
    elif len(bs) > 1 or (len(bs) == 1 and bs[0] != 1):
        raise ValueError(f"brdf parameters have batch shape {tuple(bs)}; accepted: scalars or [V] = [{V}]")
    elif len(bs) == 1:
        brdf = brdf.view()  # a single [1] material -> scalar parameters
    view_dirs = icosphere_directions(views) if isinstance(views, int) else torch.as_tensor(views, dtype=torch.float64)
    if view_dirs.ndim != 2 or view_dirs.shape[1] != 3:
        raise ValueError(f"views has shape {tuple(view_dirs.shape)}; accepted: [J, 3] directions or an icosphere frequency")
    view_dirs = view_dirs / view_dirs.norm(dim=-1, keepdim=True)
    J = view_dirs.shape[0]
    F = check_frames(mesh)
    texels, solid = cube_directions(res)
    P = 6 * res * res
    chunk_size = run.chunks(int(max(1, min(4096, (8 << 20) // (J * P)))))
    out = Path(out)
    fingerprint = {"mesh_hash": mesh.content_hash(), "brdf": brdf.meta() if mat_index is None else "per-vertex",
                   "views": view_dirs.tolist() if isinstance(views, torch.Tensor) else int(views), "res": res,
                   "supersample": None if plan is None else {k: v for k, v in plan.items() if k != "reason"},
                   "dtype": dtype, "shadows": shadows, "offset": offset, "chunk_size": chunk_size,
                   "horizon_eps": HORIZON_EPS}
    manifest_path = out / "manifest.json"
    if out.exists():
        if overwrite:
            import shutil

            shutil.rmtree(out)
        elif not resume:
            raise FileExistsError(f"output {str(out)!r} exists; pass resume=True to continue it or overwrite=True to replace it")
        else:
            try:
                have = json.loads(manifest_path.read_text())["fingerprint"]
            except (OSError, ValueError, KeyError):
                have = None
            if have != json.loads(json.dumps(fingerprint)):
                raise ValueError(f"{str(out)!r} holds transport tables with other parameters; accepted: the same "
                                 "parameters to resume, or overwrite=True")
    out.mkdir(parents=True, exist_ok=True)
    n_chunks = math.ceil(V / chunk_size)
    meta: dict[str, Any] = {
        "kind": "transfer/transport", "transfer_kind": "transport", "fingerprint": fingerprint,
        "vertices": V, "views": J, "res": res, "texels": P, "dtype": dtype, "chunk_size": chunk_size,
        "chunks": n_chunks, "brdf": brdf.meta(), "shadows": shadows, "mesh_name": mesh.name,
        "shape_per_vertex": [J, 6, res, res], "bytes_total": V * J * P * (4 if dtype == "float32" else 2),
        "layout": "cube faces +x,-x,+y,-y,+z,-z (OpenGL); data[v, j, face, row, col]",
        "normalisation": "L_o(x_v, views[j]) = sum over texels of data * L(texel dir) * solid_angle",
        "complete": False, **shadow_meta,
        "supersample": plan if plan is not None else {"sub": 1, "reason": "point values at the texel centres (no lobe narrower "
                                                                          "than the texels, or supersample=1)"},
        "visibility": {"stored": "each chunk file's 'visibility': uint8 [k, ceil(P/8)], texel p at bit p % 8 (little "
                                 "order) of byte p // 8: V_p of the tables (ray unblocked, some of the texel above the "
                                 "tangent plane), independent of the view", "bytes_per_vertex": (P + 7) // 8},
    }
    if auto:
        meta["auto"] = auto
    io.atomic_write_json(manifest_path, meta)
    io.save(out / "views.prt", {"views": view_dirs, "texels": texels, "solid_angles": solid}, kind="transfer/transport_views")
    io.save(out / "mesh.prt", mesh.to_tensors("mesh."), kind="scene/mesh", meta={"mesh_name": mesh.name})
    caster = RayCaster(mesh, workers=run.workers, offset=offset) if shadows else None
    texels_flat = texels.reshape(-1, 3)
    subs = None if plan is None else sub_texel_sets(res, plan)
    store = torch.float32 if dtype == "float32" else torch.float16
    bar = None
    if run.progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=V, desc=f"transport {mesh.name}", unit="vtx", dynamic_ncols=True)
    t0, new = time.perf_counter(), 0
    ranges = [(c * chunk_size, min(V, (c + 1) * chunk_size)) for c in range(n_chunks)]

    # The chunk files are written by one background thread while the next chunk is computed (issue 42 §2: writing
    # the 3.6 GB default table through the page cache was ~12 s of a ~50 s run, the compute waiting): two chunk
    # buffers, one being written while the other fills; finished() returns once at most one write is pending, and
    # a chunk is reported (progress, callback) when its file is written, in order. A failed write raises here.
    pool: list[torch.Tensor] = []  # this process's chunk buffers
    free: list[torch.Tensor] = []  # those not being written
    writing: collections.deque = collections.deque()  # (chunk, future, buffer or None) in the order submitted
    writer = ThreadPoolExecutor(1, thread_name_prefix="prt-transport-write")
    home = os.getpid()

    def compute(c: int) -> list[torch.Tensor]:  # one chunk file's tables (in a list finished() empties); a task of run.executor
        a, b = ranges[c]
        if os.getpid() != home:  # a task in another process (Ray): its result is serialised as it returns and no
            if not pool:  # buffer comes back, so one buffer serves every task of that process (as before the writer)
                pool.append(torch.empty(chunk_size * J * P, dtype=store))
            buf = pool[0]
        else:
            if not free:
                pool.append(torch.empty(chunk_size * J * P, dtype=store))
                free.append(pool[-1])
            buf = free.pop()
        threads = torch.get_num_threads()  # this process's (a Ray task's: its CPUs): the BRDF passes use them all
        vis = torch.empty(b - a, P, dtype=torch.bool)
        with torch_threads(CHUNK_THREADS):
            T = _chunk_transport(caster, brdf, mesh.vertices[a:b], mesh.normals[a:b], F[a:b], texels_flat,
                                 view_dirs, None if mat_index is None else mat_index[a:b], shadows, store, out=buf,
                                 plan=plan, sub_texels=subs, average_threads=threads, visibility=vis)
        return [pack_visibility(vis), T.reshape(b - a, J, 6, res, res)]

    def report(c: int) -> None:
        if bar is not None:
            bar.update(ranges[c][1] - ranges[c][0])
        if run.callback is not None:
            run.callback(c, n_chunks)

    def settle(keep: int) -> None:  # wait until at most `keep` writes are pending, reporting the written chunks
        while len(writing) > keep:
            c, fut, buf = writing[0]
            fut.result()
            writing.popleft()
            if buf is not None:
                free.append(buf)
            report(c)

    def finished(c: int, box: list[torch.Tensor] | None) -> None:
        if box is None:
            settle(0)
            report(c)
            return
        data = box.pop()  # the executor's result list keeps no table
        bits = box.pop()  # the texels' visibility, packed (pack_visibility)
        buf = next((x for x in pool if x.data_ptr() == data.data_ptr()), None)
        writing.append((c, writer.submit(io.save, out / f"chunk_{c:06d}.prt", {"data": data, "visibility": bits},
                                         kind="transfer/transport_chunk",
                                         meta={"chunk": c, "start": ranges[c][0], "stop": ranges[c][1]}, direct=True), buf))
        settle(1)

    try:
        todo = []
        for c in range(n_chunks):
            if (out / f"chunk_{c:06d}.prt").exists():
                finished(c, None)
            elif max_chunks is None or len(todo) < max_chunks:
                todo.append(c)
        ex = LocalExecutor() if run.executor is None else run.executor
        res = ex.map(compute, todo, on_result=lambda k, T: finished(todo[k], T))
        settle(0)
        new = sum(not isinstance(r, TaskFailure) for r in res)
        bad = [r for r in res if isinstance(r, TaskFailure)]
        if bad:
            raise RuntimeError(f"transport {mesh.name}: chunk {todo[bad[0].index]} failed {bad[0].attempts} time(s): {bad[0].error}; "
                               f"{len(bad)} chunk(s) failed, the others are kept in {str(out)!r} (resume to compute the rest)")
    finally:
        for _, fut, _ in writing:  # on an error: the writes under way finish (each file whole or absent) before we return
            fut.exception()
        writer.shutdown()
        if bar is not None:
            bar.close()
        if caster is not None:
            caster.close()
    done = all((out / f"chunk_{c:06d}.prt").exists() for c in range(n_chunks))
    meta["complete"] = done
    meta["seconds_last_run"] = time.perf_counter() - t0
    meta["chunks_computed_last_run"] = new
    io.atomic_write_json(manifest_path, meta)
    return TransportTable(out)


class TransportTable:
    """Read access to a streamed transport directory (see module docstring)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        mp = self.path / "manifest.json"
        if not mp.exists():
            raise FileNotFoundError(f"{str(self.path)!r} is not a transport table (no manifest.json)")
        self.meta = json.loads(mp.read_text())
        if self.meta.get("kind") != "transfer/transport":
            raise ValueError(f"{str(mp)!r} has kind {self.meta.get('kind')!r}; accepted: 'transfer/transport'")
        t, _ = io.load(self.path / "views.prt")
        self.views, self.texels, self.solid_angles = t["views"], t["texels"], t["solid_angles"]

    @property
    def num_vertices(self) -> int:
        return int(self.meta["vertices"])

    def chunk(self, c: int) -> tuple[int, int, torch.Tensor]:
        """(start, stop, data ``[k, J, 6, r, r]``) of chunk ``c``."""
        t, m = io.load(self.path / f"chunk_{c:06d}.prt", expect_kind="transfer/transport_chunk")
        return int(m["start"]), int(m["stop"]), t["data"]

    def __iter__(self) -> Iterator[tuple[int, int, torch.Tensor]]:
        for c in range(int(self.meta["chunks"])):
            if (self.path / f"chunk_{c:06d}.prt").exists():
                yield self.chunk(c)

    def visibility(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The stored texel visibility (:func:`texel_visibility`'s bits, written with each chunk since issue
        42 §2): ``(vis [V, P] bool, have [V] bool)``, ``have`` False (and ``vis`` False) for the vertices of
        a chunk file without it (a table written before) or missing."""
        from safetensors import safe_open

        V, P, k = self.num_vertices, int(self.meta["texels"]), int(self.meta["chunk_size"])
        vis, have = torch.zeros(V, P, dtype=torch.bool), torch.zeros(V, dtype=torch.bool)
        for c in range(int(self.meta["chunks"])):
            f = self.path / f"chunk_{c:06d}.prt"
            if not f.exists():
                continue
            with safe_open(str(f), framework="pt") as h:  # the bits alone (the tables are not read)
                if "visibility" in h.keys():
                    a, b = c * k, min(V, (c + 1) * k)
                    bits = h.get_tensor("visibility")
                    if bits.dtype != torch.uint8 or tuple(bits.shape) != (b - a, (P + 7) // 8):
                        raise ValueError(f"{str(f)!r}: visibility is {bits.dtype} {list(bits.shape)}; accepted: uint8 "
                                         f"[{b - a}, {(P + 7) // 8}] (the chunk's vertices x ceil(texels/8)), as the manifest says")
                    vis[a:b], have[a:b] = unpack_visibility(bits, P), True
        return vis, have

    def mesh(self) -> Mesh:
        t, m = io.load(self.path / "mesh.prt")
        return Mesh.from_tensors(t, name=m.get("mesh_name", "mesh"))

    def radiance(self, light: torch.Tensor, view: int) -> torch.Tensor:
        """Exit radiance ``[V, C]`` towards ``views[view]`` under a cube-map light ``[C, 6, r, r]``
        (radiance per texel), chunk by chunk (Green eq. 1.1). Missing chunks give NaN rows."""
        out = torch.full((self.num_vertices, light.shape[0]), float("nan"), dtype=torch.float64)
        for a, b, T in self:
            out[a:b] = transport_radiance(T[:, view], light, self.solid_angles)
        return out

    def __repr__(self) -> str:
        m = self.meta
        return f"TransportTable({str(self.path)!r}, V={m['vertices']}, views={m['views']}, res={m['res']}, complete={m['complete']})"


def transport_radiance(T: torch.Tensor, light: torch.Tensor, solid_angles: torch.Tensor) -> torch.Tensor:
    """Σ_texels T · L · Δω (Green 2005 eq. 1.1) for tables ``T [k, 6, r, r]`` and a cube light
    ``[C, 6, r, r]`` → ``[k, C]`` float64."""
    w = (light.to(torch.float64) * solid_angles.to(torch.float64)[None]).reshape(light.shape[0], -1)
    return T.reshape(T.shape[0], -1).to(torch.float64) @ w.T
