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
 * work-group, barriers between the stages (see there).
 *
 * Build options:
 *   CLOTH_N                                      grid side n (index arithmetic folds)
 *   CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_PLANES collider counts (0 when absent)
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
 *   CLOTH_STRICT  every operation in the order docs/pbd.md fixes, no contraction, sqrt and
 *                 '/', no dot(): equal to the NumPy float32 reference bit for bit. Without
 *                 it (fast): one rsqrt per constraint, dot(), contraction (-cl-mad-enable).
 * Numbers (h, g*h, compliance/h^2, rest lengths, damping, relaxation, Chebyshev weights) are
 * kernel arguments, rounded once to float32 on the host. The collider table and the colliders
 * are collide.cl's (included by the host, as verlet_cloth.cl includes it): spheres (centre,
 * radius); cylinders (start, length), (unit axis, radius), (radial_r, 0); planes (point, 0),
 * (unit normal, 0).
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
#ifndef CLOTH_SPHERES
#define CLOTH_SPHERES 0
#endif
#ifndef CLOTH_CYLINDERS
#define CLOTH_CYLINDERS 0
#endif
#ifndef CLOTH_PLANES
#define CLOTH_PLANES 0
#endif
#define N CLOTH_N
#define N2 (CLOTH_N * CLOTH_N)

/* The extra arguments of a scene with meshes, motion or attached pins (verlet_cloth.cl's
 * names): STEP_ARG, MESH_ARG, PIN_ARG in a kernel's parameters, *_PASS through the helpers. */
#ifndef CLOTH_MESHES
#define CLOTH_MESHES 0
#endif
#define MESH_ROWS 6 /* collider-table rows per mesh: pose, margins, box (collide_mesh.cl) */
#define ANALYTIC_ROWS (CLOTH_SPHERES + 3 * CLOTH_CYLINDERS + 2 * CLOTH_PLANES)
#define TABLE_ROWS (ANALYTIC_ROWS + MESH_ROWS * CLOTH_MESHES) /* a substep's collider table */
#if CLOTH_MESHES > 0
#define MESH_ARG , __global const float4 *mesh_geometry, __global const int *mesh_ints
#define MESH_PASS , mesh_geometry, mesh_ints
#else
#define MESH_ARG
#define MESH_PASS
#endif
#ifdef CLOTH_ATTACHED_PINS
#define PIN_ARG , __global const int *pin_slot, __global const float *pin_target
#define PIN_PASS , pin_slot, pin_target
#else
#define PIN_ARG
#define PIN_PASS
#endif
#ifdef CLOTH_PER_STEP
#define STEP_ARG , const int step
#else
#define STEP_ARG
#endif

/* The 12-spring stencil (d_row, d_col) in the order docs/semantics.md fixes; offsets 0-3 are
 * structural, 4-7 shear, 8-11 bend (the .x, .y, .z of `rest` and `at`). */
__constant int2 OFFSETS[12] = {
    (int2)(0, -1), (int2)(0, 1), (int2)(-1, 0), (int2)(1, 0),
    (int2)(-1, -1), (int2)(-1, 1), (int2)(1, -1), (int2)(1, 1),
    (int2)(-2, -2), (int2)(-2, 2), (int2)(2, -2), (int2)(2, 2),
};

/* (a.x*b.x + a.y*b.y) + a.z*b.z in strict mode; dot() sums in the driver's order */
float dot3(float3 a, float3 b)
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

/* predict: v += g*h, xs = x + v*h; pinned particles stay and have no velocity, but a pin
 * following a body goes to its target at the end of the substep (pin_target: this
 * substep's CLOTH_PINS float3s) */
