"""Diffuse transfer vectors: unshadowed (analytic), shadowed (Monte Carlo), interreflected.

Normalisation (used everywhere in prt_torch): the diffuse transfer vector t_p maps the SH light
vector l (radiance, ``[C, n²]``) to *exit radiance* at p by a dot product,

    L_out(p) = Σ_i t_{p,i} l_i,        t_{p,i} = (ρ_p/π) ∫ V(p,s) max(n_p·s, 0) y_i(s) ds

(Sloan, Kautz & Snyder 2002; course notes 2005, "Diffuse PRT", t⁰_{p,i}). Here s is the
direction *towards* the light. A constant white environment of radiance 1 has l_00 = 2√π and
gives L_out = ρ on an unoccluded vertex: t_00 = (ρ/π) · π · Y_00 = ρ/(2√π).

* Unshadowed: t = (ρ/π) · rotate_zonal(h, n) with h_l the clamped-cosine zonal coefficients
  (Ramamoorthi 2002 eq. 4.11: f_lm = Λ_l h_l y_lm(n) = A_l y_lm(n)) — exact, no rays.
* Shadowed: Monte Carlo over a stratified direction set (course notes 2005,
  "Precomputation"): t = (4π/N)(ρ/π) Σ_j V(p,s_j) max(n·s_j,0) y(s_j), evaluated for a chunk of
  vertices as one masked GEMM W[k,N] @ Y[N,n²]; or with cosine-weighted hemisphere samples
  t = (ρ/N) Σ_j V(p,s_j) y(s_j).
* Interreflection, bounce b (course notes 2005, "Precomputation – Interreflections"):
  t^b_p = (ρ_p/π) ∫ t^{b-1}_{q(s)} (1 − V(p,s)) max(n_p·s, 0) ds, with t^{b-1} at the first hit
  q(s) interpolated from its triangle's vertices by barycentrics; t = Σ_b t^b. All bounces reuse
  the hits of the shadow pass: they form a sparse matrix S [V,V] (S_pq = Σ_j w_j β_q(hit_j)), so
  bounce b is one sparse product t̃^b = S (ρ ⊙ t̃^{b-1}). Hits on the back of a triangle
  (the ray arrives from behind it) contribute nothing (one-sided surfaces are black behind).

Internally ρ_p is kept out (t̃ = t/ρ_p per channel, exact: the bounce uses ρ_q of the *hit*
vertices). A grey scene needs one channel; coloured albedo with bounces needs three (colour
bleeding). The stored data is ``[V, n²]`` with ``meta['albedo_folded'] = False`` (multiply
by ``mesh.albedo`` at run time), or ``[V, 3, n²]`` with the albedo folded in.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import scipy.sparse
import torch

from .._checks import check_choice, check_float, check_int
from ..scene import Mesh, RayCaster, default_workers
from ..sh import clamped_cosine, eval_sh, rotate_zonal
from .base import RunOptions, Transfer
from .sampling import cosine_hemisphere, to_world, uniform_sphere

__all__ = [
    "unshadowed_transfer",
    "transfer_at_points",
    "precompute_diffuse",
    "probe_self_occlusion",
    "DiffuseSampler",
    "MAX_DIFFUSE_BANDS",
    "MAX_SAMPLES",
]

MAX_DIFFUSE_BANDS = 32
MAX_SAMPLES = 1 << 20
MAX_BOUNCES = 64


def unshadowed_transfer(normals: torch.Tensor, bands: int, albedo: torch.Tensor | None = None) -> torch.Tensor:
    """Analytic unshadowed diffuse transfer (no rays).

    t_p = (ρ_p/π) Λ_l h_l y_lm(n_p) with h the clamped cosine (Ramamoorthi 2002 eq. 4.11,
    A_l = Λ_l h_l); Sloan 2002's unshadowed transfer.

    Args:
        normals: ``[V,3]`` unit normals (float32/64).
        bands: SH bands n (n² coefficients).
        albedo: optional ``[V]`` or ``[V,C]`` reflectance; None means ρ = 1.
    Returns:
        ``[V, n²]`` (or ``[V, C, n²]`` with a ``[V,C]`` albedo), dtype of ``normals``.
    """
    bands = check_int("bands", bands, 1, MAX_DIFFUSE_BANDS)
    t = rotate_zonal(clamped_cosine(bands) / math.pi, normals)
    if albedo is None:
        return t
    a = albedo.to(t.dtype)
    return t * a[:, None] if a.ndim == 1 else a[:, :, None] * t[:, None, :]


class DiffuseSampler:
    """The direction set of one run, with SH values evaluated once where they are shared."""

    def __init__(self, bands: int, samples: int, seed: int, sampling: str):
        self.bands, self.samples, self.sampling = bands, samples, sampling
        if sampling == "uniform":
            self.dirs, _ = uniform_sphere(samples, seed)  # [N,3] float64, weights 4π/N
            self.Y = eval_sh(self.dirs, bands)  # [N, n²], shared by every vertex
            self.weight = 4.0 / samples  # (4π/N)·(1/π)
            self.dirs32 = np.ascontiguousarray(self.dirs.numpy(), np.float32)
        else:
            self.dirs = cosine_hemisphere(samples, seed)  # local frame
            self.Y = None
            self.weight = 1.0 / samples

    def rays(self, points: torch.Tensor, normals: torch.Tensor, frames: torch.Tensor | None, eps: float):
        """Ray set of a chunk of k vertices (numpy, ready for Embree).

        Returns ``(i [R] vertex index, j [R] sample index, origins float32 [R,3],
        dirs float32 [R,3], cos)`` with origins offset by ``eps`` along the normal. For uniform
        sampling only directions above the tangent plane are traced and ``cos`` is the
        ``[k,N]`` matrix max(n·s, 0); for cosine sampling ``cos`` is None and dirs are per vertex.
        """
        o_v = (points + eps * normals).numpy().astype(np.float32)  # [k,3] offset origins
        if self.sampling == "uniform":
            cos = (normals @ self.dirs.T).numpy()  # [k,N] float64
            up = cos > 0
            i, j = np.nonzero(up)  # row-major: rays grouped by vertex
            o = np.repeat(o_v, up.sum(1), axis=0)  # == o_v[i], without a gather
            return i, j, o, np.take(self.dirs32, j, axis=0), np.maximum(cos, 0.0, out=cos)
        k = normals.shape[0]
        world = to_world(self.dirs, frames).reshape(-1, 3).numpy()  # [k·N,3]
        i = np.repeat(np.arange(k), self.samples)
        j = np.tile(np.arange(self.samples), k)
        return i, j, o_v[i], world, None


def _check_points(points: Any, normals: Any) -> tuple[torch.Tensor, torch.Tensor]:
    p = torch.as_tensor(points, dtype=torch.float64)
    n = torch.as_tensor(normals, dtype=torch.float64)
    if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
        raise ValueError(f"points {tuple(p.shape)} and normals {tuple(n.shape)}; accepted: equal shapes [P, 3]")
    if not (torch.isfinite(p).all() and torch.isfinite(n).all()):
        raise ValueError("points/normals hold NaN or Inf; accepted: finite values")
    return p, n / n.norm(dim=-1, keepdim=True)


def _chunk(caster: RayCaster, sampler: DiffuseSampler, points: torch.Tensor, normals: torch.Tensor,
           frames: torch.Tensor | None, faces: np.ndarray | None, face_normals: np.ndarray | None,
           n_vertices: int, record_hits: bool) -> dict[str, torch.Tensor]:
    """Shadowed transfer (ρ = 1) of a chunk of k points, and (optionally) its bounce entries.

    Uniform sampling: T = (4/N) · (V ⊙ max(n·s,0)) @ Y — one masked GEMM per chunk
    (course notes 2005, "Precomputation"). Cosine sampling: T = (1/N) Σ_j V y(s_j).
    """
    k = points.shape[0]
    i, j, o, d, cos = sampler.rays(points, normals, frames, caster.eps)
    if record_hits:
        prim, bu, bv, _ = caster.trace(o, d, "intersect")
        hit = prim != -1
    else:
        hit = caster.trace(o, d, "occluded")
    out: dict[str, torch.Tensor] = {"rays": torch.tensor([i.shape[0]], dtype=torch.int64)}
    if sampler.sampling == "uniform":
        W = cos * sampler.weight  # [k,N]; zero below the horizon
        W[i[hit], j[hit]] = 0.0  # blocked directions
        out["T"] = torch.from_numpy(W) @ sampler.Y  # one GEMM per chunk
        w_ray = W.dtype.type(sampler.weight) * cos[i, j] if record_hits else None
    else:
        vis = ~hit
        Y = eval_sh(torch.from_numpy(d[vis]).to(torch.float64), sampler.bands, check=False)  # per-vertex directions
        out["T"] = torch.zeros(k, Y.shape[1], dtype=torch.float64).index_add_(0, torch.from_numpy(i[vis]), Y * sampler.weight)
        w_ray = np.full(i.shape[0], sampler.weight) if record_hits else None
    if record_hits:
        h = np.nonzero(hit)[0]
        tri = prim[h].astype(np.int64)
        dh = d[h].astype(np.float64)
        front = np.einsum("ij,ij->i", face_normals[tri], dh) < 0  # the ray meets the front of the triangle
        h, tri = h[front], tri[front]
        u, v = bu[h].astype(np.float64), bv[h].astype(np.float64)
        beta = np.stack([1 - u - v, u, v], 1)  # [h,3] barycentric weights of faces[tri]
        rows = np.repeat(i[h], 3)
        cols = faces[tri].reshape(-1)
        vals = (w_ray[h][:, None] * beta).reshape(-1)
        # this chunk's rows of S [V,V] in CSR form, duplicates summed (scipy's C++ conversion)
        S = scipy.sparse.coo_matrix((vals, (rows, cols)), shape=(k, n_vertices)).tocsr()
        S.sum_duplicates()
        out["S_indptr"] = torch.from_numpy(S.indptr.astype(np.int64))
        out["S_indices"] = torch.from_numpy(S.indices.astype(np.int32))
        out["S_data"] = torch.from_numpy(S.data.astype(np.float64))
    return out


def transfer_at_points(caster: RayCaster, points: Any, normals: Any, bands: int, samples: int, seed: int = 0,
                       sampling: str = "uniform") -> torch.Tensor:
    """Shadowed diffuse transfer (ρ = 1, no interreflection) at arbitrary surface points.

    Args:
        caster: ``RayCaster`` of the occluding geometry.
        points, normals: ``[P,3]``.
    Returns:
        ``[P, n²] float64`` — course notes 2005 t⁰ with ρ = 1 (Monte Carlo, see module docstring).
    """
    bands = check_int("bands", bands, 1, MAX_DIFFUSE_BANDS)
    samples = check_int("samples", samples, 1, MAX_SAMPLES)
    check_choice("sampling", sampling, ["uniform", "cosine"])
    p, n = _check_points(points, normals)
    from ..scene.mesh import tangent_frames

    frames = None
    if sampling == "cosine":
        t, b = tangent_frames(n.numpy())
        frames = torch.stack([torch.from_numpy(t), torch.from_numpy(b), n], dim=-2)
    return _chunk(caster, DiffuseSampler(bands, samples, seed, sampling), p, n, frames, None, None, 0, False)["T"]


def probe_self_occlusion(caster: RayCaster, mesh: Mesh, seed: int = 0, vertices: int = 1024,
                         directions: int = 64) -> dict[str, Any]:
    """Estimate how much the scene shadows itself from a sample of vertices and directions.

    Returns ``{'rays', 'occluded_rays', 'occluded_fraction'}`` where the fraction is
    cosine-weighted (Σ V̄ cos / Σ cos over the probe rays): the share of unshadowed diffuse energy
    that shadowing would remove at the probed vertices. On a convex mesh only grazing rays
    clipped by the tessellation are hit, a fraction of order (facet angle)².
    """
    V = mesh.num_vertices
    g = torch.Generator().manual_seed(int(seed) + 7919)
    idx = torch.randperm(V, generator=g)[: min(V, vertices)]
    dirs, _ = uniform_sphere(directions, seed + 1)
    n = mesh.normals[idx]
    cos = n @ dirs.T
    i, j = torch.nonzero(cos > 0, as_tuple=True)
    occ = caster.occluded(mesh.vertices[idx][i], dirs[j], normals=n[i])
    c = cos[i, j]
    frac = float((c * occ).sum() / c.sum().clamp_min(1e-300))
    return {"rays": int(i.shape[0]), "occluded_rays": int(occ.sum()), "occluded_fraction": frac}


def precompute_diffuse(
    mesh: Mesh,
    bands: int = 5,
    samples: int = 1024,
    bounces: int = 0,
    seed: int = 0,
    *,
    sampling: str = "uniform",
    shadows: str = "auto",
    fold_albedo: bool | None = None,
    bounce_tol: float = 1e-3,
    probe_tol: float = 1e-3,
    run: RunOptions | None = None,
) -> Transfer:
    """Diffuse PRT transfer vectors for every vertex of ``mesh`` (see module docstring).

    Args:
        mesh: the scene (vertices, normals, frames, albedo).
        bands: SH bands n in [1, 32] (n² coefficients).
        samples: Monte Carlo directions N in [1, 2²⁰] per vertex (uniform: over the sphere, about
            half of them traced; cosine: over the hemisphere).
        bounces: interreflection bounces B in [0, 64] after the direct (shadowed) pass.
        seed: direction-set seed; the same seed gives the same result.
        sampling: 'uniform' (one global stratified set, SH evaluated once) or 'cosine'
            (stratified cosine-weighted hemisphere per vertex frame).
        shadows: 'auto' (probe; trace only if shadowing removes more than ``probe_tol`` of the
            energy), 'always', or 'never' (unshadowed analytic transfer, no interreflection).
        fold_albedo: None = fold only when needed (coloured albedo with interreflection),
            True = always ``[V,3,n²]``, False = always ``[V,n²]`` (refused if colour bleeds).
        bounce_tol: stop adding bounces once one adds less than this fraction of the
            accumulated transfer's norm (the bounce is kept).
        run: how it runs (:class:`RunOptions`: chunks — default ~2²⁰ traced rays each —,
            workers, ray offset, resumable state, progress).
    Returns:
        ``Transfer(kind='diffuse')`` with ``data`` float32 ``[V,n²]`` or ``[V,3,n²]`` and ``meta``
        recording every choice (shadows traced, probe, bounces used and their energy, albedo folding).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a prt_torch.scene.Mesh, got {type(mesh).__name__}")
    run = RunOptions() if run is None else run
    bands = check_int("bands", bands, 1, MAX_DIFFUSE_BANDS)
    samples = check_int("samples", samples, 1, MAX_SAMPLES)
    bounces = check_int("bounces", bounces, 0, MAX_BOUNCES)
    seed = check_int("seed", seed, 0, 2**63 - 1)
    check_choice("sampling", sampling, ["uniform", "cosine"])
    check_choice("shadows", shadows, ["auto", "always", "never"])
    check_choice("fold_albedo", fold_albedo, [None, True, False])
    bounce_tol = check_float("bounce_tol", bounce_tol, 0.0, 1.0, hi_open=True)
    probe_tol = check_float("probe_tol", probe_tol, 0.0, 1.0, hi_open=True)
    t_start = time.perf_counter()
    if fold_albedo is False and bounces > 0 and not mesh.is_grey():
        raise ValueError("fold_albedo=False with coloured albedo and bounces > 0: interreflection bleeds colour, so the albedo "
                         "cannot be kept separate; accepted: fold_albedo=None/True, or bounces=0, or a grey albedo")
    meta: dict[str, Any] = {
        "bands": bands, "samples": samples, "seed": seed, "sampling": sampling, "bounces_requested": bounces,
        "bounce_tol": bounce_tol, "shadows": shadows, "offset": run.offset,
        "normalisation": "exit radiance L_out[v,c] = sum_i data[v,(c),i] * l[c,i] (times mesh.albedo[v,c] when "
                         "albedo_folded is false); t = (rho/pi) int V max(n.s,0) y(s) ds; constant radiance 1 -> l00 = 2 sqrt(pi)",
        "sh_convention": "real SH, graphics convention, no Condon-Shortley phase, index l(l+1)+m",
    }
    caster = None
    try:
        if shadows != "never":
            caster = RayCaster(mesh, workers=_workers(run, mesh, samples, sampling), offset=run.offset)
            meta["ray_eps"] = caster.eps
        traced = _decide_shadows(caster, mesh, shadows, seed, probe_tol, meta)
        if traced:
            T0, S = _trace_direct(caster, mesh, bands, samples, seed, sampling, bounces > 0, run, meta)
        else:
            T0, S = unshadowed_transfer(mesh.normals, bands), None  # [V, n²] float64, exact
            meta["rays_traced"] = 0
        total, C = _interreflect(T0, S, mesh, bounces, bounce_tol, meta)
        data = _store_albedo(total, mesh, C, fold_albedo, meta)
        meta["seconds"] = time.perf_counter() - t_start
        meta["rays_per_second"] = meta["rays_traced"] / meta["seconds"] if meta["rays_traced"] else 0.0
        meta["workers"] = caster.workers if caster is not None else 1
        tr = Transfer(kind="diffuse", data=data.to(torch.float32).contiguous(), mesh=mesh, meta=meta)
    finally:
        if caster is not None:
            caster.close()
    run.finish()
    return tr


