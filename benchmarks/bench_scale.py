"""Benchmark: how each stage's cost grows with the mesh, 10k -> 100k -> 1M vertices (issue 42, part 3).

    .venv/bin/python benchmarks/bench_scale.py [--sizes 10000 100000 1000000] [--stages ...]
        [--samples 64] [--mrt-samples 32] [--work DIR] [--quick] [--out reports/benchmarks/scale.md]

Stages, on ``bumpy_sphere:<size>`` (``size`` a vertex count: the nearest geodesic level,
10 f² + 2 vertices; 1M is ``bumpy_sphere:xl``), each run **in a child process of its own**
(``python bench_scale.py --child STAGE ...``) so that its peak memory is its own —
``resource.getrusage`` in the child: ``ru_maxrss`` of the child itself and of its own children
(Embree workers, ``prt bench``):

* ``diffuse``: ``precompute_diffuse`` with shadows traced (qmc + auto, the defaults), no bounces,
  ``--bands`` bands, ``--samples`` samples, chunks streamed to a state directory, then saved;
* ``mrt``: the ``mrt`` kind (``--mrt-bands`` bands, M = ``--mrt-tents``, Phong s = 12,
  ``--mrt-samples`` samples; low bands so that 1M fits beside five other users' jobs), saved;
* ``cpca``: CPCA (16 clusters, 4 vectors) fit + encode of the diffuse transfer, loaded from its
  file, and the codec file saved;
* ``cpca_stream``: the same fit + encode from the transfer file's data memory-mapped
  (``io.load_mmap``: the signal is not read into memory; the codec streams it by chunks,
  ``codecs.chunks``), the codec file saved;
* ``relight``: the codec file loaded and relit under the built-in ``sky`` (median of 5 calls,
  after one warm-up), beside the uncompressed diffuse relighting of the same transfer;
* ``bench``: ``prt bench`` of a config with this scene, the same diffuse transfer (its own cache:
  the whole command, precompute included), one codec (CPCA 16×4), one light, one view, no renders.

Reported per stage and size: seconds, seconds per vertex, the peak RSS and the peak above the
child's RSS after its imports (what the stage itself added), per vertex; the last column is
each per-vertex figure over the smallest size's (goal: ≤ 1.5 at 1M). The **marginal** memory
(issue 42 part 3, (1)): each child first runs its stage once on a tiny input (a 642-vertex
mesh, or 2048 rows) — imports, kernel compiles, thread pools, first-use allocations — then
resets its peak (``/proc/self/clear_refs``) and records ``VmHWM`` − RSS at the reset over the
real stage: what the stage's own arrays took, not the fixed costs (which made the 10k figures
noise before). The Embree worker is a process of its own: its peak is the ``worker`` column. Every child is single
ray-casting worker (``workers=1``) and torch's default threads, so rows compare like with like.
The machine is shared (2 cores, six users): the load average is recorded with every row; time
ratios taken under load are not a speed figure, memory figures do not depend on it.

``--quick``: 2k and 10k vertices, small samples (a CI-sized smoke, about a minute).
Writes ``--out`` (.md) and the same numbers as .json beside it, atomically.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

STAGES = ("embree", "diffuse", "mrt", "cpca", "cpca_stream", "relight", "bench")


def rss_now() -> int:
    """Resident set size of this process now, bytes (``/proc/self/statm``)."""
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def peak_rss() -> tuple[int, int]:
    """(peak RSS of this process, largest peak RSS of any of its waited-for children), bytes."""
    return (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024,
            resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss * 1024)


def reset_peak() -> bool:
    """Reset this process's peak RSS (Linux: ``echo 5 > /proc/self/clear_refs``); False where
    the kernel does not allow it."""
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")
        return True
    except OSError:
        return False


def vm_hwm() -> int:
    """Peak RSS since the last :func:`reset_peak` (``VmHWM`` of ``/proc/self/status``), bytes."""
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    return 0


class AnonSampler:
    """The peak of ``RssAnon`` (memory the process holds: heap, anonymous maps — not file pages,
    which the kernel writes back and drops under pressure) sampled every ``dt`` seconds in a
    thread, bytes: ``VmHWM`` counts a file-backed result's resident pages as well, this does not."""

    def __init__(self, dt: float = 0.02):
        import threading

        self.dt, self.peak, self._stop = dt, 0, threading.Event()
        self._t = threading.Thread(target=self._run, daemon=True)

    @staticmethod
    def now() -> int:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith("RssAnon:"):
                    return int(line.split()[1]) * 1024
        return 0

    def _run(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, self.now())
            self._stop.wait(self.dt)

    def __enter__(self):
        self.peak = self.now()
        self._t.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._t.join()
        self.peak = max(self.peak, self.now())


# ----------------------------------------------------------------------------------------------
# the child: one stage, one size
# ----------------------------------------------------------------------------------------------

def _paths(work: Path, size: int) -> dict[str, Path]:
    return {"diffuse": work / f"diffuse_{size}.prt", "mrt": work / f"mrt_{size}.prt",
            "cpca": work / f"diffuse_{size}.cpca.prt"}


