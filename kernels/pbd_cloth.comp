// pbd_cloth.comp: the Position Based Dynamics (XPBD) cloth solver as GL 4.3 compute shaders,
// one program per stage (STAGE below), as in the compute-shader PBD cloth this mirrors. The
// solver and the order of every operation are docs/pbd.md; the colliders docs/semantics.md
// (the shared kernels/collide_*.glsl). Host: clothbench/backends/gl/compute_pbd.py.
//
// State: std430 arrays of vec4 (w = inverse mass, 0 = pinned): x = x(t), v (w unused), and
// two predicted-position buffers xs that the Jacobi passes ping-pong. The host dispatches,
// per substep, with a memory barrier after every dispatch (the next one reads its writes):
//   STAGE_PREDICT   x, v -> v, xs
//   STAGE_JACOBI    X -> Y, per iteration one dispatch for the interior and one for the
//                   border (PART); the host then swaps X and Y; or
//   STAGE_COLOURED  one dispatch per batch of constraints sharing no particle, 12 per iteration,
//   or STAGE_COLOURED_SWEEP: the 12 batches in one dispatch of one work-group (barriers)
//   STAGE_COLLIDE   xs in place (only when the scene has colliders or meshes); or, with
//   STAGE_SELF_COLLISION  ([self_collision] only, after the host's keys and sort,
//                   kernels/self_collision.comp) X -> Y: pushed apart, then collided
//   STAGE_UPDATE    x, xs -> v, x
//
// The host prepends #version 430 and:
//   LOCAL_SIZE   work-group size
//   PART         the Jacobi dispatch's particles (PART_* below): the interior, 2 or more from
//                every edge (no bounds tests), the border, or all (n < 5)
//   IMAGE_READS  the constraint passes read positions through an imageBuffer view of their
//                buffer (vector gathers on llvmpipe, where an SSBO load goes lane by lane)
//   STRICT       bit-exact with the numpy float32 reference: the documented operation order,
//                every temporary `precise`, no dot/length/normalize. Without it (fast): dot()
//                and one inversesqrt per constraint.
//   CHEBYSHEV    the Jacobi stage extrapolates its iterate and multipliers from the ones
//                before (docs/pbd.md, "Chebyshev"); the weight is the uniform omega
//   N_VALUE, H_VALUE, GH_VALUE, AT_VALUE, REST_VALUE, DAMP_VALUE, RELAX_VALUE and the
//                collider constants: exact float32 literals, rounded once from float64.
//   MESH_*, MOTION, PIN_ATTACH  meshes (kernels/collide_mesh.glsl, in collide after the planes),
//                moving colliders and pins attached to a body, as the Verlet kernels take them
//                (gl/context.py body_defines, GLBodies): with MOTION the collider rows and pin
//                targets are one block per substep, at its end (docs/pbd.md); attached pins
//                take their target in the predict stage.
// lambda: 12 per particle in the Jacobi form (lam[o * n2 + i]: each end of a constraint keeps
// its own copy, taking the share relax / cnt of its dlam that its position takes), one per
// constraint in the coloured form. The first pass of a substep (uniform iteration = 0 in the
// Jacobi stage, first_pass in the coloured) reads lambda as 0 instead of clearing it.

#ifdef STRICT
#define P precise
#else
#define P
#endif

#define STAGE_PREDICT 0
#define STAGE_JACOBI 1
#define STAGE_COLOURED 2
#define STAGE_COLLIDE 3
#define STAGE_UPDATE 4
#define STAGE_COLOURED_SWEEP 5
#define STAGE_SELF_COLLISION 6
#define PART_ALL 0  // which particles a Jacobi dispatch covers: every one, with bounds tests,
#define PART_INTERIOR 1  // the (n - 4)^2 with all 12 neighbours, without,
#define PART_BORDER 2  // or the 8n - 16 others, with

layout(local_size_x = LOCAL_SIZE) in;

const int n = N_VALUE;
const int n2 = N_VALUE * N_VALUE;
const float h = H_VALUE;                // dt / substeps
const vec3 gh = GH_VALUE;               // g * h
const float at[3] = AT_VALUE;           // compliance / h^2: structural, shear, bend
const float rest[3] = REST_VALUE;       // rest lengths: structural, shear, bend
const float damp = DAMP_VALUE;          // 1 - 12 b h / m
const float relax = RELAX_VALUE;        // Jacobi over-relaxation

