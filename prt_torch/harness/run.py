"""The benchmark run: scene -> transfer (cached) -> every codec setting -> records -> report.

``run_benchmark(cfg)`` (what ``prt bench`` calls):

1. loads the scene and estimates memory (transfer + codec workspace) — refused before any
   work when over ``metrics.max_memory_gb``;
2. computes the transfer once and caches it in ``cache_dir/transfer-<hash>.prt`` keyed by the
   scene, its mesh content hash and the transfer parameters, so sweeps and re-runs reuse it;
3. loads the lights (built-in names, files, analytic specs) and places the views;
4. for every codec setting (grids expanded), fits and encodes, then measures: encode time;
   bytes (total, per vertex), compression ratio and Sloan's cost; SE and relative error;
   random-lighting PSNR (MRT eq. 11, Monte Carlo and closed form); PSNR against the
   uncompressed result for every light × view; relighting throughput (vertices/s, fps) as
   the median of repeats after warm-up with its spread, next to the uncompressed peer
   measured in the same run;
5. writes each finished setting's record to ``records/<id>.json`` and its fitted codec and
   encoding to ``records/<id>.prt`` at once (atomic), so an interrupted sweep keeps what it
   finished and a re-run skips it;
6. optional target search (smallest size parameter meeting a PSNR target);
7. renders the uncompressed result and the best setting of each codec from the encodings it
   has (harness.renders), then hands the results (a plain JSON-able dict) and the image paths
   to harness.report, which writes results.json/csv, report.md and the plots.

Layers flow one way: run → renders, run → report; report never fits, relights or renders.
"""
from __future__ import annotations

import copy
import dataclasses
import json
import math
import time
from pathlib import Path
from typing import Any, Callable

import torch

from .. import codecs, io
from ..executor import Executor, LocalExecutor, TaskFailure
from ..transfer import Transfer
from .config import config_hash, expand_codecs, part_configs
from .convex import run_convex
from .evaluate import Evaluator
from .metrics import psnr_vs_reference, random_light_psnr, random_light_psnr_analytic, squared_error
from .renders import render_best, render_convex
from .report import load_results, write_outputs
from .target import find_smallest, search_families
from .timing import (io_bound_fn, machine_info, measure, measure_paired, measure_paired_cold, rate_policy,
                     release_eviction_buffer, torch_threads, working_set)

__all__ = ["run_benchmark", "compute_transfer", "evaluate_setting", "convex_results", "RESULTS_VERSION"]

RESULTS_VERSION = 1
#: short interleaved sample pairs behind each speed-up and bound fraction (timing.measure_paired:
#: the ratio of the fastest tenth of each side, robust to other processes taking the cores; the one-thread
#: speed-up's samples are timed in the thread's CPU time)
FLOOR_PAIRS = 40
#: the speed-up column's floor phase adds batches of FLOOR_PAIRS pairs, up to this many, while its even and odd
#: pairs' estimates differ by more than 10% (a busy machine: reports/benchmarks/timing_trust.md)
FLOOR_MAX_PAIRS = 160


# --------------------------------------------------------------------------- transfer

def transfer_params(cfg: dict) -> dict:
    """The precompute parameters of ``cfg['transfer']`` (everything but ``type``, and ``energy`` where no
    ``'auto'`` choice keeps it); the run's ``seed`` unless the transfer sets its own."""
    from ..transfer import get_kind

    from ..transfer.auto import energy_choices

    t = cfg["transfer"]
    p = {k: v for k, v in t.items() if k != "type"}
    if "energy" in p and not energy_choices(t["type"], p):  # one point of a sweep where no 'auto' keeps it (the config
        del p["energy"]  # is refused where none does): the same transfer, the same cache entry
    if "seed" in get_kind(t["type"]).constraints:
        p.setdefault("seed", cfg["seed"])
    return p


def transport_res(cfg: dict) -> int:
    """The cube face resolution of ``cfg``'s transport tables: its ``res``, or the one ``res: auto``
    (the default) chooses from its BRDF (``transfer.transport.choose_cube_res``)."""
    from ..transfer import get_kind

    return int(get_kind("transport").resolve(transfer_params(cfg))[0]["res"])


def signal_shape(cfg: dict) -> tuple[int, tuple[int, int]] | None:
    """``(D, matrix_shape)`` of the codec signal ``cfg``'s transfer will give, where the config fixes
    it (glossy and MRT with integer bands, tents; transport tables), else None (diffuse: grey or
    RGB rows depend on the albedo; ``auto`` sizes depend on the data)."""
    from ..transfer import get_kind

    t = cfg["transfer"]
    p = {**get_kind(t["type"]).defaults(), **transfer_params(cfg)}
    if any(p.get(k) == "auto" for k in ("bands", "bands_out", "M")):
        return None
    n2 = int(p.get("bands", 1)) ** 2
    if t["type"] == "glossy":
        ms = (int(p["bands_out"] or p["bands"]) ** 2, n2)
    elif t["type"] == "mrt":
        ms = (int(p["M"]) ** 2, n2)
    elif t["type"] == "transport":
        v = p["views"]
        ms = (10 * int(v) ** 2 + 2 if isinstance(v, int) else len(v), 6 * transport_res(cfg) ** 2)
    else:
        return None
    return ms[0] * ms[1], ms


