"""``prt compress TRANSFER.prt --codec cpca --clusters 64 --vectors 8 -o out.prt``

Fits a codec (prt_torch.codecs, by registry name) on the transfer signal of a transfer file
(io kind ``transfer/<kind>``: tensor ``data [V, ...]``, each vertex's data flattened to a row;
``meta['matrix_shape']`` or the data's trailing two axes give the matrix shape) and writes the
fitted codec with its encoding (io kind ``codec/<name>``; ``prt info`` reads it). Any codec
parameter can be given with ``--param KEY=VALUE`` (YAML scalars); ``prt compress --list``
shows the codecs and ``prt compress --describe NAME`` their parameters (defaults and docs of
the codec class; see docs/codecs.md).

``prt compress TRANSPORT_DIR --codec gaussian --param lobes=2 -o out.prt`` fits Green 2005's
spherical Gaussians to a transport table directory (``prt precompute --kind transport``); the
views, cube texels and mesh faces come from the table. ``--json`` reports ``relative_l2``, the
fit's relative L2 error over all functions (‖T̃ − T‖/‖T‖ with texel solid angles for the
Gaussian codec; √(relative SE) for the others).
"""
from __future__ import annotations

import json
import sys
import time


def register(subparsers) -> None:
    p = subparsers.add_parser("compress", help="compress a transfer file with a codec (VQ, PCA, CPCA, MRT-PCA)")
    p.add_argument("transfer", nargs="?", help="transfer file (.prt, io kind transfer/*) or a transport table directory")
    p.add_argument("-o", "--output", help="output codec file (.prt)")
    p.add_argument("--codec", default="cpca", help="codec name (see --list); default cpca")
    p.add_argument("--clusters", type=int, help="number of clusters m_c (vq, cpca)")
    p.add_argument("--vectors", type=int, help="PCA vectors n' per cluster (pca, cpca, mrt_pca)")
    p.add_argument("--method", help="cpca method: static | iterative | adaptive")
    p.add_argument("--budget", type=float, help="adaptive cpca: mean PCA weights per point")
    p.add_argument("--seed", type=int, help="random seed")
    p.add_argument("--param", action="append", default=[], metavar="KEY=VALUE",
                   help="any other codec parameter (repeatable), value parsed as YAML")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output file")
    p.add_argument("--stream", action="store_true",
                   help="fit from the transfer file memory-mapped: the signal is not read into memory, the codec reads it "
                        "by chunks (vq, pca, cpca, mrt_pca; docs/codecs.md). Larger signals than memory work this way")
    p.add_argument("--dry-run", action="store_true",
                   help="print what the fit will hold (signal, copies, work, bookkeeping, codes), whether it streams, and its "
                        "estimated time (a calibration fit of a sample of rows, scaled); writes nothing")
    p.add_argument("--memory-limit", type=float, default=None, metavar="GIB",
                   help="GiB; refuse a fit estimated above it before reading the signal (default 60%% of RAM)")
    p.add_argument("--list", action="store_true", help="list codec names and exit")
    p.add_argument("--describe", metavar="NAME", help="show the parameters of codec NAME and exit")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def _params(args) -> dict:
    from ..params import parse_assignments

    params = {k: getattr(args, k) for k in ("clusters", "vectors", "method", "budget", "seed") if getattr(args, k) is not None}
    params.update(parse_assignments(args.param, what="--param"))
    return params


def load_signal(path):
    """``(X [V, D] float32, matrix_shape or None, meta)`` from a transfer file."""
    import torch

    from .. import io

    from ..transfer import check_transfer_values

    tensors, meta = io.load(path, expect_kind="transfer/")
    check_transfer_values(path, tensors, meta)  # what render and validate refuse, refused here too
    data = tensors["data"]
    if data.ndim < 2:
        raise ValueError(f"{str(path)!r}: data has shape {tuple(data.shape)}; accepted: [V, ...]")
    ms = meta.get("matrix_shape")
    if ms is None and data.ndim == 3:
        ms = list(data.shape[1:])
    X = data.reshape(data.shape[0], -1).to(torch.float32)
    return X, (tuple(int(v) for v in ms) if ms else None), meta


