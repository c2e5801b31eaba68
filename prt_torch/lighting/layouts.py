"""Image layouts of environment maps: pixel <-> direction, exact per-pixel solid angles, frames.

World frame (everywhere in prt_torch): right-handed, **+z is up**. For the layouts that have a
"view" (angular map, cube crosses, cube faces) the viewer stands at the origin looking
**forward = +y**, with **up = +z** and **right = forward × up = +x**. Every layout below puts the
top of the image towards +z, so an ordinary light probe needs no rotation at load.

Pixel (row i, column j) covers the continuous image coordinates y ∈ [i, i+1], x ∈ [j, j+1]
(y down the rows, x along the columns); its centre is (i + ½, j + ½). The mappings below are
functions of continuous (y, x); pixel-centre directions are their values at the centres.

* ``latlong`` (equirectangular, H × 2H; pbrt-v3's convention, the same grid as
  :func:`prt_torch.sh.latlong_grid`): θ = π y / H from +z, φ = 2π x / W measured from +x
  towards +y,  d = (sin θ cos φ, sin θ sin φ, cos θ). Row 0 is the zenith, the left edge is
  +x, a quarter of the way across is +y, the middle column is -x. (Seen from inside the
  sphere this image is mirrored left-right, as in pbrt.)  Solid angle of a pixel, exact:
  Δφ (cos θ0 - cos θ1).
* ``angular`` (Debevec's light-probe "angular map", N × N): a = 2x/N - 1 (right),
  b = 1 - 2y/N (up), r = √(a²+b²) ≤ 1; the angle from forward is ψ = π r, and
  d = cos ψ · F + sin ψ · (a·R + b·U)/r  with F = +y, R = +x, U = +z. Centre = forward (+y),
  the rim circle = backward (-y); it is Debevec's formula (centre -z, up +y, right +x, in a
  y-up frame) followed by the standard y-up -> z-up rotation (x, y, z) -> (x, -z, y), so probes
  from his site load with no ``up``. Solid angle density dΩ = π sin(π r)/r da db (it vanishes
  continuously at the rim); per pixel it is integrated by an s×s midpoint rule over
  pixel ∩ disk (s = 8); pixels wholly outside the disk have Ω = 0 and are masked out.
* cube maps: each face is an N × N square seen from inside, with a face normal n, an image
  "right" r and image "up" u (r = n × u): pixel coords a = 2x'/N - 1, b = 1 - 2y'/N inside the
  face, d ∝ n + a r + b u. Faces (n; r; u):

      +x: (+x; -y; +z)   -x: (-x; +y; +z)   +y (front): (+y; +x; +z)   -y (back): (-y; -x; +z)
      +z (up): (+z; +x; -y)                 -z (down): (-z; +x; +y)

  Exact solid angle of a pixel [a0,a1]×[b0,b1] on the face plane at distance 1:
  Ω = F(a1,b1) - F(a0,b1) - F(a1,b0) + F(a0,b0), F(a, b) = atan2(a b, √(a² + b² + 1)).

  ``hcross`` (4N wide × 3N tall) and ``vcross`` (3N wide × 4N tall), tiles (row, col)::

        hcross:           vcross:
        .  +z .  .        .  +z .
        -x +y +x -y       -x +y +x
        .  -z .  .        .  -z .
                          .  -y*.        (* back face rotated 180°: r = +x, u = -z)

  i.e. the cube unfolded around the front face as a viewer inside sees it (HDRShop's crosses).
  Blank tiles are masked out (Ω = 0). ``faces``: six separate N × N images in the order
  (+x, -x, +y, -y, +z, -z) with the orientations above; in memory they are kept side by side
  as an N × 6N strip.

Loading can rotate: world direction = R_rotation · R_up · d_file (see :func:`up_rotation`,
:func:`euler_matrix`, :func:`resolve_rotation`).
"""
from __future__ import annotations

import math
from typing import Any, Sequence

import torch

from .._checks import check_choice, check_finite, check_int, describe

__all__ = [
    "LAYOUTS",
    "FACE_NAMES",
    "FORWARD",
    "detect_layout",
    "layout_shape",
    "layout_size",
    "pixel_to_dir",
    "dir_to_pixel",
    "pixel_directions",
    "solid_angles",
    "cube_face_solid_angles",
    "valid_mask",
    "up_rotation",
    "euler_matrix",
    "resolve_rotation",
]

LAYOUTS = ("latlong", "angular", "vcross", "hcross", "faces")
#: face order of the ``faces`` layout and of file patterns ``{face}`` (px = +x, nx = -x, ...)
FACE_NAMES = ("px", "nx", "py", "ny", "pz", "nz")
FORWARD = (0.0, 1.0, 0.0)
_RIGHT = (1.0, 0.0, 0.0)
_UP = (0.0, 0.0, 1.0)

