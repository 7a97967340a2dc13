/* verlet_cloth.c: the mass-spring cloth step (docs/semantics.md) in C with OpenMP, the CPU
 * path as a performance engineer writes it. Host code: clothbench/backends/c/verlet.py;
 * build and measurements: docs/c.md.
 *
 * Built per scene by clothbench/native.py with -D options, so the compiler folds them:
 *   CLOTH_N                grid side n: strides, bounds and the interior range are constants.
 *   CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_BOXES, CLOTH_PLANES
 *                          collider counts (clothbench/model/colliders/kinds.py): each kind's loop
 *                          unrolls, an absent kind vanishes.
 *   CLOTH_DOUBLE           float64 (the fast reference for accuracy figures); else float32.
 *   CLOTH_SELF             the scene's [self_collision] pass (docs/semantics.md, "Self-collision")
 *                          between the position update and the colliders; without it nothing of
 *                          the pass is compiled.
 *   CLOTH_STRICT           every operation in the order docs/semantics.md fixes, damping once
 *                          per spring, sqrt and '/': with -ffp-contract=off and no fast math
 *                          the result is NumPy's bit for bit (float32 and float64 alike).
 *                          Without it (fast): the damping of all springs is added once, each
 *                          spring costs one 1/sqrt (a correctly rounded sqrt and divide: no
 *                          fast math, see docs/c.md), and the host lets the compiler contract.
 * The numbers (k, b, dt, dt2, g, rest lengths, the collider table) are arguments, rounded once
 * on the host (clothbench/model/kernel_inputs.py), so a dt or stiffness sweep builds nothing.
 *
 * Layout: positions as three planes x | y | z of n*n values, PLANE apart (below); w (inverse
 * mass, 0 = pinned) in its own plane. Two state buffers, ping-ponged by the step count: a
 * particle reads its own previous position and nothing else of that buffer, so x(t+dt) overwrites x(t-dt) in
 * place and the buffer that held x(t) is the next step's previous position. No copy, and one
 * state written per step instead of two (pos_out and pos_prev_out, as the GPU kernels do).
 *
 * Work split: rows over OpenMP threads (static, so a thread keeps the same rows, in its own
 * cache, every step); within a row the interior columns 2..n-3 of interior rows (all 12
 * neighbours present: no bounds checks, springs unrolled) are one SIMD loop across columns,
 * the two-wide frame goes through the bounds-checked particle. One parallel region covers
 * all the steps of an advance, with the loop's barrier between steps.
 *
 * No #include: the host resolves includes itself and has no system headers to give
 * (clothbench/kernel_source.py); this file needs nothing from libc or libm (sqrt is the
 * compiler's builtin, one instruction with -fno-math-errno).
 */

#ifndef CLOTH_N
#error "CLOTH_N (grid side) must be defined"
#endif
#define N CLOTH_N
#define N2 (N * N)
/* The distance between the x, y and z planes of a state buffer: n*n values and a pad
 * (CLOTH_PLANE_PAD, set by this step's host; 0 where another kernel includes this file and
 * keeps its planes n*n apart). Without one, at n = 1024 or 2048 each plane starts 4 or 16 MiB
 * after the last, so the same column of every plane, and of the 5 rows the stencil reads
 * (4 KiB apart), falls in one L1 set and on the same 4 KiB alias: 20-28% of the step with the
 * buffers' own alignment (docs/c.md, "Planes apart"). */
#ifndef CLOTH_PLANE_PAD
#define CLOTH_PLANE_PAD 0
#endif
#define PLANE (N2 + CLOTH_PLANE_PAD)

#ifdef CLOTH_DOUBLE
typedef double real;
#define SQRT(v) __builtin_sqrt(v)
#define ABS(v) __builtin_fabs(v)
#else
typedef float real;
#define SQRT(v) __builtin_sqrtf(v)
#define ABS(v) __builtin_fabsf(v)
#endif

#define INLINE static inline __attribute__((always_inline))

/* The constants, as the host packs them (one array of real). */
enum { K_K, K_B, K_DT, K_DT2, K_GX, K_GY, K_GZ, K_REST0, K_REST1, K_REST2, K_COUNT };

/* The collider table, reals per collider of each kind (kernel_inputs.collider_rows). */
#define SPHERE_REALS 4   /* centre, radius */
#define CYLINDER_REALS 12 /* (start, length), (unit axis, radius), (radial_r, 0) */
#define BOX_REALS 16     /* (centre, 0), (axis i, half extent i) for i = 0, 1, 2 */
#define PLANE_REALS 8    /* (point, 0), (unit normal, 0) */
#define FIRST_CYLINDER (SPHERE_REALS * CLOTH_SPHERES)
#define FIRST_BOX (FIRST_CYLINDER + CYLINDER_REALS * CLOTH_CYLINDERS)
#define FIRST_PLANE (FIRST_BOX + BOX_REALS * CLOTH_BOXES)
#define COLLIDER_REALS (FIRST_PLANE + PLANE_REALS * CLOTH_PLANES + 1)

/* The 12-spring stencil (d_row, d_col) in the order every backend sums it (scene.OFFSETS):
 * 0-3 structural, 4-7 shear, 8-11 bend. */
