/* pbd_cloth.cl: the Position Based Dynamics (XPBD) cloth solver in OpenCL C: one kernel per
 * stage, and pbd_substeps, whole substeps in one launch. The solver and the order of every
 * operation are docs/pbd.md; the colliders are docs/semantics.md. Host code:
 * clothbench/backends/opencl/pbd.py.
 *
 * State (float4 per particle, w = inverse mass, 0 = pinned): x (positions x(t)), v (velocity,
 * w unused), and two predicted-position buffers that the Jacobi passes ping-pong.
 * The `per-stage` shape enqueues, per substep, on an in-order queue (each launch sees the
 * one before):
 *   pbd_predict                    x, v -> v, xs
 *   pbd_jacobi_interior + pbd_jacobi_border, x iterations: X -> Y (the host then swaps
 *                                  X and Y; see "Jacobi" below), or
 *   pbd_coloured x 12 x iterations one launch per batch of constraints sharing no particle
 *   pbd_collide                    xs, in place (only when the scene has colliders or meshes)
 *   pbd_update                     x, xs -> v, x
 * The `one-launch` shape runs the same functions in the same order in pbd_substeps, one
 * work-group, barriers between the stages (see there); the `bands-R` shapes run predict and
 * the Jacobi passes in pbd_jacobi_bands, a work-group per band of R rows (see there), then
 * collide and update; `one-launch-vectors` runs whole coloured substeps in
 * pbd_coloured_vectors, its batches in vectors (see there).
 *
 * Build options:
 *   CLOTH_N                                      grid side n (index arithmetic folds)
 *   CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_BOXES, CLOTH_PLANES collider counts (0 when absent)
 *   CLOTH_VECTOR_WIDTH                           particles per work item of the Jacobi
 *                                                interior: 4, 8 or 16
 *   CLOTH_COLOURED   pbd_substeps runs the coloured method (else Jacobi)
 *   CLOTH_CHEBYSHEV  Jacobi with Chebyshev acceleration (docs/pbd.md): each pass extrapolates
 *                    its iterate and multipliers from the ones before
 *   CLOTH_MESHES, CLOTH_MESH_BVH, CLOTH_PER_STEP, CLOTH_ATTACHED_PINS, CLOTH_PINS
 *                    meshes, moving colliders and pins attached to a body, as in
 *                    verlet_cloth.cl (the host code is opencl/bodies.py, shared with it):
 *                    the meshes are kernels/collide_mesh.cl, after the planes in collide;
 *                    with CLOTH_PER_STEP the collider table (and the pin targets) is one per
 *                    substep, a launch told the index `step` of its (first) substep; the
 *                    attached pins take their target in predict (docs/pbd.md).
 *   CLOTH_PLANAR  the program of the bands and vector-sweep shapes (pbd_jacobi_bands,
 *                 pbd_coloured_vectors): the iterates are planar scratch grids (grid_t, below)
 *   CLOTH_STRICT  every operation in the order docs/pbd.md fixes, no contraction, sqrt and
 *                 '/', no dot(): equal to the NumPy float32 reference bit for bit. Without
 *                 it (fast): one rsqrt per constraint, dot(), contraction (-cl-mad-enable);
 *                 the interior vectors take fast_math.cl's estimates for 1/sqrt and 1/denom.
 * Numbers (h, g*h, compliance/h^2, rest lengths, damping, relaxation, Chebyshev weights) are
 * kernel arguments, rounded once to float32 on the host. The collider table and the colliders
 * are collide.cl's (included by the host, as verlet_cloth.cl includes it): spheres (centre,
 * radius); cylinders (start, length), (unit axis, radius), (radial_r, 0); boxes (centre, 0),
 * (axis i, half extent i); planes (point, 0), (unit normal, 0).
 *
 * lambda: the Jacobi form keeps 12 per particle (lam[o * n2 + i], one for each end of a
 * constraint; each takes the share relax / cnt of its dlam that its position takes), the
 * coloured form one per constraint. A Jacobi pass reads `lam` and writes `lam_out`: the same
 * buffer, or with Chebyshev two that ping-pong. A pass told its iteration `it` (or `first`,
 * the first pass of a substep) reads lambda as 0 on the first pass instead of clearing it. */

#ifdef CLOTH_STRICT
/* PoCL fuses a*b+c into an FMA unless told not to; strict rounds every operation. */
#pragma OPENCL FP_CONTRACT OFF
#endif

#ifndef CLOTH_N
#error "build with -DCLOTH_N=<grid side>"
#endif
#include "collider_counts.cl"
#define N CLOTH_N
#define N2 (CLOTH_N * CLOTH_N)
/* the stride of a grid's planes and of the multipliers' planes: N2 in the float4 program; in
 * the planar one padded by CLOTH_PLANE_PAD floats, so that the 12 multipliers and 4 coordinates of
 * one particle do not all fall in one cache set when n * n * 4 bytes is a multiple of 4 KiB */
#ifdef CLOTH_PLANAR
#define PLANE (N2 + CLOTH_PLANE_PAD)
#else
#define PLANE N2
#endif
/* Every helper is inlined, and vector loads, stores and select() are plain C, for the reasons
 * verlet_cloth.cl gives: PoCL leaves bigger helpers as calls that pass the vectors through
 * memory, and the PoCL wheel calls vloadn, vstoren and select() out of line. */
#define INLINE __attribute__((always_inline))
#define SELECT(a, b, c) ((c) ? (b) : (a))

/* The extra arguments of a scene with meshes, motion or attached pins: STEP_ARG, MESH_ARG,
 * PIN_ARG in a kernel's parameters, *_PASS through the helpers. */
#include "body_args.cl"
#define TABLE_ROWS (ANALYTIC_ROWS + MESH_ROWS * CLOTH_MESHES) /* a substep's collider table */

/* The 12-spring stencil (d_row, d_col) in the order docs/semantics.md fixes; offsets 0-3 are
 * structural, 4-7 shear, 8-11 bend (the .x, .y, .z of `rest` and `at`). */
__constant int2 OFFSETS[12] = {
    (int2)(0, -1), (int2)(0, 1), (int2)(-1, 0), (int2)(1, 0),
    (int2)(-1, -1), (int2)(-1, 1), (int2)(1, -1), (int2)(1, 1),
    (int2)(-2, -2), (int2)(-2, 2), (int2)(2, -2), (int2)(2, 2),
};

