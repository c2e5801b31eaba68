"""The project's on-disk format: tensors plus versioned JSON metadata, written atomically.

Layout of a ``.prt`` file (it *is* a safetensors file, so any safetensors reader opens it):

* the tensors, by name, little-endian, in the safetensors layout (written by :func:`save` itself,
  the library's bytes; with ``direct=True`` the JSON header carries more trailing spaces, which
  safetensors readers accept, so that one big tensor is written past the page cache);
* the safetensors ``__metadata__`` holds one key, ``"prt_torch"``, whose value is a JSON
  object with at least::

      {"format": "prt_torch", "format_version": 1, "kind": "<what this file is>", ...}

  ``kind`` says what the tensors mean (e.g. ``"transfer/diffuse"``, ``"codec/cpca"``); the
  rest is free-form metadata of the producer (bands, samples, seed, mesh hash, ...).

No pickle is ever used: a file can be loaded by another program with ``prt_torch`` (or with
``safetensors`` and ``json`` alone).

Writing is atomic: data goes to ``<path>.<pid>.<thread>.partial`` and is renamed over ``path``
only once it is complete, so an interrupted write never leaves a half-written file at ``path``
(and two threads, or two processes, writing one path each write their own temporary file: the
last rename wins, whole).
"""
from __future__ import annotations

import contextlib
import json
import math
import os
import threading
import weakref
from pathlib import Path
from typing import Any, Callable, Iterator

import torch

FORMAT = "prt_torch"
FORMAT_VERSION = 1

