"""Issue 39's integer multiply-add idea for the wavelet kernel's dense part (measured and not kept:
docs/wavelet_kernel_log.md; benchmarks/bench_wavelet_madd_micro.py): the claims its report rests on, checked against float64.

- The light's int16 quantisation (``quantise_light``) never lets an int32 sum overflow: with the columns' largest
  stored magnitudes tmax, Σ_k tmax_k |Lq_k| ≤ 2³¹ − 1 per group and |Lq| ≤ 32767 (integer arithmetic, int64), and
  |Lq s − L| ≤ s/2 — for lights built to stress it: one huge term and many tiny ones, all negative, all equal,
  one term, an odd count.
- The measured loops (AVX2 ``vpmaddwd``, in intrinsics and asm; AVX-512 VNNI ``vpdpwssd``, one block and two in
  lockstep, where the CPU has it) compute Σ_k T_v,k L_k within the stated bound
  Σ_g (s_g/2) Σ_{k∈g} |T_v,k| (+ float32 rounding) against the float64 sum of the same stored values: on the extreme
  layout (|T| = 32767 everywhere, signs alternating or not, a light of equal terms: the largest int32 sums the rule
  allows), on random layouts with random lights, and on a real transfer's dense blocks; on the VNNI path a light that
  would overflow int32 wraps (the check sees it) and the rules' lights do not.
- The wavelet relighter's default on an AVX-512 VNNI CPU (``kernels/wavelet.c``'s VNNI dense loop, the default
  since 2026-11-30) relights within its stated bound (``vnni_bound``) of the float64 sums of the same stored values,
  also under high-dynamic-range lights (a sun 1e4 x the sky; one huge term among small ones), and its opt-out
  (``arith='float'``) is the float loop.
"""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]


def _bench():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        return __import__("bench_wavelet_madd_micro")
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


@pytest.fixture(scope="module")
def bench():
    return _bench()


@pytest.fixture(scope="module")
def lib(bench):
    lib = bench.build_library()
    if lib is None:
        pytest.skip("no compiler for the micro-benchmark")
    probe = torch.zeros(1, 2, 32, dtype=torch.int16)
    k = bench.pack(torch.tensor([0, 1]), torch.zeros(2, 3, dtype=torch.int32), torch.ones(1, 3), 2)
    if bench.madd_call(lib, "lean", probe, k, torch.zeros(1, 3, 32)) != 0:
        pytest.skip("no AVX2 here: the integer loops are not built")
    return lib


def _variants(bench, lib) -> tuple[str, ...]:
    """The loops to check: the AVX2 ones, and the AVX-512 VNNI ones where this build has them."""
    return bench.VARIANTS + (tuple(bench.VNNI) if lib.vnni_floor(0, 1) >= 0 else ())


