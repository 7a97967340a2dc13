/*
 * One mass-spring cloth step, one CUDA thread per particle: the chapter's
 * verlet_cloth_kernel.cu (Game Engine Gems 2, section 22.7, after Listing 22.1).
 *
 * The step is defined operation by operation in docs/semantics.md; this kernel performs
 * those operations in that order and does not restate them. The launch is in Python
 * (clothbench/backends/cuda.py: PingPong), which owns the two pairs of buffers
 * (pos, pos_prev) x (in, out) and either swaps them or copies out to in after each step.
 *
 * Constants are kernel arguments, float32 values the host rounded once from float64
 * (docs/semantics.md, "Constants"), so one compiled kernel serves every scene.
 *
 * Two modes, chosen by the host's compile options (cuda.compile_options):
 *   CLOTH_STRICT defined: sqrtf and '/', built with --fmad=false --ftz=false
 *       --prec-div=true --prec-sqrt=true, so every operation is one correctly rounded
 *       IEEE float operation and the result equals the NumPy float32 reference bit for bit.
 *   otherwise (fast): rsqrtf for the spring and collision normalisation, built with
 *       --use_fast_math (contraction, flush-to-zero, approximate division); measured
 *       against the float64 reference instead.
 */

// A neighbour's offset in the grid: (row, column), as docs/semantics.md writes it.
struct Offset {
    int dr, dc;
};

// |d|^2 summed as (x*x + y*y) + z*z, the documented order (no dot(): its order is not ours).
__device__ __forceinline__ float length2(float3 d)
{
    return (d.x * d.x + d.y * d.y) + d.z * d.z;
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

// Section 22.3: a particle inside the sphere (centre xyz, radius w) is moved to the surface
// along the ray from the centre; one exactly at the centre has no ray and goes straight up.
__device__ __forceinline__ float3 collide_sphere(float3 x, float4 sphere)
{
    const float3 c = make_float3(sphere.x, sphere.y, sphere.z);
    const float r = sphere.w;
    const float3 d = make_float3(x.x - c.x, x.y - c.y, x.z - c.z);
    const float L2 = length2(d);
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

// Every collider, in scene order. Spheres only for now; other shapes get their own function.
__device__ __forceinline__ float3 collide(float3 x, const float4* spheres, int sphere_count)
{
    for (int s = 0; s < sphere_count; ++s) x = collide_sphere(x, spheres[s]);
    return x;
}

extern "C" __global__ void verlet_step(
    const float4* __restrict__ pos,       // x(t); w = inverse mass, 0 = pinned
    const float4* __restrict__ pos_prev,  // x(t - dt)
    float4* __restrict__ pos_out,         // x(t + dt)
    float4* __restrict__ pos_prev_out,    // x(t), the next step's previous position
    int n,                                // particles per side
    float dt, float dt2,                  // dt2 = dt*dt rounded once on the host
    float k, float b,                     // spring stiffness and damping
    float gx, float gy, float gz,         // gravity, an acceleration (differs: not scaled by 1/m)
    float rest_structural, float rest_shear, float rest_bend,  // |(dr, dc)| * h
    const float4* __restrict__ spheres,   // (centre, radius) per sphere, in scene order
    int sphere_count)
{
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * n) return;
    const int row = i / n;
    const int col = i % n;

    // steps 1-3: current and previous position, the lagged velocity, its damping term
    const float4 p = pos[i];
    const float4 q = pos_prev[i];
    const float3 x = make_float3(p.x, p.y, p.z);
    const float3 xp = make_float3(q.x, q.y, q.z);
    const float w = p.w;
    const float3 vel = make_float3((x.x - xp.x) / dt, (x.y - xp.y) / dt, (x.z - xp.z) / dt);
    const float3 bv = make_float3(b * vel.x, b * vel.y, b * vel.z);

    // step 4: springs only; gravity is an acceleration and joins in step 6 (differs)
    float3 force = make_float3(0.0f, 0.0f, 0.0f);

    // step 5: the 12-spring stencil in summation order (differs: row and column offsets
    // are not mixed as in the listing); a neighbour outside the grid adds nothing
    const Offset stencil[12] = {
        {0, -1}, {0, 1}, {-1, 0}, {1, 0},      // structural
        {-1, -1}, {-1, 1}, {1, -1}, {1, 1},    // shear
        {-2, -2}, {-2, 2}, {2, -2}, {2, 2},    // bend: the long diagonals, as the chapter's demo
    };
    const float rest[3] = {rest_structural, rest_shear, rest_bend};
#pragma unroll
    for (int o = 0; o < 12; ++o) {
        const int r = row + stencil[o].dr;
        const int c = col + stencil[o].dc;
        if (r < 0 || r >= n || c < 0 || c >= n) continue;
        const float4 pj = pos[r * n + c];
        const float3 d = make_float3(pj.x - x.x, pj.y - x.y, pj.z - x.z);
        const float s = spring_scale(length2(d), rest[o / 4], k);
        // damping -b*vel once per existing spring, as in the listing
        force.x += s * d.x - bv.x;
        force.y += s * d.y - bv.y;
        force.z += s * d.z - bv.z;
    }

    // step 6: position Verlet, then collisions; pinned particles (w = 0) do not move
    float3 x_new = x;
    if (w != 0.0f) {
        const float3 acc = make_float3(force.x * w + gx, force.y * w + gy, force.z * w + gz);
        x_new = make_float3((2.0f * x.x - xp.x) + acc.x * dt2,
                            (2.0f * x.y - xp.y) + acc.y * dt2,
                            (2.0f * x.z - xp.z) + acc.z * dt2);
        x_new = collide(x_new, spheres, sphere_count);
    }

    // steps 7-8: the new position, and the current one as the next step's previous
    pos_out[i] = make_float4(x_new.x, x_new.y, x_new.z, w);
    pos_prev_out[i] = make_float4(x.x, x.y, x.z, w);
}
