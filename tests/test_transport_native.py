"""The transport tables' compiled BRDF passes (``transfer.transport_kernels``, ``kernels/transport.c``; issue 42 §2)
against the torch path (``BRDF.eval`` on the same pairs, ``PRT_TORCH_NATIVE=0``): float64 tables within relative
1e-12 for every model the C knows (integer exponents by repeated squaring, others through pow; Fresnel, diffuse,
anisotropy, per-vertex parameters), at odd sizes (one vertex, odd cube resolutions and view counts: vector tails),
in 1 and 2 threads (bit for bit the same), in float32 / float16 within one rounding of the float64 value; Ward 1992
(isotropic, anisotropic, roughness 0.03 to 1) and Ramamoorthi's microfacet model (sigma 0.02 to 2) the same way, and at
grazing views and texels; models it does not know (subclasses included) keep torch. The texel averages' independent
check (a brute-force block mean of the fine grid) is ``tests/test_transport_supersample.py``, which runs the compiled
path by default."""
from __future__ import annotations

import pytest
import torch

from prt_torch import brdf as B
from prt_torch.transfer import transport_kernels as TK
from prt_torch.transfer.transport import (HORIZON_EPS, _chunk_transport, cube_directions, icosphere_directions, sub_texel_sets,
                                          supersample_plan)

native = pytest.mark.skipif(not TK.available()[0], reason=f"no compiled transport kernel: {TK.available()[1]}")

AS40 = B.AshikhminShirley(40.0, 40.0, rs=0.05, rd=0.0)
MODELS = {
    "as40": AS40,
    "as_aniso_pow": B.AshikhminShirley(37.3, 12.5, rs=0.1, rd=0.4),  # non-integer, anisotropic: pow, diffuse term
    "as_nofresnel": B.AshikhminShirley(40.0, 40.0, rs=0.2, rd=0.3, fresnel=False),
    "as_nodiffuse": B.AshikhminShirley(100.0, 100.0, rs=0.05, rd=0.5, diffuse=False),
    "phong": B.Phong(200.0),
    "phong_reflection": B.Phong(30.5, ks=0.7, kd=0.2, form="reflection"),
    "blinn": B.BlinnPhong(64.0, kd=0.3),
    "lambert": B.Lambertian(0.6),
    # Ward 1992: the default, anisotropic with a diffuse term, the roughness extremes (a lobe narrower than a texel, whose
    # exp underflows to subnormals at grazing pairs; a lobe wider than the hemisphere)
    "ward": B.Ward(0.2),
    "ward_aniso": B.Ward(0.3, 0.07, rs=0.2, rd=0.4),
    "ward_sharp": B.Ward(0.03, rs=0.05),
    "ward_rough": B.Ward(1.0, 0.8, rs=0.5),
    # Ramamoorthi 2002 eq. 5.34 over cos theta_i: the default, the roughness extremes (sigma in (0, 2])
    "microfacet": B.Microfacet(0.2),
    "microfacet_sharp": B.Microfacet(0.02, ks=0.7),
    "microfacet_rough": B.Microfacet(2.0),
}
#: one of each compiled family for the tests that vary something else (sizes, threads, dtypes, builds)
FAMILIES = ("as40", "ward_aniso", "microfacet")


def _vertices(k: int, seed: int = 0):
    """k random points with random normals and orthonormal frames (rows t, b, n), float64."""
    g = torch.Generator().manual_seed(seed)
    n = torch.nn.functional.normalize(torch.randn(k, 3, generator=g, dtype=torch.float64), dim=-1)
    a = torch.nn.functional.normalize(torch.randn(k, 3, generator=g, dtype=torch.float64), dim=-1)
    t = torch.nn.functional.normalize(a - (a * n).sum(-1, keepdim=True) * n, dim=-1)
    return torch.zeros(k, 3, dtype=torch.float64), n, torch.stack([t, torch.linalg.cross(n, t), n], 1)


