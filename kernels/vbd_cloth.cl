/* vbd_cloth.cl: the VBD cloth solver (implicit Euler by Vertex Block Descent) in OpenCL C, one
 * kernel per stage. The solver and the order of every operation are docs/vbd.md; the colliders
 * are docs/semantics.md. Host code: clothbench/backends/opencl/vbd.py.
 *
 * State (float4 per particle, w = inverse mass, 0 = pinned): x (positions at the start of the
 * substep), v (velocity, w unused), xs (the iterate, swept in place), y (the inertial target).
 * Per substep, on an in-order queue (each launch sees the one before):
 *   vbd_predict                      x, v -> y, xs
 *   iterations x (vbd_sweep x 4 colours, then with Chebyshev vbd_chebyshev)
 *   vbd_collide                      xs, in place (only when the scene has colliders or meshes)
 *     or, with [self_collision]: self_cell_keys, self_sort_stage x stages, pbd_self_collision
 *                                    xs -> y, pushed apart, then collided (self_collision.cl)
 *   vbd_update                       x, xs (or y) -> v, x
 * That is the `gather` shape; the planes shapes (opencl/vbd.py, "The planes shapes" below) run
 *   vbd_predict_planes               x, v -> the planes of the iterate, y, x and the masses
 *   iterations x (vbd_sweep_vectors and vbd_sweep_rest x 4 colours, then with Chebyshev
 *                 vbd_chebyshev_planes)
 *   vbd_finish_planes                x, the iterate's planes -> collided, then v, x
 * A sweep launch updates the particles of one colour (docs/vbd.md, "Vertex colours"): no two
 * share a spring, so each reads only neighbours no other item of the launch writes, and the
 * launch order within a colour changes no bit.
 *
 * Build options:
 *   CLOTH_N                                      grid side n (index arithmetic folds)
 *   CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_BOXES, CLOTH_PLANES collider counts (0 when absent)
 *   CLOTH_MESHES, CLOTH_MESH_BVH, CLOTH_PER_STEP, CLOTH_ATTACHED_PINS, CLOTH_PINS
 *                    meshes, moving colliders and pins attached to a body, as in pbd_cloth.cl
 *                    (host: opencl/bodies.py): one collider table (and set of pin targets) per
 *                    substep, at its end; a launch is told the index `step` of its substep
 *   CLOTH_VECTOR_WIDTH  the planes shapes' lanes W (4, 8 or 16; 1: no planes kernels built)
 *   CLOTH_STRICT     every operation in docs/vbd.md's order, no contraction, sqrt and '/':
 *                    equal to the NumPy float32 reference bit for bit. Without it (fast): one
 *                    rsqrt per spring and contraction (-cl-mad-enable).
 * Numbers (h, g*h^2, m/h^2, b/h, k, rest lengths, Chebyshev weights) are kernel arguments,
 * rounded once to float32 on the host (backends/kernel_inputs.py VbdConstants). */

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
#define INLINE __attribute__((always_inline))
/* floats from one plane of the planes shapes' copies to the next: the grid and 16 more,
 * as a vector load of the last interior row's neighbours reads one float past its plane */
#define PLANE (N2 + 16)

#include "body_args.cl"
#define TABLE_ROWS (ANALYTIC_ROWS + MESH_ROWS * CLOTH_MESHES) /* a substep's collider table */

/* The 12-spring stencil (d_row, d_col) in the order docs/semantics.md fixes; offsets 0-3 are
 * structural, 4-7 shear, 8-11 bend (the .x, .y, .z of `rest`). */
__constant int2 OFFSETS[12] = {
    (int2)(0, -1), (int2)(0, 1), (int2)(-1, 0), (int2)(1, 0),
    (int2)(-1, -1), (int2)(-1, 1), (int2)(1, -1), (int2)(1, 1),
    (int2)(-2, -2), (int2)(-2, 2), (int2)(2, -2), (int2)(2, 2),
};

/* Offset o's rest length (the .x, .y, .z of `rest`: structural, shear, bend), and a spring's
 * s = k (1 - rest / L) from L^2: strict with sqrt and '/', fast with one rsqrt; of a float or
 * of a vector of them. */
