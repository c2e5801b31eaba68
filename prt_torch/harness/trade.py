"""The all-frequency trade of a wavelet transfer (issue 39; Ng, Ramamoorthi & Hanrahan 2003; the
course notes' blocker-over-plane comparison): what SH gives and what N wavelet terms give, each
against the exact result, per light, with the relighting time and bytes per vertex.

For a run whose transfer is kind ``wavelet`` (the config's ``trade`` section):

* **exact**: every Haar term of the light on the cube (``Evaluator.reference``; the stored
  transfer, so the trade isolates the light's approximation);
* **wavelets, N terms**: the light's N most important terms (``trade.selection``,
  :func:`prt_torch.lighting.haar.select_terms`), sparse light × sparse transfer
  (:class:`prt_torch.relight.WaveletRelighter`). Only the light's nonzero terms are ever selected (those above
  ``haar.ZERO_TERM`` of its largest; the headline's ``nonzero_terms``): an N past them keeps them all, the exact
  result, once — a row's ``N`` is the terms kept, ``terms_requested`` the trade's N that gave it, and a larger
  N, which would keep the same terms, makes no row of its own;
* **SH, n bands, from the same visibility**: the stored transfer back in the pixel basis
  (``ihaar2d``), projected t_lm = Σ_j T_j y_lm(d_j), the light projected from its cube
  L_lm = Σ_j L_j y_lm(d_j) Ω_j, relit by :func:`prt_torch.relight.diffuse` (n² floats per vertex; 3n² for a coloured transfer, one per colour).

Error: relative L2 over vertices and RGB against the exact result. That result is the *stored*
transfer's (its K kept terms, quantised): what the stored transfer itself costs against the
pixel-basis transfer of all 6R² terms, under each light, is measured beside it on
:data:`STORED_CHECK_VERTICES` vertices spread over the mesh (their full transfer traced again by
:func:`prt_torch.transfer.wavelet.dense_wavelet_transfer`, the precompute's rays: the headline's
``stored_error``; grid-sampled direct transfers only — jittered or interreflected ones say why not). Times: in one thread (the
work of each method; at the process's thread count a busy machine stalls OpenMP's parallel
regions on descheduled peers — at load 3.9 on 2 cores every relight read 8 or 16 ms, a scheduler
slice, for 0.03–0.6 ms of work): each row the median per relight in the render-loop form a user's loop
calls (wavelets: :meth:`~prt_torch.relight.WaveletRelighter.prepared`, the form the kernel report times; SH:
:func:`sh_loop`, the product into a reused output), with the plain call beside it (``call_s``: the relighter
called with the light, or :func:`prt_torch.relight.diffuse`: the per-call checks and conversions, 1.2–2.3× the
wavelet kernel at small N); the headline's SH/wavelet ratio timed paired (interleaved, same run), render-loop
forms, in this thread's CPU time, the ratio of the fastest tenth of 40 short pairs, as the harness's speed-up
column (``harness.run``).
"""
from __future__ import annotations

import time
from typing import Any, Callable

import torch

from .. import relight
from .evaluate import Evaluator
from .timing import measure, measure_paired, torch_threads

__all__ = ["wavelet_trade", "stored_check", "sh_loop", "TARGETS", "STORED_CHECK_VERTICES"]

#: the headline's error targets (relative L2)
TARGETS = (0.05, 0.01)
#: vertices on which the stored transfer is compared with its full pixel-basis transfer
STORED_CHECK_VERTICES = 64


def stored_check(ev: Evaluator) -> dict[str, Any]:
    """The full (all 6R², float64) Haar transfer of :data:`STORED_CHECK_VERTICES` vertices evenly spread
    over the index range, traced as the stored transfer was (same cube, sub-texel grid, offset, shadows):
    ``{'vertices': int64 [k], 'full': [k, 6R²]}``, or ``{'skipped': why}`` where the precompute's rays cannot
    be repeated that way (jittered sampling: per-chunk draws; interreflection: per-path hit rays)."""
    from ..transfer.wavelet import dense_wavelet_transfer

    m = ev.transfer.meta
    if m.get("bounces_used"):
        return {"skipped": "an interreflected transfer (its bounce rays are not repeated here)"}
    if m.get("sampling", "grid") != "grid":
        return {"skipped": "jittered texel sampling (its per-chunk random points are not repeated here)"}
    V, R = ev.V, ev.relighter.res
    idx = torch.unique(torch.linspace(0, V - 1, min(V, STORED_CHECK_VERTICES)).round().to(torch.int64))
    full = dense_wavelet_transfer(ev.transfer.mesh, R, supersample=int(m.get("supersample", 1)),
                                  shadows=bool(m.get("shadows_traced", True)), offset=float(m.get("offset", 1e-4)), vertices=idx)
    return {"vertices": idx, "full": full.reshape(idx.numel(), -1)}


