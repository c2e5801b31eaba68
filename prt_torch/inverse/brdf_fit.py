"""BRDFs from images under known lighting beyond the Phong lobe (Ramamoorthi 2002 §6.4.2): the
microfacet model of eq. 5.34 and Ashikhmin–Shirley by non-linear least squares with autograd, and
the isotropic SH BRDF coefficients ρ̂_lpq (eq. 5.4–5.6, 5.8) by linear least squares.

Half-vector lobes are not radially symmetric about the reflected view, so eq. 6.12's zonal
shortcut (:mod:`.material`, Phong) does not apply. Each pixel p is instead the direct-light
integral over its local hemisphere, by a fixed product Gauss rule {s_q, w_q} (``gauss_hemisphere``,
shared by all pixels, aligned with the horizon so the BRDF's cut at z = 0 falls on the rule's
boundary):

    B_p,c = Σ_q f*(s_q, ω_o,p; θ) · W_pqc,    W_pqc = w_q V_p(s_q) L_c(F_pᵀ s_q)

f* the cosine-weighted BRDF of the engine's own classes (:class:`prt_torch.brdf.Microfacet`,
:class:`~prt_torch.brdf.AshikhminShirley`, :class:`~prt_torch.brdf.Lambertian`), ω_o,p the view
in the pixel's frame F_p (rows t, b, n: the interpolated normal and tangent), V_p(s) one Embree
occlusion ray per pixel and node (shadows are data, not error: the thesis's eq. 6.11 checked the
reflected ray only), L_c the known SH light evaluated at the node's world direction. W does not
depend on the BRDF: it is built once (:func:`slice_model`), and each evaluation of the fit is one
BRDF evaluation on ``[P, Q]`` and a contraction. Interreflection is not modelled (direct light).

Parametric fits (:func:`fit_parametric`): a scan of the non-linear parameter (σ; the isotropic
exponent n) with the parameters the model is linear in solved by least squares at each point
(the thesis's nested procedure), then Levenberg–Marquardt on every free parameter with the
Jacobian by forward-mode autograd (:func:`jacobian_fwd`), and standard errors from (JᵀJ)⁻¹σ̂².

SH BRDF (:func:`fit_sh_brdf`): with the BRDF matrix B of the engine's glossy transfer (B_ij =
∫_H∫_H y_i(v) y_j(s) f*(s, v), :func:`prt_torch.brdf.double_project_isotropic`) a pixel is
y(ω_o)ᵀ B r_p with r_p,j = Σ_q y_j(s_q) W_pq — linear in B. An isotropic B is block-diagonal in
the azimuthal order (eq. 5.4–5.6: only |m_out| = |m_in| = q couples) and, for a BRDF even in
φ_i − φ_o, B_(p,q),(l,q) = B_(p,−q),(l,−q) = ρ̂_lpq with the cos·sin blocks zero; the unknowns are
the ρ̂_lpq, q ≥ 0, solved per channel by :func:`prt_torch.inverse.light.solve_tikhonov` (λ by GCV
or the L-curve) with the resolution and standard error of each coefficient reported.
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
import torch.autograd.forward_ad as fwAD

__all__ = ["BRDFFit", "SliceModel", "slice_model", "jacobian_fwd", "levenberg_marquardt", "covariance_stderr",
           "PARAMETERS", "fit_parametric", "sh_brdf_index", "sh_brdf_coeffs", "sh_brdf_matrix", "sh_brdf_design",
           "fit_sh_brdf"]


@dataclasses.dataclass
class BRDFFit:
    """Fitted BRDF parameters.

    Attributes:
        params: name → float (or ``[C]`` list for per-channel parameters).
        stderr: the same keys, standard errors from (JᵀJ)⁻¹ σ̂² at the optimum (σ̂² the residual
            variance; 0 for a parameter held fixed); ``relative_stderr`` likewise divided by the values.
        predicted: ``[P, C]`` float64; rss: residual sum of squares; iterations (Levenberg–Marquardt).
        out_of_range: names of parameters outside the model's accepted range (the linear ones are
            unconstrained least squares: a negative ks, or rs > 1, says the model does not fit the
            images — wrong light, wrong model, or a surface without a visible highlight).
    """

    params: dict
    stderr: dict
    relative_stderr: dict
    predicted: torch.Tensor
    rss: float
    iterations: int
    out_of_range: list = dataclasses.field(default_factory=list)


# ----------------------------------------------------------------------------------------- fitting core
def jacobian_fwd(fn, theta: torch.Tensor) -> torch.Tensor:
    """Jacobian ``[R, k]`` of ``fn: [k] -> [R]`` by forward-mode autograd, one dual pass per
    parameter (``torch.autograd.forward_ad``; not ``torch.func.jacfwd``, whose vmap refuses the
    data-dependent range checks the BRDF classes run on their parameters)."""
    cols = []
    for i in range(theta.numel()):  # k ≤ ~8 parameters
        with fwAD.dual_level():
            t = torch.zeros_like(theta)
            t[i] = 1.0
            cols.append(fwAD.unpack_dual(fn(fwAD.make_dual(theta, t))).tangent)
    return torch.stack(cols, 1)


def levenberg_marquardt(resid, theta: torch.Tensor, *, iterations: int = 50, project=None, jacobian=jacobian_fwd,
                        rtol: float = 1e-14, xtol: float = 1e-12):
    """Minimise ‖resid(θ)‖² from ``theta [k]`` float64 (Levenberg–Marquardt with Marquardt's
    diagonal scaling; ``project(θ)`` puts a step back into the feasible box). Stops when an
    accepted step lowers ‖r‖² by less than ``rtol`` relative or moves θ by less than ``xtol``.

    Returns (θ, r [R], f = ‖r‖², J [R, k] at θ, iterations)."""
    project = project or (lambda t: t)
    mu = 1e-3
    r = resid(theta)
    f = float(r @ r)
    it = 0
    for it in range(1, iterations + 1):  # a handful of parameters: a few tens of iterations at most
        J = jacobian(resid, theta)
        g = J.T @ r
        H = J.T @ J
        step = torch.linalg.solve(H + mu * torch.diag(torch.diagonal(H).clamp_min(1e-300)), -g)
        cand = project(theta + step)
        r_new = resid(cand)
        f_new = float(r_new @ r_new)
        if f_new < f:
            rel = (f - f_new) / max(f, 1e-300)
            moved = float((cand - theta).abs().max())
            theta, r, f = cand, r_new, f_new
            mu = max(mu / 10, 1e-12)
            if rel < rtol or moved < xtol:
                break
        else:
            mu *= 10
            if mu > 1e12:
                break
    return theta, r, f, jacobian(resid, theta), it


def covariance_stderr(J: torch.Tensor, f: float) -> torch.Tensor:
    """``[k]`` standard errors sqrt(diag((JᵀJ)⁻¹) σ̂²), σ̂² = f / (R − k) (inf where JᵀJ is singular:
    a parameter the data do not determine)."""
    dof = max(J.shape[0] - J.shape[1], 1)
    try:
        cov = torch.linalg.inv(J.T @ J) * (f / dof)
        return torch.sqrt(torch.diagonal(cov).clamp_min(0))
    except RuntimeError:
        return torch.full((J.shape[1],), math.inf, dtype=torch.float64)


# ----------------------------------------------------------------------------------------- the model
@dataclasses.dataclass
class SliceModel:
    """The BRDF-independent part of the direct-light integral of every pixel (module doc).

    Attributes:
        wi: ``[Q, 3]`` float64 local light directions s_q of the hemisphere rule (z ≥ 0), shared
            by every pixel, or ``[P, Q, 3]`` one rule per pixel (split at its z_o).
        wo: ``[P, 3]`` float64 the pixels' view directions in their local frames.
        W: ``[P, Q, C]`` float64 w_q V_p(s_q) L_c(F_pᵀ s_q).
        visible: fraction of (pixel, node) rays that leave the object.
        quad_bands: the rule's size (``gauss_hemisphere(quad_bands)``: (L+1)(2L+1) nodes).
    """

    wi: torch.Tensor
    wo: torch.Tensor
    W: torch.Tensor
    visible: float
    quad_bands: int

    @property
    def P(self) -> int:
        return int(self.wo.shape[0])

    def cosine_weighted(self, brdf) -> torch.Tensor:
        """``[P, Q]`` f*(s_q, ω_o,p) of a :class:`prt_torch.brdf.BRDF` with scalar parameters
        (``[B, P, Q]`` for parameters of shape ``[B, 1, 1]``)."""
        return brdf.cosine_weighted(self.wi if self.wi.ndim == 3 else self.wi[None], self.wo[:, None])

    def integrate(self, f: torch.Tensor) -> torch.Tensor:
        """``[..., P, C]`` Σ_q f_pq W_pqc for ``f [..., P, Q]`` (a batch of parameter sets in front)."""
        return torch.matmul(f.unsqueeze(-2), self.W).squeeze(-2)  # batched over p ([1, Q] @ [Q, C]); einsum was 10× slower

    def render(self, brdf) -> torch.Tensor:
        """``[P, C]`` pixels of a BRDF model (module doc); ``[B, P, C]`` for a batch ``[B, 1, 1]``."""
        return self.integrate(self.cosine_weighted(brdf))


def _pixel_rules(wo: torch.Tensor, L: int, grade: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-pixel hemisphere rules for views ``wo [P, 3]`` (local): (dirs ``[P, Q, 3]``, w ``[P, Q]``)
    float64, Q = 2(⌊(L+2)/2⌋+1)(2L+1).

    z: two Gauss–Legendre panels split at z_o (:func:`prt_torch.brdf.split_hemisphere_rules`).
    φ: the periodic map φ = φ_m + t − a sin t of 2L+1 uniform t, weights (2π/(2L+1))(1 − a cos t),
    φ_m = φ_o + π the mirror azimuth — nodes 1/(1 − a) times denser there. A half-vector lobe
    (microfacet, Ashikhmin–Shirley) seen at grazing z_o is ~z_o·√(8/n) wide in azimuth (h_z =
    2z_o/√(δφ² + 4z_o²) at the horizon), far below a uniform grid's spacing: with a = 0.9 and
    L = 24 the spacing there is 0.013 rad. The trapezoid rule stays spectrally accurate (the map
    is smooth and periodic)."""
    from ..brdf import split_hemisphere_rules

    nphi = 2 * L + 1
    zd, zw = split_hemisphere_rules(wo[:, 2].clamp(1e-6, 1 - 1e-6), (L + 2) // 2 + 1, 1)  # φ = 0 only: z nodes
    z, wz = zd[..., 2], zw / (2 * math.pi)  # [P, Z]
    t = -math.pi + (torch.arange(nphi, dtype=torch.float64) + 0.5) * (2 * math.pi / nphi)
    phi = torch.atan2(-wo[:, 1], -wo[:, 0])[:, None] + t - grade * torch.sin(t)  # [P, nphi]
    wphi = (2 * math.pi / nphi) * (1 - grade * torch.cos(t))
    r = torch.sqrt((1 - z * z).clamp_min(0))
    d = torch.stack([r[:, :, None] * torch.cos(phi)[:, None], r[:, :, None] * torch.sin(phi)[:, None],
                     z[:, :, None].expand(-1, -1, nphi)], -1)
    return d.reshape(len(wo), -1, 3), (wz[:, :, None] * wphi).reshape(len(wo), -1)


def slice_model(mesh, obs, L: torch.Tensor, *, quad_bands: int = 16, visibility: bool = True, split: bool = True,
                grade: float = 0.9,
                caster=None, chunk: int = 1 << 20) -> SliceModel:
    """Build :class:`SliceModel` for ``obs`` (:class:`~prt_torch.inverse.inputs.Observations`) under
    the known light ``L [C, n²]`` (world frame, graphics SH).

    The pixel's frame: n the barycentric blend of the vertex normals, t the blend of the vertex
    tangents made orthogonal to n, b = n × t. ``visibility``: one occlusion ray per pixel and
    node (P·Q rays, in chunks of ``chunk``); False for a convex object. ``quad_bands`` L: the
    product rule over the hemisphere, 2L+1 azimuths; ``split`` (default): one rule per pixel
    (:func:`_pixel_rules`: z split at z_o, where Ashikhmin–Shirley's max(z_i, z_o) has a kink,
    azimuths graded by ``grade`` about the mirror azimuth, where a half-vector lobe seen at grazing
    angles is narrow — uniform azimuths at L = 24 are 12 % off for n = 60, graded ones 6e-6 at
    L = 16: reports/benchmarks/inverse_brdf.md); else one ``gauss_hemisphere(L)`` rule shared by all pixels ((L+1)(2L+1) nodes;
    enough for the SH BRDF, whose basis is smooth)."""
    from .._checks import check_int
    from ..scene import RayCaster
    from ..sh import eval_sh, gauss_hemisphere

    quad_bands = check_int("quad_bands", quad_bands, 2, 256)
    L = L.to(torch.float64)
    bands = math.isqrt(L.shape[1])
    bary = obs.bary[:, :, None]
    n = (torch.as_tensor(mesh.normals, dtype=torch.float64)[obs.corners] * bary).sum(1)
    n = n / n.norm(dim=1, keepdim=True).clamp_min(1e-300)
    t = (torch.as_tensor(mesh.tangents, dtype=torch.float64)[obs.corners] * bary).sum(1)
    t = t - (t * n).sum(1, keepdim=True) * n
    tn = t.norm(dim=1, keepdim=True)
    if bool((tn < 1e-6).any()):  # a tangent parallel to the normal after blending: any orthogonal one
        alt = torch.where(n[:, :1].abs() < 0.9, torch.tensor([[1.0, 0, 0]], dtype=torch.float64),
                          torch.tensor([[0, 1.0, 0]], dtype=torch.float64))
        alt = alt - (alt * n).sum(1, keepdim=True) * n
        t = torch.where(tn < 1e-6, alt, t)
    t = t / t.norm(dim=1, keepdim=True)
    b = torch.cross(n, t, dim=1)
    F = torch.stack([t, b, n], 1)  # [P, 3, 3] world -> local
    wo = torch.einsum("pij,pj->pi", F, obs.to_eye.to(torch.float64))
    P, C = obs.P, L.shape[0]
    if split:  # one rule per pixel: z split at the view's z, azimuths graded about the mirror azimuth
        wi, w = _pixel_rules(wo, quad_bands, grade)
    else:
        wi, w = gauss_hemisphere(quad_bands)
    Q = wi.shape[-2]
    W = torch.empty(P, Q, C, dtype=torch.float64)
    step = max(1, chunk // Q)
    own = visibility and caster is None
    caster = RayCaster(mesh, workers=1) if own else caster
    vis_sum = 0.0
    try:
        for a in range(0, P, step):  # chunks of pixels bound memory (P·Q/chunk iterations)
            Fc = F[a:a + step]
            k = len(Fc)
            wic = wi[a:a + step] if split else wi[None].expand(k, Q, 3)
            wc = w[a:a + step] if split else w[None].expand(k, Q)
            d = torch.einsum("pji,pqj->pqi", Fc, wic)  # local node -> world: Fᵀ s
            rad = (eval_sh(d.reshape(-1, 3), bands, check=False) @ L.T).reshape(k, Q, C)
            if visibility:
                o = obs.points[a:a + step, None].expand(k, Q, 3).reshape(-1, 3)
                nn = n[a:a + step, None].expand(k, Q, 3).reshape(-1, 3)
                vis = ~caster.occluded(o.numpy(), d.reshape(-1, 3).numpy(), normals=nn.numpy())
                vis = vis.reshape(k, Q).to(torch.float64)
                vis_sum += float(vis.sum())
                rad = rad * vis[:, :, None]
            W[a:a + step] = rad * wc[:, :, None]
    finally:
        if own:
            caster.close()
    return SliceModel(wi, wo, W, vis_sum / (P * Q) if visibility else 1.0, quad_bands)


# ----------------------------------------------------------------------------------------- parametric
#: name → (parameter, per colour channel, lower, upper) of the fitted models; the lobe's width
#: (σ, n, N_u, N_v) is the non-linear parameter, fitted on a log scale.
PARAMETERS = {
    "microfacet": (("kd", True, 0.0, 1.0), ("ks", False, 0.0, math.inf), ("sigma", False, 0.01, 2.0)),
    "ashikhmin-shirley": (("rd", True, 0.0, 1.0), ("rs", False, 0.0, 1.0), ("n", False, 0.5, 1e5)),
    "ashikhmin-shirley-anisotropic": (("rd", True, 0.0, 1.0), ("rs", False, 0.0, 1.0),
                                      ("nu", False, 0.5, 1e5), ("nv", False, 0.5, 1e5)),
}
_WIDTH = {"microfacet": ("sigma",), "ashikhmin-shirley": ("n",), "ashikhmin-shirley-anisotropic": ("nu", "nv")}
_SCAN = {"sigma": (0.03, 1.0), "n": (1.0, 3000.0), "nu": (1.0, 3000.0), "nv": (1.0, 3000.0)}


class _Separable:
    """A parametric model written as offset(φ) + Σ_k x_k column_k(φ): linear in x for fixed lobe
    widths φ (variable projection, Golub & Pereyra 1973), each image evaluated through the
    engine's BRDF classes on the :class:`SliceModel`.

    microfacet (eq. 6.12 with eq. 5.34): x = (kd_c, ks), columns kd_c → E (Lambertian, unit
    albedo, channel c), ks → f*_Microfacet(σ, 1). Ashikhmin–Shirley (2000, eq. 4–5): Schlick's
    F = rs + (1 − rs)(1 − k·h)⁵ is linear in rs and the coupled diffuse term is rd (1 − rs) D with
    D independent of N_u, N_v, so x = (rs, u_c = rd_c (1 − rs)): offset S(F with rs = 0),
    rs → S(rs = 1) − S(rs = 0), u_c → D. Held (``fixed``) parameters move into the offset."""

    def __init__(self, sm: SliceModel, model: str, fixed: dict, C: int):
        self.sm, self.model, self.C = sm, model, C
        self.fixed = {k: torch.as_tensor(v, dtype=torch.float64) for k, v in fixed.items()}
        self.D = self.diffuse(sm)
        self.width = [k for k in _WIDTH[model] if k not in fixed]
        self._rs10 = torch.tensor([1.0, 0.0], dtype=torch.float64).reshape(2, 1, 1)

    def diffuse(self, sm: SliceModel) -> torch.Tensor:
        """``[P, C]``: the Lambertian image of unit albedo (microfacet) or the Ashikhmin–Shirley
        coupled diffuse term at rd = 1, rs = 0 (independent of the exponents)."""
        from ..brdf import AshikhminShirley, Lambertian

        if self.model == "microfacet":
            return sm.render(Lambertian(1.0))
        return sm.render(AshikhminShirley(nu=1.0, rs=0.0, rd=1.0)) - sm.render(AshikhminShirley(nu=1.0, rs=0.0, rd=0.0))

    def _channel(self, img: torch.Tensor, c: int) -> torch.Tensor:
        out = torch.zeros_like(img)
        out[:, c] = img[:, c]
        return out

    def _widths(self, phi: torch.Tensor) -> dict:
        w = {k: self.fixed[k] for k in _WIDTH[self.model] if k in self.fixed}
        w.update({k: torch.exp(phi[i]) for i, k in enumerate(self.width)})
        return w

    def columns(self, phi: torch.Tensor, sm: SliceModel | None = None):
        """(offset ``[P, C]``, columns ``[K, P, C]``, names of x) at log widths ``phi``."""
        from ..brdf import AshikhminShirley, Microfacet

        sm = sm or self.sm
        if sm is not self.sm and getattr(self, "_sub", (None,))[0] is not sm:
            self._sub = (sm, self.diffuse(sm))  # the scan's pixel subset: its diffuse image once
        D = self.D if sm is self.sm else self._sub[1]
        w = self._widths(phi)
        fx, C = self.fixed, self.C
        if self.model == "microfacet":
            S = sm.render(Microfacet(sigma=w["sigma"], ks=1.0))
            off = torch.zeros_like(S)
            cols, names = [], []
            if "kd" in fx:
                off = off + fx["kd"].expand(C)[None] * D
            else:
                cols += [self._channel(D, c) for c in range(C)]
                names += [("kd", c) for c in range(C)]
            if "ks" in fx:
                off = off + fx["ks"] * S
            else:
                cols.append(S)
                names.append(("ks", None))
            return off, cols, names
        nu, nv = (w["n"], w["n"]) if self.model == "ashikhmin-shirley" else (w["nu"], w["nv"])
        # rs = 1 (F = 1) and rs = 0 (F = (1 − k·h)⁵) as one batch of two parameter sets: the
        # direction terms are computed once
        F1, F0 = sm.render(AshikhminShirley(nu=nu, nv=nv, rs=self._rs10, diffuse=False)).unbind(0)
        if "rs" in fx and "rd" in fx:
            return F0 + fx["rs"] * (F1 - F0) + (fx["rd"].expand(C) * (1 - fx["rs"]))[None] * D, [], []
        if "rs" in fx:  # u_c = rd_c (1 − rs) linear
            return F0 + fx["rs"] * (F1 - F0), [self._channel(D, c) for c in range(C)], [("u", c) for c in range(C)]
        if "rd" in fx:  # F0 + rd D + rs (F1 − F0 − rd D)
            rdD = fx["rd"].expand(C)[None] * D
            return F0 + rdD, [F1 - F0 - rdD], [("rs", None)]
        return F0, [F1 - F0] + [self._channel(D, c) for c in range(C)], [("rs", None)] + [("u", c) for c in range(C)]

    def natural(self, x: torch.Tensor, names: list, phi: torch.Tensor) -> dict:
        """The model's own parameters (kd_c, ks, σ | rd_c, rs, n or nu, nv) from (x, φ); differentiable."""
        C = self.C
        p = {k: v for k, v in self.fixed.items()}
        p.update(self._widths(phi))
        lin: dict = {}
        for v, (k, c) in zip(x, names):
            if c is None:
                lin[k] = v
            else:
                lin.setdefault(k, [None] * C)[c] = v
        lin = {k: torch.stack(v) if isinstance(v, list) else v for k, v in lin.items()}
        if self.model == "microfacet":
            p.update(lin)
            if "kd" in p:
                p["kd"] = p["kd"].expand(C)
            return p
        p.update({k: v for k, v in lin.items() if k != "u"})
        if "u" in lin:
            p["rd"] = lin["u"] / (1 - p["rs"])
        p["rd"] = p["rd"].expand(C)
        return p


def _solve_linear(off, cols, y):
    """x ``[K]`` minimising ‖off + Σ x_k col_k − y‖² (all channels), by the normal equations
    (differentiable, forward mode included); the fitted image ``[P, C]``."""
    if not cols:
        return off.new_zeros(0), off
    A = torch.stack([c.T.reshape(-1) for c in cols], 1)  # [(C·P), K]
    b = (y - off).T.reshape(-1)
    x = torch.linalg.solve(A.T @ A, A.T @ b)
    return x, off + torch.einsum("k,kpc->pc", x, torch.stack(cols))


def fit_parametric(sm: SliceModel, values: torch.Tensor, model: str, *, fixed: dict | None = None,
                   scan: int = 12, scan_pixels: int = 400, iterations: int = 30, seed: int = 0) -> BRDFFit:
    """Fit ``model`` ∈ :data:`PARAMETERS` to ``values [P, C]`` (Ramamoorthi 2002 §6.4.2).

    microfacet: B = kd_c E + f*_Microfacet(σ, ks) (eq. 6.12's diffuse + the lobe of eq. 5.34; kd per
    channel); ashikhmin-shirley: Ashikhmin & Shirley 2000 eq. 4–5 with Schlick's Fresnel, isotropic
    (one n) or ``-anisotropic`` (nu along the tangent, nv along the bitangent); rd per channel.

    The parameters the model is linear in are eliminated (variable projection, :class:`_Separable`):
    a scan of ``scan`` log-spaced lobe widths on ``scan_pixels`` random pixels (the thesis's nested
    procedure, its simplex replaced by the scan), then Levenberg–Marquardt on the log widths with the
    Jacobian of the projected residual by forward-mode autograd (:func:`jacobian_fwd`, through the
    linear solve). Standard errors: (JᵀJ)⁻¹σ̂² with J the full Jacobian in (x, log widths), carried
    to the model's parameters by the delta method. ``fixed``: name → value held (per-channel ones:
    a float or ``[C]``); their standard error is 0. Returns :class:`BRDFFit`."""
    if model not in PARAMETERS:
        raise ValueError(f"BRDF model {model!r}; accepted: {', '.join(PARAMETERS)}")
    spec = PARAMETERS[model]
    fixed = dict(fixed or {})
    names_all = [s[0] for s in spec]
    for k in fixed:
        if k not in names_all:
            raise ValueError(f"fixed parameter {k!r} of {model}; accepted: {', '.join(names_all)}")
    y = values.to(torch.float64)
    C = y.shape[1]
    sep = _Separable(sm, model, fixed, C)
    nw = len(sep.width)

    def resid(phi, s=None, yy=None):
        off, cols, _ = sep.columns(phi, s)
        return (_solve_linear(off, cols, y if yy is None else yy)[1] - (y if yy is None else yy)).reshape(-1)

    if nw:  # scan the isotropic width (N_u = N_v) on a pixel subset
        g = torch.Generator().manual_seed(seed)
        sub = torch.randperm(sm.P, generator=g)[:scan_pixels]
        sm_sub = dataclasses.replace(sm, wo=sm.wo[sub], W=sm.W[sub], wi=sm.wi[sub] if sm.wi.ndim == 3 else sm.wi)
        lo, hi = _SCAN[sep.width[0]]
        best = None
        for v in np.linspace(math.log(lo), math.log(hi), scan):  # `scan` projected residuals
            phi = torch.full((nw,), float(v), dtype=torch.float64)
            r = resid(phi, sm_sub, y[sub])
            f = float(r @ r)
            if best is None or f < best[0]:
                best = (f, phi)
        bounds = torch.tensor([[math.log(s[2]), math.log(s[3])] for s in spec if s[0] in sep.width], dtype=torch.float64)
        project = lambda t: torch.maximum(torch.minimum(t, bounds[:, 1]), bounds[:, 0])  # noqa: E731
        phi, _, f, _, it = levenberg_marquardt(resid, best[1], iterations=iterations, project=project, rtol=1e-10, xtol=1e-7)
    else:
        phi, it = torch.zeros(0, dtype=torch.float64), 0
    off, cols, names = sep.columns(phi)
    x, pred = _solve_linear(off, cols, y)
    rss = float(((pred - y) ** 2).sum())

    def full(theta):  # the residual in (x, log widths): its Jacobian gives the covariance
        o, cc, _ = sep.columns(theta[len(x):])
        return (o + (torch.einsum("k,kpc->pc", theta[:len(x)], torch.stack(cc)) if cc else 0) - y).reshape(-1)

    theta = torch.cat([x, phi])
    if theta.numel():  # the full covariance (the delta method needs the correlations too)
        Jx = torch.stack([c.reshape(-1) for c in cols], 1) if cols else torch.zeros(y.numel(), 0, dtype=torch.float64)
        Jphi = jacobian_fwd(lambda ph: full(torch.cat([x, ph])), phi) if nw else Jx[:, :0]
        J = torch.cat([Jx, Jphi], 1)  # ∂r/∂x are the columns themselves: autograd only for the widths
        try:
            cov = torch.linalg.inv(J.T @ J) * (rss / max(J.shape[0] - J.shape[1], 1))
        except RuntimeError:
            cov = torch.full((theta.numel(), theta.numel()), math.inf, dtype=torch.float64)

    def nat_vec(th):
        p = sep.natural(th[:len(x)], names, th[len(x):])
        return torch.cat([p[k].reshape(-1) for k in names_all])

    p = sep.natural(x, names, phi)
    vals = torch.cat([p[k].reshape(-1) for k in names_all])
    if theta.numel():
        G = torch.autograd.functional.jacobian(nat_vec, theta)  # [n_nat, n_theta]
        se_nat = torch.sqrt(torch.diagonal(G @ cov @ G.T).clamp_min(0))
    else:
        se_nat = torch.zeros_like(vals)
    params, stderr, rel = {}, {}, {}
    i = 0
    for (k, ch, _lo, _hi) in spec:
        sz = C if ch else 1
        v, e = vals[i:i + sz], se_nat[i:i + sz]
        i += sz
        if k in fixed:
            e = torch.zeros_like(e)
        params[k] = [float(a) for a in v] if ch else float(v[0])
        stderr[k] = [float(a) for a in e] if ch else float(e[0])
        r_ = [float(a) / abs(float(b)) if float(b) else math.inf for a, b in zip(e, v)]
        rel[k] = r_ if ch else r_[0]
    bad = [k for (k, ch, lo, hi) in spec
           if any(not lo <= v <= hi for v in (params[k] if ch else [params[k]]))]
    return BRDFFit(params, stderr, rel, pred, rss, it, bad)


# ----------------------------------------------------------------------------------------- SH BRDF
def sh_brdf_index(bands_out: int, bands_in: int) -> torch.Tensor:
    """``[K, 3]`` int64 (l, p, q) of the isotropic SH BRDF coefficients ρ̂_lpq (Ramamoorthi 2002
    eq. 5.8: l the light's band, p the view's band, q ≥ 0 the shared azimuthal order, q ≤ min(l, p)),
    ordered by q, then l, then p. K = Σ_q (bands_in − q)(bands_out − q)."""
    rows = [(l, p, q) for q in range(min(bands_out, bands_in)) for l in range(q, bands_in) for p in range(q, bands_out)]
    return torch.tensor(rows, dtype=torch.int64).reshape(-1, 3)


def sh_brdf_coeffs(B: torch.Tensor, bands_out: int, bands_in: int) -> torch.Tensor:
    """ρ̂_lpq ``[..., K]`` of a BRDF matrix ``B [..., bands_out², bands_in²]`` (rows the view's SH,
    columns the light's, as :func:`prt_torch.brdf.brdf_matrix`): B_(p,q),(l,q) — the (p,−q),(l,−q)
    entry is the same for an isotropic BRDF even in φ_i − φ_o."""
    idx = sh_brdf_index(bands_out, bands_in)
    l, p, q = idx.unbind(1)
    return B[..., p * (p + 1) + q, l * (l + 1) + q]


def sh_brdf_matrix(coeffs: torch.Tensor, bands_out: int, bands_in: int) -> torch.Tensor:
    """The BRDF matrix ``[..., bands_out², bands_in²]`` of ρ̂_lpq ``[..., K]`` (both ±q entries)."""
    idx = sh_brdf_index(bands_out, bands_in)
    l, p, q = idx.unbind(1)
    B = torch.zeros(*coeffs.shape[:-1], bands_out ** 2, bands_in ** 2, dtype=coeffs.dtype)
    B[..., p * (p + 1) + q, l * (l + 1) + q] = coeffs
    B[..., p * (p + 1) - q, l * (l + 1) - q] = coeffs
    return B


def sh_brdf_design(sm: SliceModel, bands_out: int, bands_in: int) -> torch.Tensor:
    """``[C, P, K]`` float64: pixel p of channel c is Σ_k A_cpk ρ̂_k (module doc): column (l, p, q)
    is Σ_± y_(p,±q)(ω_o) r_(l,±q), r_p,j = Σ_q y_j(s_q) W_pq — the pixel's shadowed incident light
    on its hemisphere, projected on the local SH (the zero-hemisphere projection of the engine's
    glossy transfer, Sloan 2003 §3.1)."""
    from ..sh import eval_sh

    if sm.wi.ndim == 2:
        r = torch.einsum("pqc,qj->cpj", sm.W, eval_sh(sm.wi, bands_in, check=False))  # [C, P, n_in²]
    else:  # one rule per pixel: chunks of pixels bound the [p, Q, n_in²] basis values
        step = max(1, (1 << 22) // (sm.wi.shape[1] * bands_in ** 2))
        r = torch.cat([torch.einsum("pqc,pqj->cpj", sm.W[a:a + step],
                                    eval_sh(sm.wi[a:a + step].reshape(-1, 3), bands_in, check=False)
                                    .reshape(-1, sm.wi.shape[1], bands_in ** 2)) for a in range(0, sm.P, step)], 1)
    yo = eval_sh(sm.wo, bands_out, check=False)  # [P, n_out²]
    l, p, q = sh_brdf_index(bands_out, bands_in).unbind(1)
    A = yo[:, p * (p + 1) + q][None] * r[:, :, l * (l + 1) + q]
    neg = q > 0
    A[:, :, neg] += yo[:, (p * (p + 1) - q)[neg]][None] * r[:, :, (l * (l + 1) - q)[neg]]
    return A


def fit_sh_brdf(sm: SliceModel, values: torch.Tensor, bands_out: int, bands_in: int | None = None, *,
                method: str = "gcv", eps: float = 2.0 ** -24) -> dict:
    """ρ̂_lpq per channel from ``values [P, C]`` by Tikhonov least squares (Ramamoorthi 2002 §6.4.2,
    "we simply solve a linear system"; λ from the data by :func:`~prt_torch.inverse.light.solve_tikhonov`).

    Returns a dict: ``index`` ``[K, 3]`` (l, p, q), ``coeffs`` ``[C, K]`` float64, ``matrix``
    ``[C, bands_out², bands_in²]`` (the BRDF matrix, :func:`sh_brdf_matrix`), ``resolution``
    ``[C, K]`` (diagonal of the model resolution matrix V F Vᵀ: 1 for a coefficient the images
    determine, 0 for one they do not — e.g. every q > 0 under a constant light, whose local
    incident light is zonal), ``stderr`` ``[C, K]`` (σ̂ ‖(V F S⁻¹)_k‖, σ̂² the residual variance),
    ``determined`` ``[K]`` bool (resolution ≥ ½ in every channel), ``singular_values`` (channel 0,
    relative), ``lam`` per channel (relative), ``predicted`` ``[P, C]``."""
    from .light import solve_tikhonov

    bands_in = bands_out if bands_in is None else bands_in
    A = sh_brdf_design(sm, bands_out, bands_in)
    y = values.to(torch.float64)
    C, P, K = A.shape
    fits = [solve_tikhonov(A[c], y[:, c], method, eps) for c in range(C)]
    x = torch.stack([f["x"] for f in fits])
    pred = torch.einsum("cpk,ck->pc", A, x)
    res = torch.stack([f["resolution"] for f in fits])
    se = []
    for f, c in zip(fits, range(C)):
        s, lam = f["s"], f["lam"]
        dof = max(P - float(f["filter"].sum()), 1.0)
        sig = math.sqrt(max(float(((pred[:, c] - y[:, c]) ** 2).sum()), 0.0) / dof)
        se.append(sig * ((f["Vh"].T * (s / (s ** 2 + lam ** 2))[None]) ** 2).sum(1).sqrt())
    smax = float(fits[0]["s"][0])
    return {"index": sh_brdf_index(bands_out, bands_in), "coeffs": x, "matrix": sh_brdf_matrix(x, bands_out, bands_in),
            "resolution": res, "stderr": torch.stack(se), "determined": (res >= 0.5).all(0),
            "singular_values": [float(v) / smax for v in fits[0]["s"]], "lam": [f["lam"] / float(f["s"][0]) for f in fits],
            "predicted": pred, "bands_out": bands_out, "bands_in": bands_in}