static const int DR[12] = {0, 0, -1, 1, -1, -1, 1, 1, -2, -2, 2, 2};
static const int DC[12] = {-1, 1, 0, 0, -1, 1, -1, 1, -2, 2, -2, 2};

/* Strict arithmetic must not depend on a flush-to-zero mode some other library left in the
 * thread (Taichi sets it process-wide): NumPy keeps subnormals, so strict threads clear
 * MXCSR's FTZ and DAZ bits for the run and restore them after. */
#if defined(CLOTH_STRICT) && (defined(__x86_64__) || defined(__i386__))
#define MXCSR_FTZ_DAZ ((1u << 15) | (1u << 6))
#define FP_ENTER unsigned saved_mxcsr = __builtin_ia32_stmxcsr(); __builtin_ia32_ldmxcsr(saved_mxcsr & ~MXCSR_FTZ_DAZ)
#define FP_LEAVE __builtin_ia32_ldmxcsr(saved_mxcsr)
#else
#define FP_ENTER
#define FP_LEAVE
#endif

typedef struct {
    real k, b, dt, dt2, gx, gy, gz, rest[3];
    real kr[3]; /* fast only: k * rest, so a spring is one multiply-add off 1/L */
    real damp;  /* fast only: b / dt, the damping of one spring per unit displacement */
} constants;

/* One spring's force on x from its neighbour at (jx, jy, jz), added to f (steps 5.3-5.6). */
INLINE void spring(const constants *c, int kind, real x, real y, real z, real jx, real jy, real jz,
                   real bx, real by, real bz, real *fx, real *fy, real *fz)
{
    real dx = jx - x, dy = jy - y, dz = jz - z;
    real L2 = (dx * dx + dy * dy) + dz * dz;
#ifdef CLOTH_STRICT
    real L = SQRT(L2);
    real q = (c->k * (L - c->rest[kind])) / L; /* computed always, kept only when L2 > 0 */
    real s = L2 > 0 ? q : (real)0;             /* coincident: no direction, no spring force */
    *fx = *fx + (s * dx - bx);
    *fy = *fy + (s * dy - by);
    *fz = *fz + (s * dz - bz);
#else
    (void)bx, (void)by, (void)bz; /* the damping is added once per particle, below */
    real inv = (real)1 / SQRT(L2);
    real q = c->k - c->kr[kind] * inv;
    real s = L2 > 0 ? q : (real)0;
    *fx += s * dx;
    *fy += s * dy;
    *fz += s * dz;
#endif
}

/* --- colliders (docs/semantics.md, Collisions), lane by lane and branch free, so the SIMD
 * loop keeps them; `inside` selects, as NumPy's copyto(where=inside) does ------------------ */

INLINE void collide_sphere(const real *s, real *x, real *y, real *z)
{
    real cx = s[0], cy = s[1], cz = s[2], r = s[3];
    real dx = *x - cx, dy = *y - cy, dz = *z - cz;
    real L2 = (dx * dx + dy * dy) + dz * dz;
    real L = SQRT(L2);
    int inside = L < r;
    real f = r / L;
    int centre = L2 == 0; /* exactly at the centre: straight up */
    real px = centre ? cx : cx + dx * f;
    real py = centre ? cy + r : cy + dy * f;
    real pz = centre ? cz : cz + dz * f;
    *x = inside ? px : *x;
    *y = inside ? py : *y;
    *z = inside ? pz : *z;
}

INLINE void collide_cylinder(const real *c, real *x, real *y, real *z)
{
    real ax = c[0], ay = c[1], az = c[2], len = c[3];
    real ux = c[4], uy = c[5], uz = c[6], r = c[7];
    real rx = c[8], ry = c[9], rz = c[10];
    real dx = *x - ax, dy = *y - ay, dz = *z - az;
    real t = (dx * ux + dy * uy) + dz * uz; /* axial coordinate from the start cap */
    real qx = ux * t, qy = uy * t, qz = uz * t;
    real px = dx - qx, py = dy - qy, pz = dz - qz; /* radial vector */
    real rho2 = (px * px + py * py) + pz * pz;
    real rho = SQRT(rho2);
    int inside = (t > 0) & (t < len) & (rho < r);
    real side = r - rho, to_end = len - t;
    int through_side = (side <= t) & (side <= to_end);
    int through_start = !through_side & (t <= to_end);
    int on_axis = rho2 == 0;
    real f = r / rho;
    real aqx = ax + qx, aqy = ay + qy, aqz = az + qz;
    real sx = on_axis ? aqx + rx : aqx + px * f;
    real sy = on_axis ? aqy + ry : aqy + py * f;
    real sz = on_axis ? aqz + rz : aqz + pz * f;
    real cx = through_start ? *x - qx : *x + ux * to_end;
    real cy = through_start ? *y - qy : *y + uy * to_end;
    real cz = through_start ? *z - qz : *z + uz * to_end;
    *x = inside ? (through_side ? sx : cx) : *x;
    *y = inside ? (through_side ? sy : cy) : *y;
    *z = inside ? (through_side ? sz : cz) : *z;
}

