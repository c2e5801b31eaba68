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
  (:class:`prt_torch.relight.WaveletRelighter`; Ng et al. 2003).

View-dependent kinds (glossy, MRT, transport tables) take the camera position ``--view X,Y,Z`` (default: the
camera ``prt render`` places by default); view-independent ones refuse it.
"""
from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np

OUT_EXTS = (".npy", ".ply")


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
    p.add_argument("--selection", default="transport", choices=["magnitude", "area", "transport"],
                   help="wavelet transfers: how the N terms are chosen (Ng 2003 §5; default transport-weighted, measured in "
                        "reports/benchmarks/wavelet.md)")
    p.add_argument("--transfer", dest="source", default=None, metavar="TRANSFER.prt",
                   help="codec files: the transfer it was compressed from (default: the path the codec file records)")
    p.add_argument("--view", type=_vector, default=None, metavar="X,Y,Z",
                   help="glossy/MRT: camera position in world space (default: prt render's default camera)")
    p.add_argument("--exposure", default="auto", help=".ply: stops (EV) for the vertex colours, or 'auto'")
    p.add_argument("-o", "--output", required=True, help="output: .npy ([V, 3] float32) or .ply (mesh with vertex colours)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
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
        out, what = ev.reference(L, vw), "transport tables"
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
        transfer = Transfer.load(src)
        codec, enc = check_codec_file(args.transfer, PRTScene(transfer))
        return transfer, codec, enc
    if not kind.startswith("transfer/"):
        raise ValueError(f"{args.transfer!r} holds {kind!r}; accepted: a transfer file (prt precompute) or a codec file "
                         "(prt compress)")
    if args.source is not None:
        raise ValueError("--transfer applies to codec files; the input is a transfer")
    return Transfer.load(args.transfer), None, None


def radiance(transfer, light: str, codec=None, enc=None, terms: int | None = None, selection: str = "transport",
             view=None):
    """Per-vertex exit radiance ``[V, 3]`` float32 and a one-line description (module docstring)."""
    import torch

    from .. import relight
    from ..render import Camera, PRTScene
    from ..lighting import load_light

    if transfer.kind == "wavelet":
        if codec is not None:  # pragma: no cover - compress refuses wavelet transfers
            raise ValueError("a wavelet transfer has no codec files")
        if view is not None:
            raise ValueError("--view applies to glossy and MRT transfers; a wavelet transfer is diffuse (view-independent)")
        r = relight.WaveletRelighter(transfer)
        li, lv, rec = r.light(light, terms, selection)
        if rec.get("upsampled"):
            warnings.warn(rec["warning"])
        out = r(li, lv)
        if out.shape[1] == 1:
            out = out.expand(-1, 3)
        return out.contiguous(), (f"wavelet R={r.res}, {li.numel()} of {r.P} light terms ({selection}), "
                                  f"{r.touched(li)} transfer coefficients read")
    if terms is not None:
        raise ValueError(f"--terms {terms} applies to wavelet transfers; a {transfer.kind} transfer takes the light in "
                         "its own SH bands")
    scene = PRTScene(transfer)
    if scene.needs_view:
        eye = torch.tensor(view, dtype=torch.float64) if view is not None else torch.as_tensor(Camera.fit(transfer.mesh).eye)
        v = scene.view(eye)
    elif view is not None:
        raise ValueError(f"--view applies to glossy and MRT transfers; a {transfer.kind} transfer is view-independent")
    else:
        v = None
    bands = int(round(scene.n_in ** 0.5))
    L = load_light(light, bands=bands)
    out = scene.cpu_radiance(L, v, codec, enc)
    what = f"{transfer.kind} transfer, {bands} bands" + (f", codec {codec.codec_name}" if codec is not None else "")
    return out, what


def _write_ply(path: Path, mesh, rgb: np.ndarray, exposure: str, overwrite: bool) -> float:
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
    return ev


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
    io.check_outputs({"-o/--output": out}, {"TRANSFER_OR_CODEC": args.transfer, "--transfer": args.source,
                                            "--light": args.light}, args.overwrite)
    if Path(args.transfer).is_dir():  # Green 2005 transport tables
        if args.terms is not None:
            raise ValueError(f"--terms {args.terms} applies to wavelet transfers; transport tables take the light in SH")
        rad, what = _transport(args.transfer, args.light, args.view)
        transfer = None
    else:
        transfer, codec, enc = _load(args)
        if codec == "transport":  # a codec file of transport tables: transfer is the table's directory
            if args.terms is not None:
                raise ValueError(f"--terms {args.terms} applies to wavelet transfers; transport tables take the light in SH")
            rad, what = _transport(transfer, args.light, args.view, args.transfer)
            transfer = None
        else:
            rad, what = radiance(transfer, args.light, codec, enc, args.terms, args.selection, args.view)
    rgb = rad.numpy().astype(np.float32)
    if out.suffix.lower() == ".npy":
        with io.atomic_path(out, overwrite=args.overwrite) as tmp:
            with open(tmp, "wb") as f:
                np.save(f, rgb)
        print(f"wrote {out} ([{rgb.shape[0]}, {rgb.shape[1]}] float32; {what}; radiance range "
              f"[{float(rgb.min()):.4g}, {float(rgb.max()):.4g}])")
    else:
        if transfer is None:
            from ..transfer import TransportTable

            src = args.transfer if Path(args.transfer).is_dir() else (io.load_meta(args.transfer).get("extra") or {})["source"]
            mesh = TransportTable(src).mesh()
        else:
            mesh = transfer.mesh
        ev = _write_ply(out, mesh, rgb, args.exposure, args.overwrite)
        print(f"wrote {out} ({rgb.shape[0]} vertices with colours at exposure {ev:+.2f} EV; {what})")
    return 0
