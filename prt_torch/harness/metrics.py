"""Error metrics of the harness, each a small function with its definition.

* Squared error over the signal (Sloan 2003 §4): SE = Σ_p ‖x_p − x̂_p‖², relative error
  SE / Σ_p ‖x_p‖².
* Random-lighting PSNR (Lehtinen & Kautz 2003, eq. 11): PSNR_avg = −10 log10 E{‖L − L̂‖²},
  the expectation over lighting vectors l uniform on the unit sphere of R^{n_in} and over
  points p, with L = M_p l the per-point output vector. For a linear transfer this
  expectation is exact in closed form: E_l{‖Δ_p l‖²} = ‖Δ_p‖_F² / n_in, so
  PSNR_avg = −10 log10(SE / (P·n_in)); the harness also reports the Monte Carlo estimate over
  the configured number of random lights (both must agree within sampling error).
* Image / per-vertex PSNR against the uncompressed result: 10 log10(peak² / MSE) with
  peak = max of the reference radiance over points and channels, MSE over points × channels.
"""
from __future__ import annotations

import math

import torch

from .timing import torch_threads

__all__ = ["squared_error", "psnr_from_mse", "psnr_vs_reference", "random_unit_vectors", "random_light_psnr", "random_light_psnr_analytic"]


#: elements of one row block of the float64 temporaries in :func:`squared_error` and :func:`random_light_psnr`
#: (32 MiB of float64): a [10242, 16128] transport table made 1.3 GB temporaries at once before
BLOCK_ELEMENTS = 1 << 22


