"""Synthetic transfer-like signals for tests and benchmarks of the codecs (no scene needed).

A PRT signal over a surface is smooth where visibility is smooth, jumps where shadows begin,
and its energy falls with SH band (Sloan 2003 §4: "local linearity" is what CPCA exploits).
``transfer_like`` imitates that: points carry a latent normal u ∈ S²; the signal is

    x_p = A·φ(u_p)  +  R[region(u_p)]  +  noise

with φ a bank of smooth random Fourier features of u (low-rank smooth part), ``region`` the
Voronoi cell of u among ``regions`` random seeds (piecewise-constant "shadow" jumps), both
with columns scaled by exp(−l/2) for the SH band l of the input coefficient, plus white noise
of relative size ``noise``. ``tent_taps`` gives the 4 bilinear taps of an M×M grid as used by
MRT (Lehtinen & Kautz 2003 §4.3) for random view positions.
"""
from __future__ import annotations

import math

import torch

__all__ = ["transfer_like", "tent_taps_random"]


def transfer_like(P: int, n_out: int, n_in: int, *, regions: int = 128, features: int = 256, noise: float = 1e-3,
                  max_freq: float = 6.0,
                  seed: int = 0) -> torch.Tensor:
    """``float32 [P, n_out·n_in]`` transfer-like signal (rows: row-major n_out×n_in matrices)."""
    g = torch.Generator().manual_seed(seed)
    D = n_out * n_in
    u = torch.randn(P, 3, generator=g, dtype=torch.float64)
    u = u / u.norm(dim=1, keepdim=True)
    band = torch.tensor([math.isqrt(i) for i in range(n_in)], dtype=torch.float64)
    band_out = torch.tensor([math.isqrt(i) for i in range(n_out)], dtype=torch.float64)
    scale = (torch.exp(-0.5 * band_out)[:, None] * torch.exp(-0.5 * band)[None, :]).reshape(D)
    freq = torch.randn(features, 3, generator=g, dtype=torch.float64) * torch.linspace(0.5, max_freq, features, dtype=torch.float64)[:, None]
    phase = torch.rand(features, generator=g, dtype=torch.float64) * 2 * math.pi
    phi = torch.cos(u @ freq.T + phase)  # [P, F]
    A = torch.randn(features, D, generator=g, dtype=torch.float64) / math.sqrt(features)
    x = (phi @ A) * scale
    seeds = torch.randn(regions, 3, generator=g, dtype=torch.float64)
    seeds = seeds / seeds.norm(dim=1, keepdim=True)
    region = torch.argmax(u @ seeds.T, dim=1)
    R = torch.randn(regions, D, generator=g, dtype=torch.float64) * scale * 0.7
    x = x + R[region]
    x = x + noise * float(x.std()) * torch.randn(P, D, generator=g, dtype=torch.float64)
    return x.to(torch.float32)


def tent_taps_random(P: int, M: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Bilinear ("tent") taps on an M×M grid at random positions of the unit square:
    ``(idx int64 [P, 4], w float32 [P, 4])`` with weights summing to 1 (Lehtinen & Kautz 2003 §4.3)."""
    g = torch.Generator().manual_seed(seed)
    st = torch.rand(P, 2, generator=g) * (M - 1)
    i0 = st.floor().long().clamp_max(M - 2) if M > 1 else torch.zeros(P, 2, dtype=torch.long)
    f = st - i0
    a, b = i0[:, 0], i0[:, 1]
    idx = torch.stack([a * M + b, a * M + b + 1, (a + 1) * M + b, (a + 1) * M + b + 1], 1)
    w = torch.stack([(1 - f[:, 0]) * (1 - f[:, 1]), (1 - f[:, 0]) * f[:, 1], f[:, 0] * (1 - f[:, 1]), f[:, 0] * f[:, 1]], 1)
    return idx.clamp_max(M * M - 1), w.to(torch.float32)
