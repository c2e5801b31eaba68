"""benchmarks/bench_relight_split.py: the two threads' ranges it times alone are exactly a two-thread call's
(together the whole call's bits, with and without a cluster-sorted visiting order, rows and dense views), the work it
counts per range is the codes' (points, multiply-adds J·n_out·C), and bad --rows are refused naming the item."""
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
import torch

from prt_torch import codecs
from prt_torch.codecs import affine, relight_kernels
from prt_torch.codecs.synthetic import transfer_like

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import bench_relight_split  # noqa: E402


@pytest.mark.parametrize("name,params,sort", [("cpca_static", {"clusters": 7, "vectors": 3, "max_iter": 5}, True),
                                              ("cpca_static", {"clusters": 7, "vectors": 3, "max_iter": 5}, False),
                                              ("mrt_pca", {"vectors": 4}, False)])
@pytest.mark.parametrize("kind", ["rows", "dense"])
def test_two_ranges_alone_write_the_whole_call(name, params, sort, kind, monkeypatch):
    lib = relight_kernels.native()
    if lib is None:
        pytest.skip("no compiled kernels")
    monkeypatch.setattr(affine, "SORT_MIN_CLUSTER_BYTES", 0 if sort else 1 << 60)
    P, n_out = 301, 20
    c = codecs.get(name, **params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(transfer_like(P, n_out, 6, seed=3, regions=8), matrix_shape=(n_out, 6))
    L = torch.randn(6, 3, generator=torch.Generator().manual_seed(1))
    y = torch.randn(P, n_out, generator=torch.Generator().manual_seed(2)) if kind == "dense" else None
    pl = c._kernel_plan(lib, enc, c._n_eff(None), kind, 3, 0)
    assert (pl.keep[5] is not None) == (sort and name != "mrt_pca")
    whole = c.relight(enc, L, view=y)
    out = torch.full(whole.shape, float("nan"))
    T = relight_kernels._scratch(pl.kind, pl.size)
    row = out[0].numel() * 4
    for q0, q1 in ((0, 150), (150, P)):
        a, r = bench_relight_split.sub_plan(pl, q0, q1)
        lib.prt_relight_plan(a.data_ptr(), L.contiguous().data_ptr(), T.data_ptr(), out.data_ptr() + r * row,
                             None if y is None else y.data_ptr() + r * n_out * 4, None, 1)
    assert torch.equal(out.view(torch.int32), whole.view(torch.int32))
    w = [bench_relight_split.work(c, pl, 0, 150, "none" if y is None else "dense"),
         bench_relight_split.work(c, pl, 150, P, "none" if y is None else "dense")]
    J = int(c.n_vectors_.max()) + (1 if c.means_ is not None else 0)
    per = J * n_out * 3 + (n_out * 3 if y is not None else 0)
    assert [x["points"] for x in w] == [150, 151] and [x["macs"] for x in w] == [150 * per, 151 * per]
    assert sum(x["runs"] + x["same_next"] for x in w) == P


def test_bad_rows_are_refused_naming_them():
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_relight_split.py"), "--rows", "vq:none", "--out", "-"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "--rows item 'vq:none'; accepted: codec:view" in r.stderr, r.stderr
