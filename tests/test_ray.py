"""``--executor ray`` (issue 13): a local Ray with 2 CPUs gives the same per-setting figures as
the local executor and a bit-identical precompute; a killed task is retried; a failing setting
is reported while the others finish; an interrupted sweep resumes without recomputing.

Every comparison is against the local executor run in the same test (an independent path:
in-process, in order, no pickling). One Ray instance serves the whole module. Without Ray the
Ray tests skip (in CI, where ``.[dev]`` installs Ray, they fail instead); the tests of the
"Ray is missing" message run everywhere."""
import json
import os
import sys

import pytest
import torch
import yaml

from prt_torch.executor import ExecutorUnavailable, LocalExecutor, RayExecutor, TaskFailure, make_executor

try:
    import ray
except ImportError:  # pragma: no cover - dev installs ray
    ray = None

needs_ray = pytest.mark.skipif(ray is None and os.environ.get("CI", "").lower() != "true",
                               reason="Ray is not installed (pip install 'prt-torch[ray]'); the --executor ray tests need it")

SWEEP = {
    "name": "raysweep",
    "scene": {"name": "convex", "size": "small"},
    "transfer": {"type": "diffuse", "bands": 3, "samples": 64},
    "lights": ["sky", "directional:direction=0.3,0.2,1;intensity=2"],
    "metrics": {"random_lights": 64, "repeats": 2, "warmup": 0},
    "codecs": [{"type": "vq", "clusters": [4]}, {"type": "cpca", "clusters": 4, "vectors": 2}],
    "render": {"enabled": False},
}
#: the figures that must not depend on where a setting ran (timing columns do, and are not compared)
SAME = ("bytes_total", "bytes_per_vertex", "compression_ratio", "sloan_cost_floats", "storage", "se", "relative_se",
        "psnr_random_db", "psnr_random_closed_form_db", "psnr_lights_db", "psnr_lights_min_db", "psnr_per_light_view", "params")


@pytest.fixture(scope="module")
def ray_ex():
    """One local Ray (2 CPUs) for the module; test functions are pickled by value (the workers
    cannot import this test file)."""
    if ray is None:
        pytest.fail("CI=true but Ray is not installed: .[dev] must install it")
    ex = RayExecutor(num_cpus=2, max_retries=1).start()
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    yield ex
    ex.close()


def _cfg(tmp_path, sub, **over):
    from prt_torch.harness import config as hc

    c = {**SWEEP, **over, "cache_dir": str(tmp_path / sub / "cache"), "output_dir": str(tmp_path / sub / "reports")}
    p = tmp_path / f"{sub}.yaml"
    p.write_text(yaml.safe_dump(c))
    return hc.load_config(str(p))


def _square_or_fail(x):
    if x == 3:
        raise ValueError(f"item {x} is refused")
    return x * x


def _die_once(item):
    """Kills its worker process on the first attempt (a flag file marks it), then succeeds."""
    flag, x = item
    if not os.path.exists(flag):
        open(flag, "w").close()
        os._exit(1)  # no exception, no cleanup: the worker dies as if killed
    return x + 100


# ------------------------------------------------------------------------------ without Ray


def test_without_ray_the_message_says_how_to_install(monkeypatch, tmp_path, capsys):
    from prt_torch.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError
    with pytest.raises(ExecutorUnavailable, match=r"pip install 'prt-torch\[ray\]'"):
        make_executor("ray")
    monkeypatch.chdir(tmp_path)
    assert main(["bench", "default", "--executor", "ray", "--quiet"]) == 2  # refused before any work
    assert "pip install 'prt-torch[ray]'" in capsys.readouterr().err
    assert not (tmp_path / "cache").exists() and not (tmp_path / "reports").exists()
    assert main(["precompute", "convex", "-o", str(tmp_path / "t.prt"), "--executor", "ray"]) == 2
    assert "pip install 'prt-torch[ray]'" in capsys.readouterr().err


