"""GLSL decoding (prt_torch.render.glsl) against the torch engine, every shader path.

Each path renders the same scene twice with one camera: decoded in the vertex shader, and as the
per-vertex radiance the CPU engine computed (``relight`` / ``codec.relight``) drawn by the same
rasteriser. The coverage masks must be identical and the GLSL image must match the CPU image
above 50 dB PSNR (peak = max of the CPU image) on float32 images.

These tests render for real (EGL + Mesa llvmpipe). Without EGL they FAIL with the installation
hint; PRT_SKIP_GL=1 skips them explicitly — except under CI (CI=true), where they always run.
"""
from __future__ import annotations


import numpy as np
import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs.synthetic import transfer_like
from prt_torch.lighting import load_light
from prt_torch.render import (
    AffineDecoder,
    Camera,
    Decoder,
    PRTScene,
    TransferDecoder,
    codec_decoder,
    codec_decoders,
    glsl_vs_cpu,
    psnr,
    register_codec_decoder,
)
from prt_torch.scene import load_scene
from prt_torch.transfer import Transfer, unshadowed_transfer

MIN_DB = 50.0
# short fits on purpose (the decode is under test): a not-converged clustering is still a codec
pytestmark = pytest.mark.filterwarnings("ignore::prt_torch.codecs.base.ConvergenceWarning")


RENDER_SIZE = (80, 64)  # the shared `renderer` fixture (conftest.py)


@pytest.fixture(scope="module")
def mesh():
    return load_scene("bumpy_sphere", size="small").with_albedo([0.9, 0.6, 0.3])


@pytest.fixture(scope="module")
def transfers(mesh):
    """One transfer of each shape the engine relights: diffuse grey (real, unshadowed, albedo
    not folded), diffuse RGB, glossy exit transfer [V, 9, 16] and MRT [V, 36, 16] (synthetic
    transfer-like data of the right shape: the decode, not the precompute, is under test)."""
    V = mesh.num_vertices
    T = unshadowed_transfer(mesh.normals, 4).float()
    rgb = T[:, None, :] * torch.tensor([1.0, 0.7, 0.4])[None, :, None]
    return {
        "diffuse": Transfer("diffuse", T, mesh, {"albedo_folded": False}),
        "diffuse_rgb": Transfer("diffuse", rgb.contiguous(), mesh, {"albedo_folded": True}),
        "glossy": Transfer("glossy", transfer_like(V, 9, 16, seed=1).view(V, 9, 16), mesh,
                           {"matrix_shape": [9, 16], "out_index": list(range(9))}),
        "mrt": Transfer("mrt", transfer_like(V, 36, 16, seed=2).view(V, 36, 16), mesh, {"matrix_shape": [36, 16]}),
    }


@pytest.fixture(scope="module")
def light():
    return load_light("sky", bands=4)  # [3, 16]


@pytest.fixture(scope="module")
def camera(mesh):
    return Camera.fit(mesh, azimuth=30, elevation=20, fov=40, aspect=80 / 64)


CODECS = {  # small, cheap fits: the decode is under test, not the fit
    "vq": dict(clusters=12, max_iter=5),
    "pca": dict(vectors=6),
    "cpca": dict(clusters=6, vectors=4, max_iter=3, iterations=2),
    "cpca_adaptive": dict(clusters=6, vectors=4, max_iter=3, iterations=2, adapt_iters=1),
    "mrt_pca": dict(vectors=8),
    "neural": dict(latent=3, features=8, width=8, depth=1, clusters=2, epochs=10, encode_iters=5),
    "neural_full": dict(latent=3, features=8, width=8, depth=1, clusters=2, cluster_decoder="full", epochs=10, encode_iters=5),
}
#: the codec each CODECS entry fits (where the key is not the codec's name)
CODEC_OF = {"neural_full": "neural"}
_FITS: dict = {}
PATHS = ([(k, None) for k in ("diffuse", "diffuse_rgb", "glossy", "mrt")]
         + [(k, c) for k in ("diffuse", "diffuse_rgb", "glossy", "mrt") for c in ("vq", "pca", "cpca", "cpca_adaptive")]
         + [("mrt", "mrt_pca"), ("glossy", "mrt_pca")]
         + [(k, "neural") for k in ("diffuse", "diffuse_rgb", "glossy", "mrt")]
         + [(k, "neural_full") for k in ("glossy", "mrt")])  # one whole decoder per cluster


def _fit(tr, name):
    """(PRTScene, fitted codec, encoding), fitted once per transfer and codec in this module."""
    key = (id(tr), name)
    if key not in _FITS:
        sc = PRTScene(tr)
        X = tr.signal()
        codec = codecs.get(CODEC_OF.get(name, name), **CODECS[name]).fit(X, matrix_shape=sc.matrix_shape)
        _FITS[key] = (tr, sc, codec, codec.encode(X))
    return _FITS[key][1:]


