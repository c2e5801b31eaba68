"""HDR image reading and writing: OpenImageIO for .hdr/.exr/.tif (and anything else it reads),
a small exact codec for .pfm.

Rules (documented in docs/lighting.md):

* Pixels come back as linear float32 RGB ``[H, W, 3]``, row 0 = the top of the image.
* Channels: 1 channel -> replicated to RGB; 2 channels (grey + alpha) -> grey replicated,
  alpha dropped; ≥ 3 channels -> R, G, B by name when the file names them, else the first
  three; alpha and any other channel are dropped (listed in ``info['dropped_channels']``).
* Integer-typed files (8/16-bit PNG, JPEG, TIFF, ...) are scaled to [0, 1] by OpenImageIO and,
  when the file's colour space is sRGB (OIIO's ``oiio:ColorSpace``), decoded with the sRGB
  transfer function to linear. Float files are taken as linear.
* NaN/Inf or negative pixels are refused with a ValueError naming the file and the counts,
  unless ``clamp=True``: then non-finite and negative values become 0 and the counts are
  returned in ``info['clamped']`` (and a warning is issued).
* PFM: OpenImageIO 3.x's PFM reader and writer disagree on row order (its writer stores the
  rows bottom-to-top, as the format requires, its reader returns them in file order, i.e.
  upside down). PFM is therefore read and written here directly, following the format:
  header ``PF``/``Pf``, ``W H``, scale (negative = little-endian), rows bottom-to-top.
"""
from __future__ import annotations

import os
import re
import warnings
from pathlib import Path

import numpy as np

from ..io import atomic_path

__all__ = ["read_image", "write_image", "to_rgb"]


def _fail_unreadable(path: Path, why: str) -> None:
    raise ValueError(f"cannot read image {str(path)!r}: {why}; accepted: an image OpenImageIO can read "
                     "(.hdr, .exr, .pfm, .tif, .png, ...)")


def _read_pfm(path: Path) -> np.ndarray:
    data = path.read_bytes()
    m = re.match(rb"(P[Ff])\s+(\d+)\s+(\d+)\s+([-+0-9.eE]+)\s", data)
    if not m:
        _fail_unreadable(path, "not a valid PFM header ('PF'/'Pf', width height, scale)")
    kind, w, h, scale = m.group(1), int(m.group(2)), int(m.group(3)), float(m.group(4))
    c = 3 if kind == b"PF" else 1
    n = w * h * c
    body = data[m.end():]
    if len(body) < 4 * n:
        _fail_unreadable(path, f"PFM body has {len(body)} bytes, needs {4 * n} for {w}x{h}x{c}")
    arr = np.frombuffer(body[: 4 * n], dtype="<f4" if scale < 0 else ">f4").reshape(h, w, c)
    return np.ascontiguousarray(arr[::-1]).astype(np.float32)  # file rows are bottom-to-top


def _write_pfm(path: Path, img: np.ndarray) -> None:
    h, w, c = img.shape
    head = f"{'PF' if c == 3 else 'Pf'}\n{w} {h}\n-1.0\n".encode()
    with open(path, "wb") as f:
        f.write(head)
        f.write(np.ascontiguousarray(img[::-1]).astype("<f4").tobytes())


def _srgb_to_linear(v: np.ndarray) -> np.ndarray:
    return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4).astype(np.float32)


def to_rgb(arr: np.ndarray, names: list[str] | None = None, source: str = "image") -> tuple[np.ndarray, list[str]]:
    """Apply the channel rule to ``arr [H, W, C]``: returns (``[H, W, 3]`` float32, dropped channel names)."""
    if arr.ndim == 2:
        arr = arr[:, :, None]
    c = arr.shape[2]
    names = list(names) if names else [f"channel{i}" for i in range(c)]
    if c == 1:
        return np.repeat(arr, 3, axis=2).astype(np.float32), []
    if c == 2:
        return np.repeat(arr[:, :, :1], 3, axis=2).astype(np.float32), [names[1]]
    upper = [n.upper() for n in names]
    if all(k in upper for k in ("R", "G", "B")):
        idx = [upper.index(k) for k in ("R", "G", "B")]
    else:
        idx = [0, 1, 2]
    dropped = [names[i] for i in range(c) if i not in idx]
    return np.ascontiguousarray(arr[:, :, idx]).astype(np.float32), dropped


