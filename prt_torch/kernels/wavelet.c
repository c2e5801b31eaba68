/* wavelet.c: all-frequency relighting, sparse Haar light x sparse Haar transfer (library "wavelet",
 * called by prt_torch/relight.py, WaveletRelighter; Ng, Ramamoorthi & Hanrahan 2003 eq. 2 and §6).
 *
 *     out[v, c] = f[v, c] * sum_n L[c', n] * T[v, c'', sel[n]]
 *
 * over the light's N kept Haar terms (indices sel int64 [N], values lv float32 [C, N]), with T[v, ct, j]
 * the vertex's stored (quantised: int8 / int16, or float32) value of Haar coefficient j in transfer
 * channel ct (CT = 1: one grey transfer, C <= 4 light channels, c' = c, c'' = 0; CT = 3: one transfer
 * per colour — interreflection of a coloured mesh —, the light grey (C = 1, c' = 0) or RGB (C = 3,
 * c' = c), c'' = c) and f [V, CO] the per-vertex factor (the quantisation scale of the vertex and
 * channel times the albedo) applied once at the end. CO = max(C, CT) output channels.
 * The factor's two forms (relight.py: WaveletRelighter._kfactor): f float32 [V, OC] (OC output channels: 3 for a
 * grey-summed RGB light, else CO), or — C passed as C | F1 (256), RGB output of a grey transfer only (else 1 is
 * returned) — f float32 [V + 4]: f[v] one factor per vertex and f[V + c] one per output channel (1 for a grey albedo
 * or none: the multiply skipped; a uniform albedo's colour), the factor of (v, c) being fl(f[v] f[V + c]): the same
 * float32 products as the [V, OC] form, so the same bits. For a grey albedo the kernel then reads 4 bytes per vertex
 * of it instead of 12 (large blocker scene: 0.21 against 0.62 MB per call, beside 1.0 MB of dense lines at N = 10);
 * per 8 vertices one 32-byte load of the factors and the same three multiplies, before the interleave instead of
 * after it (store_rgb8 / put_rgb8), in the 8- and the 16-lane builds alike. Measured: reports/benchmarks/
 * wavelet_factor.md (bench_wavelet_factor.py; docs/wavelet_kernel_log.md "The factor per vertex").
 * DENSE_VNNI (the default since 2026-11-30 in W16 builds whose target has AVX-512 VNNI and BW: DVNNI; -DDENSE_VNNI=0
 * builds the float loop only; above DENSE_TERMS): the 16-lane dense loop on integer dot products (vpdpwssd zmm, two
 * light terms per instruction) for the calls of 16-bit values, CT = 1, CO = 3 that take the 16-lane loop, the dense
 * light quantised per call to int16 by the column-maximum rule in flush groups (the layout's dtmax): chunks of VNNI_G =
 * 16 terms merged per call while the call's column-max bound stays within VNNI_RHO = 1.25 x the 16-term groups' (grp17;
 * -DVNNI_L2=1: vnb18's L2 rule, a knob), a flush to float per group; not the float loop's bits (error per vertex and
 * channel within f_v sum_g (s_g / 2) sum_{k in g} |T_v,k|). The per-call guard (vg18, VNNI_GUARD = 1): a call whose L2
 * bound sum_G (s_G,c / 2) sum_{k in G} ||scale (.) T_:,k||_2 (the layout's dnorm) exceeds VNNI_GUARD x the transfer's
 * own 16-bit bound ||scale||_2 sum_k |L_k,c| / 2 in some channel takes the float loop (C | FDENSE's bits), so the
 * premise of the default — its error below the stored transfer's own — holds, in these L2 terms over the vertices (not
 * per vertex: a dim vertex may still carry more than its own), for every light it runs.
 * C | FDENSE (512) opts a call out (the float loop, its bits: relight.py's arith="float");
 * builds without DVNNI refuse the bit (1) and are unchanged (avx2, znver3, avx512-256, portable, skylake-avx512 and
 * -DDENSE_VNNI=0 objects byte-identical to fdd5d3e's, objdump). prt_wavelet_isa's bit 64 says the build has it.
 * Measured on the Intel Xeon (bench_wavelet_madd_micro.py --vnni --proto, reports/benchmarks/wavelet_vnni_default.md;
 * docs/wavelet_kernel_log.md), the whole call paired with the opt-out on one layout: small 1.07-1.31x, medium N = 10-30
 * 1.12-1.24x, N >= 100 1.00-1.04x (the lines from L3); output error 8e-6-6e-5 rel. L2 against float64, its bound
 * 0.28-0.90x the transfer's own 16-bit bound; per vertex up to ~2e-3 relative at the dimmest vertices (cancellation;
 * under a sun 1e4x the sky at R = 8, 3-6% at the sun-shadowed vertices: docs/wavelet_kernel_log.md).
 * OUT_NT (a measurement knob, W16 only, off by default): the RGB output by streaming stores once it holds at least
 * OUT_NT bytes (and out is 32-byte aligned), an sfence at the call's end; not kept (the same report: faster alone at
 * large N = 10, slower with a read of the output right after the call).
 *
 * The transfer's columns (one per Haar coefficient j) are stored in one of two forms, chosen per
 * column when the relighter is built:
 *  - dense, for the columns most vertices keep (the coarse Haar levels; relight.py's dense_min: at least b/(4+b) of
 *    the vertices for b-byte values, 0.2 for 16-bit values where prt_wavelet_isa reports the VNNI dense loop, bit 64:
 *    its (term, block) step costs about a sparse 8-vertex block's, docs/wavelet_kernel_log.md). dense [ceil(V/32), Pd, CT, 32]:
 *    for each block of 32 vertices, the Pd dense columns' values side by side (zeros where a vertex
 *    did not keep the coefficient), dslot[j] the column's slot (-1: sparse). A block keeps its CO x 4
 *    vectors of 8 sums in registers over every dense light term: one load and CO multiply-adds per 8
 *    values (CT = 1), no index, no scatter (a register-blocked GEMV). Built with AVX-512F (W16 below, the
 *    condition of vec.h's HAVE_W16; not with PRT_TORCH_KERNEL_ISA=avx2 or avx512-256): CO x 2 vectors of 16
 *    sums instead, one widening load and CO multiply-adds per 16 values (one 64-byte line of 16-bit values
 *    per term and block), each vertex's terms added in the same order, so the same bits as the 8-lane loop;
 *    the same layout. Measured on an Intel Xeon (AVX-512, 2 MB L2 per core), paired against the avx2 build
 *    on one layout, one thread's CPU time (bench_wavelet_isa.py): the dense terms alone 1.07-1.12x faster,
 *    whole lights 1.02-1.13x except the studio light at N = 100-300 (0.96-1.05x; an ad-hoc C loop of the same
 *    work from L1: 1.26x; in the kernel the 1-2 MB come partly from L3, and zmm FMAs cost ~5% of clock).
 *    The 16-lane loop takes a tile's blocks 2i and 2i + 1 in lockstep (the last of an odd count alone): one slot
 *    load, address and CO light broadcasts per term for both, 2 x CO x 2 independent sums (CO = 4: 16 of the 32
 *    zmm registers), block 2i + 1's sums kept (as 8-lane halves) for its own call; each vertex's order unchanged
 *    (the same bits); a call with fewer than ZMM_MIN (dense term, block) pairs takes the 8-lane loop instead (the
 *    zmm loop's first use costs ~0.3-0.4 us a call). Against 69385e0's one-block loop on the Xeon, one thread's CPU
 *    time (bench_wavelet_dense16.py, load 2.2): the dense terms alone 1.09-1.16x, whole lights 1.01-1.17x at every
 *    N = 1-all (studio/sky N = 1 1.15/1.17x, 10 1.04/1.04x, 100 1.12/1.10x, 1000 1.05/1.04x, all 1.01/1.03x),
 *    and 1.05-1.27x faster than the avx2 build at every N.
 *    What is left above the ports' floor (bench_wavelet_dense16_micro.py): the term's mix alone in assembly, from
 *    L1, 5.7-5.8 cycles per term and block at the nominal clock (10 uops on the two 512-bit pipes: 5, and the clock
 *    drops under zmm FMAs: 12 of them alone read 6.5 for 6); the loop on the real layout from L2 6.8-7.5 (2 blocks)
 *    against 7.4-8.2 (1 block): the per-term slot load, shifts, prefetch and its test, the broadcasts; through a
 *    Python call ~1 more (the first pass after the interpreter, and the interpreter after a zmm-heavy call).
 *    Not kept (paired against the pair, load 4-6): four blocks in lockstep (CO <= 3, 24 zmm sums) 0.88-0.99x; the
 *    pair's loop split at nd - PF (no prefetch test per term) 0.93-1.03x; the RGB output on 16 lanes (a vpermt2ps
 *    and a masked vpermps per output vector) 0.96-1.04x (OUT_Z's interleave per 8 vertices, below, is kept); the prefetch distance 3 / 10 / 16 terms with the pair
 *    0.94-1.01x of 6.
 *    Prefetch across units (PF_FAR, W16): when the dense layout holds at least PFX_MIN bytes (0 by default: every
 *    layout; 2 MB, the Xeon's L2, until the cache regimes below were measured), the 16-lane loops prefetch the
 *    (term, unit) step PFX = 24 steps ahead (a unit: the pair of blocks, or a block alone), past the unit's last term
 *    into the next unit's first terms (PF_FAR); below PFX_MIN a second copy of the loops (PF_IN, kept for a
 *    PFX_MIN override): the term PF = 6 ahead within the unit, none for its last PF terms, as in main. A block
 *    spans Pd x 64 B (15.6 KB at R = 32, K = 256) and a light reads its nd lines scattered in it: no stream the
 *    hardware follows, and once the layout outgrows the L2 the first PF terms of every block were demand misses from
 *    L3. Measured on the Intel Xeon, one thread's CPU time, paired with main's build (bench_wavelet_prefetch.py,
 *    reports/benchmarks/wavelet_prefetch.md, load 6-8): occluder_over_plane large (V 51335, 23.9 MB) 1.22-1.45x at
 *    N = 10, 1.08-1.25x at N = 30, about 1.05x at N = 100-300; medium (V 10585, 4.9 MB) 1.02-1.20x at N = 10-100.
 *    PFX 12 / 48 about as 24, 6 less. At small (1.1 MB, the far path never taken) some rows 0.93-0.97x (studio
 *    N = 30 / 100, sky N = 100; A/A 0.99-1.03): the call's extra argument and branch or code placement, unresolved;
 *    one loop branching per term on the mode 0.90-0.95x, the far loops out of line (a
 *    function per block, main's loop text kept below PFX_MIN) no better at small and 0.93-0.94x at medium N = 10-30, every unit's tail prefetching the
 *    next unit also below PFX_MIN 0.92-0.98x.
 *    PFX_MIN from three cache regimes (bench_wavelet_regimes.py, reports/benchmarks/wavelet_regimes.md; Intel Xeon,
 *    one thread's CPU time, paired with the 2 MB build, A/A control, load 2-6): small (1.1 MB, where 2 MB kept the
 *    in-unit loop), the far path always (PFX_MIN 0) against 2 MB: warm (back-to-back calls, the layout in L2)
 *    0.96-1.03x (the A/A 0.95-1.01; studio N = 30 0.96-0.98x in each run: ~0.2-0.3 us of 6-7), evicted (a 2-4 MB
 *    streaming read of other data before each call: the lines from L3) 0.98-1.17x, cold (the working set flushed:
 *    from memory) 1.03-1.30x; 512 KB and 1 MB (the far path at small too) the same within noise; medium (4.9 MiB)
 *    takes it with either (the in-unit loop forced there: 0.80-1.04x warm, 0.76-1.00x evicted, 0.65-0.93x cold). A render loop does other work between relights (the evicted and cold regimes), and there the gains are
 *    2-17 us a call against the warm loss of at most ~0.3 us, so 0. The in-unit variants, where they would still
 *    apply (small, PFX_MIN 2 MB), paid in no regime: PF = 3 / 10 / 16 evicted 0.92-1.13x / 0.87-1.04x / 0.86-1.06x,
 *    cold 0.90-0.98x / 0.87-1.06x / 0.92-1.11x (two runs); the unit's last PF terms prefetching the next unit's first (-DPF_NEXT,
 *    a measurement knob) evicted 0.95-1.17x, cold 0.99-1.21x (the far path: 1.04-1.30x); PF_FAR's wrap without a
 *    branch (a mask) warm 0.92-1.00x, evicted and cold within the A/A.
 *    The 8-lane loop (AVX2, avx512-256 and portable builds) takes the same prefetch across units (PF_X8 = 1, on by
 *    default since 2026-11-29; -DPF_X8=0: the in-unit PF_IN only, the code tuned on the AMD Zen 3), a unit there one
 *    block, PFX = 24 and PFX_MIN 0 as above. Decided on the Intel Xeon as a proxy (no Zen 3 to measure): the avx2 build
 *    (PRT_TORCH_KERNEL_ISA=avx2) with it against without, one layout, one thread's CPU time, A/A control 0.95-1.07
 *    (bench_wavelet_regimes.py --isa avx2, reports/benchmarks/wavelet_regimes_avx2.md and _large.md, load 1.0-3.6,
 *    small / medium / large, studio and sky at N = 10-all): warm (back-to-back) 1.00-1.06x / 1.04-1.36x / 1.19-1.85x;
 *    evicted by a 3 MB read 1.04-1.20x / 1.05-1.47x / 1.08-1.61x; by a 1.5 MB read (~512 KB of the Xeon's 2 MB L2
 *    left to the call: a Zen 3 core's L2) 1.04-1.28x / 1.07-1.54x / 1.10-1.72x; cold 1.13-1.66x / 1.15-2.07x /
 *    1.19-1.92x: no row below 1.00 (the lowest 0.995; a second small run 0.995-1.58x; the avx512-256 build, small /
 *    medium, 0.95-2.09x, below 1.00 only where a light reads the whole small layout: 0.95-0.98x, A/A 0.97-1.01). PFX 12 lower in nearly every row (cold geometric means 1.26 /
 *    1.33 / 1.34 against 24's 1.39 / 1.53 / 1.52), PFX 48 as 24 (1.40 / 1.57 / 1.56; warm small 0.97-1.04x): 24 kept,
 *    as on 16 lanes. The argument for the Zen 3: its L2 is 512 KB per core, so every layout here (1.1 / 4.9 / 23.9 MB
 *    dense) outgrows it and its warm calls find the dense lines in L3, the regime of the Xeon's evicted rows, where
 *    the far prefetch gained 1.04-1.72x; where the lines are already in L1/L2 it costs an issued prefetch per line
 *    (on the Zen 3, as here, a load-pipe uop that finds the line present) and the far step's counter: the in-unit
 *    loop issues one prefetch per term too (none for the unit's last PF), so the added work is the counter and its
 *    wrap, which the Xeon's warm small rows (the L2-resident case) price at 1.00-1.06x (no loss). The 16-lane loop's
 *    warm small loss (~3% at studio N = 30, above) did not appear on 8 lanes. The object code (znver3, objdump): the
 *    only functions that change are the three tile bodies (prt_wavelet_relight_{f32,i8,i16}._omp_fn.0, where
 *    dense_block_T is inlined; the entry points only by that function's address): a second copy of each 8-lane
 *    dense loop (+51 vfmadd231ps, +32 widening loads, +7-16 prefetcht0, the step's counter; PFX_START's division
 *    once per block), every sparse-pass and output instruction's count unchanged (vpermd, vblendps, vmulps, vaddps,
 *    vpermps, vmovups); the W16 build's object code byte-identical.
 *    The sparse blocks, the row-major pass and the output stay on 8 lanes (a 16-lane read-modify-write of
 *    two channels' scratch per block measured 0.90-0.94x of the 8-lane one: not kept; the output's RGB interleave alone
 *    takes 16-lane shuffles, OUT_Z below); the column-major sparse
 *    pass takes three blocks per loop step in these builds (SPARSE_RANGE), and with AVX-512's 32 registers the
 *    row-major pass walks two 8-vertex blocks in lockstep (ROWS_LOCKSTEP below).
 *  - block-sparse, the rest: the vertices in tiles of TV (a multiple of 32), and within a tile, per
 *    column, the 8-vertex blocks holding any of its nonzero values: bofs int32 (the byte offset of the
 *    block's accumulator in the tile's scratch, 128 per block: 4 channels x 8 floats) and vals
 *    [CT, 8] (zeros where a vertex of the block did not keep it). Tile t's blocks of column j are
 *    tbase[t] + tptr[t, j] .. tbase[t] + tptr[t, j + 1]. A block adds one 8-lane multiply-add per
 *    output channel into its accumulator, which stays in L1 (a tile's scratch: TV/8 x 128 bytes).
 * Per tile (the unit of the threads' split, OpenMP, `threads`; at one thread the AVX-512 build (W16) runs the
 * tiles in a plain loop instead, no OpenMP region: SERIAL_TILES below): its sparse blocks of the light's
 * sparse terms into the zeroed scratch, then its dense blocks, each adding the scratch and writing
 * its outputs once (the AVX-512 build: a scratch of its own that is zero between calls and a touched map, no zeroing
 * per call, only the touched blocks added back and re-zeroed: zacc / tmark below). Only the columns of the light's terms are read — except when the light's sparse
 * terms hold at least row_permille / 1000 of all sparse blocks: then every sparse block is read from a
 * row-major copy (per 8-vertex block its columns' entries) into the dense block's register sums, the
 * light looked up per column (zero for the columns the light does not hold; no scratch; W16: two 8-vertex
 * blocks at a time, each in its own entry order, ROWS_LOCKSTEP). The index
 * check (0 <= sel < P) runs before any work (returns 2); an unsupported C returns 1 (CT = 1: 1..4;
 * CT = 3: 1 or 3); a light that chooses the row-major pass while the layout has no row-major copy
 * (rptr NULL: relight.py builds it on first need) returns 3 before any output is written, the light
 * scratch zero again. A column listed more than once adds its light values. An RGB light with three equal
 * channels on a grey transfer takes one sum per vertex (CO = 1), written to the three outputs. The layout's scratch (the
 * light per column lp, zero between calls: each call zeroes its own columns at its end; the term
 * lists; the tiles' accumulators; W16: zacc and tmark, zero between calls whichever build ran last) makes one call at a
 * time per layout. */

