/* verlet_cloth.cl: one mass-spring cloth step in OpenCL C.
 *
 * The step and the colliders are docs/semantics.md, which follows Listing 22.1 of the chapter
 * (Fratarcangeli, "GPGPU Cloth Simulation Using GLSL, OpenCL, and CUDA", Game Engine Gems 2);
 * the numbered comments below are the listing's steps. Host code: clothbench/backends/opencl/verlet.py.
 *
 * Two builds of this file, chosen by the host:
 *   generic (-DCLOTH_GENERIC): kernel verlet_cloth. The listing as written: float4 positions
 *       (w = inverse mass), one work item per particle, every neighbour bounds-checked. One
 *       program serves every scene: the grid side, the constants and every collider kind
 *       with its count come in as kernel arguments (meshes and motion, where the scene has
 *       them, as the -D options below). `--generic`.
 *   specialised (the default): built for one scene's shape: SoA planes, V particles per
 *       work item as explicit vectors, grid side and collider counts as -D constants, and
 *       the code of a collider kind compiled in only when the scene has one. Three ways to
 *       split the work (the host's kernel shapes, clothbench/backends/opencl/verlet_shapes.py):
 *       verlet_cloth_interior (all 12 neighbours present: no bounds checks, unrolled) +
 *       verlet_cloth_border (a small bounds-checked frame, one particle per work item), which
 *       write pos_out and pos_prev_out, the chapter's four buffers;
 *       verlet_cloth_rows (every row in vectors, the edge masked lane by lane, one launch);
 *       verlet_cloth_steps (the rows kernel's work, several steps in one launch, one
 *       work-group); these two write x(t+dt) over x(t-dt) in place, two state buffers.
 * and two arithmetics, for either build:
 *   strict (-DCLOTH_STRICT): every operation in the order docs/semantics.md fixes, sqrt and
 *       '/', damping once per spring, no FMA contraction, no dot()/length(): the result
 *       equals the NumPy float32 reference bit for bit. Vectors do not change IEEE results,
 *       so the specialised build is exact too and is what `--strict` runs by default.
 *   fast (default): contraction allowed (-cl-mad-enable) in both builds; the specialised
 *       springs also use one reciprocal square root each (on AVX-512 with 16 lanes the
 *       hardware estimate and a Newton step) and sum the damping once per particle.
 *       Measured against float64 instead.
 *
 * What comes in how, and why:
 *   -D build options: what changes the shape of the code, so the compiler can specialise it
 *       (specialised build only).
 *       CLOTH_N             grid side n: index arithmetic, neighbour strides and bounds fold
 *                           to constants.
 *       CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_BOXES, CLOTH_PLANES
 *                           collider counts: each kind's loop unrolls into straight-line
 *                           code, and a kind the scene lacks is not compiled at all.
 *       CLOTH_VECTOR_WIDTH  particles per work item (1 for the border kernel).
 *       CLOTH_PAD           floats before and after the planes in each state buffer.
 *       CLOTH_STATE_GAP     floats between the planes beyond n*n (STATE_STRIDE below).
 *   Meshes, motion and attached pins (docs/semantics.md), either build, each only where the
 *       scene has it (the host sets them; a scene without them compiles none of it):
 *       CLOTH_MESHES        triangle meshes: their code is kernels/collide_mesh.cl, in the
 *                           source only then (`#include <mesh_colliders>`); CLOTH_MESH_BVH
 *                           picks the accelerated search (the host's BVH) over the naive loop.
 *       CLOTH_PER_STEP      a collider moves or the pins follow a body: the collider table
 *                           holds one table per step of the launch (poses evaluated on the
 *                           host in float64, rounded once) and the kernel takes the index
 *                           `step` of its first step in it.
 *       CLOTH_ATTACHED_PINS, CLOTH_PINS
 *                           pins following a body: pin_slot (per particle, -1 for none)
 *                           indexes pin_target, CLOTH_PINS float3 targets per step.
 *       CLOTH_SELF_COLLISION [self_collision]: kernels/self_collision.cl, in the source only
 *                           then (`#include <self_collision>`), runs its pass and then the
 *                           colliders in a launch of its own after the step's; the step's
 *                           kernels leave the colliders out.
 *   -DCLOTH_NORMALS (either build): also write each particle's normal (docs/normals.md) of
 *       the state the step read, x(t), to one more buffer, normal_out; without it the
 *       kernels neither compute nor take it.
 *   Kernel arguments: the numbers (k, b, dt, dt2, g, rest, the collider table), each rounded
 *       once to float32 on the host and passed with an explicit dtype, so a dt or stiffness
 *       sweep does not rebuild, and a wrongly typed argument is refused by the host wrapper
 *       instead of being reinterpreted silently (the chapter's section 22.8 complaint).
 *       Exact hex literals instead (-D, c_float) would gain nothing (docs/opencl.md, "What it
 *       decided").
 *
 * The collider table (one __constant float4 array, rows rounded once from float64): spheres
 * (centre, radius); then cylinders, three rows each: (start, length), (unit axis, radius),
 * (radial_r, 0); then boxes, four rows each: (centre, 0), (axis i, half extent i); then planes,
 * two rows each: (point, 0), (unit normal, 0); then meshes, MESH_ROWS each (collide_mesh.cl
 * has them). The generic build
 * takes its colliders from collide.cl (included by the host, as pbd_cloth.cl does); the
 * specialised build has its own vectorised ones below, the same operations lane by lane.
 */

#ifdef CLOTH_STRICT
/* PoCL fuses a*b+c into an FMA unless told not to; strict rounds every operation. */
#pragma OPENCL FP_CONTRACT OFF
#endif

/* The 12-spring stencil (d_row, d_col), in the order every backend sums it (scene.OFFSETS).
 * Offsets 0-3 are structural (rest.x), 4-7 shear (rest.y), 8-11 bend (rest.z). */
__constant int2 OFFSETS[12] = {
    (int2)(0, -1), (int2)(0, 1), (int2)(-1, 0), (int2)(1, 0),
    (int2)(-1, -1), (int2)(-1, 1), (int2)(1, -1), (int2)(1, 1),
    (int2)(-2, -2), (int2)(-2, 2), (int2)(2, -2), (int2)(2, 2),
};