/* (a.x*b.x + a.y*b.y) + a.z*b.z in strict mode; dot() sums in the driver's order */
INLINE float dot3(float3 a, float3 b)
{
#ifdef CLOTH_STRICT
    return (a.x * b.x + a.y * b.y) + a.z * b.z;
#else
    return dot(a, b);
#endif
}

/* The colliders (docs/semantics.md, "Collisions") and collide(x, colliders, counts...),
 * shared with verlet_cloth.cl. */
#include "collide.cl"

/* predict: v += g*h, xs = x + v*h (returned; vel: the new v); pinned particles stay and have
 * no velocity, but a pin following a body goes to its target at the end of the substep
 * (pin_target: this substep's CLOTH_PINS float3s) */
INLINE float4 predict_position(int i, __global const float4 *x, __global const float4 *v, float h,
                        float4 gh, float3 *vel PIN_ARG)
{
    float4 p = x[i];
    if (p.w == 0.0f) {
        *vel = (float3)(0.0f);
#ifdef CLOTH_ATTACHED_PINS
        int slot = pin_slot[i];
        if (slot >= 0)
            p = (float4)(pin_target[3 * slot], pin_target[3 * slot + 1], pin_target[3 * slot + 2], p.w);
#endif
        return p;
    }
    *vel = v[i].xyz + gh.xyz;
    return (float4)(p.xyz + *vel * h, p.w);
}

INLINE void predict_particle(int i, __global const float4 *x, __global float4 *v, __global float4 *xs,
                      float h, float4 gh PIN_ARG)
{
    float3 vel;
    xs[i] = predict_position(i, x, v, h, gh, &vel PIN_PASS);
    v[i] = (float4)(vel, 0.0f);
}

__kernel void pbd_predict(__global const float4 *x, __global float4 *v, __global float4 *xs,
                          const float h, const float4 gh STEP_ARG PIN_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded to a multiple of the work-group size */
#ifdef CLOTH_ATTACHED_PINS
    pin_target += 3 * CLOTH_PINS * step; /* this substep's targets */
#endif
    predict_particle(i, x, v, xs, h, gh PIN_PASS);
}

/* ---- Jacobi (docs/pbd.md, "Jacobi"): every particle gathers the corrections of its own
 * constraints from the previous iterate X and writes the next iterate Y. Two kernels: the
 * interior (rows and columns 2 .. n-3: all 12 neighbours exist, no bounds tests, cnt = 12)
 * in vectors of V consecutive particles of a row, and every other particle (the border, and
 * the interior columns the vectors do not cover) one per work item from an index list.
 * The invalid cases (coincident particles; both ends pinned and rigid) are selected away,
 * not branched around: adding d * 0 to corr leaves its bits unchanged (corr is never -0),
 * so strict stays exact, and the lanes stay together. ---------------------------------- */

/* The Jacobi iterates X and Y are `grid_t`s: float4 per particle, or with CLOTH_PLANAR (the
 * program of the bands and vector-sweep shapes, whose iterates live in scratch grids only
 * their kernels read) x, y, z and w planes of n * n floats each, so that a vector of V
 * particles is four plain vector loads instead of 4V float4s dealt out into lanes. Read and written through these macros
 * (the vector forms after floatv, below); the operations on the values are the same. */
#ifdef CLOTH_PLANAR
typedef __global float *grid_t;
typedef __global const float *cgrid_t;
#define GRID_GET(g, i) ((float4)((g)[i], (g)[(i) + PLANE], (g)[(i) + 2 * PLANE], (g)[(i) + 3 * PLANE]))
#define GRID_SET(g, i, p) \
    ((g)[i] = (p).x, (g)[(i) + PLANE] = (p).y, (g)[(i) + 2 * PLANE] = (p).z, (g)[(i) + 3 * PLANE] = (p).w)
#define GRID_LOADV(g, i, x, y, z, w) \
    (*(x) = VLOAD(i, g), *(y) = VLOAD((i) + PLANE, g), *(z) = VLOAD((i) + 2 * PLANE, g), \
     *(w) = VLOAD((i) + 3 * PLANE, g))
#define GRID_STOREV(g, i, x, y, z, w) \
    (VSTORE(x, i, g), VSTORE(y, (i) + PLANE, g), VSTORE(z, (i) + 2 * PLANE, g), VSTORE(w, (i) + 3 * PLANE, g))
#else
typedef __global float4 *grid_t;
typedef __global const float4 *cgrid_t;
#define GRID_GET(g, i) ((g)[i])
#define GRID_SET(g, i, p) ((g)[i] = (p))
#define GRID_LOADV(g, i, x, y, z, w) loadv((g) + (i), x, y, z, w)
#define GRID_STOREV(g, i, x, y, z, w) storev((g) + (i), x, y, z, w)
#endif

/* One Jacobi pass for particle i, with bounds tests (scalar x, y, z). */
INLINE void jacobi_particle(int i, cgrid_t X, grid_t Y, __global const float *lam,
                     __global float *lam_out, int it, float4 rest, float4 at, float relax,
                     float omega)
{
    int first = it == 0;
    int row = i / N, col = i % N;
    float4 xi = GRID_GET(X, i);
    float w = xi.w;
    float cx = 0.0f, cy = 0.0f, cz = 0.0f; /* corr */
    int cnt = 0; /* constraints inside the grid */
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        cnt = cnt + ((r >= 0) & (r < N) & (c >= 0) & (c < N));
    }
    float scale = relax / (float)cnt; /* the share of each correction, and of its dlam */
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        if (r < 0 || r >= N || c < 0 || c >= N)
            continue; /* outside the grid: nothing added */
        float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
        float at_o = o < 4 ? at.x : (o < 8 ? at.y : at.z);
        float4 xj = GRID_GET(X, r * N + c);
        float dx = xi.x - xj.x, dy = xi.y - xj.y, dz = xi.z - xj.z;
        float L2 = (dx * dx + dy * dy) + dz * dz; /* not dot(): its order is the driver's */
        float denom = (w + xj.w) + at_o;
        float lam_o = first ? 0.0f : lam[o * PLANE + i];
#ifdef CLOTH_STRICT
        float L = sqrt(L2);
        float dl = ((-(L - rest_o)) - at_o * lam_o) / denom;
        float s = (w * dl) / L;
#else
        float inv_L = rsqrt(L2);
        float dl = (rest_o - L2 * inv_L - at_o * lam_o) / denom;
        float s = w * dl * inv_L;
