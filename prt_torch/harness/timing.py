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
from ..executor import torch_threads  # noqa: F401  (re-exported: where it lived before issue 42)

__all__ = ["Timing", "Paired", "measure", "measure_paired", "measure_paired_cold", "last_level_cache_bytes", "torch_threads",
           "io_bound_fn", "read_bound_fn", "machine_info", "cpu_label", "rate_policy"]


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


@dataclass
class Paired:
    """Interleaved timing of a function and its peer (:func:`measure_paired`).

    ``test`` / ``peer``: per-call :class:`Timing` of each; ``ratio``: the distribution of the
    per-repeat ratio peer/test (how many times faster ``test`` is), each ratio taken from two
    samples measured back to back, so a slow-down of the machine hits both sides of a ratio;
    ``contention``: what the process saw while timing — involuntary context switches per
    second (the scheduler handing our cores to other processes), CPU time over wall time, and
    the load average — and ``trusted``, false when the figures should not be believed."""

    test: Timing
    peer: Timing
    ratio: Timing
    contention: dict
    #: the speed-up estimate to report: peer/test of the fastest tenth of many short interleaved
    #: samples (``floor_pairs`` of :func:`measure_paired`), else the median per-repeat ratio
    speedup: float = float("nan")
    floor: dict | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"test": self.test.as_dict(), "peer": self.peer.as_dict(), "ratio": self.ratio.as_dict(),
                "contention": dict(self.contention), "speedup": self.speedup, "floor": self.floor}


def _quantiles(xs: list[float], warmup: int, inner: int = 1) -> Timing:
    xs = sorted(xs)
    q = statistics.quantiles(xs, n=4) if len(xs) >= 2 else [xs[0]] * 3
    return Timing(statistics.median(xs), q[0], q[2], xs[0], xs[-1], len(xs), warmup, inner)


def _inner(fn: Callable[[], Any], min_sample_time: float) -> int:
    t0 = time.perf_counter()
    fn()
    first = time.perf_counter() - t0
    return 1 if first <= 0 or first >= min_sample_time else min(10_000, int(math.ceil(min_sample_time / first)))


