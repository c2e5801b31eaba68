"""The benchmark harness: configs, overrides and sweeps, an end-to-end tiny sweep whose numbers
are checked against each other, resume after a crash, the target search, and the metrics."""
import csv
import json
import math
import time

import pytest
import torch
import yaml

from prt_torch.harness import config as hc
from prt_torch.harness import metrics as hm
from prt_torch.harness.timing import measure, torch_threads

TINY = {
    "name": "tiny",
    "scene": {"name": "convex", "size": "small"},
    "transfer": {"type": "diffuse", "bands": 3, "samples": 64},
    "lights": ["sky", "directional:direction=0.3,0.2,1;intensity=2"],
    "metrics": {"random_lights": 256, "repeats": 3, "warmup": 1, "cold_pairs": 3},
    "codecs": [
        {"type": "vq", "clusters": [4, 16]},
        {"type": "pca", "vectors": [2]},
        {"type": "cpca", "clusters": 4, "vectors": 2},
    ],
    "render": {"enabled": True, "width": 64, "height": 64},
}


def write_cfg(tmp_path, cfg):
    c = dict(cfg)
    c.setdefault("cache_dir", str(tmp_path / "cache"))
    c.setdefault("output_dir", str(tmp_path / "reports"))
    p = tmp_path / "cfg.yaml"
    p.write_text(yaml.safe_dump(c))
    return p


# ------------------------------------------------------------------ config, overrides, sweeps

def test_overrides_and_sweep_expansion(tmp_path):
    p = write_cfg(tmp_path, TINY)
    cfg = hc.load_config(str(p), ["transfer.bands=4", "codecs.1.vectors=[1,2,3]", "metrics.repeats=7"])
    assert cfg["transfer"]["bands"] == 4 and cfg["metrics"]["repeats"] == 7
    settings = hc.expand_codecs(cfg["codecs"])
    assert [s["type"] for s in settings] == ["vq", "vq", "pca", "pca", "pca", "cpca"]
    assert [s.get("vectors") for s in settings if s["type"] == "pca"] == [1, 2, 3]
    grid = hc.expand_codecs([{"type": "cpca", "clusters": [2, 4], "vectors": [1, 2, 3]}])
    assert len(grid) == 6 and {(g["clusters"], g["vectors"]) for g in grid} == {(c, v) for c in (2, 4) for v in (1, 2, 3)}
    runs = hc.expand_runs(hc.load_config(str(p), ["transfer.bands=[2,3]"]))
    assert [r["transfer"]["bands"] for r in runs] == [2, 3]
    assert [r["name"] for r in runs] == ["tiny-bands2", "tiny-bands3"]


@pytest.mark.parametrize(
    "override, match",
    [
        ("transfer.bandz=3", "bandz"),
        ("transfer.M=8", "M"),  # a parameter of mrt, not of diffuse
        ("transfer.bands=0", "bands"),
        ("transfer.brdf={type: nosuchbrdf}", "brdf"),
        ("metrics.repeats=abc", "metrics.repeats"),
        ("codecs.0.type=nosuchcodec", "nosuchcodec"),
        ("codecs.1.vectors=-1", "vectors"),
        ("codecs.0.colour=1", "colour"),
        ("transfer.type=spectral", "transfer.type"),
        ("lights.1={type: spotlight}", "lights.1"),
        ("views.count=0", "views.count"),
        ("render.width=0", "render.width"),
        ("scene.size=huge", "scene.size"),
        ("metrics.max_memory_gb=-1", "max_memory_gb"),
        ("target.lo=70", "lo=70 > hi"),
        ("target.metric=speed", "target.metric"),
        ("scene.name=/no/such/mesh.obj", "scene.name"),
        ("codecs.5.vectors=1", "not a valid index"),
        ("nonsense", "key.path=value"),
    ],
)
def test_invalid_config_fails_before_any_work(tmp_path, override, match):
    p = write_cfg(tmp_path, TINY)
    with pytest.raises((ValueError, FileNotFoundError), match=match):
        hc.load_config(str(p), [override])
    assert not (tmp_path / "cache").exists() and not (tmp_path / "reports").exists()


def test_unknown_top_level_key_and_missing_config(tmp_path):
    bad = dict(TINY, colour_space="srgb")
    with pytest.raises(ValueError, match="unknown config key 'colour_space'"):
        hc.load_config(str(write_cfg(tmp_path, bad)))
    with pytest.raises(FileNotFoundError, match="not found"):
        hc.load_config("no-such-config")


def test_shipped_configs_validate():
    names = hc.builtin_configs()
    assert {"default", "glossy", "diffuse"} <= set(names)
    for n in names:
        cfg = hc.load_config(n)
        # a wavelet transfer is relit sparse as it is: its config (allfrequency) has no SH codecs
        assert hc.expand_codecs(cfg["codecs"]) or cfg["transfer"]["type"] == "wavelet"


@pytest.mark.parametrize("entry, where", [
    ({"codecs": [{"name": "pca", "vectors": 2}]}, "codecs.0.name"),
    ({"transfer": {"kind": "diffuse"}}, "transfer.kind"),
    ({"transfer": {"type": "glossy", "params": {"bands_out": 3}}}, "transfer.params"),
])
def test_old_config_keys_say_what_they_are_now(tmp_path, entry, where):
    with pytest.raises(ValueError, match=f"'{where}'"):
        hc.load_config(str(write_cfg(tmp_path, {**TINY, **entry})))


