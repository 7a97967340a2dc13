// self_collision.comp: the search of the [self_collision] pass (docs/semantics.md, "The search:
// a uniform grid, sorted") for the glsl-compute solvers, one invocation per slot of the sort:
//   SELF_STAGE 0  every particle's cell id and index (kernels/self_collision.glsl)
//   SELF_STAGE 1  one compare-and-exchange stage of a bitonic sort by (id, index): the host
//                 dispatches it once per stage (uniforms sort_j, sort_k), a memory barrier
//                 after each, so the sort needs no atomics and orders the same every run.
// The host (clothbench/backends/gl/self_contact.py) prepends #version 430, LOCAL_SIZE,
// SELF_STAGE, N_VALUE and self_collision.glsl's defines. Positions: vec4 rows at binding 0.

layout(local_size_x = LOCAL_SIZE) in;
layout(std430, binding = 0) readonly buffer Positions { vec4 x_in[]; };
#define SELF_X(j) x_in[j]

#include <self_collision>

uniform int sort_j, sort_k;

void main()
{
    // the host spreads large dispatches over y (GL promises 65535 groups per dimension)
    int s = int(gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * LOCAL_SIZE + int(gl_LocalInvocationID.x);
    if (s >= SELF_SLOTS)
        return;
#if SELF_STAGE == 0
    self_cell_key(s, N_VALUE * N_VALUE);
#else
    self_sort_stage(s, sort_j, sort_k);
#endif
}