INLINE void collide_box(const real *b, real *x, real *y, real *z)
{
    const real *a0 = b + 4, *a1 = b + 8, *a2 = b + 12; /* (axis i, half extent i) */
    real dx = *x - b[0], dy = *y - b[1], dz = *z - b[2];
    real l0 = (dx * a0[0] + dy * a0[1]) + dz * a0[2]; /* coordinates along the box's axes */
    real l1 = (dx * a1[0] + dy * a1[1]) + dz * a1[2];
    real l2 = (dx * a2[0] + dy * a2[1]) + dz * a2[2];
    real p0 = a0[3] - ABS(l0), p1 = a1[3] - ABS(l1), p2 = a2[3] - ABS(l2); /* depth per face pair */
    int inside = (p0 > 0) & (p1 > 0) & (p2 > 0);
    int k1 = p1 < p0; /* the face pair of least depth, ties to the lower axis */
    real least = k1 ? p1 : p0;
    int k2 = p2 < least;
    real lk = k2 ? l2 : (k1 ? l1 : l0);
    real hk = k2 ? a2[3] : (k1 ? a1[3] : a0[3]);
    real ux = k2 ? a2[0] : (k1 ? a1[0] : a0[0]);
    real uy = k2 ? a2[1] : (k1 ? a1[1] : a0[1]);
    real uz = k2 ? a2[2] : (k1 ? a1[2] : a0[2]);
    real m = (lk >= 0 ? hk : -hk) - lk; /* to the face on the particle's side */
    *x = inside ? *x + ux * m : *x;
    *y = inside ? *y + uy * m : *y;
    *z = inside ? *z + uz * m : *z;
}

INLINE void collide_plane(const real *p, real *x, real *y, real *z)
{
    real nx = p[4], ny = p[5], nz = p[6];
    real dist = ((*x - p[0]) * nx + (*y - p[1]) * ny) + (*z - p[2]) * nz;
    int inside = dist < 0;
    *x = inside ? *x - nx * dist : *x;
    *y = inside ? *y - ny * dist : *y;
    *z = inside ? *z - nz * dist : *z;
}

/* Every collider in the fixed order: spheres, cylinders, boxes, planes. */
INLINE void collide(const real *colliders, real *x, real *y, real *z)
{
#if CLOTH_SPHERES > 0
    for (int s = 0; s < CLOTH_SPHERES; ++s)
        collide_sphere(colliders + SPHERE_REALS * s, x, y, z);
#endif
#if CLOTH_CYLINDERS > 0
    for (int s = 0; s < CLOTH_CYLINDERS; ++s)
        collide_cylinder(colliders + FIRST_CYLINDER + CYLINDER_REALS * s, x, y, z);
#endif
#if CLOTH_BOXES > 0
    for (int s = 0; s < CLOTH_BOXES; ++s)
        collide_box(colliders + FIRST_BOX + BOX_REALS * s, x, y, z);
#endif
#if CLOTH_PLANES > 0
    for (int s = 0; s < CLOTH_PLANES; ++s)
        collide_plane(colliders + FIRST_PLANE + PLANE_REALS * s, x, y, z);
#endif
    (void)colliders, (void)x, (void)y, (void)z;
}

/* Steps 6-8 for particle i with force f from `springs` springs: integrate unless pinned,
 * collide, and write x(t+dt) over x(t-dt) in q. */
INLINE void integrate(const constants *c, const real *colliders, int i, real springs, real x, real y, real z,
                      real xp, real yp, real zp, real fx, real fy, real fz, real w, real *restrict q)
{
#ifdef CLOTH_STRICT
    (void)springs;
    /* NumPy's order: force *= w; force += g; force *= dt2; new = 2*pos; new -= prev; new += force */
    fx = ((fx * w) + c->gx) * c->dt2;
    fy = ((fy * w) + c->gy) * c->dt2;
    fz = ((fz * w) + c->gz) * c->dt2;
    real nx = ((real)2 * x - xp) + fx;
    real ny = ((real)2 * y - yp) + fy;
    real nz = ((real)2 * z - zp) + fz;
#else
    real damp = springs * c->damp; /* -b*vel of every spring, added at once */
    real nx = ((real)2 * x - xp) + (c->gx + (fx - damp * (x - xp)) * w) * c->dt2;
    real ny = ((real)2 * y - yp) + (c->gy + (fy - damp * (y - yp)) * w) * c->dt2;
    real nz = ((real)2 * z - zp) + (c->gz + (fz - damp * (z - zp)) * w) * c->dt2;
#endif
#ifdef CLOTH_SELF
    (void)colliders; /* the colliders act after the self-collision pass (contact_row) */
#else
    collide(colliders, &nx, &ny, &nz);
#endif
    int pinned = w == 0; /* never integrated nor collided */
    q[i] = pinned ? x : nx;
    q[PLANE + i] = pinned ? y : ny;
    q[2 * PLANE + i] = pinned ? z : nz;
}

/* The velocity term of the damping, b * ((x - xp) / dt), per component (step 3). */
#define DAMPING(c, v, vp) ((c)->b * (((v) - (vp)) / (c)->dt))

