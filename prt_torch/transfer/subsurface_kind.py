"""Transfer kind ``subsurface`` (issue 41): the transferred irradiance of the diffuse precompute
spread by the dipole over the hierarchy of :mod:`prt_torch.transfer.subsurface` — a module of
its own because it runs both (the diffuse kind's ``subsurface:`` term calls the term alone)."""
from __future__ import annotations

import dataclasses
import warnings
from typing import Any

import torch

from .._checks import check_float, check_int
from ..scene import Mesh
from .base import RunOptions, Transfer
from .diffuse import precompute_diffuse
from .subsurface import (DEFAULT_EPSILON, DEFAULT_SPACING, check_closed, check_scale, resolve_material, sub_state,
                         subsurface_term)

__all__ = ["precompute_subsurface"]


def precompute_subsurface(
    mesh: Mesh,
    material: Any = None,
    scale: float = 1.0,
    bands: int = 3,
    samples: int = 256,
    bounces: int = 0,
    seed: int = 0,
    *,
    shadows: str = "auto",
    sigma_a: Any = None,
    sigma_s: Any = None,
    eta: float | None = None,
    epsilon: float = DEFAULT_EPSILON,
    fresnel: bool = True,
    method: str = "hierarchical",
    spacing: float = DEFAULT_SPACING,
    run: RunOptions | None = None,
) -> Transfer:
    """Transfer kind ``subsurface``: the subsurface scattering term alone (Sloan 2003 §3.1,
    Jensen & Buhler 2002, Jensen 2001), as diffuse transfer with the colour folded in.

    Args:
        mesh: a closed mesh (an open one is warned about, naming where).
        material: a preset name (:data:`PRESETS`) or ``{sigma_a, sigma_s, eta}`` (mm⁻¹); None:
            ``sigma_a``, ``sigma_s`` (σ'_s), ``eta`` given one by one (the CLI's --sigma-a R,G,B
            --sigma-s R,G,B --eta E), or marble when none is.
        scale: mm per mesh unit (> 0); a mean free path below size/1000 or above the object is
            warned about with the numbers.
        bands, samples, bounces, seed, shadows: the transferred irradiance's precompute
            (:func:`~prt_torch.transfer.diffuse.precompute_diffuse`, ρ = 1).
        epsilon: the hierarchy's solid-angle threshold (default: ≤ 1% from the O(V²) sum).
        fresnel: F_dt at entry and exit (False: none, for the slab's closed form).
        method: 'hierarchical' or 'brute' (O(V²)).
        spacing: irradiance samples at most this multiple of the smallest mean free path apart
            (:func:`subsurface_term`; the vertices themselves when they are that dense).
        run: chunks, resume, executor (shared by both passes; the scatter's chunks are receivers).
    Returns:
        ``Transfer(kind='diffuse')``, data float32 ``[V, 3, n²]`` (``albedo_folded``: the
        material's colour is in the data; exit radiance = data[v, c] · l[c]), ``meta['subsurface']``.
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a prt_torch.scene.Mesh, got {type(mesh).__name__}")
    m = resolve_material(material, sigma_a, sigma_s, eta)
    scale = check_float("scale", scale, 0.0, None, lo_open=True)
    check_int("bands", bands, 1, 32)
    run = RunOptions() if run is None else run
    for w in (check_closed(mesh), check_scale(mesh, m, scale)):
        if w:
            warnings.warn(w, stacklevel=2)
    direct = precompute_diffuse(mesh.with_albedo(1.0), bands=bands, samples=samples, bounces=bounces, seed=seed,
                                shadows=shadows, fold_albedo=False,
                                run=dataclasses.replace(run, state_dir=sub_state(run, "irradiance"), keep_state=True))
    # (kept until the scatter is done: an interrupted scatter resumes without recomputing the irradiance)
    sub: dict[str, Any] = {}
    # the receivers' rows are converted to float32 as each chunk is copied in (in a file when large: subsurface_term)
    L = subsurface_term(mesh, direct.data, m, scale, epsilon=epsilon, fresnel=fresnel, method=method, spacing=spacing,
                        seed=seed, run=dataclasses.replace(run, state_dir=sub_state(run, "scatter")), meta=sub,
                        dtype=torch.float32)
    meta = dict(direct.meta)
    meta.update(albedo_folded=True, channels=3, transfer_kind_requested="subsurface", subsurface=sub,
                normalisation="exit radiance L_out[v,c] = sum_i data[v,c,i] * l[c,i]; the subsurface term "
                              "(F_dt^2/pi) sum_j R_d(|x_j - x_v|) A_j E_j, E = pi t (Jensen 2001, Jensen & Buhler 2002); "
                              "constant radiance 1 -> l00 = 2 sqrt(pi)")
    run.finish()
    return Transfer(kind="diffuse", data=L, mesh=mesh, meta=meta)


