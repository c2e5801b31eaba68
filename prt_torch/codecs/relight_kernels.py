"""Fused CPU kernels for relighting straight from the compressed forms (Sloan 2003 §6; Green 2005).

Per point p of cluster k = k(p) with weights w_p (n_k of them) and per-cluster constants
``T_k = [M_0^k l, M_1^k l, ...]`` (computed once per light by ``AffineCodec.cluster_constants``):

* rows:  ``e_p = T_k[0] + Σ_{i<n_k} w_p^i T_k[1+i]``                 (no view, ``[P, n_out·C]``)
* dense: ``o_p = Σ_r y_pr e_{p,r}``                                     (Sloan 2003 §3.1, ``[P, C]``)
* taps:  ``o_p = Σ_t g_pt e_{p,idx_pt}``                                (Lehtinen & Kautz 2003 eq. (13))

One pass over the codes (labels, weights, view), the constants table staying in cache: the
view is folded in per point before anything of size n_out·C leaves the core, so a dense view
costs J·n_out·C multiply-adds per point and no ``[P, n_out, C]`` intermediate (Sloan 2003's
cost model). torch has no fused op for these small per-point contractions (a GEMM, gather or
``embedding_bag`` each leave an intermediate as large as the view behind), so they are C, in
``prt_torch/kernels/`` (``affine_constants.c``, ``affine_rows.c``, ``affine_dense.c``,
``affine_taps.c``, ``relight_plan.c``, ``sg_lookup.c`` and their headers; ``prt_kernels.h`` declares
the entry points), compiled on first use with the system C compiler (``cc``, OpenMP, about 10 s
here) or at ``pip install`` time (:mod:`prt_torch._native`), cached on disk by a hash of the
sources, flags and CPU, and called through ctypes (the GIL is released). This module keeps the
planning (layouts, argument blocks, checks) and the calls. Without a compiler — or with ``PRT_TORCH_NATIVE=0`` — :func:`native` returns None
and ``AffineCodec.relight`` uses its torch formulation, which gives the same results to
float32 rounding (tests run both).

Per light, ``AffineCodec.relight`` runs a :class:`Plan` of its encoding (:func:`plan`, built once
and cached; :func:`run_plan`): the arguments of the constants kernel and of the point kernel
that do not change between lights, as one int64 array, handed to ``prt_relight_plan`` — one
ctypes call, the same kernels as :func:`constants` followed by :func:`affine_rows`,
:func:`affine_dense` or :func:`affine_taps` (tests hold them to the same bits).

Codes as stored by ``AffineCodec`` (no copies): labels ``[P]`` uint8/int16/int32 (absent when
K = 1), weights ``[P, n_max]`` float32 (row stride n_max, the first n used) or packed (the
n_{k(p)} weights of each point one after the other; ``offsets int64 [P]`` where each starts,
``n_vectors int64 [K]``). Constants float32 contiguous: ``[K, J, n_out·C]`` (rows, dense) or
``[K, n_out, J·C]`` (taps), J = (1 if a mean) + n. Points may be visited in a given order
(CPCA: cluster by cluster within blocks, from codes stored in that order; ``AffineCodec``
chooses), and the result written into a given tensor (``out``). Without a view, and with an
RGB dense view of up to 24 rows (with 16 vector registers, 17–24 rows as vector groups 2 + 1; two points within one block of 8),
two consecutive visits of one cluster with the same term count are combined in one pass over
``T_k`` (with a dense view each load kept in a register for both points' multiply-adds; each
point's sums in the same order: same bits). Compiled with ``-ffp-contract=fast``: each
``a += w·t`` is one fused multiply-add where the CPU has them (measured, paired: dense views
3–15% faster; results differ from separate rounding by float32 rounding only, and a point's
bits still do not depend on pairing, order or threads).

The Gaussian codec's relighting (Green 2005 eq. 2.7 and §2.3) runs here too: per lobe, the
prefiltered cube-map lookup (face, bilinear texels, linear in log σ between levels) and the
weighted sum over the lobes (:func:`sg_lookup_sum`); with view taps, the blend of the tapped
views' lobes as well (:func:`sg_taps`) — one pass per vertex instead of ~30 torch ops over
lobe-sized intermediates.
"""
from __future__ import annotations

import ctypes
import os
import threading
import weakref

import torch

from .._checks import check_finite_float32, tensor_version
from .._native import LIBRARIES, compile_library, cpu_isa, kernel_isa, kernel_sources

__all__ = ["native", "native_status", "kernel_path", "constants", "constants_layout", "model_t", "affine_rows", "affine_dense", "affine_taps",
           "plan", "run_plan", "light_flagged", "Plan", "sg_lookup_sum", "sg_taps", "lobe_layout", "fits", "MAX_ROW"]

#: largest per-point row (n_out·C for dense views, J·C for taps) the kernels hold on the stack
MAX_ROW = 4096

#: the kernels' C sources (files in prt_torch/kernels/, compiled together into one library) and compiler flags
_SOURCES, _FLAGS = LIBRARIES["relight"][0], list(LIBRARIES["relight"][1])
_lock = threading.Lock()
_state: dict = {}


def _compile(sources: dict[str, str] | None = None, flags: list[str] | None = None) -> tuple[ctypes.CDLL | None, str]:
    """The library built from ``sources`` (``{file name: C text}``; default: the files of ``_SOURCES``
    in prt_torch/kernels/) and ``flags`` (default: the module's ``_FLAGS``, read at call time: tests
    patch it; ``benchmarks/ab_kernels.py`` passes another revision's sources and flags), followed by what
    ``PRT_TORCH_KERNEL_ISA`` adds (``_native.kernel_isa``: ``avx2`` builds the AVX2 paths on an AVX-512 CPU)."""
    i64, vp, ci = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int
    flags = list(_FLAGS if flags is None else flags) + list(kernel_isa()[1])
    common = [vp, ci, vp, i64, vp, vp, i64, ci, vp, i64]
    return compile_library("relight", kernel_sources(_SOURCES) if sources is None else sources, flags, {
        "prt_affine_rows": [i64, i64, i64, *common, vp, vp, ci, ci],
        "prt_affine_dense": [i64, i64, i64, i64, i64, *common, vp, vp, vp, ci, ci],
        "prt_affine_taps": [i64, i64, i64, *common, i64, vp, vp, vp, vp, ci, ci],
        "prt_constants": [i64] * 7 + [vp, vp, vp] + [i64] * 4 + [vp, ci, ci],
        "prt_constants_lanes": [i64] * 5 + [vp, vp, vp] + [i64] * 2 + [ci],
        "prt_relight_plan": [vp, vp, vp, vp, vp, vp, ci],
        "prt_dense_pad": [i64],
        "prt_plan_path": [vp],
        "prt_isa": [],
        "prt_rows_pad": [i64, i64],
        "prt_sg_lookup_sum": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, i64, i64, vp, i64, vp, ci],
        "prt_sg_lookup_sum_q": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, i64, i64, vp, i64, vp, ci],
        "prt_sg_prepare": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, i64, i64, vp, vp, ci],
        "prt_sg_lookup_prepared": [i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, vp, i64, i64, vp, vp, ci],
        "prt_sg_taps": [i64, i64, i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, vp, i64, i64, vp, i64, vp, ci],
        "prt_sg_taps_prepare": [i64, i64, i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, i64, i64, vp, vp, vp, ci],
        "prt_sg_taps_prepared": [i64, i64, i64, i64, i64, i64, vp, vp, vp, i64, i64, i64, vp, vp, vp, vp, vp, i64, i64, vp, vp, ci],
    })


