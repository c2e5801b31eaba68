"""The Gaussian codec's fit from scratch (Green 2005 §2.2: greedy peaks-and-moments start, then batched
Levenberg–Marquardt with up to ``fit.LM_TRIES`` damped solves per iteration; issue 42 §2): synthetic
functions made of 1–3 spherical Gaussians of known parameters — one lobe near the narrowest resolvable
width, overlapping lobes — are recovered to a stated tolerance by both LM loops, the fits converge by
the codec's own criterion, and the greedy start ends no worse than the plain one (all N lobes from
peaks and moments at once)."""
from __future__ import annotations

import itertools
import math
import warnings

import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs.gaussian import fit as F
from prt_torch.codecs.gaussian import mixture, relative_l2
from prt_torch.lighting.prefilter import cube_map_directions

R = 12  # cube face resolution (texel spacing h = 2/R ≈ 0.167 rad; the width bound 0.35 h ≈ 0.058 rad)


@pytest.fixture(scope="module")
def cube():
    d, sa = cube_map_directions(R)
    return d.reshape(-1, 3), sa.reshape(-1)


def _rotate(v, g):
    """Random rotations (one per row) of ``v [B, N, 3]``: QR of Gaussian matrices."""
    q, r = torch.linalg.qr(torch.randn(v.shape[0], 3, 3, generator=g, dtype=torch.float64))
    q = q * torch.sign(torch.diagonal(r, dim1=1, dim2=2))[:, None, :]
    return torch.einsum("bij,bnj->bni", q, v)


def _case(name: str, B: int, h: float, seed: int = 0):
    """``B`` mixtures of a named layout, randomly rotated: (w [B, N], mu [B, N, 3], sigma [B, N]) float64.
    'bound': one lobe at 0.45 h (just above the bound 0.35 h). 'bound+wide': that lobe and a wide one
    90° away. 'overlap': two lobes 25° apart (widths 0.25, 0.12 rad: their half-maximum caps overlap).
    'three': lobes at 0.45 h, 0.3 and 0.6 rad, 70–110° apart. 'three-overlap': 'overlap' plus a third
    lobe 100° away."""
    g = torch.Generator().manual_seed(seed)

    def at(deg_from_z, az=0.0):
        t, a = math.radians(deg_from_z), math.radians(az)
        return [math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)]

    layouts = {
        "bound": ([1.0], [at(0)], [0.45 * h]),
        "bound+wide": ([0.6, 1.5], [at(0), at(90)], [0.45 * h, 0.5]),
        "overlap": ([1.0, 0.5], [at(0), at(25)], [0.25, 0.12]),
        "three": ([0.5, 1.0, 1.6], [at(0), at(70), at(110, 120)], [0.45 * h, 0.3, 0.6]),
        "three-overlap": ([1.0, 0.5, 1.2], [at(0), at(25), at(100, 200)], [0.25, 0.12, 0.45]),
    }
    w0, mu0, s0 = layouts[name]
    N = len(w0)
    w = torch.tensor(w0, dtype=torch.float64).expand(B, N) * torch.empty(B, N, dtype=torch.float64).uniform_(0.8, 1.25, generator=g)
    mu = _rotate(torch.tensor(mu0, dtype=torch.float64).expand(B, N, 3), g)
    sg = torch.tensor(s0, dtype=torch.float64).expand(B, N).clone()
    return w, mu, sg


def _fit(T, N, init=None, **kw):
    c = codecs.get("gaussian", lobes=N, **kw)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(T.float(), init=init)
    return c, enc


