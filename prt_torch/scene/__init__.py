"""prt_torch.scene — validated triangle meshes, built-in procedural scenes, Embree ray casting.

World frame: right-handed, +z up; built-in scenes stand on the plane z = 0.
"""
from __future__ import annotations

import os
from pathlib import Path

from .builtins import SIZES, builtin, geodesic_sphere, list_builtins, sphere_on_plane_visibility
from .mesh import MESH_SUFFIXES, Mesh, load_mesh, make_mesh, tangent_frames, vertex_normals
from .raycast import RayCaster, default_workers

__all__ = [
    "Mesh", "make_mesh", "load_mesh", "load_scene", "builtin", "list_builtins", "SIZES",
    "RayCaster", "default_workers", "vertex_normals", "tangent_frames", "geodesic_sphere",
    "sphere_on_plane_visibility", "MESH_SUFFIXES",
]


def load_scene(name_or_path: str | os.PathLike, size: str = "small", up: str = "z", albedo=None, **kw) -> Mesh:
    """A built-in scene by name (``"bumpy_sphere"`` or ``"bumpy_sphere:large"``) or a mesh file.

    Built-in names take precedence over a file of the same name only when no such file exists.
    Extra keywords go to ``load_mesh`` for files.
    """
    s = str(name_or_path)
    if not Path(s).exists() and s.split(":", 1)[0] in list_builtins():
        return builtin(s, size=size, albedo=albedo)
    if not Path(s).exists() and Path(s).suffix.lower() not in MESH_SUFFIXES:
        raise ValueError(f"{s!r} is neither an existing mesh file nor a built-in scene; "
                         f"accepted: a path ending in {list(MESH_SUFFIXES)} or one of {list_builtins()} (optionally 'name:size')")
    return load_mesh(s, up=up, albedo=albedo, **kw)