/* The extra arguments of a scene with meshes, motion or attached pins: BODY_ARG in a kernel's
 * parameters (after the normals), BODY_PARAMS and BODY_PASS through the helpers. */
#include "body_args.cl"
#define BODY_ARG STEP_ARG MESH_ARG PIN_ARG
#define BODY_PARAMS MESH_ARG PIN_ARG
#define BODY_PASS MESH_PASS PIN_PASS

#ifdef CLOTH_NORMALS
/* docs/normals.md: the six triangles around a particle (each grid quad split along its
 * (r,c)-(r+1,c+1) diagonal) are (x, RING[e], RING[e+1]) for consecutive ring entries: up,
 * up-left, left, down, down-right, right, (up). A face counts when both are in the grid. */
__constant int2 RING[6] = {
    (int2)(-1, 0), (int2)(-1, -1), (int2)(0, -1), (int2)(1, 0), (int2)(1, 1), (int2)(0, 1),
};
#endif

#ifdef CLOTH_GENERIC
/* ======================================================================================
 * Generic: Listing 22.1 as written, float4 positions, one program for every scene.
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

/* (a.x*b.x + a.y*b.y) + a.z*b.z, strict or fast: not dot(), whose order is the driver's */
float dot3(float3 a, float3 b)
{
    return (a.x * b.x + a.y * b.y) + a.z * b.z;
}

/* The colliders and collide(x, colliders, counts...), shared with pbd_cloth.cl. */
#include "collide.cl"
/* The meshes: collide_meshes(x, rows, geometry, ints), only where the scene has them. */
#include <mesh_colliders>

#ifdef CLOTH_NORMALS
/* v / |v|, or 0 for a zero vector (a degenerate triangle has no direction) */
float3 unit_or_zero(float3 v)
{
    float L2 = (v.x * v.x + v.y * v.y) + v.z * v.z;
    return L2 > 0.0f ? v / sqrt(L2) : (float3)(0.0f);
}

/* The normal of particle (row, col) at x: the unit sum of its faces' unit normals, each
 * a x c written out (not cross(): its order is the driver's). */
float3 normal_at(__global const float4 *pos, int n, int row, int col, float3 x)
{
    float3 sum = (float3)(0.0f);
    for (int e = 0; e < 6; ++e) {
        int ra = row + RING[e].x, ca = col + RING[e].y;
        int rb = row + RING[(e + 1) % 6].x, cb = col + RING[(e + 1) % 6].y;
        if (ra < 0 || ra >= n || ca < 0 || ca >= n || rb < 0 || rb >= n || cb < 0 || cb >= n)
            continue;
        float3 a = pos[ra * n + ca].xyz - x, c = pos[rb * n + cb].xyz - x;
        float3 f = (float3)(a.y * c.z - a.z * c.y, a.z * c.x - a.x * c.z, a.x * c.y - a.y * c.x);
        sum = sum + unit_or_zero(f);
    }
    return unit_or_zero(sum);
}
#define NORMALS_ARG , __global float4 *normal_out
#else
#define NORMALS_ARG
#endif

__kernel void verlet_cloth(__global const float4 *pos, __global const float4 *pos_prev,
                           __global float4 *pos_out, __global float4 *pos_prev_out,
                           const int n, const float k, const float b, const float dt,
                           const float dt2, const float4 g, const float4 rest,
                           __constant float4 *colliders, const int num_spheres,
                           const int num_cylinders, const int num_boxes,
                           const int num_planes NORMALS_ARG BODY_ARG)
{
    int i = get_global_id(0);
    if (i >= n * n)
        return; /* the launch is padded when the work-group size does not divide n*n */
    int row = i / n, col = i % n;
    int analytic_rows = num_spheres + 3 * num_cylinders + 4 * num_boxes + 2 * num_planes;
#ifdef CLOTH_PER_STEP
    colliders += step * (analytic_rows + MESH_ROWS * CLOTH_MESHES); /* this step's poses */
    PIN_STEP_TARGETS(step);
#endif

    float3 x = pos[i].xyz;       /* 1. */
    float3 xp = pos_prev[i].xyz; /* 2. */
    float w = pos[i].w;          /* inverse mass; 0 = pinned */
    float3 vel = (x - xp) / dt;  /* 3. */
    float3 bv = b * vel;
    float3 force = (float3)(0.0f); /* 4. (differs: gravity is an acceleration, added in 6.) */

    for (int o = 0; o < 12; ++o) { /* 5. */
        /* (differs: the listing mixes x and y offsets; row and column stay paired here) */
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        if (r < 0 || r >= n || c < 0 || c >= n)
            continue; /* outside the grid: nothing added, not even zero */
        float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
        force = force + spring_force(x, pos[r * n + c].xyz, rest_o, k, bv);
    }

    float3 x_new = x; /* pinned particles are never integrated nor collided */
    if (w != 0.0f) {
        float3 acc = g.xyz + force * w;           /* (m*g + force) / m */
        x_new = (2.0f * x - xp) + acc * dt2;      /* 6. */
    }
#ifdef CLOTH_ATTACHED_PINS
    int slot = pin_slot[i]; /* a pin following a body goes to its target */
    if (slot >= 0)
        x_new = (float3)(pin_target[3 * slot], pin_target[3 * slot + 1], pin_target[3 * slot + 2]);
#endif
#ifndef CLOTH_SELF_COLLISION /* else self_collision.cl collides, after its pass */
    if (w != 0.0f) {
        x_new = collide(x_new, colliders, num_spheres, num_cylinders, num_boxes, num_planes);
#if CLOTH_MESHES > 0
        x_new = collide_meshes(x_new, colliders + analytic_rows, mesh_geometry, mesh_ints); /* after the planes */
#endif
    }
#endif
    pos_out[i] = (float4)(x_new, w); /* 7. */
    pos_prev_out[i] = (float4)(x, w); /* 8. */
#ifdef CLOTH_NORMALS
    normal_out[i] = (float4)(normal_at(pos, n, row, col, x), 0.0f); /* of x(t), for rendering */
#endif
}