#include <stdint.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif
/* Only static inline functions return vectors here; the ABI note GCC gives without AVX
 * (-Wpsabi) is about calls across libraries, which these never are (as in vec.h). */
#pragma GCC diagnostic ignored "-Wpsabi"
typedef int64_t i64;
typedef float v8f __attribute__((vector_size(32)));
typedef int16_t v8s __attribute__((vector_size(16)));
typedef int8_t v8b __attribute__((vector_size(8)));
#ifdef __AVX2__
#include <immintrin.h>
#endif
#define BV 32 /* vertices per dense block: CO x 4 vectors of 8 sums */
#ifndef PF
#define PF 6 /* dense terms ahead the prefetch reads */
#endif
#ifndef SMALL_N
#define SMALL_N 256 /* at most this many light terms: the set-up lists them from the light itself, unsorted */
#endif

#ifdef __AVX2__ /* one 8-lane widening load (gcc splits __builtin_convertvector of 16-bit lanes into halves) */
static inline v8f load8_int16_t(const int16_t *p) {
    return _mm256_cvtepi32_ps(_mm256_cvtepi16_epi32(_mm_loadu_si128((const __m128i *)p))); }
static inline v8f load8_int8_t(const int8_t *p) {
    return _mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(_mm_loadl_epi64((const __m128i *)p))); }
#else
static inline v8f load8_int16_t(const int16_t *p) { v8s x; memcpy(&x, p, sizeof x); return __builtin_convertvector(x, v8f); }
static inline v8f load8_int8_t(const int8_t *p) { v8b x; memcpy(&x, p, sizeof x); return __builtin_convertvector(x, v8f); }
#endif
static inline v8f load8_float(const float *p) { v8f x; memcpy(&x, p, sizeof x); return x; }
static inline v8f ld8(const float *p) { v8f x; memcpy(&x, p, sizeof x); return x; }
static inline void st8(float *p, v8f x) { memcpy(p, &x, sizeof x); }
/* a broadcast straight from memory (no zero register held for it: the dense block needs all 16) */
#ifdef __AVX__
static inline v8f bc8(const float *p) { const float x = *p; return (v8f){x, x, x, x, x, x, x, x}; }
#else /* portable builds (no AVX): always inlined, or gcc makes an IPA clone (bc8.isra) returning a 32-byte vector, whose
 * -Wpsabi note the pragma above does not reach (tests/test_kernel_sources.py builds with -Werror); the AVX builds keep
 * the line above, their object code unchanged */
static inline __attribute__((always_inline)) v8f bc8(const float *p) { const float x = *p; return (v8f){x, x, x, x, x, x, x, x}; }
#endif

/* AVX-512 (the condition of vec.h's HAVE_W16: off with PRT_NO_W16, PRT_TORCH_KERNEL_ISA=avx512-256, and without
 * AVX-512F, e.g. PRT_TORCH_KERNEL_ISA=avx2 or an AVX2 CPU): the dense loop on 16-lane vectors, a 32-vertex block's
 * channel in two of them (one 64-byte line of 16-bit values per term), loaded by one widening load (vpmovsxwd zmm,
 * port 5) and one conversion (vcvtdq2ps, port 0) per 16 values, CO multiply-adds on ports 0 and 5: per term and
 * block 4 + 2 CO operations on two ports where the 8-lane loop issues 4 + 4 CO onto the two 256-bit FMA ports (plus
 * 4 widening loads on port 5). Everything after the dense terms (the row-major sparse entries, the scratch, the
 * output) takes the 8-lane code on the sums' halves (the row-major entries two 8-vertex blocks at a time). */
#if defined(__AVX512F__) && !defined(PRT_NO_W16)
#define W16 1
typedef float v16f __attribute__((vector_size(64)));
static inline v16f load16_int16_t(const int16_t *p) {
    return (v16f)_mm512_cvtepi32_ps(_mm512_cvtepi16_epi32(_mm256_loadu_si256((const __m256i *)p))); }
static inline v16f load16_int8_t(const int8_t *p) {
    return (v16f)_mm512_cvtepi32_ps(_mm512_cvtepi8_epi32(_mm_loadu_si128((const __m128i *)p))); }
static inline v16f load16_float(const float *p) { v16f x; memcpy(&x, p, sizeof x); return x; }
static inline v16f bc16(const float *p) { return (v16f)_mm512_set1_ps(*p); }
static inline v8f lo8(v16f x) { return (v8f)_mm512_castps512_ps256((__m512)x); }
static inline v8f hi8(v16f x) { return (v8f)_mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd((__m512)x), 1)); }
#else
#define W16 0
#endif
/* DVNNI: the dense loop on AVX-512 VNNI (DENSE_VNNI below), the default of W16 builds whose target has AVX-512 VNNI and
 * BW (-march=native on such a CPU; PRT_TORCH_KERNEL_ISA native or avx512); -DDENSE_VNNI=0 builds the float loop only
 * (the code of the builds before it became the default). Never in the avx2, avx512-256 or portable builds. */
#if W16 && defined(__AVX512VNNI__) && defined(__AVX512BW__) && (!defined(DENSE_VNNI) || DENSE_VNNI)
#define DVNNI 1
#else
#define DVNNI 0
#endif

/* what the library was built with (relight.py: wavelet_kernel_path): 1 AVX, 2 AVX2, 4 FMA, 8 AVX-512F (the bits of
 * the relight library's prt_isa), 32 the dense loop on 16 lanes (W16), 64 the dense loop on AVX-512 VNNI (DVNNI: the
 * calls DENSE_VNNI names take it unless C carries FDENSE; relight.py then stores 16-bit columns dense from 0.2 of the
 * vertices, WaveletRelighter.default_dense_min) */
int prt_wavelet_isa(void) {
    int b = 0;
#if defined(__AVX__)
    b |= 1;
#endif
#if defined(__AVX2__)
    b |= 2;
#endif
#if defined(__FMA__)
    b |= 4;
#endif
#if defined(__AVX512F__)
    b |= 8;
#endif
    b |= W16 ? 32 : 0;
    b |= DVNNI ? 64 : 0;
    return b;
}

/* 8 vertices' RGB values r, g, b (one channel per vector) interleaved into o [3] (out [8, 3]'s three vectors): each
 * output vector gathers its vertices from all three (a permute with one index vector) and takes each lane's channel
 * by two blends (AVX2; the portable path through a small buffer, store_rgb8 only) */
#ifdef __AVX2__
static inline void rgb8_interleave(v8f r, v8f g, v8f b, __m256 o[3]) {
    const __m256i i0 = _mm256_setr_epi32(0, 0, 0, 1, 1, 1, 2, 2), i1 = _mm256_setr_epi32(2, 3, 3, 3, 4, 4, 4, 5),
                  i2 = _mm256_setr_epi32(5, 5, 6, 6, 6, 7, 7, 7);
    const __m256 R = (__m256)r, G = (__m256)g, B = (__m256)b;
    o[0] = _mm256_blend_ps(_mm256_blend_ps(_mm256_permutevar8x32_ps(R, i0), _mm256_permutevar8x32_ps(G, i0), 0x92),
                           _mm256_permutevar8x32_ps(B, i0), 0x24);
    o[1] = _mm256_blend_ps(_mm256_blend_ps(_mm256_permutevar8x32_ps(R, i1), _mm256_permutevar8x32_ps(G, i1), 0x24),
                           _mm256_permutevar8x32_ps(B, i1), 0x49);
    o[2] = _mm256_blend_ps(_mm256_blend_ps(_mm256_permutevar8x32_ps(R, i2), _mm256_permutevar8x32_ps(G, i2), 0x49),
                           _mm256_permutevar8x32_ps(B, i2), 0x92);
}
#endif
/* The RGB interleave in the AVX-512 builds (OUT_Z 1): while the dense loop's zmm multiply-adds are in flight, port 1
 * takes no vector work, so rgb8_interleave's 9 permutes and 6 blends per 8 vertices compete with them for ports 0 and
 * 5; rgb8_interleave_z issues 3 shuffles (an insert and two vpermt2ps) and one 64-byte store with one 32-byte store.
 * Data movement only: the same bits. Measured on the Xeon against the tree without it (bench_wavelet_scratch.py
 * --base ., load 4-5, A/A warm 0.94-1.07): warm N = 10 1.05-1.10x (small / medium / large studio 1.05 / 1.08 / 1.10, sky
 * 1.06 / 1.09 / 1.01), N = 30 0.95-1.05x, N >= 100 0.96-1.04x; the output pass alone (N = 0: the 8-lane loop, no zmm
 * in flight) unchanged. Not kept: OUT_Z 2 (out [0, 16) as two 32-byte stores, one more extract) no better; OUT_PFW
 * (each dense block prefetching the next block's output lines for writing) 0.95-0.97x of main at N = 10
 * (the tree 0.97-0.99x in the same run), 0.99-1.07x of the tree at N = 30. */
#if W16 && !defined(OUT_Z)
#define OUT_Z 1 /* 0: rgb8_interleave's, as the 8-lane builds; 2: out [0, 16) as two stores */
#endif
#if W16 && OUT_Z
/* the same interleave in the AVX-512 builds (OUT_Z): r | g as one 16-lane vector (one insert), then two two-source
 * permutes (vpermt2ps) with b giving out [0, 16) in o01 and out [16, 24) in o2's lower half — 3 shuffles on port 5
 * per 8 vertices where rgb8_interleave issues 9 permutes and 6 blends */
static inline void rgb8_interleave_z(v8f r, v8f g, v8f b, __m512 *o01, __m512 *o2) {
    const __m512 rg = _mm512_castpd_ps(_mm512_insertf64x4(_mm512_castps_pd(_mm512_castps256_ps512((__m256)r)),
                                                          _mm256_castps_pd((__m256)g), 1));
    const __m512 bz = _mm512_castps256_ps512((__m256)b);
    const __m512i i01 = _mm512_setr_epi32(0, 8, 16, 1, 9, 17, 2, 10, 18, 3, 11, 19, 4, 12, 20, 5),
                  i2 = _mm512_setr_epi32(13, 21, 6, 14, 22, 7, 15, 23, 0, 0, 0, 0, 0, 0, 0, 0);
    *o01 = _mm512_permutex2var_ps(rg, i01, bz);
    *o2 = _mm512_permutex2var_ps(rg, i2, bz);
}
#endif
/* 8 vertices' RGB sums r, g, b times their factors f [8, 3] (one per vertex and channel), written interleaved to
 * out [8, 3]: three loads of the factors, three multiplies after the interleave */
static inline void store_rgb8(float *out, const float *f, v8f r, v8f g, v8f b) {
#if W16 && OUT_Z
    __m512 o01, o2;
    rgb8_interleave_z(r, g, b, &o01, &o2);
    _mm512_storeu_ps(out, _mm512_mul_ps(o01, _mm512_loadu_ps(f)));
    _mm256_storeu_ps(out + 16, _mm256_mul_ps(_mm512_castps512_ps256(o2), _mm256_loadu_ps(f + 16)));
#elif defined(__AVX2__)
    __m256 o[3];
    rgb8_interleave(r, g, b, o);
    _mm256_storeu_ps(out, _mm256_mul_ps(o[0], _mm256_loadu_ps(f)));
    _mm256_storeu_ps(out + 8, _mm256_mul_ps(o[1], _mm256_loadu_ps(f + 8)));
    _mm256_storeu_ps(out + 16, _mm256_mul_ps(o[2], _mm256_loadu_ps(f + 16)));
#else
    float s[24];
    for (int v = 0; v < 8; v++) { s[3 * v] = r[v]; s[3 * v + 1] = g[v]; s[3 * v + 2] = b[v]; }
    for (int q = 0; q < 24; q++) out[q] = s[q] * f[q];
#endif
}
/* 8 vertices' RGB outputs r, g, b (the factors already applied) written interleaved to out [8, 3]; OUT_NT builds
 * (a measurement knob: the output by streaming stores, W16 only) with nt set: non-temporal stores (out 32-byte
 * aligned) */
static inline void put_rgb8(float *out, v8f r, v8f g, v8f b, int nt) {
    (void)nt;
#if W16 && OUT_Z && !defined(OUT_NT)
    __m512 o01, o2;
    rgb8_interleave_z(r, g, b, &o01, &o2);
#if OUT_Z == 2 /* out [0, 16) as two 32-byte stores (one more shuffle: the upper half's extract) */
    _mm256_storeu_ps(out, _mm512_castps512_ps256(o01));
    _mm256_storeu_ps(out + 8, _mm256_castpd_ps(_mm512_extractf64x4_pd(_mm512_castps_pd(o01), 1)));
#else /* one 64-byte store (half of them across two lines: out [8, 3] blocks are 96 bytes apart) */
    _mm512_storeu_ps(out, o01);
#endif
    _mm256_storeu_ps(out + 16, _mm512_castps512_ps256(o2));
    return;
#endif
#ifdef __AVX2__
    __m256 o[3];
    rgb8_interleave(r, g, b, o);
#if W16 && defined(OUT_NT)
    if (nt) {
        _mm256_stream_ps(out, o[0]);
        _mm256_stream_ps(out + 8, o[1]);
        _mm256_stream_ps(out + 16, o[2]);
        return;
    }
#endif
    _mm256_storeu_ps(out, o[0]);
    _mm256_storeu_ps(out + 8, o[1]);
    _mm256_storeu_ps(out + 16, o[2]);
#else
    for (int v = 0; v < 8; v++) { out[3 * v] = r[v]; out[3 * v + 1] = g[v]; out[3 * v + 2] = b[v]; }
#endif
}

/* the dense terms into a[c][k]: with W16 two 16-lane sums per channel (z[c][h], its halves a[c][2h], a[c][2h + 1]),
 * the prefetch as in the 8-lane loop; and two blocks in lockstep (pm, the block's mode: 1 this block and the next, pst
 * elements on, over the same terms: one slot load, one address and CO light broadcasts per term for both, and
 * 2 x CO x 2 independent sums; the next block's sums kept in keep [4, 32] float32 for its own call, pm = 2; 0 this
 * block alone; 3 the 8-lane loop, DENSE_TERMS8, when the call holds fewer than ZMM_MIN (dense term, block) pairs).
 * Each vertex's terms are added in the same order in every mode: the same bits. keep is written and read in 32-byte
 * halves: the 8-lane halves a[c][k] read back from 64-byte stores missed store forwarding, ~0.4 us per call (0.82x
 * at N = 1, 0.92x at N = 10 against the one-block loop; halves: 0.97x, 1.00x). */
/* within the unit only (layouts below PFX_MIN, none by default; the W16 builds' 8-lane loop for calls of few dense terms;
 * the 8-lane builds with -DPF_X8=0): the lines of the term PF ahead, none for the unit's last PF terms */
#if defined(PF_NEXT) && W16 /* a measurement only (bench_wavelet_regimes.py): the unit's last PF terms prefetch the next
                              * unit's first PF terms (us elements on; past the layout's end: a prefetch, never a load) */
#define PF_IN(T, us, two)                                                                                    \
    {                                                                                                        \
        const int nx_ = t + PF >= nd;                                                                        \
        const i64 tt_ = nx_ ? t + PF - nd : t + PF;                                                          \
        if (tt_ < nd && (!nx_ || (us)))                                                                      \
            for (i64 q = 0; q < stride * (i64)sizeof(T); q += 64) {                                          \
                const uintptr_t a_ = (uintptr_t)blk + (uintptr_t)((ds[tt_] * stride + (nx_ ? (us) : 0)) * (i64)sizeof(T)); \
                __builtin_prefetch((const char *)(a_ + q));                                                  \
                if (two) __builtin_prefetch((const char *)(a_ + (uintptr_t)((us) / 2 * (i64)sizeof(T)) + q)); \
            }                                                                                                \
    }
#else
#define PF_IN(T, us, two)                                                                                    \
    if (t + PF < nd)                                                                                         \
        for (i64 q = 0; q < stride * (i64)sizeof(T); q += 64) {                                              \
            const i64 op = ds[t + PF] * stride;                                                              \
            __builtin_prefetch((const char *)(blk + op) + q);                                                \
            if (two) __builtin_prefetch((const char *)(blk + (us) / 2 + op) + q); /* the unit's next block */ \
        }
