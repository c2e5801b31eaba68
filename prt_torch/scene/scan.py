"""Scan-like meshes: what a crude, topology-breaking decimation of a 3-D scan looks like.

A real scan reduced for PRT (issue 37: a Stanford scan at 8k vertices with 150 non-manifold
edges, 123 boundary edges around holes in its base and sliver triangles) differs from the
procedural built-ins in ways a ray tracer feels: open holes, edges shared by three or more
faces, folded and sliver triangles, vertex normals that disagree with their faces. This module
makes such meshes procedurally, each artefact switchable, so that tests and ``prt validate``
can pin how the engine behaves on each (docs/validate.md):

1. **Surface** — an organic blob: a geodesic sphere with radial displacement by von Mises bumps
   r(d) = 1 + Σ_k a_k exp(κ_k (d·c_k − 1)) (random centres c_k, signed amplitudes — ridges and
   narrow valleys), a flat base (a scan's table contact) and ``noise`` radial Gaussian scanner
   noise.
2. **Decimation by vertex clustering** (Rossignac & Borrel 1993) — vertices snapped to the mean
   of their cell in a uniform grid, faces re-indexed, collapsed faces dropped, repeated faces
   kept once. It does not preserve topology: thin parts collapse into non-manifold edges and
   folds, and triangles become slivers.
3. **Holes** in the base — the faces whose centroid lies in ``holes`` discs on the base removed
   (the unscanned table contact), leaving boundary edges.
4. **Non-manifold fins** — ``fins`` extra triangles, each on an existing edge with its apex off
   the surface: that edge then has three faces (a scan's stray flap).
5. **Slivers** — ``slivers`` manifold edges split at a point 2% along them in both of their
   faces: each face becomes a sliver and a fat triangle (no crack).

:func:`prt_torch.scene.mesh_features` counts what a mesh has (boundary and non-manifold edges,
slivers, vertices of each class); the validator reports its errors per class of vertex
(:func:`prt_torch.scene.vertex_classes`).
"""
from __future__ import annotations

import math

import numpy as np

from .._checks import check_float, check_int
from .geodesic import geodesic_sphere
from .mesh import Mesh, make_mesh, mesh_features

__all__ = ["scan_like", "SCAN_FEATURES"]

#: the artefacts :func:`scan_like` can add, each switchable
SCAN_FEATURES = ("decimate", "holes", "fins", "slivers", "noise")


