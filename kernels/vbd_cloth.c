/* vbd_cloth.c: the VBD step (docs/vbd.md: implicit Euler by Vertex Block Descent) in C with
 * OpenMP. Host code: clothbench/backends/c/vbd.py; build: docs/c.md.
 *
 * Built with the Verlet kernel's -D options (CLOTH_N, the collider counts, CLOTH_DOUBLE,
 * CLOTH_STRICT) and its source included below, for the one collider code the step shares
 * with it (docs/vbd.md: colliders are the Verlet step's projections) and its types; the
 * Verlet library itself includes none of this file.
 *   strict  docs/vbd.md's operations in its order, every one rounded on its own (the host
 *           builds with -ffp-contract=off): NumPy's float32 (and float64) bit for bit.
 *   fast    contraction, and s = k - (k rest) / L from one 1/sqrt per spring.
 * The numbers (h, m/h^2, b/h, k, g h^2, rest lengths, the Chebyshev weights) are arguments,
 * rounded once on the host (clothbench/backends/kernel_inputs.py VbdConstants).
 *
 * State: x (position at the start of the substep) and v (velocity) as x | y | z planes, w
 * (inverse mass, 0 = pinned) in its own plane; y (the inertial target) and X (the iterate) are
 * scratch planes, and with Chebyshev B holds the inputs of the last two sweeps.
 *
 * Work split: a sweep takes the colours 0..3 in order (docs/vbd.md "Vertex colours": colour =
 * 2 (row mod 2) + ((col + row div 2) mod 2)), so a colour is every other row and, in a row,
 * every other column; its rows are split over the threads, a barrier between colours. In an
 * interior row (2..n-3) the interior columns of the colour (all 12 neighbours present) are
 * one `omp simd` loop with no bounds checks; the rest goes through the bounds-checked
 * particle. The threads split rows only, never one particle's work: no bit depends on them.
 * The per-particle passes (predict, Chebyshev, collide and update) split the rows the same
 * way every substep, so a thread reads only what it wrote there, or what a barrier published.
 *
 * CLOTH_SELF (the scene's [self_collision], docs/vbd.md): after the last sweep (and Chebyshev)
 * the final iterate goes through verlet_cloth.c's pass as the Verlet step calls it (bucket_row,
 * sort_buckets on one thread, contact_row: pushed, then collided) into y, free once the sweeps
 * are done, and the update reads y, colliding nothing again. Three barriers more per substep.
 */

#include "verlet_cloth.c"

/* libgomp's own entry points (no system headers here, see verlet_cloth.c) */
int omp_get_thread_num(void);
int omp_get_num_threads(void);

/* The constants, as the host packs them (one array of real), the Chebyshev weights after. */
enum { V_H, V_MH2, V_BH, V_K, V_GX, V_GY, V_GZ, V_REST0, V_REST1, V_REST2, V_OMEGA };

typedef struct {
    real h, mh2, bh, k, gx, gy, gz, rest[3];
    real kr[3]; /* fast only: k * rest */
} vbd_constants;

#ifdef CLOTH_SELF
#define VBD_CONTACT_PARAMS , const real *contact_numbers, long long exclude2, int *cells
#define CONTACT_ARG , const contact *ct
#define CONTACT_PASS , ct
#else
#define VBD_CONTACT_PARAMS
#define CONTACT_ARG
#define CONTACT_PASS
#endif

/* A barrier among the threads, none on one thread: the serial path calls no OpenMP function
 * (a child forked after its parent ran a parallel region steps that way, docs/c.md). */
#define BARRIER(threads)              \
    do {                              \
        if ((threads) > 1) {          \
            _Pragma("omp barrier");   \
        }                             \
    } while (0)

/* One particle's Newton step (docs/vbd.md, "One particle's step") from the iterate X: its
 * new position in (ox, oy, oz). `interior` (a constant where inlined): all 12 neighbours
 * present, no bounds checks. */
