"""Glossy / exit / MRT transfer (Sloan 2003 §3.1, Lehtinen & Kautz 2003 eq. 9) against brute-force
Monte Carlo shading with visibility, rotation invariance, the diffuse transfer of
prt_torch.transfer.diffuse, and bad input."""
import dataclasses
import math

import pytest
import torch

from prt_torch import brdf as B
from prt_torch import relight, sh
from prt_torch.scene import RayCaster, builtin
from prt_torch.transfer import ChunkInterrupt, RunOptions, precompute_diffuse
from prt_torch.transfer.glossy import precompute_glossy
from prt_torch.transfer.mrt import precompute_mrt
from prt_torch.transfer.transport import HORIZON_EPS, cube_directions, precompute_transport, TransportTable


class PolyBRDF(B.BRDF):
    """A test reflectance polynomial in both directions: f_r = 0.3 + 0.5 (r·wi)² + 0.3 wo_x wi_y.
    f* = f_r s_z is degree 3 in the light (band-limited to 4 bands on H) and degree 2 in the
    view (3 bands), so every SH truncation error below is known exactly."""

    name = "poly_test"
    param_names = ("k",)

    def __init__(self):
        self.k = torch.tensor(1.0, dtype=torch.float64)

    def _eval(self, wi, wo, p):
        c = (B.reflect(wo) * wi).sum(-1)
        return p["k"] * (0.3 + 0.5 * c * c + 0.3 * wo[..., 0] * wi[..., 1])


@pytest.fixture(scope="module")
def scene():
    return builtin("sphere_on_plane", "small")


def _test_vertices(mesh):
    """Plane vertices near the sphere's foot and low sphere vertices: partly occluded."""
    v = mesh.vertices
    r = v[:, :2].norm(dim=-1)
    plane = torch.nonzero((v[:, 2] == 0) & (r > 1.1) & (r < 1.5)).flatten()[:3]
    low = torch.nonzero((v[:, 2] > 0.25) & (v[:, 2] < 0.45)).flatten()[:2]
    return torch.cat([plane, low])


def _views(k, seed):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(k, 3, generator=g, dtype=torch.float64)
    d[:, 2] = d[:, 2].abs() + 0.3
    return d / d.norm(dim=-1, keepdim=True)


def test_exit_transfer_matches_brute_force_within_truncation_bound(scene):
    """M_p·l at a local view vs brute-force ∫_H L V f* (direct lighting with visibility).

    With least-squares projections (Sloan 2003 eq. 1) the SH result is ∫_H (P a) b_v where a =
    L V on H and b_v = f*(·, v); the error ⟨a - Pa, b_v - Pb_v⟩ is bounded by
    ‖a - Pa‖ ‖b_v - Pb_v‖ (both measured here by brute force). With n = 4 lighting bands b_v is
    band-limited, so the bound is zero: the result must match to Monte Carlo accuracy."""
    mesh = scene
    vids = _test_vertices(mesh)
    k = vids.numel()
    F = mesh.frames()
    views = _views(k, 0)
    g = torch.Generator().manual_seed(5)
    L3 = torch.randn(1, 9, generator=g, dtype=torch.float64)  # band-limited 3-band light
    dirs, w = sh.stratified_sphere(60000, seed=11)
    caster = RayCaster(mesh)
    br = PolyBRDF()
    for n in (3, 4):
        L = torch.cat([L3, torch.zeros(1, n * n - 9, dtype=torch.float64)], 1)
        tr = precompute_glossy(mesh, n, 3, brdf=br, projection="least_squares", samples=16384, vertices=vids, seed=1)
        got = relight.glossy(tr.data.double(), L, views, tr.meta["out_index"])[:, 0]
        for i, p in enumerate(vids.tolist()):
            nrm = mesh.normals[p]
            up = dirs @ nrm > 0
            d, wu = dirs[up], w[up]
            vis = (~caster.occluded(mesh.vertices[p].expand(d.shape[0], 3), d, normals=nrm.expand(d.shape[0], 3))).double()
            assert 0.05 < float((vis * wu).sum()) / (2 * math.pi) < 0.98  # the vertex is partly shadowed
            loc = d @ F[p].T
            y = sh.eval_sh(loc, n)  # local SH (the LS fit lives on the local hemisphere)
            A = (y * wu[:, None]).T @ y  # Gram of the same samples: discrete least squares
            a = (sh.eval_sh(d, n) @ L[0]) * vis
            bv = br.cosine_weighted(loc, views[i].expand_as(loc))
            ref = float((wu * a * bv).sum())

            def resid(f):  # ‖f - P_H f‖ on H with the LS projection (Sloan 2003 §9.1)
                b = (y * (wu * f)[:, None]).sum(0)
                return math.sqrt(max(float((wu * f * f).sum() - b @ torch.linalg.solve(A, b)), 0.0))

            bound = resid(a) * resid(bv)
            scale = math.sqrt(float((wu * a * a).sum()) * float((wu * bv * bv).sum()))
            err = abs(float(got[i]) - ref)
            if n == 4:
                assert resid(bv) < 1e-6 * scale
            assert err <= bound + 0.01 * scale, (n, p, err, bound, scale)
    caster.close()