#endif
/* the 8-lane loop over the nd dense terms, added to a[c][k], STEP the prefetch (PF_IN; PF_X8 builds: PF_FAR), US its unit */
#define TERMS8(T, STEP, US)                                                                                   \
    for (i64 t = 0; t < nd; t++) {                                                                           \
        const T *p = blk + ds[t] * stride;                                                                   \
        STEP(T, US, 0)  /* the selected slots are scattered in the block (N < all): no stream to prefetch */ \
        v8f l[4];                                                                                            \
        for (int c = 0; c < CO; c++) l[c] = bc8(lw + 4 * t + c);                                             \
        for (int k = 0; k < 4; k++)                                                                          \
            for (int c = 0; c < CO; c++) {                                                                   \
                const v8f x = load8_##T(p + (CT == 1 ? 0 : c * BV) + 8 * k);                                 \
                a[c][k] += x * l[c];                                                                         \
            }                                                                                                \
    }
/* the 8-lane loop: CO x 4 vectors of 8 sums (W16 builds: lights of few dense terms) */
#define ZERO8 for (int c = 0; c < 4; c++) for (int k = 0; k < 4; k++) a[c][k] = (v8f){0};
#define DENSE_TERMS8(T) ZERO8 TERMS8(T, PF_IN, 0)
#ifndef PFX
#define PFX 24 /* (term, unit) steps ahead the 16-lane loops prefetch, across their unit's end into the next unit's terms */
#endif
#ifndef PFX_MIN /* dense layouts of at least this many bytes take the prefetch across units (far): 0, every layout (2 MB,
                  * the Xeon's L2, before: in L2 the far path costs ~1-2% a call, from L3 or memory it gains; the header) */
#define PFX_MIN 0LL
#endif
/* the prefetch's target PFX steps ahead of this unit's term 0 (a unit: the block, or the pair of blocks, us elements
 * long; the next unit starts us elements on): pt_ its term, po_ its unit's offset from blk in elements */
#define PFX_START(us)                                                                                        \
    i64 pt_ = PFX, po_ = 0;                                                                                  \
    if (pt_ >= nd) { const i64 u_ = pt_ / nd; pt_ -= u_ * nd; po_ = u_ * (us); }
/* one step's prefetch across units (far: the layout outgrows PFX_MIN), both blocks' lines when two: the target term's
 * lines, then the target one step on, into the next unit after this one's last term; the address as an integer (past
 * the layout's end after its last unit: a prefetch, never a load) */
#define PF_FAR(T, us, two)                                                                                   \
    {                                                                                                        \
        const uintptr_t a_ = (uintptr_t)blk + (uintptr_t)((po_ + ds[pt_] * stride) * (i64)sizeof(T));      \
        for (i64 q = 0; q < stride * (i64)sizeof(T); q += 64) {                                              \
            __builtin_prefetch((const char *)(a_ + q));                                                      \
            if (two) __builtin_prefetch((const char *)(a_ + (uintptr_t)(pst * (i64)sizeof(T)) + q));         \
        }                                                                                                    \
        if (++pt_ == nd) { pt_ = 0; po_ += (us); }                                                           \
    }
#ifndef PF_X8 /* the 8-lane loop's prefetch across units (not W16 builds): 1 (0 before 2026-11-29; the header) */
#define PF_X8 1
#endif
#if W16 /* the pair mode's parameters, arguments (blocks 2i and 2i + 1 in lockstep) and keep, in W16 builds only */
#define PAIR_PARAMS const int pm, const i64 pst, const int far, float *keep, VNNI_PARAMS
#ifndef ZMM_MIN /* fewer (dense term, 32-vertex block) pairs than this in a call: the 8-lane loop (the zmm loop's first
                 * use in a call costs ~0.3-0.4 us on the Xeon: measured 1.10-1.21x at 1-3 dense terms x 71 blocks,
                 * 0.93-0.97x at 5-7) */
#define ZMM_MIN 256
#endif
#define PAIR_ARGS(b, nb, pst) nd * ((V + BV - 1) / BV) < ZMM_MIN ? 3 : (b) & 1 ? 2 : (b) + 1 < (nb), (pst),       \
    (V + BV - 1) / BV * (pst) * (i64)sizeof(*dense) >= PFX_MIN, keep, VNNI_ARGS
#define PAIR_KEEP float keep[128] __attribute__((aligned(64))) = {0};
/* blocks blk and nblk in lockstep over the nd dense terms, STEP the prefetch (PF_FAR or PF_IN) */
#define PAIR_TERMS(T, STEP)                                                                                  \
    for (i64 t = 0; t < nd; t++) {                                                                           \
        const i64 o = ds[t] * stride;                                                                        \
        STEP(T, 2 * pst, 1)                                                                                  \
        v16f l[4];                                                                                           \
        for (int c = 0; c < CO; c++) l[c] = bc16(lw + 4 * t + c);                                            \
        for (int h = 0; h < 2; h++)                                                                          \
            for (int c = 0; c < CO; c++) {                                                                   \
                const i64 e = o + (CT == 1 ? 0 : c * BV) + 16 * h;                                           \
                const v16f x = load16_##T(blk + e), w = load16_##T(nblk + e);                                \
                z[c][h] += x * l[c];                                                                         \
                y[c][h] += w * l[c];                                                                         \
            }                                                                                                \
    }
/* block blk alone over the nd dense terms */
#define ONE_TERMS(T, STEP)                                                                                   \
    for (i64 t = 0; t < nd; t++) {                                                                           \
        const T *p = blk + ds[t] * stride;                                                                   \
        STEP(T, pst, 0)                                                                                      \
        v16f l[4];                                                                                           \
        for (int c = 0; c < CO; c++) l[c] = bc16(lw + 4 * t + c);                                            \
        for (int h = 0; h < 2; h++)                                                                          \
            for (int c = 0; c < CO; c++) {                                                                   \
                const v16f x = load16_##T(p + (CT == 1 ? 0 : c * BV) + 16 * h);                              \
                z[c][h] += x * l[c];                                                                         \
            }                                                                                                \
    }
/* DENSE_VNNI (the default of W16 builds on a CPU with AVX-512 VNNI and BW since 2026-11-30, DVNNI above; -DDENSE_VNNI=0:
 * the float loop only; the calls it takes: 16-bit values, CT = 1, an RGB light on three output channels (CO = 3, a
 * grey RGB light excluded), the 16-lane loop (at least ZMM_MIN (dense term, block) pairs), C without FDENSE (512: the
 * caller's opt-out, relight.py's arith="float", the float loop's bits); every other call takes the float loop, the same
 * bits as the builds without it): the dense
 * terms with integer dot products. Per call (VNNI_SETUP, when the call takes the 16-lane loop) the dense light lw
 * [nd, 4] is quantised in place to int16 per channel and flush group g (consecutive dense terms in the kernel's dense
 * order: chunks of VNNI_G = 16 merged per call under VNNI_RHO, vnni_quantise below), s_g[c] = max(sum_k tmax_k |L_k| / (2^31 - 1 - sum_k tmax_k / 2), max |L| / 32767) rounded up
 * to float32 (bench_wavelet_madd_micro.py's quantise_light, "column max": no int32 sum of a group overflows for the
 * stored values; tmax the layout's dtmax [Pd], each dense column's largest stored magnitude, built once in relight.py;
 * a layout without it (NULL): the "65535 rule", s_g[c] = max(sum |L| / (65538 - n_g / 2), max |L| / 32767), any
 * |T| <= 32767), written over lw as the pairs' lights int32 [ceil(nd / 2), 4], (Lq_2q & 0xFFFF) |
 * Lq_2q+1 << 16 (an odd last term paired with itself at light 0). Per pair and 32-vertex block: the two rows (64
 * bytes each) interleaved by vpunpcklwd / vpunpckhwd, one vpdpwssd zmm per interleaving and channel (6 int32 sums;
 * the two blocks of the W16 pair in lockstep, the broadcasts shared), the prefetch's targets as the float loop's (across
 * units, PFX steps ahead, on layouts of at least PFX_MIN bytes; else PF terms ahead within the unit); after each group's
 * pairs a flush (the int32 sums converted, times the group's scales, added to float sums by FMA, zeroed);
 * at the end the vertex order restored (vpermt2ps) into z / y as the float loop leaves them. Error per vertex and
 * channel |dS| <= sum_g (s_g[c] / 2) sum_{k in g} |T_v,k| (+ float rounding): not the same bits as the float loop. Measured: reports/benchmarks/wavelet_madd_micro_vnni.md (the loops),
 * wavelet_vnni_proto.md (the whole call; docs/wavelet_kernel_log.md).
 * The records (2026-11-30, branch vnni17): VNNI_SETUP also rewrites the call's dense slots wk [nd] (int64) in place as
 * records int32 [nd, 2] (vnni_records: the term's row offset in bytes, its prefetch step's target from the unit's start,
 * the same for every unit), so a pair step loads two records and adds them to the block's address — no slot shift, no
 * odd-term select, no prefetch counter with its wrap, no division per unit (PFX_START's) — and an odd last term takes a
 * step of its own after its group's pairs. The same sums in the same order: the outputs bit for bit those of the loop
 * before (fdd5d3e..2913585's). Where the call's loop cost went, on the Intel Xeon (family 6 model 167), small blocker
 * scene, studio 292 kept (71 dense terms x 71 blocks), one thread's CPU time, timing-only builds paired with main's
 * (bench_wavelet_scratch.py, load 1.3-2.0; docs/wavelet_kernel_log.md "The VNNI dense steps in the call"): of the ~18.4 us call
 * the dense terms ~9.1 us, ~8.4 of it the term loop with its flushes (every dense block's lines from its own block
 * 0.27-0.38 us less: the lines come from L2 at little cost), the per-block work around it (sums zeroed, permutes,
 * the pair's keep) ~0.75 us, one group instead of 16-term groups 0.2-0.5 us less (sky N = 300, 246 dense terms: 2.8 of
 * 35 us); the loop's scalar bookkeeping the rest above the asm body's 2.6 cycles per (term, block). With the records
 * the call is faster warm at small 1.01-1.10x (studio 292 kept 1.05-1.07x; A/A 0.98-1.04), medium 0.99-1.14x (N = 10-30
 * 1.05-1.14x), evicted 0.93-1.09x (A/A 0.92-1.09; reports/benchmarks/wavelet_vnni_records.md, load 1.7-2.0), the
 * outputs bit for bit main's; the fourth row 0.45 of the streaming read against main's 0.41 in that run. Not kept: the pair
 * loop unrolled by 2 (GCC unroll) no better (0.99-1.03x of the records alone); no prefetch at all 0.90-0.97x of the
 * records warm and 0.87-0.98x evicted; loops aligned to 32 / 64 bytes 0.98-1.02x; four blocks in lockstep (a timing-only
 * prototype, 24 int32 sums in registers, the float sums flushed through the stack) 0.83-1.00x warm.
 * The flush groups per call (2026-11-30, branch grp17): fixed groups of 32 put sky N = 100's bound at 1.19x the
 * transfer's own 16-bit bound (16: 0.76x), so the groups are chosen per call: 16-term chunks merged left to right while
 * sum_G s_G,c T_G (T: the group's sum of tmax) stays within VNNI_RHO = 1.25 x the 16-term groups' for every channel
 * (vnni_quantise; O(nd); the group's end in vq's lane 3, read by the loop). Small / medium blocker scene: studio 292
 * kept 5 -> 3 groups, sky N = 100 6 -> 2, sky N >= 300 16 -> 5; the bound (rel. L2) of the transfer's own 0.24-0.77 ->
 * 0.28-0.85 (bench_wavelet_madd_micro.vnni_groups recomputes the rule for vnni_bound). Paired with a506b53 on one layout
 * (Intel Xeon family 6 model 167, load 3.1-3.8, one thread's CPU time; reports/benchmarks/wavelet_vnni_groups.md): warm
 * small 0.97-1.06x (studio 292 kept 1.05x, sky N = 30-1000 1.02-1.04x; A/A 0.97-1.03), medium 0.95-1.05x (0.95 at
 * studio N = 30, whose groups do not change; A/A 0.97-1.01); section 7's fourth row 0.51 against 0.48 in that run
 * (bench_wavelet.py --only kernel --size small, load 5.4: 0.49). Other builds' .text byte-identical (objcopy).
 * -DVNNI_RHO=0 -DVNNI_BETA=0: the 16-term groups, a506b53's bits.
 * The flush groups by an L2 bound (2026-11-30, branch vnb18): the column-max bound sum_G s_G T_G (a vertex holding
 * every column's maximum) overestimates the per-vertex bound's rel. L2 2.7-4.4x (the lead's figure), so its budget
 * could only be relative. By the triangle inequality the output's L2 error over the vertices is at most sum_G (s_G,c /
 * 2) sum_{k in G} ||f_c (.) T_:,k||_2 (f the factor: the vertex's quantisation scale times the albedo), 1.07-1.21x the
 * per-vertex bound's rel. L2 on the blocker scene; the layout's dnorm [Pd + 1] holds each dense column's ||scale (.)
 * T_:,k||_2 and ||scale||_2 (relight.py's _dense_norms, float64, built with dtmax; the albedo left out: a per-call
 * option and per channel; grey or uniform it is a constant per channel on both sides of the budget). The rule: grp17's
 * left-to-right merge of 16-term chunks, each run weighed by its columns' norms instead of their maxima (the scales
 * unchanged: the column-maximum rule, overflow-safe), within max(VNNI_RHO x the 16-term groups' L2 bound, VNNI_BETA x
 * ||scale|| sum_k |L_k,c|): an absolute budget in the terms the VNNI default rests on (the bound below the transfer's
 * own 16-bit error). VNNI_BETA 0.75 by measurement (bench_wavelet_scratch.py --vnni against f1408bf, Intel Xeon family
 * 6 model 167, one thread's CPU time, 11 repeats, load 3.3-4.2, two runs;
 * reports/benchmarks/wavelet_vnni_l2groups.md): studio N = 30 (2 -> 1 groups) warm 1.02-1.05x (small 1.02-1.03, medium
 * 1.04-1.05; beta 0.9 the same), every other row 0.98-1.02x in the second run (A/A 0.99-1.02; medium sky N = 300 1.04
 * [0.98, 1.05]; the fourth row, 3 -> 2 groups, 0.99x: one flush per block pair less is ~0.1 us of 14), in the first
 * the 0.75 variant 0.95-0.97x at small N = 10-30 rows whose groups and bits are the base's (noise or code placement);
 * beta 0.5 0.97-1.02x everywhere over the two runs; section 7's fourth row 0.41-0.42 for both rules (bench_wavelet.py
 * --only kernel --size small, back to back, load 2.5-3.4: a call of 13.7-14.0 us against a streaming read of 5.7-5.8
 * us). Groups at small / medium (grp17 -> vnb18): studio N = 30 2 -> 1, 292 kept 3 -> 2, sky N >= 300 5 -> 4, the rest
 * unchanged; the stated bound of the transfer's own (per vertex, rel. L2) 0.28-0.85 -> 0.51-0.85, in the rule's L2
 * terms at most 0.92 (sky N = 30: its 1.25 x the 16-term groups'); the error (rel. L2) 1.3e-5-5.7e-5
 * (reports/benchmarks/wavelet_vnni_l2groups_error.md). -DVNNI_L2=0: grp17's groups, f1408bf's bits (checked per row).
 * Since vg18 VNNI_L2 is 0 by default again (the L2 rule gave no speed on the rows that matter: the fourth row 0.99x,
 * studio N = 30 1.02-1.05x), a knob; dnorm stays in the layout for the guard.
 * The per-call guard (2026-11-30, branch vg18): vnb18 found one light term x 1e4 at N = 100 (in the first flush group)
 * putting the stated bound at 2.8x the transfer's own 16-bit bound, with any grouping — the default's premise (the VNNI
 * error below the error the stored transfer already carries) failing for that light. So vnni_quantise, after the
 * groups are chosen, sums per channel B_c = sum_G s_G,c sum_{k in G} dnorm_k (s_G the float32 scales the loop uses;
 * the chunks' dnorm sums taken in the chunk pass, O(nc) more) and returns 0 — the light left as float, wk as slots:
 * the float loop, the bits of C | FDENSE — when B_c > VNNI_GUARD x ||scale||_2 sum_k |L_k,c| for a channel with light
 * (the albedo, grey or uniform, a constant per channel on both sides). VNNI_GUARD 1 (the lead's rule; 0: no guard).
 * Where it trips (bench_wavelet_madd_micro.vnni_guard, the same sums; small blocker scene, R = 32, K = 256): ordinary
 * studio / sky rows 0.32-0.92 (none), sky + sun 1e4 at N = 100-1000 0.54-0.64 (none), one term x 1e4 at N = 100 3.0
 * (float loop), at N = 300 / 1000 0.40; at R = 16, K = 64 / 128 sky N = 30 (one merged group) 1.2 and one term x 1e4
 * at N = 300 1.2-1.4 trip too; at R = 8, K = 32 every studio / sky light (1.0-2.0: few, full dense columns). Its cost
 * (bench_wavelet_scratch.py --vnni --base f1408bf --sizes small, Intel Xeon family 6 model 167, one thread's CPU time,
 * load 1.0-1.2, reports/benchmarks/wavelet_vnni_guard.md): warm 0.96-1.01x of f1408bf (median ~0.99; noguard, the same
 * source with VNNI_GUARD 0, 0.98-1.01x; A/A 0.99-1.01; 21 repeats at N >= 300: 0.97-0.99x, noguard 0.99-1.02), the
 * outputs f1408bf's bits on every row: ~1-2%, also with the sums computed and the decision ignored, and with the sums
 * taken from the column maxima instead of dnorm (not its lines; unexplained, placement suspected); vnni_quantise is
 * noinline (once per call; the kernel body's code then does not move with the set-up's). avx2, znver3, avx512-256,
 * portable, skylake-avx512 and -DDENSE_VNNI=0 objects' .text byte-identical to f1408bf's (gcc + objcopy).
 * The set-up on vectors (2026-11-30, branch su19): VNNI_SETUP split in place (bench_wavelet_setup.py --tsc, Intel Xeon
 * family 6 model 167, small blocker scene): studio 292 kept 0.76 us = chunk pass 0.22 + flush groups 0.11 + guard test
 * and int16 write 0.34 + records 0.06 (sky N = 1000: 2.66 = 0.92 + 0.34 + 1.13 + 0.22; the guard's sums ride in the
 * chunk and groups passes, its test is three comparisons). vnni_quantise's chunk pass (a term's channels in one
 * float64 vector) and its write (a pair's two terms in one, one vdivpd for six divsd) now take the scalar code's
 * operations per lane: the same groups, scales, lights and outputs, bit for bit; 0.76 -> 0.57 us (2.66 -> 1.95).
 * With gather_light's RGB rows (su19, DVNNI only: 16 terms transposed, one 16-byte add per term; the same bits) paired
 * with e5b4207 (bench_wavelet_setup.py --pair, load 1.1): the fourth row 1.020-1.032x, sky N = 100-2000 1.03-1.05x,
 * N = 10 0.99x (A/A 0.97-1.02); bench_wavelet_scratch.py --vnni (the per-vertex factor) warm small 0.99-1.04x (the
 * fourth row 0.99-1.00x), medium 0.98-1.02x; reports/benchmarks/wavelet_setup19.md. Other builds' .text
 * byte-identical to e5b4207's (avx2, znver3, avx512-256, portable, skylake-avx512, -DDENSE_VNNI=0; objcopy). */
