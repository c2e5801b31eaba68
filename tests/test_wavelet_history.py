"""benchmarks/wavelet_history.py: section 7's runs kept across runs. The kernel-source hash ignores comments and
whitespace but not code; the history file is added to without duplicates and a bad file is refused in one line; the
rendered medians, the read speed and the rows below the line are checked against values worked by hand; the backfill
reads a real git history (a throwaway repository with two commits of a report)."""

from __future__ import annotations

import json
import subprocess

import pytest


@pytest.fixture(scope="module")
def wh(bench_module):
    return bench_module("wavelet_history")  # conftest's benchmarks/ importer


def _run(times: dict, utc: str = "2026-11-30T10:00:00Z", size: str = "small") -> dict:
    """A kernel run as bench_wavelet.kernel_run writes it: per (light, N), (kernel s, read s, bytes)."""
    rows = [{"light": lt, "N": n, "terms_kept": min(n, 292) if lt == "studio" else n, "bytes": b,
             "relight_cpu_s_1": k, "read_bound_cpu_s_1": r, "of_read_bound_cpu_1": r / k,
             "of_read_pick_cpu_1": r / k, "of_read_bound_cold": 0.7, "other": 1}
            for (lt, n), (k, r, b) in times.items()]
    return {"machine": {"load_before": 1.0, "load_after": 1.5}, "utc": utc, "size": size, "vertices": 2251,
            "build": {"isa": "avx512", "isa_choice": "native", "w16": True}, "rows": rows}


def test_source_hash_ignores_comments_not_code(wh):
    a = b"int f(int x) {\n  return x + 1; /* one */\n}\n"
    b = b"/* header\n * changed */\nint f(int x)   {\n\treturn x + 1; // other words\n}\n"
    c = b"int f(int x) {\n  return x + 2; /* one */\n}\n"
    assert wh.source_hash(a) == wh.source_hash(b)
    assert wh.source_hash(a) != wh.source_hash(c)
    assert len(wh.source_hash(a)) == 12


def test_record_keeps_the_criterion_fields(wh):
    run = _run({("sky", 1000): (60e-6, 30e-6, 1_500_000), ("studio", 300): (15e-6, 7.5e-6, 400_000)})
    run["rows"].append({"light": "studio", "N": 10, "of_bound_1": 0.9})  # a row from before the streaming read
    rec = wh.record(run, "CPU X", utc=run["utc"], time_from="run", source="abc", commit="1234567")
    assert [(r["light"], r["N"]) for r in rec["rows"]] == [("sky", 1000), ("studio", 300)]
    assert "other" not in rec["rows"][0]
    assert rec["build"] == "avx512 (native, w16 True)" and rec["load_before"] == 1.0
    assert wh.read_speed(rec) == pytest.approx(1_500_000 / 30e-6 / 1e9)  # 50 GB/s


def test_append_dedups_and_refuses_a_bad_file(wh, tmp_path):
    path = tmp_path / "h.json"
    r1 = wh.record(_run({("sky", 1000): (60e-6, 30e-6, 1_500_000)}, "2026-11-30T12:00:00Z"), "C", utc="2026-11-30T12:00:00Z",
                   time_from="run", source="s", commit="c")
    r0 = wh.record(_run({("sky", 1000): (70e-6, 30e-6, 1_500_000)}, "2026-11-30T09:00:00Z"), "C", utc="2026-11-30T09:00:00Z",
                   time_from="run", source="s", commit="c")
    assert wh.append([r1], path) == 1
    assert wh.append([r1, r0], path) == 1  # r1 is kept already
    assert [r["utc"] for r in json.loads(path.read_text())] == ["2026-11-30T09:00:00Z", "2026-11-30T12:00:00Z"]
    assert not list(tmp_path.glob("*.tmp*"))
    path.write_text("{not json")
    with pytest.raises(SystemExit, match=r"h\.json is not JSON.*list of kernel-run records"):
        wh.load_history(path)
    path.write_text(json.dumps({"rows": []}))
    with pytest.raises(SystemExit, match=r"h\.json is not a list of kernel-run records"):
        wh.load_history(path)


