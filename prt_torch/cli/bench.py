"""``prt bench [CONFIG] [key.path=value ...]`` — the benchmark harness (prt_torch.harness)."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path


def stage_memory(cfg: dict, mesh, mem: dict) -> str:
    """One line: the precompute's stages (:func:`prt_torch.transfer.estimate.estimate`, without
    its timing probe: ``prt precompute --dry-run`` times it) and the benchmark's own peak
    (signal, codec workspace, metrics: ``harness.run.estimate_memory``)."""
    from ..harness.run import transfer_params
    from ..io import format_bytes as fb
    from ..transfer import get_kind
    from ..transfer.estimate import estimate

    if "auto" in transfer_params(cfg).values():
        pre = "precompute: after its 'auto' choices (see prt precompute --dry-run)"
    else:
        e = estimate(get_kind(cfg["transfer"]["type"]), mesh, transfer_params(cfg), probe=False)
        pre = "precompute " + ", ".join(f"{st['stage']} {fb(st['bytes'])}" for st in e.stages) + f", peak {fb(e.peak_bytes)}"
    return (f"{pre}; benchmark peak {fb(mem['estimated_peak_bytes'])} (signal {fb(mem['signal_bytes'])}, codec workspace "
            f"{fb(mem['codec_workspace_bytes'])}, metrics {fb(mem['metrics_bytes'])}); cached transfers are not recomputed")


#: calibrations already timed in this process: (what) -> seconds
_TIMED: dict = {}
#: codecs whose fit time ``--dry-run`` estimates from a calibration fit on a synthetic signal
CALIBRATED_CODECS = ("vq", "pca", "cpca", "cpca_static", "cpca_iterative", "cpca_adaptive", "mrt_pca")


def stage_time(cfg: dict, mesh, mem: dict, rows: int = 1024, probe_vertices: int = 256, max_dim: int = 4096) -> str:
    """One line: each stage's estimated time. The precompute from
    :func:`prt_torch.transfer.estimate.estimate`'s probe (two chunks of the real run timed, scaled
    to every vertex; a cached transfer is not recomputed); each affine codec setting's fit + encode
    from a calibration fit of ``rows`` rows of a synthetic signal of the transfer's shape
    (``codecs.synthetic.transfer_like``), scaled by V / rows (each calibration once per process);
    signals wider than ``max_dim`` are not calibrated (their fixed per-cluster eigensolves of a
    D×D scatter dominate a small sample: the scaled figure would mislead, and the calibration
    alone would take tens of seconds). Estimates, said as such; the metrics' timing repeats are
    not estimated (they are ``metrics.repeats`` short relights)."""
    import time

    from .. import codecs
    from ..codecs.synthetic import transfer_like
    from ..harness.config import expand_codecs
    from ..harness.run import signal_shape, transfer_params
    from ..transfer import get_kind
    from ..transfer.estimate import estimate

    params = transfer_params(cfg)
    if "auto" in params.values():
        pre = "precompute: after its 'auto' choices (see prt precompute --dry-run)"
    else:
        key = (cfg["transfer"]["type"], mesh.content_hash(), repr(sorted(params.items())))
        if key not in _TIMED:
            e = estimate(get_kind(cfg["transfer"]["type"]), mesh, params, probe=True, probe_vertices=probe_vertices,
                         mesh_seconds=0.0)
            _TIMED[key] = e.seconds
        sec = _TIMED[key]
        pre = "precompute " + ("not estimated" if sec is None else f"~{sec:.3g} s (probe of {probe_vertices}-vertex chunks, unless cached)")
    V = mesh.num_vertices
    shape = signal_shape(cfg)
    if shape is None and cfg["transfer"]["type"] == "diffuse" and "auto" not in params.values():
        from ..transfer.estimate import result_bytes_per_vertex

        kw, _ = get_kind("diffuse").resolve(params)  # grey [V, n²] or RGB [V, 3, n²]: the mesh and bounces say which
        n2 = int(kw["bands"]) ** 2
        D = result_bytes_per_vertex("diffuse", kw, mesh)[0] // 4
        shape = (D, (D // n2, n2))
    parts = []
    if shape is not None and shape[0] > max_dim:
        parts.append(f"not estimated for D={shape[0]} > {max_dim}")
    elif shape is not None:
        n_out, n_in = shape[1]
        s_rows = min(V, rows)
        X = transfer_like(s_rows, n_out, n_in)
        for st in expand_codecs(cfg["codecs"]):
            kw = {k: v for k, v in st.items() if k != "type"}
            if st["type"] not in CALIBRATED_CODECS:
                parts.append(f"{st['type']} not estimated")
                continue
            key = (st["type"], repr(sorted(kw.items())), n_out, n_in, s_rows)
            if key not in _TIMED:  # once per setting and shape in this process (a sweep repeats them)
                c = codecs.get(st["type"], **kw)
                if ("warm", st["type"]) not in _TIMED:  # the family's first fit pays one-off costs (kernel
                    codecs.get(st["type"], **kw).fit_encode(X, matrix_shape=(n_out, n_in))  # loading, first-use
                    _TIMED[("warm", st["type"])] = 0.0  # allocations) a real run pays once, not per setting
                t = time.perf_counter()
                c.fit_encode(X, matrix_shape=(n_out, n_in))
                _TIMED[key] = time.perf_counter() - t
            parts.append(f"{st['type']} {','.join(f'{k}={v}' for k, v in kw.items())} ~{_TIMED[key] * V / s_rows:.3g} s")
    return (f"{pre}; codec fit + encode (calibration: {min(V, rows)} synthetic rows, scaled to {V}): "
            + ("; ".join(parts) if parts else "not estimated") + " — estimates")


def register(sub) -> None:
    p = sub.add_parser(
        "bench",
        help="run a benchmark config: transfer, every codec setting, PSNR/fps tables, plots, renders",
        description="Run a benchmark config (default: the packaged 'default'; also 'glossy', 'diffuse', or a YAML path). "
        "Outputs go to cache/ and reports/ under the current directory. Overrides are dotted "
        "key=value pairs parsed as YAML, e.g. transfer.bands=3 'codecs.0.vectors=[2,4]'. Lists expand into sweeps.",
    )
    p.add_argument("config", nargs="?", default=None, help="a packaged config name (default, glossy, diffuse) or a YAML path (default: default)")
    p.add_argument("overrides", nargs="*", help="key.path=value overrides")
    p.add_argument("--target-psnr", type=float, default=None,
                   help="find the cheapest setting meeting this PSNR (dB): of every codec family in the config, or of --target-codec")
    p.add_argument("--target-by", choices=["bytes", "fps"], default=None,
                   help="what 'cheapest' means across families: fewest bytes per vertex (default) or highest relighting rate")
    p.add_argument("--target-codec", default=None, help="search only this codec's --target-param (default: the config's target.codec)")
    p.add_argument("--target-param", default=None, help="integer size parameter to search (default: the config's target.param)")
    p.add_argument("--no-resume", action="store_true", help="recompute settings even if their records exist")
    p.add_argument("--no-render", action="store_true", help="skip the pyrender images")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--dry-run", action="store_true", help="validate and print the resolved config and sweep, memory and "
                   "estimated time per stage, do no work")
    p.add_argument("--no-time", action="store_true", help="with --dry-run: skip the time estimates (a precompute probe and "
                   "a calibration fit per codec setting: seconds per config)")
    add_executor_args(p, "the transfer's chunks and the codec settings")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def add_executor_args(p, what: str) -> None:
    """``--executor {local,ray}`` and ``--ray-address`` (shared with ``prt precompute``)."""
    from ..executor import EXECUTORS

    p.add_argument("--executor", choices=list(EXECUTORS), default="local",
                   help=f"where {what} run: 'local' (this process, default) or 'ray' (one Ray task each; needs "
                        "pip install 'prt-torch[ray]'; docs/ray.md)")
    p.add_argument("--ray-address", default=None, metavar="ADDR",
                   help="with --executor ray: join this Ray cluster (HOST:PORT from `ray start --head`, or 'auto'); "
                        "default: start a local Ray with every core")


def executor_from_args(args: argparse.Namespace, connect: bool = True):
    """The executor ``--executor``/``--ray-address`` ask for; checks that Ray is installed and
    (``connect``) connects to it before any work, so that an unreachable address is refused,
    naming it, before anything is created."""
    from ..executor import make_executor

    if args.ray_address is not None and args.executor != "ray":
        raise ValueError(f"--ray-address {args.ray_address!r} needs --executor ray (got --executor {args.executor})")
    ex = make_executor(args.executor, args.ray_address)
    if connect and hasattr(ex, "start"):
        ex.start()
    return ex


def run(args: argparse.Namespace) -> int:
    import json

    from ..harness.config import expand_codecs, expand_runs, load_config, part_configs
    from ..harness.run import run_benchmark

    overrides = list(args.overrides)
    if args.config is not None and "=" in args.config:  # `prt bench key=value ...` with the default config
        overrides.insert(0, args.config)
        args.config = None
    if args.no_render:
        overrides.append("render.enabled=false")
    if args.target_psnr is not None:
        overrides.append(f"target.psnr={args.target_psnr}")
    if args.target_by:
        overrides.append(f"target.by={args.target_by}")
    if args.target_codec:
        overrides.append(f"target.codec={args.target_codec}")
    if args.target_param:
        overrides.append(f"target.param={args.target_param}")
    executor = executor_from_args(args, connect=not args.dry_run)
    cfg = load_config(args.config, overrides)
    runs = expand_runs(cfg)
    if args.dry_run:
        from ..harness.run import ablation_values, load_mesh_within_budget

        for c in runs:
            for sub in [c] + part_configs(c):
                for _, one in ablation_values(sub):  # each value of a transfer ablation is its own transfer
                    mesh, mem = load_mesh_within_budget(one)  # the memory estimate the real run refuses on
                    print(f"# memory per stage, {mesh.name} ({mesh.num_vertices} vertices): " + stage_memory(one, mesh, mem))
                    if not args.no_time:
                        print(f"# time per stage: {stage_time(one, mesh, mem)}")
                if sub["target"].get("psnr") is not None:
                    from ..harness.target import search_cost

                    cost = search_cost(sub, mesh.num_vertices, mem["D"])
                    if sub["target"].get("codec"):
                        timed = "untimed, then the setting found timed"
                    elif sub["target"]["by"] == "fps":
                        timed = "every probe timed (target.by: fps)"
                    else:
                        timed = f"untimed, then the winner and each family's best timed (at most {len(cost) - 1})"
                    print(f"# target search: at most {cost.pop('total')} fits ("
                          + ", ".join(f"{k} {v}" for k, v in cost.items()) + f"; fewer with branch and bound on bytes), {timed}")
                if sub is not c:
                    print(f"# part {sub['name']!r}: {sub['_part']['note']}")
                print(json.dumps({k: v for k, v in sub.items() if not k.startswith("_")}, indent=2))
                print(f"# {len(expand_codecs(sub['codecs']))} codec settings")
        return 0
    if len(runs) > 1:  # a sweep: every point's checks before the first point runs
        from ..harness.run import ablation_values, load_mesh_within_budget

        for c in runs[1:]:
            for sub in [c] + part_configs(c):
                for _, one in ablation_values(sub):
                    try:
                        load_mesh_within_budget(one)
                    except ValueError as e:
                        raise ValueError(f"sweep point {c['name']!r}: {e}") from None
    failed = 0
    with executor:
        for c in runs:
            again = ("run the same command again without --no-resume to continue" if args.no_resume
                     else "run the same command again to continue")  # --no-resume again would recompute them all
            args.resume_hint = (f"finished settings are kept in {str(Path(c['output_dir']) / c['name'] / 'records')!r}; "
                                f"{again} (they are not recomputed)")
            out = run_benchmark(c, resume=not args.no_resume, progress=not args.quiet, executor=executor)
            print(f"report: {out / 'report.md'}")
            res = json.loads((out / "results.json").read_text())
            fails = list(res.get("failures") or []) + [f for part in res.get("parts") or [] for f in part["results"].get("failures") or []]
            for f in fails:
                print(f"prt bench: setting {f['setting_id']} failed after {f['attempts']} attempt(s): {f['error']}", file=sys.stderr)
            failed += len(fails)
    if failed:
        print(f"prt bench: {failed} setting(s) failed (listed in the report); run the same command again to retry them",
              file=sys.stderr)
        return 1
    return 0