def _lights(g: torch.Generator, nd: int) -> dict[str, torch.Tensor]:
    """[nd, 3] float32 lights that stress the quantisation."""
    huge = torch.full((nd, 3), 1e-6)
    huge[nd // 2] = torch.tensor([1e3, -2e3, 5e2])
    return {"random": torch.randn(nd, 3, generator=g), "one huge, many tiny": huge,
            "all negative": -torch.rand(nd, 3, generator=g) - 0.1, "equal": torch.full((nd, 3), 0.75),
            "grey": torch.randn(nd, 1, generator=g).expand(nd, 3).contiguous()}


@pytest.mark.parametrize("nd", [1, 7, 64])
@pytest.mark.parametrize("rule", ["column max", "65535 rule"])
def test_quantisation_cannot_overflow_and_is_within_half_a_step(bench, nd, rule):
    g = torch.Generator().manual_seed(nd)
    tmax = torch.randint(1, 32768, (nd,), generator=g)
    tmax[0] = 32767
    for name, L in _lights(g, nd).items():
        for group in (2, 16, 4096):
            q, s, grp = bench.quantise_light(L, group, tmax if rule == "column max" else None)
            assert int(q.abs().max()) <= 32767, (name, group)
            bound_t = tmax if rule == "column max" else torch.full((nd,), 32767)
            worst = torch.zeros(s.shape[0], 3, dtype=torch.int64).index_add_(0, grp, bound_t[:, None] * q.long().abs())
            assert int(worst.max()) <= 2 ** 31 - 1, (name, group)
            err = (q.double() * s.double()[grp] - L.double()).abs()
            assert bool((err <= s.double()[grp] / 2 * (1 + 1e-12)).all()), (name, group)


def _check(bench, lib, d16: torch.Tensor, ds: torch.Tensor, L: torch.Tensor, group: int, use_tmax: bool):
    """Every loop's sums against the float64 sums of the same stored values, within the stated bound."""
    tmax = d16.abs().amax(dim=(0, 2)).long()
    q, s, grp = bench.quantise_light(L, group, tmax[ds] if use_tmax else None)
    k = bench.pack(ds, q, s, group)
    tv = d16[:, ds, :].double()
    exact = torch.einsum("bkv,kc->bcv", tv, L.double())
    bound = torch.einsum("bkv,kc->bcv", tv.abs(), s.double()[grp] / 2)
    slack = 1e-6 * torch.einsum("bkv,kc->bcv", tv.abs(), L.double().abs()) + 1e-30
    for variant in _variants(bench, lib):
        out = torch.full((d16.shape[0], 3, 32), float("nan"))
        assert bench.madd_call(lib, variant, d16, k, out) == 0
        err = (out.double() - exact).abs()
        assert bool((err <= bound + slack).all()), (variant, float((err - bound).max()))


@pytest.mark.parametrize("signs", ["all positive", "alternating"])
def test_extreme_values_do_not_overflow(bench, lib, signs):
    """|T| = 32767 in every value and a light of equal terms: each int32 sum reaches the rule's limit (21 equal
    terms: 65535 / 21 = 3120.7 rounds up, so the plain Σ|L| / 65535 rule would give Σ|Lq| = 65541 > 65538 and wrap)."""
    nb, Pd = 3, 40
    d16 = torch.full((nb, Pd, 32), 32767, dtype=torch.int16)
    if signs == "alternating":
        d16[:, :, 1::2] = -32767
    for nd in (1, 2, 21, 39):
        ds = torch.arange(nd)
        for use_tmax in (True, False):
            _check(bench, lib, d16, ds, torch.full((nd, 3), 0.5), 4096, use_tmax)
            _check(bench, lib, d16, ds, -torch.full((nd, 3), 2.0), 16, use_tmax)


def test_random_layouts_and_lights_within_the_bound(bench, lib):
    g = torch.Generator().manual_seed(3)
    nb, Pd = 4, 50
    d16 = torch.randint(-32767, 32768, (nb, Pd, 32), generator=g).to(torch.int16)
    d16[torch.rand(nb, Pd, 32, generator=g) < 0.3] = 0  # vertices that do not keep the column
    for nd in (1, 5, 33, 50):
        ds = torch.sort(torch.randperm(Pd, generator=g)[:nd]).values
        for L in _lights(g, nd).values():
            for group, use_tmax in ((4096, True), (16, True), (4096, False), (2, True)):
                _check(bench, lib, d16, ds, L, group, use_tmax)


def test_real_transfer_dense_blocks_within_the_bound(bench, lib):
    from prt_torch import relight
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions
    from prt_torch.transfer.wavelet import precompute_wavelet

    tr = precompute_wavelet(builtin("occluder_over_plane", "small"), 8, 32, 16, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="column")
    assert rl.CT == 1 and rl.dense.dtype == torch.int16 and rl.Pd > 1
    d16 = rl.dense.reshape(rl.dense.shape[0], rl.Pd, 32)
    assert int(d16.min()) >= -32767  # the stored range is symmetric: vpmaddwd's one overflow cannot occur
    for spec, N in (("studio", 100), ("sky", rl.P)):
        li, lv, _ = rl.light(spec, N, "transport")
        d = rl.dslot[li] >= 0
        order = torch.argsort(rl.dslot[li[d]].long())
        ds = rl.dslot[li[d]].long()[order]
        L = lv[:, d].T.float()[order].contiguous()
        for group, use_tmax in ((4096, True), (16, True), (4096, False)):
            _check(bench, lib, d16, ds, L, group, use_tmax)


def test_vnni_light_that_would_overflow_does_not(bench, lib):
    """The VNNI path (vpdpwssd accumulates into int32 and wraps): |T| = 32767 everywhere and a light of equal terms
    quantised with full int16 range (Lq = 32767: Σ_k |T| |Lq| = n 32767² > 2³¹ − 1 from n = 2) wraps — the check is
    sensitive — while quantise_light's rules, for the same light, keep every sum in range and within the bound; an odd
    block count takes the two-block loop's lone last block."""
    if lib.vnni_floor(0, 1) < 0:
        pytest.skip("no AVX-512 VNNI here")
    nb, Pd, nd = 3, 8, 8
    d16 = torch.full((nb, Pd, 32), 32767, dtype=torch.int16)
    ds = torch.arange(nd)
    L = torch.full((nd, 3), 0.5)
    exact = torch.einsum("bkv,kc->bcv", d16[:, ds, :].double(), L.double())
    naive_s = torch.full((1, 3), 0.5 / 32767)  # the largest term at 32767: the sums overflow
    naive = bench.pack(ds, torch.full((nd, 3), 32767, dtype=torch.int32), naive_s, 4096)
    for variant in bench.VNNI:
        out = torch.zeros(nb, 3, 32)
        assert bench.madd_call(lib, variant, d16, naive, out) == 0
        assert float((out.double() - exact).abs().max()) > 0.1 * float(exact.abs().max()), variant  # wrapped
    tmax = d16.abs().amax(dim=(0, 2)).long()
    for use_tmax in (True, False):
        _check(bench, lib, d16, ds, L, 4096, use_tmax)
        q, s, grp = bench.quantise_light(L, 4096, tmax[ds] if use_tmax else None)
        assert int((tmax[ds, None] * q.long().abs()).sum(0).max()) <= 2 ** 31 - 1


@pytest.fixture(scope="module")
def vnni_rl():
    """A real 16-bit grey transfer (blocker scene, small: 2251 vertices, 71 blocks with a partial last one; R = 16,
    K = 64: ordinary lights keep the VNNI loop's bound below the transfer's own, so its per-call guard lets them take
    it) and its default relighter, where this process's wavelet build has the VNNI dense loop (else skipped)."""
    from prt_torch import relight
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions
    from prt_torch.transfer.wavelet import precompute_wavelet

    if not relight.wavelet_kernel_path().get("vnni"):
        pytest.skip("this wavelet build has no VNNI dense loop (no AVX-512 VNNI here, or PRT_TORCH_KERNEL_ISA)")
    tr = precompute_wavelet(builtin("occluder_over_plane", "small"), 16, 64, 16, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="column")
    assert rl.CT == 1 and rl.dense.dtype == torch.int16 and (rl.dense.shape[0] % 2 == 1 or rl.V % 32)
    return rl


@pytest.fixture(scope="module")
def vnni_rl8(vnni_rl):
    """The same scene at R = 8, K = 32 (few, full dense columns: the VNNI loop's L2 bound is 1.0-2.0x the transfer's
    own for the studio and sky lights, so the per-call guard sends them to the float loop), where this build has the
    VNNI loop (``vnni_rl`` skips otherwise)."""
    from prt_torch import relight
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions
    from prt_torch.transfer.wavelet import precompute_wavelet

    tr = precompute_wavelet(builtin("occluder_over_plane", "small"), 8, 32, 16, shadows="always", run=RunOptions(workers=1))
    return relight.WaveletRelighter(tr, threads=1, layouts="column")


def _exact(rl, li, lv):
    """The float64 reference of the same stored values (dequantised rows, times the albedo) [V, 3]."""
    from prt_torch import relight

    ref_index, ref_vals = rl.reference_rows(0, rl.V)
    return relight.wavelet_dense(ref_vals.double(), ref_index, li, lv.double(), rl.P) * rl.albedo[:, :3].double()


def _default_and_float(rl, li, lv):
    """The default call (the VNNI dense loop where it applies) and the opt-out's (``arith='float'``) on one layout,
    through the relighter's own entry points (``__call__`` and ``prepared``, which must agree bit for bit)."""
    from prt_torch import relight

    default = rl(li, lv).clone()
    assert torch.equal(default, rl.prepared(li, lv)())
    fl = relight.WaveletRelighter(rl.transfer, threads=1, layouts="column", arith="float")
    opt = fl(li, lv).clone()
    assert torch.equal(opt, fl.prepared(li, lv)())
    return default, opt


def test_kernel_vnni_default_within_the_bound(bench, vnni_rl):
    """The default relighter on an AVX-512 VNNI CPU (kernels/wavelet.c's VNNI dense loop) relights within its stated
    bound of the float64 sums of the same stored values: |out - exact| <= f_v sum_g (s_g,c / 2) sum_{k in g} |T_v,k|
    over the dense terms (``vnni_bound``: quantise_light's column-maximum rule in groups of 16 terms on the columns'
    largest stored magnitudes found by brute force) + float rounding; odd and even dense-term counts, an odd block
    count, the light's order and slot order; the VNNI loop was taken (not the opt-out's bits), the opt-out is the float
    loop (float32 rounding only), and the layout's column maxima are the brute-force ones."""
    rl = vnni_rl
    rl._kernel()
    d16 = rl.dense.reshape(rl.dense.shape[0], rl.Pd, 32)
    assert torch.equal(rl._dtmax, d16.to(torch.int32).abs().amax(dim=(0, 2)))
    # the layout's norms (kernels/wavelet.c's dnorm) against a per-vertex sum of squares in float64
    sv = rl.scale[:, 0].double()
    T = torch.stack([d16[v // 32, :, v % 32] for v in range(rl.V)]).double()  # [V, Pd], vertex by vertex
    assert torch.allclose(rl._dnorm[:-1], ((T * sv[:, None]) ** 2).sum(0).sqrt(), rtol=1e-12, atol=0)
    assert torch.allclose(rl._dnorm[-1], (sv ** 2).sum().sqrt(), rtol=1e-12, atol=0)
    for spec, N in (("studio", 60), ("sky", 61), ("sky", rl.P)):
        li, lv, _ = rl.light(spec, N, "transport")
        lv = lv.float().contiguous()
        assert rl._takes_vnni(li, lv)
        out, opt = _default_and_float(rl, li, lv)
        exact = _exact(rl, li, lv)
        b = bench.vnni_bound(rl, li, lv)
        assert not b["guard"] and b["guard_ratio"] <= 1, (spec, N, b["guard_ratio"])  # the premise holds: no guard
        assert b["groups"] >= 2 or b["nd"] <= 16
        assert bool(((out.double() - exact).abs() <= b["bound"] + b["slack"]).all()), (spec, N)
        # the output's L2 error over the vertices within the L2 bound the flush groups are chosen by, per channel
        assert bool(((out.double() - exact).norm(dim=0) <= b["l2"] + b["slack_l2"]).all()), (spec, N)
        assert bool(((opt.double() - exact).abs() <= b["slack"]).all()), (spec, N)  # the float loop: rounding only
        assert not torch.equal(out, rl.float32(li, lv)), "the VNNI loop was not taken (C | FDENSE's bits)"
        assert rl.kernel_path()["dense"] == "int16 vnni"


def test_kernel_vnni_default_hdr_lights_within_the_bound(bench, vnni_rl):
    """High-dynamic-range lights (``bench_wavelet_madd_micro.hdr_lights``: a sun 1e4 x the sky's mean radiance; one huge term in a group of
    small ones) on the VNNI default: every vertex within the stated bound (the step of a group follows its largest
    light term, so the error of a vertex follows the group's largest term, not its own radiance); the relative error of
    the vertices the sun does not reach (its own contribution under 1e-3 of its largest: shadowed by the blocker) is
    printed beside the opt-out's, for docs/wavelet_kernel_log.md."""
    rl = vnni_rl
    for name, (li, lv, sun) in bench.hdr_lights(rl).items():
        assert rl._takes_vnni(li, lv)
        out, opt = _default_and_float(rl, li, lv)
        exact = _exact(rl, li, lv)
        b = bench.vnni_bound(rl, li, lv)
        if b["guard"]:  # the per-call guard: the float loop, C | FDENSE's bits
            assert torch.equal(out, rl.float32(li, lv)), name
        assert bool(((out.double() - exact).abs() <= b["bound"] + b["slack"]).all()), name
        assert bool(((opt.double() - exact).abs() <= b["slack"]).all()), name
        if sun is not None:
            s = _exact(rl, li, sun).norm(dim=1)
            mask = (s <= 1e-3 * s.max()) & (exact.norm(dim=1) > 0)
        else:
            mask = exact.norm(dim=1) > 0
        assert int(mask.sum()) > 0
        ev = (out.double() - exact).norm(dim=1)[mask] / exact.norm(dim=1)[mask]
        ef = (opt.double() - exact).norm(dim=1)[mask] / exact.norm(dim=1)[mask]
        bv = b["bound"].norm(dim=1)[mask] / exact.norm(dim=1)[mask]
        print(f"\n[hdr] {name}: {int(mask.sum())} of {rl.V} vertices ({'sun-shadowed' if sun is not None else 'all lit'}): "
              f"relative error per vertex, VNNI median {float(ev.median()):.1e} / 99% {float(ev.quantile(0.99)):.1e} / "
              f"max {float(ev.max()):.1e} (bound median {float(bv.median()):.1e} / max {float(bv.max()):.1e}); "
              f"float median {float(ef.median()):.1e} / max {float(ef.max()):.1e}; whole output rel. L2 VNNI "
              f"{float((out.double() - exact).norm() / exact.norm()):.1e}")


def _col_max_bound(bench, lw, tmax, grp):
    """sum_g s_g,c T_g per channel [3] (float64): the column-maximum bound of a grouping, by quantise_light's scales."""
    _, s, g = bench.quantise_light(lw, grp, tmax)
    T = torch.zeros(s.shape[0], dtype=torch.float64).index_add_(0, g, tmax.double())
    return (s.double() * T[:, None]).sum(0)


def test_vnni_groups_rule(bench):
    """``vnni_groups`` (the kernel's flush groups, recomputed): unions of consecutive 16-term chunks whose column-max
    bound sum_G s_G,c T_G is within 1.25 x that of fixed groups of 16, found here by ``quantise_light``'s own sums;
    equal light terms on small column maxima (the max |L| / 32767 branch binds: merging costs nothing) make one group,
    equal terms on full columns (the sum branch: two chunks merged double s T) stay in groups of 16."""
    gen = torch.Generator().manual_seed(17)
    for nd in (1, 16, 17, 33, 92, 250):
        for _ in range(4):
            lw = torch.randn(nd, 3, generator=gen) * torch.rand(nd, 1, generator=gen) ** 4
            tmax = torch.randint(1, 32768, (nd,), generator=gen)
            grp = bench.vnni_groups(lw, tmax)
            assert grp.shape == (nd,) and int(grp[0]) == 0 and bool((grp.diff() >= 0).all())
            assert bool((grp.diff() <= 1).all())
            starts = (torch.nonzero(grp.diff()).flatten() + 1).tolist()
            assert all(s % 16 == 0 for s in starts), starts
            b, b16 = _col_max_bound(bench, lw, tmax, grp), _col_max_bound(bench, lw, tmax, 16)
            assert bool((b <= 1.25 * b16 * (1 + 1e-9)).all()), (nd, b / b16)
    lw = torch.ones(64, 3)
    assert int(bench.vnni_groups(lw, torch.ones(64, dtype=torch.int64)).max()) == 0
    assert bench.vnni_groups(lw, torch.full((64,), 32767)).tolist() == (torch.arange(64) // 16).tolist()


def _l2_bound(bench, lw, tmax, norms, grp):
    """sum_G s_G,c W_G per channel [3] (float64): a grouping's L2 bound (W: the group's sum of column norms; the
    factor 1/2 on both sides of the budget left out), by quantise_light's scales."""
    _, s, g = bench.quantise_light(lw, grp, tmax)
    W = torch.zeros(s.shape[0], dtype=torch.float64).index_add_(0, g, norms.double())
    return (s.double() * W[:, None]).sum(0)


def test_vnni_groups_l2_rule(bench):
    """``vnni_groups`` with the columns' norms (the kernel's rule since vnb18, recomputed): unions of consecutive 16-term
    chunks whose L2 bound sum_G s_G,c W_G (W: the group's sum of norms) is within max(1.25 x that of fixed groups of 16,
    beta x ns sum_k |L_k,c|) for every channel, found here by ``quantise_light``'s own sums and a plain sum of |L|;
    beta 0 the relative budget alone; a huge beta one group; norms equal to the maxima and beta 0: grp17's groups
    (the column-maximum rule) exactly."""
    gen = torch.Generator().manual_seed(18)
    groups = {0.0: 0, 0.5: 0}
    for nd in (1, 16, 17, 33, 71, 92, 250):
        for _ in range(4):
            lw = torch.randn(nd, 3, generator=gen) * torch.rand(nd, 1, generator=gen) ** 4
            tmax = torch.randint(1, 32768, (nd,), generator=gen)
            # a column's norm at most its max x the scale's norm, mostly well below (the blocker scene: ~0.2 x on average)
            ns = 40.0
            norms = tmax.double() * torch.rand(nd, generator=gen, dtype=torch.float64) * 0.1 * ns
            b16 = _l2_bound(bench, lw, tmax, norms, 16)
            own = ns * lw.double().abs().sum(0)
            for beta in (0.0, 0.5):
                grp = bench.vnni_groups(lw, tmax, norms=norms, nscale=ns, beta=beta)
                assert grp.shape == (nd,) and int(grp[0]) == 0 and bool((grp.diff() >= 0).all() and (grp.diff() <= 1).all())
                starts = (torch.nonzero(grp.diff()).flatten() + 1).tolist()
                assert all(st % 16 == 0 for st in starts), starts
                b = _l2_bound(bench, lw, tmax, norms, grp)
                assert bool((b <= torch.maximum(1.25 * b16, beta * own) * (1 + 1e-9)).all()), (nd, beta, b / b16, b / own)
                groups[beta] += int(grp.max()) + 1
            assert torch.equal(bench.vnni_groups(lw, tmax, norms=tmax.double(), beta=0.0), bench.vnni_groups(lw, tmax))
            assert int(bench.vnni_groups(lw, tmax, norms=norms, nscale=ns, beta=1e30).max()) == 0
    assert groups[0.5] < groups[0.0] < sum(4 * ((nd + 15) // 16) for nd in (1, 16, 17, 33, 71, 92, 250)), groups


def test_kernel_vnni_takes_the_merged_groups(bench, vnni_rl):
    """The kernel's flush groups are grp17's column-maximum rule's (``kernel_groups``: VNNI_L2 0, the default again
    since vg18; the columns' maxima by brute force): on lights whose groups merge, the default call equals the float64
    emulation of the quantised sums with those groups (exact + f_v sum_k T_v,k (q_k s_g(k) - L_k)) within float
    rounding, and its difference from the emulation with fixed groups of 16, and with vnb18's L2 groups where they
    differ, is the groupings' difference (least-squares factor 1 +- 0.2, not 0); within the bound; the per-call guard
    does not trip on these lights (their L2 bound below the transfer's own)."""
    merged = differ = 0
    for rl, spec, N in ((vnni_rl, "studio", 100), (vnni_rl, "sky", 61), (vnni_rl, "sky", 100), (vnni_rl, "sky", 300),
                        (vnni_rl, "sky", vnni_rl.P)):
        rl._kernel()
        nb = rl.dense.shape[0]
        d16 = rl.dense.reshape(nb, rl.Pd, 32)
        tmax = d16.to(torch.int32).abs().amax(dim=(0, 2))
        nrm, ns = bench.dense_norms(rl)
        fac = rl._factor(3, True).double()
        li, lv, _ = rl.light(spec, N, "transport")
        lv = lv.float().contiguous()
        ds, lw = bench.kernel_dense_order(rl, li, lv)
        grp = bench.vnni_groups(lw, tmax[ds])  # grp17's rule, the kernel's default
        g_l2 = bench.vnni_groups(lw, tmax[ds], norms=nrm[ds], nscale=ns)  # vnb18's (-DVNNI_L2=1)
        out, _ = _default_and_float(rl, li, lv)
        exact = _exact(rl, li, lv)
        b = bench.vnni_bound(rl, li, lv)
        assert not b["guard"], (spec, N, b["guard_ratio"])
        assert bool(((out.double() - exact).abs() <= b["bound"] + b["slack"]).all()), (spec, N)
        tk = d16[:, ds, :].double()

        def emul(g):
            q, s, gi = bench.quantise_light(lw, g, tmax[ds])
            dq = q.double() * s.double()[gi] - lw.double()  # [nd, 3]
            return exact + torch.einsum("bkv,kc->bvc", tk, dq).reshape(-1, 3)[:rl.V] * fac

        e_g = emul(grp)
        assert bool(((out.double() - e_g).abs() <= b["slack"]).all()), (spec, N)
        for other, g_o in ((16, torch.arange(ds.numel()) // 16), ("L2", g_l2)):
            if torch.equal(g_o, grp):
                continue
            e_o = emul(g_o)
            if other == 16 and int(grp.max()) + 1 < (ds.numel() + 15) // 16:
                merged += 1
            differ += other != 16
            dg = (e_g - e_o).flatten()  # the grouping's own effect: out - e_o = a dg + rounding, a = 1 with these groups
            a = float(((out.double() - e_o).flatten() @ dg) / (dg @ dg))
            assert abs(a - 1) < 0.2, (spec, N, other, a)
    assert merged >= 1, (merged, differ)


def test_kernel_vnni_guard_takes_the_float_loop(bench, vnni_rl, vnni_rl8):
    """kernels/wavelet.c's per-call guard (vg18): a call whose VNNI L2 bound sum_G (s_G,c / 2) sum_{k in G} ||scale (.)
    T_:,k|| exceeds the transfer's own ||scale|| sum_k |L_k,c| / 2 in some channel takes the float dense loop — its
    output is C | FDENSE's bits (``float32``) and within float rounding of the float64 sum of the same stored values
    (``relight.wavelet_dense``) — and the others the VNNI loop (not those bits, within the VNNI bound); the mirror
    (``vnni_bound``'s ``guard``, brute-force norms and maxima) decides as the kernel does. One light term x 1e4 at
    N = 100 (the huge term in the first flush group: bound ~3x the transfer's own) and on the R = 8 layout the studio
    and sky lights (1.0-2.0x) trip it; the sky with a 1e4 sun keeps the premise at R = 16 (bound below the
    transfer's own) and takes the VNNI loop, within its bound."""
    seen = {True: 0, False: 0}
    hdr = bench.hdr_lights(vnni_rl, 100)
    cases = [(vnni_rl, name, li, lv) for name, (li, lv, _) in hdr.items()]
    cases += [(vnni_rl8, f"R8 {spec} {N}", *vnni_rl8.light(spec, N, "transport")[:2]) for spec, N in (("studio", 10),
                                                                                                     ("sky", 100))]
    for rl, name, li, lv in cases:
        lv = lv.float().contiguous()
        assert rl._takes_vnni(li, lv), name
        b = bench.vnni_bound(rl, li, lv)
        out, fl = rl(li, lv).clone(), rl.float32(li, lv).clone()
        exact = _exact(rl, li, lv)
        assert b["guard"] == (b["guard_ratio"] > 1), name
        if b["guard"]:
            assert torch.equal(out, fl), (name, b["guard_ratio"])
            assert bool(((out.double() - exact).abs() <= b["slack"]).all()), name  # the float loop: rounding only
        else:
            assert not torch.equal(out, fl), (name, b["guard_ratio"])
            assert bool(((out.double() - exact).abs() <= b["bound"] + b["slack"]).all()), name
        seen[b["guard"]] += 1
    assert bench.vnni_bound(vnni_rl, *hdr["one term x 1e4"][:2])["guard"]
    assert not bench.vnni_bound(vnni_rl, *hdr["sky + sun 1e4"][:2])["guard"]
    assert seen[True] >= 3 and seen[False] >= 1, seen
