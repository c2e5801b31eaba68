"""GLSL decoders: precomputed radiance transfer evaluated in the vertex shader.

Every decoder here computes, per vertex p, the exit radiance of one transfer kind from data
uploaded unquantised (float attributes, int attributes, ``RGBA32F`` texture buffers, float
uniforms — see :mod:`.program`), and writes it to the rasteriser as a varying (Gouraud). The
CPU side computes only what a real-time engine computes per light (the light vector, and the
per-cluster constants M_k·l of a codec) and per camera (the per-vertex view weights).

Programs are generated from a few integers (rows, clusters, vectors, view mode) so that Python
and GLSL cannot disagree; :func:`ShaderProgram` values are cached (equal specs share one
compiled program in a :class:`~prt_torch.render.Renderer`).

View modes (how the n_out outputs of a vertex become one RGB radiance):

* ``'none'``     — vector signal (diffuse ``[V, n²]``): rgb = row 0 (× albedo).
* ``'diagonal'`` — diffuse RGB transfer ``[V, 3, n²]``: channel c = channel c of row c.
* ``'dense'``    — glossy exit transfer (Sloan 2003 §3.1): rgb = Σ_o y_{o}(v_p) row_o, the
  per-vertex SH weights y(v_p) (zero below the horizon, ``relight.glossy_view_weights``) read
  from a texture buffer ``[V·n_out]``.
* ``'taps'``     — matrix radiance transfer (Lehtinen & Kautz 2003 eq. 13): rgb = Σ_{t<4}
  g_t(v_p) row_{idx_t}, the four tent taps (``relight.mrt_view_taps``) as ``ivec4``/``vec4``
  attributes.

Rows:

* :class:`TransferDecoder` (uncompressed): row_o = Σ_i T_p[o, i] l_i, the transfer read from a
  texture buffer (RGBA32F, 4 coefficients a texel) and the light as a uniform array
  (Sloan 2002 eq. (7) for diffuse; e_p = M_p l, Sloan 2003 §3.1; A_p l, MRT eq. 9).
* :class:`AffineDecoder` and its per-family subclasses (VQ, PCA, CPCA, MRT-PCA; Sloan 2003
  §6.2 eq. (3)–(4), MRT eq. 13): row_o = (M_k^0 l)_o + Σ_i w_p^i (M_k^i l)_o with k the
  vertex's cluster (int attribute), w_p its PCA weights (``vec4`` attributes, or a texture
  buffer when there are more than fit the attribute budget) and the per-cluster constants
  M_k^i l computed per light on the CPU (``codec.cluster_constants``) into a float table
  indexed by cluster id. :class:`NeuralDecoder` (the learned codec) is the same program on the
  cached features h(z_p) and the constants W_k^T l.

* :class:`GaussianDecoder` (Green 2005 eq. 2.7, §2.3): Σ_k w_k E_{σ_k}(μ_k) with the lobes
  interpolated across the three nearest stored views on the CPU once per camera
  (:func:`gaussian_view_lobes`) and the prefiltered-environment lookup done in GLSL exactly as
  ``PrefilteredEnvironment.lookup`` (the cube levels as one RGBA32F texture buffer).

Codec decoders are chosen by codec name (:func:`register_codec_decoder`,
:func:`codec_decoder`): a new codec family registers its own
:class:`~prt_torch.render.decoders.Decoder` subclass with a ``from_codec`` constructor.
"""
from __future__ import annotations

import functools
from typing import Callable

import numpy as np

from .decoders import Decoder, DrawInputs, TableData
from .program import Attribute, ShaderProgram

__all__ = ["VIEW_MODES", "TransferDecoder", "AffineDecoder", "VQDecoder", "PCADecoder", "CPCADecoder",
           "MRTPCADecoder", "NeuralDecoder", "register_codec_decoder", "codec_decoder", "codec_decoders", "transfer_program",
           "affine_program", "MAX_WEIGHT_ATTRIBUTES", "GaussianDecoder", "gaussian_program", "gaussian_view_lobes",
           "MAX_LOBE_ATTRIBUTES"]

VIEW_MODES = ("none", "diagonal", "dense", "taps")
#: vec4 weight attributes at most (16 attribute slots on every GL 4 implementation: position,
#: cluster, albedo, two tap attributes leave 11); more weights go through a texture buffer.
MAX_WEIGHT_ATTRIBUTES = 11


def _np(name: str, x, dtype) -> np.ndarray:
    a = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x)
    if a.dtype.kind not in "fiub":
        raise TypeError(f"{name} has dtype {a.dtype}; accepted: real numbers")
    a = np.ascontiguousarray(a, dtype=dtype)
    if a.dtype.kind == "f" and not np.isfinite(a).all():
        raise ValueError(f"{name} has non-finite values; accepted: finite float32 values")
    return a


def _frozen(a: np.ndarray) -> np.ndarray:
    """A read-only private copy: the renderer keeps read-only arrays resident on the GPU (uploaded
    once, for as long as the array lives)."""
    b = np.array(a, copy=True, order="C")
    b.setflags(write=False)
    return b


_FRAGMENT = """
in vec3 v_radiance;
void main() {
    prt_color = vec4(v_radiance, 1.0);
}
"""