def test_transfer_parameter_lists_sweep_unless_the_parameter_takes_a_list(tmp_path):
    cfg = hc.load_config(str(write_cfg(tmp_path, dict(TINY, transfer={"type": "glossy", "bands": [2, 3], "drop_out": [[1, 0]]}))))
    runs = hc.expand_runs(cfg)
    assert [r["transfer"]["bands"] for r in runs] == [2, 3]
    assert all(r["transfer"]["drop_out"] == [[1, 0]] for r in runs)


# ------------------------------------------------------------------ metrics and timing

def test_random_light_psnr_does_not_depend_on_the_thread_count():
    """A setting run on a Ray worker (one thread) reports the local run's figures bit for bit: the
    Gram matrix's reduction over every point is taken in one thread (MKL split it between
    threads on an Intel Xeon, and the PSNR moved in its last digits), compared as floats at 1,
    2 and 3 threads. (Where MKL does not split it, this holds without the fix too.)"""
    from prt_torch.harness.timing import torch_threads

    for seed in range(12):  # a last-bit difference in G reaches the PSNR for some inputs only (1 of these 12 before)
        g = torch.Generator().manual_seed(seed)
        X = 10 * torch.randn(5000, 2 * 9, generator=g)
        Xh = X + 0.3 * torch.randn(5000, 18, generator=g)
        got = []
        for n in (1, 2, 3):
            with torch_threads(n):
                got.append(hm.random_light_psnr(X, Xh, 9, n_lights=64, seed=seed))
        assert got[0] == got[1] == got[2], (seed, got)


def test_random_light_psnr_monte_carlo_matches_closed_form():
    g = torch.Generator().manual_seed(0)
    X = torch.randn(300, 2 * 9, generator=g)
    Xh = X + 0.01 * torch.randn(300, 18, generator=g)
    se, rel = hm.squared_error(X, Xh)
    closed = hm.random_light_psnr_analytic(se, 300, 9)
    mc = hm.random_light_psnr(X, Xh, 9, n_lights=20000, seed=1)
    assert abs(mc - closed) < 0.1
    # brute force for a handful of lights, straight from the definition
    L = hm.random_unit_vectors(500, 9, seed=2)
    d = (X - Xh).double().reshape(300, 2, 9)
    brute = float(((d @ L.T) ** 2).sum(1).mean())
    assert abs(-10 * math.log10(brute) - hm.random_light_psnr(X, Xh, 9, n_lights=500, seed=2)) < 1e-9
    assert 0 < rel < 1e-3


@pytest.mark.parametrize("n_lights", [5, 40])  # fewer lights than inputs (projection form) and more (Gram form)
def test_random_light_psnr_and_squared_error_by_row_blocks(monkeypatch, n_lights):
    """By row blocks (BLOCK_ELEMENTS made tiny: 7 rows a block, the last one short) both metrics
    equal the brute force from their definitions: SE = Σ (x − x̂)², and the mean over the sampled
    lights of Σ_p ‖Δ_p l‖² / P in float64 — for n_lights below n_in too, where the row blocks are
    projected on the lights instead of forming the Gram matrix."""
    g = torch.Generator().manual_seed(3)
    X = torch.randn(103, 3 * 12, generator=g)
    Xh = X + 0.05 * torch.randn(103, 36, generator=g)
    monkeypatch.setattr(hm, "BLOCK_ELEMENTS", 7 * 36)
    d = (X.double() - Xh.double())
    se, rel = hm.squared_error(X, Xh)
    assert se == pytest.approx(float((d * d).sum()), rel=1e-12)
    assert rel == pytest.approx(float((d * d).sum() / (X.double() ** 2).sum()), rel=1e-12)
    L = hm.random_unit_vectors(n_lights, 12, seed=4)
    brute = float(((d.reshape(103, 3, 12) @ L.T) ** 2).sum(1).mean())
    # the Gram form sums in float64 (1e-9 dB); the projection form takes float32 inputs' difference and
    # their projection on the lights in float32 (a relative rounding of ~12 eps32 at most per product
    # over these 12 inputs: 4.343 · 12 · 2^-24 ≈ 3e-6 dB), the squares summed in float64
    tol = 1e-9 if n_lights >= 12 else 1e-5
    assert abs(-10 * math.log10(brute) - hm.random_light_psnr(X, Xh, 12, n_lights=n_lights, seed=4)) < tol


def test_psnr_vs_reference_definition():
    ref = torch.tensor([[1.0, 2.0], [4.0, 0.0]], dtype=torch.float64)
    test = ref + torch.tensor([[0.1, -0.1], [0.0, 0.2]], dtype=torch.float64)
    mse = (0.01 + 0.01 + 0.04) / 4
    assert math.isclose(hm.psnr_vs_reference(ref, test), 10 * math.log10(16 / mse), rel_tol=1e-12)
    assert hm.psnr_vs_reference(ref, ref) == float("inf")


def test_measure_reports_median_and_spread():
    calls = []

    def f():
        calls.append(1)
        time.sleep(0.002)

    t = measure(f, repeats=5, warmup=2, min_sample_time=0.0)
    assert len(calls) == 8 and t.repeats == 5 and t.warmup == 2 and t.inner == 1  # + 1 calibration call
    fast = []
    t2 = measure(lambda: fast.append(1), repeats=3, warmup=0, min_sample_time=0.01)
    assert t2.inner > 1 and len(fast) == 1 + 3 * t2.inner  # timeit-style inner loop for fast functions
    assert 0.0019 < t.median < 0.5 and t.min <= t.q1 <= t.median <= t.q3 <= t.max
    assert t.spread >= 0 and t.rate(10) == pytest.approx(10 / t.median)


