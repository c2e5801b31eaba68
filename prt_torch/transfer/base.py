"""The ``Transfer`` container and the chunked, resumable runner every precompute uses.

File layout (``prt_torch.io``, kind ``"transfer/<kind>"``): tensor ``data`` plus the mesh arrays
under ``mesh.*`` (vertices, faces, normals, tangents, bitangents, albedo), and metadata::

    {"kind": "transfer/diffuse", "transfer_version": 1, "transfer_kind": "diffuse",
     "mesh_name": ..., "mesh_hash": ..., "bands": 5, "samples": 1024, "seed": 0, ...}

Shapes of ``data`` (interfaces.md): diffuse ``[V, n²]`` (albedo kept separate, in
``mesh.albedo``) or ``[V, 3, n²]`` (RGB, albedo folded); glossy ``[V, n_out, n_in]``
(``meta['matrix_shape'] = [n_out, n_in]``); MRT ``[V, M*M, n²]``; transport as its module says;
wavelet ``[V, K]`` quantised Haar coefficients (int8/int16/float32) with ``aux.index [V, K]`` and
``aux.scale [V]`` or ``[V, L]``, or ``[V, 3, K]`` (a coloured mesh's interreflection, albedo folded)
with ``aux.scale [V, 3, …]`` (:mod:`prt_torch.transfer.wavelet`). ``Transfer.aux`` tensors are saved as
``aux.<name>``.
"""
from __future__ import annotations

import copyreg
import dataclasses
import hashlib
import json
import math
import os
import shutil
import time
from pathlib import Path
from typing import Any, Callable

import torch

from .. import io
from .._checks import check_choice, check_float, check_int
from ..executor import Executor, LocalExecutor, TaskFailure
from ..scene import Mesh, RayCaster

__all__ = ["Transfer", "KINDS", "TRANSFER_VERSION", "RunOptions", "run_chunks", "ChunkInterrupt", "default_state_dir",
           "remove_state", "check_transfer_values", "MAX_ABS_TRANSFER", "STREAM_RESULT_BYTES", "cast_rows",
           "stream_result_bytes"]

KINDS = ("diffuse", "glossy", "mrt", "transport", "wavelet")
TRANSFER_VERSION = 1
#: A precompute's assembled result larger than this (bytes) is kept in a file beside its state
#: directory rather than in memory (``RunOptions.stream_result=None``; issue 42 part 3): the
#: same threshold as a codec fit's streaming (``codecs.chunks.STREAM_BYTES``). The environment
#: variable ``PRT_STREAM_RESULT_BYTES`` lowers (or raises) it for a process — what the tests use
#: to stream a tiny mesh's result through the command line (:func:`stream_result_bytes`).
STREAM_RESULT_BYTES = 256 * 2**20


def stream_result_bytes() -> int:
    """The streaming threshold in force: ``PRT_STREAM_RESULT_BYTES`` (bytes, an integer ≥ 0)
    when set, else :data:`STREAM_RESULT_BYTES`. A value that is not such an integer is refused
    naming the variable."""
    v = os.environ.get("PRT_STREAM_RESULT_BYTES")
    if v is None or v == "":
        return STREAM_RESULT_BYTES
    try:
        n = int(v)
    except ValueError:
        n = -1
    if n < 0:
        raise ValueError(f"PRT_STREAM_RESULT_BYTES={v!r}; accepted: a number of bytes, an integer >= 0 "
                         f"(unset: {STREAM_RESULT_BYTES})")
    return n


