"""Spherical harmonic reflection maps (prt_torch.shrm, Ramamoorthi 2002 ch. 5) against independent
references: the engine's irradiance maps (ch. 4), brute-force hemispherical integrals, the
environment's own SH projection, the angular-space prefilter, and the thesis' numbers."""
from __future__ import annotations

import math

import pytest
import torch

from prt_torch import shrm as S
from prt_torch.brdf import AshikhminShirley, BlinnPhong, Lambertian, Microfacet, Phong, Ward
from prt_torch.lighting import builtin_environment, irradiance, irradiance_map, load_light
from prt_torch.sh import eval_sh, gauss_sphere, latlong_grid


@pytest.fixture(scope="module")
def light6():
    return load_light("studio", bands=6, size=32)


def _unit(n, seed):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return d / d.norm(dim=-1, keepdim=True)


def _grid_dirs(H, W):
    return latlong_grid(H, W)[0]


def _brute_force(brdf, L, normals, view, extended=False, quad_bands=120):
    """∫ L(ω) f_r(ω, v) max(n·ω, 0) dω per normal by a product Gauss rule over the whole sphere, in
    each normal's own tangent frame (the BRDF's definition; nothing of the SHRM code)."""
    dirs, w = gauss_sphere(quad_bands)
    bands = int(round(math.sqrt(L.shape[-1])))
    Lval = eval_sh(dirs, bands) @ L.T  # [Q, C]
    t = torch.linalg.cross(normals, torch.tensor([0.31, 0.17, 0.93], dtype=torch.float64).expand_as(normals))
    t = t / t.norm(dim=-1, keepdim=True)
    fr = torch.stack([t, torch.linalg.cross(normals, t), normals], -2)  # rows: tangent, bitangent, normal
    wi = torch.einsum("nij,qj->nqi", fr, dirs)
    wo = (fr @ view)[:, None, :].expand_as(wi)
    f = brdf.extended(wi, wo) if extended else brdf.cosine_weighted(wi, wo)
    return torch.einsum("nq,q,qc->nc", f, w, Lval)


def _rel_sq(a, b):
    return float(((a - b) ** 2).sum() / (b ** 2).sum())


def test_lambertian_shrm_is_the_irradiance_map(light6):
    """ch. 4 reduction: the Lambertian SHRM's map is kd/π times the engine's irradiance map
    (lighting.irradiance_map, A_l of eq. 4.11) texel by texel, and its radiance kd E(n)/π."""
    s = S.build_shrm(Lambertian(0.8), light6, orders=(5, 0), height=16)
    assert s.axis == "normal" and (s.F_B, s.P_B) == (5, 0)
    env = irradiance_map(light6, "latlong", 16)  # 16 x 32, the same grid
    ours = s.maps[:, 0].permute(1, 2, 0).double() * float(eval_sh(torch.tensor([[0.0, 0.0, 1.0]]), 1)[0, 0])
    assert torch.allclose(ours, 0.8 / math.pi * env.image.double(), rtol=1e-5, atol=1e-6)
    n = _unit(300, 1)
    ref = 0.8 / math.pi * irradiance(light6, n)
    assert torch.allclose(s.radiance(n, n, "coeffs"), ref, atol=1e-12)
    v = _unit(300, 2)
    vis = (n * v).sum(-1) > 0
    assert torch.allclose(s.radiance(n[vis], v[vis], "map"), ref[vis], rtol=0.02, atol=0.02 * float(ref.abs().max()))


def test_lambertian_through_the_general_quadrature(light6):
    """A Lambertian written as Blinn-Phong with ks = 0 is not radial, so it goes through the
    reflection-vector quadrature (eq. 5.22) and the P > 0 prefilter; it must still give kd E(n)/π
    for every view, within the ε its orders promise."""
    b = BlinnPhong(s=1.0, ks=0.0, kd=0.8)
    s = S.build_shrm(b, light6, epsilon=0.01, height=32)
    assert s.axis == "reflection" and s.P_B > 0
    n, v = _unit(400, 3), _unit(400, 4)
    vis = (n * v).sum(-1) > 0.05
    n, v = n[vis], v[vis]
    ref = 0.8 / math.pi * irradiance(light6, n)
    assert _rel_sq(s.radiance(n, v, "coeffs"), ref) <= 0.01
    assert _rel_sq(s.radiance(n, v, "map"), ref) <= 0.01


