"""The wavelet kernel's per-vertex factor (issue 39; ``WaveletRelighter._kfactor``, kernels/wavelet.c ``F1``): where the
quantisation scale × albedo is the same across output channels (a grey transfer with a grey albedo or none) the kernel
reads one float per vertex, ``f [V + 4]``; a uniform coloured albedo is one float per vertex times one colour; a
per-vertex coloured albedo and a coloured transfer keep ``f [V, CO]``. Each form, each build this CPU runs, against the
float64 gather of the same stored values times the float64 factor (``relight.wavelet_dense``), on 2251 vertices (70
blocks of 32 and 11: the partial block's plain loop too); the builds' outputs bit-identical; the form's bytes counted in
``bytes_read``."""

from __future__ import annotations

import os

import pytest
import torch

from prt_torch import _native, relight
from prt_torch.scene import builtin
from prt_torch.transfer import Transfer

pytestmark = pytest.mark.skipif(os.environ.get("PRT_TORCH_NATIVE", "1") == "0" or relight._wavelet_lib() is None,
                                reason="no compiled wavelet kernel")

HAS_AVX2 = _native.cpu_isa() in ("avx2", "avx512")


def _transfer(albedo, CT: int, res: int = 8, K: int = 24, seed: int = 5) -> Transfer:
    """A synthetic 16-bit wavelet transfer on the 2251-vertex blocker scene, a scale per vertex (and channel) in
    [0.5, 1.5), the albedo given (CT = 1: applied at relight time; CT = 3: folded, as interreflection stores it)."""
    scene = builtin("occluder_over_plane", "small", albedo=albedo)
    g = torch.Generator().manual_seed(seed)
    V, P = scene.num_vertices, 6 * res * res
    index = (torch.rand(V, P, generator=g) * torch.where(torch.arange(P) < 16, 50.0, 1.0)).topk(K, dim=1).indices
    shape = (V, K) if CT == 1 else (V, CT, K)
    q = torch.randint(-30000, 30001, shape, generator=g).to(torch.int16)
    scale = torch.rand(V if CT == 1 else (V, CT), generator=g) + 0.5
    return Transfer("wavelet", q, scene, {"res": res, "terms": K, "albedo_folded": CT > 1},
                    aux={"index": index.to(torch.int16), "scale": scale})


def _albedos(V: int) -> dict:
    g = torch.Generator().manual_seed(7)
    grey = torch.rand(V, 1, generator=g).expand(V, 3) * 0.9
    return {"grey": grey.contiguous(), "uniform": torch.tensor([0.8, 0.5, 0.25]),
            "vertex": torch.rand(V, 3, generator=g) * 0.9}


def _reference(r, li, lv, albedo: bool) -> torch.Tensor:
    """float64: the gather of the stored values times the float64 scale × albedo of each output channel."""
    idx, vals = r.reference_rows()  # the stored values times the scale (float32), [V, K] or [V, CT, K]
    q = r.transfer.data.to(torch.float64)
    sc = r.transfer.aux["scale"].to(torch.float64)
    C = lv.shape[0]
    CO = max(C, r.CT)
    if r.CT == 1:
        s = relight.wavelet_dense(q, idx, li, lv.double(), r.P)  # [V, C]
        s = s.expand(-1, CO) if C < CO else s
        f = sc[:, None].expand(-1, CO)
    else:
        s = torch.stack([relight.wavelet_dense(q[:, c], idx, li, lv[min(c, C - 1):min(c, C - 1) + 1].double(), r.P)[:, 0]
                         for c in range(3)], 1)
        f = sc
    if albedo:
        a = r.transfer.mesh.albedo.double()[:, :CO] if r.CT == 1 and not r.transfer.meta["albedo_folded"] else 1.0
        f = f * (a if CO > 1 or not torch.is_tensor(a) else a[:, :1])
    return s * f


@pytest.mark.parametrize("isa", [pytest.param("native", id="native"),
                                 pytest.param("avx2", id="avx2", marks=pytest.mark.skipif(not HAS_AVX2, reason="no AVX2"))])
