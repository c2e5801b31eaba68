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
  (A_p l) (Lehtinen & Kautz 2003, eq. 9 and §5).

View weights are dense ``[V, n_out]`` (glossy) or sparse taps ``(idx [V, k], w [V, k])`` (MRT),
zero below each vertex's horizon, from :mod:`prt_torch.relight` (the project's one uncompressed
reference): the reference relights through ``relight`` and every codec gets the same weights,
so a PSNR measures the codec alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from .. import relight, sh
from ..transfer import Transfer

__all__ = ["Evaluator", "camera_positions", "KINDS"]

#: transfer kinds the harness can relight
KINDS = ("diffuse", "glossy", "mrt")


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
        elif t.kind in KINDS:
            self.matrix_shape = tuple(int(v) for v in t.meta.get("matrix_shape", data.shape[1:3]))
            self.n_in = self.matrix_shape[1]
        else:
            raise ValueError(f"transfer kind {t.kind!r} is not supported by the harness; accepted: {', '.join(KINDS)}")
        self.bands_in = sh.band_of_coeffs(self.n_in, "transfer input coefficients")
        self.frames = t.mesh.frames().to(torch.float64)  # [V, 3, 3] rows (t, b, n)
        self.points = torch.as_tensor(t.mesh.vertices).to(torch.float64)  # [V, 3]

    @property
    def needs_view(self) -> bool:
        return self.kind in ("glossy", "mrt")

    @property
    def raw_bytes(self) -> int:
        return self.X.numel() * 4

    def light_matrix(self, light: torch.Tensor) -> torch.Tensor:
        """SH light ``[C, n²]`` (any bands) -> ``[n_in, C]`` float32, truncated or zero-padded."""
        L = torch.zeros(self.n_in, light.shape[0], dtype=torch.float32)
        k = min(self.n_in, light.shape[1])
        L[:k] = light[:, :k].T.to(torch.float32)
        return L

    def local_views(self, camera: torch.Tensor) -> torch.Tensor:
        """Unit view directions toward ``camera [3]`` in each vertex's local frame, ``[V, 3]``."""
        v = camera[None].double() - self.points
        v = v / v.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        return torch.einsum("vij,vj->vi", self.frames, v)

    def view_weights(self, camera: torch.Tensor | None) -> Any:
        """Per-vertex weights over the n_out outputs for ``camera`` (None for view-independent
        kinds), zero below the horizon: ``relight.glossy_view_weights`` / ``relight.mrt_view_taps``."""
        if not self.needs_view:
            return None
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
        return out

    def reference(self, light: torch.Tensor, view: Any) -> torch.Tensor:
        """Uncompressed relighting through :mod:`prt_torch.relight`: the peer every codec is
        compared against. ``light [C, n²]`` (any bands; truncated or zero-padded), ``view``
        from :meth:`view_weights`. Returns ``[V, C]`` float32."""
        L = self.light_matrix(light).T  # [C, n_in]
        if self.kind == "diffuse":
            data = self.X if self.matrix_shape is None else self.X.view(self.V, *self.matrix_shape)
            out = relight.diffuse(data, L)
            return out * self.albedo[:, : out.shape[1]] if self.matrix_shape is None else out
        Mx = self.X.view(self.V, *self.matrix_shape)
        if isinstance(view, tuple):
            return relight.apply_taps(Mx, L, *view)
        return relight.apply_dense(Mx, L, view)
