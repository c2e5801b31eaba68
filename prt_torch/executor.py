"""Where batches of independent tasks run: in this process, or as Ray tasks on a cluster.

One small abstraction shared by the chunked precompute runner
(:func:`prt_torch.transfer.run_chunks`: one task per chunk) and the benchmark sweep
(:func:`prt_torch.harness.run.evaluate_run`: one task per codec setting)::

    ex.map(fn, items, on_result=save)   # -> [fn(item) or TaskFailure, ...] in the order of items

``on_result(index, value)`` runs **in the calling process** as each task finishes, so the
caller keeps writing its state (chunk files, records) itself, atomically, exactly as a local
run does: the Ray path reuses the same resumable state, and nothing but the computation moves.

* :class:`LocalExecutor` (``--executor local``, the default): ``fn(item)`` in order, in this
  process; an exception stops the map (as before Ray existed).
* :class:`RayExecutor` (``--executor ray [--ray-address ADDR]``): one Ray task per item. ``fn``
  is put in the object store once and deserialised once per worker process (its captured
  state — a mesh, a ray caster, an evaluator — is not re-sent per task). A task that raises or
  whose worker dies (killed, out of memory) is retried ``max_retries`` times; if it fails
  again it comes back as a :class:`TaskFailure` while the other items finish. Tasks run with
  ``threads`` torch threads (default: the CPUs each task reserves), set before every task, so a
  result does not depend on which worker ran it. Ctrl-C (or an exception from ``on_result``)
  cancels the tasks still pending.

Ray is optional (``pip install 'prt-torch[ray]'``) and imported only when a
:class:`RayExecutor` starts.
"""
from __future__ import annotations

import collections
import dataclasses
import os
import traceback
from typing import Any, Callable, Iterable, Sequence

from ._checks import check_choice, check_int

__all__ = ["Executor", "LocalExecutor", "RayExecutor", "TaskFailure", "ExecutorUnavailable", "EXECUTORS", "RAY_INSTALL_HINT",
           "make_executor", "require_ray", "failures", "torch_threads"]

EXECUTORS = ("local", "ray")
RAY_INSTALL_HINT = "Ray is not installed; install it with: pip install 'prt-torch[ray]' (or pip install 'ray>=2.9')"


class ExecutorUnavailable(ValueError):
    """``--executor ray`` without Ray installed (the message says how to install it)."""


def require_ray():
    """Import Ray, or raise :class:`ExecutorUnavailable` with :data:`RAY_INSTALL_HINT`."""
    try:
        import ray
    except ImportError:
        raise ExecutorUnavailable(f"executor 'ray' is not available: {RAY_INSTALL_HINT}") from None
    return ray


@dataclasses.dataclass
class TaskFailure:
    """An item whose task failed on every attempt.

    Attributes:
        index: position of the item in ``items``.
        item: the item itself.
        error: ``"ExceptionType: message"`` of the last attempt (a dead worker reads
            ``WorkerCrashedError: ...``).
        attempts: how many times it ran (1 + retries).
        traceback: the last attempt's traceback text.
    """

    index: int
    item: Any
    error: str
    attempts: int
    traceback: str = ""


class Executor:
    """Runs ``fn`` over items (see module docstring). Subclasses: :class:`LocalExecutor`, :class:`RayExecutor`."""

    name = "executor"

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any], *,
            on_result: Callable[[int, Any], None] | None = None) -> list[Any]:  # pragma: no cover - interface
        raise NotImplementedError

    @property
    def parallelism(self) -> int:
        """How many tasks can run at once."""
        return 1

    def describe(self) -> dict:
        """JSON-able description (recorded in results)."""
        return {"executor": self.name, "parallelism": self.parallelism}

    def close(self) -> None:
        """Release what the executor started (a local Ray instance)."""

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class LocalExecutor(Executor):
    """``fn(item)`` for each item in order, in this process; ``on_result`` after each. No retry:
    an exception propagates at once (a local run stops as it always has)."""

    name = "local"

    def map(self, fn, items, *, on_result=None):
        out = []
        for i, it in enumerate(items):  # in-process, in order: the reference behaviour
            v = fn(it)
            if on_result is not None:
                on_result(i, v)
            out.append(v)
        return out


# ---------------------------------------------------------------------------------------- Ray

#: per worker process: object-ref hex -> deserialised ``fn`` (the last few maps only)
_FN_CACHE: "collections.OrderedDict[str, Callable]" = collections.OrderedDict()
_FN_CACHE_SIZE = 2


