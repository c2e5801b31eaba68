"""Decoders: what turns the engine's per-vertex data into a colour on the GPU.

A :class:`Decoder` pairs a :class:`~prt_torch.render.program.ShaderProgram` with the data it
needs for one draw (:class:`DrawInputs`): per-vertex attributes, uniforms and float tables
(2-D textures or texture buffers). The renderer uploads those as float32 and runs the program;
nothing is quantised on the way (see ``FloatTexture``).

Implemented here:

* :class:`RadianceDecoder` — exit radiance already computed per vertex (``[V,3]`` float), passed
  through and interpolated by the rasteriser (Gouraud): the image of what ``relight`` computed.
* :class:`IndexedRadianceDecoder` — per-vertex integer index into a per-cluster float table,
  fetched in the vertex shader: the GPU form of VQ relighting (Sloan 2003 §3, eq. (2): every
  point of cluster k shares the representative M_k, so its exit radiance is the table entry
  M_k·l computed once per cluster).

The PRT decoders — uncompressed diffuse/glossy/MRT transfer and the piecewise-affine codecs
(VQ, PCA, CPCA, MRT-PCA; Sloan 2003 §6.2, Lehtinen & Kautz 2003 eq. 13) — are in :mod:`.glsl`,
built on these classes. See docs/render.md.
"""
from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from .program import Attribute, ShaderProgram

__all__ = ["DrawInputs", "TableData", "Decoder", "RadianceDecoder", "IndexedRadianceDecoder",
           "RADIANCE_PROGRAM", "INDEXED_RADIANCE_PROGRAM"]


@dataclasses.dataclass
class TableData:
    """A float table for a sampler uniform: ``kind='buffer'`` (``samplerBuffer``, data ``[N]`` or
    ``[N, C]``) or ``kind='2d'`` (``sampler2D``, data ``[H, W]`` or ``[H, W, C]``), C in 1..4."""

    data: Any
    kind: str = "buffer"

    def __post_init__(self):
        if self.kind not in ("buffer", "2d"):
            raise ValueError(f"TableData kind={self.kind!r}; accepted: 'buffer' or '2d'")


@dataclasses.dataclass
class DrawInputs:
    """What one draw needs besides geometry and camera.

    Attributes:
        attributes: name -> ``[V, k]`` (or ``[V]``) array per program attribute (float32/int32).
        uniforms: name -> value for ``GLProgram.set_uniform``.
        tables: sampler uniform name -> :class:`TableData`.
    """

    attributes: dict = dataclasses.field(default_factory=dict)
    uniforms: dict = dataclasses.field(default_factory=dict)
    tables: dict = dataclasses.field(default_factory=dict)


class Decoder:
    """Base class: ``program`` (a :class:`ShaderProgram` with ``mesh=True``), ``channels`` (how
    many of prt_color's rgb channels carry the value) and ``inputs(num_vertices)``."""

    program: ShaderProgram
    channels: int = 3

    def inputs(self, num_vertices: int) -> DrawInputs:  # pragma: no cover - interface
        raise NotImplementedError


def _array(name: str, x) -> np.ndarray:
    a = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x)
    if a.dtype.kind not in "fiub":
        raise TypeError(f"{name} has dtype {a.dtype}; accepted: real numbers")
    return a


RADIANCE_PROGRAM = ShaderProgram(
    name="per_vertex_radiance",
    attributes=(Attribute("radiance", 3),),
    vertex_body="""
uniform mat4 prt_mvp;
out vec3 v_radiance;
void main() {
    v_radiance = radiance;
    gl_Position = prt_mvp * vec4(position, 1.0);
}
""",
    fragment_body="""
in vec3 v_radiance;
void main() {
    prt_color = vec4(v_radiance, 1.0);
}
""",
)


