"""Diagnosis (issue 42 §2): why ``prt bench gaussian``'s PSNR at the view taps falls with more lobes
while the tables' error falls — one factor at a time, against a brute-force truth.

    .venv/bin/python benchmarks/bench_gaussian_taps.py [--table DIR] [--config gaussian] [--lobes 1 2 3]
        [--every 4] [--res 56] [--out reports/benchmarks/gaussian_taps]

``--table``: a complete transport directory of the config's scene (``prt bench gaussian`` leaves it in
``cache/transfer-transport-*``; without it the table is computed into ``--cache`` through the harness's
``compute_transfer``, overrides after ``--set``). The config's lights and cameras (harness
``camera_positions``, ``Evaluator.view_weights``: the three stored views nearest each vertex's direction
to the camera, barycentric, zero below the horizon) are used as ``prt bench`` uses them.

Per lobe count (the codec's own fit, ``codecs.get('gaussian', lobes=N)`` with the harness's geometry) and
per (light, camera), the per-vertex RGB radiance of:

* ``table at taps``: the harness's reference before issue 42 §2 (``Evaluator.uncompressed``: the table
  relit at the three tapped views and blended linearly — a cross-fade of three views' radiance);
* ``exact``: the harness's reference since (``Evaluator.reference`` → ``exact_transport``: the table's
  texels with their stored visibility and the BRDF at each vertex's own view, sub-texel sums), what
  ``prt bench`` now measures every codec against — itself checked here against the brute-force truth;
* ``codec relight``: what ``prt bench`` measures (Green 2005 §2.3: the tapped views' lobes blended —
  weights and widths linearly, means as the normalised sum — then eq. 2.7 by prefiltered lookups);
* ``param blend, f64``: the same blended lobes, E_σ(μ) = ∫ G(ω; μ, σ) L(ω) dω in float64 by Funk–Hecke
  (``gaussian.sh_light_lobe_integral``; the lights are SH);
* ``radiance blend``: every tapped view relit alone by the codec (prefiltered lookups), the three
  radiances blended linearly as the reference blends the table's;
* ``decoded table``: the fitted lobes evaluated at the texel centres (``codec.decode``) relit as the
  reference relights the table (texel sums, radiance blend);
* at every stored view (no interpolation): the codec's lookups and the float64 evaluation against the table;
* ``codec relight as fitted (fill_empty=False)``: the lobes before ``gaussian.fill_empty_lobes`` (the rows
  above are with it, the codec's default since issue 42 §2; it leaves the tables unchanged), and how often
  a camera's taps meet a zero function or a lobe that appears or vanishes (``tap_incidence``).

And the truth at each vertex's own view direction (no view interpolation at all), for every ``--every``-th
vertex: L_o = Σ_p f_r(ω_p, ω_o) V(ω_p) max(n·ω_p, 0) L(ω_p) Δω_p over a ``--res`` cube map's texel centres
(brute force: one Embree shadow ray per texel above the horizon, the BRDF of the table's manifest — the
default Ashikhmin–Shirley N = 40), checked against the table at two stored views. PSNR as the harness
(``metrics.psnr_vs_reference``: peak = max of the reference, mean over the lights and cameras). Accuracy
only, no timing; the CPU and load average are recorded anyway.

``--pca 4 8``: PCA settings of the same tables (``codecs.get('pca', vectors=K)``, relit at the same taps),
each against the same three references: the before/after of ``prt bench gaussian``'s PCA rows.
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import copy  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs, relight  # noqa: E402
from prt_torch.codecs.gaussian import blend_lobes, fill_empty_lobes, sh_light_lobe_integral  # noqa: E402
from prt_torch.harness.config import load_config  # noqa: E402
from prt_torch.harness.evaluate import Evaluator, load_directory_transfer  # noqa: E402
from prt_torch.harness.metrics import psnr_vs_reference, squared_error  # noqa: E402
from prt_torch.harness.timing import cpu_label  # noqa: E402
from prt_torch.sh import eval_sh  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def tap_blend(R: torch.Tensor, idx: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
    """Σ_t a_t R[v, idx_t] for per-view radiance ``R [V, J, C]`` → ``[V, C]`` (the reference's blend)."""
    rows = torch.arange(R.shape[0])[:, None]
    return (R[rows, idx] * a[..., None].to(R.dtype)).sum(1)


def tap_incidence(w: torch.Tensor, views: list) -> list[dict]:
    """Per camera, over the vertices it sees: the fraction with a tapped view whose function is zero (every
    lobe weight 0: a stored view below the vertex's horizon) and the fraction where some lobe carries > 10%
    of its function's weight at one tap and < 2% at another (appearing or vanishing between the taps).
    ``w [V, J, N]`` fitted weights; ``views``: the harness's taps per camera."""
    out = []
    tot = w.sum(-1)
    share = w / tot.clamp_min(1e-30)[..., None]
    for idx, a in views:
        seen = a.sum(1) > 0
        rows = torch.arange(w.shape[0])[:, None]
        ti, sh, act = tot[rows, idx], share[rows, idx], (a > 0)[..., None]
        zero = ((ti <= 0) & (a > 0)).any(1) & seen
        van = (((sh > 0.10) & act).any(1) & ((sh < 0.02) & act & (ti > 0)[..., None]).any(1)).any(1) & seen
        n = max(1, int(seen.sum()))
        out.append({"seen": int(seen.sum()), "zero_function_tap": float(zero.sum()) / n, "lobe_appears_or_vanishes": float(van.sum()) / n})
    return out


def brute_force(ev: Evaluator, lights: list, cams: torch.Tensor, every: int, res: int) -> tuple[torch.Tensor, dict, list]:
    """The truth at every ``every``-th vertex's own direction to each camera: ``{cam: [lights, k, C]}``
    float64, and the table-vs-brute-force PSNR at two stored views (the brute force's own check)."""
    from prt_torch.brdf import AshikhminShirley
    from prt_torch.scene import RayCaster
    from prt_torch.transfer.transport import cube_directions

    b = ev.transfer.meta.get("brdf") or {}
    if b.get("model", "ashikhmin_shirley") != "ashikhmin_shirley":
        raise ValueError(f"table BRDF {b.get('model')!r}; accepted: ashikhmin_shirley (the config's)")
    brdf = AshikhminShirley(float(b.get("nu", 40.0)), float(b.get("nv", 40.0)), rs=float(b.get("rs", 0.05)),
                            rd=float(b.get("rd", 0.0)))
    dirs, sa = cube_directions(res)
    dirs, sa = dirs.reshape(-1, 3).double(), sa.reshape(-1).double()
    Ls = [eval_sh(dirs, math.isqrt(L.shape[1])) @ L.double().T for L in lights]  # [P, C]
    S = torch.arange(0, ev.V, every)
    F, pts = ev.frames[S], ev.points[S]
    nrm = F[:, 2]
    cos = nrm @ dirs.T
    W = cos.clamp_min(0)
    i, j = torch.nonzero(cos > 0, as_tuple=True)
    occ = RayCaster(ev.transfer.mesh, workers=1, offset=float(ev.transfer.meta.get("offset", 1e-4))).occluded(
        pts[i], dirs[j], normals=nrm[i])
    W[i[occ], j[occ]] = 0
    wi = torch.einsum("kab,pb->kpa", F, dirs)

    def radiance(wdir: torch.Tensor) -> torch.Tensor:  # [k, 3] world view directions -> [lights, k, C]
        wo = torch.einsum("kab,kb->ka", F, wdir)
        f = brdf.eval(wi.reshape(-1, 3), wo[:, None].expand(-1, wi.shape[1], -1).reshape(-1, 3)).view(len(S), -1)
        return torch.stack([(f * W * sa) @ L for L in Ls])

    truth = {}
    for ci, c in enumerate(cams):
        d = c[None].double() - pts
        truth[ci] = radiance(d / d.norm(dim=-1, keepdim=True))
    P = ev.matrix_shape[1]
    checks = []
    for jj in (0, ev.views.shape[0] // 2):
        tab = ev.X.view(ev.V, -1, P)[S, jj].double() @ ev.light_matrix(lights[0]).double()
        checks.append(psnr_vs_reference(radiance(ev.views[jj][None].expand(len(S), 3))[0], tab))
    return S, truth, checks


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="gaussian")
    ap.add_argument("--set", nargs="*", default=[], help="config overrides (e.g. transfer.views=3)")
    ap.add_argument("--table", type=Path, default=None)
    ap.add_argument("--cache", type=Path, default=ROOT / "cache")
    ap.add_argument("--lobes", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--res", type=int, default=56)
    ap.add_argument("--out", type=Path, default=ROOT / "reports/benchmarks/gaussian_taps")
    ap.add_argument("--pca", type=int, nargs="*", default=[], help="PCA vector counts to measure too")
    args = ap.parse_args(argv)
    torch.manual_seed(0)
    cfg = load_config(args.config, args.set)
    if args.table is not None:
        tr = load_directory_transfer(args.table)
    else:
        from prt_torch.harness.run import compute_transfer, load_mesh_within_budget

        tr, _ = compute_transfer(cfg, load_mesh_within_budget(cfg)[0], args.cache, progress=False)
    ev = Evaluator(tr)
    lights, cams, views = ev.config_views(cfg)
    S, truth, checks = brute_force(ev, lights, cams, args.every, args.res)
    V, J = ev.V, ev.views.shape[0]
    head = {"cpu": cpu_label(), "load": os.getloadavg(), "vertices": V, "views": J, "res": ev.res, "config": args.config,
            "set": args.set, "truth_vertices": len(S), "truth_res": args.res, "truth_vs_table_at_stored_views_db": checks}
    print(json.dumps(head), flush=True)
    exact = {(li, vi): ev.reference(L, v) for li, L in enumerate(lights) for vi, v in enumerate(views)}
    head["exact_reference"] = ev.reference_info
    head["exact_reference_vs_truth_db"] = [psnr_vs_reference(truth[vi][li], exact[li, vi][S])
                                           for li in range(len(lights)) for vi in range(len(views))]
    head["table_at_taps_vs_truth_db"] = [psnr_vs_reference(truth[vi][li], ev.uncompressed(L, v)[S])
                                         for li, L in enumerate(lights) for vi, v in enumerate(views)]
    rows = []
    for K in args.pca:
        codec = codecs.get("pca", vectors=K)
        enc = codec.fit_encode(ev.X, matrix_shape=ev.matrix_shape)
        res: dict[str, list] = {}
        for li, L in enumerate(lights):
            Lm = ev.light_matrix(L)
            for vi, v in enumerate(views):
                out = codec.relight(enc, Lm, view=v)
                for k, ref in (("vs table at taps", ev.uncompressed(L, v)), ("vs exact (harness reference)", exact[li, vi])):
                    res.setdefault(k + ": pca relight", []).append(psnr_vs_reference(ref, out))
                res.setdefault("vs truth: pca relight", []).append(psnr_vs_reference(truth[vi][li], out[S]))
        rec = {"pca": K, "relative_l2": squared_error(ev.X, codec.decode(enc).float())[1] ** 0.5,
               "psnr_db": {k: {"mean": sum(v) / len(v), "each": v} for k, v in res.items()}}
        print(json.dumps(rec), flush=True)
        rows.append(rec)
    for N in args.lobes:
        # fitted as before issue 42 §2's fill (fill_empty=False), then filled as the codec now does by default
        # (gaussian.fill_empty_lobes on the fitted lobes: weights, hence the tables, unchanged)
        codec = codecs.get("gaussian", lobes=N, fill_empty=False)
        enc = codec.fit_encode(ev.X, matrix_shape=ev.matrix_shape, **ev.fit_kwargs(codec))
        w, mu, sg = codec.lobes_of(enc)
        fitted = copy.copy(enc)
        fitted.tensors, fitted.cache = dict(enc.tensors), {}
        wf, mf, sf = fill_empty_lobes(w, mu, sg, ev.views)
        enc.tensors["lobes_by_view"] = torch.cat([wf[..., None], mf, sf[..., None]], -1).transpose(0, 1).contiguous()
        enc.cache.clear()
        mu, sg = mf, sf
        Xh = codec.decode(enc).float().view(V, J, -1)
        res: dict[str, list] = {}
        incidence = tap_incidence(w, views)

        def put(key, ref, test):
            res.setdefault(key, []).append(psnr_vs_reference(ref, test))

        for li, L in enumerate(lights):
            pe = ev.codec_light(codec, L)
            for vi, v in enumerate(views):
                out = codec.relight(fitted, pe, view=v)
                put("vs exact (harness reference): codec relight as fitted (fill_empty=False)", exact[li, vi], out)
                put("vs truth: codec relight as fitted (fill_empty=False)", truth[vi][li], out[S])
            Lm = ev.light_matrix(L).T
            every = codec.relight(enc, pe)  # [V, J, C]
            ex = (w.double()[..., None] * sh_light_lobe_integral(L, mu.reshape(-1, 3), sg.reshape(-1)).view(V, J, N, -1)).sum(2)
            table_views = torch.einsum("vjp,cp->vjc", ev.X.view(V, J, -1).double(), Lm.double())
            put("stored views: codec lookups vs table", table_views, every)
            put("stored views: f64 lobes vs table", table_views, ex)
            for vi, (idx, a) in enumerate(views):
                ref = ev.uncompressed(L, (idx, a))
                rows_ = torch.arange(V)[:, None]
                tot = a.sum(1, keepdim=True)
                wb, mb, sb = blend_lobes(w[rows_, idx].double(), mu[rows_, idx].double(), sg[rows_, idx].double(),
                                         (a / tot.clamp_min(1e-12)).double())
                outs = {"table at taps (harness reference before)": ref,
                        "codec relight (param blend, lookups)": codec.relight(enc, pe, view=(idx, a)),
                        "param blend, f64": (wb[..., None] * sh_light_lobe_integral(L, mb.reshape(-1, 3), sb.reshape(-1)).view(V, N, -1)
                                             ).sum(1) * tot.double(),
                        "radiance blend, lookups": tap_blend(every, idx, a),
                        "decoded table at taps": relight.apply_taps(Xh, Lm, idx, a)}
                for k, v in outs.items():
                    if k != "table at taps (harness reference before)":
                        put("vs table at taps: " + k, ref, v)
                        put("vs exact (harness reference): " + k, exact[li, vi], v)
                    put("vs truth: " + k, truth[vi][li], v[S])
        rec = {"lobes": N, "relative_l2": codec.fit_info_["relative_l2"], "tap_incidence": incidence,
               "psnr_db": {k: {"mean": sum(v) / len(v), "each": v} for k, v in res.items()}}
        rows.append(rec)
        print(json.dumps(rec), flush=True)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out.with_suffix(".json"), json.dumps({"head": head, "rows": rows}, indent=1))
    mean = lambda x: sum(x) / len(x)  # noqa: E731
    lines = [f"CPU: {head['cpu']}; load average {head['load'][0]:.1f}. {V} vertices × {J} views, 6×{ev.res}×{ev.res} tables "
             f"({args.config} {' '.join(args.set)}); truth at {len(S)} vertices (every {args.every}th), {args.res}² texels a face "
             f"(vs the table at two stored views: {checks[0]:.1f} / {checks[1]:.1f} dB).", "",
             f"References vs truth (mean over lights × cameras): the exact reference (harness, visibility "
             f"{head['exact_reference']['visibility']}) {mean(head['exact_reference_vs_truth_db']):.2f} dB; the table at the taps "
             f"cross-faded (the reference before) {mean(head['table_at_taps_vs_truth_db']):.2f} dB.", ""]
    for group in ([r for r in rows if "pca" in r], [r for r in rows if "lobes" in r]):
        if not group:
            continue
        name = (lambda r: f"pca {r['pca']}") if "pca" in group[0] else (lambda r: f"{r['lobes']} lobe{'s' if r['lobes'] > 1 else ''}")
        lines += ["| PSNR dB (mean over lights × cameras) | " + " | ".join(name(r) for r in group) + " |",
                  "|---|" + "---|" * len(group),
                  "| table relative L2 | " + " | ".join(f"{r['relative_l2']:.3f}" for r in group) + " |"]
        for k in group[0]["psnr_db"]:
            lines.append(f"| {k} | " + " | ".join(f"{r['psnr_db'][k]['mean']:.2f}" for r in group) + " |")
        if "tap_incidence" in group[0]:
            for key, what in (("zero_function_tap", "seen vertices with a zero-function tap (per camera)"),
                              ("lobe_appears_or_vanishes", "seen vertices with a lobe > 10% at one tap, < 2% at another")):
                lines.append(f"| {what} | " + " | ".join(" / ".join(f"{c[key]:.3f}" for c in r["tap_incidence"]) for r in group) + " |")
        lines.append("")
    atomic_write_text(args.out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