def test_torch_threads_sets_and_restores_the_count_even_on_error():
    before = torch.get_num_threads()
    seen = []
    with pytest.raises(RuntimeError):
        with torch_threads(1):
            seen.append(torch.get_num_threads())
            raise RuntimeError("inside")
    assert seen == [1] and torch.get_num_threads() == before
    with pytest.raises(ValueError, match="threads"):
        torch_threads(0)


# ------------------------------------------------------------------ end to end

def test_tiny_sweep_end_to_end_and_consistent_numbers(tmp_path, monkeypatch):
    from prt_torch.harness import timing
    from prt_torch.harness.run import run_benchmark

    method = timing.flush_method()
    if method is not None:  # the cold column flushes the setting's own tensors: the LLC-sized junk is never allocated

        def no_junk(nbytes):
            raise AssertionError(f"the timing path allocated {nbytes} bytes of eviction junk")

        monkeypatch.setattr(timing, "_junk", no_junk)
    cfg = hc.load_config(str(write_cfg(tmp_path, TINY)))
    logs = []
    run_dir = run_benchmark(cfg, progress=False, log=logs.append)
    for f in ["results.json", "results.csv", "report.md", "rd.png", "speed_accuracy.png", "renders/uncompressed.png", "renders/uncompressed.exr"]:
        assert (run_dir / f).is_file(), f
    res = json.loads((run_dir / "results.json").read_text())
    assert res["format"] == "prt_torch.results" and len(res["records"]) == 4
    assert res["machine"]["cores"] and res["config"]["transfer"]["bands"] == 3
    V = res["scene"]["vertices"]
    raw = res["transfer"]["raw_bytes"]
    n_in = res["transfer"]["n_in"]
    assert n_in == 9
    for r in res["records"]:
        assert r["bytes_per_vertex"] == pytest.approx(r["bytes_total"] / V)
        assert r["compression_ratio"] == pytest.approx(raw / r["bytes_total"])
        assert r["psnr_random_closed_form_db"] == pytest.approx(-10 * math.log10(r["se"] / (V * n_in)), abs=1e-9)
        assert abs(r["psnr_random_db"] - r["psnr_random_closed_form_db"]) < 1.0  # 256 random lights
        assert r["fps"] == pytest.approx(1 / r["relight_s"]) and r["vertices_per_s"] == pytest.approx(V / r["relight_s"])
        assert r["relight_timing"]["repeats"] >= 3
        assert 0 < r["fraction_of_bound"] < 2  # the bound is a lower bound on the time (noise aside)
        assert 0 < r["fraction_of_bound_cold"] < 3 and r["bound_cold"]["bound_s"] > 0  # the same from cold caches
        ev = r["bound_cold"]["eviction"]
        assert ev["method"] == (method or "junk read")
        if method is not None:  # what the two sides touch: at least the bound's buffers (2 x read + written), no LLC
            rb, wb = r["bound_bytes"]["read"], r["bound_bytes"]["written"]
            assert 2 * rb + wb <= ev["bytes"] < 2 * rb + wb + 4 * (rb + wb) + (1 << 20)
        assert len(r["psnr_per_light_view"]) == 2
        assert r["psnr_lights_db"] == pytest.approx(sum(p["psnr_db"] for p in r["psnr_per_light_view"]) / 2)
    vq = sorted((r for r in res["records"] if r["codec"] == "vq"), key=lambda r: r["params"]["clusters"])
    assert vq[1]["se"] <= vq[0]["se"]  # more clusters, less error
    rows = list(csv.DictReader((run_dir / "results.csv").open()))
    assert len(rows) == 4 and float(rows[0]["se"]) == pytest.approx(res["records"][0]["se"])
    md = (run_dir / "report.md").read_text()
    assert "| vq |" in md and "| pca |" in md and "| cpca |" in md and "Pareto front" in md
    renders = list((run_dir / "renders").glob("*.png"))
    assert len(renders) == 4  # uncompressed + best of each of 3 codecs
    # cached transfer, records for resume
    assert len(list((tmp_path / "cache").glob("transfer-diffuse-*.prt"))) == 1
    assert len(list((run_dir / "records").glob("*.json"))) == 4


def test_crash_mid_sweep_keeps_records_and_resume_skips_them(tmp_path, monkeypatch):
    from prt_torch.harness import run as hr

    cfg = hc.load_config(str(write_cfg(tmp_path, dict(TINY, render={"enabled": False}))))
    real = hr.evaluate_setting
    calls = []

    def crashing(ev, setting, *a, **k):
        calls.append(setting)
        if len(calls) == 3:
            raise KeyboardInterrupt("simulated interruption")
        return real(ev, setting, *a, **k)

    monkeypatch.setattr(hr, "evaluate_setting", crashing)
    with pytest.raises(KeyboardInterrupt):
        hr.run_benchmark(cfg, progress=False, log=lambda s: None)
    run_dir = tmp_path / "reports" / "tiny"
    assert len(list((run_dir / "records").glob("*.json"))) == 2
    assert not (run_dir / "results.json").exists()
    calls.clear()
    monkeypatch.setattr(hr, "evaluate_setting", real)
    counted = []
    monkeypatch.setattr(hr, "evaluate_setting", lambda *a, **k: counted.append(1) or real(*a, **k))
    hr.run_benchmark(cfg, progress=False, log=lambda s: None)
    assert len(counted) == 2  # only the two unfinished settings ran
    assert len(json.loads((run_dir / "results.json").read_text())["records"]) == 4


