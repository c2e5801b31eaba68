"""GLSL decoding of REAL glossy and MRT transfer (a small precompute, not synthetic data).

A 362-vertex geodesic sphere (convex: no shadows to trace), glossy exit transfer (Sloan 2003
§3.1, default Ashikhmin–Shirley BRDF) and MRT (Lehtinen & Kautz 2003, 4×4 tents), 3 bands,
64 directions per vertex, a coarse BRDF quadrature: about two seconds. Checked: the CPU path is
``relight.glossy`` / ``relight.mrt`` at the camera's local views; GLSL equals it above 50 dB
with identical coverage, uncompressed and compressed; a light from +x lights the +x half.

Rendering for real (EGL + llvmpipe); without EGL these FAIL (PRT_SKIP_GL=1 skips them outside CI).
"""
from __future__ import annotations


import numpy as np
import pytest
import torch

from prt_torch import codecs, relight
from prt_torch.lighting import load_light
from prt_torch.render import Camera, PRTScene, glsl_vs_cpu
from prt_torch.scene import geodesic_sphere, make_mesh

pytestmark = pytest.mark.filterwarnings("ignore::prt_torch.codecs.base.ConvergenceWarning")


RENDER_SIZE = (72, 64)  # the shared `renderer` fixture (conftest.py)


@pytest.fixture(scope="module")
def real():
    from prt_torch.transfer.glossy import precompute_glossy
    from prt_torch.transfer.mrt import precompute_mrt

    v, f = geodesic_sphere(6)
    mesh = make_mesh(v, f, name="geodesic362")
    common = dict(samples=64, shadows=False, quad_bands=6)
    return {"glossy": precompute_glossy(mesh, 3, 3, **common), "mrt": precompute_mrt(mesh, 3, 4, M=4, **common)}


@pytest.mark.parametrize("kind,codec,params", [("glossy", None, {}), ("glossy", "cpca", dict(clusters=4, vectors=3)),
                                               ("mrt", None, {}), ("mrt", "mrt_pca", dict(vectors=6))])
def test_real_view_dependent_transfer(renderer, real, kind, codec, params):
    tr = real[kind]
    sc = PRTScene(tr)
    light = load_light("directional:direction=1,0,0.3;intensity=3", bands=3)
    cam = Camera.fit(tr.mesh, azimuth=-90, elevation=0, fov=40, aspect=72 / 64)
    view = sc.view(cam.eye)
    # the CPU path is the project's reference relighting at the camera's local views
    vl = relight.local_view(sc.frames, sc.points, eye=torch.as_tensor(cam.eye))
    L = sc.light_matrix(light).T
    ref = (relight.glossy(sc.rows, L, vl, tr.meta.get("out_index")) if kind == "glossy" else relight.mrt(sc.rows, L, vl))
    assert torch.allclose(sc.cpu_radiance(light, view), ref.float(), atol=1e-5 * float(ref.abs().max()))
    cd = enc = None
    if codec:
        X = tr.signal()
        cd = codecs.get(codec, **params).fit(X, matrix_shape=sc.matrix_shape)
        enc = cd.encode(X)
    c = glsl_vs_cpu(renderer, sc, light, cam, cd, enc)
    assert c.same_mask and c.mask.sum() > 500
    assert c.psnr_db > 50, c.psnr_db
    W = c.mask.shape[1]
    for img in (c.glsl, c.cpu):
        lum = img.mean(2)
        left = lum[:, : W // 2][c.mask[:, : W // 2]].mean()
        right = lum[:, W // 2:][c.mask[:, W // 2:]].mean()
        assert right > 2 * max(left, 1e-6), (kind, codec, left, right)
    assert np.isfinite(c.glsl[c.mask]).all()
