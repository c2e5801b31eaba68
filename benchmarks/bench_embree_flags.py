"""Benchmark: what embreex lets us change about Embree's BVH, paired against the default (issue 42 part 3).

    .venv/bin/python benchmarks/bench_embree_flags.py [--sizes 10242 998562] [--repeats 5]
        [--out reports/benchmarks/embree_flags.md]

At 1M vertices a bare Embree occlusion ray costs up to ~1.9× one at 10k (``scale.md``: the BVH of
2M triangles outgrows the caches). embreex 4 exposes, of Embree's scene and build settings, only
``EmbreeScene(robust=True)`` (``RTC_SCENE_FLAG_ROBUST``); not ``RTC_SCENE_FLAG_COMPACT``, not the
build quality, not the device configuration string (checked: ``EmbreeDevice()`` takes no
arguments). So the experiment is default against robust, on ``bumpy_sphere:<size>``:

* build: CPU seconds (``time.process_time``) and the RSS growth of building and committing the
  scene (first trace);
* rays: 32 occlusion rays per vertex (a hemisphere set in each vertex frame, as ``bench_scale``'s
  ``embree`` stage) from 32768 vertices spread evenly over the whole mesh (every part of the BVH is
  visited, as a precompute does), traced by both scenes alternately ``--repeats`` times, one
  thread; per ray CPU nanoseconds (median), the paired ratio robust / default (median, min, max)
  and whether both scenes give the same answers.

The machine is shared (the load average is recorded); CPU time, paired and alternated, is what
the load moves least.
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def rays(mesh, k: int = 32768, rpv: int = 32):
    """Origins and directions float32 ``[k·rpv, 3]``: ``rpv`` directions over each of ``k``
    vertices' upper hemispheres (uniform in solid angle, golden-angle azimuths), vertices evenly
    spaced over the mesh's order."""
    V = mesh.num_vertices
    idx = np.unique(np.linspace(0, V - 1, min(k, V)).round().astype(np.int64))
    u = (np.arange(rpv) + 0.5) / rpv
    phi = 2 * np.pi * ((np.arange(rpv) * 0.6180339887498949) % 1.0)
    r = np.sqrt(1 - u * u)
    local = np.stack([r * np.cos(phi), r * np.sin(phi), u], 1)
    F = mesh.frames().numpy()[idx]
    d = np.einsum("nk,vkj->vnj", local, F).reshape(-1, 3).astype(np.float32)
    o = np.repeat((mesh.vertices.numpy()[idx] + 1e-4 * mesh.normals.numpy()[idx]), rpv, axis=0).astype(np.float32)
    return np.ascontiguousarray(o), np.ascontiguousarray(d)


def build(mesh, robust: bool):
    from embreex import rtcore_scene
    from embreex.mesh_construction import TriangleMesh

    r0, c0 = rss(), time.process_time()
    scene = rtcore_scene.EmbreeScene(robust=True) if robust else rtcore_scene.EmbreeScene()
    TriangleMesh(scene, np.ascontiguousarray(mesh.vertices.numpy(), np.float32),
                 np.ascontiguousarray(mesh.faces.numpy(), np.int32))
    one = np.zeros((1, 3), np.float32)
    scene.run(one, one + np.float32([0, 0, 1]), query="OCCLUDED")  # the commit (BVH build) happens on the first query
    return scene, time.process_time() - c0, rss() - r0


