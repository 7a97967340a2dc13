/* verlet_cloth.cl: one mass-spring cloth step in OpenCL C.
 *
 * The step is docs/semantics.md, which follows Listing 22.1 of the chapter (Fratarcangeli,
 * "GPGPU Cloth Simulation Using GLSL, OpenCL, and CUDA", Game Engine Gems 2); the numbered
 * comments below are the listing's steps. Host code: clothbench/backends/opencl.py.
 *
 * Two variants of the same step live in this file:
 *   strict (-DCLOTH_STRICT): kernel verlet_cloth. float4 positions (w = inverse mass), every
 *       operation in the order docs/semantics.md fixes, no FMA contraction, no dot()/length(),
 *       no fast math: the result equals the NumPy float32 reference bit for bit.
 *   fast (default): kernels verlet_cloth_interior + verlet_cloth_border. The same physics
 *       shaped for the CPU's SIMD units (../shared/DRIVERS.md, and the measurement in the
 *       fast section below): SoA planes, V particles per work item as explicit vectors, one
 *       reciprocal square root per spring, select() instead of if, an interior kernel with
 *       all 12 neighbours present (no bounds checks, unrolled) and a small bounds-checked
 *       border kernel. Contraction allowed (-cl-mad-enable) and damping summed once per
 *       particle instead of once per spring, so it is measured against float64 instead.
 *
 * What comes in how, and why:
 *   -D build options: what changes the shape of the code, so the compiler can specialise it.
 *       CLOTH_N            grid side n: index arithmetic, neighbour strides and bounds fold
 *                          to constants.
 *       CLOTH_NUM_SPHERES  number of spheres: the collider loop unrolls into straight-line
 *                          code.
 *       CLOTH_STRICT       the strict variant (FP_CONTRACT OFF).
 *       CLOTH_VECTOR_WIDTH fast variant: particles per work item (1 for the border kernel).
 *   Kernel arguments: the numbers (k, b, dt, dt2, g, rest, sphere centres and radii), each
 *       rounded once to float32 on the host and passed with an explicit dtype, so one program
 *       serves every scene of the same shape (a dt or stiffness sweep does not rebuild), and a
 *       wrongly typed argument is refused by the host wrapper instead of being reinterpreted
 *       silently (the chapter's section 22.8 complaint).
 */

#ifndef CLOTH_N
#error "build with -DCLOTH_N=<grid side>"
#endif
#ifndef CLOTH_NUM_SPHERES
#define CLOTH_NUM_SPHERES 0
#endif

#ifdef CLOTH_STRICT
/* PoCL fuses a*b+c into an FMA unless told not to; strict rounds every operation. */
#pragma OPENCL FP_CONTRACT OFF
#endif

#define N CLOTH_N
#define N2 (CLOTH_N * CLOTH_N)

/* The 12-spring stencil (d_row, d_col), in the order every backend sums it (scene.OFFSETS).
 * Offsets 0-3 are structural (rest.x), 4-7 shear (rest.y), 8-11 bend (rest.z). */
__constant int2 OFFSETS[12] = {
    (int2)(0, -1), (int2)(0, 1), (int2)(-1, 0), (int2)(1, 0),
    (int2)(-1, -1), (int2)(-1, 1), (int2)(1, -1), (int2)(1, 1),
    (int2)(-2, -2), (int2)(-2, 2), (int2)(2, -2), (int2)(2, 2),
};

/* ======================================================================================
 * Strict: Listing 22.1 as written, float4 positions, bit-exact with the NumPy reference.
 * ====================================================================================== */

/* Steps 5.3-5.6 for one neighbour: the spring force pulling x toward x_neigh, minus damping. */
float3 spring_force(float3 x, float3 x_neigh, float rest, float k, float3 bv)
{
    float3 d = x_neigh - x;
    float L2 = (d.x * d.x + d.y * d.y) + d.z * d.z; /* not dot(): its order is the driver's */
    float L = sqrt(L2);
    float s = L2 > 0.0f ? (k * (L - rest)) / L : 0.0f; /* coincident: no direction, no force */
    return s * d - bv;
}

