"""Glossy transfer matrices: transferred radiance T_p and exit-radiance transfer
M_p = B R_p T_p (Sloan 2003 §3.1), and the machinery shared with matrix radiance transfer
(:mod:`prt_torch.transfer.mrt`, A_p = G⁻¹ C B_p R_p T_p).

Quantities per vertex p (lighting l is a *global* SH radiance vector, n² = ``bands²``):

* T_p (n² × n², global frame; Sloan et al. 2002 shadowed glossy transfer):
  (T_p)_ij = ∫ y_i(s) y_j(s) V_p(s) [n_p·s > 0] ds, so T_p l are the SH coefficients of the
  transferred incident radiance L(s) V_p(s), zeroed below the tangent plane (the
  "zero-hemisphere" transferred radiance of Sloan 2003 §3.2). Monte Carlo over one shared
  stratified sphere set {s_k} with weights 4π/N: T_p = Σ_k w_k V_pk y(s_k) y(s_k)ᵀ, summed over
  only each vertex's selected directions (:func:`outer_sums`: one rank-1 update per entry in a
  compiled pass, ``kernels/glossy.c``; no dense ``[k, N]`` weights or ``[k, N, n²]`` hit buffer).
* R_p (block-diagonal SH rotation, Kautz et al. 2002; Sloan 2003 §3.1): D(F_p) with F_p the
  rows (t, b, n) of ``Mesh.frames()``; R_p T_p l is the transferred radiance in the local
  frame (normal = +z, tangent = +x).
* M_p = B_p R_p T_p (N_r × N_i; Sloan 2003 §3.1, eq. (1) with the least-squares projection
  folded into B; N_r = m² or m² - 1 with (1,0) dropped, §6.1). Exit radiance towards the
  local view v: L_out = Σ_r y_{o(r)}(v) (M_p l)_r with o = ``meta['out_index']``.
* A_p = (G⁻¹ C) B_p R_p T_p (M² × n²; Lehtinen & Kautz eq. 9): exit radiance in the tent basis,
  L_out(v) = Σ_{4 taps j} g_j(v) (A_p l)_j (eq. 13 without PCA).

Interreflection (``bounces > 0``): a blocked direction s brings the diffuse exit radiance of
the point q it hits, t_q·l (diffuse transfer with one bounce fewer, interpolated over the hit
triangle; backs black), so T_p gains Σ_s w_s (1 - V(p,s)) y(s) t_q(s)ᵀ — Sloan et al. 2002
§5 with diffuse reflectors (see :func:`transferred_radiance`).
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Any

import numpy as np
import torch

from .._checks import check_choice, check_int, describe
from ..executor import torch_threads
from ..io import format_bytes
from ..brdf import BRDF, AshikhminShirley, brdf_matrices, output_index
from ..scene import Mesh, RayCaster, default_workers
from ..sh import blocks_to_dense, eval_sh, hemisphere_gram, rotation_blocks
from .base import RunOptions, Transfer
from .diffuse import HitBounce, boundary_nudge, hit_bounce, offset_origins, probe_fingerprint, record_probe_log
from .ray_kernels import outer_accumulate, upper_rays
from .sampling import uniform_sphere

__all__ = [
    "MAX_GLOSSY_BANDS",
    "ESTIMATORS",
    "check_frames",
    "check_brdf",
    "check_memory",
    "check_common",
    "decide_shadows",
    "default_chunk",
    "estimate_memory",
    "transferred_radiance",
    "unshadowed_transferred",
    "outer_sums",
    "rotate_rows",
    "run_exit_transfer",
    "submesh",
    "precompute_glossy",
]

MAX_GLOSSY_BANDS = 16
#: torch threads inside a glossy/MRT chunk (None: torch's default).
CHUNK_THREADS: int | None = 1
MAX_SAMPLES = 1 << 18
#: T_p's estimators: per vertex the smaller part ('auto'), the exact unshadowed T_p minus the blocked
#: directions ('control') or the visible sum ('plain'); with bounces the hit points read the diffuse
#: estimator of the same name (:class:`~prt_torch.transfer.diffuse.HitBounce`).
ESTIMATORS = ("auto", "control", "plain")


def _available_memory() -> int:
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover
        return 16 << 30


def check_frames(mesh: Mesh, tol: float = 1e-6) -> torch.Tensor:
    """Return ``mesh.frames()`` ``[V, 3, 3]`` float64 after checking every frame is a proper
    rotation (rows orthonormal, det +1, finite): R_p needs one per vertex. Raises naming the
    number of bad vertices and the first."""
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a prt_torch.scene.Mesh, got {describe(mesh)}")
    F = mesh.frames().to(torch.float64)
    ok = torch.isfinite(F).all(dim=(-1, -2))
    dev = (F @ F.transpose(-1, -2) - torch.eye(3, dtype=torch.float64)).abs().amax(dim=(-1, -2))
    det = torch.linalg.det(torch.where(ok[:, None, None], F, torch.eye(3, dtype=torch.float64)))
    good = ok & (dev <= tol) & (det > 0)
    if not bool(good.all()):
        bad = torch.nonzero(~good).flatten()
        i = int(bad[0])
        raise ValueError(
            f"mesh {mesh.name!r} has {bad.numel()} vertices without a usable tangent frame (first: vertex {i}, "
            f"|F Fᵀ - I| = {float(dev[i]) if bool(ok[i]) else float('nan'):.3g}, det = {float(det[i]):.3g}); accepted: "
            "orthonormal right-handed rows (t, b, n) — rebuild the frames with prt_torch.scene.tangent_frames"
        )
    return F


def estimate_memory(vertices: int, n_out: int, n_in: int, samples: int, chunk_size: int, streamed: bool = False,
                    bounces: int = 0) -> int:
    """Bytes a glossy/MRT precompute holds at its peak: the float32 result once (each chunk is
    copied into it as it finishes: ``run_chunks``' sink; none when it is assembled in a file,
    ``RunOptions.stream_result``) plus one chunk's working set (cosines, the upper pairs' indices, rays,
    float64 matrices). No ``[N, n⁴]`` outer-product table and no dense ``[k, N]`` weights: the sums run
    over each vertex's entries (:func:`outer_sums`). With ``bounces``: the chunk's interreflected part
    (:func:`transferred_radiance`) holds the hits' exit transfers ``[H, n²]`` float64 (H up to the
    k·N/2 directions above the tangent planes), their records and the hit estimator's per-batch
    buffers: counted as ``k · N · n² · 8`` bytes (the ``[k, N, n²]`` hit buffer the sums once
    scattered into is gone; ``reports/benchmarks/precompute_estimate.md``, command-line section)."""
    result = 0 if streamed else vertices * n_out * n_in * 4
    chunk = chunk_size * (samples * (8 + 3 * 8 * 2 + 16) + n_in * n_in * 8 * 3 + n_out * n_in * 8 * 2)
    if bounces:
        chunk += chunk_size * samples * n_in * 8
    return int(result + chunk)


def memory_budget(max_memory: int | None) -> int:
    """The byte budget of a precompute: ``max_memory``, or (None) 60% of the machine's RAM."""
    return int(0.6 * _available_memory()) if max_memory is None else int(max_memory)




