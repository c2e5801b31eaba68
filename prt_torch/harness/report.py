"""Result files of a benchmark run and the pictures made from them.

reports/<run>/
  results.json     one record per codec setting + run context (schema: docs/harness.md)
  results.csv      the scalar columns of the records, one row per setting
  report.md        PSNR / fps tables, the target search, links to the figures
  rd.png           rate–distortion: PSNR vs bytes per vertex, one line per codec
  speed_accuracy.png  relighting fps vs PSNR, Pareto front marked
  renders/         uncompressed vs best setting of each codec, with error heat maps (made by
                   harness.renders in the run step; this module only links them)
  records/         one JSON per finished setting and its encoding as a codec file (what makes
                   a run resumable)

This module reads results (a plain dict, or a results.json) and writes files; it never fits,
relights or renders.
"""
from __future__ import annotations

import csv
import io as _io
import json
import math
from pathlib import Path
from typing import Any, Callable

from .. import io
from ..shrm import CONVEX_PROBE_TOL

__all__ = ["write_outputs", "pareto_front", "plot_results", "CSV_COLUMNS", "load_results", "PLOT_FILES", "convex_lines",
           "codec_rows", "learned_table", "learned_findings", "learned_summary", "learned_verdicts", "learned_lines", "plot_learned", "where_label"]

#: the files :func:`plot_results` writes into its directory
PLOT_FILES = ("rd.png", "speed_accuracy.png")

CSV_COLUMNS = [
    "setting_id", "codec", "params", "encode_s", "bytes_total", "bytes_per_vertex", "compression_ratio",
    "sloan_cost_floats", "se", "relative_se", "psnr_random_db", "psnr_random_closed_form_db", "psnr_lights_db",
    "psnr_lights_min_db", "relight_s", "relight_spread", "vertices_per_s", "fps", "speedup_vs_uncompressed", "speedup_spread", "fraction_of_bound",
    "fraction_of_bound_cold",
    "timing_trusted",
]


