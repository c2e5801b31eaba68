"""Transport tables' ``res: auto`` (issue 42 part 2, "defaults that work together"): the cube
resolution follows from the BRDF's narrowest lobe (``transfer.transport.choose_cube_res``).

Checked against independent figures: the lobe width against the angular second moment of the
transport function T(ω_i) = f_r(ω_i, ω_o) max(n·ω_i, 0) integrated by brute force on a fine grid
around its peak, the texel spacing against the closed-form solid angle of a cube texel, the chosen
resolution against its definition (2σ spans two texel spacings there and not one resolution
below); the manifest records the decision; bad values are refused in one line.
"""
from __future__ import annotations

import json
import math
import pytest
import torch

from prt_torch import brdf as B
from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions, get_kind, precompute_transport
from prt_torch.transfer.transport import (AUTO_GRAZING_DEG, AUTO_MAX_RES, AUTO_MIN_RES, choose_cube_res, lobe_width,
                                          texel_spacing)


def _moment_widths(brdf: B.BRDF, theta_o_deg: float, n: int = 601, span: float = 0.8) -> tuple[float, float]:
    """Angular standard deviations (in the plane of incidence, across it) of T(ω_i) = f_r max(n·ω_i, 0)
    about its centroid, by a brute-force sum on an exponential-map grid around the mirror direction."""
    th = math.radians(theta_o_deg)
    wo = torch.tensor([math.sin(th), 0.0, math.cos(th)], dtype=torch.float64)
    r = torch.tensor([-math.sin(th), 0.0, math.cos(th)], dtype=torch.float64)
    e_pp = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    e_in = torch.linalg.cross(e_pp, r)
    a = torch.linspace(-span, span, n, dtype=torch.float64)
    A, C = torch.meshgrid(a, a, indexing="ij")
    ang = torch.sqrt(A ** 2 + C ** 2).clamp_min(1e-12)
    d = torch.cos(ang)[..., None] * r + (torch.sin(ang) / ang)[..., None] * (A[..., None] * e_in + C[..., None] * e_pp)
    d = d.reshape(-1, 3)
    T = (brdf.eval(d, wo.expand_as(d)) * d[:, 2].clamp_min(0)).reshape(n, n)
    w = T * torch.sin(ang) / ang  # the exponential map's area element
    m = w.sum()
    ma, mc = (w * A).sum() / m, (w * C).sum() / m
    return (math.sqrt(float((w * (A - ma) ** 2).sum() / m)), math.sqrt(float((w * (C - mc) ** 2).sum() / m)))


@pytest.mark.parametrize("brdf", [B.Phong(64.0), B.Phong(128.0, ks=0.7, kd=0.0)], ids=["phong64", "phong128"])
def test_phong_lobe_width_is_its_second_moment(brdf):
    """A Phong lobe about the reflected view: σ = 1/√s in both directions at normal exitance, and
    across the plane of incidence at any view (not narrowed towards grazing; in the plane the
    cosine factor skews it a little)."""
    sigma, why = lobe_width(brdf)
    assert sigma == pytest.approx(1 / math.sqrt(float(brdf.s)), rel=1e-12) and "phong" in why
    for got in _moment_widths(brdf, 0.0):
        assert got == pytest.approx(sigma, rel=0.05)
    assert _moment_widths(brdf, AUTO_GRAZING_DEG)[1] == pytest.approx(sigma, rel=0.05)


@pytest.mark.parametrize("brdf", [B.AshikhminShirley(64.0, rs=1.0, fresnel=False, diffuse=False), B.BlinnPhong(256.0),
                                  B.Microfacet(0.1)], ids=["as64", "blinn256", "microfacet0.1"])
def test_half_vector_lobe_width_at_the_grazing_view(brdf):
    """A half-vector lobe narrows across the plane of incidence by cos θ_o: the width res: auto
    sizes the table by is the brute-force width across the plane at θ_o = AUTO_GRAZING_DEG, and
    the normal-exitance width is 1/cos of it (2/√N for Blinn-Phong and Ashikhmin–Shirley)."""
    sigma, _ = lobe_width(brdf)
    c = math.cos(math.radians(AUTO_GRAZING_DEG))
    _, across = _moment_widths(brdf, AUTO_GRAZING_DEG)
    assert across == pytest.approx(sigma, rel=0.06)
    at_normal = _moment_widths(brdf, 0.0)
    assert at_normal[0] == pytest.approx(at_normal[1], rel=1e-6)
    assert at_normal[0] == pytest.approx(sigma / c, rel=0.06)


def test_texel_spacing_is_the_largest_texel_solid_angle():
    """h(r) = √Ω of the texel next to a face centre (even r): Ω = atan(xy / √(x² + y² + 1)) at
    x = y = 2/r, the cube-face area integral of a texel with a corner at the centre."""
    for r in (2, 8, 16, 32):
        x = 2.0 / r
        assert texel_spacing(r) == pytest.approx(math.sqrt(math.atan(x * x / math.sqrt(2 * x * x + 1))), rel=1e-12)


