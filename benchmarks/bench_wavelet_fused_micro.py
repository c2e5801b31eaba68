"""Can the wavelet kernel's dense GEMV and its column-major sparse pass overlap (issue 39, N = 1000, one thread)?

The two passes are bound by different parts of the core (``docs/wavelet_kernel_log.md``): the dense terms' register-blocked
GEMV by the multiply-add pipes (12 multiply-adds and 4 int16 -> float conversions per 32 stored values for RGB),
the sparse pass by the scratch's read-modify-writes (three 32-byte stores per 8-vertex block). Run one after the
other (the kernel's order, per tile) their times add; interleaved in one instruction stream the out-of-order core
could run the stores under the multiply-adds. This compiles both forms side by side (CT = 1, RGB, 16-bit values)
over one light's real terms and blocks and times them paired by this thread's CPU time:

  - ``separate``: per tile the sparse blocks into the zeroed scratch (the kernel's ``sparse_tile``), then each
    32-vertex block's GEMV over the dense terms (12 sums in registers, the kernel's prefetch) added into the
    scratch (the kernel then writes the outputs from there: the same in both forms, not timed);
  - ``fused S``: per tile one loop over the dense terms of each half block (16 vertices: 6 sums, so that the
    sparse step's registers fit beside them), each dense step followed by S sparse blocks taken from a cursor over
    the tile's (term, block range) list; what is left of either stream runs alone after; the half block's sums are
    added into the scratch;
  - ``dense only`` / ``sparse only``: each pass of ``separate`` alone (their sum is what overlapping can save from);
    ``dense half``: the fused forms' dense loop alone (half blocks, 6 sums), no sparse step;
  - ``fused flat`` (a diagnostic, not a kernel form: its list is built per light outside the timing): the fused
    loop with the tile's sparse blocks flattened into one list (block, its range's light), no cursor branches.

Every form's scratch (the last tile's, the same sums in another order) is checked against ``separate``'s.
Studio and sky (transport-weighted) at N terms (default 300, 1000, 2000); the kernel section's transfer
(occluder_over_plane small, R = 32, K = 256, 16 bits, the relighter's tiles). Each: the median of 15 paired samples
of 100 calls (``measure_paired``, ``clock=time.thread_time``). Writes reports/benchmarks/wavelet_fused_micro.md.

    .venv/bin/python benchmarks/bench_wavelet_fused_micro.py [--terms 1000 ...]     (about 30 s)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import argparse  # noqa: E402
import ctypes  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT  # noqa: E402
from bench_wavelet_dense_micro import dense_terms  # noqa: E402
from bench_wavelet_pass_micro import C_PRELUDE, grouped  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import compile_library  # noqa: E402
from prt_torch.harness.timing import machine_info, measure_paired  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

SRC = C_PRELUDE + r"""
typedef int64_t i64;
#define PF 6
/* rng [nr, 3] (tile, first block, end), ordered by tile; slw [nr, 4] the range's light; bofs [NB] bytes; bv [NB, 8];
 * dense [nb, Pd, 32]; ds [nd] the light's dense slots (ascending), dlw [nd, 4]; tile t: 32-blocks tb[t] .. tb[t+1];
 * acc: one tile's scratch (TV/8 x 128 bytes); what: 1 sparse, 2 dense, 3 both */
