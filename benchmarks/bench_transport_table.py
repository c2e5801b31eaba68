"""Benchmark (issue 42 §2): the whole default transport table from the command line, this checkout against another
revision, paired and alternating.

    .venv/bin/python benchmarks/bench_transport_table.py --against /tmp/tt42_main [--pairs 2] [--scene bumpy_sphere]
        [--size medium] [--extra '--brdf ward'] [--out reports/benchmarks/transport_table.md]

Each run is ``prt precompute <scene> --size <size> --kind transport --no-progress -o DIR`` (defaults only: 92 views,
``res: auto``, texel averages) in a fresh process, the other revision's (``git archive main | tar -x -C DIR``, put
first on ``PYTHONPATH``) and this checkout's alternating ``--pairs`` times, the other first. Per run: wall seconds,
user and system CPU of the process and its children (``os.wait4``'s rusage of the run: the ray-casting workers
included), its peak RSS and minor page faults, the 1-minute load before and after. The machine is shared: the CPU seconds (user + system) are the
figure to trust, wall is what this load gave. The last pair's tables are compared value for value (every
``--compare-every``-th chunk, the others removed after each run so that the disk holds one table at a time: the count
of differing float32 values and the largest relative difference), then removed. Writes a markdown report.
"""
from __future__ import annotations

import argparse
import os
import shlex
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


from prt_torch.harness.timing import cpu_label  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402


def _cpu() -> str:
    return f"{cpu_label()}, {os.cpu_count()} cores"


def run_once(code_root: str | None, args: list[str], out: Path) -> dict:
    """One ``prt precompute`` in a fresh interpreter with ``code_root`` first on PYTHONPATH (None: this checkout)."""
    env = dict(os.environ)
    if code_root:
        env["PYTHONPATH"] = code_root + os.pathsep + env.get("PYTHONPATH", "")
    shutil.rmtree(out, ignore_errors=True)
    cmd = [sys.executable, "-c", "import sys; from prt_torch.cli import main; sys.argv[0] = 'prt'; sys.exit(main())",
           "precompute", *args, "--kind", "transport", "--no-progress", "-o", str(out)]
    load0 = os.getloadavg()[0]
    t0 = time.perf_counter()
    with tempfile.TemporaryFile() as err:
        p = subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=err, cwd=str(ROOT) if code_root is None else code_root)
        _, status, ru = os.wait4(p.pid, 0)  # this run's own rusage: CPU and peak RSS of it and its waited-for children
        wall = time.perf_counter() - t0
        p.returncode = os.waitstatus_to_exitcode(status)
        if p.returncode:
            err.seek(0)
            raise RuntimeError(f"{' '.join(cmd)} failed ({p.returncode}): {err.read().decode()[-2000:]}")
    return {"wall": wall, "user": ru.ru_utime, "sys": ru.ru_stime, "rss": ru.ru_maxrss / 2**20, "minflt": ru.ru_minflt,
            "load0": load0, "load1": os.getloadavg()[0]}


def prune(out: Path, every: int) -> None:
    """Keep every ``every``-th chunk file of a finished table (the comparison's sample; the disk holds one whole table
    at a time, not two)."""
    for f in out.glob("chunk_*.prt"):
        if int(f.stem.split("_")[1]) % every:
            f.unlink()


