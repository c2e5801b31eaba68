"""``prt relight``'s memory plan for a wavelet transfer (plan 10, issue 39 review): it counted the relighter
as one more copy of the stored coefficients (~792 B/vertex on the blocker scene, R = 32, K = 256) while
``WaveletRelighter.held_bytes()`` reports ~1520 B/vertex with both layouts at N = all, and the relighter also
keeps float32 values and int64 indices and builds its layout through int64 entry lists and a sort (~40–90 B per
kept coefficient). The plan now takes :meth:`WaveletRelighter.estimate_bytes` (the layout arithmetic on counts
read from the mapped file, without building it; the row-major copy counted when the run's light takes that pass —
sky at every term does, the studio light's 292 nonzero Haar terms of 6144 do not), checked here against an
independent measure: the arrays a
real relighter holds (``held_bytes()``, byte for byte) and the peak RSS a real ``prt relight`` reaches in a
fresh process (``VmHWM``): 1.0 <= plan peak / measured growth <= 2.0, as the precompute's estimate
(tests/test_precompute_estimate_memory.py). Before: 0.1 (the plan said ~6 MiB for a ~50 MiB run)."""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from prt_torch.cli import main as cli_main
from prt_torch.cli import relight as rl
from prt_torch.relight import WaveletRelighter
from prt_torch.scene import builtin
from prt_torch.transfer import RunOptions, Transfer, get_kind

PARTS = ("dense", "column", "row", "other", "total")


def _wavelet(path, scene="occluder_over_plane", **params):
    tr = get_kind("wavelet").precompute(builtin(scene), params, run=RunOptions(workers=1, progress=False))
    tr.save(path)
    return path


@pytest.fixture(scope="module")
def blocker32(tmp_path_factory):
    """The brief's transfer: the blocker scene, R = 32, K = 256, 8 bits with a scale per Haar level."""
    return _wavelet(tmp_path_factory.mktemp("w") / "w32.prt", res=32)


def test_estimate_follows_arith(tmp_path):
    """``estimate_bytes(arith=)`` plans the layout a relighter of that ``arith`` builds (its ``dense_min`` default,
    :meth:`WaveletRelighter.default_dense_min`: 0.2 for 16-bit values where the call runs the VNNI loop, else 1/3):
    every part equals ``held_bytes()`` of the relighter built with it, for both values."""
    path = _wavelet(tmp_path / "w.prt", res=16, terms=64, bits=16, scales="vertex")
    for arith in ("auto", "float"):
        est = WaveletRelighter.estimate_bytes(path, light="sky", arith=arith, row_min=0.5)
        r = WaveletRelighter(Transfer.load(path), row_min=0.5, arith=arith)
        li, lv, _ = r.light("sky")
        r(li, lv)
        assert {k: est[k] for k in PARTS} == r.held_bytes(), (arith, est, r.held_bytes())
        assert est["Pd"] == r.Pd, (arith, est["Pd"], r.Pd)


