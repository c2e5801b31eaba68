"""Issue 42 part 3 (linear cost to a million vertices): the geodesic sizes (``bumpy_sphere:xl``,
vertex counts), the vectorised mesh kernels against their former formulations, the streamed
precompute (chunks on disk, a forced stop, ``--resume``) against the in-memory result, the
per-stage estimate of ``prt precompute --dry-run`` against the real result's bytes, the refusal
up front, and the sample count the qmc set rounds."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

from prt_torch.cli import main as cli_main
from prt_torch.harness.config import load_config
from prt_torch.scene import builtin, check_size, geodesic_sphere, load_scene
from prt_torch.scene.builtins import _freq_for
from prt_torch.scene.mesh import edge_face_counts, vertex_normals
from prt_torch.transfer import ChunkInterrupt, RunOptions, Transfer, default_state_dir, get_kind, precompute_diffuse
from prt_torch.transfer.diffuse import samples_rounding
from prt_torch.transfer.estimate import check_fits, estimate, result_bytes_per_vertex

warnings.filterwarnings("ignore", message="Sparse")


# ------------------------------------------------------------------------------ sizes
def test_geodesic_sizes_are_closed_spheres_of_the_asked_count():
    """A vertex count picks the nearest level f (10 f² + 2 vertices, 20 f² faces), a closed
    2-manifold (every edge on two faces; Euler characteristic V − E + F = 2); 'xl' is ~1M."""
    m = builtin("bumpy_sphere:3000")
    f = _freq_for(3000)
    assert m.num_vertices == 10 * f * f + 2 and m.num_faces == 20 * f * f and m.meta["size"] == 3000
    edges, counts = edge_face_counts(m.faces, m.num_vertices)
    assert (counts == 2).all() and m.num_vertices - edges.shape[0] + m.num_faces == 2
    fx = _freq_for(1_000_000)  # xl: not built here (5 s, 1.3 GB); its level and count
    assert 10 * fx * fx + 2 == 998_562
    assert load_scene("convex:500").num_vertices == 10 * _freq_for(500) ** 2 + 2
    assert check_size("bumpy_sphere", "xl") == "xl" and check_size("bumpy_sphere", "100000") == 100000


@pytest.mark.parametrize("name, err", [
    ("cornell_box:xl", "'xl' is not accepted for 'cornell_box'"),
    ("scan_blob:5000", r"a vertex count\) is not accepted for .scan_blob."),
    ("bumpy_sphere:5", r"size=5 vertices for 'bumpy_sphere'; accepted: a count in \[12, 20000000\]"),
    ("bumpy_sphere:huge", "size='huge' is not accepted"),
])
def test_bad_sizes_are_refused_naming_the_size(name, err):
    with pytest.raises(ValueError, match=err):
        builtin(name)


def test_config_takes_xl_and_counts(tmp_path):
    p = tmp_path / "c.yaml"
    p.write_text("scene: {name: bumpy_sphere, size: 100000}\ntransfer: {type: diffuse}\ncodecs: [{type: pca, vectors: 2}]\n")
    assert load_config(p)["scene"]["size"] == 100000
    p.write_text("scene: {name: bumpy_sphere, size: 11}\ntransfer: {type: diffuse}\ncodecs: [{type: pca, vectors: 2}]\n")
    with pytest.raises(ValueError, match="scene.size"):
        load_config(p)


def _np_unique_geodesic(freq: int) -> tuple[np.ndarray, np.ndarray]:
    """geodesic_sphere as it was, merging shared lattice points with np.unique(axis=0)."""
    freq = int(freq)
    t = (1 + 5 ** 0.5) / 2
    ico_v = np.array([[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                      [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]], dtype=np.float64)
    ico_f = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
                      [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
                      [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]])
    # barycentric lattice of one face: points (i, j) with i + j <= f
    ii, jj = np.meshgrid(np.arange(freq + 1), np.arange(freq + 1), indexing="ij")
    keep = ii + jj <= freq
    i, j = ii[keep], jj[keep]
    idx = -np.ones((freq + 1, freq + 1), np.int64)
    idx[i, j] = np.arange(i.shape[0])
    # small triangles of the lattice (upward and downward)
    a_i, a_j = np.meshgrid(np.arange(freq), np.arange(freq), indexing="ij")
    up = a_i + a_j <= freq - 1
    tri_up = np.stack([idx[a_i[up], a_j[up]], idx[a_i[up] + 1, a_j[up]], idx[a_i[up], a_j[up] + 1]], 1)
    dn = a_i + a_j <= freq - 2
    tri_dn = np.stack([idx[a_i[dn] + 1, a_j[dn]], idx[a_i[dn] + 1, a_j[dn] + 1], idx[a_i[dn], a_j[dn] + 1]], 1)
    local_f = np.concatenate([tri_up, tri_dn])
    A, B, C = ico_v[ico_f[:, 0]], ico_v[ico_f[:, 1]], ico_v[ico_f[:, 2]]  # [20,3]
    w_b = i / freq
    w_c = j / freq
    w_a = 1 - w_b - w_c
    pts = w_a[None, :, None] * A[:, None] + w_b[None, :, None] * B[:, None] + w_c[None, :, None] * C[:, None]
    pts = pts / np.linalg.norm(pts, axis=-1, keepdims=True)
    P = pts.shape[1]
    faces = (local_f[None] + (np.arange(20) * P)[:, None, None]).reshape(-1, 3)
    flat = pts.reshape(-1, 3)
    # merge the lattice points shared by neighbouring icosahedron faces
    key = np.round(flat * 1e9).astype(np.int64)
    _, first, inv = np.unique(key, axis=0, return_index=True, return_inverse=True)
    inv = inv.reshape(-1)
    order = np.argsort(first)
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    verts = flat[first[order]]
    faces = rank[inv][faces]
    # orient outward
    tri = verts[faces]
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    flip = np.einsum("ij,ij->i", nrm, tri.mean(1)) < 0
    faces[flip] = faces[flip][:, ::-1]
    return verts, faces


@pytest.mark.parametrize("freq", [1, 2, 9, 40])
def test_geodesic_merge_equals_the_np_unique_merge(freq):
    """The lexsort merge gives exactly the vertices and faces of the np.unique merge it replaced."""
    v, f = geodesic_sphere(freq)
    v0, f0 = _np_unique_geodesic(freq)
    assert np.array_equal(v, v0) and np.array_equal(f, f0)
    assert v.shape[0] == 10 * freq * freq + 2 and f.shape[0] == 20 * freq * freq


def test_vertex_normals_equal_the_add_at_formulation():
    """The bincount scatter sums in np.add.at's order: bit-identical normals (angle and area)."""
    m = builtin("scan_blob")  # folded, sliver and non-manifold vertices: the fall-backs run too
    v, f = m.vertices.numpy().astype(np.float64), m.faces.numpy()
    tri = v[f]
    cr = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm = np.linalg.norm(cr, axis=1, keepdims=True)
    area = np.zeros((v.shape[0], 3))
    nhat = np.divide(cr, nrm, out=np.zeros_like(cr), where=nrm > 0)
    acc = np.zeros((v.shape[0], 3))
    for k in range(3):
        np.add.at(area, f[:, k], cr)
        e1, e2 = tri[:, (k + 1) % 3] - tri[:, k], tri[:, (k + 2) % 3] - tri[:, k]
        ang = np.where(nrm[:, 0] > 0, np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2)), 0.0)
        np.add.at(acc, f[:, k], nhat * ang[:, None])
    ok = np.linalg.norm(acc, axis=1) > 1e-6  # vertices the fall-backs do not touch
    want = acc[ok] / np.linalg.norm(acc[ok], axis=1, keepdims=True)
    got = vertex_normals(v, f, "angle")
    assert ok.mean() > 0.95 and np.array_equal(got[ok], want)
    a_ok = np.linalg.norm(area, axis=1) > 1e-9
    got_a = vertex_normals(v, f, "area")
    assert np.array_equal(got_a[a_ok], area[a_ok] / np.linalg.norm(area[a_ok], axis=1, keepdims=True))


