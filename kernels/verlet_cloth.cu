/*
 * The mass-spring cloth step in two kernels (docs/cuda.md):
 *
 *   verlet_step   one step, one CUDA thread per particle: the chapter's verlet_cloth_kernel.cu
 *                 (Game Engine Gems 2, section 22.7, after Listing 22.1);
 *   verlet_steps  `steps` steps in one launch of one thread block that holds the whole grid in
 *                 shared memory, each thread several particles, __syncthreads() between steps:
 *                 for small grids, where a launch costs more than a step.
 *
 * Both call verlet_particle, so a particle's operations are the same in both. The step is
 * defined operation by operation in docs/semantics.md, the normals in docs/normals.md; this
 * file performs those operations in that order and does not restate them. The launch is in
 * Python (clothbench/backends/cuda/launch.py: PingPong), which owns the two pairs of buffers
 * (pos, pos_prev) x (in, out) and either swaps them or copies out to in after each launch.
 *
 * The host builds this one file in several ways, with -D switches (verlet.py: kernel_defines):
 *
 *   CLOTH_STRICT   sqrtf and '/', built with --fmad=false --ftz=false --prec-div=true
 *                  --prec-sqrt=true, so every operation is one correctly rounded IEEE float
 *                  operation and the result equals the NumPy float32 reference bit for bit.
 *                  Otherwise (fast): rsqrtf for the spring, sphere and normal normalisation,
 *                  built with --use_fast_math; measured against the float64 reference instead.
 *   CLOTH_GENERIC  one kernel for every scene: the constants, and every collider kind with its
 *                  count and parameters, are kernel arguments (`--generic`).
 *                  Otherwise (specialised, the default): the scene's values are compile-time
 *                  constants, exact float literals rounded once on the host (CLOTH_N, CLOTH_DT,
 *                  ..., CLOTH_SPHERE_COUNT, CLOTH_SPHERES = {{x, y, z, r}, ...}, ...), and the
 *                  code of a collider kind the scene lacks is not compiled at all.
 *   CLOTH_NORMALS  also write the normal of x(t) to a fifth buffer; without it there is no
 *                  normal code and no normal buffer.
 *   CLOTH_MESH_COUNT (specialised) / CLOTH_MESHES (generic)   the scene has triangle meshes:
 *                  collide_mesh.cuh, with two buffers uploaded once (docs/cuda.md, "Meshes");
 *                  CLOTH_MESH_BVH picks the accelerated search. Without it there is no mesh code.
 *   CLOTH_MOTION   the scene has moving colliders or pins attached to a body: every collider's
 *                  rows, each mesh's pose and the attached pins' targets come from a per-step
 *                  table (`motion`, the rows of one step after another) instead of constants.
 *                  Without it there is no motion code.
 *   CLOTH_SELF_COLLISION   the scene has [self_collision]: self_collision.cuh's kernels, and
 *                  verlet_step leaves the colliders to its pass (docs/cuda.md, "Self-collision").
 *                  Without it there is no self-collision code.
 */

// A neighbour's offset in the grid: (row, column), as docs/semantics.md writes it.
struct Offset {
    int dr, dc;
};

// The 12-spring stencil in summation order (scene.OFFSETS): the springs of step 5, and the
// pairs the self-collision pass leaves out.
#define STENCIL                                                                              \
    {                                                                                        \
        {0, -1}, {0, 1}, {-1, 0}, {1, 0},     /* structural */                               \
        {-1, -1}, {-1, 1}, {1, -1}, {1, 1},   /* shear */                                    \
        {-2, -2}, {-2, 2}, {2, -2}, {2, 2},   /* bend: the long diagonals, as the chapter's demo */ \
    }

