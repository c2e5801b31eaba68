"""Haar wavelets on cube maps: the orthonormal 2-D non-standard Haar transform per face, lights
rasterised onto a cube at resolution R, and the non-linear N-term approximation of a light
(Ng, Ramamoorthi & Hanrahan 2003, "All-Frequency Shadows Using Non-linear Wavelet Lighting
Approximation", §4–5; course notes 2005, "PRT with Haar Wavelets").

Cube layout: the ``faces`` layout of :mod:`prt_torch.lighting.layouts` — six R × R faces in the
order (+x, -x, +y, -y, +z, -z), pixel (row i, column j) of face f with the direction and exact
solid angle that module gives. A cube map is a tensor ``[..., 6, R, R]`` (R a power of two).

Transform (per face, R = 2^J): the non-standard decomposition — at each level one averaging /
differencing step (``(p + q)/√2, (p - q)/√2``) along the rows of the current low-pass block, then
one along its columns, then recurse on the low-low quarter. Every step is an orthogonal 2 × 2
rotation, so the whole transform is orthonormal: ⟨Ha, Hb⟩ = ⟨a, b⟩, which is what lets a
relighting sum Σ_j T_j L_j over texels be computed as Σ_k T̂_k L̂_k over wavelet coefficients.
Coefficient (i, j) of a face (after the transform) with m = max(i, j): m = 0 is the face's
scaling function (support: the whole face); for 2^ℓ ≤ m < 2^(ℓ+1) it is a detail wavelet whose
support is the block of (R / 2^ℓ)² texels at block position (i mod 2^ℓ, j mod 2^ℓ).
"""
from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import torch

from .._checks import check_choice, check_float, check_int, describe
from . import layouts as L

__all__ = ["haar2d", "ihaar2d", "check_res", "cube_geometry", "support_solid_angles", "haar_levels", "cube_light",
           "sub_texel_blocks", "LIGHT_BLOCK_SAMPLES", "select_terms", "ZERO_TERM", "SELECTIONS", "DEFAULT_SELECTION",
           "MAX_HAAR_RES"]

#: largest face resolution accepted (6·128² = 98 304 texels)
MAX_HAAR_RES = 128
#: the non-linear approximations of a light (Ng 2003 §5): which N coefficients to keep
SELECTIONS = ("magnitude", "area", "transport")
#: the default selection, chosen by measurement (reports/benchmarks/wavelet.md: the lowest mean error
#: over the blocker scene's five lights, three budgets and N = 10..2000)
DEFAULT_SELECTION = "transport"
_S = 1.0 / math.sqrt(2.0)


def check_res(res: Any, name: str = "res") -> int:
    """``res`` as an int: a power of two in [1, :data:`MAX_HAAR_RES`] (Haar halves the face at
    every level). Raises ValueError naming ``name``."""
    r = check_int(name, res, 1, MAX_HAAR_RES)
    if r & (r - 1):
        raise ValueError(f"{name}={r} is not a power of two; accepted: 1, 2, 4, ..., {MAX_HAAR_RES} "
                         "(the Haar transform halves the cube face at every level)")
    return r


def _step(n: int, dtype: torch.dtype) -> torch.Tensor:
    """The one-level orthonormal Haar matrix ``[n, n]``: rows 0..n/2-1 the averages
    (e_2i + e_2i+1)/√2, rows n/2.. the differences (e_2i - e_2i+1)/√2."""
    key = (n, dtype)
    if key not in _STEPS:
        h = n // 2
        H = torch.zeros(n, n, dtype=torch.float64)
        i = torch.arange(h)
        H[i, 2 * i] = _S
        H[i, 2 * i + 1] = _S
        H[h + i, 2 * i] = _S
        H[h + i, 2 * i + 1] = -_S
        _STEPS[key] = H.to(dtype)
    return _STEPS[key]


_STEPS: dict = {}


def _both(a: torch.Tensor, M: torch.Tensor) -> torch.Tensor:
    """Mᵀ A M for every trailing ``[n, n]`` block of ``a``, as two flat GEMMs (rows of all blocks
    at once, then columns), not a batch of small ones."""
    n = a.shape[-1]
    lead = a.shape[:-2]
    z = (a.reshape(-1, n) @ M).reshape(*lead, n, n)  # A M: every row of every block
    return (z.transpose(-1, -2).reshape(-1, n) @ M).reshape(*lead, n, n).transpose(-1, -2)  # Mᵀ (A M)