def sh_loop(T: torch.Tensor, L: torch.Tensor) -> Callable[[], torch.Tensor]:
    """The SH side's render-loop form, as :meth:`prt_torch.relight.WaveletRelighter.prepared` is the wavelets':
    :func:`prt_torch.relight.diffuse`'s product (Sloan 2002) with its checks and the light's layout done once and
    the output reused, so a call is the product alone. ``T [V, n²]`` or ``[V, CT, n²]`` float32, ``L [C, n²]``;
    the returned ``run()`` gives ``[V, C]`` (``[V, CT]``) float32, equal to ``relight.diffuse(T, L)`` (the same
    sums; tested)."""
    Lc = relight._light(L, T.shape[-1], T.dtype)
    if T.ndim == 2:
        Lt = Lc.T.contiguous()  # [n², C]
        o = torch.empty(T.shape[0], Lt.shape[1], dtype=T.dtype)
        return lambda: torch.mm(T, Lt, out=o)
    Lc = (Lc.expand(T.shape[1], -1) if Lc.shape[0] == 1 else Lc).contiguous()  # [CT, n²]
    tmp = torch.empty_like(T)
    o = torch.empty(T.shape[0], T.shape[1], dtype=T.dtype)

    def run() -> torch.Tensor:  # [V, CT, n²] · [CT, n²] summed over n²: relight.diffuse's einsum, into reused buffers
        return torch.sum(torch.mul(T, Lc, out=tmp), -1, out=o)
    return run


def _rel(x: torch.Tensor, ref: torch.Tensor) -> float:
    return float((x.double() - ref.double()).norm() / ref.double().norm().clamp_min(1e-300))