#ifdef CLOTH_GENERIC
#define HAS_SPHERES 1
#define HAS_CYLINDERS 1
#define HAS_BOXES 1
#define HAS_PLANES 1
#ifdef CLOTH_MESHES
#define HAS_MESHES 1
#define MESH_COUNT mesh_count
#else
#define HAS_MESHES 0
#define MESH_COUNT 0
#endif
#ifdef CLOTH_MOTION
#define HAS_PIN_TARGETS 1  // pin_slot is an argument; -1 everywhere where no pin is attached
#endif
#define SPHERE_COUNT sphere_count
#define CYLINDER_COUNT cylinder_count
#define BOX_COUNT box_count
#define PLANE_COUNT plane_count
#elif !defined(CLOTH_N)
#error "build with -DCLOTH_GENERIC, or with the scene's -D values (clothbench.backends.cuda.verlet.kernel_defines)"
#else
// the scene, baked in: the compiler folds these into the code (n * n, i / n, k * ..., ...)
constexpr int n = CLOTH_N;
constexpr float dt = CLOTH_DT, dt2 = CLOTH_DT2;
constexpr float k = CLOTH_K, b = CLOTH_B;
constexpr float gx = CLOTH_GX, gy = CLOTH_GY, gz = CLOTH_GZ;
constexpr float rest_structural = CLOTH_REST_STRUCTURAL, rest_shear = CLOTH_REST_SHEAR,
                rest_bend = CLOTH_REST_BEND;
#define HAS_SPHERES (CLOTH_SPHERE_COUNT > 0)
#define HAS_CYLINDERS (CLOTH_CYLINDER_COUNT > 0)
#define HAS_BOXES (CLOTH_BOX_COUNT > 0)
#define HAS_PLANES (CLOTH_PLANE_COUNT > 0)
// the colliders, in the row layout the generic kernel takes as arguments (see verlet_step)
#if HAS_SPHERES
constexpr int sphere_count = CLOTH_SPHERE_COUNT;
#endif
#if HAS_CYLINDERS
constexpr int cylinder_count = CLOTH_CYLINDER_COUNT;
#endif
#if HAS_BOXES
constexpr int box_count = CLOTH_BOX_COUNT;
#endif
#if HAS_PLANES
constexpr int plane_count = CLOTH_PLANE_COUNT;
#endif
#ifndef CLOTH_MOTION  // a moving scene reads every collider's rows from the step's table
#if HAS_SPHERES
static __device__ const float4 spheres[sphere_count] = CLOTH_SPHERES;
#endif
#if HAS_CYLINDERS
static __device__ const float4 cylinders[3 * cylinder_count] = CLOTH_CYLINDERS;
#endif
#if HAS_BOXES
static __device__ const float4 boxes[4 * box_count] = CLOTH_BOXES;
#endif
#if HAS_PLANES
static __device__ const float4 planes[2 * plane_count] = CLOTH_PLANES;
#endif
#endif
#ifdef CLOTH_MESH_COUNT
#define HAS_MESHES 1
constexpr int mesh_count = CLOTH_MESH_COUNT;
#define MESH_COUNT CLOTH_MESH_COUNT
#else
#define HAS_MESHES 0
#define MESH_COUNT 0
#endif
#ifdef CLOTH_MOTION
constexpr int motion_rows = CLOTH_MOTION_ROWS;  // rows of the table per step
#define HAS_PIN_TARGETS (CLOTH_PIN_COUNT > 0)
#endif
#define SPHERE_COUNT CLOTH_SPHERE_COUNT
#define CYLINDER_COUNT CLOTH_CYLINDER_COUNT
#define BOX_COUNT CLOTH_BOX_COUNT
#define PLANE_COUNT CLOTH_PLANE_COUNT
#endif
#ifndef HAS_PIN_TARGETS
#define HAS_PIN_TARGETS 0  // no motion: pinned particles stay where they are
#endif

