"""The wavelet relighter's memory (mem10, issue 39 review): ``WaveletRelighter`` kept, beside its kernel layout
(``held_bytes()``), an int64 copy of the kept indices and a float32 copy of the values (~3 KB/vertex on the blocker
scene at R = 32, K = 256: twice the layout) that neither the kernel nor the torch path reads, and its construction
peaked at ~18x what it holds (whole-transfer int64 entry lists, keys and a sort). Now it is built in chunks of rows
and the reference paths derive the copies from the stored transfer (``reference_rows``). Checked here against
independent measures: the float64 dense reference ``relight.wavelet_dense`` and the torch path for several chunk
sizes (one chunk, many, chunks smaller than a tile); every tensor the relighter holds counted by ``held_bytes()``;
a fresh process's peak RSS growth while constructing; the refusal hint of a wavelet run over budget."""
from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from prt_torch import relight
from prt_torch.cli import main as cli_main
from prt_torch.relight import WaveletRelighter
from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions, Transfer, get_kind


def _wavelet(scene="occluder_over_plane", **params):
    return get_kind("wavelet").precompute(builtin(scene), params, run=RunOptions(workers=1, progress=False))


@pytest.fixture(scope="module")
def blocker32(tmp_path_factory):
    """The brief's transfer: the blocker scene, R = 32, K = 256, 8 bits with a scale per Haar level."""
    path = tmp_path_factory.mktemp("wb") / "w32.prt"
    _wavelet(res=32).save(path)
    return path


@pytest.mark.parametrize("params", [
    {"res": 16, "terms": 64},  # 8-bit, a scale per level: re-quantised to 16 bits
    {"res": 16, "terms": 64, "bits": 8, "scales": "vertex"},  # the stored int8 values as they are
    {"res": 8, "terms": 48, "bits": 32},  # float32 values
    {"scene": "cornell_box", "res": 4, "terms": 48, "bounces": 1, "hit_samples": 4},  # coloured: CT = 3
], ids=["8bit-level", "8bit-vertex", "float32", "coloured"])
@pytest.mark.parametrize("chunk", [1 << 30, 1 << 13, 1], ids=["one-chunk", "chunks", "32-row-chunks"])
def test_chunked_build_equals_dense_reference_and_torch_path(params, chunk, monkeypatch):
    """Built in chunks of any size (the whole transfer at once; several; one 32-vertex block each, smaller than a
    tile, so the chunks' sparse blocks interleave and are merged by the sort), the kernel equals the float64 dense
    sum over each vertex's kept coefficients (Ng 2003 eq. 2, ``wavelet_dense`` on ``reference_rows``) to float32
    rounding, and the torch path (``PRT_TORCH_NATIVE=0``) equals it too, at N = all and N = 40, column-only and
    both layouts."""
    tr = _wavelet(**params)
    monkeypatch.setattr(WaveletRelighter, "BUILD_CHUNK_BYTES", chunk)
    for layouts in ("column", "both"):
        # the float dense loop (arith='float'): this test is about the chunked construction, to float32 rounding
        r = WaveletRelighter(tr, layouts=layouts, tile=64 if chunk == 1 else None, arith="float")
        assert WaveletRelighter._build_rows_per_chunk(r.K, r.CT) < r.V or chunk > 1 << 20
        idx, vals = r.reference_rows()
        assert idx.shape == (r.V, r.K) and vals.dtype == torch.float32
        for terms in (None, 40):
            li, lv, _ = r.light("sky", terms)  # every sky term: the row-major pass at R = 16 with 'both' (not studio's few)
            got = r(li, lv.float())
            a = tr.mesh.albedo[:, :3].double() if r.CT == 1 else torch.ones(r.V, 3, dtype=torch.float64)
            if r.CT == 1:
                ref = relight.wavelet_dense(vals.double(), idx, li, lv, r.P) * a
            else:  # one transfer per colour sharing the vertex's indices
                ref = torch.stack([relight.wavelet_dense(vals[:, c].double(), idx, li, lv[c:c + 1], r.P)[:, 0]
                                   for c in range(3)], 1)
            scale = ref.abs().max()
            assert float((got.double() - ref).abs().max()) <= 2e-5 * float(scale), (layouts, terms)
            monkeypatch.setenv("PRT_TORCH_NATIVE", "0")
            try:
                fb = r(li, lv.float())
            finally:
                monkeypatch.delenv("PRT_TORCH_NATIVE")
            assert float((fb.double() - ref).abs().max()) <= 2e-5 * float(scale), (layouts, terms)


