"""Independent ground truth: per-vertex exit radiance of a transfer against Mitsuba 3 path tracing.

``validate(transfer, light)`` measures sampled vertices the way PRT defines them and compares,
with no scale fit:

* **What a vertex is.** Diffuse exit radiance at vertex p is (ρ_p/π) E_p with E_p the
  irradiance over the hemisphere of the vertex normal n_p at the vertex position (course notes
  2005, "Diffuse PRT"). Mitsuba measures E_p with an ``irradiancemeter`` sensor attached to a
  tiny one-sided disk (radius ``1e-2·eps``, black) centred at the engine's ray origin
  p + eps·n_p (+ eps·b_p on open mesh boundaries, :func:`prt_torch.transfer.diffuse.offset_origins`)
  facing n_p — eps is the transfer's own ray offset (``offset`` × bounding-box diagonal), so
  both sides start their rays at the same point. The rest of the scene is the transfer's mesh, flat-shaded (its
  triangles, as the engine's rays see them), one-sided Lambertian (Mitsuba's ``diffuse`` is
  black behind, as the engine's bounces are) with the mesh albedo as a vertex attribute.
* **The light.** The SH light ``[C, n²]`` is reconstructed on a lat-long image in Mitsuba's
  ``envmap`` parametrisation (Mitsuba local direction (sin θ sin φ, cos θ, −sin θ cos φ) for
  u = φ/2π, v = θ/π; with the identity ``to_world`` this is also prt_torch's world frame, +z up —
  pinned by tests/test_validate.py). Because the transfer vector is the projection of the
  transfer function onto the first n bands, t·l equals the integral of the band-limited light
  against the *full* transfer: the comparison is exact, no SH truncation enters. A light whose
  band-limited reconstruction goes negative (a directional light, a sharp cap at many bands)
  cannot be emitted and is refused by name before any work. ``light_source='image'`` (files
  and built-in environments) gives Mitsuba the original image instead; the difference between
  the two Mitsuba runs is what SH truncation of the light contributes (reported).
* **Direct and interreflected.** Mitsuba's ``path`` integrator with ``max_depth = 1`` sees only
  the environment from the probe (= the engine's shadowed, B = 0 transfer); ``max_depth = B+1``
  adds B bounces (= the engine's B bounces). The two renders share their seeds, so the
  difference (the interreflected part) is estimated with correlated noise. On the engine side
  the direct part is recomputed at the sampled vertices with the transfer's own direction set
  (:func:`prt_torch.transfer.transfer_at_points`, same samples, seed, offset), so
  engine interreflection = stored total − direct.
* **Noise.** Mitsuba: ``batches`` independent renders per vertex and depth, standard error of
  their mean. Engine: the per-ray estimator's standard error (the variance of the ray
  contributions over N, an upper bound for stratified sets); for the interreflected part the
  ray contributions use the stored total's exit radiance interpolated at the hits (an estimate).
  The ratio engine/Mitsuba of sums over the vertices carries both, combined in quadrature.

* **Glossy exit transfer** (kind 'glossy', quantity 'exit'): :func:`validate_glossy`.
  The engine's BRDF model becomes a Mitsuba BSDF written in Python (:func:`engine_bsdf`:
  f_r·cos θ_i in the vertex frame, cosine-hemisphere sampling) on a tiny disk at the engine's
  ray origin; a ``radiancemeter`` along a view v looks back at it (``max_depth`` 2: direct
  light; B+2 adds the transfer's B diffuse bounces). The engine side is :func:`prt_torch.relight.glossy`, recomputed from the transfer's own
  direction set (noise from replica seeds) and, on a dense set, with the BRDF unprojected: the
  engine's SH truncation bias at the vertices is reported apart (docs/validate.md).

Mitsuba is an optional dependency (``pip install 'prt-torch[validate]'``); without it
:func:`require_mitsuba` raises :class:`ValidatorUnavailable` with that one line.
"""
from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ._checks import check_choice, check_int
from .lighting import Environment, list_builtin_environments, load_light
from .relight import diffuse_transfer
from .scene import Mesh, RayCaster
from .sh import eval_sh
from .transfer import Transfer
from .transfer.diffuse import DiffuseSampler, HitBounce, boundary_nudge, face_points, offset_origins, transfer_at_points, vertex_transfer

__all__ = [
    "ValidatorUnavailable",
    "INSTALL_HINT",
    "require_mitsuba",
    "mitsuba_envmap_directions",
    "light_image",
    "check_expressible",
    "sample_vertices",
    "sharp_vertices",
    "mitsuba_exit_radiance",
    "engine_parts",
    "validate",
    "format_report",
    "BSDF_PLUGIN",
    "engine_bsdf",
    "glossy_brdf",
    "engine_glossy",
    "mitsuba_glossy_exit",
    "validate_glossy",
]

INSTALL_HINT = "prt validate needs Mitsuba 3: pip install 'prt-torch[validate]' (or: pip install 'mitsuba>=3.5')"
VARIANT = "scalar_rgb"
_LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


class ValidatorUnavailable(RuntimeError):
    """Mitsuba 3 is not installed (the message says how to install it)."""


def require_mitsuba():
    """Import Mitsuba 3 and set the ``scalar_rgb`` variant; raise :class:`ValidatorUnavailable`
    with :data:`INSTALL_HINT` when it is missing."""
    try:
        import mitsuba as mi
    except ImportError:
        raise ValidatorUnavailable(INSTALL_HINT) from None
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


# ---------------------------------------------------------------------------------------------
# light
# ---------------------------------------------------------------------------------------------

def mitsuba_envmap_directions(height: int) -> torch.Tensor:
    """World directions ``[H, 2H, 3]`` float64 of the pixel centres of a Mitsuba ``envmap``
    lat-long image with the identity ``to_world``: u = φ/2π, v = θ/π,
    d = (sin θ sin φ, cos θ, −sin θ cos φ) (Mitsuba 3 ``envmap.cpp``; pinned by a test)."""
    H, W = int(height), 2 * int(height)
    th = math.pi * (torch.arange(H, dtype=torch.float64) + 0.5) / H
    ph = 2 * math.pi * (torch.arange(W, dtype=torch.float64) + 0.5) / W
    st, ct = torch.sin(th)[:, None], torch.cos(th)[:, None]
    return torch.stack([st * torch.sin(ph), ct.expand(H, W), -st * torch.cos(ph)], -1)


def light_image(L: torch.Tensor, height: int = 128) -> np.ndarray:
    """The SH light ``L [C, n²]`` (C = 1 or 3) reconstructed on Mitsuba's lat-long grid:
    ``[H, 2H, 3]`` float32 radiance (grey lights replicated to RGB)."""
    L = torch.as_tensor(L, dtype=torch.float64)
    L = L[None] if L.ndim == 1 else L
    bands = int(round(math.sqrt(L.shape[1])))
    d = mitsuba_envmap_directions(height)
    img = eval_sh(d.reshape(-1, 3), bands) @ L.T  # [HW, C]
    img = img.expand(-1, 3) if img.shape[1] == 1 else img
    return img.reshape(d.shape[0], d.shape[1], 3).numpy().astype(np.float32)


