"""Encode benchmarks (issue 15): k-means, the CPCA classification step, PCA and iterative CPCA,
every figure a ratio to a peer or bound measured in the same run.

1. k-means, 256 clusters, 20 Lloyd iterations: our VQ codec (greedy k-means++ seeds, bounded
   Lloyd; the whole ``fit``) against ``faiss.Kmeans`` (niter=20, random seeds from the data)
   and scikit-learn's ``KMeans`` (k-means++, n_init=1, max_iter=20, tol=0, lloyd). Time ratio
   (interleaved pairs for faiss) and squared-error ratio, the SE of each method's centres
   computed here the same way (every point at its nearest centre, float64).
   The assignment kernel alone: ``kmeans.assign`` vs faiss ``IndexFlatL2.search(k=1)``.
2. The CPCA classification step (Sloan 2003 §4.2, 256 clusters × (1 + 8) representatives):
   exact ``classify_all`` against its bound, the bare GEMM ``[P, D] @ [D, K(1+n)]`` alone; the
   candidate-set classification against the exact one.
3. PCA n' = 8: our PCA codec's fit against scikit-learn's randomized PCA (same threads), with the
   SE of both subspaces computed here and the optimum (float64 eigen-decomposition).
4. Iterative CPCA (Sloan 2003 §4.2), 256 clusters × 8 vectors: time against the 30 s goal and
   against static CPCA (§4.1) in the same run; SE against the figures in
   reports/benchmarks/codecs.json (the code before issue 15, same data and seed).

Data: synthetic ``transfer_like`` 50 000 × 625 (25×25), and glossy transfer, 24×25 exit matrices,
Ashikhmin–Shirley, of ``--glossy-scene``: by default the scan-like mesh of the built-in scan_blob
(``scene.scan.scan_like``: decimation, holes, fins, slivers) at 25 000 vertices, issue 42 §4's
"real glossy transfer of a 25k-vertex scan" (no built-in size has ~25k vertices); before issue 42
it was bumpy_sphere large (50 412 vertices), the signal of bench_codecs.py
(``--glossy-scene bumpy_sphere:large``).

Per CPU (issue 42 §4): every k-means row names the CPU (model name, family/model, widest vector
ISA) and the code it ran (torch's GEMM choice and ISA, faiss's compile options, scikit-learn's
OpenBLAS kernel); encode.json keeps one run per CPU, a new run replacing its own CPU's.

Peers: faiss-cpu is a benchmark-only dependency (``.venv/bin/pip install faiss-cpu``); without
it the faiss rows are skipped with a note. Threads: torch, faiss (``omp_set_num_threads``) and
scikit-learn (threadpoolctl) all run with ``--threads`` (default 2). The load average is
recorded before and after (other jobs may share the machine: compare the ratios).

Run: .venv/bin/python benchmarks/bench_encode.py   (about 5 minutes on an idle 2-core machine;
--quick: small sizes, prints only; --no-glossy; --no-sklearn-kmeans)
Writes reports/benchmarks/encode.md and encode.json.
"""
from __future__ import annotations

import os

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import json  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.codecs import kmeans as km  # noqa: E402
from prt_torch.codecs.affine import classify_all  # noqa: E402
from prt_torch.codecs.synthetic import transfer_like  # noqa: E402
from prt_torch.harness.timing import cpu_label, machine_info, measure, measure_paired  # noqa: E402
from prt_torch.io import atomic_write_json, atomic_write_text  # noqa: E402

OUT = Path(__file__).resolve().parent.parent / "reports" / "benchmarks"
GOAL_ITERATIVE_S = 30.0


def timed(fn):
    t0 = time.perf_counter()
    r = fn()
    return r, time.perf_counter() - t0


def centre_se(X: torch.Tensor, C) -> float:
    """Σ_p min_k ||x_p − c_k||², float64 (the same measure for every method's centres)."""
    C = torch.as_tensor(np.asarray(C)).double()
    cc = C.square().sum(1)
    se = 0.0
    for i in range(0, X.shape[0], 4096):
        x = X[i:i + 4096].double()
        d = (x.square().sum(1)[:, None] - 2 * x @ C.T + cc).clamp_min(0)
        se += float(d.min(1).values.sum())
    return se