def _check_faces(x: torch.Tensor, what: str) -> int:
    r = x.shape[-1]
    if x.ndim < 2 or x.shape[-2] != r:
        raise ValueError(f"{what}: input of shape {tuple(x.shape)}; accepted: [..., R, R] square faces")
    check_res(r, "face size R")
    return r


def haar2d(x: torch.Tensor) -> torch.Tensor:
    """Orthonormal 2-D non-standard Haar transform of every face: ``x [..., R, R]`` (R a power of
    two; any float dtype, any leading batch shape such as ``[B, 6]``) → the same shape and dtype
    (module docstring; Ng 2003 §4). Level by level on the low-pass block A (n × n, n = R, R/2,
    ..., 2): A ← H_n A H_nᵀ with H_n the one-level Haar matrix (rows then columns), as batched
    GEMMs. Exactly inverted by :func:`ihaar2d`."""
    r = _check_faces(x, "haar2d")
    y = x.clone()
    n = r
    while n > 1:  # one level per pass (log2 R passes), each two GEMMs over every face at once
        y[..., :n, :n] = _both(y[..., :n, :n], _step(n, y.dtype).T)
        n //= 2
    return y


def ihaar2d(y: torch.Tensor) -> torch.Tensor:
    """Inverse of :func:`haar2d` (its transpose: A ← H_nᵀ A H_n from the coarsest level up):
    ``[..., R, R]`` → ``[..., R, R]``, same dtype."""
    r = _check_faces(y, "ihaar2d")
    x = y.clone()
    n = 2
    while n <= r:
        x[..., :n, :n] = _both(x[..., :n, :n], _step(n, x.dtype))
        n *= 2
    return x