// Where a step finds its colliders' rows: the fixed ones, or its part of the per-step table,
// `step_rows` (docs/semantics.md, "Moving colliders"): the rows of every sphere, cylinder, box
// and plane in the fixed layout, then three rows (R row i, T_i) per mesh, then one row per
// attached pin (its target), in that order.
#ifdef CLOTH_MOTION
#define SPHERE_ROWS (step_rows)
#define CYLINDER_ROWS (SPHERE_ROWS + SPHERE_COUNT)
#define BOX_ROWS (CYLINDER_ROWS + 3 * CYLINDER_COUNT)
#define PLANE_ROWS (BOX_ROWS + 4 * BOX_COUNT)
#define MESH_POSE(m) (PLANE_ROWS + 2 * PLANE_COUNT + 3 * (m))
#define PIN_TARGETS (PLANE_ROWS + 2 * PLANE_COUNT + 3 * MESH_COUNT)
#else
#define SPHERE_ROWS spheres
#define CYLINDER_ROWS cylinders
#define BOX_ROWS boxes
#define PLANE_ROWS planes
#define MESH_POSE(m) (mesh_rows + MESH_HEADER_ROWS * (m) + 2)  // the fixed pose, in the header
#endif

__device__ __forceinline__ bool inside_grid(int r, int c, int n)
{
    return r >= 0 && r < n && c >= 0 && c < n;
}

__device__ __forceinline__ float3 minus(float3 a, float3 c)
{
    return make_float3(a.x - c.x, a.y - c.y, a.z - c.z);
}

// (a.x*c.x + a.y*c.y) + a.z*c.z, the documented order (no dot(): its order is not ours).
__device__ __forceinline__ float dot3(float3 a, float3 c)
{
    return (a.x * c.x + a.y * c.y) + a.z * c.z;
}

// Steps 5.3-5.5: the factor s with spring force s * d, d = x_j - x_i: k (L - rest) / L.
// Coincident particles (L2 = 0) have no direction and add no spring force.
__device__ __forceinline__ float spring_scale(float L2, float rest, float k)
{
    if (!(L2 > 0.0f)) return 0.0f;
#ifdef CLOTH_STRICT
    const float L = sqrtf(L2);
    return (k * (L - rest)) / L;
#else
    const float inv_L = rsqrtf(L2);  // approximate on the GPU: one instruction for sqrt and '/'
    return k * (L2 * inv_L - rest) * inv_L;
#endif
}

#if HAS_SPHERES
// Section 22.3: a particle inside the sphere (centre xyz, radius w) is moved to the surface
// along the ray from the centre; one exactly at the centre has no ray and goes straight up.
__device__ __forceinline__ float3 collide_sphere(float3 x, float4 sphere)
{
    const float3 c = make_float3(sphere.x, sphere.y, sphere.z);
    const float r = sphere.w;
    const float3 d = minus(x, c);
    const float L2 = dot3(d, d);
#ifdef CLOTH_STRICT
    const float L = sqrtf(L2);
    if (!(L < r)) return x;
    if (!(L2 > 0.0f)) return make_float3(c.x, c.y + r, c.z);
    const float s = r / L;
#else
    if (!(L2 < r * r)) return x;
    if (!(L2 > 0.0f)) return make_float3(c.x, c.y + r, c.z);
    const float s = r * rsqrtf(L2);
#endif
    return make_float3(c.x + d.x * s, c.y + d.y * s, c.z + d.z * s);
}
#endif

#if HAS_CYLINDERS
// A capped cylinder, rows (start a, length len), (unit axis u, radius r), (radial_r, 0):
// a particle inside is pushed out the shortest way, through the side or the nearer cap.
__device__ __forceinline__ float3 collide_cylinder(float3 x, float4 a_len, float4 u_r, float4 radial_r)
{
    const float3 a = make_float3(a_len.x, a_len.y, a_len.z);
    const float3 u = make_float3(u_r.x, u_r.y, u_r.z);
    const float len = a_len.w, r = u_r.w;
    const float3 d = minus(x, a);
    const float t = dot3(d, u);  // axial coordinate from the start cap
    const float3 q = make_float3(u.x * t, u.y * t, u.z * t);
    const float3 p = minus(d, q);  // radial vector
    const float rho2 = dot3(p, p);
    const float rho = sqrtf(rho2);
    if (!(t > 0.0f && t < len && rho < r)) return x;
    const float side = r - rho;
    const float to_end = len - t;
    if (side <= t && side <= to_end) {  // through the curved side
        const float3 base = make_float3(a.x + q.x, a.y + q.y, a.z + q.z);
        if (!(rho2 > 0.0f))  // exactly on the axis: out along the fixed radial direction
            return make_float3(base.x + radial_r.x, base.y + radial_r.y, base.z + radial_r.z);
        const float s = r / rho;
        return make_float3(base.x + p.x * s, base.y + p.y * s, base.z + p.z * s);
    }
    if (t <= to_end) return minus(x, q);                                   // through the start cap
    return make_float3(x.x + u.x * to_end, x.y + u.y * to_end, x.z + u.z * to_end);  // the end cap
}
#endif