def subspace_se(X: torch.Tensor, mean, comps) -> float:
    """||X − mean||² − ||(X − mean) Vᵀ||² (float64) for orthonormalised rows V of ``comps``."""
    V = torch.linalg.qr(torch.as_tensor(np.asarray(comps)).double().T)[0]  # [D, n]
    m = torch.as_tensor(np.asarray(mean)).double()
    se = 0.0
    for i in range(0, X.shape[0], 4096):
        y = X[i:i + 4096].double() - m
        se += float(y.square().sum() - (y @ V).square().sum())
    return se


def optimal_pca_se(X: torch.Tensor, n: int) -> float:
    """The least SE of any n-dimensional affine subspace: discarded eigenvalues (float64 eigh)."""
    m = X.double().mean(0)
    S = torch.zeros(X.shape[1], X.shape[1], dtype=torch.float64)
    for i in range(0, X.shape[0], 4096):
        y = X[i:i + 4096].double() - m
        S += y.T @ y
    ev = torch.linalg.eigvalsh(S).flip(0)
    return float(ev[n:].sum())


def limits(threads: int):
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=threads)


SEEDS = (1, 2, 3)


def ours_path(threads: int) -> str:
    """The code our k-means / CPCA / PCA rows ran (issue 42 §4): torch's GEMM choice (``kmeans.gemm_choice``:
    MKL addmm or oneDNN linear, measured once per process), the ISA torch's kernels dispatch to on this CPU,
    and the threads."""
    g = km.gemm_choice()
    return f"torch {g['backend']} GEMM ({torch.backends.cpu.get_cpu_capability()}), {threads} threads"


def faiss_path(faiss, threads: int) -> str:
    """Which faiss build ran: its compile options (the SIMD level of the module the loader picked for this CPU)."""
    return f"faiss {faiss.__version__} ({faiss.get_compile_options().strip()}), {threads} threads"


def sklearn_path(threads: int) -> str:
    """scikit-learn's BLAS and OpenMP as threadpoolctl sees them (the OpenBLAS kernel architecture)."""
    from threadpoolctl import threadpool_info

    libs = [f"{i['internal_api']} {i.get('version') or ''} {i.get('architecture') or ''}".strip() for i in threadpool_info()
            if i.get("internal_api") == "openblas" and "sklearn" in str(i.get("filepath", "")) + str(i.get("prefix", ""))]
    return f"scikit-learn ({', '.join(libs) or 'BLAS: ' + ', '.join(sorted({i['internal_api'] for i in threadpool_info()}))}), {threads} threads"


