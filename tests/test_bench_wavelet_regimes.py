"""benchmarks/bench_wavelet_regimes.py (issue 39, the dense loop's prefetch in three cache regimes): bad input is
refused in one line naming the option, the value and what is accepted, before any kernel is built; every variant
is a set of ``#define`` lines the kernel guards (``#ifndef``), and the in-unit variants keep the base's threshold;
the 8-lane variants (--isa avx2) take PF_X8 on every layout; one evicted regime per --evict-mb size."""

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
    (["--evict-mb", "0.1"], "--evict-mb '0.1'; accepted: comma-separated distinct sizes 0.5 to 64 (MB)"),
    (["--evict-mb", "3,x"], "--evict-mb '3,x'; accepted: comma-separated distinct sizes 0.5 to 64 (MB)"),
    (["--evict-mb", "3,3"], "--evict-mb '3,3'; accepted: comma-separated distinct sizes 0.5 to 64 (MB)"),
    (["--isa", "sse"], "--isa 'sse'; accepted: one of native, avx2, avx512, avx512-256"),
    (["--isa", "avx2", "--variants", "x8,pfx0"], "--variants 'pfx0' with --isa avx2: it leaves that build's dense loop "
     "as the base's; accepted with --isa avx2: x8, x8pfx12, x8pfx48"),
    (["--variants", "x8"], "--variants 'x8' with --isa native: it leaves that build's dense loop as the base's; "
     "accepted with --isa native: pfx0,"),
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
    for name, lines in [("base", br.BASE), ("base_x8", br.BASE_X8), *br.VARIANTS.items()]:
        for line in lines.strip().splitlines():
            macro = line.split()[1]
            assert line.startswith("#define ") and (f"#ifndef {macro}" in text or f"defined({macro})" in text), (name, line)
    for name in ("pf3", "pf10", "pf16", "next"):
        assert br.BASE in br.VARIANTS[name], name  # at small they replace the in-unit loop the base runs


def test_one_evicted_regime_per_size_between_warm_and_cold(br):
    assert br.regimes([3.0]) == [("warm", None), ("evicted", 3 << 20), ("cold", None)]
    assert br.regimes([3.0, 1.5]) == [("warm", None), ("evicted 3 MB", 3 << 20), ("evicted 1.5 MB", 3 << 19), ("cold", None)]


def test_the_8_lane_variants_take_the_far_prefetch_on_every_layout(br):
    for name in br.X8:
        assert "#define PF_X8 1" in br.VARIANTS[name] and "#define PFX_MIN 0LL" in br.VARIANTS[name], name


def test_native_on_a_cpu_without_avx512_is_an_8_lane_build(br, monkeypatch):
    """On an AVX2-only CPU (the AMD Zen 3) the native build runs the 8-lane loop: its base is the code without the far
    prefetch and the x8 variants are its own; on an AVX-512 CPU native is the 16-lane build."""
    monkeypatch.setattr(br, "cpu_isa", lambda: "avx2")
    assert br.is_8lane("native") and br.base_lines("native") == br.BASE_X8
    monkeypatch.setattr(br, "cpu_isa", lambda: "avx512")
    assert not br.is_8lane("native") and br.base_lines("native") == br.BASE
    assert br.is_8lane("avx2") and br.is_8lane("avx512-256")
