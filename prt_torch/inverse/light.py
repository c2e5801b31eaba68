"""Unknown lighting, known BRDF (Ramamoorthi 2002 §6.4.3, eq. 6.16, with visibility and
interreflection through the precomputed transfer).

Every observed pixel p is linear in the SH light: B_p,c = a_p,c · L_c with the pixel's design row
a_p,c = Σ_i β_pi d_c(v_pi, ω_o,p) — the barycentric blend (β, its triangle's corners v_pi) of the
per-vertex rows the engine relights with: albedo_v,c T_v for diffuse transfer (Sloan 2002),
y(ω_o)ᵀ M_v for glossy exit transfer (Sloan 2003 §3.1), the four tents' rows of A_v for MRT
(Lehtinen & Kautz 2003 eq. 13), each with the pixel's own view direction in the vertex's frame.
Engine images (Gouraud: per-vertex radiance interpolated at the pixel centre) are thus exactly in
the model's range.

The least-squares problem min ‖A_c L_c − b_c‖² + λ² ‖L_c‖² (Tikhonov) is solved per channel by
the SVD A = U S Vᵀ with filter factors f_i = s_i²/(s_i² + λ²) (Hansen, *Rank-deficient and
discrete ill-posed problems*, 1998, §4–7). λ is chosen from the data: by generalised
cross-validation (Golub, Heath & Wahba 1979: GCV(λ) = P ‖r_λ‖² / (P − Σ f_i)²) or at the corner
of the L-curve (maximum curvature of (log ‖r_λ‖, log ‖L_λ‖)), never a hand-set constant, above
the data's own floor: λ ≥ ε·s_max with ε the unit roundoff of the stored observations and
transfer (float32: 2⁻²⁴; 8-bit images: 1/255), below which a singular value is numerically zero
(numpy's ``rcond``, the numerical rank of Hansen §3).

Well-posedness (ch. 2 §2.4.2, eq. 2.65: a band the kernel annihilates cannot be recovered): the
model resolution matrix R = V F Vᵀ maps the true light to the expected estimate; its diagonal,
averaged over a band's 2l+1 coefficients, is 1 for a band the images determine and 0 for one they
filter away. A band is *recoverable* when that mean is ≥ ½ in every channel. A convex Lambertian
object determines bands 0–2 (odd bands ≥ 3 vanish, eq. 2.65's Λ_l ρ̂_l = 0); shadows and gloss
recover more.

Positivity (eq. 6.24): radiance cannot be negative, but a least-squares SH estimate can be —
where the light is dark, and in the bands the images filter away. Ramamoorthi adds a soft
penalty (ν' = ν + λ(ν₀/κ₀)κ, κ the squared negative radiance, minimised by conjugate gradients);
:func:`solve_positive` imposes it as hard linear constraints instead: the same Tikhonov objective
(the same λ, chosen by GCV / the L-curve on the unconstrained problem) subject to Y x ≥ 0 at a
dense set of directions (spherical Fibonacci, :func:`positive_directions`), a strictly convex QP
solved exactly as a least-distance problem through non-negative least squares (Lawson & Hanson,
*Solving least squares problems*, 1974, ch. 23, Algorithm LDP; NNLS ch. 23 §3).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import torch

from .. import relight
from .._checks import check_choice

__all__ = ["design_matrix", "corner_rows", "solve_tikhonov", "LightFit", "fit_light", "well_posedness", "FLOAT32_EPS",
           "nnls", "solve_positive", "positive_directions", "negativity"]

FLOAT32_EPS = 2.0 ** -24
_GRID = 400  # candidate λ, log-spaced from the floor to s_max; the minimum is refined on two finer grids


def corner_rows(scene, vid: torch.Tensor, to_eye: torch.Tensor) -> torch.Tensor:
    """Per-vertex design rows d_c(v, ω_o) of a :class:`prt_torch.render.prt.PRTScene`: exit radiance
    of vertex ``vid [K]`` towards ``to_eye [K, 3]`` (world, unit) is ``d_c · L_c``.

    Returns ``[C, K, n_in]`` float64 (C = 3): albedo_c T_v (diffuse, Sloan 2002), T_v,c (diffuse
    RGB), y(ω_o,local)ᵀ M_v zero below the horizon (glossy, Sloan 2003 §3.1), or Σ_t g_t A_v[idx_t]
    over the four tents (MRT, Lehtinen & Kautz 2003 eq. 13)."""
    rows = scene.rows[vid].to(torch.float64)  # [K, R, n]
    if scene.mode == "none":
        return rows[:, 0][None] * scene.albedo[vid].T.to(torch.float64)[:, :, None]
    if scene.mode == "diagonal":
        return rows.permute(1, 0, 2).contiguous()
    vl = relight.local_view(scene.frames[vid], direction=to_eye.to(torch.float64))
    if scene.mode == "dense":
        y = relight.glossy_view_weights(vl, scene.transfer.meta.get("out_index"), scene.n_out, torch.float64)
        d = torch.einsum("kr,krn->kn", y, rows)
    else:
        idx, g = relight.mrt_view_taps(vl, math.isqrt(scene.n_out), torch.float64)
        d = torch.einsum("kt,ktn->kn", g, torch.gather(rows, 1, idx[:, :, None].expand(-1, -1, rows.shape[2])))
    return (d[None] * scene.albedo[vid].T.to(torch.float64)[:, :, None])


def design_matrix(scene, obs) -> torch.Tensor:
    """The linear map from the SH light to the observed pixels (module doc, eq. 6.16): ``[C, P, n_in]``
    float64, row p of channel c the barycentric blend of its triangle's corner rows."""
    P = obs.P
    vid = obs.corners.reshape(-1)
    d = corner_rows(scene, vid, obs.to_eye.repeat_interleave(3, 0))  # [C, 3P, n]
    return (d.reshape(d.shape[0], P, 3, -1) * obs.bary[None, :, :, None]).sum(2)


