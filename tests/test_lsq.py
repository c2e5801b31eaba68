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


def test_glossy_ten_bands_against_brute_force():
    """The known silently-wrong extreme: glossy exit transfer at 10 bands (Phong s=4, 1024
    samples, least squares). Against a brute-force hemisphere integral of BRDF × light × cos
    (no SH on the BRDF side; the light is exactly 2 bands), the exact inverse is tens of percent
    off; the precompute's own choice of rcond is within ~2%."""
    import math
    import warnings

    from prt_torch import relight
    from prt_torch.scene import load_scene
    from prt_torch.transfer import precompute_glossy

    mesh = load_scene("convex", size="small")
    vids = torch.arange(0, mesh.num_vertices, 211)[:8]
    br = B.Phong(4.0, ks=1.0, kd=0.0)
    L = torch.zeros(1, 100, dtype=torch.float64)
    L[0, 0], L[0, 2], L[0, 3] = 1.0, 0.6, 0.3  # 2 bands, positive everywhere
    views = torch.nn.functional.normalize(torch.tensor([[0.3, 0.2, 0.9], [-0.5, 0.1, 0.8], [0.7, -0.6, 0.4]],
                                                       dtype=torch.float64), dim=1)
    g = torch.Generator().manual_seed(1)
    N = 200_000
    s = torch.randn(N, 3, generator=g, dtype=torch.float64)
    s = s / s.norm(dim=1, keepdim=True)
    s[:, 2] = s[:, 2].abs()
    F = mesh.frames()[vids].double()
    ref = torch.tensor([[float((br.eval(s, v.expand(N, 3)) * (eval_sh(s @ F[p], 2) @ L[0, :4]) * s[:, 2]).mean() * 2 * math.pi)
                         for p in range(len(vids))] for v in views])
    errs = {}
    for label, kw in (("exact", {"rcond": 1e-300}), ("chosen", {})):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            tr = precompute_glossy(mesh, 10, 10, brdf=br, samples=1024, vertices=vids, shadows=False, **kw)
        out = torch.stack([relight.glossy(tr.data.double(), L, v.expand(len(vids), 3), tr.meta["out_index"])[:, 0] for v in views])
        errs[label] = float((out - ref).norm() / ref.norm())
        if label == "chosen":
            assert tr.meta["rcond_chosen"] is not None and "predicted error" in tr.meta["rcond_decision"]
    # the exact inverse's figure is rounding noise amplified by the Gram's condition (3e12 at 10 bands): a
    # 8e-16 change in B (the isotropic projection, issue 42) moved it from above 0.3 to 0.275 — "tens of percent"
    assert errs["exact"] > 0.2 and errs["chosen"] < 0.03, errs
