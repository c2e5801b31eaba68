"""``WaveletRelighter.row_min``'s default per kernel build (issue 39): the row-major sparse pass from
:attr:`~prt_torch.relight.WaveletRelighter.ROW_MIN_W16` of the sparse blocks in the AVX-512 builds with the 16-lane code,
from :attr:`~prt_torch.relight.WaveletRelighter.ROW_MIN` (0.5, the AMD Zen 3's crossover) in the others; an explicit
``row_min`` wins; either pass equals a dense float64 sum over the Haar terms for lights on either side of each
threshold (reports/benchmarks/wavelet_rowmin.md has the measured crossovers)."""

from __future__ import annotations

import pytest
import torch

from prt_torch import relight
from prt_torch.scene import builtin
from prt_torch.transfer import Transfer

W = relight.WaveletRelighter
W16 = {"backend": "native", "isa": "avx512", "w16": True}
W16V = {**W16, "vnni": True}  # the dense loop on integer dot products (DENSE_VNNI compiled in)
NO_W16 = ({"backend": "native", "isa": "avx2", "w16": False}, {"backend": "native", "isa": "avx512", "w16": False},
          {"backend": "torch"})


def test_row_min_default_follows_the_kernel_build(monkeypatch):
    """The W16 build's record gives ROW_MIN_W16; AVX2, avx512-256 (no W16) and the torch formulation 0.5; without a
    record, this process's build as :func:`relight.wavelet_kernel_path` names it (read once, then kept)."""
    assert W.ROW_MIN == 0.5
    assert 0.5 < W.ROW_MIN_W16 <= 1
    assert W.default_row_min(W16) == W.ROW_MIN_W16
    for rec in NO_W16:
        assert W.default_row_min(rec) == 0.5, rec
    monkeypatch.delitem(relight._WAVELET, "row_min_path", raising=False)
    assert W.default_row_min() == W.default_row_min(relight.wavelet_kernel_path())
    monkeypatch.setitem(relight._WAVELET, "row_min_path", W16)  # the record is read once: kept after
    assert W.default_row_min() == W.ROW_MIN_W16


def test_dense_min_default_follows_the_kernel_build(monkeypatch):
    """16-bit values in the W16 build with the VNNI dense loop: DENSE_MIN_W16 (0.2); every other build (the W16 float
    loop too), the torch formulation and the other value sizes keep the bytes rule b/(4+b); without a record, this
    process's build; an explicit ``dense_min`` wins."""
    assert W.DENSE_MIN_W16 == 0.2
    assert W.default_dense_min(2, W16V) == 0.2
    assert W.default_dense_min(2, W16V, arith="float") == 2 / 6  # the opt-out runs the float loop: the bytes rule
    for b in (1, 4):
        assert W.default_dense_min(b, W16V) == b / (4 + b)
    for rec in (W16, *NO_W16):
        for b in (1, 2, 4):
            assert W.default_dense_min(b, rec) == b / (4 + b), (rec, b)
    monkeypatch.delitem(relight._WAVELET, "row_min_path", raising=False)
    assert W.default_dense_min(2) == W.default_dense_min(2, relight.wavelet_kernel_path())