try:  # CPython's os.environ keeps its values in a dict of encoded keys: a lookup there costs 0.05 µs per
    # relight, os.environ.get 0.7 µs (its KeyError path when the variable is unset); both see os.environ's updates
    _ENV, _ENV_KEY, _ENV_OFF = os.environ._data, os.environ.encodekey("PRT_TORCH_NATIVE"), os.environ.encodevalue("0")
except AttributeError:  # pragma: no cover  (another Python)
    _ENV = None


def _disabled() -> bool:
    """``PRT_TORCH_NATIVE=0`` in the environment (read at every call: tests and benchmarks set it)."""
    if _ENV is not None:
        return _ENV.get(_ENV_KEY) == _ENV_OFF
    return os.environ.get("PRT_TORCH_NATIVE", "1") == "0"  # pragma: no cover


def native() -> ctypes.CDLL | None:
    """The compiled kernels (compiled on the first call of a process, then cached on disk), or
    None: no C compiler, a failed compile, or ``PRT_TORCH_NATIVE=0``. ``PRT_TORCH_KERNEL_ISA``
    (``native``, ``avx2``, ``avx512``: ``_native.kernel_isa``) is read at that first call, once per
    process: plans and layouts (``dense_pad``, ``rows_pad``) are those of the library loaded then; a
    value that is not accepted raises ``ValueError`` naming it."""
    if _disabled():
        return None
    if "lib" not in _state:
        with _lock:
            if "lib" not in _state:
                isa, extra = kernel_isa()  # raises for a bad value before anything is compiled or cached
                _state["lib"], _state["why"] = _compile()
                _state["isa_choice"], _state["flags"] = isa, " ".join(list(_FLAGS) + list(extra))
    return _state["lib"]


def native_status() -> dict:
    """``{'native': bool, 'detail': str}``: whether relighting uses the compiled kernels and why (not)."""
    if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return {"native": False, "detail": "disabled by PRT_TORCH_NATIVE=0"}
    lib = native()
    return {"native": lib is not None, "detail": _state.get("why", "")}


#: prt_plan_path's codes (PRT_ROWS_*, PRT_DENSE_*, PRT_TAPS_* in kernels/prt_kernels.h, in that order): the point
#: kernel a plan runs, as the kernels dispatch
_PATH_NAMES = {1: "rows: VQ row copy",
               2: "rows/1 vector: VQ RGB, 8 points (uint8 labels: 4 points in three 16-byte stores without AVX-512; else packed)",
               3: "rows/1 vector: VQ row copy",
               4: "rows/1 vector: PCA RGB, 8 points in lanes (AVX2)", 5: "rows/1 vector: fixed term count (weights broadcast)",
               6: "rows/1 vector: one point at a time", 7: "rows: 16 lanes (AVX-512)", 8: "rows: 8 lanes, two points per load",
               9: "rows: 8 lanes", 10: "dense: VQ, 8 lanes, 8 points", 11: "dense: 16 lanes (AVX-512)",
               12: "dense: 8 lanes, RGB, two points per load", 13: "dense: 8 lanes, RGB", 14: "dense: per colour, 8 lanes",
               15: "taps: one term", 16: "taps: RGB, 8 points (8 lanes)", 17: "taps: general"}
#: the loop within a path (AVX2 builds without AVX-512: prt_plan_path returns path + 32 x its code, PRT_SUBPATH and
#: PRT_SEQ_TAPS_* / PRT_FIXED_U8_RGB / PRT_PAIRS_GROUPS in kernels/prt_kernels.h), by path
_SUBPATH_NAMES = {5: {1: "uint8 labels, RGB: 8 labels per load, 16-byte stores"},
                  12: {1: "vector groups 2 + 1, 16 registers"},
                  16: {1: "points in order, constant strides", 2: "points in order, constant strides, weight rows in place",
                       3: "points in order, one cluster, 4 taps"}}


def _isa_name(bits: int) -> str:
    return "avx512" if bits & 8 else "avx2" if bits & 2 and bits & 4 else "avx" if bits & 1 else "baseline"


def kernel_path(pl: "Plan | None" = None) -> dict:
    """Which compiled code runs (issue 42 §4: a benchmark row names its kernel path): ``backend``
    (``native``, or ``torch`` with ``why``), the library's instruction set as its ``#if`` branches
    saw it at compile time (``isa``: avx512 / avx2 / avx / baseline, from ``prt_isa``; ``w16``: the
    16-lane AVX-512 affine kernels built; ``sg16``: the Gaussian codec's 16-lobe ones), the
    ``PRT_TORCH_KERNEL_ISA`` choice, this CPU's own (``cpu_isa``), the compiler flags, the kernel
    threads (torch's count, passed to every call) and, for a plan ``pl`` (:func:`plan`), the point
    kernel it runs (``path``, from ``prt_plan_path``: the dispatch functions the kernels switch on,
    not a guess from the CPU's flags)."""
    lib = native()
    out = {"backend": "native" if lib is not None else "torch", "cpu_isa": cpu_isa(), "threads": torch.get_num_threads()}
    if lib is None:
        out["why"] = native_status()["detail"]
        out["path"] = "torch formulation"
        return out
    bits = int(lib.prt_isa())
    out.update({"isa": _isa_name(bits), "w16": bool(bits & 32), "avx512vl": bool(bits & 16), "fma": bool(bits & 4), "sg16": bool(bits & 64),
                "isa_choice": _state.get("isa_choice", "native"), "flags": _state.get("flags", "")})
    if pl is not None:
        code = int(lib.prt_plan_path(pl.args_ptr))
        out["path_code"] = code
        path, sub = code % 32, code // 32
        out["path"] = _PATH_NAMES.get(path, f"code {path}")
        if sub:
            out["path"] += f" ({_SUBPATH_NAMES.get(path, {}).get(sub, f'loop {sub}')})"
    return out


_LAB_KIND = {torch.uint8: 1, torch.int16: 2, torch.int32: 3}


def _ptr(t: torch.Tensor | None):
    return None if t is None else t.data_ptr()