def load_results(path: str | Path) -> dict:
    """Read a results.json (or the run directory holding one)."""
    p = Path(path)
    if p.is_dir():
        p = p / "results.json"
    if not p.is_file():
        raise FileNotFoundError(f"no results file at {str(p)!r}; accepted: a results.json or a reports/<run>/ directory")
    try:
        data = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{str(p)!r} is not valid JSON ({e})") from None
    if data.get("format") != "prt_torch.results":
        raise ValueError(f"{str(p)!r} is not a prt_torch results file (format={data.get('format')!r})")
    # what the tables and plots read, checked here (a hand-made or truncated file reached a KeyError before)
    missing = [k for k in ("name", "records") if k not in data]
    if missing or not isinstance(data.get("records"), list):
        raise ValueError(f"{str(p)!r} lacks {', '.join(missing) or 'a list of records'}; accepted: a results.json written by prt bench")
    need = ("setting_id", "codec", "bytes_per_vertex", "psnr_lights_db", "fps")
    for i, r in enumerate(data["records"]):
        gone = [k for k in need if not isinstance(r, dict) or k not in r]
        if gone:
            raise ValueError(f"{str(p)!r}: records[{i}] lacks {', '.join(gone)}; accepted: a results.json written by prt bench")
    return data


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points not dominated when maximising both coordinates."""
    idx = []
    for i, (a, b) in enumerate(points):
        if not any((c >= a and d >= b) and (c > a or d > b) for j, (c, d) in enumerate(points) if j != i):
            idx.append(i)
    return idx


def _stored(r: dict) -> str:
    """What a transfer's raw size counts: a wavelet transfer's stored sparse bytes, else float32."""
    return "stored, sparse" if r["transfer"]["kind"] == "wavelet" else "float32"


def _fmt(v: Any, digits: int = 3) -> str:
    if isinstance(v, float):
        if math.isinf(v):
            return "∞"
        if v != 0 and (abs(v) >= 1e5 or abs(v) < 1e-3):
            return f"{v:.{digits - 1}e}"
        return f"{v:.{digits}g}" if abs(v) < 100 else f"{v:.1f}"
    return str(v)


def _params(p: dict) -> str:
    return ", ".join(f"{k}={v}" for k, v in p.items()) or "–"


def write_csv(path: Path, records: list[dict]) -> None:
    buf = _io.StringIO()
    w = csv.writer(buf)
    w.writerow(CSV_COLUMNS)
    for r in records:
        w.writerow([json.dumps(r["params"], sort_keys=True) if c == "params" else r.get(c) for c in CSV_COLUMNS])
    io.atomic_write_text(path, buf.getvalue())


def _by_codec(res: dict) -> list[tuple[str, list[dict]]]:
    by: dict[str, list[dict]] = {}
    for r in res["records"]:
        by.setdefault(r["codec"], []).append(r)
    return sorted(by.items())


def _save_figure(fig, path: Path) -> Path:
    import matplotlib.pyplot as plt

    with io.atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)
    return path


def plot_results(results_list: list[dict], out_dir: Path, labels: list[str] | None = None) -> list[Path]:
    """Rate–distortion and speed–accuracy plots of one or more result sets (``prt plot``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    labels = labels or [r["name"] for r in results_list]
    paths = []
    markers = "osD^v<>p*h"
    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    for ri, (res, lab) in enumerate(zip(results_list, labels)):
        for ci, (codec, rs) in enumerate(_by_codec(res)):
            rs = sorted(rs, key=lambda r: r["bytes_per_vertex"])
            ys = [min(r["psnr_lights_db"], 120.0) for r in rs]
            ax.plot([r["bytes_per_vertex"] for r in rs], ys, marker=markers[ci % len(markers)],
                    linestyle="-" if ri == 0 else "--", label=f"{codec}" + (f" ({lab})" if len(results_list) > 1 else ""))
        unc = res.get("uncompressed", {})
        if unc and ri == 0:
            ax.axvline(unc["bytes_per_vertex"], color="grey", linestyle=":", label="uncompressed size")
    ax.set_xscale("log")
    ax.set_xlabel("bytes per vertex")
    ax.set_ylabel("PSNR vs uncompressed, lights × views (dB)")
    ax.set_title("Rate–distortion")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(_save_figure(fig, out_dir / PLOT_FILES[0]))

    fig, ax = plt.subplots(figsize=(6.4, 4.4))
    allpts = []
    for ri, (res, lab) in enumerate(zip(results_list, labels)):
        for ci, (codec, rs) in enumerate(_by_codec(res)):
            xs = [min(r["psnr_lights_db"], 120.0) for r in rs]
            ys = [r["fps"] for r in rs]
            allpts += list(zip(xs, ys))
            ax.scatter(xs, ys, marker=markers[ci % len(markers)], label=codec + (f" ({lab})" if len(results_list) > 1 else ""))
        unc = res.get("uncompressed", {})
        if unc and ri == 0:
            ax.axhline(unc["fps"], color="grey", linestyle=":", label="uncompressed relight")
    front = sorted((allpts[i] for i in pareto_front(allpts)), key=lambda t: t[0])
    if front:
        ax.plot([f[0] for f in front], [f[1] for f in front], color="black", linewidth=1, label="Pareto front")
    ax.set_yscale("log")
    ax.set_xlabel("PSNR vs uncompressed (dB)")
    ax.set_ylabel("relighting frames/s (whole mesh, CPU)")
    ax.set_title("Speed–accuracy")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    paths.append(_save_figure(fig, out_dir / PLOT_FILES[1]))
    return paths


def _config_arg(r: dict) -> str:
    """How a user names this run's config: a packaged config's name, else the file path."""
    src = r.get("config_source")
    if not src:
        return r["name"]
    p = Path(src)
    return p.stem if p.parent.name == "configs" else str(p)


def scene_required(results: dict) -> list[str]:
    """Markdown lines: the precompute's automatic decisions (shadows traced or skipped, bounces
    used, 'auto' parameters with the energy they keep) from ``results['transfer']['meta']``."""
    m = results["transfer"].get("meta") or {}
    items = []
    if m.get("shadow_decision"):
        items.append(f"shadows: {m['shadow_decision']}")
    if "bounces_used" in m or m.get("bounce_decision"):
        items.append(f"bounces: {m.get('bounces_used', 0)} used" + (f" ({m['bounce_decision']})" if m.get("bounce_decision") else ""))
    elif "bounces" in m:
        items.append(f"bounces: {m['bounces']}")
    for k, d in (m.get("auto") or {}).items():
        if d.get("energy_kept") is not None:  # bands, bands_out, M, the wavelet res: an energy target (None: no lights)
            items.append(f"{k} = {d['value']} (auto): keeps {d['energy_kept']:.4f} of the energy, target {d['target']:g} — {d['reason']}")
        else:  # the transport res: a lobe-width rule (transfer.transport.choose_cube_res)
            items.append(f"{k} = {d['value']} (auto): {d['reason']}")
    for k in ("bands", "bands_out", "M"):
        if k in m and k not in (m.get("auto") or {}):
            items.append(f"{k} = {m[k]} (as configured)")
    if not items:
        return []
    return ["## What the scene required", ""] + [f"- {x}" for x in items] + [""]


def _bound(x: dict) -> str:
    """Fraction of the setting's own memory-bandwidth bound (1 = at the bound)."""
    return f"{x['fraction_of_bound']:.2f}" if "fraction_of_bound" in x else "–"


def _bound_cold(x: dict) -> str:
    """The same fraction from cold caches (the memory-bandwidth bound proper)."""
    return f"{x['fraction_of_bound_cold']:.2f}" if "fraction_of_bound_cold" in x else "–"


def _speedup(x: dict) -> str:
    """'2.41× (±8%)', with ⚠ when the paired timing saw contention (harness.timing.measure_paired)."""
    out = f"{_fmt(x['speedup_vs_uncompressed'])}×"
    if "speedup_spread" in x:
        out += f" (±{x['speedup_spread']:.0%})"
    if x.get("timing_trusted") is False:
        out += " ⚠"
    return out


def _contention_note(records: list[dict]) -> list[str]:
    bad = [r for r in records if r.get("timing_trusted") is False]
    if not bad:
        return []
    why = sorted({w for r in bad for w in r.get("contention", {}).get("why_not", [])})[:4]
    redone = sum(1 for r in bad if (r.get("rate_policy") or {}).get("redecided"))
    return [f"⚠ {len(bad)} of {len(records)} settings were timed under contention ({'; '.join(why)}): their rates are "
            "not to be trusted; their speed-ups, paired ratios of interleaved samples, are more robust but wider."
            + (f" {redone} of them were re-timed when the contention was seen, in one thread and at the run's thread count "
               "(spinning OpenMP threads stall when other processes take the cores after import; harness.timing.rate_policy): "
               "their Mvert/s and fps are the faster, with the thread count in the cell." if redone else ""), ""]


def executor_lines(res: dict) -> list[str]:
    """Where the settings ran (``prt bench --executor``) and the settings that failed there."""
    ex = res.get("executor") or {}
    out: list[str] = []
    if ex.get("executor", "local") != "local":
        out += [f"Executor: {ex['executor']} ({ex.get('address', '')}, {ex.get('parallelism', '?')} task slots): settings ran "
                "concurrently, so their absolute rates (Mvert/s, fps) are contended; compare the paired speed-ups "
                "(vs uncompr.), which are timed back to back inside each task. Errors, bytes and PSNR do not depend on it.", ""]
    fails = res.get("failures") or []
    if fails:
        out += [f"## Failed settings ({len(fails)})", "", "Each failed on every attempt; the other settings finished. "
                "Run the same command again to retry only these.", "", "| setting | attempts | error |", "|---|---|---|"]
        out += [f"| {f['setting_id']} | {f['attempts']} | {str(f['error']).replace('|', '/')} |" for f in fails] + [""]
    return out


def _setting(x: dict) -> str:
    """A record's parameters, led by its ablation value when it has one."""
    a = x.get("ablation")
    lead = f"**{a['key'].split('.')[-1]}={a['value']}**" if a and a["key"].startswith("transfer.") else ""
    return ", ".join(p for p in (lead, _params(x["params"])) if p)


def ablation_lines(res: dict) -> list[str]:
    """Markdown of an ablation: the swept key, and for a transfer key what each value costs and
    how far its uncompressed result is from the reference value's."""
    a = res["ablation"]
    out = ["## Ablation", "", f"Swept `{a['key']}` over {a['values']}; every record carries `ablation: {{key, value}}`.", ""]
    if a["key"].startswith("transfer."):
        out += [f"Model PSNR: the uncompressed radiance of each value against that of `{a['key'].split('.')[-1]}="
                f"{a['reference_value']}` (the reference), over the same lights × views — what the modelling choice costs "
                "before any compression.", "",
                "| value | transfer | B/vertex (raw) | precompute (s) | rays | model PSNR (dB) | uncompressed Mvert/s | decisions |",
                "|---|---|---|---|---|---|---|---|"]
        for p in a["per_value"]:
            d = p.get("decisions", {})
            dec = "; ".join(str(d[k]) for k in ("shadow_decision", "bounce_decision") if k in d)
            out.append(f"| {p['value']} | {tuple(p['transfer_shape'])} | {p['raw_bytes_per_vertex']:.0f} | {_fmt(p['precompute_s'])} | "
                       f"{p['rays_traced']} | {_fmt(p['model_psnr_db'])} | {p['uncompressed']['vertices_per_s'] / 1e6:.2f} | {dec or '–'} |")
        out.append("")
    return out


def _ms(x: float) -> str:
    return f"{x * 1e3:.3f} ms"


def trade_lines(t: dict) -> list[str]:
    """The all-frequency trade of a wavelet transfer (harness.trade): the headline "relight time
    to reach 5% and 1% error, SH vs wavelets" per light, then every row."""
    loop = t.get("timed") == "render_loop"  # results before it timed the plain call
    rel = "render loop" if loop else "relight"
    L = ["## SH vs wavelets: the all-frequency trade", "",
         f"Each light cut to N Haar terms ({t['selection']} selection; R = {t['res']}, the stored transfer, "
         f"{t['bytes_per_vertex']} B/vertex) and SH at n bands projected from the same visibility (n² floats per vertex, "
         "3n² for a coloured transfer), "
         "each against the exact result (every term of the light): relative L2 over vertices and RGB; only a light's "
         "nonzero Haar terms are selected (above `haar.ZERO_TERM` of its largest), so an N past them keeps them all, "
         "once: one row, marked 'all nonzero'. Times: "
         f"{'one thread, ' if t.get('threads') == 1 else ''}median per relight in one process"
         + (", in the render-loop form a user's loop calls (wavelets: `WaveletRelighter.prepared`, the form the kernel "
            "report times; SH: the product into a reused output), the plain call (the relighter or `relight.diffuse` "
            "called with the light: its per-call checks and conversions) in its own column"
            if loop else ", the plain call (the relighter called with the light)")
         + f"; SH/wavelet: the two settings timed paired in this run{' (render-loop forms)' if loop else ''}"
         f"{' in one thread by its CPU time' if t.get('ratio_clock') == 'thread_time' else ''} "
         "(> 1: wavelets faster; ⚠: contention).", ""]
    sc = t.get("stored_check") or {}
    if sc:  # what the exact result above itself costs: the stored transfer against all 6R² terms
        L += [("Stored vs all terms: the stored transfer (its K terms, quantised) against its full pixel-basis transfer "
               f"(all 6R² terms, traced again) on {sc['vertices']} vertices, under each light — the floor every row "
               "above sits on, which the errors above (against the stored transfer) do not include."
               if "vertices" in sc else f"Stored vs all terms: not measured ({sc['skipped']})."), ""]
    L += [f"| light | SH to 5% ({rel}) | wavelets to 5% ({rel}) | SH/wavelet | SH to 1% ({rel}) | wavelets to 1% ({rel}) "
          "| SH/wavelet | best SH | best wavelets | stored vs all terms |",
          "|---|---|---|---|---|---|---|---|---|---|"]
    for h in t["headline"]:
        cells = [h["light"]]
        for tgt in (0.05, 0.01):
            s, w, q = h.get(f"sh_{tgt}"), h.get(f"wavelet_{tgt}"), h.get(f"ratio_{tgt}")
            cells.append("not reached" if s is None else f"{s['bands']} bands, {_ms(s['relight_s'])}")
            cells.append("not reached" if w is None else f"N={w['N']}, {_ms(w['relight_s'])}")
            cells.append(f"{q['sh_over_wavelet']:.2f}{'' if q['trusted'] else ' ⚠'}" if q else "—")
        cells += [f"{h['sh_best_error']:.4f}", f"{h['wavelet_best_error']:.4f}",
                  "—" if h.get("stored_error") is None else f"{h['stored_error']:.4f}"]
        L.append("| " + " | ".join(cells) + " |")
    if loop:
        L += ["", "| light | method | N or bands | error | relight (render loop) | fps (render loop) | plain call | B/vertex |",
              "|---|---|---|---|---|---|---|---|"]
    else:
        L += ["", "| light | method | N or bands | error | relight | fps | B/vertex |", "|---|---|---|---|---|---|---|"]
    for x in t["rows"]:
        size = x["N"] if x["method"] == "wavelet" else x["bands"]
        if x["method"] == "wavelet" and x.get("terms_requested", x["N"]) > x["N"]:  # the light has no more nonzero terms
            size = f"{x['N']} (all nonzero; {x['terms_requested']} asked)"
        call = f" {_ms(x['call_s'])} |" if loop else ""
        L.append(f"| {x['light']} | {x['method']} | {size} | {x['error']:.4f} | {_ms(x['relight_s'])} | {x['fps']:.0f} |"
                 f"{call} {x['bytes_per_vertex']} |")
    return L + [""]


def light_labels(specs: list[str], width: int = 28) -> list[str]:
    """Short legend labels for light specs, distinct where the specs are: a spec up to ``width``
    characters as is; a longer analytic one as its type and the parameters that tell it from the
    other lights of its type (``cap half_angle_deg=0.5``); a path as its file name; what is still
    too long cut to ``width``, and any label still shared numbered (``#2``)."""
    from pathlib import PurePath

    from ..lighting.spec import parse_light_spec

    def parsed(s: str) -> dict | None:
        try:
            return parse_light_spec(s)
        except ValueError:
            return None

    ps = [parsed(s) for s in specs]
    out = []
    for s, d in zip(specs, ps):
        if len(s) <= width:
            out.append(s)
        elif d is not None:
            same = [e for e in ps if e is not None and e.get("type") == d.get("type")]
            keys = [k for k in d if k != "type" and any(e.get(k) != d.get(k) for e in same)]
            out.append(" ".join([str(d["type"])] + [f"{k}={_spec_value(d[k])}" for k in keys]))
        else:
            out.append(PurePath(s).name)
    out = [x if len(x) <= width else x[:width - 1] + "…" for x in out]
    counts = {x: out.count(x) for x in out}
    seen: dict[str, int] = {}
    for i, x in enumerate(list(out)):
        seen[x] = seen.get(x, 0) + 1
        if counts[x] > 1:
            out[i] = f"{x} #{seen[x]}"
    return out


def _spec_value(v) -> str:
    return ",".join(f"{x:g}" for x in v) if isinstance(v, (list, tuple)) else (f"{v:g}" if isinstance(v, float) else str(v))


def plot_trade(t: dict, out_dir: Path) -> Path:
    """trade.png: error vs terms (N light terms; n² SH coefficients) and error vs relight time, per light."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(11.0, 4.2))
    names = light_labels([h["light"] for h in t["headline"]])
    for i, h in enumerate(t["headline"]):
        w = [x for x in t["rows"] if x["light"] == h["light"] and x["method"] == "wavelet"]
        s = [x for x in t["rows"] if x["light"] == h["light"] and x["method"] == "sh"]
        c = f"C{i % 10}"
        ax[0].loglog([x["N"] for x in w], [max(x["error"], 1e-6) for x in w], "-o", color=c, label=f"{names[i]} wavelets")
        ax[0].loglog([x["bands"] ** 2 for x in s], [max(x["error"], 1e-6) for x in s], "--s", color=c, label="SH")
        ax[1].loglog([x["relight_s"] * 1e3 for x in w], [max(x["error"], 1e-6) for x in w], "-o", color=c)
        ax[1].loglog([x["relight_s"] * 1e3 for x in s], [max(x["error"], 1e-6) for x in s], "--s", color=c)
    ax[0].set_xlabel("terms (wavelets: N; SH: n²)")
    ax[1].set_xlabel("relight time (ms)")
    for a in ax:
        a.set_ylabel("relative L2 error vs exact (drawn ≥ 1e-6)")
        for y in (0.05, 0.01):
            a.axhline(y, color="grey", lw=0.5)
    ax[0].legend(fontsize=6)
    fig.tight_layout()
    return _save_figure(fig, Path(out_dir) / "trade.png")


def plot_ablation(res: dict, out_dir: Path) -> Path:
    """ablation.png: PSNR (each codec setting, and for transfer keys the model PSNR) and
    relighting rate across the swept values."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    a = res["ablation"]
    labels = [str(v) for v in a["values"]]
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10.0, 4.2))
    lines: dict[str, dict] = {}
    for r in res["records"]:
        if r.get("ablation") is None:
            continue
        name = f"{r['codec']} {_params(r['params'])}" if a["key"].startswith("transfer.") else r["codec"]
        lines.setdefault(name, {})[str(r["ablation"]["value"])] = r
    for name, by in sorted(lines.items()):
        xs = [i for i, v in enumerate(labels) if v in by]
        ax1.plot(xs, [min(by[labels[i]]["psnr_lights_db"], 120.0) for i in xs], marker="o", label=name)
        ax2.plot(xs, [by[labels[i]]["fps"] for i in xs], marker="o", label=name)
    if a["key"].startswith("transfer."):
        ax1.plot(range(len(labels)), [min(p["model_psnr_db"], 120.0) for p in a["per_value"]], color="black", linestyle="--",
                 marker="s", label=f"uncompressed vs {a['reference_value']}")
        ax2.plot(range(len(labels)), [p["uncompressed"]["fps"] for p in a["per_value"]], color="black", linestyle="--",
                 marker="s", label="uncompressed")
    for ax, yl in ((ax1, "PSNR (dB)"), (ax2, "relighting frames/s")):
        ax.set_xticks(range(len(labels)), labels)
        ax.set_xlabel(a["key"])
        ax.set_ylabel(yl)
        ax.grid(True, alpha=0.3)
    ax2.set_yscale("log")
    ax1.legend(fontsize=7)
    fig.suptitle(f"Ablation of {a['key']}")
    fig.tight_layout()
    return _save_figure(fig, out_dir / "ablation.png")