def test_rotating_light_and_object_agree(scene):
    """Rotate the mesh by R and the light by D(R): the exit radiance at the same local views is
    unchanged. Exact for the unshadowed Kautz path; to Monte Carlo accuracy for shadowed M_p."""
    R = sh.random_rotations(1, seed=4)[0]
    mesh = scene
    rot = dataclasses.replace(mesh, vertices=mesh.vertices @ R.T, normals=mesh.normals @ R.T,
                              tangents=mesh.tangents @ R.T, bitangents=mesh.bitangents @ R.T)
    g = torch.Generator().manual_seed(6)
    L = torch.randn(1, 16, generator=g, dtype=torch.float64)
    LR = sh.rotate(L, R)
    Bm = B.brdf_matrix(B.AshikhminShirley(8.0, 3.0, rd=0.2), 4, 4, quad_bands=12)
    idx = torch.arange(0, mesh.num_vertices, 97)
    views = _views(idx.numel(), 1)
    F, FR = mesh.frames()[idx], rot.frames()[idx]
    a = relight.kautz(None, relight.kautz_setup(F, 4), Bm, L, views)
    b = relight.kautz(None, relight.kautz_setup(FR, 4), Bm, LR, views)
    assert torch.allclose(a, b, atol=1e-10)
    wrong = relight.kautz(None, relight.kautz_setup(FR, 4), Bm, sh.rotate(L, R.T), views)
    assert (wrong - a).abs().max() > 1e-2
    # shadowed exit transfer, Monte Carlo
    vids = _test_vertices(mesh)
    br = B.Phong(4.0, kd=0.3)
    m1 = precompute_glossy(mesh, 4, 4, brdf=br, samples=16384, vertices=vids, quad_bands=12)
    m2 = precompute_glossy(rot, 4, 4, brdf=br, samples=16384, vertices=vids, quad_bands=12)
    v = _views(vids.numel(), 2)
    e1 = relight.glossy(m1.data.double(), L, v, m1.meta["out_index"])
    e2 = relight.glossy(m2.data.double(), LR, v, m2.meta["out_index"])
    assert (e1 - e2).abs().max() < 0.03 * e1.abs().max()


def test_lambertian_exit_transfer_equals_diffuse_transfer(scene):
    """With a Lambertian BRDF and least-squares projection, M_p l at any view is the diffuse
    transfer t_p·l (shadowed, same stratified set) computed by transfer.diffuse."""
    mesh = scene.with_albedo(1.0)
    vids = _test_vertices(mesh)
    tr = precompute_glossy(mesh, 3, 2, brdf=B.Lambertian(1.0), samples=2048, seed=3, vertices=vids, estimator="control")
    sub = dataclasses.replace(mesh)  # the same estimator on both sides ('auto' chooses by count here, by cosine weight there)
    diff = precompute_diffuse(sub, 3, 2048, seed=3, shadows="always", sampling="uniform", estimator="control")
    g = torch.Generator().manual_seed(7)
    L = torch.randn(1, 9, generator=g, dtype=torch.float64)
    e = relight.glossy(tr.data.double(), L, _views(vids.numel(), 3), tr.meta["out_index"])
    d = relight.diffuse(diff.data.double()[vids], L)
    assert torch.allclose(e, d, atol=2e-5 * float(d.abs().max()) + 1e-6)