def test_dense_min_default_layout_equals_the_dense_sum(transfer, monkeypatch):
    """A transfer with columns kept by ~27% of the vertices (between 0.2 and 1/3): dense in a relighter whose build
    record is W16 with the VNNI loop, sparse under the others' bytes rule (and with an explicit ``dense_min`` = 1/3, or
    ``arith='float'``, which runs the float loop);
    each relights as the dense float64 sum over the Haar terms (scale and albedo applied)."""
    _, _, alb = transfer
    scene = builtin("occluder_over_plane", "small")
    g = torch.Generator().manual_seed(392)
    V, res, K = scene.num_vertices, 8, 12
    P = 6 * res * res
    # columns 0-7 kept by every vertex, 8-15 by the ~27% of vertices of a random mask each, the rest rare
    w = torch.rand(V, P, generator=g)
    w[:, :8] += 100.0
    w[:, 8:16] += 50.0 * (torch.rand(V, 8, generator=g) < 0.27)
    index = w.topk(K, dim=1).indices
    q = torch.randint(-32767, 32768, (V, K), generator=g).to(torch.int16)
    scale = torch.rand(V, generator=g) + 0.5
    tr = Transfer("wavelet", q, scene, {"res": res, "terms": K, "bits": 16}, aux={"index": index.to(torch.int16), "scale": scale})
    dense = torch.zeros(V, P, dtype=torch.float64).scatter_(1, index, q.double() * scale.double()[:, None])
    li = torch.arange(P)
    lv = torch.rand(3, P, generator=g) + 0.1
    ref = (lv.double() @ dense.T).T * alb
    for rec, dmin, want, arith in ((W16V, None, 16, "auto"), (W16, None, 8, "auto"), (NO_W16[0], None, 8, "auto"),
                                   (NO_W16[2], None, 8, "auto"), (W16V, 1 / 3, 8, "auto"), (W16V, None, 8, "float")):
        monkeypatch.setitem(relight._WAVELET, "row_min_path", rec)
        r = W(tr, threads=1, dense_min=dmin, arith=arith)
        assert r.Pd == want, (rec, dmin, arith, r.Pd)
        assert r.dense_min == (W.default_dense_min(2, rec, arith=arith) if dmin is None else dmin)
        got = r(li, lv).double()
        if r.kernel_path()["dense"] == "int16 vnni":  # this CPU's build runs the VNNI loop (rec only picks the layout)
            from test_wavelet_isa import _within_vnni_bound

            assert _within_vnni_bound(r, got, ref, li, lv, albedo=True), (rec, dmin)
        else:
            assert (got - ref).abs().max() <= 1e-5 * float(ref.abs().max()) + 1e-6, (rec, dmin)


@pytest.fixture(scope="module")
def transfer():
    """A 16-bit grey wavelet transfer of random values at R = 8 on the small blocker scene (2251 vertices, K = 24: the
    first 16 columns kept by most vertices, dense; the rest sparse) and its values in float64 ``[V, P]`` (zeros where a
    vertex keeps no coefficient) and the albedo ``[V, 3]`` the relighter applies to an RGB light."""
    scene = builtin("occluder_over_plane", "small")
    g = torch.Generator().manual_seed(391)
    V, res, K = scene.num_vertices, 8, 24
    P = 6 * res * res
    index = (torch.rand(V, P, generator=g) * torch.where(torch.arange(P) < 16, 50.0, 1.0)).topk(K, dim=1).indices
    q = torch.randint(-32767, 32768, (V, K), generator=g).to(torch.int16)
    scale = torch.rand(V, generator=g) + 0.5
    tr = Transfer("wavelet", q, scene, {"res": res, "terms": K, "bits": 16}, aux={"index": index.to(torch.int16), "scale": scale})
    dense = torch.zeros(V, P, dtype=torch.float64).scatter_(1, index, q.double() * scale.double()[:, None])
    return tr, dense, scene.albedo.double()[:, :3]


def _light(r: W, share: float, g: torch.Generator) -> tuple[torch.Tensor, torch.Tensor, float]:
    """Every dense column and, in a random order, the sparse columns until their blocks reach ``share`` of the sparse
    blocks; RGB values. → ``(li [N] int64, lv [3, N] float32, the share held)``."""
    sparse = torch.nonzero((r.dslot < 0) & (r.nnz > 0)).flatten()
    sparse = sparse[torch.randperm(sparse.numel(), generator=g)]
    held = torch.cumsum(r._cblk[sparse].long(), 0) / r.NB
    n = int(torch.searchsorted(held, torch.tensor([share], dtype=held.dtype))[0]) + 1
    li = torch.cat([torch.nonzero(r.dslot >= 0).flatten(), sparse[:n]])
    return li, torch.rand(3, li.numel(), generator=g) + 0.1, float(held[n - 1])


