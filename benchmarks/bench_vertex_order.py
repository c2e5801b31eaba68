"""Diagnostic (issue 42 part 3, item 4): does the vertex order of bumpy_sphere:xl slow the diffuse precompute's rays at 1M?

    .venv/bin/python benchmarks/bench_vertex_order.py

Bare Embree occlusion rays (RayCaster, one worker, 32 rays per vertex in each vertex frame, float32),
traced in chunks of 1024 vertices as the precompute does, over the first 131072 vertices of three
orders: the file order (the mesh as built), Morton (Z-order of the positions on a 1024³ grid) and a
random permutation. Prints ns per ray for each (two rounds) and the spatial extent of a chunk.
Results and the machine: reports/benchmarks/vertex_order.md.
"""
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from prt_torch.scene import RayCaster, load_scene  # noqa: E402


def spread(x):
    """The bits of a 10-bit integer spread three apart (Morton interleave)."""
    x &= 0x3ff
    x = (x | (x << 16)) & 0x30000ff
    x = (x | (x << 8)) & 0x300f00f
    x = (x | (x << 4)) & 0x30c30c3
    return (x | (x << 2)) & 0x9249249


def main() -> None:
    mesh = load_scene("bumpy_sphere:xl")
    V = mesh.num_vertices
    P = mesh.vertices.numpy()
    N = mesh.normals.numpy()
    q = ((P - P.min(0)) / np.ptp(P, 0).max() * 1023).astype(np.int64)
    mo = np.argsort(spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2), kind="stable")
    for name, order in (("file order", np.arange(V)), ("Morton", mo)):
        ext = [np.ptp(P[order[i:i + 1024]], 0).max() for i in range(0, V, V // 20)]
        print(f"chunk extent ({name}), median {np.median(ext):.3f}")
    caster = RayCaster(mesh, workers=1)
    F = mesh.frames().numpy()
    rpv = 32
    u = (np.arange(rpv) + 0.5) / rpv
    phi = 2 * np.pi * ((np.arange(rpv) * 0.6180339887498949) % 1.0)
    r = np.sqrt(1 - u * u)
    local = np.stack([r * np.cos(phi), r * np.sin(phi), u], 1)

    def run(order, n=131072):
        t = 0.0
        for i in range(0, n, 1024):
            idx = order[i:i + 1024]
            d = np.einsum("nk,vkj->vnj", local, F[idx]).reshape(-1, 3).astype(np.float32)
            o = np.repeat(caster.local(P[idx]) + 1e-4 * N[idx], rpv, axis=0).astype(np.float32)
            t0 = time.perf_counter()
            caster.trace(o, d)
            t += time.perf_counter() - t0
        return t / (n * rpv)

    caster.trace(np.zeros((4, 3), np.float32), np.ones((4, 3), np.float32))
    rng = np.random.default_rng(0)
    for _ in range(2):
        a, b, c = run(np.arange(V)), run(mo), run(rng.permutation(V))
        print(f"ns/ray: file order {a * 1e9:.0f}, Morton {b * 1e9:.0f}, random {c * 1e9:.0f}  load {os.getloadavg()[0]:.1f}",
              flush=True)
    caster.close()


if __name__ == "__main__":
    main()
