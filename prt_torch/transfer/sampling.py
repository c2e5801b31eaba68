"""Direction sets for Monte Carlo transfer: stratified, deterministic per seed.

* ``uniform_sphere(n, seed)``: jittered stratified directions uniform on the sphere with equal
  weights 4π/n (course notes 2005, "Precomputation": t = 4π/N Σ_j ...). The same set serves
  every vertex, so its SH values are evaluated once (the standard PRT approach).
* ``cosine_hemisphere(n, seed)``: jittered stratified directions in the *local* frame (z ≥ 0)
  with density cos θ / π (Malley's method: stratified unit square -> disk r = √u, φ = 2πv, then
  lifted to z = √(1 − r²)). The estimator of (1/π) ∫ f(s) max(n·s, 0) ds is (1/n) Σ f(s_j).
  ``to_world(dirs_local, frames)`` turns them into per-vertex world directions.
"""
from __future__ import annotations

import math

import torch

from .._checks import check_int
from ..sh import stratified_sphere, stratified_square

__all__ = ["uniform_sphere", "cosine_hemisphere", "to_world"]


def uniform_sphere(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` stratified uniform sphere directions ``[n,3] float64`` and weights ``[n]`` = 4π/n."""
    n = check_int("samples", n, 1)
    return stratified_sphere(n, seed=int(seed), dtype=torch.float64)


def cosine_hemisphere(n: int, seed: int = 0) -> torch.Tensor:
    """``n`` stratified cosine-weighted directions in the local frame, ``[n,3] float64``, z > 0.

    Strata: a ⌊√n⌋ × ⌈n/⌊√n⌋⌉ grid on the unit square (leftover samples uniform), jittered by a
    ``torch.Generator`` seeded with ``seed``; mapped by Malley's method (pdf = cos θ / π).
    """
    n = check_int("samples", n, 1)
    ab = stratified_square(n, seed)
    a, b = ab[:, 0], ab[:, 1]
    r = torch.sqrt(a)
    phi = 2 * math.pi * b
    z = torch.sqrt((1 - a).clamp_min(0.0))
    d = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)
    # guard the measure-zero horizon (z = 0) so every ray leaves the surface
    d[:, 2] = d[:, 2].clamp_min(1e-12)
    return d / d.norm(dim=-1, keepdim=True)


def to_world(dirs_local: torch.Tensor, frames: torch.Tensor) -> torch.Tensor:
    """Local directions ``[N,3]`` -> world ``[V,N,3]`` through frames ``[V,3,3]`` whose rows are
    (t, b, n) (world->local), i.e. s_world = Fᵀ s_local."""
    return torch.einsum("nk,vkj->vnj", dirs_local.to(frames.dtype), frames)