INLINE void vbd_particle(const vbd_constants *c, int interior, int row, int col, const real *restrict X,
                         const real *restrict y, const real *restrict x0, const real *restrict w, real *ox,
                         real *oy, real *oz)
{
    const int i = row * N + col;
    const real xi = X[i], yi = X[N2 + i], zi = X[2 * N2 + i];
    real cnt = 12; /* the springs the particle has: an exact small integer */
    if (!interior) {
        cnt = 0;
        for (int o = 0; o < 12; ++o) {
            int r = row + DR[o], cc = col + DC[o];
            cnt += (r >= 0 && r < N && cc >= 0 && cc < N) ? (real)1 : (real)0;
        }
    }
    const real cb = cnt * c->bh, hd = c->mh2 + cb;
    real fx = (xi - y[i]) * c->mh2 + (xi - x0[i]) * cb;
    real fy = (yi - y[N2 + i]) * c->mh2 + (yi - x0[N2 + i]) * cb;
    real fz = (zi - y[2 * N2 + i]) * c->mh2 + (zi - x0[2 * N2 + i]) * cb;
    real hxx = hd, hyy = hd, hzz = hd, hxy = 0, hxz = 0, hyz = 0;
#pragma GCC unroll 12 /* whole, before the vectoriser sees the interior loop (a loop in it stops it) */
    for (int o = 0; o < 12; ++o) {
        if (!interior) {
            int r = row + DR[o], cc = col + DC[o];
            if (r < 0 || r >= N || cc < 0 || cc >= N)
                continue;
        }
        const int j = i + DR[o] * N + DC[o];
        const real dx = xi - X[j], dy = yi - X[N2 + j], dz = zi - X[2 * N2 + j];
        const real L2 = (dx * dx + dy * dy) + dz * dz;
        const int on = L2 > 0; /* coincident (or not a number): nothing added */
#ifdef CLOTH_STRICT
        const real s = c->k * ((real)1 - c->rest[o / 4] / SQRT(L2));
#else
        const real s = c->k - c->kr[o / 4] * ((real)1 / SQRT(L2));
#endif
        const real a = s > 0 ? s : (real)0; /* a select, as NumPy's where: k max(1 - rest/L, 0) */
        const real bb = (c->k - a) / L2;
        const real bx = bb * dx, by = bb * dy, bz = bb * dz;
        /* computed always, kept where the spring counts: the SIMD loop keeps its lanes */
        fx = on ? fx + dx * s : fx;
        fy = on ? fy + dy * s : fy;
        fz = on ? fz + dz * s : fz;
        hxx = on ? hxx + (a + bx * dx) : hxx;
        hyy = on ? hyy + (a + by * dy) : hyy;
        hzz = on ? hzz + (a + bz * dz) : hzz;
        hxy = on ? hxy + bx * dy : hxy;
        hxz = on ? hxz + bx * dz : hxz;
        hyz = on ? hyz + by * dz : hyz;
    }
    /* H p = f by LDL^T, docs/vbd.md's order */
    const real l10 = hxy / hxx, l20 = hxz / hxx;
    const real d1 = hyy - l10 * hxy;
    const real t = hyz - l20 * hxy;
    const real l21 = t / d1;
    const real d2 = (hzz - l20 * hxz) - l21 * t;
    const real z1 = fy - l10 * fx;
    const real z2 = (fz - l20 * fx) - l21 * z1;
    const real pz = z2 / d2;
    const real py = z1 / d1 - l21 * pz;
    const real px = (fx / hxx - l10 * py) - l20 * pz;
    const int move = (w[i] != 0) & (hxx > 0) & (d1 > 0) & (d2 > 0); /* pinned: never moved */
    *ox = move ? xi - px : xi;
    *oy = move ? yi - py : yi;
    *oz = move ? zi - pz : zi;
}

/* A bounds-checked particle, in place: the neighbours are of other colours, so nothing this
 * colour writes is read by it. */
static void border_vbd_particle(const vbd_constants *c, int row, int col, real *restrict X, const real *restrict y,
                                const real *restrict x0, const real *restrict w)
{
    const int i = row * N + col;
    real ox, oy, oz;
    vbd_particle(c, 0, row, col, X, y, x0, w, &ox, &oy, &oz);
    X[i] = ox;
    X[N2 + i] = oy;
    X[2 * N2 + i] = oz;
}

/* The particles of one colour in `row`: columns first, first + 2, ... Never inlined, so its
 * `restrict` is about one colour's pass (see PASS below). */