def check_settings(cfg: dict, num_vertices: int) -> None:
    """Refuse, before any work, a codec setting that the data's shape will refuse at its fit:
    clusters beyond the vertices, vectors beyond the signal's dimension where the config fixes it
    (:func:`signal_shape`). What ``--dry-run`` and the real run both check before the precompute."""
    shape = signal_shape(cfg)
    for s in expand_codecs(cfg["codecs"]):
        params = {k: v for k, v in s.items() if k != "type"}
        c = codecs.get(s["type"], **params)
        try:
            if shape is None:
                c.check_data_shape(num_vertices)
            else:
                c.check_data_shape(num_vertices, shape[0], shape[1])
        except ValueError as e:
            raise ValueError(f"codec setting {setting_id(s)} on {num_vertices} vertices"
                             + (f" of dimension {shape[0]} ({shape[1][0]}x{shape[1][1]} matrices)" if shape else "")
                             + f": {e}") from None


def estimate_memory(cfg: dict, num_vertices: int) -> dict:
    """Rough peak bytes: the transfer signal (float32) a few times over (signal, decoded copy,
    float64 error pass) plus the largest codec workspace (per-cluster covariances in float64)."""
    from ..transfer import get_kind

    t = cfg["transfer"]
    p = {**get_kind(t["type"]).defaults(), **transfer_params(cfg)}
    for k, worst in (("bands", 16), ("bands_out", 16), ("M", 24)):  # 'auto': bound by the largest choice
        if p.get(k) == "auto":
            p[k] = worst if t["type"] != "diffuse" else 32
    n2 = p.get("bands", 1) ** 2
    if t["type"] in ("diffuse", "subsurface"):  # subsurface: a diffuse transfer [V, 3, n²]
        D = n2 * 3
    elif t["type"] == "glossy":
        D = int(p["bands_out"] or p["bands"]) ** 2 * n2
    elif t["type"] == "transport":
        v = p["views"]
        D = (10 * int(v) ** 2 + 2 if isinstance(v, int) else len(v)) * 6 * transport_res(cfg) ** 2
    elif t["type"] == "wavelet":
        D = 2 * int(p["terms"])  # values and indices, a few times over (the relighter's CSC copy)
    else:
        D = int(p["M"]) ** 2 * n2
    signal = num_vertices * D * 4
    # metrics: the float64 difference of signal and decoded signal (random-light PSNR, SE) and
    # the random lights themselves
    metrics = num_vertices * D * 8 + int(cfg["metrics"]["random_lights"]) * n2 * 8
    work = 0
    for s in expand_codecs(cfg["codecs"]):
        k = int(s.get("clusters", 1) or 1)
        m = min(D, max(1, num_vertices // k))
        work = max(work, k * m * m * 8)
    total = 6 * signal + work + metrics
    return {"signal_bytes": signal, "codec_workspace_bytes": work, "metrics_bytes": metrics, "estimated_peak_bytes": total, "D": D}


def compute_transfer(cfg: dict, mesh, cache_dir: Path, progress: bool = True,
                     executor: Executor | None = None) -> tuple[Transfer, dict]:
    """Transfer for ``cfg`` on ``mesh``, from the cache if it is there. Returns (transfer, info).

    A cache miss precomputes once, its chunks on ``executor`` (None: in this process; a
    ``RayExecutor``: one Ray task per chunk — the same result, bit for bit).
    ``'auto'`` parameters are chosen from the config's lights (projected to 32 bands) and the
    BRDF (``prt_torch.transfer.auto``); the choices are part of the cache key and land in
    ``meta['auto']``."""
    from ..lighting import load_light
    from ..transfer import RunOptions, get_kind

    kind = cfg["transfer"]["type"]
    params = transfer_params(cfg)
    lights = None
    keyed: dict[str, Any] = {"kind": kind, "params": params, "mesh": mesh.content_hash()}
    if "auto" in params.values():
        # wavelet res: auto measures the lights themselves on the cube (not band-limited)
        lights = list(cfg["lights"]) if kind == "wavelet" else [load_light(spec, bands=32) for spec in cfg["lights"]]
        _, decisions = get_kind(kind).resolve(params, lights)
        keyed["auto"] = {k: d["value"] for k, d in decisions.items()}
    key = config_hash(keyed)
    if get_kind(kind).output == "directory":  # streamed tables (transport): a resumable cache directory
        from .evaluate import load_directory_transfer

        path = Path(cache_dir) / f"transfer-{kind}-{key}"
        t0 = time.perf_counter()
        hit = (path / "manifest.json").is_file() and json.loads((path / "manifest.json").read_text()).get("complete")
        if not hit:
            get_kind(kind).precompute(mesh, params, run=RunOptions(progress=progress, resume=path.exists(), executor=executor), out=path)
        tr = load_directory_transfer(path)
        return tr, {"cache": "hit" if hit else "miss", "path": str(path), "seconds": time.perf_counter() - t0, "key": key}
    path = Path(cache_dir) / f"transfer-{kind}-{key}.prt"
    if path.is_file():
        t0 = time.perf_counter()
        tr = Transfer.load(path)
        return tr, {"cache": "hit", "path": str(path), "seconds": time.perf_counter() - t0, "key": key}
    t0 = time.perf_counter()
    tr = get_kind(kind).precompute(mesh, params, run=RunOptions(progress=progress, executor=executor), lights=lights)
    secs = time.perf_counter() - t0
    tr.save(path, overwrite=True)
    return tr, {"cache": "miss", "path": str(path), "seconds": secs, "key": key}


# --------------------------------------------------------------------------- one setting

def setting_id(setting: dict) -> str:
    parts = [setting["type"]] + [f"{k}{v}" for k, v in sorted(setting.items()) if k != "type"]
    return "-".join(str(p).replace("/", "_").replace(" ", "") for p in parts)


def evaluate_setting(ev: Evaluator, setting: dict, lights: list[torch.Tensor], views: list[Any], cfg: dict,
                     ref_cache: dict, timed: bool = True) -> tuple[dict, Any, Any]:
    """Fit, encode and measure one codec setting ``{type: NAME, <param>: value}``.
    Returns (the record, JSON-able; the fitted codec; its encoding).

    ``timed=False``: the error, bytes and PSNR only (what a target search decides on), no
    relighting rate; the record carries ``timed: False`` and its rate fields are absent, so it
    stays out of the PSNR / fps tables (:func:`time_setting` adds them later from the same
    codec and encoding, without a refit)."""
    params = dict(setting)
    name = params.pop("type")
    codec = codecs.get(name, **params)
    X = ev.X
    t0 = time.perf_counter()
    enc = codec.fit_encode(X, matrix_shape=ev.matrix_shape, **ev.fit_kwargs(codec))
    encode_s = time.perf_counter() - t0
    storage = dict(codec.storage(enc))
    X_hat = codec.decode(enc).to(torch.float32)
    se, rel = squared_error(X, X_hat)
    m = cfg["metrics"]
    psnr_rand = random_light_psnr(X, X_hat, ev.n_in, m["random_lights"], seed=cfg["seed"])
    psnr_rand_closed = random_light_psnr_analytic(se, ev.V, ev.n_in)
    per = []
    for li, L in enumerate(lights):
        Lm = ev.codec_light(codec, L)
        for vi, view in enumerate(views):
            ref = ref_cache[(li, vi)]
            out = ev.finish(codec.relight(enc, Lm, view=view))
            per.append({"light": li, "view": vi, "psnr_db": psnr_vs_reference(ref, out)})
    psnrs = [p["psnr_db"] for p in per]
    finite = [p for p in psnrs if math.isfinite(p)]
    mean_psnr = (sum(finite) / len(finite)) if len(finite) == len(psnrs) else float("inf")
    bytes_total = int(storage["bytes_total"])
    rec = {
        "setting_id": setting_id(setting),
        "codec": name,
        "params": params,
        "encode_s": encode_s,
        "bytes_total": bytes_total,
        "bytes_per_vertex": bytes_total / ev.V,
        "compression_ratio": ev.raw_bytes / bytes_total if bytes_total else float("inf"),
        "sloan_cost_floats": storage.get("sloan_cost_floats"),
        "storage": storage,
        "se": se,
        "relative_se": rel,
        "psnr_random_db": psnr_rand,
        "psnr_random_closed_form_db": psnr_rand_closed,
        "psnr_lights_db": mean_psnr,
        "psnr_lights_min_db": min(psnrs),
        "psnr_per_light_view": per,
        "timed": False,
    }
    if timed:
        rec.update(time_setting(ev, codec, enc, lights, views, cfg))
    return rec, codec, enc


def time_setting(ev: Evaluator, codec, enc, lights: list[torch.Tensor], views: list[Any], cfg: dict) -> dict:
    """The relighting-rate fields of a fitted setting's record (``timed: True``, ``relight_s``,
    ``vertices_per_s``, ``fps``, the paired speed-ups and bound fractions, the contention seen;
    docs/harness.md), measured on ``codec``'s encoding ``enc`` relighting the first light and view."""
    m = cfg["metrics"]
    # throughput: relight one light (and view) from the compressed form; median of repeats
    L0 = ev.codec_light(codec, lights[0])
    v0 = views[0]
    # paired with the uncompressed peer, interleaved: the speed-up comes from back-to-back samples.
    # fps: at the process's thread count; the speed-up column: the same pairs in one thread, the
    # ratio of the work itself, which a busy machine or OpenMP's wait policy does not move
    # (timing.torch_threads; the multi-threaded ratio is kept as speedup_parallel), each sample timed
    # in this thread's CPU time, so time other processes held the core is in neither side
    def relit():
        return codec.relight(enc, L0, view=v0)

    def uncompressed():
        return ev.uncompressed(lights[0], v0)

    pt = measure_paired(relit, uncompressed, repeats=m["repeats"], warmup=m["warmup"], floor_pairs=FLOOR_PAIRS)
    # contention that started after import: re-decided here (timing.rate_policy: re-timed, in one thread too)
    tm, policy = rate_policy(relit, pt.test, pt.contention, repeats=m["repeats"], warmup=m["warmup"])
    with torch_threads(1):
        pw = measure_paired(relit, uncompressed, repeats=m["repeats"], warmup=m["warmup"], floor_pairs=FLOOR_PAIRS,
                            floor_max_pairs=FLOOR_MAX_PAIRS, clock=time.thread_time)
    # its own bound: read the encoded data (and the view) once, write the output once (the codec
    # says which bytes: Codec.relight_bytes; the Gaussian codec's taps read only the tapped views)
    read_bytes = codec.relight_bytes(enc, v0)
    out_bytes = ev.V * L0.shape[-1] * 4
    # as a render loop calls it: prepared once (Codec.relighter), into a reused result, as the bound
    # writes into a reused buffer
    buf = torch.empty_like(relit())
    prepared = codec.relighter(enc, v0)

    def relit_into():
        return prepared(L0, out=buf)

    bound = io_bound_fn(read_bytes, out_bytes)
    pb = measure_paired(relit_into, bound, repeats=m["repeats"], warmup=m["warmup"], floor_pairs=FLOOR_PAIRS)
    # the same pair from cold caches (each call alone after evicting them): back to back, both
    # sides' data stay in the L2/L3 at these sizes, so the above is a cache-bandwidth bound
    # (metrics.cold_pairs single-call pairs; 0: not measured). The eviction flushes what the two sides
    # touch — the prepared relighter's encoding, model and plans, the light, the output, the bound's
    # buffers: working_set of what they close over — at a cost in proportion to those bytes, not to
    # the last-level cache (timing.measure_paired_cold)
    pc = (measure_paired_cold(relit_into, bound, repeats=m["cold_pairs"], evict=working_set(relit_into, bound))
          if m.get("cold_pairs", 0) > 0 else None)
    rec = {
        "timed": True,
        "relight_s": tm.median,
        "relight_spread": tm.spread,
        "relight_timing": tm.as_dict(),
        "vertices_per_s": tm.rate(ev.V),
        "fps": 1.0 / tm.median if tm.median > 0 else float("inf"),
        "fraction_of_bound": pb.speedup,  # t_bound / t_relight(out=), paired: 1 = at the bandwidth bound
        "relight_into_s": pb.test.median,  # relight(..., out=reused result), the render-loop form
        "bound_bytes": {"read": read_bytes, "written": out_bytes},
        "speedup_vs_uncompressed": pw.speedup,  # one thread: the work ratio (timing.torch_threads)
        "speedup_threads": 1,
        "speedup_median_pair": pw.ratio.median,
        "speedup_floor": pw.floor,  # its floor phase: pairs, the quantile's per-call CPU times, even/odd halves
        "speedup_spread": pw.ratio.spread,
        "speedup_parallel": pt.speedup,  # the same, at the process's thread count (moves with load)
        "speedup_parallel_spread": pt.ratio.spread,
        "timing_trusted": pt.contention["trusted"] and pw.contention["trusted"],
        "rate_threads": policy["threads"],  # the thread count behind relight_s, vertices_per_s, fps
        "rate_policy": policy,
        "contention": pt.contention,
        "contention_one_thread": pw.contention,
    }
    if pc is not None:  # the same from cold caches: the memory-bandwidth bound proper
        rec["fraction_of_bound_cold"] = pc.speedup
        rec["bound_cold"] = {"relight_s": pc.test.median, "bound_s": pc.peer.median, "q1": pc.ratio.q1, "q3": pc.ratio.q3,
                             "eviction": pc.eviction}
    return rec


class SettingTask:
    """``setting -> (record, codec, encoding)``: :func:`evaluate_setting` with one run's context
    (evaluator, lights, views, config, reference radiance) bound — what :func:`evaluate_run`
    hands its executor (for Ray, pickled once and shared by every setting's task)."""

    def __init__(self, ev: Evaluator, lights: list[torch.Tensor], views: list[Any], cfg: dict, ref_cache: dict,
                 timed: bool = True):
        self.ev, self.lights, self.views, self.cfg, self.ref_cache = ev, lights, views, cfg, ref_cache
        self.timed = timed

    def __call__(self, setting: dict) -> tuple[dict, Any, Any]:
        return evaluate_setting(self.ev, setting, self.lights, self.views, self.cfg, self.ref_cache, timed=self.timed)


# --------------------------------------------------------------------------- the run

def _load_records(rec_dir: Path) -> dict[str, dict]:
    """Finished settings of an earlier run: key -> record, for records whose encoding
    (``<id>.prt``) is there too."""
    out = {}
    if rec_dir.is_dir():
        for p in sorted(rec_dir.glob("*.json")):
            try:
                r = json.loads(p.read_text())
            except (OSError, json.JSONDecodeError):
                continue  # a torn file cannot exist (atomic writes), but never trust the disk
            if "key" in r and p.with_suffix(".prt").is_file():
                out[r["key"]] = r
    return out


def load_mesh_within_budget(cfg: dict):
    """The config's scene, after checking the run's estimated peak memory against
    ``metrics.max_memory_gb`` (refused before any precompute). Returns (mesh, estimate)."""
    from ..scene import load_scene
    from .evaluate import check_codecs_for_kind

    check_codecs_for_kind(cfg["transfer"]["type"], sorted({s["type"] for s in expand_codecs(cfg["codecs"])}))
    sc = cfg["scene"]
    mesh = load_scene(sc["name"], size=sc["size"], up=sc["up"], albedo=sc["albedo"], param="config key 'scene.name' =")
    check_settings(cfg, mesh.num_vertices)  # the data-dependent sizes, before any precompute
    from ..lighting import load_light

    for i, spec in enumerate(cfg["lights"]):  # a light file's contents (not only its name), before any precompute
        try:
            load_light(spec, bands=2)
        except (ValueError, OSError) as e:
            raise ValueError(f"config key 'lights.{i}' = {spec!r}: {e}") from None
    mem = estimate_memory(cfg, mesh.num_vertices)
    if mem["estimated_peak_bytes"] > float(cfg["metrics"]["max_memory_gb"]) * 2**30:
        fb = io.format_bytes
        raise ValueError(
            f"this config needs an estimated {fb(mem['estimated_peak_bytes'])} (signal {fb(mem['signal_bytes'])} for "
            f"{mesh.num_vertices} vertices × D={mem['D']}, codec workspace {fb(mem['codec_workspace_bytes'])}, metrics "
            f"{fb(mem['metrics_bytes'])}) > metrics.max_memory_gb={cfg['metrics']['max_memory_gb']} "
            f"({fb(float(cfg['metrics']['max_memory_gb']) * 2**30)}); accepted: a smaller scene, fewer bands or clusters, "
            "or a larger max_memory_gb"
        )
    return mesh, mem


def measure_uncompressed(ev: Evaluator, lights: list[torch.Tensor], views: list[Any], metrics: dict) -> tuple[dict, dict]:
    """The reference radiance ``[V, C]`` for every (light, view) (``Evaluator.reference``: for transport
    tables the exact radiance at each vertex's view) and the uncompressed peer's throughput (relighting the
    first light and view through ``prt_torch.relight``: ``Evaluator.uncompressed``)."""
    refs = {(li, vi): ev.reference(L, v) for li, L in enumerate(lights) for vi, v in enumerate(views)}
    t = measure(lambda: ev.uncompressed(lights[0], views[0]), repeats=metrics["repeats"], warmup=metrics["warmup"])
    return refs, {"relight_s": t.median, "relight_spread": t.spread, "vertices_per_s": t.rate(ev.V), "fps": 1.0 / t.median,
                  "bytes_total": ev.raw_bytes, "bytes_per_vertex": ev.raw_bytes / ev.V, **ev.reference_info}


@dataclasses.dataclass
class RunState:
    """One transfer's evaluation inside a run: what the target search, the renders and the
    results need (``run_setting(setting) -> record`` evaluates, saves and caches a setting)."""

    cfg: dict
    mesh: Any
    mem: dict
    tr: Transfer
    tinfo: dict
    ev: Evaluator
    lights: list
    cams: torch.Tensor
    views: list
    refs: dict
    uncompressed: dict
    records: list
    run_setting: Callable[..., dict]  # (setting, timed=True) -> record
    failures: list = dataclasses.field(default_factory=list)
    executor: dict = dataclasses.field(default_factory=lambda: LocalExecutor().describe())


def evaluate_run(cfg: dict, run_dir: Path, resume: bool = True, progress: bool = True,
                 log: Callable[[str], None] = print, label: str | None = None,
                 executor: Executor | None = None) -> RunState:
    """Transfer (cached), lights, views, the uncompressed reference, and every codec setting of
    ``cfg`` evaluated (or restored from ``run_dir/records``). ``label`` prefixes the setting ids
    (an ablation's value, so that its settings do not collide with another value's).

    ``executor`` (:mod:`prt_torch.executor`; None: this process, in order) runs the transfer's
    chunks and the settings still to evaluate: each setting is one task; its record and encoding
    are written here as it finishes (atomic, so an interruption keeps every finished setting and
    a re-run skips it). With a ``RayExecutor`` a setting whose task fails on every attempt is
    listed in ``RunState.failures`` (setting, error, attempts) while the others finish."""

    executor = LocalExecutor() if executor is None else executor
    rec_dir = run_dir / "records"
    mesh, mem = load_mesh_within_budget(cfg)
    log(f"[bench] {cfg['name']}{f' [{label}]' if label else ''}: scene {mesh.name} ({mesh.num_vertices} vertices), "
        f"transfer {cfg['transfer']['type']}")
    tr, tinfo = compute_transfer(cfg, mesh, Path(cfg["cache_dir"]), progress=progress, executor=executor)
    log(f"[bench] transfer {tuple(tr.data.shape)} ({tinfo['cache']}, {tinfo['seconds']:.1f} s)")
    ev = Evaluator(tr, wavelet_arith=cfg.get("wavelet", {}).get("arith", "auto"))
    lights, cams, views = ev.config_views(cfg)
    ref_cache, uncompressed = measure_uncompressed(ev, lights, views, cfg["metrics"])

    settings = expand_codecs(cfg["codecs"])
    done = _load_records(rec_dir) if resume else {}
    context_key = config_hash({"transfer": tinfo["key"], "lights": cfg["lights"], "views": cfg["views"],
                               "metrics": cfg["metrics"], "seed": cfg["seed"]})
    task = SettingTask(ev, lights, views, cfg, ref_cache)
    probe = SettingTask(ev, lights, views, cfg, ref_cache, timed=False)  # a target search's probes: no timing
    fitted: dict[str, tuple[Any, Any]] = {}  # key -> (codec, encoding) of the untimed settings fitted here

    def key_of(s: dict) -> str:
        return config_hash({"setting": s, "context": context_key})

    def save(s: dict, result: tuple[dict, Any, Any]) -> dict:
        rec, codec, enc = result
        rec["key"] = key_of(s)
        if label and not rec["setting_id"].startswith(f"{label}-"):
            rec["setting_id"] = f"{label}-{rec['setting_id']}"
        if not rec.get("timed", True):
            fitted[rec["key"]] = (codec, enc)
        codec.save(rec_dir / f"{rec['setting_id']}.prt", enc, overwrite=True)  # before the record: a record implies its encoding
        io.atomic_write_json(rec_dir / f"{rec['setting_id']}.json", rec)
        done[rec["key"]] = rec
        return rec

    def run_setting(s: dict, timed: bool = True) -> dict:
        """One setting (the target search's probes): from the records, else evaluated on the executor.
        ``timed=False``: error, bytes and PSNR only (:func:`evaluate_setting`); a later timed call of
        the same setting times its saved codec and encoding (:func:`time_setting`) without a refit."""
        k = key_of(s)
        if k in done and (done[k].get("timed", True) or not timed):
            return done[k]
        if k in done:  # fitted untimed: time it now, in this process
            codec, enc = fitted.get(k) or codecs.load(rec_dir / f"{done[k]['setting_id']}.prt")
            rec = {**done[k], **time_setting(ev, codec, enc, lights, views, cfg)}
            return save(s, (rec, codec, enc))
        (res,) = executor.map(task if timed else probe, [s])
        if isinstance(res, TaskFailure):
            raise RuntimeError(f"codec setting {setting_id(s)} failed {res.attempts} time(s): {res.error}")
        return save(s, res)

    def finished_timed(s: dict) -> bool:  # a record from an earlier run, with its rates (not a search's probe)
        return key_of(s) in done and done[key_of(s)].get("timed", True)

    todo = [s for s in settings if not finished_timed(s)]
    skipped = len(settings) - len(todo)
    bar = None
    if progress and todo:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), desc="codec settings", unit="setting")

    def finished(i: int, result: tuple[dict, Any, Any]) -> None:
        rec = save(todo[i], result)
        if bar is not None:
            bar.update(1)
        log(f"[bench] {rec['setting_id']}: {rec['bytes_per_vertex']:.1f} B/vertex, PSNR {rec['psnr_lights_db']:.2f} dB, "
            f"{rec['vertices_per_s'] / 1e6:.2f} Mvert/s, encode {rec['encode_s']:.2f} s")

    try:
        out = executor.map(task, todo, on_result=finished)
    finally:
        if bar is not None:
            bar.close()
    failures = []
    for f in out:
        if isinstance(f, TaskFailure):
            sid = f"{label}-{setting_id(f.item)}" if label else setting_id(f.item)
            failures.append({"setting_id": sid, "setting": f.item, "error": f.error, "attempts": f.attempts})
            log(f"[bench] FAILED {sid} after {f.attempts} attempt(s): {f.error}")
    records = [done[key_of(s)] for s in settings if finished_timed(s)]
    # the cold column's fallback eviction buffer (4x the LLC; only where the cache flush is not available): kept
    # across this run's settings, not into the renders or the next part's precompute
    release_eviction_buffer()
    if skipped:
        log(f"[bench] resumed: {skipped} finished setting(s) reused from {rec_dir}")
    return RunState(cfg, mesh, mem, tr, tinfo, ev, lights, cams, views, ref_cache, uncompressed, records, run_setting,
                    failures, executor.describe())