#if DVNNI
#define VNNI_PARAMS const float *vq,
#define VNNI_ARGS vq,
#ifndef VNNI_G /* dense terms per scale group (even): the int32 sums flushed to float once per group */
#define VNNI_G 16
#endif
#ifndef VNNI_RHO /* the flush groups' budget: the call's bound at most VNNI_RHO x the VNNI_G groups' (or VNNI_BETA's) */
#define VNNI_RHO 1.25
#endif
#ifndef VNNI_L2 /* the flush groups weighed by the columns' L2 norms (the layout's dnorm; vnb18, a knob); 0: by their maxima (grp17) */
#define VNNI_L2 0
#endif
#ifndef VNNI_GUARD /* the per-call guard (vg18): the float loop when the call's L2 bound > VNNI_GUARD x the transfer's own; 0: off */
#define VNNI_GUARD 1.0
#endif
#ifndef VNNI_BETA /* ... or at most VNNI_BETA x the transfer's own 16-bit bound in the same L2 terms (VNNI_L2 only) */
#define VNNI_BETA 0.75
#endif
/* a run's scales sc [3] by the column-maximum rule from its sums sum [3] of tmax_k |L_k,c|, maxima mx [3] of |L_k,c|
 * and half = sum tmax_k / 2 (tm NULL: the 65535 rule, tmax 1, n the run's terms); returns its sum of tmax, 2 half */
static inline double vnni_rule(const double sum[3], const double mx[3], double half, i64 n, const int tm, double sc[3]) {
    for (int c = 0; c < 3; c++) { /* bench_wavelet_madd_micro.py's quantise_light: the same scales */
        const double s = tm ? sum[c] / (2147483647.0 - half) : sum[c] / (65538.0 - (double)n / 2);
        const double sm = mx[c] / 32767.0;
        sc[c] = s > sm ? s : sm;
    }
    return 2 * half;
}
/* a group's scales sc [3] (float64) rounded up to float32 into s32 [3] (0: the least normal float) */
static inline void vnni_scale32(const double sc[3], float *s32) {
    for (int c = 0; c < 3; c++) {
        float f = sc[c] > 0 ? (float)sc[c] : 1.17549435e-38f;
        if ((double)f < sc[c]) { uint32_t u; memcpy(&u, &f, 4); u++; memcpy(&f, &u, 4); } /* the next float up */
        s32[c] = f;
    }
}
/* the dense light lw [nd, 4] (float32) quantised per flush group and channel, in place as the pairs' lights int32
 * [ceil(nd / 2), 4]; vq [ng, 4] the groups' scales (float32, rounded up) and in lane 3 the group's end (int32 bits: its
 * last term + 1; ng <= ceil(nd / VNNI_G)); tm the layout's column maxima int32 [Pd] (NULL: the 65535 rule, groups of
 * VNNI_G), ds [nd] the terms' slots; nm the layout's dnorm [Pd] float64 (the columns' L2 norms of scale x T; NULL, or
 * VNNI_L2 0: the column-maximum weights, grp17's rule) and ns its ||scale||_2. The flush groups: runs of consecutive
 * VNNI_G-term chunks, merged left to right while, for every channel c, done_c + s_G,c W_G + rest_c <= budget_c, with
 * W a run's weight — vnb18: the sum of its columns' L2 norms nm, so that sum_G (s_G,c / 2) W_G is the triangle
 * inequality's bound of the output's L2 error over the vertices (the factor's per-vertex scale in the norms; a grey or
 * uniform albedo a constant per channel on both sides of the budget); grp17 (tm without nm): the sum of the columns'
 * maxima tmax, a bound at a vertex holding every column's maximum —, s its scale (the column-maximum rule, from tm:
 * the scales never change with the weights), done the closed groups' s W, rest the chunks after the run as VNNI_G
 * groups, and budget_c = max(VNNI_RHO x B16_c, VNNI_BETA x ns x sum_k |L_k,c|) (B16_c = sum over the chunks g of
 * s_g,c W_g, the VNNI_G groups' bound; ns sum_k |L_k,c| (/ 2) the transfer's own 16-bit bound for the same terms in the
 * same L2 terms: its stored values off by at most scale_v / 2 each; the second term with nm only): the call's L2 bound
 * at most VNNI_RHO times the VNNI_G groups' or VNNI_BETA times the transfer's own, whichever is larger. A run's sums:
 * its chunks' sums added in order. O(nd). bench_wavelet_madd_micro.py's vnni_groups: the same rule, the same sums in
 * the same order. The guard (nm non-NULL, VNNI_GUARD > 0; whatever VNNI_L2): with the groups chosen, B_c = sum_G s32_G,c
 * x (the group's sum of nm), and B_c > VNNI_GUARD x ns x sum_k |L_k,c| for a channel with light returns 0 before lw is
 * written (the caller takes the float loop); else lw is quantised and 1 returned (bench_wavelet_madd_micro.vnni_guard) */
static __attribute__((noinline)) int vnni_quantise(i64 nd, float *lw, float *vq, const int32_t *tm, const i64 *ds, const double *nm,
                                double ns) {
    const i64 nc = (nd + VNNI_G - 1) / VNNI_G;
    double cs[3 * nc + 3], cm[3 * nc + 3], ch[nc + 1], cw[nc + 1], cg[nc + 1], rest[3 * nc + 3], sc[3], la[3] = {0, 0, 0};
    const double *gn = VNNI_GUARD > 0 ? nm : NULL; /* the guard's norms: the layout's dnorm whatever the rule */
#if !VNNI_L2
    nm = NULL;
#endif
    /* each chunk's sums, maxima, half, weight: a term's channels in the lanes of one float64 vector (lane 3: the
     * light's fourth float, zero, unused), per lane the operations of the scalar loop before (su += x w as gcc's
     * contraction of it under -ffp-contract=fast: one fused multiply-add; mx = x > mx ? x : mx, vmaxpd's operand
     * order; la += x; |x| by the sign bit cleared: -0.0 and NaN lights give the scalar loop's sums and maxima): the same
     * sums in the same order, so the same groups and scales (su19: 0.21 -> 0.11 us on the fourth row, rdtsc in place) */
    __m256d lav = _mm256_setzero_pd();
    const __m256d sgn4 = _mm256_set1_pd(-0.0);
    for (i64 i = 0; i < nc; i++) {
        double half = 0, wt = 0, wg = 0;
        __m256d su = _mm256_setzero_pd(), mx = su;
        for (i64 t = i * VNNI_G; t < (i + 1) * VNNI_G && t < nd; t++) {
            const double w = tm ? (double)tm[ds[t]] : 1.0;
            half += w / 2;
            wt += nm ? nm[ds[t]] : w;
            wg += gn ? gn[ds[t]] : 0.0;
            const __m256d x = _mm256_andnot_pd(sgn4, _mm256_cvtps_pd(_mm_loadu_ps(lw + 4 * t)));
            su = _mm256_fmadd_pd(x, _mm256_set1_pd(w), su);
            mx = _mm256_max_pd(x, mx);
            lav = _mm256_add_pd(lav, x);
        }
        double su4[4], mx4[4];
        _mm256_storeu_pd(su4, su);
        _mm256_storeu_pd(mx4, mx);
        for (int c = 0; c < 3; c++) { cs[3 * i + c] = su4[c]; cm[3 * i + c] = mx4[c]; }
        ch[i] = half;
        cw[i] = wt;
        cg[i] = wg;
    }
    {
        double la4[4];
        _mm256_storeu_pd(la4, lav);
        for (int c = 0; c < 3; c++) la[c] = la4[c];
    }
    rest[3 * nc] = rest[3 * nc + 1] = rest[3 * nc + 2] = 0;
    for (i64 i = nc - 1; i >= 0; i--) { /* the VNNI_G groups' s W, summed from the back: rest [i] the chunks i.. */
        vnni_rule(cs + 3 * i, cm + 3 * i, ch[i], VNNI_G, tm != NULL, sc);
        for (int c = 0; c < 3; c++) rest[3 * i + c] = rest[3 * i + 3 + c] + sc[c] * cw[i];
    }
    double bud[3];
    for (int c = 0; c < 3; c++) {
        const double r = VNNI_RHO * rest[c], a = nm ? VNNI_BETA * ns * la[c] : 0.0;
        bud[c] = r > a ? r : a;
    }
    double done[3] = {0, 0, 0}, cur[3] = {0, 0, 0}, gs[3] = {0, 0, 0}, gm[3] = {0, 0, 0}, gh = 0, gw = 0, gg = 0;
    double vb[3] = {0, 0, 0}; /* the guard's sum_G s_G,c sum_{k in G} dnorm_k (the float32 scales) */
    i64 ng = 0;
    for (i64 i = 0; i < nc; i++) {
        if (i > 0 && tm) { /* the open group extended by chunk i, if the budget allows */
            double s2[3], m2[3];
            for (int c = 0; c < 3; c++) { s2[c] = gs[c] + cs[3 * i + c]; m2[c] = gm[c] > cm[3 * i + c] ? gm[c] : cm[3 * i + c]; }
            const double h2 = gh + ch[i], w2 = gw + cw[i];
            vnni_rule(s2, m2, h2, 0, 1, sc);
            int ok = 1;
            for (int c = 0; c < 3; c++) ok &= done[c] + sc[c] * w2 + rest[3 * i + 3 + c] <= bud[c];
            if (ok) {
                for (int c = 0; c < 3; c++) { gs[c] = s2[c]; gm[c] = m2[c]; cur[c] = sc[c] * w2; }
                gh = h2;
                gw = w2;
                gg += cg[i];
                continue;
            }
        }
        if (i > 0) { /* the open group closed at chunk i: its scales, its end */
            vnni_rule(gs, gm, gh, VNNI_G, tm != NULL, sc); /* n: the 65535 rule's only (a group one full chunk) */
            for (int c = 0; c < 3; c++) done[c] += cur[c];
            vnni_scale32(sc, vq + 4 * ng);
            for (int c = 0; c < 3; c++) vb[c] += (double)vq[4 * ng + c] * gg;
            const int32_t e0 = (int32_t)(i * VNNI_G);
            memcpy(vq + 4 * ng + 3, &e0, 4);
            ng++;
        }
        for (int c = 0; c < 3; c++) { gs[c] = cs[3 * i + c]; gm[c] = cm[3 * i + c]; }
        gh = ch[i];
        gw = cw[i];
        gg = cg[i];
        vnni_rule(gs, gm, gh, VNNI_G, tm != NULL, sc);
        for (int c = 0; c < 3; c++) cur[c] = sc[c] * gw;
    }
    if (nd) { /* the last group */
        vnni_rule(gs, gm, gh, nd - (nc - 1) * VNNI_G, tm != NULL, sc);
        vnni_scale32(sc, vq + 4 * ng);
        for (int c = 0; c < 3; c++) vb[c] += (double)vq[4 * ng + c] * gg;
        const int32_t e0 = (int32_t)nd;
        memcpy(vq + 4 * ng + 3, &e0, 4);
        ng++;
    }
    if (gn) /* the guard: sum_G s_G,c sum_{k in G} dnorm_k > VNNI_GUARD x ns sum_k |L_k,c| (both / 2) -> 0 */
        for (int c = 0; c < 3; c++)
            if (la[c] > 0 && vb[c] > VNNI_GUARD * ns * la[c]) return 0; /* lw untouched: the float loop's light */
    /* the pairs' lights: per pair q, terms 2q and 2q + 1 as one float64 vector [a0 a1 a2 a3 b0 b1 b2 b3] (an odd last
     * term's b zero: a masked load) divided by the group's scales [s0 s1 s2 1 s0 s1 s2 1] (vdivpd: the scalar divsd's
     * IEEE quotients), rounded half away from zero as x + copysign(0.5, x) truncated (the scalar form's x + (x < 0 ?
     * -0.5 : 0.5) but for x = -0.0: both truncate to 0), then (qa & 0xFFFF) | qb << 16 per channel, lane 3 zero: the
     * same int32 lights as the scalar loop before, one vdivpd per pair for six divsd (su19: 0.34 -> 0.21 us on the fourth
     * row, the divider's throughput the limit: 6 of 8 lanes used) */
    int32_t *lq = (int32_t *)lw;
    i64 g = 0;
    int32_t ge;
    memcpy(&ge, vq + 3, 4);
    const __m512d hlf = _mm512_set1_pd(0.5), sgn = _mm512_set1_pd(-0.0);
    __m512d dv = _mm512_setzero_pd();
    for (i64 q = 0, gq = -1; 2 * q < nd; q++) { /* pair q's lights read (terms 2q, 2q + 1) before entry q is written */
        if (2 * q >= ge) { g++; memcpy(&ge, vq + 4 * g + 3, 4); } /* groups start at multiples of VNNI_G: even */
        if (g != gq) { /* the group's divisors, lane 3 and 7 one */
            const __m128 s4 = _mm_blend_ps(_mm_loadu_ps(vq + 4 * g), _mm_set1_ps(1.0f), 8);
            dv = _mm512_cvtps_pd(_mm256_set_m128(s4, s4));
            gq = g;
        }
        __m512d x = _mm512_cvtps_pd(_mm256_maskz_loadu_ps(2 * q + 1 < nd ? 0xFF : 0x0F, lw + 8 * q));
        x = _mm512_div_pd(x, dv);
        x = _mm512_add_pd(x, _mm512_or_pd(_mm512_and_pd(x, sgn), hlf));
        const __m256i qi = _mm512_cvttpd_epi32(x);
        const __m128i w = _mm_or_si128(_mm_and_si128(_mm256_castsi256_si128(qi), _mm_set1_epi32(0xFFFF)),
                                       _mm_slli_epi32(_mm256_extracti128_si256(qi, 1), 16));
        _mm_storeu_si128((__m128i *)(lq + 4 * q), _mm_blend_epi32(w, _mm_setzero_si128(), 8));
    }
    return 1;
}
/* the dense terms' slots ds = wk [nd] (int64) rewritten in place as records int32 [nd, 2]: (ds[t] x 64, the byte offset
 * of term t's row in its block; the prefetch's target of step t), read by vnni_terms instead of ds. far (the layout
 * outgrows PFX_MIN): the target PFX steps ahead across units, u x us + ds[(t + PFX) % nd] x 64 with u = (t + PFX) / nd
 * units ahead and us the unit's bytes (a pair of blocks: the same offsets for every unit); else the term PF ahead within
 * the unit (the last term's row for the unit's last PF terms). The caller checks that the offsets fit an int32
 * ((PFX / nd + 1) us + Pd x 64 <= INT32_MAX; else the float loop) */
static inline void vnni_records(i64 nd, i64 *wk, i64 us, const int far) {
    int32_t *r = (int32_t *)wk;
    for (i64 t = 0; t < nd; t++) { const i64 sl = wk[t]; r[2 * t] = (int32_t)(sl * 64); r[2 * t + 1] = 0; }
    i64 u = far ? PFX / nd : 0, tt = far ? PFX - u * nd : PF;
    for (i64 t = 0; t < nd; t++) {
        if (far) {
            r[2 * t + 1] = (int32_t)(u * us + r[2 * tt]);
            if (++tt == nd) { tt = 0; u++; }
        } else
            r[2 * t + 1] = r[2 * (t + PF < nd ? t + PF : nd - 1)];
    }
}
/* one block's pair body: row a loaded, row b the unpacks' memory operand, 6 vpdpwssd (asm: in intrinsics gcc copied
 * every sum through another register at each step) */