/* A particle with all 12 neighbours (rows and columns 2..n-3): no bounds checks. */
INLINE void interior_particle(const constants *c, const real *colliders, int i, const real *restrict p,
                              real *restrict q, const real *restrict w)
{
    const real *px = p, *py = p + PLANE, *pz = p + 2 * PLANE;
    real x = px[i], y = py[i], z = pz[i];
    real xp = q[i], yp = q[PLANE + i], zp = q[2 * PLANE + i];
#ifdef CLOTH_STRICT
    real bx = DAMPING(c, x, xp), by = DAMPING(c, y, yp), bz = DAMPING(c, z, zp);
#else
    real bx = 0, by = 0, bz = 0;
#endif
    real fx = 0, fy = 0, fz = 0;
#define SPRING(kind, j) spring(c, kind, x, y, z, px[j], py[j], pz[j], bx, by, bz, &fx, &fy, &fz)
    SPRING(0, i - 1); /* structural */
    SPRING(0, i + 1);
    SPRING(0, i - N);
    SPRING(0, i + N);
    SPRING(1, i - N - 1); /* shear */
    SPRING(1, i - N + 1);
    SPRING(1, i + N - 1);
    SPRING(1, i + N + 1);
    SPRING(2, i - 2 * N - 2); /* bend */
    SPRING(2, i - 2 * N + 2);
    SPRING(2, i + 2 * N - 2);
    SPRING(2, i + 2 * N + 2);
#undef SPRING
    integrate(c, colliders, i, (real)12, x, y, z, xp, yp, zp, fx, fy, fz, w[i], q);
}

/* A particle of the two-wide frame: a neighbour outside the grid is skipped (not added as 0). */
static void border_particle(const constants *c, const real *colliders, int row, int col,
                            const real *restrict p, real *restrict q, const real *restrict w)
{
    const real *px = p, *py = p + PLANE, *pz = p + 2 * PLANE;
    int i = row * N + col;
    real x = px[i], y = py[i], z = pz[i];
    real xp = q[i], yp = q[PLANE + i], zp = q[2 * PLANE + i];
    real bx = DAMPING(c, x, xp), by = DAMPING(c, y, yp), bz = DAMPING(c, z, zp);
    real fx = 0, fy = 0, fz = 0;
    real springs = 0;
    for (int o = 0; o < 12; ++o) {
        int r = row + DR[o], cc = col + DC[o];
        if (r < 0 || r >= N || cc < 0 || cc >= N)
            continue;
        int j = r * N + cc;
        spring(c, o / 4, x, y, z, px[j], py[j], pz[j], bx, by, bz, &fx, &fy, &fz);
        springs += 1;
    }
    integrate(c, colliders, i, springs, x, y, z, xp, yp, zp, fx, fy, fz, w[i], q);
}

static void step_row(const constants *c, const real *colliders, int row, const real *restrict p,
                     real *restrict q, const real *restrict w)
{
    if (row < 2 || row >= N - 2) {
        for (int col = 0; col < N; ++col)
            border_particle(c, colliders, row, col, p, q, w);
        return;
    }
    border_particle(c, colliders, row, 0, p, q, w);
    border_particle(c, colliders, row, 1, p, q, w);
    /* The numbers as locals: a value the vectoriser sees used under a condition (the rest
     * length when L2 > 0, radial_r on a cylinder's axis) it loads only there, through a
     * masked load from the caller's pointer, which GCC 12 cannot vectorise (the loop then
     * runs scalar: docs/c.md, "What the kernel does"); from a local it loads unconditionally. */
    const constants local = *c;
    real table[COLLIDER_REALS];
    for (int k = 0; k < COLLIDER_REALS; ++k)
        table[k] = colliders[k];
    const int first = row * N + 2, end = row * N + N - 2;
#pragma omp simd
    for (int i = first; i < end; ++i)
        interior_particle(&local, table, i, p, q, w);
    border_particle(c, colliders, row, N - 2, p, q, w);
    border_particle(c, colliders, row, N - 1, p, q, w);
}

#ifdef CLOTH_SELF
/* --- self-collision (docs/semantics.md, "Self-collision") ------------------------------------
 * After every particle's position update (written over x(t-dt) in q, uncollided), one Jacobi
 * projection reads q and writes x(t+dt), collided, into a third buffer: the three buffers
 * rotate, so nothing is copied. The search is a uniform grid of cells, hashed into BUCKETS
 * buckets and sorted by a counting sort in ascending particle order (deterministic, no atomics).
 * A cell's bucket keeps its x coordinate's low RUN_BITS bits, so the three cells of a row along x
 * are consecutive buckets, one range of the sorted particles (two where the row crosses a block
 * of 2^RUN_BITS cells): a particle reads 9 to 18 ranges, not 27 buckets. The sort also lays the
 * positions out in its order, so a range's candidates are tested from contiguous memory, as one
 * SIMD loop. A particle's corrections are summed in ascending j, each partner once, as the
 * definition sums them, whatever order its ranges deliver them in (push). A hash collision or a
 * clamped key only adds candidates, which the distance test rejects. */

/* The pass's numbers, as the host packs them (kernel_inputs.SelfCollisionConstants). */
enum { S_THICKNESS, S_THICKNESS2, S_RELAX, S_INV_CELL, S_COUNT };

#define KEY_LIMIT (1 << 20) /* cell coordinates are clamped to [-KEY_LIMIT, KEY_LIMIT - 1] */

#ifdef CLOTH_DOUBLE
#define FLOOR(v) __builtin_floor(v)
#else
#define FLOOR(v) __builtin_floorf(v)
#endif

