"""Sums of spherical Gaussians per vertex and view (Green 2005): batched non-linear fits and
relighting from a Gaussian-prefiltered environment.

Representation (Green eq. 2.1, 3.2). For vertex x and stored view v, the tabulated transport
function T_{x,v}(ω) (:mod:`prt_torch.transfer.transport`, a cube map of P = 6r² texels) is
approximated by N isotropic spherical Gaussians

    T̃_{x,v}(ω) = Σ_k w_k G(ω, μ_k, σ_k),   w_k ≥ 0, ‖μ_k‖ = 1, σ_k > 0,

with G the normalised spherical Gaussian of :mod:`prt_torch.lighting.prefilter` (unit
integral; Green's eq. 3.2 with the chord distance instead of the cube unfolding M_μ, which
needs no special case at cube edges and corners). Each lobe is 5 floats (scalar weight — the
tables are scalar — 3 for the mean, 1 width); Green's RGB weights make it 7.

The package, one idea a module:

* here: :class:`GaussianCodec` — its parameters, the table geometry (views, texel directions
  and solid angles), fit and encode, decode, ``relight`` (every stored view, view taps, surface
  points) and its checks, the prepared ``relighter``, storage and saved state;
* :mod:`.fit`: the mixture (eq. 2.1), the objective (eq. 2.2–2.6) and its batched optimiser,
  the starting lobes, the narrowest resolvable lobe and the flood-fill order (§2.2.2);
* :mod:`.views`: the stored views, their neighbours (eq. 2.4–2.5), view taps and the
  interpolation of lobes across views and triangle vertices (§2.3);
* :mod:`.relight`: lookups into the Gaussian-prefiltered environment (eq. 2.7) and
  :class:`GaussianRelighter`;
* :mod:`.compare`: the SH and Haar approximations Green compares the Gaussians with (Fig. 3-3).

Rendering (Green §2.3, eq. 2.7; :mod:`.relight`): parameters are interpolated across the three
nearest stored views (barycentric weights; μ renormalised) and, on a surface, across the
triangle's vertices; each lobe is one lookup w_k E_{σ_k}(μ_k) into a
:class:`PrefilteredEnvironment`. An optional view-independent part (per texel the minimum over a vertex's views with data) is kept in SH
(``diffuse_bands``; Green §3.1) and relit as t·l.

As one array (``transform``, ``inverse_transform``), a row per vertex, float32: its J·N lobe
records in view-then-lobe order, 5 columns each (w, μx, μy, μz, σ), named
``gaussian_v{j}_l{k}_{w,mux,muy,muz,sigma}``; with ``diffuse_bands`` = n > 0 then its n² SH
diffuse coefficients (``gaussian_diffuse{i}``) and its J has-data flags as 0/1
(``gaussian_has_data_v{j}``).
"""
from __future__ import annotations

import math
import time
import warnings
from typing import Any

import torch

from ..._checks import check_finite_float32, tensor_state, tensor_version
from ...lighting.prefilter import PrefilteredEnvironment, cube_map_directions
from ...params import Boolean, Interval, Options
from ..base import (Codec, Encoded, array_type, as_array_type, check_cpu, check_out, check_signal, grad_required, input_ref, register,
                    typed, typed_relighter, view_nbytes, view_tensors)
from ..relight_kernels import lobe_layout, sg_prepare, sg_taps, sg_taps_prepare, sg_taps_prepared
from .compare import haar_truncation, relative_l2, sh_light_lobe_integral, sh_truncation
from .fit import RESOLVE_FACTOR, fit_all, flood_fill_order, mixture, prob_pairs, resolvable_sigma  # noqa: F401 (importable here as before)
from .fit import Problem as _Problem, tangents as _tangents  # noqa: F401 (the names tests/test_gaussian.py uses)
from .relight import GaussianRelighter, fused, lobe_sum, lobes_state
from .views import (blend_lobes, default_views, fibonacci_directions, fill_empty_lobes, order_lobes, view_neighbours, view_taps,
                    views_cover_sphere)

__all__ = ["GaussianCodec", "resolvable_sigma", "relative_l2", "sh_truncation", "haar_truncation", "sh_light_lobe_integral",
           "fibonacci_directions", "default_views", "view_neighbours", "view_taps",
           "views_cover_sphere", "mixture", "blend_lobes", "lobe_sum", "flood_fill_order", "MAX_LOBES", "order_lobes", "fill_empty_lobes"]

#: the largest lobe count accepted (Green uses 1–3, plots up to 10)
MAX_LOBES = 16

# relight with taps keeps their blend and its addressing (GaussianCodec._prepare) from the second
# call with the same taps on where they make at least this many lookups (V·N): its key costs about
# 4 µs a call, which taps that change at every call (a moving camera) pay for nothing — under 10%
# of a relight from here on (about 10 ns a lookup), while unchanged taps relight 2.5-4x faster
TAPS_CACHE_MIN_LOOKUPS = 4096


