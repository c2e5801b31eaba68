"""Offscreen float rendering: own GLSL programs into a ``GL_RGBA32F`` framebuffer, read back as
float32 (pyrender's default path is RGBA8 and quantises vertex colours to 8 bits; this one
does not).

One :class:`Renderer` owns a framebuffer (colour ``GL_RGBA32F`` + depth
``GL_DEPTH_COMPONENT32F`` renderbuffers, reallocated when the size changes) and a cache of
compiled programs, in the process-wide EGL context (:mod:`.context`). Use it as a context
manager, or call :meth:`Renderer.close`; it can render any number of images of any size in
between. :func:`render_radiance` uses a shared default renderer.

Rasterisation: depth test ``GL_LESS`` (nearest surface wins), no blending, no multisampling;
both faces drawn unless ``cull_back``. A pixel is covered when its centre is inside a triangle
(GL's rule), and its value is the perspective-correct barycentric interpolation of the vertex
values at the pixel centre. ``supersample=s`` renders s×s samples per pixel and averages the
*covered* samples (edges do not blend toward the background); the mask is "any sample covered".

Resident data: a numpy array passed as an attribute or table that is READ-ONLY
(``arr.flags.writeable`` False) is uploaded once and kept on the GPU for as long as the array
lives (cached by identity through a weak reference), the way a real-time engine keeps static
vertex data resident; writeable arrays (e.g. per-light constants) are uploaded on every draw.
The GLSL decoders mark their per-vertex data read-only.
"""
from __future__ import annotations

import atexit
import ctypes
import weakref
from typing import Any

import numpy as np

from .._checks import check_int
from . import context
from .camera import Camera, bounding_sphere
from .decoders import Decoder, DrawInputs, RadianceDecoder, TableData
from .program import Attribute, FloatBuffer, FloatTexture, GLProgram, ShaderProgram

__all__ = ["Renderer", "render_radiance", "render", "default_renderer", "MAX_PIXELS"]

MAX_PIXELS = 1 << 26  # 64 Mi pixels (1 GiB of RGBA32F): refuse before allocating


def _geometry(mesh) -> tuple[np.ndarray, np.ndarray]:
    if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
        v, f = mesh
    elif hasattr(mesh, "vertices") and hasattr(mesh, "faces"):
        v, f = mesh.vertices, mesh.faces
    else:
        raise TypeError(f"mesh of type {type(mesh).__name__}; accepted: a Mesh (or anything with .vertices "
                        "[V,3] and .faces [F,3]) or a (vertices, faces) pair")
    v = np.asarray(v.detach().cpu().numpy() if hasattr(v, "detach") else v, dtype=np.float64)
    f = np.asarray(f.detach().cpu().numpy() if hasattr(f, "detach") else f)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"mesh vertices have shape {v.shape}; accepted: [V, 3] with V ≥ 1")
    if not np.isfinite(v).all():
        raise ValueError("mesh vertices have non-finite coordinates; accepted: finite values")
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        raise ValueError(f"mesh faces have shape {f.shape} and dtype {f.dtype}; accepted: [F, 3] integers")
    if f.size and (f.min() < 0 or f.max() >= v.shape[0]):
        raise ValueError(f"mesh faces index vertices in [{f.min()}, {f.max()}]; accepted: 0..{v.shape[0] - 1}")
    return v, np.ascontiguousarray(f, dtype=np.uint32)


def _translation(c: np.ndarray) -> np.ndarray:
    m = np.eye(4)
    m[:3, 3] = c
    return m


_FULLSCREEN_TEX = ShaderProgram(
    name="float_roundtrip_2d",
    attributes=(Attribute("corner", 2),),
    mesh=False,
    vertex_body="void main() { gl_Position = vec4(corner, 0.0, 1.0); }\n",
    fragment_body="""
uniform sampler2D data;
uniform int prt_height;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    prt_color = texelFetch(data, ivec2(p.x, prt_height - 1 - p.y), 0);
}
""",
)

_FULLSCREEN_BUF = ShaderProgram(
    name="float_roundtrip_buffer",
    attributes=(Attribute("corner", 2),),
    mesh=False,
    vertex_body="void main() { gl_Position = vec4(corner, 0.0, 1.0); }\n",
    fragment_body="""
uniform samplerBuffer data;
uniform int prt_height;
uniform int prt_width;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    prt_color = texelFetch(data, (prt_height - 1 - p.y) * prt_width + p.x);
}
""",
)


