/*
 * What both CUDA cloth kernels, kernels/verlet_cloth.cu and kernels/vbd_cloth.cu, take from the
 * scene: its colliders (the spheres, cylinders, boxes and planes of docs/semantics.md, then the
 * meshes of collide_mesh.cuh) and the collision response, one code for both solvers
 * (docs/vbd.md: VBD collides with the Verlet step's projections), and the grid's helpers
 * (Offset, STENCIL, inside_grid, minus, dot3).
 *
 * The including kernel defines the grid side `n` first (a constant, or in verlet_cloth.cu's
 * generic build a parameter). Switches, as verlet_cloth.cu's header describes them:
 * CLOTH_GENERIC (every collider kind, their counts and rows as kernel parameters), otherwise
 * the collider counts and rows as -D values (clothbench.backends.cuda.verlet.scene_defines);
 * CLOTH_MESH_COUNT / CLOTH_MESHES and CLOTH_MESH_BVH; CLOTH_MOTION (every collider's rows, each
 * mesh's pose and the attached pins' targets from the step's rows, `step_rows`).
 * A kind the scene lacks compiles no code.
 */

// A neighbour's offset in the grid: (row, column), as docs/semantics.md writes it.
struct Offset {
    int dr, dc;
};

// The 12-spring stencil in summation order (scene.OFFSETS): the springs of step 5 and of VBD's
// Newton step, and the pairs the self-collision pass leaves out.
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
#else
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

#if HAS_MESHES
#include "collide_mesh.cuh"
#endif

// The colliders of the generic build: kernel parameters (a moving scene: only their counts).
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

// Pins attached to a body: each particle's row among the step's pin targets (-1: not attached).
#if HAS_PIN_TARGETS
#define PIN_PARAMS , const int* __restrict__ pin_slot
#define PIN_ARGS , pin_slot
#else
#define PIN_PARAMS
#define PIN_ARGS
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

// The colliders' part of step 6: every collider in the fixed order, all spheres, cylinders,
// boxes, planes, then meshes (at the step's rows where they move).
__device__ __forceinline__ float3 apply_colliders(float3 x_new COLLIDE_PARAMS MESH_PARAMS ROWS_PARAM)
{
#ifdef CLOTH_MOTION
    (void)step_rows;  // a scene whose only motion is its attached pins reads no collider rows
#endif
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
