"""Encode kernels of issue 15 against brute force and other libraries.

* ``kmeans.lloyd`` (Hamerly-bounded) against a plain float64 Lloyd written here (every distance
  evaluated), on data with duplicates, exact ties and more clusters than distinct points;
* ``kmeans.assign(second=True)`` against sorted brute-force distances (numpy);
* ``kmeans.kmeans_pp`` (pruned) against the unpruned greedy k-means++ written here (same draws);
* ``affine.classify_all`` and ``_Work.classify_candidates`` against explicit projections;
* the one-cluster randomized PCA path against a matrix with known singular values and vectors;
* iterative CPCA's stage schedule (early stop, restart from static) never above static.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs import kmeans as km
from prt_torch.codecs.affine import classify_all
from prt_torch.codecs.synthetic import transfer_like


def plain_lloyd(X, C, iters, w=None):
    """Reference Lloyd in float64: all P×K distances every iteration, empty clusters keep their centre."""
    X = X.double()
    C = C.double().clone()
    w = torch.ones(X.shape[0], dtype=torch.float64) if w is None else w.double()
    for _ in range(iters):
        lab = torch.cdist(X, C).argmin(1)
        ws = torch.zeros(C.shape[0], dtype=torch.float64).index_add_(0, lab, w)
        s = torch.zeros_like(C).index_add_(0, lab, X * w[:, None])
        C = torch.where(ws[:, None] > 0, s / ws.clamp_min(1e-300)[:, None], C)
    lab = torch.cdist(X, C).argmin(1)
    return C, lab


def blobs(P, D, K0, seed, spread=0.05):
    g = torch.Generator().manual_seed(seed)
    centres = torch.randn(K0, D, generator=g, dtype=torch.float64) * 3
    lab = torch.randint(0, K0, (P,), generator=g)
    return centres[lab] + spread * torch.randn(P, D, generator=g, dtype=torch.float64)


@pytest.mark.parametrize("seed,weighted", [(0, False), (1, True), (2, False)])
def test_bounded_lloyd_equals_plain_lloyd(seed, weighted):
    X = blobs(1500, 12, 25, seed, spread=0.6)
    X[:40] = X[40:80]  # exact duplicates
    g = torch.Generator().manual_seed(seed + 10)
    w = torch.rand(X.shape[0], generator=g, dtype=torch.float64) + 0.1 if weighted else None
    C0 = X[torch.randperm(X.shape[0], generator=g)[:30]]
    res = km.lloyd(X, C0, 60, 0.0, w)
    assert res["repaired"] == 0
    C_ref, lab_ref = plain_lloyd(X, C0, res["n_iter"], w)
    assert torch.equal(res["labels"], lab_ref)
    assert torch.allclose(res["centers"], C_ref, atol=1e-10)
    d2 = (X - C_ref[lab_ref]).square().sum(1)
    assert math.isclose(res["inertia"], float((d2 * (w if w is not None else 1)).sum()), rel_tol=1e-10)
    # the bounds skipped most distance rows once the clusters settled
    assert res["distance_rows"] < res["n_iter"] + 1


def test_bounded_lloyd_float32_matches_float64_reference():
    X = transfer_like(3000, 5, 9, seed=4)
    g = torch.Generator().manual_seed(0)
    C0 = X[torch.randperm(3000, generator=g)[:40]]
    res = km.lloyd(X, C0, 15, 0.0)
    C_ref, lab_ref = plain_lloyd(X, C0, res["n_iter"])
    # float32 distances: labels may differ only where two centres are equally near to ~1e-5
    D = torch.cdist(X.double(), C_ref)
    own = D.gather(1, res["labels"][:, None]).squeeze(1)
    assert bool((own <= D.min(1).values * (1 + 1e-4) + 1e-6).all())
    assert (res["labels"] != lab_ref).float().mean() < 1e-3
    assert math.isclose(res["inertia"], float(D.min(1).values.square().sum()), rel_tol=1e-4)


def test_bounded_lloyd_repairs_degenerate_clusters():
    # 6 distinct points, 8 clusters, two centres start on the same point: empties are repaired
    base = torch.tensor([[0.0, 0], [1, 0], [0, 1], [5, 5], [5, 6], [9, 0]], dtype=torch.float64)
    X = base.repeat_interleave(torch.tensor([5, 5, 5, 5, 5, 5]), 0)
    C0 = torch.cat([base[[0, 0]], base[1:], base[[3]]])  # 8 centres, duplicated seeds
    res = km.lloyd(X, C0, 20, 0.0)
    counts = torch.bincount(res["labels"], minlength=8)
    assert int(counts.min()) >= 1
    assert res["repaired"] >= 2
    # every point is at its own centre or shares it with identical points: error ≤ brute force of the centres
    D = torch.cdist(X, res["centers"])
    assert res["inertia"] <= float(D.min(1).values.square().sum()) + 1e-9


def test_assign_second_matches_sorted_distances_with_ties():
    g = torch.Generator().manual_seed(3)
    X = torch.randint(-3, 4, (500, 6), generator=g).double()  # integer grid: many exact ties
    C = torch.randint(-3, 4, (20, 6), generator=g).double()
    C[5] = C[4]  # duplicate centre: every point has a tie between 4 and 5 or elsewhere
    lab, d2, d2b = km.assign(X, C, second=True)
    ref = np.sort(((X.numpy()[:, None] - C.numpy()[None]) ** 2).sum(-1), axis=1)
    np.testing.assert_allclose(d2.numpy(), ref[:, 0], atol=1e-9)
    np.testing.assert_allclose(d2b.numpy(), ref[:, 1], atol=1e-9)
    own = ((X - C[lab]) ** 2).sum(1)
    np.testing.assert_allclose(own.numpy(), ref[:, 0], atol=1e-9)
    lab1, d1 = km.assign(X, C)
    assert torch.equal(d1, d2)
    _, _, inf = km.assign(X, C[:1], second=True)  # one centre: no second
    assert bool(torch.isinf(inf).all())


def unpruned_kmeans_pp(X, K, gen, trials):
    """Greedy k-means++ with every distance evaluated (the reference for the pruned version)."""
    P = X.shape[0]
    wd = torch.ones(P, dtype=torch.float64)
    chosen = [int(torch.multinomial(wd / wd.sum(), 1, generator=gen)[0])]
    d2 = ((X - X[chosen[0]]) ** 2).sum(1)
    for _ in range(1, K):
        cand = torch.multinomial(d2 / d2.sum(), trials, replacement=True, generator=gen)
        dc = torch.cdist(X, X[cand]).square()
        new = torch.minimum(d2[:, None], dc)
        best = int(torch.argmin(new.sum(0)))
        d2 = new[:, best]
        chosen.append(int(cand[best]))
    return torch.tensor(chosen)


def test_pruned_kmeans_pp_draws_the_same_seeds():
    X = blobs(2000, 10, 40, 5, spread=0.3)
    ours = km.kmeans_pp(X, 40, torch.Generator().manual_seed(7))
    ref = unpruned_kmeans_pp(X, 40, torch.Generator().manual_seed(7), 2 + int(math.log(40)))
    assert torch.equal(ours, ref)


def brute_errors(X, means, basis):
    """e_k(x) = ||x − x0||² − Σ ((x − x0)·b_i)² for all points and clusters, float64 numpy."""
    X, means, basis = X.double().numpy(), means.numpy(), basis.numpy()
    R = X[:, None, :] - means[None]  # [P, K, D]
    proj = np.einsum("pkd,knd->pkn", R, basis)
    return (R ** 2).sum(-1) - (proj ** 2).sum(-1)


def test_classify_all_matches_explicit_projections():
    g = torch.Generator().manual_seed(0)
    P, D, K, n = 700, 15, 9, 3
    X = torch.randn(P, D, generator=g, dtype=torch.float64)
    means = torch.randn(K, D, generator=g, dtype=torch.float64)
    basis = torch.linalg.qr(torch.randn(K, D, n, generator=g, dtype=torch.float64))[0].transpose(1, 2).contiguous()
    E = brute_errors(X, means, basis)
    lab, emin, top = classify_all(X, X.square().sum(1), means, basis, top=4)
    np.testing.assert_array_equal(lab.numpy(), E.argmin(1))
    np.testing.assert_allclose(emin.numpy(), E.min(1), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(top.numpy(), np.argsort(E, axis=1, kind="stable")[:, :4])
    # float32 data, no vectors (plain distances)
    lab0, e0, _ = classify_all(X.float(), X.float().square().sum(1), means, basis[:, :0])
    E0 = brute_errors(X, means, basis[:, :0])
    assert (lab0.numpy() == E0.argmin(1)).mean() > 0.999
    np.testing.assert_allclose(e0.numpy(), E0.min(1), rtol=1e-4, atol=1e-4)


def test_classify_candidates_matches_restricted_argmin():
    from prt_torch.codecs.cpca import _Work

    g = torch.Generator().manual_seed(1)
    P, D, K, n, L = 600, 12, 10, 2, 3
    X = torch.randn(P, D, generator=g, dtype=torch.float64)
    labels = torch.randint(0, K, (P,), generator=g)
    work = _Work(X, None, K)
    work.set_labels(labels)
    means = torch.randn(K, D, generator=g, dtype=torch.float64)
    basis = torch.linalg.qr(torch.randn(K, D, n, generator=g, dtype=torch.float64))[0].transpose(1, 2).contiguous()
    cand = torch.stack([torch.cat([torch.tensor([k]), torch.randperm(K, generator=g)[:L - 1]]) for k in range(K)])
    lab, emin = work.classify_candidates({"means": means, "basis": basis}, cand)
    E = brute_errors(X, means, basis)
    allowed = cand[labels].numpy()  # [P, L] candidate clusters of each point's cluster
    Ec = np.take_along_axis(E, allowed, 1)
    np.testing.assert_allclose(emin.numpy(), Ec.min(1), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(lab.numpy(), allowed[np.arange(P), Ec.argmin(1)])


@pytest.mark.parametrize("solver", ["auto", "krylov"])
def test_one_cluster_randomized_pca_recovers_known_spectrum(solver):
    # P·D > 2^23, tall (P ≥ 4D): the auto solver takes the randomized GEMM path (krylov: the block
    # Krylov one); singular values and right singular vectors known by construction (centred
    # orthonormal U, orthonormal V)
    P, D, n = 13200, 640, 8
    g = torch.Generator().manual_seed(2)
    U = torch.randn(P, 24, generator=g, dtype=torch.float64)
    U = torch.linalg.qr(U - U.mean(0))[0]
    V = torch.linalg.qr(torch.randn(D, 24, generator=g, dtype=torch.float64))[0]
    s = torch.logspace(2, 0, 24, dtype=torch.float64)
    X = ((U * s) @ V.T + torch.linspace(-1, 1, D, dtype=torch.float64)).float()
    c = codecs.get("pca", vectors=n, solver=solver).fit(X)
    assert c.fit_info_["solver"] == ("randomized" if solver == "auto" else solver)
    np.testing.assert_allclose(np.array(c.fit_info_["eigenvalues"]), (s[:n] ** 2).numpy(), rtol=1e-4)
    # the same subspace as the known top-n singular vectors: cosines of the principal angles are 1
    sv = np.linalg.svd(c.basis_[0].double().numpy() @ V[:, :n].numpy(), compute_uv=False)
    assert sv.min() > 1 - 1e-5
    # the error is the discarded energy
    assert math.isclose(c.fit_info_["se"], float((s[n:] ** 2).sum()), rel_tol=1e-3)


@pytest.mark.parametrize("seed", [0, 1])
def test_iterative_schedule_never_above_static(seed):
    X = transfer_like(500, 4, 9, seed=seed + 20).double()
    kw = dict(clusters=8, vectors=3, seed=seed)
    st = codecs.get("cpca_static", **kw).fit(X)
    fast = codecs.get("cpca_iterative", **kw).fit(X)
    full = codecs.get("cpca_iterative", stage_tol=0.0, **kw).fit(X)
    for c in (fast, full):
        assert c.fit_info_["se"] <= st.fit_info_["se"] * (1 + 1e-9)
    # stage_tol = 0: the stages before the last run until no label changes or `iterations` rounds
    for s in full.fit_info_["stages"][:-1]:
        assert len(s["changes"]) == 10 or s["changes"][-1] == 0
    assert sum(len(s["changes"]) for s in fast.fit_info_["stages"]) <= sum(len(s["changes"]) for s in full.fit_info_["stages"])


def test_stage_tol_is_validated():
    with pytest.raises(ValueError, match="stage_tol"):
        codecs.get("cpca_iterative", stage_tol=-1.0).fit(transfer_like(200, 2, 4, seed=0))


def test_linear_is_the_gemm_with_bias_whichever_kernel_the_machine_chose():
    """kmeans.linear = X Wᵀ + b (oneDNN's linear or addmm, chosen by measurement) against a
    float64 product, for a large product (the chosen kernel) and a small one (addmm)."""
    g = torch.Generator().manual_seed(3)
    choice = km.gemm_choice()
    assert choice["backend"] in ("onednn", "mkl") and choice["how"]
    for m in (4096, 16):
        X, W, b = torch.randn(m, 640, generator=g), torch.randn(96, 640, generator=g), torch.randn(96, generator=g)
        ref = X.double() @ W.double().T + b.double()
        out = km.linear(X, W, b)
        assert out.shape == (m, 96) and out.dtype == torch.float32
        assert torch.allclose(out.double(), ref, rtol=1e-5, atol=1e-4)


@pytest.mark.parametrize("near", [2, 3, 5])
def test_near_centre_bounds_prune_and_keep_plain_lloyd_labels(monkeypatch, near):
    """The per-centre bounds of the next-nearest centres (``kmeans.NEAR``, Elkan 2003 Lemma 2 on
    those centres, Hamerly 2010 on the rest) give plain Lloyd's labels and centres (the float64
    brute force above) on overlapping blobs where they prune, for 1, 2 and 4 tracked centres."""
    X = blobs(3000, 16, 60, 7, spread=1.2)  # overlapping blobs: many points near a boundary
    g = torch.Generator().manual_seed(3)
    C0 = X[torch.randperm(X.shape[0], generator=g)[:80]]
    monkeypatch.setattr(km, "NEAR", near)
    res = km.lloyd(X, C0, 25, 0.0)
    C_ref, lab_ref = plain_lloyd(X, C0, res["n_iter"])
    assert torch.equal(res["labels"], lab_ref)
    assert torch.allclose(res["centers"], C_ref, atol=1e-10)
    assert res["distance_rows"] < res["n_iter"] + 1  # it pruned


def test_near_centre_bounds_skip_more_rows_than_one_lower_bound(monkeypatch):
    """NEAR = 3 (2nd and 3rd nearest centres bounded by their own shifts) evaluates fewer
    distance rows than NEAR = 2 on the same run, with the same labels."""
    X = blobs(3000, 16, 60, 7, spread=1.2)
    g = torch.Generator().manual_seed(3)
    C0 = X[torch.randperm(X.shape[0], generator=g)[:80]]
    out = {}
    for near in (2, 3):
        monkeypatch.setattr(km, "NEAR", near)
        out[near] = km.lloyd(X, C0, 25, 0.0)
    assert torch.equal(out[2]["labels"], out[3]["labels"])
    assert out[3]["distance_rows"] < out[2]["distance_rows"]