// (a.x*b.x + a.y*b.y) + a.z*b.z in strict mode; dot() is the driver's order
float dot3(vec3 a, vec3 c)
{
#ifdef STRICT
    P float s = (a.x * c.x + a.y * c.y) + a.z * c.z;
    return s;
#else
    return dot(a, c);
#endif
}

// this invocation's item (particle or constraint); the host spreads large dispatches over y
int item()
{
    return int(gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * LOCAL_SIZE
           + int(gl_LocalInvocationID.x);
}

#ifdef MOTION
// A scene that moves: this substep's collider rows, mesh poses and attached-pin targets,
// MOTION_STRIDE vec4s per substep at the offsets of gl/context.py motion_offsets (the Verlet
// kernels' layout), uploaded by the host in blocks before the dispatches that read them.
layout(std430, binding = 6) readonly buffer MotionRows { vec4 motion_rows[]; };
uniform int motion_step;  // this substep's place in the uploaded block
#define MOTION_ROW(j) motion_rows[motion_step * MOTION_STRIDE + (j)]
#endif

#if STAGE == STAGE_PREDICT
layout(std430, binding = 0) readonly buffer Pos { vec4 x[]; };
layout(std430, binding = 1) buffer Vel { vec4 v[]; };
layout(std430, binding = 2) writeonly buffer Pred { vec4 xs[]; };

#ifdef PIN_ATTACH
// pins that follow a body: per particle its row among the pin targets, or -1
layout(std430, binding = 10) readonly buffer PinSlots { int pin_slot[]; };
#endif

// v += g*h, xs = x + v*h; pinned particles stay and have no velocity, but a pin following a
// body goes to its target at the end of the substep
void main()
{
    int i = item();
    if (i >= n2)
        return;
    vec4 p = x[i];
    if (p.w == 0.0) {
        v[i] = vec4(0.0);
#ifdef PIN_ATTACH
        int slot = pin_slot[i];
        if (slot >= 0)
            p = vec4(MOTION_ROW(MOTION_PINS + slot).xyz, p.w);
#endif
        xs[i] = p;
        return;
    }
    P vec3 vel = v[i].xyz + gh;
    P vec3 pred = p.xyz + vel * h;
    v[i] = vec4(vel, 0.0);
    xs[i] = vec4(pred, p.w);
}

#elif STAGE == STAGE_JACOBI
// previous iterate: an imageBuffer view of the buffer (IMAGE_READS) or the SSBO itself
#ifdef IMAGE_READS
layout(rgba32f, binding = 0) readonly uniform imageBuffer X;
#define LOAD_X(i) imageLoad(X, i)
#else
layout(std430, binding = 0) readonly buffer From { vec4 X[]; };
#define LOAD_X(i) X[i]
#endif
#ifdef CHEBYSHEV
// Y holds the iterate before X until this pass writes the next one; lam_out likewise the
// lambdas before lam (docs/pbd.md, "Chebyshev")
layout(std430, binding = 1) buffer To { vec4 Y[]; };
layout(std430, binding = 2) readonly buffer Lambda { float lam[]; };
layout(std430, binding = 3) buffer LambdaOut { float lam_out[]; };
uniform float omega;  // this pass's Chebyshev weight
#else
layout(std430, binding = 1) writeonly buffer To { vec4 Y[]; };   // next iterate
layout(std430, binding = 2) buffer Lambda { float lam[]; };
#define lam_out lam
#endif
uniform int iteration;  // the pass's index in its substep

// the 12-spring stencil (d_row, d_col) in the order docs/semantics.md fixes
const ivec2 OFFSETS[12] = ivec2[12](
    ivec2(0, -1), ivec2(0, 1), ivec2(-1, 0), ivec2(1, 0),     // structural
    ivec2(-1, -1), ivec2(-1, 1), ivec2(1, -1), ivec2(1, 1),   // shear
    ivec2(-2, -2), ivec2(-2, 2), ivec2(2, -2), ivec2(2, 2));  // bend

// (row, col) of this invocation's particle, or (-1, -1) past the end of the part
ivec2 particle()
{
    int t = item();
#if PART == PART_INTERIOR
    int m = n - 4;  // the (n - 4)^2 block from (2, 2)
    return t < m * m ? ivec2(2 + t / m, 2 + t % m) : ivec2(-1);
#elif PART == PART_BORDER
    // rows 0, 1, n-2, n-1 in full (4n particles), then columns 0, 1, n-2, n-1 of rows 2..n-3
    if (t < 4 * n) {
        int r = t / n;
        return ivec2(r < 2 ? r : n - 4 + r, t % n);
    }
    t -= 4 * n;
    if (t >= 4 * (n - 4))
        return ivec2(-1);
    int c = t % 4;
    return ivec2(2 + t / 4, c < 2 ? c : n - 4 + c);
#else
    return t < n2 ? ivec2(t / n, t % n) : ivec2(-1);
#endif
}

// particle i gathers the corrections of its constraints from X, averaged and over-relaxed;
// PART_INTERIOR: all 12 neighbours exist, no bounds tests (the same operations, so strict
// stays exact)
void main()
{
    ivec2 rc = particle();
    if (rc.x < 0)
        return;
    int i = rc.x * n + rc.y;
    vec4 xi = LOAD_X(i);
    float w = xi.w;
    P vec3 corr = vec3(0.0);
    int cnt = 0;  // constraints inside the grid
    for (int o = 0; o < 12; ++o) {
        ivec2 rj = rc + OFFSETS[o];
        cnt += all(greaterThanEqual(rj, ivec2(0))) && all(lessThan(rj, ivec2(n))) ? 1 : 0;
    }
    P float scale = relax / float(cnt);  // the share of each correction, and of its dlam
    for (int o = 0; o < 12; ++o) {
        ivec2 rj = rc + OFFSETS[o];
#if PART != PART_INTERIOR
        if (any(lessThan(rj, ivec2(0))) || any(greaterThanEqual(rj, ivec2(n))))
            continue;  // outside the grid: nothing added
#endif
        int kind = o >> 2;
        vec4 xj = LOAD_X(rj.x * n + rj.y);
        P vec3 d = xi.xyz - xj.xyz;
        P float L2 = dot3(d, d);
        P float denom = (w + xj.w) + at[kind];
        float lam_o = iteration == 0 ? 0.0 : lam[o * n2 + i];
        P float dlam = 0.0;
        if (L2 > 0.0 && denom > 0.0) {  // coincident, or both pinned and rigid: no change
#ifdef STRICT
            P float L = sqrt(L2);
            dlam = ((-(L - rest[kind])) - at[kind] * lam_o) / denom;
            P float s = (w * dlam) / L;
#else
            float inv_L = inversesqrt(L2);
            dlam = (rest[kind] - L2 * inv_L - at[kind] * lam_o) / denom;
            float s = w * dlam * inv_L;
#endif
            corr = corr + d * s;
        }
        P float lam_new = lam_o + dlam * scale;
#ifdef CHEBYSHEV
        if (iteration > 0) {
            float before = iteration == 1 ? 0.0 : lam_out[o * n2 + i];
            P float e = omega * (lam_new - before) + before;
            lam_new = e;
        }
#endif
        lam_out[o * n2 + i] = lam_new;
    }
    P vec3 y = xi.xyz + corr * scale;
#ifdef CHEBYSHEV
    if (iteration > 0) {
        vec3 before = Y[i].xyz;
        P vec3 e = omega * (y - before) + before;
        y = e;
    }
#endif
    Y[i] = vec4(y, w);
}

#elif STAGE == STAGE_COLOURED || STAGE == STAGE_COLOURED_SWEEP
// updated in place; with IMAGE_READS read through an imageBuffer view of the same buffer (an
// invocation reads only the two particles it writes, and no other invocation touches them).
// The sweep reads the SSBO itself, coherent: a batch reads what the batch before it wrote.
#ifdef IMAGE_READS
layout(rgba32f, binding = 0) readonly uniform imageBuffer X_in;
#define LOAD_X(i) imageLoad(X_in, i)
#else
#define LOAD_X(i) X[i]
#endif
#if STAGE == STAGE_COLOURED_SWEEP
#define COHERENT coherent
#else
#define COHERENT
#endif
layout(std430, binding = 0) COHERENT buffer State { vec4 X[]; };
layout(std430, binding = 1) readonly buffer Pairs { ivec2 ij[]; };  // every batch's (i, j)
layout(std430, binding = 2) buffer Lambda { float lam[]; };       // one per constraint
uniform int first_pass;

// constraint c (of a batch of `kind`) moves both its ends; no two constraints of a batch
// share one
void project(int c, int kind, bool first)
{
    ivec2 e = ij[c];
    vec4 xi = LOAD_X(e.x);
    vec4 xj = LOAD_X(e.y);
    float at_c = at[kind];
    P vec3 d = xi.xyz - xj.xyz;
    P float L2 = dot3(d, d);
    P float denom = (xi.w + xj.w) + at_c;
    float lam_c = first ? 0.0 : lam[c];
    P float dlam = 0.0;
    if (L2 > 0.0 && denom > 0.0) {
#ifdef STRICT
        P float L = sqrt(L2);
        dlam = ((-(L - rest[kind])) - at_c * lam_c) / denom;
        P vec3 yi = xi.xyz + d * ((xi.w * dlam) / L);
        P vec3 yj = xj.xyz - d * ((xj.w * dlam) / L);
#else
        float inv_L = inversesqrt(L2);
        dlam = (rest[kind] - L2 * inv_L - at_c * lam_c) / denom;
        float s = dlam * inv_L;
        vec3 yi = xi.xyz + d * (xi.w * s);
        vec3 yj = xj.xyz - d * (xj.w * s);
#endif
        X[e.x] = vec4(yi, xi.w);
        X[e.y] = vec4(yj, xj.w);
    }
    P float lam_new = lam_c + dlam;
    lam[c] = lam_new;
}

#if STAGE == STAGE_COLOURED
uniform int batch_offset, batch_count, batch_kind;

// one batch: constraint k of it per invocation
void main()
{
    int k = item();
    if (k >= batch_count)
        return;
    project(batch_offset + k, batch_kind, first_pass != 0);
}
#else
const int batch_start[13] = BATCH_OFFSETS_VALUE;  // where each batch starts, and the end

// all 12 batches of one iteration in one dispatch of one work-group, a barrier between
// batches (valid within a work-group): the invocations stride over each batch
void main()
{
    int first_item = int(gl_LocalInvocationID.x);
    for (int b = 0; b < 12; ++b) {  // batches 0-3 structural, 4-7 shear, 8-11 bend
        for (int c = batch_start[b] + first_item; c < batch_start[b + 1]; c += LOCAL_SIZE)
            project(c, b >> 2, first_pass != 0);
        memoryBarrierBuffer();
        barrier();
    }
}
#endif

#elif STAGE == STAGE_COLLIDE || STAGE == STAGE_SELF_COLLISION
#if STAGE == STAGE_COLLIDE
layout(std430, binding = 0) buffer Pred { vec4 xs[]; };
#else
// the last iterate, read by every particle's pass (kernels/self_collision.glsl), and the pushed
layout(std430, binding = 0) readonly buffer From { vec4 X[]; };
layout(std430, binding = 1) writeonly buffer To { vec4 Y[]; };
#define SELF_X(j) X[j]
#include <self_collision>  // kernels/self_collision.glsl, where the scene has the table
#endif

// `vec3 collide(vec3 x)`: the scene's colliders in the fixed order (spheres, cylinders,
// boxes, planes, meshes), from kernels/collide_KIND.glsl and collide_mesh.glsl (the host puts
// them here; with MOTION they read this substep's rows)
#include <colliders>

#if STAGE == STAGE_COLLIDE
// collisions as position projections, free particles only
void main()
{
    int i = item();
    if (i >= n2)
        return;
    vec4 p = xs[i];
    if (p.w == 0.0)
        return;  // pinned particles are never collided
    xs[i] = vec4(collide(p.xyz), p.w);
}
#else
// the pass (docs/semantics.md, "Self-collision"), then the colliders, free particles only
void main()
{
    int i = item();
    if (i >= n2)
        return;
    float w = X[i].w;
    vec3 x = self_push(i, n);
    if (w != 0.0)
        x = collide(x);
    Y[i] = vec4(x, w);
}
#endif

#elif STAGE == STAGE_UPDATE
layout(std430, binding = 0) buffer Pos { vec4 x[]; };
layout(std430, binding = 1) writeonly buffer Vel { vec4 v[]; };
layout(std430, binding = 2) readonly buffer Pred { vec4 xs[]; };

// v = (xs - x) / h, damped; x = xs
void main()
{
    int i = item();
    if (i >= n2)
        return;
    vec4 p = xs[i];
    P vec3 vel = (p.xyz - x[i].xyz) / h;
    P vec3 damped = vel * damp;
    v[i] = vec4(damped, 0.0);
    x[i] = p;
}
#endif