/* Buckets: the smallest power of two >= n*n (and >= 2); a constant (clz of a constant folds). */
#define BUCKET_BITS (N2 > 2 ? 32 - __builtin_clz((unsigned)N2 - 1u) : 1)
#define BUCKETS (1 << BUCKET_BITS)
#define NOWHERE BUCKETS /* the bucket of a particle with a coordinate that is not finite: no pair */
#define RUN_BITS (BUCKET_BITS > 4 ? 3 : BUCKET_BITS - 1) /* 2^RUN_BITS cells along x: consecutive buckets */
#define RUN_MASK ((1 << RUN_BITS) - 1)
_Static_assert(N <= 32768, "dr^2 + dc^2 must fit an int"); /* 2 (N - 1)^2 < 2^31 */

typedef struct {
    real thickness, thickness2, relax, inv_cell;
    long long exclude2;         /* dr^2 + dc^2 < exclude2 apart on the grid: closer at rest, excluded */
    int exclude2i;              /* the same as an int, for the SIMD candidate test */
    unsigned char joined[5][5]; /* [dr + 2][dc + 2]: a stencil offset (a spring joins them) */
    real *sorted;               /* 3 n*n: the positions as x | y | z planes in the sort's order */
    int *bucket;                /* n*n: each particle's bucket */
    int *order;                 /* n*n: the particles by bucket, ascending index within one */
    int *start;                 /* BUCKETS + 3: bucket b holds order[start[b] .. start[b + 1]) */
} contact;

/* floor(v * inv_cell) in the working precision, clamped (v finite). */
INLINE int cell_key(real v, real inv_cell)
{
    real k = FLOOR(v * inv_cell);
    k = k < (real)-KEY_LIMIT ? (real)-KEY_LIMIT : k;
    k = k > (real)(KEY_LIMIT - 1) ? (real)(KEY_LIMIT - 1) : k;
    return (int)k;
}

/* The cell (kx, ky, kz) (clamped keys) to a bucket: its block of 2^RUN_BITS cells along x
 * (Fibonacci hashing of the block's id) and, within the block, the low bits of x. */
INLINE int bucket_of(int kx, int ky, int kz)
{
    unsigned ux = (unsigned)(kx + KEY_LIMIT);
    unsigned long long id = (unsigned long long)(ux >> RUN_BITS) | ((unsigned long long)(ky + KEY_LIMIT) << 21) |
                            ((unsigned long long)(kz + KEY_LIMIT) << 42);
    int block = (int)((id * 0x9E3779B97F4A7C15ull) >> (64 - (BUCKET_BITS - RUN_BITS)));
    return (block << RUN_BITS) | (int)(ux & RUN_MASK);
}

INLINE int clamp_key(int k) { return k < -KEY_LIMIT ? -KEY_LIMIT : k > KEY_LIMIT - 1 ? KEY_LIMIT - 1 : k; }

/* Each particle's bucket, for one row of q (the positions the pass reads). */
static void bucket_row(const contact *ct, int row, const real *restrict q)
{
    for (int i = row * N; i < row * N + N; ++i) {
        real x = q[i], y = q[PLANE + i], z = q[2 * PLANE + i];
        int finite = __builtin_isfinite(x) && __builtin_isfinite(y) && __builtin_isfinite(z);
        ct->bucket[i] = finite ? bucket_of(cell_key(x, ct->inv_cell), cell_key(y, ct->inv_cell),
                                           cell_key(z, ct->inv_cell))
                               : NOWHERE;
    }
}

/* The counting sort: particles by bucket, ascending index within a bucket, and their positions
 * q in that order (one thread). */
static void sort_buckets(const contact *ct, const real *restrict q)
{
    int *start = ct->start;
    for (int b = 0; b < BUCKETS + 3; ++b)
        start[b] = 0;
    for (int i = 0; i < N2; ++i) /* the count of bucket b at start[b + 2] */
        start[ct->bucket[i] + 2] += 1;
    for (int b = 2; b < BUCKETS + 3; ++b) /* start[b + 1]: the first slot of bucket b */
        start[b] += start[b - 1];
    for (int i = 0; i < N2; ++i) { /* ... then, filled, its end: bucket b is [start[b], start[b + 1]) */
        int k = start[ct->bucket[i] + 1]++;
        ct->order[k] = i;
        ct->sorted[k] = q[i];
        ct->sorted[N2 + k] = q[PLANE + i];
        ct->sorted[2 * N2 + k] = q[2 * PLANE + i];
    }
}

/* Whether slots [from, to) may hold a pair of i at (x, y, z), grid row and col: the distance and
 * the rest exclusion tested for every candidate at once, in whole vectors of LANES slots (SIMD,
 * no early exit, no scalar remainder: a range is a few vectors, often less than one); close_pair
 * then decides, stencil and coincidence included. Most ranges hold none: the sheet's own
 * neighbours fail here. The slots past `to` that the last vector reads are in the work space
 * (sorted, then bucket, order, then start, follow each other) and are masked out. */