def cube_geometry(res: int, supersample: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Texel directions ``[6, r, r, 3]`` and exact solid angles ``[6, r, r]`` (float64) of the
    ``faces`` cube layout at face size r = res · supersample (world frame = file frame)."""
    res = check_res(res)
    s = check_int("supersample", supersample, 1, 16)
    r = res * s
    d = L.pixel_directions("faces", r, 6 * r)  # [r, 6r, 3]
    om = L.solid_angles("faces", r, 6 * r)  # [r, 6r]
    return d.reshape(r, 6, r, 3).permute(1, 0, 2, 3).contiguous(), om.reshape(r, 6, r).permute(1, 0, 2).contiguous()


def haar_levels(res: int) -> torch.Tensor:
    """The level of every Haar coefficient of the cube at face size ``res``, flat ``[6R²]`` int64
    (index f·R² + i·R + j, the layout of :func:`haar2d`): 0 for the scaling coefficient of each face,
    ℓ = floor(log2(max(i, j))) + 1 for the details (1 the coarsest, log2 R the finest): the
    coefficient covers a block of (R / 2^(ℓ-1))² texels. log2(R) + 1 levels."""
    res = check_res(res)
    m = torch.arange(res)
    m = torch.maximum(m[:, None], m[None, :]).reshape(-1)
    lev = torch.zeros_like(m)
    nz = m > 0
    lev[nz] = torch.floor(torch.log2(m[nz].to(torch.float64))).to(torch.int64) + 1
    return lev.repeat(6)


def support_solid_angles(res: int) -> torch.Tensor:
    """Solid angle of the support of every Haar coefficient of a cube at face size ``res``,
    ``[6, R, R]`` float64 (module docstring: coefficient (i, j), m = max(i, j), covers a block
    of (R / 2^ℓ)² texels, the whole face for m = 0): the weights of the area-weighted selection."""
    res = check_res(res)
    _, om = cube_geometry(res)
    out = torch.empty(6, res, res, dtype=torch.float64)
    out[:, 0, 0] = om.sum((1, 2))
    h = 1
    while h < res:  # levels: blocks of (R/h)² texels, h = 1, 2, 4, ...
        b = res // h
        blocks = om.reshape(6, h, b, h, b).sum((2, 4))  # [6, h, h]
        for bi, bj in ((0, h), (h, 0), (h, h)):  # the three detail quadrants of this level
            out[:, bi:bi + h, bj:bj + h] = blocks
        h *= 2
    return out


#: sub-texel directions per block of :func:`cube_light`'s rasterisation (:func:`sub_texel_blocks`): a block's
#: directions, solid angles, the light evaluated there and its temporaries, a few hundred B each: a few MiB
LIGHT_BLOCK_SAMPLES = 1 << 14


def sub_texel_blocks(res: int, s: int):
    """The ``s`` × ``s`` sub-texel grid of the ``faces`` cube at face size ``res`` in blocks of whole texel rows of one
    face, about :data:`LIGHT_BLOCK_SAMPLES` directions each: yields ``(f, i0, i1, dirs [(i1-i0)·s, r, 3],
    omega [(i1-i0)·s, r])`` float64 (r = res · s) for face f and texel rows i0…i1-1 — the values of
    :func:`cube_geometry` (res, s) there, bit for bit, without the whole grid at once (at R = 64, s = 4 the grid and
    its temporaries took ~78 MiB, ~200 B per direction)."""
    r = res * s
    face_om = L.cube_face_solid_angles(r)  # [r, r], the same on every face
    rows = max(1, LIGHT_BLOCK_SAMPLES // (r * s))  # texel rows per block
    x = torch.arange(r, dtype=torch.float64)
    for f in range(6):  # a loop over faces and row blocks, each block one batched evaluation
        xx = (x + f * r)[None, :] + 0.5
        for i0 in range(0, res, rows):
            i1 = min(res, i0 + rows)
            yy = torch.arange(i0 * s, i1 * s, dtype=torch.float64)[:, None] + 0.5
            d = L.pixel_to_dir("faces", r, 6 * r, yy.expand(-1, r), xx.expand(yy.shape[0], -1))[0]
            yield f, i0, i1, d, face_om[i0 * s:i1 * s]


def _averaged(fn, res: int, s: int) -> torch.Tensor:
    """``[6, R, R, C]`` float64: ``fn`` (directions ``[n, 3]`` float64 → radiance ``[n, C]``) averaged by solid angle
    over each texel's ``s``² sub-texels, block by block (:func:`sub_texel_blocks`)."""
    om_R = _texel_omega(res)
    img = None
    for f, i0, i1, d, om in sub_texel_blocks(res, s):
        v = torch.as_tensor(fn(d.reshape(-1, 3))).to(torch.float64).reshape(d.shape[0], d.shape[1], -1)
        part = (v * om[..., None]).reshape(i1 - i0, s, res, s, -1).sum((1, 3)) / om_R[f, i0:i1, :, None]
        if img is None:
            img = torch.empty(6, res, res, part.shape[-1], dtype=torch.float64)
        img[f, i0:i1] = part
    return img


def _energy_cap(img: torch.Tensor, d: torch.Tensor, alpha: float, radiance: torch.Tensor, res: int, s: int) -> None:
    """Add a uniform cap (direction ``d``, half-angle ``alpha``, radiance ``[C]``) to ``img [6, R, R, C]``
    energy-conservingly: texel coverage from ``s``² sub-texel directions (block by block,
    :func:`sub_texel_blocks`), rescaled so Σ L Ω is the cap's exact power; a cap smaller than every sample
    puts its power in the texel holding ``d`` (the rule of the built-in environments)."""
    cosa = math.cos(alpha)
    cov_om = torch.empty(6, res, res, dtype=torch.float64)  # [6, R, R] covered solid angle
    for f, i0, i1, dirs, omega in sub_texel_blocks(res, s):
        inside = ((dirs @ d) >= cosa).to(torch.float64)  # at the block's sub-texel grid
        cov_om[f, i0:i1] = (inside * omega).reshape(i1 - i0, s, res, s).sum((1, 3))
    power = 2 * math.pi * (1 - cosa)
    raster = float(cov_om.sum())
    if raster > 0:
        img += (cov_om * (power / raster))[..., None] * radiance / _texel_omega(res)[..., None]
    else:
        f, i, j = _texel_of(d, res)
        img[f, i, j] += radiance * (power / float(_texel_omega(res)[f, i, j]))


def _texel_omega(res: int) -> torch.Tensor:
    """``[6, R, R]`` float64: :func:`cube_geometry` (res)'s solid angles, without its directions."""
    return L.cube_face_solid_angles(res).expand(6, res, res)


def _texel_of(d: torch.Tensor, res: int) -> tuple[int, int, int]:
    y, x = L.dir_to_pixel("faces", res, 6 * res, d.to(torch.float64))
    col = int(x)
    return col // res, int(y), col % res


def cube_light(spec: Any, res: int, supersample: int = 4, channels: int = 3) -> tuple[torch.Tensor, dict]:
    """A light as radiance per texel of the ``faces`` cube at face size ``res``: ``[C, 6, R, R]``
    float64, and a record ``{'source', 'upsampled', ...}``.

    Accepted ``spec`` (the engine's lights, :func:`prt_torch.lighting.load_light`'s vocabulary,
    *not* band-limited): an :class:`~prt_torch.lighting.Environment`; a built-in environment
    name (rasterised at ``res`` by its own energy-conserving rule); a file path or '{face}'
    pattern; an analytic spec (``cap`` and ``directional`` rasterised energy-conservingly: a cap
    by its sub-texel coverage rescaled to its exact power, a directional light as its power π·I in
    the texel holding its direction; ``hemisphere``, ``sky_gradient``, ``constant`` by their
    radiance functions averaged over ``supersample``² sub-texel directions); a dict of the same;
    or an SH light ``[C, n²]`` tensor or ``.json`` file (``prt light --json``'s layout; evaluated at the
    sub-texel directions). An image
    resampled to the cube: each source pixel's power L·Ω lands in the cube texel holding its
    centre (energy-conserving) when every texel holds at least one pixel centre; otherwise the
    image is coarser than the cube somewhere, the cube is point-sampled at sub-texel directions
    and ``record['upsampled']`` / ``record['warning']`` say so (the caller warns).
    """
    from .environment import Environment, load_environment
    from .spec import analytic_params, check_light_path, parse_light_spec
    from .builtin import builtin_environment, list_builtin_environments

    res = check_res(res)
    s = check_int("supersample", supersample, 1, 16)
    om_R = _texel_omega(res)
    rec: dict[str, Any] = {"res": res, "upsampled": False}

    def averaged(fn) -> torch.Tensor:  # sub-texel radiance averaged by solid angle -> [6, R, R, C], block by block
        return _averaged(fn, res, s)

    if isinstance(spec, torch.Tensor):
        from ..sh import band_of_coeffs, eval_sh

        if spec.ndim != 2:
            raise ValueError(f"an SH light has shape {tuple(spec.shape)}; accepted: [C, n²]")
        bands = band_of_coeffs(spec.shape[1], "light coefficients")
        img = averaged(lambda d: eval_sh(d, bands, check=False) @ spec.to(torch.float64).T)
        rec["source"] = f"SH light, {bands} bands"
        return img.permute(3, 0, 1, 2).contiguous(), rec
    if isinstance(spec, str) and spec in list_builtin_environments():
        env = builtin_environment(spec, layout="faces", size=res)
        img = env.image.to(torch.float64).reshape(res, 6, res, -1).permute(1, 0, 2, 3)
        rec["source"] = f"built-in {spec!r} rasterised at R={res}"
        return img.permute(3, 0, 1, 2).contiguous(), rec
    d = spec if isinstance(spec, dict) else (parse_light_spec(spec) if isinstance(spec, str) else None)
    if d is not None:
        kind, d = analytic_params(d)
        rec["source"] = f"analytic {kind} rasterised at R={res}"
        return _analytic_cube(kind, d, res, s).permute(3, 0, 1, 2).contiguous(), rec
    if isinstance(spec, (str, os.PathLike)) and str(spec).lower().endswith(".json") and Path(spec).is_file():
        from .spec import load_light_json  # an SH light file (prt light --json, prt invert): evaluated, as a tensor

        img, rec = cube_light(load_light_json(spec), res, supersample, channels)
        rec["source"] = f"SH light file {str(spec)!r} ({rec['source']})"
        return img, rec
    if isinstance(spec, Environment):
        env = spec
    elif isinstance(spec, (str, list, tuple)) or hasattr(spec, "__fspath__"):
        check_light_path(spec)
        env = load_environment(spec)
    else:
        raise TypeError(f"light spec {describe(spec)}; accepted: a built-in name, an analytic spec, a file, an "
                        "Environment or an SH light [C, n²]")
    rec["source"] = f"image {env.name!r} ({env.layout} {env.shape[1]}x{env.shape[0]})"
    dd, om, idx = env.directions().reshape(-1, 3), env.solid_angles().reshape(-1), env.mask().reshape(-1)
    y, x = L.dir_to_pixel("faces", res, 6 * res, dd[idx])
    col = x.long()
    lin = (col // res) * res * res + y.long() * res + col % res
    empty = int((torch.bincount(lin, minlength=6 * res * res) == 0).sum())
    if empty:  # some texel holds no pixel centre: the image is coarser than the cube there (point samples)
        rec["upsampled"] = True
        rec["warning"] = (f"light {env.name!r} ({env.shape[1]}x{env.shape[0]} {env.layout}) is coarser than the cube at "
                          f"R={res}: {empty} of {6 * res * res} texels hold no pixel; upsampled (point samples), not filtered")
        img = averaged(lambda d: env.sample(d))
        return img.permute(3, 0, 1, 2).contiguous(), rec
    vals = env.image.reshape(-1, env.channels).to(torch.float64)[idx] * om[idx, None]  # power per pixel
    acc = torch.zeros(6 * res * res, env.channels, dtype=torch.float64).index_add_(0, lin, vals)
    img = acc.reshape(6, res, res, -1) / om_R[..., None]
    return img.permute(3, 0, 1, 2).contiguous(), rec


def _analytic_cube(kind: str, d: dict, res: int, s: int) -> torch.Tensor:
    """``[6, R, R, C]`` radiance of an analytic light (see :func:`cube_light`)."""
    from . import analytic as A

    om_R = _texel_omega(res)
    try:
        if kind == "cap":
            if ("intensity" in d) == ("radiance" in d):
                raise ValueError("cap: give exactly one of intensity= or radiance=")
            alpha = check_float("half_angle", d.pop("half_angle"), 0.0, math.pi, lo_open=True)  # as analytic.cap_zonal
            direction = A.unit_direction(d.pop("direction"))
            if "intensity" in d:
                Lc = A.color(d.pop("intensity")) / math.sin(min(alpha, math.pi / 2)) ** 2
            else:
                Lc = A.color(d.pop("radiance"), "radiance")
            if d:
                raise TypeError(f"unexpected keys {sorted(d)}")
            img = torch.zeros(6, res, res, Lc.numel(), dtype=torch.float64)
            _energy_cap(img, direction, alpha, Lc, res, s)
            return img
        if kind == "directional":
            direction = A.unit_direction(d.pop("direction"))
            I = A.color(d.pop("intensity", 1.0))
            if d:
                raise TypeError(f"unexpected keys {sorted(d)}")
            img = torch.zeros(6, res, res, I.numel(), dtype=torch.float64)
            f, i, j = _texel_of(direction, res)
            img[f, i, j] = math.pi * I / float(om_R[f, i, j])  # power π I in one texel
            return img
        if kind == "constant":
            c = A.color(d.pop("value", 1.0), "value")
            if d:
                raise TypeError(f"unexpected keys {sorted(d)}")
            return c.expand(6, res, res, c.numel()).clone()
        if kind in ("hemisphere", "sky_gradient"):
            if kind == "hemisphere":
                up_v, lo_v = d.pop("upper", 1.0), d.pop("lower", 0.0)
                z = h = A.color(up_v, "upper")
                g = A.color(lo_v, "lower")
            else:
                z = A.color(d.pop("zenith", (0.3, 0.5, 1.0)), "zenith")
                h = A.color(d.pop("horizon", (0.9, 0.9, 1.0)), "horizon")
                g = A.color(d.pop("ground", (0.2, 0.18, 0.15)), "ground")
            up = A.unit_direction(d.pop("up", (0.0, 0.0, 1.0)), "up")
            if d:
                raise TypeError(f"unexpected keys {sorted(d)}")
            z, h, g = torch.broadcast_tensors(z, h, g)

            def radiance(dirs: torch.Tensor) -> torch.Tensor:  # [n, 3] -> [n, C]
                t = (dirs @ up)[..., None]
                return torch.where(t >= 0, h + (z - h) * t.clamp_min(0), g)
            return _averaged(radiance, res, s)
    except TypeError as e:
        raise ValueError(f"light spec for {kind!r}: {e}") from None
    raise ValueError(f"light type {kind!r}; accepted: cap, directional, constant, hemisphere, sky_gradient")


#: relative size below which a light's Haar coefficient counts as zero (:func:`select_terms`): 1e-12 of the
#: largest |L̂_k| — about 5000 float64 roundings above the transform's round-off (~1e-16 relative per level) and
#: far below any real light's range (an HDR sun over a sky spans ~1e6); float32 lights carry no information there.
ZERO_TERM = 1e-12


def select_terms(coeffs: torch.Tensor, terms: int, selection: str = DEFAULT_SELECTION,
                 weights: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The non-linear N-term approximation of a light (Ng 2003 §5): the ``terms`` wavelet
    coefficients of largest importance.

    Args:
        coeffs: Haar coefficients of the light ``[C, P]`` (P = 6R², flattened ``[6, R, R]``).
        terms: N ≥ 1 (clipped to P).
        selection: importance of coefficient k, with |L̂_k| = Σ_c |L̂_ck|:
            'magnitude' — |L̂_k|; 'area' — |L̂_k| · (solid angle of the support of k)
            (:func:`support_solid_angles`); 'transport' — |L̂_k| · ``weights[k]``, the mean
            |T̂_vk| of the transfer over the vertices (Ng's transport-weighted selection).
        weights: ``[P]`` per-coefficient weights ('transport'; 'area' computes its own).
    Returns:
        (indices ``[N']`` int64 into P, sorted by decreasing importance; values ``[C, N']``, dtype of
        ``coeffs``), N' = min(N, P, the light's nonzero terms): a coefficient whose |L̂_k| (summed over the
        channels, as the selections rank it) is at most :data:`ZERO_TERM` of the largest |L̂_k| is the
        transform's round-off (a light that is piecewise constant on blocks, such as caps or area lights on
        black, has exact zeros there that the float64 Haar sums leave at ~1e-17), carries no light, and is
        never selected, whatever its weight — ranking such terms would make which transfer columns an N
        above the light's real terms reads depend on the CPU's rounding. A coloured light's term is kept
        when any channel carries it (a term zero in red and green but not in blue is kept, with its zeros);
        a channel's terms below ``ZERO_TERM`` of the whole light's largest |L̂_k| count as zero. Each dropped
        term changes the relit result by at most ZERO_TERM · max|L̂_k| times its transfer coefficient.
        An all-zero light keeps its largest term (one, of value 0).
    """
    if coeffs.ndim != 2:
        raise ValueError(f"coeffs has shape {tuple(coeffs.shape)}; accepted: [C, P] Haar coefficients")
    P = coeffs.shape[1]
    terms = check_int("terms", terms, 1)
    check_choice("selection", selection, SELECTIONS)
    mag = coeffs.abs().sum(0).to(torch.float64)
    imp = mag.clone()
    if selection == "area":
        r = math.isqrt(P // 6)
        if 6 * r * r != P:
            raise ValueError(f"coeffs has {P} columns; accepted: 6·R² for the area-weighted selection")
        imp = imp * support_solid_angles(r).reshape(-1)
    elif selection == "transport":
        if weights is None or weights.shape != (P,):
            raise ValueError(f"selection='transport' needs weights [P] = [{P}] (mean |transfer coefficient| per wavelet); "
                             f"got {None if weights is None else tuple(weights.shape)}")
        imp = imp * weights.to(torch.float64)
    real = mag > ZERO_TERM * (float(mag.max()) if P else 0.0)  # [P] bool: the light's nonzero terms (mag: |L̂_k| summed over C)
    nonzero = int(real.sum())
    if nonzero:  # round-off terms rank below every real one, whatever their weight (a weight can be 0)
        imp = torch.where(real, imp, torch.full_like(imp, -1.0))
    k = min(terms, P, max(nonzero, 1))
    idx = torch.topk(imp, k, sorted=True).indices
    return idx, coeffs[:, idx]
