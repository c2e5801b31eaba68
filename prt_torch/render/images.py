"""Images for reports: exposure and tone mapping, error maps and heat maps, PNG/EXR writers, a
labelled side-by-side composite. No OpenGL here.

Rule: a float image is LINEAR (radiance, or linear RGB); a uint8 image is DISPLAY-encoded
(sRGB). Writers encode floats to sRGB for PNG (via ``prt_torch.lighting.write_image``) and keep
them as float32 in EXR. Heat maps are returned as linear float RGB in [0, 1] (the colormap's
sRGB colours decoded), so that ``save_png`` reproduces the colormap exactly and EXR holds the
same picture.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

import numpy as np

from .._checks import check_choice, check_float
from ..io import atomic_path
from ..lighting.imageio import write_image

__all__ = ["srgb_encode", "srgb_decode", "auto_exposure", "tonemap", "to_display", "error_map", "error_heatmap",
           "save_png", "save_exr", "side_by_side", "TONEMAPS"]

TONEMAPS = ("clip", "reinhard")
_LUMA = np.array([0.2126, 0.7152, 0.0722])  # Rec. 709 luminance weights of linear RGB


def _np(x, name: str = "image") -> np.ndarray:
    a = np.asarray(x.detach().cpu().numpy() if hasattr(x, "detach") else x)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.ndim != 3 or a.shape[2] not in (1, 3, 4):
        raise ValueError(f"{name} has shape {a.shape}; accepted: [H, W], [H, W, 1], [H, W, 3] or [H, W, 4]")
    return a


def _rgb(a: np.ndarray) -> np.ndarray:
    if a.shape[2] == 1:
        return np.repeat(a, 3, axis=2)
    return a[:, :, :3]


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 sRGB transfer function, linear [0,1] -> encoded [0,1] (float64)."""
    v = np.clip(np.asarray(linear, np.float64), 0.0, 1.0)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)