def _match(w, mu, sg, fw, fmu, fs):
    """Per function the lobe permutation of the fit nearest the truth (smallest largest mean angle):
    (largest mean angle [B] in degrees, largest relative width error [B], largest relative weight error [B])."""
    N = w.shape[1]
    best = None
    for perm in itertools.permutations(range(N)):  # loop over N! lobe orders (N ≤ 3)
        p = list(perm)
        ang = torch.rad2deg(torch.acos((fmu[:, p] * mu).sum(-1).clamp(-1, 1))).amax(1)
        es = ((fs[:, p] - sg).abs() / sg).amax(1)
        ew = ((fw[:, p] - w).abs() / w).amax(1)
        cand = torch.stack([ang, es, ew], 1)
        best = cand if best is None else torch.where((cand[:, :1] < best[:, :1]), cand, best)
    return best[:, 0], best[:, 1], best[:, 2]


@pytest.mark.parametrize("native", [True, False], ids=["compiled-loop", "torch-loop"])
@pytest.mark.parametrize("name", ["bound", "bound+wide", "overlap", "three", "three-overlap"])
def test_known_lobes_are_recovered_from_scratch_and_the_fit_converges(cube, name, native, monkeypatch):
    """Noise-free mixtures of known lobes, fitted from scratch with the codec's defaults (greedy
    start, max_iter 30, 5 damped solves per iteration): for at least 95% of the functions every lobe
    is recovered — mean within 0.5°, width and weight within 2% — and at least 90% converge by the
    codec's criterion (fit_info_['converged_fraction']); the whole-table relative L2 is under 1%.
    Both LM loops (compiled gauss_lm.c and torch, PRT_TORCH_NATIVE=0)."""
    if not native:
        monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    d, sa = cube
    h = math.sqrt(float(sa.max()))
    w, mu, sg = _case(name, 32, h)
    assert float(sg.min()) > F.RESOLVE_FACTOR * h  # every true lobe is representable
    T = mixture(d, w, mu, sg)
    c, enc = _fit(T, w.shape[1])
    assert c.fit_info_["lm_loop"] == ("compiled" if native else "torch")
    fw, fmu, fs = (t[:, 0].double() for t in c.lobes_of(enc))
    ang, es, ew = _match(w, mu, sg, fw, fmu, fs)
    ok = (ang < 0.5) & (es < 0.02) & (ew < 0.02)
    assert float(ok.double().mean()) >= 0.95, (name, ang.max(), es.max(), ew.max())
    assert c.fit_info_["converged_fraction"] >= 0.9
    assert c.fit_info_["relative_l2"] < 1e-2


@pytest.mark.parametrize("native", [True, False], ids=["compiled-loop", "torch-loop"])
@pytest.mark.parametrize("name", ["bound+wide", "overlap", "three", "three-overlap"])
def test_greedy_start_ends_no_worse_than_the_plain_start(cube, name, native, monkeypatch):
    """The greedy start (lobe k at the residual peak of the fitted k−1 lobes, the codec's) against the
    plain start (all N lobes by peaks and moments of the data at once, fit._init_lobes, given as
    ``init``) with the same LM budget: per function the greedy fit's relative L2 is never more than
    0.001 above the plain one's (measured: at most 2e-5; with one damped solve per iteration and
    max_iter 20, the fit before issue 42 §2, one three-overlap function ended 0.0097 above), and over the set
    it is no higher."""
    if not native:
        monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    d, sa = cube
    h = math.sqrt(float(sa.max()))
    w, mu, sg = _case(name, 32, h, seed=1)
    N = w.shape[1]
    T = mixture(d, w, mu, sg)
    smin = F.resolvable_sigma(sa)
    s_start = max(smin, F.START_FACTOR * h)
    plain = F._init_lobes(T.float(), d.float(), sa.float(), N, s_start, 3.0)
    cg, eg = _fit(T, N)
    cp, ep = _fit(T, N, init=tuple(t[:, None] for t in plain))
    rg = relative_l2(cg.decode(eg), T, sa)
    rp = relative_l2(cp.decode(ep), T, sa)
    assert float((rg - rp).max()) <= 1e-3, (name, float((rg - rp).max()))
    assert cg.fit_info_["relative_l2"] <= cp.fit_info_["relative_l2"] + 1e-6