def child(args) -> dict:
    import torch  # noqa: F401  (imports counted in the baseline, not in the stage)

    from prt_torch import codecs
    from prt_torch.scene import load_scene
    from prt_torch.transfer import RunOptions, Transfer, get_kind

    rss_imports = rss_now()
    base = max(rss_imports, peak_rss()[0])  # the imports' own peak is not the stage's
    work, size, stage = Path(args.work), int(args.size), args.child
    p = _paths(work, size)
    out: dict = {"stage": stage, "size": size, "rss_after_imports": base, "rss_now_after_imports": rss_imports}
    if not args.no_warm:
        warm_up(stage, args, work)
    import gc

    gc.collect()
    out["marginal_reset"] = reset_peak()
    out["rss_at_reset"] = rss_now()
    t0 = time.perf_counter()
    c0 = time.process_time()  # CPU seconds of this process, every thread: what the machine's load moves least
    if stage == "embree":  # the peer: bare Embree occlusion rays from the mesh's own vertices
        import numpy as np

        from prt_torch.scene import RayCaster

        mesh = load_scene(f"bumpy_sphere:{size}")
        caster = RayCaster(mesh, workers=1)
        k = min(mesh.num_vertices, 1 << 15)  # a contiguous block of vertices (the precompute's order)
        a = (mesh.num_vertices - k) // 2
        rpv = (args.samples + 1) // 2
        u = (np.arange(rpv) + 0.5) / rpv  # a hemisphere set in each vertex frame (uniform in solid angle)
        phi = 2 * np.pi * ((np.arange(rpv) * 0.6180339887498949) % 1.0)
        r = np.sqrt(1 - u * u)
        local = np.stack([r * np.cos(phi), r * np.sin(phi), u], 1)  # [rpv, 3]
        F = mesh.frames()[a:a + k].numpy()  # rows (t, b, n)
        d = np.einsum("nk,vkj->vnj", local, F).reshape(-1, 3)
        o = np.repeat((caster.local(mesh.vertices[a:a + k]) + 1e-4 * mesh.normals[a:a + k]).numpy(), rpv, axis=0)
        caster.trace(o[:1024], d[:1024])  # warm-up
        t, c = time.perf_counter(), time.process_time()
        for i in range(0, o.shape[0], 1 << 18):
            caster.trace(o[i:i + (1 << 18)], d[i:i + (1 << 18)])
        out["bare_seconds_per_ray"] = (time.perf_counter() - t) / o.shape[0]
        out["bare_cpu_seconds_per_ray"] = (time.process_time() - c) / o.shape[0]
        out["bare_rays"] = int(o.shape[0])
        caster.close()
        out["vertices"] = mesh.num_vertices
    elif stage in ("diffuse", "mrt"):
        tm = time.perf_counter()
        mesh = load_scene(f"bumpy_sphere:{size}")
        out["mesh_seconds"] = time.perf_counter() - tm
        state = Path(str(p[stage]) + ".state")
        run = RunOptions(workers=1, state_dir=state, resume=state.exists())
        params = ({"bands": args.bands, "samples": args.samples, "shadows": "always"} if stage == "diffuse" else
                  {"bands": args.mrt_bands, "M": args.mrt_tents, "samples": args.mrt_samples, "shadows": "always",
                   "brdf": {"type": "phong", "s": 12.0}})
        from prt_torch.transfer.estimate import estimate

        est = estimate(get_kind(stage), mesh, dict(params), run, probe=False,  # what --dry-run says, for comparison
                       mesh_rss=rss_now() - rss_imports)
        out["estimated_peak_bytes"], out["estimated_stages"] = est.peak_bytes, {st["stage"]: st["bytes"] for st in est.stages}
        out["rss_with_mesh"] = rss_now()
        out["marginal_hwm_before_mesh_reset"] = vm_hwm()  # the mesh build's own peak (since the warm-up's reset)
        hwm_reset = reset_peak()  # the precompute's own peak from here (the mesh build's temporaries are not its)
        t0 = time.perf_counter()  # the stage's time is the precompute and its save (the mesh: its own column)
        c0 = time.process_time()
        anon0 = AnonSampler.now()
        with AnonSampler() as anon:
            tr = get_kind(stage).precompute(mesh, dict(params), run=run)
            out["compute_seconds"] = time.perf_counter() - t0
            out["compute_cpu_seconds"] = time.process_time() - c0
            ts = time.perf_counter()
            tr.save(p[stage], overwrite=True)
            out["save_seconds"] = time.perf_counter() - ts
        out["anon_peak_growth"] = anon.peak - anon0  # held memory the precompute + save added (file pages excluded)
        out["vertices"] = mesh.num_vertices
        out["peak_after_mesh"] = vm_hwm() if hwm_reset else None  # bytes: the process's peak since the reset
        out["result_file_backed"] = "scratch" in _mapping_of(tr.data)
        out["rays"] = int(tr.meta.get("rays_traced", 0))
        out["data_bytes"] = tr.data.numel() * tr.data.element_size()
        del tr
        # what --dry-run says of the time (its probe: two chunks of the real run, scaled), after the measured run
        # (its allocations must not count in the peak above); compared with the measured compute + save
        te = time.perf_counter()
        est_t = estimate(get_kind(stage), mesh, dict(params), RunOptions(workers=1, state_dir=state), probe=True,
                         mesh_seconds=0.0)  # the run's plan, as prt precompute's (its state directory: a result streamed as it was)
        out["estimated_seconds"] = est_t.seconds
        out["estimate_wall_seconds"] = time.perf_counter() - te
        out["marginal_peak_mesh"] = out.get("marginal_hwm_before_mesh_reset")
    elif stage == "cpca":
        tr = Transfer.load(p["diffuse"])
        codec = codecs.get("cpca", clusters=16, vectors=4)
        tf = time.perf_counter()
        enc = codec.fit_encode(tr.signal())
        out["fit_seconds"] = time.perf_counter() - tf
        out["se"] = codec.fit_info_["se"]
        codec.save(p["cpca"], enc, overwrite=True, extra_meta={"transfer": str(p["diffuse"])})
        out["estimated_seconds"] = _compress_estimate(p["diffuse"], codec, stream=False)
        out["vertices"] = tr.num_vertices
        out["data_bytes"] = tr.data.numel() * 4
        out["file_bytes"] = p["diffuse"].stat().st_size
    elif stage == "cpca_stream":
        from prt_torch import io

        meta = io.describe(p["diffuse"])
        V = meta["tensors"]["data"]["shape"][0]
        X = io.load_mmap(p["diffuse"], "data").reshape(V, -1)  # a read-only memory map: streamed by the codec
        codec = codecs.get("cpca", clusters=16, vectors=4)
        tf = time.perf_counter()
        enc = codec.fit_encode(X)
        out["fit_seconds"] = time.perf_counter() - tf
        out["se"] = codec.fit_info_["se"]
        codec.save(work / f"diffuse_{size}.cpca_stream.prt", enc, overwrite=True, extra_meta={"transfer": str(p["diffuse"])})
        out["estimated_seconds"] = _compress_estimate(p["diffuse"], codec, stream=True)
        out["vertices"] = V
        out["data_bytes"] = X.size * 4
    elif stage == "relight":
        from prt_torch import relight
        from prt_torch.lighting import load_light

        codec, enc = type(codecs.get("cpca")).load(p["cpca"])
        tr = Transfer.load(p["diffuse"])
        bands = int(round(tr.data.shape[-1] ** 0.5))
        L = load_light("sky", bands=bands).to(torch.float32)  # [C, n²]
        light = L.T.contiguous()  # [n², C]
        times, ref_times = [], []
        res = codec.relight(enc, light)  # warm-up (plans, kernels)
        relight.diffuse_transfer(tr, L)
        for _ in range(5):
            t = time.perf_counter()
            res = codec.relight(enc, light, out=res)
            times.append(time.perf_counter() - t)
            t = time.perf_counter()
            relight.diffuse_transfer(tr, L)
            ref_times.append(time.perf_counter() - t)
        from prt_torch.harness.timing import io_bound_fn

        nb = codec.relight_bytes(enc)  # the codes read once, the output written once
        bound_fn = io_bound_fn(nb, res.numel() * res.element_size())
        bound = []
        for _ in range(5):
            t = time.perf_counter()
            bound_fn()
            bound.append(time.perf_counter() - t)
        bound.sort()
        times.sort()
        ref_times.sort()
        out["bound_seconds"] = bound[2]
        out["relight_seconds"] = times[2]
        out["uncompressed_seconds"] = ref_times[2]
        out["vertices"] = tr.num_vertices
        # prt relight of the uncompressed transfer file: --dry-run's estimate, then the streamed run (mapped
        # transfer, chunks into the .npy), its time and its RSS growth (the whole [V, 3] is 12 B / vertex)
        import argparse

        from prt_torch.cli import relight as rl

        del tr
        ns = argparse.Namespace(transfer=str(p["diffuse"]), source=None, output=str(work / f"r_{size}.npy"), light="sky",
                                view=None, memory_limit=None)
        tl = time.perf_counter()
        mapped = Transfer.load(p["diffuse"], mmap=True)  # what prt relight --dry-run loads (and times) first
        out["relight_cli_estimated_seconds"], _ = rl.calibrate(ns, mapped, None, None, time.perf_counter() - tl)
        out["relight_cli_plan_peak"] = rl.plan(ns)["peak"]
        r0, h0 = rss_now(), (reset_peak() and vm_hwm())
        t = time.perf_counter()
        from prt_torch import io as pio

        mapped = Transfer.load(p["diffuse"], mmap=True)
        with pio.streamed_npy(work / f"r_{size}.npy", (mapped.num_vertices, 3), overwrite=True) as arr:
            rl.radiance(mapped, "sky", out=torch.from_numpy(arr))
        out["relight_cli_seconds"] = time.perf_counter() - t
        out["relight_cli_peak_growth"] = (vm_hwm() - r0) if h0 else None
    elif stage == "bench":
        cfg = work / f"bench_{size}.yaml"
        cfg.write_text(
            f"name: scale_{size}\nseed: 0\nscene: {{name: bumpy_sphere, size: {size}}}\n"
            f"transfer: {{type: diffuse, bands: {args.bands}, samples: {args.samples}, shadows: always}}\n"
            "lights: [sky]\nviews: {count: 1}\n"
            "metrics: {random_lights: 4, repeats: 3, warmup: 1, cold_pairs: 0}\n"
            "codecs:\n  - {type: cpca, clusters: 16, vectors: 4}\n"
            "render: {enabled: false}\nvalidation: {enabled: false}\n"
            f"cache_dir: {work / 'bench_cache'}\noutput_dir: {work / 'bench_reports'}\n")
        prt = Path(sys.executable).with_name("prt")
        r = subprocess.run([str(prt), "bench", str(cfg)], capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"prt bench failed ({r.returncode}): {r.stderr[-2000:]}")
        out["vertices"] = json.loads((work / "bench_reports" / f"scale_{size}" / "results.json").read_text())["scene"]["vertices"]
        out["marginal_reset"] = False  # prt bench runs in a process of its own: no marginal figure
    out["seconds"] = time.perf_counter() - t0
    out["cpu_seconds"] = time.process_time() - c0
    out["peak_rss"], out["children_peak_rss"] = peak_rss()
    if out["marginal_reset"]:
        hwm = max(vm_hwm(), out.get("marginal_hwm_before_mesh_reset") or 0)
        out["marginal_bytes"] = max(0, hwm - out["rss_at_reset"])
    return out