def _codes(labels, W, wstride, woff, nk, nuse, mean):
    """The common argument block: labels (None: K = 1), weights ``W`` (None: no weights), row
    stride or per-point offsets ``woff int64 [P]`` with ``nk int64 [K]`` (packed), n used, mean."""
    kind = 0
    if labels is not None:
        kind = _LAB_KIND.get(labels.dtype, 0)
        if not kind:
            raise TypeError(f"labels have dtype {labels.dtype}; accepted: uint8, int16, int32")
        if not labels.is_contiguous():
            raise ValueError(f"labels must be contiguous; got {labels.dtype}, strides {labels.stride()}")
    for name, t, dt in (("weights", W, torch.float32), ("offsets", woff, torch.int64), ("n_vectors", nk, torch.int64)):
        if t is not None and (t.dtype != dt or not t.is_contiguous()):
            raise ValueError(f"{name} must be contiguous {dt}; got {t.dtype}, strides {t.stride()}")
    return [labels.data_ptr() if kind else None, kind, _ptr(W), int(wstride), _ptr(woff), _ptr(nk), int(nuse), int(bool(mean))]


def _pad8(n: int) -> int:
    return (n + 7) // 8 * 8


_MODEL_T: dict[tuple, tuple] = {}  # (id(basis), lanes) -> (weak reference to basis, key, Mt); dropped when basis dies


def model_t(means: torch.Tensor | None, basis: torch.Tensor, n_out: int, n_in: int, lanes: bool = False) -> torch.Tensor:
    """The representatives as the constants kernel reads them: ``[K, Jmax, n_in, n_pad]``
    float32 (x_0 first when ``means`` is given, then the basis rows; each n_out×n_in matrix
    transposed, n_out zero-padded to a multiple of 8); ``lanes=True`` (n_out = 1 only):
    ``[ceil(K/8), Jmax, n_in, 8]``, cluster 8b + l in lane l of block b (zero past K), as
    ``prt_constants_lanes`` reads them. Built once per model and kept while ``basis`` lives, one
    entry per basis and layout (keyed by the tensor and its version: refits and in-place edits
    rebuild; a codec of n_out = 1 relit with and without a view keeps both layouts)."""
    key = (tensor_version(basis), None if means is None else (id(means), tensor_version(means)), n_out, n_in, lanes)
    slot = (id(basis), bool(lanes))
    hit = _MODEL_T.get(slot)
    if hit is not None and hit[0]() is basis and hit[1] == key:
        return hit[2]
    K = basis.shape[0]
    reps = basis.reshape(K, -1, n_out, n_in)
    if means is not None:
        reps = torch.cat([means.reshape(K, 1, n_out, n_in), reps], 1)
    if lanes:
        if n_out != 1:
            raise ValueError(f"model_t: lanes=True lays out vectors (n_out = 1); got n_out = {n_out}")
        Mt = torch.zeros(_pad8(K), reps.shape[1], n_in, dtype=torch.float32)
        Mt[:K] = reps[:, :, 0]
        Mt = Mt.view(-1, 8, reps.shape[1], n_in).permute(0, 2, 3, 1).contiguous()
    else:
        Mt = torch.zeros(K, reps.shape[1], n_in, _pad8(n_out), dtype=torch.float32)
        Mt[..., :n_out] = reps.transpose(2, 3)
    if hit is None or hit[0]() is not basis:
        weakref.finalize(basis, _MODEL_T.pop, slot, None)
    _MODEL_T[slot] = (weakref.ref(basis), key, Mt)
    return Mt


def dense_pad(n_out: int) -> int:
    """The dense layout's colour stride for ``n_out`` rows: what the compiled kernels ask for
    (``prt_dense_pad``: 16-float lines for their 16-lane kernel), else ``n_out`` padded to 8."""
    lib = native()
    return int(lib.prt_dense_pad(n_out)) if lib is not None else _pad8(n_out)


def rows_pad(Fo: int, J: int) -> int:
    """The rows layout's row stride for rows of ``Fo`` floats and ``J`` terms: what the compiled
    kernels ask for (``prt_rows_pad``: 16-float lines for their wide pass), else ``Fo`` padded to 8."""
    lib = native()
    return int(lib.prt_rows_pad(Fo, J)) if lib is not None else _pad8(Fo)


#: where element (k, j, o, c) of the constants sits, per layout: (sizes of the padded tensor, strides k, j, o, c)
def constants_layout(kind: str, K: int, J: int, n_out: int, C: int) -> tuple[tuple, tuple]:
    if kind == "rows":  # [K, J, F8]: a point's row e_p in output order (o, c) (F8: rows_pad)
        F = rows_pad(n_out * C, J)
        return (K, J, F), (J * F, F, C, 1)
    if kind == "dense":  # [K, J, C, n8]: colour-major, each colour a dot with the view (n8: dense_pad)
        n8 = dense_pad(n_out)
        return (K, J, C, n8), (J * C * n8, C * n8, 1, n8)
    Jp = 1 if J == 1 else _pad8(J)  # taps: [K, n_out, C, J8]: a tapped row holds every term of every colour (one term: unpadded)
    return (K, n_out, C, Jp), (n_out * C * Jp, 1, C * Jp, Jp)


_WORKSPACE = threading.local()  # per thread: {(kind, size): constants buffer} (see constants(scratch=True))


def _model_args(means, basis, n: int, n_out: int, n_in: int, C: int, kind: str, nk: torch.Tensor | None) -> tuple:
    """The constants kernel's view of the model (shared by :func:`constants` and :func:`plan`):
    ``(lanes, Mt, K, J, Jmax, size, strides)`` — the layout's padded sizes and (k, j, o, c)
    strides (:func:`constants_layout`); ``nk`` checked."""
    lanes = n_out == 1 and kind == "rows"  # vectors: 8 clusters per vector (prt_constants_lanes)
    Mt = model_t(means, basis, n_out, n_in, lanes)
    K, Jmax = basis.shape[0], Mt.shape[1]
    if nk is not None and (nk.dtype != torch.int64 or nk.shape != (K,) or not nk.is_contiguous()):
        raise ValueError(f"constants: nk is {nk.dtype} {tuple(nk.shape)}{'' if nk.is_contiguous() else ', not contiguous'}; "
                         f"accepted: contiguous int64 [K] = [{K}] (the kernel indexes it per cluster)")
    J = (1 if means is not None else 0) + n
    size, strides = constants_layout(kind, K, J, n_out, C)
    return lanes, Mt, K, J, Jmax, size, strides


def _scratch(kind: str, size: tuple) -> torch.Tensor:
    """This thread's constants buffer of layout ``kind`` and padded ``size``, reused by its next
    call (zeroed once, when made: the kernels overwrite all but the padding)."""
    bufs = getattr(_WORKSPACE, "bufs", None)
    if bufs is None:
        bufs = _WORKSPACE.bufs = {}
    out = bufs.get((kind, size))
    if out is None:
        bufs.clear()  # one buffer per thread: the latest layout
        out = bufs[(kind, size)] = torch.zeros(size, dtype=torch.float32)
    return out


