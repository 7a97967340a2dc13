/* collide_mesh.cl: the triangle-mesh collider of docs/semantics.md ("Triangle mesh"),
 * operation for operation, on one float3 position. kernels/verlet_cloth.cl includes it
 * (`#include <mesh_colliders>`, resolved by the host) only when the scene has meshes, so a
 * scene without them has none of this code in its source. Host: clothbench/backends/opencl/verlet.py.
 *
 * The including file defines dot3(a, b) = (a.x*b.x + a.y*b.y) + a.z*b.z and MESH_ROWS (6) first,
 * and the build sets CLOTH_MESHES (how many meshes) and, for the accelerated algorithm,
 * CLOTH_MESH_BVH.
 *
 * Per mesh, MESH_ROWS = six rows of the collider table (per step when the scene moves), after the planes:
 *   (R row 0, margin), (R row 1, margin2), (R row 2, closed ? 1 : 0), (T, 0), (box lo, 0), (box hi, 0)
 * R and T the pose (x = R p + T), the box that of every body-frame corner.
 * mesh_geometry (float4 rows, uploaded once, never rebuilt when the mesh moves):
 *   corners a, b, c of every triangle of every mesh, three rows each, from row 0;
 *   the seven pseudo-normals (face, a, b, c, ab, ac, bc) of each, from row mesh_ints[0];
 *   the BVH nodes, two rows each, from row mesh_ints[1]: (lo, child as int bits; -1 a leaf),
 *   (hi, first * 8 + count as int bits: the leaf's run of the triangle list).
 * mesh_ints: [normals row, nodes row], then per mesh (first triangle, triangles, first node,
 * first entry of its triangle list), then the triangle lists (the BVH's leaf order, indices
 * within the mesh).
 *
 * The specialised build's vector kernels run the naive search across their V lanes at once
 * (closest_point_v, collide_mesh_v: select() for the regions), the BVH lane by lane (its
 * path differs per particle); every lane does the scalar code's operations in its order.
 */

#define MESH_STACK 33 /* colliders/mesh.py MAX_STACK + 1: the host refuses deeper BVHs */

/* NumPy's maximum and minimum: of two equal values the second, so 0.0 against -0.0 gives
 * NumPy's zero (fmax/fmin may give either; the clamped point's zero sign reaches x_new) */
float max_np(float a, float b)
{
    return a > b ? a : b;
}

float min_np(float a, float b)
{
    return a < b ? a : b;
}

float3 max3_np(float3 a, float3 b)
{
    return (float3)(max_np(a.x, b.x), max_np(a.y, b.y), max_np(a.z, b.z));
}

float3 min3_np(float3 a, float3 b)
{
    return (float3)(min_np(a.x, b.x), min_np(a.y, b.y), min_np(a.z, b.z));
}

/* Squared distance from p to the box lo..hi: g = max(max(lo - p, p - hi), 0), dot(g, g). */
float box_distance2(float3 p, float3 lo, float3 hi)
{
    float3 g = max3_np(max3_np(lo - p, p - hi), (float3)(0.0f));
    return dot3(g, g);
}

/* Ericson's ClosestPtPointTriangle with the guards and the clamp of docs/semantics.md: the
 * closest point to p on triangle a, b, c, and in *feature the index of its region's
 * pseudo-normal (face 0, a 1, b 2, c 3, ab 4, ac 5, bc 6). */