@pytest.mark.parametrize("params,layouts,light,terms,rows", [
    # sky at every term (its 6R²/2 upper-hemisphere terms): the light's sparse columns hold most sparse blocks, so the
    # kernel takes the row-major pass and 'auto' builds the copy
    ({"res": 16, "terms": 64}, "auto", "sky", None, True),  # 8-bit, a scale per level: re-quantised to 16 bits
    ({"res": 16, "terms": 64, "bits": 16, "scales": "vertex"}, "auto", "sky", None, True),  # the stored int16 values as they are
    ({"res": 16, "terms": 64, "bits": 32}, "auto", "sky", None, True),  # float32 values
    ({"res": 16, "terms": 64}, "column", "sky", 20, False),  # never the row-major copy
    ({"scene": "cornell_box", "res": 4, "terms": 48, "bounces": 1, "hit_samples": 4}, "auto", "sky", None, True),  # CT = 3
    # studio at every term: 143 nonzero Haar terms of 1536 at R = 16 (its softboxes on black; select_terms keeps no
    # round-off term), too few sparse blocks for the row-major pass: 'auto' never builds the copy
    ({"res": 16, "terms": 64}, "auto", "studio", None, False),
], ids=["8bit-level", "16bit-vertex", "float32", "column-only", "coloured", "sparse-light"])
def test_estimate_equals_held_bytes(tmp_path, params, layouts, light, terms, rows):
    """Every part of ``estimate_bytes`` for a light (from the file, nothing built) equals ``held_bytes()`` of the
    relighter built from it after relighting that light; the row-major copy is counted exactly when the real relighter
    built it; without the light, and the header-only bound, are at least the count, part by part (upper bounds)."""
    path = _wavelet(tmp_path / "w.prt", **params)
    # row_min 0.5 (the AVX2 builds' default) on every build: sky at R = 16, K = 64 holds 0.58-0.60 of the sparse blocks,
    # below the W16 builds' default (tests/test_wavelet_rowmin.py checks the default per build)
    est = WaveletRelighter.estimate_bytes(path, layouts=layouts, light=light, terms=terms, row_min=0.5)
    blind = WaveletRelighter.estimate_bytes(path, layouts=layouts)  # no light: the copy counted whatever the light
    bound = WaveletRelighter.estimate_bytes(path, layouts=layouts, exact=False)
    r = WaveletRelighter(Transfer.load(path), layouts=layouts, row_min=0.5)
    li, lv, _ = r.light(light, terms)
    r(li, lv)
    held = r.held_bytes()
    assert est["CT"] == r.CT == (3 if "scene" in params else 1)
    assert {k: est[k] for k in PARTS} == held, (est, held)
    assert (held["row"] > 0) == rows
    assert est["row_pass"] == (rows if layouts == "auto" else False)
    # the kernel's choice, counted directly on the relighter: the light's distinct sparse columns' blocks against
    # row_min (0.5) of all sparse blocks
    u = torch.unique(li)
    sb = int(r.bcount[:, u[(r.dslot[u] < 0) & (r.nnz[u] > 0)]].sum())
    assert r.row_min == est["row_min"] == 0.5
    if layouts == "auto":
        assert (sb >= 0.5 * r.NB) == rows, (sb, r.NB)
        assert est["row_share"] == sb / r.NB
    if light == "studio":
        assert li.numel() < r.P  # its nonzero terms only
    assert (est["Pd"], est["NB"], est["E"]) == (r.Pd, r.NB, int(r.nnz.sum()))
    for k in (*PARTS, "build"):
        assert bound[k] >= est[k] and blind[k] >= est[k], (k, bound[k], blind[k], est[k])
    assert (blind["row"] > 0) == (layouts != "column") and blind["row_pass"] is None