def _check(c, min_pixels=1000):
    assert c.same_mask, "GLSL and CPU renders cover different pixels"
    assert c.mask.sum() > min_pixels
    assert np.isfinite(c.glsl[c.mask]).all()
    assert c.psnr_db > MIN_DB, f"GLSL vs CPU {c.psnr_db:.1f} dB (max |Δ| {c.max_abs:.3g})"
    assert np.abs(c.cpu[c.mask]).max() > 1e-3  # not trivially black


@pytest.mark.parametrize("kind,codec", PATHS, ids=[f"{k}-{c or 'uncompressed'}" for k, c in PATHS])
def test_glsl_matches_cpu(renderer, transfers, light, camera, kind, codec):
    tr = transfers[kind]
    if codec is None:
        sc, cd, enc = PRTScene(tr), None, None
    else:
        sc, cd, enc = _fit(tr, codec)
    c = glsl_vs_cpu(renderer, sc, light, camera, cd, enc)
    _check(c)
    if cd is not None:  # the CPU path is the codec's own relight, which equals decode-then-relight
        dec = Transfer(tr.kind, cd.decode(enc).view(tr.data.shape), tr.mesh, dict(tr.meta))
        v = sc.view(camera.eye)
        ref = PRTScene(dec).cpu_radiance(light, v)
        assert torch.allclose(sc.cpu_radiance(light, v, cd, enc), ref, rtol=1e-4, atol=1e-4 * float(ref.abs().max()))


def test_weights_through_texture_buffer_and_attributes_agree(renderer, transfers, light, camera):
    sc, cd, enc = _fit(transfers["glossy"], "cpca")
    a = glsl_vs_cpu(renderer, sc, light, camera, cd, enc, weights_in="attributes")
    b = glsl_vs_cpu(renderer, sc, light, camera, cd, enc, weights_in="buffer")
    _check(a)
    _check(b)
    assert a.glsl.tobytes() == b.glsl.tobytes() or psnr(a.glsl, b.glsl, a.mask) > 100


def test_many_vectors_fall_back_to_a_weight_buffer(renderer, transfers, light, camera):
    """More PCA weights than fit in vertex attributes: read from a texture buffer instead."""
    tr = transfers["mrt"]
    sc = PRTScene(tr)
    X = tr.signal()
    cd = codecs.get("mrt_pca", vectors=50).fit(X, matrix_shape=sc.matrix_shape)
    enc = cd.encode(X)
    dec = sc.decoder(light, sc.view(camera.eye), cd, enc)
    assert "weights" in dec.inputs(sc.V).tables
    _check(glsl_vs_cpu(renderer, sc, light, camera, cd, enc))


