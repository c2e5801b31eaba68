"""Gaussian-prefiltered environment maps (Green 2005 §2.3 and §3.2; Ashikhmin & Ghosh 2002).

Green renders each spherical Gaussian of a transport function against the light by one lookup
into an environment map prefiltered with Gaussians, one mip level per width:

    L_o = ∫ Σ_k w_k G(ω, μ_k, σ_k) L(ω) dω = Σ_k w_k E_{σ_k}(μ_k),      (Green eq. 2.7)
    E_σ(μ) = ∫ G(ω, μ, σ) L(ω) dω.

The Gaussian here is the normalised isotropic spherical Gaussian (unit integral over S²)

    G(ω, μ, σ) = c(λ) exp(λ (μ·ω − 1)),  λ = 1/σ²,  c(λ) = λ / (2π (1 − e^{−2λ})),

which for small σ equals Green's eq. 3.2, 1/(2πσ²) exp(−d²/2σ²), with d the chord length
‖ω − μ‖ (≈ the geodesic angle) in place of the cube-face unfolding M_μ of Green's appendix A;
the chord is smooth across cube faces and corners, so no lobe needs special treatment there.

``prefilter_environment`` computes the levels E_{σ_l} on a cube map (OpenGL face order and
texel convention of :mod:`prt_torch.transfer.transport`) by the brute-force quadrature
Σ_j G(ω_i, ω_j, σ_l) L(ω_j) Δω_j with rows normalised to sum 1 (a constant light stays
constant at every width), for σ_l on a geometric ladder; ``PrefilteredEnvironment.lookup``
interpolates bilinearly inside a face and linearly in log σ between the two bracketing levels.
"""
from __future__ import annotations

import math
from typing import Any

import torch

from .._checks import check_int, describe, tensor_state

__all__ = ["sg_normaliser", "spherical_gaussian", "cube_map_directions", "cube_map_lookup_coords",
           "PrefilteredEnvironment", "prefilter_environment", "SIGMA_MIN", "SIGMA_MAX"]

#: default width ladder of the prefiltered levels (radians, σ of the Gaussian)
SIGMA_MIN, SIGMA_MAX = 0.02, 4.0


def sg_normaliser(lam: torch.Tensor) -> torch.Tensor:
    """c(λ) = λ / (2π (1 − e^{−2λ})) so that ∫ c(λ) exp(λ(μ·ω − 1)) dω = 1; → 1/(4π) as λ → 0.
    ``lam [...]`` float → ``[...]`` same dtype."""
    lam = torch.as_tensor(lam)
    small = lam < 1e-6
    safe = torch.where(small, torch.ones_like(lam), lam)
    c = safe / (2 * math.pi * (-torch.expm1(-2 * safe)))
    return torch.where(small, torch.full_like(lam, 1 / (4 * math.pi)) * (1 + lam), c)


