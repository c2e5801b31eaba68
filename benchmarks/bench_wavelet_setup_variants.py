"""The wavelet kernel's per-light set-up (issue 39, one thread): variants of ``kernels/wavelet.c`` compiled side by
side from its own source with one step of the set-up rewritten, each paired with the kernel as it is over whole
calls (``WaveletRelighter.prepared``'s arguments, the same layout; both through the eight-argument entry point),
outputs compared bit for bit:

  - ``bitmap listing``: the sparse terms found from a bitmap of the marks (per 64 columns, two 32-byte loads, a
    shift and a byte mask: one 64-bit word whose set bits are the sparse marks; the portable path builds it
    byte by byte) instead of a scan of 8 marks at a time — 96 words to walk at P = 6144 instead of 768;
  - ``sorted listing at every N (before)``: the kernel as it was before its small-N listing (``SMALL_N`` 0: at every N
    a pass over the Pd dense slots and a scan of the P marks, the terms in slot / column order; the kernel now lists
    up to 256 terms from the light itself, unsorted) — kernel / variant < 1: the kernel is faster.

The set-up by step and its share of the call: ``bench_wavelet_floor_micro.py`` (the set-up alone 6.4–6.7 µs of
66–86 at N = 1000; the listing's scan of the P marks 0.7 µs at any N). Studio and sky (transport-weighted) at
N = 10 … all; the kernel section's transfer (occluder_over_plane small, R = 32, K = 256, 16 bits). Each pair: the
median of 15 paired samples by this thread's CPU time. Writes reports/benchmarks/wavelet_setup_variants.md.

    .venv/bin/python benchmarks/bench_wavelet_setup_variants.py     (about 30 s)
"""

from __future__ import annotations

import prt_torch  # noqa: F401  (first: it chooses OpenMP's wait policy from the machine's load)

import ctypes  # noqa: E402
import os  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_wavelet import BITS, LIGHTS, OUT  # noqa: E402

from prt_torch import relight  # noqa: E402
from prt_torch._native import KERNELS_DIR, LIBRARIES, compile_library  # noqa: E402
from prt_torch.harness.timing import machine_info, measure_paired  # noqa: E402
from prt_torch.scene import builtin  # noqa: E402
from prt_torch.transfer import RunOptions  # noqa: E402
from prt_torch.transfer.wavelet import precompute_wavelet  # noqa: E402
from prt_torch.io import atomic_write_text  # noqa: E402

#: the kernel's sparse listing (kernels/wavelet.c), as the variants find it
LISTING = """    for (i64 w = 0; w < (rows || small ? 0 : P); w += 8) {                                                   \\
        uint64_t x = 0; /* a constant-size copy (a variable one is a libc call: ~2.5 us per call over P = 6144) */ \\
        if (P - w >= 8) memcpy(&x, mark + w, 8); else memcpy(&x, mark + w, (size_t)(P - w));                \\
        x &= 0x0101010101010101ull;                                                                          \\
        while (x) {                                                                                          \\
            const i64 j = w + (__builtin_ctzll(x) >> 3);                                                     \\
"""
BITMAP = """    for (i64 w = 0; w < (rows || small ? 0 : P); w += 64) {                                                  \\
        uint64_t x = mark_bits(mark + w, P - w < 64 ? P - w : 64);                                           \\
        while (x) {                                                                                          \\
            const i64 j = w + __builtin_ctzll(x);                                                            \\
"""
HELPER = """
/* bit k of the result: bit 0 of m[k] (a sparse mark), k < n <= 64 */
static inline uint64_t mark_bits(const unsigned char *m, i64 n) {
#ifdef __AVX2__
    if (n == 64) {
        const __m256i a = _mm256_loadu_si256((const __m256i *)m), b = _mm256_loadu_si256((const __m256i *)(m + 32));
        return (uint64_t)(uint32_t)_mm256_movemask_epi8(_mm256_slli_epi16(a, 7)) |
               (uint64_t)(uint32_t)_mm256_movemask_epi8(_mm256_slli_epi16(b, 7)) << 32;
    }
#endif
    uint64_t x = 0;
    for (i64 k = 0; k < n; k++) x |= (uint64_t)(m[k] & 1) << k;
    return x;
}
"""
VARIANTS = {"bitmap listing": ((LISTING, BITMAP),), "sorted listing at every N (before)": ()}
#: variants compiled with another SMALL_N (kernels/wavelet.c: up to SMALL_N light terms are listed from the light itself,
#: unsorted; 0: the passes over the Pd slots and the P marks at every N, as before) — their sums are added in another
#: order at small N, so outputs are compared to float rounding there, not bit for bit
SMALL_N = {"sorted listing at every N (before)": 0}