void predict_particle(int i, __global const float4 *x, __global float4 *v, __global float4 *xs,
                      float h, float4 gh PIN_ARG)
{
    float4 p = x[i];
    if (p.w == 0.0f) {
        v[i] = (float4)(0.0f);
#ifdef CLOTH_ATTACHED_PINS
        int slot = pin_slot[i];
        if (slot >= 0)
            p = (float4)(pin_target[3 * slot], pin_target[3 * slot + 1], pin_target[3 * slot + 2], p.w);
#endif
        xs[i] = p;
        return;
    }
    float3 vel = v[i].xyz + gh.xyz;
    v[i] = (float4)(vel, 0.0f);
    xs[i] = (float4)(p.xyz + vel * h, p.w);
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

/* One Jacobi pass for particle i, with bounds tests (scalar x, y, z). */
void jacobi_particle(int i, __global const float4 *X, __global float4 *Y, __global const float *lam,
                     __global float *lam_out, int it, float4 rest, float4 at, float relax,
                     float omega)
{
    int first = it == 0;
    int row = i / N, col = i % N;
    float4 xi = X[i];
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
        float4 xj = X[r * N + c];
        float dx = xi.x - xj.x, dy = xi.y - xj.y, dz = xi.z - xj.z;
        float L2 = (dx * dx + dy * dy) + dz * dz; /* not dot(): its order is the driver's */
        float denom = (w + xj.w) + at_o;
        float lam_o = first ? 0.0f : lam[o * N2 + i];
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
            float before = it == 1 ? 0.0f : lam_out[o * N2 + i];
            lam_new = omega * (lam_new - before) + before;
        }
#endif
        lam_out[o * N2 + i] = lam_new;
    }
    float4 y = (float4)(xi.x + cx * scale, xi.y + cy * scale, xi.z + cz * scale, w);
#ifdef CLOTH_CHEBYSHEV
    if (it > 0) { /* Y holds the iterate before X */
        float4 before = Y[i];
        y = (float4)(omega * (y.x - before.x) + before.x, omega * (y.y - before.y) + before.y,
                     omega * (y.z - before.z) + before.z, w);
    }
#endif
    Y[i] = y;
}

/* The particles of the index list, one per work item. */
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

/* The interior in vectors: V consecutive particles of a row per work item, their float4s
 * deinterleaved into x, y, z, w vectors. Explicit vectors because PoCL does not vectorise
 * this kernel across work items by itself: at n = 256 a pass took 2.5-3 ms in scalar form,
 * 0.8 ms with V = 16, strict or fast. IEEE arithmetic is per lane, so strict stays exact.
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

/* x, y, z, w of the 4 particles at p, and back */
void load4(__global const float4 *p, float4 *x, float4 *y, float4 *z, float4 *w)
{
    float16 a = vload16(0, (__global const float *)p);
    *x = a.s048c;
    *y = a.s159d;
    *z = a.s26ae;
    *w = a.s37bf;
}

void store4(__global float4 *p, float4 x, float4 y, float4 z, float4 w)
{
    vstore16((float16)(x.s0, y.s0, z.s0, w.s0, x.s1, y.s1, z.s1, w.s1,
                       x.s2, y.s2, z.s2, w.s2, x.s3, y.s3, z.s3, w.s3),
             0, (__global float *)p);
}

#if V == 4
typedef float4 floatv;
typedef int4 intv;
#define VLOAD vload4
#define VSTORE vstore4
void loadv(__global const float4 *p, floatv *x, floatv *y, floatv *z, floatv *w)
{
    load4(p, x, y, z, w);
}
void storev(__global float4 *p, floatv x, floatv y, floatv z, floatv w)
{
    store4(p, x, y, z, w);
}
#elif V == 8
typedef float8 floatv;
typedef int8 intv;
#define VLOAD vload8
#define VSTORE vstore8
void loadv(__global const float4 *p, floatv *x, floatv *y, floatv *z, floatv *w)
{
    float4 x0, y0, z0, w0, x1, y1, z1, w1;
    load4(p, &x0, &y0, &z0, &w0);
    load4(p + 4, &x1, &y1, &z1, &w1);
    *x = (float8)(x0, x1);
    *y = (float8)(y0, y1);
    *z = (float8)(z0, z1);
    *w = (float8)(w0, w1);
}
void storev(__global float4 *p, floatv x, floatv y, floatv z, floatv w)
{
    store4(p, x.lo, y.lo, z.lo, w.lo);
    store4(p + 4, x.hi, y.hi, z.hi, w.hi);
}
#elif V == 16
typedef float16 floatv;
typedef int16 intv;
#define VLOAD vload16
#define VSTORE vstore16
void loadv(__global const float4 *p, floatv *x, floatv *y, floatv *z, floatv *w)
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
void storev(__global float4 *p, floatv x, floatv y, floatv z, floatv w)
{
    store4(p, x.lo.lo, y.lo.lo, z.lo.lo, w.lo.lo);
    store4(p + 4, x.lo.hi, y.lo.hi, z.lo.hi, w.lo.hi);
    store4(p + 8, x.hi.lo, y.hi.lo, z.hi.lo, w.hi.lo);
    store4(p + 12, x.hi.hi, y.hi.hi, z.hi.hi, w.hi.hi);
}
#else
#error "CLOTH_VECTOR_WIDTH must be 4, 8 or 16"
#endif

