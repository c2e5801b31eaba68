"""Built-in procedural environments (no downloads): deterministic, any layout, any resolution.

Each is a smooth sky/background function plus compact disk sources (sun, softboxes). Sources
are rasterised energy-conservingly: the pixel coverage of the disk is found with 4×4
sub-pixel samples and rescaled so that Σ L Ω over the map equals the source's exact power
L_c · 2π(1 - cos α); a source smaller than every sample (e.g. the real 0.27° sun on a coarse
map) puts all its power into the pixel containing its centre. So L_00 (and, to the pixel
size, every coefficient) does not depend on the resolution.

* ``sky``: clear sky gradient (blue zenith, pale horizon, dim ground) and a sun of the real
  angular radius 0.00465 rad at 35° elevation, azimuth 60° (from +x towards +y), radiance
  1.2e5 × warm white — sun:sky radiance ratio ~1e5, direct:sky irradiance ~4:1, as outdoors.
* ``sunset``: orange horizon, dark-blue zenith, sun 4° above the horizon towards +y.
* ``studio``: dark grey room (radiance 0.03, floor 0.02) with three coloured disk "softboxes":
  warm key (12°), cool fill (20°), white rim (6°).
* ``overcast``: CIE standard overcast sky L(θ) ∝ (1 + 2 cos θ)/3 over a grey ground; smooth
  (no sources), for low-frequency tests.
"""
from __future__ import annotations

import math
from typing import Any, Callable

import torch

from .._checks import check_choice
from . import layouts as L
from .environment import Environment

__all__ = ["builtin_environment", "list_builtin_environments", "BUILTIN_SIZE"]

BUILTIN_SIZE = 128  # default base size (latlong 256x128)


def _sph(elev_deg: float, az_deg: float) -> torch.Tensor:
    e, a = math.radians(elev_deg), math.radians(az_deg)
    return torch.tensor([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)], dtype=torch.float64)


def _gradient(zenith, horizon, ground) -> Callable[[torch.Tensor], torch.Tensor]:
    z, h, g = (torch.tensor(v, dtype=torch.float64) for v in (zenith, horizon, ground))

    def f(d: torch.Tensor) -> torch.Tensor:
        t = d[:, 2:3]
        return torch.where(t >= 0, h + (z - h) * t.clamp_min(0).sqrt(), g.expand(d.shape[0], -1))
    return f


_SPECS: dict[str, dict] = {
    "sky": dict(
        background=lambda: _gradient((0.25, 0.45, 1.0), (0.85, 0.9, 1.0), (0.12, 0.11, 0.10)),
        sources=[(lambda: _sph(35, 60), 0.00465, (1.2e5, 1.14e5, 1.02e5))],
    ),
    "sunset": dict(
        background=lambda: _gradient((0.05, 0.08, 0.25), (1.0, 0.45, 0.15), (0.05, 0.04, 0.04)),
        sources=[(lambda: _sph(4, 90), 0.0055, (6e4, 3e4, 1e4))],
    ),
    "studio": dict(
        background=lambda: _gradient((0.03, 0.03, 0.03), (0.03, 0.03, 0.03), (0.02, 0.02, 0.02)),
        sources=[
            (lambda: _sph(40, -30), math.radians(12), (40.0, 30.0, 20.0)),   # warm key
            (lambda: _sph(20, 200), math.radians(20), (4.0, 6.0, 10.0)),      # cool fill
            (lambda: _sph(60, 100), math.radians(6), (80.0, 80.0, 80.0)),     # white rim
        ],
    ),
    "overcast": dict(
        background=lambda: (lambda d: torch.where(
            d[:, 2:3] >= 0, (1 + 2 * d[:, 2:3].clamp_min(0)) / 3 * torch.tensor([1.0, 1.0, 1.0], dtype=torch.float64),
            torch.tensor([0.2, 0.2, 0.2], dtype=torch.float64).expand(d.shape[0], 3))),
        sources=[],
    ),
}


def list_builtin_environments() -> list[str]:
    """Names accepted by :func:`builtin_environment`."""
    return list(_SPECS)


def builtin_environment(name: str, layout: str = "latlong", size: int = BUILTIN_SIZE, rotation: Any = None,
                        supersample: int = 2) -> Environment:
    """A built-in procedural environment as an :class:`Environment` (float32 RGB).

    ``size``: latlong height / angular edge / cube face edge. ``rotation`` rotates the scene
    content (world = R · built-in frame). Deterministic."""
    check_choice("name", name, list(_SPECS))
    spec = _SPECS[name]
    R = L.resolve_rotation(rotation, "z")
    env = Environment.from_function(spec["background"](), layout, size, supersample=supersample, name=name,
                                    meta={"builtin": name})
    img = env.image.to(torch.float64)
    omega = env.solid_angles()
    mask = env.mask()
    s = 4
    for dfun, alpha, radiance in spec["sources"]:  # a few sources per environment
        d = dfun()
        cosa = math.cos(alpha)
        cov = Environment.from_function(lambda x: ((x @ d) >= cosa).to(torch.float64)[:, None], layout, size,
                                        supersample=s).image[..., 0].to(torch.float64) * mask
        power = 2 * math.pi * (1 - cosa)  # exact solid angle of the cap
        raster = float((cov * omega).sum())
        rad = torch.tensor(radiance, dtype=torch.float64)
        if raster > 0:
            img += (cov * (power / raster))[..., None] * rad
        else:  # sub-sample source: all power into the pixel that contains its centre
            y, x = L.dir_to_pixel(layout, *env.shape, d)
            iy, ix = int(y), int(x)
            img[iy, ix] += rad * (power / float(omega[iy, ix]))
    env.image = img.to(torch.float32)
    env.rotation = R
    env._cache.clear()
    return env
