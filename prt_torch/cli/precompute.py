"""``prt precompute MESH_OR_BUILTIN --kind diffuse --bands 5 --samples 1024 --bounces 2 -o out.prt``

Loads a mesh file (OBJ, PLY, STL, OFF, GLB/GLTF) or builds a built-in scene (``name`` or
``name:size``), precomputes its transfer, and writes it atomically. An existing output is
refused unless ``--overwrite``. Finished chunks are kept in ``<out>.state/`` while running;
after an interruption ``--resume`` continues from the last finished chunk (same result as an
uninterrupted run); ``--overwrite`` discards such a state directory.

With ``--executor ray`` the chunks run as Ray tasks (a local Ray, or a cluster with
``--ray-address``); the state directory and the result are the same as a local run's.

Every kind and its options come from the transfer registry (``prt_torch.transfer.kinds()``);
an option a kind does not take is refused. Unset options take the kind's defaults.
"""
from __future__ import annotations

import argparse
import math
import shlex
import shutil
import sys
from pathlib import Path

from .._checks import check_int
from .bench import add_executor_args, executor_from_args


def _albedo_arg(text: str):
    parts = [p for p in text.replace(" ", "").split(",") if p]
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise argparse.ArgumentTypeError(f"--albedo {text!r}: accepted: one number or R,G,B in [0,1]") from None
    if len(vals) not in (1, 3):
        raise argparse.ArgumentTypeError(f"--albedo {text!r}: accepted: one number or R,G,B in [0,1]")
    return vals[0] if len(vals) == 1 else vals


def _kind_args() -> dict[str, tuple]:
    """flag -> (Arg, [kinds using it]) over every registered kind (one option per flag)."""
    from ..transfer import get_kind, kinds

    out: dict[str, tuple] = {}
    for name in kinds():
        for a in get_kind(name).args:
            if a.flag in out:
                if out[a.flag][0].param != a.param:  # pragma: no cover - a registry bug
                    raise RuntimeError(f"option {a.flag} sets {out[a.flag][0].param} and {a.param}")
                out[a.flag][1].append(name)
            else:
                out[a.flag] = (a, [name])
    return out


def _dest(flag: str) -> str:
    return "k_" + flag.lstrip("-").replace("-", "_")


def register(subparsers) -> None:
    from ..transfer import get_kind, kinds

    p = subparsers.add_parser("precompute", help="precompute transfer for a mesh or built-in scene",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="MESH_OR_BUILTIN", help="mesh file, or built-in scene name[:size] (see `prt info --builtins`)")
    p.add_argument("--kind", default="diffuse", choices=kinds(),
                   help="; ".join(f"{k}: {get_kind(k).doc}" for k in kinds()))
    p.add_argument("-o", "--output", required=True, help="output .prt file (a directory for --kind transport)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output (and discard a stale state dir)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from <output>.state/")
    p.add_argument("--size", default="small", help="built-in scene size: small, medium, large; for convex and bumpy_sphere "
                                                   "also xl (~1M vertices) or a vertex count")
    p.add_argument("--up", default="z", choices=["z", "-z", "y", "-y", "x", "-x"], help="up axis of the mesh file")
    p.add_argument("--albedo", type=_albedo_arg, default=None, help="uniform albedo: ρ or R,G,B (default: the scene's)")
    g = p.add_argument_group("run options (every kind)")
    g.add_argument("--chunk", type=int, default=None, help="vertices per chunk (default ~1M rays per chunk)")
    g.add_argument("--workers", type=int, default=None, help="ray-casting processes (default: all cores for long runs)")
    g.add_argument("--memory-limit", type=float, default=None, help="GiB; refuse a run estimated above it (default 60%% of RAM)")
    g.add_argument("--no-progress", action="store_true", help="no progress bar")
    add_executor_args(g, "the chunks")
    p.add_argument("--dry-run", action="store_true",
                   help="build the mesh, then print each stage's memory and time (time from a probe of two small "
                        "chunks) and whether it fits, and stop; a run that would not fit is refused up front anyway")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    g = p.add_argument_group("automatic choices ('auto' for --bands, --bands-out, --tents; wavelet: --res)")
    g.add_argument("--energy", type=float, default=None,
                   help="fraction of the reflected energy an 'auto' choice keeps, in (0, 1] (default 0.99); wavelet "
                        "--res auto: of the lights' Haar energy; refused where no 'auto' choice keeps it")
    g.add_argument("--light", action="append", default=None, metavar="SPEC",
                   help="a light of the scene (built-in name, file or analytic spec), repeatable: 'auto' bands keep "
                        "the energy of these lights through the BRDF lobe (default: a flat light spectrum); wavelet "
                        "--res auto: the smallest cube keeping their energy (default without: R = 32); refused where no "
                        "'auto' choice reads it (an explicit --bands / --res)")
    g = p.add_argument_group("transfer parameters (default: the kind's)")
    for flag, (a, used_by) in _kind_args().items():
        defaults = {k: get_kind(k).defaults()[a.param] for k in used_by}
        dtxt = ", ".join(f"{k}: {v}" for k, v in defaults.items()) if not a.is_switch and not a.spec else ""
        help_text = f"{a.help} [{', '.join(used_by)}" + (f"; default {dtxt}" if dtxt else "") + "]"
        help_text = help_text.replace("%", "%%")  # argparse %-formats help: a registry text's '1%' broke --help
        if a.is_switch:
            g.add_argument(flag, dest=_dest(flag), action="store_true", help=help_text)
        elif a.values is not None:
            g.add_argument(flag, dest=_dest(flag), choices=list(a.values), default=None, help=help_text)
        else:
            g.add_argument(flag, dest=_dest(flag), default=None, help=help_text, metavar=a.param.upper())
        if a.spec:
            g.add_argument(f"{flag}-param", dest=_dest(flag) + "_param", action="append", metavar="NAME=VALUE",
                           help=f"a parameter of {flag}, repeatable")
    p.set_defaults(func=run)


