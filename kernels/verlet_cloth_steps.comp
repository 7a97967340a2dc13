// verlet_cloth_steps.comp: several cloth steps in one dispatch of ONE work group that holds
// the whole grid (small grids only), the kernel shape "steps/dispatch=K" of glsl-compute
// (clothbench/backends/gl/shapes.py). The step itself is kernels/verlet_cloth_step.glsl,
// as for verlet_cloth.comp; only the data access differs.
//
// Each invocation owns the particles t = gl_LocalInvocationID.x + j * LOCAL_SIZE (j < PPI),
// so the SIMD lanes of llvmpipe still take consecutive particles. Its own x(t) and x(t - dt)
// stay in registers for the whole dispatch; the positions its neighbours need are in shared
// memory (SCRATCH_SHARED) or a scratch storage buffer (otherwise), twice: a step reads one
// half and writes the other, then barrier() makes the writes visible before the next step
// reads them (one barrier per step: the half a step writes was last read before the
// previous barrier). `steps` (a uniform) steps run; the host dispatches K at most at a time.
// A scene that moves reads step s's rows at motion_step + s of the block the host uploaded.
// State: the two buffers of verlet_cloth.comp, x(t) at binding 0 and x(t - dt) at binding 1;
// after the last step x(t + K dt) is written over binding 1 and x(t + (K - 1) dt) over
// binding 0 (each invocation reads and writes only its own particles there, and reads them
// all before the first barrier), and the host swaps the buffers' roles, as after a step of
// verlet_cloth.comp. With NORMALS, the normals of the state the last step read at binding 4.
//
// The host prepends #version 430, the switches of the shared step (STRICT, NORMALS,
// GENERIC, the constants), LOCAL_SIZE, PPI (particles per invocation), CAPACITY (particles
// the scratch holds, >= n * n) and SCRATCH_SHARED where 6 floats per particle fit in the
// driver's shared memory.

layout(local_size_x = LOCAL_SIZE) in;

layout(std430, binding = 0) buffer Pos { vec4 pos[]; };    // x(t) in, x(t + (K - 1) dt) out
layout(std430, binding = 1) buffer Prev { vec4 prev[]; };  // x(t - dt) in, x(t + K dt) out
#ifdef NORMALS
layout(std430, binding = 4) writeonly buffer NormalOut { vec4 normal_out[]; };
#endif

uniform int steps;  // steps this dispatch runs (>= 1)

// the two halves of the scratch, one float array per coordinate: [0, CAPACITY) and
// [CAPACITY, 2 * CAPACITY)
#ifdef SCRATCH_SHARED
shared float sx[2 * CAPACITY];
shared float sy[2 * CAPACITY];
shared float sz[2 * CAPACITY];
#define SYNC() memoryBarrierShared(); barrier()
#else
layout(std430, binding = 5) coherent buffer Scratch { float sx[2 * CAPACITY]; float sy[2 * CAPACITY]; float sz[2 * CAPACITY]; };
#define SYNC() memoryBarrierBuffer(); barrier()
#endif

int half_read = 0;  // offset of the half the current step reads: 0 or CAPACITY
#define POS(rc) scratch_at(half_read + (rc).x * n + (rc).y)

vec3 scratch_at(int i)
{
    return vec3(sx[i], sy[i], sz[i]);
}

void scratch_put(int i, vec3 v)
{
    sx[i] = v.x;
    sy[i] = v.y;
    sz[i] = v.z;
}

// the step (docs/semantics.md), shared with the other kernels; it reads POS(rc) above
#include "verlet_cloth_step.glsl"

void main()
{
    int first = int(gl_LocalInvocationID.x);
    vec3 x[PPI], xp[PPI];  // this invocation's particles: x(t), x(t - dt)
    float w[PPI];          // inverse mass, never changed by a step
    for (int j = 0; j < PPI; ++j) {
        int t = first + j * LOCAL_SIZE;
        if (t < n * n) {
            vec4 self = pos[t];
            x[j] = self.xyz;
            w[j] = self.w;
            xp[j] = prev[t].xyz;
            scratch_put(t, x[j]);
        }
    }
    SYNC();
    for (int s = 0; s < steps; ++s) {
#ifdef MOTION
        motion_base = (motion_step + s) * MOTION_STRIDE;  // this step's rows (verlet_cloth_step.glsl)
#endif
        vec3 x_new[PPI];
        for (int j = 0; j < PPI; ++j) {
            int t = first + j * LOCAL_SIZE;
            if (t < n * n)
                x_new[j] = verlet(ivec2(t / n, t % n), x[j], xp[j], w[j]);
        }
        int half_write = CAPACITY - half_read;
        for (int j = 0; j < PPI; ++j) {
            int t = first + j * LOCAL_SIZE;
            if (t < n * n) {
                scratch_put(half_write + t, x_new[j]);
                xp[j] = x[j];  // step 8
                x[j] = x_new[j];
            }
        }
        SYNC();
        half_read = half_write;
    }
#ifdef NORMALS
    half_read = CAPACITY - half_read;  // the half the last step read: x(t) = xp now
#endif
    for (int j = 0; j < PPI; ++j) {
        int t = first + j * LOCAL_SIZE;
        if (t < n * n) {
            prev[t] = vec4(x[j], w[j]);  // the latest state, in the buffer the host reads next as x(t)
            pos[t] = vec4(xp[j], w[j]);
#ifdef NORMALS
            normal_out[t] = vec4(normal_at(ivec2(t / n, t % n), xp[j]), 0.0);
#endif
        }
    }
}