def test_memory_estimate_refuses_before_work(tmp_path):
    from prt_torch.harness.run import run_benchmark

    cfg = hc.load_config(str(write_cfg(tmp_path, TINY)), ["metrics.max_memory_gb=0.0001"])
    with pytest.raises(ValueError, match="estimated"):
        run_benchmark(cfg, progress=False, log=lambda s: None)
    assert not (tmp_path / "cache").exists()


def test_target_search_finds_the_smallest_setting(tmp_path):
    from prt_torch.harness.run import run_benchmark

    cfg = hc.load_config(str(write_cfg(tmp_path, dict(TINY, render={"enabled": False}, codecs=[{"type": "pca", "vectors": 1}]))),
                         ["target.psnr=35", "target.codec=pca", "target.param=vectors", "target.lo=1", "target.hi=8"])
    run_dir = run_benchmark(cfg, progress=False, log=lambda s: None)
    res = json.loads((run_dir / "results.json").read_text())
    t = res["target"]
    assert t["met"] and t["achieved_db"] >= 35
    by_v = {r["params"]["vectors"]: r["psnr_lights_db"] for r in res["records"] if r["codec"] == "pca"}
    k = t["value"]
    assert by_v[k] >= 35
    if k > 1:  # brute-force check of minimality: one vector fewer misses the target
        if k - 1 not in by_v:
            cfg2 = hc.load_config(str(write_cfg(tmp_path, dict(TINY, render={"enabled": False}, codecs=[{"type": "pca", "vectors": k - 1}]))))
            res2 = json.loads((run_benchmark(cfg2, progress=False, log=lambda s: None) / "results.json").read_text())
            by_v[k - 1] = res2["records"][0]["psnr_lights_db"]
        assert by_v[k - 1] < 35


# ------------------------------------------------------------------ one uncompressed reference

@pytest.mark.parametrize("kind", ["glossy", "mrt"])
def test_harness_reference_is_relight(kind):
    """The harness's uncompressed PSNR reference and its speed peer are prt_torch.relight: the
    same numbers as relight.glossy / relight.mrt called on the transfer from a camera position,
    including the zero below each vertex's horizon."""
    from prt_torch import relight
    from prt_torch.harness.evaluate import Evaluator, camera_positions
    from prt_torch.lighting import load_light
    from prt_torch.scene import load_scene
    from prt_torch.transfer import get_kind

    mesh = load_scene("bumpy_sphere", size="small")
    params = {"bands": 3, "samples": 32, "bands_out": 3} | ({"M": 5} if kind == "mrt" else {})
    tr = get_kind(kind).precompute(mesh, params)
    ev = Evaluator(tr)
    L = load_light("sky", bands=3)
    center = ev.points.mean(0)
    cam = camera_positions(center, float((ev.points - center).norm(dim=-1).max()), 1, 35.0, 20.0)[0]
    got = ev.reference(L, ev.view_weights(cam))
    v = relight.local_view(mesh.frames().double(), mesh.vertices.double(), eye=cam)
    want = (relight.glossy(tr.data, L.float(), v, tr.meta["out_index"]) if kind == "glossy"
            else relight.mrt(tr.data, L.float(), v))
    below = v[:, 2] <= 0
    assert below.any() and not below.all()  # the camera sees some vertices from behind
    assert torch.allclose(got, want, rtol=1e-5, atol=1e-6)
    assert bool((got[below] == 0).all())


# ------------------------------------------------------------------ cross-family target search

def test_target_search_across_families_matches_brute_force(tmp_path):
    """`prt bench --target-psnr X` without a codec: the winner meets X, and brute force over the
    same grid (every family's axes, CPCA's clusters × vectors) finds no setting with fewer bytes."""
    from prt_torch.harness.run import run_benchmark

    base = dict(TINY, render={"enabled": False}, metrics={"random_lights": 8, "repeats": 1, "warmup": 0},
                codecs=[{"type": "vq", "clusters": 2}, {"type": "pca", "vectors": 1}, {"type": "cpca", "clusters": 2, "vectors": 1}])
    goal = 38.0
    over = [f"target.psnr={goal}", "target.lo=1", "target.hi=8", "target.hi_clusters=16"]
    res = json.loads((run_benchmark(hc.load_config(str(write_cfg(tmp_path, base)), over), progress=False,
                                    log=lambda s: None) / "results.json").read_text())
    t = res["target"]
    assert t["mode"] == "families" and t["met"] and t["winner"]["achieved_db"] >= goal
    assert set(t["families"]) == {"vq", "pca", "cpca"} and t["evaluated"] >= 3
    md = (tmp_path / "reports" / "tiny" / "report.md").read_text()
    assert "## Cheapest setting meeting the target" in md and f"**Winner: {t['winner']['setting_id']}**" in md
    # brute force over the same grid, in the same run directory (searched settings are reused)
    grid = dict(base, codecs=[{"type": "vq", "clusters": [1, 2, 4, 8, 16]}, {"type": "pca", "vectors": list(range(1, 9))},
                              {"type": "cpca", "clusters": [1, 2, 4, 8, 16], "vectors": list(range(1, 9))}])
    res2 = json.loads((run_benchmark(hc.load_config(str(write_cfg(tmp_path, grid))), progress=False,
                                     log=lambda s: None) / "results.json").read_text())
    meeting = [r for r in res2["records"] if r["psnr_lights_db"] >= goal]
    assert meeting and min(r["bytes_per_vertex"] for r in meeting) == pytest.approx(t["winner"]["bytes_per_vertex"])
    for name, f in t["families"].items():  # each family's runner-up is its own cheapest under brute force
        mine = [r for r in meeting if r["codec"] == name]
        if f.get("best"):
            assert min(r["bytes_per_vertex"] for r in mine) == pytest.approx(f["best"]["bytes_per_vertex"])
        else:
            assert not mine


