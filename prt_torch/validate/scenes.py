"""The Mitsuba side of the validation (docs/validate.md): importing Mitsuba 3 (an optional
dependency), the scenes both comparisons share — the light image as an ``envmap`` and the
transfer's mesh, flat-shaded, one-sided Lambertian with its vertex albedo — and the probes
placed in them: for diffuse transfer an ``irradiancemeter`` on a tiny black disk at the engine's
ray origin (:func:`mitsuba_exit_radiance`, :mod:`prt_torch.validate.diffuse`); for glossy exit
transfer the engine's BRDF as a Mitsuba BSDF written in Python (:func:`engine_bsdf`) on such a
disk, seen by a ``radiancemeter`` along a view (:func:`mitsuba_glossy_exit`,
:mod:`prt_torch.validate.glossy`).

Mitsuba is an optional dependency (``pip install 'prt-torch[validate]'``); without it
:func:`require_mitsuba` raises :class:`ValidatorUnavailable` with that one line.
"""
from __future__ import annotations

import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .._checks import check_int
from ..scene import Mesh
from ..transfer.diffuse import offset_origins

__all__ = ["ValidatorUnavailable", "INSTALL_HINT", "VARIANT", "require_mitsuba", "mitsuba_exit_radiance", "BSDF_PLUGIN", "engine_bsdf",
           "mitsuba_glossy_exit", "mitsuba_views", "MITSUBA_DIAGONAL", "MITSUBA_FRAMES", "mitsuba_frame", "MITSUBA_PROBE_TMIN"]

INSTALL_HINT = "prt validate needs Mitsuba 3: pip install 'prt-torch[validate]' (or: pip install 'mitsuba>=3.5')"
VARIANT = "scalar_rgb"


#: the bounding-box diagonal of the scene as Mitsuba is given it (``frame='normalized'``)
MITSUBA_DIAGONAL = 20.0
#: how Mitsuba is given the scene: 'normalized' (centred, scaled to :data:`MITSUBA_DIAGONAL`) or
#: 'as_is' (the mesh's own units; what the validator did before issue 37)
MITSUBA_FRAMES = ("normalized", "as_is")
#: measured (tests/test_validate.py::test_mitsuba_probe_blind_distance): Mitsuba 3 (``scalar_rgb``) does
#: not see a surface closer than about this many scene units to an ``irradiancemeter`` disk, wherever the disk is
MITSUBA_PROBE_TMIN = 1e-4


def mitsuba_frame(mesh: Mesh | None, frame: str = "normalized") -> tuple[np.ndarray, float]:
    """``(centre [3] float64, scale)``: Mitsuba sees the point x at ``(x − centre)·scale``.

    Mitsuba's epsilons are absolute, in scene units: rays leaving an ``irradiancemeter`` disk
    ignore surfaces closer than :data:`MITSUBA_PROBE_TMIN` (~1e-4 units), and the disk's own
    rays hit it again once its coordinates are large enough that their float32 rounding
    exceeds that. The engine's ray offset is relative (eps = ``offset`` × the bounding-box
    diagonal: 2e-5 for a 0.2-unit scan), so in a small mesh's own units Mitsuba sees through
    surfaces within a few engine eps of a vertex — fins, folds and non-manifold sheets next to
    it; in large units it darkens. Measured on ``scan_like`` (200 vertices, B = 2;
    reports/benchmarks/scan_validate.md): interreflected engine/Mitsuba 1.092 at 0.08× the
    mesh's size, 1.023 at 1×, 1.002 at 10× in its own units, 1.004 / 1.001 / 1.001 normalised;
    normalised to a diagonal of 3: 1.030, 10 and 30: 0.993, 100: 1.005, 1000: 1.045 (direct
    1.011; docs/validate.md). 'normalized' centres the
    mesh's bounding box and scales its diagonal to :data:`MITSUBA_DIAGONAL` (20, the plateau):
    the probe's blind distance is then 5% of the engine's default eps and coordinates stay
    below 10 units, whatever the mesh's units. Irradiance and radiance are unchanged by a
    similarity transform (the environment is at infinity). 'as_is' (or no mesh) gives the
    identity."""
    from .._checks import check_choice

    check_choice("mitsuba_frame", frame, list(MITSUBA_FRAMES))
    if mesh is None or frame == "as_is":
        return np.zeros(3), 1.0
    v = mesh.vertices.to(torch.float64).numpy()
    lo, hi = v.min(0), v.max(0)
    diag = float(np.linalg.norm(hi - lo))
    return 0.5 * (lo + hi), (MITSUBA_DIAGONAL / diag if diag > 0 else 1.0)