float3 closest_point(float3 p, float3 a, float3 b, float3 c, int *feature)
{
    float3 ab = b - a, ac = c - a, ap = p - a;
    float d1 = dot3(ab, ap), d2 = dot3(ac, ap);
    float3 bp = p - b;
    float d3 = dot3(ab, bp), d4 = dot3(ac, bp);
    float vc = d1 * d4 - d3 * d2;
    float3 cp = p - c;
    float d5 = dot3(ab, cp), d6 = dot3(ac, cp);
    float vb = d5 * d2 - d1 * d6;
    float va = d3 * d6 - d5 * d4;
    float e43 = d4 - d3, e56 = d5 - d6;
    float3 q;
    if (d1 <= 0.0f && d2 <= 0.0f) {
        q = a, *feature = 1;
    } else if (d3 >= 0.0f && d4 <= d3) {
        q = b, *feature = 2;
    } else if (vc <= 0.0f && d1 >= 0.0f && d3 <= 0.0f) {
        float s = d1 - d3;
        float v = s > 0.0f ? d1 / s : 0.0f; /* an edge shorter than the rounding: q = a */
        q = a + ab * v, *feature = 4;
    } else if (d6 >= 0.0f && d5 <= d6) {
        q = c, *feature = 3;
    } else if (vb <= 0.0f && d2 >= 0.0f && d6 <= 0.0f) {
        float s = d2 - d6;
        float w = s > 0.0f ? d2 / s : 0.0f;
        q = a + ac * w, *feature = 5;
    } else if (va <= 0.0f && e43 >= 0.0f && e56 >= 0.0f) {
        float s = e43 + e56;
        float w = s > 0.0f ? e43 / s : 0.0f;
        q = b + (c - b) * w, *feature = 6;
    } else { /* the face: va, vb, vc > 0, so s >= vb, vc > 0 and no infinity */
        float s = (va + vb) + vc;
        float v = vb / s, w = vc / s;
        q = (a + ab * v) + ac * w, *feature = 0;
    }
    /* into the triangle's box: the BVH's pruning bound then holds by construction */
    return min3_np(max3_np(q, min3_np(min3_np(a, b), c)), max3_np(max3_np(a, b), c));
}

/* The squared distance from p to triangle t's closest point. */
float triangle_distance2(float3 p, __global const float4 *corners, int t)
{
    int feature;
    float3 e = p - closest_point(p, corners[3 * t].xyz, corners[3 * t + 1].xyz, corners[3 * t + 2].xyz, &feature);
    return dot3(e, e);
}

/* Mesh m against body-frame point p: *best and the return value are the squared distance and
 * index of the closest triangle (ties to the lower index), -1 when none is finite. */
int closest_triangle(float3 p, __global const float4 *geometry, __global const int *mesh_ints,
                     int m, float *best_out)
{
    __global const int *info = mesh_ints + 2 + 4 * m;
    __global const float4 *corners = geometry + 3 * info[0];
    float best = INFINITY;
    int k = -1;
#ifdef CLOTH_MESH_BVH
    /* The host's BVH, nearer child first; a node is skipped only when its box is strictly
     * farther than the best so far: none of its triangles could win, not even a tie
     * (docs/semantics.md), so this ends on the naive loop's triangle, bit for bit. */
    __global const float4 *nodes = geometry + mesh_ints[1] + 2 * info[2];
    __global const int *tris = mesh_ints + info[3];
    int stack[MESH_STACK];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
        int node = stack[--top];
        float4 lo = nodes[2 * node], hi = nodes[2 * node + 1];
        if (box_distance2(p, lo.xyz, hi.xyz) > best)
            continue;
        int child = as_int(lo.w);
        if (child >= 0) {
            int near = child, far = child + 1;
            float near2 = box_distance2(p, nodes[2 * near].xyz, nodes[2 * near + 1].xyz);
            float far2 = box_distance2(p, nodes[2 * far].xyz, nodes[2 * far + 1].xyz);
            if (far2 < near2)
                near = child + 1, far = child;
            stack[top++] = far; /* the nearer popped first: the order is speed, not results */
            stack[top++] = near;
            continue;
        }
        int run = as_int(hi.w), first = run >> 3, count = run & 7;
        for (int j = first; j < first + count; ++j) {
            int t = tris[j];
            float d2 = triangle_distance2(p, corners, t);
            if (d2 < best || (d2 == best && t < k)) /* leaves are not in index order */
                best = d2, k = t;
        }
    }
#else
    /* naive: every triangle, in index order; a tie keeps the lower index */
    int triangles = info[1];
    for (int t = 0; t < triangles; ++t) {
        float d2 = triangle_distance2(p, corners, t);
        if (d2 < best)
            best = d2, k = t;
    }
#endif
    *best_out = best;
    return k;
}