def check_expressible(L: torch.Tensor, name: str, height: int = 128, tol: float = 1e-3) -> np.ndarray:
    """Refuse (``ValueError`` naming the light) a light Mitsuba cannot emit: one whose
    band-limited reconstruction is negative somewhere (below ``-tol`` × its peak). Returns the
    image, with round-off negatives clipped."""
    img = light_image(L, height)
    peak = float(np.abs(img).max())
    if peak == 0 or not np.isfinite(img).all():
        raise ValueError(f"light {name!r} is zero or not finite; accepted: a light with positive radiance")
    lo = float(img.min())
    if lo < -tol * peak:
        raise ValueError(f"light {name!r}: its {int(round(math.sqrt(L.shape[-1])))}-band SH reconstruction is negative "
                         f"(min {lo:.3g}, peak {peak:.3g}) and Mitsuba cannot emit negative radiance; accepted: lights whose "
                         "band-limited radiance is non-negative (constant, sky_gradient, hemisphere/cap at 2 bands, smooth "
                         "environments), or light_source='image' for an environment file")
    return np.maximum(img, 0.0)


def _source_image(spec: Any, height: int) -> np.ndarray | None:
    """The original radiance of an environment (file or built-in) on Mitsuba's grid, or None
    when ``spec`` is analytic (no image behind it)."""
    from .lighting import builtin_environment, load_environment

    if isinstance(spec, Environment):
        env = spec
    elif isinstance(spec, str) and spec in list_builtin_environments():
        env = builtin_environment(spec)
    elif isinstance(spec, (str, os.PathLike)) and Path(spec).exists():
        env = load_environment(spec)
    else:
        return None
    d = mitsuba_envmap_directions(height)
    v = env.sample(d.reshape(-1, 3)).to(torch.float64)  # [HW, C]
    v = v.expand(-1, 3) if v.shape[1] == 1 else v
    return v.reshape(d.shape[0], d.shape[1], 3).numpy().astype(np.float32)


# ---------------------------------------------------------------------------------------------
# vertices
# ---------------------------------------------------------------------------------------------

def sharp_vertices(mesh: Mesh) -> torch.Tensor:
    """``[V]`` float64: the largest angle (degrees) between a vertex normal and the geometric
    normals of its adjacent faces (0 on flat parts; large at sharp and concave vertices)."""
    _, fn, _ = face_points(mesh)
    f = mesh.faces.to(torch.int64)
    cosang = (mesh.normals.to(torch.float64)[f] * fn[:, None, :]).sum(-1).clamp(-1, 1)  # [F,3]
    worst = torch.full((mesh.num_vertices,), 1.0, dtype=torch.float64)
    worst = worst.scatter_reduce(0, f.reshape(-1), cosang.reshape(-1), reduce="amin")
    return torch.rad2deg(torch.arccos(worst))


def sample_vertices(mesh: Mesh, n: int, seed: int = 0) -> torch.Tensor:
    """``n`` distinct vertex indices (sorted), uniformly at random with ``seed``."""
    n = check_int("vertices", n, 1)
    g = torch.Generator().manual_seed(int(seed) + 104729)
    return torch.randperm(mesh.num_vertices, generator=g)[: min(n, mesh.num_vertices)].sort().values


# ---------------------------------------------------------------------------------------------
# Mitsuba side
# ---------------------------------------------------------------------------------------------

