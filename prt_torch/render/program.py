"""GLSL programs with a declared vertex-attribute layout, and float data uploads.

A :class:`ShaderProgram` is pure data (no GL): a name, an attribute layout and the bodies of
the vertex and fragment shaders. The header of each stage is generated from the layout so
that Python and GLSL cannot disagree::

    #version 410 core
    layout(location = 0) in vec3 position;      // attribute 0 is always the position
    layout(location = 1) in vec3 radiance;      // then the program's own attributes, in order
    ...
    // fragment stage:
    layout(location = 0) out vec4 prt_color;    // rgb = the value, a = 1 where covered

Every mesh program receives ``uniform mat4 prt_mvp`` (clip-from-world, with the renderer's
model offset folded in) and must write ``prt_color`` with alpha 1 (the coverage mask is
``alpha > 0``; the framebuffer is cleared to alpha 0).

Float data reaches shaders without quantisation through

* vertex attributes: ``float`` (``glVertexAttribPointer``, GL_FLOAT) or ``int``
  (``glVertexAttribIPointer``, GL_INT — e.g. a cluster id);
* :class:`FloatTexture`: a 2-D ``GL_R32F``/``GL_RG32F``/``GL_RGB32F``/``GL_RGBA32F`` texture
  uploaded with ``glTexImage2D(..., GL_FLOAT, ...)``, nearest filtering, read with
  ``texelFetch`` (exact: no filtering, no normalisation);
* :class:`FloatBuffer`: a texture buffer object (``samplerBuffer``), a 1-D float array of up to
  ``GL_MAX_TEXTURE_BUFFER_SIZE`` texels (128 Mi on llvmpipe) — for per-cluster tables longer than
  a texture row;
* uniforms (scalars, vectors, matrices, arrays), set by name with the type GL reports for them.

GL objects are created in the shared context (:mod:`.context`); callers hold ``context.LOCK``.
"""
from __future__ import annotations

import dataclasses
import re

import numpy as np

__all__ = ["Attribute", "ShaderProgram", "GLProgram", "FloatTexture", "FloatBuffer", "GLSL_VERSION"]

GLSL_VERSION = "410 core"
_FLOAT_TYPES = {1: "float", 2: "vec2", 3: "vec3", 4: "vec4"}
_INT_TYPES = {1: "int", 2: "ivec2", 3: "ivec3", 4: "ivec4"}
_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")


@dataclasses.dataclass(frozen=True)
class Attribute:
    """One per-vertex input: ``name`` (a GLSL identifier), ``components`` in 1..4, ``kind``
    ``'float'`` (float32 data) or ``'int'`` (int32 data, e.g. a cluster index)."""

    name: str
    components: int
    kind: str = "float"

    def __post_init__(self):
        if not isinstance(self.name, str) or not _NAME.match(self.name) or self.name.startswith("gl_"):
            raise ValueError(f"attribute name {self.name!r}; accepted: a GLSL identifier not starting with gl_")
        if self.components not in (1, 2, 3, 4):
            raise ValueError(f"attribute {self.name!r}: components={self.components!r}; accepted: 1, 2, 3 or 4 "
                             "(split longer vectors over several attributes)")
        if self.kind not in ("float", "int"):
            raise ValueError(f"attribute {self.name!r}: kind={self.kind!r}; accepted: 'float' or 'int'")

    @property
    def glsl_type(self) -> str:
        return (_FLOAT_TYPES if self.kind == "float" else _INT_TYPES)[self.components]

    @property
    def numpy_dtype(self):
        return np.float32 if self.kind == "float" else np.int32


POSITION = Attribute("position", 3)


