"""Relighting straight from every compressed form against its memory-bandwidth bound (issue 15).

For every piecewise-affine codec (VQ 256, PCA 8, CPCA static / iterative / adaptive 256×8 on a
50 000-point 24×25 transfer-like signal, ``codecs.synthetic.transfer_like``; MRT-PCA with 16
vectors on a 50 000-point 49×25 MRT-like signal) and every view mode (none; dense ``[P, n_out]``;
MRT's four tent taps, Lehtinen & Kautz 2003 eq. (13)), one light per call ``[25, 3]``:

* **fraction of the bound** = bound time / relight time (1.0: at the bound; the goal is ≥ 0.5),
  where the bound is ``harness.timing.io_bound_fn(bytes read, bytes written)`` — a plain
  ``copy_`` of the bytes a relight must read once (the codec's stored bytes, model and codes,
  ``storage()['bytes_total']``, plus the view) and a ``fill_`` of the output's bytes — timed
  interleaved with the relight in the same run (``measure_paired``: median of per-repeat ratios),
  the relight writing into a reused result (``relight(..., out=)``, as a render loop does; the
  allocating call is the **new output** column);
* **compute floor** = the per-point multiply-adds at this machine's float32 rate, measured in the
  same run (a cache-resident 256³ GEMM, at the start and at the end, the faster kept), and **roofline** = max(bound, floor) / relight: where the
  floor is over twice the bound, no kernel meets the 0.5 goal on this CPU;
* **cold** = the same fraction with both sides from cold caches (``measure_paired_cold``: each
  call timed alone after flushing what both sides touch from the caches): the memory-bandwidth bound proper,
  where the back-to-back repeats above keep the 20–50 MB of a row largely in the L3;
* **of peak** / **goal needs** = compute floor / relight, and compute floor / (2 × bound): the
  share of the peak rate the kernel sustains, and the share the 0.5 goal would need;
* **vs uncompressed** = time of the reference path on the decoded matrices
  (``relight.apply_dense`` / ``apply_taps``, or ``M @ l`` without a view) / relight time, also paired;
* the same fraction for the torch formulation (``PRT_TORCH_NATIVE=0``: no compiled kernels),
  the path taken on a machine without a C compiler.

The codecs are fitted on the first 8 000 points and then encode all 50 000 (relighting cost
depends on P, K, n_k and the shapes, not on the fitted values; a full 50k × 600 iterative fit
takes minutes). Fits are cached in ``--cache`` (default: a directory in the system temp dir).
The Gaussian codec (Green 2005) relights from the same light prefiltered with spherical Gaussians
(``lighting.prefilter_environment``, 20 widths, 6×16×16): 1 and 3 lobes per function, 92 stored
views per vertex (Green's icosphere), fitted to synthetic mixtures on 64 vertices and tiled to the
50 000 (``gaussian_fitted``); every stored view (no view: ``[P, 92, C]``) and three-view taps of a
camera (``gaussian_view``). Its taps read only the tapped views' lobes, which is the bound's byte
count; it has no uncompressed column here (the 92 × 384-texel tables of 50 000 vertices are 7 GB:
benchmarks/bench_gaussian.py compares with the uncompressed tables on a real mesh).

Threads: ``--threads`` (default 2, the project's target machine); OpenMP's wait policy is the
package's choice (``import prt_torch`` first, as for any user). The load average is recorded before and after, and each paired measurement
records its contention (``trusted`` false: busy machine).

Per CPU and kernel build (issue 42 §4): every row records the CPU (model name, family/model, widest vector
ISA: ``harness.timing.cpu_label``) and the code it ran (``codec.kernel_path``: the build's ISA and the point
kernel of its plan, from the kernels' own dispatch); at one thread it is also timed by the thread's CPU time
(the column a shared machine cannot stretch). relight.json keeps one run per CPU and build, a new run
replacing its own; ``--isa auto`` (default) also runs the ``avx512-256`` and ``avx2`` builds (``PRT_TORCH_KERNEL_ISA``, each in a
child process) where the native one is AVX-512, and the report then puts the builds' fractions side by side.

Run: .venv/bin/python benchmarks/bench_relight.py   (a few minutes; --quick: 5 000 points, prints only;
--no-gaussian: skip the Gaussian rows, which take seconds per call without AVX-512)
Writes reports/benchmarks/relight.md and relight.json.
"""
from __future__ import annotations

import os

import prt_torch  # noqa: E402,F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import hashlib  # noqa: E402
import json  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs, relight  # noqa: E402
from prt_torch.codecs.relight_kernels import kernel_path, native_status  # noqa: E402
from prt_torch.codecs.synthetic import tent_taps_random, transfer_like  # noqa: E402
from prt_torch.harness.timing import cpu_label, io_bound_fn, machine_info, measure_paired, measure_paired_cold, working_set  # noqa: E402
from prt_torch.io import atomic_write_json, atomic_write_text  # noqa: E402
from prt_torch.lighting import prefilter_environment  # noqa: E402

OUT = Path(__file__).resolve().parent.parent / "reports" / "benchmarks"
FIT_POINTS = 8000


def settings(quick: bool) -> list[tuple[str, str, dict, str]]:
    """(label, codec name, parameters, signal) of every codec benchmarked."""
    K = 64 if quick else 256
    return [
        (f"vq {K}", "vq", {"clusters": K, "max_iter": 10}, "glossy"),
        ("pca 8", "pca", {"vectors": 8}, "glossy"),
        (f"cpca static {K}x8", "cpca_static", {"clusters": K, "vectors": 8, "max_iter": 10}, "glossy"),
        (f"cpca iterative {K}x8", "cpca_iterative", {"clusters": K, "vectors": 8, "max_iter": 10, "iterations": 3}, "glossy"),
        (f"cpca adaptive {K}x8", "cpca_adaptive",
         {"clusters": K, "vectors": 8, "max_iter": 10, "iterations": 3, "adapt_iters": 2}, "glossy"),
        ("mrt_pca 16", "mrt_pca", {"vectors": 16}, "mrt"),
        # diffuse PRT: vectors of 16 SH coefficients, an RGB result per point (12 bytes out)
        (f"vq {K} (diffuse)", "vq", {"clusters": K, "max_iter": 10}, "diffuse"),
        ("pca 8 (diffuse)", "pca", {"vectors": 8}, "diffuse"),
        ("cpca static 64x4 (diffuse)", "cpca_static", {"clusters": 64, "vectors": 4, "max_iter": 10}, "diffuse"),
    ]