#if HAS_BOXES
// An oriented box, rows (centre c, 0), (axis i, half extent h_i) for i = 0, 1, 2, axis i the
// world direction of its local axis i: a particle strictly inside is moved along the axis of
// least penetration (ties to the lower axis) onto the face on its side (+ at l_k == 0).
__device__ __forceinline__ float3 collide_box(float3 x, float4 center, float4 ax0, float4 ax1, float4 ax2)
{
    const float3 d = minus(x, make_float3(center.x, center.y, center.z));
    const float3 a0 = make_float3(ax0.x, ax0.y, ax0.z);
    const float3 a1 = make_float3(ax1.x, ax1.y, ax1.z);
    const float3 a2 = make_float3(ax2.x, ax2.y, ax2.z);
    const float l0 = dot3(d, a0), l1 = dot3(d, a1), l2 = dot3(d, a2);  // the box's own coordinates
    const float p0 = ax0.w - fabsf(l0), p1 = ax1.w - fabsf(l1), p2 = ax2.w - fabsf(l2);  // depths
    if (!(p0 > 0.0f && p1 > 0.0f && p2 > 0.0f)) return x;
    float3 u = a0;
    float lk = l0, hk = ax0.w, pk = p0;
    if (p1 < pk) u = a1, lk = l1, hk = ax1.w, pk = p1;
    if (p2 < pk) u = a2, lk = l2, hk = ax2.w;
    const float move = (lk >= 0.0f ? hk : -hk) - lk;
    return make_float3(x.x + u.x * move, x.y + u.y * move, x.z + u.z * move);
}
#endif

#if HAS_PLANES
// A one-sided plane, rows (point p0, 0), (unit normal nrm, 0): solid where the signed
// distance is negative (a floor); a particle below it is moved back onto it along nrm.
__device__ __forceinline__ float3 collide_plane(float3 x, float4 point, float4 normal)
{
    const float3 nrm = make_float3(normal.x, normal.y, normal.z);
    const float dist = dot3(minus(x, make_float3(point.x, point.y, point.z)), nrm);
    if (!(dist < 0.0f)) return x;
    return make_float3(x.x - nrm.x * dist, x.y - nrm.y * dist, x.z - nrm.z * dist);
}
#endif

// Where a step reads x(t): the input buffer (verlet_step) or the block's copy of it in shared
// memory, one array per component (verlet_steps). pos(j) is particle j's position.
struct GlobalPositions {
    const float4* __restrict__ p;
    __device__ __forceinline__ float3 operator()(int j) const
    {
        const float4 v = p[j];
        return make_float3(v.x, v.y, v.z);
    }
};

struct SharedPositions {
    const float* x;
    const float* y;
    const float* z;
    __device__ __forceinline__ float3 operator()(int j) const { return make_float3(x[j], y[j], z[j]); }
};

#if HAS_MESHES
#include "collide_mesh.cuh"
#endif

#ifdef CLOTH_NORMALS
// docs/normals.md: v / |v|, or 0 for a zero vector (a degenerate triangle has no direction)
__device__ __forceinline__ float3 unit_or_zero(float3 v)
{
    const float L2 = dot3(v, v);
    if (!(L2 > 0.0f)) return make_float3(0.0f, 0.0f, 0.0f);
#ifdef CLOTH_STRICT
    const float L = sqrtf(L2);
    return make_float3(v.x / L, v.y / L, v.z / L);
#else
    const float inv_L = rsqrtf(L2);
    return make_float3(v.x * inv_L, v.y * inv_L, v.z * inv_L);
#endif
}