def _blob(freq: int, rng: np.random.Generator, bumps: int, noise: float) -> tuple[np.ndarray, np.ndarray]:
    """Dense organic surface ``(vertices [V,3] float64, faces [F,3] int64)``, closed, outward CCW."""
    v, f = geodesic_sphere(freq)
    c = rng.standard_normal((bumps, 3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    amp = rng.uniform(0.15, 0.4, bumps) * rng.choice([-1.0, 1.0], bumps, p=[0.5, 0.5])
    kappa = rng.uniform(6.0, 40.0, bumps)
    r = 1.0 + (amp[None] * np.exp(kappa[None] * (v @ c.T - 1.0))).sum(1)  # [V]: sum over a handful of bumps
    p = v * r[:, None] * np.array([1.0, 0.85, 0.75])
    base = p[:, 2].min() + 0.18 * (p[:, 2].max() - p[:, 2].min())
    p[:, 2] = np.maximum(p[:, 2], base)  # the flat base the object stood on while scanned
    if noise > 0:
        p += noise * rng.standard_normal(p.shape[0])[:, None] * v
    p[:, 2] -= p[:, 2].min()
    return p, f


def _cluster(v: np.ndarray, f: np.ndarray, cell: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertex-clustering decimation (Rossignac & Borrel 1993): one vertex per occupied grid cell
    (the mean of its members), faces re-indexed, faces with a repeated vertex dropped, a face
    repeated with the same vertex set and orientation kept once."""
    key = np.floor((v - v.min(0)) / cell).astype(np.int64)
    _, inv = np.unique(key, axis=0, return_inverse=True)
    inv = inv.reshape(-1)
    n = int(inv.max()) + 1
    rep = np.zeros((n, 3))
    np.add.at(rep, inv, v)
    rep /= np.bincount(inv, minlength=n)[:, None]
    g = inv[f]
    keep = (g[:, 0] != g[:, 1]) & (g[:, 1] != g[:, 2]) & (g[:, 0] != g[:, 2])
    g = g[keep]
    rot = np.argmin(g, axis=1)  # the same cyclic order starting at the smallest index: same face, same orientation
    canon = np.stack([g[np.arange(len(g)), (rot + k) % 3] for k in range(3)], 1)
    _, first = np.unique(canon, axis=0, return_index=True)
    return rep, g[np.sort(first)]


def _punch_holes(v: np.ndarray, f: np.ndarray, holes: int, rng: np.random.Generator) -> np.ndarray:
    """The faces without those of ``holes`` discs on the flat base (facing down, at the bottom)."""
    t = v[f]
    c = t.mean(1)
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    down = fn[:, 2] < -0.8 * np.linalg.norm(fn, axis=1)
    on_base = down & (c[:, 2] - v[:, 2].min() < 0.05 * float(np.ptp(v[:, 2])))  # facing down, at the bottom
    if not on_base.any() or holes == 0:
        return f
    bc = c[on_base]
    lo, hi = bc[:, :2].min(0), bc[:, :2].max(0)
    size = float((hi - lo).min())
    drop = np.zeros(len(f), bool)
    for _ in range(holes):  # a handful of discs
        centre = bc[rng.integers(len(bc)), :2]
        radius = size * rng.uniform(0.05, 0.12)
        drop |= on_base & (np.linalg.norm(c[:, :2] - centre, axis=1) < radius)
    return f[~drop]


def _edges(f: np.ndarray) -> np.ndarray:
    """``[3F, 2]`` the faces' edges, each sorted (face k's edges at rows k, F+k, 2F+k)."""
    return np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)


def _add_fins(v: np.ndarray, f: np.ndarray, fins: int, rng: np.random.Generator, size: float) -> tuple[np.ndarray, np.ndarray]:
    """``fins`` triangles each on a distinct existing interior edge, apex off the surface along
    the edge's mean face normal and sideways: edges with three faces."""
    if fins == 0:
        return v, f
    F = len(f)
    e = _edges(f)
    key = e[:, 0] * len(v) + e[:, 1]
    uk, first, cnt = np.unique(key, return_index=True, return_counts=True)
    cand = first[cnt == 2]
    pick = rng.choice(cand, size=min(fins, len(cand)), replace=False)
    a, b = e[pick, 0], e[pick, 1]
    tri = v[f[pick % F]]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    mid = 0.5 * (v[a] + v[b])
    along = v[b] - v[a]
    side = np.cross(fn, along)
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    h = np.linalg.norm(along, axis=1, keepdims=True)
    apex = mid + h * (0.8 * fn + rng.uniform(-0.6, 0.6, (len(pick), 1)) * side) + 0.01 * size * rng.standard_normal((len(pick), 3))
    ids = len(v) + np.arange(len(pick))
    flip = rng.random(len(pick)) < 0.5
    new = np.where(flip[:, None], np.stack([b, a, ids], 1), np.stack([a, b, ids], 1))
    return np.concatenate([v, apex]), np.concatenate([f, new])


def _add_slivers(v: np.ndarray, f: np.ndarray, slivers: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """About ``slivers`` manifold edges split at a point m 2% along them, in both of their faces:
    face (x, a, b) becomes the sliver (x, a, m) and (x, m, b) — no crack, no new boundary."""
    if slivers == 0:
        return v, f
    F = len(f)
    e = _edges(f)
    key = e[:, 0] * len(v) + e[:, 1]
    order = np.argsort(key, kind="stable")
    ks = key[order]
    pair = np.nonzero((ks[1:] == ks[:-1]) & np.r_[True, ks[1:-1] != ks[:-2]] & np.r_[ks[2:] != ks[1:-1], True])[0]
    rows = np.stack([order[pair], order[pair + 1]], 1)  # [P,2] rows of _edges: the two faces of a manifold edge
    rows = rows[rng.permutation(len(rows))[: 3 * slivers]]
    faces2 = rows % F
    _, first = np.unique(faces2.reshape(-1), return_index=True)
    once = np.zeros(faces2.size, bool)
    once[first] = True
    counts = np.bincount(faces2.reshape(-1), minlength=F)
    ok = (counts[faces2] == 1).all(1)  # edges whose faces no other picked edge touches
    rows, faces2 = rows[ok][:slivers], faces2[ok][:slivers]
    a, b = e[rows[:, 0], 0], e[rows[:, 0], 1]
    m_ids = len(v) + np.arange(len(rows))
    m = v[a] + 0.02 * (v[b] - v[a])
    new = []
    for s in range(2):  # the two faces of each split edge
        fi, k = faces2[:, s], rows[:, s] // F  # edge k of face fi runs face[k] -> face[(k+1)%3]
        r = f[fi]
        r1, r2, r0 = r[np.arange(len(r)), k], r[np.arange(len(r)), (k + 1) % 3], r[np.arange(len(r)), (k + 2) % 3]
        new += [np.stack([r0, r1, m_ids], 1), np.stack([r0, m_ids, r2], 1)]
    keep = np.ones(F, bool)
    keep[faces2.reshape(-1)] = False
    return np.concatenate([v, m]), np.concatenate([f[keep]] + new)


def scan_like(vertices: int = 2000, *, seed: int = 0, features: tuple[str, ...] | str = SCAN_FEATURES, holes: int = 4,
              fins: int | None = None, slivers: int | None = None, noise: float = 0.004, bumps: int = 14,
              albedo=0.8, name: str = "scan_blob") -> Mesh:
    """A scan-like mesh (module docstring), standing on z = 0, about 2 units across.

    Args:
        vertices: about how many vertices after decimation (in [100, 200000]).
        seed: the shape, holes, fins and slivers (the same seed gives the same mesh).
        features: which artefacts to add, a subset of :data:`SCAN_FEATURES` ('all' = every one,
            'none' = the clean dense surface at ``vertices`` vertices). Without 'decimate' the
            surface is built at about ``vertices`` vertices directly (manifold, closed).
        holes: hole discs punched in the base (feature 'holes').
        fins: non-manifold fins (feature 'fins'; default 1% of the vertices).
        slivers: faces split into slivers (feature 'slivers'; default 2% of the faces).
        noise: radial scanner noise, in units of the blob's radius (feature 'noise').
        bumps: von Mises bumps of the organic surface.
        albedo: as :func:`prt_torch.scene.make_mesh` (default 0.8 grey).
    Returns:
        a :class:`Mesh` (``vertices [V,3] float64``, ``faces [F,3] int64``), repaired only of
        zero-area faces; ``meta['scan']`` holds the settings and :func:`mesh_features`' counts.
    """
    vertices = check_int("vertices", vertices, 100, 200000)
    seed = check_int("seed", seed, 0, 2**32 - 1)
    if isinstance(features, str):
        features = {"all": SCAN_FEATURES, "none": ()}.get(features, tuple(x for x in features.split(",") if x))
    bad = [x for x in features if x not in SCAN_FEATURES]
    if bad:
        raise ValueError(f"scan_like features {bad}: unknown; accepted: a subset of {list(SCAN_FEATURES)}, 'all' or 'none'")
    holes = check_int("holes", holes, 0, 64)
    noise = check_float("noise", noise, 0.0, 0.1)
    rng = np.random.default_rng(seed)
    dense = "decimate" in features
    freq = max(2, int(round(math.sqrt(max(vertices * (6 if dense else 1) - 2, 10) / 10))))
    v, f = _blob(freq, np.random.default_rng(seed + 1), check_int("bumps", bumps, 0, 256), noise if "noise" in features else 0.0)
    if dense:  # cell size for about `vertices` clusters on a surface of this extent
        area = 0.5 * np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1).sum()
        v, f = _cluster(v, f, math.sqrt(area / vertices) * 1.1)
    if "holes" in features:
        f = _punch_holes(v, f, holes, rng)
    size = float(np.linalg.norm(np.ptp(v, axis=0)))
    if "fins" in features:
        v, f = _add_fins(v, f, check_int("fins", max(1, vertices // 100) if fins is None else fins, 0, 100000), rng, size)
    if "slivers" in features:
        v, f = _add_slivers(v, f, check_int("slivers", max(1, len(f) // 50) if slivers is None else slivers, 0, 1000000), rng)
    v[:, 2] -= v[:, 2].min()
    mesh = make_mesh(v, f, albedo, name=name, merge_duplicates=False)
    mesh.meta["scan"] = {"seed": seed, "features": list(features), "holes": holes, "noise": noise, "bumps": bumps,
                         "counts": mesh_features(mesh)}
    return mesh
