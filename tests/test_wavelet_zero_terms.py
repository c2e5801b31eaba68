"""select_terms never ranks a light's zero (round-off) Haar terms (lighting.haar.ZERO_TERM).

A light that is constant on blocks has exact zeros in the Haar basis; the float64 transform leaves
them at round-off (~1e-17), whose order is the CPU's rounding, not the light. Independent reference:
the light is built in the Haar basis itself (a few chosen coefficients, inverse-transformed), so its
nonzero terms are known without the forward transform under test."""
import math

import pytest
import torch

from prt_torch.lighting.haar import ZERO_TERM, cube_light, haar2d, ihaar2d, select_terms
from prt_torch.relight import wavelet_dense


def _light_with_terms(res: int, picks: dict[int, float]) -> torch.Tensor:
    """A [1, 6, R, R] cube whose Haar coefficients are exactly ``picks`` (flat index -> value), back in the pixel basis."""
    P = 6 * res * res
    h = torch.zeros(1, P, dtype=torch.float64)
    for k, v in picks.items():
        h[0, k] = v
    return ihaar2d(h.reshape(1, 6, res, res))


@pytest.mark.parametrize("selection", ["magnitude", "area", "transport"])
def test_round_off_terms_are_never_selected(selection):
    R = 16
    P = 6 * R * R
    picks = {0: 3.0, 5: -0.7, 300: 1e-6, 1000: 2.5e-9, 1500: 0.25}  # 1e-6 and 2.5e-9: real, far above round-off
    img = _light_with_terms(R, picks)
    H = haar2d(img).reshape(1, P)
    off = H.clone()
    off[0, list(picks)] = 0
    assert 0 < float(off.abs().max()) < 1e-14  # the forward transform's round-off is really there
    w = torch.rand(P, dtype=torch.float64, generator=torch.Generator().manual_seed(1)) * 10
    w[list(picks)] = 1e-3  # transport weights that favour the round-off terms over the real ones
    idx, vals = select_terms(H, 2000, selection, w if selection == "transport" else None)
    assert sorted(idx.tolist()) == sorted(picks)
    assert vals.shape == (1, len(picks))
    assert torch.allclose(vals[0], torch.tensor([picks[int(k)] for k in idx], dtype=torch.float64), rtol=1e-9, atol=1e-15)
    # fewer requested than real: the largest of the real ones (magnitude order)
    idx2, _ = select_terms(H, 2, "magnitude")
    assert idx2.tolist() == [0, 5]  # |3| then |-0.7|


def test_a_real_term_just_above_the_threshold_is_kept_and_one_below_is_not():
    R = 4
    P = 6 * R * R
    h = torch.zeros(2, P, dtype=torch.float64)
    h[0, 0], h[1, 7] = 1.0, 3 * ZERO_TERM  # summed over channels: |L̂_7| = 3e-12 of the largest
    h[0, 9] = 0.5 * ZERO_TERM
    idx, _ = select_terms(h, P, "magnitude")
    assert sorted(idx.tolist()) == [0, 7]


def test_all_zero_light_keeps_one_term_and_relights_black():
    idx, vals = select_terms(torch.zeros(3, 24, dtype=torch.float64), 10, "magnitude")
    assert idx.numel() == 1 and float(vals.abs().max()) == 0.0


def test_area_light_on_black_selects_its_nonzero_terms_only():
    """A cap rasterised on the cube: the N-term approximation at N = all equals the light exactly (nothing real is dropped)."""
    R = 16
    cube, _ = cube_light("cap:direction=0.3,0.2,1;half_angle_deg=20;radiance=1", R)
    C = cube.shape[0]
    H = haar2d(cube.permute(3, 0, 1, 2) if cube.shape[-1] == C else cube).reshape(-1, 6 * R * R)
    idx, vals = select_terms(H, 6 * R * R, "magnitude")
    assert idx.numel() < 6 * R * R  # the dark part of the cube has exact zeros
    back = torch.zeros_like(H)
    back[:, idx] = vals
    assert float((back - H).abs().max()) <= ZERO_TERM * float(H.abs().sum(0).max())
    assert math.isclose(float(back.square().sum()), float(H.square().sum()), rel_tol=1e-12)