# ------------------------------------------------------------------------------ streamed runs
KW = {"bands": 3, "samples": 32, "shadows": "always"}


def test_interrupted_cli_run_resumes_to_the_in_memory_result(tmp_path):
    """A run stopped after two chunks (its chunks on disk, as the CLI keeps them) finishes with
    ``prt precompute --resume`` computing only the rest; the file equals the in-memory result
    (no state directory, the default chunking) bit for bit."""
    mesh = builtin("bumpy_sphere:3000")
    ref = precompute_diffuse(mesh, **KW)  # in memory, default chunks
    out = tmp_path / "t.prt"
    state = default_state_dir(out)

    def stop(i, n):
        if i == 1:
            raise ChunkInterrupt("forced stop")

    with pytest.raises(ChunkInterrupt):
        get_kind("diffuse").precompute(mesh, dict(KW), run=RunOptions(chunk_size=500, state_dir=state, callback=stop))
    assert len(list(state.glob("chunk_*.prt"))) == 2 and not out.exists()
    args = ["precompute", "bumpy_sphere:3000", "--bands", "3", "--samples", "32", "--shadows", "always", "--chunk", "500",
            "-o", str(out), "--no-progress"]
    assert cli_main(args) == 2  # the state is not silently discarded
    assert cli_main(args + ["--resume"]) == 0
    assert not state.exists()
    assert torch.equal(Transfer.load(out).data, ref.data)


