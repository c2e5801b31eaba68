"""The learned codec (``neural``, issue 43): reduction to PCA (Eckart–Young, numpy's SVD as the
reference), a non-linear manifold where it beats PCA with many more vectors, relighting from the
cached features against decode-then-relight, determinism under a seed, the never-worse-than-PCA
guard, divergence detection, bad input, save/load and the command line. Training kept tiny."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from prt_torch import codecs, io
from prt_torch.codecs import ConvergenceError, ConvergenceWarning


def rotating_lobe(P, bands=5, seed=0, sharpness=8.0):
    """SH coefficients of a zonal lobe (per-band factor exp(−l(l+1)/2s), rotated to its axis
    with f_lm = sqrt(4π/(2l+1)) h_l y_lm(μ)) whose axis circles at 60° from +z: a closed curve
    (a 1-D manifold) in R^{n²} that PCA needs 2(n−1) vectors to hold exactly."""
    from prt_torch import sh

    g = torch.Generator().manual_seed(seed)
    th = 2 * math.pi * torch.rand(P, generator=g, dtype=torch.float64)
    el = math.radians(60)
    mu = torch.stack([th.cos() * math.sin(el), th.sin() * math.sin(el), torch.full_like(th, math.cos(el))], 1)
    l = torch.tensor([math.isqrt(i) for i in range(bands * bands)], dtype=torch.float64)
    return (sh.eval_sh(mu, bands) * torch.exp(-l * (l + 1) / (2 * sharpness)) * torch.sqrt(4 * math.pi / (2 * l + 1))).float()


def low_rank(P=300, D=12, rank=3, noise=0.05, seed=0):
    g = torch.Generator().manual_seed(seed)
    X = torch.randn(P, rank, generator=g, dtype=torch.float64) @ torch.randn(rank, D, generator=g, dtype=torch.float64)
    return X + noise * torch.randn(P, D, generator=g, dtype=torch.float64) + 1.5


def pca_se(X, k):
    """Σ ||x − x̃||² of PCA with k vectors by numpy's SVD (Eckart–Young: the discarded singular values)."""
    Xc = np.asarray(X, np.float64)
    Xc = Xc - Xc.mean(0)
    s = np.linalg.svd(Xc, compute_uv=False)
    return float((s[k:] ** 2).sum())


TINY = {"width": 16, "depth": 1, "epochs": 60, "encode_iters": 20}


@pytest.mark.parametrize("optimizer, lr, epochs", [("adam", 1e-2, 400), ("lbfgs", 1.0, 40)])
def test_linear_h_with_k_equal_H_reduces_to_pca(optimizer, lr, epochs):
    """A linear decoder with k = H from a random start (not the PCA start) finds PCA's optimum:
    the same error (Eckart–Young, numpy) within 1e-4 relative and the same subspace."""
    X = low_rank(P=300, D=12, rank=3, noise=0.05)
    c = codecs.get("neural", latent=3, features=3, activation="linear", init="random", optimizer=optimizer, lr=lr,
                   epochs=epochs, patience=50, holdout=0.0, fit_dtype="float64", encode_iters=0)
    enc = c.fit_encode(X)
    assert not c.fit_info_["kept_pca_start"]  # the optimiser got there itself, not the guard
    ref = pca_se(X, 3)
    assert abs(c.fit_info_["se"] - ref) <= 1e-4 * ref
    Vt = np.linalg.svd(X.numpy() - X.numpy().mean(0), full_matrices=False)[2][:3]
    Q = np.linalg.qr(c.head_[0].double().numpy().T)[0]  # an orthonormal basis of span W
    cosines = np.linalg.svd(Vt @ Q, compute_uv=False)  # cosines of the principal angles
    assert cosines.min() > 1 - 1e-4
    assert enc.tensors["z"].shape == (300, 3)