#else
/* ======================================================================================
 * Specialised: the same step shaped for a CPU's SIMD units. State as SoA planes: x[0..n2),
 * y[n2..2n2), z[2n2..3n2) in one buffer per state; inverse mass in its own read-only buffer.
 *
 * The helpers below are written once over `floatv`, V = CLOTH_VECTOR_WIDTH lanes: the host
 * builds this part with the kernel shape's V for the interior, rows and multi-step kernels
 * (V consecutive particles of a row per work item) and with V = 1 for the border kernel (one
 * particle per work item). State buffers hold CLOTH_PAD floats before and after the planes;
 * every kernel steps its state pointers past them first. Explicit vectors because PoCL 3.1
 * (LLVM 15) does not vectorise the scalar form across work items: its first optimisation pass
 * packs four springs of one particle into gathers, which then blocks the work-item loop
 * vectoriser (docs/opencl.md, "Why explicit vectors").
 * ====================================================================================== */

#ifndef CLOTH_N
#error "build with -DCLOTH_N=<grid side> (or -DCLOTH_GENERIC)"
#endif
#include "collider_counts.cl"
#define N CLOTH_N
#define N2 (CLOTH_N * CLOTH_N)
/* Floats before and after the x, y, z planes in each state buffer (CLOTH_PAD, set by the
 * host): the whole-row kernels' masked vector loads at the grid's first and last particle
 * reach one float past either end of the planes; those lanes are never used. */
#ifndef CLOTH_PAD
#define CLOTH_PAD 0
#endif
#define PAD CLOTH_PAD
/* Floats from one plane of a state buffer to the next: n*n and CLOTH_STATE_GAP (set by
 * the host). Planes exactly n*n apart put the same column of x, y and z, and of the rows the
 * stencil reads, at the same low 12 address bits whenever n*n*4 is a multiple of 4 KiB: one L1
 * set, more lines than its ways (docs/c.md, "Planes apart", measured on the c kernel). The
 * normals keep their planes n*n apart: they are written once a step, never read here. */
#ifndef CLOTH_STATE_GAP
#define CLOTH_STATE_GAP 0
#endif
#define STATE_STRIDE (N2 + CLOTH_STATE_GAP)
/* Every helper is inlined: PoCL 3.0 (the wheel) and 3.1 left the bigger ones as calls, which
 * pass the vectors through memory. */
#define INLINE __attribute__((always_inline))

#ifndef CLOTH_VECTOR_WIDTH
#define CLOTH_VECTOR_WIDTH 1
#endif
#define V CLOTH_VECTOR_WIDTH
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
/* Loads, stores and select() of vectors as plain C: PoCL 3.0 (the wheel) calls the built-ins
 * vloadn, vstoren and select() out of line, hundreds of calls per work item. A vector load
 * through a pointer to a 4-byte-aligned vector type is what vloadn does; the conditional
 * operator on vectors is select() per lane (the most significant bit of each mask lane). */
#define SELECT(a, b, c) ((c) ? (b) : (a))
#if V == 1
typedef float floatv;
typedef int intv;
#define LOADV(p, j) ((p)[j])
#define STOREV(v, p, j) ((p)[j] = (v))
#else
typedef CAT(float, V) floatv;
typedef CAT(int, V) intv;
typedef floatv floatv_u __attribute__((aligned(4)));
typedef intv intv_u __attribute__((aligned(4)));
#define LOADV(p, j) (*(__global const floatv_u *)((p) + (j)))
#define STOREV(v, p, j) (*(__global floatv_u *)((p) + (j)) = (v))
#endif

/* fast builds: fast_rsqrt() (fast_math.cl) */
#include "fast_math.cl"

/* Step 5 for one neighbour j. select(), not if, keeps the lanes together. */
INLINE void spring_add(floatv x, floatv y, floatv z, __global const float *pos, int j, float k,
                float rest, floatv bx, floatv by, floatv bz, floatv *fx, floatv *fy, floatv *fz)
{
    floatv dx = LOADV(pos, j) - x, dy = LOADV(pos, STATE_STRIDE + j) - y, dz = LOADV(pos, 2 * STATE_STRIDE + j) - z;
#ifdef CLOTH_STRICT
    /* docs/semantics.md to the letter: sqrt, '/', and the damping -b*vel of this spring */
    floatv L2 = (dx * dx + dy * dy) + dz * dz;
    floatv L = sqrt(L2);
    floatv s = SELECT((floatv)(0.0f), (k * (L - rest)) / L, L2 > 0.0f); /* coincident: 0 */
    *fx = *fx + (s * dx - bx);
    *fy = *fy + (s * dy - by);
    *fz = *fz + (s * dz - bz);
#else
    /* k*(L - rest)*d/L = (k - k*rest/L)*d: one reciprocal square root; the damping of every
     * spring is added at once by integrate_store, so bx, by, bz go unused (and uncomputed) */
    floatv L2 = dx * dx + dy * dy + dz * dz;
    floatv s = SELECT((floatv)(0.0f), k - (k * rest) * fast_rsqrt(L2), L2 > 0.0f);
    *fx += s * dx;
    *fy += s * dy;
    *fz += s * dz;
#endif
}

/* The colliders, exactly as docs/semantics.md writes them (so in strict mode too), with
 * select() for every branch. A kind's code exists only when the scene has that kind. */
#if CLOTH_SPHERES > 0
INLINE void collide_sphere_v(floatv *x, floatv *y, floatv *z, float4 sphere)
{
    floatv dx = *x - sphere.x, dy = *y - sphere.y, dz = *z - sphere.z;
    floatv L2 = (dx * dx + dy * dy) + dz * dz;
    floatv L = sqrt(L2);
    floatv s = sphere.w / L;
    intv inside = L < sphere.w;
    intv at_centre = L2 == 0.0f; /* straight up */
    *x = SELECT(*x, SELECT(sphere.x + dx * s, (floatv)(sphere.x), at_centre), inside);
    *y = SELECT(*y, SELECT(sphere.y + dy * s, (floatv)(sphere.y + sphere.w), at_centre), inside);
    *z = SELECT(*z, SELECT(sphere.z + dz * s, (floatv)(sphere.z), at_centre), inside);
}
#endif

