"""Triangle meshes for PRT: validated geometry, vertex normals, tangent frames, albedo.

World frame (docs/interfaces): right-handed, +z up. Files with another up axis are rotated
at load time (``up=``).

Conventions
-----------
* ``vertices [V,3] float64``, ``faces [F,3] int64`` (counter-clockwise seen from the front).
* ``normals [V,3] float64`` unit, angle-weighted by default (Thürmer & Wüthrich 1998: each
  incident face contributes its unit normal times the corner angle; ``normal_weighting='area'``
  uses the face area instead).
* Tangent frame rule (a continuous tangent field on a closed surface must vanish somewhere,
  hairy-ball theorem, so one documented switch is unavoidable)::

      t = normalize(x̂ − (x̂·n) n)         if |x̂ − (x̂·n) n| ≥ 1e-3
      t = normalize(ŷ − (ŷ·n) n)         otherwise (n within ~0.06° of ±x)
      b = n × t                          (so t × b = n, right-handed, det [t;b;n] = +1)

  The frame is smooth everywhere except on the tiny cone around n = ±x̂; planes with n = +z
  get exactly the world frame (t, b, n) = (x̂, ŷ, ẑ).
* ``albedo [V,3] float32`` linear RGB in [0, 1] (8-bit vertex colours are taken as sRGB and
  linearised).
"""
from __future__ import annotations

import dataclasses
import hashlib
import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._checks import check_choice, check_float

__all__ = [
    "Mesh",
    "make_mesh",
    "load_mesh",
    "vertex_normals",
    "tangent_frames",
    "face_areas",
    "MESH_SUFFIXES",
    "edge_face_counts",
    "normal_face_angles",
    "vertex_classes",
    "mesh_features",
    "VERTEX_CLASSES",
]

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")

# Rotations taking the named file axis to world +z (det +1).
_UP = {
    "z": np.eye(3),
    "-z": np.diag([1.0, -1.0, -1.0]),
    "y": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),  # +90° about x: y -> z, z -> -y
    "-y": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
    "x": np.array([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]]),  # -90° about y: x -> z
    "-x": np.array([[0, 0, 1.0], [0, 1.0, 0], [-1.0, 0, 0]]),
}


