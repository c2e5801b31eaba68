"""Diffuse transfer against Mitsuba 3 (docs/validate.md): the engine's exit radiance at sampled
vertices split into its direct and interreflected parts with their Monte Carlo noise
(:func:`engine_parts`), Mitsuba's at the same points (:func:`prt_torch.validate.scenes.mitsuba_exit_radiance`),
and their comparison (:func:`validate_diffuse`, which :func:`prt_torch.validate.validate` calls).

* **What a vertex is.** Diffuse exit radiance at vertex p is (ρ_p/π) E_p with E_p the
  irradiance over the hemisphere of the vertex normal n_p at the vertex position (course notes
  2005, "Diffuse PRT"). Mitsuba measures E_p with an ``irradiancemeter`` sensor attached to a
  tiny one-sided disk (radius ``1e-2·eps``, black) centred at the engine's ray origin
  p + eps·n_p (+ eps·b_p on open mesh boundaries, :func:`prt_torch.transfer.diffuse.offset_origins`)
  facing n_p — eps is the transfer's own ray offset (``offset`` × bounding-box diagonal), so
  both sides start their rays at the same point. The rest of the scene is the transfer's mesh, flat-shaded (its
  triangles, as the engine's rays see them), one-sided Lambertian (Mitsuba's ``diffuse`` is
  black behind, as the engine's bounces are) with the mesh albedo as a vertex attribute.
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
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from ..relight import diffuse_transfer
from ..scene import VERTEX_CLASSES, Mesh, RayCaster, edge_face_counts, normal_face_angles, vertex_classes
from ..sh import eval_sh
from ..transfer import Transfer
from ..transfer.diffuse import DiffuseSampler, HitBounce, boundary_nudge, face_points, transfer_at_points, vertex_transfer
from .compare import LUMA, ratio, rms_rel, sample_vertices
from .scenes import VARIANT, mitsuba_exit_radiance

__all__ = ["sharp_vertices", "engine_parts", "class_report", "validate_diffuse"]


def sharp_vertices(mesh: Mesh) -> torch.Tensor:
    """``[V]`` float64: the largest angle (degrees) between a vertex normal and the geometric
    normals of its adjacent faces (0 on flat parts; large at sharp and concave vertices;
    :func:`prt_torch.scene.normal_face_angles`)."""
    return torch.from_numpy(normal_face_angles(mesh))


def engine_parts(transfer: Transfer, L: torch.Tensor, idx: torch.Tensor, data: torch.Tensor | None = None,
                 replicas: int = 6) -> dict[str, Any]:
    """The engine's exit radiance at vertices ``idx`` split into direct and interreflected parts,
    with their Monte Carlo noise (this module's docstring). ``data``: replacement transfer rows for
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
    sampling = meta.get("sampling", "uniform")  # files before the qmc default say so
    estimator = meta.get("estimator", "plain")  # ... and before the control variate used the plain sum
    offset = float(meta.get("offset", 1e-4))
    hit_samples = int(meta.get("hit_samples", 8))
    hit_offset = float(meta.get("hit_offset", offset))  # files from before issue 37: hit rays left at the ray offset
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
        from ..transfer.diffuse import unshadowed_transfer

        direct = rho * (unshadowed_transfer(n, bands) @ L3.T)
        return {"total": total, "direct": direct, "inter": zero, "direct_se": zero, "inter_se": zero,
                "direct_sum_se": 0.0, "inter_sum_se": 0.0, "noise": "none (analytic unshadowed transfer)"}
    with RayCaster(mesh, offset=offset) as caster:
        t0 = transfer_at_points(caster, p, n, bands, samples, seed, sampling, nudge=boundary_nudge(mesh)[idx],
                                ids=idx, estimator=estimator)  # [k, n²], ρ = 1
        direct = rho * (t0 @ L3.T)
        hits_mode = bounces > 0 and meta.get("bounce_points") == "hits"
        if bounces > 0 and not hits_mode:
            _, inter_se = _ray_noise(caster, mesh, p, n, L3, bands, samples, seed, sampling, total_all, None, idx)
    inter = total - direct if bounces > 0 else zero
    lum = lambda x: x @ LUMA  # noqa: E731
    D, I = [], []
    for r in range(int(replicas)):  # a loop over replica seeds; each one batched over the vertices
        T0r, TBr = vertex_transfer(mesh, idx, bands, samples, seed + 7919 * (r + 1), bounces if hits_mode else 0,
                                   sampling=sampling, offset=offset, hit_samples=hit_samples, hit_offset=hit_offset,
                                   estimator=estimator)
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
    sampler = DiffuseSampler(bands, samples, seed, sampling, "plain")
    frames = None
    if sampling == "cosine":
        from ..scene import tangent_frames

        t, b = tangent_frames(n.numpy())
        frames = torch.stack([torch.from_numpy(t), torch.from_numpy(b), n], dim=-2)
    i, j, o, d, cos = sampler.rays(caster.local(p), n, frames, caster.eps, boundary_nudge(mesh)[idx],
                                   ids=None if idx is None else idx.numpy())
    prim, bu, bv, _ = caster.trace(o, d, "intersect")
    hit = prim != -1
    k = p.shape[0]
    Ns = sampler.per_vertex  # the estimator averages over all its directions (zeros below the horizon)
    w = sampler.ray_weights(i, j, cos) * Ns  # per-sample values: w_j N
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
    ii = torch.from_numpy(i)

    def se(x: torch.Tensor) -> torch.Tensor:
        s1 = torch.zeros(k, 3, dtype=torch.float64).index_add_(0, ii, x)
        s2 = torch.zeros(k, 3, dtype=torch.float64).index_add_(0, ii, x * x)
        var = (s2 / Ns - (s1 / Ns) ** 2).clamp_min(0)
        return (var / Ns).sqrt()

    return se(f_dir), se(f_ind)


def class_report(mesh: Mesh, idx: torch.Tensor, eng: dict[str, Any], m_dir: torch.Tensor, m_dir_se: torch.Tensor,
                 m_int: torch.Tensor | None, m_int_se: torch.Tensor | None, sharp_deg: float = 18.0) -> tuple[dict, dict]:
    """Where the mesh is hard, and the error there (issue 37): ``(features, classes)``.

    ``features``: the mesh's boundary / non-manifold edges and the vertices of each class of
    :func:`prt_torch.scene.vertex_classes` (boundary, non-manifold, sharp, folded, sliver,
    regular), counted over the whole mesh. ``classes[name]``: ``mesh`` (vertices of the class
    in the mesh), ``sampled`` (among the ``idx`` ``[k]`` compared) and, where any was
    sampled, the engine/Mitsuba ratios of the class's summed luminance — ``direct`` and (with
    ``m_int`` ``[k, 3]``) ``inter`` — with both sides' noise (the engine's from its replica
    seeds where :func:`engine_parts` measured them, ``eng['direct_reps']`` / ``['inter_reps']``)."""
    cls = vertex_classes(mesh, sharp_deg)
    e, cnt = edge_face_counts(mesh.faces.numpy(), mesh.num_vertices)
    features = {"vertices": mesh.num_vertices, "faces": mesh.num_faces, "boundary_edges": int((cnt == 1).sum()),
                "nonmanifold_edges": int((cnt >= 3).sum()), **{f"{k}_vertices": int(cls[k].sum()) for k in VERTEX_CLASSES}}
    ii = idx.numpy()
    out: dict[str, dict] = {}
    for name in VERTEX_CLASSES:  # a loop over six classes, each batched over its vertices
        sel = torch.from_numpy(cls[name][ii])
        entry: dict[str, Any] = {"mesh": int(cls[name].sum()), "sampled": int(sel.sum())}
        if bool(sel.any()):
            for part, m, m_se in (("direct", m_dir, m_dir_se), ("inter", m_int, m_int_se)):
                if m is None:
                    continue
                reps = eng.get(f"{part}_reps")
                sum_se = None if reps is None else float((reps[:, sel] @ LUMA).sum(1).std())
                entry[part] = ratio(eng[part][sel], eng[f"{part}_se"][sel], m[sel], m_se[sel], sum_se)
        out[name] = entry
    return features, out


def validate_diffuse(transfer: Transfer, L: torch.Tensor, name: str, sh_img: np.ndarray | None, src_img: np.ndarray | None, *,
                     light_source: str = "sh", codec: tuple | None = None, codec_file: Any = None, vertices: int = 32,
                     spp: int = 1024, batches: int = 8, seed: int = 0, sharp_deg: float = 18.0,
                     idx: torch.Tensor | None = None, mitsuba_frame: str = "normalized") -> dict[str, Any]:
    """Diffuse exit radiance, engine vs Mitsuba (:func:`prt_torch.validate.validate` for kind
    'diffuse', after its checks): direct, and with bounces B > 0 interreflected and total, at
    ``vertices`` sampled vertices (or ``idx``); the same over the sharp vertices (``sharp_deg``).
    ``L [C, n²]`` float64 the SH light named ``name``; ``sh_img``: its band-limited image
    (:func:`prt_torch.validate.lights.check_expressible`; None where Mitsuba cannot emit it),
    ``src_img``: the environment's original image (``light_source='image'``; then the report adds
    Mitsuba under ``sh_img`` against it, the SH truncation); ``codec``: ``(codec, encoding)``
    loaded from ``codec_file``, whose reconstruction is compared too."""
    bands = int(transfer.meta["bands"])
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
    mit = mitsuba_exit_radiance(mesh, p, n, sh_img if src_img is None else src_img, depths, spp, batches, eps, seed, rho, nudge,
                               mitsuba_frame)
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
        "mitsuba_variant": VARIANT, "mitsuba_frame": mitsuba_frame, "eps": eps,
        "direct": ratio(eng["direct"], eng["direct_se"], m_dir, m_dir_se, eng["direct_sum_se"]),
        "total": ratio(eng["total"], tot_se, m_tot, m_tot_se, tot_sum_se),
        "engine_noise": eng["noise"],
        "direct_rms_rel": rms_rel(eng["direct"], m_dir),
    }
    if bounces:
        rep["inter"] = ratio(eng["inter"], eng["inter_se"], m_int, m_int_se, eng["inter_sum_se"])
        if bool(sharp.any()) and bool((~sharp).any()):  # both subsets, else 'inter' says it all
            for key, sel in (("inter_sharp", sharp), ("inter_smooth", ~sharp)):
                reps = eng.get("inter_reps")
                sum_se = None if reps is None else float((reps[:, sel] @ LUMA).sum(1).std())
                rep[key] = ratio(eng["inter"][sel], eng["inter_se"][sel], m_int[sel], m_int_se[sel], sum_se)
    rep["mesh_features"], rep["classes"] = class_report(mesh, idx, eng, m_dir, m_dir_se, m_int if bounces else None,
                                                        m_int_se if bounces else None, sharp_deg)
    if codec is not None:
        c, enc = codec
        rows = c.decode(enc).to(torch.float64)
        if rows.shape[0] != mesh.num_vertices:
            raise ValueError(f"codec file {str(codec_file)!r} holds {rows.shape[0]} points; the transfer has {mesh.num_vertices} vertices")
        ce = engine_parts(transfer, L, idx, data=rows[idx], replicas=0)
        rep["codec"] = {"file": str(codec_file), "total": ratio(ce["total"], tot_se, m_tot, m_tot_se, tot_sum_se)}
        if bounces:
            rep["codec"]["inter"] = ratio(ce["total"] - eng["direct"], eng["inter_se"], m_int, m_int_se, eng["inter_sum_se"])
    if src_img is not None and sh_img is not None:  # Mitsuba under the band-limited light / under the image
        msh = mitsuba_exit_radiance(mesh, p, n, sh_img, depths, spp, batches, eps, seed, rho, nudge, mitsuba_frame)
        rep["sh_truncation"] = ratio(msh["radiance"][-1], msh["radiance_se"][-1], m_tot, m_tot_se)
    rep["per_vertex"] = {
        "index": idx.tolist(), "sharp": sharp.tolist(),
        "engine_direct": eng["direct"].tolist(), "engine_inter": eng["inter"].tolist(),
        "mitsuba_direct": m_dir.tolist(), "mitsuba_inter": m_int.tolist(),
        "engine_direct_se": eng["direct_se"].tolist(), "engine_inter_se": eng["inter_se"].tolist(),
        "mitsuba_direct_se": m_dir_se.tolist(), "mitsuba_inter_se": m_int_se.tolist(),
    }
    return rep