#if CLOTH_CYLINDERS > 0
INLINE void collide_cylinder_v(floatv *x, floatv *y, floatv *z, float4 start_len, float4 axis_r,
                        float4 radial_r)
{
    float len = start_len.w, r = axis_r.w;
    floatv dx = *x - start_len.x, dy = *y - start_len.y, dz = *z - start_len.z;
    floatv t = (dx * axis_r.x + dy * axis_r.y) + dz * axis_r.z; /* axial, from the start cap */
    floatv qx = axis_r.x * t, qy = axis_r.y * t, qz = axis_r.z * t;
    floatv px = dx - qx, py = dy - qy, pz = dz - qz; /* radial vector */
    floatv rho2 = (px * px + py * py) + pz * pz;
    floatv rho = sqrt(rho2);
    intv inside = (t > 0.0f) & (t < len) & (rho < r);
    floatv side = r - rho, to_end = len - t;
    intv through_side = (side <= t) & (side <= to_end);
    intv through_start = t <= to_end;
    intv on_axis = rho2 == 0.0f; /* a fixed radial direction */
    floatv s = r / rho;
    floatv ax = start_len.x + qx, ay = start_len.y + qy, az = start_len.z + qz;
    floatv side_x = SELECT(ax + px * s, ax + radial_r.x, on_axis);
    floatv side_y = SELECT(ay + py * s, ay + radial_r.y, on_axis);
    floatv side_z = SELECT(az + pz * s, az + radial_r.z, on_axis);
    floatv cap_x = SELECT(*x + axis_r.x * to_end, *x - qx, through_start);
    floatv cap_y = SELECT(*y + axis_r.y * to_end, *y - qy, through_start);
    floatv cap_z = SELECT(*z + axis_r.z * to_end, *z - qz, through_start);
    *x = SELECT(*x, SELECT(cap_x, side_x, through_side), inside);
    *y = SELECT(*y, SELECT(cap_y, side_y, through_side), inside);
    *z = SELECT(*z, SELECT(cap_z, side_z, through_side), inside);
}
#endif

#if CLOTH_BOXES > 0
INLINE void collide_box_v(floatv *x, floatv *y, floatv *z, float4 center, float4 ax0, float4 ax1,
                          float4 ax2)
{
    floatv dx = *x - center.x, dy = *y - center.y, dz = *z - center.z;
    floatv l0 = (dx * ax0.x + dy * ax0.y) + dz * ax0.z; /* the box's coordinates */
    floatv l1 = (dx * ax1.x + dy * ax1.y) + dz * ax1.z;
    floatv l2 = (dx * ax2.x + dy * ax2.y) + dz * ax2.z;
    floatv p0 = ax0.w - fabs(l0), p1 = ax1.w - fabs(l1), p2 = ax2.w - fabs(l2); /* depth per face pair */
    intv inside = (p0 > 0.0f) & (p1 > 0.0f) & (p2 > 0.0f);
    intv take1 = p1 < p0; /* the face pair of least penetration; ties to the lower axis */
    intv take2 = p2 < SELECT(p0, p1, take1);
    floatv l = SELECT(SELECT(l0, l1, take1), l2, take2);
    floatv h = SELECT(SELECT((floatv)(ax0.w), (floatv)(ax1.w), take1), (floatv)(ax2.w), take2);
    floatv m = SELECT(-h, h, l >= 0.0f) - l; /* to the face on the point's side (+ at l == 0) */
    floatv ux = SELECT(SELECT((floatv)(ax0.x), (floatv)(ax1.x), take1), (floatv)(ax2.x), take2);
    floatv uy = SELECT(SELECT((floatv)(ax0.y), (floatv)(ax1.y), take1), (floatv)(ax2.y), take2);
    floatv uz = SELECT(SELECT((floatv)(ax0.z), (floatv)(ax1.z), take1), (floatv)(ax2.z), take2);
    *x = SELECT(*x, *x + ux * m, inside);
    *y = SELECT(*y, *y + uy * m, inside);
    *z = SELECT(*z, *z + uz * m, inside);
}
#endif

#if CLOTH_PLANES > 0
INLINE void collide_plane_v(floatv *x, floatv *y, floatv *z, float4 point, float4 normal)
{
    floatv dist = ((*x - point.x) * normal.x + (*y - point.y) * normal.y) + (*z - point.z) * normal.z;
    intv inside = dist < 0.0f;
    *x = SELECT(*x, *x - normal.x * dist, inside);
    *y = SELECT(*y, *y - normal.y * dist, inside);
    *z = SELECT(*z, *z - normal.z * dist, inside);
}
#endif

/* Every collider, in the order docs/semantics.md fixes: spheres, cylinders, boxes, planes. */
INLINE void collide_v(floatv *x, floatv *y, floatv *z, __constant float4 *colliders)
{
#if CLOTH_SPHERES > 0
    for (int s = 0; s < CLOTH_SPHERES; ++s)
        collide_sphere_v(x, y, z, colliders[s]);
#endif
#if CLOTH_CYLINDERS > 0
    __constant float4 *cylinders = colliders + CLOTH_SPHERES;
    for (int c = 0; c < CLOTH_CYLINDERS; ++c)
        collide_cylinder_v(x, y, z, cylinders[3 * c], cylinders[3 * c + 1], cylinders[3 * c + 2]);
#endif
#if CLOTH_BOXES > 0
    __constant float4 *boxes = colliders + CLOTH_SPHERES + 3 * CLOTH_CYLINDERS;
    for (int b = 0; b < CLOTH_BOXES; ++b)
        collide_box_v(x, y, z, boxes[4 * b], boxes[4 * b + 1], boxes[4 * b + 2], boxes[4 * b + 3]);
#endif
#if CLOTH_PLANES > 0
    __constant float4 *planes = colliders + CLOTH_SPHERES + 3 * CLOTH_CYLINDERS + 4 * CLOTH_BOXES;
    for (int p = 0; p < CLOTH_PLANES; ++p)
        collide_plane_v(x, y, z, planes[2 * p], planes[2 * p + 1]);
#endif
}

#define TABLE_ROWS (ANALYTIC_ROWS + MESH_ROWS * CLOTH_MESHES) /* a step's collider table */