def test_a_coloured_light_keeps_a_term_any_one_channel_carries():
    """An RGB light whose channels have different zero patterns: the magnitude thresholded is Σ_c |L̂_ck| (the
    selections' own), so a term zero in two channels and nonzero in the third is kept — with its zeros —, the
    N = all result equals the relighting with every term (the dropped ones are round-off), and a channel far
    below the others (1e-9 of the largest here, above ZERO_TERM) keeps its own terms too."""
    R = 8
    P = 6 * R * R
    picks = [{0: 2.0, 5: -0.5, 40: 0.1},  # red
             {0: 1.0, 77: 0.3},  # green: 77 only here
             {0: 0.5, 5: 0.2, 130: -0.04, 200: 1e-9}]  # blue: 130 and 200 only here (200 tiny but real)
    h = torch.zeros(3, P, dtype=torch.float64)
    for c, pk in enumerate(picks):
        for k, v in pk.items():
            h[c, k] = v
    H = haar2d(ihaar2d(h.reshape(3, 6, R, R))).reshape(3, P)  # back and forth: the round-off in every channel
    real = sorted(set().union(*picks))
    off = H.clone()
    off[:, real] = 0
    assert 0 < float(off.abs().max()) < 1e-14
    for selection in ("magnitude", "area", "transport"):
        w = torch.linspace(0.1, 5.0, P, dtype=torch.float64)
        idx, vals = select_terms(H, P, selection, w if selection == "transport" else None)
        assert sorted(idx.tolist()) == real, selection
        for c, pk in enumerate(picks):  # each channel's values, its zeros where another channel carries the term
            want = torch.tensor([pk.get(int(k), 0.0) for k in idx], dtype=torch.float64)
            assert torch.allclose(vals[c], want, rtol=1e-9, atol=1e-15), (selection, c)
    # the kept terms relight as every term does (an independent sum over all P terms of a random transfer)
    g = torch.Generator().manual_seed(3)
    V, K = 50, 40
    index = torch.stack([torch.randperm(P, generator=g)[:K] for _ in range(V)])
    index[:, :len(real)] = torch.tensor(real)  # every vertex keeps the light's real terms, and some round-off ones
    values = torch.randn(V, K, generator=g, dtype=torch.float64)
    idx, vals = select_terms(H, P, "magnitude")
    got = wavelet_dense(values, index, idx, vals, P)  # [V, 3]
    ref = (values[:, None, :] * H[:, index].permute(1, 0, 2)).sum(-1)  # Σ_k over each vertex's kept terms, all of H
    assert float((got - ref).abs().max()) <= 1e-13 * float(ref.abs().max())


def test_prt_relight_says_when_it_keeps_fewer_terms_than_asked(tmp_path, capsys, nonzero_haar_terms):
    """``prt relight --terms N`` with N above the light's nonzero Haar terms keeps those (select_terms) and says so
    in one warning line naming the count — the studio light at R = 8 has 59 of 384, counted here from its
    coefficients —; the result equals the one with every term; an N below the count says nothing."""
    import numpy as np

    from prt_torch.cli import main as cli_main
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions, get_kind

    w = tmp_path / "w.prt"
    get_kind("wavelet").precompute(builtin("occluder_over_plane"), {"res": 8, "terms": 48},
                                   run=RunOptions(workers=1, progress=False)).save(w)
    nz = nonzero_haar_terms("studio", 8)
    assert 30 < nz < 384
    capsys.readouterr()
    outs = {}
    for terms in (None, 30, 200, 1000):
        o = tmp_path / f"o{terms}.npy"
        assert cli_main(["relight", str(w), "--light", "studio", "-o", str(o)]
                        + ([] if terms is None else ["--terms", str(terms)])) == 0
        said = capsys.readouterr()
        warned = [ln for ln in said.err.splitlines() if "warning" in ln]
        if terms == 200:
            assert len(warned) == 1 and f"has {nz} nonzero Haar terms of 384" in warned[0], said.err
        elif terms == 1000:  # above the cube's 6R² as well: one line for both
            assert len(warned) == 1 and f"384 Haar terms at R = 8 (6R²), of which 'studio' has {nz} nonzero" in warned[0]
        else:
            assert not warned, said.err
        if terms in (200, 1000):
            assert f"{nz} of 384 light terms" in said.out
        outs[terms] = np.load(o)
    assert np.array_equal(outs[200], outs[None]) and np.array_equal(outs[1000], outs[None])
