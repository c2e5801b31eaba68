"""prt_torch.scene: mesh loading/repair, normals and frames, built-ins, Embree ray casting."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import trimesh

from prt_torch.scene import (
    RayCaster,
    builtin,
    geodesic_sphere,
    list_builtins,
    load_mesh,
    load_scene,
    make_mesh,
    tangent_frames,
    vertex_normals,
)


# ------------------------------------------------------------------------------ built-ins
def test_geodesic_sphere_is_closed_outward_unit():
    for f in (1, 3, 7):
        v, fa = geodesic_sphere(f)
        assert v.shape == (10 * f * f + 2, 3) and fa.shape == (20 * f * f, 3)
        np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0, atol=1e-12)
        m = trimesh.Trimesh(v, fa, process=False)
        assert m.is_watertight and m.is_winding_consistent
        assert m.volume > 0  # outward orientation
        assert m.euler_number == 2


@pytest.mark.parametrize("name", list_builtins())
def test_builtins_small_are_valid(name):
    m = builtin(name, "small")
    assert 800 <= m.num_vertices <= 3000, m.num_vertices
    assert m.vertices.dtype == torch.float64 and m.faces.dtype == torch.int64 and m.albedo.dtype == torch.float32
    assert abs(float(m.vertices[:, 2].min())) < 1e-9  # stands on z = 0
    F = m.frames()
    torch.testing.assert_close(F @ F.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand_as(F), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(F), torch.ones(m.num_vertices, dtype=torch.float64), atol=1e-12, rtol=0)
    assert float(m.albedo.min()) >= 0 and float(m.albedo.max()) <= 1
    assert len(m.content_hash()) == 32


def test_builtin_sizes_and_cornell_colours():
    counts = {s: builtin("sphere_on_plane", s).num_vertices for s in ("small", "medium")}
    assert 8000 <= counts["medium"] <= 12000 and counts["small"] < counts["medium"]
    c = builtin("cornell_box:small")
    red = (c.albedo[:, 0] > 0.5) & (c.albedo[:, 1] < 0.3)
    green = (c.albedo[:, 1] > 0.5) & (c.albedo[:, 0] < 0.3)
    assert red.any() and green.any()
    # the red wall is the x = -1 wall, facing +x (inward)
    assert torch.allclose(c.vertices[red, 0], torch.tensor(-1.0, dtype=torch.float64))
    assert torch.allclose(c.normals[red], torch.tensor([1.0, 0, 0], dtype=torch.float64).expand(int(red.sum()), 3))
    with pytest.raises(ValueError, match="scene"):
        builtin("teapot")
    with pytest.raises(ValueError, match="size"):
        builtin("convex", "huge")


# ------------------------------------------------------------------------------ normals and frames
def test_angle_weighted_normals_at_cube_corner_are_symmetric():
    # each cube face is split into 2 triangles, so a corner touches 1 or 2 triangles per face:
    # the angle-weighted normal is still the diagonal (each face contributes angle π/2)
    box = trimesh.creation.box()
    n = vertex_normals(box.vertices, box.faces, "angle")
    np.testing.assert_allclose(np.abs(n), 1 / math.sqrt(3), atol=1e-12)
    np.testing.assert_allclose(np.sign(n), np.sign(box.vertices), atol=0)
    # area weighting is biased by the triangulation (independent check that the two differ)
    na = vertex_normals(box.vertices, box.faces, "area")
    assert np.abs(np.abs(na) - 1 / math.sqrt(3)).max() > 1e-3


def test_sphere_normals_are_radial():
    v, f = geodesic_sphere(8)
    n = vertex_normals(v, f)
    assert np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", n, v), -1, 1))).max() < 0.5


def test_tangent_frame_rule():
    n = np.array([[0, 0, 1.0], [1.0, 0, 0], [-1.0, 0, 0], [0, 1.0, 0], [0.6, 0, 0.8]])
    t, b = tangent_frames(n)
    np.testing.assert_allclose(t[0], [1, 0, 0]) and np.testing.assert_allclose(b[0], [0, 1, 0])
    np.testing.assert_allclose(t[1], [0, 1, 0])  # singular for x̂: falls back to ŷ
    np.testing.assert_allclose(np.cross(t, b), n, atol=1e-12)
    np.testing.assert_allclose(t[4], [0.8, 0, -0.6], atol=1e-12)  # x̂ projected onto the tangent plane


# ------------------------------------------------------------------------------ loading and repair
@pytest.mark.parametrize("suffix", [".obj", ".ply", ".stl", ".off", ".glb"])
def test_load_formats_roundtrip(tmp_path, suffix):
    src = trimesh.creation.icosphere(2)
    path = tmp_path / f"s{suffix}"
    src.export(path)
    m = load_mesh(path)
    assert m.num_faces == src.faces.shape[0]
    assert m.num_vertices == src.vertices.shape[0]  # STL's split vertices merged back
    np.testing.assert_allclose(np.sort(m.vertices.numpy(), axis=0), np.sort(src.vertices, axis=0), atol=1e-5)
    assert m.meta["source"] == str(path)


def test_repair_counts_and_up_axis(tmp_path):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 0, 0], [5, 5, 5], [0, 0, 1.0], [2, 0, 0]], float)
    f = np.array([[0, 1, 2], [0, 3, 5], [1, 1, 2], [0, 1, 6]])  # dup vertex 3, degenerate face, collinear face
    m = make_mesh(v, f)
    r = m.meta["repair"]
    assert r["duplicate_vertices_merged"] == 1
    assert r["degenerate_faces_removed"] == 2  # the repeated-index face and the zero-area (collinear) face
    assert r["unreferenced_vertices_removed"] == 2  # (5,5,5) and (2,0,0) once its face is gone
    assert m.num_faces == 2 and m.num_vertices == 4
    # up='y': the file's +y becomes world +z
    path = tmp_path / "y.obj"
    trimesh.Trimesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1.0, 0]]), np.array([[0, 1, 2]]), process=False).export(path)
    my = load_mesh(path, up="y")
    assert torch.allclose(my.vertices[:, 2].max(), torch.tensor(1.0, dtype=torch.float64))
    assert torch.allclose(my.vertices[:, 1].abs().max(), torch.tensor(0.0, dtype=torch.float64))


def test_vertex_colours_become_linear_albedo(tmp_path):
    src = trimesh.creation.icosphere(1)
    src.visual.vertex_colors = np.tile(np.array([[255, 128, 0, 255]], np.uint8), (src.vertices.shape[0], 1))
    path = tmp_path / "c.ply"
    src.export(path)
    m = load_mesh(path)
    srgb = 128 / 255
    lin = ((srgb + 0.055) / 1.055) ** 2.4  # sRGB transfer function, independent of the implementation
    torch.testing.assert_close(m.albedo[0], torch.tensor([1.0, lin, 0.0]), atol=1e-6, rtol=0)
    assert load_mesh(path, albedo=0.3).albedo.max() == pytest.approx(0.3)


def test_bad_mesh_inputs(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_mesh(tmp_path / "missing.obj")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 99\n\x00\x13garbage")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)
    pts = tmp_path / "points.ply"
    trimesh.PointCloud(np.random.default_rng(0).normal(size=(10, 3))).export(pts)
    with pytest.raises(ValueError, match="face"):
        load_mesh(pts)
    with pytest.raises(ValueError, match="suffix"):
        load_mesh(bad.with_suffix(".txt").write_text("x") and bad.with_suffix(".txt"))
    with pytest.raises(ValueError, match="no faces"):
        make_mesh(np.zeros((3, 3)), np.zeros((0, 3), int))
    v = np.array([[0, 0, 0], [1, 0, 0], [0, np.nan, 0]])
    with pytest.raises(ValueError, match="NaN"):
        make_mesh(v, [[0, 1, 2]])
    with pytest.raises(ValueError, match="zero area"):
        make_mesh([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2]])
    with pytest.raises(ValueError, match="indices"):
        make_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]])
    with pytest.raises(ValueError, match="albedo"):
        make_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], albedo=1.5)
    with pytest.raises(ValueError, match="neither"):
        load_scene("no_such_scene")
    assert load_scene("convex:small").name == "convex"


# ------------------------------------------------------------------------------ ray casting
def _quad(z=1.0, half=10.0):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return make_mesh(v, np.array([[0, 1, 2], [0, 2, 3]]))


def test_intersect_matches_analytic_plane_hits():
    m = _quad()
    rc = RayCaster(m)
    rng = np.random.default_rng(1)
    o = np.c_[rng.uniform(-1, 1, (500, 2)), np.zeros(500)]
    d = rng.normal(size=(500, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.3
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    hit, tri, bary, t = rc.intersect(o, d)
    assert hit.all()
    t_ref = 1.0 / d[:, 2]  # distance to z = 1
    np.testing.assert_allclose(t.numpy(), t_ref, rtol=1e-5, atol=1e-5)
    V, F = m.vertices.numpy(), m.faces.numpy()
    tri_v = V[F[tri.numpy()]]
    u, w = bary[:, 0].numpy()[:, None], bary[:, 1].numpy()[:, None]
    p = (1 - u - w) * tri_v[:, 0] + u * tri_v[:, 1] + w * tri_v[:, 2]
    np.testing.assert_allclose(p, o + t_ref[:, None] * d, atol=1e-4)
    # occluded agrees; a miss reports tri -1; tfar shorter than the plane distance is unoccluded
    assert rc.occluded(o, d).all()
    assert not rc.occluded(o, -d).any()
    h2, tri2, _, t2 = rc.intersect(o, -d)
    assert not h2.any() and (tri2 == -1).all() and torch.isinf(t2).all()
    assert not rc.occluded(o, d, tfar=0.5).any()


def test_offset_scales_with_scene_and_avoids_self_hits():
    small, big = builtin("convex"), builtin("convex")
    big.vertices = big.vertices * 1000.0
    a, b = RayCaster(small), RayCaster(big)
    assert b.eps == pytest.approx(1000 * a.eps)
    for m, rc in ((small, a), (big, b)):
        # rays leaving each vertex along its normal never hit the (convex) surface
        assert not rc.occluded(m.vertices, m.normals, normals=m.normals).any()
        # rays into the surface always do
        assert rc.occluded(m.vertices, -m.normals, normals=m.normals).all()


def test_worker_processes_give_identical_results():
    m = builtin("bumpy_sphere")
    rng = np.random.default_rng(3)
    o = rng.normal(size=(30000, 3)) * 0.7 + np.array([0, 0, 1.0])
    d = rng.normal(size=(30000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    one = RayCaster(m, workers=1)
    with RayCaster(m, workers=2, min_parallel_rays=1000) as two:
        assert torch.equal(one.occluded(o, d), two.occluded(o, d))
        for x, y in zip(one.intersect(o, d), two.intersect(o, d)):
            assert torch.equal(x, y)
        assert two._pool is not None and len(two._pool) == 1
    assert two._pool is None