def _results(cfg: dict, st: RunState, records: list[dict], target: dict | None) -> dict:
    """The results dict (results.json) of a run whose context is ``st``."""
    ev, tr = st.ev, st.tr
    return {
        "format": "prt_torch.results",
        "results_version": RESULTS_VERSION,
        "name": cfg["name"],
        "config": {k: v for k, v in cfg.items() if not k.startswith("_")},
        "config_source": cfg.get("_source"),
        "machine": machine_info(),
        "scene": {"name": st.mesh.name, "vertices": st.mesh.num_vertices, "faces": st.mesh.num_faces, "hash": st.mesh.content_hash()},
        "transfer": {"kind": tr.kind, "shape": list(tr.data.shape), "matrix_shape": list(ev.matrix_shape) if ev.matrix_shape else None,
                     "n_in": ev.n_in, "raw_bytes": ev.raw_bytes, "cache": st.tinfo, "meta": io.jsonable(tr.meta)},
        "memory_estimate": st.mem,
        "lights": [str(s) for s in cfg["lights"]],
        "views": st.cams.tolist() if ev.needs_view else [],
        "uncompressed": st.uncompressed,
        "target": target,
        "records": records,
        "failures": st.failures,
        "executor": st.executor,
        "renders": [],
    }


def run_target(cfg: dict, st: "RunState", log: Callable[[str], None] = print) -> dict:
    """The target search of ``cfg['target']`` on a run's state (:mod:`harness.target`), searching
    on the error alone: its probes are fitted and scored untimed (``run_setting(s, timed=False)``),
    then only what a user reads is timed — the found setting (``target.codec``), or the winner and
    each family's best — from their saved encodings, without a refit. With ``target.by: fps`` the
    rate is what the search minimises, so every probe is timed. Returns the search record with
    ``_records`` (every record it made, timed or not) and ``timing_s`` (the finalists' timing)."""
    t = cfg["target"]
    timed_probes = t.get("by") == "fps" and not t.get("codec")  # one codec's bisection decides on dB alone

    def probe(s: dict) -> dict:
        return st.run_setting(s, timed=timed_probes)

    if t.get("codec"):
        target = find_smallest(cfg, probe)
        finalists = [target] if target["met"] else []
    else:
        target = search_families(cfg, probe, st.ev.V, st.ev.X.shape[1], log=log)
        finalists = [f["best"] for f in target["families"].values() if f.get("best")]
    t0 = time.perf_counter()
    if finalists and not timed_probes:
        log(f"[target] timing {len(finalists)} setting(s): " + ", ".join(f["setting_id"] for f in finalists))
    for f in finalists:  # in place: the winner and runners-up are these same summaries
        params = f["params"] if "params" in f else {f["param"]: f["value"]}
        base = next(r for r in target["_records"] if r["setting_id"] == f["setting_id"])
        rec = st.run_setting({"type": base["codec"], **base["params"], **params}, timed=True)
        f["fps"] = rec["fps"]
        target["_records"].append(rec)
    target["timing_s"] = time.perf_counter() - t0
    if not t.get("codec"):
        log(f"[bench] target {target['goal_db']} dB: " + (
            f"{target['winner']['setting_id']} ({target['winner']['bytes_per_vertex']:.1f} B/vertex, "
            f"{target['winner']['fps']:.0f} fps) after {target['evaluated']} evaluations" if target["met"] else target["note"]))
    return target


