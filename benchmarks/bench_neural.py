"""The learned codec (issue 43) against PCA, CPCA and Gaussians under the benchmark harness.

Runs ``prt bench neural`` (prt_torch/configs/neural.yaml: the default benchmark's MRT matrices of
the medium bumpy sphere, and a part on transport tables of the small one, where Green 2005's
Gaussians run) through the harness — the same fit, error metric, lights, views and relighting
clock for every codec — and writes reports/benchmarks/neural.{md,json} and two figures:

* neural_rd.png    PSNR (lights × views, against the uncompressed relight) vs stored bytes per
                   vertex; the neural codec also at its run-time bytes (cached features, hollow);
* neural_speed.png PSNR vs relight time, as the fraction of the uncompressed relight's time (the
                   harness's paired one-thread ratio: the work, which the machine's load does not move;
                   the medians in ms moved by up to 8x with the load of a shared machine).

Every rate is the harness's: paired with the uncompressed relight in the same run (``speed-up``:
the ratio of the two sides' fastest tenths, one thread, CPU time), so a busy machine moves both
sides; the load average before and after is recorded. Encode times (the neural codec's is its
training) are wall-clock of one fit and move with the machine's load.

Run: .venv/bin/python benchmarks/bench_neural.py [--quick] [--no-resume]   (~30-60 min on 2 busy cores;
records are kept under cache/bench_neural/ and a rerun resumes).
"""
from __future__ import annotations

import os

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load, as for any user)

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
from pathlib import Path  # noqa: E402

from prt_torch import io  # noqa: E402
from prt_torch.harness.config import load_config, part_configs  # noqa: E402
from prt_torch.harness.report import LEARNED_PEERS, codec_rows, learned_findings, learned_summary, load_results, plot_learned, where_label  # noqa: E402
from prt_torch.harness.run import run_benchmark  # noqa: E402
from prt_torch.harness.timing import machine_info  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "reports" / "benchmarks"
WORK = ROOT / "cache" / "bench_neural"


#: the labels of the rows an earlier version of this script wrote to neural.json, by part (main: the MRT run)
LEGACY_LABELS = {"main": "MRT, medium bumpy sphere", "glossy": "glossy transfer, small bumpy sphere",
                 "transport": "transport tables, small bumpy sphere"}


