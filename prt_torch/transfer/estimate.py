"""What a precompute will take, per stage, before it starts (``prt precompute --dry-run``).

A precompute runs in three stages, each with its own memory:

1. **mesh** — the validated mesh (vertices, faces, normals, frames, albedo), held throughout;
   its bytes and build time are measured (it is already built when the estimate is made).
2. **rays** — the chunked pass (:func:`prt_torch.transfer.base.run_chunks`): the ray-casting
   scene (Embree's BVH, at most :data:`BVH_BYTES_PER_FACE` per face), one chunk's working set
   (its rays, SH values and matrices) and the result's rows filled so far: each chunk is written
   to the state directory as it finishes (``<out>.state/``: an interrupted run resumes) and
   copied into the assembled rows at once (``run_chunks(..., sink=)``), never kept as a list.
   Time: measured on a probe of the first three chunks of the real run (the same mesh, parameters,
   ray caster, chunk saves to a state directory and file-backed rows where the real run has
   them), the chunks as large as the real run's up to 1/16 of the vertices (the whole run when it
   has at most three chunks: :func:`probe_chunk`),
   the mean of the second and third chunk's time scaled to every vertex, plus the set-up before
   the first chunk (ray-casting scene, BRDF projection, tables). One worker, wall time under the
   load of the moment (stated in the note). Checked against real runs in
   ``benchmarks/bench_precompute_estimate.py`` (``reports/benchmarks/precompute_estimate.md``).
3. **result** — the assembled transfer (float32 rows, the kind's shape; the diffuse pass
   assembles in float64 first) and the write to the output file.

Peak memory is the mesh plus the larger of the last two stages, each counted array sum times
:data:`ALLOCATOR_SLACK` (what the allocator keeps of freed temporaries, measured). :func:`estimate` returns every
figure; :func:`check_fits` refuses — before any ray — a run whose peak exceeds the budget
(``RunOptions.max_memory``, else 60% of the machine's RAM), saying each stage's share. The
transport kind streams its tables to a directory: its result is never held (stage 3 is its
size on disk).
"""
from __future__ import annotations

import dataclasses
import math
import os
import time
from typing import Any

import torch

from ..scene import Mesh
from .base import ChunkInterrupt, RunOptions
from ..io import format_bytes
from .glossy import default_chunk, estimate_memory, memory_budget

__all__ = ["estimate", "check_fits", "format_estimate", "result_bytes_per_vertex", "rss_bytes", "BVH_BYTES_PER_FACE",
           "ALLOCATOR_SLACK", "real_chunk", "probe_chunk", "probe_seconds", "PROBE_CHUNKS", "PROBE_MIN_CHUNK", "PROBE_SHARE"]

#: what the process holds beyond the counted arrays of the rays and result stages: freed
#: temporaries the allocator keeps (heap fragments reused only by allocations that fit them). The
#: counted sums were 0.71 (MRT) and 0.85 (diffuse) of the measured peaks at 1M vertices
#: (reports/benchmarks/scale_precompute.md before this factor); 1.5 covers both.
ALLOCATOR_SLACK = 1.5

#: Embree's BVH over triangles, bytes per face (embreex's default build, measured as the RSS
#: growth of building a RayCaster and tracing once: 48 B per face on bumpy_sphere:100000, 94 on
#: bumpy_sphere:xl; a round upper figure)
BVH_BYTES_PER_FACE = 128

#: the probe's chunks: the first (set-up and first-touch costs) and the ones timed after it
PROBE_CHUNKS = 3
#: the smallest probe chunk, vertices (below it the timed chunks are a few ms: scheduler noise)
PROBE_MIN_CHUNK = 1024
#: a probe chunk is at most 1 / PROBE_SHARE of the mesh's vertices (its cost: PROBE_CHUNKS of them + set-up)
PROBE_SHARE = 16


def rss_bytes() -> int:
    """This process's resident set size now, bytes (``/proc/self/statm``; 0 where it is absent)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):  # pragma: no cover - not Linux
        return 0


def mesh_bytes(mesh: Mesh) -> int:
    """Bytes the mesh's tensors hold (vertices, faces, normals, frames, albedo)."""
    return int(sum(t.numel() * t.element_size() for t in mesh.to_tensors("").values()))


