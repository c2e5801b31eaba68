"""benchmarks/bench_wavelet_hugepages_small.py (issue 39, the small layout and the streaming read on huge pages): bad
options are refused in one line before any work."""

from __future__ import annotations

import sys

import pytest


@pytest.fixture(scope="module")
def bs(bench_module):
    return bench_module("bench_wavelet_hugepages_small")


@pytest.mark.parametrize("argv, says", [
    (["--parts", "bound,tlb"], "--parts 'bound,tlb'; accepted: a comma list of bound, buffers, pairs, fresh, relighters, "
                               "drift, corunner"),
    (["--repeats", "2"], "--repeats 2; accepted: an integer >= 3"),
    (["--processes", "1"], "--processes 1; accepted: an integer >= 2"),
    (["--mb", "0.3,big"], "--mb '0.3,big'; accepted: a comma list of positive sizes in MB"),
    (["--mb", "-1"], "--mb '-1'; accepted: a comma list of positive sizes in MB"),
    (["--buffers", "0"], "--buffers 0; accepted: an integer >= 1"),
    (["--interval", "0"], "--minutes 20.0 --interval 0.0; accepted: positive numbers"),
])
def test_bad_option_is_one_line_before_any_work(bs, monkeypatch, argv, says):
    def no_work(*a, **k):
        raise AssertionError("work started before the options were checked")
    for f in ("bound_part", "buffers_part", "pairs_part", "fresh_part", "relighters_part", "drift_part", "corunner_part"):
        monkeypatch.setattr(bs, f, no_work)
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_hugepages_small.py", *argv])
    with pytest.raises(SystemExit) as e:
        bs.main()
    assert says in str(e.value) and str(e.value).count("\n") == 0