def fitted(name: str, params: dict, X: torch.Tensor, ms: tuple, cache: Path) -> tuple:
    """Fit on the first FIT_POINTS points, encode all; cached by (codec, params, signal hash)."""
    key = hashlib.sha256(json.dumps([name, params, list(X.shape), float(X[:64].double().sum()), FIT_POINTS]).encode()).hexdigest()[:16]
    path = cache / f"{name}-{key}.prt"
    if path.exists():
        return (*codecs.load(path), True)
    c = codecs.get(name, **params)
    c.fit(X[:FIT_POINTS], matrix_shape=ms)
    enc = c.encode(X)
    c.save(path, enc, overwrite=True)
    return c, enc, False


def peak_macs_per_s(repeats: int = 15) -> float:
    """The machine's float32 multiply-add rate at the current thread count, measured here: a
    cache-resident 256×256×256 GEMM (MKL, near the FMA units' peak), the fastest of ``repeats``
    samples — a capability, which other processes taking the cores only hide (a median taken on a
    busy moment made kernels look faster than the peak: "of peak" 1.25–1.35 at 2 threads)."""
    a, b = torch.randn(256, 256), torch.randn(256, 256)
    c = torch.empty(256, 256)
    for _ in range(3):
        torch.mm(a, b, out=c)
    # at one thread by this thread's CPU time (as the rows' CPU-time column): on a shared machine the wall clock's
    # fastest sample still held other processes' time (a load of 14 on 2 cores gave 10.6 GMAC/s for 46 idle,
    # and rooflines above 1)
    clock = time.thread_time if torch.get_num_threads() == 1 else time.perf_counter
    ts = []
    for _ in range(repeats):
        t0 = clock()
        for _ in range(20):
            torch.mm(a, b, out=c)
        ts.append((clock() - t0) / 20)
    return 256 ** 3 / min(ts)


def with_peak(r: dict, macs_per_s: float) -> dict:
    """The row's figures against the peak float32 rate: compute floor = its per-point multiply-adds
    at that rate; roofline = max(bound, floor) / relight; of peak = floor / relight; goal needs =
    floor / (2 × bound), the share of the peak the 0.5 goal asks for (> 1: unreachable on this CPU);
    cold roofline = max(cold bound, floor) / cold relight (both from cold caches)."""
    compute_ms = 1e3 * r["points"] * r["macs_per_point"] / macs_per_s
    r.update({"peak_macs_per_s": macs_per_s, "compute_floor_ms": compute_ms,
              "fraction_of_roofline": max(r["bound_ms"], compute_ms) / r["relight_ms"],
              "fraction_of_roofline_cold": max(r["bound_cold_ms"], compute_ms) / r["relight_cold_ms"],
              "fraction_of_roofline_cold_relighter": max(r["bound_cold_relighter_ms"], compute_ms) / r["relighter_cold_ms"],
              "peak_fraction": compute_ms / r["relight_ms"], "peak_fraction_goal_needs": compute_ms / (2 * r["bound_ms"])})
    # the roofline by the load-robust pair (one thread: CPU time; more: the fastest tenth), where the row has one
    t, b = ((r.get("relight_cpu_ms"), r.get("bound_cpu_ms")) if r.get("relight_cpu_ms") is not None
            else (r.get("relight_fastest_tenth_ms"), r.get("bound_fastest_tenth_ms")))
    r["fraction_of_roofline_robust"] = max(b, compute_ms) / t if t else None
    return r


