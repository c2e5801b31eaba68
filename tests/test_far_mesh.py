"""A mesh far from the origin (a scan in world or georeferenced coordinates) is traced in a frame centred on
itself (``RayCaster.center``, the bounding-box centre subtracted in float64 before the float32 cast), not
refused: the course's blocker scene moved by 1e4 or 1e6 was refused by ``check_traceable`` (before that, traced
black: rays started inside the surface). Transfer under distant light is translation-invariant, so the moved
mesh's transfer must equal the unmoved one's (the same rays, keyed by vertex: equal here to the bit, the test
allows float32 noise) for every ray-traced kind, with the output's stored positions the user's (moved) ones.
What recentring cannot fix stays refused: an extent beyond float32's products, NaN/Inf."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from prt_torch.cli import main as cli_main
from prt_torch.scene import builtin
from prt_torch.scene.raycast import RayCaster
from prt_torch.transfer import RunOptions, get_kind

SHIFT = torch.tensor([1.0, -0.7, 0.3], dtype=torch.float64)

KINDS = {
    "diffuse": ("diffuse", {"bands": 3, "samples": 16, "shadows": "always"}),
    "diffuse-interreflected": ("diffuse", {"bands": 3, "samples": 16, "bounces": 1, "hit_samples": 4, "estimator": "control"}),
    "glossy": ("glossy", {"bands": 3, "bands_out": 3, "samples": 16, "shadows": "always"}),
    "wavelet": ("wavelet", {"res": 4, "terms": 96, "bits": 32, "shadows": "always"}),
    "wavelet-interreflected": ("wavelet", {"res": 4, "terms": 96, "bits": 32, "bounces": 1, "hit_samples": 4}),
}


@pytest.fixture(scope="module")
def blocker():
    return builtin("occluder_over_plane", "small")


def _moved(mesh, s: float):
    return dataclasses.replace(mesh, vertices=mesh.vertices + s * SHIFT)


def _transfer(mesh, kind, params):
    return get_kind(kind).precompute(mesh, dict(params), run=RunOptions(workers=1, progress=False))


@pytest.mark.parametrize("name", list(KINDS))
def test_moved_mesh_gives_the_transfer_at_the_origin(blocker, name):
    kind, params = KINDS[name]
    ref = _transfer(blocker, kind, params)
    d0 = ref.data.double()
    assert float(d0.abs().max()) > 0
    for s in (1e4, 1e6):
        moved = _moved(blocker, s)
        tr = _transfer(moved, kind, params)
        d = tr.data.double()
        assert d.shape == d0.shape
        assert torch.allclose(d, d0, rtol=0, atol=1e-6 * float(d0.abs().max())), (name, s, float((d - d0).abs().max()))
        assert torch.equal(tr.mesh.vertices, moved.vertices)  # stored in the user's coordinates


def test_shadows_are_traced_far_from_the_origin(blocker, upper_rays):
    """The occlusion of the same rays (8 upper-hemisphere directions per vertex) through ``occluded`` (world
    coordinates in): the moved mesh's equals the unmoved one's, which the blocker shadows."""
    v, n, f = blocker.vertices.double(), blocker.normals.double(), blocker.faces
    o, d, nn = upper_rays(v, n)
    ref = RayCaster(vertices=v, faces=f).occluded(o, d, nn)
    assert 0.05 < float(ref.float().mean()) < 0.5
    for s in (1e4, 1e6):
        c = RayCaster(vertices=v + s * SHIFT, faces=f)
        assert np.allclose(c.center, s * SHIFT.numpy() + RayCaster(vertices=v, faces=f).center, rtol=0, atol=1e-9)
        assert torch.equal(c.occluded(o + s * SHIFT, d, nn), ref)


def test_what_recentring_cannot_fix_is_still_refused(blocker):
    v, f = blocker.vertices.double(), blocker.faces
    for s in (1e20, 1e-20):  # the extent itself: float32 products over- or underflow inside Embree
        with pytest.raises(ValueError, match="rescale the mesh"):
            RayCaster(vertices=(v + 10.0) * s, faces=f)
    bad = v.clone()
    bad[0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or Inf"):
        RayCaster(vertices=bad, faces=f)


def test_cli_precompute_of_a_far_scan_file(tmp_path, capsys, blocker):
    """The command line on an OBJ in world coordinates (moved by 1e4; refused before): written, its transfer the
    unmoved file's, its stored positions the file's."""
    from prt_torch.transfer import Transfer

    paths = {}
    for s in (0.0, 1e4):
        p = tmp_path / f"m{int(s)}.obj"
        vv = (blocker.vertices.double() + s * SHIFT).numpy()
        with open(p, "w") as fh:
            fh.writelines("v %.17g %.17g %.17g\n" % tuple(x) for x in vv)
            fh.writelines("f %d %d %d\n" % tuple(t + 1) for t in blocker.faces.numpy())
        out = tmp_path / f"m{int(s)}.prt"
        assert cli_main(["precompute", str(p), "--kind", "wavelet", "--res", "4", "--terms", "96", "--bits", "32",
                         "--workers", "1", "--no-progress", "-o", str(out)]) == 0
        paths[s] = out
    a, b = Transfer.load(paths[0.0]), Transfer.load(paths[1e4])
    # the file's normals are recomputed from its moved coordinates (1e-16 apart from the unmoved file's), so a ray
    # grazing an edge may round to the other side in float32: a few vertices differ by at most one texel's weight
    diff = (b.data.double() - a.data.double()).abs().amax(1)
    assert int((diff > 1e-6).sum()) <= 0.01 * a.num_vertices, int((diff > 1e-6).sum())
    texel = float(a.data.abs().max())  # no single texel weighs more than the largest stored coefficient (bits 32)
    assert float(diff.max()) <= texel
    assert torch.allclose(b.mesh.vertices - a.mesh.vertices, (1e4 * SHIFT).expand_as(a.mesh.vertices), rtol=0, atol=1e-9)