def spherical_gaussian(dirs: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Normalised spherical Gaussian G(ω, μ, σ) (module docstring; Green eq. 3.2 with the chord
    distance). ``dirs [..., 3]``, ``mu [..., 3]`` unit, ``sigma [...]`` > 0, broadcast → ``[...]``."""
    lam = sigma.reciprocal().square()
    return sg_normaliser(lam) * torch.exp(lam * ((dirs * mu).sum(-1) - 1))


def cube_map_directions(res: int, dtype: torch.dtype = torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """Texel-centre unit directions ``[6, r, r, 3]`` and exact solid angles ``[6, r, r]`` of a
    cube map (the transport tables' convention)."""
    res = check_int("res", res, 1, 1024)
    c = (torch.arange(res, dtype=torch.float64) + 0.5) * (2.0 / res) - 1.0
    tc, sc = torch.meshgrid(c, c, indexing="ij")  # rows t, columns s
    one = torch.ones_like(sc)
    faces = [(one, -tc, -sc), (-one, -tc, sc), (sc, one, tc), (sc, -one, -tc), (sc, -tc, one), (-sc, -tc, -one)]
    d = torch.stack([torch.stack(f, -1) for f in faces])
    d = d / d.norm(dim=-1, keepdim=True)
    e = torch.linspace(-1.0, 1.0, res + 1, dtype=torch.float64)
    x0, x1, y0, y1 = e[:-1][None, :], e[1:][None, :], e[:-1][:, None], e[1:][:, None]

    def area(x, y):
        return torch.atan2(x * y, torch.sqrt(x * x + y * y + 1.0))

    sa = area(x1, y1) - area(x0, y1) - area(x1, y0) + area(x0, y0)  # [r, r], exact
    sa = sa[None].expand(6, res, res).clone()
    return d.to(dtype), sa.to(dtype)


def cube_map_lookup_coords(dirs: torch.Tensor, res: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Face index ``[...]`` int64 and continuous texel coordinates (column s, row t) ``[...]``
    (texel centres at integers) of directions ``[..., 3]`` on an r×r cube map, OpenGL faces:
    +x: (1, −tc, −sc), −x: (−1, −tc, sc), +y: (sc, 1, tc), −y: (sc, −1, −tc), +z: (sc, −tc, 1),
    −z: (−sc, −tc, −1)."""
    x, y, z = dirs.unbind(-1)
    ax, ay, az = x.abs(), y.abs(), z.abs()
    is_x = (ax >= ay) & (ax >= az)
    is_y = ~is_x & (ay >= az)
    m = torch.where(is_x, ax, torch.where(is_y, ay, az)).clamp_min(1e-30)
    face = torch.where(is_x, (x < 0).long(), torch.where(is_y, 2 + (y < 0).long(), 4 + (z < 0).long()))
    sx = torch.where(x >= 0, -z, z)          # ±x faces: sc = ∓z/|x|
    sy = x                                   # ±y faces: sc = x/|y|
    sz = torch.where(z >= 0, x, -x)          # ±z faces: sc = ±x/|z|
    tx = -y
    ty = torch.where(y >= 0, z, -z)
    tz = -y
    sc = torch.where(is_x, sx, torch.where(is_y, sy, sz)) / m
    tc = torch.where(is_x, tx, torch.where(is_y, ty, tz)) / m
    s = (sc + 1) * (res / 2) - 0.5
    t = (tc + 1) * (res / 2) - 0.5
    return face, s, t


class PrefilteredEnvironment:
    """A light as Gaussian-prefiltered cube-map levels (Green 2005 §2.3; light kind
    ``'prefiltered'`` of the ``gaussian`` codec).

    Attributes:
        levels: ``[n_levels, C, 6, r, r]`` float32, level l = E_{σ_l} at the texel centres.
        sigmas: ``[n_levels]`` float64, increasing geometric ladder of widths (radians).
        cube: ``[C, 6, r, r]`` float32 radiance at the texel centres (unfiltered).
        sh: ``[C, n²]`` float64 SH coefficients of the light (for an SH diffuse part, Green
            §3.1), or None.
    """

    def __init__(self, levels: torch.Tensor, sigmas: torch.Tensor, cube: torch.Tensor, sh: torch.Tensor | None = None):
        self.levels = levels
        self.sigmas = sigmas
        self.cube = cube
        self.sh = sh
        if not isinstance(levels, torch.Tensor) or levels.dim() != 5:
            raise ValueError(f"PrefilteredEnvironment levels: expected a tensor [n_levels, C, 6, r, r], got "
                             f"{tuple(levels.shape) if isinstance(levels, torch.Tensor) else type(levels).__name__}")
        self.res = int(levels.shape[-1])
        self.channels = int(levels.shape[1])
        if not isinstance(sigmas, torch.Tensor):
            raise ValueError(f"PrefilteredEnvironment sigmas: expected a tensor [n_levels], got {type(sigmas).__name__}")
        self.log_sigmas = sigmas.log().to(torch.float32)  # [n_levels] float32: the ladder lookups search
        self.check()

    def check(self) -> "PrefilteredEnvironment":
        """Raise ``ValueError`` naming the field and its value unless the levels, the width
        ladder, the cube and the SH coefficients agree (the kernels read ``n_levels`` from the
        ladder and the texels from ``table()``: a mismatch would read past the table). Run at
        construction and by every relight, since the attributes can be reassigned (a light
        checked before and unchanged since — each field's identity, address, shape and version,
        ``_checks.tensor_state`` — passes at once: 3.6 µs)."""
        fields = (self.levels, self.sigmas, self.log_sigmas, self.cube, self.sh)
        key = (self.res, self.channels) + tuple(tensor_state(t) if isinstance(t, torch.Tensor) else id(t) for t in fields)
        hit = getattr(self, "_checked", None)
        if hit is not None and hit[0] == key:
            return self
        lv, sig = self.levels, self.sigmas
        if not isinstance(lv, torch.Tensor) or lv.dim() != 5 or lv.shape[2] != 6 or lv.shape[3] != lv.shape[4] \
                or min(lv.shape) < 1 or not lv.is_floating_point():
            raise ValueError(f"PrefilteredEnvironment levels: expected a float tensor [n_levels, C, 6, r, r] with r ≥ 1, got "
                             f"{(lv.dtype, tuple(lv.shape)) if isinstance(lv, torch.Tensor) else type(lv).__name__}")
        L, C, _, r, _ = lv.shape
        off = [(n, t.device) for n, t in (("levels", lv), ("sigmas", sig), ("cube", self.cube), ("sh", self.sh))
               if isinstance(t, torch.Tensor) and t.device.type != "cpu"]
        if off:
            raise ValueError(f"PrefilteredEnvironment {off[0][0]} is on {off[0][1]}; accepted: CPU tensors (.cpu())")
        if (self.res, self.channels) != (r, C):
            raise ValueError(f"PrefilteredEnvironment res={self.res}, channels={self.channels} do not match levels "
                             f"{tuple(lv.shape)}; accepted: res={r}, channels={C} (build a new PrefilteredEnvironment)")
        if not isinstance(sig, torch.Tensor) or sig.shape != (L,):
            raise ValueError(f"PrefilteredEnvironment sigmas: expected one width per level, shape ({L},), got "
                             f"{tuple(sig.shape) if isinstance(sig, torch.Tensor) else type(sig).__name__}")
        if not (bool(torch.isfinite(sig).all()) and bool((sig > 0).all()) and (L == 1 or bool((sig[1:] > sig[:-1]).all()))):
            raise ValueError(f"PrefilteredEnvironment sigmas: expected finite positive widths increasing with the level, "
                             f"got {sig.tolist()}")
        ls = self.log_sigmas
        if not isinstance(ls, torch.Tensor) or ls.shape != (L,) or ls.dtype != torch.float32 \
                or not torch.equal(ls, sig.log().to(torch.float32)):
            raise ValueError("PrefilteredEnvironment log_sigmas no longer matches sigmas (sigmas was reassigned); accepted: "
                             "log_sigmas = sigmas.log().float(), or a new PrefilteredEnvironment")
        if not isinstance(self.cube, torch.Tensor) or self.cube.shape != (C, 6, r, r):
            raise ValueError(f"PrefilteredEnvironment cube: expected [C, 6, r, r] = {(C, 6, r, r)}, got "
                             f"{tuple(self.cube.shape) if isinstance(self.cube, torch.Tensor) else type(self.cube).__name__}")
        sh = self.sh
        if sh is not None and (not isinstance(sh, torch.Tensor) or sh.dim() != 2 or sh.shape[0] != C
                               or int(round(sh.shape[1] ** 0.5)) ** 2 != sh.shape[1]):
            raise ValueError(f"PrefilteredEnvironment sh: expected None or [C, n²] with C={C}, got "
                             f"{tuple(sh.shape) if isinstance(sh, torch.Tensor) else type(sh).__name__}")
        self._checked = (key, fields)  # the checked objects held: their ids cannot be reused while the key lives
        return self

    def __getstate__(self) -> dict:
        """Pickled (for a worker, a cache file) without the derived tables and the check's memo:
        rebuilt on first use (the quad table alone is 4× the levels)."""
        return {k: v for k, v in self.__dict__.items() if k not in ("_checked", "_flat", "_quads")}

    @property
    def shape(self) -> tuple[int, int]:
        """``(rows, C)``: the table as a light matrix (all levels' texels × channels), so code
        written for SH lights ``[n_in, C]`` reads the channel count from ``shape[-1]``."""
        return (int(self.levels[:, 0].numel()), self.channels)

    def __repr__(self) -> str:
        return (f"PrefilteredEnvironment(levels={self.levels.shape[0]}, C={self.channels}, res={self.res}, "
                f"sigma=[{float(self.sigmas[0]):.3g}, {float(self.sigmas[-1]):.3g}])")

    def table(self) -> torch.Tensor:
        """The pyramid as rows ``[L·6·r·r, C]`` float32 (built once): texel (level l, face f,
        row t, column s) is row ``((l·6 + f)·r + t)·r + s``."""
        key = tensor_state(self.levels)  # rebuilt after an edit of the levels, in place or through .data
        hit = getattr(self, "_flat", None)
        if hit is None or hit[0] != key:
            L, r, C = self.levels.shape[0], self.levels.shape[-1], self.levels.shape[1]
            self._flat = hit = (key, self.levels, self.levels.permute(0, 2, 3, 4, 1).reshape(L * 6 * r * r, C).float().contiguous())
        return hit[2]

    def quads(self) -> torch.Tensor:
        """The pyramid as 2×2 texel footprints ``[L·6·r·r, 16]`` float32 (built once per levels,
        as :meth:`table`): row i of texel (l, f, t, s) = the channels of texels (t, s), (t, s+1),
        (t+1, s), (t+1, s+1) of that face and level (clamped at the face's last row and column),
        then zeros to 16 floats — for RGB, one 64-byte line per bilinear lookup, read by the
        Gaussian codec's every-view kernels (``relight_kernels.sg_lookup_sum``'s ``quads``)."""
        key = tensor_state(self.levels)
        hit = getattr(self, "_quads", None)
        if hit is None or hit[0] != key:
            C, r = self.levels.shape[1], self.levels.shape[-1]
            if 4 * C > 16:
                raise ValueError(f"PrefilteredEnvironment.quads: {C} channels; accepted: at most 4")
            T = self.levels.permute(0, 2, 3, 4, 1).float()  # [L, 6, r(t), r(s), C]
            nxt = torch.arange(1, r + 1).clamp(max=r - 1)
            down = T[:, :, nxt]  # row t + 1
            Q = torch.zeros(*T.shape[:4], 16)
            for k, part in enumerate((T, T[:, :, :, nxt], down, down[:, :, :, nxt])):
                Q[..., k * C:(k + 1) * C] = part
            self._quads = hit = (key, self.levels, Q.reshape(-1, 16))
        return hit[2]

    def lookup(self, mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """E_σ(μ): ``mu [..., 3]`` unit directions, ``sigma [...]`` widths → ``[..., C]`` float32.
        Bilinear in the face (clamped at face edges), linear in log σ between the two levels
        bracketing σ (clamped to the ladder). Green eq. 2.7, Fig. 3-2's texCUBElod. When the
        levels require grad (grad mode on): ``[..., C]`` in the levels' dtype, differentiable with
        respect to them (the torch formulation of the kernels' trilinear lookup)."""
        shape = sigma.shape
        mu = mu.reshape(-1, 3).to(torch.float32)
        ls = sigma.reshape(-1).to(torch.float32).clamp_min(1e-12).log()
        r = self.res
        face, s, t = cube_map_lookup_coords(mu, r)
        s = s.clamp(0, r - 1)
        t = t.clamp(0, r - 1)
        # a non-finite direction's NaN coordinates: texel 0 for the indices (a NaN converts to an
        # index far outside the table), NaN weights for the value (NaN, as the kernels give)
        s0 = s.nan_to_num(0.0).floor().clamp(max=r - 2 if r > 1 else 0).long()
        t0 = t.nan_to_num(0.0).floor().clamp(max=r - 2 if r > 1 else 0).long()
        fs = (s - s0).clamp(0, 1)
        ft = (t - t0).clamp(0, 1)
        s1 = (s0 + 1).clamp(max=r - 1)
        t1 = (t0 + 1).clamp(max=r - 1)
        L = self.levels.shape[0]
        ladder = self.log_sigmas
        hi = torch.searchsorted(ladder, ls.contiguous()).clamp(1, L - 1) if L > 1 else torch.zeros_like(face)
        lo = (hi - 1).clamp_min(0)
        if L > 1:
            a = ((ls - ladder[lo]) / (ladder[hi] - ladder[lo])).clamp(0, 1)
        else:
            a = torch.zeros_like(ls)
        # the 8 texels (2 levels × 2×2 in the face) and their trilinear weights, summed by one
        # fused gather-weighted-sum over the flattened pyramid
        base = (face * r + t0) * r + s0  # [M] texel (t0, s0) of the face, level 0
        ds, dt = s1 - s0, (t1 - t0) * r  # 0 where the neighbour is the texel itself (r = 1)
        tex4 = base[:, None] + torch.stack([torch.zeros_like(ds), ds, dt, dt + ds], 1)  # (t0,s0), (t0,s1), (t1,s0), (t1,s1)
        w4 = torch.stack([(1 - ft) * (1 - fs), (1 - ft) * fs, ft * (1 - fs), ft * fs], 1)  # [M, 4]
        lvl = 6 * r * r
        idx = torch.cat([tex4 + (lo * lvl)[:, None], tex4 + (hi * lvl)[:, None]], 1)  # [M, 8]
        wts = torch.cat([w4 * (1 - a)[:, None], w4 * a[:, None]], 1)
        if torch.is_grad_enabled() and self.levels.requires_grad:
            # under autograd (docs/inverse.md "Differentiable relighting"): the same 8-texel trilinear sum as a
            # gather from the levels in their own dtype (float64 for gradcheck), differentiable w.r.t. the levels
            # (linear) and ``sigma``/``mu``'s weights; the texel addressing above is the kernels' (float32)
            L_, C = self.levels.shape[0], self.channels
            tab = self.levels.permute(0, 2, 3, 4, 1).reshape(L_ * lvl, C)
            out = (tab[idx] * wts.to(tab.dtype)[..., None]).sum(1)
            return out.reshape(*shape, C)
        out = torch.nn.functional.embedding_bag(idx, self.table(), per_sample_weights=wts.contiguous(), mode="sum")
        return out.reshape(*shape, self.channels)

    def brute_force(self, mu: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
        """E_σ(μ) by direct quadrature over the unfiltered cube texels (for tests): ``mu [M, 3]``,
        ``sigma [M]`` → ``[M, C]`` float64."""
        d, sa = cube_map_directions(self.res)
        G = spherical_gaussian(d.reshape(1, -1, 3), mu.double()[:, None], sigma.double()[:, None]) * sa.reshape(1, -1)
        G = G / G.sum(1, keepdim=True)
        return G @ self.cube.double().reshape(self.channels, -1).T


def _light_on_cube(light: Any, res: int, supersample: int) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Radiance ``[C, 6, r, r]`` float64 at the texel centres (SH and functions averaged over
    ``supersample``² sub-texel directions) and the SH coefficients when the light is SH."""
    from ..sh import eval_sh
    from .environment import Environment

    d, _ = cube_map_directions(res * supersample)
    if isinstance(light, torch.Tensor) and light.ndim == 4:
        if light.shape[1:] != (6, res, res):
            raise ValueError(f"light cube has shape {tuple(light.shape)}; accepted: [C, 6, {res}, {res}]")
        return light.to(torch.float64), None
    sh = None
    if isinstance(light, torch.Tensor) and light.ndim == 2:
        n2 = light.shape[1]
        bands = math.isqrt(n2)
        if bands * bands != n2:
            raise ValueError(f"SH light has {n2} coefficients; accepted: [C, n²]")
        sh = light.to(torch.float64)
        vals = torch.einsum("...k,ck->...c", eval_sh(d, bands, check=False), sh)
    elif isinstance(light, Environment):
        vals = light.sample(d).to(torch.float64)
    elif callable(light):
        vals = torch.as_tensor(light(d)).to(torch.float64)
        if vals.ndim == 3:
            vals = vals[..., None]
    else:
        raise TypeError(f"light must be an SH matrix [C, n²], a cube map [C, 6, r, r], an Environment or a "
                        f"function of directions; got {describe(light)}")
    ss = supersample
    vals = vals.reshape(6, res, ss, res, ss, -1).mean((2, 4))  # [6, r, r, C]
    return vals.permute(3, 0, 1, 2).contiguous(), sh


def prefilter_environment(light: Any, *, res: int = 16, levels: int = 20, sigma_min: float = SIGMA_MIN,
                          sigma_max: float = SIGMA_MAX, supersample: int = 2, sh_bands: int | None = None,
                          block: int = 1024) -> PrefilteredEnvironment:
    """Prefilter ``light`` with normalised spherical Gaussians (module docstring).

    Args:
        light: SH coefficients ``[C, n²]``, a cube map ``[C, 6, res, res]`` (radiance per texel),
            an :class:`Environment`, or a function ``dirs [..., 3] -> [..., C]``.
        res: cube face resolution r of every level.
        levels: number of widths σ_l, geometric from ``sigma_min`` to ``sigma_max`` (radians).
        sh_bands: also keep SH coefficients of the light with this many bands (projected from
            the cube when the light is not SH) for an SH diffuse part (Green §3.1).
        block: query texels per GEMM block (memory bound ``block × 6 r²`` floats).
    Returns:
        :class:`PrefilteredEnvironment`. Cost: ``levels`` GEMMs of (6r²)² × C. A light tensor
        that requires grad (grad mode on) gives float64 levels, cube and SH differentiable with
        respect to it (the same filter, linear in the light), for ``GaussianCodec.relight``'s
        torch path (docs/inverse.md "Differentiable relighting").
    """
    res = check_int("res", res, 1, 256)
    levels = check_int("levels", levels, 1, 256)
    if not (0 < sigma_min < sigma_max):
        raise ValueError(f"sigma_min={sigma_min!r}, sigma_max={sigma_max!r}; accepted: 0 < sigma_min < sigma_max")
    cube, sh = _light_on_cube(light, res, supersample)
    C = cube.shape[0]
    # under autograd (a light that requires grad): the same filter in float64, the slices written below tracked
    dt = torch.float64 if torch.is_grad_enabled() and cube.requires_grad else torch.float32
    d, sa = cube_map_directions(res)
    dflat, saf = d.reshape(-1, 3), sa.reshape(-1)
    Lw = cube.reshape(C, -1).T  # [P, C]
    sig = torch.logspace(math.log10(sigma_min), math.log10(sigma_max), levels, dtype=torch.float64) if levels > 1 \
        else torch.tensor([sigma_min], dtype=torch.float64)
    out = torch.empty(levels, C, 6 * res * res, dtype=dt)
    P = dflat.shape[0]
    d32, sa32, L32 = dflat.to(dt), saf.to(dt), Lw.to(dt)
    for a in range(0, P, block):  # blocks of query texels; one GEMM per block and level
        cosm = (d32[a:a + block] @ d32.T - 1).clamp_max(0)  # [b, P]
        for li in range(levels):
            K = torch.exp(cosm * (1.0 / float(sig[li]) ** 2)) * sa32[None]
            K /= K.sum(1, keepdim=True)
            out[li, :, a:a + block] = (K @ L32).T
    if sh is None and sh_bands:
        from ..sh import eval_sh

        sh = torch.einsum("pk,pc->ck", eval_sh(dflat, int(sh_bands), check=False) * saf[:, None], Lw)
    return PrefilteredEnvironment(out.reshape(levels, C, 6, res, res), sig, cube.to(dt), sh)