def test_beats_pca_on_a_rotating_lobe():
    X = rotating_lobe(400)
    c = codecs.get("neural", latent=2, features=12, width=24, depth=2, epochs=150, batch_size=512, lr=3e-3)
    enc = c.fit_encode(X)
    rel = c.fit_info_["se"] / pca_se(X, 0)
    rel_pca = {k: pca_se(X, k) / pca_se(X, 0) for k in (2, 4, 6)}
    assert rel_pca[2] > 0.3 and rel_pca[6] > 1e-2  # PCA needs 8 vectors for this curve (4 bands x cos/sin)
    assert rel < 0.1 * rel_pca[6], (rel, rel_pca)  # 2 numbers per point beat 6 PCA weights by 10x
    # new points of the same curve, codes optimised for the fitted decoder
    Y = rotating_lobe(200, seed=7)
    assert c.squared_error(Y, c.encode(Y)) / pca_se(Y, 0) < rel_pca[4]
    assert c.storage(enc)["bytes"]["codes.z"] == 400 * 2 * 4  # 2 float32 per point


def test_relight_from_cached_features_equals_decode_then_relight():
    g = torch.Generator().manual_seed(3)
    X = rotating_lobe(300).repeat(1, 3) + 0.01 * torch.randn(300, 75, generator=g)  # a 3 x 25 matrix per point
    for clusters in (1, 3):
        c = codecs.get("neural", latent=3, features=8, clusters=clusters, **TINY)
        enc = c.fit_encode(X, matrix_shape=(3, 25))
        L = torch.randn(25, 3, generator=g)
        view = torch.randn(300, 3, generator=g)
        M = c.decode(enc).double().view(300, 3, 25) @ L.double()  # [P, 3, C]: decode, then relight
        # float32 rounding of either side: a few ulps of the sum of the terms' magnitudes
        # (|b| + Σ_j |h_j| |W_j|) |l|, with h = h(z_p) in float64 from the stored codes
        F = c.features_of(enc).double()
        lab = c.labels_of(enc)
        mag = (c.bias_.double()[lab] + torch.einsum("ph,phd->pd", F.abs(), c.head_.double().abs()[lab])).view(300, 3, 25)
        tol = 64 * 2.0 ** -24 * (mag @ L.double().abs())
        no_view = c.relight(enc, L)
        assert no_view.shape == (300, 3, 3) and bool(((no_view.double() - M).abs() <= tol).all())
        dense = c.relight(enc, L, view=view)
        assert bool(((dense.double() - torch.einsum("po,poc->pc", view.double(), M)).abs()
                     <= torch.einsum("po,poc->pc", view.double().abs(), tol)).all())
        r = c.relighter(enc, view)
        out = torch.empty(300, 3)
        assert torch.equal(r(L, out=out), dense)  # the prepared relight: the same bits
        enc.tensors["z"].mul_(0.5)  # an edit of the codes is seen (features recomputed)
        assert torch.equal(r(L), c.relight(enc, L, view=view)) and not torch.equal(r(L), dense)


def test_same_seed_same_bits_and_never_worse_than_pca():
    X = low_rank(P=200, D=10, rank=4, noise=0.3, seed=5).float()
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        a = codecs.get("neural", latent=2, features=6, seed=4, **TINY).fit(X)
        b = codecs.get("neural", latent=2, features=6, seed=4, **TINY).fit(X)
        d = codecs.get("neural", latent=2, features=6, seed=5, **TINY).fit(X)
    finally:
        torch.set_num_threads(n)
    ea, eb = a.encode(X), b.encode(X)
    assert torch.equal(ea.tensors["z"], eb.tensors["z"]) and torch.equal(a.head_, b.head_)
    assert all(torch.equal(x, y) for p, q in zip(a.layers_, b.layers_) for x, y in zip(p, q))
    assert not torch.equal(a.head_, d.head_)
    for c in (a, b, d):  # noise around a rank-4 subspace, 2 codes: never above PCA with 2 vectors
        assert c.fit_info_["se"] <= pca_se(X.double(), 2) * (1 + 1e-5)


def test_divergence_keeps_the_last_good_state():
    X = rotating_lobe(200)
    c = codecs.get("neural", latent=2, features=8, lr=10.0, epochs=30, width=16, depth=1)
    with pytest.warns(ConvergenceWarning, match=r"neural: training diverged \(.*lr=10\); kept the last good state"):
        c.fit(X)
    assert c.fit_info_["stopped"] == "diverged"
    assert math.isfinite(c.fit_info_["se"]) and c.fit_info_["se"] <= pca_se(X.double(), 2) * (1 + 1e-5)
    with pytest.raises(ConvergenceError, match="diverged"):
        codecs.get("neural", latent=2, features=8, lr=10.0, epochs=30, width=16, depth=1, strict=True).fit(X)


