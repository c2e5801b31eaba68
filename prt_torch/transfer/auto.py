"""Model only what the scene requires: band count, exit bands and tent count chosen from the
energy of the lights and of the BRDF's lobe (``bands: auto``, ``bands_out: auto``, ``M: auto``).

Reflected radiance is the lighting filtered by the BRDF lobe: per band l its SH coefficients
are ρ_l L_lm with ρ_l = Λ_l h_l the lobe's filter (Ramamoorthi 2002 eq. 4.11 for the clamped
cosine, eq. 3.37 for Phong). The energy of band l of the result is therefore

    E_l = ρ_l² Σ_m L_lm²                       (Ramamoorthi 2002 eq. 5.15–5.17)

and the smallest band count n with Σ_{l<n} E_l ≥ f Σ_l E_l keeps a fraction f of it (3 bands keep
99.3% of the irradiance of a flat spectrum; a Phong lobe of exponent s, ρ_l ≈ exp(-l²/2s), needs
about √s bands). Lights come from the config (each normalised to unit energy, so every light
counts equally); without lights the spectrum is flat (Σ_m L_lm² ∝ 2l+1) and only the lobe
decides. A BRDF that is not a sum of radially symmetric lobes is represented by the Phong lobe
of its equivalent exponent (``BRDF.sharpness``) plus its diffuse part; the reason says so.

Tents (MRT): the smallest M whose M×M tent projection keeps a fraction f of the energy of exit
radiance with ``bands_out`` bands: 1 − tr(E)/tr(A_m) ≥ f with E the projection error matrix of
Lehtinen & Kautz 2003 eq. 10 and A_m the hemisphere Gram matrix (the expectation over random
unit SH vectors, eq. 11).

Every decision is returned with its reason; the harness and ``prt precompute`` store them in
``Transfer.meta['auto']``.
"""
from __future__ import annotations

import math
from typing import Any

import torch

from .._checks import check_float
from ..brdf import BRDF, Lambertian
from ..sh import band_factor, clamped_cosine, hemisphere_gram, phong
from .tents import MAX_TENTS, error_matrix

__all__ = ["AUTO", "DEFAULT_ENERGY", "lobe_filter", "light_spectrum", "choose_bands", "choose_tents", "choose_haar_res", "resolve_auto",
           "light_choices", "energy_choices"]

AUTO = "auto"
DEFAULT_ENERGY = 0.99
#: bands over which spectra are evaluated (the lobe and light energy beyond it is neglected)
SPECTRUM_BANDS = 32


def lobe_filter(brdf: BRDF | None, bands: int = SPECTRUM_BANDS) -> tuple[torch.Tensor, str]:
    """Per-band energy filter ρ_l² ``[bands]`` float64 of a BRDF's lobes (summed over lobes;
    ``None`` = diffuse transfer, the clamped cosine) and a one-line reason."""
    if brdf is None:
        rho = clamped_cosine(bands) * band_factor(bands)
        return rho ** 2, "diffuse: clamped-cosine filter A_l (Ramamoorthi 2002 eq. 4.11)"
    try:
        lobes = brdf.lobes(bands)
        parts = [(band_factor(bands) * h.reshape(-1, bands)).pow(2).amax(0) for _, h in lobes]
        return sum(parts), f"{brdf.name}: its radially symmetric lobes ({', '.join(a for a, _ in lobes)})"
    except ValueError:
        pass
    if isinstance(brdf, Lambertian):  # pragma: no cover - Lambertian defines lobes()
        return lobe_filter(None, bands)
    s = float(brdf.sharpness)
    spec = phong(s, bands) * band_factor(bands)
    diff = clamped_cosine(bands) * band_factor(bands)
    return spec ** 2 + diff ** 2 / math.pi ** 2, (f"{brdf.name}: Phong lobe of its equivalent exponent s={s:g} "
                                                   "(Ramamoorthi 2002 eq. 3.37) plus a diffuse part")


