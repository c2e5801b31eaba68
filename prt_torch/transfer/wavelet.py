"""All-frequency diffuse transfer in a Haar basis on a cube map (Ng, Ramamoorthi & Hanrahan 2003;
course notes 2005, "PRT with Haar Wavelets").

Per vertex p, the shadowed diffuse transfer in the *pixel basis* of a 6 × R × R cube map
(:mod:`prt_torch.lighting.haar`: the ``faces`` layout, exact texel solid angles) is

    T_p[j] = (1/π) ∫_{texel j} V(p, s) max(n_p·s, 0) ds  ≈ (1/π) Σ_{sub-texels} V max(n·s, 0) Ω_sub

(``sampling='grid'``: texel centres, ``supersample`` = 1, or an s × s grid of sub-texels each with
its exact solid angle; ``sampling='jittered'``: one uniformly random point in each of the s × s
sub-texels, drawn anew for every vertex, weighted by the face's solid-angle density there,
dω = da db / (1 + a² + b²)^{3/2} = |d_face|³ da db — an unbiased stratified estimate of the
texel integral, whose error is noise that differs from vertex to vertex instead of the grid's
deterministic aliasing of edges), so that exit radiance under a cube light of radiance L_j per
texel is

    L_out(p) = ρ_p Σ_j T_p[j] L_j = ρ_p Σ_k T̂_p[k] L̂_k                  (Ng 2003 eq. 1–2)

the second sum over the orthonormal Haar coefficients of both (per face, non-standard). The
albedo ρ_p is kept out (``mesh.albedo``), as in the grey diffuse kind. Of the 6R² coefficients a
vertex keeps its ``terms`` largest in magnitude (a per-row non-linear approximation of the
transport matrix, Ng 2003 §6), optionally dropping those below ``threshold`` times the row's
largest, quantised as Ng does (§6: a few bits per value with float32 scales, 16-bit indices):
``bits`` = 8 or 16 gives signed integers q with value = q · scale_{p,ℓ}, one scale per vertex and
Haar level ℓ (``scales='level'``, the default: scale_{p,ℓ} = max over p's kept values at level ℓ
of |T̂| / (2^(b-1) - 1); a level's small details no longer round to zero against the vertex's
largest, coarse value) or one per vertex (``scales='vertex'``); the quantisation error of a kept
value is at most its scale / 2, plus the float32 rounding of the product; ``bits`` = 32 stores
float32.

Stored (``Transfer(kind='wavelet')``): ``data [V, K]`` (int8 / int16 / float32 values),
``aux['index'] [V, K]`` (int16 where 6R² < 2¹⁵, else int32: flat index f·R² + i·R + j of the
Haar coefficient), ``aux['scale'] [V, log2(R)+1]`` float32 (one per vertex and Haar level,
:func:`~prt_torch.lighting.haar.haar_levels`; ``scales='vertex'``: ``[V]``); ``meta['bytes_per_vertex']``
the stored size.
Interreflection (``bounces`` B > 0): a blocked ray of p (sub-texel j, weight
w = max(n_p·s, 0) Ω/π) that meets the front of a triangle at q adds w ρ_q Σ_b x^b(q) to T_p,
x(q) in the pixel basis estimated at q itself with M cosine-weighted rays — (1/M) Σ_m V(q, s_m)
1[s_m ∈ texel] estimates (1/π)∫_texel V(q, s) cos ds, further bounces recursively — the diffuse
kind's hit-point estimator (:meth:`prt_torch.transfer.diffuse.HitBounce.texel_values`). On a
coloured mesh ρ_q differs per colour, so the transfer becomes three, T_{p,c}, one per channel (as
the SH diffuse kind's ``[V, 3, n²]``), stored with the albedo ρ_{p,c} folded in and one pattern
per vertex — the K coefficients of largest Σ_c T̂_{p,c}² — shared by the channels, each channel
quantised with its own scales (:func:`sparsify`): exit radiance L_out,c(p) = Σ_k T̂_{p,c}[k] L̂_c[k].
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import torch

from .._checks import check_choice, check_float, check_int, describe
from ..lighting.haar import MAX_HAAR_RES, check_res, cube_geometry, haar2d, haar_levels
from ..lighting.layouts import dir_to_pixel, pixel_to_dir
from ..scene import Mesh, RayCaster
from .base import RunOptions, Transfer, mesh_bytes
from .diffuse import HIT_OFFSET, HitBounce, boundary_nudge, offset_origins
from ..io import format_bytes
from .glossy import decide_shadows, memory_budget
from .ray_kernels import upper_rays

__all__ = ["precompute_wavelet", "estimate_wavelet_memory", "dense_wavelet_transfer", "sampled_wavelet_transfer",
           "sparsify", "quantise", "dequantise",
           "wavelet_values", "MAX_WAVELET_TERMS", "BITS", "SAMPLINGS", "SCALES"]

MAX_WAVELET_TERMS = 6 * MAX_HAAR_RES * MAX_HAAR_RES
#: K, the coefficients kept per vertex when none is given (``terms``)
DEFAULT_TERMS = 256
#: stored precisions: signed integers of 8 or 16 bits with a per-vertex scale, or float32
BITS = (8, 16, 32)
#: where the texel integrals are sampled: sub-texel centres, or one random point per sub-texel and vertex
SAMPLINGS = ("grid", "jittered")
#: the integers' scales: one per vertex, or one per vertex and Haar level (the default: measured,
#: reports/benchmarks/wavelet.md "Stored precision")
SCALES = ("level", "vertex")


def _jitter_seed(seed: int, start: int) -> int:
    """The jitter's seed of the chunk starting at vertex ``start``: fixed by (seed, start), so a
    resumed or re-chunked run draws the same points for the same chunk."""
    return (int(seed) * 1_000_003 + int(start)) % (1 << 62)


def _index_dtype(P: int) -> torch.dtype:
    return torch.int16 if P <= 32767 else torch.int32


def bytes_per_vertex(terms: int, bits: int, P: int, scales: int = 1, channels: int = 1) -> int:
    """Stored bytes of one vertex: K indices (2 or 4 bytes) shared by its ``channels`` transfers
    (3 for a coloured mesh's interreflection), each with K values of ``bits`` and ``scales`` float32 scales."""
    return terms * (channels * bits // 8 + (2 if P <= 32767 else 4)) + 4 * scales * channels


#: bytes per vertex of the per-vertex error sums a wavelet precompute keeps in memory (float64
#: total, dropped, quantisation error and an int32 count: ``meta``'s truncation and nnz figures)
STATS_BYTES = 3 * 8 + 4


def estimate_wavelet_memory(V: int, res: int, terms: int, bits: int, supersample: int, chunk: int,
                            jittered: bool = False, channels: int = 1, streamed: bool = False) -> int:
    """Bytes a wavelet precompute holds at its peak: the stored result once (each chunk copied
    into the assembled rows as it finishes; none when they are in a file, ``streamed``:
    :meth:`RunOptions.result_rows`) and the per-vertex error sums (:data:`STATS_BYTES`), plus one
    chunk's working set (float64 cosines and weights, float32 rays
    with their indices, at the sub-texel resolution; float64 Haar coefficients and top-K; jittered:
    each vertex's own float64 directions, weights and their intermediates; ``channels`` = 3: the
    coloured bounce's three pixel-basis transfers and their Haar coefficients)."""
    P = 6 * res * res
    Pf = P * supersample * supersample
    result = V * STATS_BYTES + (0 if streamed else V * bytes_per_vertex(terms, bits, P, 1, channels))
    work = chunk * (Pf * (8 + 8 + 12 + 12 + 16 + 1 + (120 if jittered else 0)) + channels * (P * 8 * 4 + terms * 16))
    return int(result + work + Pf * 40)


def wavelet_disk_bytes(mesh: Mesh, stored: int, streamed: bool) -> int:
    """Bytes a wavelet precompute with a state directory writes beside its output at its peak (the
    end, when the output is written and the state is not yet removed): its chunk files (the stored
    rows and :data:`STATS_BYTES` per vertex), the assembled rows when they are in a file
    (``streamed``, :meth:`RunOptions.result_rows`) and the output (the stored rows and the mesh)."""
    V = mesh.num_vertices
    return (stored + V * STATS_BYTES) + (stored if streamed else 0) + (stored + mesh_bytes(mesh))


def check_wavelet_disk(run: RunOptions, mesh: Mesh, stored: int) -> None:
    """Refuse (ValueError, before any ray) a run whose :func:`wavelet_disk_bytes` exceed the free
    space of the disk holding ``run.state_dir`` (less the chunks a resumed run already holds)."""
    from pathlib import Path

    from .. import io

    sd = Path(run.state_dir)
    have = sum(f.stat().st_size for f in sd.glob("chunk_*.prt")) if sd.is_dir() else 0
    streamed = run.streams_result(stored)
    io.check_disk_space(sd.parent / sd.name.removesuffix(".state"), wavelet_disk_bytes(mesh, stored, streamed),
                        f"wavelet transfer of {mesh.num_vertices} vertices ({format_bytes(stored)} stored: its chunks, "
                        + ("the assembled rows' file " if streamed else "") + "and the output)",
                        "a smaller res, fewer terms or bits, a smaller mesh, or an output on a disk with room", have)


def default_chunk(res: int, supersample: int) -> int:
    rays = 3 * res * res * supersample * supersample  # about half the sub-texels are above the horizon
    return int(min(max(8, (1 << 20) // rays), 8192))


def quantise(c: torch.Tensor, bits: int, level: torch.Tensor | None = None, levels: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Quantise rows of kept coefficients ``c [V, K]`` (float) to signed integers with one scale
    per row — or, with ``level [V, K]`` (each value's Haar level, :func:`~prt_torch.lighting.haar.haar_levels`),
    one per row and level (``levels`` of them): ``(q [V, K]`` int8/int16 — float32 for bits=32,
    ``scale [V]`` or ``[V, levels]`` float32), value = q · scale, scale = max|c| (of the row, or of
    its values at that level) / (2^(bits-1) - 1); |q·scale - c| ≤ scale / 2 (Ng 2003 §6), plus
    |c|·2⁻²⁴ once the product is formed in float32 (:func:`dequantise`). A scale per level keeps
    the fine levels' small details from rounding to zero against the vertex's largest value."""
    bits = check_choice("bits", bits, BITS)
    if bits == 32:
        return c.to(torch.float32), torch.ones(c.shape[0], dtype=torch.float32)
    qmax = (1 << (bits - 1)) - 1
    a = c.abs().to(torch.float64)
    if level is None:
        top = a.amax(1)
        sc = torch.where(top > 0, top / qmax, torch.ones_like(top)).to(torch.float32)
        per = sc.to(torch.float64)[:, None]
    else:
        lev = level.long()
        top = torch.zeros(c.shape[0], levels, dtype=torch.float64).scatter_reduce_(1, lev, a, "amax")
        sc = torch.where(top > 0, top / qmax, torch.ones_like(top)).to(torch.float32)
        per = sc.to(torch.float64).gather(1, lev)
    q = torch.round(c.to(torch.float64) / per).clamp_(-qmax, qmax)
    return q.to(torch.int8 if bits == 8 else torch.int16), sc


def dequantise(q: torch.Tensor, scale: torch.Tensor, level: torch.Tensor | None = None) -> torch.Tensor:
    """``q [V, K]`` (any dtype) times ``scale [V]`` — or ``scale [V, L]`` at each value's ``level
    [V, K]`` — → float32 ``[V, K]``."""
    if scale.ndim == 2:
        if level is None:
            raise ValueError("scale has one column per Haar level; pass level [V, K] (haar_levels of the indices)")
        return q.to(torch.float32) * scale.to(torch.float32).gather(1, level.long())
    return q.to(torch.float32) * scale.to(torch.float32)[:, None]


def wavelet_values(tr: Transfer) -> torch.Tensor:
    """The dequantised Haar coefficients of a wavelet transfer, ``[V, K]`` float32 (albedo out), or
    ``[V, 3, K]`` for a coloured one (one transfer per colour sharing the vertex's indices, albedo
    folded in; its scales ``[V, 3, L]`` or ``[V, 3]``)."""
    if tr.kind != "wavelet":
        raise ValueError(f"transfer kind {tr.kind!r}; accepted: 'wavelet'")
    sc, q, idx = tr.aux["scale"], tr.data, tr.aux["index"].long()
    if q.ndim == 3:  # coloured: the channels as rows sharing the vertex's indices
        V, C, K = q.shape
        idx = idx[:, None, :].expand(V, C, K).reshape(V * C, K)
        q, sc = q.reshape(V * C, K), sc.reshape(V * C, *sc.shape[2:])
        level = haar_levels(int(tr.meta["res"]))[idx] if sc.ndim == 2 else None
        return dequantise(q, sc, level).reshape(V, C, K)
    level = haar_levels(int(tr.meta["res"]))[idx] if sc.ndim == 2 else None
    return dequantise(q, sc, level)


def sparsify(H: torch.Tensor, terms: int, bits: int, threshold: float = 0.0, scales: str = "vertex",
             res: int | None = None) -> dict[str, torch.Tensor]:
    """Rows of Haar coefficients ``H [k, P]`` (float64) → their ``terms`` largest in magnitude,
    those below ``threshold`` × the row's largest zeroed, quantised (:func:`quantise`, ``scales``
    'vertex' or 'level' — this needs ``res``, the cube's face size): ``q [k, K]``, ``index [k, K]``
    (int16 for P < 2¹⁵, else int32), ``scale [k]`` or ``[k, log2(R)+1]``, and per row ``total``
    (Σ H²), ``dropped`` (Σ of the dropped H²), ``qerr`` (Σ of the squared quantisation errors), ``nnz``.

    ``H [k, C, P]`` (a coloured mesh's C = 3 transfers per vertex): one pattern per vertex shared
    by its channels — the K coefficients of largest energy Σ_c H_c² — each channel quantised as a
    row of its own: ``q [k, C, K]``, ``index [k, K]``, ``scale [k, C]`` or ``[k, C, log2(R)+1]``;
    ``total``, ``dropped``, ``qerr`` summed over the channels, ``nnz`` the coefficients kept in
    any channel."""
    P = H.shape[-1]
    scales = check_choice("scales", scales, SCALES)
    colour = H.ndim == 3
    C = H.shape[1] if colour else 1
    total = H.double().square().sum(-1).reshape(H.shape[0], -1).sum(1)
    mag = H.double().square().sum(1).sqrt() if colour else H.abs()  # [k, P]
    top = mag.topk(terms, dim=1)
    gi = top.indices[:, None, :].expand(-1, C, -1) if colour else top.indices
    kept = H.gather(-1, gi).double()
    if threshold > 0:
        keep = top.values >= threshold * top.values[:, :1]
        kept = torch.where(keep[:, None] if colour else keep, kept, torch.zeros_like(kept))
    level, n_lev = None, 1
    if scales == "level" and bits != 32:
        if res is None:
            raise ValueError("sparsify with scales='level' needs res (the cube's face size)")
        lv = haar_levels(res)
        level, n_lev = lv[gi].reshape(-1, terms), int(lv.max()) + 1
    rows = kept.reshape(-1, terms)  # [k·C, K]: each channel a row of its own
    q, scale = quantise(rows, bits, level, n_lev)
    err = (rows - dequantise(q, scale, level).double()).square().sum(1).reshape(-1, C).sum(1)
    nnz = (q != 0).reshape(H.shape[0], C, terms).any(1).sum(1).to(torch.int32)
    if colour:
        q, scale = q.reshape(-1, C, terms), scale.reshape(-1, C, *scale.shape[1:])
    return {"q": q, "index": top.indices.to(_index_dtype(P)), "scale": scale, "total": total,
            "dropped": (total - kept.square().sum(-1).reshape(H.shape[0], -1).sum(1)).clamp_min(0), "qerr": err, "nnz": nnz}


def _jittered_samples(res: int, s: int, k: int, gen: torch.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Per-vertex jittered samples (module docstring): one uniform point in each of the 6·(Rs)²
    sub-texels of the ``faces`` cube for each of ``k`` vertices, in the texel order of
    :func:`~prt_torch.lighting.haar.cube_geometry` — directions ``[k, Pf, 3]`` float64 and weights
    ``[k, Pf]`` (the sub-texel's parameter area (2/(Rs))² times the solid-angle density |d_face|³)."""
    r = res * s
    u = torch.rand(k, 2, r, 6 * r, generator=gen, dtype=torch.float64)  # vertex by vertex: a vertex's points do not depend on k
    y = torch.arange(r, dtype=torch.float64)[None, :, None] + u[:, 0]
    x = torch.arange(6 * r, dtype=torch.float64)[None, None, :] + u[:, 1]
    d, _ = pixel_to_dir("faces", r, 6 * r, y, x)  # [k, r, 6r, 3] (the faces strip: 6 tiles of r x r)
    d = d.reshape(k, r, 6, r, 3).permute(0, 2, 1, 3, 4).reshape(k, -1, 3)
    w = (2.0 / r) ** 2 * d.abs().amax(-1) ** 3
    return d.contiguous().numpy(), w.numpy()


def _texel_of(res: int):
    """Directions ``[R, 3]`` float64 → the flat index f·R² + i·R + j of the cube texel holding each
    (the ``faces`` layout of :func:`~prt_torch.lighting.haar.cube_geometry`)."""
    def f(d: np.ndarray) -> np.ndarray:
        y, x = dir_to_pixel("faces", res, 6 * res, torch.from_numpy(d))
        face = torch.div(x, res, rounding_mode="floor").long()
        return (face * res * res + y.long() * res + (x.long() - face * res)).numpy()
    return f


def _bounce(caster: RayCaster, hits: HitBounce, k: int, res: int, i: np.ndarray, j: np.ndarray, d: np.ndarray,
            prim: np.ndarray, bu: np.ndarray, bv: np.ndarray, w: np.ndarray, ids: np.ndarray) -> np.ndarray:
    """Interreflected pixel-basis transfer of a chunk's k vertices, ``[k, C, 6R²]`` float64 (C =
    ``hits.C``: 1 grey, 3 per colour for a coloured mesh): every primary ray (vertex row ``i``,
    sub-texel ``j``, direction ``d``, weight ``w`` = cos·Ω/π) that meets the front of a triangle
    brings ρ_q Σ_b x^b(q) from its hit q in the pixel basis, per channel
    (:meth:`~prt_torch.transfer.diffuse.HitBounce.texel_values`: the diffuse kind's hit-point
    estimator, B = ``hits.terms`` bounces), in batches of about 2¹⁸ secondary rays."""
    P = 6 * res * res
    out = np.zeros((k * P, hits.C))
    hh = np.nonzero(prim != -1)[0]
    tri = prim[hh].astype(np.int64)
    front = np.einsum("ij,ij->i", hits.face_normals.numpy()[tri], d[hh].astype(np.float64)) < 0
    hh, tri = hh[front], tri[front]
    texel_of = _texel_of(res)
    step = max(1, (1 << 18) // hits.M)
    for a in range(0, hh.shape[0], step):  # a loop over hit batches, each one traced batch
        h, t = hh[a:a + step], tri[a:a + step]
        bary = np.stack([1 - bu[h] - bv[h], bu[h], bv[h]], 1).astype(np.float64)
        r, tx, wt = hits.texel_values(caster, t, bary, ids[i[h]].astype(np.uint64), j[h].astype(np.uint64), texel_of)
        rho = hits.albedo_at(t, bary).numpy()  # [H, C]
        np.add.at(out, i[h][r] * P + tx, w[h][r][:, None] * rho[r] * wt)
    return np.ascontiguousarray(out.reshape(k, P, hits.C).transpose(0, 2, 1))


def _pixel_transfer(caster: RayCaster | None, points: torch.Tensor, normals: torch.Tensor, nudge: torch.Tensor | None,
                    dirs_f: np.ndarray, dirs32: np.ndarray | None, omega_f: np.ndarray, res: int, s: int,
                    eps: float, work: dict, hits: HitBounce | None = None, ids: np.ndarray | None = None) -> tuple[torch.Tensor, int]:
    """Pixel-basis transfer of k vertices, ``[k, 6, R, R]`` float64 (module docstring; ``[k, 3, 6,
    R, R]`` with the bounce of a coloured mesh, ρ_p kept out: t̃ = t/ρ_p per channel), and the
    number of rays traced. One masked pass per chunk: cosines ``[k, Pf]``, the rays above each
    tangent plane (:func:`prt_torch.transfer.ray_kernels.upper_rays`), one occlusion batch.
    ``dirs_f [Pf, 3]`` / ``omega_f [Pf]`` shared by every vertex (the grid), or per vertex
    ``[k, Pf, 3]`` / ``[k, Pf]`` (jittered; ``dirs32`` None). ``hits``: add the interreflected
    light (:func:`_bounce`; ``ids`` the vertices' global ids, the bounce rays' keys)."""
    k = points.shape[0]
    per_vertex = dirs_f.ndim == 3
    cos = np.einsum("kd,kpd->kp", normals.numpy(), dirs_f) if per_vertex else normals.numpy() @ dirs_f.T  # [k, Pf] float64
    rays = 0
    if caster is not None:
        o_v = offset_origins(caster.local(points.numpy()), normals.numpy(), eps,  # the caster's (mesh-centred) frame
                             None if nudge is None else nudge.numpy()).astype(np.float32)
        fused = None if per_vertex else upper_rays(cos, o_v, dirs32, work=work)
        if fused is not None:
            i, j, o, d = fused
        else:
            up = cos > 0
            counts = up.sum(1)
            i = np.repeat(np.arange(k), counts)
            j = np.flatnonzero(up) - i * up.shape[1]
            o = np.repeat(o_v, counts, axis=0)
            d = dirs_f[i, j].astype(np.float32) if per_vertex else np.take(dirs32, j, axis=0)
        if hits is not None:
            prim, bu, bv, _ = caster.trace(o, d, "intersect")
            hit = prim != -1
        else:
            hit = caster.trace(o, d, "occluded")
        rays = int(i.shape[0])
    W = np.maximum(cos, 0.0, out=cos)
    W *= (omega_f if per_vertex else omega_f[None, :]) * (1.0 / math.pi)
    B = None
    if caster is not None:
        flat = i * W.shape[1] + j
        if hits is not None:
            B = _bounce(caster, hits, k, res, i, j, d, prim, bu, bv, W.reshape(-1)[flat], ids)
        W.reshape(-1)[flat[hit]] = 0.0  # blocked directions
    T = torch.from_numpy(W).reshape(k, 6, res, s, res, s).sum((3, 5)) if s > 1 else torch.from_numpy(W).reshape(k, 6, res, res)
    if B is not None:
        T = T[:, None] + torch.from_numpy(B).reshape(k, -1, 6, res, res)
        T = T[:, 0] if T.shape[1] == 1 else T
    return T, rays


def dense_wavelet_transfer(mesh: Mesh, res: int, *, supersample: int = 1, shadows: bool = True, offset: float = 1e-4,
                           vertices: Any = None, haar: bool = True, sampling: str = "grid", seed: int = 0, bounces: int = 0,
                           hit_samples: int = 16, hit_offset: float | None = HIT_OFFSET) -> torch.Tensor:
    """The full (all 6R² terms, unquantised) transfer of the vertices ``vertices`` (default all),
    ``[k, 6, R, R]`` float64 (``[k, 3, 6, R, R]`` with ``bounces`` on a coloured mesh: per colour,
    ρ_p kept out — :func:`precompute_wavelet` folds it in) — Haar coefficients (``haar``) or the pixel basis; the same rays as
    :func:`precompute_wavelet` (``sampling`` 'grid' or 'jittered' with ``seed``: the jitter of the
    vertices' first chunk there; ``bounces``, ``hit_samples``, ``hit_offset`` as there). For
    references and tests on a few vertices."""
    res = check_res(res)
    sampling = check_choice("sampling", sampling, SAMPLINGS)
    idx = torch.arange(mesh.num_vertices) if vertices is None else torch.as_tensor(vertices, dtype=torch.int64)
    if sampling == "jittered":
        dirs_f, om_f = _jittered_samples(res, supersample, idx.numel(), torch.Generator().manual_seed(_jitter_seed(seed, 0)))
        dirs32 = None
    else:
        d, om = cube_geometry(res, supersample)
        dirs_f = np.ascontiguousarray(d.reshape(-1, 3).numpy())
        dirs32, om_f = dirs_f.astype(np.float32), np.ascontiguousarray(om.reshape(-1).numpy())
    nudge = boundary_nudge(mesh)[idx]
    hits = _hit_bounce(mesh, bounces, hit_samples, hit_offset, seed) if shadows else None
    caster = RayCaster(mesh, workers=1, offset=offset) if shadows else None
    try:
        T, _ = _pixel_transfer(caster, mesh.vertices[idx].to(torch.float64), mesh.normals[idx].to(torch.float64),
                               nudge if bool(nudge.any()) else None, dirs_f, dirs32, om_f, res, supersample,
                               0.0 if caster is None else caster.eps, {}, hits, idx.numpy())
    finally:
        if caster is not None:
            caster.close()
    return haar2d(T) if haar else T



def sampled_wavelet_transfer(mesh: Mesh, res: int, vertices: Any, offset: float = 1e-4) -> Transfer:
    """A ``wavelet`` :class:`Transfer` holding every Haar term (all 6R², float32, ``bits`` 32) of the
    vertices ``vertices`` (int64 ``[k]``) alone, computed by :func:`dense_wavelet_transfer`; the other
    rows are zero (index 0, scale 1) and are never to be read. What ``prt validate``'s comparisons with
    Mitsuba take on a few sampled vertices (``validate(tr, light, idx=vertices)``) without a whole
    precompute: ``data [V, 6R²]`` float32, ``aux.index [V, 6R²]``, ``aux.scale [V]``."""
    idx = torch.as_tensor(vertices, dtype=torch.int64)
    P = 6 * res * res
    s = sparsify(dense_wavelet_transfer(mesh, res, offset=offset, vertices=idx).reshape(idx.numel(), -1), P, 32)
    q = torch.zeros(mesh.num_vertices, P)
    ind = torch.zeros(mesh.num_vertices, P, dtype=s["index"].dtype)
    sc = torch.ones(mesh.num_vertices)
    q[idx], ind[idx], sc[idx] = s["q"], s["index"], s["scale"]
    return Transfer("wavelet", q, mesh, {"res": res, "terms": P, "bits": 32, "offset": offset}, aux={"index": ind, "scale": sc})

def precompute_wavelet(
    mesh: Mesh,
    res: int = 32,
    terms: int = DEFAULT_TERMS,
    bits: int = 8,
    *,
    scales: str = "level",
    threshold: float = 0.0,
    supersample: int = 1,
    sampling: str = "grid",
    bounces: int = 0,
    hit_samples: int = 16,
    hit_offset: float | None = HIT_OFFSET,
    shadows: bool | str = "auto",
    probe_tol: float = 1e-3,
    seed: int = 0,
    run: RunOptions | None = None,
) -> Transfer:
    """Sparse Haar-wavelet diffuse transfer of every vertex (module docstring; Ng 2003).

    Args:
        mesh: the scene.
        res: cube face resolution R, a power of two in [1, 128] (6R² texels).
        terms: K, coefficients kept per vertex (the largest in magnitude), in [1, 6R²].
        bits: stored precision of the kept values: 8 or 16 (integers with float32 scales,
            Ng 2003 §6) or 32 (float32).
        scales: the integers' scales: 'level' (one per vertex and Haar level, log2(R)+1 of them:
            the default, measured — 8 bits then reach 0.55% where one scale per vertex floors at
            1.8%, reports/benchmarks/wavelet.md) or 'vertex' (one per vertex).
        threshold: also drop kept coefficients below ``threshold`` × the vertex's largest
            (stored as zeros; ``meta['nonzero_per_vertex']``), in [0, 1).
        supersample: s, visibility and cosine on an s × s grid of sub-texels per texel (each
            with its exact solid angle); 1 = texel centres.
        sampling: 'grid' (sub-texel centres) or 'jittered' (one random point per sub-texel,
            drawn per vertex from ``seed`` and the chunk; module docstring).
        bounces: B, interreflection: each blocked ray's front hit q brings ρ_q Σ_b x^b(q) in the
            pixel basis, x estimated at q with ``hit_samples`` cosine-weighted rays (a quarter of
            that per further bounce; :class:`~prt_torch.transfer.diffuse.HitBounce`, the diffuse
            kind's hit-point estimator); rays leave q from ``hit_offset`` × the diagonal. A grey
            mesh keeps one channel (the albedo of p kept out); a coloured one gets three, one per
            colour (its bounces carry ρ_q per channel; the albedo of p folded in). 0 = direct only.
        shadows: 'auto' (probe self-occlusion first), 'always'/True, 'never'/False.
        seed: the probe's seed, and the jitter's.
        run: :class:`RunOptions` (chunks — default about 2²⁰ rays —, workers, offset, memory
            limit, resumable state, progress, executor).
    Returns:
        ``Transfer(kind='wavelet')``: ``data [V, K]``, ``aux['index'] [V, K]``, ``aux['scale'] [V, L]`` (or ``[V]``);
        with ``bounces`` on a coloured mesh ``data [V, 3, K]`` (one transfer per colour, the albedo folded
        in: ``meta['albedo_folded']``, ``meta['channels']`` = 3), the indices shared, ``aux['scale'] [V, 3, L]``.
    Raises:
        ValueError before any ray: R not a power of two, K out of range, or the memory estimate
        (:func:`estimate_wavelet_memory`) above ``run.max_memory`` (default 60% of RAM).
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a prt_torch.scene.Mesh, got {describe(mesh)}")
    run = RunOptions() if run is None else run
    res = check_res(res)
    P = 6 * res * res
    if isinstance(terms, int) and not isinstance(terms, bool) and terms > P:  # the bound depends on res: say so
        raise ValueError(f"terms={terms} is out of range; accepted: integers in [1, {P}] (the 6R² Haar coefficients per "
                         f"vertex at res={res})")
    terms = check_int("terms", terms, 1, P)
    bits = check_choice("bits", bits, BITS)
    scales = check_choice("scales", scales, SCALES)
    n_scales = int(math.log2(res)) + 1 if scales == "level" and bits != 32 else 1
    threshold = check_float("threshold", threshold, 0.0, 1.0, hi_open=True)
    s = check_int("supersample", supersample, 1, 16)
    sampling = check_choice("sampling", sampling, SAMPLINGS)
    bounces = check_int("bounces", bounces, 0, 8)
    hit_samples = check_int("hit_samples", hit_samples, 1, 4096)
    V = mesh.num_vertices
    chunk_size = run.chunks(default_chunk(res, s))
    C = 3 if bounces and not mesh.is_grey() else 1  # a coloured mesh's interreflection: one transfer per colour
    stored = V * bytes_per_vertex(terms, bits, P, n_scales, C)  # decides where the rows are assembled (result_rows)
    need = estimate_wavelet_memory(V, res, terms, bits, s, min(chunk_size, max(V, 1)), sampling == "jittered", C,
                                   run.streams_result(stored))
    budget = memory_budget(run.max_memory)
    if need > budget:
        raise ValueError(f"wavelet transfer of {V} vertices at res={res} (6x{res}x{res} texels, supersample {s}) with "
                         f"{terms} terms needs about {format_bytes(need)}, more than the budget {format_bytes(budget)}; "
                         "accepted: a smaller res, fewer terms, a smaller chunk_size or mesh, or a larger memory limit")
    if run.state_dir is not None:  # a CLI run: the chunks, the rows assembled in a file and the output, on one disk
        check_wavelet_disk(run, mesh, stored)
    hits = _hit_bounce(mesh, bounces, hit_samples, hit_offset, seed)
    rho = mesh.albedo.to(torch.float64)
    t0 = time.perf_counter()
    traced, shadow_meta = decide_shadows(mesh, "always" if bounces else shadows, seed, run, probe_tol)
    d, om = cube_geometry(res, s)
    dirs_f = np.ascontiguousarray(d.reshape(-1, 3).numpy())
    dirs32 = dirs_f.astype(np.float32)
    omega_f = np.ascontiguousarray(om.reshape(-1).numpy())
    nudge = boundary_nudge(mesh)
    nudge = nudge if bool(nudge.any()) else None
    points, normals = mesh.vertices.to(torch.float64), mesh.normals.to(torch.float64)
    caster = RayCaster(mesh, workers=_workers(run, V, P * s * s), offset=run.offset) if traced else None
    work: dict = {}

    def compute(a: int, b: int) -> dict[str, torch.Tensor]:
        if sampling == "jittered":
            d_f, om_f = _jittered_samples(res, s, b - a, torch.Generator().manual_seed(_jitter_seed(seed, a)))
            d32 = None
        else:
            d_f, d32, om_f = dirs_f, dirs32, omega_f
        T, rays = _pixel_transfer(caster, points[a:b], normals[a:b], None if nudge is None else nudge[a:b],
                                  d_f, d32, om_f, res, s, 0.0 if caster is None else caster.eps, work, hits, np.arange(a, b))
        if C == 3:  # coloured bounce: the albedo of p folded in per channel (as the SH diffuse kind stores [V, 3, n²])
            T = T * rho[a:b, :, None, None, None]
        # Haar in float32: the stored values carry at most 16 bits (float32 for bits=32), the
        # transform's rounding (~1e-7 relative) is far below; half the memory traffic of float64
        H = haar2d(T.to(torch.float32))
        out = sparsify(H.reshape(b - a, C, P) if C == 3 else H.reshape(b - a, P), terms, bits, threshold, scales, res)
        out["rays"] = torch.tensor([rays], dtype=torch.int64)
        return out

    fingerprint = {"kind": "wavelet", "mesh_hash": mesh.content_hash(), "res": res, "terms": terms, "bits": bits, "scales": scales,
                   "threshold": threshold, "supersample": s, "sampling": sampling, "seed": seed if sampling == "jittered" or bounces else None,
                   "bounces": bounces, "hit_samples": hit_samples if bounces else None, "hit_offset": hit_offset if bounces else None,
                   "shadows": traced, "offset": run.offset}
    cat: dict[str, torch.Tensor] = {}  # the assembled rows: q, index, scale (in a file when large) and the per-vertex sums

    def sink(a: int, b: int, p: dict[str, torch.Tensor]) -> None:  # each chunk copied in as it finishes (any order)
        for k, v in p.items():
            if k not in cat:
                shape = (1 if k == "rays" else V,) + tuple(v.shape[1:])
                cat[k] = (run.result_rows(shape, v.dtype, name=f"wavelet_{k}", nbytes=stored) if k in ("q", "index", "scale")
                          else torch.zeros(shape, dtype=v.dtype))
            if k == "rays":
                cat[k] += v
            else:
                cat[k][a:b] = v

    try:
        run.run_chunks(V, chunk_size, compute, fingerprint=fingerprint, desc=f"wavelet {mesh.name}",
                       rays_of=lambda r: int(r["rays"].sum()), sink=sink)
    finally:
        if caster is not None:
            caster.close()
    total, dropped, qerr = cat["total"], cat["dropped"], cat["qerr"]
    rel = lambda e: (e / total.clamp_min(1e-300)).sqrt()  # noqa: E731 - relative L2 per vertex
    lit = total > 0
    meta: dict[str, Any] = {
        "res": res, "texels": P, "terms": terms, "bits": bits, "threshold": threshold, "supersample": s,
        "sampling": sampling if sampling == "grid" else f"jittered (seed {seed}; one random point per sub-texel and vertex)",
        "offset": run.offset, "albedo_folded": C == 3, "channels": C, "bounces_used": bounces,
        "bounce_decision": (f"{bounces} bounce(s) estimated at each blocked ray's hit point with {hit_samples} cosine-weighted "
                            "rays (HitBounce, pixel basis)") if bounces else "no interreflection (bounces=0): direct (shadowed) transfer",
        "hit_samples": hit_samples if bounces else None, "hit_offset": hit_offset if bounces else None,
        "scales": scales if bits != 32 else "none (float32 values)",
        "bytes_per_vertex": bytes_per_vertex(terms, bits, P, n_scales, C),
        "bytes_per_vertex_dense": P * 4 * C,  # the pixel-basis transfer(s) in float32: one per colour when coloured
        "index_dtype": str(_index_dtype(P)).replace("torch.", ""),
        "nonzero_per_vertex": float(cat["nnz"].float().mean()),
        "truncation_rel_l2_mean": float(rel(dropped)[lit].mean()) if bool(lit.any()) else 0.0,
        "truncation_rel_l2_max": float(rel(dropped)[lit].max()) if bool(lit.any()) else 0.0,
        "quantisation_rel_l2_max": float(rel(qerr)[lit].max()) if bool(lit.any()) else 0.0,
        "quantisation_bound": "per kept value |error| <= scale/2 + |value| 2^-24 (aux.scale per vertex"
                              + (", column = the value's Haar level)" if n_scales > 1 else ")"),
        "rays_traced": int(cat["rays"].sum()), "chunk_size": chunk_size, "memory_estimate_bytes": need,
        "layout": "Haar coefficients of the faces cube (+x,-x,+y,-y,+z,-z), index f*R*R + i*R + j after haar2d per face",
        "normalisation": "exit radiance L_out[v] = albedo[v] * sum_k data[v,k]*scale[v] * Lhat[index[v,k]], Lhat = haar2d of "
                         "the cube light's radiance per texel; T[j] = (1/pi) int_texel V max(n.s,0) ds",
        **shadow_meta, "shadows_traced": traced,
    }
    meta["seconds"] = time.perf_counter() - t0
    meta["rays_per_second"] = meta["rays_traced"] / meta["seconds"] if meta["rays_traced"] else 0.0
    run.finish()
    return Transfer("wavelet", cat["q"].contiguous(), mesh, meta,
                    aux={"index": cat["index"].contiguous(), "scale": cat["scale"].contiguous()})


def _hit_bounce(mesh: Mesh, bounces: int, hit_samples: int, hit_offset: float | None, seed: int) -> HitBounce | None:
    """The diffuse kind's hit-point bounce estimator for ``bounces`` > 0 (one channel for a grey
    mesh, three for a coloured one: its bounces carry ρ_q per colour), else None."""
    if not bounces:
        return None
    return HitBounce(mesh, 1, hit_samples, seed, bounces, 1 if mesh.is_grey() else 3, hit_offset, "plain")


def _workers(run: RunOptions, V: int, Pf: int) -> int:
    """``run.workers``, or (None) all cores when the run traces ≥ 4M rays."""
    from ..scene import default_workers

    if run.workers is not None:
        return run.workers
    return default_workers() if V * Pf // 2 >= 4_000_000 else 1