def target_lines(t: dict) -> list[str]:
    """Markdown of a cross-family target search (harness.target.search_families)."""
    what = "fewest bytes per vertex" if t["by"] == "bytes" else "highest relighting rate"
    out = ["## Cheapest setting meeting the target", "",
           f"Target {t['goal_db']} dB ({t['metric']}), cheapest = {what}; search cost {t['evaluated']} evaluations "
           f"({t['distinct_settings']} distinct settings), {t['seconds']:.1f} s.", ""]
    if t["met"]:
        w = t["winner"]
        out += [f"**Winner: {w['setting_id']}** — {w['achieved_db']:.2f} dB at {w['bytes_per_vertex']:.1f} B/vertex, "
                f"{w['fps']:.0f} fps.", ""]
    else:
        out += [f"**Not met**: {t['note']}.", ""]
    out += ["| family | size axes | evaluated | cheapest setting meeting the target | dB | B/vertex | fps |", "|---|---|---|---|---|---|---|"]
    for name, f in t["families"].items():
        if not f.get("searched"):
            out.append(f"| {name} | – | 0 | {f['note']} | | | |")
        elif f.get("best"):
            b = f["best"]
            out.append(f"| {name} | {' × '.join(f['axes'])} | {f['evaluated']} | {_params(b['params'])} | {b['achieved_db']:.2f} | "
                       f"{b['bytes_per_vertex']:.1f} | {b['fps']:.0f} |")
        else:
            out.append(f"| {name} | {' × '.join(f['axes'])} | {f['evaluated']} | none: {f['note']} | | | |")
    return out + [""]


