"""``prt light``: project an environment map, built-in environment or analytic light to SH,
print the coefficients, optionally write the irradiance map and a preview PNG."""
from __future__ import annotations

import argparse
import json

import torch

from ..lighting import (
    LAYOUTS,
    Environment,
    builtin_environment,
    irradiance_map,
    list_builtin_environments,
    load_environment,
    parse_light_spec,
    render_sh,
    write_image,
)
from ..lighting.spec import SH_CONVENTION, load_light
from ..lighting.layouts import resolve_rotation
from ..sh import lm_of, rotate as sh_rotate


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "light",
        help="project a light (HDR file, built-in, analytic spec) to SH; irradiance map; preview",
        description=(
            "Print the SH coefficients (bands² x channels) of a light. LIGHT is an image file (.hdr, .exr, .pfm, "
            ".tif; layout auto-detected from W:H), a '{face}' pattern for six cube faces, a built-in environment ("
            + ", ".join(list_builtin_environments())
            + ") or an analytic spec like 'directional:direction=0,0,1;intensity=1', "
            "'cap:direction=0,1,1;half_angle_deg=10;intensity=2', 'sky_gradient', 'constant:value=1'. "
            "World frame: +z up; see docs/lighting.md."
        ),
    )
    p.add_argument("light", metavar="LIGHT")
    p.add_argument("--layout", choices=list(LAYOUTS), default=None, help="image layout (default: from aspect ratio)")
    p.add_argument("--bands", type=int, default=3, help="SH bands n (n² coefficients; default 3)")
    p.add_argument("--window", default=None, help="ringing window: hanning, lanczos, gaussian:SIGMA (default none)")
    p.add_argument("--up", default="z", help="up axis of the file's frame: z (default), y, -y, x, ...")
    p.add_argument("--rotate", default=None, metavar="A,B,C", help="extra rotation, Euler angles in degrees about x, y, z")
    p.add_argument("--clamp", action="store_true", help="set NaN/Inf/negative pixels to 0 instead of refusing the file")
    p.add_argument("--size", type=int, default=128, help="resolution of a built-in environment (latlong height)")
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--irradiance-map", metavar="OUT", default=None, help="write the irradiance map E(n) (eq. 4.10)")
    p.add_argument("--irradiance-layout", choices=list(LAYOUTS), default="latlong")
    p.add_argument("--irradiance-size", type=int, default=64)
    p.add_argument("--preview", metavar="OUT.png", default=None, help="tone-mapped preview: environment | irradiance")
    p.add_argument("--overwrite", action="store_true", help="replace existing output files")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def _tonemap(img: torch.Tensor) -> torch.Tensor:
    """Reinhard x/(1+x) after scaling the mean luminance to 0.5 (for previews only)."""
    lum = img.to(torch.float64).mean(-1)
    k = 0.5 / max(float(lum[lum > 0].mean()) if (lum > 0).any() else 1.0, 1e-12)
    x = img.to(torch.float64) * k
    return (x / (1 + x)).to(torch.float32)


def run(args: argparse.Namespace) -> int:
    from ..io import check_outputs

    faces = [args.irradiance_map.format(face=f) for f in ("px", "nx", "py", "ny", "pz", "nz")] \
        if args.irradiance_map and "{face}" in args.irradiance_map else args.irradiance_map
    light_files = [args.light.format(face=f) for f in ("px", "nx", "py", "ny", "pz", "nz")] if "{face}" in args.light else args.light
    check_outputs({"--irradiance-map": faces, "--preview": args.preview}, {"LIGHT": light_files}, args.overwrite)  # before any work
    env: Environment | None = None
    spec = args.light
    if spec in list_builtin_environments():
        # --up too (a built-in's frame is +z up; --up y reads it as a y-up file would be): checked, never ignored
        env = builtin_environment(spec, size=args.size, rotation=resolve_rotation(args.rotate, args.up))
    elif parse_light_spec(spec) is None and not spec.lower().endswith(".json"):
        env = load_environment(spec, layout=args.layout, rotation=args.rotate, up=args.up, clamp=args.clamp)
    if env is not None:
        L = env.project(args.bands, args.window)
    else:
        L = load_light(spec, args.bands, args.window)
        if args.rotate is not None or args.up != "z":  # analytic light: rotate its SH vector
            L = sh_rotate(L, resolve_rotation(args.rotate, args.up))
    # outputs
    if args.irradiance_map or args.preview:
        E = irradiance_map(L, args.irradiance_layout, args.irradiance_size)
        if args.irradiance_map:
            E.save(args.irradiance_map, overwrite=args.overwrite)
        if args.preview:
            src = env if env is not None else render_sh(L, "latlong", args.irradiance_size)
            a = src.to_layout("latlong", args.irradiance_size, supersample=1).image if src.layout != "latlong" else src.image
            b = E.to_layout("latlong", a.shape[0], supersample=1).image
            write_image(args.preview, torch.cat([_tonemap(a), _tonemap(b)], dim=1), overwrite=args.overwrite)
    l, m = lm_of(args.bands)
    chans = "RGB" if L.shape[0] == 3 else [f"c{i}" for i in range(L.shape[0])]
    if args.json:
        out = {
            "light": spec,
            "bands": args.bands,
            "window": args.window,
            "convention": SH_CONVENTION,
            "lm": [[int(a), int(b)] for a, b in zip(l, m)],
            "coeffs": L.tolist(),  # [C][n²]
        }
        if env is not None:
            out.update(layout=env.layout, shape=list(env.image.shape), total_power=env.total_power().tolist(),
                       clamped=[f.get("clamped") for f in env.meta.get("files", [])])
        print(json.dumps(out, indent=2))
    else:
        if env is not None:
            print(f"# {spec}: layout={env.layout} shape={tuple(env.image.shape)}")
        print(f"# SH coefficients L_lm, {args.bands} bands ({args.bands ** 2} x {L.shape[0]})")
        print(f"{'l':>3} {'m':>3} " + " ".join(f"{c:>12}" for c in chans))
        for k in range(L.shape[1]):
            print(f"{int(l[k]):>3} {int(m[k]):>3} " + " ".join(f"{float(v):12.6g}" for v in L[:, k]))
    return 0
