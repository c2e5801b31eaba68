"""Every codec row of a transport benchmark against the harness's reference before and after issue 42 §2.

    .venv/bin/python benchmarks/bench_transport_reference.py [--config gaussian] [--part gaussian]
        [--set KEY=VALUE ...] [--skip neural] [--out reports/benchmarks/transport_reference]

Before: ``Evaluator.uncompressed`` (the tables of each vertex's three stored views nearest the camera relit and
cross-faded — ``prt bench``'s reference for transport until issue 42 §2), with the Gaussian codec as fitted
(``fill_empty=False``). After: ``Evaluator.reference`` (the exact radiance at each vertex's own view:
``exact_transport``), with the Gaussian codec's default ``fill_empty`` (``gaussian.fill_empty_lobes`` on the same
fitted lobes: the tables are unchanged). Each setting of the config's codecs (``--part``: a part of the config,
e.g. the default benchmark's ``gaussian`` part at 10 242 vertices) is fitted once; PSNR as the harness
(``metrics.psnr_vs_reference``, mean over lights × cameras). Also the two references' relight time (this process's
CPU time, every thread, one call each, paired in the same run; the exact one is computed once per (light, view)
in a run) — accuracy otherwise; the CPU and load average are recorded.
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.codecs.gaussian import fill_empty_lobes  # noqa: E402
from prt_torch.harness.config import expand_codecs, load_config, part_configs  # noqa: E402
from prt_torch.harness.evaluate import Evaluator  # noqa: E402
from prt_torch.harness.metrics import psnr_vs_reference  # noqa: E402
from prt_torch.harness.run import compute_transfer, load_mesh_within_budget, setting_id  # noqa: E402
from prt_torch.harness.timing import cpu_label  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", default="gaussian")
    ap.add_argument("--part", default=None, help="run this part of the config (e.g. gaussian of the default)")
    ap.add_argument("--set", nargs="*", default=[])
    ap.add_argument("--skip", nargs="*", default=[], help="codec names to leave out")
    ap.add_argument("--cache", type=Path, default=ROOT / "cache")
    ap.add_argument("--out", type=Path, default=ROOT / "reports/benchmarks/transport_reference")
    args = ap.parse_args(argv)
    try:  # bad input named in one line, status 2, before any work
        cfg = load_config(args.config, args.set)
    except (ValueError, TypeError, OSError) as e:
        ap.error(f"--config {args.config!r} --set {' '.join(args.set)!r}: {e}")
    if args.part:
        parts = {p["name"]: p for p in part_configs(cfg)}
        if args.part not in parts:
            ap.error(f"--part {args.part!r}: the config has parts {sorted(parts)}")
        cfg = parts[args.part]
    if cfg["transfer"]["type"] != "transport":
        ap.error(f"config transfer type {cfg['transfer']['type']!r}; accepted: transport (--config gaussian, or --part gaussian "
                 "of the default)")
    warnings.simplefilter("ignore")
    tr, tinfo = compute_transfer(cfg, load_mesh_within_budget(cfg)[0], args.cache, progress=False)
    ev = Evaluator(tr)
    lights, cams, views = ev.config_views(cfg)
    t0 = time.process_time()
    ev.reference_info  # noqa: B018  the light-independent state (the stored visibility, or traced)
    t_state = time.process_time() - t0
    before, after, t_exact, t_unc = {}, {}, [], []
    for li, L in enumerate(lights):
        for vi, v in enumerate(views):
            t0 = time.process_time()
            after[li, vi] = ev.reference(L, v)
            t1 = time.process_time()
            before[li, vi] = ev.uncompressed(L, v)
            t_exact.append(t1 - t0)
            t_unc.append(time.process_time() - t1)
    head = {"cpu": cpu_label(), "load": os.getloadavg(), "config": args.config, "part": args.part, "set": args.set,
            "vertices": ev.V, "views": int(ev.views.shape[0]), "res": ev.res, "table": tinfo["path"], **ev.reference_info,
            "exact_state_cpu_s": t_state, "exact_reference_cpu_s": t_exact, "uncompressed_cpu_s": t_unc,
            "cross_fade_vs_exact_db": sum(psnr_vs_reference(after[k], before[k]) for k in after) / len(after)}
    print(json.dumps(head), flush=True)
    rows = []
    for s in expand_codecs(cfg["codecs"]):
        params = {k: v for k, v in s.items() if k != "type"}
        if s["type"] in args.skip:
            continue
        if s["type"] == "gaussian":
            params["fill_empty"] = False
        codec = codecs.get(s["type"], **params)
        t0 = time.perf_counter()
        enc = codec.fit_encode(ev.X, matrix_shape=ev.matrix_shape, **ev.fit_kwargs(codec))
        fit_s = time.perf_counter() - t0
        variants = {"before": enc}
        if s["type"] == "gaussian":  # the default now: the same lobes with fill_empty_lobes (weights, tables unchanged)
            import copy

            w, mu, sg = codec.lobes_of(enc)
            filled = copy.copy(enc)
            _, mf, sf = fill_empty_lobes(w, mu, sg, ev.views)
            filled.tensors = {**enc.tensors, "lobes_by_view": torch.cat([w[..., None], mf, sf[..., None]], -1).transpose(0, 1).contiguous()}
            filled.cache = {}
            variants["after"] = filled
        ps: dict[str, list] = {"before": [], "after": [], "fitted_vs_exact": []}
        for li, L in enumerate(lights):
            Lc = ev.codec_light(codec, L)
            for vi, v in enumerate(views):
                out_b = ev.finish(codec.relight(variants["before"], Lc, view=v))
                out_a = ev.finish(codec.relight(variants.get("after", variants["before"]), Lc, view=v))
                ps["before"].append(psnr_vs_reference(before[li, vi], out_b))
                ps["after"].append(psnr_vs_reference(after[li, vi], out_a))
                ps["fitted_vs_exact"].append(psnr_vs_reference(after[li, vi], out_b))
        rec = {"setting_id": setting_id(s), "bytes_per_vertex": int(codec.storage(enc)["bytes_total"]) / ev.V, "fit_s": fit_s,
               **{f"psnr_{k}_db": sum(v) / len(v) for k, v in ps.items()}, "each": ps}
        print(json.dumps(rec), flush=True)
        rows.append(rec)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out.with_suffix(".json"), json.dumps({"head": head, "rows": rows}, indent=1))
    mean = lambda x: sum(x) / len(x)  # noqa: E731
    lines = [f"CPU: {head['cpu']}; load average {head['load'][0]:.1f} (shared machine). Config `{args.config}`"
             + (f" part `{args.part}`" if args.part else "") + f" {' '.join(args.set)}: {ev.V} vertices × {head['views']} views, "
             f"6×{ev.res}×{ev.res} tables, {len(lights)} lights × {len(cams)} cameras. Exact reference: visibility {head['visibility']}; "
             f"{mean(t_exact):.2f} CPU s a (light, view) (+{t_state:.2f} s once), the cross-faded tables {mean(t_unc):.3f} s; "
             f"the cross-fade is {head['cross_fade_vs_exact_db']:.2f} dB from the exact radiance.", "",
             "| setting | B/vertex | PSNR before (vs cross-faded tables; Gaussians as fitted) | after (vs exact; Gaussians fill_empty) "
             "| as fitted vs exact |", "|---|---:|---:|---:|---:|"]
    for r in rows:
        lines.append(f"| {r['setting_id']} | {r['bytes_per_vertex']:.0f} | {r['psnr_before_db']:.2f} | {r['psnr_after_db']:.2f} | "
                     f"{r['psnr_fitted_vs_exact_db']:.2f} |")
    atomic_write_text(args.out.with_suffix(".md"), "\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
