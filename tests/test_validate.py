"""prt validate: engine against Mitsuba 3 path tracing, and Mitsuba's own conventions pinned.

The Mitsuba-side tests pin its orientation and units (envmap axes, a constant environment, a
single lit quad against its analytic value) so that a failing engine comparison points at one
side. The engine comparisons use small vertex and sample counts (seconds each); their
tolerance is derived from the measured noise of both sides (z-scores), not from a fixed %.
"""
from __future__ import annotations

import math
import sys

import numpy as np
import pytest
import torch

from prt_torch.brdf import Lambertian, Phong, Ward
from prt_torch.cli import main as cli_main
from prt_torch.scene import builtin, make_mesh
from prt_torch.sh import eval_sh
from prt_torch.transfer import precompute_diffuse, precompute_glossy
from prt_torch import validate as V

mi = pytest.importorskip("mitsuba", reason="pip install 'prt-torch[validate]'")

Z_MAX = 4.0  # |engine/mitsuba - 1| within 4 standard errors (both sides' noise in quadrature)


def _two_band(c0=1.0, x=0.0, y=0.0, z=0.0) -> torch.Tensor:
    """SH [1, 4] of the radiance c0 + x s_x + y s_y + z s_z (exactly 2 bands)."""
    k0, k1 = 0.5 / math.sqrt(math.pi), math.sqrt(3 / (4 * math.pi))  # y_00 = k0; y_1m = k1 (s_y, s_z, s_x)
    return torch.tensor([[c0 / k0, y / k1, z / k1, x / k1]], dtype=torch.float64)


def test_two_band_helper_is_the_function():
    L = _two_band(1.0, 0.3, -0.2, 0.5)
    d = torch.nn.functional.normalize(torch.randn(50, 3, dtype=torch.float64), dim=-1)
    got = (eval_sh(d, 2) @ L.T)[:, 0]
    torch.testing.assert_close(got, 1.0 + 0.3 * d[:, 0] - 0.2 * d[:, 1] + 0.5 * d[:, 2])


# ------------------------------------------------------------------------------ Mitsuba's conventions
def test_envmap_axes_match_the_world_frame():
    """Mitsuba's envmap, fed light_image, returns the light's radiance in every world direction
    (+z up, no hidden rotation): the axis convention of the validator."""
    V.require_mitsuba()
    L = _two_band(1.0, 0.5, 0.3, 0.2)
    em = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(V.light_image(L, 64))})
    dirs = torch.tensor([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0.6, 0, 0.8], [0, -0.6, 0.8], [0.48, 0.6, -0.64]],
                        dtype=torch.float64)
    for d in dirs:
        si = mi.SurfaceInteraction3f()
        si.wi = -mi.Vector3f(*d.tolist())
        got = float(np.asarray(em.eval(si))[0])
        want = 1.0 + 0.5 * float(d[0]) + 0.3 * float(d[1]) + 0.2 * float(d[2])
        assert abs(got - want) < 1e-2 * want, (d.tolist(), got, want)  # bilinear lookups; a wrong axis errs by 0.2+


def test_constant_environment_gives_pi_irradiance_and_albedo_exit():
    """Units: radiance 1 everywhere -> irradiance π at any probe, exit radiance = albedo."""
    L = torch.tensor([[2 * math.sqrt(math.pi)]], dtype=torch.float64)
    pts = torch.tensor([[0.0, 0, 0], [1, 2, 3]], dtype=torch.float64)
    nrm = torch.tensor([[0.0, 0, 1], [0.6, 0, -0.8]], dtype=torch.float64)
    r = V.mitsuba_exit_radiance(None, pts, nrm, V.light_image(L, 16), [1], spp=256, batches=4,
                                albedo=torch.tensor([[0.5, 0.5, 0.5], [0.8, 0.2, 0.1]]))
    torch.testing.assert_close(r["irradiance"][0], torch.full((2, 3), math.pi, dtype=torch.float64), atol=1e-3, rtol=0)
    torch.testing.assert_close(r["radiance"][0], torch.tensor([[0.5, 0.5, 0.5], [0.8, 0.2, 0.1]], dtype=torch.float64),
                               atol=1e-3, rtol=0)


