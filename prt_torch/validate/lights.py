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
  the two Mitsuba runs is what SH truncation of the light contributes (reported). That image is
  a power-conserving remap of the environment onto Mitsuba's grid (:func:`remap_to_mitsuba`):
  every source pixel's power (radiance × exact solid angle) reaches Mitsuba, whose pixels emit
  through bilinear hats (:func:`mitsuba_pixel_solid_angles`), so a sun smaller than a pixel keeps
  its power (docs/validate.md, "Environment images reach Mitsuba with their power").
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ..lighting import Environment, list_builtin_environments
from ..lighting import layouts as L
from ..sh import eval_sh

__all__ = ["mitsuba_envmap_directions", "mitsuba_pixel_solid_angles", "light_image", "check_expressible", "source_image",
           "source_height", "remap_to_mitsuba"]


def mitsuba_envmap_directions(height: int) -> torch.Tensor:
    """World directions ``[H, 2H, 3]`` float64 of the pixels of a Mitsuba ``envmap`` lat-long image
    with the identity ``to_world``, d = (sin θ sin φ, cos θ, −sin θ cos φ) (Mitsuba 3
    ``envmap.cpp``). Mitsuba interpolates the image bilinearly with row i at θ = π i/(H − 1) (the
    first and last rows *on* the poles) and column j at φ = 2π (j + ½)/W, wrapping in φ (measured
    on Mitsuba 3.9 and pinned by tests/test_validate.py); these are the directions where its
    radiance equals pixel (i, j)."""
    H, W = int(height), 2 * int(height)
    th = math.pi * torch.arange(H, dtype=torch.float64) / (H - 1)
    ph = 2 * math.pi * (torch.arange(W, dtype=torch.float64) + 0.5) / W
    st, ct = torch.sin(th)[:, None], torch.cos(th)[:, None]
    return torch.stack([st * torch.sin(ph), ct.expand(H, W), -st * torch.cos(ph)], -1)


def mitsuba_pixel_solid_angles(height: int) -> torch.Tensor:
    """Exact solid angle ``[H]`` float64 of a Mitsuba ``envmap`` pixel of row i (every column
    alike): the integral of its bilinear hat Λ_i(θ)Λ_j(φ) over the sphere,
    Δφ ∫ Λ_i(θ) sin θ dθ with node spacing h = π/(H − 1) and Δφ = 2π/W:
    Δφ · 2 sin θ_i (1 − cos h)/h inside, Δφ (1 − sin h / h) on the two pole rows. The hats sum
    to one, so W Σ_i Ω_i = 4π; a pixel's power in Mitsuba is its radiance times Ω_i."""
    H = int(height)
    h = math.pi / (H - 1)
    th = h * torch.arange(H, dtype=torch.float64)
    om = torch.sin(th) * (2 * (1 - math.cos(h)) / h)
    om[0] = om[-1] = 1 - math.sin(h) / h
    return om * (2 * math.pi / (2 * H))


