"""Built-in procedural scenes (no downloads), +z up, standing on the plane z = 0.

Each exercises what PRT is for:

* ``convex``            — an ellipsoid resting on z = 0, alone: no self-occlusion, so shadowed
                          transfer equals unshadowed transfer.
* ``sphere_on_plane``   — a unit sphere touching a square ground plane: contact shadow with an
                          analytic visible solid angle (see ``sphere_on_plane_visibility``).
* ``occluder_over_plane`` — a square receiver and a smaller square slab above it
                          (the "simple two-polygon scene" of Sloan 2003, Fig. 6).
* ``bumpy_sphere``      — a radially displaced sphere with deep valleys: strong self-shadowing
                          and interreflection.
* ``cornell_box``       — an open-front box (white floor/ceiling/back, red left (−x) wall,
                          green right (+x) wall) with two white blocks: concave, colour bleeding.
* ``scan_blob``         — a scan-like mesh (``scene.scan.scan_like``): an organic blob decimated
                          by vertex clustering, with holes in its base, non-manifold fins,
                          slivers and scanner noise — where a real scan is hard for a ray tracer.

Sizes: ``small`` (~1-3k vertices, for tests), ``medium`` (~10k), ``large`` (~50k); the scenes
made from a geodesic sphere (``convex``, ``bumpy_sphere``) also come at ``xl`` (~1M vertices: a
finer level of the same surface, for the scale benchmark) and at any vertex count
(``bumpy_sphere:100000`` is the nearest level, 10 f² + 2 vertices).
Flat parts are built as separate grids (no shared vertices across sharp edges), so normals stay
flat on them.
"""
from __future__ import annotations

import math

import numpy as np

from .._checks import check_choice
from .geodesic import geodesic_sphere
from .mesh import Mesh, make_mesh
from .scan import scan_like

__all__ = ["builtin", "list_builtins", "SIZES", "GEODESIC", "check_size", "geodesic_sphere", "sphere_on_plane_visibility"]

SIZES = ("small", "medium", "large", "xl")
#: scenes built from a geodesic sphere: they take ``xl`` and a vertex count as their size
GEODESIC = ("convex", "bumpy_sphere")
#: the largest vertex count a size may ask for (a geodesic level of about 20M vertices, 2.4 GB of
#: float64 coordinates and normals before any transfer)
MAX_VERTICES = 20_000_000

WHITE = (0.75, 0.75, 0.75)
RED = (0.75, 0.12, 0.10)
GREEN = (0.12, 0.70, 0.12)


def _freq_for(vertices: int) -> int:
    return max(1, int(round(math.sqrt(max(vertices - 2, 10) / 10))))


