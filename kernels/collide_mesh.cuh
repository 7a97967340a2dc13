/*
 * Triangle-mesh colliders for the CUDA kernels: docs/semantics.md, "Triangle mesh",
 * operation by operation (this file does not restate the rules; the names are the doc's).
 * collide.cuh includes it, for verlet_cloth.cu and vbd_cloth.cu, only for a scene with meshes
 * (HAS_MESHES): a scene without them compiles none of it. -DCLOTH_MESH_BVH selects the
 * accelerated search (the host's BVH traversed with a fixed stack), otherwise every triangle
 * in index order; both find the same triangle, so the same bits.
 *
 * The particle is taken into the mesh's body frame by its pose (R, T) instead of moving the
 * triangles, so the buffers below are uploaded once and a moving mesh costs only its pose:
 * three rows (R row i, T_i) per step (collide.cuh: MESH_POSE).
 *
 * Two buffers hold every mesh of the scene (clothbench/backends/cuda/launch.py: mesh_buffers):
 *   mesh_rows, float4: per mesh MESH_HEADER_ROWS rows (lo, margin), (hi, margin2) and the
 *              fixed pose R0|T0, R1|T1, R2|T2; then per triangle MESH_TRIANGLE_ROWS rows
 *              a, b, c, N[face], N[a], N[b], N[c], N[ab], N[ac], N[bc]; then per BVH node
 *              (lo, 0), (hi, 0);
 *   mesh_ints, int: per mesh MESH_HEADER_INTS ints (its first triangle row, its triangles, its
 *              first node row, its first node link, its first leaf triangle, closed); per BVH
 *              node (child, first, count), child -1 for a leaf; the leaves' triangle lists.
 * Offsets are absolute, triangle indices within the mesh (the index that breaks ties).
 */

#define MESH_HEADER_ROWS 5
#define MESH_HEADER_INTS 8
#define MESH_TRIANGLE_ROWS 10
#define MESH_STACK 32  // the BVH's depth limit (colliders/mesh.py: MAX_STACK)

// NumPy's maximum and minimum, which the reference uses: NaN if either is NaN, otherwise the
// second operand unless the first is strictly greater (smaller). On a tie of +0 and -0 that
// keeps the second's sign, which fmaxf/fminf leave unspecified.
__device__ __forceinline__ float max_np(float a, float c) { return (a > c || a != a) ? a : c; }
__device__ __forceinline__ float min_np(float a, float c) { return (a < c || a != a) ? a : c; }

__device__ __forceinline__ float3 xyz(float4 v) { return make_float3(v.x, v.y, v.z); }

__device__ __forceinline__ float3 along(float3 a, float3 d, float s)  // a + d * s  ·c
{
    return make_float3(a.x + d.x * s, a.y + d.y * s, a.z + d.z * s);
}

// Squared distance from p to the box lo..hi: g = max(max(lo - p, p - hi), 0), dot(g, g).
__device__ __forceinline__ float box_distance2(float3 p, float3 lo, float3 hi)
{
    const float3 g = make_float3(max_np(max_np(lo.x - p.x, p.x - hi.x), 0.0f),
                                 max_np(max_np(lo.y - p.y, p.y - hi.y), 0.0f),
                                 max_np(max_np(lo.z - p.z, p.z - hi.z), 0.0f));
    return dot3(g, g);
}

// Feature indices of the pseudo-normals (colliders/mesh.py: FEATURES).
#define FEATURE_FACE 0
#define FEATURE_A 1
#define FEATURE_B 2
#define FEATURE_C 3
#define FEATURE_AB 4
#define FEATURE_AC 5
#define FEATURE_BC 6

// closest(p, a, b, c): Ericson's ClosestPtPointTriangle with the doc's guards and clamp;
// returns q and sets `feature` to its region.
__device__ __forceinline__ float3 closest_point(float3 p, float3 a, float3 b, float3 c, int& feature)
{
    const float3 ab = minus(b, a), ac = minus(c, a);
    const float3 ap = minus(p, a), bp = minus(p, b), cp = minus(p, c);
    const float d1 = dot3(ab, ap), d2 = dot3(ac, ap);
    const float d3 = dot3(ab, bp), d4 = dot3(ac, bp);
    const float d5 = dot3(ab, cp), d6 = dot3(ac, cp);
    const float vc = d1 * d4 - d3 * d2;
    const float vb = d5 * d2 - d1 * d6;
    const float va = d3 * d6 - d5 * d4;
    float3 q;
    if (d1 <= 0.0f && d2 <= 0.0f) {
        q = a, feature = FEATURE_A;
    } else if (d3 >= 0.0f && d4 <= d3) {
        q = b, feature = FEATURE_B;
    } else if (vc <= 0.0f && d1 >= 0.0f && d3 <= 0.0f) {
        const float s = d1 - d3;
        q = along(a, ab, s > 0.0f ? d1 / s : 0.0f), feature = FEATURE_AB;
    } else if (d6 >= 0.0f && d5 <= d6) {
        q = c, feature = FEATURE_C;
    } else if (vb <= 0.0f && d2 >= 0.0f && d6 <= 0.0f) {
        const float s = d2 - d6;
        q = along(a, ac, s > 0.0f ? d2 / s : 0.0f), feature = FEATURE_AC;
    } else if (va <= 0.0f && (d4 - d3) >= 0.0f && (d5 - d6) >= 0.0f) {
        const float u = d4 - d3;
        const float s = u + (d5 - d6);
        q = along(b, minus(c, b), s > 0.0f ? u / s : 0.0f), feature = FEATURE_BC;
    } else {  // the face: va, vb, vc > 0, so s >= vb, vc > 0 and v, w in (0, 1]
        const float s = (va + vb) + vc;
        q = along(along(a, ab, vb / s), ac, vc / s), feature = FEATURE_FACE;
    }
    // clamp into the triangle's box: the BVH's bound holds by construction
    return make_float3(min_np(max_np(q.x, min_np(min_np(a.x, b.x), c.x)), max_np(max_np(a.x, b.x), c.x)),
                       min_np(max_np(q.y, min_np(min_np(a.y, b.y), c.y)), max_np(max_np(a.y, b.y), c.y)),
                       min_np(max_np(q.z, min_np(min_np(a.z, b.z), c.z)), max_np(max_np(a.z, b.z), c.z)));
}