def _row_blocks(x: torch.Tensor):
    """Row slices of ``x [P, D]`` of about :data:`BLOCK_ELEMENTS` elements."""
    step = max(1, BLOCK_ELEMENTS // max(1, x.shape[1] if x.ndim > 1 else 1))
    for i in range(0, x.shape[0], step):
        yield slice(i, i + step)


def squared_error(x: torch.Tensor, x_hat: torch.Tensor) -> tuple[float, float]:
    """(SE, relative SE) of ``x_hat [P, D]`` against ``x [P, D]``, accumulated in float64 (row
    blocks of :data:`BLOCK_ELEMENTS`: no table-sized temporaries)."""
    if x.shape != x_hat.shape:
        raise ValueError(f"x_hat has shape {tuple(x_hat.shape)} but x has {tuple(x.shape)}")
    se = ref = 0.0
    for rows in _row_blocks(x):
        xd = x[rows].double()
        se += float(torch.linalg.vector_norm(xd - x_hat[rows].double()).square())
        ref += float(torch.linalg.vector_norm(xd).square())
    return se, (se / ref if ref > 0 else float("inf") if se > 0 else 0.0)


def psnr_from_mse(mse: float, peak: float = 1.0) -> float:
    """10 log10(peak² / mse) in dB; +inf for a lossless result."""
    if mse <= 0:
        return float("inf")
    return 10.0 * math.log10(peak * peak / mse)


def psnr_vs_reference(ref: torch.Tensor, test: torch.Tensor, mask: torch.Tensor | None = None) -> float:
    """PSNR of ``test`` against ``ref`` (same shape, e.g. ``[V, C]`` radiance or ``[H, W, C]``
    image), peak = max(ref) (over ``mask`` if given), MSE over the masked entries."""
    r, t = ref.double(), test.double()
    if mask is not None:
        r, t = r[mask], t[mask]
    peak = float(r.max()) if r.numel() else 0.0
    mse = float(((r - t) ** 2).mean()) if r.numel() else 0.0
    return psnr_from_mse(mse, peak if peak > 0 else 1.0)


def random_unit_vectors(n: int, dim: int, seed: int = 0) -> torch.Tensor:
    """``[n, dim]`` float64 vectors uniform on the unit sphere of R^dim (normalised Gaussians)."""
    g = torch.Generator().manual_seed(int(seed))
    v = torch.randn(n, dim, generator=g, dtype=torch.float64)
    return v / v.norm(dim=-1, keepdim=True)


def _light_block(x: torch.Tensor, x_hat: torch.Tensor, rows: slice, n_in: int, L: torch.Tensor, gram: bool) -> torch.Tensor:
    """One row block's float64 term of :func:`random_light_psnr`: Δᵀ Δ ``[n_in, n_in]`` (Gram form) or
    Σ ‖Δ Lᵀ‖² ``[]`` (projection form) of Δ = x − x̂ ``[rows·n_out, n_in]``. float32 inputs: Δ in float32
    (one rounding of the difference), the projection a float32 GEMM over n_in terms with each row's norm
    in float32 and the squares summed in float64, the Gram form in float64 (its reduction runs over
    every row of the block); float64 inputs: all in float64."""
    f32 = x.dtype == x_hat.dtype == torch.float32
    d = (x[rows] - x_hat[rows]) if f32 else (x[rows].double() - x_hat[rows].double())
    d = d.reshape(-1, n_in)
    if gram:
        d = d.double()
        return d.T @ d
    return torch.linalg.vector_norm(d @ L.to(d.dtype).T, dim=1).double().square().sum()


def random_light_psnr(x: torch.Tensor, x_hat: torch.Tensor, n_in: int, n_lights: int = 64, seed: int = 0) -> float:
    """Monte Carlo PSNR_avg of MRT eq. 11 over ``n_lights`` random norm-1 lighting vectors.

    ``x, x_hat``: ``[P, n_out·n_in]`` (row-major matrices) or ``[P, n_in]`` (vectors), float32 or
    float64. E_l{‖Δ l‖²}/P, exact for the sampled lights, by row blocks of Δ = x − x̂
    (``[P·n_out, n_in]``, :data:`BLOCK_ELEMENTS` values each): with n_lights ≥ n_in in the Gram form
    E_l{lᵀ G l} with G = Σ Δᵀ Δ in float64 (one GEMM of n_in² per row), else as Σ ‖Δ Lᵀ‖² / n_lights
    (n_lights per row: a 384-texel transport table with 128 lights needs a third of the Gram form's
    multiply-adds) — for float32 inputs a float32 GEMM, each row's norm in float32 and every square
    summed in float64 (:func:`_light_block`; relative to a float64 evaluation ~1e-7, tested against
    numpy's). The blocks run on the process's torch threads, each block in one thread, their float64
    terms added in block order: the figure does not depend on the thread count (a Ray worker runs
    one; MKL splitting one GEMM's long reduction between threads made G's last bits depend on it).
    """
    P = x.shape[0]
    L = random_unit_vectors(n_lights, n_in, seed)
    gram = n_lights >= n_in
    blocks = list(_row_blocks(x))
    workers = min(len(blocks), max(1, torch.get_num_threads()))
    with torch_threads(1):
        if workers > 1:
            from concurrent.futures import ThreadPoolExecutor

            with ThreadPoolExecutor(workers) as pool:  # torch's kernels release the GIL
                terms = list(pool.map(lambda rows: _light_block(x, x_hat, rows, n_in, L, gram), blocks))
        else:
            terms = [_light_block(x, x_hat, rows, n_in, L, gram) for rows in blocks]
        acc = torch.zeros(n_in, n_in, dtype=torch.float64) if gram else torch.zeros((), dtype=torch.float64)
        for t in terms:  # in block order: the same sum whatever the thread count
            acc += t
        mse = (float(torch.einsum("li,ij,lj->l", L, acc, L).mean()) if gram else float(acc) / n_lights) / P
    return psnr_from_mse(mse)


def random_light_psnr_analytic(se: float, num_points: int, n_in: int) -> float:
    """Closed form of eq. 11 for linear transfer: −10 log10(SE / (P·n_in))."""
    return psnr_from_mse(se / (num_points * n_in))