def test_target_search_reaches_the_learned_codec(tmp_path):
    """`--target-psnr` searches the learned codec on its code size (harness.target: bisection on
    latent): its family's best is the smallest latent meeting the goal — checked against every
    latent of the range, whose fits the bisection leaves in records/ (3, then 2, then 1)."""
    from prt_torch.harness.run import run_benchmark

    neural = {"type": "neural", "features": 4, "width": 8, "depth": 1, "epochs": 10, "encode_iters": 0}
    base = dict(TINY, render={"enabled": False}, metrics={"random_lights": 8, "repeats": 1, "warmup": 0}, codecs=[neural])
    goal = 18.0  # measured: latent 1, 2, 3 give 16.5, 19.8, 20.1 dB here (10 epochs)
    over = [f"target.psnr={goal}", "target.lo=1", "target.hi=3"]
    run_dir = run_benchmark(hc.load_config(str(write_cfg(tmp_path, base)), over), progress=False, log=lambda s: None)
    f = json.loads((run_dir / "results.json").read_text())["target"]["families"]["neural"]
    assert f["searched"] and f["axes"] == ["latent"] and f["evaluated"] == 3
    recs = [json.loads(p.read_text()) for p in (run_dir / "records").glob("*.json")]
    by_k = {r["params"]["latent"]: r["psnr_lights_db"] for r in recs if "latent" in r["params"]}  # (the entry's own, default k)
    assert sorted(by_k) == [1, 2, 3]
    meeting = sorted(k for k, v in by_k.items() if v >= goal)
    assert meeting and meeting[0] > 1, by_k  # within reach, and not at the range's first value
    assert f["best"]["params"]["latent"] == meeting[0], (by_k, f)


def test_unreachable_target_says_the_best_found(tmp_path):
    from prt_torch.harness.run import run_benchmark

    base = dict(TINY, render={"enabled": False}, metrics={"random_lights": 8, "repeats": 1, "warmup": 0},
                codecs=[{"type": "vq", "clusters": 2}, {"type": "pca", "vectors": 1}])
    cfg = hc.load_config(str(write_cfg(tmp_path, base)), ["target.psnr=500", "target.hi=4", "target.hi_clusters=4"])
    run_dir = run_benchmark(cfg, progress=False, log=lambda s: None)
    t = json.loads((run_dir / "results.json").read_text())["target"]
    assert not t["met"] and "the best was" in t["note"] and "dB by" in t["note"]
    assert "Not met" in (run_dir / "report.md").read_text()


# ------------------------------------------------------------------ ablations

def test_transfer_ablation_lands_in_one_combined_report(tmp_path):
    from prt_torch.harness.run import run_benchmark

    cfg = dict(TINY, name="abl", render={"enabled": False}, metrics={"random_lights": 8, "repeats": 1, "warmup": 0},
               scene={"name": "occluder_over_plane", "size": "small"},
               transfer={"type": "diffuse", "bands": 3, "samples": 32, "shadows": ["never", "always"]},
               codecs=[{"type": "pca", "vectors": [1, 2]}], ablation="transfer.shadows")
    c = hc.load_config(str(write_cfg(tmp_path, cfg)))
    assert len(hc.expand_runs(c)) == 1  # the ablation key is not a run sweep
    run_dir = run_benchmark(c, progress=False, log=lambda s: None)
    assert sorted(p.name for p in (tmp_path / "reports").iterdir()) == ["abl"]
    res = json.loads((run_dir / "results.json").read_text())
    a = res["ablation"]
    assert a["key"] == "transfer.shadows" and a["reference_value"] == "always" and len(res["records"]) == 4
    assert {(r["ablation"]["value"], r["params"]["vectors"]) for r in res["records"]} == {(v, k) for v in ("never", "always") for k in (1, 2)}
    by = {p["value"]: p for p in a["per_value"]}
    assert by["always"]["model_psnr_db"] == float("inf") and by["never"]["rays_traced"] == 0 and by["always"]["rays_traced"] > 0
    assert math.isfinite(by["never"]["model_psnr_db"]) and by["never"]["model_psnr_db"] < 40  # shadows matter on this scene
    md = (run_dir / "report.md").read_text()
    assert "## Ablation" in md and "**shadows=never**" in md and (run_dir / "ablation.png").is_file()