def wavelet_trade(ev: Evaluator, lights: list[torch.Tensor], cfg: dict, log: Callable[[str], None] = print) -> dict[str, Any]:
    """The trade's rows and headline (module docstring) for the run's lights (Haar coefficients
    ``[C, 6R²]`` from :meth:`Evaluator.load_light`). Returns a JSON-able dict."""
    from ..lighting.haar import cube_geometry, ihaar2d, select_terms
    from ..sh import eval_sh

    t = cfg["trade"]
    r = ev.relighter
    V, P, R = ev.V, r.P, r.res
    sel = t["selection"]
    d, om = cube_geometry(R)
    dirs, om = d.reshape(-1, 3), om.reshape(-1)
    bands = sorted(set(int(b) for b in t["bands"]))
    terms = sorted(set(min(int(n), P) for n in t["terms"]))  # N above the cube's 6R² terms is all of them: one row
    Y = eval_sh(dirs, max(bands), check=False)  # [P, n²]
    nb = max(bands) ** 2
    CT = r.CT  # 3: a coloured mesh's interreflection, one transfer per colour (albedo folded): SH per colour too
    t_all = torch.empty(V, CT, nb, dtype=torch.float64)
    step = max(1, (64 << 20) // (P * 8 * CT))  # chunks of vertices: the dense rows stay ~64 MB at any V and R
    for a in range(0, V, step):  # the stored transfer, dense, back in the pixel basis, projected
        k = min(step, V - a)
        ind, vals = r.reference_rows(a, a + k)  # derived from the stored transfer per chunk (the relighter holds neither)
        H = torch.zeros(k, CT, P, dtype=torch.float64).scatter_(2, ind[:, None, :].expand(-1, CT, -1),
                                                                 vals.reshape(k, CT, -1).double())
        t_all[a:a + step] = ihaar2d(H.reshape(-1, 6, R, R)).reshape(k, CT, P) @ Y
    t_sh = {n: (t_all[:, 0, : n * n] if CT == 1 else t_all[:, :, : n * n]).to(torch.float32).contiguous() for n in bands}
    del t_all
    albedo = r.albedo
    chk = stored_check(ev)
    rows: list[dict] = []
    head: list[dict] = []
    for li, (spec, Lhat) in enumerate(zip(cfg["lights"], lights)):  # a few lights
        C = Lhat.shape[0]
        ref = ev.reference(Lhat, None)
        cube = ihaar2d(Lhat.double().reshape(C, 6, R, R)).reshape(C, P)
        out = torch.empty(V, max(C, CT))
        wav, shr = [], []
        nonzero = int(select_terms(Lhat.double(), P, "magnitude")[0].numel())  # the light's nonzero Haar terms
        for N in terms:
            idx, vals = select_terms(Lhat.double(), N, sel, r.weights if sel == "transport" else None)
            if wav and wav[-1]["N"] == int(idx.numel()):  # N past the light's nonzero terms (select_terms): the same row
                continue
            vals = vals.to(torch.float32).contiguous()  # the kernel's light (a plain call would convert per call)
            o = r(idx, vals, out=out)
            e = _rel(o, ref)
            with torch_threads(1):  # prepared at one thread: its kernel arguments hold the thread count
                s = measure(r.prepared(idx, vals, out=out), repeats=5, warmup=1).median
                sc = measure(lambda: r(idx, vals, out=out), repeats=5, warmup=1).median
            # N: the terms kept (at most the light's nonzero ones), terms_requested: the trade's N that gave the row
            wav.append({"light": str(spec), "method": "wavelet", "N": int(idx.numel()), "terms_requested": N,
                        "error": e, "relight_s": s,
                        "fps": 1.0 / s, "call_s": sc, "bytes_per_vertex": ev.bytes_per_vertex,
                        "coefficients_read": r.touched(idx)})
        for n in bands:
            Lsh = ((cube * om) @ Y[:, : n * n]).to(torch.float32)  # [C, n²]
            o = relight.diffuse(t_sh[n], Lsh) * albedo[:, :max(C, CT)]
            e = _rel(o, ref)
            with torch_threads(1):
                s = measure(sh_loop(t_sh[n], Lsh), repeats=5, warmup=1).median
                sc = measure(lambda: relight.diffuse(t_sh[n], Lsh), repeats=5, warmup=1).median  # noqa: B023
            shr.append({"light": str(spec), "method": "sh", "bands": n, "error": e, "relight_s": s, "fps": 1.0 / s,
                        "call_s": sc, "bytes_per_vertex": n * n * 4 * CT})  # CT = 3: one SH vector per colour
        rows += wav + shr
        h: dict[str, Any] = {"light": str(spec), "nonzero_terms": nonzero, "sh_best_error": min(x["error"] for x in shr),
                             "wavelet_best_error": min(x["error"] for x in wav)}
        if "full" in chk:  # the stored transfer (K terms, quantised) against all 6R² terms, under this light
            vi = chk["vertices"]
            exact = (chk["full"] @ Lhat.double().T) * albedo[vi, :C].double()  # [k, C]
            h["stored_error"] = _rel(ref[vi], exact)
        else:
            h["stored_error"] = None
        for tgt in TARGETS:
            s = next((x for x in shr if x["error"] <= tgt), None)
            w = next((x for x in wav if x["error"] <= tgt), None)
            h[f"sh_{tgt}"], h[f"wavelet_{tgt}"] = s, w
            if s is not None and w is not None:  # paired: SH's relighting time over the wavelets'
                idx, vals = select_terms(Lhat.double(), w["N"], sel, r.weights if sel == "transport" else None)
                Lsh = ((cube * om) @ Y[:, : s["bands"] ** 2]).to(torch.float32)
                with torch_threads(1):  # the render-loop forms, as the rows
                    p = measure_paired(r.prepared(idx, vals.to(torch.float32), out=out), sh_loop(t_sh[s["bands"]], Lsh),
                                       repeats=5, warmup=1, floor_pairs=40, clock=time.thread_time)
                h[f"ratio_{tgt}"] = {"sh_over_wavelet": p.speedup, "trusted": bool(p.contention.get("trusted"))}
        head.append(h)
        log(f"[bench] trade {spec}: best SH {h['sh_best_error']:.4f}, best wavelets {h['wavelet_best_error']:.4f}")
    stored = ({"vertices": int(chk["vertices"].numel()), "note": "stored transfer vs its full pixel-basis transfer (all 6R² "
               "terms, float64, traced again with the precompute's rays) on vertices evenly spread over the index range"}
              if "full" in chk else {"skipped": chk["skipped"]})
    return {"selection": sel, "res": R, "terms": terms, "bands": bands, "rows": rows, "headline": head, "stored_check": stored,
            "bytes_per_vertex": ev.bytes_per_vertex, "threads": 1, "ratio_clock": "thread_time",
            "timed": "render_loop", "kernel": r.kernel_path()}  # the build and its dense arithmetic (arith, VNNI)