def kmeans_section(X: torch.Tensor, K: int, iters: int, repeats: int, threads: int, faiss, sk: bool) -> dict:
    """Ours and faiss over the same seeds (``SEEDS``: seeding luck moves either's SE by ~1%, so
    one seed each compares luck): per seed one interleaved pair of fits, timed back to back;
    reported: the mean time ratio and the mean SE of each."""
    P, D = X.shape
    Xn = np.ascontiguousarray(X.numpy())
    out: dict = {"clusters": K, "iterations": iters, "seeds": list(SEEDS), "cpu": cpu_label(), "ours_path": ours_path(threads)}
    if faiss is not None:
        out["faiss_path"] = faiss_path(faiss, threads)

    def ours(seed=SEEDS[0]):
        return codecs.get("vq", clusters=K, max_iter=iters, tol=0.0, seed=seed).fit(X)

    vq, t_first = timed(ours)
    out["ours"] = {"first_fit_s": t_first, "init_dims": vq.init_dims, "lloyd_iterations": vq.fit_info_["lloyd_iterations"]}
    if faiss is not None:
        def peer(seed=SEEDS[0]):
            f = faiss.Kmeans(D, K, niter=iters, seed=seed, verbose=False)
            f.train(Xn)
            return f

        per_seed = []
        for seed in SEEDS:
            pair = measure_paired(lambda: ours(seed), lambda: peer(seed), repeats=repeats, warmup=0)
            o, f = ours(seed), peer(seed)
            per_seed.append({"seed": seed, "ours_s": pair.test.median, "faiss_s": pair.peer.median, "ratio": pair.ratio.median,
                             "ours_se": centre_se(X, o.means_), "faiss_se": centre_se(X, f.centroids), "contention": pair.contention})
        out["per_seed"] = per_seed
        mean = lambda key: sum(r[key] for r in per_seed) / len(per_seed)  # noqa: E731
        out["ours"].update({"seconds": mean("ours_s"), "se": mean("ours_se")})
        out["faiss"] = {"seconds": mean("faiss_s"), "se": mean("faiss_se"), "version": faiss.__version__}
        out["paired"] = {"contention": per_seed[-1]["contention"]}
        out["time_faiss_over_ours"] = mean("ratio")
        out["se_ours_over_faiss"] = out["ours"]["se"] / out["faiss"]["se"]
        # the same pair at one thread each, timed by this thread's CPU time (timing.measure_paired's clock): on a
        # shared machine the time other processes held the core is in neither side (the 2-thread ratio above moves
        # with the load); seed SEEDS[0]
        from prt_torch.harness.timing import torch_threads

        faiss.omp_set_num_threads(1)
        try:
            with torch_threads(1):
                one = measure_paired(ours, peer, repeats=repeats, warmup=0, clock=time.thread_time)
        finally:
            faiss.omp_set_num_threads(threads)
        out["one_thread_cpu_time"] = {"ours_s": one.test.median, "faiss_s": one.peer.median, "time_faiss_over_ours": one.ratio.median,
                                      "q1_q3": [one.ratio.q1, one.ratio.q3], "seed": SEEDS[0],
                                      "ours_path": ours_path(1), "faiss_path": faiss_path(faiss, 1)}
        f = peer()
        # the assignment kernel alone (one full classification against the faiss centroids)
        C = torch.from_numpy(f.centroids.copy())
        xx = X.square().sum(1)
        index = faiss.IndexFlatL2(D)
        index.add(f.centroids)
        a = measure_paired(lambda: km.assign(X, C, xx), lambda: index.search(Xn, 1), repeats=repeats + 2, warmup=1)
        lab, _ = km.assign(X, C, xx)
        _, I = index.search(Xn, 1)
        out["assign"] = {"ours_s": a.test.median, "faiss_s": a.peer.median, "time_faiss_over_ours": a.ratio.median,
                         "label_agreement": float((lab.numpy() == I[:, 0]).mean()), "contention": a.contention}
    else:
        out["ours"]["seconds"] = measure(ours, repeats=repeats, warmup=0).median
        out["ours"]["se"] = centre_se(X, vq.means_)
    if sk:
        from sklearn.cluster import KMeans

        with limits(threads):
            skm, t_sk = timed(lambda: KMeans(n_clusters=K, init="k-means++", n_init=1, max_iter=iters, tol=0.0,
                                             algorithm="lloyd", random_state=0).fit(Xn))
        out["sklearn"] = {"seconds": t_sk, "se": centre_se(X, skm.cluster_centers_), "iterations": int(skm.n_iter_),
                          "path": sklearn_path(threads)}
        out["time_sklearn_over_ours"] = t_sk / out["ours"]["seconds"]
        out["se_ours_over_sklearn"] = out["ours"]["se"] / out["sklearn"]["se"]
    return out


def classify_section(X: torch.Tensor, st, repeats: int) -> dict:
    """Exact and candidate classification of a fitted static CPCA model against the GEMM bound."""
    from prt_torch.codecs.cpca import _Work, _candidate_sets  # the fit's internals: the step itself

    off = st.means_.double().mean(0)
    Xc = (X.double() - off).float()
    means = st.means_.double() - off
    basis = st.basis_.double()
    K, n, D = basis.shape
    xx = Xc.square().sum(1)
    W = torch.cat([means[:, None], basis], 1).float().reshape(K * (1 + n), D)
    exact = measure_paired(lambda: classify_all(Xc, xx, means, basis), lambda: Xc @ W.T, repeats=repeats, warmup=1)
    labels, emin, top = classify_all(Xc, xx, means, basis, top=8)
    work = _Work(Xc, None, K)
    work.set_labels(labels)
    cand = _candidate_sets(labels, top, K, 8)
    state = {"means": means, "basis": basis}
    c = measure_paired(lambda: work.classify_candidates(state, cand), lambda: classify_all(Xc, xx, means, basis),
                       repeats=repeats, warmup=1)
    lab_c, _ = work.classify_candidates(state, cand)
    return {"clusters": K, "vectors": n, "exact_s": exact.test.median, "gemm_s": exact.peer.median,
            "exact_over_gemm": 1.0 / exact.ratio.median, "exact_contention": exact.contention,
            "candidates": 8, "candidate_s": c.test.median, "exact_over_candidate": c.ratio.median,
            "candidate_label_agreement": float((lab_c == labels).double().mean())}