// The chapter's per-particle normal: the normalised sum of the unit normals of the (up to
// six) triangles around (row, col), each grid quad split along its (r,c)-(r+1,c+1) diagonal.
template <class Positions>
__device__ __forceinline__ float3 normal_at(Positions pos, int row, int col, int n, float3 x)
{
    // the ring of neighbours: up, up-left, left, down, down-right, right (then up again)
    const Offset ring[7] = {{-1, 0}, {-1, -1}, {0, -1}, {1, 0}, {1, 1}, {0, 1}, {-1, 0}};
    float3 sum = make_float3(0.0f, 0.0f, 0.0f);
#pragma unroll
    for (int e = 0; e < 6; ++e) {
        const int ra = row + ring[e].dr, ca = col + ring[e].dc;
        const int rb = row + ring[e + 1].dr, cb = col + ring[e + 1].dc;
        if (!inside_grid(ra, ca, n) || !inside_grid(rb, cb, n)) continue;
        const float3 a = minus(pos(ra * n + ca), x);
        const float3 c = minus(pos(rb * n + cb), x);
        const float3 f = unit_or_zero(make_float3(a.y * c.z - a.z * c.y,    // a x c, written out
                                                  a.z * c.x - a.x * c.z,
                                                  a.x * c.y - a.y * c.x));
        sum = make_float3(sum.x + f.x, sum.y + f.y, sum.z + f.z);
    }
    return unit_or_zero(sum);
}
#endif

// The scene's values: kernel parameters of the generic build (the same names as the
// specialised build's constants above, so the code below reads the same in both).
#ifdef CLOTH_GENERIC
#ifdef CLOTH_MOTION  // the collider rows are in the step's table: only their counts
#define COLLIDER_PARAMS int sphere_count, int cylinder_count, int box_count, int plane_count
#define COLLIDER_ARGS sphere_count, cylinder_count, box_count, plane_count
#else
#define COLLIDER_PARAMS                                                                     \
    const float4* __restrict__ spheres, int sphere_count,     /* (centre, radius) */        \
    const float4* __restrict__ cylinders, int cylinder_count, /* 3 rows, collide_cylinder */ \
    const float4* __restrict__ boxes, int box_count,          /* 4 rows, collide_box */      \
    const float4* __restrict__ planes, int plane_count        /* 2 rows, collide_plane */
#define COLLIDER_ARGS spheres, sphere_count, cylinders, cylinder_count, boxes, box_count, planes, plane_count
#endif
#define SCENE_PARAMS                                                                        \
    , int n,                              /* particles per side */                          \
    float dt, float dt2,                  /* dt2 = dt*dt rounded once on the host */        \
    float k, float b,                     /* spring stiffness and damping */                \
    float gx, float gy, float gz,         /* gravity, an acceleration (not scaled by 1/m) */ \
    float rest_structural, float rest_shear, float rest_bend, /* |(dr, dc)| * h */          \
    COLLIDER_PARAMS
#define SCENE_ARGS , n, dt, dt2, k, b, gx, gy, gz, rest_structural, rest_shear, rest_bend, COLLIDER_ARGS
#else
#define SCENE_PARAMS
#define SCENE_ARGS
#endif

// The meshes' two buffers (collide_mesh.cuh), in both builds; generic: and their count.
#if HAS_MESHES && defined(CLOTH_GENERIC)
#define MESH_PARAMS , const float4* __restrict__ mesh_rows, const int* __restrict__ mesh_ints, int mesh_count
#define MESH_ARGS , mesh_rows, mesh_ints, mesh_count
#elif HAS_MESHES
#define MESH_PARAMS , const float4* __restrict__ mesh_rows, const int* __restrict__ mesh_ints
#define MESH_ARGS , mesh_rows, mesh_ints
#else
#define MESH_PARAMS
#define MESH_ARGS
#endif

