"""The transport tables' BRDF passes compiled (issue 42 §2): the point values f_r W on the (upper view,
visible texel) pairs and the texel averages Σ_s a_s f_r(ω_s) max(n·ω_s, 0) (Green 2005 eq. 1.2), each a
fused loop over the pairs with the BRDF inline, for the models the C knows (:func:`native_model`:
Ashikhmin–Shirley, Phong in both forms, Blinn-Phong, Lambertian, Ward 1992 (isotropic and anisotropic) and
Ramamoorthi 2002's microfacet model (eq. 5.34); exactly those classes, not subclasses).

The C is ``prt_torch/kernels/transport.c`` (library ``transport``, built by :mod:`prt_torch._native`; its
opening comment gives the layouts). Where torch made ~15 elementwise passes over block-sized float64
temporaries per evaluation (~140 ns each), the C evaluates each pair once in registers, the power 4 lanes
at a time (glibc's libmvec on the AVX2 path, libm's ``pow`` on the portable one; Ward's and the microfacet's
``exp`` and ``acos`` the same way). The values are the torch
path's to a few ulp in float64 (``tests/test_transport_native.py``: relative 1e-12), rounded once to the
stored dtype. Without a compiler or libmvec, with ``PRT_TORCH_NATIVE=0``, for another BRDF or dtype, the
functions return False and the caller keeps torch.
"""
from __future__ import annotations

import ctypes
import os
import threading

import torch

from .._native import LIBRARIES, compile_library, kernel_sources

__all__ = ["native_model", "points", "averages", "available"]

_SOURCES, _FLAGS = LIBRARIES["transport"][0], list(LIBRARIES["transport"][1])
_lock = threading.Lock()
_state: dict = {}
_i64, _vp, _ci = ctypes.c_int64, ctypes.c_void_p, ctypes.c_int
#: the library's functions and their ctypes argument types (as ``kernels/transport.c`` declares them)
_SIGNATURES = {
    "prt_transport_points": [_i64, _i64, _i64, _vp, _vp, _vp, ctypes.c_double, _i64, _vp, _vp, _vp, _ci, _ci, _vp, _ci, _vp, _ci],
    "prt_transport_averages": [_i64, _vp, _vp, _vp, _vp, _i64, _i64, _i64, _vp, _vp, _vp, _vp, _vp, _ci, _ci, _vp, _ci, _vp, _ci],
    "prt_transport_abi": [],
}
#: out_dtype codes of the C
_DTYPES = {torch.float32: 0, torch.float64: 1, torch.float16: 2}


def _lib() -> ctypes.CDLL | None:
    if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return None
    if "lib" not in _state:
        with _lock:
            if "lib" not in _state:
                lib, why = compile_library("transport", kernel_sources(_SOURCES), _FLAGS, _SIGNATURES)
                _state["abi"] = int(lib.prt_transport_abi()) if lib is not None else 0
                _state["why"] = why
                _state["lib"] = lib
    return _state["lib"]


def available() -> tuple[bool, str]:
    """(whether the compiled passes run here, how they were built or why not)."""
    if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return False, "PRT_TORCH_NATIVE=0"
    lib = _lib()
    return lib is not None, _state.get("why", "")


def native_model(brdf, k: int, mat_index: torch.Tensor | None = None) -> tuple[int, int, torch.Tensor] | None:
    """``(model, flags, par float64 [k, 4])`` of ``brdf`` for the C (its header: 0 Ashikhmin–Shirley with flags
    bit 0 Fresnel, bit 1 diffuse, par (nu, nv, rs, rd); 1/2 Phong modified/reflection and 3 Blinn-Phong, par (s,
    ks, kd); 4 Lambertian, par (kd); 5 Ward, par (ax, ay, rs, rd); 6 microfacet, par (sigma, ks)), one row per
    vertex of the chunk (``mat_index [k]``: per-vertex parameters, else shared); None for a model the C does not
    know (its own ``_eval`` then runs in torch)."""
    from ..brdf import AshikhminShirley, BlinnPhong, Lambertian, Microfacet, Phong, Ward

    t = type(brdf)
    if t is AshikhminShirley:
        model, names, flags = 0, ("nu", "nv", "rs", "rd"), int(brdf.fresnel) | (int(brdf.diffuse) << 1)
    elif t is Phong:
        model, names, flags = (1 if brdf.form == "modified" else 2), ("s", "ks", "kd"), 0
    elif t is BlinnPhong:
        model, names, flags = 3, ("s", "ks", "kd"), 0
    elif t is Lambertian:
        model, names, flags = 4, ("kd",), 0
    elif t is Ward:
        model, names, flags = 5, ("ax", "ay", "rs", "rd"), 0
    elif t is Microfacet:
        model, names, flags = 6, ("sigma", "ks"), 0
    else:
        return None
    b = brdf if mat_index is None else brdf.select(mat_index)
    par = torch.zeros(k, 4, dtype=torch.float64)
    for c, n in enumerate(names):
        v = getattr(b, n).to(torch.float64)
        if v.ndim > 1 or (v.ndim == 1 and v.shape[0] not in (1, k)):
            return None
        par[:, c] = v.reshape(-1) if v.ndim == 1 else v
    return model, flags, par