def measure_paired(test: Callable[[], Any], peer: Callable[[], Any], repeats: int = 7, warmup: int = 1,
                   min_sample_time: float = 0.02, max_switch_rate: float = 50.0, max_spread: float = 0.5,
                   floor_pairs: int = 0, floor_sample_time: float = 0.002, floor_quantile: float = 0.1,
                   floor_max_pairs: int = 0, floor_agree: float = 0.1,
                   clock: Callable[[], float] = time.perf_counter) -> Paired:
    """Time ``test`` and its ``peer`` interleaved: every repeat times one sample of each, back to
    back (the order alternating), and the speed-up is the median of the per-repeat ratios
    peer/test — a paired estimate that a busy machine slows down on both sides at once.

    Contention is measured, not assumed: involuntary context switches per second of timing
    (``getrusage``), process CPU time over wall time, and the 1-minute load average against
    the core count. ``trusted`` is false when switches exceed ``max_switch_rate`` per second,
    the load exceeds the cores, or the ratio's relative spread exceeds ``max_spread``.

    ``floor_pairs`` > 0 adds a second interleaved phase of that many pairs of short samples
    (of equal duration on both sides, ≥ ``floor_sample_time``) and sets ``speedup`` to the ratio of the two sides'
    ``floor_quantile`` quantiles: on a busy machine most samples are stretched by other processes
    taking the cores, but the fastest tenth of short samples of each side ran (nearly)
    undisturbed, so their ratio stays the work ratio an idle machine shows, where a median of
    per-pair ratios drifts with how each side's parallel regions stall (measured:
    reports/benchmarks/timing_trust.md).

    ``floor_max_pairs`` > ``floor_pairs`` makes that phase adaptive: while the estimates from its
    even and its odd pairs differ by more than ``floor_agree`` (relative), another
    ``floor_pairs`` pairs are timed, up to ``floor_max_pairs`` — a noisy machine gets more
    samples, a quiet one no more time.

    ``clock`` times every sample: ``time.perf_counter`` (wall time, the default), or
    ``time.thread_time`` (this thread's CPU time) for a pairing run in one thread
    (:class:`torch_threads`; refused otherwise), where all the work is on the calling thread: the time other
    processes held the core is then not in either side's samples at all, where the floor phase
    can only hope some samples escaped it (measured: reports/benchmarks/timing_trust.md, where
    the wall-clock floor once read 11.7× beside two busy processes for a 24.9× idle ratio)."""
    import resource

    repeats = check_int("repeats", repeats, 1)
    warmup = check_int("warmup", warmup, 0)
    if clock is time.thread_time and torch.get_num_threads() != 1:
        raise ValueError(f"measure_paired: clock=time.thread_time counts only the calling thread's CPU time, and torch runs "
                         f"{torch.get_num_threads()} threads; accepted: one thread (with timing.torch_threads(1): ...)")
    for _ in range(warmup):
        test()
        peer()
    n_t, n_p = _inner(test, min_sample_time), _inner(peer, min_sample_time)
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    c0, w0 = time.process_time(), time.perf_counter()
    tt, tp, ratios = _alternate(test, peer, repeats, n_t, n_p, clock=clock)
    ratio = _quantiles(ratios, warmup)
    contention = _contention(r0, c0, w0, ratio, max_switch_rate, max_spread)
    speedup, floor = ratio.median, None
    if floor_pairs > 0:
        # equal sample durations on both sides (≥ floor_sample_time): a longer sample is less often
        # undisturbed, which would bias the ratio of the fastest samples
        c_t, c_p = statistics.median(tt), statistics.median(tp)  # per-call times of the first phase
        target = max(floor_sample_time, c_t, c_p)
        f_t, f_p = (max(1, min(10_000, round(target / max(c, 1e-9)))) for c in (c_t, c_p))
        st: list[float] = []
        sp: list[float] = []

        def estimate(a: list[float], b: list[float]) -> tuple[float, float, float]:
            a, b = sorted(a), sorted(b)
            k = min(len(a) - 1, int(floor_quantile * len(a)))
            return (b[k] / a[k] if a[k] > 0 else float("inf")), a[k], b[k]

        cap = max(floor_pairs, floor_max_pairs)
        while True:
            a, b, _ = _alternate(test, peer, floor_pairs, f_t, f_p, clock=clock)
            st += a
            sp += b
            halves = (estimate(st[0::2], sp[0::2])[0], estimate(st[1::2], sp[1::2])[0])
            agree = abs(halves[0] - halves[1]) <= floor_agree * max(min(halves), 1e-12)
            if agree or len(st) + floor_pairs > cap:
                break
        speedup, t_k, p_k = estimate(st, sp)
        floor = {"pairs": len(st), "quantile": floor_quantile, "test_s": t_k, "peer_s": p_k,
                 "inner_test": f_t, "inner_peer": f_p, "halves": list(halves)}
    return Paired(_quantiles(tt, warmup, n_t), _quantiles(tp, warmup, n_p), ratio, contention, speedup, floor)


def _alternate(test: Callable[[], Any], peer: Callable[[], Any], repeats: int, n_t: int, n_p: int,
               before: Callable[[], Any] | None = None,
               clock: Callable[[], float] = time.perf_counter) -> tuple[list[float], list[float], list[float]]:
    """``repeats`` pairs of samples, back to back, the order swapped every repeat: a sample of
    ``test`` is ``n_t`` calls in a row (of ``peer``, ``n_p``), preceded by ``before()`` untimed
    when given, timed by ``clock``. Returns the per-call times of each side and the per-pair
    ratios peer/test."""
    tt: list[float] = []
    tp: list[float] = []
    ratios: list[float] = []
    for i in range(repeats):
        pair = {}
        for name in (("test", "peer") if i % 2 == 0 else ("peer", "test")):
            fn, n = (test, n_t) if name == "test" else (peer, n_p)
            if before is not None:
                before()
            t0 = clock()
            for _ in range(n):
                fn()
            pair[name] = (clock() - t0) / n
        tt.append(pair["test"])
        tp.append(pair["peer"])
        ratios.append(pair["peer"] / pair["test"] if pair["test"] > 0 else float("inf"))
    return tt, tp, ratios


def _contention(r0, c0: float, w0: float, ratio: Timing, max_switch_rate: float, max_spread: float) -> dict:
    """What the process saw since ``getrusage`` ``r0``, process time ``c0`` and wall time ``w0``
    (:func:`measure_paired`): involuntary context switches per second, CPU over wall time, the
    1-minute load against the cores, and ``trusted`` with the reasons it is not."""
    import resource

    wall, cpu = time.perf_counter() - w0, time.process_time() - c0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    switches = (r1.ru_nivcsw - r0.ru_nivcsw) / max(wall, 1e-9)
    try:
        load = os.getloadavg()[0]
    except OSError:  # pragma: no cover
        load = float("nan")
    cores = os.cpu_count() or 1
    reasons = []
    if switches > max_switch_rate:
        reasons.append(f"{switches:.0f} involuntary context switches/s (> {max_switch_rate:g})")
    if load > cores:
        reasons.append(f"load average {load:.1f} > {cores} cores")
    if ratio.spread > max_spread:
        reasons.append(f"speed-up spread {ratio.spread:.0%} (> {max_spread:.0%})")
    return {"involuntary_switches_per_s": switches, "cpu_over_wall": cpu / max(wall, 1e-9), "load_average_1min": load,
            "cores": cores, "torch_threads": torch.get_num_threads(), "trusted": not reasons, "why_not": reasons}


