/*
 * self_collision.cuh: the [self_collision] pass of docs/semantics.md ("Self-collision"),
 * operation for operation, then the colliders. verlet_cloth.cu includes it only with
 * -DCLOTH_SELF_COLLISION (where the scene has the table); verlet_step then leaves the
 * colliders to `self_collision`, so they act after the pass, as the definition places them.
 *
 * A pass is three kinds of launch after verlet_step, in stream order (docs/cuda.md,
 * "Self-collision"): self_cell_keys (each particle's cell), self_sort_stage once per stage of a
 * bitonic sort (the particles by cell, then index), then self_collision, one thread per
 * particle reading the step's x_new (x_in) and writing its own position (x_out): a Jacobi
 * projection, race-free, no atomics. Its candidates are the particles of the 27 cells around
 * its own, merged in ascending index: the sum's order, hence the NumPy reference's bits.
 *
 * The numbers are kernel_inputs.SelfCollisionConstants, rounded once on the host: thickness,
 * thickness2, relax, inv_cell and the integer exclude2 (pairs closer than that on the grid at
 * rest are excluded like stencil neighbours). `slots` is the sort's length, the particle count
 * rounded up to a power of two (an argument, so the generic build serves every grid).
 */

typedef unsigned long long cell_id_t;  // 21 bits an axis: x the low field

#define KEY_LIMIT 1048576  // colliders/self_contact.py KEY_LIMIT: 2^20
#define NO_CELL 0xffffffffffffffffULL  // pad slots and positions that are not finite: sorted last

// Whether particles (dr, dc) apart on the grid are joined by a spring or closer at rest than
// the thickness (dr^2 + dc^2 < exclude2).
__device__ __forceinline__ bool self_excluded(int dr, int dc, int exclude2)
{
    if (dr * dr + dc * dc < exclude2) return true;
    const Offset stencil[12] = STENCIL;
    for (int o = 0; o < 12; ++o)
        if (stencil[o].dr == dr && stencil[o].dc == dc) return true;
    return false;
}

__device__ __forceinline__ bool finite3(float3 x)
{
    return isfinite(x.x) && isfinite(x.y) && isfinite(x.z);
}

// One axis of the cell key: floor(x * inv_cell) in float32, clamped to [-KEY_LIMIT, KEY_LIMIT - 1].
__device__ __forceinline__ int cell_axis(float x, float inv_cell)
{
    return (int)fminf(fmaxf(floorf(x * inv_cell), (float)-KEY_LIMIT), (float)(KEY_LIMIT - 1));
}

__device__ __forceinline__ int clamp_axis(int k)
{
    return k < -KEY_LIMIT ? -KEY_LIMIT : (k > KEY_LIMIT - 1 ? KEY_LIMIT - 1 : k);
}

__device__ __forceinline__ cell_id_t cell_id(int kx, int ky, int kz)
{
    return (cell_id_t)(kx + KEY_LIMIT) | ((cell_id_t)(ky + KEY_LIMIT) << 21) | ((cell_id_t)(kz + KEY_LIMIT) << 42);
}

// Slot s: particle s's cell id, or NO_CELL (a pad slot, or a position that is not finite).
extern "C" __global__ void self_cell_keys(const float4* __restrict__ x_in, cell_id_t* __restrict__ keys,
                                          int* __restrict__ order, float inv_cell, int count, int slots)
{
    const int s = blockIdx.x * blockDim.x + threadIdx.x;
    if (s >= slots) return;
    cell_id_t id = NO_CELL;
    if (s < count) {
        const float4 p = x_in[s];
        if (finite3(make_float3(p.x, p.y, p.z)))
            id = cell_id(cell_axis(p.x, inv_cell), cell_axis(p.y, inv_cell), cell_axis(p.z, inv_cell));
    }
    keys[s] = id;
    order[s] = s;
}

// One compare-and-exchange stage (block k, distance j) of the bitonic sort by (id, index): the
// same order whatever the run, and within a cell ascending index.
extern "C" __global__ void self_sort_stage(cell_id_t* __restrict__ keys, int* __restrict__ order, int j, int k,
                                           int slots)
{
    const int s = blockIdx.x * blockDim.x + threadIdx.x;
    const int t = s ^ j;
    if (s >= slots || t <= s) return;
    const cell_id_t ks = keys[s], kt = keys[t];
    const int os = order[s], ot = order[t];
    const bool later = ks > kt || (ks == kt && os > ot);  // s after t in (id, index) order
    if (((s & k) == 0) == later) {  // ascending blocks put the smaller first, descending last
        keys[s] = kt, keys[t] = ks;
        order[s] = ot, order[t] = os;
    }
}

// The first slot whose id is at least `id` (keys sorted).
__device__ __forceinline__ int lower_slot(const cell_id_t* __restrict__ keys, int slots, cell_id_t id)
{
    int lo = 0, hi = slots;
    while (lo < hi) {
        const int mid = (lo + hi) / 2;
        if (keys[mid] < id) lo = mid + 1;
        else hi = mid;
    }
    return lo;
}

