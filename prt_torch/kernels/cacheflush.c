/* cacheflush.c: write back and evict address ranges from every cache level (library "cacheflush", called by
 * prt_torch/harness/timing.py, flush_caches / measure_paired_cold).
 *
 * Cold-cache timing needs a timed call's inputs and outputs in memory, not in any cache. Reading a buffer
 * several times the last-level cache evicts them too, but its cost grows with the cache (on a VM that lists a
 * 480 MiB L3: 1920 MiB per eviction); flushing exactly the lines the call touches costs in proportion to
 * the data. Per 64-byte line (x86-64: the CLFLUSH line size from CPUID leaf 1; aarch64: CTR_EL0's DminLine):
 *  - x86-64 with CLFLUSHOPT (a build for a CPU that has it, __CLFLUSHOPT__): _mm_clflushopt per line, then
 *    _mm_sfence (CLFLUSHOPT is ordered by SFENCE, Intel SDM vol. 2A "CLFLUSHOPT");
 *  - other x86-64: _mm_clflush per line (SSE2, every x86-64 CPU), then _mm_mfence;
 *  - aarch64: "dc civac" per line (clean and invalidate to the point of coherence; Linux lets EL0 issue it),
 *    then "dsb ish";
 *  - elsewhere: nothing (prt_flush_method returns 0 and the caller reads its junk buffer instead).
 * A flushed dirty line is written back to memory here, not in the timed call that follows, and the data
 * are unchanged (a flush never modifies memory). The ranges must be mapped and readable (the caller passes
 * tensor storages); a range of length 0 is skipped. */

#include <stddef.h>
#include <stdint.h>

#if defined(__x86_64__)
#include <cpuid.h>
#include <immintrin.h>
#define PRT_FLUSH_X86 1
#elif defined(__aarch64__)
#define PRT_FLUSH_ARM 1
#endif

/* The method this build uses: 0 none, 1 clflush, 2 clflushopt, 3 dc civac. */
int prt_flush_method(void) {
#if defined(PRT_FLUSH_X86) && defined(__CLFLUSHOPT__)
    return 2;
#elif defined(PRT_FLUSH_X86)
    return 1;
#elif defined(PRT_FLUSH_ARM)
    return 3;
#else
    return 0;
#endif
}

/* The flush granule in bytes (64 where the CPU does not say). */
int prt_flush_line_bytes(void) {
#if defined(PRT_FLUSH_X86)
    unsigned int a = 0, b = 0, c = 0, d = 0;
    if (__get_cpuid(1, &a, &b, &c, &d)) {
        unsigned int line = ((b >> 8) & 0xffu) * 8u;
        if (line >= 16u && line <= 512u) return (int)line;
    }
    return 64;
#elif defined(PRT_FLUSH_ARM)
    uint64_t ctr;
    __asm__ volatile("mrs %0, ctr_el0" : "=r"(ctr));
    return 4 << ((ctr >> 16) & 0xf);
#else
    return 64;
#endif
}

/* Flush ranges [ptrs[i], ptrs[i] + lens[i]) for i < n from every cache level, then fence. Returns 0, or 1
 * where this build has no flush instruction (nothing done). */
int prt_flush_ranges(int64_t n, const int64_t *ptrs, const int64_t *lens) {
#if defined(PRT_FLUSH_X86) || defined(PRT_FLUSH_ARM)
    const uintptr_t line = (uintptr_t)prt_flush_line_bytes();
    for (int64_t i = 0; i < n; i++) {
        if (lens[i] <= 0) continue;
        uintptr_t p = (uintptr_t)ptrs[i] & ~(line - 1);
        const uintptr_t end = (uintptr_t)ptrs[i] + (uintptr_t)lens[i];
        for (; p < end; p += line) {
#if defined(PRT_FLUSH_X86) && defined(__CLFLUSHOPT__)
            _mm_clflushopt((void *)p);
#elif defined(PRT_FLUSH_X86)
            _mm_clflush((const void *)p);
#else
            __asm__ volatile("dc civac, %0" : : "r"(p) : "memory");
#endif
        }
    }
#if defined(PRT_FLUSH_X86) && defined(__CLFLUSHOPT__)
    _mm_sfence();
#elif defined(PRT_FLUSH_X86)
    _mm_mfence();
#else
    __asm__ volatile("dsb ish" : : : "memory");
#endif
    return 0;
#else
    (void)n;
    (void)ptrs;
    (void)lens;
    return 1;
#endif
}