def test_history_md_medians_by_hand(wh):
    # three runs of one source (fractions 0.40 / 0.60 / 0.45 for studio 300: median 0.45, below the line;
    # sky N = 1000: 0.50 / 0.80 / 0.70: median 0.70) and one of an older source, which only gets its line
    fr = [(0.40, 0.50), (0.60, 0.80), (0.45, 0.70)]
    recs = []
    for i, (a, b) in enumerate(fr):
        run = _run({("studio", 300): (10e-6, a * 10e-6, 400_000), ("sky", 1000): (10e-6, b * 10e-6, 1_000_000)},
                   f"2026-11-30T1{i}:00:00Z")
        recs.append(wh.record(run, "CPU X", utc=run["utc"], time_from="run", source="new", commit=f"c{i}"))
    old = _run({("studio", 300): (10e-6, 3e-6, 400_000), ("sky", 1000): (10e-6, 9e-6, 1_000_000)}, "2026-11-29T08:00:00Z")
    recs.append(wh.record(old, "CPU X", utc=old["utc"], time_from="commit", source="old", commit="c9"))
    md = "\n".join(wh.history_md(recs, "new"))
    lines = md.splitlines()
    studio = next(x for x in lines if x.startswith("| studio | 300 (292 kept)"))
    sky = next(x for x in lines if x.startswith("| sky | 1000"))
    assert studio.split("|")[2:7] == [" 300 (292 kept) ", " 0.40 ", " 0.60 ", " 0.45 ", " **0.45** ⚠ "]
    assert sky.split("|")[5:7] == [" 0.70 ", " **0.70** "] and "⚠" not in sky
    assert "0.40 – 0.60" in studio
    # one line per run, oldest first, the older source's run marked by its commit time; its lowest row studio 0.30
    runs = [x for x in lines if x.startswith("| 2026-")]
    assert len(runs) == 4 and runs[0].startswith("| 2026-11-29 08:00 (commit) | `old`")
    assert "studio 300 (292 kept) 0.30" in runs[0]
    # read speed of sky N = 1000: 1 MB over 0.5 * 10 us = 200 GB/s in the first run
    assert "| 200 GB/s |" in runs[1]
    assert "fewer than three runs" not in md
    # one run of this source: not yet a judgement
    assert "fewer than three runs" in "\n".join(wh.history_md(recs[:1], "new"))
    assert "No run on this checkout's kernel source" in "\n".join(wh.history_md(recs[3:], "new"))


def test_backfill_reads_a_git_history(wh, tmp_path):
    repo = tmp_path / "repo"
    (repo / "reports" / "benchmarks").mkdir(parents=True)
    (repo / "prt_torch" / "kernels").mkdir(parents=True)
    git = ["git", "-c", "user.email=t@t", "-c", "user.name=t"]

    def commit(kernel: str, runs: list[dict], when: str) -> None:
        (repo / wh.KERNEL).write_text(kernel)
        (repo / "reports" / "benchmarks" / "wavelet.json").write_text(json.dumps({"kernel_runs": runs}))
        subprocess.run(git + ["add", "-A"], cwd=repo, check=True)
        subprocess.run(git + ["commit", "-q", "-m", "x"], cwd=repo, check=True,
                       env={"GIT_COMMITTER_DATE": when, "GIT_AUTHOR_DATE": when, "PATH": "/usr/bin:/bin"})

    subprocess.run(["git", "init", "-q"], cwd=repo, check=True)
    a = _run({("sky", 1000): (60e-6, 30e-6, 1_500_000)})
    b = _run({("sky", 1000): (50e-6, 30e-6, 1_500_000)}, size="medium")
    for r in (a, b):
        r["machine"].update(cpu="CPU X")
    commit("int k; /* v1 */", [a], "2026-11-29T10:00:00+01:00")
    commit("int k; /* v1, comment edited */", [a, b], "2026-11-29T12:00:00+00:00")  # run a kept: recorded once
    commit("int k2;", [b], "2026-11-29T13:00:00+00:00")
    path = tmp_path / "h.json"
    assert wh.backfill(repo, path) == 2
    recs = json.loads(path.read_text())
    assert [(r["utc"], r["size"], r["time_from"]) for r in recs] == [
        ("2026-11-29T09:00:00Z", "small", "commit"), ("2026-11-29T12:00:00Z", "medium", "commit")]
    assert recs[0]["kernel_source"] == recs[1]["kernel_source"] == wh.source_hash(b"int k;")
    assert wh.backfill(repo, path) == 0  # nothing new the second time


def test_read_sweep_one_thread_and_rendered(wh):
    import torch

    before = torch.get_num_threads()
    sw = wh.read_sweep((64, 128), seconds=0.005)
    assert torch.get_num_threads() == before
    assert set(sw) == {"64", "128"} and all(0.1 < v < 10_000 for v in sw.values())  # GB/s, not s or B/s
    run = _run({("sky", 1000): (60e-6, 30e-6, 1_500_000)})
    run["read_sweep"] = {str(k): float(i + 10) for i, k in enumerate(wh.SWEEP_KIB)}
    rec = wh.record(run, "C", utc=run["utc"], time_from="run", source="s", commit="c")
    line = next(x for x in wh.history_md([rec], "s") if x.startswith("| 2026-"))
    assert "| 10 / 11 / 12 / 13 / 14 |" in line