__device__ __forceinline__ float3 position_of(const float4* __restrict__ x, int j)
{
    const float4 p = x[j];
    return make_float3(p.x, p.y, p.z);
}

// Particle i's position after the pass: x_i plus its pairs' corrections, summed in ascending j:
// the runs of the 27 cells around i's (each distinct cell once, sorted by index) merged by
// smallest j.
__device__ float3 self_push(int i, int n, const float4* __restrict__ x_in, const cell_id_t* __restrict__ keys,
                            const int* __restrict__ order, int slots, float thickness, float thickness2,
                            float relax, float inv_cell, int exclude2)
{
    const float4 pi = x_in[i];
    const float3 xi = make_float3(pi.x, pi.y, pi.z);
    const float wi = pi.w;
    if (!(wi > 0.0f) || !finite3(xi)) return xi;  // a pinned particle does not move; one not finite is in no pair
    // The 27 cells as nine rows along x: a row's cells have consecutive ids (x is the id's low
    // field), so one search finds the row's first particle and a scan its cells' runs; a cell
    // clamping made one with its neighbour is one id, met once. Rows are one only at the key's
    // limits, where clamping makes them so: there a row met before is skipped.
    const int kx = cell_axis(xi.x, inv_cell), ky = cell_axis(xi.y, inv_cell), kz = cell_axis(xi.z, inv_cell);
    const bool edge = kx <= -KEY_LIMIT + 1 || ky <= -KEY_LIMIT + 1 || kz <= -KEY_LIMIT + 1 ||
                      kx >= KEY_LIMIT - 2 || ky >= KEY_LIMIT - 2 || kz >= KEY_LIMIT - 2;
    cell_id_t rows[9];
    int next[27], end[27], runs = 0, row_count = 0;
    for (int dy = -1; dy <= 1; ++dy)
        for (int dz = -1; dz <= 1; ++dz) {
            const int y = clamp_axis(ky + dy), z = clamp_axis(kz + dz);
            const cell_id_t lo = cell_id(clamp_axis(kx - 1), y, z), hi = cell_id(clamp_axis(kx + 1), y, z);
            bool seen = false;
            for (int r = 0; edge && r < row_count; ++r) seen = seen || rows[r] == lo;
            if (seen) continue;
            rows[row_count++] = lo;
            int slot = lower_slot(keys, slots, lo);
            while (slot < slots && keys[slot] <= hi) {  // each cell of the row: one run
                const cell_id_t id = keys[slot];
                next[runs] = slot;
                while (slot < slots && keys[slot] == id) ++slot;
                end[runs++] = slot;
            }
        }
    const int row = i / n, col = i % n;
    float3 corr = make_float3(0.0f, 0.0f, 0.0f);
    bool pushed = false;
    for (;;) {
        int best = -1, j = 0;
        for (int r = 0; r < runs; ++r)
            if (next[r] < end[r] && (best < 0 || order[next[r]] < j)) best = r, j = order[next[r]];
        if (best < 0) break;
        ++next[best];
        const float3 d = minus(xi, position_of(x_in, j));
        const float L2 = dot3(d, d);
        // j == i has L2 = 0; coincident particles have no direction: nothing added
        if (!(L2 < thickness2) || !(L2 > 0.0f) || self_excluded(j / n - row, j % n - col, exclude2)) continue;
        const float wj = x_in[j].w;
        const float L = sqrtf(L2);
        const float share = wi / (wi + wj);  // i's part of the shortfall, by inverse mass
        float s = relax * (thickness - L);
        s = s * share;
        s = s / L;
        const float3 push = make_float3(d.x * s, d.y * s, d.z * s);  // rounded, then added
        corr = make_float3(corr.x + push.x, corr.y + push.y, corr.z + push.z);
        pushed = true;
    }
    return pushed ? make_float3(xi.x + corr.x, xi.y + corr.y, xi.z + corr.z) : xi;
}

// The pass: x_out = x_in pushed apart, then (free particles) collided, as verlet_step would
// have; w carried over. Generic: n and the colliders are arguments; motion: the step's rows.
#ifdef CLOTH_GENERIC
#define PASS_PARAMS , int n COLLIDE_PARAMS
#else
#define PASS_PARAMS
#endif
extern "C" __global__ void self_collision(const float4* __restrict__ x_in, float4* __restrict__ x_out,
                                          const cell_id_t* __restrict__ keys, const int* __restrict__ order,
                                          int slots, float thickness, float thickness2, float relax,
                                          float inv_cell, int exclude2 PASS_PARAMS MESH_PARAMS ROWS_PARAM)
{
    const int i = blockIdx.x * blockDim.x + threadIdx.x;
    if (i >= n * n) return;
    const float w = x_in[i].w;
    float3 x = self_push(i, n, x_in, keys, order, slots, thickness, thickness2, relax, inv_cell, exclude2);
    if (w != 0.0f) x = apply_colliders(x COLLIDE_ARGS MESH_ARGS ROWS_ARG);  // then the colliders
    x_out[i] = make_float4(x.x, x.y, x.z, w);
}
