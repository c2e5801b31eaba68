"""The dry runs' stage tables line up (left39 item 2): ``prt relight``'s wavelet plan has a stage named
``build|light`` (11 characters) and the table printed names in a 7-wide column, so that row's bytes and note
stood 4 characters right of the others'; a precompute estimate's ``time not measured`` (17) overflowed its
12-wide time column the same way. Checked on the printed text: every row's bytes column ends, and its note
begins, at the same character as every other row's (the ``peak`` row's bytes too)."""
from __future__ import annotations

import re

import pytest

from prt_torch.cli import main as cli_main
from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions, get_kind
from prt_torch.transfer.estimate import estimate, format_estimate

BYTES = re.compile(r"\d+(\.\d+)? (B|KiB|MiB|GiB|TiB)")


def _columns(rows: list[str]) -> list[tuple[int, int]]:
    """(end of the bytes field, start of what follows it) per row."""
    out = []
    for line in rows:
        m = BYTES.search(line)
        assert m, line
        rest = len(line) - len(line[m.end():].lstrip())
        out.append((m.end(), rest))
    return out


@pytest.fixture(scope="module")
def wavelet_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("w") / "w4.prt"
    get_kind("wavelet").precompute(builtin("occluder_over_plane"), {"res": 4, "terms": 24},
                                   run=RunOptions(workers=1, progress=False)).save(path)
    return path


def test_relight_wavelet_plan_columns_line_up(wavelet_file, tmp_path, capsys):
    capsys.readouterr()
    assert cli_main(["relight", str(wavelet_file), "--light", "sky", "-o", str(tmp_path / "o.npy"), "--dry-run"]) == 0
    rows = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("  ")]
    names = [ln.split()[0] for ln in rows]
    assert "build|light" in names and names[-1] == "peak", names
    cols = _columns(rows)
    assert len(set(cols)) == 1, list(zip(names, cols))
    assert {ln[2:cols[0][0]].split()[0] for ln in rows} == set(names)  # the name column holds the names only


@pytest.mark.parametrize("probe", [True, False], ids=["timed", "time-not-measured"])
def test_precompute_estimate_columns_line_up(probe):
    """Every row's bytes end, and its note starts, at the same characters, with the time measured (a probe) or not
    (``time not measured``, wider than the time column was)."""
    e = estimate(get_kind("wavelet"), builtin("occluder_over_plane"), {"res": 4, "terms": 24},
                 RunOptions(workers=1, progress=False), probe=probe, mesh_seconds=0.1 if probe else None)
    rows = format_estimate(e)
    assert any("time not measured" in r for r in rows) == (not probe)
    assert len({c[0] for c in _columns(rows)}) == 1, rows
    notes = [st["note"] for st in e.stages] + ["mesh + the larger"]
    assert len({r.index(n) for r, n in zip(rows, notes)}) == 1, rows


def test_relight_wavelet_dry_run_estimates_time(wavelet_file, tmp_path, capsys):
    """The wavelet dry run said 'time not estimated'; it now times a calibration relighter of the first rows (scaled to
    every row) and the light on the cube, as the SH path times its first chunk (no timed assertion: the figure is the
    benchmark's); nothing written."""
    out = tmp_path / "o.npy"
    capsys.readouterr()
    assert cli_main(["relight", str(wavelet_file), "--light", "sky", "--terms", "20", "-o", str(out), "--dry-run"]) == 0
    err = capsys.readouterr().err
    peak = next(ln for ln in err.splitlines() if ln.strip().startswith("peak"))
    assert "s relight (an estimate; calibration: loading" in peak and "relighter of the first 2048 rows" in peak, peak
    assert "time not estimated" not in err and not out.exists()
