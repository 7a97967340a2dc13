// verlet_cloth.frag: one cloth step per fragment, the chapter's section 22.6 in core-profile
// GLSL. The step itself (docs/semantics.md, Listing 22.1) is kernels/verlet_cloth_step.glsl,
// shared with the compute shader; this file is the data access around it.
//
// One fragment per texel of an n x n viewport, one texel per particle: texel (x, y) is
// particle (row = y, col = x). The inputs are RGBA32F textures read texel by texel (no
// filtering, integer coordinates); the outputs are render targets: the new position, the
// new previous position and, with NORMALS only, the normal.
//
// The host (clothbench/backends/gl/fragment.py) prepends #version and the switches of the shared
// step (STRICT, NORMALS, GENERIC, the constants: see verlet_cloth_step.glsl), and:
//   NORMALS      also write the particle's normal to a third target.
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

// the step (docs/semantics.md), shared with the other kernel; it reads POS(rc) above
#include "verlet_cloth_step.glsl"

void main()
{
    // (A branch that skips the bounds tests for interior particles, as the compute shader
    // does, made llvmpipe's fragment shader slower, not faster: measured.)
    ivec2 rc = ivec2(gl_FragCoord.yx);  // (row, col)
#ifdef MOTION
    motion_base = motion_step * MOTION_STRIDE;  // this step's rows (verlet_cloth_step.glsl)
#endif
    vec4 self = LOAD(pos_tex, rc);
    vec3 x = self.xyz;                // step 1
    vec3 xp = LOAD(prev_tex, rc).xyz;  // step 2
    pos_out = vec4(verlet(rc, x, xp, self.w), self.w);  // step 7
    prev_out = self;                                    // step 8: x(t), w unchanged
#ifdef NORMALS
    normal_out = vec4(normal_at(rc, x), 0.0);
#endif
}
