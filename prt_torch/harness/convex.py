"""Convex objects: a spherical harmonic reflection map (Ramamoorthi 2002 ch. 5) against unshadowed
glossy PRT (Sloan 2003 §3.1, exit matrices M_p = B R_p T_p) — the same BRDF, the same light — as a
section of a benchmark report (config key ``convex``; shipped config ``prt bench convex``).

For every mesh of ``convex.meshes`` (``sphere``: a unit geodesic sphere; ``hull:SCENE``: the
convex hull of a built-in scene or mesh file, e.g. the bumpy sphere standing in for a scan; any
other built-in scene or mesh file as it is) and every camera of ``views``:

* the **reference**: per vertex, Σ over the environment's pixels of L(ω) f_r(ω, v) max(n·ω, 0) Ω
  (eq. 5.1 without visibility, :func:`prt_torch.shrm.reference_radiance`: the full-resolution
  light, no SH, nothing of either method);
* **glossy PRT**: the run's glossy transfer (its bands, samples, BRDF) precomputed on the mesh
  with ``shadows: never`` (a convex object has none; cached like every harness transfer),
  relit with the environment's own SH projection through the harness's uncompressed path
  (``Evaluator.reference``: ``relight.glossy_view_weights`` + ``relight.apply_dense``);
* **SHRM**: one per ``convex.epsilons`` (orders F_B, P_B from ε, eq. 5.16–5.19), built once from
  the same environment (frequency-space prefilter, ``convex.map_height`` lat-long maps) and
  saved as ``<run>/convex/shrm-eps<ε>.prt`` (``prt render`` renders it); radiance per vertex by
  map lookup (``SHRM.radiance(method="map")``, what the GLSL decoder computes).

Measured: PSNR of each against the reference over the vertices facing the camera (n·v > 0.02;
peak = the reference's maximum; mean over cameras), the same over grazing vertices only
(0.02 < n·v < cos 75°), the same with the radiance clamped at 0 (what ``prt render`` shows by
default), the most negative radiance each produces (truncation ringing), the share of diffuse energy
the self-occlusion probe finds shadowed (a warning above ``shrm.CONVEX_PROBE_TOL``: nothing here has
visibility), bytes
(the SHRM file, per object; the exit matrices, float32, per vertex), precompute time (the SHRM's
build; the transfer's own ``meta['seconds']``, also on a cache hit) and per-frame time — the
radiance of every vertex for a new view — as a paired ratio (interleaved, one thread, CPU time:
``harness.timing.measure_paired``).

This module takes the transfer as a callable (``transfer_fn(mesh) -> (Transfer, info)``, what
``harness.run`` passes: its cached ``compute_transfer``), so it depends on nothing after it.
"""
from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any, Callable

import torch

from .. import shrm as S
from ..brdf import from_spec as brdf_from_spec
from ..lighting import builtin_environment, list_builtin_environments, load_environment, parse_light_spec
from ..scene import RayCaster
from ..transfer.diffuse import probe_self_occlusion
from .evaluate import Evaluator, camera_positions
from .metrics import psnr_vs_reference
from .timing import measure_paired, torch_threads

__all__ = ["CONVEX_DEFAULTS", "check_convex", "load_convex_mesh", "convex_environment", "run_convex", "SPHERE_FREQ",
           "GRAZING_COS", "FACING_COS"]

#: the config section's keys and defaults (``harness.config.DEFAULTS['convex']``)
CONVEX_DEFAULTS: dict[str, Any] = {"enabled": False, "meshes": ["sphere", "hull:bumpy_sphere"], "size": "small",
                                   "epsilons": [0.03, 0.01], "map_height": 64, "light_size": 64}
#: geodesic frequency of ``sphere`` per size (10 f² + 2 vertices: 2562, 10242, 40962)
SPHERE_FREQ = {"small": 16, "medium": 32, "large": 64}
#: vertices count as facing the camera above this n·v, as grazing below GRAZING_COS (cos 75°)
FACING_COS = 0.02
GRAZING_COS = math.cos(math.radians(75.0))


def _mesh_name(spec: str) -> str:
    return spec[5:] + "_hull" if spec.startswith("hull:") else spec


