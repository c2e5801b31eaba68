"""The compiled ray generation of the uniform diffuse precompute (``transfer.ray_kernels``)
against numpy's own formulation of the same ray set."""
import numpy as np
import pytest
import torch

from prt_torch.transfer import ray_kernels
from prt_torch.transfer.diffuse import DiffuseSampler


def _reference(cos, origins, dirs):
    """(i, j) of cos > 0 in row-major order by np.nonzero, the origins and directions gathered."""
    i, j = np.nonzero(cos > 0)
    return i.astype(np.int64), j.astype(np.int64), origins[i], dirs[j]


def _native_or_skip():
    if ray_kernels.upper_rays(np.ones((1, 1)), np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32)) is None:
        pytest.skip("no compiled ray generation (no C compiler, or PRT_TORCH_NATIVE=0)")


@pytest.mark.parametrize("threads", [1, 2])
def test_upper_rays_equal_numpy_nonzero(threads):
    _native_or_skip()
    rng = np.random.default_rng(0)
    k, N = 37, 50
    cos = rng.standard_normal((k, N))
    cos[3] = -np.abs(cos[3])  # a vertex with no direction above its plane
    cos[5, ::7] = 0.0  # exactly tangent directions are not traced (cos > 0, strictly)
    cos[6, 2] = -0.0
    cos[7] = np.abs(cos[7]) + 1e-300  # every direction
    o = rng.standard_normal((k, 3)).astype(np.float32)
    d = rng.standard_normal((N, 3)).astype(np.float32)
    work = {}
    for call in range(2):  # the second call rewrites the same buffers
        got = ray_kernels.upper_rays(cos, o, d, threads=threads, work=work)
        for g, r, name in zip(got, _reference(cos, o, d), "ijod"):
            assert g.dtype == r.dtype and g.shape == r.shape, name
            assert np.array_equal(g, r), name
    assert got[0].shape[0] == int((cos > 0).sum()) and 3 not in got[0] and (got[0] == 7).sum() == N
    small = ray_kernels.upper_rays(cos[:4], o[:4], d, work=work)  # fewer rays into the kept buffers
    assert all(np.array_equal(g, r) for g, r in zip(small, _reference(cos[:4], o[:4], d)))
    assert ray_kernels.upper_rays(cos[:0], o[:0], d)[0].shape == (0,)


def test_upper_rays_refuses_mismatched_shapes():
    _native_or_skip()
    with pytest.raises(ValueError, match=r"origins \(4, 3\).*\[5, 3\]"):
        ray_kernels.upper_rays(np.ones((5, 6)), np.zeros((4, 3), np.float32), np.zeros((6, 3), np.float32))


def test_sampler_rays_same_with_and_without_the_compiled_pass(monkeypatch):
    """DiffuseSampler.rays (uniform) gives the same arrays through the kernel (with and without
    reused buffers) and through numpy (PRT_TORCH_NATIVE=0)."""
    _native_or_skip()
    s = DiffuseSampler(3, 256, 0, "uniform")
    g = torch.Generator().manual_seed(1)
    n = torch.nn.functional.normalize(torch.randn(90, 3, generator=g, dtype=torch.float64), dim=1)
    p = torch.randn(90, 3, generator=g, dtype=torch.float64)
    fused = [a.copy() for a in s.rays(p, n, None, 1e-4)]
    kept = [a.copy() for a in s.rays(p, n, None, 1e-4, reuse=True)]
    monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    assert ray_kernels.upper_rays(np.ones((1, 1)), np.zeros((1, 3), np.float32), np.zeros((1, 3), np.float32)) is None
    plain = s.rays(p, n, None, 1e-4, reuse=True)
    for a, b, c in zip(fused, kept, plain):
        assert a.dtype == c.dtype and np.array_equal(a, c) and np.array_equal(b, c)
    import pickle

    s2 = pickle.loads(pickle.dumps(s))  # a sampler sent to a Ray task: without its kept buffers
    assert s._work and s2._work == {} and np.array_equal(s2.dirs32, s.dirs32)