def pca_section(X: torch.Tensor, n: int, repeats: int, threads: int) -> dict:
    from sklearn.decomposition import PCA as SKPCA

    Xn = np.ascontiguousarray(X.numpy())

    def ours():
        return codecs.get("pca", vectors=n).fit(X)

    def peer():
        with limits(threads):
            return SKPCA(n_components=n, svd_solver="randomized", random_state=0).fit(Xn)

    pair = measure_paired(ours, peer, repeats=repeats, warmup=1)
    o, s = ours(), peer()
    se_o = subspace_se(X, o.means_[0], o.basis_[0])
    se_s = subspace_se(X, s.mean_, s.components_)
    best = optimal_pca_se(X, n)
    return {"vectors": n, "solver": o.fit_info_["solver"], "ours_s": pair.test.median, "sklearn_randomized_s": pair.peer.median,
            "time_sklearn_over_ours": pair.ratio.median, "se_ours": se_o, "se_sklearn": se_s, "se_optimal": best,
            "se_ours_over_sklearn": se_o / se_s, "se_ours_over_optimal": se_o / best, "se_sklearn_over_optimal": se_s / best,
            "contention": pair.contention}


def cpca_section(X: torch.Tensor, ms, K: int, n: int) -> dict:
    it, t_it = timed(lambda: codecs.get("cpca_iterative", clusters=K, vectors=n).fit(X, matrix_shape=ms))
    stc, t_st = timed(lambda: codecs.get("cpca_static", clusters=K, vectors=n).fit(X, matrix_shape=ms))
    info = it.fit_info_
    return {"clusters": K, "vectors": n, "iterative_s": t_it, "iterative_se": info["se"], "static_s": t_st,
            "static_se": stc.fit_info_["se"], "iterative_over_static_time": t_it / t_st,
            "goal_s": GOAL_ITERATIVE_S, "goal_over_time": GOAL_ITERATIVE_S / t_it,
            "restarted_from_static": info.get("restarted_from_static"),
            "stages": [{"vectors": s["vectors"], "se": s["se"], "rounds": len(s["changes"])} for s in info["stages"]],
            "_codec": stc}


def before_figures() -> dict:
    """Encode figures of reports/benchmarks/codecs.json (written by bench_codecs.py before issue 15)."""
    p = OUT / "codecs.json"
    if not p.exists():
        return {}
    d = json.loads(p.read_text())
    out = {}
    for key, label in (("encode_synthetic", "synthetic"), ("encode_glossy", "glossy")):
        e = d.get(key)
        if e:
            out[label] = {"iterative_s": e["iterative"]["seconds"], "iterative_se": e["iterative"]["se"],
                          "static_s": e["static"]["seconds"], "static_se": e["static"]["se"],
                          "vq_s": e["vq"]["seconds"], "vq_inertia": e["vq"]["inertia"], "pca_s": e["pca"]["seconds"],
                          "pca_se": e["pca"]["se"], "load_average_before": d.get("load_average_before")}
    return out


