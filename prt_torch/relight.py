"""Uncompressed reference relighting: light vector (and view) in, exit radiance per vertex out.

View-dependent paths return 0 where the local view is below the tangent plane (v_z ≤ 0): exit
radiance is only defined over the hemisphere (a hemispherical least-squares fit extrapolates
wildly below it). All paths are batched over vertices (GEMMs and gathers, no per-vertex Python loop) and run in
float32 by default (run-time precision; pass float64 tensors for references). Lighting is
``L [C, n²]`` (global SH radiance, coefficients last, C = 1 or 3) or ``[n²]``.

* :func:`diffuse` — Sloan et al. 2002: one dot product per vertex and channel.
* :func:`glossy` — exit-radiance transfer (Sloan 2003 §3.1): e_p = M_p l, then
  L_out = Σ_r y_{o(r)}(v_p) e_{p,r} at the local view v_p.
* :func:`mrt` — matrix radiance transfer (Lehtinen & Kautz 2003 eq. 9 / eq. 13 without PCA):
  only the four tents nonzero at v_p are needed: four rows of A_p, four dot products.
* :func:`kautz` — Kautz, Sloan & Snyder 2002, the baseline of MRT's Table 1 (a): transferred
  radiance T_p l (global), rotated into the local frame with R_p, dotted with the view-dependent
  BRDF coefficients b(v_p) = Bᵀ y(v_p) ("rotate, multiply, dot").
* :func:`local_view` — the per-vertex local view direction F_p (eye - x_p)/|eye - x_p| or F_p d.

The view-dependent paths are two steps, so that a caller relighting many lights from one view
(the harness, a codec) computes the view part once: :func:`glossy_view_weights` /
:func:`mrt_view_taps` turn local views into per-vertex output weights (zero below the horizon),
:func:`apply_dense` / :func:`apply_taps` apply them. ``glossy`` and ``mrt`` are the two steps
in one call. These are *the* uncompressed reference of the project: the harness, the
benchmarks and ``prt render`` all relight through them.
"""
from __future__ import annotations

import math

import torch

from ._checks import check_shape, describe
from .sh import band_of_coeffs, eval_sh, rotation_blocks
from .transfer.tents import tent_taps

__all__ = ["diffuse", "diffuse_transfer", "glossy", "mrt", "kautz", "kautz_setup", "local_view", "glossy_view_weights", "mrt_view_taps",
           "apply_dense", "apply_taps"]


def _light(L: torch.Tensor, n_in: int, dtype: torch.dtype) -> torch.Tensor:
    if not isinstance(L, torch.Tensor):
        raise TypeError(f"light must be a torch.Tensor [C, n²] or [n²], got {describe(L)}")
    L = L[None] if L.ndim == 1 else L
    if L.ndim != 2 or L.shape[1] != n_in:
        raise ValueError(f"light has shape {tuple(L.shape)}; accepted: [C, {n_in}] or [{n_in}] (SH coefficients last)")
    return L.to(dtype)


def local_view(frames: torch.Tensor, positions: torch.Tensor | None = None, eye: torch.Tensor | None = None,
               direction: torch.Tensor | None = None) -> torch.Tensor:
    """Per-vertex local view directions ``[V, 3]`` (towards the viewer).

    Either ``eye [3]`` with ``positions [V, 3]`` (perspective: v = (eye - x_p)/|eye - x_p|) or a
    global ``direction [3]`` / ``[V, 3]`` towards the viewer; rotated to local by ``frames``
    ``[V, 3, 3]`` (rows t, b, n). Dtype of ``frames``.
    """
    if eye is not None:
        if positions is None:
            raise ValueError("local_view with eye= needs positions [V, 3]")
        d = eye.to(frames.dtype)[None] - positions.to(frames.dtype)
    elif direction is not None:
        d = direction.to(frames.dtype).expand(frames.shape[0], 3)
    else:
        raise ValueError("local_view needs eye= (with positions=) or direction=")
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-30)
    return torch.einsum("vij,vj->vi", frames, d)


