"""The cross-family target search's branch and bound (harness.target): the bytes floor known before
a fit never exceeds what a fitted codec stores, and the pruned search finds what brute force over
the same grid finds, with fewer fits; the dry run's cost bound holds."""
import math
import warnings

import pytest
import torch

from prt_torch import codecs
from prt_torch.harness.target import bytes_floor, search_cost, search_families


@pytest.mark.parametrize("setting", [
    {"type": "vq", "clusters": 7}, {"type": "vq", "clusters": 300},
    {"type": "pca", "vectors": 3}, {"type": "pca", "vectors": 5, "center": False},
    {"type": "mrt_pca", "vectors": 4},
    {"type": "cpca", "clusters": 4, "vectors": 3}, {"type": "cpca_static", "clusters": 300, "vectors": 2},
    {"type": "cpca_iterative", "clusters": 8, "vectors": 2, "iterations": 1},
])
def test_the_floor_never_exceeds_the_stored_bytes(setting):
    X = torch.randn(500, 48, generator=torch.Generator().manual_seed(0))
    params = {k: v for k, v in setting.items() if k != "type"}
    c = codecs.get(setting["type"], **params)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        enc = c.fit_encode(X, **({"matrix_shape": (16, 3)} if setting["type"] == "mrt_pca" else {}))
    stored = c.storage(enc)["bytes_total"] / 500
    floor = bytes_floor(setting, 500, 48)
    assert 0 < floor <= stored, (floor, stored)
    assert floor >= 0.5 * stored or setting["type"] == "vq"  # a bound with teeth: the weights and basis are most of it


def _fake_run(calls, points, dim):
    """A codec family whose PSNR grows with clusters and vectors (the search's premise), stored
    bytes above the floor (labels and means added), evaluated without any fit."""
    def run_setting(s):
        calls.append(s)
        K, n = s.get("clusters", 1), s.get("vectors", 0)
        psnr = 20 + 6 * math.log2(1 + n) + 2.5 * math.log2(K)
        b = bytes_floor(s, points, dim) + (1 if K > 1 else 0) + 4.0 * K * dim / points
        sid = f"{s['type']}-" + "-".join(f"{k}{v}" for k, v in sorted(s.items()) if k != "type")
        return {"setting_id": sid, "codec": s["type"], "params": {k: v for k, v in s.items() if k != "type"},
                "psnr_lights_db": psnr, "bytes_per_vertex": b, "fps": 1.0}
    return run_setting


def _cfg(goal):
    return {"codecs": [{"type": "vq"}, {"type": "pca"}, {"type": "cpca"}],
            "target": {"psnr": goal, "metric": "psnr_lights_db", "by": "bytes", "lo": 1, "hi": 32, "hi_clusters": 256}}


@pytest.mark.parametrize("goal", [38.0, 44.0, 50.0])
def test_branch_and_bound_finds_the_brute_force_cheapest_with_fewer_fits(goal):
    P, D = 10242, 1024
    calls: list = []
    out = search_families(_cfg(goal), _fake_run(calls, P, D), P, D)
    grid = [{"type": "vq", "clusters": 2 ** i} for i in range(9)] + [{"type": "pca", "vectors": n} for n in range(1, 33)] + \
        [{"type": "cpca", "clusters": 2 ** i, "vectors": n} for i in range(9) for n in range(1, 33)]
    everything = [_fake_run([], P, D)(s) for s in grid]
    meeting = [r for r in everything if r["psnr_lights_db"] >= goal]
    assert out["met"] == bool(meeting)
    if meeting:
        assert out["winner"]["bytes_per_vertex"] == pytest.approx(min(r["bytes_per_vertex"] for r in meeting))
        for fam, f in out["families"].items():
            mine = [r for r in meeting if r["codec"] == fam]
            assert bool(mine) == bool(f.get("best"))
            if mine:
                assert f["best"]["bytes_per_vertex"] == pytest.approx(min(r["bytes_per_vertex"] for r in mine))
    cost = search_cost(_cfg(goal), P, D)
    assert len(calls) <= cost["total"]
    assert out["pruned"], "the bound cut nothing on a front where large cluster counts cost more"


class _State:
    """What harness.run.run_target reads of a run: V, X's width and run_setting(s, timed)."""

    def __init__(self, points, dim):
        import types

        self.calls: list = []
        self.ev = types.SimpleNamespace(V=points, X=torch.empty(0, dim))
        fake = _fake_run([], points, dim)

        def run_setting(s, timed=True):
            self.calls.append((dict(s), timed))
            r = fake(s)
            return {**r, "timed": timed, "fps": 100.0 if timed else None}
        self.run_setting = run_setting


