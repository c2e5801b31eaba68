"""Renders of a benchmark run (the run step makes them; the report only links them).

For the first light and view: the uncompressed result and, for each codec, its best setting
(highest PSNR), relit from the encoding the run saved (``records/<setting_id>.prt``, the
project's codec file — no refitting), side by side with an |error| heat map.

Every run also re-validates the GLSL decoders (prt_torch.render.glsl): each best setting is
rendered decoded in the vertex shader and as the CPU engine's per-vertex radiance
(``codec.relight``) with the same camera, and the PSNR of the GLSL image against the CPU image
(same coverage required) is recorded with the GLSL frame rate (per-light constants on the CPU,
upload, draw, float read-back) next to the CPU relighting rate of the same setting measured by
the run (``fps`` of its record).
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch

from .. import codecs, render
from .evaluate import Evaluator
from .timing import measure

__all__ = ["render_best", "best_per_codec", "glsl_check", "render_convex"]


def best_per_codec(records: list[dict]) -> dict[str, dict]:
    """codec name -> its record with the highest ``psnr_lights_db``."""
    best: dict[str, dict] = {}
    for x in records:
        if x["codec"] not in best or x["psnr_lights_db"] > best[x["codec"]]["psnr_lights_db"]:
            best[x["codec"]] = x
    return best


def glsl_check(rd, scene, light: torch.Tensor, cam, codec=None, enc=None, repeats: int = 5) -> dict:
    """GLSL vs CPU decode of one setting: ``{psnr_db, same_mask, max_abs, glsl_fps, glsl_spread}``
    (``psnr_db`` None when the images are identical, i.e. infinite), or ``{error}`` when the
    codec has no GLSL decoder or the shader fails."""
    try:
        c = render.glsl_vs_cpu(rd, scene, light, cam, codec, enc)
        dec = scene.decoder(light, scene.view(cam.eye), codec, enc)  # per-vertex data resident on the GPU
        Lm = scene.light_matrix(light)

        def frame():  # per light: constants on the CPU and their upload, draw, float read-back
            dec.set_light(Lm)
            return rd.render(scene.mesh, dec, cam)

        t = measure(frame, repeats=repeats, warmup=1)
    except (ValueError, TypeError) as e:
        return {"error": f"{type(e).__name__}: {e}"}
    return {"psnr_db": None if math.isinf(c.psnr_db) else float(c.psnr_db), "same_mask": c.same_mask,
            "max_abs": c.max_abs, "glsl_fps": 1.0 / t.median, "glsl_spread": t.spread}


def render_best(run_dir: Path, records: list[dict], ev: Evaluator, light: torch.Tensor, view: Any,
                eye: torch.Tensor, opts: dict) -> dict:
    """Render the uncompressed result and the best setting of each codec under ``light``
    (SH ``[C, n²]``) seen from ``eye [3]`` (``view``: its per-vertex weights); ``opts`` is the
    config's ``render`` section (width, height).

    Returns ``{"images": [composite paths relative to run_dir], "glsl": {codec name: {setting_id,
    psnr_db (GLSL vs CPU, None = identical), same_mask, glsl_fps, cpu_fps, ...}, "uncompressed":
    {...}}}`` — the GLSL decoders re-validated against the CPU engine in every run."""
    out_dir = Path(run_dir) / "renders"
    out_dir.mkdir(parents=True, exist_ok=True)
    mesh = ev.transfer.mesh
    ref = ev.uncompressed(light, view).clamp_min(0)
    center = ev.points.mean(0)
    radius = float((ev.points - center).norm(dim=-1).max())
    dist = float((eye - center).norm())
    # the same eye as the view directions used for glossy/MRT metrics; fov frames the bounding sphere
    fov = 2 * math.degrees(math.asin(min(0.99, 1.08 * radius / dist)))
    cam = render.Camera(eye=eye.numpy(), target=center.numpy(), fov=fov, near=max(1e-3, dist - 1.5 * radius), far=dist + 1.5 * radius)
    Lm = ev.light_matrix(light)
    paths = []
    glsl: dict[str, dict] = {}
    # a wavelet transfer has no GLSL decoder (Ng 2003: the terms change with every light; a CPU method)
    scene = render.PRTScene(ev.transfer) if ev.kind != "wavelet" else None
    with render.Renderer(opts["width"], opts["height"]) as rd:
        img_ref, mask = rd.render_radiance(mesh, ref, camera=cam)
        expo = render.auto_exposure(img_ref, mask)  # stops, shared by every panel
        render.save_png(out_dir / "uncompressed.png", img_ref, exposure=expo)
        render.save_exr(out_dir / "uncompressed.exr", img_ref)
        vmax = float(max(1e-12, abs(img_ref[mask]).max())) * 0.1 if mask.any() else None
        if scene is not None:
            glsl["uncompressed"] = glsl_check(rd, scene, light, cam)
        for name, x in sorted(best_per_codec(records).items()):
            codec, enc = codecs.load(Path(run_dir) / "records" / f"{x['setting_id']}.prt")
            out = ev.finish(codec.relight(enc, Lm, view=view)).clamp_min(0)
            img, _ = rd.render_radiance(mesh, out, camera=cam)
            heat = render.error_heatmap(img, img_ref, mask, vmax=vmax)
            p = out_dir / f"{x['setting_id']}.png"
            render.side_by_side([img_ref, img, heat],
                                ["uncompressed", f"{name} ({x['psnr_lights_db']:.1f} dB)", "|error| (10% of peak = top)"],
                                exposure=[expo, expo, 0.0], path=p)
            paths.append(f"renders/{p.name}")
            g = glsl_check(rd, scene, light, cam, codec, enc)
            g.update(setting_id=x["setting_id"], cpu_fps=x.get("fps"))
            glsl[name] = g
    return {"images": paths, "glsl": glsl}


def render_convex(run_dir: Path, shots: list[dict], opts: dict) -> list[str]:
    """The convex-objects section's pictures (:mod:`prt_torch.harness.convex`): per mesh, seen from
    its first camera, the brute-force reference | each SHRM | the glossy PRT, per-vertex radiance
    clamped at 0, one exposure for all panels, each labelled with its PSNR.

    ``shots``: ``[{"mesh": Mesh, "eye": [3] tensor, "panels": [(label, [V, C] radiance), ...]}]``
    with the reference first; ``opts``: the config's ``render`` section (width, height).
    Returns the composite paths relative to ``run_dir`` (``renders/convex-<mesh>.png``)."""
    out_dir = Path(run_dir) / "renders"
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    with render.Renderer(opts["width"], opts["height"]) as rd:
        for shot in shots:
            mesh, eye = shot["mesh"], shot["eye"].to(torch.float64)
            pts = mesh.vertices.to(torch.float64)
            center = pts.mean(0)
            radius = float((pts - center).norm(dim=-1).max())
            dist = float((eye - center).norm())
            fov = 2 * math.degrees(math.asin(min(0.99, 1.08 * radius / dist)))
            cam = render.Camera(eye=eye.numpy(), target=center.numpy(), fov=fov, near=max(1e-3, dist - 1.5 * radius),
                                far=dist + 1.5 * radius)
            imgs = [rd.render_radiance(mesh, rad.clamp_min(0).to(torch.float32), camera=cam)[0] for _, rad in shot["panels"]]
            expo = render.auto_exposure(imgs[0])
            p = out_dir / f"convex-{mesh.name}.png"
            render.side_by_side(imgs, [label for label, _ in shot["panels"]], exposure=expo, path=p)
            paths.append(f"renders/{p.name}")
    return paths
