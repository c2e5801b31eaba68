"""Model only what the scene requires: 'auto' bands / exit bands / tents from the energy of the
lights and the BRDF lobe (checked against analytic spectra), shadows skipped on convex scenes,
and the decisions reported."""
import math

import numpy as np
import pytest
import torch
from scipy.special import eval_legendre

from prt_torch import brdf as B
from prt_torch.lighting import load_light
from prt_torch.scene import load_scene
from prt_torch.sh import clamped_cosine_A, hemisphere_gram
from prt_torch.transfer import get_kind
from prt_torch.transfer.auto import choose_bands, choose_tents, light_spectrum, lobe_filter
from prt_torch.transfer.tents import error_matrix


def test_constant_environment_needs_one_band_for_diffuse():
    L = torch.zeros(1, 32 * 32, dtype=torch.float64)
    L[0, 0] = 2 * math.sqrt(math.pi)  # constant radiance 1: only l = 0
    p, d = get_kind("diffuse").resolve({"bands": "auto"}, lights=[L])
    assert p["bands"] == 1 and d["bands"]["energy_kept"] == pytest.approx(1.0)


def test_irradiance_needs_three_bands_for_a_flat_spectrum():
    """Ramamoorthi 2002 ch. 4: A_l² (2l+1) keeps > 99% with 3 bands, < 99% with 2 — from the A_l
    formula directly, not from the code under test."""
    A = clamped_cosine_A(32)
    e = A ** 2 * (2 * torch.arange(32, dtype=torch.float64) + 1)
    frac = torch.cumsum(e, 0) / e.sum()
    assert frac[1] < 0.99 <= frac[2]
    lobe, _ = lobe_filter(None)
    flat, _ = light_spectrum(None)
    assert choose_bands(0.99, lobe, flat, 32) == (3, pytest.approx(float(frac[2])))


def test_sharper_phong_lobe_needs_more_bands_about_sqrt_s():
    flat, _ = light_spectrum(None)
    ns = []
    for s in (4, 16, 64, 256):
        lobe, why = lobe_filter(B.Phong(float(s), form="reflection"))
        n, kept = choose_bands(0.99, lobe, flat, 64)
        assert kept >= 0.99 and "lobes" in why
        ns.append(n)
        assert 1.0 * math.sqrt(s) <= n <= 2.5 * math.sqrt(s) + 1
    assert ns == sorted(ns) and len(set(ns)) == 4
    # brute force: the Phong filter f_l (Ramamoorthi eq. 3.37) from the Legendre integral
    s, l = 16.0, torch.arange(8, dtype=torch.float64)
    xn, wn = np.polynomial.legendre.leggauss(400)
    x, w = torch.tensor(xn), torch.tensor(wn)
    lobe = (s + 1) / (2 * math.pi) * x.clamp_min(0) ** s
    f = torch.stack([2 * math.pi * (lobe * torch.tensor(eval_legendre(int(k), xn)) * w).sum() for k in l])
    got, _ = lobe_filter(B.Phong(s, form="reflection"), 8)
    assert torch.allclose(got, f ** 2, rtol=1e-6, atol=1e-12)


def test_tent_count_meets_the_energy_it_claims():
    M, kept = choose_tents(5, 0.99)
    E = error_matrix(M, 5)
    assert 1 - float(torch.trace(E)) / float(torch.trace(hemisphere_gram(5))) == pytest.approx(kept)
    assert kept >= 0.99
    assert 1 - float(torch.trace(error_matrix(M - 1, 5))) / float(torch.trace(hemisphere_gram(5))) < 0.99


def test_energy_out_of_range_is_refused_before_work():
    for bad in (0.0, 1.5, -1.0, float("nan")):
        with pytest.raises((ValueError, TypeError), match="energy"):
            get_kind("diffuse").validate({"bands": "auto", "energy": bad})
    with pytest.raises(ValueError, match="bands"):
        get_kind("diffuse").validate({"bands": "many"})


def test_convex_scene_traces_no_shadow_rays_and_auto_is_recorded():
    mesh = load_scene("convex", size="small")
    tr = get_kind("diffuse").precompute(mesh, {"bands": "auto", "samples": 64}, lights=[load_light("sky", bands=32)])
    assert tr.meta["rays_traced"] == 0 and not tr.meta["shadows_traced"]
    assert tr.meta["auto"]["bands"]["value"] == tr.data.shape[-1] ** 0.5 and tr.meta["auto"]["bands"]["energy_kept"] >= 0.99
    g = get_kind("glossy").precompute(mesh, {"bands": 2, "samples": 16, "shadows": "auto"})
    assert g.meta["rays_traced"] == 0 and "no self-occlusion" in g.meta["shadow_decision"]


def test_bench_reports_what_the_scene_required(tmp_path):
    import yaml

    from prt_torch.harness import config as hc
    from prt_torch.harness.run import run_benchmark

    cfg = {"name": "auto", "scene": {"name": "convex", "size": "small"},
           "transfer": {"type": "diffuse", "bands": "auto", "samples": 32, "energy": 0.95},
           "lights": ["sky"], "metrics": {"random_lights": 8, "repeats": 1, "warmup": 0},
           "codecs": [{"type": "pca", "vectors": 1}], "render": {"enabled": False},
           "cache_dir": str(tmp_path / "c"), "output_dir": str(tmp_path / "r")}
    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump(cfg))
    run_dir = run_benchmark(hc.load_config(str(p)), progress=False, log=lambda s: None)
    md = (run_dir / "report.md").read_text()
    assert "## What the scene required" in md and "bands = " in md and "(auto)" in md and "shadows:" in md
