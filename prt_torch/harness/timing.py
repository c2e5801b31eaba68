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
import threading
import time
from dataclasses import asdict, dataclass
from typing import Any, Callable

import torch

from .._checks import check_int
from ..executor import torch_threads  # noqa: F401  (re-exported: where it lived before issue 42)

__all__ = ["Timing", "Paired", "measure", "measure_paired", "measure_paired_cold", "last_level_cache_bytes", "torch_threads",
           "flush_caches", "flush_method", "working_set", "release_eviction_buffer", "io_bound_fn", "read_bound_fn",
           "machine_info", "cpu_label", "rate_policy"]


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
    #: :func:`measure_paired_cold`'s eviction before each call: method, bytes, median seconds (None elsewhere)
    eviction: dict | None = None

    def as_dict(self) -> dict[str, Any]:
        return {"test": self.test.as_dict(), "peer": self.peer.as_dict(), "ratio": self.ratio.as_dict(),
                "contention": dict(self.contention), "speedup": self.speedup, "floor": self.floor,
                "eviction": self.eviction}


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
    ``test`` is ``n_t`` calls (of ``peer``, ``n_p``), in a row, or with ``before`` each call preceded by
    ``before()`` untimed (the sample: the sum of its calls' times), timed by ``clock``. Returns the per-call
    times of each side and the per-pair ratios peer/test."""
    tt: list[float] = []
    tp: list[float] = []
    ratios: list[float] = []
    for i in range(repeats):
        pair = {}
        for name in (("test", "peer") if i % 2 == 0 else ("peer", "test")):
            fn, n = (test, n_t) if name == "test" else (peer, n_p)
            if before is not None:
                dt = 0.0
                for _ in range(n):
                    before()
                    t0 = clock()
                    fn()
                    dt += clock() - t0
                pair[name] = dt / n
                continue
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


#: what ``prt_flush_method`` of the cacheflush library reports (prt_torch/kernels/cacheflush.c)
FLUSH_METHODS = {1: "clflush", 2: "clflushopt", 3: "dc civac"}

_FLUSH: dict = {}
_FLUSH_LOCK = threading.Lock()
#: the junk buffer of the fallback eviction (:func:`_junk`): allocated once, kept until :func:`release_eviction_buffer`
_JUNK: dict = {}


def _flush_lib():
    """The compiled cache-flush helper (``prt_torch/kernels/cacheflush.c``), or None (no compiler, or no flush
    instruction on this CPU). A measuring tool, not a computation path: loaded whatever ``PRT_TORCH_NATIVE`` says
    (that variable chooses the relighting path being timed, not how the caches are emptied between calls)."""
    if "lib" not in _FLUSH:
        with _FLUSH_LOCK:
            if "lib" not in _FLUSH:
                import ctypes

                from .._native import LIBRARIES, compile_library, kernel_sources

                names, flags = LIBRARIES["cacheflush"]
                lib, why = compile_library("cacheflush", kernel_sources(names), list(flags), {
                    "prt_flush_method": [], "prt_flush_line_bytes": [],
                    "prt_flush_ranges": [ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p]})
                if lib is not None and lib.prt_flush_method() not in FLUSH_METHODS:
                    lib, why = None, f"no cache-flush instruction in this build for {platform.machine()} ({why})"
                _FLUSH["why"] = why
                _FLUSH["lib"] = lib
    return _FLUSH["lib"]


def flush_method() -> str | None:
    """How :func:`flush_caches` evicts on this machine: ``'clflushopt'`` (x86-64 CPUs that have it),
    ``'clflush'`` (other x86-64), ``'dc civac'`` (aarch64), or None where the helper is not available (no C
    compiler, another architecture: :func:`measure_paired_cold` then reads its junk buffer)."""
    lib = _flush_lib()
    return None if lib is None else FLUSH_METHODS[lib.prt_flush_method()]


def _byte_range(i: int, t: Any) -> tuple[int, int] | None:
    """``(address, length)`` of the bytes tensor or array ``t`` (item ``i`` of the caller's list) can reach:
    from its lowest to its highest element, so a strided view spans the gaps between its elements; None
    when it holds no element. Refuses anything else in one line."""
    if isinstance(t, torch.Tensor):
        if t.device.type != "cpu":
            raise ValueError(f"flush_caches: tensors[{i}] is on {t.device}; accepted: CPU tensors (a device's memory is "
                             f"not in the CPU's caches)")
        if t.layout != torch.strided:
            raise ValueError(f"flush_caches: tensors[{i}] has layout {t.layout}; accepted: strided tensors (pass a "
                             f"sparse tensor's indices and values)")
        if t.numel() == 0:
            return None
        ptr, shape, strides, item = t.data_ptr(), t.shape, [s * t.element_size() for s in t.stride()], t.element_size()
    else:
        import numpy as np

        if not isinstance(t, np.ndarray):
            raise ValueError(f"flush_caches: tensors[{i}] is a {type(t).__name__}; accepted: CPU torch tensors or "
                             f"numpy arrays")
        if t.size == 0:
            return None
        ptr, shape, strides, item = t.__array_interface__["data"][0], t.shape, t.strides, t.itemsize
    lo = sum(min(0, (n - 1) * s) for n, s in zip(shape, strides))
    hi = sum(max(0, (n - 1) * s) for n, s in zip(shape, strides)) + item
    return ptr + lo, hi - lo


def _flush_ranges(tensors: Any) -> tuple[torch.Tensor, int]:
    """The merged byte ranges of ``tensors`` (a sequence of CPU tensors / numpy arrays) as an int64 tensor
    ``[2, n]`` (addresses, lengths), and their total bytes."""
    if isinstance(tensors, torch.Tensor) or not hasattr(tensors, "__iter__"):
        raise ValueError(f"flush_caches: tensors is a {type(tensors).__name__}; accepted: a list or tuple of CPU "
                         f"torch tensors or numpy arrays (working_set(...) gathers them)")
    spans = sorted(r for i, t in enumerate(tensors) if (r := _byte_range(i, t)) is not None)
    merged: list[list[int]] = []
    for a, n in spans:
        if merged and a <= merged[-1][0] + merged[-1][1]:
            merged[-1][1] = max(merged[-1][1], a + n - merged[-1][0])
        else:
            merged.append([a, n])
    arr = torch.tensor(merged, dtype=torch.int64).reshape(-1, 2).t().contiguous()
    return arr, int(arr[1].sum()) if merged else 0


def flush_caches(tensors: Any) -> int:
    """Write back and evict from every cache level the bytes of ``tensors`` (a list or tuple of CPU torch tensors
    of any dtype, shape and strides — a strided view's whole span — or numpy arrays; empty ones are skipped):
    CLFLUSHOPT / CLFLUSH per 64-byte line then a fence on x86-64, ``dc civac`` on aarch64
    (``prt_torch/kernels/cacheflush.c``). The data are unchanged. Costs in proportion to the bytes, whatever
    the size of the last-level cache. Returns the bytes flushed (overlapping tensors counted once).

    Raises ``ValueError`` (one line naming the item) for anything else — a GPU or sparse tensor, another type —
    and ``RuntimeError`` where the helper is not available here (:func:`flush_method` is None)."""
    arr, total = _flush_ranges(tensors)
    lib = _flush_lib()
    if lib is None:
        raise RuntimeError(f"flush_caches: the cache-flush helper is not available here ({_FLUSH.get('why')}); accepted: "
                           f"a machine with a C compiler on x86-64 or aarch64 (measure_paired_cold falls back to a junk read)")
    if arr.shape[1]:
        lib.prt_flush_ranges(arr.shape[1], arr[0].data_ptr(), arr[1].data_ptr())
    return total


def working_set(*objs: Any, max_depth: int = 8) -> list:
    """The CPU tensors (strided) and numpy arrays reachable from ``objs``: what a timed call that holds them
    can touch, for ``measure_paired_cold(..., evict=...)``. Followed: tensors and arrays themselves, dicts,
    lists, tuples and sets, a function's closure (the variables a ``lambda`` or nested function closes over; for
    a function in ``objs`` also the module-level variables its code names, a script's lambda; a bound method's
    object), and the attributes (``__dict__`` and ``__slots__``) of prt_torch's own objects —
    a codec, an encoding with its cached kernel plans, a prepared relighter, a light — to ``max_depth`` levels;
    not other libraries' objects (a torch module, a ctypes array). Each tensor once, in the order found."""
    import types

    import numpy as np

    out: list = []
    seen: set[int] = set()
    stack = [(o, 0) for o in reversed(objs)]
    while stack:
        o, depth = stack.pop()
        if id(o) in seen or depth > max_depth or o is None or isinstance(o, (str, bytes, int, float, bool)):
            continue
        seen.add(id(o))
        if isinstance(o, torch.Tensor):
            if o.device.type == "cpu" and o.layout == torch.strided:
                out.append(o)
            continue
        if isinstance(o, np.ndarray):
            out.append(o)
            continue
        kids: list = []
        if isinstance(o, dict):
            kids = list(o.values())
        elif isinstance(o, (list, tuple, set, frozenset)):
            kids = list(o)
        elif isinstance(o, types.FunctionType):
            kids = [c.cell_contents for c in (o.__closure__ or ()) if _cell_filled(c)]
            if depth == 0:  # one passed here: also the module-level variables it names (a script's lambda)
                g = o.__globals__
                kids += [g[n] for n in o.__code__.co_names if n in g and not isinstance(g[n], (types.ModuleType, type))]
        elif isinstance(o, types.MethodType):
            kids = [o.__self__, o.__func__]
        elif type(o).__module__.startswith("prt_torch"):
            kids = list(getattr(o, "__dict__", {}).values())
            for cls in type(o).__mro__:
                for name in getattr(cls, "__slots__", ()):
                    if hasattr(o, name) and name not in ("__dict__", "__weakref__"):
                        kids.append(getattr(o, name))
        stack.extend((k, depth + 1) for k in reversed(kids))
    return out


def _cell_filled(cell) -> bool:
    try:
        cell.cell_contents
    except ValueError:  # a variable the function closes over that is not yet assigned
        return False
    return True


def _junk(nbytes: int) -> torch.Tensor:
    """The fallback eviction's buffer of ``nbytes`` (float32 ones), allocated and filled once and kept at module
    level (:func:`release_eviction_buffer` frees it): allocating and filling 1920 MiB took 6.9 s on a busy
    Xeon, once per ``measure_paired_cold`` call before."""
    n = max(1, int(nbytes) // 4)
    t = _JUNK.get("t")
    if t is None or t.numel() != n:
        _JUNK.pop("t", None)
        t = _JUNK["t"] = torch.ones(n, dtype=torch.float32)
    return t


def release_eviction_buffer() -> int:
    """Free :func:`measure_paired_cold`'s cached junk buffer (the fallback eviction's); returns its bytes (0: none
    was held)."""
    t = _JUNK.pop("t", None)
    return 0 if t is None else t.numel() * 4


def measure_paired_cold(test: Callable[[], Any], peer: Callable[[], Any], repeats: int = 15, warmup: int = 1,
                        evict_bytes: int | None = None, max_switch_rate: float = 50.0, max_spread: float = 0.5,
                        evict: Any = None, clock: Callable[[], float] = time.perf_counter, calls: int = 1) -> Paired:
    """:func:`measure_paired` from cold caches: every timed call is a single call, preceded (untimed) by an
    eviction of what the previous calls left in the caches, so each side reads its inputs from memory and
    writes its outputs back, as in a render loop whose other work between frames evicts them. The two
    sides alternate (order swapped every repeat); ``ratio`` is the distribution of per-repeat ratios
    peer/test, ``speedup`` its median. ``calls`` > 1: a sample is that many such calls (each after its own
    eviction), its time their mean — a steadier per-repeat ratio for calls of a few microseconds.

    The eviction: with ``evict`` (a list of the CPU tensors / numpy arrays the two sides read and write —
    :func:`working_set` of the two callables gathers what they close over) the bytes of those tensors are
    flushed from every cache level (:func:`flush_caches`: CLFLUSHOPT, CLFLUSH or ``dc civac`` per line; dirty
    lines written back during the flush, not in the timed call), at a cost in proportion to the data. Without
    ``evict``, or where the flush helper is not available (:func:`flush_method` None), a read of
    ``evict_bytes`` (default 4× the last-level cache, at least 64 MiB; its lines are clean, so no write-back
    lands in the timed call) from a junk buffer allocated once per process (:func:`release_eviction_buffer`);
    its cost grows with the cache (1920 MiB per call where sysfs lists a 480 MiB L3). The junk read also evicts
    the code, the interpreter's and torch's state and the page tables, a per-call cost that is not the data's
    (0.1–3 ms a call on a Xeon VM, reports/benchmarks/cold_evict.md): the flush times the data alone.
    Paired's ``eviction`` says which ran: ``method`` (``clflushopt``, ``clflush``, ``dc civac`` or ``junk
    read``), ``bytes`` per eviction and ``median_s``, its median time per call (and ``why`` the flush was not
    used, where ``evict`` was given). ``clock`` times the calls as in :func:`measure_paired` (``time.thread_time``:
    this thread's CPU time, in one thread only; a stall on memory is CPU time of the thread).

    Where the data fit in the last-level cache, :func:`measure_paired`'s back-to-back repeats
    measure an L3-bandwidth bound; this one measures the memory-bandwidth bound
    (reports/benchmarks/relight.md, "cold"; the two evictions agree: reports/benchmarks/cold_evict.md)."""
    import resource

    repeats = check_int("repeats", repeats, 1)
    warmup = check_int("warmup", warmup, 0)
    calls = check_int("calls", calls, 1)
    if clock is time.thread_time and torch.get_num_threads() != 1:
        raise ValueError(f"measure_paired_cold: clock=time.thread_time counts only the calling thread's CPU time, and torch "
                         f"runs {torch.get_num_threads()} threads; accepted: one thread (with timing.torch_threads(1): ...)")
    method = flush_method() if evict is not None else None
    if method is not None:
        arr, nbytes = _flush_ranges(evict)
        lib, n = _flush_lib(), arr.shape[1]
        a0, a1 = arr[0].data_ptr(), arr[1].data_ptr()

        def evict_now():
            if n:
                lib.prt_flush_ranges(n, a0, a1)
    else:
        if evict is not None:
            _flush_ranges(evict)  # bad input is refused here too
        nbytes = int(evict_bytes if evict_bytes is not None else max(64 * 1024 ** 2, 4 * last_level_cache_bytes()))
        evict_now = _junk(nbytes).sum
        method = "junk read"
    costs: list[float] = []

    def before():
        t0 = time.perf_counter()
        evict_now()
        costs.append(time.perf_counter() - t0)

    for _ in range(warmup):
        test()
        peer()
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    c0, w0 = time.process_time(), time.perf_counter()
    tt, tp, ratios = _alternate(test, peer, repeats, calls, calls, before=before, clock=clock)
    ratio = _quantiles(ratios, warmup)
    contention = _contention(r0, c0, w0, ratio, max_switch_rate, max_spread)
    eviction = {"method": method, "bytes": nbytes, "median_s": statistics.median(costs)}
    if evict is not None and method == "junk read":
        eviction["why"] = _FLUSH.get("why")
    return Paired(_quantiles(tt, warmup, calls), _quantiles(tp, warmup, calls), ratio, contention, ratio.median, None, eviction)


def io_bound_fn(bytes_read: int, bytes_written: int) -> Callable[[], Any]:
    """The memory-bandwidth bound of a kernel that reads ``bytes_read`` once and writes
    ``bytes_written`` once: a plain ``copy_`` of that many bytes plus a ``fill_`` of the output's
    bytes (buffers allocated here, outside the timed call)."""
    src = torch.empty(max(1, int(bytes_read)), dtype=torch.uint8).random_(0, 255)
    dst = torch.empty_like(src)
    out = torch.empty(max(1, int(bytes_written)), dtype=torch.uint8)
    return lambda: (dst.copy_(src), out.fill_(1))


def read_bound_fn(bytes_read: int, bytes_written: int, huge: bool = False, pick: int = 1) -> Callable[[], Any]:
    """A stricter bound than :func:`io_bound_fn`: the ``bytes_read`` are only read (a sum over them as
    int64, eight bytes per add: a streaming read, not arithmetic, bounds it) and the output's
    ``bytes_written`` filled once. :func:`io_bound_fn`'s copy also writes every byte it reads, so it
    takes longer: on AMD EPYC Zen 3 at 1-2 MB, one thread, the copy took 1.8-1.9x this read
    (``benchmarks/bench_wavelet.py``'s kernel section reports the kernel against both). Buffers are
    allocated here, outside the timed call; the sum's one-element result is the only allocation.

    ``huge``: both buffers in one mapping advised for 2 MiB pages (:class:`prt_torch.io.HugePageArena`, whole huge
    pages; torch's buffers where huge pages are unavailable or ``PRT_TORCH_HUGEPAGES=0``). Measured on the Intel Xeon
    VM (reports/benchmarks/wavelet_hugepages_small.md): no steadier than the 4 KB read — near the L2's size a read's
    time depends on which pages it got (1.53 MB: 16.6-22.9 us over 4 KB buffers, 16.8-22.9 over 2 MiB pages).

    ``pick`` > 1: ``pick`` candidate reads are built at once (distinct pages) and timed here (each the fastest of
    five short samples of back-to-back calls, wall time), and the one of median time is returned, the others freed:
    the bound of a typical placement rather than of whichever pages one allocation got (a 1.53 MB read, 18 reads in six
    fresh processes on the Intel Xeon VM: 16.7-20.7 us with one buffer each, 18.4-20.1 with the median of eight)."""
    from .. import io

    pick = check_int("pick", pick, 1)
    n = max(1, -(-int(bytes_read) // 8))
    nw = max(1, int(bytes_written))

    def one() -> Callable[[], Any]:
        if huge:
            arena = io.HugePageArena(n * 8 + nw + io.HugePageArena.ALIGN)
            src = arena.zeros((n * 8,), torch.uint8).random_(0, 255).view(torch.int64)
            out = arena.zeros((nw,), torch.uint8)
        else:
            src = torch.empty(n * 8, dtype=torch.uint8).random_(0, 255).view(torch.int64)
            out = torch.empty(nw, dtype=torch.uint8)
        return lambda: (src.sum(), out.fill_(1))

    if pick == 1:
        return one()
    cands = [one() for _ in range(pick)]

    def fastest(fn: Callable[[], Any]) -> float:
        fn()
        calls = _inner(fn, 2e-4)
        best = math.inf
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(calls):
                fn()
            best = min(best, (time.perf_counter() - t0) / calls)
        return best

    times = [fastest(c) for c in cands]
    return cands[sorted(range(pick), key=times.__getitem__)[pick // 2]]


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
