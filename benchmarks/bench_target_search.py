"""The whole `prt bench CONFIG --target-psnr X --no-render` command, two revisions side by side.

    .venv/bin/python benchmarks/bench_target_search.py --base f73f3c5            # base vs the working tree
    .venv/bin/python benchmarks/bench_target_search.py --base f73f3c5 --sequential

Each revision's package (``git archive`` of ``--base``; the working tree for ``--test .``) runs the
command from a fresh directory (so the transfer is precomputed too: what a new user waits for),
with this checkout's virtual environment. By default the two run at the same time, so that a
machine shared with other jobs loads both alike (a paired measurement: the ratio of their wall
times is the figure; each alone also stretches with the load); ``--sequential`` runs base then
test. Reports the wall time of each whole command, the search's own seconds, evaluations and
winner (results.json ``target``), the grid's settings, the load average at start and end, and the
CPU; ``--out`` writes the markdown table (reports/benchmarks/target_search.md).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from prt_torch.harness.timing import machine_info  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402


def export(rev: str, dest: Path) -> Path:
    """The package of ``rev`` ('.' = this working tree) as a directory to put first on PYTHONPATH."""
    if rev == ".":
        return ROOT
    dest.mkdir(parents=True)
    tar = dest / "src.tar"
    with open(tar, "wb") as f:
        subprocess.run(["git", "-C", str(ROOT), "archive", rev], stdout=f, check=True)
    with tarfile.open(tar) as t:
        t.extractall(dest, filter="data")
    return dest


def start(src: Path, work: Path, argv: list[str]) -> tuple[subprocess.Popen, float, list[float]]:
    work.mkdir(parents=True)
    env = {**os.environ, "PYTHONPATH": str(src)}
    p = subprocess.Popen([sys.executable, "-m", "prt_torch", *argv], cwd=work, env=env,
                         stdout=open(work / "out.log", "w"), stderr=open(work / "err.log", "w"))
    return p, time.perf_counter(), list(os.getloadavg())


def finish(p: subprocess.Popen, t0: float, load0: list[float], work: Path, name: str) -> dict:
    rc = p.wait()
    wall = time.perf_counter() - t0
    res = json.loads(next(work.glob("reports/*/results.json")).read_text()) if rc == 0 else {}
    t = res.get("target") or {}
    return {"revision": name, "rc": rc, "wall_s": wall, "load_start": load0, "load_end": list(os.getloadavg()),
            "search_s": t.get("seconds"), "timing_s": t.get("timing_s"), "evaluated": t.get("evaluated"),
            "most_fits": t.get("most_fits"), "winner": (t.get("winner") or {}).get("setting_id"),
            "winner_bytes": (t.get("winner") or {}).get("bytes_per_vertex"), "grid_settings": len(res.get("records") or [])}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=True, help="git revision to compare against")
    ap.add_argument("--test", default=".", help="git revision under test, or '.' for the working tree (default)")
    ap.add_argument("--config", default="default")
    ap.add_argument("--psnr", type=float, default=36.0)
    ap.add_argument("--sequential", action="store_true", help="run base, then test (default: both at once, paired)")
    ap.add_argument("--out", default=None, help="write the markdown table here")
    args = ap.parse_args()
    argv = ["bench", args.config, "--target-psnr", f"{args.psnr:g}", "--no-render", "--quiet"]
    tmp = Path(tempfile.mkdtemp(prefix="bench_target_"))
    srcs = {name: export(rev, tmp / f"src_{name}") for name, rev in (("base", args.base), ("test", args.test))}
    rows = []
    if args.sequential:
        for name in ("base", "test"):
            rows.append(finish(*start(srcs[name], tmp / name, argv), tmp / name, name))
    else:
        runs = {name: start(srcs[name], tmp / name, argv) for name in ("base", "test")}
        rows = [finish(*runs[name], tmp / name, name) for name in ("base", "test")]
    m = machine_info()
    lines = [f"`prt {' '.join(argv)}`, base `{args.base}` vs test `{args.test}`, "
             f"{'one after the other' if args.sequential else 'both at once (paired under the same load)'}; "
             f"CPU {m['cpu']}, {m['cores']} cores; each from a fresh directory (precompute included).", "",
             "| revision | whole command (s) | search (s) | finalists timed (s) | evaluations (bound) | winner | B/vertex | load at start → end |",
             "|---|---|---|---|---|---|---|---|"]
    def f(v):
        return "–" if v is None else f"{v:.0f}"

    for r in rows:
        lines.append(f"| {r['revision']} | {r['wall_s']:.0f} | {f(r['search_s'])} | {f(r['timing_s'])} | {r['evaluated']} ({r['most_fits']}) | "
                     f"{r['winner']} | {r['winner_bytes'] or 0:.1f} | {r['load_start'][0]:.1f} → {r['load_end'][0]:.1f} |")
    lines += ["", f"test / base, whole command: {rows[1]['wall_s'] / rows[0]['wall_s']:.2f}"]
    text = "\n".join(lines)
    print(text)
    if args.out:
        atomic_write_text(Path(args.out), text + "\n")
    return 0 if all(r["rc"] == 0 for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
