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
:data:`ALLOCATOR_SLACK` (what the allocator keeps of freed temporaries, measured). Its tolerance: 1.0–2.0×
the peak RSS growth a run reaches (it is what :func:`check_fits` refuses on: never low, not so high that
it refuses runs that fit); measured at the command line 1.10–1.93× (diffuse and glossy with a bounce, and
transport tables, on scan_blob, bumpy_sphere small and medium and the Cornell box:
``benchmarks/bench_precompute_estimate.py --scenes``; ``tests/test_precompute_estimate_memory.py``). The
time is wall time under the load of the moment, per run 0.58–2.50× the real run there (median 0.98) on a
shared 2-core machine. :func:`estimate` returns every
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
from .base import ChunkInterrupt, RunOptions, mesh_bytes
from ..io import format_bytes
from .glossy import default_chunk, estimate_memory, memory_budget

__all__ = ["estimate", "check_fits", "format_estimate", "stage_width", "result_bytes_per_vertex", "memory_plan", "MemoryPlan", "full_params",
           "rss_bytes", "BVH_BYTES_PER_FACE",
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


def full_params(kind: str, kw: dict[str, Any]) -> dict[str, Any]:
    """Resolved keywords ``kw`` of ``kind`` with the kind's defaults filled in where unset (the
    estimate sizes what the run will do: subsurface's 3 bands and 256 samples, wavelet's res 32)."""
    from .registry import get_kind

    d = {k: v for k, v in get_kind(kind).defaults().items() if v is not None}
    return {**d, **{k: v for k, v in kw.items() if v is not None}}


def _diffuse_layout(kw: dict[str, Any], mesh: Mesh) -> tuple[int, int, bool, int, int]:
    """(n², bounces, hit-point bounces, hit channels, stored channels) of a diffuse run (precompute_diffuse)."""
    n2 = int(kw.get("bands", 5)) ** 2
    bounces = int(kw.get("bounces", 0) or 0)
    hits = bounces > 0 and kw.get("bounce_points", "hits") == "hits"
    fold = kw.get("fold_albedo")
    C = 3 if (kw.get("subsurface") is not None or fold is True or (fold is None and bounces > 0 and not mesh.is_grey())) else 1
    return n2, bounces, hits, 1 if mesh.is_grey() else 3, C


def result_bytes_per_vertex(kind: str, kw: dict[str, Any], mesh: Mesh) -> tuple[int, int]:
    """(bytes per vertex of the stored result, bytes per vertex held while assembling it, in
    memory or in files) for resolved precompute keywords ``kw`` of ``kind`` (defaults filled in:
    :func:`full_params`). Diffuse: ``[V, (3,) n²]`` float32, assembled from t⁰ in float64 and,
    with the hit-point estimator's bounces, its bounce terms (``diffuse.held_bytes_per_vertex``;
    the sparse ``bounce_points`` hold every bounce term and the sum too); glossy ``[V, m², n²]``, MRT
    ``[V, M², n²]`` float32 (chunks copied into it and released one by one); wavelet ``[V, K]``
    values + index + scales; transport: streamed, nothing held; subsurface ``[V, 3, n²]`` float32
    after a grey diffuse pass."""
    from .diffuse import held_bytes_per_vertex

    kw = full_params(kind, kw)
    n2 = int(kw.get("bands", 5)) ** 2
    if kind == "diffuse":
        n2, bounces, hits, Ch, C = _diffuse_layout(kw, mesh)
        out = 4 * C * n2
        if bounces == 0 or hits:
            return out, held_bytes_per_vertex(int(kw.get("bands", 5)), bounces if hits else 0, Ch, C)
        return out, 8 * n2 * (1 + 3 * (bounces + 2)) + out
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
        _, work = result_bytes_per_vertex("diffuse", {**kw, "fold_albedo": False, "subsurface": None}, mesh.with_albedo(1.0))
        out = 4 * 3 * n2
        return out, work + out
    raise ValueError(f"kind={kind!r}; accepted: diffuse, glossy, mrt, wavelet, transport, subsurface")


@dataclasses.dataclass
class MemoryPlan:
    """Where a run's result lives (:func:`memory_plan`): stored bytes per vertex, whether its
    assembled rows are in files (``RunOptions.streams_result``), the bytes held in memory while
    the rays run (rows filled so far) and at the result stage, and what is held whole, and why."""

    out_pv: int
    held_pv: int
    streamed: bool
    rows: int
    result: int
    whole: list[str]


def _scatter_plan(mesh: Mesh, spec: dict[str, Any], n2: int) -> tuple[int, int]:
    """(bytes the subsurface scatter holds whole, irradiance samples) for a term ``spec``."""
    from .subsurface import DEFAULT_SPACING, sample_count, scatter_bytes

    S = sample_count(mesh, spec["material"], float(spec["scale"]), float(spec.get("spacing", DEFAULT_SPACING)))
    return scatter_bytes(mesh.num_vertices, S, n2), S


def memory_plan(kind, kw: dict[str, Any], mesh: Mesh, run: RunOptions) -> MemoryPlan:
    """The memory of ``kind``'s result for resolved keywords ``kw`` (defaults filled in here):
    what streams to files (the kind's :meth:`RunOptions.result_rows` decisions, taken on the
    same byte counts) and what every pass must hold whole in memory (the dry run names it).

    - diffuse without bounces or with the hit-point estimator (default): t⁰, its bounce terms and
      the stored rows (:func:`diffuse.held_bytes_per_vertex`) in files when they exceed the
      threshold; the sparse ``bounce_points`` ('vertices', 'faces', 'corners') hold every row.
    - glossy, MRT: the rows, in a file when larger than the threshold.
    - wavelet: values, indices and scales in files when larger; 28 B per vertex of error sums held.
    - subsurface (and a ``subsurface:`` term): the irradiance samples and their hierarchy are held
      whole (:func:`subsurface.scatter_bytes`: every receiver may read any sample); the receivers'
      rows stream.
    - transport: a directory of chunk files, nothing held."""
    name = kind.name
    kw = full_params(name, kw)
    V = mesh.num_vertices
    out_pv, held_pv = result_bytes_per_vertex(name, kw, mesh)
    whole: list[str] = []
    if kind.output == "directory":
        return MemoryPlan(out_pv, held_pv, True, 0, 0, whole)
    blocks = 0  # the block-wise assembly's temporaries (diffuse), a few MiB
    if name in ("diffuse", "subsurface"):
        dkw = kw if name == "diffuse" else {**kw, "fold_albedo": False, "subsurface": None}
        dmesh = mesh if name == "diffuse" else mesh.with_albedo(1.0)
        n2, bounces, hits, Ch, C = _diffuse_layout(dkw, dmesh)
        d_out, d_held = result_bytes_per_vertex("diffuse", dkw, dmesh)
        from .diffuse import ASSEMBLE_ROWS

        blocks = ASSEMBLE_ROWS * 8 * n2 * (3 * C + 1)
        if bounces == 0 or hits:
            d_streamed = run.streams_result(d_held * V)
            rows = 0 if d_streamed else (d_held - d_out) * V
            d_result = blocks + (0 if d_streamed else d_held * V)
        else:
            d_streamed, rows, d_result = False, (d_held - d_out) * V, d_held * V
            whole.append(f"bounce_points={kw.get('bounce_points')!r}: its sparse bounces read every row, held in memory "
                         f"({format_bytes(d_held * V)}; bounce_points='hits' streams)")
        spec = kw.get("subsurface") if name == "diffuse" else {
            "material": _material(kw), "scale": kw.get("scale", 1.0), "spacing": kw.get("spacing", 1.0)}
        if spec is None:
            return MemoryPlan(out_pv, held_pv, d_streamed, rows, d_result, whole)
        sc, S = _scatter_plan(mesh, spec, n2)
        whole.append(f"the subsurface hierarchy over {S} irradiance samples, held whole (every receiver may read any "
                     f"sample): about {format_bytes(sc)}")
        if name == "diffuse":
            L = 24 * n2 * V  # the term's float64 rows (their own decision), then the assembly adds them
            L_mem = 0 if run.streams_result(L) else L
            irr = 8 * n2 * V
            result = (0 if d_streamed else (d_held - d_out) * V) + L_mem + max(irr + sc, blocks + (0 if d_streamed else d_out * V))
            return MemoryPlan(out_pv, held_pv, d_streamed, rows, result, whole)
        streamed = run.streams_result(out_pv * V)
        result = max(d_result, (0 if d_streamed else d_out * V) + sc + (0 if streamed else out_pv * V))
        return MemoryPlan(out_pv, held_pv, streamed and d_streamed, rows, result, whole)
    if name == "wavelet":
        from .wavelet import STATS_BYTES

        streamed = run.streams_result(out_pv * V)
        rows = STATS_BYTES * V + (0 if streamed else out_pv * V)
        return MemoryPlan(out_pv, held_pv, streamed, rows, rows + (0 if streamed else out_pv * V // 4), whole)
    streamed = run.streams_result(out_pv * V)  # glossy, mrt
    rows = 0 if streamed else out_pv * V
    result = 0 if streamed else held_pv * V + out_pv * V // 4
    spec = kw.get("subsurface") if name == "glossy" else None
    if spec is not None:  # the irradiance's diffuse pass (grey, ρ = 1), the hierarchy, the term's float64 rows; added in place
        dkw = {"bands": kw.get("bands", 5), "bounces": kw.get("bounces", 0), "fold_albedo": False}
        n2 = int(kw.get("bands", 5)) ** 2
        d_out, d_held = result_bytes_per_vertex("diffuse", dkw, mesh.with_albedo(1.0))
        d_mem = 0 if run.streams_result(d_held * V) else d_held * V
        sc, S = _scatter_plan(mesh, spec, n2)
        L = 24 * n2 * V
        result = rows + max(d_mem, (0 if run.streams_result(d_held * V) else d_out * V) + sc + (0 if run.streams_result(L) else L))
        whole.append(f"the subsurface hierarchy over {S} irradiance samples, held whole (every receiver may read any "
                     f"sample): about {format_bytes(sc)}")
    return MemoryPlan(out_pv, held_pv, streamed, rows, result, whole)


def _material(kw: dict[str, Any]):
    """The subsurface kind's material from its keywords (preset, or sigma_a/sigma_s/eta)."""
    from .subsurface import resolve_material

    return resolve_material(kw.get("material"), kw.get("sigma_a"), kw.get("sigma_s"), kw.get("eta"))


def real_chunk(kind: str, kw: dict[str, Any], chunk_size: int | None) -> int:
    """Vertices per chunk of the real run of ``kind`` (``chunk_size``, else the kind's default:
    ``glossy.default_chunk`` for glossy/MRT, 2²⁰ rays per chunk within [16, 16384] for diffuse
    and subsurface's irradiance pass, ``wavelet.default_chunk`` (about 2²⁰ rays at the sub-texel
    resolution) and ``transport``'s 8 Mi table entries per chunk file, at most 4096 vertices)."""
    if chunk_size is not None:
        return int(chunk_size)
    kw = full_params(kind, kw)
    samples = int(kw.get("samples", 1024))
    if kind in ("glossy", "mrt"):
        return default_chunk(samples)
    if kind in ("diffuse", "subsurface"):
        from .diffuse import rays_per_vertex

        return int(min(max(16, (1 << 20) // max(1, rays_per_vertex(samples, kw.get("sampling", "qmc")))), 16384))
    if kind == "wavelet":
        from .wavelet import default_chunk as wavelet_chunk

        return wavelet_chunk(int(kw.get("res", 32)), int(kw.get("supersample", 1)))
    if kind == "transport":
        return int(max(1, min(4096, (8 << 20) // (_views(kw) * 6 * int(kw.get("res", 8)) ** 2))))
    return 1024


def _views(kw: dict[str, Any]) -> int:
    """View directions J of a transport table (an icosphere frequency f: 10 f² + 2)."""
    views = kw.get("views", 3)
    return 10 * int(views) ** 2 + 2 if isinstance(views, int) else len(views)


def _chunk_bytes(kind: str, kw: dict[str, Any], V: int, chunk_size: int | None, grey: bool = True) -> int:
    """One chunk's working set (rays, their SH values, matrices), bytes (``grey``: the mesh's albedo is
    grey, one channel at the hit points)."""
    kw = full_params(kind, kw)
    n2 = int(kw.get("bands", 5)) ** 2
    samples = int(kw.get("samples", 1024))
    if kind in ("glossy", "mrt"):
        rows = int(kw.get("M", 11)) ** 2 if kind == "mrt" else int(kw.get("bands_out") or kw.get("bands", 5)) ** 2
        return estimate_memory(0, rows, n2, samples, min(real_chunk(kind, kw, chunk_size), max(V, 1)),
                               bounces=int(kw.get("bounces", 0) or 0))
    if kind in ("diffuse", "subsurface"):  # subsurface: its diffuse pass's rays
        from . import ray_kernels
        from .diffuse import rays_per_vertex

        sampling = kw.get("sampling", "qmc")
        rpv = rays_per_vertex(samples, sampling)
        c = min(real_chunk(kind, kw, chunk_size), max(V, 1))
        # origins, directions, ids, cosines, weights; and each ray's SH values except where the compiled qmc pass
        # accumulates them without a per-ray row (ray_kernels.sh_accumulate): counting them there read 3.8-4x the
        # measured peak growth (scan_blob, 2154 vertices, 1024 samples: 834 MiB against 220 MiB with one bounce)
        sh = 0 if sampling == "qmc" and ray_kernels.available() else 8 * n2
        bounces = int(kw.get("bounces", 0) or 0)
        if bounces == 0:
            return c * rpv * (73 + sh)
        if kw.get("bounce_points", "hits") != "hits":  # the sparse bounce rows: the rays' records twice, as before
            return c * rpv * (73 + sh) * 2
        # the hit-point estimator (diffuse._chunk_work, _hit_bounces): each ray's hit record (prim, barycentrics, its
        # (vertex, direction) indices and weight: 36 B) and, for half the rays taken as front hits (the blocked share
        # is not known before the rays), the hit's arrays (face, keys, float64 direction, weights: 100 B each); then
        # per batch of 2¹⁸ secondary rays (2¹⁸ / M hits): their rays and three [h, terms, C, n²] float64 buffers
        # (the terms, their weighted copy, the index_add). Measured peak growth, 1024 samples, one bounce: scan_blob
        # 202 MB (3% of the rays blocked; every ray counted as a hit read 2.07x that), the Cornell box 356 MB (77%
        # blocked, coloured hits: 1.3x with half)
        from .diffuse import resolve_hit_samples

        M = resolve_hit_samples(kw.get("hit_samples", "auto"), kw.get("estimator", "auto"))
        Ch = 1 if grey else 3
        batch = (1 << 18) * 73 + 3 * max(1, (1 << 18) // M) * bounces * Ch * n2 * 8
        return c * rpv * (73 + sh + 36 + 50) + batch
    c = min(real_chunk(kind, kw, chunk_size), max(V, 1))
    if kind == "wavelet":  # its own working-set count, without the result (V = 0)
        from .wavelet import estimate_wavelet_memory

        res, K, bits = int(kw.get("res", 32)), int(kw.get("terms", 256)), int(kw.get("bits", 8))
        C = 3 if int(kw.get("bounces", 0) or 0) > 0 else 1
        return estimate_wavelet_memory(0, res, min(K, 6 * res * res), bits, int(kw.get("supersample", 1)), c,
                                       kw.get("sampling") == "jittered", C)
    if kind == "transport":  # the chunk's table and the one being written (two reused buffers: transport's pool, a
        # chunk's file written in the background while the next computes), its rays and the BRDF on blocks of pairs
        from .transport import PAIR_BLOCK

        from .transport import AUTO_SUPERSAMPLE

        P = 6 * int(kw.get("res", 8)) ** 2
        ss = kw.get("supersample", "auto")
        sub = AUTO_SUPERSAMPLE if ss == "auto" else int(ss)  # texel averages: the sub-texels' heights per (vertex, texel)
        item = 2 if kw.get("dtype") == "float16" else 4
        return 2 * c * _views(kw) * P * item + c * P * 40 + c * P * sub * sub * 16 + PAIR_BLOCK * 256
    return 64 << 20


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
    whole: list[str] = dataclasses.field(default_factory=list)

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
    plan = memory_plan(kind, kw, mesh, run)
    out_pv, held_pv, streamed = plan.out_pv, plan.held_pv, plan.streamed
    m_bytes = max(mesh_bytes(mesh), int(mesh_rss or 0))
    traced = kw.get("shadows", True) not in (False, "never")
    bvh = BVH_BYTES_PER_FACE * F if traced else 0
    chunk = _chunk_bytes(kind.name, kw, V, run.chunk_size, mesh.is_grey())
    # the assembled rows, filled as each chunk finishes (run_chunks' sink); none in memory when they are
    # assembled in files (RunOptions.stream_result: a result larger than STREAM_RESULT_BYTES with a state
    # directory, as prt precompute always has) — only what a pass must hold whole (memory_plan) counts
    finished = plan.rows
    rays_stage = int(ALLOCATOR_SLACK * (bvh + chunk + finished))
    result_stage = int(ALLOCATOR_SLACK * max(plan.result, chunk if streamed else 0))
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
                  + (f"; time from {probe_info['note']}" if probe_info.get("note") else "")),
         "passes": probe_info.get("passes")},
        {"stage": "result", "bytes": result_stage, "seconds": None if seconds_rays is None else 0.0,
         "note": (f"{format_bytes(out_pv * V)} on disk, streamed per chunk (not held)" if kind.output == "directory" else
                  f"{format_bytes(out_pv * V)} assembled in a file beside the state directory and written from it "
                  "(page cache, not held)" if streamed else
                  f"{format_bytes(out_pv)} per vertex stored ({format_bytes(out_pv * V)}), {format_bytes(held_pv)} per vertex "
                  "held while assembling") + "".join(f"; {w}" for w in plan.whole)},
    ]
    if seconds_rays is not None and kind.output == "directory":  # transport: each chunk file is written inside the
        # probed pass (a background thread while the next chunk computes; a chunk counts as done once written), so the
        # probe's per-chunk time already holds the writes: adding the write rate again counted them twice
        stages[2]["note"] += "; written within each chunk's time above (the probe times the writes)"
    elif seconds_rays is not None:
        stages[2]["seconds"] = probe_info.get("write_seconds_per_byte", 0.0) * out_pv * V
    peak = m_bytes + max(rays_stage, result_stage)
    return Estimate(kind.name, V, F, stages, int(peak), memory_budget(run.max_memory), probe_info.get("rays"), list(plan.whole))


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


def _passes(kind, mesh: Mesh, params: dict, lights) -> list[tuple[str, Any, Mesh, dict, Any]]:
    """The passes of ``kind``'s run the probe times one by one: (name, kind, mesh, params, lights).
    Most kinds are one chunked pass; a subsurface scatter (the subsurface kind, a ``subsurface:``
    term of diffuse or glossy) is a second pass over the receivers — ``('scatter', None, mesh,
    {material, scale, spacing, epsilon, fresnel, method, bands, seed}, None)`` — after the
    irradiance's diffuse pass (the glossy term's own, a third)."""
    from .registry import get_kind

    name = kind.name
    if name == "subsurface":
        kw = full_params(name, kind.resolve(params, lights)[0])
        d = {k: kw[k] for k in ("bands", "samples", "bounces", "seed", "shadows") if k in kw}
        scatter = {"material": _material(kw), "scale": kw.get("scale", 1.0), "spacing": kw.get("spacing", 1.0),
                   "epsilon": kw.get("epsilon"), "fresnel": kw.get("fresnel", True), "method": kw.get("method", "hierarchical"),
                   "bands": int(kw.get("bands", 3)), "seed": int(kw.get("seed", 0))}
        return [("irradiance", get_kind("diffuse"), mesh.with_albedo(1.0), {**d, "fold_albedo": False}, None),
                ("scatter", None, mesh, scatter, None)]
    spec = params.get("subsurface") if name in ("diffuse", "glossy") else None
    if spec is None:
        return [(name, kind, mesh, params, lights)]
    from .subsurface import check_term_spec

    sp = check_term_spec(spec)
    kw = full_params(name, kind.resolve(params, lights)[0])
    bands = int(kw.get("bands", 5))
    scatter = {"material": sp["material"], "scale": sp["scale"], "spacing": sp["spacing"], "epsilon": sp["epsilon"],
               "fresnel": sp["fresnel"], "method": "hierarchical", "bands": bands, "seed": 0}
    main = {k: v for k, v in params.items() if k != "subsurface"}
    out = [(name, kind, mesh, main, lights)]
    if name == "glossy":  # its irradiance: a grey diffuse pass with the glossy run's rays (glossy._add_subsurface)
        shadows = kw.get("shadows", True)
        out.append(("irradiance", get_kind("diffuse"), mesh.with_albedo(1.0),
                    {"bands": bands, "samples": int(kw.get("samples", 1024)), "bounces": int(kw.get("bounces", 0)),
                     "seed": int(kw.get("seed", 0)), "fold_albedo": False,
                     "shadows": "always" if shadows not in (False, "never") else "never"}, None))
    return out + [("scatter", None, mesh, scatter, None)]


def _time_pass(go, V: int, k: int) -> tuple[float, dict[str, Any]]:
    """Seconds of one chunked pass over ``V`` items from its first :data:`PROBE_CHUNKS` chunks of
    ``k`` (:func:`probe_seconds`): ``go(callback)`` runs the pass with ``callback`` after each
    chunk (which stops it by :class:`ChunkInterrupt` after the third)."""
    marks: list[float] = []
    total = [0]  # the pass's chunk count, as its callback reports it

    def stop(i: int, n: int) -> None:
        marks.append(time.perf_counter())
        total[0] = n
        if len(marks) >= PROBE_CHUNKS and len(marks) < n:
            raise ChunkInterrupt("probe done")

    t0 = time.perf_counter()
    try:
        go(stop)
    except ChunkInterrupt:
        pass
    done = time.perf_counter()
    if len(marks) < PROBE_CHUNKS or len(marks) >= total[0]:  # the whole pass ran within the probe (small mesh, nothing
        # traced, or exactly PROBE_CHUNKS chunks: its time is the pass's, not the mean of chunks 2-3 scaled — the last
        # chunk may be a sliver: 106 of 2154 vertices in chunks of 1024, counted as a whole one, read 0.72-0.97)
        return done - t0, {"whole": True}
    timed = [marks[i] - marks[i - 1] for i in range(1, len(marks))]
    seconds, setup, per = probe_seconds(V, k, marks[0] - t0, timed)
    return seconds, {"whole": False, "setup_seconds": setup, "chunk_seconds": per, "timed": len(timed)}


def _probe(kind, mesh: Mesh, params: dict, run: RunOptions, lights, k: int | None) -> tuple[float | None, dict]:
    """Seconds of the ray stage from the first :data:`PROBE_CHUNKS` chunks of the real run
    (:func:`probe_chunk` vertices each; :func:`probe_seconds`), pass by pass (:func:`_passes`: a
    subsurface scatter is timed on its own receivers' chunks after the irradiance pass, its
    hierarchy built on the real samples from the unshadowed transfer — its cost is the geometry's,
    not the values'). As the real run, the probe saves each chunk to a state directory and fills
    file-backed rows where the real run would (the run's ``stream_result`` with a state directory;
    in memory without one) — in a temporary directory, removed after."""
    import tempfile
    import warnings

    V = mesh.num_vertices
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    t0 = time.perf_counter()
    total, notes, infos = 0.0, [], []
    with tempfile.TemporaryDirectory(prefix="prt_probe_") as tmp:
        stream = run.stream_result if run.state_dir is not None else False
        for i, (name, pk, pmesh, pparams, plights) in enumerate(_passes(kind, mesh, params, lights)):
            base = dataclasses.replace(run, state_dir=f"{tmp}/state{i}", resume=False, keep_state=False, stream_result=stream,
                                       progress=False, executor=None, workers=1)
            if pk is None:  # the subsurface scatter over the receivers (chunks of run.chunk_size, default 2048)
                kk = probe_chunk(V, run.chunk_size or 2048, k)

                def go(cb, base=base, kk=kk, sp=pparams):
                    from .diffuse import unshadowed_transfer
                    from .subsurface import subsurface_term

                    T = unshadowed_transfer(mesh.normals.to(torch.float64), sp["bands"])
                    with warnings.catch_warnings():
                        warnings.simplefilter("ignore")
                        subsurface_term(mesh, T, sp["material"], sp["scale"], epsilon=sp["epsilon"], fresnel=sp["fresnel"],
                                        method=sp["method"], spacing=sp["spacing"], seed=sp["seed"], meta={},
                                        run=dataclasses.replace(base, chunk_size=kk, callback=cb), dtype=torch.float32)
            else:
                pkw, _ = pk.resolve(pparams, plights)
                kk = probe_chunk(V, real_chunk(pk.name, pkw, run.chunk_size), k)

                def go(cb, base=base, kk=kk, pk=pk, pmesh=pmesh, pparams=pparams, plights=plights):
                    opts = dataclasses.replace(base, chunk_size=kk, callback=cb)
                    if pk.output == "directory":
                        pk.precompute(pmesh, pparams, run=opts, out=tmp + "/t", lights=plights)
                    else:
                        pk.precompute(pmesh, pparams, run=opts, lights=plights)
            sec, info = _time_pass(go, V, kk)
            total += sec
            infos.append({"pass": name, "chunk": kk, "seconds": sec, **info})
            label = "" if name == kind.name else f"{name}: "
            notes.append(f"{label}the whole pass ({sec:.2f} s: it finished within the probe)" if info["whole"] else
                         f"{label}set-up {info['setup_seconds']:.2f} s + {info['chunk_seconds']:.3f} s per chunk of {kk} "
                         f"vertices (mean of {info['timed']}) × {V / kk:.1f} chunks")
        # the write rate of the output's file system is not probed (it would write there); this
        # machine's temporary directory stands in: 32 MiB written and flushed
        buf = torch.zeros(8 << 20, dtype=torch.float32).numpy()
        tw = time.perf_counter()
        with open(tmp + "/w", "wb") as f:
            f.write(memoryview(buf))
            f.flush()
        write = (time.perf_counter() - tw) / buf.nbytes
    first = infos[0]
    info: dict[str, Any] = {"write_seconds_per_byte": write, "probe_wall_seconds": time.perf_counter() - t0,
                            "probe_chunk": first["chunk"], "load": load, "passes": infos}
    if not first["whole"]:
        info.update(setup_seconds=first["setup_seconds"], chunk_seconds=first["chunk_seconds"])
    if len(infos) == 1 and first["whole"]:
        return total, {**info, "note": f"the whole run (it finished within the probe), load {load:.1f}"}
    return total, {**info, "note": f"a probe: {'; '.join(notes)}; one worker, load {load:.1f}; the probe took "
                                   f"{info['probe_wall_seconds']:.1f} s"}


def stage_width(stages: list[dict]) -> int:
    """The width of a dry run's stage-name column: the longest of ``stages``' names and 'peak', at least 7 (the
    columns after it line up whatever the names: ``prt relight``'s wavelet plan has 'build|light')."""
    return max(7, len("peak"), *(len(str(st["stage"])) for st in stages))


def format_estimate(e: Estimate) -> list[str]:
    """One line per stage and a total, for ``--dry-run``: name, bytes, time and note in aligned columns."""
    lines = []
    w = stage_width(e.stages)
    secs = ["time not measured" if st["seconds"] is None else f"~{st['seconds']:.1f} s" for st in e.stages]
    tot = "" if e.seconds is None else f"~{e.seconds:.1f} s"
    ws = max(12, len(tot), *map(len, secs))  # 'time not measured' is wider than '~0.5 s'
    for st, sec in zip(e.stages, secs):
        lines.append(f"  {st['stage']:{w}s} {format_bytes(st['bytes']):>10s}  {sec:>{ws}s}  {st['note']}")
    lines.append(f"  {'peak':{w}s} {format_bytes(e.peak_bytes):>10s}  {tot:>{ws}s}  "
                 f"mesh + the larger of rays and result; budget {format_bytes(e.budget_bytes)} "
                 f"({'fits' if e.fits else 'does NOT fit'})")
    return lines


def check_fits(e: Estimate, what: str = "precompute") -> None:
    """Raise ValueError (one line, with every stage's estimate) when ``e`` exceeds its budget."""
    if e.fits:
        return
    parts = ", ".join(f"{st['stage']} {format_bytes(st['bytes'])}" for st in e.stages)
    raise ValueError(f"{what} {e.kind} of {e.vertices} vertices needs about {format_bytes(e.peak_bytes)} at its peak "
                     f"({parts}; chunks are already streamed to disk"
                     + "".join(f"; {w}" for w in e.whole) + f") but the budget is {format_bytes(e.budget_bytes)}; "
                     "accepted: fewer bands (or tents, bands_out, terms), a smaller mesh, or a larger --memory-limit "
                     "(RunOptions.max_memory) on a machine that has it")
