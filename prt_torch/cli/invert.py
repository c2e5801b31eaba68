"""``prt invert``: lighting, material or both from images of a known mesh (Ramamoorthi 2002 ch. 6),
through the engine's transfer (shadows and interreflection included). docs/inverse.md."""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

import numpy as np
import torch

UNKNOWNS = ("light", "brdf", "both")
KINDS = ("diffuse", "glossy", "mrt")  # the transfer kinds --kind precomputes (the rows of inverse.light.corner_rows)
#: --brdf values; QUADRATURE: fitted through the per-pixel hemisphere quadrature (inverse.brdf_fit)
BRDF_TYPES = ("lambertian", "phong", "microfacet", "ashikhmin-shirley", "ashikhmin-shirley-anisotropic", "sh")
QUADRATURE = ("microfacet", "ashikhmin-shirley", "ashikhmin-shirley-anisotropic", "sh")
MAX_PIXELS_QUADRATURE = 3000  # default pixel subset of the quadrature fits (P·(Q+1)(2Q+1) BRDF values per step)


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "invert",
        help="recover SH lighting, BRDF parameters or both from images of a known mesh (Ramamoorthi 2002 ch. 6)",
        description=(
            "Inverse rendering. The images and their cameras come from a NeRF/Blender transforms.json (file_path "
            "relative to it; camera_angle_x or fl_x/fl_y/cx/cy; 4x4 camera-to-world, OpenGL axes); pixels are traced "
            "to the mesh with Embree, pixels off the mesh or with alpha 0 are masked. --unknown light: linear least "
            "squares through the transfer (regularisation by GCV or the L-curve) and a well-posedness report per "
            "band; brdf: reflection-form Phong kd/ks/s under --light (autograd Levenberg-Marquardt); both: light and "
            "Phong with the ambiguities fixed (kd+ks=1, grey BRDF). The output JSON holds the light in prt light "
            "--json's layout (usable as --light anywhere). docs/inverse.md."
        ),
    )
    p.add_argument("--mesh", required=True, metavar="MESH", help="mesh file or built-in scene NAME or NAME:SIZE (the known geometry)")
    p.add_argument("--cameras", required=True, metavar="transforms.json", help="NeRF/Blender cameras and image paths")
    p.add_argument("--unknown", required=True, choices=UNKNOWNS, help="what to recover")
    p.add_argument("--bands", type=int, default=3, help="SH bands of the light (n² unknowns per channel; default 3)")
    p.add_argument("--albedo", default=None, metavar="A", help="known diffuse albedo: one value or r,g,b (default: the "
                   "mesh's, 0.8 grey for built-ins)")
    p.add_argument("--brdf", default="lambertian", metavar="TYPE",
                   help="reflectance model: lambertian (default; the transfer's), phong (reflection form, eq. 6.12); "
                        "with --unknown brdf also microfacet (eq. 5.34 + Lambertian), ashikhmin-shirley (isotropic n), "
                        "ashikhmin-shirley-anisotropic (nu, nv) or sh (SH BRDF coefficients by linear least squares)")
    p.add_argument("--brdf-param", action="append", default=[], metavar="NAME=VALUE",
                   help="a known BRDF parameter, repeatable, held fixed by --unknown brdf: kd ks s (phong); kd ks sigma "
                        "(microfacet); rd rs n (ashikhmin-shirley); rd rs nu nv (-anisotropic)")
    p.add_argument("--brdf-bands", type=int, default=None, metavar="N",
                   help="--brdf sh: SH bands of the BRDF on the view and the light side (default --bands)")
    p.add_argument("--brdf-quad", type=int, default=16, metavar="Q",
                   help="microfacet, ashikhmin-shirley, sh: the per-pixel hemisphere rule gauss_hemisphere(Q), (Q+1)(2Q+1) "
                        "directions (default 16)")
    p.add_argument("--light", default=None, metavar="SPEC", help="the known light (--unknown brdf): built-in, image, "
                   "analytic spec or a light JSON (prt light --json / prt invert output)")
    p.add_argument("--bounces", type=int, default=0, help="interreflection bounces in the precomputed transfer (default 0)")
    p.add_argument("--samples", type=int, default=512, help="directions per vertex of the precomputed transfer")
    p.add_argument("--transfer", default=None, metavar="T.prt", help="transfer of this mesh (else precomputed: --kind)")
    p.add_argument("--kind", choices=KINDS, default=None,
                   help="the transfer precomputed when no --transfer is given (--unknown light): diffuse (default; shadowed, "
                        "--bounces), glossy (Sloan 2003 exit transfer) or mrt (Lehtinen & Kautz 2003), with the BRDF "
                        "--transfer-brdf and --bands-out, --tents as prt precompute takes them")
    p.add_argument("--transfer-brdf", default=None, metavar="TYPE",
                   help="BRDF of a precomputed glossy/MRT transfer (prt precompute's --brdf: phong, blinn_phong, "
                        "ashikhmin_shirley, ward, lambertian; default the kind's)")
    p.add_argument("--transfer-brdf-param", action="append", default=[], metavar="NAME=VALUE",
                   help="a parameter of --transfer-brdf, repeatable (e.g. s=16 ks=0.5 kd=0.5)")
    p.add_argument("--bands-out", type=int, default=None, help="exit-radiance SH bands of a precomputed glossy/MRT "
                   "transfer (default the kind's)")
    p.add_argument("--tents", type=int, default=None, help="M, the MxM tent basis of a precomputed MRT transfer "
                   "(default the kind's)")
    p.add_argument("--regularizer", choices=("gcv", "lcurve"), default="gcv",
                   help="how the Tikhonov weight is chosen from the data (default gcv)")
    p.add_argument("--positive", action="store_true",
                   help="constrain the recovered light's radiance to be >= 0 over the sphere (Ramamoorthi eq. 6.24, as hard "
                        "constraints; same regularisation). Off by default: it helps when the light is smooth and the images "
                        "filter bands away, and biases the fit when the light has detail beyond --bands (docs/inverse.md)")
    p.add_argument("--max-pixels", type=int, default=None, help="use a random subset of this many pixels")
    p.add_argument("-o", "--output", required=True, metavar="RESULT.json")
    p.add_argument("--report", default=None, metavar="DIR", help="write input | re-rendered | error images per view")
    p.add_argument("--overwrite", action="store_true", help="replace existing outputs")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def _albedo(text: str | None):
    if text is None:
        return None
    from ..params import parse_value

    v = parse_value(text)
    vals = v if isinstance(v, list) else [v]
    if len(vals) not in (1, 3) or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and 0 <= x <= 1
                                          and math.isfinite(x) for x in vals):
        raise ValueError(f"--albedo {text!r}; accepted: one value or r,g,b in [0, 1]")
    return vals[0] if len(vals) == 1 else vals


