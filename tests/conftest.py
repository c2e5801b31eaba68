"""Shared fixtures."""
import os
from pathlib import Path

import pytest
import torch


@pytest.fixture(scope="module")
def renderer(request):
    """One offscreen float renderer per test module, of the module's ``RENDER_SIZE`` (width,
    height). No GL: skipped only with PRT_SKIP_GL=1 outside CI; in CI (CI=true) the test fails."""
    from prt_torch.render import Renderer, RenderUnavailable

    w, h = getattr(request.module, "RENDER_SIZE", (64, 48))
    try:
        r = Renderer(w, h)
    except RenderUnavailable as e:
        if os.environ.get("PRT_SKIP_GL") == "1" and os.environ.get("CI", "").lower() != "true":
            pytest.skip(f"PRT_SKIP_GL=1 and no GL: {e}")
        raise
    yield r
    r.close()


def _file_backed(t) -> bool:
    """Whether ``t``'s memory is a shared mapping of a (deleted) scratch file: /proc/self/maps."""
    p = t.untyped_storage().data_ptr()
    with open("/proc/self/maps") as f:
        for line in f:
            lo, hi = (int(x, 16) for x in line.split()[0].split("-"))
            if lo <= p < hi:
                return ".scratch.npy" in line and line.split()[1][3] == "s"
    return False


@pytest.fixture
def file_backed():
    """``file_backed(t) -> bool``: whether a tensor's memory is a result streamed to its scratch file
    (a shared mapping of a deleted ``*.scratch.npy``), read from /proc/self/maps."""
    return _file_backed


def _saved_alike(got, ref, d) -> None:
    """``got`` and ``ref`` (Transfers) saved to ``d``/a.prt and b.prt load back as the same tensors, and
    ``d`` holds nothing else (no state directory, no scratch file left behind)."""
    import torch

    from prt_torch import io

    got.save(d / "a.prt")
    ref.save(d / "b.prt")
    ta, _ = io.load(d / "a.prt")
    tb, _ = io.load(d / "b.prt")
    assert ta.keys() == tb.keys() and all(torch.equal(ta[k], tb[k]) for k in ta)
    assert sorted(p.name for p in d.iterdir()) == ["a.prt", "b.prt"]


@pytest.fixture
def saved_alike():
    """``saved_alike(got, ref, dir)``: the two results' files are equal and nothing else was left in dir."""
    return _saved_alike



@pytest.fixture
def tilted_plane():
    """A 12×12 grid (``prt_torch.scene.mesh.make_mesh``) in the plane through (0.37, 0.37, 0.37) with normal
    n ∝ (0.3, -0.5, 0.8): one normal up to float64 rounding, so a distant view lying in the plane has cos θ_o ~ ±1e-16
    of both signs at its vertices. Returns (mesh, n, t, b), n, t, b float64 numpy unit vectors (t, b span the plane)."""
    import numpy as np

    from prt_torch.scene.mesh import make_mesh

    n = np.array([0.3, -0.5, 0.8])
    n /= np.linalg.norm(n)
    t = np.cross(n, [0.0, 0.0, 1.0])
    t /= np.linalg.norm(t)
    b = np.cross(n, t)
    g = np.linspace(-1.0, 1.0, 12)
    P = np.array([x * t + y * b + 0.37 for x in g for y in g])
    corners = [i * 12 + j for i in range(11) for j in range(11)]
    F = [[a, a + 12, a + 1] for a in corners] + [[a + 1, a + 12, a + 13] for a in corners]
    return make_mesh(P, np.array(F), name="tilted plane"), n, t, b


def _upper_rays(v, n, k: int = 8, seed: int = 0):
    """``k`` random directions per vertex in the hemisphere of its normal (float64, seeded): origins ``[V·k, 3]``
    (the vertices repeated), directions ``[V·k, 3]`` unit, normals ``[V·k, 3]`` — rays for ``RayCaster.occluded``."""
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(v.shape[0] * k, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    o, nn = v.repeat_interleave(k, 0), n.repeat_interleave(k, 0)
    return o, torch.where((d * nn).sum(1, keepdim=True) < 0, -d, d), nn


@pytest.fixture
def upper_rays():
    return _upper_rays


def _nonzero_haar_terms(spec, res: int) -> int:
    """The number of nonzero Haar terms of a light on the cube at ``res`` (``lighting.haar.cube_light``, as the
    harness and ``prt relight`` rasterise it; ``haar2d`` in float64, |L̂_ck| summed over the channels), counted
    directly: the terms above 1e-9 of the largest, checked to be the same terms as above 1e-15 — the light's real
    terms lie decades above the transform's round-off (~1e-17 of the largest), so the count does not depend on
    where a threshold between them sits (select_terms' ``haar.ZERO_TERM`` = 1e-12 is not used here)."""
    from prt_torch.lighting.haar import cube_light, haar2d

    cube, _ = cube_light(spec, res)
    m = haar2d(cube.double()).reshape(cube.shape[0], -1).abs().sum(0)
    top = float(m.max())
    n = int((m > 1e-9 * top).sum())
    assert n == int((m > 1e-15 * top).sum()), f"{spec!r} at R = {res}: terms between 1e-15 and 1e-9 of its largest"
    return n


@pytest.fixture
def nonzero_haar_terms():
    """``nonzero_haar_terms(spec, res) -> int``: a light's nonzero Haar terms on the cube at ``res``, counted
    directly from its coefficients (:func:`_nonzero_haar_terms`)."""
    return _nonzero_haar_terms


def _bench_module(name: str):
    """``benchmarks/<name>.py`` imported as a module: the benchmarks folder is on ``sys.path`` only while it imports."""
    import importlib
    import sys

    bench = str(Path(__file__).resolve().parents[1] / "benchmarks")
    sys.path.insert(0, bench)
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(bench)


@pytest.fixture(scope="session")
def bench_module():
    """:func:`_bench_module`: ``bench_module("bench_wavelet")`` gives that benchmark script as a module."""
    return _bench_module