def test_bad_executor_values_are_named(tmp_path, capsys):
    from prt_torch.cli import main

    with pytest.raises(ValueError, match=r"executor='dask' is not accepted; choose one of \['local', 'ray'\]"):
        make_executor("dask")
    with pytest.raises(SystemExit):
        main(["bench", "--executor", "dask"])
    assert "invalid choice: 'dask'" in capsys.readouterr().err
    assert main(["precompute", "convex", "-o", str(tmp_path / "t.prt"), "--ray-address", "10.0.0.1:6379"]) == 2
    assert "--ray-address '10.0.0.1:6379' needs --executor ray" in capsys.readouterr().err
    with pytest.raises(ValueError, match="num_cpus=2 applies only to a local Ray"):
        RayExecutor("auto", num_cpus=2)


# ------------------------------------------------------------------------------ executor


@needs_ray
def test_map_equals_local_and_a_failing_item_is_reported_after_its_retry(ray_ex):
    items = [0, 1, 2, 3, 4, 5]
    seen = []
    out = ray_ex.map(_square_or_fail, items, on_result=lambda i, v: seen.append(i))
    assert [o for i, o in enumerate(out) if i != 3] == [_square_or_fail(x) for x in items if x != 3]
    f = out[3]
    assert isinstance(f, TaskFailure) and f.item == 3 and f.attempts == 2
    assert f.error == "ValueError: item 3 is refused"
    assert sorted(seen) == [0, 1, 2, 4, 5]  # on_result for the finished ones only
    with pytest.raises(ValueError, match="item 3"):  # the local executor stops at once, as before
        LocalExecutor().map(_square_or_fail, items)


@needs_ray
def test_a_killed_task_is_retried(ray_ex, tmp_path):
    flag = str(tmp_path / "died")
    assert ray_ex.map(_die_once, [(flag, 1)]) == [101]
    assert os.path.exists(flag)  # the first attempt did die
    flag2 = str(tmp_path / "died2")
    (f,) = RayExecutor(max_retries=0).map(_die_once, [(flag2, 2)])  # no retry: reported, not raised
    assert isinstance(f, TaskFailure) and f.attempts == 1 and "WorkerCrashedError" in f.error


# ------------------------------------------------------------------------------ precompute