def _write_ply(path: Path, mesh: Mesh) -> None:
    v = mesh.vertices.numpy().astype("<f4")
    c = mesh.albedo.numpy().astype("<f4")
    f = mesh.faces.numpy()
    hdr = ("ply\nformat binary_little_endian 1.0\n"
           f"element vertex {v.shape[0]}\nproperty float x\nproperty float y\nproperty float z\n"
           "property float r\nproperty float g\nproperty float b\n"
           f"element face {f.shape[0]}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    fd = np.zeros(f.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    fd["n"], fd["i"] = 3, f
    with open(path, "wb") as fh:
        fh.write(hdr)
        fh.write(np.concatenate([v, c], 1).tobytes())
        fh.write(fd.tobytes())


def _base_scene(mi, image: np.ndarray, mesh: Mesh | None, tmp: Path) -> dict[str, Any]:
    """The Mitsuba scene both measurements share: the light image as ``envmap`` and (if given)
    the mesh, flat-shaded, one-sided Lambertian with its vertex albedo (written to ``tmp``)."""
    scene: dict[str, Any] = {"type": "scene", "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(image, np.float32))}}
    if mesh is not None:
        ply = tmp / "mesh.ply"
        _write_ply(ply, mesh)
        scene["mesh"] = {"type": "ply", "filename": str(ply), "face_normals": True,
                         "bsdf": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}}
    return scene


def _probe(mi, p: np.ndarray, n: np.ndarray, radius: float, spp: int) -> dict:
    up = (0.0, 0.0, 1.0) if abs(n[2]) < 0.9 else (1.0, 0.0, 0.0)
    T = mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(*p), target=mi.ScalarPoint3f(*(p + n)), up=mi.ScalarVector3f(*up))
    sensor = mi.load_dict({"type": "irradiancemeter",
                           "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                           "sampler": {"type": "independent", "sample_count": int(spp)}})
    return {"type": "disk", "to_world": T @ mi.ScalarTransform4f().scale(radius),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}, "sensor": sensor}


def mitsuba_exit_radiance(mesh: Mesh | None, points: Any, normals: Any, image: np.ndarray, depths: list[int], spp: int = 1024,
                          batches: int = 8, eps: float = 1e-4, seed: int = 0, albedo: Any = None,
                          nudge: Any = None) -> dict[str, torch.Tensor]:
    """Mitsuba 3 path-traced irradiance at probe points (module docstring).

    Args:
        mesh: the scene (flat-shaded, one-sided Lambertian, ``mesh.albedo``); None = only the
            environment.
        points, normals: ``[P, 3]``; each probe is centred at p + eps·n (+ eps·nudge) facing n —
            the engine's ray origin (:func:`prt_torch.transfer.diffuse.offset_origins`).
        nudge: optional ``[P, 3]`` :func:`prt_torch.transfer.diffuse.boundary_nudge` rows.
        image: ``[H, 2H, 3]`` environment radiance on Mitsuba's lat-long grid (:func:`light_image`).
        depths: ``path`` integrator ``max_depth`` values (1 = direct light only).
        spp: samples per probe and depth, split over ``batches`` independent renders.
        albedo: ``[P, C]`` exit albedo of the probes (exit radiance = albedo/π × irradiance);
            None = 1.
    Returns:
        ``{'irradiance': [D, P, 3], 'irradiance_se': [D, P, 3], 'radiance': [D, P, 3],
        'radiance_se': [D, P, 3]}`` float64 (standard errors of the batch means), and
        ``'diff_se'`` ``[D, P, 3]``: the standard error of depth d minus depth 0 (same seeds).
    """
    mi = require_mitsuba()
    P = torch.as_tensor(points, dtype=torch.float64).numpy()
    N = torch.as_tensor(normals, dtype=torch.float64)
    N = (N / N.norm(dim=-1, keepdim=True)).numpy()
    C = offset_origins(P, N, eps, None if nudge is None else torch.as_tensor(nudge, dtype=torch.float64).numpy())
    batches = check_int("batches", batches, 2)
    per = max(1, int(spp) // batches)
    radius = max(eps * 1e-2, 1e-7)
    with tempfile.TemporaryDirectory() as tmp:
        scene = _base_scene(mi, image, mesh, Path(tmp))
        for k in range(P.shape[0]):  # scene description, one probe per vertex (Mitsuba builds the scene once)
            scene[f"probe_{k:06d}"] = _probe(mi, C[k], N[k], radius, per)
        sc = mi.load_dict(scene)
    sensors = sc.sensors()
    if len(sensors) != P.shape[0]:  # pragma: no cover - Mitsuba always keeps them in order
        raise RuntimeError("Mitsuba did not keep one sensor per probe")
    out = np.zeros((len(depths), batches, P.shape[0], 3))
    for di, depth in enumerate(depths):
        integ = mi.load_dict({"type": "path", "max_depth": int(depth), "rr_depth": 1000})
        for k in range(P.shape[0]):  # Mitsuba renders one sensor per call (C++ inside, spp samples each)
            for b in range(batches):
                sd = (int(seed) * 7919 + b * 100003 + k * 1009) % (1 << 31)  # independent per probe and batch
                out[di, b, k] = np.asarray(mi.render(sc, sensor=k, integrator=integ, spp=per, seed=sd)).reshape(-1)[:3]
    E = torch.from_numpy(out)
    mean = E.mean(1)
    se = E.std(1, unbiased=True) / math.sqrt(batches)
    diff_se = (E - E[:1]).std(1, unbiased=True) / math.sqrt(batches)
    a = torch.ones(P.shape[0], 3, dtype=torch.float64) if albedo is None else torch.as_tensor(albedo, dtype=torch.float64)
    a = (a.expand(-1, 3) if a.shape[1] == 1 else a) / math.pi
    return {"irradiance": mean, "irradiance_se": se, "radiance": mean * a, "radiance_se": se * a, "diff_se": diff_se * a}


# ---------------------------------------------------------------------------------------------
# engine side
# ---------------------------------------------------------------------------------------------

def engine_parts(transfer: Transfer, L: torch.Tensor, idx: torch.Tensor, data: torch.Tensor | None = None,
                 replicas: int = 6) -> dict[str, Any]:
    """The engine's exit radiance at vertices ``idx`` split into direct and interreflected parts,
    with their Monte Carlo noise (module docstring). ``data``: replacement transfer rows for
    ``idx`` (e.g. a codec's reconstruction); its total replaces the stored one.

    Noise: the engine shares one direction set between all vertices, so its errors are
    correlated across vertices and a sum over vertices does not average them down. It is
    measured by re-running the sampled vertices with ``replicas`` other seeds
    (:func:`prt_torch.transfer.diffuse.vertex_transfer`, the precompute's own estimator): the
    standard deviation over replicas per vertex (``*_se``) and of the vertex sum (``*_sum_se``,
    luminance). Interreflection with ``bounce_points`` other than 'hits' needs the whole mesh
    per seed; there the per-ray estimate is used instead (``noise`` says which).

    Returns ``{'total', 'direct', 'inter', 'direct_se', 'inter_se'}`` ``[k, 3]`` float64,
    ``direct_sum_se``, ``inter_sum_se`` (floats or None) and ``noise`` (str)."""
    mesh, meta = transfer.mesh, transfer.meta
    bands = int(meta["bands"])
    samples, seed = int(meta.get("samples", 1024)), int(meta.get("seed", 0))
    sampling = meta.get("sampling", "uniform")
    offset = float(meta.get("offset", 1e-4))
    hit_samples = int(meta.get("hit_samples", 8))
    L = torch.as_tensor(L, dtype=torch.float64)
    L3 = L.expand(3, -1) if L.shape[0] == 1 else L  # [3, n²]
    tr = transfer if data is None else Transfer(kind="diffuse", data=_scatter_rows(transfer, idx, data), mesh=mesh, meta=meta)
    total_all = diffuse_transfer(tr, L3)  # [V, 3]
    total = total_all[idx]
    rho = mesh.albedo.to(torch.float64)[idx]  # [k, 3]
    p, n = mesh.vertices[idx].to(torch.float64), mesh.normals[idx].to(torch.float64)
    traced = bool(meta.get("shadows_traced", True))
    bounces = int(meta.get("bounces_used", 0))
    zero = torch.zeros(idx.numel(), 3, dtype=torch.float64)
    if not traced:  # analytic unshadowed transfer: exact, no Monte Carlo noise
        from .transfer.diffuse import unshadowed_transfer

        direct = rho * (unshadowed_transfer(n, bands) @ L3.T)
        return {"total": total, "direct": direct, "inter": zero, "direct_se": zero, "inter_se": zero,
                "direct_sum_se": 0.0, "inter_sum_se": 0.0, "noise": "none (analytic unshadowed transfer)"}
    with RayCaster(mesh, offset=offset) as caster:
        t0 = transfer_at_points(caster, p, n, bands, samples, seed, sampling, nudge=boundary_nudge(mesh)[idx])  # [k, n²], ρ = 1
        direct = rho * (t0 @ L3.T)
        hits_mode = bounces > 0 and meta.get("bounce_points") == "hits"
        if bounces > 0 and not hits_mode:
            _, inter_se = _ray_noise(caster, mesh, p, n, L3, bands, samples, seed, sampling, total_all, None, idx)
    inter = total - direct if bounces > 0 else zero
    lum = lambda x: x @ _LUMA  # noqa: E731
    D, I = [], []
    for r in range(int(replicas)):  # a loop over replica seeds; each one batched over the vertices
        T0r, TBr = vertex_transfer(mesh, idx, bands, samples, seed + 7919 * (r + 1), bounces if hits_mode else 0,
                                   sampling=sampling, offset=offset, hit_samples=hit_samples)
        D.append(rho * (T0r @ L3.T))
        if TBr is not None:
            tb = TBr.sum(1)  # [k, C, n²]
            tb = tb.expand(-1, 3, -1) if tb.shape[1] == 1 else tb
            I.append(rho * torch.einsum("kcn,cn->kc", tb, L3))
    if not D:  # no replicas: no noise estimate
        return {"total": total, "direct": direct, "inter": inter, "direct_se": zero, "inter_se": zero, "direct_sum_se": 0.0,
                "inter_sum_se": 0.0, "noise": "not measured"}
    D = torch.stack(D)
    out = {"total": total, "direct": direct, "inter": inter, "direct_se": D.std(0), "direct_sum_se": float(lum(D).sum(1).std()),
           "direct_reps": D, "noise": f"engine: std over {replicas} replica seeds (direct"}
    if bounces == 0:
        out.update(inter_se=zero, inter_sum_se=0.0)
        out["noise"] += ")"
    elif hits_mode:
        I = torch.stack(I)
        out.update(inter_se=I.std(0), inter_sum_se=float(lum(I).sum(1).std()), inter_reps=I)
        out["noise"] += " and interreflected)"
    else:
        out.update(inter_se=rho * inter_se, inter_sum_se=None)
        out["noise"] += "); interreflected: per-ray estimate, uncorrelated (an underestimate for sums)"
    return out


def _scatter_rows(transfer: Transfer, idx: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    data = transfer.data.clone()
    data[idx] = rows.to(data.dtype).reshape(data[idx].shape)
    return data


def _ray_noise(caster: RayCaster, mesh: Mesh, p: torch.Tensor, n: torch.Tensor, L3: torch.Tensor, bands: int, samples: int,
               seed: int, sampling: str, total_all: torch.Tensor, hits: HitBounce | None = None,
               idx: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Standard errors ``[k, 3]`` (ρ = 1) of the per-ray estimators of the direct part
    (4 V cos y·l for uniform, V y·l for cosine sampling) and of the interreflected part (the
    same with (1 − V) and the hit's exit radiance: with ``hits`` the engine's own per-hit
    estimate — same keys, so its hit-sampling noise is included —, else the stored total
    interpolated at the hit)."""
    sampler = DiffuseSampler(bands, samples, seed, sampling)
    frames = None
    if sampling == "cosine":
        from .scene import tangent_frames

        t, b = tangent_frames(n.numpy())
        frames = torch.stack([torch.from_numpy(t), torch.from_numpy(b), n], dim=-2)
    i, j, o, d, cos = sampler.rays(p, n, frames, caster.eps, boundary_nudge(mesh)[idx])
    prim, bu, bv, _ = caster.trace(o, d, "intersect")
    hit = prim != -1
    k = p.shape[0]
    w = (4.0 * cos[i, j]) if sampling == "uniform" else np.ones(i.shape[0])
    Ld = eval_sh(torch.from_numpy(d).to(torch.float64), bands, check=False) @ L3.T  # [R, 3]
    f_dir = torch.from_numpy(w * ~hit)[:, None] * Ld
    f = mesh.faces.numpy()
    tri = np.where(hit, prim, 0).astype(np.int64)
    beta = torch.from_numpy(np.stack([1 - bu - bv, bu, bv], 1).astype(np.float64))
    _, fn, _ = face_points(mesh)
    front = hit & (np.einsum("ij,ij->i", fn.numpy()[tri], d) < 0)
    if hits is not None:
        Lh = torch.zeros(i.shape[0], 3, dtype=torch.float64)
        fr = np.nonzero(front)[0]
        x = hits.exit_transfer(caster, tri[fr], beta[fr].numpy(), idx.numpy()[i[fr]], j[fr])  # [H, C, n²]
        Lh[torch.from_numpy(fr)] = torch.einsum("hcn,cn->hc", x.expand(-1, 3, -1) if x.shape[1] == 1 else x, L3)
    else:
        Lh = (beta[:, :, None] * total_all[torch.from_numpy(f[tri])]).sum(1)  # [R, 3]
    f_ind = torch.from_numpy(w * front)[:, None] * Lh
    Ns = samples  # the estimator averages over all N directions (zeros below the horizon)
    ii = torch.from_numpy(i)

    def se(x: torch.Tensor) -> torch.Tensor:
        s1 = torch.zeros(k, 3, dtype=torch.float64).index_add_(0, ii, x)
        s2 = torch.zeros(k, 3, dtype=torch.float64).index_add_(0, ii, x * x)
        var = (s2 / Ns - (s1 / Ns) ** 2).clamp_min(0)
        return (var / Ns).sqrt()

    return se(f_dir), se(f_ind)


# ---------------------------------------------------------------------------------------------
# the comparison
# ---------------------------------------------------------------------------------------------

def _ratio(e: torch.Tensor, e_se: torch.Tensor, m: torch.Tensor, m_se: torch.Tensor, e_sum_se: float | None = None) -> dict[str, float]:
    """Engine/Mitsuba ratio of sums (luminance over the vertices) with its 1σ noise: Mitsuba's
    per-vertex errors are independent (quadrature); the engine's sum error is ``e_sum_se`` when
    measured (replica seeds), else the quadrature of ``e_se``."""
    lum = lambda x: x @ _LUMA  # noqa: E731
    lum_se = lambda x: ((x ** 2) @ (_LUMA ** 2)).sqrt()  # noqa: E731
    E, M = float(lum(e).sum()), float(lum(m).sum())
    sE = float(lum_se(e_se).pow(2).sum().sqrt()) if e_sum_se is None else float(e_sum_se)
    sM = float(lum_se(m_se).pow(2).sum().sqrt())
    if M <= 0:
        return {"engine": E, "mitsuba": M, "ratio": float("nan"), "ratio_se": float("nan"), "engine_se": sE, "mitsuba_se": sM}
    r = E / M
    rse = abs(r) * math.sqrt((sE / E) ** 2 + (sM / M) ** 2) if E != 0 else sE / M
    return {"engine": E, "mitsuba": M, "ratio": r, "ratio_se": rse, "engine_se": sE, "mitsuba_se": sM,
            "z": (r - 1.0) / rse if rse > 0 else float("inf")}


def _rms_rel(e: torch.Tensor, m: torch.Tensor) -> float:
    lum_e, lum_m = e @ _LUMA, m @ _LUMA
    return float(((lum_e - lum_m).pow(2).mean().sqrt()) / lum_m.abs().mean().clamp_min(1e-300))


def validate(transfer: Transfer | str | os.PathLike, light: Any, *, vertices: int = 32, spp: int = 1024, batches: int = 8,
             seed: int = 0, codec_file: str | os.PathLike | None = None, light_source: str = "sh", light_name: str | None = None,
             sharp_deg: float = 18.0, image_height: int = 128, idx: torch.Tensor | None = None, mesh: Mesh | None = None,
             view_deg: float = 60.0) -> dict[str, Any]:
    """Engine vs Mitsuba 3 at ``vertices`` sampled vertices (module docstring); no scale fit.

    Args:
        transfer: a diffuse or glossy (exit) :class:`Transfer` or its file; glossy goes
            to :func:`validate_glossy` (``mesh``: the full mesh of a vertex-subset transfer;
            ``view_deg``: the views' largest angle from the normal).
        light: anything :func:`prt_torch.lighting.load_light` takes, or an SH tensor ``[C, n²]``.
        spp, batches: Mitsuba samples per vertex and depth, split into independent batches (noise).
        codec_file: also compare a codec's reconstruction of this transfer (total and
            interreflected against the engine's direct part).
        light_source: 'sh' (Mitsuba sees the band-limited light: exact comparison) or 'image'
            (Mitsuba sees the original environment; the report adds the SH-truncation effect).
        sharp_deg: vertices whose adjacent faces tilt at least this far from the vertex normal
            are reported separately.
    Returns:
        a JSON-able dict: ``direct``/``inter``/``total`` ratios (engine/Mitsuba of summed
        luminance, with 1σ noise and z), the same over the sharp vertices, per-vertex arrays,
        the settings.
    Raises:
        ValueError: a transfer kind, light or BRDF the validator cannot express (before any work).
        ValidatorUnavailable: Mitsuba 3 is not installed.
    """
    if not isinstance(transfer, Transfer):
        transfer = Transfer.load(transfer)
    if transfer.kind not in ("diffuse", "glossy"):
        raise ValueError(f"transfer kind {transfer.kind!r}: the validator expresses diffuse and glossy exit transfer; "
                         "accepted: prt precompute --kind diffuse or --kind glossy")
    if transfer.kind == "glossy":
        glossy_brdf(transfer)  # a BRDF, quantity or bounces it cannot express: refused before any work
        if codec_file is not None:
            raise ValueError("codec_file with a glossy transfer: codec comparison is for diffuse transfer; accepted: no codec_file")
    check_choice("light_source", light_source, ["sh", "image"])
    bands = int(transfer.meta["bands"])
    name = light_name or (str(light) if not isinstance(light, torch.Tensor) else "SH tensor")
    L = light if isinstance(light, torch.Tensor) else load_light(light, bands)
    L = torch.as_tensor(L, dtype=torch.float64)
    L = L[None] if L.ndim == 1 else L
    if L.shape[1] != bands * bands:
        raise ValueError(f"light {name!r} has {L.shape[1]} SH coefficients; accepted: {bands * bands} (the transfer's {bands} bands)")
    src_img = None
    if light_source == "sh":
        sh_img = check_expressible(L, name, image_height)
    else:
        try:  # the band-limited light too, when Mitsuba can emit it: the SH truncation figure
            sh_img = check_expressible(L, name, image_height)
        except ValueError:
            sh_img = None
        if isinstance(light, torch.Tensor) or (src_img := _source_image(light, image_height)) is None:
            raise ValueError(f"light_source='image' with light {name!r}: no environment image behind it; accepted: an "
                             "environment file or a built-in environment name, or light_source='sh'")
    codec = None
    if codec_file is not None:
        from . import codecs

        codec = codecs.load(codec_file)
    require_mitsuba()
    if transfer.kind == "glossy":
        rep = validate_glossy(transfer, L, name, sh_img if src_img is None else src_img, mesh=mesh, vertices=vertices, spp=spp,
                              batches=batches, seed=seed, view_deg=view_deg, idx=idx)
        rep["light_source"] = light_source
        return rep
    mesh = transfer.mesh
    if idx is None:
        idx = sample_vertices(mesh, vertices, seed)
    idx = torch.as_tensor(idx, dtype=torch.int64)
    bounces = int(transfer.meta.get("bounces_used", 0))
    eng = engine_parts(transfer, L, idx)
    eps = float(transfer.meta.get("ray_eps", float(transfer.meta.get("offset", 1e-4)) * float(
        np.linalg.norm(mesh.vertices.numpy().max(0) - mesh.vertices.numpy().min(0)))))
    depths = [1] if bounces == 0 else [1, bounces + 1]
    rho = mesh.albedo.to(torch.float64)[idx]
    p, n = mesh.vertices[idx], mesh.normals[idx]
    nudge = boundary_nudge(mesh)[idx]
    mit = mitsuba_exit_radiance(mesh, p, n, sh_img if src_img is None else src_img, depths, spp, batches, eps, seed, rho, nudge)
    m_dir, m_dir_se = mit["radiance"][0], mit["radiance_se"][0]
    if bounces:
        m_tot, m_tot_se = mit["radiance"][1], mit["radiance_se"][1]
        m_int, m_int_se = m_tot - m_dir, mit["diff_se"][1]
    else:
        m_tot, m_tot_se = m_dir, m_dir_se
        m_int, m_int_se = torch.zeros_like(m_dir), torch.zeros_like(m_dir)
    sharp = sharp_vertices(mesh)[idx] >= sharp_deg
    tot_se = (eng["direct_se"] ** 2 + eng["inter_se"] ** 2).sqrt()
    tot_sum_se = None if eng["inter_sum_se"] is None else math.hypot(eng["direct_sum_se"], eng["inter_sum_se"])
    rep: dict[str, Any] = {
        "scene": mesh.name, "vertices": int(idx.numel()), "bounces": bounces, "bands": bands, "light": name,
        "light_source": light_source, "spp": int(spp), "batches": int(batches), "samples": int(transfer.meta.get("samples", 0)),
        "bounce_points": transfer.meta.get("bounce_points"), "sharp_deg": sharp_deg, "sharp_vertices": int(sharp.sum()),
        "mitsuba_variant": VARIANT, "eps": eps,
        "direct": _ratio(eng["direct"], eng["direct_se"], m_dir, m_dir_se, eng["direct_sum_se"]),
        "total": _ratio(eng["total"], tot_se, m_tot, m_tot_se, tot_sum_se),
        "engine_noise": eng["noise"],
        "direct_rms_rel": _rms_rel(eng["direct"], m_dir),
    }
    if bounces:
        rep["inter"] = _ratio(eng["inter"], eng["inter_se"], m_int, m_int_se, eng["inter_sum_se"])
        if bool(sharp.any()) and bool((~sharp).any()):  # both subsets, else 'inter' says it all
            for key, sel in (("inter_sharp", sharp), ("inter_smooth", ~sharp)):
                reps = eng.get("inter_reps")
                sum_se = None if reps is None else float((reps[:, sel] @ _LUMA).sum(1).std())
                rep[key] = _ratio(eng["inter"][sel], eng["inter_se"][sel], m_int[sel], m_int_se[sel], sum_se)
    if codec is not None:
        c, enc = codec
        rows = c.decode(enc).to(torch.float64)
        if rows.shape[0] != mesh.num_vertices:
            raise ValueError(f"codec file {str(codec_file)!r} holds {rows.shape[0]} points; the transfer has {mesh.num_vertices} vertices")
        ce = engine_parts(transfer, L, idx, data=rows[idx], replicas=0)
        rep["codec"] = {"file": str(codec_file), "total": _ratio(ce["total"], tot_se, m_tot, m_tot_se, tot_sum_se)}
        if bounces:
            rep["codec"]["inter"] = _ratio(ce["total"] - eng["direct"], eng["inter_se"], m_int, m_int_se, eng["inter_sum_se"])
    if src_img is not None and sh_img is not None:  # Mitsuba under the band-limited light / under the image
        msh = mitsuba_exit_radiance(mesh, p, n, sh_img, depths, spp, batches, eps, seed, rho, nudge)
        rep["sh_truncation"] = _ratio(msh["radiance"][-1], msh["radiance_se"][-1], m_tot, m_tot_se)
    rep["per_vertex"] = {
        "index": idx.tolist(), "sharp": sharp.tolist(),
        "engine_direct": eng["direct"].tolist(), "engine_inter": eng["inter"].tolist(),
        "mitsuba_direct": m_dir.tolist(), "mitsuba_inter": m_int.tolist(),
        "engine_direct_se": eng["direct_se"].tolist(), "engine_inter_se": eng["inter_se"].tolist(),
        "mitsuba_direct_se": m_dir_se.tolist(), "mitsuba_inter_se": m_int_se.tolist(),
    }
    return rep


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
    out.append(line("direct", rep["direct"]) + f"   rms rel {rep['direct_rms_rel']:.4f}")
    for k, label in (("inter", "interreflected"), ("inter_sharp", "interreflected, sharp"), ("inter_smooth", "interreflected, rest")):
        if k in rep:
            out.append(line(label, rep[k]))
    out.append(line("total", rep["total"]))
    if "codec" in rep:
        out.append(line("codec total", rep["codec"]["total"]))
        if "inter" in rep["codec"]:
            out.append(line("codec interreflected", rep["codec"]["inter"]))
    if "sh_truncation" in rep:
        out.append(line("SH light / image light", rep["sh_truncation"]))
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# glossy exit transfer
# ---------------------------------------------------------------------------------------------

_BSDF_CLASS: Any = None
BSDF_PLUGIN = "prt_engine_brdf"


def _bsdf_class(mi):
    """The Mitsuba BSDF (written in Python, registered once as ``prt_engine_brdf``) that
    evaluates an engine :class:`prt_torch.brdf.BRDF` in a given local frame."""
    global _BSDF_CLASS
    if _BSDF_CLASS is not None:
        return _BSDF_CLASS

    class EngineBRDF(mi.BSDF):
        """f_r of an engine BRDF in the frame ``self.frame`` (rows t, b, n, world), so anisotropic
        models keep the engine's tangent; ``eval`` returns f_r(wi, wo)·cos θ_i (Mitsuba's
        convention: its ``wo`` is the engine's wi, towards the light; its ``si.wi`` is the
        engine's wo, towards the viewer); ``sample`` draws a cosine-weighted direction about
        the shading normal (pdf cos θ/π, positive wherever f_r·cos is), so estimates are
        unbiased whatever the lobe."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags
            self.brdf = None
            self.frame = np.eye(3)

        def _local(self, si, d) -> np.ndarray:
            w = si.to_world(d)
            return self.frame @ np.array([float(w[0]), float(w[1]), float(w[2])])

        def _f_cos(self, si, wo) -> float:
            a, b = self._local(si, wo), self._local(si, si.wi)  # towards the light, towards the viewer
            if a[2] <= 0 or b[2] <= 0:
                return 0.0
            a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
            f = float(self.brdf.eval(torch.from_numpy(a)[None], torch.from_numpy(b)[None]).reshape(-1)[0])
            return f * float(a[2])

        def eval(self, ctx, si, wo, active=True):
            return mi.Color3f(self._f_cos(si, wo))

        def pdf(self, ctx, si, wo, active=True):
            return mi.warp.square_to_cosine_hemisphere_pdf(wo) if float(mi.Frame3f.cos_theta(si.wi)) > 0 else mi.Float(0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            if float(mi.Frame3f.cos_theta(si.wi)) <= 0:
                return bs, mi.Color3f(0.0)
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            pdf = float(mi.warp.square_to_cosine_hemisphere_pdf(wo))
            bs.wo, bs.pdf, bs.eta = wo, pdf, 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = 0
            return bs, mi.Color3f(self._f_cos(si, wo) / pdf if pdf > 0 else 0.0)

        def to_string(self):
            return f"EngineBRDF[{self.brdf!r}]"

    mi.register_bsdf(BSDF_PLUGIN, lambda props: EngineBRDF(props))
    _BSDF_CLASS = EngineBRDF
    return EngineBRDF


def engine_bsdf(brdf: Any, frame: Any):
    """A Mitsuba BSDF object evaluating the engine BRDF ``brdf`` (one material) in the local
    frame ``frame`` ``[3, 3]`` (rows t, b, n in world coordinates)."""
    mi = require_mitsuba()
    _bsdf_class(mi)
    obj = mi.load_dict({"type": BSDF_PLUGIN})
    obj.brdf = brdf
    obj.frame = torch.as_tensor(frame, dtype=torch.float64).numpy()
    return obj


def _frame_transform(mi, frame: np.ndarray, centre: np.ndarray, scale: float):
    m = np.eye(4)
    m[:3, :3] = frame.T * scale  # columns t, b, n: the disk's local x, y, z (normal)
    m[:3, 3] = centre
    return mi.ScalarTransform4f(m.tolist())


def mitsuba_glossy_exit(mesh: Mesh | None, points: Any, frames: Any, views: Any, brdfs: list, image: np.ndarray, spp: int = 1024,
                        batches: int = 8, eps: float = 1e-4, seed: int = 0, nudge: Any = None,
                        max_depth: int = 2, depths: list[int] | None = None) -> dict[str, torch.Tensor]:
    """Mitsuba 3 exit radiance of the engine's BRDF at probe points towards world views.

    Each probe is a one-sided disk (radius ``1e-2·eps``) centred at the engine's ray origin
    p + eps·n (+ eps·nudge), its local frame the vertex frame ``frames[k]`` (rows t, b, n), with
    :func:`engine_bsdf` ``brdfs[k]``; a ``radiancemeter`` at distance eps along ``views[k]``
    looks back at its centre. ``max_depth`` 2: the disk plus one segment to the environment
    (direct light; the mesh only occludes); ``depths`` = [2, B+2] adds B bounces off the mesh
    (one-sided Lambertian, ``mesh.albedo``). Returns ``{'radiance': [P, 3], 'radiance_se': [P, 3]}``
    float64 (standard error of the mean of ``batches`` renders) for ``max_depth``; with ``depths``
    ``[D, P, 3]`` each and ``'diff_se'`` (depth d minus the first, same seeds)."""
    mi = require_mitsuba()
    P = torch.as_tensor(points, dtype=torch.float64).numpy()
    F = torch.as_tensor(frames, dtype=torch.float64).numpy()
    Vw = torch.as_tensor(views, dtype=torch.float64)
    Vw = (Vw / Vw.norm(dim=-1, keepdim=True)).numpy()
    C = offset_origins(P, F[:, 2], eps, None if nudge is None else torch.as_tensor(nudge, dtype=torch.float64).numpy())
    batches = check_int("batches", batches, 2)
    per = max(1, int(spp) // batches)
    radius = max(eps * 1e-2, 1e-7)
    with tempfile.TemporaryDirectory() as tmp:
        scene = _base_scene(mi, image, mesh, Path(tmp))
        for k in range(P.shape[0]):
            scene[f"probe_{k:06d}"] = {"type": "disk", "to_world": _frame_transform(mi, F[k], C[k], radius),
                                       "bsdf": engine_bsdf(brdfs[k], F[k])}
            o = C[k] + eps * Vw[k]
            up = F[k, 0] if abs(float(F[k, 0] @ Vw[k])) < 0.9 else F[k, 1]
            scene[f"sensor_{k:06d}"] = {
                "type": "radiancemeter",
                "to_world": mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(*o), target=mi.ScalarPoint3f(*C[k]),
                                                           up=mi.ScalarVector3f(*up)),
                "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                "sampler": {"type": "independent", "sample_count": per}}
        sc = mi.load_dict(scene)
    sensors = sc.sensors()
    if len(sensors) != P.shape[0]:  # pragma: no cover
        raise RuntimeError("Mitsuba did not keep one sensor per probe")
    ds = [int(max_depth)] if depths is None else [int(d) for d in depths]
    out = np.zeros((len(ds), batches, P.shape[0], 3))
    for di, depth in enumerate(ds):
        integ = mi.load_dict({"type": "path", "max_depth": depth, "rr_depth": 1000})
        for k in range(P.shape[0]):
            for b in range(batches):
                sd = (int(seed) * 7919 + b * 100003 + k * 1009) % (1 << 31)
                out[di, b, k] = np.asarray(mi.render(sc, sensor=k, integrator=integ, spp=per, seed=sd)).reshape(-1)[:3]
    R = torch.from_numpy(out)
    mean, se = R.mean(1), R.std(1, unbiased=True) / math.sqrt(batches)
    if depths is None:
        return {"radiance": mean[0], "radiance_se": se[0]}
    return {"radiance": mean, "radiance_se": se, "diff_se": (R - R[:1]).std(1, unbiased=True) / math.sqrt(batches)}


def glossy_brdf(transfer: Transfer) -> Any:
    """The engine BRDF of a glossy exit transfer, rebuilt from ``meta['brdf']``; ``ValueError``
    naming the model when the validator cannot express it (before any work)."""
    from .brdf import MODELS, make_brdf

    meta = transfer.meta
    if meta.get("quantity", "exit") != "exit":
        raise ValueError(f"glossy transfer quantity {meta.get('quantity')!r}: the validator compares exit radiance; accepted: "
                         "quantity 'exit' (prt precompute --kind glossy, the default)")
    spec = dict(meta.get("brdf") or {})
    model = str(spec.pop("model", None))
    if model not in MODELS:
        raise ValueError(f"glossy transfer BRDF model {model!r}: the validator's Mitsuba BSDF evaluates the engine's own "
                         f"models only; accepted: {sorted(MODELS)}")
    try:
        return make_brdf(model, **spec)
    except ValueError as e:
        raise ValueError(f"glossy transfer BRDF {meta.get('brdf')!r} cannot be rebuilt: {e}") from None


def _view_directions(frames: torch.Tensor, max_deg: float, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-vertex view directions: local (θ uniform in cos over [0, max_deg], φ uniform) and world."""
    g = torch.Generator().manual_seed(int(seed) + 7727)
    k = frames.shape[0]
    cmin = math.cos(math.radians(max_deg))
    ct = 1 - (1 - cmin) * torch.rand(k, generator=g, dtype=torch.float64)
    ph = 2 * math.pi * torch.rand(k, generator=g, dtype=torch.float64)
    st = (1 - ct * ct).clamp_min(0).sqrt()
    vl = torch.stack([st * torch.cos(ph), st * torch.sin(ph), ct], -1)
    return vl, torch.einsum("kij,ki->kj", frames, vl)


def engine_glossy(transfer: Transfer, L: torch.Tensor, idx: torch.Tensor, view_local: torch.Tensor, mesh: Mesh,
                  brdf: Any, dense: int = 1 << 14, replicas: int = 6) -> dict[str, Any]:
    """The engine's glossy exit radiance at vertices ``idx`` towards ``view_local`` and what
    it is made of.

    The stored rows give ``stored`` (:func:`prt_torch.relight.glossy`). The same number is the
    mean over the transfer's direction set {s_k} (seed, samples, ray offset) of the per-ray
    contributions x_k = 4π V_k [n·s_k > 0] h(s_k) L(s_k), h(s) = y_out(v)ᵀ B_p y(F_p s) (the
    SH-projected BRDF at the view): ``recomputed`` (a check that the reading is right). Its
    noise ``se`` ``[k, 3]`` and ``sum_se`` (luminance, summed over vertices: one direction set
    for all vertices, so errors correlate) is the spread of the same estimator over
    ``replicas`` other seeds (B_p reused); with ``replicas=0`` the per-ray standard error
    (an upper bound for stratified sets). On a dense independent set
    (``dense`` directions, traced) the same integral with the BRDF itself in place of h gives
    ``exact`` (no SH truncation; its noise ``exact_se``) and ``truncation`` = mean of
    (h − f_r cos θ_i) — the engine's SH truncation bias at these vertices, visibility included."""
    from .brdf import brdf_matrices
    from .relight import glossy as relight_glossy
    from .transfer.sampling import uniform_sphere

    meta = transfer.meta
    bands, bands_out = int(meta["bands"]), int(meta.get("bands_out", meta["bands"]))
    samples, seed = int(meta.get("samples", 1024)), int(meta.get("seed", 0))
    out_index = torch.as_tensor(meta.get("out_index", list(range(bands_out * bands_out))), dtype=torch.int64)
    L3 = L.expand(3, -1) if L.shape[0] == 1 else L
    rows = transfer.data.to(torch.float64)
    sub = meta.get("vertices")
    pos = idx if sub is None else torch.as_tensor([list(sub).index(int(i)) for i in idx], dtype=torch.int64)
    stored = relight_glossy(rows[pos], L3, view_local, out_index)
    B, mat = brdf_matrices(brdf, bands_out, bands, projection=meta.get("projection") or "least_squares",
                           drop_out=[tuple(d) for d in meta.get("drop_out") or []] or None, rcond=meta.get("rcond_chosen"),
                           window=meta.get("window"))
    mat = mat.expand(mesh.num_vertices) if mat.numel() == 1 else mat
    F = mesh.frames().to(torch.float64)[idx]
    n = F[:, 2]
    p = mesh.vertices.to(torch.float64)[idx]
    nudge = boundary_nudge(mesh)[idx]
    diag = float(np.linalg.norm(mesh.vertices.numpy().max(0) - mesh.vertices.numpy().min(0)))
    eps = float(meta.get("ray_eps", 1e-4 * diag))
    yv = eval_sh(view_local, bands_out, check=False)[:, out_index] * (view_local[:, 2:3] > 0)  # [k, N_r]
    hv = torch.einsum("kr,krj->kj", yv, B.to(torch.float64)[mat[idx]])  # [k, n²]: the projected BRDF at the view
    res = {k: torch.zeros(idx.numel(), 3, dtype=torch.float64) for k in ("recomputed", "se", "exact", "exact_se", "truncation")}
    sets = {"engine": uniform_sphere(samples, seed)[0], "dense": uniform_sphere(int(dense), seed + 999331)[0]}
    for r in range(int(replicas)):  # the precompute's estimator with other seeds: the engine's noise
        sets[f"replica_{r}"] = uniform_sphere(samples, seed + 7919 * (r + 1))[0]
    reps = []
    with RayCaster(mesh, offset=eps / diag) as caster:
        for name, dirs in sets.items():
            Ld = eval_sh(dirs, bands, check=False) @ L3.T  # [N, 3]
            N = dirs.shape[0]
            for k in range(idx.numel()):
                up = torch.nonzero(dirs @ n[k] > 0).flatten()
                o = offset_origins(p[k:k + 1].numpy(), n[k:k + 1].numpy(), caster.eps,
                                   None if nudge is None else nudge[k:k + 1].numpy())
                d = dirs[up].numpy()
                vis = ~caster.trace(np.repeat(o, d.shape[0], 0).astype(np.float32), d.astype(np.float32), "occluded")
                s_loc = dirs[up] @ F[k].T  # local directions F s
                h = eval_sh(s_loc, bands, check=False) @ hv[k]
                w = torch.zeros(N, dtype=torch.float64)
                w[up] = 4 * math.pi * torch.from_numpy(vis.astype(np.float64))
                x_sh = (w * torch.zeros(N, dtype=torch.float64).index_put_((up,), h))[:, None] * Ld  # [N, 3]
                if name == "engine":
                    res["recomputed"][k] = x_sh.mean(0)
                    res["se"][k] = x_sh.std(0) / math.sqrt(N)
                    continue
                if name.startswith("replica"):
                    if k == 0:
                        reps.append(torch.zeros(idx.numel(), 3, dtype=torch.float64))
                    reps[-1][k] = x_sh.mean(0)
                    continue
                b = brdf.select(mat[idx[k]:idx[k] + 1]) if len(brdf.batch_shape) else brdf
                fc = b.cosine_weighted(s_loc, view_local[k].expand_as(s_loc)).reshape(-1)
                x_f = (w * torch.zeros(N, dtype=torch.float64).index_put_((up,), fc))[:, None] * Ld
                res["exact"][k] = x_f.mean(0)
                res["exact_se"][k] = x_f.std(0) / math.sqrt(N)
                res["truncation"][k] = (x_sh - x_f).mean(0)
    res["stored"] = stored
    bounces = int(meta.get("bounces", 0))
    if bounces:  # the stored total also holds B bounces; rerun the precompute's driver per seed (B_p reused)
        from .transfer import RunOptions
        from .transfer.glossy import run_exit_transfer

        def total(sd: int) -> torch.Tensor:
            data, _ = run_exit_transfer("glossy", mesh, B.to(torch.float64), mat, bands, samples, sd, True,
                                        RunOptions(offset=eps / diag), {}, idx, bounces=bounces)
            return relight_glossy(data.to(torch.float64), L3, view_local, out_index)

        res["total_check"] = total(seed)
        tots = [total(seed + 7919 * (r + 1)) for r in range(len(reps))]
        I = torch.stack([t - d for t, d in zip(tots, reps)]) if reps else None
        res["inter"] = stored - res["recomputed"]
        if I is not None:
            res["inter_se"], res["inter_sum_se"] = I.std(0), float((I @ _LUMA).sum(1).std())
    if reps:
        R = torch.stack(reps)  # [replicas, k, 3]
        res["se"] = R.std(0)
        res["sum_se"] = float((R @ _LUMA).sum(1).std())
        res["noise"] = f"engine: std over {len(reps)} replica seeds of the precompute's estimator (B_p reused)"
    else:
        res["sum_se"] = None
        res["noise"] = "engine: per-ray standard error, per vertex in quadrature (an upper bound for stratified sets)"
    return res


def validate_glossy(transfer: Transfer, L: torch.Tensor, name: str, image: np.ndarray, *, mesh: Mesh | None = None,
                    vertices: int = 16, spp: int = 4096, batches: int = 8, seed: int = 0, view_deg: float = 60.0,
                    idx: torch.Tensor | None = None, dense: int = 1 << 14) -> dict[str, Any]:
    """Glossy exit radiance, engine vs Mitsuba (:func:`validate` for kind 'glossy'): direct, and
    with bounces B > 0 interreflected (Mitsuba max_depth B+2 minus 2, mesh at its luminance
    albedo) and total.

    ``mesh``: the full mesh when the transfer holds a vertex subset (``vertices=`` in
    :func:`prt_torch.transfer.precompute_glossy`; its content hash must match). Views: one per
    vertex, within ``view_deg`` of the normal. The report's ``direct`` is the stored SH
    transfer against Mitsuba; ``direct_unprojected`` the engine's rays with the BRDF itself
    (no SH truncation) against Mitsuba — 1 within noise when visibility, frames, BRDF and light
    agree; ``sh_truncation`` the engine's truncation bias relative to Mitsuba, so
    ``direct`` − 1 ≈ ``sh_truncation`` ± noise."""
    import dataclasses

    brdf = glossy_brdf(transfer)
    meta = transfer.meta
    bounces = int(meta.get("bounces", 0))
    if meta.get("vertices") is not None:
        want = transfer.mesh.meta.get("subset_of")
        if mesh is None or mesh.content_hash() != want:
            raise ValueError("this glossy transfer holds a vertex subset (no faces to trace); accepted: pass mesh= the full "
                             "mesh it was computed on (same content hash)")
        pool = torch.as_tensor(meta["vertices"], dtype=torch.int64)
    else:
        mesh = transfer.mesh
        pool = torch.arange(mesh.num_vertices)
    if idx is None and pool.numel() == mesh.num_vertices:
        idx = sample_vertices(mesh, vertices, seed)
    elif idx is None:
        g = torch.Generator().manual_seed(int(seed) + 104729)
        idx = pool[torch.randperm(pool.numel(), generator=g)[: min(check_int("vertices", vertices, 1), pool.numel())]].sort().values
    idx = torch.as_tensor(idx, dtype=torch.int64)
    F = mesh.frames().to(torch.float64)[idx]
    vl, vw = _view_directions(F, view_deg, seed)
    eng = engine_glossy(transfer, L, idx, vl, mesh, brdf, dense)
    eps = float(meta.get("ray_eps", 1e-4 * float(np.linalg.norm(mesh.vertices.numpy().max(0) - mesh.vertices.numpy().min(0)))))
    brdfs = [brdf.select(torch.tensor([int(i)])) if len(brdf.batch_shape) else brdf for i in idx]
    # the engine's reflectors are grey (luminance albedo: one glossy matrix for all channels)
    grey = dataclasses.replace(mesh, albedo=(mesh.albedo.to(torch.float64) @ _LUMA)[:, None].expand(-1, 3).contiguous())
    mit = mitsuba_glossy_exit(grey, mesh.vertices[idx], F, vw, brdfs, image, spp, batches, eps, seed, boundary_nudge(mesh)[idx],
                              depths=[2, bounces + 2] if bounces else [2])
    m, m_se = mit["radiance"][0], mit["radiance_se"][0]
    lum = lambda x: float((x @ _LUMA).sum())  # noqa: E731
    M = lum(m)
    rep = {
        "kind": "glossy", "scene": mesh.name, "vertices": int(idx.numel()), "bounces": bounces, "bands": int(meta["bands"]),
        "bands_out": int(meta.get("bands_out", meta["bands"])), "brdf": meta.get("brdf"), "projection": meta.get("projection"),
        "light": name, "spp": int(spp), "batches": int(batches), "samples": int(meta.get("samples", 0)), "view_deg": view_deg,
        "mitsuba_variant": VARIANT, "eps": eps, "dense": int(dense),
        "direct": _ratio(eng["recomputed"] if bounces else eng["stored"], eng["se"], m, m_se, eng["sum_se"]),
        "direct_unprojected": _ratio(eng["exact"], eng["exact_se"], m, m_se),
        "sh_truncation": lum(eng["truncation"]) / M if M > 0 else float("nan"),
        "recomputed_rel": float(((eng["total_check"] if bounces else eng["recomputed"]) - eng["stored"]).abs().max()
                                / eng["stored"].abs().max().clamp_min(1e-300)),
        "direct_rms_rel": _rms_rel(eng["recomputed"] if bounces else eng["stored"], m),
        "engine_noise": eng["noise"],
    }
    if bounces:
        m_int, m_int_se = mit["radiance"][1] - m, mit["diff_se"][1]
        e_int_se, e_int_sum = eng.get("inter_se", torch.zeros_like(m)), eng.get("inter_sum_se")
        rep["inter"] = _ratio(eng["inter"], e_int_se, m_int, m_int_se, e_int_sum)
        tot_sum = None if e_int_sum is None or eng["sum_se"] is None else math.hypot(eng["sum_se"], e_int_sum)
        rep["total"] = _ratio(eng["stored"], (eng["se"] ** 2 + e_int_se ** 2).sqrt(), mit["radiance"][1], mit["radiance_se"][1], tot_sum)
        rep["per_vertex"] = {"engine_inter": eng["inter"].tolist(), "mitsuba_inter": m_int.tolist()}
    rep.setdefault("per_vertex", {}).update({"index": idx.tolist(), "view_local": vl.tolist(), "engine": eng["stored"].tolist(),
                         "engine_se": eng["se"].tolist(), "engine_unprojected": eng["exact"].tolist(),
                         "truncation": eng["truncation"].tolist(), "mitsuba": m.tolist(), "mitsuba_se": m_se.tolist()})
    return rep