# ------------------------------------------------------------------ the qmc set (issue 42 part 2)
def _qmc_textbook(s, normals, ids):
    """The qmc directions as the class docstring writes them (the density p(z) = ¾ + z/2), with
    libm's cos/sin of φ itself: a' = (a + u1) mod 1, z = max(2a' / (¾ + √(9/16 + a')), 1e-12),
    r = √(1 − z²), φ = 2π((b + u2) mod 1), d = r cos φ t + r sin φ b + z n."""
    from prt_torch.scene.mesh import tangent_frames
    from prt_torch.transfer.diffuse import _hash_uniform

    keys = np.asarray(ids, np.int64)
    zero = np.zeros_like(keys)
    u1 = _hash_uniform(s.seed, keys, zero, 1 << 20)[:, None]
    u2 = _hash_uniform(s.seed, keys, zero, (1 << 20) + 1)[:, None]
    a = (s.base[None, :, 0] + u1) % 1.0
    phi = 2 * np.pi * ((s.base[None, :, 1] + u2) % 1.0)
    z = np.maximum(2 * a / (0.75 + np.sqrt(0.5625 + a)), 1e-12)
    r = np.sqrt(1 - z * z)
    n = np.asarray(normals, np.float64)
    t, b = tangent_frames(n)
    d = (r * np.cos(phi))[..., None] * t[:, None] + (r * np.sin(phi))[..., None] * b[:, None] + z[..., None] * n[:, None]
    return d.reshape(-1, 3), z.reshape(-1)


@pytest.mark.parametrize("samples", [1, 7, 256])
def test_qmc_rays_compiled_equal_numpy_and_textbook(monkeypatch, samples):
    """The compiled qmc pass gives numpy's bits (the same float64 operations), and both give the
    textbook directions (cos φ, sin φ by libm) to float rounding: z exactly, d within 2 float32 ulps,
    unit length, z = n·d, origins repeated per vertex."""
    _native_or_skip()
    s = DiffuseSampler(3, samples, 5, "qmc", "auto")
    g = torch.Generator().manual_seed(2)
    n = torch.nn.functional.normalize(torch.randn(60, 3, generator=g, dtype=torch.float64), dim=1)
    n[0] = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)  # the tangent rule's fallback axis
    p = torch.randn(60, 3, generator=g, dtype=torch.float64)
    ids = np.arange(1000, 1060)
    fused = [a.copy() for a in s.chunk_rays(p, n, 1e-3, ids=ids, reuse=True)]
    monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    plain = s.chunk_rays(p, n, 1e-3, ids=ids)
    for a, b in zip(fused, plain):
        assert a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b)
    o, d, z = fused
    d_ref, z_ref = _qmc_textbook(s, n.numpy(), ids)
    M = s.M
    assert o.shape == (60 * M, 3) and np.array_equal(z, z_ref)
    assert np.abs(d - d_ref).max() <= 2 * 2.0 ** -24
    assert np.allclose(np.linalg.norm(d.astype(np.float64), axis=1), 1, atol=1e-6)
    assert np.allclose(np.einsum("ij,ij->i", np.repeat(n.numpy(), M, 0), d.astype(np.float64)), z, atol=1e-6)
    o_ref = (p + 1e-3 * n).numpy().astype(np.float32)
    assert np.array_equal(o, np.repeat(o_ref, M, 0))
    i, j, o2, d2, z2 = DiffuseSampler(3, samples, 5, "qmc").rays(p, n, None, 1e-3, ids=ids)  # the index form, same rays
    assert np.array_equal(i, np.repeat(np.arange(60), M)) and np.array_equal(j, np.tile(np.arange(M), 60))
    assert np.array_equal(d2, d) and np.array_equal(z2, z)


@pytest.mark.parametrize("estimator", ["auto", "control", "plain"])
def test_select_rays_equal_the_bincount_choice(estimator):
    """select_rays gives diffuse._chunk's numpy choice: per vertex open where the weighted visible
    rays are at least half (bincount sums), then the blocked rays of open vertices and the
    visible rays of the others."""
    _native_or_skip()
    rng = np.random.default_rng(3)
    k, M = 41, 16
    z = rng.random(k * M)
    hit = rng.random(k * M) < rng.random(k).repeat(M)  # vertices from open to enclosed
    hit[:M] = False  # an open vertex
    hit[M:2 * M] = True  # an enclosed one
    i = np.repeat(np.arange(k), M)
    w = 0.125 * z
    if estimator == "auto":
        open_ref = np.bincount(i, weights=np.where(hit, 0.0, w), minlength=k) >= 0.5 * np.bincount(i, weights=w, minlength=k)
    else:
        open_ref = np.full(k, estimator == "control")
    open_v, sel = ray_kernels.select_rays(z, hit, M, 0.125, estimator)
    assert np.array_equal(open_v, open_ref)
    assert np.array_equal(sel, np.flatnonzero(hit == open_ref[i]))
    assert open_v[0] == (estimator != "plain") and (open_v[1] == (estimator == "control"))
    with pytest.raises(ValueError, match="M=5"):
        ray_kernels.select_rays(z, hit, 5, 0.125, estimator)


