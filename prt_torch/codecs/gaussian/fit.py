"""The fit of a Gaussian encoding (Green 2005 §2.2, eq. 2.1–2.6): the mixture itself (eq. 2.1), the
objective and its batched optimiser, the starting lobes, the narrowest lobe a table resolves and
the flood-fill order of the vertices (§2.2.2); :func:`fit_all` runs it over a transport table.

Fit (Green eq. 2.2): for all functions of a batch of vertices at once, minimise

    α D + β M + γ V + δ S
    D = Σ_ω Δω (T̃(ω) − T(ω))²                                              (eq. 2.3/3.1)
    M = Σ_k ‖(1/R) Σ_{r(v)} μ_k^{r} − μ_k^{v}‖²,  V = Σ_k ((1/R) Σ_{r(v)} σ_k^{r} − σ_k^{v})²   (eq. 2.4, 2.5)
    S = Σ_{k1<k2} Σ_{s(x)} max(−⟨μ_{x,k1} − μ_{x,k2}, μ_{s,k1} − μ_{s,k2}⟩, 0)³            (eq. 2.6)

(D weighted by the texel solid angles, so it is the L2 norm on the sphere; T is scaled per
vertex to unit peak energy so the weights β, γ, δ are relative). Optimiser: batched
Levenberg–Marquardt — each function has 4N unknowns (log w, log σ and two tangent-plane
coordinates of μ, re-centred every step: constraints by reparameterisation), so the normal
equations are 4N×4N (assembled from per-texel moments, :meth:`Problem.normal_equations`) and
one batched Cholesky solve per iteration serves thousands of functions; Gauss–Newton converges
in a few tens of steps on these near-Gaussian lobes (Green reports "several hundred" fmincon
iterations). The loop runs compiled where a C compiler is (:mod:`.lm_native`: each function's step in
one pass over its texels; :func:`_lm_loop` is the same iterations in torch, run with
``PRT_TORCH_NATIVE=0``). ``optimizer='lbfgs'`` (torch's L-BFGS on the batch's summed objective) is kept as
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

The narrowest lobe is :func:`resolvable_sigma` (0.35 × the texel spacing; it was 0.6 until issue 42 §2):
narrower, a fit could put a lobe between texel centres whose prefiltered integral (what rendering
uses) the texel values no longer constrain. At 0.6 the bound itself was the error of the default
tables (Ashikhmin–Shirley N = 40 at res: auto = 13): their energy sits at grazing views, where the
lobe is cos θ_o times narrower across the plane of incidence, so a quarter to a third of the lobes
sat at the bound and 3 lobes fitted no better than 1
(docs/precompute_log.md, "Transport tables: `res: auto` — what it did to the Gaussian codec").

Initialisation: peaks and moments — lobe k at the centroid of the half-maximum region around
the largest remaining value, σ² from that region's solid angle (2π ln2 σ² for a Gaussian),
w from the peak height. Without ``init`` the start is greedy (as Green's fit of lobes one at a
time): lobe k starts at the residual peak of the (k−1)-lobe fit after a short LM stage
(a quarter of ``max_iter``), then all N lobes are optimised together.

Convergence (issue 42 §2): a function has converged when an accepted step lowers its objective
by at most ``tol`` of it (or every step coordinate is below 1e-4, or its damping reached 1e12).
Each iteration forms the normal equations once and tries up to :data:`LM_TRIES` damped solves
on them (Marquardt's inner loop): with one, a third of the iterations of 3-lobe fits on the
default tables were rejected steps and 38% of the functions stopped unconverged at max_iter
20; with 5 tries and max_iter 30, 92% converge (benchmarks/bench_gaussian_convergence.py,
reports/benchmarks/gaussian_convergence.md). Converged functions leave the active set, so the
larger budget costs only the functions that use it.
"""
from __future__ import annotations

import contextlib
import math
import os
import time

import torch

from ...lighting.prefilter import sg_normaliser
from . import lm_native
from .views import view_neighbours

__all__ = ["mixture", "resolvable_sigma", "flood_fill_order", "fit_all", "Problem", "tangents", "prob_pairs", "RESOLVE_FACTOR"]

