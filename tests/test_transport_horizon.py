"""Transport tables at views lying in a vertex's tangent plane (Green 2005 eq. 1.2: f_r(ω_i, ω_o) = 0 below it).

Ward 1992's 1/√(cos θ_i cos θ_o) diverges as cos θ_o → 0, and on geodesic meshes with icosphere views a stored view
lies exactly in some vertices' tangent planes (cos θ_o ~ 1e-16 after the float64 rotation): one such vertex set a Ward
table's maximum (5.9e6 on sphere_on_plane:small, Ward(0.3, 0.1, rs=0.2, rd=0.3), views=1, res=6, where every view
at least 1e-3 above a tangent plane gives at most ~1.4). A view with cos θ_o ≤ ``transport.HORIZON_EPS`` now counts
as below the horizon in the torch and compiled table passes, the harness's exact reference and its view taps; the
tests check the values there are zero, that the views just above stay what Ward gives (Ward's closed form at
one pair), and that without the epsilon the same inputs do diverge (so the checks can fail).
"""
from __future__ import annotations

import json
import math

import pytest
import torch

from prt_torch import brdf as B
from prt_torch.harness.evaluate import Evaluator, load_directory_transfer
from prt_torch.lighting import load_light
from prt_torch.scene import load_scene
from prt_torch.transfer import RunOptions, precompute_transport
from prt_torch.transfer import transport as TR
from prt_torch.transfer import transport_kernels as TK
from prt_torch.transfer.glossy import check_frames
from prt_torch.transfer.transport import (HORIZON_EPS, _chunk_transport, cube_directions, sub_texel_sets,
                                          supersample_plan)

native = pytest.mark.skipif(not TK.available()[0], reason=f"no compiled transport kernel: {TK.available()[1]}")
WARD = B.Ward(0.3, 0.1, rs=0.2, rd=0.3)  # the reviewer's example


def _plane_table(monkeypatch, on: bool, cos_o: torch.Tensor, res: int = 6) -> torch.Tensor:
    """One vertex of normal +z (a plane's), views at local cos θ_o = ``cos_o`` [J] (azimuths turned by 1.1 rad),
    no shadows, the ``res: auto`` texel averages: T ``[J, P]`` float64 from the torch (on=False) or compiled pass."""
    monkeypatch.setenv("PRT_TORCH_NATIVE", "1" if on else "0")
    az = torch.arange(cos_o.numel(), dtype=torch.float64) * 1.1
    s = (1 - cos_o * cos_o).sqrt()
    views = torch.stack([s * az.cos(), s * az.sin(), cos_o], -1)
    n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    frames = torch.eye(3, dtype=torch.float64)[None]
    texels = cube_directions(res)[0].reshape(-1, 3)
    plan = supersample_plan(WARD, res, "auto")
    subs = None if plan is None else sub_texel_sets(res, plan)
    return _chunk_transport(None, WARD, torch.zeros(1, 3, dtype=torch.float64), n, frames, texels, views, None, False,
                            torch.float64, plan=plan, sub_texels=subs, average_threads=1)[0]


#: local cos θ_o of the plane test's views: in the tangent plane (exactly, and at float64 rounding noise of both
#: signs), at and just under the epsilon, then 1e-3 (the reference) and ordinary views
COS = torch.tensor([0.0, 1e-17, -1e-17, 1.1e-16, 5e-10, HORIZON_EPS, 1e-3, 0.3, 0.9], dtype=torch.float64)
TANGENT = COS <= HORIZON_EPS


