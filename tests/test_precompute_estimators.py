"""The diffuse precompute's estimators (issue 42, part 1): every direction set and estimator is
unbiased, the control variate is exact where nothing is blocked, and qmc's per-vertex
rotations depend on neither chunking nor the subset asked for.

References are independent of the estimators: the analytic unshadowed transfer (Ramamoorthi
2002 eq. 4.11) for an open point, and the analytic visible fraction of a point on the ground
next to a sphere (``sphere_on_plane_visibility``, a closed form) for an occluded one.
"""
import math

import numpy as np
import pytest
import torch

from prt_torch.scene import RayCaster, builtin, geodesic_sphere, make_mesh, sphere_on_plane_visibility
from prt_torch.sh import eval_sh
from prt_torch.transfer import RunOptions
from prt_torch.transfer.glossy import ESTIMATORS as GLOSSY_ESTIMATORS
from prt_torch.transfer.diffuse import (
    ESTIMATORS,
    FACE_PROBE_RAYS,
    GUIDE_GRID,
    SAMPLINGS,
    DiffuseSampler,
    HitBounce,
    face_points,
    precompute_diffuse,
    qmc_rays,
    transfer_at_points,
    unshadowed_transfer,
)

Y00 = 0.5 / math.sqrt(math.pi)


@pytest.fixture(scope="module")
def sphere_caster():
    v, f = geodesic_sphere(24)  # unit sphere resting on z = 0 at the origin (no ground: rays below leave)
    rc = RayCaster(make_mesh(v + np.array([0, 0, 1.0]), f))
    yield rc
    rc.close()


def _ground(d):
    d = torch.as_tensor(d, dtype=torch.float64)
    pts = torch.stack([d, torch.zeros_like(d), torch.zeros_like(d)], 1)
    return pts, torch.tensor([0, 0, 1.0], dtype=torch.float64).expand(d.shape[0], 3)


@pytest.mark.parametrize("sampling", SAMPLINGS)
@pytest.mark.parametrize("estimator", ["control", "auto"])
def test_control_variate_is_exact_where_nothing_is_blocked(sphere_caster, sampling, estimator):
    # points above the sphere looking up, and one beside it looking away: no ray meets the mesh
    pts = torch.tensor([[0, 0, 2.5], [0.3, -0.2, 4.0], [3.0, 0, 1.0]], dtype=torch.float64)
    n = torch.tensor([[0, 0, 1.0], [0.3, 0.1, 0.9], [1.0, 0, 0]], dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    exact = unshadowed_transfer(n, 4)
    t = transfer_at_points(sphere_caster, pts, n, 4, 64, seed=3, sampling=sampling, estimator=estimator)
    torch.testing.assert_close(t, exact, atol=1e-13, rtol=0)
    plain = transfer_at_points(sphere_caster, pts, n, 4, 64, seed=3, sampling=sampling, estimator="plain")
    assert float((plain - exact).abs().max()) > 1e-4  # the plain sum carries its sampling error there


@pytest.mark.parametrize("estimator", ESTIMATORS)
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_every_estimator_is_unbiased_against_closed_forms(sphere_caster, sampling, estimator):
    """Mean over seeds within 3σ (σ: the spread over seeds / √seeds) of the analytic values:
    t00 = Y00 · visible fraction on the ground near the sphere, and the unshadowed transfer of
    a tilted open point (every coefficient)."""
    seeds = 48
    d = [0.5, 1.0, 2.0]
    pts, n = _ground(d)
    open_p = torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64)
    open_n = torch.tensor([[0.6, 0.0, 0.8]], dtype=torch.float64)
    P, N = torch.cat([pts, open_p]), torch.cat([n, open_n])
    runs = torch.stack([transfer_at_points(sphere_caster, P, N, 3, 32, seed=s, sampling=sampling, estimator=estimator)
                        for s in range(seeds)])  # [S, 4, 9]
    mean, se = runs.mean(0), runs.std(0) / math.sqrt(seeds)
    ref_occ = torch.tensor([Y00 * sphere_on_plane_visibility(x) for x in d], dtype=torch.float64)
    # the tessellated sphere (geodesic 24) sits inside the true one: its occlusion is smaller by ~1e-3 relative
    tol_occ = 3 * se[:3, 0] + 2e-3 * ref_occ
    assert ((mean[:3, 0] - ref_occ).abs() <= tol_occ).all(), (mean[:3, 0], ref_occ, se[:3, 0])
    ref_open = unshadowed_transfer(open_n, 3)[0]
    assert ((mean[3] - ref_open).abs() <= 3 * se[3] + 1e-12).all(), (mean[3], ref_open, se[3])
    assert float(se[:3, 0].max()) > 0  # the occluded points do carry noise: the check above is not vacuous


