/* self_collision.cl: the [self_collision] pass of docs/semantics.md ("Self-collision"),
 * operation for operation, then the colliders, for verlet_cloth.cl (either build) and
 * pbd_cloth.cl (which defines CLOTH_PBD first). The host puts it in the source
 * (`#include <self_collision>`) only where the scene has the table. Verlet: with
 * CLOTH_SELF_COLLISION its kernels leave the colliders to `self_collision`, so they act after
 * the pass, as the definition places them. PBD: `pbd_self_collision` takes the place of
 * pbd_collide in the substep, after the last constraint iteration.
 *
 * One work item per particle reads the positions before the pass (x_in) and writes its own
 * (x_out): a Jacobi projection, race-free. The search is the definition's brute-force form,
 * every j in ascending order: the sum's order, hence the NumPy reference's bits, with no sort.
 *
 * Numbers (kernel_inputs.SelfCollisionConstants, rounded once on the host): thickness,
 * thickness2, relax, and the integer exclude2 (pairs closer than that on the grid at rest
 * are excluded like stencil neighbours).
 */

#if defined(CLOTH_GENERIC) || defined(CLOTH_PBD)
/* float4 rows, the inverse mass in w */
#define SC_STATE __global const float4 *
#define SC_X(s, j) ((s)[j].xyz)
#define SC_W(s, inv_mass, j) ((s)[j].w)
#else
/* x, y, z planes (the pointer past CLOTH_PAD), the inverse mass in its own buffer */
#include "collide.cl"
#define SC_STATE __global const float *
#define SC_X(s, j) ((float3)((s)[j], (s)[N2 + (j)], (s)[2 * N2 + (j)]))
#define SC_W(s, inv_mass, j) ((inv_mass)[j])
#endif

/* Whether particles (dr, dc) apart on the grid are joined by a spring (scene.OFFSETS) or
 * closer at rest than the thickness (dr^2 + dc^2 < exclude2). */
bool self_excluded(int dr, int dc, int exclude2)
{
    if (dr * dr + dc * dc < exclude2)
        return true;
    for (int o = 0; o < 12; ++o)
        if (OFFSETS[o].x == dr && OFFSETS[o].y == dc)
            return true;
    return false;
}

/* Particle i's position after the pass: x_i plus its pairs' corrections, summed in ascending j. */
float3 self_push(int i, int n, SC_STATE x_in, __global const float *inv_mass, float thickness,
                 float thickness2, float relax, int exclude2)
{
    float3 xi = SC_X(x_in, i);
    float wi = SC_W(x_in, inv_mass, i);
    if (!(wi > 0.0f))
        return xi; /* a pinned particle does not move */
    int row = i / n, col = i % n;
    float3 corr = (float3)(0.0f);
    bool pushed = false;
    for (int j = 0; j < n * n; ++j) {
        float3 d = xi - SC_X(x_in, j);
        float L2 = (d.x * d.x + d.y * d.y) + d.z * d.z; /* not dot(): its order is the driver's */
        /* j == i has L2 = 0; coincident particles have no direction: nothing added */
        if (!(L2 < thickness2) || !(L2 > 0.0f) || self_excluded(j / n - row, j % n - col, exclude2))
            continue;
        float wj = SC_W(x_in, inv_mass, j);
        float L = sqrt(L2);
        float share = wi / (wi + wj); /* i's part of the shortfall, by inverse mass */
        float s = relax * (thickness - L);
        s = s * share;
        s = s / L;
        corr = corr + d * s;
        pushed = true;
    }
    return pushed ? xi + corr : xi;
}

#if defined(CLOTH_PBD)
__kernel void pbd_self_collision(__global const float4 *xs_in, __global float4 *xs_out,
                                 const float thickness, const float thickness2, const float relax,
                                 const int exclude2, __constant float4 *colliders STEP_ARG MESH_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded when the work-group size does not divide n*n */
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this substep's poses */
#endif
    float3 x = self_push(i, N, xs_in, 0, thickness, thickness2, relax, exclude2);
    xs_out[i] = collide_particle((float4)(x, xs_in[i].w), colliders MESH_PASS); /* then the colliders */
}
#elif defined(CLOTH_GENERIC)
__kernel void self_collision(__global const float4 *x_in, __global float4 *x_out, const int n,
                             const float thickness, const float thickness2, const float relax,
                             const int exclude2, __constant float4 *colliders, const int num_spheres,
                             const int num_cylinders, const int num_planes BODY_ARG)
{
    int i = get_global_id(0);
    if (i >= n * n)
        return; /* the launch is padded when the work-group size does not divide n*n */
    int analytic_rows = num_spheres + 3 * num_cylinders + 2 * num_planes;
#ifdef CLOTH_PER_STEP
    colliders += step * (analytic_rows + MESH_ROWS * CLOTH_MESHES); /* this step's poses */
#endif
    float w = x_in[i].w;
    float3 x = self_push(i, n, x_in, 0, thickness, thickness2, relax, exclude2);
    if (w != 0.0f) { /* then the colliders, as the Verlet kernel would have */
        x = collide(x, colliders, num_spheres, num_cylinders, num_planes);
#if CLOTH_MESHES > 0
        x = collide_meshes(x, colliders + analytic_rows, mesh_geometry, mesh_ints); /* after the planes */
#endif
    }
    x_out[i] = (float4)(x, w);
}
#else
__kernel void self_collision(__global const float *x_in, __global const float *inv_mass,
                             __global float *x_out, const float thickness, const float thickness2,
                             const float relax, const int exclude2, __constant float4 *colliders BODY_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded when the work-group size does not divide n*n */
    x_in += PAD, x_out += PAD;
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this step's poses */
#endif
    float w = inv_mass[i];
    float3 x = self_push(i, N, x_in, inv_mass, thickness, thickness2, relax, exclude2);
    if (w != 0.0f) { /* then the colliders, as the Verlet kernels would have */
        x = collide(x, colliders, CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_PLANES);
#if CLOTH_MESHES > 0
        x = collide_meshes(x, colliders + ANALYTIC_ROWS, mesh_geometry, mesh_ints); /* after the planes */
#endif
    }
    x_out[i] = x.x, x_out[N2 + i] = x.y, x_out[2 * N2 + i] = x.z;
}
#endif