// d2 = dot(p - q, p - q) to triangle t (its rows), the closest point and its feature.
__device__ __forceinline__ float triangle_distance2(float3 p, const float4* tri, float3& q, int& feature)
{
    q = closest_point(p, xyz(tri[0]), xyz(tri[1]), xyz(tri[2]), feature);
    const float3 e = minus(p, q);
    return dot3(e, e);
}

// The closest triangle of a mesh to body-frame p (its index within the mesh, or -1) and its
// squared distance `best`; a tie goes to the lower index.
__device__ __forceinline__ int closest_triangle(float3 p, const float4* __restrict__ mesh_rows,
                                                const int* __restrict__ mesh_ints, const int* head, float& best)
{
    const float4* tris = mesh_rows + head[0];
    best = __int_as_float(0x7f800000);  // +inf
    int best_tri = -1;
    float3 q;
    int feature;
#ifdef CLOTH_MESH_BVH
    // nodes: boxes at mesh_rows + head[2] (2 rows each), links at mesh_ints + head[3] (3 ints)
    const float4* node_boxes = mesh_rows + head[2];
    const int* links = mesh_ints + head[3];
    const int* leaf_tris = mesh_ints + head[4];
    int stack[MESH_STACK];
    int top = 0;
    stack[top++] = 0;
    while (top > 0) {
        const int node = stack[--top];
        if (box_distance2(p, xyz(node_boxes[2 * node]), xyz(node_boxes[2 * node + 1])) > best)
            continue;  // every triangle in it is strictly farther: it could not win, not even a tie
        const int child = links[3 * node];
        if (child >= 0) {  // the nearer child is popped first: the order changes speed, not results
            int near_node = child, far_node = child + 1;
            if (box_distance2(p, xyz(node_boxes[2 * far_node]), xyz(node_boxes[2 * far_node + 1])) <
                box_distance2(p, xyz(node_boxes[2 * near_node]), xyz(node_boxes[2 * near_node + 1]))) {
                near_node = child + 1, far_node = child;
            }
            stack[top++] = far_node;
            stack[top++] = near_node;
            continue;
        }
        const int first = links[3 * node + 1], count = links[3 * node + 2];
        for (int j = 0; j < count; ++j) {
            const int t = leaf_tris[first + j];
            const float d2 = triangle_distance2(p, tris + MESH_TRIANGLE_ROWS * t, q, feature);
            if (d2 < best || (d2 == best && t < best_tri)) best = d2, best_tri = t;
        }
    }
#else
    (void)mesh_ints;
    const int count = head[1];
    for (int t = 0; t < count; ++t) {  // every triangle, in index order
        const float d2 = triangle_distance2(p, tris + MESH_TRIANGLE_ROWS * t, q, feature);
        if (d2 < best) best = d2, best_tri = t;
    }
#endif
    return best_tri;
}

// One mesh, m, at pose rows pose[0..2] = (R row i, T_i): x_new pushed out of it, or unchanged.
__device__ __forceinline__ float3 collide_mesh(float3 x, const float4* __restrict__ mesh_rows,
                                               const int* __restrict__ mesh_ints, int m, const float4* pose)
{
    const float4 r0 = pose[0], r1 = pose[1], r2 = pose[2];
    const float3 d = make_float3(x.x - r0.w, x.y - r1.w, x.z - r2.w);
    const float3 p = make_float3((r0.x * d.x + r1.x * d.y) + r2.x * d.z,  // p = R^T d
                                 (r0.y * d.x + r1.y * d.y) + r2.y * d.z,
                                 (r0.z * d.x + r1.z * d.y) + r2.z * d.z);
    const float4 lo_margin = mesh_rows[MESH_HEADER_ROWS * m];
    const float4 hi_margin2 = mesh_rows[MESH_HEADER_ROWS * m + 1];
    // outside the box by more than the margin (or not finite): not touched
    if (!(box_distance2(p, xyz(lo_margin), xyz(hi_margin2)) <= hi_margin2.w)) return x;
    const int* head = mesh_ints + MESH_HEADER_INTS * m;
    float best;
    const int t = closest_triangle(p, mesh_rows, mesh_ints, head, best);
    if (t < 0) return x;
    const float4* tri = mesh_rows + head[0] + MESH_TRIANGLE_ROWS * t;
    int feature;
    const float3 q = closest_point(p, xyz(tri[0]), xyz(tri[1]), xyz(tri[2]), feature);
    const float3 nrm = xyz(tri[3 + feature]);
    const float side = dot3(minus(p, q), nrm);
    const bool push = head[5] ? (side < 0.0f || best < hi_margin2.w)   // closed: inside, or within the margin
                              : (side < 0.0f && best < hi_margin2.w);  // open: in the skin under the surface
    if (!push) return x;
    const float3 y = along(q, nrm, lo_margin.w);
    return make_float3(((r0.x * y.x + r0.y * y.y) + r0.z * y.z) + r0.w,  // x = R y + T
                       ((r1.x * y.x + r1.y * y.y) + r1.z * y.z) + r1.w,
                       ((r2.x * y.x + r2.y * y.y) + r2.z * y.z) + r2.w);
}