def solve_tikhonov(A: torch.Tensor, b: torch.Tensor, method: str = "gcv", eps: float = FLOAT32_EPS) -> dict:
    """Tikhonov least squares ``min ‖A x − b‖² + λ²‖x‖²`` with λ from the data (module doc).

    Args:
        A: ``[P, n]`` float64; b: ``[P]`` float64.
        method: 'gcv' (generalised cross-validation) or 'lcurve' (L-curve corner).
        eps: relative precision of the data; λ ≥ eps·s_max.
    Returns:
        dict: x ``[n]`` float64, lam (float), s ``[n]`` singular values, Vh ``[n, n]``,
        filter ``[n]`` factors f_i, resolution ``[n]`` diagonal of V F Vᵀ, rss (‖A x − b‖²), gcv.
    """
    check_choice("method", method, ["gcv", "lcurve"])
    P, n = A.shape
    U, s, Vh = torch.linalg.svd(A, full_matrices=False)
    beta = U.T @ b
    r0 = max(float(b @ b - beta @ beta), 0.0)
    smax = float(s[0]) if s.numel() else 0.0
    lo = max(eps * smax, 1e-300)
    if smax == 0:
        raise ValueError("the design matrix is zero (no pixel responds to the light); accepted: views of a lit, visible surface")

    def curves(lt: torch.Tensor):
        """Filter factors ``[G, n]``, ‖r‖² ``[G]`` and ‖x‖² ``[G]`` at log10 λ = ``lt [G]`` (one pass)."""
        lam2 = (10.0 ** lt)[:, None] ** 2
        f = s[None] ** 2 / (s[None] ** 2 + lam2)
        rss = (((1 - f) * beta[None]) ** 2).sum(1) + r0
        xn = ((s[None] * beta[None] / (s[None] ** 2 + lam2)) ** 2).sum(1)  # f β / s, finite where s = 0
        return f, rss, xn

    def gcv(lt: torch.Tensor) -> torch.Tensor:
        f, rss, _ = curves(lt)
        return P * rss / (P - f.sum(1)).clamp_min(1e-300) ** 2

    grid = torch.linspace(math.log10(lo), math.log10(smax), _GRID, dtype=torch.float64)
    if method == "gcv":
        for _ in range(3):  # the grid, then two finer grids around its minimum
            vals = gcv(grid)
            k = int(torch.argmin(vals))
            lt = float(grid[k])
            a, c = grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)]
            grid = torch.linspace(float(a), float(c), 64, dtype=torch.float64)
    else:
        _, rss_g, xn_g = curves(grid)
        rho, eta = 0.5 * torch.log(rss_g.clamp_min(1e-300)), 0.5 * torch.log(xn_g.clamp_min(1e-300))
        dr, de = torch.gradient(rho, spacing=(grid,))[0], torch.gradient(eta, spacing=(grid,))[0]
        ddr, dde = torch.gradient(dr, spacing=(grid,))[0], torch.gradient(de, spacing=(grid,))[0]
        kappa = (dr * dde - ddr * de) / (dr ** 2 + de ** 2).clamp_min(1e-300) ** 1.5
        lt = float(grid[int(torch.argmax(kappa[2:-2])) + 2])
    lam = 10.0 ** lt
    f, rss, _ = curves(torch.tensor([lt], dtype=torch.float64))
    f, rss = f[0], float(rss[0])
    x = Vh.T @ (s * beta / (s ** 2 + lam ** 2))  # = V F S⁻¹ Uᵀ b, finite where a singular value is 0
    res = ((Vh.T ** 2) * f[None]).sum(1)  # diag(V F Vᵀ)
    return {"x": x, "lam": lam, "s": s, "Vh": Vh, "filter": f, "resolution": res, "rss": rss,
            "gcv": float(gcv(torch.tensor([lt], dtype=torch.float64))[0]),
            "lam_floor": lo}


