"""The dry run's time probe (``transfer.estimate``, issue 42 part 3): its chunk choice, its
arithmetic and its message. No timed assertions: the estimate against real runs is
``benchmarks/bench_precompute_estimate.py`` (``reports/benchmarks/precompute_estimate.md``)."""
from __future__ import annotations

import pytest

from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions, get_kind
from prt_torch.transfer.estimate import (PROBE_CHUNKS, PROBE_MIN_CHUNK, PROBE_SHARE, estimate, probe_chunk, probe_seconds,
                                         real_chunk)

MRT = {"bands": 2, "M": 2, "samples": 16, "shadows": "always", "brdf": {"type": "phong", "s": 12.0}}
DIFFUSE = {"bands": 2, "samples": 16, "shadows": "always"}


def test_probe_chunk_rule():
    assert (PROBE_CHUNKS, PROBE_MIN_CHUNK, PROBE_SHARE) == (3, 1024, 16)
    assert probe_chunk(100_002, 8192) == 100_002 // 16 == 6250  # at most V / 16 per chunk
    assert probe_chunk(998_562, 8192) == 8192  # a large mesh: the real chunk
    assert probe_chunk(998_562, 16384) == 16384
    assert probe_chunk(10_242, 8192) == 8192  # at most three real chunks: the probe is the whole run
    assert probe_chunk(10_242, 16384) == 16384
    assert probe_chunk(40_000, 1000) == 1000  # never above the real chunk
    assert probe_chunk(30_000, 8192) == 30_000 // 16 and probe_chunk(15_000, 4096) == PROBE_MIN_CHUNK  # floor 1024
    assert probe_chunk(10**6, 8192, k=128) == 128  # as asked


def test_probe_seconds_arithmetic():
    # set-up = first chunk's end less one (mean) chunk; V / k chunks, the partial one in proportion
    s, setup, per = probe_seconds(1000, 300, 1.5, [0.2, 0.4])
    assert per == pytest.approx(0.3) and setup == pytest.approx(1.2) and s == pytest.approx(1.2 + 0.3 * 1000 / 300)
    s, setup, per = probe_seconds(500, 100, 0.1, [0.3])  # a first chunk faster than the mean: no negative set-up
    assert setup == 0.0 and s == pytest.approx(1.5)
    with pytest.raises(ValueError, match=r"probe_seconds: timed is empty; accepted: .*at least one chunk"):
        probe_seconds(10, 1, 1.0, [])


def test_a_pass_of_exactly_probe_chunks_is_timed_whole(monkeypatch):
    """A pass of exactly PROBE_CHUNKS chunks whose last is a sliver (2154 vertices in chunks of 1024: 1024, 1024, 106)
    is timed as what it took, not as the mean of chunks 2-3 scaled to V / k, which counted the 106-vertex chunk as a
    whole one (0.72-0.97 of the real run for glossy with a bounce on scan_blob and the Cornell box). A fake clock
    (no timing): chunks of 40, 40 and 4 ms take 84 ms (the scaled mean said 0.018 + 0.022 · 2154 / 1024 = 64 ms); a
    pass of six 30 ms chunks is cut after three and scaled: 6 × 30 ms."""
    from prt_torch.transfer import estimate as E

    clock = [0.0]
    monkeypatch.setattr(E.time, "perf_counter", lambda: clock[0])
    ran = []

    def go(cb, sizes):
        for i, dt in enumerate(sizes):
            clock[0] += dt
            ran.append(i)
            cb(i, len(sizes))

    sec, info = E._time_pass(lambda cb: go(cb, [0.04, 0.04, 0.004]), 2154, 1024)
    assert E.PROBE_CHUNKS == 3 and info == {"whole": True} and sec == pytest.approx(0.084)
    ran.clear()
    sec, info = E._time_pass(lambda cb: go(cb, [0.03] * 6), 6 * 1024, 1024)
    assert ran == [0, 1, 2] and not info["whole"] and info["timed"] == 2 and sec == pytest.approx(0.18)


@pytest.mark.parametrize("kind,params", [("mrt", MRT), ("diffuse", DIFFUSE)])
def test_real_chunk_is_the_runs_own(kind, params):
    """The probe sizes its chunks from the chunk the kind itself chooses (its run meta)."""
    mesh = builtin("bumpy_sphere:642")
    k = get_kind(kind)
    kw, _ = k.resolve(dict(params))
    tr = k.precompute(mesh, dict(params), run=RunOptions(progress=False))
    assert real_chunk(kind, kw, None) == tr.meta["chunk_size"]
    assert real_chunk(kind, kw, 77) == 77


def test_probe_note_and_state(tmp_path):
    """A probe of chunks: its note states set-up, per-chunk time, the chunk, the mean of two, the
    chunks counted and the load; a run within three chunks is measured whole; nothing is left in
    the run's state directory."""
    mesh = builtin("bumpy_sphere:3000")
    V = mesh.num_vertices
    e = estimate(get_kind("mrt"), mesh, dict(MRT), RunOptions(state_dir=tmp_path / "s"), probe=True, probe_vertices=256)
    note = e.stages[1]["note"]
    assert f"per chunk of 256 vertices (mean of {PROBE_CHUNKS - 1}) × {V / 256:.1f} chunks" in note and "load " in note
    assert e.stages[1]["seconds"] > 0 and not (tmp_path / "s").exists()
    whole = estimate(get_kind("mrt"), mesh, dict(MRT), RunOptions(), probe=True)  # V <= 3 real chunks
    assert "the whole run (it finished within the probe)" in whole.stages[1]["note"]
    assert whole.stages[1]["seconds"] > 0


@pytest.mark.parametrize("stream", [True, False])
def test_probe_does_the_runs_io(monkeypatch, tmp_path, stream):
    """The probe saves each chunk to a (temporary) state directory as the real run does, and
    fills file-backed rows exactly when the real run would (``RunOptions.streams_result``)."""
    from prt_torch import io

    saved, scratch = [], []
    save, rows = io.save, io.scratch_rows
    monkeypatch.setattr(io, "save", lambda p, *a, **k: (saved.append(str(p)), save(p, *a, **k))[1])
    monkeypatch.setattr(io, "scratch_rows", lambda *a, **k: (scratch.append(str(a[0])), rows(*a, **k))[1])
    mesh = builtin("bumpy_sphere:3000")
    estimate(get_kind("mrt"), mesh, dict(MRT), RunOptions(state_dir=tmp_path / "s", stream_result=stream), probe=True,
             probe_vertices=256)
    chunks = [p for p in saved if "chunk_" in p]
    assert len(chunks) == PROBE_CHUNKS and all("prt_probe_" in p for p in chunks)
    assert len(scratch) == int(stream) and all("prt_probe_" in p for p in scratch)
    assert not (tmp_path / "s").exists() and list(tmp_path.iterdir()) == []
