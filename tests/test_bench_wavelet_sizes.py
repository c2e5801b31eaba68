"""benchmarks/bench_wavelet.py's ``--size`` for the kernel section (issue 39, section 7 at the sizes users relight):
bad input is refused in one line before any work, and a run of one size replaces only the kept run of its own CPU,
build and size (runs from before ``--size`` count as the small mesh's)."""

from __future__ import annotations

import sys

import pytest


@pytest.fixture(scope="module")
def bw(bench_module):
    return bench_module("bench_wavelet")


@pytest.mark.parametrize("argv, says", [
    (["--only", "kernel", "--size", "huge"], "--size huge: not a size; accepted: small, medium, large"),
    (["--only", "kernel", "--size", "xl"], "--size xl: not a size; accepted: small, medium, large"),
    (["--only", "quant", "--size", "large"], "--size large: section 7 only; accepted: with --only kernel (given: --only quant)"),
    (["--size", "medium"], "--size medium: section 7 only; accepted: with --only kernel"),
])
def test_bad_size_is_one_line_before_any_work(bw, monkeypatch, capsys, argv, says):
    def no_work(*a, **k):
        raise AssertionError("work started before --size was checked")

    monkeypatch.setattr(bw, "kernel_only", no_work)
    monkeypatch.setattr(bw, "section_only", no_work)
    monkeypatch.setattr(bw, "isa_runs", no_work)
    monkeypatch.setattr(sys, "argv", ["bench_wavelet.py", *argv])
    with pytest.raises(SystemExit) as e:
        bw.main()
    assert e.value.code == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("bench_wavelet.py: ") and says in err


@pytest.mark.parametrize("size", [None, "small", "medium", "large"])
def test_good_size_is_accepted(bw, size):
    assert bw.check_size(size, "kernel") == (size or "small")
    assert bw.size_choice(size, "bench_wavelet_rowpass.py") == (size or "small")


@pytest.mark.parametrize("only", [None, "quant", "sampling"])
def test_no_size_is_the_small_mesh_for_every_section(bw, only):
    assert bw.check_size(None, only) == "small"


def test_size_choice_names_the_benchmark(bw, capsys):
    with pytest.raises(SystemExit) as e:
        bw.size_choice("Large", "bench_wavelet_dense16.py")
    assert e.value.code == 2
    assert capsys.readouterr().err.strip() == "bench_wavelet_dense16.py: --size Large: not a size; accepted: small, medium, large"


def _run(cpu: str, isa: str, size: str | None, tag: str) -> dict:
    run = {"machine": {"cpu": cpu, "cpu_family": "6", "cpu_model": "167", "cpu_isa": "avx512"},
           "build": {"backend": "native", "isa": isa, "isa_choice": "native" if isa == "avx512" else "avx2", "w16": isa == "avx512"},
           "rows": [{"tag": tag}]}
    if size is not None:
        run["size"] = size
    return run


def test_a_run_of_one_size_keeps_the_other_sizes_rows(bw):
    old_small = [_run("Xeon", "avx512", None, "old small 512"), _run("Xeon", "avx2", None, "old small avx2"),
                 _run("EPYC", "avx2", None, "epyc small")]
    res = {"kernel_runs": list(old_small)}
    bw.merge_kernel_runs(res, [_run("Xeon", "avx512", "medium", "medium 512"), _run("Xeon", "avx2", "medium", "medium avx2")])
    tags = sorted(r["rows"][0]["tag"] for r in res["kernel_runs"])
    assert tags == ["epyc small", "medium 512", "medium avx2", "old small 512", "old small avx2"]
    # a large run of one build: the medium and small runs stay, and a second large run of that build replaces the first
    bw.merge_kernel_runs(res, [_run("Xeon", "avx512", "large", "large 512 a")])
    bw.merge_kernel_runs(res, [_run("Xeon", "avx512", "large", "large 512 b")])
    tags = sorted(r["rows"][0]["tag"] for r in res["kernel_runs"])
    assert tags == ["epyc small", "large 512 b", "medium 512", "medium avx2", "old small 512", "old small avx2"]
    # a small run (the default size, recorded as such) replaces the small run from before --size of its CPU and build only
    bw.merge_kernel_runs(res, [_run("Xeon", "avx512", "small", "new small 512")])
    tags = sorted(r["rows"][0]["tag"] for r in res["kernel_runs"])
    assert tags == ["epyc small", "large 512 b", "medium 512", "medium avx2", "new small 512", "old small avx2"]
    assert len({bw.kernel_run_key(r) for r in res["kernel_runs"]}) == len(res["kernel_runs"])


def test_bytes_home_names_the_level_that_holds_them(bw):
    caches = {"l2_bytes": 2 * 2 ** 20, "l3_bytes": 480 * 2 ** 20}
    assert bw.bytes_home(2 ** 20, caches).startswith("L2 (0.50 of 2 MiB)")
    assert bw.bytes_home(2 * 2 ** 20 + 1, caches).startswith("L3 (1.0× L2)")
    assert bw.bytes_home(10 * 2 ** 20, caches).startswith("L3 (5.0× L2)")
    assert bw.bytes_home(481 * 2 ** 20, caches) == "memory"