@dataclasses.dataclass
class Mesh:
    """A validated triangle mesh with per-vertex frames and albedo (all tensors, CPU).

    Attributes:
        vertices: ``[V,3] float64`` positions (world frame, +z up).
        faces: ``[F,3] int64`` vertex indices.
        normals, tangents, bitangents: ``[V,3] float64`` orthonormal, right-handed (t × b = n).
        albedo: ``[V,3] float32`` diffuse reflectance ρ per channel, linear RGB in [0,1].
        name: a label (file stem or built-in name).
        meta: free-form provenance (repair counts, source file, built-in parameters).
    """

    vertices: torch.Tensor
    faces: torch.Tensor
    normals: torch.Tensor
    tangents: torch.Tensor
    bitangents: torch.Tensor
    albedo: torch.Tensor
    name: str = "mesh"
    meta: dict = dataclasses.field(default_factory=dict)

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    def frames(self) -> torch.Tensor:
        """``[V,3,3] float64`` whose rows are (t, b, n): the world->local rotation (det +1),
        directly usable with ``prt_torch.sh.rotate`` (Sloan 2003 §3.1: R_p aligns n with z)."""
        return torch.stack([self.tangents, self.bitangents, self.normals], dim=-2)

    def bbox_diagonal(self) -> float:
        """Length of the axis-aligned bounding-box diagonal (the scene scale)."""
        v = self.vertices
        return float((v.max(0).values - v.min(0).values).norm()) if v.numel() else 0.0

    def is_grey(self) -> bool:
        """True when every vertex has equal R, G and B albedo (transfer needs one channel)."""
        a = self.albedo
        return bool(((a - a[:, :1]).abs() <= 1e-7).all())

    def content_hash(self) -> str:
        """SHA-256 (hex, first 16 bytes) of vertices, faces and albedo: identifies the geometry
        and reflectance a transfer file was computed for (normals/frames derive from these)."""
        h = hashlib.sha256()
        for t in (self.vertices.to(torch.float64), self.faces.to(torch.int64), self.albedo.to(torch.float32)):
            h.update(str(tuple(t.shape)).encode())
            h.update(t.contiguous().numpy().tobytes())
        return h.hexdigest()[:32]

    def with_albedo(self, albedo: Any) -> "Mesh":
        """Copy with another albedo (a float, an RGB triple or ``[V,3]``)."""
        return dataclasses.replace(self, albedo=_albedo(albedo, self.num_vertices), meta=dict(self.meta))

    def to_tensors(self, prefix: str = "mesh.") -> dict[str, torch.Tensor]:
        """The arrays to store next to data in a file (see ``Mesh.from_tensors``)."""
        return {
            prefix + "vertices": self.vertices,
            prefix + "faces": self.faces,
            prefix + "normals": self.normals,
            prefix + "tangents": self.tangents,
            prefix + "bitangents": self.bitangents,
            prefix + "albedo": self.albedo,
        }

    @classmethod
    def from_tensors(cls, tensors: dict[str, torch.Tensor], name: str = "mesh", prefix: str = "mesh.",
                     meta: dict | None = None) -> "Mesh":
        """Rebuild a mesh written by ``to_tensors`` (no recomputation, frames kept as stored)."""
        need = ["vertices", "faces", "normals", "tangents", "bitangents", "albedo"]
        missing = [prefix + k for k in need if prefix + k not in tensors]
        if missing:
            raise ValueError(f"mesh arrays {missing} missing; accepted: a file written by Transfer.save / Mesh.to_tensors")
        g = {k: tensors[prefix + k] for k in need}
        V = g["vertices"].shape[0]
        for k in need:
            if g[k].ndim != 2 or g[k].shape[1] != 3 or (k != "faces" and g[k].shape[0] != V):
                raise ValueError(f"stored {prefix + k} has shape {tuple(g[k].shape)}; accepted: [{V}, 3]")
        return cls(
            vertices=g["vertices"].to(torch.float64), faces=g["faces"].to(torch.int64),
            normals=g["normals"].to(torch.float64), tangents=g["tangents"].to(torch.float64),
            bitangents=g["bitangents"].to(torch.float64), albedo=g["albedo"].to(torch.float32),
            name=name, meta=dict(meta or {}),
        )

    def to_trimesh(self):
        """A ``trimesh.Trimesh`` view (no processing) for export or rendering."""
        import trimesh

        return trimesh.Trimesh(self.vertices.numpy(), self.faces.numpy(), vertex_normals=self.normals.numpy(),
                               process=False)

    def __repr__(self) -> str:
        return f"Mesh(name={self.name!r}, V={self.num_vertices}, F={self.num_faces})"


# ----------------------------------------------------------------------------------------
# geometry kernels (numpy, vectorised over faces/vertices)
# ----------------------------------------------------------------------------------------

