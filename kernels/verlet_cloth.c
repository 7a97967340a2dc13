/* verlet_cloth.c: the mass-spring cloth step (docs/semantics.md) in C with OpenMP, the CPU
 * path as a performance engineer writes it. Host code: clothbench/backends/c/verlet.py;
 * build and measurements: docs/c.md.
 *
 * Built per scene by clothbench/native.py with -D options, so the compiler folds them:
 *   CLOTH_N                grid side n: strides, bounds and the interior range are constants.
 *   CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_BOXES, CLOTH_PLANES
 *                          collider counts (clothbench/colliders/kinds.py): each kind's loop
 *                          unrolls, an absent kind vanishes.
 *   CLOTH_DOUBLE           float64 (the fast reference for accuracy figures); else float32.
 *   CLOTH_STRICT           every operation in the order docs/semantics.md fixes, damping once
 *                          per spring, sqrt and '/': with -ffp-contract=off and no fast math
 *                          the result is NumPy's bit for bit (float32 and float64 alike).
 *                          Without it (fast): the damping of all springs is added once, each
 *                          spring costs one 1/sqrt (a correctly rounded sqrt and divide: no
 *                          fast math, see docs/c.md), and the host lets the compiler contract.
 * The numbers (k, b, dt, dt2, g, rest lengths, the collider table) are arguments, rounded once
 * on the host (clothbench/backends/kernel_inputs.py), so a dt or stiffness sweep builds nothing.
 *
 * Layout: positions as three planes x | y | z of n*n values; w (inverse mass, 0 = pinned)
 * in its own plane. Two state buffers, ping-ponged by the step count: a particle reads its
 * own previous position and nothing else of that buffer, so x(t+dt) overwrites x(t-dt) in
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
    collide(colliders, &nx, &ny, &nz);
    int pinned = w == 0; /* never integrated nor collided */
    q[i] = pinned ? x : nx;
    q[N2 + i] = pinned ? y : ny;
    q[2 * N2 + i] = pinned ? z : nz;
}

/* The velocity term of the damping, b * ((x - xp) / dt), per component (step 3). */
#define DAMPING(c, v, vp) ((c)->b * (((v) - (vp)) / (c)->dt))

/* A particle with all 12 neighbours (rows and columns 2..n-3): no bounds checks. */
INLINE void interior_particle(const constants *c, const real *colliders, int i, const real *restrict p,
                              real *restrict q, const real *restrict w)
{
    const real *px = p, *py = p + N2, *pz = p + 2 * N2;
    real x = px[i], y = py[i], z = pz[i];
    real xp = q[i], yp = q[N2 + i], zp = q[2 * N2 + i];
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
    const real *px = p, *py = p + N2, *pz = p + 2 * N2;
    int i = row * N + col;
    real x = px[i], y = py[i], z = pz[i];
    real xp = q[i], yp = q[N2 + i], zp = q[2 * N2 + i];
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

/* Advance `steps` steps on `threads` threads. a holds x(t) and b x(t-dt) as x|y|z planes; w
 * the inverse mass. Returns which buffer holds the new x(t) (0: a, 1: b); the other then holds
 * the new x(t-dt). */
int cloth_advance(real *a, real *b, const real *w, const real *numbers, const real *colliders, int steps,
                  int threads)
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
}

/* The build's shape, for the host to check it loaded the library it asked for. */
int cloth_grid(void) { return N; }
int cloth_real_bytes(void) { return (int)sizeof(real); }