def load_input(path, codec):
    """``(X [V, D] float32, matrix_shape, meta, fit keywords)`` from a transfer file or a
    transport table directory; a codec with light kind 'prefiltered' (gaussian) takes only
    the latter — refused (reading only metadata) before any data is loaded."""
    from pathlib import Path

    from .. import io

    p = Path(path)
    wants_transport = getattr(codec, "light_kind", "sh") == "prefiltered"
    if p.is_dir():
        from ..harness.evaluate import load_directory_transfer

        if not (p / "manifest.json").is_file():
            raise FileNotFoundError(f"{str(path)!r} is a directory without manifest.json; accepted: a transfer file or a "
                                    "transport table directory (prt precompute --kind transport)")
        tr = load_directory_transfer(p)
        X = tr.data.reshape(tr.data.shape[0], -1)
        ms = tuple(tr.meta["matrix_shape"])
        geometry = {"views": tr.meta["views"], "faces": tr.mesh.faces, "kind": "transport"} if wants_transport else {}
        return X, ms, dict(tr.meta, kind="transfer/transport", mesh_hash=tr.mesh.content_hash()), geometry
    if wants_transport:
        kind = io.load_meta(path).get("kind")
        raise ValueError(f"codec {codec.codec_name!r} fits transport tables; {str(path)!r} holds {kind!r}; accepted: a "
                         "transport table directory (prt precompute --kind transport -o DIR)")
    kind = io.load_meta(path).get("kind")
    if kind == "transfer/wavelet":
        raise ValueError(f"{str(path)!r} is a wavelet transfer (sparse Haar coefficients, Ng 2003), which codec "
                         f"{codec.codec_name!r} cannot take (it compresses SH transfer rows); accepted: an SH transfer "
                         "(diffuse, glossy, mrt); a wavelet transfer is already sparse: relight it with prt relight or "
                         "prt bench")
    X, ms, meta = load_signal(path)
    return X, ms, meta, {}


def _mapped_input(path):
    """``(X [V, D] float32 numpy memmap, matrix_shape, meta, {})`` of a transfer file, not read
    into memory (``io.load_mmap``); the values are checked by the codec as it reads them."""
    from pathlib import Path

    from .. import io

    if Path(path).is_dir():
        raise ValueError(f"--stream takes a transfer file; {str(path)!r} is a directory")
    d = io.describe(path)
    meta = d["meta"]
    if not str(meta.get("kind", "")).startswith("transfer/") or meta.get("kind") == "transfer/wavelet":
        raise ValueError(f"--stream: {str(path)!r} holds kind={meta.get('kind')!r}; accepted: an SH transfer file (diffuse, glossy, mrt)")
    if d["tensors"]["data"]["dtype"] != "F32":
        raise ValueError(f"--stream: {str(path)!r} stores its data as {d['tensors']['data']['dtype']}; accepted: float32 (F32)")
    shape = d["tensors"]["data"]["shape"]
    ms = meta.get("matrix_shape") or (shape[1:] if len(shape) == 3 else None)
    X = io.load_mmap(path, "data").reshape(shape[0], -1)
    return X, (tuple(int(v) for v in ms) if ms else None), meta, {}


def fit_plan(args, codec) -> dict:
    """``codecs.chunks.fit_memory`` of this fit from the file's header only (``P``, ``D``, the
    codec's clusters and vectors; streamed with ``--stream``), with ``'P'``, ``'D'`` and the budget
    (``--memory-limit``, default 60% of RAM: ``transfer.glossy.memory_budget``)."""
    from .. import io
    from ..codecs.chunks import fit_memory
    from ..transfer.glossy import memory_budget

    shape = io.describe(args.transfer)["tensors"]["data"]["shape"]
    P, D = int(shape[0]), 1
    for v in shape[1:]:
        D *= int(v)
    p = codec.get_params()
    m = fit_memory(P, D, p.get("clusters", 1), p.get("vectors", 0), streamed=True if args.stream else None)
    m.update(P=P, D=D, budget=memory_budget(None if args.memory_limit is None else int(args.memory_limit * (1 << 30))))
    return m


