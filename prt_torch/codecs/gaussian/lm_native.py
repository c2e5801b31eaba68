"""The Gaussian fit's Levenberg–Marquardt loop compiled (``prt_torch/kernels/gauss_lm.c``): the same
iterations as :func:`.fit._lm_loop` (Green 2005 eq. 2.2–2.6; the objective, the Gauss–Newton normal
equations from per-texel moments, the active set at the bounds, per-function damping and
convergence, the view targets by block Jacobi) with each function's step — its lobe terms, residual,
moments, 4N×4N system, Cholesky solve, trial step and its objective — in one pass over its P texels
instead of a dozen batched torch passes over ``[b, N, P]`` per iteration, and the loop itself in C
(no per-iteration gather / scatter of the active functions).

:func:`lm_loop` has :func:`.fit._lm_loop`'s contract plus the view geometry (``vn``, ``J``);
:func:`available` says whether the library is there. Without a C compiler, or with
``PRT_TORCH_NATIVE=0``, the fit runs the torch loop (tests compare both).
"""
from __future__ import annotations

import ctypes
import os
import threading

import torch

from ..._native import LIBRARIES, compile_library, kernel_sources

__all__ = ["available", "lm_loop", "normal_equations", "peaks", "why"]

_lock = threading.Lock()
_state: dict = {}


def _lib():
    if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return None
    if "lib" not in _state:
        with _lock:
            if "lib" not in _state:
                names, flags = LIBRARIES["gauss_lm"]
                i64, vp, dbl = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double
                _state["lib"], _state["why"] = compile_library("gauss_lm", kernel_sources(names), list(flags), {
                    "prt_gauss_lm_loop": [i64] * 7 + [vp] * 7 + [dbl] * 8 + [i64, i64] + [vp] * 5 + [ctypes.c_int],
                    "prt_gauss_normal_equations": [i64] * 5 + [vp] * 6 + [dbl] * 3 + [vp] * 8,
                    "prt_gauss_peaks": [i64, i64, vp, vp, vp, dbl, dbl, vp, vp, vp, ctypes.c_int]})
    return _state["lib"]


def available() -> bool:
    """Whether the compiled loop runs here (a C compiler, and ``PRT_TORCH_NATIVE`` is not 0)."""
    return _lib() is not None


def why() -> str:
    """How the library was obtained, or why not."""
    _lib()
    return _state.get("why", "disabled by PRT_TORCH_NATIVE=0")


def _c(t: torch.Tensor, dtype) -> torch.Tensor:
    return t.detach().to(dtype).contiguous()


def lm_loop(prob, a, ls, mu, conv, z, sb, max_iter, tol, smin, smax, vn, J, tries=1):
    """:func:`.fit._lm_loop` compiled: ``prob`` (:class:`.fit.Problem`: tables ``T [B, P]``, texel
    directions and solid angles, N, β, γ, δ, width bounds), ``a``, ``ls [B, N]``, ``mu [B, N, 3]``
    float32 (updated in place and returned), ``conv [B]`` bool (True: not optimised; updated), ``z
    [B]`` bool zero functions, ``sb [B, pairs, Q, 3]`` or None (eq. 2.6's neighbour differences),
    ``vn [J, R]`` int64 view neighbours (R = 0 or β = 0: no view terms), ``J`` views per vertex,
    ``tries`` damped solves per iteration (a rejected trial step retried at 5× the damping; 1: one).
    Runs ``torch.get_num_threads()`` OpenMP threads. → ``(a, ls, mu, conv, iterations)``."""
    lib = _lib()
    B, N = a.shape
    P = prob.T.shape[1]
    f32 = torch.float32
    T, dirs, sa = _c(prob.T, f32), _c(prob.dirs_t, f32), _c(prob.sa, f32)  # dirs_t [3, P]: one row per axis
    en = _c(prob.energy, f32)
    a_, ls_, mu_ = _c(a, f32), _c(ls, f32), _c(mu, f32)
    cv = _c(conv, torch.uint8)
    zz = _c(z, torch.uint8)
    vn_ = _c(vn, torch.int64)
    R = vn_.shape[1] if (prob.beta > 0 and vn_.ndim == 2) else 0
    use_sb = prob.delta > 0 and sb is not None and len(prob.pairs) > 0
    sb_ = _c(sb, f32) if use_sb else None
    Q = sb_.shape[2] if use_sb else 0
    pairs = torch.tensor(prob.pairs if prob.pairs else [(0, 0)], dtype=torch.int32).contiguous()
    it = lib.prt_gauss_lm_loop(B, N, P, J, R, Q, len(prob.pairs) if use_sb else 0, T.data_ptr(), dirs.data_ptr(), sa.data_ptr(),
                               en.data_ptr(), vn_.data_ptr(), sb_.data_ptr() if use_sb else None, pairs.data_ptr(),
                               float(prob.beta), float(prob.gamma), float(prob.delta), float(prob.lsmin), float(prob.lsmax),
                               float(smin), float(smax), float(tol), int(max_iter), int(tries), a_.data_ptr(), ls_.data_ptr(), mu_.data_ptr(),
                               cv.data_ptr(), zz.data_ptr(), int(torch.get_num_threads()))
    if it == -1:
        raise ValueError(f"prt_gauss_lm_loop: lobes N={N}, texels P={P}, functions B={B}, tries={tries}; "
                         "accepted: 1 <= N <= 16, P >= 1, B >= 1, tries >= 1")
    if it < 0:
        raise MemoryError(f"prt_gauss_lm_loop: out of memory for B={B} functions of N={N} lobes, P={P} texels")
    a.copy_(a_)
    ls.copy_(ls_)
    mu.copy_(mu_)
    conv.copy_(cv.bool())
    return a, ls, mu, conv, int(it)


