"""The bounce estimator's guided first hits compiled, and its face probe traced only where first
hits land (issue 42 §1/§2, ``diffuse.HitBounce``).

* ``ray_kernels.guided_rays_native`` (kernels/guided.c) writes the same bits as the numpy reference
  (``HitBounce._guided_rays``, Malley's map in numpy) for lopsided guides, and refuses a face that
  has no guide.
* The probe of a subset of faces (``face_openness(caster, faces)`` / ``prepare``) gives each face
  the value and guide the whole-mesh probe gives it, whatever was probed before: a function of
  (seed, mesh, face) only — so the transfer stays bit-identical however the chunks fall and
  whichever process probes.
* 1 and 2 ray-casting workers give the same glossy one-bounce matrices and probe counts.

Unbiasedness of the guided path (its weights and warp) against brute force is checked in
tests/test_precompute_estimators.py, which now runs through the compiled pass.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from prt_torch.scene import RayCaster, builtin
from prt_torch.transfer import RunOptions
from prt_torch.transfer import ray_kernels
from prt_torch.transfer.diffuse import FACE_PROBE_RAYS, GUIDE_GRID, HitBounce, _hammersley, _hammersley_tables
from prt_torch.transfer.glossy import precompute_glossy

needs_lib = pytest.mark.skipif(ray_kernels._lib() is None, reason="no C compiler: the numpy reference runs")


def _guided_box():
    """A grey Cornell box whose guide is built from the whole-mesh probe (seed 3)."""
    mesh = builtin("cornell_box", "small", albedo=0.8)
    return mesh, HitBounce(mesh, 2, 8, 3, 1, 1, estimator="auto")


@needs_lib
def test_compiled_guided_rays_equal_the_numpy_reference_bit_for_bit():
    mesh, hb = _guided_box()
    with RayCaster(mesh, workers=1) as caster:
        hb.face_openness(caster)
    gf = np.flatnonzero(hb.guided)
    assert gf.size > 100 and float(hb.guide_mass.max() / hb.guide_mass.min()) > 5  # lopsided guides, not the cosine density
    rng = np.random.default_rng(0)
    M, H = 8, 3000
    tri = rng.choice(gf, H)
    g = np.sort(rng.choice(H, H // 2, replace=False))  # the guided hits among H hits
    u1, v2 = rng.random(H), rng.random(H)
    ta, tb = _hammersley_tables(_hammersley(M))[0], _hammersley(M)[:, 1]
    D = np.full((H * M, 3), 7.0, np.float32)
    W = np.ones(H * M)
    assert ray_kernels.guided_rays_native(M, g, tri[g], u1[g], v2[g], ta, tb, hb._guide_row, *hb._guide_cdf, hb.guide_mass,
                                          hb.frames, D, W)
    r = (g[:, None] * M + np.arange(M)).reshape(-1)
    ua = np.mod(ta[None, :] + u1[g, None], 1.0).reshape(-1)
    ub = np.mod(tb[None, :] + v2[g, None], 1.0).reshape(-1)
    d_ref, q_ref = hb._guided_rays(np.repeat(tri[g], M), ua, ub)
    assert np.array_equal(D[r], d_ref) and np.array_equal(W[r], q_ref)
    rest = np.setdiff1d(np.arange(H * M), r)
    assert (D[rest] == 7.0).all() and (W[rest] == 1.0).all()  # the other hits' rays are left alone
    assert q_ref.min() < 0.5 < 2.0 < q_ref.max()  # weights far from 1: the warp is not the identity
    unguided = np.flatnonzero(~hb.guided)[:1]
    with pytest.raises(ValueError, match=f"face {int(unguided[0])} has no guide"):
        ray_kernels.guided_rays_native(M, np.zeros(1, np.int64), unguided, u1[:1], v2[:1], ta, tb, hb._guide_row,
                                       *hb._guide_cdf, hb.guide_mass, hb.frames, D, W)
    F = hb._guide_row.shape[0]
    for h, t in ((np.array([-1]), gf[:1]), (np.zeros(1, np.int64), np.array([F])), (np.zeros(1, np.int64), np.array([-1]))):
        with pytest.raises(ValueError, match=rf"accepted: hits >= 0, tri in \[0, {F}\)"):  # no out-of-range read or write in the C
            ray_kernels.guided_rays_native(M, h, t, u1[:1], v2[:1], ta, tb, hb._guide_row, *hb._guide_cdf, hb.guide_mass,
                                           hb.frames, D, W)


def test_probe_of_a_subset_equals_the_whole_mesh_probe_at_those_faces():
    mesh, whole = _guided_box()
    F = mesh.faces.shape[0]
    rng = np.random.default_rng(1)
    with RayCaster(mesh, workers=1) as caster:
        full = whole.face_openness(caster).copy()
        part = HitBounce(mesh, 2, 8, 3, 1, 1, estimator="auto")
        first, second = rng.choice(F, 200, replace=False), rng.choice(F, 300, replace=False)
        part.prepare(caster, first)
        part.prepare(caster, np.concatenate([second, first]))  # overlapping batches, repeats: each face once
        rays = part.probe_rays
    hit = np.union1d(first, second)
    assert np.isnan(part._face_open).sum() == (~part.probed).sum() > 0  # faces nobody asked for stay unprobed
    assert part.probed[hit].all() and rays == FACE_PROBE_RAYS * int(part.probed.sum()) < FACE_PROBE_RAYS * F
    assert np.array_equal(part._face_open[part.probed], full[part.probed])  # the same rays per face
    assert np.array_equal(part.guided[hit], whole.guided[hit]) and part.guided[hit].any()
    g = hit[part.guided[hit]]
    assert np.array_equal(part.guide_mass[part._guide_row[g]], whole.guide_mass[whole._guide_row[g]])
    for a, b in zip(part._guide_cdf, whole._guide_cdf):
        assert np.array_equal(a[part._guide_row[g]], b[whole._guide_row[g]])
    log = part.take_probe_log()
    assert int(log["probe_rays"]) == rays and np.array_equal(np.sort(log["probed_faces"].numpy()), np.flatnonzero(part.probed))
    assert np.array_equal(np.sort(log["guided_faces"].numpy()), g)
    assert int(part.take_probe_log()["probe_rays"]) == 0  # taken once


def test_glossy_one_bounce_is_the_same_on_one_and_two_workers():
    mesh = builtin("cornell_box", "small")
    kw = dict(bands=3, bands_out=3, samples=64, bounces=1, seed=4, vertices=torch.arange(0, mesh.num_vertices, 5))
    a = precompute_glossy(mesh, **kw, run=RunOptions(chunk_size=150, workers=1, progress=False))
    b = precompute_glossy(mesh, **kw, run=RunOptions(chunk_size=150, workers=2, progress=False))
    assert a.meta["hit_guide"]["faces_guided"] > 0 and a.meta["hit_guide"]["faces_probed"] > 0
    assert torch.equal(a.data, b.data)
    assert a.meta["hit_guide"] == b.meta["hit_guide"] and a.meta["hit_choice_rays"] == b.meta["hit_choice_rays"]
    assert GUIDE_GRID[0] * GUIDE_GRID[1] == FACE_PROBE_RAYS


def test_thinned_probe_of_curved_faces_is_the_full_probe_at_its_cells_and_unbiased():
    """probe_rays=8 (:data:`FIRST_PROBE_RAYS`, what a run takes): every face probes 8 of the 32 cells
    first (every 4th from a hashed first), each the full probe's ray for that cell; curved faces (the
    sphere) stop there, so their open fraction is a stratified estimate of the same quantity: its mean
    over 24 seeds equals the full probe's mean over 24 other seeds within 3σ, over the sphere's lower
    faces (partly blocked by the ground); faces that may be guided (≥ 8 coplanar: the ground) go on
    to every cell — bit for bit the full probe — unless their 8 rays all left (read as open, 1); the
    rays counted are 32 per completed face and 8 per other."""
    mesh = builtin("sphere_on_plane", "small")
    F = mesh.faces.shape[0]
    with RayCaster(mesh, workers=1) as caster:
        full, thin = HitBounce(mesh, 2, 4, 0, 1, 1, estimator="auto"), HitBounce(mesh, 2, 4, 0, 1, 1, estimator="auto", probe_rays=8)
        of, ot = full.face_openness(caster), thin.face_openness(caster)
        flat = full._coplanar()[0] >= 8
        assert flat.any() and (~flat).any()
        done = thin._cells.all(1)  # every cell traced (completed, or topped up for a neighbour's guide)
        assert (done <= flat).all() and (done & flat).any() and (~done & flat).any()
        opened = flat & (ot == 1.0)  # flat faces read open: their 8 first rays all left (then maybe topped up)
        assert np.array_equal(of[flat & ~opened], ot[flat & ~opened]) and (of[opened] >= 0.25).all()
        assert (of[flat & ~opened] < 1.0).all() and opened.any() and (flat & ~opened).any()
        assert (thin._cells[~done].sum(1) == 8).all() and np.array_equal(thin._opened[thin._cells], full._opened[thin._cells])
        assert (thin._opened[flat & ~done][thin._cells[flat & ~done]]).all()  # the stopped flat faces: all 8 rays left
        assert thin.probe_rays == 32 * int(done.sum()) + 8 * int((~done).sum()) and full.probe_rays == 32 * F
        c = mesh.vertices.to(torch.float64)[mesh.faces.to(torch.int64)].mean(1)
        low = np.flatnonzero(~flat & (c[:, 2].numpy() < 0.5 * float(c[:, 2].max())) & (of < 1.0))  # the sphere's lower faces
        assert low.size > 50
        a = np.stack([HitBounce(mesh, 2, 4, s, 1, 1, estimator="auto", probe_rays=8).face_openness(caster)[low] for s in range(24)])
        b = np.stack([HitBounce(mesh, 2, 4, 100 + s, 1, 1, estimator="auto").face_openness(caster)[low] for s in range(24)])
    ma, mb = a.mean(1), b.mean(1)  # [24] per seed, over the faces
    se = np.sqrt(ma.var(ddof=1) / 24 + mb.var(ddof=1) / 24)
    assert se > 0 and abs(ma.mean() - mb.mean()) <= 3 * se, (ma.mean(), mb.mean(), se)
    assert ma.var() > mb.var()  # fewer rays: a noisier estimate (the check is not vacuous)
    with pytest.raises(ValueError, match="probe_rays=5"):
        HitBounce(mesh, 2, 4, 0, 1, 1, estimator="auto", probe_rays=5)


def test_diffuse_one_bounce_is_the_same_on_one_and_two_workers_and_any_chunking():
    """sphere_on_plane (flat ground: guided faces, full probe; curved sphere: the 8-ray probe): one
    bounce under 'auto' on 1 worker in chunks of 500 and on 2 workers in chunks of 1300 gives the same
    bits, the same faces probed and guided and the same probe rays (local: each face once)."""
    from prt_torch.transfer.diffuse import FIRST_PROBE_RAYS, precompute_diffuse

    m = builtin("sphere_on_plane", "small")
    kw = dict(seed=3, shadows="always", fold_albedo=False, bounce_tol=0.0)
    a = precompute_diffuse(m, 2, 64, 1, run=RunOptions(chunk_size=500, workers=1, progress=False), **kw)
    b = precompute_diffuse(m, 2, 64, 1, run=RunOptions(chunk_size=1300, workers=2, progress=False), **kw)
    assert torch.equal(a.data, b.data)
    assert a.meta["hit_guide"] == b.meta["hit_guide"] and a.meta["hit_choice_rays"] == b.meta["hit_choice_rays"]
    g = a.meta["hit_guide"]
    assert g["faces_guided"] > 0 and g["first_probe_rays"] == FIRST_PROBE_RAYS
    assert FIRST_PROBE_RAYS * g["faces_probed"] < a.meta["hit_choice_rays"] < FACE_PROBE_RAYS * g["faces_probed"]  # both kinds


def test_vertex_transfer_reproduces_rows_whose_hits_land_on_curved_faces():
    """vertex_transfer (the validator's re-run of chosen vertices) takes the run's probe (8 rays on
    the curved sphere, every cell on the ground): its rows equal the precompute's, at ground vertices
    whose first hits land on the sphere and sphere vertices whose hits land on the ground."""
    from prt_torch.transfer.diffuse import precompute_diffuse, vertex_transfer

    m = builtin("sphere_on_plane", "small")
    tr = precompute_diffuse(m, 2, 64, bounces=1, seed=4, bounce_tol=0.0, fold_albedo=False, shadows="always",
                            run=RunOptions(progress=False))
    z = m.vertices[:, 2]
    r = torch.linalg.norm(m.vertices[:, :2], dim=1)
    ground = torch.nonzero((z.abs() < 1e-9) & (r > 0.3) & (r < 1.2))[:3, 0]
    sphere = torch.nonzero((z > 0.05) & (z < 0.3))[:3, 0]
    idx = torch.cat([ground, sphere])
    assert idx.numel() == 6
    T0, TB = vertex_transfer(m, idx, 2, 64, 4, 1)
    torch.testing.assert_close((T0 + TB.sum(1)[:, 0]).float(), tr.data[idx], rtol=1e-5, atol=1e-6)  # grey: one channel


def test_face_openness_refuses_faces_outside_the_mesh():
    """``face_openness(caster, faces)``: an index outside [0, F) named in one line (not an IndexError mid-probe)."""
    mesh, hb = _guided_box()
    F = mesh.faces.shape[0]
    with RayCaster(mesh, workers=1) as caster:
        for bad in ([0, F], [-1, 3]):
            with pytest.raises(ValueError, match=rf"^faces holds indices in \[{min(bad)}, {max(bad)}\]; accepted: face indices in \[0, {F}\)$"):
                hb.face_openness(caster, np.array(bad))
        assert hb.probe_rays == 0  # nothing traced
