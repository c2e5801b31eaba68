"""The all-frequency trade (``prt bench allfrequency``, harness/trade.py) timed the wavelets' plain call,
``relighter(idx, vals, out=out)``, while the kernel report (benchmarks/bench_wavelet.py) times
``WaveletRelighter.prepared``, the render-loop form: the plain call adds its per-call checks (1.2–2.3× the kernel
at small N). The trade's rows and headline now time the render-loop forms — wavelets ``prepared``, SH the product
into a reused output (:func:`prt_torch.harness.trade.sh_loop`) — with the plain call beside them (``call_s``), and
the report's tables say which. Checked by recording what each timing ran (no timed assertion), and ``sh_loop``
against :func:`prt_torch.relight.diffuse`."""
from __future__ import annotations

import json

import pytest
import torch

from prt_torch import relight
from prt_torch.cli import main as cli_main
from prt_torch.harness import trade


@pytest.mark.parametrize("shape,C", [((50, 9), 1), ((50, 9), 3), ((50, 3, 16), 1), ((50, 3, 16), 3)])
def test_sh_loop_equals_diffuse(shape, C):
    g = torch.Generator().manual_seed(1)
    T = torch.randn(*shape, generator=g)
    L = torch.randn(C, shape[-1], generator=g)
    run = trade.sh_loop(T, L)
    want = relight.diffuse(T, L)
    got = run()
    assert got.shape == want.shape and torch.allclose(got, want, rtol=1e-6, atol=1e-6)
    assert run() is got  # the output is reused


def test_trade_times_the_render_loop_forms(tmp_path, monkeypatch):
    timed: list[tuple[str, float]] = []  # (what was timed, its median)
    paired: list[tuple[str, str]] = []

    def name(fn) -> str:
        return fn.__qualname__

    real_measure, real_paired = trade.measure, trade.measure_paired

    def measure(fn, *a, **k):
        t = real_measure(fn, *a, **k)
        timed.append((name(fn), t.median))
        return t

    def measure_paired(fn, peer, *a, **k):
        paired.append((name(fn), name(peer)))
        return real_paired(fn, peer, *a, **k)

    monkeypatch.setattr(trade, "measure", measure)
    monkeypatch.setattr(trade, "measure_paired", measure_paired)
    assert cli_main(["bench", "allfrequency", "transfer.res=4", "transfer.terms=32", "render.enabled=false",
                     f"output_dir={tmp_path / 'r'}", f"cache_dir={tmp_path / 'c'}", "metrics.repeats=1", "name=t",
                     "trade.terms=[1, 10, 96]", "trade.bands=[2, 3, 4, 6]", "lights=[overcast]"]) == 0
    res = json.loads((tmp_path / "r" / "t" / "results.json").read_text())["trade"]
    loop = {"WaveletRelighter.prepared.<locals>.run", "sh_loop.<locals>.<lambda>", "sh_loop.<locals>.run"}
    medians = {m for n, m in timed if n in loop}
    calls = {m for n, m in timed if n not in loop}
    assert res["timed"] == "render_loop" and len(res["rows"]) == 3 + 4
    for x in res["rows"]:  # every row's relight time is a render-loop timing, its plain call one of the others
        assert x["relight_s"] in medians and x["call_s"] in calls and x["fps"] == pytest.approx(1 / x["relight_s"]), x
    assert paired and all(a in loop and b in loop for a, b in paired), paired
    h = res["headline"][0]
    for tgt in trade.TARGETS:  # the headline's cells are the rows that first reach each target
        for method, key in (("sh", "bands"), ("wavelet", "N")):
            rows = [x for x in res["rows"] if x["method"] == method]
            first = next((x for x in rows if x["error"] <= tgt), None)
            assert h[f"{method}_{tgt}"] == first
    md = (tmp_path / "r" / "t" / "report.md").read_text()
    assert "| SH to 5% (render loop) | wavelets to 5% (render loop) |" in md
    assert "| relight (render loop) | fps (render loop) | plain call |" in md
