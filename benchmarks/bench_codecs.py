"""Codec benchmarks, every figure a ratio against a peer or bound measured in this run.

1. Encode time of iterative CPCA (Sloan 2003 §4.2), 256 clusters, n' = 8:
   * on a 50 000 × 625 float32 synthetic transfer-like signal (``codecs.synthetic.transfer_like``:
     smooth low-rank part + piecewise-constant "shadow" regions + noise, SH-band energy decay);
   * on real glossy transfer of the built-in scene ``bumpy_sphere`` (large, 50 412 vertices),
     24×25 exit matrices with an anisotropic Ashikhmin–Shirley BRDF (N_u=40, N_v=10) — the
     setting of Sloan 2003 Table 1 ("bird gloss-anis": 48 688 vertices, 24×25, 256×8:
     static 6 m 34 s, iterative 3 h 43 m).
   Ratios: paper time / ours (the paper took 1–4.5 h per encode), and static CPCA / VQ / PCA
   against scikit-learn (KMeans, KMeans + per-cluster PCA, PCA) on the same data.
2. (Relighting throughput against the memory-bandwidth bound moved to benchmarks/bench_relight.py:
   every codec × view mode at 50 000 points, each a paired ratio to the bound measured in its run.)
3. Rate–distortion in the spirit of Sloan 2003 Fig. 10 on the glossy scene: VQ (m_c = 1792),
   PCA (n' = 20), CPCA static / iterative (256 × 8) and adaptive — the paper's settings of
   matched rendering cost — with squared error, PSNR of relit exit radiance under random SH
   lights, bytes, and measured relight time.

Threads: 2 (``torch.set_num_threads(2)``). OpenMP's wait policy is the package's choice
(``import prt_torch`` first: PASSIVE only when other processes already hold the cores, as for
any user; README "OpenMP wait policy"). The machine's load average is recorded before and after.

Run: .venv/bin/python benchmarks/bench_codecs.py   (about 10 minutes; --quick: a smoke test that prints)
Writes reports/benchmarks/codecs.md and codecs.json.
"""
from __future__ import annotations

import os

import prt_torch  # noqa: E402,F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import math  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.codecs.synthetic import transfer_like  # noqa: E402
from prt_torch.harness.timing import machine_info, measure  # noqa: E402
from prt_torch.io import atomic_write_json, atomic_write_text  # noqa: E402

OUT = Path(__file__).resolve().parent.parent / "reports" / "benchmarks"
PAPER_ITER_S = (3600.0, 4.5 * 3600.0)  # Sloan 2003 Table 1: iterative encodes took 1 h 51 m .. 4 h 34 m


def timed(fn):
    t0 = time.perf_counter()
    r = fn()
    return r, time.perf_counter() - t0


def fit(name, X, ms, **params):
    c = codecs.get(name, **params)
    enc, secs = timed(lambda: c.fit_encode(X, matrix_shape=ms))
    return c, enc, secs


def sklearn_vq_and_static(X: np.ndarray, K: int, n: int, max_iter: int, seed: int):
    from sklearn.cluster import KMeans
    from sklearn.decomposition import PCA as SKPCA

    km, t_km = timed(lambda: KMeans(n_clusters=K, n_init=1, max_iter=max_iter, random_state=seed, algorithm="lloyd").fit(X))
    t0 = time.perf_counter()
    se = 0.0
    for k in range(K):  # the peer: one scikit-learn PCA per cluster (a Python loop, as a user would write it)
        Xk = X[km.labels_ == k]
        if len(Xk) == 0:
            continue
        m = min(n, len(Xk), X.shape[1])
        p = SKPCA(n_components=m, svd_solver="full").fit(Xk)
        r = Xk - p.inverse_transform(p.transform(Xk))
        se += float((r.astype(np.float64) ** 2).sum())
    t_pca = time.perf_counter() - t0
    return {"kmeans_s": t_km, "kmeans_inertia": float(km.inertia_), "kmeans_iters": int(km.n_iter_),
            "static_s": t_km + t_pca, "static_se": se}


