"""BRDF recovery beyond Phong (issue 38, Ramamoorthi 2002 §6.4.2): the microfacet σ of eq. 5.34 and
Ashikhmin–Shirley by autograd non-linear least squares, and the isotropic SH BRDF ρ̂_lpq by linear
least squares — each against pixels rendered by an independent path: a brute-force quadrature, on a
dense Fibonacci set of *world* directions, of the BRDF formula written out here in numpy (not the
engine's classes, not its SH forward path)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prt_torch import inverse
from prt_torch.inverse import brdf_fit
from prt_torch.lighting import load_light
from prt_torch.render.camera import Camera
from prt_torch.scene import load_scene

FOV = 40.0


def _observe(mesh, n_views=4, W=24, max_pixels=None, el=30.0):
    cams = [Camera.fit(mesh, azimuth=10 + k * 360.0 / n_views, elevation=el, fov=FOV) for k in range(n_views)]
    views = [inverse.CameraView(None, np.linalg.inv(c.view_matrix()), None, None, None, None, W, W,
                                angle_x=math.radians(FOV)).resolve(W, W) for c in cams]
    imgs = [np.zeros((W, W, 3)) for _ in views]
    return inverse.observe(mesh, views, imgs, [np.ones((W, W), bool)] * len(views), max_pixels=max_pixels)


def _fib(n):
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = math.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1), 4 * math.pi / n


def _frames(mesh, obs):
    """The pixel's local frame as slice_model builds it (normal and tangent blended, Gram–Schmidt)."""
    b = obs.bary.numpy()[:, :, None]
    n = (mesh.normals.numpy().astype(np.float64)[obs.corners.numpy()] * b).sum(1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = (mesh.tangents.numpy().astype(np.float64)[obs.corners.numpy()] * b).sum(1)
    t -= (t * n).sum(1, keepdims=True) * n
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    return t, np.cross(n, t), n


def _brute_force(mesh, obs, L, fstar, n_dirs=30000):
    """Pixels ∫ f*(ω_i, ω_o) L(ω_i) dω_i over the world sphere (f* zero below the horizon): a Fibonacci
    set of ``n_dirs`` world directions, the light evaluated there, f* given in the pixel's frame."""
    from prt_torch.sh import eval_sh

    d, w = _fib(n_dirs)
    Ld = (eval_sh(torch.from_numpy(d), math.isqrt(L.shape[1])) @ L.T).numpy()  # [N, C]
    t, b, n = _frames(mesh, obs)
    e = obs.to_eye.numpy()
    wo = np.stack([(e * t).sum(1), (e * b).sum(1), (e * n).sum(1)], 1)
    out = np.zeros((obs.P, L.shape[0]))
    for a in range(0, obs.P, 64):  # chunks of pixels (memory)
        s = slice(a, a + 64)
        wi = np.stack([d @ t[s].T, d @ b[s].T, d @ n[s].T], -1).transpose(1, 0, 2)  # [p, N, 3]
        f = fstar(wi, wo[s, None, :])
        out[s] = np.einsum("pn,nc->pc", f, Ld) * w
    return torch.from_numpy(out)


def _microfacet(kd, ks, sigma):
    """Eq. 5.34 (f* = ks e^{−(θh/σ)²}/(4πσ²)) plus eq. 6.12's diffuse kd cos θi / π; zero when either
    direction is below the horizon."""
    def f(wi, wo):
        h = wi + wo
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        th = np.arccos(np.clip(h[..., 2], -1, 1))
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return np.where(up, kd / math.pi * wi[..., 2] + ks * np.exp(-(th / sigma) ** 2) / (4 * math.pi * sigma ** 2), 0.0)
    return f


def _ashikhmin_shirley(nu, nv, rs, rd):
    """Ashikhmin & Shirley 2000, eq. 4 (Schlick's Fresnel) + eq. 5, times cos θi."""
    def f(wi, wo):
        h = wi + wo
        h = h / np.linalg.norm(h, axis=-1, keepdims=True)
        ci, co, hn, kh = wi[..., 2], wo[..., 2], h[..., 2], (wi * h).sum(-1)
        sin2 = np.maximum(1 - hn * hn, 1e-30)
        expo = (nu * h[..., 0] ** 2 + nv * h[..., 1] ** 2) / sin2
        F = rs + (1 - rs) * (1 - kh) ** 5
        spec = math.sqrt((nu + 1) * (nv + 1)) / (8 * math.pi) * np.maximum(hn, 0) ** expo / (kh * np.maximum(ci, co)) * F
        diff = 28 * rd / (23 * math.pi) * (1 - rs) * (1 - (1 - ci / 2) ** 5) * (1 - (1 - co / 2) ** 5)
        up = (ci > 0) & (co > 0)
        return np.where(up, (spec + diff) * ci, 0.0)
    return f


def _light(bands=8):
    """A bright cap (the highlight that determines the lobe's width) over a sky, band-limited, lifted
    by a constant until its radiance is ≥ 0 everywhere (images must be ≥ 0)."""
    from prt_torch.sh import eval_sh

    L = load_light("cap:direction=0.3,0.2,1;half_angle_deg=20;intensity=3", bands) + load_light("sky", bands)
    d, _ = _fib(20000)
    lo = float((eval_sh(torch.from_numpy(d), bands) @ L.T).min())
    L[:, 0] += max(-lo, 0.0) / 0.28209479177387814
    return L


@pytest.fixture(scope="module")
def scene():
    mesh = load_scene("convex")
    L = _light()
    obs = _observe(mesh, n_views=4, W=24, max_pixels=300)
    sm = brdf_fit.slice_model(mesh, obs, L, visibility=False, quad_bands=16)
    return mesh, L, obs, sm


def test_microfacet_sigma_against_brute_force(scene):
    """σ within 2 %, kd and ks within 2 %, from pixels of eq. 5.34 + Lambertian by brute force."""
    mesh, L, obs, sm = scene
    truth = dict(kd=0.5, ks=0.6, sigma=0.2)
    y = _brute_force(mesh, obs, L, _microfacet(**truth))
    fit = brdf_fit.fit_parametric(sm, y, "microfacet")
    p = fit.params
    assert max(abs(k - truth["kd"]) for k in p["kd"]) < 0.02 * truth["kd"], p
    assert abs(p["ks"] - truth["ks"]) < 0.02 * truth["ks"], p
    assert abs(p["sigma"] - truth["sigma"]) < 0.02 * truth["sigma"], p
    assert 0 < fit.relative_stderr["sigma"] < 0.05
    held = brdf_fit.fit_parametric(sm, y, "microfacet", fixed={"sigma": 0.2})  # a held parameter stays, error 0
    assert held.params["sigma"] == 0.2 and held.stderr["sigma"] == 0.0
    assert abs(held.params["ks"] - truth["ks"]) < 0.02 * truth["ks"]


def test_ashikhmin_shirley_against_brute_force(scene):
    """Isotropic n within 5 %, rs and rd within 3 %."""
    mesh, L, obs, sm = scene
    truth = dict(nu=60.0, nv=60.0, rs=0.3, rd=0.6)
    y = _brute_force(mesh, obs, L, _ashikhmin_shirley(**truth))
    fit = brdf_fit.fit_parametric(sm, y, "ashikhmin-shirley")
    p = fit.params
    assert abs(p["n"] - 60.0) < 0.05 * 60.0, p
    assert abs(p["rs"] - 0.3) < 0.03 * 0.3, p
    assert max(abs(v - 0.6) for v in p["rd"]) < 0.03 * 0.6, p


def test_cli_microfacet_and_bad_input(tmp_path, capsys):
    """``prt invert --unknown brdf --brdf microfacet`` on EXR images of brute-force pixels: σ, kd,
    ks within 3 % with their standard errors in the output; bad --brdf options are one line, status 2."""
    import json

    from prt_torch.cli import main
    from prt_torch.lighting import write_image

    mesh = load_scene("convex")
    L = _light()
    W = 20
    obs = _observe(mesh, n_views=3, W=W)
    y = _brute_force(mesh, obs, L, _microfacet(0.4, 0.7, 0.25), n_dirs=20000)
    frames = []
    for k, v in enumerate(obs.views):
        write_image(tmp_path / f"v{k}.exr", obs.image(y, k))
        frames.append({"file_path": f"v{k}.exr", "transform_matrix": v.c2w.tolist()})
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": math.radians(FOV), "frames": frames}))
    (tmp_path / "light.json").write_text(json.dumps(inverse.light_json(L, 8, "test")))
    base = ["invert", "--mesh", "convex", "--cameras", str(tmp_path / "transforms.json"), "--unknown", "brdf",
            "--light", str(tmp_path / "light.json"), "--bands", "8"]
    out = tmp_path / "mf.json"
    assert main(base + ["--brdf", "microfacet", "--max-pixels", "300", "-o", str(out)]) == 0
    res = json.loads(out.read_text())["inverse"]
    p = res["brdf"]
    assert p["type"] == "microfacet" and abs(p["sigma"] - 0.25) < 0.03 * 0.25 and abs(p["ks"] - 0.7) < 0.03 * 0.7
    assert max(abs(v - 0.4) for v in p["kd"]) < 0.03 * 0.4
    assert 0 < res["brdf_fit"]["stderr"]["sigma"] < 0.01 and res["pixels"] == 300
    assert res["residual"]["psnr_db"] > 40
    capsys.readouterr()
    for extra, needle in [(["--brdf", "cook-torrance"], "--brdf 'cook-torrance'; accepted: lambertian, phong, microfacet"),
                          (["--brdf", "microfacet", "--brdf-param", "s=3"], "--brdf-param s=3; accepted for microfacet: kd, ks, sigma"),
                          (["--brdf", "microfacet", "--brdf-param", "sigma=0"], "--brdf-param sigma=0; accepted: a finite number in"),
                          (["--brdf", "microfacet", "--brdf-bands", "3"], "--brdf-bands 3 with --brdf microfacet; accepted: --brdf sh only")]:
        assert main(base + extra + ["-o", str(tmp_path / "x.json")]) == 2
        err = capsys.readouterr().err.strip()
        assert needle in err and len(err.splitlines()) == 1, err
    assert main(["invert", "--mesh", "convex", "--cameras", str(tmp_path / "transforms.json"), "--unknown", "light",
                 "--brdf", "ashikhmin-shirley", "-o", str(tmp_path / "x.json")]) == 2
    assert "accepted: --unknown brdf" in capsys.readouterr().err
    assert not (tmp_path / "x.json").exists()
