"""What Green 2005 measures the Gaussians against (Fig. 3-3, §3.3): the relative L2 error of an
approximation of a transport function on the sphere, and the linear SH and the non-linear Haar
(Ng et al. 2003) approximations with a given number of coefficients
(benchmarks/bench_gaussian.py, reports/benchmarks/gaussian.md).
"""
from __future__ import annotations

import math

import torch

__all__ = ["relative_l2", "sh_truncation", "haar_truncation"]


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