def run_benchmark(cfg: dict, resume: bool = True, progress: bool = True, log: Callable[[str], None] = print,
                  executor: Executor | None = None) -> Path:
    """Run one benchmark config end to end; returns the run directory reports/<name>/.
    A config with ``ablation`` set runs every value of that key into one combined report
    (:func:`run_ablation`). ``executor``: where the transfer's chunks and the codec settings
    run (:func:`evaluate_run`; None: this process); failed settings are listed in
    ``results['failures']`` and the report."""
    cfg = copy.deepcopy(cfg)
    if cfg.get("ablation"):
        return run_ablation(cfg, resume=resume, progress=progress, log=log, executor=executor)
    run_dir = Path(cfg["output_dir"]) / cfg["name"]
    st = evaluate_run(cfg, run_dir, resume, progress, log, executor=executor)
    ev, lights, views, cams, records = st.ev, st.lights, st.views, st.cams, list(st.records)

    target = None
    if cfg["target"].get("psnr") is not None:
        target = run_target(cfg, st, log)
        for r in target.pop("_records"):  # the timed ones: a search's untimed probes stay out of the tables
            if r.get("timed", True) and r["setting_id"] not in {x["setting_id"] for x in records}:
                records.append(r)

    results = _results(cfg, st, records, target)
    if ev.kind == "wavelet":  # SH vs N wavelet terms, each against the exact result (harness.trade)
        from .trade import wavelet_trade

        results["trade"] = wavelet_trade(ev, lights, cfg, log)
    if cfg["validation"]["enabled"]:
        results["validation"] = run_validation(st, cfg, log)
    if (cfg.get("convex") or {}).get("enabled"):
        results["convex"] = convex_results(cfg, run_dir, log, progress)
    if cfg["render"]["enabled"]:
        try:
            rendered = render_best(run_dir, records, ev, lights[0], views[0], cams[0], cfg["render"])
            results["renders"], results["glsl"] = rendered["images"], rendered["glsl"]  # GLSL vs CPU per codec
        except Exception as e:  # rendering must not lose a finished benchmark; say why
            log(f"[bench] renders skipped: {type(e).__name__}: {e}")
            results["render_error"] = f"{type(e).__name__}: {e}"
    for sub in part_configs(cfg):  # further benchmarks of the same report, on their own scene/transfer
        log(f"[bench] part {sub['name']!r}: {sub['_part']['note']}")
        part_dir = run_benchmark(sub, resume=resume, progress=progress, log=log, executor=executor)
        results.setdefault("parts", []).append({"name": sub["name"], "note": sub["_part"]["note"],
                                                "dir": str(part_dir.relative_to(run_dir)), "results": load_results(part_dir)})
    write_outputs(run_dir, results, log=log)
    return run_dir


