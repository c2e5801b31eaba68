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