@register("gaussian")
class GaussianCodec(Codec):
    """Green 2005: per vertex and view, a sum of spherical Gaussians fitted to transport tables; relit from a Gaussian-prefiltered environment.

    Parameters
    ----------
    lobes : int, default=1
        Number N of Gaussians per transport function (Green uses 1–3).
    max_iter : int, default=30
        Optimiser iterations per batch (the last lobe's stage; earlier stages of the greedy
        start take a quarter). Each LM iteration forms the normal equations once and tries up
        to ``fit.LM_TRIES`` = 5 damped steps on them. Was 20 with one try until issue 42 §2,
        where 38% of the functions of 3 lobes on the default tables stopped unconverged
        (docs/codecs_log.md, "Convergence").
    optimizer : {'lm', 'lbfgs'}, default='lm'
        'lm': batched Levenberg–Marquardt (Gauss–Newton normal equations per function, one
        4N×4N Cholesky each; per-function damping and convergence). 'lbfgs': torch's L-BFGS
        with a strong-Wolfe line search on the batch's summed objective (widths through a
        sigmoid between the bounds, means normalised) — kept as the measured alternative:
        benchmarks/bench_gaussian.py compares both at equal iterations and equal time.
    tol : float, default=1e-4
        A function has converged when an accepted step lowers its objective by less than this
        fraction (or every coordinate of its step is below 1e-4, or its damping reached 1e12).
    view_weight : float, default=1e-3
        β = γ of Green eq. 2.4–2.5 (alignment of means and widths with the neighbouring views),
        relative to each function's energy Σ Δω T².
    spatial_weight : float, default=1e-2
        δ of Green eq. 2.6 (arrangement of the lobes consistent with fitted mesh neighbours),
        relative to each function's energy.
    sigma_min : float, default=0.01
        Smallest lobe width (radians); at least :func:`resolvable_sigma` of the tables is used
        (0.35 × the texel spacing, 2/r on a cube map: a narrower lobe could fall between texel
        centres).
    sigma_max : float, default=3.0
        Largest lobe width (radians; wider than a hemisphere is allowed).
    diffuse_bands : int, default=0
        Keep a view-independent part in SH with this many bands (Green §3.1; 0: none).
    batch_size : int, default=8192
        Transport functions optimised together (memory ~ batch · 6r² · 4N floats).
    seed : int, default=0
        Unused by the deterministic fit; kept for the common interface.
    strict : bool, default=False
        Raise instead of warning when functions did not converge within ``max_iter``.
    fill_empty : bool, default=True
        After the fit, give each lobe of weight 0 (zero functions below a vertex's horizon, dropped
        lobes) its neighbouring views' mean and width (:func:`fill_empty_lobes`): the tables are
        unchanged, the blend at view taps (§2.3) no longer pulls a lobe toward a placeholder
        (issue 42 §2: +1.9 dB at 2 lobes, 162 views, against the exact radiance). False: as fitted.
    """

    linear = False
    light_kind = "prefiltered"
    _parameter_constraints = {
        "lobes": [Interval(int, 1, MAX_LOBES)],
        "max_iter": [Interval(int, 1, 10000)],
        "optimizer": [Options("lm", "lbfgs")],
        "tol": [Interval(float, 0, 1, closed="left")],
        "view_weight": [Interval(float, 0, None)],
        "spatial_weight": [Interval(float, 0, None)],
        "sigma_min": [Interval(float, 1e-4, 1.0)],
        "sigma_max": [Interval(float, 0.1, 10.0)],
        "diffuse_bands": [Interval(int, 0, 12)],
        "batch_size": [Interval(int, 1, None)],
        "seed": [Interval(int, 0, None)],
        "strict": [Boolean()],
        "fill_empty": [Boolean()],
    }

    def __init__(self, *, lobes=1, max_iter=30, optimizer="lm", tol=1e-4, view_weight=1e-3, spatial_weight=1e-2, sigma_min=0.01,
                 sigma_max=3.0, diffuse_bands=0, batch_size=8192, seed=0, strict=False, fill_empty=True):
        self.lobes = lobes
        self.max_iter = max_iter
        self.optimizer = optimizer
        self.tol = tol
        self.view_weight = view_weight
        self.spatial_weight = spatial_weight
        self.sigma_min = sigma_min
        self.sigma_max = sigma_max
        self.diffuse_bands = diffuse_bands
        self.batch_size = batch_size
        self.seed = seed
        self.strict = strict
        self.fill_empty = fill_empty

    def _check_params(self, p):
        if p["sigma_min"] >= p["sigma_max"]:
            raise ValueError(f"codec {self.codec_name!r}: sigma_min={p['sigma_min']} >= sigma_max={p['sigma_max']}; "
                             "accepted: sigma_min < sigma_max")

    def __getstate__(self):
        return {k: v for k, v in super().__getstate__().items() if k != "_train"}

    # ------------------------------------------------------------------ geometry
    def _geometry(self, D, matrix_shape, views, directions, solid_angles, kind):
        if kind is not None and kind != "transport":
            raise ValueError(f"codec {self.codec_name!r} fits transport tables (transfer kind 'transport', "
                             f"prt precompute --kind transport); got a transfer of kind {kind!r}")
        if matrix_shape is None:
            J, P = 1, D
        else:
            J, P = (int(v) for v in matrix_shape)
            if J * P != D or J < 1 or P < 1:
                raise ValueError(f"matrix_shape={tuple(matrix_shape)} does not fold D={D}; accepted: (views J, texels P) with J*P = D")
        if directions is not None:
            dirs = torch.as_tensor(directions, dtype=torch.float64).reshape(-1, 3)
            if dirs.shape[0] != P:
                raise ValueError(f"directions has {dirs.shape[0]} rows; accepted: one per texel, P = {P}")
            dirs = dirs / dirs.norm(dim=-1, keepdim=True)
            sa = (torch.full((P,), 4 * math.pi / P, dtype=torch.float64) if solid_angles is None
                  else torch.as_tensor(solid_angles, dtype=torch.float64).reshape(-1))
            layout = "given"
        else:
            r = math.isqrt(P // 6)
            if 6 * r * r == P:
                d, s = cube_map_directions(r)
                dirs, sa, layout = d.reshape(-1, 3), s.reshape(-1), f"cube{r}"
            else:
                dirs, sa, layout = fibonacci_directions(P), torch.full((P,), 4 * math.pi / P, dtype=torch.float64), "fibonacci"
        if sa.shape != (P,) or not bool(torch.isfinite(sa).all()) or bool((sa < 0).any()):
            raise ValueError(f"solid_angles must be [P] = [{P}] finite non-negative texel solid angles")
        if views is not None:
            vw = torch.as_tensor(views, dtype=torch.float64)
            if vw.ndim != 2 or vw.shape != (J, 3):
                raise ValueError(f"views has shape {tuple(vw.shape)}; accepted: [J, 3] = [{J}, 3], one per stored view")
            if not bool(torch.isfinite(vw).all()) or bool((vw.norm(dim=-1) < 1e-9).any()):
                raise ValueError("views must be finite non-zero directions")
            vw = vw / vw.norm(dim=-1, keepdim=True)
            ok, worst = views_cover_sphere(vw)
            if not ok:
                raise ValueError(f"views do not cover the hemisphere of every vertex: some direction is {worst:.1f}° from "
                                 "the nearest view; accepted: a view set with every direction within 75° of a view "
                                 "(e.g. the icosphere views of prt precompute --kind transport)")
        else:
            vw = default_views(J)
        return J, P, dirs, sa, vw, layout

    # ------------------------------------------------------------------ fit / encode
    def fit(self, X, y=None, weights=None, matrix_shape=None, *, views=None, directions=None, solid_angles=None,
            faces=None, kind=None, init=None) -> "GaussianCodec":
        """Fit on transport tables ``X [V, J·P]`` (row v: J functions of P texels; ``matrix_shape
        = (J, P)``). Geometry keywords: ``views [J, 3]`` (default: the icosphere when J = 10f²+2),
        ``directions [P, 3]`` and ``solid_angles [P]`` (default: the cube map when P = 6r²),
        ``faces [F, 3]`` (mesh, for the flood fill and the spatial term eq. 2.6), ``kind`` (the
        transfer kind; anything but 'transport' is refused), ``init`` (starting parameters instead
        of peaks and moments: an :class:`Encoded` of this codec or ``(w [V, J, N], mu [V, J, N, 3],
        sigma [V, J, N])``). All checks before any work."""
        p = self._validate()
        X_in = X
        X = check_signal("X", X)
        if weights is not None:
            raise ValueError(f"codec {self.codec_name!r} does not take per-point weights; accepted: weights=None")
        J, P, dirs, sa, vw, layout = self._geometry(X.shape[1], matrix_shape, views, directions, solid_angles, kind)
        if faces is not None:
            faces = torch.as_tensor(faces).long()
            if faces.ndim != 2 or faces.shape[1] != 3 or (faces.numel() and (int(faces.min()) < 0 or int(faces.max()) >= X.shape[0])):
                raise ValueError(f"faces must be [F, 3] vertex indices in [0, {X.shape[0]})")
        if init is not None:
            if isinstance(init, Encoded):
                init = self.lobes_of(init)
            init = tuple(torch.as_tensor(t, dtype=torch.float32) for t in init)
            want = [(X.shape[0], J, p["lobes"]), (X.shape[0], J, p["lobes"], 3), (X.shape[0], J, p["lobes"])]
            if len(init) != 3 or [tuple(t.shape) for t in init] != want or not all(bool(torch.isfinite(t).all()) for t in init):
                raise ValueError(f"init must be finite (w, mu, sigma) of shapes {want}")
        self.J_, self.P_, self.layout_ = J, P, layout
        self.views_, self.directions_, self.solid_angles_ = vw.float(), dirs.float(), sa.float()
        self.n_features_in_ = X.shape[1]
        self.faces_ = faces
        self.fitted_ = True
        enc, info = self._encode(X, p, init)
        enc.array_type = array_type(X_in)
        self._train = ((X.data_ptr(), tuple(X.shape), X.dtype, tensor_version(X)), input_ref(X_in), enc)
        self.fit_info_ = info
        if info.get("lobes_at_resolution_limit", 0.0) > 0.25:
            warnings.warn(
                f"codec {self.codec_name!r}: {100 * info['lobes_at_resolution_limit']:.0f}% of the fitted lobes sit at the "
                f"narrowest width the tables resolve (sigma = {info['sigma_resolvable']:.3f} rad, {RESOLVE_FACTOR:g} texel spacings at "
                f"{layout}): the transport is sharper than its texels, so those functions keep a large error whatever "
                "the lobe count; tabulate with a finer cube map (prt precompute --kind transport with the default --cube-res auto, "
                "which sizes it from the BRDF's lobe, or --cube-res 16 or more)",
                UserWarning, stacklevel=2)
        if info["converged_fraction"] < 1.0:
            self._warn_or_raise(f"codec {self.codec_name!r}: {info['not_converged']} of {info['functions_fitted']} "
                                f"transport functions did not converge in max_iter={p['max_iter']} iterations")
        return self

    def fit_encode(self, X, weights=None, matrix_shape=None, **geometry) -> Encoded:
        return self.fit(X, weights=weights, matrix_shape=matrix_shape, **geometry).encode(X)

    def encode(self, X) -> Encoded:
        """Fit the Gaussian parameters of ``X [V, J·P]`` with the fitted geometry (the training
        signal's encoding is returned without refitting; ``Encoded.array_type``: X's)."""
        self._require_fitted()
        kind = array_type(X)
        X = check_signal("X", X)
        self._check_features(X)
        train = getattr(self, "_train", None)
        if train is not None and train[0] == (X.data_ptr(), tuple(X.shape), X.dtype, tensor_version(X)) and train[1]() is not None:
            return typed(train[2], kind)
        enc = self._encode(X, self.params)[0]
        enc.array_type = kind
        return enc

    def _encode(self, X: torch.Tensor, p: dict, init=None) -> tuple[Encoded, dict]:
        t0 = time.perf_counter()
        V, J, P, N = X.shape[0], self.J_, self.P_, p["lobes"]
        T = X.reshape(V, J, P).to(torch.float32)
        dirs, sa = self.directions_, self.solid_angles_
        enc_t: dict[str, torch.Tensor] = {}
        nb = self.diffuse_bands_ = int(p["diffuse_bands"])
        if nb:
            from ...sh import eval_sh

            has = T.amax(-1) > 0  # [V, J]
            big = torch.finfo(torch.float32).max
            Dmin = torch.where(has[..., None], T, torch.full_like(T, big)).amin(1)
            Dmin = torch.where(has.any(1, keepdim=True), Dmin, torch.zeros_like(Dmin)).clamp_min(0)  # [V, P]
            Y = eval_sh(dirs.double(), nb, check=False).float()  # [P, n²]
            t = (Dmin * sa) @ Y  # [V, n²]  (SH projection, solid-angle quadrature)
            T = T - (t @ Y.T)[:, None, :] * has[..., None]
            enc_t["diffuse"] = t
            enc_t["has_data"] = has.to(torch.uint8)
        w, mu, sg, info = fit_all(T, p, init, self.directions_, self.solid_angles_, self.views_, self.faces_)
        # lobe n of neighbouring views the same lobe, so that the taps' blend (Green §2.3) blends corresponding
        # lobes: +0.5-0.8 dB against the truth at 2-3 lobes (reports/benchmarks/gaussian_taps.md); tables unchanged
        w, mu, sg = order_lobes(w, mu, sg, self.views_)
        if p["fill_empty"]:  # weight-0 lobes placed where their neighbours' are, so a tap on them only fades (issue 42 §2)
            w, mu, sg = fill_empty_lobes(w, mu, sg, self.views_)
        # view-major records [J, V, N, 5] (lobes_of): a camera's taps, a few views shared by neighbouring
        # vertices, read runs along the vertices (vertex-major [V, J, N, 5]: three scattered runs per vertex)
        enc_t["lobes_by_view"] = torch.cat([w[..., None], mu, sg[..., None]], -1).transpose(0, 1).contiguous()
        enc = self._encoded(enc_t, V, N, nb)
        err, ref, se, tot = self._fit_errors(X.reshape(V, J, P), enc)
        nz = ref > 0
        rel_f = (err[nz] / ref[nz]).sqrt()
        info.update({
            "relative_l2": math.sqrt(float(err.sum()) / max(1e-300, float(ref.sum()))),
            "relative_l2_median": float(rel_f.median()) if rel_f.numel() else 0.0,
            "relative_l2_p90": float(rel_f.quantile(0.9)) if rel_f.numel() else 0.0,
            "se": se, "seconds": time.perf_counter() - t0,
        })
        info["se_relative"] = se / max(1e-300, tot)
        info["functions_per_s"] = V * J / max(info["seconds"], 1e-9)
        return enc, info

    def _fit_errors(self, T: torch.Tensor, enc: Encoded, rows: int = 64) -> tuple[torch.Tensor, torch.Tensor, float, float]:
        """The fit's error statistics against the tables ``T [V, J, P]``: per function the
        solid-angle weighted squared error ``Σ_p Δω_p (T̃ − T)²`` and energy ``Σ_p Δω_p T²`` (``[V, J]``
        float64), the plain squared error ``Σ (T̃ − T)²`` and ``Σ T²`` (floats) — all in float64,
        decoded ``rows`` vertices at a time into one reused buffer, so no table-sized float64
        temporary is made (before: five of them, 1.3 GB each at 10k vertices × 42 views × 6×8×8). 64 rows
        (8 MiB float64 blocks at 42 × 384): under glibc's largest mmap threshold (32 MiB), so the blocks
        come back from the heap instead of fresh pages (256 rows: 33 MiB, mapped and faulted in at every
        block; 2000 vertices of the default part's tables: 0.35 → 0.26 s CPU, 28k → 0 page faults)."""
        V, J, P = T.shape
        sa64 = self.solid_angles_.double()
        err = torch.empty(V, J, dtype=torch.float64)
        ref = torch.empty(V, J, dtype=torch.float64)
        se = tot = 0.0
        lobes = self.lobes_of(enc)
        buf = torch.empty(min(V, rows), J, P, dtype=torch.float64)
        for a in range(0, V, rows):  # row blocks: bounded float64 temporaries
            b = min(V, a + rows)
            d = buf[:b - a]
            d.copy_(self._decode_rows(enc, lobes, a, b))
            t = T[a:b].double()
            d.sub_(t)
            se += float(torch.linalg.vector_norm(d).square())
            tot += float(torch.linalg.vector_norm(t).square())
            err[a:b] = d.square_().matmul(sa64)
            ref[a:b] = t.square().matmul(sa64)  # not in place: .double() of a float64 T is T itself (the caller's X)
        return err, ref, se, tot

    def _encoded(self, tensors: dict[str, torch.Tensor], V: int, N: int, nb: int) -> Encoded:
        """An encoding of ``V`` vertices with ``N`` lobes and ``nb`` diffuse bands (meta from the fitted geometry)."""
        return Encoded(codec=self.codec_name, tensors=tensors,
                       meta={"points": V, "dim": self.J_ * self.P_, "matrix_shape": [self.J_, self.P_], "lobes": N,
                             "layout": self.layout_, "diffuse_bands": nb})

    @property
    def n_iter_(self) -> int:
        """Optimiser iterations of the fit: the most any batch ran (``fit_info_['batches']``)."""
        try:
            return max((int(b["iterations"]) for b in self.fit_info_["batches"]), default=0)
        except (AttributeError, KeyError):
            raise AttributeError(f"{type(self).__name__} has no n_iter_ before a fit") from None

    # ------------------------------------------------------------------ codes as one array
    def _code_layout(self) -> tuple[int, int, int]:
        """``(J, N, n²)``: views, lobes (the ``lobes`` parameter) and SH diffuse coefficients per vertex."""
        self._require_fitted()
        p = self.params
        return self.J_, int(p["lobes"]), int(p["diffuse_bands"]) ** 2

    def _code_columns(self) -> list[str]:
        J, N, nd = self._code_layout()
        cols = [f"_v{j}_l{k}_{f}" for j in range(J) for k in range(N) for f in ("w", "mux", "muy", "muz", "sigma")]
        if nd:
            cols += [f"_diffuse{i}" for i in range(nd)] + [f"_has_data_v{j}" for j in range(J)]
        return cols

    def _codes_to_array(self, enc: Encoded) -> torch.Tensor:
        """``[V, J·N·5 (+ n² + J)]`` float32: the lobe records vertex-major (``lobes_of``), then the
        diffuse part and the has-data flags."""
        self._require_fitted()
        w, mu, sg = self.lobes_of(enc)
        V = w.shape[0]
        parts = [torch.cat([w[..., None], mu, sg[..., None]], -1).reshape(V, -1).float()]
        if "diffuse" in enc.tensors:
            parts += [enc.tensors["diffuse"].float(), enc.tensors["has_data"].float()]
        out = torch.cat(parts, 1)
        if out.shape[1] != len(self._code_columns()):
            raise ValueError(f"this encoding has {out.shape[1]} values per vertex; this codec's layout has "
                             f"{len(self._code_columns())} (lobes and diffuse_bands as when it was encoded?)")
        return out

    def _codes_from_array(self, Z: torch.Tensor) -> Encoded:
        """The encoding of ``Z`` (``_codes_to_array``'s layout); has-data flags must be 0 or 1."""
        J, N, nd = self._code_layout()
        V, nl = Z.shape[0], J * N * 5
        tensors = {"lobes_by_view": Z[:, :nl].reshape(V, J, N, 5).transpose(0, 1).contiguous()}
        if nd:
            has = Z[:, nl + nd:]
            bad = (has != 0) & (has != 1)
            if bool(bad.any()):
                v, j = (int(i) for i in torch.nonzero(bad)[0])
                raise ValueError(f"Z[{v}, {nl + nd + j}] = {float(has[v, j])!r} is a has-data flag; accepted: 0 or 1")
            tensors["diffuse"] = Z[:, nl:nl + nd].contiguous()
            tensors["has_data"] = has.to(torch.uint8)
        return self._encoded(tensors, V, N, int(self.params["diffuse_bands"]))

    # ------------------------------------------------------------------ decode / relight
    @staticmethod
    def lobes_of(enc: Encoded) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(w [V, J, N], mu [V, J, N, 3], sigma [V, J, N])`` of an encoding: views of its lobe
        records (w, μx, μy, μz, σ) float32, read in place by the kernels. Stored view-major,
        ``lobes_by_view [J, V, N, 5]``: view j of vertices v, v+1, ... is one run, so a camera's
        taps (a few views shared by neighbouring vertices) read a few runs along the vertices —
        measured 1.4–2× faster at 50 000 vertices than vertex-major records, whose three tapped
        runs per vertex sit in three cache lines 20·J·N bytes apart
        (reports/benchmarks/relight.md). Encodings saved with vertex-major ``lobes [V, J, N, 5]``
        (format before 2026-11-24), or before the records (separate ``weights``, ``mu``,
        ``sigma``), are returned as they are."""
        t = enc.tensors
        name = "lobes_by_view" if "lobes_by_view" in t else "lobes"
        if name in t:
            rec = t[name]
            key = (name, rec.data_ptr(), tuple(rec.shape), rec.stride(), rec.dtype)  # .data = / set_() keep the object
            hit = enc.cache.get("lobe_views")
            if hit is not None and hit[0] is rec and hit[1] == key:  # three views cost ~12 µs a call, a sixth of a small relight
                return hit[2]
            if rec.ndim != 4 or rec.shape[-1] != 5:
                shape = "[J, V, N, 5]" if name == "lobes_by_view" else "[V, J, N, 5]"
                raise ValueError(f"encoding tensor {name!r} has shape {tuple(rec.shape)}; accepted: {shape}")
            r = rec.transpose(0, 1) if name == "lobes_by_view" else rec  # [V, J, N, 5]
            views = (r.select(-1, 0), r.narrow(-1, 1, 3), r.select(-1, 4))
            lay = lobe_layout(*views)  # kept only where it reads the records in place (float32): no copy to go stale
            enc.cache["lobe_views"] = (rec, key, views, lay if lay[0] is views[0] else None)
            return views
        missing = [k for k in ("weights", "mu", "sigma") if k not in t]
        if missing:
            raise ValueError(f"not a gaussian encoding: no tensor 'lobes_by_view' (nor 'lobes', nor {', '.join(map(repr, missing))}); "
                             f"it has {sorted(t)}")
        return t["weights"], t["mu"], t["sigma"]

    @classmethod
    def _lobes_and_layout(cls, enc: Encoded) -> tuple[tuple, tuple | None]:
        """``(lobes_of(enc), their relight_kernels.lobe_layout)``, the layout kept with the cached
        views (records; None for separate arrays, whose layout the kernels work out per call)."""
        views = cls.lobes_of(enc)
        hit = enc.cache.get("lobe_views")
        return views, (hit[3] if hit is not None and hit[2] is views else None)

    def decode(self, enc: Encoded) -> torch.Tensor:
        """The fitted tables ``[V, J·P]`` float32 (Green eq. 2.1 at the texel directions, plus
        the SH diffuse part where the view has data): a tensor, or a numpy array for an encoding of
        numpy data (``Encoded.array_type``)."""
        self._require_fitted()
        lobes = self.lobes_of(enc)
        V, J, N = lobes[0].shape
        out = torch.empty(V, J, self.P_)
        step = max(1, 65536 // max(1, J))
        for a in range(0, V, step):  # chunks bound the [V·J, N, P] temporary
            b = min(V, a + step)
            out[a:b] = self._decode_rows(enc, lobes, a, b)
        return as_array_type(out.reshape(V, -1), enc.array_type)

    def _decode_rows(self, enc: Encoded, lobes: tuple, a: int, b: int) -> torch.Tensor:
        """Vertices ``a:b`` of the fitted tables, ``[b − a, J, P]`` float32 (``decode``'s block):
        Green eq. 2.1 at the texel directions from ``lobes = lobes_of(enc)``, plus the SH diffuse
        part where the view has data."""
        w, mu, sg = (t[a:b] for t in lobes)
        n, J, N = w.shape
        out = mixture(self.directions_, w.reshape(-1, N), mu.reshape(-1, N, 3), sg.reshape(-1, N)).reshape(n, J, -1)
        if "diffuse" in enc.tensors:
            from ...sh import eval_sh

            Y = eval_sh(self.directions_.double(), int(enc.meta["diffuse_bands"]), check=False).float()
            out += (enc.tensors["diffuse"][a:b] @ Y.T)[:, None, :] * enc.tensors["has_data"][a:b].float()[..., None]
        return out

    def _check_light(self, light):
        if not isinstance(light, PrefilteredEnvironment):
            raise TypeError(f"codec {self.codec_name!r} relights from a Gaussian-prefiltered environment "
                            "(light_kind 'prefiltered': prt_torch.lighting.prefilter_environment(light)); "
                            f"got {type(light).__name__}")
        return light.check()  # the kernels size the pyramid from its ladder: a mismatch would read past it

    @staticmethod
    def _check_diffuse_light(enc, light):
        """An encoding with an SH diffuse part needs a light with SH coefficients."""
        if "diffuse" in enc.tensors and light.sh is None:
            raise ValueError(f"this encoding has an SH diffuse part of {enc.tensors['diffuse'].shape[1]} coefficients; accepted: "
                             "a PrefilteredEnvironment with SH coefficients (an SH light, or prefilter_environment(..., sh_bands=))")

    def _diffuse(self, enc, light):
        """t·l per vertex ``[V, C]`` (Green §3.1's SH diffuse part); an SH light with fewer
        coefficients is zero beyond them. Differentiable with respect to ``light.sh`` when it
        requires grad (in its dtype)."""
        t = enc.tensors["diffuse"]
        self._check_diffuse_light(enc, light)
        dt = light.sh.dtype if grad_required(light.sh) else torch.float32  # under autograd: the light's dtype
        k = min(t.shape[1], light.sh.shape[1])
        L = torch.nn.functional.pad(light.sh[:, :k].to(dt), (0, t.shape[1] - k))
        return t.to(dt) @ L.T  # [V, C]

    def checked_taps(self, view: Any, V: int, J: int, values: bool = True) -> tuple[torch.Tensor, torch.Tensor]:
        """A view as taps over the stored views: ``(idx int64 [V, k], w [V, k])`` as given, or
        the three nearest views of global directions ``[V, 3]`` (:func:`view_taps`). Refuses
        other shapes, indices outside 0..J-1 and weights that are negative or not finite (also
        once converted to float32), naming the first (shared by :meth:`relight` and the GLSL
        decoder). ``values=False`` checks types and shapes only, for a caller whose kernel flags
        bad values itself (``relight_kernels.sg_taps``) and then calls this to raise."""
        if not isinstance(view, (torch.Tensor, tuple, list)):
            view = view_tensors(view)  # numpy directions as a tensor sharing their memory (taps: torch.as_tensor below)
        if isinstance(view, torch.Tensor):
            if view.shape != (V, 3):
                raise ValueError(f"view has shape {tuple(view.shape)}; accepted: taps (idx, w) or global directions [V, 3]")
            view = view_taps(self.views_, view / view.norm(dim=-1, keepdim=True).clamp_min(1e-12))
        if not (isinstance(view, (tuple, list)) and len(view) == 2):
            raise TypeError("view must be taps (idx int64 [V, k], w [V, k]) or directions [V, 3]")
        idx, a = (torch.as_tensor(v) for v in view)
        check_cpu("view taps", idx, a)
        if idx.ndim != 2 or idx.shape[0] != V or a.shape != idx.shape:
            raise ValueError(f"view taps have shapes {tuple(idx.shape)}, {tuple(a.shape)}; accepted: [V, k] with V={V}")
        if idx.is_floating_point() or idx.dtype == torch.bool:
            raise TypeError(f"view tap indices have dtype {idx.dtype}; accepted: an integer dtype")
        if not a.is_floating_point():
            raise TypeError(f"view tap weights have dtype {a.dtype}; accepted: a float dtype")
        idx = idx.long()
        if not values:
            return idx, a
        if idx.numel() and (int(idx.min()) < 0 or int(idx.max()) >= J):
            raise ValueError(f"view tap indices span [{int(idx.min())}, {int(idx.max())}]; accepted: 0..{J - 1}")
        check_finite_float32("view tap weights", a)
        if a.numel() and bool((a < 0).any()):  # the blend (§2.3) is convex: a negative weight has no meaning
            first = tuple(int(i) for i in torch.nonzero(a < 0)[0])
            raise ValueError(f"view tap weights has a negative value {float(a[first]):g} at index {first}; accepted: "
                             "weights >= 0 (barycentric, as view_taps gives them)")
        return idx, a

    def relight(self, enc: Encoded, light: PrefilteredEnvironment, view: Any = None, out: torch.Tensor | None = None) -> torch.Tensor:
        """Exit radiance from the Gaussian form (Green eq. 2.7: Σ_k w_k E_{σ_k}(μ_k)).

        ``light``: :class:`PrefilteredEnvironment`. ``view``: None → every stored view,
        ``[V, J, C]``; taps ``(idx int64 [V, k], w [V, k])`` over the stored views (weights zero
        below the horizon, e.g. from :func:`view_taps`) → ``[V, C]`` with the lobes interpolated
        across the tapped views (§2.3); a tensor ``[V, 3]`` of global view directions → the
        three nearest views' taps, ``[V, C]``. float32: a tensor, or a numpy array for an
        encoding of numpy data (``Encoded.array_type``; the view may be numpy arrays too).
        ``out``: an optional result tensor of that shape (``base.check_out``), written and returned.

        Under autograd — the light's ``levels`` (e.g. ``prefilter_environment`` of an SH light
        that requires grad) or its ``sh`` require grad — the fused kernels (forward-only) give
        way to the torch lookups (``PrefilteredEnvironment.lookup``'s trilinear sum, in the
        levels' dtype): the result is differentiable with respect to the light, the same values
        to float32 rounding; ``out`` is refused then.

        With taps of at least ``TAPS_CACHE_MIN_LOOKUPS`` lookups (V·N), the second call with the
        same taps tensors, unchanged, and a light of the same pyramid keeps their blend and its
        addressing in ``enc.cache['taps_prepared']`` (20 bytes per lobe and 4 per vertex), and
        later such calls read only the texels: the same bits (a static camera under changing
        light; :meth:`relighter` keeps it from the first call).
        """
        res = self._relight_checked(enc, light, view, out)
        return res if out is not None else as_array_type(res, enc.array_type)

    def _relight_checked(self, enc: Encoded, light, view: Any, out, prepare=None) -> torch.Tensor:
        """``relight``'s checks, then ``_relight``; ``prepare(light, lobes, taps)``: the prepared
        addressing to read (``GaussianRelighter``), or None."""
        self._require_fitted()
        light = self._check_light(light)
        lobes = self._lobes_and_layout(enc)
        V, J, _ = lobes[0][0].shape
        if view is not None:  # values: by the fused kernel as it reads them (it flags bad ones), else in _relight
            view = self.checked_taps(view, V, J, values=False)
        self._check_diffuse_light(enc, light)  # refused before anything is written into out
        if out is not None and grad_required(light.levels, light.sh):
            raise ValueError("out= with a light whose levels or SH coefficients require grad; accepted: out=None (autograd "
                             "cannot write into a reused buffer)")
        if out is not None:  # the fused kernels write into it (no result-sized temporary and copy)
            out = check_out(out, (V, light.channels) if view is not None else (V, J, light.channels), view,
                            tuple(enc.tensors.values()), light.table(), light.log_sigmas)
        if prepare is not None:
            prepared = prepare(light, lobes, view)
        elif view is not None and V * lobes[0][0].shape[2] >= TAPS_CACHE_MIN_LOOKUPS:
            # taps: the blend kept in enc.cache from the second call with these taps on
            prepared, enc.cache["taps_prepared"] = self._prepare(enc, light, lobes, view, enc.cache.pop("taps_prepared", None),
                                                                 eager=False)
        else:
            prepared = None
        return self._relight(enc, light, view, out, lobes, prepared)

    def _prepare(self, enc: Encoded, light: PrefilteredEnvironment, lobes: tuple, taps: tuple | None, hit: tuple | None,
                 eager: bool) -> tuple:
        """The light-independent part of relighting ``enc`` with ``light`` — every lobe's pyramid
        addressing (``sg_prepare``), or with ``taps`` the blend across them and its addressing
        (``sg_taps_prepare``) — from ``hit = (key, prepared, held tensors, made)`` where its key
        is this call's: the light's resolution and width ladder, the lobe tensors' and the taps'
        states. Otherwise made now, or (not ``eager``) at the second call with the same key, so
        that taps that change at every call (a moving camera) cost only the key. → ``(prepared or
        None, the entry to keep)``. None where the kernels do not take it (no compiled kernels,
        not RGB, separate lobe arrays, a shape the 16-lane kernels do not take)."""
        lib = fused(light)
        (w, mu, sg), layout = lobes
        if lib is None or light.channels != 3 or layout is None:
            return None, None
        held = tuple(enc.tensors.values())
        ladder = light.log_sigmas
        key = (light.res, ladder.dtype, ladder.numpy().tobytes(), lobes_state(enc))
        if taps is not None:
            key += (tensor_state(taps[0]), tensor_state(taps[1]))
            held += tuple(taps)
        if hit is not None and hit[0] == key and hit[3]:
            return hit[1], hit
        if not eager and (hit is None or hit[0] != key):
            return None, (key, None, held, False)  # seen once
        if taps is None:
            prep = sg_prepare(lib, ladder, light.res, w, mu, sg, layout)
        else:
            prep, flag = sg_taps_prepare(lib, ladder, light.res, w, mu, sg, taps[0], taps[1].float(), layout=layout)
            if flag:  # a bad tap (nothing kept): raise naming it
                self.checked_taps(taps, w.shape[0], w.shape[1])
                raise RuntimeError("prt_sg_taps_prepare flagged the taps but none is out of range, negative or non-finite")  # pragma: no cover
        return prep, (key, prep, held, True)

    def relighter(self, enc: Encoded, view: Any = None) -> "GaussianRelighter":
        """A prepared relighting (``base.Relighter``): ``r = codec.relighter(enc)``, then ``r(light,
        out=buf)`` per light, the same bits as ``relight(enc, light, out=buf)``. Without a view,
        the addressing of every lobe in the pyramid (face, texel and level, and their fractions:
        most of a lookup's arithmetic, and independent of the light's values) is computed at the
        first light and kept while the lobes and the light's resolution and
        width ladder stay the same (20 bytes per lobe); each light then costs only the texel reads
        (reports/benchmarks/relight.md, "prepared"). With taps, the same for the lobes blended
        across each vertex's taps (the blend and its normalisation kept too: 20 bytes per blended
        lobe and Σa per vertex), kept while the taps are also unchanged (edited in place, replaced
        or converted: another int64 ``idx`` or another ``a`` prepares again); a view of global
        directions ``[V, 3]`` keeps its taps (:func:`view_taps`) while the directions are unchanged."""
        self._require_fitted()
        return typed_relighter(GaussianRelighter(self, enc, view_tensors(view), {}))

    def _relight(self, enc: Encoded, light: PrefilteredEnvironment, view: tuple | None, out: torch.Tensor | None = None,
                 lobes: tuple | None = None, prepared: torch.Tensor | None = None) -> torch.Tensor:
        """``view``: None or checked taps; ``out``: None or a checked result buffer; ``lobes``:
        ``_lobes_and_layout(enc)`` when the caller has them; ``prepared``: ``sg_prepare``'s
        addressing of these lobes for this light (every view), or ``sg_taps_prepare``'s of these
        lobes blended by these taps (taps)."""
        (w, mu, sg), layout = lobes if lobes is not None else self._lobes_and_layout(enc)
        V, J, N = w.shape
        if view is None:
            res = lobe_sum(light, w, mu, sg, out=out, layout=layout, prepared=prepared)
            if "diffuse" in enc.tensors:
                res = _add(res, self._diffuse(enc, light)[:, None, :] * enc.tensors["has_data"].float()[..., None])
            return res
        lib = fused(light)
        # the taps' values: checked by the fused kernel as it reads them (it flags a bad one), else here
        idx, a = view if lib is not None else self.checked_taps(view, V, J)
        a = a.float()
        if lib is not None and prepared is not None:  # the blend and addressing kept: per vertex only the texel reads
            res, flag = sg_taps_prepared(lib, prepared, light.table(), light.log_sigmas, light.res, out=out)
        elif lib is not None:  # blend, look up and sum in one fused pass per vertex
            res, flag = sg_taps(lib, light.table(), light.log_sigmas, light.res, w, mu, sg, idx, a, out=out, layout=layout)
            if flag:  # a bad tap (nothing computed or written): raise naming it
                self.checked_taps(view, V, J)
                raise RuntimeError("prt_sg_taps flagged the taps but none is out of range, negative or non-finite")  # pragma: no cover
        else:
            rows = torch.arange(V)[:, None]
            tot = a.sum(1, keepdim=True)
            wb, mb, sgb = blend_lobes(w[rows, idx], mu[rows, idx], sg[rows, idx], a / tot.clamp_min(1e-12))
            res = lobe_sum(light, wb, mb, sgb) * tot
            res = res if out is None else out.copy_(res)
        if "diffuse" in enc.tensors:
            hd = enc.tensors["has_data"].float()[torch.arange(V)[:, None], idx]
            res = _add(res, self._diffuse(enc, light) * (a * hd).sum(1, keepdim=True))
        return res

    def relight_surface(self, enc: Encoded, light: PrefilteredEnvironment, faces: torch.Tensor, face_index: torch.Tensor,
                        bary: torch.Tensor, view_dirs: torch.Tensor) -> torch.Tensor:
        """Radiance at surface points inside triangles (Green §2.3): at each of the triangle's
        three vertices the lobes of the three nearest views are blended, then the three
        vertices' lobes are blended with the barycentric weights. ``faces [F, 3]``,
        ``face_index [M]``, ``bary [M, 3]``, global ``view_dirs [M, 3]`` → ``[M, C]`` float32 (a
        numpy array for an encoding of numpy data)."""
        self._require_fitted()
        light = self._check_light(light)
        w, mu, sg = self.lobes_of(enc)
        N = w.shape[2]
        vid = torch.as_tensor(faces).long()[face_index.long()]  # [M, 3]
        idx, a = view_taps(self.views_, view_dirs / view_dirs.norm(dim=-1, keepdim=True))
        M, k = idx.shape
        vv = vid[:, :, None].expand(M, 3, k)
        jj = idx[:, None, :].expand(M, 3, k)
        aa = a[:, None, :].expand(M, 3, k).reshape(M * 3, k)
        wv, mv, sv = blend_lobes(w[vv, jj].reshape(M * 3, k, N), mu[vv, jj].reshape(M * 3, k, N, 3),
                                 sg[vv, jj].reshape(M * 3, k, N), aa)
        wb, mb, sgb = blend_lobes(wv.reshape(M, 3, N), mv.reshape(M, 3, N, 3), sv.reshape(M, 3, N), bary.float())
        out = lobe_sum(light, wb, mb, sgb)
        if "diffuse" in enc.tensors:
            d = self._diffuse(enc, light)[vid]  # [M, 3, C]
            hd = enc.tensors["has_data"].float()[vv, jj]  # [M, 3, k]
            out = out + (bary.float()[..., None] * d * (hd * a[:, None, :]).sum(-1, keepdim=True)).sum(1)
        return as_array_type(out, enc.array_type)

    # ------------------------------------------------------------------ storage / state
    def relight_bytes(self, enc: Encoded, view: Any = None) -> int:
        """Without a view every stored lobe (and the diffuse part) is read; with taps ``(idx [V, k],
        a [V, k])`` only the k tapped views' lobes of each vertex (5 floats each), its diffuse part
        and the taps — the other views are never touched, so the whole encoding would be a bound
        J/k times too loose. A view of directions ``[V, 3]`` reads three views' lobes."""
        if view is None:
            return super().relight_bytes(enc)
        V, J, N = self.lobes_of(enc)[0].shape
        k = min(3, J) if isinstance(view, torch.Tensor) else int(torch.as_tensor(view[0]).shape[-1])
        diffuse = enc.tensors["diffuse"][0].numel() * 4 + k if "diffuse" in enc.tensors else 0  # and k has_data flags
        return V * (k * N * 5 * 4 + diffuse) + view_nbytes(view)

    def storage(self, enc: Encoded) -> dict[str, Any]:
        st = super().storage(enc)
        V, J, N = self.lobes_of(enc)[0].shape
        per_fn = N * 5
        floats = V * J * per_fn + (enc.tensors["diffuse"].numel() if "diffuse" in enc.tensors else 0)
        st.update({"sloan_cost_floats": floats, "floats_per_function": per_fn, "floats_per_lobe": 5,
                   "relight_macs_per_point_per_channel": N * 3 * 2})
        return st

    def _state(self):
        return ({"views": self.views_, "directions": self.directions_, "solid_angles": self.solid_angles_},
                {"J": self.J_, "P": self.P_, "layout": self.layout_})

    def _set_state(self, tensors, meta):
        self.views_, self.directions_, self.solid_angles_ = tensors["views"], tensors["directions"], tensors["solid_angles"]
        self.J_, self.P_, self.layout_ = int(meta["J"]), int(meta["P"]), meta["layout"]
        self.n_features_in_ = self.J_ * self.P_
        self.faces_ = None


def _add(res: torch.Tensor, part: torch.Tensor) -> torch.Tensor:
    """``res + part``: in place (``res`` may be the caller's ``out``) unless autograd tracks either,
    then out of place in the promoted dtype (float64 for gradcheck)."""
    if res.requires_grad or part.requires_grad:
        return res + part
    return res.add_(part)
