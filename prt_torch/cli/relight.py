"""``prt relight TRANSFER_OR_CODEC.prt --light SPEC [--terms N] [--view X,Y,Z] -o OUT.npy|OUT.ply``

Each vertex's exit radiance under a light, without rendering: ``.npy`` writes ``[V, C]`` float32
(C = 3, RGB; the numbers), ``.ply`` the mesh with vertex colours (tone-mapped sRGB, one exposure
for the whole mesh, ``--exposure``) for a mesh viewer. Every kind:

* SH transfer (diffuse, glossy, MRT): the light projected to the transfer's bands, relit through
  :mod:`prt_torch.relight` (the project's uncompressed reference);
* a codec file (``prt compress`` output): relit from the compressed form (``codec.relight``),
  its mesh, frames and albedo from the transfer it was compressed from (``--transfer``, default
  the path the codec file records; refused when it does not belong to it);
* transport tables (``prt precompute --kind transport``, a directory) and their codec files (the
  Gaussian codec): relit toward the camera through the harness's evaluator, as ``prt render``;
* a wavelet transfer (``prt precompute --kind wavelet``): the light on the cube at the transfer's
  R (not band-limited), its ``--terms`` N largest Haar coefficients by ``--selection`` (default:
  all 6R², the exact pixel-basis result), sparse light × sparse transfer
  (:class:`prt_torch.relight.WaveletRelighter`; Ng et al. 2003). ``--arith``: the dense terms' arithmetic
  (``auto``, the default: int16 VNNI dot products on a CPU with AVX-512 VNNI where the call allows, within a stated
  bound, at the median vertex no more than the stored 16-bit transfer's own error, more at dim vertices and in HDR
  shadows; ``float``: the float32 loop, the bits of every other CPU; docs/wavelet.md).

View-dependent kinds (glossy, MRT, transport tables) take the camera position ``--view X,Y,Z`` (default: the
camera ``prt render`` places by default); view-independent ones refuse it.

Larger than memory (issue 42 part 3): an SH transfer is memory-mapped (``Transfer.load(mmap=True)``:
only the rows being relit are read) and relit by chunks of :data:`CHUNK_VERTICES` vertices, each
written at once into the ``.npy`` through ``np.lib.format.open_memmap`` (``io.streamed_npy``: a
``.partial`` file renamed at the end, removed on an interruption), so neither the transfer nor the
``[V, 3]`` output is held. A codec file's source transfer is mapped too (only its mesh is read).
``--dry-run`` prints each stage's memory and an estimated time (a calibration relight of the first
chunk, scaled to every vertex) and writes nothing; a run whose estimate exceeds the budget
(``--memory-limit``, default 60% of RAM) is refused before any work, naming the sizes.
"""
from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

OUT_EXTS = (".npy", ".ply")
#: vertices per chunk when an SH transfer is relit (and streamed to the .npy) by chunks: the
#: chunk's rows (≤ 4 KiB each for MRT 11×11 × 5 bands), its view weights and its output
CHUNK_VERTICES = 1 << 15


def _vector(text: str) -> list[float]:
    import math

    try:
        v = [float(p) for p in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"--view {text!r}; accepted: a camera position X,Y,Z (three finite numbers)")
    return v


