"""benchmarks/bench_face_probe.py: bad options named in one line, status 2, no traceback, before any precompute."""
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("args,msg", [(["--scenes", "nope:small"], "--scenes item 'nope:small'; accepted: NAME:SIZE"),
                                      (["--scenes", "cornell_box"], "--scenes item 'cornell_box'; accepted: NAME:SIZE"),
                                      (["--samples", "64", "0"], "--samples 0; accepted: integers >= 1"),
                                      (["--compare", "/nonexistent.json", "b.json"], "--compare '/nonexistent.json': no such file")])
def test_bad_options_are_refused_naming_them(args, msg, tmp_path):
    out = tmp_path / "o.md"
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_face_probe.py"), *args, "--out", str(out)],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not out.exists()
