"""Sums of spherical Gaussians per vertex and view (Green 2005): batched non-linear fits and
relighting from a Gaussian-prefiltered environment.

Representation (Green eq. 2.1, 3.2). For vertex x and stored view v, the tabulated transport
function T_{x,v}(ω) (:mod:`prt_torch.transfer.transport`, a cube map of P = 6r² texels) is
approximated by N isotropic spherical Gaussians

    T̃_{x,v}(ω) = Σ_k w_k G(ω, μ_k, σ_k),   w_k ≥ 0, ‖μ_k‖ = 1, σ_k > 0,

with G the normalised spherical Gaussian of :mod:`prt_torch.lighting.prefilter` (unit
integral; Green's eq. 3.2 with the chord distance instead of the cube unfolding M_μ, which
needs no special case at cube edges and corners). Each lobe is 5 floats (scalar weight — the
tables are scalar — 3 for the mean, 1 width); Green's RGB weights make it 7.

Fit (Green eq. 2.2): for all functions of a batch of vertices at once, minimise

    α D + β M + γ V + δ S
    D = Σ_ω Δω (T̃(ω) − T(ω))²                                              (eq. 2.3/3.1)
    M = Σ_k ‖(1/R) Σ_{r(v)} μ_k^{r} − μ_k^{v}‖²,  V = Σ_k ((1/R) Σ_{r(v)} σ_k^{r} − σ_k^{v})²   (eq. 2.4, 2.5)
    S = Σ_{k1<k2} Σ_{s(x)} max(−⟨μ_{x,k1} − μ_{x,k2}, μ_{s,k1} − μ_{s,k2}⟩, 0)³            (eq. 2.6)

(D weighted by the texel solid angles, so it is the L2 norm on the sphere; T is scaled per
vertex to unit peak energy so the weights β, γ, δ are relative). Optimiser: batched
Levenberg–Marquardt — each function has 4N unknowns (log w, log σ and two tangent-plane
coordinates of μ, re-centred every step: constraints by reparameterisation), so the normal
equations are 4N×4N (assembled from per-texel moments, :meth:`_Problem.normal_equations`) and
one batched Cholesky solve per iteration serves thousands of functions; Gauss–Newton converges
in a few tens of steps on these near-Gaussian lobes (Green reports "several hundred" fmincon
iterations). ``optimizer='lbfgs'`` (torch's L-BFGS on the batch's summed objective) is kept as
the measured alternative: on the same functions and start it ends at a higher error with 5×
the iterations (reports/benchmarks/gaussian.md). Widths and weights at their bounds are
handled as an active set (frozen for a step when the gradient points outward). The
view terms M, V couple a function to its R = 6 nearest views; they enter each iteration with
the neighbours' parameters of the previous iterate as fixed targets (a block-Jacobi splitting
of eq. 2.2, which keeps the solves per function). The spatial term S uses the already fitted
vertices among the mesh neighbours: vertices are processed in Green's flood-fill (breadth-first)
order from vertex 0, a wavefront of vertices per batch.

Green's factorisation (§3.1, Algorithms 1–2) exploits that most of a table is zero. Here the
zero set is exploited per function, where it is largest: a function that is zero everywhere (a
view below the vertex's horizon or fully shadowed — about half of all functions) is not
optimised at all (weights 0; μ, σ follow their view neighbours, the minimiser of eq. 2.4–2.5
alone). Within a nonzero function the data term runs over all P texels: with the 6×8×8 tables
of the transport precompute (P = 384) a dense batched evaluation is cheaper than Green's
per-function quadtree of the zero region (Algorithm 2), and the closed form of Algorithm 1 is
not used (Green found it less stable; it also breaks the Gauss–Newton structure).

The narrowest lobe is :func:`resolvable_sigma` (0.6 × the texel spacing): on coarser tables a
fit could put a lobe between texel centres, and its prefiltered integral (what rendering uses)
would then differ from the table's texel sum by tens of percent.

Initialisation: peaks and moments — lobe k at the centroid of the half-maximum region around
the largest remaining value, σ² from that region's solid angle (2π ln2 σ² for a Gaussian),
w from the peak height; the lobe is then subtracted and the next peak taken.

Rendering (Green §2.3, eq. 2.7): parameters are interpolated across the three nearest stored
views (barycentric weights; μ renormalised) and, on a surface, across the triangle's vertices;
each lobe is one lookup w_k E_{σ_k}(μ_k) into a :class:`PrefilteredEnvironment`. An optional
view-independent part (per texel the minimum over a vertex's views with data) is kept in SH
(``diffuse_bands``; Green §3.1) and relit as t·l.
"""
from __future__ import annotations

import contextlib
import math
import os
import time
import warnings
import weakref
from typing import Any

import torch

from .._checks import check_finite_float32, tensor_state, tensor_version
from ..lighting.prefilter import PrefilteredEnvironment, cube_map_directions, sg_normaliser
from ..params import Boolean, Interval, Options
from .base import Codec, Encoded, Relighter, check_cpu, check_out, check_signal, register, view_nbytes
from .relight_kernels import (lobe_layout, native, sg_lookup_prepared, sg_lookup_sum, sg_prepare, sg_quads_worth, sg_taps, sg_taps_prepare,
                              sg_taps_prepared, sg_taps_prepared_call)

__all__ = ["GaussianCodec", "resolvable_sigma", "relative_l2", "sh_truncation", "haar_truncation",
           "fibonacci_directions", "default_views", "view_neighbours", "view_taps",
           "views_cover_sphere", "mixture", "blend_lobes", "lobe_sum", "flood_fill_order", "MAX_LOBES"]

#: the largest lobe count accepted (Green uses 1–3, plots up to 10)
MAX_LOBES = 16
_LOG_W_MIN = math.log(1e-10)
#: narrowest lobe, in texel spacings (resolvable_sigma)
RESOLVE_FACTOR = 0.6


# --------------------------------------------------------------------------- geometry

def fibonacci_directions(n: int) -> torch.Tensor:
    """``[n, 3]`` float64 near-uniform unit directions (Fibonacci lattice); n = 1: +z."""
    if n == 1:
        return torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1 - 2 * i / n
    phi = i * math.pi * (3 - math.sqrt(5))
    rho = (1 - z * z).clamp_min(0).sqrt()
    return torch.stack([rho * torch.cos(phi), rho * torch.sin(phi), z], -1)