#if CLOTH_MESHES > 0 || defined(CLOTH_SELF_COLLISION)
/* (a.x*b.x + a.y*b.y) + a.z*b.z, for collide_mesh.cl and collide.cl: not dot(), whose order is the driver's */
INLINE float dot3(float3 a, float3 b)
{
    return (a.x * b.x + a.y * b.y) + a.z * b.z;
}
#endif
/* The meshes: collide_meshes_v(x, y, z, w, rows, geometry, ints), only where the scene has them. */
#include <mesh_colliders>

#ifdef CLOTH_ATTACHED_PINS
/* The lanes that are pins following a body take their targets (the others keep x). */
INLINE void pin_targets_v(int i, __global const int *pin_slot, __global const float *pin_target,
                          floatv *x, floatv *y, floatv *z)
{
#if V == 1
    int slot = pin_slot[i];
    if (slot >= 0)
        *x = pin_target[3 * slot], *y = pin_target[3 * slot + 1], *z = pin_target[3 * slot + 2];
#else
    float lx[V], ly[V], lz[V];
    *(floatv_u *)lx = *x, *(floatv_u *)ly = *y, *(floatv_u *)lz = *z;
    for (int l = 0; l < V; ++l) {
        int slot = pin_slot[i + l];
        if (slot >= 0)
            lx[l] = pin_target[3 * slot], ly[l] = pin_target[3 * slot + 1], lz[l] = pin_target[3 * slot + 2];
    }
    *x = *(floatv_u *)lx, *y = *(floatv_u *)ly, *z = *(floatv_u *)lz;
#endif
}
#endif

/* Store lanes first_lane .. V-1 of v at p[j..]: all of them, except in the last vector of
 * an interior row, whose first lanes the vector before it has written already. */
INLINE void store_lanes(floatv v, __global float *p, int j, int first_lane)
{
#if V == 1
    p[j] = v;
#else
    if (first_lane == 0) {
        STOREV(v, p, j);
        return;
    }
    float lanes[V];
    *(floatv_u *)lanes = v;
    for (int l = first_lane; l < V; ++l)
        p[j + l] = lanes[l];
#endif
}

#ifdef CLOTH_NORMALS
/* v / |v|, or 0 for a zero vector (a degenerate triangle has no direction) */
INLINE void unit_or_zero_v(floatv *x, floatv *y, floatv *z)
{
    floatv L2 = (*x * *x + *y * *y) + *z * *z;
    floatv L = sqrt(L2);
    intv some = L2 > 0.0f;
    *x = SELECT((floatv)(0.0f), *x / L, some);
    *y = SELECT((floatv)(0.0f), *y / L, some);
    *z = SELECT((floatv)(0.0f), *z / L, some);
}

/* Adds the unit normal of the face (x, ja, jb) to the sum: (a - x) x (c - x) written out. */
INLINE void face_add(floatv x, floatv y, floatv z, __global const float *pos, int ja, int jb,
              floatv *sx, floatv *sy, floatv *sz)
{
    floatv ax = LOADV(pos, ja) - x, ay = LOADV(pos, STATE_STRIDE + ja) - y, az = LOADV(pos, 2 * STATE_STRIDE + ja) - z;
    floatv cx = LOADV(pos, jb) - x, cy = LOADV(pos, STATE_STRIDE + jb) - y, cz = LOADV(pos, 2 * STATE_STRIDE + jb) - z;
    floatv fx = ay * cz - az * cy, fy = az * cx - ax * cz, fz = ax * cy - ay * cx;
    unit_or_zero_v(&fx, &fy, &fz);
    *sx = *sx + fx;
    *sy = *sy + fy;
    *sz = *sz + fz;
}

INLINE void store_normal(int i, int first_lane, floatv sx, floatv sy, floatv sz,
                  __global float *normal_out)
{
    unit_or_zero_v(&sx, &sy, &sz);
    store_lanes(sx, normal_out, i, first_lane);
    store_lanes(sy, normal_out, N2 + i, first_lane);
    store_lanes(sz, normal_out, 2 * N2 + i, first_lane);
}
#define NORMALS_ARG , __global float *normal_out
#else
#define NORMALS_ARG
#endif

/* Step 6 for the particles at i, which have `springs` springs each (per lane): integrate
 * unless pinned, collide; x(t+dt) in *nx_out, *ny_out, *nz_out. */
INLINE void integrate(int i, floatv x, floatv y, floatv z, floatv xp, floatv yp, floatv zp,
                      floatv fx, floatv fy, floatv fz, floatv springs, __global const float *inv_mass,
                      __constant float4 *colliders, float b, float dt, float dt2, float4 g,
                      floatv *nx_out, floatv *ny_out, floatv *nz_out BODY_PARAMS)
{
    floatv w = LOADV(inv_mass, i);
#ifdef CLOTH_STRICT
    /* acc = g + force*w, then (2x - xp) + acc*dt2, each operation rounded (6.) */
    floatv nx = (2.0f * x - xp) + (g.x + fx * w) * dt2;
    floatv ny = (2.0f * y - yp) + (g.y + fy * w) * dt2;
    floatv nz = (2.0f * z - zp) + (g.z + fz * w) * dt2;
#else
    /* the damping -b*vel of each of the particle's springs, added at once */
    floatv b_dt = springs * b / dt;
    floatv nx = (2.0f * x - xp) + (g.x + (fx - b_dt * (x - xp)) * w) * dt2;
    floatv ny = (2.0f * y - yp) + (g.y + (fy - b_dt * (y - yp)) * w) * dt2;
    floatv nz = (2.0f * z - zp) + (g.z + (fz - b_dt * (z - zp)) * w) * dt2;
#endif
    intv pinned = w == 0.0f; /* never integrated nor collided */
    nx = SELECT(nx, x, pinned), ny = SELECT(ny, y, pinned), nz = SELECT(nz, z, pinned);
#ifdef CLOTH_ATTACHED_PINS
    pin_targets_v(i, pin_slot, pin_target, &nx, &ny, &nz); /* before the colliders, as NumPy */
#endif
    floatv cx = nx, cy = ny, cz = nz;
#ifndef CLOTH_SELF_COLLISION /* else self_collision.cl collides, after its pass */
    collide_v(&cx, &cy, &cz, colliders);
#if CLOTH_MESHES > 0
    collide_meshes_v(&cx, &cy, &cz, w, colliders + ANALYTIC_ROWS, mesh_geometry, mesh_ints);
#endif
#endif
    *nx_out = SELECT(cx, nx, pinned), *ny_out = SELECT(cy, ny, pinned), *nz_out = SELECT(cz, nz, pinned);
}