@pytest.mark.parametrize("bands", [1, 2, 5, 9, 32])
def test_sh_accumulate_equals_eval_sh_index_add(bands):
    """The fused pass equals eval_sh (the torch recurrence, an independent code) summed by
    index_add to float64 rounding; the closed forms of band 1 check the convention."""
    from prt_torch.sh import eval_sh

    _native_or_skip()
    rng = np.random.default_rng(bands)
    k, M = 30, 7
    d = rng.standard_normal((k * M, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d = d.astype(np.float32)
    z = rng.random(k * M)
    sel = np.sort(rng.choice(k * M, 120, replace=False))
    got = ray_kernels.sh_accumulate(k, M, sel, d, z, 0.3, bands)
    dn = torch.nn.functional.normalize(torch.from_numpy(d[sel]).double(), dim=1)  # as the kernel takes them
    Y = eval_sh(dn, bands, check=False, backend="torch")
    ref = torch.zeros(k, bands * bands, dtype=torch.float64).index_add_(
        0, torch.from_numpy(sel // M), Y * torch.from_numpy(0.3 * z[sel])[:, None]).numpy()
    assert np.abs(got - ref).max() <= 1e-13 * max(1.0, np.abs(ref).max())
    one = ray_kernels.sh_accumulate(1, 1, np.array([0]), np.array([[0.6, 0.0, 0.8]], np.float32), None, 1.0, max(bands, 2))
    c = np.sqrt(3 / (4 * np.pi))  # y_1-1 = c y, y_10 = c z, y_11 = c x (graphics convention, no phase)
    x, y, zz = np.array([0.6, 0.0, 0.8], np.float32).astype(np.float64)
    x, y, zz = np.array([x, y, zz]) / np.sqrt(x * x + y * y + zz * zz)
    assert np.allclose(one[0, :4], [0.5 / np.sqrt(np.pi), c * y, c * zz, c * x], rtol=0, atol=1e-15)
    with pytest.raises(ValueError, match="bands=33"):
        ray_kernels.sh_accumulate(k, M, sel, d, z, 0.3, 33)
    with pytest.raises(ValueError, match="ray indices"):
        ray_kernels.sh_accumulate(k, M, np.array([k * M]), d, z, 0.3, bands)


@pytest.mark.parametrize("estimator", ["auto", "control", "plain"])
def test_qmc_transfer_same_with_and_without_the_compiled_passes(monkeypatch, estimator):
    """The shadowed qmc transfer of a self-shadowing scene through the compiled passes (rays,
    choice, fused SH sum) equals numpy/torch's formulation (the same rays, eval_sh, index_add) to
    float64 rounding (eval_sh by sphericart, which normalises the float32 directions as the kernel
    does), and the choice of 'auto' is the same (no vertex switches branch)."""
    from prt_torch.scene import RayCaster, builtin
    from prt_torch.sh.basis import _have_sphericart_cached
    from prt_torch.transfer.diffuse import transfer_at_points

    _native_or_skip()
    if not _have_sphericart_cached():
        pytest.skip("eval_sh without sphericart takes float32 directions unnormalised (1e-8 apart)")
    mesh = builtin("sphere_on_plane")
    idx = torch.arange(0, mesh.num_vertices, 7)
    with RayCaster(mesh, workers=1) as c:
        args = (c, mesh.vertices[idx], mesh.normals[idx], 4, 96, 3)
        fused = transfer_at_points(*args, estimator=estimator, ids=idx)
        monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
        plain = transfer_at_points(*args, estimator=estimator, ids=idx)
    assert torch.allclose(fused, plain, rtol=0, atol=1e-13)
    assert float((fused[:, 0] - plain[:, 0]).abs().max()) < 1e-13 and float(plain.abs().max()) > 0.1