def default_views(J: int) -> torch.Tensor:
    """The view set a J-view table is assumed to use: the icosphere of frequency f when
    J = 10 f² + 2 (f = 3: Green's 92 views; :func:`transfer.transport.icosphere_directions`),
    else a Fibonacci lattice. ``[J, 3]`` float64."""
    f = math.isqrt(max(0, (J - 2) // 10))
    if J >= 12 and 10 * f * f + 2 == J:
        from ..transfer.transport import icosphere_directions

        return icosphere_directions(f)
    return fibonacci_directions(J)


def view_neighbours(views: torch.Tensor, k: int = 6) -> torch.Tensor:
    """Indices ``[J, min(k, J−1)]`` int64 of each view's nearest other views (r(v) of eq. 2.4)."""
    J = views.shape[0]
    k = min(k, J - 1)
    if k <= 0:
        return torch.zeros(J, 0, dtype=torch.long)
    c = views @ views.T
    c.fill_diagonal_(-2.0)
    return c.topk(k, dim=1).indices


def views_cover_sphere(views: torch.Tensor, max_angle_deg: float = 75.0) -> tuple[bool, float]:
    """Whether every direction has a stored view within ``max_angle_deg`` (so each vertex's
    hemisphere of views is covered and three nearest views bracket any view). Returns
    (ok, the largest angle to the nearest view in degrees, over 4096 test directions)."""
    test = fibonacci_directions(4096)
    v = views.to(torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    worst = math.degrees(math.acos(float((test @ v.T).amax(1).min().clamp(-1, 1))))
    return worst <= max_angle_deg, worst


def view_taps(views: torch.Tensor, dirs: torch.Tensor, k: int = 3) -> tuple[torch.Tensor, torch.Tensor]:
    """The three nearest stored views of each direction and barycentric weights (Green §2.3:
    "interpolate the parameters from the three closest views"). ``views [J, 3]``, ``dirs
    [M, 3]`` unit → ``(idx int64 [M, k], w float32 [M, k])``, weights ≥ 0 summing to 1 (the
    barycentric coordinates of the direction in the triangle of the three views, clamped)."""
    J = views.shape[0]
    k = min(k, J)
    d = dirs.to(torch.float64)
    vv = views.to(torch.float64)
    c = d @ vv.T
    idx = c.topk(k, dim=1).indices
    if k < 3:
        w = c.gather(1, idx).clamp_min(0) + 1e-12
        return idx, (w / w.sum(1, keepdim=True)).to(torch.float32)
    B = vv[idx].transpose(1, 2)  # [M, 3, 3] columns = the three views
    det = torch.linalg.det(B)
    ok = det.abs() > 1e-9
    Bs = torch.where(ok[:, None, None], B, torch.eye(3, dtype=B.dtype).expand_as(B))
    b = torch.linalg.solve(Bs, d[..., None])[..., 0].clamp_min(0)
    fallback = c.gather(1, idx).clamp_min(0) + 1e-12
    b = torch.where(ok[:, None] & (b.sum(1, keepdim=True) > 0), b, fallback)
    return idx, (b / b.sum(1, keepdim=True)).to(torch.float32)


def mixture(dirs: torch.Tensor, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Σ_k w_k G(ω, μ_k, σ_k) (Green eq. 2.1) at ``dirs [P, 3]`` for ``w [B, N]``, ``mu [B, N, 3]``,
    ``sigma [B, N]`` → ``[B, P]`` (dtype of w)."""
    lam = sigma.reciprocal().square()
    cos = torch.einsum("bnc,pc->bnp", mu, dirs.to(mu.dtype))
    return torch.einsum("bn,bnp->bp", w * sg_normaliser(lam), torch.exp(lam[..., None] * (cos - 1)))


def blend_lobes(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, a: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Interpolate corresponding lobes (Green §2.3; barycentric across views or triangle
    vertices): ``w [M, T, N]``, ``mu [M, T, N, 3]``, ``sigma [M, T, N]``, weights ``a [M, T]``
    → ``(w [M, N], mu [M, N, 3] unit, sigma [M, N])``. Weights and widths blend linearly, means
    as the normalised weighted sum (the non-linear interpolation that moves a highlight instead
    of cross-fading it)."""
    a = a.to(w.dtype)
    wb = torch.einsum("mt,mtn->mn", a, w)
    sb = torch.einsum("mt,mtn->mn", a, sigma)
    mb = torch.einsum("mt,mtnc->mnc", a, mu)
    mb = mb / mb.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return wb, mb, sb.clamp_min(1e-6)


def resolvable_sigma(solid_angles: torch.Tensor) -> float:
    """The narrowest lobe a table resolves: 0.6 h, h = √(largest texel solid angle) (2/r on a
    cube map). Below it the texel sum of a Gaussian departs from its integral (the Riemann sum
    of a Gaussian of width σ on spacing h errs by ~2 exp(−2π²σ²/h²) per axis: 0.2% at 0.6 h,
    30% at 0.36 h, measured on 6×8×8 tables), so a fit could put a lobe between texel centres
    whose prefiltered integral the data do not constrain."""
    return RESOLVE_FACTOR * math.sqrt(float(solid_angles.double().max()))


def _vertex_neighbours(faces: torch.Tensor, V: int, kmax: int = 8) -> torch.Tensor:
    """Mesh neighbours ``[V, kmax]`` int64 padded with −1 (first kmax by index)."""
    f = faces.long()
    e = torch.cat([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    e = torch.cat([e, e.flip(1)])
    e = torch.unique(e, dim=0)  # sorted by source, then target
    src, dst = e[:, 0], e[:, 1]
    counts = torch.bincount(src, minlength=V)
    start = torch.cumsum(counts, 0) - counts
    rank = torch.arange(e.shape[0]) - start[src]
    keep = rank < kmax
    out = torch.full((V, kmax), -1, dtype=torch.long)
    out[src[keep], rank[keep]] = dst[keep]
    return out


def flood_fill_order(faces: torch.Tensor | None, V: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Green's flood fill (§2.2.2): vertices in breadth-first order from vertex 0 (each further
    connected component from its lowest unvisited vertex). Returns (order ``[V]`` int64,
    neighbours ``[V, kmax]`` int64 padded with −1; empty ``[V, 0]`` without faces)."""
    if faces is None or V == 0:
        return torch.arange(V), torch.zeros(V, 0, dtype=torch.long)
    nb = _vertex_neighbours(faces, V)
    seen = torch.zeros(V, dtype=torch.bool)
    order = []
    while len(order) == 0 or sum(len(o) for o in order) < V:  # one pass per connected component
        seed = int((~seen).nonzero()[0])
        front = torch.tensor([seed])
        seen[seed] = True
        while front.numel():  # one step per BFS layer (not per vertex)
            order.append(front)
            cand = nb[front].reshape(-1)
            cand = cand[cand >= 0]
            cand = torch.unique(cand[~seen[cand]])
            seen[cand] = True
            front = cand
    return torch.cat(order), nb


@contextlib.contextmanager
def _threads_for(work: int, small: int = 1 << 25):
    """One thread for batches below ``small`` texel·lobe evaluations when other processes held
    the cores at import (``OMP_WAIT_POLICY=PASSIVE``, chosen by :mod:`prt_torch` from the
    runnable-process count): there the per-op thread hand-off of the many mid-sized tensors of
    an LM step cost more than it gained (200 functions: 0.4 s on 1 thread vs 3–9 s on 2;
    4600 functions × 2 lobes: 17 s vs 62 s, load average 5–7). On an idle machine all threads."""
    n = torch.get_num_threads()
    busy = os.environ.get("OMP_WAIT_POLICY", "").upper() == "PASSIVE"
    if busy and work < small and n > 1:
        torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _tangents(mu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal tangents (t1, t2) ``[..., 3]`` of unit ``mu [..., 3]``."""
    ax = torch.zeros_like(mu)
    i = mu.abs().argmin(-1, keepdim=True)
    ax.scatter_(-1, i, 1.0)
    t1 = torch.linalg.cross(mu, ax)
    t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return t1, torch.linalg.cross(mu, t1)


# --------------------------------------------------------------------------- the comparison (Green Fig. 3-3)

def relative_l2(approx: torch.Tensor, T: torch.Tensor, solid_angles: torch.Tensor) -> torch.Tensor:
    """‖T̃ − T‖ / ‖T‖ on the sphere (texel solid angles as the quadrature) per function:
    ``approx, T [B, P]``, ``solid_angles [P]`` → ``[B]`` float64 (0 where T = 0 and T̃ = 0)."""
    sa = solid_angles.double()
    num = ((approx.double() - T.double()).square() * sa).sum(-1)
    den = (T.double().square() * sa).sum(-1)
    return torch.where(den > 0, (num / den.clamp_min(1e-300)).sqrt(), num.sqrt())


def sh_truncation(T: torch.Tensor, dirs: torch.Tensor, solid_angles: torch.Tensor, k: int) -> torch.Tensor:
    """Linear SH approximation with the first ``k`` coefficients (flat order l(l+1)+m),
    projected with the texel solid angles: ``T [B, P]`` → ``[B, P]`` float64."""
    from ..sh import eval_sh

    bands = math.isqrt(k - 1) + 1
    Y = eval_sh(dirs.double(), bands, check=False)[:, :k]  # [P, k]
    c = (T.double() * solid_angles.double()) @ Y
    return c @ Y.T


def haar_truncation(T: torch.Tensor, k: int) -> torch.Tensor:
    """Non-linear Haar approximation on the cube map (Ng et al. 2003, as Green §3.3): the
    orthonormal 2D (non-standard) Haar transform of each face, keep the ``k`` largest
    coefficients over all six faces, invert. ``T [B, 6, r, r]`` (r a power of 2) → same shape,
    float64."""
    B, F, r, _ = T.shape
    if r & (r - 1):
        raise ValueError(f"Haar needs a power-of-two face size; got r={r}")
    x = T.double().clone()
    n = r
    while n > 1:  # forward, one level per step (log2 r levels, batched over functions and faces)
        a = x[..., :n, :n]
        p, q = a[..., 0::2, :], a[..., 1::2, :]
        lo, hi = (p + q) / math.sqrt(2), (p - q) / math.sqrt(2)
        rows = torch.cat([lo, hi], -2)
        p, q = rows[..., :, 0::2], rows[..., :, 1::2]
        x[..., :n, :n] = torch.cat([(p + q) / math.sqrt(2), (p - q) / math.sqrt(2)], -1)
        n //= 2
    flat = x.reshape(B, -1)
    keep = flat.abs().topk(min(k, flat.shape[1]), dim=1).indices
    y = torch.zeros_like(flat).scatter_(1, keep, flat.gather(1, keep)).reshape(B, F, r, r)
    n = 2
    while n <= r:  # inverse
        a = y[..., :n, :n]
        h = n // 2
        lo, hi = a[..., :, :h], a[..., :, h:]
        cols = torch.empty_like(a)
        cols[..., :, 0::2], cols[..., :, 1::2] = (lo + hi) / math.sqrt(2), (lo - hi) / math.sqrt(2)
        lo, hi = cols[..., :h, :], cols[..., h:, :]
        out = torch.empty_like(a)
        out[..., 0::2, :], out[..., 1::2, :] = (lo + hi) / math.sqrt(2), (lo - hi) / math.sqrt(2)
        y[..., :n, :n] = out
        n *= 2
    return y


# --------------------------------------------------------------------------- fitting

def _init_lobes(T: torch.Tensor, dirs: torch.Tensor, sa: torch.Tensor, N: int, smin: float, smax: float):
    """Peaks and moments (module docstring): ``T [B, P]`` ≥ 0 mostly → ``(w [B, N], mu [B, N, 3],
    sigma [B, N])``. A loop over the N lobes, each step batched over all B functions."""
    B = T.shape[0]
    R = T.clone()
    w = torch.empty(B, N, dtype=T.dtype)
    mu = torch.empty(B, N, 3, dtype=T.dtype)
    sg = torch.empty(B, N, dtype=T.dtype)
    ln2 = math.log(2.0)
    for k in range(N):
        peak, p = R.max(1)
        pdir = dirs[p]  # [B, 3]
        cos = pdir @ dirs.T  # [B, P]
        above = R >= 0.5 * peak[:, None]
        # the contiguous half-maximum cap: out to the nearest texel below half the peak
        c_out = torch.where(above, torch.full_like(cos, -1.0), cos).amax(1)  # [B]
        cap = cos > c_out[:, None]
        c_in = torch.where(cap, cos, torch.ones_like(cos)).amin(1)
        one_minus_c = 0.5 * ((1 - c_out) + (1 - c_in))
        s = (one_minus_c / ln2).sqrt().clamp(smin, smax)  # 1 − cos θ_half = ln2 σ² for a Gaussian
        c = (R.clamp_min(0) * cap * sa) @ dirs  # first moment over the cap
        cn = c.norm(dim=-1, keepdim=True)
        m = torch.where(cn > 1e-30, c / cn.clamp_min(1e-30), pdir)
        lam = s.reciprocal().square()
        off = torch.exp(lam * ((m * pdir).sum(-1) - 1)).clamp_min(0.5)
        wk = peak.clamp_min(0) / off / sg_normaliser(lam)
        w[:, k], mu[:, k], sg[:, k] = wk, m, s
        R = R - wk[:, None] * sg_normaliser(lam)[:, None] * torch.exp(lam[:, None] * (m @ dirs.T - 1))
    return w, mu, sg


class _Problem:
    """One batch: functions ``T [B, P]`` (scaled), the geometry and the regularisers."""

    def __init__(self, T, dirs, sa, N, beta, gamma, delta, smin, smax):
        self.T, self.dirs, self.sa = T, dirs, sa
        self.energy = (T.square() * sa).sum(1)  # [B]: β, γ, δ act relative to each function's energy
        self.N, self.beta, self.gamma, self.delta = N, beta, gamma, delta
        self.lsmin, self.lsmax = math.log(smin), math.log(smax)
        self.pairs = prob_pairs(N)
        self.rsa = sa.sqrt()  # [P]
        d1 = torch.cat([torch.ones_like(dirs[:, :1]), dirs], 1)  # [P, 4]: (1, ω)
        self.moments = (d1[:, :, None] * d1[:, None, :]).reshape(-1, 16)  # [P, 16]: (1, ω)(1, ω)ᵀ
        self.d1 = d1

    def evaluate(self, a, ls, mu, sel, tgt_mu, tgt_s, sb):
        """Objective per function ``[b]``, the residual ``r [b, P]``, the lobe terms
        ``w_k G(ω_p; μ_k, σ_k)`` ``[b, N, P]`` and λ = σ⁻² ``[b, N]``."""
        T = self.T[sel]
        lam = torch.exp(-2 * ls)
        term = torch.matmul(mu, self.dirs.T)  # cos [b, N, P], then (in place unless differentiated) the lobe terms
        coef = (torch.exp(a) * sg_normaliser(lam))[..., None]
        if torch.is_grad_enabled() and (a.requires_grad or ls.requires_grad or mu.requires_grad):
            term = torch.exp(lam[..., None] * (term - 1)) * coef
        else:
            term.sub_(1).mul_(lam[..., None]).exp_().mul_(coef)
        r = term.sum(1) - T
        E = (r * r * self.sa).sum(1)
        if self.beta > 0 and tgt_mu is not None:
            en = self.energy[sel]
            E = E + en * (self.beta * (mu - tgt_mu).square().sum((1, 2)) + self.gamma * (ls.exp() - tgt_s).square().sum(1))
        if self.delta > 0 and sb is not None and self.pairs:
            E = E + self.energy[sel] * self.delta * self._spatial(mu, sb)[0].pow(3).sum((1, 2))
        return E, r, term, lam

    def _spatial(self, mu, sb):
        """f = max(−⟨Δμ_x, Δμ_s⟩, 0) per pair and neighbour ``[b, pairs, Q]`` (eq. 2.6) with the
        neighbour differences ``sb [b, pairs, Q, 3]`` (zero where no processed neighbour)."""
        i = torch.tensor([p[0] for p in self.pairs])
        j = torch.tensor([p[1] for p in self.pairs])
        dx = mu[:, i] - mu[:, j]  # [b, pairs, 3]
        f = -(dx[:, :, None, :] * sb).sum(-1)
        return f.clamp_min(0), i, j

    def normal_equations(self, a, ls, mu, sel, tgt_mu, tgt_s, sb):
        """Gauss–Newton ``JᵀJ [b, 4N, 4N]`` and ``Jᵀr [b, 4N]`` (float64) in the coordinates
        (log w, log σ, u, v) per lobe, and the current objective ``[b]``.

        The data term's Jacobian row of lobe k at texel p is ``g_k(p) A_k (1, ω_p)``: the lobe
        term g_k times a 4×4 matrix A_k (rows: ∂/∂log w = 1; ∂/∂log σ = −2λ(∂log c/∂λ + μ·ω − 1);
        ∂/∂u = λ t₁·ω; ∂/∂v = λ t₂·ω) applied to the homogeneous direction. Hence
        ``JᵀJ_{kl} = A_k (Σ_p Δω_p g_k g_l (1, ω)(1, ω)ᵀ) A_lᵀ`` and ``Jᵀr_k = A_k Σ_p Δω_p g_k r (1, ω)``:
        two GEMMs over the texels against fixed per-texel moments instead of forming the
        ``[b, 4N, P]`` Jacobian (4× less memory traffic at N = 1, 8× at N = 2)."""
        E, r, term, lam = self.evaluate(a, ls, mu, sel, tgt_mu, tgt_s, sb)
        b, N = a.shape
        P = term.shape[-1]
        t1, t2 = _tangents(mu)
        x = lam.double()
        dlogc = torch.where(x < 1e-3, 1 - x / 3, 1 / x.clamp_min(1e-3) - 2 / torch.expm1(2 * x.clamp_min(1e-3)))
        A = torch.zeros(b, N, 4, 4, dtype=torch.float64)
        A[:, :, 0, 0] = 1.0
        A[:, :, 1, 0] = -2 * x * (dlogc - 1)
        A[:, :, 1, 1:] = -2 * x[..., None] * mu.double()
        A[:, :, 2, 1:] = x[..., None] * t1.double()
        A[:, :, 3, 1:] = x[..., None] * t2.double()
        g = term.mul_(self.rsa)  # √Δω g_k  [b, N, P] (term is not used after this)
        M = torch.matmul((g[:, :, None, :] * g[:, None, :, :]).reshape(-1, P), self.moments)  # [b·N·N, 16]
        M = M.view(b, N, N, 4, 4).double()
        JtJ = torch.einsum("bkij,bkljm,blnm->bkiln", A, M, A).reshape(b, 4 * N, 4 * N)
        v = torch.matmul(g * (r * self.rsa)[:, None, :], self.d1).double()  # [b, N, 4]
        Jtr = torch.einsum("bkij,bkj->bki", A, v).reshape(b, 4 * N)
        en = self.energy[sel].double()[:, None]
        if self.beta > 0 and tgt_mu is not None:
            dm = (mu - tgt_mu).double()
            iu, iv, is_ = torch.arange(N) * 4 + 2, torch.arange(N) * 4 + 3, torch.arange(N) * 4 + 1
            JtJ[:, iu, iu] += self.beta * en
            JtJ[:, iv, iv] += self.beta * en
            Jtr[:, iu] += self.beta * en * (t1.double() * dm).sum(-1)
            Jtr[:, iv] += self.beta * en * (t2.double() * dm).sum(-1)
            s = ls.exp().double()
            JtJ[:, is_, is_] += self.gamma * en * s * s
            Jtr[:, is_] += self.gamma * en * s * (s - tgt_s.double())
        if self.delta > 0 and sb is not None and self.pairs:
            f, i, j = self._spatial(mu, sb)
            coef = (1.5 * math.sqrt(self.delta)) * f.sqrt()  # d r / d f with r = √δ f^{3/2}
            res = math.sqrt(self.delta) * f.pow(1.5)
            # df/du_k1 = −t1_k1·b, df/du_k2 = +t1_k2·b (b = Δμ_s)
            g = torch.stack([-(t1[:, i, None] * sb).sum(-1), -(t2[:, i, None] * sb).sum(-1),
                             (t1[:, j, None] * sb).sum(-1), (t2[:, j, None] * sb).sum(-1)], -1) * coef[..., None]
            blk = torch.einsum("bpqi,bpqj->bpij", g, g).double() * en[..., None, None]  # [b, pairs, 4, 4]
            rhs = torch.einsum("bpqi,bpq->bpi", g, res).double() * en[..., None]
            for n, (k1, k2) in enumerate(self.pairs):  # loop over lobe pairs (model structure)
                ids = torch.tensor([4 * k1 + 2, 4 * k1 + 3, 4 * k2 + 2, 4 * k2 + 3])
                JtJ[:, ids[:, None], ids[None, :]] += blk[:, n]
                Jtr[:, ids] += rhs[:, n]
        return JtJ, Jtr, E

    def step(self, a, ls, mu, delta):
        """Apply ``delta [b, 4N]`` (constraints by reparameterisation; means re-centred)."""
        b, N = a.shape
        d = delta.to(a.dtype).reshape(b, N, 4)
        t1, t2 = _tangents(mu)
        a2 = (a + d[..., 0]).clamp(_LOG_W_MIN, 60.0)
        ls2 = (ls + d[..., 1]).clamp(self.lsmin, self.lsmax)
        m2 = mu + d[..., 2:3] * t1 + d[..., 3:4] * t2
        return a2, ls2, m2 / m2.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def lobe_sum(light: PrefilteredEnvironment, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
             out: torch.Tensor | None = None, layout: tuple | None = None, prepared: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over the lobes (last axis of ``w [..., N]``) of w · E_σ(μ) — Green 2005 eq. 2.7 with
    ``mu [..., N, 3]``, ``sigma [..., N]`` → ``[..., C]`` float32: one fused pass per lobe
    (``relight_kernels.sg_lookup_sum``) where the kernels are compiled, else
    ``light.lookup`` and a sum (the same values to float32 rounding; tests compare them).
    ``out``: an optional contiguous float32 result of that shape, written and returned;
    ``layout``: ``relight_kernels.lobe_layout(w, mu, sigma)`` where the caller keeps it;
    ``prepared``: ``relight_kernels.sg_prepare``'s addressing of these lobes for this light's
    resolution and width ladder (``GaussianRelighter``), the same bits read faster."""
    lib = _fused(light)
    if lib is not None:
        table = light.table()
        quads = light.quads() if sg_quads_worth(table.shape[0], light.channels, light.res, w.numel()) else None
        if prepared is not None:
            return sg_lookup_prepared(lib, prepared, table, light.log_sigmas, light.res, w, mu, sigma, out=out, layout=layout,
                                      quads=quads)
        return sg_lookup_sum(lib, table, light.log_sigmas, light.res, mu, sigma, w, out=out, layout=layout, quads=quads)
    res = (w[..., None] * light.lookup(mu, sigma)).sum(-2)
    return res if out is None else out.copy_(res)


def _fused(light: PrefilteredEnvironment):
    """The compiled kernels when they take this light (≤ 16 channels), else None (torch path)."""
    lib = native()
    return lib if lib is not None and light.channels <= 16 else None


@register("gaussian")
class GaussianCodec(Codec):
    """Green 2005: per vertex and view, a sum of spherical Gaussians fitted to transport tables; relit from a Gaussian-prefiltered environment.

    Parameters
    ----------
    lobes : int, default=1
        Number N of Gaussians per transport function (Green uses 1–3).
    max_iter : int, default=20
        Optimiser iterations per batch (the last lobe's stage; earlier stages of the greedy
        start take a quarter).
    optimizer : {'lm', 'lbfgs'}, default='lm'
        'lm': batched Levenberg–Marquardt (Gauss–Newton normal equations per function, one
        4N×4N Cholesky each; per-function damping and convergence). 'lbfgs': torch's L-BFGS
        with a strong-Wolfe line search on the batch's summed objective (widths through a
        sigmoid between the bounds, means normalised) — kept as the measured alternative:
        benchmarks/bench_gaussian.py compares both at equal iterations and equal time.
    tol : float, default=1e-4
        A function has converged when an accepted step lowers its objective by less than this
        fraction.
    view_weight : float, default=1e-3
        β = γ of Green eq. 2.4–2.5 (alignment of means and widths with the neighbouring views),
        relative to each function's energy Σ Δω T².
    spatial_weight : float, default=1e-2
        δ of Green eq. 2.6 (arrangement of the lobes consistent with fitted mesh neighbours),
        relative to each function's energy.
    sigma_min : float, default=0.01
        Smallest lobe width (radians); at least :func:`resolvable_sigma` of the tables is used
        (0.6 × the texel spacing, 2/r on a cube map: a narrower lobe could fall between texel
        centres).
    sigma_max : float, default=3.0
        Largest lobe width (radians; wider than a hemisphere is allowed).
    diffuse_bands : int, default=0
        Keep a view-independent part in SH with this many bands (Green §3.1; 0: none).
    batch_size : int, default=8192
        Transport functions optimised together (memory ~ batch · 6r² · 4N floats).
    seed : int, default=0
        Unused by the deterministic fit; kept for the common interface.
    strict : bool, default=False
        Raise instead of warning when functions did not converge within ``max_iter``.
    """

    linear = False
    light_kind = "prefiltered"
    _parameter_constraints = {
        "lobes": [Interval(int, 1, MAX_LOBES)],
        "max_iter": [Interval(int, 1, 10000)],
        "optimizer": [Options("lm", "lbfgs")],
        "tol": [Interval(float, 0, 1, closed="left")],
        "view_weight": [Interval(float, 0, None)],
        "spatial_weight": [Interval(float, 0, None)],
        "sigma_min": [Interval(float, 1e-4, 1.0)],
        "sigma_max": [Interval(float, 0.1, 10.0)],
        "diffuse_bands": [Interval(int, 0, 12)],
        "batch_size": [Interval(int, 1, None)],
        "seed": [Interval(int, 0, None)],
        "strict": [Boolean()],
    }

    def __init__(self, *, lobes=1, max_iter=20, optimizer="lm", tol=1e-4, view_weight=1e-3, spatial_weight=1e-2, sigma_min=0.01,
                 sigma_max=3.0, diffuse_bands=0, batch_size=8192, seed=0, strict=False):
        self.lobes = lobes
        self.max_iter = max_iter
        self.optimizer = optimizer
        self.tol = tol
        self.view_weight = view_weight
        self.spatial_weight = spatial_weight
        self.sigma_min = sigma_min
        self.sigma_max = sigma_max
        self.diffuse_bands = diffuse_bands
        self.batch_size = batch_size
        self.seed = seed
        self.strict = strict

    def _check_params(self, p):
        if p["sigma_min"] >= p["sigma_max"]:
            raise ValueError(f"codec {self.codec_name!r}: sigma_min={p['sigma_min']} >= sigma_max={p['sigma_max']}; "
                             "accepted: sigma_min < sigma_max")

    def __getstate__(self):
        return {k: v for k, v in super().__getstate__().items() if k != "_train"}

    # ------------------------------------------------------------------ geometry
    def _geometry(self, D, matrix_shape, views, directions, solid_angles, kind):
        if kind is not None and kind != "transport":
            raise ValueError(f"codec {self.codec_name!r} fits transport tables (transfer kind 'transport', "
                             f"prt precompute --kind transport); got a transfer of kind {kind!r}")
        if matrix_shape is None:
            J, P = 1, D
        else:
            J, P = (int(v) for v in matrix_shape)
            if J * P != D or J < 1 or P < 1:
                raise ValueError(f"matrix_shape={tuple(matrix_shape)} does not fold D={D}; accepted: (views J, texels P) with J*P = D")
        if directions is not None:
            dirs = torch.as_tensor(directions, dtype=torch.float64).reshape(-1, 3)
            if dirs.shape[0] != P:
                raise ValueError(f"directions has {dirs.shape[0]} rows; accepted: one per texel, P = {P}")
            dirs = dirs / dirs.norm(dim=-1, keepdim=True)
            sa = (torch.full((P,), 4 * math.pi / P, dtype=torch.float64) if solid_angles is None
                  else torch.as_tensor(solid_angles, dtype=torch.float64).reshape(-1))
            layout = "given"
        else:
            r = math.isqrt(P // 6)
            if 6 * r * r == P:
                d, s = cube_map_directions(r)
                dirs, sa, layout = d.reshape(-1, 3), s.reshape(-1), f"cube{r}"
            else:
                dirs, sa, layout = fibonacci_directions(P), torch.full((P,), 4 * math.pi / P, dtype=torch.float64), "fibonacci"
        if sa.shape != (P,) or not bool(torch.isfinite(sa).all()) or bool((sa < 0).any()):
            raise ValueError(f"solid_angles must be [P] = [{P}] finite non-negative texel solid angles")
        if views is not None:
            vw = torch.as_tensor(views, dtype=torch.float64)
            if vw.ndim != 2 or vw.shape != (J, 3):
                raise ValueError(f"views has shape {tuple(vw.shape)}; accepted: [J, 3] = [{J}, 3], one per stored view")
            if not bool(torch.isfinite(vw).all()) or bool((vw.norm(dim=-1) < 1e-9).any()):
                raise ValueError("views must be finite non-zero directions")
            vw = vw / vw.norm(dim=-1, keepdim=True)
            ok, worst = views_cover_sphere(vw)
            if not ok:
                raise ValueError(f"views do not cover the hemisphere of every vertex: some direction is {worst:.1f}° from "
                                 "the nearest view; accepted: a view set with every direction within 75° of a view "
                                 "(e.g. the icosphere views of prt precompute --kind transport)")
        else:
            vw = default_views(J)
        return J, P, dirs, sa, vw, layout

    # ------------------------------------------------------------------ fit / encode
    def fit(self, X, y=None, weights=None, matrix_shape=None, *, views=None, directions=None, solid_angles=None,
            faces=None, kind=None, init=None) -> "GaussianCodec":
        """Fit on transport tables ``X [V, J·P]`` (row v: J functions of P texels; ``matrix_shape
        = (J, P)``). Geometry keywords: ``views [J, 3]`` (default: the icosphere when J = 10f²+2),
        ``directions [P, 3]`` and ``solid_angles [P]`` (default: the cube map when P = 6r²),
        ``faces [F, 3]`` (mesh, for the flood fill and the spatial term eq. 2.6), ``kind`` (the
        transfer kind; anything but 'transport' is refused), ``init`` (starting parameters instead
        of peaks and moments: an :class:`Encoded` of this codec or ``(w [V, J, N], mu [V, J, N, 3],
        sigma [V, J, N])``). All checks before any work."""
        p = self._validate()
        X_in = X
        X = check_signal("X", X)
        if weights is not None:
            raise ValueError(f"codec {self.codec_name!r} does not take per-point weights; accepted: weights=None")
        J, P, dirs, sa, vw, layout = self._geometry(X.shape[1], matrix_shape, views, directions, solid_angles, kind)
        if faces is not None:
            faces = torch.as_tensor(faces).long()
            if faces.ndim != 2 or faces.shape[1] != 3 or (faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= X.shape[0])):
                raise ValueError(f"faces must be [F, 3] vertex indices in [0, {X.shape[0]})")
        if init is not None:
            if isinstance(init, Encoded):
                init = self.lobes_of(init)
            init = tuple(torch.as_tensor(t, dtype=torch.float32) for t in init)
            want = [(X.shape[0], J, p["lobes"]), (X.shape[0], J, p["lobes"], 3), (X.shape[0], J, p["lobes"])]
            if len(init) != 3 or [tuple(t.shape) for t in init] != want or not all(bool(torch.isfinite(t).all()) for t in init):
                raise ValueError(f"init must be finite (w, mu, sigma) of shapes {want}")
        self.J_, self.P_, self.layout_ = J, P, layout
        self.views_, self.directions_, self.solid_angles_ = vw.float(), dirs.float(), sa.float()
        self.n_features_in_ = X.shape[1]
        self.faces_ = faces
        self.fitted_ = True
        enc, info = self._encode(X, p, init)
        self._train = ((X.data_ptr(), tuple(X.shape), X.dtype, tensor_version(X)), weakref.ref(X_in), enc)
        self.fit_info_ = info
        if info.get("lobes_at_resolution_limit", 0.0) > 0.25:
            warnings.warn(
                f"codec {self.codec_name!r}: {100 * info['lobes_at_resolution_limit']:.0f}% of the fitted lobes sit at the "
                f"narrowest width the tables resolve (sigma = {info['sigma_resolvable']:.3f} rad, 0.6 texel spacings at "
                f"{layout}): the transport is sharper than its texels, so those functions keep a large error whatever "
                "the lobe count; tabulate with a finer cube map (prt precompute --kind transport --res 16 or more)",
                UserWarning, stacklevel=2)
        if info["converged_fraction"] < 1.0:
            self._warn_or_raise(f"codec {self.codec_name!r}: {info['not_converged']} of {info['functions_fitted']} "
                                f"transport functions did not converge in max_iter={p['max_iter']} iterations")
        return self

    def fit_encode(self, X, weights=None, matrix_shape=None, **geometry) -> Encoded:
        return self.fit(X, weights=weights, matrix_shape=matrix_shape, **geometry).encode(X)

    def encode(self, X) -> Encoded:
        """Fit the Gaussian parameters of ``X [V, J·P]`` with the fitted geometry (the training
        signal's encoding is returned without refitting)."""
        self._require_fitted()
        X = check_signal("X", X)
        if X.shape[1] != self.J_ * self.P_:
            raise ValueError(f"X has D={X.shape[1]}; this codec was fitted with D={self.J_ * self.P_}")
        train = getattr(self, "_train", None)
        if train is not None and train[0] == (X.data_ptr(), tuple(X.shape), X.dtype, tensor_version(X)) and train[1]() is not None:
            return train[2]
        return self._encode(X, self.params)[0]

    def _encode(self, X: torch.Tensor, p: dict, init=None) -> tuple[Encoded, dict]:
        t0 = time.perf_counter()
        V, J, P, N = X.shape[0], self.J_, self.P_, p["lobes"]
        T = X.reshape(V, J, P).to(torch.float32)
        dirs, sa = self.directions_, self.solid_angles_
        enc_t: dict[str, torch.Tensor] = {}
        nb = self.diffuse_bands_ = int(p["diffuse_bands"])
        if nb:
            from ..sh import eval_sh

            has = T.amax(-1) > 0  # [V, J]
            big = torch.finfo(torch.float32).max
            Dmin = torch.where(has[..., None], T, torch.full_like(T, big)).amin(1)
            Dmin = torch.where(has.any(1, keepdim=True), Dmin, torch.zeros_like(Dmin)).clamp_min(0)  # [V, P]
            Y = eval_sh(dirs.double(), nb, check=False).float()  # [P, n²]
            t = (Dmin * sa) @ Y  # [V, n²]  (SH projection, solid-angle quadrature)
            T = T - (t @ Y.T)[:, None, :] * has[..., None]
            enc_t["diffuse"] = t
            enc_t["has_data"] = has.to(torch.uint8)
        w, mu, sg, info = self._fit_all(T, p, init)
        # view-major records [J, V, N, 5] (lobes_of): a camera's taps, a few views shared by neighbouring
        # vertices, read runs along the vertices (vertex-major [V, J, N, 5]: three scattered runs per vertex)
        enc_t["lobes_by_view"] = torch.cat([w[..., None], mu, sg[..., None]], -1).transpose(0, 1).contiguous()
        enc = Encoded(codec=self.codec_name, tensors=enc_t,
                      meta={"points": V, "dim": J * P, "matrix_shape": [J, P], "lobes": N, "layout": self.layout_,
                            "diffuse_bands": nb})
        Xh = self.decode(enc).reshape(V, J, P).double()
        T0 = X.reshape(V, J, P).double()
        sa64 = sa.double()
        err = ((Xh - T0).square() * sa64).sum(-1)  # [V, J]
        ref = (T0.square() * sa64).sum(-1)
        nz = ref > 0
        rel_f = (err[nz] / ref[nz]).sqrt()
        info.update({
            "relative_l2": math.sqrt(float(err.sum()) / max(1e-300, float(ref.sum()))),
            "relative_l2_median": float(rel_f.median()) if rel_f.numel() else 0.0,
            "relative_l2_p90": float(rel_f.quantile(0.9)) if rel_f.numel() else 0.0,
            "se": float((Xh - T0).square().sum()), "seconds": time.perf_counter() - t0,
        })
        info["se_relative"] = info["se"] / max(1e-300, float(T0.square().sum()))
        info["functions_per_s"] = V * J / max(info["seconds"], 1e-9)
        return enc, info

    def _fit_all(self, T: torch.Tensor, p: dict, init=None):
        """All vertices in flood-fill order, a wavefront batch at a time. ``T [V, J, P]``."""
        V, J, P = T.shape
        N = p["lobes"]
        smin, smax = max(p["sigma_min"], resolvable_sigma(self.solid_angles_)), p["sigma_max"]
        if smin >= smax:
            smin = 0.5 * smax
        order, nbr = flood_fill_order(self.faces_, V)
        vn = view_neighbours(self.views_.double()).long()  # [J, R]
        beta = p["view_weight"] if vn.shape[1] else 0.0
        delta = p["spatial_weight"] if (N > 1 and nbr.shape[1]) else 0.0
        W = torch.zeros(V, J, N)
        MU = torch.zeros(V, J, N, 3)
        SG = torch.ones(V, J, N)
        done = torch.zeros(V, dtype=torch.bool)
        bv = max(1, p["batch_size"] // J)
        batches, fitted, not_conv = [], 0, 0
        dirs, sa = self.directions_, self.solid_angles_
        for b0 in range(0, V, bv):  # loop over batches of vertices (each batch: thousands of functions)
            tb = time.perf_counter()
            verts = order[b0:b0 + bv]
            Tb = T[verts]  # [bv, J, P]
            scale = (Tb.clamp_min(0).square() * sa).sum(-1).amax(1).sqrt().clamp_min(1e-30)  # [bv]
            Tn = (Tb / scale[:, None, None]).reshape(-1, P)
            nonzero = Tn.clamp_min(0).amax(1) > 1e-7
            sb = None
            if delta > 0:
                nb = nbr[verts]  # [bv, Q]
                okn = (nb >= 0) & done[nb.clamp_min(0)]
                pairs = prob_pairs(N)
                ii = torch.tensor([q[0] for q in pairs])
                jj = torch.tensor([q[1] for q in pairs])
                mun = MU[nb.clamp_min(0)]  # [bv, Q, J, N, 3]
                d = (mun[..., ii, :] - mun[..., jj, :]) * okn[:, :, None, None, None]  # [bv, Q, J, pairs, 3]
                sb = d.permute(0, 2, 3, 1, 4).reshape(-1, len(pairs), nb.shape[1], 3)
            with _threads_for(Tn.shape[0] * P * N):
                w, mu, sg, it, conv, E = _lm_batch(Tn, nonzero, dirs, sa, J, vn, N, beta, delta, sb, smin, smax,
                                                   p["max_iter"], p["tol"], self.views_,
                                                   None if init is None else tuple(t[verts].reshape(-1, *t.shape[2:]) / (
                                                       scale.repeat_interleave(J).reshape(-1, *[1] * (t.ndim - 2))
                                                       if i == 0 else 1) for i, t in enumerate(init)),
                                                   loop=_lm_loop if p["optimizer"] == "lm" else _lbfgs_loop)
            W[verts] = (w.reshape(-1, J, N) * scale[:, None, None]).float()
            MU[verts] = mu.reshape(-1, J, N, 3).float()
            SG[verts] = sg.reshape(-1, J, N).float()
            done[verts] = True
            nf = int(nonzero.sum())
            fitted += nf
            not_conv += int((~conv & nonzero).sum())
            batches.append({"vertices": int(verts.numel()), "functions": int(Tn.shape[0]), "nonzero_functions": nf,
                            "iterations": it, "converged_fraction": float(conv[nonzero].float().mean()) if nf else 1.0,
                            "objective_mean": float(E[nonzero].mean()) if nf else 0.0,
                            "seconds": time.perf_counter() - tb})
        live = W > 0
        at_limit = float((live & (SG <= smin * (1 + 1e-3))).sum()) / max(1, int(live.sum()))
        info = {"batches": batches, "functions": V * J, "functions_fitted": fitted, "not_converged": not_conv,
                "sigma_resolvable": smin, "lobes_at_resolution_limit": at_limit,
                "converged_fraction": 1.0 - not_conv / max(1, fitted), "lobes": N,
                "optimiser": ("batched Levenberg-Marquardt (4N x 4N Cholesky per function)" if p["optimizer"] == "lm"
                              else "L-BFGS (strong Wolfe) on the batch's summed objective"),
                "flood_fill": self.faces_ is not None}
        return W, MU, SG, info

    # ------------------------------------------------------------------ decode / relight
    @staticmethod
    def lobes_of(enc: Encoded) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(w [V, J, N], mu [V, J, N, 3], sigma [V, J, N])`` of an encoding: views of its lobe
        records (w, μx, μy, μz, σ) float32, read in place by the kernels. Stored view-major,
        ``lobes_by_view [J, V, N, 5]``: view j of vertices v, v+1, ... is one run, so a camera's
        taps (a few views shared by neighbouring vertices) read a few runs along the vertices —
        measured 1.4–2× faster at 50 000 vertices than vertex-major records, whose three tapped
        runs per vertex sit in three cache lines 20·J·N bytes apart
        (reports/benchmarks/relight.md). Encodings saved with vertex-major ``lobes [V, J, N, 5]``
        (format before 2026-11-24), or before the records (separate ``weights``, ``mu``,
        ``sigma``), are returned as they are."""
        t = enc.tensors
        name = "lobes_by_view" if "lobes_by_view" in t else "lobes"
        if name in t:
            rec = t[name]
            key = (name, rec.data_ptr(), tuple(rec.shape), rec.stride(), rec.dtype)  # .data = / set_() keep the object
            hit = enc.cache.get("lobe_views")
            if hit is not None and hit[0] is rec and hit[1] == key:  # three views cost ~12 µs a call, a sixth of a small relight
                return hit[2]
            if rec.ndim != 4 or rec.shape[-1] != 5:
                shape = "[J, V, N, 5]" if name == "lobes_by_view" else "[V, J, N, 5]"
                raise ValueError(f"encoding tensor {name!r} has shape {tuple(rec.shape)}; accepted: {shape}")
            r = rec.transpose(0, 1) if name == "lobes_by_view" else rec  # [V, J, N, 5]
            views = (r.select(-1, 0), r.narrow(-1, 1, 3), r.select(-1, 4))
            lay = lobe_layout(*views)  # kept only where it reads the records in place (float32): no copy to go stale
            enc.cache["lobe_views"] = (rec, key, views, lay if lay[0] is views[0] else None)
            return views
        missing = [k for k in ("weights", "mu", "sigma") if k not in t]
        if missing:
            raise ValueError(f"not a gaussian encoding: no tensor 'lobes_by_view' (nor 'lobes', nor {', '.join(map(repr, missing))}); "
                             f"it has {sorted(t)}")
        return t["weights"], t["mu"], t["sigma"]

    @classmethod
    def _lobes_and_layout(cls, enc: Encoded) -> tuple[tuple, tuple | None]:
        """``(lobes_of(enc), their relight_kernels.lobe_layout)``, the layout kept with the cached
        views (records; None for separate arrays, whose layout the kernels work out per call)."""
        views = cls.lobes_of(enc)
        hit = enc.cache.get("lobe_views")
        return views, (hit[3] if hit is not None and hit[2] is views else None)

    def decode(self, enc: Encoded) -> torch.Tensor:
        """The fitted tables ``[V, J·P]`` float32 (Green eq. 2.1 at the texel directions, plus
        the SH diffuse part where the view has data)."""
        self._require_fitted()
        w, mu, sg = self.lobes_of(enc)
        V, J, N = w.shape
        out = torch.empty(V, J, self.P_)
        step = max(1, 65536 // max(1, J))
        for a in range(0, V, step):  # chunks bound the [V·J, N, P] temporary
            b = min(V, a + step)
            out[a:b] = mixture(self.directions_, w[a:b].reshape(-1, N), mu[a:b].reshape(-1, N, 3),
                               sg[a:b].reshape(-1, N)).reshape(b - a, J, -1)
        if "diffuse" in enc.tensors:
            from ..sh import eval_sh

            Y = eval_sh(self.directions_.double(), int(enc.meta["diffuse_bands"]), check=False).float()
            out += (enc.tensors["diffuse"] @ Y.T)[:, None, :] * enc.tensors["has_data"].float()[..., None]
        return out.reshape(V, -1)

    def _check_light(self, light):
        if not isinstance(light, PrefilteredEnvironment):
            raise TypeError(f"codec {self.codec_name!r} relights from a Gaussian-prefiltered environment "
                            "(light_kind 'prefiltered': prt_torch.lighting.prefilter_environment(light)); "
                            f"got {type(light).__name__}")
        return light.check()  # the kernels size the pyramid from its ladder: a mismatch would read past it

    @staticmethod
    def _check_diffuse_light(enc, light):
        """An encoding with an SH diffuse part needs a light with SH coefficients."""
        if "diffuse" in enc.tensors and light.sh is None:
            raise ValueError(f"this encoding has an SH diffuse part of {enc.tensors['diffuse'].shape[1]} coefficients; accepted: "
                             "a PrefilteredEnvironment with SH coefficients (an SH light, or prefilter_environment(..., sh_bands=))")

    def _diffuse(self, enc, light):
        """t·l per vertex ``[V, C]`` (Green §3.1's SH diffuse part); an SH light with fewer
        coefficients is zero beyond them."""
        t = enc.tensors["diffuse"]
        self._check_diffuse_light(enc, light)
        L = torch.zeros(light.channels, t.shape[1])
        k = min(t.shape[1], light.sh.shape[1])
        L[:, :k] = light.sh[:, :k].float()
        return t @ L.T  # [V, C]

    def checked_taps(self, view: Any, V: int, J: int, values: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """A view as taps over the stored views: ``(idx int64 [V, k], w [V, k])`` as given, or
        the three nearest views of global directions ``[V, 3]`` (:func:`view_taps`). Refuses
        other shapes, indices outside 0..J-1 and weights that are negative or not finite (also
        once converted to float32), naming the first (shared by :meth:`relight` and the GLSL
        decoder). ``values=False`` checks types and shapes only, for a caller whose kernel flags
        bad values itself (``relight_kernels.sg_taps``) and then calls this to raise."""
        if isinstance(view, torch.Tensor):
            if view.shape != (V, 3):
                raise ValueError(f"view has shape {tuple(view.shape)}; accepted: taps (idx, w) or global directions [V, 3]")
            view = view_taps(self.views_, view / view.norm(dim=-1, keepdim=True).clamp_min(1e-12))
        if not (isinstance(view, (tuple, list)) and len(view) == 2):
            raise TypeError("view must be taps (idx int64 [V, k], w [V, k]) or directions [V, 3]")
        idx, a = (torch.as_tensor(v) for v in view)
        check_cpu("view taps", idx, a)
        if idx.ndim != 2 or idx.shape[0] != V or a.shape != idx.shape:
            raise ValueError(f"view taps have shapes {tuple(idx.shape)}, {tuple(a.shape)}; accepted: [V, k] with V={V}")
        if idx.is_floating_point() or idx.dtype == torch.bool:
            raise TypeError(f"view tap indices have dtype {idx.dtype}; accepted: an integer dtype")
        if not a.is_floating_point():
            raise TypeError(f"view tap weights have dtype {a.dtype}; accepted: a float dtype")
        idx = idx.long()
        if not values:
            return idx, a
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= J):
            raise ValueError(f"view tap indices span [{int(idx.min())}, {int(idx.max())}]; accepted: 0..{J - 1}")
        check_finite_float32("view tap weights", a)
        if a.numel() and bool((a < 0).any()):  # the blend (§2.3) is convex: a negative weight has no meaning
            first = tuple(int(i) for i in torch.nonzero(a < 0)[0])
            raise ValueError(f"view tap weights has a negative value {float(a[first]):g} at index {first}; accepted: "
                             "weights >= 0 (barycentric, as view_taps gives them)")
        return idx, a

    def relight(self, enc: Encoded, light: PrefilteredEnvironment, view: Any = None, out: torch.Tensor | None = None) -> torch.Tensor:
        """Exit radiance from the Gaussian form (Green eq. 2.7: Σ_k w_k E_{σ_k}(μ_k)).

        ``light``: :class:`PrefilteredEnvironment`. ``view``: None → every stored view,
        ``[V, J, C]``; taps ``(idx int64 [V, k], w [V, k])`` over the stored views (weights zero
        below the horizon, e.g. from :func:`view_taps`) → ``[V, C]`` with the lobes interpolated
        across the tapped views (§2.3); a tensor ``[V, 3]`` of global view directions → the
        three nearest views' taps, ``[V, C]``. float32. ``out``: an optional result tensor of
        that shape (``base.check_out``), written and returned.

        With taps of at least ``TAPS_CACHE_MIN_LOOKUPS`` lookups (V·N), the second call with the
        same taps tensors, unchanged, and a light of the same pyramid keeps their blend and its
        addressing in ``enc.cache['taps_prepared']`` (20 bytes per lobe and 4 per vertex), and
        later such calls read only the texels: the same bits (a static camera under changing
        light; :meth:`relighter` keeps it from the first call).
        """
        return self._relight_checked(enc, light, view, out)

    def _relight_checked(self, enc: Encoded, light, view: Any, out, prepare=None) -> torch.Tensor:
        """``relight``'s checks, then ``_relight``; ``prepare(light, lobes, taps)``: the prepared
        addressing to read (``GaussianRelighter``), or None."""
        self._require_fitted()
        light = self._check_light(light)
        lobes = self._lobes_and_layout(enc)
        V, J, _ = lobes[0][0].shape
        if view is not None:  # values: by the fused kernel as it reads them (it flags bad ones), else in _relight
            view = self.checked_taps(view, V, J, values=False)
        self._check_diffuse_light(enc, light)  # refused before anything is written into out
        if out is not None:  # the fused kernels write into it (no result-sized temporary and copy)
            out = check_out(out, (V, light.channels) if view is not None else (V, J, light.channels), view,
                            tuple(enc.tensors.values()), light.table(), light.log_sigmas)
        if prepare is not None:
            prepared = prepare(light, lobes, view)
        elif view is not None and V * lobes[0][0].shape[2] >= TAPS_CACHE_MIN_LOOKUPS:
            # taps: the blend kept in enc.cache from the second call with these taps on
            prepared, enc.cache["taps_prepared"] = self._prepare(enc, light, lobes, view, enc.cache.pop("taps_prepared", None),
                                                                 eager=False)
        else:
            prepared = None
        return self._relight(enc, light, view, out, lobes, prepared)

    def _prepare(self, enc: Encoded, light: PrefilteredEnvironment, lobes: tuple, taps: tuple | None, hit: tuple | None,
                 eager: bool) -> tuple:
        """The light-independent part of relighting ``enc`` with ``light`` — every lobe's pyramid
        addressing (``sg_prepare``), or with ``taps`` the blend across them and its addressing
        (``sg_taps_prepare``) — from ``hit = (key, prepared, held tensors, made)`` where its key
        is this call's: the light's resolution and width ladder, the lobe tensors' and the taps'
        states. Otherwise made now, or (not ``eager``) at the second call with the same key, so
        that taps that change at every call (a moving camera) cost only the key. → ``(prepared or
        None, the entry to keep)``. None where the kernels do not take it (no compiled kernels,
        not RGB, separate lobe arrays, a shape the 16-lane kernels do not take)."""
        lib = _fused(light)
        (w, mu, sg), layout = lobes
        if lib is None or light.channels != 3 or layout is None:
            return None, None
        held = tuple(enc.tensors.values())
        ladder = light.log_sigmas
        key = (light.res, ladder.dtype, ladder.numpy().tobytes(), _lobes_state(enc))
        if taps is not None:
            key += (tensor_state(taps[0]), tensor_state(taps[1]))
            held += tuple(taps)
        if hit is not None and hit[0] == key and hit[3]:
            return hit[1], hit
        if not eager and (hit is None or hit[0] != key):
            return None, (key, None, held, False)  # seen once
        if taps is None:
            prep = sg_prepare(lib, ladder, light.res, w, mu, sg, layout)
        else:
            prep, flag = sg_taps_prepare(lib, ladder, light.res, w, mu, sg, taps[0], taps[1].float(), layout=layout)
            if flag:  # a bad tap (nothing kept): raise naming it
                self.checked_taps(taps, w.shape[0], w.shape[1])
                raise RuntimeError("prt_sg_taps_prepare flagged the taps but none is out of range, negative or non-finite")  # pragma: no cover
        return prep, (key, prep, held, True)

    def relighter(self, enc: Encoded, view: Any = None) -> "GaussianRelighter":
        """A prepared relighting (``base.Relighter``): ``r = codec.relighter(enc)``, then ``r(light,
        out=buf)`` per light, the same bits as ``relight(enc, light, out=buf)``. Without a view,
        the addressing of every lobe in the pyramid (face, texel and level, and their fractions:
        most of a lookup's arithmetic, and independent of the light's values) is computed at the
        first light and kept while the lobes and the light's resolution and
        width ladder stay the same (20 bytes per lobe); each light then costs only the texel reads
        (reports/benchmarks/relight.md, "prepared"). With taps, the same for the lobes blended
        across each vertex's taps (the blend and its normalisation kept too: 20 bytes per blended
        lobe and Σa per vertex), kept while the taps are also unchanged (edited in place, replaced
        or converted: another int64 ``idx`` or another ``a`` prepares again); a view of global
        directions ``[V, 3]`` keeps its taps (:func:`view_taps`) while the directions are unchanged."""
        self._require_fitted()
        return GaussianRelighter(self, enc, view, {})

    def _relight(self, enc: Encoded, light: PrefilteredEnvironment, view: tuple | None, out: torch.Tensor | None = None,
                 lobes: tuple | None = None, prepared: torch.Tensor | None = None) -> torch.Tensor:
        """``view``: None or checked taps; ``out``: None or a checked result buffer; ``lobes``:
        ``_lobes_and_layout(enc)`` when the caller has them; ``prepared``: ``sg_prepare``'s
        addressing of these lobes for this light (every view), or ``sg_taps_prepare``'s of these
        lobes blended by these taps (taps)."""
        (w, mu, sg), layout = lobes if lobes is not None else self._lobes_and_layout(enc)
        V, J, N = w.shape
        if view is None:
            res = lobe_sum(light, w, mu, sg, out=out, layout=layout, prepared=prepared)
            if "diffuse" in enc.tensors:
                res += self._diffuse(enc, light)[:, None, :] * enc.tensors["has_data"].float()[..., None]
            return res
        lib = _fused(light)
        # the taps' values: checked by the fused kernel as it reads them (it flags a bad one), else here
        idx, a = view if lib is not None else self.checked_taps(view, V, J)
        a = a.float()
        if lib is not None and prepared is not None:  # the blend and addressing kept: per vertex only the texel reads
            res, flag = sg_taps_prepared(lib, prepared, light.table(), light.log_sigmas, light.res, out=out)
        elif lib is not None:  # blend, look up and sum in one fused pass per vertex
            res, flag = sg_taps(lib, light.table(), light.log_sigmas, light.res, w, mu, sg, idx, a, out=out, layout=layout)
            if flag:  # a bad tap (nothing computed or written): raise naming it
                self.checked_taps(view, V, J)
                raise RuntimeError("prt_sg_taps flagged the taps but none is out of range, negative or non-finite")  # pragma: no cover
        else:
            rows = torch.arange(V)[:, None]
            tot = a.sum(1, keepdim=True)
            wb, mb, sgb = blend_lobes(w[rows, idx], mu[rows, idx], sg[rows, idx], a / tot.clamp_min(1e-12))
            res = lobe_sum(light, wb, mb, sgb) * tot
            res = res if out is None else out.copy_(res)
        if "diffuse" in enc.tensors:
            hd = enc.tensors["has_data"].float()[torch.arange(V)[:, None], idx]
            res += self._diffuse(enc, light) * (a * hd).sum(1, keepdim=True)
        return res

    def relight_surface(self, enc: Encoded, light: PrefilteredEnvironment, faces: torch.Tensor, face_index: torch.Tensor,
                        bary: torch.Tensor, view_dirs: torch.Tensor) -> torch.Tensor:
        """Radiance at surface points inside triangles (Green §2.3): at each of the triangle's
        three vertices the lobes of the three nearest views are blended, then the three
        vertices' lobes are blended with the barycentric weights. ``faces [F, 3]``,
        ``face_index [M]``, ``bary [M, 3]``, global ``view_dirs [M, 3]`` → ``[M, C]`` float32."""
        self._require_fitted()
        light = self._check_light(light)
        w, mu, sg = self.lobes_of(enc)
        N = w.shape[2]
        vid = torch.as_tensor(faces).long()[face_index.long()]  # [M, 3]
        idx, a = view_taps(self.views_, view_dirs / view_dirs.norm(dim=-1, keepdim=True))
        M, k = idx.shape
        vv = vid[:, :, None].expand(M, 3, k)
        jj = idx[:, None, :].expand(M, 3, k)
        aa = a[:, None, :].expand(M, 3, k).reshape(M * 3, k)
        wv, mv, sv = blend_lobes(w[vv, jj].reshape(M * 3, k, N), mu[vv, jj].reshape(M * 3, k, N, 3),
                                 sg[vv, jj].reshape(M * 3, k, N), aa)
        wb, mb, sgb = blend_lobes(wv.reshape(M, 3, N), mv.reshape(M, 3, N, 3), sv.reshape(M, 3, N), bary.float())
        out = lobe_sum(light, wb, mb, sgb)
        if "diffuse" in enc.tensors:
            d = self._diffuse(enc, light)[vid]  # [M, 3, C]
            hd = enc.tensors["has_data"].float()[vv, jj]  # [M, 3, k]
            out = out + (bary.float()[..., None] * d * (hd * a[:, None, :]).sum(-1, keepdim=True)).sum(1)
        return out

    # ------------------------------------------------------------------ storage / state
    def relight_bytes(self, enc: Encoded, view: Any = None) -> int:
        """Without a view every stored lobe (and the diffuse part) is read; with taps ``(idx [V, k],
        a [V, k])`` only the k tapped views' lobes of each vertex (5 floats each), its diffuse part
        and the taps — the other views are never touched, so the whole encoding would be a bound
        J/k times too loose. A view of directions ``[V, 3]`` reads three views' lobes."""
        if view is None:
            return super().relight_bytes(enc)
        V, J, N = self.lobes_of(enc)[0].shape
        k = min(3, J) if isinstance(view, torch.Tensor) else int(torch.as_tensor(view[0]).shape[-1])
        diffuse = enc.tensors["diffuse"][0].numel() * 4 + k if "diffuse" in enc.tensors else 0  # and k has_data flags
        return V * (k * N * 5 * 4 + diffuse) + view_nbytes(view)

    def storage(self, enc: Encoded) -> dict[str, Any]:
        st = super().storage(enc)
        V, J, N = self.lobes_of(enc)[0].shape
        per_fn = N * 5
        floats = V * J * per_fn + (enc.tensors["diffuse"].numel() if "diffuse" in enc.tensors else 0)
        st.update({"sloan_cost_floats": floats, "floats_per_function": per_fn, "floats_per_lobe": 5,
                   "relight_macs_per_point_per_channel": N * 3 * 2})
        return st

    def _state(self):
        return ({"views": self.views_, "directions": self.directions_, "solid_angles": self.solid_angles_},
                {"J": self.J_, "P": self.P_, "layout": self.layout_})

    def _set_state(self, tensors, meta):
        self.views_, self.directions_, self.solid_angles_ = tensors["views"], tensors["directions"], tensors["solid_angles"]
        self.J_, self.P_, self.layout_ = int(meta["J"]), int(meta["P"]), meta["layout"]
        self.n_features_in_ = self.J_ * self.P_
        self.faces_ = None


def _lm_batch(Tn, nonzero, dirs, sa, J, vn, N, beta, delta, sb, smin, smax, max_iter, tol, views, init=None,
              restart_above=0.02, loop=None):
    """Batched Levenberg–Marquardt over ``Tn [B, P]`` (B = vertices·J, view-major within a
    vertex), from peaks and moments (or ``init = (w, mu, sigma)`` ``[B, N]``, ``[B, N, 3]``,
    ``[B, N]``). Functions still above ``restart_above`` relative L2 error afterwards get one
    restart with their weakest lobe re-initialised at the peak of the residual (kept when it
    lowers the objective). Returns (w [B, N], mu [B, N, 3], sigma [B, N], iterations,
    converged [B] bool, objective [B])."""
    B, P = Tn.shape
    dt = torch.float32
    loop = loop or _lm_loop
    dirs, sa = dirs.to(dt), sa.to(dt)
    view_of = torch.arange(B) % J
    z = ~nonzero
    base = (torch.arange(B) // J) * J

    def targets(mu, ls, sel):
        if beta <= 0:
            return None, None
        nbrs = base[sel, None] + vn[view_of[sel]]  # [b, R]
        mn, sn = mu[nbrs], ls.exp()[nbrs]  # [b, R, N, 3], [b, R, N]
        if mu.shape[1] > 1:  # lobe correspondence: lobe k of a view is aligned with the nearest lobe of each neighbour
            k = torch.einsum("bnc,brmc->brnm", mu[sel], mn).argmax(-1)  # [b, R, N]
            mn, sn = mn.gather(2, k[..., None].expand(-1, -1, -1, 3)), sn.gather(2, k)
        return mn.mean(1), sn.mean(1)

    def zero_start(a, ls, mu):  # zero functions: weights 0, the mean starts at the view, then follows the neighbours
        if bool(z.any()):
            mu[z] = views.to(dt)[view_of[z]][:, None, :].expand(-1, mu.shape[1], 3)
            ls[z] = math.log(min(max(0.5, smin), smax))
            a[z] = _LOG_W_MIN

    it = 0
    if init is not None:
        w0, mu, sg = (t.to(dt).clone() for t in init)
        mu = mu / mu.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        a, ls = w0.clamp_min(1e-10).log(), sg.clamp(smin, smax).log()
        zero_start(a, ls, mu)
        prob = _Problem(Tn, dirs, sa, N, beta, beta, delta, smin, smax)
        a, ls, mu, conv, it = loop(prob, a, ls, mu, z.clone(), z, targets, sb, max_iter, tol, smin, smax)
    else:
        # greedy: lobe k starts at the peak of the residual of the (k−1)-lobe fit (peaks and
        # moments), then all k lobes are optimised together
        Tp = Tn.clamp_min(0)
        a = torch.empty(B, 0, dtype=dt)
        ls = torch.empty(B, 0, dtype=dt)
        mu = torch.empty(B, 0, 3, dtype=dt)
        for k in range(1, N + 1):
            if k > 1:
                lam = torch.exp(-2 * ls)
                fit = ((a.exp() * sg_normaliser(lam))[..., None]
                       * torch.exp(lam[..., None] * (torch.einsum("bnc,pc->bnp", mu, dirs) - 1))).sum(1)
                res = (Tp - fit).clamp_min(0)
            else:
                res = Tp
            w1, m1, s1 = _init_lobes(res, dirs, sa, 1, smin, smax)
            a = torch.cat([a, w1.clamp_min(1e-10).log()], 1)
            ls = torch.cat([ls, s1.log()], 1)
            mu = torch.cat([mu, m1], 1)
            zero_start(a, ls, mu)
            prob = _Problem(Tn, dirs, sa, k, beta, beta, delta if k > 1 else 0.0, smin, smax)
            sbk = None
            if sb is not None and k > 1:
                sbk = sb[:, [q for q, (i, j) in enumerate(prob_pairs(N)) if j < k]]
            stage_iter = max_iter if k == N else max(5, max_iter // 4)  # earlier stages only start the next lobe
            a, ls, mu, conv, itk = loop(prob, a, ls, mu, z.clone(), z, targets, sbk, stage_iter, tol, smin, smax)
            it += itk
    sel = torch.arange(B)
    tm, ts = targets(mu, ls, sel)
    E, r = prob.evaluate(a, ls, mu, sel, tm, ts, sb)[:2]
    ref = (Tn.square() * sa).sum(1)
    rel = ((r.square() * sa).sum(1) / ref.clamp_min(1e-30)).sqrt()
    bad = nonzero & (rel > restart_above)
    if N > 1 and bool(bad.any()):
        bi = bad.nonzero()[:, 0]
        k = a[bi].argmin(1)
        a2, ls2, mu2 = a.clone(), ls.clone(), mu.clone()
        keep = torch.ones(bi.numel(), N, dtype=torch.bool)
        keep[torch.arange(bi.numel()), k] = False
        lam = torch.exp(-2 * ls[bi])
        others = ((a[bi].exp() * sg_normaliser(lam) * keep)[..., None]
                  * torch.exp(lam[..., None] * (torch.einsum("bnc,pc->bnp", mu[bi], dirs) - 1))).sum(1)
        w1, m1, s1 = _init_lobes((Tn[bi] - others).clamp_min(0), dirs, sa, 1, smin, smax)
        a2[bi, k] = w1[:, 0].clamp_min(1e-10).log()
        mu2[bi, k] = m1[:, 0]
        ls2[bi, k] = s1[:, 0].log()
        a2, ls2, mu2, conv2, it2 = loop(prob, a2, ls2, mu2, ~bad, z, targets, sb, max(5, max_iter // 2), tol, smin, smax)
        E2 = prob.evaluate(a2[bi], ls2[bi], mu2[bi], bi, *targets(mu2, ls2, bi), None if sb is None else sb[bi])[0]
        better = E2 < E[bi]
        gi = bi[better]
        a[gi], ls[gi], mu[gi], conv[gi], E[gi] = a2[gi], ls2[gi], mu2[gi], conv2[gi], E2[better]
        it += it2
    w = a.exp()
    w[z] = 0.0
    w = torch.where(a <= _LOG_W_MIN + 1e-3, torch.zeros_like(w), w)
    return w, mu, ls.exp(), it, conv | z, E


def prob_pairs(N: int) -> list[tuple[int, int]]:
    """Lobe pairs (k1 < k2) of eq. 2.6 in the order of the S residuals."""
    return [(i, j) for i in range(N) for j in range(i + 1, N)]


def _lm_loop(prob, a, ls, mu, conv, z, targets, sb, max_iter, tol, smin, smax):
    """The LM iterations on the functions not yet ``conv`` (per-function damping λ: ÷3 on an
    accepted step, ×5 on a rejected one). Zero functions ``z`` take the minimiser of M + V."""
    B = a.shape[0]
    lm = torch.full((B,), 1e-3, dtype=torch.float64)
    it = 0
    for it in range(1, max_iter + 1):
        act = (~conv).nonzero()[:, 0]
        if prob.beta > 0 and bool(z.any()):  # zero functions: the minimiser of M + V alone (eq. 2.4-2.5)
            zi = z.nonzero()[:, 0]
            tm, ts = targets(mu, ls, zi)
            mu[zi] = tm / tm.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            ls[zi] = ts.clamp(smin, smax).log()
        if act.numel() == 0:
            break
        tm, ts = targets(mu, ls, act)
        sba = None if sb is None else sb[act]
        JtJ, Jtr, E0 = prob.normal_equations(a[act], ls[act], mu[act], act, tm, ts, sba)
        # active set (projected Newton): a log-width or log-weight at its bound whose gradient
        # points outward is frozen for this step (its row and column replaced by the identity,
        # its gradient zeroed), so the bound no longer swallows the step of the others
        nA = act.numel()
        frozen = torch.zeros(nA, a.shape[1], 4, dtype=torch.bool)
        g4 = Jtr.view(nA, -1, 4)
        frozen[..., 1] = ((ls[act] <= prob.lsmin + 1e-6) & (g4[..., 1] > 0)) | ((ls[act] >= prob.lsmax - 1e-6) & (g4[..., 1] < 0))
        frozen[..., 0] = (a[act] <= _LOG_W_MIN + 1e-6) & (g4[..., 0] > 0)
        frozen = frozen.reshape(nA, -1)
        if bool(frozen.any()):
            free = (~frozen).double()
            JtJ = JtJ * free[:, :, None] * free[:, None, :] + torch.diag_embed(frozen.double())
            Jtr = Jtr * free
        diag = torch.diagonal(JtJ, dim1=1, dim2=2)
        A = JtJ + torch.diag_embed(lm[act, None] * diag + 1e-12 * (1 + diag.amax(1, keepdim=True)))
        L, info = torch.linalg.cholesky_ex(A)
        step = torch.cholesky_solve(-Jtr[..., None], L)[..., 0]
        step = torch.where((info == 0)[:, None], step, torch.zeros_like(step)).clamp(-2.0, 2.0)
        a2, ls2, mu2 = prob.step(a[act], ls[act], mu[act], step)
        E1 = prob.evaluate(a2, ls2, mu2, act, tm, ts, sba)[0]
        acc = (E1 <= E0) & torch.isfinite(E1)
        ai = act[acc]
        a[ai], ls[ai], mu[ai] = a2[acc], ls2[acc], mu2[acc]
        lm[act] = torch.where(acc, lm[act] / 3, lm[act] * 5).clamp(1e-9, 1e12)
        small = ((E0 - E1).abs() <= tol * E0.abs() + 1e-14) | (step.abs().amax(1) < 1e-4).to(acc.device)
        conv[act] = (acc & small) | (lm[act] >= 1e12) | (E0 <= 1e-14)
    return a, ls, mu, conv, it


def _lbfgs_loop(prob, a, ls, mu, conv, z, targets, sb, max_iter, tol, smin, smax):
    """The alternative to :func:`_lm_loop` with the same contract: ``torch.optim.LBFGS``
    (history 10, strong-Wolfe line search) on the summed objective of the functions not yet
    ``conv``, ``max_iter`` iterations; log-widths through a sigmoid between the bounds, means
    normalised from free 3-vectors, log-weights free. The view targets are fixed for the call
    (the LM loop refreshes them every iteration). One line search serves the whole batch, so
    convergence is only known for the batch: all functions are marked converged when L-BFGS
    stopped on its tolerance before ``max_iter``."""
    act = (~conv).nonzero()[:, 0]
    if prob.beta > 0 and bool(z.any()):
        zi = z.nonzero()[:, 0]
        tm, ts = targets(mu, ls, zi)
        mu[zi] = tm / tm.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        ls[zi] = ts.clamp(smin, smax).log()
    if act.numel() == 0:
        return a, ls, mu, conv, 0
    tm, ts = targets(mu, ls, act)
    sba = None if sb is None else sb[act]
    lo, span = prob.lsmin, prob.lsmax - prob.lsmin
    p_a = a[act].clone().requires_grad_()
    p_s = torch.logit(((ls[act] - lo) / span).clamp(1e-4, 1 - 1e-4)).requires_grad_()
    p_m = mu[act].clone().requires_grad_()
    opt = torch.optim.LBFGS([p_a, p_s, p_m], lr=1.0, max_iter=max_iter, history_size=10, line_search_fn="strong_wolfe",
                            tolerance_change=tol * 1e-3, tolerance_grad=1e-10)
    scale = 1.0 / act.numel()

    def closure():
        opt.zero_grad()
        m = p_m / p_m.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        E = prob.evaluate(p_a, lo + span * torch.sigmoid(p_s), m, act, tm, ts, sba)[0]
        loss = E.sum() * scale
        loss.backward()
        return loss

    opt.step(closure)
    it = int(opt.state[p_a].get("n_iter", max_iter))
    with torch.no_grad():
        a[act] = p_a.detach().clamp(_LOG_W_MIN, 60.0)
        ls[act] = lo + span * torch.sigmoid(p_s.detach())
        mu[act] = p_m.detach() / p_m.detach().norm(dim=-1, keepdim=True).clamp_min(1e-12)
    conv[act] = it < max_iter
    return a, ls, mu, conv, it


def _lobes_state(enc: Encoded) -> tuple:
    """What a cache derived from a Gaussian encoding's lobes compares: its point count, its tensors'
    names (the layout: view-major ``lobes_by_view`` or vertex-major ``lobes``) and each one's
    ``_checks.tensor_state`` (address, shape and strides too: ``t.data = t[..., :1]`` keeps the
    address and the version; ``base.encoding_state`` keys only identity, address and version)."""
    return (enc.meta.get("points"), tuple(enc.tensors), *(tensor_state(t) for t in enc.tensors.values()))


# relight with taps keeps their blend and its addressing (GaussianCodec._prepare) from the second
# call with the same taps on where they make at least this many lookups (V·N): its key costs about
# 4 µs a call, which taps that change at every call (a moving camera) pay for nothing — under 10%
# of a relight from here on (about 10 ns a lookup), while unchanged taps relight 2.5-4x faster
TAPS_CACHE_MIN_LOOKUPS = 4096


class GaussianRelighter(Relighter):
    """``GaussianCodec.relighter``: relighting from the lobes' prepared addressing
    (``relight_kernels.sg_prepare``; with taps ``sg_taps_prepare``, of the lobes blended across
    the taps), kept with the state it was computed from — the light's resolution and width
    ladder, the lobe tensors' names and states (``_lobes_state``) and the
    taps' (``_checks.tensor_state``): an edit of the lobes or taps, a replaced tensor or a light
    of another pyramid computes it again. Lights of other channel counts than 3, or no compiled
    kernels, relight as ``relight`` does. Edits that bypass torch's version counter (through
    numpy) are not seen.

    With taps, a call takes a fast path when the last call took the prepared path and nothing it
    checked has changed since: the same light object with the same fields at the same states
    (``_checks.tensor_state``: what ``PrefilteredEnvironment.check`` memoises), the same ``out``
    at the same address and layout, the same taps and lobes at the same states, the codec not
    refitted (its views at the same state), the kernels not switched off (``PRT_TORCH_NATIVE``),
    and no SH diffuse part. Then only the prepared kernel runs (relight's checks cost
    about 25 µs a call: a tenth of a one-lobe relight of 50 000 vertices at 2 threads)."""

    __slots__ = ("_prep", "_taps", "_hot")

    def __init__(self, codec: GaussianCodec, enc: Encoded, view: Any, kwargs: dict):
        super().__init__(codec, enc, view, kwargs)
        self._prep: tuple | None = None  # GaussianCodec._prepare's entry: (key, prepared, held tensors, made)
        self._taps: tuple | None = None  # a view of directions: (key, its taps, the directions, the codec's views)
        self._hot: tuple | None = None  # taps: (light, out, _hot_key, lib, prepared, table, held, the kernel's arguments)

    def _hot_key(self, light: PrefilteredEnvironment, out: torch.Tensor | None) -> list | None:
        """What the fast path compares: the states of the light's fields, ``out``'s, the view's
        and the encoding's tensors, the light's sizes and the codec's views (the tensors are held
        with the key in ``_hot``, so that no id is reused); None where the view is not tensors."""
        view = self.view
        vt = view if isinstance(view, tuple) else (view,)
        if not all(isinstance(t, torch.Tensor) for t in vt):
            return None
        key = [light.res, light.channels, self.codec.J_, _lobes_state(self.enc)]
        for t in (self.codec.views_, light.levels, light.sigmas, light.log_sigmas, light.cube, light.sh, out, *vt):
            key.append(tensor_state(t) if isinstance(t, torch.Tensor) else id(t))  # (a reassigned non-tensor: checked on the full path)
        return key

    def __call__(self, light: Any, out: torch.Tensor | None = None) -> torch.Tensor:
        hot = self._hot
        if (hot is not None and light is hot[0] and out is hot[1] and native() is hot[3]
                and self._hot_key(light, out) == hot[2]):
            if out is not None:  # the kernel's arguments as the full call checked them (all unchanged since)
                if not hot[3].prt_sg_taps_prepared(*hot[7], torch.get_num_threads()):
                    return out
            else:
                res, flag = sg_taps_prepared(hot[3], hot[4], hot[5], light.log_sigmas, light.res)
                if not flag:
                    return res
        self._hot = None  # a full call (which raises for a bad tap), then the fast path again where it can
        res = self._full(light, out)
        prep = self._prep
        if (self.view is not None and isinstance(light, PrefilteredEnvironment) and prep is not None and prep[1] is not None
                and "diffuse" not in self.enc.tensors and _fused(light) is not None and light.channels == 3):
            held = (self.codec.views_, light.levels, light.sigmas, light.log_sigmas, light.cube, light.sh, out, prep[2])
            key = self._hot_key(light, out)
            if key is not None:
                table = light.table()
                call = None if out is None else sg_taps_prepared_call(prep[1], table, light.log_sigmas, light.res, out)[1]
                self._hot = (light, out, key, _fused(light), prep[1], table, held, call)
        return res

    def _full(self, light: Any, out: torch.Tensor | None) -> torch.Tensor:
        view = self.view
        if isinstance(view, torch.Tensor):  # global directions [V, 3]: their three nearest views' taps, kept
            hit, key = self._taps, (tensor_state(view), tensor_state(self.codec.views_))  # (a refit replaces the views)
            if hit is None or hit[0] != key:
                V, J, _ = self.codec.lobes_of(self.enc)[0].shape
                hit = self._taps = (key, self.codec.checked_taps(view, V, J, values=False), view, self.codec.views_)
            view = hit[1]
        return self.codec._relight_checked(self.enc, light, view, out, prepare=self._prepared)

    def _prepared(self, light: PrefilteredEnvironment, lobes: tuple, taps: tuple | None) -> tuple | torch.Tensor | None:
        prep, self._prep = self.codec._prepare(self.enc, light, lobes, taps, self._prep, eager=True)
        return prep