/* lanes first_lane .. V-1 of a to p[lane] (all of them with one store when first_lane = 0) */
void store_lanes(floatv a, int first_lane, __global float *p)
{
    if (first_lane == 0) {
        VSTORE(a, 0, p);
        return;
    }
    float lanes[V];
    VSTORE(a, 0, lanes);
    for (int l = first_lane; l < V; ++l)
        p[l] = lanes[l];
}

#if VECTORS_PER_ROW > 0
#define INTERIOR_VECTORS (VECTORS_PER_ROW * (N - 4))
/* One Jacobi pass for the V interior particles of vector t. */
void jacobi_vector(int t, __global const float4 *X, __global float4 *Y, __global const float *lam,
                   __global float *lam_out, int it, float4 rest, float4 at, float relax,
                   float omega)
{
    int first = it == 0;
    int vector = t % VECTORS_PER_ROW, last = vector == VECTORS_PER_ROW - 1;
    int i = (2 + t / VECTORS_PER_ROW) * N + (last ? N - 2 - V : 2 + V * vector);
    int first_lane = last ? LAST_FIRST_LANE : 0;
    floatv x, y, z, w;
    loadv(X + i, &x, &y, &z, &w);
    floatv cx = 0.0f, cy = 0.0f, cz = 0.0f; /* corr */
    float scale = relax / 12.0f; /* relax / cnt: all 12 constraints exist */
#pragma unroll
    for (int o = 0; o < 12; ++o) {
        int j = i + OFFSETS[o].x * N + OFFSETS[o].y;
        float rest_o = o < 4 ? rest.x : (o < 8 ? rest.y : rest.z);
        float at_o = o < 4 ? at.x : (o < 8 ? at.y : at.z);
        floatv xj, yj, zj, wj;
        loadv(X + j, &xj, &yj, &zj, &wj);
        floatv dx = x - xj, dy = y - yj, dz = z - zj;
#ifdef CLOTH_STRICT
        floatv L2 = (dx * dx + dy * dy) + dz * dz;
#else
        floatv L2 = dx * dx + dy * dy + dz * dz;
#endif
        floatv denom = (w + wj) + at_o;
        floatv lam_o = VLOAD(0, lam + o * N2 + i);
        lam_o = first ? (floatv)(0.0f) : lam_o;
#ifdef CLOTH_STRICT
        floatv L = sqrt(L2);
        floatv dl = ((-(L - rest_o)) - at_o * lam_o) / denom;
        floatv s = (w * dl) / L;
#else
        floatv inv_L = rsqrt(L2);
        floatv dl = (rest_o - L2 * inv_L - at_o * lam_o) / denom;
        floatv s = w * dl * inv_L;
#endif
        intv valid = (L2 > 0.0f) & (denom > 0.0f);
        s = select((floatv)(0.0f), s, valid);
        cx = cx + dx * s;
        cy = cy + dy * s;
        cz = cz + dz * s;
        floatv lam_new = lam_o + select((floatv)(0.0f), dl, valid) * scale;
#ifdef CLOTH_CHEBYSHEV
        if (it > 0) {
            floatv before = it == 1 ? (floatv)(0.0f) : VLOAD(0, lam_out + o * N2 + i);
            lam_new = omega * (lam_new - before) + before;
        }
#endif
        store_lanes(lam_new, first_lane, lam_out + o * N2 + i);
    }
    floatv yx = x + cx * scale, yy = y + cy * scale, yz = z + cz * scale;
#ifdef CLOTH_CHEBYSHEV
    if (it > 0) {
        floatv bx, by, bz, bw;
        loadv(Y + i, &bx, &by, &bz, &bw);
        yx = omega * (yx - bx) + bx;
        yy = omega * (yy - by) + by;
        yz = omega * (yz - bz) + bz;
    }
#endif
    if (first_lane == 0) {
        storev(Y + i, yx, yy, yz, w);
    } else {
        float lx[V], ly[V], lz[V], lw[V];
        VSTORE(yx, 0, lx);
        VSTORE(yy, 0, ly);
        VSTORE(yz, 0, lz);
        VSTORE(w, 0, lw);
        for (int l = first_lane; l < V; ++l)
            Y[i + l] = (float4)(lx[l], ly[l], lz[l], lw[l]);
    }
}

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
#else
#define INTERIOR_VECTORS 0
#endif

