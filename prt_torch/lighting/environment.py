"""Environment maps: an HDR image in a layout, its world directions and solid angles, and its
projection onto spherical harmonics.

Projection (Ramamoorthi 2002, eq. 4.13, as a pixel sum with exact per-pixel solid angles):

    L_lm = Σ_pixels L(p) y_lm(d_p) Ω_p

done per channel and batched as one GEMM per chunk of pixels through
:func:`prt_torch.sh.eval_sh` (basis) and a matrix product, in float64.
"""
from __future__ import annotations

import math

import os
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import torch

from .._checks import check_choice, check_int, check_shape, describe
from ..sh import MAX_BANDS, band_of_coeffs, eval_sh, window as sh_window
from . import layouts as L
from .imageio import read_image, write_image

__all__ = [
    "Environment",
    "load_environment",
    "render_sh",
    "project_images",
    "window_factors",
    "expand_window",
]

_CHUNK = 1 << 16  # pixels per GEMM chunk: bounds the [chunk, n²] basis to a few MB
#: pixels per row block of :meth:`Environment.from_function` (each sub-pixel pass's directions, the function's values
#: and their temporaries, a few hundred bytes per pixel: a few MiB a block)
FROM_FUNCTION_BLOCK = 1 << 14


def window_factors(window: Any, bands: int) -> torch.Tensor | None:
    """Per-band factors ``[bands]`` float64 for ``window`` (None -> None, i.e. no windowing).

    Accepted: None/'none'; 'hanning' or 'lanczos' (width = bands-1, :func:`prt_torch.sh.window`);
    'gaussian:σ' or ('gaussian', σ) — exp(-(σ l)²), Ramamoorthi 2002 eq. 6.7 (σ in radians);
    a tensor/sequence of ``bands`` factors."""
    if window is None or (isinstance(window, str) and window == "none"):
        return None
    if isinstance(window, str):
        if window.startswith("gaussian"):
            parts = window.split(":")
            if len(parts) != 2:
                raise ValueError(f"window={window!r}; accepted: 'gaussian:SIGMA' (SIGMA in radians, eq. 6.7)")
            return sh_window(bands, "gaussian", sigma=float(parts[1]))
        check_choice("window", window, ["none", "hanning", "lanczos", "gaussian:SIGMA"])
        return sh_window(bands, window)
    if isinstance(window, (tuple, list)) and len(window) == 2 and window[0] == "gaussian":
        return sh_window(bands, "gaussian", sigma=float(window[1]))
    w = torch.as_tensor(window, dtype=torch.float64)
    if w.shape != (bands,):
        raise ValueError(f"window {describe(window)}; accepted: None, 'hanning', 'lanczos', 'gaussian:SIGMA' "
                         f"or {bands} per-band factors")
    return w


def expand_window(w: torch.Tensor) -> torch.Tensor:
    """Per-band factors ``[bands]`` -> per-coefficient ``[bands²]``."""
    bands = w.shape[0]
    return w[torch.repeat_interleave(torch.arange(bands), 2 * torch.arange(bands) + 1)]