#: rows of the calibration fit ``--dry-run`` times (at least 64 per cluster, at most the signal)
CALIBRATION_ROWS = 16384


def calibrate(args, codec, P: int, streamed: bool) -> tuple[float, str]:
    """(estimated seconds of the fit + encode, how): the same codec fitted on ``s`` evenly spaced
    rows of the memory-mapped signal (streamed like the real fit when it streams), timed after a
    warm-up on 256 rows, scaled by P / s — an estimate: Lloyd's iterations to converge and the
    fixed costs (seeding on a fixed sample, per-cluster eigensolves) do not scale with P."""
    import time

    import numpy as np
    import torch
    from sklearn.base import clone

    from .. import io

    X = io.load_mmap(args.transfer, "data")
    X = X.reshape(X.shape[0], -1)
    K = int(codec.get_params().get("clusters", 1) or 1)
    s = min(P, max(CALIBRATION_ROWS, 64 * K))
    idx = np.unique(np.linspace(0, P - 1, s).round().astype(np.int64))
    sample = torch.from_numpy(np.ascontiguousarray(X[idx], dtype=np.float32))
    warm = clone(codec)
    warm.fit_encode(sample[:max(256, 2 * K)])
    c = clone(codec)
    if streamed:
        c.stream_bytes_ = 0  # read by chunks, as the real fit of the mapped file
    t = time.perf_counter()
    c.fit_encode(sample)
    dt = time.perf_counter() - t
    return dt * P / idx.size, f"calibration: {idx.size} rows fitted and encoded in {dt:.3g} s, × {P / idx.size:.3g}"


def _dry_run(args, codec) -> int:
    """What the fit will hold, from the file's header (``codecs.chunks.fit_memory``), and how long
    it will take (:func:`calibrate`)."""
    from .. import io

    m = fit_plan(args, codec)
    P, D = m["P"], m["D"]
    f = io.format_bytes
    print(f"{args.codec}: {P} points × D={D}; the fit {'streams the signal by chunks' if m['streamed'] else 'holds the signal in memory'}"
          + (" (--stream: from the memory-mapped file)" if args.stream else ""))
    print(f"  signal loaded {f(m['signal'])}, centred and tile-ordered copies {f(m['copies'])}, chunk work {f(m['work'])}, "
          f"bookkeeping {f(m['bookkeeping'])}, codes {f(m['codes'])}, fixed blocks {f(m['fixed'])}")
    seconds, how = calibrate(args, codec, P, m["streamed"])
    print(f"  peak ~{f(m['peak'])} (the counted sum × the allocator slack, plus the fixed blocks; nothing written); "
          f"budget {f(m['budget'])} ({'fits' if m['peak'] <= m['budget'] else 'does NOT fit'})")
    print(f"  time ~{seconds:.3g} s fit + encode (an estimate; {how})")
    check_plan(args, m)
    return 0


def check_plan(args, m: dict) -> None:
    """Refuse (ValueError, one line naming the sizes) a fit whose estimated peak exceeds the budget."""
    from .. import io

    if m["peak"] <= m["budget"]:
        return
    f = io.format_bytes
    hint = ("the fit already streams; accepted: fewer clusters or vectors, or a larger --memory-limit on a machine that has it"
            if m["streamed"] else "accepted: --stream (the signal is then read from the file by chunks), fewer clusters or "
            "vectors, or a larger --memory-limit")
    raise ValueError(f"{args.codec} fit of {m['P']} points × D={m['D']} needs about {f(m['peak'])} at its peak (signal "
                     f"{f(m['signal'])}, copies {f(m['copies'])}, work {f(m['work'])}, bookkeeping {f(m['bookkeeping'])}, "
                     f"codes {f(m['codes'])}) but the budget is {f(m['budget'])}; {hint}")