class _Directions:
    """Shared stratified sphere set: directions ``dirs [N, 3]`` float64 (and float32), weight 4π/N,
    SH values ``Y [N, n²]`` float64 evaluated once. (No ``[N, n⁴]`` table of outer products, 8·N·n⁴
    bytes: the sums take y(s) yᵀ per entry, :func:`outer_sums`.)"""

    def __init__(self, bands: int, samples: int, seed: int):
        self.dirs, w = uniform_sphere(samples, seed)  # [N,3] float64, weights 4π/N
        self.weight = float(w[0])
        self.Y = eval_sh(self.dirs, bands)  # [N, n²]
        self.dirs32 = np.ascontiguousarray(self.dirs.numpy(), np.float32)
        self.n2 = bands * bands


#: entries per torch step of :func:`outer_sums` without the compiled pass ([B, n², n²] float64 at a time)
OUTER_BATCH = 2048


def outer_sums(k: int, rows: torch.Tensor, dirs: torch.Tensor, Y: torch.Tensor, c: float,
               R: torch.Tensor | None = None) -> torch.Tensor:
    """``S [k, n², n²]`` float64 with S[p] = c · Σ_{e: rows_e = p} y(s_{dirs_e}) r_eᵀ, r_e = ``R[e]``
    or (None) y(s_{dirs_e}): the Monte Carlo sums of T_p (Sloan et al. 2002 §4–5; module docstring)
    over only the entries given — a vertex's selected (direction, hit) pairs — instead of dense
    ``[k, N]`` / ``[k, N, n²]`` buffers multiplied by the whole set (issue 42 §2).

    ``rows, dirs int64 [E]`` (``rows`` nondecreasing: entries grouped by vertex, as ``torch.nonzero``
    gives them); ``Y float64 [N, n²]``; ``R float64 [E, n²]`` or None. The compiled pass
    (:func:`~prt_torch.transfer.ray_kernels.outer_accumulate`) adds each vertex's entries in their
    order (bits independent of chunking and threads); without it torch adds ``OUTER_BATCH`` entries'
    outer products at a time with ``index_add_`` (the same sums, float64 rounding apart)."""
    n2 = Y.shape[1]
    S = torch.zeros(k, n2, n2, dtype=torch.float64)
    E = int(rows.numel())
    if E == 0:
        return S
    if bool((rows[1:] < rows[:-1]).any()) or int(rows[0]) < 0 or int(rows[-1]) >= k:
        raise ValueError(f"outer_sums: rows must be nondecreasing in [0, {k}) (entries grouped by vertex); got rows in "
                         f"[{int(rows.min())}, {int(rows.max())}], sorted: {not bool((rows[1:] < rows[:-1]).any())}")
    ptr = torch.zeros(k + 1, dtype=torch.int64)
    ptr[1:] = torch.cumsum(torch.bincount(rows, minlength=k), 0)
    Rn = None if R is None else R.to(torch.float64).contiguous().numpy()
    if outer_accumulate(S.numpy(), ptr.numpy(), dirs.numpy(), Y.numpy(), c, Rn, threads=torch.get_num_threads()):
        return S
    flat = S.view(k, n2 * n2)
    for a in range(0, E, OUTER_BATCH):  # batches of entries (not of vertices): [B, n², n²] at a time
        y = Y[dirs[a:a + OUTER_BATCH]]
        r = y if R is None else R[a:a + OUTER_BATCH].to(torch.float64)
        flat.index_add_(0, rows[a:a + OUTER_BATCH], ((y * c)[:, :, None] * r[:, None, :]).reshape(-1, n2 * n2))
    return S


