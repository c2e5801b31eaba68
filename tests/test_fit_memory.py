"""Blockwise float64 accumulation in place of float64 copies (issue 42 §2/§3, "nothing held twice
that need not be"): the learned codec's moments and PCA start, the harness's random-light PSNR —
each against an independent float64 numpy evaluation at a small size."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs import neural
from prt_torch.harness import metrics as hm
from prt_torch.harness.timing import torch_threads


def test_centred_moments_match_numpy_float64(monkeypatch):
    """x̄, Σ ||x − x̄||² and Σ w ||x − x̄||² by float64 row blocks (a float32 signal far from the
    origin, blocks of 7 rows) equal numpy's float64 evaluation of their definitions."""
    g = torch.Generator().manual_seed(0)
    X = (100 + torch.randn(503, 37, generator=g)).to(torch.float32)
    w = torch.rand(503, generator=g) + 0.1
    Xn, wn = X.numpy().astype(np.float64), w.numpy().astype(np.float64)
    monkeypatch.setattr(neural, "CHUNK_ELEMENTS", 7 * 37)
    for wt in (None, w):
        mu, ss, ssw = neural._centred_moments(X, wt)
        mu_ref = Xn.mean(0) if wt is None else (Xn * wn[:, None]).sum(0) / wn.sum()
        r = ((Xn - mu_ref) ** 2).sum(1)
        np.testing.assert_allclose(mu.numpy(), mu_ref, rtol=1e-13)
        assert ss == pytest.approx(r.sum(), rel=1e-11)
        assert ssw == pytest.approx(r.sum() if wt is None else (r * wn).sum(), rel=1e-11)


def test_neural_float32_start_is_the_float64_optimum():
    """Above 2^23 values the learned codec's PCA start runs in float32 passes (float64 sums) on the
    scaled table itself: its squared error is PCA's float64 optimum with k vectors (Eckart–Young,
    numpy's eigh of the centred Gram matrix), and the fit's relative SE is numpy's float64
    evaluation of the decoded codes. (The memory itself is measured at the default benchmark's size:
    benchmarks/profile_neural_start.py; at this size the fit's fixed work buffers dominate it.)"""
    P, D, k = 600, 14000, 3  # 8.4 M values > 2^23: AffineCodec's auto float32 path, streamed by chunks
    g = torch.Generator().manual_seed(1)
    U = torch.randn(P, 8, generator=g) * torch.tensor([9.0, 7, 5, 3, 2, 1.5, 1, 0.5])
    X = (U @ torch.randn(8, D, generator=g) / math.sqrt(D) + 0.05 * torch.randn(P, D, generator=g) + 3.0).to(torch.float32)
    c = codecs.get("neural", latent=k, features=k, epochs=1, holdout=0.0, encode_iters=0)
    enc = c.fit_encode(X)
    info = c.fit_info_
    Y = X.numpy().astype(np.float64)
    Y -= Y.mean(0)
    tv = float((Y * Y).sum())
    lam = np.linalg.eigvalsh(Y @ Y.T)[-k:]
    optimum = tv - lam.sum()
    start = info["pca_loss"] * P * info["scale"] ** 2
    assert start == pytest.approx(optimum, rel=1e-5), (start, optimum)
    dec = np.asarray(c.decode(enc), np.float64)
    se = float(((X.numpy().astype(np.float64) - dec) ** 2).sum())
    assert info["se_relative"] == pytest.approx(se / tv, rel=1e-5)
    assert info["se"] <= start * (1 + 1e-6)  # never worse than the start


@pytest.mark.parametrize("n_in,n_lights", [(16, 128), (48, 20)])  # the Gram form and the projection form
def test_random_light_psnr_float32_matches_numpy_float64(monkeypatch, n_in, n_lights):
    """float32 inputs, blocks of 5 rows run on two threads: the PSNR equals numpy's float64 mean of
    ‖Δ_p l‖² over the same lights within 1e-6 dB (a 1.3e-7 relative MSE), and the same bits at one
    and at two threads."""
    g = torch.Generator().manual_seed(n_in)
    P, n_out = 211, 3
    X = (50 * torch.randn(P, n_out * n_in, generator=g)).to(torch.float32)
    Xh = (X + 0.02 * torch.randn(P, n_out * n_in, generator=g)).to(torch.float32)
    L = hm.random_unit_vectors(n_lights, n_in, seed=6).numpy()
    d = X.numpy().astype(np.float64) - Xh.numpy().astype(np.float64)
    ref = -10 * math.log10(float(((d.reshape(P, n_out, n_in) @ L.T) ** 2).sum(1).mean()))
    monkeypatch.setattr(hm, "BLOCK_ELEMENTS", 5 * n_out * n_in)
    got = []
    for n in (1, 2):
        with torch_threads(n):
            got.append(hm.random_light_psnr(X, Xh, n_in, n_lights=n_lights, seed=6))
    assert got[0] == got[1]
    assert abs(got[0] - ref) < 1e-6, (got[0], ref)