@pytest.mark.parametrize("brdf,eps,extended", [
    (Microfacet(0.3), 0.03, False),
    (Phong(32.0, form="reflection"), 0.01, True),
    (BlinnPhong(16.0), 0.03, False),
])
def test_sphere_matches_brute_force_within_epsilon(light6, brdf, eps, extended):
    """A sphere seen from one distant view: SHRM radiance against a brute-force integral per
    normal (the Phong reflection form as the thesis treats it, §3.2.6: the lobe not cut at the
    horizon), relative squared error ≤ the predicted ε, through the coefficients and the maps."""
    s = S.build_shrm(brdf, light6, epsilon=eps, height=64)
    assert 1 - s.meta["energy"] <= eps
    view = torch.tensor([0.3, -0.5, 0.81], dtype=torch.float64)
    view = view / view.norm()
    n = _unit(500, 5)
    n = n[(n @ view) > 0.05][:200]
    ref = _brute_force(brdf, light6, n, view, extended=extended)
    assert _rel_sq(s.radiance(n, view, "coeffs"), ref) <= eps
    assert _rel_sq(s.radiance(n, view, "map"), ref) <= eps


def test_radiance_zero_facing_away(light6):
    s = S.build_shrm(Microfacet(0.4), light6, orders=(5, 2), height=8)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    assert float(s.radiance(n, -n, "coeffs").abs().max()) == 0.0


def test_two_prefilters_give_the_same_maps():
    """Frequency-space (eq. 5.23–5.24) and angular-space (hemispherical sums per texel) prefilters
    of one lat-long light (a band-limited image, so both converge to the same maps)."""
    L = load_light("studio", bands=6, size=32)
    H = W = 32
    img = (eval_sh(_grid_dirs(H, W).reshape(-1, 3), 6) @ L.T).reshape(H, W, 3)
    views = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, -0.8, 0.6]], dtype=torch.float64)
    for brdf, orders, tol in ((Phong(16.0, form="reflection"), (16, 0), 2e-3), (Microfacet(0.3), (20, 8), 1e-2)):
        F, P = orders
        rho, _ = S.brdf_coefficients(brdf, F, P)
        fm = S.prefilter_frequency(S.project_latlong(img, F + 1), rho, F, P, H, W)
        fmaps = torch.einsum("vj,cjhw->vchw", eval_sh(views, P + 1), fm)
        am = S.prefilter_angular(img, brdf, H, views, cone=S.angular_cone(brdf, 1e-4))
        assert float((am - fmaps).norm() / am.norm()) < tol, brdf


def test_project_latlong_equals_environment_projection():
    """The separable transform of eq. 5.21 against Environment.project (all pixels, eval_sh)."""
    env = builtin_environment("studio", size=16)  # latlong 16 x 32
    assert torch.allclose(S.project_latlong(env.image, 7), env.project(7), rtol=1e-9, atol=1e-10)


def test_frame_convention_matches_engine_rotation():
    """local_frames' columns are R_αβ = Rz(β) Ry(α): its third column is the axis, and the engine's
    rotation of L by the frame's transpose is the light seen in that frame."""
    d = _unit(50, 7)
    R = S.local_frames(d)
    assert torch.allclose(R[..., 2], d, atol=1e-12)
    assert torch.allclose(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(50, dtype=torch.float64))


