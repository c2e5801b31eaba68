"""Results larger than memory streamed to their files (issue 42 part 3): a precompute's assembled
rows in a file-backed buffer (``RunOptions.stream_result``, ``io.scratch_rows``), ``prt relight``'s
``[V, 3]`` written through ``np.lib.format.open_memmap`` by chunks (``io.streamed_npy``).

Each is checked three ways: the streamed file equals the in-memory result bit for bit (and a
``.npy`` equals the file ``np.save`` writes for the same array, byte for byte); an interrupted run
leaves nothing half-written; and under a data limit (``RLIMIT_DATA`` in a subprocess) that the
whole result breaks, the streamed run finishes (shared file mappings are not data)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
import torch

from prt_torch import io
from prt_torch.scene import builtin
from prt_torch.transfer import ChunkInterrupt, RunOptions, Transfer, get_kind

MRT = {"bands": 3, "M": 3, "bands_out": 3, "samples": 16, "shadows": "always", "brdf": {"type": "phong", "s": 4.0}}
DIFFUSE = {"bands": 3, "samples": 16, "shadows": "always"}


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Every test here in one torch thread (the memory-limited child processes already set one): the
    comparisons (streamed vs in-memory results, resumed vs uninterrupted) are within one thread count,
    and the short parallel regions of precomputes, fits and relights stall on OpenMP's spinning
    threads when other processes hold the cores (see test_stream_kinds)."""
    from prt_torch.executor import torch_threads

    with torch_threads(1):
        yield


# ------------------------------------------------------------------------------ precompute
@pytest.mark.parametrize("kind, params", [("diffuse", DIFFUSE), ("mrt", MRT)])
def test_streamed_result_equals_in_memory(tmp_path, kind, params, file_backed, saved_alike):
    """The rows assembled in a file equal the rows assembled in memory bit for bit, and so do
    the saved files' tensors; the buffer is a shared file mapping and leaves no file behind."""
    mesh = builtin("bumpy_sphere:642")
    ref = get_kind(kind).precompute(mesh, dict(params), run=RunOptions(chunk_size=100))
    got = get_kind(kind).precompute(mesh, dict(params), run=RunOptions(chunk_size=100, state_dir=tmp_path / "s",
                                                                         stream_result=True))
    assert file_backed(got.data) and not file_backed(ref.data)
    assert got.data.dtype == ref.data.dtype == torch.float32 and torch.equal(got.data, ref.data)
    saved_alike(got, ref, tmp_path)


def test_stream_result_needs_a_state_dir_and_threshold():
    with pytest.raises(ValueError, match="stream_result=True needs a state_dir"):
        RunOptions(stream_result=True)
    with pytest.raises(TypeError, match="stream_result"):
        RunOptions(stream_result="yes")
    from prt_torch.transfer.base import STREAM_RESULT_BYTES

    r = RunOptions(state_dir="x")
    assert not r.streams_result(STREAM_RESULT_BYTES) and r.streams_result(STREAM_RESULT_BYTES + 1)
    assert not RunOptions().streams_result(10 * STREAM_RESULT_BYTES)  # no state directory: in memory


def test_interrupted_streamed_run_leaves_nothing_half_written(tmp_path):
    """Stopped after two chunks: the state directory holds them, no scratch file and no output
    exist; resumed, the result equals the uninterrupted one."""
    mesh = builtin("bumpy_sphere:642")
    state = tmp_path / "o.prt.state"

    def stop(i, n):
        if i == 1:
            raise ChunkInterrupt("stop")

    with pytest.raises(ChunkInterrupt):
        get_kind("mrt").precompute(mesh, dict(MRT), run=RunOptions(chunk_size=100, state_dir=state, stream_result=True,
                                                                    callback=stop))
    assert [p.name for p in tmp_path.iterdir()] == ["o.prt.state"]
    assert len(list(state.glob("chunk_*.prt"))) == 2
    got = get_kind("mrt").precompute(mesh, dict(MRT), run=RunOptions(chunk_size=100, state_dir=state, resume=True,
                                                                      stream_result=True))
    ref = get_kind("mrt").precompute(mesh, dict(MRT), run=RunOptions(chunk_size=100))
    assert torch.equal(got.data, ref.data)