def light_spectrum(lights: list[torch.Tensor] | None, bands: int = SPECTRUM_BANDS) -> tuple[torch.Tensor, str]:
    """Per-band light energy Σ_m L_lm² ``[bands]`` float64, each light ``[C, n²]`` normalised to
    unit energy and summed; ``None``/empty: a flat spectrum (2l+1 per band)."""
    if not lights:
        return torch.arange(bands, dtype=torch.float64) * 2 + 1, "no lights given: flat light spectrum"
    out = torch.zeros(bands, dtype=torch.float64)
    for L in lights:
        L = L.to(torch.float64).reshape(-1, L.shape[-1])
        n = min(bands, math.isqrt(L.shape[-1]))
        e = torch.stack([L[:, l * l:(l + 1) ** 2].pow(2).sum() for l in range(n)])  # a loop over bands
        tot = float(e.sum())
        if tot > 0:
            out[:n] += e / tot
    return out, f"{len(lights)} light(s), each normalised to unit energy"


def choose_bands(energy: float, lobe: torch.Tensor, light: torch.Tensor, max_bands: int) -> tuple[int, float]:
    """Smallest n ≤ ``max_bands`` with Σ_{l<n} E_l ≥ energy · Σ_l E_l, E_l = lobe_l · light_l.
    Returns (n, fraction kept); n = max_bands (and its fraction) when even that is short."""
    e = lobe[: light.numel()] * light[: lobe.numel()]
    total = float(e.sum())
    if total <= 0:
        return 1, 1.0
    cum = torch.cumsum(e, 0) / total
    ok = torch.nonzero(cum >= energy - 1e-12).flatten()
    n = int(ok[0]) + 1 if ok.numel() else e.numel()
    n = min(n, max_bands)
    return n, float(cum[n - 1])


def choose_tents(bands_out: int, energy: float, max_tents: int = 24) -> tuple[int, float]:
    """Smallest M in [2, max_tents] whose tent projection keeps ``energy`` of exit radiance with
    ``bands_out`` bands: 1 − tr(E)/tr(A_m) (Lehtinen & Kautz 2003 eq. 10–11). Returns (M, kept)."""
    total = float(torch.trace(hemisphere_gram(bands_out)))
    kept = 0.0
    for M in range(2, min(max_tents, MAX_TENTS) + 1):  # a short search, one small matrix each
        kept = 1.0 - float(torch.trace(error_matrix(M, bands_out))) / total
        if kept >= energy:
            return M, kept
    return min(max_tents, MAX_TENTS), kept


#: the finest cube resolution ``res: auto`` chooses (the lights are measured at twice it: what a
#: sharp edge keeps losing level by level beyond it is then part of the figure)
AUTO_HAAR_MAX_RES = 64
#: ``res: auto`` without lights
AUTO_HAAR_DEFAULT_RES = 32


