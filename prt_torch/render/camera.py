"""Look-at cameras (perspective or orthographic) fitted to a mesh's bounding sphere.

World frame: right-handed, +z up. A camera at azimuth φ (from +x toward +y, as the lat-long
layout) and elevation ε (above the xy-plane) sits in direction
``(cos ε cos φ, cos ε sin φ, sin ε)`` from the target and looks at it with +z as "up" on screen.

Matrices follow OpenGL (``gluLookAt``, ``gluPerspective``, ``glOrtho``): eye space looks down −z,
clip space maps the view volume to NDC [−1, 1]³, and the window transform puts NDC x = −1 at
the left edge, y = +1 at the TOP edge of the returned image (row 0). Pixel (row r, column c) has
its centre at NDC ``x = (c + 0.5)/W·2 − 1``, ``y = 1 − (r + 0.5)/H·2``. They agree with
pyrender's ``PerspectiveCamera``/``OrthographicCamera`` (tested).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .._checks import check_choice, check_float

__all__ = ["Camera", "bounding_sphere", "look_at", "perspective", "orthographic"]


def _vec3(name: str, v) -> np.ndarray:
    a = np.asarray(v.detach().cpu().numpy() if hasattr(v, "detach") else v, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"{name}={v!r}; accepted: 3 finite numbers")
    return a


def look_at(eye, target, up) -> np.ndarray:
    """``[4,4] float64`` world -> eye matrix (``gluLookAt``): the camera at ``eye`` looks down −z
    toward ``target``, with ``up`` projected to +y."""
    eye, target, up = _vec3("eye", eye), _vec3("target", target), _vec3("up", up)
    f = target - eye
    if np.linalg.norm(f) == 0:
        raise ValueError("camera eye and target coincide; accepted: distinct points")
    f = f / np.linalg.norm(f)
    s = np.cross(f, up)
    if np.linalg.norm(s) < 1e-9 * max(np.linalg.norm(up), 1e-300):
        raise ValueError(f"camera up={up.tolist()} is parallel to the viewing direction {f.tolist()}; accepted: "
                         "an up vector not parallel to target − eye")
    s = s / np.linalg.norm(s)
    u = np.cross(s, f)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = s, u, -f
    m[:3, 3] = -m[:3, :3] @ eye
    return m


def perspective(fov_y_deg: float, aspect: float, near: float, far: float) -> np.ndarray:
    """``[4,4] float64`` clip-from-eye matrix of ``gluPerspective`` (vertical field of view)."""
    f = 1.0 / math.tan(math.radians(fov_y_deg) / 2)
    m = np.zeros((4, 4))
    m[0, 0], m[1, 1] = f / aspect, f
    m[2, 2], m[2, 3] = (far + near) / (near - far), 2 * far * near / (near - far)
    m[3, 2] = -1.0
    return m


def orthographic(height: float, aspect: float, near: float, far: float) -> np.ndarray:
    """``[4,4] float64`` clip-from-eye matrix of ``glOrtho`` for a view volume ``height`` world
    units tall and ``height·aspect`` wide, centred on the axis."""
    m = np.eye(4)
    m[0, 0], m[1, 1] = 2.0 / (height * aspect), 2.0 / height
    m[2, 2], m[2, 3] = -2.0 / (far - near), -(far + near) / (far - near)
    return m


def bounding_sphere(vertices) -> tuple[np.ndarray, float]:
    """(centre ``[3]`` float64, radius): the bounding-box centre and the largest vertex distance
    from it (a sphere containing every vertex; within √3 of the tightest)."""
    v = np.asarray(vertices.detach().cpu().numpy() if hasattr(vertices, "detach") else vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or v.shape[0] == 0:
        raise ValueError(f"vertices have shape {v.shape}; accepted: [V, 3] with V ≥ 1")
    c = 0.5 * (v.min(0) + v.max(0))
    return c, float(np.sqrt(((v - c) ** 2).sum(1).max()))


@dataclasses.dataclass
class Camera:
    """A look-at camera.

    Attributes:
        eye, target, up: world points/vector (float64 ``[3]``).
        projection: ``'perspective'`` (uses ``fov``, vertical, degrees) or ``'orthographic'``
            (uses ``ortho_height``, the full height of the view volume in world units).
        near, far: clip distances along the view axis (> 0 for perspective).
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray = dataclasses.field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    projection: str = "perspective"
    fov: float = 40.0
    ortho_height: float = 2.0
    near: float = 0.01
    far: float = 100.0

    def __post_init__(self):
        self.eye, self.target, self.up = _vec3("eye", self.eye), _vec3("target", self.target), _vec3("up", self.up)
        check_choice("projection", self.projection, ["perspective", "orthographic"])
        self.fov = check_float("fov", self.fov, 0.0, 180.0, lo_open=True, hi_open=True)
        self.ortho_height = check_float("ortho_height", self.ortho_height, 0.0, lo_open=True)
        if self.projection == "perspective":
            self.near = check_float("near", self.near, 0.0, lo_open=True)
        else:
            self.near = check_float("near", self.near)
        self.far = check_float("far", self.far, self.near, lo_open=True)
        look_at(self.eye, self.target, self.up)  # validates eye != target, up not parallel

    @classmethod
    def fit(cls, mesh, azimuth: float = 35.0, elevation: float = 25.0, fov: float = 40.0,
            projection: str = "perspective", margin: float = 1.05, aspect: float = 1.0) -> "Camera":
        """A camera at ``azimuth``/``elevation`` (degrees, see module doc) looking at the centre of
        ``mesh``'s bounding sphere (``mesh`` has ``.vertices [V,3]``, or is a ``[V,3]`` array),
        framing the sphere × ``margin`` in both directions of an image with width/height
        ``aspect``. Near/far enclose the sphere."""
        check_choice("projection", projection, ["perspective", "orthographic"])
        az = math.radians(check_float("azimuth", azimuth))
        el = math.radians(check_float("elevation", elevation, -90.0, 90.0))
        fov = check_float("fov", fov, 0.0, 180.0, lo_open=True, hi_open=True)
        margin = check_float("margin", margin, 0.0, lo_open=True)
        aspect = check_float("aspect", aspect, 0.0, lo_open=True)
        c, r = bounding_sphere(getattr(mesh, "vertices", mesh))
        r = r if r > 0 else 1.0
        rm = r * margin
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        up = np.array([0.0, 0.0, 1.0]) if abs(d[2]) < 0.999 else np.array([-math.cos(az), -math.sin(az), 0.0]) * np.sign(d[2])
        if np.linalg.norm(up) < 0.5:  # pragma: no cover - |d_z| ≥ 0.999 implies a horizontal azimuth vector
            up = np.array([0.0, 1.0, 0.0])
        if projection == "perspective":
            half_y = math.radians(fov) / 2
            half = min(half_y, math.atan(math.tan(half_y) * aspect))
            dist = rm / math.sin(half)
            near, far = max(dist - 1.2 * rm, dist * 1e-4), dist + 1.2 * rm
            return cls(c + dist * d, c, up, "perspective", fov=fov, near=near, far=far)
        dist = 3.0 * rm
        height = 2.0 * rm * max(1.0, 1.0 / aspect)
        return cls(c + dist * d, c, up, "orthographic", fov=fov, ortho_height=height, near=dist - 1.2 * rm,
                   far=dist + 1.2 * rm)

    def view_matrix(self) -> np.ndarray:
        """``[4,4] float64`` world -> eye."""
        return look_at(self.eye, self.target, self.up)

    def projection_matrix(self, aspect: float) -> np.ndarray:
        """``[4,4] float64`` eye -> clip for an image of width/height ``aspect``."""
        if self.projection == "perspective":
            return perspective(self.fov, aspect, self.near, self.far)
        return orthographic(self.ortho_height, aspect, self.near, self.far)

    def clip_matrix(self, width: int, height: int) -> np.ndarray:
        """``[4,4] float64`` world -> clip (projection · view) for a ``width``×``height`` image."""
        return self.projection_matrix(width / height) @ self.view_matrix()

    def project(self, points, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """Pixel coordinates of world ``points [N,3]``: (``[N,2]`` float64 (x = column, y = row,
        continuous, pixel centres at +0.5, row 0 at the top), ``[N]`` NDC depth in [−1, 1])."""
        p = np.asarray(points.detach().cpu().numpy() if hasattr(points, "detach") else points, dtype=np.float64)
        h = np.concatenate([p.reshape(-1, 3), np.ones((p.reshape(-1, 3).shape[0], 1))], 1) @ self.clip_matrix(width, height).T
        ndc = h[:, :3] / h[:, 3:4]
        xy = np.stack([(ndc[:, 0] + 1) * 0.5 * width, (1 - ndc[:, 1]) * 0.5 * height], 1)
        return xy, ndc[:, 2]
