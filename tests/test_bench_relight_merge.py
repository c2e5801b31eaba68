"""benchmarks/bench_relight.py --only X --merge (``merge_rows``): re-measured rows take the place of
the rows of the same codec, view and threads in the kept run of the same CPU and kernel build, new
rows and other builds' runs are added, every other row is kept as it was, the section names the
re-measured rows with their load and command, and a run of another point count is refused."""
import json

import pytest


@pytest.fixture(scope="module")
def br(bench_module):
    return bench_module("bench_relight")


def _run(cpu: str, points: int, rows: list[tuple], load: tuple = (1.0, 1.0, 1.0)) -> dict:
    return {"machine": {"cpu": cpu}, "kernel_build": {"isa": "avx2"}, "points": points, "load_average_before": load,
            "load_average_after": load, "native": {"detail": "a build"},
            "rows": [{"codec": c, "view": v, "threads": t, "relight_ms": ms} for c, v, t, ms in rows],
            "fits": [{"codec": c} for c in sorted({r[0] for r in rows})]}


def test_merge_replaces_only_the_same_rows_and_notes_them(br, tmp_path):
    path = tmp_path / "relight.json"
    kept = _run("cpu A", 50000, [("vq", "none", 1, 1.0), ("vq", "none", 2, 2.0), ("pca", "none", 1, 3.0)])
    other = _run("cpu B", 50000, [("vq", "none", 1, 9.0)])
    path.write_text(json.dumps({"runs": [kept, other]}))
    new = _run("cpu A", 50000, [("vq", "none", 1, 0.5), ("cpca", "none", 1, 4.0)], load=(7.5, 7.0, 6.0))
    runs = br.merge_rows(path, [new], "--only x --merge")
    a = next(r for r in runs if r["machine"]["cpu"] == "cpu A")
    got = {(x["codec"], x["view"], x["threads"]): x["relight_ms"] for x in a["rows"]}
    assert got == {("vq", "none", 1): 0.5, ("vq", "none", 2): 2.0, ("pca", "none", 1): 3.0, ("cpca", "none", 1): 4.0}
    assert [x["relight_ms"] for x in next(r for r in runs if r["machine"]["cpu"] == "cpu B")["rows"]] == [9.0]
    assert {f["codec"] for f in a["fits"]} == {"vq", "pca", "cpca"}
    (note,) = a["reruns"]
    assert note["rows"] == ["vq none 1 thr", "cpca none 1 thr"] and note["command"] == "--only x --merge"
    assert tuple(note["load_average_before"]) == (7.5, 7.0, 6.0)
    # measured again: the earlier note keeps only the rows this one did not re-measure
    path.write_text(json.dumps({"runs": runs}))
    runs = br.merge_rows(path, [_run("cpu A", 50000, [("cpca", "none", 1, 3.5)])], "--only cpca --merge")
    a = next(r for r in runs if r["machine"]["cpu"] == "cpu A")
    assert [(n["rows"], n["command"]) for n in a["reruns"]] == [(["vq none 1 thr"], "--only x --merge"),
                                                                (["cpca none 1 thr"], "--only cpca --merge")]
    rerun = json.loads(json.dumps(a))
    rerun["reruns"][0]["rows"] = []  # a note left with no row is dropped
    path.write_text(json.dumps({"runs": [rerun]}))
    a = br.merge_rows(path, [_run("cpu A", 50000, [("vq", "none", 1, 0.4)])], "--only vq --merge")[0]
    assert [n["rows"] for n in a["reruns"]] == [["cpca none 1 thr"], ["vq none 1 thr"]]


def test_merge_into_another_point_count_is_refused(br, tmp_path):
    path = tmp_path / "relight.json"
    path.write_text(json.dumps({"runs": [_run("cpu A", 50000, [("vq", "none", 1, 1.0)])]}))
    with pytest.raises(SystemExit, match="a run of 50000 points from one of 5000 points"):
        br.merge_rows(path, [_run("cpu A", 5000, [("vq", "none", 1, 1.0)])], "--only vq --merge")


def test_a_new_build_is_added_whole(br, tmp_path):
    path = tmp_path / "relight.json"
    path.write_text(json.dumps({"runs": [_run("cpu A", 50000, [("vq", "none", 1, 1.0)])]}))
    runs = br.merge_rows(path, [_run("cpu C", 50000, [("pca", "none", 1, 2.0)])], "--only pca --merge")
    assert sorted(r["machine"]["cpu"] for r in runs) == ["cpu A", "cpu C"]
    assert "reruns" not in next(r for r in runs if r["machine"]["cpu"] == "cpu C")
