"""All-frequency relighting with Haar wavelets on cube maps against SH (issue 39; Ng, Ramamoorthi &
Hanrahan 2003; course notes 2005 "PRT with Haar Wavelets" and its blocker-over-plane figure).

Scene: the built-in ``occluder_over_plane`` (small: a receiver plane and a blocker slab, the
course's scene). Lights, not band-limited, rasterised onto the cube at R (lighting.haar.cube_light):
caps of 0.5°, 20° and 40° half-angle from above (tilted), and the built-in environments ``sky``
(a real-size sun) and ``studio`` (three disk softboxes) — two images with sharp features.

1. Precompute: ``precompute_wavelet`` (R = 32, K = 256, 8 bits) against bare Embree tracing the
   same rays (the same chunks' rays, ``RayCaster.trace`` alone), one worker each, paired.
2. The exact result per light: the full pixel-basis transfer (all 6R² terms, float64) · the cube
   light; every error below is the relative L2 over vertices and channels against it (same R).
3. Wavelets: per-vertex budgets K (8-bit values, 16-bit indices), light terms N = 10 … 2000 by
   each selection (magnitude, area-weighted, transport-weighted): error, relight time (the C
   kernel), bytes/vertex. The default selection is the one with the lowest mean error.
4. SH at 3–10 bands projected from the same visibility (t_lm = Σ_j T_j y_lm(d_j) of the
   pixel-basis transfer; the light projected from its cube, L_lm = Σ_j L_j y_lm(d_j) Ω_j), relit
   by ``relight.diffuse``: error, time, bytes/vertex (n² float32).
5. Headline: per light, the relight time to reach 5% and 1% error, SH vs wavelets.
6. Bytes/vertex vs error at R = 16, 32, 64 and several K (all light terms), also against the
   R = 64 exact result (what a coarser cube cannot place).
7. Relight time vs N, against the kernel's read-once/write-once bound (the transfer coefficients
   it touches — int32 row + stored value — and the output), ``timing.io_bound_fn``, paired. One
   section per CPU and kernel build (``relight.wavelet_kernel_path``: on an AVX-512 CPU the dense loop
   on 16 lanes, on an AVX2 one the 8-lane code): a run replaces the section of its own CPU and build and
   keeps the others; ``--isa auto`` (default) also runs the ``avx2`` build (``PRT_TORCH_KERNEL_ISA``, in a
   child process) where the native one is AVX-512, and the report then puts the builds side by side.
   ``--size small|medium|large`` (:data:`KERNEL_SIZES`; default small, V ≈ 2.3k / 10.6k / 51k vertices) times the
   section on that size of ``occluder_over_plane`` — the sizes users relight, whose bytes outgrow the core's L2 —
   and its run replaces only the rows of its own CPU, build and size. Every row also has the two-thread pairing
   against the streaming read, the one-thread pairing of both from cold caches (``timing.measure_paired_cold``,
   the bytes the two sides hold flushed before each call) and where its bytes live (the L2 and L3 sizes sysfs lists).

Run: .venv/bin/python benchmarks/bench_wavelet.py [--quick]   (about 5 minutes on 2 cores)
     .venv/bin/python benchmarks/bench_wavelet.py --only kernel [--isa auto|native,avx2,...]   (25 s per build)
     .venv/bin/python benchmarks/bench_wavelet.py --only kernel --size medium|large   (1-2 min per build; large
     precomputes for ~30 s in each build's process)
Writes reports/benchmarks/wavelet.{md,json,png}.
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from prt_torch import io, relight  # noqa: E402
from prt_torch.harness.timing import (cpu_label, io_bound_fn, machine_info, measure, measure_paired,  # noqa: E402
                                      measure_paired_cold, read_bound_fn, working_set)
from prt_torch.lighting.haar import cube_geometry, cube_light, haar2d, haar_levels  # noqa: E402
from prt_torch.scene import RayCaster, builtin  # noqa: E402
from prt_torch.sh import eval_sh  # noqa: E402
from prt_torch.transfer import RunOptions, Transfer  # noqa: E402
from prt_torch.transfer.diffuse import offset_origins  # noqa: E402
from prt_torch.transfer.ray_kernels import upper_rays  # noqa: E402
from prt_torch.transfer.wavelet import bytes_per_vertex, dense_wavelet_transfer, dequantise, precompute_wavelet, quantise, sparsify  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

import wavelet_history  # noqa: E402  (benchmarks/: section 7's runs kept across runs)

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "reports" / "benchmarks"
D = "0.3,0.2,1"
LIGHTS = {
    "cap 0.5°": f"cap:direction={D};half_angle_deg=0.5;intensity=1",
    "cap 20°": f"cap:direction={D};half_angle_deg=20;intensity=1",
    "cap 40°": f"cap:direction={D};half_angle_deg=40;intensity=1",
    "sky (sun)": "sky",
    "studio": "studio",
}
TERMS = [10, 30, 100, 300, 1000, 2000]
BANDS = list(range(3, 11))
SELECTIONS = ("magnitude", "area", "transport")
#: stored precision of the transfers of sections 3, 5 and 7 (8 bits floors the error near 1.7%: section 6)
BITS = 16


def load() -> float:
    return os.getloadavg()[0]


def dense(mesh, res: int, chunk: int = 256) -> torch.Tensor:
    """Pixel-basis transfer ``[V, 6R²]`` float64 (all terms), chunk by chunk (bounded memory)."""
    V = mesh.num_vertices
    out = torch.empty(V, 6 * res * res, dtype=torch.float64)
    for a in range(0, V, chunk):  # chunks of vertices, each one traced batch
        idx = torch.arange(a, min(V, a + chunk))
        out[idx] = dense_wavelet_transfer(mesh, res, vertices=idx, haar=False).reshape(idx.numel(), -1)
    return out


def rel(x: torch.Tensor, ref: torch.Tensor) -> float:
    return float((x.double() - ref).norm() / ref.norm().clamp_min(1e-300))


def wavelet_transfer(mesh, H: torch.Tensor, res: int, K: int, bits: int = 8) -> Transfer:
    s = sparsify(H, K, bits)
    return Transfer("wavelet", s["q"], mesh, {"res": res, "terms": K, "bits": bits, "albedo_folded": False},
                    aux={"index": s["index"], "scale": s["scale"]})


def precompute_vs_bare(mesh, res: int, K: int) -> dict:
    """Paired: the whole wavelet precompute and bare Embree tracing its rays (one worker each)."""
    d, om = cube_geometry(res)
    dirs = np.ascontiguousarray(d.reshape(-1, 3).numpy())
    d32 = dirs.astype(np.float32)
    caster = RayCaster(mesh, workers=1)
    rays = []
    chunk = 4096 * 256 // (6 * res * res)
    for a in range(0, mesh.num_vertices, chunk):  # the same rays, built once, outside the timing
        p, n = mesh.vertices[a:a + chunk].double(), mesh.normals[a:a + chunk].double()
        cos = n.numpy() @ dirs.T
        o_v = offset_origins(caster.local(p.numpy()), n.numpy(), caster.eps).astype(np.float32)  # the caster's frame
        _, _, o, dd = upper_rays(cos, o_v, d32)
        rays.append((o.copy(), dd.copy()))
    n_rays = sum(o.shape[0] for o, _ in rays)
    pre = lambda: precompute_wavelet(mesh, res=res, terms=K, bits=8, shadows="always", run=RunOptions(workers=1))  # noqa: E731
    bare = lambda: [caster.trace(o, dd, "occluded") for o, dd in rays]  # noqa: E731
    p = measure_paired(pre, bare, repeats=3, warmup=0, min_sample_time=0.0)
    t_pre = measure(pre, repeats=1, warmup=0).median
    caster.close()
    return {"res": res, "terms": K, "rays": n_rays, "precompute_s": t_pre, "bare_over_precompute": p.speedup,
            "spread": (p.ratio.q3 - p.ratio.q1) / p.ratio.median if p.ratio.median else float("nan"), "trusted": bool(p.contention.get("trusted"))}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="R = 16 and 32 only, fewer budgets")
    ap.add_argument("--only", choices=["kernel", "sampling", "quant"], help="one section, its rows replaced in the existing wavelet.json")
    ap.add_argument("--isa", default="auto", help="section 7's kernel builds, each in its own process: auto (this CPU's "
                    "native build, and also avx2 where native is AVX-512), or a comma list of native, avx2, avx512, "
                    "avx512-256 (PRT_TORCH_KERNEL_ISA)")
    ap.add_argument("--size", default=None, help="section 7's mesh: occluder_over_plane at small (default, ~2.3k vertices), "
                    "medium (~10.6k) or large (~51k); only with --only kernel")
    ap.add_argument("--child-json", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    size = check_size(args.size, args.only)
    if args.child_json:  # one build's section-7 run for a parent (child_run): the run as JSON, nothing else written
        res = json.loads((OUT / "wavelet.json").read_text())
        Path(args.child_json).write_text(json.dumps(kernel_run(res["selection_default"], size), default=str))
        return None
    isas = isa_runs(args.isa)
    if args.only == "kernel":
        return kernel_only(isas, size)
    if args.only in ("sampling", "quant"):
        return section_only(args.only)
    torch.set_num_threads(1)
    torch.manual_seed(0)
    res_list = [16, 32] if args.quick else [16, 32, 64]
    mesh = builtin("occluder_over_plane", "small")
    V = mesh.num_vertices
    alb = mesh.albedo.double()
    info = machine_info()
    loads = [load()]
    results: dict = {"machine": info, "scene": {"name": mesh.name, "vertices": V}, "lights": LIGHTS}
    print(f"[wavelet] {mesh.name}: {V} vertices; load {loads[0]:.1f}", flush=True)

    # 1. precompute vs bare Embree
    results["precompute"] = precompute_vs_bare(mesh, 32, 256)
    print(f"[wavelet] precompute {results['precompute']}", flush=True)

    # 2-4 at R = 32 (the main resolution), 6 at every R
    pix: dict[int, torch.Tensor] = {}
    t0 = time.perf_counter()
    for r in res_list:
        pix[r] = dense(mesh, r)
    results["dense_seconds"] = time.perf_counter() - t0
    R = 32
    T = pix[R]
    P = T.shape[1]
    H = haar2d(T.reshape(V, 6, R, R)).reshape(V, P)
    cubes = {name: cube_light(spec, R)[0] for name, spec in LIGHTS.items()}  # [C, 6, R, R]
    exact = {name: (T @ c.reshape(c.shape[0], -1).T) * alb[:, :c.shape[0]] for name, c in cubes.items()}

    # 3. wavelets: K budgets x N x selection
    budgets = [64, 256] if args.quick else [64, 256, 1024]
    wav_rows = []
    relighters = {}
    for K in budgets:
        tr = wavelet_transfer(mesh, H, R, K, BITS)
        rl = relight.WaveletRelighter(tr)
        relighters[K] = rl
        for name, spec in LIGHTS.items():
            for sel in SELECTIONS:
                for N in TERMS:
                    li, lv, rec = rl.light(spec, N, sel)
                    out = rl(li, lv)
                    row = {"K": K, "bytes_per_vertex": bytes_per_vertex(K, BITS, P), "light": name,
                           "selection": sel, "N": N, "terms_kept": int(li.numel()),  # at most the light's nonzero terms
                           "error": rel(out, exact[name]), "touched": rl.touched(li),
                           "relight_s": measure(lambda: rl(li, lv, out=out), repeats=5, warmup=1).median}
                    wav_rows.append(row)
        print(f"[wavelet] K={K} done; load {load():.1f}", flush=True)
    results["wavelet"] = wav_rows
    mean_err = {s: float(np.mean([math.log(max(r["error"], 1e-9)) for r in wav_rows if r["selection"] == s]))
                for s in SELECTIONS}
    default_sel = min(mean_err, key=mean_err.get)
    results["selection_mean_log_error"] = mean_err
    results["selection_default"] = default_sel

    # 4. SH projected from the same visibility
    d, om = cube_geometry(R)
    dirs, om = d.reshape(-1, 3), om.reshape(-1)
    Y = eval_sh(dirs, max(BANDS), check=False)  # [P, n²]
    sh_rows = []
    for n in BANDS:
        t_sh = (T @ Y[:, : n * n]).to(torch.float32)  # [V, n²]
        for name, c in cubes.items():
            Lsh = (c.reshape(c.shape[0], -1) * om) @ Y[:, : n * n]  # [C, n²]
            out = relight.diffuse(t_sh, Lsh.to(torch.float32)) * mesh.albedo[:, : c.shape[0]]
            ts = measure(lambda: relight.diffuse(t_sh, Lsh.to(torch.float32)), repeats=5, warmup=1).median
            sh_rows.append({"bands": n, "bytes_per_vertex": n * n * 4, "light": name, "error": rel(out, exact[name]),
                            "relight_s": ts})
    results["sh"] = sh_rows
    print(f"[wavelet] SH done; load {load():.1f}", flush=True)

    # 5. headline: time to reach 5% and 1%, the two relightings timed paired (interleaved, same run)
    K_head = budgets[-1]
    rl_head = relighters[K_head]
    sh_fns = {}
    for n in BANDS:
        t_sh = (T @ Y[:, : n * n]).to(torch.float32)
        sh_fns[n] = t_sh
    head = []
    for name in LIGHTS:
        row = {"light": name}
        for tgt in (0.05, 0.01):
            shs = [r for r in sh_rows if r["light"] == name and r["error"] <= tgt]
            wvs = [r for r in wav_rows if r["light"] == name and r["K"] == K_head and r["selection"] == default_sel
                   and r["error"] <= tgt]
            s = min(shs, key=lambda r: r["bands"]) if shs else None
            w = min(wvs, key=lambda r: r["N"]) if wvs else None
            row[f"sh_{tgt}"] = None if s is None else {"bands": s["bands"], "relight_s": s["relight_s"], "error": s["error"]}
            row[f"wavelet_{tgt}"] = None if w is None else {"N": w["N"], "relight_s": w["relight_s"], "error": w["error"]}
            if s is not None and w is not None:  # paired: SH's time over the wavelets' (> 1: wavelets faster)
                c = cubes[name]
                Lsh = ((c.reshape(c.shape[0], -1) * om) @ Y[:, : s["bands"] ** 2]).to(torch.float32)
                t_sh = sh_fns[s["bands"]]
                li, lv, _ = rl_head.light(LIGHTS[name], w["N"], default_sel)
                buf = torch.empty(V, 3)
                p = measure_paired(lambda: rl_head(li, lv, out=buf), lambda: relight.diffuse(t_sh, Lsh), repeats=7, warmup=1,
                                   floor_pairs=40)
                row[f"paired_{tgt}"] = {"sh_over_wavelet": p.speedup, "trusted": bool(p.contention.get("trusted"))}
        row["sh_best_error"] = min(r["error"] for r in sh_rows if r["light"] == name)
        row["wavelet_best_error"] = min(r["error"] for r in wav_rows if r["light"] == name and r["K"] == K_head
                                        and r["selection"] == default_sel)
        head.append(row)
    results["headline"] = head

    # 6. bytes/vertex vs error over R and K (all light terms)
    ref64 = max(res_list)
    bve = []
    for r in res_list:
        Tr = pix[r]
        Hr = haar2d(Tr.reshape(V, 6, r, r)).reshape(V, -1)
        cub = {name: cube_light(spec, r)[0] for name, spec in LIGHTS.items()}
        ex = {name: (Tr @ c.reshape(c.shape[0], -1).T) * alb[:, :c.shape[0]] for name, c in cub.items()}
        exf = {name: (pix[ref64] @ cube_light(spec, ref64)[0].reshape(3, -1).T) * alb for name, spec in LIGHTS.items()}
        for K in [16, 64, 256, 1024, 6 * r * r]:
            if K > 6 * r * r:
                continue
            for bits in (8, 16, 32):
                tr = wavelet_transfer(mesh, Hr, r, K, bits)
                rl = relight.WaveletRelighter(tr)
                errs, errs_f = [], []
                for name, spec in LIGHTS.items():
                    li, lv, _ = rl.light(spec, None, "area")
                    out = rl(li, lv)
                    errs.append(rel(out, ex[name]))
                    errs_f.append(rel(out, exf[name]))
                bve.append({"res": r, "K": K, "bits": bits, "bytes_per_vertex": bytes_per_vertex(K, bits, 6 * r * r),
                            "error_mean": float(np.mean(errs)), "error_max": float(np.max(errs)),
                            f"error_vs_R{ref64}_mean": float(np.mean(errs_f)), "per_light": dict(zip(LIGHTS, errs))})
        print(f"[wavelet] R={r} bytes/error done; load {load():.1f}", flush=True)
    results["bytes_vs_error"] = bve

    # 7. relight time vs N against the bound (paired), studio, K = 256: this build, then the others (child processes)
    before = load()
    runs = [{"machine": dict(machine_info(), load_before=before), "utc": wavelet_history.now_utc(),
             "read_sweep": wavelet_history.read_sweep(),
             "build": relight.wavelet_kernel_path(),
             "rows": kernel_rows(relighters[256], results["selection_default"],
                                 relight.WaveletRelighter(relighters[256].transfer, threads=2))}]  # two threads' tiles
    runs[0]["machine"]["load_after"] = load()
    if (OUT / "wavelet.json").exists():  # the kept runs of other CPUs and builds
        merge_kernel_runs(results, kernel_runs(json.loads((OUT / "wavelet.json").read_text())))
    merge_kernel_runs(results, runs)
    results["sampling"] = sampling_rows(mesh)
    results["quant"] = quant_rows(mesh)
    loads.append(load())
    results["load_average"] = loads
    results["notes"] = []
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet.json", json.dumps(results, indent=1, default=str))
    if len(isas) > 1:  # the other builds' section 7, each in a child process, reading the file just written
        more = [child_run(isa) for isa in isas[1:]]
        merge_kernel_runs(results, more)
        runs += more
        atomic_write_text(OUT / "wavelet.json", json.dumps(results, indent=1, default=str))
    keep_history(runs)
    plot(results)
    write_md(results, args.quick)
    print(f"[wavelet] wrote {OUT / 'wavelet.md'}", flush=True)


def _n_kept(r: dict) -> str:
    """A row's N, with the terms really kept when fewer (``select_terms`` keeps only the light's nonzero Haar terms:
    the studio light has 292 at R = 32); rows from before ``terms_kept`` was recorded: N alone."""
    k = r.get("terms_kept", r["N"])
    return f"{r['N']} ({k} kept)" if k < r["N"] else str(r["N"])


def _row_key(r: dict) -> tuple[str, int]:
    """A section-7 row's (light, N); rows from before the sky light was timed there are the studio's."""
    return r.get("light", "studio"), r["N"]


def previous_layout_bytes(rl, li: torch.Tensor) -> int:
    """The bytes the previous layout read for these terms (the same dense columns; each sparse column
    a CSC list of (int32 row offset, value) pairs padded to groups of 4): the bound that kernel was
    measured against (0.27-0.35)."""
    d = rl.dslot[li] >= 0
    b = rl.bvals.element_size()
    return int(d.sum()) * rl.dense.shape[0] * rl.BLOCK * b + int(((rl.nnz[li[~d]] + 3) // 4 * 4).sum()) * (4 + b)


KERNEL_LIGHTS = ("studio", "sky")
#: section 7's mesh sizes (``occluder_over_plane``; ``--size``): V = 2251 / 10585 / 51335 vertices on the Intel Xeon
KERNEL_SIZES = ("small", "medium", "large")


def size_choice(size: str | None, who: str = "bench_wavelet.py") -> str:
    """A ``--size`` value checked before any work: one of :data:`KERNEL_SIZES` (None, not given: ``small``), else one
    line on stderr naming ``who``, the option, the value and what is accepted, and exit status 2. The kernel
    benchmarks that take the kernel section's transfer at a size (bench_wavelet_dense16) check it here."""
    if size is None or size in KERNEL_SIZES:
        return size or "small"
    print(f"{who}: --size {size}: not a size; accepted: {', '.join(KERNEL_SIZES)}", file=sys.stderr)
    raise SystemExit(2)


