"""Benchmark: where the one-bounce error of the diffuse precompute comes from (issue 42 §1) — the
vertices' first-hit directions, the hit points' own estimates, or their weighting — by swapping in
a high-sample estimate for one part at a time, on a subset of vertices.

    .venv/bin/python benchmarks/bench_bounce_parts.py --ref-cache /tmp/ref_cornell.pt
        [--scene cornell_box --size small --albedo 0.8|scene] [--every 4] [--seeds 2] [--hit-samples 2 3 4 8]

The references are those of ``bench_precompute_error.py`` (its ``--ref-cache`` file, made with the
same scene, bands and reference size: 64 × 1024 samples by default): the shadowed transfer t⁰ and
the total with one bounce, 64× the default's vertex rays, independent seeds. Each row runs the
precompute's own chunk function (``diffuse._chunk``) on every ``--every``-th vertex (their ids
keep the full run's rotations, so a row's numbers are the full run's rows) and prints the
relative RMS error of the shadowed part, of the interreflected part and of the total, against
every ray traced per vertex (vertex rays + hit rays, intersect and occluded; the guide's per-face
probe is counted too). Rows:

* ``default``: N = 1024, 8 rays per hit (the precompute's defaults);
* ``hits x4`` / ``hits x16``: 32 / 128 rays per hit — the hits' own error nearly gone, what is left
  is the first-hit directions' (and the weighting's);
* ``vertices x4``: N = 4096 with 8 rays per hit;
* splits of about the same rays between first hits and hit rays (N = 1744 with 4 per hit, N = 2800
  with 2 per hit);
* ``unguided``: the default with the hits' guide switched off (every hit's rays the
  cosine-weighted set, as before the guide), and ``today``: uniform + plain.

``--hit-samples M ...`` replaces those rows (issue 42 §1, the Cornell box's margin): for each M the
default at N = 1024 with M rays per hit, then today's estimator at about the same rays — at the
perfect square N = k² nearest them (its jittered sphere set is a whole k × k grid there; other N
leave strata out and read worse than 1/√N) — with the per-seed ratio, corrected by √ of the small
remaining ray ratio, and the ratio to today's N = 1024 error scaled by 1/√rays.

Errors do not depend on the machine's load; the seconds printed do (orientation only).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from prt_torch.scene import RayCaster, builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer import diffuse as D  # noqa: E402


class Counting:
    """A RayCaster that counts the rays it traces (every query)."""

    def __init__(self, caster: RayCaster):
        self.caster, self.rays = caster, 0

    def __getattr__(self, k):
        return getattr(self.caster, k)

    def trace(self, o, d, query="occluded", tfar=None):
        self.rays += o.shape[0]
        return self.caster.trace(o, d, query, tfar)


def rel(x: torch.Tensor, ref: torch.Tensor) -> float:
    return float(((x - ref) ** 2).sum().sqrt() / (ref ** 2).sum().sqrt())


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="cornell_box")
    ap.add_argument("--size", default="small")
    ap.add_argument("--albedo", type=lambda x: None if x == "scene" else float(x), default=0.8,
                    help="a grey albedo for every vertex, or 'scene' (the scene's own; as the reference was made)")
    ap.add_argument("--bands", type=int, default=5)
    ap.add_argument("--every", type=int, default=4)
    ap.add_argument("--seeds", type=int, default=2)
    ap.add_argument("--ref-cache", required=True, help="bench_precompute_error.py's --ref-cache file for this scene")
    ap.add_argument("--hit-samples", type=int, nargs="*", default=None,
                    help="instead of the fixed rows: today's and the default at N = 1024 with each of these rays per hit")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    mesh = builtin(args.scene, args.size, albedo=args.albedo)
    V = mesh.num_vertices
    if not os.path.exists(args.ref_cache):
        sys.exit(f"--ref-cache {args.ref_cache}: no such file; accepted: a file bench_precompute_error.py --ref-cache wrote")
    ref = torch.load(args.ref_cache)
    if ref["key"]["mesh"] != mesh.content_hash() or ref["key"]["bands"] != args.bands:
        sys.exit(f"--ref-cache {args.ref_cache}: made for {ref['key']['scene']} (bands {ref['key']['bands']}, albedo "
                 f"{ref['key']['albedo']}); accepted: the same scene, size, albedo and bands")
    sub = np.arange(0, V, args.every)
    ref0, ref1 = ref["ref0"][sub], ref["ref1"][sub]
    refi = ref1 - ref0
    caster = RayCaster(mesh, workers=1, offset=RunOptions().offset).start()
    nudge = D.boundary_nudge(mesh)
    t = mesh.vertices.numpy()[mesh.faces.numpy()]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    print(f"[parts] {args.scene}:{args.size} {len(sub)} of {V} vertices; reference {ref['key']['ref_n']} samples; "
          f"CPU {os.uname().machine}, load {os.getloadavg()[0]:.1f}")

    def one(N, Mh, sampling, est, seed, guided=True):
        hb = D.HitBounce(mesh, args.bands, Mh, seed, 1, 1, D.HIT_OFFSET, est)
        probe = 0
        if est != "plain":
            hb.face_openness(caster)
            probe = D.FACE_PROBE_RAYS * mesh.faces.shape[0] / V
            if not guided:
                hb.guided[:] = False
        cc = Counting(caster)
        out = D._chunk(cc, D.DiffuseSampler(args.bands, N, seed, sampling, est), mesh.vertices[sub], mesh.normals[sub],
                       None, mesh.faces.numpy(), fn, V, True, "hits", hb, 0, nudge[sub], ids=sub)
        return out["T"], out["TB"][:, 0, 0], cc.rays / len(sub) + probe

    rows = [("today (uniform + plain)", 1024, 8, "uniform", "plain", True),
            ("default (qmc + auto)", 1024, 8, "qmc", "auto", True),
            ("unguided hits", 1024, 8, "qmc", "auto", False),
            ("hits x4 (32 rays each)", 1024, 32, "qmc", "auto", True),
            ("hits x16 (128 rays each)", 1024, 128, "qmc", "auto", True),
            ("vertices x4 (N = 4096)", 4096, 8, "qmc", "auto", True),
            ("split: N = 1744, 4 per hit", 1744, 4, "qmc", "auto", True),
            ("split: N = 2800, 2 per hit", 2800, 2, "qmc", "auto", True),
            ("split, unguided: N = 1744, 4 per hit", 1744, 4, "qmc", "auto", False)]
    print("| row | rays / vertex | shadowed | interreflected part | total, 1 bounce |")
    print("|---|---:|---:|---:|---:|")

    def measure(name, N, Mh, sampling, est, guided):
        e = []
        t0 = time.perf_counter()
        for s in range(args.seeds):
            T, TB, r = one(N, Mh, sampling, est, s, guided)
            e.append((r, rel(T, ref0), rel(TB, refi), rel(T + TB, ref1)))
        e = np.array(e)
        m = e.mean(0)
        print(f"| {name} | {m[0]:.0f} | {m[1]:.4f} | {m[2]:.4f} | {m[3]:.4f} |  <!-- total per seed "
              f"{' / '.join(f'{x:.4f}' for x in e[:, 3])}; {time.perf_counter() - t0:.0f} s -->", flush=True)
        return e

    if args.hit_samples is None:
        for row in rows:
            measure(*row)
    else:  # each rays-per-hit setting against today's estimator at the N that traces the same rays
        today = measure(*rows[0])
        for m in args.hit_samples:
            d = measure(f"default, {m} per hit", 1024, m, "qmc", "auto", True)
            # today at a perfect square N (its jittered set a whole k × k grid) near the default's rays; the rest of
            # the difference in rays corrected by √(rays ratio); and today's N = 1024 error scaled by 1/√rays
            k = max(1, int(round(math.sqrt(1024 * d[:, 0].mean() / today[:, 0].mean()))))
            t = measure(f"today at N = {k * k} (about equal rays)", k * k, 8, "uniform", "plain", True)
            q = d[:, 3] / t[:, 3] * math.sqrt(d[:, 0].mean() / t[:, 0].mean())
            c = d[:, 3] / (today[:, 3].mean() * math.sqrt(today[:, 0].mean() / d[:, 0].mean()))
            print(f"|  ratio at equal rays, per seed: {' / '.join(f'{x:.3f}' for x in q)}; on the means {q.mean():.3f}; "
                  f"against today's N = 1024 scaled by 1/√rays: {' / '.join(f'{x:.3f}' for x in c)} | | | | |", flush=True)
    caster.close()


if __name__ == "__main__":
    main()
