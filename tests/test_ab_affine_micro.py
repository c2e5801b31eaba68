"""benchmarks/ab_affine_micro.py, the bare-C A/B of the taps, one-vector rows and dense-view kernels: it builds
both revisions' kernels into programs, runs them and reports equal results for equal sources; bad
arguments are refused naming the option."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TOOL = ROOT / "benchmarks" / "ab_affine_micro.py"


@pytest.mark.skipif(shutil.which("cc") is None and shutil.which("gcc") is None, reason="no C compiler")
@pytest.mark.skipif(not (ROOT / ".git").exists(), reason="not a git checkout")
def test_same_source_gives_the_same_result_and_a_ratio_near_one():
    r = subprocess.run([sys.executable, str(TOOL), "--base", ".", "--test", ".", "--rounds", "2", "--reps", "3",
                        "--points", "1001"], capture_output=True, text=True, cwd=ROOT, timeout=600)
    assert r.returncode == 0, r.stderr
    rows = [line for line in r.stdout.splitlines() if line.startswith(("| taps", "| rows", "| dense"))]
    assert len(rows) == 3 and all(line.rstrip().endswith("| True |") for line in rows), r.stdout
    ratios = [float(line.split("**")[1]) for line in rows]
    assert all(0.2 < x < 5 for x in ratios), r.stdout  # timings are real numbers, not placeholders


def test_bad_arguments_are_refused_naming_them():
    r = subprocess.run([sys.executable, str(TOOL), "--points", "0"], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode != 0 and "--points 0; accepted: a positive integer" in r.stderr
