"""Inverse rendering against an independent renderer (issue 38): images of a self-shadowing mesh
path-traced by Mitsuba 3 under an SH-band-limited environment, with their cameras in a
``transforms.json``, are inverted by ``prt invert`` to that environment's 9×3 SH coefficients —
no scale fit (the albedo is known), 8 views. Ramamoorthi 2002 §6.4.3 (eq. 6.16, here with
visibility through the precomputed transfer).

Why these views (docs/inverse.md, "Against Mitsuba 3"): the light is determined only in the
directions the pixels see. ``bumpy_sphere`` seen from the 8 corners of a cube shows every normal
(design condition ~4); ``sphere_on_plane`` seen only from above hides the light from below
(condition ~200, its weakest direction the zonal lobe towards −z), and a 0.1–0.3% systematic
difference between the images and the model (silhouette pixels mixing in the background, which
the coverage mask now removes; Gouraud vs per-point shading) moves the light by 24–45% — the
failure of the first attempt, measured by ``test_light_from_below_is_the_ill_posed_direction``.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba", reason="pip install 'prt-torch[validate]'")

from prt_torch import inverse  # noqa: E402
from prt_torch.cli import main  # noqa: E402
from prt_torch.lighting import load_light, write_image  # noqa: E402
from prt_torch.render.camera import Camera  # noqa: E402
from prt_torch.scene import load_scene  # noqa: E402
from prt_torch.validate.lights import check_expressible, light_image  # noqa: E402
from prt_torch.validate.scenes import mitsuba_views  # noqa: E402

FOV = 40.0
ALBEDO = 0.8
Y00 = 0.5 / math.sqrt(math.pi)


def _light() -> torch.Tensor:
    """``studio`` at 3 bands, lifted by a constant until its band-limited radiance is ≥ 0
    everywhere (Mitsuba cannot emit negative radiance; clipping the lobes would change the
    light): all 27 coefficients non-zero, coloured."""
    L = load_light("studio", 3).clone()
    L[:, 0] += 1.25 * max(0.0, -float(light_image(L, 64).min())) / Y00
    return L


def _cube_views(mesh, W):
    cams = [Camera.fit(mesh, azimuth=45 + 90 * k, elevation=e, fov=FOV) for e in (35.26, -35.26) for k in range(4)]
    return cams, [inverse.CameraView(None, np.linalg.inv(c.view_matrix()), None, None, None, None, W, W,
                                     angle_x=math.radians(FOV)).resolve(W, W) for c in cams]


def _invert(tmp_path, bounces, tag):
    out = tmp_path / f"light{tag}.json"
    assert main(["invert", "--mesh", "bumpy_sphere", "--albedo", str(ALBEDO), "--cameras", str(tmp_path / "transforms.json"),
                 "--unknown", "light", "--bands", "3", "--samples", "1024", "--bounces", str(bounces), "-o", str(out)]) == 0
    return json.loads(out.read_text())


@pytest.mark.parametrize("bounces", [0, 2])
def test_mitsuba_images_invert_to_their_light_within_3_percent(tmp_path, bounces):
    """bumpy_sphere (self-shadowing, interreflecting), 8 views from the cube's corners, 48×48 px,
    64 spp; Mitsuba's ``max_depth`` = 2 + the engine's ``--bounces`` (0: direct light with
    shadows; 2: two bounces): the 27 coefficients come back within 3% relative (L2, measured
    1.4% and 0.7%; each channel too), and the images determine bands 0-2. With bounces in the
    images, a model without them is off by more than 3% (measured 5.8%): interreflection is data."""
    mesh = load_scene("bumpy_sphere", albedo=[ALBEDO] * 3)
    L = _light()
    W = 48
    cams, views = _cube_views(mesh, W)
    imgs = mitsuba_views(mesh, views, check_expressible(L, "studio+", 64), spp=64, max_depth=2 + bounces, seed=3)
    frames = []
    for k, (c, im) in enumerate(zip(cams, imgs)):
        a = (im[..., 3:] > 0.999).astype(np.float32)  # whole pixels of the mesh; silhouettes mix in the background
        write_image(tmp_path / f"v{k}.exr", np.concatenate([im[..., :3] * a, a], 2))
        frames.append({"file_path": f"v{k}", "transform_matrix": np.linalg.inv(c.view_matrix()).tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(FOV), "frames": frames}))
    res = _invert(tmp_path, bounces, "")
    got = torch.tensor(res["coeffs"], dtype=torch.float64)
    assert got.shape == (3, 9)
    print(f"mitsuba -> light: rel L2 {float((got - L).norm() / L.norm()):.4f}, per channel "
          f"{[round(float((got[c] - L[c]).norm() / L[c].norm()), 4) for c in range(3)]}, psnr {res['inverse']['residual']['psnr_db']:.1f} dB")
    assert float((got - L).norm() / L.norm()) < 0.03
    for c in range(3):
        assert float((got[c] - L[c]).norm() / L[c].norm()) < 0.03
    wp = res["inverse"]["well_posedness"]
    assert wp["recoverable_bands"] == [0, 1, 2] and wp["condition"] < 10
    assert max(b["gain"] for b in wp["bands"]) < 10  # a 1% model error moves no coefficient by more than 10% of ‖L‖
    if bounces:
        direct = torch.tensor(_invert(tmp_path, 0, "_direct")["coeffs"], dtype=torch.float64)
        print(f"  through a model without bounces: rel L2 {float((direct - L).norm() / L.norm()):.4f}")
        assert float((direct - L).norm() / L.norm()) > 0.03


def test_light_from_below_is_the_ill_posed_direction():
    """The first attempt's 33-44%: sphere_on_plane seen only from above. The engine's own images
    of the same cameras invert exactly (so cameras and conventions agree), Mitsuba's agree with
    the engine's to ~1% in sum, yet the design's weakest direction (s_min/s_max < 1%) is the
    zonal lobe from below (Y00, Y10, Y20 only), which the plane hides: the error of the light
    recovered from Mitsuba's images lies along it."""
    from prt_torch.render.prt import PRTScene
    from prt_torch.transfer.diffuse import precompute_diffuse

    mesh = load_scene("sphere_on_plane", albedo=[ALBEDO] * 3)
    T = precompute_diffuse(mesh, bands=3, samples=1024, shadows="always", fold_albedo=False)
    L = _light()
    W = 40
    cams = [Camera.fit(mesh, azimuth=10 + 45 * k, elevation=60, fov=FOV) for k in range(8)]
    views = [inverse.CameraView(None, np.linalg.inv(c.view_matrix()), None, None, None, None, W, W,
                                angle_x=math.radians(FOV)).resolve(W, W) for c in cams]
    imgs = mitsuba_views(mesh, views, check_expressible(L, "studio+", 64), spp=32, max_depth=2, seed=1)
    obs = inverse.observe(mesh, views, [im[..., :3].astype(np.float64) for im in imgs], [im[..., 3] > 0.999 for im in imgs])
    A = inverse.design_matrix(PRTScene(T), obs)
    engine = torch.einsum("cpn,cn->pc", A, L)
    assert float((inverse.fit_light(A, engine).light - L).norm() / L.norm()) < 1e-8  # same cameras: exact
    assert abs(float(obs.values.sum() / engine.sum()) - 1) < 0.015
    _, s, Vh = torch.linalg.svd(A[0], full_matrices=False)
    assert float(s[-1] / s[0]) < 0.01
    weak = Vh[-1]
    assert float(weak[[0, 2, 6]].norm()) > 0.999 and float(weak[2] * weak[0]) < 0  # zonal, pointing down (−z)
    fit = inverse.fit_light(A, obs.values)
    err = fit.light - L
    rep = fit.report  # the report names the culprit: a large gain, the weakest combination peaking at −z
    assert max(b["gain"] for b in rep["bands"]) > 30  # measured 50-130 (GCV's λ moves with the noise); bumpy_sphere: 3.8
    assert rep["weakest"]["peak_direction"][2] < -0.95
    assert rep["weakest"]["relative_singular_value"] < 0.01
    along = (err @ weak).norm()  # per channel, the error's component on the weakest direction
    print(f"sphere_on_plane from above: light rel L2 {float(err.norm() / L.norm()):.3f}, s_min/s_max {float(s[-1] / s[0]):.4f}, "
          f"share of the error on the weakest direction {float(along / err.norm()):.3f}")
    assert float(along / err.norm()) > 0.8  # measured 0.93 here, 0.98-0.998 at 64×64