static __attribute__((noinline)) void sweep_row(const vbd_constants *c, int row, int first, real *restrict X,
                                                const real *restrict y, const real *restrict x0,
                                                const real *restrict w)
{
    if (row < 2 || row >= N - 2) {
        for (int col = first; col < N; col += 2)
            border_vbd_particle(c, row, col, X, y, x0, w);
        return;
    }
    int col = first;
    for (; col < 2; col += 2)
        border_vbd_particle(c, row, col, X, y, x0, w);
    /* The interior: every new position into a row buffer, then into X. Written in place, a
     * lane that keeps its position (pinned) is a masked store at stride 2, which GCC cannot
     * vectorise (the loop runs scalar); no particle of a colour reads another, so writing
     * them after all are computed gives the same bits. Numbers as locals: verlet_cloth.c
     * step_row says why. */
    const vbd_constants local = *c;
    const int count = (N - 2 - col + 1) / 2;
    real ox[N / 2 + 1], oy[N / 2 + 1], oz[N / 2 + 1];
#pragma omp simd
    for (int m = 0; m < count; ++m)
        vbd_particle(&local, 1, row, col + 2 * m, X, y, x0, w, &ox[m], &oy[m], &oz[m]);
    for (int m = 0; m < count; ++m) {
        const int i = row * N + col + 2 * m;
        X[i] = ox[m];
        X[N2 + i] = oy[m];
        X[2 * N2 + i] = oz[m];
    }
    for (int cc = (N - 2) + (((N - 2) - first) & 1); cc < N; cc += 2) /* the first of the colour >= n-2 */
        border_vbd_particle(c, row, cc, X, y, x0, w);
}

/* Rows [lo, hi) of this thread's share of `count` rows. */
#define SHARE(count, tid, threads, lo, hi) \
    const int lo = (int)((long)(count) * (tid) / (threads)), hi = (int)((long)(count) * ((tid) + 1) / (threads))

/* The passes over rows [lo, hi) of one thread, each a function of its own, never inlined:
 * `restrict` may hold within one pass (between two barriers), never across a barrier, where
 * other threads write the same buffers through their own pointers. */
#define PASS static __attribute__((noinline))

/* predict: y = (x + v h) + g h^2; the first iterate y, or x where pinned */
PASS void predict_rows(const vbd_constants *c, int lo, int hi, const real *restrict x, const real *restrict v,
                       const real *restrict w, real *restrict y, real *restrict X, real *restrict B, int chebyshev)
{
    const real g[3] = {c->gx, c->gy, c->gz};
    for (int a = 0; a < 3; ++a)
        for (int i = a * N2 + lo * N; i < a * N2 + hi * N; ++i) {
            const real ya = (x[i] + v[i] * c->h) + g[a];
            y[i] = ya;
            X[i] = w[i - a * N2] != 0 ? ya : x[i];
        }
    if (chebyshev) /* the input of sweep 0 */
        for (int a = 0; a < 3; ++a)
            for (int i = a * N2 + lo * N; i < a * N2 + hi * N; ++i)
                B[i] = X[i];
}

/* Chebyshev after sweep k: X = omega (X - before) + before where free and k > 0; then
 * `before` takes X, the input of sweep k + 1 */
PASS void chebyshev_rows(int lo, int hi, int k, real omega, const real *restrict w, real *restrict X,
                         real *restrict before)
{
    for (int a = 0; a < 3; ++a)
        for (int i = a * N2 + lo * N; i < a * N2 + hi * N; ++i) {
            const int extrapolate = (k > 0) & (w[i - a * N2] != 0);
            const real e = extrapolate ? omega * (X[i] - before[i]) + before[i] : X[i];
            X[i] = e;
            before[i] = e;
        }
}

/* collide (free particles only; with CLOTH_SELF the pass has, and X is its output), then
 * v = (X - x) / h, x = X. Each plane through a pointer
 * of its own: through one, x[N2 + i] of iteration i is x[i'] of iteration i' = i + N2, and
 * GCC's predictive commoning carried values across that, writing back rows of the other
 * threads (measured: 2 threads at 4^2 in float64 gave different bits from run to run). */
PASS void update_rows(const vbd_constants *c, const real *colliders, int lo, int hi, real *restrict x0,
                      real *restrict x1, real *restrict x2, real *restrict v0, real *restrict v1, real *restrict v2,
                      const real *restrict w, const real *restrict X0, const real *restrict X1,
                      const real *restrict X2)
{
#ifndef CLOTH_SELF
    real table[COLLIDER_REALS]; /* as locals: see verlet_cloth.c step_row */
    for (int k = 0; k < COLLIDER_REALS; ++k)
        table[k] = colliders[k];
#else
    (void)colliders;
#endif
    const real h = c->h;
    for (int i = lo * N; i < hi * N; ++i) {
        real px = X0[i], py = X1[i], pz = X2[i];
#ifndef CLOTH_SELF
        collide(table, &px, &py, &pz);
#endif
        const int free = w[i] != 0;
        px = free ? px : X0[i];
        py = free ? py : X1[i];
        pz = free ? pz : X2[i];
        v0[i] = (px - x0[i]) / h;
        v1[i] = (py - x1[i]) / h;
        v2[i] = (pz - x2[i]) / h;
        x0[i] = px;
        x1[i] = py;
        x2[i] = pz;
    }
}