def _brdf(args) -> dict:
    from ..brdf import MODELS
    from ..params import parse_assignments

    from ..inverse.brdf_fit import PARAMETERS

    name = args.brdf.lower()
    if name not in BRDF_TYPES:
        known = ", ".join(sorted(MODELS))
        raise ValueError(f"--brdf {args.brdf!r}; accepted: {', '.join(BRDF_TYPES)} (inverse rendering fits these; the "
                         f"engine knows {known})")
    params = parse_assignments(args.brdf_param, what="--brdf-param")
    allowed = {"lambertian": set(), "phong": {"kd", "ks", "s"}, "sh": set(),
               **{k: {p[0] for p in v} for k, v in PARAMETERS.items()}}[name]
    bounds = {p[0]: (p[2], p[3]) for v in PARAMETERS.values() for p in v}
    for k, v in params.items():
        if k not in allowed:
            raise ValueError(f"--brdf-param {k}={v!r}; accepted for {name}: {', '.join(sorted(allowed)) or 'none'}")
        lo, hi = bounds.get(k, (0.0, math.inf))
        if k in ("s", "sigma", "n", "nu", "nv"):
            lo = max(lo, 1e-300)  # a lobe width must be positive
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not lo <= v <= hi:
            raise ValueError(f"--brdf-param {k}={v!r}; accepted: a finite number in [{lo:g}, {hi:g}]"
                             + (" (> 0)" if k in ("s", "sigma", "n", "nu", "nv") else ""))
    return {"type": name, **params}


