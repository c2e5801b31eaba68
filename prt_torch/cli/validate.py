"""``prt validate TRANSFER.prt --light SPEC [--vertices N] [--spp S]``

Per-vertex exit radiance of a diffuse transfer (and of a codec's reconstruction of it, with
``--codec-file``) against Mitsuba 3 path tracing of the same mesh, albedo and light, at sampled
vertices, with no scale fit: the direct part (Mitsuba ``max_depth`` 1 against the transfer's
shadowed pass) and the interreflected part (``max_depth`` B+1 minus 1 against the transfer's
bounces), each with both sides' Monte Carlo noise. A glossy exit transfer is compared toward one
view per vertex (direct and interreflected), with the engine's BRDF as a Mitsuba BSDF (the SH
truncation bias reported apart). A wavelet transfer (all-frequency, Ng 2003; every Haar term of the
light) is compared under the environment's original image: ``--light-source image`` (required for it)
with an environment file or built-in name (docs/wavelet.md). See docs/validate.md.

Mitsuba 3 is optional: ``pip install 'prt-torch[validate]'``. A transfer kind or light the
validator cannot express is refused by name before any work.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path


def register(subparsers) -> None:
    p = subparsers.add_parser("validate", help="compare a transfer's exit radiance with Mitsuba 3 path tracing",
                              description=__doc__.split("\n\n")[1])
    p.add_argument("transfer", help="a diffuse, glossy (exit) or wavelet transfer file (prt precompute)")
    p.add_argument("--light", required=True,
                   help="built-in environment, environment file or analytic spec (see prt light); its band-limited "
                        "radiance must be non-negative")
    p.add_argument("--vertices", type=int, default=32, help="vertices sampled (default 32)")
    p.add_argument("--spp", type=int, default=4096, help="Mitsuba samples per vertex and depth (default 4096)")
    p.add_argument("--batches", type=int, default=8, help="independent Mitsuba renders the samples are split over (noise)")
    p.add_argument("--seed", type=int, default=0, help="vertex sampling and Mitsuba seed")
    p.add_argument("--codec-file", help="also compare this codec file's reconstruction of the transfer")
    p.add_argument("--light-source", choices=["sh", "image"], default="sh",
                   help="what Mitsuba sees: the band-limited light (sh, exact comparison) or the original environment "
                        "image (image; adds the SH-truncation effect)")
    p.add_argument("--mesh", help="glossy transfer of a vertex subset: the full mesh it was computed on (built-in NAME or "
                                  "NAME:SIZE, or a file; same content hash)")
    p.add_argument("--view-deg", type=float, default=60.0,
                   help="glossy: views drawn within this angle of each vertex normal (default 60)")
    p.add_argument("--json", metavar="PATH", help="also write the full report (per-vertex values) as strict JSON "
                                                  "(a non-finite value as null)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --json file")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def run(args) -> int:
    from ..validate import ValidatorUnavailable, format_report, validate

    from ..io import atomic_write_text, check_outputs, strict_json

    if not Path(args.transfer).exists():
        raise FileNotFoundError(f"transfer file {args.transfer!r} does not exist")
    check_outputs({"--json": args.json}, {"TRANSFER": args.transfer, "--codec-file": args.codec_file, "--light": args.light,
                                          "--mesh": args.mesh}, args.overwrite)  # before any work
    mesh = None
    if args.mesh:
        from ..scene import load_scene

        mesh = load_scene(args.mesh, param="--mesh")  # the one rule for naming a mesh (prt_torch.scene.check_scene)
    try:
        rep = validate(args.transfer, args.light, vertices=args.vertices, spp=args.spp, batches=args.batches, seed=args.seed,
                       codec_file=args.codec_file, light_source=args.light_source, light_name=args.light, mesh=mesh,
                       view_deg=args.view_deg)
    except ValidatorUnavailable as e:
        print(f"prt validate: {e}", file=sys.stderr)
        return 3
    print(format_report(rep))
    if args.json:
        atomic_write_text(args.json, json.dumps(strict_json(rep), indent=1, allow_nan=False))
    return 0