/* One mesh (its six table rows) against world point x; x unchanged unless pushed. */
float3 collide_mesh(float3 x, __constant float4 *rows, __global const float4 *geometry,
                    __global const int *mesh_ints, int m)
{
    float4 r0 = rows[0], r1 = rows[1], r2 = rows[2], tr = rows[3];
    float margin = r0.w, margin2 = r1.w;
    float3 d = x - tr.xyz;
    /* p = R^T d, each component (R[0][i]*d.x + R[1][i]*d.y) + R[2][i]*d.z */
    float3 p = (float3)((r0.x * d.x + r1.x * d.y) + r2.x * d.z, (r0.y * d.x + r1.y * d.y) + r2.y * d.z,
                        (r0.z * d.x + r1.z * d.y) + r2.z * d.z);
    if (!(box_distance2(p, rows[4].xyz, rows[5].xyz) <= margin2))
        return x; /* farther than the margin from the mesh's box (or not a number) */
    float best;
    int k = closest_triangle(p, geometry, mesh_ints, m, &best);
    if (k < 0)
        return x; /* no finite distance: a non-finite p */
    int t = mesh_ints[2 + 4 * m] + k, feature;
    float3 q = closest_point(p, geometry[3 * t].xyz, geometry[3 * t + 1].xyz, geometry[3 * t + 2].xyz, &feature);
    float3 n = geometry[mesh_ints[0] + 7 * t + feature].xyz;
    float3 e = p - q;
    float side = dot3(e, n);
    int push = r2.w != 0.0f ? (side < 0.0f || best < margin2) /* closed: inside, or within the margin */
                            : (side < 0.0f && best < margin2); /* open: in the skin under it */
    if (!push)
        return x; /* a particle not pushed keeps its own bits */
    float3 y = q + n * margin;
    /* x = R y + T, each component ((R[i][0]*y.x + R[i][1]*y.y) + R[i][2]*y.z) + T.i */
    return (float3)(((r0.x * y.x + r0.y * y.y) + r0.z * y.z) + tr.x, ((r1.x * y.x + r1.y * y.y) + r1.z * y.z) + tr.y,
                    ((r2.x * y.x + r2.y * y.y) + r2.z * y.z) + tr.z);
}

/* Every mesh, in file order, after the analytic colliders: `rows` is the first mesh's row. */
float3 collide_meshes(float3 x, __constant float4 *rows, __global const float4 *geometry,
                      __global const int *mesh_ints)
{
    for (int m = 0; m < CLOTH_MESHES; ++m)
        x = collide_mesh(x, rows + MESH_ROWS * m, geometry, mesh_ints, m);
    return x;
}

#ifndef CLOTH_GENERIC
#if V > 1 && !defined(CLOTH_MESH_BVH)
/* ---- The naive search across the lanes: every lane tests the same triangle at once, as a
 * GPU's SIMD group does (NvCloth, the compute-shader PBD), the regions chosen by select();
 * each lane's value is the scalar code's operations in its order, so the same bits. ---- */
INLINE floatv max_np_v(floatv a, floatv b)
{
    return SELECT(b, a, a > b); /* max_np per lane */
}

INLINE floatv min_np_v(floatv a, floatv b)
{
    return SELECT(b, a, a < b);
}

