/*
 * The VBD cloth solver (implicit Euler by Vertex Block Descent) in CUDA, one kernel per stage.
 * The solver and the order of every operation are docs/vbd.md; the colliders are
 * docs/semantics.md's, performed by collide.cuh, the code verlet_cloth.cu collides with.
 * Host code: clothbench/backends/cuda/vbd.py (VbdLaunches, CudaVbdBackend).
 *
 * State (float4 per particle, w = inverse mass, 0 = pinned): x (positions at the start of the
 * substep), v (velocity, w unused), xs (the iterate, swept in place), y (the inertial target).
 * Per substep, on one stream (each launch sees the one before):
 *   vbd_predict                      x, v -> y, xs
 *   iterations x (vbd_sweep x 4 colours, then with Chebyshev vbd_chebyshev)
 *   vbd_collide                      xs, in place (only when the scene has colliders or meshes)
 *   vbd_update                       x, xs -> v, x
 * With [self_collision] (-DCLOTH_SELF_COLLISION: self_collision.cuh, the Verlet kernel's pass)
 * the pass and then the colliders take vbd_collide's place, from xs into y (no longer read),
 * and vbd_update reads y (docs/vbd.md, "Self-collision"). Without it there is no pass code.
 * A sweep launch updates the particles of one colour (docs/vbd.md, "Vertex colours"): no two
 * share a spring, so each reads only neighbours no other thread of the launch writes, and the
 * order of the threads within a colour changes no bit.
 *
 * Built for one scene (clothbench/backends/cuda/vbd.py: vbd_defines): CLOTH_N, the collider
 * counts and rows, meshes and motion as collide.cuh takes them; in a moving scene each launch
 * that reads them takes its substep's rows (`step_rows`, at the end of the substep) and the
 * pin slots. There is no generic build. The numbers (h, g h^2, m/h^2, b/h, k, rest lengths,
 * Chebyshev weights) are kernel arguments, rounded once on the host (model/kernel_inputs.py
 * VbdConstants).
 *
 *   CLOTH_STRICT  sqrtf and '/', built with --fmad=false --ftz=false --prec-div=true
 *                 --prec-sqrt=true: every operation one correctly rounded float operation, in
 *                 docs/vbd.md's order, so NumPy's float32 VBD bit for bit. Otherwise (fast):
 *                 one rsqrtf per spring, built with --use_fast_math.
 */

#ifdef CLOTH_GENERIC
#error "vbd_cloth.cu has no generic build: build it with the scene's -D values (cuda/vbd.py: vbd_defines)"
#endif
#ifndef CLOTH_N
#error "build with the scene's -D values (clothbench.backends.cuda.vbd.vbd_defines)"
#endif
constexpr int n = CLOTH_N;

#include "collide.cuh"
// one spring's terms and the LDL^T solve, shared with vbd_cloth.c and vbd_cloth.cl
#define VBD_REAL float
#define VBD_FN __device__ __forceinline__
#include "vbd_newton.h"

#if HAS_PIN_TARGETS
#define PREDICT_PARAMS , const float4* __restrict__ step_rows PIN_PARAMS
#else
#define PREDICT_PARAMS
#endif

// predict: the inertial target y = (x + v*h) + g*h^2 and the first iterate xs = y; a pinned
// particle stays (xs = x), or, following a body, goes to its target at the end of the substep
// (y is then never read: no sweep moves a pinned particle)
extern "C" __global__ void vbd_predict(const float4* __restrict__ x, const float4* __restrict__ v,
                                       float4* __restrict__ xs, float4* __restrict__ y, float h, float gx,
                                       float gy, float gz PREDICT_PARAMS)
{
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * n) return;  // the launch is padded to whole blocks
    float4 p = x[i];
    if (p.w == 0.0f) {
#if HAS_PIN_TARGETS
        const int slot = pin_slot[i];
        if (slot >= 0) {
            const float4 target = PIN_TARGETS[slot];
            p = make_float4(target.x, target.y, target.z, p.w);
        }
#endif
        xs[i] = p;
        y[i] = p;
        return;
    }
    const float4 q = v[i];
    const float4 target = make_float4((p.x + q.x * h) + gx, (p.y + q.y * h) + gy, (p.z + q.z * h) + gz, p.w);
    y[i] = target;
    xs[i] = target;
}