#endif
        int valid = (L2 > 0.0f) & (denom > 0.0f);
        s = valid ? s : 0.0f;
        cx = cx + dx * s;
        cy = cy + dy * s;
        cz = cz + dz * s;
        float lam_new = lam_o + (valid ? dl : 0.0f) * scale;
#ifdef CLOTH_CHEBYSHEV
        if (it > 0) { /* lam_out holds the lambda before this pass's input (0 before the first) */
            float before = it == 1 ? 0.0f : lam_out[o * PLANE + i];
            lam_new = omega * (lam_new - before) + before;
        }
#endif
        lam_out[o * PLANE + i] = lam_new;
    }
    float4 y = (float4)(xi.x + cx * scale, xi.y + cy * scale, xi.z + cz * scale, w);
#ifdef CLOTH_CHEBYSHEV
    if (it > 0) { /* Y holds the iterate before X */
        float4 before = GRID_GET(Y, i);
        y = (float4)(omega * (y.x - before.x) + before.x, omega * (y.y - before.y) + before.y,
                     omega * (y.z - before.z) + before.z, w);
    }
#endif
    GRID_SET(Y, i, y);
}

/* The particles of the index list, one per work item. */
#ifndef CLOTH_PLANAR /* the per-stage shape: float4 iterates */
__kernel void pbd_jacobi_border(__global const float4 *X, __global float4 *Y,
                                __global const float *lam, __global float *lam_out,
                                const int it, const float4 rest, const float4 at,
                                const float relax, const float omega,
                                __global const int *particles, const int count)
{
    int t = get_global_id(0);
    if (t >= count)
        return; /* the launch is padded to a multiple of the work-group size */
    jacobi_particle(particles[t], X, Y, lam, lam_out, it, rest, at, relax, omega);
}
#endif

/* The interior in vectors: V consecutive particles of a row per work item, their float4s
 * deinterleaved into x, y, z, w vectors (or, planar, loaded as they are). Explicit vectors
 * because PoCL does not vectorise this kernel across work items by itself (docs/opencl.md,
 * "Why explicit vectors"). IEEE arithmetic is per lane, so strict stays exact.
 * When V does not divide the n - 4 interior columns, the last vector of a row overlaps the
 * one before it and stores only the lanes that one does not (its other lanes may read
 * multipliers the neighbouring item is rewriting: they are never stored), so the scalar
 * border list is only the 2-wide ring. */
#ifndef CLOTH_VECTOR_WIDTH
#define CLOTH_VECTOR_WIDTH 4
#endif
#define V CLOTH_VECTOR_WIDTH
#define VECTORS_PER_ROW (N - 4 >= V ? (N - 4 + V - 1) / V : 0)
#define LAST_FIRST_LANE (V * VECTORS_PER_ROW - (N - 4)) /* lanes the last vector leaves */

typedef float16 float16_u __attribute__((aligned(4))); /* a float4 pointer is 16-byte aligned */

/* x, y, z, w of the 4 particles at p, and back */
INLINE void load4(__global const float4 *p, float4 *x, float4 *y, float4 *z, float4 *w)
{
    float16 a = *(__global const float16_u *)p;
    *x = a.s048c;
    *y = a.s159d;
    *z = a.s26ae;
    *w = a.s37bf;
}

INLINE void store4(__global float4 *p, float4 x, float4 y, float4 z, float4 w)
{
    *(__global float16_u *)p = (float16)(x.s0, y.s0, z.s0, w.s0, x.s1, y.s1, z.s1, w.s1,
                                         x.s2, y.s2, z.s2, w.s2, x.s3, y.s3, z.s3, w.s3);
}

#if V == 4
typedef float4 floatv;
typedef int4 intv;
#define convert_floatv convert_float4
INLINE void loadv(__global const float4 *p, floatv *x, floatv *y, floatv *z, floatv *w)
{
    load4(p, x, y, z, w);
}
INLINE void storev(__global float4 *p, floatv x, floatv y, floatv z, floatv w)
{
    store4(p, x, y, z, w);
}
#elif V == 8
typedef float8 floatv;
typedef int8 intv;
#define convert_floatv convert_float8
INLINE void loadv(__global const float4 *p, floatv *x, floatv *y, floatv *z, floatv *w)
{
    float4 x0, y0, z0, w0, x1, y1, z1, w1;
    load4(p, &x0, &y0, &z0, &w0);
    load4(p + 4, &x1, &y1, &z1, &w1);
    *x = (float8)(x0, x1);
    *y = (float8)(y0, y1);
    *z = (float8)(z0, z1);
    *w = (float8)(w0, w1);
}
INLINE void storev(__global float4 *p, floatv x, floatv y, floatv z, floatv w)
{
    store4(p, x.lo, y.lo, z.lo, w.lo);
    store4(p + 4, x.hi, y.hi, z.hi, w.hi);
}
#elif V == 16
typedef float16 floatv;
typedef int16 intv;
#define convert_floatv convert_float16
INLINE void loadv(__global const float4 *p, floatv *x, floatv *y, floatv *z, floatv *w)
{
    float4 x0, y0, z0, w0, x1, y1, z1, w1, x2, y2, z2, w2, x3, y3, z3, w3;
    load4(p, &x0, &y0, &z0, &w0);
    load4(p + 4, &x1, &y1, &z1, &w1);
    load4(p + 8, &x2, &y2, &z2, &w2);
    load4(p + 12, &x3, &y3, &z3, &w3);
    *x = (float16)(x0, x1, x2, x3);
    *y = (float16)(y0, y1, y2, y3);
    *z = (float16)(z0, z1, z2, z3);
    *w = (float16)(w0, w1, w2, w3);
}
INLINE void storev(__global float4 *p, floatv x, floatv y, floatv z, floatv w)
{
    store4(p, x.lo.lo, y.lo.lo, z.lo.lo, w.lo.lo);
    store4(p + 4, x.lo.hi, y.lo.hi, z.lo.hi, w.lo.hi);
    store4(p + 8, x.hi.lo, y.hi.lo, z.hi.lo, w.hi.lo);
    store4(p + 12, x.hi.hi, y.hi.hi, z.hi.hi, w.hi.hi);
}
#else
#error "CLOTH_VECTOR_WIDTH must be 4, 8 or 16"
#endif
typedef floatv floatv_u __attribute__((aligned(4)));
typedef intv intv_u __attribute__((aligned(4)));
/* fast builds: fast_rsqrt() and fast_recip() over floatv */
#include "fast_math.cl"