def encode_section(label: str, X: torch.Tensor, ms, quick: bool, sk: bool) -> dict:
    K, n = (64, 4) if quick else (256, 8)
    out = {"signal": label, "points": X.shape[0], "dim": X.shape[1], "matrix_shape": ms, "clusters": K, "vectors": n}
    it, e_it, t_it = fit("cpca_iterative", X, ms, clusters=K, vectors=n)
    st, e_st, t_st = fit("cpca_static", X, ms, clusters=K, vectors=n)
    vq, e_vq, t_vq = fit("vq", X, ms, clusters=K, max_iter=20)
    pc, e_pc, t_pc = fit("pca", X, ms, vectors=n)
    out["iterative"] = {"seconds": t_it, "se": it.fit_info_["se"], "se_relative": it.fit_info_["se_relative"],
                        "static_se_same_run": it.fit_info_["static_se"],
                        "restarted_from_static": "restarted_from_static" in it.fit_info_,
                        "stages": [{"vectors": s["vectors"], "se": s["se"], "rounds": len(s["changes"])} for s in it.fit_info_["stages"]]}
    out["paper_over_ours"] = [PAPER_ITER_S[0] / t_it, PAPER_ITER_S[1] / t_it]
    out["static"] = {"seconds": t_st, "se": st.fit_info_["se"]}
    out["vq"] = {"seconds": t_vq, "inertia": vq.fit_info_["inertia"], "iterations": vq.fit_info_["lloyd_iterations"]}
    out["pca"] = {"seconds": t_pc, "se": pc.fit_info_["se"], "eigenvalues": pc.fit_info_["eigenvalues"]}
    out["_fits"] = {"cpca_iterative": (it, e_it), "cpca_static": (st, e_st)}
    if sk:
        from sklearn.decomposition import PCA as SKPCA

        Xn = X.numpy()
        s = sklearn_vq_and_static(Xn, K, n, 20, 0)
        skp, t_skp = timed(lambda: SKPCA(n_components=n, svd_solver="full").fit(Xn))
        skr, t_skr = timed(lambda: SKPCA(n_components=n, svd_solver="randomized", random_state=0).fit(Xn))
        ev_sk = skp.explained_variance_ * (X.shape[0] - 1)
        out["sklearn"] = {**s, "pca_full_s": t_skp, "pca_randomized_s": t_skr,
                          "pca_eigenvalues": ev_sk.tolist()}
        out["ratios"] = {
            "vq_time_sklearn_over_ours": s["kmeans_s"] / t_vq,
            "vq_inertia_ours_over_sklearn": out["vq"]["inertia"] / s["kmeans_inertia"],
            "static_time_sklearn_over_ours": s["static_s"] / t_st,
            "static_se_ours_over_sklearn": out["static"]["se"] / s["static_se"],
            "pca_time_sklearn_full_over_ours": t_skp / t_pc,
            "pca_time_sklearn_randomized_over_ours": t_skr / t_pc,
            "pca_eigenvalue_max_rel_diff": float(np.max(np.abs(np.array(out["pca"]["eigenvalues"]) - ev_sk) / ev_sk)),
            "iterative_se_over_static_se": out["iterative"]["se"] / out["static"]["se"],
        }
    return out


