"""The stability suite (benchmarks/bench_extremes.py writes the full report): degenerate data
every codec must represent exactly, fully shadowed points, views at the horizon."""
import math
import tempfile
from pathlib import Path

import pytest
import torch

from prt_torch import codecs, relight

_g = torch.Generator().manual_seed(0)
_BASIS = torch.randn(2, 12, generator=_g)
CASES = {
    "identical": torch.ones(400, 12),
    "zero": torch.zeros(300, 12),
    "5 distinct points of a 2-D subspace x 80 (clusters 8 > 5)": (torch.randn(5, 2, generator=_g) @ _BASIS).repeat(80, 1),
}


@pytest.mark.parametrize("name", [n for n in codecs.available() if n != "gaussian"])
@pytest.mark.parametrize("case", list(CASES))
def test_degenerate_data_is_represented_exactly(name, case):
    X = CASES[case]
    kw = {"vectors": 2} if name in ("pca", "mrt_pca") else ({"clusters": 8, "vectors": 2} if "cpca" in name else {"clusters": 8})
    c = codecs.get(name, **kw)
    enc = c.fit_encode(X, matrix_shape=(3, 4) if name == "mrt_pca" else None)
    err = float((c.decode(enc) - X).abs().max())
    assert math.isfinite(err) and err < 1e-4 * max(1.0, float(X.abs().max()))


def test_points_inside_a_closed_box_see_nothing():
    import trimesh

    from prt_torch.scene import RayCaster, load_scene
    from prt_torch.transfer.diffuse import transfer_at_points

    with tempfile.TemporaryDirectory() as tmp:
        p = Path(tmp) / "box.obj"
        trimesh.creation.box(extents=(2.0, 2.0, 2.0)).export(p)
        box = load_scene(str(p))
    caster = RayCaster(box, workers=1)
    try:
        t = transfer_at_points(caster, torch.tensor([[0.0, 0.0, 0.0], [0.9, -0.9, 0.9]], dtype=torch.float64),
                               torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=torch.float64), 3, 256)
    finally:
        caster.close()
    assert torch.equal(t, torch.zeros_like(t))


def test_views_at_the_horizon():
    # cos θ_o <= transport.HORIZON_EPS (1e-9) counts as below the horizon, as in the transport tables
    t = torch.tensor([-1e-9, 0.0, 1e-9, 2e-9, 1e-3], dtype=torch.float64)
    v = torch.stack([torch.sqrt(1 - t * t), torch.zeros_like(t), t], 1)
    idx, w = relight.mrt_view_taps(v, 8, torch.float64)
    assert (w[:3] == 0).all() and torch.allclose(w[3:].sum(1), torch.ones(2, dtype=torch.float64))
    assert (relight.glossy_view_weights(v, None, 16, torch.float64)[:3] == 0).all()