#define REST_OF(o, rest) ((o) < 4 ? (rest).x : (o) < 8 ? (rest).y : (rest).z)
#ifdef CLOTH_STRICT
#define SPRING_SCALE(k, rl, L2) ((k) * (1.0f - (rl) / sqrt(L2)))
#else
#define SPRING_SCALE(k, rl, L2) ((k) * (1.0f - (rl) * rsqrt(L2)))
#endif

/* (a.x*b.x + a.y*b.y) + a.z*b.z: strict rounds each operation; fast may contract it (PoCL's
 * dot() on a float3 made the fast sweep 2x slower than strict, 2026-12-04) */
INLINE float dot3(float3 a, float3 b)
{
    return (a.x * b.x + a.y * b.y) + a.z * b.z;
}

#include "collide.cl"
/* one spring's terms and the LDL^T solve, shared with vbd_cloth.c and vbd_cloth.cu */
#define VBD_REAL float
#define VBD_FN INLINE
#include "vbd_newton.h"
#if CLOTH_MESHES > 0
/* collide_mesh.cl holds, beside the scalar collide_meshes() used here, the lane forms of
 * verlet_cloth.cl's vector kernels; one particle per work item is their one-lane case. */
#define V 1
typedef float floatv;
#include <mesh_colliders>
#endif
#include "collide_particle.cl"

/* predict: the inertial target y = (x + v*h) + g*h^2, which is also the first iterate; a pinned
 * particle stays (x), or, following a body, goes to its target at the end of the substep (y is
 * then never read: no sweep moves a pinned particle) */
INLINE float4 predicted(int i, __global const float4 *x, __global const float4 *v, const float h,
                        const float4 gh2 STEP_ARG PIN_ARG)
{
    float4 p = x[i];
    if (p.w == 0.0f) {
#ifdef CLOTH_ATTACHED_PINS
        pin_target += 3 * CLOTH_PINS * step; /* this substep's targets */
        int slot = pin_slot[i];
        if (slot >= 0)
            p = (float4)(pin_target[3 * slot], pin_target[3 * slot + 1], pin_target[3 * slot + 2], p.w);
#endif
        return p;
    }
    return (float4)((p.xyz + v[i].xyz * h) + gh2.xyz, p.w);
}

__kernel void vbd_predict(__global const float4 *x, __global const float4 *v, __global float4 *xs,
                          __global float4 *y, const float h, const float4 gh2 STEP_ARG PIN_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded to a multiple of the work-group size */
    y[i] = xs[i] = predicted(i, x, v, h, gh2 STEP_PASS PIN_PASS);
}

/* Particle j of the iterate: from the float4 rows X, or (X null: the planes shapes' scalar
 * launch) from the planes P. Every call passes a constant null for one of them, so each call
 * site compiles to one layout's load. */
INLINE float3 neighbour(__global const float4 *X, __global const float *P, int j)
{
    return X ? X[j].xyz : (float3)(P[j], P[PLANE + j], P[2 * PLANE + j]);
}

/* One free particle's 3x3 Newton step on the incremental potential, its neighbours (of other
 * colours) held: docs/vbd.md, "One particle's step", operation for operation. One walk with
 * bounds tests for every particle: with a second, unchecked walk for the interior behind a
 * branch, Intel's runtime ran both for every work item (its work-item vectoriser makes a
 * divergent branch both paths, masked): 2x the sweep's time (2026-12-05, Zen 4). */
INLINE float3 newton_step(int row, int col, float3 xi, __global const float4 *X, __global const float *P,
                          float3 yi, float3 x0, float mh2, float bh, float k, float4 rest)
{
    int cnt = 0; /* the springs the particle has: an exact small integer */
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        cnt += (r >= 0 && r < N && c >= 0 && c < N);
    }
    float cb = (float)cnt * bh;
    float hd = mh2 + cb;
    float3 f0 = (xi - yi) * mh2 + (xi - x0) * cb;
    float f[3] = {f0.x, f0.y, f0.z};
    float h[6] = {hd, hd, hd, 0.0f, 0.0f, 0.0f}; /* Hxx, Hyy, Hzz, Hxy, Hxz, Hyz */
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        if (r < 0 || r >= N || c < 0 || c >= N)
            continue;
        float3 d = xi - neighbour(X, P, r * N + c);
        float L2 = dot3(d, d);
        if (!(L2 > 0.0f))
            continue; /* coincident: nothing added */
        float s = SPRING_SCALE(k, REST_OF(o, rest), L2);
        vbd_add_spring(d.x, d.y, d.z, L2, s, k, f, h);
    }
    float px, py, pz;
    if (vbd_ldlt_solve(h[0], h[1], h[2], h[3], h[4], h[5], f[0], f[1], f[2], &px, &py, &pz))
        return xi - (float3)(px, py, pz);
    return xi; /* never for a finite state: H is positive definite */
}