def _mapping_of(t) -> str:
    """The /proc/self/maps line holding tensor ``t``'s memory ('' when anonymous or not found)."""
    ptr = t.untyped_storage().data_ptr()
    with open("/proc/self/maps") as f:
        for line in f:
            lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
            if lo <= ptr < hi:
                return line.strip()
    return ""


def _compress_estimate(path: Path, codec, stream: bool) -> float:
    """What ``prt compress --dry-run`` says of the fit + encode time (``cli.compress.calibrate``)."""
    import argparse

    from prt_torch import io
    from prt_torch.cli import compress as cc

    V = io.describe(path)["tensors"]["data"]["shape"][0]
    sec, _ = cc.calibrate(argparse.Namespace(transfer=str(path)), codec, V, stream or V * 16 * 4 > 256 * 2**20)
    return sec


def warm_up(stage: str, args, work: Path) -> None:
    """The stage once on a tiny input, in this process, before the measured run: imports,
    compiled kernels, thread pools and first-use allocations are then not the stage's."""
    import torch

    from prt_torch import codecs
    from prt_torch.scene import load_scene
    from prt_torch.transfer import RunOptions, get_kind

    if stage in ("diffuse", "mrt"):
        params = ({"bands": args.bands, "samples": args.samples, "shadows": "always"} if stage == "diffuse" else
                  {"bands": args.mrt_bands, "M": args.mrt_tents, "samples": args.mrt_samples, "shadows": "always",
                   "brdf": {"type": "phong", "s": 12.0}})
        get_kind(stage).precompute(load_scene("bumpy_sphere:642"), dict(params), run=RunOptions(workers=1))
    elif stage in ("cpca", "cpca_stream", "relight"):
        D = args.bands * args.bands
        X = torch.randn(2048, D, generator=torch.Generator().manual_seed(0))
        codec = codecs.get("cpca", clusters=16, vectors=4)
        enc = codec.fit_encode(X)
        if stage == "relight":
            from prt_torch.lighting import load_light

            codec.relight(enc, load_light("sky", bands=args.bands).to(torch.float32).T.contiguous())