def test_glossy_kautz_and_mrt_paths_agree(scene):
    """M_p = B R_p T_p against the Kautz path built from the stored global T_p (same samples),
    and the MRT four-tap against glossy m-band exit radiance within the tent projection error."""
    mesh = scene
    vids = _test_vertices(mesh)
    br = B.AshikhminShirley(6.0, 6.0, rd=0.3)
    kw = dict(samples=512, vertices=vids, quad_bands=14)
    M = precompute_glossy(mesh, 4, 5, brdf=br, projection="zero", **kw)
    T = precompute_glossy(mesh, 4, exit=False, **kw)
    assert T.meta["quantity"] == "transferred" and T.data.shape == (vids.numel(), 16, 16)
    A = precompute_mrt(mesh, 4, 5, 13, brdf=br, **kw)
    assert A.data.shape == (vids.numel(), 169, 16) and A.meta["matrix_shape"] == [169, 16]
    Bm = B.brdf_matrix(br, 5, 4, quad_bands=14)
    g = torch.Generator().manual_seed(8)
    L = torch.randn(3, 16, generator=g, dtype=torch.float64)
    v = _views(vids.numel(), 4)
    e = relight.glossy(M.data.double(), L, v, M.meta["out_index"])
    k = relight.kautz(T.data.double(), relight.kautz_setup(mesh.frames()[vids], 4), Bm, L, v)
    assert torch.allclose(e, k, atol=1e-5 * float(e.abs().max()))
    a = relight.mrt(A.data.double(), L, v)
    assert (a - e).abs().max() < 0.1 * e.abs().max()


def test_memory_estimate_and_bad_input(scene, tmp_path):
    with pytest.raises(ValueError, match=r"needs about .*(MiB|GiB)"):
        precompute_glossy(scene, 16, samples=4096, run=RunOptions(max_memory=1 << 20))
    with pytest.raises(ValueError, match="bands"):
        precompute_glossy(scene, 0)
    with pytest.raises(ValueError, match="M"):
        precompute_mrt(scene, 5, 8, 1)
    bad = dataclasses.replace(scene, tangents=scene.normals.clone())
    with pytest.raises(ValueError, match="tangent frame"):
        precompute_glossy(bad, 3, samples=16)
    with pytest.raises(ValueError, match="batch shape"):
        precompute_glossy(scene, 3, brdf=B.Phong(torch.tensor([1.0, 2.0])), samples=16)


def test_resume_gives_the_uninterrupted_result(tmp_path):
    mesh = builtin("occluder_over_plane", "small")
    vids = torch.arange(0, mesh.num_vertices, 7)
    kw = dict(brdf=B.Phong(8.0), samples=64, vertices=vids, quad_bands=12)
    full = precompute_glossy(mesh, 3, **kw, run=RunOptions(chunk_size=64))

    def stop(i, n):
        if i == 1:
            raise ChunkInterrupt

    state = tmp_path / "g.state"
    with pytest.raises(ChunkInterrupt):
        precompute_glossy(mesh, 3, **kw, run=RunOptions(chunk_size=64, state_dir=state, callback=stop))
    again = precompute_glossy(mesh, 3, **kw, run=RunOptions(chunk_size=64, state_dir=state, resume=True))
    assert torch.equal(full.data, again.data)
    assert not state.exists()