/* One colour of a sweep, the `gather` shape: the particles order[first .. first + count - 1]
 * (every particle of the colour; a pinned one returns), one per work item, X in place. */
__kernel void vbd_sweep(__global float4 *X, __global const float4 *y, __global const float4 *x,
                        __global const int *order, const int first, const int count, const float mh2,
                        const float bh, const float k, const float4 rest)
{
    int t = get_global_id(0);
    if (t >= count)
        return;
    int i = order[first + t];
    float4 p = X[i];
    if (p.w == 0.0f)
        return;
    X[i] = (float4)(newton_step(i / N, i % N, p.xyz, X, 0, y[i].xyz, x[i].xyz, mh2, bh, k, rest), p.w);
}

/* Chebyshev (docs/vbd.md): with `apply`, X = omega (X - before) + before for the free
 * particles; then, applied or not, `before` takes X: the input of the next sweep, the one the
 * extrapolation after the sweep after it reads. */
__kernel void vbd_chebyshev(__global float4 *X, __global float4 *before, const float omega, const int apply)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    float4 p = X[i];
    if (apply && p.w != 0.0f) {
        float3 b = before[i].xyz;
        p = (float4)(omega * (p.xyz - b) + b, p.w);
        X[i] = p;
    }
    before[i] = p;
}

/* the colliders (collide_particle.cl: free particles only; the substep's table) */
INLINE float4 collided(float4 p, __constant float4 *colliders STEP_ARG MESH_ARG)
{
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this substep's poses */
#endif
    return collide_particle(p, colliders MESH_PASS);
}

__kernel void vbd_collide(__global float4 *xs, __constant float4 *colliders STEP_ARG MESH_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    xs[i] = collided(xs[i], colliders STEP_PASS MESH_PASS);
}

/* update from the final iterate p: v = (p - x) / h (no damping factor: the damping is in the
 * potential); x = p */
INLINE void update_particle(int i, __global float4 *x, __global float4 *v, float4 p, const float h)
{
    v[i] = (float4)((p.xyz - x[i].xyz) / h, 0.0f);
    x[i] = p;
}

__kernel void vbd_update(__global float4 *x, __global float4 *v, __global const float4 *xs, const float h)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    update_particle(i, x, v, xs[i], h);
}

/* --- The planes shapes: the sweeps on planar copies, VBD_W particles of a colour at a time ---
 * vbd_predict_planes writes the first iterate, y and x as planes (x, y, z; PLANE floats apart)
 * and the inverse masses as one plane; every sweep runs on those, and vbd_finish_planes
 * collides the final iterate and updates x and v from it. A colour's particles in an interior
 * row (rows and columns 2 .. n-3) are every other float of a plane, so VBD_W of them and each of their
 * neighbours are the even floats of 2 VBD_W consecutive ones: vbd_sweep_vectors takes every
 * interior particle of the colour, VBD_W consecutive ones per work item, the row's last vector
 * moved back to end at the row's last particle and storing only the lanes the one before it did
 * not (a lane's result depends on its own particle and its neighbours, of other colours, so
 * what it read of a particle the other work item was writing is dropped with the lane), in
 * rows with at least VBD_W of them; vbd_sweep_rest takes the colour's other particles (the
 * border, and every row of a narrower grid: opencl/vbd.py vector_rest), one per work item,
 * through an index list. Each lane does a scalar particle's operations in its order (the
 * coincident spring and the pinned particle by select), so a strict build stays bit-exact. */