@pytest.mark.parametrize("brdf", [None, B.Phong(12.0, ks=0.7, kd=0.3), B.Phong(300.0), B.Microfacet(0.2),
                                  B.BlinnPhong(64.0), B.Ward(0.15)], ids=["default", "phong12", "phong300", "mf", "blinn", "ward"])
def test_choose_cube_res_meets_its_definition(brdf):
    """The chosen r is the smallest in [AUTO_MIN_RES, AUTO_MAX_RES] with 2σ ≥ 2 h(r); at the cap it says so."""
    r, d = choose_cube_res(brdf)
    sigma = lobe_width(brdf)[0]
    assert AUTO_MIN_RES <= r <= AUTO_MAX_RES and d["value"] == r and d["lobe_sigma"] == sigma
    if 2 * sigma >= 2 * texel_spacing(r):
        assert r == AUTO_MIN_RES or 2 * sigma < 2 * texel_spacing(r - 1)
        assert "smallest r" in d["reason"]
    else:
        assert r == AUTO_MAX_RES and "largest" in d["reason"]
    assert d["texels_per_lobe"] == pytest.approx(2 * sigma / texel_spacing(r))


def test_default_brdf_resolves_finer_than_six_by_eight_by_eight():
    """The default Ashikhmin–Shirley N = 40 (σ = 2/√40 at normal exitance) at a 60° view: 0.158 rad
    across the plane, so 6×8×8 (h = 0.24) does not resolve it and res: auto goes finer."""
    r, d = choose_cube_res(None)
    assert d["lobe_sigma"] == pytest.approx(2 / math.sqrt(40) * 0.5, rel=1e-12)
    assert r > 8 and 2 * d["lobe_sigma"] >= 2 * texel_spacing(r)
    lam = choose_cube_res(B.Lambertian(0.5))
    assert lam[0] == AUTO_MIN_RES and math.isinf(lam[1]["lobe_sigma"])


def test_manifest_records_the_choice(tmp_path):
    """Both entries — the function's default and the registry's resolve (CLI, configs) — write
    the chosen r and its reason into the manifest."""
    mesh = builtin("convex", "small")
    brdf = B.Phong(150.0)
    want, _ = choose_cube_res(brdf)
    t = precompute_transport(mesh, tmp_path / "a", brdf=brdf, views=1, shadows=False, max_chunks=1,
                             run=RunOptions(chunk_size=64))
    assert t.meta["res"] == want and t.meta["auto"]["res"]["value"] == want
    k = get_kind("transport")
    t2 = k.precompute(mesh, {"brdf": {"type": "phong", "s": 150.0}, "views": 1, "shadows": False, "max_chunks": 1},
                      run=RunOptions(chunk_size=64), out=tmp_path / "b")
    m = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert t2.meta["res"] == m["res"] == want and "smallest r" in m["auto"]["res"]["reason"]
    t3 = precompute_transport(mesh, tmp_path / "c", brdf=brdf, views=1, res=5, shadows=False, max_chunks=1,
                              run=RunOptions(chunk_size=64))
    assert t3.meta["res"] == 5 and "auto" not in t3.meta


@pytest.mark.parametrize("bad", ["fine", 0, 65, 2.5, True])
def test_bad_res_is_refused(tmp_path, bad):
    mesh = builtin("convex", "small")
    with pytest.raises((ValueError, TypeError), match="res"):
        precompute_transport(mesh, tmp_path / "t", res=bad, views=1)
    assert not (tmp_path / "t").exists()
    with pytest.raises(ValueError, match="texels"):
        choose_cube_res(None, texels=0)


@pytest.mark.parametrize("value", ["fine", "0", "65"])
def test_cli_bad_cube_res_one_line(tmp_path, capsys, value):
    from prt_torch.cli import main as cli_main

    out = tmp_path / "t"
    assert cli_main(["precompute", "convex", "--kind", "transport", "--no-progress", "--cube-res", value, "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--cube-res" in err[0] and value in err[0] and "auto" in err[0], err
    assert not out.exists()


def test_report_lists_the_res_decision():
    """The report's "What the scene required" takes a decision without an energy target (the
    transport res) next to those with one."""
    from prt_torch.harness.report import scene_required

    _, d = choose_cube_res(None)
    lines = scene_required({"transfer": {"meta": {"auto": {"res": d, "bands": {"value": 4, "energy_kept": 0.995, "target": 0.99,
                                                                                  "reason": "lobe"}}}}})
    assert any(x.startswith(f"- res = {d['value']} (auto): smallest r") for x in lines)
    assert any(x.startswith("- bands = 4 (auto): keeps 0.9950") for x in lines)