#define LANES 8
INLINE int may_pair(const contact *ct, int from, int to, int row, int col, real x, real y, real z)
{
    const real *sx = ct->sorted, *sy = ct->sorted + N2, *sz = ct->sorted + 2 * N2;
    const real thickness2 = ct->thickness2;
    const int exclude2 = ct->exclude2i, *restrict order = ct->order;
    int count = 0; /* a sum, written as GCC 12 vectorises it (not an |= of the tests) */
    for (int base = from; base < to; base += LANES) {
#pragma omp simd reduction(+ : count)
        for (int lane = 0; lane < LANES; ++lane) {
            int k = base + lane;
            real dx = x - sx[k], dy = y - sy[k], dz = z - sz[k];
            real L2 = (dx * dx + dy * dy) + dz * dz; /* close_pair's operations: the same bits */
            unsigned j = (unsigned)order[k];
            int dr = (int)(j / N) - row, dc = (int)(j % N) - col;
            int far = dr * dr + dc * dc >= exclude2; /* i itself is not: exclude2 >= 1 */
            count += (k < to && L2 < thickness2 && far) ? 1 : 0;
        }
    }
    return count > 0;
}

/* Whether (i, j) is a pair (not neighbours, closer than the thickness, not coincident), with
 * d = x_i - x_j and its L2; i at (x, y, z) = q_i, grid row and col. */
INLINE int close_pair(const contact *ct, int i, int row, int col, int j, const real *restrict q, real x, real y,
                      real z, real *d, real *L2)
{
    int dr = j / N - row, dc = j % N - col;
    if (j == i || (long long)dr * dr + (long long)dc * dc < ct->exclude2)
        return 0;
    if (dr >= -2 && dr <= 2 && dc >= -2 && dc <= 2 && ct->joined[dr + 2][dc + 2])
        return 0;
    d[0] = x - q[j];
    d[1] = y - q[PLANE + j];
    d[2] = z - q[2 * PLANE + j];
    *L2 = (d[0] * d[0] + d[1] * d[1]) + d[2] * d[2];
    return *L2 < ct->thickness2 && *L2 > 0; /* coincident: no direction, nothing added */
}

/* One pair's correction of i, added to corr (docs/semantics.md, in its order). */
INLINE void add_push(const contact *ct, real wi, real wj, const real *d, real L2, real *corr)
{
    real L = SQRT(L2);
    real share = wi / (wi + wj); /* i's part of the shortfall, by inverse mass */
    real s = ct->relax * (ct->thickness - L);
    s = s * share;
    s = s / L;
    corr[0] = corr[0] + d[0] * s;
    corr[1] = corr[1] + d[1] * s;
    corr[2] = corr[2] + d[2] * s;
}

#define MAX_HITS 32 /* pairs of one particle sorted on the stack; more take the merge */

/* The slots [from, to) of i's cells along x from kx - 1 to kx + 1 (clamped) in the row (ky, kz):
 * one range, or two where the row crosses from one block of buckets into the next. Returns how
 * many it added to from/to, skipping a range met before (hashing, clamping: then it is the same
 * range, whole: the ranges of one particle share their x split, so two differ by block or by
 * x and are disjoint). */
INLINE int row_ranges(const contact *ct, int kx, int ky, int kz, int *from, int *to, int ranges)
{
    int lo = clamp_key(kx - 1), hi = clamp_key(kx + 1), y = clamp_key(ky), z = clamp_key(kz);
    int first = bucket_of(lo, y, z), last = bucket_of(hi, y, z), added = 0;
    int split = ((unsigned)(lo + KEY_LIMIT) >> RUN_BITS) != ((unsigned)(hi + KEY_LIMIT) >> RUN_BITS);
    int piece_first[2] = {first, last & ~RUN_MASK}, piece_last[2] = {split ? first | RUN_MASK : last, last};
    for (int p = 0; p <= split; ++p) {
        int f = ct->start[piece_first[p]], t = ct->start[piece_last[p] + 1], seen = f == t;
        for (int r = 0; r < ranges + added && !seen; ++r)
            seen = from[r] == f;
        if (!seen) {
            from[ranges + added] = f;
            to[ranges + added++] = t;
        }
    }
    return added;
}

/* A cell's ranges of candidates (row_ranges over its 9 rows), kept for the next particle: the
 * Verlet pass walks the particles in the sort's order, a cell's one after another. */
typedef struct {
    int kx, ky, kz, ranges; /* ranges < 0: none kept */
    int from[18], to[18];
} cell_ranges;

/* The pass for free particle i at (x, y, z) = q_i (w_i > 0): its corrections from every pair,
 * in ascending j, added to it when it has one. The candidates are tested first range by range,
 * most failing; the few pairs found are then summed in ascending j. A particle with more than
 * MAX_HITS pairs merges its buckets' runs (each ascending) by smallest j instead. */