def light_flagged(L: torch.Tensor, Lc: torch.Tensor) -> None:
    """Raise naming the light's first non-finite value (as given, else as converted to float32:
    a float64 value beyond its range), after a kernel flagged the float32 light it read."""
    check_finite_float32("light", L, Lc)
    raise RuntimeError("prt_constants flagged the light but no value of it is NaN or Inf")  # pragma: no cover


def constants(lib, means, basis, n: int, n_out: int, n_in: int, L: torch.Tensor, kind: str, scratch: bool = False,
              nk: torch.Tensor | None = None) -> torch.Tensor:
    """Per-cluster constants M_i^k l (Sloan 2003 §6) for ``light L [n_in, C]`` float32, the
    first ``n`` basis rows (and the mean), laid out for kernel ``kind`` ('rows', 'dense',
    'taps'), zero-padded; one pass over the model (:func:`model_t`). A light holding NaN or
    Inf, or a value beyond float32's range, raises ``ValueError`` naming the first one (the
    kernel checks the float32 light as it reads it). ``scratch=True`` writes into this thread's
    buffer of that layout, reused by its next call (its padding zeroed once, the rest
    overwritten): for a caller that uses the result before calling again, as
    ``AffineCodec.relight`` does — no allocation and no zeroing per light. ``nk`` (contiguous
    int64 ``[K]``, optional: the vectors each cluster keeps, CPCA adaptive): the kernels read
    cluster k's first (mean) + min(n, nk[k]) terms only; the rest of its rows are undefined
    ('rows', 'dense': vectors, whose constants take 8 clusters at a time, compute them all) or
    zero ('taps')."""
    C = L.shape[1]
    lanes, Mt, K, J, Jmax, size, (sk, sj, so, sc) = _model_args(means, basis, n, n_out, n_in, C, kind, nk)
    out = _scratch(kind, size) if scratch else torch.zeros(size, dtype=torch.float32)
    Lc = _as(L, torch.float32)
    if lanes:  # every term of every cluster: the rows past a cluster's n_k are never read
        bad = lib.prt_constants_lanes(K, J, Jmax, n_in, C, Mt.data_ptr(), Lc.data_ptr(), out.data_ptr(), sk, sj,
                                      torch.get_num_threads())
    else:
        bad = lib.prt_constants(K, J, Jmax, n_in, n_out, Mt.shape[3], C, Mt.data_ptr(), Lc.data_ptr(), out.data_ptr(),
                                sk, sj, so, sc, _ptr(nk), int(means is not None), torch.get_num_threads())
    if bad:
        light_flagged(L, Lc)
    return out


#: ``prt_relight_plan``'s argument array, in its PL_ order (the C enum)
_PLAN_FIELDS = ("kind", "lanes", "K", "J", "Jmax", "n_in", "n_out", "n_pad", "C", "Mt", "sk", "sj", "so", "sc", "nk_c", "mean",
                "P", "x", "Fo", "lab", "lab_kind", "W", "wstride", "woff", "nk", "nuse", "order", "csort", "ntap")


class Plan:
    """One encoding's relighting, ready to run per light (:func:`plan`, :func:`run_plan`): the
    kernels' arguments that do not change between lights, as one int64 array, and the tensors
    they point into (kept alive with it)."""

    __slots__ = ("args", "args_ptr", "keep", "kind", "size", "n_in", "C", "P", "n_out", "ntap", "shape", "numel")


def plan(lib, means, basis, n: int, n_out: int, n_in: int, C: int, kind: str, labels, W, wstride, woff, nk, nuse, mean,
         P: int, order: torch.Tensor | None = None, codes_sorted: bool = False, ntap: int = 0) -> Plan:
    """A :class:`Plan` of one relighting — :func:`constants` (into this thread's scratch buffer)
    then :func:`affine_rows`, :func:`affine_dense` or :func:`affine_taps` (``kind``; ``ntap``
    taps per point), with the same arguments and checks, run by :func:`run_plan` in one ctypes
    call (``prt_relight_plan``): the same kernels, so the same bits. For a caller that relights
    one encoding under many lights (``AffineCodec`` caches one per encoding): the two calls'
    argument conversion and checks, ~10 µs of a small relight, are paid once."""
    lanes, Mt, K, J, Jmax, size, (sk, sj, so, sc) = _model_args(means, basis, n, n_out, n_in, C, kind, nk)
    code = _codes(labels, W, wstride, woff, nk, nuse, mean)
    if kind == "rows":
        x, Fo = size[2], n_out * C
    elif kind in ("dense", "taps"):
        x, Fo = size[3], n_out
    else:
        raise ValueError(f"plan: kind {kind!r}; accepted: 'rows', 'dense', 'taps'")
    if kind == "taps" and not 1 <= ntap <= 64:
        raise ValueError(f"plan: {ntap} taps per point; accepted: 1..64")
    vals = {"kind": {"rows": 0, "dense": 1, "taps": 2}[kind], "lanes": int(lanes), "K": K, "J": J, "Jmax": Jmax, "n_in": n_in,
            "n_out": n_out, "n_pad": Mt.shape[3] if not lanes else 8, "C": C, "Mt": Mt.data_ptr(), "sk": sk, "sj": sj, "so": so,
            "sc": sc, "nk_c": _ptr(nk) or 0, "mean": int(means is not None), "P": P, "x": x, "Fo": Fo,
            "lab": code[0] or 0, "lab_kind": code[1], "W": code[2] or 0, "wstride": code[3], "woff": code[4] or 0,
            "nk": code[5] or 0, "nuse": code[6], "order": _order(order, P) or 0, "csort": _csort(order, codes_sorted),
            "ntap": ntap}
    pl = Plan()
    pl.args = torch.tensor([vals[f] for f in _PLAN_FIELDS], dtype=torch.int64)
    pl.args_ptr = pl.args.data_ptr()
    pl.keep = (Mt, labels, W, woff, nk, order)
    pl.kind, pl.size, pl.n_in, pl.C, pl.P, pl.n_out, pl.ntap = kind, size, n_in, C, P, n_out, ntap
    pl.shape = (P, Fo) if kind == "rows" else (P, C)
    pl.numel = P * pl.shape[1]
    return pl