def test_factor_forms_equal_the_float64_reference_and_the_builds_agree(isa):
    """Each factor form (grey, uniform-colour and per-vertex-colour albedo, albedo off; CT = 1 and 3; grey, RGB and
    RGB-with-equal-channels lights; the column- and row-major passes) relit by the build equals the float64 reference
    to float32 rounding (measured max |err| / max |ref| below 1e-6), and bit for bit the native build's."""
    lib, nat = relight._wavelet_lib(isa), relight._wavelet_lib()
    g = torch.Generator().manual_seed(13)
    for CT in (1, 3):
        for name, alb in _albedos(2251).items():
            r = relight.WaveletRelighter(_transfer(alb, CT), threads=1, layouts="both")
            for albedo in (True, False):
                form = relight.WaveletRelighter._factor_form(
                    r.albedo[:, :3] if albedo and CT == 1 else None, CT, 3)
                assert form == ("channel" if CT == 3 or (albedo and name == "vertex") else
                                "uniform" if albedo and name == "uniform" else "vertex"), (CT, name, albedo, form)
                for C, N in ((1, 40), (3, 40), (3, 300), ("grey3", 40)):
                    li = torch.randperm(r.P, generator=g)[:N]
                    lv = torch.randn(1 if C == 1 else 3, N, generator=g)
                    if C == "grey3":
                        lv = lv[:1].expand(3, N).contiguous()
                    ref = _reference(r, li, lv, albedo)
                    outs = []
                    for lb in (lib, nat):
                        f, Ck = r._kfactor(lv.shape[0], albedo)
                        out = torch.empty(r.V, max(lv.shape[0], CT))
                        r._kernel()
                        # the float dense loop (C | FDENSE where the build has the VNNI loop): float32 rounding, and
                        # the builds' bits agree
                        st = lb.prt_wavelet_relight_i16(r._layout.data_ptr(), N, li.data_ptr(), lv.data_ptr(),
                                                        Ck | relight.float_dense_flag(lb), f.data_ptr(), out.data_ptr(), 1)
                        assert st == 0 and (Ck & r.F1) == (form != "channel" and max(lv.shape[0], CT) > 1) * r.F1
                        outs.append(out)
                    err = float((outs[0].double() - ref).abs().max() / ref.abs().max())
                    assert err < 1e-6, (isa, CT, name, albedo, C, N, err)
                    assert torch.equal(outs[0], outs[1]), (isa, CT, name, albedo, C, N)


def test_the_per_vertex_factor_gives_the_same_bits_as_the_per_channel_one():
    """``f [V + 4]`` (``C | F1``) and ``f [V, CO]`` hold the same float32 products (``fl(f[v] fc[c])``): one layout
    relit with each gives the same bits (grey and uniform albedo, RGB and grey lights, N = 40 and 2000), and
    ``relighter(...)`` and ``prepared`` take the per-vertex form."""
    g = torch.Generator().manual_seed(17)
    for name in ("grey", "uniform"):
        r = relight.WaveletRelighter(_transfer(_albedos(2251)[name], 1), threads=1, layouts="both")
        for C, N in ((3, 40), (3, 380), (1, 40)):
            li = torch.randperm(r.P, generator=g)[:N]
            lv = torch.randn(C, N, generator=g)
            f1, Ck = r._kfactor(C, True)
            assert (Ck == C | r.F1) == (C > 1)
            full = r._factor(C, True)  # [V, CO]: the products expanded
            out = torch.empty(r.V, C)
            r._kernel()
            assert r._native(N, li.data_ptr(), lv.data_ptr(), C, full.data_ptr(), out.data_ptr(), 1) == 0
            assert torch.equal(r(li, lv), out), (name, C, N)
            assert torch.equal(r.prepared(li, lv)(), out), (name, C, N)


def test_bytes_read_counts_the_factor_the_kernel_reads():
    """``bytes_read`` adds the factor's bytes (``factor_bytes``): 4 (V + 4) for a grey or uniform albedo on a grey
    transfer, 12 V for a per-vertex colour (RGB light) or a coloured transfer; ``factor=False`` the count before."""
    V = 2251
    li = torch.arange(0, 384, 7)
    for CT, name, per in ((1, "grey", 4), (1, "uniform", 4), (1, "vertex", 12), (3, "grey", 12)):
        r = relight.WaveletRelighter(_transfer(_albedos(V)[name], CT), threads=1)
        fb = 4 * (V + 4) if per == 4 else 12 * V
        assert r.factor_bytes(3, True) == fb, (CT, name)
        assert r.bytes_read(li) - r.bytes_read(li, factor=False) == fb, (CT, name)
        assert r.factor_bytes(1, True) == (4 * V if CT == 1 else 12 * V)  # one output channel: [V, 1] is one per vertex


def test_the_kernel_refuses_the_per_vertex_factor_where_it_has_no_code_for_it():
    """``C | F1`` is taken for three output channels of a grey transfer only: a grey light (one output), a
    four-channel one, or a coloured transfer given it return 1 (an unsupported C) before any output is written."""
    for CT, C in ((1, 1), (1, 4), (3, 3)):
        r = relight.WaveletRelighter(_transfer(None, CT), threads=1)
        r._kernel()
        li, lv = torch.arange(8), torch.ones(C, 8)
        f = torch.ones(r.V + 4)
        out = torch.full((r.V, max(C, CT)), 7.0)
        assert r._native(8, li.data_ptr(), lv.data_ptr(), C | r.F1, f.data_ptr(), out.data_ptr(), 1) == 1, (CT, C)
        assert bool((out == 7).all())