def unshadowed_transferred(normals: torch.Tensor, bands: int, blocks: list[torch.Tensor] | None = None) -> torch.Tensor:
    """The exact unshadowed T_p: (T_p)_ij = ∫_{n_p·s > 0} y_i(s) y_j(s) ds, ``[k, n², n²]``
    float64, as D_pᵀ A D_p with A the hemisphere Gram matrix over z ≥ 0 (Sloan 2003 Appendix
    §9.1, :func:`prt_torch.sh.hemisphere_gram`) and D_p the SH rotation into a frame whose third
    axis is n_p (y(s) = D_pᵀ y(F_p s); A is invariant under rotations about z, so any tangent
    frame serves). The control variate of :func:`transferred_radiance`. ``blocks``: the
    points' :func:`~prt_torch.sh.rotation_blocks` into frames whose third axis is the normal, when
    the caller has them already (the exit-transfer driver rotates its rows with the same blocks)."""
    from ..scene.mesh import tangent_frames

    if blocks is None:
        n = normals.to(torch.float64)
        t, b = tangent_frames(n.numpy())
        F = torch.stack([torch.from_numpy(t), torch.from_numpy(b), n], dim=-2)  # [k,3,3] rows (t, b, n)
        blocks = rotation_blocks(F, bands)
    D = blocks_to_dense(blocks)  # [k, n², n²]
    return D.transpose(1, 2) @ hemisphere_gram(bands) @ D


def transferred_radiance(caster: RayCaster | None, points: torch.Tensor, normals: torch.Tensor,
                         directions: _Directions, bounce: "Bounce | None" = None,
                         ids: torch.Tensor | None = None, nudge: torch.Tensor | None = None,
                         estimator: str = "plain", blocks: list[torch.Tensor] | None = None) -> tuple[torch.Tensor, int]:
    """T_p for a chunk of points (module docstring): ``[k, n², n²]`` float64 and rays traced.
    ``caster=None`` skips visibility (unshadowed: only the tangent-plane cut).

    ``bounce``: interreflection. A direction s blocked by the mesh brings the exit radiance of
    the point q it hits, x_q·l, where x_q is the diffuse transfer of q itself over the hit face's
    hemisphere (with its own shadowing and one bounce fewer, albedo folded), estimated at the hit
    by :class:`prt_torch.transfer.diffuse.HitBounce` with the keys (vertex id ``ids``, direction
    index) the diffuse precompute uses — so a Lambertian glossy transfer equals the diffuse one;
    the backs of triangles are black (as in the diffuse bounces). Ray origins follow
    :func:`~prt_torch.transfer.diffuse.offset_origins`. So
    T_p = Σ_s w_s [V(p,s) y(s) y(s)ᵀ + (1 - V(p,s)) y(s) t_q(s)ᵀ] over n·s > 0
    (Sloan et al. 2002 §5's interreflected transfer, with diffuse reflectors).

    ``estimator='control'`` (issue 42): the first term as the exact unshadowed T_p
    (:func:`unshadowed_transferred`) minus Σ_s w_s (1 − V(p,s)) y(s) y(s)ᵀ over the blocked
    directions — the same rays, unbiased, exact where nothing is blocked; 'plain': the sum;
    'auto': per vertex the control variate where at least half of its directions above the
    tangent plane are open and the plain sum elsewhere (the diffuse 'auto''s rule: the smaller
    part sampled, exact for an open and for an enclosed vertex; choosing from the same rays leaves
    a second-order bias, not detected at 3σ in tests/test_precompute_estimators.py). In a closed
    room (Cornell box) 'control' had 1.5–1.7× the error of 'plain' (N = 1024)
    (reports/benchmarks/precompute_error.md, glossy section)."""
    cos = normals.to(torch.float64) @ directions.dirs.T  # [k, N]
    k = cos.shape[0]
    fused = None
    if caster is not None:
        o_v = offset_origins(caster.local(points.to(torch.float64).numpy()), normals.to(torch.float64).numpy(), caster.eps,
                             None if nudge is None else nudge.numpy()).astype(np.float32)  # the one offset rule
        fused = upper_rays(cos.numpy(), o_v, directions.dirs32)  # the rays above each tangent plane in one compiled pass
    if fused is not None:
        i, j, o, d = torch.from_numpy(fused[0]), torch.from_numpy(fused[1]), fused[2], fused[3]
    else:  # the same pairs, origins and directions (upper_rays' numpy equivalent)
        i, j = torch.nonzero(cos > 0, as_tuple=True)  # grouped by vertex (row-major): outer_sums' entries
        if caster is not None:
            o, d = o_v[i.numpy()], directions.dirs32[j.numpy()]
    T_ind = None
    open_v = None  # [k] bool: the rows estimated by the control variate
    if caster is not None and i.numel():
        if bounce is None:
            vis = ~torch.from_numpy(caster.trace(o, d, "occluded"))
        else:
            prim, bu, bv, _ = caster.trace(o, d, "intersect")
            hit = torch.from_numpy(prim != -1)
            vis = ~hit
            h = torch.nonzero(hit).flatten()
            th = torch.from_numpy(prim.astype(np.int64))[h]
            front = (bounce.hits.face_normals[th] * directions.dirs[j[h]]).sum(-1) < 0
            h, th = h[front].numpy(), th[front].numpy()
            bary = np.stack([1 - bu[h] - bv[h], bu[h], bv[h]], 1).astype(np.float64)
            vid = (torch.arange(points.shape[0]) if ids is None else ids.to(torch.int64))[i].numpy()
            t_hit = bounce.hits.exit_transfer(caster, th, bary, vid[h], j.numpy()[h], _LUMA)  # [H, n²] at the hit itself
            h = torch.from_numpy(h)
            # Σ_s w y(s) t_q(s)ᵀ over each vertex's front hits: the radiance transfer arriving along its blocked directions
            T_ind = outer_sums(k, i[h], j[h], directions.Y, directions.weight, R=t_hit)  # [k, n², n²]
        if estimator == "auto":  # per vertex: the control variate where at least half of its upper directions are open
            open_v = torch.bincount(i[vis], minlength=k) * 2 >= torch.bincount(i, minlength=k)  # [k]
            sel = vis != open_v[i]  # the blocked directions of open vertices, the visible ones of the others
        else:
            open_v = torch.full((k,), estimator == "control")
            sel = ~vis if estimator == "control" else vis
        # Σ_s w y(s) y(s)ᵀ over the selected directions (control rows: the blocked ones, subtracted below)
        T = outer_sums(k, i[sel], j[sel], directions.Y, directions.weight)
    else:
        T = outer_sums(k, i, j, directions.Y, directions.weight)  # every direction above the tangent plane
    if caster is not None and estimator != "plain" and open_v is None:  # no direction above any tangent plane
        open_v = torch.full((k,), True)
    if open_v is not None and bool(open_v.any()):
        U = unshadowed_transferred(normals, int(round(math.sqrt(directions.n2))), blocks)
        T = torch.where(open_v[:, None, None], U - T, T)
    if T_ind is not None:
        T += T_ind
    return T, int(i.numel()) if caster is not None else 0