def test_control_variate_lowers_the_error_at_equal_rays(sphere_caster):
    """On the ground near the sphere (partly blocked) the control variate's spread over seeds is
    below the plain sum's for the same rays (its error is that of the blocked part alone)."""
    pts, n = _ground([1.5, 2.5, 4.0])
    spread = {}
    for est in ESTIMATORS:
        runs = torch.stack([transfer_at_points(sphere_caster, pts, n, 3, 64, seed=s, sampling="uniform", estimator=est)
                            for s in range(24)])
        spread[est] = float(runs.std(0).norm())
    assert spread["control"] < 0.7 * spread["plain"], spread


def test_qmc_rotations_depend_on_neither_chunking_nor_subset():
    m = builtin("sphere_on_plane")
    a = precompute_diffuse(m, 3, 64, seed=2, shadows="always", fold_albedo=False, run=RunOptions(chunk_size=97))
    b = precompute_diffuse(m, 3, 64, seed=2, shadows="always", fold_albedo=False, run=RunOptions(chunk_size=1000))
    assert a.meta["sampling"] == "qmc" and a.meta["estimator"] == "auto"  # the defaults
    assert torch.equal(a.data, b.data)
    idx = torch.tensor([5, 700, 1200, 3])
    from prt_torch.transfer.diffuse import boundary_nudge

    with RayCaster(m) as rc:
        t = transfer_at_points(rc, m.vertices[idx], m.normals[idx], 3, 64, seed=2, nudge=boundary_nudge(m)[idx], ids=idx)
    torch.testing.assert_close(t.to(torch.float32), a.data[idx], atol=1e-6, rtol=0)
    # another seed gives other rotations
    c = precompute_diffuse(m, 3, 64, seed=3, shadows="always", fold_albedo=False)
    assert not torch.equal(a.data, c.data)


def test_qmc_ray_count_and_weights():
    assert [qmc_rays(n) for n in (1, 2, 3, 1024, 1025)] == [1, 1, 2, 512, 513]
    s = DiffuseSampler(2, 100, 0, "qmc")
    n = torch.tensor([[0, 0, 1.0], [1.0, 0, 0]], dtype=torch.float64)
    i, j, o, d, cos = s.rays(n, n, None, 1e-4, ids=np.array([10, 11]))
    assert i.shape == (100,) and d.shape == (100, 3)
    dn = np.einsum("rk,rk->r", d.astype(np.float64), n.numpy()[i])
    np.testing.assert_allclose(dn, cos, atol=1e-6)  # the returned cosines are the rays' own
    assert (cos > 0).all()
    # the density p(z) = 3/4 + z/2 (3/4 uniform in solid angle, 1/4 cosine): the weights (1/M)·2z/(3/4 + z/2)
    # integrate the clamped cosine, (1/π)∫ max(n·s,0) ds = 1; the mean cosine is E[z] = 3/8 + 1/6 = 13/24
    # (1/2 for the uniform density, 2/3 for the cosine one)
    w = s.ray_weights(i, j, cos)
    np.testing.assert_allclose(w, 2 * cos / (0.75 + 0.5 * cos) / 50, rtol=1e-15)
    np.testing.assert_allclose(np.bincount(i, weights=w), [1.0, 1.0], rtol=0.02)
    np.testing.assert_allclose(np.bincount(i, weights=cos) / 50, [13 / 24, 13 / 24], atol=0.01)