def normal_equations(prob, a, ls, mu, tgt_mu, tgt_s, sb):
    """The compiled objective and Gauss–Newton system of every function of ``prob`` (as
    :meth:`.fit.Problem.normal_equations` for ``sel`` = all, before the active set and damping):
    ``a``, ``ls [B, N]``, ``mu [B, N, 3]``, view targets ``tgt_mu [B, N, 3]``, ``tgt_s [B, N]`` (or
    None), ``sb [B, pairs, Q, 3]`` (or None) → ``(JtJ [B, 4N, 4N], Jtr [B, 4N], E [B])`` float64.
    What each step of :func:`lm_loop` solves with; for tests."""
    lib = _lib()
    B, N = a.shape
    P = prob.T.shape[1]
    f32 = torch.float32
    T, dirs, sa, en = _c(prob.T, f32), _c(prob.dirs_t, f32), _c(prob.sa, f32), _c(prob.energy, f32)
    a_, ls_, mu_ = _c(a, f32), _c(ls, f32), _c(mu, f32)
    views = prob.beta > 0 and tgt_mu is not None
    tm, ts = (_c(tgt_mu, f32), _c(tgt_s, f32)) if views else (None, None)
    use_sb = prob.delta > 0 and sb is not None and len(prob.pairs) > 0
    sb_ = _c(sb, f32) if use_sb else None
    pairs = torch.tensor(prob.pairs if prob.pairs else [(0, 0)], dtype=torch.int32).contiguous()
    E = torch.empty(B, dtype=torch.float64)
    JtJ = torch.empty(B, 4 * N, 4 * N, dtype=torch.float64)
    Jtr = torch.empty(B, 4 * N, dtype=torch.float64)
    rc = lib.prt_gauss_normal_equations(B, N, P, sb_.shape[2] if use_sb else 0, len(prob.pairs) if use_sb else 0, T.data_ptr(),
                                        dirs.data_ptr(), sa.data_ptr(), en.data_ptr(), sb_.data_ptr() if use_sb else None,
                                        pairs.data_ptr(), float(prob.beta), float(prob.gamma), float(prob.delta), a_.data_ptr(),
                                        ls_.data_ptr(), mu_.data_ptr(), tm.data_ptr() if views else None,
                                        ts.data_ptr() if views else None, E.data_ptr(), JtJ.data_ptr(), Jtr.data_ptr())
    if rc == -1:
        raise ValueError(f"prt_gauss_normal_equations: lobes N={N}, texels P={P}; accepted: 1 <= N <= 16, P >= 1")
    if rc != 0:
        raise MemoryError(f"prt_gauss_normal_equations: out of memory for N={N} lobes, P={P} texels")
    return JtJ, Jtr, E


def peaks(R, dirs_t, sa, smin, smax):
    """:func:`.fit._init_lobes` for one lobe, compiled (peaks and moments: the centroid of the
    half-maximum cap around each function's largest texel, σ from the cap's angular radius, w from
    the peak): ``R [B, P]``, texel directions ``dirs_t [3, P]``, solid angles ``sa [P]`` → ``(w [B, 1],
    mu [B, 1, 3], sigma [B, 1])`` float32. ``torch.get_num_threads()`` threads."""
    lib = _lib()
    f32 = torch.float32
    R, dirs_t, sa = _c(R, f32), _c(dirs_t, f32), _c(sa, f32)
    B, P = R.shape
    w = torch.empty(B, 1, dtype=f32)
    mu = torch.empty(B, 1, 3, dtype=f32)
    sg = torch.empty(B, 1, dtype=f32)
    if lib.prt_gauss_peaks(B, P, R.data_ptr(), dirs_t.data_ptr(), sa.data_ptr(), float(smin), float(smax), w.data_ptr(),
                           mu.data_ptr(), sg.data_ptr(), int(torch.get_num_threads())) != 0:
        raise ValueError(f"prt_gauss_peaks: functions B={B}, texels P={P}; accepted: B >= 0, P >= 1")
    return w, mu, sg
