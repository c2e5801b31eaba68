"""GLSL decoder of a spherical harmonic reflection map (Ramamoorthi 2002 §5.4, §5.7.5).

Per vertex p the vertex shader evaluates eq. 5.10,

    B(p) = Σ_{j = (p, q)} y_j(ω'o,p) · bilinear(B_j)(α_p, β_p),

reading the SHRM's maps B_pq(α, β) unquantised from one ``RGBA32F`` 2-D texture (map j's H × W
texels side by side: texel (row i, column j·W + x) holds B_j at texel (i, x), RGB in RGB) with
the same bilinear rule as ``shrm.SHRM.radiance(method="map")`` — rows clamped, columns wrapped
around in β. (α_p, β_p) are computed in GLSL from the vertex's axis (the reflected view, or the
normal for a Lambertian SHRM), an attribute; the view's SH weights y_j(ω'o,p) (zero where the
vertex faces away) are computed per camera on the CPU (``SHRM.view_terms``) and read from a
texture buffer, as the glossy decoder's view weights are (``render.glsl``, view mode 'dense').

:func:`render_shrm` draws an SHRM on a mesh either way (``shading="vertex"``: that decoder, or the
CPU's per-vertex radiance, interpolated across triangles) or per pixel (``shading="pixel"``:
deferred — the rasteriser interpolates only the vertex normals and positions, and every sample is
shaded on the CPU from its own normal and view by ``SHRM.radiance``, as the thesis' renderer does
per pixel, §5.7.5).
"""
from __future__ import annotations

import functools

import numpy as np
import torch

from ..shrm import SHRM
from .camera import Camera
from .decoders import Decoder, DrawInputs, TableData
from .program import Attribute, ShaderProgram

__all__ = ["SHRMDecoder", "shrm_program", "render_shrm", "camera_views"]

_FRAGMENT = """
in vec3 v_radiance;
void main() {
    prt_color = vec4(v_radiance, 1.0);
}
"""


@functools.lru_cache(maxsize=None)
def shrm_program(n_p: int, height: int, width: int, clamp: bool = False) -> ShaderProgram:
    """The SHRM vertex program for (P_B+1)² = ``n_p`` maps of ``height`` × ``width`` texels
    (``clamp``: the radiance clamped at 0, as ``SHRM.radiance(clamp=True)``).

    Attribute ``axis`` (vec3); tables ``maps`` (sampler2D, RGBA32F ``[H, W·n_p]``) and
    ``view_weights`` (samplerBuffer, R32F ``[V·n_p]``)."""
    body = f"""
uniform mat4 prt_mvp;
uniform sampler2D maps;              // RGBA32F [H, W * NP]: map j at columns j*W .. j*W + W-1
uniform samplerBuffer view_weights;  // R32F [V * NP]: y_j(w'o) per vertex, 0 when facing away
out vec3 v_radiance;
const int NP = {n_p};
const int H = {height};
const int W = {width};
const float PI = 3.14159265358979323846;

vec3 texel(int y, int x, int j) {{
    return texelFetch(maps, ivec2(j * W + x, y), 0).rgb;
}}

void main() {{
    vec3 a = normalize(axis);
    float al = acos(clamp(a.z, -1.0, 1.0));
    float be = atan(a.y, a.x);
    if (be < 0.0) be += 2.0 * PI;
    float fy = clamp(al * (float(H) / PI) - 0.5, 0.0, float(H - 1));
    float fx = be * (float(W) / (2.0 * PI)) - 0.5;
    int y0 = min(int(floor(fy)), H - 1);
    int y1 = min(y0 + 1, H - 1);
    float x0f = floor(fx);
    int x0 = int(x0f);
    if (x0 < 0) x0 += W;
    if (x0 >= W) x0 -= W;
    int x1 = x0 + 1;
    if (x1 >= W) x1 -= W;
    float ty = fy - float(y0);
    float tx = fx - x0f;
    vec3 s = vec3(0.0);
    int base = gl_VertexID * NP;
    for (int j = 0; j < NP; ++j) {{
        float w = texelFetch(view_weights, base + j).r;
        if (w == 0.0) continue;
        vec3 b = (1.0 - ty) * ((1.0 - tx) * texel(y0, x0, j) + tx * texel(y0, x1, j))
               + ty * ((1.0 - tx) * texel(y1, x0, j) + tx * texel(y1, x1, j));
        s += w * b;
    }}
    v_radiance = {"max(s, vec3(0.0))" if clamp else "s"};
    gl_Position = prt_mvp * vec4(position, 1.0);
}}
"""
    return ShaderProgram(f"shrm_p{n_p}_{height}x{width}{'_clamp' if clamp else ''}", (Attribute("axis", 3),), body, _FRAGMENT)


