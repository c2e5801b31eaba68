"""``prt precompute --dry-run``'s peak memory against the peak a real run reaches (``transfer.estimate``).

The estimate is what ``check_fits`` refuses on, so it must not read low, and it should not read so high that it
refuses runs that fit. Each case runs in a fresh interpreter: imports and the mesh, then the process's peak RSS
(``VmHWM``) before and after the precompute (with a state directory, as the CLI runs it); the growth is checked
against the estimate's peak less its mesh stage: 1.0 <= estimate / measured <= 2.0.

Before: glossy with one bounce on the Cornell box read 0.31 here (its chunk's [k, N, n²] interreflection buffer and
the hits' exit transfers were not counted) and diffuse with one bounce on scan_blob 4.28 (per-ray SH values that the
compiled qmc pass never materialises): both cases fail on that code. Transport on scan_blob read 1.02 here
(0.93 at the command line, ``reports/benchmarks/precompute_estimate.md``: the second, in-flight chunk buffer
was not counted); it now reads 1.20 (glossy 1.54, diffuse 1.61).
"""
from __future__ import annotations

import json
import subprocess
import sys
import textwrap

import pytest

from prt_torch.transfer import ray_kernels

CHILD = textwrap.dedent("""
    import json, sys, tempfile, warnings

    def peak():  # this process's peak RSS, bytes: VmHWM is the fresh address space's own (ru_maxrss keeps the
        # forking parent's high-water mark across exec: a pytest process at 650 MB read as this child's peak)
        with open("/proc/self/status") as f:
            return next(int(ln.split()[1]) * 1024 for ln in f if ln.startswith("VmHWM:"))

    from prt_torch.scene import load_scene
    from prt_torch.transfer import RunOptions, get_kind
    from prt_torch.transfer.estimate import estimate
    scene, kind, params = sys.argv[1], sys.argv[2], json.loads(sys.argv[3])
    mesh = load_scene(scene, size="small")
    k = get_kind(kind)
    with tempfile.TemporaryDirectory() as d:
        run = RunOptions(workers=1, state_dir=d + "/s", progress=False)
        e = estimate(k, mesh, params, run, probe=False)
        before = peak()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            if k.output == "directory":
                k.precompute(mesh, params, run=run, out=d + "/t")
            else:
                k.precompute(mesh, params, run=run).save(d + "/x.prt")
        after = peak()
    print("JSON " + json.dumps({"estimate": e.peak_bytes - e.stages[0]["bytes"], "growth": after - before}))
""")


def _measure(scene: str, kind: str, params: dict) -> dict:
    p = subprocess.run([sys.executable, "-c", CHILD, scene, kind, json.dumps(params)], capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    return json.loads(next(ln for ln in p.stdout.splitlines() if ln.startswith("JSON "))[5:])


@pytest.mark.skipif(not ray_kernels.available(), reason="the compiled ray library (qmc pass) is not built here")
@pytest.mark.parametrize("scene, kind, params", [
    ("cornell_box", "glossy", {"bounces": 1}),
    ("scan_blob", "diffuse", {"bounces": 1}),
    ("scan_blob", "transport", {}),
], ids=["glossy-bounce-cornell", "diffuse-bounce-scan", "transport-scan"])
def test_dry_run_peak_covers_the_real_peak_within_2x(scene, kind, params):
    r = _measure(scene, kind, params)
    ratio = r["estimate"] / r["growth"]
    assert 1.0 <= ratio <= 2.0, (r, ratio)
