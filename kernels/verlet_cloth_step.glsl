// verlet_cloth_step.glsl: the cloth step shared by verlet_cloth.frag and verlet_cloth.comp,
// which differ only in how they read and write the state. The step is docs/semantics.md
// (Listing 22.1); this file follows it operation for operation and does not restate it.
//
// GLSL has no #include: the host (clothbench/backends/gl/context.py, shader_source) puts
// this file where a kernel includes it. The kernel defines POS(rc) before it, the position
// of particle rc = (row, col). Switches the host defines in front:
//   STRICT    bit-exact with the numpy float32 reference: the documented operation order,
//             every temporary `precise` (no reassociation, no contraction), and no
//             dot/length/normalize/cross, whose evaluation order is the driver's.
//             Without it (fast): built-ins and a reciprocal square root per spring.
//   NORMALS   also compute the particle's normal (docs/normals.md): normal_at().
//   SELF_COLLISION  verlet() returns x_new uncollided: the self-collision pass collides it.
//   GENERIC   constants are uniforms, one program for every scene; otherwise they are exact
//             literals (*_VALUE: the float32 bit patterns from kernel_source.glsl_float),
//             folded by the compiler, and N_VALUE bakes the grid size in.

#ifdef STRICT
#define P precise
#else
#define P
#endif

#ifdef GENERIC
uniform int n;
uniform float dt, dt2, k, b;
uniform vec3 g;
uniform float rest[3];  // structural, shear, bend
#else
const int n = N_VALUE;
const float dt = DT_VALUE;
const float dt2 = DT2_VALUE;
const float k = K_VALUE;
const float b = B_VALUE;
const vec3 g = G_VALUE;
const float rest[3] = REST_VALUE;  // structural, shear, bend
#endif

// the 12-spring stencil as (d_row, d_col), in the order the forces are summed
const ivec2 OFFSETS[12] = ivec2[12](
    ivec2(0, -1), ivec2(0, 1), ivec2(-1, 0), ivec2(1, 0),     // structural
    ivec2(-1, -1), ivec2(-1, 1), ivec2(1, -1), ivec2(1, 1),   // shear
    ivec2(-2, -2), ivec2(-2, 2), ivec2(2, -2), ivec2(2, 2));  // bend

bool inside(ivec2 rc)
{
    return all(greaterThanEqual(rc, ivec2(0))) && all(lessThan(rc, ivec2(n)));
}

// (a.x*b.x + a.y*b.y) + a.z*b.z in strict mode, as docs/semantics.md fixes; dot() is the
// driver's order (llvmpipe: x*x + (y*y + z*z))
float dot3(vec3 a, vec3 c)
{
#ifdef STRICT
    P float s = (a.x * c.x + a.y * c.y) + a.z * c.z;
    return s;
#else
    return dot(a, c);
#endif
}

// steps 5.3-5.6 for the neighbour at xj: the spring's pull toward xj minus the damping b*vel
vec3 spring(vec3 x, vec3 xj, vec3 bv, float rest_o)
{
    P vec3 d = xj - x;
    P float L2 = dot3(d, d);
#ifdef STRICT
    P float L = sqrt(L2);
    P float s = L2 > 0.0 ? (k * (L - rest_o)) / L : 0.0;  // coincident: no direction, no force
#else
    // k (L - rest) / L, with one reciprocal square root instead of a sqrt and a divide
    float s = L2 > 0.0 ? k - (k * rest_o) * inversesqrt(L2) : 0.0;
#endif
    P vec3 f = s * d - bv;
    return f;
}

#ifdef MOTION
// A scene that moves (docs/semantics.md, "Moving colliders"): this step's collider rows, mesh
// poses and attached-pin targets, MOTION_STRIDE vec4s per step at the offsets MOTION_SPHERES,
// MOTION_CYLINDERS, ..., MOTION_MESHES, MOTION_PINS (clothbench/backends/gl/bodies.py,
// motion_offsets), evaluated on the host in float64 and rounded once. The host uploads the
// rows of a block of steps before dispatching them; the kernel sets motion_base per step.
layout(std430, binding = 6) readonly buffer MotionRows { vec4 motion_rows[]; };
uniform int motion_step;  // the (first) step's place in the uploaded block
int motion_base = 0;
#define MOTION_ROW(j) motion_rows[motion_base + (j)]
#endif
#ifdef PIN_ATTACH
// pins that follow a body: per particle its row among the pin targets, or -1
layout(std430, binding = 10) readonly buffer PinSlots { int pin_slot[]; };
#endif