def kernel_transfer(size: str):
    """Section 7's transfer at ``size`` (:data:`KERNEL_SIZES`): ``occluder_over_plane``, R = 32, K = 256, :data:`BITS`-bit
    values, shadowed, one precompute worker — what the kernel benchmarks that pair builds or layouts relight."""
    return precompute_wavelet(builtin("occluder_over_plane", size), 32, 256, BITS, shadows="always", run=RunOptions(workers=1))


def kernel_lights(rl, terms):
    """Section 7's lights for a relighter ``rl``: ``(light, N, idx, vals)`` for studio and sky at each N of ``terms`` and
    at all ``rl.P`` terms (transport-weighted; ``vals`` float32 [C, n], ``idx`` int64 [n], both contiguous)."""
    for light in ("studio", "sky (sun)"):
        for N in tuple(terms) + (rl.P,):
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            yield light, N, li.contiguous(), lv.to(torch.float32).contiguous()


def layout_info(rl, size: str) -> dict:
    """A relighter's layout for a report's header: ``{size, V, Pd, dense_mb}``."""
    return {"size": size, "V": rl.V, "Pd": rl.Pd, "dense_mb": rl.dense.numel() * rl.dense.element_size() / 2**20}


def check_size(size: str | None, only: str | None) -> str:
    """bench_wavelet.py's ``--size`` checked before any work (:func:`size_choice`), and only with ``--only kernel``
    (the other sections' tables are the small mesh's): one line and exit status 2 otherwise."""
    if size is None:
        return "small"
    size = size_choice(size)
    if only == "kernel":
        return size
    why = (f"section 7 only; accepted: with --only kernel (given: --only {only})" if only else
           "section 7 only; accepted: with --only kernel (the full run's tables are the small mesh's)")
    print(f"bench_wavelet.py: --size {size}: {why}", file=sys.stderr)
    raise SystemExit(2)