def test_orders_table_5_5():
    """Table 5.5: microfacet (eq. 5.34), ε < 0.03 -> (F_B, P_B) = (24,3), (12,2), (7,2), (5,2), (5,2).
    Ours: P_B = 2 for σ ≥ 0.2 (Fig. 5.6: P = 2 gives ε < .03 at σ = 0.2) and F_B within one order of
    the thesis'; σ = 0.1 needs P = 2 here (reports/benchmarks/shrm.md shows the energies)."""
    paper = {0.2: (12, 2), 0.3: (7, 2), 0.4: (5, 2), 0.5: (5, 2)}
    for sigma, (F, P) in paper.items():
        F_B, P_B, info = S.choose_orders(Microfacet(sigma), 0.03)
        assert P_B == P and abs(F_B - F) <= 1 and info["energy"] >= 0.97, (sigma, F_B, P_B)


def test_phong_orders_follow_eq_5_28():
    """Phong, reflection form: F ≈ √(-s log ε) (eq. 5.28, from Λ_l ρ_l ≈ exp(-l²/2s), eq. 3.40)."""
    for s_ in (8.0, 32.0, 128.0):
        F_B, P_B, info = S.choose_orders(Phong(s_, form="reflection"), 0.01)
        assert P_B == 0 and info["radial"] == "reflection"
        assert abs(F_B - math.sqrt(-s_ * math.log(0.01))) <= 2, (s_, F_B)


def test_energy_estimates_are_conservative(light6):
    """Fig. 5.5: both estimates (min of errors, residual bound eq. 5.19) and the BRDF error
    are at least the true error of an order-F truncation of B (radial Phong, exact light)."""
    brdf = Phong(32.0, form="reflection")
    rho, total = S.brdf_coefficients(brdf, 30, 0)
    lam2 = torch.tensor([4 * math.pi / (2 * l + 1) for l in range(31)], dtype=torch.float64)
    L = torch.nn.functional.pad(light6, (0, 31 * 31 - light6.shape[-1]))
    l_idx = torch.repeat_interleave(torch.arange(31), 2 * torch.arange(31) + 1)
    Be = (L ** 2).sum(0) * lam2[l_idx] * rho[l_idx, 0, 0] ** 2
    for F in (2, 4, 5):
        true_eps = 1 - float(Be[: (F + 1) ** 2].sum() / Be.sum())
        bound = S.residual_bound(rho, total, light6, float((light6 ** 2).sum()), F, 0)
        eps_rho = 1 - float(S.energy_table(rho)[F, 0]) / total
        assert bound >= 0 and eps_rho >= true_eps * 0.999


def test_save_load_roundtrip(tmp_path, light6):
    s = S.build_shrm(Microfacet(0.4), light6, epsilon=0.05, height=8)
    p = s.save(tmp_path / "m.prt")
    t = S.load_shrm(p)
    assert (t.F_B, t.P_B, t.axis) == (s.F_B, s.P_B, s.axis)
    assert torch.equal(t.maps, s.maps) and torch.equal(t.rho, s.rho) and torch.equal(t.light, s.light)
    assert t.meta["reason"] == s.meta["reason"]
    with pytest.raises(FileExistsError):
        s.save(p)


@pytest.mark.parametrize("brdf,word", [
    (AshikhminShirley(40.0, 10.0), "anisotropic"),
    (Ward(0.1, 0.3), "anisotropic"),
    (Phong(torch.tensor([8.0, 16.0]), form="reflection"), "batch"),
])
def test_refuses_anisotropic_and_batched_brdfs(light6, brdf, word):
    with pytest.raises(ValueError, match=word) as e:
        S.build_shrm(brdf, light6, epsilon=0.03, height=8)
    assert "accepted: isotropic BRDFs" in str(e.value) and type(brdf).__name__ in str(e.value)


@pytest.mark.parametrize("eps", [0.0, 1.0, -0.1, 1.5, float("nan")])
def test_refuses_epsilon_outside_unit_interval(light6, eps):
    with pytest.raises(ValueError, match=r"epsilon=.*accepted: finite values in \(0, 1\)"):
        S.build_shrm(Microfacet(0.3), light6, epsilon=eps, height=8)


