/* machine_bounds.c: what this CPU can do at most, measured in the same process as the sweep
 * (clothbench/harness/bounds.py builds and calls it; docs/bounds.md says how the numbers are
 * used). Built with OpenMP; every test runs on `threads` threads (0 = OpenMP's default, all
 * the process may use). Each thread times short chunks of its own work and keeps its fastest
 * chunk, and the threads' rates add up: a core shared with another process (a scheduler's
 * time slice is milliseconds long) costs some chunks, not the measurement. An upper estimate
 * of what the machine does, which is what a lower bound on a step needs.
 *
 * Memory: STREAM's triad a[i] = b[i] + s*c[i] and scale c[i] = s*a[i] (a copy's traffic:
 *   one read stream, one write stream; written as a scale because a plain copy loop becomes a
 *   memcpy call whose large-size path uses non-temporal stores, which no kernel here does).
 *   Bytes counted as STREAM counts them: 3 (triad) or 2 (scale) arrays x element size per
 *   element, no write-allocate reads, the same convention bounds.py uses for the cloth step.
 *   The arrays are allocated (huge pages advised, on Linux) and first touched here, by the
 *   threads that later stream them.
 * Arithmetic: many independent chains (8 vectors of 16 floats, or 16 of 8 doubles, per
 *   thread) so the rate is the unit's throughput, not an operation's latency. Each chain
 *   stays at a fixed normal value (never 0, 1 or subnormal, which some dividers finish
 *   early). The extra multiply in the sqrt chains runs on the FMA ports, beside the divider,
 *   and is not counted.
 *
 * Built twice by the host: once exact (-ffp-contract=off: add and multiply stay separate, as
 * in a strict kernel) for everything but the rsqrt and reciprocal tests, and once with
 * -ffast-math for those: on AVX-512 they time kernels/fast_math.cl's estimates and Newton
 * steps, what the fast cloth kernels compute, and mb_newton_fp_* say how many adds and
 * multiplies those Newton steps are; elsewhere the compiler's own 1/sqrtf and division under
 * fast math.
 */

/* No system #include: the host resolves includes itself (clothbench/kernel_source.py), so the
 * few library functions used are declared here; sqrt is the compiler's builtin. */
typedef __SIZE_TYPE__ size_t;
extern double omp_get_wtime(void);
extern int omp_get_max_threads(void);
extern int omp_get_thread_num(void);
extern int omp_get_num_threads(void);
extern int posix_memalign(void **memptr, size_t alignment, size_t size);
extern void free(void *ptr);
#define sqrtf(v) __builtin_sqrtf(v)
#define sqrt(v) __builtin_sqrt(v)

#define LANES_F32 128 /* floats per thread in flight: 8 vectors of 16 (AVX-512) */
#define LANES_F64 128 /* doubles per thread: 16 vectors of 8 */
#define ALIGN 64

static int team(int threads)
{
    return threads > 0 ? threads : omp_get_max_threads();
}

int mb_threads(void)
{
    return omp_get_max_threads();
}

/* Keeps a value alive without a store the compiler could drop. */
static volatile double sink;

/* ---- memory ----------------------------------------------------------------------------- */

#if defined(__linux__)
extern int madvise(void *addr, size_t length, int advice);
#define MB_MADV_HUGEPAGE 14 /* Linux's MADV_HUGEPAGE: fewer page faults at first touch */
#endif

static float *alloc_floats(size_t n)
{
    void *p = 0;
    size_t bytes = n * sizeof(float);
    if (posix_memalign(&p, 2u << 20, bytes) != 0)
        return 0;
#if defined(__linux__)
    madvise(p, bytes, MB_MADV_HUGEPAGE); /* advice only: ignored where there are none */
#endif
    return (float *)p;
}

/* STREAM triad and scale over three arrays of `n` floats, allocated once. Each thread streams
 * its own share (the one it first touched) in chunks of CHUNK_FLOATS and times every chunk
 * and every whole pass over its share; rates[0] and rates[1] get the sum over threads of each
 * thread's fastest triad and scale chunk, rates[2] and rates[3] of its fastest whole triad and
 * scale pass, over `rounds` passes of each. A chunk is short (under a millisecond) beside a
 * scheduler's time slice, so a thread preempted by another process loses that chunk, not the
 * measurement; a thread that streams while another is preempted can only see more
 * bandwidth, never less. Returns 0, or -1 when the arrays could not be allocated. */