def run(args) -> int:
    from .. import codecs
    from ..codecs import ConvergenceError

    if args.list:
        for name in codecs.available():
            print(f"{name:16s} {codecs.describe(name)['doc']}")
        return 0
    if args.describe:
        d = codecs.describe(args.describe)
        print(f"{d['name']}: {d['doc']}")
        for k, v in d["params"].items():
            fixed = " (fixed by this name)" if v["fixed"] else ""
            print(f"  {k} = {v['default']!r}{fixed}: {v['doc']}")
        return 0
    if not args.transfer or not args.output:
        raise ValueError("prt compress needs TRANSFER (input file) and -o OUTPUT (or --list / --describe NAME)")
    params = _params(args)
    if "progress" not in params and "progress" in codecs.describe(args.codec)["params"] and sys.stderr.isatty():
        params["progress"] = True  # a codec with a progress bar (the learned codec's loss) shows it on a terminal
    codec = codecs.get(args.codec, **params)  # validates name and parameters before any work

    from ..io import check_outputs

    affine = args.codec in ("vq", "pca", "cpca", "cpca_static", "cpca_iterative", "cpca_adaptive", "mrt_pca")
    if (args.stream or args.dry_run) and not affine:
        raise ValueError(f"--stream/--dry-run with codec {args.codec!r}: it fits in memory only; accepted: vq, pca, cpca "
                         "(and its presets), mrt_pca")
    import math

    if args.memory_limit is not None and not (math.isfinite(args.memory_limit) and 0 < args.memory_limit <= 1 << 20):
        raise ValueError(f"--memory-limit {args.memory_limit!r} GiB; accepted: a finite number of GiB in (0, 1048576]")
    # before the fit, and before a dry run, which refuses what the run would (as prt precompute's and prt relight's do)
    check_outputs({"-o/--output": args.output}, {"TRANSFER": args.transfer}, args.overwrite)
    if args.dry_run:
        return _dry_run(args, codec)
    from pathlib import Path

    if affine and not Path(args.transfer).is_dir():
        check_plan(args, fit_plan(args, codec))  # before the signal is read: what cannot fit even streamed
    X, ms, meta, geometry = _mapped_input(args.transfer) if args.stream else load_input(args.transfer, codec)
    t0 = time.perf_counter()
    try:
        enc = codec.fit_encode(X, matrix_shape=ms, **geometry)
    except ConvergenceError as e:
        raise ValueError(str(e)) from None
    secs = time.perf_counter() - t0
    st = codec.storage(enc)
    codec.save(args.output, enc, overwrite=args.overwrite,
               extra_meta={"source": str(args.transfer), "source_kind": meta.get("kind"),
                           "mesh_hash": meta.get("mesh_hash"), "encode_seconds": secs})
    info = codec.fit_info_
    summary = {
        "output": args.output, "codec": args.codec, "params": codec.get_params(), "points": X.shape[0], "dim": X.shape[1],
        "matrix_shape": ms, "encode_seconds": secs, "se": info.get("se"), "se_relative": info.get("se_relative"),
        "bytes_total": st["bytes_total"], "compression_ratio": st["compression_ratio"],
        "sloan_cost_floats": st["sloan_cost_floats"],
        "relative_l2": info.get("relative_l2", (info.get("se_relative") or 0.0) ** 0.5),
    }
    for k in ("functions", "functions_fitted", "converged_fraction", "relative_l2_median", "functions_per_s"):
        if k in info:
            summary[k] = info[k]
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
    else:
        print(f"{args.codec}: {X.shape[0]} points × D={X.shape[1]}"
              + (f" ({ms[0]}×{ms[1]})" if ms else "") + f" encoded in {secs:.2f} s")
        print(f"  SE {info.get('se'):.6g} (relative {info.get('se_relative'):.3g}, relative L2 {summary['relative_l2']:.4g}); "
              f"{st['bytes_total']} bytes, ratio {st['compression_ratio']:.1f}:1 vs float32; "
              f"Sloan cost {st['sloan_cost_floats']} floats")
        print(f"  wrote {args.output}")
    return 0
