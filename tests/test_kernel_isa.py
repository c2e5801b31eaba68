"""The relight kernels' instruction-set choice and path report (issue 42 §4).

``PRT_TORCH_KERNEL_ISA`` (``native`` | ``avx2`` | ``avx512``) selects which ``#if`` branches of
prt_torch/kernels/*.c are compiled; it is read once per process, so each choice runs in a
subprocess here. Every build is checked against a float64 reference computed without the kernels
(the decoded matrices times the light, and the view applied, in float64: Sloan 2003 eq. (6) and
§3.1, Lehtinen & Kautz 2003 eq. (13)), within float32 rounding; ``kernel_path`` must name the build
it loaded and a point kernel for every row.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest
import torch

from prt_torch import _native
from prt_torch.codecs.relight_kernels import native

pytestmark = pytest.mark.skipif(native() is None, reason="no C compiler: the kernels are not built")

_SCRIPT = r"""
import json, sys, torch
from prt_torch import codecs
from prt_torch.codecs.relight_kernels import kernel_path
from prt_torch.codecs.synthetic import tent_taps_random, transfer_like
torch.manual_seed(0)
P = 600
cases = [("vq", {"clusters": 16}, transfer_like(P, 24, 25, seed=0), (24, 25)),
         ("pca", {"vectors": 8}, transfer_like(P, 24, 25, seed=0), (24, 25)),
         ("cpca_static", {"clusters": 8, "vectors": 8}, transfer_like(P, 24, 25, seed=0), (24, 25)),
         ("mrt_pca", {"vectors": 16}, transfer_like(P, 49, 25, seed=3), (49, 25)),
         ("vq", {"clusters": 16}, transfer_like(P, 1, 16, seed=5), None),
         ("pca", {"vectors": 8}, transfer_like(P, 1, 16, seed=5), None),
         ("cpca_static", {"clusters": 8, "vectors": 4}, transfer_like(P, 1, 16, seed=5), None)]
out = {"build": kernel_path(), "rows": []}
for name, params, X, ms in cases:
    c = codecs.get(name, **params)
    enc = c.fit_encode(X, matrix_shape=ms) if ms else c.fit_encode(X)
    n_out, n_in = ms or (1, X.shape[1])
    L = torch.randn(n_in, 3)
    M = c.decode(enc).double().reshape(P, n_out, n_in)
    E = torch.einsum("poi,ic->poc", M, L.double())  # exit radiance per output row, float64
    views = [("none", None, E if ms else E[:, 0])]
    if ms:
        y = torch.randn(P, n_out)
        views.append(("dense", y, torch.einsum("po,poc->pc", y.double(), E)))
    if name == "mrt_pca":
        idx, g = tent_taps_random(P, 7, seed=4)
        views.append(("taps", (idx, g), (E[torch.arange(P)[:, None], idx] * g.double()[..., None]).sum(1)))
    for mode, view, ref in views:
        got = c.relight(enc, L, view=view).double()
        scale = float(ref.abs().max())
        out["rows"].append({"codec": name, "signal": "matrix" if ms else "vector", "view": mode,
                            "path": c.kernel_path(enc, view)["path"], "err": float((got - ref).abs().max()) / scale})
