"""The light as Mitsuba sees it (docs/validate.md, "The light"): an SH light reconstructed on
Mitsuba's ``envmap`` lat-long grid, the check that Mitsuba can emit it, and the original image
of an environment for ``light_source='image'``.

The SH light ``[C, n²]`` is reconstructed on a lat-long image in Mitsuba's
  ``envmap`` parametrisation (Mitsuba local direction (sin θ sin φ, cos θ, −sin θ cos φ) for
  u = φ/2π, v = θ/π; with the identity ``to_world`` this is also prt_torch's world frame, +z up —
  pinned by tests/test_validate.py). Because the transfer vector is the projection of the
  transfer function onto the first n bands, t·l equals the integral of the band-limited light
  against the *full* transfer: the comparison is exact, no SH truncation enters. A light whose
  band-limited reconstruction goes negative (a directional light, a sharp cap at many bands)
  cannot be emitted and is refused by name before any work. ``light_source='image'`` (files
  and built-in environments) gives Mitsuba the original image instead; the difference between
  the two Mitsuba runs is what SH truncation of the light contributes (reported).
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..lighting import Environment, list_builtin_environments
from ..sh import eval_sh

__all__ = ["mitsuba_envmap_directions", "light_image", "check_expressible", "source_image"]


def mitsuba_envmap_directions(height: int) -> torch.Tensor:
    """World directions ``[H, 2H, 3]`` float64 of the pixel centres of a Mitsuba ``envmap``
    lat-long image with the identity ``to_world``: u = φ/2π, v = θ/π,
    d = (sin θ sin φ, cos θ, −sin θ cos φ) (Mitsuba 3 ``envmap.cpp``; pinned by a test)."""
    H, W = int(height), 2 * int(height)
    th = math.pi * (torch.arange(H, dtype=torch.float64) + 0.5) / H
    ph = 2 * math.pi * (torch.arange(W, dtype=torch.float64) + 0.5) / W
    st, ct = torch.sin(th)[:, None], torch.cos(th)[:, None]
    return torch.stack([st * torch.sin(ph), ct.expand(H, W), -st * torch.cos(ph)], -1)


def light_image(L: torch.Tensor, height: int = 128) -> np.ndarray:
    """The SH light ``L [C, n²]`` (C = 1 or 3) reconstructed on Mitsuba's lat-long grid:
    ``[H, 2H, 3]`` float32 radiance (grey lights replicated to RGB)."""
    L = torch.as_tensor(L, dtype=torch.float64)
    L = L[None] if L.ndim == 1 else L
    bands = int(round(math.sqrt(L.shape[1])))
    d = mitsuba_envmap_directions(height)
    img = eval_sh(d.reshape(-1, 3), bands) @ L.T  # [HW, C]
    img = img.expand(-1, 3) if img.shape[1] == 1 else img
    return img.reshape(d.shape[0], d.shape[1], 3).numpy().astype(np.float32)


def check_expressible(L: torch.Tensor, name: str, height: int = 128, tol: float = 1e-3) -> np.ndarray:
    """Refuse (``ValueError`` naming the light) a light Mitsuba cannot emit: one whose
    band-limited reconstruction is negative somewhere (below ``-tol`` × its peak). Returns the
    image, with round-off negatives clipped."""
    img = light_image(L, height)
    peak = float(np.abs(img).max())
    if peak == 0 or not np.isfinite(img).all():
        raise ValueError(f"light {name!r} is zero or not finite; accepted: a light with positive radiance")
    lo = float(img.min())
    if lo < -tol * peak:
        raise ValueError(f"light {name!r}: its {int(round(math.sqrt(L.shape[-1])))}-band SH reconstruction is negative "
                         f"(min {lo:.3g}, peak {peak:.3g}) and Mitsuba cannot emit negative radiance; accepted: lights whose "
                         "band-limited radiance is non-negative (constant, sky_gradient, hemisphere/cap at 2 bands, smooth "
                         "environments), or light_source='image' for an environment file")
    return np.maximum(img, 0.0)


def source_image(spec: Any, height: int) -> np.ndarray | None:
    """The original radiance of an environment (file or built-in) on Mitsuba's grid, or None
    when ``spec`` is analytic (no image behind it)."""
    from ..lighting import builtin_environment, load_environment

    if isinstance(spec, Environment):
        env = spec
    elif isinstance(spec, str) and spec in list_builtin_environments():
        env = builtin_environment(spec)
    elif isinstance(spec, (str, os.PathLike)) and Path(spec).exists():
        env = load_environment(spec)
    else:
        return None
    d = mitsuba_envmap_directions(height)
    v = env.sample(d.reshape(-1, 3)).to(torch.float64)  # [HW, C]
    v = v.expand(-1, 3) if v.shape[1] == 1 else v
    return v.reshape(d.shape[0], d.shape[1], 3).numpy().astype(np.float32)
