// collide_sphere.glsl: the spheres, as in the chapter (docs/semantics.md, "Sphere").
// Included by the host into verlet_cloth_step.glsl only when the program handles spheres.
// Every result is a `precise` temporary, so strict mode rounds exactly where the reference does.

#ifdef GENERIC
uniform int num_spheres;
uniform vec4 spheres[MAX_COLLIDERS];  // centre, radius
#define SPHERE_COUNT num_spheres
#else
const vec4 spheres[SPHERE_COUNT] = SPHERES_VALUE;  // centre, radius
#endif

// a particle inside the sphere (centre c, radius r) is pushed to the surface along the ray
vec3 collide_sphere(vec3 x, vec4 sphere)
{
    vec3 c = sphere.xyz;
    float r = sphere.w;
    P vec3 d = x - c;
    P float L2 = dot3(d, d);
    P float L = sqrt(L2);
    if (L < r) {
        if (L2 > 0.0) {
            P float s = r / L;
            P vec3 pushed = c + d * s;
            return pushed;
        }
        P vec3 up = c + vec3(0.0, r, 0.0);  // exactly at the centre: straight up
        return up;
    }
    return x;
}

vec3 collide_spheres(vec3 x)
{
    for (int i = 0; i < SPHERE_COUNT; ++i)
        x = collide_sphere(x, spheres[i]);
    return x;
}