_LOG_W_MIN = math.log(1e-10)
#: narrowest lobe, in texel spacings (resolvable_sigma). Was 0.6: on the default transport tables
#: (Ashikhmin–Shirley N = 40, res: auto = 13; 150 vertices of scan_blob / bumpy_sphere:medium) 0.35
#: takes the whole-table relative L2 of 1 → 3 lobes from 0.560 → 0.547 / 0.586 → 0.572 to 0.310 → 0.202 /
#: 0.352 → 0.234 (no width-limit warning), and the encodings' constant-light relighting (Σ w, the SG
#: integrals) from 0.27–0.33 to 0.08–0.19 of the table's texel sum (benchmarks/bench_transport_res.py
#: --resolve-factor 0.6 0.35; docs/precompute_log.md, "Texel averages and the fit's width bound")
RESOLVE_FACTOR = 0.35
#: functions still above this relative L2 error after the fit get one restart of their weakest lobe
#: (_lm_batch). Was 0.02, below the median function's error of two lobes on 6×8×8 tables (0.11-0.12),
#: so most functions paid 10 more iterations for nothing: on the default benchmark's 10k-vertex tables
#: (42 views, Phong s = 12; the first 600 / 1000 vertices, 2 lobes) 0.2 gives the same error (whole-table
#: relative L2 0.12302 vs 0.12297, 0.11378 vs 0.11372; SE +0.1%; median and p90 unchanged to 4 digits)
#: for 27-28% less CPU time (benchmarks/profile_gaussian_part.py, docs/harness.md)
RESTART_ABOVE = 0.2
#: a starting lobe (peaks and moments, and the restart's) is no narrower than this many texel spacings,
#: the former width bound: the fit may then narrow it to resolvable_sigma. Started at 0.35 instead, 2 lobes
#: on Phong s = 12 tables (the default benchmark's part: 600 vertices × 42 views, 6×8×8) end at relative L2
#: 0.1260 against 0.1230 with the former bound; started at 0.6, 0.1244 (and 0.1507 instead of 0.1484 at
#: 3 lobes on the default Ashikhmin–Shirley tables, r = 13 texel averages)
START_FACTOR = 0.6
#: damped solves per LM iteration (_lm_loop, gauss_lm.c): a rejected trial step is retried at 5× the damping
#: on the same normal equations (Marquardt's inner loop) before the iteration ends. Was 1 (with max_iter 20):
#: a third of the trial steps were rejected, each costing a whole iteration, and 38% of the functions of 3 lobes
#: on the default tables (Ashikhmin–Shirley N = 40, r = 13 texel averages, 150 vertices spread over scan_blob)
#: stopped unconverged; 5 tries with max_iter 30: 92% converged, relative L2 0.152 -> 0.142 at 3 lobes
#: (benchmarks/bench_gaussian_convergence.py, docs/codecs_log.md "Convergence")
LM_TRIES = 5