/* Push a point inside a sphere (centre xyz, radius w) out to its surface. */
float3 collide_sphere(float3 x, float4 sphere)
{
    float3 c = sphere.xyz;
    float r = sphere.w;
    float3 d = x - c;
    float L2 = (d.x * d.x + d.y * d.y) + d.z * d.z;
    float L = sqrt(L2);
    if (L < r)
        x = L2 > 0.0f ? c + d * (r / L)
                      : (float3)(c.x, c.y + r, c.z); /* exactly at the centre: straight up */
    return x;
}

/* Every collider, in the order docs/semantics.md fixes: spheres (cylinders and planes, when
 * this kernel gets them, follow here). */
float3 collide(float3 x, __constant float4 *spheres)
{
    for (int s = 0; s < CLOTH_NUM_SPHERES; ++s)
        x = collide_sphere(x, spheres[s]);
    return x;
}

__kernel void verlet_cloth(__global const float4 *pos, __global const float4 *pos_prev,
                           __global float4 *pos_out, __global float4 *pos_prev_out,
                           __constant float4 *spheres, const float k, const float b,
                           const float dt, const float dt2, const float4 g, const float4 rest)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded when the work-group size does not divide n*n */
    int row = i / N, col = i % N;

    float3 x = pos[i].xyz;       /* 1. */
    float3 xp = pos_prev[i].xyz; /* 2. */
    float w = pos[i].w;          /* inverse mass; 0 = pinned */
    float3 vel = (x - xp) / dt;  /* 3. */
    float3 bv = b * vel;
    float3 force = (float3)(0.0f); /* 4. (differs: gravity is an acceleration, added in 6.) */

    for (int o = 0; o < 12; ++o) { /* 5. */
        /* (differs: the listing mixes x and y offsets; row and column stay paired here) */
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        if (r < 0 || r >= N || c < 0 || c >= N)
            continue; /* outside the grid: nothing added, not even zero */
        float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
        force = force + spring_force(x, pos[r * N + c].xyz, rest_o, k, bv);
    }

    float3 x_new = x; /* pinned particles are never integrated nor collided */
    if (w != 0.0f) {
        float3 acc = g.xyz + force * w;           /* (m*g + force) / m */
        x_new = (2.0f * x - xp) + acc * dt2;      /* 6. */
        x_new = collide(x_new, spheres);
    }
    pos_out[i] = (float4)(x_new, w); /* 7. */
    pos_prev_out[i] = (float4)(x, w); /* 8. */
}

/* ======================================================================================
 * Fast: the same step shaped for a CPU's SIMD units. State as SoA planes: x[0..n2),
 * y[n2..2n2), z[2n2..3n2) in one buffer per state; inverse mass in its own read-only buffer.
 *
 * The helpers below are written once over `floatv`, V = CLOTH_VECTOR_WIDTH lanes: the host
 * builds this file with V = the device's preferred float width for the interior kernel (V
 * consecutive particles of a row per work item) and with V = 1 for the border kernel (one
 * particle per work item). Explicit vectors because PoCL 3.1 (LLVM 15) did not vectorise the
 * scalar form across work items: its first optimisation pass packs four springs of one
 * particle into gathers, which then blocks the work-item loop vectoriser. Measured at
 * n = 256: the interior kernel took 2.6 ms per step in scalar form, 0.15 ms with float16.
 * ====================================================================================== */

#ifndef CLOTH_VECTOR_WIDTH
#define CLOTH_VECTOR_WIDTH 1
#endif
#define V CLOTH_VECTOR_WIDTH
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#if V == 1
typedef float floatv;
typedef int intv;
#define LOADV(p, j) ((p)[j])
#define STOREV(v, p, j) ((p)[j] = (v))
#else
typedef CAT(float, V) floatv;
typedef CAT(int, V) intv;
#define LOADV(p, j) CAT(vload, V)(0, (p) + (j))
#define STOREV(v, p, j) CAT(vstore, V)((v), 0, (p) + (j))
#endif

