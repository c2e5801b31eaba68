"""Benchmark (issue 42 part 2, "defaults that work together"): what the transport table's cube
resolution does to the Gaussian codec (Green 2005), split by the view's angle from the normal.

    .venv/bin/python benchmarks/bench_transport_res.py [--scene scan_blob] [--res 8 13] [--lobes 1 2 3]
        [--vertices 150] [--spread] [--brdf phong12]

For each resolution: the transport tables of the scene (92 views, the default Ashikhmin–Shirley N = 40
or Phong s = 12; ``--spread``: the whole mesh, then every (V // vertices)-th vertex fitted; else only
the first chunks, the first ``vertices`` vertices), a Gaussian fit of N lobes (the codec's own fit,
what ``prt compress --codec gaussian --param lobes=N`` runs) and its relative L2 error
‖T̃ − T‖/‖T‖ (texel solid angles) over the whole table and over the functions whose view is 0–60°,
60–80° and 80–90° from the vertex normal, with each band's share of Σ T² Δω; the fit's fraction of
lobes at the narrowest resolvable width and whether it warned. One JSON line per fit on stdout
(docs/precompute_log.md, "Transport tables: `res: auto` — what it did to the Gaussian codec", has the tables
of a run).

Two further figures, clearly secondary to the plain relative L2 (the headline): ``rel_l2_cos``, the
same error with each function weighted by its view's projected area cos θ_o (what a view's pixels
see of the vertex), and ``relight_const``, the relative RMS difference over the functions between
the encoding's relighting under a constant unit light (Σ_k w_k: the lobes' SG integrals, what
``relight`` computes) and the table's own (Σ_p T Δω). ``--resolve-factor F [F ...]`` fits with the
codec's narrowest width at F texel spacings (``codecs.gaussian.fit.RESOLVE_FACTOR``; default: the
codec's), one row each, in the same run (issue 42 §2: 0.6 before, 0.35 after). ``--supersample S
[S ...]``: tables with texel averages over S × S sub-texels where the lobe is narrower than the
texels (``precompute_transport(supersample=S)``; 1: point values, the tables before issue 42 §2;
default 'auto'), one table each, with ``table_s`` its precompute time. ``--reference-sub R``: each
table's own error, ``table_const``: the relative RMS over the fitted functions of Σ_p T Δω against
a brute-force reference, the same vertices tabulated at (R·r)² texels per face with a ray per fine
texel and summed (∫ T dω to that resolution: what relighting from a table should give under a
constant light).
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch import brdf as B  # noqa: E402
from prt_torch import codecs  # noqa: E402
from prt_torch.scene import builtin, default_workers  # noqa: E402
from prt_torch.transfer import RunOptions, precompute_transport  # noqa: E402

BANDS = [(0, 60), (60, 80), (80, 90)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="scan_blob")
    ap.add_argument("--res", type=int, nargs="+", default=[8, 13])
    ap.add_argument("--lobes", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--vertices", type=int, default=150)
    ap.add_argument("--spread", action="store_true", help="tabulate the whole mesh and fit vertices spread over it")
    ap.add_argument("--brdf", choices=["default", "phong12"], default="default")
    ap.add_argument("--resolve-factor", type=float, nargs="+", default=[None],
                    help="the fit's narrowest lobe in texel spacings (default: the codec's RESOLVE_FACTOR)")
    ap.add_argument("--supersample", nargs="+", default=["auto"], help="sub-texels per texel side ('auto' or an integer)")
    ap.add_argument("--reference-sub", type=int, default=0, help="brute-force reference of each table's own error (0: none)")
    args = ap.parse_args(argv)
    from prt_torch.codecs.gaussian import fit as gfit
    from prt_torch.scene import RayCaster
    from prt_torch.transfer.glossy import check_frames
    from prt_torch.transfer.transport import _chunk_transport, _cube_directions

    default_rf = gfit.RESOLVE_FACTOR
    mesh = builtin(args.scene)
    brdf = B.Phong(12.0, ks=0.7, kd=0.3) if args.brdf == "phong12" else None
    tmp = Path(tempfile.mkdtemp(prefix="bench_transport_res_"))
    refs: dict[int, torch.Tensor] = {}  # the brute-force constant-light reference per res (the same vertices)
    try:
        for r, ss in [(r, ss) for r in args.res for ss in args.supersample]:
            out = tmp / f"t{r}_{ss}"
            chunk = 60
            kw = {} if args.spread else {"max_chunks": (args.vertices + chunk - 1) // chunk}
            t0 = time.perf_counter()
            t = precompute_transport(mesh, out, brdf=brdf, views=3, res=r, supersample=ss if ss == "auto" else int(ss),
                                     run=RunOptions(workers=default_workers(), chunk_size=chunk), **kw)
            table_s = time.perf_counter() - t0
            T = torch.cat([c for _, _, c in t]).float()
            idx = (torch.arange(0, T.shape[0], max(1, T.shape[0] // args.vertices)) if args.spread else torch.arange(T.shape[0]))[:args.vertices]
            T = T[idx]
            V, J = T.shape[:2]
            table_const = None
            if args.reference_sub > 1 and refs.get(r) is None:
                R = args.reference_sub
                fd, fsa = _cube_directions(r * R)
                frames = check_frames(mesh)
                with RayCaster(mesh, workers=default_workers()) as rc:
                    Tf = torch.cat([_chunk_transport(rc, brdf or B.AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0),
                                                     mesh.vertices[ii], mesh.normals[ii], frames[ii], fd.reshape(-1, 3),
                                                     t.views.double(), None, True) @ fsa.reshape(-1)[:, None]
                                    for ii in idx.split(2)])[..., 0]  # [V, J] ∫ T dω at (R r)² texels per face
                refs[r] = Tf
            if args.reference_sub > 1:
                Tf = refs[r]
                mine = (T.double().reshape(V, J, -1) * t.solid_angles.reshape(-1).double()).sum(-1)
                table_const = round(float(((mine - Tf).square().sum() / Tf.square().sum()).sqrt()), 4)
            X = T.reshape(V, -1)
            sa = t.solid_angles.reshape(-1).double()
            th = torch.rad2deg(torch.arccos((mesh.normals[idx].double() @ t.views.double().T).clamp(-1, 1)))  # [V, J]
            Td = X.reshape(V, J, -1).double()
            ref = (Td.square() * sa).sum(-1)
            cos_o = (mesh.normals[idx].double() @ t.views.double().T).clamp_min(0)  # [V, J] projected area of each view
            integ = (Td * sa).sum(-1)  # [V, J] the table's relighting under a constant unit light
            for rf, n in [(rf, n) for rf in args.resolve_factor for n in args.lobes]:
                gfit.RESOLVE_FACTOR = default_rf if rf is None else rf
                c = codecs.get("gaussian", lobes=n)
                t0, c0 = time.perf_counter(), time.process_time()
                with warnings.catch_warnings(record=True) as w:
                    warnings.simplefilter("always")
                    enc = c.fit_encode(X, matrix_shape=(J, X.shape[1] // J), views=t.views, faces=None, kind="transport")
                secs, cpu = time.perf_counter() - t0, time.process_time() - c0
                err = ((torch.as_tensor(c.decode(enc)).reshape(V, J, -1).double() - Td).square() * sa).sum(-1)
                lit = c.lobes_of(enc)[0].double().sum(-1)  # [V, J] Σ_k w_k
                row = {"scene": args.scene, "brdf": args.brdf, "res": r, "supersample": ss, "table_s": round(table_s, 1),
                       "table_const": table_const, "vertices": V, "spread": args.spread, "lobes": n,
                       "resolve_factor": gfit.RESOLVE_FACTOR, "lm_loop": c.fit_info_.get("lm_loop"),
                       "fit_s": round(secs, 1), "fit_cpu_s": round(cpu, 1), "rel_l2_all": round(float(c.fit_info_["relative_l2"]), 4),
                       "at_limit": round(float(c.fit_info_["lobes_at_resolution_limit"]), 3),
                       "warns": any("narrowest" in str(x.message) for x in w), "load": os.getloadavg()[0],
                       "rel_l2_cos": round(float(((err * cos_o).sum() / (ref * cos_o).sum()).sqrt()), 4),
                       "relight_const": round(float(((lit - integ).square().sum() / integ.square().sum().clamp_min(1e-300)).sqrt()), 4)}
                for lo, hi in BANDS:
                    m = (th >= lo) & (th < hi)
                    row[f"rel_l2_{lo}_{hi}"] = round(float((err[m].sum() / ref[m].sum().clamp_min(1e-300)).sqrt()), 4)
                    row[f"energy_{lo}_{hi}"] = round(float(ref[m].sum() / ref.sum()), 3)
                print(json.dumps(row), flush=True)
            shutil.rmtree(out, ignore_errors=True)
        gfit.RESOLVE_FACTOR = default_rf
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
