"""Tests for prt_torch.lighting: layouts, file formats, projection, analytic lights, irradiance.

References are independent of the code under test: hand-derived pixel directions, raw
file bytes / OpenImageIO written directly, closed forms (2√π c, 3/32, 17/16, thesis
constants), scipy Legendre polynomials, Gauss quadrature and brute-force hemispherical sums.
"""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from scipy.special import eval_legendre

import OpenImageIO as oiio
from prt_torch import sh
from prt_torch.lighting import (
    LAYOUTS,
    Environment,
    builtin_environment,
    cap,
    cap_zonal,
    constant,
    detect_layout,
    directional,
    euler_matrix,
    hemisphere,
    irradiance,
    irradiance_coeffs,
    irradiance_constants,
    irradiance_map,
    irradiance_matrix,
    irradiance_polynomial,
    irradiance_quadratic,
    layout_shape,
    list_builtin_environments,
    load_environment,
    load_light,
    project_images,
    read_image,
    render_sh,
    sky_gradient,
    solid_angles,
    up_rotation,
    write_image,
)

X, Y, Z = (torch.tensor(v, dtype=torch.float64) for v in ([1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]))


def _oiio_write(path, arr):
    """Write with OpenImageIO directly (not through prt_torch's writer)."""
    arr = np.ascontiguousarray(arr, dtype=np.float32)
    h, w, c = arr.shape
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), oiio.ImageSpec(w, h, c, "float"))
    assert out.write_image(arr)
    out.close()


def _raw_pfm(path, arr):
    """PFM by the format: 'PF', W H, -1 (little endian), rows bottom-to-top."""
    h, w, _ = arr.shape
    with open(path, "wb") as f:
        f.write(f"PF\n{w} {h}\n-1.0\n".encode())
        f.write(np.ascontiguousarray(arr[::-1], dtype="<f4").tobytes())


# ---------------------------------------------------------------------------------------
# orientation: hand-derived landmark pixels per layout

LANDMARKS = [
    # layout, size, (row, col), expected direction (hand-derived from docs/lighting.md)
    ("latlong", 16, (0, 3), Z), ("latlong", 16, (15, 3), -Z),
    ("latlong", 16, (8, 0), X), ("latlong", 16, (8, 8), Y), ("latlong", 16, (8, 16), -X), ("latlong", 16, (8, 24), -Y),
    ("angular", 16, (8, 8), Y), ("angular", 16, (8, 12), X), ("angular", 16, (8, 3), -X),
    ("angular", 16, (3, 8), Z), ("angular", 16, (12, 8), -Z), ("angular", 16, (8, 15), -Y),
    ("hcross", 8, (12, 12), Y), ("hcross", 8, (4, 12), Z), ("hcross", 8, (20, 12), -Z),
    ("hcross", 8, (12, 4), -X), ("hcross", 8, (12, 20), X), ("hcross", 8, (12, 28), -Y),
    ("vcross", 8, (12, 12), Y), ("vcross", 8, (4, 12), Z), ("vcross", 8, (20, 12), -Z),
    ("vcross", 8, (12, 4), -X), ("vcross", 8, (12, 20), X), ("vcross", 8, (28, 12), -Y),
    ("faces", 8, (4, 4), X), ("faces", 8, (4, 12), -X), ("faces", 8, (4, 20), Y),
    ("faces", 8, (4, 28), -Y), ("faces", 8, (4, 36), Z), ("faces", 8, (4, 44), -Z),
]


@pytest.mark.parametrize("layout,size,pix,expect", LANDMARKS)
def test_landmark_pixels(layout, size, pix, expect, tmp_path):
    """A marked pixel written to a file maps to the documented direction and dominates the
    band-1 coefficients in that direction."""
    h, w = layout_shape(layout, size)
    img = np.zeros((h, w, 3), np.float32)
    img[pix] = 1.0
    p = tmp_path / "m.exr"
    _oiio_write(p, img)
    env = load_environment(p, layout=layout)
    d = env.directions()[pix]
    assert float(d @ expect) > math.cos(math.radians(25))
    L = env.project(2)[0]
    band1 = torch.stack([L[3], L[1], L[2]])  # (x, y, z) order of y_1,1 y_1,-1 y_1,0
    assert float(band1 @ expect) / float(band1.norm()) > 0.9


