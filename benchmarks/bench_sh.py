"""SH core throughput, each figure against a peer measured in the same run.

1. Basis evaluation (directions/s) at 3, 5, 9, 16 bands in float32 and float64:
   prt_torch's own recurrence (backend="torch") vs sphericart-torch (backend="sphericart"),
   with their maximum disagreement (float64 must be ≤ 1e-12 for sphericart to be used).
2. Rotation matrices for 100k rotations at 5 and 6 bands: Ivanic–Ruedenberg recurrences
   (rotation_blocks) vs the direct construction D_ij = Σ_q w_q y_i(R s_q) y_j(s_q) by exact
   quadrature (the textbook peer), plus the cost of applying the blocks to 100k vectors
   relative to a plain dense bmm with the same matrices.

Run: .venv/bin/python benchmarks/bench_sh.py [--quick]
Writes reports/benchmarks/sh.md and sh.json.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import torch

from prt_torch import sh
from prt_torch.harness.timing import machine_info, measure
from prt_torch.io import atomic_write_json, atomic_write_text

OUT = Path(__file__).resolve().parent.parent / "reports" / "benchmarks"


def unit(n, dtype, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return (d / d.norm(dim=-1, keepdim=True)).to(dtype)


def bench_basis(n_dirs: int, repeats: int):
    rows = []
    for dtype in (torch.float32, torch.float64):
        d = unit(n_dirs, dtype)
        for bands in (3, 5, 9, 16):
            ref = sh.eval_sh(d.double(), bands, backend="torch")
            res = {}
            for backend in ("torch", "sphericart"):
                y = sh.eval_sh(d, bands, backend=backend, check=False)
                t = measure(lambda: sh.eval_sh(d, bands, backend=backend, check=False), repeats=repeats, warmup=1)
                res[backend] = (t, float((y.double() - ref).abs().max()))
            rows.append({
                "dtype": str(dtype).replace("torch.", ""), "bands": bands, "directions": n_dirs,
                "torch_dirs_per_s": res["torch"][0].rate(n_dirs), "torch_spread": res["torch"][0].spread,
                "sphericart_dirs_per_s": res["sphericart"][0].rate(n_dirs), "sphericart_spread": res["sphericart"][0].spread,
                "speedup_sphericart_over_torch": res["torch"][0].median / res["sphericart"][0].median,
                "max_abs_diff_vs_float64_torch": res["sphericart"][1],
            })
    return rows


def bench_rotation(n_rot: int, repeats: int):
    rows = []
    R = sh.random_rotations(n_rot, seed=1)
    for bands in (5, 6):
        for dtype in (torch.float32, torch.float64):
            Rd = R.to(dtype)
            t_ir = measure(lambda: sh.rotation_blocks(Rd, bands), repeats=repeats, warmup=1)
            dirs, w = sh.gauss_sphere(bands, dtype=dtype, oversample=2)
            Ys = sh.eval_sh(dirs, bands) * w[:, None]
            n_peer = min(n_rot, 10_000)  # the peer's rate is measured on a subset (its [B, Q, n²] is large)

            def quad_peer():
                out = []
                for i in range(0, n_peer, 2000):  # chunks bound the [B, Q, n²] intermediate
                    rs = torch.einsum("bij,qj->bqi", Rd[i : i + 2000], dirs)
                    out.append(torch.einsum("bqi,qj->bij", sh.eval_sh(rs, bands, check=False), Ys))
                return torch.cat(out)

            t_q = measure(quad_peer, repeats=3, warmup=0)
            D_ir = sh.blocks_to_dense(sh.rotation_blocks(Rd, bands))
            agree = float((quad_peer() - D_ir[:n_peer]).abs().max())
            blocks = sh.rotation_blocks(Rd, bands)
            c = torch.randn(n_rot, bands * bands, dtype=dtype)
            t_apply = measure(lambda: sh.rotate(c, blocks), repeats=repeats, warmup=1)
            t_dense = measure(lambda: torch.bmm(D_ir, c[:, :, None]), repeats=repeats, warmup=1)
            rows.append({
                "bands": bands, "dtype": str(dtype).replace("torch.", ""), "rotations": n_rot,
                "ir_rotations_per_s": t_ir.rate(n_rot), "ir_spread": t_ir.spread,
                "quadrature_peer_rotations_per_s": t_q.rate(n_peer), "quadrature_peer_rotations": n_peer,
                "speedup_ir_over_quadrature": t_ir.rate(n_rot) / t_q.rate(n_peer),
                "max_abs_diff_ir_vs_quadrature": agree,
                "apply_blocks_vectors_per_s": t_apply.rate(n_rot),
                "apply_dense_bmm_vectors_per_s": t_dense.rate(n_rot),
                "apply_speedup_blocks_over_dense": t_dense.median / t_apply.median,
            })
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (smoke test)")
    args = ap.parse_args(argv)
    n_dirs = 20_000 if args.quick else 200_000
    n_rot = 10_000 if args.quick else 100_000
    reps = 3 if args.quick else 7
    basis = bench_basis(n_dirs, reps)
    rot = bench_rotation(n_rot, reps)
    info = machine_info()
    result = {"machine": info, "basis": basis, "rotation": rot}
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_json(OUT / "sh.json", result)
    md = ["# SH core benchmark", "", f"Machine: {info['cpu']}, {info['cores']} cores, torch {info['torch']} ({info['torch_threads']} threads).",
          f"Reproduce: `.venv/bin/python benchmarks/bench_sh.py`. Median of {reps} runs after warm-up; spread = IQR/median.", "",
          f"## Basis evaluation, {n_dirs} directions (peer: sphericart-torch, same run)", "",
          "| dtype | bands | prt_torch (Mdir/s) | sphericart (Mdir/s) | sphericart / prt_torch | max abs diff vs float64 |",
          "|---|---|---|---|---|---|"]
    for r in basis:
        md.append(f"| {r['dtype']} | {r['bands']} | {r['torch_dirs_per_s']/1e6:.2f} (±{r['torch_spread']:.0%}) | "
                  f"{r['sphericart_dirs_per_s']/1e6:.2f} (±{r['sphericart_spread']:.0%}) | {r['speedup_sphericart_over_torch']:.2f}× "
                  f"| {r['max_abs_diff_vs_float64_torch']:.1e} |")
    md += ["", f"## Rotation matrices, {n_rot} rotations (peer: direct quadrature construction on {min(n_rot, 10_000)} of them, "
           "same run; rates per rotation)", "",
           "| bands | dtype | IR (rotations/s) | quadrature peer (rotations/s) | IR / peer | max diff | apply blocks (vec/s) | blocks / dense bmm |",
           "|---|---|---|---|---|---|---|---|"]
    for r in rot:
        md.append(f"| {r['bands']} | {r['dtype']} | {r['ir_rotations_per_s']/1e6:.2f} M | {r['quadrature_peer_rotations_per_s']/1e6:.3f} M | "
                  f"{r['speedup_ir_over_quadrature']:.1f}× | {r['max_abs_diff_ir_vs_quadrature']:.1e} | "
                  f"{r['apply_blocks_vectors_per_s']/1e6:.2f} M | {r['apply_speedup_blocks_over_dense']:.2f}× |")
    atomic_write_text(OUT / "sh.md", "\n".join(md) + "\n")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