/* what vloadn / vstoren do, inline: V floats at p + j of global memory */
#define VLOAD(j, p) (*(__global const floatv_u *)((p) + (j)))
#define VSTORE(v, j, p) (*(__global floatv_u *)((p) + (j)) = (v))

/* lanes first_lane .. V-1 of a to p[lane] (all of them with one store when first_lane = 0) */
INLINE void store_lanes(floatv a, int first_lane, __global float *p)
{
    if (first_lane == 0) {
        VSTORE(a, 0, p);
        return;
    }
    float lanes[V];
    *(floatv_u *)lanes = a; /* private memory */
    for (int l = first_lane; l < V; ++l)
        p[l] = lanes[l];
}

#if V == 4
#define LANE_IDS ((intv)(0, 1, 2, 3))
#elif V == 8
#define LANE_IDS ((intv)(0, 1, 2, 3, 4, 5, 6, 7))
#else
#define LANE_IDS ((intv)(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15))
#endif

/* -1 in the lanes whose neighbour o (from row `row`, columns `col`) is inside the grid, else 0 */
INLINE intv inside_grid(int row, intv col, int o)
{
    int r = row + OFFSETS[o].x;
    intv c = col + OFFSETS[o].y;
    return ((intv)(-(r >= 0 && r < N))) & (c >= 0) & (c < N);
}

/* One Jacobi pass for the V particles of a row from i, storing lanes first_lane .. V-1. With
 * `edge` (a constant where it is inlined), any of their neighbours may lie outside the grid: a
 * lane skips such a constraint as jacobi_particle's `continue` does (its sum keeps its bits;
 * the multiplier it stores there is never read) and divides relax by its own count; a row
 * outside the grid is read from the particles' own (and dropped), and a column past either
 * side reads at most two floats past the grid, which the planar scratch's margin holds.
 * Without `edge` every neighbour is inside (the interior vectors). */
INLINE void jacobi_lanes(int i, int first_lane, int edge, cgrid_t X, grid_t Y,
                         __global const float *lam, __global float *lam_out, int it, float4 rest,
                         float4 at, float relax, float omega)
{
    int first = it == 0;
    /* all bits after the first pass: the multipliers' select takes a lane mask, since
     * `first ? 0 : lam` became a branch in the unrolled loop below and PoCL's LLVM then spilled
     * every end's values across its twelve blocks (docs/pbd.md, "The spills were a branch") */
    intv later = (intv)(first - 1);
    int row = i / N;
    intv col = (i % N) + LANE_IDS;
    floatv x, y, z, w;
    GRID_LOADV(X, i, &x, &y, &z, &w);
    floatv cx = 0.0f, cy = 0.0f, cz = 0.0f; /* corr */
    floatv scale = relax / 12.0f; /* relax / cnt: all 12 constraints exist */
    if (edge) {
        intv cnt = 0;
        for (int o = 0; o < 12; ++o)
            cnt = cnt - inside_grid(row, col, o);
        scale = relax / convert_floatv(cnt);
    }
#pragma unroll
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x;
        intv inside = edge ? inside_grid(row, col, o) : (intv)(-1);
        int j = (!edge || (r >= 0 && r < N)) ? i + OFFSETS[o].x * N + OFFSETS[o].y : i;
        float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
        float at_o = o < 4 ? at.x : (o < 8 ? at.y : at.z);
        floatv xj, yj, zj, wj;
        GRID_LOADV(X, j, &xj, &yj, &zj, &wj);
        floatv dx = x - xj, dy = y - yj, dz = z - zj;
#ifdef CLOTH_STRICT
        floatv L2 = (dx * dx + dy * dy) + dz * dz;
#else
        floatv L2 = dx * dx + dy * dy + dz * dz;
#endif
        floatv denom = (w + wj) + at_o;
        floatv lam_o = SELECT((floatv)(0.0f), VLOAD(0, lam + o * PLANE + i), later);
#ifdef CLOTH_STRICT
        floatv L = sqrt(L2);
        floatv dl = ((-(L - rest_o)) - at_o * lam_o) / denom;
        floatv s = (w * dl) / L;
#else
        floatv inv_L = fast_rsqrt(L2);
        floatv dl = (rest_o - L2 * inv_L - at_o * lam_o) * fast_recip(denom);
        floatv s = w * dl * inv_L;
#endif
        intv valid = (L2 > 0.0f) & (denom > 0.0f);
        s = SELECT((floatv)(0.0f), s, valid);
        if (edge) { /* a neighbour outside: nothing added (garbage read there is dropped) */
            cx = SELECT(cx, cx + dx * s, inside);
            cy = SELECT(cy, cy + dy * s, inside);
            cz = SELECT(cz, cz + dz * s, inside);
        } else {
            cx = cx + dx * s;
            cy = cy + dy * s;
            cz = cz + dz * s;
        }
        floatv lam_new = lam_o + SELECT((floatv)(0.0f), dl, valid) * scale;
#ifdef CLOTH_CHEBYSHEV
        if (it > 0) {
            intv extrapolated = (intv)((it == 1) - 1); /* a lane mask, as `later` is */
            floatv before = SELECT((floatv)(0.0f), VLOAD(0, lam_out + o * PLANE + i), extrapolated);
            lam_new = omega * (lam_new - before) + before;
        }
#endif
        store_lanes(lam_new, first_lane, lam_out + o * PLANE + i);
    }
    floatv yx = x + cx * scale, yy = y + cy * scale, yz = z + cz * scale;
#ifdef CLOTH_CHEBYSHEV
    if (it > 0) {
        floatv bx, by, bz, bw;
        GRID_LOADV(Y, i, &bx, &by, &bz, &bw);
        yx = omega * (yx - bx) + bx;
        yy = omega * (yy - by) + by;
        yz = omega * (yz - bz) + bz;
    }
#endif
    if (first_lane == 0) {
        GRID_STOREV(Y, i, yx, yy, yz, w);
    } else {
        float lx[V], ly[V], lz[V], lw[V];
        *(floatv_u *)lx = yx;
        *(floatv_u *)ly = yy;
        *(floatv_u *)lz = yz;
        *(floatv_u *)lw = w;
        for (int l = first_lane; l < V; ++l)
            GRID_SET(Y, i + l, (float4)(lx[l], ly[l], lz[l], lw[l]));
    }
}