def result_bytes_per_vertex(kind: str, kw: dict[str, Any], mesh: Mesh) -> tuple[int, int]:
    """(bytes per vertex of the stored result, bytes per vertex held while assembling it) for
    resolved precompute keywords ``kw`` of ``kind``. Diffuse: ``[V, (3,) n²]`` float32, assembled
    in float64 (with bounces, every bounce term and the sum too); glossy ``[V, m², n²]``, MRT
    ``[V, M², n²]`` float32 (chunks copied into it and released one by one); wavelet ``[V, K]``
    values + index + a scale; transport: streamed, nothing held; subsurface ``[V, 3, n²]`` float32 after
    a grey diffuse pass."""
    n2 = int(kw.get("bands", 5)) ** 2
    if kind == "diffuse":
        bounces = int(kw.get("bounces", 0))
        fold = kw.get("fold_albedo")
        C = 3 if (fold is True or (fold is None and bounces > 0 and not mesh.is_grey())) else 1
        out = 4 * C * n2
        work = 8 * n2 + out if bounces == 0 else 8 * n2 * (1 + 3 * (bounces + 2)) + out
        return out, work
    if kind in ("glossy", "mrt"):
        rows = int(kw.get("M", 11)) ** 2 if kind == "mrt" else int(kw.get("bands_out") or kw.get("bands", 5)) ** 2
        out = 4 * rows * n2
        return out, out
    if kind == "wavelet":
        from .wavelet import bytes_per_vertex as wavelet_bytes

        K, bits = int(kw.get("terms", 256)), int(kw.get("bits", 8))
        res = int(kw.get("res", 32))
        n_scales = int(math.log2(res)) + 1 if kw.get("scales", "level") == "level" and bits != 32 else 1  # wavelet.precompute_wavelet
        C = 3 if int(kw.get("bounces", 0) or 0) > 0 and not mesh.is_grey() else 1  # a coloured bounce: one transfer per colour
        out = wavelet_bytes(K, bits, 6 * res * res, n_scales, C)
        return out, out + 8 * K * C
    if kind == "transport":
        views = kw.get("views", 3)
        J = 10 * int(views) ** 2 + 2 if isinstance(views, int) else len(views)
        res = int(kw.get("res", 8))
        return J * 6 * res * res * (2 if kw.get("dtype") == "float16" else 4), 0
    if kind == "subsurface":  # a grey diffuse precompute, then the dipole term in colour (subsurface_kind)
        _, work = result_bytes_per_vertex("diffuse", {**kw, "fold_albedo": False}, mesh)
        out = 4 * 3 * n2
        # + the colour term and the irradiance samples' SH rows (float64, about one sample per vertex
        # where vertices are closer than the spacing; denser meshes of a thin medium hold more)
        return out, work + out + 2 * 8 * 3 * n2
    raise ValueError(f"kind={kind!r}; accepted: diffuse, glossy, mrt, wavelet, transport, subsurface")