@dataclasses.dataclass(frozen=True)
class RunOptions:
    """How a precompute runs (every kind takes one as ``run=``); none of these changes the
    result except ``offset``, which is part of each run's fingerprint.

    Attributes:
        chunk_size: vertices per chunk (None: each kind's default, about 2¹⁹–2²⁰ rays per chunk).
        workers: ray-casting processes (None: all cores when the run traces ≥ 4M rays, else 1).
        offset: ray-origin offset along the normal, relative to the mesh's bounding radius.
        max_memory: bytes; refuse a run estimated above it before any work (None: 60% of RAM).
        state_dir: where finished chunks are kept (resumable); None = in memory only.
        resume: continue from ``state_dir``; without it an existing state dir is refused.
        keep_state: keep ``state_dir`` after success.
        progress: a tqdm bar with rays/s.
        callback: ``callback(chunk_index, n_chunks)`` after each chunk is saved (may raise,
            e.g. :class:`ChunkInterrupt`).
        executor: where the chunks run (:mod:`prt_torch.executor`): None = this process, in
            order; a ``RayExecutor`` runs each chunk as a Ray task (the state files are still
            written here, by :func:`run_chunks`). Not part of the result: a chunk is a
            deterministic function of its range and the fingerprint.
        stream_result: where the assembled result rows live (:func:`result_rows`): True = in a
            file beside ``state_dir`` (``io.scratch_rows``: page cache, not memory; needs a
            ``state_dir``), False = in memory, None = a file when the rows exceed
            :data:`STREAM_RESULT_BYTES` and there is a ``state_dir``. Not part of the result
            (the same bits either way).
    """

    chunk_size: int | None = None
    workers: int | None = 1
    offset: float = 1e-4
    max_memory: int | None = None
    state_dir: str | os.PathLike | None = None
    resume: bool = False
    keep_state: bool = False
    progress: bool = False
    callback: Callable[[int, int], None] | None = None
    executor: Executor | None = None
    stream_result: bool | None = None

    def __post_init__(self):
        if self.chunk_size is not None:
            check_int("chunk_size", self.chunk_size, 1)
        if self.workers is not None:
            check_int("workers", self.workers, 1)
        check_float("offset", self.offset, 0.0, 0.1)
        if self.max_memory is not None:
            check_int("max_memory", self.max_memory, 1)
        for k in ("resume", "keep_state", "progress"):
            if not isinstance(getattr(self, k), bool):
                raise TypeError(f"RunOptions.{k} must be true or false, got {getattr(self, k)!r}")
        if self.stream_result not in (None, True, False):
            raise TypeError(f"RunOptions.stream_result must be true, false or None, got {self.stream_result!r}")
        if self.stream_result is True and self.state_dir is None:
            raise ValueError("RunOptions.stream_result=True needs a state_dir (the result's file goes beside it); "
                             "accepted: a state_dir, or stream_result=None/False")
        if self.callback is not None and not callable(self.callback):
            raise TypeError(f"RunOptions.callback must be callable, got {self.callback!r}")
        if self.executor is not None and not isinstance(self.executor, Executor):
            raise TypeError(f"RunOptions.executor must be a prt_torch.executor.Executor (LocalExecutor, RayExecutor) or None, "
                            f"got {self.executor!r}")

    def chunks(self, default: int) -> int:
        """``chunk_size`` or the kind's ``default``."""
        return default if self.chunk_size is None else int(self.chunk_size)

    def run_chunks(self, n_items: int, chunk_size: int, compute, *, fingerprint: dict, desc: str,
                   rays_of=None, sink=None) -> list[dict[str, torch.Tensor]]:
        """:func:`run_chunks` with these options (state dir, resume, progress, callback)."""
        return run_chunks(n_items, chunk_size, compute, state_dir=self.state_dir, fingerprint=fingerprint,
                          resume=self.resume, progress=self.progress, desc=desc, rays_of=rays_of, callback=self.callback,
                          executor=self.executor, sink=sink)

    def streams_result(self, nbytes: int) -> bool:
        """Whether a result of ``nbytes`` is assembled in a file (``stream_result``, above)."""
        if self.stream_result is None:
            return self.state_dir is not None and nbytes > stream_result_bytes()
        return bool(self.stream_result)

    def result_rows(self, shape: tuple[int, ...], dtype: torch.dtype = torch.float32, name: str = "result",
                    nbytes: int | None = None) -> torch.Tensor:
        """The tensor a precompute assembles its chunks into (``run_chunks``' sink copies each
        chunk in): ``torch.empty`` in memory, or — a result larger than :data:`STREAM_RESULT_BYTES`
        with a state directory, or ``stream_result=True`` — rows backed by an unlinked file beside
        the state directory (``io.scratch_rows``), so that a result larger than memory is written
        out by the kernel as it is filled and ``Transfer.save`` streams it from the page cache.
        Shape and dtype as asked; the values are the same bits either way. ``nbytes``: the size
        that decides (a kind assembling several buffers decides once for all of them, on what it
        holds in all — what its dry-run estimate counts); None: this buffer's own size."""
        n = torch.tensor([], dtype=dtype).element_size()
        for d in shape:
            n *= int(d)
        if not self.streams_result(n if nbytes is None else int(nbytes)):
            return torch.empty(shape, dtype=dtype)
        sd = Path(self.state_dir)
        return io.scratch_rows(sd.parent, shape, dtype, name=f"{sd.name}.{name}")

    def finish(self) -> None:
        """After a successful run: remove the state directory unless ``keep_state``."""
        if not self.keep_state:
            remove_state(self.state_dir)