#if VECTORS_PER_ROW > 0
#define INTERIOR_VECTORS (VECTORS_PER_ROW * (N - 4))
/* One Jacobi pass for the V interior particles of vector t (columns 2 .. n-3 of rows 2 .. n-3). */
INLINE void jacobi_vector(int t, cgrid_t X, grid_t Y, __global const float *lam,
                          __global float *lam_out, int it, float4 rest, float4 at, float relax,
                          float omega)
{
    int vector = t % VECTORS_PER_ROW, last = vector == VECTORS_PER_ROW - 1;
    int i = (2 + t / VECTORS_PER_ROW) * N + (last ? N - 2 - V : 2 + V * vector);
    jacobi_lanes(i, last ? LAST_FIRST_LANE : 0, 0, X, Y, lam, lam_out, it, rest, at, relax, omega);
}

#ifndef CLOTH_PLANAR /* the per-stage shape: float4 iterates */
__kernel void pbd_jacobi_interior(__global const float4 *X, __global float4 *Y,
                                  __global const float *lam, __global float *lam_out,
                                  const int it, const float4 rest, const float4 at,
                                  const float relax, const float omega)
{
    int t = get_global_id(0);
    if (t >= INTERIOR_VECTORS)
        return;
    jacobi_vector(t, X, Y, lam, lam_out, it, rest, at, relax, omega);
}
#endif
#else
#define INTERIOR_VECTORS 0
#endif

/* One coloured Gauss-Seidel constraint between particles i and j of X, updating both ends in
 * place; its multiplier at *lam. */
INLINE void coloured_pair(int i, int j, grid_t X, __global float *lam, int first, float rest, float at)
{
    float4 xi = GRID_GET(X, i), xj = GRID_GET(X, j);
    float3 d = xi.xyz - xj.xyz;
    float L2 = dot3(d, d);
    float denom = (xi.w + xj.w) + at;
    float lam_c = first ? 0.0f : *lam;
    float dlam = 0.0f;
    if (L2 > 0.0f && denom > 0.0f) {
#ifdef CLOTH_STRICT
        float L = sqrt(L2);
        dlam = ((-(L - rest)) - at * lam_c) / denom;
        GRID_SET(X, i, (float4)(xi.xyz + d * ((xi.w * dlam) / L), xi.w));
        GRID_SET(X, j, (float4)(xj.xyz - d * ((xj.w * dlam) / L), xj.w));
#else
        float inv_L = rsqrt(L2);
        dlam = (rest - L2 * inv_L - at * lam_c) / denom;
        float s = dlam * inv_L;
        GRID_SET(X, i, (float4)(xi.xyz + d * (xi.w * s), xi.w));
        GRID_SET(X, j, (float4)(xj.xyz - d * (xj.w * s), xj.w));
#endif
    }
    *lam = lam_c + dlam;
}

#ifndef CLOTH_PLANAR /* the per-stage and one-launch shapes: float4 state */
/* Constraint c of the coloured Gauss-Seidel pass: it joins ij[c]; no two constraints of a
 * batch share a particle (constraints.py). */
INLINE void coloured_constraint(int c, __global float4 *X, __global const int2 *ij, __global float *lam,
                                int first, float rest, float at)
{
    int2 e = ij[c];
    coloured_pair(e.x, e.y, X, lam + c, first, rest, at);
}

/* One batch: constraints offset .. offset + count - 1. */
__kernel void pbd_coloured(__global float4 *X, __global const int2 *ij, __global float *lam,
                           const int offset, const int count, const int first, const float rest,
                           const float at)
{
    int k = get_global_id(0);
    if (k >= count)
        return;
    coloured_constraint(offset + k, X, ij, lam, first, rest, at);
}
#endif

#if CLOTH_MESHES > 0
/* collide_mesh.cl holds, beside the scalar collide_meshes() used here, the lane-parallel forms
 * of verlet_cloth.cl's vector kernels, written with INLINE, SELECT, floatv_u and intv_u
 * (defined above; unused here: PBD collides one particle per work item). */
/* The meshes: collide_meshes(x, rows, geometry, ints), only where the scene has them. */
#include <mesh_colliders>
#endif

#include "collide_particle.cl"

__kernel void pbd_collide(__global float4 *xs, __constant float4 *colliders STEP_ARG MESH_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this substep's poses */
#endif
    xs[i] = collide_particle(xs[i], colliders MESH_PASS);
}

/* update: v = (xs - x) / h, damped; x = xs */
INLINE void update_particle(int i, float4 p, __global float4 *x, __global float4 *v, float h, float damp)
{
    float3 vel = (p.xyz - x[i].xyz) / h;
    v[i] = (float4)(vel * damp, 0.0f);
    x[i] = p;
}

/* The end of a substep in the kernels that run whole substeps (pbd_substeps,
 * pbd_coloured_vectors): collide and update every particle from the iterate X, the work-group's
 * items striding over them, then a barrier. */
INLINE void collide_update_all(cgrid_t X, int first_item, int stride, __global float4 *x,
                               __global float4 *v, float h, float damp,
                               __constant float4 *colliders MESH_ARG)
{
    for (int i = first_item; i < N2; i += stride) {
#if CLOTH_SPHERES + CLOTH_CYLINDERS + CLOTH_BOXES + CLOTH_PLANES + CLOTH_MESHES > 0
        update_particle(i, collide_particle(GRID_GET(X, i), colliders MESH_PASS), x, v, h, damp);
#else
        update_particle(i, GRID_GET(X, i), x, v, h, damp);
#endif
    }
    barrier(CLK_GLOBAL_MEM_FENCE);
}

/* Those kernels' per-substep constants: the tables of substep `step` (their first), and then
 * of the next one (one collider table, and one set of pin targets, per substep) */
#ifdef CLOTH_PER_STEP
#ifdef CLOTH_ATTACHED_PINS
#define FIRST_SUBSTEP_TABLES() (colliders += step * TABLE_ROWS, pin_target += 3 * CLOTH_PINS * step)
#define NEXT_SUBSTEP_TABLES() (colliders += TABLE_ROWS, pin_target += 3 * CLOTH_PINS)
#else
#define FIRST_SUBSTEP_TABLES() (colliders += step * TABLE_ROWS)
#define NEXT_SUBSTEP_TABLES() (colliders += TABLE_ROWS)
#endif
#else
#define FIRST_SUBSTEP_TABLES() ((void)0)
#define NEXT_SUBSTEP_TABLES() ((void)0)
#endif

__kernel void pbd_update(__global float4 *x, __global float4 *v, __global const float4 *xs,
                         const float h, const float damp)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    update_particle(i, xs[i], x, v, h, damp);
}

