/* pbd_cloth.cl: the Position Based Dynamics (XPBD) cloth solver in OpenCL C, one kernel per
 * stage. The solver and the order of every operation are docs/pbd.md; the colliders are
 * docs/semantics.md. Host code: clothbench/backends/opencl/pbd.py.
 *
 * State (float4 per particle, w = inverse mass, 0 = pinned): x (positions x(t)), v (velocity,
 * w unused), and two predicted-position buffers that the Jacobi passes ping-pong.
 * The host enqueues, per substep, on an in-order queue (each launch sees the one before):
 *   pbd_predict                    x, v -> v, xs
 *   pbd_jacobi_interior + pbd_jacobi_border, x iterations: X -> Y (the host then swaps
 *                                  X and Y; see "Jacobi" below), or
 *   pbd_coloured x 12 x iterations one launch per batch of constraints sharing no particle
 *   pbd_collide                    xs, in place (only when the scene has colliders)
 *   pbd_update                     x, xs -> v, x
 *
 * Build options:
 *   CLOTH_N                                      grid side n (index arithmetic folds)
 *   CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_PLANES collider counts (0 when absent)
 *   CLOTH_VECTOR_WIDTH                           particles per work item of the Jacobi
 *                                                interior: 4, 8 or 16
 *   CLOTH_STRICT  every operation in the order docs/pbd.md fixes, no contraction, sqrt and
 *                 '/', no dot(): equal to the NumPy float32 reference bit for bit. Without
 *                 it (fast): one rsqrt per constraint, dot(), contraction (-cl-mad-enable).
 * Numbers (h, g*h, compliance/h^2, rest lengths, damping, relaxation) are kernel arguments,
 * rounded once to float32 on the host. The collider table and the colliders are collide.cl's
 * (included by the host, as verlet_cloth.cl includes it): spheres (centre, radius); cylinders
 * (start, length), (unit axis, radius), (radial_r, 0); planes (point, 0), (unit normal, 0).
 *
 * lambda: the Jacobi form keeps 12 per particle (lam[o * n2 + i], one for each end of a
 * constraint: both ends compute the same value), the coloured form one per constraint. A
 * kernel told `first` (the first pass of a substep) reads lambda as 0 instead of clearing it.
 */

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

/* predict: v += g*h, xs = x + v*h; pinned particles stay and have no velocity */
__kernel void pbd_predict(__global const float4 *x, __global float4 *v, __global float4 *xs,
                          const float h, const float4 gh)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded to a multiple of the work-group size */
    float4 p = x[i];
    if (p.w == 0.0f) {
        v[i] = (float4)(0.0f);
        xs[i] = p;
        return;
    }
    float3 vel = v[i].xyz + gh.xyz;
    v[i] = (float4)(vel, 0.0f);
    xs[i] = (float4)(p.xyz + vel * h, p.w);
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
void jacobi_particle(int i, __global const float4 *X, __global float4 *Y, __global float *lam,
                     int first, float4 rest, float4 at, float relax)
{
    int row = i / N, col = i % N;
    float4 xi = X[i];
    float w = xi.w;
    float cx = 0.0f, cy = 0.0f, cz = 0.0f; /* corr */
    int cnt = 0;
    for (int o = 0; o < 12; ++o) {
        int r = row + OFFSETS[o].x, c = col + OFFSETS[o].y;
        if (r < 0 || r >= N || c < 0 || c >= N)
            continue; /* outside the grid: not counted, nothing added */
        cnt = cnt + 1;
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
        lam[o * N2 + i] = lam_o + (valid ? dl : 0.0f);
    }
    float scale = relax / (float)cnt;
    Y[i] = (float4)(xi.x + cx * scale, xi.y + cy * scale, xi.z + cz * scale, w);
}

/* The particles of the index list, one per work item. */
__kernel void pbd_jacobi_border(__global const float4 *X, __global float4 *Y,
                                __global float *lam, const int first, const float4 rest,
                                const float4 at, const float relax,
                                __global const int *particles, const int count)
{
    int t = get_global_id(0);
    if (t >= count)
        return; /* the launch is padded to a multiple of the work-group size */
    jacobi_particle(particles[t], X, Y, lam, first, rest, at, relax);
}