class RadianceDecoder(Decoder):
    """Per-vertex radiance ``[V,3]`` (or ``[V]`` / ``[V,1]`` grey, replicated) float, interpolated
    across triangles (perspective-correct barycentric interpolation of the vertex values).

    Values are converted to float32 (the only rounding); non-finite values are refused."""

    program = RADIANCE_PROGRAM

    def __init__(self, radiance):
        r = _array("radiance", radiance).astype(np.float32)
        if r.ndim == 1:
            r = r[:, None]
        if r.ndim != 2 or r.shape[1] not in (1, 3):
            raise ValueError(f"radiance has shape {r.shape}; accepted: [V, 3], [V, 1] or [V]")
        if r.shape[1] == 1:
            r = np.repeat(r, 3, axis=1)
        bad = ~np.isfinite(r)
        if bad.any():
            first = tuple(int(i) for i in np.argwhere(bad)[0])
            raise ValueError(f"radiance has {int(bad.sum())} non-finite value(s) (NaN or Inf, float32), first at "
                             f"{first}; accepted: finite values within float32 range")
        self.radiance = np.ascontiguousarray(r)

    def inputs(self, num_vertices: int) -> DrawInputs:
        if self.radiance.shape[0] != num_vertices:
            raise ValueError(f"radiance has {self.radiance.shape[0]} rows but the mesh has {num_vertices} vertices")
        return DrawInputs(attributes={"radiance": self.radiance})


INDEXED_RADIANCE_PROGRAM = ShaderProgram(
    name="indexed_radiance",
    attributes=(Attribute("cluster", 1, "int"),),
    vertex_body="""
uniform mat4 prt_mvp;
uniform samplerBuffer table;   // [K] RGBA32F: rgb = radiance of cluster k
out vec3 v_radiance;
void main() {
    v_radiance = texelFetch(table, cluster).rgb;
    gl_Position = prt_mvp * vec4(position, 1.0);
}
""",
    fragment_body="""
in vec3 v_radiance;
void main() {
    prt_color = vec4(v_radiance, 1.0);
}
""",
)


class IndexedRadianceDecoder(Decoder):
    """VQ on the GPU (Sloan 2003 eq. (2)): ``index [V]`` int cluster of each vertex and
    ``table [K,3]`` (or ``[K]``) float exit radiance of each cluster representative, M_k·l.
    Radiance at vertex p is ``table[index[p]]``, fetched from a texture buffer in the vertex
    shader and interpolated like :class:`RadianceDecoder`."""

    program = INDEXED_RADIANCE_PROGRAM

    def __init__(self, index, table):
        idx = _array("index", index)
        if idx.dtype.kind not in "iu" or idx.ndim != 1:
            raise ValueError(f"index has shape {idx.shape} and dtype {idx.dtype}; accepted: [V] integers")
        t = _array("table", table).astype(np.float32)
        if t.ndim == 1:
            t = t[:, None]
        if t.ndim != 2 or t.shape[1] not in (1, 3):
            raise ValueError(f"table has shape {t.shape}; accepted: [K, 3], [K, 1] or [K]")
        if t.shape[1] == 1:
            t = np.repeat(t, 3, axis=1)
        if not np.isfinite(t).all():
            raise ValueError("table has non-finite values; accepted: finite float32 values")
        if idx.size and (idx.min() < 0 or idx.max() >= t.shape[0]):
            raise ValueError(f"index values span [{idx.min()}, {idx.max()}]; accepted: 0..{t.shape[0] - 1} (table rows)")
        self.index = np.ascontiguousarray(idx, dtype=np.int32)
        self.table = np.ascontiguousarray(np.concatenate([t, np.ones((t.shape[0], 1), np.float32)], 1))

    def inputs(self, num_vertices: int) -> DrawInputs:
        if self.index.shape[0] != num_vertices:
            raise ValueError(f"index has {self.index.shape[0]} entries but the mesh has {num_vertices} vertices")
        return DrawInputs(attributes={"cluster": self.index}, tables={"table": TableData(self.table, "buffer")})