def srgb_decode(encoded: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_encode` (float64)."""
    v = np.clip(np.asarray(encoded, np.float64), 0.0, 1.0)
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)


def _mask(mask, shape) -> np.ndarray:
    if mask is None:
        return np.ones(shape, bool)
    m = np.asarray(mask.detach().cpu().numpy() if hasattr(mask, "detach") else mask).astype(bool)
    if m.shape != shape:
        raise ValueError(f"mask has shape {m.shape}; accepted: {shape} (the image's [H, W])")
    return m


def auto_exposure(img, mask=None, percentile: float = 99.0, target: float = 0.8) -> float:
    """Exposure in stops (EV) that maps the ``percentile`` of luminance over the covered,
    finite pixels to ``target``: ``log2(target / p)``. 0 for an all-dark image. Use the SAME
    value for a reference and its approximations so they compare."""
    a = _rgb(_np(img)).astype(np.float64)
    percentile = check_float("percentile", percentile, 0.0, 100.0)
    target = check_float("target", target, 0.0, lo_open=True)
    lum = a @ _LUMA
    m = _mask(mask, lum.shape) & np.isfinite(lum)
    if not m.any():
        return 0.0
    p = float(np.percentile(lum[m], percentile))
    return float(np.log2(target / p)) if p > 0 else 0.0


def tonemap(img, exposure: float = 0.0, method: str = "clip", background=0.0) -> np.ndarray:
    """Linear ``img [H,W,C]`` -> linear ``[H,W,3] float32`` in [0, 1] for display.

    ``x = img · 2**exposure``; ``'clip'``: min(max(x, 0), 1); ``'reinhard'``: x/(1+x) per channel
    (Reinhard et al. 2002, eq. (3), applied to each channel). Non-finite pixels (e.g. a NaN
    background) become ``background``."""
    check_choice("tonemap", method, TONEMAPS)
    exposure = check_float("exposure", exposure)
    a = _rgb(_np(img)).astype(np.float64) * 2.0 ** exposure
    bad = ~np.isfinite(a).all(axis=2)
    a = np.where(np.isfinite(a), a, 0.0)
    a = np.maximum(a, 0.0)
    a = np.minimum(a, 1.0) if method == "clip" else a / (1.0 + a)
    a[bad] = np.broadcast_to(np.asarray(background, np.float64), (3,))
    return a.astype(np.float32)


def to_display(img, exposure: float = 0.0, method: str = "clip", background=0.0) -> np.ndarray:
    """``[H,W,3] uint8`` sRGB: uint8 input is returned as is (already display-encoded), float
    input goes through :func:`tonemap` then the sRGB encoding, rounded."""
    a = _np(img)
    if a.dtype == np.uint8:
        return np.ascontiguousarray(_rgb(a))
    return np.round(srgb_encode(tonemap(a, exposure, method, background)) * 255.0).astype(np.uint8)


def error_map(img, ref, mask=None, kind: str = "abs", eps: float | None = None) -> np.ndarray:
    """Per-pixel error ``[H, W] float64`` between ``img`` and ``ref`` (``[H,W,C]``), NaN outside ``mask``.

    ``'abs'``: mean over channels of |img − ref|; ``'rel'``: that divided by
    max(mean_c |ref|, eps), eps defaulting to 1e-3 × the mean of mean_c |ref| over the mask
    (so black reference pixels do not explode); ``'sq'``: mean over channels of (img − ref)²."""
    check_choice("kind", kind, ["abs", "rel", "sq"])
    a, b = _np(img, "img").astype(np.float64), _np(ref, "ref").astype(np.float64)
    if a.shape != b.shape:
        raise ValueError(f"img has shape {a.shape} but ref has {b.shape}; accepted: equal shapes")
    m = _mask(mask, a.shape[:2])
    d = a - b
    e = (d * d).mean(2) if kind == "sq" else np.abs(d).mean(2)
    if kind == "rel":
        r = np.abs(b).mean(2)
        if eps is None:
            inside = r[m & np.isfinite(r)]
            eps = 1e-3 * float(inside.mean()) if inside.size and inside.mean() > 0 else 1e-12
        e = e / np.maximum(r, check_float("eps", eps, 0.0, lo_open=True))
    return np.where(m, e, np.nan)


def error_heatmap(img, ref, mask=None, kind: str = "abs", vmax: float | None = None, cmap: str = "inferno",
                  background=(1.0, 1.0, 1.0), percentile: float = 99.0) -> np.ndarray:
    """Heat map of :func:`error_map` as linear RGB ``[H, W, 3] float32`` in [0, 1].

    The error is divided by ``vmax`` (default: its ``percentile`` over the mask; pass the same
    value to every panel of a comparison and state it in the label) and coloured by the
    matplotlib colormap ``cmap``; pixels outside ``mask`` get ``background`` (white by default,
    distinct from inferno's black zero)."""
    import matplotlib

    e = error_map(img, ref, mask, kind)
    valid = np.isfinite(e)
    if vmax is None:
        vmax = float(np.percentile(e[valid], check_float("percentile", percentile, 0.0, 100.0))) if valid.any() else 0.0
        if not vmax > 0:
            vmax = float(e[valid].max()) if valid.any() and e[valid].max() > 0 else 1.0
    vmax = check_float("vmax", vmax, 0.0, lo_open=True)
    try:
        cm = matplotlib.colormaps[cmap]
    except KeyError:
        raise ValueError(f"cmap={cmap!r} is not a matplotlib colormap; e.g. 'inferno', 'viridis', 'magma'") from None
    rgba = cm(np.clip(np.where(valid, e, 0.0) / vmax, 0.0, 1.0))  # display (sRGB) colours
    out = srgb_decode(rgba[:, :, :3])
    out[~valid] = np.broadcast_to(np.asarray(background, np.float64), (3,))
    return out.astype(np.float32)


def save_exr(path: str | os.PathLike, img, overwrite: bool = True) -> Path:
    """Write linear float ``img [H,W,C]`` as float32 OpenEXR (atomic; NaN kept)."""
    path = Path(path)
    if path.suffix.lower() != ".exr":
        raise ValueError(f"save_exr path {str(path)!r}; accepted: a name ending in .exr")
    a = _np(img)
    if a.dtype == np.uint8:
        raise TypeError("save_exr takes a linear float image; got uint8 (display) data")
    return write_image(path, a.astype(np.float32), overwrite=overwrite)


def save_png(path: str | os.PathLike, img, exposure: float = 0.0, tonemap: str = "clip", background=0.0,
             overwrite: bool = True) -> Path:
    """Write an 8-bit sRGB PNG (atomic). Float ``img`` is linear: scaled by 2**exposure, tone
    mapped (:func:`tonemap`), sRGB-encoded; uint8 ``img`` is written unchanged."""
    import OpenImageIO as oiio

    path = Path(path)
    if path.suffix.lower() != ".png":
        raise ValueError(f"save_png path {str(path)!r}; accepted: a name ending in .png")
    data = to_display(img, exposure, tonemap, background)
    h, w, c = data.shape
    with atomic_path(path, overwrite=overwrite) as tmp:
        out = oiio.ImageOutput.create("png")
        spec = oiio.ImageSpec(w, h, c, "uint8")
        spec.attribute("oiio:ColorSpace", "sRGB")
        if out is None or not out.open(str(tmp), spec):
            raise ValueError(f"cannot write {str(path)!r}: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(data))
        out.close()
        if not ok:
            raise ValueError(f"cannot write {str(path)!r}: {out.geterror()}")
    return path


def _label_strip(text: str, width: int, height: int, fontsize: float) -> np.ndarray:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    dpi = 100
    fig = Figure(figsize=(width / dpi, height / dpi), dpi=dpi, facecolor="white")
    FigureCanvasAgg(fig)
    fig.text(0.5, 0.5, text, ha="center", va="center", fontsize=fontsize, color="black")
    fig.canvas.draw()
    buf = np.asarray(fig.canvas.buffer_rgba())[:, :, :3]
    if buf.shape[:2] != (height, width):  # pragma: no cover - Agg renders exactly figsize·dpi
        buf = np.pad(buf, ((0, max(0, height - buf.shape[0])), (0, max(0, width - buf.shape[1])), (0, 0)),
                     constant_values=255)[:height, :width]
    return np.ascontiguousarray(buf, dtype=np.uint8)


def side_by_side(images: Sequence, labels: Sequence[str] | None = None, exposure=0.0, tonemap: str = "clip",
                 columns: int | None = None, gap: int = 4, label_height: int = 22, fontsize: float = 10.0,
                 background=0.0, path: str | os.PathLike | None = None) -> np.ndarray:
    """Composite panels into one display image ``[H', W', 3] uint8`` (sRGB), each with its label
    above it, for reports (e.g. reference | codec | error heat map).

    Args:
        images: ``[H_i, W_i, C]`` arrays/tensors; float = linear (tone mapped with ``exposure``
            and ``tonemap``), uint8 = already display-encoded.
        labels: one string per image (or None).
        exposure: stops, one value for all panels or a list (None entries = 0): give a
            reference and its approximations the same value and heat maps 0.
        columns: panels per row (default: all in one row).
        path: also write the composite there as PNG.
    Pixels of each panel are copied exactly (no resampling); panels smaller than the largest
    are padded with white.
    """
    if not len(images):
        raise ValueError("side_by_side needs at least one image")
    n = len(images)
    if labels is not None and len(labels) != n:
        raise ValueError(f"{len(labels)} labels for {n} images; accepted: one label per image")
    exps = list(exposure) if isinstance(exposure, (list, tuple)) else [exposure] * n
    if len(exps) != n:
        raise ValueError(f"{len(exps)} exposures for {n} images; accepted: one value or one per image")
    panels = [to_display(im, 0.0 if e is None else e, tonemap, background) for im, e in zip(images, exps)]
    cols = n if columns is None else max(1, min(int(columns), n))
    rows = -(-n // cols)
    ph = max(p.shape[0] for p in panels)
    pw = max(p.shape[1] for p in panels)
    lh = label_height if labels is not None else 0
    H = rows * (ph + lh) + (rows + 1) * gap
    W = cols * pw + (cols + 1) * gap
    out = np.full((H, W, 3), 255, np.uint8)
    for i, p in enumerate(panels):
        r, c = divmod(i, cols)
        y = gap + r * (ph + lh + gap)
        x = gap + c * (pw + gap)
        if labels is not None:
            out[y:y + lh, x:x + pw] = _label_strip(str(labels[i]), pw, lh, fontsize)
        out[y + lh:y + lh + p.shape[0], x:x + p.shape[1]] = p
    if path is not None:
        save_png(path, out)
    return out
