"""The Gaussian fit's compiled Levenberg–Marquardt loop (prt_torch/kernels/gauss_lm.c,
prt_torch.codecs.gaussian.lm_native) against the torch loop (fit._lm_loop, whose normal equations
tests/test_gaussian.py checks against autograd and whose optimum against scipy's least_squares),
with the view terms (eq. 2.4–2.5), the spatial term (eq. 2.6), zero functions and bounds."""
from __future__ import annotations

import math
import warnings

import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs.gaussian import fit as F
from prt_torch.codecs.gaussian import lm_native, mixture, view_neighbours
from prt_torch.codecs.gaussian.views import default_views
from prt_torch.lighting.prefilter import cube_map_directions

pytestmark = pytest.mark.skipif(not lm_native.available(), reason="no C compiler: the compiled loop does not run")


def _problem(N, seed, V=12, J=12, r=8):
    """A batch as fit_all makes it: V vertices × J views of noisy N-lobe mixtures on a 6×r×r cube (a
    quarter of them zero: below the horizon), the view neighbours and random neighbour differences
    sb for the spatial term."""
    d, sa = cube_map_directions(r)
    dirs, sa = d.reshape(-1, 3).float(), sa.reshape(-1).float()
    g = torch.Generator().manual_seed(seed)
    B = V * J
    w = torch.empty(B, N).uniform_(0.3, 2.0, generator=g)
    mu = torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g), dim=-1)
    sg = torch.empty(B, N).uniform_(0.2, 0.6, generator=g)
    T = mixture(dirs, w, mu, sg)
    T = (T + 0.05 * T.amax(1, keepdim=True) * torch.rand(T.shape, generator=g)).float()
    T[torch.rand(B, generator=g) < 0.25] = 0.0
    T = T / (T.square() * sa).sum(1).sqrt().clamp_min(1e-30)[:, None]  # fit_all's per-vertex scale, per function here
    nonzero = T.amax(1) > 1e-7
    views = default_views(J).float()
    vn = view_neighbours(views.double()).long()
    npairs = len(F.prob_pairs(N))
    sb = 0.3 * torch.randn(B, npairs, 4, 3, generator=g) if npairs else None
    start = (w * torch.empty(B, N).uniform_(0.6, 1.4, generator=g),
             torch.nn.functional.normalize(mu + 0.15 * torch.randn(B, N, 3, generator=g), dim=-1),
             sg * torch.empty(B, N).uniform_(0.7, 1.4, generator=g))
    return T, nonzero, dirs, sa, J, vn, sb, views, start


def _batch(native, monkeypatch, T, nonzero, dirs, sa, J, vn, sb, views, start, N, max_iter, init=True, restart_above=1e9):
    monkeypatch.setenv("PRT_TORCH_NATIVE", "1" if native else "0")
    assert lm_native.available() == native
    smin, smax = F.resolvable_sigma(sa), 3.0
    return F._lm_batch(T, nonzero, dirs, sa, J, vn, N, 1e-3, 1e-2 if N > 1 else 0.0, sb, smin, smax, max_iter, 1e-4, views,
                       init=start if init else None, restart_above=restart_above)


@pytest.mark.parametrize("N", [1, 2, 3])
def test_one_iteration_equals_the_torch_loop(N, monkeypatch):
    """From the same start, one LM iteration (view targets, zero functions, normal equations with
    the view and spatial terms, active set, damped Cholesky step, acceptance) gives the torch
    loop's step: per function the parameters differ by under 1% of the step taken (median under
    0.05%: float32 texel sums in another order, through a 4N×4N solve), the objectives by under 1%
    with neither side lower more often (no systematic difference), and the same functions
    converge. Measured: largest 0.14–0.7%, median 0.002–0.016% of the step."""
    T, nonzero, dirs, sa, J, vn, sb, views, start = p = _problem(N, seed=N)
    (w1, m1, s1, it1, c1, E1), (w0, m0, s0, it0, c0, E0) = (_batch(native, monkeypatch, *p, N, max_iter=1) for native in (True, False))
    assert it1 == it0 == 1
    nz = nonzero
    for x1, x0, xs in ((w1, w0, start[0]), (m1, m0, start[1]), (s1, s0, start[2])):
        step = (x0 - xs)[nz].abs().flatten(1).amax(1)
        assert float(step.median()) > 1e-3  # the iteration moved the functions (not a vacuous pass)
        ratio = (x1 - x0)[nz].abs().flatten(1).amax(1) / step.clamp_min(1e-6)
        assert float(ratio.max()) < 1e-2 and float(ratio.median()) < 5e-4
    rel = (E1 - E0)[nz] / E0[nz]
    assert float(rel.abs().max()) < 1e-2
    assert 0.3 < float((rel < 0).float().mean()) < 0.7
    assert bool((c1 == c0).all())


