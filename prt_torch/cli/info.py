"""``prt info FILE``: metadata and tensor shapes of any prt_torch file (tensors are not read).

``prt info --builtins`` lists the built-in scenes instead.
"""
from __future__ import annotations

import json


def register(subparsers) -> None:
    p = subparsers.add_parser("info", help="show metadata and tensor shapes of a prt_torch file")
    p.add_argument("file", nargs="?", help="a .prt file (any kind)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of text")
    p.add_argument("--builtins", action="store_true", help="list the built-in scenes")
    p.add_argument("--debug", action="store_true", help="show tracebacks")
    p.set_defaults(func=run)


def _short(v, limit: int = 8):
    if isinstance(v, list) and len(v) > limit:
        return v[:limit] + [f"... ({len(v)} items)"]
    if isinstance(v, dict):
        return {k: _short(x, limit) for k, x in v.items()}
    return v


def describe_file(path) -> dict:
    """``{'meta': {...}, 'tensors': {name: {'shape': [...], 'dtype': str}}}`` of a prt_torch file,
    after its kind's consistency check (``prt_torch.io.describe``; a transfer file's values too:
    ``transfer.check_transfer_values``, a codec file's: ``codecs.base.check_codec_values``)."""
    from .. import io

    d = io.describe(path)
    kind = str(d["meta"].get("kind", ""))
    if kind.startswith("transfer/") and kind.split("/", 1)[1] not in ("chunk", "transport_chunk", "transport_views"):
        from ..transfer import check_transfer_values

        check_transfer_values(path, io.load(path)[0], d["meta"])  # the values too: what render refuses, info refuses
    elif kind.startswith("codec/"):
        from ..codecs.base import check_codec_values

        check_codec_values(path, io.load(path)[0], d["meta"])  # the same check render --codec-file and validate run
    return d


def run(args) -> int:
    if args.builtins:
        from ..scene import GEODESIC, SIZES, list_builtins

        for name in list_builtins():
            sizes = ", ".join(SIZES) + ", or a vertex count" if name in GEODESIC else ", ".join(SIZES[:3])
            print(f"{name}  (sizes: {sizes})")
        return 0
    if not args.file:
        raise ValueError("prt info needs FILE (a .prt file) or --builtins")
    d = describe_file(args.file)
    if args.json:
        print(json.dumps(d, indent=2, default=str))
        return 0
    meta = d["meta"]
    print(f"{args.file}: kind={meta.get('kind')} format={meta.get('format')} v{meta.get('format_version')}")
    for k, v in meta.items():
        if k in ("kind", "format", "format_version"):
            continue
        print(f"  {k}: {json.dumps(_short(v), default=str)}")
    print("tensors:")
    width = max((len(k) for k in d["tensors"]), default=0)
    for k, t in d["tensors"].items():
        print(f"  {k:<{width}}  {t['dtype']:<8} {tuple(t['shape'])}")
    return 0