def _mitsuba_coords(d: torch.Tensor, height: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Continuous Mitsuba node coordinates (t row, u column) of world directions ``[N, 3]``:
    t = θ/h ∈ [0, H − 1], u = φ W/2π − ½ (periodic); the inverse of
    :func:`mitsuba_envmap_directions` at integer (t, u)."""
    H, W = int(height), 2 * int(height)
    t = torch.arccos(d[:, 1].clamp(-1, 1)) * ((H - 1) / math.pi)
    u = torch.remainder(torch.atan2(d[:, 0], -d[:, 2]), 2 * math.pi) * (W / (2 * math.pi)) - 0.5
    return t, u


def _hat_entries(d: torch.Tensor, w: torch.Tensor, e: torch.Tensor, height: int):
    """Bilinear (hat) weights of points ``d [N, 3]`` (weights ``w [N]``, engine pixels ``e [N]``)
    on Mitsuba's nodes: (node index [4N], engine pixel [4N], weight [4N])."""
    H, W = int(height), 2 * int(height)
    t, u = _mitsuba_coords(d, H)
    i0 = t.floor().clamp(0, H - 2)
    ft = t - i0
    j0 = u.floor()
    fu = u - j0
    i0, j0 = i0.long(), torch.remainder(j0.long(), W)
    j1 = torch.remainder(j0 + 1, W)
    node = torch.cat([i0 * W + j0, i0 * W + j1, (i0 + 1) * W + j0, (i0 + 1) * W + j1])
    wt = torch.cat([w * (1 - ft) * (1 - fu), w * (1 - ft) * fu, w * ft * (1 - fu), w * ft * fu])
    return node, e.repeat(4), wt


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


def source_height(env: Environment, height: int) -> int:
    """Mitsuba's image height for ``env``: at least ``height`` and twice the lat-long height with
    as many pixels as the environment has valid ones (√(P/2)), so that the conservative remap of
    :func:`remap_to_mitsuba` blurs a one-pixel feature by at most about one source pixel."""
    P = int(env.mask().sum())
    return max(int(height), 2 * math.ceil(math.sqrt(P / 2)))


def remap_to_mitsuba(env: Environment, height: int, supersample: int = 4, pull: int = 2, iters: int = 200,
                     tol: float = 1e-9) -> tuple[torch.Tensor, dict]:
    """A power-conserving resample of ``env`` onto Mitsuba's ``envmap`` grid: ``[H, 2H, C]`` float64.

    The engine's radiance is piecewise constant over its pixels e (solid angle Ω_e,
    :meth:`Environment.solid_angles`); Mitsuba's is Σ_m v_m Λ_m(ω) with the bilinear hats Λ_m of
    :func:`mitsuba_envmap_directions` (solid angle Ω̃_m = ∫Λ_m, :func:`mitsuba_pixel_solid_angles`).
    The conservative (first-order) remap (Jones 1999, "First- and second-order conservative
    remapping schemes for grids in spherical coordinates", Mon. Wea. Rev. 127, eq. 2, with
    Mitsuba's hats in place of its target cells) is v_m = Σ_e A_me L_e / Ω̃_m with the overlap
    A_me = ∫ Λ_m 1_e dω, whose margins are known exactly: Σ_e A_me = Ω̃_m (a constant stays
    constant) and Σ_m A_me = Ω_e (the hats sum to one: every source pixel keeps its power). A is
    estimated by two quadratures, averaged: ``supersample``² points per engine pixel (centres of
    the sub-pixels of the ``supersample``-times finer grid of its layout, weighted by their exact
    solid angles; every engine pixel is seen) and ``pull``² points per cell of Mitsuba's grid
    (exact lat-long sub-cell solid angles; every Mitsuba pixel is seen), each splatted on its
    four nodes with the hat weights and weighted by the balance heuristic of the two point
    densities (Veach & Guibas 1995: each quadrature counts where its points are the denser). The estimate's margins are then made exact by alternate
    row and column scaling (Sinkhorn & Knopp 1967, iterative proportional fitting), ending on the columns:
    the image's power per source pixel, Σ_m A_me, is Ω_e to round-off, and its row margins
    (the image of a constant light, i.e. the per-pixel fluctuation) within the reported residual.

    Returns (image ``[H, 2H, C]`` float64, info dict: ``iters``, ``row_residual`` = max over
    Mitsuba pixels of |Σ_e A_me/Ω̃_m − 1|, ``entries``). A Mitsuba pixel that meets no engine
    pixel (only possible where the source has no light: the rim of an angular map) is 0."""
    H, W = int(height), 2 * int(height)
    s, q = int(supersample), int(pull)
    eh, ew = env.shape
    om_e = env.solid_angles().reshape(-1)  # [E]
    E = om_e.numel()
    # push: the engine's sub-pixels (exact sub-solid angles of the s-times finer grid)
    ys = torch.arange(eh * s, dtype=torch.float64)[:, None].expand(eh * s, ew * s)
    xs = torch.arange(ew * s, dtype=torch.float64)[None, :].expand(eh * s, ew * s)
    d1, _ = L.pixel_to_dir(env.layout, eh * s, ew * s, ys + 0.5, xs + 0.5)
    w1 = L.solid_angles(env.layout, eh * s, ew * s).reshape(-1)
    e1 = ((ys.long() // s) * ew + xs.long() // s).reshape(-1)
    keep = (w1 > 0) & (om_e[e1] > 0)
    d1 = (d1.reshape(-1, 3) @ env.rotation.T)[keep]
    w1, e1 = w1[keep], e1[keep]
    bare = (om_e > 0) & (torch.bincount(e1, w1, E) == 0)  # rim pixels of an angular map: their centre stands in
    if bool(bare.any()):
        eb = torch.nonzero(bare).squeeze(1)
        d1 = torch.cat([d1, env.directions().reshape(-1, 3)[eb]])
        w1, e1 = torch.cat([w1, om_e[eb]]), torch.cat([e1, eb])
    hq = math.pi / ((H - 1) * q)
    cell = hq * (2 * math.pi / (W * q))  # a pull sub-cell's solid angle is cell · sin θ (to first order)
    pull_w = cell * torch.sqrt((1 - d1[:, 1] ** 2).clamp_min(0))
    n1, c1, a1 = _hat_entries(d1, w1 * pull_w / (w1 + pull_w), e1, H)
    # pull: sub-cells of Mitsuba's node grid (rows between nodes, columns between column centres)
    t0 = torch.arange((H - 1) * q, dtype=torch.float64) * hq
    wrow = (torch.cos(t0) - torch.cos(t0 + hq)) * (2 * math.pi / (W * q))  # [(H-1)q]
    th = (t0 + hq / 2)[:, None].expand(-1, W * q)
    ph = ((torch.arange(W * q, dtype=torch.float64) + 0.5) / q)[None, :].expand((H - 1) * q, -1) * (2 * math.pi / W)
    st = torch.sin(th)
    d2 = torch.stack([st * torch.sin(ph), torch.cos(th), -st * torch.cos(ph)], -1).reshape(-1, 3)
    w2 = wrow[:, None].expand(-1, W * q).reshape(-1)
    y2, x2 = L.dir_to_pixel(env.layout, eh, ew, d2 @ env.rotation)
    e2 = y2.long() * ew + x2.long()
    keep = om_e[e2] > 0
    w2, e2 = w2[keep], e2[keep]
    push_w = om_e[e2] / (s * s)
    n2, c2, a2 = _hat_entries(d2[keep], w2 * push_w / (w2 + push_w), e2, H)
    key, inv = torch.unique(torch.cat([n1 * E + c1, n2 * E + c2]), return_inverse=True)
    A = torch.zeros(key.numel(), dtype=torch.float64).index_add_(0, inv, torch.cat([a1, a2]))
    node, pix = key // E, key % E
    om_m = mitsuba_pixel_solid_angles(H).repeat_interleave(W)  # [H W]
    seen = torch.bincount(node, minlength=H * W) > 0  # a Mitsuba pixel no engine pixel meets (an angular map's rim) stays 0
    it, res = 0, float("inf")
    for it in range(1, iters + 1):  # Sinkhorn: each pass two bincounts over the entries
        row = torch.bincount(node, A, H * W)
        res = float((row / om_m - 1)[seen].abs().max())
        A *= (om_m / row.clamp_min(1e-300))[node]
        col = torch.bincount(pix, A, E)
        A *= (om_e / col.clamp_min(1e-300))[pix]
        if res < tol:
            break
    row = torch.bincount(node, A, H * W)
    res = float((row / om_m - 1)[seen].abs().max())
    vals = env.image.reshape(-1, env.channels).to(torch.float64)  # [E, C]
    img = torch.zeros(H * W, env.channels, dtype=torch.float64).index_add_(0, node, A[:, None] * vals[pix])
    img /= om_m[:, None]
    return img.reshape(H, W, -1), {"iters": it, "row_residual": res, "entries": int(key.numel())}


def _environment_of(spec: Any) -> Environment | None:
    from ..lighting import builtin_environment, load_environment

    if isinstance(spec, Environment):
        return spec
    if isinstance(spec, str) and spec in list_builtin_environments():
        return builtin_environment(spec)
    if isinstance(spec, (str, os.PathLike)) and Path(spec).exists():
        return load_environment(spec)
    return None


def source_image(spec: Any, height: int) -> np.ndarray | None:
    """The original radiance of an environment (file or built-in) on Mitsuba's grid
    ``[H', 2H', 3]`` float32, H' = :func:`source_height` (≥ ``height``), by the power-conserving
    :func:`remap_to_mitsuba` (every source pixel's power reaches Mitsuba exactly); None when
    ``spec`` is analytic (no image behind it)."""
    env = _environment_of(spec)
    if env is None:
        return None
    img, _ = remap_to_mitsuba(env, source_height(env, height))
    img = img.expand(-1, -1, 3) if img.shape[2] == 1 else img
    return img.clamp_min(0).numpy().astype(np.float32)