@dataclasses.dataclass
class Bounce:
    """What the glossy interreflection needs: the diffuse precompute's hit-point estimator
    (:class:`prt_torch.transfer.diffuse.HitBounce`; its face probe traced by the chunks where their hits land)."""

    hits: HitBounce


#: Luminance weights (Rec. 709) used to make a coloured bounce table monochrome: glossy
#: transfer matrices are one per vertex, shared by the colour channels of the light.
_LUMA = torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64)


def bounce_table(mesh: Mesh, bands: int, samples: int, seed: int, bounces: int, offset: float,
                 estimator: str = "plain", meta: dict | None = None) -> Bounce:
    """What a blocked direction brings (the hit point's diffuse transfer with ``bounces - 1``
    bounces), via :func:`prt_torch.transfer.diffuse.hit_bounce` — the estimator the diffuse
    bounces use (coloured albedo becomes luminance: one matrix per vertex). ``meta`` receives the
    hit settings and, under 'auto', the face probe's ray count (``hit_choice_rays``) and guide."""
    return Bounce(hits=hit_bounce(mesh, bands, samples, seed, bounces, offset=offset, estimator=estimator, meta=meta))


def rotate_rows(T: torch.Tensor, blocks: list[torch.Tensor]) -> torch.Tensor:
    """R_p T_p: apply per-vertex block-diagonal SH rotations (``rotation_blocks(F [k,3,3])``)
    to the rows of ``T [k, n², c]``. A loop over bands (n iterations), each a batched matmul."""
    bands = int(round(math.sqrt(T.shape[1])))
    out = torch.empty_like(T)
    for l in range(bands):
        a, b = l * l, (l + 1) * (l + 1)
        out[:, a:b] = blocks[l].to(T.dtype) @ T[:, a:b]
    return out


def check_brdf(mesh: Mesh, brdf: BRDF | None) -> BRDF:
    if brdf is None:
        return AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0)
    if not isinstance(brdf, BRDF):
        raise TypeError(f"brdf must be a prt_torch.brdf.BRDF, got {describe(brdf)}")
    bs = brdf.batch_shape
    if len(bs) not in (0, 1) or (len(bs) == 1 and bs[0] not in (1, mesh.num_vertices)):
        raise ValueError(f"brdf parameters have batch shape {tuple(bs)}; accepted: scalars (one material) or "
                         f"[V] = [{mesh.num_vertices}] (one per vertex)")
    return brdf