/* Every substep of an advance, on thread `tid` of `threads`. No `restrict` here: the buffers
 * are written by every thread between the barriers. */
static void vbd_run(const vbd_constants *c, const real *omega, const real *colliders, real *x, real *v,
                    const real *w, real *y, real *X, real *B, int iterations, int chebyshev, int substeps, int tid,
                    int threads CONTACT_ARG)
{
    SHARE(N, tid, threads, lo, hi);
    for (int s = 0; s < substeps; ++s) {
        predict_rows(c, lo, hi, x, v, w, y, X, B, chebyshev);
        BARRIER(threads);
        for (int k = 0; k < iterations; ++k) {
            for (int colour = 0; colour < 4; ++colour) {
                const int parity = colour >> 1, bit = colour & 1;
                SHARE((N - parity + 1) / 2, tid, threads, first, end);
                for (int r = first; r < end; ++r) {
                    const int row = parity + 2 * r;
                    sweep_row(c, row, (bit + (row >> 1)) & 1, X, y, x, w);
                }
                BARRIER(threads);
            }
            if (chebyshev) {
                /* B[(k + 1) & 1] holds the input of sweep k - 1, and then of sweep k + 1 */
                chebyshev_rows(lo, hi, k, omega[k], w, X, B + ((k + 1) & 1) * 3 * N2);
                BARRIER(threads);
            }
        }
#ifdef CLOTH_SELF
        /* [self_collision]: the final iterate (published by the last barrier) keyed, sorted,
         * then pushed and collided into y; the update reads this thread's rows of y */
        for (int row = lo; row < hi; ++row)
            bucket_row(ct, row, X);
        BARRIER(threads);
        if (tid == 0)
            sort_buckets(ct, X);
        BARRIER(threads);
        for (int row = lo; row < hi; ++row)
            contact_row(ct, colliders, row, X, y, w);
        update_rows(c, colliders, lo, hi, x, x + N2, x + 2 * N2, v, v + N2, v + 2 * N2, w, y, y + N2, y + 2 * N2);
        BARRIER(threads); /* the next predict writes X, which the pass reads in every row */
#else
        /* the next predict reads only this thread's rows: no barrier until after it */
        update_rows(c, colliders, lo, hi, x, x + N2, x + 2 * N2, v, v + N2, v + 2 * N2, w, X, X + N2, X + 2 * N2);
#endif
    }
}

/* Advance `substeps` substeps of VBD on `threads` threads: x and v (x|y|z planes) in place;
 * y, X and (with chebyshev) B = 2 * 3 n^2 values are scratch. With CLOTH_SELF the pass's
 * numbers, exclude2 and work space follow, as cloth_advance takes them. */
void cloth_vbd_advance(real *x, real *v, const real *w, real *y, real *X, real *B, const real *numbers,
                       const real *colliders, int iterations, int chebyshev, int substeps,
                       int threads VBD_CONTACT_PARAMS)
{
    vbd_constants c;
    c.h = numbers[V_H];
    c.mh2 = numbers[V_MH2];
    c.bh = numbers[V_BH];
    c.k = numbers[V_K];
    c.gx = numbers[V_GX];
    c.gy = numbers[V_GY];
    c.gz = numbers[V_GZ];
    for (int kind = 0; kind < 3; ++kind) {
        c.rest[kind] = numbers[V_REST0 + kind];
        c.kr[kind] = c.k * c.rest[kind];
    }
    const real *omega = numbers + V_OMEGA;
#ifdef CLOTH_SELF
    const contact contact_constants = contact_of(contact_numbers, exclude2, cells);
    const contact *ct = &contact_constants;
#endif
    if (threads <= 1) {
        FP_ENTER;
        vbd_run(&c, omega, colliders, x, v, w, y, X, B, iterations, chebyshev, substeps, 0, 1 CONTACT_PASS);
        FP_LEAVE;
        return;
    }
#pragma omp parallel num_threads(threads) firstprivate(c)
    {
        FP_ENTER;
        vbd_run(&c, omega, colliders, x, v, w, y, X, B, iterations, chebyshev, substeps, omp_get_thread_num(),
                omp_get_num_threads() CONTACT_PASS);
        FP_LEAVE;
    }
}
