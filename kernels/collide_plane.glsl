// collide_plane.glsl: the one-sided planes, e.g. a floor (docs/semantics.md, "Plane").
// Included by the host into verlet_cloth_step.glsl only when the program handles planes.
// Every result is a `precise` temporary, so strict mode rounds exactly where the reference does.

#ifdef GENERIC
uniform int num_planes;
uniform vec4 planes[2 * MAX_COLLIDERS];  // (point, 0), (unit normal, 0)
#define PLANE_COUNT num_planes
#else
const vec4 planes[2 * PLANE_COUNT] = PLANES_VALUE;  // as above, two rows each
#endif

// solid where the signed distance to the plane (point p0, unit normal nrm) is < 0
vec3 collide_plane(vec3 x, vec3 p0, vec3 nrm)
{
    P vec3 d = x - p0;
    P float dist = dot3(d, nrm);
    if (dist < 0.0) {
        P vec3 out_plane = x - nrm * dist;
        return out_plane;
    }
    return x;
}

vec3 collide_planes(vec3 x)
{
    for (int i = 0; i < PLANE_COUNT; ++i)
        x = collide_plane(x, planes[2 * i].xyz, planes[2 * i + 1].xyz);
    return x;
}