def test_streamed_mrt_equals_in_memory(tmp_path):
    """MRT with its chunks written to a state directory, stopped and resumed, equals the run
    held in memory (bit for bit)."""
    mesh = builtin("bumpy_sphere:300")
    p = {"bands": 2, "M": 2, "bands_out": 2, "samples": 32, "shadows": "always", "brdf": {"type": "phong", "s": 4.0}}
    ref = get_kind("mrt").precompute(mesh, dict(p))
    state = tmp_path / "s"

    def stop(i, n):
        if i == 2:
            raise ChunkInterrupt("forced stop")

    with pytest.raises(ChunkInterrupt):
        get_kind("mrt").precompute(mesh, dict(p), run=RunOptions(chunk_size=60, state_dir=state, callback=stop))
    got = get_kind("mrt").precompute(mesh, dict(p), run=RunOptions(chunk_size=60, state_dir=state, resume=True))
    assert torch.equal(got.data, ref.data)


# ------------------------------------------------------------------------------ the estimate
@pytest.mark.parametrize("kind, params, scene", [
    ("diffuse", {"bands": 4, "samples": 16, "shadows": "always"}, "bumpy_sphere"),
    ("diffuse", {"bands": 3, "samples": 16, "bounces": 1, "shadows": "always"}, "cornell_box"),  # coloured: [V, 3, n²]
    ("mrt", {"bands": 3, "M": 3, "bands_out": 3, "samples": 16, "shadows": "always", "brdf": {"type": "phong", "s": 4.0}},
     "bumpy_sphere:300"),
    ("glossy", {"bands": 3, "bands_out": 2, "samples": 16, "shadows": "always", "brdf": {"type": "phong", "s": 4.0}},
     "bumpy_sphere:300"),
    ("wavelet", {"res": 4, "terms": 20, "bits": 8, "shadows": "always"}, "bumpy_sphere:300"),
    ("subsurface", {"bands": 3, "samples": 16, "material": "marble", "scale": 10.0}, "bumpy_sphere:300"),
])
def test_estimated_result_bytes_equal_the_result(kind, params, scene):
    """The estimate's stored bytes per vertex are those of the transfer the run returns (data
    and aux tensors), for every file kind and diffuse's two layouts."""
    mesh = load_scene(scene)
    k = get_kind(kind)
    tr = k.precompute(mesh, dict(params))
    got = (tr.data.numel() * tr.data.element_size() + sum(t.numel() * t.element_size() for t in tr.aux.values()))
    kw, _ = k.resolve(dict(params))
    per_vertex, held = result_bytes_per_vertex(kind, kw, mesh)
    assert per_vertex * mesh.num_vertices == pytest.approx(got, rel=0.02 if kind == "wavelet" else 0)
    assert held >= per_vertex