def cache_sizes() -> dict:
    """This CPU's data caches as sysfs lists them for cpu0: ``{"l1d_bytes", "l2_bytes", "l3_bytes"}`` (a level
    sysfs does not list is absent). The L2 is one core's; the L3 the VM's listing (480 MiB on the Intel Xeon here)."""
    out = {}
    base = Path("/sys/devices/system/cpu/cpu0/cache")
    for d in sorted(base.glob("index*")) if base.is_dir() else []:
        try:
            level, kind, txt = ((d / f).read_text().strip() for f in ("level", "type", "size"))
        except OSError:
            continue
        if kind == "Instruction" or not txt[:-1].isdigit():
            continue
        mult = {"K": 1024, "M": 1024 ** 2, "G": 1024 ** 3}.get(txt[-1], 1)
        out[{"1": "l1d_bytes", "2": "l2_bytes", "3": "l3_bytes"}.get(level, f"l{level}_bytes")] = int(txt.rstrip("KMG")) * mult
    return out


def bytes_home(nbytes: int, caches: dict) -> str:
    """Where a row's bytes (read + written) live between back-to-back calls of one thread, in words: the smallest
    of one core's L2 and the L3 holding them, with the bytes as a share of it (sizes from :func:`cache_sizes`)."""
    l2, l3 = caches.get("l2_bytes"), caches.get("l3_bytes")
    if l2 and nbytes <= l2:
        return f"L2 ({nbytes / l2:.2f} of {l2 / 2 ** 20:.0f} MiB)"
    if l3 and nbytes <= l3:
        return f"L3 ({nbytes / l2:.1f}× L2)" if l2 else "L3"
    return "memory" if l3 else "?"


#: a one-thread CPU-time pairing whose per-repeat ratios spread more than this (relative inter-quartile range) is timed
#: again, up to STEADY_TRIES times in all, and the steadiest kept (``kernel_rows``: the row's ``tries_cpu_1``)
STEADY_SPREAD = 0.2
#: the kernel section's second streaming read: ``timing.read_bound_fn(pick=READ_PICK)``, the median-time one of this many
#: fresh buffers (a placement-robust read; the one-buffer read stays the criterion)
READ_PICK = 8
STEADY_TRIES = 3


def steady_pair(test, peer, repeats: int = 15) -> tuple:
    """``(paired, tries)``: ``measure_paired(test, peer, clock=time.thread_time)`` (15 repeats: the median of the
    per-repeat ratios, as the small mesh's rows, and a floor phase of short samples: ``paired.speedup`` is the ratio of
    the two sides' fastest tenth by CPU time, 40-160 pairs) timed again while the median's per-repeat ratios spread
    more than :data:`STEADY_SPREAD`, up to :data:`STEADY_TRIES` times, the steadiest kept. On a shared 2-core machine
    another process's time slice on this core evicts the L2 the two sides use; the thread's CPU time leaves the other's
    time out but not the refill after it, so a sample that held a switch is slow on either side (more on a streaming
    read than on the kernel): a wide spread says the pairing caught such switches, and the fastest tenth of short
    samples pairs the least disturbed ones (past the L2, the other processes' traffic in the shared L3 and memory
    slows every sample, which neither estimate removes)."""
    best, tries = None, 0
    for tries in range(1, STEADY_TRIES + 1):
        p = measure_paired(test, peer, repeats=repeats, warmup=1, clock=time.thread_time, floor_pairs=40, floor_max_pairs=160)
        if best is None or p.ratio.spread < best.ratio.spread:
            best = p
        if p.ratio.spread <= STEADY_SPREAD:
            break
    return best, tries


