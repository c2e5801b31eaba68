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
  t^b_p = (ρ_p/π) ∫ ρ_q t^{b-1}_{q(s)} (1 − V(p,s)) max(n_p·s, 0) ds with q(s) the first hit;
  t = Σ_b t^b. The hit's t^{b-1}_q is taken (``bounce_points``) at the hit point itself over the
  hit face's hemisphere (default 'hits': ``hit_samples`` rays from each hit, :class:`HitBounce`;
  the hit's own deeper bounces read face-centroid tables x_f, themselves bounced by a sparse
  face-to-face matrix), or — kept for comparison — from face-centroid tables ('faces'), the
  face's corners ('corners'), or the course notes' interpolation of the hit triangle's *vertex*
  values ('vertices': a sparse S [V,V], S_pq = Σ_j w_j β_q(hit_j), t̃^b = S (ρ ⊙ t̃^{b-1})). A
  vertex value is an integral over the vertex normal's hemisphere, which differs from the hit
  face's where the faces tilt away from the vertex normal: checked against Mitsuba 3
  (docs/validate.md) the 'vertices' interpolation runs high there. Hits on the back of a
  triangle (the ray arrives from behind it) contribute nothing (one-sided surfaces are black
  behind). Every tracer offsets ray origins by :func:`offset_origins`.

Internally ρ_p is kept out (t̃ = t/ρ_p per channel, exact: the bounce uses ρ_q of the *hit*
vertices). A grey scene needs one channel; coloured albedo with bounces needs three (colour
bleeding). The stored data is ``[V, n²]`` with ``meta['albedo_folded'] = False`` (multiply
by ``mesh.albedo`` at run time), or ``[V, 3, n²]`` with the albedo folded in.
"""
from __future__ import annotations

import math
import os
import time
from typing import Any

import numpy as np
import torch

from .._checks import check_choice, check_float, check_int
from ..executor import torch_threads
from ..scene import Mesh, RayCaster, default_workers, edge_face_counts
from ..sh import clamped_cosine, eval_sh, rotate_zonal
from .base import RunOptions, Transfer, remove_state, run_chunks
from .ray_kernels import guided_rays_native, luma_mix, qmc_rays_native, select_rays, sh_accumulate, upper_rays
from .sampling import cosine_hemisphere, to_world, uniform_sphere

__all__ = [
    "unshadowed_transfer",
    "transfer_at_points",
    "precompute_diffuse",
    "face_points",
    "face_transfer",
    "boundary_nudge",
    "vertex_transfer",
    "hit_bounce",
    "HitBounce",
    "record_probe_log",
    "probe_fingerprint",
    "FIRST_PROBE_RAYS",
    "offset_origins",
    "hit_ray_eps",
    "HIT_OFFSET",
    "HIT_SAMPLES_AUTO",
    "probe_self_occlusion",
    "DiffuseSampler",
    "MAX_DIFFUSE_BANDS",
    "MAX_SAMPLES",
    "SAMPLINGS",
    "ESTIMATORS",
    "qmc_rays",
    "held_bytes_per_vertex",
]

MAX_DIFFUSE_BANDS = 32
MAX_SAMPLES = 1 << 20
MAX_BOUNCES = 64
SAMPLINGS = ("qmc", "uniform", "cosine")
ESTIMATORS = ("auto", "control", "plain")
#: the cells of the hit rays' guide (:meth:`HitBounce.face_openness`): rings × sectors of Malley's
#: square (a = sin²θ, b = φ/2π), each of equal cosine-weighted solid angle; one probe ray per cell
GUIDE_GRID = (4, 8)
#: rays per face of :meth:`HitBounce.face_openness` (the bounce estimator's per-hit choice under
#: 'auto' and its guide): one jittered ray per cell of :data:`GUIDE_GRID`
FACE_PROBE_RAYS = GUIDE_GRID[0] * GUIDE_GRID[1]
#: rays per probed curved face HitBounce accepts (``probe_rays``): every cell, every 2nd, every 4th
PROBE_RAYS_CHOICES = (FACE_PROBE_RAYS, FACE_PROBE_RAYS // 2, FACE_PROBE_RAYS // 4)
#: a run's first probe rays per face (``HitBounce(probe_rays=)``, :meth:`HitBounce._probe`): a stratified
#: quarter of the cells. A face that cannot be guided (curved: fewer than GUIDE_MIN_FACES coplanar faces) stops
#: there — its probe only chooses between the plain sum and the control variate, which a quarter of the cells
#: does as well; so does a flat face whose first rays all left (read open); the other flat faces go on to every
#: cell (their guide pools them). One-bounce error unchanged to 3 digits, up to 60% fewer rays per vertex at
#: N = 64-1024 (4 seeds; reports/benchmarks/face_probe.md, docs/precompute_log.md, "The face probe where it pays")
FIRST_PROBE_RAYS = FACE_PROBE_RAYS // 4
#: a face's guide pools the probes of the coplanar faces among its GUIDE_POOL nearest centroids; it
#: is used only where at least GUIDE_MIN_FACES of them are coplanar (a flat region: their cells are
#: the same directions); the uniform share of the guided density (Hesterberg 1995's defensive mixture)
GUIDE_POOL, GUIDE_MIN_FACES, GUIDE_UNIFORM = 32, 8, 0.3
FACE_PROBE_STREAM = 1 << 21  # its hash streams, apart from the vertices' (1 << 20) and the hits' (1, 2, ...)
#: default offset of the rays leaving a bounce hit point, as a fraction of the bounding-box
#: diagonal (issue 37; :func:`hit_ray_eps`). The vertices' own offset (``RunOptions.offset``,
#: 1e-4) defines where a vertex's hemisphere is seen from and stays.
HIT_OFFSET = 1e-6
#: the floor of that offset in float32 ulps of the largest coordinate (Embree traces float32)
HIT_OFFSET_ULPS = 16
#: ``hit_samples='auto'`` (the default): rays per first hit by estimator. Under 'auto' (the guided
#: hits) 4: a vertex's first hits share its stratification and average over hundreds of hits, so
#: their rays buy less error than the vertices' own — Cornell box (grey 0.8, one bounce, N = 1024,
#: 4 seeds; benchmarks/bench_bounce_parts.py) 4 per hit 0.0289 at 2212 rays per vertex against 8 per
#: hit 0.0249 at 3856: 0.34× / 0.47× the error of uniform + plain at equal rays. 'control' and
#: 'plain' keep 8 (the estimators before: their numbers unchanged).
HIT_SAMPLES_AUTO = {"auto": 4, "control": 8, "plain": 8}


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


def boundary_nudge(mesh: Mesh) -> torch.Tensor:
    """``[V,3]`` float64: for a vertex on an open boundary of the mesh (an edge with one face),
    the unit direction in its tangent plane towards the centroid of its faces; zero elsewhere.

    Such a vertex can lie on *another* surface (a floor vertex at the foot of a wall, a box's
    open bottom edge standing on the floor); :func:`offset_origins` moves its ray origins by eps
    along this direction, into the vertex's own surface, so that the hemisphere it integrates
    is the limit from inside its faces: rays towards the wall meet the wall's front, rays away
    from it leave. Closed-surface and interior vertices are not moved."""
    f = mesh.faces.numpy().astype(np.int64)
    V = mesh.num_vertices
    e, cnt = edge_face_counts(f, V)
    border = e[cnt == 1].reshape(-1)
    out = torch.zeros(V, 3, dtype=torch.float64)
    if border.size == 0:
        return out
    v = mesh.vertices.to(torch.float64).numpy()
    c = v[f].mean(1)  # [F,3] face centroids
    acc = np.zeros((V, 3))
    np.add.at(acc, f.reshape(-1), np.repeat(c, 3, axis=0))
    deg = np.bincount(f.reshape(-1), minlength=V)[:, None]
    on = np.zeros(V, bool)
    on[border] = True
    n = mesh.normals.to(torch.float64).numpy()
    d = acc / np.maximum(deg, 1) - v
    d -= np.einsum("ij,ij->i", d, n)[:, None] * n  # into the tangent plane
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    ok = on & (norm[:, 0] > 0)
    out[torch.from_numpy(ok)] = torch.from_numpy(d[ok] / norm[ok])
    return out


def _csr_rows(indptr: np.ndarray, indices: np.ndarray, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The entries of ``rows`` (int64 ``[G]``) of a CSR pattern, row after row: (their column indices,
    int64 ``[Σ lengths]``; each row's start in it, int64 ``[G]``) — one gather, no per-row loop."""
    start, length = indptr[rows], indptr[rows + 1] - indptr[rows]
    seg = np.zeros(rows.size, np.int64)
    np.cumsum(length[:-1], out=seg[1:])
    pos = np.repeat(start - seg, length) + np.arange(int(length.sum()), dtype=np.int64)
    return indices[pos].astype(np.int64), seg


def offset_origins(points: Any, normals: Any, eps: float, nudge: Any = None) -> np.ndarray:
    """Ray origins leaving surface points: ``p + eps·n (+ eps·b)``, float64 numpy ``[k,3]`` —
    the one self-intersection rule of every transfer tracer (diffuse, glossy, MRT, the bounce's
    face and hit points; rays are traced only above the tangent plane, so the origin sits on the
    side they leave towards). ``nudge`` b: :func:`boundary_nudge` rows for mesh vertices (zero
    except on open boundaries, where a vertex may lie on another surface)."""
    o = np.asarray(points, np.float64) + eps * np.asarray(normals, np.float64)
    if nudge is not None:
        o = o + eps * np.asarray(nudge, np.float64)
    return o


def hit_ray_eps(mesh: Mesh, hit_offset: float = HIT_OFFSET) -> float:
    """The offset of rays leaving a bounce hit point q (origin q + eps_h·n_f, n_f the hit face's
    normal): ``max(hit_offset × bounding-box diagonal, HIT_OFFSET_ULPS float32 ulps of the
    largest coordinate)`` — as small as float32 ray tracing allows (issue 37).

    A larger offset carries the origin through a surface closer than it to q — the other wall
    of a narrow fold, a non-manifold sheet or fin over the hit — and rays that should meet that
    wall from the front leave behind it: light leaks into the fold. On a vertex-clustered scan
    (``scene.scan_like``) the fraction of hit rays that meet the mesh fell from 4.73% to 4.62%
    at 1e-4 (the vertices' offset, the rule before) and 4.17% at 1e-3, and interreflection ran
    1.1–2.4% high against Mitsuba; from 1e-5 down it no longer changes (docs/validate.md). Own-face
    hits are none from 1e-7 of the diagonal up on a mesh near the origin; far from it (coordinates
    of 1000 for a 3-unit mesh) 1e-5 gave 0.8% and the ulp floor (16 ulps) keeps them away."""
    v = mesh.vertices.to(torch.float64)
    if v.numel():  # the largest coordinate in the frame rays are traced in (RayCaster: centred on the bounding box)
        v = v - (v.amin(0) + v.amax(0)) / 2
    floor = HIT_OFFSET_ULPS * 2.0 ** -23 * float(v.abs().max()) if v.numel() else 0.0
    return max(float(hit_offset) * mesh.bbox_diagonal(), floor)


