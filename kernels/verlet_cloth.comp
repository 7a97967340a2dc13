// verlet_cloth.comp: one cloth step as a GL 4.3 compute shader, one invocation per particle.
// The step is docs/semantics.md (Listing 22.1), operation for operation; its code below is
// the same text as in verlet_cloth.frag, only the data access differs.
//
// State: std430 arrays of vec4 (a vec3 array would be padded to 16 bytes anyway), particle
// i = row * n + col, w = inverse mass. The host ping-pongs two (pos, prev) pairs of buffers
// by swapping which pair is read and which is written (bindings 2-3).
//
// The host (clothbench/backends/glsl_compute.py) prepends #version 430, LOCAL_SIZE and:
//   STRICT       bit-exact with the numpy float32 reference: the documented operation order,
//                every temporary `precise`, no dot/length/normalize/cross.
//   NORMALS      also write the particle's normal (docs/normals.md) to binding 4.
//   GENERIC      constants are uniforms; otherwise exact literals (*_VALUE: float32 bits).
//   IMAGE_READS  read the input pair through imageBuffer views of the same buffers rather
//                than as SSBOs: llvmpipe loads an SSBO one lane at a time, with a bounds
//                test per component, and an image with vector gathers (half the step time
//                at n = 256). The bits read are the same.
//   PASS         which particles this dispatch covers: PASS_ALL (every particle, with
//                bounds tests), PASS_INTERIOR (2 or more from every edge: all 12 neighbours
//                exist, no tests) or PASS_BORDER (the 8n - 16 others, with tests).

#define PASS_ALL 0
#define PASS_INTERIOR 1
#define PASS_BORDER 2
#if PASS == PASS_INTERIOR
#define NO_BOUNDS_TESTS
#endif

layout(local_size_x = LOCAL_SIZE) in;

#ifdef IMAGE_READS
layout(rgba32f, binding = 0) readonly uniform imageBuffer pos_in;   // x(t)
layout(rgba32f, binding = 1) readonly uniform imageBuffer prev_in;  // x(t - dt)
#define LOAD(buf, i) imageLoad(buf, i)
#else
layout(std430, binding = 0) readonly buffer PosIn { vec4 pos_in[]; };    // x(t)
layout(std430, binding = 1) readonly buffer PrevIn { vec4 prev_in[]; };  // x(t - dt)
#define LOAD(buf, i) buf[i]
#endif
layout(std430, binding = 2) writeonly buffer PosOut { vec4 pos_out[]; };    // x(t + dt)
layout(std430, binding = 3) writeonly buffer PrevOut { vec4 prev_out[]; };  // x(t)
#ifdef NORMALS
layout(std430, binding = 4) writeonly buffer NormalOut { vec4 normal_out[]; };
#endif
#define POS(rc) LOAD(pos_in, (rc).x * n + (rc).y).xyz

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

// (row, col) of this invocation's particle, or (-1, -1) past the end of the pass
ivec2 particle()
{
    // the host spreads large dispatches over y (GL promises 65535 groups per dimension)
    int t = int(gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * LOCAL_SIZE
            + int(gl_LocalInvocationID.x);
#if PASS == PASS_INTERIOR
    int m = n - 4;  // the interior is the (n - 4)^2 block from (2, 2)
    return t < m * m ? ivec2(2 + t / m, 2 + t % m) : ivec2(-1);
#elif PASS == PASS_BORDER
    // rows 0, 1, n-2, n-1 in full (4n particles), then columns 0, 1, n-2, n-1 of rows 2..n-3
    if (t < 4 * n) {
        int r = t / n;
        return ivec2(r < 2 ? r : n - 4 + r, t % n);
    }
    t -= 4 * n;
    if (t >= 4 * (n - 4))
        return ivec2(-1);
    int c = t % 4;
    return ivec2(2 + t / 4, c < 2 ? c : n - 4 + c);
#else
    return t < n * n ? ivec2(t / n, t % n) : ivec2(-1);
#endif
}

void main()
{
    ivec2 rc = particle();
    if (rc.x < 0)
        return;
    int i = rc.x * n + rc.y;
    vec4 self = LOAD(pos_in, i);
    vec3 x = self.xyz;                // step 1
    vec3 xp = LOAD(prev_in, i).xyz;  // step 2
    pos_out[i] = vec4(verlet(rc, x, xp, self.w), self.w);  // step 7
    prev_out[i] = self;                                    // step 8: x(t), w unchanged
#ifdef NORMALS
    normal_out[i] = vec4(normal_at(rc, x), 0.0);
#endif
}
