"""Robust wall-clock measurement and a record of the machine it ran on.

Used by the benchmark harness and by benchmarks/: every throughput figure is the *median*
of ``repeats`` timed runs after ``warmup`` untimed ones, reported with its spread
(inter-quartile range and min/max), so a noisy machine shows up as a wide spread instead of
a wrong number.
"""
from __future__ import annotations

import math
import os
import platform
import statistics
import sys
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

import torch

from .._checks import check_int

__all__ = ["Timing", "measure", "machine_info"]


@dataclass
class Timing:
    """Seconds per call: median, quartiles, min, max over ``repeats`` runs."""

    median: float
    q1: float
    q3: float
    min: float
    max: float
    repeats: int
    warmup: int
    inner: int = 1

    @property
    def spread(self) -> float:
        """Relative inter-quartile range (q3 - q1) / median."""
        return (self.q3 - self.q1) / self.median if self.median > 0 else 0.0

    def rate(self, items: float) -> float:
        """Items per second at the median time."""
        return items / self.median if self.median > 0 else float("inf")

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["spread"] = self.spread
        return d


def measure(fn: Callable[[], Any], repeats: int = 5, warmup: int = 1, min_time: float = 0.0,
            min_sample_time: float = 0.02) -> Timing:
    """Time ``fn()``: ``warmup`` untimed calls, then ``repeats`` timed samples (more are added
    until ``min_time`` seconds in total). Like ``timeit``, a sample of a fast function runs it
    ``inner`` times in a row, with ``inner`` calibrated so a sample lasts ≥ ``min_sample_time``
    (scheduler noise on a busy machine is ~10 ms slices); times are per call."""
    repeats = check_int("repeats", repeats, 1)
    warmup = check_int("warmup", warmup, 0)
    for _ in range(warmup):
        fn()
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    inner = 1 if first <= 0 or first >= min_sample_time else min(10_000, int(math.ceil(min_sample_time / first)))
    times: list[float] = []
    total = 0.0
    while len(times) < repeats or (total < min_time and len(times) < 1000):
        t0 = time.perf_counter()
        for _ in range(inner):
            fn()
        dt = time.perf_counter() - t0
        times.append(dt / inner)
        total += dt
    times.sort()
    q = statistics.quantiles(times, n=4) if len(times) >= 2 else [times[0]] * 3
    return Timing(statistics.median(times), q[0], q[2], times[0], times[-1], len(times), warmup, inner)


def _cpu_name() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def machine_info() -> dict[str, Any]:
    """CPU, core and thread counts, Python/torch/numpy versions — recorded with every result."""
    import numpy

    info: dict[str, Any] = {
        "cpu": _cpu_name(),
        "cores": os.cpu_count(),
        "torch_threads": torch.get_num_threads(),
        "python": sys.version.split()[0],
        "torch": torch.__version__,
        "numpy": numpy.__version__,
        "platform": platform.platform(),
    }
    try:
        info["load_average_1min"] = os.getloadavg()[0]  # > cores: timings were taken on a busy machine
    except OSError:  # pragma: no cover
        pass
    try:
        import prt_torch

        info["prt_torch"] = prt_torch.__version__
    except Exception:  # pragma: no cover
        pass
    return info
