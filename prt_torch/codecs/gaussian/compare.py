"""What Green 2005 measures the Gaussians against (Fig. 3-3, §3.3): the relative L2 error of an
approximation of a transport function on the sphere, and the linear SH and the non-linear Haar
(Ng et al. 2003) approximations with a given number of coefficients
(benchmarks/bench_gaussian.py, reports/benchmarks/gaussian.md); and the exact value of a lobe's lookup
against an SH light (Green eq. 2.7 in float64), the independent reference of the relight path
(benchmarks/bench_gaussian_taps.py, reports/benchmarks/gaussian_taps_v42.md).
"""
from __future__ import annotations

import math

import torch

__all__ = ["relative_l2", "sh_truncation", "haar_truncation", "sh_light_lobe_integral"]


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
    from ...sh import eval_sh

    bands = math.isqrt(k - 1) + 1
    Y = eval_sh(dirs.double(), bands, check=False)[:, :k]  # [P, k]
    c = (T.double() * solid_angles.double()) @ Y
    return c @ Y.T


def haar_truncation(T: torch.Tensor, k: int) -> torch.Tensor:
    """Non-linear Haar approximation on the cube map (Ng et al. 2003, as Green §3.3): the
    orthonormal 2D (non-standard) Haar transform of each face
    (:func:`prt_torch.lighting.haar.haar2d`), keep the ``k`` largest coefficients over all six
    faces, invert. ``T [B, 6, r, r]`` (r a power of 2) → same shape, float64."""
    from ...lighting.haar import haar2d, ihaar2d

    B, F, r, _ = T.shape
    if r & (r - 1):
        raise ValueError(f"Haar needs a power-of-two face size; got r={r}")
    flat = haar2d(T.double()).reshape(B, -1)
    keep = flat.abs().topk(min(k, flat.shape[1]), dim=1).indices
    y = torch.zeros_like(flat).scatter_(1, keep, flat.gather(1, keep)).reshape(B, F, r, r)
    return ihaar2d(y)


def sh_light_lobe_integral(L: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, n: int = 96,
                           chunk: int = 20000) -> torch.Tensor:
    """E_σ(μ) = ∫ G(ω; μ, σ) L(ω) dω (Green 2005 eq. 2.7's lookup, without the prefiltered pyramid)
    in float64 for an SH light ``L [C, n²]``: Funk–Hecke (Ramamoorthi 2002 eq. 3.28) with the
    normalised Gaussian's zonal coefficients h_l = 2π ∫ c(λ) e^{λ(t−1)} Y_l0(t) dt by ``n``-point
    Gauss–Legendre on [max(−1, 1 − 60σ²), 1] (the integrand is below e^−60 of its peak beyond),
    rotated to μ (``sh.rotate_zonal``). ``mu [M, 3]`` (normalised here; a zero mean — the blend of
    zero lobes — gets +z), ``sigma [M]`` > 0 → ``[M, C]`` float64, in blocks of ``chunk``."""
    from ...lighting.prefilter import sg_normaliser
    from ...sh.basis import eval_zonal_basis
    from ...sh.zonal import gauss_legendre, rotate_zonal

    bands = math.isqrt(L.shape[1])
    x, wx = gauss_legendre(n)
    out = []
    for a in range(0, mu.shape[0], chunk):
        m, s = mu[a:a + chunk].double(), sigma[a:a + chunk].double()
        nm = m.norm(dim=-1, keepdim=True)
        m = torch.where(nm > 0.5, m / nm.clamp_min(1e-12), torch.tensor([0.0, 0.0, 1.0], dtype=m.dtype))
        lam = s.reciprocal().square()
        lo = (1 - 60 * s * s).clamp(-1, 1)
        t = lo[:, None] + (x[None] + 1) * (1 - lo[:, None]) / 2
        wt = wx[None] * (1 - lo[:, None]) / 2
        g = sg_normaliser(lam)[:, None] * torch.exp(lam[:, None] * (t - 1))
        h = 2 * math.pi * torch.einsum("mn,mnl->ml", wt * g, eval_zonal_basis(t.clamp(-1, 1), bands))
        out.append(rotate_zonal(h, m, check=False) @ L.double().T)
    return torch.cat(out) if out else torch.zeros(0, L.shape[0], dtype=torch.float64)