def test_codec_parameter_ablation_tags_records(tmp_path):
    from prt_torch.harness.run import run_benchmark

    cfg = dict(TINY, name="abl2", render={"enabled": False}, metrics={"random_lights": 8, "repeats": 1, "warmup": 0},
               codecs=[{"type": "cpca", "method": ["static", "iterative"], "clusters": 4, "vectors": 2}], ablation="codecs.0.method")
    res = json.loads((run_benchmark(hc.load_config(str(write_cfg(tmp_path, cfg))), progress=False, log=lambda s: None)
                      / "results.json").read_text())
    assert sorted(r["ablation"]["value"] for r in res["records"]) == ["iterative", "static"]
    with pytest.raises(ValueError, match="ablation"):
        hc.load_config(str(write_cfg(tmp_path, dict(cfg, ablation="codecs.0.clusters"))))  # not a list


def test_paired_timing_in_cpu_time_leaves_out_time_off_the_core():
    """measure_paired(clock=time.thread_time): a side that spends its time off the CPU (sleeping,
    as when other processes hold the core) costs its CPU time only; in wall time the two sides
    below are equal (2 ms each), in CPU time the sleeping one is nearly free."""
    import time

    from prt_torch.harness.timing import measure_paired, torch_threads

    def spin():
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < 0.002:
            pass

    def sleep():
        time.sleep(0.002)

    wall = measure_paired(sleep, spin, repeats=5, warmup=1, min_sample_time=0.004, floor_pairs=10)
    with torch_threads(1):
        cpu = measure_paired(sleep, spin, repeats=5, warmup=1, min_sample_time=0.004, floor_pairs=10, clock=time.thread_time)
    assert 0.5 < wall.speedup < 1.2  # sleep overshoots a little: wall ratio spin/sleep just under 1
    assert cpu.speedup > 10 and cpu.ratio.median > 10  # both phases timed in CPU time
    # CPU time of the calling thread only: refused while torch would run its work on others too
    with torch_threads(2), pytest.raises(ValueError, match="counts only the calling thread's CPU time, and torch runs 2"):
        measure_paired(sleep, spin, repeats=1, clock=time.thread_time)


def test_paired_timing_gives_the_work_ratio_and_reports_contention():
    """measure_paired: a peer doing exactly twice the test's work comes out ~2x slower (the
    estimator, not a speed goal), and the contention record names its evidence."""
    from prt_torch.harness.timing import measure_paired

    import time

    def work(k):  # waits, not arithmetic (as in the cold test below): a busy machine does not move the ratio
        time.sleep(0.001 * k)

    p = measure_paired(lambda: work(2), lambda: work(4), repeats=9, warmup=1, min_sample_time=0.01, floor_pairs=20)
    assert 1.3 < p.ratio.median < 3.0
    assert 1.3 < p.speedup < 3.0 and p.floor["pairs"] == 20  # the fastest tenth of short samples: the same work ratio
    q = measure_paired(lambda: work(1), lambda: work(2), repeats=3)
    assert q.speedup == q.ratio.median and q.floor is None  # without the floor phase: the median per-pair ratio
    c = p.contention
    assert {"involuntary_switches_per_s", "cpu_over_wall", "load_average_1min", "trusted", "why_not"} <= set(c)
    assert c["trusted"] == (not c["why_not"])
    strict = measure_paired(lambda: work(1), lambda: work(1), repeats=3, max_switch_rate=-1.0)
    assert not strict.contention["trusted"] and "context switches" in strict.contention["why_not"][0]
    # adaptive floor phase: more batches of pairs while its even and odd pairs disagree, up to the cap
    # (floor_agree < 0: never agree; a huge floor_agree: always)
    grown = measure_paired(lambda: work(1), lambda: work(2), repeats=3, floor_pairs=6, floor_max_pairs=20, floor_agree=-1.0)
    assert grown.floor["pairs"] == 18 and len(grown.floor["halves"]) == 2  # 6, 12, 18; a fourth batch would pass 20
    once = measure_paired(lambda: work(1), lambda: work(2), repeats=3, floor_pairs=6, floor_max_pairs=20, floor_agree=1e9)
    assert once.floor["pairs"] == 6


def test_cold_paired_timing_alternates_single_calls_after_an_eviction():
    """measure_paired_cold: each side called warmup + repeats times, one call per sample, the
    order swapped every repeat; the per-pair ratio is the work ratio (a peer doing twice the
    test's work: ~2, the estimator, not a speed goal); the eviction buffer defaults to 4x the
    last-level cache, at least 64 MiB."""
    from prt_torch.harness.timing import last_level_cache_bytes, measure_paired_cold

    import time

    calls = []

    def work(name, k):  # waits, not arithmetic: the ratio is the estimator's, whatever else the machine runs
        calls.append(name)
        time.sleep(0.002 * k)  # (matrix products here once read 7x for 2x the work on a busy machine)

    p = measure_paired_cold(lambda: work("t", 1), lambda: work("p", 2), repeats=7, warmup=1, evict_bytes=1 << 20)
    assert calls == ["t", "p"] + ["t", "p", "p", "t"] * 3 + ["t", "p"]
    assert p.ratio.repeats == 7 and p.test.inner == 1 and p.speedup == p.ratio.median
    assert 1.5 < p.ratio.median < 2.5
    assert {"involuntary_switches_per_s", "trusted", "why_not"} <= set(p.contention)
    assert last_level_cache_bytes() >= 1 << 16
    with pytest.raises(ValueError, match="repeats"):
        measure_paired_cold(lambda: None, lambda: None, repeats=0)


