// vbd_cloth.comp: the VBD cloth solver (implicit Euler by Vertex Block Descent) as GL 4.3
// compute shaders, one program per stage (STAGE below). The solver and the order of every
// operation are docs/vbd.md; the colliders docs/semantics.md (the shared kernels/collide_*.glsl).
// Host: clothbench/backends/gl/compute_vbd.py.
//
// State: std430 arrays of vec4 (w = inverse mass, 0 = pinned): x (positions at the start of
// the substep), v (velocity, w unused), xs (the iterate, swept in place), y (the inertial
// target), and with Chebyshev two buffers of earlier iterates. The host dispatches, per
// substep, with a memory barrier after every dispatch (the next one reads its writes):
//   STAGE_PREDICT    x, v -> y, xs
//   iterations x (STAGE_SWEEP once per vertex colour, then with Chebyshev STAGE_CHEBYSHEV)
//   STAGE_COLLIDE    xs in place (only when the scene has colliders or meshes); or, with
//   STAGE_SELF_COLLISION  ([self_collision] only, after the host's keys and sort,
//                    kernels/self_collision.comp) xs -> y: pushed apart, then collided
//   STAGE_UPDATE     x, xs -> v, x
// A sweep dispatch updates the particles of one colour (docs/vbd.md, "Vertex colours"): no two
// share a spring, so each reads only neighbours no other invocation of the dispatch writes,
// and how the colour is spread over invocations changes no bit.
//
// The host prepends #version 430 and:
//   LOCAL_SIZE   work-group size
//   IMAGE_READS  the sweep reads the iterate through an imageBuffer view of its buffer (vector
//                gathers on llvmpipe, where an SSBO load goes lane by lane; docs/llvmpipe.md)
//   STRICT       bit-exact with the numpy float32 reference: docs/vbd.md's operation order,
//                every temporary `precise` (no contraction), sqrt and '/', no dot/length.
//                Without it (fast): one inversesqrt per spring, contraction allowed.
//   N_VALUE, H_VALUE, GH2_VALUE, MH2_VALUE, BH_VALUE, K_VALUE, REST_VALUE and the collider
//                constants: exact float32 literals, rounded once from float64
//                (model/kernel_inputs.py VbdConstants).
//   MESH_*, MOTION, PIN_ATTACH  meshes, moving colliders and pins attached to a body, as
//                pbd_cloth.comp takes them (gl/context.py body_defines, GLBodies): with MOTION
//                the collider rows and pin targets are one block per substep, at its end.

#ifdef STRICT
#define P precise
#else
#define P
#endif

#define STAGE_PREDICT 0
#define STAGE_SWEEP 1
#define STAGE_CHEBYSHEV 2
#define STAGE_COLLIDE 3
#define STAGE_UPDATE 4
#define STAGE_SELF_COLLISION 5

layout(local_size_x = LOCAL_SIZE) in;

const int n = N_VALUE;
const int n2 = N_VALUE * N_VALUE;
const float h = H_VALUE;               // dt / substeps
const vec3 gh2 = GH2_VALUE;            // g * h^2
const float mh2 = MH2_VALUE;           // m / h^2: the inertia's stiffness
const float bh = BH_VALUE;             // b / h: one spring's share of the damping's stiffness
const float k = K_VALUE;
const float rest[3] = REST_VALUE;      // rest lengths: structural, shear, bend

// (a.x*b.x + a.y*b.y) + a.z*b.z in strict mode; dot() is the driver's order (the sweep's and the
// colliders')
float dot3(vec3 a, vec3 c)
{
#ifdef STRICT
    P float s = (a.x * c.x + a.y * c.y) + a.z * c.z;
    return s;
#else
    return dot(a, c);
#endif
}