@pytest.mark.parametrize("params, match", [
    ({"latent": 0}, r"latent=0; accepted: an int in \[1, 256\]"),
    ({"features": 2000}, r"features=2000; accepted"),
    ({"depth": 17}, r"depth=17; accepted: an int in \[0, 16\]"),
    ({"latent": 8, "features": 4}, "features=4 is below latent=8"),
    ({"lr": 0.0}, r"lr=0.0; accepted: a real number in \(0, 10\]"),
    ({"code_dtype": "int8"}, "code_dtype='int8'; accepted"),
])
def test_bad_parameters_are_refused(params, match):
    with pytest.raises((ValueError, TypeError), match=match):
        codecs.get("neural", **params)


def test_bad_data_is_refused():
    X = low_rank(P=50, D=6).float()
    c = codecs.get("neural", latent=6, features=8)
    with pytest.raises(ValueError, match=r"latent=6 must be < D=6 \(n_features = 6\)"):
        c.fit(X)
    X[3, 2] = float("nan")
    with pytest.raises(ValueError, match=r"X has 1 non-finite value\(s\) \(NaN or Inf\), first at index \(3, 2\)"):
        codecs.get("neural", latent=2).fit(X)


def test_save_load_float16_codes_and_storage(tmp_path):
    X = rotating_lobe(300)
    c = codecs.get("neural", latent=2, features=10, code_dtype="float16", **TINY)
    enc = c.fit_encode(X)
    assert enc.tensors["z"].dtype == torch.float16
    st = c.storage(enc)
    assert st["bytes"]["codes.z"] == 300 * 2 * 2 and st["code_dtype"] == "float16"
    assert st["runtime_feature_bytes"] == 300 * 10 * 4 and st["runtime_bytes"] > st["bytes_codes"]
    # the error is measured with the stored (rounded) codes: decode reads them as they are
    assert c.fit_info_["se"] == pytest.approx(float((c.decode(enc).double() - X.double()).square().sum()), rel=1e-6)
    path = c.save(tmp_path / "n.prt", enc)
    c2, enc2 = codecs.load(path)
    assert torch.equal(c2.decode(enc2), c.decode(enc))
    L = torch.randn(25, 3)
    assert torch.equal(c2.relight(enc2, L), c.relight(enc, L))
    Y = rotating_lobe(50, seed=9)  # a loaded codec encodes new data as the fitted one does
    assert torch.equal(c2.encode(Y).tensors["z"], c.encode(Y).tensors["z"])
    tensors, meta = io.load(path)
    assert meta["codec"] == "neural" and tensors["codes.z"].dtype == torch.float16