def test_cold_paired_timing_calls_per_sample_each_after_its_own_eviction():
    """measure_paired_cold(calls=3): a sample is three calls, each preceded by an eviction (none of them timed: the
    per-call time is the sample's mean of the calls alone, so a slow eviction does not enter it)."""
    import time

    from prt_torch.harness import timing

    seq = []

    def work(name, k):
        seq.append(name)
        time.sleep(0.002 * k)

    def slow_evict():  # the junk read replaced by a slow step: were it timed, the ratio would drift toward 1
        seq.append("e")
        time.sleep(0.02)

    orig = timing._junk
    try:
        timing._junk = lambda nbytes: type("J", (), {"sum": staticmethod(slow_evict)})()
        p = timing.measure_paired_cold(lambda: work("t", 1), lambda: work("p", 2), repeats=3, warmup=0, calls=3)
    finally:
        timing._junk = orig
    assert seq == ["e", "t"] * 3 + ["e", "p"] * 6 + ["e", "t"] * 6 + ["e", "p"] * 3
    assert p.test.inner == 3 and p.ratio.repeats == 3
    assert 1.5 < p.ratio.median < 2.5
    with pytest.raises(ValueError, match="calls"):
        timing.measure_paired_cold(lambda: None, lambda: None, calls=0)


def test_cold_paired_timing_with_evict_flushes_the_given_tensors_and_caches_the_junk():
    """measure_paired_cold(evict=tensors): the same single-call alternation, the eviction a flush of
    exactly those tensors' bytes (overlaps once; the flush helper where there is one, else the junk
    read); without evict, the junk buffer is allocated once and reused, and freed on request."""
    from prt_torch.harness import timing

    calls = []
    a = torch.zeros(1000)  # 4000 B
    b = torch.zeros(10, 30)[:, ::2]  # a strided view: its span, 9 * 120 + 14 * 8 + 4 = 1196 B

    def work(name):
        calls.append(name)
        a.add_(1)

    p = timing.measure_paired_cold(lambda: work("t"), lambda: work("p"), repeats=5, warmup=1, evict=[a, a[10:], b])
    assert calls == ["t", "p"] + ["t", "p", "p", "t"] * 2 + ["t", "p"]
    assert p.ratio.repeats == 5 and p.test.inner == 1
    assert bool((a == 12).all())  # warm-up + repeats calls of each side
    method = timing.flush_method()
    if method is not None:
        assert p.eviction["method"] == method and p.eviction["bytes"] == 4000 + 1196 and p.eviction["median_s"] >= 0
    else:
        assert p.eviction["method"] == "junk read" and p.eviction["why"]
    timing.release_eviction_buffer()
    q1 = timing.measure_paired_cold(lambda: None, lambda: None, repeats=2, evict_bytes=1 << 20)
    junk = timing._JUNK["t"]
    q2 = timing.measure_paired_cold(lambda: None, lambda: None, repeats=2, evict_bytes=1 << 20)
    assert timing._JUNK["t"] is junk and q1.eviction == dict(q2.eviction, median_s=q1.eviction["median_s"])
    assert q1.eviction["method"] == "junk read" and q1.eviction["bytes"] == 1 << 20
    assert timing.release_eviction_buffer() == 1 << 20 and "t" not in timing._JUNK
    with pytest.raises(ValueError, match=r"tensors\[1\] is a str"):
        timing.measure_paired_cold(lambda: None, lambda: None, repeats=1, evict=[a, "a"])
    with timing.torch_threads(2), pytest.raises(ValueError, match="thread_time.*accepted: one thread"):
        timing.measure_paired_cold(lambda: None, lambda: None, repeats=1, evict=[a], clock=time.thread_time)


def test_flush_caches_keeps_the_bytes_and_refuses_what_it_cannot_flush():
    """The flush writes back and evicts, never changes memory: bytes equal after it (dirty lines of a
    just-written tensor included); strided views count their span, overlaps once, empty tensors and
    numpy arrays are accepted; a device, sparse or non-tensor item is refused naming it."""
    import numpy as np

    from prt_torch.harness import timing

    if timing.flush_method() is None:
        pytest.skip(f"no cache-flush helper here: {timing._FLUSH.get('why')}")
    g = torch.Generator().manual_seed(0)
    x = torch.randint(-2 ** 31, 2 ** 31 - 1, (4096,), dtype=torch.int32, generator=g)  # 16 KiB, just written: dirty lines
    want = x.numpy().tobytes()
    arr = np.arange(100, dtype=np.float64)[::-1]  # a negative stride
    assert timing.flush_caches([x, x[::3], x.view(64, 64).t(), torch.empty(0), torch.empty(0, 5)[:, 1:], arr]) == 16384 + 800
    assert x.numpy().tobytes() == want and arr[0] == 99.0
    assert timing.flush_caches([x[::3]]) == (1365 * 3 + 1) * 4 and timing.flush_caches([]) == 0
    for bad, match in [(torch.empty(3, device="meta"), r"tensors\[0\] is on meta"),
                       (torch.eye(3).to_sparse(), r"tensors\[0\] has layout torch.sparse_coo"),
                       ([1, 2], r"tensors\[0\] is a list")]:
        with pytest.raises(ValueError, match=match):
            timing.flush_caches([bad])
    with pytest.raises(ValueError, match="tensors is a Tensor; accepted: a list"):
        timing.flush_caches(x)


