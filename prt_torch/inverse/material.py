"""Unknown BRDF (Ramamoorthi 2002 §6.4.2) and both unknown (§6.4.4), through the thesis's model of
the reflected light field with visibility, eq. 6.12 (its slow part; eq. 6.16 for the light):

    B_p,c = k_d,c · E_p,c + k_s · V(R_p) · Σ_l Λ_l h_l(s) Σ_m L_c,lm Y_lm(R_p)

E_p,c = Σ_i β_pi T_i · L_c is the shadowed irradiance term of eq. 6.10 through the engine's diffuse
transfer computed with unit albedo (Ỹ_lm of the thesis; Sloan 2002); R_p the view reflected about
the interpolated shading normal, V(R_p) whether that reflected ray leaves the object (one Embree
occlusion ray per pixel: the thesis's "check the reflected ray", eq. 6.11); h_l(s) the zonal
coefficients of the normalised Phong lobe (s+1)/(2π) max(R·ω, 0)^s (eq. 3.37,
:func:`prt_torch.sh.phong`) — the reflection form of :class:`prt_torch.brdf.Phong` (its
:meth:`~prt_torch.brdf.Phong.lobes`), Λ_l = √(4π/(2l+1)).

The model is linear in the light for fixed (k_d, k_s, s) — unknown light is eq. 6.16 — and linear in
(k_d, k_s) for fixed s: the non-linear fit (:func:`fit_phong`) starts from the best s of a
log-spaced scan with (k_d, k_s) solved linearly at each (the thesis's nested procedure), then
refines every parameter by Gauss–Newton / Levenberg–Marquardt on the autograd Jacobian
(``torch.func.jacfwd``: forward mode, one pass per parameter), reporting standard errors from (JᵀJ)⁻¹ (how well the images determine each
parameter: ch. 2 §2.4.2, eq. 2.64 — ill-conditioned when the light lacks the lobe's frequencies).

Both unknown (:func:`fit_both`, §6.4.4): the outer problem over (k_s/(k_d+k_s), s), the inner one the
light by :func:`prt_torch.inverse.light.fit_light` (GCV). The ambiguities of the chapter, fixed and
reported: the global scale between light and reflectance (k_d + k_s = 1 on the luminance; the
light carries the absolute scale), the colour of light vs diffuse albedo (the light is grey-balanced
to the specular k_s, which is colourless for dielectrics), and roughness vs light blur (s is
ill-conditioned under low-frequency light: its standard error says so).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch

from ..sh import band_factor, eval_sh, phong as phong_zonal
from .brdf_fit import BRDFFit, covariance_stderr, levenberg_marquardt

__all__ = ["LobeModel", "lobe_model", "fit_phong", "fit_both", "BRDFFit", "PARAMETRIC"]

PARAMETRIC = ("phong",)  # models fitted by fit_phong (the reflection-form Phong of eq. 6.12)


@dataclasses.dataclass
class LobeModel:
    """Per-pixel terms of eq. 6.12 for a set of observations.

    Attributes:
        E: ``[P, n²]`` float64 diffuse rows (Σ_i β_pi T_i, unit albedo, shadowed).
        S: ``[P, n²]`` float64 specular rows V(R_p) Y_lm(R_p).
        bands: n.
        visible: ``[P]`` bool V(R_p).
    """

    E: torch.Tensor
    S: torch.Tensor
    bands: int
    visible: torch.Tensor

    def band_index(self) -> torch.Tensor:
        """``[n²]`` int64 band l of each flat SH index."""
        return torch.cat([torch.full((2 * l + 1,), l, dtype=torch.int64) for l in range(self.bands)])

    def spec_weights(self, s: torch.Tensor) -> torch.Tensor:
        """``[n²]`` Λ_l h_l(s) per flat index (differentiable in ``s``)."""
        h = phong_zonal(s, self.bands) * band_factor(self.bands)
        return h[self.band_index()]

    def light_rows(self, kd: torch.Tensor, ks: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """Eq. 6.16: ``[C, P, n²]`` rows with B_p,c = rows_c,p · L_c (``kd [C]``)."""
        return kd[:, None, None] * self.E[None] + ks * (self.S * self.spec_weights(s))[None]

    def render(self, L: torch.Tensor, kd: torch.Tensor, ks: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
        """Eq. 6.12: ``[P, C]`` for ``L [C, n²]``."""
        e = self.E @ L.T  # [P, C]
        sp = (self.S * self.spec_weights(s)) @ L.T
        return kd[None] * e + ks * sp


def lobe_model(mesh, transfer, obs, bands: int, caster=None) -> LobeModel:
    """Build :class:`LobeModel` for ``obs`` (:class:`~prt_torch.inverse.inputs.Observations`).

    ``transfer``: diffuse Transfer of ``mesh`` with data ``[V, n²]`` (albedo not folded in; the
    irradiance term uses it as unit albedo). The shading normal is the barycentric blend of the
    vertex normals; R = 2(n·ω_o)n − ω_o; V(R) one occlusion ray per pixel from the surface point."""
    from ..scene import RayCaster

    data = transfer.data
    if transfer.kind != "diffuse" or data.ndim != 2:
        raise ValueError(f"the BRDF fit needs diffuse transfer [V, n²] without albedo folded in; got {transfer.kind} "
                         f"{tuple(data.shape)} (precompute it with prt precompute --kind diffuse, grey)")
    n2 = bands * bands
    if data.shape[1] < n2:
        raise ValueError(f"transfer has {data.shape[1]} coefficients; accepted: at least bands²={n2} (--bands {bands})")
    T = data[:, :n2].to(torch.float64)
    E = (T[obs.corners] * obs.bary[:, :, None]).sum(1)
    nrm = (torch.as_tensor(mesh.normals, dtype=torch.float64)[obs.corners] * obs.bary[:, :, None]).sum(1)
    nrm = nrm / nrm.norm(dim=1, keepdim=True).clamp_min(1e-300)
    wo = obs.to_eye
    R = 2 * (nrm * wo).sum(1, keepdim=True) * nrm - wo
    R = R / R.norm(dim=1, keepdim=True)
    own = caster is None
    caster = RayCaster(mesh, workers=1) if own else caster
    try:
        blocked = caster.occluded(obs.points.numpy(), R.numpy(), normals=nrm.numpy())
    finally:
        if own:
            caster.close()
    vis = ~torch.as_tensor(np.asarray(blocked), dtype=torch.bool)
    S = eval_sh(R, bands) * vis[:, None].to(torch.float64)
    return LobeModel(E, S, bands, vis)


def _linear_kd_ks(model: LobeModel, L: torch.Tensor, y: torch.Tensor, s: float, grey: bool):
    """(kd [C], ks, rss) minimising ‖kd_c e_c + ks sp_c − y_c‖² jointly over channels for fixed s."""
    e = model.E @ L.T  # [P, C]
    sp = (model.S * model.spec_weights(torch.tensor(s, dtype=torch.float64))) @ L.T
    P, C = e.shape
    if grey:
        A = torch.stack([e.T.reshape(-1), sp.T.reshape(-1)], 1)  # [(C·P), 2]
    else:
        A = torch.zeros(C * P, C + 1, dtype=torch.float64)
        for c in range(C):  # C ≤ 3 channels: block columns
            A[c * P:(c + 1) * P, c] = e[:, c]
        A[:, C] = sp.T.reshape(-1)
    b = y.T.reshape(-1)
    x = torch.linalg.lstsq(A, b[:, None]).solution[:, 0]
    rss = float(((A @ x - b) ** 2).sum())
    kd = x[:1].expand(C) if grey else x[:C]
    return kd.clone(), x[-1].clone(), rss


def fit_phong(model: LobeModel, L: torch.Tensor, values: torch.Tensor, *, grey: bool = False,
              s_range: tuple[float, float] = (1.0, 2000.0), scan: int = 48, iterations: int = 50,
              fixed: dict | None = None) -> BRDFFit:
    """Reflection-form Phong (kd, ks, s) from pixels ``values [P, C]`` under the known ``L [C, n²]``
    (§6.4.2 with eq. 6.12): scan of ``scan`` log-spaced s in ``s_range`` with (kd, ks) linear,
    then Levenberg–Marquardt on (kd_c, ks, log s) with the autograd Jacobian. ``grey``: one kd
    for all channels. ``fixed``: {'s': value} keeps s (then the fit is linear)."""
    L = L.to(torch.float64)
    y = values.to(torch.float64)
    fixed = fixed or {}
    C = y.shape[1]
    if "s" in fixed:
        s_best = float(fixed["s"])
    else:
        grid = np.exp(np.linspace(math.log(s_range[0]), math.log(s_range[1]), scan))
        rss = [_linear_kd_ks(model, L, y, float(s), grey)[2] for s in grid]
        s_best = float(grid[int(np.argmin(rss))])
    kd0, ks0, _ = _linear_kd_ks(model, L, y, s_best, grey)
    nk = 1 if grey else C

    def unpack(theta):
        kd = theta[:nk].expand(C) if grey else theta[:nk]
        ks = theta[nk]
        # s kept inside s_range (a surface without a visible lobe leaves s free: ks → 0 and log s would run away)
        s = torch.exp(theta[nk + 1].clamp(math.log(s_range[0]), math.log(s_range[1]))) if "s" not in fixed \
            else torch.tensor(float(fixed["s"]), dtype=torch.float64)
        return kd, ks, s

    def resid(theta):
        kd, ks, s = unpack(theta)
        return (model.render(L, kd, ks, s) - y).reshape(-1)

    theta = torch.cat([kd0[:nk], ks0.reshape(1)] + ([torch.tensor([math.log(s_best)], dtype=torch.float64)] if "s" not in fixed else []))

    def project(t):
        if "s" in fixed:
            return t
        t = t.clone()
        t[nk + 1] = t[nk + 1].clamp(math.log(s_range[0]), math.log(s_range[1]))
        return t

    theta, r, f, J, it = levenberg_marquardt(resid, theta, iterations=iterations, project=project,
                                             jacobian=lambda fn, t: torch.func.jacfwd(fn)(t))
    se = covariance_stderr(J, f)
    kd, ks, s = unpack(theta)
    params = {"kd": [float(v) for v in kd], "ks": float(ks), "s": float(s)}
    se_kd = [float(se[0])] * C if grey else [float(v) for v in se[:nk]]
    se_s = float(se[nk + 1]) * float(s) if "s" not in fixed else 0.0  # d s = s d(log s)
    stderr = {"kd": se_kd, "ks": float(se[nk]), "s": se_s}
    relse = {"kd": [e / abs(v) if v else math.inf for e, v in zip(se_kd, params["kd"])],
             "ks": stderr["ks"] / abs(params["ks"]) if params["ks"] else math.inf,
             "s": se_s / params["s"]}
    with torch.no_grad():
        pred = model.render(L, kd, ks, s)
    return BRDFFit(params, stderr, relse, pred, f, it)


def fit_both(model: LobeModel, values: torch.Tensor, *, method: str = "gcv", eps: float = 2.0 ** -24,
             s_range: tuple[float, float] = (1.0, 2000.0), scan: int = 12) -> dict:
    """Light and reflection-form Phong both unknown (§6.4.4): for each candidate (w = k_s/(k_d+k_s),
    s) the light is solved linearly (GCV, :func:`~prt_torch.inverse.light.fit_light`) with
    k_d = 1 − w, k_s = w (grey), and the pair with the least residual is refined by golden sections
    on each coordinate in turn. The fixes of the ambiguities (module doc) are applied and listed.

    Returns a dict: light ``[C, n²]``, params {'kd', 'ks', 's'} (kd + ks = 1), fit (the LightFit),
    ambiguities (list of str)."""
    from .light import fit_light

    y = values.to(torch.float64)
    C = y.shape[1]

    def solve(w: float, s: float):
        rows = model.light_rows(torch.full((C,), 1.0 - w, dtype=torch.float64), torch.tensor(w, dtype=torch.float64),
                                torch.tensor(s, dtype=torch.float64))
        fit = fit_light(rows, y, method, eps)
        return float(((fit.predicted - y) ** 2).sum()), fit

    ws = np.linspace(0.0, 1.0, 6)
    ss = np.exp(np.linspace(math.log(s_range[0]), math.log(s_range[1]), scan))
    best = (math.inf, 0.0, 1.0)
    for w in ws:  # a coarse grid over two parameters (6 × scan linear solves of n² unknowns)
        for s in ss:
            r = solve(float(w), float(s))[0]
            if r < best[0]:
                best = (r, float(w), float(s))
    _, w, s = best

    def golden(f, a, b, iters=14):
        g = (math.sqrt(5) - 1) / 2
        c, d = b - g * (b - a), a + g * (b - a)
        fc, fd = f(c), f(d)
        for _ in range(iters):
            if fc < fd:
                b, d, fd = d, c, fc
                c = b - g * (b - a)
                fc = f(c)
            else:
                a, c, fc = c, d, fd
                d = a + g * (b - a)
                fd = f(d)
        return 0.5 * (a + b)

    step_w, step_ls = 0.2, math.log(ss[1] / ss[0])
    for _ in range(3):  # coordinate refinement
        w = golden(lambda t: solve(t, s)[0], max(w - step_w, 0.0), min(w + step_w, 1.0))
        ls = golden(lambda t: solve(w, math.exp(t))[0], math.log(s) - step_ls, math.log(s) + step_ls)
        s = math.exp(ls)
        step_w, step_ls = step_w / 3, step_ls / 3
    rss, fit = solve(w, s)
    amb = [
        "global scale between light and reflectance: fixed by kd + ks = 1 (Ramamoorthi 2002 §6.4.4); the light carries "
        "the absolute scale, so light × c with (kd, ks) / c renders the same images",
        "colour of the light vs the diffuse albedo: fixed by a grey BRDF (kd the same in every channel; ks is colourless "
        "for dielectrics, §6.4.4 'Color'); the light carries the colour",
        "light bands above the recoverable ones (well_posedness.recoverable_bands) are filtered away by the BRDF (ch. 2 "
        "eq. 2.65); the light returned is the regularised (filtered) one",
        "roughness vs light blur: s is ill-conditioned when the light lacks high frequencies (§6.4.4); see "
        "ks/s sensitivity below",
    ]
    return {"light": fit.light, "params": {"kd": [1.0 - w] * C, "ks": w, "s": s}, "fit": fit, "rss": rss,
            "ambiguities": amb}