@pytest.mark.parametrize("light,per_vertex,rows", [
    ("sky", (1400, 1650), True),  # every term takes the row-major pass: both layouts held (1508 B/vertex)
    ("studio", (1000, 1250), False),  # 292 nonzero terms of 6144: the column-major pass, no row-major copy (1123 B/vertex)
])
def test_dry_run_states_what_the_relighter_holds(blocker32, tmp_path, capsys, light, per_vertex, rows):
    """The dry run's *held* stage is ``held_bytes()`` of the relighter after relighting the run's light (nothing else
    held since mem10; the row-major copy only when that light takes the row-major pass, as the real relighter builds
    it); a budget between the exact peak and the header's bound is counted exactly and the run proceeds; one
    below the exact peak is refused in one line naming the stages, nothing written."""
    out = tmp_path / "o.npy"
    capsys.readouterr()
    assert cli_main(["relight", str(blocker32), "--light", light, "-o", str(out), "--dry-run"]) == 0
    err = capsys.readouterr().err
    r = WaveletRelighter(Transfer.load(blocker32))
    li, lv, _ = r.light(light)
    r(li, lv)
    held = r.held_bytes()
    assert (held["row"] > 0) == rows
    assert f": {held['total'] / r.V:.0f} B/vertex\n" in err and per_vertex[0] < held["total"] / r.V < per_vertex[1], err
    assert ("this light takes that pass" if rows else "not built: this light takes the column-major pass") in err
    ns = dict(transfer=str(blocker32), source=None, output=str(out), memory_limit=None, light=light, terms=None,
              selection=None)
    exact = rl.plan(argparse.Namespace(**ns, dry_run=True))
    st = {s["stage"]: s["bytes"] for s in exact["stages"]}
    bound = rl._wavelet_plan(argparse.Namespace(**ns, dry_run=False), exact["V"], st["input"], 0, exact=False)
    assert st["held"] == held["total"]
    assert bound["peak"] > exact["peak"]
    mid = (exact["peak"] + bound["peak"]) / 2 / 2**30
    pl = rl.plan(argparse.Namespace(**{**ns, "memory_limit": mid}, dry_run=False))
    assert pl["relighter"]["exact"] and pl["peak"] == exact["peak"]
    assert cli_main(["relight", str(blocker32), "--light", light, "-o", str(out), "--memory-limit", str(mid)]) == 0
    assert out.exists()
    low = exact["peak"] * 0.9 / 2**30
    out2 = tmp_path / "o2.npy"
    capsys.readouterr()
    assert cli_main(["relight", str(blocker32), "--light", light, "-o", str(out2), "--memory-limit", str(low)]) == 2
    e = capsys.readouterr().err.strip().splitlines()
    assert len(e) == 1 and "held" in e[0] and "build" in e[0] and not out2.exists(), e


CHILD = textwrap.dedent("""
    import argparse, json, sys

    def peak():  # this process's peak RSS (VmHWM: the fresh address space's own)
        with open("/proc/self/status") as f:
            return next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmHWM:"))

    from prt_torch.cli import main as cli_main
    from prt_torch.cli import relight as rl
    path, warm, out = sys.argv[1:4]
    # warm-up on a tiny transfer: imports, the kernel's library and thread pools are not the plan's
    assert cli_main(["relight", warm, "--light", "studio", "-o", out + ".warm.npy"]) == 0
    before = peak()
    assert cli_main(["relight", path, "--light", "sky", "-o", out]) == 0  # every term: the row-major pass
    growth = peak() - before
    pl = rl.plan(argparse.Namespace(transfer=path, source=None, output=out, memory_limit=None, dry_run=True,
                                    light="sky", terms=None, selection=None))
    print("JSON " + json.dumps({"plan": pl["peak"], "growth": growth}))
""")


def test_plan_peak_covers_the_measured_peak_within_2x(blocker32, tmp_path):
    """A fresh process relights every term of the sky (the row-major copy built); its RSS growth from the warm-up's
    high-water mark is what the plan must cover: 1.0 <= plan peak / growth <= 2.0, the largest growth of three runs
    (measured 1.2–1.3 at R = 32 on 2251 vertices and 1.0–1.2 on 10 585; the old plan read 0.1; with the light
    rasterised in blocks and the construction's bound fitted, 1.50–2.26 for single runs, growth 10.0–15.2 MB)."""
    warm = _wavelet(tmp_path / "w2.prt", res=2, terms=24)
    runs = []
    for i in range(3):  # the growth of one run moved 10.0-15.2 MB between runs once the light was rasterised in blocks
        p = subprocess.run([sys.executable, "-c", CHILD, str(blocker32), str(warm), str(tmp_path / f"o{i}.npy")],
                           capture_output=True, text=True, timeout=600, env={**os.environ, "OMP_NUM_THREADS": "1"})
        assert p.returncode == 0, p.stderr[-2000:]
        runs.append(json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("JSON "))[5:]))
    r = {"plan": runs[0]["plan"], "growth": max(x["growth"] for x in runs)}  # the plan must cover the largest
    ratio = r["plan"] / r["growth"]
    print(r, ratio)
    assert 1.0 <= ratio <= 2.0, (r, ratio)