def test_working_set_finds_what_the_timed_callables_hold():
    """working_set: a nested function's closure, the bound's own buffers (io_bound_fn: read bytes
    copied into a buffer of the same size, the written bytes filled), containers and prt_torch
    objects' attributes; each tensor once."""
    from prt_torch import codecs
    from prt_torch.harness.timing import _flush_ranges, io_bound_fn, working_set

    bound = io_bound_fn(1000, 200)
    assert _flush_ranges(working_set(bound))[1] == 1000 + 1000 + 200
    X = torch.rand(50, 6)
    codec = codecs.get("pca", vectors=2)
    enc = codec.fit_encode(X)
    light = torch.rand(6, 1)
    buf = torch.empty(50, 1)
    prepared = codec.relighter(enc)

    def make():
        return lambda: prepared(light, out=buf)

    fn = make()
    fn()
    found = working_set(fn, bound)
    ids = {id(t) for t in found}
    assert len(ids) == len(found)
    assert {id(light), id(buf), *(id(t) for t in enc.tensors.values())} <= ids
    assert id(codec.basis_) in ids  # the model
    assert working_set({"a": [(light,)]}, None, 3) == [light]


def test_bench_report_has_a_mitsuba_validation_section(tmp_path):
    import os

    if not os.environ.get("CI"):  # in CI Mitsuba is installed (dev extra) and a missing one must fail
        pytest.importorskip("mitsuba")
    from prt_torch.harness.run import run_benchmark

    cfg = dict(TINY, name="val", render={"enabled": False}, metrics={"random_lights": 8, "repeats": 1, "warmup": 0},
               scene={"name": "occluder_over_plane", "size": "small"}, codecs=[{"type": "pca", "vectors": 2}],
               transfer={"type": "diffuse", "bands": 2, "samples": 64}, lights=["studio"],
               validation={"enabled": True, "vertices": 8, "spp": 64})
    run_dir = run_benchmark(hc.load_config(str(write_cfg(tmp_path, cfg))), progress=False, log=lambda s: None)
    res = json.loads((run_dir / "results.json").read_text())
    d = res["validation"]["report"]["direct"]
    assert 0.5 < d["ratio"] < 1.5 and d["ratio_se"] > 0  # 8 vertices, 64 spp: a coarse but independent check
    assert "## Validation against Mitsuba 3" in (run_dir / "report.md").read_text()


PART = {"name": "g", "note": "Gaussians on their own transfer.", "scene": {"name": "convex", "size": "small"},
        "transfer": {"type": "transport", "views": 1, "res": 4, "shadows": False, "brdf": {"type": "phong", "s": 4.0}},
        "codecs": [{"type": "gaussian", "lobes": 1, "max_iter": 5}, {"type": "pca", "vectors": 2}], "render": {"enabled": False}}


@pytest.mark.parametrize("part, match", [
    ({"note": "x"}, r"parts\.0\.name"),
    ({"name": "a/b"}, r"parts\.0\.name"),
    ({"name": "g", "target": {"psnr": 30}}, r"parts\.0.*target"),
    ({"name": "g", "codecs": [{"type": "gaussian", "lobes": 0}]}, r"parts\.0.*lobes"),
    ({"name": "g", "transfer": {"type": "transport", "res": 0}}, r"parts\.0.*res"),
])
def test_invalid_parts_fail_naming_the_entry(tmp_path, part, match):
    cfg = dict(TINY, parts=[part])
    with pytest.raises(ValueError, match=match):
        hc.load_config(str(write_cfg(tmp_path, cfg)))


def test_part_runs_on_its_own_transfer_into_the_same_report(tmp_path):
    """A config part (here: the Gaussian codec on transport tables) runs as a benchmark of its
    own under parts/<name>/ and lands as a section of the parent report with its scene, note
    and table; its figures equal those of the same config run on its own."""
    from prt_torch.harness.run import run_benchmark

    cfg = hc.load_config(str(write_cfg(tmp_path, dict(TINY, codecs=[{"type": "pca", "vectors": 2}], render={"enabled": False},
                                                       parts=[PART]))))
    run_dir = run_benchmark(cfg, progress=False, log=lambda s: None)
    res = json.loads((run_dir / "results.json").read_text())
    (part,) = res["parts"]
    assert part["name"] == "g" and part["dir"] == "parts/g"
    assert (run_dir / "parts" / "g" / "report.md").is_file()
    assert {r["codec"] for r in part["results"]["records"]} == {"gaussian", "pca"}
    assert part["results"]["transfer"]["kind"] == "transport" and res["transfer"]["kind"] == "diffuse"
    md = (run_dir / "report.md").read_text()
    assert "## Part `g`" in md and "Gaussians on their own transfer." in md and "| gaussian | lobes=1" in md
    alone = dict(PART, output_dir=str(tmp_path / "alone"), cache_dir=str(tmp_path / "cache"))
    alone.pop("note")
    alone.update({k: TINY[k] for k in ("lights", "metrics")})
    solo = run_benchmark(hc.load_config(str(write_cfg(tmp_path, alone))), progress=False, log=lambda s: None)
    ref = {r["setting_id"]: r for r in json.loads((solo / "results.json").read_text())["records"]}
    for r in part["results"]["records"]:
        assert r["se"] == pytest.approx(ref[r["setting_id"]]["se"], rel=1e-6)
        assert r["psnr_lights_db"] == pytest.approx(ref[r["setting_id"]]["psnr_lights_db"], abs=1e-6)