@dataclasses.dataclass(frozen=True)
class ShaderProgram:
    """A GLSL program as data: ``attributes`` (after the implicit ``position``) and the two
    shader bodies (everything after the generated header: uniforms, varyings, ``main``).

    ``mesh=False`` programs (full-screen passes) have no implicit ``position`` attribute and no
    ``prt_mvp``; their first attribute is whatever they declare."""

    name: str
    attributes: tuple[Attribute, ...]
    vertex_body: str
    fragment_body: str
    mesh: bool = True

    def __post_init__(self):
        names = [a.name for a in self.layout]
        if len(set(names)) != len(names):
            raise ValueError(f"program {self.name!r}: duplicate attribute names {names}")

    @property
    def layout(self) -> tuple[Attribute, ...]:
        """Attributes in location order (location i = index i)."""
        return ((POSITION,) if self.mesh else ()) + tuple(self.attributes)

    def vertex_source(self) -> str:
        decl = "\n".join(f"layout(location = {i}) in {a.glsl_type} {a.name};" for i, a in enumerate(self.layout))
        return f"#version {GLSL_VERSION}\n{decl}\n#line 1\n{self.vertex_body}"

    def fragment_source(self) -> str:
        return f"#version {GLSL_VERSION}\nlayout(location = 0) out vec4 prt_color;\n#line 1\n{self.fragment_body}"


def _gl():
    from OpenGL import GL

    return GL


def _compile(GL, kind, source: str, program_name: str, stage: str) -> int:
    sh = GL.glCreateShader(kind)
    GL.glShaderSource(sh, source)
    GL.glCompileShader(sh)
    if not GL.glGetShaderiv(sh, GL.GL_COMPILE_STATUS):
        log = GL.glGetShaderInfoLog(sh)
        GL.glDeleteShader(sh)
        log = log.decode(errors="replace") if isinstance(log, bytes) else str(log)
        raise ValueError(f"GLSL {stage} shader of program {program_name!r} does not compile:\n{log}")
    return sh