@pytest.mark.parametrize("N", [1, 2])
def test_whole_fit_reaches_the_torch_loops_objective(N, monkeypatch):
    """The whole batch (greedy peaks-and-moments start, every lobe stage, the restart of the
    weakest lobe), compiled and torch: per function the same objective within 0.5% (or 1e-6 of
    the unit-energy function) on 98% of the functions, and the batch's mean objective within 0.2%."""
    p = _problem(N, seed=10 + N)
    (w1, m1, s1, it1, c1, E1), (w0, m0, s0, it0, c0, E0) = (
        _batch(native, monkeypatch, *p, N, max_iter=20, init=False, restart_above=0.05) for native in (True, False))
    nz = p[1]
    close = (E1[nz] - E0[nz]).abs() <= 5e-3 * E0[nz].abs() + 1e-6
    assert float(close.float().mean()) >= 0.98
    assert float(E1[nz].mean()) == pytest.approx(float(E0[nz].mean()), rel=2e-3)
    assert float(E1[nz].mean()) < 0.5 * float((p[0][nz].square() * p[3]).sum(1).mean())  # a real fit: well below ‖T‖²


@pytest.mark.parametrize("threads", [1, 2])
def test_codec_fit_compiled_equals_torch_and_does_not_depend_on_threads(threads, monkeypatch):
    """``GaussianCodec.fit`` on a small mesh-free table (2 lobes, view terms): the compiled loop's
    encoding relights (decodes) to the torch loop's within 0.5% relative L2 of each other, and its
    result is the same bits on 1 and 2 threads (functions are independent within an iteration)."""
    T, nonzero, dirs, sa, J, vn, sb, views, start = _problem(2, seed=7, V=20, J=12)
    X = T.reshape(20, -1)
    n = torch.get_num_threads()
    res = {}
    try:
        for native, th in ((False, 1), (True, 1), (True, threads)):
            monkeypatch.setenv("PRT_TORCH_NATIVE", "1" if native else "0")
            torch.set_num_threads(th)
            c = codecs.get("gaussian", lobes=2)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                enc = c.fit_encode(X, matrix_shape=(J, T.shape[1]), views=views)
            assert c.fit_info_["lm_loop"] == ("compiled" if native else "torch")
            res[(native, th)] = (c.decode(enc).double(), c.fit_info_["relative_l2"])
    finally:
        torch.set_num_threads(n)
    d0, e0 = res[(False, 1)]
    d1, e1 = res[(True, 1)]
    assert (d1 - d0).norm() / d0.norm() < 5e-3
    assert e1 == pytest.approx(e0, rel=5e-3, abs=1e-4)
    assert torch.equal(res[(True, threads)][0], d1)


def test_bounds_hold_and_a_zero_table_stays_zero(monkeypatch):
    """Widths stay within [resolvable σ, σ_max], weights ≥ 0, means unit; all-zero functions keep
    zero weights and finite parameters (the compiled loop's active set and zero-function update)."""
    T, nonzero, dirs, sa, J, vn, sb, views, start = _problem(2, seed=3)
    T[:J] = 0.0  # a whole vertex below the horizon
    nonzero = T.amax(1) > 1e-7
    w, mu, s, it, conv, E = _batch(True, monkeypatch, T, nonzero, dirs, sa, J, vn, sb, views, start, 2, max_iter=20, init=False)
    smin = F.resolvable_sigma(sa)
    assert bool(torch.isfinite(w).all() and torch.isfinite(mu).all() and torch.isfinite(s).all())
    assert float(s.min()) >= smin * (1 - 1e-5) and float(s.max()) <= 3.0 * (1 + 1e-5)
    assert float(w.min()) >= 0.0 and float(w[~nonzero].abs().max()) == 0.0
    torch.testing.assert_close(mu.norm(dim=-1), torch.ones(mu.shape[:2]), rtol=0, atol=1e-5)
    assert math.isfinite(float(E.sum()))