def test_each_build_takes_its_pass_and_both_equal_the_dense_sum(transfer, monkeypatch):
    """Lights holding ~0.40, ~0.56 (between the two defaults) and ~0.80 of the sparse blocks, on a relighter whose
    build record is W16 or not (``layouts='auto'``: the row-major copy exists after a call exactly when that light took
    the row-major pass) and with an explicit ``row_min`` (0.9: the column-major pass for all three; 0.3: the row-major
    pass for all three, whatever the build): the pass taken is the threshold's, and every output equals the dense
    float64 sum over the Haar terms Σ_k T̂_vk L_k (scale and albedo applied)."""
    tr, dense, alb = transfer
    probe = W(tr, threads=1, row_min=2.0)
    if probe._kernel() is None:
        pytest.skip("no native kernel here (the torch formulation takes no row-major pass)")
    g = torch.Generator().manual_seed(7)
    lights = [_light(probe, s, g) for s in (0.40, 0.56, 0.80)]
    assert lights[0][2] < 0.5 < lights[1][2] < W.ROW_MIN_W16 < lights[2][2], [x[2] for x in lights]
    for rec, row_min, want in ((W16, None, (False, False, True)), (NO_W16[0], None, (False, True, True)),
                               (NO_W16[1], None, (False, True, True)), (W16, 0.9, (False, False, False)),
                               (NO_W16[0], 0.9, (False, False, False)), (W16, 0.3, (True, True, True))):
        monkeypatch.setitem(relight._WAVELET, "row_min_path", rec)
        for (li, lv, share), rows in zip(lights, want):
            r = W(tr, threads=1, row_min=row_min, arith="float")  # the float dense loop: this test is about the passes
            assert r.row_min == (W.default_row_min(rec) if row_min is None else row_min)
            got = r(li, lv).double()
            assert (r.rptr is not None) == rows, (rec, row_min, share)
            ref = (torch.zeros(3, r.P, dtype=torch.float64).index_add_(1, li, lv.double()) @ dense.T).T * alb  # [V, 3]
            assert (got - ref).abs().max() <= 1e-5 * float(ref.abs().max()) + 1e-6, (rec, row_min, share)


def test_estimate_and_dry_run_follow_the_build(tmp_path, monkeypatch, capsys):
    """``estimate_bytes`` (what ``prt relight --dry-run`` plans with) decides the row-major copy with the build's
    default as the relighter does, and the dry run names the light's share of the sparse blocks and the threshold:
    sky at R = 16, K = 64 on the blocker scene (its sparse terms hold ~0.60 of the sparse blocks)."""
    from prt_torch.cli import main as cli_main
    from prt_torch.transfer import RunOptions, get_kind

    path = tmp_path / "w16.prt"
    get_kind("wavelet").precompute(builtin("occluder_over_plane"), {"res": 16, "terms": 64},
                                   run=RunOptions(workers=1, progress=False)).save(path)
    for rec in (W16, NO_W16[0]):
        monkeypatch.setitem(relight._WAVELET, "row_min_path", rec)
        est = W.estimate_bytes(path, light="sky")
        assert est["row_min"] == W.default_row_min(rec)
        assert 0.5 < est["row_share"] < 0.7
        assert est["row_pass"] == (est["row_share"] >= est["row_min"]), rec
        assert (est["row"] > 0) == est["row_pass"]
        assert W.estimate_bytes(path, light="sky", row_min=0.9)["row_pass"] is False  # an explicit row_min wins
        capsys.readouterr()
        assert cli_main(["relight", str(path), "--light", "sky", "-o", str(tmp_path / "o.npy"), "--dry-run"]) == 0
        err = capsys.readouterr().err
        assert (f"its sparse terms hold {est['row_share']:.2f} of the sparse blocks, row_min {est['row_min']:g} for this "
                "kernel build") in err, err