def run_exit_transfer(
    kind: str, mesh: Mesh, left: torch.Tensor, index: torch.Tensor, bands: int, samples: int, seed: int,
    shadows: bool, run: RunOptions, fingerprint: dict, vertices: torch.Tensor | None, bounces: int = 0,
    estimator: str = "plain",
) -> tuple[torch.Tensor, dict]:
    """Shared driver of glossy and MRT: data[p] = left[index[p]] @ R_p T_p over chunks of
    vertices (``left``: ``[U, n_out, n²]`` float64, e.g. B or G⁻¹CB; empty = identity, the
    global T_p). Returns (data ``[V, n_out, n²]`` float32, run meta)."""
    F_all = check_frames(mesh)
    n2 = bands * bands
    sel = torch.arange(mesh.num_vertices) if vertices is None else vertices
    V = int(sel.numel())
    n_out = left.shape[1] if left.numel() else n2
    rays_per_vertex = max(1, samples // 2)
    chunk_size = check_int("chunk_size", run.chunks(default_chunk(samples)), 1)
    need = check_memory(kind, V, n_out, n2, samples, chunk_size, run.max_memory, run.streams_result(V * n_out * n2 * 4),
                        bounces)
    directions = _Directions(bands, samples, seed)
    caster = None
    meta: dict[str, Any] = {"estimated_bytes": need, "chunk_size": chunk_size, "estimator": estimator}
    t0 = time.perf_counter()
    try:
        if shadows:
            workers = run.workers
            if workers is None:
                workers = default_workers() if V * rays_per_vertex >= 4_000_000 else 1
            caster = RayCaster(mesh, workers=workers, offset=run.offset).start()
            meta["ray_eps"] = caster.eps
        nudge = boundary_nudge(mesh) if shadows else None  # the diffuse tracer's origins (offset_origins)
        nudge = nudge if nudge is not None and bool(nudge.any()) else None
        bounce = None
        if bounces:
            if not shadows:
                raise ValueError("bounces > 0 needs shadows traced (interreflected light arrives along blocked directions)")
            tb = time.perf_counter()
            bounce = bounce_table(mesh, bands, samples, seed, bounces, run.offset, estimator, meta)
            meta["bounce_table_seconds"] = time.perf_counter() - tb
            # the face probe's settings (as the diffuse run's): chunks of an earlier probe do not mix into a resumed run
            fingerprint = {**fingerprint, **probe_fingerprint(bounce.hits)}

        def compute(a: int, b: int) -> dict[str, torch.Tensor]:
            if CHUNK_THREADS is None:
                return chunk_work(a, b)
            with torch_threads(CHUNK_THREADS):  # as the diffuse chunk: the cores are the ray-casting workers'
                return chunk_work(a, b)

        def chunk_work(a: int, b: int) -> dict[str, torch.Tensor]:
            idx = sel[a:b]
            blocks = rotation_blocks(F_all[idx], bands) if left.numel() or estimator != "plain" else None  # once per chunk
            hit0 = 0 if bounce is None else bounce.hits.rays_traced
            T, rays = transferred_radiance(caster, mesh.vertices[idx], mesh.normals[idx], directions, bounce, ids=idx,
                                           nudge=None if nudge is None else nudge[idx], estimator=estimator, blocks=blocks)
            hit_rays = 0 if bounce is None else bounce.hits.rays_traced - hit0  # this chunk's hit rays (any executor)
            if left.numel():
                out = left[index[idx]] @ rotate_rows(T, blocks)  # B_p R_p T_p
            else:
                out = T  # the global transferred-radiance matrices (Sloan 2002)
            res = {"data": out.to(torch.float32), "rays": torch.tensor([rays], dtype=torch.int64),
                   "hit_rays": torch.tensor([hit_rays], dtype=torch.int64)}
            if bounce is not None and bounce.hits.mode == "auto":
                res.update(bounce.hits.take_probe_log())  # the faces this chunk probed (diffuse.record_probe_log)
            return res

        data = run.result_rows((V, n_out, n2), torch.float32)  # in memory, or a file when larger than memory allows
        seen: dict = {}

        def sink(a: int, b: int, p: dict[str, torch.Tensor]) -> None:  # each chunk copied in as it finishes
            data[a:b] = p["data"]
            meta["rays_traced"] = meta.get("rays_traced", 0) + int(p["rays"].sum())
            if bounce is not None and "hit_rays" in p:  # the hit points' rays, intersect and occluded (chunks of an older run: none)
                meta["hit_rays_traced"] = meta.get("hit_rays_traced", 0) + int(p["hit_rays"].sum())
            record_probe_log(meta, p, seen)

        with torch_threads(CHUNK_THREADS or torch.get_num_threads()):  # the sink's copies and the chunk saves too
            run.run_chunks(V, chunk_size, compute, fingerprint=fingerprint, desc=f"{kind} {mesh.name}",
                           rays_of=lambda r: int(r["rays"].sum()), sink=sink)
    finally:
        if caster is not None:
            meta["workers"] = caster.workers
            caster.close()
    meta["seconds"] = time.perf_counter() - t0
    meta.setdefault("rays_traced", 0)
    run.finish()
    return data, meta


def decide_shadows(mesh: Mesh, shadows: bool | str, seed: int, run: RunOptions, probe_tol: float = 1e-3) -> tuple[bool, dict]:
    """Whether to trace visibility: ``True``/'always', ``False``/'never', or 'auto' (probe the
    mesh's self-occlusion as the diffuse precompute does and trace only when shadowing removes
    more than ``probe_tol`` of the energy). Returns (trace, meta with ``shadow_decision``)."""
    if isinstance(shadows, bool):
        shadows = "always" if shadows else "never"
    check_choice("shadows", shadows, ["auto", "always", "never", True, False])
    if shadows == "always":
        return True, {"shadow_decision": "tracing shadow rays"}
    if shadows == "never":
        return False, {"shadow_decision": "shadows off: tangent-plane cut only"}
    from .diffuse import probe_self_occlusion

    caster = RayCaster(mesh, workers=1, offset=run.offset)
    try:
        probe = probe_self_occlusion(caster, mesh, seed)
    finally:
        caster.close()
    traced = probe["occluded_fraction"] > probe_tol
    return traced, {"probe": probe, "shadow_decision": (
        f"probe: shadowing removes {probe['occluded_fraction']:.3g} of the energy "
        f"({'>' if traced else '<='} probe_tol={probe_tol:g}); "
        + ("tracing shadow rays" if traced else "no self-occlusion: tangent-plane cut only"))}


def default_chunk(samples: int) -> int:
    return int(min(max(8, (1 << 19) // max(1, samples // 2)), 8192))


def check_memory(kind: str, V: int, n_out: int, n2: int, samples: int, chunk_size: int | None,
                  max_memory: int | None, streamed: bool = False, bounces: int = 0) -> int:
    """Refuse up front (before any BRDF projection or ray) when the estimate exceeds the budget
    (``streamed``: the result is assembled in a file, ``RunOptions.result_rows``, and not counted;
    ``bounces``: the chunk's interreflection buffers, :func:`estimate_memory`)."""
    chunk = default_chunk(samples) if chunk_size is None else chunk_size
    need = estimate_memory(V, n_out, n2, samples, min(chunk, max(V, 1)), streamed, bounces)
    budget = int(0.6 * _available_memory()) if max_memory is None else int(max_memory)
    if need > budget:
        held = "assembled in a file beside the state directory" if streamed else "held once while assembling"
        raise ValueError(
            f"{kind} transfer for {V} vertices with {n_out}×{n2} matrices and {samples} samples needs about "
            f"{format_bytes(need)} (result {format_bytes(V * n_out * n2 * 4)} float32, {held}), "
            f"more than the budget {format_bytes(budget)}; accepted: fewer bands or tents, fewer samples / a smaller "
            "chunk_size, a vertex subset, a state directory (the result then streams to a file), or a larger max_memory"
        )
    return need


#: Above this condition number of the hemisphere Gram matrix (9 bands and more) the exact
#: least-squares inverse amplifies the Monte Carlo error of T_p enough to matter, and the
#: glossy precompute chooses its rcond from the predicted error (prt_torch.transfer.lsq).
LSQ_CHECK_CONDITION = 1e10


def _least_squares_rcond(brdf: BRDF, bands_out: int, bands: int, samples: int, seed: int, drop_out, quad_bands) -> tuple:
    """(rcond, meta) for the least-squares projection when the caller gave none: the exact
    inverse while the Gram matrices are well enough conditioned, else the rcond with the
    smallest predicted error for these samples (transfer.lsq.choose_rcond, on the first
    material); a predicted error above 10% is warned about."""
    import warnings

    from ..sh import hemisphere_gram
    from .lsq import choose_rcond

    b = max(bands_out, bands)
    ev = torch.linalg.eigvalsh(hemisphere_gram(b))
    cond = float(ev[-1] / ev[0])
    if cond <= LSQ_CHECK_CONDITION:
        return None, {"rcond_decision": f"exact least-squares inverse (hemisphere Gram condition {cond:.3g} at {b} bands "
                                        f"<= {LSQ_CHECK_CONDITION:g})"}
    first = brdf.select(torch.zeros(1, dtype=torch.int64)) if len(brdf.batch_shape) else brdf  # the first material
    r = choose_rcond(first, bands_out, bands, samples, seed, drop_out, quad_bands)
    why = (f"rcond={r['rcond']} chosen from the predicted error for {samples} samples: {r['predicted_error']:.3g} "
           + (f"(exact inverse: {r['exact_error']:.3g})" if r["exact_error"] is not None else "(no exact inverse)")
           + f"; hemisphere Gram condition {cond:.3g} at {b} bands")
    if r["predicted_error"] > 0.1:
        warnings.warn(f"glossy least-squares projection at {bands_out}x{bands} bands with {samples} samples: predicted "
                      f"error {r['predicted_error']:.0%} even with the best rcond; use more samples, fewer bands or "
                      "projection='zero'", UserWarning, stacklevel=3)
    return r["rcond"], {"rcond_decision": why, "rcond_chosen": r["rcond"], "lsq_predicted_error": r["predicted_error"]}


def check_common(bands: int, samples: int, seed: int) -> tuple[int, int, int]:
    """bands in [1, 16], samples in [1, 2¹⁸], seed ≥ 0 (glossy and MRT)."""
    bands = check_int("bands", bands, 1, MAX_GLOSSY_BANDS)
    samples = check_int("samples", samples, 1, MAX_SAMPLES)
    seed = check_int("seed", seed, 0, 2**63 - 1)
    return bands, samples, seed


def precompute_glossy(
    mesh: Mesh,
    bands: int = 5,
    bands_out: int | None = None,
    *,
    brdf: BRDF | None = None,
    exit: bool = True,
    projection: str = "least_squares",
    drop_out: list[tuple[int, int]] | None = None,
    rcond: float | None = None,
    window: str | None = None,
    window_width: int | None = None,
    quad_bands: int | None = None,
    samples: int = 1024,
    seed: int = 0,
    shadows: bool | str = True,
    bounces: int = 0,
    vertices: torch.Tensor | None = None,
    estimator: str = "auto",
    subsurface: dict | None = None,
    run: RunOptions | None = None,
) -> Transfer:
    """Glossy transfer for every vertex (or the subset ``vertices``) of ``mesh``.

    Args:
        bands: n, lighting bands (n² = N_i columns), 1..16.
        bands_out: m, exit radiance bands (default n); N_r = m² rows (minus dropped ones).
        brdf: the reflectance (default isotropic Ashikhmin–Shirley N = 40, Rs = 0.05);
            parameters may be per vertex ``[V]`` (each distinct set gets its own B).
        exit: True: M_p = B_p R_p T_p (Sloan 2003 §3.1); False: the global transferred-radiance
            matrices T_p of Sloan et al. 2002 (``meta['quantity']='transferred'``; BRDF unused).
        projection, drop_out, rcond, window, window_width, quad_bands: as
            :func:`prt_torch.brdf.brdf_matrix` (default least squares, Sloan 2003 eq. (1)).
        samples: stratified sphere directions per vertex (about half are traced).
        shadows: trace visibility: True/'always', False/'never' (only the tangent-plane cut,
            no rays), or 'auto' (probe the mesh's self-occlusion first, :func:`decide_shadows`).
        bounces: interreflection bounces (0: shadowed direct light only). Blocked directions bring
            the exit radiance of the diffuse surface they hit, from a diffuse transfer with
            ``bounces - 1`` bounces (see :func:`transferred_radiance`); coloured albedo is
            reduced to luminance since the glossy matrices are shared by the colour channels.
        estimator: 'auto' (default: per vertex 'control' where at least half of its directions are
            open, 'plain' elsewhere), 'control' (the exact unshadowed T_p minus the blocked directions'
            part, :func:`transferred_radiance`) or 'plain' (the sum over visible directions).
        subsurface: ``{material, scale}`` (optional ``epsilon``, ``fresnel``, ``spacing``): add
            the view-independent subsurface term of Sloan 2003 §3.1 to the constant exit
            coefficient (row y_00; :mod:`~prt_torch.transfer.subsurface`, from the shadowed diffuse
            transfer of the same bands, samples, seed, shadows and bounces), reduced to luminance
            as coloured albedo is (one matrix per vertex). Exit transfer of every vertex only.
        run: how it runs (:class:`RunOptions`: chunks, workers, ray offset, memory limit —
            refused up front when the estimate exceeds it —, resumable state, progress).
    Returns:
        ``Transfer(kind='glossy')``, data float32 ``[V, N_r, n²]``, ``meta['matrix_shape']``,
        ``meta['out_index']`` (flat SH index of each row), ``meta['brdf']``.
    """
    run = RunOptions() if run is None else run
    bands, samples, seed = check_common(bands, samples, seed)
    bounces = check_int("bounces", bounces, 0, 16)
    check_choice("estimator", estimator, ESTIMATORS)
    bands_out = bands if bands_out is None else check_int("bands_out", bands_out, 1, MAX_GLOSSY_BANDS)
    if subsurface is not None:
        from .subsurface import check_term_spec

        check_term_spec(subsurface)
        if not exit or vertices is not None or (0, 0) in [tuple(d) for d in (drop_out or [])]:
            raise ValueError("subsurface: the term goes to the constant exit coefficient of every vertex; accepted: exit "
                             "transfer (not --transferred), no vertex subset, (0,0) not dropped")
    brdf = check_brdf(mesh, brdf)
    check_frames(mesh)
    n_rows = (bands_out * bands_out - len(drop_out or [])) if exit else bands * bands
    n_sel = mesh.num_vertices if vertices is None else len(vertices)
    check_memory("glossy", n_sel, n_rows, bands * bands, samples, run.chunk_size, run.max_memory,
                 run.streams_result(n_sel * n_rows * bands * bands * 4), bounces)
    shadows, shadow_meta = decide_shadows(mesh, shadows, seed, run)
    t0 = time.perf_counter()
    rcond_meta: dict[str, Any] = {}
    if exit and projection == "least_squares" and rcond is None:
        rcond, rcond_meta = _least_squares_rcond(brdf, bands_out, bands, samples, seed, drop_out, quad_bands)
    if exit:
        with torch_threads(1):  # small steps: one thread is steady (0.05–0.1 s) where two spin (up to 0.9 s, 2 cores)
            B, index = brdf_matrices(brdf, bands_out, bands, projection=projection, drop_out=drop_out, rcond=rcond,
                                     window=window, window_width=window_width, quad_bands=quad_bands)
        if index.numel() == 1:
            index = index.expand(mesh.num_vertices)
        out_idx = output_index(bands_out, drop_out)
    else:
        B, index = torch.zeros(0, 0, 0, dtype=torch.float64), torch.zeros(mesh.num_vertices, dtype=torch.int64)
        out_idx = torch.arange(bands * bands)
    t_brdf = time.perf_counter() - t0
    sel = None if vertices is None else torch.as_tensor(vertices, dtype=torch.int64)
    fp = {"kind": "glossy", "mesh_hash": mesh.content_hash(), "bands": bands, "bands_out": bands_out,
          "exit": exit, "brdf": brdf.meta() if exit else None, "projection": projection, "drop_out": drop_out,
          "rcond": rcond, "window": window, "window_width": window_width, "samples": samples, "seed": seed,
          "shadows": shadows, "bounces": bounces, "offset": run.offset, "quad_bands": quad_bands,
          "vertices": None if sel is None else sel.tolist()}
    if estimator != "plain":
        fp["estimator"] = estimator
    # with a subsurface term its passes follow under the state directory: kept until the last (an interruption
    # there resumes without recomputing the glossy rows), removed after it
    data, run_meta = run_exit_transfer("glossy", mesh, B, index, bands, samples, seed, shadows,
                                       run if subsurface is None else dataclasses.replace(run, keep_state=True), fp, sel,
                                       bounces=bounces, estimator=estimator)
    meta = {**shadow_meta, **run_meta, **rcond_meta}
    meta.update(
        bands=bands, bands_in=bands, bands_out=bands_out, samples=samples, seed=seed, shadows=shadows, bounces=bounces,
        quantity="exit" if exit else "transferred", frame="local" if exit else "global",
        matrix_shape=[int(data.shape[1]), int(data.shape[2])], out_index=out_idx.tolist(),
        projection=projection if exit else None, drop_out=[list(d) for d in (drop_out or [])],
        window=window, brdf=brdf.meta() if exit else None, brdf_seconds=t_brdf,
        materials=int(B.shape[0]) if exit else 0,
        vertices=None if sel is None else sel.tolist(),
        normalisation=("exit radiance towards local view v: sum_r y_{out_index[r]}(v) (data[p] @ l)[r], "
                       "l global SH radiance [n²]" if exit else
                       "transferred incident radiance coefficients (global frame) T_p @ l, zero below the tangent plane"),
        sh_convention="real SH, graphics convention, no Condon-Shortley phase, index l(l+1)+m",
    )
    if subsurface is not None:
        data = _add_subsurface(mesh, data, out_idx, subsurface, bands, samples, seed, shadows, bounces, run, meta)
        run.finish()
    mesh_out = mesh if sel is None else submesh(mesh, sel)
    return Transfer(kind="glossy", data=data, mesh=mesh_out, meta=meta)


def _add_subsurface(mesh: Mesh, data: torch.Tensor, out_idx: torch.Tensor, spec: dict, bands: int, samples: int,
                    seed: int, shadows: bool, bounces: int, run: RunOptions, meta: dict) -> torch.Tensor:
    """``data [V, N_r, n²]`` with the subsurface term's luminance (``[V, n²]``) added to the row of
    y_00, divided by y_00 = 1/(2√π) so that the exit radiance gains exactly the term."""
    import dataclasses

    from .diffuse import precompute_diffuse
    from .subsurface import add_term, sub_state

    t = precompute_diffuse(mesh.with_albedo(1.0), bands=bands, samples=samples, bounces=bounces, seed=seed,
                           shadows="always" if shadows else "never", fold_albedo=False,
                           run=dataclasses.replace(run, state_dir=sub_state(run, "irradiance"), keep_state=True))
    L = add_term(mesh, spec, t.data, run, meta)  # [V, 3, n²] (in a file when large: subsurface_term)
    del t
    r0 = int((out_idx == 0).nonzero()[0, 0])
    w = [float(x) for x in _LUMA]
    for a in range(0, data.shape[0], 1 << 14):  # in place, by blocks of rows (data may be file-backed): no second copy
        x = L[a:a + (1 << 14)]
        data[a:a + (1 << 14), r0] += ((x[:, 0] * w[0] + x[:, 1] * w[1] + x[:, 2] * w[2]) * (2 * math.sqrt(math.pi))).to(data.dtype)
    meta["subsurface"]["glossy"] = "luminance (Rec. 709) added to the y_00 exit row"
    return data


def submesh(mesh: Mesh, sel: torch.Tensor) -> Mesh:
    """Point-set mesh of the selected vertices (no faces survive a vertex subset; a degenerate
    triangle on vertex 0 keeps the container valid). Used when ``vertices=`` is given."""
    import dataclasses

    faces = torch.zeros(1, 3, dtype=torch.int64)
    return dataclasses.replace(
        mesh, vertices=mesh.vertices[sel], faces=faces, normals=mesh.normals[sel], tangents=mesh.tangents[sel],
        bitangents=mesh.bitangents[sel], albedo=mesh.albedo[sel], name=f"{mesh.name}[subset {sel.numel()}]",
        meta={**mesh.meta, "subset_of": mesh.content_hash(), "subset_vertices": int(sel.numel())},
    )
