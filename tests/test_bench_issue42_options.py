"""benchmarks/bench_face_probe.py and bench_transport_reference.py: bad options named in one line, status 2, no traceback,
before any precompute."""
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


@pytest.mark.parametrize("args,msg", [(["--config", "nope"], "config 'nope' not found; accepted:"),
                                      (["--config", "default"], "config transfer type 'mrt'; accepted: transport"),
                                      (["--config", "default", "--part", "nope"], "--part 'nope': the config has parts"),
                                      (["--set", "foo=1"], "unknown key 'foo'; accepted:")])
def test_bench_transport_reference_refuses_bad_options(args, msg, tmp_path):
    """benchmarks/bench_transport_reference.py (issue 42 §2's before/after rows): the same rule."""
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_transport_reference.py"), *args, "--out",
                        str(tmp_path / "o")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert not list(tmp_path.iterdir())