def test_cli_compress_neural(tmp_path, capsys):
    from prt_torch.cli import main

    X = rotating_lobe(200).repeat(1, 2)
    src = tmp_path / "glossy.prt"
    io.save(src, {"data": X.view(200, 2, 25)}, kind="transfer/glossy", meta={"matrix_shape": [2, 25]})
    out = tmp_path / "n.prt"
    rc = main(["compress", str(src), "--codec", "neural", "--param", "latent=2", "--param", "features=6",
               "--param", "epochs=20", "--param", "width=8", "-o", str(out), "--json"])
    assert rc == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["matrix_shape"] == [2, 25]
    c, enc = codecs.load(out)
    assert c.latent == 2 and enc.tensors["z"].shape == (200, 2)
    bad = tmp_path / "bad.prt"
    assert main(["compress", str(src), "--codec", "neural", "--param", "latent=0", "-o", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "latent=0" in err and len(err.strip().splitlines()) == 1 and not bad.exists()


def test_early_stopping_on_held_out_points():
    """Noise has nothing to learn beyond PCA: the held-out loss stops falling and the fit stops
    `patience` epochs after its best, keeping the best epoch's state."""
    g = torch.Generator().manual_seed(11)
    X = torch.randn(300, 10, generator=g)
    c = codecs.get("neural", latent=2, features=8, width=16, depth=1, epochs=300, patience=5, holdout=0.2, lr=1e-2,
                   encode_iters=0).fit(X)
    fi = c.fit_info_
    assert fi["holdout_points"] == 60 and fi["train_points"] == 240 and fi["criterion"] == "holdout"
    assert fi["stopped"] == "early_stop" and fi["epochs"] == fi["best_epoch"] + 5 < 300
    hold = [h[1] for h in fi["history"]]  # epochs 1.. (epoch 0: the PCA start, its criterion the first best)
    assert min(hold[fi["best_epoch"]:]) >= fi["best_criterion"]
    assert fi["best_epoch"] == 0 or hold[fi["best_epoch"] - 1] == fi["best_criterion"]


def test_point_weights_decide_what_is_fitted():
    """The loss is Σ w_p ||x_p − x̃_p||², as for the other codecs: points of weight ~0 (large noise
    here) stop pulling the decoder away from the weighted points' curve."""
    X1 = rotating_lobe(200)
    g = torch.Generator().manual_seed(2)
    X = torch.cat([X1, 3.0 * torch.randn(200, 25, generator=g)])
    w = torch.cat([torch.ones(200), torch.full((200,), 1e-6)])
    kw = dict(latent=2, features=8, width=16, depth=1, epochs=80, encode_iters=0)
    plain = codecs.get("neural", **kw)
    weighted = codecs.get("neural", **kw)
    e_plain, e_weighted = plain.fit_encode(X), weighted.fit_encode(X, weights=w)
    err = [float((c.decode(e)[:200].double() - X1.double()).square().sum()) for c, e in ((plain, e_plain), (weighted, e_weighted))]
    assert err[1] < 0.1 * err[0]
    assert weighted.fit_info_["se"] == pytest.approx(float(((weighted.decode(e_weighted).double() - X.double()).square().sum(1)
                                                            * w.double()).sum()), rel=1e-6)


def test_report_lists_the_run_time_bytes_apart():
    """The harness report's "Stored vs run-time size" table: the cached features' bytes per vertex
    next to the stored ones, only for codecs that report them."""
    from prt_torch.harness.report import runtime_lines

    X = rotating_lobe(120)
    c = codecs.get("neural", latent=2, features=6, **TINY)
    st = c.storage(c.fit_encode(X))
    rec = {"codec": "neural", "setting_id": "neural-latent2", "params": {"latent": 2}, "bytes_per_vertex": st["bytes_per_point"],
           "storage": st, "psnr_lights_db": 30.0, "encode_s": 1.0}
    pca = {**rec, "codec": "pca", "setting_id": "pca-vectors2", "storage": {"bytes_total": 10}}
    lines = runtime_lines([pca, rec])
    row = [ln for ln in lines if ln.startswith("| neural")]
    assert len(row) == 1 and not any(ln.startswith("| pca") for ln in lines)
    assert f"| {(120 * 6 * 4 + (6 + 1) * 25 * 4) / 120:.1f} |" in row[0]  # features [P, H] + head and bias, float32
    assert runtime_lines([pca]) == []


def test_clustered_decoder_encodes_new_data_in_the_right_cluster():
    """With ``clusters`` > 1 each cluster has its own last layer; new points are coded in the
    cluster whose decoder reconstructs them best: three well separated copies of the lobe's curve
    (offsets of 20 along different axes) keep their points together, and new points are
    reconstructed about as well as the training points."""
    offsets = 20.0 * torch.eye(25)[:3]

    def data(P, seed):
        lab = torch.randint(0, 3, (P,), generator=torch.Generator().manual_seed(seed))
        return rotating_lobe(P, seed=seed) + offsets[lab], lab

    X, lab = data(450, 1)
    c = codecs.get("neural", latent=2, features=8, clusters=3, **TINY)
    enc = c.fit_encode(X)
    Y, lab_y = data(150, 2)
    ey = c.encode(Y)
    got = c.labels_of(ey)
    mapping = {int(t): int(got[lab_y == t].mode().values) for t in range(3)}
    assert sorted(mapping.values()) == [0, 1, 2] and all(bool((got[lab_y == t] == k).all()) for t, k in mapping.items())
    rel_train = c.squared_error(X, enc) / float((X - X.mean(0)).square().sum())
    rel_new = c.squared_error(Y, ey) / float((Y - Y.mean(0)).square().sum())
    assert rel_new < 3 * rel_train + 1e-4, (rel_new, rel_train)


def test_one_whole_decoder_per_cluster(tmp_path):
    """``cluster_decoder='full'``: each cluster has a decoder of its own (φ_k and W_k, b_k; weights
    ``[K, out, in]``). Three clusters on lobes of different sharpness (different curves, far apart):
    the decode equals eq. (1) evaluated point by point in numpy from the saved file's tensors with
    the point's own cluster's φ_k (an independent evaluation, not the tile-batched GEMMs), relighting
    from the cached features equals decode-then-relight to float32 rounding, the fit is no worse than
    static CPCA with k vectors (its start) and beats it on these curves; and with one cluster 'full'
    is 'head' bit for bit."""
    offsets = 20.0 * torch.eye(25)[:3]
    lab = torch.randint(0, 3, (240,), generator=torch.Generator().manual_seed(3))
    X = torch.empty(240, 25)
    for t, s in enumerate((4.0, 8.0, 16.0)):
        m = lab == t
        X[m] = rotating_lobe(int(m.sum()), seed=10 + t, sharpness=s) + offsets[t]
    c = codecs.get("neural", latent=1, features=6, clusters=3, cluster_decoder="full", **{**TINY, "epochs": 40})
    enc = c.fit_encode(X)
    assert [tuple(w.shape) for w, _ in c.layers_] == [(3, 16, 1), (3, 5, 16)]
    c.save(tmp_path / "n.prt", enc)
    tensors, meta = io.load(tmp_path / "n.prt")
    z = tensors["codes.z"].double().numpy()
    labels = tensors["codes.labels"].long().numpy()
    head, bias = tensors["model.head"].double().numpy(), tensors["model.bias"].double().numpy()
    Ws = [(tensors[f"model.layer{i}.weight"].double().numpy(), tensors[f"model.layer{i}.bias"].double().numpy()) for i in range(2)]
    ref, mag = np.empty((240, 25)), np.empty((240, 25))
    for p in range(240):  # eq. (1) for one point with its cluster's own φ_k and W_k
        k, a = labels[p], z[p]
        for w, b in Ws:
            a = w[k] @ a + b[k]
            a = a / (1 + np.exp(-a))  # SiLU
        h = np.concatenate([z[p], a])
        ref[p], mag[p] = bias[k] + h @ head[k], np.abs(bias[k]) + np.abs(h) @ np.abs(head[k])
    dec = np.asarray(c.decode(enc), np.float64)
    err = np.abs(dec - ref) / (mag * np.finfo(np.float32).eps)
    assert err.max() <= 64
    L = torch.randn(25, 3, generator=torch.Generator().manual_seed(4))
    r = torch.as_tensor(c.relight(enc, L)).double()
    exact = torch.as_tensor(dec) @ L.double()
    # float32 relighting's rounding scales with the magnitudes summed (|b_k| + |h| |W_k|) |l|, not with
    # the result (the head's entries reach ~3400 here, the radiance ~55): the decode's bound, per light
    bound = torch.as_tensor(mag) @ L.double().abs() * (64 * np.finfo(np.float32).eps)
    assert bool(((r - exact).abs() <= bound).all()), float(((r - exact).abs() / bound).max())
    cp = codecs.get("cpca_static", clusters=3, vectors=1)
    se_cpca = cp.squared_error(X, cp.fit_encode(X))
    assert c.fit_info_["se"] < 0.9 * se_cpca, (c.fit_info_["se"], se_cpca)
    one = [codecs.get("neural", latent=2, features=5, cluster_decoder=cd, **{**TINY, "epochs": 5}) for cd in ("head", "full")]
    outs = [torch.as_tensor(o.decode(o.fit_encode(X[:120]))) for o in one]
    assert torch.equal(outs[0], outs[1])