def nnls(E: torch.Tensor, f: torch.Tensor, max_iter: int | None = None) -> torch.Tensor:
    """Non-negative least squares ``min ‖E u − f‖ s.t. u ≥ 0`` by the active-set method of Lawson &
    Hanson (1974, ch. 23 §3, Algorithm NNLS), in torch float64.

    Args:
        E: ``[m, k]`` float64 (here m = n² + 1 ≪ k, the constraint directions).
        f: ``[m]`` float64.
        max_iter: inner iterations allowed (default 3k; each frees or fixes one variable).
    Returns:
        u ``[k]`` float64, u ≥ 0 (exactly 0 off the passive set).
    Raises:
        RuntimeError naming the iteration count when it does not converge (does not happen in
        exact arithmetic: the method terminates finitely, L&H Theorem 23.10).
    """
    m, k = E.shape
    dt = E.dtype
    u = torch.zeros(k, dtype=dt)
    passive = torch.zeros(k, dtype=torch.bool)
    tol = 10 * torch.finfo(dt).eps * max(m, k) * float(E.abs().sum(0).max())  # L&H's dual-feasibility tolerance
    max_iter = 3 * k if max_iter is None else int(max_iter)
    it = 0
    w = E.T @ (f - E @ u)  # the dual vector (negative gradient)
    blocked = torch.zeros(k, dtype=torch.bool)  # a column whose entry came out ≤ 0 on entering (rounding): skipped once
    while True:
        cand = ~passive & ~blocked & (w > tol)
        if not bool(cand.any()):
            break
        j = int(torch.argmax(torch.where(cand, w, torch.full_like(w, -math.inf))))
        passive[j] = True
        first = True
        while True:
            it += 1
            if it > max_iter:
                raise RuntimeError(f"nnls: no convergence in max_iter={max_iter} iterations ({int(passive.sum())} passive "
                                   f"variables of {k}); accepted: a larger max_iter")
            idx = torch.nonzero(passive).flatten()
            sP = torch.linalg.lstsq(E[:, idx], f[:, None]).solution[:, 0]
            if bool((sP > 0).all()):
                u.zero_()
                u[idx] = sP
                blocked.zero_()
                break
            if first and bool((sP[idx == j] <= 0).any()):  # the entering column does not help (rounding): undo
                passive[j] = False
                blocked[j] = True
                break
            first = False
            uP = u[idx]
            neg = sP <= 0
            alpha = float((uP[neg] / (uP[neg] - sP[neg])).min())
            uP = uP + alpha * (sP - uP)
            u.zero_()
            u[idx] = uP
            passive[idx] = uP > 0
            u[~passive] = 0
            if not bool(passive.any()):
                break
        w = E.T @ (f - E @ u)
    return u


