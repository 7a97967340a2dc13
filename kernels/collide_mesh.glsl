// collide_mesh.glsl: triangle-mesh colliders (docs/semantics.md, "Triangle mesh"), followed
// operation for operation, as the NumPy reference (clothbench/backends/numpy/collide_mesh.py).
// Included by the host into verlet_cloth_step.glsl only when the scene has meshes. Every
// result is a `precise` temporary, so strict mode rounds exactly where the reference does.
//
// The particle is taken into the mesh's body frame (p = R^T (x - T)); the triangles, their
// pseudo-normals and the BVH stay as uploaded once (clothbench/backends/gl/context.py,
// MeshBuffers). The host defines:
//   MESH_COUNT       meshes in the scene, applied in order after the analytic colliders
//   MESH_BOX_VALUE   per mesh (lo, margin), (hi, margin2): its box of every corner
//   MESH_INFO_VALUE  per mesh (first triangle, triangles, first BVH node, closed)
//   MESH_POSE_VALUE  per mesh three rows (row i of R, T.i) where the scene does not move;
//                    with MOTION they are this step's rows (MOTION_ROW(MOTION_MESHES + ...))
//   MESH_BVH         the accelerated traversal of the host's BVH (MESH_STACK entries deep);
//                    without it, the naive loop over every triangle in index order

layout(std430, binding = 7) readonly buffer MeshCorners { vec4 mesh_corner[]; };  // a, b, c (a.w: index)
layout(std430, binding = 8) readonly buffer MeshNormals { vec4 mesh_normal[]; };  // 7 per triangle
#ifdef MESH_BVH
// lo (w: first child, or -triangles for a leaf) and hi (w: a leaf's first triangle), int bits
layout(std430, binding = 9) readonly buffer MeshNodes { vec4 mesh_node[]; };
#endif

const vec4 mesh_box[2 * MESH_COUNT] = MESH_BOX_VALUE;
const ivec4 mesh_info[MESH_COUNT] = MESH_INFO_VALUE;
#ifdef MOTION
#define MESH_POSE(m, i) MOTION_ROW(MOTION_MESHES + 3 * (m) + (i))
#else
const vec4 mesh_pose[3 * MESH_COUNT] = MESH_POSE_VALUE;
#define MESH_POSE(m, i) mesh_pose[3 * (m) + (i)]
#endif

// the squared distance from p to the box lo..hi: g = max(max(lo - p, p - hi), 0), dot(g, g)
float box_distance2(vec3 p, vec3 lo, vec3 hi)
{
    P vec3 g = max(max(lo - p, p - hi), vec3(0.0));
    P float g2 = dot3(g, g);
    return g2;
}

// Ericson's ClosestPtPointTriangle with the guards and the clamp of docs/semantics.md: the
// closest point of triangle abc to p, and in `feature` the pseudo-normal of its region
// (0 face, 1 a, 2 b, 3 c, 4 ab, 5 ac, 6 bc)
vec3 closest_point(vec3 p, vec3 a, vec3 b, vec3 c, out int feature)
{
    P vec3 ab = b - a;
    P vec3 ac = c - a;
    P vec3 ap = p - a;
    P float d1 = dot3(ab, ap);
    P float d2 = dot3(ac, ap);
    P vec3 bp = p - b;
    P float d3 = dot3(ab, bp);
    P float d4 = dot3(ac, bp);
    P float vc = d1 * d4 - d3 * d2;
    P vec3 cp = p - c;
    P float d5 = dot3(ab, cp);
    P float d6 = dot3(ac, cp);
    P float vb = d5 * d2 - d1 * d6;
    P float va = d3 * d6 - d5 * d4;
    P float e43 = d4 - d3;
    P float e56 = d5 - d6;
    P vec3 q;
    if (d1 <= 0.0 && d2 <= 0.0) {
        q = a;
        feature = 1;
    } else if (d3 >= 0.0 && d4 <= d3) {
        q = b;
        feature = 2;
    } else if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0) {
        P float s = d1 - d3;
        P float v = s > 0.0 ? d1 / s : 0.0;  // an edge shorter than the rounding: q = a
        q = a + ab * v;
        feature = 4;
    } else if (d6 >= 0.0 && d5 <= d6) {
        q = c;
        feature = 3;
    } else if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0) {
        P float s = d2 - d6;
        P float w = s > 0.0 ? d2 / s : 0.0;
        q = a + ac * w;
        feature = 5;
    } else if (va <= 0.0 && e43 >= 0.0 && e56 >= 0.0) {
        P float s = e43 + e56;
        P float w = s > 0.0 ? e43 / s : 0.0;
        P vec3 bc = c - b;
        q = b + bc * w;
        feature = 6;
    } else {
        P float s = (va + vb) + vc;  // > 0 here: va, vb, vc > 0 (two divisions, no 1/s)
        P float v = vb / s;
        P float w = vc / s;
        q = (a + ab * v) + ac * w;
        feature = 0;
    }
    // into the triangle's box (exact): the BVH's pruning bound holds by construction
    P vec3 clamped = min(max(q, min(min(a, b), c)), max(max(a, b), c));
    return clamped;
}