def _check_args(args, brdf: dict) -> None:
    from .._checks import check_int

    check_int("--bands", args.bands, 1, 16)
    check_int("--bounces", args.bounces, 0, 16)
    check_int("--samples", args.samples, 1, 1 << 20)
    if args.max_pixels is not None:
        check_int("--max-pixels", args.max_pixels, 1)
    if args.unknown == "brdf":
        if args.light is None:
            raise ValueError("--unknown brdf needs the known light: --light SPEC")
        if brdf["type"] == "lambertian":
            raise ValueError(f"--unknown brdf with --brdf {brdf['type']}; accepted: --brdf "
                             f"{', '.join(t for t in BRDF_TYPES if t != 'lambertian')} (the fitted models)")
    if args.brdf_bands is not None:
        check_int("--brdf-bands", args.brdf_bands, 1, 8)
        if brdf["type"] != "sh":
            raise ValueError(f"--brdf-bands {args.brdf_bands} with --brdf {brdf['type']}; accepted: --brdf sh only")
    check_int("--brdf-quad", args.brdf_quad, 2, 128)
    if brdf["type"] in QUADRATURE and (args.transfer is not None or args.bounces):
        given = "--transfer" if args.transfer is not None else f"--bounces {args.bounces}"
        raise ValueError(f"{given} with --brdf {brdf['type']}: that fit integrates each pixel's direct light itself (no "
                         "transfer, no interreflection); accepted: without it, or --brdf phong")
    if args.unknown != "brdf" and brdf["type"] in QUADRATURE:
        raise ValueError(f"--unknown {args.unknown} with --brdf {brdf['type']}; accepted: --unknown brdf (the light "
                         "with a known BRDF or both unknown use --brdf lambertian or phong)")
    if args.unknown == "both" and brdf["type"] != "phong":
        raise ValueError(f"--unknown both with --brdf {brdf['type']}; accepted: --brdf phong (a Lambertian object under "
                         "unknown light is --unknown light with a known albedo)")
    if args.positive and args.unknown != "light":
        raise ValueError(f"--positive with --unknown {args.unknown}; accepted: --unknown light (the constraint is on the "
                         "recovered light)")
    if args.unknown == "light" and args.light is not None:
        raise ValueError("--light is the known light of --unknown brdf; with --unknown light it is what is recovered")
    if args.unknown == "light" and brdf["type"] == "phong" and not {"kd", "ks", "s"} <= set(brdf):
        raise ValueError("--unknown light with --brdf phong needs its parameters: --brdf-param kd=.. ks=.. s=..")


def _kind_params(args, brdf: dict) -> tuple[str, dict] | None:
    """The precompute ``prt invert`` runs when no ``--transfer`` is given: (kind, parameters), the
    parameters checked by the transfer registry (``TransferKind.validate``) before any work; None
    with ``--transfer``. Options of another kind or a combination that does not apply: one line."""
    from ..params import parse_assignments
    from ..transfer import get_kind

    glossy_opts = [f for f, v in (("--transfer-brdf", args.transfer_brdf), ("--transfer-brdf-param", args.transfer_brdf_param),
                                  ("--bands-out", args.bands_out), ("--tents", args.tents)) if v not in (None, [])]
    if args.transfer is not None:
        if args.kind is not None or glossy_opts:
            raise ValueError(f"{args.kind and '--kind ' + args.kind or glossy_opts[0]} with --transfer {args.transfer!r}; "
                             "accepted: one of them (--kind and its options choose the transfer precomputed when no "
                             "--transfer is given)")
        return None
    kind = args.kind or "diffuse"
    if kind == "diffuse":
        if glossy_opts:
            raise ValueError(f"{glossy_opts[0]} with --kind diffuse; accepted: --kind glossy or mrt (options of the "
                             "precomputed glossy/MRT transfer)")
        return kind, {}
    if args.unknown != "light":
        raise ValueError(f"--kind {kind} with --unknown {args.unknown}; accepted: --unknown light (the BRDF fits use a "
                         "diffuse transfer)")
    if brdf["type"] != "lambertian":
        raise ValueError(f"--kind {kind} with --brdf {brdf['type']}; accepted: --transfer-brdf for the BRDF of a {kind} "
                         "transfer (--brdf phong fits eq. 6.12 on a diffuse one)")
    if args.tents is not None and kind != "mrt":
        raise ValueError(f"--tents with --kind {kind}; accepted: --kind mrt")
    params: dict = {"bands": args.bands, "samples": args.samples, "bounces": args.bounces}
    if args.transfer_brdf is not None or args.transfer_brdf_param:
        params["brdf"] = {"type": args.transfer_brdf or "ashikhmin_shirley",  # the precompute's default model, as prt precompute
                          **parse_assignments(args.transfer_brdf_param, what="--transfer-brdf-param")}
    if args.bands_out is not None:
        params["bands_out"] = args.bands_out
    if args.tents is not None:
        params["M"] = args.tents
    names = {"M": "--tents", "bands_out": "--bands-out", "brdf": "--transfer-brdf", "samples": "--samples",
             "bounces": "--bounces", "bands": "--bands"}
    try:
        get_kind(kind).validate(params, where=f"--kind {kind}")
    except (ValueError, TypeError) as e:
        msg = str(e)
        for k, flag in names.items():
            msg = msg.replace(f": {k}=", f": {flag} ", 1)
        raise ValueError(msg) from None
    return kind, params