def test_bad_choices_name_the_parameter():
    m = builtin("convex")
    with pytest.raises(ValueError, match="estimator='cv'"):
        precompute_diffuse(m, 2, 16, estimator="cv")
    with pytest.raises(ValueError, match="sampling='sobol'"):
        precompute_diffuse(m, 2, 16, sampling="sobol")


# ------------------------------------------------------------------ glossy / MRT transferred radiance T_p
def test_unshadowed_transferred_is_the_hemisphere_integral():
    """D_pᵀ A D_p against a brute-force sum over a dense spherical-Fibonacci set (no rotation,
    no Gram matrix): (T_p)_ij = ∫_{n·s>0} y_i y_j ds."""
    from prt_torch.sh import eval_sh, fibonacci_sphere
    from prt_torch.transfer.glossy import unshadowed_transferred

    n = torch.tensor([[0, 0, 1.0], [0.3, -0.5, 0.81], [-1.0, 0, 0], [0.1, 0.2, -0.97]], dtype=torch.float64)
    n = n / n.norm(dim=1, keepdim=True)
    T = unshadowed_transferred(n, 4)  # [4, 16, 16]
    dirs, w = fibonacci_sphere(400_000)
    Y = eval_sh(dirs, 4)
    for k in range(4):
        up = (dirs @ n[k] > 0).to(torch.float64) * w
        ref = (Y * up[:, None]).T @ Y
        torch.testing.assert_close(T[k], ref, atol=2e-4, rtol=0)


@pytest.mark.parametrize("estimator", GLOSSY_ESTIMATORS)
def test_transferred_radiance_unbiased_and_exact_when_open(sphere_caster, estimator):
    """T_00 on the ground beside the sphere = Y00² · visible solid angle = Y00² 2π cos α
    (the sphere's cap, sin α = r/√(d² + r²), lies wholly above the horizon); an open point's
    control-variate T_p is the exact D_pᵀ A D_p."""
    from prt_torch.transfer.glossy import _Directions, transferred_radiance, unshadowed_transferred

    d = torch.tensor([0.3, 0.55, 0.7, 1.5], dtype=torch.float64)  # open fraction cos α: 0.29 / 0.48 / 0.57 / 0.83 ('auto':
    pts, n = _ground(d)  # the plain sum, either branch by seed, mostly the control variate, the control variate)
    runs = torch.stack([transferred_radiance(sphere_caster, pts, n, _Directions(3, 64, s), estimator=estimator)[0][:, 0, 0]
                        for s in range(40)])  # [S, 4]
    mean, se = runs.mean(0), runs.std(0) / math.sqrt(runs.shape[0])
    cos_a = d / torch.sqrt(d * d + 1.0)
    ref = Y00 ** 2 * 2 * math.pi * cos_a
    assert ((mean - ref).abs() <= 3 * se + 2e-3 * ref).all(), (mean, ref, se)
    open_p = torch.tensor([[0.0, 0.0, 3.0]], dtype=torch.float64)
    open_n = torch.tensor([[0.0, 0.6, 0.8]], dtype=torch.float64)
    T, _ = transferred_radiance(sphere_caster, open_p, open_n, _Directions(3, 64, 0), estimator=estimator)
    exact = unshadowed_transferred(open_n, 3)
    if estimator in ("control", "auto"):  # auto takes the control variate at an open point
        torch.testing.assert_close(T, exact, atol=1e-12, rtol=0)
    else:
        assert float((T - exact).abs().max()) > 1e-4