def test_refuses_orders_too_large_for_memory_before_work(light6):
    with pytest.raises(ValueError, match=r"orders=\(120, 60\).*GiB.*estimated before any work.*accepted"):
        S.build_shrm(Microfacet(0.3), light6, orders=(120, 60), height=512)
    with pytest.raises(ValueError, match="orders P_B"):
        S.build_shrm(Microfacet(0.3), light6, orders=(4, -1), height=8)
    with pytest.raises(ValueError, match="orders F_B"):
        S.build_shrm(Microfacet(0.3), light6, orders=(400, 2), height=8)


def test_cli_shrm_json_and_file(tmp_path, capsys):
    """`prt shrm ... --json` prints F_B, P_B and the energy; the file loads back. σ = 0.3 at ε = 0.03
    is the thesis' (7, 2) (Table 5.5)."""
    import json

    from prt_torch.cli import main

    out = tmp_path / "m.prt"
    rc = main(["shrm", "--brdf", "microfacet", "--brdf-param", "sigma=0.3", "--light", "studio", "--epsilon", "0.03",
               "--size", "16", "-o", str(out), "--json"])
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    assert (info["F_B"], info["P_B"]) == (7, 2) and 0.97 <= info["energy"] < 1
    m = S.load_shrm(out)
    assert (m.F_B, m.P_B) == (7, 2) and tuple(m.maps.shape) == (3, 9, 16, 32)
    assert main(["shrm", "--brdf", "microfacet", "--light", "studio", "--size", "8", "-o", str(out)]) == 2  # exists
    assert "--overwrite" in capsys.readouterr().err
    assert main(["shrm", "--brdf", "ward", "--brdf-param", "ax=0.1", "--brdf-param", "ay=0.3", "--light", "studio",
                 "-o", str(tmp_path / "w.prt")]) == 2
    assert "anisotropic" in capsys.readouterr().err
    assert main(["shrm", "--brdf", "phong", "--light", "sky", "--orders", "3", "-o", str(tmp_path / "p.prt")]) == 2
    assert "--orders='3'; accepted: two integers F,P" in capsys.readouterr().err


def test_render_shrm_constant_light_gives_albedo(tmp_path, capsys):
    """`prt render SHRM.prt --mesh convex`: a Lambertian SHRM under uniform radiance 1 shades every
    covered pixel kd (E = π everywhere), through the maps, the per-vertex views and the renderer."""
    import numpy as np
    import OpenImageIO as oiio

    from prt_torch.cli import main

    m = tmp_path / "lam.prt"
    assert main(["shrm", "--brdf", "lambertian", "--brdf-param", "kd=0.8", "--light", "constant:value=1",
                 "--orders", "2,0", "--size", "16", "-o", str(m)]) == 0
    out = tmp_path / "lam.exr"
    rc = main(["render", str(m), "--mesh", "convex", "-o", str(out), "--width", "40", "--height", "32",
               "--background", "-1", "--supersample", "1", "--decode", "cpu"])
    if rc == 3:
        pytest.skip("no EGL context: " + capsys.readouterr().err)
    assert rc == 0, capsys.readouterr().err
    inp = oiio.ImageInput.open(str(out))
    spec = inp.spec()
    img = np.asarray(inp.read_image(0, 0, 0, spec.nchannels, "float")).reshape(spec.height, spec.width, -1)
    inp.close()
    covered = img[:, :, 0] != -1
    assert covered.sum() > 200 and np.abs(img[covered] - 0.8).max() < 1e-4
    assert "warning" not in capsys.readouterr().err  # convex: no self-occlusion
    assert main(["render", str(m), "--mesh", "sphere_on_plane", "-o", str(tmp_path / "s.png"), "--width", "24",
                 "--height", "24"]) == 0
    err = capsys.readouterr().err
    assert "prt render: warning: mesh 'sphere_on_plane' is not convex" in err and "ignores visibility" in err