def diffuse(T: torch.Tensor, L: torch.Tensor, albedo: torch.Tensor | None = None) -> torch.Tensor:
    """Diffuse PRT (Sloan 2002): ``T [V, n²]`` (shared across channels) or ``[V, C, n²]`` with
    ``L [C, n²]`` → ``[V, C]`` (dtype of T); ``albedo [V, C']`` multiplies the result of
    ``[V, n²]`` transfer stored without it (``meta['albedo_folded']`` false; C' = 3 broadcasts
    a grey light to colour)."""
    check_shape("T", T, last=(T.shape[-1],))
    Lc = _light(L, T.shape[-1], T.dtype)
    if T.ndim == 2:
        out = T @ Lc.T
        return out if albedo is None else out * albedo.to(T.dtype)
    if T.ndim == 3:
        Lc = Lc.expand(T.shape[1], -1) if Lc.shape[0] == 1 else Lc
        return torch.einsum("vcn,cn->vc", T, Lc)
    raise ValueError(f"T has shape {tuple(T.shape)}; accepted: [V, n²] or [V, C, n²]")


def diffuse_transfer(transfer, L: torch.Tensor) -> torch.Tensor:
    """Exit radiance ``[V, C]`` float64 of a diffuse :class:`~prt_torch.transfer.Transfer` under
    ``L [C, n²]``: :func:`diffuse` with the mesh albedo applied when it is not folded in."""
    if transfer.kind != "diffuse":
        raise ValueError(f"transfer holds {transfer.kind!r} data; accepted: diffuse")
    data = transfer.data.to(torch.float64)
    folded = transfer.meta.get("albedo_folded", data.ndim == 3)
    return diffuse(data, L.to(torch.float64), None if folded else transfer.mesh.albedo)


