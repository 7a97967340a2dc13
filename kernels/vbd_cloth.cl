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

#include "body_args.cl"
#define TABLE_ROWS (ANALYTIC_ROWS + MESH_ROWS * CLOTH_MESHES) /* a substep's collider table */

/* The 12-spring stencil (d_row, d_col) in the order docs/semantics.md fixes; offsets 0-3 are
 * structural, 4-7 shear, 8-11 bend (the .x, .y, .z of `rest`). */
__constant int2 OFFSETS[12] = {
    (int2)(0, -1), (int2)(0, 1), (int2)(-1, 0), (int2)(1, 0),
    (int2)(-1, -1), (int2)(-1, 1), (int2)(1, -1), (int2)(1, 1),
    (int2)(-2, -2), (int2)(-2, 2), (int2)(2, -2), (int2)(2, 2),
};

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

/* predict: the inertial target y = (x + v*h) + g*h^2 and the first iterate xs = y; a pinned
 * particle stays (xs = x), or, following a body, goes to its target at the end of the substep
 * (y is then never read: no sweep moves a pinned particle) */
__kernel void vbd_predict(__global const float4 *x, __global const float4 *v, __global float4 *xs,
                          __global float4 *y, const float h, const float4 gh2 STEP_ARG PIN_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded to a multiple of the work-group size */
    float4 p = x[i];
    if (p.w == 0.0f) {
#ifdef CLOTH_ATTACHED_PINS
        pin_target += 3 * CLOTH_PINS * step; /* this substep's targets */
        int slot = pin_slot[i];
        if (slot >= 0)
            p = (float4)(pin_target[3 * slot], pin_target[3 * slot + 1], pin_target[3 * slot + 2], p.w);
#endif
        xs[i] = p;
        y[i] = p;
        return;
    }
    float3 target = (p.xyz + v[i].xyz * h) + gh2.xyz;
    y[i] = xs[i] = (float4)(target, p.w);
}

/* One free particle's 3x3 Newton step on the incremental potential, its neighbours (of other
 * colours) held: docs/vbd.md, "One particle's step", operation for operation. */
INLINE float3 newton_step(int i, float3 xi, __global const float4 *X, float3 yi, float3 x0, float mh2,
                          float bh, float k, float4 rest)
{
    int row = i / N, col = i % N;
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
        float3 d = xi - X[r * N + c].xyz;
        float L2 = dot3(d, d);
        if (!(L2 > 0.0f))
            continue; /* coincident: nothing added */
        float rl = o < 4 ? rest.x : o < 8 ? rest.y : rest.z;
#ifdef CLOTH_STRICT
        float s = k * (1.0f - rl / sqrt(L2));
#else
        float s = k * (1.0f - rl * rsqrt(L2));
#endif
        vbd_add_spring(d.x, d.y, d.z, L2, s, k, f, h);
    }
    float px, py, pz;
    if (vbd_ldlt_solve(h[0], h[1], h[2], h[3], h[4], h[5], f[0], f[1], f[2], &px, &py, &pz))
        return xi - (float3)(px, py, pz);
    return xi; /* never for a finite state: H is positive definite */
}

/* One colour of a sweep: the particles order[first .. first + count - 1] (every particle of
 * the colour; a pinned one returns), each one Newton step, X in place. */
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
    X[i] = (float4)(newton_step(i, p.xyz, X, y[i].xyz, x[i].xyz, mh2, bh, k, rest), p.w);
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

/* the colliders, in place (collide_particle.cl: free particles only; the substep's table) */
__kernel void vbd_collide(__global float4 *xs, __constant float4 *colliders STEP_ARG MESH_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this substep's poses */
#endif
    xs[i] = collide_particle(xs[i], colliders MESH_PASS);
}

/* update: v = (xs - x) / h (no damping factor: the damping is in the potential); x = xs */
__kernel void vbd_update(__global float4 *x, __global float4 *v, __global const float4 *xs, const float h)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    float4 p = xs[i];
    v[i] = (float4)((p.xyz - x[i].xyz) / h, 0.0f);
    x[i] = p;
}

/* [self_collision] (docs/vbd.md), only where the scene has the table: self_collision.cl's pass
 * for float4 rows, pbd_self_collision (named for PBD, whose rows, collider tables and
 * collide_particle these are too), from the final iterate into y in place of vbd_collide. */
#define CLOTH_PBD
#include <self_collision>
