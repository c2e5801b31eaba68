"""Issue 39 reviewed a second time from the command line (`--res auto`, lights, odd meshes, the
harness's trade): each test here failed before its fix. Small scenes and cubes so the module runs in
seconds."""
from __future__ import annotations

import numpy as np

from prt_torch.cli import main as cli_main
from prt_torch.transfer import Transfer


def test_res_auto_clamps_the_default_terms_to_a_small_cube(tmp_path, capsys):
    """``--res auto`` under a smooth light chooses a small cube (overcast: R = 4, 96 Haar coefficients),
    and the run was then refused for the default K it had not been given ('--terms 256 is out of range;
    accepted: integers in [1, 96]'). Now K becomes 6R² (said on a line of its own and in meta['auto']):
    every vertex keeps every coefficient, i.e. its indices are a permutation of 0..95."""
    f = tmp_path / "w.prt"
    assert cli_main(["precompute", "occluder_over_plane", "--kind", "wavelet", "--res", "auto", "--light", "overcast",
                     "--bits", "32", "--workers", "1", "--no-progress", "-o", str(f)]) == 0
    err = capsys.readouterr().err
    assert "terms=96" in err
    tr = Transfer.load(f)
    R = tr.meta["res"]
    assert R == 4 and tr.meta["terms"] == 6 * R * R == tr.data.shape[1]
    assert tr.meta["auto"]["terms"]["value"] == 96
    idx = np.sort(tr.aux["index"].numpy().astype(np.int64), axis=1)
    assert (idx == np.arange(96)[None]).all()