def validate_wavelet(transfer: Transfer, light: Any, name: str, src_img: np.ndarray, *, vertices: int = 32, spp: int = 1024,
                     batches: int = 8, seed: int = 0, idx: torch.Tensor | None = None) -> dict[str, Any]:
    """Shadowed diffuse exit radiance of a wavelet transfer (Ng et al. 2003; every Haar term of
    the light on the transfer's cube, :class:`prt_torch.relight.WaveletRelighter`) against
    Mitsuba 3 path tracing under the environment's *original* image ``src_img`` (not band-limited,
    Mitsuba's lat-long grid), at ``vertices`` sampled vertices (or ``idx``); no scale fit: direct
    light only, or with the transfer's B bounces (``meta['bounces_used']``) against Mitsuba's path
    depth 1 + B (``'total'``). The engine's error is the cube's (its R, the transfer's kept terms
    and quantisation) and, with bounces, the hit-point estimator's noise."""
    from ..relight import WaveletRelighter

    mesh = transfer.mesh
    if idx is None:
        idx = sample_vertices(mesh, vertices, seed)
    idx = torch.as_tensor(idx, dtype=torch.int64)
    r = WaveletRelighter(transfer)
    li, lv, rec = r.light(light, None)
    eng = r(li, lv)[idx].to(torch.float64)
    eng = eng.expand(-1, 3) if eng.shape[1] == 1 else eng
    eps = float(transfer.meta.get("offset", 1e-4)) * float(np.linalg.norm(mesh.vertices.numpy().max(0) - mesh.vertices.numpy().min(0)))
    rho = mesh.albedo.to(torch.float64)[idx]
    B = int(transfer.meta.get("bounces_used", 0) or 0)
    mit = mitsuba_exit_radiance(mesh, mesh.vertices[idx], mesh.normals[idx], src_img, [1 + B], spp, batches, eps, seed, rho,
                                boundary_nudge(mesh)[idx])
    m, m_se = mit["radiance"][0], mit["radiance_se"][0]
    zero = torch.zeros_like(eng)
    total = ratio(eng, zero, m, m_se, 0.0)
    return {
        "scene": mesh.name, "kind": "wavelet", "vertices": int(idx.numel()), "bounces": B, "bands": None, "light": name,
        "light_source": "image", "spp": int(spp), "batches": int(batches), "samples": 6 * r.res * r.res,
        "res": r.res, "terms": int(transfer.meta.get("terms", transfer.data.shape[1])), "bits": transfer.meta.get("bits"),
        "light_record": rec, "sharp_deg": 0.0, "sharp_vertices": 0, "mitsuba_variant": VARIANT, "eps": eps,
        "mitsuba_max_depth": 1 + B,
        # without bounces the whole result is the direct light; with B bounces Mitsuba's path depth 1 + B is the total
        "direct": total if B == 0 else None, "total": total, "direct_rms_rel": rms_rel(eng, m) if B == 0 else None,
        "total_rms_rel": rms_rel(eng, m),
        "per_vertex": {"index": idx.tolist(), "engine_direct": eng.tolist(), "mitsuba_direct": m.tolist(),
                       "mitsuba_direct_se": m_se.tolist()},
    }