class GLProgram:
    """A compiled and linked :class:`ShaderProgram` in the current context, with its active
    uniforms (name -> (location, GL type, array size)) introspected after linking."""

    def __init__(self, spec: ShaderProgram):
        GL = _gl()
        self.spec = spec
        vs = _compile(GL, GL.GL_VERTEX_SHADER, spec.vertex_source(), spec.name, "vertex")
        try:
            fs = _compile(GL, GL.GL_FRAGMENT_SHADER, spec.fragment_source(), spec.name, "fragment")
        except Exception:
            GL.glDeleteShader(vs)
            raise
        prog = GL.glCreateProgram()
        GL.glAttachShader(prog, vs)
        GL.glAttachShader(prog, fs)
        GL.glLinkProgram(prog)
        GL.glDeleteShader(vs)
        GL.glDeleteShader(fs)
        if not GL.glGetProgramiv(prog, GL.GL_LINK_STATUS):
            log = GL.glGetProgramInfoLog(prog)
            GL.glDeleteProgram(prog)
            log = log.decode(errors="replace") if isinstance(log, bytes) else str(log)
            raise ValueError(f"GLSL program {spec.name!r} does not link:\n{log}")
        self.id = int(prog)
        self.uniforms: dict[str, tuple[int, int, int]] = {}
        for i in range(int(GL.glGetProgramiv(prog, GL.GL_ACTIVE_UNIFORMS))):
            name, size, typ = GL.glGetActiveUniform(prog, i)
            name = name.decode() if isinstance(name, bytes) else str(name)
            base = name[:-3] if name.endswith("[0]") else name
            self.uniforms[base] = (int(GL.glGetUniformLocation(prog, name)), int(typ), int(size))

    def use(self) -> None:
        _gl().glUseProgram(self.id)

    def set_uniform(self, name: str, value) -> None:
        """Set uniform ``name`` (program in use) from a number or array, by its GLSL type.

        Accepted: float/vecN/matN (float32, matrices given row-major ``[..., N, N]`` as in numpy),
        int/ivecN and samplers (ints); arrays as ``[count, ...]``. Unknown names (e.g. optimised
        out) are refused with the list of active uniforms."""
        GL = _gl()
        if name not in self.uniforms:
            raise ValueError(f"program {self.spec.name!r} has no active uniform {name!r}; active: {sorted(self.uniforms)}")
        loc, typ, size = self.uniforms[name]
        setters = {
            GL.GL_FLOAT: (GL.glUniform1fv, 1), GL.GL_FLOAT_VEC2: (GL.glUniform2fv, 2),
            GL.GL_FLOAT_VEC3: (GL.glUniform3fv, 3), GL.GL_FLOAT_VEC4: (GL.glUniform4fv, 4),
            GL.GL_INT: (GL.glUniform1iv, 1), GL.GL_INT_VEC2: (GL.glUniform2iv, 2),
            GL.GL_INT_VEC3: (GL.glUniform3iv, 3), GL.GL_INT_VEC4: (GL.glUniform4iv, 4),
        }
        mats = {GL.GL_FLOAT_MAT2: (GL.glUniformMatrix2fv, 4), GL.GL_FLOAT_MAT3: (GL.glUniformMatrix3fv, 9),
                GL.GL_FLOAT_MAT4: (GL.glUniformMatrix4fv, 16)}
        samplers = {GL.GL_SAMPLER_2D, GL.GL_SAMPLER_BUFFER, GL.GL_INT_SAMPLER_2D, GL.GL_INT_SAMPLER_BUFFER,
                    GL.GL_UNSIGNED_INT_SAMPLER_2D, GL.GL_UNSIGNED_INT_SAMPLER_BUFFER}
        arr = np.asarray(value.detach().cpu().numpy() if hasattr(value, "detach") else value)
        if typ in mats:
            fn, n = mats[typ]
            data = np.ascontiguousarray(arr, dtype=np.float32).reshape(-1)
            count = data.size // n
            if data.size != count * n or not 1 <= count <= size:
                raise ValueError(f"uniform {name!r} of program {self.spec.name!r} takes {size} matrix(es) of {n} "
                                 f"floats; got shape {arr.shape}")
            fn(loc, count, GL.GL_TRUE, data)  # row-major numpy -> transpose=GL_TRUE
            return
        if typ in samplers:
            fn, n = GL.glUniform1iv, 1
        elif typ in setters:
            fn, n = setters[typ]
        else:
            raise ValueError(f"uniform {name!r} of program {self.spec.name!r} has GL type 0x{typ:04x}, which "
                             "set_uniform does not handle")
        is_int = fn in (GL.glUniform1iv, GL.glUniform2iv, GL.glUniform3iv, GL.glUniform4iv)
        data = np.ascontiguousarray(arr, dtype=np.int32 if is_int else np.float32).reshape(-1)
        count = data.size // n
        if data.size != count * n or not 1 <= count <= size:
            raise ValueError(f"uniform {name!r} of program {self.spec.name!r} takes up to {size} value(s) of {n} "
                             f"component(s); got shape {arr.shape}")
        fn(loc, count, data)

    def delete(self) -> None:
        if self.id:
            _gl().glDeleteProgram(self.id)
            self.id = 0


_TEX_FORMATS = {1: ("GL_R32F", "GL_RED"), 2: ("GL_RG32F", "GL_RG"), 3: ("GL_RGB32F", "GL_RGB"), 4: ("GL_RGBA32F", "GL_RGBA")}


def _float_array(name: str, data, ndim_ok: tuple[int, ...]) -> np.ndarray:
    arr = np.asarray(data.detach().cpu().numpy() if hasattr(data, "detach") else data)
    if arr.dtype.kind not in "fiu":
        raise TypeError(f"{name} has dtype {arr.dtype}; accepted: real numbers (stored as float32)")
    if arr.ndim not in ndim_ok:
        raise ValueError(f"{name} has shape {arr.shape}; accepted: {' or '.join(f'{d}-D' for d in ndim_ok)}")
    return np.ascontiguousarray(arr, dtype=np.float32)


