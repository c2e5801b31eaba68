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
    scene: dict[str, Any] = {"type": "scene", "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(image, np.float32))}}
    radius = max(eps * 1e-2, 1e-7)
    with tempfile.TemporaryDirectory() as tmp:
        if mesh is not None:
            ply = Path(tmp) / "mesh.ply"
            _write_ply(ply, mesh)
            scene["mesh"] = {"type": "ply", "filename": str(ply), "face_normals": True,
                             "bsdf": {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}}
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
             sharp_deg: float = 18.0, image_height: int = 128, idx: torch.Tensor | None = None) -> dict[str, Any]:
    """Engine vs Mitsuba 3 at ``vertices`` sampled vertices (module docstring); no scale fit.

    Args:
        transfer: a diffuse :class:`Transfer` or its file.
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
    if transfer.kind != "diffuse":
        raise ValueError(f"transfer kind {transfer.kind!r}: the validator expresses diffuse (Lambertian) transfer only so far; "
                         "accepted: a diffuse transfer (prt precompute --kind diffuse)")
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