#: the prelude of the memory-limited child scripts: ``limit_data(extra)`` caps the process's data
#: segment (RLIMIT_DATA) at what it holds now plus ``extra`` bytes
_DATA_LIMIT = textwrap.dedent("""
    import resource


    def limit_data(extra):
        for line in open("/proc/self/status"):
            if line.startswith("VmData:"):
                held = int(line.split()[1]) * 1024
        resource.setrlimit(resource.RLIMIT_DATA, (held + extra, resource.RLIM_INFINITY))
""")


_LIMITED_PRECOMPUTE = _DATA_LIMIT + textwrap.dedent("""
    import json, resource, sys, torch
    torch.set_num_threads(1)
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions, get_kind
    out, mode, limit = sys.argv[1], sys.argv[2], int(sys.argv[3])
    p = {"bands": 4, "M": 8, "bands_out": 3, "samples": 8, "shadows": "never", "brdf": {"type": "phong", "s": 4.0}}
    mesh = builtin("bumpy_sphere:2562")
    get_kind("mrt").precompute(builtin("bumpy_sphere:642"), dict(p), run=RunOptions(chunk_size=256))  # warm-up
    big = builtin("bumpy_sphere:10242")
    limit_data(limit)
    try:
        run = RunOptions(chunk_size=256, max_memory=1 << 40, state_dir=out + ".state", stream_result=mode == "stream")
        tr = get_kind("mrt").precompute(big, dict(p), run=run)
        tr.save(out)
        print(json.dumps({"ok": True, "bytes": tr.data.numel() * 4}))
    except MemoryError:
        print(json.dumps({"ok": False, "error": "MemoryError"}))
    except RuntimeError as e:
        print(json.dumps({"ok": False, "error": str(e)[:200]}))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_DATA as Linux enforces it")
def test_precompute_result_larger_than_the_memory_limit(tmp_path):
    """An MRT result of 40 MiB (10242 vertices × 64×16 float32) under a data limit of 24 MiB above
    the warmed-up process: assembled in memory it fails, assembled in a file it is written."""
    limit = 24 * 2**20
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    out = {}
    for mode in ("memory", "stream"):
        r = subprocess.run([sys.executable, "-c", _LIMITED_PRECOMPUTE, str(tmp_path / f"{mode}.prt"), mode, str(limit)],
                           capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        out[mode] = json.loads(r.stdout.strip().splitlines()[-1])
    assert not out["memory"]["ok"], out  # the limit bites: the whole result does not fit
    assert out["stream"]["ok"] and out["stream"]["bytes"] > limit, out
    d = io.describe(tmp_path / "stream.prt")
    assert d["tensors"]["data"]["shape"] == [10242, 64, 16]


# ------------------------------------------------------------------------------ io helpers
def test_streamed_npy_is_np_save_and_atomic(tmp_path):
    """Filled by chunks, the file is byte for byte what ``np.save`` writes; an exception in the
    block leaves no file (and an existing one untouched)."""
    x = np.random.default_rng(0).standard_normal((1001, 3)).astype(np.float32)
    with io.streamed_npy(tmp_path / "a.npy", x.shape) as a:
        for i in range(0, 1001, 97):
            a[i:i + 97] = x[i:i + 97]
    np.save(tmp_path / "b.npy", x)
    assert (tmp_path / "a.npy").read_bytes() == (tmp_path / "b.npy").read_bytes()
    with pytest.raises(KeyboardInterrupt):
        with io.streamed_npy(tmp_path / "b.npy", x.shape, overwrite=True) as a:
            a[:10] = 0
            raise KeyboardInterrupt
    assert (tmp_path / "b.npy").read_bytes() == (tmp_path / "a.npy").read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npy", "b.npy"]
    with pytest.raises(FileExistsError):
        with io.streamed_npy(tmp_path / "a.npy", x.shape):
            pass


def test_scratch_rows_zero_unlinked_and_refused_where_it_cannot_be(tmp_path, file_backed):
    t = io.scratch_rows(tmp_path, (100, 4), torch.float64)
    assert t.dtype == torch.float64 and t.shape == (100, 4) and not t.any() and file_backed(t)
    assert list(tmp_path.iterdir()) == []
    (tmp_path / "f").write_text("")
    with pytest.raises(ValueError, match=r"cannot create .* scratch rows in .*f"):
        io.scratch_rows(tmp_path / "f", (10, 4))


# ------------------------------------------------------------------------------ prt relight
def _mrt_file(tmp_path, V="bumpy_sphere:642", M=3):
    p = dict(MRT, M=M)
    tr = get_kind("mrt").precompute(builtin(V), p, run=RunOptions(chunk_size=4096))
    path = tmp_path / "m.prt"
    tr.save(path)
    return path, tr


@pytest.mark.parametrize("kind", ["diffuse", "mrt"])
def test_relight_streamed_npy_equals_in_memory(tmp_path, kind, monkeypatch):
    """``prt relight`` of a mapped transfer, by chunks straight into the .npy: the file is byte for
    byte ``np.save`` of the same relight of the transfer loaded whole (in memory); and both agree
    with the float64 relighting of ``prt_torch.relight`` (diffuse: ``diffuse_transfer``; MRT: the
    four-tap sum ``relight.mrt``) within float32 rounding."""
    from prt_torch import relight
    from prt_torch.cli import main as cli_main
    from prt_torch.cli import relight as rl
    from prt_torch.lighting import load_light
    from prt_torch.render import Camera

    monkeypatch.setattr(rl, "CHUNK_VERTICES", 100)  # several chunks on a small mesh
    if kind == "mrt":
        path, tr = _mrt_file(tmp_path)
    else:
        tr = get_kind("diffuse").precompute(builtin("bumpy_sphere:642"), dict(DIFFUSE))
        path = tmp_path / "d.prt"
        tr.save(path)
    out = tmp_path / "r.npy"
    assert cli_main(["relight", str(path), "--light", "sky", "-o", str(out)]) == 0
    whole = Transfer.load(path)  # in memory
    ref, _ = rl.radiance(whole, "sky", rows=100)
    np.save(tmp_path / "ref.npy", ref.numpy())
    assert out.read_bytes() == (tmp_path / "ref.npy").read_bytes()
    n2 = whole.data.shape[-1]
    L = load_light("sky", bands=int(round(n2 ** 0.5))).to(torch.float64)
    if kind == "diffuse":
        exact = relight.diffuse_transfer(whole, L)
    else:
        eye = torch.as_tensor(Camera.fit(whole.mesh).eye, dtype=torch.float64)
        v = relight.local_view(whole.mesh.frames().double(), whole.mesh.vertices.double(), eye=eye)
        exact = relight.mrt(whole.data.double(), L.expand(3, -1), v)
    np.testing.assert_allclose(np.load(out), exact.expand(-1, 3).numpy(), rtol=1e-5, atol=1e-5 * float(exact.abs().max()))


def test_relight_interrupted_leaves_nothing(tmp_path, monkeypatch):
    """An interruption between chunks (Ctrl-C) removes the partial file; an existing output is
    left as it was."""
    from prt_torch.cli import relight as rl
    from prt_torch.render import PRTScene

    path, _ = _mrt_file(tmp_path)
    out = tmp_path / "r.npy"
    out.write_bytes(b"old")
    monkeypatch.setattr(rl, "CHUNK_VERTICES", 100)
    calls = {"n": 0}
    real = PRTScene.cpu_radiance

    def stop(self, *a, **k):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(self, *a, **k)

    monkeypatch.setattr(PRTScene, "cpu_radiance", stop)
    from prt_torch.cli import main as cli_main

    assert cli_main(["relight", str(path), "--light", "sky", "-o", str(out), "--overwrite"]) == 130
    assert out.read_bytes() == b"old" and sorted(p.name for p in tmp_path.iterdir()) == ["m.prt", "r.npy"]


_LIMITED_RELIGHT = _DATA_LIMIT + textwrap.dedent("""
    import json, resource, sys, torch
    torch.set_num_threads(1)
    from prt_torch.cli import relight as rl
    from prt_torch.transfer import Transfer
    path, out, mode, limit = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    from prt_torch import io
    rl.radiance(Transfer.load(path, mmap=True), "sky", rows=4096)  # warm-up: imports, light, kernels
    limit_data(limit)
    try:
        tr = Transfer.load(path, mmap=mode == "stream")
        with io.streamed_npy(out, (tr.num_vertices, 3)) as arr:
            rl.radiance(tr, "sky", out=torch.from_numpy(arr), rows=4096)
        print(json.dumps({"ok": True}))
    except ValueError as e:  # io.load: the file's tensors cannot be mapped for copying
        print(json.dumps({"ok": False, "error": str(e)[:300]}))
    except MemoryError:
        print(json.dumps({"ok": False, "error": "MemoryError"}))
    except RuntimeError as e:
        print(json.dumps({"ok": False, "error": str(e)[:200]}))
""")


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="RLIMIT_DATA as Linux enforces it")
def test_relight_transfer_larger_than_the_memory_limit(tmp_path):
    """An MRT transfer of 40 MiB (10242 × 64×16 float32) under a data limit of 24 MiB above the
    warmed-up process: loading it whole fails; mapped and relit by chunks into the .npy it works,
    and the file equals the relight of the transfer loaded whole (without a limit)."""
    from prt_torch.cli import relight as rl

    tr = get_kind("mrt").precompute(builtin("bumpy_sphere:10242"), dict(MRT, M=8, bands=4, samples=8, shadows="never"),
                                    run=RunOptions(chunk_size=4096))
    path = tmp_path / "m.prt"
    tr.save(path)
    limit = 24 * 2**20
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    res = {}
    for mode in ("load", "stream"):
        r = subprocess.run([sys.executable, "-c", _LIMITED_RELIGHT, str(path), str(tmp_path / f"{mode}.npy"), mode, str(limit)],
                           capture_output=True, text=True, env=env, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        res[mode] = json.loads(r.stdout.strip().splitlines()[-1])
    assert not res["load"]["ok"] and res["stream"]["ok"], res
    assert not (tmp_path / "load.npy").exists()
    ref, _ = rl.radiance(Transfer.load(path), "sky", rows=4096)
    assert np.array_equal(np.load(tmp_path / "stream.npy"), ref.numpy())


def test_relight_dry_run_arithmetic_and_refusal(tmp_path, capsys):
    """``--dry-run`` writes nothing and states each stage from the headers: the input is the mesh
    arrays plus PRTScene's frames, points and albedo (108 B per vertex), the data mapped (not
    counted), the output streamed (0); the peak is their sum × ALLOCATOR_SLACK; the time is an
    estimate. A budget below the peak is refused in one line naming the sizes (status 2)."""
    from prt_torch import io as pio
    from prt_torch.cli import main as cli_main
    from prt_torch.cli import relight as rl
    from prt_torch.transfer.estimate import ALLOCATOR_SLACK

    path, tr = _mrt_file(tmp_path)
    out = tmp_path / "r.npy"
    assert cli_main(["relight", str(path), "--light", "sky", "-o", str(out), "--dry-run"]) == 0
    err = capsys.readouterr().err
    assert not out.exists() and "nothing written" in err and "(an estimate; calibration" in err
    V = tr.num_vertices
    mesh = sum(t.numel() * t.element_size() for t in tr.mesh.to_tensors("").values())
    import argparse

    pl = rl.plan(argparse.Namespace(transfer=str(path), source=None, output=str(out), memory_limit=None))
    st = {s["stage"]: s["bytes"] for s in pl["stages"]}
    assert st["input"] == mesh + 108 * V and st["output"] == 0
    assert st["relight"] == V * (2 * tr.data[0].numel() * 4 + 212)  # one chunk (V < CHUNK_VERTICES)
    assert pl["peak"] == int(ALLOCATOR_SLACK * sum(st.values())) and pl["streamed"]
    assert f"peak    {pio.format_bytes(pl['peak']):>10s}" in err
    assert cli_main(["relight", str(path), "--light", "sky", "-o", str(out), "--memory-limit", "0.0001"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs about" in err[0] and "input" in err[0] and "budget is 105 KiB" in err[0], err
    assert not out.exists()


def test_estimate_does_not_count_a_streamed_result(tmp_path):
    """``transfer.estimate``: with the result assembled in a file the rays stage holds no rows and
    the result stage one chunk's work (said in its note); in memory the rows count (float32 × V for MRT). The
    difference of the two rays stages is the result's bytes × ALLOCATOR_SLACK exactly."""
    from prt_torch.transfer.estimate import ALLOCATOR_SLACK, estimate

    mesh = builtin("bumpy_sphere:642")
    k = get_kind("mrt")
    st = {so: estimate(k, mesh, dict(MRT), RunOptions(state_dir=tmp_path / "s", stream_result=so), probe=False)
          for so in (True, False)}
    rays = {so: e.stages[1]["bytes"] for so, e in st.items()}
    result = mesh.num_vertices * 9 * 9 * 4
    assert abs((rays[False] - rays[True]) - ALLOCATOR_SLACK * result) <= 1
    assert "assembled in a file" in st[True].stages[2]["note"] and "assembled in a file" not in st[False].stages[2]["note"]
    assert not (tmp_path / "s").exists()