def _workers(run: RunOptions, mesh: Mesh, samples: int, sampling: str) -> int:
    """``run.workers``, or (None) all cores when the run traces ≥ 4M rays: processes pay off
    only for long runs (pool start ~0.5 s)."""
    if run.workers is not None:
        return run.workers
    est = mesh.num_vertices * (samples // 2 if sampling == "uniform" else samples)
    return default_workers() if est >= 4_000_000 else 1


def _decide_shadows(caster: RayCaster | None, mesh: Mesh, shadows: str, seed: int, probe_tol: float, meta: dict) -> bool:
    """Step 1: trace shadow rays or not ('auto' probes the self-occlusion). Records the decision."""
    if shadows == "never":
        meta["shadow_decision"] = "shadows='never': analytic unshadowed transfer, no bounces"
        traced = False
    elif shadows == "always":
        meta["shadow_decision"] = "shadows='always': tracing shadow rays"
        traced = True
    else:
        probe = probe_self_occlusion(caster, mesh, seed)
        meta["probe"] = probe
        traced = probe["occluded_fraction"] > probe_tol
        meta["shadow_decision"] = (f"probe: shadowing removes {probe['occluded_fraction']:.3g} of the energy "
                                   f"({'>' if traced else '<='} probe_tol={probe_tol:g}); "
                                   + ("tracing shadow rays" if traced else "no self-occlusion: analytic unshadowed transfer, no bounces"))
    meta["shadows_traced"] = traced
    return traced


def _trace_direct(caster: RayCaster, mesh: Mesh, bands: int, samples: int, seed: int, sampling: str,
                  record_hits: bool, run: RunOptions, meta: dict) -> tuple[torch.Tensor, Any]:
    """Step 2: shadowed transfer t⁰ ``[V, n²]`` float64 over resumable chunks, and (when
    ``record_hits``) the bounce matrix S ``[V, V]`` (scipy CSR) of the same rays."""
    V = mesh.num_vertices
    sampler = DiffuseSampler(bands, samples, seed, sampling)
    rays_per_vertex = samples // 2 if sampling == "uniform" else samples
    chunk_size = check_int("chunk_size", run.chunks(int(min(max(16, (1 << 20) // max(1, rays_per_vertex)), 16384))), 1)
    frames = mesh.frames() if sampling == "cosine" else None
    faces_np = mesh.faces.numpy()
    tri = mesh.vertices.numpy()[faces_np]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # geometric face normals (winding)

    def compute(a: int, b: int) -> dict[str, torch.Tensor]:
        return _chunk(caster, sampler, mesh.vertices[a:b], mesh.normals[a:b],
                      None if frames is None else frames[a:b], faces_np, fn, V, record_hits)

    fingerprint = {"mesh_hash": mesh.content_hash(), "bands": bands, "samples": samples, "seed": seed,
                   "sampling": sampling, "record_hits": record_hits, "offset": run.offset, "kind": "diffuse"}
    parts = run.run_chunks(V, chunk_size, compute, fingerprint=fingerprint, desc=f"diffuse {mesh.name}",
                           rays_of=lambda r: int(r["rays"].sum()))
    T0 = torch.cat([p["T"] for p in parts]).to(torch.float64)
    meta["rays_traced"] = int(sum(int(p["rays"].sum()) for p in parts))
    meta["chunk_size"] = chunk_size
    if not record_hits:
        return T0, None
    S = scipy.sparse.vstack([
        scipy.sparse.csr_matrix((p["S_data"].numpy(), p["S_indices"].numpy(), p["S_indptr"].numpy()),
                                shape=(p["T"].shape[0], V)) for p in parts], format="csr")
    meta["bounce_matrix_nnz"] = int(S.nnz)
    return T0, S


def _interreflect(T0: torch.Tensor, S: Any, mesh: Mesh, bounces: int, bounce_tol: float, meta: dict) -> tuple[torch.Tensor, int]:
    """Step 3: t = Σ_b t̃^b with t̃^b = S (ρ ⊙ t̃^{b-1}) (course notes 2005, "Interreflections"),
    ρ_p kept out. Returns (``[V, C, n²]`` float64, C) with C = 3 only for coloured bounces."""
    V, n2 = T0.shape
    rho = mesh.albedo.to(torch.float64)
    C = 1 if (mesh.is_grey() or S is None) else 3
    rho_c = rho[:, :1] if C == 1 else rho  # [V,C]
    tb = T0[:, None, :].expand(V, C, n2).clone()  # t̃⁰ (ρ_p kept out)
    total = tb.clone()
    energy = []
    used = 0
    if S is not None:
        for b in range(1, bounces + 1):  # a loop over bounces: each one sparse product over all vertices
            x = (rho_c[:, :, None] * tb).reshape(V, C * n2)
            tb = torch.from_numpy(S @ x.numpy()).reshape(V, C, n2)
            total += tb
            used = b
            frac = float(tb.norm() / total.norm().clamp_min(1e-300))
            energy.append(frac)
            if frac < bounce_tol:
                break
    meta["bounces_used"] = used
    meta["bounce_energy_fraction"] = energy
    if bounces > 0 and S is None:
        meta["bounce_decision"] = "no interreflection: shadow rays were not traced (no occluding geometry)"
    elif bounces > 0:
        meta["bounce_decision"] = (f"stopped after {used} of {bounces} bounces"
                                   + (f" (bounce {used} added {energy[-1]:.3g} < bounce_tol)" if used < bounces else ""))
    return total, C


def _store_albedo(total: torch.Tensor, mesh: Mesh, C: int, fold_albedo: bool | None, meta: dict) -> torch.Tensor:
    """Step 4: ``[V, 3, n²]`` with the albedo folded in, or ``[V, n²]`` without (module docstring)."""
    fold = (C == 3) if fold_albedo is None else bool(fold_albedo)
    meta["albedo_folded"] = fold
    meta["channels"] = 3 if fold else 1
    if fold:
        V, _, n2 = total.shape
        return mesh.albedo.to(torch.float64)[:, :, None] * total.expand(V, 3, n2)
    return total[:, 0, :]