# --------------------------------------------------------------------------- convex objects

def convex_results(cfg: dict, run_dir: Path, log: Callable[[str], None] = print, progress: bool = True) -> dict:
    """The config's ``convex`` section (:func:`prt_torch.harness.convex.run_convex`): SHRM vs
    unshadowed glossy PRT on each of ``convex.meshes``, the PRT peer being the run's glossy transfer
    with ``shadows: never`` from the transfer cache (:func:`compute_transfer`); SHRM files under
    ``run_dir/convex/``; with ``render.enabled`` one picture per mesh (reference | SHRMs | PRT,
    ``renders.render_convex``). Returns the section's dict (results.json ``convex``)."""
    sub = copy.deepcopy(cfg)
    sub["transfer"]["shadows"] = "never"  # unshadowed: a convex object has no self-occlusion to trace
    shots: list = []
    res = run_convex(sub, lambda mesh: compute_transfer(sub, mesh, Path(cfg["cache_dir"]), progress=progress),
                     Path(run_dir) / "convex", log, shots=shots if cfg["render"]["enabled"] else None)
    if shots:
        try:  # pictures must not lose the section; say why
            res["renders"] = render_convex(run_dir, shots, cfg["render"])
        except Exception as e:
            log(f"[bench] convex renders skipped: {type(e).__name__}: {e}")
            res["render_error"] = f"{type(e).__name__}: {e}"
    return res


