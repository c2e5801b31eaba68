"""Glossy exit transfer against Mitsuba 3 (docs/validate.md): the BRDF a glossy transfer was
computed with, the engine's exit radiance towards sampled views with its noise and its SH
truncation bias (:func:`engine_glossy`), Mitsuba's (:func:`prt_torch.validate.scenes.mitsuba_glossy_exit`)
and their comparison (:func:`validate_glossy`).

Glossy exit transfer (kind 'glossy', quantity 'exit'). The engine's BRDF model becomes a Mitsuba BSDF written in Python (:func:`engine_bsdf`:
  f_r·cos θ_i in the vertex frame, cosine-hemisphere sampling) on a tiny disk at the engine's
  ray origin; a ``radiancemeter`` along a view v looks back at it (``max_depth`` 2: direct
  light; B+2 adds the transfer's B diffuse bounces). The engine side is :func:`prt_torch.relight.glossy`, recomputed from the transfer's own
  direction set (noise from replica seeds) and, on a dense set, with the BRDF unprojected: the
  engine's SH truncation bias at the vertices is reported apart (docs/validate.md).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np
import torch

from .._checks import check_int
from ..scene import Mesh, RayCaster
from ..sh import eval_sh
from ..transfer import Transfer
from ..transfer.diffuse import boundary_nudge, offset_origins
from .compare import LUMA, ratio, rms_rel, sample_vertices
from .scenes import VARIANT, mitsuba_glossy_exit

__all__ = ["glossy_brdf", "engine_glossy", "validate_glossy"]


def glossy_brdf(transfer: Transfer) -> Any:
    """The engine BRDF of a glossy exit transfer, rebuilt from ``meta['brdf']``; ``ValueError``
    naming the model when the validator cannot express it (before any work)."""
    from ..brdf import MODELS, make_brdf

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
    from ..brdf import brdf_matrices
    from ..relight import glossy as relight_glossy
    from ..transfer.sampling import uniform_sphere

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
    est = meta.get("estimator", "plain")  # files before the control variate summed the visible rays
    control = est == "control"
    if est in ("control", "auto"):  # ('auto': where at least half of the vertex's directions are open)
        # ∫_{n·s>0} h(s) L(s) ds = hvᵀ A (D_p l): the exact unshadowed part, per vertex [k, 3]
        from ..sh import hemisphere_gram, rotate

        l_loc = rotate(L3[:, None, :].expand(-1, idx.numel(), -1), F)  # [3, k, n²]: D_p l, the light in each local frame
        U = torch.einsum("kj,ji,cki->kc", hv, hemisphere_gram(bands), l_loc)
    with RayCaster(mesh, offset=eps / diag) as caster:
        for name, dirs in sets.items():
            Ld = eval_sh(dirs, bands, check=False) @ L3.T  # [N, 3]
            N = dirs.shape[0]
            for k in range(idx.numel()):
                up = torch.nonzero(dirs @ n[k] > 0).flatten()
                o = offset_origins(caster.local(p[k:k + 1].numpy()), n[k:k + 1].numpy(), caster.eps,
                                   None if nudge is None else nudge[k:k + 1].numpy())
                d = dirs[up].numpy()
                vis = ~caster.trace(np.repeat(o, d.shape[0], 0).astype(np.float32), d.astype(np.float32), "occluded")
                s_loc = dirs[up] @ F[k].T  # local directions F s
                h = eval_sh(s_loc, bands, check=False) @ hv[k]
                w = torch.zeros(N, dtype=torch.float64)
                w[up] = 4 * math.pi * torch.from_numpy(vis.astype(np.float64))
                cv = control or (est == "auto" and 2 * int(vis.sum()) >= vis.shape[0])  # the precompute's per-vertex choice
                if cv and name != "dense":  # the precompute's control variate: exact open part minus the blocked rays
                    wb = torch.zeros(N, dtype=torch.float64)
                    wb[up] = 4 * math.pi * torch.from_numpy((~vis).astype(np.float64))
                    x_sh = U[k] - (wb * torch.zeros(N, dtype=torch.float64).index_put_((up,), h))[:, None] * Ld  # [N, 3]
                else:
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
        from ..transfer import RunOptions
        from ..transfer.glossy import run_exit_transfer

        def total(sd: int) -> torch.Tensor:
            data, _ = run_exit_transfer("glossy", mesh, B.to(torch.float64), mat, bands, samples, sd, True,
                                        RunOptions(offset=eps / diag), {}, idx, bounces=bounces,
                                        estimator=meta.get("estimator", "plain"))
            return relight_glossy(data.to(torch.float64), L3, view_local, out_index)

        res["total_check"] = total(seed)
        tots = [total(seed + 7919 * (r + 1)) for r in range(len(reps))]
        I = torch.stack([t - d for t, d in zip(tots, reps)]) if reps else None
        res["inter"] = stored - res["recomputed"]
        if I is not None:
            res["inter_se"], res["inter_sum_se"] = I.std(0), float((I @ LUMA).sum(1).std())
    if reps:
        R = torch.stack(reps)  # [replicas, k, 3]
        res["se"] = R.std(0)
        res["sum_se"] = float((R @ LUMA).sum(1).std())
        res["noise"] = f"engine: std over {len(reps)} replica seeds of the precompute's estimator (B_p reused)"
    else:
        res["sum_se"] = None
        res["noise"] = "engine: per-ray standard error, per vertex in quadrature (an upper bound for stratified sets)"
    return res


def validate_glossy(transfer: Transfer, L: torch.Tensor, name: str, image: np.ndarray, *, mesh: Mesh | None = None,
                    vertices: int = 16, spp: int = 4096, batches: int = 8, seed: int = 0, view_deg: float = 60.0,
                    idx: torch.Tensor | None = None, dense: int = 1 << 14, mitsuba_frame: str = "normalized") -> dict[str, Any]:
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
            rec = transfer.mesh.meta  # the full mesh's own meta, kept by the subset (built-in name and size if one)
            on = f"{rec['builtin']}:{rec.get('size', 'small')}" if rec.get("builtin") else "a mesh file"
            got = "none given" if mesh is None else (f"{mesh.name!r}" + (f" size {mesh.meta['size']!r}" if "size" in mesh.meta
                                                                         else "") + f", {mesh.num_vertices} vertices")
            raise ValueError(f"this glossy transfer holds a vertex subset (no faces to trace) of {on} (content hash "
                             f"{str(want)[:12]}); got mesh= {got}; accepted: pass mesh= the full mesh it was computed on "
                             "(same content hash)")
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
    grey = dataclasses.replace(mesh, albedo=(mesh.albedo.to(torch.float64) @ LUMA)[:, None].expand(-1, 3).contiguous())
    mit = mitsuba_glossy_exit(grey, mesh.vertices[idx], F, vw, brdfs, image, spp, batches, eps, seed, boundary_nudge(mesh)[idx],
                              depths=[2, bounces + 2] if bounces else [2], frame=mitsuba_frame)
    m, m_se = mit["radiance"][0], mit["radiance_se"][0]
    lum = lambda x: float((x @ LUMA).sum())  # noqa: E731
    M = lum(m)
    rep = {
        "kind": "glossy", "scene": mesh.name, "vertices": int(idx.numel()), "bounces": bounces, "bands": int(meta["bands"]),
        "bands_out": int(meta.get("bands_out", meta["bands"])), "brdf": meta.get("brdf"), "projection": meta.get("projection"),
        "light": name, "spp": int(spp), "batches": int(batches), "samples": int(meta.get("samples", 0)), "view_deg": view_deg,
        "mitsuba_variant": VARIANT, "mitsuba_frame": mitsuba_frame, "eps": eps, "dense": int(dense),
        "direct": ratio(eng["recomputed"] if bounces else eng["stored"], eng["se"], m, m_se, eng["sum_se"]),
        "direct_unprojected": ratio(eng["exact"], eng["exact_se"], m, m_se),
        "sh_truncation": lum(eng["truncation"]) / M if M > 0 else float("nan"),
        "recomputed_rel": float(((eng["total_check"] if bounces else eng["recomputed"]) - eng["stored"]).abs().max()
                                / eng["stored"].abs().max().clamp_min(1e-300)),
        "direct_rms_rel": rms_rel(eng["recomputed"] if bounces else eng["stored"], m),
        "engine_noise": eng["noise"],
    }
    if bounces:
        m_int, m_int_se = mit["radiance"][1] - m, mit["diff_se"][1]
        e_int_se, e_int_sum = eng.get("inter_se", torch.zeros_like(m)), eng.get("inter_sum_se")
        rep["inter"] = ratio(eng["inter"], e_int_se, m_int, m_int_se, e_int_sum)
        tot_sum = None if e_int_sum is None or eng["sum_se"] is None else math.hypot(eng["sum_se"], e_int_sum)
        rep["total"] = ratio(eng["stored"], (eng["se"] ** 2 + e_int_se ** 2).sqrt(), mit["radiance"][1], mit["radiance_se"][1], tot_sum)
        rep["per_vertex"] = {"engine_inter": eng["inter"].tolist(), "mitsuba_inter": m_int.tolist()}
    rep.setdefault("per_vertex", {}).update({"index": idx.tolist(), "view_local": vl.tolist(), "engine": eng["stored"].tolist(),
                         "engine_se": eng["se"].tolist(), "engine_unprojected": eng["exact"].tolist(),
                         "truncation": eng["truncation"].tolist(), "mitsuba": m.tolist(), "mitsuba_se": m_se.tolist()})
    return rep