// Collisions (section 22.3): `vec3 collide(vec3 x)`, every collider in the fixed order
// (spheres, cylinders, boxes, planes, then meshes: clothbench/model/colliders/kinds.py). The host
// puts here the file of each collider kind the program handles (kernels/collide_sphere.glsl,
// collide_cylinder.glsl, collide_box.glsl, collide_plane.glsl: only the kinds the scene has,
// or all of them with GENERIC; and collide_mesh.glsl only where the scene has meshes) and
// collide() calling them.
#include <colliders>

// One step for the particle at rc (Listing 22.1 steps 3-6); returns x(t + dt).
// With NO_BOUNDS_TESTS the caller guarantees all 12 neighbours exist (the same operations in
// the same order, so strict stays exact).
vec3 verlet(ivec2 rc, vec3 x, vec3 xp, float w)
{
    // step 3: velocity from the two positions; damping uses it once per spring
#ifdef STRICT
    P vec3 vel = (x - xp) / dt;
    P vec3 bv = b * vel;
#else
    vec3 bv = (x - xp) * (b / dt);
#endif
    P vec3 force = vec3(0.0);  // step 4: gravity is added below, as an acceleration (differs)

    // step 5: the 12 springs in OFFSETS order; a neighbour outside the grid adds nothing
    for (int o = 0; o < 12; ++o) {
        ivec2 rj = rc + OFFSETS[o];
#ifndef NO_BOUNDS_TESTS
        if (inside(rj))
#endif
            force = force + spring(x, POS(rj), bv, rest[o >> 2]);
    }

    // step 6: Verlet with acceleration g + force * w; pinned particles (w = 0) stay put
    if (w == 0.0) {
#ifdef PIN_ATTACH
        int slot = pin_slot[rc.x * n + rc.y];
        if (slot >= 0)
            return MOTION_ROW(MOTION_PINS + slot).xyz;  // or follow their body: the host's target
#endif
        return x;
    }
    P vec3 acc = g + force * w;
    P vec3 x_new = (2.0 * x - xp) + acc * dt2;
#ifdef SELF_COLLISION
    return x_new;  // the pass pushes it, then collides (verlet_cloth.comp PASS_SELF_COLLISION)
#else
    return collide(x_new);
#endif
}

#ifdef NORMALS
// docs/normals.md. The six triangles around a particle (each grid quad split along its
// (r,c)-(r+1,c+1) diagonal) are (x, RING[e], RING[e+1]) for consecutive ring entries: up,
// up-left, left, down, down-right, right, (up); cross(a - x, c - x) is +y on the initial sheet.
const ivec2 RING[6] = ivec2[6](ivec2(-1, 0), ivec2(-1, -1), ivec2(0, -1),
                               ivec2(1, 0), ivec2(1, 1), ivec2(0, 1));

// v / |v|, or 0 for a zero vector (a degenerate triangle has no direction)
vec3 unit_or_zero(vec3 v)
{
    P float L2 = dot3(v, v);
#ifdef STRICT
    P vec3 u = L2 > 0.0 ? v / sqrt(L2) : vec3(0.0);
#else
    vec3 u = L2 > 0.0 ? v * inversesqrt(L2) : vec3(0.0);
#endif
    return u;
}

vec3 face_normal(vec3 a, vec3 c)
{
#ifdef STRICT
    P vec3 f = vec3(a.y * c.z - a.z * c.y, a.z * c.x - a.x * c.z, a.x * c.y - a.y * c.x);
    return f;
#else
    return cross(a, c);
#endif
}

// the normalised sum of the unit normals of the triangles around rc, in the state the
// step read (x(t): the previous position this step writes)
vec3 normal_at(ivec2 rc, vec3 x)
{
    P vec3 sum = vec3(0.0);
    for (int e = 0; e < 6; ++e) {
        ivec2 ra = rc + RING[e];
        ivec2 rb = rc + RING[(e + 1) % 6];
        if (inside(ra) && inside(rb))
            sum = sum + unit_or_zero(face_normal(POS(ra) - x, POS(rb) - x));
    }
    return unit_or_zero(sum);
}
#endif