def _check_mesh_spec(i: int, spec: Any) -> None:
    from ..scene import accepted_meshes, check_scene

    if not isinstance(spec, str) or not spec:
        raise ValueError(f"config key 'convex.meshes.{i}' = {spec!r}; accepted: 'sphere', 'hull:MESH' or MESH, MESH "
                         f"{accepted_meshes()}")
    name = spec[5:] if spec.startswith("hull:") else spec
    if name == "sphere" and not spec.startswith("hull:"):
        return
    try:  # the one rule for naming a mesh (prt_torch.scene.check_scene)
        check_scene(name, param=f"config key 'convex.meshes.{i}' = {spec!r}: mesh")
    except (ValueError, FileNotFoundError) as e:
        raise type(e)(f"{e}; or 'sphere', or 'hull:' before one") from None


def check_convex(cfg: dict) -> None:
    """Refuse, before any work, a ``convex`` section the run cannot do (called by
    ``harness.config.validate`` when ``convex.enabled``): the run's transfer must be glossy (the
    PRT peer) with an isotropic BRDF an SHRM accepts (``shrm.check_brdf``), its first light an
    environment image (built-in or file: the reference sums its pixels), the meshes known,
    ε in (0, 1), map height 4..1024, light size 8..1024. Raises ValueError / FileNotFoundError
    naming the key, the value and what is accepted."""
    c = cfg["convex"]
    t = cfg["transfer"]
    if t.get("type") != "glossy":
        raise ValueError(f"config key 'convex.enabled' needs transfer.type glossy (the unshadowed glossy PRT peer), got "
                         f"{t.get('type')!r}; accepted: transfer: {{type: glossy, brdf: {{...}}}}")
    if isinstance(t.get("brdf"), list):
        raise ValueError("config key 'transfer.brdf' is swept; accepted with 'convex': one BRDF (the SHRM's and the PRT's)")
    try:
        S.check_brdf(brdf_from_spec(t.get("brdf") or {"type": "phong"}))
    except (ValueError, TypeError) as e:
        raise ValueError(f"config key 'transfer.brdf' (convex section): {e}") from None
    light = cfg["lights"][0]
    if not (isinstance(light, str) and (light in list_builtin_environments()
                                        or (parse_light_spec(light) is None and Path(light).is_file()))):
        raise ValueError(f"config key 'lights.0' = {light!r}: the convex section sums the environment's pixels; accepted: "
                         f"a built-in environment ({', '.join(list_builtin_environments())}) or an image file")
    meshes = c["meshes"]
    if not isinstance(meshes, list) or not meshes:
        raise ValueError(f"config key 'convex.meshes' = {meshes!r}; accepted: a non-empty list of meshes")
    for i, spec in enumerate(meshes):
        _check_mesh_spec(i, spec)
    if len({_mesh_name(m) for m in meshes}) != len(meshes):
        raise ValueError(f"config key 'convex.meshes' = {meshes!r} names a mesh twice; accepted: distinct meshes")
    eps = c["epsilons"]
    if not isinstance(eps, list) or not eps:
        raise ValueError(f"config key 'convex.epsilons' = {eps!r}; accepted: a non-empty list of numbers in (0, 1)")
    for i, e in enumerate(eps):
        if isinstance(e, bool) or not isinstance(e, (int, float)) or not 0 < e < 1:
            raise ValueError(f"config key 'convex.epsilons.{i}' = {e!r}; accepted: a number in (0, 1) (the BRDF energy "
                             "an SHRM may lose, Ramamoorthi 2002 eq. 5.18)")


def load_convex_mesh(spec: str, size: str = "small"):
    """The mesh a ``convex.meshes`` entry names: ``'sphere'`` (unit geodesic sphere,
    ``SPHERE_FREQ[size]``), ``'hull:SCENE'`` (the convex hull of that scene, trimesh/qhull) or a
    built-in scene / mesh file (``scene.load_scene``). Returns a ``scene.Mesh``."""
    import numpy as np
    import trimesh

    from ..scene import load_scene, make_mesh
    from ..scene.builtins import geodesic_sphere

    if spec == "sphere":
        v, f = geodesic_sphere(SPHERE_FREQ[size])
        return make_mesh(np.asarray(v), np.asarray(f), name="sphere")
    if spec.startswith("hull:"):
        src = load_scene(spec[5:], size=size)
        h = trimesh.Trimesh(src.vertices.numpy(), src.faces.numpy(), process=False).convex_hull
        return make_mesh(np.asarray(h.vertices), np.asarray(h.faces), name=_mesh_name(spec))
    return load_scene(spec, size=size)