def _argv(args: argparse.Namespace) -> list[str]:
    """The command line that started this run, without --resume/--overwrite (for the hint)."""
    argv = sys.argv[1:] if sys.argv and sys.argv[0].endswith(("prt", "__main__.py")) else ["precompute", args.scene, "-o", args.output]
    return [a for a in argv if a not in ("--resume", "--overwrite")]


def params_from_args(kind: str, args: argparse.Namespace) -> dict:
    """The parameters of ``kind`` given on the command line (unset options are left out);
    options of other kinds are refused."""
    from ..params import parse_assignments, parse_value
    from ..transfer import get_kind

    k = get_kind(kind)
    mine = {a.flag for a in k.args}
    params: dict = {}
    for flag, (a, used_by) in _kind_args().items():
        v = getattr(args, _dest(flag), None)
        sub = getattr(args, _dest(flag) + "_param", None) if a.spec else None
        if v in (None, False) and not sub:
            continue
        if flag not in mine:
            raise ValueError(f"{flag} does not apply to --kind {kind}; it is an option of {', '.join(used_by)}")
        if a.is_switch:
            params[a.param] = a.const
        elif a.values is not None:
            params[a.param] = a.values[v]
        elif a.spec:
            spec = {"type": v if v is not None else k.defaults()[a.param] or "ashikhmin_shirley"}
            spec.update(parse_assignments(sub or [], what=f"{flag}-param"))
            params[a.param] = spec
        else:
            if isinstance(v, str) and not v.strip():  # parse_value reads '' as null: say what was typed
                raise ValueError(f"{flag} {v!r} is empty; accepted: a value ({a.help.split(';')[0].split(' (')[0]})")
            params[a.param] = parse_value(v)
    if getattr(args, "energy", None) is not None:
        params["energy"] = args.energy
    return params


class ResumeHint:
    """What an interrupted precompute says it kept, read when it is said: the state directory's
    finished chunks and the ``--resume`` command, or (stopped before the first chunk finished —
    a 1M-vertex mesh takes a while to build) that nothing was kept."""

    def __init__(self, state: Path, command: str):
        self.state, self.command = Path(state), command

    def __str__(self) -> str:
        n = len(list(self.state.glob("chunk_*.prt"))) if self.state.is_dir() else 0
        if n or (self.state.is_dir() and any(self.state.iterdir())):
            return (f"finished chunks ({n}) are kept in {str(self.state)!r}; continue with: {self.command} --resume")
        return f"no chunk had finished, nothing was kept; run it again: {self.command}"


class _TableDir:
    """Moves a finished transport table from the state directory to the output."""

    def __init__(self, table):
        self.table = table

    def save(self, path: Path, overwrite: bool = False) -> Path:
        if not self.table.meta.get("complete"):
            raise ValueError(f"transport table in {str(self.table.path)!r} is incomplete; rerun with --resume")
        if path.exists():
            if not overwrite:
                raise FileExistsError(f"output {str(path)!r} exists; pass --overwrite to replace it")
            shutil.rmtree(path) if path.is_dir() else path.unlink()
        self.table.path.rename(path)
        self.table.path = path
        return path


def run(args) -> int:
    with executor_from_args(args) as executor:  # Ray checked before any work; a local Ray stops at the end
        return _run(args, executor)