def test_face_orientation_within_tiles():
    """Off-centre pixels: the in-tile orientation of the documented (n; r; u) frames."""
    env = Environment(torch.zeros(24, 32, 3), "hcross")  # N = 8
    d = env.directions()
    # front tile, top-right corner pixel: towards +x and +z
    assert d[8, 15, 0] > 0.4 and d[8, 15, 2] > 0.4
    # up tile, top edge middle: image up of the +z face is -y (towards the back)
    assert d[0, 12, 1] < -0.5 and d[0, 12, 2] > 0.5
    # down tile, bottom edge: image down of the -z face is -y
    assert d[23, 12, 1] < -0.5
    venv = Environment(torch.zeros(32, 24, 3), "vcross")
    # vcross back tile (rotated 180°): its top rows are next to the floor (-z)
    assert venv.directions()[25, 12, 2] < -0.5
    # latlong: a quarter of the way across is +y, so φ increases to the right (from +x to +y)
    ll = Environment(torch.zeros(16, 32, 3), "latlong").directions()
    assert ll[8, 4, 1] > 0.5 and ll[8, 4, 0] > 0.5


@pytest.mark.parametrize("fmt", ["exr", "hdr", "tif", "pfm"])
def test_file_format_orientation(fmt, tmp_path):
    """Marked pixel near the top of a latlong written by an independent writer is read on its row,
    and our writer round-trips it (PFM: OIIO's reader/writer disagree, we follow the format)."""
    img = np.zeros((16, 32, 3), np.float32)
    img[1, 8] = [4.0, 2.0, 1.0]
    p = tmp_path / f"m.{fmt}"
    (_raw_pfm if fmt == "pfm" else _oiio_write)(p, img)
    rgb, info = read_image(p)
    assert tuple(np.argwhere(rgb[..., 0] > 0.5)[0]) == (1, 8)
    env = load_environment(p)
    assert env.layout == "latlong"
    assert float(env.directions()[1, 8] @ Z) > 0.9
    q = tmp_path / f"w.{fmt}"
    write_image(q, img)
    back, _ = read_image(q)
    assert tuple(np.argwhere(back[..., 0] > 0.5)[0]) == (1, 8)
    np.testing.assert_allclose(back[1, 8], img[1, 8], rtol=1e-2)
    if fmt == "pfm":  # our file stores the top row last, as the format says
        raw = np.frombuffer(q.read_bytes()[len(b"PF\n32 16\n-1.0\n"):], "<f4").reshape(16, 32, 3)
        assert raw[14, 8, 0] == 4.0


def test_six_face_files(tmp_path):
    n = 8
    faces = {}
    for k, name in enumerate(["px", "nx", "py", "ny", "pz", "nz"]):
        a = np.zeros((n, n, 3), np.float32)
        a[4, 4] = k + 1
        faces[name] = a
        _oiio_write(tmp_path / f"env_{name}.exr", a)
    env = load_environment(str(tmp_path / "env_{face}.exr"))
    assert env.layout == "faces" and tuple(env.image.shape) == (n, 6 * n, 3)
    axes = [X, -X, Y, -Y, Z, -Z]
    for k in range(6):
        assert float(env.directions()[4, k * n + 4] @ axes[k]) > 0.95
        assert float(env.image[4, k * n + 4, 0]) == k + 1
    env2 = load_environment([tmp_path / f"env_{f}.exr" for f in ["px", "nx", "py", "ny", "pz", "nz"]])
    assert torch.equal(env.image, env2.image)
    env.save(str(tmp_path / "out_{face}.pfm"))
    env3 = load_environment(str(tmp_path / "out_{face}.pfm"))
    assert torch.equal(env.image, env3.image)


# ---------------------------------------------------------------------------------------
# solid angles and constant maps