static void sparse_ranges(const i64 *rng, i64 r0, i64 r1, const float *slw, const int32_t *bofs, const int16_t *bv,
                          float *acc) {
    for (i64 r = r0; r < r1; r++) {
        const v8f l0 = bc8(slw + 4 * r), l1 = bc8(slw + 4 * r + 1), l2 = bc8(slw + 4 * r + 2);
        const i64 e1 = rng[3 * r + 2];
        for (i64 e = rng[3 * r + 1]; e < e1; e++) {
            float *a = (float *)((char *)acc + bofs[e]);
            const v8f w = load8(bv + 8 * e);
            st8(a, ld8(a) + w * l0); st8(a + 8, ld8(a + 8) + w * l1); st8(a + 16, ld8(a + 16) + w * l2);
        }
    }
}
static void dense_block(i64 nd, const i64 *ds, const float *dlw, const int16_t *blk, float *acc) {
    v8f a[3][4];
    for (int c = 0; c < 3; c++) for (int k = 0; k < 4; k++) a[c][k] = (v8f){0};
    for (i64 t = 0; t < nd; t++) {
        const int16_t *p = blk + ds[t] * 32;
        if (t + PF < nd) __builtin_prefetch(blk + ds[t + PF] * 32);
        v8f l[3];
        for (int c = 0; c < 3; c++) l[c] = bc8(dlw + 4 * t + c);
        for (int k = 0; k < 4; k++) {
            const v8f x = load8(p + 8 * k);
            for (int c = 0; c < 3; c++) a[c][k] += x * l[c];
        }
    }
    for (int k = 0; k < 4; k++) for (int c = 0; c < 3; c++) st8(acc + 32 * k + 8 * c, ld8(acc + 32 * k + 8 * c) + a[c][k]);
}
int separate(const i64 *rng, i64 nr, const float *slw, const int32_t *bofs, const int16_t *bv, const int16_t *dense,
             i64 Pd, const i64 *ds, i64 nd, const float *dlw, const i64 *tb, i64 nt, float *acc, i64 nacc, i64 what,
             i64 reps) {
    for (i64 r_ = 0; r_ < reps; r_++) {
        i64 r0 = 0;
        for (i64 t = 0; t < nt; t++) {
            memset(acc, 0, (size_t)nacc * sizeof(float));
            i64 r1 = r0;
            while (r1 < nr && rng[3 * r1] == t) r1++;
            if (what & 1) sparse_ranges(rng, r0, r1, slw, bofs, bv, acc);
            if (what & 2)
                for (i64 b = tb[t]; b < tb[t + 1]; b++) dense_block(nd, ds, dlw, dense + b * Pd * 32, acc + 128 * (b - tb[t]));
            r0 = r1;
        }
    }
    return 0;
}
/* one dense step of a half block (16 vertices, 6 sums) followed by S sparse blocks from the cursor (r, e, e1) */
#define FUSED(S)                                                                                            \
int fused##S(const i64 *rng, i64 nr, const float *slw, const int32_t *bofs, const int16_t *bv, const int16_t *dense, \
             i64 Pd, const i64 *ds, i64 nd, const float *dlw, const i64 *tb, i64 nt, float *acc, i64 nacc,   \
             i64 what, i64 reps) {                                                                           \
    (void)what;                                                                                              \
    for (i64 r_ = 0; r_ < reps; r_++) {                                                                      \
        i64 r0 = 0;                                                                                          \
        for (i64 t = 0; t < nt; t++) {                                                                       \
            memset(acc, 0, (size_t)nacc * sizeof(float));                                                    \
            i64 r1 = r0;                                                                                     \
            while (r1 < nr && rng[3 * r1] == t) r1++;                                                        \
            i64 r = r0, e = r0 < r1 ? rng[3 * r0 + 1] : 0, e1 = r0 < r1 ? rng[3 * r0 + 2] : 0;               \
            const float *sl = slw + 4 * r0;                                                                  \
            for (i64 b = tb[t]; b < tb[t + 1]; b++)                                                          \
                for (int h = 0; h < 2; h++) {                                                                \
                    const int16_t *blk = dense + b * Pd * 32 + 16 * h;                                       \
                    v8f a00 = {0}, a01 = {0}, a10 = {0}, a11 = {0}, a20 = {0}, a21 = {0};                    \
                    for (i64 q = 0; q < nd; q++) {                                                           \
                        const int16_t *p = blk + ds[q] * 32;                                                 \
                        if (q + PF < nd) __builtin_prefetch(blk + ds[q + PF] * 32);                          \
                        const v8f x0 = load8(p), x1 = load8(p + 8);                                          \
                        const v8f l0 = bc8(dlw + 4 * q), l1 = bc8(dlw + 4 * q + 1), l2 = bc8(dlw + 4 * q + 2); \
                        a00 += x0 * l0; a01 += x1 * l0; a10 += x0 * l1; a11 += x1 * l1; a20 += x0 * l2; a21 += x1 * l2; \
                        for (int s = 0; s < S; s++) {                                                        \
                            while (e >= e1 && r + 1 < r1) { r++; sl += 4; e = rng[3 * r + 1]; e1 = rng[3 * r + 2]; } \
                            if (e < e1) {                                                                    \
                                float *a = (float *)((char *)acc + bofs[e]);                                 \
                                const v8f w = load8(bv + 8 * e);                                             \
                                st8(a, ld8(a) + w * bc8(sl));                                                \
                                st8(a + 8, ld8(a + 8) + w * bc8(sl + 1));                                    \
                                st8(a + 16, ld8(a + 16) + w * bc8(sl + 2));                                  \
                                e++;                                                                         \
                            }                                                                                \
                        }                                                                                    \
                    }                                                                                        \
                    float *o = acc + 128 * (b - tb[t]) + 64 * h;                                             \
                    st8(o, ld8(o) + a00); st8(o + 8, ld8(o + 8) + a10); st8(o + 16, ld8(o + 16) + a20);      \
                    st8(o + 32, ld8(o + 32) + a01); st8(o + 40, ld8(o + 40) + a11); st8(o + 48, ld8(o + 48) + a21); \
                }                                                                                            \
            /* what is left of the sparse stream */                                                         \
            if (e < e1) {                                                                                    \
                const v8f l0 = bc8(sl), l1 = bc8(sl + 1), l2 = bc8(sl + 2);                                  \
                for (; e < e1; e++) {                                                                        \
                    float *a = (float *)((char *)acc + bofs[e]);                                             \
                    const v8f w = load8(bv + 8 * e);                                                         \
                    st8(a, ld8(a) + w * l0); st8(a + 8, ld8(a + 8) + w * l1); st8(a + 16, ld8(a + 16) + w * l2); \
                }                                                                                            \
            }                                                                                                \
            if (r + 1 < r1) sparse_ranges(rng, r + 1, r1, slw, bofs, bv, acc);                               \
            r0 = r1;                                                                                         \
        }                                                                                                    \
    }                                                                                                        \
    return 0;                                                                                                \
}
FUSED(1)
FUSED(2)
FUSED(3)
/* diagnostic (not a kernel form: the list is built per light here, outside the timing): the fused loop with the
 * sparse stream flattened — fb [nf] the tile-ordered blocks, fr [nf] each one's range (its light), fte [nt] each
 * tile's end in the list — so a sparse step has no branch but the end test */