def test_glossy_and_mrt_record_the_estimator():
    from prt_torch.transfer.glossy import precompute_glossy
    from prt_torch.transfer.mrt import precompute_mrt

    m = builtin("sphere_on_plane")
    sel = torch.tensor([0, 900, 1500])
    g = precompute_glossy(m, 3, samples=64, vertices=sel)
    assert g.meta["estimator"] == "auto" and precompute_mrt(m, 3, 3, 3, samples=64, vertices=sel).meta["estimator"] == "auto"
    gp = precompute_glossy(m, 3, samples=64, vertices=sel, estimator="plain")
    assert gp.meta["estimator"] == "plain" and not torch.equal(g.data, gp.data)
    mr = precompute_mrt(m, 3, 3, 3, samples=64, vertices=sel, estimator="plain")
    assert mr.meta["estimator"] == "plain"
    with pytest.raises(ValueError, match="estimator='x'"):
        precompute_mrt(m, 3, 3, 3, samples=64, vertices=sel, estimator="x")


@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_auto_is_exact_for_an_enclosed_point_where_control_is_not(sampling):
    """Inside a closed box every ray is blocked: the true transfer is 0. 'auto' (the plain sum there) and
    'plain' give exactly 0; 'control' keeps the direction set's error of the unshadowed integral."""
    v, f = geodesic_sphere(6)
    with RayCaster(make_mesh(v * 3.0, f[:, ::-1].copy())) as rc:  # a sphere of radius 3, inward-facing
        p = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.2, 1.0]], dtype=torch.float64)
        n = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
        t = {e: transfer_at_points(rc, p, n, 3, 64, seed=1, sampling=sampling, estimator=e) for e in ESTIMATORS}
    assert torch.equal(t["auto"], torch.zeros_like(t["auto"])) and torch.equal(t["plain"], torch.zeros_like(t["plain"]))
    assert float(t["control"].abs().max()) > 0


def test_glossy_auto_is_exact_for_an_enclosed_point_where_control_is_not():
    """T_p inside a closed box is 0 (every direction blocked): 'auto' (the plain sum there) and 'plain'
    give exactly 0, 'control' keeps the sphere set's error of the unshadowed T_p; at an open point
    'auto' equals 'control' bit for bit (exact, checked above against D_pᵀ A D_p)."""
    from prt_torch.transfer.glossy import _Directions, transferred_radiance

    p = torch.tensor([[0.0, 0.0, 0.0], [0.5, -0.2, 1.0]], dtype=torch.float64)
    n = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64)
    with RayCaster(_enclosure()) as rc:
        t = {e: transferred_radiance(rc, p, n, _Directions(3, 64, 1), estimator=e)[0] for e in GLOSSY_ESTIMATORS}
    assert torch.equal(t["auto"], torch.zeros_like(t["auto"])) and torch.equal(t["plain"], torch.zeros_like(t["plain"]))
    assert float(t["control"].abs().max()) > 1e-3


def _enclosure():
    """A sphere of radius 3 facing inwards: every ray from inside is blocked."""
    v, f = geodesic_sphere(6)
    return make_mesh(v * 3.0, f[:, ::-1].copy())