// Motion: a launch takes the table of its steps (`motion`, motion_rows rows a step) and, with
// attached pins, each particle's row among the pin targets (pin_slot, -1: not attached); a
// step reads its own rows (`step_rows`). Generic: motion_rows is an argument.
#if HAS_PIN_TARGETS
#define PIN_PARAMS , const int* __restrict__ pin_slot
#define PIN_ARGS , pin_slot
#else
#define PIN_PARAMS
#define PIN_ARGS
#endif
#if defined(CLOTH_MOTION) && defined(CLOTH_GENERIC)
#define MOTION_PARAMS , const float4* __restrict__ motion, int motion_rows PIN_PARAMS
#elif defined(CLOTH_MOTION)
#define MOTION_PARAMS , const float4* __restrict__ motion PIN_PARAMS
#else
#define MOTION_PARAMS
#endif
#ifdef CLOTH_MOTION
#define STEP_ROWS_PARAMS , const float4* __restrict__ step_rows PIN_PARAMS
#define STEP_ROWS_ARGS(step) , motion + (step) * motion_rows PIN_ARGS
#else
#define STEP_ROWS_PARAMS
#define STEP_ROWS_ARGS(step)
#endif

// What the colliders read (apply_colliders): generic, the collider parameters; with motion, the
// step's rows (no pin slots).
#ifdef CLOTH_GENERIC
#define COLLIDE_PARAMS , COLLIDER_PARAMS
#define COLLIDE_ARGS , COLLIDER_ARGS
#else
#define COLLIDE_PARAMS
#define COLLIDE_ARGS
#endif
#ifdef CLOTH_MOTION
#define ROWS_PARAM , const float4* __restrict__ step_rows
#define ROWS_ARG , step_rows
#else
#define ROWS_PARAM
#define ROWS_ARG
#endif
// The step collides its particles, unless the self-collision pass does it after pushing them.
#ifdef CLOTH_SELF_COLLISION
#define COLLIDE_IN_STEP false
#else
#define COLLIDE_IN_STEP true
#endif

// The colliders' part of step 6: every collider in the fixed order, all spheres, cylinders,
// boxes, planes, then meshes (at the step's rows where they move).
__device__ __forceinline__ float3 apply_colliders(float3 x_new COLLIDE_PARAMS MESH_PARAMS ROWS_PARAM)
{
#if HAS_SPHERES
    for (int s = 0; s < sphere_count; ++s)
        x_new = collide_sphere(x_new, SPHERE_ROWS[s]);
#endif
#if HAS_CYLINDERS
    for (int c = 0; c < cylinder_count; ++c)
        x_new = collide_cylinder(x_new, CYLINDER_ROWS[3 * c], CYLINDER_ROWS[3 * c + 1], CYLINDER_ROWS[3 * c + 2]);
#endif
#if HAS_BOXES
    for (int o = 0; o < box_count; ++o)
        x_new = collide_box(x_new, BOX_ROWS[4 * o], BOX_ROWS[4 * o + 1], BOX_ROWS[4 * o + 2], BOX_ROWS[4 * o + 3]);
#endif
#if HAS_PLANES
    for (int f = 0; f < plane_count; ++f)
        x_new = collide_plane(x_new, PLANE_ROWS[2 * f], PLANE_ROWS[2 * f + 1]);
#endif
#if HAS_MESHES
    for (int m = 0; m < mesh_count; ++m)
        x_new = collide_mesh(x_new, mesh_rows, mesh_ints, m, MESH_POSE(m));
#endif
    return x_new;
}

