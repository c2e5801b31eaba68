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
