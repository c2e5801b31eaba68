"""The wavelet relighter's memory (issue 39 review, mem10): what ``WaveletRelighter`` holds after
construction and its construction peak, before (commit 1f32c50: whole-transfer construction, the int64
index and float32 values copies kept) against now (built in chunks of rows, the copies derived from the
stored transfer on demand, ``reference_rows``).

Per transfer (occluder_over_plane small and medium, R = 32, K = 256, 16-bit and 8-bit values, one scale
per Haar level — the kernel re-quantises both to 16 bits): in a fresh process per version, after a warm-up
construction on a tiny transfer and with the transfer loaded, the RSS high-water growth (``VmHWM``) of one
construction (``layouts='auto'``, nothing relit) and what the relighter then holds (``held_bytes()`` plus,
before, its ``values``/``index`` copies); and in one process both versions built alternately, this thread's
CPU time (``time.thread_time``, one thread), the ratio per pair, median [quartiles]. The outputs of both
versions are checked equal bit for bit (tests/test_relight_wavelet_build.py checks the new one against the
float64 dense reference and the torch path).

Writes reports/benchmarks/wavelet_build.md (CPU, load average named).

    .venv/bin/python benchmarks/bench_wavelet_build.py
"""

from __future__ import annotations

import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

from prt_torch.io import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "reports" / "benchmarks"
BEFORE = "1f32c50"  # the branch's base: the whole-transfer construction
PAIRS = 21

CHILD = r'''
import json, sys, time, importlib.util
import torch
torch.set_num_threads(1)
def peak():
    with open("/proc/self/status") as f:
        return next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmHWM:"))
spec = importlib.util.spec_from_file_location("relight_before", sys.argv[4])
old = importlib.util.module_from_spec(spec); spec.loader.exec_module(old)
from prt_torch import relight
from prt_torch.transfer import Transfer
mode, path, warm = sys.argv[1:4]
versions = {"before": old.WaveletRelighter, "after": relight.WaveletRelighter}
tr = Transfer.load(path)
if mode == "time":
    w = Transfer.load(warm)
    for c in versions.values():
        c(w)
    res = {"before": [], "after": []}
    for i in range(int(sys.argv[5])):
        for k in (("before", "after") if i % 2 == 0 else ("after", "before")):
            t = time.thread_time(); r = versions[k](tr); res[k].append(time.thread_time() - t); del r
    a, b = old.WaveletRelighter(tr), relight.WaveletRelighter(tr)
    li, lv, _ = b.light("studio")
    li2, lv2, _ = b.light("studio", 100)
    res["equal"] = bool(torch.equal(a(li, lv), b(li, lv)) and torch.equal(a(li2, lv2), b(li2, lv2)))
else:
    cls = versions[mode]
    cls(Transfer.load(warm))
    before = peak()
    r = cls(tr)
    res = {"growth": peak() - before, "held": r.held_bytes()["total"], "V": r.V,
           "copies": sum(x.numel() * x.element_size() for x in (r.__dict__.get("values"), r.__dict__.get("index")) if x is not None)}
print("JSON " + json.dumps(res))
'''


def child(*args) -> dict:
    p = subprocess.run([sys.executable, "-c", CHILD, *map(str, args)], capture_output=True, text=True, cwd=ROOT,
                       env={**os.environ, "OMP_NUM_THREADS": "1"}, timeout=900)
    if p.returncode:
        raise SystemExit(p.stderr[-3000:])
    return json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("JSON "))[5:])


def q(xs):
    s = sorted(xs)
    return statistics.median(s), s[len(s) // 4], s[(3 * len(s)) // 4]


def main() -> None:
    sys.path.insert(0, str(ROOT))
    from prt_torch.harness.timing import machine_info
    from prt_torch.scene import builtin
    from prt_torch.transfer import RunOptions, get_kind

    tmp = Path(tempfile.mkdtemp(prefix="bench_wavelet_build_"))
    src = subprocess.run(["git", "show", f"{BEFORE}:prt_torch/relight.py"], capture_output=True, text=True, cwd=ROOT,
                         check=True).stdout
    src = re.sub(r"from \.(\w)", r"from prt_torch.\1", re.sub(r"from \. import", "from prt_torch import", src))
    (tmp / "relight_before.py").write_text(src)
    wk = get_kind("wavelet")
    warm = tmp / "warm.prt"
    wk.precompute(builtin("occluder_over_plane"), {"res": 2, "terms": 24}, run=RunOptions(workers=1, progress=False)).save(warm)
    info, la, rows = machine_info(), [os.getloadavg()[0]], []
    for size in ("small", "medium"):
        for bits in (16, 8):
            path = tmp / f"w_{size}_{bits}.prt"
            wk.precompute(builtin("occluder_over_plane", size), {"res": 32, "terms": 256, "bits": bits},
                          run=RunOptions(workers=1, progress=False)).save(path)
            m = {v: child(v, path, warm, tmp / "relight_before.py") for v in ("before", "after")}
            t = child("time", path, warm, tmp / "relight_before.py", PAIRS)
            la.append(os.getloadavg()[0])
            rows.append({"size": size, "bits": bits, "V": m["after"]["V"], **m, "t": t,
                         "ratio": q([a / b for a, b in zip(t["after"], t["before"])])})
            print(rows[-1], flush=True)
    L = ["# Wavelet relighter: held bytes and construction peak (before / after)\n",
         f"CPU: {info['cpu']} (family {info.get('cpu_family')} model {info.get('cpu_model')}), one thread; load average "
         f"{min(la):.1f}-{max(la):.1f} on {os.cpu_count()} cores (shared with other jobs: the times are this thread's CPU "
         "time, `time.thread_time`). Scene occluder_over_plane, R = 32, K = 256, one scale per Haar level (the kernel "
         f"re-quantises to 16 bits), `layouts='auto'`, nothing relit. *before*: commit {BEFORE} (whole-transfer "
         "construction, int64 index and float32 values copies kept); *after*: this commit (chunks of rows, the copies "
         "derived on demand by `reference_rows`). Peak: RSS high-water growth (`VmHWM`) of one construction in a fresh "
         "process after a warm-up, the transfer already loaded. Outputs of both equal bit for bit (studio light, N = all "
         f"and 100). Reproduce: `.venv/bin/python benchmarks/bench_wavelet_build.py`.\n",
         "| size | bits | V | held before (incl. copies) B/vertex | **held after** B/vertex | peak growth before MiB | "
         "**peak growth after** MiB | peak before / after | peak after / held after | construction CPU before ms | after ms | "
         "**after / before** (median [quartiles] of paired ratios) | equal |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        V, b, a = r["V"], r["before"], r["after"]
        hb, ha = b["held"] + b["copies"], a["held"] + a["copies"]
        m, lo, hi = r["ratio"]
        L.append(f"| {r['size']} | {r['bits']} | {V} | {hb / V:.0f} | **{ha / V:.0f}** | {b['growth'] / 2**20:.1f} | "
                 f"**{a['growth'] / 2**20:.1f}** | {b['growth'] / max(a['growth'], 1):.1f} | {a['growth'] / ha:.2f} | "
                 f"{statistics.median(r['t']['before']) * 1e3:.0f} | {statistics.median(r['t']['after']) * 1e3:.0f} | "
                 f"**{m:.3f}** [{lo:.3f}, {hi:.3f}] | {r['t']['equal']} |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_build.md", "\n".join(L) + "\n")
    print("\n".join(L))


if __name__ == "__main__":
    main()