// the squared distance from p to triangle `tri` (its corners' position in mesh_corner)
float triangle_distance2(vec3 p, int tri)
{
    int feature;
    P vec3 q = closest_point(p, mesh_corner[3 * tri].xyz, mesh_corner[3 * tri + 1].xyz,
                             mesh_corner[3 * tri + 2].xyz, feature);
    P vec3 e = p - q;
    P float d2 = dot3(e, e);
    return d2;
}

vec3 collide_mesh(vec3 x, int m)
{
    vec4 r0 = MESH_POSE(m, 0), r1 = MESH_POSE(m, 1), r2 = MESH_POSE(m, 2);
    vec3 trans = vec3(r0.w, r1.w, r2.w);
    P vec3 d = x - trans;
    P vec3 p = (r0.xyz * d.x + r1.xyz * d.y) + r2.xyz * d.z;  // p.i = (R0i d.x + R1i d.y) + R2i d.z
    float margin = mesh_box[2 * m].w, margin2 = mesh_box[2 * m + 1].w;
    if (box_distance2(p, mesh_box[2 * m].xyz, mesh_box[2 * m + 1].xyz) > margin2)
        return x;  // farther than the margin from the mesh's box: not inside, not in the skin
    ivec4 info = mesh_info[m];
    float best = uintBitsToFloat(0x7f800000u);  // +inf
    int k = -1;     // the closest triangle's index in its mesh (ties: the lowest)
    int k_at = -1;  // where its corners are in mesh_corner
#ifdef MESH_BVH
    // the host's BVH: a node is skipped only when its box is strictly farther than the best,
    // which no triangle in it could beat or tie (docs/semantics.md); nearer child first
    int stack[MESH_STACK];
    float stack_d2[MESH_STACK];
    int top = 1;
    stack[0] = 0;
    stack_d2[0] = 0.0;
    // A node is pushed only by its parent, so a traversal pops each of the mesh's at most
    // 2T - 1 nodes (T triangles, a leaf holds one or more) at most once: the bound never cuts
    // one short. It is there for llvmpipe's fragment shader, where a bare `while (top > 0)`
    // runs on (to Mesa's loop limit, by our reading) in lanes no fragment uses, many times the
    // step's own cost (docs/llvmpipe.md, "The fragment loop").
    for (int visit = 0; top > 0 && visit < 2 * info.y; ++visit) {
        --top;
        if (stack_d2[top] > best)
            continue;
        int node = info.z + stack[top];
        int child = floatBitsToInt(mesh_node[2 * node].w);
        if (child >= 0) {
            int near = child, far = child + 1;
            float d_near = box_distance2(p, mesh_node[2 * (info.z + near)].xyz, mesh_node[2 * (info.z + near) + 1].xyz);
            float d_far = box_distance2(p, mesh_node[2 * (info.z + far)].xyz, mesh_node[2 * (info.z + far) + 1].xyz);
            if (d_far < d_near) {
                near = child + 1;
                far = child;
                float swap = d_near;
                d_near = d_far;
                d_far = swap;
            }
            if (!(d_far > best)) {
                stack[top] = far;
                stack_d2[top] = d_far;
                ++top;
            }
            if (!(d_near > best)) {
                stack[top] = near;
                stack_d2[top] = d_near;
                ++top;
            }
            continue;
        }
        int first = info.x + floatBitsToInt(mesh_node[2 * node + 1].w);
        for (int j = 0; j < -child; ++j) {
            int at = first + j;
            int t = int(mesh_corner[3 * at].w);
            float d2 = triangle_distance2(p, at);
            if (d2 < best || (d2 == best && t < k)) {
                best = d2;
                k = t;
                k_at = at;
            }
        }
    }
#else
    for (int t = 0; t < info.y; ++t) {  // every triangle, in index order
        float d2 = triangle_distance2(p, info.x + t);
        if (d2 < best) {
            best = d2;
            k = t;
        }
    }
    k_at = info.x + k;
#endif
    if (k < 0)
        return x;  // no finite distance: a non-finite p
    int feature;
    P vec3 q = closest_point(p, mesh_corner[3 * k_at].xyz, mesh_corner[3 * k_at + 1].xyz,
                             mesh_corner[3 * k_at + 2].xyz, feature);
    vec3 nrm = mesh_normal[7 * (info.x + k) + feature].xyz;
    P vec3 e = p - q;
    P float side = dot3(e, nrm);
    bool push = info.w != 0 ? (side < 0.0 || best < margin2)   // closed: inside, or within the margin
                            : (side < 0.0 && best < margin2);  // open: in the skin under the surface
    if (!push)
        return x;
    P vec3 y = q + nrm * margin;
    P vec3 pushed = vec3(((r0.x * y.x + r0.y * y.y) + r0.z * y.z) + r0.w,  // x = R y + T
                         ((r1.x * y.x + r1.y * y.y) + r1.z * y.z) + r1.w,
                         ((r2.x * y.x + r2.y * y.y) + r2.z * y.z) + r2.w);
    return pushed;
}

vec3 collide_meshes(vec3 x)
{
    for (int m = 0; m < MESH_COUNT; ++m)
        x = collide_mesh(x, m);
    return x;
}