class DiffuseSampler:
    """The direction set of one run, with SH values evaluated once where they are shared.

    ``sampling``:

    * ``'uniform'``: one jittered stratified set of N directions over the sphere shared by every
      vertex (weights 4π/N; about N/2 above a tangent plane are traced), SH evaluated once.
    * ``'cosine'``: N stratified cosine-weighted directions over each vertex's hemisphere.
    * ``'qmc'``: M = ⌈N/2⌉ directions per vertex (the rays 'uniform' traces) from a Hammersley set
      over the vertex's hemisphere, drawn from a defensive mixture of the uniform (¾) and the cosine
      (¼) densities, p(z) = ¾ + z/2 for z = cos θ ∈ [0, 1] (z = 2a / (¾ + √(9/16 + a)) of the set's
      first coordinate a; Hesterberg 1995's defensive importance sampling), Cranley–Patterson rotated per
      vertex by :func:`_hash_uniform` of (seed, vertex id) so that every vertex has its own
      randomised low-discrepancy set and the numbers depend on neither chunking nor executor:
      (1/π) ∫ f max(n·s, 0) ds ≈ (1/M) Σ_m q(z_m) f(s_m), q(z) = 2z / (¾ + z/2) (:func:`qmc_factor`).
      Measured (benchmarks/bench_precompute_error.py, N = 1024, shadowed, 2 seeds, relative RMS):
      the cosine density alone had 0.80× the uniform one's error where occlusion is heavy
      (cornell_box: walls high above the horizon; 0.0222 vs 0.0276) but 1.4× on a scan (scan_blob,
      0.0060 vs 0.0043: bumps occlude near the horizon, where the cosine density puts few rays); the
      cosine share ¼ keeps bumpy_sphere's error (0.0063 vs 0.0062; ½: 0.0066) and scan_blob's (0.0042)
      and takes most of the Cornell box's gain (0.0247; ½: 0.0224).

    ``estimator``: ``'plain'`` sums the visible directions, P = Σ_j w_j V_j y(s_j); ``'control'``
    (issue 42) uses the exact unshadowed transfer as a control variate and samples only what is
    blocked, t = t_unshadowed − Σ_j w_j (1 − V_j) y(s_j) — unbiased, exact for an unoccluded
    vertex, and its error is that of the occluded part alone; ``'auto'`` (default) chooses per
    vertex: 'control' where at least half of its (cosine-weighted) rays are open, 'plain'
    elsewhere — each vertex samples the smaller of its open and blocked parts, so it is exact both
    for an open vertex and for an enclosed one (where 'control' keeps the direction set's error of
    the unshadowed integral), and only those rays' SH values are evaluated. The choice is read
    from the same rays; both branches are unbiased and they differ by the set's error of the
    unshadowed integral alone, so its bias is second order (below 3σ over 48 seeds in the tests).
    """

    def __init__(self, bands: int, samples: int, seed: int, sampling: str, estimator: str = "auto"):
        self.bands, self.samples, self.sampling, self.seed = bands, samples, sampling, int(seed)
        self.estimator = check_choice("estimator", estimator, ESTIMATORS)
        if sampling == "uniform":
            self.dirs, _ = uniform_sphere(samples, seed)  # [N,3] float64, weights 4π/N
            self.Y = eval_sh(self.dirs, bands)  # [N, n²], shared by every vertex
            self.weight = 4.0 / samples  # (4π/N)·(1/π)
            self.dirs_np = np.ascontiguousarray(self.dirs.numpy())
            self.dirs32 = self.dirs_np.astype(np.float32)
            self.Y_np = np.ascontiguousarray(self.Y.numpy())
            self._work: dict = {}  # ray buffers of rays(reuse=True)
        elif sampling == "qmc":
            self.M = qmc_rays(samples)
            self.base = _hammersley(self.M)  # [M, 2] in [0,1)², rotated per vertex
            self.base_tables = _hammersley_tables(self.base)
            self._work = {}
            self.Y = None
            self.weight = 1.0 / self.M  # times qmc_factor(z) per ray
        else:
            self.dirs = cosine_hemisphere(samples, seed)  # local frame
            self.Y = None
            self.weight = 1.0 / samples

    @property
    def per_vertex(self) -> int:
        """Directions each vertex's estimate averages over (the N of its 1/N)."""
        return self.M if self.sampling == "qmc" else self.samples

    def __getstate__(self):  # the kept ray buffers (tens of MB) do not travel with a pickled sampler (Ray tasks)
        st = dict(self.__dict__)
        if "_work" in st:
            st["_work"] = {}
        return st

    def rays(self, points: torch.Tensor, normals: torch.Tensor, frames: torch.Tensor | None, eps: float,
             nudge: torch.Tensor | None = None, reuse: bool = False, ids: np.ndarray | None = None):
        """Ray set of a chunk of k vertices (numpy, ready for Embree).

        Returns ``(i [R] vertex index, j [R] sample index, origins float32 [R,3],
        dirs float32 [R,3], cos)`` with origins by :func:`offset_origins` (``nudge``: the
        points' :func:`boundary_nudge` rows, or None). For uniform
        sampling only directions above the tangent plane are traced and ``cos`` is the
        ``[k,N]`` matrix max(n·s, 0); for cosine sampling ``cos`` is None and dirs are per vertex;
        for qmc ``cos`` is the ``[R]`` float64 cosine of each ray and dirs are per vertex (in the
        frame :func:`~prt_torch.scene.mesh.tangent_frames` gives the normal; ``frames`` is not used;
        ``ids`` ``[k]`` the vertices' global ids, the keys of their rotations; None: 0..k-1).
        ``reuse``: the uniform rays are written into buffers this sampler keeps (views of them are
        returned, overwritten by its next call with ``reuse``), not into fresh memory.
        """
        o_v = offset_origins(points.numpy(), normals.numpy(), eps, None if nudge is None else nudge.numpy()).astype(np.float32)
        if self.sampling == "uniform":
            cos = normals.numpy() @ self.dirs_np.T  # [k,N] float64
            fused = upper_rays(cos, o_v, self.dirs32, work=self._work if reuse else None)  # one compiled pass (same arrays as below)
            if fused is not None:
                i, j, o, d = fused
            else:
                up = cos > 0
                counts = up.sum(1)
                # row-major: rays grouped by vertex (np.nonzero's order; flatnonzero + repeat is ~5x faster)
                i = np.repeat(np.arange(up.shape[0]), counts)
                j = np.flatnonzero(up) - i * up.shape[1]
                o = np.repeat(o_v, counts, axis=0)  # == o_v[i], without a gather
                d = np.take(self.dirs32, j, axis=0)
            return i, j, o, d, np.maximum(cos, 0.0, out=cos)
        k = normals.shape[0]
        if self.sampling == "qmc":
            o, d, z = self._qmc(o_v, normals, ids, self._work if reuse else None)
            M = self.M
            return np.repeat(np.arange(k), M), np.tile(np.arange(M), k), o, d, z
        world = to_world(self.dirs, frames).reshape(-1, 3).numpy()  # [k·N,3]
        i = np.repeat(np.arange(k), self.samples)
        j = np.tile(np.arange(self.samples), k)
        return i, j, o_v[i], world, None

    def chunk_rays(self, points: torch.Tensor, normals: torch.Tensor, eps: float, nudge: torch.Tensor | None = None,
                 ids: np.ndarray | None = None, reuse: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ``'qmc'`` rays of a chunk of k vertices without the index arrays of :meth:`rays`:
        ``(origins float32 [k·M, 3], dirs float32 [k·M, 3], z float64 [k·M])``, ray v·M + m the
        m-th direction of vertex v, z its cosine (:meth:`_qmc`)."""
        o_v = offset_origins(points.numpy(), normals.numpy(), eps, None if nudge is None else nudge.numpy()).astype(np.float32)
        return self._qmc(o_v, normals, ids, self._work if reuse else None)

    def _qmc(self, o_v: np.ndarray, normals: torch.Tensor, ids: np.ndarray | None, work: dict | None):
        """The qmc direction set of k vertices (class docstring): the Hammersley set (a_m, b_m)
        Cranley–Patterson rotated by the vertex's (u1, u2) = :func:`_hash_uniform` of (seed,
        vertex id), a = (a_m + u1) mod 1, z = max(2a / (¾ + √(9/16 + a)), 1e-12) (the defensive mixture
        p(z) = ¾ + z/2), r = √(1 − z²), φ = 2π((b_m + u2) mod 1), d = r cos φ t + r sin φ b + z n (frame rows of
        :func:`~prt_torch.scene.mesh.tangent_frames`
        from the normals alone). cos φ, sin φ by the angle sum of the set's 2πb_m and the vertex's
        2πu2 (no libm call per ray). One compiled pass (``ray_kernels.qmc_rays_native``) or the same
        float64 operations in numpy (same bits): ``(o float32 [k·M, 3], d float32 [k·M, 3], z float64 [k·M])``."""
        from ..scene.mesh import tangent_frames

        k = normals.shape[0]
        keys = np.arange(k, dtype=np.int64) if ids is None else np.asarray(ids, np.int64)
        zero = np.zeros_like(keys)
        u1 = _hash_uniform(self.seed, keys, zero, 1 << 20)  # streams apart from the hit estimator's
        u2 = 2 * math.pi * _hash_uniform(self.seed, keys, zero, (1 << 20) + 1)
        cu, su = np.cos(u2), np.sin(u2)
        n = normals.numpy().astype(np.float64)
        t, b = tangent_frames(n)  # the module rule from the normals alone, whatever frames the mesh has
        F = np.stack([t, b, n], 1)  # [k,3,3] rows (t, b, n)
        return _rotated_rays(F, o_v, u1, cu, su, self.base_tables, 2, work)

    def ray_weights(self, i: np.ndarray, j: np.ndarray, cos: Any) -> np.ndarray:
        """``[R]`` float64 w_j of each ray in t = Σ_j w_j V_j y(s_j) (ρ = 1)."""
        if self.sampling == "uniform":
            return self.weight * cos[i, j]
        if self.sampling == "qmc":
            return self.weight * qmc_factor(cos)
        return np.full(i.shape[0], self.weight)


def qmc_factor(z: np.ndarray) -> np.ndarray:
    """``[R]`` float64 q(z) = 2z / (¾ + z/2): a qmc ray's weight times M — the clamped cosine's
    (1/π) max(n·s, 0) = z/π over the mixture density p(s) = (¾ + z/2)/(2π) per steradian
    (:class:`DiffuseSampler`)."""
    return (2.0 * z) / (0.75 + 0.5 * z)


def rays_per_vertex(samples: int, sampling: str) -> int:
    """Rays a vertex traces for a ``samples`` setting: about N/2 ('uniform': the sphere set's
    directions above the tangent plane; 'qmc': :func:`qmc_rays`) or N ('cosine')."""
    return {"uniform": int(samples) // 2, "qmc": qmc_rays(samples)}.get(sampling, int(samples))


def qmc_rays(samples: int) -> int:
    """Rays per vertex of ``sampling='qmc'`` for a ``samples`` setting: ⌈N/2⌉, the rays the
    uniform sphere set traces above a tangent plane on average (``samples`` keeps one meaning)."""
    return max(1, (int(samples) + 1) // 2)


def samples_rounding(samples: int, sampling: str) -> str | None:
    """What a ``samples`` count becomes when the direction set cannot honour it exactly, or None.

    ``'qmc'`` traces ⌈N/2⌉ rays per vertex (:func:`qmc_rays`): an odd N traces the rays of N + 1.
    ``'uniform'`` and ``'cosine'`` take any N (their strata grid's leftover samples are uniform).
    """
    if sampling == "qmc" and int(samples) % 2:
        M = qmc_rays(samples)
        return (f"samples={int(samples)} with sampling='qmc' is rounded to {2 * M}: the Hammersley set over each "
                f"vertex's hemisphere traces ⌈N/2⌉ = {M} rays per vertex; accepted exactly: an even count")
    return None


_M1, _M2, _M3 = np.uint64(0x9E3779B97F4A7C15), np.uint64(0xBF58476D1CE4E5B9), np.uint64(0x94D049BB133111EB)


def _hash_uniform(seed: int, a: np.ndarray, b: np.ndarray, stream: int) -> np.ndarray:
    """Uniform [0,1) ``[R]`` float64 from (seed, a, b, stream) by splitmix64: a function of the
    keys only, so a hit's random numbers do not depend on chunking or on which tracer asks."""
    with np.errstate(over="ignore"):
        x = (np.uint64(seed) * _M1) ^ (a.astype(np.uint64) * _M2) ^ (b.astype(np.uint64) * _M3) ^ (np.uint64(stream) * np.uint64(0x632BE59BD9B4E019))
        for _ in range(2):
            x = x + _M1
            x = (x ^ (x >> np.uint64(30))) * _M2
            x = (x ^ (x >> np.uint64(27))) * _M3
            x = x ^ (x >> np.uint64(31))
    return (x >> np.uint64(11)).astype(np.float64) * (1.0 / (1 << 53))


def _radical_inverse(j: np.ndarray, base: int) -> np.ndarray:
    """``[R]`` float64 radical inverse of the integers ``j`` in ``base`` (Halton's sequence: the
    digits of j mirrored about the point)."""
    j = np.asarray(j).astype(np.int64)
    out, f = np.zeros(j.shape), 1.0 / base
    while j.any():  # one pass per digit
        out += f * (j % base)
        j = j // base
        f /= base
    return out


def _hammersley(M: int) -> np.ndarray:
    """``[M, 2]`` Hammersley points ((m + ½)/M, radical inverse base 2 of m)."""
    m = np.arange(M)
    rad = np.zeros(M)
    f, k = 0.5, m.copy()
    while k.any():  # radical inverse base 2 (van der Corput), one pass per bit
        rad += f * (k & 1)
        k >>= 1
        f *= 0.5
    return np.stack([(m + 0.5) / M, rad], 1)


def _hammersley_tables(base: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(a, cos 2πb, sin 2πb)`` float64 ``[M]`` each of a ``[M, 2]`` point set (a, b): what
    :func:`_rotated_rays` rotates."""
    return np.ascontiguousarray(base[:, 0]), np.cos(2 * math.pi * base[:, 1]), np.sin(2 * math.pi * base[:, 1])


def _rotated_rays(frames: np.ndarray, o_v: np.ndarray, u1: np.ndarray, cu: np.ndarray, su: np.ndarray,
                  tables: tuple[np.ndarray, np.ndarray, np.ndarray], cosine: bool, work: dict | None = None):
    """M directions over each of k hemispheres from one point set (a_m, b_m), Cranley–Patterson
    rotated per hemisphere by (u1, u2) (cu, su = cos, sin 2πu2): a = (a_m + u1) mod 1, φ = 2π((b_m
    + u2) mod 1) with cos φ, sin φ by the angle sum (a whole turn drops out), and

    * ``cosine=False`` (the vertices' qmc set, uniform in solid angle): z = max(a, 1e-12), r = √(1 − z²);
    * ``cosine=True`` / 1 (the bounce estimator's set at hit points, cosine-weighted, Malley's method):
      r = √a, z = √max(1 − a, 1e-24);
    * ``cosine=2`` (the vertices' qmc set, :class:`DiffuseSampler`): the defensive mixture of the
      uniform (¾) and cosine (¼) densities, p(z) = ¾ + z/2 on z ∈ [0, 1], z = max(2a / (¾ + √(9/16 + a)), 1e-12),
      r = √(1 − z²);

    d = r cos φ t + r sin φ b + z n with ``frames float64 [k, 3, 3]`` rows (t, b, n), origin the
    hemisphere's ``o_v float32 [k, 3]``. One compiled pass (``ray_kernels.qmc_rays_native``), or the
    same float64 operations in numpy (same bits). Returns ``(o float32 [k·M, 3], d float32 [k·M, 3],
    z float64 [k·M])``, ray v·M + m; ``work``: kept buffers (:func:`ray_kernels.upper_rays`)."""
    a, cb, sb = tables
    fused = qmc_rays_native(frames, o_v, u1, cu, su, a, cb, sb, work=work, cosine=cosine)
    if fused is not None:
        return fused
    z = a[None, :] + u1[:, None]  # [k,M]
    z = np.where(z >= 1.0, z - 1.0, z)  # mod 1 (exact here)
    if cosine == 1:
        r, z = np.sqrt(z), np.sqrt(np.maximum(1.0 - z, 1e-24))
    elif cosine == 2:  # the defensive mixture p(z) = ¾ + z/2 (DiffuseSampler)
        z = np.maximum((2.0 * z) / (0.75 + np.sqrt(0.5625 + z)), 1e-12)
        r = np.sqrt(1.0 - z * z)
    else:
        z = np.maximum(z, 1e-12)  # every ray leaves the tangent plane (measure-zero horizon)
        r = np.sqrt(1.0 - z * z)
    x = r * (cb[None, :] * cu[:, None] - sb[None, :] * su[:, None])
    y = r * (sb[None, :] * cu[:, None] + cb[None, :] * su[:, None])
    d = (x[..., None] * frames[:, None, 0] + y[..., None] * frames[:, None, 1]) + z[..., None] * frames[:, None, 2]  # [k,M,3]
    return np.repeat(o_v, a.shape[0], axis=0), d.reshape(-1, 3).astype(np.float32), z.reshape(-1)


def _malley_dirs(frames: np.ndarray, rows: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``[R, 3]`` float32 cosine-weighted directions by Malley's map of (a, b) ∈ [0,1)² ``[R]``
    float64 each: r = √a, z = √(1 − a), φ = 2πb, d = r cos φ t + r sin φ b + z n in the frame
    ``frames[rows]`` (``frames float64 [F, 3, 3]`` rows (t, b, n)) — the map of
    :func:`_rotated_rays` with ``cosine=1``, for points given one by one."""
    r, z = np.sqrt(a), np.sqrt(np.maximum(1.0 - a, 1e-24))
    phi = 2 * math.pi * b
    fr = frames[rows]
    d = (r * np.cos(phi))[:, None] * fr[:, 0] + (r * np.sin(phi))[:, None] * fr[:, 1] + z[:, None] * fr[:, 2]
    return d.astype(np.float32)


class HitBounce:
    """Exit transfer at bounce-ray hit points, estimated at the hit point itself.

    A blocked direction of vertex p hits face f at q. What it brings is ρ_q x(q)·l with x(q) the
    diffuse transfer of q over the hemisphere of f's normal (course notes 2005,
    "Interreflections", with the integrand evaluated where the ray lands), x = Σ_k x^k over the
    ``terms`` = B bounce terms. x(q) is estimated at q with M cosine-weighted rays over the
    face's hemisphere (a Hammersley set, Cranley–Patterson-rotated per hit, so the numbers depend
    on neither chunking nor which tracer asks: at the first hit by the vertex's :func:`_hash_uniform`
    of (seed, vertex) plus the radical inverses in bases 3 and 5 of the primary direction's index j
    (mod 1) — each hit's rotation uniform, the hits of one vertex stratified together like a 4-D
    Halton–Hammersley set, 0.86× the interreflected part's error of independent rotations on
    occluder_over_plane (estimators 'control' and 'auto'; 'plain', the estimator before issue 42,
    keeps its rotations bit for bit); further hits, and every hit under 'plain', by
    :func:`_hash_uniform` of (seed, vertex, direction, path)):
    x⁰(q) = (1/M) Σ_m V(q,s_m) y(s_m) and, recursively,
    x^k(q) = (1/M) Σ_m [front hit q'] ρ_{q'} x^{k-1}(q'). M = ``hit_samples`` at the first hit
    and a quarter of it per further level (at least 1): an unbiased path-traced estimate of
    every bounce, no per-vertex table ('auto' reads one open fraction per face). Rays leave q from q + eps_h·n_f with eps_h =
    :func:`hit_ray_eps` (``hit_offset``; None: the caster's own eps, the rule before issue 37).
    ``estimator='control'`` (issue 42): x⁰(q) = t_unshadowed(n_f) − (1/M) Σ_m (1 − V(q,s_m))
    y(s_m), exact where the hit's hemisphere is open. ``'auto'``: per hit, that control variate
    where the hit face is mostly open and the plain sum elsewhere, chosen from the face's open
    fraction measured by :meth:`face_openness` (:data:`FACE_PROBE_RAYS` rays per face that may be
    guided and not read open from the first ``probe_rays`` (:data:`FIRST_PROBE_RAYS` in a run), those
    first rays on the other faces, their own
    rotations; traced for the faces the hits land on, as they arrive: :meth:`prepare`): a choice
    independent of the hit's own rays, so each hit's estimate stays unbiased (a choice read from
    its M = 4 to 8 rays would correlate with their set's error). In an enclosure
    (a Cornell box) 'control' at every hit had 1.8× the interreflected part's error of 'plain'
    (reports/benchmarks/precompute_error.md). Under 'auto' the first hits on flat, mostly blocked
    faces draw their rays from a density guided by the same probe (:meth:`_build_guide`: the
    cells' open fractions pooled over coplanar neighbours, a defensive mixture with the cosine
    density), each ray weighted by q = cosine density / guided density (:meth:`_guided_rays`):
    x⁰(q) = (1/M) Σ_m q_m V(q,s_m) y(s_m), unbiased, with the rays where the face's hemisphere is
    open (Cornell box, one bounce: the interreflected part's error 0.064 → 0.045, the total's
    0.0287 → 0.0250 at 1.6% more rays; benchmarks/bench_bounce_parts.py).
    """

    def __init__(self, mesh: Mesh, bands: int, hit_samples: int, seed: int, terms: int, channels: int,
                 hit_offset: float | None = HIT_OFFSET, estimator: str = "plain", probe_rays: int = FACE_PROBE_RAYS):
        from ..scene.mesh import tangent_frames

        self.bands, self.M, self.seed, self.C = bands, int(hit_samples), int(seed), channels
        if probe_rays not in PROBE_RAYS_CHOICES:
            raise ValueError(f"probe_rays={probe_rays!r}; accepted: one of {PROBE_RAYS_CHOICES} (rays per probed face)")
        self.probe_stride = FACE_PROBE_RAYS // int(probe_rays)  # a face probes every probe_stride-th cell (_probe)
        self.hit_offset = None if hit_offset is None else check_float("hit_offset", hit_offset, 0.0, 0.1)
        self.hit_eps = None if hit_offset is None else hit_ray_eps(mesh, hit_offset)
        self.mode = check_choice("estimator", estimator, ESTIMATORS)
        self.control = self.mode != "plain"
        self.terms = int(terms)
        centroids, fn, _ = face_points(mesh)
        self.face_centroids = centroids.numpy()
        self._face_open: np.ndarray | None = None  # [F] float64, auto's per-face choice (face_openness; NaN: not probed)
        self.probe_rays = 0  # probe rays this process traced (face_openness)
        self._cells: np.ndarray | None = None  # [F, K] bool, the cells each face probed (_probe)
        self._log: tuple = (0, [], [])  # (probe_rays at the last take_probe_log, faces probed, guided since)
        self._decided: np.ndarray | None = None  # [F] bool, the faces 'auto' has probed and decided (prepare)
        self._pool = None  # (cnt, csr) the faces' coplanar neighbours (_coplanar)
        self.guided: np.ndarray | None = None  # [F] bool, faces whose deepest hits are guided (_build_guide)
        self.rays_traced = 0  # hit rays this process traced with this estimator (intersect + occluded; not the probe)
        self.face_normals = fn
        self.face_normals_np = fn.numpy()
        self._tables: dict = {}  # M -> the Hammersley set's tables (_hammersley_tables)
        self._face_unshadowed = None
        t, b = tangent_frames(fn.numpy())
        self.frames = np.stack([t, b, fn.numpy()], 1)  # [F,3,3] rows (t, b, n)
        self.rho_vertices = mesh.albedo.to(torch.float64)
        self.faces = mesh.faces.numpy()
        self.vertices = mesh.vertices.to(torch.float64).numpy()
        rf = self.rho_vertices[mesh.faces.to(torch.int64)]  # [F,3,3]
        # faces whose three vertices share one albedo (every built-in scene): a lookup, no interpolation
        self.rho_face = rf[:, 0] if bool((rf == rf[:, :1]).all()) else None

    def face_openness(self, caster: RayCaster, faces: np.ndarray | None = None) -> np.ndarray:
        """``[F]`` float64: each face's open fraction, (1/K) Σ_m [ray m leaves the scene], from K =
        :data:`FACE_PROBE_RAYS` cosine-weighted rays leaving its centroid (the hits' offset rule),
        one per cell of :data:`GUIDE_GRID` in Malley's square (a = sin²θ, b = φ/2π), jittered in
        its cell by :func:`_hash_uniform` of (seed, face, cell) on streams apart from the hits' —
        a stratified estimate of the cosine-weighted open fraction of the face's hemisphere, what
        'auto' reads to choose a hit's estimator; the same rays give the hits' guide
        (:meth:`_build_guide`). A function of (seed, mesh, face) only: the same value in every
        process and chunk, whichever faces were probed before, so the numbers stay independent of
        chunking and executor.

        ``faces`` (int64 ``[n]``): probe only these faces (and, under 'auto', the coplanar
        neighbours a guided one pools: :meth:`prepare`), as a run does for the faces its first hits
        land on (issue 42 §2: a face no ray reaches is never probed); None: every face (F·K rays).
        Faces not probed read NaN. Traced in batches of about 2¹⁸ rays."""
        F = self.face_normals_np.shape[0]
        faces = np.arange(F, dtype=np.int64) if faces is None else np.unique(np.asarray(faces, np.int64))
        if faces.size and (faces[0] < 0 or faces[-1] >= F):  # sorted by np.unique
            raise ValueError(f"faces holds indices in [{int(faces[0])}, {int(faces[-1])}]; accepted: face indices in [0, {F})")
        if self.mode == "auto":
            self.prepare(caster, faces)
        else:
            self._probe(caster, faces)
        return self._face_open

    def _probe(self, caster: RayCaster, faces: np.ndarray, full: bool = False) -> None:
        """Trace the probe (:meth:`face_openness`) of ``faces`` (int64, unique) where not yet traced,
        whose mean is the face's open fraction: K/s cells per face first (s = ``probe_stride`` = K /
        ``probe_rays``, 4 in a run (:data:`FIRST_PROBE_RAYS`): every s-th cell from a first one
        hashed from (seed, face) — two opposite sectors per ring, a stratified estimate all the
        same; all K at s = 1); then every cell of the faces that may be guided (at least
        :data:`GUIDE_MIN_FACES` coplanar faces: geometry only) unless all their first rays left the
        scene (read as open, 1: the control variate, not guided), their open fraction from all K —
        a choice from the probe's own rays, independent of the hits' (no bias). ``full``:
        then the faces' remaining cells too (what a guide pools, :meth:`prepare`). Cell c of face f
        is always the same ray and each step reads the face's own rays only, so the values do not
        depend on the order of calls."""
        F, K, s = self.face_normals_np.shape[0], FACE_PROBE_RAYS, self.probe_stride
        if self._cells is None:
            self._face_open = np.full(F, np.nan)
            self._opened = np.zeros((F, K), bool)  # [F, K] the probe rays that left the scene (32 B per face)
            self._cells = np.zeros((F, K), bool)  # [F, K] the cells traced
            self.probed = np.zeros(F, bool)
        new = faces[~self.probed[faces]]
        if new.size:  # the first stage: its open fraction
            k = K // s
            c = np.tile(s * np.arange(k, dtype=np.int64), new.shape[0])  # every s-th cell from a random first one
            if s > 1:
                c = c + np.repeat((_hash_uniform(self.seed, new, np.zeros_like(new), FACE_PROBE_STREAM + 2) * s).astype(np.int64), k)
            opened = self._trace_cells(caster, np.repeat(new, k), c).reshape(-1, k)
            self._face_open[new] = opened.mean(1, dtype=np.float64)
            if s > 1:  # faces that may be guided, unless all their first rays left: every cell, the open fraction of all
                rest = new[(self._coplanar()[0][new] >= GUIDE_MIN_FACES) & ~opened.all(1)]
                f, c = np.nonzero(~self._cells[rest])
                if f.size:
                    self._trace_cells(caster, rest[f], c)
                    self._face_open[rest] = self._opened[rest].mean(1, dtype=np.float64)
            self.probed[new] = True
            self._log[1].append(new)
        if full and s > 1:  # the faces' remaining cells
            f, c = np.nonzero(~self._cells[faces])
            if f.size:
                self._trace_cells(caster, faces[f], c)

    def _trace_cells(self, caster: RayCaster, f: np.ndarray, c: np.ndarray) -> np.ndarray:
        """Trace probe ray (f, c) for each face f and cell c (int64 ``[R]``, grouped by face), one
        jittered cosine-weighted ray in cell c of :data:`GUIDE_GRID` from f's centroid; records
        them in ``_opened``/``_cells`` and the ray count. Returns ``opened bool [R]``. Traced in
        batches of about 2¹⁸ rays."""
        Gb = GUIDE_GRID[1]
        eps = caster.eps if self.hit_eps is None else self.hit_eps
        out = np.empty(f.shape[0], bool)
        step = 1 << 18
        for s0 in range(0, f.shape[0], step):  # a loop over ray batches, each one traced batch
            fb, cb = f[s0:s0 + step], c[s0:s0 + step]
            a = (cb // Gb + _hash_uniform(self.seed, fb, cb, FACE_PROBE_STREAM)) / GUIDE_GRID[0]
            b = (cb % Gb + _hash_uniform(self.seed, fb, cb, FACE_PROBE_STREAM + 1)) / Gb
            d = _malley_dirs(self.frames, fb, a, b)
            o = offset_origins(caster.local(self.face_centroids[fb]), self.face_normals_np[fb], eps).astype(np.float32)
            out[s0:s0 + step] = ~caster.trace(o, d, "occluded")
        self._opened[f, c] = out
        self._cells[f, c] = True
        self.probe_rays += f.shape[0]
        return out

    def take_probe_log(self) -> dict[str, torch.Tensor]:
        """What this process probed since the last call, for a chunk's result (any executor; a run
        sums and unites them: :func:`record_probe_log`): ``probe_rays`` int64 ``[1]`` (rays traced),
        ``probed_faces`` and ``guided_faces`` int64 (the faces newly probed, newly guided)."""
        rays, probed, guided = self.probe_rays - self._log[0], self._log[1], self._log[2]
        self._log = (self.probe_rays, [], [])
        def cat(xs: list) -> torch.Tensor:
            return torch.from_numpy(np.concatenate(xs).astype(np.int64)) if xs else torch.zeros(0, dtype=torch.int64)
        return {"probe_rays": torch.tensor([rays], dtype=torch.int64), "probed_faces": cat(probed), "guided_faces": cat(guided)}

    def prepare(self, caster: RayCaster, faces: np.ndarray, guide: bool = True) -> None:
        """What a batch of hits on ``faces`` (int64 ``[n]``, repeats allowed) needs before its rays
        (estimator 'auto'; nothing otherwise): the faces' probe (:meth:`face_openness`), and
        (``guide``: first hits) for each face first seen here whether its first hits are guided,
        with its guide (:meth:`_build_guide`), after probing the coplanar neighbours the guide
        pools. Each face is decided once per process; what is decided is a function of (seed,
        mesh, face) only."""
        if self.mode != "auto":
            return
        if not guide:
            self._probe(caster, np.unique(faces))
            return
        if self._decided is None:
            self._decided = np.zeros(self.face_normals_np.shape[0], bool)
        faces = np.unique(faces)
        new = faces[~self._decided[faces]]
        if not new.size:
            return
        self._probe(caster, new)
        cnt, pool = self._coplanar()
        cand = new[(cnt[new] >= GUIDE_MIN_FACES) & (self._face_open[new] < 0.5)]  # the faces guided (_build_guide)
        if cand.size:  # the neighbours their guides pool (themselves included), every cell
            self._probe(caster, np.unique(_csr_rows(*pool, cand)[0]).astype(np.int64), full=True)
        self._build_guide(self._opened, new)
        self._decided[new] = True

    def _coplanar(self):
        """``(cnt int64 [F], (indptr int64 [F+1], indices int32 [nnz]))``: per face its coplanar faces
        (normals within 2.6°, centroids within 1e-3 of the diagonal of the plane) among the
        :data:`GUIDE_POOL` nearest centroids (itself included), row f of a CSR pattern (no values: the
        former scipy matrix's were all 1; numpy arrays keep the 0.17 CPU s scipy.sparse import off the
        glossy/MRT bounce precompute), rows kept only for faces that may be guided; once per estimator
        (geometry only, no rays). ``scipy.spatial`` is imported here only (~0.4-0.5 s CPU on the 2-core
        Zen 3, paired: reports/benchmarks/import_cost.md; every estimator-'auto' bounce run needs these sets,
        whose probe they steer): a brute-force or grid k-NN in torch/numpy would pick other faces
        where centroids tie at the 32nd distance, and they do on the planar scenes (small sizes:
        the 32nd and 33rd equal for 974 of 4480 faces of sphere_on_plane, 816/4096 occluder_over_plane,
        951/3690 cornell_box; 0 bumpy_sphere, 19/4307 scan_blob), so no cheaper path keeps the output."""
        if self._pool is None:
            from scipy.spatial import cKDTree

            c, n = self.face_centroids, self.face_normals_np
            F = c.shape[0]
            pool = min(GUIDE_POOL, F)
            tree = cKDTree(c)
            diag = float(np.linalg.norm(c.max(0) - c.min(0))) if F else 0.0
            nb = np.empty((F, pool), np.int64)
            same = np.empty((F, pool), bool)
            step = 1 << 16
            for s0 in range(0, F, step):  # face blocks: the [block, pool, 3] gathers stay small at millions of faces
                sl = slice(s0, s0 + step)
                nb[sl] = tree.query(c[sl], pool)[1].reshape(-1, pool)
                same[sl] = (np.einsum("ij,ikj->ik", n[sl], n[nb[sl]]) > 0.999) & \
                    (np.abs(np.einsum("ij,ikj->ik", n[sl], c[nb[sl]] - c[sl, None, :])) <= 1e-3 * diag)
            cnt = same.sum(1)
            same &= (cnt >= GUIDE_MIN_FACES)[:, None]  # rows of faces that may be guided only (the others are never read)
            indptr = np.zeros(F + 1, np.int64)
            np.cumsum(same.sum(1), out=indptr[1:])
            indices = nb[same].astype(np.int32 if F < (1 << 31) else np.int64)  # row f: its coplanar neighbours, 4 B each
            self._pool = (cnt, (indptr, indices))
        return self._pool

    def _build_guide(self, opened: np.ndarray, faces: np.ndarray | None = None) -> None:
        """The hits' guide of ``faces`` (int64, default every face) from the probe's ``opened [F, K]``
        (1 where a cell's probe ray left the scene; the rows of the faces and of their coplanar
        neighbours are read): per face the cell masses P ``[4, 8]`` of a piecewise-constant density
        over Malley's square, P = u/K + (1 − u) g/Σg with u = :data:`GUIDE_UNIFORM` and g each cell's
        open fraction averaged over the coplanar faces (:meth:`_coplanar`) among the
        :data:`GUIDE_POOL` nearest centroids (uniform where no probe ray left). Guided
        (``self.guided[f]``): the faces where 'auto' takes the plain sum (open fraction < ½: the
        open cells are what it sums) with at least :data:`GUIDE_MIN_FACES` such coplanar faces; not
        the curved regions (a cell's directions differ from face to face) nor the faces where it
        takes the control variate (guided weights q up to 1/u could take its estimate below 0,
        where the cosine set's never is), which keep the cosine-weighted set. The guides are kept
        for the guided faces only (544 B each), appended as faces are decided."""
        F, K = opened.shape
        faces = np.arange(F, dtype=np.int64) if faces is None else faces
        cnt, pool = self._coplanar()
        if self.guided is None:
            self.guided = np.zeros(F, bool)
            self._guide_row = np.full(F, -1, np.int64)
            self.guide_mass = np.zeros((0, *GUIDE_GRID))
            self._guide_cdf = (np.zeros((0, GUIDE_GRID[0])), np.zeros((0, *GUIDE_GRID)))
        gf = faces[(cnt[faces] >= GUIDE_MIN_FACES) & (self._face_open[faces] < 0.5)]
        gf = gf[self._guide_row[gf] < 0]  # not yet guided
        self.guided[gf] = True
        self._log[2].append(gf)
        if not gf.size:
            return
        cells = np.ones(opened.shape, bool) if self._cells is None else self._cells
        n_cell = np.empty((gf.size, K))  # [G, K] probe rays per cell (cnt each: every cell probed)
        g = np.empty((gf.size, K))  # [G, K] pooled open fraction per cell
        for b0 in range(0, gf.size, 1 << 12):  # blocks of guided faces: [block · pool, K] gathers
            nbr, seg = _csr_rows(*pool, gf[b0:b0 + (1 << 12)])  # their coplanar neighbours (each has >= GUIDE_MIN_FACES)
            n_cell[b0:b0 + seg.size] = np.add.reduceat(cells[nbr].astype(np.float64), seg, axis=0)  # sums of 0/1: exact
            g[b0:b0 + seg.size] = np.add.reduceat(opened[nbr].astype(np.float64), seg, axis=0)
        g = g / np.maximum(n_cell, 1)
        tot = g.sum(1, keepdims=True)
        g = np.where(tot > 0, g / np.maximum(tot, 1e-300), 1.0 / K)
        self._guide_row[gf] = self.guide_mass.shape[0] + np.arange(gf.size)
        P = (GUIDE_UNIFORM / K + (1.0 - GUIDE_UNIFORM) * g).reshape(gf.size, *GUIDE_GRID)
        Pa = P.sum(2)  # [G, Ga] ring masses
        self.guide_mass = np.concatenate([self.guide_mass, P])  # [G, Ga, Gb] of the guided faces, each sums to 1
        self._guide_cdf = (np.concatenate([self._guide_cdf[0], np.cumsum(Pa, 1)]),
                           np.concatenate([self._guide_cdf[1], np.cumsum(P / Pa[:, :, None], 2)]))

    def _guided_rays(self, tri: np.ndarray, ua: np.ndarray, ub: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Warp rotated points (``ua, ub`` float64 ``[R]`` in [0,1)², face ``tri [R]``) by the face's
        guide (:meth:`_build_guide`): the ring by the inverse of its marginal CDF, the sector by
        the conditional one, each linearly inside its cell (a monotone map per coordinate, so the
        set's stratification carries over). Returns (directions float32 ``[R, 3]`` by Malley's map,
        q float64 ``[R]`` = 1/(K P_cell), the ratio of the cosine density to the guided one: the ray's
        weight factor, so that (1/M) Σ q f is unbiased for (1/π) ∫ f cos, as Σ f/M is under the
        cosine set)."""
        Ga, Gb = GUIDE_GRID
        cA, cB = self._guide_cdf
        gr = self._guide_row[tri]  # [R] the faces' guide rows (guided faces only)
        if (gr < 0).any():
            raise ValueError(f"_guided_rays: faces {np.unique(tri[gr < 0])[:5]} are not guided; accepted: faces with guided True")
        R = np.arange(tri.shape[0])
        rows = cA[gr]  # [R, Ga]
        ia = np.minimum((rows[:, :-1] <= ua[:, None]).sum(1), Ga - 1)
        lo = np.where(ia > 0, rows[R, np.maximum(ia - 1, 0)], 0.0)
        pa = rows[R, ia] - lo
        a = (ia + np.clip((ua - lo) / pa, 0.0, 1.0 - 1e-12)) / Ga
        cols = cB[gr, ia]  # [R, Gb]
        ib = np.minimum((cols[:, :-1] <= ub[:, None]).sum(1), Gb - 1)
        lob = np.where(ib > 0, cols[R, np.maximum(ib - 1, 0)], 0.0)
        pb = cols[R, ib] - lob
        b = (ib + np.clip((ub - lob) / pb, 0.0, 1.0 - 1e-12)) / Gb
        return _malley_dirs(self.frames, tri, a, b), 1.0 / (Ga * Gb * self.guide_mass[gr, ia, ib])

    def samples_at(self, level: int) -> int:
        """Rays per hit at recursion ``level`` (0 = the first hit)."""
        return max(1, self.M >> (2 * level))

    def albedo_at(self, tri: np.ndarray, bary: np.ndarray) -> torch.Tensor:
        """ρ_q ``[H, C]``: the vertex albedo interpolated at the hit."""
        if self.rho_face is not None:
            rho = self.rho_face[torch.from_numpy(tri)]
        else:
            rho = (torch.from_numpy(bary)[:, :, None] * self.rho_vertices[torch.from_numpy(self.faces[tri])]).sum(1)
        return rho[:, :1] if self.C == 1 else rho

    def exit_transfer(self, caster: RayCaster, tri: np.ndarray, bary: np.ndarray, key_a: np.ndarray,
                      key_b: np.ndarray, channel_weights: torch.Tensor | None = None) -> torch.Tensor:
        """``[H, C, n²]`` float64: ρ_q Σ_k x^k(q), the whole exit transfer a hit brings (albedo
        folded), in batches of about 2¹⁸ secondary rays. ``channel_weights`` (float64 ``[3]``, the
        glossy kind's luminance weights): ``[H, n²]`` instead, (w₀ t₀ + w₁ t₁) + w₂ t₂ with t_c the
        channel's exit transfer (the order ``einsum('hcn,c->hn')`` takes here), or the one channel
        of a grey mesh — per batch, never the ``[H, 3, n²]`` whole."""
        n2 = self.bands * self.bands
        out = torch.empty((tri.shape[0], self.C, n2) if channel_weights is None else (tri.shape[0], n2), dtype=torch.float64)
        step = max(1, (1 << 18) // self.M)
        for a in range(0, tri.shape[0], step):  # a loop over hit batches, each one traced batch
            sl = slice(a, a + step)
            if self.terms == 1:  # one term (one bounce): x⁰ itself, without the [H, terms, C, n²] buffer and its sum
                x = self._first_term(caster, tri[sl], bary[sl], key_a[sl], key_b[sl], 0, False)[0][:, None, :]
            else:
                x = self.values(caster, tri[sl], bary[sl], key_a[sl], key_b[sl]).sum(1)
            rho = self.albedo_at(tri[sl], bary[sl])  # [h, C]
            if channel_weights is None:
                torch.mul(rho[:, :, None], x, out=out[sl])
            elif self.C == 1:
                torch.mul(rho, x[:, 0], out=out[sl])
            elif not luma_mix(out[sl].numpy(), rho.numpy(), x.numpy(), channel_weights.numpy()):  # one pass, the same bits
                w, o = channel_weights, out[sl]
                xs = [x[:, min(c, x.shape[1] - 1)] for c in range(3)]  # x [h, 1 or C, n²]
                torch.mul(rho[:, 0:1], xs[0], out=o).mul_(w[0])  # in place: no fresh [h, n²] pages per operation
                t = torch.mul(rho[:, 1:2], xs[1]).mul_(w[1])
                o.add_(t).add_(torch.mul(rho[:, 2:3], xs[2], out=t).mul_(w[2]))
        return out

    def _rays(self, caster: RayCaster, tri: np.ndarray, bary: np.ndarray, key_a: np.ndarray, key_b: np.ndarray,
              level: int, intersect: bool):
        """The M = :meth:`samples_at` (level) cosine-weighted rays of each hit (class docstring), traced:
        the Hammersley set Cranley–Patterson rotated per hit, in the hit face's frame, from the compiled
        ray generator (:func:`_rotated_rays`); at the first hit on a guided face (estimator 'auto',
        :meth:`_build_guide`) the same rotated points warped by the face's guide (one compiled pass,
        ``ray_kernels.guided_rays_native``, or its numpy reference :meth:`_guided_rays`: the same bits;
        the same at every ``terms``, so a run with more bounces adds terms to the same first-hit
        estimate). Returns (directions
        float32 ``[H·M, 3]``, ray h·M + m of hit h; blocked ``bool [H·M]``; for ``intersect`` the
        Embree (prim, u, v) of each ray, else None; q float64 ``[H·M]``, each ray's weight factor,
        or None where no ray is guided: every factor 1)."""
        M = self.samples_at(level)
        ft = self.faces[tri]
        vt, c = self.vertices, caster.center
        # [H,3] hit points in the caster's (mesh-centred) frame: Embree's float32 barycentrics sum to 1 only within
        # ~6e-8, an error that scales with the corners' coordinates (7e-4 at 1e4 from the origin), so the corners are
        # moved to that frame first
        q = bary[:, :1] * (vt[ft[:, 0]] - c) + bary[:, 1:2] * (vt[ft[:, 1]] - c) + bary[:, 2:3] * (vt[ft[:, 2]] - c)
        n = self.face_normals_np[tri]
        if level == 0 and self.mode != "plain":  # the vertex's shift + a Halton offset over its direction index (class doc)
            zero = np.zeros_like(key_b)
            u1 = np.mod(_hash_uniform(self.seed, key_a, zero, 1) + _radical_inverse(key_b, 3), 1.0)
            v2 = np.mod(_hash_uniform(self.seed, key_a, zero, 2) + _radical_inverse(key_b, 5), 1.0)
        else:
            u1 = _hash_uniform(self.seed, key_a, key_b, 2 * level + 1)
            v2 = _hash_uniform(self.seed, key_a, key_b, 2 * level + 2)
        u2 = 2 * math.pi * v2
        o_h = offset_origins(q, n, caster.eps if self.hit_eps is None else self.hit_eps).astype(np.float32)
        tables = self._tables.get(M)
        if tables is None:
            tables = self._tables[M] = _hammersley_tables(_hammersley(M))
        o, d, _ = _rotated_rays(self.frames[tri], o_h, u1, np.cos(u2), np.sin(u2), tables, True)
        self.rays_traced += o.shape[0]
        w = None
        if self.mode == "auto" and level == 0:
            self.prepare(caster, tri)  # the faces' probe and guides, where not yet decided
            g = np.flatnonzero(self.guided[tri])  # [G] the guided hits
            if g.size:
                w = np.ones(d.shape[0])
                if not guided_rays_native(M, g, tri[g], u1[g], v2[g], tables[0], self._base_b(M), self._guide_row,
                                          *self._guide_cdf, self.guide_mass, self.frames, d, w):  # numpy: the reference
                    r = (g[:, None] * M + np.arange(M)).reshape(-1)  # their rays
                    ua = np.mod(tables[0][None, :] + u1[g, None], 1.0).reshape(-1)
                    ub = np.mod(self._base_b(M)[None, :] + v2[g, None], 1.0).reshape(-1)
                    d[r], w[r] = self._guided_rays(np.repeat(tri[g], M), ua, ub)
        if intersect:
            prim, bu, bv, _ = caster.trace(o, d, "intersect")
            return d, prim != -1, (prim, bu, bv), w
        return d, caster.trace(o, d, "occluded"), None, w

    def guided_faces(self, caster: RayCaster) -> np.ndarray:
        """``[F]`` bool: the faces whose first hits' rays are guided (:meth:`_build_guide`; none but
        under 'auto'), probing every face first if needed (the whole-mesh probe; a run probes
        only the faces its hits land on, :meth:`prepare`)."""
        if self.mode != "auto":
            return np.zeros(self.face_normals_np.shape[0], bool)
        self.face_openness(caster)
        return self.guided

    def _base_b(self, M: int) -> np.ndarray:
        """``[M]`` float64 the Hammersley set's second coordinate (radical inverse base 2)."""
        key = ("b", M)
        if key not in self._tables:
            self._tables[key] = _hammersley(M)[:, 1]
        return self._tables[key]

    def _front_hits(self, d: np.ndarray, hit: np.ndarray, isect, key_a: np.ndarray, key_b: np.ndarray, M: int):
        """The rays of :meth:`_rays` that meet the front of a triangle, as the next level's hits:
        (their hit's row ``[R]``, triangles ``[R]``, barycentrics float64 ``[R, 3]``, key_a, key_b, and
        their ray index ``[R]`` into the level's rays)."""
        prim, bu, bv = isect
        hh = np.flatnonzero(hit)
        t2 = prim[hh].astype(np.int64)
        front = np.einsum("ij,ij->i", self.face_normals_np[t2], d[hh].astype(np.float64)) < 0
        hh, t2 = hh[front], t2[front]
        row = hh // M
        bary2 = np.stack([1 - bu[hh] - bv[hh], bu[hh], bv[hh]], 1).astype(np.float64)
        kb2 = key_b[row].astype(np.uint64) * np.uint64(64) + (hh % M).astype(np.uint64)
        return row, t2, bary2, key_a[row], kb2, hh

    def values(self, caster: RayCaster, tri: np.ndarray, bary: np.ndarray, key_a: np.ndarray, key_b: np.ndarray,
               level: int = 0) -> torch.Tensor:
        """``[H, terms - level, C, n²]`` float64: x^k(q), k = 0 .. terms-level-1, for each hit
        (ρ_q not applied) — the class docstring's estimates, one traced batch per level."""
        H, depth = tri.shape[0], self.terms - level
        n2 = self.bands * self.bands
        M = self.samples_at(level)
        out = torch.zeros(H, depth, self.C, n2, dtype=torch.float64)
        if H == 0:
            return out
        x0, d, hit, isect, w = self._first_term(caster, tri, bary, key_a, key_b, level, depth > 1)
        out[:, 0] = x0[:, None, :]
        if depth > 1:
            row, t2, bary2, ka2, kb2, hh = self._front_hits(d, hit, isect, key_a, key_b, M)
            x2 = self.values(caster, t2, bary2, ka2, kb2, level + 1)  # [R, depth-1, C, n²]
            w2 = self.albedo_at(t2, bary2)[:, None, :, None] / M
            if w is not None:  # guided rays: their weight factors (_guided_rays)
                w2 = w2 * torch.from_numpy(w[hh])[:, None, None, None]
            out[:, 1:] = torch.zeros(H, depth - 1, self.C, n2, dtype=torch.float64).index_add_(
                0, torch.from_numpy(row), w2 * x2)
        return out

    def _first_term(self, caster: RayCaster, tri: np.ndarray, bary: np.ndarray, key_a: np.ndarray, key_b: np.ndarray,
                    level: int, intersect: bool):
        """x⁰(q) ``[H, n²]`` float64 of each hit at ``level`` (the class docstring's estimate of the
        chosen estimator; ρ_q not applied) and the level's traced rays as :meth:`_rays` returns them
        (directions, blocked, the intersections when ``intersect``, weight factors or None)."""
        H, n2, M = tri.shape[0], self.bands * self.bands, self.samples_at(level)
        d, hit, isect, w = self._rays(caster, tri, bary, key_a, key_b, level, intersect)
        if self.mode == "auto":  # per hit: the control variate where its face is mostly open (face_openness)
            self.prepare(caster, tri, guide=level == 0)  # (done by _rays at the first hits)
            open_h = self._face_open[tri] >= 0.5  # [H]
            sel = np.flatnonzero(hit == np.repeat(open_h, M))  # the open faces' blocked rays, the others' open ones
        else:
            sel = np.flatnonzero(hit if self.control else ~hit)
        x0 = sh_accumulate(H, M, sel, d, w, 1.0 / M, self.bands)  # [H, n²], SH summed in the pass
        if x0 is None:  # without the compiled pass
            Y = eval_sh(torch.from_numpy(d[sel]).to(torch.float64), self.bands, check=False) / M  # [R_sel, n²]
            if w is not None:
                Y = Y * torch.from_numpy(w[sel])[:, None]
            x0 = torch.zeros(H, n2, dtype=torch.float64).index_add_(0, torch.from_numpy(sel // M), Y).numpy()
        x0 = torch.from_numpy(x0)
        if self.control:  # the exact unshadowed transfer of the face's hemisphere minus its blocked rays
            if self._face_unshadowed is None:  # [F, n²], once per estimator: a hit reads its face's row
                self._face_unshadowed = unshadowed_transfer(self.face_normals, self.bands)
            if self.mode == "auto":
                oh = torch.from_numpy(open_h)
                x0[oh] = self._face_unshadowed[torch.from_numpy(tri[open_h])] - x0[oh]
            else:
                x0 = self._face_unshadowed[torch.from_numpy(tri)] - x0
        return x0, d, hit, isect, w

    def texel_values(self, caster: RayCaster, tri: np.ndarray, bary: np.ndarray, key_a: np.ndarray, key_b: np.ndarray,
                     texel_of, level: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The same estimate in a pixel basis (the wavelet kind's bounce; plain estimator): Σ_k x^k(q)
        as sparse triplets (hit row ``[R]``, texel ``[R]``, weight ``[R, C]``, one per colour channel:
        C = 1 grey, 3 for a coloured mesh, whose later bounces carry ρ per channel), duplicates to be
        summed. An open ray of a level-ℓ path adds the path's weight (Π of ρ/M of its earlier hits,
        per channel, 1/M at the first) to the texel ``texel_of(direction)`` holds
        (``texel_of``: ``[R, 3]`` float64 → int64 ``[R]``): (1/M) Σ_m V(q, s_m) 1[s_m ∈ texel] is
        the cosine-sampled estimate of (1/π) ∫_texel V(q, s) cos ds."""
        H, depth = tri.shape[0], self.terms - level
        if H == 0:
            e = np.zeros(0, np.int64)
            return e, e, np.zeros((0, self.C))
        M = self.samples_at(level)
        d, hit, isect, q = self._rays(caster, tri, bary, key_a, key_b, level, depth > 1)
        op = np.flatnonzero(~hit)
        w0 = np.full((op.shape[0], self.C), 1.0 / M) if q is None else np.repeat(q[op, None] / M, self.C, 1)
        rows, texels, w = [op // M], [texel_of(d[op].astype(np.float64))], [w0]
        if depth > 1:
            row, t2, bary2, ka2, kb2, hh = self._front_hits(d, hit, isect, key_a, key_b, M)
            r2, tx2, w2 = self.texel_values(caster, t2, bary2, ka2, kb2, texel_of, level + 1)
            rho = self.albedo_at(t2, bary2).numpy()  # [R2, C]
            if q is not None:
                rho = rho * q[hh, None]
            rows.append(row[r2])
            texels.append(tx2)
            w.append(w2 * rho[r2] / M)
        return np.concatenate(rows), np.concatenate(texels), np.concatenate(w)


def _check_points(points: Any, normals: Any) -> tuple[torch.Tensor, torch.Tensor]:
    p = torch.as_tensor(points, dtype=torch.float64)
    n = torch.as_tensor(normals, dtype=torch.float64)
    if p.ndim != 2 or p.shape[1] != 3 or n.shape != p.shape:
        raise ValueError(f"points {tuple(p.shape)} and normals {tuple(n.shape)}; accepted: equal shapes [P, 3]")
    if not (torch.isfinite(p).all() and torch.isfinite(n).all()):
        raise ValueError("points/normals hold NaN or Inf; accepted: finite values")
    return p, n / n.norm(dim=-1, keepdim=True)


def _chunk(*args, **kwargs) -> dict[str, torch.Tensor]:
    """:func:`_chunk_work` with torch on one thread: the chunk's torch steps are small or
    elementwise, and the cores are the ray-casting processes' (measured on 2 cores, 10k vertices,
    one bounce: torch's second thread cost the calling process 2.6 s of CPU — spinning between
    parallel regions — against 1.3 s of Embree work in it; reports/benchmarks/transfer_diffuse.md)."""
    with torch_threads(1):
        return _chunk_work(*args, **kwargs)


def _chunk_work(caster: RayCaster, sampler: DiffuseSampler, points: torch.Tensor, normals: torch.Tensor,
                frames: torch.Tensor | None, faces: np.ndarray | None, face_normals: np.ndarray | None,
                n_vertices: int, record_hits: bool, hit_columns: str = "vertices", hits: HitBounce | None = None,
                first_id: int = 0, nudge: torch.Tensor | None = None, ids: np.ndarray | None = None) -> dict[str, torch.Tensor]:
    """Shadowed transfer (ρ = 1) of a chunk of k points, and (optionally) its bounce entries.

    Uniform sampling: T = (4/N) · (V ⊙ max(n·s,0)) @ Y — one masked GEMM per chunk
    (course notes 2005, "Precomputation"). Cosine sampling: T = (1/N) Σ_j V y(s_j); qmc:
    T = (1/M) Σ_j q(z_j) V y(s_j) (:func:`qmc_factor`). With ``sampler.estimator == 'control'`` the same rays give
    T = T_unshadowed − Σ_j w_j (1 − V_j) y(s_j) instead (:class:`DiffuseSampler`): only the
    blocked rays' SH values are needed; 'auto' chooses per vertex.
    Bounce entries (rows of S): ``hit_columns='faces'`` puts a front hit's weight on the hit
    face's column (``n_vertices`` is then the face count), ``'corners'`` on the hit face's three
    corner points by barycentrics, ``'vertices'`` on the hit face's vertices by barycentrics.
    ``hit_columns='hits'`` (with ``hits``): no S; the bounce terms are estimated at each hit point
    (:class:`HitBounce`, keys: vertex ``first_id + i`` and direction j) and returned as
    ``TB [k, terms, C, n²]`` (ρ_p kept out, ρ_q in).
    """
    k = points.shape[0]
    keys = (first_id + np.arange(k)) if ids is None else np.asarray(ids)
    if sampler.sampling == "qmc":  # rays in blocks of M per vertex: the index arrays only where needed
        o, d, cos = sampler.chunk_rays(caster.local(points), normals, caster.eps, nudge, ids=keys, reuse=True)  # consumed
        i = j = None  # within this chunk; origins in the caster's (mesh-centred) frame
    else:
        i, j, o, d, cos = sampler.rays(caster.local(points), normals, frames, caster.eps, nudge, reuse=True, ids=keys)
    if record_hits:
        prim, bu, bv, _ = caster.trace(o, d, "intersect")
        hit = prim != -1
    else:
        hit = caster.trace(o, d, "occluded")
    out: dict[str, torch.Tensor] = {"rays": torch.tensor([o.shape[0]], dtype=torch.int64)}
    est = sampler.estimator
    q = qmc_factor(cos) if i is None else None  # qmc: ray weights weight · q(z) (the mixture density's)
    picked = select_rays(q, hit, sampler.M, sampler.weight, est) if i is None else None
    if picked is not None:  # qmc: the estimator's rays chosen in one compiled pass (the same choice as below)
        open_v, sel = picked
        S = sh_accumulate(k, sampler.M, sel, d, q, sampler.weight, sampler.bands)  # [k, n²], SH in the same pass
        if open_v.any():
            S[open_v] = unshadowed_transfer(torch.from_numpy(normals.numpy()[open_v]).to(torch.float64), sampler.bands).numpy() - S[open_v]
        out["T"] = torch.from_numpy(S)
        if record_hits:
            i, j = np.repeat(np.arange(k), sampler.M), np.tile(np.arange(sampler.M), k)
    elif sampler.sampling == "uniform" and est == "plain":
        W = cos * sampler.weight  # [k,N]; zero below the horizon
        W.reshape(-1)[(i * W.shape[1] + j)[hit]] = 0.0  # blocked directions
        out["T"] = torch.from_numpy(W @ sampler.Y_np)  # one GEMM per chunk (numpy's float64 GEMM: 3x torch's here)
    else:
        if i is None:  # qmc without the compiled pass
            i, j = np.repeat(np.arange(k), sampler.M), np.tile(np.arange(sampler.M), k)
        w_all = sampler.ray_weights(i, j, cos)  # [R]
        if est == "auto":  # per vertex: the control variate where at least half of the (cosine-weighted) rays are open
            w_open = np.bincount(i, weights=np.where(hit, 0.0, w_all), minlength=k)
            open_v = w_open >= 0.5 * np.bincount(i, weights=w_all, minlength=k)  # [k]
            sel = hit == open_v[i]  # the blocked rays of open vertices, the visible rays of the others
        else:
            open_v = np.full(k, est == "control")
            sel = hit if est == "control" else ~hit  # only the rays the estimator reads
        if sampler.sampling == "uniform":
            Y = torch.from_numpy(sampler.Y_np[j[sel]])  # [R_sel, n²] rows of the shared table
        else:
            Y = eval_sh(torch.from_numpy(d[sel]).to(torch.float64), sampler.bands, check=False)  # per-vertex directions
        S = torch.zeros(k, Y.shape[1], dtype=torch.float64).index_add_(0, torch.from_numpy(i[sel]), Y * torch.from_numpy(w_all[sel])[:, None])
        if open_v.any():
            ov = torch.from_numpy(open_v)
            S[ov] = unshadowed_transfer(normals.to(torch.float64)[ov], sampler.bands) - S[ov]
        out["T"] = S
    if record_hits:
        w_ray = sampler.ray_weights(i, j, cos)
        h = np.nonzero(hit)[0]
        tri = prim[h].astype(np.int64)
        dh = d[h].astype(np.float64)
        front = np.einsum("ij,ij->i", face_normals[tri], dh) < 0  # the ray meets the front of the triangle
        h, tri = h[front], tri[front]
        if hits is not None:
            out["TB"], n_hit = _hit_bounces(caster, hits, k, i[h], j[h], tri,
                                            bu[h], bv[h], w_ray[h], first_id, sampler.bands, ids)
            out["hit_rays"] = torch.tensor([n_hit], dtype=torch.int64)
            if hits.mode == "auto":
                out.update(hits.take_probe_log())  # the faces this chunk probed (record_probe_log)
            return out
        if hit_columns == "faces":
            rows, cols, vals = i[h], tri, w_ray[h]
        else:
            u, v = bu[h].astype(np.float64), bv[h].astype(np.float64)
            beta = np.stack([1 - u - v, u, v], 1)  # [h,3] barycentric weights of faces[tri]
            rows = np.repeat(i[h], 3)
            cols = (faces[tri] if hit_columns == "vertices" else 3 * tri[:, None] + np.arange(3)).reshape(-1)
            vals = (w_ray[h][:, None] * beta).reshape(-1)
        # this chunk's rows of S [V,V] in CSR form, duplicates summed (scipy's C++ conversion)
        import scipy.sparse  # here, not at the top: 0.17 CPU s the glossy/MRT kinds and the hit-point bounces never need

        S = scipy.sparse.coo_matrix((vals, (rows, cols)), shape=(k, n_vertices)).tocsr()
        S.sum_duplicates()
        out["S_indptr"] = torch.from_numpy(S.indptr.astype(np.int64))
        out["S_indices"] = torch.from_numpy(S.indices.astype(np.int32))
        out["S_data"] = torch.from_numpy(S.data.astype(np.float64))
    return out


def _hit_bounces(caster: RayCaster, hits: HitBounce, k: int, rows: np.ndarray, dirs_j: np.ndarray, tri: np.ndarray,
                 u: np.ndarray, v: np.ndarray, w: np.ndarray, first_id: int, bands: int,
                 ids: np.ndarray | None = None) -> torch.Tensor:
    """Σ over a chunk's front hits of w ρ_q x^k(q), per vertex row: ``[k, terms, C, n²]`` float64,
    in batches of about 2¹⁸ secondary rays, and the number of hit rays traced for it."""
    n2 = bands * bands
    out = torch.zeros(k, hits.terms, hits.C, n2, dtype=torch.float64)
    traced = hits.rays_traced
    step = max(1, (1 << 18) // hits.M)
    for a in range(0, rows.shape[0], step):  # a loop over hit batches, each one traced batch
        sl = slice(a, a + step)
        bary = np.stack([1 - u[sl] - v[sl], u[sl], v[sl]], 1).astype(np.float64)
        key = first_id + rows[sl] if ids is None else ids[rows[sl]]  # global vertex ids
        x = hits.values(caster, tri[sl], bary, key, dirs_j[sl])  # [h, terms, C, n²]
        wr = torch.from_numpy(np.asarray(w[sl], np.float64))[:, None] * hits.albedo_at(tri[sl], bary)  # [h, C]
        out.index_add_(0, torch.from_numpy(rows[sl]), x * wr[:, None, :, None])
    return out, hits.rays_traced - traced


def transfer_at_points(caster: RayCaster, points: Any, normals: Any, bands: int, samples: int, seed: int = 0,
                       sampling: str = "qmc", nudge: Any = None, ids: Any = None,
                       estimator: str = "auto") -> torch.Tensor:
    """Shadowed diffuse transfer (ρ = 1, no interreflection) at arbitrary surface points.

    Args:
        caster: ``RayCaster`` of the occluding geometry.
        points, normals: ``[P,3]``.
        nudge: optional ``[P,3]`` :func:`boundary_nudge` rows (mesh vertices: the precompute's origins).
        sampling, estimator: as :func:`precompute_diffuse`.
        ids: ``[P]`` int keys of the points' per-vertex rotations (qmc); the mesh's vertex ids
            reproduce the precompute's numbers for those vertices. None: 0..P-1.
    Returns:
        ``[P, n²] float64`` — course notes 2005 t⁰ with ρ = 1 (Monte Carlo, see module docstring).
    """
    bands = check_int("bands", bands, 1, MAX_DIFFUSE_BANDS)
    samples = check_int("samples", samples, 1, MAX_SAMPLES)
    check_choice("sampling", sampling, SAMPLINGS)
    check_choice("estimator", estimator, ESTIMATORS)
    p, n = _check_points(points, normals)
    from ..scene.mesh import tangent_frames

    frames = None
    if sampling == "cosine":
        t, b = tangent_frames(n.numpy())
        frames = torch.stack([torch.from_numpy(t), torch.from_numpy(b), n], dim=-2)
    nd = None if nudge is None else torch.as_tensor(nudge, dtype=torch.float64)
    keys = None if ids is None else np.asarray(torch.as_tensor(ids, dtype=torch.int64).numpy())
    return _chunk(caster, DiffuseSampler(bands, samples, seed, sampling, estimator), p, n, frames, None, None, 0, False,
                  nudge=nd, ids=keys)["T"]


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
    sampling: str = "qmc",
    estimator: str = "auto",
    shadows: str = "auto",
    fold_albedo: bool | None = None,
    bounce_tol: float = 1e-3,
    probe_tol: float = 1e-3,
    bounce_points: str = "hits",
    hit_samples: int | str = "auto",
    hit_offset: float = HIT_OFFSET,
    subsurface: dict | None = None,
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
        sampling: 'qmc' (default: a Hammersley set over each vertex's hemisphere,
            Cranley–Patterson rotated per vertex, ⌈N/2⌉ rays), 'uniform' (one global stratified
            sphere set, SH evaluated once) or 'cosine' (stratified cosine-weighted hemisphere per
            vertex frame, N rays). :class:`DiffuseSampler`.
        estimator: 'auto' (default), 'control' (the exact unshadowed transfer minus the blocked
            rays' part — exact for an unoccluded vertex) or 'plain' (the sum over visible rays);
            :class:`DiffuseSampler`.
            benchmarks/bench_precompute_error.py measures both with every sampling.
        shadows: 'auto' (probe; trace only if shadowing removes more than ``probe_tol`` of the
            energy), 'always', or 'never' (unshadowed analytic transfer, no interreflection).
        fold_albedo: None = fold only when needed (coloured albedo with interreflection),
            True = always ``[V,3,n²]``, False = always ``[V,n²]`` (refused if colour bleeds).
        bounce_tol: stop adding bounces once one adds less than this fraction of the
            accumulated transfer's norm (the bounce is kept).
        bounce_points: where a bounce ray's hit takes its exit radiance from (no effect without
            bounces): 'hits' (default) — the hit point's own transfer over the hit face's
            hemisphere, estimated with ``hit_samples`` rays from the hit (:class:`HitBounce`;
            deeper bounces of the hit read face-centroid tables); 'faces' — the hit face's
            transfer at its centroid; 'corners' — the hit face's transfer at its three corners
            (over the face's hemisphere) interpolated by barycentrics; 'vertices' — the hit
            face's vertex transfers interpolated by barycentrics (course notes 2005; each over
            its vertex normal's hemisphere, which runs high at sharp and concave vertices). The
            last three are kept for comparison (docs/validate.md has the measurements).
        hit_samples: rays per hit point for ``bounce_points='hits'`` (in [1, 4096]), or 'auto'
            (default): :data:`HIT_SAMPLES_AUTO` of the estimator (4 under 'auto', 8 otherwise).
        hit_offset: offset of the rays leaving a hit point, as a fraction of the bounding-box
            diagonal (in [0, 0.1]; floored at a few float32 ulps, :func:`hit_ray_eps`). The
            vertices' own ray offset is ``run.offset``.
        subsurface: ``{material: NAME | {sigma_a, sigma_s, eta}, scale: MM_PER_UNIT}`` (optional
            ``epsilon``, ``fresnel``): add the subsurface scattering term of Sloan 2003 §3.1
            (:mod:`~prt_torch.transfer.subsurface`: Jensen 2001's dipole over Jensen & Buhler
            2002's hierarchy, from this transfer's irradiance); the data is then ``[V,3,n²]``
            with the albedo folded in (``fold_albedo=False`` is refused).
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
    check_choice("sampling", sampling, SAMPLINGS)
    check_choice("estimator", estimator, ESTIMATORS)
    check_choice("shadows", shadows, ["auto", "always", "never"])
    check_choice("fold_albedo", fold_albedo, [None, True, False])
    check_choice("bounce_points", bounce_points, ["hits", "faces", "corners", "vertices"])
    hit_samples = resolve_hit_samples(hit_samples, estimator)
    hit_offset = check_float("hit_offset", hit_offset, 0.0, 0.1)
    bounce_tol = check_float("bounce_tol", bounce_tol, 0.0, 1.0, hi_open=True)
    probe_tol = check_float("probe_tol", probe_tol, 0.0, 1.0, hi_open=True)
    rounding = samples_rounding(samples, sampling) if shadows != "never" else None
    if rounding is not None:
        import warnings

        warnings.warn(rounding, stacklevel=2)
    t_start = time.perf_counter()
    V = mesh.num_vertices
    if fold_albedo is False and bounces > 0 and not mesh.is_grey():
        raise ValueError("fold_albedo=False with coloured albedo and bounces > 0: interreflection bleeds colour, so the albedo "
                         "cannot be kept separate; accepted: fold_albedo=None/True, or bounces=0, or a grey albedo")
    meta: dict[str, Any] = {
        "bands": bands, "samples": samples, "seed": seed, "sampling": sampling, "estimator": estimator,
        "bounces_requested": bounces,
        "bounce_tol": bounce_tol, "shadows": shadows, "offset": run.offset,
        "bounce_points": bounce_points if bounces > 0 else None,
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
            caster.start()  # the workers start while this process prepares the first chunk
        faces = None
        hits = None
        if traced and bounces > 0 and bounce_points == "hits":
            hits = _hit_tables(caster, mesh, bands, samples, seed, sampling, bounces, hit_samples, run, meta, hit_offset,
                               estimator)
        C_out = 3 if (subsurface is not None or fold_albedo is True or (fold_albedo is None and bounces > 0 and traced
                                                                          and not mesh.is_grey())) else 1
        held = V * held_bytes_per_vertex(bands, bounces if hits is not None else 0, 1 if mesh.is_grey() else 3, C_out)
        if traced:
            hit_columns = bounce_points if bounces > 0 else "vertices"
            T0, S = _trace_direct(caster, mesh, bands, samples, seed, sampling, bounces > 0, run, meta, hit_columns, hits,
                                  estimator, held)
            if bounces > 0 and bounce_points in ("faces", "corners"):
                faces = _trace_faces(caster, mesh, bands, samples, seed, sampling, bounces > 1, run, meta, bounce_points,
                                     estimator)
        else:
            T0, S = unshadowed_transfer(mesh.normals, bands), None  # [V, n²] float64, exact
            meta["rays_traced"] = 0
        if subsurface is not None and fold_albedo is False:
            raise ValueError("fold_albedo=False with a subsurface term: the term is coloured (R_d per channel); "
                             "accepted: fold_albedo=None/True")
        if S is None or isinstance(S, torch.Tensor):  # no bounce term, or the hit-point estimator's: by blocks of rows
            C, used = _bounce_decision(T0, S, mesh, bounces, bounce_tol, meta)
            fold = True if subsurface is not None else ((C == 3) if fold_albedo is None else bool(fold_albedo))
            L = None
            if subsurface is not None:
                from .subsurface import add_term

                L = add_term(mesh, subsurface, _irradiance_rows(T0, S, C, used), run, meta)
            data = _assemble(T0, S, C, used, mesh, fold, meta, run, L, held)
            del T0, S, L
        else:  # bounce_points 'vertices', 'faces', 'corners' (kept for comparison): their sparse bounces read every row
            total, C = _interreflect(T0, S, mesh, bounces, bounce_tol, meta, faces)
            if subsurface is not None:
                from .subsurface import add_term

                data = _store_albedo(total, mesh, C, True, meta) + add_term(mesh, subsurface, total, run, meta)
            else:
                data = _store_albedo(total, mesh, C, fold_albedo, meta)
            data = data.to(torch.float32).contiguous()
        meta["seconds"] = time.perf_counter() - t_start
        meta["rays_per_second"] = meta["rays_traced"] / meta["seconds"] if meta["rays_traced"] else 0.0
        meta["workers"] = caster.workers if caster is not None else 1
        tr = Transfer(kind="diffuse", data=data, mesh=mesh, meta=meta)
    finally:
        if caster is not None:
            caster.close()
    run.finish()
    if not run.keep_state:
        remove_state(face_state_dir(run))
    return tr


def _workers(run: RunOptions, mesh: Mesh, samples: int, sampling: str) -> int:
    """``run.workers``, or (None) all cores when the run traces ≥ 4M rays: processes pay off
    only for long runs (pool start ~0.5 s)."""
    if run.workers is not None:
        return run.workers
    est = mesh.num_vertices * rays_per_vertex(samples, sampling)
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


def _hit_tables(caster: RayCaster, mesh: Mesh, bands: int, samples: int, seed: int, sampling: str, bounces: int,
                hit_samples: int, run: RunOptions, meta: dict, hit_offset: float | None = HIT_OFFSET,
                estimator: str = "plain") -> HitBounce:
    """Step 2a (``bounce_points='hits'``): the :class:`HitBounce` estimator of this run (it
    needs no table: every bounce is estimated at its own hit point)."""
    hb = HitBounce(mesh, bands, hit_samples, seed, bounces, 1 if mesh.is_grey() else 3, hit_offset, estimator,
                   FIRST_PROBE_RAYS)
    meta.update(hit_samples=hit_samples, hit_offset=hit_offset, hit_eps=hb.hit_eps)
    if hb.mode == "auto":  # auto's per-face choice and the hits' guide: probed by the chunks, where their hits land
        hb._coplanar()  # the geometry (no rays) here, once: it travels with the estimator to the executor's tasks
        meta["hit_choice_rays"] = 0
        meta["hit_guide"] = {"grid": list(GUIDE_GRID), "pool": GUIDE_POOL, "min_faces": GUIDE_MIN_FACES,
                             "uniform_share": GUIDE_UNIFORM, "faces_guided": 0, "faces_probed": 0,
                             "faces": int(hb.face_normals_np.shape[0]), "first_probe_rays": FIRST_PROBE_RAYS}
    return hb


def probe_fingerprint(hits: HitBounce) -> dict[str, Any]:
    """The resume-fingerprint entries of the bounce estimator's face probe and guide (issue 42): under
    'auto' the guide's constants (``hit_guide``) and, with the probe's first stage thinned, its rays per
    face (``hit_probe_rays``: :data:`FIRST_PROBE_RAYS`), so that chunks written with an earlier probe (every
    face, :data:`FACE_PROBE_RAYS` rays, up front) — whose per-face choices differ — do not mix into a resumed
    run; ``{}`` for the other estimators (no probe). Used by the diffuse, glossy and MRT runs alike."""
    if hits.mode != "auto":
        return {}
    out: dict[str, Any] = {"hit_guide": [*GUIDE_GRID, GUIDE_POOL, GUIDE_MIN_FACES, GUIDE_UNIFORM]}
    if hits.probe_stride > 1:
        out["hit_probe_rays"] = FACE_PROBE_RAYS // hits.probe_stride
    return out


def record_probe_log(meta: dict, part: dict, seen: dict) -> None:
    """Add a chunk's probe log (:meth:`HitBounce.take_probe_log`) to a run's ``meta``:
    ``hit_choice_rays`` sums the probe rays traced (on the Ray executor a face whose hits reach
    several workers is probed in each of them), ``hit_guide['faces_probed' / 'faces_guided']``
    count the distinct faces over all chunks (the same on any executor). ``seen``: the run's
    ``{'probed': bool [F], 'guided': bool [F]}``, created on the first call."""
    if "probe_rays" not in part or "hit_guide" not in meta:
        return
    F = meta["hit_guide"]["faces"]
    for k in ("probed", "guided"):
        arr = seen.setdefault(k, np.zeros(F, bool))
        arr[part[f"{k}_faces"].numpy()] = True
        meta["hit_guide"][f"faces_{k}"] = int(arr.sum())
    meta["hit_choice_rays"] = meta.get("hit_choice_rays", 0) + int(part["probe_rays"].sum())


def _trace_direct(caster: RayCaster, mesh: Mesh, bands: int, samples: int, seed: int, sampling: str,
                  record_hits: bool, run: RunOptions, meta: dict, hit_columns: str = "vertices",
                  hits: HitBounce | None = None, estimator: str = "plain",
                  held: int | None = None) -> tuple[torch.Tensor, Any]:
    """Step 2: shadowed transfer t⁰ ``[V, n²]`` float64 over resumable chunks, and (when
    ``record_hits``) the bounce matrix S of the same rays (scipy CSR): ``[V, V]`` for
    ``hit_columns='vertices'``, ``[V, F]`` for ``'faces'``; with ``hits`` (the hit-point
    estimator) its bounce terms TB ``[V, B, C, n²]`` float64 instead. t⁰ and TB are assembled as
    each chunk finishes (``run_chunks``' sink) in :meth:`RunOptions.result_rows` — in a file
    beside the state directory when ``held`` (the bytes the whole assembly holds,
    :func:`held_bytes_per_vertex`) exceeds the streaming threshold."""
    V = mesh.num_vertices
    sampler = DiffuseSampler(bands, samples, seed, sampling, estimator)
    rpv = rays_per_vertex(samples, sampling)
    chunk_size = check_int("chunk_size", run.chunks(int(min(max(16, (1 << 20) // max(1, rpv)), 16384))), 1)
    frames = mesh.frames() if sampling == "cosine" else None
    faces_np = mesh.faces.numpy()
    tri = mesh.vertices.numpy()[faces_np]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # geometric face normals (winding)

    n_cols = {"faces": faces_np.shape[0], "corners": 3 * faces_np.shape[0]}.get(hit_columns, V)
    nudge = boundary_nudge(mesh)
    nudge = nudge if bool(nudge.any()) else None

    def compute(a: int, b: int) -> dict[str, torch.Tensor]:
        return _chunk(caster, sampler, mesh.vertices[a:b], mesh.normals[a:b],
                      None if frames is None else frames[a:b], faces_np, fn, n_cols, record_hits, hit_columns, hits, a,
                      None if nudge is None else nudge[a:b])

    fingerprint = {"mesh_hash": mesh.content_hash(), "bands": bands, "samples": samples, "seed": seed,
                   "sampling": sampling, "record_hits": record_hits, "offset": run.offset, "kind": "diffuse"}
    if estimator != "plain":
        fingerprint["estimator"] = estimator
    if record_hits and hit_columns != "vertices":
        fingerprint["hit_columns"] = hit_columns
    if hits is not None:
        fingerprint.update(hit_samples=hits.M, hit_terms=hits.terms, hit_offset=hits.hit_offset, **probe_fingerprint(hits))
    if record_hits and hits is None:
        parts = run.run_chunks(V, chunk_size, compute, fingerprint=fingerprint, desc=f"diffuse {mesh.name}",
                               rays_of=lambda r: int(r["rays"].sum()))
        meta["rays_traced"] = int(sum(int(p["rays"].sum()) for p in parts))
        T0 = torch.cat([p["T"] for p in parts]).to(torch.float64)
    else:  # each chunk copied in as it finishes: the transfer is never held twice
        # in memory, or file-backed (RunOptions.stream_result), decided once for every buffer of the assembly
        T0 = run.result_rows((V, bands * bands), torch.float64, name="t0", nbytes=held)
        TB = None if hits is None else run.result_rows((V, hits.terms, hits.C, bands * bands), torch.float64, name="tb",
                                                       nbytes=held)
        meta["rays_traced"] = 0
        seen: dict = {}

        def sink(a: int, b: int, p: dict[str, torch.Tensor]) -> None:
            T0[a:b] = p["T"]
            if TB is not None:
                TB[a:b] = p["TB"]
            meta["rays_traced"] += int(p["rays"].sum())
            if "hit_rays" in p:
                meta["hit_rays_traced"] = meta.get("hit_rays_traced", 0) + int(p["hit_rays"].sum())
            record_probe_log(meta, p, seen)

        run.run_chunks(V, chunk_size, compute, fingerprint=fingerprint, desc=f"diffuse {mesh.name}",
                       rays_of=lambda r: int(r["rays"].sum()), sink=sink)
    meta["chunk_size"] = chunk_size
    meta["rays_per_vertex"] = rpv if sampling != "uniform" else f"about {rpv} (the sphere set's directions above each tangent plane)"
    if not record_hits:
        return T0, None
    if hits is not None:
        return T0, TB  # [V, terms, C, n²]
    import scipy.sparse

    S = scipy.sparse.vstack([
        scipy.sparse.csr_matrix((p["S_data"].numpy(), p["S_indices"].numpy(), p["S_indptr"].numpy()),
                                shape=(p["T"].shape[0], n_cols)) for p in parts], format="csr")
    meta["bounce_matrix_nnz"] = int(S.nnz)
    return T0, S


def face_points(mesh: Mesh) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The surface points a bounce takes its exit radiance from: face centroids ``[F,3]``, unit
    geometric (winding) normals ``[F,3]`` and face albedo (mean of the vertices') ``[F,3]``,
    all float64. Degenerate faces get the normal +z (they are never hit)."""
    v = mesh.vertices.to(torch.float64)
    f = mesh.faces.to(torch.int64)
    tri = v[f]  # [F,3,3]
    fn = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], dim=-1)
    norm = fn.norm(dim=-1, keepdim=True)
    fn = torch.where(norm > 0, fn / norm.clamp_min(1e-300), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    return tri.mean(1), fn, mesh.albedo.to(torch.float64)[f].mean(1)


def face_state_dir(run: RunOptions) -> str | None:
    """Where the face pass keeps its finished chunks: ``<state_dir>.faces`` (beside the vertex
    pass's state, which must not exist before the vertex pass starts)."""
    return None if run.state_dir is None else os.fspath(run.state_dir) + ".faces"


def _trace_faces(caster: RayCaster, mesh: Mesh, bands: int, samples: int, seed: int, sampling: str,
                 record_hits: bool, run: RunOptions, meta: dict, points: str = "faces",
                 estimator: str = "plain") -> dict[str, Any]:
    """Step 2b (bounces with ``bounce_points`` 'faces' or 'corners'): the shadowed transfer x⁰
    of the reflector points over their face's own hemisphere (the same direction set and ray
    offset rule as the vertices) — ``[F, n²]`` at the face centroids, or ``[3F, n²]`` at each
    face's three corners (row 3f+k: corner k of face f) — and (``record_hits``, for bounces ≥ 2)
    the point-to-point bounce matrix ``[P, P]``. Resumable: chunks under :func:`face_state_dir`."""
    c, fn, rho_f = face_points(mesh)
    if points == "corners":
        f = mesh.faces.to(torch.int64)
        c = mesh.vertices.to(torch.float64)[f].reshape(-1, 3)  # [3F,3] the corners themselves
        fn = fn.repeat_interleave(3, 0)
        rho_f = mesh.albedo.to(torch.float64)[f].reshape(-1, 3)
    F = c.shape[0]
    sampler = DiffuseSampler(bands, samples, seed, sampling, estimator)
    rays_per_point = rays_per_vertex(samples, sampling)
    chunk_size = check_int("chunk_size", run.chunks(int(min(max(16, (1 << 20) // max(1, rays_per_point)), 16384))), 1)
    frames = None
    if sampling == "cosine":
        from ..scene.mesh import tangent_frames

        t, b = tangent_frames(fn.numpy())
        frames = torch.stack([torch.from_numpy(t), torch.from_numpy(b), fn], dim=-2)
    faces_np = mesh.faces.numpy()
    fn_np = face_points(mesh)[1].numpy()

    def compute(a: int, b: int) -> dict[str, torch.Tensor]:
        return _chunk(caster, sampler, c[a:b], fn[a:b], None if frames is None else frames[a:b], faces_np, fn_np, F,
                      record_hits, points, first_id=a)

    fingerprint = {"mesh_hash": mesh.content_hash(), "bands": bands, "samples": samples, "seed": seed,
                   "sampling": sampling, "record_hits": record_hits, "offset": run.offset, "kind": f"diffuse_{points}"}
    if estimator != "plain":
        fingerprint["estimator"] = estimator
    state = face_state_dir(run)
    if state is not None and not run.resume and os.path.exists(state):
        if os.path.exists(run.state_dir):  # an interrupted run: refused as the vertex pass would refuse it
            raise FileExistsError(f"state directory {os.fspath(run.state_dir)!r} holds an interrupted run; pass resume=True "
                                  "(CLI: --resume) to continue it, or remove it (CLI: --overwrite) to start again")
        remove_state(state)  # the face pass of a run whose state was discarded (CLI --overwrite)
    parts = run_chunks(F, chunk_size, compute, state_dir=state, fingerprint=fingerprint, resume=run.resume,
                       progress=run.progress, desc=f"diffuse faces {mesh.name}", rays_of=lambda r: int(r["rays"].sum()),
                       executor=run.executor)
    X0 = torch.cat([p["T"] for p in parts]).to(torch.float64)
    meta["rays_traced"] = meta.get("rays_traced", 0) + int(sum(int(p["rays"].sum()) for p in parts))
    meta["face_points"] = F
    S = None
    if record_hits:
        import scipy.sparse

        S = scipy.sparse.vstack([
            scipy.sparse.csr_matrix((p["S_data"].numpy(), p["S_indices"].numpy(), p["S_indptr"].numpy()),
                                    shape=(p["T"].shape[0], F)) for p in parts], format="csr")
        meta["face_bounce_matrix_nnz"] = int(S.nnz)
    return {"X0": X0, "S": S, "rho": rho_f, "normals": fn}


def resolve_hit_samples(hit_samples: int | str, estimator: str) -> int:
    """Rays per first hit: ``hit_samples`` checked in [1, 4096], or for 'auto' the estimator's
    :data:`HIT_SAMPLES_AUTO`."""
    if hit_samples == "auto":
        return HIT_SAMPLES_AUTO[check_choice("estimator", estimator, ESTIMATORS)]
    if isinstance(hit_samples, str):
        raise ValueError(f"hit_samples={hit_samples!r}; accepted: an integer in [1, 4096] or 'auto'")
    return check_int("hit_samples", hit_samples, 1, 4096)


def vertex_transfer(mesh: Mesh, idx: Any, bands: int, samples: int, seed: int, bounces: int = 0, *,
                    sampling: str = "qmc", offset: float = 1e-4, hit_samples: int | str = "auto",
                    hit_offset: float | None = HIT_OFFSET, estimator: str = "auto") -> tuple[torch.Tensor, torch.Tensor | None]:
    """What ``precompute_diffuse(..., bounce_points='hits')`` computes for the vertices ``idx``
    alone (the same rays, keys and offsets): ``(t⁰ [k, n²], TB [k, B, C, n²] or None)`` float64,
    ρ_p kept out. Cheap for a few vertices (no pass over the mesh): the validator uses it to
    measure the engine's Monte Carlo noise by re-running other seeds."""
    idx = torch.as_tensor(idx, dtype=torch.int64)
    hit_samples = resolve_hit_samples(hit_samples, estimator)
    frames = mesh.frames()[idx] if sampling == "cosine" else None
    nudge = boundary_nudge(mesh)[idx]
    run = RunOptions(offset=offset)
    with RayCaster(mesh, workers=_workers(run, mesh, samples, sampling), offset=offset) as caster:
        hits = (HitBounce(mesh, bands, hit_samples, seed, bounces, 1 if mesh.is_grey() else 3, hit_offset, estimator,
                          FIRST_PROBE_RAYS) if bounces > 0 else None)
        faces_np = mesh.faces.numpy()
        out = _chunk(caster, DiffuseSampler(bands, samples, seed, sampling, estimator), mesh.vertices[idx], mesh.normals[idx], frames,
                     faces_np, face_points(mesh)[1].numpy(), faces_np.shape[0], bounces > 0, "hits" if bounces else "vertices",
                     hits, 0, nudge, idx.numpy())
    return out["T"].to(torch.float64), out.get("TB")


def hit_bounce(mesh: Mesh, bands: int, samples: int, seed: int, bounces: int, offset: float = 1e-4,
               hit_samples: int | str = "auto", sampling: str = "uniform", hit_offset: float | None = HIT_OFFSET,
               estimator: str = "plain", meta: dict | None = None) -> HitBounce:
    """The :class:`HitBounce` a diffuse precompute with ``bounces`` ≥ 1 uses (its face tables
    traced here): a glossy/MRT vertex with ``bounces`` bounces reads the same hit values, so
    its interreflection equals the diffuse one. ``meta``: receives what :func:`_hit_tables`
    records (hit settings; under 'auto' the probe's ``hit_choice_rays`` and ``hit_guide``)."""
    bounces = check_int("bounces", bounces, 1, MAX_BOUNCES)
    hit_samples = resolve_hit_samples(hit_samples, estimator)
    run = RunOptions(offset=offset)
    with RayCaster(mesh, workers=_workers(run, mesh, samples, sampling), offset=offset) as caster:
        return _hit_tables(caster, mesh, bands, samples, seed, sampling, bounces, hit_samples, run,
                           {} if meta is None else meta, hit_offset, estimator)


def face_transfer(mesh: Mesh, bands: int, samples: int, seed: int, bounces: int, offset: float = 1e-4,
                  sampling: str = "uniform") -> tuple[torch.Tensor, torch.Tensor]:
    """Diffuse transfer of every face (at its centroid, over its own hemisphere) with ``bounces``
    bounces and the face albedo folded in: ``([F, C, n²] float64, unit face normals [F, 3])``,
    C = 3 for coloured albedo, else 1. What a bounce ray hitting face f brings (exit radiance
    x_f · l); used by the glossy/MRT interreflection so that it equals the diffuse bounces."""
    bands = check_int("bands", bands, 1, MAX_DIFFUSE_BANDS)
    samples = check_int("samples", samples, 1, MAX_SAMPLES)
    bounces = check_int("bounces", bounces, 0, MAX_BOUNCES)
    run = RunOptions(offset=offset)
    meta: dict[str, Any] = {}
    with RayCaster(mesh, workers=_workers(run, mesh, samples, sampling), offset=offset) as caster:
        fc = _trace_faces(caster, mesh, bands, samples, seed, sampling, bounces > 0, run, meta)
    C = 1 if mesh.is_grey() else 3
    rho = fc["rho"][:, :1] if C == 1 else fc["rho"]  # [F,C]
    F, n2 = fc["X0"].shape
    x = fc["X0"][:, None, :].expand(F, C, n2).clone()
    total = x.clone()
    for _ in range(bounces):  # a loop over bounces: each one sparse product over all faces
        x = torch.from_numpy(fc["S"] @ (rho[:, :, None] * x).reshape(F, C * n2).numpy()).reshape(F, C, n2)
        total += x
    return rho[:, :, None] * total, fc["normals"]


def _record_bounce_decision(meta: dict, used: int, energy: list, bounces: int) -> None:
    """The bounce stopping rule's outcome into ``meta``: bounces used, each bounce's energy fraction
    (‖term‖ / ‖total so far‖) and the one-line reason (both assembly paths, in memory and by row blocks)."""
    meta["bounces_used"] = used
    meta["bounce_energy_fraction"] = energy
    meta["bounce_decision"] = (f"stopped after {used} of {bounces} bounces"
                               + (f" (bounce {used} added {energy[-1]:.3g} < bounce_tol)" if used < bounces else ""))


def _interreflect(T0: torch.Tensor, S: Any, mesh: Mesh, bounces: int, bounce_tol: float, meta: dict,
                  faces: dict | None = None) -> tuple[torch.Tensor, int]:
    """Step 3 for the sparse bounce matrices (``bounce_points`` 'vertices', 'faces', 'corners';
    no bounce and the hit-point estimator go by blocks of rows: :func:`_bounce_decision`,
    :func:`_assemble`): t = Σ_b t̃^b (course notes 2005, "Interreflections"), ρ_p kept out.
    Returns (``[V, C, n²]`` float64, C) with C = 3 only for coloured bounces. Each bounce reads
    every row of the one before (a sparse product over the whole mesh), so it is held in memory.

    ``faces`` None (``bounce_points='vertices'``): t̃^b = S (ρ ⊙ t̃^{b-1}) with S ``[V,V]``.
    ``faces`` given: the hit face's own transfer x_f (centroid, face hemisphere) is what a bounce
    ray brings: t̃^b = S_vf (ρ_f ⊙ x^{b-1}), x^b = S_ff (ρ_f ⊙ x^{b-1}), x⁰ the faces' direct pass."""
    V, n2 = T0.shape
    rho = mesh.albedo.to(torch.float64)
    C = 1 if mesh.is_grey() else 3
    rho_c = rho[:, :1] if C == 1 else rho  # [V,C]
    tb = T0[:, None, :].expand(V, C, n2).clone()  # t̃⁰ (ρ_p kept out)
    total = tb.clone()
    energy = []
    used = 0
    if faces is not None:
        F = faces["X0"].shape[0]
        rho_c = faces["rho"][:, :1] if C == 1 else faces["rho"]  # [F,C]: the reflectors are faces
        xf = faces["X0"][:, None, :].expand(F, C, n2).clone()

    def bounce_terms():  # t̃^1, t̃^2, ... lazily, so a converged sum stops computing
        nonlocal tb
        xb = xf if faces is not None else None
        for b in range(1, bounces + 1):  # each bounce one sparse product over all vertices
            if faces is None:
                tb = torch.from_numpy(S @ (rho_c[:, :, None] * tb).reshape(V, C * n2).numpy()).reshape(V, C, n2)
            else:
                x = (rho_c[:, :, None] * xb).reshape(F, C * n2).numpy()
                tb = torch.from_numpy(S @ x).reshape(V, C, n2)
                if b < bounces:
                    xb = torch.from_numpy(faces["S"] @ x).reshape(F, C, n2)
            yield tb

    for b, term in enumerate(bounce_terms(), 1):  # a loop over bounces
        total += term
        used = b
        frac = float(term.norm() / total.norm().clamp_min(1e-300))
        energy.append(frac)
        if frac < bounce_tol:
            break
    _record_bounce_decision(meta, used, energy, bounces)
    return total, C


#: rows per block of the diffuse assembly (bounce sums, albedo, float32 rows): a few MiB of temporaries
ASSEMBLE_ROWS = 1 << 14


def held_bytes_per_vertex(bands: int, hit_terms: int, hit_channels: int, channels: int) -> int:
    """Bytes per vertex the diffuse assembly holds (:func:`_assemble`): t⁰ ``[n²]`` float64, the
    hit-point estimator's bounce terms ``[hit_terms, hit_channels, n²]`` float64 and the stored
    rows ``[channels, n²]`` float32. A result whose assembly holds more than the streaming
    threshold (``RunOptions.streams_result``) is assembled in files; the dry run counts the same."""
    n2 = int(bands) ** 2
    return 8 * n2 + 8 * int(hit_terms) * int(hit_channels) * n2 + 4 * int(channels) * n2


def _block_total(T0: torch.Tensor, TB: torch.Tensor | None, C: int, a: int, b: int, terms: int) -> torch.Tensor:
    """t̃⁰ + Σ_{k<terms} t̃^{k+1} of rows a..b-1, ``[b-a, C, n²]`` float64 (ρ_p kept out): the
    running sum of :func:`_interreflect`, in the same order (a new tensor: the rows are not changed)."""
    tot = T0[a:b, None, :].expand(b - a, C, T0.shape[1]).clone()
    for k in range(terms):  # a loop over bounces
        t = TB[a:b, k]
        tot += t if t.shape[1] == C else t.expand(-1, C, -1)
    return tot


def _bounce_decision(T0: torch.Tensor, TB: torch.Tensor | None, mesh: Mesh, bounces: int, bounce_tol: float,
                     meta: dict, rows: int = ASSEMBLE_ROWS) -> tuple[int, int]:
    """Step 3 without the sum (no bounce term, or the hit-point estimator's terms ``TB [V, B, C, n²]``):
    how many bounce terms the stored transfer keeps (course notes 2005, "Interreflections": stop once
    a bounce adds less than ``bounce_tol`` of the accumulated transfer's norm, that bounce kept).
    The norms are accumulated over blocks of ``rows`` rows (sums of squares in float64), so the
    rows may live in a file (:meth:`RunOptions.result_rows`). Returns (channels C, bounces used)."""
    C = 1 if (mesh.is_grey() or TB is None) else 3
    if bounces == 0 or TB is None:  # no bounce term: t = t⁰ itself
        meta["bounces_used"], meta["bounce_energy_fraction"] = 0, []
        if bounces > 0:
            meta["bounce_decision"] = "no interreflection: shadow rays were not traced (no occluding geometry)"
        return C, 0
    B = min(bounces, TB.shape[1])
    ss_term = torch.zeros(B, dtype=torch.float64)
    ss_total = torch.zeros(B, dtype=torch.float64)
    for a in range(0, T0.shape[0], rows):
        b = min(T0.shape[0], a + rows)
        tot = _block_total(T0, TB, C, a, b, 0)
        for k in range(B):  # a loop over bounces
            t = TB[a:b, k]
            t = t if t.shape[1] == C else t.expand(-1, C, -1)
            tot += t
            ss_term[k] += t.square().sum()
            ss_total[k] += tot.square().sum()
    energy, used = [], 0
    for k in range(B):
        used = k + 1
        frac = float(ss_term[k].sqrt() / ss_total[k].sqrt().clamp_min(1e-300))
        energy.append(frac)
        if frac < bounce_tol:
            break
    _record_bounce_decision(meta, used, energy, bounces)
    return C, used


def _irradiance_rows(T0: torch.Tensor, TB: torch.Tensor | None, C: int, used: int,
                     rows: int = ASSEMBLE_ROWS) -> torch.Tensor:
    """``[V, n²]`` float64 in memory: the transfer with ``used`` bounces, channels averaged (ρ_p
    kept out) — what a subsurface term spreads (``subsurface.add_term``: its hierarchy reads every
    sample, so this is held whole), built by blocks of rows."""
    out = torch.empty(T0.shape, dtype=torch.float64)
    for a in range(0, T0.shape[0], rows):
        b = min(T0.shape[0], a + rows)
        out[a:b] = _block_total(T0, TB, C, a, b, used).mean(1)
    return out


def _assemble(T0: torch.Tensor, TB: torch.Tensor | None, C: int, used: int, mesh: Mesh, fold: bool, meta: dict,
              run: RunOptions, L: torch.Tensor | None = None, held: int | None = None,
              rows: int = ASSEMBLE_ROWS) -> torch.Tensor:
    """Steps 3 and 4 by blocks of rows: t = t̃⁰ + Σ_{b≤used} t̃^b (``TB``), the albedo folded
    (``[V, 3, n²]``) or kept out (``[V, n²]``), plus a subsurface term ``L [V, 3, n²]`` (float64),
    cast to float32 into :meth:`RunOptions.result_rows` (a file when ``held`` exceeds the streaming
    threshold). Every step is elementwise, so the bits do not depend on where the rows live;
    they are those of :func:`_interreflect` + :func:`_store_albedo` on the whole tensors."""
    V, n2 = T0.shape
    meta["albedo_folded"] = bool(fold)
    meta["channels"] = 3 if fold else 1
    out = run.result_rows((V, 3, n2) if fold else (V, n2), torch.float32, nbytes=held)
    rho = mesh.albedo.to(torch.float64) if fold else None
    for a in range(0, V, rows):
        b = min(V, a + rows)
        tot = _block_total(T0, TB, C, a, b, used)
        x = rho[a:b, :, None] * tot.expand(b - a, 3, n2) if fold else tot[:, 0, :]
        if L is not None:
            x = x + L[a:b]
        out[a:b] = x
    return out


def _store_albedo(total: torch.Tensor, mesh: Mesh, C: int, fold_albedo: bool | None, meta: dict) -> torch.Tensor:
    """Step 4: ``[V, 3, n²]`` with the albedo folded in, or ``[V, n²]`` without (module docstring)."""
    fold = (C == 3) if fold_albedo is None else bool(fold_albedo)
    meta["albedo_folded"] = fold
    meta["channels"] = 3 if fold else 1
    if fold:
        V, _, n2 = total.shape
        return mesh.albedo.to(torch.float64)[:, :, None] * total.expand(V, 3, n2)
    return total[:, 0, :]