@dataclasses.dataclass
class Transfer:
    """Per-vertex transfer of one kind over one mesh.

    Attributes:
        kind: 'diffuse' | 'glossy' | 'mrt' | 'transport' | 'wavelet'.
        data: ``float32 [V, ...]`` (see module docstring for the shapes of each kind; a wavelet
            transfer's quantised values keep their integer dtype).
        mesh: the ``Mesh`` it was computed for (frames, albedo).
        meta: bands, samples, seed, bounces, mesh hash, choices made, timings ...
        aux: further per-vertex tensors of the kind (wavelet: ``index [V, K]``, ``scale [V]``),
            saved as ``aux.<name>`` with their dtypes.
    """

    kind: str
    data: torch.Tensor
    mesh: Mesh
    meta: dict = dataclasses.field(default_factory=dict)
    aux: dict = dataclasses.field(default_factory=dict)

    def __post_init__(self):
        check_choice("kind", self.kind, KINDS)
        if not isinstance(self.data, torch.Tensor) or self.data.ndim < 2:
            raise ValueError(f"Transfer.data must be a tensor [V, ...]; got {getattr(self.data, 'shape', type(self.data))}")
        if self.data.shape[0] != self.mesh.num_vertices:
            raise ValueError(f"Transfer.data has {self.data.shape[0]} rows but the mesh has {self.mesh.num_vertices} vertices")

    @property
    def num_vertices(self) -> int:
        return int(self.data.shape[0])

    def signal(self) -> torch.Tensor:
        """``[V, D]`` float32: the per-vertex data flattened for codecs (Sloan 2003 §3.3: the
        n-dimensional signal x_p). ``meta['matrix_shape']`` says how to fold D back for matrices."""
        return self.data.reshape(self.data.shape[0], -1).to(torch.float32)

    def save(self, path: str | os.PathLike, overwrite: bool = False) -> Path:
        """Write atomically as io kind ``"transfer/<kind>"`` with the mesh arrays alongside."""
        meta = dict(self.meta)
        meta.update(transfer_version=TRANSFER_VERSION, transfer_kind=self.kind, mesh_name=self.mesh.name,
                    mesh_hash=self.mesh.content_hash(), data_shape=list(self.data.shape),
                    mesh_meta=io.jsonable(self.mesh.meta))
        keep = not self.data.is_floating_point()  # quantised wavelet values keep their integer dtype
        tensors = {"data": self.data if keep else self.data.to(torch.float32)}
        tensors.update({f"aux.{k}": v.contiguous() for k, v in self.aux.items()})
        tensors.update(self.mesh.to_tensors("mesh."))
        return io.save(path, tensors, kind=f"transfer/{self.kind}", meta=meta, overwrite=overwrite)

    @classmethod
    def load(cls, path: str | os.PathLike, mmap: bool = False) -> "Transfer":
        """Load a file written by ``save``; checks kind, shapes and the mesh hash. ``mmap``: the
        data tensor is a read-only memory map of the file (``io.load_mmap``: its pages are read
        when used and dropped under memory pressure — what ``prt relight`` streams a transfer
        larger than memory by; never write to it), the other tensors are loaded."""
        if mmap:
            tensors, meta = io.load_mapped(path, ("data",), expect_kind="transfer/")
        else:
            tensors, meta = io.load(path, expect_kind="transfer/")
        kind = meta["kind"].split("/", 1)[1]
        mesh = check_transfer_values(path, tensors, meta)
        if mesh is None:  # names the missing arrays
            mesh = Mesh.from_tensors(tensors, name=meta.get("mesh_name", "mesh"), meta=meta.get("mesh_meta"))
        for k in ("format", "format_version", "kind", "transfer_version", "transfer_kind", "mesh_name", "mesh_hash",
                  "data_shape", "mesh_meta"):
            meta.pop(k, None)
        aux = {k[4:]: v for k, v in tensors.items() if k.startswith("aux.")}
        return cls(kind=kind, data=tensors["data"], mesh=mesh, meta=meta, aux=aux)

    def __repr__(self) -> str:
        return f"Transfer(kind={self.kind!r}, data={tuple(self.data.shape)}, mesh={self.mesh!r})"


