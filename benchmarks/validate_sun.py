"""engine/Mitsuba under the built-in ``sky`` (a one-pixel sun) with ``--light-source image``:
the issue-39 review's case (docs/validate.md, "Environment images"): a full-K R = 64 wavelet
transfer of ``scan_blob`` at sampled vertices, shadowed diffuse exit radiance, against Mitsuba 3
fed :func:`prt_torch.validate.lights.source_image` (the power-conserving remap).

Also prints the remap's figures per environment: total power engine vs Mitsuba image (Mitsuba's
pixel solid angles), the power in a 3° cone around the brightest engine pixel (each side's pixels
by their centres: a like-for-like figure for a point-like source such as the sky's sun; for an
extended one the two grids' pixel sets cover different solid angles), the largest
deviation from 1 of the remap of a constant light (per-pixel fluctuation), the remap's CPU time.

    .venv/bin/python benchmarks/validate_sun.py [--vertices 16] [--spp 2048] [--lights sky,studio,overcast]
"""
from __future__ import annotations

import argparse
import math
import time

import torch

from prt_torch.lighting import builtin_environment
from prt_torch.scene import builtin
from prt_torch.transfer.wavelet import sampled_wavelet_transfer
from prt_torch.validate import lights as VL
from prt_torch.validate import sample_vertices, validate


def remap_figures(name: str) -> dict:
    env = builtin_environment(name)
    H = VL.source_height(env, 128)
    t = time.thread_time()
    img, info = VL.remap_to_mitsuba(env, H)
    cpu = time.thread_time() - t
    om = VL.mitsuba_pixel_solid_angles(H).repeat_interleave(2 * H)
    flat = img.reshape(-1, img.shape[-1])
    P, Pe = (flat * om[:, None]).sum(0), env.total_power()
    k = int(env.image.sum(-1).argmax())
    de = env.directions().reshape(-1, 3)
    c = math.cos(math.radians(3))
    ine = de @ de[k] > c
    pe = (env.image.reshape(-1, env.channels).double()[ine] * env.solid_angles().reshape(-1)[ine, None]).sum(0)
    inm = VL.mitsuba_envmap_directions(H).reshape(-1, 3) @ de[k] > c
    pm = (flat[inm] * om[inm, None]).sum(0)
    ones = builtin_environment(name)
    ones.image = torch.ones_like(ones.image)
    flat1, _ = VL.remap_to_mitsuba(ones, H)
    return {"env": name, "height": H, "power_rel": float(((P - Pe) / Pe).abs().max()), "cone_engine": float(pe[0]),
            "cone_mitsuba": float(pm[0]), "const_maxdev": float((flat1 - 1).abs().max()), "iters": info["iters"],
            "cpu_s": round(cpu, 2)}


def point_image(spec, height: int = 128):
    """The image the validator gave Mitsuba before the remap: nearest-pixel radiance at the
    pixel centres θ = π (i + ½)/H of a 128-row grid."""
    env = builtin_environment(spec)
    H, W = 128, 256
    th = math.pi * (torch.arange(H, dtype=torch.float64) + 0.5) / H
    ph = 2 * math.pi * (torch.arange(W, dtype=torch.float64) + 0.5) / W
    st, ct = torch.sin(th)[:, None], torch.cos(th)[:, None]
    d = torch.stack([st * torch.sin(ph), ct.expand(H, W), -st * torch.cos(ph)], -1)
    v = env.sample(d.reshape(-1, 3)).to(torch.float64)
    v = v.expand(-1, 3) if v.shape[1] == 1 else v
    return v.reshape(H, W, 3).numpy().astype("float32")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--vertices", type=int, default=16)
    ap.add_argument("--spp", type=int, default=2048)
    ap.add_argument("--lights", default="sky,studio,overcast")
    ap.add_argument("--res", type=int, default=64)
    ap.add_argument("--point", action="store_true", help="also the image before: the environment point-sampled at the "
                    "pixel centres of a 128-row grid (pixel-centre rows, as the validator did)")
    a = ap.parse_args()
    for name in a.lights.split(","):
        print(remap_figures(name), flush=True)
    m = builtin("scan_blob", "small")
    idx = sample_vertices(m, a.vertices, 0)
    R = a.res
    tr = sampled_wavelet_transfer(m, R, idx)
    for name in a.lights.split(","):
        t = time.time()
        rep = validate(tr, name, light_source="image", idx=idx, spp=a.spp, batches=8)
        d = rep["direct"]
        print(f"{name} (remap): engine/Mitsuba {d['ratio']:.4f} ± {d['ratio_se']:.4f} (z {d['z']:+.2f}), per-vertex RMS "
              f"{rep['direct_rms_rel']:.3f}, {time.time() - t:.1f} s wall", flush=True)
        if a.point:
            import prt_torch.validate as V

            keep = V.source_image
            V.source_image = point_image
            try:
                rep = validate(tr, name, light_source="image", idx=idx, spp=a.spp, batches=8)
            finally:
                V.source_image = keep
            d = rep["direct"]
            print(f"{name} (point-sampled, before): engine/Mitsuba {d['ratio']:.4f} ± {d['ratio_se']:.4f}", flush=True)


if __name__ == "__main__":
    main()