def test_estimate_stages_probe_and_refusal(tmp_path):
    """Every stage has bytes and (with the probe) seconds; the probe writes nothing; a budget
    below the peak is refused naming every stage and the budget."""
    mesh = builtin("bumpy_sphere:3000")
    k = get_kind("diffuse")
    e = estimate(k, mesh, dict(KW), RunOptions(state_dir=tmp_path / "never"), probe=True, probe_vertices=128, mesh_seconds=0.1)
    assert [s["stage"] for s in e.stages] == ["mesh", "rays", "result"]
    assert all(s["bytes"] > 0 and s["seconds"] is not None and s["seconds"] >= 0 for s in e.stages)
    assert e.stages[0]["bytes"] >= mesh.vertices.numel() * 4 and e.fits
    assert e.peak_bytes == e.stages[0]["bytes"] + max(e.stages[1]["bytes"], e.stages[2]["bytes"])
    assert not (tmp_path / "never").exists()
    small = estimate(k, mesh, dict(KW), RunOptions(max_memory=1 << 20), probe=False)
    assert small.stages[1]["seconds"] is None and not small.fits
    with pytest.raises(ValueError, match=r"needs about .* \(mesh .*, rays .*, result .*\).* budget is 1 MiB"):
        check_fits(small)


def test_cli_dry_run_prints_stages_writes_nothing_and_refuses_up_front(tmp_path, capsys):
    out = tmp_path / "t.prt"
    base = ["precompute", "bumpy_sphere:1000", "--bands", "3", "--samples", "16", "-o", str(out), "--no-progress"]
    assert cli_main(base + ["--dry-run"]) == 0
    err = capsys.readouterr().err
    for word in ("mesh", "rays", "result", "peak", "fits", "nothing written"):
        assert word in err
    assert not out.exists() and not default_state_dir(out).exists()
    assert cli_main(base + ["--dry-run", "--memory-limit", "0.001"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "does NOT fit" in "\n".join(err) and "budget is 1.02 MiB" in err[-1] and "Traceback" not in "\n".join(err)
    assert cli_main(base + ["--memory-limit", "0.001"]) == 2  # a real run: refused before any ray, nothing left behind
    assert not out.exists() and not default_state_dir(out).exists()


# ------------------------------------------------------------------------------ bad input
def test_a_sample_count_the_qmc_set_cannot_honour_says_what_it_rounds_to():
    assert samples_rounding(32, "qmc") is None and samples_rounding(33, "uniform") is None
    mesh = builtin("bumpy_sphere:300")
    with pytest.warns(UserWarning, match=r"samples=33 with sampling='qmc' is rounded to 34: .* 17 rays per vertex"):
        a = precompute_diffuse(mesh, bands=2, samples=33, shadows="always")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        b = precompute_diffuse(mesh, bands=2, samples=34, shadows="always")
    assert torch.equal(a.data, b.data)  # what it rounds to is what it traces
    assert a.meta["rays_traced"] == b.meta["rays_traced"] == 17 * mesh.num_vertices


def test_rounding_is_one_cli_line(tmp_path, capsys):
    out = tmp_path / "t.prt"
    assert cli_main(["precompute", "bumpy_sphere:300", "--samples", "9", "--bands", "2", "-o", str(out), "--no-progress"]) == 0
    lines = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert lines == ["prt precompute: warning: samples=9 with sampling='qmc' is rounded to 10: the Hammersley set over each "
                     "vertex's hemisphere traces ⌈N/2⌉ = 5 rays per vertex; accepted exactly: an even count"]
    assert math.isfinite(float(Transfer.load(out).data.sum()))


# ------------------------------------------------------------------------------ the benchmark
def test_bench_scale_smoke(tmp_path):
    """benchmarks/bench_scale.py end to end on two tiny sizes (each stage in its own child): every
    row measured, the peer tables written, the json readable and the report rewritable from it."""
    import importlib.util
    import json
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_scale.py"
    spec = importlib.util.spec_from_file_location("bench_scale", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    out = tmp_path / "scale.md"
    assert mod.main(["--sizes", "300", "--stages", "diffuse", "cpca", "relight", "--samples", "8",
                     "--work", str(tmp_path / "w"), "--out", str(out)]) == 0
    rows = json.loads(out.with_suffix(".json").read_text())["rows"]
    assert len(rows) == 3 and not any("error" in r for r in rows)
    assert all(r["stage_peak_rss"] > 0 and r["vertices"] == 252 for r in rows)
    text = out.read_text()
    for part in ("| diffuse | 252 |", "bound / CPCA", "estimate / measured", "**Marginal memory**"):
        assert part in text
    # the marginal memory (issue 42 part 3): measured after a warm-up and a peak reset, positive
    assert all(r["marginal_reset"] and r["marginal_bytes"] > 0 for r in rows)
    again = tmp_path / "again.md"
    assert mod.main(["--from-json", str(out.with_suffix(".json")), "--out", str(again)]) == 0
    assert again.read_text() == text


def test_interruption_hint_says_what_was_kept(tmp_path):
    """Stopped before the first chunk (a big mesh still building) the hint does not claim kept
    chunks; with chunks on disk it counts them and gives the --resume command."""
    from prt_torch.cli.precompute import ResumeHint

    state = tmp_path / "t.prt.state"
    h = ResumeHint(state, "prt precompute bumpy_sphere:xl -o t.prt")
    assert str(h) == "no chunk had finished, nothing was kept; run it again: prt precompute bumpy_sphere:xl -o t.prt"
    state.mkdir()
    (state / "chunk_000000.prt").write_bytes(b"")
    (state / "chunk_000001.prt").write_bytes(b"")
    assert str(h) == (f"finished chunks (2) are kept in {str(state)!r}; continue with: "
                      "prt precompute bumpy_sphere:xl -o t.prt --resume")


def test_run_chunks_with_a_sink_holds_no_finished_chunk():
    """With ``sink``, a chunk's result is freed once the sink has copied it: while chunk i computes,
    no earlier chunk's tensor is alive (the executor's result list used to keep every one until the
    map ended, so a run held its result twice), and the assembled result is every chunk's rows."""
    import weakref

    from prt_torch.transfer.base import run_chunks

    refs: list = []
    dead_at: list[bool] = []

    def compute(a: int, b: int) -> dict:
        dead_at.append(all(r() is None for r in refs))
        t = torch.arange(a, b, dtype=torch.float64)[:, None].expand(-1, 4).clone()
        refs.append(weakref.ref(t))
        return {"T": t}

    got = torch.full((10, 4), -1.0, dtype=torch.float64)

    def sink(a: int, b: int, p: dict) -> None:
        got[a:b] = p["T"]

    out = run_chunks(10, 3, compute, fingerprint={"t": 1}, sink=sink)
    assert dead_at == [True] * 4 and all(r() is None for r in refs)
    assert out == [None] * 4
    assert torch.equal(got, torch.arange(10, dtype=torch.float64)[:, None].expand(-1, 4))