def rate_policy(fn: Callable[[], Any], first: Timing, contention: dict, repeats: int = 7, warmup: int = 1,
                busy: bool | None = None) -> tuple[Timing, dict]:
    """Re-decide, where a rate is measured, what the import-time OpenMP wait policy decided.

    ``prt_torch`` chooses spinning or PASSIVE OpenMP threads once, at import, from the load it
    sees then; the policy is fixed once torch has loaded OpenMP. When other processes take the
    cores later, spinning threads stall on descheduled peers (2-thread relighting measured at
    0.64 M vertices/s for settings that run at 100–160 M idle; reports/benchmarks/threads.md).
    ``first`` is ``fn``'s timing at the process's thread count and ``contention`` what
    :func:`measure_paired` saw while taking it. When that figure is untrusted, or the machine is
    busy now (``prt_torch.busy_now``, the import-time rule; ``busy`` overrides it) while this
    process spins with more than one thread, ``fn`` is timed again: in one thread (no parallel
    region, so no thread to wait for: the one policy choice still open at run time) and at the
    process's thread count. The fastest median is the rate reported — what the machine gives
    now with the better choice — and the decision record says why, what each candidate measured
    and which thread count (``threads``) the reported rate used.

    Returns ``(timing to report, {'redecided', 'why', 'threads', 'spinning', 'busy_now', 'candidates'})``."""
    import prt_torch

    threads = torch.get_num_threads()
    busy = prt_torch.busy_now() if busy is None else bool(busy)
    why = []
    if not contention.get("trusted", True):
        why.append("untrusted: " + "; ".join(contention.get("why_not") or ["contention"]))
    if busy and prt_torch.OMP_SPINNING and threads > 1:
        why.append(f"other processes took the cores after import ({prt_torch.OMP_POLICY_CHOICE}) and {threads} threads spin")
    out = {"redecided": bool(why), "why": why, "threads": threads, "spinning": prt_torch.OMP_SPINNING, "busy_now": busy,
           "candidates": {f"{threads} threads (first)": first.median}}
    if not why:
        return first, out
    cands = [(first, threads)]
    if threads > 1:
        with torch_threads(1):
            cands.append((measure(fn, repeats=repeats, warmup=warmup), 1))
        out["candidates"]["1 thread"] = cands[-1][0].median
    cands.append((measure(fn, repeats=repeats, warmup=warmup), threads))
    out["candidates"][f"{threads} threads (again)"] = cands[-1][0].median
    best, out["threads"] = min(cands, key=lambda c: c[0].median)
    return best, out


def last_level_cache_bytes() -> int:
    """This CPU's largest cache in bytes (Linux sysfs), else 32 MiB."""
    best = 0
    base = "/sys/devices/system/cpu/cpu0/cache"
    try:
        for d in os.listdir(base):
            try:
                with open(os.path.join(base, d, "size")) as f:
                    txt = f.read().strip().upper()
            except OSError:
                continue
            mult = {"K": 1024, "M": 1024 ** 2, "G": 1024 ** 3}.get(txt[-1:], 1)
            digits = txt.rstrip("KMG")
            if digits.isdigit():
                best = max(best, int(digits) * mult)
    except OSError:
        pass
    return best or 32 * 1024 ** 2


