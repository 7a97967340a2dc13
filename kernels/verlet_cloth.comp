// verlet_cloth.comp: one cloth step as a GL 4.3 compute shader, one invocation per particle.
// The step itself (docs/semantics.md, Listing 22.1) is kernels/verlet_cloth_step.glsl, shared
// with the fragment shader; this file is the data access around it.
//
// State: std430 arrays of vec4 (a vec3 array would be padded to 16 bytes anyway), particle
// i = row * n + col, w = inverse mass, in two buffers: x(t) at binding 0 and x(t - dt) at
// binding 1. A step writes x(t + dt) in place over x(t - dt) (only this particle's invocation
// reads that slot, the neighbours are read from binding 0), and the host swaps the two
// buffers' roles: step 8 (x(t - dt) <- x(t)) is that swap. 48 bytes a particle a step where
// the chapter's two pairs of buffers (x(t), x(t - dt)) -> (x(t + dt), x(t)) move 64.
//
// The host (clothbench/backends/gl/compute.py) prepends #version 430, LOCAL_SIZE, the
// switches of the shared step (STRICT, NORMALS, GENERIC, the constants: see
// verlet_cloth_step.glsl), and:
//   NORMALS      also write the particle's normal to binding 4.
//   IMAGE_READS  read x(t), the neighbours' positions, through an imageBuffer view of the
//                same buffer rather than as an SSBO: llvmpipe loads an SSBO one lane at a
//                time, with a bounds test per component, and an image with vector gathers
//                (half the step time at n = 256). The bits read are the same. x(t - dt),
//                read and written by its own invocation, stays an SSBO.
//   PASS         which particles this dispatch covers: PASS_ALL (every particle, with
//                bounds tests), PASS_INTERIOR (2 or more from every edge: all 12 neighbours
//                exist, no tests) or PASS_BORDER (the 8n - 16 others, with tests).
//   TILE_W, TILE_H  (interior pass only) 2-D work groups of TILE_W columns x TILE_H rows
//                over the interior block, dispatched as a 2-D grid of groups, instead of
//                LOCAL_SIZE consecutive particles: the kernel shape "wg=WxH"
//                (clothbench/backends/gl/shapes.py). The operations on a particle are the same.
//   SELF_COLLISION  (a scene with [self_collision] only) the step leaves the colliders out and
//                writes x_new to binding 2; the program with PASS_SELF_COLLISION then reads every
//                particle's x_new at binding 0 (pos_in), pushes the pairs apart
//                (kernels/self_collision.glsl), collides, and writes pos_out (binding 2, there
//                the x(t - dt) buffer): the colliders act after the pass, as docs/semantics.md
//                places them.

#define PASS_ALL 0
#define PASS_INTERIOR 1
#define PASS_BORDER 2
#define PASS_SELF_COLLISION 3
#if PASS == PASS_INTERIOR
#define NO_BOUNDS_TESTS
#endif

#if defined(TILE_W) && PASS == PASS_INTERIOR
layout(local_size_x = TILE_W, local_size_y = TILE_H) in;
#else
layout(local_size_x = LOCAL_SIZE) in;
#endif

#ifdef IMAGE_READS
layout(rgba32f, binding = 0) readonly uniform imageBuffer pos_in;  // x(t)
#define LOAD(buf, i) imageLoad(buf, i)
#else
layout(std430, binding = 0) readonly buffer PosIn { vec4 pos_in[]; };  // x(t)
#define LOAD(buf, i) buf[i]
#endif
layout(std430, binding = 1) buffer Prev { vec4 prev[]; };  // x(t - dt) in, x(t + dt) out
#ifdef SELF_COLLISION
layout(std430, binding = 2) writeonly buffer PosOut { vec4 pos_out[]; };  // step: x_new; pass: x(t + dt)
#endif
#ifdef NORMALS
layout(std430, binding = 4) writeonly buffer NormalOut { vec4 normal_out[]; };
#endif
#define POS(rc) LOAD(pos_in, (rc).x * n + (rc).y).xyz

// the step (docs/semantics.md), shared with the other kernel; it reads POS(rc) above
#include "verlet_cloth_step.glsl"

#if PASS == PASS_SELF_COLLISION
#define SELF_X(j) LOAD(pos_in, j)  // x_new: the step's output, before the pass
#include <self_collision>  // kernels/self_collision.glsl, where the scene has the table
#endif

// (row, col) of this invocation's particle, or (-1, -1) past the end of the pass
ivec2 particle()
{
#if defined(TILE_W) && PASS == PASS_INTERIOR
    ivec2 g = ivec2(gl_GlobalInvocationID.xy);  // (col, row) within the interior block
    return all(lessThan(g, ivec2(n - 4))) ? ivec2(2 + g.y, 2 + g.x) : ivec2(-1);
#else
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
#endif
}

void main()
{
    ivec2 rc = particle();
    if (rc.x < 0)
        return;
    int i = rc.x * n + rc.y;
#ifdef MOTION
    motion_base = motion_step * MOTION_STRIDE;  // this step's rows (verlet_cloth_step.glsl)
#endif
#if PASS == PASS_SELF_COLLISION
    float w = LOAD(pos_in, i).w;
    vec3 x = self_push(i, n);
    if (w != 0.0)
        x = collide(x);  // then the colliders, as the step would have: free particles only
    pos_out[i] = vec4(x, w);
#else
    vec4 self = LOAD(pos_in, i);
    vec3 x = self.xyz;      // step 1
    vec3 xp = prev[i].xyz;  // step 2
    vec4 x_new = vec4(verlet(rc, x, xp, self.w), self.w);
#ifdef SELF_COLLISION
    pos_out[i] = x_new;  // the pass pushes it apart, collides it and writes it over x(t - dt)
#else
    prev[i] = x_new;  // step 7, over x(t - dt); step 8 is the host's swap of the buffers
#endif
#ifdef NORMALS
    normal_out[i] = vec4(normal_at(rc, x), 0.0);
#endif
#endif
}