def dataset(label: str, X: torch.Tensor, ms, args, faiss) -> dict:
    K, n = (64, 4) if args.quick else (256, 8)
    rep = 2 if args.quick else 3
    print(f"[{label}] k-means", flush=True)
    r = {"signal": label, "points": X.shape[0], "dim": X.shape[1], "matrix_shape": list(ms)}
    r["kmeans"] = kmeans_section(X, K, 20, rep, args.threads, faiss, sk=not args.no_sklearn_kmeans and label == "synthetic")
    print(f"[{label}] iterative CPCA", flush=True)
    r["cpca"] = cpca_section(X, ms, K, n)
    print(f"[{label}] classification", flush=True)
    r["classify"] = classify_section(X, r["cpca"].pop("_codec"), rep + 2)
    print(f"[{label}] PCA", flush=True)
    r["pca"] = pca_section(X, n, rep + 4, args.threads)
    return r


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test); prints, writes nothing")
    ap.add_argument("--no-glossy", action="store_true", help="skip the built-in glossy scene")
    ap.add_argument("--no-sklearn-kmeans", action="store_true", help="skip scikit-learn's KMeans (the slowest peer)")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--glossy-scene", default="scan_blob:25000",
                    help="the glossy case's mesh: scan_blob:N (the scan-like mesh of the built-in scan_blob, "
                         "scene.scan.scan_like, at about N vertices: issue 42 §4's ~25k-vertex scan) or a built-in NAME:SIZE "
                         "(bumpy_sphere:large, 50 412 vertices, was the case before issue 42)")
    ap.add_argument("--no-synthetic", action="store_true", help="skip the synthetic signal (the glossy case only)")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    try:
        import faiss

        faiss.omp_set_num_threads(args.threads)
        faiss_note = f"faiss {faiss.__version__}"
    except ImportError:
        faiss = None
        faiss_note = "faiss not installed (.venv/bin/pip install faiss-cpu): faiss rows skipped"
        print(faiss_note)
    load0 = os.getloadavg()
    t_all = time.perf_counter()
    result: dict = {"machine": machine_info(), "omp_wait_policy": prt_torch.OMP_POLICY_CHOICE, "threads": args.threads,
                    "faiss": faiss_note, "load_average_before": load0, "quick": args.quick, "before": before_figures()}
    P = 5000 if args.quick else 50000
    if not args.no_synthetic:
        result["synthetic"] = dataset("synthetic", transfer_like(P, 25, 25, seed=0), (25, 25), args, faiss)
    if not args.no_glossy:
        from prt_torch import brdf as B
        from prt_torch.transfer.base import RunOptions
        from prt_torch.transfer.glossy import precompute_glossy

        scene, mesh = glossy_mesh(args.glossy_scene, args.quick)
        tr, t_pre = timed(lambda: precompute_glossy(mesh, bands=5, samples=256, seed=0, run=RunOptions(workers=2),
                                                    brdf=B.AshikhminShirley(40, 10, rs=0.05, rd=0.3), drop_out=[(1, 0)]))
        result["glossy_scene"] = {"scene": scene, "vertices": mesh.num_vertices,
                                  "matrix_shape": list(tr.meta["matrix_shape"]),
                                  "brdf": "Ashikhmin-Shirley N_u=40 N_v=10 Rs=0.05 Rd=0.3", "samples": 256, "precompute_s": t_pre}
        result["glossy"] = dataset("glossy", tr.signal(), tuple(tr.meta["matrix_shape"]), args, faiss)
    result["seconds_total"] = time.perf_counter() - t_all
    result["load_average_after"] = os.getloadavg()
    if args.quick:
        print(report(result))
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    runs = [result]  # one run per CPU: this one replaces its CPU's, the others' are kept (issue 42 §4)
    if (OUT / "encode.json").exists():
        old = json.loads((OUT / "encode.json").read_text())
        runs += [x for x in old.get("runs", [old]) if cpu_label(x["machine"]) != cpu_label(result["machine"])]
    atomic_write_json(OUT / "encode.json", {"runs": runs})
    text = "\n\n".join(report(x, level=2) for x in runs)
    atomic_write_text(OUT / "encode.md", "# Encode benchmarks (issue 15; per CPU: issue 42 §4)\n\n"
                      f"Sections: {'; '.join(cpu_label(x['machine']) for x in runs)}. A run replaces its own CPU's section "
                      "and keeps the others.\n\n" + text)
    print(report(result))
    return 0


def glossy_mesh(spec: str, quick: bool):
    """``(label, Mesh)`` of ``--glossy-scene``: ``scan_blob:N`` is the built-in scan_blob's generator
    (``scene.scan.scan_like``) at about N vertices; any other ``NAME[:SIZE]`` a built-in scene."""
    from prt_torch.scene import builtin
    from prt_torch.scene.scan import scan_like

    name, _, size = spec.partition(":")
    if name == "scan_blob" and size.isdigit():
        n = 2000 if quick else int(size)
        return f"scan_blob at {n} vertices (scene.scan.scan_like({n}))", scan_like(n)
    return f"{name}:{size or 'large'}", builtin(name, "small" if quick else (size or "large"))


def _f(v, nd=4):
    if v is None:
        return "—"
    if isinstance(v, float):
        return f"{v:.{nd}g}" if abs(v) < 1e5 else f"{v:.{nd}e}"
    return str(v)