def _rect_ff(X: float, Y: float) -> float:
    """Form factor from a differential area to a parallel X×Y rectangle (unit height) with one
    corner straight above/below it."""
    a, b = math.sqrt(1 + X * X), math.sqrt(1 + Y * Y)
    return (X / a * math.atan(Y / a) + Y / b * math.atan(X / b)) / (2 * math.pi)


def test_single_lit_quad_against_its_analytic_value():
    """A quad facing +z under L = 1 + s_z (albedo ρ): a probe on it facing up gets E = π + 2π/3
    (direct); a probe at height h facing down sees the quad reflect L_q = ρ (1 + 2/3), so its
    one-bounce part (max_depth 2 minus 1) is L_q · π · F with F the analytic form factor."""
    a, h, rho = 1.0, 0.5, 0.6
    quad = make_mesh(np.array([[-a, -a, 0], [a, -a, 0], [a, a, 0], [-a, a, 0]], float), np.array([[0, 1, 2], [0, 2, 3]]),
                     rho, name="quad")
    L = _two_band(1.0, 0.0, 0.0, 1.0)
    pts = torch.tensor([[0.1, 0.2, 0.0], [0.0, 0.0, h]], dtype=torch.float64)
    nrm = torch.tensor([[0.0, 0, 1], [0.0, 0, -1]], dtype=torch.float64)
    r = V.mitsuba_exit_radiance(quad, pts, nrm, V.light_image(L, 64), [1, 2], spp=1 << 15, batches=8, eps=1e-5, seed=1)
    E_up = r["irradiance"][0, 0, 0]
    assert abs(float(E_up) - (math.pi + 2 * math.pi / 3)) < 4 * float(r["irradiance_se"][0, 0, 0]) + 2e-3
    bounce = float(r["irradiance"][1, 1, 0] - r["irradiance"][0, 1, 0])
    want = rho * (5 / 3) * math.pi * 4 * _rect_ff(a / h, a / h)
    se = float(r["diff_se"][1, 1, 0])
    assert abs(bounce - want) < 4 * se + 2e-3 * want, (bounce, want, se)


def _quad_over_probe(a: float, h: float, base: float = 0.0, frame: str = "as_is", eps: float = 1e-9) -> float:
    """E/π at an irradiance probe at (0, 0, base) facing +z under a constant environment, with a
    quad of half-size ``a`` facing down at height ``base + h`` (Mitsuba, ``frame``)."""
    v = np.array([[-a, -a, 0], [a, -a, 0], [a, a, 0], [-a, a, 0]], float) + [0, 0, base + h]
    quad = make_mesh(v, np.array([[0, 2, 1], [0, 3, 2]]), 0.5, name="quad")
    L = torch.tensor([[2 * math.sqrt(math.pi)]], dtype=torch.float64)
    r = V.mitsuba_exit_radiance(quad, torch.tensor([[0.0, 0, base]], dtype=torch.float64), torch.tensor([[0.0, 0, 1]], dtype=torch.float64),
                                V.light_image(L, 16), [1], spp=2048, batches=4, eps=eps, frame=frame)
    return float(r["irradiance"][0, 0, 0]) / math.pi


def test_mitsuba_probe_blind_distance():
    """Pins MITSUBA_PROBE_TMIN (issue 37's cause): Mitsuba does not see a surface closer than
    ~1e-4 scene units to an irradiancemeter disk, wherever the disk is. Seen, a quad of half-size
    1 at height h leaves the probe E/π = 1 − 4 F(1/h, 1/h) ≈ 0 (F the corner form factor); with a
    blind distance τ the rays shorter than τ miss it: E/π = 1 − (h/τ)² for h < τ."""
    tau = V.scenes.MITSUBA_PROBE_TMIN
    for base in (0.0, 10.0):
        assert 0.85 < _quad_over_probe(1.0, 0.3 * tau, base) < 0.96  # 1 − 0.09 = 0.91: not seen
        assert _quad_over_probe(1.0, 10 * tau, base) < 0.01  # 1 − 4F ≈ 2e-7: seen


