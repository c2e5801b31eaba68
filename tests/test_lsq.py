"""The least-squares projection's regularisation is chosen from the error it predicts for the
samples used: exact where harmless, regularised at 10 bands (where the exact inverse is
known to be tens of percent off against a path tracer)."""
import torch

from prt_torch import brdf as B
from prt_torch.sh import eval_sh, hemisphere_gram, hemisphere_projector
from prt_torch.transfer.lsq import choose_rcond, projection_error


def test_ten_bands_are_regularised_and_five_are_not():
    r10 = choose_rcond(B.Phong(4.0), 10, 10, 1024)
    assert r10["exact_error"] > 0.5 and r10["rcond"] is not None and r10["predicted_error"] < 0.15
    r5 = choose_rcond(B.Phong(4.0), 5, 5, 1024)
    assert r5["exact_error"] is not None and r5["predicted_error"] <= r5["exact_error"] + 1e-9 and r5["exact_error"] < 0.05


def test_prediction_equals_a_direct_monte_carlo_computation():
    """ε from projection_error against the same quantity computed here from scratch: an
    unoccluded vertex's Monte Carlo T (plain i.i.d. directions, another seed) through the
    projected BRDF matrix, error of exit radiance measured by quadrature over the hemisphere."""
    bo = bi = 4
    Bz = B.brdf_matrix(B.Phong(8.0), bo, bi, projection="zero")
    P = hemisphere_projector(bi, "least_squares")
    G = P @ Bz @ P
    M = P @ Bz
    g = torch.Generator().manual_seed(5)
    N = 1 << 16
    s = torch.randn(N, 3, generator=g, dtype=torch.float64)
    s = s / s.norm(dim=1, keepdim=True)
    up = s[:, 2] > 0
    Y = eval_sh(s[up], bi)
    T_hat = (Y * (4 * torch.pi / N)).T @ Y
    E = G @ T_hat - M
    A = hemisphere_gram(bo)
    direct = float(torch.sqrt(torch.trace(E.T @ A @ E) / torch.trace(M.T @ A @ M)))
    ours = projection_error(Bz, bo, bi, N, seed=0, rcond=None, normals=1, directions=(s, torch.full((N,), 4 * torch.pi / N)))
    assert abs(ours - direct) < 1e-5 * direct and direct > 0  # rounding amplified by cond(A) ~ 1e5
    # the engine's stratified set has a smaller quadrature error than i.i.d. directions
    assert projection_error(Bz, bo, bi, N, seed=0, rcond=None, normals=1) < direct