def _transfer(args, mesh, brdf: dict, kind_params: tuple[str, dict] | None = None):
    from ..transfer import Transfer
    from ..transfer.diffuse import precompute_diffuse

    if args.transfer is not None:
        tr = Transfer.load(args.transfer)
        if tr.mesh.content_hash() != mesh.content_hash() and (tr.mesh.vertices.shape != mesh.vertices.shape
                                                              or not torch.allclose(tr.mesh.vertices, mesh.vertices)):
            raise ValueError(f"--transfer {args.transfer!r} was computed for another mesh than --mesh {args.mesh!r}; "
                             "accepted: a transfer of that mesh")
        n2 = tr.data.shape[-1]
        if n2 < args.bands ** 2:
            raise ValueError(f"--transfer {args.transfer!r} has {math.isqrt(n2)} bands; accepted: at least --bands {args.bands}")
        if tr.kind not in ("diffuse", "glossy", "mrt"):
            raise ValueError(f"--transfer {args.transfer!r} is of kind {tr.kind!r}; accepted: diffuse, glossy, mrt")
        if brdf["type"] != "lambertian" and (tr.kind != "diffuse" or tr.data.ndim != 2):
            raise ValueError(f"--brdf {brdf['type']} uses the shadowed irradiance of a grey diffuse transfer; --transfer "
                             f"{args.transfer!r} is {tr.kind} {tuple(tr.data.shape)}")
        return tr
    if kind_params is not None and kind_params[0] != "diffuse":
        from ..transfer import RunOptions, get_kind

        kind, params = kind_params
        return get_kind(kind).precompute(mesh, params, run=RunOptions(workers=1, progress=False))
    return precompute_diffuse(mesh, bands=args.bands, samples=args.samples, bounces=args.bounces,
                              shadows="auto", fold_albedo=False)


def _truncate(tr, bands: int):
    """The transfer restricted to the first bands² light coefficients (a diffuse or matrix transfer
    of more bands answers fewer exactly: the light's higher coefficients are zero)."""
    import dataclasses

    n2 = bands * bands
    if tr.data.shape[-1] == n2:
        return tr
    return dataclasses.replace(tr, data=tr.data[..., :n2].contiguous())


