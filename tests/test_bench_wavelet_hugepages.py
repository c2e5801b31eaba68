"""benchmarks/bench_wavelet_hugepages.py (issue 39, the dense layout on huge pages): bad options are refused in one
line before any work, and a run of some sizes replaces only those sizes' rows in the kept JSON (the other sizes' rows
and the load of the session that measured them stay), the report rendered from it."""

from __future__ import annotations

import json
import sys

import pytest


@pytest.fixture(scope="module")
def bh(bench_module):
    return bench_module("bench_wavelet_hugepages")


def _no_work(bh, monkeypatch):
    def no_work(*a, **k):
        raise AssertionError("work started before the options were checked")
    for f in ("pages_part", "spread_part", "prefetch_part", "avx2_part"):
        monkeypatch.setattr(bh, f, no_work)


@pytest.mark.parametrize("argv, says", [
    (["--parts", "pages,tlb"], "--parts 'pages,tlb'; accepted: a comma list of pages, spread, prefetch, avx2"),
    (["--repeats", "2"], "--repeats 2; accepted: an integer >= 3"),
    (["--processes", "1"], "--processes 1; accepted: an integer >= 2"),
    (["--sizes", "huge"], "--size huge: not a size; accepted: small, medium, large"),
])
def test_bad_option_is_one_line_before_any_work(bh, monkeypatch, capsys, argv, says):
    _no_work(bh, monkeypatch)
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_hugepages.py", *argv])
    with pytest.raises(SystemExit) as e:
        bh.main()
    text = str(e.value) if isinstance(e.value.code, str) else capsys.readouterr().err
    assert says in text and text.strip().count("\n") == 0


def test_bad_switch_is_one_line_before_any_work(bh, monkeypatch):
    _no_work(bh, monkeypatch)
    monkeypatch.setenv("PRT_TORCH_HUGEPAGES", "maybe")
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_hugepages.py", "--parts", "pages"])
    with pytest.raises(ValueError, match=r"^PRT_TORCH_HUGEPAGES='maybe'; accepted: 1 "):
        bh.main()


def _pair(r):
    return {"r": r, "q": [r - 0.01, r + 0.01], "us": [10.0, 10.0 * r], "tries": 1}


def _pages(bh, sizes, r):
    rows = [{"size": s, "light": "studio", "N": 10, "nd": 10, "mb": 0.1, "same": True, "hp": _pair(r), "aa": _pair(1.0),
             "sparse": _pair(1.0), "hp_read": _pair(0.5), "4k_read": _pair(0.4), "load": 1.0} for s in sizes]
    infos = [{"size": s, "V": 10, "Pd": 1, "held": {"dense": 2 ** 21, "total": 2 ** 22}, "held_same": True,
              "anon_huge_kb": {"hp": 2048, "4k": 0, bh.AA: 0, "hp+sparse": 2048}, "backed": {"hp+sparse": ["dense"]},
              "build": _pair(1.0)} for s in sizes]
    return {"rows": rows, "infos": infos}


def test_a_run_of_one_size_replaces_only_its_rows(bh, monkeypatch, tmp_path):
    out = tmp_path / "hp.md"
    monkeypatch.setattr(bh.torch, "set_num_threads", lambda n: None)  # main() sets one thread: not in the test process
    monkeypatch.setattr(bh, "pages_part", lambda sizes, repeats: _pages(bh, sizes, 1.5))
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_hugepages.py", "--parts", "pages", "--sizes", "small,large",
                                      "--write", str(out)])
    bh.main()
    monkeypatch.setattr(bh, "pages_part", lambda sizes, repeats: _pages(bh, sizes, 1.25))
    monkeypatch.setattr(sys, "argv", ["bench_wavelet_hugepages.py", "--parts", "pages", "--sizes", "large",
                                      "--repeats", "5", "--write", str(out)])
    bh.main()
    res = json.loads(out.with_suffix(".json").read_text())
    got = {r["size"]: r["hp"]["r"] for r in res["pages"]["rows"]}
    assert got == {"small": 1.5, "large": 1.25}
    assert [(m["sizes"], m["repeats"]) for m in res["pages"]["sessions"]] == [(["small"], 11), (["large"], 5)]
    md = out.read_text()
    assert "| small | studio | 10 | 10 | 0.10 |" in md and "**1.50 [1.49, 1.51]**" in md and "**1.25 [1.24, 1.26]**" in md
    assert "(small, 11 repeats)" in md and "(large, 5 repeats)" in md