def _table(monkeypatch, on: bool, brdf, k=5, res=7, views=None, dtype=torch.float64, threads=1, mat_index=None, sub="auto"):
    monkeypatch.setenv("PRT_TORCH_NATIVE", "1" if on else "0")
    pts, nrm, frm = _vertices(k)
    views = icosphere_directions(2) if views is None else views
    texels = cube_directions(res)[0].reshape(-1, 3)
    plan = supersample_plan(brdf, res, sub)
    subs = None if plan is None else sub_texel_sets(res, plan)
    T = _chunk_transport(None, brdf, pts, nrm, frm, texels, views, mat_index, False, dtype, plan=plan, sub_texels=subs,
                         average_threads=threads)
    return T, plan


def _rel_close(got, want, rtol, floor=0.0):
    """Whether |got - want| <= rtol max(|want|, floor) everywhere, and the largest such ratio. ``floor``: the float64
    subnormals (Ward's and the microfacet's exp at grazing pairs of a sharp lobe) carry fewer bits than any relative
    tolerance; below the smallest normal, 2^-1022, they are compared to it (an absolute 1e-12 · 2^-1022)."""
    d = (got.double() - want.double()).abs()
    ref = want.double().abs().clamp_min(floor)
    # exp's conditioning: these tables are exp(-x) times a prefactor, and an argument x rounded a few ulps apart by
    # two paths (torch's vectorised kernels and the C loop order) moves the value by |x| times that, |x| ~ -ln(value):
    # 32 ulps of x allowed on top of rtol (at 1e-293, |x| ~ 674: 4.8e-12; above 1e-80 rtol = 1e-12 governs). Seen on an
    # AVX-512 Xeon: 1.25e-12 (ward) and 1.93e-12 (microfacet_sharp) at values ~1e-279..1e-293.
    tol = torch.maximum(torch.full_like(ref, rtol), 32 * torch.finfo(torch.float64).eps * (-ref.clamp_min(1e-300).log()).clamp_min(0))
    return bool((d <= tol * ref).all()), float((d / ref.clamp_min(1e-300)).max())


TINY = torch.finfo(torch.float64).tiny


def rtol_of(name: str) -> float:
    """1e-12; 4e-12 for the sharp lobes (Ward a = 0.05-ish, microfacet sigma = 0.02): their exponent
    x = tan²θ_h / σ² is computed from the half vector, where 1 - cos²θ_h loses ~1/sin²θ_h of its bits near the lobe's
    peak, and exp(-x) carries x's error times |x|. Measured on an Intel Xeon (AVX-512): a uniform 1.10e-12 from
    microfacet_sharp's values 1e-9 to 0.13, 1.93e-12 at 1e-279, ward_sharp 1.25e-12; below 1e-12 on an AMD Zen 3."""
    return 4e-12 if "sharp" in name else 1e-12


@native
@pytest.mark.parametrize("name", list(MODELS))
def test_float64_table_equals_the_torch_path_to_1e12(monkeypatch, name):
    """Point values and texel averages (res 7 is below the default BRDF's `res: auto`, so many views average)."""
    brdf = MODELS[name]
    want, plan = _table(monkeypatch, False, brdf, sub=4 if name == "phong" else "auto")
    got, _ = _table(monkeypatch, True, brdf, sub=4 if name == "phong" else "auto")
    ok, worst = _rel_close(got, want, rtol_of(name), TINY)
    assert ok, f"{name}: max relative difference {worst:.3g}"
    assert torch.equal(got == 0, want == 0) and int((want > 0).sum()) > 1000
    if name in ("as40", "phong") or name.startswith(("ward", "microfacet")):
        assert plan is not None  # the averages ran


@native
@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("k,res,J", [(1, 5, 7), (3, 9, 13), (13, 7, 42)])
def test_odd_sizes_and_tails(monkeypatch, k, res, J, name):
    """One vertex; odd texel and view counts (lists of visible texels and sub-texels of every length mod 4)."""
    views = torch.nn.functional.normalize(torch.randn(J, 3, generator=torch.Generator().manual_seed(J), dtype=torch.float64), dim=-1)
    want, _ = _table(monkeypatch, False, MODELS[name], k=k, res=res, views=views)
    got, _ = _table(monkeypatch, True, MODELS[name], k=k, res=res, views=views)
    ok, worst = _rel_close(got, want, 1e-12, TINY)
    assert ok, worst