def kernel_rows(rl, selection: str, rl2=None) -> list[dict]:
    """Section 7: the C kernel per light (:data:`KERNEL_LIGHTS`: studio, 292 nonzero Haar terms at R = 32, and
    sky, 3072, so that N = 300-2000 also time lights that really hold that many terms) and N (an N whose kept terms
    equal the previous N's is not timed again: ``select_terms`` keeps only nonzero terms), at one and two threads, each
    paired with its
    read-once/write-once bound — a copy of the transfer bytes it reads (:meth:`WaveletRelighter.bytes_read`:
    dense columns' blocks, the sparse 8-vertex blocks with their offsets and the per-tile pointers, and the factor —
    quantisation scale × albedo — the kernel reads: ``factor_bytes``, 4 (V + 4) on the blocker scene's grey albedo;
    rows from before 0182f3f have no ``factor_bytes`` and did not count it)
    and a fill of the output, at the same thread count —, and at one thread with the previous
    layout's bound (dense + CSC pairs: :func:`previous_layout_bytes`); and the torch path. Also, per row: at one
    thread, by the thread's CPU time, against the same bytes only read (``timing.read_bound_fn``, a streaming read)
    warm and from cold caches (``measure_paired_cold``: before each call, untimed, the bytes both sides hold — the
    whole relighter's tensors and the bound's buffers, ``timing.working_set`` — are flushed from every cache level);
    at two threads (wall time, fastest tenth) against the streaming read too. Fields: ``of_read_bound_cpu_1``,
    ``of_read_bound_2``, ``of_read_bound_cold`` [``_q`` quartiles], the bounds' own times (``*_bound_*_s``); beside the
    criterion, ``of_read_pick_cpu_1`` / ``read_pick_cpu_s_1``: against the median-time one of :data:`READ_PICK` fresh
    reads (``read_bound_fn(pick=)``: the read of a typical placement, not of whichever pages one buffer got).
    ``rl2``: the relighter the two-thread rows call (built for two threads: ``WaveletRelighter._tile``'s default
    follows the threads a relighter is built for; None: ``rl``); ``tiles_1`` / ``tiles_2`` each side's tile count."""
    V = rl.V
    rl2 = rl if rl2 is None else rl2
    rows = []
    for light, N in [(x, n) for x in KERNEL_LIGHTS for n in TERMS + [rl.P]]:
        li, lv, _ = rl.light(light, N, selection)
        if rows and rows[-1]["light"] == light and rows[-1]["terms_kept"] == li.numel():
            continue  # the same kept terms as the previous N: the same call
        lv = lv.to(torch.float32).contiguous()
        out = torch.empty(V, 3)
        E = rl.touched(li)
        nbytes = rl.bytes_read(li)
        prev = previous_layout_bytes(rl, li)
        row = {"light": light, "N": N, "terms_kept": int(li.numel()), "touched": E, "bytes": nbytes + V * 12, "previous_bytes": prev + V * 12,
               "factor_bytes": rl.factor_bytes(lv.shape[0])}  # in "bytes" (bytes_read counts the factor from 0182f3f on)
        row["tiles_1"], row["tiles_2"] = rl.NT, rl2.NT
        trusted = True
        for th in (1, 2):
            torch.set_num_threads(th)
            r = rl if th == 1 else rl2
            r.threads = th
            nbytes = r.bytes_read(li)  # the two-thread relighter's own bytes (its per-tile pointers)
            f = r.prepared(li, lv, out)  # the render-loop form: checks and ctypes arguments once
            if th == 1:  # the plain call's extra (its per-call checks), paired
                pc = measure_paired(lambda: rl(li, lv, out=out), f, repeats=7, warmup=1, floor_pairs=40)  # noqa: B023
                row["call_over_prepared"] = 1.0 / pc.speedup
            # at two threads a descheduled thread stalls the whole call: the floor phase grows while its halves disagree
            more = 200 if th == 2 else 0
            p = measure_paired(f, io_bound_fn(nbytes, V * 3 * 4), repeats=7, warmup=1, floor_pairs=40, floor_max_pairs=more)
            row[f"of_bound_{th}"] = p.speedup
            row[f"relight_s_{th}"] = measure(f, repeats=7, warmup=1).median
            trusted = trusted and bool(p.contention.get("trusted"))
            if th == 2:  # the stricter bound at two threads too (the sum's reduction splits between the threads)
                p2r = measure_paired(f, read_bound_fn(nbytes, V * 3 * 4), repeats=7, warmup=1, floor_pairs=40, floor_max_pairs=more)
                row["of_read_bound_2"] = p2r.speedup
                row["read_bound_s_2"], row["relight_floor_s_2"] = p2r.floor["peer_s"], p2r.floor["test_s"]  # per call
                trusted = trusted and bool(p2r.contention.get("trusted"))
            if th == 1:
                pb = measure_paired(f, io_bound_fn(prev, V * 3 * 4), repeats=7, warmup=1, floor_pairs=40)
                row["of_previous_bound"] = pb.speedup
                trusted = trusted and bool(pb.contention.get("trusted"))
                # the same pair timed by this thread's CPU time (the kernel runs on the calling thread at one thread):
                # the time other processes held the core is in neither side — the figure the load does not move
                # (timing.measure_paired's clock; median of 15 per-repeat ratios, with their quartiles)
                # (timed again while its ratios spread more than STEADY_SPREAD: steady_pair)
                pc1, t_c = steady_pair(f, io_bound_fn(nbytes, V * 3 * 4))
                row["of_bound_cpu_1"] = pc1.ratio.median
                row["of_bound_cpu_1_floor"] = pc1.speedup
                row["of_bound_cpu_1_q"] = [pc1.ratio.q1, pc1.ratio.q3]
                row["relight_cpu_s_1"] = pc1.test.median
                # and against a stricter bound: the same bytes only read (a streaming sum), the output filled
                # (timing.read_bound_fn; the copy above also writes every byte it reads)
                pr1, t_r = steady_pair(f, read_bound_fn(nbytes, V * 3 * 4))
                row["tries_cpu_1"] = [t_c, t_r]
                row["of_read_bound_cpu_1"] = pr1.ratio.median
                row["of_read_bound_cpu_1_floor"] = pr1.speedup
                row["relight_cpu_floor_s_1"], row["read_bound_cpu_floor_s_1"] = pr1.floor["test_s"], pr1.floor["peer_s"]
                row["of_read_bound_cpu_1_q"] = [pr1.ratio.q1, pr1.ratio.q3]
                row["read_over_copy_1"] = pr1.peer.median / pc1.peer.median
                row["copy_bound_cpu_s_1"], row["read_bound_cpu_s_1"] = pc1.peer.median, pr1.peer.median
                # the same read from the median-time one of READ_PICK fresh buffers (timing.read_bound_fn's pick): near
                # the L2's size one buffer's read varies with its pages (reports/benchmarks/wavelet_hugepages_small.md);
                # reported beside the criterion above, not instead of it
                pp1, _ = steady_pair(f, read_bound_fn(nbytes, V * 3 * 4, pick=READ_PICK))
                row["of_read_pick_cpu_1"], row["read_pick_cpu_s_1"] = pp1.ratio.median, pp1.peer.median
                # from cold caches: each call (kernel or read) after a flush of everything both sides hold, by this
                # thread's CPU time (a stall on memory is the thread's CPU time; other processes' time is not)
                rb = read_bound_fn(nbytes, V * 3 * 4)
                pcold = measure_paired_cold(f, rb, repeats=15, warmup=1, evict=working_set(f, rb), clock=time.thread_time)
                row["of_read_bound_cold"] = pcold.speedup
                row["of_read_bound_cold_q"] = [pcold.ratio.q1, pcold.ratio.q3]
                row["relight_cold_s"], row["read_bound_cold_s"] = pcold.test.median, pcold.peer.median
                row["eviction"] = pcold.eviction
        torch.set_num_threads(1)
        rl.threads = rl2.threads = None
        os.environ["PRT_TORCH_NATIVE"] = "0"
        row["torch_relight_s"] = measure(lambda: rl(li, lv, out=out), repeats=3, warmup=1).median
        os.environ.pop("PRT_TORCH_NATIVE")
        d = rl.dslot[li] >= 0
        row.update({"dense_terms": int(d.sum()), "dense_coefficients": int(rl.nnz[li[d]].sum()), "relight_s": row["relight_s_1"],
                    "dense": "int16 vnni" if rl._takes_vnni(li, lv) else "float",  # the call's dense arithmetic
                    "of_bound": row["of_bound_1"], "trusted": trusted, "load": load()})
        rows.append(row)
        print(f"[wavelet] kernel {light} N={N}: {rows[-1]}", flush=True)
    return rows


def sampling_rows(mesh, R: int = 32, every: int = 15, chunk: int = 16) -> dict:
    """Section 8: grid (sub-texel centres) vs jittered (one random point per sub-texel and vertex)
    sampling of the texel integrals at s = 1, 2, 4 (s² rays per texel), every ``every``-th vertex,
    against the s = 8 grid (64 rays per texel) — exit radiance under each light: relative L2 and
    the mean signed relative error (bias), with each setting's time (one worker)."""
    idx = torch.arange(0, mesh.num_vertices, every)

    def pix(s: int, sampling: str) -> tuple[torch.Tensor, float]:
        t0 = time.perf_counter()
        parts = [dense_wavelet_transfer(mesh, R, supersample=s, vertices=idx[a:a + chunk], haar=False, sampling=sampling,
                                        seed=a).reshape(-1, 6 * R * R) for a in range(0, idx.numel(), chunk)]
        return torch.cat(parts), time.perf_counter() - t0

    ref, _ = pix(8, "grid")
    cubes = {name: cube_light(spec, R)[0].reshape(3, -1) for name, spec in LIGHTS.items()}
    exref = {name: ref @ c.T for name, c in cubes.items()}
    rows = []
    for s in (1, 2, 4):
        for sampling in ("grid", "jittered"):
            T, secs = pix(s, sampling)
            row = {"s": s, "sampling": sampling, "seconds": secs, "per_light": {}}
            for name, c in cubes.items():
                out = T @ c.T
                row["per_light"][name] = {"error": rel(out, exref[name]),
                                          "bias": float((out - exref[name]).sum() / exref[name].sum())}
            rows.append(row)
            print(f"[wavelet] sampling s={s} {sampling}: {row}", flush=True)
    return {"vertices": int(idx.numel()), "res": R, "rows": rows}


def _minifloat_table(e_bits: int = 4, m_bits: int = 3) -> torch.Tensor:
    """Magnitudes of an unsigned (e_bits, m_bits) minifloat relative to 1 (the largest normal = 2 − 2^-m ≈ 2
    rescaled to 1): subnormals at exponent 0, float64, ascending."""
    bias = (1 << e_bits) - 1
    mags = [m / (1 << m_bits) * 2.0 ** (1 - bias) for m in range(1 << m_bits)]
    mags += [(1 + m / (1 << m_bits)) * 2.0 ** (e - bias) for e in range(1, 1 << e_bits) for m in range(1 << m_bits)]
    t = torch.tensor(sorted(set(mags)), dtype=torch.float64)
    return t / t.max()


