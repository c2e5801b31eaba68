"""A transfer (and optionally a codec) ready to be decoded on the CPU or in GLSL, and the
GLSL-vs-CPU validation.

:class:`PRTScene` wraps a :class:`~prt_torch.transfer.Transfer` of any kind the engine relights
(diffuse grey ``[V, n²]``, diffuse RGB ``[V, 3, n²]``, glossy exit transfer ``[V, n_out, n²]``,
MRT ``[V, M², n²]``) and gives, for a light and a camera eye:

* :meth:`PRTScene.view` — per-vertex view weights: None, y(v_p) ``[V, n_out]``
  (``relight.glossy_view_weights``) or four tent taps (``relight.mrt_view_taps``), the local
  view v_p from ``relight.local_view`` with the mesh frames (zero below the horizon);
* :meth:`PRTScene.cpu_radiance` — the torch engine's per-vertex radiance ``[V, 3]``: ``relight``
  for uncompressed transfer, ``codec.relight`` for a codec (which equals decode-then-relight);
* :meth:`PRTScene.decoder` — the GLSL decoder computing the same in the vertex shader
  (:mod:`.glsl`).

:func:`glsl_vs_cpu` renders both with one camera and reports the PSNR of the GLSL image
against the CPU image over the covered pixels (both masks must be identical).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .. import relight
from .glsl import TransferDecoder, codec_decoder

__all__ = ["PRTScene", "psnr", "glsl_vs_cpu", "GLSLCheck", "check_codec_file", "frame_rate", "RELIGHT_KINDS"]

RELIGHT_KINDS = ("diffuse", "glossy", "mrt")


def psnr(img: np.ndarray, ref: np.ndarray, mask: np.ndarray, peak: float | None = None) -> float:
    """PSNR in dB of ``img`` against ``ref`` (``[H, W, C]``) over ``mask [H, W]``:
    10 log10(peak² / MSE) with peak = max |ref| over the mask (default); ∞ when equal."""
    m = np.asarray(mask, bool)
    a, b = np.asarray(img, np.float64)[m], np.asarray(ref, np.float64)[m]
    if not a.size:
        raise ValueError("psnr over an empty mask")
    mse = float(np.mean((a - b) ** 2))
    peak = float(np.abs(b).max()) if peak is None else float(peak)
    if mse == 0.0:
        return math.inf
    return 10.0 * math.log10(max(peak, 1e-300) ** 2 / mse)


class PRTScene:
    """A transfer prepared for relighting on the CPU and in GLSL.

    Args:
        transfer: a ``Transfer`` of kind diffuse, glossy or mrt.
    Attributes:
        kind, V, mode (GLSL view mode), rows ``[V, R, n_in]`` float32 view of the data,
        n_out, n_in, albedo ``[V, 3]`` float32 (ones unless diffuse grey transfer stored
        without it), frames ``[V, 3, 3]`` float64, points ``[V, 3]`` float64.
    """

    def __init__(self, transfer):
        if transfer.kind not in RELIGHT_KINDS:
            raise ValueError(f"transfer kind {transfer.kind!r}; accepted: {', '.join(RELIGHT_KINDS)}")
        self.transfer = transfer
        self.kind = transfer.kind
        self.mesh = transfer.mesh
        data = transfer.data
        self.V = int(data.shape[0])
        self.albedo = torch.ones(self.V, 3, dtype=torch.float32)
        if self.kind == "diffuse":
            if data.ndim == 2:
                self.mode, self.matrix_shape = "none", None
                self.rows = data.to(torch.float32)[:, None, :]
                folded = transfer.meta.get("albedo_folded", False)
                if not folded:
                    self.albedo = torch.as_tensor(self.mesh.albedo).to(torch.float32).expand(self.V, 3).contiguous()
            elif data.ndim == 3 and data.shape[1] == 3:
                self.mode, self.matrix_shape = "diagonal", (3, int(data.shape[2]))
                self.rows = data.to(torch.float32)
            else:
                raise ValueError(f"diffuse transfer of shape {tuple(data.shape)}; accepted: [V, n²] or [V, 3, n²]")
        else:
            ms = transfer.meta.get("matrix_shape", list(data.shape[1:3]))
            self.matrix_shape = (int(ms[0]), int(ms[1]))
            self.rows = data.reshape(self.V, *self.matrix_shape).to(torch.float32)
            self.mode = "dense" if self.kind == "glossy" else "taps"
        self.n_out = int(self.rows.shape[1])
        self.n_in = int(self.rows.shape[2])
        self.D = self.n_out * self.n_in
        self.frames = self.mesh.frames().to(torch.float64)
        self.points = torch.as_tensor(self.mesh.vertices).to(torch.float64)

    @property
    def needs_view(self) -> bool:
        return self.kind in ("glossy", "mrt")

    def light_matrix(self, light: torch.Tensor) -> torch.Tensor:
        """SH light ``[C, n²]`` (any bands, C = 1 or 3) -> ``[n_in, 3]`` float32, truncated or
        zero-padded, grey replicated to RGB (the layout codecs take)."""
        light = torch.as_tensor(light)
        light = light[None] if light.ndim == 1 else light
        if light.ndim != 2 or light.shape[0] not in (1, 3):
            raise ValueError(f"light has shape {tuple(light.shape)}; accepted: [C, n²] with C = 1 or 3")
        L = torch.zeros(self.n_in, light.shape[0], dtype=torch.float32)
        k = min(self.n_in, light.shape[1])
        L[:k] = light[:, :k].T.to(torch.float32)
        return L.expand(self.n_in, 3).contiguous()

    def view(self, eye, rows: slice | None = None) -> Any:
        """Per-vertex view weights for a camera at ``eye [3]`` (world): None (diffuse), dense
        y(v_p) ``[V, n_out]`` float32 (glossy, Sloan 2003 §3.1) or taps (idx ``[V, 4]`` int64,
        g ``[V, 4]`` float32) (MRT eq. 13); zero below each vertex's horizon. ``rows``: only
        those vertices (a slice; the leading dimension is then its length)."""
        if not self.needs_view:
            return None
        sl = slice(None) if rows is None else rows
        v = relight.local_view(self.frames[sl], self.points[sl], eye=torch.as_tensor(np.asarray(eye, np.float64)))
        if self.kind == "glossy":
            return relight.glossy_view_weights(v, self.transfer.meta.get("out_index"), self.n_out)
        return relight.mrt_view_taps(v, math.isqrt(self.n_out))

    def check_codec(self, codec, enc, source: str = "codec", meta: dict | None = None) -> None:
        """Refuse a codec/encoding that does not belong to this transfer: mesh hash (when the
        file records one), number of points, signal dimension and matrix shape
        (``codecs.check_codec_matches``, the check ``prt validate`` runs too)."""
        from ..codecs.base import check_codec_matches

        check_codec_matches(source, codec, enc, meta, mesh_hash=self.mesh.content_hash(), points=self.V, dim=self.D,
                            matrix_shape=self.matrix_shape, n_in=self.n_in, kind=self.kind)

    def cpu_radiance(self, light: torch.Tensor, view: Any = None, codec=None, enc=None,
                     rows: slice | None = None) -> torch.Tensor:
        """The torch engine's exit radiance ``[V, 3]`` float32 under ``light [C, n²]``.

        Uncompressed: ``relight.diffuse`` / ``relight.apply_dense`` / ``relight.apply_taps``
        (the project's reference); with ``codec``: ``codec.relight(enc, light [n_in, 3], view)``
        (Sloan 2003 §6 / MRT eq. 13 from the compressed form). Albedo applied for diffuse grey
        transfer stored without it; the diagonal taken for RGB diffuse transfer. ``rows``
        (uncompressed only): those vertices only, ``view`` being theirs (``view(eye, rows)``) —
        what ``prt relight`` streams a transfer larger than memory by (only those rows are read)."""
        Lm = self.light_matrix(light)  # [n_in, 3]
        if codec is None:
            sl = slice(None) if rows is None else rows
            if self.mode == "none":
                out = relight.diffuse(self.rows[sl, 0], Lm.T)
            elif self.mode == "diagonal":
                out = relight.diffuse(self.rows[sl], Lm.T)
            elif self.mode == "dense":
                out = relight.apply_dense(self.rows[sl], Lm.T, view)
            else:
                out = relight.apply_taps(self.rows[sl], Lm.T, *view)
            return (out.to(torch.float32) * self.albedo[sl]).contiguous()
        if rows is not None:
            raise ValueError("cpu_radiance(rows=...) applies to uncompressed transfer; a codec relights every point at once")
        out = codec.relight(enc, Lm, view=view if self.needs_view else None)
        if self.mode == "diagonal":
            out = torch.diagonal(out, dim1=1, dim2=2)
        elif out.ndim == 3:
            out = out[:, 0]
        return (out.to(torch.float32) * self.albedo).contiguous()

    def decoder(self, light: torch.Tensor, view: Any = None, codec=None, enc=None, **kw):
        """The GLSL decoder computing :meth:`cpu_radiance` in the vertex shader: a
        :class:`~.glsl.TransferDecoder` (light as uniforms, transfer as a float table) or the
        codec's decoder by name (:func:`~.glsl.codec_decoder`; per-cluster constants per light)."""
        Lm = self.light_matrix(light)
        v = view if self.needs_view else None
        if codec is None:
            return TransferDecoder(self.rows, Lm, self.mode, v, self.albedo)
        return codec_decoder(codec, enc, Lm, mode=self.mode, view=v, albedo=self.albedo, **kw)


def check_codec_file(path: str | Path, scene: PRTScene):
    """Load ``(codec, enc)`` from a codec file and refuse it (ValueError) when it does not belong
    to ``scene``'s transfer (mesh hash, point count, dimension, matrix shape)."""
    from .. import codecs, io

    meta = io.load_meta(path)
    codec, enc = codecs.load(path)
    scene.check_codec(codec, enc, source=f"codec file {str(path)!r}", meta=meta)
    return codec, enc


@dataclass
class GLSLCheck:
    """One GLSL-vs-CPU comparison: images ``[H, W, 3]`` float32, the common mask, the PSNR of
    GLSL against CPU (dB) and whether the masks were identical."""

    glsl: np.ndarray
    cpu: np.ndarray
    mask: np.ndarray
    psnr_db: float
    same_mask: bool
    max_abs: float


def glsl_vs_cpu(renderer, scene: PRTScene, light: torch.Tensor, camera, codec=None, enc=None, width=None,
                height=None, **kw) -> GLSLCheck:
    """Render ``scene`` (and ``codec``/``enc`` if given) under ``light [C, n²]`` from ``camera``
    twice — decoded in GLSL and decoded by the torch engine (per-vertex radiance drawn by the
    same rasteriser) — and compare over the covered pixels."""
    view = scene.view(camera.eye) if scene.needs_view else None
    cpu = scene.cpu_radiance(light, view, codec, enc)
    img_c, m_c = renderer.render_radiance(scene.mesh, cpu, camera, width, height)
    img_g, m_g = renderer.render(scene.mesh, scene.decoder(light, view, codec, enc, **kw), camera, width, height)
    same = bool(np.array_equal(m_c, m_g))
    m = m_c & m_g
    d = float(np.abs(img_g[m].astype(np.float64) - img_c[m]).max()) if m.any() else 0.0
    return GLSLCheck(img_g, img_c, m, psnr(img_g, img_c, m) if m.any() else math.nan, same, d)


def frame_rate(fn, min_time: float = 0.5, max_frames: int = 50) -> float:
    """Frames per second of ``fn()`` (median of per-call times after one warm-up call)."""
    fn()
    ts = []
    t_end = time.perf_counter() + min_time
    while len(ts) < max_frames and (len(ts) < 3 or time.perf_counter() < t_end):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1.0 / float(np.median(ts))