# face k: (normal, right, up), k in the FACE_NAMES order
_FACES = (
    ((1, 0, 0), (0, -1, 0), (0, 0, 1)),
    ((-1, 0, 0), (0, 1, 0), (0, 0, 1)),
    ((0, 1, 0), (1, 0, 0), (0, 0, 1)),
    ((0, -1, 0), (-1, 0, 0), (0, 0, 1)),
    ((0, 0, 1), (1, 0, 0), (0, -1, 0)),
    ((0, 0, -1), (1, 0, 0), (0, 1, 0)),
)
_BACK_ROT = ((0, -1, 0), (1, 0, 0), (0, 0, -1))  # -y face in vcross, rotated 180 degrees
# tiles: (tiles_w, tiles_h, [(row, col, face index, (n, r, u))])
_TILES = {
    "hcross": (4, 3, [(0, 1, 4, _FACES[4]), (1, 0, 1, _FACES[1]), (1, 1, 2, _FACES[2]),
                      (1, 2, 0, _FACES[0]), (1, 3, 3, _FACES[3]), (2, 1, 5, _FACES[5])]),
    "vcross": (3, 4, [(0, 1, 4, _FACES[4]), (1, 0, 1, _FACES[1]), (1, 1, 2, _FACES[2]),
                      (1, 2, 0, _FACES[0]), (2, 1, 5, _FACES[5]), (3, 1, 3, _BACK_ROT)]),
    "faces": (6, 1, [(0, k, k, _FACES[k]) for k in range(6)]),
}
_ASPECT = {"latlong": (2, 1), "angular": (1, 1), "vcross": (3, 4), "hcross": (4, 3), "faces": (6, 1)}
ANGULAR_SUBSAMPLES = 8


def _check_layout(layout: str) -> str:
    return check_choice("layout", layout, LAYOUTS)


def detect_layout(height: int, width: int, source: str = "image") -> str:
    """Layout from the aspect ratio: 2:1 latlong, 1:1 angular, 3:4 vcross, 4:3 hcross, 6:1 faces strip.

    Raises ValueError naming ``source`` when W:H fits none of them (the fix: name ``layout=``
    explicitly, or convert the image)."""
    for name in ("latlong", "angular", "vcross", "hcross", "faces"):
        aw, ah = _ASPECT[name]
        if width * ah == height * aw and width % aw == 0:
            return name
    raise ValueError(
        f"{source}: a {width}x{height} (WxH) image fits no environment-map layout; accepted aspect "
        "ratios W:H are 2:1 (latlong), 1:1 (angular), 3:4 (vcross), 4:3 (hcross), 6:1 (faces strip), "
        "or six square face files via a '{face}' pattern / list of 6 paths"
    )


def layout_shape(layout: str, size: int) -> tuple[int, int]:
    """(H, W) of a layout at base ``size``: latlong H = size (W = 2·size); angular size×size;
    cubes: face edge = size (vcross 4N×3N, hcross 3N×4N, faces N×6N as (H, W))."""
    _check_layout(layout)
    size = check_int("size", size, 1, 1 << 15)
    aw, ah = _ASPECT[layout]
    if layout == "latlong":
        return size, 2 * size
    return ah * size, aw * size


def layout_size(layout: str, height: int, width: int, source: str = "image") -> int:
    """Inverse of :func:`layout_shape`; raises if (H, W) does not fit ``layout``."""
    _check_layout(layout)
    aw, ah = _ASPECT[layout]
    if layout == "latlong":
        ok, n = width == 2 * height, height
    else:
        ok, n = width * ah == height * aw and width % aw == 0, width // aw
    if not ok or n < 1:
        raise ValueError(
            f"{source}: a {width}x{height} (WxH) image does not fit layout={layout!r}, which needs W:H = {aw}:{ah}; "
            f"pass the right layout or omit it to auto-detect"
        )
    return n


def _t(v, dtype=torch.float64) -> torch.Tensor:
    return torch.tensor(v, dtype=dtype)


def _cube_tables(layout: str):
    tw, th, tiles = _TILES[layout]
    tile_id = torch.full((th, tw), -1, dtype=torch.long)
    nru = torch.zeros(len(tiles), 3, 3, dtype=torch.float64)
    rows = torch.zeros(len(tiles), dtype=torch.long)
    cols = torch.zeros(len(tiles), dtype=torch.long)
    face_of = torch.zeros(len(tiles), dtype=torch.long)
    for t, (r, c, f, frame) in enumerate(tiles):  # six tiles: a tiny setup loop
        tile_id[r, c] = t
        nru[t] = _t(frame)
        rows[t], cols[t], face_of[t] = r, c, f
    return tw, th, tile_id, nru, rows, cols, face_of


