"""Issue 42 part 2 ("every kind near its rays"): the faster formulations of the transport tables
and of the bounce estimator against the direct ones, and their unbiasedness."""
import math

import numpy as np
import pytest
import torch

from prt_torch import brdf as B
from prt_torch.scene import RayCaster, builtin, sphere_on_plane_visibility
from prt_torch.transfer.diffuse import HitBounce, face_points, unshadowed_transfer
from prt_torch.transfer.transport import HORIZON_EPS, _chunk_transport, cube_directions, icosphere_directions


def _dense_transport(caster, brdf, points, normals, frames, texels, views, mat_index):
    """Green 2005 eq. 1.2 on every (view, texel) pair: f_r(ω_i, ω_o) V max(n·ω_i, 0), the BRDF
    evaluated on the whole [k, J, P] grid (the formulation before issue 42), zero at views with cos θ_o ≤
    ``transport.HORIZON_EPS`` (lying in the tangent plane: below the horizon, as the tables have it)."""
    cos = normals @ texels.T
    W = cos.clamp_min(0)
    i, j = torch.nonzero(cos > 0, as_tuple=True)
    occ = caster.occluded(points[i], texels[j], normals=normals[i])
    W[i[occ], j[occ]] = 0.0
    wi = torch.einsum("kab,pb->kpa", frames, texels)
    wo = torch.einsum("kab,jb->kja", frames, views)
    b = brdf if mat_index is None else brdf.select(mat_index).view(-1, 1, 1)
    return b.eval(wi[:, None, :, :], wo[:, :, None, :]) * W[:, None, :] * (wo[:, :, 2:] > HORIZON_EPS)


def test_transport_chunk_equals_the_dense_grid():
    """The table evaluated only where it can be non-zero (upper view, visible texel) equals the
    BRDF on the whole grid times W, for a shared and a per-vertex BRDF, zeros included (to the
    last bits of torch's vectorised pow: 2e-14 measured)."""
    mesh = builtin("sphere_on_plane")
    idx = torch.arange(0, mesh.num_vertices, 5)
    texels, _ = cube_directions(4)
    texels = texels.reshape(-1, 3)
    views = icosphere_directions(1)
    frames = mesh.frames()[idx]
    with RayCaster(mesh, workers=1) as c:
        args = (c, mesh.vertices[idx], mesh.normals[idx], frames, texels, views)
        brdf = B.AshikhminShirley(30.0, 10.0, rs=0.2, rd=0.3)
        got = _chunk_transport(c, brdf, *args[1:], None, True)
        ref = _dense_transport(*args[:1], brdf, *args[1:], None)
        assert got.shape == ref.shape and torch.equal(got == 0, ref == 0)
        assert torch.allclose(got, ref, rtol=1e-13, atol=0) and float(ref.max()) > 0.1
        V = mesh.num_vertices
        per_vertex = B.Phong(torch.linspace(2.0, 40.0, V, dtype=torch.float64))
        mi = torch.arange(V)[idx]
        got = _chunk_transport(c, per_vertex, *args[1:], mi, True)
        ref = _dense_transport(*args[:1], per_vertex, *args[1:], mi)
        assert torch.equal(got == 0, ref == 0) and torch.allclose(got, ref, rtol=1e-13, atol=0)
        half = _chunk_transport(c, per_vertex, *args[1:], mi, True, torch.float16)  # the stored dtype, rounded once
        assert half.dtype == torch.float16 and torch.equal(half, got.to(torch.float16))
    frac = float((ref > 0).double().mean())
    assert 0.1 < frac < 0.4  # about a quarter of the grid is evaluated


@pytest.mark.parametrize("estimator", ["plain", "control", "auto"])
def test_hit_estimator_unbiased_and_exact_where_open(estimator):
    """The bounce estimator's x⁰(q) at hit points (compiled rays and SH sums): on the ground beside
    the sphere its mean over seeds is Y00 · the closed-form visible fraction within 3σ (plus the
    tessellation's 3e-3); on top of the sphere, whose hemisphere is open, the control variate is
    the exact unshadowed transfer (1e-13)."""
    mesh = builtin("sphere_on_plane", "medium")
    c, fn, _ = face_points(mesh)
    r = torch.linalg.norm(c[:, :2], dim=1)
    ground = (fn[:, 2] > 0.999) & (c[:, 2].abs() < 1e-9)
    picks = [int(torch.nonzero(ground & ((r - d).abs() < 0.08))[0]) for d in (0.6, 1.0, 2.0)]
    top = int(torch.argmax(c[:, 2]))
    tri = np.array(picks + [top])
    bary = np.full((4, 3), 1.0 / 3.0)
    ka, kb = np.arange(4), np.zeros(4, np.int64)
    Y00 = 0.5 / math.sqrt(math.pi)
    with RayCaster(mesh, workers=1) as caster:
        runs = torch.stack([HitBounce(mesh, 3, 16, s, 1, 1, estimator=estimator).values(caster, tri, bary, ka, kb)[:, 0, 0]
                            for s in range(48)])  # [S, 4, 9]
    mean, se = runs.mean(0), runs.std(0) / math.sqrt(runs.shape[0])
    ref = torch.tensor([Y00 * sphere_on_plane_visibility(float(r[t])) for t in picks], dtype=torch.float64)
    assert ((mean[:3, 0] - ref).abs() <= 3 * se[:3, 0] + 3e-3 * ref).all(), (mean[:3, 0], ref, se[:3, 0])
    assert float(se[:3, 0].min()) > 0
    open_ref = unshadowed_transfer(fn[top:top + 1], 3)[0]
    if estimator in ("control", "auto"):  # auto: the top face is open (face_openness 1), so the control variate
        assert float((runs[:, 3] - open_ref).abs().max()) <= 1e-13
    else:
        assert ((mean[3] - open_ref).abs() <= 3 * se[3] + 1e-12).all()


def test_raycaster_start_is_the_lazy_pool_started_early():
    """start() runs the worker processes before the first batch: the same answers as tracing in
    this process alone; a no-op with one worker."""
    mesh = builtin("sphere_on_plane")
    rng = np.random.default_rng(0)
    o = (rng.random((3000, 3)) * [6, 6, 3] - [3, 3, 0]).astype(np.float32)
    d = rng.standard_normal((3000, 3))
    d = (d / np.linalg.norm(d, axis=1, keepdims=True)).astype(np.float32)
    with RayCaster(mesh, workers=1) as one:
        assert one.start() is one and one._pool is None
        ref = one.trace(o, d, "occluded")
    with RayCaster(mesh, workers=2, min_parallel_rays=1) as two:
        two.start()
        assert two._pool is not None and len(two._pool) == 1
        assert np.array_equal(two.trace(o, d, "occluded"), ref) and 0 < ref.mean() < 1