class SHRMDecoder(Decoder):
    """An SHRM decoded in the vertex shader (:func:`shrm_program`).

    Args:
        shrm: an :class:`~prt_torch.shrm.SHRM` with maps (RGB: C = 3, or C = 1 replicated).
        normals: ``[V, 3]`` unit vertex normals; views: ``[V, 3]`` or ``[3]`` unit directions
            towards the viewer (per camera).
        clamp: the radiance clamped at 0 (``SHRM.radiance(clamp=True)``).
    """

    def __init__(self, shrm: SHRM, normals, views, clamp: bool = False):
        if shrm.maps is None:
            raise ValueError("the SHRM has no maps; accepted: one computed with a map size (SHRM.prefilter)")
        C, nP, H, W = shrm.maps.shape
        if C not in (1, 3):
            raise ValueError(f"SHRM maps have {C} channels; accepted: 1 or 3")
        n = torch.as_tensor(normals, dtype=torch.float64)
        v = torch.as_tensor(views, dtype=torch.float64)
        ax, _, y = shrm.view_terms(n, v)
        m = shrm.maps.to(torch.float32).expand(3, nP, H, W)  # [3, nP, H, W]
        tex = np.zeros((H, nP * W, 4), np.float32)
        tex[:, :, :3] = m.permute(2, 1, 3, 0).reshape(H, nP * W, 3).numpy()  # (row, j*W + x, c)
        tex.setflags(write=False)  # resident on the GPU: uploaded once
        yw = np.ascontiguousarray(y.to(torch.float32).numpy().reshape(-1))
        yw.setflags(write=False)
        ax32 = np.ascontiguousarray(ax.to(torch.float32).numpy())
        ax32.setflags(write=False)
        self.program = shrm_program(nP, H, W, bool(clamp))
        self.num_vertices = int(n.shape[0])
        self._attrs = {"axis": ax32}
        self._tables = {"maps": TableData(tex, "2d"), "view_weights": TableData(yw, "buffer")}

    def inputs(self, num_vertices: int) -> DrawInputs:
        if num_vertices != self.num_vertices:
            raise ValueError(f"decoder holds {self.num_vertices} vertices but the mesh has {num_vertices}")
        return DrawInputs(attributes=self._attrs, uniforms={}, tables=self._tables)


def camera_views(camera: Camera, points: torch.Tensor) -> torch.Tensor:
    """Unit directions from ``points [N, 3]`` towards ``camera``'s eye (perspective) or along its
    axis towards the eye (orthographic): ``[N, 3]`` float64."""
    eye = torch.as_tensor(np.asarray(camera.eye, np.float64))
    pts = torch.as_tensor(points).to(torch.float64)
    if camera.projection == "orthographic":
        d = eye - torch.as_tensor(np.asarray(camera.target, np.float64))
        return (d / d.norm()).expand_as(pts).contiguous()
    v = eye - pts
    return v / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)


def render_shrm(renderer, shrm: SHRM, mesh, camera: Camera, *, decode: str = "glsl", shading: str = "vertex",
                width: int | None = None, height: int | None = None, background: float = 0.0,
                supersample: int = 1, clamp: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """A convex ``mesh`` shaded from ``shrm`` (Ramamoorthi 2002 eq. 5.10) seen by ``camera``.

    ``shading="vertex"``: each vertex's radiance for its normal and its view towards the eye,
    decoded in GLSL (``decode="glsl"``, :class:`SHRMDecoder`) or on the CPU (``"cpu"``,
    ``SHRM.radiance(method="map")``), interpolated across triangles. ``shading="pixel"`` (CPU
    decode only): a G-buffer of the interpolated vertex normals and positions at
    ``supersample``² samples per pixel, each covered sample shaded from its own (normalised)
    normal and its view towards the eye, covered samples averaged. ``clamp`` (default): radiance
    clamped at 0 in either decode (``SHRM.radiance(clamp=True)``: the series' ringing below 0).

    Args: ``renderer``: an open :class:`~prt_torch.render.Renderer`; ``mesh``: a ``scene.Mesh``.
    Returns: (image ``[H, W, 3]`` float32, mask ``[H, W]`` bool), as ``Renderer.render``.
    """
    if shading not in ("vertex", "pixel"):
        raise ValueError(f"shading={shading!r}; accepted: 'vertex', 'pixel'")
    if decode not in ("glsl", "cpu"):
        raise ValueError(f"decode={decode!r}; accepted: 'glsl', 'cpu'")
    if shading == "pixel" and decode != "cpu":
        raise ValueError("shading='pixel' is decoded on the CPU (deferred); accepted: decode='cpu', or shading='vertex'")
    n = mesh.normals.to(torch.float64)
    n = n / n.norm(dim=-1, keepdim=True)
    pos = mesh.vertices.to(torch.float64)
    if shading == "vertex":
        views = camera_views(camera, pos)
        if decode == "glsl":
            return renderer.render(mesh, SHRMDecoder(shrm, n, views, clamp), camera, width, height, background, supersample)
        rad = shrm.radiance(n, views, method="map", clamp=clamp).to(torch.float32)
        return renderer.render_radiance(mesh, rad, camera, width, height, background, supersample)
    W = renderer.width if width is None else int(width)
    H = renderer.height if height is None else int(height)
    s = int(supersample)
    gn, cov = renderer.render_radiance(mesh, n.to(torch.float32), camera, W * s, H * s, float("nan"), 1)
    gp, _ = renderer.render_radiance(mesh, pos.to(torch.float32), camera, W * s, H * s, float("nan"), 1)
    idx = np.flatnonzero(cov.reshape(-1))
    pn = torch.from_numpy(gn.reshape(-1, 3)[idx]).to(torch.float64)
    pn = pn / pn.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    pv = camera_views(camera, torch.from_numpy(gp.reshape(-1, 3)[idx]))
    rad = shrm.radiance(pn, pv, method="map", clamp=clamp).to(torch.float64)
    C = rad.shape[1]
    samples = np.zeros((H * s * W * s, 3), np.float64)
    samples[idx] = rad.expand(-1, 3).numpy() if C == 1 else rad.numpy()
    blk = samples.reshape(H, s, W, s, 3)
    c = cov.reshape(H, s, W, s).astype(np.float64)
    cnt = c.sum(axis=(1, 3))
    mask = cnt > 0
    img = np.divide((blk * c[..., None]).sum(axis=(1, 3)), cnt[..., None], out=np.zeros((H, W, 3)), where=mask[..., None])
    img = img.astype(np.float32)
    img[~mask] = background
    return img, mask
