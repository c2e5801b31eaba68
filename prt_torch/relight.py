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

import functools
import math
import os
import warnings

import torch

from . import io
from ._checks import check_shape, describe
from .sh import band_of_coeffs, eval_sh, rotation_blocks
from .transfer.tents import tent_taps
from .transfer.transport import HORIZON_EPS

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


def _above(view_local: torch.Tensor) -> torch.Tensor:
    """``[V, 1]`` bool: the local view ``view_local [V, 3]`` is above the vertex's tangent plane,
    cos θ_o = z > :data:`~prt_torch.transfer.transport.HORIZON_EPS` — the one horizon test of every
    view-dependent relight here (glossy, MRT, Kautz), the transport tables and the harness's exact
    reference (Green 2005 eq. 1.2: f_r = 0 below the horizon; a view in the plane counts as below)."""
    return view_local[:, 2:3] > HORIZON_EPS


def glossy_view_weights(view_local: torch.Tensor, out_index: torch.Tensor | list | None, n_out: int,
                        dtype: torch.dtype = torch.float32) -> torch.Tensor:
    """Per-vertex weights over the rows of exit transfer (Sloan 2003 §3.1): y_{o(r)}(v_p),
    zero where the local view is below the horizon. ``view_local [V, 3]`` → ``[V, n_out]``.
    Below the horizon means cos θ_o = z ≤ :data:`~prt_torch.transfer.transport.HORIZON_EPS` (1e-9), as
    the transport tables, their exact reference and view taps have it: a view lying in the tangent
    plane comes out of the float64 frame rotation at z ~ ±1e-17, and a ``> 0`` test gave it the full
    grazing weights or none by the sign of that rounding (:func:`_above`)."""
    idx = torch.arange(n_out) if out_index is None else torch.as_tensor(out_index, dtype=torch.int64)
    if idx.numel() != n_out:
        raise ValueError(f"out_index has {idx.numel()} entries but the matrices have {n_out} rows; accepted: one SH index per row")
    y = eval_sh(view_local.to(torch.float64), _bands_from_index(idx), check=False)[:, idx]
    return (y * _above(view_local)).to(dtype)