@pytest.mark.parametrize("N", [1, 2, 3])
def test_compiled_normal_equations_equal_problem_and_finite_differences(N):
    """The compiled objective and Gauss–Newton system (``lm_native.normal_equations``, what each
    compiled step solves with) with the data, view (eq. 2.4–2.5) and spatial (eq. 2.6) terms all
    active: E, JᵀJ, Jᵀr equal fit.Problem's (float64) to float32 rounding, and 2 Jᵀr equals the
    central finite-difference gradient of the float64 objective in the step's coordinates (log w,
    log σ, tangent-plane u, v of each mean) — an independent check of the view and spatial terms,
    which the autograd test of the data term does not cover."""
    r = 8
    d, s = cube_map_directions(r)
    dirs, sa = d.reshape(-1, 3).double(), s.reshape(-1).double()
    g = torch.Generator().manual_seed(20 + N)
    B = 4
    T = mixture(dirs, torch.empty(B, N, dtype=torch.float64).uniform_(0.5, 1.5, generator=g),
                torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g, dtype=torch.float64), dim=-1),
                torch.empty(B, N, dtype=torch.float64).uniform_(0.3, 0.6, generator=g))
    T = T.float().double()  # representable in float32: both sides see the same table
    a = torch.empty(B, N, dtype=torch.float64).uniform_(-0.5, 0.5, generator=g)
    ls = torch.empty(B, N, dtype=torch.float64).uniform_(math.log(0.3), math.log(0.7), generator=g)
    mu = torch.nn.functional.normalize(torch.randn(B, N, 3, generator=g, dtype=torch.float64), dim=-1)
    tm = mu + 0.2 * torch.randn(B, N, 3, generator=g, dtype=torch.float64)
    ts = ls.exp() * torch.empty(B, N, dtype=torch.float64).uniform_(0.7, 1.3, generator=g)
    npairs = len(F.prob_pairs(N))
    sb = torch.randn(B, npairs, 5, 3, generator=g, dtype=torch.float64) if npairs else None
    beta, delta = 0.05, 0.5
    a, ls, mu, tm, ts = (t.float().double() for t in (a, ls, mu, tm, ts))
    sb = None if sb is None else sb.float().double()
    p64 = F.Problem(T, dirs.float().double(), sa.float().double(), N, beta, beta, delta, 0.05, 3.0)
    p32 = F.Problem(T.float(), dirs.float(), sa.float(), N, beta, beta, delta, 0.05, 3.0)
    JtJ_c, Jtr_c, E_c = lm_native.normal_equations(p32, a.float(), ls.float(), mu.float(), tm.float(), ts.float(),
                                                   None if sb is None else sb.float())
    JtJ_t, Jtr_t, E_t = p64.normal_equations(a, ls, mu, torch.arange(B), tm, ts, sb)
    torch.testing.assert_close(E_c, E_t, rtol=1e-5, atol=1e-9)
    scale = JtJ_t.abs().amax((1, 2), keepdim=True)
    torch.testing.assert_close(JtJ_c / scale, JtJ_t / scale, rtol=0, atol=2e-5)
    torch.testing.assert_close(Jtr_c / scale[..., 0], Jtr_t / scale[..., 0], rtol=0, atol=2e-5)
    if npairs:
        assert float(p64._spatial(mu, sb)[0].amax()) > 0.1  # the spatial hinge is active somewhere

    def objective(theta):  # [B, 4N] steps in the LM's coordinates → E [B] (float64)
        a2, ls2, mu2 = p64.step(a, ls, mu, theta)
        return p64.evaluate(a2, ls2, mu2, torch.arange(B), tm, ts, sb)[0]

    h = 1e-6
    grad = torch.empty(B, 4 * N, dtype=torch.float64)
    for i in range(4 * N):
        e = torch.zeros(B, 4 * N, dtype=torch.float64)
        e[:, i] = h
        grad[:, i] = (objective(e) - objective(-e)) / (2 * h)
    gs = grad.abs().amax(1, keepdim=True)
    torch.testing.assert_close(2 * Jtr_c / gs, grad / gs, rtol=0, atol=1e-4)


