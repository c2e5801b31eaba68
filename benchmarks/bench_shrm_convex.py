"""Convex objects: a spherical harmonic reflection map (Ramamoorthi 2002 ch. 5) against unshadowed
glossy PRT (Sloan 2003 §3.1) for the same BRDF and light, on a sphere and on the convex hull of a
scan-like mesh (the built-in bumpy_sphere's hull) — the convex section of ``prt bench convex``
(``prt_torch.harness.convex``, the logic lives there) run alone, without the config's codecs.

Per mesh and camera: PSNR of each method against the brute-force reference (per vertex, Σ over the
environment's pixels of L f_r max(n·ω, 0) Ω, ``shrm.reference_radiance``), also over grazing
vertices only; the most negative radiance; bytes (the SHRM file, per object; the exit matrices,
per vertex, float32); precompute time; per-frame time as an interleaved paired ratio.

Run: .venv/bin/python benchmarks/bench_shrm_convex.py [--quick] [--size small|medium] [key=value ...]
     (the config ``convex`` with overrides, e.g. convex.epsilons=[0.05,0.01]; about 1 minute)
Writes reports/benchmarks/shrm_convex.md and shrm_convex.json (--quick: shrm_convex_quick.*).
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from prt_torch.harness.config import load_config
from prt_torch.harness.report import convex_lines
from prt_torch.harness.run import convex_results
from prt_torch.harness.timing import machine_info
from prt_torch.io import atomic_write_json, atomic_write_text

OUT = Path(__file__).resolve().parent.parent / "reports" / "benchmarks"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true", help="6 bands, 1024 samples, one camera")
    ap.add_argument("--size", choices=["small", "medium", "large"], default="small", help="mesh size (convex.size)")
    ap.add_argument("overrides", nargs="*", help="config overrides key.path=value")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as d:
        ov = [f"output_dir={d}/reports", f"cache_dir={d}/cache", f"convex.size={args.size}"]
        if args.quick:
            ov += ["transfer.bands=6", "transfer.bands_out=6", "transfer.samples=1024", "views.count=1"]
        cfg = load_config("convex", ov + list(args.overrides))
        res = convex_results(cfg, Path(d) / "run", log=lambda s: print(s, file=sys.stderr), progress=False)
    machine = machine_info()
    res.update(machine=machine, quick=args.quick, overrides=list(args.overrides), transfer=cfg["transfer"],
               wall_s=time.perf_counter() - t0)
    cmd = " ".join(["benchmarks/bench_shrm_convex.py"] + (["--quick"] if args.quick else [])
                   + (["--size", args.size] if args.size != "small" else []) + list(args.overrides))
    t = cfg["transfer"]
    lines = ["# Convex objects: SHRM vs unshadowed glossy PRT", "",
             f"`{cmd}` (the config `convex`'s section, `prt_torch.harness.convex`; also in `prt bench convex`'s report). "
             f"PRT: glossy transfer, {t['bands']} light and {t['bands_out']} exit bands, {t['samples']} directions, "
             f"shadows never. CPU {machine.get('cpu')}, {machine.get('cores')} cores, load "
             f"{machine.get('load_average_1min', float('nan')):.1f} at the end (the machine was shared with other jobs); "
             f"ran {res['wall_s']:.0f} s.", ""]
    lines += convex_lines(res, machine)[2:]  # the section without its heading
    OUT.mkdir(parents=True, exist_ok=True)
    name = "shrm_convex_quick" if args.quick else "shrm_convex"
    atomic_write_json(OUT / f"{name}.json", res)
    atomic_write_text(OUT / f"{name}.md", "\n".join(lines))
    print(f"wrote {OUT / (name + '.md')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
