"""prt_torch.scene — validated triangle meshes, built-in procedural scenes, Embree ray casting.

World frame: right-handed, +z up; built-in scenes stand on the plane z = 0.

Public API (imported lazily, PEP 562, so that ray-casting worker processes importing
``prt_torch.scene._embree_worker`` start without torch):

* ``Mesh``, ``make_mesh``, ``load_mesh``, ``vertex_normals``, ``tangent_frames`` (mesh.py)
* ``edge_face_counts``, ``normal_face_angles``, ``vertex_classes``, ``mesh_features``, ``VERTEX_CLASSES``
  (mesh.py: where a mesh is hard — boundary, non-manifold, sharp, folded, sliver vertices)
* ``builtin``, ``list_builtins``, ``SIZES``, ``GEODESIC``, ``check_size``, ``geodesic_sphere``,
  ``sphere_on_plane_visibility`` (builtins.py; ``bumpy_sphere:xl`` ~1M vertices, ``bumpy_sphere:100000``)
* ``scan_like``, ``SCAN_FEATURES`` (scan.py: scan-like meshes, each artefact switchable)
* ``RayCaster``, ``default_workers`` (raycast.py)
* ``load_scene(name_or_path, size='small', up='z', albedo=None)``
"""
from __future__ import annotations

import importlib
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

_LAZY = {
    "Mesh": "mesh", "make_mesh": "mesh", "load_mesh": "mesh", "vertex_normals": "mesh", "tangent_frames": "mesh",
    "MESH_SUFFIXES": "mesh", "face_areas": "mesh", "edge_face_counts": "mesh", "normal_face_angles": "mesh",
    "vertex_classes": "mesh", "mesh_features": "mesh", "VERTEX_CLASSES": "mesh",
    "scan_like": "scan", "SCAN_FEATURES": "scan",
    "builtin": "builtins", "list_builtins": "builtins", "SIZES": "builtins", "geodesic_sphere": "builtins",
    "sphere_on_plane_visibility": "builtins", "check_size": "builtins", "GEODESIC": "builtins",
    "RayCaster": "raycast", "default_workers": "raycast",
}

__all__ = sorted(_LAZY) + ["load_scene"]

if TYPE_CHECKING:  # pragma: no cover
    from .builtins import (GEODESIC, SIZES, builtin, check_size, geodesic_sphere, list_builtins,  # noqa: F401
                           sphere_on_plane_visibility)
    from .mesh import (MESH_SUFFIXES, VERTEX_CLASSES, Mesh, edge_face_counts, face_areas, load_mesh, make_mesh,  # noqa: F401
                       mesh_features, normal_face_angles, tangent_frames, vertex_classes, vertex_normals)
    from .scan import SCAN_FEATURES, scan_like  # noqa: F401
    from .raycast import RayCaster, default_workers  # noqa: F401


def __getattr__(name: str) -> Any:
    mod = _LAZY.get(name)
    if mod is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{mod}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))


def load_scene(name_or_path: str | os.PathLike, size: str = "small", up: str = "z", albedo=None, **kw):
    """A built-in scene by name (``"bumpy_sphere"`` or ``"bumpy_sphere:large"``) or a mesh file -> ``Mesh``.

    A built-in name is used only when no file of that name exists. Extra keywords go to
    ``load_mesh`` for files.
    """
    from .builtins import builtin, list_builtins
    from .mesh import MESH_SUFFIXES, load_mesh

    s = str(name_or_path)
    if not Path(s).exists() and s.split(":", 1)[0] in list_builtins():
        return builtin(s, size=size, albedo=albedo)
    if not Path(s).exists() and Path(s).suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{s!r} is neither an existing mesh file nor a built-in scene; "
                         f"accepted: a path ending in {list(MESH_SUFFIXES)} or one of {list_builtins()} (optionally 'name:size')")
    return load_mesh(s, up=up, albedo=albedo, **kw)