def test_bench_dry_run_time_line(tmp_path, capsys, monkeypatch):
    """``prt bench --dry-run`` prints a time line per config: the precompute's probe and each
    affine codec setting's calibrated fit (estimates); a codec it cannot calibrate says so;
    ``--no-time`` leaves the line out; nothing is written."""
    from prt_torch.cli import main as cli_main

    monkeypatch.chdir(tmp_path)
    args = ["bench", "diffuse", "transfer.bands=3", "transfer.samples=16", "transfer.bounces=0", "target.psnr=null",
            "codecs=[{type: pca, vectors: 2}, {type: cpca, clusters: 4, vectors: 2}, {type: neural}]", "--dry-run"]
    assert cli_main(args) == 0
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("# time per stage"))
    assert "precompute ~" in line and "pca vectors=2 ~" in line and "cpca clusters=4,vectors=2 ~" in line
    assert "neural not estimated" in line and line.endswith("estimates")
    assert cli_main(args + ["--no-time"]) == 0
    assert "# time per stage" not in capsys.readouterr().out
    assert not (tmp_path / "reports").exists() and not (tmp_path / "cache").exists()


def test_compress_dry_run_time_and_refusal(tmp_path, capsys):
    """``prt compress --dry-run`` states the fit's time as an estimate from a calibration fit
    (here of every row: the whole signal is smaller than the calibration sample, so the factor is
    1), and a budget below ``fit_memory``'s peak is refused before the signal is read: one line
    naming every count and suggesting --stream; nothing is written."""
    from prt_torch.cli import main as cli_main
    from prt_torch.codecs.chunks import fit_memory

    tr = get_kind("diffuse").precompute(builtin("bumpy_sphere:642"), dict(DIFFUSE))
    src, out = tmp_path / "d.prt", tmp_path / "c.prt"
    tr.save(src)
    base = ["compress", str(src), "--clusters", "4", "--vectors", "2", "-o", str(out)]
    assert cli_main(base + ["--dry-run"]) == 0
    text = capsys.readouterr().out
    assert f"calibration: {tr.num_vertices} rows fitted and encoded in" in text and " s, × 1)" in text
    assert "time ~" in text and "(an estimate;" in text and not out.exists()
    # the dry run refuses the outputs the run refuses (as prt precompute's and prt relight's do): the same one line
    out.write_bytes(b"kept")
    for argv, said in ((base, "exists; pass --overwrite"), (base[:-1] + [str(src)], "is the input TRANSFER")):
        assert cli_main(argv) == 2  # an existing output; the input as the output
        run_err = capsys.readouterr().err
        assert cli_main(argv + ["--dry-run"]) == 2
        assert capsys.readouterr().err == run_err and len(run_err.strip().splitlines()) == 1 and said in run_err, run_err
    assert cli_main(base + ["--dry-run", "--overwrite"]) == 0 and out.read_bytes() == b"kept"  # a dry run writes nothing
    capsys.readouterr()
    out.unlink()
    m = fit_memory(tr.num_vertices, 9, 4, 2)
    assert cli_main(base + ["--memory-limit", str(0.5 * m["peak"] / 2**30)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"needs about {io.format_bytes(m['peak'])}" in err[0] and "--stream" in err[0], err
    assert not out.exists()