int fused_flat(const i64 *fb, const int32_t *fr, const i64 *fte, const float *slw, const int32_t *bofs,
               const int16_t *bv, const int16_t *dense, i64 Pd, const i64 *ds, i64 nd, const float *dlw, const i64 *tb,
               i64 nt, float *acc, i64 nacc, i64 reps) {
    for (i64 r_ = 0; r_ < reps; r_++) {
        i64 k = 0;
        for (i64 t = 0; t < nt; t++) {
            memset(acc, 0, (size_t)nacc * sizeof(float));
            const i64 k1 = fte[t];
            for (i64 b = tb[t]; b < tb[t + 1]; b++)
                for (int h = 0; h < 2; h++) {
                    const int16_t *blk = dense + b * Pd * 32 + 16 * h;
                    v8f a00 = {0}, a01 = {0}, a10 = {0}, a11 = {0}, a20 = {0}, a21 = {0};
                    for (i64 q = 0; q < nd; q++) {
                        const int16_t *p = blk + ds[q] * 32;
                        if (q + PF < nd) __builtin_prefetch(blk + ds[q + PF] * 32);
                        const v8f x0 = load8(p), x1 = load8(p + 8);
                        const v8f l0 = bc8(dlw + 4 * q), l1 = bc8(dlw + 4 * q + 1), l2 = bc8(dlw + 4 * q + 2);
                        a00 += x0 * l0; a01 += x1 * l0; a10 += x0 * l1; a11 += x1 * l1; a20 += x0 * l2; a21 += x1 * l2;
                        if (k < k1) {
                            const i64 e = fb[k];
                            const float *sl = slw + 4 * fr[k];
                            float *a = (float *)((char *)acc + bofs[e]);
                            const v8f w = load8(bv + 8 * e);
                            st8(a, ld8(a) + w * bc8(sl)); st8(a + 8, ld8(a + 8) + w * bc8(sl + 1));
                            st8(a + 16, ld8(a + 16) + w * bc8(sl + 2));
                            k++;
                        }
                    }
                    float *o = acc + 128 * (b - tb[t]) + 64 * h;
                    st8(o, ld8(o) + a00); st8(o + 8, ld8(o + 8) + a10); st8(o + 16, ld8(o + 16) + a20);
                    st8(o + 32, ld8(o + 32) + a01); st8(o + 40, ld8(o + 40) + a11); st8(o + 48, ld8(o + 48) + a21);
                }
            for (; k < k1; k++) {
                const i64 e = fb[k];
                const float *sl = slw + 4 * fr[k];
                float *a = (float *)((char *)acc + bofs[e]);
                const v8f w = load8(bv + 8 * e);
                st8(a, ld8(a) + w * bc8(sl)); st8(a + 8, ld8(a + 8) + w * bc8(sl + 1)); st8(a + 16, ld8(a + 16) + w * bc8(sl + 2));
            }
        }
    }
    return 0;
}
/* diagnostic: the dense half-block loop of the fused forms alone (6 sums; no sparse step) */
int dense_half(const int16_t *dense, i64 Pd, const i64 *ds, i64 nd, const float *dlw, const i64 *tb, i64 nt,
               float *acc, i64 nacc, i64 reps) {
    for (i64 r_ = 0; r_ < reps; r_++)
        for (i64 t = 0; t < nt; t++) {
            memset(acc, 0, (size_t)nacc * sizeof(float));
            for (i64 b = tb[t]; b < tb[t + 1]; b++)
                for (int h = 0; h < 2; h++) {
                    const int16_t *blk = dense + b * Pd * 32 + 16 * h;
                    v8f a00 = {0}, a01 = {0}, a10 = {0}, a11 = {0}, a20 = {0}, a21 = {0};
                    for (i64 q = 0; q < nd; q++) {
                        const int16_t *p = blk + ds[q] * 32;
                        if (q + PF < nd) __builtin_prefetch(blk + ds[q + PF] * 32);
                        const v8f x0 = load8(p), x1 = load8(p + 8);
                        const v8f l0 = bc8(dlw + 4 * q), l1 = bc8(dlw + 4 * q + 1), l2 = bc8(dlw + 4 * q + 2);
                        a00 += x0 * l0; a01 += x1 * l0; a10 += x0 * l1; a11 += x1 * l1; a20 += x0 * l2; a21 += x1 * l2;
                    }
                    float *o = acc + 128 * (b - tb[t]) + 64 * h;
                    st8(o, ld8(o) + a00); st8(o + 8, ld8(o + 8) + a10); st8(o + 16, ld8(o + 16) + a20);
                    st8(o + 32, ld8(o + 32) + a01); st8(o + 40, ld8(o + 40) + a11); st8(o + 48, ld8(o + 48) + a21);
                }
        }
    return 0;
}
"""


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--terms", type=int, nargs="+", default=[300, 1000, 2000])
    ap.add_argument("--reps", type=int, default=100)
    args = ap.parse_args()
    torch.set_num_threads(1)
    lib, how = compile_library("wavelet_fused_micro", SRC, ["-O3", "-march=native", "-ffp-contract=fast", "-shared",
                                                            "-fPIC", "-std=c99"], {})
    if lib is None:
        raise SystemExit(f"bench_wavelet_fused_micro: no compiler: {how}")
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    forms = ("separate", "fused1", "fused2", "fused3")
    for name in forms:
        getattr(lib, name).argtypes = [vp, i64, vp, vp, vp, vp, i64, vp, i64, vp, vp, i64, vp, i64, i64, i64]
    lib.fused_flat.argtypes = [vp, vp, vp, vp, vp, vp, vp, i64, vp, i64, vp, vp, i64, vp, i64, i64]
    lib.dense_half.argtypes = [vp, i64, vp, i64, vp, vp, i64, vp, i64, i64]
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1, layouts="column")
    assert rl.CT == 1 and rl.dense.dtype == torch.int16
    acc = torch.zeros(rl.TV // 8 * 32)
    nacc = acc.numel()
    tb = torch.tensor([min(t * rl.TV, rl.V) // 32 if t < rl.NT else -(-rl.V // 32) for t in range(rl.NT + 1)],
                      dtype=torch.int64)
    tb[-1] = rl.dense.shape[0]
    load0 = os.getloadavg()[0]
    rows = []
    for light in ("studio", "sky (sun)"):
        for N in args.terms:
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            ds, dlw = dense_terms(rl, li, lv)
            rng, gl, bofs, vals = grouped(rl, torch.arange(rl.P), 1, li, lv)
            order_r = torch.argsort(rng[:, 0], stable=True)
            rng, gl = rng[order_r].contiguous(), gl[order_r].reshape(-1, 4).contiguous()
            nblk = int((rng[:, 2] - rng[:, 1]).sum())

            def call(name, what=3, reps=1):
                return getattr(lib, name)(rng.data_ptr(), rng.shape[0], gl.data_ptr(), bofs.data_ptr(), vals.data_ptr(),
                                          rl.dense.data_ptr(), rl.dense.shape[1], ds.data_ptr(), ds.numel(),
                                          dlw.data_ptr(), tb.data_ptr(), rl.NT, acc.data_ptr(), nacc, what, reps)

            # the flattened sparse stream of the diagnostic form: per tile its ranges' blocks in order, each one's range
            lens = (rng[:, 2] - rng[:, 1])
            fb = torch.cat([torch.arange(int(a), int(b)) for _, a, b in rng.tolist()]) if rng.numel() else torch.zeros(0, dtype=torch.int64)
            fr = torch.repeat_interleave(torch.arange(rng.shape[0], dtype=torch.int32), lens)
            fte = torch.cumsum(torch.bincount(rng[:, 0], weights=lens.double(), minlength=rl.NT), 0).long()

            def call_flat(reps=1):
                return lib.fused_flat(fb.data_ptr(), fr.data_ptr(), fte.data_ptr(), gl.data_ptr(), bofs.data_ptr(),
                                      vals.data_ptr(), rl.dense.data_ptr(), rl.dense.shape[1], ds.data_ptr(), ds.numel(),
                                      dlw.data_ptr(), tb.data_ptr(), rl.NT, acc.data_ptr(), nacc, reps)

            def call_half(reps=1):
                return lib.dense_half(rl.dense.data_ptr(), rl.dense.shape[1], ds.data_ptr(), ds.numel(), dlw.data_ptr(),
                                      tb.data_ptr(), rl.NT, acc.data_ptr(), nacc, reps)

            call("separate")
            ref = acc.clone()
            for name in forms[1:] + ("flat",):
                call(name) if name != "flat" else call_flat()
                err = float((acc - ref).abs().max()) / max(float(ref.abs().max()), 1e-30)
                assert err < 1e-5, (name, err)
            base = lambda: call("separate", 3, args.reps)  # noqa: E731
            res = {"light": light, "N": N, "dense terms": int(ds.numel()), "sparse blocks": nblk}
            for name, what in (("dense only", 2), ("sparse only", 1)) + tuple((f, 3) for f in forms[1:]):
                p = measure_paired(lambda n=name, w=what: call("separate" if "only" in n else n, w, args.reps), base,
                                   repeats=15, warmup=1, clock=time.thread_time)
                res[name] = p.test.median / args.reps * 1e6
                res["separate"] = p.peer.median / args.reps * 1e6
                res[name + " ratio"] = p.speedup
                print(f"[fused_micro] {light} N={N} {name}: {res[name]:.1f} us, separate {res['separate']:.1f} us, "
                      f"separate/this {p.speedup:.3f}", flush=True)
            for name, fn in (("fused flat", lambda: call_flat(args.reps)), ("dense half", lambda: call_half(args.reps))):
                p = measure_paired(fn, base, repeats=15, warmup=1, clock=time.thread_time)
                res[name] = p.test.median / args.reps * 1e6
                res[name + " ratio"] = p.speedup
                print(f"[fused_micro] {light} N={N} {name}: {res[name]:.1f} us, separate {p.peer.median / args.reps * 1e6:.1f}"
                      f" us, separate/this {p.speedup:.3f}", flush=True)
            rows.append(res)
    m = machine_info()
    L = ["# Wavelet kernel: the dense GEMV and the sparse pass interleaved (issue 39)\n",
         f"{m['cpu']}, one thread, `-O3 -march=native` (this benchmark's own 8-lane code; this CPU: {m.get('cpu_isa')}); load average "
         f"{load0:.1f} → {os.getloadavg()[0]:.1f} (shared machine; this thread's CPU time). The kernel section's "
         f"transfer (V = {rl.V}, R = 32, K = 256, {BITS}-bit, tiles of {rl.TV}); CT = 1, RGB. Per form: µs per call "
         "(the two passes over every tile, outputs not written), the median of 15 paired samples of "
         f"{args.reps} calls against `separate` (the kernel's order); **separate / form** > 1: the form is faster. "
         "Forms in the module docstring. Reproduce: `.venv/bin/python benchmarks/bench_wavelet_fused_micro.py`.\n",
         "| light | N | dense terms | sparse blocks | separate µs | dense only µs | dense half µs | sparse only µs | "
         "fused 1 µs | fused 2 µs | fused 3 µs | fused flat µs | **separate / fused 1, 2, 3, flat** |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        L.append(f"| {r['light']} | {r['N']} | {r['dense terms']} | {r['sparse blocks']} | {r['separate']:.1f} | "
                 f"{r['dense only']:.1f} | {r['dense half']:.1f} | {r['sparse only']:.1f} | {r['fused1']:.1f} | "
                 f"{r['fused2']:.1f} | {r['fused3']:.1f} | {r['fused flat']:.1f} | **{r['fused1 ratio']:.2f} / "
                 f"{r['fused2 ratio']:.2f} / {r['fused3 ratio']:.2f} / {r['fused flat ratio']:.2f}** |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_fused_micro.md", "\n".join(L) + "\n")
    print(f"[fused_micro] wrote {OUT / 'wavelet_fused_micro.md'}", flush=True)


if __name__ == "__main__":
    main()