static void push(const contact *ct, cell_ranges *cell, int i, const real *restrict q, const real *restrict w, real *x,
                 real *y, real *z)
{
    int kx = cell_key(*x, ct->inv_cell), ky = cell_key(*y, ct->inv_cell), kz = cell_key(*z, ct->inv_cell);
    if (cell->ranges < 0 || kx != cell->kx || ky != cell->ky || kz != cell->kz) {
        cell->kx = kx, cell->ky = ky, cell->kz = kz, cell->ranges = 0;
        for (int dz = -1; dz <= 1; ++dz)
            for (int dy = -1; dy <= 1; ++dy)
                cell->ranges += row_ranges(ct, kx, ky + dy, kz + dz, cell->from, cell->to, cell->ranges);
    }
    const int *from = cell->from, *to = cell->to, ranges = cell->ranges;
    const int row = i / N, col = i % N;
    const real wi = w[i];
    real d[3], L2, corr[3] = {0, 0, 0};
    int hits[MAX_HITS], count = 0;
    for (int r = 0; r < ranges; ++r) {
        if (!may_pair(ct, from[r], to[r], row, col, *x, *y, *z))
            continue;
        for (int k = from[r]; k < to[r]; ++k) {
            int j = ct->order[k];
            if (close_pair(ct, i, row, col, j, q, *x, *y, *z, d, &L2)) {
                if (count < MAX_HITS)
                    hits[count] = j;
                ++count;
            }
        }
    }
    if (count == 0)
        return; /* a particle with no pair keeps its bits */
    if (count <= MAX_HITS) {
        for (int a = 1; a < count; ++a) /* insertion sort: ascending j */
            for (int b = a; b > 0 && hits[b - 1] > hits[b]; --b) {
                int t = hits[b];
                hits[b] = hits[b - 1], hits[b - 1] = t;
            }
        for (int h = 0; h < count; ++h) {
            close_pair(ct, i, row, col, hits[h], q, *x, *y, *z, d, &L2);
            add_push(ct, wi, w[hits[h]], d, L2, corr);
        }
    } else {
        int next[27], end[27], runs = 0; /* each bucket of the ranges: one run, ascending */
        for (int r = 0; r < ranges; ++r)
            for (int k = from[r]; k < to[r];) {
                int b = ct->bucket[ct->order[k]], e = ct->start[b + 1];
                next[runs] = k;
                end[runs++] = e;
                k = e;
            }
        for (;;) {
            int best = -1, j = N2;
            for (int r = 0; r < runs; ++r) /* the smallest index at the head of any run */
                if (next[r] < end[r] && ct->order[next[r]] < j)
                    j = ct->order[next[r]], best = r;
            if (best < 0)
                break;
            next[best] += 1;
            if (close_pair(ct, i, row, col, j, q, *x, *y, *z, d, &L2))
                add_push(ct, wi, w[j], d, L2, corr);
        }
    }
    *x = *x + corr[0];
    *y = *y + corr[1];
    *z = *z + corr[2];
}

/* Particle i through the pass: q_i (its updated position, uncollided) pushed, then collided,
 * into out; `cell` keeps the ranges of the last cell met. */
INLINE void contact_particle(const contact *ct, cell_ranges *cell, const real *colliders, int i,
                             const real *restrict q, real *restrict out, const real *restrict w)
{
    real x = q[i], y = q[PLANE + i], z = q[2 * PLANE + i];
    if (w[i] != 0) { /* pinned: neither pushed nor collided */
        if (w[i] > 0 && ct->bucket[i] != NOWHERE)
            push(ct, cell, i, q, w, &x, &y, &z);
        collide(colliders, &x, &y, &z);
    }
    out[i] = x;
    out[PLANE + i] = y;
    out[2 * PLANE + i] = z;
}

/* One grid row of the pass: q (the updated positions, uncollided) to out, then the colliders;
 * it writes that row of out alone (the implicit solver's pass, whose update then reads its own rows). */
__attribute__((unused)) static void contact_row(const contact *ct, const real *colliders, int row, const real *restrict q,
                        real *restrict out, const real *restrict w)
{
    cell_ranges cell = {.ranges = -1};
    for (int i = row * N; i < row * N + N; ++i)
        contact_particle(ct, &cell, colliders, i, q, out, w);
}

/* The pass for the particles of n slots of the sort (slots chunk n .. chunk n + n - 1), so that
 * the particles of one cell follow each other and share its ranges; chunks 0..n-1 together are
 * every particle once, each written where contact_row would write it. For a caller that reads
 * out only after every chunk is done (a barrier), as the Verlet step does. */
static void contact_chunk(const contact *ct, const real *colliders, int chunk, const real *restrict q,
                          real *restrict out, const real *restrict w)
{
    cell_ranges cell = {.ranges = -1};
    for (int k = chunk * N; k < chunk * N + N; ++k)
        contact_particle(ct, &cell, colliders, ct->order[k], q, out, w);
}

#define SORTED_INTS ((int)(3 * N2 * sizeof(real) / sizeof(int)))

/* The pass's constants and work space from the host's arrays. */
static contact contact_of(const real *numbers, long long exclude2, int *cells)
{
    contact ct;
    ct.thickness = numbers[S_THICKNESS];
    ct.thickness2 = numbers[S_THICKNESS2];
    ct.relax = numbers[S_RELAX];
    ct.inv_cell = numbers[S_INV_CELL];
    ct.exclude2 = exclude2;
    ct.exclude2i = exclude2 > 0x7fffffff ? 0x7fffffff : (int)exclude2; /* past 2 (n - 1)^2 all alike */
    for (int r = 0; r < 5; ++r)
        for (int c = 0; c < 5; ++c)
            ct.joined[r][c] = 0;
    for (int o = 0; o < 12; ++o)
        ct.joined[DR[o] + 2][DC[o] + 2] = 1;
    ct.sorted = (real *)cells; /* first: the host's int array is aligned for a real */
    ct.bucket = cells + SORTED_INTS;
    ct.order = ct.bucket + N2;
    ct.start = ct.order + N2;
    return ct;
}