def _run_task(fn_box: list, item: Any, threads: int) -> Any:
    """The body of every Ray task: ``fn(item)`` with ``fn`` fetched once per worker process
    (``fn_box`` holds its object ref inside a list, so Ray does not resolve it per task)."""
    import ray
    import torch

    ref = fn_box[0]
    key = ref.hex()
    fn = _FN_CACHE.get(key)
    if fn is None:
        fn = ray.get(ref)
        _FN_CACHE[key] = fn
        while len(_FN_CACHE) > _FN_CACHE_SIZE:
            _FN_CACHE.popitem(last=False)
    else:
        _FN_CACHE.move_to_end(key)
    if torch.get_num_threads() != threads:
        torch.set_num_threads(threads)
    return fn(item)


def _describe_error(e: BaseException) -> tuple[str, str]:
    """("Type: message", traceback text) of a Ray error, unwrapping the task's own exception."""
    cause = getattr(e, "cause", None)
    if isinstance(cause, BaseException):
        return f"{type(cause).__name__}: {cause}", str(e)
    first = str(e).strip().splitlines()[0] if str(e).strip() else ""
    return f"{type(e).__name__}: {first}", "".join(traceback.format_exception(type(e), e, e.__traceback__))


class RayExecutor(Executor):
    """One Ray task per item, on a local Ray started here or on an existing cluster.

    Args:
        address: an existing cluster (``ray start --head`` prints it, e.g. ``'10.0.0.1:6379'``,
            or ``'auto'`` on a node of the cluster); None starts a local Ray in this process
            (shut down by :meth:`close`).
        num_cpus: CPUs of the local Ray (None: all); not allowed with ``address``.
        cpus_per_task: CPUs each task reserves (Ray's ``num_cpus``): tasks in flight ≤ cluster CPUs / this.
        max_retries: extra attempts for a task that raised or whose worker died.
        threads: torch threads inside each task (None: ``cpus_per_task``).
        max_in_flight: tasks submitted ahead of the results (None: twice the task slots): bounds
            the results waiting in the object store.
    """

    name = "ray"

    def __init__(self, address: str | None = None, *, num_cpus: int | None = None, cpus_per_task: int = 1,
                 max_retries: int = 1, threads: int | None = None, max_in_flight: int | None = None):
        if address is not None and (not isinstance(address, str) or not address.strip()):
            raise ValueError(f"ray address must be a non-empty string such as 'HOST:6379' or 'auto', got {address!r}")
        if address is not None and num_cpus is not None:
            raise ValueError(f"num_cpus={num_cpus!r} applies only to a local Ray (address=None); a cluster has its own CPUs")
        self.address = address
        self.num_cpus = None if num_cpus is None else check_int("num_cpus", num_cpus, 1)
        self.cpus_per_task = check_int("cpus_per_task", cpus_per_task, 1)
        self.max_retries = check_int("max_retries", max_retries, 0)
        self.threads = self.cpus_per_task if threads is None else check_int("threads", threads, 1)
        self.max_in_flight = None if max_in_flight is None else check_int("max_in_flight", max_in_flight, 1)
        self._started = False
        self._remote = None
        self._shipped: tuple[Any, Any] | None = None  # (fn, its object ref): a fn mapped again is not re-sent

    def start(self) -> "RayExecutor":
        """Connect (or start a local Ray) now; idempotent. Raises :class:`ExecutorUnavailable`
        without Ray, ``ConnectionError`` naming the address when nothing answers there within
        ``$PRT_TORCH_RAY_TIMEOUT`` seconds (default 10; Ray itself would retry for minutes)."""
        ray = require_ray()
        if not ray.is_initialized():
            if self.address is not None:
                probe_address(self.address, float(os.environ.get("PRT_TORCH_RAY_TIMEOUT", "10")))
            kw: dict[str, Any] = {"include_dashboard": False, "log_to_driver": True}
            if self.address is None:
                kw["num_cpus"] = self.num_cpus
            ray.init(address=self.address, **kw)
            self._started = True
        if self._remote is None:
            self._remote = ray.remote(_run_task)
        return self

    @property
    def parallelism(self) -> int:
        ray = require_ray()
        if not ray.is_initialized():
            return 1
        return max(1, int(ray.cluster_resources().get("CPU", 1)) // self.cpus_per_task)

    def describe(self) -> dict:
        return {"executor": self.name, "address": self.address or "local", "parallelism": self.parallelism,
                "cpus_per_task": self.cpus_per_task, "threads": self.threads, "max_retries": self.max_retries}

    def map(self, fn, items, *, on_result=None):
        self.start()
        import ray

        items = list(items)
        if not items:
            return []
        task = self._remote.options(num_cpus=self.cpus_per_task, max_retries=self.max_retries, retry_exceptions=True)
        if self._shipped is None or self._shipped[0] is not fn:  # e.g. the target search's one-setting maps
            self._shipped = (fn, ray.put(fn))
        fn_box = [self._shipped[1]]
        limit = self.max_in_flight or 2 * self.parallelism
        out: list[Any] = [None] * len(items)
        pending: dict[Any, int] = {}
        todo = iter(range(len(items)))
        try:
            for i in todo:
                pending[task.remote(fn_box, items[i], self.threads)] = i
                if len(pending) >= limit:
                    break
            while pending:
                (ref,), _ = ray.wait(list(pending), num_returns=1)
                i = pending.pop(ref)
                try:
                    v = ray.get(ref)
                except ray.exceptions.RayError as e:
                    err, tb = _describe_error(e)
                    out[i] = TaskFailure(i, items[i], err, 1 + self.max_retries, tb)
                else:
                    out[i] = v
                    if on_result is not None:
                        on_result(i, v)
                for j in todo:  # keep the pipeline full
                    pending[task.remote(fn_box, items[j], self.threads)] = j
                    break
        except BaseException:
            for ref in pending:  # Ctrl-C or a failing on_result: drop what is queued, interrupt what runs
                ray.cancel(ref, force=False)  # (KeyboardInterrupt in the task; its worker stays up for the next map)
            raise
        return out

    def close(self) -> None:
        if self._started:
            import ray

            ray.shutdown()
            self._started = False
        self._remote = None
        self._shipped = None


def probe_address(address: str, timeout: float) -> None:
    """Refuse, within ``timeout`` seconds, a Ray address ``HOST:PORT`` (or ``ray://HOST:PORT``) where
    nothing accepts a TCP connection: ``ConnectionError`` naming it. ``auto`` and other forms are left
    to Ray (it refuses them at once when no cluster is found)."""
    import socket

    hostport = address[len("ray://"):] if address.startswith("ray://") else address
    host, sep, port = hostport.rpartition(":")
    if not sep or not port.isdigit():
        return
    try:
        with socket.create_connection((host.strip("[]") or "127.0.0.1", int(port)), timeout=timeout):
            pass
    except OSError as e:
        raise ConnectionError(f"--ray-address {address!r}: no Ray cluster answers there ({e.strerror or e}; waited up to {timeout:g} s); "
                              "accepted: the address `ray start --head` printed, of a cluster that is running "
                              "(PRT_TORCH_RAY_TIMEOUT sets the wait)") from None


def make_executor(name: str = "local", address: str | None = None, **kwargs) -> Executor:
    """The executor called ``name`` (``'local'`` or ``'ray'``; ``address`` only with ``'ray'``).
    ``'ray'`` checks that Ray is importable first (:class:`ExecutorUnavailable` otherwise) but
    connects only when it first runs something."""
    check_choice("executor", name, EXECUTORS)
    if name == "local":
        if address is not None:
            raise ValueError(f"ray address {address!r} given with executor 'local'; accepted: executor 'ray' with an address")
        if kwargs:
            raise TypeError(f"executor 'local' takes no options, got {sorted(kwargs)}")
        return LocalExecutor()
    require_ray()
    return RayExecutor(address, **kwargs)


def failures(results: Iterable[Any]) -> list[TaskFailure]:
    """The :class:`TaskFailure` entries of a ``map`` result."""
    return [r for r in results if isinstance(r, TaskFailure)]


class torch_threads:
    """``with torch_threads(n):`` runs the block with ``torch.set_num_threads(n)`` (which the
    relighting kernels follow too), restoring the previous count after.

    Why speed-ups are timed in one thread (reports/benchmarks/timing_trust.md; the same holds for the
    small torch steps of a precompute's chunk, issue 42: reports/benchmarks/transfer_diffuse.md): a ratio of two
    multi-threaded timings moves with the machine's load and with OpenMP's wait policy — each
    parallel region pays a wake-up or a barrier stall that a busy machine stretches, and short
    calls run many regions per unit of work (measured on 2 cores: PASSIVE alone halved the
    fastest codec's speed-up on an idle machine, 30× → 14×). One thread has no regions to
    wait on, so the paired ratio is the ratio of the work itself."""

    def __init__(self, n: int):
        self.n = check_int("threads", n, 1)
        self.prev = None

    def __enter__(self) -> "torch_threads":
        import torch

        self.prev = torch.get_num_threads()
        torch.set_num_threads(self.n)
        return self

    def __exit__(self, *exc) -> None:
        import torch

        torch.set_num_threads(self.prev)