def _fine_solid_angles(layout, h, w, s=12):
    """Brute force: s×s midpoint rule of the cube / latlong Jacobians, written independently."""
    if layout == "latlong":
        theta = (torch.arange(h * s, dtype=torch.float64) + 0.5) * math.pi / (h * s)
        dens = torch.sin(theta)[:, None].expand(h * s, w * s) * (math.pi / (h * s)) * (2 * math.pi / (w * s))
    else:
        n = w // {"hcross": 4, "vcross": 3, "faces": 6}[layout]
        a = (torch.arange(n * s, dtype=torch.float64) + 0.5) / (n * s) * 2 - 1
        face = (2 / (n * s)) ** 2 / (1 + a[:, None] ** 2 + a[None, :] ** 2) ** 1.5
        tiles = {"hcross": [[0, 1, 0, 0], [1, 1, 1, 1], [0, 1, 0, 0]],
                 "vcross": [[0, 1, 0], [1, 1, 1], [0, 1, 0], [0, 1, 0]], "faces": [[1] * 6]}[layout]
        dens = torch.kron(torch.tensor(tiles, dtype=torch.float64), face)
    return dens.reshape(h, s, w, s).sum((1, 3))


@pytest.mark.parametrize("layout", ["latlong", "hcross", "vcross", "faces"])
def test_solid_angles_exact(layout):
    h, w = layout_shape(layout, 8)
    om = solid_angles(layout, h, w)
    assert abs(float(om.sum()) - 4 * math.pi) < 1e-12
    torch.testing.assert_close(om, _fine_solid_angles(layout, h, w), rtol=2e-3, atol=1e-9)


def test_angular_solid_angles():
    om = solid_angles("angular", 32, 32)
    assert abs(float(om.sum()) - 4 * math.pi) < 1e-4
    # brute force, independently: 24x24 midpoint rule of dΩ = π sin(π r)/r da db inside the disk
    n, s = 32, 24
    a = (torch.arange(n * s, dtype=torch.float64) + 0.5) / (n * s) * 2 - 1
    r = torch.sqrt(a[None, :] ** 2 + a[:, None] ** 2)
    dens = torch.where(r < 1, math.pi * torch.sin(math.pi * r) / r, torch.zeros_like(r)) * (2 / (n * s)) ** 2
    torch.testing.assert_close(om, dens.reshape(n, s, n, s).sum((1, 3)), atol=2e-5, rtol=0)
    # the disk of radius 1/2 is the forward hemisphere
    r_c = torch.sqrt(a[None, :] ** 2 + a[:, None] ** 2)
    assert abs(float(dens[r_c < 0.5].sum()) - 2 * math.pi) < 1e-3


@pytest.mark.parametrize("layout,size", [("latlong", 32), ("angular", 48), ("hcross", 12), ("vcross", 12), ("faces", 12)])
def test_constant_map_projects_to_L00(layout, size, tmp_path):
    c = 1.7
    h, w = layout_shape(layout, size)
    img = np.full((h, w, 3), c, np.float32)
    p = tmp_path / "c.exr"
    _oiio_write(p, img)
    L = load_environment(p, layout=layout).project(4)
    l00 = 2 * math.sqrt(math.pi) * c
    torch.testing.assert_close(L[:, 0], torch.full((3,), l00, dtype=torch.float64), rtol=2e-6, atol=0)
    assert float(L[:, 1:].abs().max()) < 3e-3 * l00


# ---------------------------------------------------------------------------------------
# projection


def test_small_disk_projects_to_solid_angle_times_Y():
    d = torch.tensor([0.3, -0.5, 0.6], dtype=torch.float64)
    d = d / d.norm()
    alpha, c = 0.06, 50.0
    env = Environment.from_function(lambda s: c * ((s @ d) >= math.cos(alpha)).to(torch.float64)[:, None].repeat(1, 3),
                                    "latlong", 96, supersample=6)
    L = env.project(3)[0]
    omega = 2 * math.pi * (1 - math.cos(alpha))
    ref = c * omega * sh.eval_sh(d, 3)
    assert float((L - ref).norm()) < 0.05 * float(ref.norm())


def _smooth(s):
    a = torch.tensor([0.48, 0.6, 0.64], dtype=torch.float64)
    v = 1.0 + 0.5 * s[:, 0] + 0.3 * s[:, 1] * s[:, 2] + 2.0 * torch.exp(3.0 * (s @ a - 1.0))
    return torch.stack([v, 0.5 * v, 2.0 - 0.4 * s[:, 2]], -1)