// this invocation's item (particle, or place in a colour); the host spreads large dispatches
// over y
int item()
{
    return int(gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * LOCAL_SIZE
           + int(gl_LocalInvocationID.x);
}

#ifdef MOTION
// a scene that moves: this substep's rows (pbd_cloth.comp's layout, gl/context.py motion_offsets)
layout(std430, binding = 6) readonly buffer MotionRows { vec4 motion_rows[]; };
uniform int motion_step;  // this substep's place in the uploaded block
#define MOTION_ROW(j) motion_rows[motion_step * MOTION_STRIDE + (j)]
#endif

#if STAGE == STAGE_PREDICT
layout(std430, binding = 0) readonly buffer Pos { vec4 x[]; };
layout(std430, binding = 1) readonly buffer Vel { vec4 v[]; };
layout(std430, binding = 2) writeonly buffer Iterate { vec4 xs[]; };
layout(std430, binding = 3) writeonly buffer Target { vec4 y[]; };

#ifdef PIN_ATTACH
// pins that follow a body: per particle its row among the pin targets, or -1
layout(std430, binding = 10) readonly buffer PinSlots { int pin_slot[]; };
#endif

// y = (x + v*h) + g*h^2 and the first iterate xs = y; a pinned particle stays (xs = x), or,
// following a body, goes to its target at the end of the substep (its y is never read)
void main()
{
    int i = item();
    if (i >= n2)
        return;
    vec4 p = x[i];
    if (p.w == 0.0) {
#ifdef PIN_ATTACH
        int slot = pin_slot[i];
        if (slot >= 0)
            p = vec4(MOTION_ROW(MOTION_PINS + slot).xyz, p.w);
#endif
        xs[i] = p;
        y[i] = p;
        return;
    }
    P vec3 target = (p.xyz + v[i].xyz * h) + gh2;
    xs[i] = vec4(target, p.w);
    y[i] = vec4(target, p.w);
}

#elif STAGE == STAGE_SWEEP
// the iterate, updated in place; with IMAGE_READS read through an imageBuffer view of the same
// buffer (the neighbours are of other colours: no invocation of this dispatch writes them)
layout(std430, binding = 0) buffer Iterate { vec4 X[]; };
#ifdef IMAGE_READS
layout(rgba32f, binding = 0) readonly uniform imageBuffer X_in;
#define LOAD_X(i) imageLoad(X_in, i)
#else
#define LOAD_X(i) X[i]
#endif
layout(std430, binding = 1) readonly buffer Target { vec4 y[]; };
layout(std430, binding = 2) readonly buffer Pos { vec4 x[]; };
layout(std430, binding = 3) readonly buffer Order { int order[]; };  // every particle, by colour
uniform int first, count;  // this colour's range of order

// the 12-spring stencil (d_row, d_col) in the order docs/semantics.md fixes; offsets 0-3 are
// structural, 4-7 shear, 8-11 bend (rest[o >> 2])
const ivec2 OFFSETS[12] = ivec2[12](
    ivec2(0, -1), ivec2(0, 1), ivec2(-1, 0), ivec2(1, 0),     // structural
    ivec2(-1, -1), ivec2(-1, 1), ivec2(1, -1), ivec2(1, 1),   // shear
    ivec2(-2, -2), ivec2(-2, 2), ivec2(2, -2), ivec2(2, 2));  // bend

// one free particle's 3x3 Newton step on the incremental potential, its neighbours (of other
// colours) held: docs/vbd.md, "One particle's step", operation for operation
vec3 newton_step(ivec2 rc, vec3 xi, vec3 yi, vec3 x0)
{
    int cnt = 0;  // the springs the particle has: an exact small integer
    for (int o = 0; o < 12; ++o) {
        ivec2 rj = rc + OFFSETS[o];
        cnt += all(greaterThanEqual(rj, ivec2(0))) && all(lessThan(rj, ivec2(n))) ? 1 : 0;
    }
    P float cb = float(cnt) * bh;
    P float hd = mh2 + cb;
    P vec3 f = (xi - yi) * mh2 + (xi - x0) * cb;
    P float hxx = hd, hyy = hd, hzz = hd, hxy = 0.0, hxz = 0.0, hyz = 0.0;
    for (int o = 0; o < 12; ++o) {
        ivec2 rj = rc + OFFSETS[o];
        if (any(lessThan(rj, ivec2(0))) || any(greaterThanEqual(rj, ivec2(n))))
            continue;  // outside the grid: nothing added
        P vec3 d = xi - LOAD_X(rj.x * n + rj.y).xyz;
        P float L2 = dot3(d, d);
        if (!(L2 > 0.0))
            continue;  // coincident: nothing added
#ifdef STRICT
        P float L = sqrt(L2);
        P float s = k * (1.0 - rest[o >> 2] / L);
#else
        float s = k * (1.0 - rest[o >> 2] * inversesqrt(L2));
#endif
        f = f + d * s;
        P float a = s > 0.0 ? s : 0.0;  // the clamped isotropic part: k max(1 - rest/L, 0)
        P float bb = (k - a) / L2;
        P vec3 bd = bb * d;  // bx, by, bz
        hxx = hxx + (a + bd.x * d.x);
        hyy = hyy + (a + bd.y * d.y);
        hzz = hzz + (a + bd.z * d.z);
        hxy = hxy + bd.x * d.y;
        hxz = hxz + bd.x * d.z;
        hyz = hyz + bd.y * d.z;
    }
    // H p = f by LDL^T, in docs/vbd.md's order
    P float l10 = hxy / hxx;
    P float l20 = hxz / hxx;
    P float d1 = hyy - l10 * hxy;
    P float t = hyz - l20 * hxy;
    P float l21 = t / d1;
    P float d2 = (hzz - l20 * hxz) - l21 * t;
    P float z1 = f.y - l10 * f.x;
    P float z2 = (f.z - l20 * f.x) - l21 * z1;
    P float pz = z2 / d2;
    P float py = z1 / d1 - l21 * pz;
    P float px = (f.x / hxx - l10 * py) - l20 * pz;
    if (hxx > 0.0 && d1 > 0.0 && d2 > 0.0) {
        P vec3 stepped = xi - vec3(px, py, pz);
        return stepped;
    }
    return xi;  // never for a finite state: H is positive definite
}

// one colour of a sweep: the particles order[first .. first + count - 1] (every particle of
// the colour; a pinned one returns), each one Newton step
void main()
{
    int t = item();
    if (t >= count)
        return;
    int i = order[first + t];
    vec4 p = LOAD_X(i);
    if (p.w == 0.0)
        return;
    X[i] = vec4(newton_step(ivec2(i / n, i % n), p.xyz, y[i].xyz, x[i].xyz), p.w);
}

#elif STAGE == STAGE_CHEBYSHEV
layout(std430, binding = 0) buffer Iterate { vec4 X[]; };
layout(std430, binding = 1) buffer Before { vec4 before[]; };
uniform float omega;  // this sweep's Chebyshev weight
uniform int apply;    // 0: only keep X (the first sweep's input, or after sweep 0)

// docs/vbd.md, "Chebyshev acceleration": with `apply`, X = omega (X - before) + before for the
// free particles; then, applied or not, `before` takes X: the input of the next sweep, which
// the extrapolation after the sweep after it reads
void main()
{
    int i = item();
    if (i >= n2)
        return;
    vec4 p = X[i];
    if (apply != 0 && p.w != 0.0) {
        vec3 b = before[i].xyz;
        P vec3 e = omega * (p.xyz - b) + b;
        p = vec4(e, p.w);
        X[i] = p;
    }
    before[i] = p;
}

#elif STAGE == STAGE_COLLIDE || STAGE == STAGE_SELF_COLLISION
#if STAGE == STAGE_COLLIDE
layout(std430, binding = 0) buffer Iterate { vec4 xs[]; };
#else
// the final iterate, read by every particle's pass (kernels/self_collision.glsl), and the
// pushed one, into y (no longer read: the sweeps are done), which update reads
layout(std430, binding = 0) readonly buffer From { vec4 X[]; };
layout(std430, binding = 1) writeonly buffer To { vec4 Y[]; };
#define SELF_X(j) X[j]
#include <self_collision>  // kernels/self_collision.glsl, where the scene has the table
#endif

// `vec3 collide(vec3 x)`: the scene's colliders in the fixed order (spheres, cylinders,
// boxes, planes, meshes), from kernels/collide_KIND.glsl and collide_mesh.glsl (the host puts
// them here; with MOTION they read this substep's rows)
#include <colliders>

#if STAGE == STAGE_COLLIDE
// collisions as position projections on the final iterate, free particles only
void main()
{
    int i = item();
    if (i >= n2)
        return;
    vec4 p = xs[i];
    if (p.w == 0.0)
        return;  // pinned particles are never collided
    xs[i] = vec4(collide(p.xyz), p.w);
}
#else
// the pass (docs/semantics.md, "Self-collision"), then the colliders, free particles only
void main()
{
    int i = item();
    if (i >= n2)
        return;
    float w = X[i].w;
    vec3 x = self_push(i, n);
    if (w != 0.0)
        x = collide(x);
    Y[i] = vec4(x, w);
}
#endif

#elif STAGE == STAGE_UPDATE
layout(std430, binding = 0) buffer Pos { vec4 x[]; };
layout(std430, binding = 1) writeonly buffer Vel { vec4 v[]; };
layout(std430, binding = 2) readonly buffer Iterate { vec4 xs[]; };

// v = (xs - x) / h (no damping factor: the damping is in the potential); x = xs
void main()
{
    int i = item();
    if (i >= n2)
        return;
    vec4 p = xs[i];
    P vec3 vel = (p.xyz - x[i].xyz) / h;
    v[i] = vec4(vel, 0.0);
    x[i] = p;
}
#endif
