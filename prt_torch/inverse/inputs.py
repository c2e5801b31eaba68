"""Inputs of inverse rendering: cameras in the NeRF/Blender ``transforms.json`` convention, linear
images, and the pixels traced to surface points of the known mesh (Ramamoorthi 2002 §6.2: "object
geometry and photographs from a number of viewing directions, with known extrinsic and intrinsic
camera parameters").

``transforms.json`` (the layout NeRF's Blender scenes, instant-ngp and nerfstudio write)::

    {"camera_angle_x": 0.69,            # horizontal field of view, radians   -- or --
     "fl_x": 711.1, "fl_y": 711.1,      # focal lengths in pixels (fl_y defaults to fl_x)
     "cx": 400, "cy": 400,              # principal point in pixels (default w/2, h/2)
     "w": 800, "h": 800,                # image size (default: read from each image)
     "frames": [{"file_path": "./train/r_0.png",      # relative to the json; no suffix: tried
                 "transform_matrix": [[...4 rows...]]}]}   # .exr .hdr .pfm .png .jpg in turn

Any intrinsic key may also sit in a frame (it then overrides the top-level one for that frame).
``transform_matrix`` is camera-to-world, OpenGL axes: the camera looks down its −z, +y is up
in the image, +x to the right. Pixel (row r, column c) has its centre at ``(c + 0.5, r + 0.5)``
(row 0 at the top), so its ray leaves the camera centre along
``R · ((c + 0.5 − cx)/fx, −(r + 0.5 − cy)/fy, −1)`` with R the matrix's upper 3×3 — the rule of
:mod:`prt_torch.render.camera` (and of OpenGL rasterisation), so engine renders invert exactly.

The world frame is the mesh's (the engine's: +z up, docs/lighting.md); a capture in another frame
passes its mesh through ``prt_torch.scene.load_scene(..., up=)`` and its matrices likewise.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["CameraView", "Observations", "load_cameras", "load_images", "observe", "pixel_rays",
           "camera_from_view", "IMAGE_SUFFIXES"]

IMAGE_SUFFIXES = (".exr", ".hdr", ".pfm", ".png", ".jpg", ".jpeg", ".tif", ".tiff")


@dataclasses.dataclass
class CameraView:
    """One frame of ``transforms.json``.

    Attributes:
        file: the image path (resolved against the json's directory).
        c2w: ``[4, 4]`` float64 camera-to-world (OpenGL axes).
        fx, fy, cx, cy: intrinsics in pixels; w, h: image size in pixels (None: from the image).
    """

    file: Path
    c2w: np.ndarray
    fx: float | None
    fy: float | None
    cx: float | None
    cy: float | None
    w: int | None
    h: int | None
    angle_x: float | None = None
    angle_y: float | None = None

    def resolve(self, w: int, h: int) -> "CameraView":
        """The intrinsics completed for an image of ``w × h`` pixels (focal length from
        ``camera_angle_x``: fx = w / (2 tan(angle_x / 2)); fy = fx unless given; principal point
        at the centre unless given)."""
        fx = self.fx if self.fx is not None else 0.5 * w / math.tan(0.5 * self.angle_x)
        fy = self.fy if self.fy is not None else (0.5 * h / math.tan(0.5 * self.angle_y) if self.angle_y else fx)
        cx = self.cx if self.cx is not None else 0.5 * w
        cy = self.cy if self.cy is not None else 0.5 * h
        return dataclasses.replace(self, fx=float(fx), fy=float(fy), cx=float(cx), cy=float(cy), w=int(w), h=int(h))

    @property
    def eye(self) -> np.ndarray:
        """``[3]`` float64 camera centre in world space."""
        return self.c2w[:3, 3]


def _number(where: str, key: str, v: Any, lo: float = 0.0, lo_open: bool = True) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or (v <= lo if lo_open else v < lo):
        raise ValueError(f"{where}: {key}={v!r}; accepted: a finite number {'>' if lo_open else '≥'} {lo:g}")
    return float(v)


def _find_image(base: Path, rel: str, where: str) -> Path:
    p = (base / rel) if not Path(rel).is_absolute() else Path(rel)
    if p.is_file():
        return p
    if p.suffix.lower() not in IMAGE_SUFFIXES:  # NeRF's Blender scenes store "./train/r_0" without a suffix
        for s in IMAGE_SUFFIXES:
            q = p.with_name(p.name + s)
            if q.is_file():
                return q
    raise FileNotFoundError(f"{where}: file_path {rel!r} does not exist (looked for {str(p)!r}"
                            + ("" if p.suffix else f" with suffixes {', '.join(IMAGE_SUFFIXES)}") + ")")


def load_cameras(path: str | os.PathLike) -> list[CameraView]:
    """Read ``transforms.json`` (module doc): one :class:`CameraView` per frame, every value
    checked (intrinsics present and positive, a finite invertible 4×4 ``transform_matrix`` whose
    rotation part is orthonormal, an existing image file per frame) before anything is traced.
    Raises FileNotFoundError / ValueError naming the file, the frame, the key and what is accepted."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"cameras file {str(path)!r} does not exist")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise ValueError(f"cameras file {str(path)!r} is not JSON ({e}); accepted: a NeRF/Blender transforms.json") from None
    if not isinstance(doc, dict) or not isinstance(doc.get("frames"), list) or not doc["frames"]:
        raise ValueError(f"cameras file {str(path)!r} has no 'frames' list; accepted: a transforms.json with "
                         "frames [{file_path, transform_matrix}, ...]")
    views = []
    for i, fr in enumerate(doc["frames"]):
        where = f"{path}: frames[{i}]"
        if not isinstance(fr, dict):
            raise ValueError(f"{where} is {type(fr).__name__}; accepted: an object with file_path and transform_matrix")
        get = lambda k: fr.get(k, doc.get(k))  # noqa: E731 (per-frame intrinsics override the top level)
        if get("camera_angle_x") is None and get("fl_x") is None:
            raise ValueError(f"{where} has no intrinsics: neither camera_angle_x nor fl_x is given (in the frame or at "
                             "the top level); accepted: camera_angle_x (radians) or fl_x/fl_y/cx/cy in pixels")
        ax = _number(where, "camera_angle_x", get("camera_angle_x")) if get("fl_x") is None else None
        if ax is not None and ax >= math.pi:
            raise ValueError(f"{where}: camera_angle_x={ax!r}; accepted: a horizontal field of view in radians in (0, π)")
        ay = _number(where, "camera_angle_y", get("camera_angle_y")) if get("camera_angle_y") is not None else None
        fx = _number(where, "fl_x", get("fl_x")) if get("fl_x") is not None else None
        fy = _number(where, "fl_y", get("fl_y")) if get("fl_y") is not None else None
        cx = _number(where, "cx", get("cx"), lo_open=False) if get("cx") is not None else None
        cy = _number(where, "cy", get("cy"), lo_open=False) if get("cy") is not None else None
        w = get("w")
        h = get("h")
        for k, v in (("w", w), ("h", h)):
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float)) or v != int(v) or v < 1):
                raise ValueError(f"{where}: {k}={v!r}; accepted: a positive whole number of pixels")
        if "file_path" not in fr or not isinstance(fr["file_path"], str):
            raise ValueError(f"{where} has no file_path string; accepted: the image path relative to {path.name}")
        try:
            M = np.asarray(fr["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"{where}: transform_matrix={fr.get('transform_matrix')!r}; accepted: a 4x4 list of numbers "
                             "(camera-to-world)") from None
        if M.shape != (4, 4) or not np.isfinite(M).all():
            raise ValueError(f"{where}: transform_matrix has shape {M.shape}{'' if np.isfinite(M).all() else ' with NaN/Inf'}; "
                             "accepted: a finite 4x4 camera-to-world matrix")
        R = M[:3, :3]
        if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or not np.allclose(M[3], [0, 0, 0, 1], atol=1e-6):
            raise ValueError(f"{where}: transform_matrix is not a rigid camera-to-world transform (rotation part not "
                             "orthonormal or last row not 0,0,0,1); accepted: [R t; 0 0 0 1] with R a rotation")
        views.append(CameraView(_find_image(path.parent, fr["file_path"], where), M, fx, fy, cx, cy,
                                None if w is None else int(w), None if h is None else int(h), ax, ay))
    return views


def load_images(views: list[CameraView]) -> tuple[list[CameraView], list[np.ndarray], list[np.ndarray], list[dict]]:
    """Read every view's image: (views with intrinsics resolved, images ``[H, W, 3]`` float64
    linear, masks ``[H, W]`` bool (alpha > 0 where the file has alpha, else all), infos).

    8-bit files are decoded from sRGB (a warning says so: quantised, clipped at 1, not
    radiance). Refused, naming the file: an image whose size disagrees with the json's w/h, the
    same size across views is not required; NaN/Inf or negative values where alpha > 0; a file
    whose alpha is 0 everywhere."""
    from ..lighting.imageio import read_image

    out_v, imgs, masks, infos = [], [], [], []
    ldr = []
    for v in views:
        rgb, info = read_image(v.file, what="image", check=False)
        H, W = rgb.shape[:2]
        if (v.w is not None and v.w != W) or (v.h is not None and v.h != H):
            raise ValueError(f"image {str(v.file)!r} is {W}x{H} pixels but its camera says w={v.w}, h={v.h}; accepted: "
                             "the size transforms.json gives (or no w/h there)")
        mask = np.ones((H, W), bool) if info["alpha"] is None else info["alpha"] > 0
        if not mask.any():
            raise ValueError(f"image {str(v.file)!r} has alpha 0 everywhere; accepted: an image showing the object")
        sel = rgb[mask]
        n_nf, n_neg = int((~np.isfinite(sel)).sum()), int((sel < 0).sum())
        if n_nf or n_neg:
            raise ValueError(f"image {str(v.file)!r} has {n_nf} NaN/Inf and {n_neg} negative channel value(s) where alpha > 0; "
                             "accepted: linear radiance, finite and ≥ 0 (mask such pixels with alpha 0)")
        if info["integer"]:
            ldr.append(v.file.name)
        out_v.append(v.resolve(W, H))
        imgs.append(np.where(mask[..., None], rgb, 0.0).astype(np.float64))
        masks.append(mask)
        infos.append(info)
    if ldr:
        warnings.warn(f"{len(ldr)} image(s) are 8/16-bit ({', '.join(ldr[:3])}{', ...' if len(ldr) > 3 else ''}): decoded "
                      "from sRGB to linear; quantised and clipped at 1, so radiance is only approximate — prefer EXR/HDR/PFM",
                      stacklevel=2)
    return out_v, imgs, masks, infos


def pixel_rays(view: CameraView, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World rays through pixel centres (module doc): origins ``[R, 3]`` and unit directions
    ``[R, 3]`` float64 for ``rows``/``cols`` ``[R]`` of a resolved view."""
    d = np.stack([(cols + 0.5 - view.cx) / view.fx, -(rows + 0.5 - view.cy) / view.fy, -np.ones(rows.shape)], 1)
    d = d @ view.c2w[:3, :3].T
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return np.broadcast_to(view.eye, d.shape).copy(), d


def camera_from_view(view: CameraView):
    """The :class:`prt_torch.render.camera.Camera` of a resolved view with square pixels and a
    centred principal point (what the engine's renderer draws): eye, a target one unit down −z,
    up +y of the camera, vertical field of view 2·atan(h / (2 fy))."""
    from ..render.camera import Camera

    R = view.c2w[:3, :3]
    return Camera(view.eye, view.eye - R[:, 2], R[:, 1], "perspective", fov=math.degrees(2 * math.atan(0.5 * view.h / view.fy)),
                  near=1e-3, far=1e3)


@dataclasses.dataclass
class Observations:
    """Pixels of known geometry (Ramamoorthi 2002 §6.2): each valid pixel traced to the point of
    the mesh it sees.

    Attributes:
        tri: ``[P]`` int64 triangle hit; corners: ``[P, 3]`` int64 its vertex ids.
        bary: ``[P, 3]`` float64 barycentric weights of the corners (sum 1).
        points: ``[P, 3]`` float64 surface points; to_eye: ``[P, 3]`` float64 unit directions
            from the point towards the camera (the view direction ω_o).
        values: ``[P, C]`` float64 linear radiance observed (C = 3).
        view: ``[P]`` int64 view index; pixel: ``[P]`` int64 flat index ``row·W + col`` in it.
        shapes: ``[(H, W)]`` per view; views: the resolved :class:`CameraView` list.
        counts: per view, dict(masked=pixels with alpha > 0, hit=pixels that see the front of the
            mesh, back=pixels that see a face from behind, dropped).
    """

    tri: torch.Tensor
    corners: torch.Tensor
    bary: torch.Tensor
    points: torch.Tensor
    to_eye: torch.Tensor
    values: torch.Tensor
    view: torch.Tensor
    pixel: torch.Tensor
    shapes: list
    views: list
    counts: list

    @property
    def P(self) -> int:
        return int(self.values.shape[0])

    def subset(self, idx: torch.Tensor) -> "Observations":
        """The observations at ``idx`` (a ``[k]`` index or ``[P]`` bool mask)."""
        f = {k: getattr(self, k)[idx] for k in ("tri", "corners", "bary", "points", "to_eye", "values", "view", "pixel")}
        return dataclasses.replace(self, **f)

    def image(self, per_pixel: torch.Tensor, k: int, fill: float = 0.0) -> np.ndarray:
        """View ``k`` as an ``[H, W, C]`` float32 image of ``per_pixel [P, C]``, ``fill`` elsewhere."""
        H, W = self.shapes[k]
        img = np.full((H * W, per_pixel.shape[1]), fill, np.float32)
        sel = (self.view == k).numpy()
        img[self.pixel.numpy()[sel]] = per_pixel.detach().numpy()[sel]
        return img.reshape(H, W, -1)


def _sphere_in_frustum(view: CameraView, centre: np.ndarray, radius: float) -> bool:
    """Whether a sphere may be seen by ``view`` (conservative: False only when it lies wholly
    outside one of the four side planes or behind the camera)."""
    c = view.c2w[:3, :3].T @ (centre - view.eye)  # camera coordinates, looking down −z
    if -c[2] <= -radius:
        return False
    # side planes through the eye with inward normals (OpenGL axes: x right, y up)
    xs = (-view.cx / view.fx, (view.w - view.cx) / view.fx)
    ys = (-(view.h - view.cy) / view.fy, view.cy / view.fy)
    planes = [np.array([1.0, 0.0, xs[0]]), np.array([-1.0, 0.0, -xs[1]]), np.array([0.0, 1.0, ys[0]]), np.array([0.0, -1.0, -ys[1]])]
    return all(float(n @ c) / np.linalg.norm(n) > -radius for n in planes)


def _refine_hits(V: np.ndarray, F: np.ndarray, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Barycentrics ``[R, 3]`` and points ``[R, 3]`` of rays ``o + t d`` on the triangles ``F [R, 3]``
    Embree reported, recomputed in float64 (Möller & Trumbore 1997; Embree answers in float32)."""
    v0, e1, e2 = V[F[:, 0]], V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    det = np.where(np.abs(det) > 0, det, 1e-300)
    s = o - v0
    u = np.einsum("ij,ij->i", s, p) / det
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) / det
    B = np.stack([1 - u - v, u, v], 1)
    return B, (B[:, :, None] * np.stack([V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]], 1)).sum(1)


def observe(mesh, views: list[CameraView], images: list[np.ndarray], masks: list[np.ndarray], *,
            unknowns: int = 0, max_pixels: int | None = None, seed: int = 0, caster=None) -> Observations:
    """Trace every valid pixel of every view to the mesh in one batched Embree query
    (:meth:`prt_torch.scene.RayCaster.intersect`: first hit, its triangle and barycentrics).

    Pixels off the mesh or with alpha 0 are dropped, and so are pixels whose ray meets its
    triangle from behind (the side its vertex normals turn away from: the underside of an open
    ground plane), since the transfer describes the front side only — a one-sided surface, as
    Mitsuba renders it, is black there, a thin two-sided one lit otherwise (``counts``: ``back``
    per view). Checked before any ray is traced: each
    view's frustum meets the mesh's bounding sphere ("covers none of the mesh"), and the valid
    pixels (alpha > 0) outnumber ``unknowns``; after tracing, a view that sees none of the mesh
    and fewer hit pixels than ``unknowns`` are refused too. ``max_pixels``: a uniform random
    subset of that many hit pixels (``seed``), as Ramamoorthi 2002 §6.4.2 subsamples 12000.
    """
    from ..render.camera import bounding_sphere
    from ..scene import RayCaster

    if len(views) != len(images) or len(images) != len(masks):
        raise ValueError(f"{len(views)} cameras for {len(images)} images; accepted: one image per camera")
    centre, radius = bounding_sphere(mesh.vertices)
    for k, v in enumerate(views):
        if not _sphere_in_frustum(v, centre, radius):
            raise ValueError(f"image {str(v.file)!r} covers none of the mesh (its camera's view misses the mesh's bounding "
                             f"sphere, centre {np.round(centre, 4).tolist()}, radius {radius:.4g}); accepted: cameras that see the "
                             "mesh (same world frame as the mesh)")
    valid = sum(int(m.sum()) for m in masks)
    if valid < unknowns:
        raise ValueError(f"{valid} valid pixels (alpha > 0) for {unknowns} unknowns; accepted: more pixels than unknowns "
                         "(more or larger views, fewer --bands)")
    origins, dirs, vid, pix = [], [], [], []
    for k, (v, m) in enumerate(zip(views, masks)):
        r, c = np.nonzero(m)
        o, d = pixel_rays(v, r.astype(np.float64), c.astype(np.float64))
        origins.append(o)
        dirs.append(d)
        vid.append(np.full(r.shape, k, np.int64))
        pix.append(r.astype(np.int64) * m.shape[1] + c)
    o, d = np.concatenate(origins), np.concatenate(dirs)
    vid, pix = np.concatenate(vid), np.concatenate(pix)
    own = caster is None
    caster = RayCaster(mesh, workers=1) if own else caster
    try:
        hit, tri, bary, t = caster.intersect(o, d)
    finally:
        if own:
            caster.close()
    hit = np.asarray(hit, bool)
    back = np.zeros_like(hit)
    if hit.any():  # the transfer is the front side's: a ray that meets a face from behind sees the unmodelled back side
        tri_h = np.asarray(tri, np.int64)[hit]
        V = np.asarray(mesh.vertices, np.float64)
        F = np.asarray(mesh.faces, np.int64)[tri_h]
        ng = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
        ns = np.asarray(mesh.normals, np.float64)[F].sum(1)  # the side the vertex normals (and the transfer) face
        ng *= np.where(np.einsum("ij,ij->i", ng, ns) < 0, -1.0, 1.0)[:, None]
        back[np.nonzero(hit)[0]] = np.einsum("ij,ij->i", ng, d[hit]) > 0
    hit_front = hit & ~back
    counts = []
    for k, v in enumerate(views):
        n_hit = int(hit_front[vid == k].sum())
        counts.append({"masked": int((vid == k).sum()), "hit": n_hit, "back": int(back[vid == k].sum())})
        if n_hit == 0:
            raise ValueError(f"image {str(v.file)!r} covers none of the mesh (no pixel with alpha > 0 sees its front side; "
                             f"{counts[-1]['back']} see faces from behind); accepted: "
                             "views that show the object")
    sel = np.nonzero(hit_front)[0]
    if sel.size < unknowns:
        raise ValueError(f"{sel.size} pixels see the mesh for {unknowns} unknowns; accepted: more pixels than unknowns")
    if max_pixels is not None and sel.size > max_pixels:
        g = np.random.default_rng(seed)
        sel = np.sort(g.choice(sel, size=int(max_pixels), replace=False))
    tri_s = np.asarray(tri, np.int64)[sel]
    B, pts = _refine_hits(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)[tri_s], o[sel], d[sel])
    flat = np.concatenate([im.reshape(-1, 3) for im in images])  # every view's pixels, one after another
    offset = np.cumsum([0] + [im.shape[0] * im.shape[1] for im in images])[:-1]
    vals = flat[offset[vid[sel]] + pix[sel]]
    faces = torch.as_tensor(np.asarray(mesh.faces)).to(torch.int64)
    t_ = lambda a, dt=torch.float64: torch.as_tensor(np.ascontiguousarray(a)).to(dt)  # noqa: E731
    return Observations(tri=t_(tri_s, torch.int64), corners=faces[t_(tri_s, torch.int64)], bary=t_(B), points=t_(pts),
                        to_eye=t_(-d[sel]), values=t_(vals), view=t_(vid[sel], torch.int64),
                        pixel=t_(pix[sel], torch.int64), shapes=[m.shape for m in masks], views=list(views), counts=counts)