@pytest.mark.parametrize("by", ["bytes", "fps"])
def test_probes_are_untimed_and_only_the_finalists_are_timed(by):
    """Search on the error alone: every probe asks for no timing, then exactly the winner and each
    family's best are timed (and carry their fps); with by=fps, the rate is the criterion, so
    every probe is timed."""
    from prt_torch.harness.run import run_target

    P, D = 10242, 1024
    st = _State(P, D)
    cfg = _cfg(44.0)
    cfg["target"]["by"] = by
    out = run_target(cfg, st, log=lambda s: None)
    probes = [c for c in st.calls[:out["evaluated"]]]
    finals = st.calls[out["evaluated"]:]
    bests = [f["best"] for f in out["families"].values() if f.get("best")]
    assert bests and out["winner"] in bests
    if by == "bytes":
        assert all(not timed for _, timed in probes)
        assert sorted(s["type"] for s, _ in finals) == sorted(b["codec"] for b in bests) and all(t for _, t in finals)
    else:
        assert all(timed for _, timed in probes)
    assert all(b["fps"] == 100.0 for b in bests)  # what the report prints for each family's best was timed


def test_cpca_at_one_cluster_reuses_pcas_probes():
    """CPCA's single-cluster bisection reads PCA's outcomes at the same vector counts (the same fit)
    and fits once, at the vector count found, for its bytes."""
    P, D = 10242, 1024
    calls: list = []
    out = search_families(_cfg(44.0), _fake_run(calls, P, D), P, D)
    one = [c for c in calls if c["type"] == "cpca" and c.get("clusters") == 1]
    pca_v = out["families"]["pca"]["best"]["params"]["vectors"]
    assert [c["vectors"] for c in one] == [pca_v] and out["reused"]


@pytest.mark.parametrize("setting", [
    {"type": "neural", "latent": 2, "features": 6, "width": 8, "depth": 1},
    {"type": "neural", "latent": 3, "features": 8, "width": 8, "depth": 2, "code_dtype": "float16"},
    {"type": "neural", "latent": 2, "features": 6, "width": 8, "depth": 1, "clusters": 3},
    {"type": "neural", "latent": 2, "features": 6, "width": 8, "depth": 1, "clusters": 3, "cluster_decoder": "full"},
    {"type": "neural", "latent": 4},  # the codec's defaults for the rest (H = 16, width 32, depth 2)
])
def test_the_neural_floor_is_what_a_fitted_codec_stores_but_its_labels(setting):
    """The learned codec's floor (codes, last layers, φ, code samples; from the setting and the codec's
    defaults, before any fit) equals the stored bytes of a fit less its labels (int8 per point with
    clusters, int32 per code sample): never above, with teeth."""
    X = torch.randn(300, 20, generator=torch.Generator().manual_seed(1))
    params = {k: v for k, v in setting.items() if k != "type"}
    c = codecs.get("neural", epochs=2, encode_iters=0, **params)
    enc = c.fit_encode(X)
    st = c.storage(enc)
    labels = st["bytes"].get("codes.labels", 0) + st["bytes"]["model.code_sample_labels"]
    floor = bytes_floor(setting, 300, 20)
    assert floor * 300 == pytest.approx(st["bytes_total"] - labels, rel=1e-12), (floor, st["bytes"])


def test_neural_latent_search_bisects_and_prunes_what_cannot_be_cheaper():
    """The learned codec is searched on its code size k (bisection on [lo, min(hi, D - 1, H)]): a
    fake family whose PSNR grows with k finds the smallest k meeting the target; and after a cheaper
    family, by bytes, code sizes whose floor is above it are not fitted (pruned, said)."""
    P, D = 2000, 256
    calls: list = []

    def run_setting(s):
        calls.append(dict(s))
        if s["type"] == "neural":
            psnr, b = 20 + 3 * s["latent"], bytes_floor(s, P, D) + 1
        else:
            psnr, b = 20 + 6 * math.log2(1 + s["vectors"]), bytes_floor(s, P, D)
        sid = f"{s['type']}-" + "-".join(f"{k}{v}" for k, v in sorted(s.items()) if k != "type")
        return {"setting_id": sid, "codec": s["type"], "params": {k: v for k, v in s.items() if k != "type"},
                "psnr_lights_db": psnr, "bytes_per_vertex": b, "fps": 1.0}

    cfg = {"codecs": [{"type": "neural", "features": 16}],
           "target": {"psnr": 38.0, "metric": "psnr_lights_db", "by": "bytes", "lo": 1, "hi": 64, "hi_clusters": 16}}
    out = search_families(cfg, run_setting, P, D)
    assert out["families"]["neural"]["best"]["params"]["latent"] == 6  # 20 + 3k >= 38
    assert all(s["latent"] <= 16 for s in calls) and len(calls) <= search_cost(cfg, P, D)["total"] == 5
    calls.clear()
    cfg["codecs"] = [{"type": "pca"}, {"type": "neural", "features": 16}]
    out = search_families(cfg, run_setting, P, D)
    pca_b = out["families"]["pca"]["best"]["bytes_per_vertex"]
    assert all(bytes_floor(s, P, D) < pca_b for s in calls if s["type"] == "neural")
    assert any(x.startswith("neural latent") for x in out["pruned"])
