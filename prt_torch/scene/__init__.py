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
* ``load_scene(name_or_path, size='small', up='z', albedo=None, param='mesh')``, ``check_scene`` (the one rule
  for naming a mesh, checked without building it: every command and config key that takes a mesh), ``accepted_meshes``
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

__all__ = sorted(_LAZY) + ["load_scene", "check_scene", "accepted_meshes"]

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


def accepted_meshes() -> str:
    """The forms a mesh argument takes, in words (every command and config key that takes a mesh)."""
    from .builtins import GEODESIC, MAX_VERTICES, SIZES, list_builtins
    from .mesh import MESH_SUFFIXES

    return (f"a built-in scene NAME or NAME:SIZE (NAME one of {', '.join(list_builtins())}; SIZE one of "
            f"{', '.join(SIZES[:3])}, for {' and '.join(GEODESIC)} also xl or a vertex count in [12, {MAX_VERTICES}]; "
            f"default small), or an existing mesh file ({', '.join(MESH_SUFFIXES)})")


def check_scene(name_or_path: str | os.PathLike, size: str | int = "small", param: str = "mesh") -> tuple[str, Any]:
    """Resolve a mesh argument without building or reading it: the one rule for naming a mesh.

    An existing path is a mesh file (a built-in name is used only when no file of that name
    exists); otherwise ``NAME`` or ``NAME:SIZE`` names a built-in scene (``size`` is used when the
    text has no ``:SIZE``). Returns ``("file", path)`` or ``("builtin", (name, size))`` with the
    size checked (:func:`check_size`; a vertex count as int). Raises FileNotFoundError (a missing
    path with a mesh suffix) or ValueError, one line naming ``param``, the value and the accepted
    forms (:func:`accepted_meshes`).
    """
    from .builtins import check_size, list_builtins
    from .mesh import MESH_SUFFIXES

    s = str(name_or_path)
    if Path(s).is_file():
        return "file", s
    name, colon, sz = s.partition(":")
    if not Path(s).exists() and name in list_builtins():
        try:
            return "builtin", (name, check_size(name, sz if colon else size))
        except ValueError as e:
            if not colon:  # the size came separately (precompute's --size, a config's scene.size): its own message
                raise ValueError(f"{param} {s!r}: {e}") from None
            raise ValueError(f"{param} {s!r}: size {sz!r} is not accepted for {name!r}; accepted: {accepted_meshes()}") from None
    what = "a directory" if Path(s).is_dir() else "neither a built-in scene nor an existing mesh file"
    missing_file = not Path(s).exists() and Path(s).suffix.lower() in MESH_SUFFIXES  # as load_mesh: a file that is not there
    raise (FileNotFoundError if missing_file else ValueError)(f"{param} {s!r} is {what}; accepted: {accepted_meshes()}")


def load_scene(name_or_path: str | os.PathLike, size: str = "small", up: str = "z", albedo=None, param: str = "mesh", **kw):
    """A built-in scene by name (``"bumpy_sphere"`` or ``"bumpy_sphere:large"``) or a mesh file -> ``Mesh``.

    Resolved by :func:`check_scene` (its errors name ``param``). A built-in name is used only
    when no file of that name exists. Extra keywords go to ``load_mesh`` for files.
    """
    from .builtins import builtin
    from .mesh import load_mesh

    kind, what = check_scene(name_or_path, size=size, param=param)
    if kind == "builtin":
        return builtin(what[0], size=what[1], albedo=albedo)
    return load_mesh(what, up=up, albedo=albedo, **kw)