def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """``[F]`` triangle areas."""
    tri = vertices[faces]
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def vertex_normals(vertices: np.ndarray, faces: np.ndarray, weighting: str = "angle") -> np.ndarray:
    """Unit vertex normals ``[V,3] float64``.

    ``'angle'``: Σ_f α_{f,v} n̂_f (Thürmer & Wüthrich 1998), ``'area'``: Σ_f A_f n̂_f.
    A vertex whose weighted sum cancels (its length at most 1e-9 of the sum of the weights: a
    vertex only on a face and the same face reversed, as a topology-breaking decimation of a
    scan makes) falls back to the area-weighted sum under the same test, then to the normal of
    its largest face (the first of those within 1e-6 of the largest), then (no face) to +z — a choice that depends on
    neither rounding nor the mesh's units (the sum's rounding residue pointed anywhere).
    """
    check_choice("normal_weighting", weighting, ["angle", "area"])
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    tri = v[f]  # [F,3,3]
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # 2A n̂
    V = v.shape[0]
    nrm = np.linalg.norm(cr, axis=1, keepdims=True)
    corner = f.T.reshape(-1)  # [3F]: every face's corner 0, then corner 1, then corner 2

    def scatter(vals: np.ndarray) -> np.ndarray:  # Σ over the 3 corners in that order (np.add.at's sums, bit for bit)
        return np.bincount(corner, weights=vals, minlength=V)

    area_sum = np.stack([scatter(np.tile(cr[:, j], 3)) for j in range(3)], axis=1)
    area_w = scatter(np.tile(nrm[:, 0], 3))
    if weighting == "area":
        acc, w = area_sum, area_w
    else:
        nhat = np.divide(cr, nrm, out=np.zeros_like(cr), where=nrm > 0)
        angs = []
        for k in range(3):  # 3 corners: a fixed tiny loop, vectorised over faces
            e1 = tri[:, (k + 1) % 3] - tri[:, k]
            e2 = tri[:, (k + 2) % 3] - tri[:, k]
            c = np.einsum("ij,ij->i", e1, e2)
            s = np.linalg.norm(np.cross(e1, e2), axis=1)
            angs.append(np.where(nrm[:, 0] > 0, np.arctan2(s, c), 0.0))
        ang = np.concatenate(angs)  # [3F] in the corner order of ``corner``
        acc = np.stack([scatter(np.tile(nhat[:, j], 3) * ang) for j in range(3)], axis=1)
        w = scatter(ang)
    n = np.linalg.norm(acc, axis=1, keepdims=True)
    bad = n[:, 0] <= 1e-9 * w
    if bad.any():
        acc[bad] = area_sum[bad]
        n[bad] = np.linalg.norm(area_sum[bad], axis=1, keepdims=True)
        still = bad & (n[:, 0] <= 1e-9 * area_w)
        if still.any():  # the first (lowest index) of the vertex's largest faces (areas within 1e-6 count as equal)
            amax = np.zeros(V)
            for k in range(3):
                np.maximum.at(amax, f[:, k], nrm[:, 0])
            big = np.full(V, f.shape[0])
            for k in range(3):
                ok = nrm[:, 0] >= (1 - 1e-6) * amax[f[:, k]]
                np.minimum.at(big, f[ok, k], np.nonzero(ok)[0])
            has = still & (big < f.shape[0]) & (amax > 0)
            big = np.minimum(big, f.shape[0] - 1)
            acc[has] = cr[big[has]]
            n[has] = nrm[big[has]]
            none = still & ~has
            acc[none] = (0.0, 0.0, 1.0)
            n[none] = 1.0
    return acc / n


