"""``cube_light`` rasterises a light on the cube in blocks of sub-texel rows (left39 item 5): it built the whole
``s`` × ``s`` sub-texel grid of the cube at once (directions, solid angles, the light there and temporaries: ~78 MiB at
R = 64, s = 4, the largest part of a wavelet ``prt relight``'s peak), even for lights that never read it (built-in
environments, constants, images fine enough for the cube). Checked against the whole-grid computation written out
here from :func:`cube_geometry` (the previous code's arithmetic), for every light kind that reads the grid, at block
sizes from one texel row to a whole face; and the peak memory of the light's path at R = 64 in a fresh process."""
from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
import torch

from prt_torch.lighting import haar
from prt_torch.lighting.haar import cube_geometry, cube_light, sub_texel_blocks

RES, S = 8, 4


def _whole_grid(spec, res: int, s: int) -> torch.Tensor:
    """The previous, unchunked rasterisation ``[C, 6, R, R]`` of the lights that read the sub-texel grid."""
    from prt_torch.lighting import analytic as A
    from prt_torch.lighting.spec import analytic_params, parse_light_spec
    from prt_torch.sh import band_of_coeffs, eval_sh

    dirs, omega = cube_geometry(res, s)
    om_R = cube_geometry(res)[1]

    def averaged(fn):
        v = torch.as_tensor(fn(dirs.reshape(-1, 3))).to(torch.float64).reshape(6, res * s, res * s, -1)
        return (v * omega[..., None]).reshape(6, res, s, res, s, -1).sum((2, 4)) / om_R[..., None]

    if isinstance(spec, torch.Tensor):
        img = averaged(lambda d: eval_sh(d, band_of_coeffs(spec.shape[1]), check=False) @ spec.double().T)
        return img.permute(3, 0, 1, 2)
    kind, d = analytic_params(parse_light_spec(spec))
    if kind == "cap":
        alpha, direction = d["half_angle"], A.unit_direction(d["direction"])
        Lc = A.color(d["radiance"], "radiance")
        cosa = math.cos(alpha)
        cov = (((dirs @ direction) >= cosa).double() * omega).reshape(6, res, s, res, s).sum((2, 4))
        img = (cov * (2 * math.pi * (1 - cosa) / float(cov.sum())))[..., None] * Lc / om_R[..., None]
        return img.permute(3, 0, 1, 2)
    assert kind == "hemisphere"
    h, g, up = A.color(d["upper"], "upper"), A.color(d["lower"], "lower"), A.unit_direction(d.get("up", (0, 0, 1)))
    t = (dirs @ up)[..., None]
    v = torch.where(t >= 0, h + (h - h) * t.clamp_min(0), g)
    return ((v * omega[..., None]).reshape(6, res, s, res, s, -1).sum((2, 4)) / om_R[..., None]).permute(3, 0, 1, 2)


LIGHTS = {
    "sh": torch.tensor([[1.0, 0.3, -0.5, 0.2, 0.1, 0.0, -0.2, 0.05, 0.3]] * 3) * torch.tensor([[1.0], [0.8], [0.6]]),
    "cap": "cap:direction=0.3,0.2,1;half_angle_deg=20;radiance=1",
    "hemisphere": "hemisphere:upper=1;lower=0.2",
}


def test_blocks_are_the_whole_grid_bit_for_bit():
    dirs, omega = cube_geometry(RES, S)
    seen = torch.zeros(6, RES * S, RES * S, dtype=torch.bool)
    for f, i0, i1, d, om in sub_texel_blocks(RES, S):
        assert torch.equal(d, dirs[f, i0 * S:i1 * S]) and torch.equal(om, omega[f, i0 * S:i1 * S])
        seen[f, i0 * S:i1 * S] = True
    assert bool(seen.all())


@pytest.mark.parametrize("block", [1, 64, 1 << 16, 1 << 30], ids=["row", "rows", "default", "whole-face"])
@pytest.mark.parametrize("name", list(LIGHTS))
def test_chunked_equals_the_whole_grid(monkeypatch, name, block):
    monkeypatch.setattr(haar, "LIGHT_BLOCK_SAMPLES", block)
    got, _ = cube_light(LIGHTS[name], RES, supersample=S)
    want = _whole_grid(LIGHTS[name], RES, S)
    assert got.shape == want.shape
    assert torch.allclose(got, want, rtol=1e-13, atol=1e-15 * float(want.abs().max())), float((got - want).abs().max())


def test_upsampled_image_chunked_equals_point_samples(tmp_path, monkeypatch):
    """An image coarser than the cube is point-sampled at the sub-texel grid (``Environment.sample``)."""
    from prt_torch.lighting import load_environment
    from prt_torch.lighting.imageio import write_image

    rng = np.random.default_rng(3)
    write_image(tmp_path / "coarse.hdr", rng.random((8, 16, 3)).astype(np.float32))
    monkeypatch.setattr(haar, "LIGHT_BLOCK_SAMPLES", 64)
    got, rec = cube_light(str(tmp_path / "coarse.hdr"), RES, supersample=S)
    assert rec["upsampled"]
    env = load_environment(str(tmp_path / "coarse.hdr"))
    dirs, omega = cube_geometry(RES, S)
    v = env.sample(dirs.reshape(-1, 3)).double().reshape(6, RES * S, RES * S, -1)
    want = ((v * omega[..., None]).reshape(6, RES, S, RES, S, -1).sum((2, 4)) / cube_geometry(RES)[1][..., None]).permute(3, 0, 1, 2)
    assert torch.allclose(got, want, rtol=1e-13, atol=1e-15 * float(want.abs().max()))


PEAK = r'''
import sys, torch
from prt_torch.relight import wavelet_light
spec, res = sys.argv[1], int(sys.argv[2])
wavelet_light(spec, 2, None, "magnitude")  # imports and one-off tables at a tiny size
def status(key):
    return int(open("/proc/self/status").read().split(key + ":")[1].split()[0]) * 1024
r0 = status("VmRSS")
open("/proc/self/clear_refs", "w").write("5")  # resets VmHWM to the current RSS
wavelet_light(spec, res, None, "magnitude")
print(status("VmHWM") - r0)
'''


@pytest.mark.parametrize("spec", ["cap:direction=0.3,0.2,1;half_angle_deg=20;intensity=1", "constant"])
def test_light_peak_is_bounded(spec):
    """The light's path at R = 64, supersample 4 (393 216 sub-texel directions) in a fresh process: its peak RSS growth
    was 78–99 MiB (200–263 B per direction); now within the plan's ``build|light`` estimate and below 40 MiB."""
    from prt_torch.cli.relight import light_bytes

    out = subprocess.run([sys.executable, "-c", PEAK, spec, "64"], capture_output=True, text=True, check=True)
    grown = int(out.stdout.split()[-1])
    assert grown <= light_bytes(64) and grown < 40 << 20, (grown, light_bytes(64))