def _ok(T: torch.Tensor) -> bool:
    return T.dtype in _DTYPES and T.is_contiguous() and (T.dtype != torch.float16 or _state.get("abi", 0) >= 2)


def _f64(x: torch.Tensor) -> torch.Tensor:
    return x.to(torch.float64).contiguous()


def points(T: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, W: torch.Tensor,
           averaged: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None, model: tuple[int, int, torch.Tensor],
           threads: int = 1, *, horizon: float) -> bool:
    """The point pass into ``T [k, J·P]`` (every element written: f_r W on the pairs of an upper view — local
    z > ``horizon``, the callers' ``transport.HORIZON_EPS`` — and a texel with W > 0 that are not ``averaged``,
    0 elsewhere), from ``wi [k, P, 3]``, ``wo [k, J, 3]`` local directions and ``W [k, P]`` (float64).
    ``averaged``: the (vertex, view, texel) int64 triples the texel averages write, in lexicographic order
    (as ``transport._averaged_pairs`` gives them), or None. False (nothing written) without the library."""
    lib = _lib()
    if lib is None or not _ok(T):
        return False
    k, P, J = wi.shape[0], wi.shape[1], wo.shape[1]
    wi, wo, W = _f64(wi), _f64(wo), _f64(W)
    e = torch.empty(0, dtype=torch.int64)
    ai, aj, ap = (e, e, e) if averaged is None else (x.to(torch.int64).contiguous() for x in averaged)
    m, flags, par = model
    rc = lib.prt_transport_points(k, J, P, wi.data_ptr(), wo.data_ptr(), W.data_ptr(), float(horizon), ai.numel(), ai.data_ptr(), aj.data_ptr(),
                                  ap.data_ptr(), m, flags, par.data_ptr(), _DTYPES[T.dtype], T.data_ptr(), int(threads))
    if rc:
        raise RuntimeError(f"prt_transport_points returned {rc} (1: bad model or dtype, 2: out of memory, 3: an averaged "
                           "pair out of range, 4: averaged pairs not in (vertex, view, texel) order)")
    return True


_packed: dict = {}


def _pack(sub_texels: dict[int, tuple[torch.Tensor, torch.Tensor]]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The sub-texel sets ``{S: ([P, S², 3], [P, S²])}`` as one float64 buffer of directions, one of shares and
    the offsets ``soff int64 [9]`` (-1: no set of that S), kept for the dict ``sub_texels`` (by identity)."""
    key = id(sub_texels)
    got = _packed.get(key)
    if got is not None and got[0] is sub_texels:
        return got[1]
    soff = torch.full((9,), -1, dtype=torch.int64)
    ds, ws, at = [], [], 0
    for S in sorted(sub_texels):
        d, w = sub_texels[S]
        soff[S] = at
        ds.append(_f64(d).reshape(-1))
        ws.append(_f64(w).reshape(-1))
        at += w.numel()
    packed = (torch.cat(ds), torch.cat(ws), soff)
    _packed.clear()
    _packed[key] = (sub_texels, packed)
    return packed


def averages(T: torch.Tensor, frames: torch.Tensor, wo: torch.Tensor, pairs: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
             subs: torch.Tensor, sub_texels: dict, model: tuple[int, int, torch.Tensor], threads: int = 1) -> bool:
    """The texel averages of ``pairs`` (vertex, view, texel int64 ``[n]`` each; ``subs [n]`` their sub-texel
    counts) into ``T [k, J·P]``, from ``frames [k, 3, 3]``, ``wo [k, J, 3]`` and ``sub_texels`` (as
    :func:`transport.sub_texel_sets`). The C takes the pairs in (vertex, texel) order (a counting sort) so that
    each one's sub-texels are rotated once per S for its views. False (nothing written) without the library."""
    lib = _lib()
    if lib is None or not _ok(T):
        return False
    iv, jv, pv = pairs
    n = iv.numel()
    if not n:
        return True
    k, J, P = wo.shape[0], wo.shape[1], T.shape[1] // wo.shape[1]
    iv, jv, pv, sv = (x.to(torch.int64).contiguous() for x in (iv, jv, pv, subs))
    sd, sw, soff = _pack(sub_texels)
    fr, wo = _f64(frames), _f64(wo)
    m, flags, par = model
    rc = lib.prt_transport_averages(n, iv.data_ptr(), jv.data_ptr(), pv.data_ptr(), sv.data_ptr(), k, J, P, fr.data_ptr(),
                                    wo.data_ptr(), sd.data_ptr(), sw.data_ptr(), soff.data_ptr(), m, flags, par.data_ptr(),
                                    _DTYPES[T.dtype], T.data_ptr(), int(threads))
    if rc:
        raise RuntimeError(f"prt_transport_averages returned {rc} (1: bad model or dtype, 2: out of memory, 3: a pair out "
                           "of range or a sub-texel count without its set)")
    return True