/* ---- Whole substeps in one launch (the `one-launch` shape), for grids small enough that
 * one work-group does them faster than a launch per pass: the work-group's items stride over
 * the particles (or a batch's constraints) of each stage, and a barrier separates the stages
 * (valid inside one work-group; the state stays in the global buffers, and the Jacobi
 * iterates ping-pong by swapping pointers as the host does between launches). The same
 * functions as the one-stage kernels above, in the same order: the same bits. Collide and
 * update share a loop: both touch only the particle's own data. ------------------------ */
#ifndef CLOTH_PLANAR /* the one-launch shape: float4 iterates */
__kernel void pbd_substeps(__global float4 *x, __global float4 *v, __global float4 *xs0,
                           __global float4 *xs1, __global float *lam0, __global float *lam1,
                           __global const float *omega,
                           __global const int *border, const int border_count,
                           __global const int2 *ij, __global const int *batch_offsets,
                           const float h, const float4 gh, const float4 rest, const float4 at,
                           const float relax, const float damp, __constant float4 *colliders,
                           const int iterations, const int substeps STEP_ARG MESH_ARG PIN_ARG)
{
    int first_item = get_local_id(0), stride = get_local_size(0);
    FIRST_SUBSTEP_TABLES();
    for (int s = 0; s < substeps; ++s) {
        for (int i = first_item; i < N2; i += stride)
            predict_particle(i, x, v, xs0, h, gh PIN_PASS);
        barrier(CLK_GLOBAL_MEM_FENCE);
        __global float4 *X = xs0, *Y = xs1;
        __global float *lam = lam0, *lam_out = lam1; /* the same buffer without Chebyshev */
        for (int it = 0; it < iterations; ++it) {
            int first = it == 0;
#ifdef CLOTH_COLOURED
            for (int b = 0; b < 12; ++b) { /* batches 0-3 structural, 4-7 shear, 8-11 bend */
                float rest_b = b < 4 ? rest.x : (b < 8 ? rest.y : rest.z);
                float at_b = b < 4 ? at.x : (b < 8 ? at.y : at.z);
                for (int c = batch_offsets[b] + first_item; c < batch_offsets[b + 1]; c += stride)
                    coloured_constraint(c, X, ij, lam, first, rest_b, at_b);
                barrier(CLK_GLOBAL_MEM_FENCE);
            }
#else
            for (int t = first_item; t < INTERIOR_VECTORS + border_count; t += stride) {
#if INTERIOR_VECTORS > 0
                if (t < INTERIOR_VECTORS) {
                    jacobi_vector(t, X, Y, lam, lam_out, it, rest, at, relax, omega[it]);
                    continue;
                }
#endif
                jacobi_particle(border[t - INTERIOR_VECTORS], X, Y, lam, lam_out, it, rest, at,
                                relax, omega[it]);
            }
            barrier(CLK_GLOBAL_MEM_FENCE);
            __global float4 *T = X;
            X = Y;
            Y = T;
            __global float *U = lam;
            lam = lam_out;
            lam_out = U;
#endif
        }
        collide_update_all(X, first_item, stride, x, v, h, damp, colliders MESH_PASS);
        NEXT_SUBSTEP_TABLES();
    }
}
#endif

/* ---- Jacobi in bands (the `bands-R` shapes): a substep's predict and all its Jacobi passes
 * in one launch, one work-group per band of R rows, each in its own scratch copy of the
 * grid. Iterate k + 1 of a particle depends only on iterate k within two rows of it, so a
 * band that predicts its rows and 2 * iterations rows either side, and computes each pass
 * over 2 rows fewer either side than the pass before, holds exact final iterates on its own
 * rows (temporal blocking): the same functions, the same operands, the same bits as the
 * per-stage passes, with no launch between passes and the multipliers (never needed outside
 * the substep) kept in the band's scratch, in cache, instead of streamed through memory each
 * pass. The price: the halo rows are computed by both bands that overlap there. A band writes
 * its own rows of xs; collide and update are then the per-stage launches. ---------------- */

/* One Jacobi pass over rows a .. b-1, the items of a work-group striding over one flat range of
 * units so that a wide work-group keeps every item busy. */
#if defined(CLOTH_PLANAR) && N >= 2 * V
/* Where a row holds two vectors, the bands take every particle in vectors: a row's units are
 * an edge vector at either side (columns 0 .. V-1 and n-V .. n-1, jacobi_lanes with `edge`)
 * and the interior vectors between them (the last overlapping the one before), every unit of
 * rows 0, 1, n-2 and n-1 an edge one. A particle alone costs about as much as a vector of V (its
 * bounds tests, scalar division and square root), so the border columns and rows one at a time
 * were a large share of a pass (docs/pbd.md, "Time per step on OpenCL"). */
#define MIDDLE_VECTORS ((N - 2 * V + V - 1) / V)
#define ROW_UNITS (MIDDLE_VECTORS + 2)
#define MIDDLE_FIRST_LANE (V * MIDDLE_VECTORS - (N - 2 * V)) /* lanes the last interior vector leaves */
INLINE void jacobi_rows(int a, int b, int first_item, int stride, cgrid_t X, grid_t Y,
                        __global const float *lam, __global float *lam_out, int it, float4 rest,
                        float4 at, float relax, float omega)
{
    for (int t = first_item; t < (b - a) * ROW_UNITS; t += stride) {
        int r = a + t / ROW_UNITS, u = t % ROW_UNITS, m = u - 1; /* m: the interior vector */
        int col = u == 0 ? 0 : (u == ROW_UNITS - 1 ? N - V : (m == MIDDLE_VECTORS - 1 ? N - 2 * V : V + V * m));
        int first_lane = (u > 0 && m == MIDDLE_VECTORS - 1) ? MIDDLE_FIRST_LANE : 0;
        if (u == 0 || u == ROW_UNITS - 1 || r < 2 || r >= N - 2)
            jacobi_lanes(r * N + col, first_lane, 1, X, Y, lam, lam_out, it, rest, at, relax, omega);
        else
            jacobi_lanes(r * N + col, first_lane, 0, X, Y, lam, lam_out, it, rest, at, relax, omega);
    }
}
#else
/* Otherwise as pbd_jacobi_interior and pbd_jacobi_border divide a pass: the interior rows'
 * units (the vectors of rows 2 .. n-3, then their four border columns), then every particle of
 * the other rows. */
