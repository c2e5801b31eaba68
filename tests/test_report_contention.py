"""A rate measured under contention is marked in the table itself (Mvert/s and fps cells), not
only in the footnote: a user reads those columns (issue 36)."""
from prt_torch.harness import report


def _rec(sid, trusted, vectors=2):
    return {"codec": "pca", "setting_id": sid, "params": {"vectors": vectors}, "bytes_per_vertex": 8.0, "compression_ratio": 4.0,
            "se": 1.0, "relative_se": 0.01, "psnr_random_db": 30.0, "psnr_lights_db": 31.0, "vertices_per_s": 2.5e6,
            "relight_spread": 0.05, "fps": 250.0, "speedup_vs_uncompressed": 3.0, "encode_s": 0.1, "timing_trusted": trusted,
            "contention": {"trusted": trusted, "why_not": [] if trusted else ["involuntary switches"]}}


def test_untrusted_rates_are_marked_in_their_cells():
    lines = report._records_table([_rec("pca-vectors2", True), _rec("pca-vectors3", False, vectors=3)])
    rows = {ln.split("|")[2].strip(): [c.strip() for c in ln.strip("|").split("|")] for ln in lines if ln.startswith("| pca")}
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    mv, fps = header.index("Mvert/s"), header.index("fps")
    bad = next(v for k, v in rows.items() if "3" in k)
    good = next(v for k, v in rows.items() if "3" not in k)
    assert bad[mv].endswith("⚠") and bad[fps].endswith("⚠")
    assert "⚠" not in good[mv] and "⚠" not in good[fps]
    assert report._contention_note([_rec("a", False)])  # and the footnote still says why


# ------------------------------------------------------------------ contention that starts after import

def _first(seconds):
    from prt_torch.harness.timing import Timing

    return Timing(seconds, seconds, seconds, seconds, seconds, 5, 1)


def test_contention_after_import_is_re_decided_where_the_rate_is_measured(monkeypatch):
    """The import-time policy spins; other processes take the cores later (busy now): the rate is
    re-timed in one thread and at the run's thread count, and the faster is reported with its
    thread count. The work here waits 20 ms whenever it runs on more than one thread (as spinning
    threads stall behind descheduled peers), so one thread must win."""
    import time

    import prt_torch
    import torch
    from prt_torch.harness.timing import rate_policy, torch_threads

    monkeypatch.setattr(prt_torch, "OMP_SPINNING", True)
    monkeypatch.setattr(prt_torch, "busy_now", lambda others=None: True)
    calls = []

    def fn():
        calls.append(torch.get_num_threads())
        if torch.get_num_threads() > 1:
            time.sleep(0.02)

    with torch_threads(2):
        tm, policy = rate_policy(fn, _first(0.02), {"trusted": True, "why_not": []}, repeats=3, warmup=0)
    assert policy["redecided"] and policy["threads"] == 1 and tm.median < 0.01
    assert any("after import" in w for w in policy["why"])
    assert set(policy["candidates"]) == {"2 threads (first)", "1 thread", "2 threads (again)"}
    assert 1 in calls and 2 in calls  # both choices were timed


def test_a_quiet_trusted_rate_is_kept_without_re_timing(monkeypatch):
    import prt_torch
    from prt_torch.harness.timing import rate_policy, torch_threads

    monkeypatch.setattr(prt_torch, "busy_now", lambda others=None: False)
    calls = []
    first = _first(0.001)
    with torch_threads(2):
        tm, policy = rate_policy(lambda: calls.append(1), first, {"trusted": True, "why_not": []})
    assert tm is first and not policy["redecided"] and calls == []


def test_an_untrusted_rate_is_re_measured_even_in_one_thread(monkeypatch):
    import prt_torch
    from prt_torch.harness.timing import rate_policy, torch_threads

    monkeypatch.setattr(prt_torch, "busy_now", lambda others=None: False)
    calls = []
    with torch_threads(1):
        tm, policy = rate_policy(lambda: calls.append(1), _first(5.0), {"trusted": False, "why_not": ["load average 9 > 2 cores"]},
                                 repeats=3, warmup=0)
    assert policy["redecided"] and "load average" in policy["why"][0] and calls
    assert policy["threads"] == 1 and tm.median < 5.0  # the re-measured figure replaced the stretched one


def test_a_re_decided_rate_says_its_thread_count_in_its_cells():
    rec = dict(_rec("pca-vectors2", False), rate_threads=1, rate_policy={"redecided": True, "threads": 1})
    lines = report._records_table([rec])
    row = next(ln for ln in lines if ln.startswith("| pca"))
    assert row.count("⚠ (1 thr)") == 2  # Mvert/s and fps
    assert "re-timed" in " ".join(report._contention_note([rec]))