def max_resolved_bands(pixels: int) -> int:
    """The most SH bands a map of ``pixels`` valid pixels resolves without aliasing: two samples
    per shortest wavelength (2π/l) along a great circle. A lat-long H×2H map (2H² pixels) has H
    rows over π, so l ≤ H/2: n = ⌊√(P/8)⌋ + 1 bands (P/8 = H²/4)."""
    return math.isqrt(max(0, int(pixels)) // 8) + 1


def _project_flat(values: torch.Tensor, dirs: torch.Tensor, weights: torch.Tensor, bands: int) -> torch.Tensor:
    """values ``[P, K]``, dirs ``[P, 3]``, weights ``[P]`` -> ``[K, n²]`` float64, chunked GEMM.
    Refuses ``bands`` beyond what P samples resolve (:func:`max_resolved_bands`)."""
    bands = check_int("bands", bands, 1, MAX_BANDS)
    top = max_resolved_bands(values.shape[0])
    if bands > top:
        raise ValueError(f"bands={bands} from a map of {values.shape[0]} pixels would alias: it resolves at most {top} bands; "
                         f"accepted: bands <= {top}, or a larger image (about {8 * (bands - 1) ** 2} pixels for {bands} bands)")
    out = torch.zeros(values.shape[1], bands * bands, dtype=torch.float64)
    for s in range(0, values.shape[0], _CHUNK):  # a handful of chunks, each a GEMM
        y = eval_sh(dirs[s:s + _CHUNK], bands, check=False)
        out += (values[s:s + _CHUNK] * weights[s:s + _CHUNK, None]).T @ y
    return out


class Environment:
    """An environment map: ``image [H, W, C]`` float32 linear radiance in ``layout``.

    ``rotation [3, 3]`` float64 maps the layout's (file) directions to the world
    (world = rotation · d_file). ``faces`` images are an N × 6N strip (+x, -x, +y, -y, +z, -z).

    Methods: :meth:`directions` ``[H, W, 3]``, :meth:`solid_angles` ``[H, W]``, :meth:`mask`
    ``[H, W]``, :meth:`project` -> ``[C, n²]`` float64, :meth:`sample`, :meth:`to_layout`,
    :meth:`rotated`, :meth:`save`, :meth:`from_function`.
    """

    def __init__(self, image, layout: str, rotation: torch.Tensor | None = None, name: str = "",
                 meta: dict | None = None):
        img = torch.as_tensor(np.asarray(image) if not isinstance(image, torch.Tensor) else image)
        if img.ndim == 2:
            img = img[:, :, None]
        check_shape("image", img, ndim=3)
        if not img.is_floating_point():
            raise TypeError(f"image has dtype {img.dtype}; accepted: a float tensor (linear radiance)")
        self.image = img.to(torch.float32).contiguous()
        self.layout = check_choice("layout", layout, L.LAYOUTS)
        self.size = L.layout_size(layout, img.shape[0], img.shape[1], source=name or "image")
        self.rotation = torch.eye(3, dtype=torch.float64) if rotation is None else torch.as_tensor(rotation, dtype=torch.float64)
        self.name = name
        self.meta = dict(meta or {})
        self._cache: dict = {}

    # ---- geometry ---------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape[0], self.image.shape[1]

    @property
    def channels(self) -> int:
        return self.image.shape[2]

    def file_directions(self) -> torch.Tensor:
        """Pixel-centre directions in the layout's own frame, ``[H, W, 3]`` float64."""
        if "fdirs" not in self._cache:
            self._cache["fdirs"] = L.pixel_directions(self.layout, *self.shape)
        return self._cache["fdirs"]

    def directions(self) -> torch.Tensor:
        """World directions of pixel centres, ``[H, W, 3]`` float64 (rotation applied)."""
        if "dirs" not in self._cache:
            self._cache["dirs"] = self.file_directions() @ self.rotation.T
        return self._cache["dirs"]

    def solid_angles(self) -> torch.Tensor:
        """Per-pixel solid angles ``[H, W]`` float64 (Σ = 4π; 0 on masked pixels)."""
        if "omega" not in self._cache:
            self._cache["omega"] = L.solid_angles(self.layout, *self.shape)
        return self._cache["omega"]

    def mask(self) -> torch.Tensor:
        """Pixels that carry light ``[H, W]`` bool."""
        if "mask" not in self._cache:
            self._cache["mask"] = L.valid_mask(self.layout, *self.shape) & (self.solid_angles() > 0)
        return self._cache["mask"]

    def _flat_geometry(self):
        """Cached (dirs [P, 3], Ω [P], pixel index [P] or None when every pixel is valid)."""
        if "flat" not in self._cache:
            m = self.mask().reshape(-1)
            d = self.directions().reshape(-1, 3)
            om = self.solid_angles().reshape(-1)
            if bool(m.all()):
                self._cache["flat"] = (d, om, None)
            else:
                idx = torch.nonzero(m).squeeze(1)
                self._cache["flat"] = (d[idx].contiguous(), om[idx].contiguous(), idx)
        return self._cache["flat"]

    # ---- SH ---------------------------------------------------------------------------
    def project(self, bands: int, window: Any = None) -> torch.Tensor:
        """SH coefficients of the map, ``[C, n²]`` float64 (Ramamoorthi 2002, eq. 4.13).

        ``window`` (off by default): see :func:`window_factors` — 'hanning', 'lanczos',
        'gaussian:σ' (eq. 6.7) or per-band factors."""
        dirs, omega, idx = self._flat_geometry()
        vals = self.image.reshape(-1, self.channels)
        vals = (vals if idx is None else vals[idx]).to(torch.float64)  # [P, C]
        out = _project_flat(vals, dirs, omega, bands)
        w = window_factors(window, bands)
        return out if w is None else out * expand_window(w)

    def total_power(self) -> torch.Tensor:
        """∫ L dω per channel, ``[C]`` float64."""
        return (self.image.to(torch.float64) * self.solid_angles()[..., None]).sum((0, 1))

    # ---- lookups and conversions ------------------------------------------------------
    def sample(self, dirs: torch.Tensor) -> torch.Tensor:
        """Nearest-pixel radiance at world directions ``[*S, 3]`` -> ``[*S, C]`` float32."""
        check_shape("dirs", dirs, last=(3,))
        fd = dirs.to(torch.float64) @ self.rotation  # world -> file: Rᵀ d
        y, x = L.dir_to_pixel(self.layout, *self.shape, fd)
        return self.image[y.long(), x.long()]

    def to_layout(self, layout: str, size: int, supersample: int = 2) -> "Environment":
        """Resample into another layout (same world orientation, identity rotation), by
        nearest-pixel lookups at ``supersample``² sub-pixel directions averaged per pixel."""
        return Environment.from_function(self.sample, layout, size, supersample=supersample,
                                         name=self.name, meta=dict(self.meta, resampled_from=self.layout))

    def rotated(self, R: Any) -> "Environment":
        """The same image with world = R · (current world); R as for :func:`layouts.resolve_rotation`."""
        Rm = L.resolve_rotation(R, "z")
        return Environment(self.image, self.layout, Rm @ self.rotation, self.name, self.meta)

    def save(self, path: str | os.PathLike, overwrite: bool = False) -> list[Path]:
        """Write the image in its layout (world rotation is not baked in). A ``faces`` map is
        written as six files when ``path`` contains '{face}' (px, nx, py, ny, pz, nz), else as
        an N × 6N strip."""
        p = str(path)
        if self.layout == "faces" and "{face}" in p:
            n = self.size
            out = []
            for k, fname in enumerate(L.FACE_NAMES):  # six faces
                out.append(write_image(p.format(face=fname), self.image[:, k * n:(k + 1) * n], overwrite=overwrite))
            return out
        return [write_image(p, self.image, overwrite=overwrite)]

    @classmethod
    def from_function(cls, fn: Callable[[torch.Tensor], torch.Tensor], layout: str, size: int,
                      supersample: int = 1, rotation: Any = None, name: str = "", meta: dict | None = None) -> "Environment":
        """Rasterise ``fn(world dirs [N, 3] float64) -> [N, C]`` into ``layout`` at ``size``,
        averaging ``supersample``² sub-pixel samples per pixel (samples outside the angular
        disk or in blank cross tiles are skipped). ``rotation`` as in :func:`load_environment`.
        Rasterised in blocks of about :data:`FROM_FUNCTION_BLOCK` pixels' rows (each pixel's samples summed in the
        same order as a whole-image pass): the directions and their temporaries (~1 KB per pixel at
        ``supersample`` 4) never exist for the whole image at once."""
        R = L.resolve_rotation(rotation, "z")
        h, w = L.layout_shape(layout, size)
        s = check_int("supersample", supersample, 1, 32)
        rows = max(1, FROM_FUNCTION_BLOCK // w)
        xa = torch.arange(w, dtype=torch.float64)[None, :]
        img = None
        for y0 in range(0, h, rows):  # a loop over row blocks and the s² sub-pixel offsets; each a batched call
            y1 = min(h, y0 + rows)
            ya = torch.arange(y0, y1, dtype=torch.float64)[:, None].expand(y1 - y0, w)
            xb = xa.expand(y1 - y0, w)
            acc = None
            cnt = torch.zeros(y1 - y0, w, dtype=torch.float64)
            for p in range(s):
                for q in range(s):
                    d, valid = L.pixel_to_dir(layout, h, w, ya + (p + 0.5) / s, xb + (q + 0.5) / s)
                    v = torch.as_tensor(fn((d @ R.T).reshape(-1, 3))).to(torch.float64).reshape(y1 - y0, w, -1)
                    v = v * valid[..., None]
                    acc = v if acc is None else acc + v
                    cnt += valid
            block = (acc / cnt.clamp_min(1)[..., None]).to(torch.float32)
            if img is None:
                img = torch.empty(h, w, block.shape[-1], dtype=torch.float32)
            img[y0:y1] = block
        return cls(img, layout, R, name, meta)

    def __repr__(self) -> str:
        return (f"Environment(name={self.name!r}, layout={self.layout!r}, shape={tuple(self.image.shape)}, "
                f"rotated={not torch.equal(self.rotation, torch.eye(3, dtype=torch.float64))})")


def _face_paths(path: str | os.PathLike | Sequence) -> list[str] | None:
    if isinstance(path, (list, tuple)):
        if len(path) != 6:
            raise ValueError(f"a cube map from separate faces needs 6 paths (+x, -x, +y, -y, +z, -z); got {len(path)}")
        return [str(p) for p in path]
    p = str(path)
    if "{face}" in p:
        return [p.format(face=f) for f in L.FACE_NAMES]
    return None


def load_environment(path, layout: str | None = None, rotation: Any = None, up: str = "z",
                     clamp: bool = False, name: str | None = None) -> Environment:
    """Read an HDR environment map.

    Args:
        path: an image file (.hdr, .exr, .pfm, .tif, ...); or six face files as a list
            (+x, -x, +y, -y, +z, -z) or a pattern containing '{face}' (filled with px, nx, py,
            ny, pz, nz).
        layout: None (auto-detect from W:H: 2:1 latlong, 1:1 angular, 3:4 vcross, 4:3 hcross,
            6:1 faces strip) or one of 'latlong', 'angular', 'vcross', 'hcross', 'faces'.
        rotation: None, 3×3 matrix, or Euler angles in degrees (x, y, z; see
            :func:`layouts.euler_matrix`), applied after ``up``.
        up: the file frame's up axis ('z' default, 'y', '-y', 'x', ...); see
            :func:`layouts.up_rotation`.
        clamp: set NaN/Inf and negative pixels to 0 (counted in ``meta['clamped']``) instead
            of refusing the file.
    Returns:
        :class:`Environment` with world = R_rotation · R_up · d_file.
    """
    if layout is not None:
        check_choice("layout", layout, L.LAYOUTS)
    R = L.resolve_rotation(rotation, up)
    faces = _face_paths(path)
    if faces is not None:
        if layout not in (None, "faces"):
            raise ValueError(f"six face files were given but layout={layout!r}; accepted: layout='faces' or None")
        imgs, infos = [], []
        for fp in faces:  # six files
            img, info = read_image(fp, clamp=clamp)
            if img.shape[0] != img.shape[1]:
                raise ValueError(f"cube face {fp!r} is {img.shape[1]}x{img.shape[0]}; accepted: square faces")
            if imgs and img.shape != imgs[0].shape:
                raise ValueError(f"cube face {fp!r} is {img.shape[1]}x{img.shape[0]} but {faces[0]!r} is "
                                 f"{imgs[0].shape[1]}x{imgs[0].shape[0]}; accepted: six faces of one size")
            imgs.append(img)
            infos.append(info)
        img = np.concatenate(imgs, axis=1)
        meta = {"source": faces, "files": infos}
        return Environment(torch.from_numpy(img), "faces", R, name or Path(faces[0]).stem, meta)
    img, info = read_image(path, clamp=clamp)
    h, w = img.shape[:2]
    lay = layout or L.detect_layout(h, w, source=str(path))
    L.layout_size(lay, h, w, source=str(path))
    return Environment(torch.from_numpy(img), lay, R, name or Path(path).stem,
                       {"source": str(path), "files": [info], "layout_detected": layout is None})


def render_sh(coeffs: torch.Tensor, layout: str = "latlong", size: int = 64, rotation: Any = None,
              name: str = "sh") -> Environment:
    """Render an SH vector ``[C, n²]`` (or ``[n²]``) into an image layout (SH -> image):
    pixel value = Σ c_lm y_lm(world direction of the pixel centre); masked pixels are 0.
    ``rotation`` is stored on the Environment, so projecting the result gives ``coeffs`` back
    (up to the layout's quadrature error)."""
    c = coeffs[None] if coeffs.ndim == 1 else coeffs
    bands = band_of_coeffs(c.shape[-1], "coeffs.shape[-1]")
    R = L.resolve_rotation(rotation, "z")
    h, w = L.layout_shape(layout, size)
    d = L.pixel_directions(layout, h, w) @ R.T
    img = (eval_sh(d, bands, check=False) @ c.to(torch.float64).reshape(-1, c.shape[-1]).T)
    img = img * L.valid_mask(layout, h, w)[..., None]
    return Environment(img.to(torch.float32), layout, R, name, {"bands": bands})


def project_images(images: torch.Tensor, layout: str, bands: int, rotation: Any = None, window: Any = None) -> torch.Tensor:
    """Batched projection of many maps of one layout and size: ``images [B, H, W, C]`` ->
    ``[B, C, n²]`` float64, one GEMM per pixel chunk (Ramamoorthi 2002, eq. 4.13)."""
    check_shape("images", images, ndim=4)
    B, h, w, C = images.shape
    L.layout_size(layout, h, w, source="images")
    R = L.resolve_rotation(rotation, "z")
    m = L.valid_mask(layout, h, w) & (L.solid_angles(layout, h, w) > 0)
    d = (L.pixel_directions(layout, h, w) @ R.T)[m]
    om = L.solid_angles(layout, h, w)[m]
    vals = images.to(torch.float64)[:, m].permute(1, 0, 2).reshape(-1, B * C)  # [P, B*C]
    out = _project_flat(vals, d, om, bands).reshape(B, C, bands * bands)
    wf = window_factors(window, bands)
    return out if wf is None else out * expand_window(wf)
