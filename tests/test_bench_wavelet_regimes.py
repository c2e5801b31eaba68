"""benchmarks/bench_wavelet_regimes.py (issue 39, the dense loop's prefetch in three cache regimes): bad input is
refused in one line naming the option, the value and what is accepted, before any kernel is built; every variant
is a set of ``#define`` lines the kernel guards (``#ifndef``), and the in-unit variants keep the base's threshold."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def br(bench_module):
    return bench_module("bench_wavelet_regimes")


@pytest.mark.parametrize("argv, says", [
    (["--variants", "pfx0,fast"], "--variants 'fast'; accepted: a comma-separated list of pfx0, pfx512k"),
    (["--calls", "0"], "--calls 0; accepted: an integer >= 1"),
    (["--repeats", "2"], "--repeats 2; accepted: an integer >= 3"),
    (["--evict-mb", "0.1"], "--evict-mb 0.1; accepted: 0.5 to 64 (MB)"),
    (["--terms", "10,x"], "--terms '10,x'; accepted: comma-separated integers >= 1"),
    (["--terms", "0"], "--terms '0'; accepted: comma-separated integers >= 1"),
])
def test_bad_option_is_one_line_before_any_build(br, monkeypatch, argv, says):
    def no_work(*a, **k):
        raise AssertionError("a kernel was built before the options were checked")

    monkeypatch.setattr(br, "builds", no_work)
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_regimes.py", *argv])
    with pytest.raises(SystemExit) as e:
        br.main()
    msg = str(e.value.code)
    assert msg.count("\n") == 0 and msg.startswith("bench_wavelet_regimes.py: ") and says in msg


def test_variants_are_guarded_defines_and_the_in_unit_ones_keep_the_base_threshold(br):
    text = (ROOT / "prt_torch" / "kernels" / "wavelet.c").read_text()
    for name, lines in [("base", br.BASE), *br.VARIANTS.items()]:
        for line in lines.strip().splitlines():
            macro = line.split()[1]
            assert line.startswith("#define ") and (f"#ifndef {macro}" in text or f"defined({macro})" in text), (name, line)
    for name in ("pf3", "pf10", "pf16", "next"):
        assert br.BASE in br.VARIANTS[name], name  # at small they replace the in-unit loop the base runs
