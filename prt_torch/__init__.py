"""prt_torch: precomputed radiance transfer (PRT) and its compression, in PyTorch.

Modules, in dependency order (a module imports only those before it):
_checks, params, io, sh, lighting, scene, brdf, transfer, codecs, relight, render, validate,
harness, cli. See docs/ARCHITECTURE.md.

OpenMP wait policy (benchmarks/bench_threads.py, reports/benchmarks/threads.md): on an idle
2-core machine the default (spinning) OpenMP threads relight 1.1–2.4× faster than
``OMP_WAIT_POLICY=PASSIVE``; beside two busy processes spinning threads stall on descheduled
peers (PASSIVE 1.4–14× faster at the median, tails up to 18×). So when this package is
imported before torch while other processes already occupy ≥ 0.75 × the cores (runnable now,
from /proc/loadavg — not the load average, which counts our own recent work), PASSIVE is set —
unless the user set ``OMP_WAIT_POLICY`` themselves. ``OMP_POLICY_CHOICE`` records what
was decided (it lands in every benchmark's machine record).
"""
import os as _os

__version__ = "0.1.0"


def others_running(samples: int = 5) -> int | None:
    """Runnable processes other than this one right now (median of a few reads of /proc/loadavg's
    running count; the load *average* would count this package's own recent work)."""
    import time

    counts = []
    for i in range(samples):
        try:
            with open("/proc/loadavg") as f:
                counts.append(int(f.read().split()[3].split("/")[0]) - 1)
        except (OSError, ValueError, IndexError):
            return None
        if i + 1 < samples:
            time.sleep(0.005)
    return sorted(counts)[len(counts) // 2]


def _choose_omp_wait_policy() -> str:
    if "OMP_WAIT_POLICY" in _os.environ:
        return f"user: OMP_WAIT_POLICY={_os.environ['OMP_WAIT_POLICY']}"
    others, cores = others_running(), _os.cpu_count() or 1
    if others is None:
        return "default spinning threads (no /proc/loadavg)"
    if busy_now(others):
        _os.environ["OMP_WAIT_POLICY"] = "PASSIVE"
        return f"PASSIVE ({others} other runnable processes on {cores} cores at import)"
    return f"default spinning threads ({others} other runnable processes on {cores} cores at import)"


def busy_now(others: int | None = None) -> bool:
    """Whether other processes occupy at least 0.75 × the cores right now (``others``: runnable
    processes besides this one; default :func:`others_running`): the rule the import-time wait
    policy follows, which ``harness.timing.rate_policy`` re-applies where rates are measured."""
    others = others_running() if others is None else others
    return others is not None and others >= max(1, round(0.75 * (_os.cpu_count() or 1)))


OMP_POLICY_CHOICE = _choose_omp_wait_policy()
#: whether this process's OpenMP threads spin while waiting (the policy is fixed when torch loads OpenMP)
OMP_SPINNING = _os.environ.get("OMP_WAIT_POLICY", "").upper() != "PASSIVE"