#if CLOTH_VECTOR_WIDTH >= 4
#define VBD_W CLOTH_VECTOR_WIDTH
#define VBD_CAT_(a, b) a##b
#define VBD_CAT(a, b) VBD_CAT_(a, b)
typedef VBD_CAT(float, VBD_W) floatw;
typedef VBD_CAT(int, VBD_W) intw;
/* loads through a pointer to a 4-byte-aligned vector type (a typedef: PoCL 3.1 dropped the
 * attribute written in the cast, and its aligned load of an unaligned address faulted), the
 * ternary for select(): PoCL 3.0 (the wheel) calls the vloadn and select built-ins out of line
 * (verlet_cloth.cl) */
typedef float16 float16_u __attribute__((aligned(4)));
typedef float8 float8_u __attribute__((aligned(4)));
#define EVENS2(p, j, n) (*(__global const VBD_CAT(VBD_CAT(float, n), _u) *)((p) + (j))).even
#if VBD_W == 16
#define EVENS(p, j) ((float16)(EVENS2(p, j, 16), EVENS2(p, (j) + 16, 16)))
#elif VBD_W == 8
#define EVENS(p, j) EVENS2(p, j, 16)
#else
#define EVENS(p, j) EVENS2(p, j, 8)
#endif
/* the lanes' vbd_newton.h: the same text, floatw for float */
#undef VBD_REAL
#undef VBD_MASK
#define VBD_REAL floatw
#define VBD_MASK intw
#define vbd_add_spring vbd_add_spring_w
#define vbd_ldlt_solve vbd_ldlt_solve_w
#include "vbd_newton.h"
#undef vbd_add_spring
#undef vbd_ldlt_solve

/* the first interior column of colour (parity, bit) in `row`, and how many of its particles the
 * row's interior has */
#define FIRST_COLUMN(bit, row) (2 + (((bit) + (row) / 2) & 1))
#define INTERIOR_COUNT(first) (((N - 3) - (first)) / 2 + 1)

/* vec_type_hint: the kernel is vectors already; without it Intel's runtime vectorised it again
 * across work items, its sweeps 10-20% slower (docs/vbd.md, "Kernel shapes") */
__kernel __attribute__((vec_type_hint(floatw))) void
vbd_sweep_vectors(__global float *P, __global const float *Yp, __global const float *Xp, __global const float *Wp,
                  const int parity, const int bit, const float mh2, const float bh, const float k, const float4 rest)
{
    int row = 2 + parity + 2 * (int)get_global_id(1);
    int col = FIRST_COLUMN(bit, row);
    int t = get_global_id(0);
    int count = INTERIOR_COUNT(col);
    if (row > N - 3 || count < VBD_W || t >= (count + VBD_W - 1) / VBD_W)
        return; /* the launch covers the longest row's vectors; padding */
    int lane = min(VBD_W * t, count - VBD_W); /* the vector's first particle in the row's colour */
    int stored = VBD_W * t - lane;            /* its lanes before this: the previous vector's */
    int i = row * N + col + 2 * lane;
    floatw xx = EVENS(P, i), xy = EVENS(P, PLANE + i), xz = EVENS(P, 2 * PLANE + i);
    floatw cb = (float)12 * bh; /* an interior particle has all 12 springs */
    floatw hd = mh2 + cb;
    floatw f[3] = {(xx - EVENS(Yp, i)) * mh2 + (xx - EVENS(Xp, i)) * cb,
                   (xy - EVENS(Yp, PLANE + i)) * mh2 + (xy - EVENS(Xp, PLANE + i)) * cb,
                   (xz - EVENS(Yp, 2 * PLANE + i)) * mh2 + (xz - EVENS(Xp, 2 * PLANE + i)) * cb};
    floatw h[6] = {hd, hd, hd, (floatw)0.0f, (floatw)0.0f, (floatw)0.0f};
#pragma unroll
    for (int o = 0; o < 12; ++o) {
        int j = i + OFFSETS[o].x * N + OFFSETS[o].y;
        floatw dx = xx - EVENS(P, j), dy = xy - EVENS(P, PLANE + j), dz = xz - EVENS(P, 2 * PLANE + j);
        floatw L2 = (dx * dx + dy * dy) + dz * dz;
        floatw s = SPRING_SCALE(k, REST_OF(o, rest), L2);
        floatw fs[3] = {f[0], f[1], f[2]}, hs[6] = {h[0], h[1], h[2], h[3], h[4], h[5]};
        vbd_add_spring_w(dx, dy, dz, L2, s, (floatw)k, fs, hs);
        intw spring = L2 > 0.0f; /* coincident: nothing added, as the scalar walk's continue */
        for (int a = 0; a < 3; ++a)
            f[a] = spring ? fs[a] : f[a];
        for (int a = 0; a < 6; ++a)
            h[a] = spring ? hs[a] : h[a];
    }
    floatw px, py, pz;
    intw move = vbd_ldlt_solve_w(h[0], h[1], h[2], h[3], h[4], h[5], f[0], f[1], f[2], &px, &py, &pz);
    move = move & (EVENS(Wp, i) != 0.0f); /* a pinned particle stays */
    floatw out[3] = {move ? xx - px : xx, move ? xy - py : xy, move ? xz - pz : xz};
    for (int a = 0; a < 3; ++a) {
        const float *lanes = (const float *)&out[a]; /* stride 2: a lane at a time */
#pragma unroll
        for (int l = 0; l < VBD_W; ++l)
            if (l >= stored)
                P[a * PLANE + i + 2 * l] = lanes[l];
    }
}