@pytest.mark.parametrize("on", [False, pytest.param(True, marks=native)], ids=["torch", "compiled"])
def test_a_view_in_the_tangent_plane_gives_a_zero_table_under_ward(monkeypatch, on):
    """Views with cos θ_o ≤ HORIZON_EPS give all-zero tables, bounded by the table at cos θ_o = 1e-3 (non-zero,
    finite); at cos θ_o = 1e-3 and above the values are Ward's: one point pair checked against the closed form
    ρd/π + ρs exp(-tan²θh (cos²φh/αx² + sin²φh/αy²)) / (4π αx αy √(cos θi cos θo)) · cos θi, written out here."""
    T = _plane_table(monkeypatch, on, COS)
    assert bool(torch.isfinite(T).all())
    ref = T[COS == 1e-3]
    assert float(ref.max()) > 0
    assert float(T[TANGENT].abs().max()) == 0.0 <= float(ref.max())
    assert bool((T[~TANGENT].amax(-1) > 0).all())
    # Ward's closed form at the texel nearest the normal for the 0.3 view (a point value: far from the mirror cap)
    texels = cube_directions(6)[0].reshape(-1, 3)
    p = int(texels[:, 2].argmax())
    j = int((COS == 0.3).nonzero())
    wi = texels[p]
    wo = torch.tensor([math.sqrt(1 - 0.09) * math.cos(1.1 * j), math.sqrt(1 - 0.09) * math.sin(1.1 * j), 0.3],
                      dtype=torch.float64)
    h = (wi + wo) / (wi + wo).norm()
    ax, ay, rs, rd = 0.3, 0.1, 0.2, 0.3
    f = rd / math.pi + rs * math.exp(-((h[0] / ax) ** 2 + (h[1] / ay) ** 2) / h[2] ** 2) / (
        4 * math.pi * ax * ay * math.sqrt(float(wi[2]) * 0.3))
    assert float(T[j, p]) == pytest.approx(f * float(wi[2]), rel=1e-9)


@native
def test_torch_and_compiled_tables_agree_at_the_horizon(monkeypatch):
    """The torch and compiled passes agree to 1e-12 at every view, the zeros in the same places (the compiled
    pass takes the same epsilon)."""
    want = _plane_table(monkeypatch, False, COS)
    got = _plane_table(monkeypatch, True, COS)
    assert torch.equal(got == 0, want == 0)
    assert float(((got - want).abs() / want.abs().clamp_min(1e-300)).max()) <= 1e-12


def test_without_the_epsilon_the_tangent_view_diverges(monkeypatch):
    """The check above can fail: with HORIZON_EPS = 0 the view at cos θ_o = 1e-17 gives Ward's 1/√cos θ_o blow-up,
    orders of magnitude above the table at cos θ_o = 1e-3 (torch pass)."""
    monkeypatch.setattr(TR, "HORIZON_EPS", 0.0)
    T = _plane_table(monkeypatch, False, COS)
    assert float(T[COS == 1e-17].max()) > 1e4 * float(T[COS == 1e-3].max())


@pytest.fixture(scope="module")
def reviewer_table(tmp_path_factory):
    """The reviewer's example: sphere_on_plane:small, Ward(0.3, 0.1, rs=0.2, rd=0.3), views=1 (12), res=6."""
    mesh = load_scene("sphere_on_plane", size="small")
    out = tmp_path_factory.mktemp("graze") / "table"
    table = precompute_transport(mesh, out, brdf=WARD, views=1, res=6)
    T = torch.cat([c for _, _, c in table], 0).double()
    cos = check_frames(mesh)[:, 2] @ table.views.T  # [V, J] cos θ_o of every (vertex, stored view)
    return out, T.reshape(T.shape[0], T.shape[1], -1), cos


def test_reviewer_example_is_bounded(reviewer_table):
    """Vertex 120's view 3 lies in its tangent plane (cos θ_o ~ 1e-16; the table held 5.9e6 there): every pair with
    cos θ_o ≤ HORIZON_EPS (thousands, most exactly 0 or negative, 50 at +1e-17 .. +1e-16) is zero, and the table's maximum is that of
    the views at least 1e-3 above a tangent plane."""
    _, T, cos = reviewer_table
    assert abs(float(cos[120, 3])) < 1e-15 and float(T[120, 3].abs().max()) == 0.0
    tangent = (cos.abs() < 1e-12) & (cos > 0)
    assert int(tangent.sum()) >= 20  # the systematic case: views in tangent planes on the positive side of rounding (50 here)
    assert float(T[cos <= HORIZON_EPS].abs().max()) == 0.0
    assert float(T.max()) <= float(T[cos >= 1e-3].max()) < 10.0