def glossy_view_weights(view_local: torch.Tensor, out_index: torch.Tensor | list | None, n_out: int,
                        dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Per-vertex weights over the rows of exit transfer (Sloan 2003 §3.1): y_{o(r)}(v_p),
    zero where the local view is below the horizon. ``view_local [V, 3]`` → ``[V, n_out]``."""
    idx = torch.arange(n_out) if out_index is None else torch.as_tensor(out_index, dtype=torch.int64)
    if idx.numel() != n_out:
        raise ValueError(f"out_index has {idx.numel()} entries but the matrices have {n_out} rows; accepted: one SH index per row")
    y = eval_sh(view_local.to(torch.float64), _bands_from_index(idx), check=False)[:, idx]
    return (y * (view_local[:, 2:3] > 0)).to(dtype)


def mrt_view_taps(view_local: torch.Tensor, M: int, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """The four nonzero tents at each local view (Lehtinen & Kautz 2003 eq. 13), weights zero
    below the horizon: (idx int64 ``[V, 4]`` into the M² rows, w ``[V, 4]``)."""
    idx, w = tent_taps(view_local.to(torch.float64), M)
    return idx, (w * (view_local[:, 2:3] > 0)).to(dtype)


def apply_dense(M: torch.Tensor, L: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Σ_r y_pr (M_p l_c)_r: ``M [V, N_r, N_i]``, ``L [C, N_i]``, ``y [V, N_r]`` → ``[V, C]``
    (dtype of M; one GEMM over all rows, then the weighted sum)."""
    check_shape("M", M, ndim=3)
    V, n_out, n_in = M.shape
    Lc = _light(L, n_in, M.dtype)
    e = (M.reshape(V * n_out, n_in) @ Lc.T).reshape(V, n_out, -1)  # [V, N_r, C]
    return torch.einsum("vr,vrc->vc", y.to(M.dtype), e)


def apply_taps(A: torch.Tensor, L: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Σ_k w_pk (A_p l_c)_{idx_pk}: ``A [V, R, N_i]``, ``L [C, N_i]``, taps ``[V, k]`` → ``[V, C]``
    (a gather of k rows per vertex, then one GEMM)."""
    check_shape("A", A, ndim=3)
    V, R, n_in = A.shape
    Lc = _light(L, n_in, A.dtype)
    rows = (torch.arange(V)[:, None] * R + idx).reshape(-1)
    taps = A.reshape(V * R, n_in).index_select(0, rows)  # [V·k, N_i]
    e = (taps @ Lc.T).reshape(V, idx.shape[1], -1)
    return (e * w.to(A.dtype)[:, :, None]).sum(1)


def glossy(M: torch.Tensor, L: torch.Tensor, view_local: torch.Tensor, out_index: torch.Tensor | list | None = None) -> torch.Tensor:
    """Exit radiance from glossy exit transfer (Sloan 2003 §3.1).

    Args:
        M: ``[V, N_r, N_i]`` exit-transfer matrices (Transfer kind 'glossy', quantity 'exit').
        L: ``[C, N_i]`` light. view_local: ``[V, 3]`` unit local view directions.
        out_index: flat SH index of each row (``meta['out_index']``; default 0..N_r-1).
    Returns:
        ``[V, C]`` (dtype of M): Σ_r y_{o(r)}(v_p) (M_p L_c)_r, zero below the horizon.
    """
    check_shape("M", M, ndim=3)
    return apply_dense(M, L, glossy_view_weights(view_local, out_index, M.shape[1], M.dtype))


def _bands_from_index(idx: torch.Tensor) -> int:
    top = int(idx.max()) if idx.numel() else 0
    return math.isqrt(top) + 1


def mrt(A: torch.Tensor, L: torch.Tensor, view_local: torch.Tensor) -> torch.Tensor:
    """Matrix radiance transfer exit radiance, four taps (Lehtinen & Kautz 2003 eq. 9).

    Args:
        A: ``[V, M², n²]`` (Transfer kind 'mrt'). L: ``[C, n²]``. view_local: ``[V, 3]``.
    Returns:
        ``[V, C]`` = Σ_{j ∈ 4 taps} g_j(v_p) (A_p L)_j — only the four rows of A_p whose tents
        are nonzero at v_p are read (a gather of 4·n² floats per vertex, then one GEMM); zero
        below the horizon.
    """
    check_shape("A", A, ndim=3)
    M2 = A.shape[1]
    Mside = math.isqrt(M2)
    if Mside * Mside != M2:
        raise ValueError(f"A has {M2} rows; accepted: M² rows of an M×M tent basis")
    return apply_taps(A, L, *mrt_view_taps(view_local, Mside, A.dtype))


def kautz_setup(frames: torch.Tensor, bands: int) -> list[torch.Tensor]:
    """Per-vertex SH rotation blocks R_p = D(F_p) for :func:`kautz` (static; computed once)."""
    return rotation_blocks(frames, bands)


def kautz(T: torch.Tensor | None, rot_blocks: list[torch.Tensor], B: torch.Tensor, L: torch.Tensor,
          view_local: torch.Tensor, material_index: torch.Tensor | None = None) -> torch.Tensor:
    """Kautz, Sloan & Snyder 2002 (MRT Table 1 (a)): rotate, multiply, dot.

    Args:
        T: ``[V, n², n²]`` global transferred-radiance matrices (Transfer 'glossy' with
            quantity 'transferred'), or None for unshadowed lighting (T_p = I).
        rot_blocks: from :func:`kautz_setup` (blocks ``[V, 2l+1, 2l+1]``).
        B: BRDF matrix ``[m², n²]`` (zero-hemisphere or least squares, all m² rows) or one per
            material ``[U, m², n²]`` with ``material_index [V]``.
        L: ``[C, n²]``. view_local: ``[V, 3]``.
    Returns:
        ``[V, C]``: b(v_p) · R_p T_p L with the view-dependent BRDF coefficients b(v) = Bᵀ y(v).
    """
    n_in = B.shape[-1]
    bands_in = band_of_coeffs(n_in, "B columns")
    bands_out = band_of_coeffs(B.shape[-2], "B rows")
    dtype = rot_blocks[0].dtype if T is None else T.dtype
    Lc = _light(L, n_in, dtype)
    V = view_local.shape[0]
    if T is None:
        t = Lc.T.expand(V, n_in, Lc.shape[0])  # [V, n², C]
    else:
        t = (T.reshape(-1, n_in) @ Lc.T).reshape(V, n_in, -1)  # transferred radiance, global
    tl = torch.empty(V, n_in, Lc.shape[0], dtype=dtype)
    for l in range(bands_in):  # rotate into the local frame: a loop over bands, batched bmm each
        a, b = l * l, (l + 1) * (l + 1)
        tl[:, a:b] = rot_blocks[l].to(dtype) @ t[:, a:b]
    y = eval_sh(view_local.to(dtype), bands_out, check=False)  # [V, m²]
    Bd = B.to(dtype)
    if Bd.ndim == 2:
        bv = y @ Bd  # [V, n²] view-dependent BRDF coefficients (one GEMM)
    else:
        if material_index is None:
            raise ValueError("B holds one matrix per material; pass material_index [V]")
        bv = torch.einsum("vi,vij->vj", y, Bd[material_index])
    return torch.einsum("vj,vjc->vc", bv, tl) * (view_local[:, 2:3] > 0).to(dtype)


# --------------------------------------------------------------------------------------------
# all-frequency relighting: sparse Haar light x sparse Haar transfer (Ng et al. 2003)

def wavelet_light(spec, res: int, terms: int | None = None, selection: str = "transport",
                  weights: torch.Tensor | None = None, supersample: int = 4) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """A light's non-linear wavelet approximation (Ng 2003 §5): the light on the ``faces`` cube at
    ``res`` (:func:`prt_torch.lighting.haar.cube_light`, not band-limited), its Haar coefficients
    per face, and the ``terms`` most important of them by ``selection`` ('magnitude', 'area',
    'transport' with ``weights [P]``; :func:`prt_torch.lighting.haar.select_terms`). ``terms``
    None: all 6R² (the exact pixel-basis result). Returns (indices ``[N]`` int64, values ``[C, N]``
    float64, record of the rasterisation with ``'energy_kept'``, the fraction of Σ L̂² kept)."""
    from .lighting.haar import cube_light, haar2d, select_terms

    cube, rec = cube_light(spec, res, supersample=supersample)
    H = haar2d(cube).reshape(cube.shape[0], -1)  # [C, P]
    P = H.shape[1]
    idx, vals = select_terms(H, P if terms is None else terms, selection, weights)
    tot = float(H.square().sum())
    rec = dict(rec, terms=int(idx.numel()), selection=selection,
               energy_kept=float(vals.square().sum()) / tot if tot > 0 else 1.0)
    return idx, vals, rec


def wavelet_dense(values: torch.Tensor, index: torch.Tensor, light_idx: torch.Tensor, light_vals: torch.Tensor,
                  P: int) -> torch.Tensor:
    """The dense reference of sparse wavelet relighting: the light's kept terms scattered into a
    dense ``[C, P]`` coefficient vector, then for every vertex Σ_k values[v,k] · L̂[c, index[v,k]]
    (Ng 2003 eq. 2 as a gather). ``values [V, K]`` float, ``index [V, K]`` int → ``[V, C]`` in
    the dtype of ``values`` (albedo not applied)."""
    C = light_vals.shape[0]
    Ld = torch.zeros(C, P, dtype=values.dtype)
    Ld[:, light_idx] = light_vals.to(values.dtype)
    g = Ld[:, index.long()]  # [C, V, K]
    return (g * values[None]).sum(-1).T.contiguous()


class WaveletRelighter:
    """Sparse light × sparse transfer (Ng 2003 §6), the all-frequency relighting of a wavelet
    transfer (:mod:`prt_torch.transfer.wavelet`).

    Built once per transfer: the kept coefficients re-ordered by wavelet index (Ng's layout —
    per Haar coefficient the (vertex, value) pairs, zeros dropped), each column stored in the form
    that reads fewer bytes (``prt_torch/kernels/wavelet.c``):

    * **dense** — the columns at least ``dense_min`` × V vertices keep (default b/(4+b) for b-byte
      values: a dense column of V values is then no larger than its (int32 row, value) pairs; in
      practice the coarse Haar levels, which every vertex above the horizon keeps, and most of the
      coefficients a light reads): ``dense [ceil(V/32), Pd, 32]`` in the stored dtype (blocks of 32
      vertices, zeros where a vertex did not keep the coefficient), ``dslot [P]`` the column's slot
      or -1. Relit as a register-blocked GEMV: no index read, no scatter.
    * **sparse** — the rest, a CSC matrix: ``colptr [P+1]`` int64 (dense columns empty), ``offs [E]``
      int32 (16 × the vertex: the byte offset of its accumulator row), ``qvals [E]`` the stored
      values, each column padded to a multiple of 4 entries (value 0 on row V); scattered into
      16-byte accumulator rows.

    ``dense_min`` > 1 stores every column sparse (the plain CSC layout). Per light only the
    columns of its N kept terms are read: :meth:`touched` nonzero coefficients, :meth:`bytes_read`
    bytes. ``weights`` ``[P]``: mean |T̂_vk| over vertices (for the transport-weighted selection).

    ``relighter(light_idx [N], light_vals [C, N]) -> [V, C]`` float32 exit radiance, albedo
    applied (``mesh.albedo``, the first C channels; grey C=1 takes channel 0). The C kernel when
    it compiles, else (and with ``PRT_TORCH_NATIVE=0``) the same two forms in torch; light values
    that require grad take :meth:`relight_grad` (differentiable, for a fixed term selection).
    """

    BLOCK = 32  # vertices per dense block (kernels/wavelet.c BV)

    def __init__(self, transfer, dense_min: float | None = None):
        from .transfer.wavelet import wavelet_values

        if getattr(transfer, "kind", None) != "wavelet":
            raise ValueError(f"WaveletRelighter needs a transfer of kind 'wavelet'; got {getattr(transfer, 'kind', describe(transfer))!r}")
        vals = wavelet_values(transfer)  # [V, K] float32
        index = transfer.aux["index"].long()
        self.transfer = transfer
        V, K = vals.shape
        # the kernel's values: the stored (quantised) integers, the scale applied per vertex at the end
        qstore = transfer.data
        quantised = qstore.dtype in (torch.int8, torch.int16)
        self.scale = transfer.aux["scale"].to(torch.float32) if quantised else torch.ones(V)
        if quantised and self.scale.ndim == 2:
            # one scale per vertex and Haar level: the kernel applies one factor per vertex at the end, so the values are
            # re-quantised to 16 bits with one scale per vertex (added error per value <= max|T̂_v| / 65534)
            from .transfer.wavelet import dequantise, quantise

            qstore, self.scale = quantise(vals, 16)
            vals = dequantise(qstore, self.scale)  # the values relit with
        self.V, self.K = V, K
        self.res = int(transfer.meta["res"])
        self.P = P = 6 * self.res * self.res
        flat_idx = index.reshape(-1)
        flat_val = vals.reshape(-1)
        nz = flat_val != 0
        order = torch.argsort(flat_idx[nz], stable=True)
        src = torch.nonzero(nz).flatten()[order]  # column-major order, rows ascending within a column
        col = flat_idx[src]
        self.nnz = torch.bincount(col, minlength=P)  # [P] nonzero coefficients per column
        self.weights = torch.zeros(P, dtype=torch.float64).index_add_(
            0, col, flat_val[src].abs().to(torch.float64)) / max(V, 1)
        self.albedo = transfer.mesh.albedo.to(torch.float32)
        if transfer.meta.get("albedo_folded"):
            self.albedo = torch.ones_like(self.albedo)
        self.values, self.index = vals, index
        q = qstore.reshape(-1) if quantised else flat_val
        b = q.element_size()
        self.dense_min = b / (4 + b) if dense_min is None else float(dense_min)
        is_dense = self.nnz >= max(self.dense_min * V, 1)
        self.dslot = torch.full((P,), -1, dtype=torch.int64)
        dcols = torch.nonzero(is_dense).flatten()
        self.dslot[dcols] = torch.arange(dcols.numel())
        self.Pd = Pd = int(dcols.numel())
        in_dense = is_dense[col]
        nb = -(-V // self.BLOCK)
        dense = torch.zeros(nb, max(Pd, 1), self.BLOCK, dtype=q.dtype)
        ds, dv = src[in_dense], src[in_dense] // K
        dense[dv // self.BLOCK, self.dslot[flat_idx[ds]], dv % self.BLOCK] = q[ds]
        self.dense = dense.contiguous()
        # sparse columns padded to a multiple of 4 entries (zero values on the dummy row V): whole groups in the kernel
        ss = src[~in_dense]
        counts = torch.where(is_dense, 0, self.nnz)
        padded = (counts + 3) // 4 * 4
        self.colptr = torch.zeros(P + 1, dtype=torch.int64)
        self.colptr[1:] = torch.cumsum(padded, 0)
        cs = col[~in_dense]  # each entry's place: its column's start + its rank within the column
        at = self.colptr[cs] + torch.arange(ss.numel()) - (torch.cumsum(counts, 0) - counts)[cs]
        E = int(self.colptr[-1])
        self.offs = torch.full((E,), 16 * V, dtype=torch.int32)  # byte offsets of the 16-byte accumulator rows
        self.qvals = torch.zeros(E, dtype=q.dtype)
        self.offs[at] = (ss // K * 16).to(torch.int32)
        self.qvals[at] = q[ss]
        self._f: dict = {}
        self._acc = torch.empty(V + 1, 4, dtype=torch.float32)  # the kernel's scratch: sums of sparse columns (16-byte rows; V: the padding's row)
        self._wk = torch.empty(P, dtype=torch.int64)  # the light's terms split into dense / sparse
        self._lw = torch.empty(P, 4, dtype=torch.float32)
        self._ld = torch.empty(max(self.Pd, 1), 4, dtype=torch.float32)  # the light of each dense slot
        self._mk = torch.empty(max(self.Pd, 1), dtype=torch.uint8)
        self._native = None

    @property
    def bytes_per_entry(self) -> int:
        """Bytes the kernel reads per sparse transfer coefficient: an int32 row offset and the stored value."""
        return 4 + self.qvals.element_size()

    def bytes_read(self, light_idx: torch.Tensor) -> int:
        """Transfer bytes a light with these kept terms reads: the selected dense columns (32-vertex
        blocks, zeros included) and the selected sparse columns' (row, value) pairs (padding included)."""
        li = light_idx.long()
        d = self.dslot[li] >= 0
        b = self.qvals.element_size()
        ls = li[~d]
        return int(d.sum()) * self.dense.shape[0] * self.BLOCK * b + int((self.colptr[ls + 1] - self.colptr[ls]).sum()) * (4 + b)

    def _factor(self, C: int, albedo: bool) -> torch.Tensor:
        key = (C, albedo)
        if key not in self._f:
            a = (self.albedo[:, :C] if C > 1 else self.albedo[:, :1]) if albedo else torch.ones(self.V, C)
            self._f[key] = (a * self.scale[:, None]).contiguous()
        return self._f[key]

    def touched(self, light_idx: torch.Tensor) -> int:
        """Nonzero transfer coefficients a light with these kept terms reads (Σ_n nnz(column n))."""
        return int(self.nnz[light_idx.long()].sum())

    def light(self, spec, terms: int | None = None, selection: str = "transport", supersample: int = 4):
        """:func:`wavelet_light` at this transfer's resolution (``'transport'`` uses :attr:`weights`)."""
        return wavelet_light(spec, self.res, terms, selection, self.weights if selection == "transport" else None,
                             supersample)

    def _kernel(self):
        """The compiled kernel bound to this transfer's arrays: a function of (N, sel, lv, C, f, out)
        pointers returning the kernel's status; None without a compiler or with PRT_TORCH_NATIVE=0."""
        import os

        if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
            return None
        if self._native is None:
            lib = _wavelet_lib()
            if lib is None:
                return None
            fn = {torch.int8: lib.prt_wavelet_relight_i8, torch.int16: lib.prt_wavelet_relight_i16}.get(
                self.qvals.dtype, lib.prt_wavelet_relight_f32)
            # kernels/wavelet.c's wavelet_layout: the arrays' addresses, built once (kept alive by self); dense terms in slot order
            self._layout = torch.tensor([self.P, self.dense.shape[1], self.V, self.colptr.data_ptr(), self.offs.data_ptr(),
                                         self.qvals.data_ptr(), self.dslot.data_ptr(), self.dense.data_ptr(),
                                         self._acc.data_ptr(), self._wk.data_ptr(), self._lw.data_ptr(), self._ld.data_ptr(),
                                         self._mk.data_ptr()], dtype=torch.int64)
            lay = self._layout.data_ptr()
            self._native = lambda N, sel, lv, C, f, out: fn(lay, N, sel, lv, C, f, out)
        return self._native

    def __call__(self, light_idx: torch.Tensor, light_vals: torch.Tensor, out: torch.Tensor | None = None,
                 albedo: bool = True) -> torch.Tensor:
        if torch.is_grad_enabled() and isinstance(light_vals, torch.Tensor) and light_vals.requires_grad:
            if out is not None:
                raise ValueError("out= with light values that require grad; accepted: out=None (autograd cannot write "
                                 "into a reused buffer)")
            return self.relight_grad(light_idx, light_vals, albedo)
        li, lv = light_idx, light_vals  # no conversion on the fast path (int64 indices, float32 values)
        if not (isinstance(li, torch.Tensor) and li.dtype == torch.int64):
            li = torch.as_tensor(li).long()
        if not (isinstance(lv, torch.Tensor) and lv.dtype == torch.float32):
            lv = torch.as_tensor(lv).to(torch.float32)
        N = li.numel()
        if lv.ndim != 2 or lv.shape[1] != N or li.ndim != 1:
            raise ValueError(f"light values {tuple(lv.shape)} for indices {tuple(li.shape)}; accepted: indices [N], values [C, N]")
        C = lv.shape[0]
        o = torch.empty(self.V, C, dtype=torch.float32) if out is None else out
        if o.shape != (self.V, C) or o.dtype != torch.float32 or not o.is_contiguous():
            raise ValueError(f"out {tuple(o.shape)} {o.dtype}; accepted: a contiguous float32 [{self.V}, {C}]")
        f = self._factor(C, albedo)
        kern = self._kernel() if C <= 4 else None
        if kern is not None:
            li, lv = li.contiguous(), lv.contiguous()
            if kern(N, li.data_ptr(), lv.data_ptr(), C, f.data_ptr(), o.data_ptr()) == 0:
                return o
        self._check_indices(li)
        return self._torch(li, lv, o).mul_(f)

    def relight_grad(self, light_idx: torch.Tensor, light_vals: torch.Tensor, albedo: bool = True) -> torch.Tensor:
        """The relighting under autograd (the C kernel is forward-only; ``__call__`` comes here when
        ``light_vals`` requires grad): Ng 2003 eq. 2 for a fixed term selection, :meth:`_sums`
        (the torch path's dense GEMV and sparse gather, out of place) in the values' dtype (float64 for
        gradcheck), differentiable with respect to ``light_vals [C, N]`` (not the indices: the
        selection is piecewise constant). → ``[V, C]``, albedo and the quantisation scale applied
        (float32 factors, so the values equal the kernel's to float32 rounding)."""
        li = torch.as_tensor(light_idx).long()
        lv = light_vals
        if lv.ndim != 2 or li.ndim != 1 or lv.shape[1] != li.numel() or not lv.is_floating_point():
            raise ValueError(f"light values {tuple(lv.shape)} {lv.dtype} for indices {tuple(li.shape)}; accepted: indices [N], "
                             "float values [C, N]")
        self._check_indices(li)
        dt = torch.promote_types(lv.dtype, torch.float32)
        return self._sums(li, lv, dt) * self._factor(lv.shape[0], albedo).to(dt)

    def _check_indices(self, li: torch.Tensor) -> None:
        if li.numel():
            lo, hi = (int(v) for v in torch.aminmax(li))
            if lo < 0 or hi >= self.P:
                raise ValueError(f"light indices span {lo}..{hi}; accepted: 0..{self.P - 1} (6R², R={self.res})")

    def _torch(self, li: torch.Tensor, lv: torch.Tensor, o: torch.Tensor) -> torch.Tensor:
        """The torch path (no compiler, C > 4, or PRT_TORCH_NATIVE=0): :meth:`_sums` in float32, into ``o``."""
        return o.copy_(self._sums(li, lv, torch.float32))

    def _sums(self, li: torch.Tensor, lv: torch.Tensor, dt: torch.dtype) -> torch.Tensor:
        """Σ_n L̂[c, n] T̂[v, n] over the light's terms ``li [N]``, ``lv [C, N]`` in ``dt`` (scale and
        albedo not applied), out of place (differentiable with respect to ``lv``): the dense
        columns as one batched GEMV over the 32-vertex blocks, the sparse ones gathered and added
        by one ``index_add``. → ``[V, C]``."""
        lv = lv.to(dt)
        C = lv.shape[0]
        slot = self.dslot[li]
        d = slot >= 0
        o = torch.einsum("bnv,cn->bvc", self.dense[:, slot[d]].to(dt), lv[:, d]).reshape(-1, C)[:self.V]
        ls, lvs = li[~d], lv[:, ~d]
        starts = self.colptr[ls]
        cnt = self.colptr[ls + 1] - starts
        total = int(cnt.sum())
        if total:  # gather the sparse columns, one index_add
            seg = torch.repeat_interleave(torch.arange(ls.numel()), cnt)
            first = torch.cumsum(cnt, 0) - cnt
            pos = starts[seg] + torch.arange(total) - first[seg]
            r = self.offs[pos].long() // 16
            keep = r < self.V  # not the padding
            o = o.index_add(0, r[keep], self.qvals[pos[keep], None].to(dt) * lvs.T[seg[keep]])
        return o


_WAVELET: dict = {}


def _wavelet_lib():
    """The compiled sparse relighting kernel (``prt_torch/kernels/wavelet.c``), or None (torch path)."""
    import ctypes
    import os

    if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return None
    if "lib" not in _WAVELET:
        from ._native import LIBRARIES, compile_library, kernel_sources

        names, flags = LIBRARIES["wavelet"]
        i64, vp = ctypes.c_int64, ctypes.c_void_p
        sig = [vp, i64, vp, vp, i64, vp, vp]
        _WAVELET["lib"], _WAVELET["why"] = compile_library("wavelet", kernel_sources(names), list(flags), {
            "prt_wavelet_relight_f32": sig, "prt_wavelet_relight_i8": sig, "prt_wavelet_relight_i16": sig})
    return _WAVELET["lib"]