INLINE void jacobi_rows(int a, int b, int first_item, int stride, cgrid_t X, grid_t Y,
                        __global const float *lam, __global float *lam_out, int it, float4 rest,
                        float4 at, float relax, float omega)
{
    int inner_a = a, inner_b = a; /* the rows of a .. b-1 with interior vectors */
#if INTERIOR_VECTORS > 0
    inner_a = max(a, 2);
    inner_b = max(inner_a, min(b, N - 2));
#define UNITS (VECTORS_PER_ROW + 4)
    for (int t = first_item; t < (inner_b - inner_a) * UNITS; t += stride) {
        int r = inner_a + t / UNITS, u = t % UNITS;
        if (u < VECTORS_PER_ROW) {
            jacobi_vector((r - 2) * VECTORS_PER_ROW + u, X, Y, lam, lam_out, it, rest, at, relax, omega);
        } else {
            int c = u - VECTORS_PER_ROW; /* columns 0, 1, n-2, n-1 */
            c = c < 2 ? c : N - 4 + c;
            jacobi_particle(r * N + c, X, Y, lam, lam_out, it, rest, at, relax, omega);
        }
    }
#undef UNITS
#endif
    /* the rest: a .. inner_a-1 and inner_b .. b-1, every particle */
    int before = (inner_a - a) * N;
    for (int t = first_item; t < (b - a - (inner_b - inner_a)) * N; t += stride) {
        int i = t < before ? a * N + t : inner_b * N + (t - before);
        jacobi_particle(i, X, Y, lam, lam_out, it, rest, at, relax, omega);
    }
}
#endif

/* scratch: CLOTH_PLANAR_MARGIN floats, then two planar grids per band (the ping-pong, 4 planes
 * of PLANE floats each), then the margin again (an edge vector reads up to two floats past a
 * grid); lam_scratch: 12 planes per band, twice with Chebyshev (its two multiplier buffers) */
#ifdef CLOTH_PLANAR /* its own program: planar scratch iterates */
__kernel void pbd_jacobi_bands(__global const float4 *x, __global const float4 *v,
                               __global float4 *xs, __global float *scratch,
                               __global float *lam_scratch, __global const float *omega,
                               const float h, const float4 gh, const float4 rest,
                               const float4 at, const float relax, const int iterations,
                               const int band_rows STEP_ARG PIN_ARG)
{
    int band = get_group_id(0), first_item = get_local_id(0), stride = get_local_size(0);
    int r0 = band * band_rows, r1 = min(N, r0 + band_rows);
    grid_t X = scratch + CLOTH_PLANAR_MARGIN + 2 * band * 4 * PLANE, Y = X + 4 * PLANE;
#ifdef CLOTH_CHEBYSHEV
    __global float *lam = lam_scratch + 2 * band * 12 * PLANE, *lam_out = lam + 12 * PLANE;
#else
    __global float *lam = lam_scratch + band * 12 * PLANE, *lam_out = lam;
#endif
#ifdef CLOTH_ATTACHED_PINS
    pin_target += 3 * CLOTH_PINS * step; /* this substep's targets */
#endif
    int halo = 2 * iterations;
    float3 vel; /* unused: update computes the velocity again from xs */
    for (int i = max(0, r0 - halo) * N + first_item; i < min(N, r1 + halo) * N; i += stride)
        GRID_SET(X, i, predict_position(i, x, v, h, gh, &vel PIN_PASS));
    barrier(CLK_GLOBAL_MEM_FENCE);
    for (int it = 0; it < iterations; ++it) {
        int reach = 2 * (iterations - 1 - it); /* rows either side this pass must get right */
        jacobi_rows(max(0, r0 - reach), min(N, r1 + reach), first_item, stride, X, Y, lam, lam_out,
                    it, rest, at, relax, omega[it]);
        barrier(CLK_GLOBAL_MEM_FENCE);
        grid_t T = X;
        X = Y;
        Y = T;
        __global float *U = lam;
        lam = lam_out;
        lam_out = U;
    }
    for (int i = r0 * N + first_item; i < r1 * N; i += stride)
        xs[i] = GRID_GET(X, i);
}
#endif

/* ---- The coloured sweep in vectors (the `one-launch-vectors` shape, coloured only): whole
 * substeps in one launch of one work-group, like pbd_substeps, on a planar scratch copy of the
 * predicted positions, each batch's constraints V at a time. A batch along (dr, dc) with
 * dr > 0 holds, for each row r of its parity, every link (r, c) -- (r + dr, c + dc): V
 * consecutive c are V plain vector loads at each end. The (0, 1) batches hold the links from
 * the columns of one parity: V of them are 2V consecutive columns, dealt into even and odd
 * lanes. Each constraint does coloured_pair's operations in coloured_pair's order (the tail
 * of a row is coloured_pair itself); no two share a particle, so the order within a batch
 * cannot matter and strict is the reference's bits. The multipliers are the scratch's own,
 * one per first endpoint per batch (never read outside the substep). ------------------- */
#if defined(CLOTH_PLANAR) && defined(CLOTH_COLOURED)
/* V constraints i + l -- j + l (l < V: stride 1) or i + 2l -- i + 2l + 1 (`paired`), their
 * multipliers at lam + l (or lam + 2l) */
