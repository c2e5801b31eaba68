"""Glossy, MRT and Kautz relighting at a view lying in a vertex's tangent plane (Sloan 2003 §3.1, Lehtinen &
Kautz 2003 eq. 13, Kautz 2002: zero below the horizon; Green 2005 eq. 1.2 for the tables).

The view weights kept a ``z > 0`` horizon test while the transport tables, their exact reference and view taps
count cos θ_o ≤ ``transport.HORIZON_EPS`` (1e-9) as below it. A view lying in a tangent plane comes out of the
float64 frame rotation at z ~ ±1e-16 with either sign, so under ``> 0`` a flat surface with the same transfer at
every vertex, seen by a distant view in its plane, relit to a stripe pattern: the full grazing value at the
vertices whose rounding came out positive, zero at the others. The independent check is the geometry's: every
vertex of such a plane has the same normal, frame and view, so it must relight to one value (all of them zero,
as below the horizon); 1e-3 above the plane they relight to one non-zero value, and there the weights are the
SH basis at the view (:func:`prt_torch.sh.eval_sh`) and tents summing to one.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from prt_torch import relight
from prt_torch.sh import eval_sh
from prt_torch.transfer.transport import HORIZON_EPS


def _views(n, t, b, lift: float) -> list[torch.Tensor]:
    """Distant view directions at elevation ``lift`` (radians) above the plane, at four azimuths in it."""
    out = []
    for d in (t, b, t + b, 0.3 * t - b):
        d = d / np.linalg.norm(d)
        v = math.cos(lift) * d + math.sin(lift) * n
        out.append(torch.tensor(v / np.linalg.norm(v)))
    return out


def _relit(mesh, d: torch.Tensor) -> dict[str, torch.Tensor]:
    """Glossy (16×9), MRT (M = 4, 9 coefficients) and Kautz (B 16×9) radiance ``[V, 3]`` float64 of the same
    transfer at every vertex (fixed random matrices), under one light, seen from direction ``d``."""
    g = torch.Generator().manual_seed(7)
    V = mesh.num_vertices
    L = torch.rand(3, 9, generator=g, dtype=torch.float64)
    Mg = torch.rand(16, 9, generator=g, dtype=torch.float64).expand(V, 16, 9).contiguous()
    A = torch.rand(16, 9, generator=g, dtype=torch.float64).expand(V, 16, 9).contiguous()
    Bk = torch.rand(16, 9, generator=g, dtype=torch.float64)
    frames = mesh.frames()
    v = relight.local_view(frames, direction=d)
    return {"glossy": relight.glossy(Mg, L, v), "mrt": relight.mrt(A, L, v),
            "kautz": relight.kautz(None, relight.kautz_setup(frames, 3), Bk, L, v), "z": v[:, 2]}


def test_a_plane_seen_along_itself_relights_to_one_value(tilted_plane):
    """Every vertex of the plane, seen by a distant view lying in it, relights to zero under glossy, MRT and Kautz
    — whichever sign the float64 rotation gave its cos θ_o (both signs occur here: that is what made it a stripe
    pattern under ``> 0``)."""
    mesh, n, t, b = tilted_plane
    assert float((mesh.normals - torch.tensor(n)).abs().max()) < 1e-12  # one normal: one radiance per view
    signs = set()
    for d in _views(n, t, b, 0.0):
        r = _relit(mesh, d)
        z = r["z"]
        assert float(z.abs().max()) < 1e-14  # in the tangent plane up to rounding
        signs |= {int(s) for s in torch.sign(z).unique().tolist()}
        for k in ("glossy", "mrt", "kautz"):
            assert float(r[k].abs().max()) == 0.0, (k, float(r[k].abs().max()))
    assert {-1, 1} <= signs  # the rounding gave both signs: a `> 0` test split the plane


def test_just_above_the_plane_one_non_zero_value(tilted_plane):
    """At 1e-3 rad above the plane the same vertices relight to one non-zero value each (spread at rounding level):
    the zero above is the horizon's, not a transfer that happens to vanish."""
    mesh, n, t, b = tilted_plane
    for d in _views(n, t, b, 1e-3):
        r = _relit(mesh, d)
        for k in ("glossy", "mrt", "kautz"):
            x = r[k]
            assert float(x.abs().min()) > 1e-3
            assert float((x - x[0]).abs().max()) <= 1e-12 * float(x.abs().max()), k


@pytest.mark.parametrize("z", [0.0, 1e-17, -1e-17, 1.1e-16, 5e-10, HORIZON_EPS, 2e-9, 1e-3, 0.5])
def test_view_weights_follow_the_tables_horizon(z):
    """The weights are zero at cos θ_o ≤ HORIZON_EPS, as the transport tables (transport.HORIZON_EPS), and above
    it the real SH basis at the view (eval_sh, glossy) and four tents summing to one (MRT eq. 13)."""
    x = math.sqrt(1.0 - z * z)
    v = torch.tensor([[x * math.cos(0.4), x * math.sin(0.4), z]], dtype=torch.float64)
    y = relight.glossy_view_weights(v, None, 16, torch.float64)
    _, w = relight.mrt_view_taps(v, 8, torch.float64)
    if z <= HORIZON_EPS:
        assert float(y.abs().max()) == 0.0 and float(w.abs().max()) == 0.0
    else:
        torch.testing.assert_close(y, eval_sh(v, 4), rtol=0, atol=1e-15)
        assert abs(float(w.sum()) - 1.0) < 1e-12