def markdown(results: dict, figures: list[str], renders: list[str]) -> str:
    r = results
    m = r["machine"]
    unc = r["uncompressed"]
    lines = [
        f"# Benchmark `{r['name']}`",
        "",
        f"Scene **{r['scene']['name']}** ({r['scene']['vertices']} vertices), transfer **{r['transfer']['kind']}** "
        f"{tuple(r['transfer']['shape'])} ({r['transfer']['raw_bytes'] / 2**20:.2f} MiB {_stored(r)}), "
        f"lights: {', '.join(r['lights'])}; {max(1, len(r['views']))} view(s).",
        f"Machine: {m['cpu']}, {m['cores']} cores, torch {m['torch']} with {m['torch_threads']} threads, "
        f"load average {m.get('load_average_1min', float('nan')):.1f} at the start"
        + (" — **busy machine: throughput figures are unreliable**." if m.get("load_average_1min", 0) > (m.get("cores") or 1) else "."),
        f"Reproduce: `prt bench {_config_arg(r)}` (the fully resolved config is recorded in results.json).",
        "",
        f"Uncompressed relighting (the peer): {unc['vertices_per_s'] / 1e6:.2f} M vertices/s, {unc['fps']:.1f} fps "
        f"(spread {unc['relight_spread']:.0%}), {unc['bytes_per_vertex']:.0f} B/vertex.",
        "",
        "## PSNR / fps",
        "",
        ("PSNR (lights) is against the exact radiance at each vertex's own view (the texels' visibility " + unc["visibility"] + "; not the tables "
         "relit at the three tapped views and cross-faded, the peer above: Evaluator.reference, docs/harness.md)"
         if "visibility" in unc else "PSNR (lights) is against the uncompressed result")
        + ", averaged over lights × views; PSNR (rand) is MRT eq. 11 over "
        "random norm-1 lighting vectors (Monte Carlo; closed form in results.json). Throughput: median of repeats after "
        "warm-up; spread = IQR/median; speed-up = the uncompressed relighting's time over the codec's, from 40 pairs of short, "
        "equal-length samples timed back to back (interleaved, same run) in one thread and in its CPU time, the ratio of each "
        "side's fastest tenth — "
        "the ratio of the work, which other processes taking the cores or OpenMP's wait policy do not move (measured: "
        "reports/benchmarks/timing_trust.md; the same ratio at the process's thread count is `speedup_parallel` in "
        "results.json); ± = the spread of per-pair ratios; ⚠ = measured under contention. "
        "Of bound: the time of reading the encoded data (and the view) once and writing the output once (a copy_ and a fill_ "
        "of those byte counts, paired in the same run) over the relighting time — 1 is at the bound. Timed back to back, both "
        "sides keep their data in the caches, so at these sizes that is a cache-bandwidth bound; cold: the same pair with each "
        "call timed alone after evicting the caches (harness.timing.measure_paired_cold) — the memory-bandwidth bound.",
        "",
    ]
    if r["records"]:
        lines += _records_table(r["records"])
    else:  # codecs: [] (a wavelet run's trade, below): no table, no front, no empty plots
        lines = lines[:lines.index("## PSNR / fps")] + [
            "## PSNR / fps", "", "No codec settings in this run (`codecs: []`): nothing compressed to compare with the peer "
            "above" + (" (the trade below compares the light's approximations)." if r.get("trade") else "."), ""]
    lines += _contention_note(r["records"])
    lines += runtime_lines(r["records"])
    for part in r.get("parts") or []:
        lines += part_lines(part)
    lines += learned_lines(learned_table(r), LEARNED_PLOT if LEARNED_PLOT in figures else None)
    lines += executor_lines(r)
    lines += scene_required(r)
    if r.get("validation"):
        v = r["validation"]
        lines += ["## Validation against Mitsuba 3", ""]
        lines += (["Engine vs an independent path tracer (prt_torch.validate, docs/validate.md), no scale fit:", "", "```",
                   v["text"], "```", ""] if "text" in v else [f"Not run: {v['skipped']}", ""])
    if r.get("convex"):
        lines += convex_lines(r["convex"], r.get("machine"))
    if r.get("ablation"):
        lines += ablation_lines(r)
    if r.get("trade"):
        lines += trade_lines(r["trade"])
    t = r.get("target")
    if t and t.get("mode") == "families":
        lines += target_lines(t)
    elif t:
        lines += ["## Smallest setting meeting the target", ""]
        if t["met"]:
            lines.append(f"{t['codec']}: {t['param']}={t['value']} reaches {t['achieved_db']:.2f} dB ≥ {t['goal_db']} dB "
                         f"({t['metric']}) at {t['bytes_per_vertex']:.1f} B/vertex; evaluated {t['param']} ∈ {t['evaluated']}.")
        else:
            lines.append(f"{t['codec']}: not met — {t['note']}.")
        lines.append("")
    if figures:
        lines += ["## Plots", ""] + [f"![{Path(f).stem}]({f})" for f in figures if f != LEARNED_PLOT] + [""]
    if renders:
        lines += ["## Renders", "", "Left to right: uncompressed, compressed, |error| heat map (first light, first view).", ""]
        lines += [f"![{Path(f).stem}]({f})" for f in renders] + [""]
    if r.get("glsl"):  # harness.renders: every run re-validates the GLSL decoders against the CPU engine
        lines += ["## GLSL decode vs CPU", "", "Each best setting rendered decoded in the vertex shader and as the CPU engine's "
                  "per-vertex radiance (same camera, same coverage required); PSNR of GLSL against CPU (inf = identical). "
                  "GLSL fps: per-light constants, upload, draw and float read-back on the run's GL renderer (Mesa "
                  "llvmpipe without a GPU); CPU fps: the run's relighting rate of the same setting.", "",
                  "| codec | setting | GLSL vs CPU | same coverage | GLSL fps | CPU relight fps |", "|---|---|---|---|---|---|"]
        for name, g in sorted(r["glsl"].items()):
            if "error" in g:
                lines.append(f"| {name} | {g.get('setting_id', '')} | not decoded in GLSL: {g['error']} | | | |")
                continue
            db = "inf" if g.get("psnr_db") is None else f"{g['psnr_db']:.1f}"
            cpu = _fmt(g["cpu_fps"]) if g.get("cpu_fps") is not None else _fmt(unc["fps"])
            lines.append(f"| {name} | {g.get('setting_id', '(uncompressed)')} | GLSL vs CPU: {db} dB | "
                         f"{'yes' if g['same_mask'] else 'NO'} | {g['glsl_fps']:.1f} | {cpu} |")
        lines.append("")
    return "\n".join(lines)


