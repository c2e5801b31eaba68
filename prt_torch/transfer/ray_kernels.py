"""Compiled passes of the diffuse precompute: the uniform set's rays (below), the qmc set's
rotated Hammersley rays per vertex or per hit (:func:`qmc_rays_native`), the estimators' choice of
rays (:func:`select_rays`), their SH sums per vertex (:func:`sh_accumulate`), the bounce
estimator's guided first-hit rays (:func:`guided_rays_native`, ``kernels/guided.c``) and the
glossy / MRT transferred-radiance sums per vertex (:func:`outer_accumulate`, ``kernels/glossy.c``) — issue 42.

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
import math
import os
import threading

import numpy as np

from .._native import LIBRARIES, compile_library, kernel_sources

__all__ = ["available", "upper_rays", "qmc_rays_native", "select_rays", "sh_accumulate", "guided_rays_native", "outer_accumulate",
           "luma_mix"]

#: the C source (prt_torch/kernels/raygen.c) and compiler flags
_SOURCES, _FLAGS = LIBRARIES["raygen"][0], list(LIBRARIES["raygen"][1])

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
                    "prt_qmc_rays": [i64, i64, vp, vp, vp, vp, vp, vp, vp, vp, vp, vp, vp, ci, ci],
                    "prt_select_rays": [i64, i64, vp, vp, ctypes.c_double, ci, vp, vp, vp],
                    "prt_sh_accumulate": [i64, vp, i64, vp, vp, ctypes.c_double, ci, vp, vp],
                    "prt_guided_rays": [i64, i64, vp, vp, vp, vp, vp, vp, vp, vp, vp, vp, ci, ci, vp, vp, vp, ci],
                    "prt_outer_accumulate": [i64, i64, vp, vp, vp, vp, ctypes.c_double, vp, ci],
                    "prt_luma_mix": [i64, i64, i64, vp, vp, vp, vp],
                })
                if _state["lib"] is not None:
                    _state["lib"].prt_guided_rays.restype = i64
    return _state["lib"]


def available() -> bool:
    """True when the compiled ray library (``kernels/raygen.c``) is loaded: the qmc diffuse chunk then
    selects its rays and accumulates their SH in one pass (:func:`select_rays`, :func:`sh_accumulate`),
    holding no per-ray SH values (what ``transfer.estimate`` counts)."""
    return _lib() is not None


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


def qmc_rays_native(frames: np.ndarray, origins: np.ndarray, u1: np.ndarray, cu: np.ndarray, su: np.ndarray,
                    a: np.ndarray, cb: np.ndarray, sb: np.ndarray, threads: int | None = None, work: dict | None = None,
                    cosine: bool = False):
    """The qmc diffuse precompute's rays of k vertices, M each, in one compiled pass, or None
    without the library (``kernels/raygen.c``, ``prt_qmc_rays``: the formulas and their order).

    ``frames float64 [k, 3, 3]`` rows (t, b, n); ``origins float32 [k, 3]`` (already offset);
    ``u1, cu, su float64 [k]``: each vertex's Cranley–Patterson shift of z and cos/sin of its
    azimuth shift 2πu2; ``a, cb, sb float64 [M]``: the Hammersley set's first coordinate and
    cos/sin 2π of its second. → ``(o float32 [k·M, 3], d float32 [k·M, 3], z float64 [k·M])``
    grouped by vertex (ray v·M + m), z = n_v · d (before rounding d to float32). ``work``: as
    :func:`upper_rays`. ``cosine``: 1 (True) the bounce estimator's cosine-weighted set
    (``diffuse.HitBounce``: r = √a, z = √(1 − a)); 2 the vertices' defensive mixture of the uniform
    and cosine densities, p(z) = ¾ + z/2 (``diffuse.DiffuseSampler``: z = 2a / (¾ + √(9/16 + a)),
    r = √(1 − z²)); 0 (False) the set uniform in solid angle (z = a, r = √(1 − z²)).
    """
    lib = _lib()
    if lib is None:
        return None
    k, M = frames.shape[0], a.shape[0]
    if frames.shape != (k, 3, 3) or origins.shape != (k, 3) or any(x.shape != (k,) for x in (u1, cu, su)) \
            or cb.shape != (M,) or sb.shape != (M,):
        raise ValueError(f"qmc_rays_native: frames {frames.shape}, origins {origins.shape}, u1/cu/su {u1.shape}/{cu.shape}/"
                         f"{su.shape}, a/cb/sb {a.shape}/{cb.shape}/{sb.shape}; accepted: [k,3,3], [k,3], [k] and [M]")
    f64 = [np.ascontiguousarray(x, np.float64) for x in (frames, u1, cu, su, a, cb, sb)]
    ov = np.ascontiguousarray(origins, np.float32)
    R = k * M
    o, d = _buffer(work, "o", (R, 3), np.float32), _buffer(work, "d", (R, 3), np.float32)
    z = _buffer(work, "z", (R,), np.float64)
    F, u1, cu, su, a, cb, sb = f64
    lib.prt_qmc_rays(k, M, F.ctypes.data, ov.ctypes.data, u1.ctypes.data, cu.ctypes.data, su.ctypes.data, a.ctypes.data,
                     cb.ctypes.data, sb.ctypes.data, o.ctypes.data, d.ctypes.data, z.ctypes.data, int(cosine),
                     int(threads or 1))
    return o, d, z


#: ``mode`` of :func:`select_rays`
SELECT_MODES = {"auto": 0, "control": 1, "plain": 2}


def select_rays(z: np.ndarray, hit: np.ndarray, M: int, weight: float, estimator: str):
    """The rays a diffuse estimator reads, for rays grouped by vertex in blocks of ``M`` with
    weights ``weight · z`` (``kernels/raygen.c``, ``prt_select_rays``), or None without the library.

    ``z float64 [k·M]``, ``hit bool [k·M]`` (blocked) → ``(open_v bool [k], sel int64 [S])``:
    'auto' — open_v where Σ w z over visible rays ≥ half of Σ w z (sums in ray order, as
    ``np.bincount``), sel the blocked rays of open vertices and the visible rays of the others;
    'control' — every vertex open, sel the blocked rays; 'plain' — none open, sel the visible
    rays. Ray indices ascending. What ``diffuse._chunk`` computes with two bincounts and a mask
    over all R rays, in one pass.
    """
    lib = _lib()
    if lib is None:
        return None
    R = z.shape[0]
    if hit.shape != (R,) or M < 1 or R % M:
        raise ValueError(f"select_rays: z {z.shape}, hit {hit.shape}, M={M}; accepted: equal [k·M] shapes, M >= 1")
    k = R // M
    z = np.ascontiguousarray(z, np.float64)
    h = np.ascontiguousarray(hit, np.bool_).view(np.uint8)
    open_v = np.empty(k, np.uint8)
    sel = np.empty(R, np.int64)
    n = np.zeros(1, np.int64)
    lib.prt_select_rays(k, M, z.ctypes.data, h.ctypes.data, float(weight), SELECT_MODES[estimator], open_v.ctypes.data,
                        sel.ctypes.data, n.ctypes.data)
    return open_v.view(np.bool_), sel[:int(n[0])]


def _sh_scale(bands: int) -> np.ndarray:
    """``[bands²]`` float64 K_lm = √((2l+1)/(4π) (l−|m|)!/(l+|m|)!), times √2 for m ≠ 0, by flat
    index l(l+1)+m (Ramamoorthi 2002 eq. 4.5's normalisation, graphics convention)."""
    K = np.empty(bands * bands)
    for l in range(bands):  # a loop over bands (at most 32²)
        for m in range(-l, l + 1):
            a = abs(m)
            K[l * (l + 1) + m] = math.sqrt((2 * l + 1) / (4 * math.pi) * math.exp(math.lgamma(l - a + 1) - math.lgamma(l + a + 1)))
            if m:
                K[l * (l + 1) + m] *= math.sqrt(2.0)
    return K


def sh_accumulate(k: int, M: int, sel: np.ndarray, dirs: np.ndarray, z: np.ndarray | None, weight: float, bands: int):
    """``S [k, bands²] float64``: Σ over the rays ``sel`` of ``weight · z_r · y(dirs_r)`` into the
    row ``sel_r // M`` (rays grouped by vertex in blocks of M), the real SH y (graphics convention,
    Ramamoorthi 2002 eq. 4.5, flat index l(l+1)+m) computed in the pass (``kernels/raygen.c``,
    ``prt_sh_accumulate``) — never an ``[R, bands²]`` table; or None without the library.

    ``sel int64 [S]`` ray indices; ``dirs float32 [R, 3]`` unit directions (normalised in float64
    first, as eval_sh's sphericart backend does: float32 rounding leaves |d| = 1 ± 1e-7);
    ``z float64 [R]`` per-ray factors or None (1). Equals ``index_add(sel // M, weight · z[sel] ·
    eval_sh(dirs[sel]))`` to float64 rounding (the tests: 1e-13). bands in [1, 32].
    """
    lib = _lib()
    if lib is None:
        return None
    if not 1 <= bands <= 32:
        raise ValueError(f"sh_accumulate: bands={bands}; accepted: 1..32")
    sel = np.ascontiguousarray(sel, np.int64)
    d = np.ascontiguousarray(dirs, np.float32)
    if d.ndim != 2 or d.shape[1] != 3 or (z is not None and z.shape != (d.shape[0],)):
        raise ValueError(f"sh_accumulate: dirs {d.shape}, z {None if z is None else z.shape}; accepted: [R, 3] and [R]")
    if sel.size and (int(sel.min()) < 0 or int(sel.max()) >= min(d.shape[0], k * M)):
        raise ValueError(f"sh_accumulate: ray indices in [{int(sel.min())}, {int(sel.max())}]; accepted: [0, {min(d.shape[0], k * M)})")
    key = ("K", bands)
    if key not in _state:
        _state[key] = _sh_scale(bands)
    S = np.zeros((k, bands * bands), np.float64)
    zz = None if z is None else np.ascontiguousarray(z, np.float64)
    lib.prt_sh_accumulate(sel.shape[0], sel.ctypes.data, int(M), d.ctypes.data, None if zz is None else zz.ctypes.data,
                          float(weight), int(bands), _state[key].ctypes.data, S.ctypes.data)
    return S


def guided_rays_native(M: int, hits: np.ndarray, tri: np.ndarray, u1: np.ndarray, v2: np.ndarray, ta: np.ndarray,
                       tb: np.ndarray, guide_row: np.ndarray, cdf_a: np.ndarray, cdf_b: np.ndarray, mass: np.ndarray,
                       frames: np.ndarray, D: np.ndarray, W: np.ndarray, threads: int | None = None) -> bool:
    """The guided first-hit rays of the bounce estimator (``diffuse.HitBounce._rays`` under 'auto'),
    written in place in one compiled pass (``kernels/guided.c``, ``prt_guided_rays``: the formulas);
    False without the library (the caller takes the numpy reference, ``HitBounce._guided_rays``).

    ``hits, tri int64 [G]``: each guided hit's row in the level's hits and its face; ``u1, v2
    float64 [G]``: its Cranley–Patterson shifts; ``ta, tb float64 [M]``: the Hammersley set's two
    coordinates; ``guide_row int64 [F]`` (-1: no guide), ``cdf_a [Gf, Ga]``, ``cdf_b [Gf, Ga, Gb]``
    and ``mass [Gf, Ga, Gb]`` float64 the guides (``HitBounce._build_guide``); ``frames float64 [F, 3, 3]``.
    Writes rays h·M + m, m < M, of each guided hit h into ``D float32 [H·M, 3]`` (directions) and
    ``W float64 [H·M]`` (weight factors q = 1/(K P_cell)); the other rows are left as they are.
    Same float64 operations as the numpy reference in its order (tests/test_guided_kernel.py: the
    same bits). One thread by default (as :func:`upper_rays`)."""
    lib = _lib()
    if lib is None:
        return False
    G = hits.shape[0]
    Gf, Ga, Gb = mass.shape
    if tri.shape != (G,) or u1.shape != (G,) or v2.shape != (G,) or ta.shape != (M,) or tb.shape != (M,) \
            or cdf_a.shape != (Gf, Ga) or cdf_b.shape != (Gf, Ga, Gb) or frames.shape != (guide_row.shape[0], 3, 3):
        raise ValueError(f"guided_rays_native: tri/u1/v2 {tri.shape}/{u1.shape}/{v2.shape}, ta/tb {ta.shape}/{tb.shape}, "
                         f"guides {cdf_a.shape}/{cdf_b.shape}/{mass.shape}, frames {frames.shape}; accepted: [G] = "
                         f"[{G}], [M] = [{M}], [Gf, Ga](, Gb) and [F, 3, 3] with F = guide_row's length")
    if D.dtype != np.float32 or W.dtype != np.float64 or not D.flags.c_contiguous or not W.flags.c_contiguous \
            or D.shape[0] != W.shape[0] or (G and int(hits.max()) * M + M > D.shape[0]):
        raise ValueError(f"guided_rays_native: D {D.dtype} {D.shape}, W {W.dtype} {W.shape}; accepted: contiguous "
                         f"float32 [R, 3] and float64 [R] with R >= (max hit + 1)·M")
    F = guide_row.shape[0]
    if G and (int(hits.min()) < 0 or int(tri.min()) < 0 or int(tri.max()) >= F) or (F and int(guide_row.max()) >= Gf):
        # the C indexes D/W by hits, guide_row by tri and the guides by guide_row unchecked: out of range is memory corruption
        raise ValueError(f"guided_rays_native: hits in [{int(hits.min()) if G else 0}, {int(hits.max()) if G else 0}], tri in "
                         f"[{int(tri.min()) if G else 0}, {int(tri.max()) if G else 0}], guide_row up to "
                         f"{int(guide_row.max()) if F else -1}; accepted: hits >= 0, tri in [0, {F}), guide_row < {Gf}")
    c = [np.ascontiguousarray(x, np.int64) for x in (hits, tri, guide_row)]
    f = [np.ascontiguousarray(x, np.float64) for x in (u1, v2, ta, tb, cdf_a, cdf_b, mass, frames)]
    bad = lib.prt_guided_rays(G, int(M), c[0].ctypes.data, c[1].ctypes.data, f[0].ctypes.data, f[1].ctypes.data,
                              f[2].ctypes.data, f[3].ctypes.data, c[2].ctypes.data, f[4].ctypes.data, f[5].ctypes.data,
                              f[6].ctypes.data, Ga, Gb, f[7].ctypes.data, D.ctypes.data, W.ctypes.data, int(threads or 1))
    if bad:
        raise ValueError(f"guided_rays_native: face {int(tri[bad - 1])} has no guide; accepted: faces with a guide row >= 0")
    return True


def outer_accumulate(T: np.ndarray, ptr: np.ndarray, dirs: np.ndarray, Y: np.ndarray, c: float,
                     R: np.ndarray | None = None, threads: int | None = None) -> bool:
    """``T[p] += c · Σ_e y(s_{dirs_e}) r_eᵀ`` over each vertex's entries ``ptr[p] <= e < ptr[p+1]``,
    with ``r_e = R[e]`` or (``R`` None) ``y(s_{dirs_e})`` — the Monte Carlo sums of glossy transferred
    radiance T_p (Sloan et al. 2002 §4–5; ``glossy.transferred_radiance``) in one compiled pass
    (``kernels/glossy.c``, ``prt_outer_accumulate``), in place; False without the library (the caller
    takes its torch path).

    ``T float64 [k, n, n]`` C-contiguous (added to); ``ptr int64 [k+1]`` (0 first, nondecreasing, E
    last); ``dirs int64 [E]`` rows of ``Y float64 [N, n]``; ``R float64 [E, n]`` or None. Each vertex's
    entries are added in their order (the same bits for any chunking or thread count); OpenMP over
    vertices with ``threads`` (default 1, as :func:`upper_rays`)."""
    lib = _lib()
    if lib is None:
        return False
    k, n = T.shape[0], Y.shape[1] if Y.ndim == 2 else -1
    E = dirs.shape[0]
    if T.dtype != np.float64 or not T.flags.c_contiguous or T.shape != (k, n, n) or ptr.shape != (k + 1,) \
            or dirs.ndim != 1 or (R is not None and R.shape != (E, n)):
        raise ValueError(f"outer_accumulate: T {T.dtype} {T.shape}, ptr {ptr.shape}, dirs {dirs.shape}, Y {Y.shape}, R "
                         f"{None if R is None else R.shape}; accepted: contiguous float64 [k, n, n], [k+1], [E], [N, n] "
                         "and [E, n] or None")
    p = np.ascontiguousarray(ptr, np.int64)
    d = np.ascontiguousarray(dirs, np.int64)
    if int(p[0]) != 0 or int(p[-1]) != E or (k and bool((p[1:] < p[:-1]).any())) \
            or (E and (int(d.min()) < 0 or int(d.max()) >= Y.shape[0])):
        # the C reads R and Y by these indices unchecked: out of range is an out-of-bounds read
        raise ValueError(f"outer_accumulate: ptr from {int(p[0])} to {int(p[-1])} (E = {E}), directions in "
                         f"[{int(d.min()) if E else 0}, {int(d.max()) if E else 0}]; accepted: ptr 0 .. E nondecreasing, "
                         f"directions in [0, {Y.shape[0]})")
    y = np.ascontiguousarray(Y, np.float64)
    r = None if R is None else np.ascontiguousarray(R, np.float64)
    lib.prt_outer_accumulate(k, n, p.ctypes.data, d.ctypes.data, y.ctypes.data, None if r is None else r.ctypes.data,
                             float(c), T.ctypes.data, int(threads or 1))
    return True


def luma_mix(out: np.ndarray, rho: np.ndarray, x: np.ndarray, w: np.ndarray) -> bool:
    """``out[h] = ((ρ_h0 x_h0) w0 + (ρ_h1 x_h1) w1) + (ρ_h2 x_h2) w2``: a coloured hit's exit transfer made
    monochrome by the luminance weights (the glossy bounce, ``diffuse.HitBounce.exit_transfer``), in one
    compiled pass (``kernels/glossy.c``, ``prt_luma_mix``) with the torch steps' operations in their order
    (the same bits); False without the library.

    ``out float64 [H, n]`` C-contiguous (written); ``rho float64 [H, 3]``; ``x float64 [H, C, n]`` (channel c
    read from min(c, C - 1)); ``w float64 [3]``."""
    lib = _lib()
    if lib is None:
        return False
    H, n = out.shape if out.ndim == 2 else (-1, -1)
    if out.dtype != np.float64 or not out.flags.c_contiguous or rho.shape != (H, 3) or x.ndim != 3 \
            or x.shape[0] != H or x.shape[2] != n or x.shape[1] < 1 or np.shape(w) != (3,):
        raise ValueError(f"luma_mix: out {out.dtype} {out.shape}, rho {rho.shape}, x {x.shape}, w {np.shape(w)}; accepted: "
                         "contiguous float64 [H, n], [H, 3], [H, C, n] with C >= 1, [3]")
    r = np.ascontiguousarray(rho, np.float64)
    xx = np.ascontiguousarray(x, np.float64)
    ww = np.ascontiguousarray(w, np.float64)
    lib.prt_luma_mix(H, n, xx.shape[1], r.ctypes.data, xx.ctypes.data, ww.ctypes.data, out.ctypes.data)
    return True
