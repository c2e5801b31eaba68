"""prt_torch.relight reference paths against explicit per-vertex formulas (small V, loops in
the test only)."""
import pytest
import torch

from prt_torch import relight, sh
from prt_torch.transfer import tents as mrt


def _views(V, seed, below=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(V, 3, generator=g, dtype=torch.float64)
    d[:, 2] = d[:, 2].abs() + 0.05
    d[:below, 2] = -d[:below, 2]
    return d / d.norm(dim=-1, keepdim=True)


def test_diffuse_dot_product():
    g = torch.Generator().manual_seed(0)
    T = torch.randn(6, 16, generator=g)
    L = torch.randn(3, 16, generator=g)
    out = relight.diffuse(T, L)
    assert out.shape == (6, 3) and torch.allclose(out, torch.stack([T @ L[c] for c in range(3)], 1), atol=1e-6)
    T3 = torch.randn(6, 3, 16, generator=g)
    assert torch.allclose(relight.diffuse(T3, L), torch.stack([(T3[:, c] * L[c]).sum(-1) for c in range(3)], 1), atol=1e-6)


def test_glossy_evaluates_exit_sh_at_local_view():
    g = torch.Generator().manual_seed(1)
    M = torch.randn(5, 24, 25, generator=g, dtype=torch.float64)
    L = torch.randn(2, 25, generator=g, dtype=torch.float64)
    v = _views(5, 2, below=1)
    idx = [0, 1] + list(range(3, 25))  # (1,0) dropped
    out = relight.glossy(M, L, v, idx)
    for p in range(5):
        y = sh.eval_sh(v[p], 5)[idx]
        want = y @ (M[p] @ L.T) if v[p, 2] > 0 else torch.zeros(2, dtype=torch.float64)
        assert torch.allclose(out[p], want, atol=1e-12)


def test_mrt_four_taps_equal_dense_tent_sum():
    g = torch.Generator().manual_seed(3)
    M = 7
    A = torch.randn(4, M * M, 9, generator=g, dtype=torch.float64)
    L = torch.randn(3, 9, generator=g, dtype=torch.float64)
    v = _views(4, 4)
    out = relight.mrt(A, L, v)
    dense = mrt._tents_at_square(mrt.hemisphere_to_square(v), M)  # [V, M²] all tents
    want = torch.einsum("vj,vjc->vc", dense, A @ L.T)
    assert torch.allclose(out, want, atol=1e-12)


def test_kautz_rotate_multiply_dot():
    g = torch.Generator().manual_seed(5)
    V, n, m = 3, 3, 4
    R = sh.random_rotations(V, seed=6)
    T = torch.randn(V, n * n, n * n, generator=g, dtype=torch.float64)
    Bs = torch.randn(2, m * m, n * n, generator=g, dtype=torch.float64)
    mat = torch.tensor([1, 0, 1])
    L = torch.randn(1, n * n, generator=g, dtype=torch.float64)
    v = _views(V, 7)
    out = relight.kautz(T, relight.kautz_setup(R, n), Bs, L, v, material_index=mat)
    for p in range(V):
        lp = sh.rotation_matrix(R[p], n) @ (T[p] @ L[0])
        want = sh.eval_sh(v[p], m) @ Bs[mat[p]] @ lp
        assert torch.allclose(out[p, 0], want, atol=1e-12)
    with pytest.raises(ValueError, match="material_index"):
        relight.kautz(T, relight.kautz_setup(R, n), Bs, L, v)


def test_local_view_and_bad_light():
    F = sh.random_rotations(2, seed=1)
    pos = torch.zeros(2, 3, dtype=torch.float64)
    eye = torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)
    v = relight.local_view(F, pos, eye=eye)
    assert torch.allclose(v, F[:, :, 2], atol=1e-12)  # F @ (0,0,1)
    with pytest.raises(ValueError, match="light has shape"):
        relight.diffuse(torch.zeros(2, 9), torch.zeros(3, 16))