def convex_lines(c: dict, machine: dict | None = None) -> list[str]:
    """The convex-objects section (config ``convex``, :mod:`prt_torch.harness.convex`): SHRM vs
    unshadowed glossy PRT per mesh — PSNR against the brute-force reference (all facing vertices and
    grazing ones), the most negative radiance, bytes, precompute and per-frame time."""
    b = c["brdf"]
    bp = ", ".join(f"{k} = {v}" for k, v in b.items() if k not in ("type", "model") and not isinstance(v, (dict, list)))
    lines = [
        "## Convex objects: SHRM vs unshadowed glossy PRT", "",
        f"One BRDF ({b.get('type', b.get('model', '?'))}{', ' + bp if bp else ''}) under one light (`{c['light']}`, "
        f"{c['light_pixels'][0]}×{c['light_pixels'][1]} pixels), {c['views']} camera(s) per mesh. Reference: per vertex, Σ over "
        "the environment's pixels of L f_r max(n·ω, 0) Ω (no SH, no visibility: `shrm.reference_radiance`). SHRM "
        "(Ramamoorthi 2002 ch. 5): orders from ε (eq. 5.18), frequency-space prefilter, "
        f"{c['map_height']}×{2 * c['map_height']} maps, radiance by map lookup; files in `{c.get('dir', 'convex')}/`. "
        "Glossy PRT (Sloan 2003 §3.1): this run's glossy transfer with shadows never, relit by the harness's "
        "uncompressed path. PSNR over the vertices facing each camera (n·v > 0.02), peak = the reference's maximum, mean "
        "over cameras; clamped: the radiance clamped at 0 first (radiance is never negative; what `prt render` shows); grazing: "
        "0.02 < n·v < cos 75° only; min: the most negative radiance (truncation ringing).", "",
        "| mesh | vertices (facing, grazing) | method | orders / bands | PSNR vs reference | clamped ≥ 0 | grazing PSNR | min radiance "
        "| bytes | bytes / vertex | precompute (s) | per frame (ms) |",
        "|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in c["rows"]:
        p = r["prt"]
        for k, s_ in enumerate(r["shrm"]):
            head = f"| {r['mesh']} | {r['vertices']} ({r['facing']}, {r['grazing']})" if k == 0 else "| |"
            lines.append(f"{head} | SHRM ε = {s_['epsilon']:g} | F_B={s_['F_B']}, P_B={s_['P_B']} | {s_['psnr_db']:.1f} dB | "
                         f"{s_['psnr_clamped_db']:.1f} dB | {s_['psnr_grazing_db']:.1f} dB | {s_['min_radiance']:.3g} | "
                         f"{s_['bytes']} | {s_['bytes_per_vertex']:.0f} | "
                         f"{s_['precompute_s']:.2f} | {1e3 * s_['frame_s']:.2f} |")
        lines.append(f"| | | glossy PRT | n = {p['bands']}, m = {p['bands_out']}, {p['samples']} samples | {p['psnr_db']:.1f} dB | "
                     f"{p['psnr_clamped_db']:.1f} dB | "
                     f"{p['psnr_grazing_db']:.1f} dB | {p['min_radiance']:.3g} | {p['bytes']} | {p['bytes_per_vertex']:.0f} | "
                     f"{p['precompute_s']:.2f} ({p['cache']}) | {1e3 * p['frame_s']:.2f} |")
    cpu = f" on {machine['cpu']}" if machine else ""
    load = f", load {machine.get('load_average_1min', float('nan')):.1f}" if machine else ""
    lines += [
        "",
        "Self-occlusion probe (share of the diffuse energy shadowed; none of the three has visibility, so only a convex "
        "mesh compares them fairly): " + "; ".join(
            f"{r['mesh']} {r['occluded_fraction']:.2g}" + (" ⚠ not convex" if r["occluded_fraction"] > CONVEX_PROBE_TOL else "")
            for r in c["rows"] if "occluded_fraction" in r) + ".",
        "",
        f"Per frame: the radiance of every vertex for the first camera, timed interleaved with the PRT relighting in one "
        f"thread and its CPU time (median of per-pair ratios{cpu}{load}; ⚠ = contention seen). PRT time / SHRM time: "
        + "; ".join(f"{r['mesh']} " + ", ".join(f"ε {x['epsilon']:g}: {x['frame_ratio_prt_over_shrm']:.2f}×"
                                               + ("" if x["trusted"] else " ⚠") for x in r["shrm"]) for r in c["rows"])
        + ". SHRM against PRT: " + "; ".join(f"{r['mesh']} " + ", ".join(f"ε {x['epsilon']:g}: {x['vs_prt_psnr_db']:.1f} dB"
                                                                      for x in r["shrm"]) for r in c["rows"]) + ".",
        "",
        "The SHRM is one set of maps per BRDF and light, for any convex object (its bytes do not grow with the mesh; its "
        "precompute is shared by every mesh); PRT stores a matrix per vertex but relights under any light of its bands "
        "without recomputation. The PRT precompute time is the transfer's own (also on a cache hit).",
        "",
    ]
    if c.get("renders"):
        lines += ["First camera, per-vertex radiance clamped at 0, one exposure per picture: reference | SHRM at each ε "
                  "(in the order above) | glossy PRT, each with its PSNR from that camera.",
                  ""] + [f"![{Path(f).stem}]({f})" for f in c["renders"]] + [""]
    elif c.get("render_error"):
        lines += [f"Pictures not made: {c['render_error']}", ""]
    return lines


def _records_table(records: list[dict]) -> list[str]:
    """The PSNR / fps table of a run's records and its Pareto front (PSNR vs fps)."""
    lines = [
        "| codec | setting | B/vertex | ratio | SE | rel. SE | PSNR rand (dB) | PSNR lights (dB) | Mvert/s | fps | of bound "
        "| cold | vs uncompr. | encode (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for x in sorted(records, key=lambda x: (x["codec"], x["bytes_per_vertex"])):
        warn = " ⚠" if x.get("timing_trusted") is False else ""  # the rates themselves marked, not only the footnote
        if (x.get("rate_policy") or {}).get("redecided"):  # re-timed under contention (timing.rate_policy): at which threads
            warn += f" ({x['rate_threads']} thr)"
        lines.append(
            f"| {x['codec']} | {_setting(x)} | {x['bytes_per_vertex']:.1f} | {_fmt(x['compression_ratio'])} | {_fmt(x['se'])} | "
            f"{_fmt(x['relative_se'])} | {_fmt(x['psnr_random_db'])} | {_fmt(x['psnr_lights_db'])} | {x['vertices_per_s'] / 1e6:.2f} "
            f"(±{x['relight_spread']:.0%}){warn} | {_fmt(x['fps'])}{warn} | {_bound(x)} | {_bound_cold(x)} | {_speedup(x)} | "
            f"{_fmt(x['encode_s'])} |"
        )
    pts = [(min(x["psnr_lights_db"], 1e9), x["fps"]) for x in records]
    front = [records[i]["setting_id"] for i in pareto_front(pts)]
    return lines + ["", f"Pareto front (PSNR vs fps): {', '.join(front)}.", ""]


def runtime_lines(records: list[dict]) -> list[str]:
    """"Stored vs run-time size" for the records of codecs that relight from a cached form larger
    than what they store (``storage['runtime_bytes']``: the learned codec's features h(z_p)), with
    the encode (training) time; nothing when no record has one."""
    rows = [x for x in records if (x.get("storage") or {}).get("runtime_bytes") is not None]
    if not rows:
        return []
    lines = ["Stored vs run-time size: these codecs relight from a cached form (the neural codec's features h(z_p), "
             "float32, and its last layer), built once per encoding, larger than what they store.", "",
             "| codec | setting | stored B/vertex | run-time B/vertex | PSNR lights (dB) | encode (s) |", "|---|---|---|---|---|---|"]
    for x in sorted(rows, key=lambda x: (x["codec"], x["bytes_per_vertex"])):
        st = x["storage"]
        lines.append(f"| {x['codec']} | {_setting(x)} | {x['bytes_per_vertex']:.1f} | {st['runtime_bytes'] / max(1, st['points']):.1f} | "
                     f"{_fmt(x['psnr_lights_db'])} | {_fmt(x['encode_s'])} |")
    return lines + [""]


#: the families the learned codec is compared with (issue 43): PCA, CPCA and its fits, Green 2005's Gaussians
LEARNED_PEERS = ("pca", "cpca", "cpca_static", "cpca_iterative", "cpca_adaptive", "gaussian")
#: the file :func:`plot_learned` writes into a run directory
LEARNED_PLOT = "learned.png"


def where_label(results: dict) -> str:
    """'mrt on bumpy_sphere (10242 vertices)': what a run's (or a part's) records were measured on."""
    return f"{results['transfer']['kind']} on {results['scene']['name']} ({results['scene']['vertices']} vertices)"


def codec_rows(results: dict, where: str, codecs: tuple[str, ...] | None = None) -> list[dict]:
    """One plain row per record of ``results`` (of ``codecs`` only, when given) for the learned-vs-classic
    comparison: stored and run-time bytes per vertex (``storage['runtime_bytes']``: the neural codec's
    cached features; else the stored bytes), PSNR over lights × views, the relight time as the paired
    one-thread fraction of the uncompressed relight's (``1 / speedup_vs_uncompressed``) and in ms, the
    encode (training) time. ``where`` labels the run (:func:`where_label`)."""
    out = []
    for x in results["records"]:
        if codecs is not None and x["codec"] not in codecs:
            continue
        st = x.get("storage") or {}
        prm = x["params"]
        family = x["codec"] + "".join(f" {k}={prm[k]}" for k in ("clusters", "cluster_decoder", "code_dtype")
                                      if x["codec"] == "neural" and k in prm)
        sp = x.get("speedup_vs_uncompressed")
        out.append({
            "part": where, "codec": x["codec"], "family": family, "setting": x["setting_id"], "params": prm,
            "stored_B_per_vertex": x["bytes_per_vertex"],
            "runtime_B_per_vertex": (st["runtime_bytes"] / max(1, st["points"])) if st.get("runtime_bytes") is not None
            else x["bytes_per_vertex"],
            "psnr_lights_db": x["psnr_lights_db"], "psnr_random_db": x.get("psnr_random_db"), "relative_se": x.get("relative_se"),
            "relight_ms": 1e3 * x["relight_s"], "relight_spread": x.get("relight_spread", 0.0),
            "speedup_vs_uncompressed": sp, "encode_s": x["encode_s"],
            "relight_vs_uncompressed": 1.0 / sp if sp else math.inf,
            "timing_trusted": x.get("timing_trusted"),
        })
    return out


def learned_table(results: dict) -> list[dict]:
    """:func:`codec_rows` of the neural codec and its peers (``LEARNED_PEERS``) in the main run and
    in every part that has a neural record; empty when no run has one."""
    runs = [results] + [p["results"] for p in results.get("parts") or []]
    table: list[dict] = []
    for r in runs:
        if any(x["codec"] == "neural" for x in r["records"]):
            table += codec_rows(r, where_label(r), ("neural",) + LEARNED_PEERS)
    return table


#: the budgets a neural setting is compared within: (name, the peers' key, the neural row's key)
LEARNED_BUDGETS = (("stored bytes", "stored_B_per_vertex", "stored_B_per_vertex"),
                   ("run-time bytes", "stored_B_per_vertex", "runtime_B_per_vertex"),
                   ("relight time", "relight_vs_uncompressed", "relight_vs_uncompressed"))


def learned_verdicts(table: list[dict]) -> list[dict]:
    """Per neural row of ``table`` (:func:`codec_rows`), within each of ``LEARNED_BUDGETS`` (its stored
    bytes, its run-time bytes, its relight time): the best setting of each other family of the same
    part that fits the budget (``best``), and whether the neural setting ``wins`` (a higher PSNR than
    all of them, or none fits) with its ``margin_db`` over the best (negative: it loses)."""
    out = []
    for part in dict.fromkeys(r["part"] for r in table):
        sub = [r for r in table if r["part"] == part]
        others = [r for r in sub if r["codec"] != "neural"]
        for n in sorted((r for r in sub if r["codec"] == "neural"), key=lambda r: r["stored_B_per_vertex"]):
            v = {"row": n, "budgets": {}}
            for what, key, mine in LEARNED_BUDGETS:
                best = []
                for fam in sorted({r["codec"] for r in others}):
                    fit = [r for r in others if r["codec"] == fam and r[key] <= n[mine] * 1.001]
                    if fit:
                        best.append(max(fit, key=lambda r: r["psnr_lights_db"]))
                top = max((b["psnr_lights_db"] for b in best), default=None)
                margin = None if top is None else n["psnr_lights_db"] - top
                v["budgets"][what] = {"key": key, "best": best, "wins": margin is None or margin > 0, "margin_db": margin}
            out.append(v)
    return out


def learned_findings(table: list[dict]) -> list[str]:
    """Plain statements from :func:`learned_verdicts`: per neural setting and budget, the verdict —
    wins (higher PSNR than every other family's best within the budget, or nothing fits it) or loses
    (by how much) — and the peers' best settings within it."""
    out = []
    for v in learned_verdicts(table):
        n, said = v["row"], []
        for what, b in v["budgets"].items():
            verdict = ("wins (nothing else fits)" if b["margin_db"] is None else
                       f"**wins** by {b['margin_db']:.2f} dB" if b["wins"] else f"**loses** by {-b['margin_db']:.2f} dB")
            unit = ((lambda r: f"{r['relight_vs_uncompressed']:.3f}") if b["key"] == "relight_vs_uncompressed"
                    else (lambda r: f"{r['stored_B_per_vertex']:.0f} B"))
            peers = ", ".join(f"{r['codec']} {r['psnr_lights_db']:.2f} dB: {r['setting']}, {unit(r)}" for r in b["best"])
            said.append(f"at no more {what} {verdict}" + (f" ({peers})" if peers else ""))
        out.append(f"- {n['part']}, {n['setting']}: {n['psnr_lights_db']:.2f} dB at {n['stored_B_per_vertex']:.1f} stored / "
                   f"{n['runtime_B_per_vertex']:.1f} run-time B/vertex, relight {n['relight_vs_uncompressed']:.3f} of the "
                   f"uncompressed relight's (paired), trained in {n['encode_s']:.0f} s. " + "; ".join(said) + ".")
    return out


def learned_summary(table: list[dict]) -> list[str]:
    """One line per part: how many of its neural settings win within their stored bytes, their
    run-time bytes and their relight time (:func:`learned_verdicts`)."""
    out = []
    vs = learned_verdicts(table)
    for part in dict.fromkeys(v["row"]["part"] for v in vs):
        mine = [v for v in vs if v["row"]["part"] == part]
        wins = {what: [v["row"]["setting"] for v in mine if v["budgets"][what]["wins"]] for what, _, _ in LEARNED_BUDGETS}
        out.append(f"- **{part}**: of {len(mine)} neural setting(s), "
                   + "; ".join(f"{len(w)} win at equal {what}" + (f" ({', '.join(w)})" if w else "") for what, w in wins.items())
                   + ".")
    return out


def learned_lines(table: list[dict], figure: str | None = None) -> list[str]:
    """The report's "Learned vs classic codecs" section (issue 43) from :func:`learned_table`: one
    row per setting (stored and run-time bytes, PSNR, relight time, encode/training time), the
    verdicts of :func:`learned_findings`, and the figure; nothing for an empty table."""
    if not table:
        return []
    lines = ["## Learned vs classic codecs", "",
             "The learned codec (`neural`: a latent code per vertex and a shared decoder whose last layer is linear, "
             "docs/codecs.md) next to PCA, CPCA and, on transport tables, Gaussians, on the same data, error metric and "
             "relighting clock. Stored: what the codec file keeps (codes + decoder); run-time: what relighting reads (the "
             "neural codec's cached features h(z_p), float32; the others relight from what they store). Relight: the "
             "paired one-thread time as a fraction of the uncompressed relight's (the work; the load does not move it), "
             "and the median in ms. Encode: wall-clock of the fit — the neural codec's is its training.", "",
             "| run | codec | setting | stored B/vertex | run-time B/vertex | PSNR lights (dB) | relight / uncompr. | relight (ms) "
             "| encode (s) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(table, key=lambda r: (r["part"], r["codec"], r["stored_B_per_vertex"])):
        warn = " ⚠" if r["timing_trusted"] is False else ""
        lines.append(f"| {r['part']} | {r['codec']} | {r['setting']} | {r['stored_B_per_vertex']:.1f} | {r['runtime_B_per_vertex']:.1f} | "
                     f"{_fmt(r['psnr_lights_db'])} | {r['relight_vs_uncompressed']:.3f}{warn} | {r['relight_ms']:.3f} | "
                     f"{_fmt(r['encode_s'])} |")
    lines += ["", "Where the learned codec wins and where it does not (computed from the rows above, so against the settings "
              "run here only: within a neural setting's stored bytes, its run-time bytes and its relight time, the best setting "
              "of each other family):", ""]
    lines += learned_summary(table) + [""] + learned_findings(table) + [""]
    if figure:
        lines += [f"![{Path(figure).stem}]({figure})", ""]
    return lines


def plot_learned(table: list[dict], path: Path) -> Path:
    """PSNR vs stored bytes per vertex (top; the neural codec also at its run-time bytes, hollow) and
    PSNR vs relight time as a fraction of the uncompressed relight's (bottom), one column per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parts = list(dict.fromkeys(r["part"] for r in table))
    fig, axes = plt.subplots(2, len(parts), figsize=(5.6 * len(parts), 7.6), squeeze=False)
    for col, part in enumerate(parts):
        sub = [r for r in table if r["part"] == part]
        for row, (key, xlabel) in enumerate((("stored_B_per_vertex", "stored bytes per vertex"),
                                             ("relight_vs_uncompressed", "relight time / uncompressed (paired, 1 thread)"))):
            ax = axes[row][col]
            for fam in sorted({r["family"] for r in sub}):
                pts = sorted(((r[key], min(r["psnr_lights_db"], 120.0), r) for r in sub if r["family"] == fam), key=lambda p: p[0])
                (ln,) = ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-" if row == 0 else "o", label=fam)
                if fam.startswith("neural") and row == 0:
                    ax.plot([p[2]["runtime_B_per_vertex"] for p in pts], [p[1] for p in pts], "o", mfc="none",
                            color=ln.get_color(), label=f"{fam} (run-time bytes)")
            ax.set_xscale("log")
            ax.set_xlabel(xlabel)
            ax.set_ylabel("PSNR, lights (dB)")
            ax.set_title(part, fontsize=9)
            ax.grid(True, alpha=0.3)
            ax.legend(fontsize=7)
    fig.tight_layout()
    return _save_figure(fig, Path(path))


def part_lines(part: dict) -> list[str]:
    """A part of the benchmark (config ``parts``): what differs, its own scene/transfer, its
    uncompressed peer and its PSNR / fps table; its full report is in ``part['dir']``."""
    r = part["results"]
    unc = r["uncompressed"]
    lines = [f"## Part `{part['name']}`", ""]
    if part.get("note"):
        lines += [part["note"], ""]
    lines += [
        f"Scene **{r['scene']['name']}** ({r['scene']['vertices']} vertices), transfer **{r['transfer']['kind']}** "
        f"{tuple(r['transfer']['shape'])} ({r['transfer']['raw_bytes'] / 2**20:.2f} MiB {_stored(r)}). Uncompressed relighting "
        f"(this part's peer): {unc['vertices_per_s'] / 1e6:.2f} M vertices/s, {unc['fps']:.1f} fps. Full report, plots: "
        f"[{part['dir']}/report.md]({part['dir']}/report.md).",
        "",
    ]
    lines += _records_table(r["records"])
    return lines + _contention_note(r["records"]) + runtime_lines(r["records"])


def write_outputs(run_dir: Path, results: dict, log: Callable[[str], None] = print) -> None:
    """Write results.json, results.csv, the plots and report.md for ``results`` (a plain dict,
    as harness.run makes it; ``results['renders']`` lists image paths relative to ``run_dir``)."""
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    io.atomic_write_json(run_dir / "results.json", results)
    write_csv(run_dir / "results.csv", results["records"])
    figs = [p.name for p in plot_results([results], run_dir)] if results["records"] else []  # codecs: []: nothing to plot
    if results.get("ablation"):
        figs.append(plot_ablation(results, run_dir).name)
    if results.get("trade"):
        figs.append(plot_trade(results["trade"], run_dir).name)
    learned = learned_table(results)
    if learned:
        figs.append(plot_learned(learned, run_dir / LEARNED_PLOT).name)
    renders = list(results.get("renders") or [])
    io.atomic_write_text(run_dir / "report.md", markdown(results, figs, renders))
    log(f"[bench] wrote {run_dir}/report.md, results.json, results.csv, {', '.join(figs)}" + (f", {len(renders)} render(s)" if renders else ""))