def rd_section(X: torch.Tensor, ms, fits: dict, quick: bool, lights: int = 4) -> list[dict]:
    P = X.shape[0]
    n_out, n_in = ms
    settings = [("vq", {"clusters": 224 if quick else 1792}), ("pca", {"vectors": 20}),
                ("cpca_static", {"clusters": 64 if quick else 256, "vectors": 4 if quick else 8}),
                ("cpca_iterative", {"clusters": 64 if quick else 256, "vectors": 4 if quick else 8}),
                ("cpca_adaptive", {"clusters": 64 if quick else 256, "vectors": 4 if quick else 8, "adapt_iters": 2})]
    g = torch.Generator().manual_seed(1)
    Ls = [torch.randn(n_in, 3, generator=g) * torch.exp(-0.5 * torch.tensor([math.isqrt(i) for i in range(n_in)]))[:, None]
          for _ in range(lights)]
    M = X.view(P, n_out, n_in)
    refs = [M @ L for L in Ls]
    rows = []
    for name, params in settings:
        key = name if name in fits and not quick else None
        if key is not None and fits[key][0].params["clusters"] == params.get("clusters"):
            c, enc = fits[key]
            secs = c.fit_info_["seconds"]
        else:
            c, enc, secs = fit(name, X, ms, **params)
        st = c.storage(enc)
        psnr = []
        for L, ref in zip(Ls, refs):
            out = c.relight(enc, L)
            mse = float((out.double() - ref.double()).square().mean())
            psnr.append(10 * math.log10(float(ref.abs().max()) ** 2 / max(mse, 1e-300)))
        view = torch.randn(P, n_out, generator=g)
        t = measure(lambda: c.relight(enc, Ls[0], view=view), repeats=5, warmup=1)
        rows.append({"codec": name, "params": params, "encode_s": secs, "se": c.fit_info_["se"],
                     "se_relative": c.fit_info_["se_relative"], "psnr_db_mean": float(np.mean(psnr)),
                     "psnr_db_min": float(np.min(psnr)), "bytes_total": st["bytes_total"],
                     "compression_ratio": st["compression_ratio"], "sloan_cost_floats": st["sloan_cost_floats"],
                     "relight_view_s": t.median, "relight_macs_per_point_per_channel": st["relight_macs_per_point_per_channel"]})
    return rows


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    ap.add_argument("--no-glossy", action="store_true", help="skip the built-in glossy scene")
    args = ap.parse_args()
    torch.set_num_threads(2)
    load0 = os.getloadavg()
    t_all = time.perf_counter()
    P = 5000 if args.quick else 50000
    result: dict = {"machine": machine_info(), "omp_wait_policy": prt_torch.OMP_POLICY_CHOICE,
                    "load_average_before": load0, "quick": args.quick}

    # ---- 1. encode on the synthetic 50k x 625 signal
    X = transfer_like(P, 25, 25, seed=0)
    enc_syn = encode_section("synthetic transfer_like 25x25", X, (25, 25), args.quick, sk=True)
    fits_syn = enc_syn.pop("_fits")
    result["encode_synthetic"] = enc_syn
    print("synthetic:", {k: enc_syn[k] for k in ("iterative", "static", "ratios")})

    # ---- 1b + 3. real glossy transfer (built-in scene)
    glossy = None
    if not args.no_glossy:
        try:
            from prt_torch import brdf as B
            from prt_torch.scene import builtin
            from prt_torch.transfer.base import RunOptions
            from prt_torch.transfer.glossy import precompute_glossy

            mesh = builtin("bumpy_sphere", "small" if args.quick else "large")
            tr, t_pre = timed(lambda: precompute_glossy(mesh, bands=5, samples=256, seed=0, run=RunOptions(workers=2),
                                                        brdf=B.AshikhminShirley(40, 10, rs=0.05, rd=0.3), drop_out=[(1, 0)]))
            glossy = (tr.signal(), tuple(tr.meta["matrix_shape"]))
            result["glossy_scene"] = {"scene": "bumpy_sphere", "vertices": mesh.num_vertices, "matrix_shape": list(glossy[1]),
                                      "brdf": "Ashikhmin-Shirley N_u=40 N_v=10 Rs=0.05 Rd=0.3", "samples": 256,
                                      "precompute_s": t_pre}
        except Exception as e:  # noqa: BLE001 - the report says why the real scene was not used
            result["glossy_scene"] = {"error": f"{type(e).__name__}: {e}"}
    if glossy is not None:
        Xg, msg = glossy
        enc_g = encode_section("glossy bumpy_sphere 24x25", Xg, msg, args.quick, sk=False)
        fits_g = enc_g.pop("_fits")
        result["encode_glossy"] = enc_g
        print("glossy:", {k: enc_g[k] for k in ("iterative", "static")})
        rd_X, rd_ms, rd_fits, rd_label = Xg, msg, fits_g, "glossy bumpy_sphere (built-in scene)"
    else:
        rd_X, rd_ms, rd_fits, rd_label = X, (25, 25), fits_syn, "synthetic transfer_like (glossy scene unavailable)"

    # ---- 3. rate-distortion (Sloan 2003 Fig. 10)
    result["rate_distortion"] = {"signal": rd_label, "rows": rd_section(rd_X, rd_ms, rd_fits, args.quick)}
    for r in result["rate_distortion"]["rows"]:
        print("rd:", r["codec"], r["params"], f"SE {r['se']:.4g} PSNR {r['psnr_db_mean']:.2f} dB")

    result["seconds_total"] = time.perf_counter() - t_all
    result["load_average_after"] = os.getloadavg()
    if args.quick:  # smoke test: print, do not overwrite the report
        print(report(result))
        return 0
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_json(OUT / "codecs.json", result)
    atomic_write_text(OUT / "codecs.md", report(result))
    print(f"wrote {OUT / 'codecs.md'} in {result['seconds_total']:.0f} s")
    return 0