def choose_haar_res(lights: list | None, energy: float, max_res: int = AUTO_HAAR_MAX_RES) -> tuple[int, float | None, str]:
    """``res: auto`` of the wavelet kind: the smallest cube face resolution R ≤ ``max_res`` whose
    Haar levels keep ``energy`` of each light's energy (Σ L̂² over the coefficients coarser than R
    of the light's cube at 2·``max_res``, each light normalised to unit energy and summed, as for
    bands): what the dropped finer levels hold is the light's detail a coarser cube cannot place;
    ``max_res`` with the fraction it keeps when even that is short. When every light is an image
    coarser than the measuring cube (``cube_light`` point-samples it: its pixels' edges would count as
    detail), R is at most the finest cube every texel of which holds one of its pixel centres. Lights: SH
    tensors ``[C, n²]`` or specs (:func:`prt_torch.lighting.haar.cube_light`). Returns
    (R, fraction kept, reason); without lights R = :data:`AUTO_HAAR_DEFAULT_RES` and the fraction None
    (nothing measured; metadata is JSON, which has no NaN)."""
    from ..lighting.haar import cube_light, haar2d

    if not lights:
        return AUTO_HAAR_DEFAULT_RES, None, f"no lights given: the default R={AUTO_HAAR_DEFAULT_RES}"
    r = 2 * max_res
    m = torch.arange(r)
    level = torch.maximum(m[:, None], m[None, :])  # coefficient (i, j) belongs to resolution > max(i, j)
    per_res = torch.zeros(r.bit_length(), dtype=torch.float64)  # energy first resolved at R = 2^k
    fills: list[tuple[str, int]] = []  # images coarser than the measuring cube: (name, the finest R they fill)
    for spec in lights:  # a few lights
        cube, rec = cube_light(spec, r, supersample=2)
        if rec.get("upsampled"):  # point samples at r: the image's pixel edges would read as detail to resolve
            f = r // 2
            while f > 1 and cube_light(spec, f, supersample=1)[1].get("upsampled"):
                f //= 2
            fills.append((str(rec.get("source", spec)), f))
        e = haar2d(cube).square().sum((0, 1))  # [R, R] summed over channels and faces
        tot = float(e.sum())
        if tot <= 0:
            continue
        for k in range(r.bit_length()):  # log2 R + 1 levels
            lo, hi = (0, 1) if k == 0 else (1 << (k - 1), 1 << k)
            per_res[k] += float(e[(level >= lo) & (level < hi)].sum()) / tot
    cum = torch.cumsum(per_res, 0) / per_res.sum().clamp_min(1e-300)
    ok = torch.nonzero(cum >= energy - 1e-12).flatten()
    top = max_res.bit_length() - 1
    k_energy = min(int(ok[0]), top) if ok.numel() else top
    cap = max((f for _, f in fills), default=0)  # the finest cube the coarse images fill: a finer one holds no more
    if fills and len(fills) == len(lights) and cap.bit_length() - 1 < k_energy:  # of them (cube_light point-samples)
        k = cap.bit_length() - 1
        return 1 << k, float(cum[k]), (f"R={1 << k}: the light(s) are images no finer than the cube at R={cap} (every texel "
                                       f"holds a pixel centre there, beyond it they are point-sampled: "
                                       f"{'; '.join(n for n, _ in fills)}); keeps {float(cum[k]):.4f} of the energy of "
                                       f"their point-sampled cube at R={r}, whose pixel edges hold the rest (target {energy:g})")
    if ok.numel() and int(ok[0]) <= top:
        k = int(ok[0])
        return 1 << k, float(cum[k]), (f"smallest cube face resolution whose Haar levels keep {energy:g} of the energy of "
                                       f"{len(lights)} light(s) (each normalised, measured at R={r})")
    return max_res, float(cum[top]), (f"R={max_res}, the largest res: auto chooses, keeps {float(cum[top]):.4f} < {energy:g} of "
                                      f"the energy of {len(lights)} light(s) (each normalised, measured at R={r}): sharper "
                                      "than the cube resolves; pass --res 128 for more")


def light_choices(kind: str, params: dict[str, Any]) -> list[str]:
    """The parameters of ``params`` (validated, the kind's defaults not filled in) whose ``'auto'``
    choice in :func:`resolve_auto` reads the lights: a wavelet transfer's ``res`` (the lights' Haar
    energy, :func:`choose_haar_res`), an SH kind's ``bands`` (the light spectrum × the lobe,
    :func:`choose_bands`). ``bands_out`` and ``M`` come from the lobe alone and the transport kind's
    ``res`` from the BRDF, so an empty list means the lights change nothing (``prt precompute``
    refuses ``--light`` then)."""
    if kind == "wavelet":
        return ["res"] if params.get("res") == AUTO else []
    return ["bands"] if params.get("bands") == AUTO else []