def test_same_environment_in_every_layout(tmp_path):
    """A smooth map + a small disk light written in each layout (several formats) projects to
    the same SH vector as an independent high-order Gauss quadrature + the closed-form cap."""
    bands = 4
    dc = torch.tensor([-0.6, 0.0, 0.8], dtype=torch.float64)
    alpha = 0.15

    def f(s):
        return _smooth(s) + 20.0 * ((s @ dc) >= math.cos(alpha)).to(torch.float64)[:, None]

    ref = sh.project_callable(_smooth, bands, oversample=8) + cap(dc, alpha, radiance=20.0, bands=bands)
    sizes = {"latlong": (48, "m.exr"), "angular": (96, "m.hdr"), "vcross": (24, "m.pfm"), "hcross": (24, "m.tif"),
             "faces": (24, "m_{face}.exr")}
    for layout, (size, name) in sizes.items():
        env = Environment.from_function(f, layout, size, supersample=4)
        env.save(str(tmp_path / f"{layout}_{name}"))
        back = load_environment(str(tmp_path / f"{layout}_{name}"), layout=layout)
        L = back.project(bands)
        err = float((L - ref).norm() / ref.norm())
        assert err < 0.005, (layout, err)


@pytest.mark.parametrize("layout,size", [("latlong", 48), ("angular", 96), ("hcross", 24), ("vcross", 24), ("faces", 24)])
def test_sh_image_sh_round_trip(layout, size):
    g = torch.Generator().manual_seed(3)
    c = torch.randn(3, 16, generator=g, dtype=torch.float64)
    R = sh.random_rotations(1, seed=5)[0]
    env = render_sh(c, layout, size, rotation=R)
    back = env.project(4)
    tol = 2e-3 if layout != "angular" else 1e-2
    assert float((back - c).norm() / c.norm()) < tol


def test_project_images_batched_matches_single():
    g = torch.Generator().manual_seed(0)
    imgs = torch.rand(3, 12, 24, 3, generator=g)
    B = project_images(imgs, "latlong", 3)
    for b in range(3):
        torch.testing.assert_close(B[b], Environment(imgs[b], "latlong").project(3))


def test_window_off_by_default_and_applied():
    env = builtin_environment("studio", size=16)
    L = env.project(5)
    Lh = env.project(5, window="hanning")
    w = sh.window(5, "hanning")
    l = torch.repeat_interleave(torch.arange(5), 2 * torch.arange(5) + 1)
    torch.testing.assert_close(Lh, L * w[l])
    Lg = env.project(5, window="gaussian:0.2")
    torch.testing.assert_close(Lg[:, 6], L[:, 6] * math.exp(-(0.2 * 2) ** 2))  # eq. 6.7 at l = 2
    with pytest.raises(ValueError, match="window"):
        env.project(5, window="bogus")


# ---------------------------------------------------------------------------------------
# rotation


def test_rotating_map_equals_rotating_sh(tmp_path):
    env = Environment.from_function(_smooth, "latlong", 48, supersample=2)
    env.save(tmp_path / "s.exr")
    R = euler_matrix([30.0, -20.0, 75.0])
    L = load_environment(tmp_path / "s.exr").project(4)
    Lr = load_environment(tmp_path / "s.exr", rotation=[30.0, -20.0, 75.0]).project(4)
    torch.testing.assert_close(Lr, sh.rotate(L, R), atol=2e-3 * float(L.norm()), rtol=0)
    # and against rasterising the rotated function itself: g(s) = f(Rᵀ s)
    Lg = Environment.from_function(lambda s: _smooth(s @ R), "latlong", 48, supersample=2).project(4)
    torch.testing.assert_close(Lr, Lg, atol=5e-3 * float(L.norm()), rtol=0)


def test_up_axis_and_euler():
    for up in ["x", "y", "z", "-x", "-y", "-z"]:
        R = up_rotation(up)
        v = torch.zeros(3, dtype=torch.float64)
        v["xyz".index(up[-1])] = -1.0 if up.startswith("-") else 1.0
        torch.testing.assert_close(R @ v, Z)
        assert abs(float(torch.linalg.det(R)) - 1) < 1e-12
    torch.testing.assert_close(up_rotation("y") @ Z, -Y)  # (x, y, z) -> (x, -z, y)
    torch.testing.assert_close(euler_matrix([0, 0, 90]) @ X, Y, atol=1e-15, rtol=0)
    torch.testing.assert_close(euler_matrix([90, 0, 0]) @ Y, Z, atol=1e-15, rtol=0)