/* The interior in vectors: V consecutive particles of a row per work item, their float4s
 * deinterleaved into x, y, z, w vectors. Explicit vectors because PoCL does not vectorise
 * this kernel across work items by itself: at n = 256 a pass took 2.5-3 ms in scalar form,
 * 0.8 ms with V = 16, strict or fast. IEEE arithmetic is per lane, so strict stays exact. */
#ifndef CLOTH_VECTOR_WIDTH
#define CLOTH_VECTOR_WIDTH 4
#endif
#define V CLOTH_VECTOR_WIDTH
#define VECTORS_PER_ROW ((N - 4) / V)

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

#if VECTORS_PER_ROW > 0
__kernel void pbd_jacobi_interior(__global const float4 *X, __global float4 *Y,
                                  __global float *lam, const int first, const float4 rest,
                                  const float4 at, const float relax)
{
    int t = get_global_id(0);
    if (t >= VECTORS_PER_ROW * (N - 4))
        return;
    int i = (2 + t / VECTORS_PER_ROW) * N + 2 + V * (t % VECTORS_PER_ROW);
    floatv x, y, z, w;
    loadv(X + i, &x, &y, &z, &w);
    floatv cx = 0.0f, cy = 0.0f, cz = 0.0f; /* corr */
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
        VSTORE(lam_o + select((floatv)(0.0f), dl, valid), 0, lam + o * N2 + i);
    }
    float scale = relax / 12.0f; /* relax / cnt: all 12 constraints exist */
    storev(Y + i, x + cx * scale, y + cy * scale, z + cz * scale, w);
}
#endif

/* One batch of the coloured Gauss-Seidel pass: constraint k joins ij[offset + k] and updates
 * both ends in place; no two constraints of a batch share a particle (constraints.py). */
__kernel void pbd_coloured(__global float4 *X, __global const int2 *ij, __global float *lam,
                           const int offset, const int count, const int first, const float rest,
                           const float at)
{
    int k = get_global_id(0);
    if (k >= count)
        return;
    int2 c = ij[offset + k];
    float4 xi = X[c.x], xj = X[c.y];
    float3 d = xi.xyz - xj.xyz;
    float L2 = dot3(d, d);
    float denom = (xi.w + xj.w) + at;
    float lam_c = first ? 0.0f : lam[offset + k];
    float dlam = 0.0f;
    if (L2 > 0.0f && denom > 0.0f) {
#ifdef CLOTH_STRICT
        float L = sqrt(L2);
        dlam = ((-(L - rest)) - at * lam_c) / denom;
        X[c.x] = (float4)(xi.xyz + d * ((xi.w * dlam) / L), xi.w);
        X[c.y] = (float4)(xj.xyz - d * ((xj.w * dlam) / L), xj.w);
#else
        float inv_L = rsqrt(L2);
        dlam = (rest - L2 * inv_L - at * lam_c) / denom;
        float s = dlam * inv_L;
        X[c.x] = (float4)(xi.xyz + d * (xi.w * s), xi.w);
        X[c.y] = (float4)(xj.xyz - d * (xj.w * s), xj.w);
#endif
    }
    lam[offset + k] = lam_c + dlam;
}

/* collisions as position projections, free particles only: spheres, cylinders, planes */
__kernel void pbd_collide(__global float4 *xs, __constant float4 *colliders)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    float4 p = xs[i];
    if (p.w == 0.0f)
        return; /* pinned particles are never collided */
    float3 x = collide(p.xyz, colliders, CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_PLANES);
    xs[i] = (float4)(x, p.w);
}

/* update: v = (xs - x) / h, damped; x = xs */
__kernel void pbd_update(__global float4 *x, __global float4 *v, __global const float4 *xs,
                         const float h, const float damp)
{
    int i = get_global_id(0);
    if (i >= N2)
        return;
    float4 p = xs[i];
    float3 vel = (p.xyz - x[i].xyz) / h;
    v[i] = (float4)(vel * damp, 0.0f);
    x[i] = p;
}
