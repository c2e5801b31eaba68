"""Resumed runs must not mix chunks of an earlier estimate (review of issue 42's merge): the diffuse, glossy
and MRT runs with bounces under 'auto' all fingerprint the face probe (the first stage's rays per face and the
guide's constants), since a face probed with 8 rays may choose another estimator than with 32."""
from __future__ import annotations

import pytest

from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions, precompute_diffuse
from prt_torch.transfer.diffuse import FIRST_PROBE_RAYS, GUIDE_GRID


class _Stop(Exception):
    pass


@pytest.mark.parametrize("kind", ["diffuse", "glossy", "mrt"])
def test_auto_bounce_runs_fingerprint_the_face_probe(monkeypatch, kind):
    """The fingerprint handed to the chunk runner (what a resume compares with the state directory's) names the
    thinned probe (8 of 32 rays per face) and the guide, for each kind; with estimator 'plain' (no probe) neither."""
    from prt_torch.transfer.glossy import precompute_glossy
    from prt_torch.transfer.mrt import precompute_mrt

    seen = []

    def capture(self, n, chunk, compute, *, fingerprint, **kw):
        seen.append(dict(fingerprint))
        raise _Stop

    monkeypatch.setattr(RunOptions, "run_chunks", capture)
    mesh = builtin("sphere_on_plane", "small")
    run = {"diffuse": lambda est: precompute_diffuse(mesh, 2, 16, 1, estimator=est, shadows="always", run=RunOptions(progress=False)),
           "glossy": lambda est: precompute_glossy(mesh, 2, samples=16, exit=False, shadows=True, bounces=1, estimator=est,
                                                   run=RunOptions(progress=False)),
           "mrt": lambda est: precompute_mrt(mesh, 2, samples=16, shadows=True, bounces=1, estimator=est,
                                             run=RunOptions(progress=False))}[kind]
    for est in ("auto", "plain"):
        with pytest.raises(_Stop):
            run(est)
    auto, plain = seen[-2], seen[-1]
    assert auto["hit_probe_rays"] == FIRST_PROBE_RAYS == GUIDE_GRID[0] * GUIDE_GRID[1] // 4
    assert auto["hit_guide"][:2] == list(GUIDE_GRID)
    assert "hit_probe_rays" not in plain and "hit_guide" not in plain