INLINE void coloured_vector(int i, int j, int paired, int first_lane, grid_t X, __global float *lam,
                            int first, float rest, float at)
{
    floatv xi, yi, zi, wi, xj, yj, zj, wj, lam_c = 0.0f;
    if (paired) { /* 2V columns from i: the even ones are the first ends, the odd ones the second */
        floatv a, b, c, d, e, f, g, h;
        GRID_LOADV(X, i, &a, &b, &c, &d);
        GRID_LOADV(X, i + V, &e, &f, &g, &h);
        xi = (floatv)(a.even, e.even), xj = (floatv)(a.odd, e.odd);
        yi = (floatv)(b.even, f.even), yj = (floatv)(b.odd, f.odd);
        zi = (floatv)(c.even, g.even), zj = (floatv)(c.odd, g.odd);
        wi = (floatv)(d.even, h.even), wj = (floatv)(d.odd, h.odd);
        if (!first)
            lam_c = (floatv)(VLOAD(0, lam).even, VLOAD(V, lam).even);
    } else {
        GRID_LOADV(X, i, &xi, &yi, &zi, &wi);
        GRID_LOADV(X, j, &xj, &yj, &zj, &wj);
        if (!first)
            lam_c = VLOAD(0, lam);
    }
    floatv dx = xi - xj, dy = yi - yj, dz = zi - zj;
    floatv denom = (wi + wj) + at;
#ifdef CLOTH_STRICT
    floatv L2 = (dx * dx + dy * dy) + dz * dz;
    floatv L = sqrt(L2);
    floatv dlam = ((-(L - rest)) - at * lam_c) / denom;
    floatv si = (wi * dlam) / L, sj = (wj * dlam) / L;
#else
    floatv L2 = dx * dx + dy * dy + dz * dz;
    floatv inv_L = fast_rsqrt(L2);
    floatv dlam = (rest - L2 * inv_L - at * lam_c) * fast_recip(denom);
    floatv s = dlam * inv_L;
    floatv si = wi * s, sj = wj * s;
#endif
    intv valid = (L2 > 0.0f) & (denom > 0.0f); /* else: nothing moves, dlam = 0 */
    dlam = SELECT((floatv)(0.0f), dlam, valid);
    xi = SELECT(xi, xi + dx * si, valid), yi = SELECT(yi, yi + dy * si, valid), zi = SELECT(zi, zi + dz * si, valid);
    xj = SELECT(xj, xj - dx * sj, valid), yj = SELECT(yj, yj - dy * sj, valid), zj = SELECT(zj, zj - dz * sj, valid);
    floatv lam_new = lam_c + dlam;
    if (!paired && first_lane == 0) {
        VSTORE(lam_new, 0, lam);
        GRID_STOREV(X, i, xi, yi, zi, wi);
        GRID_STOREV(X, j, xj, yj, zj, wj);
        return;
    }
    /* lane by lane: the (0, 1) batches' interleaved ends, or only the lanes first_lane .. V-1
     * of a row's last vector (the others, overlapping the vector before it, read ends that one
     * has already moved: they are computed and dropped) */
    float li[V], lx[V], ly[V], lz[V], mx[V], my[V], mz[V];
    *(floatv_u *)li = lam_new;
    *(floatv_u *)lx = xi, *(floatv_u *)ly = yi, *(floatv_u *)lz = zi;
    *(floatv_u *)mx = xj, *(floatv_u *)my = yj, *(floatv_u *)mz = zj;
    int step = paired ? 2 : 1; /* lane l's first end is i + step * l, its second j + step * l */
    j = paired ? i + 1 : j;
    for (int l = first_lane; l < V; ++l) {
        int p = i + step * l, q = j + step * l;
        lam[step * l] = li[l];
        X[p] = lx[l], X[p + PLANE] = ly[l], X[p + 2 * PLANE] = lz[l];
        X[q] = mx[l], X[q + PLANE] = my[l], X[q + 2 * PLANE] = mz[l];
    }
}

/* unit u of a row of `len` constraints in vectors: its first constraint and the first lane it
 * stores (the last vector overlaps the one before it where V does not divide len) */
INLINE int2 vector_unit(int u, int len)
{
    int vectors = (len + V - 1) / V;
    return u < vectors - 1 ? (int2)(V * u, 0) : (int2)(len - V, V * vectors - len);
}

/* batch b (constraints.py's order: direction b / 2, parity b % 2) of X, the items of the
 * work-group striding over its rows' vectors and tails */
INLINE void coloured_batch(int b, int first_item, int stride, grid_t X, __global float *lam,
                           int first, float rest, float at)
{
    const int2 dirs[6] = {(int2)(0, 1), (int2)(1, 0), (int2)(1, 1), (int2)(1, -1), (int2)(2, 2), (int2)(2, -2)};
    int dr = dirs[b / 2].x, dc = dirs[b / 2].y, parity = b % 2;
    lam += b * PLANE; /* the batch's multipliers, at each constraint's first end */
    /* a row's constraints: (0, 1) the links from columns parity, parity + 2, ... (c + 1 < n);
     * dr > 0, in rows r with (r / dr) % 2 == parity and r + dr < n, those from c0 .. c0 + len - 1.
     * In vectors of V (the last overlapping), or one by one where a row has fewer than V. */
    int paired = dr == 0, c0 = dc < 0 ? -dc : 0;
    int len = paired ? (N - parity) / 2 : N - (dc < 0 ? -dc : dc);
    int in_vectors = len >= V, units = in_vectors ? (len + V - 1) / V : len;
    int rows = paired ? N : N - dr; /* dr > 0: the rows of the other parity idle */
    for (int t = first_item; t < rows * units; t += stride) {
        int r = t / units, u = t % units;
        if (!paired && (r / dr) % 2 != parity)
            continue;
        int2 unit = in_vectors ? vector_unit(u, len) : (int2)(u, 0);
        int i = r * N + (paired ? parity + 2 * unit.x : c0 + unit.x);
        int j = paired ? i + 1 : i + dr * N + dc;
        if (in_vectors)
            coloured_vector(i, j, paired, unit.y, X, lam + i, first, rest, at);
        else
            coloured_pair(i, j, X, lam + i, first, rest, at);
    }
}

/* scratch: one planar grid (4 * n * n floats); lam_scratch: 12 * n * n floats */
__kernel void pbd_coloured_vectors(__global float4 *x, __global float4 *v, __global float *scratch,
                                   __global float *lam_scratch, const float h, const float4 gh,
                                   const float4 rest, const float4 at, const float damp,
                                   __constant float4 *colliders, const int iterations,
                                   const int substeps STEP_ARG MESH_ARG PIN_ARG)
{
    int first_item = get_local_id(0), stride = get_local_size(0);
    grid_t X = scratch;
    FIRST_SUBSTEP_TABLES();
    for (int s = 0; s < substeps; ++s) {
        float3 vel; /* unused: update computes the velocity again from xs */
        for (int i = first_item; i < N2; i += stride)
            GRID_SET(X, i, predict_position(i, x, v, h, gh, &vel PIN_PASS));
        barrier(CLK_GLOBAL_MEM_FENCE);
        for (int it = 0; it < iterations; ++it) {
            for (int b = 0; b < 12; ++b) { /* batches 0-3 structural, 4-7 shear, 8-11 bend */
                float rest_b = b < 4 ? rest.x : (b < 8 ? rest.y : rest.z);
                float at_b = b < 4 ? at.x : (b < 8 ? at.y : at.z);
                coloured_batch(b, first_item, stride, X, lam_scratch, it == 0, rest_b, at_b);
                barrier(CLK_GLOBAL_MEM_FENCE);
            }
        }
        collide_update_all(X, first_item, stride, x, v, h, damp, colliders MESH_PASS);
        NEXT_SUBSTEP_TABLES();
    }
}
#endif

/* [self_collision]: its pass and the colliders after it, only where the scene has the table. */
#define CLOTH_PBD
#include <self_collision>