def run_plan(lib, pl: Plan, L: torch.Tensor, view=None, out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """Relight under ``L [n_in, C]`` by plan ``pl``: ``(result, flag)`` as the kernel of its kind
    returns them (rows: ``[P, n_out·C]``; dense, taps: ``[P, C]``; into ``out`` when given).
    ``view``: dense ``y [P, n_out]`` float32, taps ``(idx int64 [P, t], g float32 [P, t])``, or
    None (rows). A non-finite light raises naming the value, as :func:`constants` does."""
    Lc = _as(L, torch.float32)
    if Lc.shape != (pl.n_in, pl.C):
        raise ValueError(f"run_plan: light {tuple(Lc.shape)}; accepted: [{pl.n_in}, {pl.C}] (the plan's)")
    y0 = y1 = None
    if pl.kind == "dense":
        if view.dtype != torch.float32 or view.shape != (pl.P, pl.n_out):
            raise ValueError(f"run_plan: dense view {view.dtype} {tuple(view.shape)}; accepted: float32 [{pl.P}, {pl.n_out}]")
        view = view if view.is_contiguous() else view.contiguous()
        y0 = view.data_ptr()
    elif pl.kind == "taps":
        idx, g = view
        if idx.dtype != torch.int64 or g.dtype != torch.float32 or idx.shape != (pl.P, pl.ntap) or g.shape != idx.shape:
            raise ValueError(f"run_plan: taps {idx.dtype} {tuple(idx.shape)}, {g.dtype} {tuple(g.shape)}; accepted: int64 and "
                             f"float32 [{pl.P}, {pl.ntap}]")
        idx, g = _as(idx, torch.int64), _as(g, torch.float32)
        y0, y1 = idx.data_ptr(), g.data_ptr()
    elif view is not None:
        raise ValueError("run_plan: a view for a plan of kind 'rows'; accepted: None")
    out = _out(out, pl.numel, pl.shape)
    return out, run_checked(lib, pl, L, Lc, y0, y1, out)


def run_checked(lib, pl: Plan, L: torch.Tensor, Lc: torch.Tensor, y0, y1, out: torch.Tensor) -> int:
    """The kernel call of :func:`run_plan`, after its checks (``Lc``: the light as float32
    contiguous ``[n_in, C]``; ``y0``, ``y1``: the view's addresses; ``out``: contiguous float32 of
    the plan's size) — for a caller that has checked them (``AffineRelighter``'s fast path):
    the kernels' flag, after raising for a flagged light."""
    T = _scratch(pl.kind, pl.size)
    flag = lib.prt_relight_plan(pl.args_ptr, Lc.data_ptr(), T.data_ptr(), out.data_ptr(), y0, y1, torch.get_num_threads())
    if flag & 16:
        light_flagged(L, Lc)
    return int(flag)


_ORDERS_CHECKED: dict[int, tuple] = {}  # id(order) -> (weak reference, version): range already checked


def _order(order, P: int):
    """The visiting order: None (point order) or a permutation ``int32 [P]`` (cluster order).
    Its range is checked once per tensor and version (a cached order is reused every call)."""
    if order is None:
        return None
    if order.dtype != torch.int32 or order.shape != (P,) or not order.is_contiguous():
        raise ValueError(f"order must be a contiguous int32 permutation [{P}]; got {order.dtype} {tuple(order.shape)}")
    hit = _ORDERS_CHECKED.get(id(order))
    if hit is None or hit[0]() is not order or hit[1] != tensor_version(order):
        lo, hi = (int(x) for x in torch.aminmax(order)) if P else (0, -1)
        if P and (lo < 0 or hi >= P):
            raise ValueError(f"order spans [{lo}, {hi}]; accepted: a permutation of 0..{P - 1}")
        if hit is None or hit[0]() is not order:
            weakref.finalize(order, _ORDERS_CHECKED.pop, id(order), None)
        _ORDERS_CHECKED[id(order)] = (weakref.ref(order), tensor_version(order))
    return order.data_ptr()


def _as(t: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``t`` as a contiguous tensor of ``dtype``: itself when it already is (a ``.to()`` and a
    ``.contiguous()`` cost about a microsecond each even when they copy nothing)."""
    return t if t.dtype == dtype and t.is_contiguous() else t.to(dtype).contiguous()


def _pyramid(fn: str, table: torch.Tensor, ladder: torch.Tensor, res: int) -> None:
    """Refuse, before a kernel reads them, a pyramid whose rows are not ``L·6·r·r`` for the
    ladder's L levels and resolution r, or a table or ladder off the CPU: the kernels size their
    reads from the ladder and r (a light's own check can be got around by assigning through
    ``.data``; this one is at the call, in O(1)). A quad table is checked against the table by
    :func:`_quads_ptr`."""
    off = [(n, t.device) for n, t in (("table", table), ("ladder", ladder)) if t.device.type != "cpu"]
    if off:
        raise ValueError(f"{fn}: the pyramid's {off[0][0]} is on {off[0][1]}; accepted: CPU tensors")
    rows = ladder.numel() * 6 * int(res) * int(res)
    if table.dim() != 2 or table.shape[0] != rows:
        raise ValueError(f"{fn}: a pyramid table {tuple(table.shape)} for {ladder.numel()} levels of 6×{res}×{res}; "
                         f"accepted: {rows} rows (levels · 6 · res²)")


def _out(out: torch.Tensor | None, numel: int, shape: tuple) -> torch.Tensor:
    """The kernels' result tensor: ``out`` (contiguous float32 with ``numel`` elements, any shape
    of them) or a new ``[shape]``."""
    if out is None:
        return torch.empty(shape, dtype=torch.float32)
    if out.dtype != torch.float32 or not out.is_contiguous() or out.numel() != numel:
        raise ValueError(f"out must be contiguous float32 with {numel} elements; got {out.dtype} {tuple(out.shape)}")
    return out


def _csort(order, codes_sorted: bool) -> int:
    """1 when the codes are stored in visiting order (the q-th point visited reads the q-th code
    and writes output row ``order[q]``), 0 when they are in point order."""
    if codes_sorted and order is None:
        raise ValueError("codes_sorted=True needs an order (the permutation the codes were sorted by)")
    return int(bool(codes_sorted))


def affine_rows(lib, T: torch.Tensor, J: int, n_out: int, C: int, labels, W, wstride, woff, nk, nuse, mean, P: int,
                order: torch.Tensor | None = None, codes_sorted: bool = False, out: torch.Tensor | None = None) -> torch.Tensor:
    """No view: ``e_p`` for every point, ``[P, n_out·C] float32`` (into ``out``, contiguous
    float32 of P·n_out·C elements, when given), from the constants ``T`` of layout 'rows';
    ``order`` (a permutation ``int32 [P]``, e.g. by cluster) is the order the points are visited
    in (None: 0..P-1); ``codes_sorted``: the codes are stored in that order."""
    Fo = n_out * C
    if Fo > T.shape[2]:
        raise ValueError(f"affine_rows: rows of n_out·C = {Fo} floats from constants of {T.shape[2]}; accepted: n_out·C <= T.shape[2]")
    out = _out(out, P * Fo, (P, Fo))
    lib.prt_affine_rows(P, T.shape[2], Fo, *_codes(labels, W, wstride, woff, nk, nuse, mean), T.data_ptr(), J,
                        out.data_ptr(), _order(order, P), _csort(order, codes_sorted), torch.get_num_threads())
    return out


def affine_dense(lib, T: torch.Tensor, J: int, n_out: int, C: int, labels, W, wstride, woff, nk, nuse, mean,
                 y: torch.Tensor, order: torch.Tensor | None = None, codes_sorted: bool = False,
                 out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """Dense view ``y [P, n_out]`` float32 contiguous: ``[P, C]`` from the constants ``T`` of
    layout 'dense', and a flag (2: a non-finite output)."""
    if not y.is_contiguous() or y.dtype != torch.float32 or y.shape[1] != n_out:
        raise ValueError(f"affine_dense: the view must be contiguous float32 [P, {n_out}]")
    P = y.shape[0]
    out = _out(out, P * C, (P, C))
    flag = lib.prt_affine_dense(T.shape[0], P, n_out, T.shape[3], C, *_codes(labels, W, wstride, woff, nk, nuse, mean), T.data_ptr(), J,
                                y.data_ptr(), out.data_ptr(), _order(order, P), _csort(order, codes_sorted), torch.get_num_threads())
    return out, int(flag)


def affine_taps(lib, T: torch.Tensor, J: int, n_out: int, C: int, labels, W, wstride, woff, nk, nuse, mean,
                idx: torch.Tensor, g: torch.Tensor, order: torch.Tensor | None = None,
                codes_sorted: bool = False, out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """Taps ``(idx int64 [P, t], g float32 [P, t])`` contiguous, t ≤ 64: ``[P, C]`` from the
    constants ``T`` of layout 'taps', and a flag (1: a tap index outside [0, n_out); 2: a
    non-finite output)."""
    if idx.dtype != torch.int64 or g.dtype != torch.float32 or not idx.is_contiguous() or not g.is_contiguous() or idx.shape[1] > 64:
        raise ValueError("affine_taps: taps must be contiguous (idx int64, g float32), at most 64 per point")
    P, t = idx.shape
    out = _out(out, P * C, (P, C))
    flag = lib.prt_affine_taps(P, n_out, C, *_codes(labels, W, wstride, woff, nk, nuse, mean), T.data_ptr(), T.shape[3],
                               t, idx.data_ptr(), g.data_ptr(), out.data_ptr(), _order(order, P), _csort(order, codes_sorted),
                               torch.get_num_threads())
    return out, int(flag)


def _strides_are(t: torch.Tensor, shape: tuple, step: int) -> bool:
    """``t``'s strides are those of a contiguous ``shape`` times ``step`` (size-1 axes ignored)."""
    want = step
    for size, stride in zip(reversed(shape), reversed(t.stride()[:len(shape)])):
        if size > 1 and stride != want:
            return False
        want *= size
    return True


def lobe_layout(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor) -> tuple:
    """``(w, mu, sigma, sw, sm, ss, fb)`` for the kernels: lobe m's parameters at ``w[sw·m]``,
    ``mu[sm·m + c]``, ``sigma[ss·m]``. Views of one record array ``rec [..., 5]`` = (w, μx, μy,
    μz, σ) (``rec[..., 0]``, ``rec[..., 1:4]``, ``rec[..., 4]``, as the Gaussian codec stores its
    lobes) are read in place, strides (5, 5, 5); anything else as contiguous float32 arrays,
    strides (1, 3, 1). ``fb``: 0 where the lobes are in the order of ``w [..., N]``'s elements
    (m = g·N + n for function g); ``V·N`` for ``w [V, J, N]`` viewing view-major records
    ``[J, V, N, 5]`` permuted (the Gaussian codec's ``lobes_by_view``): m = v·N + j·V·N + n."""
    if w.dtype == torch.float32 and mu.data_ptr() == w.data_ptr() + 4 and sigma.data_ptr() == w.data_ptr() + 16:
        st, step = [], 5  # the views rec[..., 0], rec[..., 1:4], rec[..., 4] of a contiguous rec [..., 5]: exact strides
        for d in reversed(w.shape):
            st.append(step)
            step *= d
        st = tuple(reversed(st))
        if w.ndim == 3:  # or of a view-major rec [J, V, N, 5] permuted to [V, J, N, 5]
            V, J, N = w.shape
            vm = (5 * N, 5 * V * N, 5)
            if (V > 1 and J > 1 and w.stride() == vm and sigma.stride() == vm and mu.stride() == (*vm, 1)
                    and mu.dtype == sigma.dtype == torch.float32 and mu.shape == (*w.shape, 3) and sigma.shape == w.shape):
                return w, mu, sigma, 5, 5, 5, V * N
        if (w.stride() == st and sigma.stride() == st and mu.stride() == (*st, 1) and mu.dtype == sigma.dtype == torch.float32
                and mu.shape == (*w.shape, 3) and sigma.shape == w.shape):
            return w, mu, sigma, 5, 5, 5, 0
    if tuple(mu.shape) != (*w.shape, 3) or tuple(sigma.shape) != tuple(w.shape):  # the kernels read w.numel() lobes of each
        raise ValueError(f"lobes: mu {tuple(mu.shape)} and sigma {tuple(sigma.shape)} do not match w {tuple(w.shape)}; "
                         f"accepted: mu {(*w.shape, 3)}, sigma {tuple(w.shape)}")
    shape = tuple(w.shape)
    if (all(t.dtype == torch.float32 for t in (w, mu, sigma)) and tuple(mu.shape) == (*shape, 3) and tuple(sigma.shape) == shape
            and mu.data_ptr() == w.data_ptr() + 4 and sigma.data_ptr() == w.data_ptr() + 16 and mu.stride(-1) == 1
            and _strides_are(w, shape, 5) and _strides_are(sigma, shape, 5) and _strides_are(mu, shape, 5)):
        return w, mu, sigma, 5, 5, 5, 0
    return _as(w, torch.float32), _as(mu, torch.float32), _as(sigma, torch.float32), 1, 3, 1, 0


#: the quad table (``PrefilteredEnvironment.quads``) is read where a relight makes at least this many lookups per
#: table row (its build, 64 bytes a row, then costs under 2%) and it holds at most SG_QUADS_MAX_BYTES (beyond, its
#: lines fall out of the L2 that the table's 12 bytes a texel stay in)
SG_QUADS_MIN_LOOKUPS_PER_ROW = 16
SG_QUADS_MAX_BYTES = 8 << 20


def sg_quads_worth(rows: int, channels: int, res: int, lookups: int) -> bool:
    """Whether ``lookups`` lobe lookups in an RGB pyramid of ``rows`` texels (``L·6·r·r``) and
    resolution ``res`` should read its quad table (:func:`sg_lookup_sum`'s ``quads``)."""
    return (channels == 3 and res >= 2 and rows * 64 <= SG_QUADS_MAX_BYTES
            and lookups >= SG_QUADS_MIN_LOOKUPS_PER_ROW * rows)


def sg_lookup_sum(lib, table: torch.Tensor, log_sigmas: torch.Tensor, res: int, mu: torch.Tensor, sigma: torch.Tensor,
                  w: torch.Tensor, out: torch.Tensor | None = None, layout: tuple | None = None,
                  quads: torch.Tensor | None = None) -> torch.Tensor:
    """Σ over the last axis of ``w [..., N]`` of w · E_σ(μ) (Green 2005 eq. 2.7) from a prefiltered
    pyramid ``table [L·6·r·r, C]`` float32 (``PrefilteredEnvironment.table``) with ladder
    ``log_sigmas [L]``: ``mu [..., N, 3]``, ``sigma [..., N]`` → ``[..., C]`` float32, one fused
    pass per lobe (the torch formulation builds ~30 lobe-sized intermediates). The three may be
    views of one record array ``[..., N, 5]``, or of view-major records ``[J, V, N, 5]`` permuted
    to ``[V, J, N, 5]`` (read in place, :func:`lobe_layout`; the latter a block of 16 vertices
    at a time, every view of each, its rows of the result staying in L1), or any tensors of
    those shapes (else ``ValueError``). ``out``: an optional contiguous float32 result
    ``[..., C]`` (checked by the caller), written and returned. ``layout``: ``lobe_layout(w, mu,
    sigma)`` where the caller keeps it (the Gaussian codec, per encoding: ~2 µs a call).
    ``quads``: ``PrefilteredEnvironment.quads()`` of this table ``[L·6·r·r, 16]`` float32, or
    None: with it, RGB lookups in blocks of 16 read one 64-byte line per level (the 2×2 texels)
    instead of four (the same products, summed in another order: float32 rounding); worth its
    build where :func:`sg_quads_worth`."""
    C = table.shape[1]
    if C > 16:
        raise ValueError(f"sg_lookup_sum: {C} channels; accepted: at most 16")
    lead, N, G, A, B, lay = _sg_args(w, mu, sigma, layout)
    w, mu, sigma, sw, sm, ss, fb = lay
    _pyramid("sg_lookup_sum", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    given = out
    out = _out(out, G * C, (G, C))
    q = _quads_ptr(quads, table)
    lib.prt_sg_lookup_sum_q(A, B, fb, N, mu.data_ptr(), sigma.data_ptr(), w.data_ptr(), sw, sm, ss, table.data_ptr(), q, int(res),
                            ladder.numel(), ladder.data_ptr(), C, out.data_ptr(), torch.get_num_threads())
    return given if given is not None else out.reshape(*lead, C)


def _quads_ptr(quads: torch.Tensor | None, table: torch.Tensor) -> int | None:
    """The address of a quad table of ``table`` for the kernels (None: read the table itself)."""
    if quads is None:
        return None
    if quads.dtype != torch.float32 or not quads.is_contiguous() or quads.shape != (table.shape[0], 16) or table.shape[1] != 3 \
            or quads.device.type != "cpu":
        raise ValueError(f"quads: {quads.dtype} {tuple(quads.shape)} on {quads.device} for a table {tuple(table.shape)}; accepted: "
                         f"contiguous float32 [{table.shape[0]}, 16] on the CPU, of an RGB table (PrefilteredEnvironment.quads())")
    return quads.data_ptr()


def _sg_args(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, layout: tuple | None) -> tuple:
    """``(lead, N, G, A, B, layout)`` of lobes ``w [..., N]``: G functions, which the kernels take
    as A × B (view-major records: A vertices in blocks of 16, every one of the B views of each; else
    G × 1), and the lobes' :func:`lobe_layout`."""
    lead, N = tuple(w.shape[:-1]), w.shape[-1]
    G = w.numel() // max(N, 1)
    lay = layout or lobe_layout(w, mu, sigma)
    A, B = (lay[0].shape[0], lay[0].shape[1]) if lay[6] else (G, 1)
    return lead, N, G, A, B, lay


def sg_prepare(lib, log_sigmas: torch.Tensor, res: int, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
               layout: tuple | None = None) -> torch.Tensor | None:
    """The addressing of every lobe in the pyramid of resolution ``res`` and width ladder
    ``log_sigmas`` (face, texel, level and their fractions: ``prt_sg_prepare``, the part of a
    lookup that does not depend on the light's values), for :func:`sg_lookup_prepared`:
    ``int32 [⌊A/16⌋·B·N·80]`` (20 bytes per lobe), or None where the 16-lane kernels do not take
    this shape (no AVX-512, sizes past their int32 indices, a pyramid of one texel per side or
    one width: relight as usual)."""
    _, N, _, A, B, (w, mu, sigma, sw, sm, ss, fb) = _sg_args(w, mu, sigma, layout)
    ladder = _as(log_sigmas, torch.float32)
    P = torch.empty((A // 16) * B * N * 80, dtype=torch.int32)
    if lib.prt_sg_prepare(A, B, fb, N, mu.data_ptr(), sigma.data_ptr(), w.data_ptr(), sw, sm, ss, int(res), ladder.numel(),
                          ladder.data_ptr(), P.data_ptr(), torch.get_num_threads()):
        return None
    return P


def sg_lookup_prepared(lib, prepared: torch.Tensor, table: torch.Tensor, log_sigmas: torch.Tensor, res: int, w: torch.Tensor,
                       mu: torch.Tensor, sigma: torch.Tensor, out: torch.Tensor | None = None,
                       layout: tuple | None = None, quads: torch.Tensor | None = None) -> torch.Tensor:
    """:func:`sg_lookup_sum` of RGB lights (``table [L·6·r·r, 3]``) from :func:`sg_prepare`'s
    addressing of these lobes for this ``res`` and ``log_sigmas`` (the caller keeps it valid: the
    same lobes, unchanged): per lobe only the 8 texel reads, the tail of fewer than 16 functions
    from the records. The same bits as :func:`sg_lookup_sum` with the same ``quads``."""
    lead, N, G, A, B, (w, mu, sigma, sw, sm, ss, fb) = _sg_args(w, mu, sigma, layout)
    if table.shape[1] != 3 or prepared.numel() != (A // 16) * B * N * 80:
        raise ValueError(f"sg_lookup_prepared: table {tuple(table.shape)}, prepared {prepared.numel()} values; accepted: "
                         f"[rows, 3] and {(A // 16) * B * N * 80} (sg_prepare of these lobes)")
    _pyramid("sg_lookup_prepared", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    given = out
    out = _out(out, G * 3, (G, 3))
    if lib.prt_sg_lookup_prepared(A, B, fb, N, mu.data_ptr(), sigma.data_ptr(), w.data_ptr(), sw, sm, ss, prepared.data_ptr(),
                                  table.data_ptr(), _quads_ptr(quads, table), int(res), ladder.numel(), ladder.data_ptr(),
                                  out.data_ptr(), torch.get_num_threads()):
        raise RuntimeError("prt_sg_lookup_prepared refused a shape sg_prepare took")  # pragma: no cover
    return given if given is not None else out.reshape(*lead, 3)


def sg_taps(lib, table: torch.Tensor, log_sigmas: torch.Tensor, res: int, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
            idx: torch.Tensor, a: torch.Tensor, out: torch.Tensor | None = None, layout: tuple | None = None) -> torch.Tensor:
    """Gaussian relighting with view taps (Green 2005 §2.3, eq. 2.7), fused per vertex: the lobes
    of the tapped views blended with ``a / Σa`` (``gaussian.blend_lobes``), looked up in the
    pyramid (as :func:`sg_lookup_sum`), summed over the lobes and scaled by Σa. ``w [V, J, N]``,
    ``mu [V, J, N, 3]``, ``sigma [V, J, N]`` (views of the codec's records are read in place,
    :func:`lobe_layout`: view-major ``lobes_by_view [J, V, N, 5]``, where a camera's taps, a few
    views shared by neighbouring vertices, read a few runs along the vertices; or vertex-major
    ``lobes [V, J, N, 5]``, three runs of 20·N bytes per vertex), ``idx int64 [V, k]``,
    ``a [V, k]`` → ``([V, C]`` float32 (into ``out`` when given, checked by the caller), flag``):
    flag 1, with nothing computed or written, when a tap has an index outside [0, J) or a
    negative or non-finite weight (one pass over the taps in the kernel, where torch's checks
    took four; the caller raises naming it). ``layout``: as for :func:`sg_lookup_sum`."""
    C = table.shape[1]
    if C > 16:
        raise ValueError(f"sg_taps: {C} channels; accepted: at most 16")
    args, _held = _taps_args(w, mu, sigma, idx, a, layout)
    _pyramid("sg_taps", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    out = _out(out, args[0] * C, (args[0], C))
    flag = lib.prt_sg_taps(*args, table.data_ptr(), int(res), ladder.numel(), ladder.data_ptr(), C, out.data_ptr(),
                           torch.get_num_threads())
    return out, int(flag)


def _taps_args(w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor, idx: torch.Tensor, a: torch.Tensor, layout: tuple | None):
    """``prt_sg_taps*``'s shape and lobe arguments ``[V, J, N, k, fv, fj, w, mu, sigma, sw, sm, ss, idx, a]``
    (pointers for the tensors) and the tensors they point into (kept alive by the caller)."""
    V, J, N = w.shape
    k = idx.shape[1]
    w, mu, sigma, sw, sm, ss, fb = layout or lobe_layout(w, mu, sigma)
    fv, fj = (N, fb) if fb else (J * N, N)  # lobe index of (v, j, 0): view-major records, else in order
    a, idx = _as(a, torch.float32), _as(idx, torch.int64)
    held = (w, mu, sigma, idx, a)
    return [V, J, N, k, fv, fj, w.data_ptr(), mu.data_ptr(), sigma.data_ptr(), sw, sm, ss, idx.data_ptr(), a.data_ptr()], held


def sg_taps_prepare(lib, log_sigmas: torch.Tensor, res: int, w: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
                    idx: torch.Tensor, a: torch.Tensor, layout: tuple | None = None) -> tuple:
    """The part of :func:`sg_taps` that does not depend on the light's values, for
    :func:`sg_taps_prepared`: each whole block of 16 vertices' lobes blended across the taps
    (``prt_sg_taps_prepare``), normalised and addressed in the pyramid of resolution ``res`` and
    width ladder ``log_sigmas`` (face, texel, level and their fractions, as :func:`sg_prepare`).
    Arguments as :func:`sg_taps`. → ``(prepared, flag)``: prepared = ``(P int32 [⌊V/16⌋·N·80],
    tot float32 [⌊V/16⌋·16], the kernels' lobe and taps arguments, the tensors they point into)``,
    20 bytes per blended lobe and Σa per vertex; ``(None, 0)`` where the 16-lane kernels do not
    take this shape (no AVX-512, sizes past their int32 indices, more than 8 taps, a pyramid of
    one texel per side or one width); ``(None, 1)`` with a bad tap (as :func:`sg_taps`' flag)."""
    args, held = _taps_args(w, mu, sigma, idx, a, layout)
    V, N = args[0], args[2]
    ladder = _as(log_sigmas, torch.float32)
    P = torch.empty((V // 16) * N * 80, dtype=torch.int32)
    tot = torch.empty((V // 16) * 16, dtype=torch.float32)
    flag = lib.prt_sg_taps_prepare(*args, int(res), ladder.numel(), ladder.data_ptr(), P.data_ptr(), tot.data_ptr(),
                                   torch.get_num_threads())
    if flag == 2:
        return None, 0
    return (None, 1) if flag else ((P, tot, tuple(args), held), 0)


def sg_taps_prepared(lib, prepared: tuple, table: torch.Tensor, log_sigmas: torch.Tensor, res: int,
                     out: torch.Tensor | None = None) -> tuple[torch.Tensor, int]:
    """:func:`sg_taps` of RGB lights (``table [L·6·r·r, 3]``) from :func:`sg_taps_prepare`'s
    blend and addressing of its lobes and taps for this ``res`` and ``log_sigmas`` (the caller
    keeps it valid: the same lobes and taps, unchanged, and the same ``res`` and ladder): per
    blended lobe only the 8 texel reads, the tail of fewer than 16 vertices from the records and
    taps. The same bits as :func:`sg_taps`. → ``([V, 3]`` float32, flag``)``: flag 1, nothing
    written, when a tap of the tail (the only taps read) is bad."""
    out, call = sg_taps_prepared_call(prepared, table, log_sigmas, res, out)
    flag = lib.prt_sg_taps_prepared(*call, torch.get_num_threads())
    if flag == 2:
        raise RuntimeError("prt_sg_taps_prepared refused a shape sg_taps_prepare took")  # pragma: no cover
    return out, int(flag)


def sg_taps_prepared_call(prepared: tuple, table: torch.Tensor, log_sigmas: torch.Tensor, res: int,
                          out: torch.Tensor | None = None) -> tuple[torch.Tensor, tuple]:
    """:func:`sg_taps_prepared`'s checks, then ``(out, the arguments of prt_sg_taps_prepared but
    the thread count)``: what a caller that keeps ``prepared``, the pyramid and ``out`` unchanged
    (``GaussianRelighter``'s fast path) may pass again without the checks."""
    P, tot, args, _held = prepared
    V, N = args[0], args[2]
    if (table.shape[1] != 3 or P.numel() != (V // 16) * N * 80 or tot.numel() != (V // 16) * 16 or P.dtype != torch.int32
            or tot.dtype != torch.float32 or not (P.is_contiguous() and tot.is_contiguous())):
        raise ValueError(f"sg_taps_prepared: table {tuple(table.shape)}, prepared {P.numel()} and {tot.numel()} values; accepted: "
                         f"[rows, 3], {(V // 16) * N * 80} int32 and {(V // 16) * 16} float32 (sg_taps_prepare of these lobes and taps)")
    _pyramid("sg_taps_prepared", table, log_sigmas, res)
    table, ladder = _as(table, torch.float32), _as(log_sigmas, torch.float32)
    out = _out(out, V * 3, (V, 3))
    return out, (*args, P.data_ptr(), tot.data_ptr(), table.data_ptr(), int(res), ladder.numel(), ladder.data_ptr(), out.data_ptr())


def fits(J: int, n_out: int, C: int) -> bool:
    """Whether the kernels' per-point buffers hold these sizes (else the torch path is used)."""
    return C <= 16 and max(_pad8(n_out * C), C * _pad8(n_out), C * _pad8(J)) <= MAX_ROW  # taps with J = 1: C floats