def measure(c, enc, light, view, unc, repeats: int) -> dict:
    """The paired measurements of one row: the relight into a reused result (as a render loop
    calls it) and allocating it, against the bound — ``c.relight_bytes(enc, view)`` read, the
    output written — and against ``unc``, the uncompressed peer (None: not measured here)."""
    fresh_fn = lambda: c.relight(enc, light, view=view)  # noqa: E731
    buf = torch.empty_like(fresh_fn())
    fn = lambda: c.relight(enc, light, view=view, out=buf)  # noqa: E731  (a render loop's reused result)
    rb, wb = c.relight_bytes(enc, view), buf.numel() * buf.element_size()
    st = c.storage(enc)
    bound = io_bound_fn(rb, wb)
    b = measure_paired(fn, bound, repeats=repeats, warmup=2)
    # the same pair from cold caches (each call after an eviction): the memory-bandwidth bound
    # proper, where the back-to-back repeats above keep the data of either side in the L3
    cold = measure_paired_cold(fn, bound, repeats=max(15, repeats), warmup=1, evict=working_set(fn, bound))
    # relight allocating its result (first-touch page faults of a new tensor: significant when the
    # output is large, i.e. without a view) against the same bound
    fresh = measure_paired(fresh_fn, bound, repeats=max(3, repeats // 2), warmup=1)
    # a render loop's prepared form (Codec.relighter: the per-call checks done once), same bound
    rl = c.relighter(enc, view)
    prep = measure_paired(lambda: rl(light, out=buf), bound, repeats=repeats, warmup=2)
    prep_cold = measure_paired_cold(lambda: rl(light, out=buf), bound, repeats=max(15, repeats), warmup=1,
                                    evict=working_set(rl, light, buf, bound))
    # at one thread, the same pair timed by this thread's CPU time (timing.measure_paired's clock): the time other
    # processes held the core is in neither side, so on a shared machine this is the work ratio (the wall-clock
    # column above moves with the load; reports/benchmarks/timing_trust.md)
    cpu = measure_paired(fn, bound, repeats=repeats, warmup=1, clock=time.thread_time) if torch.get_num_threads() == 1 else None
    # and the prepared form's (issue 42 part 4: its goal is stated in CPU time too)
    cpu_prep = (measure_paired(lambda: rl(light, out=buf), bound, repeats=repeats, warmup=1, clock=time.thread_time)
                if torch.get_num_threads() == 1 else None)
    # the two render-loop forms against each other, paired (issue 42 §4: the prepared and relight fractions above come
    # from separate pairings minutes apart, and on a shared machine their bounds differ by more than the forms do):
    # relight time / prepared time, > 1: the prepared form faster; one thread by CPU time, else the wall clock
    pvr = measure_paired(lambda: rl(light, out=buf), fn, repeats=repeats, warmup=1,
                         clock=time.thread_time if torch.get_num_threads() == 1 else time.perf_counter)
    # with several threads, the wall-clock pair's fastest tenth (measure_paired's floor phase: short samples of equal
    # length, the ratio of the two sides' 10% quantiles): what a quiet machine would show, where a spinning parallel
    # region stalls whenever another process holds one of the cores (reports/benchmarks/timing_trust.md)
    fl = (measure_paired(fn, bound, repeats=3, warmup=1, floor_pairs=40, floor_max_pairs=160)
          if torch.get_num_threads() > 1 else None)
    u = measure_paired(fresh_fn, unc, repeats=repeats, warmup=1) if unc is not None else None
    out = fn().clone()
    prev = os.environ.get("PRT_TORCH_NATIVE")
    os.environ["PRT_TORCH_NATIVE"] = "0"
    try:
        ft = measure_paired(fn, bound, repeats=max(3, repeats // 2), warmup=1)
        ref_torch = fn()
    finally:
        if prev is None:
            del os.environ["PRT_TORCH_NATIVE"]
        else:
            os.environ["PRT_TORCH_NATIVE"] = prev
    return {"bytes_read": rb, "bytes_written": wb, "bytes_per_point": (rb + wb) / enc.points,
            "bytes_model": st["bytes_model"], "bytes_codes": st["bytes_codes"],
            "relight_ms": 1e3 * b.test.median, "bound_ms": 1e3 * b.peer.median,
            "fraction_of_bound": b.ratio.median, "fraction_q1_q3": [b.ratio.q1, b.ratio.q3],
            "fraction_cpu_time": cpu.ratio.median if cpu else None,
            "fraction_cpu_time_q1_q3": [cpu.ratio.q1, cpu.ratio.q3] if cpu else None,
            "fraction_relighter_cpu_time": cpu_prep.ratio.median if cpu_prep else None,
            "fraction_relighter_cpu_time_q1_q3": [cpu_prep.ratio.q1, cpu_prep.ratio.q3] if cpu_prep else None,
            "relight_cpu_ms": 1e3 * cpu.test.median if cpu else None, "bound_cpu_ms": 1e3 * cpu.peer.median if cpu else None,
            "prepared_vs_relight": pvr.ratio.median, "prepared_vs_relight_q1_q3": [pvr.ratio.q1, pvr.ratio.q3],
            "prepared_vs_relight_clock": "cpu" if cpu else "wall",
            "fraction_fastest_tenth": fl.speedup if fl else None,
            "relight_fastest_tenth_ms": 1e3 * fl.floor["test_s"] if fl else None,
            "bound_fastest_tenth_ms": 1e3 * fl.floor["peer_s"] if fl else None,
            "relight_new_output_ms": 1e3 * fresh.test.median, "fraction_new_output": fresh.ratio.median,
            "relighter_ms": 1e3 * prep.test.median, "fraction_relighter": prep.ratio.median,
            "fraction_relighter_q1_q3": [prep.ratio.q1, prep.ratio.q3],
            "relighter_cold_ms": 1e3 * prep_cold.test.median, "bound_cold_relighter_ms": 1e3 * prep_cold.peer.median,
            "relight_cold_ms": 1e3 * cold.test.median, "bound_cold_ms": 1e3 * cold.peer.median,
            "fraction_cold": cold.ratio.median, "fraction_cold_q1_q3": [cold.ratio.q1, cold.ratio.q3],
            "uncompressed_ms": 1e3 * u.peer.median if u else None, "speedup_vs_uncompressed": u.ratio.median if u else None,
            "torch_path_ms": 1e3 * ft.test.median, "torch_path_fraction_of_bound": ft.ratio.median,
            "native_vs_torch_max_abs_diff": float((out - ref_torch).abs().max()),
            "output_max_abs": float(out.abs().max()),
            "contention": b.contention, "timing": b.as_dict()}


def row(label, c, enc, light, view, mode, unc, repeats) -> dict:
    st = c.storage(enc)
    n_out = c.matrix_shape_[0] if c.matrix_shape_ else 1
    # terms per point: the mean and the weights actually stored (CPCA adaptive: n_k of the point's
    # cluster, 8.05 on average here, not the largest n_k)
    J = st["vectors_mean_per_point"] + (1 if c.means_ is not None else 0)
    C = light.shape[1]
    if mode == "taps":  # gather-sum of t rows of J·C, then J·C
        macs = (view[0].shape[1] + 1) * J * C
    else:  # e_p (J·n_out·C), then the view's dot (n_out·C)
        macs = J * n_out * C + (n_out * C if mode == "dense" else 0)
    return {"codec": label, "view": mode, "points": enc.points, "macs_per_point": macs, "cpu": cpu_label(),
            "kernel": c.kernel_path(enc, view, C=C), **measure(c, enc, light, view, unc, repeats)}


GAUSS_VIEWS, GAUSS_RES, GAUSS_FIT = 92, 8, 64


def gaussian_fitted(lobes: int, P: int) -> tuple:
    """The Gaussian codec (Green 2005) fitted to synthetic transport tables of ``GAUSS_FIT``
    vertices (92 views, Green's icosphere; 6×8×8 texels; every function a mixture of ``lobes``
    random spherical Gaussians), the encoding tiled to ``P`` vertices: relighting cost depends
    on V, J, N and the views, not on the fitted values (a fit of 50k × 92 functions takes minutes)."""
    import warnings

    from prt_torch.codecs.gaussian import mixture
    from prt_torch.lighting.prefilter import cube_map_directions

    d, _ = cube_map_directions(GAUSS_RES)
    d = d.reshape(-1, 3)
    g = torch.Generator().manual_seed(5)
    n = GAUSS_FIT * GAUSS_VIEWS
    mu = torch.nn.functional.normalize(torch.randn(n, lobes, 3, generator=g, dtype=torch.float64), dim=-1)
    sg = torch.empty(n, lobes, dtype=torch.float64).uniform_(0.2, 0.8, generator=g)
    w = torch.empty(n, lobes, dtype=torch.float64).uniform_(0.5, 1.5, generator=g)
    T = mixture(d, w, mu, sg).reshape(GAUSS_FIT, -1).float()
    c = codecs.get("gaussian", lobes=lobes)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(T, matrix_shape=(GAUSS_VIEWS, d.shape[0]))
    return c, tile_encoding(enc, P)


def tile_encoding(enc, P: int):
    """``enc`` with its per-vertex tensors repeated to ``P`` vertices (relighting cost does not
    depend on the values; shared with benchmarks/bench_gaussian.py)."""
    rep = -(-P // enc.points)
    axis = {"lobes_by_view": 1}  # the vertex axis of view-major records [J, V, N, 5]; 0 for the rest
    enc.tensors = {k: v.repeat(*[rep if d == axis.get(k, 0) else 1 for d in range(v.ndim)]).narrow(axis.get(k, 0), 0, P).contiguous()
                   for k, v in enc.tensors.items()}
    enc.cache.clear()
    enc.meta["points"] = P
    return enc


def gaussian_view(c, P: int) -> tuple:
    """Taps ``(idx int64 [P, 3], a float32 [P, 3])`` over the stored views for a camera at
    (0, −4, 2) looking at P points on the unit sphere (Fibonacci order: neighbouring indices
    see the camera from similar directions, as a mesh's vertex order does)."""
    from prt_torch.codecs.gaussian import fibonacci_directions, view_taps

    pts = fibonacci_directions(P)
    v = torch.tensor([0.0, -4.0, 2.0], dtype=torch.float64) - pts
    idx, a = view_taps(c.views_, v / v.norm(dim=-1, keepdim=True))
    return idx.contiguous(), a.contiguous()


def gaussian_row(label, c, enc, pe, view, mode, repeats) -> dict:
    """One Gaussian row. Bytes read (``GaussianCodec.relight_bytes``): without a view every stored
    lobe; with taps only the tapped views' lobes (k·N·5 floats per vertex: the other views' are
    never touched, so the whole encoding would be a bound 30× too loose) and the taps. MACs: per
    lobe the trilinear lookup (8 texels × C), with taps also the blend (5 floats × k)."""
    P, J, N = c.lobes_of(enc)[0].shape
    C = pe.channels
    macs = J * N * 8 * C if view is None else N * (8 * C + 5 * view[0].shape[1])
    k = kernel_path()
    if k["backend"] == "native":  # sg_lookup.c: 16 lobes per vector where sg_texels.h has SG16 (AVX-512F + VL)
        k["path"] = ("sg: 16 lobes per vector (AVX-512)" if k.get("sg16") else "sg: one lobe at a time") + (
            ", taps blended" if view is not None else "")
    return {"codec": label, "view": mode, "points": P, "macs_per_point": macs, "cpu": cpu_label(), "kernel": k,
            **measure(c, enc, pe, view, None, repeats)}


def print_row(r: dict) -> None:
    u = r["speedup_vs_uncompressed"]
    cpu = f" cpu-time {r['fraction_cpu_time']:.2f}" if r.get("fraction_cpu_time") is not None else ""
    print(f"[{r['cpu']} | {kernel_label(r)}]{cpu}")
    print(f"{r['codec']:22s} {r['view']:6s} {r['threads']} thr  relight {r['relight_ms']:7.3f} ms  bound {r['bound_ms']:6.3f} ms  "
          f"fraction {r['fraction_of_bound']:.2f} (prepared {r['fraction_relighter']:.2f}, cold {r['fraction_cold']:.2f}, "
          f"new output {r['fraction_new_output']:.2f}, "
          f"roofline {r['fraction_of_roofline']:.2f})  torch path {r['torch_path_fraction_of_bound']:.2f}"
          + (f"  vs uncompressed {u:.1f}x" if u is not None else "") + f"  load {os.getloadavg()[0]:.1f}", flush=True)


def kernel_label(r: dict) -> str:
    """A row's kernel path in one line: the build's ISA and the point kernel it ran (rows of runs
    before issue 42 §4 did not record it)."""
    k = r.get("kernel")
    if not k:
        return "not recorded"
    if k["backend"] != "native":
        return f"torch ({k.get('why') or k.get('path')})"
    build = k["isa"] + ("" if k.get("isa_choice", "native") == "native" else f" (PRT_TORCH_KERNEL_ISA={k['isa_choice']})")
    return f"{build} build: {k.get('path', '?')}"


def isa_runs(spec: str) -> list[str]:
    """The kernel builds a run measures, each in its own process (``PRT_TORCH_KERNEL_ISA`` is read once per
    process): ``auto`` = this process's build, and also ``avx512-256`` (AVX-512VL without the 16-lane kernels)
    and ``avx2`` where that build is AVX-512 (the alternatives issue 42 §4 asks to settle on AMD Zen 4); else a
    comma list of native, avx2, avx512, avx512-256 (the first in this process). Each value is checked here
    (one line naming it and what this CPU accepts, status 2)."""
    from prt_torch._native import check_isa_list

    if spec == "auto":
        return ["", "avx512-256", "avx2"] if kernel_path()["isa"] == "avx512" else [""]
    try:
        out = check_isa_list(spec)
    except ValueError as e:
        print(f"bench_relight.py: --isa {spec}: {e}", file=sys.stderr)
        raise SystemExit(2) from None
    return out


def child_run(isa: str, args) -> dict:
    """This benchmark in a child process with ``PRT_TORCH_KERNEL_ISA=isa``: its result."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "run.json"
        cmd = [sys.executable, __file__, "--threads", str(args.threads), "--repeats", str(args.repeats), "--cache", args.cache,
               "--only", args.only, "--child-json", str(out)] + (["--quick"] if args.quick else []) + (
            ["--no-gaussian"] if args.no_gaussian else [])
        print(f"--- kernels built for {isa}: {' '.join(cmd)}", flush=True)
        subprocess.run(cmd, env={**os.environ, "PRT_TORCH_KERNEL_ISA": isa}, check=True)
        return json.loads(out.read_text())


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="5 000 points, 64 clusters; print, write nothing")
    ap.add_argument("--threads", default="2", help="torch/kernel threads; a comma list (e.g. 1,2) measures each")
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--only", default="", help="measure only codecs whose label contains this text (prints, writes nothing "
                    "unless --merge)")
    ap.add_argument("--merge", action="store_true", help="with --only: put the re-measured rows in place of the same rows "
                    "(codec, view, threads) of the kept run of this CPU and build, and write the report; the section then "
                    "lists them with their load and command")
    ap.add_argument("--cache", default=os.path.join(tempfile.gettempdir(), "prt_bench_relight"))
    ap.add_argument("--isa", default="auto", help="kernel builds to measure, each in its own process: auto (this CPU's "
                    "native build, and also avx512-256 and avx2 where native is AVX-512), or a comma list of native, avx2, "
                    "avx512, avx512-256 (PRT_TORCH_KERNEL_ISA; docs/codecs.md)")
    ap.add_argument("--no-gaussian", action="store_true", help="skip the Gaussian codec's rows (without AVX-512 its lookups "
                    "run one lobe at a time: 3 lobes at 50 000 points take seconds per call)")
    ap.add_argument("--child-json", default="", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child_json:  # one build's run for a parent (child_run): the result as JSON, nothing else written
        atomic_write_json(Path(args.child_json), run(args))
        return 0
    isas = isa_runs(args.isa)
    if isas[0]:
        os.environ["PRT_TORCH_KERNEL_ISA"] = isas[0]  # before the kernels are first loaded in this process
    if args.merge and (not args.only or args.quick):
        raise SystemExit(f"bench_relight: --merge with --only {args.only!r}{' and --quick' if args.quick else ''}; accepted: "
                         "--merge with a non-empty --only and without --quick (rows re-measured at full size)")
    results = [run(args)] + [child_run(isa, args) for isa in isas[1:]]
    text = report_all(results)
    if args.quick or (args.only and not args.merge):
        print(text)
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    if args.merge:
        runs = merge_rows(OUT / "relight.json", results, " ".join(sys.argv[1:]))
        atomic_write_json(OUT / "relight.json", {"runs": runs})
        atomic_write_text(OUT / "relight.md", report_all(runs))
        print(text)
        print(f"merged {sum(len(r['rows']) for r in results)} row(s) into {OUT / 'relight.md'}")
        return 0
    runs = merge_runs(OUT / "relight.json", results)
    atomic_write_json(OUT / "relight.json", {"runs": runs})
    atomic_write_text(OUT / "relight.md", report_all(runs))
    print(f"wrote {OUT / 'relight.md'}: {len(runs)} run(s) ({', '.join(run_key(r) for r in runs)})")
    return 0


def run_key(r: dict) -> str:
    """A run's CPU and kernel build: a new run replaces a kept one of the same key."""
    b = r.get("kernel_build") or {}
    return cpu_label(r["machine"]) + (f", kernels {b.get('isa')}" + (f" (PRT_TORCH_KERNEL_ISA={b['isa_choice']})"
                                      if b.get("isa_choice", "native") != "native" else "") if b else "")


def merge_runs(path: Path, results: list[dict]) -> list[dict]:
    """The runs kept in ``path`` (one run per CPU and kernel build; a file of one run from before issue 42 §4 is
    that run) with ``results`` replacing those of the same key and the others appended."""
    runs: list[dict] = []
    if path.exists():
        old = json.loads(path.read_text())
        runs = old.get("runs", [old] if "rows" in old else [])
    keys = [run_key(r) for r in results]
    kept = [r for r in runs if run_key(r) not in keys]
    return results + kept


def merge_rows(path: Path, results: list[dict], command: str) -> list[dict]:
    """The runs kept in ``path`` with each of ``results``' rows (a ``--only`` run) in place of the row of the same
    codec, view and threads in the kept run of the same key (appended where it has none), its fits likewise, and a
    note of the re-measured rows, their load and the command in that run's ``reruns``; a key with no kept run is
    added as it is. Refused where the kept run measured another point count."""
    runs = merge_runs(path, []) if path.exists() else []
    for res in results:
        key = run_key(res)
        kept = next((r for r in runs if run_key(r) == key), None)
        if kept is None:
            runs.insert(0, res)
            continue
        if kept.get("points") != res["points"]:
            raise SystemExit(f"bench_relight: --merge into a run of {kept.get('points')} points from one of {res['points']} points; "
                             "accepted: the same point count")
        ident = lambda x: (x["codec"], x["view"], x["threads"])  # noqa: E731
        for new in res["rows"]:
            idx = next((i for i, x in enumerate(kept["rows"]) if ident(x) == ident(new)), None)
            if idx is None:
                kept["rows"].append(new)
            else:
                kept["rows"][idx] = new
        for f in res["fits"]:
            idx = next((i for i, x in enumerate(kept["fits"]) if x["codec"] == f["codec"]), None)
            if idx is None:
                kept["fits"].append(f)
            else:
                kept["fits"][idx] = f
        names = [f"{x['codec']} {x['view']} {x['threads']} thr" for x in res["rows"]]
        for rr in kept.get("reruns", []):  # an earlier rerun's rows measured again are this one's now
            rr["rows"] = [n for n in rr["rows"] if n not in names]
        kept["reruns"] = [rr for rr in kept.get("reruns", []) if rr["rows"]]
        kept["reruns"].append({
            "rows": names, "command": command,
            "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "load_average_before": res["load_average_before"],
            "load_average_after": res["load_average_after"], "kernels": res["native"]["detail"]})
    return runs


def run(args) -> dict:
    """Every row of this process's kernel build: the result dict (rows, fits, machine, peaks, loads)."""
    threads = [int(t) for t in str(args.threads).split(",")]
    torch.set_num_threads(max(threads))
    load0 = os.getloadavg()
    t_all = time.perf_counter()
    cache = Path(args.cache)
    cache.mkdir(parents=True, exist_ok=True)
    P = 5000 if args.quick else 50000
    X = transfer_like(P, 24, 25, seed=0)
    Mm = 7
    A = transfer_like(P, Mm * Mm, 25, seed=3)
    signals = {"glossy": (X, (24, 25)), "mrt": (A, (Mm * Mm, 25)), "diffuse": (transfer_like(P, 1, 16, seed=5), None)}
    g = torch.Generator().manual_seed(0)
    light = torch.randn(25, 3, generator=g) * torch.exp(-0.5 * torch.tensor([float(int(i ** 0.5)) for i in range(25)]))[:, None]
    views = {"glossy": torch.randn(P, 24, generator=g), "mrt": torch.randn(P, Mm * Mm, generator=g)}
    taps = tent_taps_random(P, Mm, seed=4)
    result: dict = {"machine": machine_info(), "omp_wait_policy": prt_torch.OMP_POLICY_CHOICE,
                    "threads": threads, "load_average_before": load0, "points": P, "fit_points": FIT_POINTS,
                    "native": native_status(), "kernel_build": kernel_path(), "quick": args.quick, "fits": [], "rows": []}
    print("kernels:", result["native"]["detail"], flush=True)
    peaks: dict[int, float] = {}
    for label, name, params, sig in settings(args.quick):
        if args.only not in label:
            continue
        Xs, ms = signals[sig]
        t0 = time.perf_counter()
        c, enc, was_cached = fitted(name, params, Xs, ms, cache)
        st = c.storage(enc)
        result["fits"].append({"codec": label, "name": name, "params": params, "signal": sig, "cached": was_cached,
                               "fit_encode_s": time.perf_counter() - t0, "clusters": c.K_,
                               "n_vectors": [int(v) for v in c.n_vectors_.unique()],
                               "vectors_mean_per_point": st["vectors_mean_per_point"], "bytes_total": st["bytes_total"],
                               "compression_ratio": st["compression_ratio"]})
        n_out, n_in = ms or (1, Xs.shape[1])
        M = c.decode(enc).view(P, n_out, n_in)  # the uncompressed reference reads the decoded matrices
        Ls = light[:n_in]
        Lc = Ls.T.contiguous()  # relight.* take lights as [C, n_in]
        modes = [("none", None, lambda: (M.reshape(P * n_out, n_in) @ Ls).view(P, n_out, 3))]
        if ms is None:  # vectors: [P, C], no view
            modes = [("none", None, lambda: M.view(P, n_in) @ Ls)]
        else:
            modes.append(("dense", views[sig], lambda: relight.apply_dense(M, Lc, views[sig])))
        if sig == "mrt":
            modes.append(("taps", taps, lambda: relight.apply_taps(M, Lc, *taps)))
        for nt in threads:
            torch.set_num_threads(nt)
            peak = peaks.setdefault(nt, peak_macs_per_s())
            for mode, view, unc in modes:
                r = with_peak(row(label, c, enc, Ls, view, mode, unc, args.repeats), peak)
                r["threads"] = nt
                result["rows"].append(r)
                print_row(r)
    # the Gaussian codec (Green 2005): lobes looked up in a prefiltered environment of the same light
    pe = prefilter_environment(light.T.contiguous().double(), res=16)
    for lobes in (1, 3):
        label = f"gaussian {lobes} lobe{'s' if lobes > 1 else ''}"
        if args.only not in label or args.no_gaussian:
            continue
        t0 = time.perf_counter()
        c, enc = gaussian_fitted(lobes, P)
        st = c.storage(enc)
        result["fits"].append({"codec": label, "name": "gaussian", "params": {"lobes": lobes}, "signal": "gaussian mixtures",
                               "cached": False, "fit_encode_s": time.perf_counter() - t0, "clusters": 0, "n_vectors": [lobes],
                               "vectors_mean_per_point": float(GAUSS_VIEWS * lobes), "bytes_total": st["bytes_total"],
                               "compression_ratio": st["compression_ratio"]})
        gview = gaussian_view(c, P)
        for nt in threads:
            torch.set_num_threads(nt)
            peak = peaks.setdefault(nt, peak_macs_per_s())
            for mode, view in (("none", None), ("taps", gview)):
                r = with_peak(gaussian_row(label, c, enc, pe, view, mode, args.repeats), peak)
                r["threads"] = nt
                result["rows"].append(r)
                print_row(r)
    # the peak again at the end, the faster of the two kept: a busy moment during one measurement
    # lowers it (a run once showed kernels at 1.38 "of peak"), and a capability is its best showing
    for nt in threads:
        torch.set_num_threads(nt)
        peaks[nt] = max(peaks[nt], peak_macs_per_s())
    for r in result["rows"]:
        with_peak(r, peaks[r["threads"]])
    result["peak_macs_per_s"] = {str(k): v for k, v in peaks.items()}
    result["seconds_total"] = time.perf_counter() - t_all
    result["load_average_after"] = os.getloadavg()
    return result


def report_all(runs: list[dict]) -> str:
    """The report of every kept run: one section per CPU and kernel build (newest first), the definitions once,
    and, where one CPU has runs of two builds, their fractions side by side."""
    r = runs[0]
    L = ["# Relighting from the compressed forms vs the memory-bandwidth bound", "",
         "Reproduce: `.venv/bin/python benchmarks/bench_relight.py` (writes this file and relight.json; a run replaces the "
         "section of its own CPU and kernel build and keeps the others; `--isa auto` also measures the avx512-256 and avx2 "
         "builds where the native one is AVX-512, `--isa native,avx2,avx512,avx512-256` names them). Sections: " + "; ".join(run_key(x) for x in runs)
         + ".", "",
         f"{r['points']} points, one SH light [25, 3] per call. Signals: `transfer_like(P, 24, 25)` (VQ, PCA, CPCA) and "
         f"`transfer_like(P, 49, 25)` (MRT-PCA, 7×7 tents). Codecs fitted on the first {r['fit_points']} points, then "
         "encoding all of them. **fraction** = bound / relight, where the bound is reading the stored bytes "
         "(model + codes + view) once and writing the output once: a `copy_` of the bytes read plus a `fill_` of the "
         "bytes written into existing buffers (`harness.timing.io_bound_fn`), timed interleaved with the relight in "
         "this run (`measure_paired`, median of per-repeat ratios; IQR in brackets). 1.0 = at the bound, goal ≥ 0.5. "
         "The relight is timed as a render loop calls it, writing into a reused result (`relight(..., out=buf)`), as "
         "the bound writes into a reused buffer; **new output** is the same fraction for `relight` allocating its "
         "result (the first-touch page faults of a large output — no view: n_out·C floats per point — are a cost "
         "the bound does not pay). **prepared** = the same fraction for the render loop's prepared form, `r = "
         "codec.relighter(enc, view)` once, then `r(light, out=buf)` per light (the same bits; relight's per-call checks "
         "done once: a few µs per call, which is much of a small relight; the Gaussian codec's keeps every lobe's "
         "pyramid addressing for every-view relighting); its cold figures are in the summary below. **compute floor** = the per-point "
         "multiply-adds (MACs column) at this machine's "
         "peak float32 rate, measured in the same run at the same thread count (a cache-resident 256³ GEMM at the start and at "
         "the end of the run, the faster kept: given in each section); "
         "**roofline** = max(bound, compute floor) / relight: where the floor exceeds the bound, no kernel can reach "
         "the bound on this CPU, and 2× the floor is the most the 0.5 goal can ask. **of peak** = compute floor / relight, "
         "the share of the peak rate the kernel sustains (the MACs are the cost model's; the per-light constants are "
         "not counted); **goal needs** = compute floor / (2 × bound), the share it would have to sustain for "
         "fraction 0.5 (over 1: unreachable on this CPU). **cold** = the same fraction from cold caches "
         "(`harness.timing.measure_paired_cold`: each call, relight or bound, timed alone after flushing what both "
         "sides touch from the caches, pairs alternating; median of per-pair ratios [IQR]): the bound is then the "
         "memory-bandwidth bound proper, while the back-to-back repeats of the main column keep either side's data "
         "(20–50 MB here) largely in the L3 and measure an L3-bandwidth bound. "
         "**vs uncompressed**: `relight.apply_dense` / `apply_taps` (or `M @ l`) on the decoded matrices, paired, "
         "over relight (> 1: compressed faster; both allocate their results). **torch path**: the fraction without "
         "the compiled kernels (`PRT_TORCH_NATIVE=0`, the path without a C compiler). "
         "**CPU · kernel path** (issue 42 §4): the CPU (model name, family/model, widest ISA the kernels have paths "
         "for) and the code the row ran, from the kernels' own dispatch (`relight_kernels.kernel_path`, `prt_plan_path`): "
         "the build's instruction set (`prt_isa`: the `#if` branches compiled in) and the point kernel of the row's plan. "
         "**1 thr CPU time**: at one thread, the same pair timed by the thread's CPU time (`measure_paired(clock="
         "time.thread_time)`): the time other processes held the core is in neither side, so on a shared machine it is the "
         "work ratio where the wall-clock fraction moves with the load; **prepared** there: the prepared form "
         "(`r(light, out=buf)`) against the same bound by the same clock. **2 thr fastest tenth**: at two threads, the "
         "wall-clock pair's floor phase (`measure_paired(floor_pairs=40, floor_max_pairs=160)`: short samples of equal "
         "length, the ratio of the two sides' 10% quantiles), what a quiet machine shows where a spinning parallel region "
         "stalls whenever another process holds a core. **roofline, load-robust**: max(bound, compute floor) / relight from "
         "that pair's times (1 thread: CPU time; 2 threads: the fastest tenth). **prepared vs relight (paired)**: the two "
         "render-loop forms timed against each other in one pairing (relight time / prepared time; > 1: the prepared form "
         "faster; 1 thread by CPU time, 2 threads wall clock): the prepared and fraction columns come from separate "
         "pairings, each against its own samples of the bound.", ""]
    L += compare_builds(runs)
    for x in runs:
        L += report(x)
    L += COST_MODEL
    return "\n".join(L)


def compare_builds(runs: list[dict]) -> list[str]:
    """Where one CPU has runs of two kernel builds (``--isa``): each row's fraction of the bound per build."""
    out: list[str] = []
    by_cpu: dict[str, list[dict]] = {}
    for x in runs:
        by_cpu.setdefault(cpu_label(x["machine"]), []).append(x)
    for cpu, rs in by_cpu.items():
        if len(rs) < 2 or not all(x.get("kernel_build") for x in rs):
            continue
        names = [kernel_label({"kernel": x["kernel_build"]}).replace(" build: ?", "") for x in rs]
        out += [f"## {cpu}: the kernel builds side by side", "",
                "Fraction of the bound (wall clock; at 1 thread also CPU time) per build, each paired with its own bound in "
                "its own process (ratios of ratios: the bound is the same copy in both).", "",
                "| codec | view | threads | " + " | ".join(names) + " |", "|---|---|---|" + "---|" * len(rs)]
        index = [{(y["codec"], y["view"], y["threads"]): y for y in x["rows"]} for x in rs]
        for key in index[0]:
            cells = []
            for ix in index:
                y = ix.get(key)
                ct = f" / {y['fraction_cpu_time']:.2f}" if y and y.get("fraction_cpu_time") is not None else ""
                cells.append(f"{y['fraction_of_bound']:.2f}{ct} ({y['kernel'].get('path', '?')})" if y else "—")
            out.append(f"| {key[0]} | {key[1]} | {key[2]} | " + " | ".join(cells) + " |")
        out.append("")
    return out


def report(r: dict) -> list[str]:
    """One run's section: its CPU and kernel build, machine state, rows, fits and tallies."""
    m = r["machine"]
    la = lambda t: tuple(round(x, 2) for x in t)  # noqa: E731
    untrusted = [x for x in r["rows"] if not x["contention"]["trusted"]]
    L = [f"## {run_key(r)}", "",
         f"Machine: {cpu_label(m)}, {m.get('cores')} cores, threads {r['threads']}, OpenMP: {r['omp_wait_policy']}; "
         f"load average before {la(r['load_average_before'])}, after {la(r['load_average_after'])}. "
         f"Total {r['seconds_total']:.0f} s. Kernels: {r['native']['detail']}. Peak float32 rate (compute floor): "
         f"{', '.join(f'{float(v) / 1e9:.0f} GMAC/s at {k} thread(s)' for k, v in r['peak_macs_per_s'].items())}.", ""]
    for rr in r.get("reruns", []):
        L += [f"Re-measured {rr['date']} (`bench_relight.py {rr['command']}`), load average before "
              f"{la(rr['load_average_before'])}, after {la(rr['load_average_after'])}: {', '.join(rr['rows'])} "
              f"(kernels: {rr['kernels']}); the other rows are from the run above.", ""]
    if not r.get("kernel_build"):
        L += ["This run is from before issue 42 §4: its rows did not record their kernel path or the CPU's family/model "
              "(the library was built `-march=native` on this CPU, as its Kernels line says).", ""]
    if untrusted:
        L += [f"**{len(untrusted)} of {len(r['rows'])} rows were measured on a busy machine** (contention not trusted: "
              + "; ".join(sorted({w for x in untrusted for w in x['contention']['why_not']}))[:400] + "): the ratios are paired, "
              "but re-run on a quiet machine for final figures.", ""]
    L += ["| codec | view | threads | bytes read | bytes written | MACs / point | relight (ms) | bound (ms) | compute floor (ms) "
          "| fraction of bound | prepared | roofline | of peak | goal needs | cold (relight / bound ms) | new output | torch path "
          "| vs uncompressed | 1 thr CPU time | 2 thr fastest tenth | roofline, load-robust | prepared vs relight (paired) "
          "| CPU · kernel path |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        q1, q3 = x["fraction_q1_q3"]
        L.append(f"| {x['codec']} | {x['view']} | {x['threads']} | {x['bytes_read']:,} | {x['bytes_written']:,} | {x['macs_per_point']:.0f} | "
                 f"{x['relight_ms']:.3f} | {x['bound_ms']:.3f} | {x['compute_floor_ms']:.3f} | "
                 f"**{x['fraction_of_bound']:.2f}** [{q1:.2f}, {q3:.2f}] | {x['fraction_relighter']:.2f} "
                 f"[{x['fraction_relighter_q1_q3'][0]:.2f}, {x['fraction_relighter_q1_q3'][1]:.2f}] | {x['fraction_of_roofline']:.2f} | "
                 f"{x['peak_fraction']:.2f} | {x['peak_fraction_goal_needs']:.2f} | "
                 f"{x['fraction_cold']:.2f} [{x['fraction_cold_q1_q3'][0]:.2f}, {x['fraction_cold_q1_q3'][1]:.2f}] "
                 f"({x['relight_cold_ms']:.2f} / {x['bound_cold_ms']:.2f}) | "
                 f"{x['fraction_new_output']:.2f} | {x['torch_path_fraction_of_bound']:.2f} | "
                 + (f"{x['speedup_vs_uncompressed']:.1f}× |" if x["speedup_vs_uncompressed"] is not None else "— |")
                 + (f" {x['fraction_cpu_time']:.2f} [{x['fraction_cpu_time_q1_q3'][0]:.2f}, {x['fraction_cpu_time_q1_q3'][1]:.2f}]"
                    if x.get("fraction_cpu_time") is not None else " —")
                 + (f"; prepared {x['fraction_relighter_cpu_time']:.2f} [{x['fraction_relighter_cpu_time_q1_q3'][0]:.2f}, "
                    f"{x['fraction_relighter_cpu_time_q1_q3'][1]:.2f}] |" if x.get("fraction_relighter_cpu_time") is not None else " |")
                 + (f" {x['fraction_fastest_tenth']:.2f} |" if x.get("fraction_fastest_tenth") is not None else " — |")
                 + (f" {x['fraction_of_roofline_robust']:.2f} |" if x.get("fraction_of_roofline_robust") is not None else " — |")
                 + (f" {x['prepared_vs_relight']:.3f} [{x['prepared_vs_relight_q1_q3'][0]:.3f}, {x['prepared_vs_relight_q1_q3'][1]:.3f}]"
                    f" ({x['prepared_vs_relight_clock']}) |" if x.get("prepared_vs_relight") is not None else " — |")
                 + f" {x.get('cpu') or cpu_label(m)} · {kernel_label(x)} |")
    L += ["", "Fits (fit on the first points + encode all, or loaded from the cache):", "",
          "| codec | clusters | n_k | mean weights per point | stored bytes | compression | fit+encode (s) |",
          "|---|---|---|---|---|---|---|"]
    for f in r["fits"]:
        L.append(f"| {f['codec']} | {f['clusters']} | {f['n_vectors']} | {f['vectors_mean_per_point']:.2f} | {f['bytes_total']:,} | "
                 f"{f['compression_ratio']:.1f} | {f['fit_encode_s']:.1f}{' (cached)' if f['cached'] else ''} |")
    ok = [x for x in r["rows"] if x["fraction_of_bound"] >= 0.5]
    L += ["", f"Rows at ≥ 0.5 of the bound: {len(ok)} of {len(r['rows'])}"
          + (" (" + ", ".join(f"{x['codec']} {x['view']} {x['threads']} thr" for x in ok) + ")" if ok else "") + "."]

    def tally(key: str, text: str, values: bool = True) -> str:
        """``text`` with {n} of {N} rows whose ``key`` is ≥ 0.5, then the others named (and their values)."""
        short = [x for x in r["rows"] if x[key] < 0.5]
        names = ", ".join(f"{x['codec']} {x['view']} {x['threads']} thr" + (f" {x[key]:.2f}" if values else "") for x in short)
        return text.format(n=len(r["rows"]) - len(short), N=len(r["rows"])) + (f" (not: {names})" if short else "") + "."

    L += [tally("fraction_relighter", "Prepared (`codec.relighter`), rows at ≥ 0.5 of the bound: {n} of {N}"),
          tally("fraction_cold", "From cold caches (the cold column): {n} of {N} rows at ≥ 0.5 of the memory-bandwidth bound",
                values=False)]
    capped = [x for x in r["rows"] if x["compute_floor_ms"] > 2 * x["bound_ms"]]
    okr = [x for x in r["rows"] if x["fraction_of_roofline"] >= 0.5]
    L += [f"Rows whose compute floor is over twice the bound (the 0.5 goal unreachable at this CPU's peak): {len(capped)}"
          + (" (" + ", ".join(f"{x['codec']} {x['view']} {x['threads']} thr" for x in capped) + ")" if capped else "") + ".",
          f"Rows at ≥ 0.5 of the roofline: {len(okr)} of {len(r['rows'])}."]
    L += [tally("fraction_of_roofline_cold", "From cold caches, against max(cold bound, compute floor) (the memory-bandwidth "
                "bound, or the arithmetic where it dominates): {n} of {N} rows at ≥ 0.5"),
          tally("fraction_of_roofline_cold_relighter", "Prepared (`codec.relighter`), from cold caches, against max(cold bound, "
                "compute floor): {n} of {N} rows at ≥ 0.5")]
    robust = [x for x in r["rows"] if x.get("fraction_of_roofline_robust") is not None]
    if robust:
        low = [x for x in robust if x["fraction_of_roofline_robust"] < 0.5]
        L += [f"Rows at ≥ 0.5 of the roofline by the load-robust pair (1 thread: CPU time; 2 threads: the fastest tenth): "
              f"{len(robust) - len(low)} of {len(robust)}"
              + (" (not: " + ", ".join(f"{x['codec']} {x['view']} {x['threads']} thr {x['fraction_of_roofline_robust']:.2f}"
                                       for x in low) + ")" if low else "") + "."]
    pv = [x for x in r["rows"] if x.get("prepared_vs_relight") is not None]
    if pv:
        slower = [x for x in pv if x["prepared_vs_relight_q1_q3"][1] < 1.0]
        vals = sorted(x["prepared_vs_relight"] for x in pv)
        L += [f"Prepared vs relight, paired (relight time / prepared time): {vals[0]:.3f}–{vals[-1]:.3f}, median "
              f"{vals[len(vals) // 2]:.3f}; prepared slower beyond its IQR (upper quartile < 1) in {len(slower)} of {len(pv)} rows"
              + (" (" + ", ".join(f"{x['codec']} {x['view']} {x['threads']} thr {x['prepared_vs_relight']:.3f}" for x in slower) + ")"
                 if slower else "") + "."]
    need = sorted(x["peak_fraction_goal_needs"] for x in r["rows"] if x["fraction_of_bound"] < 0.5)
    got = sorted(x["peak_fraction"] for x in r["rows"])
    if need:
        L += [f"Rows under 0.5: the goal would need {need[0]:.2f}–{need[-1]:.2f} of the peak float32 rate (median "
              f"{need[len(need) // 2]:.2f}); the kernels sustain {got[0]:.2f}–{got[-1]:.2f} of it (median {got[len(got) // 2]:.2f})."]
    L += [""]
    return L


#: the cost model and the Gaussian rows' reading, once per report
COST_MODEL = ["", "Cost model (Sloan 2003 §6; Lehtinen & Kautz 2003 eq. (13)): per light, the per-cluster constants M_i^k l "
    "(K·J·n_out·C floats, one GEMM over the stored model); per point one pass over its codes — J·n_out·C "
    "multiply-adds without a view or with a dense view (the view folded in before anything n_out·C-sized leaves "
    "the core), t·J·C with t taps — in `prt_torch/codecs/relight_kernels.py`. The MACs column is that per-point "
    "arithmetic: where it is large against the bytes per point (MRT-PCA with a dense view: 16·49·3 MACs for 260 "
    "bytes), the kernel is compute-bound and no relight reads-once-and-writes-once at the copy's speed.", "",
    "Gaussian rows (Green 2005 eq. 2.7, §2.3): per lobe one trilinear lookup in the prefiltered pyramid "
    "(8 texels × C multiply-adds, the MACs column, after the face, texel and level addressing: a cube-face "
    "projection, a division, a logarithm and a search of the width ladder); with taps, first the blend of the k "
    "tapped views' lobes (5 floats each) and a normalisation. Bytes read: no view, the whole encoding; taps, only the "
    "tapped views' lobes and the taps (the other 89 views are never read). The work is address arithmetic and "
    "scattered table reads, which neither the copy bound nor the multiply-add floor captures; the fraction says how "
    "far the lookup is from the bytes it must move. Prepared (`codec.relighter`), the addressing is kept per lobe "
    "(every view) or, with taps, the blend across the taps and its addressing (20 bytes per blended lobe and 4 per "
    "vertex); `relight` with taps keeps the same in `enc.cache` from its second call with the same taps (these "
    "rows' repeats): both then read derived data that is smaller than the bound's bytes, so a fraction above 1 "
    "means that, not a faster memory. In the fits table, a Gaussian row's n_k is its lobes per "
    "function and its mean weights per point its lobes per vertex (92 views × N).", ""]


if __name__ == "__main__":
    raise SystemExit(main())