def register(subparsers) -> None:
    p = subparsers.add_parser("relight", help="per-vertex exit radiance of any transfer or codec file under a light (.npy/.ply)",
                              description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("transfer", metavar="TRANSFER_OR_CODEC.prt")
    p.add_argument("--light", required=True, help="built-in environment, analytic spec or image file")
    p.add_argument("--terms", type=int, default=None,
                   help="wavelet transfers: the light's N largest Haar terms (default: all 6R², exact)")
    p.add_argument("--selection", default=None, choices=["magnitude", "area", "transport"],
                   help="wavelet transfers: how the N terms are chosen (Ng 2003 §5; default transport-weighted, measured in "
                        "reports/benchmarks/wavelet.md)")
    p.add_argument("--arith", default=None, choices=["auto", "float"],
                   help="wavelet transfers: the kernel's dense arithmetic (default auto: int16 VNNI dot products on a CPU with "
                        "AVX-512 VNNI where the call allows, else float32; float: the float32 loop everywhere, the same bits "
                        "on every CPU)")
    p.add_argument("--transfer", dest="source", default=None, metavar="TRANSFER.prt",
                   help="codec files: the transfer it was compressed from (default: the path the codec file records)")
    p.add_argument("--view", type=_vector, default=None, metavar="X,Y,Z",
                   help="glossy/MRT: camera position in world space (default: prt render's default camera)")
    p.add_argument("--exposure", default="auto", help=".ply: stops (EV) for the vertex colours, or 'auto'")
    p.add_argument("-o", "--output", required=True, help="output: .npy ([V, 3] float32) or .ply (mesh with vertex colours)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--dry-run", action="store_true",
                   help="print each stage's memory and estimated time (a calibration relight of one chunk), write nothing")
    p.add_argument("--memory-limit", type=float, default=None, metavar="GIB",
                   help="GiB; refuse a run estimated above it before any work (default 60%% of RAM)")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def _transport(table: str, light: str, view, codec_file: str | None = None):
    """Green 2005 transport tables (a directory) relit toward the camera ``view`` (default: prt
    render's), uncompressed or from a codec file (e.g. the Gaussian codec), through the harness's
    evaluator as ``prt render`` does: ``([V, 3] float32, description)``."""
    import torch

    from .. import codecs
    from ..harness.evaluate import Evaluator, load_directory_transfer
    from ..lighting import load_light
    from ..render import Camera

    tr = load_directory_transfer(table)
    ev = Evaluator(tr)
    eye = torch.tensor(view, dtype=torch.float64) if view is not None else torch.as_tensor(Camera.fit(tr.mesh).eye).double()
    vw = ev.view_weights(eye)
    L = load_light(light, bands=ev.bands_in)
    if codec_file is None:
        out, what = ev.uncompressed(L, vw), "transport tables"
    else:
        codec, enc = codecs.load(codec_file)
        if enc.points != ev.V or enc.meta.get("dim") != ev.X.shape[1]:
            raise ValueError(f"codec file {codec_file!r} ({enc.points} points x {enc.meta.get('dim')}) does not belong to the "
                             f"transport table {table!r} ({ev.V} vertices x {ev.X.shape[1]}); accepted: a codec file compressed "
                             "from this table (--transfer TABLE_DIR)")
        out, what = ev.finish(codec.relight(enc, ev.codec_light(codec, L), view=vw)), f"transport tables, codec {codec.codec_name}"
    out = out.to(torch.float32)
    return (out.expand(-1, 3) if out.shape[1] == 1 else out).contiguous(), what


def _load(args):
    """(transfer, codec or None, encoding or None) for the input file."""
    from .. import io
    from ..transfer import Transfer

    kind = str(io.load_meta(args.transfer).get("kind", ""))
    if kind.startswith("codec/"):
        from ..render import PRTScene, check_codec_file

        meta = io.load_meta(args.transfer)
        src = args.source or (meta.get("extra") or {}).get("source")
        if src and Path(src).is_dir():  # compressed transport tables (e.g. the Gaussian codec)
            return src, "transport", None
        if not src or not Path(src).is_file():
            raise FileNotFoundError(f"codec file {args.transfer!r}: its transfer {src!r} is not a file; accepted: "
                                    "--transfer TRANSFER.prt, the file it was compressed from (its mesh, frames and albedo)")
        transfer = Transfer.load(src, mmap=True)  # its mesh, frames and albedo: the data is mapped, not read
        codec, enc = check_codec_file(args.transfer, PRTScene(transfer))
        return transfer, codec, enc
    if not kind.startswith("transfer/"):
        raise ValueError(f"{args.transfer!r} holds {kind!r}; accepted: a transfer file (prt precompute) or a codec file "
                         "(prt compress)")
    if args.source is not None:
        raise ValueError("--transfer applies to codec files; the input is a transfer")
    return Transfer.load(args.transfer, mmap=kind != "transfer/wavelet"), None, None  # SH rows: read by chunks


def radiance(transfer, light: str, codec=None, enc=None, terms: int | None = None, selection: str = "transport",
             view=None, out=None, rows: int | None = None, record: dict | None = None, arith: str = "auto"):
    """Per-vertex exit radiance ``[V, 3]`` float32 and a one-line description (module docstring).
    A wavelet transfer: relit with ``arith`` (``WaveletRelighter(arith=)``: ``'auto'`` or ``'float'``, the dense
    terms' arithmetic, named in the description); ``record`` (a dict, when given) receives the light's record (``relight.wavelet_light``:
    ``terms``, the terms kept, ``terms_requested``, ...); ``--terms`` N above the light's nonzero Haar terms keeps
    those (the same result) and says so in one warning line.

    An uncompressed SH transfer is relit by chunks of ``rows`` (default :data:`CHUNK_VERTICES`) vertices (``PRTScene.cpu_radiance``
    with ``rows=``; the same bits whether its data is in memory or memory-mapped), each written into
    ``out`` (a ``[V, 3]`` float32 tensor, e.g. over the memory map of the output file) when given.
    Other inputs (codec, wavelet) are computed whole and copied into ``out``."""
    import torch

    from .. import relight
    from ..lighting.haar import ZERO_TERM

    if transfer.kind == "wavelet":
        if codec is not None:  # pragma: no cover - compress refuses wavelet transfers
            raise ValueError("a wavelet transfer has no codec files")
        if view is not None:
            raise ValueError("--view applies to glossy and MRT transfers; a wavelet transfer is diffuse (view-independent)")
        r = relight.WaveletRelighter(transfer, arith=arith)
        li, lv, rec = r.light(light, terms, selection)
        if record is not None:
            record.update(rec)
        n = int(li.numel())
        if terms is not None and n < min(terms, r.P):  # select_terms keeps the light's nonzero terms only
            zero = f"the rest are zero: at most {ZERO_TERM:g} of its largest"
            warnings.warn((f"--terms {terms} is more than the light's {r.P} Haar terms at R = {r.res} (6R²), of which "
                           f"{light!r} has {n} nonzero ({zero})" if terms > r.P else
                           f"--terms {terms}: the light {light!r} has {n} nonzero Haar terms of {r.P} at R = {r.res} ({zero})")
                          + f"; {n} are used, the same result as all")
        elif terms is not None and terms > r.P:
            warnings.warn(f"--terms {terms} is more than the light's {r.P} Haar terms at R = {r.res} (6R²); all {r.P} are used")
        if rec.get("upsampled"):
            warnings.warn(rec["warning"])
        res = r(li, lv)
        if res.shape[1] == 1:
            res = res.expand(-1, 3)
        dense = "int16 vnni" if r._takes_vnni(li, lv.to(torch.float32)) else "float"
        return _into(res.contiguous(), out), (f"wavelet R={r.res}, {li.numel()} of {r.P} light terms ({selection}, dense "
                                              f"{dense}), "
                                              f"{r.touched(li)} transfer coefficients read, relighter holds "
                                              f"{r.held_bytes()['total'] / r.V:.0f} B/vertex")
    if terms is not None:
        raise ValueError(f"--terms {terms} applies to wavelet transfers; a {transfer.kind} transfer takes the light in "
                         "its own SH bands")
    scene, L, eye = _sh_setup(transfer, light, view)
    bands = int(round(scene.n_in ** 0.5))
    what = f"{transfer.kind} transfer, {bands} bands" + (f", codec {codec.codec_name}" if codec is not None else "")
    if codec is not None:
        return _into(scene.cpu_radiance(L, None if eye is None else scene.view(eye), codec, enc), out), what
    res = torch.empty(scene.V, 3, dtype=torch.float32) if out is None else out
    rows = CHUNK_VERTICES if rows is None else int(rows)
    for a in range(0, scene.V, rows):  # by chunks: only these rows of a mapped transfer are read
        sl = slice(a, min(scene.V, a + rows))
        res[sl] = scene.cpu_radiance(L, None if eye is None else scene.view(eye, sl), rows=sl)
    return res, what


def _sh_setup(transfer, light: str, view):
    """``(PRTScene, light [C, n²], eye [3] float64 or None)`` of an SH transfer for :func:`radiance`."""
    import torch

    from ..lighting import load_light
    from ..render import Camera, PRTScene

    scene = PRTScene(transfer)
    eye = None
    if scene.needs_view:
        eye = torch.tensor(view, dtype=torch.float64) if view is not None else torch.as_tensor(Camera.fit(transfer.mesh).eye)
    elif view is not None:
        raise ValueError(f"--view applies to glossy and MRT transfers; a {transfer.kind} transfer is view-independent")
    return scene, load_light(light, bands=int(round(scene.n_in ** 0.5))), eye


def _into(res, out):
    """``res`` copied into ``out`` (when given; returned), else ``res``."""
    if out is None:
        return res
    out[:] = res
    return out


def _write_ply(path: Path, mesh, rgb: np.ndarray, exposure: str, overwrite: bool) -> tuple[float, int]:
    """Write the mesh with vertex colours sRGB(clip(radiance · 2^EV, 0, 1)); returns (EV, the vertices
    with a channel clipped at white, i.e. radiance above 2^-EV: 'auto' puts the 99th percentile of
    luminance at 0.8, so about the brightest 1% and any channel beyond)."""
    import trimesh

    from .. import io
    from ..render import auto_exposure
    from ..render.images import to_display

    img = rgb[None].astype(np.float32)  # [1, V, 3] as an image row
    ev = auto_exposure(img) if exposure == "auto" else float(exposure)
    cols = to_display(img, ev)[0]
    tm = trimesh.Trimesh(mesh.vertices.numpy(), mesh.faces.numpy(), process=False,
                         vertex_colors=np.concatenate([cols, np.full((cols.shape[0], 1), 255, np.uint8)], 1))
    data = trimesh.exchange.ply.export_ply(tm, encoding="binary", vertex_normal=False)
    with io.atomic_path(path, overwrite=overwrite) as tmp:
        Path(tmp).write_bytes(data)
    return ev, int((rgb.astype(np.float64) * 2.0 ** ev > 1.0).any(1).sum())


def _tensor_bytes(info: dict) -> int:
    """Bytes of one tensor from ``io.describe``'s ``{'shape', 'dtype'}``."""
    n = 1
    for d in info["shape"]:
        n *= int(d)
    return n * {"F64": 8, "I64": 8, "F32": 4, "I32": 4, "F16": 2, "I16": 2, "U8": 1, "I8": 1, "BOOL": 1}.get(info["dtype"], 4)


def plan(args) -> dict:
    """What the run will hold, from the files' headers only (no data read): ``{'V', 'stages':
    [{'stage', 'bytes', 'note'}], 'peak', 'budget', 'streamed'}``. Stages: *input* (the mesh and
    what :class:`~prt_torch.render.PRTScene` derives from it — frames, points, albedo —; an SH
    transfer's data is memory-mapped: its pages are page cache, not counted; a codec's codes,
    a wavelet transfer's coefficients and transport tables are loaded whole), *relight* (one chunk's
    rows, view weights and output; a codec, wavelet or table: the whole ``[V, 3]`` result and its
    work), *output* (``.npy``: written chunk by chunk through a file mapping, not held; ``.ply``: the
    colours and the trimesh mesh whole). Peak = the sum × ``transfer.estimate.ALLOCATOR_SLACK``. A wavelet
    transfer: :func:`_wavelet_plan` (*held* and *build* stages besides; a dry run reads the file's coefficients,
    mapped, to count them)."""
    from .. import io

    fb = io.format_bytes
    src = Path(args.transfer)
    if src.is_dir():  # transport tables: the evaluator loads the table whole
        size = sum(f.stat().st_size for f in src.rglob("*") if f.is_file())
        V = int(json_load(src / "manifest.json").get("vertices", 0) or 0) if (src / "manifest.json").is_file() else 0
        stages = [{"stage": "input", "bytes": 2 * size, "note": f"transport tables {fb(size)} loaded whole (and weighted)"},
                  {"stage": "relight", "bytes": V * 3 * 8, "note": "the whole result at once"}]
        streamed, kind = False, "transport"
    else:
        d = io.describe(src)
        kind = str(d["meta"].get("kind", ""))
        codes = 0
        if kind.startswith("codec/"):
            codes = sum(_tensor_bytes(t) for t in d["tensors"].values())
            srcf = args.source or (d["meta"].get("extra") or {}).get("source")
            if srcf and Path(srcf).is_file():
                d = io.describe(srcf)
            elif srcf and Path(srcf).is_dir():
                return plan(type(args)(**{**vars(args), "transfer": srcf, "source": None}))
        t = d["tensors"]
        if "data" not in t:
            raise ValueError(f"{str(src)!r}: no transfer data to plan from; accepted: a transfer or codec file")
        V = int(t["data"]["shape"][0])
        mesh = sum(_tensor_bytes(v) for k, v in t.items() if k.startswith("mesh."))
        data = sum(_tensor_bytes(v) for k, v in t.items() if k == "data" or k.startswith("aux."))
        scene = V * (72 + 24 + 12)  # PRTScene: frames float64, points float64, albedo float32
        row = _tensor_bytes(t["data"]) // max(V, 1)
        wavelet = d["meta"].get("kind") == "transfer/wavelet"
        if codes:
            inp, note = mesh + scene + codes, f"mesh {fb(mesh)} + frames {fb(scene)}, codes {fb(codes)}; the source's data mapped, not read"
            work, wnote = V * 3 * 4 * 3, "the whole [V, 3] result at once (a codec relights every point in one call)"
        elif wavelet:
            return _wavelet_plan(args, V, mesh, data)
        else:
            k = min(V, CHUNK_VERTICES)
            inp, note = mesh + scene, f"mesh {fb(mesh)} + frames {fb(scene)}; the data ({fb(data)}) memory-mapped, read by chunks"
            work, wnote = k * (2 * row + 200 + 12), f"one chunk of {k} vertices (rows, view weights, output)"
        stages = [{"stage": "input", "bytes": inp, "note": note}, {"stage": "relight", "bytes": work, "note": wnote}]
        streamed = not codes and not wavelet
    return _finish_plan(args, V, kind, stages, streamed)


def _finish_plan(args, V: int, kind: str, stages: list, streamed: bool, how: str = "chunk by chunk ") -> dict:
    """:func:`plan`'s *output* stage appended to ``stages``, the budget and the peak (the sum × ALLOCATOR_SLACK)."""
    from .. import io
    from ..transfer.estimate import ALLOCATOR_SLACK
    from ..transfer.glossy import memory_budget

    fb = io.format_bytes
    if Path(args.output).suffix.lower() == ".npy":
        stages.append({"stage": "output", "bytes": 0, "note": f"{fb(V * 12)} .npy written {how}through a file "
                                                            "mapping (a .partial renamed at the end), not held"})
    else:
        stages.append({"stage": "output", "bytes": V * 64, "note": f".ply: colours and the mesh for trimesh, whole ({fb(V * 64)})"})
    budget = memory_budget(None if args.memory_limit is None else int(args.memory_limit * (1 << 30)))
    peak = int(ALLOCATOR_SLACK * sum(st["bytes"] for st in stages))
    return {"V": V, "kind": kind, "stages": stages, "peak": peak, "budget": budget, "streamed": streamed}


#: a wavelet light's rasterisation (``relight.wavelet_light``) works in blocks of sub-texel directions
#: (``lighting.haar.sub_texel_blocks``, ``Environment.from_function``'s row blocks): bytes per direction of a block
#: (its directions, solid angles, the light there and the temporaries, float64) and per cube texel (the cube, its
#: Haar transform, the term selection); fitted with a margin to the peak RSS growth of the light's path in a fresh
#: process (sky, studio, a 20° cap, constant, hemisphere; supersample 4): 12.0-13.5 MiB at R = 64, 27.4-30.6 MiB at
#: R = 128, 3.3-7.9 MiB at R = 32 (before the blocks: 78-99 MiB at R = 64, ~200-263 B per sub-texel direction)
LIGHT_BLOCK_SAMPLE_BYTES, LIGHT_TEXEL_BYTES = 400, 320


def light_bytes(res: int, supersample: int = 4) -> int:
    """The peak bytes of a wavelet light's rasterisation and transform on the cube at face size ``res``: one block of
    sub-texel directions (at most ``lighting.haar.LIGHT_BLOCK_SAMPLES``) × :data:`LIGHT_BLOCK_SAMPLE_BYTES` plus
    :data:`LIGHT_TEXEL_BYTES` per texel (6 res²)."""
    from ..lighting.haar import LIGHT_BLOCK_SAMPLES

    P = 6 * res * res
    return min(P * supersample * supersample, LIGHT_BLOCK_SAMPLES) * LIGHT_BLOCK_SAMPLE_BYTES + P * LIGHT_TEXEL_BYTES


def _wavelet_plan(args, V: int, mesh: int, data: int, exact: bool | None = None) -> dict:
    """:func:`plan` of a wavelet transfer: *input* (the mesh and the file's coefficients, loaded whole),
    *held* (:meth:`~prt_torch.relight.WaveletRelighter.estimate_bytes`: its kernel layouts — dense
    columns, column-major blocks, the row-major copy 'auto' builds for a light that takes that pass: counted from the
    file, for ``args.light`` with its ``--terms`` and ``--selection``, counted or not as the relighter will build it;
    the header's bound counts it whatever the light — and
    tables, as :meth:`~prt_torch.relight.WaveletRelighter.held_bytes` will report them), *build|light* (the
    larger of its construction's temporaries and the light's rasterisation on the cube at R,
    :func:`light_bytes`, a block of sub-texel directions and the cube: one after the other, each freed before the next),
    *relight* (the whole ``[V, 3]`` result), *output*. ``exact`` None: counted from the file for a dry run;
    otherwise the header's bound first, counted only when that bound does not fit the budget (a run that fits
    reads nothing here)."""
    from .. import io
    from ..relight import WaveletRelighter

    fb = io.format_bytes
    if exact is None:
        exact = bool(getattr(args, "dry_run", False))
    # counted exactly, the relighter's row-major copy follows the run's light (built only when it takes that pass)
    e = WaveletRelighter.estimate_bytes(args.transfer, exact=exact, light=getattr(args, "light", None),
                                        terms=getattr(args, "terms", None),
                                        selection=getattr(args, "selection", None) or "transport",
                                        arith=getattr(args, "arith", None) or "auto")
    rowp = {True: "this light takes that pass", False: "not built: this light takes the column-major pass",
            None: "built on first need"}[e["row_pass"]]
    if "row_share" in e:  # the kernel's choice: the light's sparse terms' share of the sparse blocks against row_min
        rowp += (f" — its sparse terms hold {e['row_share']:.2f} of the sparse blocks, row_min {e['row_min']:g} for this "
                 f"kernel build")
    lay = (f"dense {fb(e['dense'])}, column-major {fb(e['column'])}, row-major {fb(e['row'])} ({rowp}), "
           f"tables {fb(e['other'])}: {e['total'] / max(V, 1):.0f} B/vertex{'' if exact else ' at most (header bound)'}")
    light = light_bytes(int(round((e["P"] / 6) ** 0.5)))
    stages = [{"stage": "input", "bytes": mesh + data, "note": f"mesh {fb(mesh)}, coefficients {fb(data)} loaded whole"},
              {"stage": "held", "bytes": e["total"], "note": lay},
              # the construction's temporaries, then the light's rasterisation: one after the other, each freed before
              # the next (the larger counts)
              {"stage": "build|light", "bytes": max(e["build"], light),
               "note": f"the larger of the relighter's construction temporaries {fb(e['build'])} ({e['E']} kept "
                       f"coefficients, built in chunks of rows) and the light rasterised on the cube {fb(light)} "
                       f"(in blocks of 4x4 sub-texel directions), one after the other"},
              {"stage": "relight", "bytes": V * 3 * 4 * 3, "note": "the whole [V, 3] result at once"}]
    pl = _finish_plan(args, V, "transfer/wavelet", stages, False, how="")
    if pl["peak"] > pl["budget"] and not exact:  # the bound does not fit: count what the relighter will really hold
        return _wavelet_plan(args, V, mesh, data, exact=True)
    return dict(pl, relighter=e)


def json_load(path):
    import json

    return json.loads(Path(path).read_text())


def calibrate(args, transfer, codec, enc, load_seconds: float = 0.0) -> tuple[float | None, str]:
    """(estimated seconds of the whole relight, how): an SH transfer's first chunk relit and timed
    (after a warm-up of 64 vertices), scaled to every chunk; a codec: one relight of every point
    (the codes are small: the call is the stage itself, nothing written); a wavelet transfer:
    :func:`_calibrate_wavelet`; otherwise (transport tables) not estimated."""
    import time

    if transfer is None or isinstance(transfer, (str, Path)):
        return None, "not estimated for transport tables"
    if transfer.kind == "wavelet":
        return _calibrate_wavelet(args, transfer, load_seconds)
    V = transfer.num_vertices
    if codec is not None:
        radiance(transfer, args.light, codec, enc, view=args.view)  # warm-up (kernels, plans)
        t = time.perf_counter()
        radiance(transfer, args.light, codec, enc, view=args.view)
        return load_seconds + time.perf_counter() - t, (f"loading {load_seconds:.3g} s + one relight of the codes timed "
                                                        "(the stage itself, nothing written)")
    import torch

    k = min(V, CHUNK_VERTICES)
    t = time.perf_counter()
    scene, L, eye = _sh_setup(transfer, args.light, args.view)  # once per run: frames, camera, light
    setup = time.perf_counter() - t
    sub = torch.empty(k, 3, dtype=torch.float32)

    def chunk(a: int, b: int) -> None:
        sl = slice(a, b)
        sub[:b - a] = scene.cpu_radiance(L, None if eye is None else scene.view(eye, sl), rows=sl)

    chunk(0, min(V, 64))  # warm-up
    t = time.perf_counter()
    chunk(0, k)
    dt = time.perf_counter() - t
    n = -(-V // k)
    return load_seconds + setup + dt * n, (f"calibration: loading {load_seconds:.3g} s + set-up {setup:.3g} s + the first {k} "
                                           f"vertices relit in {dt:.3g} s "
                            f"(from the mapped file) × {n} chunks")


#: vertices of a wavelet transfer's calibration relighter (:func:`_calibrate_wavelet`)
WAVELET_CALIBRATION_ROWS = 2048


def _calibrate_wavelet(args, transfer, load_seconds: float) -> tuple[float, str]:
    """A wavelet relight's time, by the SH path's method (a first chunk timed, scaled to every row): a relighter built
    from the first :data:`WAVELET_CALIBRATION_ROWS` rows (its construction and one relight scale with the rows), the
    light rasterised and cut to its terms at R (independent of V: timed whole, the stage itself), after the load."""
    import time
    import types

    from ..relight import WaveletRelighter

    V = transfer.num_vertices
    k = min(V, WAVELET_CALIBRATION_ROWS)
    rows = types.SimpleNamespace(kind="wavelet", data=transfer.data[:k], aux={n: a[:k] for n, a in transfer.aux.items()},
                                 meta=transfer.meta, mesh=types.SimpleNamespace(albedo=transfer.mesh.albedo[:k]),
                                 num_vertices=k)
    t = time.perf_counter()
    r = WaveletRelighter(rows, arith=getattr(args, "arith", None) or "auto")
    build = time.perf_counter() - t
    t = time.perf_counter()
    li, lv, _ = r.light(args.light, args.terms, args.selection or "transport")
    light = time.perf_counter() - t
    r(li, lv)  # warm-up (the row-major copy, if this light takes that pass)
    t = time.perf_counter()
    r(li, lv)
    call = time.perf_counter() - t
    f = V / k
    return load_seconds + (build + call) * f + light, (f"calibration: loading {load_seconds:.3g} s + a relighter of the "
                                                       f"first {k} rows built in {build:.3g} s and relit in {call:.3g} s "
                                                       f"× {f:.3g} + the light on the cube {light:.3g} s")


def _print_plan(pl: dict, seconds: float | None, how: str) -> None:
    from .. import io
    from ..transfer.estimate import stage_width

    fb = io.format_bytes
    import sys

    print(f"prt relight: dry run, {pl['kind']} with {pl['V']} vertices: memory and time per stage", file=sys.stderr)
    w = stage_width(pl["stages"])  # 'build|light' (a wavelet transfer's) is wider than the others
    for st in pl["stages"]:
        print(f"  {st['stage']:{w}s} {fb(st['bytes']):>10s}  {st['note']}", file=sys.stderr)
    tot = "time not estimated" if seconds is None else f"~{seconds:.3g} s relight (an estimate; {how})"
    print(f"  {'peak':{w}s} {fb(pl['peak']):>10s}  {tot}; budget {fb(pl['budget'])} "
          f"({'fits' if pl['peak'] <= pl['budget'] else 'does NOT fit'})", file=sys.stderr)


def check_plan(pl: dict) -> None:
    """Refuse (ValueError, one line with every stage's size) a run whose peak exceeds the budget."""
    from .. import io

    if pl["peak"] <= pl["budget"]:
        return
    fb = io.format_bytes
    parts = ", ".join(f"{st['stage']} {fb(st['bytes'])}" for st in pl["stages"])
    if pl["kind"] == "transfer/wavelet":  # the output is never the problem: the coefficients and their layout are
        ok = ("a wavelet transfer keeping fewer coefficients per vertex (prt precompute --kind wavelet --terms K, or a "
              "smaller --res R: the relighter's layout and its construction grow with the kept coefficients)")
    else:
        ok = "a .npy output, an SH transfer (streamed by chunks)"
    raise ValueError(f"prt relight of {pl['V']} vertices needs about {fb(pl['peak'])} at its peak ({parts}"
                     + ("; the transfer is already mapped and the .npy streamed" if pl["streamed"] else "")
                     + f") but the budget is {fb(pl['budget'])}; accepted: {ok}, or a larger --memory-limit on a machine "
                     "that has it")


def wavelet_options_only(args, why: str) -> None:
    """Refuse ``--terms`` / ``--selection`` (the light's Haar terms) / ``--arith`` for an input that is not a wavelet
    transfer."""
    for flag, v in (("--terms", args.terms), ("--selection", args.selection), ("--arith", getattr(args, "arith", None))):
        if v is not None:
            raise ValueError(f"{flag} {v} applies to wavelet transfers; {why}")


def run(args) -> int:
    from .. import io

    out = Path(args.output)
    if out.suffix.lower() not in OUT_EXTS:
        raise ValueError(f"-o {args.output!r}; accepted extensions: {', '.join(OUT_EXTS)}")
    if args.terms is not None and args.terms < 1:
        raise ValueError(f"--terms {args.terms}; accepted: N >= 1 Haar terms of the light")
    if args.exposure != "auto":
        try:
            float(args.exposure)
        except ValueError:
            raise ValueError(f"--exposure {args.exposure!r}; accepted: a number of stops or 'auto'") from None
    import math

    if args.memory_limit is not None and not (math.isfinite(args.memory_limit) and 0 < args.memory_limit <= 1 << 20):
        raise ValueError(f"--memory-limit {args.memory_limit!r} GiB; accepted: a finite number of GiB in (0, 1048576]")
    io.check_outputs({"-o/--output": out}, {"TRANSFER_OR_CODEC": args.transfer, "--transfer": args.source,
                                            "--light": args.light}, args.overwrite)
    pl = plan(args)  # from the headers: refused here, before anything is read, when it cannot fit
    if not args.dry_run:
        check_plan(pl)
    if args.dry_run:
        transfer = codec = enc = None
        if not Path(args.transfer).is_dir():
            import time

            t = time.perf_counter()
            transfer, codec, enc = _load(args)  # what the run loads first (the mesh; the data mapped)
            load = time.perf_counter() - t
        seconds, how = calibrate(args, transfer, codec, enc, load if transfer is not None else 0.0)
        _print_plan(pl, seconds, how)
        check_plan(pl)
        print("prt relight: dry run: nothing written", file=__import__("sys").stderr)
        return 0
    if Path(args.transfer).is_dir():  # Green 2005 transport tables
        wavelet_options_only(args, "transport tables take the light in SH")
        rad, what = _transport(args.transfer, args.light, args.view)
        transfer = None
    else:
        transfer, codec, enc = _load(args)
        if codec == "transport":  # a codec file of transport tables: transfer is the table's directory
            wavelet_options_only(args, "transport tables take the light in SH")
            rad, what = _transport(transfer, args.light, args.view, args.transfer)
            transfer = None
        elif transfer.kind != "wavelet":
            wavelet_options_only(args, f"a {transfer.kind} transfer takes the light in its own SH bands")
        if transfer is None:
            pass
        elif out.suffix.lower() == ".npy":  # streamed: each chunk written into the file's mapping as it is relit
            import torch

            with io.streamed_npy(out, (transfer.num_vertices, 3), "float32", overwrite=args.overwrite) as arr:
                _, what = radiance(transfer, args.light, codec, enc, args.terms, args.selection or "transport", args.view,
                                   out=torch.from_numpy(arr), arith=args.arith or "auto")
                lo, hi = float(arr.min()), float(arr.max())
            print(f"wrote {out} ([{transfer.num_vertices}, 3] float32; {what}; radiance range [{lo:.4g}, {hi:.4g}])")
            return 0
        else:
            rad, what = radiance(transfer, args.light, codec, enc, args.terms, args.selection or "transport", args.view,
                                 arith=args.arith or "auto")
    rgb = rad.numpy().astype(np.float32)
    if out.suffix.lower() == ".npy":
        with io.streamed_npy(out, rgb.shape, "float32", overwrite=args.overwrite) as arr:
            arr[:] = rgb
        print(f"wrote {out} ([{rgb.shape[0]}, {rgb.shape[1]}] float32; {what}; radiance range "
              f"[{float(rgb.min()):.4g}, {float(rgb.max()):.4g}])")
    else:
        if transfer is None:
            from ..transfer import TransportTable

            src = args.transfer if Path(args.transfer).is_dir() else (io.load_meta(args.transfer).get("extra") or {})["source"]
            mesh = TransportTable(src).mesh()
        else:
            mesh = transfer.mesh
        ev, clipped = _write_ply(out, mesh, rgb, args.exposure, args.overwrite)
        print(f"wrote {out} ({rgb.shape[0]} vertices with colours at exposure {ev:+.2f} EV, {clipped} clipped at white "
              f"(radiance above {2.0 ** -ev:.4g}: the .npy keeps the values); {what})")
    return 0