// Steps 1-6 of docs/semantics.md for the particle at (row, col), at x(t) = x with x(t - dt) =
// xp and inverse mass w, its neighbours' x(t) read through pos: x(t + dt).
template <class Positions>
__device__ __forceinline__ float3 verlet_particle(Positions pos, int row, int col, float3 x,
                                                  float3 xp, float w SCENE_PARAMS MESH_PARAMS STEP_ROWS_PARAMS)
{
    // steps 1-3: the lagged velocity, its damping term
    const float3 vel = make_float3((x.x - xp.x) / dt, (x.y - xp.y) / dt, (x.z - xp.z) / dt);
    const float3 bv = make_float3(b * vel.x, b * vel.y, b * vel.z);

    // step 4: springs only; gravity is an acceleration and joins in step 6 (differs)
    float3 force = make_float3(0.0f, 0.0f, 0.0f);

    // step 5: the 12-spring stencil in summation order (differs: row and column offsets
    // are not mixed as in the listing); a neighbour outside the grid adds nothing
    const Offset stencil[12] = STENCIL;
    const float rest[3] = {rest_structural, rest_shear, rest_bend};
#pragma unroll
    for (int o = 0; o < 12; ++o) {
        const int r = row + stencil[o].dr;
        const int c = col + stencil[o].dc;
        if (!inside_grid(r, c, n)) continue;
        const float3 pj = pos(r * n + c);
        const float3 d = make_float3(pj.x - x.x, pj.y - x.y, pj.z - x.z);
        const float s = spring_scale(dot3(d, d), rest[o / 4], k);
        // damping -b*vel once per existing spring, as in the listing
        force.x += s * d.x - bv.x;
        force.y += s * d.y - bv.y;
        force.z += s * d.z - bv.z;
    }

    // step 6: position Verlet, then collisions; pinned particles (w = 0) do not move, or
    // follow their body: the step's pin target
#if HAS_PIN_TARGETS
    if (w == 0.0f) {
        const int slot = pin_slot[row * n + col];
        if (slot < 0) return x;
        const float4 target = PIN_TARGETS[slot];
        return make_float3(target.x, target.y, target.z);
    }
#else
    if (w == 0.0f) return x;
#endif
    const float3 acc = make_float3(force.x * w + gx, force.y * w + gy, force.z * w + gz);
    float3 x_new = make_float3((2.0f * x.x - xp.x) + acc.x * dt2,
                               (2.0f * x.y - xp.y) + acc.y * dt2,
                               (2.0f * x.z - xp.z) + acc.z * dt2);
    // with [self_collision] they act after the pass instead (self_collision.cuh)
    return COLLIDE_IN_STEP ? apply_colliders(x_new COLLIDE_ARGS MESH_ARGS ROWS_ARG) : x_new;
}

extern "C" __global__ void verlet_step(
    const float4* __restrict__ pos,       // x(t); w = inverse mass, 0 = pinned
    const float4* __restrict__ pos_prev,  // x(t - dt)
    float4* __restrict__ pos_out,         // x(t + dt)
    float4* __restrict__ pos_prev_out     // x(t), the next step's previous position
#ifdef CLOTH_NORMALS
    , float4* __restrict__ normal_out     // the normal of x(t), w = 0 (docs/normals.md)
#endif
    SCENE_PARAMS MESH_PARAMS MOTION_PARAMS)
{
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * n) return;
    const int row = i / n;
    const int col = i % n;
    const float4 p = pos[i];
    const float4 q = pos_prev[i];
    const float3 x = make_float3(p.x, p.y, p.z);
    const float3 x_new = verlet_particle(GlobalPositions{pos}, row, col, x, make_float3(q.x, q.y, q.z),
                                         p.w SCENE_ARGS MESH_ARGS STEP_ROWS_ARGS(0));
    // steps 7-8: the new position, and the current one as the next step's previous
    pos_out[i] = make_float4(x_new.x, x_new.y, x_new.z, p.w);
    pos_prev_out[i] = p;
#ifdef CLOTH_NORMALS
    const float3 normal = normal_at(GlobalPositions{pos}, row, col, n, x);  // for rendering only
    normal_out[i] = make_float4(normal.x, normal.y, normal.z, 0.0f);
#endif
}