# --------------------------------------------------------------------------- validation

def run_validation(st: RunState, cfg: dict, log: Callable[[str], None] = print) -> dict:
    """Engine vs Mitsuba 3 path tracing at ``validation.vertices`` sampled vertices of the run's
    transfer under the first config light the validator can emit (:func:`prt_torch.validate.validate`).
    Returns ``{'report': ..., 'text': ...}`` or ``{'skipped': why}`` (Mitsuba missing with
    ``enabled: auto``, a transfer kind or light it cannot express); never raises, so a finished
    benchmark is not lost."""
    from .. import validate as V

    v = cfg["validation"]
    try:
        V.require_mitsuba()
    except V.ValidatorUnavailable as e:
        if v["enabled"] == "auto":
            return {"skipped": str(e)}
        raise ValueError(f"config key 'validation.enabled' is true but {e}") from None
    refusals = []
    for spec in cfg["lights"]:
        for source in ("sh", "image"):  # the SH light itself, else (environments) Mitsuba sees the original image
            try:
                t0 = time.perf_counter()
                rep = V.validate(st.tr, spec, vertices=v["vertices"], spp=v["spp"], seed=cfg["seed"], light_source=source)
                log(f"[bench] validation against Mitsuba: {time.perf_counter() - t0:.1f} s")
                return {"report": io.jsonable(rep), "text": V.format_report(rep), "seconds": time.perf_counter() - t0}
            except ValueError as e:
                refusals.append(f"{spec} ({source}): {e}")
    return {"skipped": "; ".join(refusals)}