#define CHUNK_FLOATS (1L << 19) /* 2 MiB of each array */
int mb_stream(size_t n, int threads, int rounds, double *rates)
{
    float *a = alloc_floats(n), *b = alloc_floats(n), *c = alloc_floats(n);
    for (int k = 0; k < 4; ++k)
        rates[k] = 0.0;
    if (!a || !b || !c) {
        free(a);
        free(b);
        free(c);
        return -1;
    }
    int t = team(threads);
    long ln = (long)n;
    volatile float scale_v = 0.75f; /* not a constant the compiler could fold into the loop */
    float s = scale_v;
    double chunk_triad = 0.0, chunk_scale = 0.0, pass_triad = 0.0, pass_scale = 0.0, seen = 0.0;
#pragma omp parallel num_threads(t) reduction(+ : chunk_triad, chunk_scale, pass_triad, pass_scale, seen)
    {
        int me = omp_get_thread_num(), all = omp_get_num_threads();
        long lo = ln * me / all, hi = ln * (me + 1) / all;
        for (long i = lo; i < hi; ++i) { /* first touch: this thread's pages are its own */
            a[i] = 0.0f;
            b[i] = 1.0f + (float)(i & 1023) * 1e-3f;
            c[i] = 2.0f - (float)(i & 511) * 1e-3f;
        }
        double best[4] = {0.0, 0.0, 0.0, 0.0}; /* chunk triad, chunk scale, pass triad, pass scale */
        for (int r = 0; r < 2 * rounds; ++r) { /* a triad pass, then a scale pass */
            int is_triad = r % 2 == 0;
            double arrays = is_triad ? 3.0 : 2.0;
            double pass_start = omp_get_wtime();
            for (long start = lo; start < hi; start += CHUNK_FLOATS) {
                long end = start + CHUNK_FLOATS < hi ? start + CHUNK_FLOATS : hi;
                double t0 = omp_get_wtime();
                if (is_triad) {
#pragma omp simd
                    for (long i = start; i < end; ++i)
                        a[i] = b[i] + s * c[i];
                } else {
                    /* a's chunk was written a whole pass ago: out of the caches by now */
#pragma omp simd
                    for (long i = start; i < end; ++i)
                        c[i] = s * a[i];
                }
                double seconds = omp_get_wtime() - t0;
                double rate = arrays * (double)(end - start) * sizeof(float) / seconds;
                if (seconds > 0 && rate > best[!is_triad])
                    best[!is_triad] = rate;
            }
            double seconds = omp_get_wtime() - pass_start;
            double rate = arrays * (double)(hi - lo) * sizeof(float) / seconds;
            if (seconds > 0 && rate > best[2 + !is_triad])
                best[2 + !is_triad] = rate;
        }
        chunk_triad += best[0];
        chunk_scale += best[1];
        pass_triad += best[2];
        pass_scale += best[3];
        seen += hi > lo ? (double)(a[lo] + c[hi - 1]) : 0.0; /* the stores are read: not dead */
    }
    sink = seen;
    rates[0] = chunk_triad;
    rates[1] = chunk_scale;
    rates[2] = pass_triad;
    rates[3] = pass_scale;
    free(a);
    free(b);
    free(c);
    return 0;
}

/* ---- arithmetic ------------------------------------------------------------------------- */

/* One chain kernel: rounds over LANES values per thread, `ops` counted operations per value
 * per round, in chunks of CHUNK rounds (tens of microseconds) until `seconds` have passed.
 * Each thread times every chunk and keeps its fastest, and the threads' rates add up: the
 * units are per core, so a thread that starts late or is preempted by another process for
 * a while (its core was busy) loses those chunks, not the measurement. Returns operations
 * per second of all threads, the best of `repeats` runs. */
#define CHUNK 1024
#define CHAIN_TEST(name, type, lanes, start, ops, body) CHAIN_TEST_W(name, type, lanes, 1, start, ops, body)
/* the same, `width` values of x at a time: a body of explicit vectors (VEC(x, j)) */
#define CHAIN_TEST_W(name, type, lanes, width, start, ops, body)                               \
    double name(double seconds, int threads, int repeats)                                      \
    {                                                                                          \
        int t = team(threads);                                                                 \
        double best = 0.0;                                                                     \
        volatile type knob = (type)(start);                                                   \
        for (int r = 0; r < repeats; ++r) {                                                    \
            double rate = 0.0, total = 0.0;                                                    \
            _Pragma("omp parallel num_threads(t) reduction(+ : rate, total)")                  \
            {                                                                                  \
                type x[lanes] __attribute__((aligned(ALIGN)));                                 \
                type k = knob;                                                                 \
                for (int j = 0; j < lanes; ++j)                                                \
                    x[j] = k + (type)j * (type)(1.0 / 4096.0);                                 \
                double t0 = omp_get_wtime(), now = t0, fastest = 1e30;                         \
                do {                                                                           \
                    double before = now;                                                       \
                    for (int it = 0; it < CHUNK; ++it) {                                       \
                        _Pragma("omp simd aligned(x : ALIGN)")                                 \
                        for (int j = 0; j < lanes; j += (width))                               \
                            body;                                                              \
                    }                                                                          \
                    now = omp_get_wtime();                                                     \
                    if (now - before < fastest)                                                \
                        fastest = now - before;                                                \
                } while (now - t0 < seconds);                                                  \
                rate += (double)(ops) * (double)(lanes) * (double)CHUNK / fastest;             \
                for (int j = 0; j < lanes; ++j)                                                \
                    total += (double)x[j];                                                     \
            }                                                                                  \
            sink = total;                                                                      \
            if (rate > best)                                                                   \
                best = rate;                                                                   \
        }                                                                                      \
        return best;                                                                           \
    }

