"""``prt invert`` precomputing glossy and MRT transfer itself (issue 38): ``--kind glossy|mrt``
with the precompute's BRDF and band options. Round trip: images of the engine's glossy / MRT
radiance (``relight.glossy`` / ``relight.mrt``, the reference relight paths, each pixel the
barycentric blend of its triangle's vertices towards that pixel's camera, written as float32 EXR
with alpha) under a known light are inverted, with no ``--transfer``, to that light to 1e-6
relative; bad combinations are one line, status 2, before any work."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from prt_torch import inverse, relight
from prt_torch.cli import main
from prt_torch.lighting import load_light, write_image
from prt_torch.render.camera import Camera
from prt_torch.render.prt import PRTScene
from prt_torch.scene import load_scene
from prt_torch.transfer import RunOptions, get_kind

FOV, W, VIEWS, BANDS = 40.0, 32, 4, 3
MESH = "occluder_over_plane"
KIND_ARGS = {"glossy": ["--transfer-brdf", "phong", "--transfer-brdf-param", "s=8", "--samples", "64"],
             "mrt": ["--transfer-brdf", "phong", "--transfer-brdf-param", "s=8", "--samples", "64", "--tents", "4",
                     "--bands-out", "4"]}
KIND_PARAMS = {"glossy": {"bands": BANDS, "samples": 64, "bounces": 0, "brdf": {"type": "phong", "s": 8}},
               "mrt": {"bands": BANDS, "samples": 64, "bounces": 0, "brdf": {"type": "phong", "s": 8}, "M": 4, "bands_out": 4}}


def _dataset(d, T, L):
    """EXR views (RGB + alpha = the pixels whose ray hits the mesh, radiance ≥ 0) of the engine's radiance of
    transfer ``T`` under ``L``, and their transforms.json."""
    mesh = T.mesh
    cams = [Camera.fit(mesh, azimuth=10 + k * 360.0 / VIEWS, elevation=30.0, fov=FOV) for k in range(VIEWS)]
    views = [inverse.CameraView(None, np.linalg.inv(c.view_matrix()), None, None, None, None, W, W,
                                angle_x=math.radians(FOV)).resolve(W, W) for c in cams]
    obs = inverse.observe(mesh, views, [np.zeros((W, W, 3))] * VIEWS, [np.ones((W, W), bool)] * VIEWS)
    sc = PRTScene(T)
    corner = obs.corners.reshape(-1)
    vl = relight.local_view(sc.frames[corner], direction=obs.to_eye.repeat_interleave(3, 0))
    M = T.data.to(torch.float64)[corner]
    r = relight.glossy(M, L, vl, T.meta.get("out_index")) if T.kind == "glossy" else relight.mrt(M, L, vl)
    vals = (r.reshape(-1, 3, r.shape[1]) * obs.bary[:, :, None]).sum(1)
    frames = []
    for k, c in enumerate(cams):
        # alpha: the pixel hits the mesh and its radiance is ≥ 0 (a 3-band glossy transfer's exit radiance can ring
        # slightly below 0 under a non-negative light; the CLI refuses negative pixels unless masked)
        ok = (vals >= 0).all(1, keepdim=True).to(torch.float64)
        img = np.concatenate([obs.image(vals * ok, k), obs.image(ok, k)], 2)
        write_image(d / f"v{k}.exr", img)
        frames.append({"file_path": f"v{k}.exr", "transform_matrix": np.linalg.inv(c.view_matrix()).tolist()})
    (d / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(FOV), "frames": frames}))
    return d / "transforms.json"


def _physical(spec):
    """The light's band-limited radiance lifted by a constant until it is ≥ 0 everywhere (images
    cannot hold negative radiance; the CLI refuses them)."""
    from prt_torch.sh import eval_sh
    from prt_torch.sh.quadrature import fibonacci_sphere

    L = load_light(spec, BANDS)
    rad = eval_sh(fibonacci_sphere(8192)[0], BANDS) @ L.T  # [D, C]
    L[:, 0] += (-rad.min(0).values).clamp_min(0) * 1.2 * 2 * math.sqrt(math.pi)  # Y00 = 1/(2√π)
    return L


@pytest.mark.parametrize("kind", ["glossy", "mrt"])
def test_cli_precomputes_glossy_and_mrt_and_inverts_to_1e6(tmp_path, kind):
    mesh = load_scene(MESH)
    T = get_kind(kind).precompute(mesh, KIND_PARAMS[kind], run=RunOptions(workers=1))
    L = _physical("studio")
    tj = _dataset(tmp_path, T, L)
    out = tmp_path / "r.json"
    assert main(["invert", "--mesh", MESH, "--cameras", str(tj), "--unknown", "light", "--bands", str(BANDS),
                 "--kind", kind, *KIND_ARGS[kind], "-o", str(out)]) == 0
    res = json.loads(out.read_text())
    got = torch.tensor(res["coeffs"], dtype=torch.float64)
    assert float((got - L).norm() / L.norm()) < 1e-6
    tr = res["inverse"]["transfer"]
    assert tr["kind"] == kind and tr["precomputed"] and tr["meta"]["samples"] == 64
    # the glossy transfer's view dependence is in the model: the same images through a diffuse transfer fit far worse
    out2 = tmp_path / "d.json"
    assert main(["invert", "--mesh", MESH, "--cameras", str(tj), "--unknown", "light", "--bands", str(BANDS),
                 "--samples", "64", "-o", str(out2)]) == 0
    assert json.loads(out2.read_text())["inverse"]["residual"]["psnr_db"] < res["inverse"]["residual"]["psnr_db"] - 40


@pytest.mark.parametrize("extra,needle", [
    (["--kind", "glossy", "--unknown", "brdf", "--brdf", "phong", "--light", "sky"], "--kind glossy with --unknown brdf"),
    (["--kind", "mrt", "--unknown", "light", "--brdf", "phong", "--brdf-param", "kd=0.5", "--brdf-param", "ks=0.5",
      "--brdf-param", "s=8"], "--transfer-brdf"),
    (["--kind", "glossy", "--unknown", "light", "--tents", "4"], "--tents with --kind glossy"),
    (["--unknown", "light", "--bands-out", "4"], "--bands-out with --kind diffuse"),
    (["--kind", "mrt", "--unknown", "light", "--tents", "1"], "--tents 1; accepted"),
    (["--kind", "glossy", "--unknown", "light", "--transfer-brdf", "shiny"], "--transfer-brdf {'type': 'shiny'}"),
    (["--kind", "glossy", "--unknown", "light", "--transfer", "t.prt"], "with --transfer"),
])
def test_bad_kind_options_one_line(tmp_path, capsys, extra, needle):
    mesh = load_scene("bumpy_sphere")
    cam = Camera.fit(mesh, azimuth=10, elevation=30, fov=FOV)
    write_image(tmp_path / "v0.pfm", np.full((16, 16, 3), 0.5, np.float32))
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(FOV), "frames": [
        {"file_path": "v0.pfm", "transform_matrix": np.linalg.inv(cam.view_matrix()).tolist()}]}))
    (tmp_path / "t.prt").write_bytes(b"")
    rc = main(["invert", "--mesh", "bumpy_sphere", "--cameras", str(tmp_path / "transforms.json"), *extra,
               "-o", str(tmp_path / "o.json")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and needle in err, err
    assert not (tmp_path / "o.json").exists()
