"""Issue 39 reviewed a second time from the command line (`--res auto`, lights, odd meshes, the
harness's trade): each test here failed before its fix. Small scenes and cubes so the module runs in
seconds. The last test is a check of `--res auto` the review asked for (it passed before)."""
from __future__ import annotations

import numpy as np

from prt_torch.cli import main as cli_main
from prt_torch.transfer import Transfer


def _coarse_image(path, h: int = 16) -> str:
    """A 2h x h lat-long image (radiance 0.3, one pixel of 500): far coarser than a cube at R = 64."""
    from prt_torch.lighting.imageio import write_image

    img = np.full((h, 2 * h, 3), 0.3, np.float32)
    img[3, 5] = 500.0
    write_image(path, img)
    return str(path)


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


def test_precompute_res_auto_takes_an_image_coarser_than_sh_32_bands(tmp_path, capsys):
    """The CLI read every ``--light`` as an SH light at 32 bands before any work, also for the wavelet
    kind, which never uses it: a 32x16 image was refused ('--bands 32 from a map of 512 pixels would
    alias'), and ``--dry-run`` sized the run from the SH projection's R rather than the run's. Now the
    wavelet kind reads the lights as the library does (on the cube): the CLI's R is the library's for
    the same image, and a missing file is still one line before any work."""
    from prt_torch.scene import builtin
    from prt_torch.transfer import get_kind

    light = _coarse_image(tmp_path / "coarse.hdr")
    f = tmp_path / "w.prt"
    assert cli_main(["precompute", "occluder_over_plane", "--kind", "wavelet", "--res", "auto", "--light", light,
                     "--terms", "16", "--workers", "1", "--no-progress", "-o", str(f)]) == 0
    capsys.readouterr()
    kw, decisions = get_kind("wavelet").resolve({"res": "auto", "terms": 16}, [light])
    assert Transfer.load(f).meta["res"] == kw["res"] == decisions["res"]["value"]
    assert builtin("occluder_over_plane", "small").num_vertices == Transfer.load(f).data.shape[0]
    bad = tmp_path / "bad.prt"
    assert cli_main(["precompute", "occluder_over_plane", "--kind", "wavelet", "--res", "auto", "--light",
                     str(tmp_path / "missing.hdr"), "-o", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "missing.hdr" in err and "Traceback" not in err and not bad.exists()