/* The ints of work space the host gives cloth_advance: sorted | bucket | order | start. */
int cloth_contact_ints(void) { return SORTED_INTS + 2 * N2 + BUCKETS + 3; }
#endif

#ifdef CLOTH_SELF
/* cloth_advance with the pass: three buffers p (x(t)), q (x(t-dt), then the updated positions)
 * and o (x(t+dt)), which then rotate. Returns steps % 3: how many places (a, b, spare) rotated. */
static int advance_with_contact(const constants *c, const contact *ct, real *a, real *b, real *spare, const real *w,
                                const real *colliders, int steps, int threads)
{
    if (threads <= 1) { /* no OpenMP runtime call, as in cloth_advance */
        FP_ENTER;
        real *p = a, *q = b, *o = spare;
        for (int s = 0; s < steps; ++s) {
            for (int row = 0; row < N; ++row) {
                step_row(c, colliders, row, p, q, w);
                bucket_row(ct, row, q);
            }
            sort_buckets(ct, q);
            for (int chunk = 0; chunk < N; ++chunk)
                contact_chunk(ct, colliders, chunk, q, o, w);
            real *t = q;
            q = p, p = o, o = t;
        }
        FP_LEAVE;
        return steps % 3;
    }
#pragma omp parallel num_threads(threads)
    {
        FP_ENTER;
        const constants local = *c;
        real *p = a, *q = b, *o = spare;
        for (int s = 0; s < steps; ++s) {
#pragma omp for schedule(static)
            for (int row = 0; row < N; ++row) {
                step_row(&local, colliders, row, p, q, w);
                bucket_row(ct, row, q); /* the row this thread just wrote */
            }
#pragma omp single
            sort_buckets(ct, q);
            /* each barrier: the pass reads every row's update and the sorted buckets; its chunks
             * cost what their pairs and candidates cost (a fold's cells many, a flat sheet's few),
             * so they are handed out as threads come free: no bit depends on the thread */
#pragma omp for schedule(guided)
            for (int chunk = 0; chunk < N; ++chunk)
                contact_chunk(ct, colliders, chunk, q, o, w);
            real *t = q;
            q = p, p = o, o = t;
        }
        FP_LEAVE;
    }
    return steps % 3;
}
#define CONTACT_PARAMS , real *spare, const real *contact_numbers, long long exclude2, int *cells
#else
#define CONTACT_PARAMS
#endif

/* Advance `steps` steps on `threads` threads. a holds x(t) and b x(t-dt) as x|y|z planes; w
 * the inverse mass. Returns which buffer holds the new x(t) (0: a, 1: b); the other then holds
 * the new x(t-dt). With CLOTH_SELF, `spare` is a third buffer, the pass's numbers and work space
 * follow, and the return is how many places (a, b, spare) rotated (advance_with_contact). */
int cloth_advance(real *a, real *b, const real *w, const real *numbers, const real *colliders, int steps,
                  int threads CONTACT_PARAMS)
{
    constants c;
    c.k = numbers[K_K];
    c.b = numbers[K_B];
    c.dt = numbers[K_DT];
    c.dt2 = numbers[K_DT2];
    c.gx = numbers[K_GX];
    c.gy = numbers[K_GY];
    c.gz = numbers[K_GZ];
    for (int kind = 0; kind < 3; ++kind) {
        c.rest[kind] = numbers[K_REST0 + kind];
        c.kr[kind] = c.k * c.rest[kind];
    }
    c.damp = c.b / c.dt;
#ifdef CLOTH_SELF
    const contact ct = contact_of(contact_numbers, exclude2, cells);
    return advance_with_contact(&c, &ct, a, b, spare, w, colliders, steps, threads);
#else
    if (threads <= 1) {
        /* no OpenMP runtime call at all: GNU libgomp hangs in a child forked after the parent
         * ran a parallel region, and the host steps such a child on one thread this way */
        FP_ENTER;
        for (int s = 0; s < steps; ++s) {
            const real *p = (s & 1) ? b : a;
            real *q = (s & 1) ? a : b;
            for (int row = 0; row < N; ++row)
                step_row(&c, colliders, row, p, q, w);
        }
        FP_LEAVE;
        return steps & 1;
    }
#pragma omp parallel num_threads(threads) firstprivate(c)
    {
        FP_ENTER;
        for (int s = 0; s < steps; ++s) {
            const real *p = (s & 1) ? b : a;
            real *q = (s & 1) ? a : b;
#pragma omp for schedule(static)
            for (int row = 0; row < N; ++row)
                step_row(&c, colliders, row, p, q, w);
            /* the loop's barrier: every row of this step is written before the next reads it */
        }
        FP_LEAVE;
    }
    return steps & 1;
#endif
}

/* The build's shape, for the host to check it loaded the library it asked for. */
int cloth_grid(void) { return N; }
int cloth_plane(void) { return PLANE; }
int cloth_real_bytes(void) { return (int)sizeof(real); }
