"""prt_torch.render without GL: camera matrices (vs pyrender), tone mapping, error maps, heat
maps, PNG/EXR writers, side-by-side composites."""
from __future__ import annotations

import math

import matplotlib
import numpy as np
import pytest
import torch

from prt_torch.render import (
    Camera,
    auto_exposure,
    bounding_sphere,
    error_heatmap,
    error_map,
    save_exr,
    save_png,
    side_by_side,
    to_display,
    tonemap,
)


def _read(path, fmt):
    import OpenImageIO as oiio

    inp = oiio.ImageInput.open(str(path))
    spec = inp.spec()
    arr = inp.read_image(0, 0, 0, spec.nchannels, fmt)
    inp.close()
    return np.asarray(arr).reshape(spec.height, spec.width, spec.nchannels)


def srgb8(x):
    """IEC 61966-2-1 encoding to 8 bits, written out here independently of the module."""
    x = np.clip(np.asarray(x, np.float64), 0, 1)
    y = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    return np.round(y * 255).astype(np.uint8)


# ---------------------------------------------------------------------------------------------
# camera
# ---------------------------------------------------------------------------------------------

def test_projection_matrices_match_pyrender():
    import pyrender

    cam = Camera(eye=[1, 2, 3], target=[0, 0, 0], fov=37.0, near=0.3, far=12.0)
    ref = pyrender.PerspectiveCamera(yfov=math.radians(37.0), znear=0.3, zfar=12.0).get_projection_matrix(64, 48)
    assert np.allclose(cam.projection_matrix(64 / 48), ref, rtol=1e-12, atol=0)
    ortho = Camera(eye=[1, 2, 3], target=[0, 0, 0], projection="orthographic", ortho_height=3.0, near=0.5, far=9.0)
    ref = pyrender.OrthographicCamera(xmag=1.5, ymag=1.5, znear=0.5, zfar=9.0).get_projection_matrix(64, 48)
    assert np.allclose(ortho.projection_matrix(64 / 48), ref, rtol=1e-12, atol=0)


def test_view_matrix_geometry():
    eye, target = np.array([2.0, -1.0, 1.5]), np.array([0.1, 0.2, -0.3])
    V = Camera(eye=eye, target=target).view_matrix()
    R = V[:3, :3]
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-14) and np.isclose(np.linalg.det(R), 1.0)
    assert np.allclose(V @ np.append(eye, 1), [0, 0, 0, 1], atol=1e-14)
    d = np.linalg.norm(target - eye)
    assert np.allclose(V @ np.append(target, 1), [0, 0, -d, 1], atol=1e-14)  # looks down −z
    up_eye = R @ np.array([0, 0, 1.0])
    assert up_eye[1] > 0 and abs(up_eye[0]) < 1e-14  # world +z appears upward, no roll


def test_fit_direction_and_sphere():
    v = torch.tensor([[0, 0, 0], [2, 0, 0], [0, 4, 0], [0, 0, 1.0]], dtype=torch.float64)
    c, r = bounding_sphere(v)
    assert np.allclose(c, [1, 2, 0.5]) and math.isclose(r, math.sqrt(1 + 4 + 0.25))
    cam = Camera.fit(v, azimuth=90.0, elevation=0.0, fov=30.0)
    d = (cam.eye - cam.target) / np.linalg.norm(cam.eye - cam.target)
    assert np.allclose(d, [0, 1, 0], atol=1e-12)  # azimuth from +x toward +y
    assert math.isclose(np.linalg.norm(cam.eye - cam.target), 1.05 * r / math.sin(math.radians(15)))
    top = Camera.fit(v, azimuth=10.0, elevation=90.0)
    assert np.allclose((top.eye - top.target) / np.linalg.norm(top.eye - top.target), [0, 0, 1], atol=1e-12)
    with pytest.raises(ValueError, match="elevation"):
        Camera.fit(v, elevation=95.0)
    with pytest.raises(ValueError, match="projection"):
        Camera.fit(v, projection="fisheye")
    with pytest.raises(ValueError, match="coincide"):
        Camera(eye=[0, 0, 0], target=[0, 0, 0])
    with pytest.raises(ValueError, match="parallel"):
        Camera(eye=[0, 0, 1], target=[0, 0, 0], up=[0, 0, 1])