def _run(args, executor) -> int:
    from ..scene import check_scene, load_scene
    from ..transfer import RunOptions, default_state_dir, get_kind

    kind = get_kind(args.kind)
    if args.memory_limit is not None and not (math.isfinite(args.memory_limit) and 0 < args.memory_limit <= 1 << 20):
        raise ValueError(f"--memory-limit {args.memory_limit!r} GiB; accepted: a finite number of GiB in (0, 1048576]")
    args.cli_names = {a.param: a.flag for a in kind.args}  # errors name --quad-bands, not quad_bands
    for opt, v in (("--chunk", args.chunk), ("--workers", args.workers)):  # before the scene is read and announced
        if v is not None:
            check_int(opt, v, 1)
    params = params_from_args(args.kind, args)
    kind.validate(params, where=f"--kind {args.kind}")
    if args.light:
        _check_lights_used(kind, params, args.light)
    if args.energy is not None:
        _check_energy_used(kind, params, args.energy)
    out = Path(args.output)
    from ..io import check_outputs

    check_outputs({"-o/--output": out}, {"MESH_OR_BUILTIN": args.scene, "--light": args.light}, args.overwrite,
                  directories=("-o/--output",) if kind.output == "directory" else ())  # before any work
    check_scene(args.scene, size=args.size, param="MESH_OR_BUILTIN")  # the one rule for naming a mesh, before any work
    state = default_state_dir(out)
    if args.resume and not state.exists() and not args.dry_run:  # said, not silently a fresh run
        import warnings

        warnings.warn(f"--resume: no interrupted run in {str(state)!r}; starting from the beginning", stacklevel=1)
    if state.exists() and not args.resume and not args.dry_run:  # a dry run removes nothing
        if args.overwrite:
            shutil.rmtree(state)
        else:
            raise FileExistsError(f"{str(state)!r} holds an interrupted run for this output; pass --resume to continue it "
                                  "or --overwrite to start again")
    lights = None
    if args.light:  # read before the scene is announced: a bad light is one line, before any work
        from ..lighting import load_light
        from ..lighting.haar import cube_light

        lights = []
        for spec in args.light:
            try:
                if kind.name == "wavelet":  # res auto measures the light itself on the cube, not its SH projection
                    cube_light(spec, 1, supersample=1)  # (an image of any size; its SH at 32 bands need not exist)
                    lights.append(spec)
                else:
                    lights.append(load_light(spec, bands=32))
            except (ValueError, OSError) as e:
                raise ValueError(f"--light {spec!r}: {e}") from None
    import time

    from ..transfer.estimate import check_fits, estimate, format_estimate

    from ..transfer.estimate import rss_bytes

    t_mesh, rss0 = time.perf_counter(), rss_bytes()
    mesh = load_scene(args.scene, size=args.size, up=args.up, albedo=args.albedo, param="MESH_OR_BUILTIN")
    t_mesh, mesh_rss = time.perf_counter() - t_mesh, rss_bytes() - rss0
    print(f"prt precompute: {mesh.name}: {mesh.num_vertices} vertices, {mesh.num_faces} faces", file=sys.stderr)
    plan = RunOptions(chunk_size=args.chunk, workers=args.workers, offset=RunOptions.offset, state_dir=state,
                      max_memory=None if args.memory_limit is None else int(args.memory_limit * (1 << 30)))  # a result over
    # STREAM_RESULT_BYTES is assembled in a file beside the state directory: the estimate does not count it in memory
    est = estimate(kind, mesh, params, plan, lights=lights, probe=args.dry_run, mesh_seconds=t_mesh, mesh_rss=mesh_rss)
    if args.dry_run:
        _print_auto(kind.resolve(params, lights)[1])  # what 'auto' chose (the estimate is for it)
        print(f"prt precompute: dry run, {kind.name} on {mesh.num_vertices} vertices: memory and time per stage", file=sys.stderr)
        for line in format_estimate(est):
            print(line, file=sys.stderr)
        check_fits(est, "prt precompute:")
        print("prt precompute: dry run: nothing written", file=sys.stderr)
        return 0
    check_fits(est, "prt precompute:")  # before any ray: what cannot fit even with its chunks on disk
    args.resume_hint = ResumeHint(state, f"prt {' '.join(shlex.quote(a) for a in _argv(args))}")
    opts = RunOptions(chunk_size=args.chunk, workers=args.workers, state_dir=state, resume=args.resume,
                      progress=not args.no_progress, executor=executor,
                      max_memory=None if args.memory_limit is None else int(args.memory_limit * (1 << 30)))
    if kind.output == "directory":
        table = kind.precompute(mesh, params, run=opts, out=state)
        _TableDir(table).save(out, overwrite=args.overwrite)
        print(f"prt precompute: wrote {out}/ kind={kind.name} ({table!r})", file=sys.stderr)
        return 0
    tr = kind.precompute(mesh, params, run=opts, lights=lights)
    tr.save(out, overwrite=args.overwrite)
    m = tr.meta
    _print_auto(m.get("auto", {}))
    stored = f", {m['bytes_per_vertex']} B/vertex stored" if "bytes_per_vertex" in m else ""  # the wavelet kind's sparse rows
    print(f"prt precompute: wrote {out} kind={tr.kind} data={tuple(tr.data.shape)}{stored} "
          f"({m.get('shadow_decision', '')}; bounces used {m.get('bounces_used', m.get('bounces', 0))}; "
          f"{ray_summary(m)} in {m.get('seconds', 0):.1f} s)", file=sys.stderr)
    return 0


