"""Every transfer kind streams its result (issue 42 part 3): diffuse with hit-point bounces, a
folded albedo or a subsurface term, the subsurface kind, glossy's subsurface term and the wavelet
kind assemble their rows in files (``RunOptions.result_rows``) when the result is larger than
the streaming threshold — lowered here with ``PRT_STREAM_RESULT_BYTES`` — and the file they
write equals the in-memory run's bit for bit; what a pass must hold whole (the subsurface
hierarchy, the sparse ``bounce_points``) is named by the dry run and refused up front when it
does not fit; an interrupted run (a ``ChunkInterrupt`` or ``kill -9`` after a few chunks) resumes
to the uninterrupted result."""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import warnings

import pytest
import torch

from prt_torch import io
from prt_torch.scene import builtin
from prt_torch.transfer import ChunkInterrupt, RunOptions, get_kind
from prt_torch.transfer.base import STREAM_RESULT_BYTES, stream_result_bytes

SSS = {"material": "skin1", "scale": 10.0, "spacing": 4.0}
GREY = "bumpy_sphere:642"
CASES = {
    "diffuse_bounces": ("diffuse", {"bands": 3, "samples": 16, "shadows": "always", "bounces": 2, "bounce_tol": 0.0}, False),
    "diffuse_bounce_colour": ("diffuse", {"bands": 3, "samples": 16, "shadows": "always", "bounces": 1}, True),
    "diffuse_folded": ("diffuse", {"bands": 3, "samples": 16, "shadows": "always", "fold_albedo": True}, True),
    "diffuse_subsurface": ("diffuse", {"bands": 2, "samples": 16, "shadows": "always", "bounces": 1, "subsurface": SSS}, False),
    "subsurface": ("subsurface", {"bands": 2, "samples": 16, "shadows": "always", **SSS}, False),
    "glossy_subsurface": ("glossy", {"bands": 2, "samples": 16, "shadows": "always", "brdf": {"type": "phong", "s": 4.0},
                                     "subsurface": SSS}, False),
    "wavelet": ("wavelet", {"res": 4, "terms": 16, "shadows": "always"}, False),
    "wavelet_bounce_colour": ("wavelet", {"res": 4, "terms": 16, "bounces": 1, "hit_samples": 4}, True),
}


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Every test here in one torch thread (the killed CLI runs already set ``OMP_NUM_THREADS=1``):
    the comparisons are within one thread count (streamed vs in memory, resumed vs uninterrupted),
    and the precomputes' many small parallel regions stall on OpenMP's spinning threads when other
    processes hold the cores — the module took 79 s at load 11-13 for its killed-run tests with two
    spinning threads, 19 s with ``OMP_WAIT_POLICY=PASSIVE``."""
    from prt_torch.executor import torch_threads

    with torch_threads(1):
        yield


def _mesh(colour: bool):
    m = builtin(GREY)
    return m.with_albedo([0.8, 0.5, 0.3]) if colour else m




def _run(kind, mesh, params, **run):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the subsurface term's scale/holes notes
        return get_kind(kind).precompute(mesh, dict(params), run=RunOptions(chunk_size=100, **run))


def _same(a, b) -> bool:
    return (a.data.dtype == b.data.dtype and torch.equal(a.data, b.data) and a.aux.keys() == b.aux.keys()
            and all(torch.equal(a.aux[k], b.aux[k]) for k in a.aux))


@pytest.fixture(scope="module")
def in_memory():
    """Each case's uninterrupted in-memory result (no state directory), computed once."""
    return {name: _run(kind, _mesh(colour), params) for name, (kind, params, colour) in CASES.items()}