/* closest_point() for V points p against one triangle: *q and *feature per lane */
INLINE void closest_point_v(floatv px, floatv py, floatv pz, float3 a, float3 b, float3 c, floatv *qx,
                            floatv *qy, floatv *qz, intv *feature)
{
    float3 ab = b - a, ac = c - a, cb = c - b;
    floatv apx = px - a.x, apy = py - a.y, apz = pz - a.z;
    floatv d1 = (ab.x * apx + ab.y * apy) + ab.z * apz, d2 = (ac.x * apx + ac.y * apy) + ac.z * apz;
    floatv bpx = px - b.x, bpy = py - b.y, bpz = pz - b.z;
    floatv d3 = (ab.x * bpx + ab.y * bpy) + ab.z * bpz, d4 = (ac.x * bpx + ac.y * bpy) + ac.z * bpz;
    floatv vc = d1 * d4 - d3 * d2;
    floatv cpx = px - c.x, cpy = py - c.y, cpz = pz - c.z;
    floatv d5 = (ab.x * cpx + ab.y * cpy) + ab.z * cpz, d6 = (ac.x * cpx + ac.y * cpy) + ac.z * cpz;
    floatv vb = d5 * d2 - d1 * d6;
    floatv va = d3 * d6 - d5 * d4;
    floatv e43 = d4 - d3, e56 = d5 - d6;
    intv in_a = (d1 <= 0.0f) & (d2 <= 0.0f);
    intv in_b = (d3 >= 0.0f) & (d4 <= d3);
    intv in_ab = (vc <= 0.0f) & (d1 >= 0.0f) & (d3 <= 0.0f);
    intv in_c = (d6 >= 0.0f) & (d5 <= d6);
    intv in_ac = (vb <= 0.0f) & (d2 >= 0.0f) & (d6 <= 0.0f);
    intv in_bc = (va <= 0.0f) & (e43 >= 0.0f) & (e56 >= 0.0f);
    floatv s_ab = d1 - d3, s_ac = d2 - d6, s_bc = e43 + e56;
    floatv t_ab = SELECT((floatv)(0.0f), d1 / s_ab, s_ab > 0.0f);
    floatv t_ac = SELECT((floatv)(0.0f), d2 / s_ac, s_ac > 0.0f);
    floatv t_bc = SELECT((floatv)(0.0f), e43 / s_bc, s_bc > 0.0f);
    floatv s = (va + vb) + vc;
    floatv v = vb / s, w = vc / s;
    /* the face, then each region over it from the last to the first: the first that holds wins */
    floatv x = (a.x + ab.x * v) + ac.x * w, y = (a.y + ab.y * v) + ac.y * w, z = (a.z + ab.z * v) + ac.z * w;
    intv f = 0;
    x = SELECT(x, b.x + cb.x * t_bc, in_bc), y = SELECT(y, b.y + cb.y * t_bc, in_bc);
    z = SELECT(z, b.z + cb.z * t_bc, in_bc);
    f = SELECT(f, (intv)(6), in_bc);
    x = SELECT(x, a.x + ac.x * t_ac, in_ac), y = SELECT(y, a.y + ac.y * t_ac, in_ac);
    z = SELECT(z, a.z + ac.z * t_ac, in_ac);
    f = SELECT(f, (intv)(5), in_ac);
    x = SELECT(x, (floatv)(c.x), in_c), y = SELECT(y, (floatv)(c.y), in_c), z = SELECT(z, (floatv)(c.z), in_c);
    f = SELECT(f, (intv)(3), in_c);
    x = SELECT(x, a.x + ab.x * t_ab, in_ab), y = SELECT(y, a.y + ab.y * t_ab, in_ab);
    z = SELECT(z, a.z + ab.z * t_ab, in_ab);
    f = SELECT(f, (intv)(4), in_ab);
    x = SELECT(x, (floatv)(b.x), in_b), y = SELECT(y, (floatv)(b.y), in_b), z = SELECT(z, (floatv)(b.z), in_b);
    f = SELECT(f, (intv)(2), in_b);
    x = SELECT(x, (floatv)(a.x), in_a), y = SELECT(y, (floatv)(a.y), in_a), z = SELECT(z, (floatv)(a.z), in_a);
    f = SELECT(f, (intv)(1), in_a);
    float3 lo = min3_np(min3_np(a, b), c), hi = max3_np(max3_np(a, b), c);
    *qx = min_np_v(max_np_v(x, (floatv)(lo.x)), (floatv)(hi.x));
    *qy = min_np_v(max_np_v(y, (floatv)(lo.y)), (floatv)(hi.y));
    *qz = min_np_v(max_np_v(z, (floatv)(lo.z)), (floatv)(hi.z));
    *feature = f;
}

