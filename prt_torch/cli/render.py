"""``prt render TRANSFER.prt [--light SPEC] [--codec-file X] [--decode glsl|cpu] -o out.png``:
relight a transfer file of any kind (diffuse, glossy, MRT) with a light and render it offscreen
as a float image (PNG tone-mapped, or EXR/PFM/HDR/TIF float).

``--decode glsl`` (default) decodes in the vertex shader, the way a real-time engine does
(prt_torch.render.glsl: light as uniforms, transfer or per-cluster constants M_k·l as float
tables, per-vertex codec weights as attributes); ``--decode cpu`` draws the per-vertex radiance
the torch engine computed (``relight`` / ``codec.relight``). For view-dependent kinds the camera
eye gives each vertex its local view direction (``relight.local_view`` with the mesh frames).
``--codec-file`` renders from a compressed transfer (refused when it belongs to another
transfer); ``--compare OUT.png`` also writes uncompressed (CPU) | this render | error heat map,
as PNG and as linear EXR (OUT.exr); ``--validate`` renders both decodes and prints their PSNR.

``prt render --method shrm [MESH] --light L --brdf TYPE [--brdf-param k=v] [--epsilon E | --orders
F,P]`` builds a spherical harmonic reflection map (Ramamoorthi 2002 ch. 5, ``shrm.build_shrm``) on
the fly and renders the convex MESH (built-in scene or mesh file; default ``convex``) from it, as
``prt render SHRM.prt --mesh MESH`` renders a saved one; ``--shading pixel`` shades every pixel
from its own normal and view (deferred, CPU decode).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

EXTS_FLOAT = (".exr", ".pfm", ".hdr", ".tif", ".tiff")


def _pixels(flag: str):
    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            v = -1
        if not 1 <= v <= 16384:
            raise argparse.ArgumentTypeError(f"{flag} {text!r}; accepted: an integer number of pixels in 1..16384")
        return v
    return parse


def _finite(flag: str):
    def parse(text: str) -> float:
        try:
            v = float(text)
        except ValueError:
            v = float("nan")
        if not math.isfinite(v):
            raise argparse.ArgumentTypeError(f"{flag} {text!r}; accepted: a finite number")
        return v
    return parse


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "render",
        help="render a relit transfer file (diffuse, glossy, MRT; raw or compressed) offscreen (EGL) to PNG/EXR",
        description=(
            "Relight TRANSFER (a .prt file from `prt precompute`: diffuse, glossy or mrt) with LIGHT, optionally from "
            "a compressed form (--codec-file, from `prt compress`), and render it through pyrender's EGL context into "
            "a float framebuffer, decoded in GLSL (--decode glsl) or on the CPU (--decode cpu). The output format "
            "follows the extension: .png (tone-mapped 8-bit sRGB) or .exr/.pfm/.hdr/.tif (linear float). An SHRM file "
            "(`prt shrm`) shades a convex --mesh instead; --method shrm [MESH] --light L --brdf TYPE [--epsilon E | --orders "
            "F,P] builds the spherical harmonic reflection map (Ramamoorthi 2002 ch. 5) on the fly and shades MESH from it. "
            "Needs EGL: PYOPENGL_PLATFORM=egl and the Debian packages libegl1 libegl-mesa0 libgl1-mesa-dri."
        ),
    )
    p.add_argument("transfer", metavar="TRANSFER.prt|MESH", nargs="?", default=None,
                   help="a transfer or SHRM file; with --method shrm the convex mesh to shade (built-in scene or mesh "
                        "file, default: the built-in 'convex')")
    p.add_argument("--method", default="transfer", choices=["transfer", "shrm"],
                   help="transfer: render TRANSFER.prt (default); shrm: build a spherical harmonic reflection map "
                        "(Ramamoorthi 2002 ch. 5) of --brdf under --light on the fly and shade MESH from it")
    p.add_argument("--light", default=None,
                   help="built-in environment, analytic spec or image file (default: sky); an SHRM file carries its own")
    p.add_argument("--brdf", default=None, metavar="TYPE",
                   help="--method shrm: the isotropic reflectance model (lambertian, phong, blinn_phong, microfacet, "
                        "ashikhmin_shirley, ward)")
    p.add_argument("--brdf-param", action="append", default=[], metavar="NAME=VALUE",
                   help="--method shrm: a model parameter, repeatable (sigma=0.2, s=32 form=reflection, kd=0.8)")
    p.add_argument("--epsilon", type=_finite("--epsilon"), default=None,
                   help="--method shrm: accepted BRDF energy loss in (0, 1), orders by eq. 5.18 (default 0.03)")
    p.add_argument("--orders", default=None, metavar="F,P", help="--method shrm: the orders F_B,P_B instead of --epsilon")
    p.add_argument("--map-size", type=_pixels("--map-size"), default=64,
                   help="--method shrm: map height H of the lat-long maps H x 2H (default 64)")
    p.add_argument("--no-clamp", action="store_true",
                   help="SHRMs: keep the truncated series' negative radiance (ringing) instead of clamping it at 0")
    p.add_argument("--shading", default="vertex", choices=["vertex", "pixel"],
                   help="SHRMs: vertex (each vertex's normal and view, interpolated; default) or pixel (each pixel's "
                        "interpolated normal and its view, shaded on the CPU: --decode cpu)")
    p.add_argument("--codec-file", default=None, help="render from this compressed transfer (prt compress output)")
    p.add_argument("--decode", default=None, choices=["glsl", "cpu"],
                   help="glsl: decode in the vertex shader (default); cpu: per-vertex radiance from the torch engine")
    p.add_argument("--mesh", default=None, metavar="MESH",
                   help="SHRM files (prt shrm output) only: the convex object to shade, a built-in scene NAME or "
                        "NAME:SIZE or a mesh file (default: the built-in 'convex'); each vertex is shaded from the SHRM's maps for its normal "
                        "and its view towards the camera")
    p.add_argument("-o", "--output", required=True, help="output image (.png, .exr, .pfm, .hdr, .tif)")
    p.add_argument("--compare", default=None, metavar="OUT.png",
                   help="also write uncompressed (CPU) | this render | relative-error heat map (OUT.png and OUT.exr); "
                        "a wavelet transfer with --terms: every term of the light | N terms | error")
    p.add_argument("--terms", type=int, default=None,
                   help="wavelet transfers: the light's N largest Haar terms (default: all 6R², exact; Ng 2003)")
    p.add_argument("--selection", default=None, choices=["magnitude", "area", "transport"],
                   help="wavelet transfers: how the N terms are chosen (Ng 2003 §5; default transport-weighted)")
    p.add_argument("--validate", action="store_true",
                   help="also render with the other decode and print GLSL vs CPU PSNR (exit 1 below 50 dB)")
    p.add_argument("--width", type=_pixels("--width"), default=512, help="image width in pixels (1..16384)")
    p.add_argument("--height", type=_pixels("--height"), default=512, help="image height in pixels (1..16384)")
    p.add_argument("--azimuth", type=float, default=35.0, help="camera azimuth in degrees (from +x toward +y)")
    p.add_argument("--elevation", type=float, default=25.0, help="camera elevation in degrees above the xy-plane")
    p.add_argument("--fov", type=float, default=40.0, help="vertical field of view in degrees (perspective)")
    p.add_argument("--orthographic", action="store_true", help="orthographic projection")
    p.add_argument("--exposure", default="auto", help="stops (EV) for PNG output, or 'auto' (default)")
    p.add_argument("--tonemap", default="clip", choices=["clip", "reinhard"])
    p.add_argument("--supersample", type=int, default=2, help="s×s samples per pixel (default 2)")
    p.add_argument("--background", type=_finite("--background"), default=0.0, help="value of uncovered pixels (default 0)")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


VALIDATE_DB = 50.0


def _bands(transfer) -> int:
    from ..sh import band_of_coeffs

    return band_of_coeffs(int(transfer.data.shape[-1]), "transfer coefficients per vertex")


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


def _linear_composite(panels: list[np.ndarray], gap: int = 4) -> np.ndarray:
    """Float panels ``[H, W, 3]`` side by side with NaN gaps (linear, for EXR)."""
    h = panels[0].shape[0]
    sep = np.full((h, gap, 3), np.nan, np.float32)
    parts = []
    for i, p in enumerate(panels):
        parts += ([sep] if i else []) + [p.astype(np.float32)]
    return np.concatenate(parts, 1)


SHRM_ONLY = ("--brdf", "--brdf-param", "--epsilon", "--orders", "--map-size")


def _check_method(args) -> None:
    """Options that belong to the other method, refused before any work (one line each)."""
    given = {"--brdf": args.brdf is not None, "--brdf-param": bool(args.brdf_param), "--epsilon": args.epsilon is not None,
             "--orders": args.orders is not None, "--map-size": args.map_size != 64}
    if args.method != "shrm":
        if args.transfer is None:
            raise ValueError("TRANSFER.prt is missing; accepted: a transfer or SHRM file, or --method shrm [MESH] --brdf TYPE")
        extra = [k for k in SHRM_ONLY if given[k]]
        if extra:
            raise ValueError(f"{', '.join(extra)}: only with --method shrm (an SHRM built on the fly); accepted for "
                             f"{args.transfer!r}: drop them, or add --method shrm with a mesh")
        return
    if args.brdf is None:
        raise ValueError("--method shrm needs --brdf TYPE (e.g. --brdf microfacet --brdf-param sigma=0.2)")
    if args.epsilon is not None and args.orders is not None:
        raise ValueError(f"--epsilon {args.epsilon:g} and --orders {args.orders!r} both given; accepted: one of them")
    if args.epsilon is not None and not 0 < args.epsilon < 1:
        raise ValueError(f"--epsilon {args.epsilon:g}; accepted: a number in (0, 1) (the BRDF energy the SHRM may lose)")
    if args.codec_file or args.compare:
        raise ValueError("--codec-file and --compare apply to transfers; accepted with --method shrm: -o, --light, --brdf, "
                         "--brdf-param, --epsilon/--orders, --map-size, --shading, --decode, --validate, camera and image options")
    if args.transfer is not None and args.mesh is not None:
        raise ValueError(f"the mesh given twice (MESH {args.transfer!r} and --mesh {args.mesh!r}); accepted: one of them")


def _check_shading(args) -> None:
    if args.shading == "pixel":
        if args.decode == "glsl":
            raise ValueError("--shading pixel is shaded on the CPU (deferred, per pixel); accepted: --decode cpu, or "
                             "--shading vertex for the GLSL decoder")
        if args.validate:
            raise ValueError("--validate compares the GLSL and CPU vertex decodes; accepted with --shading vertex")
        args.decode = "cpu"
    args.decode = args.decode or "glsl"


def run(args) -> int:
    from ..lighting.spec import load_light
    from ..render import (Camera, PRTScene, Renderer, RenderUnavailable, check_codec_file)
    from ..transfer import Transfer

    _check_method(args)
    out = Path(args.output)
    ext = out.suffix.lower()
    if ext not in (".png",) + EXTS_FLOAT:
        raise ValueError(f"output {str(out)!r}; accepted extensions: .png, {', '.join(EXTS_FLOAT)}")
    cmp_png = Path(args.compare) if args.compare else None
    if cmp_png is not None and cmp_png.suffix.lower() != ".png":
        raise ValueError(f"--compare {args.compare!r}; accepted: a .png path (the linear EXR goes next to it)")
    from ..io import check_outputs

    check_outputs({"-o/--output": out, "--compare": cmp_png, "--compare (its linear EXR)": cmp_png and cmp_png.with_suffix(".exr")},
                  {"TRANSFER": args.transfer if args.method != "shrm" else None, "MESH": args.transfer if args.method == "shrm" else None,
                   "--mesh": args.mesh, "--codec-file": args.codec_file, "--light": args.light},
                  args.overwrite)  # before any rendering
    if args.exposure != "auto":
        try:
            float(args.exposure)
        except ValueError:
            raise ValueError(f"--exposure {args.exposure!r}; accepted: a number of stops or 'auto'") from None

    if args.terms is not None and args.terms < 1:
        raise ValueError(f"--terms {args.terms}; accepted: N >= 1 Haar terms of the light (wavelet transfers)")
    from .relight import wavelet_options_only

    if args.method == "shrm" or Path(args.transfer).is_dir():
        wavelet_options_only(args, "SHRMs and transport tables take the light in SH")
    if args.method == "shrm":
        return _run_shrm(args, out, cmp_png)
    shading_error = ValueError(f"{'--shading pixel' if args.shading != 'vertex' else '--no-clamp'} applies to SHRMs (a file "
                               "from prt shrm, or --method shrm); accepted for transfers: neither --shading pixel nor --no-clamp")
    if Path(args.transfer).is_dir():  # Green 2005 transport tables (a directory): gaussian or other codec files
        if args.shading != "vertex" or args.no_clamp:
            raise shading_error
        args.decode = args.decode or "glsl"
        return _run_transport(args, out, cmp_png)
    from ..io import load_meta

    if load_meta(args.transfer).get("kind") == "shrm":
        wavelet_options_only(args, "SHRMs take the light in SH")
        return _run_shrm(args, out, cmp_png)
    if args.shading != "vertex" or args.no_clamp:
        raise shading_error
    if args.mesh is not None:
        raise ValueError(f"--mesh {args.mesh!r} applies to SHRM files (prt shrm output); {args.transfer!r} is a transfer, "
                         "which carries its own mesh")
    transfer = Transfer.load(args.transfer)
    if transfer.kind == "wavelet":
        return _run_wavelet(args, transfer, out, cmp_png)
    wavelet_options_only(args, f"a {transfer.kind} transfer takes the light in its own SH bands")
    args.decode = args.decode or "glsl"
    scene = PRTScene(transfer)  # refuses kinds it cannot relight, naming the accepted ones
    codec = enc = None
    if args.codec_file:
        codec, enc = check_codec_file(args.codec_file, scene)
    light = load_light(args.light or "sky", bands=_bands(transfer))
    mesh = transfer.mesh
    cam = Camera.fit(mesh, azimuth=args.azimuth, elevation=args.elevation, fov=args.fov,
                     projection="orthographic" if args.orthographic else "perspective",
                     aspect=args.width / args.height)
    view = scene.view(cam.eye)  # per-vertex view weights (None for diffuse)
    rs = dict(background=args.background, supersample=args.supersample)
    try:
        with Renderer(args.width, args.height) as r:
            def draw(decode, c, e):
                if decode == "glsl":
                    return r.render(mesh, scene.decoder(light, view, c, e), cam, **rs)
                return r.render_radiance(mesh, scene.cpu_radiance(light, view, c, e), cam, **rs)

            img, mask = draw(args.decode, codec, enc)
            ref_img = draw("cpu", None, None)[0] if cmp_png else None
            other = draw("cpu" if args.decode == "glsl" else "glsl", codec, enc) if args.validate else None
    except RenderUnavailable as e:
        print(f"prt render: error: {e}", file=sys.stderr)
        return 3
    what = f"{transfer.kind} transfer" + (f", codec {codec.codec_name}" if codec is not None else "")
    return _write_outputs(args, out, cmp_png, img, mask, ref_img, other, what)


def _run_wavelet(args, transfer, out: Path, cmp_png: Path | None) -> int:
    """``prt render WAVELET.prt --light SPEC [--terms N] [--selection S] [--compare CMP.png]``: the exit
    radiance of the sparse Haar relighting (the light rasterised on the transfer's cube, its N largest
    terms by S — Ng et al. 2003 §5 —, all 6R² by default: exact) drawn per vertex; ``--compare`` puts the
    render with every term beside it, with the relative-error map (what the N-term light approximation
    costs, per pixel). CPU decode only: the terms a light keeps change with every light, which Ng et al.
    2003 leave to the CPU (course notes 2005: "not well-suited to hardware rendering")."""
    from .relight import radiance
    from ..render import Camera, Renderer, RenderUnavailable

    if args.decode == "glsl" or args.validate or args.codec_file:
        raise ValueError("a wavelet transfer renders with --decode cpu only (no GLSL decoder: the light's terms change "
                         "with every light, Ng et al. 2003); --codec-file and --validate do not apply")
    if cmp_png is not None and args.terms is None:
        raise ValueError(f"--compare {args.compare!r} for a wavelet transfer compares N light terms with all of them; "
                         "accepted: with --terms N")
    args.decode = "cpu"
    selection = args.selection or "transport"
    rec: dict = {}
    rad, what = radiance(transfer, args.light, terms=args.terms, selection=selection, record=rec)
    ref = radiance(transfer, args.light)[0] if cmp_png is not None else None  # every term: the exact result
    mesh = transfer.mesh
    cam = Camera.fit(mesh, azimuth=args.azimuth, elevation=args.elevation, fov=args.fov,
                     projection="orthographic" if args.orthographic else "perspective", aspect=args.width / args.height)
    try:
        with Renderer(args.width, args.height) as r:
            img, mask = r.render_radiance(mesh, rad, cam, background=args.background, supersample=args.supersample)
            ref_img = (r.render_radiance(mesh, ref, cam, background=args.background, supersample=args.supersample)[0]
                       if ref is not None else None)
    except RenderUnavailable as e:
        print(f"prt render: error: {e}", file=sys.stderr)
        return 3
    return _write_outputs(args, out, cmp_png, img, mask, ref_img, None, what,
                          labels=("all light terms (exact)", f"{rec.get('terms', args.terms)} terms ({selection})"))


def _write_outputs(args, out: Path, cmp_png: Path | None, img, mask, ref_img, other, what: str,
                   labels: tuple[str, str] | None = None) -> int:
    """Write the image, the optional comparison (PNG + linear EXR) and the GLSL-vs-CPU check.
    ``labels``: the comparison's reference and render captions (default: the uncompressed CPU render
    and the codec file or 'uncompressed', with the decode)."""
    from ..render import auto_exposure, error_heatmap, error_map, psnr, side_by_side

    base = ref_img if ref_img is not None else img
    ev = auto_exposure(base, mask) if args.exposure == "auto" else float(args.exposure)
    _write(out, img, ev, args.tonemap, args.overwrite)
    print(f"wrote {out} ({args.width}x{args.height}, {what}, decoded by {args.decode}, {int(mask.sum())} covered "
          f"pixels, radiance range [{float(img[mask].min()) if mask.any() else 0:.4g}, "
          f"{float(img[mask].max()) if mask.any() else 0:.4g}], exposure {ev:+.2f} EV)")
    status = 0
    if other is not None:
        o_img, o_mask = other
        same = bool(np.array_equal(mask, o_mask))
        db = psnr(img, o_img, mask & o_mask) if (mask & o_mask).any() else float("nan")
        ok = same and db >= VALIDATE_DB
        print(f"GLSL vs CPU: {db:.1f} dB (same coverage: {'yes' if same else 'NO'}; threshold {VALIDATE_DB:.0f} dB) "
              f"-> {'ok' if ok else 'FAILED'}")
        status = 0 if ok else 1
    if cmp_png is not None:
        e = error_map(img, ref_img, mask, kind="rel")
        vmax = float(np.percentile(e[mask], 99.0)) if mask.any() else 0.0
        vmax = vmax if vmax > 0 else 1.0
        heat = error_heatmap(img, ref_img, mask, kind="rel", vmax=vmax)
        ref_label, label = labels or ("uncompressed (cpu)",
                                      (Path(args.codec_file).name if args.codec_file else "uncompressed") + f" ({args.decode})")
        db = psnr(img, ref_img, mask) if mask.any() else float("nan")
        side_by_side([ref_img, img, heat], [ref_label, f"{label}, {db:.1f} dB",
                                            f"relative error (0..{vmax:.3g})"],
                     exposure=[ev, ev, 0.0], path=cmp_png)
        abserr = np.nan_to_num(error_map(img, ref_img, mask, kind="abs"), nan=0.0).astype(np.float32)
        _write(cmp_png.with_suffix(".exr"), _linear_composite([ref_img, img, np.repeat(abserr[:, :, None], 3, 2)]),
               ev, args.tonemap, args.overwrite)
        print(f"wrote {cmp_png} and {cmp_png.with_suffix('.exr')} (linear: reference | render | |error|), "
              f"PSNR vs {'uncompressed' if labels is None else labels[0]} {db:.1f} dB")
    return status


def _run_shrm(args, out: Path, cmp_png: Path | None) -> int:
    """A convex object shaded from a spherical harmonic reflection map (Ramamoorthi 2002 eq. 5.10):
    ``prt render SHRM.prt [--mesh MESH]`` (a saved SHRM; ``--light`` refused, the SHRM carries its
    light) or ``prt render --method shrm [MESH] --light L --brdf TYPE [--brdf-param k=v]
    [--epsilon E | --orders F,P]`` (built on the fly, ``shrm.build_shrm``). Per vertex (its normal's
    axis and its view towards the eye; orthographic: the camera's direction), decoded in GLSL
    (``render.shrm.SHRMDecoder``, default) or on the CPU (``SHRM.radiance``); ``--shading pixel``:
    per pixel from the interpolated normal and the pixel's view (CPU, ``render.shrm.render_shrm``).
    ``--validate`` renders both vertex decodes and prints their PSNR. A mesh the self-occlusion
    probe finds shadowed gets a one-line warning (an SHRM ignores visibility)."""
    import warnings

    from .. import shrm as S
    from ..brdf import from_spec
    from ..params import parse_assignments
    from ..render import Camera, Renderer, RenderUnavailable
    from ..render.shrm import render_shrm
    from ..scene import RayCaster, load_scene
    from ..transfer.diffuse import probe_self_occlusion
    from .shrm import parse_orders

    if args.method != "shrm" and (args.codec_file or cmp_png is not None):
        raise ValueError("--codec-file and --compare apply to transfers; accepted for an SHRM: -o, --mesh, --decode, "
                         "--shading, --validate, the camera and image options")
    if args.method != "shrm" and args.light is not None:
        raise ValueError(f"--light {args.light!r}: the SHRM {args.transfer!r} carries the light it was computed for; accepted: "
                         "no --light, or --method shrm --brdf TYPE --light L to build one under another light")
    _check_shading(args)
    name = (args.transfer if args.method == "shrm" else None) or args.mesh or "convex"
    param = "MESH" if args.method == "shrm" and args.transfer else "--mesh"
    if args.method == "shrm":  # every check of the SHRM's inputs before the mesh, the probe or the build
        brdf = S.check_brdf(from_spec({"type": args.brdf, **parse_assignments(args.brdf_param, what="--brdf-param")}))
        orders = parse_orders(args.orders) if args.orders is not None else None
    mesh = load_scene(name, param=param)  # the one rule for naming a mesh (prt_torch.scene.check_scene), before the build
    if args.method == "shrm":
        m = S.build_shrm(brdf, args.light or "sky", epsilon=args.epsilon if args.epsilon is not None else 0.03, orders=orders,
                         height=args.map_size)
    else:
        m = S.load_shrm(args.transfer)
        if m.maps is None:
            raise ValueError(f"SHRM {args.transfer!r} has no maps; accepted: a file written by prt shrm")
    caster = RayCaster(mesh, workers=1)
    try:  # an SHRM has no visibility (§5.3): say how much a non-convex mesh shadows itself
        probe = probe_self_occlusion(caster, mesh)
    finally:
        caster.close()
    if probe["occluded_fraction"] > S.CONVEX_PROBE_TOL:
        warnings.warn(f"mesh {name!r} is not convex: the self-occlusion probe finds {probe['occluded_fraction']:.3g} of the "
                      f"diffuse energy shadowed ({probe['occluded_rays']} of {probe['rays']} rays); an SHRM ignores "
                      "visibility (Ramamoorthi 2002 §5.3), so shadowed regions are shaded as if unoccluded")
    cam = Camera.fit(mesh, azimuth=args.azimuth, elevation=args.elevation, fov=args.fov,
                     projection="orthographic" if args.orthographic else "perspective", aspect=args.width / args.height)
    rs = dict(background=args.background, supersample=args.supersample)
    try:
        with Renderer(args.width, args.height) as r:
            rs["clamp"] = not args.no_clamp
            img, mask = render_shrm(r, m, mesh, cam, decode=args.decode, shading=args.shading, **rs)
            other = (render_shrm(r, m, mesh, cam, decode="cpu" if args.decode == "glsl" else "glsl", **rs)
                     if args.validate else None)
    except RenderUnavailable as e:
        print(f"prt render: error: {e}", file=sys.stderr)
        return 3
    what = (f"SHRM F_B={m.F_B} P_B={m.P_B} (energy {m.meta['energy']:.4f}) on {name}, {args.shading} shading, "
            + ("unclamped" if args.no_clamp else "clamped at 0"))
    return _write_outputs(args, out, None, img, mask, None, other, what)


def _run_transport(args, out: Path, cmp_png: Path | None) -> int:
    """``prt render TABLE_DIR [--codec-file F]``: transport tables (Green 2005) relit toward the
    camera through the harness's evaluator — the three nearest stored views, zero below each
    vertex's horizon — uncompressed (CPU only) or from a codec file (CPU, or GLSL with the
    codec's decoder, e.g. the Gaussian prefiltered lookups)."""
    import torch

    from .. import codecs
    from ..harness.evaluate import Evaluator, load_directory_transfer
    from ..lighting.spec import load_light
    from ..render import Camera, Renderer, RenderUnavailable, codec_decoder

    tr = load_directory_transfer(args.transfer)
    ev = Evaluator(tr)
    codec = enc = None
    if args.codec_file:
        codec, enc = codecs.load(args.codec_file)
        if enc.points != ev.V or enc.meta.get("dim") != ev.X.shape[1]:
            raise ValueError(f"codec file {args.codec_file!r} ({enc.points} points × {enc.meta.get('dim')}) does not belong to "
                             f"the transport table {args.transfer!r} ({ev.V} vertices × {ev.X.shape[1]}); accepted: a codec "
                             "file compressed from this table")
    if args.decode == "glsl" and codec is None:
        raise ValueError("uncompressed transport tables have no GLSL decoder; accepted: --decode cpu, or --codec-file "
                         "with a codec that has one (e.g. gaussian)")
    light = load_light(args.light or "sky", bands=ev.bands_in)
    mesh = tr.mesh
    cam = Camera.fit(mesh, azimuth=args.azimuth, elevation=args.elevation, fov=args.fov,
                     projection="orthographic" if args.orthographic else "perspective", aspect=args.width / args.height)
    view = ev.view_weights(torch.as_tensor(np.asarray(cam.eye, np.float64)))
    rs = dict(background=args.background, supersample=args.supersample)

    def rgb(x):
        return x.expand(-1, 3) if x.shape[1] == 1 else x

    try:
        with Renderer(args.width, args.height) as r:
            def draw(decode, use_codec):
                if not use_codec:
                    return r.render_radiance(mesh, rgb(ev.uncompressed(light, view)), cam, **rs)
                Lc = ev.codec_light(codec, light)
                if decode == "glsl":
                    return r.render(mesh, codec_decoder(codec, enc, Lc, mode="taps", view=view), cam, **rs)
                return r.render_radiance(mesh, rgb(ev.finish(codec.relight(enc, Lc, view=view))), cam, **rs)

            img, mask = draw(args.decode, codec is not None)
            ref_img = draw("cpu", False)[0] if cmp_png else None
            other = draw("cpu" if args.decode == "glsl" else "glsl", True) if (args.validate and codec is not None) else None
    except RenderUnavailable as e:
        print(f"prt render: error: {e}", file=sys.stderr)
        return 3
    what = "transport tables" + (f", codec {codec.codec_name}" if codec is not None else "")
    return _write_outputs(args, out, cmp_png, img, mask, ref_img, other, what)