def test_project_pixel_convention():
    cam = Camera(eye=[0, 0, 3], target=[0, 0, 0], up=[0, 1, 0], projection="orthographic", ortho_height=2.0,
                 near=1, far=5)
    xy, z = cam.project(np.array([[0, 0, 0], [-2, 1, 0], [2, -1, 0]]), 40, 20)  # aspect 2: x in [-2, 2]
    assert np.allclose(xy, [[20, 10], [0, 0], [40, 20]])  # top-left corner is (0, 0), row 0 at the top
    assert np.allclose(z, (3 - 3) / 2)  # depth 3 is mid-way between near 1 and far 5: NDC 0


# ---------------------------------------------------------------------------------------------
# tone mapping, exposure
# ---------------------------------------------------------------------------------------------

def test_tonemap_and_display():
    img = np.array([[[0.25, 2.0, -1.0], [np.nan, 0.5, 0.5]]], np.float32)
    t = tonemap(img, exposure=1.0, method="clip", background=0.125)
    assert np.allclose(t[0, 0], [0.5, 1.0, 0.0]) and np.allclose(t[0, 1], 0.125)
    r = tonemap(img, method="reinhard")
    assert np.allclose(r[0, 0], [0.2, 2 / 3, 0.0])
    d = to_display(img)
    assert d.dtype == np.uint8 and np.array_equal(d[0, 0], srgb8([0.25, 1.0, 0.0]))
    u8 = np.arange(12, dtype=np.uint8).reshape(2, 2, 3)
    assert np.array_equal(to_display(u8), u8)  # uint8 is already display-encoded
    with pytest.raises(ValueError, match="tonemap"):
        tonemap(img, method="aces")


def test_auto_exposure():
    lum = np.linspace(0, 4, 101)
    img = np.repeat(lum[None, :, None], 3, 2)
    ev = auto_exposure(img, percentile=50.0, target=0.5)
    assert math.isclose(2.0 ** ev * np.percentile(lum, 50), 0.5)
    mask = np.zeros((1, 101), bool)
    mask[0, :11] = True  # luminance 0..0.4
    assert math.isclose(2.0 ** auto_exposure(img, mask, 100.0, 0.8) * 0.4, 0.8)
    assert auto_exposure(np.zeros((2, 2, 3))) == 0.0


# ---------------------------------------------------------------------------------------------
# error maps, heat maps
# ---------------------------------------------------------------------------------------------

def test_error_maps():
    rng = np.random.default_rng(0)
    ref = rng.uniform(0.5, 2, (6, 5, 3))
    img = ref + rng.normal(0, 0.1, ref.shape)
    mask = rng.random((6, 5)) > 0.3
    a = error_map(img, ref, mask, "abs")
    assert np.allclose(a[mask], np.abs(img - ref).mean(2)[mask]) and np.isnan(a[~mask]).all()
    s = error_map(img, ref, mask, "sq")
    assert np.allclose(s[mask], ((img - ref) ** 2).mean(2)[mask])
    r = error_map(img, ref, mask, "rel", eps=1e-9)
    assert np.allclose(r[mask], (np.abs(img - ref).mean(2) / np.abs(ref).mean(2))[mask])
    zero_ref = np.zeros_like(ref)
    assert np.isfinite(error_map(img, zero_ref, None, "rel")).all()  # black reference: eps guards
    with pytest.raises(ValueError, match="equal shapes"):
        error_map(img, ref[:, :4])
    with pytest.raises(ValueError, match="kind"):
        error_map(img, ref, kind="psnr")