__all__ = ["save", "load", "load_meta", "atomic_path", "atomic_write_text", "atomic_write_json", "jsonable", "check_writable",
           "check_outputs", "check_disk_space", "strict_json", "describe", "register_check", "format_bytes", "FORMAT_VERSION", "load_mmap",
           "scratch_rows", "streamed_npy", "load_mapped", "hugepage_zeros", "hugepage_backed", "huge_pages_enabled",
           "HUGE_PAGE_BYTES", "HugePageArena"]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; rename it over ``path`` when the block succeeds.

    The temporary name carries the process id and the thread's id (``threading.get_ident``), so
    concurrent writers of one path never share it. On an exception the temporary file is removed and ``path`` is left as it was. With
    ``overwrite=False`` an existing ``path`` is refused before any work.
    """
    path = Path(path)
    if not overwrite and path.exists():
        raise FileExistsError(f"output {str(path)!r} exists; pass overwrite=True (CLI: --overwrite) to replace it")
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.partial")
    try:
        yield tmp
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def check_disk_space(path: str | os.PathLike, need: int, what: str, accepted: str, have: int = 0) -> None:
    """Refuse with ValueError (before any work) when the disk that will hold ``path`` (its nearest
    existing ancestor) has less free space than the ``need`` bytes ``what`` will write there, less
    the ``have`` bytes already written (a resumed run's chunks), plus 5%. One line: what, the
    bytes, the place, the free space and ``accepted``."""
    import shutil

    anc = Path(path).resolve()
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    free = shutil.disk_usage(anc).free
    if need - have > 0.95 * free:
        raise ValueError(f"{what} need {format_bytes(need - have)} at {str(path)!r}, where {format_bytes(free)} are free; "
                         f"accepted: {accepted}")


def format_bytes(b: float) -> str:
    """'3.2 MiB', '0.0123 GiB'-free: three significant digits in the largest unit below the value."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if abs(b) < 1024 or unit == "TiB":
            return f"{b:.3g} {unit}"
        b /= 1024
    return f"{b:.3g} TiB"  # pragma: no cover


def _umask() -> int:
    """The process umask (read without changing it where /proc allows)."""
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:  # pragma: no cover - not Linux
        pass
    m = os.umask(0o022)  # pragma: no cover
    os.umask(m)  # pragma: no cover
    return m  # pragma: no cover


def check_writable(path: str | os.PathLike, what: str = "output", directory: bool = False) -> Path:
    """Refuse, before any work, an output location that cannot be written: ``path`` (a file,
    or with ``directory=True`` a directory) must be creatable — its nearest existing ancestor a
    writable directory, ``path`` itself not a directory (for files) — which is checked by
    creating and removing a probe file there. Raises ValueError naming ``what`` and the path."""
    path = Path(path)
    if not directory and path.is_dir():
        raise ValueError(f"{what} {str(path)!r} is a directory; accepted: a file path")
    if directory and path.exists() and not path.is_dir():
        raise ValueError(f"{what} {str(path)!r} exists and is not a directory; accepted: a directory path")
    parent = path if directory else path.parent
    anc = parent
    while not anc.exists() and anc != anc.parent:
        anc = anc.parent
    if not anc.is_dir():
        raise ValueError(f"{what} {str(path)!r}: {str(anc)!r} is not a directory; accepted: a path under a writable directory")
    probe = anc / f".prt_write_probe.{os.getpid()}"
    try:
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise ValueError(f"{what} {str(path)!r} cannot be written ({e.strerror or e}: {str(anc)!r}); "
                         "accepted: a path in a writable directory") from None
    return path


def _identity(path: Path):
    """What names one file: (device, inode) of an existing path (links followed), else its resolved path."""
    try:
        st = path.stat()
        return (st.st_dev, st.st_ino)
    except OSError:
        return str(path.resolve())


def check_outputs(outputs: dict[str, Any], inputs: dict[str, Any] | None = None, overwrite: bool = False,
                  directories: tuple[str, ...] = ()) -> None:
    """Refuse, before any work, outputs that would destroy a file: ``outputs`` and ``inputs`` map
    the option that names each (``"-o"``, ``"--compare"``, ``"TRANSFER"``) to its path (None: not
    given; a list: several). An output may never be an input or another output of the same command
    (the same file by any name: links followed), every output must be writable
    (:func:`check_writable`; the options in ``directories`` name directories), and an existing
    output is replaced only with ``overwrite`` (the command's ``--overwrite``). Raises ValueError or
    FileExistsError naming the options and paths."""
    def items(d):
        for opt, v in (d or {}).items():
            for x in (v if isinstance(v, (list, tuple)) else [v]):
                if x is not None and str(x) != "":
                    yield opt, Path(x)

    ins = [(opt, p, _identity(p)) for opt, p in items(inputs) if p.exists()]
    seen: dict = {}
    for opt, p in items(outputs):
        ident = _identity(p)
        for iopt, ip, iid in ins:
            if ident == iid:
                raise ValueError(f"{opt} {str(p)!r} is the input {iopt} {str(ip)!r}: writing it would destroy the input; "
                                 "accepted: an output path that is not one of the command's inputs")
        if ident in seen:
            o2, p2 = seen[ident]
            raise ValueError(f"{opt} {str(p)!r} and {o2} {str(p2)!r} are the same file: one output would replace the other; "
                             "accepted: distinct output paths")
        seen[ident] = (opt, p)
        check_writable(p, opt, directory=opt in directories)
        if p.exists() and not overwrite:
            raise FileExistsError(f"{opt} {str(p)!r} exists; pass --overwrite to replace it")


def atomic_write_text(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def atomic_write_json(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON to ``path`` atomically."""
    atomic_write_text(path, json.dumps(obj, indent=2, sort_keys=False, default=_json_default) + "\n")


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON types (tensors and arrays to lists, paths and other objects to
    strings): what metadata and result files store."""
    return json.loads(json.dumps(obj, default=lambda o: _json_default(o, strict=False)))


def strict_json(obj: Any) -> Any:
    """``obj`` as plain JSON types (:func:`jsonable`) with every NaN or infinity replaced by ``null``:
    what ``json.dumps(..., allow_nan=False)`` accepts (JSON has no NaN; Python's ``NaN`` token is not
    read by other parsers)."""
    def walk(o):
        if isinstance(o, float) and not math.isfinite(o):
            return None
        if isinstance(o, dict):
            return {k: walk(v) for k, v in o.items()}
        if isinstance(o, list):
            return [walk(v) for v in o]
        return o
    return walk(jsonable(obj))


def _json_default(o: Any, strict: bool = True) -> Any:
    if isinstance(o, torch.Tensor):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    if hasattr(o, "item"):
        return o.item()
    if hasattr(o, "tolist"):
        return o.tolist()
    if not strict:
        return str(o)
    raise TypeError(f"cannot serialise {type(o).__name__} to JSON")


#: the safetensors dtype codes of the torch dtypes :func:`save` writes itself, in the order the library lays tensors out
#: (safetensors' ``Dtype`` enum, descending; ties by name): the file is then the library's byte for byte
_ST_DTYPES = [(torch.uint64, "U64"), (torch.int64, "I64"), (torch.float64, "F64"), (torch.complex64, "C64"),
              (torch.float32, "F32"), (torch.uint32, "U32"), (torch.int32, "I32"), (torch.bfloat16, "BF16"),
              (torch.float16, "F16"), (torch.uint16, "U16"), (torch.int16, "I16"), (torch.int8, "I8"), (torch.uint8, "U8"),
              (torch.bool, "BOOL")]
_ST_RANK = {d: (i, c) for i, (d, c) in enumerate(_ST_DTYPES)}
#: O_DIRECT's alignment of memory, file offsets and lengths (4 KiB: every common logical block size divides it)
_DIRECT_ALIGN = 4096
#: the least bytes of the one big tensor of a file for which ``direct=True`` bypasses the page cache
_DIRECT_MIN = 4 << 20


def _memory(t: torch.Tensor) -> memoryview:
    """The bytes of a contiguous CPU tensor, in place (no copy; the caller keeps ``t`` alive while it is used)."""
    import ctypes

    n = t.numel() * t.element_size()
    return memoryview((ctypes.c_char * n).from_address(t.data_ptr())).cast("B") if n else memoryview(b"")


def _write_all(fd: int, buf: memoryview) -> None:
    """``os.write`` until all of ``buf`` is written (Linux writes at most 2 GiB - 4 KiB per call)."""
    while len(buf):
        buf = buf[os.write(fd, buf):]


def _safetensors_header(data: dict[str, torch.Tensor], metadata: dict[str, str], align: tuple[str, int] | None = None
                        ) -> tuple[bytes, list[str]]:
    """The safetensors header of ``data`` (its 8-byte little-endian length, then the JSON, padded with spaces) and the
    tensors' names in file order, as ``safetensors`` 0.4-0.8 lays them out: the JSON without spaces,
    ``__metadata__`` first, the tensors by dtype (``_ST_DTYPES``' order) then name, padded to a multiple of 8 bytes —
    or, with ``align = (name, a)`` (``a`` a multiple of 8), padded so that tensor ``name`` starts at a file offset
    congruent to ``a`` modulo :data:`_DIRECT_ALIGN` (the readers accept any trailing spaces)."""
    order = sorted(data, key=lambda k: (_ST_RANK[data[k].dtype][0], k))
    header: dict[str, Any] = {"__metadata__": metadata}
    off, where = 0, 0
    for k in order:
        t = data[k]
        nb = t.numel() * t.element_size()
        if align is not None and k == align[0]:
            where = off
        header[k] = {"dtype": _ST_RANK[t.dtype][1], "shape": list(t.shape), "data_offsets": [off, off + nb]}
        off += nb
    text = json.dumps(header, separators=(",", ":"), ensure_ascii=False).encode("utf-8")
    if align is None:
        n = len(text) + (-len(text)) % 8
    else:  # 8 + n + where = a (mod A); n = 0 (mod 8) when a and where are multiples of 8
        n = len(text) + (align[1] - 8 - where - len(text)) % _DIRECT_ALIGN
    return n.to_bytes(8, "little") + text + b" " * (n - len(text)), order


def _write_safetensors(path: Path, data: dict[str, torch.Tensor], metadata: dict[str, str], direct: bool = False) -> None:
    """Write ``data`` (contiguous CPU tensors) as the safetensors file ``path``, each tensor from its own memory: no
    serialised copy, whatever the installed ``safetensors`` (0.4's ``save_file`` copied every tensor into a ``bytes``
    first; 0.8's passes pointers). The file is the one ``safetensors.torch.save_file`` writes, byte for byte (tested).

    ``direct``: where one tensor holds at least :data:`_DIRECT_MIN` bytes, the others together less, and those laid
    out before it a multiple of 8 bytes (so the padded header stays a multiple of 8, as the library writes it), its
    page-aligned bulk is written with ``O_DIRECT`` from the tensor's memory — the kernel does not copy it into the page
    cache (on this machine that copy, and the reclaim of the pages it takes, was most of the system time of a transport
    table: 35 % of its CPU; issue 42 §2). The header is then padded with spaces so that the tensor's file offset is
    congruent to its address modulo 4 KiB, what comes before and after its aligned bulk (the header, the small tensors,
    its partial first and last blocks) goes through small aligned buffers, and the file is cut to its length: a file
    ``safetensors`` reads back identically (tested), not the library's bytes. Where the file system refuses
    ``O_DIRECT`` (tmpfs: EINVAL) the file is written through the page cache instead."""
    import sys

    if direct and getattr(os, "O_DIRECT", 0) and data and sys.byteorder == "little":
        size = {k: t.numel() * t.element_size() for k, t in data.items()}
        big = max(size, key=size.get)
        order = sorted(data, key=lambda k: (_ST_RANK[data[k].dtype][0], k))
        before = sum(size[k] for k in order[:order.index(big)])  # a multiple of 8, or the padded header would not be
        if size[big] >= _DIRECT_MIN and sum(size.values()) - size[big] < _DIRECT_MIN and data[big].data_ptr() % 8 == 0 \
                and before % 8 == 0:
            try:
                _write_direct(path, data, metadata, big)
                return
            except OSError as e:
                import errno

                if e.errno != errno.EINVAL:
                    raise
    head, order = _safetensors_header(data, metadata)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), 0o666)
    try:
        _write_all(fd, memoryview(head))
        for k in order:
            _write_all(fd, _memory(data[k]))
    finally:
        os.close(fd)


def _write_direct(path: Path, data: dict[str, torch.Tensor], metadata: dict[str, str], big: str) -> None:
    """:func:`_write_safetensors`' ``O_DIRECT`` form (its docstring) for the big tensor ``big``."""
    import mmap

    A = _DIRECT_ALIGN
    mem = _memory(data[big])
    head, order = _safetensors_header(data, metadata, align=(big, data[big].data_ptr() % A))
    at = order.index(big)
    before = [memoryview(head)] + [_memory(data[k]) for k in order[:at]]
    D = sum(len(m) for m in before)  # the big tensor's file offset, congruent to its address modulo A
    lead = min((-D) % A, len(mem))  # its bytes before its first aligned block
    bulk = (len(mem) - lead) // A * A
    after = [mem[lead + bulk:]] + [_memory(data[k]) for k in order[at + 1:]]

    def staged(parts):  # parts copied into a page-aligned buffer, zero padded to a whole number of blocks
        n = sum(len(m) for m in parts)
        buf = mmap.mmap(-1, max(A, -(-n // A) * A))
        pos = 0
        for m in parts:
            buf[pos:pos + len(m)] = m
            pos += len(m)
        return memoryview(buf)[:-(-n // A) * A]

    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_DIRECT | getattr(os, "O_CLOEXEC", 0), 0o666)
    try:
        _write_all(fd, staged(before + [mem[:lead]]))  # D + lead: a whole number of blocks
        _write_all(fd, mem[lead:lead + bulk])  # from the tensor's memory: no copy
        _write_all(fd, staged(after))
        os.ftruncate(fd, D + len(mem) + sum(len(m) for m in after[1:]))
    finally:
        os.close(fd)


def save(
    path: str | os.PathLike,
    tensors: dict[str, torch.Tensor],
    kind: str,
    meta: dict[str, Any] | None = None,
    overwrite: bool = True,
    direct: bool = False,
) -> Path:
    """Save ``tensors`` (name -> tensor, any shape/dtype) with metadata, atomically.

    Tensors are made contiguous and moved to the CPU. ``meta`` must be JSON-serialisable; a NaN or
    infinity in it is written as ``null`` (:func:`strict_json`: JSON has no such numbers, and parsers
    other than Python's refuse the ``NaN`` token), so the header reads in any JSON parser.
    The file is written from the tensors' memory (:func:`_write_safetensors`: the bytes ``safetensors``'
    ``save_file`` writes, without the copy older versions made); ``direct=True`` writes one big
    tensor past the page cache (``O_DIRECT``: no kernel copy; for large files this process
    will not read back soon, such as the transport tables' chunks). Tensors that share memory are
    written each as its own values (``save_file`` refuses them). Returns the path written.
    """
    import sys

    from safetensors.torch import save_file

    if not isinstance(kind, str) or not kind:
        raise ValueError(f"kind={kind!r}; accepted: a non-empty string such as 'transfer/diffuse'")
    if not isinstance(direct, bool):  # a truthy string ("no") would bypass the page cache unasked
        raise ValueError(f"direct={direct!r}; accepted: True or False")
    for k, v in tensors.items():
        if not isinstance(v, torch.Tensor):
            raise TypeError(f"tensors[{k!r}] is {type(v).__name__}; accepted: torch.Tensor")
    header = {"format": FORMAT, "format_version": FORMAT_VERSION, "kind": kind}
    header.update(meta or {})
    # JSON proper (other programs' parsers refuse Python's NaN/Infinity tokens): a non-finite number is written null
    text = json.dumps(strict_json(json.loads(json.dumps(header, default=_json_default))), allow_nan=False)
    data = {k: v.detach().to("cpu").resolve_conj().resolve_neg().contiguous() for k, v in tensors.items()}
    own = sys.byteorder == "little" and all(v.dtype in _ST_RANK for v in data.values())
    try:
        with atomic_path(path, overwrite=overwrite) as tmp:
            if own:
                _write_safetensors(tmp, data, {FORMAT: text}, direct=direct)
            else:  # a dtype without its code here (float8, ...) or a big-endian host: the library's writer
                save_file(data, str(tmp), metadata={FORMAT: text})
                os.chmod(tmp, 0o666 & ~_umask())  # safetensors writes through a private (0600) temporary file
    except FileExistsError:
        raise
    except Exception as e:  # OSError, or safetensors' own SafetensorError for I/O failures
        if not isinstance(e, OSError) and type(e).__name__ != "SafetensorError":
            raise
        raise OSError(f"cannot write {str(path)!r}: {e}") from None
    return Path(path)


def load_meta(path: str | os.PathLike) -> dict[str, Any]:
    """Read only the metadata of a ``.prt`` file (cheap: the tensors are not read)."""
    from safetensors import safe_open

    path = _existing(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            raw = (f.metadata() or {}).get(FORMAT)
    except Exception as e:  # safetensors raises its own error types
        raise ValueError(f"{str(path)!r} is not a readable prt_torch file ({e}); expected a file written by prt_torch.io.save") from None
    return _parse_meta(path, raw)


#: kind prefix -> checker(path, meta, shapes {name: [dims]}) raising ValueError on a file whose
#: metadata disagrees with its tensors; registered by the modules that own each kind.
_CHECKS: dict[str, Callable[[Path, dict, dict], None]] = {}


def register_check(kind_prefix: str, check: Callable[[Path, dict, dict], None]) -> None:
    """Register the consistency check of the files whose ``kind`` starts with ``kind_prefix``
    (e.g. ``"transfer/"``); :func:`load` and :func:`describe` run it on every file they open."""
    _CHECKS[kind_prefix] = check


def _check(path: Path, meta: dict, shapes: dict) -> None:
    for prefix, fn in _CHECKS.items():
        if str(meta.get("kind", "")).startswith(prefix):
            fn(path, meta, shapes)


def describe(path: str | os.PathLike) -> dict[str, Any]:
    """``{'meta': {...}, 'tensors': {name: {'shape', 'dtype'}}}`` of a ``.prt`` file without
    reading the tensors, after the kind's consistency check (metadata against shapes)."""
    from safetensors import safe_open

    path = _existing(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            raw = (f.metadata() or {}).get(FORMAT)
            tensors = {k: {"shape": list(f.get_slice(k).get_shape()), "dtype": str(f.get_slice(k).get_dtype())} for k in f.keys()}
    except Exception as e:
        raise ValueError(f"{str(path)!r} is not a readable prt_torch file ({e}); expected a file written by prt_torch.io.save") from None
    meta = _parse_meta(path, raw)
    _check(path, meta, {k: t["shape"] for k, t in tensors.items()})
    return {"meta": meta, "tensors": tensors}


def load(path: str | os.PathLike, expect_kind: str | None = None) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """Load a ``.prt`` file: returns ``(tensors, meta)``, after the kind's consistency check
    (:func:`register_check`).

    ``expect_kind``, if given, is a prefix the file's ``kind`` must start with
    (e.g. ``"transfer/"``); anything else is refused with the kind found.
    """
    from safetensors import safe_open

    path = _existing(path)
    try:
        with safe_open(str(path), framework="pt") as f:
            raw = (f.metadata() or {}).get(FORMAT)
            tensors = {k: f.get_tensor(k) for k in f.keys()}
    except Exception as e:
        raise ValueError(f"{str(path)!r} is not a readable prt_torch file ({e}); expected a file written by prt_torch.io.save") from None
    meta = _parse_meta(path, raw)
    if expect_kind is not None and not str(meta.get("kind", "")).startswith(expect_kind):
        raise ValueError(f"{str(path)!r} holds kind={meta.get('kind')!r}; expected a kind starting with {expect_kind!r}")
    _check(path, meta, {k: list(v.shape) for k, v in tensors.items()})
    return tensors, meta


_NP_DTYPES = {"F32": "<f4", "F64": "<f8", "F16": "<f2", "I64": "<i8", "I32": "<i4", "I16": "<i2", "U8": "u1", "I8": "i1"}


def _raw_header(path: Path) -> tuple[int, dict, dict]:
    """``(data start, {name: header entry}, meta)`` of a ``.prt`` (safetensors) file read from its
    first bytes only — no mapping of the file (``safe_open`` maps it whole, which a memory limit
    counts) — after the kind's consistency check. Raises ValueError naming the file."""
    size = path.stat().st_size
    try:
        with open(path, "rb") as f:
            n = int.from_bytes(f.read(8), "little")
            if not 0 < n <= min(size - 8, 100 << 20):
                raise ValueError(f"header length {n} does not fit the file's {size} bytes")
            header = json.loads(f.read(n))
        raw = (header.pop("__metadata__", None) or {}).get(FORMAT)
        for k, v in header.items():
            a, b = v["data_offsets"]
            if not 0 <= a <= b <= size - 8 - n:
                raise ValueError(f"tensor {k!r} lies beyond the end of the file")
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{str(path)!r} is not a readable prt_torch file ({e}); expected a file written by prt_torch.io.save") from None
    meta = _parse_meta(path, raw)
    _check(path, meta, {k: list(v["shape"]) for k, v in header.items()})
    return 8 + n, header, meta


def _np_tensor(path: Path, start: int, info: dict, mapped: bool):
    """One tensor of a safetensors file as numpy: a read-only ``np.memmap`` or read into memory."""
    import numpy as np

    if info["dtype"] not in _NP_DTYPES:
        raise ValueError(f"{str(path)!r}: tensor has dtype {info['dtype']}; accepted for a memory map: {sorted(_NP_DTYPES)}")
    a, b = info["data_offsets"]
    shape, dt = tuple(info["shape"]), np.dtype(_NP_DTYPES[info["dtype"]])
    if b == a:
        return np.zeros(shape, dtype=dt)
    if mapped:
        return np.memmap(path, dtype=dt, mode="r", offset=start + a, shape=shape)
    out = np.empty(shape, dtype=dt)
    with open(path, "rb") as f:
        f.seek(start + a)
        f.readinto(memoryview(out).cast("B"))
    return out


def load_mmap(path: str | os.PathLike, name: str):
    """One tensor of a ``.prt`` (safetensors) file as a read-only ``numpy.memmap`` — not read into
    memory: its pages are read when used and can be dropped again (what a streamed codec fit
    reads, issue 42 part 3: ``codecs.get('cpca').fit(io.load_mmap(p, 'data').reshape(V, -1))``).
    The file's kind check runs first. Raises ValueError naming the file and the tensor when it is
    absent or of a dtype numpy cannot map."""
    path = _existing(path)
    start, header, _ = _raw_header(path)
    if name not in header:
        raise ValueError(f"{str(path)!r} has no tensor {name!r}; it holds {sorted(header)}")
    return _np_tensor(path, start, header[name], mapped=True)


def load_mapped(path: str | os.PathLike, mapped: tuple[str, ...] = ("data",),
                expect_kind: str | None = None) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
    """:func:`load` with the tensors named in ``mapped`` left on disk: read-only memory maps
    (``np.memmap`` under a torch tensor; never write to them) whose pages are read when used and
    dropped under memory pressure; the others read into memory. Nothing maps the whole file
    (a limit on process memory, ``RLIMIT_DATA``, does not count the mapped tensors)."""
    import warnings

    path = _existing(path)
    start, header, meta = _raw_header(path)
    if expect_kind is not None and not str(meta.get("kind", "")).startswith(expect_kind):
        raise ValueError(f"{str(path)!r} holds kind={meta.get('kind')!r}; expected a kind starting with {expect_kind!r}")
    tensors = {}
    with warnings.catch_warnings():  # a read-only map: torch warns that the tensor is not writable (it is never written)
        warnings.simplefilter("ignore", UserWarning)
        for k, info in header.items():
            tensors[k] = torch.from_numpy(_np_tensor(path, start, info, mapped=k in mapped))
    return tensors, meta


def scratch_rows(directory: str | os.PathLike, shape: tuple[int, ...], dtype: torch.dtype = torch.float32,
                 name: str = "rows") -> torch.Tensor:
    """A tensor of ``shape`` and ``dtype`` backed by a file in ``directory`` rather than by
    memory (issue 42 part 3: a result larger than memory, assembled chunk by chunk): a shared
    writable mapping (``np.lib.format.open_memmap``) of a file unlinked as soon as it is mapped,
    so that nothing is ever left on disk (not even after SIGKILL) and its pages are the page
    cache's — written back and dropped under memory pressure, never swap or ``RLIMIT_DATA``. The
    space is freed when the last reference to the tensor goes. Values start at zero.

    Raises ValueError naming ``directory`` when it cannot hold the file (one line)."""
    import numpy as np

    directory = Path(directory)
    n = 1
    for d in shape:
        n *= int(d)
    itemsize = torch.tensor([], dtype=dtype).element_size()
    np_dtype = {torch.float32: np.float32, torch.float64: np.float64, torch.float16: np.float16,
                torch.int64: np.int64, torch.int32: np.int32, torch.int16: np.int16, torch.int8: np.int8,
                torch.uint8: np.uint8}.get(dtype)
    if np_dtype is None:
        raise ValueError(f"scratch_rows: dtype={dtype}; accepted: float16/32/64, int8/16/32/64, uint8")
    path = directory / f".{name}.{os.getpid()}.{id(shape):x}.scratch.npy"
    try:
        if n == 0:
            return torch.zeros(shape, dtype=dtype)
        directory.mkdir(parents=True, exist_ok=True)
        arr = np.lib.format.open_memmap(path, mode="w+", dtype=np_dtype, shape=tuple(int(d) for d in shape))
    except OSError as e:
        raise ValueError(f"cannot create {format_bytes(n * itemsize)} of scratch rows in {str(directory)!r} "
                         f"({e.strerror or e}); accepted: a directory on a file system with that much free space") from None
    finally:
        if path.exists():
            path.unlink()  # the mapping keeps the file alive; nothing remains on disk once it is gone
    return torch.from_numpy(arr)


#: the size of a transparent huge page on Linux with 4 KB base pages (x86-64, aarch64): the helper below allocates
#: in huge-page-advised memory from this size up (a smaller array would occupy a huge page it does not fill)
HUGE_PAGE_BYTES = 2 << 20
_HUGE_MAPS: "weakref.WeakValueDictionary[int, Any]" = weakref.WeakValueDictionary()  # aligned start -> its mmap


def huge_pages_enabled() -> bool:
    """``PRT_TORCH_HUGEPAGES``: ``1`` (or unset / empty, the default) lets :func:`hugepage_zeros` advise transparent
    huge pages, ``0`` keeps every array in torch's own buffers. Raises ``ValueError`` (one line naming the variable,
    its value and what is accepted) for another value."""
    raw = os.environ.get("PRT_TORCH_HUGEPAGES", "")
    v = raw.strip()
    if v not in ("", "0", "1"):
        raise ValueError(f"PRT_TORCH_HUGEPAGES={raw!r}; accepted: 1 (the default: arrays of 2 MiB or more in "
                         "memory advised for transparent huge pages) or 0 (torch's own buffers)")
    return v != "0"


def _thp_mode() -> str:
    """Linux's transparent huge page mode (``always``, ``madvise``, ``never``), or ``''`` where it is not told."""
    try:
        text = Path("/sys/kernel/mm/transparent_hugepage/enabled").read_text()
    except OSError:
        return ""
    return text[text.find("[") + 1:text.find("]")] if "[" in text else ""


def hugepage_zeros(shape: tuple[int, ...] | torch.Size, dtype: torch.dtype, huge: bool | None = None,
                   min_bytes: int = HUGE_PAGE_BYTES) -> torch.Tensor:
    """A zero-filled, contiguous tensor of ``shape`` and ``dtype`` (any torch dtype), on the CPU, in memory advised
    for transparent huge pages (2 MiB pages: one TLB entry where 4 KB pages take 512) when that is possible and
    worth it: on Linux, with ``huge`` True (None: :func:`huge_pages_enabled`, the ``PRT_TORCH_HUGEPAGES`` switch), at
    least ``min_bytes`` (default :data:`HUGE_PAGE_BYTES`; 0: any size, a smaller array then occupies one huge page it
    does not fill — :class:`HugePageArena` packs several into it), the kernel's mode not ``never``, and ``mmap``/``madvise(MADV_HUGEPAGE)``
    available and succeeding. Then the tensor lies in a private anonymous mapping (zero pages until written: no
    fill, no second copy) whose start is rounded up to a 2 MiB boundary (one huge page of address space more than
    the data, never touched, so never resident; its length a whole number of huge pages, so the last one is huge
    too: up to 2 MiB resident beyond the data, which :meth:`nbytes`-style counts do not include) and which lives as long as the tensor's storage does
    (``torch.frombuffer`` holds a reference to it; unmapped when the last view goes). Otherwise, and on any
    failure, ``torch.zeros(shape, dtype=dtype)``. The kernel backs the advised range with huge pages as far as it
    can at the first touch (``AnonHugePages`` in ``/proc/self/smaps_rollup``; 4 KB pages where it cannot find
    2 MiB of contiguous memory). :func:`hugepage_backed` says which of the two a tensor got."""
    import mmap
    import sys

    shape = torch.Size(shape)
    nbytes = shape.numel() * torch.empty((), dtype=dtype).element_size()
    huge = huge_pages_enabled() if huge is None else bool(huge)
    if not (huge and sys.platform.startswith("linux") and nbytes >= min_bytes and hasattr(mmap, "MADV_HUGEPAGE")
            and _thp_mode() != "never"):
        return torch.zeros(shape, dtype=dtype)
    try:
        span = max(1, -(-nbytes // HUGE_PAGE_BYTES)) * HUGE_PAGE_BYTES  # whole huge pages from the aligned start
        mm = mmap.mmap(-1, span + HUGE_PAGE_BYTES, flags=mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS)
        mm.madvise(mmap.MADV_HUGEPAGE)
    except (OSError, ValueError, AttributeError):
        return torch.zeros(shape, dtype=dtype)
    base = torch.frombuffer(mm, dtype=torch.uint8)  # holds mm: the mapping lives while any view of it does
    off = -base.data_ptr() % HUGE_PAGE_BYTES
    _HUGE_MAPS[base.data_ptr() + off] = mm
    return base[off:off + nbytes].view(dtype).view(shape)


def hugepage_backed(t: torch.Tensor | None) -> bool:
    """Whether ``t`` (a tensor or a view of one) lies in a mapping :func:`hugepage_zeros` advised for huge pages."""
    if t is None or t.numel() == 0:
        return False
    p = t.data_ptr()
    return any(a <= p < a + len(mm) - HUGE_PAGE_BYTES for a, mm in list(_HUGE_MAPS.items()))


class HugePageArena:
    """Several small arrays in one zero-filled mapping advised for 2 MiB pages (:func:`hugepage_zeros` with
    ``min_bytes=0``): ``capacity`` bytes rounded up to whole huge pages, each array carved at the next
    :attr:`ALIGN`-byte boundary (a bump allocator: nothing is freed; the mapping lives while any carved view does).
    Where huge pages are off or unavailable (``huge`` False, None with ``PRT_TORCH_HUGEPAGES=0``, not Linux, THP
    ``never``, a failing ``mmap``) the arena is empty and :meth:`zeros` / :meth:`take` fall back to torch's buffers.
    Arrays that no longer fit fall back the same way: the arena never grows. For arrays below 2 MiB that should share
    one TLB entry (``timing.read_bound_fn(huge=True)``'s buffers). Whether a 2 MiB page is physically contiguous below
    the guest is the host's business: on the Intel Xeon VM a read near the L2's size varied with its huge page as
    much as with 4 KB pages, and the small wavelet layout was no faster in an arena
    (reports/benchmarks/wavelet_hugepages_small.md)."""

    ALIGN = 64  # bytes: a cache line, as torch's own allocations

    def __init__(self, capacity: int, huge: bool | None = None):
        cap = max(1, -(-int(capacity) // HUGE_PAGE_BYTES)) * HUGE_PAGE_BYTES
        buf = hugepage_zeros((cap,), torch.uint8, huge=huge, min_bytes=0)
        self.buf = buf if hugepage_backed(buf) else None  # uint8 [capacity] or None (the fall-back: torch's buffers)
        self.capacity = cap if self.buf is not None else 0
        self.used = 0

    def zeros(self, shape: tuple[int, ...] | torch.Size, dtype: torch.dtype) -> torch.Tensor:
        """A zero-filled contiguous ``shape`` ``dtype`` tensor in the arena, or ``torch.zeros`` where it does not fit."""
        shape = torch.Size(shape)
        nbytes = shape.numel() * torch.empty((), dtype=dtype).element_size()
        a = -(-self.used // self.ALIGN) * self.ALIGN
        if self.buf is None or a + nbytes > self.capacity:
            return torch.zeros(shape, dtype=dtype)
        self.used = a + nbytes
        return self.buf[a:a + nbytes].view(dtype).view(shape)

    def take(self, t: torch.Tensor | None) -> torch.Tensor | None:
        """A contiguous copy of ``t`` in the arena (``t`` itself where it does not fit, or None)."""
        if t is None or self.buf is None:
            return t
        a = -(-self.used // self.ALIGN) * self.ALIGN
        if a + t.numel() * t.element_size() > self.capacity:
            return t
        return self.zeros(t.shape, t.dtype).copy_(t)


@contextlib.contextmanager
def streamed_npy(path: str | os.PathLike, shape: tuple[int, ...], dtype="float32", overwrite: bool = False):
    """Write a ``.npy`` file of ``shape`` chunk by chunk without holding it: yields a writable
    ``numpy.memmap`` of ``<path>.<pid>.<thread>.partial`` (``np.lib.format.open_memmap``, a shared
    file mapping: its pages are the page cache's), flushed and renamed over ``path`` when the block
    succeeds; on an exception (Ctrl-C included) the partial file is removed and ``path`` is left as
    it was (:func:`atomic_path`). The file is the one ``np.save`` writes for the same array."""
    import numpy as np

    with atomic_path(path, overwrite=overwrite) as tmp:
        arr = np.lib.format.open_memmap(tmp, mode="w+", dtype=np.dtype(dtype), shape=tuple(int(d) for d in shape))
        try:
            yield arr
            arr.flush()
        finally:
            del arr


def _existing(path: str | os.PathLike) -> Path:
    path = Path(path)
    if path.is_dir():
        raise ValueError(f"{str(path)!r} is a directory; accepted: a .prt file")
    if not path.is_file():
        raise FileNotFoundError(f"no such file: {str(path)!r}")
    return path


def _parse_meta(path: Path, raw: str | None) -> dict[str, Any]:
    if raw is None:
        raise ValueError(f"{str(path)!r} is a safetensors file without prt_torch metadata; expected a file written by prt_torch.io.save")
    try:
        meta = json.loads(raw)
    except json.JSONDecodeError as e:
        raise ValueError(f"{str(path)!r}: its prt_torch metadata is not valid JSON ({e})") from None
    if not isinstance(meta, dict):
        raise ValueError(f"{str(path)!r}: its prt_torch metadata is not a JSON object")
    version = meta.get("format_version")
    if not isinstance(version, int) or version > FORMAT_VERSION:
        raise ValueError(
            f"{str(path)!r} has format_version={version!r}; this prt_torch reads versions 1..{FORMAT_VERSION} (upgrade prt_torch)"
        )
    return meta