def mesh_bytes(mesh: Mesh) -> int:
    """Bytes the mesh's tensors hold (vertices, faces, normals, frames, albedo)."""
    return int(sum(t.numel() * t.element_size() for t in mesh.to_tensors("").values()))


def check_transfer_file(path: Path, meta: dict, shapes: dict[str, list[int]]) -> None:
    """Consistency of a transfer file (``io.register_check('transfer/')``): the data tensor
    against the recorded shape, the mesh rows, the bands and the matrix shape. Raises
    ValueError naming the file and the disagreement."""
    kind = str(meta.get("kind", "")).split("/", 1)[-1]
    if kind in ("chunk", "transport_chunk", "transport_views"):
        return
    if "data" not in shapes:
        raise ValueError(f"{str(path)!r} has no 'data' tensor; accepted: a file written by Transfer.save")
    d = shapes["data"]
    problems = []
    if meta.get("data_shape") is not None and list(meta["data_shape"]) != d:
        problems.append(f"metadata data_shape {meta['data_shape']} but the data tensor is {d}")
    if "mesh.vertices" in shapes and shapes["mesh.vertices"][0] != d[0]:
        problems.append(f"{shapes['mesh.vertices'][0]} mesh vertices but {d[0]} data rows")
    bands = meta.get("bands_in", meta.get("bands"))
    if isinstance(bands, int) and kind in ("diffuse", "glossy", "mrt") and d[-1] != bands * bands:
        problems.append(f"bands={bands} (n²={bands * bands}) but {d[-1]} coefficients per row")
    ms = meta.get("matrix_shape")
    if ms is not None and kind in ("glossy", "mrt") and list(ms) != d[1:3]:
        problems.append(f"matrix_shape {ms} but data {d}")
    if kind == "mrt" and isinstance(meta.get("M"), int) and d[1] != meta["M"] ** 2:
        problems.append(f"M={meta['M']} (M²={meta['M'] ** 2}) but {d[1]} rows")
    if kind == "wavelet":
        problems += _wavelet_shape_problems(meta, shapes)
    if problems:
        raise ValueError(f"{str(path)!r} is inconsistent: {'; '.join(problems)}")


io.register_check("transfer/", check_transfer_file)


def _wavelet_shape_problems(meta: dict, shapes: dict[str, list[int]]) -> list[str]:
    """A wavelet transfer's arrays against each other and its ``res`` (transfer.wavelet's layout:
    ``data [V, K]`` or ``[V, C, K]``, ``aux.index [V, K]``, ``aux.scale [V]``/``[V, L]`` or
    ``[V, C]``/``[V, C, L]`` with L = log2(res) + 1 Haar levels, K ≤ 6·res²)."""
    d, res = shapes["data"], meta.get("res")
    if not (isinstance(res, int) and not isinstance(res, bool) and 1 <= res <= 1 << 15 and not res & (res - 1)):
        return [f"res={res!r}; accepted: a power of two (the cube's face size)"]
    if len(d) not in (2, 3):
        return []  # the rank is named by check_transfer_values
    out, K, P = [], d[-1], 6 * res * res
    if K > P:
        out.append(f"{K} terms per vertex but a 6x{res}x{res} cube has {P} coefficients")
    if shapes.get("aux.index") != [d[0], K]:
        out.append(f"aux.index is {shapes.get('aux.index')} for data {d}; accepted: [{d[0]}, {K}]")
    sc, lead = shapes.get("aux.scale"), d[:-1]
    if sc not in (lead, lead + [int(math.log2(res)) + 1]):
        out.append(f"aux.scale is {sc} for data {d} at res={res}; accepted: {lead} or {lead + [int(math.log2(res)) + 1]}")
    return out

#: the largest |value| a transfer file may hold: squares and sums over a row stay finite in float32
#: (radiance transfer is of order 1; a value beyond this is a corrupt or mis-scaled file)
MAX_ABS_TRANSFER = 1e15