@native
@pytest.mark.parametrize("name", ["as40", "ward", "ward_sharp", "microfacet", "microfacet_sharp"])
def test_grazing_views_and_texels(monkeypatch, name):
    """Views 2e-9 rad (just above transport.HORIZON_EPS) to 5 degrees above the tangent plane of vertices whose
    normal is +z (tangent frames turned by irrational angles), a cube resolution whose texel rows straddle the
    horizon: the pairs where Ward's 1/sqrt(cos θi cos θo), the microfacet's 1/cos θi and the half vector's θ_h
    are worst conditioned, point values and averages."""
    from prt_torch.transfer.transport import _chunk_transport

    monkeypatch.setenv("PRT_TORCH_NATIVE", "1")
    k, res = 4, 9
    ang = torch.arange(k, dtype=torch.float64) * 0.7390851332
    t = torch.stack([ang.cos(), ang.sin(), torch.zeros(k, dtype=torch.float64)], -1)
    n = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64).expand(k, 3)
    frames = torch.stack([t, torch.linalg.cross(n, t), n], 1)
    el = torch.tensor([2e-9, 1e-6, 1e-3, 0.01, 0.05, 0.09], dtype=torch.float64)  # radians above the tangent plane
    az = torch.arange(el.numel(), dtype=torch.float64) * 1.1
    views = torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], -1)
    texels = cube_directions(res)[0].reshape(-1, 3)
    brdf = MODELS[name]
    plan = supersample_plan(brdf, res, "auto")
    subs = sub_texel_sets(res, plan)
    out = {}
    for on in ("0", "1"):
        monkeypatch.setenv("PRT_TORCH_NATIVE", on)
        out[on] = _chunk_transport(None, brdf, torch.zeros(k, 3, dtype=torch.float64), n.contiguous(), frames, texels, views,
                                   None, False, torch.float64, plan=plan, sub_texels=subs, average_threads=1)
    ok, worst = _rel_close(out["1"], out["0"], rtol_of(name), TINY)
    assert ok, f"{name}: {worst:.3g}"
    assert torch.equal(out["1"] == 0, out["0"] == 0) and int((out["0"] > 0).sum()) > 100


@native
@pytest.mark.parametrize("name", FAMILIES)
def test_threads_give_the_same_bits(monkeypatch, name):
    """13 vertices, every view at r = 5 averaged in blocks of 512 pairs split between 2 threads: the same bits as one."""
    brdf = MODELS[name]
    one, plan = _table(monkeypatch, True, brdf, k=13, res=5, threads=1)
    two, _ = _table(monkeypatch, True, brdf, k=13, res=5, threads=2)
    assert plan is not None and torch.equal(one, two)
    want, _ = _table(monkeypatch, False, brdf, k=13, res=5, threads=2)
    assert _rel_close(two, want, 1e-12, TINY)[0]


@native
def test_per_vertex_parameters(monkeypatch):
    """[V] parameters selected per vertex (``mat_index``), different at every vertex (some isotropic integer, some not)."""
    k = 6
    nu = torch.tensor([40.0, 12.5, 100.0, 7.0, 40.0, 63.2], dtype=torch.float64)
    nv = torch.tensor([40.0, 30.0, 100.0, 7.0, 20.0, 63.2], dtype=torch.float64)
    brdf = B.AshikhminShirley(nu, nv, rs=torch.linspace(0.02, 0.3, k, dtype=torch.float64),
                              rd=torch.tensor([0.0, 0.2, 0.0, 0.5, 0.1, 0.0], dtype=torch.float64))
    idx = torch.arange(k)
    want, _ = _table(monkeypatch, False, brdf, k=k, mat_index=idx)
    got, _ = _table(monkeypatch, True, brdf, k=k, mat_index=idx)
    assert _rel_close(got, want, 1e-12)[0]