def convex_environment(spec: str, size: int):
    """The run's first light as an ``Environment`` (a built-in at lat-long height ``size``, or an
    image file at its own resolution): what the reference sums and both methods project."""
    if spec in list_builtin_environments():
        return builtin_environment(spec, size=size)
    return load_environment(spec)


def run_convex(cfg: dict, transfer_fn: Callable[[Any], tuple[Any, dict]], out_dir: Path,
               log: Callable[[str], None] = print, shots: list | None = None) -> dict:
    """The convex-objects comparison of ``cfg`` (module docstring): returns a JSON-able dict
    ``{brdf, light, light_pixels, map_height, epsilons, views, shrms: [...], rows: [per mesh: {mesh,
    vertices, facing, prt: {...}, shrm: [per ε: {...}]}], seconds}``; writes the SHRM files under
    ``out_dir``. ``transfer_fn(mesh) -> (glossy Transfer, info)`` gives the PRT peer. ``shots`` (a
    list) receives, per mesh, the first camera's per-vertex radiance of the reference, each SHRM and
    the PRT (``{"mesh", "eye", "panels": [(label, [V, C])]}``, for ``harness.renders.render_convex``)."""
    t_start = time.perf_counter()
    c = cfg["convex"]
    brdf = S.check_brdf(brdf_from_spec(cfg["transfer"].get("brdf") or {"type": "phong"}))
    env = convex_environment(cfg["lights"][0], int(c["light_size"]))
    dirs = env.directions().reshape(-1, 3).to(torch.float64)
    Lw = env.image.reshape(-1, env.channels).to(torch.float64) * env.solid_angles().reshape(-1, 1).to(torch.float64)
    m_cfg = cfg["metrics"]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    shrms = []
    for eps in c["epsilons"]:  # one SHRM per ε, for every object under this light
        t0 = time.perf_counter()
        m = S.build_shrm(brdf, env, epsilon=float(eps), height=int(c["map_height"]))
        secs = time.perf_counter() - t0
        m.meta.update(light=str(cfg["lights"][0]), seconds=secs)
        path = m.save(out_dir / f"shrm-eps{eps:g}.prt", overwrite=True)
        shrms.append((m, {"epsilon": float(eps), "F_B": m.F_B, "P_B": m.P_B, "energy": float(m.meta["energy"]),
                          "precompute_s": secs, "bytes": path.stat().st_size, "file": path.name}))
        log(f"[bench] convex: SHRM eps {eps:g}: F_B={m.F_B}, P_B={m.P_B}, {secs:.2f} s")
    rows = []
    for spec in c["meshes"]:
        mesh = load_convex_mesh(spec, c["size"])
        caster = RayCaster(mesh, workers=1)
        try:  # no method here has visibility: say how much a non-convex mesh shadows itself
            probe = probe_self_occlusion(caster, mesh)
        finally:
            caster.close()
        if probe["occluded_fraction"] > S.CONVEX_PROBE_TOL:
            log(f"[bench] convex: warning: mesh {mesh.name!r} is not convex: the self-occlusion probe finds "
                f"{probe['occluded_fraction']:.3g} of the diffuse energy shadowed; the SHRM, the PRT (shadows never) and the "
                "reference all ignore visibility")
        tr, tinfo = transfer_fn(mesh)
        ev = Evaluator(tr)
        L = env.project(ev.bands_in)  # [C, n²]: the PRT's light, the environment's own projection
        n = mesh.normals.to(torch.float64)
        n = n / n.norm(dim=-1, keepdim=True)
        pos = mesh.vertices.to(torch.float64)
        centre = pos.mean(0)
        cams = camera_positions(centre, float((pos - centre).norm(dim=-1).max()), cfg["views"]["count"],
                                cfg["views"]["elevation"], cfg["views"]["azimuth0"])
        acc = {"prt": [], "shrm": [[] for _ in shrms]}
        for cam in cams:
            v = cam[None] - pos
            v = v / v.norm(dim=-1, keepdim=True)
            cos = (v * n).sum(-1)
            facing, grazing = cos > FACING_COS, (cos > FACING_COS) & (cos < GRAZING_COS)
            ref = S.reference_radiance(brdf, dirs, Lw, n, v)
            w = ev.view_weights(cam)
            prt = ev.reference(L, w).to(torch.float64)

            def stats(rad):
                return {"psnr": psnr_vs_reference(ref, rad, facing), "clamped": psnr_vs_reference(ref, rad.clamp_min(0), facing),
                        "grazing": psnr_vs_reference(ref[grazing], rad[grazing]) if grazing.any() else float("nan"),
                        "min": float(rad[facing].min()), "facing": int(facing.sum()), "grazing_n": int(grazing.sum())}

            acc["prt"].append(stats(prt))
            panels = [("reference", ref)]
            for k, (m, _) in enumerate(shrms):
                rad = m.radiance(n, v, "map")
                s_ = stats(rad)
                s_["vs_prt"] = psnr_vs_reference(prt, rad, facing)
                acc["shrm"][k].append(s_)
                panels.append((f"SHRM {s_['psnr']:.1f} dB", rad))
            if shots is not None and len(acc["prt"]) == 1:  # the first camera's pictures
                shots.append({"mesh": mesh, "eye": cam,
                              "panels": panels + [(f"PRT {acc['prt'][0]['psnr']:.1f} dB", prt)]})

        def mean(xs, key):
            vals = [x[key] for x in xs if math.isfinite(x[key])]
            return sum(vals) / len(vals) if vals else float("nan")

        V = mesh.num_vertices
        raw = ev.raw_bytes
        prt_row = {"bands": ev.bands_in, "bands_out": math.isqrt(ev.matrix_shape[0]), "samples": tr.meta.get("samples"),
                   "psnr_db": mean(acc["prt"], "psnr"), "psnr_clamped_db": mean(acc["prt"], "clamped"),
                   "psnr_grazing_db": mean(acc["prt"], "grazing"), "min_radiance": min(x["min"] for x in acc["prt"]),
                   "bytes": raw, "bytes_per_vertex": raw / V, "precompute_s": float(tr.meta.get("seconds", tinfo["seconds"])),
                   "cache": tinfo["cache"]}
        # per frame: every vertex's radiance for the first camera, the two methods interleaved, one thread
        v0 = cams[0][None] - pos
        v0 = v0 / v0.norm(dim=-1, keepdim=True)
        w0 = ev.view_weights(cams[0])
        shrm_rows = []
        for k, (m, info) in enumerate(shrms):
            with torch_threads(1):
                pr = measure_paired(lambda: m.radiance(n, v0, "map"), lambda: ev.reference(L, w0),
                                    repeats=m_cfg["repeats"], warmup=m_cfg["warmup"], clock=time.thread_time)
            xs = acc["shrm"][k]
            shrm_rows.append({**info, "bytes_per_vertex": info["bytes"] / V, "psnr_db": mean(xs, "psnr"), "psnr_clamped_db": mean(xs, "clamped"),
                              "psnr_grazing_db": mean(xs, "grazing"), "min_radiance": min(x["min"] for x in xs),
                              "vs_prt_psnr_db": mean(xs, "vs_prt"), "frame_s": pr.test.median, "prt_frame_s": pr.peer.median,
                              "frame_ratio_prt_over_shrm": pr.ratio.median, "frame_ratio_spread": pr.ratio.spread,
                              "trusted": bool(pr.contention.get("trusted", False))})
        prt_row["frame_s"] = shrm_rows[0]["prt_frame_s"]
        rows.append({"mesh": mesh.name, "spec": spec, "vertices": V, "occluded_fraction": probe["occluded_fraction"],
                     "facing": acc["prt"][0]["facing"],
                     "grazing": acc["prt"][0]["grazing_n"], "prt": prt_row, "shrm": shrm_rows})
        log(f"[bench] convex: {mesh.name} ({V} vertices): PRT {prt_row['psnr_db']:.1f} dB, SHRM "
            + ", ".join(f"eps {x['epsilon']:g} {x['psnr_db']:.1f} dB" for x in shrm_rows))
    return {"brdf": brdf.meta(), "light": str(cfg["lights"][0]), "light_pixels": list(env.image.shape[:2]),
            "map_height": int(c["map_height"]), "epsilons": [float(e) for e in c["epsilons"]], "views": int(cfg["views"]["count"]),
            "shrms": [info for _, info in shrms], "rows": rows, "seconds": time.perf_counter() - t_start,
            "dir": out_dir.name}