def test_hit_auto_choice_reads_face_openness_not_the_hits_rays():
    """'auto' at bounce hits chooses per hit from HitBounce.face_openness (its own rays, traced
    once): open faces (top of the sphere) read 1 and take the control variate, an enclosure's faces
    read 0 and take the plain sum (exactly 0 there, where the control variate keeps its set's
    error); on the ground beside the sphere the openness' mean over seeds is the closed-form
    cosine-weighted visible fraction within 3σ (+ the tessellation's 3e-3)."""
    mesh = builtin("sphere_on_plane", "medium")
    c, fn, _ = face_points(mesh)
    r = torch.linalg.norm(c[:, :2], dim=1)
    ground = (fn[:, 2] > 0.999) & (c[:, 2].abs() < 1e-9)
    picks = [torch.nonzero(ground & ((r - d).abs() < 0.05))[:, 0] for d in (0.7, 1.2)]
    top = int(torch.argmax(c[:, 2]))
    with RayCaster(mesh, workers=1) as caster:
        op = np.stack([HitBounce(mesh, 2, 8, s, 1, 1, estimator="auto").face_openness(caster) for s in range(24)])
    assert op.shape == (24, mesh.faces.shape[0]) and (op[:, top] == 1.0).all()
    for d, idx in zip((0.7, 1.2), picks):
        per_seed = op[:, idx.numpy()].mean(1)  # [S] the faces near distance d
        ref = np.mean([sphere_on_plane_visibility(float(x)) for x in r[idx]])
        se = per_seed.std() / math.sqrt(len(per_seed))
        assert se > 0 and abs(per_seed.mean() - ref) <= 3 * se + 3e-3, (d, per_seed.mean(), ref, se)
    box = _enclosure()
    tri = np.arange(0, box.faces.shape[0], 7)
    bary = np.full((tri.shape[0], 3), 1.0 / 3.0)
    ka, kb = np.arange(tri.shape[0]), 3 * np.arange(tri.shape[0])
    with RayCaster(box, workers=1) as caster:
        hb = HitBounce(box, 3, 8, 1, 1, 1, estimator="auto")
        assert (hb.face_openness(caster) == 0).all()
        auto = hb.values(caster, tri, bary, ka, kb)
        ctrl = HitBounce(box, 3, 8, 1, 1, 1, estimator="control").values(caster, tri, bary, ka, kb)
    assert torch.equal(auto, torch.zeros_like(auto)) and float(ctrl.abs().max()) > 1e-3


def test_hit_auto_unbiased_against_brute_force_where_both_branches_run():
    """x⁰(q) at hits in a grey Cornell box, where some faces are mostly open (control variate) and
    others mostly blocked (plain sum), with first-hit rotations offset by direction index (Halton)
    and the rays guided by each face's pooled open-fraction grid (its weights 1/(K P_cell)):
    the mean of 'auto' over 40 seeds (16 rays per hit) equals a brute-force plain estimate of 8192
    rays per hit (another estimator, independent seeds) within 3σ of both, every coefficient."""
    mesh = builtin("cornell_box", "small", albedo=0.8)
    with RayCaster(mesh, workers=1) as caster:
        op = HitBounce(mesh, 2, 16, 0, 1, 1, estimator="auto").face_openness(caster)
        rng = np.random.default_rng(0)
        both = np.concatenate([rng.choice(np.flatnonzero((op > 0.05) & (op < 0.4)), 4, replace=False),
                               rng.choice(np.flatnonzero((op > 0.6) & (op < 0.95)), 4, replace=False)])
        bary = np.full((8, 3), 1.0 / 3.0)
        ka, kb = np.arange(8) + 100, np.arange(8) * 5 + 1
        hbs = [HitBounce(mesh, 2, 16, s, 1, 1, estimator="auto") for s in range(40)]
        guided = np.stack([hb.guided_faces(caster)[both] for hb in hbs])  # [S, 8] per seed's own probe
        assert guided[:, :4].mean() > 0.75 and not guided[:, 4:].any()  # the mostly blocked hits' rays guided, not the open
        runs = torch.stack([hb.values(caster, both, bary, ka, kb)[:, 0, 0] for hb in hbs])  # [S, 8, 4]
        ref = torch.stack([HitBounce(mesh, 2, 8192, 1000 + s, 1, 1, estimator="plain").values(caster, both, bary, ka, kb)[:, 0, 0]
                           for s in range(4)])
    mean, se = runs.mean(0), runs.std(0) / math.sqrt(runs.shape[0])
    rmean, rse = ref.mean(0), ref.std(0) / math.sqrt(ref.shape[0])
    tol = 3 * torch.sqrt(se ** 2 + rse ** 2) + 1e-12
    assert ((mean - rmean).abs() <= tol).all(), (mean, rmean, tol)
    assert float(se[:, 0].min()) > 0  # every hit carries noise: the check is not vacuous