def real_chunk(kind: str, kw: dict[str, Any], chunk_size: int | None) -> int:
    """Vertices per chunk of the real run of ``kind`` (``chunk_size``, else the kind's default:
    ``glossy.default_chunk`` for glossy/MRT, 2²⁰ rays per chunk within [16, 16384] for diffuse
    and subsurface, 1024 otherwise)."""
    if chunk_size is not None:
        return int(chunk_size)
    samples = int(kw.get("samples", 1024))
    if kind in ("glossy", "mrt"):
        return default_chunk(samples)
    if kind in ("diffuse", "subsurface"):
        from .diffuse import rays_per_vertex

        return int(min(max(16, (1 << 20) // max(1, rays_per_vertex(samples, kw.get("sampling", "qmc")))), 16384))
    return 1024


def _chunk_bytes(kind: str, kw: dict[str, Any], V: int, chunk_size: int | None) -> int:
    """One chunk's working set (rays, their SH values, matrices), bytes."""
    n2 = int(kw.get("bands", 5)) ** 2
    samples = int(kw.get("samples", 1024))
    if kind in ("glossy", "mrt"):
        rows = int(kw.get("M", 11)) ** 2 if kind == "mrt" else int(kw.get("bands_out") or kw.get("bands", 5)) ** 2
        return estimate_memory(0, rows, n2, samples, min(real_chunk(kind, kw, chunk_size), max(V, 1)))
    if kind in ("diffuse", "subsurface"):  # subsurface: its diffuse pass's rays
        from .diffuse import rays_per_vertex

        rpv = rays_per_vertex(samples, kw.get("sampling", "qmc"))
        c = min(real_chunk(kind, kw, chunk_size), max(V, 1))
        return c * rpv * (73 + 8 * n2) * (1 + int(kw.get("bounces", 0) > 0))  # origins, directions, ids, cosines, SH
    return 64 << 20  # wavelet, transport: their chunks are bounded by their own defaults


@dataclasses.dataclass
class Estimate:
    """Per-stage figures of a planned precompute (bytes, seconds; None where not measured)."""

    kind: str
    vertices: int
    faces: int
    stages: list[dict[str, Any]]
    peak_bytes: int
    budget_bytes: int
    rays: int | None = None

    @property
    def fits(self) -> bool:
        return self.peak_bytes <= self.budget_bytes

    @property
    def seconds(self) -> float | None:
        s = [st["seconds"] for st in self.stages]
        return None if any(x is None for x in s) else float(sum(s))


def estimate(kind, mesh: Mesh, params: dict[str, Any], run: RunOptions | None = None, lights: list | None = None,
             probe: bool = True, probe_vertices: int | None = None, mesh_seconds: float | None = None,
             mesh_rss: int | None = None) -> Estimate:
    """Per-stage memory and time of ``kind.precompute(mesh, params, run)`` (module docstring).

    Args:
        kind: a :class:`~prt_torch.transfer.registry.TransferKind`.
        params: its parameters (validated and resolved here, ``'auto'`` from ``lights``).
        probe: time the first :data:`PROBE_CHUNKS` chunks of the real run (state and output in a
            temporary directory, removed; the result is discarded). Without it the seconds are None.
        probe_vertices: vertices per probe chunk; None: :func:`probe_chunk` (the real run's chunk,
            at most V / :data:`PROBE_SHARE`, at least :data:`PROBE_MIN_CHUNK`).
        mesh_seconds: how long the mesh took to build (measured by the caller).
        mesh_rss: the process's RSS growth over the mesh build (measured by the caller): the
            mesh stage counts the larger of it and the mesh's tensors (a build leaves freed heap
            the allocator keeps: 378 MiB of RSS for 149 MiB of tensors at 1M vertices).
    Returns:
        :class:`Estimate`; ``peak_bytes`` = mesh + max(rays stage, result stage).
    """
    run = RunOptions() if run is None else run
    kw, _ = kind.resolve(params, lights)
    V, F = mesh.num_vertices, mesh.num_faces
    out_pv, held_pv = result_bytes_per_vertex(kind.name, kw, mesh)
    m_bytes = max(mesh_bytes(mesh), int(mesh_rss or 0))
    traced = kw.get("shadows", True) not in (False, "never")
    bvh = BVH_BYTES_PER_FACE * F if traced else 0
    chunk = _chunk_bytes(kind.name, kw, V, run.chunk_size)
    # the assembled rows, filled as each chunk finishes (run_chunks' sink): float64 for diffuse, the stored rows elsewhere;
    # none in memory when they are assembled in a file (RunOptions.stream_result: a result larger than
    # STREAM_RESULT_BYTES with a state directory, as prt precompute always has) — only what streaming cannot
    # take: diffuse with bounces or a folded albedo, subsurface, wavelet assemble in memory
    streamed = (kind.output != "directory" and kind.name in ("glossy", "mrt", "diffuse") and run.streams_result(out_pv * V)
                and not (kind.name == "diffuse" and (int(kw.get("bounces", 0)) > 0 or out_pv != 4 * int(kw.get("bands", 5)) ** 2)))
    finished = 0 if kind.output == "directory" or streamed else (held_pv - out_pv if kind.name == "diffuse" else out_pv) * V
    rays_stage = int(ALLOCATOR_SLACK * (bvh + chunk + finished))
    result_stage = (int(ALLOCATOR_SLACK * chunk) if streamed else  # the result is written from the page cache
                    int(ALLOCATOR_SLACK * (held_pv * V + (0 if kind.output == "directory" else out_pv * V // 4))))  # + scratch
    seconds_rays = None
    probe_info: dict[str, Any] = {}
    if probe:
        seconds_rays, probe_info = _probe(kind, mesh, params, run, lights, probe_vertices)
    stages = [
        {"stage": "mesh", "bytes": m_bytes, "seconds": mesh_seconds,
         "note": f"{V} vertices, {F} faces (held throughout)"},
        {"stage": "rays", "bytes": rays_stage, "seconds": seconds_rays,
         "note": (f"ray-casting scene ~{format_bytes(bvh)}, one chunk ~{format_bytes(chunk)}, the rows filled so far "
                  f"{format_bytes(finished)} (each chunk also on disk in the state directory)"
                  + (f"; time from {probe_info['note']}" if probe_info.get("note") else ""))},
        {"stage": "result", "bytes": result_stage, "seconds": None if seconds_rays is None else 0.0,
         "note": (f"{format_bytes(out_pv * V)} on disk, streamed per chunk (not held)" if kind.output == "directory" else
                  f"{format_bytes(out_pv * V)} assembled in a file beside the state directory and written from it "
                  "(page cache, not held)" if streamed else
                  f"{format_bytes(out_pv)} per vertex stored ({format_bytes(out_pv * V)}), {format_bytes(held_pv)} per vertex "
                  "held while assembling")},
    ]
    if seconds_rays is not None:
        stages[2]["seconds"] = probe_info.get("write_seconds_per_byte", 0.0) * out_pv * V
    peak = m_bytes + max(rays_stage, result_stage)
    return Estimate(kind.name, V, F, stages, int(peak), memory_budget(run.max_memory), probe_info.get("rays"))


def probe_chunk(V: int, chunk: int, k: int | None = None) -> int:
    """Vertices per chunk of the probe for ``V`` vertices whose real run uses chunks of ``chunk``.

    ``k`` when given. Else the real chunk when the real run has at most :data:`PROBE_CHUNKS`
    chunks (the probe then is the whole run, at most three chunks of the kind's ~2¹⁹–2²⁰ rays),
    and otherwise ``min(chunk, max(PROBE_MIN_CHUNK, V // PROBE_SHARE))``: the real chunk where the
    mesh is large enough, never more than ``1 / PROBE_SHARE`` of the vertices per chunk (the
    probe's cost). Why not the former 1024 vertices: such a chunk is ~10 ms of work, and one
    preemption on a shared machine doubles it (estimates 2–3× the real run at 100k vertices,
    load 2.3–3.4), and with torch's spinning OpenMP threads MRT's wall time per vertex in
    1024-vertex chunks was at times 2–3× that in its real 8192-vertex ones
    (``reports/benchmarks/precompute_estimate.md``)."""
    if k is not None:
        return max(1, int(k))
    chunk = max(1, int(chunk))
    if V <= PROBE_CHUNKS * chunk:
        return chunk
    return min(chunk, max(PROBE_MIN_CHUNK, int(V) // PROBE_SHARE))


def probe_seconds(V: int, k: int, first: float, timed: list[float]) -> tuple[float, float, float]:
    """(seconds, set-up, seconds per chunk) of the ray stage from a probe over chunks of ``k``
    vertices: ``first`` = seconds from the start to the end of the first chunk (set-up + one
    chunk), ``timed`` = the seconds of the chunks after it. The per-chunk time is their mean
    (one 10 ms chunk alone is at the mercy of the scheduler on a shared machine); the set-up is
    ``first`` less one chunk (never negative); the run = set-up + per-chunk × V / k (the last,
    partial chunk counted in proportion, not as a whole one)."""
    if not timed:
        raise ValueError("probe_seconds: timed is empty; accepted: the seconds of at least one chunk after the first")
    per = sum(timed) / len(timed)
    setup = max(0.0, first - per)
    return setup + per * V / k, setup, per


def _probe(kind, mesh: Mesh, params: dict, run: RunOptions, lights, k: int | None) -> tuple[float | None, dict]:
    """Seconds of the ray stage from the first :data:`PROBE_CHUNKS` chunks of the real run
    (:func:`probe_chunk` vertices each; :func:`probe_seconds`). As the real run, the probe saves
    each chunk to a state directory and, where the real result would be assembled in a file
    (``RunOptions.streams_result``), fills file-backed rows — in a temporary directory, removed after."""
    import tempfile

    V = mesh.num_vertices
    kw, _ = kind.resolve(params, lights)
    out_pv, _ = result_bytes_per_vertex(kind.name, kw, mesh)
    k = probe_chunk(V, real_chunk(kind.name, kw, run.chunk_size), k)
    marks: list[float] = []

    def stop(i: int, n: int) -> None:
        marks.append(time.perf_counter())
        if len(marks) >= PROBE_CHUNKS:
            raise ChunkInterrupt("probe done")

    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="prt_probe_") as tmp:
        opts = dataclasses.replace(run, chunk_size=k, callback=stop, state_dir=tmp + "/state", resume=False, keep_state=False,
                                   stream_result=run.streams_result(out_pv * V), progress=False, executor=None, workers=1)
        try:
            if kind.output == "directory":
                kind.precompute(mesh, params, run=opts, out=tmp + "/t", lights=lights)
            else:
                kind.precompute(mesh, params, run=opts, lights=lights)
        except ChunkInterrupt:
            pass
        done = time.perf_counter()
        # the write rate of the output's file system is not probed (it would write there); this
        # machine's temporary directory stands in: 32 MiB written and flushed
        buf = torch.zeros(8 << 20, dtype=torch.float32).numpy()
        tw = time.perf_counter()
        with open(tmp + "/w", "wb") as f:
            f.write(memoryview(buf))
            f.flush()
        write = (time.perf_counter() - tw) / buf.nbytes
    info: dict[str, Any] = {"write_seconds_per_byte": write, "probe_wall_seconds": time.perf_counter() - t0, "probe_chunk": k,
                            "load": load}
    if len(marks) < PROBE_CHUNKS:  # the whole run finished within the probe (small mesh, or nothing traced)
        return done - t0, {**info, "note": f"the whole run (it finished within the probe), load {load:.1f}"}
    timed = [marks[i] - marks[i - 1] for i in range(1, len(marks))]
    seconds, setup, per = probe_seconds(V, k, marks[0] - t0, timed)
    info.update(setup_seconds=setup, chunk_seconds=per)
    return seconds, {**info, "note": f"a probe: set-up {setup:.2f} s + {per:.3f} s per chunk of {k} vertices (mean of "
                                     f"{len(timed)}) × {V / k:.1f} chunks, one worker, load {load:.1f}; the probe took "
                                     f"{info['probe_wall_seconds']:.1f} s"}


def format_estimate(e: Estimate) -> list[str]:
    """One line per stage and a total, for ``--dry-run``."""
    lines = []
    for st in e.stages:
        sec = "time not measured" if st["seconds"] is None else f"~{st['seconds']:.1f} s"
        lines.append(f"  {st['stage']:7s} {format_bytes(st['bytes']):>10s}  {sec:>12s}  {st['note']}")
    tot = e.seconds
    lines.append(f"  peak    {format_bytes(e.peak_bytes):>10s}  {'' if tot is None else f'~{tot:.1f} s':>12s}  "
                 f"mesh + the larger of rays and result; budget {format_bytes(e.budget_bytes)} "
                 f"({'fits' if e.fits else 'does NOT fit'})")
    return lines


def check_fits(e: Estimate, what: str = "precompute") -> None:
    """Raise ValueError (one line, with every stage's estimate) when ``e`` exceeds its budget."""
    if e.fits:
        return
    parts = ", ".join(f"{st['stage']} {format_bytes(st['bytes'])}" for st in e.stages)
    raise ValueError(f"{what} {e.kind} of {e.vertices} vertices needs about {format_bytes(e.peak_bytes)} at its peak "
                     f"({parts}; chunks are already streamed to disk) but the budget is {format_bytes(e.budget_bytes)}; "
                     "accepted: fewer bands (or tents, bands_out, terms), a smaller mesh, or a larger --memory-limit "
                     "(RunOptions.max_memory) on a machine that has it")