def report(r: dict, level: int = 1) -> str:
    m = r["machine"]
    la, lb = r["load_average_before"], r["load_average_after"]
    h = "#" * (level - 1)
    L = ["# Encode benchmarks (issue 15)" if level == 1 else f"## {cpu_label(m)}", "",
         f"Machine: {cpu_label(m)}, {m.get('cores')} cores; threads {r['threads']} for torch, faiss and scikit-learn "
         f"(threadpoolctl); OpenMP: {r.get('omp_wait_policy')}; {r['faiss']}; our GEMM (`kmeans.gemm_choice`): "
         f"{m.get('encode_gemm', 'not recorded')}. Load average before "
         f"{tuple(round(x, 2) for x in la)}, after {tuple(round(x, 2) for x in lb)} (the run's own threads add about "
         f"{r['threads']}; more means other jobs shared the machine and absolute times are inflated); every ratio compares "
         "measurements of the same run (paired ones interleaved, "
         f"median of per-repeat ratios). Total {r['seconds_total']:.0f} s.", "",
         "Reproduce: `.venv/bin/python benchmarks/bench_encode.py` (faiss-cpu needed for the faiss rows: "
         "`.venv/bin/pip install faiss-cpu`).", ""]
    for key in ("synthetic", "glossy"):
        d = r.get(key)
        if not d:
            continue
        title = ("synthetic transfer_like 25×25" if key == "synthetic" else
                 f"glossy {r['glossy_scene']['scene']} ({r['glossy_scene']['vertices']} vertices, "
                 f"{r['glossy_scene']['brdf']}, {r['glossy_scene']['samples']} samples)")
        L += [f"{h}## {title}: {d['points']} × {d['dim']} float32", ""]
        k = d["kmeans"]
        cpu, nr = k.get("cpu") or cpu_label(m), "not recorded (before issue 42 §4)"
        L += [f"{h}### k-means, {k['clusters']} clusters, {k['iterations']} Lloyd iterations", "",
              "SE: Σ min_k ||x − c_k||² of each method's centres, computed here in float64. Time ratio > 1: ours faster; "
              f"SE ratio < 1: ours lower. Ours and faiss: means over seeds {k.get('seeds')} (seeding luck moves either's SE by "
              "about 1%), each seed's pair of fits timed back to back (interleaved).", "",
              "| method | time (s) | SE | time peer / ours | SE ours / peer | CPU · kernel path |", "|---|---|---|---|---|---|",
              f"| ours (vq codec fit: k-means++ seeds in the sample's top-{k['ours'].get('init_dims')} principal directions "
              f"+ bounded Lloyd) | {k['ours']['seconds']:.2f} | {_f(k['ours']['se'])} | | | {cpu} · {k.get('ours_path', nr)} |"]
        if "faiss" in k:
            L.append(f"| faiss.Kmeans (niter={k['iterations']}) | {k['faiss']['seconds']:.2f} | {_f(k['faiss']['se'])} | "
                     f"**{k['time_faiss_over_ours']:.2f}×** | **{k['se_ours_over_faiss']:.4f}** | {cpu} · {k.get('faiss_path', nr)} |")
        else:
            L.append("| faiss.Kmeans | skipped: faiss not installed | | | | |")
        if "one_thread_cpu_time" in k:
            o = k["one_thread_cpu_time"]
            L.append(f"| same pair at 1 thread each, CPU time (seed {o['seed']}): ours / faiss | {o['ours_s']:.2f} / "
                     f"{o['faiss_s']:.2f} | | **{o['time_faiss_over_ours']:.2f}×** [{o['q1_q3'][0]:.2f}, {o['q1_q3'][1]:.2f}] | | "
                     f"{cpu} · {o['ours_path']}; {o['faiss_path']} |")
        if "sklearn" in k:
            L.append(f"| scikit-learn KMeans (k-means++, n_init=1, max_iter={k['iterations']}) | {k['sklearn']['seconds']:.2f} | "
                     f"{_f(k['sklearn']['se'])} | {k['time_sklearn_over_ours']:.2f}× | {k['se_ours_over_sklearn']:.4f} | "
                     f"{cpu} · {k['sklearn'].get('path', nr)} |")
        if "per_seed" in k:
            L += ["", "Per seed (ours / faiss): " + "; ".join(
                f"{r['seed']}: {r['ours_s']:.2f} / {r['faiss_s']:.2f} s, SE {_f(r['ours_se'])} / {_f(r['faiss_se'])}"
                for r in k.get("per_seed", [])) + "."]
        if "assign" in k:
            a = k["assign"]
            L += ["", f"Assignment kernel alone (every point to its nearest of the faiss centroids): ours "
                  f"{1e3 * a['ours_s']:.0f} ms, faiss IndexFlatL2.search {1e3 * a['faiss_s']:.0f} ms: "
                  f"**{a['time_faiss_over_ours']:.2f}×** (labels agree on {a['label_agreement']:.4%})."]
        if "paired" in k:
            c = k["paired"]["contention"]
            L += ["", f"Paired timing contention: load {c['load_average_1min']:.1f}, {c['involuntary_switches_per_s']:.0f} "
                  f"involuntary switches/s, trusted: {c['trusted']}."]
        c = d["cpca"]
        b = r.get("before", {}).get(key)
        if key == "glossy" and not str(r["glossy_scene"]["scene"]).startswith("bumpy_sphere"):
            b = None  # codecs.json's figures are of bumpy_sphere large: another signal
        L += ["", f"{h}### Iterative CPCA (Sloan 2003 §4.2), {c['clusters']} clusters × {c['vectors']} vectors", "",
              "| fit | time (s) | SE |", "|---|---|---|",
              f"| iterative | **{c['iterative_s']:.1f}** | {_f(c['iterative_se'])} |",
              f"| static (§4.1) | {c['static_s']:.1f} | {_f(c['static_se'])} |"]
        if b:
            L += [f"| before issue 15: iterative (codecs.json, load {b['load_average_before'][0]:.1f}) | {b['iterative_s']:.1f} | "
                  f"{_f(b['iterative_se'])} |",
                  f"| before issue 15: static | {b['static_s']:.1f} | {_f(b['static_se'])} |"]
        L += ["", f"Goal {c['goal_s']:.0f} s: goal / time = **{c['goal_over_time']:.2f}** (> 1: under the goal); "
              f"iterative / static time in this run: {c['iterative_over_static_time']:.2f}. Stages (vectors: SE, rounds): "
              + ", ".join(f"{s['vectors']}: {_f(s['se'])} ({s['rounds']})" for s in c["stages"])
              + (f". The incremental path reached {c['vectors']} vectors with SE {_f(c['restarted_from_static']['incremental_se'])} "
                 f"> static {_f(c['restarted_from_static']['static_se'])}, so the last stage continued from the static fit."
                 if c["restarted_from_static"] else ".")]
        q = d["classify"]
        L += ["", f"{h}### The CPCA classification step", "",
              f"Exact: every point against all {q['clusters']} clusters × (1 + {q['vectors']}) representatives "
              f"(`classify_all`): {1e3 * q['exact_s']:.0f} ms; the bare GEMM of the same shape alone: {1e3 * q['gemm_s']:.0f} ms; "
              f"exact / GEMM bound = **{q['exact_over_gemm']:.2f}**. Candidate sets ({q['candidates']} clusters per cluster, "
              f"the rounds between exact passes): {1e3 * q['candidate_s']:.0f} ms, **{q['exact_over_candidate']:.1f}×** faster "
              f"than exact; same label for {q['candidate_label_agreement']:.2%} of the points on this model.", ""]
        p = d["pca"]
        L += [f"{h}### PCA, n' = {p['vectors']}", "",
              "| method | time (s) | SE | SE / optimum |", "|---|---|---|---|",
              f"| ours (pca codec fit, solver {p['solver']}) | {p['ours_s']:.3f} | {_f(p['se_ours'])} | {p['se_ours_over_optimal']:.6f} |",
              f"| scikit-learn PCA (randomized) | {p['sklearn_randomized_s']:.3f} | {_f(p['se_sklearn'])} | "
              f"{p['se_sklearn_over_optimal']:.6f} |", "",
              f"scikit-learn / ours time: **{p['time_sklearn_over_ours']:.2f}×**; SE ours / scikit-learn: "
              f"**{p['se_ours_over_sklearn']:.6f}** (optimum: float64 eigen-decomposition of the scatter matrix).", ""]
        if b:
            L += [f"Before issue 15 (codecs.json): PCA fit {b['pca_s']:.2f} s, SE {_f(b['pca_se'])}; VQ fit {b['vq_s']:.1f} s, "
                  f"inertia {_f(b['vq_inertia'])} (seed 0; ours now: SE {_f(k['ours']['se'])}, mean over seeds {k.get('seeds')}).", ""]
    return "\n".join(L)


if __name__ == "__main__":
    raise SystemExit(main())