def test_faces_seen_from_behind_are_dropped_as_mitsuba_renders_them_black():
    """Views from just below sphere_on_plane's ground see mostly its underside, which the
    transfer (the front side's) does not describe and Mitsuba's one-sided BSDF renders black:
    ``observe`` drops those pixels (``counts[k]['back']``), and what is left of each view — the
    sphere beyond the plane's edge — agrees with Mitsuba in sum (it was 2% of the model's before
    the rule: the underside's pixels carried the top's transfer)."""
    from prt_torch.render.prt import PRTScene
    from prt_torch.transfer.diffuse import precompute_diffuse

    mesh = load_scene("sphere_on_plane", albedo=[ALBEDO] * 3)
    T = precompute_diffuse(mesh, bands=3, samples=512, shadows="always", fold_albedo=False)
    L = _light()
    W = 40
    cams = [Camera.fit(mesh, azimuth=45 + 90 * k, elevation=-10, fov=FOV) for k in range(4)]
    views = [inverse.CameraView(None, np.linalg.inv(c.view_matrix()), None, None, None, None, W, W,
                                angle_x=math.radians(FOV)).resolve(W, W) for c in cams]
    imgs = mitsuba_views(mesh, views, check_expressible(L, "studio+", 64), spp=32, max_depth=2, seed=2)
    obs = inverse.observe(mesh, views, [im[..., :3].astype(np.float64) for im in imgs], [im[..., 3] > 0.999 for im in imgs])
    model = torch.einsum("cpn,cn->pc", inverse.design_matrix(PRTScene(T), obs), L)
    for k in range(4):
        assert obs.counts[k]["back"] > obs.counts[k]["hit"] > 20
        sel = obs.view == k
        print(k, obs.counts[k], float(obs.values[sel].sum() / model[sel].sum()))
        assert abs(float(obs.values[sel].sum() / model[sel].sum()) - 1) < 0.1