# ------------------------------------------------------------------------------ streamed == in memory
@pytest.mark.parametrize("name", list(CASES))
def test_streamed_result_equals_in_memory(tmp_path, monkeypatch, name, in_memory, file_backed, saved_alike):
    """With the threshold at 0 bytes (``PRT_STREAM_RESULT_BYTES``) and a state directory, the rows
    are a shared file mapping; their values, the saved file's tensors and the bounce decision equal
    the in-memory run's bit for bit; nothing is left beside the output."""
    kind, params, colour = CASES[name]
    monkeypatch.setenv("PRT_STREAM_RESULT_BYTES", "0")
    ref = in_memory[name]
    got = _run(kind, _mesh(colour), params, state_dir=tmp_path / "o.prt.state")
    assert file_backed(got.data) and not file_backed(ref.data)
    assert all(file_backed(t) for t in got.aux.values())
    assert _same(got, ref)
    for k in ("bounces_used", "bounce_energy_fraction", "albedo_folded", "channels", "nonzero_per_vertex"):
        assert got.meta.get(k) == ref.meta.get(k), k
    saved_alike(got, ref, tmp_path)


def test_bounce_decision_by_blocks_is_the_whole_tensors_norm():
    """The block-wise bounce norms (sums of squares over blocks of rows) give the fractions
    ‖t̃^b‖ / ‖Σ_{≤b} t̃‖ of the whole tensors (torch.linalg.norm) and the same stop."""
    from prt_torch.transfer.diffuse import _bounce_decision

    g = torch.Generator().manual_seed(3)
    V, n2 = 1000, 9
    T0 = torch.rand(V, n2, generator=g, dtype=torch.float64)
    TB = 0.3 ** torch.arange(1, 5, dtype=torch.float64)[None, :, None, None] * torch.rand(V, 4, 1, n2, generator=g,
                                                                                          dtype=torch.float64)
    mesh = builtin("bumpy_sphere:300")
    meta: dict = {}
    C, used = _bounce_decision(T0, TB, mesh, 4, 0.05, meta, rows=64)
    total = T0.clone()
    want = []
    for b in range(4):
        total = total + TB[:, b, 0]
        want.append(float(torch.linalg.norm(TB[:, b, 0]) / torch.linalg.norm(total)))
    stop = next(b + 1 for b, f in enumerate(want) if f < 0.05)
    assert C == 1 and used == stop and meta["bounces_used"] == stop
    assert meta["bounce_energy_fraction"] == pytest.approx(want[:stop], rel=1e-12)


def test_threshold_variable(monkeypatch):
    """``PRT_STREAM_RESULT_BYTES`` sets the threshold; unset, 256 MiB; a bad value is refused naming it."""
    monkeypatch.delenv("PRT_STREAM_RESULT_BYTES", raising=False)
    assert stream_result_bytes() == STREAM_RESULT_BYTES == 256 * 2**20
    r = RunOptions(state_dir="x")
    assert not r.streams_result(1000)
    monkeypatch.setenv("PRT_STREAM_RESULT_BYTES", "999")
    assert not r.streams_result(999) and r.streams_result(1000) and not RunOptions().streams_result(1000)
    for bad in ("-1", "1e6", "lots"):
        monkeypatch.setenv("PRT_STREAM_RESULT_BYTES", bad)
        with pytest.raises(ValueError, match=rf"PRT_STREAM_RESULT_BYTES='{bad}'; accepted: a number of bytes"):
            r.streams_result(1)


# ------------------------------------------------------------------------------ what the estimate counts
@pytest.mark.parametrize("name", ["diffuse_bounces", "diffuse_bounce_colour", "subsurface", "wavelet"])
def test_plan_counts_the_buffers_the_run_streams(tmp_path, monkeypatch, name):
    """The dry run's memory plan (``estimate.memory_plan``) says the result streams exactly when the
    run assembles it in files, and its bytes are those files': for diffuse every buffer of the
    assembly (t⁰, bounce terms, stored rows: ``held_pv`` per vertex), for the wavelet and subsurface
    kinds the stored rows (``out_pv``)."""
    from prt_torch.transfer.estimate import memory_plan

    kind, params, colour = CASES[name]
    mesh = _mesh(colour)
    made = []
    real = io.scratch_rows
    monkeypatch.setattr(io, "scratch_rows", lambda d, shape, dtype=torch.float32, name="rows": (
        made.append((name, torch.Size(shape).numel() * torch.tensor([], dtype=dtype).element_size())), real(d, shape, dtype, name))[1])
    k = get_kind(kind)
    kw, _ = k.resolve(dict(params))
    V = mesh.num_vertices
    run = RunOptions(state_dir=tmp_path / "s")
    monkeypatch.setenv("PRT_STREAM_RESULT_BYTES", "0")
    plan = memory_plan(k, kw, mesh, run)
    assert plan.streamed and plan.rows < plan.held_pv * V
    _run(kind, mesh, params, state_dir=tmp_path / "s")
    if kind == "diffuse":
        assert sum(n for _, n in made) == plan.held_pv * V, made
    elif kind == "subsurface":
        assert [n for nm, n in made if "subsurface" in nm] == [plan.out_pv * V], made
    else:
        assert sum(n for _, n in made) == pytest.approx(plan.out_pv * V, rel=0.02), made
    made.clear()
    monkeypatch.setenv("PRT_STREAM_RESULT_BYTES", str(10 * plan.held_pv * V))
    assert not memory_plan(k, kw, mesh, run).streamed
    _run(kind, mesh, params, state_dir=tmp_path / "s")
    assert made == []