def test_matches_mitsuba_on_a_sphere():
    """Against an independent renderer: Mitsuba 3 path-traces the engine's Phong (modified form, its
    own BRDF code as a Mitsuba BSDF, validate.scenes) on probes of a unit sphere under a band-limited
    environment (4-band overcast sky as Mitsuba's envmap); the SHRM's map radiance agrees within 2%
    relative RMS (Mitsuba's own standard error is reported beside it)."""
    pytest.importorskip("mitsuba")
    from prt_torch.validate.lights import check_expressible
    from prt_torch.validate.scenes import mitsuba_glossy_exit

    L = load_light("overcast", bands=4)
    img = check_expressible(L, "overcast", height=64)
    brdf = Phong(6.0)
    m = S.build_shrm(brdf, L, epsilon=0.001, height=64)
    N = 4
    g = torch.Generator().manual_seed(3)
    n = torch.randn(N, 3, generator=g, dtype=torch.float64)
    n = n / n.norm(dim=-1, keepdim=True)
    a = torch.randn(N, 3, generator=g, dtype=torch.float64)
    a = a - (a * n).sum(-1, keepdim=True) * n
    a = a / a.norm(dim=-1, keepdim=True)
    th = torch.rand(N, generator=g, dtype=torch.float64) * math.radians(60)
    v = torch.cos(th)[:, None] * n + torch.sin(th)[:, None] * a  # views within 60° of the normal
    frames = torch.stack([a, torch.linalg.cross(n, a), n], -2)
    r = mitsuba_glossy_exit(None, n, frames, v, [brdf] * N, img, spp=8192, batches=4)
    mi = r["radiance"]
    err = float((m.radiance(n, v, "map") - mi).norm() / mi.norm())
    se = float(r["radiance_se"].norm() / mi.norm())
    assert err < 0.02, (err, se)


def test_glsl_decoder_matches_cpu(tmp_path, capsys):
    """The SHRM's GLSL decoder (render.shrm) against the CPU path (SHRM.radiance, map lookup) on the
    same mesh and camera: ≥ 50 dB and the same pixel coverage, as every decoder of the engine."""
    from prt_torch.cli import main

    m = tmp_path / "mf.prt"
    assert main(["shrm", "--brdf", "microfacet", "--brdf-param", "sigma=0.3", "--light", "studio", "--size", "32",
                 "-o", str(m)]) == 0
    rc = main(["render", str(m), "--mesh", "convex", "-o", str(tmp_path / "g.exr"), "--width", "64", "--height", "64",
               "--validate"])
    out = capsys.readouterr()
    if rc == 3:
        pytest.skip("no EGL context: " + out.err)
    assert rc == 0, out.err
    line = next(x for x in out.out.splitlines() if x.startswith("GLSL vs CPU"))
    assert "same coverage: yes" in line and float(line.split()[3]) >= 50.0, line


