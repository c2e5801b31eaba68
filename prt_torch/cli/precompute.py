"""``prt precompute MESH_OR_BUILTIN --kind diffuse --bands 5 --samples 1024 --bounces 2 -o out.prt``

Loads a mesh file (OBJ, PLY, STL, OFF, GLB/GLTF) or builds a built-in scene (``name`` or
``name:size``), precomputes its transfer, and writes it atomically. An existing output is
refused unless ``--overwrite``. Finished chunks are kept in ``<out>.state/`` while running;
after an interruption ``--resume`` continues from the last finished chunk (same result as an
uninterrupted run); ``--overwrite`` discards such a state directory.

Kinds other than ``diffuse`` are provided by their transfer modules: ``prt_torch.transfer.<kind>``
may define ``add_precompute_arguments(parser)`` and ``precompute_from_args(mesh, args) -> Transfer``.
"""
from __future__ import annotations

import argparse
import importlib
import shutil
import sys
from pathlib import Path


def _albedo_arg(text: str):
    parts = [p for p in text.replace(" ", "").split(",") if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--albedo {text!r}: accepted: one number or R,G,B in [0,1]") from None
    if len(vals) not in (1, 3):
        raise argparse.ArgumentTypeError(f"--albedo {text!r}: accepted: one number or R,G,B in [0,1]")
    return vals[0] if len(vals) == 1 else vals


def register(subparsers) -> None:
    p = subparsers.add_parser("precompute", help="precompute transfer for a mesh or built-in scene",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="MESH_OR_BUILTIN", help="mesh file, or built-in scene name[:size] (see `prt info --builtins`)")
    p.add_argument("--kind", default="diffuse", choices=["diffuse", "glossy", "mrt", "transport"])
    p.add_argument("--bands", type=int, default=5, help="SH bands n (n² coefficients), default 5")
    p.add_argument("--samples", type=int, default=1024, help="Monte Carlo directions per vertex, default 1024")
    p.add_argument("--bounces", type=int, default=0, help="interreflection bounces after the direct pass, default 0")
    p.add_argument("--seed", type=int, default=0, help="direction-set seed, default 0")
    p.add_argument("-o", "--output", required=True, help="output .prt file")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output (and discard a stale state dir)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from <output>.state/")
    p.add_argument("--size", default="small", choices=["small", "medium", "large"], help="built-in scene size")
    p.add_argument("--up", default="z", choices=["z", "-z", "y", "-y", "x", "-x"], help="up axis of the mesh file")
    p.add_argument("--albedo", type=_albedo_arg, default=None, help="uniform albedo: ρ or R,G,B (default: the scene's)")
    p.add_argument("--sampling", default="uniform", choices=["uniform", "cosine"])
    p.add_argument("--shadows", default="auto", choices=["auto", "always", "never"])
    p.add_argument("--fold-albedo", default="auto", choices=["auto", "yes", "no"],
                   help="store [V,3,n²] with albedo folded (yes), [V,n²] without (no), or as needed (auto)")
    p.add_argument("--bounce-tol", type=float, default=1e-3, help="stop adding bounces below this energy fraction")
    p.add_argument("--chunk", type=int, default=None, help="vertices per chunk (default ~1M rays per chunk)")
    p.add_argument("--workers", type=int, default=None, help="ray-casting processes (default: all cores)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    for kind in ("glossy", "mrt", "transport"):
        try:
            mod = importlib.import_module(f"prt_torch.transfer.{kind}")
        except ImportError:
            continue
        if hasattr(mod, "add_precompute_arguments"):
            mod.add_precompute_arguments(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from ..scene import load_scene
    from ..transfer import default_state_dir, precompute_diffuse

    out = Path(args.output)
    if out.exists() and not args.overwrite:
        raise FileExistsError(f"output {str(out)!r} exists; pass --overwrite to replace it")
    if out.is_dir():
        raise ValueError(f"output {str(out)!r} is a directory; accepted: a file path")
    state = default_state_dir(out)
    if state.exists() and not args.resume:
        if args.overwrite:
            shutil.rmtree(state)
        else:
            raise FileExistsError(f"{str(state)!r} holds an interrupted run for this output; pass --resume to continue it "
                                  "or --overwrite to start again")
    mesh = load_scene(args.scene, size=args.size, up=args.up, albedo=args.albedo)
    print(f"prt precompute: {mesh.name}: {mesh.num_vertices} vertices, {mesh.num_faces} faces", file=sys.stderr)
    if args.kind == "diffuse":
        fold = {"auto": None, "yes": True, "no": False}[args.fold_albedo]
        tr = precompute_diffuse(
            mesh, args.bands, args.samples, args.bounces, args.seed, sampling=args.sampling, shadows=args.shadows,
            fold_albedo=fold, bounce_tol=args.bounce_tol, chunk_size=args.chunk, workers=args.workers,
            state_dir=state, resume=args.resume, progress=not args.no_progress,
        )
    else:
        try:
            mod = importlib.import_module(f"prt_torch.transfer.{args.kind}")
        except ModuleNotFoundError:
            mod = None
        if mod is None or not hasattr(mod, "precompute_from_args"):
            raise ValueError(f"--kind {args.kind} is not available in this build; accepted: diffuse")
        args.state_dir = state
        tr = mod.precompute_from_args(mesh, args)
    tr.save(out, overwrite=args.overwrite)
    m = tr.meta
    print(f"prt precompute: wrote {out} kind={tr.kind} data={tuple(tr.data.shape)} "
          f"({m.get('shadow_decision', '')}; bounces used {m.get('bounces_used', 0)}; "
          f"{m.get('rays_traced', 0)} rays in {m.get('seconds', 0):.1f} s)", file=sys.stderr)
    return 0