def trace(scene, o, d, chunk: int = 1 << 18):
    out = np.empty(o.shape[0], np.int32)
    c = time.process_time()
    for s in range(0, o.shape[0], chunk):
        out[s:s + chunk] = scene.run(o[s:s + chunk], d[s:s + chunk], query="OCCLUDED")
    return time.process_time() - c, out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[10242, 998562])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=str(ROOT / "reports" / "benchmarks" / "embree_flags.md"))
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    from prt_torch import io
    from prt_torch.harness.timing import machine_info
    from prt_torch.scene import load_scene

    info = machine_info()
    load0 = os.getloadavg()[0]
    rows = []
    for size in args.sizes:
        mesh = load_scene(f"bumpy_sphere:{size}")
        o, d = rays(mesh)
        res = {}
        for robust in (False, True):
            scene, bsec, brss = build(mesh, robust)
            res[robust] = {"scene": scene, "build_cpu": bsec, "build_rss": brss, "times": []}
        trace(res[False]["scene"], o[:4096], d[:4096])  # warm-up
        trace(res[True]["scene"], o[:4096], d[:4096])
        same = True
        ratios = []
        for i in range(args.repeats):
            order = (False, True) if i % 2 == 0 else (True, False)
            got = {}
            for robust in order:
                t, hit = trace(res[robust]["scene"], o, d)
                res[robust]["times"].append(t / o.shape[0])
                got[robust] = hit
            same &= bool(np.array_equal(got[False] != -1, got[True] != -1))
            ratios.append(res[True]["times"][-1] / res[False]["times"][-1])
        row = {"vertices": mesh.num_vertices, "faces": mesh.num_faces, "rays": int(o.shape[0]), "same": same,
               "ratio_median": statistics.median(ratios), "ratio_min": min(ratios), "ratio_max": max(ratios)}
        for rb, v in res.items():
            name = "robust" if rb else "default"
            row.update({f"{name}_build_cpu": v["build_cpu"], f"{name}_build_rss": v["build_rss"],
                        f"{name}_ns": statistics.median(v["times"]) * 1e9})
        rows.append(row)
        print(f"V={mesh.num_vertices}: default {rows[-1]['default_ns']:.0f} ns/ray, robust {rows[-1]['robust_ns']:.0f}, "
              f"robust/default {rows[-1]['ratio_median']:.3f} [{rows[-1]['ratio_min']:.3f}, {rows[-1]['ratio_max']:.3f}], "
              f"same answers {same}", flush=True)
        del res
    load1 = os.getloadavg()[0]
    fam = {}
    with open("/proc/cpuinfo") as f:  # family/model: which kernels Embree picks (AVX2 vs AVX-512) is named by the flags
        for line in f:
            k, _, v = line.partition(":")
            if k.strip() in ("cpu family", "model", "flags") and k.strip() not in fam:
                fam[k.strip()] = v.strip()
    isa = "AVX-512" if "avx512f" in fam.get("flags", "").split() else "AVX2" if "avx2" in fam.get("flags", "").split() else "SSE"
    info["cpu"] = f"{info['cpu']} (CPU family {fam.get('cpu family', '?')} model {fam.get('model', '?')}; Embree's {isa} path)"
    cmd = "python benchmarks/bench_embree_flags.py " + " ".join(argv if argv is not None else sys.argv[1:])
    L = ["# Embree's BVH at 1M vertices: what embreex exposes, paired against the default (issue 42 part 3)", "",
         f"`{cmd}` on {info['cpu']}, {info['cores']} cores, "
         f"one thread, CPU time (`time.process_time`); load average {load0:.1f} at the start, {load1:.1f} at the end "
         "(shared machine: the ratios are paired and alternated in one process, the absolute nanoseconds are not "
         "quiet-machine figures).", "",
         "embreex 4 exposes one scene flag, `robust` (`RTC_SCENE_FLAG_ROBUST`); `RTC_SCENE_FLAG_COMPACT`, the build "
         "quality and the device configuration are not reachable from Python through it. Rays: 32 occlusion rays per "
         "vertex from 32768 vertices spread evenly over the mesh.", "",
         "| vertices | faces | rays | default ns / ray | robust ns / ray | robust / default (median [min, max]) | "
         "build CPU s default | robust | build RSS MiB default | robust | same answers |",
         "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|:---:|"]
    for r in rows:
        L.append(f"| {r['vertices']} | {r['faces']} | {r['rays']} | {r['default_ns']:.0f} | {r['robust_ns']:.0f} | "
                 f"{r['ratio_median']:.3f} [{r['ratio_min']:.3f}, {r['ratio_max']:.3f}] | {r['default_build_cpu']:.2f} | "
                 f"{r['robust_build_cpu']:.2f} | {r['default_build_rss'] / 2**20:.0f} | {r['robust_build_rss'] / 2**20:.0f} | "
                 f"{'yes' if r['same'] else 'no'} |")
    if len(rows) >= 2:
        a, b = rows[0], rows[-1]
        L += ["", f"Per-ray cost at {b['vertices']} over {a['vertices']} vertices: default "
              f"{b['default_ns'] / a['default_ns']:.2f}×, robust {b['robust_ns'] / a['robust_ns']:.2f}×."]
    out = Path(args.out)
    with io.atomic_path(out, overwrite=True) as t:
        Path(t).write_text("\n".join(L) + "\n")
    io.atomic_write_json(out.with_suffix(".json"), {"machine": info, "load": [load0, load1], "rows": rows, "command": cmd})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