def test_one_bounce_auto_depends_on_neither_chunking_nor_subset():
    m = builtin("sphere_on_plane")
    kw = dict(seed=2, shadows="always", fold_albedo=False, bounce_tol=0.0)
    a = precompute_diffuse(m, 3, 64, 1, run=RunOptions(chunk_size=97), **kw)
    b = precompute_diffuse(m, 3, 64, 1, run=RunOptions(chunk_size=1000), **kw)
    # the probe traced where first hits land (issue 42 §2), K rays per distinct face, the same faces in any chunking
    ga, gb = a.meta["hit_guide"], b.meta["hit_guide"]
    assert a.meta["estimator"] == "auto" and a.meta["hit_choice_rays"] == b.meta["hit_choice_rays"]
    assert (ga["faces_probed"], ga["faces_guided"]) == (gb["faces_probed"], gb["faces_guided"])
    assert 0 < ga["faces_probed"] < m.faces.shape[0]  # faces no vertex ray reaches are not probed
    assert ga["faces_guided"] > 0  # the ground's faces: the guided path is what is compared
    assert torch.equal(a.data, b.data)


def _plane():
    """A flat 8 × 8-cell grid on z = 0 facing +z (128 coplanar faces)."""
    g = np.linspace(-1, 1, 9)
    X, Y = np.meshgrid(g, g)
    v = np.stack([X.ravel(), Y.ravel(), np.zeros(X.size)], 1)
    idx = np.arange(81).reshape(9, 9)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    return make_mesh(v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))


def test_guided_warp_is_unbiased_for_the_clamped_cosine_integral():
    """HitBounce._guided_rays: uniform points warped by a face's guide, weighted by q = 1/(K P_cell),
    average to (1/π) ∫ y(s) max(n·s, 0) ds — the analytic unshadowed transfer (Ramamoorthi 2002
    eq. 4.11) — within 4σ per coefficient, for a lopsided guide (one cell 100× another); and every
    direction leaves the face's side."""
    mesh = _plane()
    hb = HitBounce(mesh, 3, 8, 0, 1, 1, estimator="auto")
    F, K = mesh.faces.shape[0], FACE_PROBE_RAYS
    rng = np.random.default_rng(5)
    opened = (rng.random((F, K)) < np.where(np.arange(K) % GUIDE_GRID[1] < 2, 0.9, 0.05)).astype(np.float64)  # 2 sectors open
    hb._face_open = opened.mean(1)
    hb._build_guide(opened)
    assert hb.guided[7] and float(hb.guide_mass.max() / hb.guide_mass.min()) > 5  # lopsided, not the cosine density
    tri = np.full(200_000, 7)
    d, q = hb._guided_rays(tri, rng.random(tri.shape[0]), rng.random(tri.shape[0]))
    n = hb.face_normals[7]
    assert (d.astype(np.float64) @ n.numpy() > 0).all()
    x = eval_sh(torch.from_numpy(d).to(torch.float64), 3) * torch.from_numpy(q)[:, None]  # [R, 9]
    mean, se = x.mean(0), x.std(0) / math.sqrt(x.shape[0])
    exact = unshadowed_transfer(n[None], 3)[0]
    assert ((mean - exact).abs() <= 4 * se + 1e-12).all(), (mean, exact, se)