def mrt_view_taps(view_local: torch.Tensor, M: int, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
    """The four nonzero tents at each local view (Lehtinen & Kautz 2003 eq. 13), weights zero
    below the horizon (cos θ_o ≤ ``HORIZON_EPS``, :func:`_above`): (idx int64 ``[V, 4]`` into the M² rows,
    w ``[V, 4]``)."""
    idx, w = tent_taps(view_local.to(torch.float64), M)
    return idx, (w * _above(view_local)).to(dtype)


def apply_dense(M: torch.Tensor, L: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """Σ_r y_pr (M_p l_c)_r: ``M [V, N_r, N_i]``, ``L [C, N_i]``, ``y [V, N_r]`` → ``[V, C]``
    (dtype of M; one GEMM over all rows, then the weighted sum)."""
    check_shape("M", M, ndim=3)
    V, n_out, n_in = M.shape
    Lc = _light(L, n_in, M.dtype)
    e = (M.reshape(V * n_out, n_in) @ Lc.T).reshape(V, n_out, -1)  # [V, N_r, C]
    return torch.einsum("vr,vrc->vc", y.to(M.dtype), e)


#: bytes of gathered tap rows :func:`apply_taps` holds at once (one reused buffer per call). Gathering
#: every vertex's rows at once made a fresh ``V·k·N_i`` temporary per call (47 MB for the default
#: Gaussian part's tables), which glibc either served from its heap or mapped anew — page-faulted on
#: first touch every call, 2-3x the call's time — depending on the process's allocation history
#: (reports/benchmarks/taps_first_touch.md). 4 MiB: the default MRT run's peer (10 242 × 4 taps × 16
#: floats, 2.6 MB) stays one gather, as before (1 MiB blocks there paired 0.91-1.03x whole).
TAPS_BLOCK_BYTES = 4 << 20


def apply_taps(A: torch.Tensor, L: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """Σ_k w_pk (A_p l_c)_{idx_pk}: ``A [V, R, N_i]``, ``L [C, N_i]``, taps ``[V, k]`` → ``[V, C]``
    (Lehtinen & Kautz 2003 eq. 9's taps; the transport tables' cross-fade between stored views):
    a gather of k rows per vertex, then one GEMM, by blocks of vertices whose gathered rows fill
    :data:`TAPS_BLOCK_BYTES` (one buffer reused across the blocks: the same per-row arithmetic as
    one gather, no per-call first-touch page faults). With autograd recording through ``A``, ``L``
    or ``w``: one gather of every vertex (differentiable)."""
    check_shape("A", A, ndim=3)
    V, R, n_in = A.shape
    Lc = _light(L, n_in, A.dtype)
    k = idx.shape[1]
    rows = (torch.arange(V)[:, None] * R + idx).reshape(-1)
    Af = A.reshape(V * R, n_in)
    nb = max(1, TAPS_BLOCK_BYTES // max(1, k * n_in * A.element_size()))
    if nb >= V or (torch.is_grad_enabled() and (A.requires_grad or Lc.requires_grad or w.requires_grad)):
        e = (Af.index_select(0, rows) @ Lc.T).reshape(V, k, -1)  # [V·k, N_i] gathered at once
    else:
        e = A.new_empty(V * k, Lc.shape[0])
        buf = A.new_empty(nb * k, n_in)
        for s in range(0, V, nb):  # a few blocks (V·k·N_i·4 / 4 MiB), each a batched gather + GEMM
            a, b = s * k, min(s + nb, V) * k
            torch.mm(torch.index_select(Af, 0, rows[a:b], out=buf[: b - a]), Lc.T, out=e[a:b])
        e = e.view(V, k, -1)
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
    return torch.einsum("vj,vjc->vc", bv, tl) * _above(view_local).to(dtype)


# --------------------------------------------------------------------------------------------
# all-frequency relighting: sparse Haar light x sparse Haar transfer (Ng et al. 2003)

def wavelet_light(spec, res: int, terms: int | None = None, selection: str = "transport",
                  weights: torch.Tensor | None = None, supersample: int = 4) -> tuple[torch.Tensor, torch.Tensor, dict]:
    """A light's non-linear wavelet approximation (Ng 2003 §5): the light on the ``faces`` cube at
    ``res`` (:func:`prt_torch.lighting.haar.cube_light`, not band-limited), its Haar coefficients
    per face, and the ``terms`` most important of them by ``selection`` ('magnitude', 'area',
    'transport' with ``weights [P]``; :func:`prt_torch.lighting.haar.select_terms`). ``terms``
    None: all 6R² (the exact pixel-basis result). Only the light's nonzero terms are ever kept
    (``select_terms``: above ``haar.ZERO_TERM`` of its largest), so N' = min(N, 6R², nonzero) terms.
    Returns (indices ``[N']`` int64, values ``[C, N']`` float64, record of the rasterisation with
    ``'terms'`` (N', the terms kept), ``'terms_requested'`` (N, or 6R² for None) and ``'energy_kept'``,
    the fraction of Σ L̂² kept)."""
    from .lighting.haar import cube_light, haar2d, select_terms

    cube, rec = cube_light(spec, res, supersample=supersample)
    H = haar2d(cube).reshape(cube.shape[0], -1)  # [C, P]
    P = H.shape[1]
    idx, vals = select_terms(H, P if terms is None else terms, selection, weights)
    tot = float(H.square().sum())
    rec = dict(rec, terms=int(idx.numel()), terms_requested=P if terms is None else int(terms), selection=selection,
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


class _Rows:
    """Rows ``a:b`` of a wavelet transfer's ``data``, ``aux['index']``, ``aux['scale']`` (tensors or memory maps),
    as :meth:`WaveletRelighter._kernel_values` reads a transfer (its rows are independent)."""

    kind = "wavelet"

    def __init__(self, data, meta: dict, aux: dict, a: int, b: int):
        self.data, self.meta = data[a:b], meta
        self.aux = {"index": aux["index"][a:b], "scale": aux["scale"][a:b]}


class WaveletRelighter:
    """Sparse light × sparse transfer (Ng 2003 §6), the all-frequency relighting of a wavelet
    transfer (:mod:`prt_torch.transfer.wavelet`), grey (``data [V, K]``, CT = 1) or coloured
    (``data [V, 3, K]``: one transfer per colour sharing each vertex's kept indices, CT = 3, the
    interreflection of a coloured mesh with the albedo folded in).

    Built once per transfer: the kept coefficients re-ordered by wavelet index (Ng's layout —
    per Haar coefficient its vertices' values, zeros dropped), each column stored in one of two
    forms (``prt_torch/kernels/wavelet.c``):

    * **dense** — the columns at least ``dense_min`` × V vertices keep (default :meth:`default_dense_min`: b/(4+b)
      for b-byte values, 0.2 for 16-bit values in the AVX-512 builds with the VNNI dense loop; in practice the coarse
      Haar levels, which every vertex above the horizon keeps, and most of the coefficients a light reads):
      ``dense [ceil(V/32), Pd, CT, 32]`` in the stored dtype (blocks of 32 vertices, zeros where a vertex did not keep
      the coefficient; from 2 MiB up in memory advised
      for 2 MiB transparent huge pages, :func:`prt_torch.io.hugepage_zeros`, ``PRT_TORCH_HUGEPAGES=0``: torch's
      buffer — :attr:`huge_pages` the switch as read at construction), ``dslot
      [P]`` int32 the column's slot or -1. Relit as a register-blocked GEMV: no index read, no scatter.
    * **block-sparse** — the rest, tile-major: the vertices in tiles of :attr:`TV` (a multiple of 32;
      ``tile``, default the vertices split between the relighter's ``threads`` — None: ``torch.get_num_threads()``
      at construction — up to 4096: a tile's accumulators, TV/8 × 128 bytes, stay in L2, and each thread takes whole
      tiles; a relighter built for one thread called at two runs its one tile on one thread), within a tile per column
      the 8-vertex blocks holding any of its values: ``bofs [NB]`` int32 (the block's accumulator,
      a byte offset in the tile's scratch), ``bvals [NB, CT, 8]`` the stored values (zeros where a
      vertex of the block did not keep it), ``tptr [NT, P+1]`` int32 each tile's column starts
      (relative to ``tbase [NT]``). One 8-lane multiply-add per block and output channel.

    The same sparse blocks may also be kept row-major (``rptr [4·ceil(V/32)+1]`` int64, ``rcol [NB]`` int32,
    ``rvals [NB, CT, 8]``): when a light's sparse terms hold at least ``row_min`` (> 1: never) of the sparse blocks —
    by default the crossover measured for the kernel's build (:meth:`default_row_min`: :attr:`ROW_MIN_W16` in the
    AVX-512 builds with the 16-lane code, :attr:`ROW_MIN` = 0.5 in the others; an explicit ``row_min`` wins) —, the
    kernel sums every block into the dense block's registers with the light looked up per column instead of
    scattering the selected ones into scratch. ``layouts``
    says when that copy (as many bytes as the column-major blocks, less their ``bofs``) is held:
    ``'auto'`` (default) builds it on first need — the first light that chooses the row-major pass
    (the kernel answers 3 before any work, :meth:`_build_rows`, the call is repeated), so a render
    loop at small N never holds it; ``'both'`` builds it here; ``'column'`` never (the column-major
    pass for every light, as ``row_min`` > 1). ``rptr``, ``rcol``, ``rvals`` are None until built;
    :meth:`held_bytes` the arrays held.

    ``dense_min`` > 1 stores every column sparse. Per light only the columns of its N kept terms
    are read: :meth:`touched` nonzero coefficients, :meth:`bytes_read` bytes. ``weights`` ``[P]``:
    mean |T̂_vk| over vertices and channels (for the transport-weighted selection).

    ``relighter(light_idx [N], light_vals [C, N]) -> [V, CO]`` float32 exit radiance, CO = max(C, CT),
    albedo applied (``mesh.albedo``, the first CO channels; grey C=1 takes channel 0; folded into a
    coloured transfer). A coloured transfer takes a grey (C = 1) or RGB (C = 3) light. ``threads``:
    the kernel's threads (tiles split between them; None = ``torch.get_num_threads()`` per call; the default tile
    follows the threads at construction: :meth:`_tile`).
    The C kernel when it compiles, else (and with ``PRT_TORCH_NATIVE=0``) the same two forms in torch; light values
    that require grad take :meth:`relight_grad` (differentiable, for a fixed term selection).

    ``arith``: the dense terms' arithmetic. ``'auto'`` (default): the build's — in the AVX-512 build on a CPU with
    AVX-512 VNNI (:func:`wavelet_kernel_path`'s ``vnni``) the calls of a 16-bit grey transfer (CT = 1) under an RGB
    light with unequal channels that take the 16-lane loop sum their dense terms by int16 dot products (``vpdpwssd``):
    the light quantised per call to int16 per channel in groups of 16 dense terms by the column-maximum rule, error
    per vertex and channel at most f_v Σ_g (s_g / 2) Σ_{k∈g} |T̂_v,k| (s_g the group's step: about max|L̂| / 32767,
    more where Σ_k tmax_k |L̂_k| would overflow int32): 0.28–0.90× the stored 16-bit transfer's own quantisation
    bound, an output error of 8e-6–6e-5 relative L2, but up to ~2e-3 relative at the dimmest vertices, where the
    light's terms cancel — more than the stored transfer's own error there (docs/wavelet.md, "The dense arithmetic";
    docs/wavelet_kernel_log.md, "the VNNI dense loop by default"). A per-call guard keeps that premise for every
    light: a call whose L2 bound of the VNNI error, Σ_G (s_G,c / 2) Σ_{k∈G} ‖scale ⊙ T̂_:,k‖₂, exceeds the transfer's
    own, ‖scale‖₂ Σ_k |L̂_k,c| / 2, in some channel takes the float32 loop (its bits) instead (e.g. one light term 1e4
    × the others in its flush group, or the coarse R = 8 layouts). Every other call, and every other build, the
    float32 loop. ``'float'``: the float32 loop for every call (the kernel's C | FDENSE), the bits of the builds
    without VNNI.

    ``dense_order``: the order of the dense slots in each 32-vertex block (:meth:`_dense_slots`) — ``'column'``
    (default: ascending Haar column), ``'weight'`` (descending transport weight), ``'level'`` (coarse Haar levels
    first), or a 1-D tensor of Haar columns whose dense ones take the first slots in that order (e.g. the transport-
    weighted ranking of the environment a render loop relights with, ``relighter.light(spec, P)[0]``: every N of that
    light then reads a prefix of each block's ~Pd × 64 bytes, adjacent lines, instead of lines scattered over them).
    The layout's bytes, :meth:`bytes_read` and the kernel are the same for every order; the kernel's dense list (and
    so each vertex's summation order) follows the light's order for N ≤ 256 and the column order above it in the
    AVX-512 build, the slot order in the 8-lane builds. Measured on an Intel Xeon (family 6 model 167;
    docs/wavelet_kernel_log.md "The dense slot order", reports/benchmarks/wavelet_dense_order.md): a light's own
    ranking 1.2–1.4× faster warm at the medium blocker (V = 10 585, studio N ≥ 100, sky N = 100; where its lines
    outgrow the L2 with the neighbours the prefetchers pull), none at small (the layout in L2) or where a light reads
    nearly every slot; the light-independent orders 0.92–1.09×, so ``'column'`` stays the default.
    :meth:`reorder_dense` changes the order in place.
    """

    BLOCK = 32  # vertices per dense block (kernels/wavelet.c BV)
    SUB = 8  # vertices per sparse block
    TILE_MAX = 4096  # the default tile's most vertices (_tile: a tile's scratch, TILE_MAX/8 x 128 bytes = 64 KB, in L2)
    #: ``row_min``'s default in builds without the 16-lane (W16) code (AVX2, AVX, baseline, ``avx512-256``): the
    #: row-major pass from half the sparse blocks, measured against the column-major pass on an AMD EPYC Zen 3 (AVX2;
    #: 1 thread CPU time, studio and sky, R = 32, K = 256): 0.88-0.90x at 0.39-0.42 of the blocks held, 0.99x at 0.51,
    #: 1.04-1.31x from 0.56
    ROW_MIN = 0.5
    #: ``row_min``'s default in the W16 builds (AVX-512 with the 16-lane code: the column-major pass three blocks per
    #: step), measured on an Intel Xeon (family 6 model 167; reports/benchmarks/wavelet_rowmin.md: 1 thread CPU time,
    #: blocker scene R = 32, K = 256, three runs): the passes cross at 0.56-0.69 of the blocks held by light (small,
    #: 2251 vertices; medium, 10 585: 0.60-0.67); over lights holding 0.40-0.80, 0.62 loses 0.2% on average to the
    #: faster pass (small and medium), 0.5 1.8% / 1.7%
    ROW_MIN_W16 = 0.62
    #: kernels/wavelet.c's opt-out bit of the VNNI dense loop (C | FDENSE: the float loop), passed only to builds with it
    FDENSE = 512
    #: ``arith``'s values
    ARITH = ("auto", "float")
    #: kernels/wavelet.c's ZMM_MIN: a call with fewer (dense term, 32-vertex block) pairs takes the 8-lane float loop
    ZMM_MIN = 256
    #: ``dense_min``'s default for 16-bit values in the W16 builds whose dense loop is VNNI (``vnni``: DENSE_VNNI compiled
    #: in; elsewhere, and for other value sizes, b/(4+b): 1/3 for 16-bit values, the bytes rule): a column is dense from
    #: 0.2 of the vertices.
    #: Measured on an Intel Xeon (family 6 model 167; docs/wavelet_kernel_log.md "The fourth row (small studio, 292
    #: kept) and the call's non-dense parts"; blocker scene R = 32, K = 256, one thread's CPU time, paired with a relighter of
    #: dense_min 1/3 on the same transfer, VNNI on both sides): in the call a VNNI dense (term, 32-vertex block) step
    #: costs ~6 cycles and a sparse 8-vertex block ~6.5; medium N = 30 1.08-1.15x in every run, medium N = 100-300
    #: 1.00-1.09x, small within noise (0.89-1.16x at load 5-6); the float loop on this layout down to 0.74x (evicted),
    #: so the float builds keep b/(4+b). 15-20 more dense columns (244 -> 259-264), 1-6 more bytes per vertex held
    DENSE_MIN_W16 = 0.2

    @classmethod
    def _build_record(cls) -> dict:
        """This process's kernel build (:func:`wavelet_kernel_path`), read once and kept (the key ``row_min_path``)."""
        if "row_min_path" not in _WAVELET:
            _WAVELET["row_min_path"] = wavelet_kernel_path()
        return _WAVELET["row_min_path"]

    @classmethod
    def default_dense_min(cls, b: int, path: dict | None = None, arith: str = "auto") -> float:
        """``dense_min``'s default for ``b``-byte stored values in a build of ``kernels/wavelet.c`` (``path``:
        :func:`wavelet_kernel_path`'s record; None: this process's build, read once): :attr:`DENSE_MIN_W16` for 16-bit
        values where the build's dense loop is the 16-lane one on integer dot products (``w16`` and ``vnni``: a dense
        (term, block) step costs about what a sparse 8-vertex block does), else b/(4+b) (the bytes rule: a dense
        column's b bytes per vertex against a sparse entry's 4 + b; the float loop's builds and the torch formulation,
        and ``arith='float'``, which runs the float loop on a VNNI build)."""
        path = cls._build_record() if path is None else path
        vnni = path.get("w16") and path.get("vnni") and arith == "auto"
        return cls.DENSE_MIN_W16 if b == 2 and vnni else b / (4 + b)

    @classmethod
    def default_row_min(cls, path: dict | None = None) -> float:
        """``row_min``'s default for a build of ``kernels/wavelet.c`` (``path``: :func:`wavelet_kernel_path`'s record;
        None: this process's build, read once): :attr:`ROW_MIN_W16` where the build has the 16-lane code (``w16``),
        else :attr:`ROW_MIN` (also for the torch formulation, which never takes the row-major pass)."""
        path = cls._build_record() if path is None else path
        return cls.ROW_MIN_W16 if path.get("w16") else cls.ROW_MIN

    @staticmethod
    def _row_permille(row_min: float, rows_used: bool) -> int:
        """kernels/wavelet.c's ``row_permille``: ``row_min`` in thousandths, or 1001 (never the row-major pass) when
        the relighter does not use it (``layouts='column'`` or ``row_min`` > 1)."""
        return min(int(round(row_min * 1000)), 1001) if rows_used else 1001

    @staticmethod
    def _takes_rows(sb: int, NB: int, permille: int) -> bool:
        """kernels/wavelet.c's choice of the row-major pass for a light whose distinct sparse columns hold ``sb`` of
        the ``NB`` sparse blocks: at least ``permille`` / 1000 of them (and at least one)."""
        return bool(sb and NB and permille <= 1000 and sb * 1000 >= permille * NB)

    @staticmethod
    def _kernel_values(transfer):
        """The kernel's values of a wavelet transfer (or of a slice of its rows: the rows are independent):
        ``(vals, vals3 [V, CT, K] float32 the values relit with, q3 [V, CT, K] the stored values the kernel
        reads, scale [V, CT] float32, quantised)``. ``vals`` is :func:`~prt_torch.transfer.wavelet.wavelet_values`
        (``[V, K]`` or ``[V, 3, K]``); a transfer with one scale per vertex and Haar level is re-quantised to
        16 bits with one scale per vertex and channel (the kernel applies one factor per vertex at the end;
        added error per value <= max|T̂_v| / 65534), its ``vals3`` the re-quantised values."""
        from .transfer.wavelet import dequantise, quantise, wavelet_values

        vals = wavelet_values(transfer)  # [V, K] or [V, 3, K] float32
        CT = 1 if vals.ndim == 2 else vals.shape[1]
        vals3 = vals[:, None] if CT == 1 else vals  # [V, CT, K]
        V, K = vals3.shape[0], vals3.shape[2]
        # the kernel's values: the stored (quantised) integers, the scale (per vertex and channel) applied at the end
        qstore = transfer.data if CT > 1 else transfer.data[:, None]
        quantised = qstore.dtype in (torch.int8, torch.int16)
        sc = transfer.aux["scale"].to(torch.float32)
        if quantised and sc.ndim == (3 if CT > 1 else 2):  # one scale per vertex and Haar level
            q2, s2 = quantise(vals3.reshape(V * CT, K), 16)
            qstore, scale = q2.reshape(V, CT, K), s2.reshape(V, CT)
            vals3 = dequantise(q2, s2).reshape(V, CT, K)  # the values relit with
        elif quantised:
            scale = sc.reshape(V, CT)
        else:
            scale = torch.ones(V, CT)
        return vals, vals3, (qstore if quantised else vals3.to(torch.float32)), scale, quantised

    #: the construction's chunk: rows whose 16-bit kernel values take about this many bytes (512 rows at K = 256;
    #: ~30x that in temporaries while counted and placed): the construction's peak above what it keeps. 256 KiB:
    #: 4-7x less peak than the whole-transfer build and no slower (128 KiB: 9-12x less, 0.95-1.11x its CPU time;
    #: reports/benchmarks/wavelet_build.md)
    BUILD_CHUNK_BYTES = 1 << 18

    @classmethod
    def _build_rows_per_chunk(cls, K: int, CT: int) -> int:
        """Rows per construction chunk: whole 32-vertex blocks (so whole 8-vertex sparse blocks) of about
        :attr:`BUILD_CHUNK_BYTES` of 16-bit kernel values (``K·CT·2`` bytes per row), at least one block."""
        return max(cls.BLOCK, cls.BUILD_CHUNK_BYTES // max(2 * K * CT, 1) // cls.BLOCK * cls.BLOCK)

    @classmethod
    def _tile(cls, V: int, tile: int | None, threads: int | None = None) -> int:
        """The sparse blocks' tile (vertices): ``tile``, or the vertices split between the relighter's ``threads``
        (None: ``torch.get_num_threads()`` now, at construction) rounded up to 32, at most :attr:`TILE_MAX`: no more
        tiles than the threads need (each (tile, sparse term) range of the sparse pass costs ~20 cycles, timed in place:
        bench_wavelet_setup.py --tsc; at one thread one tile of 2272 vertices against two of 1152, across placements,
        1.00-1.04x, studio 292 kept 1.02x, sky N = 1000 1.04x, Intel Xeon family 6 model 167,
        reports/benchmarks/wavelet_tile18_placements.md), none larger than a scratch of TILE_MAX/8 x 128 bytes (64 KB:
        L2). Two threads give main's tile (half the vertices); a call at more threads than a default tile was built for
        warns once (:meth:`_more_threads`)."""
        if tile is not None:
            return int(tile)
        th = max(1, int(torch.get_num_threads() if threads is None else threads))
        part = -(-V // th)
        return min(cls.TILE_MAX, max(cls.BLOCK, -(-part // cls.BLOCK) * cls.BLOCK))

    @classmethod
    def _count_chunk(cls, rows, nnz: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Construction pass 1 over a slice of rows (``_Rows``): its kernel values (:meth:`_kernel_values`),
        the nonzero count per Haar column added to ``nnz [P]`` int64 and Σ over its entries of mean_c |T̂|
        to ``weights [P]`` float64 (in place, entries in row-major order: the same sums as one pass over all
        rows). → ``(q3 [k, CT, K]`` the stored values the kernel reads, ``scale [k, CT]`` float32)."""
        _, vals3, q3, scale, _ = cls._kernel_values(rows)
        src = torch.nonzero((q3 != 0).any(1).reshape(-1)).flatten()  # the entries some channel keeps
        col = rows.aux["index"].reshape(-1)[src].long()
        nnz += torch.bincount(col, minlength=nnz.numel())
        weights.index_add_(0, col, vals3.abs().mean(1).reshape(-1)[src].to(torch.float64))
        return q3, scale

    def _place_chunk(self, q3: torch.Tensor, index: torch.Tensor, a: int, is_dense: torch.Tensor
                     ) -> tuple[torch.Tensor, torch.Tensor]:
        """Construction pass 2 over rows ``a:a+k`` (``q3 [k, CT, K]`` their kernel values, ``index [k, K]``):
        the dense columns' entries written into :attr:`dense`, the sparse ones gathered into their 8-vertex
        blocks. → ``(key [nb] int64`` the blocks' sorted keys (tile, column, block), ``bvals [nb, CT, 8]``)."""
        k, CT, K = q3.shape
        src = torch.nonzero((q3 != 0).any(1).reshape(-1)).flatten()
        col = index.reshape(-1)[src].long()
        row = src // K + a
        qk = q3.permute(0, 2, 1).reshape(k * K, CT)[src]  # [E, CT] each entry's stored values
        del src
        in_dense = is_dense[col]
        dv = row[in_dense]
        self.dense[dv // self.BLOCK, self.dslot[col[in_dense]], :, dv % self.BLOCK] = qk[in_dense]
        del dv
        out = ~in_dense
        sr, sc_, sv = row[out], col[out], qk[out]
        del row, col, qk, in_dense, out
        nb8 = -(-self.V // self.SUB)
        key = ((sr // self.TV) * self.P + sc_) * nb8 + sr // self.SUB
        ukey, inv = torch.unique(key, sorted=True, return_inverse=True)
        del key, sc_
        bvals = torch.zeros(ukey.numel(), CT, self.SUB, dtype=q3.dtype)
        bvals[inv, :, sr % self.SUB] = sv
        return ukey, bvals

    def __init__(self, transfer, dense_min: float | None = None, tile: int | None = None, threads: int | None = None,
                 row_min: float | None = None, layouts: str = "auto", arith: str = "auto", dense_order="column"):
        if getattr(transfer, "kind", None) != "wavelet":
            raise ValueError(f"WaveletRelighter needs a transfer of kind 'wavelet'; got {getattr(transfer, 'kind', describe(transfer))!r}")
        if layouts not in ("auto", "both", "column"):
            raise ValueError(f"layouts={layouts!r}; accepted: 'auto' (row-major copy on first need), 'both', 'column'")
        check_arith(arith, "arith")
        P0 = 6 * int(transfer.meta["res"]) ** 2
        dense_order = self._check_dense_order(dense_order, P0)
        self.layouts = layouts
        self.arith = arith
        self._fd = 0  # FDENSE when arith='float' and the bound build has the VNNI loop (_kernel)
        self._vnni = False  # the bound build has the VNNI dense loop (_kernel)
        self.huge_pages = io.huge_pages_enabled()  # PRT_TORCH_HUGEPAGES, read once per relighter
        self.transfer = transfer
        idx_all = transfer.aux["index"]
        self.CT = CT = 1 if transfer.data.ndim == 2 else int(transfer.data.shape[1])
        V, K = idx_all.shape
        self.V, self.K = V, K
        self.res = int(transfer.meta["res"])
        self.P = P = 6 * self.res * self.res
        # built in chunks of rows (each slice's kernel values, entries and keys freed before the next: the peak is the
        # layout plus one chunk's temporaries, measured in reports/benchmarks/wavelet_build.md); pass 1: the kernel's
        # values, the nonzero count and mean |T̂| per column (dense or sparse needs every row's count)
        step = self._build_rows_per_chunk(K, CT)
        nnz = torch.zeros(P, dtype=torch.int64)
        self.weights = torch.zeros(P, dtype=torch.float64)
        qs, scales = [], []
        for a in range(0, V, step):
            q3c, scc = self._count_chunk(_Rows(transfer.data, transfer.meta, transfer.aux, a, a + step), nnz, self.weights)
            qs.append(q3c), scales.append(scc)
        self.weights /= max(V, 1)
        self.scale = scales[0] if len(scales) == 1 else torch.cat(scales)
        del scales
        self.nnz = nnz.to(torch.int32)  # [P] nonzero coefficients per column (≤ V < 2^31)
        self.albedo = transfer.mesh.albedo.to(torch.float32)
        if transfer.meta.get("albedo_folded") or CT > 1:
            self.albedo = torch.ones_like(self.albedo)
        dtype = qs[0].dtype if qs else torch.float32
        b = dtype.itemsize
        self.dense_min = self.default_dense_min(b, arith=arith) if dense_min is None else float(dense_min)
        is_dense = self.nnz >= max(self.dense_min * V, 1)
        self.dslot = torch.full((P,), -1, dtype=torch.int32)  # [P] the column's dense slot or -1 (int32: Pd ≤ P = 6R²)
        dcols = self._dense_slots(torch.nonzero(is_dense).flatten(), dense_order)  # [Pd] the columns in slot order
        self.dslot[dcols] = torch.arange(dcols.numel(), dtype=torch.int32)
        self.dense_order = dense_order if isinstance(dense_order, str) else "columns"
        self.Pd = Pd = int(dcols.numel())
        nb = -(-V // self.BLOCK)
        # in memory advised for 2 MiB pages from 2 MiB up (io.hugepage_zeros; PRT_TORCH_HUGEPAGES=0: torch's buffer), written
        # in place below: a light's dense terms read a few scattered 64-byte lines per block, each a new 4 KB page once
        # the layout outgrows the L2 (TLB misses; reports/benchmarks/wavelet_hugepages.md)
        self.dense = io.hugepage_zeros((nb, max(Pd, 1), CT, self.BLOCK), dtype, huge=self.huge_pages)
        # block-sparse columns, tile-major: (tile, column, 8-vertex block) ascending
        # default (_tile): one tile per thread the relighter is built for, of at most 4096 vertices (a tile's scratch,
        # 64 KB, in L2): every (tile, sparse term) pair costs a pointer pair and a loop exit, measured at ~40% of the
        # sparse part's time with four tiles on the 2251-vertex blocker scene (reports/benchmarks/wavelet.md)
        TV = self._tile(V, tile, threads)
        if TV % self.BLOCK or TV < self.BLOCK:
            raise ValueError(f"tile={TV}; accepted: a positive multiple of {self.BLOCK}")
        self.TV, self.NT = TV, -(-V // TV)
        # the threads the default tile was built for (None: an explicit tile): a call at more threads than that, whose
        # own default would hold more tiles, warns once (_more_threads); _th_seen the last thread count checked
        self._th_built = None if tile is not None else max(1, int(torch.get_num_threads() if threads is None else threads))
        self._th_seen = self._th_built
        self._th_warned = False
        # pass 2: each chunk's entries into the dense columns and its sparse blocks (chunks of whole 8-vertex blocks:
        # a block lies in one chunk; the chunks' sorted keys merged by one sort of the blocks' keys)
        keys, bvs = [], []
        for i, a in enumerate(range(0, V, step)):
            k, bv = self._place_chunk(qs[i], idx_all[a:a + step], a, is_dense)
            qs[i] = None  # the chunk's kernel values: dead once placed
            keys.append(k), bvs.append(bv)
        del qs
        ukey = keys[0] if len(keys) == 1 else torch.cat(keys)
        bvals = bvs[0] if len(bvs) == 1 else torch.cat(bvs)
        del keys, bvs
        if len(range(0, V, step)) > 1:
            ukey, order = torch.sort(ukey)
            bvals = bvals[order]
            del order
        self.bvals = bvals
        NB = int(ukey.numel())
        P, nb8 = self.P, -(-V // self.SUB)
        tile_b, col_b, blk_b = ukey // (P * nb8), (ukey // nb8) % P, ukey % nb8
        del ukey
        self.bofs = ((blk_b - tile_b * (TV // self.SUB)) * (4 * self.SUB * 4)).to(torch.int32)  # 4 channels x 8 floats
        self.NB = NB
        self.rptr = self.rcol = self.rvals = None  # the row-major copy: _build_rows (layouts)
        self.row_min = self.default_row_min() if row_min is None else float(row_min)
        cnt = torch.bincount(tile_b * P + col_b, minlength=self.NT * P).reshape(self.NT, P)
        self.tbase = torch.zeros(self.NT, dtype=torch.int64)
        self.tbase[1:] = torch.cumsum(cnt.sum(1), 0)[:-1]
        tptr = torch.zeros(self.NT, P + 1, dtype=torch.int64)
        tptr[:, 1:] = torch.cumsum(cnt, 1)
        if NB and int(tptr[:, -1].max()) >= 2 ** 31:
            raise ValueError(f"a tile of {TV} vertices holds {int(tptr[:, -1].max())} sparse blocks; accepted: < 2^31 (a smaller tile)")
        self.tptr = tptr.to(torch.int32).contiguous()
        self.bcount = cnt.to(torch.int32)  # [NT, P] sparse blocks per tile and column (int32: < 2^31, checked above)
        self._rows_used = self.layouts != "column" and self.row_min <= 1  # the kernel may take the row-major pass
        self._cblk = cnt.sum(0).to(torch.int32).contiguous()  # [P] sparse blocks per column (the kernel's row/column choice)
        self.MT = max(1, min(self.NT, os.cpu_count() or 1))
        self.threads = threads
        self._f: dict = {}  # the kernel's factor per (C, albedo): (tensor, C argument), _kfactor
        self._f_full: dict = {}  # [V, CO] where the kernel's is one per vertex: _factor (torch path, gradients)
        self._acc = torch.empty(self.MT, TV // self.SUB, 4, self.SUB, dtype=torch.float32)  # the kernel's scratch, per thread (+ a dummy block)
        # the AVX-512 builds' own scratch, zero between calls, and its touched map (a byte per 32-vertex block, sized
        # per 8): kernels/wavelet.c's zacc / tmark (the AVX2 build, which may share this layout, zeroes _acc instead)
        self._zacc = torch.zeros(self.MT, TV // self.SUB, 4, self.SUB, dtype=torch.float32)
        self._tmark = torch.zeros(self.MT, TV // self.SUB, dtype=torch.uint8)
        self._wk = torch.empty(P, dtype=torch.int64)  # the light's terms split into dense / sparse
        self._lw = torch.empty(P, 4, dtype=torch.float32)
        self.dcol = dcols.contiguous()  # [Pd] the dense slot's column (ascending only with dense_order='column')
        self.cls = torch.where(is_dense, 2, (self.nnz > 0).to(torch.int64)).to(torch.uint8)  # [P] 0 empty, 1 sparse, 2 dense
        self._mark = torch.empty(P, dtype=torch.uint8)  # the light's columns: 1 sparse, 2 dense
        self._lp = torch.zeros(P, 4, dtype=torch.float32)  # the light per column (zero between the kernel's calls)
        self._native = None
        self._dtmax = None  # [Pd] int32 each dense column's largest stored magnitude (16-bit: built with the kernel's layout)
        self._dnorm = None  # [Pd + 1] float64 the dense columns' L2 norms of scale x T, then ||scale|| (_dense_norms)
        if self.layouts == "both":
            self._build_rows()

    #: ``dense_order``'s names (a tensor of Haar columns is accepted too: :meth:`_dense_slots`)
    DENSE_ORDERS = ("column", "weight", "level")

    @classmethod
    def _check_dense_order(cls, value, P: int):
        """``dense_order`` checked before any work: one of :attr:`DENSE_ORDERS`, or Haar columns (a 1-D integer
        tensor or sequence of distinct values in [0, P)) returned as an int64 tensor; one ``ValueError`` line
        naming the value and what is accepted otherwise."""
        if isinstance(value, str):
            if value not in cls.DENSE_ORDERS:
                raise ValueError(f"dense_order={value!r}; accepted: one of {cls.DENSE_ORDERS} or a 1-D tensor of "
                                 f"distinct Haar columns in [0, {P})")
            return value
        try:
            t = torch.as_tensor(value)
        except (TypeError, ValueError, RuntimeError):
            t = None
        if (t is None or t.ndim != 1 or t.dtype.is_floating_point or t.dtype.is_complex or t.dtype == torch.bool
                or (t.numel() and (int(t.min()) < 0 or int(t.max()) >= P))
                or int(torch.unique(t).numel()) != t.numel()):
            raise ValueError(f"dense_order={describe(value)}; accepted: one of {cls.DENSE_ORDERS} or a 1-D tensor of "
                             f"distinct Haar columns in [0, {P})")
        return t.long()

    def _dense_slots(self, dcols: torch.Tensor, order) -> torch.Tensor:
        """The dense columns ``dcols [Pd]`` (int64, ascending) in slot order under ``order`` (``dense_order``):
        ``'column'`` ascending column (the kernel's W16 listing then reads each block's lines at ascending addresses);
        ``'weight'`` descending transport weight (:attr:`weights`, ties by column); ``'level'`` coarse Haar levels first
        (:func:`~prt_torch.lighting.haar.haar_levels`, then column); a tensor of Haar columns: those of them that are
        dense first, in the tensor's order (e.g. a light's transport-weighted ranking, ``light(spec, P)[0]``: every
        N of that light then reads a prefix of each block's slots, adjacent lines), the rest by column. A permutation
        of ``dcols`` → int64 ``[Pd]``."""
        if isinstance(order, str):
            if order == "column":
                return dcols
            if order == "weight":
                key = self.weights[dcols]
                return dcols[torch.argsort(-key, stable=True)]
            from .lighting.haar import haar_levels
            return dcols[torch.argsort(haar_levels(self.res)[dcols], stable=True)]
        rank = torch.full((self.P,), order.numel(), dtype=torch.int64)
        rank[order] = torch.arange(order.numel())
        return dcols[torch.argsort(rank[dcols], stable=True)]

    def reorder_dense(self, order) -> "WaveletRelighter":
        """Renumber the dense slots in place to ``order`` (``dense_order``'s values: :meth:`_dense_slots`) — e.g. when a
        render loop moves to another environment, its ranking ``self.light(spec, self.P)[0]`` — without rebuilding the
        relighter: the dense values (one temporary copy of ``dense``), ``dslot``, ``dcol`` and the kernel's per-slot
        column maxima and norms are permuted in their own buffers, so the kernel's layout and every :meth:`prepared`
        call stay valid (not while a call runs: one call at a time per layout, as always). The result is the layout a
        relighter built with ``dense_order=order`` holds. Returns self."""
        order = self._check_dense_order(order, self.P)
        Pd = self.Pd
        new = self._dense_slots(torch.sort(self.dcol).values, order)  # [Pd] the dense columns in their new slot order
        old = self.dslot[new].long()  # each one's slot now
        if Pd:
            self.dense[:, :Pd].copy_(self.dense[:, old].clone())
            self.dslot[new] = torch.arange(Pd, dtype=torch.int32)
            self.dcol.copy_(new)
            if self._dtmax is not None:
                self._dtmax.copy_(self._dtmax[old].clone())
            if self._dnorm is not None:
                self._dnorm[:Pd].copy_(self._dnorm[:Pd][old].clone())
        self.dense_order = order if isinstance(order, str) else "columns"
        return self

    def _build_rows(self) -> None:
        """The row-major copy of the sparse blocks (``rptr [4·ceil(V/32)+1]`` int64: each 8-vertex block's
        first entry; ``rcol [NB]`` int32 the entry's column; ``rvals [NB, CT, 8]`` the stored values; by
        8-vertex block, then column), rebuilt from the column-major arrays (blocks ordered by tile, column,
        8-vertex block: the tile and column of each from :attr:`bcount`, the block from ``bofs``), and
        written into the kernel's layout when it exists. Once; a no-op after."""
        if self.rptr is not None:
            return
        P, NT, nb, NB = self.P, self.NT, -(-self.V // self.BLOCK), self.NB
        i32 = torch.int32
        col_b = torch.repeat_interleave(torch.arange(P, dtype=i32).repeat(NT), self.bcount.reshape(-1), output_size=NB)
        tile_b = torch.repeat_interleave(torch.arange(NT, dtype=i32), self.bcount.sum(1), output_size=NB)
        blk_b = tile_b * (self.TV // self.SUB) + (self.bofs >> 7)  # bofs: the block's 128-byte accumulator in its tile
        # a block's 8 vertices lie in one tile and, within a tile, the blocks are in column order: a stable sort by
        # block alone gives (block, column) order (measured 0.37 against 0.85 ms for the argsort of the pair's key)
        order = torch.sort(blk_b, stable=True).indices
        rcol = col_b[order].contiguous()
        # the [CT, 8] values (8·CT·b bytes: a multiple of 8) moved as int64 words: 3.4x faster than the gather of rows
        rvals = torch.index_select(self.bvals.reshape(NB, self.CT * self.SUB).view(torch.int64), 0, order).view(
            self.bvals.dtype).reshape(self.bvals.shape)
        rptr = torch.zeros(4 * nb + 1, dtype=torch.int64)  # [4 ceil(V/32) + 1]: every dense block's four
        rptr[1:] = torch.cumsum(torch.bincount(blk_b, minlength=4 * nb), 0)
        self.rcol, self.rvals, self.rptr = rcol, rvals, rptr
        if self._native is not None:  # the layout's three fields, in place (the bound kernel keeps its address)
            self._layout[20:23] = torch.tensor([rptr.data_ptr(), rcol.data_ptr(), rvals.data_ptr()])

    def reference_rows(self, a: int = 0, b: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The kept coefficients of rows ``a:b`` as the reference paths read them (``relight.wavelet_dense``,
        harness/trade.py's SH projection): ``(index [k, K]`` int64, ``values [k, K]`` — ``[k, CT, K]`` coloured —
        float32, the values relit with: re-quantised as the kernel's when the transfer has a scale per Haar level
        — a coloured one's too: before mem10 its ``values`` were the stored values dequantised, up to one 16-bit
        step of the vertex's largest value away from what the kernel relights)``, derived from the stored transfer at each call
        (not held: the relighter keeps only the kernel's layout). Rows are independent: a slice equals the
        whole's rows."""
        tr = self.transfer
        b = self.V if b is None else b
        _, vals3, _, _, _ = self._kernel_values(_Rows(tr.data, tr.meta, tr.aux, a, b))
        return tr.aux["index"][a:b].long(), (vals3 if self.CT > 1 else vals3[:, 0])

    @property
    def index(self) -> torch.Tensor:
        """``[V, K]`` int64 every vertex's kept Haar indices (:meth:`reference_rows`; a new tensor per access)."""
        return self.transfer.aux["index"].long()

    @property
    def values(self) -> torch.Tensor:
        """``[V, K]`` / ``[V, CT, K]`` float32 the values relit with (:meth:`reference_rows`; a new tensor per access)."""
        return self.reference_rows()[1]

    def held_bytes(self) -> dict:
        """Bytes of the kernel's arrays this relighter holds, by part: ``dense`` (the dense columns),
        ``column`` (the column-major sparse blocks: ``bvals``, ``bofs``, ``tptr``, ``tbase``), ``row`` (the
        row-major copy, 0 while not built), ``other`` (per-column tables, the factor cache and the
        kernel's scratch), ``total``; divide by :attr:`V` for bytes per vertex: everything it holds besides the
        transfer itself (``values``/``index``, the reference paths' float32 values and int64 indices, are derived
        from the transfer on access, :meth:`reference_rows`, not held)."""
        def nb(*ts):
            return sum(t.numel() * t.element_size() for t in ts if t is not None)
        parts = {"dense": nb(self.dense), "column": nb(self.bvals, self.bofs, self.tptr, self.tbase),
                 "row": nb(self.rptr, self.rcol, self.rvals),
                 "other": nb(self.dslot, self.bcount, self._cblk, self._acc, self._zacc, self._tmark, self._dtmax, self._dnorm,
                             self._wk,
                             self._lw,
                             self.dcol, self.cls, self._mark, self._lp, self.scale, self.albedo, self.nnz, self.weights,
                             *(f for f, _ in self._f.values()), *self._f_full.values())}
        parts["total"] = sum(parts.values())
        return parts

    @classmethod
    def estimate_bytes(cls, path, layouts: str = "auto", dense_min: float | None = None, tile: int | None = None,
                       light_channels: int = 3, chunk: int | None = None, exact: bool = True, light=None,
                       terms: int | None = None, selection: str = "transport", row_min: float | None = None,
                       supersample: int = 4, arith: str = "auto", threads: int | None = None) -> dict:
        """What a relighter of the wavelet transfer file ``path`` will hold, without building it: the layout
        arithmetic of ``__init__`` and :meth:`_build_rows` on the counts it depends on — the nonzero
        coefficients per Haar column (dense or sparse: ``dense_min``), the distinct (tile, column,
        8-vertex block) triples of the sparse ones and their number per column — counted in one pass over ``chunk``
        rows at a time (default: the construction's chunk, :meth:`_build_rows_per_chunk`; a multiple of 8)
        (``data`` and ``aux.index`` memory-mapped, each slice through :meth:`_count_chunk`, whose rows are
        independent: the counts are exact, and so are the transport weights; it holds a ``[V, K]`` bool mask and one
        slice's values).
        Returns :meth:`held_bytes`' parts after one relight by a light, plus
        ``build`` (the construction's temporaries at its peak above what it keeps — built in chunks of rows
        (:attr:`BUILD_CHUNK_BYTES`): the re-quantised kernel values of every row, one chunk's entry lists and
        keys, the merge of the chunks' sparse blocks; a bound from ``__init__``'s live tensors, checked against
        a measured peak in tests/test_relight_wavelet_plan.py) and the counts ``V, K, CT, P, E`` (nonzero entries), ``Es``
        (sparse entries), ``Pd``, ``NB``, and ``row_pass`` (below).

        ``row``, the row-major copy: 0 with ``layouts='column'``, counted with ``'both'``; with ``'auto'`` (built for
        the first light that takes the row-major pass, :meth:`bytes_read`) it follows ``light`` — a spec as
        :meth:`light` takes it (with ``terms``, ``selection``, ``supersample``: rasterised on the cube at the file's R
        after the count, its terms selected with the counted transport weights, exactly as the relighter will): counted
        when that light's sparse columns hold at least ``row_min`` (default :meth:`default_row_min`, this process's
        build) of the sparse blocks (``row_pass`` True; ``row_share``: the share they hold; ``row_min``: the
        threshold), else 0 (``row_pass`` False; e.g. a light with few nonzero Haar terms, such as the studio's
        softboxes on black: ``lighting.haar.select_terms``). Without a light (``row_pass`` None) it is counted, an upper
        bound whatever the light: the estimate never counts less than the relighter will hold.
        ``dense_min`` defaults as a relighter of ``arith`` would (:meth:`default_dense_min`); ``tile`` and ``threads``
        as the relighter takes them (:meth:`_tile`: with ``tile=None`` the tile follows ``threads``, None: torch's
        thread count now). The cached factor
        is for ``light_channels`` channels (the light's own with ``light``), in the form the file's albedo gives it
        (:meth:`_factor_form`: ``[V + 4]`` for a grey or uniform albedo, else ``[V, CO]``; ``exact=False``: ``[V, CO]``).
        The C kernel's choice: the torch path
        (``PRT_TORCH_NATIVE=0``, no compiler) never builds the copy, so it holds less.

        ``exact=False`` reads the header alone and returns an upper bound
        of every part (every coefficient kept, each in a dense column as far as ``dense_min`` allows and in
        a sparse block of its own, the row-major copy counted whatever ``light``; ``'exact': False``): what
        ``prt relight`` checks first, counting only when the bound does not fit its budget."""
        if layouts not in ("auto", "both", "column"):
            raise ValueError(f"layouts={layouts!r}; accepted: 'auto' (row-major copy on first need), 'both', 'column'")
        hd = io.describe(path)  # the header: shapes and dtypes, nothing read
        if hd["meta"].get("kind") != "transfer/wavelet":
            raise ValueError(f"{str(path)!r} holds kind={hd['meta'].get('kind')!r}; accepted: a wavelet transfer (transfer/wavelet)")
        res = int(hd["meta"]["res"])
        P = 6 * res * res
        V, K = (int(d) for d in hd["tensors"]["aux.index"]["shape"])
        dshape, dtype = hd["tensors"]["data"]["shape"], hd["tensors"]["data"]["dtype"]
        CT = 1 if len(dshape) == 2 else int(dshape[1])
        stored = {"I8": 1, "I16": 2}.get(dtype)  # quantised values' bytes; None: float
        # the relighter's tile (TV) and the counts, as __init__ derives them
        TV = cls._tile(V, tile, threads)
        rmin = cls.default_row_min() if row_min is None else float(row_min)
        permille = cls._row_permille(rmin, layouts != "column" and rmin <= 1)  # as __init__'s _rows_used
        may_rows = layouts == "both" or permille <= 1000  # the relighter may hold the row-major copy
        if not exact:  # the header's bound: b from the stored dtype (a scale per level: re-quantised to 16 bits)
            per_level = stored is not None and len(hd["tensors"]["aux.scale"]["shape"]) == (3 if CT > 1 else 2)
            b = 2 if per_level else (stored or 4)
            dmin = cls.default_dense_min(b, arith=arith) if dense_min is None else float(dense_min)
            E = V * K
            Pd = min(P, E // max(math.ceil(dmin * V), 1)) if dmin <= 1 else 0
            return cls._held_estimate(V, K, CT, P, b, TV, may_rows, light_channels, E, E, Pd, E, b != stored, exact=False)
        t, meta = io.load_mapped(path, mapped=("data", "aux.index"), expect_kind="transfer/wavelet")
        aux = {"index": t["aux.index"], "scale": t["aux.scale"]}
        nb8 = -(-V // cls.SUB)
        # whole 8-vertex blocks per slice: a sparse block never spans two slices (its key names its tile and block)
        step = cls._build_rows_per_chunk(K, CT) if chunk is None else max(cls.SUB, int(chunk) // cls.SUB * cls.SUB)
        nnz = torch.zeros(P, dtype=torch.int64)
        weights = torch.zeros(P, dtype=torch.float64)
        nz = torch.empty(V, K, dtype=torch.bool)  # [V, K] the vertex keeps coefficient k in some channel (1 B each)
        b = 4
        for a in range(0, V, step):  # __init__'s pass 1: the kernel values, nnz and the transport weights per column
            q3, _ = cls._count_chunk(_Rows(t["data"], meta, aux, a, min(V, a + step)), nnz, weights)
            b = q3.element_size()
            nz[a:a + step] = (q3 != 0).any(1)
        weights /= max(V, 1)
        dmin = cls.default_dense_min(b, arith=arith) if dense_min is None else float(dense_min)
        is_dense = nnz >= max(dmin * V, 1)
        Pd, E = int(is_dense.sum()), int(nnz.sum())
        cblk = torch.zeros(P, dtype=torch.int64)  # [P] sparse blocks per column (the kernel's row/column choice)
        for a in range(0, V, step):
            idx = t["aux.index"][a:a + step].long()
            keep = nz[a:a + step] & ~is_dense[idx]
            row = torch.nonzero(keep)[:, 0] + a
            key = torch.unique(((row // TV) * P + idx[keep]) * nb8 + row // cls.SUB)
            cblk += torch.bincount((key // nb8) % P, minlength=P)
        NB = int(cblk.sum())
        Es = E - int(nnz[is_dense].sum())
        rows, row_pass = may_rows, None
        if light is not None and layouts == "auto":  # the light the relighter will relight first: its pass decides
            li, lv, _ = wavelet_light(light, res, terms, selection, weights if selection == "transport" else None,
                                      supersample)
            light_channels = int(lv.shape[0])
            ls = torch.unique(li)
            ls = ls[~is_dense[ls] & (nnz[ls] > 0)]  # its sparse columns some vertex keeps
            rows = row_pass = cls._takes_rows(int(cblk[ls].sum()), NB, permille)
            share = int(cblk[ls].sum()) / max(NB, 1)
        elif light is not None:
            row_pass = layouts == "both"
        CO = max(light_channels, CT)  # the factor's form for the relight counted, from the file's albedo as __init__ reads it
        alb = None if meta.get("albedo_folded") or CT > 1 else t["mesh.albedo"].to(torch.float32)
        form = cls._factor_form(None if alb is None else (alb[:, :CO] if CO > 1 else alb[:, :1]), CT, CO)
        est = cls._held_estimate(V, K, CT, P, b, TV, rows, light_channels, E, Es, Pd, NB, b != stored, factor_form=form)
        est["row_pass"] = row_pass
        est["row_min"] = rmin
        if light is not None and layouts == "auto":
            est["row_share"] = share
        return est

    @classmethod
    def _held_estimate(cls, V, K, CT, P, b, TV, with_rows, light_channels, E, Es, Pd, NB, requant, exact=True,
                       factor_form: str = "channel") -> dict:
        """:meth:`estimate_bytes`' arithmetic from the counts (``b`` the kernel values' bytes, ``TV`` the tile,
        ``with_rows``: the row-major copy counted, ``requant``: the kernel's values are not the stored ones — re-quantised
        to 16 bits, or float; ``factor_form``: :meth:`_factor_form`'s, the cached factor ``[V + 4]`` unless
        ``'channel'``, ``[V, CO]``, the larger)."""
        NT, nb = -(-V // TV), -(-V // cls.BLOCK)
        MT = max(1, min(NT, os.cpu_count() or 1))
        CO = max(light_channels, CT)
        blk = NB * CT * cls.SUB * b
        parts = {"dense": nb * max(Pd, 1) * CT * cls.BLOCK * b,
                 "column": blk + 4 * NB + 4 * NT * (P + 1) + 8 * NT,
                 "row": (4 * nb + 1) * 8 + 4 * NB + blk if with_rows else 0,
                 # dslot, _cblk, nnz int32; bcount [NT, P] int32; _acc, _zacc float32, _tmark uint8; _wk int64; _lw, _lp [P, 4] float32; dcol int64;
                 # cls, _mark uint8; scale [V, CT], albedo [V, 3], the cached factor [V, CO] or [V + 4] float32
                 # (_kfactor); weights float64; _dtmax [Pd] int32 with 16-bit kernel values (once the kernel is bound),
                 # _dnorm [Pd + 1] float64 with 16-bit values on a grey transfer (the same)
                 "other": 12 * P + 4 * NT * P + MT * (TV // cls.SUB) * (2 * 4 * cls.SUB * 4 + 1) + 8 * P + 32 * P + 8 * Pd + 2 * P
                 + 4 * V * CT + 12 * V + (4 * V * CO if factor_form == "channel" else 4 * (V + 4)) + 8 * P
                 + (4 * max(Pd, 1) if b == 2 else 0) + (8 * (Pd + 1) if b == 2 and CT == 1 else 0)}
        parts["total"] = sum(parts.values())
        # __init__'s peak above what it keeps (built in chunks of rows): either while placing the chunks — the kernel
        # values of every row (held between the passes when re-quantised or float: a view of the stored values
        # otherwise), one chunk's temporaries (its kernel values, re-quantisation in float64, entry lists, keys and
        # unique's sort: ~40 B per value and 16 B per entry, fitted to the measured peak with a margin — 9.3-9.6 MiB of
        # temporaries on 2251 vertices and 14.9 on 10 585, R = 32, K = 256, against 21-24 from the 60 + 100 B bound before,
        # which the light's rasterisation hid until it was done in blocks) and the blocks placed so far — or while the
        # chunks' block keys are merged (the lists and their concatenation, the sort's keys and permutation, the
        # split into tile, column and block: ~40 B per block) and the blocks re-ordered (two copies of the values)
        rows = min(V, cls._build_rows_per_chunk(K, CT))
        place = (V * CT * K * b if requant else 0) + rows * K * (40 * CT + 16) + 8 * NB + blk
        parts["build"] = max(place, 40 * NB + 2 * blk)
        parts.update(V=V, K=K, CT=CT, P=P, E=E, Es=Es, Pd=Pd, NB=NB, exact=exact, row_pass=None)
        return parts

    def bytes_read(self, light_idx: torch.Tensor, channels: int = 3, albedo: bool = True, factor: bool = True) -> int:
        """Transfer bytes a light with these kept terms reads — the bound's byte count: the selected
        dense columns (32-vertex blocks, zeros included) and, for the selected sparse columns that
        any vertex keeps, either (column-major pass) their 8-vertex blocks (int32 offset + 8·CT
        values, zeros included) and per tile and column its two int32 block pointers, or (row-major
        pass, taken when they hold at least ``row_min`` of the sparse blocks) every sparse block
        (int32 column + 8·CT values) and the int64 row pointers (kernels/wavelet.c's choice); and the
        factor (the quantisation scale × albedo) for a light of ``channels`` channels, :meth:`factor_bytes`
        (``factor=False``: the count before it was included, the transfer's stored coefficients alone)."""
        fb = self.factor_bytes(channels, albedo) if factor else 0
        li = torch.unique(light_idx.long())
        d = self.dslot[li] >= 0
        b = self.bvals.element_size()
        ls = li[~d]
        ls = ls[self.nnz[ls] > 0]
        dense = int(d.sum()) * self.dense.shape[0] * self.BLOCK * self.CT * b
        sb = int(self.bcount[:, ls].sum())
        NR = self.NB
        if self._takes_rows(sb, NR, self._row_permille(self.row_min, self._rows_used)):
            return dense + NR * (4 + self.SUB * self.CT * b) + (4 * self.dense.shape[0] + 1) * 8 + fb
        return dense + sb * (4 + self.SUB * self.CT * b) + self.NT * int(ls.numel()) * 8 + fb

    #: kernels/wavelet.c's ``F1``: the light's channel count ``C | F1`` tells the kernel its factor is one per vertex
    #: (``f [V + 4]``: ``f [V]``, then the output channels' multipliers)
    F1 = 256

    @staticmethod
    def _factor_form(albedo: torch.Tensor | None, CT: int, CO: int) -> str:
        """How the kernel's factor (quantisation scale × albedo) is laid out for ``CO`` output channels of a
        ``CT``-channel transfer, the albedo ``[V, ≥CO]`` float32 applied (None: not applied): ``'vertex'`` one float
        per vertex (``f [V + 4]``, the last four 1: a grey transfer, RGB output — CO = 3: the kernel takes this form
        for three output channels only —, the albedo off or every vertex's channels equal), ``'uniform'`` one float
        per vertex times one colour for all (``f [V + 4]``: the scale, then the albedo's first row: every vertex the
        same colour), ``'channel'`` one per vertex and channel (``f [V, CO]``: a coloured transfer's scale per
        channel, a per-vertex coloured albedo, CO = 2 or 4, or CO = 1, where it is one per vertex anyway)."""
        if CT != 1 or CO != 3 or (albedo is not None and albedo.shape[1] < CO):
            return "channel"
        if albedo is None or albedo.shape[0] == 0:
            return "vertex"
        a = albedo[:, :CO]
        if bool((a == a[:, :1]).all()):
            return "vertex"
        return "uniform" if bool((a == a[:1]).all()) else "channel"

    def _kfactor(self, C: int, albedo: bool) -> tuple[torch.Tensor, int]:
        """The kernel's factor for a light of ``C`` channels (cached per ``(C, albedo)``) and the channel count to
        pass it with: ``(f [V, CO] float32, C)`` — one factor per vertex and output channel, CO = max(C, CT) — or,
        where one per vertex will do (:meth:`_factor_form`), ``(f [V + 4] float32, C | F1)``: ``f[:V]`` the
        factor per vertex, ``f[V:V + CO]`` the output channels' multipliers (1: grey; the uniform albedo's colour),
        the factor of vertex v and channel c being ``fl(f[v] · f[V + c])`` — the same float32 products as the
        ``[V, CO]`` form. The kernel reads all of it once per call (:meth:`factor_bytes`)."""
        key = (C, albedo)
        if key not in self._f:
            CO = max(C, self.CT)
            alb = (self.albedo[:, :CO] if CO > 1 else self.albedo[:, :1]) if albedo else None
            form = self._factor_form(alb, self.CT, CO)
            if form == "channel":
                a = alb if alb is not None else torch.ones(self.V, CO)
                self._f[key] = ((a * self.scale).contiguous(), C)  # scale [V, CT]: CT = 1 broadcasts
            else:
                f = torch.ones(self.V + 4, dtype=torch.float32)
                if form == "vertex":  # the same products as a * scale's columns (all equal)
                    f[:self.V] = self.scale[:, 0] if alb is None else alb[:, 0] * self.scale[:, 0]
                else:
                    f[:self.V] = self.scale[:, 0]
                    f[self.V:self.V + CO] = alb[0]
                self._f[key] = (f, C | self.F1)
        return self._f[key]

    def _factor(self, C: int, albedo: bool) -> torch.Tensor:
        """The factor per vertex and output channel ``[V, CO]`` float32 (quantisation scale × albedo; the torch path,
        :meth:`relight_grad`): :meth:`_kfactor`'s, expanded where it is one per vertex (the same float32 products;
        cached, as callers pass its address to the kernel)."""
        f, Ck = self._kfactor(C, albedo)
        if not Ck & self.F1:
            return f
        key = (C, albedo)
        if key not in self._f_full:  # cached (counted in held_bytes): callers pass its address to the kernel
            CO = max(C, self.CT)
            self._f_full[key] = (f[:self.V, None] * f[self.V:self.V + CO]).contiguous()
        return self._f_full[key]

    def factor_bytes(self, C: int = 3, albedo: bool = True) -> int:
        """Bytes of the factor the kernel reads once per call for a light of ``C`` channels (:meth:`_kfactor`:
        ``4 (V + 4)`` where one per vertex, else ``4 V CO``), counted in :meth:`bytes_read`."""
        f, _ = self._kfactor(C, albedo)
        return f.numel() * f.element_size()

    def touched(self, light_idx: torch.Tensor) -> int:
        """Nonzero transfer coefficients a light with these kept terms reads (Σ_n nnz(column n);
        a coloured transfer's coefficient counts once for its three values)."""
        return int(self.nnz[light_idx.long()].sum())

    def _takes_vnni(self, light_idx: torch.Tensor, light_vals: torch.Tensor, vnni: bool | None = None,
                    arith: str | None = None) -> bool:
        """kernels/wavelet.c's choice of the VNNI dense loop for a call with ``light_idx [N]``, ``light_vals [C, N]``
        float32: the build has it (``vnni``; None: the build this relighter is bound to), ``arith`` (None: this
        relighter's) is ``'auto'``, 16-bit kernel values on a grey transfer (CT = 1), an RGB light whose three channels
        are not bitwise equal at every term (a grey RGB light takes one sum per vertex), and at least :attr:`ZMM_MIN`
        (distinct dense column, 32-vertex block) pairs. The other calls take the float loop (its bits). Not modelled
        here: the kernel's per-call guard, which sends a call whose VNNI L2 bound exceeds the transfer's own to the
        float loop after the light is grouped (``benchmarks/bench_wavelet_madd_micro.vnni_guard`` recomputes it)."""
        if vnni is None:
            self._kernel()
            vnni = self._vnni
        lv = torch.as_tensor(light_vals).to(torch.float32)
        if (not vnni or (self.arith if arith is None else arith) != "auto" or self.dense.dtype != torch.int16
                or self.CT != 1 or lv.shape[0] != 3 or bool((lv[0] == lv[1]).all() and (lv[0] == lv[2]).all())):
            return False
        slots = self.dslot[torch.as_tensor(light_idx).long()]
        nd = int(torch.unique(slots[slots >= 0]).numel())
        return nd > 0 and nd * -(-self.V // self.BLOCK) >= self.ZMM_MIN

    def kernel_path(self) -> dict:
        """:func:`wavelet_kernel_path` of the build this relighter calls, with ``dense`` for its calls under an RGB light
        (unequal channels): ``'int16 vnni'`` where the build has the VNNI loop, ``arith`` is ``'auto'`` and the kernel
        values are 16-bit on a grey transfer (a call with little dense work still takes the 8-lane float loop), else
        ``'float'``; ``arith`` this relighter's."""
        p = dict(wavelet_kernel_path(arith=self.arith))
        if self.dense.dtype != torch.int16 or self.CT != 1 or os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
            p["dense"] = "float"
        return p

    def light(self, spec, terms: int | None = None, selection: str = "transport", supersample: int = 4):
        """:func:`wavelet_light` at this transfer's resolution (``'transport'`` uses :attr:`weights`)."""
        return wavelet_light(spec, self.res, terms, selection, self.weights if selection == "transport" else None,
                             supersample)

    def _dense_norms(self) -> torch.Tensor:
        """The dense columns' L2 norms over the vertices of the quantisation scale times the stored value, then the
        scale's own: float64 ``[Pd + 1]``, ``||scale (.) T_:,k||_2`` for slot k of ``dense`` (a grey transfer: CT = 1;
        ``scale`` [V, 1]) and ``||scale||_2`` — kernels/wavelet.c's ``dnorm``, the VNNI loop's flush groups' weights: the
        output's L2 error of a call is at most sum_G (s_G,c / 2) sum_{k in G} ||f (.) T_:,k||_2 per channel (the triangle
        inequality), and ``||scale|| sum_k |L_k,c| / 2`` is the transfer's own 16-bit bound in the same terms. The
        factor f is the scale times the albedo: the albedo is left out (a per-call option and per channel; grey or
        uniform, a constant per channel on both sides of the kernel's budget). Summed in steps of 32 blocks (1024
        vertices: one float64 temporary of 32 x Pd x 256 bytes, squared in place — 2 MB at Pd = 250, inside what
        ``prt relight``'s memory plan allows for; 256-block steps took 33 MB and broke that plan's 2x check)."""
        nb, Pd = self.dense.shape[0], self.Pd
        s2 = torch.zeros(nb * self.BLOCK, dtype=torch.float64)
        s2[:self.V] = self.scale[:, 0].double() ** 2
        s2 = s2.reshape(nb, self.BLOCK)
        acc = torch.zeros(Pd, dtype=torch.float64)
        step = 32
        for b0 in range(0, nb, step):
            d = self.dense[b0:b0 + step, :Pd, 0, :].double()  # [nb', Pd, 32]
            acc += torch.einsum("bkv,bv->k", d.square_(), s2[b0:b0 + step])
        return torch.cat([acc.sqrt(), s2.sum().sqrt().reshape(1)]).contiguous()

    def _kernel(self):
        """The compiled kernel bound to this transfer's arrays: a function of (N, sel, lv, C, f, out,
        threads) pointers returning the kernel's status; None without a compiler or with PRT_TORCH_NATIVE=0."""
        if os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
            return None
        if self._native is None:
            lib = _wavelet_lib()
            if lib is None:
                return None
            fn = {torch.int8: lib.prt_wavelet_relight_i8, torch.int16: lib.prt_wavelet_relight_i16}.get(
                self.bvals.dtype, lib.prt_wavelet_relight_f32)
            # kernels/wavelet.c's wavelet_layout: the arrays' addresses, built once (kept alive by self); last, each
            # dense column's largest stored magnitude int32 [Pd] for 16-bit values (the VNNI dense loop's
            # column-maximum rule; read by the builds with that loop only), else NULL
            self._dtmax = (self.dense.to(torch.int32).abs().amax(dim=(0, 2, 3)).contiguous()
                           if self.dense.dtype == torch.int16 else None)
            # and the dense columns' L2 norms (the VNNI loop's flush groups: kernels/wavelet.c's dnorm), the same
            # condition on a grey transfer (the VNNI loop's calls), else NULL
            self._dnorm = self._dense_norms() if self.dense.dtype == torch.int16 and self.CT == 1 else None
            self._layout = torch.tensor([self.P, self.Pd, self.V, self.CT, self.TV, self.NT, self.MT,
                                         self.tptr.data_ptr(), self.tbase.data_ptr(), self.bofs.data_ptr(), self.bvals.data_ptr(),
                                         self.dslot.data_ptr(), self.dense.data_ptr(), self._acc.data_ptr(), self._wk.data_ptr(),
                                         self._lw.data_ptr(), self.dcol.data_ptr(), self.cls.data_ptr(), self._mark.data_ptr(), self._lp.data_ptr(),
                                         *(0 if t is None else t.data_ptr() for t in (self.rptr, self.rcol, self.rvals)),
                                         self.NB, self._row_permille(self.row_min, self._rows_used),
                                         self._cblk.data_ptr(), self._zacc.data_ptr(), self._tmark.data_ptr(),
                                         0 if self._dtmax is None else self._dtmax.data_ptr(),
                                         0 if self._dnorm is None else self._dnorm.data_ptr()],
                                        dtype=torch.int64)
            lay = self._layout.data_ptr()
            # the opt-out bit only where the build has the VNNI loop (the others refuse any bit above F1: status 1)
            self._vnni = bool(float_dense_flag(lib))  # the build has the VNNI dense loop
            self._fd = float_dense_flag(lib) if self.arith == "float" else 0
            self._native = functools.partial(fn, lay)
            self._packed = getattr(lib, fn.__name__ + "_packed")  # the same kernel, its arguments in one int64 array
        return self._native

    def prepared(self, light_idx: torch.Tensor, light_vals: torch.Tensor, out: torch.Tensor | None = None,
                 albedo: bool = True):
        """A prepared relighting of one light for a render loop: ``run = relighter.prepared(idx, vals, out)``
        once, then ``run()`` per frame returns ``out`` relit — the same result as ``relighter(idx, vals,
        out=out)``, with the light's and the output's checks, the factor and the kernel's arguments
        (packed once into an int64 array, so ctypes converts one argument per call: ~0.8 µs less than
        the eight it took) done once here, so a call is the C kernel and one Python call
        (~3–4 µs less per call than ``__call__``). The light's values and indices may be changed in
        place between calls (same N); its indices are checked by the kernel at every call (an index
        out of range raises as ``__call__`` does; a changed light that first chooses the row-major pass
        builds that copy inside ``run``, ``layouts='auto'``). Without the kernel, ``run`` calls ``__call__``."""
        li = torch.as_tensor(light_idx).long().contiguous()
        lv = torch.as_tensor(light_vals).to(torch.float32).contiguous()
        o = self(li, lv, out=out, albedo=albedo)  # every check once, and the first result
        kern = self._kernel() if lv.shape[0] <= 4 else None
        if kern is None:
            return lambda: self(li, lv, out=o, albedo=albedo)
        f, Ck = self._kfactor(lv.shape[0], albedo)
        th = torch.get_num_threads() if self.threads is None else self.threads
        if th != self._th_seen:  # checked once here, not per frame
            self._more_threads(th)
        # the kernel's eight arguments packed once into an int64 array: ctypes then converts one argument per call
        # instead of eight (~0.8 us less per call; benchmarks/bench_wavelet_call.py)
        args = torch.tensor([self._layout.data_ptr(), li.numel(), li.data_ptr(), lv.data_ptr(), Ck | self._fd, f.data_ptr(),
                             o.data_ptr(), th], dtype=torch.int64)
        call = functools.partial(self._packed, args.data_ptr())
        held = (li, lv, f, o, args)  # the tensors the pointers address stay alive with the closure

        def run() -> torch.Tensor:
            st = call()
            if st == 3:  # the first light needing the row-major copy
                self._build_rows()
                st = call()
            if st != 0:
                self._check_indices(held[0])
            return o
        return run

    def _more_threads(self, th: int) -> None:
        """A call at ``th`` threads on a default tile built for fewer (``_th_built``): when a relighter built for
        ``th`` would hold more tiles, one warning per relighter — the tiles are the threads' unit of work, so the call
        runs on ``NT`` of its ``th`` threads (at small, one tile on one thread: 0.77-0.94x a two-tile relighter by wall
        clock at two threads, docs/wavelet_kernel_log.md "The tile follows the relighter's threads"). Build it with
        ``threads=th`` (or an explicit ``tile``)."""
        self._th_seen = th
        if self._th_warned or self._th_built is None or th <= self._th_built or self._tile(self.V, None, th) >= self.TV:
            return
        self._th_warned = True
        warnings.warn(f"WaveletRelighter built for threads={self._th_built} ({self.NT} tile{'s' * (self.NT > 1)} of "
                      f"{self.TV} vertices) called at {th} threads: it runs on {self.NT} of them; accepted for "
                      f"{th}-thread calls: WaveletRelighter(..., threads={th})", RuntimeWarning, stacklevel=3)

    def __call__(self, light_idx: torch.Tensor, light_vals: torch.Tensor, out: torch.Tensor | None = None,
                 albedo: bool = True) -> torch.Tensor:
        if torch.is_grad_enabled() and isinstance(light_vals, torch.Tensor) and light_vals.requires_grad:
            if out is not None:
                raise ValueError("out= with light values that require grad; accepted: out=None (autograd cannot write "
                                 "into a reused buffer)")
            return self.relight_grad(light_idx, light_vals, albedo)
        li, lv = light_idx, light_vals  # no conversion on the fast path (int64 indices, float32 values, contiguous)
        if not (type(li) is torch.Tensor and li.dtype == torch.int64 and li.is_contiguous()):
            li = torch.as_tensor(li).long().contiguous()
        if not (type(lv) is torch.Tensor and lv.dtype == torch.float32 and lv.is_contiguous()):
            lv = torch.as_tensor(lv).to(torch.float32).contiguous()
        N = li.numel()
        if lv.ndim != 2 or lv.shape[1] != N or li.ndim != 1:
            raise ValueError(f"light values {tuple(lv.shape)} for indices {tuple(li.shape)}; accepted: indices [N], values [C, N]")
        C = lv.shape[0]
        if self.CT > 1 and C not in (1, self.CT):
            raise ValueError(f"a light of {C} channels for a transfer of {self.CT} colour channels; accepted: 1 or {self.CT}")
        CO = C if C > self.CT else self.CT
        o = torch.empty(self.V, CO, dtype=torch.float32) if out is None else out
        if o.shape != (self.V, CO) or o.dtype != torch.float32 or not o.is_contiguous():
            raise ValueError(f"out {tuple(o.shape)} {o.dtype}; accepted: a contiguous float32 [{self.V}, {CO}]")
        kern = self._native if self._native is not None and os.environ.get("PRT_TORCH_NATIVE") != "0" else (
            self._kernel() if C <= 4 else None)
        if kern is not None:
            fk = self._f.get((C, albedo))
            f, Ck = fk if fk is not None else self._kfactor(C, albedo)
            th = torch.get_num_threads() if self.threads is None else self.threads
            if th != self._th_seen:  # one int compare per call (the check when the thread count changes)
                self._more_threads(th)
            st = kern(N, li.data_ptr(), lv.data_ptr(), Ck | self._fd, f.data_ptr(), o.data_ptr(), th)
            if st == 3:  # the first light needing the row-major copy: built, the call repeated
                self._build_rows()
                st = kern(N, li.data_ptr(), lv.data_ptr(), Ck | self._fd, f.data_ptr(), o.data_ptr(), th)
            if st == 0:
                return o
        self._check_indices(li)
        return self._torch(li, lv, o).mul_(self._factor(C, albedo))

    def float32(self, light_idx: torch.Tensor, light_vals: torch.Tensor, out: torch.Tensor | None = None,
                albedo: bool = True) -> torch.Tensor:
        """:meth:`__call__` with the float32 dense loop whatever ``arith`` (``C | FDENSE`` where the bound build has
        the VNNI loop; the light is not quantised): the harness's exact reference (``Evaluator.reference``, Ng 2003
        eq. 2 over every term), which a relighter of the default ``arith`` would otherwise compute within the VNNI
        loop's bound only. The same arguments, shapes and result as :meth:`__call__`."""
        if self._kernel() is None or not self._vnni or self._fd:
            return self(light_idx, light_vals, out, albedo)
        self._fd = self.FDENSE
        try:
            return self(light_idx, light_vals, out, albedo)
        finally:
            self._fd = 0

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
        if self.CT > 1 and lv.shape[0] not in (1, self.CT):
            raise ValueError(f"a light of {lv.shape[0]} channels for a transfer of {self.CT} colour channels; accepted: 1 or {self.CT}")
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
        """Σ_n L̂[c, n] T̂[v, (c,) n] over the light's terms ``li [N]``, ``lv [C, N]`` in ``dt`` (scale and
        albedo not applied), out of place (differentiable with respect to ``lv``): the dense columns
        as one batched GEMV over the 32-vertex blocks, the sparse blocks gathered and added by one
        ``index_add``. A grey light on a coloured transfer is broadcast. → ``[V, CO]``, CO = max(C, CT)."""
        C = lv.shape[0]
        CO = max(C, self.CT)
        L = (lv if C == CO else lv.expand(CO, -1)).to(dt)  # a grey light on a coloured transfer
        slot = self.dslot[li]
        d = slot >= 0
        if bool(d.any()):
            blocks = self.dense[:, slot[d]].to(dt)  # [nb, Nd, CT, 32]
            if self.CT == 1:
                r = torch.einsum("bnv,cn->bvc", blocks[:, :, 0], L[:, d])
            else:
                r = torch.einsum("bncv,cn->bvc", blocks, L[:, d])
            o = r.reshape(-1, CO)[:self.V]
        else:
            o = L.new_zeros(self.V, CO) * L.sum()  # keeps the graph when no column is dense
        ls, Ls = li[~d], L[:, ~d]
        if ls.numel():
            starts = self.tbase[:, None] + self.tptr[:, ls].long()  # [NT, ns]
            cnt = (self.tptr[:, ls + 1] - self.tptr[:, ls]).long()
            total = int(cnt.sum())
            if total:  # gather the blocks, one index_add
                seg = torch.repeat_interleave(torch.arange(cnt.numel()), cnt.reshape(-1))  # (tile, term) pair of each block
                first = torch.cumsum(cnt.reshape(-1), 0) - cnt.reshape(-1)
                pos = starts.reshape(-1)[seg] + torch.arange(total) - first[seg]
                term, tile = seg % ls.numel(), seg // ls.numel()
                v0 = tile * self.TV + self.bofs[pos].long() // (4 * self.SUB * 4) * self.SUB
                x = self.bvals[pos].to(dt)  # [E, CT, 8]
                add = x.transpose(1, 2) * Ls.T[term][:, None, :]  # [E, 8, CO] (CT = 1 broadcasts)
                rows = (v0[:, None] + torch.arange(self.SUB)).reshape(-1)
                keep = rows < self.V
                o = o.index_add(0, rows[keep], add.reshape(-1, CO)[keep])
        return o


_WAVELET: dict = {}


def _wavelet_lib(isa: str | None = None):
    """The compiled sparse relighting kernel (``prt_torch/kernels/wavelet.c``), or None (torch path). Built with
    the flags of ``PRT_TORCH_KERNEL_ISA`` (``_native.kernel_isa``: ``avx2`` builds the 8-lane AVX2 loops on an
    AVX-512 CPU, ``avx512-256`` AVX-512VL without the 16-lane dense loop; read at the first call, once per
    process, like the relight library's; a value not accepted raises ``ValueError`` naming it), or, with ``isa``
    given, that build (one of ``_native.KERNEL_ISAS``, checked against this CPU the same way; each build loaded
    once per process: ``benchmarks/bench_wavelet_isa.py`` pairs two builds on one layout)."""
    import ctypes
    import os

    if isa is None and os.environ.get("PRT_TORCH_NATIVE", "1") == "0":
        return None
    if isa is None and "lib" in _WAVELET:  # this process's build, read once
        return _WAVELET["lib"]
    from ._native import LIBRARIES, compile_library, kernel_isa, kernel_sources

    if isa is None:
        choice, extra = kernel_isa()  # raises for a bad value before anything is compiled
    else:
        prev = os.environ.get("PRT_TORCH_KERNEL_ISA")
        os.environ["PRT_TORCH_KERNEL_ISA"] = isa
        try:
            choice, extra = kernel_isa()
        finally:
            if prev is None:
                os.environ.pop("PRT_TORCH_KERNEL_ISA", None)
            else:
                os.environ["PRT_TORCH_KERNEL_ISA"] = prev
    key = "lib" if isa is None else f"lib:{choice}"
    if key not in _WAVELET:
        names, flags = LIBRARIES["wavelet"]
        flags = list(flags) + list(extra)
        i64, vp = ctypes.c_int64, ctypes.c_void_p
        sig = [vp, i64, vp, vp, i64, vp, vp, i64]
        lib, why = compile_library("wavelet", kernel_sources(names), flags, {
            "prt_wavelet_relight_f32": sig, "prt_wavelet_relight_i8": sig, "prt_wavelet_relight_i16": sig,
            "prt_wavelet_relight_f32_packed": [vp], "prt_wavelet_relight_i8_packed": [vp],
            "prt_wavelet_relight_i16_packed": [vp], "prt_wavelet_isa": []})
        if lib is not None:
            lib.prt_build = (choice, " ".join(flags))  # wavelet_kernel_path's PRT_TORCH_KERNEL_ISA choice and flags
        _WAVELET[key], _WAVELET["why" if isa is None else f"why:{choice}"] = lib, why
    return _WAVELET[key]


def float_dense_flag(lib) -> int:
    """The bits to or into a call's C for the float dense loop on build ``lib`` (a loaded ``kernels/wavelet.c``):
    ``WaveletRelighter.FDENSE`` where the build has the VNNI dense loop (``prt_wavelet_isa`` bit 64), else 0 (the
    builds without it take the float loop anyway and refuse the bit)."""
    return WaveletRelighter.FDENSE if int(lib.prt_wavelet_isa()) & 64 else 0


def check_arith(value, name: str = "arith") -> str:
    """``value`` if it is one of :attr:`WaveletRelighter.ARITH`, else ``ValueError`` (one line naming ``name``, the
    value and what is accepted)."""
    if value not in WaveletRelighter.ARITH:
        raise ValueError(f"{name}={value!r}; accepted: 'auto' (the build's dense arithmetic: int16 VNNI dot products on a "
                         "CPU with AVX-512 VNNI where the call allows, else float32) or 'float' (the float32 dense loop always)")
    return value


def wavelet_kernel_path(isa: str | None = None, arith: str = "auto") -> dict:
    """Which build of ``kernels/wavelet.c`` relights (a benchmark row names it): ``backend`` (``native``, or
    ``torch`` with ``why``), the build's instruction set as its ``#if`` branches saw it (``isa``: avx512 / avx2 /
    avx / baseline, from ``prt_wavelet_isa``; ``w16``: the dense loop on 16 lanes; ``vnni``: the build has the dense
    loop on AVX-512 VNNI), ``dense``: the dense arithmetic of its 16-bit grey-transfer calls under an RGB light with
    ``arith`` (``'int16 vnni'``: the build has the VNNI loop and ``arith`` is ``'auto'``; ``'float'``: the float32 loop;
    the other calls, and calls with little dense work, always ``'float'``), the ``PRT_TORCH_KERNEL_ISA`` choice, the
    compiler flags, this CPU's own ISA (``cpu_isa``) and ``path`` in words. ``isa``: that build (:func:`_wavelet_lib`)
    instead of this process's."""
    from ._native import cpu_isa

    check_arith(arith)
    lib = _wavelet_lib(isa)
    out = {"backend": "native" if lib is not None else "torch", "cpu_isa": cpu_isa()}
    if lib is None:
        out["why"] = _WAVELET.get("why") or "disabled by PRT_TORCH_NATIVE=0"
        out["path"] = "torch formulation"
        out["dense"] = "float"
        return out
    bits = int(lib.prt_wavelet_isa())
    choice, flags = lib.prt_build
    name = "avx512" if bits & 8 else "avx2" if bits & 2 and bits & 4 else "avx" if bits & 1 else "baseline"
    w16, vnni = bool(bits & 32), bool(bits & 64)
    dense = "int16 vnni" if vnni and arith == "auto" else "float"
    vec = ("AVX-512" if bits & 8 else "AVX2") if bits & 2 else "portable vector"
    out.update({"isa": name, "w16": w16, "vnni": vnni, "dense": dense, "isa_choice": choice, "flags": flags,
                "path": (f"dense loop on 16 lanes (AVX-512, zmm; {'int16 VNNI dot products' if dense != 'float' else 'float32'} "
                         "for 16-bit RGB calls), sparse blocks and output on 8 lanes" if w16 else
                         f"dense loop, sparse blocks and output on 8 lanes ({vec} code)")})
    return out