@needs_ray
def test_precompute_on_ray_is_bit_identical_and_resumes_from_the_same_state(ray_ex, tmp_path):
    from prt_torch.scene import load_scene
    from prt_torch.transfer import ChunkInterrupt, RunOptions, precompute_diffuse

    mesh = load_scene("sphere_on_plane", size="small")
    kw = dict(bands=3, samples=32, bounces=1, seed=7)
    local = precompute_diffuse(mesh, **kw, run=RunOptions(chunk_size=400)).data

    def stop_after_first(i, n):
        raise ChunkInterrupt("simulated interruption")

    state = tmp_path / "state"
    with pytest.raises(ChunkInterrupt):
        precompute_diffuse(mesh, **kw, run=RunOptions(chunk_size=400, state_dir=state, executor=ray_ex, callback=stop_after_first))
    kept = sorted(p.name for p in state.glob("chunk_*.prt"))
    assert len(kept) == 1  # the chunk finished before the interruption, written by the driver
    mtime = (state / kept[0]).stat().st_mtime_ns
    resumed = []
    out = precompute_diffuse(mesh, **kw, run=RunOptions(chunk_size=400, state_dir=state, resume=True, keep_state=True,
                                                        executor=ray_ex, callback=lambda i, n: resumed.append(i))).data
    assert torch.equal(out, local)
    assert (state / kept[0]).stat().st_mtime_ns == mtime  # loaded, not recomputed
    assert sorted(resumed) == list(range(len(resumed))) and len(resumed) == -(-mesh.num_vertices // 400)


@needs_ray
def test_glossy_one_bounce_auto_on_ray_is_bit_identical(ray_ex):
    """Glossy with one bounce under the default 'auto' (per-vertex choice, the hits' face probe and
    guide traced by each chunk where its hits land, 4 rays per hit): the Ray executor's matrices and
    ray counts equal the local run's (the hit rays and the faces probed come back with each chunk;
    a face whose hits reach several workers is probed in each, so the probe rays may exceed the
    local run's, the faces probed and guided do not)."""
    from prt_torch.scene import load_scene
    from prt_torch.transfer import RunOptions
    from prt_torch.transfer.glossy import precompute_glossy

    mesh = load_scene("cornell_box", size="small")
    kw = dict(bands=3, bands_out=3, samples=32, bounces=1, seed=5, vertices=torch.arange(0, mesh.num_vertices, 7))
    a = precompute_glossy(mesh, **kw, run=RunOptions(chunk_size=100, progress=False))
    b = precompute_glossy(mesh, **kw, run=RunOptions(chunk_size=100, progress=False, executor=ray_ex))
    assert a.meta["estimator"] == "auto" and a.meta["hit_guide"]["faces_guided"] > 0
    assert torch.equal(a.data, b.data)
    assert a.meta["hit_rays_traced"] == b.meta["hit_rays_traced"] > 0 and a.meta["rays_traced"] == b.meta["rays_traced"]
    assert a.meta["hit_guide"] == b.meta["hit_guide"] and b.meta["hit_choice_rays"] >= a.meta["hit_choice_rays"] > 0


@needs_ray
def test_cli_precompute_with_executor_ray_writes_the_local_file(ray_ex, tmp_path):
    from prt_torch.cli import main
    from prt_torch.transfer import Transfer

    args = ["precompute", "convex", "--kind", "glossy", "--bands", "3", "--samples", "32", "--chunk", "500", "--no-progress"]
    assert main(args + ["-o", str(tmp_path / "local.prt")]) == 0
    assert main(args + ["-o", str(tmp_path / "ray.prt"), "--executor", "ray"]) == 0  # joins the module's Ray
    a, b = Transfer.load(tmp_path / "local.prt"), Transfer.load(tmp_path / "ray.prt")
    assert torch.equal(a.data, b.data) and a.data.shape[0] > 500


@needs_ray
def test_transport_tables_on_ray_equal_local(ray_ex, tmp_path):
    from prt_torch.scene import load_scene
    from prt_torch.transfer import RunOptions, TransportTable, precompute_transport

    mesh = load_scene("convex", size="small")
    a = precompute_transport(mesh, tmp_path / "a", views=1, res=2, run=RunOptions(chunk_size=700))
    b = precompute_transport(mesh, tmp_path / "b", views=1, res=2, run=RunOptions(chunk_size=700, executor=ray_ex))
    assert isinstance(b, TransportTable) and b.meta["complete"] and len(list(a)) == len(list(b)) > 1
    for (a0, a1, ta), (b0, b1, tb) in zip(a, b):
        assert (a0, a1) == (b0, b1) and torch.equal(ta, tb)


# ------------------------------------------------------------------------------ sweeps


@needs_ray
def test_sweep_on_ray_gives_the_local_figures(ray_ex, tmp_path):
    from prt_torch.harness.run import run_benchmark

    loc = run_benchmark(_cfg(tmp_path, "local"), progress=False, log=lambda s: None)
    rd = run_benchmark(_cfg(tmp_path, "ray"), progress=False, log=lambda s: None, executor=ray_ex)
    a, b = (json.loads((d / "results.json").read_text()) for d in (loc, rd))
    assert b["transfer"]["cache"]["cache"] == "miss"  # the transfer was precomputed on Ray too
    from prt_torch.transfer import Transfer

    assert torch.equal(Transfer.load(a["transfer"]["cache"]["path"]).data, Transfer.load(b["transfer"]["cache"]["path"]).data)
    ra = {r["setting_id"]: r for r in a["records"]}
    rb = {r["setting_id"]: r for r in b["records"]}
    assert list(ra) == list(rb) and len(ra) == 2  # same settings, same order
    from prt_torch import io

    for sid in ra:
        for k in SAME:
            assert ra[sid][k] == rb[sid][k], (sid, k)
        ea, eb = (io.load(d / "records" / f"{sid}.prt")[0] for d in (loc, rd))
        assert ea.keys() == eb.keys() and all(torch.equal(ea[n], eb[n]) for n in ea), sid  # the same encodings
    assert a["uncompressed"]["bytes_total"] == b["uncompressed"]["bytes_total"]
    assert b["executor"]["executor"] == "ray" and b["failures"] == [] and a["executor"]["executor"] == "local"
    assert "Executor: ray" in (rd / "report.md").read_text()


@needs_ray
def test_failed_setting_is_reported_while_the_others_finish(ray_ex, tmp_path, capsys):
    from prt_torch.cli import main

    codecs = [{"type": "pca", "vectors": [2, 12]}]  # 12 vectors >= D = 9: refused by the fit, every attempt
    _cfg(tmp_path, "fail", codecs=codecs)
    assert main(["bench", str(tmp_path / "fail.yaml"), "--executor", "ray", "--quiet"]) == 1  # joins the module's Ray
    err = capsys.readouterr().err
    rd = tmp_path / "fail" / "reports" / "raysweep"
    res = json.loads((rd / "results.json").read_text())
    assert [r["params"] for r in res["records"]] == [{"vectors": 2}]
    (f,) = res["failures"]
    assert f["setting"] == {"type": "pca", "vectors": 12} and f["attempts"] == 2 and f["error"].startswith("ValueError: vectors=12")
    assert "## Failed settings (1)" in (rd / "report.md").read_text() and f["setting_id"] in (rd / "report.md").read_text()
    assert f"setting {f['setting_id']} failed after 2 attempt(s): ValueError: vectors=12" in err
    assert ray.is_initialized()  # the command joined the running Ray and left it running


@needs_ray
def test_interrupted_sweep_resumes_without_recomputing(ray_ex, tmp_path):
    from prt_torch.harness.run import run_benchmark

    cfg = _cfg(tmp_path, "resume")

    def interrupt_after_first(line):  # Ctrl-C right after the first setting's record is written
        if line.startswith("[bench] ") and "B/vertex" in line:
            raise KeyboardInterrupt("simulated interruption")

    with pytest.raises(KeyboardInterrupt):
        run_benchmark(cfg, progress=False, log=interrupt_after_first, executor=ray_ex)
    rec_dir = tmp_path / "resume" / "reports" / "raysweep" / "records"
    (first,) = rec_dir.glob("*.json")
    mtime = first.stat().st_mtime_ns
    logs = []
    rd = run_benchmark(cfg, progress=False, log=logs.append, executor=ray_ex)
    assert first.stat().st_mtime_ns == mtime  # finished before the interruption: not recomputed
    assert any("resumed: 1 finished setting(s)" in s for s in logs)
    assert sum("B/vertex" in s for s in logs) == 1  # only the other one ran
    assert len(json.loads((rd / "results.json").read_text())["records"]) == 2


@needs_ray
def test_neural_codec_sweep_on_ray(ray_ex, tmp_path):
    """The learned codec (issue 43) as a Ray task: fitted in a worker, pickled back (codec and
    encoding), the same figures as the local run to float32 rounding (a worker's thread count may
    differ from this process's, and the fit's GEMMs round by it) and a file that loads and relights."""
    from prt_torch import codecs
    from prt_torch.harness.run import run_benchmark

    over = {"codecs": [{"type": "neural", "latent": 2, "features": 4, "width": 4, "depth": 1, "epochs": 10}]}
    loc = run_benchmark(_cfg(tmp_path, "nlocal", **over), progress=False, log=lambda s: None)
    rd = run_benchmark(_cfg(tmp_path, "nray", **over), progress=False, log=lambda s: None, executor=ray_ex)
    a, b = (json.loads((d / "results.json").read_text()) for d in (loc, rd))
    assert b["failures"] == [] and [r["setting_id"] for r in b["records"]] == [r["setting_id"] for r in a["records"]]
    ra, rb = a["records"][0], b["records"][0]
    assert ra["bytes_total"] == rb["bytes_total"] and ra["storage"]["runtime_bytes"] == rb["storage"]["runtime_bytes"]
    assert rb["relative_se"] == pytest.approx(ra["relative_se"], rel=1e-3)
    assert "Stored vs run-time size" in (loc / "report.md").read_text()  # the cached features' bytes, apart
    c, enc = codecs.load(rd / "records" / f"{rb['setting_id']}.prt")
    assert c.codec_name == "neural" and enc.tensors["z"].shape[1] == 2
    L = torch.randn(c.D_, 3)
    assert torch.allclose(c.relight(enc, L), c.decode(enc) @ L, rtol=1e-4, atol=1e-4)