def test_dry_run_names_what_is_held_whole_and_refuses_up_front(tmp_path, capsys):
    """The subsurface hierarchy and the sparse bounce points are held whole: the dry run says so
    with their size, and a budget below the peak is refused in one line naming them (status 2),
    before any chunk (no state directory, no output)."""
    from prt_torch.cli import main as cli_main

    out = tmp_path / "s.prt"
    base = ["precompute", GREY, "--kind", "subsurface", "--material", "skin1", "--scale", "10", "--spacing", "4",
            "--bands", "2", "--samples", "16", "-o", str(out), "--no-progress"]
    assert cli_main(base + ["--dry-run"]) == 0
    err = capsys.readouterr().err
    assert "subsurface hierarchy over" in err and "held whole" in err and "scatter: " in err, err
    assert cli_main(base + ["--memory-limit", "0.001"]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert "held whole" in lines[-1] and "budget is 1.02 MiB" in lines[-1] and "Traceback" not in "\n".join(lines)
    assert not out.exists() and not (tmp_path / "s.prt.state").exists()
    d = ["precompute", GREY, "--bands", "3", "--samples", "16", "--bounces", "1", "--bounce-points", "vertices",
         "-o", str(out), "--no-progress", "--dry-run"]
    assert cli_main(d) == 0
    assert "bounce_points='vertices': its sparse bounces read every row" in capsys.readouterr().err


# ------------------------------------------------------------------------------ resume
#: (case, chunks before the stop): 7 chunks of 100 per pass on 642 vertices, so call 9 is in the second pass
#: (the scatter of the subsurface kind and of diffuse's term, glossy's irradiance pass) and 16 in glossy's scatter
RESUME = [("diffuse_bounces", 1), ("diffuse_bounce_colour", 1), ("wavelet", 1), ("subsurface", 1), ("subsurface", 9),
          ("diffuse_subsurface", 9), ("glossy_subsurface", 16)]


@pytest.mark.parametrize("name, stop_at", RESUME)
def test_interrupted_streamed_run_resumes_to_the_in_memory_result(tmp_path, monkeypatch, name, stop_at, in_memory, file_backed):
    """Stopped after ``stop_at`` + 1 chunks in all passes (RESUME), the result streamed: nothing but
    the state directory is left, holding every finished chunk (an earlier pass's are kept until the
    last pass ends); resumed, the result equals the uninterrupted in-memory run, and the state goes."""
    kind, params, colour = CASES[name]
    monkeypatch.setenv("PRT_STREAM_RESULT_BYTES", "0")
    mesh = _mesh(colour)
    state = tmp_path / "o.prt.state"
    calls = []

    def stop(i, n):
        calls.append(i)
        if len(calls) == stop_at + 1:
            raise ChunkInterrupt("stop")

    with pytest.raises(ChunkInterrupt):
        _run(kind, mesh, params, state_dir=state, callback=stop)
    assert [p.name for p in tmp_path.iterdir()] == ["o.prt.state"]
    assert len(list(state.rglob("chunk_*.prt"))) == stop_at + 1
    got = _run(kind, mesh, params, state_dir=state, resume=True)
    assert file_backed(got.data) and _same(got, in_memory[name])
    assert not state.exists()


_KILLED = """
import sys
from prt_torch.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="SIGKILL and /proc as on Linux")
@pytest.mark.parametrize("kind, mesh, args, watch", [
    ("diffuse", "bumpy_sphere:2562", ["--bands", "3", "--samples", "64", "--bounces", "1", "--chunk", "48"], "chunk_*.prt"),
    ("subsurface", GREY, ["--bands", "2", "--samples", "16", "--material", "skin1", "--scale", "10", "--spacing", "4",
                          "--chunk", "48"], "scatter/chunk_*.prt"),
    ("wavelet", "bumpy_sphere:2562", ["--res", "8", "--terms", "32", "--chunk", "48"], "chunk_*.prt"),
])
def test_killed_cli_run_resumes(tmp_path, kind, mesh, args, watch):
    """``prt precompute`` killed with SIGKILL after a few chunks (the result streamed: the threshold
    at 0 bytes), then ``--resume``: the file equals the uninterrupted in-memory run's; the killed
    run left no output and no scratch file (its mappings were of unlinked files)."""
    from prt_torch.cli import main as cli_main

    out = tmp_path / "t.prt"
    state = tmp_path / "t.prt.state"
    cmd = ["precompute", mesh, "--kind", kind, *args, "-o", str(out), "--no-progress", "--workers", "1"]
    env = {**os.environ, "PRT_STREAM_RESULT_BYTES": "0", "OMP_NUM_THREADS": "1"}
    p = subprocess.Popen([sys.executable, "-c", _KILLED, *cmd], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        t0 = time.monotonic()
        while len(list(state.glob(watch))) < 3 and p.poll() is None and time.monotonic() - t0 < 300:
            time.sleep(0.005)
        p.send_signal(signal.SIGKILL)
        p.wait(60)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == -signal.SIGKILL, p.stderr.read().decode()[-2000:]
    assert not out.exists() and not list(tmp_path.rglob("*.scratch.npy")) and len(list(state.glob(watch))) >= 3
    old = os.environ.get("PRT_STREAM_RESULT_BYTES")
    os.environ["PRT_STREAM_RESULT_BYTES"] = "0"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            assert cli_main(cmd + ["--resume"]) == 0
    finally:
        if old is None:
            del os.environ["PRT_STREAM_RESULT_BYTES"]
        else:
            os.environ["PRT_STREAM_RESULT_BYTES"] = old
    from prt_torch.transfer import Transfer

    got = Transfer.load(out)
    params = {"diffuse": {"bands": 3, "samples": 64, "bounces": 1},
              "subsurface": {"bands": 2, "samples": 16, **SSS},
              "wavelet": {"res": 8, "terms": 32}}[kind]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ref = get_kind(kind).precompute(builtin(mesh), params, run=RunOptions(chunk_size=int(args[-1]), workers=1))
    assert _same(got, ref)
    assert not state.exists()


@pytest.mark.parametrize("kind, params", [
    ("wavelet", {"res": 8, "terms": 16, "shadows": "always"}),
    ("wavelet", {"res": 4, "terms": 16, "supersample": 2, "shadows": "always"}),
    ("transport", {"views": 1, "res": 4, "shadows": True}),
    ("subsurface", {"bands": 2, "samples": 16, "shadows": "always", "material": "skin1", "scale": 10.0, "spacing": 4.0}),
])
def test_probe_chunk_is_the_runs_own(tmp_path, kind, params):
    """The dry run's probe sizes its chunks from the chunk the kind itself uses (its run meta):
    wavelet and transport probed 1024-vertex chunks whatever their own before; subsurface was
    sized with the diffuse kind's 1024 samples (its default is 256)."""
    from prt_torch.transfer.estimate import real_chunk

    mesh = builtin(GREY)
    k = get_kind(kind)
    kw, _ = k.resolve(dict(params))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        if k.output == "directory":
            tr = k.precompute(mesh, dict(params), run=RunOptions(), out=tmp_path / "t")
        else:
            tr = k.precompute(mesh, dict(params), run=RunOptions())
    assert real_chunk(kind, kw, None) == tr.meta["chunk_size"]
    assert real_chunk(kind, kw, 77) == 77