def _view_glsl(mode: str, n_out: int) -> tuple[tuple[Attribute, ...], str, str]:
    """Attributes, declarations and the body of ``vec3 view_sum()`` for a view mode."""
    if mode == "none":
        return (), "", "vec3 view_sum() { return row(0); }\n"
    if mode == "diagonal":
        return (), "", ("vec3 view_sum() {\n    return vec3(row(0).r, row(1).g, row(2).b);\n}\n")
    if mode == "dense":
        decl = "uniform samplerBuffer view_weights;  // R32F [V * N_OUT]: y_o(v_p), 0 below the horizon\n"
        body = ("vec3 view_sum() {\n    vec3 s = vec3(0.0);\n    int base = gl_VertexID * N_OUT;\n"
                "    for (int o = 0; o < N_OUT; ++o) {\n        float y = texelFetch(view_weights, base + o).r;\n"
                "        if (y != 0.0) s += y * row(o);\n    }\n    return s;\n}\n")
        return (), decl, body
    if mode == "taps":
        attrs = (Attribute("tap_idx", 4, "int"), Attribute("tap_w", 4))
        body = ("vec3 view_sum() {  // Lehtinen & Kautz 2003 eq. 13: four tents nonzero at v_p\n"
                "    vec3 s = vec3(0.0);\n    for (int t = 0; t < 4; ++t) {\n"
                "        if (tap_w[t] != 0.0) s += tap_w[t] * row(tap_idx[t]);\n    }\n    return s;\n}\n")
        return attrs, "", body
    raise ValueError(f"view mode {mode!r}; accepted: {', '.join(VIEW_MODES)}")


def _main() -> str:
    return ("void main() {\n    prt_setup();\n    v_radiance = view_sum() * albedo;\n"
            "    gl_Position = prt_mvp * vec4(position, 1.0);\n}\n")