def test_compiled_peaks_and_moments_equal_the_torch_start():
    """``lm_native.peaks`` (the compiled start) against ``fit._init_lobes`` with one lobe on noisy
    two-lobe mixtures (cube-map texels symmetric about the peak included): the same weights, means
    and widths to float32 rounding on every function; and for a single clean lobe both put the mean
    within a texel of the truth."""
    d, s = cube_map_directions(8)
    dirs, sa = d.reshape(-1, 3).float(), s.reshape(-1).float()
    g = torch.Generator().manual_seed(4)
    B = 2000
    T = mixture(dirs, torch.rand(B, 2, generator=g) + 0.2, torch.nn.functional.normalize(torch.randn(B, 2, 3, generator=g), dim=-1),
                torch.rand(B, 2, generator=g) * 0.5 + 0.15).float()
    T = (T + 0.02 * torch.rand(T.shape, generator=g) * T.amax(1, keepdim=True)).clamp_min(0)
    smin = F.resolvable_sigma(sa)
    w0, m0, s0 = F._init_lobes(T, dirs, sa, 1, smin, 3.0)
    w1, m1, s1 = lm_native.peaks(T, dirs.T, sa, smin, 3.0)
    torch.testing.assert_close(w1, w0, rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(m1, m0, rtol=0, atol=1e-5)
    torch.testing.assert_close(s1, s0, rtol=1e-4, atol=0)
    truth = torch.nn.functional.normalize(torch.tensor([[[0.3, -0.5, 0.8]]]), dim=-1)
    one = mixture(dirs, torch.ones(1, 1), truth, torch.full((1, 1), 0.3)).float()
    for m in (F._init_lobes(one, dirs, sa, 1, smin, 3.0)[1], lm_native.peaks(one, dirs.T, sa, smin, 3.0)[1]):
        assert float(torch.rad2deg(torch.acos((m * truth).sum(-1).clamp(-1, 1)))) < 90 / 8  # within one texel (90° / r)


@pytest.mark.parametrize("N", [2, 3])
def test_damped_retries_keep_accepted_steps_and_rescue_rejected_ones(N, monkeypatch):
    """One LM iteration with up to 5 damped solves of its normal equations (fit.LM_TRIES, Marquardt's
    inner loop: a rejected trial retried at 5× the damping) against one, in both loops: a function
    whose first trial is accepted takes that same step either way (the first trial is unchanged); more
    functions move with 5 tries (some first trials are rejected on these perturbed starts, and a more
    damped retry lowers their objective); the compiled and torch loops move the same functions."""
    T, nonzero, dirs, sa, J, vn, sb, views, start = p = _problem(N, seed=20 + N)
    moved, out = {}, {}
    for native in (True, False):
        for tries in (1, 5):
            monkeypatch.setattr(F, "LM_TRIES", tries)
            w, mu, s, it, conv, E = out[(native, tries)] = _batch(native, monkeypatch, *p, N, max_iter=1)
            moved[(native, tries)] = nonzero & ((w - start[0]).abs() > 1e-4 * start[0]).any(1)
    for native in (True, False):
        m1, m5 = moved[(native, 1)], moved[(native, 5)]
        assert bool((m5 | ~m1).all())  # accepted at the first trial -> accepted with 5 tries
        assert int(m5.sum()) > int(m1.sum())  # the retries rescue rejected first trials
        for x1, x5 in zip(out[(native, 1)][:3], out[(native, 5)][:3]):
            torch.testing.assert_close(x5[m1], x1[m1], rtol=1e-6, atol=1e-7)  # the same first step
    for tries in (1, 5):
        assert float((moved[(True, tries)] == moved[(False, tries)]).float().mean()) >= 0.98
