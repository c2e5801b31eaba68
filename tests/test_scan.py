"""Scan-like meshes (scene.scan_like), mesh topology counts (edge_face_counts, vertex_classes,
mesh_features), vertex normals of cancelling faces, and the bounce hit-point offset (issue 37).

Counts are checked against brute force over the faces (Python sets, independent of the numpy
code); the hit-offset tests against analytic visibility between two plates."""
from __future__ import annotations

import math
from collections import Counter

import numpy as np
import pytest
import torch

from prt_torch.scene import (RayCaster, SCAN_FEATURES, builtin, edge_face_counts, make_mesh, mesh_features, normal_face_angles,
                             scan_like, vertex_classes, vertex_normals)
from prt_torch.transfer.diffuse import HIT_OFFSET, HitBounce, hit_ray_eps


def _brute_edges(faces) -> Counter:
    c: Counter = Counter()
    for f in np.asarray(faces).tolist():
        for a, b in ((f[0], f[1]), (f[1], f[2]), (f[2], f[0])):
            c[(min(a, b), max(a, b))] += 1
    return c


# ------------------------------------------------------------------------------ topology counts
def test_edge_face_counts_against_brute_force():
    m = scan_like(400, seed=3)
    e, cnt = edge_face_counts(m.faces.numpy(), m.num_vertices)
    brute = _brute_edges(m.faces.numpy())
    assert {tuple(x): int(c) for x, c in zip(e.tolist(), cnt)} == dict(brute)


def test_vertex_classes_of_a_hand_built_mesh():
    # a unit square (two faces), a fin on its diagonal (0,2) and a flap face reversed onto face 0
    v = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0.5, 0.5, 1.0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3], [0, 2, 4]])
    m = make_mesh(v, f, merge_duplicates=False)
    cls = vertex_classes(m)
    assert cls["nonmanifold"].tolist() == [True, False, True, False, False]  # edge (0,2) has three faces
    assert cls["boundary"].tolist() == [True, True, True, True, True]  # every vertex is on an open rim
    feats = mesh_features(m)
    assert feats["nonmanifold_edges"] == 1 and feats["boundary_edges"] == 6 and feats["faces"] == 3
    # folded: a vertex whose normal is >= 90 deg from one of its faces (the fin is vertical: 90 deg from the square's normal)
    ang = normal_face_angles(m)
    n = m.normals.numpy()
    for k in range(5):  # brute force over the vertex's faces
        fs = [face for face in f.tolist() if k in face]
        worst = max(math.degrees(math.acos(np.clip(n[k] @ _unit_normal(v, face), -1, 1))) for face in fs)
        assert abs(ang[k] - worst) < 1e-9
    assert cls["regular"].sum() == 0


def _unit_normal(v, face):
    c = np.cross(v[face[1]] - v[face[0]], v[face[2]] - v[face[0]])
    return c / np.linalg.norm(c)


def test_cancelling_faces_give_a_normal_independent_of_units():
    """A vertex only on a face and the same face reversed (a decimation's double sheet): its
    normal is the first face's, at any scale (the rounding residue of the sum pointed anywhere)."""
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [3, 3, 3], [4, 3, 3], [3, 4, 3.2]], float)
    f = np.array([[0, 1, 2], [1, 0, 2], [3, 4, 5]])
    for s in (1e-3, 0.08, 1.0, 1e3):
        n = vertex_normals(v * s, f)
        np.testing.assert_allclose(n[:3], np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-12)
    n2 = vertex_normals(v, f[[1, 0, 2]])  # the reversed face first: its normal
    np.testing.assert_allclose(n2[:3], np.tile([0.0, 0.0, -1.0], (3, 1)), atol=1e-12)
    # ordinary vertices are untouched: the angle-weighted normal of a single face is its normal
    np.testing.assert_allclose(n[3:], np.tile(_unit_normal(v, [3, 4, 5]), (3, 1)), atol=1e-12)


# ------------------------------------------------------------------------------ the generator
def test_scan_like_features_one_at_a_time():
    clean = scan_like(600, features="none")
    f0 = mesh_features(clean)
    assert f0["boundary_edges"] == 0 and f0["nonmanifold_edges"] == 0 and f0["sliver_faces"] == 0  # closed, manifold
    assert abs(float(clean.vertices[:, 2].min())) < 1e-12
    holes = mesh_features(scan_like(600, features="holes"))
    assert holes["boundary_edges"] > 0 and holes["nonmanifold_edges"] == 0
    hm = scan_like(600, features="holes")
    e, cnt = edge_face_counts(hm.faces.numpy(), hm.num_vertices)
    rim = hm.vertices.numpy()[e[cnt == 1].reshape(-1)]
    assert float(rim[:, 2].max()) < 0.1 * float(np.ptp(hm.vertices.numpy()[:, 2]))  # the holes are in the base
    fins = mesh_features(scan_like(600, features="fins", fins=7))
    assert fins["nonmanifold_edges"] == 7 and fins["boundary_edges"] == 14  # each fin: one edge with 3 faces, 2 open edges
    sl = mesh_features(scan_like(600, features="slivers", slivers=20))
    assert sl["boundary_edges"] == 0 and sl["nonmanifold_edges"] == 0 and sl["sliver_faces"] >= 20  # split without cracks
    dec = scan_like(600, features="decimate")
    fd = mesh_features(dec)
    assert fd["nonmanifold_edges"] > 0 and fd["folded_vertices"] > 0  # vertex clustering breaks topology
    assert 400 <= dec.num_vertices <= 900
    a, b = scan_like(600, seed=5), scan_like(600, seed=5)
    assert torch.equal(a.vertices, b.vertices) and torch.equal(a.faces, b.faces)
    assert not torch.equal(a.vertices[:50], scan_like(600, seed=6).vertices[:50])
    with pytest.raises(ValueError, match="'wrinkles'.*accepted"):
        scan_like(600, features="decimate,wrinkles")
    assert set(SCAN_FEATURES) == set(scan_like(600).meta["scan"]["features"])