def variant(name: str):
    """The kernel's i16 entry point compiled with the variant's replacements (and the bitmap helper)."""
    names, flags = LIBRARIES["wavelet"]
    src = (KERNELS_DIR / names[0]).read_text()
    for old, new in VARIANTS[name]:
        if old not in src:
            raise SystemExit(f"bench_wavelet_setup_variants: kernels/wavelet.c changed: {name!r} no longer applies")
        src = src.replace(old, new, 1)
    small = f"#define SMALL_N {SMALL_N[name]}\n" if name in SMALL_N else ""
    src = src.replace("#define BV 32", HELPER + small + "#define BV 32", 1)
    lib, how = compile_library("wavelet_setup_variant", src, list(flags), {})
    if lib is None:
        raise SystemExit(f"bench_wavelet_setup_variants: no compiler: {how}")
    fn = lib.prt_wavelet_relight_i16
    i64, vp = ctypes.c_int64, ctypes.c_void_p
    fn.argtypes = [vp, i64, vp, vp, i64, vp, vp, i64]
    return fn


def main() -> None:
    torch.set_num_threads(1)
    fns = {name: variant(name) for name in VARIANTS}
    mesh = builtin("occluder_over_plane", "small")
    tr = precompute_wavelet(mesh, 32, 256, BITS, shadows="always", run=RunOptions(workers=1))
    rl = relight.WaveletRelighter(tr, threads=1)
    out, out2 = torch.empty(rl.V, 3), torch.empty(rl.V, 3)
    f3 = rl._factor(3, True)
    load0 = os.getloadavg()[0]
    rows = []
    for light in ("studio", "sky (sun)"):
        for N in (1, 10, 30, 100, 200, 300, 1000, 2000, rl.P):
            li, lv, _ = rl.light(LIGHTS[light], N, "transport")
            lv = lv.to(torch.float32).contiguous()
            rl.prepared(li, lv, out)()  # binds the layout (and builds the row-major copy when this light takes it)
            lay = rl._layout.data_ptr()
            kern8 = rl._native.func  # the kernel's eight-argument entry point, the variants' form

            def call(kern8=kern8, lay=lay, li=li, lv=lv):
                return kern8(lay, li.numel(), li.data_ptr(), lv.data_ptr(), 3, f3.data_ptr(), out.data_ptr(), 1)
            row = {"light": light, "N": N}
            for name, fn in fns.items():
                def run(fn=fn):
                    return fn(lay, li.numel(), li.data_ptr(), lv.data_ptr(), 3, f3.data_ptr(), out2.data_ptr(), 1)
                assert run() == 0
                if name in SMALL_N and li.numel() <= 256:
                    assert torch.allclose(out2, out, rtol=1e-5, atol=1e-6 * float(out.abs().max())), (name, light, N)
                else:
                    assert torch.equal(out, out2), (name, light, N)
                p = measure_paired(run, call, repeats=15, warmup=1, clock=time.thread_time)
                row[name] = (p.test.median * 1e6, p.peer.median * 1e6, p.speedup, p.ratio.q1, p.ratio.q3)
                print(f"[setup_variants] {light} N={N} {name}: {row[name]}", flush=True)
            rows.append(row)
    m = machine_info()
    L = ["# Wavelet kernel: per-light set-up variants (issue 39)\n",
         f"{m['cpu']}, one thread, `-march=native` on this CPU ({m.get('cpu_isa')}); load average {load0:.1f} → "
         f"{os.getloadavg()[0]:.1f} (shared machine; this thread's CPU time, median of 15 paired samples). "
         f"The kernel section's transfer (V = {rl.V}, R = 32, K = 256, {BITS}-bit). Each variant: `kernels/wavelet.c` "
         "with one step of its set-up rewritten (module docstring), compiled beside it and called on the same layout "
         "and light; outputs equal bit for bit. **kernel / variant** > 1: the variant is faster. Reproduce: "
         "`.venv/bin/python benchmarks/bench_wavelet_setup_variants.py`.\n",
         "| light | N | variant | kernel µs | variant µs | **kernel / variant** [quartiles] |", "|---|---|---|---|---|---|"]
    for r in rows:
        for name in VARIANTS:
            t, k, sp, q1, q3 = r[name]
            L.append(f"| {r['light']} | {'all' if r['N'] == rl.P else r['N']} | {name} | {k:.1f} | {t:.1f} | "
                     f"**{sp:.3f}** [{q1:.3f}, {q3:.3f}] |")
    OUT.mkdir(parents=True, exist_ok=True)
    atomic_write_text(OUT / "wavelet_setup_variants.md", "\n".join(L) + "\n")
    print(f"[setup_variants] wrote {OUT / 'wavelet_setup_variants.md'}", flush=True)


if __name__ == "__main__":
    main()
