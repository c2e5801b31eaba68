"""The learned codec's fit on the default benchmark's Gaussian-part table: memory, page faults, CPU
time, and its PCA start against the float64 optimum (issue 42 §2/§3: "nothing held twice that need
not be").

Loads (or precomputes into ``--cache``) the transport table of the ``gaussian`` part of
``configs/default.yaml`` (10 242 × 16 128 float32 at size medium), then fits the part's neural setting
(``neural`` latent 4, features 16, 40 epochs, patience 3, seed 0) once, recording: wall and CPU time
(user + system, ``getrusage``), minor page faults, the peak resident set within the fit
(``/proc/self/clear_refs`` resets the high-water mark; the table itself is already resident) and the
Python-heap peak is not used (torch's tensors are not traced by ``tracemalloc``). Then the figures of
the fit: the PCA start's squared error SE_0 = ``pca_loss`` · P · s² (``fit_info_``: the start's mean
loss in units of the scale s), the trained codec's SE, relative SE and closed-form random-light PSNR
(MRT eq. 11 for linear transfer, −10 log10(SE / (P · n_in))); and, after the fit (outside its
figures), the float64 optimum of PCA with k vectors: the centred table's total variance less its top-k
eigenvalues, by Lanczos (``scipy.sparse.linalg.eigsh``) on the float64 Gram operator Y Yᵀ applied as
two float64 GEMMs (no P × P or D × D matrix).

Run: OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/profile_neural_start.py --cache /tmp/c [--json out.json]
("before": the same script with ``PYTHONPATH`` at an export of the code before; the table is cached
once in ``--cache`` and shared.)
"""
from __future__ import annotations

import prt_torch  # noqa: F401  (first: OpenMP's wait policy)

import argparse  # noqa: E402
import contextlib  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import resource  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from prt_torch import codecs  # noqa: E402
from prt_torch.harness.config import expand_codecs, load_config, part_configs  # noqa: E402
from prt_torch.harness.evaluate import Evaluator  # noqa: E402
from prt_torch.harness.run import compute_transfer, load_mesh_within_budget  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402


def _peak_kib() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmHWM:"):
                return int(line.split()[1])
    return 0


def _rss_kib() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def optimum_se(X: torch.Tensor, k: int) -> tuple[float, list[float]]:
    """(Σ_p ||x_p − x̄||² − Σ_{i≤k} λ_i, the top-k λ_i): PCA's least squared error with k vectors
    (Eckart–Young), float64; λ by Lanczos on the centred Gram operator (Y Yᵀ v as Y (Yᵀ v))."""
    import numpy as np
    from scipy.sparse.linalg import LinearOperator, eigsh

    Y = X.double()
    Y -= Y.mean(0)
    tv = float(torch.linalg.vector_norm(Y).square())
    P = Y.shape[0]
    op = LinearOperator((P, P), dtype=np.float64,
                        matvec=lambda v: (Y @ (Y.T @ torch.from_numpy(np.ascontiguousarray(v).reshape(-1)))).numpy())
    lam = eigsh(op, k=k, which="LA", tol=1e-12, return_eigenvectors=False, v0=np.ones(P))
    lam = sorted((float(v) for v in lam), reverse=True)
    return tv - sum(lam), lam


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--config", default="default")
    ap.add_argument("--size", default="medium")
    ap.add_argument("--cache", required=True, help="transfer cache directory (the table is precomputed there once)")
    ap.add_argument("--no-optimum", action="store_true", help="skip the float64 optimum")
    ap.add_argument("--json", default=None)
    a = ap.parse_args(argv)
    cfg = load_config(a.config)
    cfg["cache_dir"] = a.cache
    sub = [s for s in part_configs(cfg) if s["name"] == "gaussian"][0]
    sub["scene"]["size"] = int(a.size) if a.size.isdigit() else a.size
    setting = [s for s in expand_codecs(sub["codecs"]) if s["type"] == "neural"][0]
    mesh, _ = load_mesh_within_budget(sub)
    tr, _ = compute_transfer(sub, mesh, Path(a.cache), progress=False)
    ev = Evaluator(tr)
    X = ev.X
    params = {k: v for k, v in setting.items() if k != "type"}
    print(f"prt_torch {prt_torch.__file__}; table {tuple(X.shape)} {X.dtype}; setting {params}; "
          f"OMP {prt_torch.OMP_POLICY_CHOICE}; torch threads {torch.get_num_threads()}; load {os.getloadavg()}", flush=True)
    codec = codecs.get("neural", **params)
    with contextlib.suppress(OSError):
        Path("/proc/self/clear_refs").write_text("5")
    rss0 = _rss_kib()
    l0 = os.getloadavg()[0]
    r0 = resource.getrusage(resource.RUSAGE_SELF)
    t0 = time.perf_counter()
    codec.fit(X, matrix_shape=ev.matrix_shape, **ev.fit_kwargs(codec))
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_SELF)
    peak = _peak_kib()
    info = codec.fit_info_
    P = X.shape[0]
    se0 = info["pca_loss"] * P * info["scale"] ** 2
    row = {"wall_s": wall, "user_s": r1.ru_utime - r0.ru_utime, "sys_s": r1.ru_stime - r0.ru_stime,
           "minor_faults": r1.ru_minflt - r0.ru_minflt, "rss_before_gib": rss0 / 2**20, "peak_rss_gib": peak / 2**20,
           "peak_above_start_gib": (peak - rss0) / 2**20, "load": [l0, os.getloadavg()[0]],
           "start_se": se0, "se": info["se"], "se_relative": info["se_relative"],
           "psnr_random_closed_form_db": -10 * math.log10(info["se"] / (P * ev.n_in)),
           "epochs": info.get("epochs"), "best_epoch": info.get("best_epoch"), "kept_pca_start": info.get("kept_pca_start"),
           "train_loss": info.get("train_loss")}
    print(f"fit: wall {wall:.1f} s, CPU {row['user_s'] + row['sys_s']:.1f} s ({row['user_s']:.1f} user + {row['sys_s']:.1f} sys), "
          f"{row['minor_faults'] / 1e6:.2f} M minor faults, peak RSS {row['peak_rss_gib']:.2f} GiB "
          f"({row['peak_above_start_gib']:.2f} above the {row['rss_before_gib']:.2f} before the fit), load {l0:.1f}->{row['load'][1]:.1f}")
    print(f"  start SE {se0:.8g}; trained SE {info['se']:.8g} (relative {info['se_relative']:.8g}), "
          f"PSNR (closed form) {row['psnr_random_closed_form_db']:.6f} dB; epochs {row['epochs']}, best {row['best_epoch']}, "
          f"kept PCA start {row['kept_pca_start']}", flush=True)
    if not a.no_optimum:
        opt, lam = optimum_se(X, params.get("latent", 4))
        row["optimum_se"], row["optimum_evals"] = opt, lam
        row["start_se_over_optimum"] = se0 / opt
        print(f"  float64 optimum SE {opt:.8g} (top eigenvalues {', '.join(f'{v:.6g}' for v in lam)}); start / optimum {se0 / opt:.9f}")
    if a.json:
        atomic_write_text(Path(a.json), json.dumps({"fit": row, "argv": sys.argv[1:], "prt_torch": prt_torch.__file__,
                                            "omp": prt_torch.OMP_POLICY_CHOICE}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