def _grid(origin, u, v, nu: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """A planar (nu+1)×(nv+1) vertex grid spanning origin + [0,1]u + [0,1]v, front side u × v."""
    origin, u, v = (np.asarray(x, np.float64) for x in (origin, u, v))
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = origin + a.reshape(-1, 1) * u + b.reshape(-1, 1) * v
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    k = (i * (nv + 1) + j).reshape(-1)
    faces = np.concatenate([np.stack([k, k + nv + 1, k + nv + 2], 1), np.stack([k, k + nv + 2, k + 1], 1)])
    return verts, faces


def _box_faces(lo, hi, n_per_unit: float, bottom: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """Outward-facing grids of an axis-aligned box [lo, hi] (bottom face optional)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    d = hi - lo
    n = lambda L: max(1, int(round(L * n_per_unit)))  # noqa: E731
    X, Y, Z = np.eye(3)
    parts = [
        _grid([lo[0], lo[1], hi[2]], d[0] * X, d[1] * Y, n(d[0]), n(d[1])),  # top (+z)
        _grid([lo[0], lo[1], lo[2]], d[0] * X, d[2] * Z, n(d[0]), n(d[2])),  # front (-y): X × Z = -Y
        _grid([lo[0], hi[1], lo[2]], d[2] * Z, d[0] * X, n(d[2]), n(d[0])),  # back (+y): Z × X = +Y
        _grid([lo[0], lo[1], lo[2]], d[2] * Z, d[1] * Y, n(d[2]), n(d[1])),  # left (-x): Z × Y = -X
        _grid([hi[0], lo[1], lo[2]], d[1] * Y, d[2] * Z, n(d[1]), n(d[2])),  # right (+x): Y × Z = +X
    ]
    if bottom:
        parts.append(_grid([lo[0], lo[1], lo[2]], d[1] * Y, d[0] * X, n(d[1]), n(d[0])))  # Y × X = -Z
    return parts


def _assemble(parts: list[tuple[np.ndarray, np.ndarray, tuple]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vs, fs, cs = [], [], []
    off = 0
    for v, f, c in parts:
        vs.append(v)
        fs.append(f + off)
        cs.append(np.broadcast_to(np.asarray(c, np.float64), v.shape))
        off += v.shape[0]
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(cs)


# target vertex counts per size
_TARGET = {"small": 2000, "medium": 10000, "large": 50000, "xl": 1_000_000}


def check_size(name: str, size) -> str | int:
    """The size of built-in scene ``name``: one of :data:`SIZES` (``xl`` only for the
    :data:`GEODESIC` scenes), or for those a vertex count (an int, or its decimal text as in
    ``"bumpy_sphere:100000"``) in [12, :data:`MAX_VERTICES`]. Returns the size (counts as int).
    Raises ValueError naming the size and what is accepted."""
    geo = name in GEODESIC
    text = str(size).strip()
    if not isinstance(size, bool) and (isinstance(size, int) or text.isdigit()):
        if not geo:
            raise ValueError(f"size={text} (a vertex count) is not accepted for {name!r}; accepted: one of "
                             f"{list(SIZES[:3])} (vertex counts and 'xl' are offered for {list(GEODESIC)})")
        n = int(text)
        if not 12 <= n <= MAX_VERTICES:
            raise ValueError(f"size={n} vertices for {name!r}; accepted: a count in [12, {MAX_VERTICES}] or one of {list(SIZES)}")
        return n
    if size == "xl" and not geo:
        raise ValueError(f"size='xl' is not accepted for {name!r}; accepted: one of {list(SIZES[:3])} "
                         f"('xl', ~1M vertices, is offered for {list(GEODESIC)})")
    check_choice("size", size, list(SIZES))
    return size


def _target(size: str | int) -> int:
    return int(size) if isinstance(size, int) else _TARGET[size]


def _convex(size: str):
    v, f = geodesic_sphere(_freq_for(_target(size)))
    v = v * np.array([1.0, 0.8, 0.6])
    v[:, 2] -= v[:, 2].min()
    return [(v, f, (0.8, 0.8, 0.8))], {"shape": "ellipsoid", "semi_axes": [1.0, 0.8, 0.6], "center": [0, 0, 0.6]}


def _sphere_on_plane(size: str):
    n_sphere = {"small": 640, "medium": 2500, "large": 10000}[size]
    n_plane = {"small": 40, "medium": 86, "large": 200}[size]
    half = 3.0
    v, f = geodesic_sphere(_freq_for(n_sphere))
    v = v + np.array([0.0, 0.0, 1.0])
    pv, pf = _grid([-half, -half, 0.0], [2 * half, 0, 0], [0, 2 * half, 0], n_plane, n_plane)
    return [(v, f, (0.8, 0.8, 0.8)), (pv, pf, (0.8, 0.8, 0.8))], {
        "sphere_center": [0, 0, 1.0], "sphere_radius": 1.0, "plane_half_size": half}


def _occluder_over_plane(size: str):
    n = {"small": 40, "medium": 90, "large": 200}[size]
    pv, pf = _grid([-1.0, -1.0, 0.0], [2.0, 0, 0], [0, 2.0, 0], n, n)
    h, s, th = 0.5, 0.35, 0.02  # height, half-size, thickness of the occluder slab
    parts = [(pv, pf, (0.8, 0.8, 0.8))]
    for v, f in _box_faces([-s, -s, h], [s, s, h + th], n / 2.0, bottom=True):
        parts.append((v, f, (0.8, 0.8, 0.8)))
    return parts, {"receiver": [[-1, -1, 0], [1, 1, 0]], "occluder": [[-s, -s, h], [s, s, h + th]]}


def _bumpy_sphere(size: str):
    v, f = geodesic_sphere(_freq_for(_target(size)))
    x, y, z = v.T
    # deep valleys: r = 1 + a·b(v)² with b a product of sines (Lipschitz enough for the small size)
    bump = (np.sin(5 * x + 0.3) * np.sin(5 * y + 1.1) * np.sin(5 * z + 0.7))
    r = 1.0 + 0.45 * bump ** 2 - 0.1 * bump
    v = v * r[:, None]
    v[:, 2] -= v[:, 2].min()
    return [(v, f, (0.8, 0.8, 0.8))], {"displacement": "r = 1 + 0.45 b² - 0.1 b, b = sin(5x+.3) sin(5y+1.1) sin(5z+.7)"}


def _cornell_box(size: str):
    npu = {"small": 8.5, "medium": 19.0, "large": 43.0}[size]  # grid cells per unit length
    n = lambda L: max(1, int(round(L * npu)))  # noqa: E731
    X, Y, Z = np.eye(3)
    W = 2.0  # box [-1,1] x [-1,1] x [0,2], open towards -y
    parts = [
        (*_grid([-1, -1, 0], W * X, W * Y, n(W), n(W)), WHITE),  # floor, normal +z
        (*_grid([-1, -1, W], W * Y, W * X, n(W), n(W)), WHITE),  # ceiling, normal -z
        (*_grid([-1, 1, 0], W * X, W * Z, n(W), n(W)), WHITE),  # back wall, X × Z = -Y (inward)
        (*_grid([-1, -1, 0], W * Y, W * Z, n(W), n(W)), RED),  # left wall at x=-1, Y × Z = +X (inward)
        (*_grid([1, -1, 0], W * Z, W * Y, n(W), n(W)), GREEN),  # right wall at x=+1, Z × Y = -X (inward)
    ]
    for lo, hi in (([-0.7, -0.3, 0.0], [-0.1, 0.5, 1.2]), ([0.15, -0.6, 0.0], [0.75, 0.0, 0.6])):
        for v, f in _box_faces(lo, hi, npu):
            parts.append((v, f, WHITE))
    return parts, {"box": [[-1, -1, 0], [1, 1, 2]], "open_side": "-y", "left": "red", "right": "green"}


def _scan_blob(size: str):
    m = scan_like(_TARGET[size])
    return [(m.vertices.numpy(), m.faces.numpy(), (0.8, 0.8, 0.8))], m.meta["scan"]


_BUILDERS = {
    "convex": _convex,
    "sphere_on_plane": _sphere_on_plane,
    "occluder_over_plane": _occluder_over_plane,
    "bumpy_sphere": _bumpy_sphere,
    "cornell_box": _cornell_box,
    "scan_blob": _scan_blob,
}


def list_builtins() -> list[str]:
    """Names of the built-in scenes."""
    return list(_BUILDERS)


def builtin(name: str, size: str = "small", albedo=None) -> Mesh:
    """Build a built-in scene as a validated ``Mesh`` (see module docstring).

    Args:
        name: one of ``list_builtins()``; ``"name:size"`` is accepted too.
        size: 'small' (~1-3k vertices), 'medium' (~10k), 'large' (~50k); for ``convex`` and
            ``bumpy_sphere`` also 'xl' (~1M) or a vertex count (the nearest geodesic level,
            10 f² + 2 vertices; :func:`check_size`). 'xl' builds in about 5 s on one core (no cache needed).
        albedo: None keeps the scene's own albedo (coloured walls for cornell_box, 0.8 grey
            elsewhere); a float / RGB triple / ``[V,3]`` overrides it.
    """
    if isinstance(name, str) and ":" in name:
        name, size = name.split(":", 1)
    check_choice("scene", name, list(_BUILDERS))
    size = check_size(name, size)
    parts, params = _BUILDERS[name](size)
    v, f, c = _assemble(parts)
    # merge_duplicates=False: parts meeting at sharp edges keep their own vertices (flat normals)
    mesh = make_mesh(v, f, c if albedo is None else albedo, name=name, merge_duplicates=False,
                     meta={"builtin": name, "size": size, "params": params})
    return mesh


def sphere_on_plane_visibility(d: float, radius: float = 1.0) -> float:
    """Fraction of the cosine-weighted upper hemisphere a point on the ground at distance ``d``
    from the contact point sees unoccluded by a sphere of ``radius`` resting on the ground.

    The sphere subtends a cap of half-angle α, sin α = r/√(d²+r²), whose axis has elevation β
    with sin β = r/√(d²+r²) (the cap touches the horizon since the ground is tangent to the
    sphere). A cap above the horizon has vector solid angle ∫ s dω = π sin²α · axis, so the
    occluded cosine-weighted fraction is sin²α sin β and::

        visible = 1 − (r² / (d² + r²))^{3/2}

    Under a constant environment of radiance 1 the exit radiance there is ρ · visible.
    """
    q = radius * radius / (d * d + radius * radius)
    return 1.0 - q ** 1.5