def run(args: argparse.Namespace) -> int:
    from .. import inverse
    from ..io import atomic_write_json, check_outputs
    from ..lighting.spec import load_light
    from ..render.prt import PRTScene
    from ..scene import RayCaster, check_scene, load_scene

    t0 = time.perf_counter()
    brdf = _brdf(args)
    _check_args(args, brdf)
    check_scene(args.mesh, param="--mesh")  # the one rule for naming a mesh, before the cameras and images are read
    kind_params = _kind_params(args, brdf)
    if args.report is not None:
        rep = Path(args.report)
        if rep.exists() and not rep.is_dir():
            raise ValueError(f"--report {args.report!r} is a file; accepted: a directory (created if missing)")
    views = inverse.load_cameras(args.cameras)
    check_outputs({"-o": args.output, **_report_names(args.report, len(views))},
                  {"--cameras": args.cameras, "--transfer": args.transfer, "--light": args.light,
                   "image": [str(v.file) for v in views]}, args.overwrite)  # before any work
    mesh = load_scene(args.mesh, albedo=_albedo(args.albedo), param="--mesh")
    L_known = load_light(args.light, bands=args.bands) if args.light is not None else None
    views, images, masks, infos = inverse.load_images(views)
    quad = brdf["type"] in QUADRATURE
    unknowns = {"light": args.bands ** 2, "brdf": _brdf_unknowns(brdf, args), "both": args.bands ** 2 + 2}[args.unknown]
    eps = inverse.data_eps(infos)
    max_pixels = args.max_pixels if args.max_pixels is not None or not quad else MAX_PIXELS_QUADRATURE
    with RayCaster(mesh, workers=1) as caster:
        obs = inverse.observe(mesh, views, images, masks, unknowns=unknowns, max_pixels=max_pixels, caster=caster)
        tr = None if quad else _truncate(_transfer(args, mesh, brdf, kind_params), args.bands)
        model = None
        if brdf["type"] == "phong":
            model = inverse.material.lobe_model(mesh, tr, obs, args.bands, caster)
        elif quad:
            model = inverse.brdf_fit.slice_model(mesh, obs, L_known, quad_bands=args.brdf_quad, caster=caster)
    t_trace = time.perf_counter() - t0
    out: dict = {}
    inv: dict = {"unknown": args.unknown, "brdf": brdf, "views": len(views), "pixels": obs.P,
                 "pixels_per_view": obs.counts, "data_eps": eps, "regularizer": args.regularizer}
    if tr is not None:
        inv["transfer"] = {"kind": tr.kind, "bands": args.bands, "precomputed": args.transfer is None,
                           "meta": {k: tr.meta.get(k) for k in ("samples", "bounces", "shadows", "albedo_folded", "brdf",
                                                                "bands_out", "M") if k in tr.meta}}
    else:
        inv["quadrature"] = {"quad_bands": args.brdf_quad, "directions": int(model.wi.shape[0]),
                             "visible_fraction": model.visible, "max_pixels": max_pixels}
    if args.unknown == "light":
        if model is None:
            A = inverse.design_matrix(PRTScene(tr), obs)
        else:
            C = 3
            A = model.light_rows(torch.full((C,), float(brdf["kd"]), dtype=torch.float64),
                                 torch.tensor(float(brdf["ks"]), dtype=torch.float64), torch.tensor(float(brdf["s"]), dtype=torch.float64))
        fit = inverse.fit_light(A, obs.values, args.regularizer, eps, positive=args.positive)
        L, pred = fit.light, fit.predicted
        inv["well_posedness"] = fit.report
        inv["positivity"] = fit.positivity
    elif args.unknown == "brdf" and brdf["type"] == "sh":
        nb = args.brdf_bands or args.bands
        sh = inverse.brdf_fit.fit_sh_brdf(model, obs.values, nb, nb, method=args.regularizer, eps=eps)
        L, pred = L_known, sh["predicted"]
        inv["brdf"] = {"type": "sh", "bands_out": nb, "bands_in": nb}
        inv["brdf_sh"] = _sh_report(sh)
    elif args.unknown == "brdf" and quad:
        fixed = {k: v for k, v in brdf.items() if k != "type"}
        bf = inverse.brdf_fit.fit_parametric(model, obs.values, brdf["type"], fixed=fixed)
        L, pred = L_known, bf.predicted
        inv["brdf_fit"] = {"params": bf.params, "stderr": bf.stderr, "relative_stderr": bf.relative_stderr,
                           "iterations": bf.iterations, "fixed": sorted(fixed), "out_of_range": bf.out_of_range}
        if bf.out_of_range:
            import warnings

            warnings.warn(f"fitted {', '.join(bf.out_of_range)} outside the {brdf['type']} model's range: the model does "
                          "not fit these images (wrong light or model, or no visible highlight)", stacklevel=1)
        inv["brdf"] = {"type": brdf["type"], **bf.params}
    elif args.unknown == "brdf":
        fixed = {"s": brdf["s"]} if "s" in brdf else None
        bf = inverse.material.fit_phong(model, L_known, obs.values, fixed=fixed)
        L, pred = L_known, bf.predicted
        inv["brdf_fit"] = {"params": bf.params, "stderr": bf.stderr, "relative_stderr": bf.relative_stderr,
                           "iterations": bf.iterations}
        inv["brdf"] = {"type": "phong", "form": "reflection", **bf.params}
    else:
        res = inverse.material.fit_both(model, obs.values, method=args.regularizer, eps=eps)
        L, pred = res["light"], res["fit"].predicted
        inv["well_posedness"] = res["fit"].report
        inv["brdf"] = {"type": "phong", "form": "reflection", **res["params"]}
        inv["ambiguities"] = res["ambiguities"]
    resid = pred - obs.values
    inv["residual"] = {"psnr_db": inverse.psnr(pred, obs.values), "rms": float(resid.pow(2).mean().sqrt()),
                       "relative_rms": float(resid.norm() / obs.values.norm().clamp_min(1e-300))}
    inv["seconds"] = {"trace_and_transfer": t_trace, "total": time.perf_counter() - t0}
    out.update(inverse.light_json(L, args.bands, f"prt invert --unknown {args.unknown}"))
    out["inverse"] = inv
    atomic_write_json(args.output, out)
    if args.report is not None:
        _write_report(Path(args.report), obs, pred, args.overwrite)
    w = inv.get("well_posedness")
    msg = f"prt invert: {obs.P} pixels of {len(views)} views, PSNR {inv['residual']['psnr_db']:.2f} dB"
    if w is not None:
        msg += (f", recoverable bands {w['recoverable_bands']} (largest error gain {max(b['gain'] for b in w['bands']):.3g}; "
                f"least determined: the light about {tuple(w['weakest']['peak_direction'])})")
    pos = inv.get("positivity")
    if pos is not None:
        u = pos["unconstrained"]
        msg += (f", unconstrained light negative on {100 * max(u['negative_solid_angle']):.1f}% of the sphere (least radiance "
                f"{min(u['min_relative']):.3g} x mean |radiance|)" + (", constrained >= 0" if pos["constrained"] else ""))
    if args.unknown != "light" and brdf["type"] == "sh":
        r = inv["brdf_sh"]
        msg += f", SH BRDF {len(r['index'])} coefficients per channel, {len(r['undetermined'])} not determined by the images"
    elif args.unknown != "light":
        msg += ", brdf " + json.dumps({k: v for k, v in inv["brdf"].items() if k != "type"})
    print(msg + f" -> {args.output}")
    return 0