def test_normalized_frame_sees_what_the_engine_sees():
    """A small mesh (a quad of half-size 0.01, as a scan in its own units): the quad 3e-5 above
    the probe is ~10 engine offsets (1e-4 of the diagonal) away and covers all but 1 − 4F ≈ 1e-5
    of its hemisphere (analytic, E/π ≈ 0). Given the scene in the mesh's units Mitsuba sees
    through it (E/π ≈ 0.91); normalised (the default) it sees it."""
    a, h = 0.01, 3e-5
    want = 1 - 4 * _rect_ff(a / h, a / h)
    eps = 1e-4 * a * 2 * math.sqrt(2)
    assert abs(_quad_over_probe(a, h, frame="normalized", eps=eps) - want) < 0.01
    assert _quad_over_probe(a, h, frame="as_is", eps=eps) > 0.8  # the validator before: blind to it
    c, s = V.mitsuba_frame(make_mesh(np.array([[0, 0, 0], [2, 0, 0], [0, 2, 2.0]]), np.array([[0, 1, 2]])))
    np.testing.assert_allclose(c, [1, 1, 1])
    assert s == pytest.approx(V.MITSUBA_DIAGONAL / math.sqrt(12))
    with pytest.raises(ValueError, match="mitsuba_frame.*accepted"):
        V.mitsuba_frame(None, "metres")


# ------------------------------------------------------------------------------ engine against Mitsuba
LIGHT = "hemisphere:upper=1;lower=0.2"


@pytest.mark.parametrize("scene", ["cornell_box", "occluder_over_plane", "bumpy_sphere"])
def test_engine_matches_mitsuba_direct_and_interreflected(scene):
    m = builtin(scene)
    rep0 = V.validate(precompute_diffuse(m, 2, 512, bounces=0, seed=2, shadows="always"), LIGHT, vertices=24, spp=2048, seed=5)
    assert rep0["bounces"] == 0 and "inter" not in rep0
    assert abs(rep0["direct"]["z"]) < Z_MAX, V.format_report(rep0)
    tr = precompute_diffuse(m, 2, 512, bounces=2, seed=2, bounce_tol=0.0, shadows="always")
    rep = V.validate(tr, LIGHT, vertices=24, spp=2048, seed=5)
    assert rep["bounces"] == 2 and rep["bounce_points"] == "hits"
    assert abs(rep["direct"]["z"]) < Z_MAX and abs(rep["inter"]["z"]) < Z_MAX, V.format_report(rep)
    assert rep["inter"]["mitsuba"] > 0 and rep["inter"]["ratio_se"] < 0.25  # the check has teeth
    # B = 0 results unchanged by bounces: the direct part is the same rays
    torch.testing.assert_close(torch.tensor(rep["per_vertex"]["engine_direct"]), torch.tensor(rep0["per_vertex"]["engine_direct"]))


def test_source_image_axes_and_sh_truncation(tmp_path):
    """An environment file reaches Mitsuba with the world axes of prt_torch's own projection: for
    a band-limited image the 'image' and 'sh' lights agree, so the SH truncation is ~0."""
    from prt_torch.lighting import Environment

    env = Environment.from_function(lambda d: (1.0 + 0.5 * d[:, :1] + 0.3 * d[:, 1:2] + 0.2 * d[:, 2:3]).expand(-1, 3),
                                    "latlong", 64, supersample=2)
    path = tmp_path / "env.pfm"
    env.save(path)
    img_src = V._source_image(str(path), 32)
    img_sh = V.light_image(__import__("prt_torch").lighting.load_light(str(path), 2), img_src.shape[0])  # at least 2x the file's
    assert np.abs(img_src - img_sh).max() < 0.03
    m = builtin("occluder_over_plane")
    rep = V.validate(precompute_diffuse(m, 2, 256, seed=1, shadows="always"), str(path), vertices=8, spp=512,
                     light_source="image")
    assert rep["light_source"] == "image" and abs(rep["sh_truncation"]["ratio"] - 1) < 0.02
    assert abs(rep["direct"]["z"]) < Z_MAX, V.format_report(rep)


