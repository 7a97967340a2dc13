// verlet_cloth.frag: one cloth step per fragment, the chapter's section 22.6 in core-profile
// GLSL. The step is docs/semantics.md (Listing 22.1); this file follows it operation for
// operation and does not restate it.
//
// One fragment per texel of an n x n viewport, one texel per particle: texel (x, y) is
// particle (row = y, col = x). The inputs are RGBA32F textures read texel by texel (no
// filtering, integer coordinates); the outputs are render targets: the new position, the
// new previous position and, with NORMALS only, the normal.
//
// The host (clothbench/backends/glsl.py) prepends #version and these switches:
//   STRICT       bit-exact with the numpy float32 reference: the documented operation order,
//                every temporary `precise` (no reassociation, no contraction), and no
//                dot/length/normalize/cross, whose evaluation order is the driver's.
//                Without it (fast): built-ins and a reciprocal square root per spring.
//   NORMALS      also write the particle's normal (docs/normals.md) to a third target.
//   GENERIC      constants are uniforms; otherwise they are exact literals (*_VALUE: the
//                float32 bit patterns from kernel_source.glsl_float), folded by the compiler.
//   IMAGE_READS  read the inputs with imageLoad (GL 4.2) instead of texelFetch: the same
//                bits in about half the step time on llvmpipe (its sampler path is heavier).

#ifdef IMAGE_READS
layout(rgba32f, binding = 0) readonly uniform image2D pos_tex;   // x(t); w = inverse mass
layout(rgba32f, binding = 1) readonly uniform image2D prev_tex;  // x(t - dt)
#define LOAD(tex, rc) imageLoad(tex, (rc).yx)
#else
uniform sampler2D pos_tex;   // x(t); w = inverse mass (0 = pinned)
uniform sampler2D prev_tex;  // x(t - dt)
#define LOAD(tex, rc) texelFetch(tex, (rc).yx, 0)
#endif
#define POS(rc) LOAD(pos_tex, rc).xyz

layout(location = 0) out vec4 pos_out;
layout(location = 1) out vec4 prev_out;
#ifdef NORMALS
layout(location = 2) out vec4 normal_out;  // without NORMALS there is no third target at all
#endif

// ---- the step: identical in verlet_cloth.frag and verlet_cloth.comp (a test checks) ----
// Before this section a file defines POS(rc), the position of particle rc = (row, col).

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
uniform int num_spheres, num_cylinders, num_planes;
uniform vec4 spheres[MAX_COLLIDERS];        // centre, radius
uniform vec4 cylinders[3 * MAX_COLLIDERS];  // (start, length), (unit axis, radius), (radial_r, 0)
uniform vec4 planes[2 * MAX_COLLIDERS];     // (point, 0), (unit normal, 0)
#define SPHERE_COUNT num_spheres
#define CYLINDER_COUNT num_cylinders
#define PLANE_COUNT num_planes
#define HAS_SPHERES
#define HAS_CYLINDERS
#define HAS_PLANES
#else
const int n = N_VALUE;
const float dt = DT_VALUE;
const float dt2 = DT2_VALUE;
const float k = K_VALUE;
const float b = B_VALUE;
const vec3 g = G_VALUE;
const float rest[3] = REST_VALUE;  // structural, shear, bend
#if SPHERE_COUNT > 0
#define HAS_SPHERES
const vec4 spheres[SPHERE_COUNT] = SPHERES_VALUE;
#endif
#if CYLINDER_COUNT > 0
#define HAS_CYLINDERS
const vec4 cylinders[3 * CYLINDER_COUNT] = CYLINDERS_VALUE;
#endif
#if PLANE_COUNT > 0
#define HAS_PLANES
const vec4 planes[2 * PLANE_COUNT] = PLANES_VALUE;
#endif
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

// Collisions (section 22.3, docs/semantics.md): every result is a `precise` temporary, so
// strict mode rounds exactly where the reference does.

// a sphere (centre c, radius r): a particle inside is pushed to the surface along the ray
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

// a capped cylinder (start a, unit axis u, length len, radius r): out the shortest way
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

// a one-sided plane (point p0, unit normal nrm): solid where the signed distance is < 0
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
    if (w == 0.0)
        return x;
    P vec3 acc = g + force * w;
    P vec3 x_new = (2.0 * x - xp) + acc * dt2;
    // colliders in the fixed order: spheres, cylinders, planes
#ifdef HAS_SPHERES
    for (int s = 0; s < SPHERE_COUNT; ++s)
        x_new = collide_sphere(x_new, spheres[s]);
#endif
#ifdef HAS_CYLINDERS
    for (int c = 0; c < CYLINDER_COUNT; ++c)
        x_new = collide_cylinder(x_new, cylinders[3 * c], cylinders[3 * c + 1], cylinders[3 * c + 2].xyz);
#endif
#ifdef HAS_PLANES
    for (int p = 0; p < PLANE_COUNT; ++p)
        x_new = collide_plane(x_new, planes[2 * p].xyz, planes[2 * p + 1].xyz);
#endif
    return x_new;
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
// ---- end of the step ----

void main()
{
    // (A branch that skips the bounds tests for interior particles, as the compute shader
    // does, made llvmpipe's fragment shader slower, not faster: measured.)
    ivec2 rc = ivec2(gl_FragCoord.yx);  // (row, col)
    vec4 self = LOAD(pos_tex, rc);
    vec3 x = self.xyz;                // step 1
    vec3 xp = LOAD(prev_tex, rc).xyz;  // step 2
    pos_out = vec4(verlet(rc, x, xp, self.w), self.w);  // step 7
    prev_out = self;                                    // step 8: x(t), w unchanged
#ifdef NORMALS
    normal_out = vec4(normal_at(rc, x), 0.0);
#endif
}