def _check_lights_used(kind, params: dict, lights: list[str]) -> None:
    """Refuse ``--light`` when no 'auto' choice of this run reads it (:func:`prt_torch.transfer.auto.light_choices`:
    the lights are used by ``--res auto`` of the wavelet kind and ``--bands auto`` of the SH kinds, nothing
    else): one line naming the light and what would use it, before any work (as ``prt relight --selection``
    on an SH transfer)."""
    from ..transfer.auto import light_choices

    if light_choices(kind.name, params):
        return
    param = "res" if kind.name == "wavelet" else "bands"
    flag = f"--{param}"
    try:
        usable = param in kind.constraints and bool(light_choices(kind.name, kind.validate({param: "auto"})))
    except (ValueError, TypeError):  # e.g. subsurface: bands is a number, never 'auto'
        usable = False
    if not usable:
        raise ValueError(f"--light {lights[0]!r} has no effect on --kind {kind.name}: no 'auto' choice of this kind reads a "
                         "light; accepted: no --light")
    given = params.get(param)
    now = f"{flag} {given}" if given is not None else f"the default {flag} {kind.defaults()[param]}"
    raise ValueError(f"--light {lights[0]!r} has no effect with {now}: --kind {kind.name} reads the lights only to choose "
                     f"{flag} auto; accepted: {flag} auto with --light, or no --light")


def _check_energy_used(kind, params: dict, energy: float) -> None:
    """Refuse ``--energy`` when no 'auto' choice of this run keeps it (:func:`prt_torch.transfer.auto.energy_choices`),
    one line naming the kind's options that take 'auto' with it."""
    from ..transfer.auto import energy_choices

    if energy_choices(kind.name, params):
        return
    flags = []
    for a in kind.args:
        try:
            if energy_choices(kind.name, kind.validate({a.param: "auto"})):
                flags.append(a.flag)
        except (ValueError, TypeError):
            pass
    if not flags:
        raise ValueError(f"--energy {energy:g} has no effect on --kind {kind.name}: no 'auto' choice of this kind keeps a "
                         "fraction of the energy; accepted: no --energy")
    raise ValueError(f"--energy {energy:g} has no effect: no 'auto' choice in this run; accepted: "
                     f"{' / '.join(f'{f} auto' for f in flags)} with --energy, or no --energy")


def _print_auto(decisions: dict) -> None:
    """One stderr line per 'auto' decision (``meta['auto']``: value, energy kept, reason)."""
    for k, d in decisions.items():
        kept = "" if d.get("energy_kept") is None else f" keeps {d['energy_kept']:.4f} of the energy"  # None: nothing measured
        print(f"prt precompute: {k}={d['value']}{kept} ({d['reason']})", file=sys.stderr)


def ray_counts(meta: dict) -> dict[str, int]:
    """Every ray a precompute traced, from its metadata: ``vertex`` (the vertices' own,
    ``rays_traced``), ``hit`` (the bounce hit points', intersect and occluded: ``hit_rays_traced``)
    and ``probe`` (the self-occlusion probe of ``shadows: auto``, ``probe.rays``, and the hits'
    per-face probe of estimator 'auto', ``hit_choice_rays``); ``total`` their sum."""
    c = {"vertex": int(meta.get("rays_traced", 0)), "hit": int(meta.get("hit_rays_traced", 0)),
         "probe": int((meta.get("probe") or {}).get("rays", 0)) + int(meta.get("hit_choice_rays", 0))}
    c["total"] = c["vertex"] + c["hit"] + c["probe"]
    return c


def ray_summary(meta: dict) -> str:
    """'N rays' with the parts of :func:`ray_counts` where there is more than the vertices' rays."""
    c = ray_counts(meta)
    if c["total"] == c["vertex"]:
        return f"{c['total']} rays"
    return f"{c['total']} rays: {c['vertex']} from vertices, {c['hit']} from hit points, {c['probe']} probe"