@pytest.mark.parametrize("estimator", ["control", "auto"])
def test_hit_is_exact_where_its_hemisphere_is_open(estimator):
    """A hit on a flat open plane (nothing above it): the control variate (chosen by 'auto' there,
    its face reads open, so its rays are not guided) gives exactly the unshadowed transfer of the
    face's hemisphere, whatever rays were drawn; the plain sum does not."""
    mesh = _plane()
    tri = np.arange(0, mesh.faces.shape[0], 5)
    bary = np.random.default_rng(1).dirichlet(np.ones(3), tri.shape[0])
    ka, kb = np.arange(tri.shape[0]), 2 * np.arange(tri.shape[0]) + 1
    with RayCaster(mesh, workers=1) as caster:
        hb = HitBounce(mesh, 4, 8, 3, 1, 1, estimator=estimator)
        assert not hb.guided_faces(caster).any() and (hb.face_openness(caster) == 1).all()
        x = hb.values(caster, tri, bary, ka, kb)[:, 0, 0]
        plain = HitBounce(mesh, 4, 8, 3, 1, 1, estimator="plain").values(caster, tri, bary, ka, kb)[:, 0, 0]
    _, fn, _ = face_points(mesh)
    exact = unshadowed_transfer(fn[torch.from_numpy(tri)], 4)
    torch.testing.assert_close(x, exact, atol=1e-13, rtol=0)
    assert float((plain - exact).abs().max()) > 1e-3
    assert GUIDE_GRID[0] * GUIDE_GRID[1] == FACE_PROBE_RAYS


def _room(cells=4):
    """A unit box open towards −y (floor, ceiling, back and side walls facing inwards), each wall a
    ``cells`` × ``cells`` grid: a small enclosure whose walls are guided."""
    vs, fs = [], []
    g = np.linspace(0.0, 1.0, cells + 1)
    for o, u, w in (([0, 0, 0], [1, 0, 0], [0, 1, 0]), ([0, 0, 1], [0, 1, 0], [1, 0, 0]), ([0, 1, 0], [1, 0, 0], [0, 0, 1]),
                    ([0, 0, 0], [0, 1, 0], [0, 0, 1]), ([1, 0, 0], [0, 0, 1], [0, 1, 0])):  # normals u × w point inwards
        o, u, w = (np.array(x, float) for x in (o, u, w))
        A, B = np.meshgrid(g, g, indexing="ij")
        idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1) + sum(len(x) for x in vs)
        vs.append((o + A.reshape(-1, 1) * u + B.reshape(-1, 1) * w))
        a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
        fs.append(np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))
    return make_mesh(np.concatenate(vs), np.concatenate(fs))


def test_one_bounce_with_guided_hits_is_unbiased_against_a_brute_force_reference():
    """The whole one-bounce transfer (vertex rays, guided first hits, their weights) in a small open
    room: the default (qmc + auto) averaged over 40 seeds equals a brute-force estimate by another
    estimator (uniform + plain: no control variate, no guide; 8× the vertex rays, 8× the rays per
    hit, 4 other seeds) within 3σ of both, for four floor vertices and bands 0–1."""
    mesh = _room()
    kw = dict(shadows="always", fold_albedo=False, bounce_tol=0.0, run=RunOptions(progress=False))
    n, v = mesh.normals, mesh.vertices
    floor = torch.nonzero((n[:, 2] > 0.99) & (v[:, 2].abs() < 1e-9) & (v[:, 0] > 0.1) & (v[:, 0] < 0.9)
                          & (v[:, 1] > 0.1) & (v[:, 1] < 0.9))[:, 0][:4]
    runs = []
    for s in range(40):
        tr = precompute_diffuse(mesh, 2, 64, 1, seed=s, **kw)
        runs.append(tr.data.to(torch.float64)[floor])
    assert tr.meta["hit_guide"]["faces_guided"] > 0
    ref = torch.stack([precompute_diffuse(mesh, 2, 512, 1, seed=100 + s, sampling="uniform", estimator="plain",
                                          hit_samples=64, **kw).data.to(torch.float64)[floor] for s in range(4)])
    runs = torch.stack(runs)
    mean, se = runs.mean(0), runs.std(0) / math.sqrt(runs.shape[0])
    rmean, rse = ref.mean(0), ref.std(0) / math.sqrt(ref.shape[0])
    tol = 3 * torch.sqrt(se ** 2 + rse ** 2)
    assert float(se[:, 0].min()) > 0 and ((mean - rmean).abs() <= tol).all(), (mean, rmean, tol)