class Renderer:
    """Offscreen float renderer (see module doc). Not thread-safe per instance, but every GL
    call takes the context lock, so several renderers may live in one process.

    Args:
        width, height: default image size in pixels.
        cull_back: skip triangles facing away (counter-clockwise = front). Default False.
    """

    def __init__(self, width: int = 256, height: int = 256, cull_back: bool = False):
        self.width = check_int("width", width, 1)
        self.height = check_int("height", height, 1)
        self.cull_back = bool(cull_back)
        self._programs: dict[ShaderProgram, GLProgram] = {}
        self._resident: dict[int, tuple] = {}  # id(array) -> (weakref, kind, GL object)
        self._index_max_cache: dict[int, tuple] = {}
        self._geometry_cache: dict[int, tuple] = {}
        self._fbo = 0
        self._rbos: list[int] = []
        self._size: tuple[int, int] | None = None
        self._closed = False
        context.acquire()
        self.info = context.gl_info()

    # -- lifetime -------------------------------------------------------------------------
    def __enter__(self) -> "Renderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Delete this renderer's GL objects and release the context (idempotent)."""
        if self._closed:
            return
        with context.LOCK:
            try:
                context.make_current()
                from OpenGL import GL

                for p in self._programs.values():
                    p.delete()
                for key in list(self._resident):
                    self._drop_resident(GL, key)
                self._free_fbo(GL)
            finally:
                self._programs.clear()
                self._closed = True
                context.release()

    @property
    def closed(self) -> bool:
        return self._closed

    # -- framebuffer ----------------------------------------------------------------------
    def _free_fbo(self, GL) -> None:
        if self._fbo:
            GL.glDeleteFramebuffers(1, [self._fbo])
            self._fbo = 0
        if self._rbos:
            GL.glDeleteRenderbuffers(len(self._rbos), self._rbos)
            self._rbos = []
        self._size = None

    def _framebuffer(self, GL, width: int, height: int) -> None:
        if self._size == (width, height):
            GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fbo)
            return
        limit = self.info["max_renderbuffer_size"]
        if width > limit or height > limit:
            raise ValueError(f"image size {width}x{height} (after supersampling); accepted: at most {limit} per side")
        self._free_fbo(GL)
        self._fbo = int(GL.glGenFramebuffers(1))
        GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, self._fbo)
        self._rbos = [int(x) for x in np.atleast_1d(GL.glGenRenderbuffers(2))]
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._rbos[0])
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_RGBA32F, width, height)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_COLOR_ATTACHMENT0, GL.GL_RENDERBUFFER, self._rbos[0])
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, self._rbos[1])
        GL.glRenderbufferStorage(GL.GL_RENDERBUFFER, GL.GL_DEPTH_COMPONENT32F, width, height)
        GL.glFramebufferRenderbuffer(GL.GL_FRAMEBUFFER, GL.GL_DEPTH_ATTACHMENT, GL.GL_RENDERBUFFER, self._rbos[1])
        GL.glBindRenderbuffer(GL.GL_RENDERBUFFER, 0)
        status = GL.glCheckFramebufferStatus(GL.GL_FRAMEBUFFER)
        if status != GL.GL_FRAMEBUFFER_COMPLETE:
            self._free_fbo(GL)
            raise context.RenderUnavailable(f"float framebuffer (GL_RGBA32F + GL_DEPTH_COMPONENT32F) is incomplete "
                                            f"(status 0x{int(status):04x}) on {self.info['renderer']}")
        self._size = (width, height)

    # -- resident (read-only) data ----------------------------------------------------------
    @staticmethod
    def _is_static(obj) -> bool:
        return isinstance(obj, np.ndarray) and not obj.flags.writeable

    def _drop_resident(self, GL, key: int) -> None:
        _, kind, obj = self._resident.pop(key)
        if kind in ("vbo", "ebo"):
            GL.glDeleteBuffers(1, [obj])
        else:
            obj.delete()

    def _purge_resident(self, GL) -> None:
        for key in [k for k, (ref, _, _) in self._resident.items() if ref() is None]:
            self._drop_resident(GL, key)

    def _index_max(self, indices, idx, static: bool) -> int:
        """Largest index; remembered for resident (read-only) index arrays."""
        if static:
            hit = self._index_max_cache.get(id(indices))
            if hit is not None and hit[0]() is indices:
                return hit[1]
            m = int(idx.max())
            self._index_max_cache[id(indices)] = (weakref.ref(indices), m)
            return m
        return int(idx.max())

    def _mesh_geometry(self, mesh):
        """(vertices [V,3] float64, faces [F,3] uint32 read-only, centre [3], centred positions
        [V,3] float32 read-only) of ``mesh``, computed once per mesh object (a ``Mesh`` is treated
        as immutable while it lives; (vertices, faces) pairs are recomputed every call)."""
        key = id(mesh)
        hit = self._geometry_cache.get(key)
        if hit is not None and hit[0]() is mesh and hit[1] == (id(mesh.vertices), id(mesh.faces)):
            return hit[2]
        v, f = _geometry(mesh)
        f = np.array(f, copy=True)  # private: never freeze the caller's array
        centre, _ = bounding_sphere(v)  # draw in centred coordinates: float32 keeps its precision
        pos = (v - centre).astype(np.float32)
        for a in (f, pos):
            a.setflags(write=False)  # resident on the GPU while the mesh lives
        out = (v, f, centre, pos)
        try:
            ref = weakref.ref(mesh, lambda _r, k=key, c=self._geometry_cache: c.pop(k, None))
        except TypeError:  # tuples are not weak-referenceable: no caching
            return out
        for k in [k for k, e in self._geometry_cache.items() if e[0]() is None]:
            del self._geometry_cache[k]
        self._geometry_cache[key] = (ref, (id(mesh.vertices), id(mesh.faces)), out)
        return out

    def _lookup(self, obj, kind: str):
        hit = self._resident.get(id(obj))
        if hit is not None and hit[0]() is obj and hit[1] == kind:
            return hit[2]
        return None

    def _program(self, spec: ShaderProgram) -> GLProgram:
        prog = self._programs.get(spec)
        if prog is None:
            prog = self._programs[spec] = GLProgram(spec)
        return prog

    # -- the generic draw -----------------------------------------------------------------
    def draw(self, program: ShaderProgram, attributes: dict[str, Any], indices, width: int, height: int,
             uniforms: dict[str, Any] | None = None, tables: dict[str, TableData] | None = None,
             depth_test: bool = True) -> np.ndarray:
        """Run ``program`` over indexed triangles into a ``width``×``height`` float framebuffer.

        Args:
            program: the :class:`ShaderProgram`; ``attributes`` must hold an array for each
                entry of ``program.layout`` (``[V, k]`` or ``[V]``; float32 for float
                attributes, int32 for int ones).
            indices: ``[F, 3]`` (or ``[3F]``) vertex indices.
            uniforms: name -> value (see ``GLProgram.set_uniform``).
            tables: sampler name -> :class:`TableData`, uploaded as float32 textures.
        Returns:
            ``[H, W, 4] float32``, row 0 = top: the program's ``prt_color`` where covered, 0
            elsewhere (alpha 0 = not covered).
        """
        width, height = check_int("width", width, 1), check_int("height", height, 1)
        if width * height > MAX_PIXELS:
            raise ValueError(f"image of {width}x{height} pixels; accepted: at most {MAX_PIXELS} pixels")
        if self._closed:
            raise ValueError("this Renderer is closed; create a new one")
        arrays = []
        origins = []
        nverts = None
        for a in program.layout:
            if a.name not in attributes:
                raise ValueError(f"program {program.name!r} needs attribute {a.name!r}; got {sorted(attributes)}")
            x = attributes[a.name]
            origins.append(x)
            x = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x)
            x = np.ascontiguousarray(x.reshape(x.shape[0], -1), dtype=a.numpy_dtype)
            if x.shape[1] != a.components:
                raise ValueError(f"attribute {a.name!r} has {x.shape[1]} components per vertex; program "
                                 f"{program.name!r} declares {a.components}")
            if nverts is not None and x.shape[0] != nverts:
                raise ValueError(f"attribute {a.name!r} has {x.shape[0]} rows, others {nverts}")
            nverts = x.shape[0]
            arrays.append(x)
        static_idx = self._is_static(indices) and indices.dtype == np.uint32
        idx = np.ascontiguousarray(np.asarray(indices).reshape(-1), dtype=np.uint32)
        if idx.size % 3:
            raise ValueError(f"indices hold {idx.size} values; accepted: a multiple of 3 (triangles)")
        if idx.size and nverts is not None and int(self._index_max(indices, idx, static_idx)) >= nverts:
            raise ValueError(f"indices reach {int(idx.max())}; accepted: below the {nverts} vertices")
        with context.LOCK:
            context.make_current()
            from OpenGL import GL

            prog = self._program(program)
            self._framebuffer(GL, width, height)
            GL.glViewport(0, 0, width, height)
            GL.glDisable(GL.GL_BLEND)
            GL.glDisable(GL.GL_MULTISAMPLE)
            GL.glDisable(GL.GL_DITHER)
            if depth_test:
                GL.glEnable(GL.GL_DEPTH_TEST)
                GL.glDepthFunc(GL.GL_LESS)
            else:
                GL.glDisable(GL.GL_DEPTH_TEST)
            if self.cull_back:
                GL.glEnable(GL.GL_CULL_FACE)
                GL.glCullFace(GL.GL_BACK)
            else:
                GL.glDisable(GL.GL_CULL_FACE)
            GL.glDrawBuffers(1, [GL.GL_COLOR_ATTACHMENT0])
            GL.glClearColor(0.0, 0.0, 0.0, 0.0)
            GL.glClearDepth(1.0)
            GL.glClear(GL.GL_COLOR_BUFFER_BIT | GL.GL_DEPTH_BUFFER_BIT)
            self._purge_resident(GL)
            vao = int(GL.glGenVertexArrays(1))
            vbos = [int(x) for x in np.atleast_1d(GL.glGenBuffers(len(arrays) + 1))]
            textures: list = []
            try:
                GL.glBindVertexArray(vao)
                for loc, (a, x, orig) in enumerate(zip(program.layout, arrays, origins)):
                    vbo = self._lookup(orig, "vbo") if self._is_static(orig) else None
                    if vbo is not None:
                        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
                    elif self._is_static(orig):  # upload once, keep while the array lives
                        vbo = int(np.atleast_1d(GL.glGenBuffers(1))[0])
                        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbo)
                        GL.glBufferData(GL.GL_ARRAY_BUFFER, x.nbytes, x, GL.GL_STATIC_DRAW)
                        self._resident[id(orig)] = (weakref.ref(orig), "vbo", vbo)
                    else:
                        GL.glBindBuffer(GL.GL_ARRAY_BUFFER, vbos[loc])
                        GL.glBufferData(GL.GL_ARRAY_BUFFER, x.nbytes, x, GL.GL_STATIC_DRAW)
                    GL.glEnableVertexAttribArray(loc)
                    if a.kind == "float":
                        GL.glVertexAttribPointer(loc, a.components, GL.GL_FLOAT, GL.GL_FALSE, 0, ctypes.c_void_p(0))
                    else:
                        GL.glVertexAttribIPointer(loc, a.components, GL.GL_INT, 0, ctypes.c_void_p(0))
                ebo = self._lookup(indices, "ebo") if static_idx and idx.size else None
                if ebo is not None:
                    GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ebo)
                elif static_idx and idx.size:
                    ebo = int(np.atleast_1d(GL.glGenBuffers(1))[0])
                    GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, ebo)
                    GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, idx.nbytes, idx, GL.GL_STATIC_DRAW)
                    self._resident[id(indices)] = (weakref.ref(indices), "ebo", ebo)
                else:
                    GL.glBindBuffer(GL.GL_ELEMENT_ARRAY_BUFFER, vbos[-1])
                    GL.glBufferData(GL.GL_ELEMENT_ARRAY_BUFFER, max(idx.nbytes, 4), idx if idx.size else np.zeros(1, np.uint32),
                                    GL.GL_STATIC_DRAW)
                prog.use()
                for name, value in (uniforms or {}).items():
                    prog.set_uniform(name, value)
                # create every table first, then bind: creating one binds and unbinds it on the
                # active unit, which would clear a table already bound there
                bound = []
                for name, table in (tables or {}).items():
                    kind = "tbo" if table.kind == "buffer" else "tex"
                    tex = self._lookup(table.data, kind) if self._is_static(table.data) else None
                    if tex is None:
                        tex = FloatBuffer(table.data) if table.kind == "buffer" else FloatTexture(table.data)
                        if self._is_static(table.data):
                            self._resident[id(table.data)] = (weakref.ref(table.data), kind, tex)
                        else:
                            textures.append(tex)  # deleted after the draw
                    bound.append((name, tex))
                for unit, (name, tex) in enumerate(bound):
                    tex.bind(unit)
                    prog.set_uniform(name, unit)
                if idx.size:
                    GL.glDrawElements(GL.GL_TRIANGLES, int(idx.size), GL.GL_UNSIGNED_INT, ctypes.c_void_p(0))
                GL.glFinish()
                out = np.empty((height, width, 4), np.float32)
                GL.glReadBuffer(GL.GL_COLOR_ATTACHMENT0)
                GL.glPixelStorei(GL.GL_PACK_ALIGNMENT, 1)
                GL.glReadPixels(0, 0, width, height, GL.GL_RGBA, GL.GL_FLOAT, out)
            finally:
                GL.glBindVertexArray(0)
                GL.glUseProgram(0)
                for tex in textures:
                    tex.delete()
                GL.glDeleteBuffers(len(vbos), vbos)
                GL.glDeleteVertexArrays(1, [vao])
                GL.glBindFramebuffer(GL.GL_FRAMEBUFFER, 0)
        return out[::-1].copy()  # GL rows run bottom-to-top

    # -- mesh rendering -------------------------------------------------------------------
    def render(self, mesh, decoder: Decoder, camera: Camera | None = None, width: int | None = None,
               height: int | None = None, background: float = 0.0, supersample: int = 1
               ) -> tuple[np.ndarray, np.ndarray]:
        """Render ``mesh`` coloured by ``decoder`` (see :mod:`.decoders`).

        Args:
            mesh: a ``Mesh`` (``vertices [V,3]``, ``faces [F,3]``) or a (vertices, faces) pair.
            decoder: e.g. ``RadianceDecoder(radiance [V,3])``.
            camera: a :class:`Camera`; default ``Camera.fit(mesh, aspect=width/height)``.
            width, height: pixels (default: the renderer's).
            background: value of uncovered pixels (e.g. 0.0 or ``float('nan')``).
            supersample: s ≥ 1; s×s samples per pixel, covered samples averaged.
        Returns:
            (image ``[H, W, 3] float32``, mask ``[H, W] bool`` = covered).
        """
        width = self.width if width is None else check_int("width", width, 1)
        height = self.height if height is None else check_int("height", height, 1)
        s = check_int("supersample", supersample, 1, 8)
        try:
            background = float(background)  # any float, NaN included
        except (TypeError, ValueError):
            raise TypeError(f"background={background!r}; accepted: a number (NaN allowed)") from None
        if not isinstance(decoder, Decoder):
            raise TypeError(f"decoder of type {type(decoder).__name__}; accepted: a prt_torch.render Decoder")
        if not decoder.program.mesh:
            raise ValueError(f"program {decoder.program.name!r} is not a mesh program (mesh=False)")
        if isinstance(mesh, (tuple, list)):
            v, f = _geometry(mesh)
            centre, _ = bounding_sphere(v)  # draw in centred coordinates: float32 keeps its precision
            pos = (v - centre).astype(np.float32)
        else:
            v, f, centre, pos = self._mesh_geometry(mesh)
        if camera is None:
            camera = Camera.fit(v, aspect=width / height)
        elif not isinstance(camera, Camera):
            raise TypeError(f"camera of type {type(camera).__name__}; accepted: prt_torch.render.Camera or None")
        inputs: DrawInputs = decoder.inputs(v.shape[0])
        mvp = camera.clip_matrix(width, height) @ _translation(centre)
        attrs = dict(inputs.attributes)
        attrs["position"] = pos
        uniforms = dict(inputs.uniforms)
        uniforms["prt_mvp"] = mvp
        raw = self.draw(decoder.program, attrs, f, width * s, height * s, uniforms=uniforms, tables=inputs.tables)
        c = decoder.channels
        if s == 1:
            img = raw[:, :, :c].copy()
            mask = raw[:, :, 3] > 0
        else:
            blk = raw.reshape(height, s, width, s, 4)
            cov = (blk[..., 3] > 0).astype(np.float64)
            n = cov.sum(axis=(1, 3))
            acc = (blk[..., :c].astype(np.float64) * cov[..., None]).sum(axis=(1, 3))
            mask = n > 0
            img = np.divide(acc, n[..., None], out=np.zeros_like(acc), where=mask[..., None]).astype(np.float32)
        img[~mask] = background
        return img, mask

    def render_radiance(self, mesh, radiance, camera: Camera | None = None, width: int | None = None,
                        height: int | None = None, background: float = 0.0, supersample: int = 1
                        ) -> tuple[np.ndarray, np.ndarray]:
        """Render per-vertex exit radiance ``[V,3]`` (or ``[V]``) float; see :meth:`render`."""
        return self.render(mesh, RadianceDecoder(radiance), camera, width, height, background, supersample)

    def float_roundtrip(self, data, kind: str = "2d") -> np.ndarray:
        """Upload ``data [H, W, C]`` (C in 1..4) as a float texture (``kind='2d'``) or texture
        buffer (``'buffer'``), copy it to the framebuffer with ``texelFetch`` and read it back:
        ``[H, W, C] float32``. Equal to ``data.astype(float32)`` when nothing quantises."""
        arr = np.asarray(data.detach().cpu().numpy() if hasattr(data, "detach") else data, dtype=np.float32)
        if arr.ndim == 2:
            arr = arr[:, :, None]
        if arr.ndim != 3 or arr.shape[2] not in (1, 2, 3, 4):
            raise ValueError(f"data has shape {arr.shape}; accepted: [H, W] or [H, W, C] with C in 1..4")
        h, w, c = arr.shape
        corners = np.array([[-1, -1], [3, -1], [-1, 3]], np.float32)  # one triangle covering the viewport
        if kind == "2d":
            prog, table, unif = _FULLSCREEN_TEX, TableData(arr, "2d"), {"prt_height": h}
        elif kind == "buffer":
            prog, table, unif = _FULLSCREEN_BUF, TableData(arr.reshape(h * w, c), "buffer"), {"prt_height": h, "prt_width": w}
        else:
            raise ValueError(f"kind={kind!r}; accepted: '2d' or 'buffer'")
        out = self.draw(prog, {"corner": corners}, np.arange(3), w, h, uniforms=unif, tables={"data": table},
                        depth_test=False)
        return out[:, :, :c]


