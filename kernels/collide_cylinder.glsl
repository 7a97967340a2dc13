// collide_cylinder.glsl: the capped cylinders (docs/semantics.md, "Capped cylinder").
// Included by the host into verlet_cloth_step.glsl only when the program handles cylinders.
// Every result is a `precise` temporary, so strict mode rounds exactly where the reference does.

#ifdef GENERIC
uniform int num_cylinders;
uniform vec4 cylinders[3 * MAX_COLLIDERS];  // (start, length), (unit axis, radius), (radial_r, 0)
#define CYLINDER_COUNT num_cylinders
#else
const vec4 cylinders[3 * CYLINDER_COUNT] = CYLINDERS_VALUE;  // as above, three rows each
#endif

// a particle inside the cylinder (start a, unit axis u, length len, radius r) is pushed out
// the shortest way: through the curved side or through the nearer cap
vec3 collide_cylinder(vec3 x, vec4 a_len, vec4 u_r, vec3 radial_r)
{
    vec3 a = a_len.xyz;
    vec3 u = u_r.xyz;
    float len = a_len.w, r = u_r.w;
    P vec3 d = x - a;
    P float t = dot3(d, u);  // axial coordinate from the start cap
    P vec3 q = u * t;
    P vec3 p = d - q;  // radial vector
    P float rho2 = dot3(p, p);
    P float rho = sqrt(rho2);
    if (t > 0.0 && t < len && rho < r) {
        P float side = r - rho;
        P float to_end = len - t;
        if (side <= t && side <= to_end) {  // through the curved side
            P vec3 base = a + q;
            if (rho2 > 0.0) {
                P float s = r / rho;
                P vec3 pushed = base + p * s;
                return pushed;
            }
            P vec3 out_axis = base + radial_r;  // exactly on the axis: the fixed radial direction
            return out_axis;
        }
        if (t <= to_end) {
            P vec3 out_start = x - q;  // through the start cap
            return out_start;
        }
        P vec3 out_end = x + u * to_end;  // through the end cap
        return out_end;
    }
    return x;
}

vec3 collide_cylinders(vec3 x)
{
    for (int i = 0; i < CYLINDER_COUNT; ++i)
        x = collide_cylinder(x, cylinders[3 * i], cylinders[3 * i + 1], cylinders[3 * i + 2].xyz);
    return x;
}