@native
def test_per_vertex_parameters_ward_and_microfacet(monkeypatch):
    """[V] Ward (isotropic and anisotropic, with and without the diffuse term) and microfacet parameters per vertex."""
    k = 6
    ax = torch.tensor([0.2, 0.05, 0.6, 0.3, 0.1, 1.0], dtype=torch.float64)
    ay = torch.tensor([0.2, 0.15, 0.6, 0.07, 0.1, 0.5], dtype=torch.float64)
    ward = B.Ward(ax, ay, rs=torch.linspace(0.02, 0.6, k, dtype=torch.float64),
                  rd=torch.tensor([0.0, 0.2, 0.0, 0.5, 0.1, 0.0], dtype=torch.float64))
    mf = B.Microfacet(torch.tensor([0.2, 0.03, 0.5, 1.2, 0.08, 2.0], dtype=torch.float64),
                      ks=torch.linspace(0.3, 1.5, k, dtype=torch.float64))
    idx = torch.arange(k)
    for brdf in (ward, mf):
        want, _ = _table(monkeypatch, False, brdf, k=k, mat_index=idx)
        got, _ = _table(monkeypatch, True, brdf, k=k, mat_index=idx)
        ok, worst = _rel_close(got, want, 1e-12, TINY)
        assert ok, f"{brdf.name}: {worst:.3g}"


@native
@pytest.mark.parametrize("name", FAMILIES)
@pytest.mark.parametrize("dtype,rtol", [(torch.float32, 2.0 ** -23), (torch.float16, 2.0 ** -10)])
def test_stored_dtypes_round_once(monkeypatch, dtype, rtol, name):
    """float32 / float16 tables: the float64 values rounded once, so within one unit of the stored precision of the
    torch path's (which rounds its float64 values once too); float16 only where the compiler has _Float16."""
    if dtype == torch.float16 and TK._state.get("abi", 0) < 2:
        pytest.skip("no _Float16 in this compiler: float16 tables take the torch path")
    want, _ = _table(monkeypatch, False, MODELS[name], dtype=dtype)
    got, _ = _table(monkeypatch, True, MODELS[name], dtype=dtype)
    assert got.dtype == dtype
    big = want.double().abs() > 1e-4  # normal range of float16
    ok, worst = _rel_close(got[big], want[big], rtol)
    assert ok, worst
    assert int((got != want).sum()) < 0.01 * want.numel()


def test_native_off_and_unknown_models_keep_torch(monkeypatch):
    """``PRT_TORCH_NATIVE=0``: the passes write nothing and say so; a model the C does not know (a subclass, of
    Ashikhmin–Shirley, Ward or the microfacet model, that may change ``_eval``) has no native form; Ward's and the
    microfacet's parameter rows."""
    monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    assert TK.available() == (False, "PRT_TORCH_NATIVE=0")
    T = torch.full((2, 12 * 24), float("nan"), dtype=torch.float32)
    model = TK.native_model(AS40, 2)
    wi = torch.zeros(2, 24, 3, dtype=torch.float64)
    assert not TK.points(T, wi, torch.zeros(2, 12, 3, dtype=torch.float64), torch.ones(2, 24, dtype=torch.float64), None, model,
                         horizon=HORIZON_EPS)
    assert T.isnan().all()
    for base in (B.AshikhminShirley, B.Ward, B.Microfacet):
        class Mine(base):
            pass

        assert TK.native_model(Mine(), 3) is None
    assert TK.native_model(B.Ward(0.2, 0.1, rs=0.3, rd=0.1), 2)[2].tolist() == [[0.2, 0.1, 0.3, 0.1]] * 2
    assert TK.native_model(B.Microfacet(0.4, ks=0.5), 1)[:2] == (6, 0)
    m, flags, par = TK.native_model(B.AshikhminShirley(40.0, 20.0, rs=0.1, rd=0.2, fresnel=False), 3)
    assert (m, flags) == (0, 2) and par.shape == (3, 4) and par[:, 1].eq(20.0).all()


def test_every_built_in_model_has_a_compiled_form():
    """Each class of ``brdf.MODELS`` (both Phong forms) maps to a model of the C, with one parameter row per vertex: a
    model added to brdf.py without its C form fails here rather than silently taking the ~3-6x slower torch path."""
    seen = set()
    for name, cls in B.MODELS.items():
        for brdf in ([cls(form="modified"), cls(form="reflection")] if cls is B.Phong else [cls()]):
            got = TK.native_model(brdf, 3)
            assert got is not None, name
            assert got[2].shape == (3, 4) and got[2].dtype == torch.float64
            seen.add(got[0])
    assert seen == set(range(7))


