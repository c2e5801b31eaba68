"""benchmarks/bench_wavelet_scratch.py (issue 39, the sparse scratch zero between calls and the RGB interleave): bad
input is refused in one line naming the option, the value and what is accepted, before any kernel is built; every
variant is a ``#define`` the kernel reads (guarded: ``#ifndef`` / ``#ifdef`` / ``defined``)."""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bs(bench_module):
    return bench_module("bench_wavelet_scratch")


@pytest.mark.parametrize("argv, says", [
    (["--variants", "touch8,fast"], "--variants 'fast'; accepted: a comma-separated list of touch8, outpf"),
    (["--variants", "touch8+fast"], "--variants 'touch8+fast'; accepted:"),
    (["--calls", "0"], "--calls 0; accepted: an integer >= 1"),
    (["--repeats", "2"], "--repeats 2; accepted: an integer >= 3"),
    (["--evict-mb", "0"], "--evict-mb 0.0; accepted: a number > 0"),
    (["--terms", "10,x"], "--terms '10,x'; accepted: comma-separated integers >= 1"),
    (["--terms", "0"], "--terms '0'; accepted: comma-separated integers >= 1"),
    (["--s7-terms", "x"], "--s7-terms 'x'; accepted: comma-separated integers"),
    (["--base-dense-min", "x"], "--base-dense-min 'x'; accepted: a number > 0, or 'third'"),
    (["--base-dense-min", "0"], "--base-dense-min '0'; accepted: a number > 0, or 'third'"),
    (["--base-tile", "100"], "--base-tile '100'; accepted: a positive multiple of 32, or 'half'"),
    (["--base-tile", "third"], "--base-tile 'third'; accepted: a positive multiple of 32, or 'half'"),
    (["--base-first"], "--base-first without a layout of the base's own; accepted: with --base-tile or --base-dense-min"),
])
def test_bad_option_is_one_line_before_any_build(bs, monkeypatch, argv, says):
    def no_work(*a, **k):
        raise AssertionError("a kernel was built before the options were checked")

    monkeypatch.setattr(bs, "builds", no_work)
    monkeypatch.setattr(bs, "avx2_text_same", no_work)
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_scratch.py", *argv])
    with pytest.raises(SystemExit) as e:
        bs.main()
    msg = str(e.value.code)
    assert msg.count("\n") == 0 and msg.startswith("bench_wavelet_scratch.py: ") and says in msg


def test_variants_are_defines_the_kernel_reads(bs):
    src = (ROOT / "prt_torch/kernels/wavelet.c").read_text()
    for name, text in bs.VARIANTS.items():
        m = re.fullmatch(r"#define (\w+) .+\n", text)
        assert m, name
        macro = m.group(1)
        assert f"#ifndef {macro}" in src or f"#ifdef {macro}" in src or f"defined({macro})" in src, (name, macro)


@pytest.mark.parametrize("argv, says", [
    (["--placements", "1"], "--placements 1; accepted: at least 2"),
    (["--repeats", "2"], "--repeats 2; accepted: at least 3"),
])
def test_tile_bench_bad_option_is_one_line_before_any_work(bench_module, monkeypatch, argv, says):
    """bench_wavelet_tile.py (the default tile across placements) refuses bad input in one line before building."""
    bt = bench_module("bench_wavelet_tile")

    def no_work(*a, **k):
        raise AssertionError("a transfer was built before the options were checked")

    monkeypatch.setattr(bt, "kernel_transfer", no_work)
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_tile.py", *argv])
    with pytest.raises(SystemExit) as e:
        bt.main()
    msg = str(e.value.code)
    assert msg.count("\n") == 0 and msg.startswith("bench_wavelet_tile.py: ") and says in msg
