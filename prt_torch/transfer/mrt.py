"""Matrix radiance transfer (Lehtinen & Kautz 2003): per-vertex matrices A_p that map a global
SH light vector to exit radiance in the tent basis of :mod:`prt_torch.transfer.tents`.

A_p = G⁻¹ C B_p R_p T_p (eq. 9): T_p the shadowed (optionally interreflected) transferred
radiance, R_p the rotation into the vertex frame, B_p the zero-hemisphere BRDF matrix (eq. 4)
and G⁻¹ C the projection of exit radiance SH → tents (eq. 8). At run time only the four tents
nonzero at the local view are needed (eq. 13; :func:`prt_torch.relight.mrt`). The chunked,
resumable driver and the transferred radiance are shared with glossy transfer
(:mod:`prt_torch.transfer.glossy`).
"""
from __future__ import annotations

import time

import torch

from .._checks import check_choice, check_int
from ..brdf import BRDF, brdf_matrices
from ..executor import torch_threads
from ..scene import Mesh
from .base import RunOptions, Transfer
from .glossy import (ESTIMATORS, MAX_GLOSSY_BANDS, check_brdf, check_common, check_frames, check_memory, decide_shadows,
                     run_exit_transfer, submesh)
from .tents import MAX_TENTS, MRTBasis

__all__ = ["precompute_mrt"]


def precompute_mrt(
    mesh: Mesh,
    bands: int = 5,
    bands_out: int = 8,
    M: int = 11,
    *,
    brdf: BRDF | None = None,
    window: str | None = None,
    window_width: int | None = None,
    quad_bands: int | None = None,
    samples: int = 1024,
    seed: int = 0,
    shadows: bool | str = True,
    bounces: int = 0,
    vertices: torch.Tensor | None = None,
    estimator: str = "auto",
    run: RunOptions | None = None,
) -> Transfer:
    """Matrix radiance transfer A_p = G⁻¹ C B_p R_p T_p (Lehtinen & Kautz 2003 eq. 9).

    B is the zero-hemisphere BRDF matrix (m² × n², eq. 4) — the tent projection G⁻¹C integrates
    exit radiance over the hemisphere only, so no hemispherical SH projection is needed on the
    output side. Defaults follow the paper: n = 5, m = 8, M = 11 (windowing optional).

    ``brdf``, ``window``, ``quad_bands``, ``samples``, ``shadows``, ``bounces``, ``vertices``,
    ``estimator`` and ``run`` are as in :func:`prt_torch.transfer.glossy.precompute_glossy`.

    Returns ``Transfer(kind='mrt')``, data float32 ``[V, M², n²]``, meta with ``M``,
    ``bands_out`` (m), ``cond_G`` and ``matrix_shape``.
    """
    run = RunOptions() if run is None else run
    bands, samples, seed = check_common(bands, samples, seed)
    bounces = check_int("bounces", bounces, 0, 16)
    check_choice("estimator", estimator, ESTIMATORS)
    bands_out = check_int("bands_out", bands_out, 1, MAX_GLOSSY_BANDS)
    M = check_int("M (tents per side)", M, 2, MAX_TENTS)
    brdf = check_brdf(mesh, brdf)
    check_frames(mesh)
    n_sel = mesh.num_vertices if vertices is None else len(vertices)
    check_memory("mrt", n_sel, M * M, bands * bands, samples, run.chunk_size, run.max_memory,
                 run.streams_result(n_sel * M * M * bands * bands * 4), bounces)
    shadows, shadow_meta = decide_shadows(mesh, shadows, seed, run)
    t0 = time.perf_counter()
    with torch_threads(1):  # small steps: one thread is steady (0.2–0.3 s) where two spin (up to 1 s, 2 cores)
        basis = MRTBasis(M, bands_out)
        B, index = brdf_matrices(brdf, bands_out, bands, projection="zero", window=window, window_width=window_width,
                                 quad_bands=quad_bands)
        W = basis.P_ @ B  # [U, M², n²]
    if index.numel() == 1:
        index = index.expand(mesh.num_vertices)
    t_brdf = time.perf_counter() - t0
    sel = None if vertices is None else torch.as_tensor(vertices, dtype=torch.int64)
    fp = {"kind": "mrt", "mesh_hash": mesh.content_hash(), "bands": bands, "bands_out": bands_out, "M": M,
          "brdf": brdf.meta(), "window": window, "window_width": window_width, "samples": samples, "seed": seed,
          "shadows": shadows, "bounces": bounces, "offset": run.offset, "quad_bands": quad_bands,
          "vertices": None if sel is None else sel.tolist()}
    if estimator != "plain":
        fp["estimator"] = estimator
    data, run_meta = run_exit_transfer("mrt", mesh, W, index, bands, samples, seed, shadows, run, fp, sel,
                                       bounces=bounces, estimator=estimator)
    meta = {**shadow_meta, **run_meta}
    meta.update(
        bands=bands, bands_in=bands, bands_out=bands_out, M=M, cond_G=basis.cond_G_, samples=samples, seed=seed,
        shadows=shadows, bounces=bounces, quantity="exit", frame="local", basis="tent (Shirley-Chiu concentric map)",
        matrix_shape=[M * M, bands * bands], brdf=brdf.meta(), window=window, brdf_seconds=t_brdf,
        materials=int(B.shape[0]), vertices=None if sel is None else sel.tolist(),
        normalisation="exit radiance towards local view v: sum_j g_j(v) (data[p] @ l)[j] over the 4 tents at v",
        sh_convention="real SH, graphics convention, no Condon-Shortley phase, index l(l+1)+m",
    )
    mesh_out = mesh if sel is None else submesh(mesh, sel)
    return Transfer(kind="mrt", data=data, mesh=mesh_out, meta=meta)