def report(res: dict) -> str:
    m = res["machine"]
    lines = [
        "# The learned codec (`neural`, issue 43) against PCA, CPCA and Gaussians",
        "",
        f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']} with {m['torch_threads']} threads. **The machine was shared "
        "with other jobs** (other engineers' tests and benchmarks), so absolute times and encode (training) times are "
        "inflated; the relight column that compares codecs is the harness's paired one-thread ratio against the uncompressed "
        "relight of the same run (the work, which the load does not move). Invocations (load average, 1 min, at start / end):",
        "",
    ]
    lines += [f"- {inv['date']}: {', '.join(inv['runs'])} — load {inv['load_before']:.1f} / {inv['load_after']:.1f}"
              + (f"; overrides {' '.join(inv['overrides'])}" if inv.get("overrides") else "") for inv in res["invocations"]]
    lines += [
        "",
        "Reproduce: `.venv/bin/python benchmarks/bench_neural.py` (every run of the config of `prt bench neural`; "
        "`--part NAME` reruns one part and keeps the other rows of reports/benchmarks/neural.json; outputs under "
        f"cache/bench_neural/; the harness's own report: `{res['run_dir']}/report.md`).",
        "",
        "Settings (configs/neural.yaml): neural latent k ∈ {2, 4, 8} (H = 16 features, 2 hidden layers of 32, SiLU; Adam, "
        "lr 3e-3, minibatches of 512, at most 300 epochs, early stopping on 10% held-out points), k = 4 with float16 codes, "
        "and k = 4 with 16 clusters (one last layer per CPCA cluster); PCA 2-16 vectors; CPCA 16/64 clusters x 2/4/8 "
        "vectors; on the glossy transfer of the scan-like mesh neural k = 2, 4 (and k = 2 with 16 clusters, one whole decoder each), PCA 2-16 and "
        "CPCA 16/64 x 2/4/8; on the transport tables neural k = 4, PCA 4-16 and Gaussians with 1-2 lobes.",
        "",
        "PSNR (lights) is against the harness's reference (`Evaluator.reference`): the uncompressed relight for the MRT and "
        "glossy parts; for the transport tables the exact radiance at each vertex's own view (`Evaluator.exact_transport`: "
        "the table's texels × its stored visibility × the BRDF at the exact view, docs/harness.md), not the tables relit at "
        "three stored views and cross-faded (the reference of transport rows measured before 2026-11-29). rel. SE is the "
        "reconstruction error of the stored transfer itself.",
        "",
        "| part | codec | setting | stored B/vertex | run-time B/vertex | PSNR lights (dB) | rel. SE | relight (ms) | "
        "vs uncompr. | encode (s) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in sorted(res["table"], key=lambda r: (r["part"], r["codec"], r["stored_B_per_vertex"])):
        warn = " ⚠" if r["timing_trusted"] is False else ""
        lines.append(
            f"| {r['part']} | {r['codec']} | {r['setting']} | {r['stored_B_per_vertex']:.1f} | {r['runtime_B_per_vertex']:.1f} | "
            f"{r['psnr_lights_db']:.2f} | {r['relative_se']:.3g} | {r['relight_ms']:.3f} (±{r['relight_spread']:.0%}){warn} | "
            f"{r['speedup_vs_uncompressed']:.2f}x | {r['encode_s']:.1f} |")
    lines += ["", "⚠: the harness measured these rates under contention.", ""]
    lines += ["## Where it wins and where it does not", "",
              "Computed from the table (so only against the peer settings run here): a neural setting wins within a budget "
              "when no setting of another family that fits the budget has a higher PSNR.", ""] + res.get("summary", []) + [
        "", "Per setting (computed from the table: the best of each other family within the neural setting's stored bytes, "
        "its run-time bytes and its relight time):", ""] + res.get("findings", []) + [""]
    if res.get("glsl"):
        lines += ["## GLSL decode vs CPU", "", "The harness renders the best setting of each codec (MRT part, first light and "
                  "view, 256x256, Mesa llvmpipe) decoded in the vertex shader and as the CPU engine's radiance; the neural "
                  "codec's shader is the affine one on the cached features h(z_p) (render.NeuralDecoder). PSNR of GLSL "
                  "against CPU (inf: identical):", "", "| codec | setting | GLSL vs CPU (dB) | same coverage |", "|---|---|---|---|"]
        for k, g in sorted(res["glsl"].items()):
            db = "not decoded: " + str(g["error"]) if g.get("error") else ("inf" if g.get("psnr_db") is None else f"{g['psnr_db']:.1f}")
            lines.append(f"| {k} | {g.get('setting_id') or '(uncompressed)'} | {db} | {'yes' if g.get('same_mask') else 'no'} |")
        lines.append("")
    lines += ["## Figures", ""] + [f"![{f}]({f})" for f in res["figures"]] + [""]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer settings (a smoke run)")
    ap.add_argument("--no-resume", action="store_true")
    ap.add_argument("--part", default=None, help="rerun only this part of the config (e.g. glossy); the other rows are kept "
                    "from reports/benchmarks/neural.json")
    a = ap.parse_args()
    overrides = [f"output_dir={WORK / 'reports'}", f"cache_dir={WORK / 'cache'}"]
    shown = []
    if a.quick:
        q = ["codecs.0.latent=[2]", "codecs.2.clusters=[4]"]
        overrides += q
        shown += q
    cfg = load_config("neural", overrides)
    subs = {s["name"]: s for s in part_configs(cfg)}
    if a.part is not None and a.part not in subs:
        raise SystemExit(f"bench_neural: --part {a.part!r} is not a part of configs/neural.yaml; accepted: {', '.join(subs)}")
    load_before = os.getloadavg()[0]
    peers = ("neural",) + LEARNED_PEERS
    old = json.loads((OUT / "neural.json").read_text()) if a.part and (OUT / "neural.json").is_file() else None
    if a.part:
        run_dir = run_benchmark(subs[a.part], resume=not a.no_resume, progress=False)
        res = load_results(run_dir)
        fresh = {a.part: codec_rows(res, where_label(res), peers)}
    else:
        run_dir = run_benchmark(cfg, resume=not a.no_resume, progress=False)
        res = load_results(run_dir)
        fresh = {"main": codec_rows(res, where_label(res), peers)}
        for p in res.get("parts") or []:
            fresh[p["name"]] = codec_rows(p["results"], where_label(p["results"]), peers)
    for name, rs in fresh.items():
        for r in rs:
            r["run"] = name
    table = [r for rs in fresh.values() for r in rs]
    invocations = []
    if old is not None:  # the rows of the other parts, as measured before
        for r in old["table"]:
            run = r.get("run") or next((k for k, v in LEGACY_LABELS.items() if v == r["part"]), r["part"])
            if run not in fresh and (run == "main" or run in subs):
                table.append({**r, "run": run})
        invocations = old.get("invocations") or [{"date": "earlier", "runs": ["main", "glossy", "transport"],
                                                  "load_before": old["load_before"], "load_after": old["load_after"],
                                                  "overrides": old.get("overrides", [])}]
        invocations = [dict(inv, runs=[x for x in inv["runs"] if x not in fresh]) for inv in invocations]
        invocations = [inv for inv in invocations if inv["runs"]]
    import datetime

    invocations.append({"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "runs": list(fresh),
                        "load_before": load_before, "load_after": os.getloadavg()[0], "overrides": shown})
    out = {"machine": machine_info(), "invocations": invocations, "quick": a.quick, "overrides": shown,
           "run_dir": str(Path(run_dir).relative_to(ROOT)) if str(run_dir).startswith(str(ROOT)) else str(run_dir),
           "table": table}
    out["findings"] = learned_findings(table)
    out["summary"] = learned_summary(table)
    glsl = (old or {}).get("glsl") if a.part else res.get("glsl")
    out["glsl"] = {k: {f: v.get(f) for f in ("setting_id", "psnr_db", "same_mask", "error")} for k, v in (glsl or {}).items()}
    OUT.mkdir(parents=True, exist_ok=True)
    out["figures"] = [plot_learned(table, OUT / "neural_learned.png").name]
    with io.atomic_path(OUT / "neural.json") as tmp:
        Path(tmp).write_text(json.dumps(out, indent=2, default=lambda v: None if isinstance(v, float) and not math.isfinite(v) else str(v)))
    with io.atomic_path(OUT / "neural.md") as tmp:
        Path(tmp).write_text(report(out))
    print(report(out))


if __name__ == "__main__":
    main()