def test_resuming_a_table_written_without_the_epsilon_is_refused(reviewer_table, tmp_path):
    """The epsilon is in the fingerprint: a table whose manifest lacks it (written before, its tangent views
    possibly non-zero) is not resumed into."""
    import shutil

    src, _, _ = reviewer_table
    old = tmp_path / "old"
    shutil.copytree(src, old)
    m = json.loads((old / "manifest.json").read_text())
    assert m["fingerprint"]["horizon_eps"] == HORIZON_EPS
    del m["fingerprint"]["horizon_eps"]
    (old / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(ValueError, match="other parameters"):
        precompute_transport(load_scene("sphere_on_plane", size="small"), old, brdf=WARD, views=1, res=6,
                             run=RunOptions(resume=True))


def test_exact_reference_and_taps_at_a_tangent_view_are_zero(reviewer_table):
    """The harness's exact reference (``Evaluator.exact_transport``) at each vertex's view 3 is zero wherever that
    view lies in the tangent plane (2.0e6 at vertex 120 before), and its maximum is that of the views ≥ 1e-3 above;
    a camera 1e-12 above the ground plane gives the ground vertices zero view taps (cos θ_o ~ 1e-14 ≤ the epsilon)."""
    out, _, cos = reviewer_table
    ev = Evaluator(load_directory_transfer(out))
    L = load_light("constant:value=1", bands=ev.bands_in)
    d = ev.views[3].double().expand(ev.V, 3).contiguous()
    ref = ev.exact_transport(L, d)[:, 0].double()
    c = cos[:, 3]
    assert bool(torch.isfinite(ref).all()) and float(ref[c <= HORIZON_EPS].abs().max()) == 0.0
    assert float(ref.max()) <= float(ref[c >= 1e-3].max()) < 10.0
    cam = torch.tensor([50.0, 0.0, 1e-12], dtype=torch.float64)
    view = ev.view_weights(cam)
    ground = (ev.points[:, 2].abs() < 1e-12) & (ev.frames[:, 2, 2] > 1 - 1e-12)
    up = ((cam[None] - ev.points) * ev.frames[:, 2]).sum(-1)
    assert int(ground.sum()) > 500 and bool((up[ground] > 0).any())  # above 0 for some: the old test kept them
    assert float(view[1][ground].abs().max()) == 0.0


# --- normals that are only float32-accurate (a PLY's float normals; a mesh exported in float32 and read back) -------------
#
# Every path that computes cos θ_o against HORIZON_EPS (the torch and compiled table passes, the harness's exact reference
# and view taps, relight's view weights) gets float64 frames: Mesh holds its normals and frames in float64 whatever the file
# had (make_mesh / Mesh.from_tensors convert), check_frames, Evaluator.frames and the renderer's frames are .to(float64),
# and kernels/transport.c takes double. So an epsilon that followed the frames' dtype would never change: the dtype does
# not say how accurate the normals are. What float32 normals do: a view lying in the *exact* tangent plane comes out at
# |cos θ_o| ~ 1e-9 .. 1e-7 against the stored normal instead of ~1e-16. Measured on the reviewer's example
# (sphere_on_plane:small, Ward(0.3, 0.1, rs=0.2, rd=0.3), views=1, res=6) with its normals rounded to float32 (moved by at
# most 2.0e-8): of the 6 844 (vertex, view) pairs lying in a tangent plane, 48 have cos θ_o in (1e-9, 7.0e-9]; the table
# holds up to 912 there (the views >= 1e-3 above: 1.43) and the exact reference up to 138 (0.49). Those views are above
# the stored tangent plane by 1e-9 .. 1e-8 — Ward's value there is what the model gives, within the bound HORIZON_EPS
# documents (Ward's factor at most 1/sqrt(1e-9) = 3.2e4 times its normal-view value; here 1/sqrt(cos) <= 1.2e4), and the
# tables, the exact reference and the relight taps agree on them (same frames, same epsilon). So HORIZON_EPS stays 1e-9,
# one constant for every path; the tests below pin what float32 normals give.


def _float32_normal():
    """(n exact float64, n32: n rounded to float32 and renormalised in float64, as make_mesh keeps a file's normals)."""
    n = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64)
    n = n / n.norm()
    n32 = n.float().double()
    return n, n32 / n32.norm()


def test_float32_normals_reach_every_horizon_path_as_float64(reviewer_table):
    """A mesh given float32 normals holds them (and its frames) in float64, and so do check_frames and the harness's
    Evaluator: the frames' dtype is float64 on every path that tests cos θ_o against HORIZON_EPS."""
    from prt_torch.scene.mesh import make_mesh

    n, n32 = _float32_normal()
    P = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float64)
    m = make_mesh(P.numpy(), [[0, 1, 2]], normals=n32.float().expand(3, 3).numpy())
    assert m.normals.dtype == torch.float64 and m.frames().dtype == torch.float64
    assert check_frames(m).dtype == torch.float64
    out, _, _ = reviewer_table
    assert Evaluator(load_directory_transfer(out)).frames.dtype == torch.float64


