"""Ray generation of the uniform-sampling diffuse precompute in one compiled pass.

For a chunk of k vertices and N shared sample directions, the rays traced are the pairs
(vertex v, direction s) with n_v · s > 0, grouped by vertex in row-major order (course notes
2005, "Precomputation": only the upper hemisphere contributes). numpy builds them in six passes
over k·N-sized arrays (``repeat``, ``flatnonzero``, a subtraction, ``repeat`` of the origins,
``take`` of the directions): 21 ms for 2048 vertices × 1024 directions here, about a tenth of the
precompute's time, during which the ray-casting workers wait. :func:`upper_rays` writes the four
ray arrays in one pass per thread over ``cos`` (same values, same order, so the same bits as the
numpy path: tests compare them). The C is ``prt_torch/kernels/raygen.c``, built by :mod:`prt_torch._native`; without a C compiler, or
with ``PRT_TORCH_NATIVE=0``, :func:`upper_rays` returns None and the caller keeps numpy.
"""
from __future__ import annotations

import ctypes
import os
import threading

import numpy as np

from .._native import LIBRARIES, compile_library, kernel_sources

__all__ = ["upper_rays"]

#: the C source (prt_torch/kernels/raygen.c) and compiler flags
_SOURCES, _FLAGS = LIBRARIES["raygen"][0], list(LIBRARIES["raygen"][1])

_FLAGS = ["-O3", "-march=native", "-fopenmp", "-shared", "-fPIC", "-std=c99"]
_lock = threading.Lock()
_state: dict = {}


def _lib() -> ctypes.CDLL | None:
    if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return None
    if "lib" not in _state:
        with _lock:
            if "lib" not in _state:
                i64, vp, ci = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int
                _state["lib"], _state["why"] = compile_library("raygen", kernel_sources(_SOURCES), _FLAGS, {
                    "prt_count_up": [i64, i64, vp, vp, ci],
                    "prt_fill_up": [i64, i64, vp, vp, vp, vp, vp, vp, vp, vp, ci],
                })
    return _state["lib"]


def _buffer(work: dict | None, name: str, shape: tuple, dtype) -> np.ndarray:
    """A fresh array, or (``work`` given) a view of a buffer kept in ``work`` and grown as needed:
    a chunk's 40 MB of rays written into fresh memory cost more in page faults than the pass."""
    if work is None:
        return np.empty(shape, dtype)
    n = int(np.prod(shape))
    buf = work.get(name)
    if buf is None or buf.size < n or buf.dtype != dtype:
        buf = work[name] = np.empty(max(n, 1), dtype)
    return buf[:n].reshape(shape)


def upper_rays(cos: np.ndarray, origins: np.ndarray, dirs: np.ndarray, threads: int | None = None, work: dict | None = None):
    """The rays with ``cos > 0``, grouped by vertex, or None without the compiled pass.

    ``cos float64 [k, N]`` (n_v · s), ``origins float32 [k, 3]`` (already offset), ``dirs
    float32 [N, 3]`` → ``(i int64 [R], j int64 [R], o float32 [R, 3], d float32 [R, 3])``, equal
    to ``(np.repeat(arange(k), counts), flatnonzero(cos > 0) - i·N, origins[i], dirs[j])``.
    ``threads``: default 1 (measured on 2 cores, 2048 × 1024: 3.4 ms on one thread, 3–8 ms on
    two, whose OpenMP region stalls on a shared machine). ``work``: a dict of buffers the arrays are written
    into (views of them are returned, overwritten by the next call given the same dict).
    """
    lib = _lib()
    if lib is None:
        return None
    k, N = cos.shape
    if origins.shape != (k, 3) or dirs.shape != (N, 3):
        raise ValueError(f"upper_rays: origins {origins.shape}, dirs {dirs.shape}; accepted: [{k}, 3] and [{N}, 3] for cos [{k}, {N}]")
    cos = np.ascontiguousarray(cos, np.float64)
    origins = np.ascontiguousarray(origins, np.float32)
    dirs = np.ascontiguousarray(dirs, np.float32)
    nth = int(threads or 1)
    counts = np.empty(k, np.int64)
    lib.prt_count_up(k, N, cos.ctypes.data, counts.ctypes.data, nth)
    starts = np.zeros(k, np.int64)
    np.cumsum(counts[:-1], out=starts[1:])
    R = int(counts.sum())
    i, j = _buffer(work, "i", (R,), np.int64), _buffer(work, "j", (R,), np.int64)
    o, d = _buffer(work, "o", (R, 3), np.float32), _buffer(work, "d", (R, 3), np.float32)
    lib.prt_fill_up(k, N, cos.ctypes.data, starts.ctypes.data, origins.ctypes.data, dirs.ctypes.data, i.ctypes.data, j.ctypes.data,
                    o.ctypes.data, d.ctypes.data, nth)
    return i, j, o, d
