"""Inverse rendering: lighting and materials from images of known geometry (Ramamoorthi 2002,
ch. 6), run backwards through the engine's precomputed transfer (so shadows and interreflection
are part of the model, not an error: the thesis assumed convex objects).

* :mod:`.inputs` — NeRF/Blender ``transforms.json`` cameras, linear images, pixels traced to
  surface points (Embree), masks.
* :mod:`.light` — unknown lighting, known BRDF (§6.4.3): Tikhonov least squares with λ by GCV or
  the L-curve, optionally with the radiance constrained non-negative (eq. 6.24), and the
  well-posedness report (ch. 2 §2.4.2).
* :mod:`.material` — unknown BRDF, known lighting (§6.4.2: the reflection-form Phong of eq. 6.12
  by autograd non-linear least squares) and both unknown (§6.4.4).
* :mod:`.brdf_fit` — unknown BRDF beyond Phong (§6.4.2): the microfacet σ of eq. 5.34 and
  Ashikhmin–Shirley by autograd non-linear least squares, the SH BRDF ρ̂_lpq by linear least
  squares, both through a per-pixel hemisphere quadrature of the engine's BRDF classes.

``prt invert`` (:mod:`prt_torch.cli.invert`) is the command; docs/inverse.md the guide.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from . import brdf_fit, material
from .inputs import CameraView, Observations, camera_from_view, load_cameras, load_images, observe, pixel_rays
from .light import (LightFit, corner_rows, design_matrix, fit_light, negativity, nnls, positive_directions, solve_positive,
                    solve_tikhonov, well_posedness)

__all__ = ["brdf_fit", "material", "CameraView", "Observations", "load_cameras", "load_images", "observe", "pixel_rays", "camera_from_view",
           "LightFit", "corner_rows", "design_matrix", "fit_light", "solve_tikhonov", "well_posedness",
           "nnls", "solve_positive", "positive_directions", "negativity",
           "psnr", "light_json", "data_eps"]


def psnr(pred: torch.Tensor, obs: torch.Tensor) -> float:
    """PSNR (dB) of re-rendered ``pred [P, C]`` against observed ``obs [P, C]`` pixels, peak = the
    largest observed value (the residual the output reports)."""
    mse = float(((pred - obs) ** 2).mean())
    peak = float(obs.max())
    return math.inf if mse == 0 else 10 * math.log10(peak * peak / mse)


def data_eps(infos: list[dict]) -> float:
    """The relative precision of the observations (the λ floor of :func:`solve_tikhonov`): 1/255
    when any image is 8-bit, else float32's unit roundoff 2⁻²⁴ (the stored transfer is float32
    whatever the images are)."""
    from .light import FLOAT32_EPS

    return 1.0 / 255.0 if any(i.get("integer") for i in infos) else FLOAT32_EPS


def light_json(L: torch.Tensor, bands: int, source: str) -> dict:
    """The keys and layout ``prt light --json`` prints, for a light ``[C, n²]``: ``light`` (where it
    came from), ``bands``, ``window`` (None), ``convention``, ``lm`` and ``coeffs`` ``[C][n²]``."""
    from ..lighting.spec import SH_CONVENTION
    from ..sh import lm_of

    l, m = lm_of(bands)
    return {"light": source, "bands": int(bands), "window": None,
            "convention": SH_CONVENTION,
            "lm": [[int(a), int(b)] for a, b in zip(l, m)], "coeffs": np.asarray(L.detach(), np.float64).tolist()}