@pytest.mark.parametrize("on", [False, pytest.param(True, marks=native)], ids=["torch", "compiled"])
def test_float32_normals_tangent_views_are_wards_values(monkeypatch, on):
    """Views lying in the exact tangent plane of n, against the float32-rounded normal: cos θ_o ~ 1e-8 of both signs;
    those above HORIZON_EPS hold Ward's closed form (written out here, every upper texel: point values), finite, and
    those at or below it zeros — the table is what the model gives at that elevation, not a divergence."""
    from prt_torch.scene.mesh import tangent_frames

    monkeypatch.setenv("PRT_TORCH_NATIVE", "1" if on else "0")
    n, n32 = _float32_normal()
    t, b = (torch.from_numpy(x) for x in tangent_frames(n32[None].numpy()))
    frames = torch.stack([t, b, n32[None]], 1)  # [1, 3, 3] rows (t, b, n32)
    u = torch.linalg.cross(n, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    u = u / u.norm()
    w = torch.linalg.cross(n, u)
    az = torch.arange(24, dtype=torch.float64) * (2 * math.pi / 24) + 0.05
    views = az.cos()[:, None] * u + az.sin()[:, None] * w  # [24, 3] in n's plane (float64: |n·v| ~ 1e-17)
    cos = views @ n32
    assert float((views @ n).abs().max()) < 1e-15 and 1e-10 < float(cos.abs().max()) < 1e-7
    above = cos > HORIZON_EPS
    assert int(above.sum()) >= 4 and int((~above).sum()) >= 4  # both sides occur
    texels = cube_directions(6)[0].reshape(-1, 3)
    T = _chunk_transport(None, WARD, torch.zeros(1, 3, dtype=torch.float64), n32[None], frames, texels, views, None, False,
                         torch.float64, average_threads=1)[0]  # [J, P]
    assert bool(torch.isfinite(T).all())
    assert float(T[~above].abs().max()) == 0.0
    wi = texels @ frames[0].T  # [P, 3] local
    wo = views[above] @ frames[0].T  # [J', 3] local, z = cos θ_o ~ 1e-8
    h = wi[None] + wo[:, None]
    h = h / h.norm(dim=-1, keepdim=True)
    ax, ay, rs, rd = 0.3, 0.1, 0.2, 0.3
    ci, co = wi[None, :, 2], wo[:, None, 2]
    spec = rs * torch.exp(-((h[..., 0] / ax) ** 2 + (h[..., 1] / ay) ** 2) / h[..., 2] ** 2) / (
        4 * math.pi * ax * ay * torch.sqrt(ci.clamp_min(1e-300) * co))
    want = torch.where(ci > 0, (rd / math.pi + spec) * ci, torch.zeros(()))
    got = T[above]
    # conditioning, not a tolerance for the engine: cos θ_o ~ 1e-8 is a 3-term dot product whose rounding (FMA or not,
    # per CPU and path) is ~eps absolute, so eps / cos θ_o relative, halved by Ward's 1/sqrt; and the lobe's exp(-x),
    # x = ((h_x/a_x)² + (h_y/a_y)²)/h_z², carries x's few ulps times |x|. Both on the specular share, on top of 1e-9.
    # Measured on an Intel Xeon (AVX-512): 4.4e-9 at a value 1446 (cos θ_o ~ 1e-8, x = 1.3); below 1e-9 on an AMD Zen 3.
    eps = torch.finfo(torch.float64).eps
    x = ((h[..., 0] / ax) ** 2 + (h[..., 1] / ay) ** 2) / h[..., 2] ** 2
    share = (spec / want.abs().clamp_min(1e-300)).clamp(0, 1)
    tol = 1e-9 + (64 * eps * x + 4 * eps / co.abs()) * share
    r = (got - want).abs() / want.abs().clamp_min(1e-300)
    assert bool((r <= tol).all()), float((r / tol).max())
    # large (Ward's 1/sqrt(cos θ_o) at ~1e-8: far above the lobe's peak at a normal view) but finite
    assert float(got.max()) > 50 * (rd / math.pi + rs / (4 * math.pi * ax * ay))