def edge_face_counts(faces: Any, num_vertices: int) -> tuple[np.ndarray, np.ndarray]:
    """Unique undirected edges ``[E, 2] int64`` (sorted pairs) and the number of faces on each
    ``[E] int64`` (1: boundary, 2: manifold, ≥ 3: non-manifold)."""
    f = np.asarray(faces, np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key = e[:, 0] * int(num_vertices) + e[:, 1]
    uk, cnt = np.unique(key, return_counts=True)
    return np.stack([uk // num_vertices, uk % num_vertices], 1), cnt


def normal_face_angles(mesh: "Mesh") -> np.ndarray:
    """``[V]`` float64: the largest angle (degrees) between a vertex normal and the geometric
    (winding) normals of its adjacent faces — 0 on flat parts, large at sharp and concave
    vertices, ≥ 90° where a face is seen from behind from the vertex's normal side."""
    v = mesh.vertices.to(torch.float64).numpy()
    f = mesh.faces.numpy().astype(np.int64)
    t = v[f]
    fn = np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])
    nrm = np.linalg.norm(fn, axis=1, keepdims=True)
    fn = np.divide(fn, nrm, out=np.zeros_like(fn), where=nrm > 0)
    fn[nrm[:, 0] == 0] = (0.0, 0.0, 1.0)
    cosang = np.clip(np.einsum("fkj,fj->fk", mesh.normals.to(torch.float64).numpy()[f], fn), -1.0, 1.0)  # [F,3]
    worst = np.ones(mesh.num_vertices)
    np.minimum.at(worst, f.reshape(-1), cosang.reshape(-1))
    return np.degrees(np.arccos(worst))


def _sliver_quality(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """``[F]`` 2·inradius/circumradius = 8 A² / (s·abc) (1 equilateral, 0 degenerate)."""
    t = v[f]
    a = np.linalg.norm(t[:, 1] - t[:, 2], axis=1)
    b = np.linalg.norm(t[:, 2] - t[:, 0], axis=1)
    c = np.linalg.norm(t[:, 0] - t[:, 1], axis=1)
    s = 0.5 * (a + b + c)
    area2 = np.maximum(s * (s - a) * (s - b) * (s - c), 0.0)
    return np.where(a * b * c > 0, 8 * area2 / np.maximum(a * b * c * s, 1e-300), 0.0)


#: the vertex classes :func:`vertex_classes` returns, in report order ('regular': none of the others)
VERTEX_CLASSES = ("boundary", "nonmanifold", "sharp", "folded", "sliver", "regular")


def vertex_classes(mesh: "Mesh", sharp_deg: float = 18.0, sliver_ratio: float = 0.05) -> dict[str, np.ndarray]:
    """Boolean ``[V]`` masks of the vertex classes where a mesh is hard (:data:`VERTEX_CLASSES`):
    'boundary' (on an edge with one face: holes, open rims), 'nonmanifold' (on an edge with three
    or more faces), 'sharp' (an adjacent face's normal ≥ ``sharp_deg`` from the vertex normal,
    :func:`normal_face_angles`), 'folded' (≥ 90°: a face of the vertex is seen from behind),
    'sliver' (a corner of a face whose 2·inradius/circumradius is below ``sliver_ratio``) and
    'regular' (none of these). A vertex may be in several of the first five."""
    V = mesh.num_vertices
    f = mesh.faces.numpy().astype(np.int64)
    e, cnt = edge_face_counts(f, V)
    boundary = np.zeros(V, bool)
    boundary[e[cnt == 1].reshape(-1)] = True
    nonman = np.zeros(V, bool)
    nonman[e[cnt >= 3].reshape(-1)] = True
    ang = normal_face_angles(mesh)
    sliver = np.zeros(V, bool)
    sliver[f[_sliver_quality(mesh.vertices.to(torch.float64).numpy(), f) < sliver_ratio].reshape(-1)] = True
    out = {"boundary": boundary, "nonmanifold": nonman, "sharp": ang >= sharp_deg, "folded": ang >= 90.0, "sliver": sliver}
    out["regular"] = ~np.logical_or.reduce(list(out.values()))
    return out


def mesh_features(mesh: "Mesh", sharp_deg: float = 18.0, sliver_ratio: float = 0.05) -> dict[str, int]:
    """What makes a mesh hard for a ray tracer, counted (plain ints, JSON-able): vertices, faces,
    boundary edges (one face), non-manifold edges (three or more), sliver faces
    (2·inradius/circumradius below ``sliver_ratio``) and the vertices of each of
    :func:`vertex_classes`."""
    e, cnt = edge_face_counts(mesh.faces.numpy(), mesh.num_vertices)
    q = _sliver_quality(mesh.vertices.to(torch.float64).numpy(), mesh.faces.numpy().astype(np.int64))
    cls = vertex_classes(mesh, sharp_deg, sliver_ratio)
    return {"vertices": mesh.num_vertices, "faces": mesh.num_faces, "boundary_edges": int((cnt == 1).sum()),
            "nonmanifold_edges": int((cnt >= 3).sum()), "sliver_faces": int((q < sliver_ratio).sum()),
            **{f"{k}_vertices": int(m.sum()) for k, m in cls.items()}}


def tangent_frames(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tangents and bitangents ``[V,3]`` by the module rule (project x̂, fall back to ŷ; b = n × t)."""
    n = np.asarray(normals, np.float64)
    x = np.array([1.0, 0.0, 0.0])
    y = np.array([0.0, 1.0, 0.0])
    t = x - n[:, :1] * n
    tn = np.linalg.norm(t, axis=1, keepdims=True)
    sing = tn[:, 0] < 1e-3
    if sing.any():
        t[sing] = y - n[sing, 1:2] * n[sing]
        tn[sing] = np.linalg.norm(t[sing], axis=1, keepdims=True)
    t = t / tn
    b = np.cross(n, t)
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    return t, b


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _albedo(albedo: Any, V: int) -> torch.Tensor:
    """Validate albedo: float, RGB triple, or ``[V,3]`` -> ``[V,3] float32`` in [0,1]."""
    if albedo is None:
        albedo = 0.8
    if isinstance(albedo, (int, float)) and not isinstance(albedo, bool):
        a = torch.full((V, 3), check_float("albedo", albedo, 0.0, 1.0), dtype=torch.float32)
        return a
    a = torch.as_tensor(np.asarray(albedo, dtype=np.float64), dtype=torch.float64)
    if a.ndim == 1 and a.shape[0] == 3:
        a = a.expand(V, 3)
    if a.ndim != 2 or tuple(a.shape) != (V, 3):
        raise ValueError(f"albedo has shape {tuple(a.shape)}; accepted: a float, an RGB triple [3], or [{V}, 3]")
    if not torch.isfinite(a).all() or (a < 0).any() or (a > 1).any():
        raise ValueError("albedo holds values outside [0, 1] or non-finite; accepted: linear reflectance in [0, 1]")
    return a.to(torch.float32).contiguous()


def make_mesh(vertices: Any, faces: Any, albedo: Any = None, name: str = "mesh", *, normals: Any = None,
              normal_weighting: str = "angle", repair: bool = True, merge_duplicates: bool = True,
              meta: dict | None = None) -> Mesh:
    """Validate, repair and complete raw arrays into a ``Mesh``.

    Args:
        vertices: ``[V,3]`` finite coordinates (NaN/Inf refused, with the count).
        faces: ``[F,3]`` integer indices in [0, V).
        albedo: None (0.8 grey), a float, an RGB triple, or ``[V,3]`` in [0,1].
        normals: optional ``[V,3]`` normals to keep (normalised); computed otherwise.
        repair: remove degenerate/zero-area faces, exact-duplicate vertices and unreferenced
            vertices (counts in ``mesh.meta['repair']``). Non-manifold edges and holes are accepted.
        merge_duplicates: merge vertices with identical position, albedo (and given normal);
            off for procedural scenes whose parts meet at sharp edges.
    Raises:
        ValueError naming the problem: no faces, non-finite vertices, indices out of range,
        all faces of zero area.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ValueError(f"{name}: vertices have shape {v.shape}; accepted: [V, 3]")
    f = np.asarray(faces)
    if f.size == 0:
        raise ValueError(f"{name}: the mesh has no faces (V={v.shape[0]}); accepted: a triangle mesh with at least one face")
    if f.ndim != 2 or f.shape[1] != 3:
        raise ValueError(f"{name}: faces have shape {f.shape}; accepted: [F, 3] triangles")
    if not np.issubdtype(f.dtype, np.integer):
        raise TypeError(f"{name}: faces have dtype {f.dtype}; accepted: integer indices")
    f = f.astype(np.int64)
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise ValueError(f"{name}: {int(bad.sum())} vertices have NaN or infinite coordinates (first: index {int(np.nonzero(bad)[0][0])}); "
                         "accepted: finite coordinates only (fix the file; such vertices are not repaired)")
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise ValueError(f"{name}: face indices span [{f.min()}, {f.max()}] but there are {v.shape[0]} vertices; accepted: indices in [0, V)")
    V = v.shape[0]
    alb = _albedo(albedo, V).numpy()
    nrm_in = None if normals is None else np.asarray(normals, np.float64)
    report = {"degenerate_faces_removed": 0, "duplicate_vertices_merged": 0, "unreferenced_vertices_removed": 0}
    if repair:
        # 1. duplicate vertices (identical position and albedo) merged
        key = None if not merge_duplicates else np.concatenate([v, alb.astype(np.float64)], axis=1)
        if key is not None and nrm_in is not None:
            key = np.concatenate([key, nrm_in], axis=1)
        _, first, inverse = (None, np.arange(V), np.arange(V)) if key is None else np.unique(
            key, axis=0, return_index=True, return_inverse=True)
        inverse = inverse.reshape(-1)
        if first.shape[0] < V:
            report["duplicate_vertices_merged"] = int(V - first.shape[0])
            order = np.argsort(first)  # keep original order of first occurrences
            rank = np.empty_like(order)
            rank[order] = np.arange(order.shape[0])
            keep = first[order]
            f = rank[inverse][f]
            v, alb = v[keep], alb[keep]
            nrm_in = None if nrm_in is None else nrm_in[keep]
        # 2. degenerate (repeated index) and zero-area faces removed
        scale = float(np.linalg.norm(v.max(0) - v.min(0))) if v.shape[0] else 0.0
        rep = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
        area = face_areas(v, f)
        zero = area <= (1e-12 * scale) ** 2 if scale > 0 else np.ones_like(rep)
        drop = rep | zero
        if drop.all():
            raise ValueError(f"{name}: all {f.shape[0]} faces have zero area (degenerate mesh); "
                             "accepted: a mesh with at least one face of positive area")
        report["degenerate_faces_removed"] = int(drop.sum())
        f = f[~drop]
        # 3. unreferenced vertices removed
        used = np.zeros(v.shape[0], bool)
        used[f.reshape(-1)] = True
        if not used.all():
            report["unreferenced_vertices_removed"] = int((~used).sum())
            remap = np.cumsum(used) - 1
            f = remap[f]
            v, alb = v[used], alb[used]
            nrm_in = None if nrm_in is None else nrm_in[used]
    else:
        if (face_areas(v, f) <= 0).all():
            raise ValueError(f"{name}: all {f.shape[0]} faces have zero area; accepted: a mesh with positive area")
    if nrm_in is not None:
        nn = np.linalg.norm(nrm_in, axis=1, keepdims=True)
        n = vertex_normals(v, f, normal_weighting)
        ok = (nn[:, 0] > 1e-12) & np.isfinite(nrm_in).all(axis=1)
        n[ok] = nrm_in[ok] / nn[ok]
    else:
        n = vertex_normals(v, f, normal_weighting)
    t, b = tangent_frames(n)
    m = dict(meta or {})
    m["repair"] = report
    m["normal_weighting"] = normal_weighting if nrm_in is None else "given"
    return Mesh(
        vertices=torch.from_numpy(np.ascontiguousarray(v)), faces=torch.from_numpy(np.ascontiguousarray(f)),
        normals=torch.from_numpy(n), tangents=torch.from_numpy(t), bitangents=torch.from_numpy(b),
        albedo=torch.from_numpy(np.ascontiguousarray(alb, dtype=np.float32)), name=name, meta=m,
    )


def load_mesh(path: str | os.PathLike, up: str = "z", albedo: Any = None, normal_weighting: str = "angle",
              use_file_normals: bool = False) -> Mesh:
    """Load a mesh file through trimesh (OBJ, PLY, STL, OFF, GLB/GLTF) and validate it.

    Args:
        path: the file. Scenes (GLB/GLTF with several nodes) are flattened with their transforms.
        up: the file's up axis, one of 'z', '-z', 'y', '-y', 'x', '-x'; rotated to world +z.
        albedo: None -> the file's vertex colours (8-bit sRGB, linearised) if present, else 0.8;
            or a float / RGB triple / ``[V,3]`` (after repair the count must match).
        use_file_normals: keep normals stored in the file instead of recomputing them.
    Returns:
        ``Mesh`` with ``meta['repair']`` counting what was repaired and ``meta['source']``.
    Raises:
        FileNotFoundError for a missing file; ValueError for unreadable/corrupt files, no faces,
        NaN vertices, zero-area meshes.
    """
    import trimesh

    check_choice("up", up, list(_UP))
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no such mesh file: {str(p)!r}")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"mesh file {str(p)!r} has suffix {p.suffix!r}; accepted: {list(MESH_SUFFIXES)}")
    try:
        obj = trimesh.load(str(p), force="mesh", process=False)
    except Exception as e:  # trimesh raises many error types for bad files
        raise ValueError(f"cannot read mesh file {str(p)!r}: {type(e).__name__}: {e}") from None
    if not isinstance(obj, trimesh.Trimesh):
        raise ValueError(f"mesh file {str(p)!r} holds no triangle mesh (got {type(obj).__name__}); accepted: a file with faces")
    verts = np.asarray(obj.vertices, dtype=np.float64)
    faces = np.asarray(obj.faces)
    if faces.size == 0:
        raise ValueError(f"mesh file {str(p)!r} has no faces ({verts.shape[0]} vertices); accepted: a triangle mesh")
    R = _UP[up]
    verts = verts @ R.T
    normals = None
    if use_file_normals:
        normals = np.asarray(obj.vertex_normals, np.float64) @ R.T
    colours_used = False
    if albedo is None:
        vc = None
        try:
            if obj.visual is not None and obj.visual.kind == "vertex":
                vc = np.asarray(obj.visual.vertex_colors)[:, :3]
        except Exception:
            vc = None
        if vc is not None and vc.shape[0] == verts.shape[0]:
            albedo = _srgb_to_linear(vc.astype(np.float64) / 255.0)
            colours_used = True
    return make_mesh(verts, faces, albedo, name=p.stem, normals=normals, normal_weighting=normal_weighting,
                     meta={"source": str(p), "up": up, "albedo_from_vertex_colours": colours_used})