def quantisers(res: int) -> dict:
    """Candidate storage of the kept values ``kept [V, K]`` (float64, their flat indices ``idx``): each
    returns (dequantised values, bytes per vertex for K terms with 16-bit indices)."""
    lv = haar_levels(res)  # [6R²]
    n_lev = int(lv.max()) + 1
    table = _minifloat_table()

    def uniform(bits):
        def f(kept, idx):
            q, sc = quantise(kept, bits)
            return dequantise(q, sc).double(), kept.shape[1] * (bits // 8 + 2) + 4
        return f

    def per_level(kept, idx):  # 8 bits with one float32 scale per (vertex, Haar level): the library's scales='level'
        q, sc = quantise(kept, 8, lv[idx], n_lev)
        return dequantise(q, sc, lv[idx]).double(), kept.shape[1] * 3 + 4 * n_lev

    def minifloat(kept, idx):  # 8 bits: sign + e4m3 magnitude relative to the vertex's largest (float32 scale)
        top = kept.abs().amax(1, keepdim=True).clamp_min(1e-300)
        x = kept.abs() / top
        j = torch.searchsorted(table, x.contiguous()).clamp(1, table.numel() - 1)
        lo, hi = table[j - 1], table[j]
        mag = torch.where((x - lo) <= (hi - x), lo, hi)
        return torch.sign(kept) * mag * top.to(torch.float32).double(), kept.shape[1] * 3 + 4

    def half(kept, idx):  # IEEE float16, no scale
        return kept.to(torch.float16).double(), kept.shape[1] * 4

    return {"8-bit, scale per vertex": uniform(8), "16-bit, scale per vertex": uniform(16),
            "8-bit, scale per vertex and level": per_level, "8-bit sign+e4m3, scale per vertex": minifloat,
            "float16": half}


def quant_rows(mesh, R: int = 32, budgets=(64, 128, 256, 512, 1024)) -> dict:
    """Section 9: the stored values' precision. Each vertex keeps its K largest Haar coefficients
    (the same ones for every scheme); exit radiance under every light, all light terms, against the
    exact pixel-basis result (all 6R² terms, float64): relative L2, per scheme and K, with bytes/vertex."""
    V = mesh.num_vertices
    T = dense(mesh, R)
    H = haar2d(T.reshape(V, 6, R, R)).reshape(V, -1)
    alb = mesh.albedo.double()
    cubes = {name: haar2d(cube_light(spec, R)[0]).reshape(3, -1) for name, spec in LIGHTS.items()}
    exact = {name: (H @ c.T) * alb for name, c in cubes.items()}
    rows = []
    for K in budgets:
        top = H.abs().topk(K, dim=1)
        kept = H.gather(1, top.indices)
        trunc = {name: rel(torch.einsum("vk,cvk->vc", kept, c[:, top.indices]) * alb, exact[name]) for name, c in cubes.items()}
        for scheme, fq in quantisers(R).items():
            vals, nbytes = fq(kept, top.indices)
            errs = {name: rel(torch.einsum("vk,cvk->vc", vals, c[:, top.indices]) * alb, exact[name]) for name, c in cubes.items()}
            rows.append({"K": K, "scheme": scheme, "bytes_per_vertex": nbytes, "per_light": errs,
                         "mean_error": float(np.mean(list(errs.values()))), "truncation_mean_error": float(np.mean(list(trunc.values())))})
            print(f"[wavelet] quant K={K} {scheme}: {nbytes} B, mean error {rows[-1]['mean_error']:.4f} "
                  f"(truncation alone {rows[-1]['truncation_mean_error']:.4f})", flush=True)
    return {"res": R, "rows": rows}


def section_only(name: str) -> None:
    """``--only sampling`` / ``quant``: section 8 or 9 alone, added to the existing wavelet.json, the report rewritten."""
    torch.set_num_threads(1)
    res = json.loads((OUT / "wavelet.json").read_text())
    mesh = builtin("occluder_over_plane", "small")
    before = load()
    res.setdefault("notes", [])
    note = f"Section {'Texel sampling' if name == 'sampling' else 'Stored precision'} was run alone (`--only {name}`)."
    if note not in res["notes"]:
        res["notes"].append(note)
    if name == "sampling":
        res["sampling"] = dict(sampling_rows(mesh), load_before=before, load_after=load())
    else:
        res["quant"] = quant_rows(mesh)
    atomic_write_text(OUT / "wavelet.json", json.dumps(res, indent=1, default=str))
    write_md(res, False)
    print(f"[wavelet] wrote {OUT / 'wavelet.md'} ({name})", flush=True)


def kernel_run(selection: str, size: str = "small") -> dict:
    """Section 7 in this process's kernel build (the same transfer: R = 32, K = 256, BITS) on ``occluder_over_plane``
    at ``size`` (:data:`KERNEL_SIZES`): ``{machine (with the load before and after and the caches' sizes), utc (the
    run's start), read_sweep (``wavelet_history.read_sweep`` then: the machine's state), build
    (relight.wavelet_kernel_path), size, vertices, precompute_s, rows}``; each row says where its bytes live."""
    mesh = builtin("occluder_over_plane", size)
    utc, sweep = wavelet_history.now_utc(), wavelet_history.read_sweep()  # the run's start and its machine state
    t0 = time.perf_counter()
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    t_pre = time.perf_counter() - t0
    print(f"[wavelet] kernel section at {size}: {mesh.num_vertices} vertices, precompute {t_pre:.1f} s", flush=True)
    caches = cache_sizes()
    before = load()
    # one relighter per thread count the rows time: the default tile follows the threads a relighter is built for
    # (one tile at one thread where V <= 4096, one per thread at two: WaveletRelighter._tile)
    rl = relight.WaveletRelighter(tr, threads=1)
    rl2 = relight.WaveletRelighter(tr, threads=2)
    rl2 = rl if rl2.TV == rl.TV else rl2
    pages = "2 MiB pages (io.hugepage_zeros)" if io.hugepage_backed(rl.dense) else "torch's buffer (4 KB pages)"
    rows = kernel_rows(rl, selection, rl2)
    for r in rows:
        r["lives"] = bytes_home(r["bytes"], caches)
    return {"machine": dict(machine_info(), load_before=before, load_after=load(), **caches), "utc": utc, "read_sweep": sweep,
            "build": relight.wavelet_kernel_path(), "size": size, "vertices": mesh.num_vertices, "precompute_s": t_pre,
            "dense_pages": pages, "rows": rows}


def kernel_runs(res: dict) -> list[dict]:
    """The kernel section's runs kept in ``res`` (one per CPU and kernel build); a report from before builds were
    recorded (``kernel`` + ``kernel_machine``) is one run of the AVX2 path (its CPU had no AVX-512)."""
    if "kernel_runs" in res:
        return list(res["kernel_runs"])
    if "kernel" not in res:
        return []
    m = res.get("kernel_machine", res["machine"])
    return [{"machine": m, "rows": res["kernel"], "build": {
        "backend": "native", "isa": m.get("cpu_isa") or "avx2", "w16": False, "isa_choice": "native",
        "path": "dense loop, sparse blocks and output on 8 lanes (AVX2 code: the only path then; recorded before the "
                "report named builds)"}}]


def kernel_run_key(run: dict) -> str:
    """A kernel run's CPU, build and mesh size (runs from before ``--size`` are the small mesh's): a new run replaces
    a kept one of the same key."""
    b = run.get("build") or {}
    return (cpu_label(run["machine"]) + f", kernels {b.get('isa')} ({b.get('isa_choice', 'native')}, w16 {bool(b.get('w16'))})"
            + f", {run_size(run)}")


def run_size(run: dict) -> str:
    """A kernel run's mesh size (:data:`KERNEL_SIZES`); runs from before ``--size`` timed the small mesh."""
    return run.get("size", "small")


def build_label(b: dict) -> str:
    """A kernel build in words: its ISA, the PRT_TORCH_KERNEL_ISA choice when not native, and its path."""
    if b.get("backend") != "native":
        return f"torch path ({b.get('why', '')})"
    return (f"{b['isa']} build" + (f" (`PRT_TORCH_KERNEL_ISA={b['isa_choice']}`)" if b.get("isa_choice", "native") != "native" else "")
            + f": {b['path']}")


def merge_kernel_runs(res: dict, runs: list[dict]) -> None:
    """``res``'s kernel runs with ``runs`` replacing those of the same CPU and build (first) and the others kept."""
    keys = {kernel_run_key(r) for r in runs}
    res["kernel_runs"] = runs + [r for r in kernel_runs(res) if kernel_run_key(r) not in keys]
    res.pop("kernel", None)
    res.pop("kernel_machine", None)


def isa_runs(spec: str) -> list[str]:
    """The kernel builds section 7 measures, each in its own process (``PRT_TORCH_KERNEL_ISA`` is read once per
    process): ``auto`` = this process's build, and also ``avx2`` where that build is AVX-512; else a comma list of
    native, avx2, avx512, avx512-256 (the first in this process, set here before the kernel is loaded). Each value
    is checked here (one line naming it and what this CPU accepts, status 2)."""
    from prt_torch._native import check_isa_list

    if spec == "auto":
        return ["", "avx2"] if relight.wavelet_kernel_path()["isa"] == "avx512" else [""]
    try:
        out = check_isa_list(spec)
    except ValueError as e:
        print(f"bench_wavelet.py: --isa {spec}: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    if out:
        os.environ["PRT_TORCH_KERNEL_ISA"] = out[0]  # this process's build (the kernel is not loaded yet)
    return out or [""]


def child_run(isa: str, size: str = "small") -> dict:
    """Section 7 at ``size`` in a child process with ``PRT_TORCH_KERNEL_ISA=isa``: its run."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run.json"
        cmd = [sys.executable, __file__, "--only", "kernel", "--size", size, "--child-json", str(out)]
        print(f"[wavelet] --- the kernel built for {isa}: {' '.join(cmd)}", flush=True)
        subprocess.run(cmd, env={**os.environ, "PRT_TORCH_KERNEL_ISA": isa}, check=True)
        return json.loads(out.read_text())


def kernel_only(isas: list[str], size: str = "small") -> None:
    """``--only kernel``: section 7 alone (the same transfer: R = 32, K = 256, BITS) on the mesh at ``size`` in each
    build of ``isas`` (the first in this process, the others in child processes), each run replacing the kept run of
    its own CPU, build and size in the existing wavelet.json (the others kept), and the report rewritten."""
    torch.set_num_threads(1)
    res = json.loads((OUT / "wavelet.json").read_text())
    res.setdefault("notes", [])
    note = ("Section \"Relight time vs N against the kernel's bound\" was re-run alone (`--only kernel`) with the dense / "
            "block-sparse kernel; the headline, selection and wavelet tables above it keep their relight times from the full "
            "run (the plain CSC kernel, 1.8-2.2x slower than the dense/CSC one that followed it).")
    if note not in res["notes"]:
        res["notes"].append(note)
    runs = [kernel_run(res["selection_default"], size)] + [child_run(isa, size) for isa in isas[1:]]
    merge_kernel_runs(res, runs)
    atomic_write_text(OUT / "wavelet.json", json.dumps(res, indent=1, default=str))
    keep_history(runs)
    write_md(res, False)
    print(f"[wavelet] wrote {OUT / 'wavelet.md'} (section 7: {', '.join(kernel_run_key(r) for r in runs)})", flush=True)


def keep_history(runs: list[dict]) -> None:
    """Section 7's ``runs`` added to reports/benchmarks/wavelet_kernel_history.json (``wavelet_history``: each with its
    start time, this checkout's kernel source and commit), so that section 7 can show each row across runs."""
    src, head = wavelet_history.kernel_source(), wavelet_history.git_head()
    n = wavelet_history.append([wavelet_history.record(r, cpu_label(r["machine"]), utc=r.get("utc") or wavelet_history.now_utc(),
                                                       time_from="run", source=src, commit=head) for r in runs])
    print(f"[wavelet] {n} run(s) added to {wavelet_history.HISTORY}", flush=True)


def bounds_table(run: dict) -> list[str]:
    """A kernel run's rows against each bound (the runs with the two-thread and cold pairings: ``--size`` runs):
    where the bytes live; one thread by CPU time — µs per call (the copy's / the read's), of the copy / of the read as
    the median of per-repeat ratios [the read's quartiles] and as the ratio of each side's fastest tenth of short
    samples, and the pairings' tries (:func:`steady_pair`); two threads (the kernel's fastest tenth; of the copy / of
    the read at two threads); cold (µs kernel / read; of the cold read [quartiles]). Else []."""
    rows = [r for r in run["rows"] if "of_read_bound_cold" in r]
    if not rows:
        return []
    L = [f"Where each bound stands ({run_size(run)}, V = {run.get('vertices', '?')}; one core's L2 "
         f"{run['machine'].get('l2_bytes', 0) / 2 ** 20:.0f} MiB, L3 as listed {run['machine'].get('l3_bytes', 0) / 2 ** 20:.0f} MiB):\n",
         "| light | N | bytes read + written | live in | 1 thr CPU µs (copy / read µs) | of copy / of read: median [read quartiles] "
         "| fastest tenth: of copy / of read | tries | 2 thr µs (fastest tenth) | of copy / of read (2 threads) | cold µs (read µs) "
         f"| of cold read [quartiles] | of the median-of-{READ_PICK} read (its µs) |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        q, qc = r["of_read_bound_cpu_1_q"], r["of_read_bound_cold_q"]
        fl = (f"{r['of_bound_cpu_1_floor']:.2f} / **{r['of_read_bound_cpu_1_floor']:.2f}**" if "of_read_bound_cpu_1_floor" in r else "—")
        tries = "{}, {}".format(*r["tries_cpu_1"]) if "tries_cpu_1" in r else "1, 1"
        L.append(f"| {_row_key(r)[0]} | {_n_kept(r)} | {r['bytes'] / 1e6:.2f} MB{'†' if 'factor_bytes' in r else ''} | {r.get('lives', '?')} | "
                 f"{r['relight_cpu_s_1'] * 1e6:.0f} ({r['copy_bound_cpu_s_1'] * 1e6:.0f} / {r['read_bound_cpu_s_1'] * 1e6:.0f}) | "
                 f"{r['of_bound_cpu_1']:.2f} / **{r['of_read_bound_cpu_1']:.2f}** [{q[0]:.2f}, {q[1]:.2f}] | {fl} | {tries} | "
                 f"{r['relight_floor_s_2'] * 1e6:.0f} | {r['of_bound_2']:.2f} / **{r['of_read_bound_2']:.2f}** | "
                 f"{r['relight_cold_s'] * 1e6:.0f} ({r['read_bound_cold_s'] * 1e6:.0f}) | **{r['of_read_bound_cold']:.2f}** "
                 f"[{qc[0]:.2f}, {qc[1]:.2f}] | "
                 + (f"{r['of_read_pick_cpu_1']:.2f} ({r['read_pick_cpu_s_1'] * 1e6:.1f})" if "of_read_pick_cpu_1" in r else "—")
                 + " |")
    return L + [""]


def plot(res: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    K = max(r["K"] for r in res["wavelet"])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4))
    for i, name in enumerate(res["lights"]):
        w = [r for r in res["wavelet"] if r["light"] == name and r["K"] == K and r["selection"] == res["selection_default"]]
        s = [r for r in res["sh"] if r["light"] == name]
        c = f"C{i}"
        ax[0].loglog([r["N"] for r in w], [r["error"] for r in w], "-o", color=c, label=f"{name} wavelets")
        ax[0].loglog([r["bands"] ** 2 for r in s], [r["error"] for r in s], "--s", color=c, label=f"{name} SH")
        ax[1].loglog([r["relight_s"] * 1e3 for r in w], [r["error"] for r in w], "-o", color=c)
        ax[1].loglog([r["relight_s"] * 1e3 for r in s], [r["error"] for r in s], "--s", color=c)
    ax[0].set_xlabel("terms (wavelets: N light terms; SH: n² coefficients)")
    ax[1].set_xlabel("relight time per light (ms, one thread)")
    for a in ax:
        a.set_ylabel("relative L2 error vs exact")
        a.axhline(0.05, color="grey", lw=0.5)
        a.axhline(0.01, color="grey", lw=0.5)
    ax[0].legend(fontsize=6)
    fig.suptitle(f"occluder_over_plane, R=32, K={K}, {BITS}-bit (solid: wavelets, {res['selection_default']}; dashed: SH 3-10 bands)")
    fig.tight_layout()
    fig.savefig(OUT / "wavelet.png", dpi=90)


def _ms(x: float) -> str:
    return f"{x * 1e3:.3f} ms"


def write_md(res: dict, quick: bool) -> None:
    m = res["machine"]
    la = res["load_average"]
    K = max(r["K"] for r in res["wavelet"])
    busy = max(la) > 0.75 * m["cores"]  # another job held most of a core (the same rule as prt_torch.busy_now)
    L = []
    L.append("# All-frequency relighting: Haar wavelets on cube maps vs SH (issue 39)\n")
    L.append(f"`benchmarks/bench_wavelet.py{' --quick' if quick else ''}` on {m['cpu']} ({m['cores']} cores), torch "
             f"{m['torch']}, one torch thread; load average {la[0]:.1f} before and {la[-1]:.1f} after "
             + ("(the machine was shared with other jobs: absolute times are inflated, ratios measured in the same run are "
                "what to read). " if busy else "(a quiet machine). ")
             + f"Scene `{res['scene']['name']}` (small, {res['scene']['vertices']} vertices: the course's blocker over a "
             "receiver plane). Lights rasterised onto the cube (not band-limited): "
             + ", ".join(f"{k} (`{v}`)" for k, v in res["lights"].items()) + ". Errors: relative L2 over vertices and "
             "RGB against the exact pixel-basis result at the same R (all 6R² terms, float64).\n")
    for note in res.get("notes", []):  # sections re-run alone (--only) after the full run
        L.append(f"> {note}\n")
    h = res["headline"]
    L.append(f"## Headline: relight time to reach 5% and 1% error, SH vs wavelets (R = 32, K = {K}, {BITS}-bit values, "
             f"{res['selection_default']} selection)\n")
    L.append("Times: medians of separate runs" + (" (inflated on the busy machine)" if busy else "") + "; the ratio columns are SH's time over the "
             "wavelets' for those two settings, timed paired in the same run (interleaved short samples, fastest tenth of "
             "each; > 1: wavelets faster; ⚠: measured under contention).\n")
    L.append("| light | SH to 5% | wavelets to 5% | SH/wavelet (paired) | SH to 1% | wavelets to 1% | SH/wavelet (paired) | "
             "best SH error (10 bands) | best wavelet error |")
    L.append("|---|---|---|---|---|---|---|---|---|")
    for r in h:
        cells = [r["light"]]
        for tgt in (0.05, 0.01):
            s, w = r[f"sh_{tgt}"], r[f"wavelet_{tgt}"]
            cells.append("not reached" if s is None else f"{s['bands']} bands, {_ms(s['relight_s'])}")
            cells.append("not reached" if w is None else f"N={w['N']}, {_ms(w['relight_s'])}")
            pr = r.get(f"paired_{tgt}")
            cells.append(f"{pr['sh_over_wavelet']:.2f}{'' if pr['trusted'] else ' ⚠'}" if pr else "—")
        cells += [f"{r['sh_best_error']:.3f}", f"{r['wavelet_best_error']:.3f}"]
        L.append("| " + " | ".join(cells) + " |")
    L.append("")
    L.append("![error vs terms and vs relight time](wavelet.png)\n")
    L.append("## Light-term selection (Ng 2003 §5)\n")
    L.append("Mean of log(error) over every light, K and N per selection: "
             + ", ".join(f"{s} {v:.3f}" for s, v in res["selection_mean_log_error"].items())
             + f" → default **{res['selection_default']}** (`select_terms`, `prt relight --selection`).\n")
    L.append("| light | K | N | magnitude | area | transport |")
    L.append("|---|---|---|---|---|---|")
    for name in res["lights"]:
        for N in TERMS:
            cells = [name, str(K), str(N)]
            for s in SELECTIONS:
                r = [x for x in res["wavelet"] if x["light"] == name and x["K"] == K and x["N"] == N and x["selection"] == s]
                cells.append(f"{r[0]['error']:.4f}" if r else "—")
            L.append("| " + " | ".join(cells) + " |")
    L.append("")
    L.append(f"## Wavelets: error, relight time and bytes per vertex ({res['selection_default']} selection, {BITS}-bit values)\n")
    L.append("| light | K | bytes/vertex | N | error | relight | coefficients read |")
    L.append("|---|---|---|---|---|---|---|")
    for r in res["wavelet"]:
        if r["selection"] == res["selection_default"]:
            L.append(f"| {r['light']} | {r['K']} | {r['bytes_per_vertex']} | {_n_kept(r)} | {r['error']:.4f} | "
                     f"{_ms(r['relight_s'])} | {r['touched']} |")
    L.append("")
    L.append("## SH at 3–10 bands, projected from the same visibility\n")
    L.append("| light | bands | bytes/vertex | error | relight |")
    L.append("|---|---|---|---|---|")
    for r in res["sh"]:
        L.append(f"| {r['light']} | {r['bands']} | {r['bytes_per_vertex']} | {r['error']:.4f} | {_ms(r['relight_s'])} |")
    L.append("")
    L.append("## Bytes per vertex vs error (all light terms: the transfer's truncation and quantisation alone)\n")
    ref = max(r["res"] for r in res["bytes_vs_error"])
    L.append(f"| R | K | bits | bytes/vertex | mean error (same R) | max error (same R) | mean error vs R={ref} exact |")
    L.append("|---|---|---|---|---|---|---|")
    for r in res["bytes_vs_error"]:
        L.append(f"| {r['res']} | {r['K']} | {r['bits']} | {r['bytes_per_vertex']} | {r['error_mean']:.4f} | "
                 f"{r['error_max']:.4f} | {r[f'error_vs_R{ref}_mean']:.4f} |")
    L.append("")
    p = res["precompute"]
    L.append("## Precompute against bare Embree\n")
    L.append(f"R = {p['res']}, K = {p['terms']}, 8 bits, {p['rays']} rays, one worker: the whole precompute "
             f"{p['precompute_s']:.2f} s; bare Embree tracing the same rays runs at **{p['bare_over_precompute']:.2f}** "
             f"of the precompute's time (paired, spread {p['spread']:.2f}{'' if p['trusted'] else ', ⚠ contention'}): "
             "the rest is ray generation, the Haar transform, top-K and quantisation.\n")
    L.append(f"## Relight time vs N against the kernel's bound (studio and sky, R = 32, K = 256, {BITS}-bit)\n")
    L.append(
             "One section per CPU and kernel build (`relight.wavelet_kernel_path`, from the library's own `prt_wavelet_isa`: "
             "on an AVX-512 CPU the dense loop runs on 16-lane vectors, on an AVX2 one on 8 lanes; `PRT_TORCH_KERNEL_ISA=avx2` "
             "builds the AVX2 code on an AVX-512 CPU): `--only kernel` replaces the section of its own CPU and build and keeps "
             "the others, `--isa auto` also runs the avx2 build where the native one is AVX-512. Each CPU precomputes the "
             "transfer itself (the bytes column says what each run read). Two lights: studio (a few small sources: 292 "
             "nonzero Haar terms at R = 32) and sky (a sun over a sky: 3072 nonzero terms, its lower hemisphere zero). "
             "A light keeps only its nonzero terms (`haar.select_terms`, `ZERO_TERM`), so studio's N = 300 and above "
             "time its 292 terms once (\"N (292 kept)\"), and sky's rows time what N = 300-2000 real terms cost. "
             "Rows of runs before that rule (the AMD EPYC's below) ranked a light's round-off terms too, which each "
             "machine's floating point orders its own way (studio at N = 1000: 0.97 MB read on the AMD EPYC, 1.49 MB on "
             "the Intel Xeon, for the same result). Compare fractions of each run's own bounds, not times across CPUs. "
             "The kernel reads each Haar column of the light's terms in the form stored for it "
             "(`relight.WaveletRelighter`): *dense* (32-vertex blocks of the stored values, zeros included, no index: "
             "the columns most vertices keep, the coarse levels; from 2 MiB up in memory advised for 2 MiB transparent huge "
             "pages, `PRT_TORCH_HUGEPAGES=0`: torch's buffer, reports/benchmarks/wavelet_hugepages.md; each run names "
             "its pages, runs before them had 4 KB pages) or *block-sparse* (per tile of vertices and column, "
             "the 8-vertex blocks holding a value: an int32 offset and 8 values, zeros included; two int32 pointers "
             "per tile and term — or, when the light's sparse terms hold at least `row_min` of all sparse blocks (the "
             "build's default, `WaveletRelighter.default_row_min`: 0.5 in the AVX2 build, "
             f"{relight.WaveletRelighter.ROW_MIN_W16:g} in the AVX-512 build with the 16-lane code, 0.5 in the runs "
             "before issue 39's per-build threshold; here N = 2000 and all either way), the row-major copy: every "
             "sparse block, int32 column + 8 values, summed in registers). "
             "Bytes read are that layout's and pass's, the output's included, and — rows marked † (`factor_bytes` in "
             "their JSON) — the factor the kernel reads once per call (the quantisation scale × albedo: one float per "
             "vertex on this grey scene, `WaveletRelighter.factor_bytes`); rows without † were timed before the bound "
             "counted it (the kernel then read 12 bytes per vertex of it, uncounted): compare a † row with one without "
             "only with that in mind (reports/benchmarks/wavelet_factor.md pairs both counts). Paired (interleaved short samples, "
             "fastest tenth of each side) with its own bound "
             "(the kernel timed through `WaveletRelighter.prepared`, the render-loop form whose per-call Python is one "
             "call; `relighter(idx, vals)` adds its checks: the last column, paired) "
             "— a copy of the bytes this layout reads and a fill of the output (`timing.io_bound_fn`), at the same "
             "torch thread count — and, at one thread, with the previous layout's bound (the same dense columns, "
             "the sparse ones as CSC (int32 offset, value) pairs padded to groups of 4: what the previous kernel "
             "reached 0.27–0.35 of). Two threads: the tiles split between them (OpenMP). **1 thr CPU time**: at one thread, "
             "the kernel and its bound paired by the calling thread's CPU time (`measure_paired(clock=time.thread_time)`, "
             "15 repeats: median of the per-repeat ratios and their quartiles): the time other processes held the core is "
             "in neither side, so on this shared machine it is the figure the load does not move (the wall-clock columns "
             "take the fastest tenth of short samples instead). **Last column**: the same one-thread CPU-time pairing "
             "against a stricter bound, the same bytes only read (a streaming int64 sum, `timing.read_bound_fn`) and the "
             "output filled — the copy behind every other column also writes each byte it reads —, and in brackets the "
             "read's time over the copy's. The copy moves twice the bytes through the caches (source and destination): "
             "once they outgrow the core's private cache it runs at the next level's speed while the kernel and the read "
             "still find most of their bytes there, so a fraction of the copy bound above 1 says that bound is slow "
             "there, not that the kernel beats memory — the streaming read is the bound to read then (on the Intel Xeon "
             "below, 2 MB of L2 per core, `reports/benchmarks/bound_sizes.md`: the copy fell from 32–34 GB/s at 0.5 MB to "
             "18 at 0.75 MB and 10–11 from 1.25 MB, the read from 50–79 GB/s up to 1 MB to 34 at 1.5 MB; a fresh "
             "destination per copy cost about the same, with no page fault per call: not first-touch faults).\n")
    L.append("**Sizes** (`--only kernel --size small|medium|large`): the same scene, transfer and lights on "
             "`occluder_over_plane` at ~2.3k (small, the default: every table without a size below), ~10.6k (medium) and ~51k "
             "(large) vertices, the sizes users relight; a run replaces only the rows of its own CPU, build and size. Runs at "
             "medium and large add, per row, a table of where each bound stands: the bytes read (and written) against one "
             "core's L2 and the L3 sysfs lists (between back-to-back calls of one thread the bytes live in the smallest that "
             "holds them); one thread by CPU time against the copy and against the streaming read (as above: the median of 15 "
             "per-repeat ratios, [the read's quartiles]; and the ratio of each side's fastest tenth of 40-160 short samples by "
             "CPU time, the samples other processes disturbed least — on this shared 2-core machine another process's time "
             "slice on this core evicts the L2 both sides use, and the refill after it is the thread's own CPU time; past "
             "the L2, the others' traffic in the shared L3 and memory slows both sides too; *tries*: a "
             "pairing whose per-repeat ratios spread more than 0.2 (relative quartile range) is timed again, up to three "
             "times, the steadiest kept); two threads "
             "(wall time, fastest tenth of short samples) against both at two threads; and **cold**: one thread by CPU time, "
             "each call of the kernel and of the streaming read after a flush of every byte the two hold "
             "(`timing.measure_paired_cold` with `evict=timing.working_set(...)`: the whole relighter's tensors and the "
             "bound's buffers, written back and evicted from every cache level, untimed), 15 pairs, median of the per-pair "
             "ratios and their quartiles: the memory-bandwidth bound.\n")
    hist = wavelet_history.load_history()
    if hist:
        L.append("### The criterion across runs\n")
        L.append("On a shared VM the streaming read moves 1.4-2.9x between machine states on the same code, the kernel "
                 "less, so one run's fraction depends on the hour. Every section-7 run is kept in "
                 "`wavelet_kernel_history.json` (`benchmarks/wavelet_history.py`; the runs committed before it "
                 "recorded from the report's git history, timed by their commit: `(commit)`) with its kernel source "
                 "(a hash of `wavelet.c`'s code, comments left out) and its state: the read speed of the "
                 f"{wavelet_history.REF_ROW[0]} N = {wavelet_history.REF_ROW[1]} row (its bytes over the streaming "
                 "read's one-thread CPU time) and a streaming read of 0.5-4 MiB buffers at the run's start "
                 "(`wavelet_history.read_sweep`: where the read slows tells how much of the L2 the run had). "
                 "Below, per CPU, build and size: every run on one line, then each row "
                 "across the runs on this checkout's kernel source, with the median — the figure to judge a row by "
                 "(one thread's CPU time as a fraction of the streaming read).\n")
        L += wavelet_history.history_md(hist, wavelet_history.kernel_source())
    runs = kernel_runs(res)
    by_cpu: dict[tuple[str, str], list[dict]] = {}
    for run in runs:
        by_cpu.setdefault((cpu_label(run["machine"]), run_size(run)), []).append(run)
    for (cpu, size), rs in by_cpu.items():  # the builds of one CPU and size side by side (one thread, CPU time)
        if len(rs) < 2:
            continue
        at = "" if size == "small" else f" at {size} (V = {rs[0].get('vertices', '?')})"
        L.append(f"### {cpu}{at}: the kernel builds side by side (1 thread CPU time: µs per call; of the copy bound / of the "
                 "streaming read)\n")
        L.append("Each build's run has its own bounds, timed in its own process (its rows below); the builds paired on one "
                 "layout in one process: `benchmarks/bench_wavelet_isa.py` (reports/benchmarks/wavelet_isa.md).\n")
        L.append("| light | N | " + " | ".join(build_label(r["build"]) for r in rs) + " |")
        L.append("|---|---|" + "---|" * len(rs))
        for r0 in rs[0]["rows"]:
            cells = []
            for run in rs:
                x = next((r for r in run["rows"] if _row_key(r) == _row_key(r0)), None)
                cells.append(f"{x['relight_cpu_s_1'] * 1e6:.1f} µs; {x['of_bound_cpu_1']:.2f} / {x['of_read_bound_cpu_1']:.2f}"
                             if x and "of_read_bound_cpu_1" in x else "—")
            L.append(f"| {_row_key(r0)[0]} | {_n_kept(r0)} | " + " | ".join(cells) + " |")
        L.append("")
    for run in runs:
        km, rows = run["machine"], run["rows"]
        at = "" if run_size(run) == "small" else f" · {run_size(run)}, V = {run.get('vertices', '?')}"
        L.append(f"### {cpu_label(km)} · {build_label(run.get('build') or {})}{at}\n")
        L.append(f"{km['cpu']}, {km['cores']} cores, one and two threads; load average "
                 f"{km.get('load_before', km.get('load_average_1min', float('nan'))):.1f} → "
                 f"{km.get('load_after', km.get('load_average_1min', float('nan'))):.1f}"
                 + (" (⚠: the pairing flagged contention)." if not all(r["trusted"] for r in rows) else ".")
                 + (f" Rows: {run['source']}." if run.get("source") else "")
                 + (f" Precompute {run['precompute_s']:.0f} s (one worker)." if "precompute_s" in run else "")
                 + " Dense layout on " + run.get("dense_pages", "torch's buffer (4 KB pages; before huge pages)") + ".\n")
        L.append("| light | N | coefficients read | in dense columns | bytes read (this layout) | previous layout | 1 thread | of own bound "
                 "| **1 thr CPU time: of own bound** [quartiles] | of previous layout's bound | 2 threads | of own bound (2 threads) "
                 "| torch path | C / torch | load | plain call / prepared | 1 thr CPU time: of a streaming read (read / copy) |")
        L.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in rows:
            flag = "" if r["trusted"] else " ⚠"
            if "of_bound_2" not in r:  # a report from before the block-sparse layout
                continue
            cp = f"{r['call_over_prepared']:.2f}×{flag}" if "call_over_prepared" in r else "—"
            cpu_t = (f"**{r['of_bound_cpu_1']:.2f}** [{r['of_bound_cpu_1_q'][0]:.2f}, {r['of_bound_cpu_1_q'][1]:.2f}]"
                     if "of_bound_cpu_1" in r else "—")
            rd = (f"{r['of_read_bound_cpu_1']:.2f} ({r['read_over_copy_1']:.2f})" if "of_read_bound_cpu_1" in r else "—")
            L.append(f"| {_row_key(r)[0]} | {_n_kept(r)} | {r['touched']} | {r['dense_coefficients']} ({r['dense_terms']} terms"
                     f"{', int16 VNNI' if r.get('dense') == 'int16 vnni' else ''}) | {r['bytes']}"
                     f"{'†' if 'factor_bytes' in r else ''} | "
                     f"{r['previous_bytes']} | {_ms(r['relight_s_1'])} | {r['of_bound_1']:.2f}{flag} | {cpu_t} | "
                     f"{r['of_previous_bound']:.2f}{flag} | {_ms(r['relight_s_2'])} | {r['of_bound_2']:.2f}{flag} | "
                     f"{_ms(r['torch_relight_s'])} | {r['torch_relight_s'] / r['relight_s']:.1f}× | {r['load']:.1f} | {cp} | {rd} |")
        L.append("")
        L += bounds_table(run)
    if "sampling" in res:
        sm = res["sampling"]
        L.append(f"## Texel sampling: grid vs jittered (R = {sm['res']}, {sm['vertices']} vertices)\n")
        L.append("Each texel's integral of visibility × cosine from s² rays: at the sub-texel centres (`--texel-sampling grid`) "
                 "or at one uniformly random point in each sub-texel, drawn anew per vertex and weighted by the face's "
                 "solid-angle density there (`--texel-sampling jittered`: unbiased). Exit radiance against the s = 8 grid "
                 "(64 rays per texel): relative L2 error / mean signed error (bias), per light; time for these vertices "
                 "(one worker" + (f", load {sm['load_before']:.1f} → {sm['load_after']:.1f}" if "load_before" in sm else "")
                 + ").\n")
        names = list(sm["rows"][0]["per_light"])
        L.append("| s | sampling | time | " + " | ".join(names) + " |")
        L.append("|---|---|---|" + "---|" * len(names))
        for r in sm["rows"]:
            L.append(f"| {r['s']} | {r['sampling']} | {r['seconds']:.1f} s | " + " | ".join(
                f"{r['per_light'][n]['error']:.4f} / {r['per_light'][n]['bias']:+.4f}" for n in names) + " |")
        L.append("")
    if "quant" in res:
        qr = res["quant"]["rows"]
        L.append(f"## Stored precision: the kept values' quantisation (R = {res['quant']['res']}, all light terms)\n")
        L.append("Each vertex keeps its K largest Haar coefficients (the same ones for every scheme); exit radiance under "
                 "the five lights against the exact pixel-basis result (all 6R² terms, float64): mean over lights of the "
                 "relative L2 error, with the truncation's error alone (float64 values). Schemes: signed integers with "
                 "one float32 scale per vertex (8 or 16 bits: the previous default, 8), 8-bit integers with one scale per "
                 "vertex and Haar level (log2(R)+1 = 6 scales; `--scales level`), 8-bit sign + e4m3 minifloat relative to "
                 "the vertex's largest value (measured here only), IEEE float16 without a scale (measured here only). "
                 "Indices int16.\n")
        schemes = list(dict.fromkeys(r["scheme"] for r in qr))
        L.append("| K | truncation alone | " + " | ".join(schemes) + " |")
        L.append("|---|---|" + "---|" * len(schemes))
        for K in sorted({r["K"] for r in qr}):
            rk = {r["scheme"]: r for r in qr if r["K"] == K}
            L.append(f"| {K} | {rk[schemes[0]]['truncation_mean_error']:.4f} | " + " | ".join(
                f"{rk[sc]['mean_error']:.4f} ({rk[sc]['bytes_per_vertex']} B)" for sc in schemes) + " |")
        L.append("")
    atomic_write_text(OUT / "wavelet.md", "\n".join(L) + "\n")


if __name__ == "__main__":
    main()