# ----------------------------------------------------------------------------------------------
# the parent: every stage at every size, each in a fresh child
# ----------------------------------------------------------------------------------------------

def run_stage(stage: str, size: int, args, work: Path) -> dict:
    cmd = [sys.executable, __file__, "--child", stage, "--size", str(size), "--work", str(work),
           "--bands", str(args.bands), "--samples", str(args.samples), "--mrt-bands", str(args.mrt_bands),
           "--mrt-tents", str(args.mrt_tents), "--mrt-samples", str(args.mrt_samples)] + (["--no-warm"] if args.no_warm else [])
    load0 = os.getloadavg()[0]
    t = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t
    if r.returncode != 0:
        return {"stage": stage, "size": size, "error": r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"rc {r.returncode}"}
    row = json.loads(r.stdout.strip().splitlines()[-1])
    row["wall_seconds"] = wall
    row["load_average"] = [load0, os.getloadavg()[0]]
    # the stage's own peak: the child's (bench: its `prt bench` child's; precompute: the larger of
    # the child and any Embree worker, which are separate processes)
    row["stage_peak_rss"] = max(row["peak_rss"], row["children_peak_rss"])
    base = row["rss_after_imports"]
    row["stage_added_rss"] = max(0, row["stage_peak_rss"] - base)
    V = row["vertices"]
    key = {"relight": "relight_seconds", "embree": "bare_seconds_per_ray"}.get(stage, "seconds")
    row["seconds_per_vertex"] = row[key] / V if stage != "embree" else row[key] * ((args.samples + 1) // 2)
    row["added_bytes_per_vertex"] = row["stage_added_rss"] / V
    row["seconds_measured"] = row[key]
    print(f"  {stage:8s} V={V:>8d}  {row[key]:8.3f} s  {row['seconds_per_vertex'] * 1e6:8.3f} µs/vertex  "
          f"peak {row['stage_peak_rss'] / 2**20:8.0f} MiB  added {row['added_bytes_per_vertex']:8.0f} B/vertex  "
          f"load {load0:.1f}", flush=True)
    return row


def report(rows: list[dict], args, info: dict) -> str:
    L = ["# Cost against mesh size: 10k -> 100k -> 1M vertices (issue 42, part 3)", "",
         f"`{info['command']}` on {info['cpu']} ({info['cores']} cores), torch {info['torch']}; "
         f"load average {info['load_start']:.1f} at the start, {info['load_end']:.1f} at the end "
         "(the machine was shared with other jobs: the seconds are not a quiet-machine speed figure, "
         "their ratios across sizes are only as steady as the load; the memory figures do not depend on it).", "",
         f"Scene `bumpy_sphere:<vertices>`. Diffuse: {args.bands} bands, {args.samples} samples (qmc + auto, "
         f"{(args.samples + 1) // 2} rays per vertex), shadows traced, no bounces. MRT: {args.mrt_bands} bands, "
         f"M = {args.mrt_tents}, Phong s = 12, {args.mrt_samples} samples (low bands and samples so that 1M fits "
         "on a machine shared by six; the per-vertex figures, not the totals, are the point). CPCA: 16 clusters × 4 "
         "vectors of the diffuse transfer. Relight: the CPCA file under `sky`, median of 5. `prt bench`: the whole "
         "command (diffuse precompute into an empty cache, CPCA 16×4, one light, one view, no renders). One "
         "ray-casting worker everywhere; each stage in a fresh child process.", "",
         "Peak = the stage process's `ru_maxrss` (or its children's, whichever is larger); added = peak minus "
         "the child's RSS after its imports, i.e. what the stage itself holds (mesh, inputs, work, result). "
         "Ratio = this size's per-vertex figure over the smallest size's (goal ≤ 1.5).", "",
         "The fixed costs (imports' page cache, compiled kernels, `prt bench`'s timing repeats) flatter the "
         "per-vertex figures of large meshes, so the marginal figures are given too: the growth from the previous "
         "size divided by the vertices added (Δ; a stage that holds something twice or grows super-linearly shows "
         "there).", "",
         "| stage | vertices | seconds | µs / vertex | × smallest | Δ µs / vertex | peak RSS (MiB) | added B / vertex "
         "| × smallest | Δ B / vertex | load |",
         "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    first: dict[str, dict] = {}
    prev: dict[str, dict] = {}
    for r in rows:
        if "error" in r:
            L.append(f"| {r['stage']} | {r['size']} | failed: {r['error']} | | | | | | | | |")
            continue
        f0 = first.setdefault(r["stage"], r)
        p0 = prev.get(r["stage"])
        prev[r["stage"]] = r
        key = {"relight": "relight_seconds", "embree": "bare_seconds_per_ray"}.get(r["stage"], "seconds")
        ts = r["seconds_per_vertex"] / f0["seconds_per_vertex"]
        ms = r["added_bytes_per_vertex"] / f0["added_bytes_per_vertex"] if f0["added_bytes_per_vertex"] > 0 else None
        dv = None if p0 is None else r["vertices"] - p0["vertices"]
        dt = "" if not dv else f"{(r[key] - p0[key]) / dv * 1e6:.3g}"
        dm = "" if not dv else f"{(r['stage_added_rss'] - p0['stage_added_rss']) / dv:.0f}"
        if r["stage"] == "embree":
            dt = ""  # a per-ray figure, not a total
        L.append(f"| {r['stage']} | {r['vertices']} | {r[key]:.3g} | {r['seconds_per_vertex'] * 1e6:.3g} | {ts:.2f} | {dt} | "
                 f"{r['stage_peak_rss'] / 2**20:.0f} | {r['added_bytes_per_vertex']:.0f} | "
                 f"{'–' if ms is None else f'{ms:.2f}'} | {dm} | "
                 f"{r['load_average'][0]:.1f}–{r['load_average'][1]:.1f} |")
    marg = [r for r in rows if r.get("marginal_bytes") is not None and "error" not in r]
    if marg:
        L += ["", "**Marginal memory** (each child ran its stage once on a tiny input first, then reset its peak; "
              "marginal = the peak since the reset less the RSS at the reset: the stage's own arrays — mesh, input, "
              "work, result — without imports, compiled kernels, thread pools or first-use allocations). `cpca_stream` "
              "maps the transfer file: the pages it has read count in its RSS (file-backed, reclaimable), so its "
              "figure includes the signal once. Worker = the Embree worker process's own peak RSS (its imports "
              "included).", "",
              "| stage | vertices | marginal MiB | marginal B / vertex | × smallest | worker peak MiB |", "|---|---:|---:|---:|---:|---:|"]
        m0: dict[str, float] = {}
        for r in marg:
            b = r["marginal_bytes"] / r["vertices"]
            f = m0.setdefault(r["stage"], b)
            wk = r["children_peak_rss"] / 2**20 if r["stage"] in ("diffuse", "mrt", "embree") else None
            L.append(f"| {r['stage']} | {r['vertices']} | {r['marginal_bytes'] / 2**20:.1f} | {b:.0f} | "
                     f"{b / f if f > 0 else float('nan'):.2f} | {'' if wk is None else f'{wk:.0f}'} |")
    est = [r for r in marg if r["stage"] in ("cpca", "cpca_stream")]
    if est:
        from prt_torch.codecs.chunks import fit_memory

        L += ["", "The CPCA stages' memory as `prt compress --dry-run` states it before the fit (`codecs.chunks.fit_memory`: "
              "signal, copies, chunk work, bookkeeping, codes, × the allocator slack 1.5, + fixed GEMM blocks) "
              "against the measured marginal. The stage also holds what "
              "its input takes besides the codec: `cpca` loads the whole transfer file (mesh included: the file's size "
              "less the signal is added), `cpca_stream` maps it (the signal's pages, counted in its RSS, are added):", "",
              "| stage | vertices | fit estimate MiB | + input MiB | estimate / measured |", "|---|---:|---:|---:|---:|"]
        D = args.bands * args.bands
        for r in est:
            V = r["vertices"]
            m = fit_memory(V, D, 16, 4, streamed=r["stage"] == "cpca_stream")
            extra = (r.get("file_bytes", 0) - V * D * 4) if r["stage"] == "cpca" else V * D * 4
            L.append(f"| {r['stage']} | {V} | {m['peak'] / 2**20:.1f} | {extra / 2**20:.1f} | "
                     f"{(m['peak'] + extra) / r['marginal_bytes']:.2f} |")
    cs = {(r["stage"], r["size"]): r for r in rows if r.get("stage") in ("cpca", "cpca_stream") and "error" not in r}
    pairs = [(cs[("cpca", n)], cs[("cpca_stream", n)]) for (st, n) in cs if st == "cpca" and ("cpca_stream", n) in cs]
    if pairs:
        L += ["", "CPCA in memory (the transfer loaded) against streamed from the memory-mapped file (`codecs.chunks`, "
              "16 MiB chunks), same seed:", "",
              "| vertices | in-memory s | streamed s | SE in-memory | SE streamed | SE streamed / in-memory |",
              "|---:|---:|---:|---:|---:|---:|"]
        for a, b in pairs:
            L.append(f"| {a['vertices']} | {a['seconds']:.3g} | {b['seconds']:.3g} | {a.get('se', float('nan')):.6g} | "
                     f"{b.get('se', float('nan')):.6g} | {b.get('se', float('nan')) / a.get('se', float('nan')):.6f} |")
    rel = [r for r in rows if r.get("stage") == "relight" and "error" not in r]
    if rel:
        L += ["", "Relight beside its own bound (a copy of the bytes it must read once — the codes — and write once — "
              "the output —, timed in the same child: `harness.timing.io_bound_fn`) and beside the uncompressed diffuse "
              "relighting of the same transfer:", "",
              "| vertices | CPCA s | bound s | bound / CPCA | uncompressed s | uncompressed / CPCA |", "|---:|---:|---:|---:|---:|---:|"]
        for r in rel:
            L.append(f"| {r['vertices']} | {r['relight_seconds']:.3g} | {r['bound_seconds']:.3g} | "
                     f"{r['bound_seconds'] / r['relight_seconds']:.2f} | {r['uncompressed_seconds']:.3g} | "
                     f"{r['uncompressed_seconds'] / r['relight_seconds']:.2f} |")
    emb = {r["size"]: r for r in rows if r.get("stage") == "embree" and "error" not in r}
    dif = [r for r in rows if r.get("stage") == "diffuse" and "error" not in r and r["size"] in emb]
    if dif:
        L += ["", "The diffuse precompute's compute time against bare Embree's for its rays (the `embree` rows: "
              f"{(args.samples + 1) // 2} occlusion rays from each of a contiguous block of up to 32768 vertices of the same "
              "mesh, float32, one thread, no offsets or SH: the peer measured in the same run). A ray's cost grows with "
              "the scene's BVH (2M triangles at 1M vertices no longer fit any cache), so the per-vertex time of a "
              "precompute can grow even where everything around the rays is linear:", "",
              "| vertices | bare Embree ns / ray | × smallest | precompute compute s | rays × bare s | bare / precompute |",
              "|---:|---:|---:|---:|---:|---:|"]
        e0 = emb[dif[0]["size"]]["bare_seconds_per_ray"]
        for r in dif:
            b = emb[r["size"]]["bare_seconds_per_ray"]
            L.append(f"| {r['vertices']} | {b * 1e9:.0f} | {b / e0:.2f} | {r['compute_seconds']:.3g} | {r['rays'] * b:.3g} | "
                     f"{r['rays'] * b / r['compute_seconds']:.2f} |")
    est = [r for r in rows if r.get("stage") in ("diffuse", "mrt") and r.get("peak_after_mesh")]
    if est:
        L += ["", "The `--dry-run` estimate (`transfer.estimate`, without its probe) against the measured peak, both "
              "from the built mesh on (the child's peak RSS reset after the build: `/proc/self/clear_refs`, `VmHWM`; "
              "measured = that peak less the RSS before the mesh was built, i.e. mesh + precompute + save):", "",
              "| stage | vertices | estimated peak (MiB) | measured peak (MiB) | estimate / measured |", "|---|---:|---:|---:|---:|"]
        for r in est:
            meas = r["peak_after_mesh"] - r["rss_now_after_imports"]
            L.append(f"| {r['stage']} | {r['vertices']} | {r['estimated_peak_bytes'] / 2**20:.0f} | {meas / 2**20:.0f} | "
                     f"{r['estimated_peak_bytes'] / meas:.2f} |")
    pre = [r for r in rows if r.get("stage") in ("diffuse", "mrt") and "error" not in r]
    if pre:
        L += ["", "Precompute parts (seconds): mesh build, compute (chunks streamed to the state directory), save; "
              "rays traced; result bytes per vertex:", "",
              "| stage | vertices | mesh | compute | save | rays | result B / vertex |", "|---|---:|---:|---:|---:|---:|---:|"]
        for r in pre:
            L.append(f"| {r['stage']} | {r['vertices']} | {r['mesh_seconds']:.2f} | {r['compute_seconds']:.2f} | "
                     f"{r['save_seconds']:.2f} | {r['rays']} | {r['data_bytes'] / r['vertices']:.0f} |")
    cpu = [r for r in rows if "error" not in r and r.get("stage") in ("diffuse", "mrt", "cpca", "cpca_stream", "embree")
           and (r.get("compute_cpu_seconds") or r.get("cpu_seconds") or r.get("bare_cpu_seconds_per_ray"))]
    if cpu:
        L += ["", "**CPU time** (`time.process_time` of the stage's process, every thread: what other users' jobs on the "
              "shared cores move least — a process waiting for a core accrues none; the wall seconds above include that "
              "wait). Precompute: the compute alone; embree: per ray × rays per vertex; cpca: fit + encode + save:", "",
              "| stage | vertices | CPU s | CPU µs / vertex | × smallest |", "|---|---:|---:|---:|---:|"]
        c0: dict[str, float] = {}
        rpv = (args.samples + 1) // 2
        for r in cpu:
            if r["stage"] == "embree":
                if r.get("bare_cpu_seconds_per_ray") is None:
                    continue
                tot, per = r["bare_cpu_seconds_per_ray"] * r["bare_rays"], r["bare_cpu_seconds_per_ray"] * rpv
            else:
                tot = r.get("compute_cpu_seconds", r.get("cpu_seconds"))
                per = tot / r["vertices"]
            f0 = c0.setdefault(r["stage"], per)
            L.append(f"| {r['stage']} | {r['vertices']} | {tot:.3g} | {per * 1e6:.3g} | {per / f0:.2f} |")
    anon = [r for r in rows if "error" not in r and r.get("anon_peak_growth") is not None]
    if anon:
        L += ["", "Held memory of the precompute and its save (the peak of `RssAnon`, sampled every 20 ms, less its value "
              "before: heap and anonymous maps, not file pages). A result over `transfer.base.STREAM_RESULT_BYTES` (256 MiB) "
              "is assembled in a file beside the state directory (`RunOptions.stream_result`): its pages count in the RSS "
              "above but not here (the kernel writes them back and drops them under pressure):", "",
              "| stage | vertices | result MiB | result in a file | held peak growth MiB | B / vertex | × smallest |",
              "|---|---:|---:|:---:|---:|---:|---:|"]
        a0: dict[str, float] = {}
        for r in anon:
            b = r["anon_peak_growth"] / r["vertices"]
            f0 = a0.setdefault(r["stage"], b)
            L.append(f"| {r['stage']} | {r['vertices']} | {r['data_bytes'] / 2**20:.0f} | "
                     f"{'yes' if r.get('result_file_backed') else 'no'} | {r['anon_peak_growth'] / 2**20:.0f} | {b:.0f} | "
                     f"{b / f0 if f0 > 0 else float('nan'):.2f} |")
    tim = [r for r in rows if "error" not in r and (r.get("estimated_seconds") is not None
                                                    or r.get("relight_cli_estimated_seconds") is not None)]
    if tim:
        L += ["", "**Time estimates against the measured run** (what each `--dry-run` says before it starts, measured in "
              "the same child right after the real run — not a timed assertion, a check of the estimate): precompute = "
              "`transfer.estimate`'s probe (set-up + the mean of its 2nd and 3rd chunks × V / chunk, `probe_chunk`) against the compute + "
              "save; cpca / cpca_stream = `prt compress --dry-run`'s calibration (a fit of up to 16384 evenly spaced rows, "
              "scaled by V / rows) against the fit + encode; relight = `prt relight --dry-run`'s calibration (loading + set-up + "
              "the first 32768-vertex chunk × chunks) against the streamed relight of the uncompressed diffuse file into a .npy:", "",
              "| stage | vertices | estimated s | measured s | estimate / measured |", "|---|---:|---:|---:|---:|"]
        for r in tim:
            if r["stage"] in ("diffuse", "mrt") and r.get("estimated_seconds") is not None:
                m = r["compute_seconds"] + r["save_seconds"]
                L.append(f"| {r['stage']} | {r['vertices']} | {r['estimated_seconds']:.3g} | {m:.3g} | {r['estimated_seconds'] / m:.2f} |")
            elif r["stage"] in ("cpca", "cpca_stream") and r.get("estimated_seconds") is not None:
                L.append(f"| {r['stage']} | {r['vertices']} | {r['estimated_seconds']:.3g} | {r['fit_seconds']:.3g} | "
                         f"{r['estimated_seconds'] / r['fit_seconds']:.2f} |")
            elif r["stage"] == "relight" and r.get("relight_cli_estimated_seconds") is not None:
                L.append(f"| relight (prt relight, streamed .npy) | {r['vertices']} | {r['relight_cli_estimated_seconds']:.3g} | "
                         f"{r['relight_cli_seconds']:.3g} | {r['relight_cli_estimated_seconds'] / r['relight_cli_seconds']:.2f} |")
        rl = [r for r in tim if r["stage"] == "relight" and r.get("relight_cli_peak_growth") is not None]
        if rl:
            L += ["", "`prt relight`'s streamed run: its peak RSS growth (mapped transfer pages included: they are file pages) "
                  "against the [V, 3] float32 output it never holds, and `--dry-run`'s peak:", "",
                  "| vertices | output MiB | peak growth MiB | dry-run peak MiB |", "|---:|---:|---:|---:|"]
            for r in rl:
                L.append(f"| {r['vertices']} | {r['vertices'] * 12 / 2**20:.1f} | {r['relight_cli_peak_growth'] / 2**20:.1f} | "
                         f"{r['relight_cli_plan_peak'] / 2**20:.1f} |")
    return "\n".join(L) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--stages", nargs="+", choices=STAGES, default=list(STAGES))
    ap.add_argument("--bands", type=int, default=4)
    ap.add_argument("--samples", type=int, default=64)
    ap.add_argument("--mrt-bands", type=int, default=3)
    ap.add_argument("--mrt-tents", type=int, default=4)
    ap.add_argument("--mrt-samples", type=int, default=32)
    ap.add_argument("--work", default=None, help="directory for the transfers (default: a temporary one, removed)")
    ap.add_argument("--quick", action="store_true", help="2k and 10k vertices, 16 samples: a CI-sized smoke")
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "scale.md"))
    ap.add_argument("--from-json", default=None, help="rewrite --out from an earlier run's .json (no measuring)")
    ap.add_argument("--no-warm", action="store_true", help="no warm-up run before the measured one (the marginal column is then empty)")
    ap.add_argument("--child", choices=STAGES, help=argparse.SUPPRESS)
    ap.add_argument("--size", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args)))
        return 0
    if args.from_json:
        from prt_torch import io

        saved = json.loads(Path(args.from_json).read_text())
        for k, v in saved["args"].items():
            if k not in ("out", "from_json"):
                setattr(args, k, v)
        with io.atomic_path(Path(args.out), overwrite=True) as t:
            Path(t).write_text(report(saved["rows"], args, saved["machine"]))
        print(f"wrote {args.out}")
        return 0
    if args.quick:
        args.sizes, args.samples, args.mrt_samples = [2_000, 10_000], 16, 16
    from prt_torch.harness.timing import machine_info

    info = machine_info()
    info["command"] = "python benchmarks/bench_scale.py " + " ".join(argv if argv is not None else sys.argv[1:])
    info["load_start"] = os.getloadavg()[0]
    tmp = None
    if args.work is None:
        tmp = tempfile.TemporaryDirectory(prefix="bench_scale_")
        work = Path(tmp.name)
    else:
        work = Path(args.work)
        work.mkdir(parents=True, exist_ok=True)
    rows = []
    try:
        for size in args.sizes:
            for stage in args.stages:
                rows.append(run_stage(stage, size, args, work))
    finally:
        if tmp is not None:
            tmp.cleanup()
    info["load_end"] = os.getloadavg()[0]
    from prt_torch import io

    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with io.atomic_path(out, overwrite=True) as t:
        Path(t).write_text(report(rows, args, info))
    io.atomic_write_json(out.with_suffix(".json"), {"machine": info, "args": vars(args), "rows": rows})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