def test_up_y_file_loads_rotated(tmp_path):
    img = np.zeros((16, 32, 3), np.float32)
    img[8, 8] = 1.0  # file direction ≈ +y
    _oiio_write(tmp_path / "u.exr", img)
    env = load_environment(tmp_path / "u.exr", up="y")
    assert float(env.directions()[8, 8] @ Z) > 0.95


# ---------------------------------------------------------------------------------------
# analytic lights


def test_cap_zonal_closed_form_vs_quadrature():
    alpha = 0.7
    x, w = np.polynomial.legendre.leggauss(64)
    t = math.cos(alpha) + (x + 1) * (1 - math.cos(alpha)) / 2
    wt = w * (1 - math.cos(alpha)) / 2
    ref = [2 * math.pi * math.sqrt((2 * l + 1) / (4 * math.pi)) * float(np.sum(wt * eval_legendre(l, t)))
           for l in range(12)]
    torch.testing.assert_close(cap_zonal(alpha, 12), torch.tensor(ref, dtype=torch.float64), atol=1e-13, rtol=0)


def test_analytic_normalisation():
    d = torch.tensor([1.0, 2.0, 2.0], dtype=torch.float64) / 3
    Ld = directional(d, intensity=2.0, bands=3)
    # DirectXSH-style normalisation, exact: L_lm = π I y_lm(d)
    torch.testing.assert_close(Ld, math.pi * 2.0 * sh.eval_sh(d, 3).expand(3, 9))
    # 9-term irradiance at normal incidence: π I (1/4 + 1/2 + 5/16) = π I 17/16
    E = irradiance(Ld, d[None])
    torch.testing.assert_close(E, torch.full((1, 3), math.pi * 2.0 * 17 / 16, dtype=torch.float64))
    # tiny cap of the same intensity -> the directional light
    Lc = cap(d, 1e-3, intensity=2.0, bands=3)
    torch.testing.assert_close(Lc, Ld, rtol=1e-5, atol=1e-9)
    # full-sphere cap of radiance c == constant c
    torch.testing.assert_close(cap(d, math.pi, radiance=0.7, bands=4), constant(0.7, 4), atol=1e-13, rtol=0)
    torch.testing.assert_close(constant([1.0, 2.0, 3.0], 2)[:, 0],
                               2 * math.sqrt(math.pi) * torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    torch.testing.assert_close(hemisphere(0.5, 0.5, bands=4), constant(0.5, 4), atol=1e-13, rtol=0)


def test_sky_gradient_vs_split_quadrature():
    up = torch.tensor([0.2, -0.3, 0.9], dtype=torch.float64)
    up = up / up.norm()
    zen, hor, gnd = [0.2, 0.4, 1.0], [0.9, 0.8, 0.7], [0.1, 0.1, 0.05]
    L = sky_gradient(zen, hor, gnd, up=up, bands=5)
    # independent: upper/lower hemispheres about +z, each exact Gauss, then rotate +z -> up
    du, wu = sh.gauss_hemisphere(5, oversample=4)
    dl = du * torch.tensor([1.0, 1.0, -1.0], dtype=torch.float64)
    z, h, g = (torch.tensor(v, dtype=torch.float64) for v in (zen, hor, gnd))
    ref = sh.project(h + (z - h) * du[:, 2:3], du, wu, 5) + sh.project(g.expand(dl.shape[0], 3), dl, wu, 5)
    zc = torch.cross(Z, up, dim=0)
    ang = math.acos(float(up @ Z))
    k = zc / zc.norm()
    K = torch.tensor([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]], dtype=torch.float64)
    R = torch.eye(3, dtype=torch.float64) + math.sin(ang) * K + (1 - math.cos(ang)) * K @ K  # Rodrigues, R z = up
    torch.testing.assert_close(L, sh.rotate(ref, R), atol=1e-12, rtol=0)


# ---------------------------------------------------------------------------------------
# irradiance


def test_irradiance_constants_match_thesis():
    c = irradiance_constants()
    printed = {"c1": 0.429043, "c2": 0.511664, "c3": 0.743125, "c4": 0.886227, "c5": 0.247708}
    for k, v in printed.items():
        assert abs(c[k] - v) < 2e-6, k