#define VNNI_BLOCK(k, pa, pb)                                                                                \
    __asm__("vmovdqu64 (%[pa_]), %[x]\n\t vpunpckhwd (%[pb_]), %[x], %[hi]\n\t vpunpcklwd (%[pb_]), %[x], %[x]\n\t" \
            "vpdpwssd %[l0], %[x], %[s00]\n\t vpdpwssd %[l0], %[hi], %[s01]\n\t"                              \
            "vpdpwssd %[l1], %[x], %[s10]\n\t vpdpwssd %[l1], %[hi], %[s11]\n\t"                              \
            "vpdpwssd %[l2], %[x], %[s20]\n\t vpdpwssd %[l2], %[hi], %[s21]\n\t"                              \
            : [s00] "+v"(s##k##00), [s01] "+v"(s##k##01), [s10] "+v"(s##k##10), [s11] "+v"(s##k##11),          \
              [s20] "+v"(s##k##20), [s21] "+v"(s##k##21), [x] "=&v"(x), [hi] "=&v"(hi)                        \
            : [pa_] "r"(pa), [pb_] "r"(pb), [l0] "v"(l0), [l1] "v"(l1), [l2] "v"(l2) : "memory")
/* block k's group flush: its six int32 sums converted, times the group's scales s_ [3], added to its float sums */
#define VNNI_FLUSH(k, s_)                                                                                    \
    {                                                                                                        \
        const __m512 c0_ = _mm512_set1_ps((s_)[0]), c1_ = _mm512_set1_ps((s_)[1]), c2_ = _mm512_set1_ps((s_)[2]); \
        f##k##00 = _mm512_fmadd_ps(_mm512_cvtepi32_ps(s##k##00), c0_, f##k##00);                            \
        f##k##01 = _mm512_fmadd_ps(_mm512_cvtepi32_ps(s##k##01), c0_, f##k##01);                            \
        f##k##10 = _mm512_fmadd_ps(_mm512_cvtepi32_ps(s##k##10), c1_, f##k##10);                            \
        f##k##11 = _mm512_fmadd_ps(_mm512_cvtepi32_ps(s##k##11), c1_, f##k##11);                            \
        f##k##20 = _mm512_fmadd_ps(_mm512_cvtepi32_ps(s##k##20), c2_, f##k##20);                            \
        f##k##21 = _mm512_fmadd_ps(_mm512_cvtepi32_ps(s##k##21), c2_, f##k##21);                            \
        s##k##00 = s##k##01 = s##k##10 = s##k##11 = s##k##20 = s##k##21 = _mm512_setzero_si512();           \
    }
/* blk (and with two, blk + pstb bytes: the pair's next block; pstb the blocks' stride) over the nd dense terms, their
 * records rc int32 [nd, 2] (vnni_records: each term's row offset and its prefetch step's target, both from blk), the
 * pairs' lights lq, scales vq [3]: the float sums into z (and y) [c][h], h: vertices 16h .. 16h + 15. Per pair of terms
 * two record loads, two adds, four prefetches from the records (no counter, no wrap, no shift); an odd last term alone
 * (its row as both rows, light 0 on the second) */
static inline __attribute__((always_inline)) void vnni_terms(const char *blk, i64 pstb, const int two,
        i64 nd, const int32_t *rc, const int32_t *lq, const float *vq, v16f z[4][2], v16f y[4][2]) {
    __m512i s000 = _mm512_setzero_si512(), s001 = s000, s010 = s000, s011 = s000, s020 = s000, s021 = s000,
            s100 = s000, s101 = s000, s110 = s000, s111 = s000, s120 = s000, s121 = s000;
    __m512 f000 = _mm512_setzero_ps(), f001 = f000, f010 = f000, f011 = f000, f020 = f000, f021 = f000,
           f100 = f000, f101 = f000, f110 = f000, f111 = f000, f120 = f000, f121 = f000;
    const char *blk2 = blk + pstb;
    const i64 nf = nd >> 1; /* full pairs */
    for (i64 g = 0, q0 = 0; 2 * q0 < nd; g++) { /* a flush group (vq [g, 3]: its end term e), its pairs, then its flush */
    int32_t e;
    memcpy(&e, vq + 4 * g + 3, 4);
    const i64 qe = e >> 1;
    for (i64 q = q0; q < qe; q++) {
        const int32_t *r = rc + 4 * q;
        const char *ra = blk + r[0], *rb = blk + r[2];
        __builtin_prefetch(blk + r[1]);
        __builtin_prefetch(blk + r[3]);
        if (two) { __builtin_prefetch(blk2 + r[1]); __builtin_prefetch(blk2 + r[3]); }
        const __m512i l0 = _mm512_set1_epi32(lq[4 * q]), l1 = _mm512_set1_epi32(lq[4 * q + 1]),
                      l2 = _mm512_set1_epi32(lq[4 * q + 2]);
        __m512i x, hi;
        VNNI_BLOCK(0, ra, rb);
        if (two) VNNI_BLOCK(1, ra + pstb, rb + pstb);
    }
    if (e & 1) { /* the odd last term (e = nd odd), in this group: its row twice (light 0 on the second) */
        const int32_t *r = rc + 4 * nf;
        const char *ra = blk + r[0];
        __builtin_prefetch(blk + r[1]);
        if (two) __builtin_prefetch(blk2 + r[1]);
        const __m512i l0 = _mm512_set1_epi32(lq[4 * nf]), l1 = _mm512_set1_epi32(lq[4 * nf + 1]),
                      l2 = _mm512_set1_epi32(lq[4 * nf + 2]);
        __m512i x, hi;
        VNNI_BLOCK(0, ra, ra);
        if (two) VNNI_BLOCK(1, ra + pstb, ra + pstb);
    }
    { /* the group's flush: int32 -> float, times its scale, added; the int32 sums zeroed */
        const float *s_ = vq + 4 * g;
        VNNI_FLUSH(0, s_)
        if (two) VNNI_FLUSH(1, s_)
    }
    q0 = (e + 1) >> 1;
    }
    /* lane 4j + r of the low interleaving: vertex 8j + r; of the high one: vertex 8j + 4 + r (r < 4) */
    const __m512i i0 = _mm512_setr_epi32(0, 1, 2, 3, 16, 17, 18, 19, 4, 5, 6, 7, 20, 21, 22, 23),
                  i1 = _mm512_setr_epi32(8, 9, 10, 11, 24, 25, 26, 27, 12, 13, 14, 15, 28, 29, 30, 31);
    const __m512 fi[2][3][2] = {{{f000, f001}, {f010, f011}, {f020, f021}}, {{f100, f101}, {f110, f111}, {f120, f121}}};
    for (int c = 0; c < 3; c++) {
        for (int k = 0; k < 1 + two; k++) {
            const __m512 lo = fi[k][c][0], hv = fi[k][c][1];
            v16f *o = k ? y[c] : z[c];
            o[0] = (v16f)_mm512_permutex2var_ps(lo, i0, hv);
            o[1] = (v16f)_mm512_permutex2var_ps(lo, i1, hv);
        }
    }
}
#define VNNI_ON(T) vq && CO == 3 && CT == 1 && sizeof(T) == 2 && stride == BV
#define VNNI_PAIR(T) if (VNNI_ON(T)) vnni_terms((const char *)blk, pst * (i64)sizeof(T), 1, nd, (const int32_t *)ds, (const int32_t *)lw, vq, z, y); else
#define VNNI_ONE(T) if (VNNI_ON(T)) vnni_terms((const char *)blk, pst * (i64)sizeof(T), 0, nd, (const int32_t *)ds, (const int32_t *)lw, vq, z, z); else
/* in the kernel after the term lists: the light quantised when the call takes the 16-lane loop (PAIR_ARGS's test) */
#define VNNI_SETUP(T)                                                                                        \
    float vq_[4 * ((nd + VNNI_G - 1) / VNNI_G) + 4]; /* the flush groups: scales, end [ng <= ceil(nd / VNNI_G), 4] */ \
    const float *vq = NULL;                                                                                  \
    if (!fdense && sizeof(T) == 2 && CT == 1 && CO == 3 && nd && nd * ((V + BV - 1) / BV) >= ZMM_MIN) {      \
        const i64 pstb_ = Pd * BV * (i64)sizeof(T), nbk_ = (V + BV - 1) / BV;                                \
        if ((PFX / nd + 1) * 2 * pstb_ + Pd * 64 <= INT32_MAX) { /* the records' offsets fit (else the float loop) */ \
            if (vnni_quantise(nd, lw, vq_, L->dtmax, wk, L->dnorm, L->dnorm ? L->dnorm[Pd] : 0.0)) { /* 0: the guard */ \
                vnni_records(nd, wk, 2 * pstb_, nbk_ * pstb_ >= PFX_MIN); /* wk: ds -> records (after the quantisation) */ \
                vq = vq_;                                                                                    \
            }                                                                                                \
        }                                                                                                    \
    }
#endif
#define DENSE_TERMS(T)                                                                                       \
    if (pm == 3) { DENSE_TERMS8(T) } else /* little dense work in the call: the 8-lane loop */               \
    if (pm == 2) /* computed with the previous block: its halves as stored (32-byte loads of 32-byte stores) */ \
        for (int c = 0; c < 4; c++) for (int k = 0; k < 4; k++) a[c][k] = c < CO ? ld8(keep + 32 * c + 8 * k) : (v8f){0}; \
    else {                                                                                                   \
        v16f z[4][2];                                                                                        \
        for (int c = 0; c < 4; c++) for (int h = 0; h < 2; h++) z[c][h] = (v16f){0};                        \
        if (pm == 1) {                                                                                       \
            v16f y[4][2];                                                                                    \
            for (int c = 0; c < 4; c++) for (int h = 0; h < 2; h++) y[c][h] = (v16f){0};                    \
            const T *nblk = blk + pst;                                                                       \
            VNNI_PAIR(T) if (far && nd) { PFX_START(2 * pst) PAIR_TERMS(T, PF_FAR) }                         \
            else PAIR_TERMS(T, PF_IN)                                                                        \
            for (int c = 0; c < CO; c++) for (int h = 0; h < 2; h++) {                                       \
                st8(keep + 32 * c + 16 * h, lo8(y[c][h]));                                                   \
                st8(keep + 32 * c + 16 * h + 8, hi8(y[c][h]));                                               \
            }                                                                                                \
        } else VNNI_ONE(T) if (far && nd) { PFX_START(pst) ONE_TERMS(T, PF_FAR) }                            \
        else ONE_TERMS(T, PF_IN)                                                                             \
        for (int c = 0; c < 4; c++)                                                                          \
            for (int h = 0; h < 2; h++) { a[c][2 * h] = lo8(z[c][h]); a[c][2 * h + 1] = hi8(z[c][h]); }     \
    }
#elif PF_X8 /* the 8-lane builds (AVX2, avx512-256, portable): the prefetch across units (a unit: one block), PFX steps
               * ahead from PFX_MIN up; -DPF_X8=0: the in-unit prefetch only (PF_IN), the code tuned on the AMD Zen 3 */
#define PAIR_PARAMS const i64 pst, const int far,
#define PAIR_ARGS(b, nb, pst) (pst), (V + BV - 1) / BV * (pst) * (i64)sizeof(*dense) >= PFX_MIN,
#define PAIR_KEEP
#define DENSE_TERMS(T)                                                                                       \
    if (far && nd) { ZERO8 PFX_START(pst) TERMS8(T, PF_FAR, pst) } else { DENSE_TERMS8(T) }
#else /* the 8-lane loop: CO x 4 vectors of 8 sums */
#define PAIR_PARAMS
#define PAIR_ARGS(b, nb, pst)
#define PAIR_KEEP
#define DENSE_TERMS(T) DENSE_TERMS8(T)
#endif
#if DVNNI /* C | FDENSE: the dense terms on the float loop (the caller's opt-out; decoded before C | F1) */
#define FDENSE 512
#define VNNI_FLAG                                                                                            \
    const int fdense = (int)(C >> 9 & 1);                                                                    \
    C -= fdense ? FDENSE : 0;
#endif
#ifndef VNNI_SETUP /* DENSE_VNNI's hooks (above): nothing in the builds without it (DVNNI 0) */
#define VNNI_FLAG
#define VNNI_PARAMS
#define VNNI_ARGS
#define VNNI_PAIR(T)
#define VNNI_ONE(T)
#define VNNI_SETUP(T)
#endif

/* The row-major pass with 32 vector registers (W16, AVX-512F: ymm0-31 through AVX-512VL; the AVX2 and portable
 * builds keep the loop in DENSE_BLOCK, their machine code unchanged): ROW_G(CO) of a dense block's four 8-vertex
 * blocks walked in lockstep — per step two entries of each, into that block's own two sets of sums, up to the
 * shorter block's pairs; then each block's rest and its odd entry as in the 8-lane loop — so each vertex's terms
 * are added in the same order (the same bits as one block at a time) with 2 x ROW_G independent multiply-add
 * chains per channel instead of 2; the column taken as unsigned (lp + 16 col bytes: one shift, where int arithmetic gave a
 * shift and a sign extension per entry); a prefetch of the row copy ROW_PF entries ahead. Measured on an Intel Xeon
 * (AVX-512; bench_wavelet_rowpass.py, paired with the loop before on one layout, one thread CPU time, load 1-3):
 * whole lights at N = 2000 and all 1.01-1.02x (the report's run, load 1.0; 1.00-1.02x at 2.6), 1.03-1.05x (31
 * repeats), column-major lights 1.01-1.03x (their code unchanged), the pass alone (one sparse term, the pass forced:
 * its copy stays in L2) 1.01-1.03x.
 * Without the prefetch the pass alone was 1.06-1.08x (3.8 -> 3.5 cycles per entry, the call's 1.8 us of set-up and
 * output aside) but whole lights 0.96-1.02x: in a whole call the pass costs ~65 us against 45 alone, its copy
 * (0.87 MB) and the dense blocks (1.1 MB) outgrowing the 2 MB L2 together. Four blocks (24 sums):
 * the same on the pass (0.98-1.00x of two) but the column-major lights 3.5-5.8% slower (the larger code inlined in
 * every TILE_CASE); one block with the unsigned column alone 1.00-1.05x; the prefetch 600 or 1200 entries ahead
 * about as 300 on whole lights (1.01-1.05x / 1.00-1.04x). Measured and not kept (each against the loop before,
 * paired, in runs where the lockstep without prefetch gave 1.04-1.07x): the light from a 4 KB table (in L1) or the
 * values from 4 KB, timing-only variants, 1.03-1.04x (so the pass is not waiting on L2); no column load at all (the
 * light from a fixed table) 1.14x; a prefetch per pair of entries, 16, 64 or 128 entries ahead, 0.88-0.91x (the pass
 * alone) and 0.92-0.94x (whole lights at N = all); both entries'
 * values converted by one 16-lane conversion (CT = 1) 1.03-1.06x; two pairs of entries per block and step 1.06x
 * with two blocks, 0.75x with four (spills); the blocks' entries addressed from one counter 1.06x. An assembly loop
 * of the same instructions from L1 runs at 2.6 cycles per entry (2.15 without the column load and its shift; the
 * two FMA ports' floor is 2.0: a conversion and 3 multiply-adds per entry for CO = 3), the kernel's loop at 3.45;
 * the likely cause, the scalar work per entry (column load, shift, loop counters) competing for ports 0 and 1 with
 * the multiply-adds, this VM's lack of performance counters leaves unconfirmed. */
#if W16
#ifndef ROW_LS
#define ROW_LS 2 /* 8-vertex blocks in lockstep: 1, 2 or 4 (4: CO <= 3 only, else 2; bench_wavelet_rowpass.py --ls) */
#endif
#ifndef ROW_PF
#define ROW_PF 300 /* entries ahead the lockstep loop prefetches (about half a 32-vertex block's) */
#endif
#define ROW_G(CO) ((CO) <= 3 || ROW_LS < 2 ? ROW_LS : 2)
#define ROW_LP(col) ((const float *)((const char *)lp + ((size_t)(uint32_t)(col) << 4)))
/* two row-major entries E, E + 1 of one 8-vertex block into its two sets of sums S0, S1 [CO] */
#define ROW2(T, S0, S1, E)                                                                                   \
    {                                                                                                        \
        const float *l0_ = ROW_LP(rc[E]), *l1_ = ROW_LP(rc[(E) + 1]);                                        \
        const T *x0_ = rv + (E) * 8 * CT, *x1_ = x0_ + 8 * CT;                                               \
        for (int c = 0; c < CO; c++) {                                                                       \
            S0[c] += load8_##T(x0_ + (CT == 1 ? 0 : 8 * c)) * bc8(l0_ + c);                                  \
            S1[c] += load8_##T(x1_ + (CT == 1 ? 0 : 8 * c)) * bc8(l1_ + c);                                  \
        }                                                                                                    \
    }
/* G 8-vertex blocks k0 .. k0 + G - 1 in lockstep (a[c][k]: the dense sums in, the block's sums out) */
#define ROWS_LOCKSTEP(T, G)                                                                                  \
    for (int k0 = 0; k0 < 4; k0 += (G)) {                                                                    \
        v8f s0[4][4], s1[4][4];                                                                              \
        i64 e[4], e1[4], m = INT64_MAX;                                                                      \
        for (int g = 0; g < (G); g++) {                                                                      \
            for (int c = 0; c < CO; c++) { s0[g][c] = a[c][k0 + g]; s1[g][c] = (v8f){0}; }                   \
            e[g] = rp[k0 + g];                                                                               \
            e1[g] = rp[k0 + g + 1];                                                                          \
            const i64 n = (e1[g] - e[g]) >> 1;                                                               \
            m = n < m ? n : m;                                                                               \
        }                                                                                                    \
        /* the entries ROW_PF ahead of the first block's, as many bytes per step as the step reads: in a whole    \
         * call the row copy comes partly from L3 (with the dense blocks it outgrows the L2) */               \
        uintptr_t pf_ = (uintptr_t)rv + (uintptr_t)((rp[k0] + ROW_PF) * 8 * CT * (i64)sizeof(T)); /* may pass the end */ \
        for (i64 i = 0; i < m; i++) {                                                                        \
            for (i64 q = 0; q < 2 * (G) * 8 * CT * (i64)sizeof(T); q += 64) __builtin_prefetch((const char *)(pf_ + q)); \
            pf_ += 2 * (G) * 8 * CT * (i64)sizeof(T);                                                        \
            for (int g = 0; g < (G); g++) { ROW2(T, s0[g], s1[g], e[g]) e[g] += 2; }                         \
        }                                                                                                    \
        for (int g = 0; g < (G); g++) {                                                                      \
            for (; e[g] + 1 < e1[g]; e[g] += 2) ROW2(T, s0[g], s1[g], e[g])                                  \
            if (e[g] < e1[g])                                                                                \
                for (int c = 0; c < CO; c++)                                                                 \
                    s0[g][c] += load8_##T(rv + e[g] * 8 * CT + (CT == 1 ? 0 : 8 * c)) * bc8(ROW_LP(rc[e[g]]) + c); \
            for (int c = 0; c < CO; c++) a[c][k0 + g] = s0[g][c] + s1[g][c];                                 \
        }                                                                                                    \
    }
#else
#define ROWS_LOCKSTEP(T, G) {}
#endif

/* The sparse scratch in the AVX-512 builds (W16): zero between calls, with a touched map. The column-major pass adds
 * into zacc [MT, TV/8, 4, 8] float32 (the layout's own field, never the 8-lane builds' acc: a build of each may run on
 * one layout, and the AVX2 build leaves acc dirty) and marks each block it adds to in tmark [MT, TV/8] uint8 (one byte
 * per 32-vertex block: tmark[bofs >> 9]; TOUCH8, a measurement knob: per 8-vertex block, bofs >> 7); a dense block adds
 * its accumulators back only when marked, stores zeros over the CO channels it added and clears the mark, so every
 * tile ends with its scratch and marks zero again and no call zeroes the whole scratch (before: a memset of nb x 512
 * bytes per tile, 170 KB per call at V = 10 585 — more than the L1D — and 4 x CO loads and adds per dense block,
 * touched or not). A light whose sparse terms hold more than TOUCH_X (2) sparse blocks per 8-vertex block of V marks
 * none (its blocks cover the tiles anyway): the tile's marks are set by one memset of nb bytes and every block is
 * added back and re-zeroed. The sums are the same bits: an accumulator never touched is +0, and a sum from +0 that
 * adds +0 is unchanged. The AVX2 and avx512-256 builds keep the memset and the add-back of every block (ACC_PARAMS,
 * ADD_BACK, MARK and SCRATCH_ZERO below expand to the code before: their .text is main's byte for byte, objcopy).
 * Measured on an Intel Xeon (family 6 model 167, AVX-512), one thread's CPU time, paired with main's build on one
 * layout, together with the RGB interleave below (bench_wavelet_scratch.py, reports/benchmarks/wavelet_scratch.md,
 * load 3-5, A/A 0.94-1.05): warm medium N = 30 1.18 / 1.15x (studio / sky; section 7's fraction of the streaming
 * read 0.48 / 0.46 against main's 0.40 / 0.40 in the same run), large N = 30 1.15 / 1.18x, small N = 30 1.09 / 1.07x,
 * N = 100-all 0.97-1.06x; evicted (a 3 MB read before each call) the same within noise. Not kept (each against main
 * in the same run): a mark per 8-vertex block (TOUCH8: four bytes per dense block, then each marked accumulator)
 * no better (medium N = 30 1.20 / 1.14x against 1.18 / 1.15x); no marks at all (TOUCH_X -1: every block added back
 * and re-zeroed, the memset gone) 1.10 / 1.14x. */
#if W16
#ifdef TOUCH8
#define MK_SHIFT 7
#else
#define MK_SHIFT 9
#endif
#define ACC_PARAMS float *acc, unsigned char *mk,
#define ACC_ARGS(b, on) (on) ? acc + 128 * (b) : NULL, mk + ((b) << (9 - MK_SHIFT)),
#define MK_PARAM , unsigned char *mk, const int mk_on
#define MK_ARG , mk, mk_on
#ifndef TOUCH_X
#define TOUCH_X 2 /* the light's sparse blocks, per 8-vertex block of V, up to which the sparse pass marks its blocks */
#endif
#define MARK(e) if (mk_on) mk[(uint32_t)bofs[e] >> MK_SHIFT] = 1
#define SCRATCH(tid) float *acc = L->zacc + (i64)(tid) * (TV / 8) * 32; unsigned char *mk = L->tmark + (i64)(tid) * (TV / 8);
#define MK_ON const int mk_on = sb <= TOUCH_X * ((V + 7) / 8);
#define SCRATCH_ZERO if (ns && !rows && !mk_on) memset(mk, 1, (size_t)nb << (9 - MK_SHIFT)); /* every block added back */
/* block b's scratch dropped unread (its marks and accumulators zeroed: bench_wavelet_setup.py's sparse-pass probe, which
 * calls no dense block) */
#define SCRATCH_DROP(b)                                                                                      \
    for (int k_ = 0; k_ < 1 << (9 - MK_SHIFT); k_++)                                                         \
        if (mk[((b) << (9 - MK_SHIFT)) + k_]) {                                                              \
            mk[((b) << (9 - MK_SHIFT)) + k_] = 0;                                                            \
            memset(acc + 128 * (b) + ((1 << MK_SHIFT) >> 2) * k_, 0, (size_t)1 << MK_SHIFT);                \
        }
#ifdef TOUCH8 /* per 8-vertex block: the four marks read as one word, then each one's accumulator */
#define ADD_BACK                                                                                             \
    if (acc) {                                                                                               \
        uint32_t m_;                                                                                         \
        memcpy(&m_, mk, 4);                                                                                  \
        if (m_) {                                                                                            \
            memset(mk, 0, 4);                                                                                \
            for (int k = 0; k < 4; k++)                                                                      \
                if ((m_ >> (8 * k)) & 255)                                                                   \
                    for (int c = 0; c < CO; c++) {                                                           \
                        a[c][k] += ld8(acc + 32 * k + 8 * c);                                                \
                        st8(acc + 32 * k + 8 * c, (v8f){0});                                                 \
                    }                                                                                        \
        }                                                                                                    \
    }
#else
#define ADD_BACK                                                                                             \
    if (acc && *mk) {                                                                                        \
        *mk = 0;                                                                                             \
        for (int k = 0; k < 4; k++)                                                                          \
            for (int c = 0; c < CO; c++) {                                                                   \
                a[c][k] += ld8(acc + 32 * k + 8 * c);                                                        \
                st8(acc + 32 * k + 8 * c, (v8f){0});                                                         \
            }                                                                                                \
    }
#endif
#else
#define ACC_PARAMS const float *acc,
#define ACC_ARGS(b, on) (on) ? acc + 128 * (b) : NULL,
#define MK_PARAM
#define MK_ARG
#define MARK(e)
#define SCRATCH(tid) float *acc = L->acc + (i64)(tid) * (TV / 8) * 32;
#define MK_ON
#define SCRATCH_ZERO if (ns && !rows) memset(acc, 0, (size_t)(nb * 128) * sizeof(float));
#define SCRATCH_DROP(b)
#define ADD_BACK                                                                                             \
    if (acc)                                                                                                 \
        for (int k = 0; k < 4; k++) for (int c = 0; c < CO; c++) a[c][k] += ld8(acc + 32 * k + 8 * c);
#endif

#if W16 && defined(OUT_PFW) /* a measurement knob (bench_wavelet_scratch.py): the output lines OUT_PFW blocks ahead
                               * prefetched for writing before the dense terms (past the end: a prefetch, never a store) */
#define OUT_PF                                                                                               \
    for (int q_ = 0; q_ < OC * BV * 4; q_ += 64)                                                             \
        __builtin_prefetch((const char *)(uintptr_t)((uintptr_t)(out + OC * BV * (OUT_PFW)) + (uintptr_t)q_), 1);
#else
#define OUT_PF
#endif

/* one block of BV vertices over the nd dense terms (light lw [nd, 4]); acc: the block's four 8-vertex
 * accumulators [4][4 channels][8] of the sparse part, or NULL; CT, CO constants after inlining. Each
 * term's values are loaded one vector at a time with the CO light values held (CT = 1, CO = 3: 12 sums,
 * 3 lights, 1 value = 16 registers, no spill) */
#define DENSE_BLOCK(T)                                                                                       \
static inline __attribute__((always_inline)) void dense_block_##T(const int CT, const int CO, const int OC, i64 nd, \
        const i64 *ds, const float *lw, const T *blk, i64 stride, PAIR_PARAMS ACC_PARAMS const i64 *rp,        \
        const int32_t *rc, const T *rv, const float *lp, i64 nv, const int fm, const float *fc, const float *f,   \
        float *out, const int nt) {                                                                          \
    v8f a[4][4];                                                                                             \
    OUT_PF                                                                                                   \
    DENSE_TERMS(T)                                                                                           \
    if (lp && W16) ROWS_LOCKSTEP(T, ROW_G(CO)) /* AVX-512: the 8-vertex blocks in lockstep (above) */        \
    else if (lp) /* row-major sparse entries of the block's four 8-vertex blocks, the light looked up per  \
                  * column; two entries at a time into two sets of sums (one set: a multiply-add latency   \
                  * chain per entry) */                                                                    \
        for (int k = 0; k < 4; k++) {                                                                        \
            v8f s0[4], s1[4];                                                                                \
            for (int c = 0; c < CO; c++) { s0[c] = a[c][k]; s1[c] = (v8f){0}; }                             \
            i64 e = rp[k];                                                                                   \
            const i64 e1 = rp[k + 1];                                                                        \
            for (; e + 1 < e1; e += 2) {                                                                     \
                const float *l0 = lp + 4 * rc[e], *l1 = lp + 4 * rc[e + 1];                                  \
                const T *x0 = rv + e * 8 * CT, *x1 = x0 + 8 * CT;                                            \
                for (int c = 0; c < CO; c++) {                                                               \
                    s0[c] += load8_##T(x0 + (CT == 1 ? 0 : 8 * c)) * bc8(l0 + c);                            \
                    s1[c] += load8_##T(x1 + (CT == 1 ? 0 : 8 * c)) * bc8(l1 + c);                            \
                }                                                                                            \
            }                                                                                                \
            if (e < e1)                                                                                      \
                for (int c = 0; c < CO; c++) s0[c] += load8_##T(rv + e * 8 * CT + (CT == 1 ? 0 : 8 * c)) * bc8(lp + 4 * rc[e] + c); \
            for (int c = 0; c < CO; c++) a[c][k] = s0[c] + s1[c];                                            \
        }                                                                                                    \
    ADD_BACK                                                                                                 \
    /* OC output channels: CO, or 3 from one grey sum (an RGB light with equal channels, CO = 1); fm 0: f [nv, OC] a  \
     * factor per vertex and channel; 1: f [nv] one per vertex; 2: f [nv] times fc [OC] per channel (fl(f[v] fc[c]))  \
     * — the same products as fm 0 given f [V, OC] = fl(f[v] fc[c]), so the same bits */                    \
    if (OC == 3 && nv == BV) { /* RGB: each 8 vertices' sums interleaved in registers (permute + blend) */    \
        if (fm == 0)                                                                                         \
            for (int k = 0; k < 4; k++)                                                                      \
                store_rgb8(out + 24 * k, f + 24 * k, a[0][k], a[CO == 3 ? 1 : 0][k], a[CO == 3 ? 2 : 0][k]); \
        else if (fm == 1) /* one load of 8 factors, the same three multiplies before the interleave */      \
            for (int k = 0; k < 4; k++) {                                                                    \
                const v8f s = ld8(f + 8 * k);                                                                \
                put_rgb8(out + 24 * k, a[0][k] * s, a[CO == 3 ? 1 : 0][k] * s, a[CO == 3 ? 2 : 0][k] * s, nt); \
            }                                                                                                \
        else {                                                                                               \
            const v8f c0 = bc8(fc), c1 = bc8(fc + 1), c2 = bc8(fc + 2);                                      \
            for (int k = 0; k < 4; k++) {                                                                    \
                const v8f s = ld8(f + 8 * k);                                                                \
                put_rgb8(out + 24 * k, a[0][k] * (s * c0), a[CO == 3 ? 1 : 0][k] * (s * c1),                 \
                         a[CO == 3 ? 2 : 0][k] * (s * c2), nt);                                              \
            }                                                                                                \
        }                                                                                                    \
        return;                                                                                              \
    }                                                                                                        \
    float sums[4 * BV] __attribute__((aligned(32)));                                                         \
    for (int c = 0; c < CO; c++) for (int k = 0; k < 4; k++) st8(sums + c * BV + 8 * k, a[c][k]);           \
    if (fm) { /* one factor per vertex (times fc [OC] when fm = 2; 1 exactly otherwise) */                  \
        float fcv[4] = {1.0f, 1.0f, 1.0f, 1.0f};                                                             \
        if (fm == 2) for (int c = 0; c < OC; c++) fcv[c] = fc[c];                                            \
        for (i64 v = 0; v < nv; v++)                                                                         \
            for (int c = 0; c < OC; c++) out[OC * v + c] = sums[(CO == 1 ? 0 : c) * BV + v] * (f[v] * fcv[c]); \
    } else if (nv == BV) /* constant trip counts: vectorised */                                              \
        for (int v = 0; v < BV; v++)                                                                         \
            for (int c = 0; c < OC; c++) out[OC * v + c] = sums[(CO == 1 ? 0 : c) * BV + v] * f[OC * v + c]; \
    else                                                                                                     \
        for (i64 v = 0; v < nv; v++)                                                                         \
            for (int c = 0; c < OC; c++) out[OC * v + c] = sums[(CO == 1 ? 0 : c) * BV + v] * f[OC * v + c]; \
}
DENSE_BLOCK(float)
DENSE_BLOCK(int8_t)
DENSE_BLOCK(int16_t)

/* one sparse block e of a tile into its scratch: CO 8-lane read-modify-writes at byte offset bofs[e] */
#define SPARSE_BLOCK(T, e)                                                                                   \
    {                                                                                                        \
        float *a = (float *)((char *)acc + bofs[e]);                                                         \
        const T *x = bv + (e) * 8 * CT;                                                                      \
        if (CT == 1) {                                                                                       \
            const v8f w = load8_##T(x);                                                                      \
            for (int c = 0; c < CO; c++) st8(a + 8 * c, ld8(a + 8 * c) + w * l[c]);                          \
        } else                                                                                               \
            for (int c = 0; c < CO; c++) st8(a + 8 * c, ld8(a + 8 * c) + load8_##T(x + 8 * c) * l[c]);       \
    }
/* AVX-512 builds (W16): three blocks per loop step, their offsets and (CT = 1) values loaded first, then their
 * read-modify-writes in block order (a column's blocks in a tile are distinct 8-vertex blocks, and each vertex's
 * terms are still added in column order: the same bits), the last 0-2 blocks one at a time; each block's scratch
 * address formed once (PIN). Measured on an Intel Xeon (AVX-512, 3.3-3.5 GHz), one thread's CPU time
 * (benchmarks/bench_wavelet_colpass.py, reports/benchmarks/wavelet_colpass.md): the pass alone on the real blocks
 * 4.8-5.0 -> 4.4-4.6 cycles per block (1.07-1.10x); in the kernel, paired with main's, the light's sparse terms
 * alone 1.02-1.06x at N = 100, 1.05-1.10x at N = 300, 1.07-1.11x at N = 1000, whole lights 0.99-1.03x at N = 100-300
 * and 1.02-1.06x at N = 1000 (N >= 2000 take the row-major pass: 0.97-1.01x, code placement). What bounds the
 * pass is none of its parts alone (each removed alone saves at most 5-25%: the value loads most, the stores 3-9%,
 * the scratch loads 7-16%; a fixed trip count per range, i.e. no loop-exit mispredicts, 0.94-1.01x; the stores sent
 * to a second buffer, i.e. no store-to-load chains through the scratch, 0.85-0.92x). Not kept: 2 or 4 per step (no
 * better than 3), the tail's blocks sent to a dummy scratch instead of a remainder loop (0.92-0.97x), channels 0-1 as
 * one 16-lane read-modify-write (0.91-0.95x; 1.02-1.06x at 2 per step), a prefetch of the range after next's first
 * lines (no change; in the kernel 2 or 4 terms ahead: 0.99-1.04x) or of the block pointers 4-16 terms ahead
 * (0.98-1.02x), the pass out of line (0.94x: CT and CO no
 * longer constants); the tile's ranges listed first as one flat stream of blocks (per block its index and its term's
 * light row in two stack buffers, three blocks per step each with its own light: no loop exit per range; 2026-11-30,
 * paired with main on one layout, small, one thread's CPU time) 0.77-0.86x with the float dense loop and 0.83-0.88x
 * with DENSE_VNNI (more loads per block, and spills in the large inlined function; the dense-only light 0.89x too).
 * The tile count is what the ranges cost: one tile of 2272 vertices against two of 1152 (tile=, a layout choice in
 * relight.py) 1.06x at small studio N = 292 kept (both dense loops), 1.02-1.06x at sky N >= 300, 1.00-1.02x at
 * N <= 100; since 2026-11-30 the default where the relighter is built for one thread (relight.py _tile: one tile per
 * thread it is built for, at most 4096 vertices; the kernel unchanged). The next term's range bounds loaded before
 * this term's blocks (so that after a range's mispredicted exit the next range's chain of loads need not start
 * from its term's column): 0.95-1.04x, A/A 0.98-1.03 (small and medium, both dense loops, 21 repeats): noise.
 * At one thread (2026-11-30, branch sp17, paired with LIST_TERMS's kernel, small, load 1.8-3.0): the sparse pass of
 * every tile first, term by term, each tile into its own scratch (the same number of ranges, one light broadcast per
 * term; two tiles' scratch and tptr rows in L1 together) ~0.95x on the fourth row, sky N = 1000 0.97x; each tile's
 * empty (term) ranges skipped (per 64 terms the non-empty ranges listed branch-free first; 90 of the fourth row's 314
 * ranges are empty) 0.98-0.99x; every tile's sparse pass first, tile by tile (one switch from the sparse pass to the
 * zmm dense loop per call instead of per tile) 0.96-1.00x: none kept. The probes on a one-tile layout
 * (bench_wavelet_setup.py --tile 2272, three paired runs) gave the sparse pass 0.06-0.43 us less and the dense terms
 * 0.5-0.67 us less than on two tiles; timed in place in one build instead (branch tile18, bench_wavelet_setup.py --tsc:
 * rdtsc around each tile's sparse pass and each block's dense_block call, two relighters' calls alternated, an A/A
 * relighter; Intel Xeon family 6 model 167, load 1.1-2.1), one tile's dense blocks take the same time as two tiles'
 * (studio 292 kept -0.03 us [-0.19, +0.12], A/A -0.01) and the pass is what it saves (0.41 us [0.33, 0.50] of the
 * call's 0.47: 157 ranges against 224, ~20 cycles a range; sky N = 1000 2.44 us): the ranges after all, and no per-tile
 * cost in the dense phase (docs/wavelet_kernel_log.md "The tile follows the relighter's threads").
 * The AVX2 and avx512-256 builds keep one block per step, their machine code byte-identical to before (objdump; two and four per step measured no faster on AMD Zen 3, docs/wavelet_kernel_log.md). */
#if W16
/* the block's scratch address held in a register (an empty asm: gcc otherwise forms base + offset + 32 c by one lea
 * per channel, ~3 more uops per block, where one add and the stores' displacements do) */
#define PIN(p) __asm__("" : "+r"(p))
#define SPARSE_RANGE(T)                                                                                      \
    for (; e + 2 < e1; e += 3) {                                                                             \
        float *a0 = (float *)((char *)acc + bofs[e]), *a1 = (float *)((char *)acc + bofs[e + 1]),            \
              *a2 = (float *)((char *)acc + bofs[e + 2]);                                                    \
        PIN(a0); PIN(a1); PIN(a2);                                                                           \
        MARK(e); MARK(e + 1); MARK(e + 2);                                                                   \
        const T *x = bv + e * 8 * CT;                                                                        \
        if (CT == 1) {                                                                                       \
            const v8f w0 = load8_##T(x), w1 = load8_##T(x + 8), w2 = load8_##T(x + 16);                      \
            for (int c = 0; c < CO; c++) st8(a0 + 8 * c, ld8(a0 + 8 * c) + w0 * l[c]);                       \
            for (int c = 0; c < CO; c++) st8(a1 + 8 * c, ld8(a1 + 8 * c) + w1 * l[c]);                       \
            for (int c = 0; c < CO; c++) st8(a2 + 8 * c, ld8(a2 + 8 * c) + w2 * l[c]);                       \
        } else {                                                                                             \
            for (int c = 0; c < CO; c++) st8(a0 + 8 * c, ld8(a0 + 8 * c) + load8_##T(x + 8 * c) * l[c]);    \
            for (int c = 0; c < CO; c++) st8(a1 + 8 * c, ld8(a1 + 8 * c) + load8_##T(x + 8 * (CT + c)) * l[c]); \
            for (int c = 0; c < CO; c++) st8(a2 + 8 * c, ld8(a2 + 8 * c) + load8_##T(x + 8 * (2 * CT + c)) * l[c]); \
        }                                                                                                    \
    }                                                                                                        \
    for (; e < e1; e++) {                                                                                    \
        float *a = (float *)((char *)acc + bofs[e]);                                                         \
        PIN(a);                                                                                              \
        MARK(e);                                                                                             \
        const T *x = bv + e * 8 * CT;                                                                        \
        for (int c = 0; c < CO; c++) st8(a + 8 * c, ld8(a + 8 * c) + load8_##T(x + (CT == 1 ? 0 : 8 * c)) * l[c]); \
    }
#else
#define SPARSE_RANGE(T) for (; e < e1; e++) SPARSE_BLOCK(T, e)
#endif

/* AVX-512 builds (W16): each term's range start prefetched SP_PFR (2) terms ahead — the first line of its offsets bofs
 * and the first SP_PFL (2) lines of its values bv (the term index clamped to the last term: a cmov, no branch; a
 * prefetch never faults) — so that after a range's loop exit the next ranges' first lines are on their way from L2.
 * A light's sparse columns are a subset of the tile's (ascending), so its ranges are short runs (~10-20 blocks, 1-5
 * lines of values) with gaps between them that the hardware prefetchers do not cross, and in a call the dense pass
 * of the tile before has moved them out of L1. Measured on an Intel Xeon (family 6 model 167, AVX-512), one thread's
 * CPU time, small blocker scene: the column-major pass in the call 6.47 us at studio 292 kept (3167 blocks, 6.8
 * cycles a block) against 5.12 re-run right after itself (probe 'sparse twice', bench_wavelet_setup.py); paired with
 * the kernel without it on one layout (bench_wavelet_setup.py --pair, --variant, load 2.0-2.6): studio N = 100-all
 * 1.014-1.037x (two runs), sky 0.99-1.01x, N = 10 0.98-1.01x (A/A 0.99-1.02). Measured and not kept: 1 term ahead
 * 1.01-1.02x, 4 ahead 1.00-1.02x, 2 ahead with 4 lines 1.01-1.03x; the tile's whole scratch prefetched for writing
 * before its pass (SP_PFS, when the light's sparse blocks are at least one per 8-vertex block) 0.97-0.99x at studio
 * N = 10-2000, sky N = 300 0.97x: the scratch is not what the pass waits for; the range bounds' tptr line 6 or 12
 * terms ahead besides (SP_PFT) 0.99-1.02x, noise. Section 7 at small in one session (load 1.2-2.4), the streaming
 * read: studio 292 kept 0.49 [0.45, 0.55] against 0.47 [0.45, 0.52] with SP_PFR 0. What is left of the pass's excess:
 * re-run right after itself it takes 5.12 us (4.94 with this), in the call 6.39-6.47: ~1 us a call still outside L1
 * (docs/wavelet_kernel_log.md, "The sparse pass's in-call cost"). SP_PFR 0: off (a measurement knob).
 * The 8-lane builds: none (their object code unchanged, objcopy). */
#ifndef SP_PFR
#define SP_PFR 2
#endif
#if W16 && SP_PFR > 0
#ifndef SP_PFL
#define SP_PFL 2
#endif
#ifdef SP_PFT /* a measurement knob: the range bounds' line (tp) SP_PFT terms ahead prefetched too */
#define SP_TP_PF __builtin_prefetch(tp + ss[t + SP_PFT < ns ? t + SP_PFT : ns - 1]);
#else
#define SP_TP_PF
#endif
#define SP_RANGE_PF                                                                                          \
    {                                                                                                        \
        SP_TP_PF                                                                                             \
        const i64 f_ = tp[ss[t + SP_PFR < ns ? t + SP_PFR : ns - 1]];                                        \
        __builtin_prefetch(bofs + f_);                                                                       \
        for (int q_ = 0; q_ < SP_PFL; q_++) __builtin_prefetch((const char *)(bv + f_ * 8 * CT) + 64 * q_);  \
    }
#else
#define SP_RANGE_PF
#endif
#if W16 && defined(SP_PFS) /* a measurement knob: the tile's whole scratch prefetched for writing before its sparse pass
                             * when the light's sparse blocks are at least SP_PFS per 8-vertex block of V (scaled by 8) */
#define SP_SCRATCH_PF                                                                                        \
    if (ns && !rows && 8 * sb >= (SP_PFS) * ((V + 7) / 8))                                                   \
        for (i64 q_ = 0; q_ < nb * 512; q_ += 64) __builtin_prefetch((const char *)acc + q_, 1);
#else
#define SP_SCRATCH_PF
#endif

/* the sparse terms' blocks of one tile into its scratch acc (zeroed), column-major; lw [ns, 4] the terms' light */
#define SPARSE_TILE(T)                                                                                       \
static inline __attribute__((always_inline)) void sparse_tile_##T(const int CT, const int CO, i64 ns,        \
        const i64 *ss, const float *lw, const int32_t *tp, const int32_t *bofs, const T *bv, float *acc MK_PARAM) { \
    for (i64 t = 0; t < ns; t++) {                                                                           \
        v8f l[4];                                                                                            \
        for (int c = 0; c < CO; c++) l[c] = bc8(lw + 4 * t + c);                                             \
        SP_RANGE_PF                                                                                          \
        const i64 e1 = tp[ss[t] + 1];                                                                        \
        i64 e = tp[ss[t]];                                                                                   \
        SPARSE_RANGE(T)                                                                                      \
    }                                                                                                        \
}
SPARSE_TILE(float)
SPARSE_TILE(int8_t)
SPARSE_TILE(int16_t)

/* the light per column lp [P, 4] (zero on entry; a column listed twice adds its values) and each listed
 * column's class in mark [P]: light channel c of output c (a grey light C = 1 on a coloured transfer:
 * channel 0 for all three), without a branch per term (restrict: the byte stores of mark would otherwise
 * make every later load wait for them). Returns the sparse blocks of the distinct columns listed (cblk [P]:
 * a column's sparse blocks over all tiles; counted at a column's first listing, while its mark is 0). */
static inline i64 gather_light(i64 N, const i64 *restrict sel, const float *restrict lv, i64 C, i64 CO,
                               const unsigned char *restrict cls, const int32_t *restrict cblk, unsigned char *restrict mark,
                               float *restrict lp) {
    i64 sb = 0;
#if DVNNI /* su19: an RGB light's terms 16 at a time transposed to rows (r, g, b, 0), one 16-byte add per term into lp (the
           * same float additions per channel, in the same order: the same bits); the rest as below */
    i64 n0 = 0;
    if (C == 3)
        for (; n0 + 16 <= N; n0 += 16) {
            float rw[64] __attribute__((aligned(64)));
            const __m512 r = _mm512_loadu_ps(lv + n0), g = _mm512_loadu_ps(lv + N + n0), b = _mm512_loadu_ps(lv + 2 * N + n0);
            const __m512 z = _mm512_setzero_ps();
            const __m512d lo = _mm512_castps_pd(_mm512_unpacklo_ps(r, g)), bl = _mm512_castps_pd(_mm512_unpacklo_ps(b, z)),
                          hi = _mm512_castps_pd(_mm512_unpackhi_ps(r, g)), bh = _mm512_castps_pd(_mm512_unpackhi_ps(b, z));
            /* rows 4k + i in vector i's 128-bit lane k */
            _mm512_store_pd((double *)rw, _mm512_unpacklo_pd(lo, bl));
            _mm512_store_pd((double *)(rw + 16), _mm512_unpackhi_pd(lo, bl));
            _mm512_store_pd((double *)(rw + 32), _mm512_unpacklo_pd(hi, bh));
            _mm512_store_pd((double *)(rw + 48), _mm512_unpackhi_pd(hi, bh));
            for (int m = 0; m < 16; m++) {
                const i64 j = sel[n0 + m];
                float *q = lp + 4 * j;
                sb += cblk[j] & -(i64)(mark[j] == 0);
                mark[j] = cls[j];
                _mm_storeu_ps(q, _mm_add_ps(_mm_loadu_ps(q), _mm_load_ps(rw + 16 * (m & 3) + 4 * (m >> 2))));
            }
        }
#else
    const i64 n0 = 0;
#endif
    if (C == 3)
        for (i64 n = n0; n < N; n++) {
            const i64 j = sel[n];
            float *q = lp + 4 * j;
            sb += cblk[j] & -(i64)(mark[j] == 0);
            mark[j] = cls[j];
            q[0] += lv[n]; q[1] += lv[N + n]; q[2] += lv[2 * N + n];
        }
    else if (C == 1)
        for (i64 n = 0; n < N; n++) {
            const i64 j = sel[n];
            float *q = lp + 4 * j;
            const float x = lv[n];
            sb += cblk[j] & -(i64)(mark[j] == 0);
            mark[j] = cls[j];
            for (int c = 0; c < CO; c++) q[c] += x;
        }
    else
        for (i64 n = 0; n < N; n++) {
            const i64 j = sel[n];
            sb += cblk[j] & -(i64)(mark[j] == 0);
            mark[j] = cls[j];
            for (int c = 0; c < CO; c++) lp[4 * j + c] += lv[c * N + n];
        }
    return sb;
}

/* the transfer's layout and the scratch, built once per transfer (relight.py: an int64 tensor of
 * these fields in this order; pointers as integers) */
typedef struct {
    i64 P, Pd, V, CT;           /* Haar coefficients 6R^2, dense columns, vertices, transfer channels */
    i64 TV, NT, MT;             /* vertices per tile (a multiple of 32), tiles, threads the scratch holds */
    const int32_t *tptr;        /* [NT, P+1] each tile's sparse columns' first block, relative to tbase */
    const i64 *tbase;           /* [NT] the tile's first block */
    const int32_t *bofs;        /* [NB] the block's accumulator: byte offset in its tile's scratch */
    const void *bvals;          /* [NB, CT, 8] stored values of the sparse blocks */
    const int32_t *dslot;       /* [P] the column's dense slot, or -1 (read for the listed dense terms: LIST_TERMS in W16 builds, N <= SMALL_N) */
    const void *dense;          /* [ceil(V/32), Pd, CT, 32] stored values of the dense columns */
    float *acc;                 /* scratch [MT, TV/8, 4, 8] */
    i64 *wk;                    /* scratch [P]: the dense terms' slots, then (from Pd) the sparse terms' columns */
    float *lw;                  /* scratch [P, 4]: their light */
    const i64 *dcol;            /* [Pd] the dense slot's column (ascending with relight.py's default dense_order) */
    const unsigned char *cls;   /* [P] the column's class: 0 empty, 1 sparse, 2 dense */
    unsigned char *mark;        /* scratch [P]: 1 the column is one of the light's sparse terms, 2 a dense one */
    float *lp;                  /* scratch [P, 4]: the light per column, zero between calls (the row-major pass reads it for
                                 * every column: zero for the columns the light does not hold) */
    const i64 *rptr;            /* [4 ceil(V/32) + 1] the row-major copy of the sparse part: 8-vertex block b's entries
                                 * (NULL: not built yet — a light choosing the row-major pass returns 3) */
    const int32_t *rcol;        /* [NR] the entry's column */
    const void *rvals;          /* [NR, CT, 8] its stored values */
    i64 NR, row_permille;       /* entries; the row-major pass is taken when the light's sparse terms hold at least
                                 * row_permille / 1000 of the sparse blocks (> 1000: never) */
    const int32_t *cblk;        /* [P] the column's sparse blocks over all tiles (0: dense or empty) */
    float *zacc;                /* W16 builds' scratch [MT, TV/8, 4, 8], zero between calls (the touched map below) */
    unsigned char *tmark;       /* W16 builds' scratch [MT, TV/8]: a tile's touched blocks, zero between calls */
    const int32_t *dtmax;       /* [Pd] the dense column's largest stored magnitude |T| (16-bit values; NULL: not held):
                                 * read by the DENSE_VNNI loop's column-maximum rule only (the light's int16 scales) */
    const double *dnorm;        /* [Pd + 1] float64: the dense column's L2 norm over the vertices of the quantisation scale
                                 * times the stored value, ||scale (.) T_:,k||_2, then ||scale||_2 (16-bit values on a grey
                                 * transfer; NULL: not held): read by the DENSE_VNNI loop's flush groups only (vnni_quantise) */
} wavelet_layout;

#define TILE_CASE(T, CT_, CO_, OC_)                                                                          \
    SP_SCRATCH_PF                                                                                            \
    if (ns && !rows) sparse_tile_##T(CT_, CO_, ns, sw, sl, tp, bofs, bv, acc MK_ARG);                        \
    PAIR_KEEP                                                                                                \
    for (i64 b = 0; b < nb; b++) {                                                                           \
        const i64 v0 = vt + b * BV, nv = V - v0 < BV ? V - v0 : BV;                                          \
        dense_block_##T(CT_, CO_, OC_, nd, wk, lw, dense + v0 * Pd * CT_, BV * CT_, PAIR_ARGS(b, nb, Pd * BV * CT_) \
                        ACC_ARGS(b, ns && !rows)                                                             \
                        L->rptr + v0 / 8, L->rcol, rvals, rows ? lp : NULL, nv, OC_ == 3 && CT_ == 1 ? fm : 0, fc, f + (fm ? 1 : OC_) * v0, \
                        out + OC_ * v0, nt_out);                                                     \
    }

/* one tile t's work (the unit of the threads' split): its scratch zeroed, its sparse blocks, its dense blocks and
 * their outputs (WAVELET_KERNEL's locals) */
#define TILE_BODY(T)                                                                                         \
        int tid = 0;                                                                                         \
        TID(tid);                                                                                            \
        SCRATCH(tid) /* W16: zacc and tmark, zero between calls; else acc, zeroed below */                   \
        const i64 vt = t * TV, nvt = V - vt < TV ? V - vt : TV, nb = (nvt + BV - 1) / BV;                    \
        const int32_t *tp = L->tptr + t * (P + 1), *bofs = L->bofs + L->tbase[t];                           \
        const T *bv = bvals + L->tbase[t] * 8 * CT;                                                          \
        SCRATCH_ZERO                                                                                         \
        if (CT == 3) { TILE_CASE(T, 3, 3, 3) }                                                               \
        else if (grey) { TILE_CASE(T, 1, 1, 3) }                                                             \
        else switch (CO) {                                                                                   \
            case 1: { TILE_CASE(T, 1, 1, 1) } break;                                                         \
            case 2: { TILE_CASE(T, 1, 2, 2) } break;                                                         \
            case 3: { TILE_CASE(T, 1, 3, 3) } break;                                                         \
            default: { TILE_CASE(T, 1, 4, 4) } break;                                                        \
        }

/* One thread in the AVX-512 build (W16): the tiles in a plain loop before (instead of) the OpenMP region — `omp parallel
 * for ... if(nt > 1)` still enters libgomp at one thread (a team set up and torn down). Measured on an Intel Xeon
 * (AVX-512), one thread's CPU time, paired with main's kernel on one layout (bench_wavelet_setup.py --pair, five runs,
 * load 3.6-6; A/A 0.97-1.02x): N = 10 1.09-1.14x (~0.4 us a call: the region's entry, as the call's probes give it:
 * 0.35-0.47 us, now 0.02-0.09), N = 100-all 1.02-1.09x (0.5-4 us). The same loop with main's pragma simply removed
 * measured 0.98-1.17x in four runs, so beyond the entry the gain moves with code placement; copying the region's shared variables
 * (firstprivate) gained nothing (0.997-1.010x). Outputs bit-identical (each vertex's terms in the same order). The
 * AVX2 and avx512-256 builds expand SERIAL_TILES to nothing: their .text is main's, byte for byte (objcopy),
 * as it was tuned on an AMD Zen 3 that this change was not measured on. */
#if W16
#define SERIAL_TILES(T) if (nt == 1) { for (i64 t = 0; t < NT; t++) { TILE_BODY(T) } } else
#else
#define SERIAL_TILES(T)
#endif

#define F1 256 /* C | F1: the factor one per vertex (f [V + 4]: f [V], then fc [4] the output channels' multipliers) */
#if W16 && defined(OUT_NT) /* a measurement knob (bench_wavelet_factor.py --nt): streaming stores for outputs of at least OUT_NT bytes */
#define NT_OUT_SET(x, bytes, out) x = (bytes) >= (OUT_NT) && ((uintptr_t)(out) & 31) == 0
#define NT_OUT_FENCE(x) if (x) _mm_sfence()
#else
#define NT_OUT_SET(x, bytes, out) (void)(out)
#define NT_OUT_FENCE(x) (void)(x)
#endif

/* The term lists (WAVELET_KERNEL, N > SMALL_N). AVX-512 builds with BW (W16): both lists from one scan of the P marks,
 * 64 per step (vptestmb of the dense bit 2 and the sparse bit 1 to two masks, then each mask's set bits): the dense
 * terms in column order, which is slot order under relight.py's default dense_order 'column' (dcol sorted; other orders:
 * column order still, the 8-lane listing's slot order then differs),
 * their slot from dslot [P] int32; the sparse terms in column order, as before — the same lists, the same order, so the
 * same bits. Before (the 8-lane builds' code, kept there byte for byte: avx2, znver3, avx512-256 and portable objects
 * identical to 2913585's, objcopy): a pass over the Pd dense slots (one mark load per slot) and a scan of the marks 8
 * per step (a 64-bit word, its sparse bits), 0.39 + 0.76 us of the fourth row's 1.7 us set-up (bench_wavelet_setup.py,
 * small studio 292 kept: Pd = 259, P = 6144); now 0.59 together. Measured on the Intel Xeon (family 6 model 167), one
 * thread's CPU time, paired with 2913585 on one layout: small studio N = 300 .. all 1.045-1.049x (19.1 -> 18.2 us; load
 * 1.4-1.7, A/A 0.99-1.00), other rows 0.98-1.01x; with evicted calls and medium (bench_wavelet_scratch.py,
 * reports/benchmarks/wavelet_listing.md, load 3.4-5.5) warm 1.04-1.06x on that row, the rest 0.94-1.07x (A/A
 * 0.99-1.04); section 7's fraction of the fourth row 0.45 (main 0.42). */
#if W16 && defined(__AVX512BW__)
#define LIST_TERMS                                                                                           \
    i64 nd = 0, ns = 0;                                                                                      \
    i64 *sw = wk + Pd;                                                                                       \
    float *sl = lw + 4 * Pd;                                                                                 \
    for (i64 w = 0; w < (small ? 0 : P); w += 64) {                                                          \
        const __mmask64 in_ = P - w >= 64 ? ~(__mmask64)0 : ((__mmask64)1 << (P - w)) - 1;                  \
        const __m512i m_ = _mm512_maskz_loadu_epi8(in_, mark + w);                                           \
        uint64_t xd = _mm512_test_epi8_mask(m_, _mm512_set1_epi8(2));                                        \
        uint64_t xs = rows ? 0 : _mm512_test_epi8_mask(m_, _mm512_set1_epi8(1));                             \
        while (xd) {                                                                                         \
            const i64 j = w + __builtin_ctzll(xd);                                                           \
            xd &= xd - 1;                                                                                    \
            wk[nd] = L->dslot[j];                                                                            \
            memcpy(lw + 4 * nd, lp + 4 * j, 4 * sizeof(float));                                              \
            nd++;                                                                                            \
        }                                                                                                    \
        while (xs) {                                                                                         \
            const i64 j = w + __builtin_ctzll(xs);                                                           \
            xs &= xs - 1;                                                                                    \
            sw[ns] = j;                                                                                      \
            memcpy(sl + 4 * ns, lp + 4 * j, 4 * sizeof(float));                                              \
            ns++;                                                                                            \
        }                                                                                                    \
    }
#else
#define LIST_TERMS                                                                                           \
    i64 nd = 0;                                                                                              \
    for (i64 s = 0; s < (small ? 0 : Pd); s++) {                                                             \
        const i64 j = L->dcol[s];                                                                            \
        wk[nd] = s;                                                                                          \
        memcpy(lw + 4 * nd, lp + 4 * j, 4 * sizeof(float));                                                  \
        nd += mark[j] >> 1;                                                                                  \
    }                                                                                                        \
    /* the sparse terms in column order (their blocks are then read front to back, the prefetcher's order),  \
     * found 8 marks at a time, after the dense list's Pd places */                                          \
    i64 *sw = wk + Pd;                                                                                       \
    float *sl = lw + 4 * Pd;                                                                                 \
    i64 ns = 0;                                                                                              \
    for (i64 w = 0; w < (rows || small ? 0 : P); w += 8) {                                                   \
        uint64_t x = 0; /* a constant-size copy (a variable one is a libc call: ~2.5 us per call over P = 6144) */ \
        if (P - w >= 8) memcpy(&x, mark + w, 8); else memcpy(&x, mark + w, (size_t)(P - w));                \
        x &= 0x0101010101010101ull;                                                                          \
        while (x) {                                                                                          \
            const i64 j = w + (__builtin_ctzll(x) >> 3);                                                     \
            x &= x - 1;                                                                                      \
            sw[ns] = j;                                                                                      \
            memcpy(sl + 4 * ns, lp + 4 * j, 4 * sizeof(float));                                              \
            ns++;                                                                                            \
        }                                                                                                    \
    }
#endif

#define WAVELET_KERNEL(NAME, T)                                                                              \
int NAME(const wavelet_layout *L, i64 N, const i64 *sel, const float *lv, i64 C, const float *f, float *out,  \
         i64 threads) {                                                                                      \
    const i64 P = L->P, Pd = L->Pd, V = L->V, CT = L->CT, TV = L->TV, NT = L->NT;                            \
    const T *dense = (const T *)L->dense, *bvals = (const T *)L->bvals;                                      \
    float *lw = L->lw;                                                                                       \
    i64 *wk = L->wk;                                                                                         \
    /* C | F1 (256): f [V + 4] one factor per vertex, then one per output channel (below); else f [V, OC]; DVNNI  \
     * builds: C | FDENSE (512) the float dense loop (other builds refuse the bit: 1, as any other high bit) */  \
    VNNI_FLAG                                                                                                \
    const int f1 = C >> 8 == 1;                                                                              \
    C -= f1 ? F1 : 0;                                                                                        \
    if (C < 1 || C > 4 || (CT == 3 && C != 1 && C != 3)) return 1;                                          \
    uint64_t bad = 0; /* no exit per term: vectorised */                                                     \
    for (i64 n = 0; n < N; n++) bad |= (uint64_t)sel[n] >= (uint64_t)P;                                      \
    if (bad) return 2;                                                                                       \
    /* an RGB light whose three channels are equal (a grey environment given as RGB) on a grey transfer:      \
     * one sum per vertex, written to all three outputs with their own factors (a third of the multiply-adds \
     * and of the scratch's read-modify-writes) */                                                           \
    int grey = C == 3 && CT == 1;                                                                            \
    for (i64 n = 0; grey && n < N; n++) { /* a coloured light stops at its first coloured term */           \
        uint32_t a, b, c;                                                                                    \
        memcpy(&a, lv + n, 4); memcpy(&b, lv + N + n, 4); memcpy(&c, lv + 2 * N + n, 4);                     \
        grey = ((a ^ b) | (a ^ c)) == 0;                                                                     \
    }                                                                                                        \
    const i64 CO = grey ? 1 : C > CT ? C : CT;                                                               \
    /* the factor's form (fm, TILE_CASE): 0 f [V, OC]; 1 f [V]; 2 f [V] times fc [OC] = f + V, a channel's not 1 */ \
    const float *fc = f1 ? f + V : NULL;                                                                     \
    const i64 OCn = CT == 3 || grey ? 3 : CO;                                                                \
    if (f1 && (OCn != 3 || CT != 1)) return 1; /* a per-vertex factor: RGB outputs of a grey transfer only */   \
    int fm = f1;                                                                                             \
    for (i64 c = 0; f1 && c < OCn; c++) fm = fc[c] != 1.0f ? 2 : fm;                                         \
    /* OUT_NT builds (W16): the output by streaming stores when it holds at least OUT_NT bytes (32-byte aligned) */ \
    int nt_out = 0;                                                                                          \
    NT_OUT_SET(nt_out, V * OCn * (i64)sizeof(float), out);                                                   \
    /* the light per column (duplicates add), and a mark per column (its class: 0 no vertex keeps it — not    \
     * read —, 1 sparse, 2 dense; 3264 of the 5900 sparse columns at N = all on the blocker scene) — without a branch per  \
     * term: in the light's order dense and sparse terms alternate, and a branch on the form mispredicted     \
     * about every other term (measured: ~5-10 ns per term, a third of the time at N = all) */                \
    unsigned char *mark = L->mark;                                                                           \
    float *lp = L->lp; /* zero for every column on entry: this call's columns are zeroed again at its end */  \
    memset(mark, 0, (size_t)P);                                                                              \
    const i64 sb = gather_light(N, sel, lv, C, CO, L->cls, L->cblk, mark, lp);                               \
    /* the row-major pass when the light's sparse terms hold at least row_permille / 1000 of the sparse blocks: \
     * each 8-vertex block's entries into the dense block's register sums (no scratch, no read-modify-write), \
     * the light looked up per column in lp (zero for the columns it does not hold); else the column-major   \
     * pass into the tiles' scratch over the sparse terms listed below */                                    \
    const int rows = sb && L->NR && L->row_permille <= 1000 && sb * 1000 >= L->row_permille * L->NR;          \
    MK_ON /* W16: whether the column-major pass marks the blocks it touches (else every block is added back) */   \
    if (rows && !L->rptr) { /* the row-major copy is built on first need (relight.py): none yet, nothing done */ \
        for (i64 n = 0; n < N; n++) memset(lp + 4 * sel[n], 0, 4 * sizeof(float));                           \
        return 3;                                                                                            \
    }                                                                                                        \
    /* the dense terms in slot order (each block's values are then read front to back), written always and   \
     * kept by advancing the count */                                                                        \
    /* few terms (N <= SMALL_N): both lists from the light's own terms, unsorted (below), instead of a       \
     * pass over the Pd dense slots and a scan of the P marks (measured per call, against that listing:      \
     * 1.18-1.36x at N = 1, 1.21-1.23x at 10, 1.05-1.10x at 100; bench_wavelet_setup_variants.py);           \
     * N < P - Pd keeps the lists' unconditional writes inside wk and lw */                                  \
    const int small = N <= SMALL_N && N < P - Pd;                                                            \
    LIST_TERMS /* the dense terms in slot order, then the sparse ones in column order (W16 + BW: one scan) */   \
    if (small) { /* dense terms (a dense mark consumed: a repeated column once), then sparse */              \
        for (i64 n = 0; n < N; n++) {                                                                        \
            const i64 j = sel[n];                                                                            \
            const unsigned m = mark[j];                                                                      \
            wk[nd] = L->dslot[j];                                                                            \
            memcpy(lw + 4 * nd, lp + 4 * j, 4 * sizeof(float));                                              \
            nd += m >> 1;                                                                                    \
            mark[j] = (unsigned char)(m & 1);                                                                \
        }                                                                                                    \
        for (i64 n = 0; n < (rows ? 0 : N); n++) {                                                           \
            const i64 j = sel[n];                                                                            \
            const unsigned m = mark[j];                                                                      \
            sw[ns] = j;                                                                                      \
            memcpy(sl + 4 * ns, lp + 4 * j, 4 * sizeof(float));                                              \
            ns += m & 1;                                                                                     \
            mark[j] = 0;                                                                                     \
        }                                                                                                    \
    }                                                                                                        \
    const T *rvals = (const T *)L->rvals;                                                                    \
    int nt = (int)(threads < 1 ? 1 : threads > L->MT ? L->MT : threads);                                     \
    (void)nt;                                                                                                \
    VNNI_SETUP(T) /* DVNNI builds: the dense light quantised (DENSE_VNNI; nothing in the others) */               \
    SERIAL_TILES(T) /* AVX-512 builds at one thread: the tiles in a plain loop, no OpenMP region (above) */       \
    _Pragma("omp parallel for schedule(static) num_threads(nt) if(nt > 1)")                                 \
    for (i64 t = 0; t < NT; t++) { TILE_BODY(T) }                                                            \
    for (i64 n = 0; n < N; n++) memset(lp + 4 * sel[n], 0, 4 * sizeof(float));                               \
    NT_OUT_FENCE(nt_out);                                                                                    \
    return 0;                                                                                                \
}

#ifdef _OPENMP
#define TID(x) x = omp_get_thread_num()
#else
#define TID(x) (void)x
#endif

WAVELET_KERNEL(prt_wavelet_relight_f32, float)
WAVELET_KERNEL(prt_wavelet_relight_i8, int8_t)
WAVELET_KERNEL(prt_wavelet_relight_i16, int16_t)

/* the same kernels with their arguments packed in one int64 array a [8] = (layout, N, sel, lv, C, f, out, threads),
 * pointers as integers: a ctypes call converts one argument instead of eight (measured: ~0.23 against ~1.03 us per
 * call through functools.partial, benchmarks/bench_wavelet_call.py), the fixed cost a render loop pays per frame
 * (relight.py: WaveletRelighter.prepared packs them once) */
#define PACKED(NAME)                                                                                         \
int NAME##_packed(const i64 *a) {                                                                            \
    return NAME((const wavelet_layout *)(intptr_t)a[0], a[1], (const i64 *)(intptr_t)a[2],                   \
                (const float *)(intptr_t)a[3], a[4], (const float *)(intptr_t)a[5], (float *)(intptr_t)a[6], a[7]); \
}
PACKED(prt_wavelet_relight_f32)
PACKED(prt_wavelet_relight_i8)
PACKED(prt_wavelet_relight_i16)
