"""How a transfer of each kind turns a light (and a view) into per-vertex radiance.

The harness evaluates every codec through the same ``Evaluator``: it knows the codec signal
``X [V, D]`` of a transfer, the matrix shape (n_out, n_in) of each row, and how to turn a
camera position into per-vertex view weights over the n_out outputs:

* diffuse, grey ``[V, n²]``: radiance_c = albedo_c · (t_p · l_c) — no view, vector signal;
* diffuse, RGB ``[V, 3, n²]``: rows are 3×n² matrices, radiance_c = (T_p l_c)_c (the
  diagonal of the [3, C] product);
* glossy ``[V, n_out, n_in]``: e_p = M_p l (exit radiance SH, Sloan 2003 §3.1), radiance =
  y(v_p)·e_p with v_p the view direction in the vertex's local frame (rows of Mesh.frames());
* mrt ``[V, M², n²]``: radiance = Σ of the four tent basis functions nonzero at v_p times
  (A_p l) (Lehtinen & Kautz 2003, eq. 9 and §5);
* transport ``[V, J, 6, r, r]`` (Green 2005 tables, a directory): rows are J×P matrices
  (P = 6r² texels); the light is the SH light evaluated at the texel centres times the texel
  solid angles, ``[P, C]`` (eq. 1.1 as a sum), so L_o = Σ_taps w_t (T_{p,j_t} · L Δω) over the
  three stored views nearest the global view direction (barycentric taps, zero below the
  horizon) — the uncompressed relighting (:meth:`Evaluator.uncompressed`); linear codecs take
  that ``[P, C]`` light, the ``gaussian`` codec (light kind 'prefiltered') a Gaussian-prefiltered
  environment of the same light (``codec_light``) and interpolates its lobes at the same taps
  (Green §2.3). The *reference* every codec is compared against is not that cross-fade (itself
  22.8 dB from the truth at 42 views: reports/benchmarks/gaussian_taps.md) but the exact radiance
  at each vertex's own view direction (:meth:`Evaluator.exact_transport`, issue 42 §2): eq. 1.1–1.2
  summed over the table's texels with their stored visibility and the BRDF at that view;
* wavelet ``[V, K]`` sparse Haar transfer on a 6×R×R cube (Ng et al. 2003): no view; the light
  is not band-limited — each config light rasterised on the cube at R and Haar-transformed
  (:meth:`Evaluator.load_light`, ``[C, 6R²]``), relit exactly (all its terms) by
  :class:`prt_torch.relight.WaveletRelighter`, the sparse kernel — the reference. SH codecs
  do not take it (:func:`check_codecs_for_kind`).

View weights are dense ``[V, n_out]`` (glossy) or sparse taps ``(idx [V, k], w [V, k])`` (MRT),
zero below each vertex's horizon, from :mod:`prt_torch.relight` (the project's one uncompressed
reference): the reference relights through ``relight`` and every codec gets the same weights,
so a PSNR measures the codec alone. Transport taps are a :class:`TransportView` (the same two
tensors, and the exact directions the reference uses).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from .. import relight, sh
from .._checks import tensor_state
from ..transfer import Transfer

__all__ = ["Evaluator", "camera_positions", "KINDS", "load_directory_transfer", "check_codecs_for_kind",
           "TRANSPORT_LIGHT_BANDS", "TransportView", "EXACT_BLOCK"]

#: transfer kinds the harness can relight ('subsurface' precomputes a diffuse transfer: relit as one)
KINDS = ("diffuse", "glossy", "mrt", "transport", "wavelet", "subsurface")
#: SH bands of the lights of a transport benchmark (evaluated on the cube texels / prefiltered)
TRANSPORT_LIGHT_BANDS = 10
#: the exact transport reference's finest sub-texels per texel side (the table's averages stop at 8; at views
#: within ~5 degrees of the horizon a half-vector lobe is narrower still)
EXACT_MAX_SUB = 16
#: (vertex, sub-texel) evaluations per block of the exact transport reference (float64 temporaries of ~40 MB)
EXACT_BLOCK = 1 << 20


class TransportView(tuple):
    """View taps over a transport table's stored views, ``(idx int64 [V, k], w float64 [V, k])`` — a
    2-tuple as every codec takes it —, that also carry ``directions [V, 3]`` float64: the unit world
    direction from each vertex to the camera, at which :meth:`Evaluator.reference` evaluates the exact
    radiance (:meth:`Evaluator.view_weights` makes them)."""

    def __new__(cls, idx: torch.Tensor, w: torch.Tensor, directions: torch.Tensor):
        self = super().__new__(cls, (idx, w))
        self.directions = directions
        return self

    def __getnewargs__(self):  # pickles (Ray tasks) with its directions
        return (self[0], self[1], self.directions)


def load_directory_transfer(path) -> Transfer:
    """A streamed transport directory (``transfer.precompute_transport``) as a :class:`Transfer`
    of kind 'transport' with ``data [V, J, 6, r, r]`` float32 and ``meta['views'] [J, 3]``,
    ``meta['res']``. Refuses an incomplete table."""
    from ..transfer import TransportTable

    table = TransportTable(path)
    if not table.meta.get("complete"):
        raise ValueError(f"transport table {str(path)!r} is incomplete (missing chunks); accepted: a complete table "
                         "(re-run prt precompute --kind transport with --resume)")
    V, J, r = table.num_vertices, int(table.meta["views"]), int(table.meta["res"])
    data = torch.empty(V, J, 6, r, r, dtype=torch.float32)
    for a, b, T in table:  # chunk files
        data[a:b] = T.to(torch.float32)
    meta = {k: v for k, v in table.meta.items() if k not in ("fingerprint",)}
    meta.update(views=table.views.tolist(), matrix_shape=[J, 6 * r * r], source=str(path))
    meta.setdefault("offset", float((table.meta.get("fingerprint") or {}).get("offset", 1e-4)))  # the rays' origins
    vis, have = table.visibility()  # the texels' visibility (tables since issue 42 §2; else traced when needed)
    aux = {}
    if bool(have.any()):
        from ..transfer.transport import pack_visibility

        aux = {"visibility": pack_visibility(vis), "visibility_stored": have}
    return Transfer("transport", data, table.mesh(), meta, aux=aux)


def check_codecs_for_kind(kind: str, names: list[str]) -> None:
    """Refuse, before any work, codecs that cannot relight transfer ``kind`` (the Gaussian
    codec, light kind 'prefiltered', fits transport tables only)."""
    from .. import codecs

    if kind == "wavelet" and names:
        raise ValueError(f"codec {names[0]!r} compresses SH transfer rows; the config's transfer type is 'wavelet' (sparse "
                         "Haar coefficients, relit sparse as they are); accepted: codecs: [] for a wavelet transfer "
                         "(benchmarks/bench_wavelet.py compares it with SH)")
    for name in names:
        lk = getattr(codecs.get(name), "light_kind", "sh")
        if lk == "prefiltered" and kind != "transport":
            raise ValueError(f"codec {name!r} fits transport tables (transfer type 'transport'); the config's transfer "
                             f"type is {kind!r}; accepted: transfer type 'transport' for codec {name!r}")


def camera_positions(center: torch.Tensor, radius: float, count: int, elevation_deg: float, azimuth0_deg: float,
                     distance_factor: float = 3.0) -> torch.Tensor:
    """``count`` camera positions ``[count, 3]`` on a ring around the mesh (world +z up)."""
    el = math.radians(elevation_deg)
    az = torch.tensor([math.radians(azimuth0_deg) + 2 * math.pi * i / count for i in range(count)], dtype=torch.float64)
    d = torch.stack([math.cos(el) * torch.cos(az), math.cos(el) * torch.sin(az), torch.full_like(az, math.sin(el))], -1)
    return center[None].double() + distance_factor * radius * d


@dataclass
class Evaluator:
    transfer: Transfer
    #: a wavelet transfer's relighter: the dense terms' arithmetic (``WaveletRelighter(arith=)``; config ``wavelet.arith``)
    wavelet_arith: str = "auto"

    def __post_init__(self):
        t = self.transfer
        self.kind = t.kind
        self.X = t.signal()  # [V, D] float32
        self.V = self.X.shape[0]
        data = t.data
        if t.kind == "diffuse":
            if data.ndim == 2:
                self.matrix_shape = None
                self.n_in = data.shape[1]
                self.albedo = t.mesh.albedo.to(torch.float32)  # [V, 3]
                if t.meta.get("albedo_folded"):
                    self.albedo = torch.ones_like(self.albedo)
            else:
                self.matrix_shape = (data.shape[1], data.shape[2])
                self.n_in = data.shape[2]
                self.albedo = None
        elif t.kind == "transport":
            J = data.shape[1]
            self.res = int(data.shape[-1])
            self.matrix_shape = (J, 6 * self.res * self.res)
            self.n_in = self.matrix_shape[1]
            self.views = torch.as_tensor(t.meta["views"], dtype=torch.float64)
            from ..lighting.prefilter import cube_map_directions

            d, sa = cube_map_directions(self.res)
            self.texels, self.solid_angles = d.reshape(-1, 3), sa.reshape(-1)
            self._prefiltered: dict[int, Any] = {}
            self._exact: dict[str, Any] | None = None
        elif t.kind == "wavelet":
            from ..relight import WaveletRelighter

            self.relighter = WaveletRelighter(t, arith=self.wavelet_arith)
            self.res = self.relighter.res
            self.matrix_shape = None
            self.n_in = self.relighter.P
            self.bytes_per_vertex = int(t.meta.get("bytes_per_vertex", 0)) or (t.data.element_size() * t.data.shape[1]
                                                                               + t.aux["index"].element_size() * t.data.shape[1] + 4)
        elif t.kind in KINDS:
            self.matrix_shape = tuple(int(v) for v in t.meta.get("matrix_shape", data.shape[1:3]))
            self.n_in = self.matrix_shape[1]
        else:
            raise ValueError(f"transfer kind {t.kind!r} is not supported by the harness; accepted: {', '.join(KINDS)}")
        self.bands_in = (TRANSPORT_LIGHT_BANDS if self.kind == "transport" else None if self.kind == "wavelet"
                         else sh.band_of_coeffs(self.n_in, "transfer input coefficients"))
        self.frames = t.mesh.frames().to(torch.float64)  # [V, 3, 3] rows (t, b, n)
        self.points = torch.as_tensor(t.mesh.vertices).to(torch.float64)  # [V, 3]

    def __getstate__(self):  # a Ray task gets the evaluator without the exact reference's state (visibility, lights)
        return {**self.__dict__, "_exact": None} if "_exact" in self.__dict__ else dict(self.__dict__)

    @property
    def needs_view(self) -> bool:
        return self.kind in ("glossy", "mrt", "transport")

    @property
    def raw_bytes(self) -> int:
        if self.kind == "wavelet":
            return self.V * self.bytes_per_vertex
        return self.X.numel() * 4

    def load_light(self, spec: Any) -> torch.Tensor:
        """A config light as this kind relights it: SH ``[C, n²]`` at :attr:`bands_in`
        (:func:`prt_torch.lighting.load_light`), or for a wavelet transfer the Haar coefficients
        ``[C, 6R²]`` float32 of the light on the cube at R (not band-limited; a light below R
        warned as upsampled)."""
        if self.kind != "wavelet":
            from ..lighting import load_light

            return load_light(spec, bands=self.bands_in)
        import warnings

        from ..lighting.haar import cube_light, haar2d

        cube, rec = cube_light(spec, self.res)
        if rec.get("upsampled"):
            warnings.warn(rec["warning"])
        return haar2d(cube).reshape(cube.shape[0], -1).to(torch.float32)

    def light_matrix(self, light: torch.Tensor) -> torch.Tensor:
        """SH light ``[C, n²]`` (any bands) -> ``[n_in, C]`` float32, truncated or zero-padded.
        Transport: the light's radiance at the texel centres (2×2 sub-texel average) times the
        texel solid angles, ``[P, C]`` (Green eq. 1.1 as a sum over texels)."""
        if self.kind == "wavelet":
            return light.T.to(torch.float32)  # [6R², C] Haar coefficients
        if self.kind == "transport":
            from ..lighting.prefilter import cube_map_directions

            d, _ = cube_map_directions(2 * self.res)
            bands = sh.band_of_coeffs(light.shape[1], "light coefficients")
            vals = sh.eval_sh(d, bands, check=False) @ light.to(torch.float64).T  # [6, 2r, 2r, C]
            vals = vals.reshape(6, self.res, 2, self.res, 2, -1).mean((2, 4)).reshape(-1, light.shape[0])
            return (vals * self.solid_angles[:, None]).to(torch.float32)
        L = torch.zeros(self.n_in, light.shape[0], dtype=torch.float32)
        k = min(self.n_in, light.shape[1])
        L[:k] = light[:, :k].T.to(torch.float32)
        return L

    def codec_light(self, codec, light: torch.Tensor) -> Any:
        """The light as ``codec`` takes it: :meth:`light_matrix` for SH-kind codecs; for light
        kind 'prefiltered' (the ``gaussian`` codec) a Gaussian-prefiltered environment of the
        same SH light (built once per light)."""
        if getattr(codec, "light_kind", "sh") != "prefiltered":
            return self.light_matrix(light)
        key = id(light)
        if key not in self._prefiltered:
            from ..lighting import prefilter_environment

            self._prefiltered[key] = (light, prefilter_environment(light.to(torch.float64), res=max(16, 2 * self.res)))
        return self._prefiltered[key][1]

    def fit_kwargs(self, codec) -> dict:
        """Geometry a codec with light kind 'prefiltered' needs (views, mesh faces, the kind)."""
        if getattr(codec, "light_kind", "sh") != "prefiltered":
            return {}
        return {"views": self.views, "faces": torch.as_tensor(self.transfer.mesh.faces), "kind": self.kind}

    def local_views(self, camera: torch.Tensor) -> torch.Tensor:
        """Unit view directions toward ``camera [3]`` in each vertex's local frame, ``[V, 3]``."""
        v = camera[None].double() - self.points
        v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return torch.einsum("vij,vj->vi", self.frames, v)

    def config_views(self, cfg: dict) -> tuple[list[torch.Tensor], torch.Tensor, list[Any]]:
        """A run config's lights and views for this mesh: ``(lights, cams, views)`` with ``lights`` each
        ``[C, n²]`` (:meth:`load_light` of ``cfg['lights']``), ``cams [count, 3]`` on the ring of
        :func:`camera_positions` (``cfg['views']``: count, elevation, azimuth0) around the vertices'
        bounding sphere, and ``views`` their :meth:`view_weights` (``[None]`` for a kind that needs no view)."""
        lights = [self.load_light(spec) for spec in cfg["lights"]]
        center = self.points.mean(0)
        radius = float((self.points - center).norm(dim=-1).max())
        v = cfg["views"]
        cams = camera_positions(center, radius, v["count"], v["elevation"], v["azimuth0"])
        views = [self.view_weights(c) for c in cams] if self.needs_view else [None]
        return lights, cams, views

    def view_weights(self, camera: torch.Tensor | None) -> Any:
        """Per-vertex weights over the n_out outputs for ``camera`` (None for view-independent
        kinds), zero below the horizon: ``relight.glossy_view_weights`` / ``relight.mrt_view_taps``."""
        if not self.needs_view:
            return None
        if self.kind == "transport":
            from ..codecs.gaussian import view_taps
            from ..transfer.transport import HORIZON_EPS

            d = camera[None].double() - self.points
            d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            idx, w = view_taps(self.views, d)
            above = (d * self.frames[:, 2]).sum(-1) > HORIZON_EPS  # the vertex's horizon, as the tables have it
            return TransportView(idx, w * above[:, None].to(w.dtype), d)
        v = self.local_views(camera)
        if self.kind == "glossy":
            return relight.glossy_view_weights(v, self.transfer.meta.get("out_index"), self.matrix_shape[0])
        return relight.mrt_view_taps(v, math.isqrt(self.matrix_shape[0]))

    def finish(self, out: torch.Tensor) -> torch.Tensor:
        """Codec output -> per-vertex RGB radiance ``[V, C]`` (albedo of unfolded diffuse
        transfer; the diagonal of an RGB diffuse [V, 3, C] product)."""
        if self.kind == "diffuse":
            if self.matrix_shape is None:
                return out * self.albedo[:, : out.shape[1]]
            return torch.diagonal(out, dim1=1, dim2=2)  # [V, 3, C] -> [V, C]
        return out  # wavelet: the relighter applies the albedo

    def reference(self, light: torch.Tensor, view: Any) -> torch.Tensor:
        """The radiance every codec is compared against, ``[V, C]`` float32: the uncompressed
        relighting (:meth:`uncompressed`), except for transport tables with a :class:`TransportView`
        (what :meth:`view_weights` gives), where it is the exact radiance at each vertex's own view
        direction (:meth:`exact_transport`), not the table's three tapped views cross-faded; for wavelet
        transfer every Haar term through the float32 dense loop (``WaveletRelighter.float32``: not the VNNI
        loop's quantised light, whatever ``wavelet.arith``)."""
        if self.kind == "transport" and isinstance(view, TransportView):
            return self.exact_transport(light, view.directions)
        if self.kind == "wavelet":  # every term, the float32 dense loop whatever wavelet.arith (no light quantisation)
            return self.relighter.float32(torch.arange(self.n_in), light)
        return self.uncompressed(light, view)

    @property
    def reference_info(self) -> dict[str, Any]:
        """What :meth:`reference` is for this kind (a results entry): for transport tables, the exact
        view's evaluation and where its visibility came from (stored in the table, or traced now for a
        table written before it was stored)."""
        if self.kind != "transport":
            return {"reference": "uncompressed relighting (prt_torch.relight)"}
        st = self._exact_state()
        return {"reference": "exact radiance at each vertex's own view (table texels x stored visibility x BRDF, "
                             "sub-texel sums; Evaluator.exact_transport)",
                "visibility": st["note"], "brdf": st["brdf"].meta() if st["brdf"].batch_shape == () else "per-vertex"}

    def _exact_state(self) -> dict[str, Any]:
        """The exact transport reference's light-independent state, made once: the BRDF of the table
        (its manifest's), the texel visibility ``[V, P]`` bool (stored, or traced for the vertices whose
        chunk files predate it: :func:`prt_torch.transfer.transport.texel_visibility`), the sub-texel
        plan and where the visibility came from."""
        if self._exact is not None:
            return self._exact
        from ..brdf import make_brdf
        from ..transfer.transport import supersample_plan, texel_visibility, unpack_visibility

        t, P = self.transfer, self.n_in
        spec = dict(t.meta.get("brdf") or {"model": "ashikhmin_shirley", "nu": 40.0, "nv": 40.0, "rs": 0.05, "rd": 0.0})
        model = spec.pop("model")
        brdf = make_brdf(model, **{k: torch.tensor(v, dtype=torch.float64) if isinstance(v, list) else v for k, v in spec.items()})
        have = t.aux.get("visibility_stored")
        vis = (unpack_visibility(t.aux["visibility"], P) if have is not None
               else torch.zeros(self.V, P, dtype=torch.bool))
        have = torch.zeros(self.V, dtype=torch.bool) if have is None else have.bool()
        missing = torch.nonzero(~have).flatten()
        if missing.numel():
            sup = t.meta.get("supersample") or {}
            vis[missing] = texel_visibility(t.mesh, self.res, plan=sup if int(sup.get("sub", 1)) > 1 else None,
                                            shadows=bool(t.meta.get("shadows", True)), offset=float(t.meta.get("offset", 1e-4)),
                                            vertices=missing)
        note = ("stored in the table" if not missing.numel() else
                f"traced now for {missing.numel()} of {self.V} vertices (a table written before the visibility was stored)")
        sharp = brdf if brdf.batch_shape == () else None
        plan = supersample_plan(sharp, self.res, "auto") if sharp is not None else None
        self._exact = {"brdf": brdf, "vis": vis, "plan": plan, "note": note, "subs": {}}
        return self._exact

    def exact_transport(self, light: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
        """The exit radiance at each vertex's own view direction, no view interpolation (Green 2005
        eq. 1.1 with eq. 1.2): ``L_o(x, ω_o) = Σ_p V_p Σ_s a_s f_r(ω_s, ω_o) max(n·ω_s, 0) L(ω_s) Δω_p``
        over the table's texels p (visibility V_p as the table stores it) and S×S sub-texels s of each
        (directions ω_s, solid-angle shares a_s), with the table's BRDF evaluated at the exact local view
        ω_o — S from the width of the BRDF's lobe at that view (``transfer.transport.view_sub`` of the
        ``res: auto`` plan: 2 where the texels resolve it, up to :data:`EXACT_MAX_SUB` at grazing views;
        2 for a model without a lobe) — and the SH light ``[C, n²]`` evaluated at every sub-texel. ``directions [V, 3]``
        float64 world unit vectors toward the camera; zero below the horizon (cos θ_o ≤ ``transport.HORIZON_EPS``,
        as the tables). Returns ``[V, C]`` float32.
        Batched over blocks of vertices of one S (the compiled BRDF pass ``transport_kernels.points`` for
        the models it knows, else ``BRDF.eval``)."""
        from ..transfer import transport_kernels
        from ..transfer.transport import AUTO_SUPERSAMPLE, HORIZON_EPS, sub_texel_sets, view_sub

        if not isinstance(directions, torch.Tensor) or tuple(directions.shape) != (self.V, 3):
            raise ValueError(f"directions has shape {tuple(getattr(directions, 'shape', ()))}; accepted: [V, 3] = "
                             f"[{self.V}, 3] unit directions toward the camera (Evaluator.view_weights(...).directions)")
        st = self._exact_state()
        brdf, vis, plan = st["brdf"], st["vis"], st["plan"]
        wo = torch.einsum("vab,vb->va", self.frames, directions.to(torch.float64))  # [V, 3] local views
        up = wo[:, 2] > HORIZON_EPS  # a view in the tangent plane is below it, as in the tables (Ward diverges there)
        S = (view_sub({**plan, "sub": EXACT_MAX_SUB, "adaptive": True}, wo[:, 2]) if plan is not None
             else torch.full((self.V,), 2, dtype=torch.long))
        if brdf.batch_shape != ():
            S = torch.full_like(S, AUTO_SUPERSAMPLE)  # per-vertex materials: the table's finest everywhere
        L = light.to(torch.float64)
        bands = sh.band_of_coeffs(L.shape[1], "light coefficients")
        out = torch.zeros(self.V, L.shape[0], dtype=torch.float64)
        key = tensor_state(light)  # the light at the sub-texels, kept for the next view under the same light
        if st.get("light_key") != key:
            st["light_key"], st["light"], st["light_at"] = key, light, {}
        P = self.n_in
        for s in S[up].unique().tolist():
            if s not in st["subs"]:
                st["subs"][s] = sub_texel_sets(self.res, {"sub": s, "adaptive": False})[s]
            sd, sw = st["subs"][s]  # [P, s², 3], [P, s²]
            Q = P * s * s
            dirs = sd.reshape(Q, 3)
            if s not in st["light_at"]:
                st["light_at"][s] = (sh.eval_sh(dirs, bands, check=False) @ L.T) * (sw * self.solid_angles[:, None]).reshape(Q, 1)
            Lw = st["light_at"][s]  # [Q, C]: L(ω_s) a_s Δω_p
            rows = torch.nonzero(up & (S == s)).flatten()
            step = max(1, EXACT_BLOCK // Q)
            for a in range(0, rows.numel(), step):  # blocks of vertices, not a loop per vertex
                i = rows[a:a + step]
                wi = torch.einsum("kab,qb->kqa", self.frames[i], dirs)  # [b, Q, 3] local sub-texel directions
                W = wi[..., 2].clamp_min(0) * vis[i].repeat_interleave(s * s, dim=1)  # cos × the parent texel's V_p
                T = torch.empty(i.numel(), Q, dtype=torch.float64)
                model = transport_kernels.native_model(brdf, i.numel(), i if brdf.batch_shape != () else None)
                if model is None or not transport_kernels.points(T, wi, wo[i][:, None], W, None, model, torch.get_num_threads(),
                                                                    horizon=HORIZON_EPS):
                    b = brdf if brdf.batch_shape == () else brdf.select(i).view(-1, 1)
                    T = b.eval(wi, wo[i][:, None, :]) * W
                out[i] = T @ Lw
        return out.to(torch.float32)

    def uncompressed(self, light: torch.Tensor, view: Any) -> torch.Tensor:
        """Uncompressed relighting through :mod:`prt_torch.relight` (the uncompressed peer a codec's
        speed is compared with; for transport tables the stored views' tables relit at the taps and
        cross-faded). ``light [C, n²]`` (any bands; truncated or zero-padded), ``view`` from
        :meth:`view_weights`. Returns ``[V, C]`` float32."""
        if self.kind == "wavelet":  # every term of the light: the exact pixel-basis result (Ng 2003 eq. 2)
            return self.relighter(torch.arange(self.n_in), light)
        L = self.light_matrix(light).T  # [C, n_in]
        if self.kind == "diffuse":
            data = self.X if self.matrix_shape is None else self.X.view(self.V, *self.matrix_shape)
            out = relight.diffuse(data, L)
            return out * self.albedo[:, : out.shape[1]] if self.matrix_shape is None else out
        Mx = self.X.view(self.V, *self.matrix_shape)
        if isinstance(view, tuple):
            return relight.apply_taps(Mx, L, *view)
        return relight.apply_dense(Mx, L, view)