def test_eq_4_10_4_14_4_16_agree():
    g = torch.Generator().manual_seed(1)
    L = torch.randn(3, 9, generator=g, dtype=torch.float64)
    n, _ = sh.fibonacci_sphere(200)
    e10 = irradiance(L, n)
    e14 = irradiance_quadratic(irradiance_matrix(L), n)
    e16 = irradiance_polynomial(L, n)
    torch.testing.assert_close(e14, e10, atol=1e-12, rtol=0)
    torch.testing.assert_close(e16, e10, atol=1e-12, rtol=0)
    M = irradiance_matrix(L)
    torch.testing.assert_close(M, M.transpose(-1, -2))


def test_directional_max_error_is_3_32():
    """Ramamoorthi §4.3.1: 9-term irradiance of a directional source errs at most 3/32 of
    its total intensity (attained at the horizon)."""
    d = torch.tensor([0.0, 0.6, 0.8], dtype=torch.float64)
    I = 1.3
    L = directional(d, I, 3)
    total = math.pi * I  # ∫ L dω
    n, _ = sh.fibonacci_sphere(4000)
    n = torch.cat([n, torch.tensor([[1.0, 0.0, 0.0]], dtype=torch.float64)])  # exactly at the horizon
    exact = total * (n @ d).clamp_min(0)
    err = (irradiance(L, n)[:, 0] - exact).abs().max() / total
    assert float(err) <= 3 / 32 + 1e-12
    assert float(err) > 3 / 32 - 1e-9


def test_higher_bands_converge_to_exact_irradiance():
    d = Z
    n, _ = sh.fibonacci_sphere(500)
    exact = math.pi * (n @ d).clamp_min(0)
    errs = [float((irradiance(directional(d, 1.0, b), n)[:, 0] - exact).abs().mean()) for b in (3, 5, 9, 17)]
    assert errs == sorted(errs, reverse=True) and errs[-1] < 0.01 * math.pi


def _brute_irradiance(env, normals):
    m = env.mask()
    d = env.directions()[m]
    w = (env.image[m].to(torch.float64) * env.solid_angles()[m][:, None])  # [P, C]
    return (normals @ d.T).clamp_min(0) @ w  # [V, C]


def test_map_irradiance_vs_brute_force():
    n, _ = sh.fibonacci_sphere(300)
    # a small bright disk on a dark map: max error within 3/32 of the total
    dd = torch.tensor([0.5, 0.5, 0.7071], dtype=torch.float64)
    dd = dd / dd.norm()
    env = Environment.from_function(lambda s: 0.01 + 100.0 * ((s @ dd) > math.cos(0.05)).to(torch.float64)[:, None].repeat(1, 3),
                                    "latlong", 48, supersample=4)
    E9 = irradiance(env.project(3), n)
    Eb = _brute_irradiance(env, n)
    total = env.total_power()
    assert float(((E9 - Eb).abs().max(0).values / total).max()) <= 3 / 32
    # smooth maps: average error about 1% of the mean irradiance
    for env in (builtin_environment("overcast", size=24), Environment.from_function(_smooth, "latlong", 24)):
        E9 = irradiance(env.project(3), n)
        Eb = _brute_irradiance(env, n)
        rel = float(((E9 - Eb).abs().mean(0) / Eb.mean(0)).max())
        assert rel < 0.01, rel


@pytest.mark.parametrize("layout", LAYOUTS)
def test_irradiance_map_of_constant(layout):
    env = irradiance_map(constant(0.5, 3), layout, 16)
    m = env.mask()
    torch.testing.assert_close(env.image[m], torch.full_like(env.image[m], math.pi * 0.5), rtol=1e-5, atol=0)
    Ld = directional(Z, 1.0, 3)
    Em = irradiance_map(Ld, layout, 16)
    torch.testing.assert_close(Em.image, irradiance(Ld, Em.directions()).to(torch.float32) * m[..., None])


def test_irradiance_coeffs_any_bands():
    L = torch.ones(2, 49, dtype=torch.float64)
    E = irradiance_coeffs(L)
    A = sh.clamped_cosine_A(7)
    assert torch.equal(E[0, 16:25], A[4].expand(9))
    assert float(E[0, 9:16].abs().max()) == 0.0  # A_3 = 0
    torch.testing.assert_close(A[:7], torch.tensor([3.141593, 2.094395, 0.785398, 0, -0.130900, 0, 0.049087],
                                                   dtype=torch.float64), atol=1e-6, rtol=0)  # thesis eq. 4.12