def positive_directions(bands: int) -> torch.Tensor:
    """``[D, 3]`` float64 spherical-Fibonacci directions where :func:`solve_positive` constrains the
    radiance: D = max(1024, 32 n²), ~4.5° apart at 8 bands (a band-l harmonic's lobes are π/l
    wide, so the radiance cannot dip far below 0 between samples)."""
    from ..sh.quadrature import fibonacci_sphere

    return fibonacci_sphere(max(1024, 32 * bands * bands))[0]


def solve_positive(fit: dict, Y: torch.Tensor) -> dict:
    """The Tikhonov problem of :func:`solve_tikhonov` with the light's radiance non-negative at the
    directions of ``Y`` (eq. 6.24's positivity as hard constraints, module doc):
    ``min ‖A x − b‖² + λ²‖x‖²  s.t.  Y x ≥ 0``, λ the unconstrained fit's (chosen from the data).

    With A = U S Vᵀ the objective is ‖R (x − x_λ)‖² + const, R = diag(√(s² + λ²)) Vᵀ and x_λ the
    unconstrained estimate; z = R (x − x_λ) turns it into the least-distance problem
    min ‖z‖ s.t. G z ≥ h with G = Y R⁻¹, h = −Y x_λ (Lawson & Hanson ch. 23, Algorithm LDP), solved by
    :func:`nnls` on ``[Gᵀ; hᵀ] u ≈ e_{n+1}``: z = −r[:n]/r[n] with r the NNLS residual. x = 0 is
    feasible, so the problem always has a solution; it is unique (strictly convex for λ > 0).

    Args:
        fit: :func:`solve_tikhonov`'s dict (x, s, Vh, lam).
        Y: ``[D, n]`` float64 SH basis at the constrained directions (``eval_sh``).
    Returns:
        dict: x ``[n]`` float64, active (constraints at equality, int), objective_increase
        (‖z‖², the Tikhonov objective's rise over the unconstrained minimum).
    """
    x0, s, Vh, lam = fit["x"], fit["s"], fit["Vh"], float(fit["lam"])
    n = x0.shape[0]
    if Vh.shape[0] < n:  # fewer pixels than unknowns: complete V (singular values 0 there)
        Q = torch.linalg.qr(Vh.T, mode="complete").Q
        Vh = torch.cat([Vh, Q[:, Vh.shape[0]:].T], 0)
        s = torch.cat([s, s.new_zeros(n - s.shape[0])])
    d = (s ** 2 + lam ** 2).sqrt()
    Rinv = Vh.T / d[None]  # [n, n]: R⁻¹ = V diag(1/d)
    y0 = Y @ x0
    scale = float(y0.abs().max()) if y0.numel() else 0.0
    if scale == 0.0 or bool((y0 >= 0).all()):
        return {"x": x0.clone(), "active": 0, "objective_increase": 0.0}
    G, h = Y @ Rinv, -y0
    E = torch.cat([G.T, h[None]], 0)  # [n + 1, D]: one column per constraint
    E = E / E.norm(dim=0, keepdim=True).clamp_min(1e-300)  # each constraint scaled to unit norm (same feasible set)
    f = torch.zeros(n + 1, dtype=E.dtype)
    f[n] = 1.0
    u = nnls(E, f)
    r = E @ u - f
    if abs(float(r[n])) < 1e-12:  # pragma: no cover (x = 0 is always feasible)
        raise RuntimeError("solve_positive: the positivity constraints are infeasible (cannot happen: x = 0 satisfies them)")
    z = -r[:n] / r[n]
    x = x0 + Rinv @ z
    yx = Y @ x
    return {"x": x, "active": int((yx <= 1e-9 * scale).sum()), "objective_increase": float(z @ z)}