// verlet_steps: the block's shared memory, sized by the host (launch.py: multistep_shared_bytes):
// x(t) and x(t - dt) of every particle, one float array per component: 6 n*n floats, 24 bytes
// a particle, so that a 64 x 64 grid (96 KiB) fits every sm_80+ device (99 KiB or more).
extern __shared__ float cloth_shared[];

// The most threads verlet_steps runs in its one block (the host never asks for more); at 1024
// the compiler must fit a thread in 64 registers.
#define MULTISTEP_MAX_THREADS 1024

// `steps` steps of the whole grid in one block of any size (each thread takes particles
// threadIdx.x, + blockDim.x, ...: the same particles every step). The state lives in shared
// memory between steps: `cur` holds x(t) and `old` x(t - dt); a step overwrites each particle's
// own x(t - dt) slot with its x(t + dt) (only that particle's thread reads that slot), then
// __syncthreads() and the two swap roles. In and out as verlet_step after `steps` of them:
// (pos_out, pos_prev_out) = (x(t + steps dt), x(t + (steps - 1) dt)), the normals those of
// the latter. Launch with one block, steps >= 1, and 6 n*n floats of dynamic shared memory.
extern "C" __global__ void __launch_bounds__(MULTISTEP_MAX_THREADS) verlet_steps(
    const float4* __restrict__ pos,       // x(t); w = inverse mass, 0 = pinned
    const float4* __restrict__ pos_prev,  // x(t - dt)
    float4* __restrict__ pos_out,         // x(t + steps dt)
    float4* __restrict__ pos_prev_out     // x(t + (steps - 1) dt)
#ifdef CLOTH_NORMALS
    , float4* __restrict__ normal_out     // the normal of pos_prev_out, w = 0
#endif
    , int steps                           // steps in this launch, >= 1
    SCENE_PARAMS MESH_PARAMS MOTION_PARAMS)  // motion: the rows of `steps` steps
{
    const int count = n * n;
    float* cur_x = cloth_shared;
    float* cur_y = cur_x + count;
    float* cur_z = cur_y + count;
    float* old_x = cur_z + count;
    float* old_y = old_x + count;
    float* old_z = old_y + count;
    for (int i = threadIdx.x; i < count; i += blockDim.x) {
        const float4 p = pos[i], q = pos_prev[i];
        cur_x[i] = p.x, cur_y[i] = p.y, cur_z[i] = p.z;
        old_x[i] = q.x, old_y[i] = q.y, old_z[i] = q.z;
    }
    __syncthreads();
    for (int s = 0; s < steps; ++s) {
        const SharedPositions now{cur_x, cur_y, cur_z};
        for (int i = threadIdx.x; i < count; i += blockDim.x) {
            const float3 x_new = verlet_particle(now, i / n, i % n, now(i),
                                                 make_float3(old_x[i], old_y[i], old_z[i]),
                                                 pos[i].w SCENE_ARGS MESH_ARGS STEP_ROWS_ARGS(s));
            old_x[i] = x_new.x, old_y[i] = x_new.y, old_z[i] = x_new.z;  // was x(t - dt)
        }
        __syncthreads();  // every x(t + dt) written before any is read as a neighbour
        float* t;
        t = cur_x, cur_x = old_x, old_x = t;
        t = cur_y, cur_y = old_y, old_y = t;
        t = cur_z, cur_z = old_z, old_z = t;
    }
    for (int i = threadIdx.x; i < count; i += blockDim.x) {
        const float w = pos[i].w;
        pos_out[i] = make_float4(cur_x[i], cur_y[i], cur_z[i], w);
        pos_prev_out[i] = make_float4(old_x[i], old_y[i], old_z[i], w);
#ifdef CLOTH_NORMALS
        const SharedPositions last{old_x, old_y, old_z};  // what the last step read
        const float3 normal = normal_at(last, i / n, i % n, n, last(i));
        normal_out[i] = make_float4(normal.x, normal.y, normal.z, 0.0f);
#endif
    }
}

#ifdef CLOTH_SELF_COLLISION
#include "self_collision.cuh"
#endif