// One free particle's 3x3 Newton step on the incremental potential, its neighbours (of other
// colours) held: docs/vbd.md, "One particle's step", operation for operation.
__device__ __forceinline__ float3 newton_step(int i, float3 xi, const float4* X, float3 yi, float3 x0, float mh2,
                                              float bh, float k, float rest_structural, float rest_shear,
                                              float rest_bend)
{
    const Offset stencil[12] = STENCIL;  // collide.cuh: docs/semantics.md's order
    const float rest[3] = {rest_structural, rest_shear, rest_bend};
    const int row = i / n, col = i % n;
    int cnt = 0;  // the springs the particle has: an exact small integer
#pragma unroll
    for (int o = 0; o < 12; ++o) cnt += inside_grid(row + stencil[o].dr, col + stencil[o].dc, n);
    const float cb = (float)cnt * bh;
    const float hd = mh2 + cb;
    float f[3] = {(xi.x - yi.x) * mh2 + (xi.x - x0.x) * cb, (xi.y - yi.y) * mh2 + (xi.y - x0.y) * cb,
                  (xi.z - yi.z) * mh2 + (xi.z - x0.z) * cb};
    float h[6] = {hd, hd, hd, 0.0f, 0.0f, 0.0f};  // Hxx, Hyy, Hzz, Hxy, Hxz, Hyz
#pragma unroll
    for (int o = 0; o < 12; ++o) {
        const int r = row + stencil[o].dr, c = col + stencil[o].dc;
        if (!inside_grid(r, c, n)) continue;
        const float4 pj = X[r * n + c];
        const float3 d = make_float3(xi.x - pj.x, xi.y - pj.y, xi.z - pj.z);
        const float L2 = dot3(d, d);
        if (!(L2 > 0.0f)) continue;  // coincident: nothing added
#ifdef CLOTH_STRICT
        const float s = k * (1.0f - rest[o / 4] / sqrtf(L2));
#else
        const float s = k * (1.0f - rest[o / 4] * rsqrtf(L2));
#endif
        vbd_add_spring(d.x, d.y, d.z, L2, s, k, f, h);
    }
    float px, py, pz;
    if (vbd_ldlt_solve(h[0], h[1], h[2], h[3], h[4], h[5], f[0], f[1], f[2], &px, &py, &pz))
        return make_float3(xi.x - px, xi.y - py, xi.z - pz);
    return xi;  // never for a finite state: H is positive definite
}

// One colour of a sweep: the particles order[first .. first + count - 1] (every particle of
// the colour; a pinned one returns), each one Newton step, X in place. X has no __restrict__:
// a thread reads its neighbours' entries and writes its own.
extern "C" __global__ void vbd_sweep(float4* X, const float4* __restrict__ y, const float4* __restrict__ x,
                                     const int* __restrict__ order, int first, int count, float mh2, float bh,
                                     float k, float rest_structural, float rest_shear, float rest_bend)
{
    const int t = blockIdx.x * blockDim.x + threadIdx.x;
    if (t >= count) return;
    const int i = order[first + t];
    const float4 p = X[i];
    if (p.w == 0.0f) return;
    const float4 yi = y[i], x0 = x[i];
    const float3 q = newton_step(i, make_float3(p.x, p.y, p.z), X, make_float3(yi.x, yi.y, yi.z),
                                 make_float3(x0.x, x0.y, x0.z), mh2, bh, k, rest_structural, rest_shear, rest_bend);
    X[i] = make_float4(q.x, q.y, q.z, p.w);
}

// Chebyshev (docs/vbd.md): with `apply`, X = omega (X - before) + before for the free
// particles; then, applied or not, `before` takes X: the input of the next sweep, the one the
// extrapolation after the sweep after it reads.
extern "C" __global__ void vbd_chebyshev(float4* __restrict__ X, float4* __restrict__ before, float omega, int apply)
{
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * n) return;
    float4 p = X[i];
    if (apply && p.w != 0.0f) {
        const float4 b = before[i];
        p = make_float4(omega * (p.x - b.x) + b.x, omega * (p.y - b.y) + b.y, omega * (p.z - b.z) + b.z, p.w);
        X[i] = p;
    }
    before[i] = p;
}

// collisions as position projections, free particles only: collide.cuh's, every collider in
// the fixed order (a moving scene: the substep's rows)
extern "C" __global__ void vbd_collide(float4* __restrict__ xs MESH_PARAMS ROWS_PARAM)
{
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * n) return;
    const float4 p = xs[i];
    if (p.w == 0.0f) return;  // pinned particles are never collided
    const float3 q = apply_colliders(make_float3(p.x, p.y, p.z) MESH_ARGS ROWS_ARG);
    xs[i] = make_float4(q.x, q.y, q.z, p.w);
}

// update: v = (xs - x) / h (no damping factor: the damping is in the potential); x = xs
extern "C" __global__ void vbd_update(float4* __restrict__ x, float4* __restrict__ v, const float4* __restrict__ xs,
                                      float h)
{
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * n) return;
    const float4 p = xs[i], q = x[i];
    v[i] = make_float4((p.x - q.x) / h, (p.y - q.y) / h, (p.z - q.z) / h, 0.0f);
    x[i] = p;
}

#ifdef CLOTH_SELF_COLLISION
#include "self_collision.cuh"
#endif