# ---------------------------------------------------------------------------------------
# built-ins, load_light, CLI


def test_builtins_deterministic_and_resolution_independent():
    assert {"sky", "studio"} <= set(list_builtin_environments())
    a = builtin_environment("sky", size=16)
    b = builtin_environment("sky", size=16)
    assert torch.equal(a.image, b.image)
    L16 = a.project(3)
    L32 = builtin_environment("sky", layout="hcross", size=12).project(3)
    torch.testing.assert_close(L16[:, 0], L32[:, 0], rtol=3e-3, atol=0)
    # realistic HDR: the sun pixel outshines the sky by orders of magnitude, and its irradiance
    # on a horizontal surface is a few times the sky's
    img = a.image.to(torch.float64)
    peak = img.sum(-1).argmax()
    iy, ix = divmod(int(peak), img.shape[1])
    assert float(img[iy, ix, 0] / img[..., 0].median()) > 1e3
    nz = a.directions()[..., 2].clamp_min(0) * a.solid_angles()
    e_all = float((img[..., 1] * nz).sum())
    e_sun = float(img[iy, ix, 1] * nz[iy, ix])
    assert 2.0 < e_sun / (e_all - e_sun) < 8.0


def test_load_light_kinds(tmp_path):
    torch.testing.assert_close(load_light("constant:value=2", 2), constant(2.0, 2))
    torch.testing.assert_close(load_light("directional:direction=0,0,1;intensity=1,2,3", 3),
                               directional(Z, [1.0, 2.0, 3.0], 3))
    torch.testing.assert_close(load_light({"type": "cap", "direction": [0, 1, 0], "half_angle_deg": 10, "intensity": 1}, 3),
                               cap(Y, math.radians(10), intensity=1.0, bands=3))
    assert load_light("studio", 3, size=16).shape == (3, 9)
    write_image(tmp_path / "c.exr", np.full((8, 16, 3), 1.0, np.float32))
    assert abs(float(load_light(str(tmp_path / "c.exr"), 1)[0, 0]) - 2 * math.sqrt(math.pi)) < 1e-5
    with pytest.raises(FileNotFoundError, match="built-in"):
        load_light("nonexistent_thing.hdr")
    with pytest.raises(ValueError, match="key=value"):
        load_light("cap:direction")