def pixel_to_dir(layout: str, height: int, width: int, y: torch.Tensor, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Directions at continuous image coordinates (in the file frame, before any rotation).

    Args:
        y, x: float64 tensors of the same shape ``[*S]`` (pixel centres are i + ½, j + ½).
    Returns:
        (dirs ``[*S, 3]`` float64 unit vectors, valid ``[*S]`` bool). Invalid points (outside the
        angular disk, blank cross tiles) get the direction of the nearest meaningful point
        (angular: the backward pole) or +z (blank tiles).
    """
    _check_layout(layout)
    y = y.to(torch.float64)
    x = x.to(torch.float64)
    if layout == "latlong":
        theta = (y / height).clamp(0, 1) * math.pi
        phi = x * (2 * math.pi / width)
        s = torch.sin(theta)
        d = torch.stack([s * torch.cos(phi), s * torch.sin(phi), torch.cos(theta)], -1)
        return d, torch.ones_like(y, dtype=torch.bool)
    if layout == "angular":
        a = 2 * x / width - 1
        b = 1 - 2 * y / height
        r = torch.sqrt(a * a + b * b)
        psi = math.pi * r.clamp(max=1.0)
        sr = torch.where(r > 0, torch.sin(psi) / r.clamp_min(1e-300), torch.full_like(r, math.pi))
        # sin(ψ)/r -> π as r -> 0
        F, R, U = _t(FORWARD), _t(_RIGHT), _t(_UP)
        d = torch.cos(psi)[..., None] * F + (sr * a)[..., None] * R + (sr * b)[..., None] * U
        d = d / d.norm(dim=-1, keepdim=True)
        return d, r <= 1.0
    tw, th, tile_id, nru, rows, cols, _ = _cube_tables(layout)
    n = width // tw
    ti = (y / n).floor().long().clamp(0, th - 1)
    tj = (x / n).floor().long().clamp(0, tw - 1)
    t = tile_id[ti, tj]
    valid = t >= 0
    tt = t.clamp_min(0)
    a = 2 * (x - tj * n) / n - 1
    b = 1 - 2 * (y - ti * n) / n
    f = nru[tt]  # [*S, 3(n,r,u), 3]
    d = f[..., 0, :] + a[..., None] * f[..., 1, :] + b[..., None] * f[..., 2, :]
    d = d / d.norm(dim=-1, keepdim=True)
    d = torch.where(valid[..., None], d, _t(_UP).expand_as(d))
    return d, valid


def dir_to_pixel(layout: str, height: int, width: int, dirs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Inverse of :func:`pixel_to_dir`: continuous (y, x) of unit directions ``[*S, 3]`` (file frame).

    Returns (y, x) float64 ``[*S]``, inside the image (clamped to [0, H) × [0, W))."""
    _check_layout(layout)
    d = dirs.to(torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    eps = 1e-9
    if layout == "latlong":
        theta = torch.arccos(d[..., 2].clamp(-1, 1))
        phi = torch.remainder(torch.atan2(d[..., 1], d[..., 0]), 2 * math.pi)
        y = theta / math.pi * height
        x = phi / (2 * math.pi) * width
    elif layout == "angular":
        F, R, U = _t(FORWARD), _t(_RIGHT), _t(_UP)
        psi = torch.arccos((d @ F).clamp(-1, 1))
        e = torch.stack([d @ R, d @ U], -1)
        en = e.norm(dim=-1)
        unit = torch.where(en[..., None] > 0, e / en.clamp_min(1e-300)[..., None], torch.tensor([1.0, 0.0], dtype=torch.float64))
        ab = (psi / math.pi)[..., None] * unit
        x = (ab[..., 0] + 1) * width / 2
        y = (1 - ab[..., 1]) * height / 2
    else:
        tw, th, tile_id, nru, rows, cols, face_of = _cube_tables(layout)
        n = width // tw
        normals = _t([f[0] for f in _FACES])  # [6, 3]
        face = (d @ normals.T).argmax(-1)  # major axis
        tile_of_face = torch.empty(6, dtype=torch.long)
        tile_of_face[face_of] = torch.arange(len(face_of))
        t = tile_of_face[face]
        f = nru[t]
        dn = (d * f[..., 0, :]).sum(-1)
        a = (d * f[..., 1, :]).sum(-1) / dn
        b = (d * f[..., 2, :]).sum(-1) / dn
        x = cols[t] * n + ((a + 1) * n / 2).clamp(0, n - eps)
        y = rows[t] * n + ((1 - b) * n / 2).clamp(0, n - eps)
    return y.clamp(0, height - eps), torch.remainder(x, width).clamp(0, width - eps)


def pixel_directions(layout: str, height: int, width: int) -> torch.Tensor:
    """Pixel-centre directions ``[H, W, 3]`` float64 (file frame)."""
    yy = torch.arange(height, dtype=torch.float64)[:, None].expand(height, width) + 0.5
    xx = torch.arange(width, dtype=torch.float64)[None, :].expand(height, width) + 0.5
    return pixel_to_dir(layout, height, width, yy, xx)[0]


def _cube_F(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.atan2(a * b, torch.sqrt(a * a + b * b + 1))


def solid_angles(layout: str, height: int, width: int, subsamples: int = ANGULAR_SUBSAMPLES) -> torch.Tensor:
    """Per-pixel solid angles ``[H, W]`` float64 (sum 4π; 0 on masked pixels).

    latlong: exact Δφ(cos θ0 - cos θ1). Cubes: exact, F(a,b) = atan2(ab, √(a²+b²+1)) over the
    pixel's corners. Angular: ``subsamples``² midpoint rule of π sin(πr)/r over pixel ∩ disk
    (the integrand is continuous, vanishing at the rim, so the rule converges as O(h²))."""
    _check_layout(layout)
    if layout == "latlong":
        t0 = torch.arange(height, dtype=torch.float64) * (math.pi / height)
        w = (torch.cos(t0) - torch.cos(t0 + math.pi / height)) * (2 * math.pi / width)
        return w[:, None].expand(height, width).clone()
    if layout == "angular":
        s = check_int("subsamples", subsamples, 1, 64)
        out = torch.zeros(height, width, dtype=torch.float64)
        ya = torch.arange(height, dtype=torch.float64)[:, None]
        xa = torch.arange(width, dtype=torch.float64)[None, :]
        da = (2.0 / width) * (2.0 / height) / (s * s)
        for p in range(s):  # loop over the s² sub-sample offsets, each a whole-image op
            for q in range(s):
                a = 2 * (xa + (q + 0.5) / s) / width - 1
                b = 1 - 2 * (ya + (p + 0.5) / s) / height
                r = torch.sqrt(a * a + b * b)
                dens = torch.where(r < 1, math.pi * torch.sin(math.pi * r) / r.clamp_min(1e-300), torch.zeros_like(r))
                dens = torch.where(r == 0, torch.full_like(r, math.pi * math.pi), dens)
                out += dens * da
        return out
    tw, th, tile_id, *_ = _cube_tables(layout)
    tiles = (tile_id >= 0).to(torch.float64)
    return torch.kron(tiles, cube_face_solid_angles(width // tw))


def cube_face_solid_angles(n: int) -> torch.Tensor:
    """Exact solid angles ``[n, n]`` float64 of the pixels of one cube face of n × n pixels (every face the same;
    F(a,b) = atan2(ab, √(a²+b²+1)) over each pixel's corners): what :func:`solid_angles` tiles over a cube layout."""
    e = torch.linspace(-1, 1, n + 1, dtype=torch.float64)
    a0, a1 = e[None, :-1], e[None, 1:]
    b0, b1 = e[:-1, None], e[1:, None]
    return _cube_F(a1, b1) - _cube_F(a0, b1) - _cube_F(a1, b0) + _cube_F(a0, b0)  # [n, n], symmetric in b


def valid_mask(layout: str, height: int, width: int) -> torch.Tensor:
    """Pixels that carry light, ``[H, W]`` bool (angular: pixel meets the disk; crosses: not blank)."""
    _check_layout(layout)
    if layout == "latlong":
        return torch.ones(height, width, dtype=torch.bool)
    if layout == "angular":
        ya = torch.arange(height, dtype=torch.float64)[:, None]
        xa = torch.arange(width, dtype=torch.float64)[None, :]
        # nearest point of the pixel square to the centre, in (a, b) units
        a0, a1 = 2 * xa / width - 1, 2 * (xa + 1) / width - 1
        b0, b1 = 1 - 2 * (ya + 1) / height, 1 - 2 * ya / height
        ca = torch.where((a0 <= 0) & (a1 >= 0), torch.zeros_like(a0), torch.minimum(a0.abs(), a1.abs()))
        cb = torch.where((b0 <= 0) & (b1 >= 0), torch.zeros_like(b0), torch.minimum(b0.abs(), b1.abs()))
        return (ca * ca + cb * cb) < 1.0
    tw, th, tile_id, *_ = _cube_tables(layout)
    n = width // tw
    return torch.kron((tile_id >= 0).long(), torch.ones(n, n, dtype=torch.long)).bool()


# --------------------------------------------------------------------------------------------
# frames and rotations

_AXES = {"x": 0, "y": 1, "z": 2}


def up_rotation(up: str = "z") -> torch.Tensor:
    """The fixed rotation ``[3, 3]`` float64 taking a file frame whose up axis is ``up`` to the
    world frame (+z up): the shortest rotation taking ``up`` to +z.

    'z': identity. 'y': +90° about x, (x, y, z) -> (x, -z, y) (the usual y-up -> z-up, e.g.
    glTF -> Blender). '-y': -90° about x. 'x': -90° about y, (x, y, z) -> (-z, y, x).
    '-x': +90° about y. '-z': 180° about x.
    """
    up = check_choice("up", up, ["x", "y", "z", "-x", "-y", "-z", "+x", "+y", "+z"]).lstrip("+")
    if up == "z":
        return torch.eye(3, dtype=torch.float64)
    if up == "-z":
        return _t([[1, 0, 0], [0, -1, 0], [0, 0, -1]])
    sign = -1.0 if up.startswith("-") else 1.0
    u = torch.zeros(3, dtype=torch.float64)
    u[_AXES[up[-1]]] = sign
    z = _t([0.0, 0.0, 1.0])
    k = torch.linalg.cross(u, z)
    k = k / k.norm()
    # rotation by 90 degrees about k: R v = k (k·v) + k × v  (cos = 0, sin = 1)
    K = _t([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return torch.outer(k, k) + K


def _axis_rot(axis: str, deg: float) -> torch.Tensor:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    if axis == "x":
        return _t([[1, 0, 0], [0, c, -s], [0, s, c]])
    if axis == "y":
        return _t([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return _t([[c, -s, 0], [s, c, 0], [0, 0, 1]])


def euler_matrix(angles_deg: Sequence[float], order: str = "xyz") -> torch.Tensor:
    """Rotation ``[3, 3]`` float64 from Euler angles in degrees, applied about the fixed world
    axes in ``order``: for order 'xyz' and angles (α, β, γ), R = Rz(γ) · Ry(β) · Rx(α)
    (rotate about x first). Positive angles turn counter-clockwise looking down the axis."""
    if len(order) != 3 or any(c not in "xyz" for c in order):
        raise ValueError(f"order={order!r}; accepted: three letters from 'xyz', e.g. 'xyz' or 'zyx'")
    if len(angles_deg) != 3:
        raise ValueError(f"Euler angles {describe(angles_deg)}; accepted: three angles in degrees")
    R = torch.eye(3, dtype=torch.float64)
    for ax, ang in zip(order, angles_deg):  # three factors
        R = _axis_rot(ax, float(ang)) @ R
    return R


def resolve_rotation(rotation: Any = None, up: str = "z") -> torch.Tensor:
    """World-from-file rotation ``[3, 3]`` float64: R_rotation · R_up.

    ``rotation``: None, a 3×3 rotation matrix (tensor / nested list; must be orthonormal with
    det +1), three Euler angles in degrees (see :func:`euler_matrix`, order xyz), or a string
    "a,b,c" of such angles."""
    Rup = up_rotation(up)
    if rotation is None:
        return Rup
    if isinstance(rotation, str):
        try:
            vals = [float(v) for v in rotation.replace(" ", "").split(",")]
        except ValueError:
            raise ValueError(f"rotation={rotation!r}; accepted: 'a,b,c' Euler angles in degrees (x, y, z)") from None
        rotation = vals
    R = torch.as_tensor(rotation, dtype=torch.float64)
    if R.shape == (3,):
        if not bool(torch.isfinite(R).all()):
            raise ValueError(f"rotation={R.tolist()}: Euler angles must be finite; accepted: three finite angles in degrees (x, y, z)")
        return euler_matrix(R.tolist()) @ Rup
    if R.shape != (3, 3):
        raise ValueError(f"rotation has shape {tuple(R.shape)}; accepted: a 3x3 matrix or 3 Euler angles (degrees)")
    check_finite("rotation", R)
    if not torch.allclose(R @ R.T, torch.eye(3, dtype=torch.float64), atol=1e-6) or float(torch.linalg.det(R)) < 0:
        raise ValueError("rotation must be a proper rotation matrix (RᵀR = I, det R = +1); got "
                         f"det = {float(torch.linalg.det(R)):.6g}")
    return R @ Rup