/* The particles at i's lanes first_lane .. V-1 of (x, y, z) into the planes of p. */
INLINE void store_position(int i, int first_lane, floatv x, floatv y, floatv z, __global float *p)
{
    store_lanes(x, p, i, first_lane);
    store_lanes(y, p, STATE_STRIDE + i, first_lane);
    store_lanes(z, p, 2 * STATE_STRIDE + i, first_lane);
}

/* Steps 6-8 for the split kernels, which keep the chapter's four state buffers: x(t+dt) to
 * pos_out (7.), x(t) to pos_prev_out (8.). */
INLINE void integrate_store(int i, int first_lane, floatv x, floatv y, floatv z, floatv xp, floatv yp,
                     floatv zp, floatv fx, floatv fy, floatv fz, floatv springs,
                     __global const float *inv_mass, __global float *pos_out,
                     __global float *pos_prev_out, __constant float4 *colliders, float b,
                     float dt, float dt2, float4 g BODY_PARAMS)
{
    floatv nx, ny, nz;
    integrate(i, x, y, z, xp, yp, zp, fx, fy, fz, springs, inv_mass, colliders, b, dt, dt2, g, &nx,
              &ny, &nz BODY_PASS);
    store_position(i, first_lane, nx, ny, nz, pos_out);
    store_position(i, first_lane, x, y, z, pos_prev_out);
}

/* The 12 springs of particles whose neighbours all exist, unrolled, in the stencil's order. */
INLINE void springs_inside(floatv x, floatv y, floatv z, __global const float *pos, int i, float k,
                    float4 rest, floatv bx, floatv by, floatv bz, floatv *fx, floatv *fy, floatv *fz)
{
    spring_add(x, y, z, pos, i - 1, k, rest.x, bx, by, bz, fx, fy, fz); /* structural */
    spring_add(x, y, z, pos, i + 1, k, rest.x, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i - N, k, rest.x, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i + N, k, rest.x, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i - N - 1, k, rest.y, bx, by, bz, fx, fy, fz); /* shear */
    spring_add(x, y, z, pos, i - N + 1, k, rest.y, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i + N - 1, k, rest.y, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i + N + 1, k, rest.y, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i - 2 * N - 2, k, rest.z, bx, by, bz, fx, fy, fz); /* bend */
    spring_add(x, y, z, pos, i - 2 * N + 2, k, rest.z, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i + 2 * N - 2, k, rest.z, bx, by, bz, fx, fy, fz);
    spring_add(x, y, z, pos, i + 2 * N + 2, k, rest.z, bx, by, bz, fx, fy, fz);
}

#ifdef CLOTH_NORMALS
/* The six faces of particles whose ring neighbours all exist: up, up-left, left, down,
 * down-right, right. */
INLINE void faces_inside(floatv x, floatv y, floatv z, __global const float *pos, int i, floatv *sx,
                  floatv *sy, floatv *sz)
{
    face_add(x, y, z, pos, i - N, i - N - 1, sx, sy, sz);
    face_add(x, y, z, pos, i - N - 1, i - 1, sx, sy, sz);
    face_add(x, y, z, pos, i - 1, i + N, sx, sy, sz);
    face_add(x, y, z, pos, i + N, i + N + 1, sx, sy, sz);
    face_add(x, y, z, pos, i + N + 1, i + 1, sx, sy, sz);
    face_add(x, y, z, pos, i + 1, i - N, sx, sy, sz);
}
#endif

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
                                    __global float *pos_prev_out, const float k, const float b,
                                    const float dt, const float dt2, const float4 g,
                                    const float4 rest, __constant float4 *colliders NORMALS_ARG BODY_ARG)
{
    int item = get_global_id(0);
    if (item >= INTERIOR_ITEMS)
        return; /* the launch is padded when the work-group size does not divide it */
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this step's poses */
    PIN_STEP_TARGETS(step);
#endif
    pos += PAD, pos_prev += PAD, pos_out += PAD, pos_prev_out += PAD;
    int row = 2 + item / VECTORS_PER_ROW, vector = item % VECTORS_PER_ROW;
    int last = vector == VECTORS_PER_ROW - 1;
    int i = row * N + (last ? N - 2 - V : 2 + V * vector);
    floatv x = LOADV(pos, i), y = LOADV(pos, STATE_STRIDE + i), z = LOADV(pos, 2 * STATE_STRIDE + i);
    floatv xp = LOADV(pos_prev, i), yp = LOADV(pos_prev, STATE_STRIDE + i), zp = LOADV(pos_prev, 2 * STATE_STRIDE + i);
    floatv bx = b * ((x - xp) / dt), by = b * ((y - yp) / dt), bz = b * ((z - zp) / dt);
    floatv fx = 0.0f, fy = 0.0f, fz = 0.0f;
    springs_inside(x, y, z, pos, i, k, rest, bx, by, bz, &fx, &fy, &fz);
    integrate_store(i, last ? LAST_FIRST_LANE : 0, x, y, z, xp, yp, zp, fx, fy, fz,
                    (floatv)(12.0f), inv_mass, pos_out, pos_prev_out, colliders, b, dt, dt2, g BODY_PASS);
#ifdef CLOTH_NORMALS
    floatv sx = 0.0f, sy = 0.0f, sz = 0.0f;
    faces_inside(x, y, z, pos, i, &sx, &sy, &sz);
    store_normal(i, last ? LAST_FIRST_LANE : 0, sx, sy, sz, normal_out);
#endif
}
#endif

#if V == 1
/* The particles the interior kernel does not cover (the two-wide frame; every particle when
 * n - 4 < V), listed by the host: bounds checked, one particle per work item. */