@native
def test_precompute_writes_every_chunk_before_reporting_it(tmp_path, monkeypatch):
    """The whole command's form: chunk files written by the background writer, each reported (callback) only once
    its file is there, in order; the table equals the torch path's within one float32 rounding; a failed write
    raises and the chunks before it stay."""
    from prt_torch import io
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions, precompute_transport

    mesh = builtin("convex", "small")
    seen = []

    def cb(c, n):
        assert (tmp_path / "n" / f"chunk_{c:06d}.prt").exists()
        seen.append(c)

    run = RunOptions(chunk_size=64, workers=1, callback=cb)
    t = precompute_transport(mesh, tmp_path / "n", views=1, res=6, max_chunks=5, run=run)
    assert seen == [0, 1, 2, 3, 4]
    monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
    ref = precompute_transport(mesh, tmp_path / "t", views=1, res=6, max_chunks=5, run=RunOptions(chunk_size=64, workers=1))
    for (a, b, x), (_, _, y) in zip(t, ref):
        assert _rel_close(x, y, 2.0 ** -23)[0] and float(y.max()) > 0
    monkeypatch.setenv("PRT_TORCH_NATIVE", "1")
    real = io.save

    def flaky(path, *a, **kw):
        if "chunk_000002" in str(path):
            raise OSError(f"cannot write {str(path)!r}: disk full")
        return real(path, *a, **kw)

    monkeypatch.setattr(io, "save", flaky)
    with pytest.raises(OSError, match="disk full"):
        precompute_transport(mesh, tmp_path / "f", views=1, res=6, max_chunks=5, run=RunOptions(chunk_size=64, workers=1))
    assert (tmp_path / "f" / "chunk_000001.prt").exists() and not (tmp_path / "f" / "chunk_000002.prt").exists()


@native
def test_portable_build_without_march_native(tmp_path, monkeypatch):
    """The library as a compiler refusing ``-march=native`` builds it (``_native.compile_library``'s fallback: the
    baseline ISA, no AVX2, so libm's scalar ``pow`` for non-integer exponents and no vector code of its own): the
    same tables as torch to 1e-12, through pow (anisotropic) and repeated squaring (N = 40)."""
    from prt_torch._native import compile_library, kernel_sources

    monkeypatch.setenv("PRT_TORCH_CACHE", str(tmp_path / "cache"))
    TK._lib()  # the real library's signatures and ABI recorded first
    flags = [f for f in TK._FLAGS if f != "-march=native"]
    lib, why = compile_library("transport", kernel_sources(TK._SOURCES), flags, TK._SIGNATURES)
    assert lib is not None, why
    assert "-march=native" not in why
    for name in ("as40", "as_aniso_pow", "phong_reflection", "ward_aniso", "microfacet", "microfacet_sharp"):
        want, _ = _table(monkeypatch, False, MODELS[name])
        monkeypatch.setitem(TK._state, "lib", lib)
        got, _ = _table(monkeypatch, True, MODELS[name])
        assert _rel_close(got, want, rtol_of(name), TINY)[0], name


@pytest.mark.parametrize("args,msg", [(["--brdf", "foo"], "--brdf 'foo': BRDF model='foo' is not known; accepted:"),
                                      (["--brdf", "ward:ax=x"], "--brdf 'ward:ax=x': parameter 'ax=x'; accepted: k=v"),
                                      (["--brdf", "as", "ward:bogus=1"], "unknown parameter 'bogus'; accepted: ax, ay, rs, rd"),
                                      (["--every", "0"], "--every 0; accepted: an integer >= 1")])
def test_bench_transport_native_refuses_bad_options(args, msg):
    """benchmarks/bench_transport_native.py: a bad --brdf or --every named in one line, status 2, no traceback, before
    any table is computed."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    r = subprocess.run([sys.executable, str(root / "benchmarks" / "bench_transport_native.py"), *args, "--out", "-"],
                       capture_output=True, text=True, cwd=root, timeout=120)
    assert r.returncode == 2 and msg in r.stderr and "Traceback" not in r.stderr, r.stderr