def test_scan_blob_is_a_builtin():
    m = builtin("scan_blob")
    f = mesh_features(m)
    assert f["boundary_edges"] > 0 and f["nonmanifold_edges"] > 0 and f["sliver_faces"] > 0 and f["folded_vertices"] > 0


# ------------------------------------------------------------------------------ the bounce hit offset
def test_hit_ray_eps_rule():
    m = scan_like(300)
    assert hit_ray_eps(m) == pytest.approx(HIT_OFFSET * m.bbox_diagonal())
    # rays are traced in a frame centred on the mesh (RayCaster.center): the rule is the same 1000 units away
    far = make_mesh(m.vertices.numpy() + [1000.0, 0, 0], m.faces.numpy(), merge_duplicates=False)
    assert hit_ray_eps(far) == pytest.approx(hit_ray_eps(m), rel=1e-9)
    v = m.vertices.double()
    floor = 16 * 2.0 ** -23 * float((v - (v.amin(0) + v.amax(0)) / 2).abs().max())  # 16 ulps of the centred extent
    assert hit_ray_eps(far, 1e-9) == pytest.approx(floor, rel=1e-9) and floor > 1e-9 * far.bbox_diagonal()


def _plates(gap: float):
    """A floor [-1,1]² facing up and a ceiling the same size facing down at height ``gap``."""
    v = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    return make_mesh(np.concatenate([v, v + [0, 0, gap]]), np.concatenate([f, f[:, ::-1] + 4]), merge_duplicates=False)


@pytest.mark.parametrize("hit_offset,leaks", [(HIT_OFFSET, False), (1e-4, True)])
def test_hit_rays_do_not_leak_through_a_narrow_fold(hit_offset, leaks):
    """Hit points on the floor under a ceiling 1e-4 above it (3.5e-5 of the diagonal: a fold of a
    decimated scan). Analytic: the ceiling covers all but ~(gap/1)² of the cosine-weighted
    hemisphere of a point near the centre, so x⁰_00 = Y_00 (1 − F) ≈ 0. With the hit rays offset
    by 1e-4 of the diagonal (the rule before issue 37) the origin is above the ceiling and every
    ray sees the sky: x⁰_00 = Y_00."""
    m = _plates(1e-4)
    H = 64
    rng = np.random.default_rng(0)
    uv = rng.uniform(0.3, 0.35, (H, 2))  # near the centre of floor face 0
    bary = np.stack([1 - uv.sum(1) + 0.0, uv[:, 0], uv[:, 1]], 1)
    tri = np.zeros(H, np.int64)
    hb = HitBounce(m, 1, 64, 0, 1, 1, hit_offset)
    with RayCaster(m) as c:
        x0 = hb.values(c, tri, bary, np.arange(H), np.zeros(H, np.int64))[:, 0, 0, 0].numpy()  # [H]
    y00 = 0.5 / math.sqrt(math.pi)
    if leaks:
        np.testing.assert_allclose(x0, y00, rtol=1e-6)
    else:
        assert float(np.abs(x0).max()) < 0.02 * y00


@pytest.mark.parametrize("value", ["nan", "0.5", "-1e-6"])
def test_cli_refuses_a_bad_hit_offset(value, tmp_path, capsys):
    from prt_torch.cli import main as cli_main

    out = tmp_path / "t.prt"
    assert cli_main(["precompute", "bumpy_sphere", "--bounces", "1", "--samples", "8", "--no-progress", f"--hit-offset={value}",
                     "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    # the value as typed or as the number it was read as ('-1e-6' is a float since params.parse_value reads exponents)
    assert len(err) == 1 and "--hit-offset" in err[0] and (value in err[0] or repr(float(value)) in err[0]), err
    assert not out.exists()


def test_precompute_records_its_hit_offset():
    from prt_torch.transfer import precompute_diffuse

    m = scan_like(300)
    tr = precompute_diffuse(m, 2, 64, bounces=1, shadows="always", hit_offset=3e-6)
    assert tr.meta["hit_offset"] == 3e-6 and tr.meta["hit_eps"] == pytest.approx(hit_ray_eps(m, 3e-6))