def test_transport_tables(tmp_path):
    """Green 2005 eq. 1.1–1.2: a Lambertian table under constant unit light integrates to kd for
    views above the tangent plane and 0 below (cos θ_o ≤ transport.HORIZON_EPS included); an interrupted table resumes to the same data."""
    mesh = builtin("convex", "small")
    kd = 0.6
    out = tmp_path / "t"
    t = precompute_transport(mesh, out, brdf=B.Lambertian(kd), views=1, res=12, run=RunOptions(chunk_size=500))
    r = t.radiance(torch.ones(1, 6, 12, 12), view=3)[:, 0]
    facing = mesh.normals @ t.views[3].double() > HORIZON_EPS  # a view in the tangent plane counts as below it
    assert torch.allclose(r[facing], torch.full_like(r[facing], kd), atol=2e-3)
    assert (r[~facing] == 0).all()
    part = tmp_path / "p"
    precompute_transport(mesh, part, brdf=B.Phong(10.0), views=1, res=4, max_chunks=1, run=RunOptions(chunk_size=500))
    assert not TransportTable(part).meta["complete"]
    done = precompute_transport(mesh, part, brdf=B.Phong(10.0), views=1, res=4, run=RunOptions(chunk_size=500, resume=True))
    ref = precompute_transport(mesh, tmp_path / "r", brdf=B.Phong(10.0), views=1, res=4, run=RunOptions(chunk_size=500))
    assert done.meta["complete"]
    for (a0, b0, x), (a1, b1, y) in zip(done, ref):
        assert (a0, b0) == (a1, b1) and torch.equal(x, y)
    _, sa = cube_directions(5)
    assert abs(float(sa.sum()) - 4 * math.pi) < 1e-12
    with pytest.raises(FileExistsError):
        precompute_transport(mesh, out, brdf=B.Lambertian(kd), views=1, res=12)


def test_glossy_interreflection_equals_diffuse_bounces(scene):
    """Glossy transfer with bounces (per-ray y(s) t_q(s)ᵀ outer products at blocked directions)
    against the diffuse precompute's bounces (sparse S-matrix products): with a Lambertian BRDF
    both are the same integral, so M_p·l at any view equals t_p·l with the same bounce count."""
    mesh = scene.with_albedo(0.8)
    vids = _test_vertices(mesh)
    g = torch.Generator().manual_seed(7)
    L = torch.randn(1, 9, generator=g, dtype=torch.float64)
    prev = None
    for bounces in (1, 2):
        tr = precompute_glossy(mesh, 3, 2, brdf=B.Lambertian(0.8), samples=1024, seed=3, vertices=vids, bounces=bounces,
                               estimator="control")  # the same estimator on both sides (their 'auto' rules differ)
        assert tr.meta["bounces"] == bounces
        diff = precompute_diffuse(mesh, 3, 1024, seed=3, shadows="always", bounces=bounces, bounce_tol=0.0,
                                  sampling="uniform", estimator="control")  # glossy: its set, keys, estimator
        assert diff.meta["bounces_used"] == bounces and diff.data.ndim == 2  # grey: albedo kept separate
        e = relight.glossy(tr.data.double(), L, _views(vids.numel(), 3), tr.meta["out_index"])
        d = relight.diffuse(diff.data.double()[vids] * 0.8, L)
        assert torch.allclose(e, d, atol=1e-5 * float(d.abs().max()))
        if prev is not None:
            assert not torch.allclose(e, prev)  # the second bounce changes the result
        prev = e


def test_glossy_bounces_add_light_and_need_shadows(scene):
    """Under a constant environment interreflected light only adds (a glossy lobe), and bounces
    without visibility are refused."""
    mesh = scene
    vids = _test_vertices(mesh)
    L = torch.zeros(1, 9, dtype=torch.float64)
    L[0, 0] = 2 * math.sqrt(math.pi)
    br = B.Phong(8.0, ks=0.6, kd=0.3)
    outs = []
    for b in (0, 1):
        tr = precompute_glossy(mesh, 3, 3, brdf=br, samples=512, seed=1, vertices=vids, bounces=b)
        outs.append(relight.glossy(tr.data.double(), L, _views(vids.numel(), 5), tr.meta["out_index"]))
    assert torch.all(outs[1] >= outs[0] - 1e-9) and float((outs[1] - outs[0]).max()) > 1e-3
    with pytest.raises(ValueError, match="bounces"):
        precompute_glossy(mesh, 3, 3, brdf=br, samples=64, vertices=vids, bounces=1, shadows=False)
    with pytest.raises(ValueError, match="bounces"):
        precompute_glossy(mesh, 3, 3, brdf=br, samples=64, vertices=vids, bounces=-1)
