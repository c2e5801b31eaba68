"""Diffuse transfer: analytic/MC agreement, shadows, interreflection, determinism, resume, CLI, bad input."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from prt_torch.cli import main as cli_main
from prt_torch.scene import RayCaster, builtin, geodesic_sphere, make_mesh, sphere_on_plane_visibility
from prt_torch.sh import eval_sh, gauss_sphere
from prt_torch.relight import diffuse_transfer as diffuse_radiance
from prt_torch.transfer import ChunkInterrupt, RunOptions, Transfer, precompute_diffuse, unshadowed_transfer
from prt_torch.transfer.diffuse import transfer_at_points
from prt_torch.transfer.sampling import cosine_hemisphere, uniform_sphere

warnings.filterwarnings("ignore", message="Sparse")

WHITE = torch.zeros(1, 25, dtype=torch.float64)
WHITE[0, 0] = 2 * math.sqrt(math.pi)  # constant radiance 1: l_00 = ∫ Y_00 = 4π / (2√π)


def white(bands: int) -> torch.Tensor:
    L = torch.zeros(1, bands * bands, dtype=torch.float64)
    L[0, 0] = 2 * math.sqrt(math.pi)
    return L


# ------------------------------------------------------------------------------ sampling
def test_samplers_are_deterministic_and_distributed():
    d1, w = uniform_sphere(400, seed=3)
    d2, _ = uniform_sphere(400, seed=3)
    assert torch.equal(d1, d2) and not torch.equal(d1, uniform_sphere(400, seed=4)[0])
    assert w.sum().item() == pytest.approx(4 * math.pi)
    assert d1.mean(0).norm() < 0.02  # stratified: nearly zero mean
    c = cosine_hemisphere(10000, seed=1)
    assert (c[:, 2] > 0).all()
    # E[cos θ] under pdf cos/π is 2/3; E[cos² θ] is 1/2 (independent closed forms)
    assert c[:, 2].mean().item() == pytest.approx(2 / 3, abs=2e-3)
    assert (c[:, 2] ** 2).mean().item() == pytest.approx(0.5, abs=2e-3)


# ------------------------------------------------------------------------------ unshadowed
def test_analytic_unshadowed_matches_brute_force_quadrature():
    bands = 6
    g = torch.Generator().manual_seed(0)
    n = torch.randn(7, 3, generator=g, dtype=torch.float64)
    n = n / n.norm(dim=-1, keepdim=True)
    t = unshadowed_transfer(n, bands)
    # brute force: (1/π) ∫ max(n·s,0) y(s) ds by a fine product quadrature (kink -> slow convergence)
    dirs, w = gauss_sphere(96, oversample=2)
    Y = eval_sh(dirs, bands)
    ref = ((n @ dirs.T).clamp_min(0) * w / math.pi) @ Y
    torch.testing.assert_close(t, ref, atol=2e-4, rtol=0)


def test_analytic_unshadowed_equals_monte_carlo_unshadowed():
    # the Monte Carlo estimator with V ≡ 1 (rays towards an occluder far below every normal)
    far = make_mesh(np.array([[-1, -1, -100.0], [1, -1, -100], [0, 1, -100]]), np.array([[0, 1, 2]]))
    rc = RayCaster(far)
    n = torch.tensor([[0, 0, 1.0], [0.6, 0, 0.8], [0, 0.8, 0.6]], dtype=torch.float64)
    p = torch.zeros(3, 3, dtype=torch.float64)
    exact = unshadowed_transfer(n, 5)
    for sampling, N, tol in (("uniform", 16384, 4e-3), ("cosine", 16384, 4e-3)):
        mc = transfer_at_points(rc, p, n, 5, N, seed=2, sampling=sampling)
        torch.testing.assert_close(mc, exact, atol=tol, rtol=0)


# ------------------------------------------------------------------------------ convex object
def test_convex_shadowed_equals_unshadowed_within_mc_error():
    m = builtin("convex")
    N = 1024
    traced = precompute_diffuse(m, 4, N, 0, seed=1, shadows="always")
    auto = precompute_diffuse(m, 4, N, 0, seed=1)
    assert traced.meta["shadows_traced"] and not auto.meta["shadows_traced"]
    assert auto.meta["probe"]["occluded_fraction"] <= 1e-3
    exact = unshadowed_transfer(m.normals, 4)
    torch.testing.assert_close(auto.data.double(), exact, atol=1e-6, rtol=0)
    # the MC error bound: per-coefficient std of the i.i.d. estimator (4/N)·Σ max(n·s,0) y(s),
    # an upper bound for stratified sampling; 3σ
    dirs, _ = uniform_sphere(N, 1)
    terms = 4 * (m.normals @ dirs.T).clamp_min(0)[:, :, None] * eval_sh(dirs, 4)[None]  # [V,N,16]
    sigma = terms.std(dim=1) / math.sqrt(N)
    err = (traced.data.double() - exact).abs()
    assert (err <= 3 * sigma + 1e-6).all(), float((err / (sigma + 1e-12)).max())


def test_constant_white_environment_gives_albedo():
    for albedo in (0.6, (0.9, 0.5, 0.2)):
        m = builtin("convex", albedo=albedo)
        rho = torch.tensor(albedo, dtype=torch.float64).expand(m.num_vertices, 3)
        tr = precompute_diffuse(m, 3, 64)  # auto: analytic (no self-occlusion)
        torch.testing.assert_close(diffuse_radiance(tr, white(3)), rho, atol=1e-6, rtol=0)
        # traced with interreflection too: nothing is hit, so still ρ (to MC accuracy)
        tr2 = precompute_diffuse(m, 3, 1024, bounces=2, shadows="always", fold_albedo=True)
        assert tr2.data.shape == (m.num_vertices, 3, 9)
        torch.testing.assert_close(diffuse_radiance(tr2, white(3)), rho, atol=0.03, rtol=0)
        assert tr2.meta["bounces_used"] <= 1


# ------------------------------------------------------------------------------ contact shadow
def test_sphere_on_plane_contact_darkening_matches_visible_solid_angle():
    v, f = geodesic_sphere(24)
    sphere = make_mesh(v + np.array([0, 0, 1.0]), f)
    rc = RayCaster(sphere)
    d = torch.tensor([0.4, 1.0, 2.0, 6.0], dtype=torch.float64)
    pts = torch.stack([d, torch.zeros(4, dtype=torch.float64), torch.zeros(4, dtype=torch.float64)], 1)
    nz = torch.tensor([0, 0, 1.0], dtype=torch.float64).expand(4, 3)
    for sampling in ("uniform", "cosine"):
        t = transfer_at_points(rc, pts, nz, 3, 8192, seed=5, sampling=sampling)
        radiance = (t @ white(3).T)[:, 0]  # ρ = 1
        ref = torch.tensor([sphere_on_plane_visibility(float(x)) for x in d], dtype=torch.float64)
        torch.testing.assert_close(radiance, ref, atol=3e-3, rtol=0)
    assert radiance[0] < radiance[1] < radiance[2] < radiance[3]  # darker towards the contact
    # the built-in scene shows the same: plane vertices near the contact are darker than far ones
    m = builtin("sphere_on_plane")
    tr = precompute_diffuse(m, 3, 256, seed=0)
    r = diffuse_radiance(tr, white(3))[:, 0]
    on_plane = (m.vertices[:, 2].abs() < 1e-9)
    rad = m.vertices[:, :2].norm(dim=1)
    near, far = on_plane & (rad > 0.2) & (rad < 0.6), on_plane & (rad > 2.5)
    assert r[near].mean() < 0.8 * 0.6 and r[far].mean() > 0.8 * 0.93


# ------------------------------------------------------------------------------ interreflection
def test_interreflection_energy_grows_converges_and_bleeds_colour():
    m = builtin("cornell_box")
    rho_max = float(m.albedo.max())
    runs = [precompute_diffuse(m, 3, 128, bounces=b, seed=4, bounce_tol=0.0, fold_albedo=True) for b in (0, 1, 2, 3)]
    E = torch.stack([diffuse_radiance(r, white(3)) for r in runs])  # [B+1, V, 3]
    inc = E[1:] - E[:-1]
    assert (inc >= -1e-9).all()  # every bounce adds light
    assert (inc.mean(dim=(1, 2))[1:] < inc.mean(dim=(1, 2))[:-1]).all()  # increments shrink
    # increments bounded by the geometric series: max inc_b <= ρ_max · max inc_{b-1}
    mx = inc.amax(dim=(1, 2))
    assert (mx[1:] <= rho_max * mx[:-1] * 1.05).all()
    # every vertex: L ≤ Σ_{b=0}^{B} ρ_max^{b+1} (MC slack 5%)
    bound = sum(rho_max ** (b + 1) for b in range(4))
    assert float(E[-1].max()) <= bound * 1.05
    # colour bleeding: the white floor next to the red wall turns red, next to the green wall green
    floor = (m.vertices[:, 2].abs() < 1e-9) & (m.normals[:, 2] > 0.99)
    near_red = floor & (m.vertices[:, 0] < -0.85) & (m.vertices[:, 1] > 0.6)
    near_green = floor & (m.vertices[:, 0] > 0.85) & (m.vertices[:, 1] > 0.6)
    direct, full = E[0], E[-1]
    torch.testing.assert_close(direct[floor, 0], direct[floor, 1], atol=1e-9, rtol=0)  # no bleeding without bounces
    assert (full[near_red, 0] / full[near_red, 1]).mean() > 1.1
    assert (full[near_green, 1] / full[near_green, 0]).mean() > 1.1
    assert runs[-1].data.shape == (m.num_vertices, 3, 9) and runs[-1].meta["albedo_folded"]
    assert runs[0].meta["bounces_used"] == 0 and runs[-1].meta["bounces_used"] == 3


def test_bounce_tolerance_stops_early_and_albedo_rules():
    m = builtin("bumpy_sphere")
    tr = precompute_diffuse(m, 3, 64, bounces=10, bounce_tol=0.02, seed=0)
    fr = tr.meta["bounce_energy_fraction"]
    assert tr.meta["bounces_used"] < 10 and fr[-1] < 0.02 and all(x >= 0.02 for x in fr[:-1])
    assert tr.data.shape == (m.num_vertices, 9) and not tr.meta["albedo_folded"]  # grey: albedo kept separate
    with pytest.raises(ValueError, match="fold_albedo"):
        precompute_diffuse(builtin("cornell_box"), 3, 16, bounces=1, fold_albedo=False)


# ------------------------------------------------------------------------------ determinism and resume
def test_same_seed_same_result_and_resume_equals_uninterrupted(tmp_path):
    m = builtin("occluder_over_plane")
    kw = dict(bands=3, samples=64, bounces=2)
    run = RunOptions(chunk_size=400)
    kw["run"] = run
    a = precompute_diffuse(m, seed=7, **kw)
    b = precompute_diffuse(m, seed=7, **kw)
    c = precompute_diffuse(m, seed=8, **kw)
    assert torch.equal(a.data, b.data) and not torch.equal(a.data, c.data)
    state = tmp_path / "run.state"
    seen = []

    def stop_after_two(i, n):
        seen.append(i)
        if i == 1:
            raise ChunkInterrupt("simulated interruption")

    with pytest.raises(ChunkInterrupt):
        precompute_diffuse(m, seed=7, **{**kw, "run": RunOptions(chunk_size=400, state_dir=state, callback=stop_after_two)})
    assert sorted(p.name for p in state.glob("chunk_*.prt")) == ["chunk_000000.prt", "chunk_000001.prt"]
    with pytest.raises(FileExistsError, match="resume"):
        precompute_diffuse(m, seed=7, **{**kw, "run": RunOptions(chunk_size=400, state_dir=state)})
    with pytest.raises(ValueError, match="other parameters"):
        precompute_diffuse(m, seed=9, **{**kw, "run": RunOptions(chunk_size=400, state_dir=state, resume=True)})
    computed = []
    r = precompute_diffuse(m, seed=7, **{**kw, "run": RunOptions(chunk_size=400, state_dir=state, resume=True,
                                                                 callback=lambda i, n: computed.append(i))})
    assert torch.equal(r.data, a.data)
    assert not state.exists()  # cleaned up after success
    assert computed == list(range(len(computed))) and len(computed) == math.ceil(m.num_vertices / 400)


# ------------------------------------------------------------------------------ file format
def test_transfer_save_load_roundtrip_and_bad_files(tmp_path):
    m = builtin("cornell_box")
    tr = precompute_diffuse(m, 3, 32, bounces=1)
    p = tmp_path / "t.prt"
    tr.save(p)
    back = Transfer.load(p)
    assert back.kind == "diffuse" and torch.equal(back.data, tr.data)
    assert back.mesh.content_hash() == m.content_hash() and torch.equal(back.mesh.frames(), m.frames())
    assert back.meta["bands"] == 3 and back.meta["bounces_used"] == 1
    assert back.signal().shape == (m.num_vertices, 27)
    with pytest.raises(FileExistsError):
        tr.save(p)
    with pytest.raises(FileNotFoundError):
        Transfer.load(tmp_path / "missing.prt")
    junk = tmp_path / "junk.prt"
    junk.write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match="junk.prt"):
        Transfer.load(junk)


def test_parameter_validation():
    m = builtin("convex")
    for kw, match in ((dict(bands=0), "bands"), (dict(bands=33), "bands"), (dict(samples=0), "samples"),
                      (dict(bounces=-1), "bounces"), (dict(shadows="maybe"), "shadows"),
                      (dict(sampling="sobol"), "sampling"), (dict(bounce_tol=1.5), "bounce_tol")):
        with pytest.raises(ValueError, match=match):
            precompute_diffuse(m, **kw)
    with pytest.raises(TypeError):
        precompute_diffuse("convex")


# ------------------------------------------------------------------------------ CLI
def test_cli_precompute_info_overwrite_and_errors(tmp_path, capsys):
    out = tmp_path / "o.prt"
    args = ["precompute", "cornell_box", "--bands", "3", "--samples", "32", "--bounces", "1", "-o", str(out),
            "--no-progress", "--workers", "1"]
    assert cli_main(args) == 0
    meta_before = out.stat().st_mtime_ns
    assert cli_main(["info", str(out)]) == 0
    text = capsys.readouterr().out
    assert "transfer/diffuse" in text and "(2156, 3, 9)" in text and "bounces_used" in text
    # an existing output is refused and left untouched; --overwrite replaces it
    assert cli_main(args) == 2
    assert "exists" in capsys.readouterr().err and out.stat().st_mtime_ns == meta_before
    assert cli_main(args + ["--overwrite", "--seed", "3"]) == 0
    # bad input: clear errors, nothing half-written
    bad = tmp_path / "bad.prt"
    for extra, match in ((["--bands", "40"], "bands"), (["--samples", "0"], "samples")):
        assert cli_main(["precompute", "convex", "-o", str(bad), "--no-progress", *extra]) == 2
        assert match in capsys.readouterr().err
    assert cli_main(["precompute", str(tmp_path / "missing.obj"), "-o", str(bad)]) == 2
    corrupt = tmp_path / "c.obj"
    corrupt.write_text("v 0 0 0\nv 1 0 0\nv nan 1 0\nf 1 2 3\n")
    assert cli_main(["precompute", str(corrupt), "-o", str(bad), "--no-progress"]) == 2
    assert "NaN" in capsys.readouterr().err
    assert cli_main(["info", str(tmp_path / "nothing.prt")]) == 2
    leftovers = [p.name for p in tmp_path.iterdir() if p.name not in ("o.prt", "c.obj")]
    assert leftovers == [], leftovers


def test_cli_resume_after_interruption(tmp_path, monkeypatch, capsys):
    import prt_torch.transfer.base as base

    out, ref = tmp_path / "r.prt", tmp_path / "ref.prt"
    common = ["precompute", "occluder_over_plane", "--bands", "3", "--samples", "32", "--chunk", "500",
              "--no-progress", "--workers", "1"]
    args = common + ["-o", str(out)]
    assert cli_main(common + ["-o", str(ref)]) == 0
    real = base.run_chunks

    def interrupted(*a, **kw):
        kw["callback"] = lambda i, n: (_ for _ in ()).throw(KeyboardInterrupt()) if i == 2 else None
        return real(*a, **kw)

    monkeypatch.setattr(base, "run_chunks", interrupted)
    assert cli_main(args) == 130  # Ctrl-C: quiet, with what was kept and how to continue
    err = capsys.readouterr().err
    assert "interrupted" in err and "r.prt.state" in err and "--resume" in err and "Traceback" not in err
    monkeypatch.setattr(base, "run_chunks", real)
    assert not out.exists() and (tmp_path / "r.prt.state").is_dir()
    assert cli_main(args) == 2  # refuses to silently restart
    assert cli_main(args + ["--resume"]) == 0
    assert torch.equal(Transfer.load(out).data, Transfer.load(ref).data)
    assert not (tmp_path / "r.prt.state").exists()