def compare(a: Path, b: Path) -> dict:
    """Value for value over every chunk: differing values, the largest |x - y| / |x| (x: a's), the value count."""

    from prt_torch.transfer import TransportTable

    ta, tb = TransportTable(a), TransportTable(b)
    n = diff = 0
    worst = 0.0
    for (s, e, x), (s2, e2, y) in zip(ta, tb):
        assert (s, e) == (s2, e2)
        x, y = x.double(), y.double()
        d = (x - y).abs()
        n += x.numel()
        diff += int((d > 0).sum())
        nz = x != 0
        if bool(nz.any()):
            worst = max(worst, float((d[nz] / x[nz].abs()).max()))
        if bool((~nz & (d > 0)).any()):
            worst = float("inf")
    return {"values": n, "differ": diff, "max_rel": worst}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", required=True, help="another revision's checkout (e.g. git archive main)")
    ap.add_argument("--pairs", type=int, default=2)
    ap.add_argument("--scene", default="bumpy_sphere")
    ap.add_argument("--size", default="medium")
    ap.add_argument("--tmp", default="/tmp/prt_bench_transport_table")
    ap.add_argument("--out", default=None)
    ap.add_argument("--compare-every", type=int, default=4, help="compare every n-th chunk of the last pair's tables")
    ap.add_argument("--extra", default="", help="more options of prt precompute, one string (e.g. '--brdf ward')")
    a = ap.parse_args(argv)
    tmp = Path(a.tmp)
    tmp.mkdir(parents=True, exist_ok=True)
    args = [a.scene, "--size", a.size, *shlex.split(a.extra)]
    rows: list[tuple[str, int, dict]] = []
    for k in range(a.pairs):
        for name, root in (("against", a.against), ("this", None)):
            r = run_once(root, args, tmp / name)
            prune(tmp / name, a.compare_every)
            rows.append((name, k, r))
            print(f"pair {k} {name}: wall {r['wall']:.1f} s, user {r['user']:.1f} s, system {r['sys']:.1f} s, "
                  f"peak RSS {r['rss']:.2f} GiB, load {r['load0']:.1f} -> {r['load1']:.1f}", flush=True)
    cmp = compare(tmp / "against", tmp / "this")
    shutil.rmtree(tmp, ignore_errors=True)
    cpu = {n: [r["user"] + r["sys"] for m, _, r in rows if m == n] for n in ("against", "this")}
    wall = {n: [r["wall"] for m, _, r in rows if m == n] for n in ("against", "this")}
    ratios = [c0 / c1 for c0, c1 in zip(cpu["against"], cpu["this"])]
    wratios = [w0 / w1 for w0, w1 in zip(wall["against"], wall["this"])]
    lines = [
        f"# The whole {'default ' if not a.extra else ''}transport table{' ' + a.extra if a.extra else ''} (issue 42 §2)",
        "",
        f"`benchmarks/bench_transport_table.py --against {a.against} --pairs {a.pairs} --scene {a.scene} --size {a.size}"
        f"{' --extra=' + repr(a.extra) if a.extra else ''}` — "
        f"`prt precompute {a.scene} --size {a.size} --kind transport --no-progress{' ' + a.extra if a.extra else ''}` "
        "(92 views, res auto, texel averages), "
        f"{a.against} (the other revision) and this checkout alternating, each in a fresh process; CPU {_cpu()}; "
        "a machine shared with other jobs (the load column): CPU seconds are the figure to trust. CPU seconds and peak RSS: "
        "`os.wait4` of the run (its process and the children it waited for; RSS: the largest of them).",
        "",
        "| pair | code | wall s | user s | system s | CPU s (user + system) | peak RSS GiB | minor faults | load before → after |",
        "|---:|---|---:|---:|---:|---:|---:|---:|---|",
    ]
    for name, k, r in rows:
        lines.append(f"| {k} | {'other (' + a.against + ')' if name == 'against' else 'this'} | {r['wall']:.1f} | {r['user']:.1f} | "
                     f"{r['sys']:.1f} | {r['user'] + r['sys']:.1f} | {r['rss']:.2f} | {r['minflt']} | {r['load0']:.1f} → {r['load1']:.1f} |")
    lines += ["", f"CPU-time ratio other / this per pair: {', '.join(f'{x:.2f}' for x in ratios)}; wall ratio: "
              f"{', '.join(f'{x:.2f}' for x in wratios)}.", "",
              f"The last pair's tables (every {a.compare_every}-th chunk): {cmp['values']} float32 values, {cmp['differ']} differ, "
              f"largest relative difference "
              f"{cmp['max_rel']:.3g} (zeros: the same set)." if cmp["max_rel"] != float("inf") else
              f"The last pair's tables: {cmp['values']} values, {cmp['differ']} differ, and some zero in one is not in the other."]
    text = "\n".join(lines) + "\n"
    print(text)
    if a.out:
        atomic_write_text(Path(a.out), text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