class FloatTexture:
    """A 2-D float32 texture from ``data [H, W]`` or ``[H, W, C]`` (C in 1..4).

    Stored as ``GL_R32F``..``GL_RGBA32F`` with nearest filtering; read in GLSL with
    ``texelFetch(sampler, ivec2(x, y), 0)`` where x is the column and y the row of ``data``.
    Upload is ``glTexImage2D(..., GL_FLOAT, data)``: bit-exact float32 (tested), except that
    denormals may be flushed to zero by the rasteriser's arithmetic, not by the texture.
    """

    def __init__(self, data):
        GL = _gl()
        arr = _float_array("texture data", data, (2, 3))
        if arr.ndim == 2:
            arr = arr[:, :, None]
        h, w, c = arr.shape
        if c not in _TEX_FORMATS:
            raise ValueError(f"texture data has {c} channels; accepted: 1..4 (shape [H, W, C])")
        limit = int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_SIZE))
        if not (1 <= h <= limit and 1 <= w <= limit):
            raise ValueError(f"texture data of {h}x{w} texels; accepted: 1..{limit} per side "
                             "(use FloatBuffer for long 1-D tables)")
        internal, fmt = (getattr(GL, n) for n in _TEX_FORMATS[c])
        self.shape = (h, w, c)
        self.target = GL.GL_TEXTURE_2D
        self.id = int(GL.glGenTextures(1))
        GL.glBindTexture(GL.GL_TEXTURE_2D, self.id)
        GL.glPixelStorei(GL.GL_UNPACK_ALIGNMENT, 1)
        GL.glTexImage2D(GL.GL_TEXTURE_2D, 0, internal, w, h, 0, fmt, GL.GL_FLOAT, arr)
        for p in (GL.GL_TEXTURE_MIN_FILTER, GL.GL_TEXTURE_MAG_FILTER):
            GL.glTexParameteri(GL.GL_TEXTURE_2D, p, GL.GL_NEAREST)
        for p in (GL.GL_TEXTURE_WRAP_S, GL.GL_TEXTURE_WRAP_T):
            GL.glTexParameteri(GL.GL_TEXTURE_2D, p, GL.GL_CLAMP_TO_EDGE)
        GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MAX_LEVEL, 0)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)

    def bind(self, unit: int) -> None:
        GL = _gl()
        GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
        GL.glBindTexture(GL.GL_TEXTURE_2D, self.id)

    def delete(self) -> None:
        if self.id:
            _gl().glDeleteTextures([self.id])
            self.id = 0


class FloatBuffer:
    """A texture buffer object from ``data [N]`` or ``[N, C]`` (C in 1..4) float32, read in GLSL
    as ``texelFetch(samplerBuffer, i)`` (``GL_R32F``..``GL_RGBA32F``; RGB32F needs GL 4.0).

    For per-cluster tables (e.g. CPCA's M_k·l, Sloan 2003 eq. (3)) longer than a texture row.
    """

    def __init__(self, data):
        GL = _gl()
        arr = _float_array("buffer data", data, (1, 2))
        if arr.ndim == 1:
            arr = arr[:, None]
        n, c = arr.shape
        if c not in _TEX_FORMATS:
            raise ValueError(f"buffer data has {c} channels; accepted: 1..4 (shape [N, C])")
        limit = int(GL.glGetIntegerv(GL.GL_MAX_TEXTURE_BUFFER_SIZE))
        if not 1 <= n <= limit:
            raise ValueError(f"buffer data of {n} texels; accepted: 1..{limit}")
        self.shape = (n, c)
        self.target = GL.GL_TEXTURE_BUFFER
        self.buffer = int(GL.glGenBuffers(1))
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, self.buffer)
        GL.glBufferData(GL.GL_TEXTURE_BUFFER, arr.nbytes, arr, GL.GL_STATIC_DRAW)
        GL.glBindBuffer(GL.GL_TEXTURE_BUFFER, 0)
        self.id = int(GL.glGenTextures(1))
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.id)
        GL.glTexBuffer(GL.GL_TEXTURE_BUFFER, getattr(GL, _TEX_FORMATS[c][0]), self.buffer)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, 0)

    def bind(self, unit: int) -> None:
        GL = _gl()
        GL.glActiveTexture(GL.GL_TEXTURE0 + unit)
        GL.glBindTexture(GL.GL_TEXTURE_BUFFER, self.id)

    def delete(self) -> None:
        GL = _gl()
        if self.id:
            GL.glDeleteTextures([self.id])
            self.id = 0
        if self.buffer:
            GL.glDeleteBuffers(1, [self.buffer])
            self.buffer = 0