# ------------------------------------------------------------------------------ refusals and CLI
def test_refusals_before_any_work(monkeypatch):
    m = builtin("occluder_over_plane")
    tr = precompute_diffuse(m, 3, 32, seed=0)
    with pytest.raises(ValueError, match="directional.*negative"):
        V.validate(tr, "directional:direction=0,0,1", vertices=4)
    g = precompute_glossy(m, 2, 2, brdf=Phong(s=4), samples=16, vertices=torch.arange(4))
    with pytest.raises(ValueError, match="vertex subset.*mesh="):
        V.validate(g, "constant", vertices=4)
    g.meta["brdf"] = {"model": "cook_torrance", "m": 0.2}
    with pytest.raises(ValueError, match="'cook_torrance'.*accepted"):
        V.validate(g, "constant", vertices=4)
    g.meta.update(brdf=Phong(s=4).meta(), quantity="transferred")
    with pytest.raises(ValueError, match="'transferred'"):
        V.validate(g, "constant", vertices=4)
    with pytest.raises(ValueError, match="light_source='image'"):
        V.validate(tr, "constant", vertices=4, light_source="image")
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # not installed
    with pytest.raises(V.ValidatorUnavailable, match=r"pip install 'prt-torch\[validate\]'"):
        V.validate(tr, "constant", vertices=4)