def test_error_heatmap_colours():
    ref = np.ones((2, 3, 3), np.float32)
    img = ref.copy()
    img[0, 1] += 0.5  # error 0.5 = vmax -> top colour
    img[0, 2] += 0.25  # half
    mask = np.ones((2, 3), bool)
    mask[1, 2] = False
    h = error_heatmap(img, ref, mask, "abs", vmax=0.5, cmap="viridis", background=(0.2, 0.3, 0.4))
    cm = matplotlib.colormaps["viridis"]
    assert h.dtype == np.float32 and h.shape == (2, 3, 3)

    def lin(c):  # sRGB colormap colour -> linear, written out here
        c = np.asarray(c[:3], np.float64)
        return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)

    assert np.allclose(h[0, 0], lin(cm(0.0)), atol=1e-6)
    assert np.allclose(h[0, 1], lin(cm(1.0)), atol=1e-6)
    assert np.allclose(h[0, 2], lin(cm(0.5)), atol=1e-6)
    assert np.allclose(h[1, 2], [0.2, 0.3, 0.4])
    # saved as PNG, the heat map shows exactly the colormap's 8-bit colours
    assert np.array_equal(to_display(h)[0, 1], np.round(np.asarray(cm(1.0)[:3]) * 255).astype(np.uint8))
    same = error_heatmap(ref, ref, mask)  # zero error: vmax falls back, no division by zero
    assert np.allclose(same[mask], lin(matplotlib.colormaps["inferno"](0.0)), atol=1e-6)
    with pytest.raises(ValueError, match="colormap"):
        error_heatmap(img, ref, cmap="nope")


# ---------------------------------------------------------------------------------------------
# writers, composite
# ---------------------------------------------------------------------------------------------

def test_save_png_and_exr(tmp_path):
    rng = np.random.default_rng(2)
    img = rng.uniform(-0.1, 1.5, (7, 9, 3)).astype(np.float32)
    p = save_png(tmp_path / "a.png", img, exposure=-0.5)
    assert np.array_equal(_read(p, "uint8"), srgb8(img * 2 ** -0.5))
    u8 = rng.integers(0, 256, (4, 5, 3)).astype(np.uint8)
    assert np.array_equal(_read(save_png(tmp_path / "b.png", u8), "uint8"), u8)
    img[0, 0] = [1234.5678, 1e-3, np.nan]
    e = save_exr(tmp_path / "c.exr", img)
    back = _read(e, "float")
    assert np.array_equal(back[~np.isnan(img)], img[~np.isnan(img)]) and np.isnan(back[0, 0, 2])
    with pytest.raises(FileExistsError):
        save_png(tmp_path / "a.png", img, overwrite=False)
    with pytest.raises(ValueError, match=".png"):
        save_png(tmp_path / "a.jpg", img)
    with pytest.raises(ValueError, match=".exr"):
        save_exr(tmp_path / "a.png", img)
    assert not list(tmp_path.glob("*.partial"))


def test_side_by_side_places_panels_exactly(tmp_path):
    rng = np.random.default_rng(4)
    a = rng.uniform(0, 1, (10, 12, 3)).astype(np.float32)
    b = rng.integers(0, 256, (8, 12, 3)).astype(np.uint8)
    c = rng.uniform(0, 4, (10, 6, 3)).astype(np.float32)
    out = side_by_side([a, b, c], ["ref", "codec", "error"], exposure=[-1.0, None, -2.0], gap=3,
                       label_height=14, path=tmp_path / "s.png")
    assert out.dtype == np.uint8 and out.shape == (3 + 14 + 10 + 3, 3 * 12 + 4 * 3, 3)
    y = 3 + 14
    assert np.array_equal(out[y:y + 10, 3:15], srgb8(a * 0.5))
    assert np.array_equal(out[y:y + 8, 18:30], b)
    assert np.all(out[y + 8:y + 10, 18:30] == 255)  # smaller panel padded white
    assert np.array_equal(out[y:y + 10, 33:39], srgb8(c * 0.25))
    assert (out[3:3 + 14, 3:15] < 128).any()  # the label strip has dark text
    assert np.array_equal(_read(tmp_path / "s.png", "uint8"), out)
    grid = side_by_side([a, a, a, a], columns=2)
    assert grid.shape == (2 * 10 + 3 * 4, 2 * 12 + 3 * 4, 3)  # 2x2 panels, default gap 4, no labels
    with pytest.raises(ValueError, match="label"):
        side_by_side([a, b], ["one"])