__kernel void verlet_cloth_border(__global const float *pos, __global const float *pos_prev,
                                  __global const float *inv_mass, __global float *pos_out,
                                  __global float *pos_prev_out, const float k, const float b,
                                  const float dt, const float dt2, const float4 g,
                                  const float4 rest, __constant float4 *colliders,
                                  __global const int *particles, const int count NORMALS_ARG BODY_ARG)
{
    int item = get_global_id(0);
    if (item >= count)
        return;
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this step's poses */
    PIN_STEP_TARGETS(step);
#endif
    pos += PAD, pos_prev += PAD, pos_out += PAD, pos_prev_out += PAD;
    int i = particles[item];
    int row = i / N, col = i % N;
    float x = pos[i], y = pos[STATE_STRIDE + i], z = pos[2 * STATE_STRIDE + i];
    float xp = pos_prev[i], yp = pos_prev[STATE_STRIDE + i], zp = pos_prev[2 * STATE_STRIDE + i];
    float bx = b * ((x - xp) / dt), by = b * ((y - yp) / dt), bz = b * ((z - zp) / dt);
    float fx = 0.0f, fy = 0.0f, fz = 0.0f;
    float springs = 0.0f;
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        if (r < 0 || r >= N || c < 0 || c >= N)
            continue; /* outside the grid: nothing added, not even zero */
        float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
        spring_add(x, y, z, pos, r * N + c, k, rest_o, bx, by, bz, &fx, &fy, &fz);
        springs += 1.0f;
    }
    integrate_store(i, 0, x, y, z, xp, yp, zp, fx, fy, fz, springs, inv_mass, pos_out,
                    pos_prev_out, colliders, b, dt, dt2, g BODY_PASS);
#ifdef CLOTH_NORMALS
    float sx = 0.0f, sy = 0.0f, sz = 0.0f;
    for (int e = 0; e < 6; ++e) {
        int ra = row + RING[e].x, ca = col + RING[e].y;
        int rb = row + RING[(e + 1) % 6].x, cb = col + RING[(e + 1) % 6].y;
        if (ra < 0 || ra >= N || ca < 0 || ca >= N || rb < 0 || rb >= N || cb < 0 || cb >= N)
            continue; /* a face needs both its ring neighbours */
        face_add(x, y, z, pos, ra * N + ca, rb * N + cb, &sx, &sy, &sz);
    }
    store_normal(i, 0, sx, sy, sz, normal_out);
#endif
}
#endif

/* ======================================================================================
 * Whole rows, one kernel for every particle (the `rows` shapes): work item `item` takes V
 * consecutive particles of one row, the rows' vectors laid side by side, the last vector of
 * a row overlapping the one before it when V does not divide n (it stores only the lanes
 * that one did not). A vector whose neighbours all exist takes the unrolled interior path;
 * one at the grid's edge runs the stencil in order and skips a spring per lane where the
 * neighbour is outside the grid: a neighbour row outside skips the spring for every lane
 * (the branch is the same for all of them), a neighbour column outside only for its lanes,
 * by select(), which leaves those lanes' force exactly as it was. So every lane does the
 * operations of docs/semantics.md in their order, and strict stays bit-exact. One launch
 * per step instead of the interior's and the border's; only grids with n >= V have it.
 * Two state buffers, not four: x(t+dt) is written over x(t-dt) in place and the host swaps
 * the two (pos <- the written buffer, pos_prev <- the old pos), so a step streams 10 floats a
 * particle instead of 13, and writes only lines it has just read (docs/bounds.md, "The count").
 *
 * verlet_cloth_steps (the `steps/launch=K` shapes) runs several steps in one launch, with
 * the whole grid in one work-group: each work item takes every local-size-th vector, a
 * barrier separates the steps (valid inside one work-group; the state stays in the global
 * buffers, written in place and swapped by pointer as the host does between launches). It pays one
 * launch per K steps, at the price of one work-group, so one core: for small grids only.
 * With CLOTH_NORMALS it writes the normals at every step; the last step's are left, those of
 * the state it read, as after a one-step launch.
 * ====================================================================================== */
#if N >= V
#define ROW_VECTORS ((N + V - 1) / V)
#define ROWS_ITEMS (ROW_VECTORS * N)
#define ROW_LAST_FIRST_LANE (V * ROW_VECTORS - N)

/* lane l of a vector is column c0 + l */
__constant int LANE_INDEX[16] = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15};

INLINE intv lane_columns(int c0)
{
#if V == 1
    return c0;
#else
    return c0 + *(__constant const intv_u *)LANE_INDEX;
#endif
}

/* A column in the grid, per lane (a vector comparison is -1 for true, as select() wants). */
INLINE intv column_in_grid(intv c)
{
    return (c >= 0) & (c < N);
}

/* spring_add for the lanes where `valid`; the other lanes keep their force exactly. */
INLINE void spring_add_masked(floatv x, floatv y, floatv z, __global const float *pos, int j, float k,
                       float rest, floatv bx, floatv by, floatv bz, floatv *fx, floatv *fy,
                       floatv *fz, intv valid)
{
    floatv gx = *fx, gy = *fy, gz = *fz;
    spring_add(x, y, z, pos, j, k, rest, bx, by, bz, &gx, &gy, &gz);
    *fx = SELECT(*fx, gx, valid);
    *fy = SELECT(*fy, gy, valid);
    *fz = SELECT(*fz, gz, valid);
}

#ifdef CLOTH_NORMALS
/* face_add for the lanes where `valid` */
INLINE void face_add_masked(floatv x, floatv y, floatv z, __global const float *pos, int ja, int jb,
                     floatv *sx, floatv *sy, floatv *sz, intv valid)
{
    floatv tx = *sx, ty = *sy, tz = *sz;
    face_add(x, y, z, pos, ja, jb, &tx, &ty, &tz);
    *sx = SELECT(*sx, tx, valid);
    *sy = SELECT(*sy, ty, valid);
    *sz = SELECT(*sz, tz, valid);
}
#endif

/* Lanes first_lane .. V-1 of p[j..]; the others take `other`. The rows kernels write x(t+dt)
 * over x(t-dt): the first lanes of a row's last vector are the vector before it's, which another
 * work item may be writing, so that vector loads only its own lanes of pos_prev. */
INLINE floatv load_lanes(__global const float *p, int j, int first_lane, floatv other)
{
#if V == 1
    return p[j];
#else
    if (first_lane == 0)
        return LOADV(p, j);
    float lanes[V];
    *(floatv_u *)lanes = other;
    for (int l = first_lane; l < V; ++l)
        lanes[l] = p[j + l];
    return *(floatv_u *)lanes;
#endif
}