def test_cli_validate(tmp_path, capsys, monkeypatch):
    m = builtin("occluder_over_plane")
    out = tmp_path / "t.prt"
    precompute_diffuse(m, 2, 128, bounces=1, seed=0, shadows="always").save(out)
    js = tmp_path / "r.json"
    assert cli_main(["validate", str(out), "--light", LIGHT, "--vertices", "6", "--spp", "256", "--json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "direct" in text and "interreflected" in text and "engine/mitsuba" in text and js.exists()
    assert cli_main(["validate", str(out), "--light", "directional:direction=0,0,1"]) == 2
    assert "negative" in capsys.readouterr().err
    monkeypatch.setitem(sys.modules, "mitsuba", None)
    assert cli_main(["validate", str(out), "--light", LIGHT]) == 3
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "pip install" in err[0]


# ------------------------------------------------------------------------------ the estimator the validator re-runs
def test_vertex_transfer_reproduces_the_precompute_rows():
    """vertex_transfer (used for the engine's noise) is the precompute's own estimator: at chosen
    vertices it gives the stored rows (same rays, keys, offsets), for direct and bounces."""
    from prt_torch.transfer.diffuse import vertex_transfer

    m = builtin("cornell_box")
    tr = precompute_diffuse(m, 2, 128, bounces=2, seed=4, bounce_tol=0.0, fold_albedo=True)
    idx = torch.tensor([3, 400, 1234, 2000])
    T0, TB = vertex_transfer(m, idx, 2, 128, 4, 2)
    rows = m.albedo.double()[idx][:, :, None] * (T0[:, None, :] + TB.sum(1))
    torch.testing.assert_close(rows.float(), tr.data[idx], rtol=1e-5, atol=1e-6)
    b0 = precompute_diffuse(m, 2, 128, bounces=0, seed=4)
    torch.testing.assert_close(T0.float(), b0.data[idx])


# ------------------------------------------------------------------------------ glossy: the engine's BRDF as a Mitsuba BSDF
def _bsdf_exit(brdf, normal, view, L, spp=1 << 13):
    """Mitsuba's exit radiance of one probe (no mesh) with the engine BRDF, frame built on ``normal``."""
    from prt_torch.scene import tangent_frames

    n = np.asarray(normal, float)[None] / np.linalg.norm(normal)
    t, b = tangent_frames(n)
    F = torch.from_numpy(np.stack([t, b, n], 1))
    r = V.mitsuba_glossy_exit(None, torch.zeros(1, 3, dtype=torch.float64), F, torch.tensor([view], dtype=torch.float64),
                              [brdf], V.light_image(L, 64), spp=spp, batches=8, seed=3)
    return float(r["radiance"][0, 0]), float(r["radiance_se"][0, 0])


def test_bsdf_lambertian_under_constant_light_is_its_albedo():
    """Constant radiance 1: exit radiance = kd from any view (eval = f·cos, sample pdf = cos/π)."""
    L = torch.tensor([[2 * math.sqrt(math.pi)]], dtype=torch.float64)
    got, se = _bsdf_exit(Lambertian(0.8), [0.3, -0.5, 0.8], [0.7, 0.1, 0.7], L, spp=2048)
    assert abs(got - 0.8) < 4 * se + 2e-3, (got, se)


def test_bsdf_phong_against_its_analytic_value():
    """Modified Phong (ks = 1, s = 8), view along a tilted normal n, light 1 + n·d:
    L_out = ∫ (s+2)/2π cos^s θ (1 + cos θ) cos θ dω = 1 + (s+2)/(s+3) (r = n at normal view).
    A wrong cosine factor, pdf or frame (light along n, not z) moves it by 10 % or more."""
    s, n = 8.0, [0.6, 0.0, 0.8]
    want = 1 + (s + 2) / (s + 3)
    got, se = _bsdf_exit(Phong(s=s), n, n, _two_band(1.0, 0.6, 0.0, 0.8))
    assert se < 0.02 * want and abs(got - want) < 4 * se + 5e-3 * want, (got, want, se)


def _glossy_tolerance(r: dict, trunc: float) -> float:
    """|engine/mitsuba - 1| allowed: Z_MAX × the ratio's 1σ noise (Mitsuba's batch spread and the
    engine's replica-seed spread, in quadrature) plus the engine's SH truncation bias measured at
    the same vertices (engine's rays, projected minus unprojected BRDF on a dense direction set)."""
    return Z_MAX * r["ratio_se"] + abs(trunc)


# 1 + 0.6 x + 0.3 y + 0.2 z as a 5-band light: varies in azimuth, so anisotropic frames matter
GLOSSY_LIGHT = torch.nn.functional.pad(_two_band(1.0, 0.6, 0.3, 0.2), (0, 21))


@pytest.mark.parametrize("scene,brdf", [("convex", Phong(s=6)), ("bumpy_sphere", Phong(s=8)),
                                        ("occluder_over_plane", Ward(0.15, 0.5, rs=0.8, rd=0.1))])
def test_engine_matches_mitsuba_glossy_direct(scene, brdf):
    """Glossy direct exit radiance (5 -> 5 bands, least squares) at 8 vertices toward one view
    each: the stored SH transfer within noise + truncation, the engine's rays with the
    unprojected BRDF within noise (visibility, frames — anisotropic Ward —, BRDF, light)."""
    m = builtin(scene)
    idx = V.sample_vertices(m, 8, 0)
    g = precompute_glossy(m, 5, 5, brdf=brdf, samples=1024, vertices=idx, seed=1)
    rep = V.validate(g, GLOSSY_LIGHT, mesh=m, vertices=8, spp=2048, seed=3)
    assert rep["kind"] == "glossy" and rep["recomputed_rel"] < 1e-5  # the engine's rows read back exactly
    d, u = rep["direct"], rep["direct_unprojected"]
    assert abs(d["ratio"] - 1) < _glossy_tolerance(d, rep["sh_truncation"]), V.format_report(rep)
    assert abs(u["z"]) < Z_MAX, V.format_report(rep)
    assert d["ratio_se"] < 0.05  # the check has teeth


def test_cli_validate_glossy(tmp_path, capsys):
    m = builtin("convex")
    out = tmp_path / "g.prt"
    precompute_glossy(m, 4, 4, brdf=Phong(s=4), samples=256, vertices=V.sample_vertices(m, 3, 0), seed=0).save(out)
    assert cli_main(["validate", str(out), "--light", "sky_gradient", "--mesh", "convex", "--vertices", "3", "--spp", "256"]) == 0
    text = capsys.readouterr().out
    assert "glossy phong" in text and "BRDF unprojected" in text and "SH truncation" in text and "interreflected" not in text
    assert cli_main(["validate", str(out), "--light", "sky_gradient"]) == 2
    assert "pass --mesh the full mesh" in capsys.readouterr().err  # the option typed, not the library's mesh=


def test_engine_matches_mitsuba_glossy_one_bounce():
    """Glossy with one diffuse bounce (cornell_box: strong interreflection): Mitsuba max_depth 3
    minus 2 (mesh grey at the albedo's luminance, as the engine's one matrix per vertex) against
    the stored total minus the recomputed direct part; both sides' noise from seeds."""
    m = builtin("cornell_box")
    idx = V.sample_vertices(m, 8, 0)
    g = precompute_glossy(m, 5, 5, brdf=Phong(s=6, ks=0.5, kd=0.5), samples=1024, vertices=idx, seed=1, bounces=1)
    rep = V.validate(g, "sky_gradient", mesh=m, vertices=8, spp=2048, seed=3)
    assert rep["bounces"] == 1 and rep["recomputed_rel"] < 1e-5  # the driver rerun reproduces the stored rows
    i, t = rep["inter"], rep["total"]
    assert i["mitsuba"] > 0.2 * t["mitsuba"] and i["ratio_se"] < 0.15, V.format_report(rep)  # the check has teeth
    assert abs(i["z"]) < Z_MAX and abs(rep["direct_unprojected"]["z"]) < Z_MAX, V.format_report(rep)
    assert abs(t["ratio"] - 1) < _glossy_tolerance(t, rep["sh_truncation"]), V.format_report(rep)


# ------------------------------------------------------------------------------ issue 37: a scan-like mesh
SCAN_LIGHT = "hemisphere:upper=1;lower=0.2;up=0.36,0.48,0.8"  # at 3 bands exactly 0.6 + 0.6 ω·u, u off-axis


def test_scan_like_mesh_interreflection_through_prt_validate(tmp_path, capsys):
    """Issue 37's test. A generated scan-like mesh (scene.scan_like: vertex-clustering
    decimation, holes in the base, non-manifold fins, slivers, scanner noise) at a scan's size in
    its own units (0.26 across), written as a PLY, precomputed and validated with the CLI (the
    issue's protocol at small sizes): the interreflected engine/Mitsuba ratio within 4σ of 1 with
    σ below 2.5% (the issue's 2% is read at 200 vertices and 32768 spp in
    reports/benchmarks/scan_validate.md; here CI-sized); the report counts the
    mesh's hard vertex classes. At the mesh's non-manifold vertices, Mitsuba given the mesh in its
    own units (the validator before the fix) reads the interreflection ~1.7× lower (12σ+)."""
    from prt_torch.scene import load_mesh, mesh_features, scan_like, vertex_classes

    m = scan_like(2000)
    m = make_mesh(m.vertices.numpy() * 0.08, m.faces.numpy(), 0.8, merge_duplicates=False)
    ply = tmp_path / "scan.ply"
    m.to_trimesh().export(ply)
    out, js = tmp_path / "scan.prt", tmp_path / "r.json"
    assert cli_main(["precompute", str(ply), "--kind", "diffuse", "--bands", "3", "--samples", "1024", "--bounces", "2",
                     "--albedo", "0.8", "--shadows", "always", "-o", str(out)]) == 0
    assert cli_main(["validate", str(out), "--light", SCAN_LIGHT, "--vertices", "96", "--spp", "8192", "--json", str(js)]) == 0
    text = capsys.readouterr().out
    assert "non-manifold" in text and "boundary" in text and "sharp" in text
    import json

    rep = json.loads(js.read_text())
    r = rep["inter"]
    assert r["ratio_se"] < 0.025, V.format_report(rep)
    assert abs(r["ratio"] - 1) < 4 * r["ratio_se"], V.format_report(rep)
    assert abs(rep["direct"]["z"]) < Z_MAX, V.format_report(rep)
    loaded = load_mesh(ply, albedo=0.8)
    feats = mesh_features(loaded)
    for k in ("boundary_edges", "nonmanifold_edges", "boundary_vertices", "nonmanifold_vertices", "sharp_vertices"):
        assert rep["mesh_features"][k] == feats[k] > 0
    assert sum(rep["classes"][k]["sampled"] for k in ("regular",)) < rep["vertices"]  # hard vertices were compared
    # teeth: at the non-manifold vertices, Mitsuba in the mesh's own units sees through the fins and folds
    hard = torch.from_numpy(np.nonzero(vertex_classes(loaded)["nonmanifold"])[0])
    tr = __import__("prt_torch").transfer.Transfer.load(out)
    now = V.validate(tr, SCAN_LIGHT, idx=hard, spp=2048, seed=3)["inter"]
    before = V.validate(tr, SCAN_LIGHT, idx=hard, spp=2048, seed=3, mitsuba_frame="as_is")["inter"]
    assert before["z"] > 3 * Z_MAX and before["ratio"] - now["ratio"] > Z_MAX * math.hypot(before["ratio_se"], now["ratio_se"]), (now, before)
    # NOT fixed: the class still reads high — 1.17 ± 0.025 here, 1.09 ± 0.02 under another light, mostly from a
    # single fin vertex (engine ~40x Mitsuba's there; docs/validate.md, Open). A guard against it growing, not a pass mark.
    assert now["ratio"] < 1.25, now