/* Step 5 for one neighbour j: adds the spring force k*(L - rest)*d/L = (k - k*rest/L)*d.
 * The damping term -b*vel of each spring is added by integrate_store, all at once. One
 * reciprocal square root per spring; select(), not if, keeps the lanes together. */
void spring_add(floatv x, floatv y, floatv z, __global const float *pos, int j, float k,
                float k_rest, floatv *fx, floatv *fy, floatv *fz)
{
    floatv dx = LOADV(pos, j) - x, dy = LOADV(pos, N2 + j) - y, dz = LOADV(pos, 2 * N2 + j) - z;
    floatv L2 = dx * dx + dy * dy + dz * dz;
    floatv s = select((floatv)(0.0f), k - k_rest * rsqrt(L2), L2 > 0.0f); /* coincident: 0 */
    *fx += s * dx;
    *fy += s * dy;
    *fz += s * dz;
}

/* Push points inside a sphere (centre xyz, radius w) out to its surface. */
void collide_sphere_v(floatv *x, floatv *y, floatv *z, float4 sphere)
{
    floatv dx = *x - sphere.x, dy = *y - sphere.y, dz = *z - sphere.z;
    floatv L2 = dx * dx + dy * dy + dz * dz;
    floatv s = sphere.w * rsqrt(L2);
    intv inside = L2 < sphere.w * sphere.w;
    intv at_centre = L2 == 0.0f; /* straight up, as in the strict variant */
    *x = select(*x, select(sphere.x + dx * s, (floatv)(sphere.x), at_centre), inside);
    *y = select(*y, select(sphere.y + dy * s, (floatv)(sphere.y + sphere.w), at_centre), inside);
    *z = select(*z, select(sphere.z + dz * s, (floatv)(sphere.z), at_centre), inside);
}

/* Every collider, spheres first (cylinders and planes, when this kernel gets them, follow). */
void collide_v(floatv *x, floatv *y, floatv *z, __constant float4 *spheres)
{
    for (int s = 0; s < CLOTH_NUM_SPHERES; ++s)
        collide_sphere_v(x, y, z, spheres[s]);
}

/* Store lanes first_lane .. V-1 of v at p[j..]: all of them, except in the last vector of
 * an interior row, whose first lanes the vector before it has written already. */
void store_lanes(floatv v, __global float *p, int j, int first_lane)
{
#if V == 1
    p[j] = v;
#else
    if (first_lane == 0) {
        STOREV(v, p, j);
        return;
    }
    float lanes[V];
    STOREV(v, lanes, 0);
    for (int l = first_lane; l < V; ++l)
        p[j + l] = lanes[l];
#endif
}

/* Steps 6-8 for the particles at i: add the damping -b*vel of each of their `springs`,
 * integrate unless pinned, collide, write both outputs. */
void integrate_store(int i, int first_lane, floatv x, floatv y, floatv z, floatv fx, floatv fy,
                     floatv fz, float springs, __global const float *pos_prev,
                     __global const float *inv_mass, __global float *pos_out,
                     __global float *pos_prev_out, __constant float4 *spheres, float b,
                     float dt, float dt2, float4 g)
{
    floatv xp = LOADV(pos_prev, i), yp = LOADV(pos_prev, N2 + i), zp = LOADV(pos_prev, 2 * N2 + i);
    floatv w = LOADV(inv_mass, i);
    float b_dt = springs * b / dt;
    floatv nx = (2.0f * x - xp) + (g.x + (fx - b_dt * (x - xp)) * w) * dt2;
    floatv ny = (2.0f * y - yp) + (g.y + (fy - b_dt * (y - yp)) * w) * dt2;
    floatv nz = (2.0f * z - zp) + (g.z + (fz - b_dt * (z - zp)) * w) * dt2;
    collide_v(&nx, &ny, &nz, spheres);
    intv pinned = w == 0.0f;
    store_lanes(select(nx, x, pinned), pos_out, i, first_lane);
    store_lanes(select(ny, y, pinned), pos_out, N2 + i, first_lane);
    store_lanes(select(nz, z, pinned), pos_out, 2 * N2 + i, first_lane);
    store_lanes(x, pos_prev_out, i, first_lane);
    store_lanes(y, pos_prev_out, N2 + i, first_lane);
    store_lanes(z, pos_prev_out, 2 * N2 + i, first_lane);
}