/* x = sqrt(x) * 1.37 settles at 1.37^2; x = 1.7 / x alternates between x0 and 1.7 / x0. */
#if !defined(MB_FAST)
CHAIN_TEST(mb_sqrt_f32, float, LANES_F32, 1.37f, 1, x[j] = sqrtf(x[j]) * k)
CHAIN_TEST(mb_div_f32, float, LANES_F32, 1.3f, 1, x[j] = (k + 0.4f) / x[j])
/* one sqrt and one division per value and round: pairs per second (ops = 1) */
CHAIN_TEST(mb_sqrt_div_f32, float, LANES_F32, 1.3f, 1, x[j] = sqrtf((k + 0.4f) / x[j]) * 1.1f)
/* a multiply and an add, not fused (-ffp-contract=off): 2 operations */
CHAIN_TEST(mb_addmul_f32, float, LANES_F32, 1.3f, 2, x[j] = x[j] * 0.999f + 0.0013f)
CHAIN_TEST(mb_sqrt_f64, double, LANES_F64, 1.37, 1, x[j] = sqrt(x[j]) * k)
CHAIN_TEST(mb_div_f64, double, LANES_F64, 1.3, 1, x[j] = (k + 0.4) / x[j])
CHAIN_TEST(mb_sqrt_div_f64, double, LANES_F64, 1.3, 1, x[j] = sqrt((k + 0.4) / x[j]) * 1.1)
CHAIN_TEST(mb_addmul_f64, double, LANES_F64, 1.3, 2, x[j] = x[j] * 0.999 + 0.0013)
#elif defined(__AVX512F__)
/* The fast kernels' own estimates with one Newton step (kernels/fast_math.cl, included as the
 * OpenCL kernels include it), 16 lanes at a time: x = rsqrt(x) settles at 1, x = 1 / (x + 0.4)
 * at 0.82 (an estimate has no early finish at 1, unlike a divider). The compiler's own
 * 1 / sqrtf under -ffast-math is a square-root estimate, a reciprocal estimate and a Newton
 * step for each, about twice the work (docs/bounds.md). */
#define V 16
#define INLINE static inline
typedef float floatv __attribute__((vector_size(64)));
#define FLOATV_ZERO ((floatv){0.0f})
#include "fast_math.cl"
#define VEC(a, j) (*(floatv *)&(a)[j])
CHAIN_TEST_W(mb_rsqrt_f32, float, LANES_F32, 16, 1.37f, 1, VEC(x, j) = fast_rsqrt(VEC(x, j)))
CHAIN_TEST_W(mb_recip_f32, float, LANES_F32, 16, 1.3f, 1, VEC(x, j) = fast_recip(VEC(x, j) + 0.4f))
/* the adds and multiplies of those Newton steps, as fast_math.cl writes them contracted: the
 * rsqrt's y * y, 0.5 * x, 1.5 - a * b, y * (); the reciprocal's 2 - x * y, y * () */
int mb_newton_fp_rsqrt(void)
{
    return 4;
}
int mb_newton_fp_recip(void)
{
    return 2;
}
#else
/* x = 1.37 / sqrt(x) settles at 1.37^(2/3): the estimate and its Newton step under -ffast-math;
 * x = 1.3 / (x + 0.4) settles at 0.96: a division fast math may take as a reciprocal estimate
 * (not the exact tests' 1.7 / x, which fast math folds: two rounds give x back) */
CHAIN_TEST(mb_rsqrt_f32, float, LANES_F32, 1.37f, 1, x[j] = k / sqrtf(x[j]))
CHAIN_TEST(mb_recip_f32, float, LANES_F32, 1.3f, 1, x[j] = k / (x[j] + 0.4f))
/* the fast kernels take the built-ins here (fast_math.cl), whose work beside an estimate is
 * not known: none counted */
int mb_newton_fp_rsqrt(void)
{
    return 0;
}
int mb_newton_fp_recip(void)
{
    return 0;
}
#endif