@pytest.mark.parametrize("codec", [None, "cpca"])
def test_lit_side_is_brighter_in_both_paths(renderer, transfers, mesh, codec):
    """A directional light from +x; camera on −y looking at +y with +z up, so +x is the right
    half of the image: brighter than the left half in GLSL and CPU renders alike."""
    tr = transfers["diffuse"]
    light = load_light("directional:direction=1,0,0;intensity=3", bands=4)
    cam = Camera.fit(mesh, azimuth=-90, elevation=0, fov=40, aspect=80 / 64)
    if codec is None:
        sc, cd, enc = PRTScene(tr), None, None
    else:
        sc, cd, enc = _fit(tr, codec)
    c = glsl_vs_cpu(renderer, sc, light, cam, cd, enc)
    _check(c, min_pixels=500)
    W = c.mask.shape[1]
    for img in (c.glsl, c.cpu):
        lum = img.mean(2)
        left = lum[:, : W // 2][c.mask[:, : W // 2]].mean()
        right = lum[:, W // 2:][c.mask[:, W // 2:]].mean()
        assert right > 3 * max(left, 1e-6), (left, right)


def test_view_dependent_decode_changes_with_the_eye_and_is_black_below_horizon(renderer, transfers, light, mesh):
    sc = PRTScene(transfers["glossy"])
    a = sc.view(Camera.fit(mesh, azimuth=0, elevation=10).eye)
    b = sc.view(Camera.fit(mesh, azimuth=180, elevation=10).eye)
    assert a.shape == (sc.V, 9) and not torch.allclose(a, b)
    below = (a == 0).all(1)
    assert 0 < int(below.sum()) < sc.V  # about half the sphere faces away
    rad = sc.cpu_radiance(light, a)
    assert (rad[below] == 0).all()
    idx, w = PRTScene(transfers["mrt"]).view(Camera.fit(mesh, azimuth=0, elevation=10).eye)
    assert idx.shape == (sc.V, 4) and torch.allclose(w.sum(1)[w.sum(1) > 0], torch.ones(1), atol=1e-5)


def test_codec_that_does_not_belong_is_refused(transfers, mesh):
    sc = PRTScene(transfers["glossy"])
    other = load_scene("bumpy_sphere", size="small").with_albedo([0.1, 0.1, 0.1])
    _, cd, enc = _fit(transfers["diffuse"], "pca")
    with pytest.raises(ValueError, match="does not belong"):
        sc.check_codec(cd, enc)  # dimension 16 vs 9x16
    _, cd, enc = _fit(transfers["glossy"], "pca")
    with pytest.raises(ValueError, match="hash"):
        sc.check_codec(cd, enc, meta={"extra": {"mesh_hash": other.content_hash()}})
    sc.check_codec(cd, enc, meta={"extra": {"mesh_hash": mesh.content_hash()}})


def test_decoder_registry_by_codec_name(transfers, light):
    reg = codec_decoders()
    for name in ("vq", "pca", "cpca", "cpca_static", "cpca_iterative", "cpca_adaptive", "mrt_pca", "neural"):
        assert issubclass(reg[name], AffineDecoder)
    sc, cd, enc = _fit(transfers["diffuse"], "vq")
    assert type(codec_decoder(cd, enc, sc.light_matrix(light))).__name__ == "VQDecoder"

    class Fake:
        codec_name = "gaussian_test_only"

    with pytest.raises(ValueError, match="no GLSL decoder"):
        codec_decoder(Fake(), None, None)

    @register_codec_decoder("gaussian_test_only")
    class GaussianDecoder(Decoder):
        @classmethod
        def from_codec(cls, codec, enc, light, mode="none", view=None, albedo=None):
            return cls()

    assert isinstance(codec_decoder(Fake(), None, None), GaussianDecoder)
    with pytest.raises(TypeError):
        register_codec_decoder("x")(object)


def test_decoder_input_checks(transfers, light):
    sc = PRTScene(transfers["glossy"])
    L = sc.light_matrix(light)
    with pytest.raises(ValueError, match="mode"):
        TransferDecoder(sc.rows, L, "sideways")
    with pytest.raises(ValueError, match="dense view weights"):
        TransferDecoder(sc.rows, L, "dense", torch.zeros(3, 9))
    with pytest.raises(ValueError, match="row"):
        TransferDecoder(sc.rows, L, "none")
    with pytest.raises(ValueError, match="labels span"):
        AffineDecoder(np.full(sc.V, 5), np.zeros((sc.V, 0)), np.zeros((2, 1, 1, 3)))
    with pytest.raises(ValueError, match="J="):
        AffineDecoder(np.zeros(sc.V, int), np.zeros((sc.V, 2)), np.zeros((1, 2, 1, 3)))
    with pytest.raises(ValueError, match="light"):
        TransferDecoder(sc.rows, torch.zeros(4, 3), "dense", torch.zeros(sc.V, 9))
    with pytest.raises(ValueError, match="vertices"):
        TransferDecoder(sc.rows, L, "dense", torch.zeros(sc.V, 9)).inputs(sc.V + 1)


def test_per_vertex_data_stays_resident_and_set_light_relights(renderer, transfers, camera):
    """Decoders mark per-vertex data read-only: the renderer uploads it once and keeps it while
    the decoder lives; a new light changes only the uniform / the constants table, and gives the
    image a freshly made decoder gives."""
    import gc

    sc, cd, enc = _fit(transfers["glossy"], "cpca")
    gc.collect()
    renderer.render_radiance(sc.mesh, np.ones((sc.V, 3)), camera)  # writeable radiance: not kept
    base = len(renderer._resident)  # the mesh's positions and indices, resident while it lives
    view = sc.view(camera.eye)
    l1, l2 = load_light("sky", bands=4), load_light("directional:direction=1,0,1;intensity=2", bands=4)
    for codec, e in ((None, None), (cd, enc)):
        dec = sc.decoder(l1, view, codec, e)
        renderer.render(sc.mesh, dec, camera)
        n_resident = len(renderer._resident)
        assert n_resident >= base + 3  # albedo, view weights, transfer / cluster ids and weights
        dec.set_light(sc.light_matrix(l2))
        a, m = renderer.render(sc.mesh, dec, camera)
        assert len(renderer._resident) == n_resident  # nothing new uploaded to stay
        b, _ = renderer.render(sc.mesh, sc.decoder(l2, view, codec, e), camera)
        assert np.array_equal(a[m], b[m])
        c = glsl_vs_cpu(renderer, sc, l2, camera, codec, e)
        assert psnr(a, c.cpu, m) > MIN_DB
        del dec
    gc.collect()
    renderer.render_radiance(sc.mesh, np.ones((sc.V, 3)), camera)  # purges data whose arrays died
    assert len(renderer._resident) == base
    user = np.ones((sc.V, 3), np.float32)
    from prt_torch.render import TransferDecoder as TD

    TD(sc.rows[:, :1, :], sc.light_matrix(l1), "none", None, user)
    assert user.flags.writeable  # the caller's arrays are copied, never frozen