/* Rows and columns 2 .. n-3: every neighbour exists, so no bounds checks and all 12 springs
 * unrolled. V consecutive particles of a row per work item; when V does not divide n - 4,
 * the last vector of a row starts at n-2-V, overlapping the one before it, and stores only
 * the lanes that one did not. Only grids with n - 4 >= V have it. */
#if N - 4 >= V
#define VECTORS_PER_ROW ((N - 4 + V - 1) / V)
#define INTERIOR_ITEMS (VECTORS_PER_ROW * (N - 4))
#define LAST_FIRST_LANE (V * VECTORS_PER_ROW - (N - 4))

__kernel void verlet_cloth_interior(__global const float *pos, __global const float *pos_prev,
                                    __global const float *inv_mass, __global float *pos_out,
                                    __global float *pos_prev_out, __constant float4 *spheres,
                                    const float k, const float b, const float dt,
                                    const float dt2, const float4 g, const float4 rest)
{
    int item = get_global_id(0);
    if (item >= INTERIOR_ITEMS)
        return; /* the launch is padded when the work-group size does not divide it */
    int row = 2 + item / VECTORS_PER_ROW, vector = item % VECTORS_PER_ROW;
    int last = vector == VECTORS_PER_ROW - 1;
    int i = row * N + (last ? N - 2 - V : 2 + V * vector);
    floatv x = LOADV(pos, i), y = LOADV(pos, N2 + i), z = LOADV(pos, 2 * N2 + i);
    floatv fx = 0.0f, fy = 0.0f, fz = 0.0f;
    float kr0 = k * rest.x, kr1 = k * rest.y, kr2 = k * rest.z;
    spring_add(x, y, z, pos, i - 1, k, kr0, &fx, &fy, &fz); /* structural */
    spring_add(x, y, z, pos, i + 1, k, kr0, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i - N, k, kr0, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i + N, k, kr0, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i - N - 1, k, kr1, &fx, &fy, &fz); /* shear */
    spring_add(x, y, z, pos, i - N + 1, k, kr1, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i + N - 1, k, kr1, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i + N + 1, k, kr1, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i - 2 * N - 2, k, kr2, &fx, &fy, &fz); /* bend */
    spring_add(x, y, z, pos, i - 2 * N + 2, k, kr2, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i + 2 * N - 2, k, kr2, &fx, &fy, &fz);
    spring_add(x, y, z, pos, i + 2 * N + 2, k, kr2, &fx, &fy, &fz);
    integrate_store(i, last ? LAST_FIRST_LANE : 0, x, y, z, fx, fy, fz, 12.0f, pos_prev,
                    inv_mass, pos_out, pos_prev_out, spheres, b, dt, dt2, g);
}
#endif

#if V == 1
/* The particles the interior kernel does not cover (the two-wide frame; every particle when
 * n - 4 < V), listed by the host: bounds checked, one particle per work item. */
__kernel void verlet_cloth_border(__global const float *pos, __global const float *pos_prev,
                                  __global const float *inv_mass, __global float *pos_out,
                                  __global float *pos_prev_out, __constant float4 *spheres,
                                  const float k, const float b, const float dt,
                                  const float dt2, const float4 g, const float4 rest,
                                  __global const int *particles, const int count)
{
    int item = get_global_id(0);
    if (item >= count)
        return;
    int i = particles[item];
    int row = i / N, col = i % N;
    float x = pos[i], y = pos[N2 + i], z = pos[2 * N2 + i];
    float fx = 0.0f, fy = 0.0f, fz = 0.0f;
    float springs = 0.0f;
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        if (r < 0 || r >= N || c < 0 || c >= N)
            continue;
        float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
        spring_add(x, y, z, pos, r * N + c, k, k * rest_o, &fx, &fy, &fz);
        springs += 1.0f;
    }
    integrate_store(i, 0, x, y, z, fx, fy, fz, springs, pos_prev, inv_mass, pos_out,
                    pos_prev_out, spheres, b, dt, dt2, g);
}
#endif
