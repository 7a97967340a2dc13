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
 * file performs those operations in that order and does not restate them; the colliders and
 * their response are collide.cuh's, which vbd_cloth.cu includes too. The launch is in
 * Python (clothbench/backends/cuda/launch.py: PingPong), which owns the state buffers: by
 * default two, x(t) and x(t - dt), a launch writing its last x(t + dt) over x(t - dt) in place
 * and the host swapping the two's roles (48 bytes a particle a step); with CLOTH_TWO_PAIRS the
 * chapter's two pairs (pos, pos_prev) x (in, out), the host copying out to in after each launch.
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
 *   CLOTH_TWO_PAIRS  (`--transfer copy`) the chapter's buffers: both kernels read (pos,
 *                  pos_prev) and write (pos_out, pos_prev_out), step 8 a store of x(t).
 *                  Without it (`--transfer swap`, the default) they take (pos, pos_prev) and
 *                  write the new state over them: x(t + dt) over x(t - dt) (only the particle's
 *                  own thread reads that slot; the neighbours are read from pos), and step 8 is
 *                  the host's swap of the two buffers.
 */

#ifdef CLOTH_TWO_PAIRS
#define STATE_PARAMS(pos_const)                                                  \
    const float4* __restrict__ pos,       /* x(t); w = inverse mass, 0 = pinned */ \
    const float4* __restrict__ pos_prev,  /* x(t - dt) */                          \
    float4* __restrict__ pos_out,         /* the latest state after the launch */  \
    float4* __restrict__ pos_prev_out     /* the state before it */
#define LATEST_OUT pos_out
#define PREVIOUS_OUT pos_prev_out
#else
#define STATE_PARAMS(pos_const)                                                  \
    pos_const float4* __restrict__ pos,   /* x(t); w = inverse mass, 0 = pinned */ \
    float4* __restrict__ pos_prev         /* x(t - dt), then the latest state */
#define LATEST_OUT pos_prev
#define PREVIOUS_OUT pos
#endif

#ifndef CLOTH_GENERIC
#ifndef CLOTH_N
#error "build with -DCLOTH_GENERIC, or with the scene's -D values (clothbench.backends.cuda.verlet.kernel_defines)"
#endif
// the scene, baked in: the compiler folds these into the code (n * n, i / n, k * ..., ...)
constexpr int n = CLOTH_N;
constexpr float dt = CLOTH_DT, dt2 = CLOTH_DT2;
constexpr float k = CLOTH_K, b = CLOTH_B;
constexpr float gx = CLOTH_GX, gy = CLOTH_GY, gz = CLOTH_GZ;
constexpr float rest_structural = CLOTH_REST_STRUCTURAL, rest_shear = CLOTH_REST_SHEAR,
                rest_bend = CLOTH_REST_BEND;
#endif

// the grid, the colliders, their rows and the collision response, shared with vbd_cloth.cu
#include "collide.cuh"

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

// Motion: a launch takes the table of its steps (`motion`, motion_rows rows a step) and, with
// attached pins, pin_slot (collide.cuh); a step reads its own rows (`step_rows`). Generic:
// motion_rows is an argument.
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

// The step collides its particles, unless the self-collision pass does it after pushing them.
#ifdef CLOTH_SELF_COLLISION
#define COLLIDE_IN_STEP false
#else
#define COLLIDE_IN_STEP true
#endif

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

// In place (the default): x(t + dt) over pos_prev[i], which the host then reads as x(t).
extern "C" __global__ void verlet_step(
    STATE_PARAMS(const)
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
    // step 7: the new position; step 8: x(t) as the next step's previous (in place: the swap)
    LATEST_OUT[i] = make_float4(x_new.x, x_new.y, x_new.z, p.w);
#ifdef CLOTH_TWO_PAIRS
    pos_prev_out[i] = p;
#endif
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
// x(t + steps dt) in LATEST_OUT (pos_out, or in place pos_prev) and x(t + (steps - 1) dt) in
// PREVIOUS_OUT (pos_prev_out, or pos), the normals those of the latter; in place, a thread
// reads and writes only its own particles' slots of pos and pos_prev. Launch with one block,
// steps >= 1, and 6 n*n floats of dynamic shared memory.
extern "C" __global__ void __launch_bounds__(MULTISTEP_MAX_THREADS) verlet_steps(
    STATE_PARAMS()
#ifdef CLOTH_NORMALS
    , float4* __restrict__ normal_out     // the normal of PREVIOUS_OUT, w = 0
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
        LATEST_OUT[i] = make_float4(cur_x[i], cur_y[i], cur_z[i], w);
        PREVIOUS_OUT[i] = make_float4(old_x[i], old_y[i], old_z[i], w);
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