/* the colour's particles no vector takes: order[first .. first + count - 1], one per work
 * item, planes in place */
__kernel void vbd_sweep_rest(__global float *P, __global const float *Yp, __global const float *Xp,
                             __global const float *Wp, __global const int *order, const int first, const int count,
                             const float mh2, const float bh, const float k, const float4 rest)
{
    int t = get_global_id(0);
    if (t >= count)
        return;
    int i = order[first + t];
    if (Wp[i] == 0.0f)
        return;
    int row = i / N, col = i % N;
    float3 xi = neighbour(0, P, i);
    float3 yi = neighbour(0, Yp, i), x0 = neighbour(0, Xp, i);
    float3 xn = newton_step(row, col, xi, 0, P, yi, x0, mh2, bh, k, rest);
    P[i] = xn.x;
    P[PLANE + i] = xn.y;
    P[2 * PLANE + i] = xn.z;
}

/* vbd_predict into planes: the first iterate and y (equal), x, and the inverse masses */
__kernel void vbd_predict_planes(__global const float4 *x, __global const float4 *v, __global float *P,
                                 __global float *Yp, __global float *Xp, __global float *Wp, const float h,
                                 const float4 gh2 STEP_ARG PIN_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    float4 p = predicted(i, x, v, h, gh2 STEP_PASS PIN_PASS), r = x[i];
    P[i] = Yp[i] = p.x, P[PLANE + i] = Yp[PLANE + i] = p.y, P[2 * PLANE + i] = Yp[2 * PLANE + i] = p.z;
    Xp[i] = r.x, Xp[PLANE + i] = r.y, Xp[2 * PLANE + i] = r.z;
    Wp[i] = p.w;
}

/* the final iterate from the planes, collided where the scene has colliders, then vbd_update */
__kernel void vbd_finish_planes(__global float4 *x, __global float4 *v, __global const float *P, const float h,
                                __constant float4 *colliders STEP_ARG MESH_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    float4 p = (float4)(P[i], P[PLANE + i], P[2 * PLANE + i], x[i].w);
#if ANALYTIC_ROWS + CLOTH_MESHES > 0
    p = collided(p, colliders STEP_PASS MESH_PASS);
#endif
    update_particle(i, x, v, p, h);
}

/* vbd_chebyshev on the planes (Before: the same layout), operation for operation */
__kernel void vbd_chebyshev_planes(__global float *P, __global float *Before, __global const float *Wp,
                                   const float omega, const int apply)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    for (int a = 0; a < 3; ++a) {
        float p = P[a * PLANE + i];
        if (apply && Wp[i] != 0.0f) {
            float b = Before[a * PLANE + i];
            p = omega * (p - b) + b;
            P[a * PLANE + i] = p;
        }
        Before[a * PLANE + i] = p;
    }
}
#endif

/* [self_collision] (docs/vbd.md), only where the scene has the table: self_collision.cl's pass
 * for float4 rows, pbd_self_collision (named for PBD, whose rows, collider tables and
 * collide_particle these are too), from the final iterate into y in place of vbd_collide. */
#define CLOTH_PBD
#include <self_collision>
