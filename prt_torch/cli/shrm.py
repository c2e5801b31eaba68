"""``prt shrm``: compute and save a spherical harmonic reflection map (Ramamoorthi 2002 ch. 5) of a
BRDF under a light, orders from ε (eq. 5.16–5.19) or given."""
from __future__ import annotations

import argparse
import json
import math
import time

from .. import shrm as S
from ..brdf import MODELS, from_spec
from ..io import check_writable, format_bytes
from ..lighting import list_builtin_environments
from ..params import parse_assignments


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "shrm",
        help="spherical harmonic reflection map of a BRDF under a light (Ramamoorthi 2002 ch. 5)",
        description=(
            "Compute the SHRM B_pq(alpha, beta) of an isotropic BRDF under a distant light: the BRDF's coefficients "
            "rho_lpq (reparameterised by the reflection vector, eq. 5.22), the light's SH, and the maps by "
            "frequency-space prefiltering (eq. 5.23-5.24) on a lat-long grid. Orders F_B, P_B from --epsilon "
            "(eq. 5.18: smallest P then F keeping 1-epsilon of the BRDF energy) or --orders. LIGHT is a built-in "
            "environment (" + ", ".join(list_builtin_environments()) + "), an image file or an analytic spec "
            "('directional:direction=0,0,1', 'cap:direction=0,1,1;half_angle_deg=10')."
        ),
    )
    p.add_argument("--brdf", required=True, metavar="TYPE",
                   help=f"reflectance model: {', '.join(sorted(MODELS))} (isotropic parameters only)")
    p.add_argument("--brdf-param", action="append", default=[], metavar="NAME=VALUE",
                   help="a model parameter, repeatable: s=32 form=reflection (Phong), sigma=0.2 (microfacet), kd=0.8")
    p.add_argument("--light", required=True, metavar="SPEC", help="built-in name, image file or analytic spec")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--epsilon", type=float, default=None, help="accepted BRDF energy loss in (0, 1) (default 0.03)")
    g.add_argument("--orders", default=None, metavar="F,P", help="the orders F_B,P_B instead of --epsilon")
    p.add_argument("--size", type=int, default=64, help="map height H (lat-long H x 2H; default 64)")
    p.add_argument("--max-memory", type=float, default=S.DEFAULT_MAX_MEMORY / 2**30, metavar="GIB",
                   help="refuse plans estimated above this many GiB (default 4)")
    p.add_argument("-o", "--output", required=True, metavar="OUT.prt")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--json", action="store_true", help="print F_B, P_B, energy and the reason as JSON")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def parse_orders(text: str, flag: str = "--orders") -> tuple[int, int]:
    parts = [t.strip() for t in text.split(",")]
    try:
        if len(parts) != 2:
            raise ValueError
        return int(parts[0]), int(parts[1])
    except ValueError:
        raise ValueError(f"{flag}={text!r}; accepted: two integers F,P (e.g. 12,2)") from None


def run(args: argparse.Namespace) -> int:
    out = check_writable(args.output)
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"output {args.output!r} exists; pass --overwrite to replace it")
    params = parse_assignments(args.brdf_param, what="--brdf-param")
    brdf = from_spec({"type": args.brdf, **params})
    orders = parse_orders(args.orders) if args.orders is not None else None
    eps = args.epsilon if args.epsilon is not None else 0.03
    if not (math.isfinite(args.max_memory) and args.max_memory > 0):  # NaN compared false and reached int(NaN)
        raise ValueError(f"--max-memory={args.max_memory!r} GiB; accepted: a finite positive number of GiB")
    t0 = time.perf_counter()
    m = S.build_shrm(brdf, args.light, epsilon=eps, orders=orders, height=args.size,
                     max_memory=int(args.max_memory * 2**30))
    elapsed = time.perf_counter() - t0
    m.meta.update(light=args.light, seconds=elapsed)
    path = m.save(args.output, overwrite=args.overwrite)
    info = {
        "F_B": m.F_B, "P_B": m.P_B, "energy": m.meta["energy"], "eps_rho": m.meta["eps_rho"],
        "epsilon": m.meta.get("epsilon"), "axis": m.axis, "reason": m.meta["reason"], "brdf": m.meta["brdf"],
        "light": args.light, "maps_shape": list(m.maps.shape), "bytes": path.stat().st_size, "output": str(path),
        "seconds": elapsed,
    }
    for k in ("eps_light", "eps_min", "eps_bound"):
        if k in m.meta:
            info[k] = m.meta[k]
    if args.json:
        print(json.dumps(info, indent=2))
    else:
        print(f"{path}: SHRM F_B={m.F_B} P_B={m.P_B} ({m.axis} axis), BRDF energy kept {m.meta['energy']:.4f}, "
              f"maps {tuple(m.maps.shape)}, {format_bytes(info['bytes'])}, {elapsed:.2f} s")
        print(f"  {m.meta['reason']}")
    return 0