def measure_paired_cold(test: Callable[[], Any], peer: Callable[[], Any], repeats: int = 15, warmup: int = 1,
                        evict_bytes: int | None = None, max_switch_rate: float = 50.0, max_spread: float = 0.5) -> Paired:
    """:func:`measure_paired` from cold caches: every timed call is a single call, preceded by a
    read of ``evict_bytes`` (default 4× the last-level cache, at least 64 MiB) that evicts what
    the previous call left in the caches (a read: the lines it leaves are clean, so no write-back
    lands in the timed call), so each side reads its inputs from memory and writes its outputs
    back, as in a render loop whose other work between frames evicts them. The two
    sides alternate (order swapped every repeat); ``ratio`` is the distribution of per-repeat
    ratios peer/test, ``speedup`` its median.

    Where the data fit in the last-level cache, :func:`measure_paired`'s back-to-back repeats
    measure an L3-bandwidth bound; this one measures the memory-bandwidth bound
    (reports/benchmarks/relight.md, "cold")."""
    import resource

    repeats = check_int("repeats", repeats, 1)
    warmup = check_int("warmup", warmup, 0)
    nbytes = evict_bytes if evict_bytes is not None else max(64 * 1024 ** 2, 4 * last_level_cache_bytes())
    junk = torch.ones(max(1, int(nbytes) // 4), dtype=torch.float32)
    for _ in range(warmup):
        test()
        peer()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    c0, w0 = time.process_time(), time.perf_counter()
    tt, tp, ratios = _alternate(test, peer, repeats, 1, 1, before=junk.sum)
    ratio = _quantiles(ratios, warmup)
    contention = _contention(r0, c0, w0, ratio, max_switch_rate, max_spread)
    return Paired(_quantiles(tt, warmup), _quantiles(tp, warmup), ratio, contention, ratio.median, None)


def io_bound_fn(bytes_read: int, bytes_written: int) -> Callable[[], Any]:
    """The memory-bandwidth bound of a kernel that reads ``bytes_read`` once and writes
    ``bytes_written`` once: a plain ``copy_`` of that many bytes plus a ``fill_`` of the output's
    bytes (buffers allocated here, outside the timed call)."""
    src = torch.empty(max(1, int(bytes_read)), dtype=torch.uint8).random_(0, 255)
    dst = torch.empty_like(src)
    out = torch.empty(max(1, int(bytes_written)), dtype=torch.uint8)
    return lambda: (dst.copy_(src), out.fill_(1))


def read_bound_fn(bytes_read: int, bytes_written: int) -> Callable[[], Any]:
    """A stricter bound than :func:`io_bound_fn`: the ``bytes_read`` are only read (a sum over them as
    int64, eight bytes per add: a streaming read, not arithmetic, bounds it) and the output's
    ``bytes_written`` filled once. :func:`io_bound_fn`'s copy also writes every byte it reads, so it
    takes longer: on AMD EPYC Zen 3 at 1-2 MB, one thread, the copy took 1.8-1.9x this read
    (``benchmarks/bench_wavelet.py``'s kernel section reports the kernel against both). Buffers are
    allocated here, outside the timed call; the sum's one-element result is the only allocation."""
    n = max(1, -(-int(bytes_read) // 8))
    src = torch.empty(n * 8, dtype=torch.uint8).random_(0, 255).view(torch.int64)
    out = torch.empty(max(1, int(bytes_written)), dtype=torch.uint8)
    return lambda: (src.sum(), out.fill_(1))


def _cpu_field(name: str) -> str | None:
    """The first ``name`` line of ``/proc/cpuinfo`` (None where there is none)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.split(":", 1)[0].strip() == name:
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return None


def _cpu_name() -> str:
    return _cpu_field("model name") or platform.processor() or platform.machine()


def cpu_label(info: dict | None = None) -> str:
    """One line naming a CPU for a report row: model name, family/model and the widest vector ISA the
    kernels use on it (``machine_info``'s ``cpu``, ``cpu_family``, ``cpu_model``, ``cpu_isa``; older records
    without the last three give the name alone), e.g. ``AMD EPYC (family 25 model 1, avx2)``."""
    info = machine_info() if info is None else info
    extra = [f"family {info['cpu_family']} model {info['cpu_model']}" if info.get("cpu_family") is not None else None,
             info.get("cpu_isa")]
    extra = [e for e in extra if e]
    return f"{info.get('cpu')}" + (f" ({', '.join(extra)})" if extra else "")


def machine_info() -> dict[str, Any]:
    """CPU, core and thread counts, Python/torch/numpy versions — recorded with every result."""
    import numpy

    from .._native import cpu_isa

    info: dict[str, Any] = {
        "cpu": _cpu_name(),
        "cpu_family": _cpu_field("cpu family"),
        "cpu_model": _cpu_field("model"),
        "cpu_isa": cpu_isa(),  # avx512 (avx512f + avx512vl) / avx2 / avx / baseline: the widest the kernels have paths for
        "torch_cpu_capability": torch.backends.cpu.get_cpu_capability(),  # the ISA torch's own kernels (and GEMMs) dispatch to
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
        info["omp_wait_policy"] = prt_torch.OMP_POLICY_CHOICE
        from ..codecs.kmeans import gemm_choice

        info["encode_gemm"] = gemm_choice()["how"]  # MKL addmm or oneDNN linear, measured (codecs.kmeans)
    except Exception:  # pragma: no cover
        pass
    return info