/* One step for the V particles of work item `item` (see above): reads x(t) from pos and its own
 * particles' x(t-dt) from pos_prev, and writes their x(t+dt) over the latter. In place is safe:
 * a particle's x(t-dt) is read only by its own work item, the neighbours' positions come from
 * pos, which no work item writes. */
INLINE void rows_item(int item, __global const float *pos, __global float *pos_prev,
               __global const float *inv_mass, float k, float b, float dt, float dt2, float4 g,
               float4 rest, __constant float4 *colliders NORMALS_ARG BODY_PARAMS)
{
    int row = item / ROW_VECTORS, vector = item % ROW_VECTORS;
    int last = vector == ROW_VECTORS - 1;
    int c0 = last ? N - V : V * vector;
    int first_lane = last ? ROW_LAST_FIRST_LANE : 0;
    int i = row * N + c0;
    int inside = row >= 2 && row < N - 2 && c0 >= 2 && c0 + V <= N - 2;
    floatv x = LOADV(pos, i), y = LOADV(pos, STATE_STRIDE + i), z = LOADV(pos, 2 * STATE_STRIDE + i);
    floatv xp = load_lanes(pos_prev, i, first_lane, x), yp = load_lanes(pos_prev, STATE_STRIDE + i, first_lane, y);
    floatv zp = load_lanes(pos_prev, 2 * STATE_STRIDE + i, first_lane, z);
    floatv bx = b * ((x - xp) / dt), by = b * ((y - yp) / dt), bz = b * ((z - zp) / dt);
    floatv fx = 0.0f, fy = 0.0f, fz = 0.0f;
    floatv springs = 12.0f;
    intv columns = lane_columns(c0);
    if (inside) {
        springs_inside(x, y, z, pos, i, k, rest, bx, by, bz, &fx, &fy, &fz);
    } else {
        springs = 0.0f;
#pragma unroll
        for (int o = 0; o < 12; ++o) { /* unrolled: the offsets and rest lengths fold */
            int r = row + OFFSETS[o].x, dc = OFFSETS[o].y;
            if (r < 0 || r >= N)
                continue; /* outside the grid for every lane: nothing added */
            intv valid = column_in_grid(columns + dc);
            float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
            spring_add_masked(x, y, z, pos, r * N + c0 + dc, k, rest_o, bx, by, bz, &fx, &fy,
                              &fz, valid);
            springs = SELECT(springs, springs + 1.0f, valid);
        }
    }
    floatv nx, ny, nz;
    integrate(i, x, y, z, xp, yp, zp, fx, fy, fz, springs, inv_mass, colliders, b, dt, dt2, g, &nx,
              &ny, &nz BODY_PASS);
    store_position(i, first_lane, nx, ny, nz, pos_prev); /* 7., over x(t-dt); the host swaps (8.) */
#ifdef CLOTH_NORMALS
    floatv sx = 0.0f, sy = 0.0f, sz = 0.0f;
    if (inside) {
        faces_inside(x, y, z, pos, i, &sx, &sy, &sz);
    } else {
#pragma unroll
        for (int e = 0; e < 6; ++e) {
            int ra = row + RING[e].x, rb = row + RING[(e + 1) % 6].x;
            if (ra < 0 || ra >= N || rb < 0 || rb >= N)
                continue; /* a face needs both its ring neighbours */
            int dca = RING[e].y, dcb = RING[(e + 1) % 6].y;
            intv valid = column_in_grid(columns + dca) & column_in_grid(columns + dcb);
            face_add_masked(x, y, z, pos, ra * N + c0 + dca, rb * N + c0 + dcb, &sx, &sy, &sz,
                            valid);
        }
    }
    store_normal(i, first_lane, sx, sy, sz, normal_out);
#endif
}

#ifdef CLOTH_NORMALS
#define NORMALS_PASS , normal_out
#else
#define NORMALS_PASS
#endif

__kernel void verlet_cloth_rows(__global const float *pos, __global float *pos_prev,
                                __global const float *inv_mass, const float k, const float b,
                                const float dt, const float dt2, const float4 g,
                                const float4 rest, __constant float4 *colliders NORMALS_ARG BODY_ARG)
{
    int item = get_global_id(0);
    if (item >= ROWS_ITEMS)
        return; /* the launch is padded when the work-group size does not divide it */
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this step's poses */
    PIN_STEP_TARGETS(step);
#endif
    rows_item(item, pos + PAD, pos_prev + PAD, inv_mass, k, b, dt, dt2, g, rest,
              colliders NORMALS_PASS BODY_PASS);
}

/* `steps` steps from (pos, pos_prev), each written in place as verlet_cloth_rows does, the two
 * buffers swapping roles between steps: the result is in (pos_prev, pos) after an odd count, in
 * (pos, pos_prev) after an even one. Launched as one work-group. */
__kernel void verlet_cloth_steps(__global float *pos, __global float *pos_prev,
                                 __global const float *inv_mass, const float k, const float b,
                                 const float dt, const float dt2, const float4 g,
                                 const float4 rest, __constant float4 *colliders,
                                 const int steps NORMALS_ARG BODY_ARG)
{
    int first = get_local_id(0), stride = get_local_size(0);
    __global float *in = pos + PAD, *in_prev = pos_prev + PAD;
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* the launch's first step's poses; one table per step */
    PIN_STEP_TARGETS(step);
#endif
    for (int s = 0; s < steps; ++s) {
        for (int item = first; item < ROWS_ITEMS; item += stride)
            rows_item(item, in, in_prev, inv_mass, k, b, dt, dt2, g, rest, colliders NORMALS_PASS BODY_PASS);
#ifdef CLOTH_PER_STEP
        colliders += TABLE_ROWS; /* the next step's */
        PIN_STEP_TARGETS(1);
#endif
        /* the next step reads what every work item wrote, and writes over what they read */
        barrier(CLK_GLOBAL_MEM_FENCE);
        __global float *t = in;
        in = in_prev, in_prev = t;
    }
}
#endif
#endif /* CLOTH_GENERIC */

/* [self_collision]: its pass and the colliders after it, only where the scene has the table. */
#include <self_collision>