/* Constraint c of the coloured Gauss-Seidel pass: it joins ij[c] and updates both ends in
 * place; no two constraints of a batch share a particle (constraints.py). */
void coloured_constraint(int c, __global float4 *X, __global const int2 *ij, __global float *lam,
                         int first, float rest, float at)
{
    int2 e = ij[c];
    float4 xi = X[e.x], xj = X[e.y];
    float3 d = xi.xyz - xj.xyz;
    float L2 = dot3(d, d);
    float denom = (xi.w + xj.w) + at;
    float lam_c = first ? 0.0f : lam[c];
    float dlam = 0.0f;
    if (L2 > 0.0f && denom > 0.0f) {
#ifdef CLOTH_STRICT
        float L = sqrt(L2);
        dlam = ((-(L - rest)) - at * lam_c) / denom;
        X[e.x] = (float4)(xi.xyz + d * ((xi.w * dlam) / L), xi.w);
        X[e.y] = (float4)(xj.xyz - d * ((xj.w * dlam) / L), xj.w);
#else
        float inv_L = rsqrt(L2);
        dlam = (rest - L2 * inv_L - at * lam_c) / denom;
        float s = dlam * inv_L;
        X[e.x] = (float4)(xi.xyz + d * (xi.w * s), xi.w);
        X[e.y] = (float4)(xj.xyz - d * (xj.w * s), xj.w);
#endif
    }
    lam[c] = lam_c + dlam;
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

#if CLOTH_MESHES > 0
/* collide_mesh.cl holds, beside the scalar collide_meshes() used here, the lane-parallel forms
 * of verlet_cloth.cl's vector kernels; these are the names they are written with (unused here:
 * PBD collides one particle per work item). */
#define INLINE __attribute__((always_inline))
#define SELECT(a, b, c) ((c) ? (b) : (a))
typedef floatv floatv_u __attribute__((aligned(4)));
typedef intv intv_u __attribute__((aligned(4)));
/* The meshes: collide_meshes(x, rows, geometry, ints), only where the scene has them. */
#include <mesh_colliders>
#endif

/* collisions as position projections, free particles only: spheres, cylinders, planes, then
 * meshes (colliders: the substep's table) */
float4 collide_particle(float4 p, __constant float4 *colliders MESH_ARG)
{
    if (p.w == 0.0f)
        return p; /* pinned particles are never collided */
    float3 x = collide(p.xyz, colliders, CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_PLANES);
#if CLOTH_MESHES > 0
    x = collide_meshes(x, colliders + ANALYTIC_ROWS, mesh_geometry, mesh_ints);
#endif
    return (float4)(x, p.w);
}

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
void update_particle(int i, float4 p, __global float4 *x, __global float4 *v, float h, float damp)
{
    float3 vel = (p.xyz - x[i].xyz) / h;
    v[i] = (float4)(vel * damp, 0.0f);
    x[i] = p;
}

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
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* the first substep's poses; one table per substep */
#ifdef CLOTH_ATTACHED_PINS
    pin_target += 3 * CLOTH_PINS * step;
#endif
#endif
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
        for (int i = first_item; i < N2; i += stride) {
#if CLOTH_SPHERES + CLOTH_CYLINDERS + CLOTH_PLANES + CLOTH_MESHES > 0
            update_particle(i, collide_particle(X[i], colliders MESH_PASS), x, v, h, damp);
#else
            update_particle(i, X[i], x, v, h, damp);
#endif
        }
        barrier(CLK_GLOBAL_MEM_FENCE);
#ifdef CLOTH_PER_STEP
        colliders += TABLE_ROWS; /* the next substep's */
#ifdef CLOTH_ATTACHED_PINS
        pin_target += 3 * CLOTH_PINS;
#endif
#endif
    }
}