def _f(v, nd=3):
    if v is None:
        return "—"
    if isinstance(v, float):
        if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
            return f"{v:.{nd}e}"
        return f"{v:.{nd}g}" if abs(v) < 1000 else f"{v:.0f}"
    return str(v)


def report(r: dict) -> str:
    m = r["machine"]
    L = ["# Codec benchmarks", "",
         f"Machine: {m.get('cpu')}, {m.get('cores')} cores, torch threads {m.get('torch_threads')}, "
         f"OpenMP: {r.get('omp_wait_policy')}; load average before {tuple(round(x, 2) for x in r['load_average_before'])}, "
         f"after {tuple(round(x, 2) for x in r['load_average_after'])} (other jobs share this machine; "
         "every ratio below compares two measurements of the same run). Total {:.0f} s.".format(r["seconds_total"]),
         "", "Reproduce: `.venv/bin/python benchmarks/bench_codecs.py` (writes this file and codecs.json).", ""]
    for key, title in (("encode_synthetic", "Encode: synthetic transfer-like signal"),
                       ("encode_glossy", "Encode: glossy transfer of a built-in scene")):
        e = r.get(key)
        if not e:
            continue
        L += [f"## {title}", "",
              f"{e['signal']}: {e['points']} points × D={e['dim']} float32; {e['clusters']} clusters, n'={e['vectors']}.", ""]
        if key == "encode_glossy":
            g = r["glossy_scene"]
            L += [f"Scene {g['scene']} ({g['vertices']} vertices), {g['brdf']}, {g['samples']} samples, "
                  f"precompute {g['precompute_s']:.1f} s. Sloan 2003 Table 1, bird gloss-anis (48 688 vertices, 24×25, 256×8): "
                  "static 6 m 34 s, iterative 3 h 43 m.", ""]
        it = e["iterative"]
        L += ["| method | encode (s) | SE | relative SE |", "|---|---|---|---|",
              f"| CPCA iterative (§4.2) | {it['seconds']:.1f} | {_f(it['se'])} | {_f(it['se_relative'])} |",
              f"| CPCA static (§4.1) | {e['static']['seconds']:.1f} | {_f(e['static']['se'])} | |",
              f"| VQ (LBG, 20 iterations) | {e['vq']['seconds']:.1f} | {_f(e['vq']['inertia'])} | |",
              f"| PCA (n'={e['vectors']}) | {e['pca']['seconds']:.1f} | {_f(e['pca']['se'])} | |", "",
              f"Iterative CPCA: **{it['seconds']:.0f} s** (goal < 120 s); the paper's iterative encodes took 1–4.5 h: "
              f"**{e['paper_over_ours'][0]:.0f}–{e['paper_over_ours'][1]:.0f}× faster** (different hardware, 2003 vs today). "
              f"Stages (vectors: SE, rounds): " + ", ".join(f"{s['vectors']}: {_f(s['se'])} ({s['rounds']})" for s in it["stages"])
              + (". The incremental path ended above the static fit, so it continued from the static one."
                 if it["restarted_from_static"] else "."), ""]
        if "ratios" in e:
            q, s = e["ratios"], e["sklearn"]
            L += ["Against scikit-learn on the same data. ratio: times are scikit-learn / ours (> 1: ours faster); "
                  "inertia and SE are ours / scikit-learn (< 1: ours lower). Both clusterings are local optima of "
                  "Lloyd from k-means++ seeds; their static-PCA errors differ by tens of percent from seed to seed "
                  "(the iterative fit removes most of that sensitivity).", "",
                  "| comparison | scikit-learn | ours | ratio |", "|---|---|---|---|",
                  f"| VQ time (KMeans k-means++, 20 Lloyd iterations) | {s['kmeans_s']:.1f} s | {e['vq']['seconds']:.1f} s "
                  f"| {q['vq_time_sklearn_over_ours']:.2f}× |",
                  f"| VQ inertia | {_f(s['kmeans_inertia'])} | {_f(e['vq']['inertia'])} | {q['vq_inertia_ours_over_sklearn']:.4f} |",
                  f"| static CPCA time (KMeans + per-cluster PCA) | {s['static_s']:.1f} s | {e['static']['seconds']:.1f} s "
                  f"| {q['static_time_sklearn_over_ours']:.2f}× |",
                  f"| static CPCA SE | {_f(s['static_se'])} | {_f(e['static']['se'])} | {q['static_se_ours_over_sklearn']:.4f} |",
                  f"| PCA time (full SVD) | {s['pca_full_s']:.2f} s | {e['pca']['seconds']:.2f} s | {q['pca_time_sklearn_full_over_ours']:.2f}× |",
                  f"| PCA time (randomized) | {s['pca_randomized_s']:.2f} s | {e['pca']['seconds']:.2f} s "
                  f"| {q['pca_time_sklearn_randomized_over_ours']:.2f}× |",
                  f"| PCA eigenvalues, max relative difference | | | {q['pca_eigenvalue_max_rel_diff']:.1e} |",
                  f"| iterative SE / static SE | | | {q['iterative_se_over_static_se']:.4f} |", ""]
    rd = r["rate_distortion"]
    L += ["## Rate–distortion at matched relighting cost (Sloan 2003 Fig. 10)", "",
          f"Signal: {rd['signal']}. Settings are the paper's matched-frame-rate choices (VQ m_c=1792, PCA n'=20, "
          "CPCA 256×8). PSNR: relit exit radiance (no view, [P, n_out, 3]) under 4 random band-limited SH lights vs "
          "uncompressed, peak = max |reference|. Relight time with a dense view [P, n_out].", "",
          "| codec | params | SE | rel. SE | PSNR mean (dB) | PSNR min (dB) | bytes | ratio | Sloan floats | relight (ms) | encode (s) |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for x in rd["rows"]:
        L.append(f"| {x['codec']} | {x['params']} | {_f(x['se'])} | {_f(x['se_relative'])} | {x['psnr_db_mean']:.2f} | "
                 f"{x['psnr_db_min']:.2f} | {x['bytes_total']} | {x['compression_ratio']:.1f} | {x['sloan_cost_floats']} | "
                 f"{1e3 * x['relight_view_s']:.1f} | {x['encode_s']:.1f} |")
    L += ["", "Sloan 2003 Fig. 10 (bird, 24×25 anisotropic): PCA n'=20 SE 101 304; VQ 1792 SE 14 799; "
          "CPCA 256×8 SE 294.4 (different model and sampling; compare the ordering and the ratios). "
          "The adaptive row's bytes include its basis stored padded to max_vectors (zero rows); its Sloan float count "
          "is the packed size.", ""]
    L += ["Relighting throughput against the memory-bandwidth bound: benchmarks/bench_relight.py "
          "(reports/benchmarks/relight.md).", ""]
    return "\n".join(L)


if __name__ == "__main__":
    raise SystemExit(main())