def test_sphere_matches_unshadowed_glossy_prt_within_both_truncations():
    """The SHRM and unshadowed glossy PRT (Sloan 2003 §3.1, exit matrices with the zero-hemisphere
    projection) of one microfacet BRDF under one 5-band light, on a sphere seen from one eye. Each
    truncation is predicted from its own energies: the SHRM's ε_S (eq. 5.18) and the PRT's
    ε_P = 1 - ‖B‖²_F / ∫∫ f*² (the BRDF energy its 5 × 5-band matrix keeps, Parseval, the
    integral by product Gauss quadrature); the two radiances agree within (√ε_S + √ε_P)²."""
    import tempfile
    from pathlib import Path

    import numpy as np
    import trimesh

    from prt_torch import relight
    from prt_torch.brdf import brdf_matrix
    from prt_torch.scene import load_mesh
    from prt_torch.scene.builtins import geodesic_sphere
    from prt_torch.sh import gauss_hemisphere
    from prt_torch.transfer import precompute_glossy

    v, f = geodesic_sphere(4)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "sphere.ply"
        trimesh.Trimesh(np.asarray(v), np.asarray(f), process=False).export(p)
        mesh = load_mesh(p)
    n, brdf = 5, Microfacet(0.4)
    L = load_light("studio", bands=n, size=32)
    g = precompute_glossy(mesh, n, n, brdf=brdf, projection="zero", shadows="never", samples=4096, seed=0, quad_bands=16)
    eye = torch.tensor([4.0, -3.0, 3.0], dtype=torch.float64)
    prt = relight.glossy(g.data.double(), L, relight.local_view(mesh.frames(), mesh.vertices, eye), g.meta.get("out_index"))
    views = eye - mesh.vertices
    views = views / views.norm(dim=-1, keepdim=True)
    facing = (views * mesh.normals).sum(-1) > 0.05
    m = S.build_shrm(brdf, L, epsilon=0.01, height=64)
    ours = m.radiance(mesh.normals, views, "map")
    B = brdf_matrix(brdf, n, n, projection="zero", quad_bands=16)
    dirs, w = gauss_hemisphere(30)
    total = float(torch.einsum("v,vs,s->", w, brdf.cosine_weighted(dirs[None], dirs[:, None]) ** 2, w))
    eps_p = 1 - float((B ** 2).sum()) / total
    eps_s = 1 - m.meta["energy"]
    assert 0 < eps_p < 0.2 and 0 < eps_s <= 0.01
    assert _rel_sq(ours[facing], prt[facing]) <= (math.sqrt(eps_s) + math.sqrt(eps_p)) ** 2


def test_reference_radiance_analytic():
    """shrm.reference_radiance (the benchmarks' brute force): a Lambertian under uniform radiance 1
    reflects kd, and a microfacet's reflected radiance is its directional albedo, the same for every
    normal at the same n·v."""
    dirs, w = gauss_sphere(60)
    n = _unit(20, 9)
    v = _unit(20, 10)
    v = torch.where(((v * n).sum(-1) > 0)[:, None], v, -v)  # views above each surface
    out = S.reference_radiance(Lambertian(0.7), dirs, w[:, None], n, v)
    assert torch.allclose(out, torch.full_like(out, 0.7), atol=1e-3)
    z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    v = torch.tensor([0.6, 0.0, 0.8], dtype=torch.float64)
    R = S.local_frames(n)  # rotations taking +z to each normal: the same configuration everywhere
    a = S.reference_radiance(Microfacet(0.3), dirs, w[:, None], n, R @ v)
    b = S.reference_radiance(Microfacet(0.3), dirs, w[:, None], z[None], v)
    assert torch.allclose(a, b.expand_as(a), rtol=5e-3)  # the product rule is not rotation invariant


def test_a_plane_seen_along_itself_is_dark_whatever_the_rounding(light6, tilted_plane):
    """A tilted plane's vertices (one normal up to float64 rounding) seen by a distant view lying in the plane: n·v
    comes out at ~±1e-16 of both signs; every point gets 0 (n·v ≤ transport.HORIZON_EPS counts as facing away, as in
    the glossy PRT the convex config compares the SHRM with: relight's view weights), not the grazing value at the
    points whose rounding came out positive. 1e-3 rad above the plane they all get one non-zero value."""
    import numpy as np

    mesh, n0, t, b = tilted_plane
    n = mesh.normals
    s = S.build_shrm(Microfacet(0.4), light6, orders=(5, 2), height=8)
    signs = set()
    for d in (t, b, (t + b) / np.linalg.norm(t + b)):
        v = torch.tensor(d)
        signs |= {int(x) for x in torch.sign(n @ v).unique().tolist()}
        for out in (s.radiance(n, v, "coeffs"), s.radiance(n, v, "map"), s.radiance_distant(n, v)):
            assert float(out.abs().max()) == 0.0
        up = torch.tensor(math.cos(1e-3) * d + math.sin(1e-3) * n0)
        r = s.radiance(n, up / up.norm(), "coeffs")
        assert float(r.abs().min()) > 0 and float((r - r[0]).abs().max()) <= 1e-9 * float(r.abs().max())
    assert {-1, 1} <= signs