def test_cli_light(tmp_path, capsys):
    import json

    from prt_torch.cli import main

    assert main(["light", "constant:value=2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert abs(out["coeffs"][0][0] - 4 * math.sqrt(math.pi)) < 1e-12 and len(out["coeffs"][0]) == 9
    write_image(tmp_path / "e.hdr", Environment.from_function(_smooth, "latlong", 16).image)
    rc = main(["light", str(tmp_path / "e.hdr"), "--bands", "2", "--irradiance-map", str(tmp_path / "irr.exr"),
               "--preview", str(tmp_path / "p.png"), "--irradiance-size", "8"])
    text = capsys.readouterr().out
    assert rc == 0 and "layout=latlong" in text and len([ln for ln in text.splitlines() if not ln.startswith("#")]) == 5
    irr = load_environment(tmp_path / "irr.exr")
    assert irr.layout == "latlong" and (tmp_path / "p.png").exists()
    # analytic light rotated by Euler angles: +z turned 90° about x points to -y
    assert main(["light", "directional:direction=0,0,1", "--rotate", "90,0,0", "--bands", "2", "--json"]) == 0
    c = json.loads(capsys.readouterr().out)["coeffs"][0]
    assert c[1] < -1.5 and abs(c[2]) < 1e-12  # y_1,-1 ∝ y, y_1,0 ∝ z
    assert main(["light", str(tmp_path / "missing.exr")]) == 2
    assert "does not exist" in capsys.readouterr().err


# ---------------------------------------------------------------------------------------
# bad input


def test_bad_files(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing.exr"):
        load_environment(tmp_path / "missing.exr")
    junk = tmp_path / "junk.exr"
    junk.write_bytes(b"not an image at all")
    with pytest.raises(ValueError, match="junk.exr"):
        load_environment(junk)
    bad_pfm = tmp_path / "t.pfm"
    bad_pfm.write_bytes(b"PF\n4 2\n-1.0\n" + b"\0" * 10)
    with pytest.raises(ValueError, match="t.pfm"):
        load_environment(bad_pfm)
    _oiio_write(tmp_path / "odd.exr", np.ones((20, 30, 3), np.float32))
    with pytest.raises(ValueError, match=r"odd\.exr.*2:1 \(latlong\)"):
        load_environment(tmp_path / "odd.exr")
    _oiio_write(tmp_path / "ll.exr", np.ones((8, 16, 3), np.float32))
    with pytest.raises(ValueError, match="does not fit layout='hcross'"):
        load_environment(tmp_path / "ll.exr", layout="hcross")
    with pytest.raises(ValueError, match="layout"):
        load_environment(tmp_path / "ll.exr", layout="spherical")
    assert detect_layout(12, 16) == "hcross" and detect_layout(16, 12) == "vcross"


def test_bad_pixels_refused_or_clamped(tmp_path):
    img = np.ones((8, 16, 3), np.float32)
    img[0, 0, 0] = np.nan
    img[1, 1, 1] = np.inf
    img[2, 2, 2] = -3.0
    _oiio_write(tmp_path / "b.exr", img)
    with pytest.raises(ValueError, match=r"b\.exr.*2 NaN/Inf and 1 negative.*clamp=True"):
        load_environment(tmp_path / "b.exr")
    with warnings.catch_warnings(record=True) as w:
        warnings.simplefilter("always")
        env = load_environment(tmp_path / "b.exr", clamp=True)
    assert any("clamped 2 NaN/Inf and 1 negative" in str(x.message) for x in w)
    assert env.meta["files"][0]["clamped"] == {"nonfinite": 2, "negative": 1}
    assert float(env.image[0, 0, 0]) == 0 and float(env.image[2, 2, 2]) == 0 and torch.isfinite(env.image).all()


def test_channel_rules(tmp_path):
    g = np.random.default_rng(0).random((8, 16, 1)).astype(np.float32)
    _oiio_write(tmp_path / "g.exr", g)
    env = load_environment(tmp_path / "g.exr")
    assert env.channels == 3 and torch.equal(env.image[..., 0], env.image[..., 2])
    np.testing.assert_array_equal(env.image[..., 1].numpy(), g[..., 0])
    rgba = np.concatenate([np.ones((8, 16, 3), np.float32), np.full((8, 16, 1), 0.25, np.float32)], -1)
    out = oiio.ImageOutput.create(str(tmp_path / "a.exr"))
    spec = oiio.ImageSpec(16, 8, 4, "float")
    out.open(str(tmp_path / "a.exr"), spec)
    out.write_image(rgba)
    out.close()
    env = load_environment(tmp_path / "a.exr")
    assert env.meta["files"][0]["dropped_channels"] == ["A"] and float(env.image.max()) == 1.0
    ga = np.concatenate([g, np.zeros_like(g)], -1)
    _oiio_write(tmp_path / "ga.tif", ga)
    env = load_environment(tmp_path / "ga.tif")
    np.testing.assert_array_equal(env.image[..., 0].numpy(), g[..., 0])


def test_bad_faces(tmp_path):
    for k, f in enumerate(["px", "nx", "py", "ny", "pz", "nz"]):
        n = 8 if f != "pz" else 4
        _oiio_write(tmp_path / f"f_{f}.exr", np.ones((n, n, 3), np.float32))
    with pytest.raises(ValueError, match="six faces of one size"):
        load_environment(str(tmp_path / "f_{face}.exr"))
    with pytest.raises(ValueError, match="6 paths"):
        load_environment([tmp_path / "f_px.exr"] * 5)
    with pytest.raises(FileNotFoundError):
        load_environment(str(tmp_path / "none_{face}.exr"))


def test_latlong_projection_matches_scipy_prefilter():
    """Independent peer: θ from +z, φ from +x towards +y, scipy's complex SH converted to real."""
    import importlib.util
    import pathlib

    spec = importlib.util.spec_from_file_location(
        "bench_lighting", pathlib.Path(__file__).resolve().parent.parent / "benchmarks" / "bench_lighting.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    img = torch.rand(8, 16, 3, generator=torch.Generator().manual_seed(2))
    ours = Environment(img, "latlong").project(4)
    np.testing.assert_allclose(ours.numpy(), mod.numpy_project(img.numpy(), 4), atol=1e-12)
