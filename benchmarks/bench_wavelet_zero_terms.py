"""What the zero-term rule changes (issue 39): ``lighting.haar.select_terms`` never keeps a light's round-off Haar
terms (at most ``haar.ZERO_TERM`` = 1e-12 of its largest). On the kernel section's transfer (occluder_over_plane
small, R = 32, K = 256, 16 bits; bench_wavelet.py section 7), for the studio and sky lights at N = 10 … all
(transport-weighted, the default): the terms kept, the dense columns among them and the transfer bytes a relight
reads (``WaveletRelighter.bytes_read``) now, against the selection without the rule (``haar.ZERO_TERM`` set to -1:
every term ranked, as before, on this CPU's rounding), with the largest difference of the two results; and the
relight time before / now paired by one thread's CPU time (``measure_paired(clock=time.thread_time)``, the render-loop
form ``prepared``) where the selections differ (sky at N = 1000, the same selection, as a control).

Writes reports/benchmarks/wavelet_zero_terms.md (CPU, kernel path and load average named).

    .venv/bin/python benchmarks/bench_wavelet_zero_terms.py     (about 30 s)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, OUT, TERMS  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch.harness.timing import cpu_label, machine_info, measure_paired, torch_threads  # noqa: E402
from prt_torch.lighting import haar  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

LIGHTS = ("studio", "sky")
TIMED = {("studio", 300), ("studio", 1000), ("studio", 2000), ("studio", "all"), ("sky", 1000)}


def select(rl, spec: str, N: int, rule: bool):
    """The light's terms with (now) or without (before) the zero-term rule: (indices [N'], float32 values [C, N'])."""
    keep = haar.ZERO_TERM
    haar.ZERO_TERM = keep if rule else -1.0  # -1: every term counts as nonzero (the selection before the rule)
    try:
        li, lv, _ = rl.light(spec, N, "transport")
    finally:
        haar.ZERO_TERM = keep
    return li, lv.to(torch.float32).contiguous()


def main() -> None:
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1, progress=False))
    rl = relight.WaveletRelighter(tr, threads=1)
    m = machine_info()
    load0 = os.getloadavg()[0]
    rows = []
    for spec in LIGHTS:
        for N in TERMS + ["all"]:
            n = rl.P if N == "all" else N
            now, before = select(rl, spec, n, True), select(rl, spec, n, False)
            a, b = rl(*now), rl(*before)
            row = {"light": spec, "N": N}
            for name, (li, _) in (("now", now), ("before", before)):
                row[name] = (int(li.numel()), int((rl.dslot[li] >= 0).sum()), rl.bytes_read(li, factor=False))
            row["diff"] = float((a - b).abs().max() / b.abs().max())
            if (spec, N) in TIMED:
                o1, o2 = torch.empty_like(a), torch.empty_like(b)
                with torch_threads(1):
                    p = measure_paired(rl.prepared(*now, out=o1), rl.prepared(*before, out=o2), repeats=15, warmup=2,
                                       clock=time.thread_time)
                row["before_over_now"] = p.speedup
                row["q"] = (p.ratio.q1, p.ratio.q3)
            rows.append(row)
            print(row, flush=True)
    load1 = os.getloadavg()[0]
    L = ["# Zero-term rule: what a light's round-off Haar terms cost (issue 39)", "",
         f"{cpu_label(m)}; kernel: {relight.wavelet_kernel_path()['path']}; load average {load0:.1f} → {load1:.1f}. "
         "`benchmarks/bench_wavelet_zero_terms.py`: the kernel section's transfer (occluder_over_plane small, "
         f"{rl.V} vertices, R = 32, K = 256, {BITS}-bit), transport-weighted selection. *Now*: `select_terms` keeps only "
         "the light's nonzero Haar terms (above `haar.ZERO_TERM` = 1e-12 of its largest); *before*: every term ranked "
         "(`ZERO_TERM` = -1), the round-off ones by this CPU's rounding. Terms kept (dense columns among them) and the "
         "transfer bytes a relight reads (`WaveletRelighter.bytes_read`, the output not included); the results' largest "
         "difference relative to their largest value; relight time before / now paired by one thread's CPU time "
         "(`prepared`, 15 repeats: median of the per-repeat ratios [quartiles]; > 1: now faster).", "",
         "| light | N | now: terms (dense) | now: MB read | before: terms (dense) | before: MB read | max diff | "
         "before / now time |", "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        t = (f"{r['before_over_now']:.2f}× [{r['q'][0]:.2f}, {r['q'][1]:.2f}]" if "before_over_now" in r else "—")
        L.append(f"| {r['light']} | {r['N']} | {r['now'][0]} ({r['now'][1]}) | {r['now'][2] / 1e6:.3f} | "
                 f"{r['before'][0]} ({r['before'][1]}) | {r['before'][2] / 1e6:.3f} | {r['diff']:.1e} | {t} |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_zero_terms.md", "\n".join(L) + "\n")
    print(f"wrote {OUT / 'wavelet_zero_terms.md'}")


if __name__ == "__main__":
    main()