@functools.lru_cache(maxsize=None)
def transfer_program(mode: str, rows: int, n_in: int) -> ShaderProgram:
    """Uncompressed transfer decoded in the vertex shader.

    Table ``transfer``: RGBA32F texture buffer ``[V · rows · N4]`` (N4 = ⌈n_in/4⌉ texels per
    row, zero-padded); uniform ``vec4 light[3·N4]`` (channel c's SH vector at ``[c·N4 ..]``).
    row_o = Σ_i T_p[o, i] l_{c,i} per channel c."""
    n4 = -(-n_in // 4)
    vattrs, vdecl, vbody = _view_glsl(mode, rows)
    body = f"""
uniform mat4 prt_mvp;
uniform samplerBuffer transfer;  // RGBA32F [V * ROWS * N4]
uniform vec4 light[{3 * n4}];       // [3 * N4]: r, g, b SH vectors, 4 coefficients a vec4
{vdecl}const int ROWS = {rows};
const int N_OUT = {rows};
const int N4 = {n4};
out vec3 v_radiance;
void prt_setup() {{}}
vec3 row(int o) {{  // (T_p l)_o per channel
    int base = (gl_VertexID * ROWS + o) * N4;
    vec3 s = vec3(0.0);
    for (int q = 0; q < N4; ++q) {{
        vec4 t = texelFetch(transfer, base + q);
        s += vec3(dot(t, light[q]), dot(t, light[N4 + q]), dot(t, light[2 * N4 + q]));
    }}
    return s;
}}
{vbody}{_main()}"""
    return ShaderProgram(name=f"prt_transfer_{mode}_{rows}x{n_in}", attributes=(Attribute("albedo", 3),) + vattrs,
                         vertex_body=body, fragment_body=_FRAGMENT)


@functools.lru_cache(maxsize=None)
def affine_program(mode: str, n_out: int, J: int, centred: bool, n_weights: int, weights_in: str) -> ShaderProgram:
    """Piecewise-affine codec (VQ / PCA / CPCA / MRT-PCA) decoded in the vertex shader.

    Table ``consts``: RGBA32F texture buffer ``[K · J · n_out]`` of M_k^j l (rgb), J = n+1 with
    the mean term (``centred``), n without; int attribute ``cluster``; the n PCA weights as
    ``vec4`` attributes ``w0..`` (``weights_in='attributes'``) or an R32F texture buffer
    ``weights [V · n]`` (``'buffer'``). row_o = Σ_j ŵ_j (M_k^j l)_o with ŵ = (1, w_p) or w_p."""
    if weights_in not in ("attributes", "buffer"):
        raise ValueError(f"weights_in={weights_in!r}; accepted: 'attributes' or 'buffer'")
    vattrs, vdecl, vbody = _view_glsl(mode, n_out)
    m4 = -(-n_weights // 4)
    wattrs: tuple[Attribute, ...] = ()
    if n_weights == 0:
        wdecl, wsetup, wfun = "", "", "float weight(int i) { return 0.0; }\n"
    elif weights_in == "attributes":
        wattrs = tuple(Attribute(f"w{i}", 4) for i in range(m4))
        wdecl = f"vec4 W[{m4}];\n"
        wsetup = f"    W = vec4[{m4}]({', '.join(f'w{i}' for i in range(m4))});\n"
        wfun = "float weight(int i) { return W[i >> 2][i & 3]; }\n"
    else:
        wdecl = "uniform samplerBuffer weights;  // R32F [V * N_W]\n"
        wsetup = ""
        wfun = "float weight(int i) { return texelFetch(weights, gl_VertexID * N_W + i).r; }\n"
    first = 1 if centred else 0
    body = f"""
uniform mat4 prt_mvp;
uniform samplerBuffer consts;  // RGBA32F [K * J * N_OUT]: rgb = M_k^j l (per light, CPU)
{vdecl}const int N_OUT = {n_out};
const int J = {J};
const int N_W = {max(n_weights, 1)};
const int FIRST = {first};        // 1: j = 0 is the mean term with weight 1
{wdecl}out vec3 v_radiance;
void prt_setup() {{
{wsetup}}}
{wfun}vec3 row(int o) {{  // Sloan 2003 eq. (4): (M_k^0 l)_o + sum_i w_p^i (M_k^i l)_o
    int base = cluster * J * N_OUT + o;
    vec3 s = vec3(0.0);
    if (FIRST == 1) s = texelFetch(consts, base).rgb;
    for (int j = FIRST; j < J; ++j) {{
        float w = weight(j - FIRST);
        if (w != 0.0) s += w * texelFetch(consts, base + j * N_OUT).rgb;
    }}
    return s;
}}
{vbody}{_main()}"""
    attrs = (Attribute("cluster", 1, "int"), Attribute("albedo", 3)) + wattrs + vattrs
    return ShaderProgram(name=f"prt_affine_{mode}_{n_out}_J{J}{'c' if centred else ''}_{weights_in}", attributes=attrs,
                         vertex_body=body, fragment_body=_FRAGMENT)


def _view_inputs(mode: str, view, V: int, n_out: int) -> tuple[dict, dict]:
    """(attributes, tables) of a view: dense weights ``[V, n_out]`` or taps (idx, w) ``[V, k≤4]``."""
    if mode in ("none", "diagonal"):
        if view is not None:
            raise ValueError(f"view mode {mode!r} takes no view; got {type(view).__name__}")
        return {}, {}
    if mode == "dense":
        y = _np("view weights", view, np.float32)
        if y.shape != (V, n_out):
            raise ValueError(f"dense view weights have shape {y.shape}; accepted: [V, n_out] = [{V}, {n_out}]")
        return {}, {"view_weights": TableData(_frozen(y.reshape(-1)), "buffer")}
    if not (isinstance(view, (tuple, list)) and len(view) == 2):
        raise TypeError("view mode 'taps' needs view = (idx int [V, k], w float [V, k]) with k ≤ 4")
    idx = _np("tap indices", view[0], np.int64)
    w = _np("tap weights", view[1], np.float32)
    if idx.ndim != 2 or idx.shape[0] != V or w.shape != idx.shape or idx.shape[1] > 4:
        raise ValueError(f"taps have shapes {idx.shape}, {w.shape}; accepted: [V, k] with V={V}, k ≤ 4")
    if idx.size and (idx.min() < 0 or idx.max() >= n_out):
        raise ValueError(f"tap indices span [{idx.min()}, {idx.max()}]; accepted: 0..{n_out - 1}")
    pad = 4 - idx.shape[1]
    idx4 = np.pad(idx, ((0, 0), (0, pad))).astype(np.int32)
    w4 = np.pad(w, ((0, 0), (0, pad))).astype(np.float32)
    return {"tap_idx": _frozen(idx4), "tap_w": _frozen(w4)}, {}


def _albedo(albedo, V: int) -> np.ndarray:
    if albedo is None:
        return _frozen(np.ones((V, 3), np.float32))
    a = _np("albedo", albedo, np.float32)
    a = a[:, None] if a.ndim == 1 else a
    if a.shape[0] != V or a.shape[1] not in (1, 3):
        raise ValueError(f"albedo has shape {a.shape}; accepted: [V, 3] or [V] with V={V}")
    return _frozen(np.broadcast_to(a, (V, 3)))


def _light3(light, n_in: int) -> np.ndarray:
    """``[n_in, C]`` (C = 1 or 3) -> ``[n_in, 3]`` float32 (grey replicated)."""
    L = _np("light", light, np.float32)
    L = L[:, None] if L.ndim == 1 else L
    if L.ndim != 2 or L.shape[0] != n_in or L.shape[1] not in (1, 3):
        raise ValueError(f"light has shape {L.shape}; accepted: [n_in, C] = [{n_in}, 1 or 3] (SH on rows)")
    return np.ascontiguousarray(np.broadcast_to(L, (n_in, 3)))


class TransferDecoder(Decoder):
    """Uncompressed PRT decoded in the vertex shader (light as uniforms, transfer as a float table).

    Args:
        transfer: ``[V, R, n_in]`` float (``[V, n_in]`` = one row): diffuse ``[V, n²]`` (R = 1,
            mode 'none'), diffuse RGB ``[V, 3, n²]`` ('diagonal'), glossy exit transfer
            ``[V, n_out, n²]`` ('dense'), MRT ``[V, M², n²]`` ('taps').
        light: ``[n_in, C]`` SH light (C = 1 or 3; coefficients on rows, as codecs take it).
        mode: one of :data:`VIEW_MODES`; view: None, dense ``[V, R]`` or taps (idx, w) ``[V, 4]``.
        albedo: ``[V, 3]`` multiplied into the result (diffuse transfer stored without albedo).
    Radiance at p: Σ_o y_o(v_p) Σ_i T_p[o, i] l_i (Sloan 2002 eq. (7); Sloan 2003 §3.1; MRT eq. 9).
    """

    def __init__(self, transfer, light, mode: str = "none", view=None, albedo=None):
        T = _np("transfer", transfer, np.float32)
        T = T[:, None, :] if T.ndim == 2 else T
        if T.ndim != 3:
            raise ValueError(f"transfer has shape {T.shape}; accepted: [V, n_in] or [V, R, n_in]")
        V, R, n_in = T.shape
        if mode not in VIEW_MODES:
            raise ValueError(f"mode={mode!r}; accepted: {', '.join(VIEW_MODES)}")
        if mode == "none" and R != 1 or mode == "diagonal" and R != 3:
            raise ValueError(f"mode {mode!r} needs {1 if mode == 'none' else 3} row(s) per vertex; transfer has {R}")
        n4 = -(-n_in // 4)
        Tp = np.zeros((V, R, n4 * 4), np.float32)
        Tp[:, :, :n_in] = T
        Tp = Tp.reshape(-1, 4)
        Tp.setflags(write=False)  # resident on the GPU: uploaded once
        self.program = transfer_program(mode, R, n_in)
        self.num_vertices, self.n_in = V, n_in
        self._attrs = {"albedo": _albedo(albedo, V)}
        va, vt = _view_inputs(mode, view, V, R)
        self._attrs.update(va)
        self._tables = {"transfer": TableData(Tp, "buffer"), **vt}
        self.set_light(light)

    def set_light(self, light) -> None:
        """A new light ``[n_in, C]``: only the uniform changes (per-light work: none on the CPU)."""
        L = _light3(light, self.n_in)
        n4 = -(-self.n_in // 4)
        Lp = np.zeros((3, n4 * 4), np.float32)
        Lp[:, :self.n_in] = L.T
        self._uniforms = {"light": Lp.reshape(3 * n4, 4)}

    def inputs(self, num_vertices: int) -> DrawInputs:
        if num_vertices != self.num_vertices:
            raise ValueError(f"decoder holds {self.num_vertices} vertices but the mesh has {num_vertices}")
        return DrawInputs(attributes=self._attrs, uniforms=self._uniforms, tables=self._tables)


class AffineDecoder(Decoder):
    """Piecewise-affine compressed transfer decoded in the vertex shader (Sloan 2003 §6.2).

    Args:
        labels: ``[V]`` int cluster of each vertex.
        weights: ``[V, n]`` float PCA weights (n may be 0: VQ).
        consts: ``[K, J, n_out, C]`` float per-cluster constants M_k^j l for the current light
            (``AffineCodec.cluster_constants``; C = 1 or 3), J = n+1 with a mean term, n without.
        centred: whether j = 0 is the mean term (weight 1).
        mode, view, albedo: as :class:`TransferDecoder`.
        weights_in: ``'auto'`` (attributes when ⌈n/4⌉ ≤ :data:`MAX_WEIGHT_ATTRIBUTES`, else a
            texture buffer), ``'attributes'`` or ``'buffer'``.
    Radiance at p: Σ_o y_o(v_p) [(M_k^0 l)_o + Σ_i w_p^i (M_k^i l)_o], k = labels[p]
    (Sloan 2003 eq. (4); with MRT taps, Lehtinen & Kautz 2003 eq. 13).
    """

    def __init__(self, labels, weights, consts, centred: bool = True, mode: str = "none", view=None, albedo=None,
                 weights_in: str = "auto"):
        lab = _np("labels", labels, np.int64)
        W = _np("weights", weights, np.float32)
        c = _np("consts", consts, np.float32)
        if lab.ndim != 1:
            raise ValueError(f"labels have shape {lab.shape}; accepted: [V]")
        V = lab.shape[0]
        W = W.reshape(V, -1)
        if c.ndim != 4 or c.shape[3] not in (1, 3):
            raise ValueError(f"the per-cluster light constants (consts, M_k^j l) have shape {c.shape}; accepted: [K, J, n_out, C] with C = 1 or 3")
        K, J, n_out, C = c.shape
        n = W.shape[1]
        if J != n + (1 if centred else 0):
            raise ValueError(f"the per-cluster light constants (consts) have J={J} terms per cluster but the PCA weights have n={n} columns "
                             f"({'centred: J = n+1' if centred else 'uncentred: J = n'})")
        if V and (lab.min() < 0 or lab.max() >= K):
            raise ValueError(f"cluster labels span [{lab.min()}, {lab.max()}]; accepted: 0..{K - 1} (clusters)")
        if mode not in VIEW_MODES:
            raise ValueError(f"mode={mode!r}; accepted: {', '.join(VIEW_MODES)}")
        if mode == "none" and n_out != 1 or mode == "diagonal" and n_out != 3:
            raise ValueError(f"view mode {mode!r} needs n_out = {1 if mode == 'none' else 3} outputs; "
                             f"the per-cluster light constants (consts) have {n_out}")
        m4 = -(-n // 4)
        if weights_in == "auto":
            weights_in = "attributes" if m4 <= MAX_WEIGHT_ATTRIBUTES else "buffer"
        self.program = affine_program(mode, n_out, J, bool(centred), n, weights_in)
        self.num_vertices = V
        self.consts_shape = (K, J, n_out)
        self._codec = None
        self._attrs = {"cluster": _frozen(lab.astype(np.int32)), "albedo": _albedo(albedo, V)}
        self._tables = {}
        if n and weights_in == "attributes":
            Wp = np.zeros((V, m4 * 4), np.float32)
            Wp[:, :n] = W
            self._attrs.update({f"w{i}": _frozen(Wp[:, 4 * i:4 * i + 4]) for i in range(m4)})
        elif n:
            self._tables["weights"] = TableData(_frozen(W.reshape(-1)), "buffer")
        va, vt = _view_inputs(mode, view, V, n_out)
        self._attrs.update(va)
        self._tables.update(vt)
        self.set_consts(c)

    def set_consts(self, consts) -> None:
        """New per-cluster constants ``[K, J, n_out, C]`` (a new light): the only per-light data
        (uploaded on the next draw; the per-vertex data stays resident)."""
        c = _np("consts", consts, np.float32)
        if c.ndim != 4 or c.shape[:3] != self.consts_shape or c.shape[3] not in (1, 3):
            raise ValueError(f"the per-cluster light constants (consts) have shape {c.shape}; accepted: "
                             f"[{', '.join(map(str, self.consts_shape))}, 1 or 3] (clusters, terms, outputs, colour channels)")
        rows = int(np.prod(self.consts_shape))
        tab = np.ones((rows, 4), np.float32)
        tab[:, :3] = np.broadcast_to(c.reshape(rows, -1), (rows, 3))
        self._tables["consts"] = TableData(tab, "buffer")

    def set_light(self, light) -> None:
        """A new light ``[n_in, C]`` for a decoder made by :meth:`from_codec`: the per-cluster
        constants ``codec.cluster_constants(light)`` (K·J·n_out dot products on the CPU)."""
        if self._codec is None:
            raise ValueError("set_light needs a decoder made by from_codec; use set_consts")
        self.set_consts(self._codec.cluster_constants(light))

    @classmethod
    def from_codec(cls, codec, enc, light, mode: str = "none", view=None, albedo=None, **kw) -> "AffineDecoder":
        """From a fitted piecewise-affine codec (``prt_torch.codecs.affine.AffineCodec``) and its
        encoding: labels and weights from the codes (``labels_of``, ``coeffs_of``), constants
        ``codec.cluster_constants(light [n_in, C])`` — K·J·n_out dot products, per light."""
        consts = codec.cluster_constants(light)
        dec = cls(codec.labels_of(enc), codec.coeffs_of(enc), consts, centred=codec.means_ is not None, mode=mode,
                  view=view, albedo=albedo, **kw)
        dec._codec = codec
        return dec

    def inputs(self, num_vertices: int) -> DrawInputs:
        if num_vertices != self.num_vertices:
            raise ValueError(f"decoder holds {self.num_vertices} vertices but the mesh has {num_vertices}")
        return DrawInputs(attributes=self._attrs, tables=self._tables)


class VQDecoder(AffineDecoder):
    """VQ (Sloan 2003 eq. (2)): n = 0, every vertex shows its cluster's M_k·l."""


class PCADecoder(AffineDecoder):
    """PCA (one cluster, Sloan 2003 §3.3): x̃_p = x_0 + Σ_i w_p^i x_i, relit as Σ_i w_p^i (x_i·l)."""


class CPCADecoder(AffineDecoder):
    """CPCA (Sloan 2003 §6.2 eq. (4)): per-cluster constants M_k^i·l indexed by cluster id,
    N' weights per vertex (static, iterative and adaptive fits alike; packed weights padded)."""


class MRTPCADecoder(AffineDecoder):
    """MRT-PCA (Lehtinen & Kautz 2003 eq. 13): Σ_{j∈4 taps} g_j(v_p) Σ_k w_p^k (A_k l)_j, the
    uncentred basis A_k relit per light on the CPU."""


class NeuralDecoder(AffineDecoder):
    """The learned codec (``codecs.neural``, issue 43): x̃_p = b_k + W_k h(z_p) with a linear last
    layer, so after caching the features h(z_p) ``[V, H]`` once (``NeuralCodec.affine_form``) it
    is CPCA with H vectors — the features as vertex attributes (or a texture buffer), the
    per-cluster constants b_k^T l and W_k^T l as the per-light uniform table (Sloan 2003 §6.2
    eq. (4)). The decoder MLP never runs in the shader."""

    @classmethod
    def from_codec(cls, codec, enc, light, mode: str = "none", view=None, albedo=None, **kw) -> "NeuralDecoder":
        inner, aenc = codec.affine_form(enc)
        return super().from_codec(inner, aenc, light, mode=mode, view=view, albedo=albedo, **kw)


_CODEC_DECODERS: dict[str, type] = {}


def register_codec_decoder(*names: str) -> Callable[[type], type]:
    """Class decorator: use this :class:`Decoder` subclass (with a ``from_codec(codec, enc,
    light, mode, view, albedo)`` classmethod) for the codecs registered under ``names``."""
    def deco(cls: type) -> type:
        if not (isinstance(cls, type) and issubclass(cls, Decoder) and hasattr(cls, "from_codec")):
            raise TypeError(f"{cls!r} is not a Decoder subclass with a from_codec classmethod")
        for n in names:
            _CODEC_DECODERS[n] = cls
        return cls
    return deco


register_codec_decoder("vq")(VQDecoder)
register_codec_decoder("pca")(PCADecoder)
register_codec_decoder("cpca", "cpca_static", "cpca_iterative", "cpca_adaptive")(CPCADecoder)
register_codec_decoder("mrt_pca")(MRTPCADecoder)
register_codec_decoder("neural")(NeuralDecoder)


def codec_decoders() -> dict[str, type]:
    """codec name -> decoder class (a copy)."""
    return dict(_CODEC_DECODERS)


def codec_decoder(codec, enc, light, mode: str = "none", view=None, albedo=None, **kw) -> Decoder:
    """The GLSL decoder of ``codec`` (by ``codec.codec_name``) for ``enc`` under ``light [n_in, C]``."""
    name = getattr(codec, "codec_name", None)
    cls = _CODEC_DECODERS.get(name)
    if cls is None:
        raise ValueError(f"codec {name!r} has no GLSL decoder; accepted: {', '.join(sorted(_CODEC_DECODERS))} "
                         "(register one with prt_torch.render.register_codec_decoder), or decode on the CPU")
    return cls.from_codec(codec, enc, light, mode=mode, view=view, albedo=albedo, **kw)


# ----------------------------------------------------------------------------- Green 2005 Gaussians

#: lobes at most passed as vertex attributes (one ``vec4 (μ, σ)`` each plus ``vec4`` weights);
#: more go through an RGBA32F texture buffer.
MAX_LOBE_ATTRIBUTES = 4

_CUBE_LOOKUP_GLSL = """
// PrefilteredEnvironment.lookup (prt_torch.lighting.prefilter), step for step: OpenGL face
// selection and texel coordinates (cube_map_lookup_coords), bilinear inside the face clamped at
// its edges, linear in log sigma between the two ladder levels bracketing sigma (clamped).
int cube_face(vec3 d, out vec2 st) {  // face 0..5 (+x, -x, +y, -y, +z, -z); st = (column s, row t)
    float ax = abs(d.x), ay = abs(d.y), az = abs(d.z);
    bool is_x = ax >= ay && ax >= az;
    bool is_y = !is_x && ay >= az;
    float m = max(is_x ? ax : (is_y ? ay : az), 1e-30);
    int face = is_x ? (d.x < 0.0 ? 1 : 0) : (is_y ? (d.y < 0.0 ? 3 : 2) : (d.z < 0.0 ? 5 : 4));
    float sc = is_x ? (d.x >= 0.0 ? -d.z : d.z) : (is_y ? d.x : (d.z >= 0.0 ? d.x : -d.x));
    float tc = is_x ? -d.y : (is_y ? (d.y >= 0.0 ? d.z : -d.z) : -d.y);
    sc /= m;
    tc /= m;
    st = vec2((sc + 1.0) * (float(RES) / 2.0) - 0.5, (tc + 1.0) * (float(RES) / 2.0) - 0.5);
    return face;
}
vec3 texel(int li, int face, int t, int s) {
    return texelFetch(levels, ((li * 6 + face) * RES + t) * RES + s).rgb;
}
vec3 prefiltered(vec3 mu, float sigma) {  // E_sigma(mu), Green eq. 2.7
    vec2 st;
    int face = cube_face(mu, st);
    float s = clamp(st.x, 0.0, float(RES - 1));
    float t = clamp(st.y, 0.0, float(RES - 1));
    int s0 = min(int(floor(s)), max(RES - 2, 0));
    int t0 = min(int(floor(t)), max(RES - 2, 0));
    float fs = clamp(s - float(s0), 0.0, 1.0);
    float ft = clamp(t - float(t0), 0.0, 1.0);
    int s1 = min(s0 + 1, RES - 1);
    int t1 = min(t0 + 1, RES - 1);
    float ls = log(max(sigma, 1e-12));
    int hi = 0;  // searchsorted(ladder, ls), clamped to 1..L-1
    while (hi < NL && ladder[hi] < ls) ++hi;
    hi = clamp(hi, 1, max(NL - 1, 1));
    int lo = max(hi - 1, 0);
    float a = 0.0;
    if (NL > 1) a = clamp((ls - ladder[lo]) / (ladder[hi] - ladder[lo]), 0.0, 1.0);
    else { hi = 0; lo = 0; }
    vec3 blo = (1.0 - ft) * ((1.0 - fs) * texel(lo, face, t0, s0) + fs * texel(lo, face, t0, s1))
             + ft * ((1.0 - fs) * texel(lo, face, t1, s0) + fs * texel(lo, face, t1, s1));
    vec3 bhi = (1.0 - ft) * ((1.0 - fs) * texel(hi, face, t0, s0) + fs * texel(hi, face, t0, s1))
             + ft * ((1.0 - fs) * texel(hi, face, t1, s0) + fs * texel(hi, face, t1, s1));
    return (1.0 - a) * blo + a * bhi;
}
"""


@functools.lru_cache(maxsize=None)
def gaussian_program(lobes: int, n_levels: int, res: int, lobes_in: str) -> ShaderProgram:
    """Green 2005's Gaussian transport decoded in the vertex shader (eq. 2.7).

    Per vertex, the N lobes already interpolated across the three nearest stored views (§2.3,
    on the CPU once per camera): weight w_k (the taps' sum folded in), unit mean μ_k and width
    σ_k — as attributes ``vec4 lobe{k} = (μ, σ)`` and ``vec4 lobe_w{q}`` (``lobes_in='attributes'``)
    or an RGBA32F texture buffer ``lobes [V · N · 2]`` = ((μ, σ), (w, 0, 0, 0)) (``'buffer'``);
    ``vec3 diffuse``: the SH diffuse part's t·l times the taps' data weight (zero without one).
    Table ``levels``: RGBA32F texture buffer ``[L · 6 · r · r]`` (level, face, row t, column s) of
    the prefiltered environment; ``uniform float ladder[L]``: log σ_l.
    radiance = albedo · (diffuse + Σ_k w_k E_{σ_k}(μ_k))."""
    if lobes_in not in ("attributes", "buffer"):
        raise ValueError(f"lobes_in={lobes_in!r}; accepted: 'attributes' or 'buffer'")
    q4 = -(-lobes // 4)
    if lobes_in == "attributes":
        attrs = tuple(Attribute(f"lobe{k}", 4) for k in range(lobes)) + tuple(Attribute(f"lobe_w{q}", 4)
                                                                               for q in range(q4))
        decl = ""
        lobe_fn = ("vec4 lobe(int k) {\n    " + " ".join(f"if (k == {k}) return lobe{k};" for k in range(lobes))
                   + "\n    return vec4(0.0, 0.0, 1.0, 1.0);\n}\n"
                   + "float lobe_weight(int k) {\n    " + " ".join(f"if ((k >> 2) == {q}) return lobe_w{q}[k & 3];"
                                                                  for q in range(q4))
                   + "\n    return 0.0;\n}\n")
    else:
        attrs = ()
        decl = "uniform samplerBuffer lobes;  // RGBA32F [V * N * 2]: (mu, sigma), (w, 0, 0, 0)\n"
        lobe_fn = ("vec4 lobe(int k) { return texelFetch(lobes, (gl_VertexID * N + k) * 2); }\n"
                   "float lobe_weight(int k) { return texelFetch(lobes, (gl_VertexID * N + k) * 2 + 1).r; }\n")
    body = f"""
uniform mat4 prt_mvp;
uniform samplerBuffer levels;  // RGBA32F [L * 6 * RES * RES]: prefiltered cube levels (rgb)
uniform float ladder[{n_levels}];     // log sigma_l, increasing
{decl}const int N = {lobes};
const int NL = {n_levels};
const int RES = {res};
out vec3 v_radiance;
{_CUBE_LOOKUP_GLSL}{lobe_fn}void main() {{
    vec3 s = diffuse;
    for (int k = 0; k < N; ++k) {{
        float w = lobe_weight(k);
        if (w != 0.0) {{
            vec4 l = lobe(k);
            s += w * prefiltered(l.xyz, l.w);
        }}
    }}
    v_radiance = s * albedo;
    gl_Position = prt_mvp * vec4(position, 1.0);
}}
"""
    return ShaderProgram(name=f"prt_gaussian_N{lobes}_L{n_levels}_r{res}_{lobes_in}",
                         attributes=(Attribute("albedo", 3), Attribute("diffuse", 3)) + attrs,
                         vertex_body=body, fragment_body=_FRAGMENT)


def gaussian_view_lobes(codec, enc, light, view) -> tuple:
    """What ``GaussianCodec.relight(enc, light, view)`` computes per camera before its lookups:
    per vertex the lobes blended across the tapped stored views (Green §2.3, ``blend_lobes``)
    with the taps' sum folded into the weights, and the SH diffuse part (Green §3.1) times the
    taps' data weight. ``view``: taps ``(idx [V, k], w [V, k])`` or global directions ``[V, 3]``.
    Returns ``(w [V, N], mu [V, N, 3], sigma [V, N], diffuse [V, C])`` float32 tensors."""
    import torch

    from ..codecs.gaussian import blend_lobes
    from ..lighting.prefilter import PrefilteredEnvironment

    if not isinstance(light, PrefilteredEnvironment):
        raise TypeError(f"light is {type(light).__name__}; accepted: a PrefilteredEnvironment "
                        "(prt_torch.lighting.prefilter_environment; the gaussian codec's light kind 'prefiltered')")
    w, mu, sg = codec.lobes_of(enc)
    V, J, N = w.shape
    if view is None:
        raise ValueError("the gaussian decoder needs a view: taps (idx [V, k], w [V, k]) or directions [V, 3] "
                         "(one radiance per vertex and camera)")
    idx, a = codec.checked_taps(view, V, J)
    rows = torch.arange(V)[:, None]
    a = a.float()
    tot = a.sum(1, keepdim=True)
    wb, mb, sgb = blend_lobes(w[rows, idx], mu[rows, idx], sg[rows, idx], a / tot.clamp_min(1e-12))
    C = int(light.channels)
    diff = torch.zeros(V, C)
    if "diffuse" in enc.tensors:
        t = enc.tensors["diffuse"]
        if light.sh is None:
            raise ValueError(f"this encoding has an SH diffuse part of {t.shape[1]} coefficients; accepted: a "
                             "PrefilteredEnvironment with SH coefficients (an SH light, or prefilter_environment(..., "
                             "sh_bands=))")
        L = torch.zeros(C, t.shape[1])
        k = min(t.shape[1], light.sh.shape[1])
        L[:, :k] = light.sh[:, :k].float()
        hd = enc.tensors["has_data"].float()[rows, idx]
        diff = (t @ L.T) * (a * hd).sum(1, keepdim=True)
    return (wb * tot).float(), mb.float(), sgb.float(), diff.float()


def _rgb(x: np.ndarray) -> np.ndarray:
    """``[..., C]`` (C = 1 or 3) -> ``[..., 3]`` (grey replicated)."""
    if x.shape[-1] not in (1, 3):
        raise ValueError(f"{x.shape[-1]} light channels; accepted: 1 or 3")
    return np.broadcast_to(x, x.shape[:-1] + (3,))


class GaussianDecoder(Decoder):
    """Green 2005's Gaussian-mixture transport decoded in the vertex shader (eq. 2.7, §2.3).

    Args:
        weights ``[V, N]``, mu ``[V, N, 3]`` (unit), sigma ``[V, N]``: each vertex's lobes for the
            current camera (interpolated across its three nearest stored views,
            :func:`gaussian_view_lobes`).
        light: the :class:`~prt_torch.lighting.PrefilteredEnvironment` (C = 1 or 3 channels).
        diffuse: ``[V, C]`` added radiance (the SH diffuse part), or None.
        albedo: ``[V, 3]`` multiplied into the result, or None.
        lobes_in: ``'auto'`` (attributes for N ≤ :data:`MAX_LOBE_ATTRIBUTES`, else a texture
            buffer), ``'attributes'`` or ``'buffer'``.
    Radiance at p: albedo · (diffuse_p + Σ_k w_pk E_{σ_pk}(μ_pk)), the lookup E done in GLSL
    exactly as ``PrefilteredEnvironment.lookup`` (same face, texels, bilinear and level weights)
    from the levels uploaded unquantised as one RGBA32F texture buffer.
    """

    def __init__(self, weights, mu, sigma, light, diffuse=None, albedo=None, lobes_in: str = "auto"):
        w = _np("lobe weights", weights, np.float32)
        if w.ndim != 2:
            raise ValueError(f"lobe weights have shape {w.shape}; accepted: [V, N]")
        V, N = w.shape
        if N < 1:
            raise ValueError("no lobes; accepted: N ≥ 1 lobes per vertex")
        if lobes_in == "auto":
            lobes_in = "attributes" if N <= MAX_LOBE_ATTRIBUTES else "buffer"
        if lobes_in not in ("attributes", "buffer"):
            raise ValueError(f"lobes_in={lobes_in!r}; accepted: 'auto', 'attributes' or 'buffer'")
        self.num_vertices, self.lobes, self.lobes_in = V, N, lobes_in
        self._attrs = {"albedo": _albedo(albedo, V)}
        self._tables: dict = {}
        self._light = None
        self.set_light(light)
        self.set_lobes(w, mu, sigma, diffuse)

    def set_light(self, light) -> None:
        """A new prefiltered environment: the levels table and the ladder (per light)."""
        from ..lighting.prefilter import PrefilteredEnvironment

        if not isinstance(light, PrefilteredEnvironment):
            raise TypeError(f"light is {type(light).__name__}; accepted: a PrefilteredEnvironment "
                            "(prt_torch.lighting.prefilter_environment)")
        lv = _np("prefiltered levels", light.levels, np.float32)  # [L, C, 6, r, r]
        L, r = lv.shape[0], lv.shape[-1]
        tab = np.ones((L, 6, r, r, 4), np.float32)
        tab[..., :3] = _rgb(np.moveaxis(lv, 1, -1))
        self._tables["levels"] = TableData(_frozen(tab.reshape(-1, 4)), "buffer")
        import torch

        ladder = _np("log sigma ladder", torch.as_tensor(light.sigmas).log().to(torch.float32), np.float32)
        self._uniforms = {"ladder": ladder}
        self.program = gaussian_program(self.lobes, L, r, self.lobes_in)
        self._light = light

    def set_lobes(self, weights, mu, sigma, diffuse=None) -> None:
        """New per-vertex lobes (a new camera): ``[V, N]``, ``[V, N, 3]``, ``[V, N]``, diffuse ``[V, C]``."""
        V, N = self.num_vertices, self.lobes
        w = _np("lobe weights", weights, np.float32)
        m = _np("lobe means", mu, np.float32)
        s = _np("lobe widths", sigma, np.float32)
        if w.shape != (V, N) or m.shape != (V, N, 3) or s.shape != (V, N):
            raise ValueError(f"lobes have shapes {w.shape}, {m.shape}, {s.shape}; accepted: [V, N], [V, N, 3], [V, N] "
                             f"with V={V}, N={N}")
        if diffuse is None:
            d = np.zeros((V, 3), np.float32)
        else:
            d = _np("diffuse", diffuse, np.float32)
            d = d[:, None] if d.ndim == 1 else d
            if d.ndim != 2 or d.shape[0] != V:
                raise ValueError(f"diffuse has shape {d.shape}; accepted: [V, C] with V={V}, C = 1 or 3")
            d = np.ascontiguousarray(_rgb(d))
        self._attrs["diffuse"] = d
        ms = np.concatenate([m, s[..., None]], -1)  # [V, N, 4]
        for k in [k for k in self._attrs if k.startswith("lobe")]:
            del self._attrs[k]
        self._tables.pop("lobes", None)
        if self.lobes_in == "attributes":
            q4 = -(-N // 4)
            wp = np.zeros((V, 4 * q4), np.float32)
            wp[:, :N] = w
            self._attrs.update({f"lobe{k}": np.ascontiguousarray(ms[:, k]) for k in range(N)})
            self._attrs.update({f"lobe_w{q}": np.ascontiguousarray(wp[:, 4 * q:4 * q + 4]) for q in range(q4)})
        else:
            tab = np.zeros((V, N, 2, 4), np.float32)
            tab[:, :, 0] = ms
            tab[:, :, 1, 0] = w
            self._tables["lobes"] = TableData(tab.reshape(-1, 4), "buffer")

    def set_view(self, view) -> None:
        """A new camera for a decoder made by :meth:`from_codec`: the lobes re-interpolated."""
        if getattr(self, "_codec", None) is None:
            raise ValueError("set_view needs a decoder made by from_codec; use set_lobes")
        self.set_lobes(*gaussian_view_lobes(self._codec, self._enc, self._light, view))

    @classmethod
    def from_codec(cls, codec, enc, light, mode: str = "taps", view=None, albedo=None, **kw) -> "GaussianDecoder":
        """From a fitted ``gaussian`` codec, its encoding, a :class:`PrefilteredEnvironment` and
        the camera's view (taps over the stored views, or global directions ``[V, 3]``; as
        ``GaussianCodec.relight``). ``mode`` is accepted for the registry's signature and not used
        (the view is always the codec's own)."""
        w, mu, sigma, diffuse = gaussian_view_lobes(codec, enc, light, view)
        dec = cls(w, mu, sigma, light, diffuse=diffuse, albedo=albedo, **kw)
        dec._codec, dec._enc = codec, enc
        return dec

    def inputs(self, num_vertices: int) -> DrawInputs:
        if num_vertices != self.num_vertices:
            raise ValueError(f"decoder holds {self.num_vertices} vertices but the mesh has {num_vertices}")
        return DrawInputs(attributes=self._attrs, uniforms=self._uniforms, tables=self._tables)


register_codec_decoder("gaussian")(GaussianDecoder)