def read_image(path: str | os.PathLike, clamp: bool = False, what: str = "environment map", check: bool = True) -> tuple[np.ndarray, dict]:
    """Read an image as linear float32 RGB ``[H, W, 3]`` (row 0 = top) plus an info dict.

    info: ``path``, ``format``, ``channels`` (in the file), ``dropped_channels``,
    ``srgb_decoded`` (bool), ``integer`` (bool: 8/16-bit data), ``alpha`` (``[H, W]`` float32
    of a channel named A/alpha, or of the 2nd of 2 / 4th of 4 unnamed channels; else None),
    ``clamped`` ({'nonfinite': n, 'negative': n} when clamp=True). ``what`` names the file in
    messages ("environment map", "image"); ``check=False`` leaves NaN/Inf/negative values as they
    are for the caller to judge (e.g. only where alpha > 0). Raises FileNotFoundError for a missing file,
    ValueError for unreadable data or bad pixels.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what} {str(path)!r} does not exist")
    if path.is_dir():
        raise ValueError(f"{str(path)!r} is a directory; accepted: an image file")
    info: dict = {"path": str(path), "srgb_decoded": False, "integer": False, "alpha": None}
    if path.suffix.lower() == ".pfm":
        arr = _read_pfm(path)
        info.update(format="pfm", channels=arr.shape[2])
        rgb, dropped = to_rgb(arr, None, str(path))
        names = None
    else:
        import OpenImageIO as oiio

        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            _fail_unreadable(path, oiio.geterror() or "unknown format")
        try:
            spec = inp.spec()
            arr = inp.read_image(0, 0, 0, spec.nchannels, "float")
            if arr is None:
                _fail_unreadable(path, inp.geterror() or "no pixel data")
            names = list(spec.channelnames)
            cs = str(spec.get_string_attribute("oiio:ColorSpace", "")).lower()
            integer = str(spec.format) not in ("float", "half", "double")
            info.update(format=inp.format_name(), channels=spec.nchannels)
        finally:
            inp.close()
        arr = np.asarray(arr, dtype=np.float32).reshape(spec.height, spec.width, spec.nchannels)
        rgb, dropped = to_rgb(arr, names, str(path))
        info["integer"] = integer
        if integer and "srgb" in cs:
            rgb = _srgb_to_linear(rgb)
            info["srgb_decoded"] = True
    info["dropped_channels"] = dropped
    if names is not None and dropped:
        up = [n.upper() for n in names]
        ia = next((i for i, n in enumerate(up) if n in ("A", "ALPHA")), None)
        if ia is None and len(names) in (2, 4) and all(n.startswith("CHANNEL") for n in up):
            ia = len(names) - 1
        if ia is not None:
            info["alpha"] = np.ascontiguousarray(arr[:, :, ia], dtype=np.float32)
    if not check:
        return rgb, info
    bad_nf = ~np.isfinite(rgb)
    n_nf = int(bad_nf.sum())
    n_neg = int((rgb < 0).sum())
    if n_nf or n_neg:
        if not clamp:
            raise ValueError(
                f"{what} {str(path)!r} has {n_nf} NaN/Inf and {n_neg} negative channel value(s) "
                f"(of {rgb.size}); radiance must be finite and ≥ 0. Fix the file, or load with clamp=True "
                "(CLI: --clamp) to set them to 0"
            )
        rgb = np.where(bad_nf | (rgb < 0), 0.0, rgb).astype(np.float32)
        warnings.warn(f"{path}: clamped {n_nf} NaN/Inf and {n_neg} negative channel value(s) to 0", stacklevel=2)
    info["clamped"] = {"nonfinite": n_nf, "negative": n_neg}
    return rgb, info


def write_image(path: str | os.PathLike, image, overwrite: bool = True) -> Path:
    """Write ``image [H, W, C]`` (C = 1, 3 or 4; numpy or torch; linear float) atomically.

    The format follows the extension (.exr half→float32 kept, .hdr RGBE, .pfm, .tif float,
    .png/.jpg 8-bit: values are sRGB-encoded and clipped to [0, 1] — for previews only).
    """
    path = Path(path)
    arr = image.detach().cpu().numpy() if hasattr(image, "detach") else np.asarray(image)
    if arr.ndim == 2:
        arr = arr[:, :, None]
    if arr.ndim != 3 or arr.shape[2] not in (1, 3, 4):
        raise ValueError(f"image to write has shape {arr.shape}; accepted: [H, W, C] with C in 1, 3, 4")
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    ext = path.suffix.lower()
    with atomic_path(path, overwrite=overwrite) as tmp:
        if ext == ".pfm":
            if arr.shape[2] == 4:
                arr = arr[:, :, :3]
            _write_pfm(tmp, arr)
            return path
        import OpenImageIO as oiio

        ldr = ext in (".png", ".jpg", ".jpeg", ".bmp", ".tga", ".gif", ".webp")
        fmt_name = ext.lstrip(".")
        out = oiio.ImageOutput.create(fmt_name)
        if out is None:
            raise ValueError(f"cannot write {str(path)!r}: no OpenImageIO writer for {ext!r} ({oiio.geterror()}); "
                             "accepted: .exr, .hdr, .pfm, .tif, .png, ...")
        h, w, c = arr.shape
        if ldr:
            v = np.clip(arr, 0.0, 1.0)
            v = np.where(v <= 0.0031308, 12.92 * v, 1.055 * np.power(v, 1 / 2.4) - 0.055)
            data = np.ascontiguousarray(np.round(v * 255.0).astype(np.uint8))
            spec = oiio.ImageSpec(w, h, c, "uint8")
            spec.attribute("oiio:ColorSpace", "sRGB")
        else:
            data = arr
            spec = oiio.ImageSpec(w, h, c, "float")
        if not out.open(str(tmp), spec):
            raise ValueError(f"cannot write {str(path)!r}: {out.geterror()}")
        ok = out.write_image(data)
        out.close()
        if not ok:
            raise ValueError(f"cannot write {str(path)!r}: {out.geterror()}")
    return path