def energy_choices(kind: str, params: dict[str, Any]) -> list[str]:
    """The parameters of ``params`` whose ``'auto'`` choice in :func:`resolve_auto` keeps the fraction
    ``energy``: ``bands``, ``bands_out``, ``M`` and a wavelet transfer's ``res`` (the transport kind's
    ``res: auto`` comes from the BRDF's narrowest lobe alone). Empty: ``energy`` changes nothing
    (``prt precompute`` refuses ``--energy`` then)."""
    names = ("bands", "bands_out", "M") + (("res",) if kind == "wavelet" else ())
    return [n for n in names if params.get(n) == AUTO]


def resolve_auto(kind: str, params: dict[str, Any], lights: list[torch.Tensor] | None, brdf: BRDF | None,
                 max_bands: int) -> tuple[dict[str, Any], dict[str, Any]]:
    """Replace ``'auto'`` in ``params`` (bands, bands_out, M; the wavelet kind's res; the transport
    kind's res, 'auto' when absent: :func:`prt_torch.transfer.transport.choose_cube_res`) by the
    chosen values. A wavelet ``terms`` (given or the default 256) above the 6R² coefficients of the
    cube ``res: auto`` chose becomes 6R² (every coefficient kept; the decision ``terms`` says so), as the
    user cannot know R beforehand.

    ``params['energy']`` (default 0.99, in (0, 1]) is the fraction kept; it is removed from the
    returned parameters. Returns (parameters for the precompute, decisions: per parameter
    ``{'value', 'energy_kept', 'reason'}``)."""
    p = dict(params)
    energy = check_float("energy", p.pop("energy", DEFAULT_ENERGY), 0.0, 1.0, lo_open=True)
    decisions: dict[str, Any] = {}
    if kind == "wavelet" and p.get("res") == AUTO:
        from .wavelet import DEFAULT_TERMS

        r, kept, why = choose_haar_res(lights, energy)
        p["res"] = r
        decisions["res"] = {"value": r, "energy_kept": kept, "target": energy, "reason": why}
        K, P = p.get("terms", DEFAULT_TERMS), 6 * r * r
        if isinstance(K, int) and K > P:  # the K asked for (or the default) is for a finer cube than auto chose
            p["terms"] = P
            decisions["terms"] = {"value": P, "energy_kept": None, "target": None,
                                  "reason": f"terms {K} > the {P} Haar coefficients of the cube res: auto chose (6R², "
                                            f"R={r}): every coefficient kept"}
    if kind == "transport" and p.get("res", AUTO) == AUTO:  # the kind's default is 'auto'
        from .transport import choose_cube_res

        p["res"], decisions["res"] = choose_cube_res(brdf)
    if not any(p.get(k) == AUTO for k in ("bands", "bands_out", "M")):
        return p, decisions
    lobe, lobe_why = lobe_filter(None if kind == "diffuse" else brdf)
    light, light_why = light_spectrum(lights)
    if p.get("bands") == AUTO:
        n, kept = choose_bands(energy, lobe, light, max_bands)
        p["bands"] = n
        decisions["bands"] = {"value": n, "energy_kept": kept, "target": energy,
                              "reason": f"smallest band count keeping {energy:g} of the reflected energy "
                                        f"(lobe filter × light spectrum; {lobe_why}; {light_why})"}
    if p.get("bands_out") == AUTO:
        n, kept = choose_bands(energy, lobe, torch.arange(lobe.numel(), dtype=torch.float64) * 2 + 1, max_bands)
        p["bands_out"] = n
        decisions["bands_out"] = {"value": n, "energy_kept": kept, "target": energy,
                                  "reason": f"smallest exit band count keeping {energy:g} of the BRDF lobe's energy ({lobe_why})"}
    if p.get("M") == AUTO:
        m = int(p.get("bands_out") or 8)
        M, kept = choose_tents(m, energy)
        p["M"] = M
        decisions["M"] = {"value": M, "energy_kept": kept, "target": energy,
                          "reason": f"smallest tent grid whose projection keeps {energy:g} of exit radiance with {m} bands "
                                    "(Lehtinen & Kautz 2003 eq. 10-11)"}
    return p, decisions