print(json.dumps(out))
"""


def _run(isa: str | None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("PRT_TORCH_KERNEL_ISA", "PRT_TORCH_NATIVE")}
    if isa is not None:
        env["PRT_TORCH_KERNEL_ISA"] = isa
    return subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, env=env, timeout=600)


def _check_build(isa: str | None, want_isa: str, w16: bool | None = None) -> None:
    r = _run(isa)
    assert r.returncode == 0, r.stderr[-2000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    b = res["build"]
    assert b["backend"] == "native" and b["isa"] == want_isa, b
    assert b["isa_choice"] == (isa or "native")
    w16 = (want_isa == "avx512") if w16 is None else w16
    assert b["w16"] == w16 and b["sg16"] == w16
    for row in res["rows"]:
        # float32 rounding of sums of ~25 terms of O(scale): a few 1e-7 relative; 1e-5 fails on a wrong layout or branch
        assert row["err"] < 1e-5, row
        assert row["path"] and not row["path"].startswith(("code ", "torch")), row
    paths = {(r["codec"], r["signal"], r["view"]): r["path"] for r in res["rows"]}
    assert paths[("vq", "matrix", "none")] == "rows: VQ row copy"  # the mean's row copied per point: no weights
    assert paths[("mrt_pca", "matrix", "taps")].startswith("taps:")
    # the 16-lane kernels are the AVX-512 build's alone (not avx512-256's)
    assert any("16 lanes" in p for p in paths.values()) == w16, paths


def test_avx2_build_matches_float64_reference():
    if _native.cpu_isa() not in ("avx2", "avx512"):
        pytest.skip(f"this CPU has {_native.cpu_isa()}: no AVX2 build")
    _check_build("avx2", "avx2")


def test_native_build_names_this_cpus_isa():
    _check_build(None, _native.cpu_isa())


@pytest.mark.parametrize("isa", ["avx512", "avx512-256"])
def test_avx512_builds_or_one_line_refusal(isa):
    if _native.cpu_isa() == "avx512":
        _check_build(isa, "avx512", w16=isa == "avx512")
        return
    r = _run(isa)
    assert r.returncode != 0
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith(f"ValueError: PRT_TORCH_KERNEL_ISA='{isa}'") and "accepted here: native" in last, last


def test_invalid_value_is_one_clear_line(monkeypatch):
    for bad in ("sse9", "AVX-512", "512", "avx512-512"):
        monkeypatch.setenv("PRT_TORCH_KERNEL_ISA", bad)
        with pytest.raises(ValueError) as e:
            _native.kernel_isa()
        msg = str(e.value)
        assert "\n" not in msg and f"PRT_TORCH_KERNEL_ISA={bad!r}" in msg and "accepted: native" in msg and "avx2" in msg
    for ok, extra in (("", ()), ("native", ()), (" AVX2 ", ("-mno-avx512f",))):
        monkeypatch.setenv("PRT_TORCH_KERNEL_ISA", ok)
        if _native.cpu_isa() in ("avx2", "avx512") or ok.strip() in ("", "native"):
            assert _native.kernel_isa()[1] == extra


def test_kernel_path_in_process_names_a_kernel_per_view():
    from prt_torch import codecs
    from prt_torch.codecs.synthetic import transfer_like

    X = transfer_like(300, 24, 25, seed=0)
    c = codecs.get("cpca_static", clusters=4, vectors=4)
    enc = c.fit_encode(X, matrix_shape=(24, 25))
    rows, dense = c.kernel_path(enc), c.kernel_path(enc, torch.randn(300, 24))
    assert rows["path"].startswith("rows") and dense["path"].startswith("dense"), (rows, dense)
    assert rows["threads"] == torch.get_num_threads() and rows["cpu_isa"] == _native.cpu_isa()


def test_check_isa_list_checks_each_value_and_leaves_the_variable(monkeypatch):
    """_native.check_isa_list (the benchmarks' --isa): each value checked as kernel_isa would, the variable as before."""
    from prt_torch._native import check_isa_list

    monkeypatch.setenv("PRT_TORCH_KERNEL_ISA", "native")
    assert check_isa_list(" native, ,native ") == ["native", "native"]
    with pytest.raises(ValueError, match="PRT_TORCH_KERNEL_ISA='bogus'; accepted: native"):
        check_isa_list("native,bogus")
    assert os.environ["PRT_TORCH_KERNEL_ISA"] == "native"
    monkeypatch.delenv("PRT_TORCH_KERNEL_ISA")
    assert check_isa_list("") == [] and "PRT_TORCH_KERNEL_ISA" not in os.environ