/* collide_mesh() for the V lanes; only the free lanes near the mesh's box can be pushed */
INLINE void collide_mesh_v(floatv *x, floatv *y, floatv *z, intv free, __constant float4 *rows,
                           __global const float4 *geometry, __global const int *mesh_ints, int m)
{
    float4 r0 = rows[0], r1 = rows[1], r2 = rows[2], tr = rows[3], lo = rows[4], hi = rows[5];
    float margin = r0.w, margin2 = r1.w;
    floatv dx = *x - tr.x, dy = *y - tr.y, dz = *z - tr.z;
    floatv px = (r0.x * dx + r1.x * dy) + r2.x * dz, py = (r0.y * dx + r1.y * dy) + r2.y * dz;
    floatv pz = (r0.z * dx + r1.z * dy) + r2.z * dz;
    floatv gx = max_np_v(max_np_v(lo.x - px, px - hi.x), (floatv)(0.0f));
    floatv gy = max_np_v(max_np_v(lo.y - py, py - hi.y), (floatv)(0.0f));
    floatv gz = max_np_v(max_np_v(lo.z - pz, pz - hi.z), (floatv)(0.0f));
    intv near = free & ((gx * gx + gy * gy) + gz * gz <= margin2);
    if (!any(near))
        return; /* no lane within the margin of the mesh's box */
    __global const int *info = mesh_ints + 2 + 4 * m;
    __global const float4 *corners = geometry + 3 * info[0];
    int triangles = info[1];
    floatv best = INFINITY, bx = 0.0f, by = 0.0f, bz = 0.0f;
    intv k = -1, bf = 0;
    for (int t = 0; t < triangles; ++t) { /* every triangle in index order; ties keep the lower */
        floatv qx, qy, qz;
        intv f;
        closest_point_v(px, py, pz, corners[3 * t].xyz, corners[3 * t + 1].xyz, corners[3 * t + 2].xyz,
                        &qx, &qy, &qz, &f);
        floatv ex = px - qx, ey = py - qy, ez = pz - qz;
        floatv d2 = (ex * ex + ey * ey) + ez * ez;
        intv better = d2 < best;
        best = SELECT(best, d2, better), k = SELECT(k, (intv)(t), better), bf = SELECT(bf, f, better);
        bx = SELECT(bx, qx, better), by = SELECT(by, qy, better), bz = SELECT(bz, qz, better);
    }
    /* the winner's pseudo-normal, gathered lane by lane */
    int lk[V], lf[V];
    float nxl[V], nyl[V], nzl[V];
    *(intv_u *)lk = k, *(intv_u *)lf = bf;
    for (int l = 0; l < V; ++l) {
        float4 n = geometry[mesh_ints[0] + 7 * (info[0] + max(lk[l], 0)) + lf[l]];
        nxl[l] = n.x, nyl[l] = n.y, nzl[l] = n.z;
    }
    floatv nx = *(floatv_u *)nxl, ny = *(floatv_u *)nyl, nz = *(floatv_u *)nzl;
    floatv ex = px - bx, ey = py - by, ez = pz - bz;
    floatv side = (ex * nx + ey * ny) + ez * nz;
    intv push = r2.w != 0.0f ? ((side < 0.0f) | (best < margin2)) : ((side < 0.0f) & (best < margin2));
    push = push & near & (k >= 0);
    floatv yx = bx + nx * margin, yy = by + ny * margin, yz = bz + nz * margin;
    *x = SELECT(*x, ((r0.x * yx + r0.y * yy) + r0.z * yz) + tr.x, push);
    *y = SELECT(*y, ((r1.x * yx + r1.y * yy) + r1.z * yz) + tr.y, push);
    *z = SELECT(*z, ((r2.x * yx + r2.y * yy) + r2.z * yz) + tr.z, push);
}
#endif

/* The meshes for the specialised build's vectors: the naive search across the lanes (above),
 * the BVH (its path differs per particle) and the one-lane border kernel on each free lane's
 * float3 (pinned lanes are never collided). */
INLINE void collide_meshes_v(floatv *x, floatv *y, floatv *z, floatv w, __constant float4 *rows,
                             __global const float4 *geometry, __global const int *mesh_ints)
{
#if V == 1
    if (w != 0.0f) {
        float3 r = collide_meshes((float3)(*x, *y, *z), rows, geometry, mesh_ints);
        *x = r.x, *y = r.y, *z = r.z;
    }
#elif !defined(CLOTH_MESH_BVH)
    for (int m = 0; m < CLOTH_MESHES; ++m)
        collide_mesh_v(x, y, z, w != 0.0f, rows + MESH_ROWS * m, geometry, mesh_ints, m);
#else
    float lx[V], ly[V], lz[V], lw[V];
    *(floatv_u *)lx = *x, *(floatv_u *)ly = *y, *(floatv_u *)lz = *z, *(floatv_u *)lw = w;
    for (int l = 0; l < V; ++l) {
        if (lw[l] == 0.0f)
            continue;
        float3 r = collide_meshes((float3)(lx[l], ly[l], lz[l]), rows, geometry, mesh_ints);
        lx[l] = r.x, ly[l] = r.y, lz[l] = r.z;
    }
    *x = *(floatv_u *)lx, *y = *(floatv_u *)ly, *z = *(floatv_u *)lz;
#endif
}
#endif