def test_hit_samples_auto_by_estimator_and_bad_values_named():
    """``hit_samples='auto'`` (the default): 4 rays per hit under 'auto', 8 under 'control' and 'plain'
    (their numbers as before); the resolved count is what the run records and traces."""
    from prt_torch.transfer.diffuse import HIT_SAMPLES_AUTO, resolve_hit_samples

    assert HIT_SAMPLES_AUTO == {"auto": 4, "control": 8, "plain": 8}
    assert resolve_hit_samples("auto", "plain") == 8 and resolve_hit_samples(5, "auto") == 5
    m = _enclosure()
    for est, M in (("auto", 4), ("plain", 8)):
        tr = precompute_diffuse(m, 2, 8, 1, estimator=est, shadows="always", fold_albedo=False, bounce_tol=0.0,
                                run=RunOptions(progress=False))
        assert tr.meta["hit_samples"] == M and tr.meta["hit_rays_traced"] == M * tr.meta["rays_traced"]  # every ray hits
    with pytest.raises(ValueError, match="hit_samples='many'; accepted: an integer in \\[1, 4096\\] or 'auto'"):
        precompute_diffuse(m, 2, 8, 1, hit_samples="many")
    with pytest.raises(ValueError, match="hit_samples"):
        precompute_diffuse(m, 2, 8, 1, hit_samples=0)


def test_glossy_one_bounce_auto_is_unbiased_against_a_brute_force_reference():
    """Glossy T_p with one bounce under the default 'auto' (per-vertex choice; the hits' probe, guided
    walls and 4 rays per hit) in the small open room: its mean over 40 seeds equals a brute-force
    estimate by another estimator ('plain': visible sum, unguided hits with 8 rays; 8× the sphere
    samples, 16 other seeds) within 4σ of both at every entry of the 4 × 4 matrices of four floor
    vertices (64 correlated entries: 4σ keeps the family-wise false alarm near 0.4%; with 160 seeds
    each, auto against plain measured max |z| 1.9 over the 64; fails with the guided weights dropped)."""
    from prt_torch.transfer.glossy import precompute_glossy

    mesh = _room()
    n, v = mesh.normals, mesh.vertices
    floor = torch.nonzero((n[:, 2] > 0.99) & (v[:, 2].abs() < 1e-9) & (v[:, 0] > 0.1) & (v[:, 0] < 0.9)
                          & (v[:, 1] > 0.1) & (v[:, 1] < 0.9))[:, 0][:4]
    kw = dict(exit=False, shadows=True, bounces=1, vertices=floor, run=RunOptions(progress=False))
    runs = []
    for s in range(40):
        tr = precompute_glossy(mesh, 2, samples=64, seed=s, **kw)
        runs.append(tr.data.to(torch.float64))
    assert tr.meta["estimator"] == "auto" and tr.meta["hit_guide"]["faces_guided"] > 0 and tr.meta["hit_samples"] == 4
    ref = torch.stack([precompute_glossy(mesh, 2, samples=512, seed=100 + s, estimator="plain", **kw).data.to(torch.float64)
                       for s in range(16)])
    runs = torch.stack(runs)
    mean, se = runs.mean(0), runs.std(0) / math.sqrt(runs.shape[0])
    rmean, rse = ref.mean(0), ref.std(0) / math.sqrt(ref.shape[0])
    tol = 4 * torch.sqrt(se ** 2 + rse ** 2) + 1e-12
    assert float(se[:, 0, 0].min()) > 0 and ((mean - rmean).abs() <= tol).all(), (mean - rmean, tol)