def check_transfer_values(path: Any, tensors: dict[str, torch.Tensor], meta: dict) -> Mesh | None:
    """The value-level half of a transfer file's consistency check, run by every command that
    reads one (``prt info``, ``compress``, ``render``, ``validate``; :meth:`Transfer.load`), after
    :func:`check_transfer_file` (metadata against shapes): the data's rank for its kind, finite
    data within ±:data:`MAX_ABS_TRANSFER`, face indices within the vertices, finite vertices, and
    the stored mesh hash. Returns the mesh (None for a file without mesh arrays: data only). Raises
    ValueError naming the file and what is wrong."""
    kind = str(meta.get("kind", "")).split("/", 1)[-1]
    name = str(path)
    if "data" not in tensors:
        raise ValueError(f"{name!r} has no 'data' tensor; accepted: a file written by Transfer.save")
    data = tensors["data"]
    ranks = {"diffuse": (2, 3), "glossy": (3,), "mrt": (3,), "wavelet": (2, 3)}.get(kind)
    if ranks is not None and data.ndim not in ranks:
        shape = {"diffuse": "[V, n²] or [V, C, n²]", "wavelet": "[V, K] or [V, 3, K]"}.get(kind, "[V, rows, n²]")
        raise ValueError(f"{name!r} is labelled kind=transfer/{kind} but its data has shape {tuple(data.shape)} (rank {data.ndim}); "
                         f"accepted for {kind}: rank {' or '.join(map(str, ranks))} ({shape})")
    top, rows = 0.0, max(1, (4 << 20) // max(1, data[:1].numel() * data.element_size()))
    for a in range(0, data.shape[0], rows):  # by chunks of rows: no [V, D] temporary (the data may be a memory map)
        part = data[a:a + rows]
        bad = ~torch.isfinite(part)
        if bool(bad.any()):
            i = tuple(int(v) for v in torch.nonzero(bad)[0])
            i = (i[0] + a,) + i[1:]
            n = int(bad.sum()) + sum(int((~torch.isfinite(data[b:b + rows])).sum()) for b in range(a + rows, data.shape[0], rows))
            raise ValueError(f"{name!r}: data holds {n} non-finite value(s), first at {i}; accepted: finite values")
        if part.numel():  # min and max in one pass, no |data| copy (a 1M-vertex file is not held twice)
            lo, hi = torch.aminmax(part) if part.is_floating_point() else (part.min(), part.max())
            top = max(top, abs(float(lo)), abs(float(hi)))
    if top > MAX_ABS_TRANSFER:
        raise ValueError(f"{name!r}: data reaches |{top:.3g}|, beyond ±{MAX_ABS_TRANSFER:g} (float32 products would overflow); "
                         "accepted: a transfer of physical scale (values of order 1)")
    if kind == "wavelet" and "aux.index" in tensors and "aux.scale" in tensors:  # shapes: check_transfer_file
        P, idx, sc = 6 * int(meta["res"]) ** 2, tensors["aux.index"], tensors["aux.scale"]
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= P):
            raise ValueError(f"{name!r}: aux.index holds Haar coefficients {int(idx.min())}..{int(idx.max())}; accepted: "
                             f"0..{P - 1} (6x{meta['res']}x{meta['res']} cube; the file is corrupt)")
        if not bool(torch.isfinite(sc).all()) or bool((sc < 0).any()):
            raise ValueError(f"{name!r}: aux.scale holds non-finite or negative scales; accepted: finite scales >= 0 "
                             "(the file is corrupt)")
    if not any(k.startswith("mesh.") for k in tensors):  # a data-only file (compress reads it; render needs the mesh)
        return None
    mesh = Mesh.from_tensors(tensors, name=meta.get("mesh_name", "mesh"), meta=meta.get("mesh_meta"))
    V = mesh.vertices.shape[0]
    f = mesh.faces
    if f.numel() and (int(f.min()) < 0 or int(f.max()) >= V):
        raise ValueError(f"{name!r}: mesh.faces index vertices {int(f.min())}..{int(f.max())}; accepted: 0..{V - 1} (the file is corrupt)")
    if not bool(torch.isfinite(mesh.vertices).all()):
        raise ValueError(f"{name!r}: mesh.vertices hold non-finite coordinates; accepted: finite vertices (the file is corrupt)")
    h = mesh.content_hash()
    if meta.get("mesh_hash") not in (None, h):
        raise ValueError(f"{name!r}: stored mesh hash {meta.get('mesh_hash')} does not match its arrays ({h}); the file is corrupt")
    return mesh