def test_reference_rows_slices_are_the_whole_rows():
    """``reference_rows(a, b)`` (what harness/trade.py reads chunk by chunk) equals rows a:b of the whole, and
    ``values`` is the re-quantised values the kernel relights with: dequantised stored values within one
    16-bit step of the vertex's largest value (the re-quantisation's stated error, max|T̂_v| / 65534)."""
    from prt_torch.transfer.wavelet import wavelet_values

    tr = _wavelet(res=8, terms=48)
    r = WaveletRelighter(tr)
    idx, vals = r.reference_rows()
    for a, b in ((0, 7), (100, 333), (r.V - 5, r.V)):
        i2, v2 = r.reference_rows(a, b)
        assert torch.equal(i2, idx[a:b]) and torch.equal(v2, vals[a:b])
    stored = wavelet_values(tr)
    step = stored.abs().amax(1, keepdim=True) / 65534
    assert bool(((vals - stored).abs() <= step * (1 + 1e-6) + 1e-12).all())
    assert torch.equal(r.index, tr.aux["index"].long())


def test_held_bytes_counts_every_tensor_the_relighter_holds(blocker32):
    """Every tensor attribute of a relighter (the transfer itself aside) is counted by ``held_bytes()``: nothing
    else is held — before, the ``values`` float32 and ``index`` int64 copies (3072 B/vertex here, twice the
    layout) were held and not counted. And the total after one relight of every term (both layouts) is the
    documented ~1520 B/vertex."""
    r = WaveletRelighter(Transfer.load(blocker32))
    li, lv, _ = r.light("sky")  # every term of the sky: the row-major pass (not the studio light's 292 nonzero terms)
    r(li, lv)
    own = [v for k, v in vars(r).items() if isinstance(v, torch.Tensor) and k not in ("_layout",)]
    own += [f for f, _ in r._f.values()] + list(r._f_full.values())  # the factors (_kfactor's: tensor, C argument)
    counted = sum(t.numel() * t.element_size() for t in own)
    assert counted == r.held_bytes()["total"], (counted, r.held_bytes())
    assert 1400 < counted / r.V < 1650


CHILD = textwrap.dedent("""
    import json, sys
    import torch

    def peak():
        with open("/proc/self/status") as f:
            return next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmHWM:"))

    from prt_torch.relight import WaveletRelighter
    from prt_torch.transfer import Transfer
    path, warm = sys.argv[1:3]
    WaveletRelighter(Transfer.load(warm))  # warm-up on a tiny transfer: imports, the allocator's first arenas
    tr = Transfer.load(path)
    before = peak()
    r = WaveletRelighter(tr)
    growth = peak() - before
    est = WaveletRelighter.estimate_bytes(path, layouts="auto")
    print("JSON " + json.dumps({"growth": growth, "held": r.held_bytes()["total"],
                                "planned": est["total"] - est["row"] + est["build"]}))
""")


def test_construction_peak_is_a_few_times_what_it_holds(blocker32, tmp_path):
    """A fresh process constructing the relighter (transfer loaded, after a warm-up construction) grows its peak
    RSS by at most 6x what the relighter then holds (measured 4.5-4.8x at the default chunk; before: 18-22x,
    45-56 MiB for 2.5 MiB, reports/benchmarks/wavelet_build.md) and by no more than the plan's count of held + build bytes."""
    warm = tmp_path / "w2.prt"
    _wavelet(res=2, terms=24).save(warm)
    p = subprocess.run([sys.executable, "-c", CHILD, str(blocker32), str(warm)], capture_output=True, text=True, timeout=600,
                       env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert p.returncode == 0, p.stderr[-2000:]
    r = json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("JSON "))[5:])
    assert r["growth"] <= 6 * r["held"], r
    assert r["growth"] <= r["planned"] * 1.25, r


def test_wavelet_refusal_names_what_would_help(blocker32, tmp_path, capsys):
    """A wavelet relight over its budget is refused in one line that suggests fewer kept coefficients (a .npy
    output changes nothing there: the output is not held), nothing written."""
    out = tmp_path / "o.npy"
    capsys.readouterr()
    assert cli_main(["relight", str(blocker32), "--light", "studio", "-o", str(out), "--memory-limit", "0.001"]) == 2
    e = capsys.readouterr().err.strip().splitlines()
    assert len(e) == 1 and "--terms" in e[0] and "--res" in e[0] and ".npy output" not in e[0], e
    assert not out.exists()


@pytest.mark.parametrize("chunk", [8, 24, 1000])
def test_estimate_counts_in_any_chunk_of_whole_blocks(blocker32, chunk):
    """``estimate_bytes`` counts in slices of whole 8-vertex blocks (not whole tiles: a block's key names its
    tile and block, so it lies in one slice): slices of 8, 24 or 1000 rows (a multiple of 8 inside the 1152-vertex
    tiles) count exactly what a relighter built from the file holds, part by part."""
    r = WaveletRelighter(Transfer.load(blocker32), layouts="column")
    li, lv, _ = r.light("studio", 50)
    r(li, lv)
    est = WaveletRelighter.estimate_bytes(blocker32, layouts="column", chunk=chunk)
    assert r.TV == 1152 and {k: est[k] for k in r.held_bytes()} == r.held_bytes()
    assert (est["NB"], est["Pd"]) == (r.NB, r.Pd)