@functools.lru_cache(maxsize=32)
def _sphere_basis(bands: int, n: int) -> torch.Tensor:
    """``[n, bands²]`` float64: the SH basis at ``n`` spherical-Fibonacci directions (cached: fit_light
    reports negativity on every call, and ``material.fit_both`` calls it for each of ~150 BRDF
    candidates). Read-only."""
    from ..sh import eval_sh
    from ..sh.quadrature import fibonacci_sphere

    return eval_sh(fibonacci_sphere(n)[0], bands)


def negativity(L: torch.Tensor, dirs: torch.Tensor | None = None) -> dict:
    """How negative the radiance f of an SH light ``L [C, n²]`` is over the sphere, per channel, at
    equal-area directions (spherical Fibonacci, ``dirs [D, 3]``, default 8192): ``min_relative``
    (the least radiance over the mean |f|), ``negative_solid_angle`` (the fraction of the sphere
    where f < 0) and ``negative_share`` (∫ max(−f, 0) / ∫ |f|). A light f ≡ 0 gives zeros."""
    from ..sh import eval_sh

    bands = math.isqrt(L.shape[1])
    Y = _sphere_basis(bands, 8192) if dirs is None else eval_sh(dirs, bands)
    f = Y @ L.to(torch.float64).T  # [D, C]
    mabs = f.abs().mean(0)
    nz = mabs > 0
    return {"min_relative": torch.where(nz, f.min(0).values / mabs.clamp_min(1e-300), 0.0).tolist(),
            "negative_solid_angle": (f < 0).double().mean(0).tolist(),
            "negative_share": torch.where(nz, (-f).clamp_min(0).mean(0) / mabs.clamp_min(1e-300), 0.0).tolist()}


def well_posedness(fits: list[dict], bands: int, A: torch.Tensor) -> dict:
    """Per-band conditioning (module doc, ch. 2 eq. 2.65) from the channel fits of :func:`fit_light`.

    Returns a dict: ``recoverable_bands`` (list of l whose mean resolution ≥ ½ in every channel),
    ``recoverable_up_to`` (largest l with every band ≤ l recoverable, −1 if none),
    ``bands`` (per l: ``resolution`` per channel, ``singular_values`` of the band's own columns of
    the channel-0 design relative to the largest singular value of the whole design,
    ``gain``: the largest :func:`_gain` of the band's coefficients over the channels — a relative
    pixel error ε moves them by at most gain·ε·‖L‖, so a band is determined *in practice* only
    when gain × (noise + model error) ≪ 1), ``weakest`` (the least determined combination of
    coefficients: its relative singular value, its ``coeffs`` ``[n²]`` and ``peak_direction``,
    where on the sphere that combination of SH peaks — e.g. (0, 0, −1), light from below, for
    an object on a plane seen from above), ``singular_values`` (whole design, channel 0, relative), ``condition``
    (s_max / s_min), ``lam`` per channel (relative to s_max), ``lam_floor`` (relative)."""
    from ..sh import eval_sh
    from ..sh.quadrature import fibonacci_sphere

    out_bands = []
    rec = []
    smax = float(fits[0]["s"][0])
    gains = [_gain(f) for f in fits]  # [n] per channel
    for l in range(bands):
        a, b = l * l, (l + 1) * (l + 1)
        resl = [float(f["resolution"][a:b].mean()) for f in fits]
        sv = torch.linalg.svdvals(A[0][:, a:b]) / smax
        out_bands.append({"l": l, "resolution": resl, "singular_values": [float(v) for v in sv],
                          "gain": max(float(g[a:b].max()) for g in gains)})
        if min(resl) >= 0.5:
            rec.append(l)
    upto = -1
    while upto + 1 in rec:
        upto += 1
    s = fits[0]["s"]
    w = fits[0]["Vh"][-1]  # the right singular vector of the smallest singular value (channel 0)
    d, _ = fibonacci_sphere(2048)
    k = int(torch.argmax((eval_sh(d, bands) @ w).abs()))
    weakest = {"relative_singular_value": float(s[-1]) / smax, "coeffs": [float(v) for v in w],
               "peak_direction": [round(float(v), 3) for v in d[k]]}
    return {"recoverable_bands": rec, "recoverable_up_to": upto, "bands": out_bands, "weakest": weakest,
            "singular_values": [float(v) / smax for v in s], "condition": float(s[0] / s[-1]) if float(s[-1]) > 0 else math.inf,
            "lam": [f["lam"] / float(f["s"][0]) for f in fits], "lam_floor": fits[0]["lam_floor"] / smax,
            "threshold": 0.5}