# ----------------------------------------------------------------------------------------
# chunked, resumable runner
# ----------------------------------------------------------------------------------------

class ChunkInterrupt(RuntimeError):
    """Raised by a ``callback`` to stop a run after a chunk (tests simulate interruption with it)."""


def default_state_dir(output: str | os.PathLike) -> Path:
    """Where a precompute writing ``output`` keeps its finished chunks: ``<output>.state/``."""
    output = Path(output)
    return output.with_name(output.name + ".state")


def _fingerprint_hash(fp: dict) -> str:
    return hashlib.sha256(json.dumps(io.jsonable(fp), sort_keys=True).encode()).hexdigest()[:32]


def run_chunks(
    n_items: int,
    chunk_size: int,
    compute: Callable[[int, int], dict[str, torch.Tensor]],
    *,
    state_dir: str | os.PathLike | None = None,
    fingerprint: dict | None = None,
    resume: bool = False,
    progress: bool = False,
    desc: str = "precompute",
    rays_of: Callable[[dict[str, torch.Tensor]], int] | None = None,
    callback: Callable[[int, int], None] | None = None,
    executor: Executor | None = None,
    sink: Callable[[int, int, dict[str, torch.Tensor]], None] | None = None,
) -> list[dict[str, torch.Tensor]]:
    """Run ``compute(start, stop)`` over ``[0, n_items)`` in chunks; return the chunk results in order.

    With ``state_dir``, each finished chunk is saved atomically as ``chunk_<i>.prt`` (io format)
    next to ``manifest.json`` holding ``fingerprint`` (all parameters that determine the result:
    mesh hash, bands, samples, seed, ...). With ``resume=True`` chunks already on disk are loaded
    instead of recomputed, so an interrupted run resumed gives exactly the uninterrupted result
    (chunks are deterministic functions of the fingerprint). Without ``resume`` an existing state
    directory is refused (it holds an interrupted run). A fingerprint mismatch is refused too.

    Args:
        compute: ``(start, stop) -> dict[name, tensor]`` for items start..stop-1.
        progress: show a tqdm bar; ``rays_of(result)`` (rays traced for a chunk) adds a rays/s figure.
        callback: called as ``callback(chunk_index, n_chunks)`` after each chunk is saved;
            it may raise (e.g. ``ChunkInterrupt``) to stop the run.
        executor: where the missing chunks are computed (:mod:`prt_torch.executor`; None: in this
            process, in order). With a ``RayExecutor`` each chunk is a Ray task (``compute`` is
            pickled with what it captures); chunks are saved here as they finish, in any order,
            so an interruption keeps every finished chunk. A chunk that fails on every attempt
            raises ``RuntimeError`` naming it after the other chunks finished (and were saved).
        sink: ``sink(start, stop, result)`` takes each chunk's result as it finishes (saved first,
            when there is a state directory) and the returned list holds None in its place: the
            caller copies it into its assembled result at once, so a run never holds its result
            twice (the chunk list and the assembled tensor; a freed chunk's heap is reused by the
            next chunk).
    """
    n_items = check_int("n_items", n_items, 0)
    chunk_size = check_int("chunk_size", chunk_size, 1)
    n_chunks = max(1, math.ceil(n_items / chunk_size)) if n_items else 0
    sd = None
    if state_dir is not None:
        sd = Path(state_dir)
        manifest = sd / "manifest.json"
        want = {"fingerprint_hash": _fingerprint_hash(fingerprint or {}), "n_items": n_items, "chunk_size": chunk_size,
                "fingerprint": io.jsonable(fingerprint or {})}
        if sd.exists():
            if not resume:
                raise FileExistsError(f"state directory {str(sd)!r} holds an interrupted run; pass resume=True (CLI: --resume) "
                                      "to continue it, or remove it (CLI: --overwrite) to start again")
            try:
                have = json.loads(manifest.read_text())
            except (OSError, ValueError):
                have = None
            if have is None or any(have.get(k) != want[k] for k in ("fingerprint_hash", "n_items", "chunk_size")):
                raise ValueError(f"state directory {str(sd)!r} belongs to a run with other parameters "
                                 f"({None if have is None else have.get('fingerprint')}); accepted: resume with the same "
                                 "mesh and parameters, or remove it (CLI: --overwrite)")
        else:
            sd.mkdir(parents=True)
            io.atomic_write_json(manifest, want)
    executor = LocalExecutor() if executor is None else executor
    ranges = [(i * chunk_size, min(n_items, (i + 1) * chunk_size)) for i in range(n_chunks)]
    paths = [None if sd is None else sd / f"chunk_{i:06d}.prt" for i in range(n_chunks)]
    results: list[dict[str, torch.Tensor] | None] = [None] * n_chunks
    bar = None
    if progress:
        from tqdm.auto import tqdm

        bar = tqdm(total=n_items, desc=desc, unit="vtx", dynamic_ncols=True)
    rays_done, t0 = 0, time.perf_counter()

    def finished(i: int, res: dict[str, torch.Tensor], fresh: bool) -> None:
        nonlocal rays_done
        start, stop = ranges[i]
        if fresh and paths[i] is not None:
            io.save(paths[i], res, kind="transfer/chunk", meta={"chunk": i, "start": start, "stop": stop})
        if sink is not None:
            sink(start, stop, res)
        else:
            results[i] = res
        if bar is not None:
            if fresh and rays_of is not None:
                rays_done += int(rays_of(res))
                el = max(time.perf_counter() - t0, 1e-9)
                bar.set_postfix_str(f"{rays_done / el / 1e6:.2f} Mrays/s")
            bar.update(stop - start)
        if callback is not None:
            callback(i, n_chunks)
        if sink is not None:
            res.clear()  # the sink has copied it: the executor's result list keeps no chunk (each is held once, briefly)

    try:
        todo = []
        for i in range(n_chunks):  # chunks of an earlier run first (a prefix, for a local run)
            if paths[i] is not None and paths[i].exists():
                finished(i, io.load(paths[i], expect_kind="transfer/chunk")[0], False)
            else:
                todo.append(i)
        out = executor.map(ChunkTask(compute, ranges), todo, on_result=lambda k, res: finished(todo[k], res, True))
        failed = [f for f in out if isinstance(f, TaskFailure)]
        if failed:
            f = failed[0]
            raise RuntimeError(f"{desc}: chunk {f.item} (items {ranges[f.item][0]}..{ranges[f.item][1] - 1}) failed "
                               f"{f.attempts} time(s): {f.error}; {len(failed)} of {n_chunks} chunk(s) failed"
                               + (f", the others are kept in {str(sd)!r} (resume to compute the rest)" if sd is not None else ""))
    finally:
        if bar is not None:
            bar.close()
    return results  # type: ignore[return-value]