def mixture(dirs: torch.Tensor, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Σ_k w_k G(ω, μ_k, σ_k) (Green eq. 2.1) at ``dirs [P, 3]`` for ``w [B, N]``, ``mu [B, N, 3]``,
    ``sigma [B, N]`` → ``[B, P]`` (dtype of w)."""
    lam = sigma.reciprocal().square()
    cos = torch.einsum("bnc,pc->bnp", mu, dirs.to(mu.dtype))
    return torch.einsum("bn,bnp->bp", w * sg_normaliser(lam), torch.exp(lam[..., None] * (cos - 1)))


def resolvable_sigma(solid_angles: torch.Tensor) -> float:
    """The narrowest lobe a fit may use: :data:`RESOLVE_FACTOR` · h = 0.35 h, h = √(largest texel
    solid angle) (2/r on a cube map). Below it the texel sum of a Gaussian departs from its
    integral (the Riemann sum of a Gaussian of width σ on spacing h errs by ~2 exp(−2π²σ²/h²) per
    axis at a face centre, more across the cube's seams: brute-force texel sums of unit lobes at
    4000 random means, r = 8: 0.98–1.02 at 0.6 h, 0.63–1.39 at 0.35 h; r = 13: 0.68–1.36 at 0.35 h;
    ``tests/test_gaussian.py`` checks ±40%), so a fit could put a lobe between texel centres whose
    prefiltered integral the data do not constrain. At 0.35 h a lobe's texel sum is that far off, but
    the fitted encodings' constant-light relighting (Σ_k w_k against Σ_p T Δω) errs less than at
    0.6 h (0.05–0.08 vs 0.18 relative at 3 lobes on the default tables, 0.15–0.19 vs 0.09 at one:
    the fit's residual, not the Riemann error, sets it;
    docs/precompute_log.md, "Texel averages and the fit's width bound")."""
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
    """One thread for batches below ``small`` texel·lobe evaluations when the cores are not free:
    other processes held them at import (``OMP_WAIT_POLICY=PASSIVE``, chosen by :mod:`prt_torch`)
    or hold them now (:func:`prt_torch.busy_now`, checked per batch: a long fit outlives the
    import-time choice). There the per-op thread hand-off of the many mid-sized tensors of an LM
    step costs more than it gains: 200 functions: 0.4 s on 1 thread vs 3–9 s on 2; 4600 functions
    × 2 lobes: 17 s vs 62 s (PASSIVE, load 5–7); with spinning threads (``OMP_WAIT_POLICY=ACTIVE``)
    beside one or two other processes (load 2.7–4.3), 1000 vertices × 42 views, 1 lobe: 2.9–6.0 s
    wall on 1 thread vs 12.7–47.7 s on 2 (and 3.7–4.2 vs 8.5–47 s of CPU); the default benchmark's
    10k part, imported at load 2.4 (spinning) and then shared, spent 164 CPU s on the one-lobe fit
    and its error pass that took 31 in one thread. On an idle machine all threads."""
    n = torch.get_num_threads()
    if n > 1 and work < small:
        from ... import busy_now

        if os.environ.get("OMP_WAIT_POLICY", "").upper() == "PASSIVE" or busy_now():
            torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def tangents(mu: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Orthonormal tangents (t1, t2) ``[..., 3]`` of unit ``mu [..., 3]``."""
    ax = torch.zeros_like(mu)
    i = mu.abs().argmin(-1, keepdim=True)
    ax.scatter_(-1, i, 1.0)
    t1 = torch.linalg.cross(mu, ax)
    t1 = t1 / t1.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return t1, torch.linalg.cross(mu, t1)


def _init_lobes(T: torch.Tensor, dirs: torch.Tensor, sa: torch.Tensor, N: int, smin: float, smax: float):
    """Peaks and moments (module docstring): ``T [B, P]`` ≥ 0 mostly → ``(w [B, N], mu [B, N, 3],
    sigma [B, N])``. A loop over the N lobes, each step batched over all B functions."""
    B = T.shape[0]
    R = T  # not written in place: each lobe's subtraction makes a new tensor
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
        # (the margin: texels at the same angle from the peak as c_out's — cube-map symmetry — stay out of
        # the cap whatever the rounding of cos; without it 2% of random functions started differently in
        # the compiled start, lm_native.peaks, whose cos rounds otherwise than this GEMM)
        cap = cos > c_out[:, None] + 1e-6
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
        if k < N - 1:  # the residual for the next lobe (none after the last: the fit calls this with N = 1)
            R = R - wk[:, None] * sg_normaliser(lam)[:, None] * torch.exp(lam[:, None] * (m @ dirs.T - 1))
    return w, mu, sg


def _start_lobe(R: torch.Tensor, dirs: torch.Tensor, sa: torch.Tensor, smin: float, smax: float):
    """One lobe by peaks and moments for each row of ``R [B, P]`` → ``(w [B, 1], mu [B, 1, 3], sigma
    [B, 1])``: :func:`_init_lobes`, compiled where the LM loop is (:func:`.lm_native.peaks`, the same
    values to float32 rounding; 3× less CPU time, 4000 functions of 384 texels)."""
    if lm_native.available():
        return lm_native.peaks(R, dirs.T, sa, smin, smax)
    return _init_lobes(R, dirs, sa, 1, smin, smax)


class Problem:
    """One batch: functions ``T [B, P]`` (scaled), the geometry and the regularisers."""

    def __init__(self, T, dirs, sa, N, beta, gamma, delta, smin, smax, energy=None):
        self.T, self.dirs, self.sa = T, dirs, sa
        self.dirs_t = dirs.T.contiguous()  # [3, P]
        # [B]: β, γ, δ act relative to each function's energy Σ Δω T² (given: the caller's, of these T)
        self.energy = (T.square() * sa).sum(1) if energy is None else energy
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
        T = self.T if sel.numel() == self.T.shape[0] else self.T[sel]  # sel: sorted distinct indices
        lam = torch.exp(-2 * ls)
        if torch.is_grad_enabled() and (a.requires_grad or ls.requires_grad or mu.requires_grad):
            coef = (torch.exp(a) * sg_normaliser(lam))[..., None]
            term = torch.exp(lam[..., None] * (torch.matmul(mu, self.dirs.T) - 1)) * coef
            r = term.sum(1) - T
            E = (r * r * self.sa).sum(1)
        else:
            # w c(λ) exp(λ(μ·ω − 1)) = exp(λμ·ω + log(w c(λ)) − λ): one GEMM with the bias, one exp pass
            # (was a GEMM and four passes over [b, N, P]); log w = a, log c(λ) of the [b, N] widths
            b, N = a.shape
            bias = (a + sg_normaliser(lam).log() - lam).reshape(-1, 1)
            term = torch.addmm(bias, (mu * lam[..., None]).reshape(-1, 3), self.dirs_t).view(b, N, -1).exp_()
            r = term.sum(1).sub_(T)
            E = torch.mv(r.square(), self.sa)
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
        t1, t2 = tangents(mu)
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
        # A_k M_kl A_lᵀ as two batched 4×4 products ([b, N, N, 4, 4]; the same bits and, measured, the same
        # time as the three-operand einsum "bkij,bkljm,blnm->bkiln": 6.2 ms per 4096 functions × 2 lobes)
        JtJ = torch.matmul(torch.matmul(A[:, :, None], M), A[:, None].transpose(-1, -2))
        JtJ = JtJ.permute(0, 1, 3, 2, 4).reshape(b, 4 * N, 4 * N)
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
        t1, t2 = tangents(mu)
        a2 = (a + d[..., 0]).clamp(_LOG_W_MIN, 60.0)
        ls2 = (ls + d[..., 1]).clamp(self.lsmin, self.lsmax)
        m2 = mu + d[..., 2:3] * t1 + d[..., 3:4] * t2
        return a2, ls2, m2 / m2.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def fit_all(T: torch.Tensor, p: dict, init, directions: torch.Tensor, solid_angles: torch.Tensor, views: torch.Tensor,
            faces: torch.Tensor | None):
    """All vertices in flood-fill order, a wavefront batch at a time (``GaussianCodec.fit``): ``T [V, J, P]``,
    the codec parameters ``p``, ``init`` (None or its ``(w, mu, sigma)``), the table geometry
    (texel ``directions [P, 3]`` and ``solid_angles [P]``, ``views [J, 3]``) and the mesh ``faces``
    (None: no flood fill, no spatial term). → ``(w [V, J, N], mu [V, J, N, 3], sigma [V, J, N],
    info)``."""
    V, J, P = T.shape
    N = p["lobes"]
    smin, smax = max(p["sigma_min"], resolvable_sigma(solid_angles)), p["sigma_max"]
    if smin >= smax:
        smin = 0.5 * smax
    order, nbr = flood_fill_order(faces, V)
    vn = view_neighbours(views.double()).long()  # [J, R]
    beta = p["view_weight"] if vn.shape[1] else 0.0
    delta = p["spatial_weight"] if (N > 1 and nbr.shape[1]) else 0.0
    W = torch.zeros(V, J, N)
    MU = torch.zeros(V, J, N, 3)
    SG = torch.ones(V, J, N)
    done = torch.zeros(V, dtype=torch.bool)
    bv = max(1, p["batch_size"] // J)
    batches, fitted, not_conv = [], 0, 0
    dirs, sa = directions, solid_angles
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
                                               p["max_iter"], p["tol"], views,
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
            # which LM loop ran (benchmarks name the path a row used): compiled (lm_native) or torch (fit._lm_loop)
            "lm_loop": ("compiled" if lm_native.available() else "torch") if p["optimizer"] == "lm" else None,
            "lm_tries": LM_TRIES if p["optimizer"] == "lm" else None,  # damped solves per LM iteration
            "flood_fill": faces is not None}
    return W, MU, SG, info


def _lm_batch(Tn, nonzero, dirs, sa, J, vn, N, beta, delta, sb, smin, smax, max_iter, tol, views, init=None,
              restart_above=None, loop=None, tries=None):
    """Batched Levenberg–Marquardt over ``Tn [B, P]`` (B = vertices·J, view-major within a
    vertex), from peaks and moments (or ``init = (w, mu, sigma)`` ``[B, N]``, ``[B, N, 3]``,
    ``[B, N]``). Functions still above ``restart_above`` (default :data:`RESTART_ABOVE`) relative L2 error afterwards get one
    restart with their weakest lobe re-initialised at the peak of the residual (kept when it
    lowers the objective). Returns (w [B, N], mu [B, N, 3], sigma [B, N], iterations,
    converged [B] bool, objective [B]: 0 for the zero functions)."""
    B, P = Tn.shape
    dt = torch.float32
    loop = loop or _lm_loop
    tries = LM_TRIES if tries is None else tries
    if loop is _lm_loop and lm_native.available():  # the same iterations compiled (PRT_TORCH_NATIVE=0: the torch loop)
        def loop(prob, a, ls, mu, conv, z, targets, sb, max_iter, tol, smin, smax):
            return lm_native.lm_loop(prob, a, ls, mu, conv, z, sb, max_iter, tol, smin, smax, vn, J, tries)
    elif loop is _lm_loop:
        def loop(prob, a, ls, mu, conv, z, targets, sb, max_iter, tol, smin, smax):
            return _lm_loop(prob, a, ls, mu, conv, z, targets, sb, max_iter, tol, smin, smax, tries)
    restart_above = RESTART_ABOVE if restart_above is None else restart_above
    s_start = min(smax, max(smin, START_FACTOR * math.sqrt(float(sa.max()))))  # a starting lobe's narrowest width
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

    ref = (Tn.square() * sa).sum(1)  # [B] each function's energy Σ Δω T² (the Problem's, and the relative L2's reference)
    nzi = nonzero.nonzero()[:, 0]
    it = 0
    if init is not None:
        w0, mu, sg = (t.to(dt).clone() for t in init)
        mu = mu / mu.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        a, ls = w0.clamp_min(1e-10).log(), sg.clamp(smin, smax).log()
        zero_start(a, ls, mu)
        prob = Problem(Tn, dirs, sa, N, beta, beta, delta, smin, smax, energy=ref)
        a, ls, mu, conv, it = loop(prob, a, ls, mu, z.clone(), z, targets, sb, max_iter, tol, smin, smax)
    else:
        # greedy: lobe k starts at the peak of the residual of the (k−1)-lobe fit (peaks and
        # moments), then all k lobes are optimised together
        # peaks and moments of the nonzero functions only (the zero ones — about half — take zero_start's
        # values): the first 1000 vertices of the default benchmark's 10k tables, 2 lobes, one thread, whole fit
        # 7.37-7.50 → 6.74-6.88 s CPU (paired, load 3-5), the same relative L2 and SE to 5 digits
        Tp = Tn[nzi].clamp_min(0)
        a = torch.empty(B, 0, dtype=dt)
        ls = torch.empty(B, 0, dtype=dt)
        mu = torch.empty(B, 0, 3, dtype=dt)
        for k in range(1, N + 1):
            if k > 1:
                fit = mixture(dirs, a[nzi].exp(), mu[nzi], ls[nzi].exp())
                res = (Tp - fit).clamp_min(0)
            else:
                res = Tp
            w1, m1, s1 = _start_lobe(res, dirs, sa, s_start, smax)
            ak = torch.full((B, 1), _LOG_W_MIN, dtype=dt)
            lk = torch.full((B, 1), math.log(smax), dtype=dt)
            mk = torch.zeros(B, 1, 3, dtype=dt)
            mk[..., 2] = 1.0
            ak[nzi], lk[nzi], mk[nzi] = w1.clamp_min(1e-10).log(), s1.log(), m1
            a = torch.cat([a, ak], 1)
            ls = torch.cat([ls, lk], 1)
            mu = torch.cat([mu, mk], 1)
            zero_start(a, ls, mu)
            prob = Problem(Tn, dirs, sa, k, beta, beta, delta if k > 1 else 0.0, smin, smax, energy=ref)
            sbk = None
            if sb is not None and k > 1:
                sbk = sb[:, [q for q, (i, j) in enumerate(prob_pairs(N)) if j < k]]
            stage_iter = max_iter if k == N else max(5, max_iter // 4)  # earlier stages only start the next lobe
            a, ls, mu, conv, itk = loop(prob, a, ls, mu, z.clone(), z, targets, sbk, stage_iter, tol, smin, smax)
            it += itk
    # the objective and relative L2 of the nonzero functions (a zero function's objective: 0)
    E = torch.zeros(B, dtype=dt)
    rel = torch.zeros(B, dtype=dt)
    if nzi.numel():
        tm, ts = targets(mu, ls, nzi)
        E_nz, r = prob.evaluate(a[nzi], ls[nzi], mu[nzi], nzi, tm, ts, None if sb is None else sb[nzi])[:2]
        E[nzi] = E_nz
        rel[nzi] = ((r.square() * sa).sum(1) / ref[nzi].clamp_min(1e-30)).sqrt()
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
        w1, m1, s1 = _start_lobe((Tn[bi] - others).clamp_min(0), dirs, sa, s_start, smax)
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


def _lm_loop(prob, a, ls, mu, conv, z, targets, sb, max_iter, tol, smin, smax, tries=1):
    """The LM iterations on the functions not yet ``conv`` (per-function damping λ: ÷3 on an
    accepted step, ×5 on a rejected one; up to ``tries`` damped solves per iteration, each rejected
    trial retried at 5× λ). Zero functions ``z`` take the minimiser of M + V."""
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
        jit = 1e-12 * (1 + diag.amax(1, keepdim=True))
        # up to `tries` damped solves of this system (Marquardt's inner loop): a rejected trial is retried at 5×
        # the damping without forming JtJ again (gauss_lm.c's lm_step: the same trials)
        lam_a = lm[act].clone()
        E1 = torch.full_like(E0, math.inf)
        acc = torch.zeros(nA, dtype=torch.bool)
        step = torch.zeros_like(Jtr)
        a2, ls2, mu2 = a[act].clone(), ls[act].clone(), mu[act].clone()
        todo = torch.arange(nA)
        for t in range(tries):  # loop over damping trials (at most `tries`, each batched over the functions still rejected)
            if t:
                lam_a[todo] = (lam_a[todo] * 5).clamp(max=1e12)
            A = JtJ[todo] + torch.diag_embed(lam_a[todo, None] * diag[todo] + jit[todo])
            L, info = torch.linalg.cholesky_ex(A)
            st = torch.cholesky_solve(-Jtr[todo, :, None], L)[..., 0]
            st = torch.where((info == 0)[:, None], st, torch.zeros_like(st)).clamp(-2.0, 2.0)
            at, lt, mt = prob.step(a[act[todo]], ls[act[todo]], mu[act[todo]], st)
            Et = prob.evaluate(at, lt, mt, act[todo], None if tm is None else tm[todo], None if ts is None else ts[todo],
                               None if sba is None else sba[todo])[0]
            ok = (Et <= E0[todo]) & torch.isfinite(Et)
            step[todo], E1[todo], acc[todo] = st, Et, ok
            a2[todo], ls2[todo], mu2[todo] = at, lt, mt
            todo = todo[~ok & (lam_a[todo] < 1e12)]
            if todo.numel() == 0:
                break
        ai = act[acc]
        a[ai], ls[ai], mu[ai] = a2[acc], ls2[acc], mu2[acc]
        lm[act] = torch.where(acc, lam_a / 3, lam_a * 5).clamp(1e-9, 1e12)
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