def _gain(fit: dict) -> torch.Tensor:
    """``[n]`` float64: how far a data error moves each coefficient of a :func:`solve_tikhonov`
    fit. The estimate is x = V F S⁻¹ Uᵀ b, so an error e of the pixels moves coefficient j by at
    most ‖(V F S⁻¹)_j‖ ‖e‖; with ‖b‖ ≤ s_max ‖x‖, a relative error ‖e‖ = ε ‖b‖ (noise, or a
    renderer that differs from the model by ε) moves it by at most gain_j · ε · ‖x‖, with
    gain_j = s_max ‖(V F S⁻¹)_j‖ (the coefficient's condition number; Hansen 1998 §4)."""
    s, lam = fit["s"], fit["lam"]
    fs = s / (s ** 2 + lam ** 2)  # f_i / s_i, finite where s_i = 0
    return float(s[0]) * ((fit["Vh"].T * fs[None]) ** 2).sum(1).sqrt()


@dataclasses.dataclass
class LightFit:
    """The recovered light and how well the images determine it.

    Attributes:
        light: ``[C, n²]`` float64 SH light (graphics convention, +z up).
        report: :func:`well_posedness`'s dict.
        predicted: ``[P, C]`` float64 re-rendered pixels; residual_rms: float.
        unconstrained: ``[C, n²]`` float64, the Tikhonov estimate (= ``light`` unless constrained).
        constraint: with ``positive``, the constrained directions, active constraints per
            channel and objective increase; else None.
        positivity (property, computed on first use): how negative the unconstrained estimate's
            radiance is (:func:`negativity`, key ``unconstrained``), ``constrained``, and with
            ``positive`` the constrained result's (``result``) and ``constraint``'s keys.
    """

    light: torch.Tensor
    report: dict
    predicted: torch.Tensor
    method: str
    unconstrained: torch.Tensor | None = None
    constraint: dict | None = None

    @functools.cached_property
    def positivity(self) -> dict:
        L0 = self.light if self.unconstrained is None else self.unconstrained
        pos = {"constrained": self.constraint is not None, "unconstrained": negativity(L0)}
        if self.constraint is not None:
            pos.update(self.constraint)
            pos["result"] = negativity(self.light)
        return pos


def fit_light(A: torch.Tensor, values: torch.Tensor, method: str = "gcv", eps: float = FLOAT32_EPS,
              positive: bool = False) -> LightFit:
    """Solve the light from the design ``A [C, P, n]`` float64 and the observations ``values [P, C]``
    (one :func:`solve_tikhonov` per channel, each with its own λ). ``positive``: the radiance
    constrained ≥ 0 over the sphere (eq. 6.24, :func:`solve_positive`, same λ); the fit's
    ``positivity`` says how negative the unconstrained estimate was either way."""
    C, P, n = A.shape
    bands = math.isqrt(n)
    fits = [solve_tikhonov(A[c], values[:, c].to(torch.float64), method, eps) for c in range(C)]
    L0 = L = torch.stack([f["x"] for f in fits])
    constraint = None
    if positive:
        D = positive_directions(bands).shape[0]
        Y = _sphere_basis(bands, D)  # the SH basis at positive_directions(bands)
        sols = [solve_positive(f, Y) for f in fits]
        L = torch.stack([p["x"] for p in sols])
        constraint = {"directions": D, "active": [p["active"] for p in sols],
                      "objective_increase": [p["objective_increase"] for p in sols]}
    pred = torch.einsum("cpn,cn->pc", A, L)
    return LightFit(L, well_posedness(fits, bands, A), pred, method, L0, constraint)