class ChunkTask:
    """``chunk index -> compute(start, stop)``: what :func:`run_chunks` hands an executor (a
    plain object, so a Ray task gets ``compute`` and the ranges in one pickle)."""

    def __init__(self, compute: Callable[[int, int], dict[str, torch.Tensor]], ranges: list[tuple[int, int]]):
        self.compute, self.ranges = compute, ranges

    def __call__(self, i: int) -> dict[str, torch.Tensor]:
        return self.compute(*self.ranges[i])


def _rebuild_caster(vertices, faces, offset: float) -> RayCaster:
    return RayCaster(vertices=vertices, faces=faces, workers=1, offset=offset)


def _reduce_caster(c: RayCaster):
    """Pickling a :class:`~prt_torch.scene.RayCaster` (a chunk's ``compute`` sent to a Ray task
    captures one): its geometry and offset; the receiving process builds its own Embree scene
    and traces in-process (``workers=1``: the executor is what runs chunks in parallel)."""
    return _rebuild_caster, (c.vertices, c.faces, c.offset)


copyreg.pickle(RayCaster, _reduce_caster)


def cast_rows(src: torch.Tensor, dtype: torch.dtype, run: RunOptions, name: str = "result",
              rows: int = 1 << 16) -> torch.Tensor:
    """``src.to(dtype).contiguous()`` by chunks of ``rows`` rows into :meth:`RunOptions.result_rows`
    (in memory or file-backed as the run says): an elementwise conversion, so the same bits as the
    whole-tensor expression, without a second whole copy in memory when the result streams."""
    out = run.result_rows(tuple(src.shape), dtype, name=name)
    for i in range(0, src.shape[0], rows):
        out[i:i + rows] = src[i:i + rows].to(dtype)
    return out


def remove_state(state_dir: str | os.PathLike | None) -> None:
    """Delete a finished run's state directory."""
    if state_dir is not None and Path(state_dir).exists():
        shutil.rmtree(state_dir)