def _brdf_unknowns(brdf: dict, args) -> int:
    """Unknowns of --unknown brdf per channel block (the pixel-count check before tracing)."""
    from ..inverse.brdf_fit import PARAMETERS, sh_brdf_index

    if brdf["type"] == "sh":
        nb = args.brdf_bands or args.bands
        return int(sh_brdf_index(nb, nb).shape[0])
    if brdf["type"] in PARAMETERS:
        return sum(3 if ch else 1 for (k, ch, *_r) in PARAMETERS[brdf["type"]] if k not in brdf)
    return 5


def _sh_report(sh: dict) -> dict:
    """The JSON of :func:`prt_torch.inverse.brdf_fit.fit_sh_brdf`: coefficients ρ̂_lpq with their
    (l, p, q), and per coefficient its resolution, standard error and whether the images determine it."""
    idx = sh["index"].tolist()
    det = sh["determined"].tolist()
    return {"index": idx, "coeffs": sh["coeffs"].tolist(), "stderr": sh["stderr"].tolist(),
            "resolution": sh["resolution"].tolist(), "determined": det,
            "undetermined": [i for i, d in zip(idx, det) if not d], "singular_values": sh["singular_values"],
            "condition": sh["singular_values"][0] / sh["singular_values"][-1] if sh["singular_values"][-1] > 0 else math.inf,
            "lam": sh["lam"], "threshold": 0.5}


def _report_names(d: str | None, n: int) -> dict:
    if d is None:
        return {}
    return {f"--report (view {k})": [str(Path(d) / f"view_{k}.png"), str(Path(d) / f"view_{k}.exr")] for k in range(n)}


def _write_report(d: Path, obs, pred: torch.Tensor, overwrite: bool) -> None:
    """``view_K.png``: input | re-rendered | |error| (same exposure for the first two) and
    ``view_K.exr``: the re-rendered image, linear."""
    from ..lighting import write_image
    from ..render.images import auto_exposure, error_heatmap, side_by_side

    d.mkdir(parents=True, exist_ok=True)  # the paths were checked before any work (_report_names)
    for k in range(len(obs.views)):
        a = obs.image(obs.values, k)
        b = obs.image(pred, k)
        m = obs.image(torch.ones(obs.P, 1), k)[..., 0] > 0
        ev = auto_exposure(a, m)
        heat = error_heatmap(b, a, m, kind="abs")
        side_by_side([a, b, heat], ["input", "re-rendered", "|error|"], exposure=[ev, ev, 0.0], path=d / f"view_{k}.png")
        write_image(d / f"view_{k}.exr", np.asarray(b), overwrite=overwrite)
