"""The default report's "Learned vs classic codecs" section (issue 43; harness.report): its rows,
its verdicts within stored bytes, run-time bytes and relight time, checked against hand-made
records whose answers are read off by hand, and its figure."""
from __future__ import annotations

from prt_torch.harness.report import learned_findings, learned_lines, learned_summary, learned_table, learned_verdicts, plot_learned


def rec(codec, sid, bpv, psnr, speedup, runtime_bpv=None, encode=1.0, P=100):
    st = {"points": P}
    if runtime_bpv is not None:
        st["runtime_bytes"] = runtime_bpv * P
    return {"codec": codec, "setting_id": sid, "params": {}, "bytes_per_vertex": bpv, "psnr_lights_db": psnr,
            "speedup_vs_uncompressed": speedup, "relight_s": 1e-3 / speedup, "relight_spread": 0.05, "encode_s": encode,
            "storage": st, "psnr_random_db": psnr, "relative_se": 0.01}


def results():
    main = [rec("neural", "neural-a", 16.0, 34.0, 10.0, runtime_bpv=70.0, encode=12.0),
            rec("pca", "pca-4", 18.0, 24.0, 18.0), rec("pca", "pca-16", 70.0, 35.0, 10.5),
            rec("cpca", "cpca-16x2", 28.0, 33.6, 15.0), rec("cpca", "cpca-16x8", 90.0, 41.6, 11.0),
            rec("vq", "vq-16", 3.0, 15.0, 40.0)]
    part = [rec("neural", "neural-t", 580.0, 25.4, 40.0, runtime_bpv=620.0), rec("gaussian", "gaussian-1", 843.0, 27.9, 31.0),
            rec("pca", "pca-8", 328.0, 24.4, 69.0)]
    r = {"records": main, "transfer": {"kind": "mrt"}, "scene": {"name": "bumpy_sphere", "vertices": 100}}
    p = {"records": part, "transfer": {"kind": "transport"}, "scene": {"name": "bumpy_sphere", "vertices": 50}}
    return {**r, "parts": [{"name": "gaussian", "results": p}]}


def test_rows_are_the_learned_codec_and_its_peers_of_every_run_with_one():
    t = learned_table(results())
    assert {r["codec"] for r in t} == {"neural", "pca", "cpca", "gaussian"}  # no VQ
    assert {r["part"] for r in t} == {"mrt on bumpy_sphere (100 vertices)", "transport on bumpy_sphere (50 vertices)"}
    n = next(r for r in t if r["setting"] == "neural-a")
    assert n["runtime_B_per_vertex"] == 70.0 and n["relight_vs_uncompressed"] == 0.1 and n["encode_s"] == 12.0
    assert learned_table({**results(), "records": results()["records"][1:], "parts": []}) == []  # no neural record: no section


def test_verdicts_within_each_budget():
    v = {x["row"]["setting"]: x["budgets"] for x in learned_verdicts(learned_table(results()))}
    a = v["neural-a"]
    # stored 16 B: nothing of PCA/CPCA fits at <= 16 B -> wins; run-time 70 B: PCA 16 (35.0) and CPCA 16x2 (33.6) -> loses by 1.0
    assert a["stored bytes"]["wins"] and a["stored bytes"]["margin_db"] is None
    assert not a["run-time bytes"]["wins"] and abs(a["run-time bytes"]["margin_db"] + 1.0) < 1e-9
    # relight 0.1 of the uncompressed: PCA 16 (1/10.5), CPCA 16x8 (1/11) fit; CPCA 16x8's 41.6 -> loses by 7.6
    assert not a["relight time"]["wins"] and abs(a["relight time"]["margin_db"] + 7.6) < 1e-9
    t = v["neural-t"]
    # stored 580 B: PCA 8 (24.4) fits, Gaussian (843 B) does not -> wins by 1.0; relight 1/40: PCA 8's 1/69 fits,
    # Gaussian's 1/31 does not -> wins by 1.0 again
    assert t["stored bytes"]["wins"] and abs(t["stored bytes"]["margin_db"] - 1.0) < 1e-9
    assert [b["setting"] for b in t["relight time"]["best"]] == ["pca-8"]
    assert t["relight time"]["wins"] and abs(t["relight time"]["margin_db"] - 1.0) < 1e-9


def test_section_lines_and_figure(tmp_path):
    t = learned_table(results())
    lines = learned_lines(t, "learned.png")
    assert lines[0] == "## Learned vs classic codecs" and "![learned](learned.png)" in lines
    rows = [ln for ln in lines if ln.startswith("| mrt on") or ln.startswith("| transport on")]
    assert len(rows) == len(t) == 8
    assert any("neural-a" in ln and "| 16.0 | 70.0 |" in ln and "| 0.100 |" in ln and "| 12 |" in ln for ln in rows)
    summ = learned_summary(t)
    assert len(summ) == 2 and "1 win at equal stored bytes (neural-a)" in summ[0] and "0 win at equal relight time" in summ[0]
    f = learned_findings(t)
    assert len(f) == 2 and "**loses** by 7.60 dB" in f[0] and "wins (nothing else fits)" in f[0]
    assert learned_lines([]) == []
    path = plot_learned(t, tmp_path / "learned.png")
    assert path.is_file() and path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