class ValidatorUnavailable(RuntimeError):
    """Mitsuba 3 is not installed (the message says how to install it)."""


def require_mitsuba():
    """Import Mitsuba 3 and set the ``scalar_rgb`` variant; raise :class:`ValidatorUnavailable`
    with :data:`INSTALL_HINT` when it is missing."""
    try:
        import mitsuba as mi
    except ImportError:
        raise ValidatorUnavailable(INSTALL_HINT) from None
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    return mi


def _write_ply(path: Path, mesh: Mesh, centre: np.ndarray, scale: float) -> None:
    v = ((mesh.vertices.to(torch.float64).numpy() - centre) * scale).astype("<f4")
    c = mesh.albedo.numpy().astype("<f4")
    f = mesh.faces.numpy()
    hdr = ("ply\nformat binary_little_endian 1.0\n"
           f"element vertex {v.shape[0]}\nproperty float x\nproperty float y\nproperty float z\n"
           "property float r\nproperty float g\nproperty float b\n"
           f"element face {f.shape[0]}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    fd = np.zeros(f.shape[0], dtype=[("n", "u1"), ("i", "<i4", (3,))])
    fd["n"], fd["i"] = 3, f
    with open(path, "wb") as fh:
        fh.write(hdr)
        fh.write(np.concatenate([v, c], 1).tobytes())
        fh.write(fd.tobytes())


def _base_scene(mi, image: np.ndarray, mesh: Mesh | None, tmp: Path, centre: np.ndarray, scale: float,
                face_normals: bool = True, bsdf: dict | None = None) -> dict[str, Any]:
    """The Mitsuba scene both measurements share: the light image as ``envmap`` and (if given)
    the mesh, flat-shaded (``face_normals``; False: Mitsuba's interpolated vertex normals),
    one-sided Lambertian with its vertex albedo (written to ``tmp``) or the Mitsuba BSDF dict
    ``bsdf``, in the frame of :func:`mitsuba_frame` (``centre``, ``scale``)."""
    scene: dict[str, Any] = {"type": "scene", "env": {"type": "envmap", "bitmap": mi.Bitmap(np.ascontiguousarray(image, np.float32))}}
    if mesh is not None:
        ply = tmp / "mesh.ply"
        _write_ply(ply, mesh, centre, scale)
        scene["mesh"] = {"type": "ply", "filename": str(ply), "face_normals": bool(face_normals),
                         "bsdf": bsdf or {"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}}
    return scene


def _probe(mi, p: np.ndarray, n: np.ndarray, radius: float, spp: int) -> dict:
    up = (0.0, 0.0, 1.0) if abs(n[2]) < 0.9 else (1.0, 0.0, 0.0)
    T = mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(*p), target=mi.ScalarPoint3f(*(p + n)), up=mi.ScalarVector3f(*up))
    sensor = mi.load_dict({"type": "irradiancemeter",
                           "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                           "sampler": {"type": "independent", "sample_count": int(spp)}})
    return {"type": "disk", "to_world": T @ mi.ScalarTransform4f().scale(radius),
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.0, 0.0, 0.0]}}, "sensor": sensor}


def mitsuba_exit_radiance(mesh: Mesh | None, points: Any, normals: Any, image: np.ndarray, depths: list[int], spp: int = 1024,
                          batches: int = 8, eps: float = 1e-4, seed: int = 0, albedo: Any = None,
                          nudge: Any = None, frame: str = "normalized") -> dict[str, torch.Tensor]:
    """Mitsuba 3 path-traced irradiance at probe points (:mod:`prt_torch.validate.diffuse`).

    Args:
        mesh: the scene (flat-shaded, one-sided Lambertian, ``mesh.albedo``); None = only the
            environment.
        points, normals: ``[P, 3]``; each probe is centred at p + eps·n (+ eps·nudge) facing n —
            the engine's ray origin (:func:`prt_torch.transfer.diffuse.offset_origins`).
        nudge: optional ``[P, 3]`` :func:`prt_torch.transfer.diffuse.boundary_nudge` rows.
        image: ``[H, 2H, 3]`` environment radiance on Mitsuba's lat-long grid (:func:`light_image`).
        depths: ``path`` integrator ``max_depth`` values (1 = direct light only).
        spp: samples per probe and depth, split over ``batches`` independent renders.
        albedo: ``[P, C]`` exit albedo of the probes (exit radiance = albedo/π × irradiance);
            None = 1.
        frame: the units Mitsuba is given the scene in (:func:`mitsuba_frame`; 'normalized':
            centred, diagonal :data:`MITSUBA_DIAGONAL`, so that Mitsuba's absolute epsilons
            are negligible whatever the mesh's units).
    Returns:
        ``{'irradiance': [D, P, 3], 'irradiance_se': [D, P, 3], 'radiance': [D, P, 3],
        'radiance_se': [D, P, 3]}`` float64 (standard errors of the batch means), and
        ``'diff_se'`` ``[D, P, 3]``: the standard error of depth d minus depth 0 (same seeds).
    """
    mi = require_mitsuba()
    P = torch.as_tensor(points, dtype=torch.float64).numpy()
    N = torch.as_tensor(normals, dtype=torch.float64)
    N = (N / N.norm(dim=-1, keepdim=True)).numpy()
    centre, scale = mitsuba_frame(mesh, frame)
    C = (offset_origins(P, N, eps, None if nudge is None else torch.as_tensor(nudge, dtype=torch.float64).numpy()) - centre) * scale
    batches = check_int("batches", batches, 2)
    per = max(1, int(spp) // batches)
    radius = max(eps * scale * 1e-2, 1e-7)
    with tempfile.TemporaryDirectory() as tmp:
        scene = _base_scene(mi, image, mesh, Path(tmp), centre, scale)
        for k in range(P.shape[0]):  # scene description, one probe per vertex (Mitsuba builds the scene once)
            scene[f"probe_{k:06d}"] = _probe(mi, C[k], N[k], radius, per)
        sc = mi.load_dict(scene)
    sensors = sc.sensors()
    if len(sensors) != P.shape[0]:  # pragma: no cover - Mitsuba always keeps them in order
        raise RuntimeError("Mitsuba did not keep one sensor per probe")
    out = np.zeros((len(depths), batches, P.shape[0], 3))
    for di, depth in enumerate(depths):
        integ = mi.load_dict({"type": "path", "max_depth": int(depth), "rr_depth": 1000})
        for k in range(P.shape[0]):  # Mitsuba renders one sensor per call (C++ inside, spp samples each)
            for b in range(batches):
                sd = (int(seed) * 7919 + b * 100003 + k * 1009) % (1 << 31)  # independent per probe and batch
                out[di, b, k] = np.asarray(mi.render(sc, sensor=k, integrator=integ, spp=per, seed=sd)).reshape(-1)[:3]
    E = torch.from_numpy(out)
    mean = E.mean(1)
    se = E.std(1, unbiased=True) / math.sqrt(batches)
    diff_se = (E - E[:1]).std(1, unbiased=True) / math.sqrt(batches)
    a = torch.ones(P.shape[0], 3, dtype=torch.float64) if albedo is None else torch.as_tensor(albedo, dtype=torch.float64)
    a = (a.expand(-1, 3) if a.shape[1] == 1 else a) / math.pi
    return {"irradiance": mean, "irradiance_se": se, "radiance": mean * a, "radiance_se": se * a, "diff_se": diff_se * a}


_BSDF_CLASS: Any = None
BSDF_PLUGIN = "prt_engine_brdf"


def _bsdf_class(mi):
    """The Mitsuba BSDF (written in Python, registered once as ``prt_engine_brdf``) that
    evaluates an engine :class:`prt_torch.brdf.BRDF` in a given local frame."""
    global _BSDF_CLASS
    if _BSDF_CLASS is not None:
        return _BSDF_CLASS

    class EngineBRDF(mi.BSDF):
        """f_r of an engine BRDF in the frame ``self.frame`` (rows t, b, n, world), so anisotropic
        models keep the engine's tangent; ``eval`` returns f_r(wi, wo)·cos θ_i (Mitsuba's
        convention: its ``wo`` is the engine's wi, towards the light; its ``si.wi`` is the
        engine's wo, towards the viewer); ``sample`` draws a cosine-weighted direction about
        the shading normal (pdf cos θ/π, positive wherever f_r·cos is), so estimates are
        unbiased whatever the lobe."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            flags = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            self.m_components = [flags]
            self.m_flags = flags
            self.brdf = None
            self.frame = np.eye(3)

        def _local(self, si, d) -> np.ndarray:
            w = si.to_world(d)
            return self.frame @ np.array([float(w[0]), float(w[1]), float(w[2])])

        def _f_cos(self, si, wo) -> float:
            a, b = self._local(si, wo), self._local(si, si.wi)  # towards the light, towards the viewer
            if a[2] <= 0 or b[2] <= 0:
                return 0.0
            a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
            f = float(self.brdf.eval(torch.from_numpy(a)[None], torch.from_numpy(b)[None]).reshape(-1)[0])
            return f * float(a[2])

        def eval(self, ctx, si, wo, active=True):
            return mi.Color3f(self._f_cos(si, wo))

        def pdf(self, ctx, si, wo, active=True):
            return mi.warp.square_to_cosine_hemisphere_pdf(wo) if float(mi.Frame3f.cos_theta(si.wi)) > 0 else mi.Float(0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            bs = mi.BSDFSample3f()
            if float(mi.Frame3f.cos_theta(si.wi)) <= 0:
                return bs, mi.Color3f(0.0)
            wo = mi.warp.square_to_cosine_hemisphere(sample2)
            pdf = float(mi.warp.square_to_cosine_hemisphere_pdf(wo))
            bs.wo, bs.pdf, bs.eta = wo, pdf, 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.GlossyReflection)
            bs.sampled_component = 0
            return bs, mi.Color3f(self._f_cos(si, wo) / pdf if pdf > 0 else 0.0)

        def to_string(self):
            return f"EngineBRDF[{self.brdf!r}]"

    mi.register_bsdf(BSDF_PLUGIN, lambda props: EngineBRDF(props))
    _BSDF_CLASS = EngineBRDF
    return EngineBRDF


def engine_bsdf(brdf: Any, frame: Any):
    """A Mitsuba BSDF object evaluating the engine BRDF ``brdf`` (one material) in the local
    frame ``frame`` ``[3, 3]`` (rows t, b, n in world coordinates)."""
    mi = require_mitsuba()
    _bsdf_class(mi)
    obj = mi.load_dict({"type": BSDF_PLUGIN})
    obj.brdf = brdf
    obj.frame = torch.as_tensor(frame, dtype=torch.float64).numpy()
    return obj


def _frame_transform(mi, frame: np.ndarray, centre: np.ndarray, scale: float):
    m = np.eye(4)
    m[:3, :3] = frame.T * scale  # columns t, b, n: the disk's local x, y, z (normal)
    m[:3, 3] = centre
    return mi.ScalarTransform4f(m.tolist())


def mitsuba_glossy_exit(mesh: Mesh | None, points: Any, frames: Any, views: Any, brdfs: list, image: np.ndarray, spp: int = 1024,
                        batches: int = 8, eps: float = 1e-4, seed: int = 0, nudge: Any = None,
                        max_depth: int = 2, depths: list[int] | None = None, frame: str = "normalized") -> dict[str, torch.Tensor]:
    """Mitsuba 3 exit radiance of the engine's BRDF at probe points towards world views.

    Each probe is a one-sided disk (radius ``1e-2·eps``) centred at the engine's ray origin
    p + eps·n (+ eps·nudge), its local frame the vertex frame ``frames[k]`` (rows t, b, n), with
    :func:`engine_bsdf` ``brdfs[k]``; a ``radiancemeter`` at distance eps along ``views[k]``
    looks back at its centre. ``max_depth`` 2: the disk plus one segment to the environment
    (direct light; the mesh only occludes); ``depths`` = [2, B+2] adds B bounces off the mesh
    (one-sided Lambertian, ``mesh.albedo``). ``frame``: the units Mitsuba is given the scene in
    (:func:`mitsuba_frame`). Returns ``{'radiance': [P, 3], 'radiance_se': [P, 3]}``
    float64 (standard error of the mean of ``batches`` renders) for ``max_depth``; with ``depths``
    ``[D, P, 3]`` each and ``'diff_se'`` (depth d minus the first, same seeds)."""
    mi = require_mitsuba()
    P = torch.as_tensor(points, dtype=torch.float64).numpy()
    F = torch.as_tensor(frames, dtype=torch.float64).numpy()
    Vw = torch.as_tensor(views, dtype=torch.float64)
    Vw = (Vw / Vw.norm(dim=-1, keepdim=True)).numpy()
    centre, scale = mitsuba_frame(mesh, frame)
    C = (offset_origins(P, F[:, 2], eps, None if nudge is None else torch.as_tensor(nudge, dtype=torch.float64).numpy()) - centre) * scale
    batches = check_int("batches", batches, 2)
    per = max(1, int(spp) // batches)
    radius = max(eps * scale * 1e-2, 1e-7)
    with tempfile.TemporaryDirectory() as tmp:
        scene = _base_scene(mi, image, mesh, Path(tmp), centre, scale)
        for k in range(P.shape[0]):
            scene[f"probe_{k:06d}"] = {"type": "disk", "to_world": _frame_transform(mi, F[k], C[k], radius),
                                       "bsdf": engine_bsdf(brdfs[k], F[k])}
            o = C[k] + eps * scale * Vw[k]
            up = F[k, 0] if abs(float(F[k, 0] @ Vw[k])) < 0.9 else F[k, 1]
            scene[f"sensor_{k:06d}"] = {
                "type": "radiancemeter",
                "to_world": mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(*o), target=mi.ScalarPoint3f(*C[k]),
                                                           up=mi.ScalarVector3f(*up)),
                "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}, "pixel_format": "rgb"},
                "sampler": {"type": "independent", "sample_count": per}}
        sc = mi.load_dict(scene)
    sensors = sc.sensors()
    if len(sensors) != P.shape[0]:  # pragma: no cover
        raise RuntimeError("Mitsuba did not keep one sensor per probe")
    ds = [int(max_depth)] if depths is None else [int(d) for d in depths]
    out = np.zeros((len(ds), batches, P.shape[0], 3))
    for di, depth in enumerate(ds):
        integ = mi.load_dict({"type": "path", "max_depth": depth, "rr_depth": 1000})
        for k in range(P.shape[0]):
            for b in range(batches):
                sd = (int(seed) * 7919 + b * 100003 + k * 1009) % (1 << 31)
                out[di, b, k] = np.asarray(mi.render(sc, sensor=k, integrator=integ, spp=per, seed=sd)).reshape(-1)[:3]
    R = torch.from_numpy(out)
    mean, se = R.mean(1), R.std(1, unbiased=True) / math.sqrt(batches)
    if depths is None:
        return {"radiance": mean[0], "radiance_se": se[0]}
    return {"radiance": mean, "radiance_se": se, "diff_se": (R - R[:1]).std(1, unbiased=True) / math.sqrt(batches)}


def mitsuba_views(mesh: Mesh, views: list, image: np.ndarray, spp: int = 64, max_depth: int = 2, seed: int = 0,
                  face_normals: bool = False, frame: str = "normalized", bsdf: dict | None = None) -> list[np.ndarray]:
    """Mitsuba 3 path-traced images of ``mesh`` (one-sided Lambertian, ``mesh.albedo``) under the
    environment ``image`` ``[H, 2H, 3]`` (:func:`prt_torch.validate.lights.light_image`), seen by
    resolved :class:`prt_torch.inverse.CameraView` s (``transforms.json``'s OpenGL camera-to-world
    matrix, square pixels, centred principal point) — the independent renderer of the inverse
    rendering tests (docs/inverse.md).

    The camera is Mitsuba's ``perspective`` sensor looking from the view's eye down its −z with
    its +y up, horizontal field of view 2·atan(w / 2 fx), box pixel filter (each pixel the mean
    over its footprint; the engine's pixel is its centre: a second-order difference on smooth
    shading). ``max_depth`` 2: direct light with shadows (the engine's ``bounces=0``); B + 2: B
    bounces. ``bsdf``: a Mitsuba BSDF dict for the mesh instead of its Lambertian albedo (e.g. a
    plugin registered with ``mi.register_bsdf``: tests/test_inverse_mitsuba_phong.py). Returns per
    view ``[h, w, 4]`` float32: linear RGB and the pixel's coverage of the mesh (1 inside,
    fractional on silhouettes, 0 on the background; the env's radiance there).
    """
    mi = require_mitsuba()
    centre, scale = mitsuba_frame(mesh, frame)
    out = []
    with tempfile.TemporaryDirectory() as tmp:
        sd = _base_scene(mi, image, mesh, Path(tmp), centre, scale, face_normals=face_normals, bsdf=bsdf)
        # hide_emitters: the background is transparent, so alpha is the pixel's coverage of the mesh (else 1 everywhere)
        sd["integrator"] = {"type": "path", "max_depth": int(max_depth), "rr_depth": 1000, "hide_emitters": True}
        sc = mi.load_dict(sd)
        for k, v in enumerate(views):
            if abs(v.fx - v.fy) > 1e-9 * v.fx or abs(v.cx - 0.5 * v.w) > 1e-9 * v.w or abs(v.cy - 0.5 * v.h) > 1e-9 * v.h:
                raise ValueError(f"view {k}: fx={v.fx}, fy={v.fy}, cx={v.cx}, cy={v.cy} for {v.w}x{v.h}; accepted: square "
                                 "pixels and a centred principal point (Mitsuba's perspective sensor)")
            R = v.c2w[:3, :3]
            eye = (v.eye - centre) * scale
            sensor = mi.load_dict({
                "type": "perspective", "fov": math.degrees(2 * math.atan(0.5 * v.w / v.fx)), "fov_axis": "x",
                "near_clip": 1e-3, "far_clip": 1e4,
                "to_world": mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(*eye), target=mi.ScalarPoint3f(*(eye - R[:, 2])),
                                                           up=mi.ScalarVector3f(*R[:, 1])),
                "film": {"type": "hdrfilm", "width": int(v.w), "height": int(v.h), "rfilter": {"type": "box"}, "pixel_format": "rgba"},
                "sampler": {"type": "independent", "sample_count": int(spp)}})
            sd_k = (int(seed) * 7919 + k * 1009) % (1 << 31)
            out.append(np.asarray(mi.render(sc, sensor=sensor, spp=int(spp), seed=sd_k), dtype=np.float32))
    return out