_default: dict = {"renderer": None}


def default_renderer() -> Renderer:
    """The process-wide renderer used by :func:`render_radiance` (created on first use, closed
    at exit)."""
    r = _default["renderer"]
    if r is None or r.closed:
        r = _default["renderer"] = Renderer()
        atexit.register(r.close)
    return r


def render(mesh, decoder: Decoder, camera: Camera | None = None, width: int = 256, height: int = 256,
           background: float = 0.0, supersample: int = 1, renderer: Renderer | None = None):
    """:meth:`Renderer.render` on ``renderer`` (default: :func:`default_renderer`)."""
    return (renderer or default_renderer()).render(mesh, decoder, camera, width, height, background, supersample)


def render_radiance(mesh, radiance, camera: Camera | None = None, width: int = 256, height: int = 256,
                    background: float = 0.0, supersample: int = 1, renderer: Renderer | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Render per-vertex exit radiance as a float image.

    Args:
        mesh: a ``Mesh`` or (vertices ``[V,3]``, faces ``[F,3]``).
        radiance: ``[V,3]`` (or ``[V]`` grey) float32/float64 tensor or array — e.g. the output
            of ``relight.diffuse`` (Sloan 2002: L_out = t_p·l).
        camera: a :class:`Camera` (default: fitted to the bounding sphere, azimuth 35°,
            elevation 25°, 40° field of view).
        width, height: pixels; background: value of uncovered pixels; supersample: s×s samples.
        renderer: a :class:`Renderer` to reuse (default: the shared one).
    Returns:
        (image ``[H, W, 3] float32`` linear radiance, row 0 = top; mask ``[H, W] bool``).
    """
    return (renderer or default_renderer()).render_radiance(mesh, radiance, camera, width, height, background,
                                                            supersample)