# --------------------------------------------------------------------------- ablations

def _get(cfg: dict, path: str) -> Any:
    node: Any = cfg
    for k in path.split("."):
        node = node[int(k)] if isinstance(node, list) else node[k]
    return node


def _put(cfg: dict, path: str, value: Any) -> None:
    ks = path.split(".")
    node: Any = cfg
    for k in ks[:-1]:
        node = node[int(k)] if isinstance(node, list) else node[k]
    if isinstance(node, list):
        node[int(ks[-1])] = value
    else:
        node[ks[-1]] = value


def ablation_values(cfg: dict) -> list[tuple[Any, dict]]:
    """``[(value, config with the ablation's key set to that value)]`` for a ``transfer.<param>``
    ablation (one transfer per value: what :func:`run_ablation` runs, and what ``--dry-run`` checks
    value by value); ``[(None, cfg)]`` otherwise (no ablation, or a codec key: one transfer, the
    codec entry's grid)."""
    key = cfg.get("ablation")
    if not key or not key.startswith("transfer."):
        return [(None, cfg)]
    out = []
    for v in _get(cfg, key):
        sub = copy.deepcopy(cfg)
        _put(sub, key, v)
        out.append((v, sub))
    return out


def run_ablation(cfg: dict, resume: bool = True, progress: bool = True, log: Callable[[str], None] = print,
                 executor: Executor | None = None) -> Path:
    """One modelling choice swept, one combined report (reports/<name>/).

    ``cfg['ablation']`` names the swept key — ``transfer.<param>`` (bands, samples, shadows,
    bounces, M, ...: one transfer per value) or ``codecs.<i>.<param>`` (e.g. CPCA's method: one
    transfer, the codec entry's grid). Every record carries ``ablation: {key, value}``. For a
    transfer key, each value's uncompressed radiance is also compared with the reference
    value's (``ablation_reference``, default the last value, the richest model): ``model_psnr_db``
    is what the modelling choice itself costs in accuracy, next to its precompute time, bytes
    and relighting rate."""
    key = cfg["ablation"]
    values = _get(cfg, key)
    run_dir = Path(cfg["output_dir"]) / cfg["name"]
    leaf = key.split(".")[-1]
    per_value: list[dict] = []
    records: list[dict] = []
    if key.startswith("transfer."):
        ref_value = values[-1] if cfg.get("ablation_reference") is None else cfg["ablation_reference"]
        states = []
        for v, sub in ablation_values(cfg):
            st = evaluate_run(sub, run_dir, resume, progress, log, label=f"{leaf}{v}", executor=executor)
            for r in st.records:
                r["ablation"] = {"key": key, "value": v}
            records += st.records
            states.append((v, st))
        ref = next(st for v, st in states if v == ref_value)
        for v, st in states:
            psnrs = [psnr_vs_reference(ref.refs[k], st.refs[k]) for k in ref.refs]
            finite = [p for p in psnrs if math.isfinite(p)]
            m = st.tr.meta
            per_value.append({
                "value": v, "transfer_shape": list(st.tr.data.shape), "raw_bytes_per_vertex": st.ev.raw_bytes / st.ev.V,
                "precompute_s": float(m.get("seconds", 0.0)), "rays_traced": int(m.get("rays_traced", 0)),
                "model_psnr_db": (sum(finite) / len(finite)) if len(finite) == len(psnrs) else float("inf"),
                "uncompressed": st.uncompressed,
                "decisions": {k: m[k] for k in ("shadow_decision", "bounces_used", "bounce_decision", "auto") if k in m},
            })
        base = ref
    else:
        base = evaluate_run(cfg, run_dir, resume, progress, log, executor=executor)
        param = key.split(".")[-1]
        for r in base.records:
            r["ablation"] = {"key": key, "value": r["params"].get(param)}
        records = list(base.records)
        per_value = [{"value": v} for v in values]
        ref_value = None
    results = _results(cfg, base, records, None)
    if key.startswith("transfer."):
        results["failures"] = [f for _, st in states for f in st.failures]
    results["ablation"] = {"key": key, "values": values, "reference_value": ref_value, "per_value": per_value}
    write_outputs(run_dir, results, log=log)
    return run_dir
