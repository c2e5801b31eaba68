"""``prt render TRANSFER.prt [--light SPEC] [--codec-file X] -o out.png``: relight a diffuse
transfer file with a light (SH dot product per vertex, Sloan 2002) and render the per-vertex
exit radiance offscreen as a float image (PNG tone-mapped, or EXR/PFM/HDR/TIF float).

With ``--codec-file`` the radiance comes from the transfer decoded from that compressed file
(needs ``prt_torch.codecs``); ``--compare OUT.png`` then also writes
reference | codec | relative-error heat map side by side.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

EXTS_FLOAT = (".exr", ".pfm", ".hdr", ".tif", ".tiff")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a relit diffuse transfer file offscreen (EGL) to PNG/EXR",
        description=(
            "Relight TRANSFER (a diffuse .prt file from `prt precompute`) with LIGHT and render the per-vertex "
            "radiance through pyrender's EGL context into a float framebuffer. The output format follows the "
            "extension: .png (tone-mapped 8-bit sRGB) or .exr/.pfm/.hdr/.tif (linear float). Needs EGL: "
            "PYOPENGL_PLATFORM=egl and the Debian packages libegl1 libegl-mesa0 libgl1-mesa-dri."
        ),
    )
    p.add_argument("transfer", metavar="TRANSFER.prt")
    p.add_argument("--light", default="sky", help="built-in environment, analytic spec or image file (default: sky)")
    p.add_argument("--codec-file", default=None, help="render from this compressed transfer instead (prt compress output)")
    p.add_argument("-o", "--output", required=True, help="output image (.png, .exr, .pfm, .hdr, .tif)")
    p.add_argument("--compare", default=None, metavar="OUT.png",
                   help="with --codec-file: also write reference | codec | error heat map")
    p.add_argument("--width", type=int, default=512)
    p.add_argument("--height", type=int, default=512)
    p.add_argument("--azimuth", type=float, default=35.0, help="camera azimuth in degrees (from +x toward +y)")
    p.add_argument("--elevation", type=float, default=25.0, help="camera elevation in degrees above the xy-plane")
    p.add_argument("--fov", type=float, default=40.0, help="vertical field of view in degrees (perspective)")
    p.add_argument("--orthographic", action="store_true", help="orthographic projection")
    p.add_argument("--exposure", default="auto", help="stops (EV) for PNG output, or 'auto' (default)")
    p.add_argument("--tonemap", default="clip", choices=["clip", "reinhard"])
    p.add_argument("--supersample", type=int, default=2, help="s×s samples per pixel (default 2)")
    p.add_argument("--background", type=float, default=0.0, help="value of uncovered pixels (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def _bands(transfer) -> int:
    from ..sh import band_of_coeffs

    return int(transfer.meta.get("bands", band_of_coeffs(int(transfer.data.shape[-1]), "transfer coefficients per vertex")))


def _decode_codec_file(path: str, transfer):
    """Transfer data reconstructed from a codec file (API of prt_torch.codecs: ``load(path)``
    returning (codec, encoded) or an object with ``decode``)."""
    try:
        from .. import codecs
    except ModuleNotFoundError as e:
        raise ValueError(f"--codec-file needs prt_torch.codecs, which this build does not have ({e})") from None
    loaded = codecs.load(path)
    if isinstance(loaded, tuple) and len(loaded) == 2:
        codec, enc = loaded
        x = codec.decode(enc)
    elif hasattr(loaded, "decode"):
        x = loaded.decode()
    else:
        raise ValueError(f"{path!r}: prt_torch.codecs.load returned {type(loaded).__name__}; "
                         "expected (codec, encoded)")
    x = torch.as_tensor(x)
    if x.numel() != transfer.data.numel():
        raise ValueError(f"{path!r} decodes to {tuple(x.shape)}, which does not match the transfer data "
                         f"{tuple(transfer.data.shape)}; was it compressed from {transfer.mesh.name!r}?")
    from ..transfer import Transfer

    return Transfer(transfer.kind, x.reshape(transfer.data.shape).to(torch.float32), transfer.mesh, dict(transfer.meta))


def _write(path: Path, img, exposure, tonemap, overwrite: bool) -> None:
    from ..lighting import write_image
    from ..render import save_exr, save_png

    ext = path.suffix.lower()
    if ext == ".png":
        save_png(path, img, exposure=exposure, tonemap=tonemap, overwrite=overwrite)
    elif ext == ".exr":
        save_exr(path, img, overwrite=overwrite)
    else:
        write_image(path, img, overwrite=overwrite)


def run(args) -> int:
    from ..lighting.spec import load_light
    from ..render import (Camera, Renderer, RenderUnavailable, auto_exposure, error_heatmap, error_map,
                          side_by_side)
    from ..relight import diffuse_transfer
    from ..transfer import Transfer

    out = Path(args.output)
    ext = out.suffix.lower()
    if ext not in (".png",) + EXTS_FLOAT:
        raise ValueError(f"output {str(out)!r}; accepted extensions: .png, {', '.join(EXTS_FLOAT)}")
    outputs = [out] + ([Path(args.compare)] if args.compare else [])
    if args.compare and not args.codec_file:
        raise ValueError("--compare needs --codec-file (it compares the codec's render with the uncompressed one)")
    if args.compare and Path(args.compare).suffix.lower() != ".png":
        raise ValueError(f"--compare {args.compare!r}; accepted: a .png path")
    for o in outputs:
        if o.exists() and not args.overwrite:
            raise FileExistsError(f"output {str(o)!r} exists; pass --overwrite to replace it")
    if args.exposure != "auto":
        try:
            float(args.exposure)
        except ValueError:
            raise ValueError(f"--exposure {args.exposure!r}; accepted: a number of stops or 'auto'") from None

    transfer = Transfer.load(args.transfer)
    if transfer.kind != "diffuse":
        raise ValueError(f"{args.transfer!r} holds {transfer.kind!r} transfer; `prt render` handles 'diffuse' "
                         "(glossy/MRT need a view direction per vertex: not implemented here yet)")
    light = load_light(args.light, bands=_bands(transfer))
    ref = diffuse_transfer(transfer, light)  # [V, C] float64, Sloan 2002: L_out = t_p · l
    rad = ref
    if args.codec_file:
        rad = diffuse_transfer(_decode_codec_file(args.codec_file, transfer), light)

    mesh = transfer.mesh
    cam = Camera.fit(mesh, azimuth=args.azimuth, elevation=args.elevation, fov=args.fov,
                     projection="orthographic" if args.orthographic else "perspective",
                     aspect=args.width / args.height)
    try:
        with Renderer(args.width, args.height) as r:
            img, mask = r.render_radiance(mesh, rad, cam, background=args.background, supersample=args.supersample)
            ref_img = None
            if args.compare:
                ref_img, _ = r.render_radiance(mesh, ref, cam, background=args.background,
                                               supersample=args.supersample)
    except RenderUnavailable as e:
        print(f"prt render: error: {e}", file=sys.stderr)
        return 3
    base = ref_img if ref_img is not None else img
    ev = auto_exposure(base, mask) if args.exposure == "auto" else float(args.exposure)
    _write(out, img, ev, args.tonemap, args.overwrite)
    print(f"wrote {out} ({args.width}x{args.height}, {int(mask.sum())} covered pixels, "
          f"radiance range [{float(img[mask].min()) if mask.any() else 0:.4g}, "
          f"{float(img[mask].max()) if mask.any() else 0:.4g}], exposure {ev:+.2f} EV)")
    if args.compare:
        e = error_map(img, ref_img, mask, kind="rel")
        vmax = float(np.percentile(e[mask], 99.0)) if mask.any() else 0.0
        vmax = vmax if vmax > 0 else 1.0
        heat = error_heatmap(img, ref_img, mask, kind="rel", vmax=vmax)
        side_by_side([ref_img, img, heat], ["uncompressed", Path(args.codec_file).name,
                                            f"relative error (0..{vmax:.3g})"],
                     exposure=[ev, ev, 0.0], path=args.compare)
        print(f"wrote {args.compare}")
    return 0
