/* self_collision.cl: the [self_collision] pass of docs/semantics.md ("Self-collision"),
 * operation for operation, then the colliders, for verlet_cloth.cl (either build) and
 * pbd_cloth.cl (which defines CLOTH_PBD first). The host puts it in the source
 * (`#include <self_collision>`) only where the scene has the table. Verlet: with
 * CLOTH_SELF_COLLISION its kernels leave the colliders to `self_collision`, so they act after
 * the pass, as the definition places them. PBD: `pbd_self_collision` takes the place of
 * pbd_collide in the substep, after the last constraint iteration.
 *
 * A pass is four kinds of launch, in queue order: self_cell_keys (each particle's cell), a bitonic
 * sort of the particles by cell, then index (self_sort_local for the stages that stay within a
 * block of 2 SORT_GROUP slots, in local memory, self_sort_stage once for each longer one), then
 * the pass itself, one work item per particle reading the positions before the pass (x_in)
 * and writing its own (x_out): a Jacobi projection, race-free, no atomics. Its candidates are
 * the particles of the 27 cells around its own, merged in ascending index: the sum's order,
 * hence the NumPy reference's bits.
 *
 * Numbers (kernel_inputs.SelfCollisionConstants, rounded once on the host): c = (thickness,
 * thickness2, relax, inv_cell), and the integer exclude2 (pairs closer than that on the grid
 * at rest are excluded like stencil neighbours). CLOTH_SELF_SLOTS: the sort's length, the
 * particle count rounded up to a power of two; CLOTH_SELF_SORT_GROUP: the work-group size of
 * self_sort_local, a power of two, at most SLOTS / 2 (self_contact.py chooses it).
 */
#define SLOTS CLOTH_SELF_SLOTS
#define SORT_GROUP CLOTH_SELF_SORT_GROUP

#if defined(CLOTH_GENERIC) || defined(CLOTH_PBD)
/* float4 rows, the inverse mass in w */
#define SC_STATE __global const float4 *
#define SC_X(s, j) ((s)[j].xyz)
#define SC_W(s, inv_mass, j) ((s)[j].w)
#else
/* x, y, z planes (the pointer past CLOTH_PAD), the inverse mass in its own buffer */
#include "collide.cl"
#define SC_STATE __global const float *
#ifndef STATE_STRIDE
#define STATE_STRIDE N2 /* the planes of a state buffer n*n apart, where the step sets no pad */
#endif
#define SC_X(s, j) ((float3)((s)[j], (s)[STATE_STRIDE + (j)], (s)[2 * STATE_STRIDE + (j)]))
#define SC_W(s, inv_mass, j) ((inv_mass)[j])
#endif

/* Whether particles (dr, dc) apart on the grid are joined by a spring (scene.OFFSETS) or
 * closer at rest than the thickness (dr^2 + dc^2 < exclude2). */
bool self_excluded(int dr, int dc, int exclude2)
{
    if (dr * dr + dc * dc < exclude2)
        return true;
    if (abs(dr) > 2 || abs(dc) > 2) /* beyond every offset: most candidates end here */
        return false;
    for (int o = 0; o < 12; ++o)
        if (OFFSETS[o].x == dr && OFFSETS[o].y == dc)
            return true;
    return false;
}

/* ---- The search: a uniform grid of cells, sorted (docs/semantics.md, "The search"). Every
 * particle's cell key floor(x * inv_cell) per axis, clamped to [-KEY_LIMIT, KEY_LIMIT - 1], as
 * one ulong id (21 bits an axis); a bitonic sort of the (id, index) pairs over SLOTS, the
 * particle count rounded up to a power of two (the pad slots and non-finite particles, in no
 * pair, take the largest id): ordered by id and then index, the same whatever the run. ---- */
#define KEY_LIMIT 1048576 /* colliders/self_contact.py KEY_LIMIT: 2^20 */
#define NO_CELL ULONG_MAX

ulong cell_id(int3 k)
{
    return (ulong)(k.x + KEY_LIMIT) | ((ulong)(k.y + KEY_LIMIT) << 21) | ((ulong)(k.z + KEY_LIMIT) << 42);
}

/* the clamped cell coordinates of a finite position, in the working precision */
int3 cell_of(float3 x, float inv_cell)
{
    float3 k = clamp(floor(x * inv_cell), (float)-KEY_LIMIT, (float)(KEY_LIMIT - 1));
    return convert_int3(k);
}

bool finite3(float3 x)
{
    return isfinite(x.x) && isfinite(x.y) && isfinite(x.z);
}

/* slot s: particle s's id, or NO_CELL (a pad slot, or a position that is not finite) */
__kernel void self_cell_keys(SC_STATE x_in, __global ulong *keys, __global int *order,
                             const float inv_cell, const int count)
{
    int s = get_global_id(0);
    if (s >= SLOTS)
        return;
#ifndef CLOTH_PBD
#ifndef CLOTH_GENERIC
    x_in += PAD;
#endif
#endif
    ulong id = NO_CELL;
    if (s < count) {
        float3 x = SC_X(x_in, s);
        if (finite3(x))
            id = cell_id(cell_of(x, inv_cell));
    }
    keys[s] = id, order[s] = s;
}

/* One compare-and-exchange stage (block k, distance j) of the bitonic sort by (id, index). */
__kernel void self_sort_stage(__global ulong *keys, __global int *order, const int j, const int k)
{
    int s = get_global_id(0);
    int t = s ^ j;
    if (s >= SLOTS || t <= s)
        return;
    ulong ks = keys[s], kt = keys[t];
    int os = order[s], ot = order[t];
    bool later = ks > kt || (ks == kt && os > ot); /* s after t in (id, index) order */
    if (((s & k) == 0) == later) /* ascending blocks put the smaller first, descending last */
        keys[s] = kt, keys[t] = ks, order[s] = ot, order[t] = os;
}

/* Every stage (jj, kk) of the sort whose distance stays within a block of 2 SORT_GROUP slots, for
 * kk from k_first to k_last (doubling) and jj from min(kk / 2, SORT_GROUP) down to 1, on each
 * block in local memory: one work-group a block, one work item a compare-and-exchange, a
 * barrier between stages. The same exchanges as self_sort_stage's, so the same order. */
__kernel void self_sort_local(__global ulong *keys, __global int *order, const int k_first, const int k_last)
{
    __local ulong lk[2 * SORT_GROUP];
    __local int lo[2 * SORT_GROUP];
    int t = get_local_id(0), base = get_group_id(0) * 2 * SORT_GROUP;
    lk[t] = keys[base + t], lo[t] = order[base + t];
    lk[t + SORT_GROUP] = keys[base + t + SORT_GROUP], lo[t + SORT_GROUP] = order[base + t + SORT_GROUP];
    barrier(CLK_LOCAL_MEM_FENCE);
    for (int kk = k_first; kk <= k_last; kk *= 2)
        for (int jj = min(kk / 2, SORT_GROUP); jj > 0; jj /= 2) {
            int a = 2 * t - (t & (jj - 1)), b = a + jj; /* the t-th slot with bit jj clear, its partner */
            ulong ka = lk[a], kb = lk[b];
            int oa = lo[a], ob = lo[b];
            bool later = ka > kb || (ka == kb && oa > ob); /* a after b in (id, index) order */
            if ((((base + a) & kk) == 0) == later)
                lk[a] = kb, lk[b] = ka, lo[a] = ob, lo[b] = oa;
            barrier(CLK_LOCAL_MEM_FENCE);
        }
    keys[base + t] = lk[t], order[base + t] = lo[t];
    keys[base + t + SORT_GROUP] = lk[t + SORT_GROUP], order[base + t + SORT_GROUP] = lo[t + SORT_GROUP];
}

/* The first slot whose id is at least `id` (keys sorted). */
int lower_slot(__global const ulong *keys, ulong id)
{
    int lo = 0, hi = SLOTS;
    while (lo < hi) {
        int mid = (lo + hi) / 2;
        if (keys[mid] < id)
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo;
}

/* Whether j is one of i's pairs (docs/semantics.md, "Which pairs"), with d = x_i - x_j and its L2. */
bool self_pair(int j, float3 xi, int row, int col, int n, SC_STATE x_in, float thickness2, int exclude2, float3 *d,
               float *L2)
{
    *d = xi - SC_X(x_in, j);
    *L2 = ((*d).x * (*d).x + (*d).y * (*d).y) + (*d).z * (*d).z; /* not dot(): its order is the driver's */
    /* j == i has L2 = 0; coincident particles have no direction: nothing added */
    return *L2 < thickness2 && *L2 > 0.0f && !self_excluded(j / n - row, j % n - col, exclude2);
}

/* One pair's correction of i, added to corr (docs/semantics.md, in its order). */
float3 self_add(float3 corr, float3 d, float L2, float wi, float wj, float4 c)
{
    float thickness = c.x, relax = c.z;
    float L = sqrt(L2);
    float share = wi / (wi + wj); /* i's part of the shortfall, by inverse mass */
    float s = relax * (thickness - L);
    s = s * share;
    s = s / L;
    return corr + d * s;
}

#define SELF_HITS 32 /* pairs of one particle sorted in private memory; more take the merge */

/* Particle i's position after the pass: x_i plus its pairs' corrections, summed in ascending j.
 * The 27 cells around i's are nine rows along x, each one range of sorted slots; the candidates
 * are tested range by range (most fail) and the few pairs found summed sorted by j. A particle
 * with more than SELF_HITS pairs merges its cells' runs (each a distinct cell once, sorted by
 * index) by smallest j instead. */
float3 self_push(int i, int n, SC_STATE x_in, __global const float *inv_mass, __global const ulong *keys,
                 __global const int *order, float4 c, int exclude2)
{
    float thickness2 = c.y, inv_cell = c.w;
    float3 xi = SC_X(x_in, i);
    float wi = SC_W(x_in, inv_mass, i);
    if (!(wi > 0.0f) || !finite3(xi))
        return xi; /* a pinned particle does not move; one not finite is in no pair */
    /* A row's cells have consecutive ids (x is the id's low field), so one search finds the
     * row's first slot, and its cells are the slots up to the first id past the row; a cell
     * clamping made one with its neighbour is one id, met once. Rows are one only at the key's
     * limits, where clamping makes them so: there a row met before is skipped. */
    int3 k = cell_of(xi, inv_cell);
    bool edge = any(k <= -KEY_LIMIT + 1) || any(k >= KEY_LIMIT - 2);
    ulong rows[9];
    int from[9], to[9], row_count = 0;
    for (int dy = -1; dy <= 1; ++dy)
        for (int dz = -1; dz <= 1; ++dz) {
            ulong lo = cell_id(clamp(k + (int3)(-1, dy, dz), -KEY_LIMIT, KEY_LIMIT - 1));
            ulong hi = cell_id(clamp(k + (int3)(1, dy, dz), -KEY_LIMIT, KEY_LIMIT - 1));
            bool seen = false;
            for (int r = 0; edge && r < row_count; ++r)
                seen = seen || rows[r] == lo;
            if (seen)
                continue;
            rows[row_count] = lo;
            from[row_count] = lower_slot(keys, lo);
            to[row_count++] = lower_slot(keys, hi + 1);
        }
    int row = i / n, col = i % n;
    int hits[SELF_HITS], count = 0;
    float3 d, corr = (float3)(0.0f);
    float L2;
    for (int r = 0; r < row_count; ++r)
        for (int s = from[r]; s < to[r]; ++s) {
            int j = order[s];
            if (self_pair(j, xi, row, col, n, x_in, thickness2, exclude2, &d, &L2)) {
                if (count < SELF_HITS)
                    hits[count] = j;
                ++count;
            }
        }
    if (count == 0)
        return xi; /* a particle with no pair keeps its bits */
    if (count <= SELF_HITS) {
        for (int a = 1; a < count; ++a) /* insertion sort: ascending j */
            for (int b = a; b > 0 && hits[b - 1] > hits[b]; --b) {
                int t = hits[b];
                hits[b] = hits[b - 1], hits[b - 1] = t;
            }
        for (int h = 0; h < count; ++h) {
            int j = hits[h];
            self_pair(j, xi, row, col, n, x_in, thickness2, exclude2, &d, &L2);
            corr = self_add(corr, d, L2, wi, SC_W(x_in, inv_mass, j), c);
        }
        return xi + corr;
    }
    int next[27], end[27], runs = 0; /* each row's cells: one run (ascending index) a cell */
    for (int r = 0; r < row_count; ++r)
        for (int s = from[r]; s < to[r];) {
            ulong id = keys[s];
            next[runs] = s;
            while (s < to[r] && keys[s] == id)
                ++s;
            end[runs++] = s;
        }
    for (;;) {
        int best = -1, j = 0;
        for (int r = 0; r < runs; ++r)
            if (next[r] < end[r] && (best < 0 || order[next[r]] < j))
                best = r, j = order[next[r]];
        if (best < 0)
            break;
        ++next[best];
        if (self_pair(j, xi, row, col, n, x_in, thickness2, exclude2, &d, &L2))
            corr = self_add(corr, d, L2, wi, SC_W(x_in, inv_mass, j), c);
    }
    return xi + corr;
}

#if defined(CLOTH_PBD)
__kernel void pbd_self_collision(__global const float4 *xs_in, __global float4 *xs_out,
                                 __global const ulong *keys, __global const int *order, const float4 c,
                                 const int exclude2, __constant float4 *colliders STEP_ARG MESH_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded when the work-group size does not divide n*n */
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this substep's poses */
#endif
    float3 x = self_push(i, N, xs_in, 0, keys, order, c, exclude2);
    xs_out[i] = collide_particle((float4)(x, xs_in[i].w), colliders MESH_PASS); /* then the colliders */
}
#elif defined(CLOTH_GENERIC)
__kernel void self_collision(__global const float4 *x_in, __global float4 *x_out, const int n,
                             __global const ulong *keys, __global const int *order, const float4 c,
                             const int exclude2, __constant float4 *colliders, const int num_spheres,
                             const int num_cylinders, const int num_boxes, const int num_planes BODY_ARG)
{
    int i = get_global_id(0);
    if (i >= n * n)
        return; /* the launch is padded when the work-group size does not divide n*n */
    int analytic_rows = num_spheres + 3 * num_cylinders + 4 * num_boxes + 2 * num_planes;
#ifdef CLOTH_PER_STEP
    colliders += step * (analytic_rows + MESH_ROWS * CLOTH_MESHES); /* this step's poses */
#endif
    float w = x_in[i].w;
    float3 x = self_push(i, n, x_in, 0, keys, order, c, exclude2);
    if (w != 0.0f) { /* then the colliders, as the Verlet kernel would have */
        x = collide(x, colliders, num_spheres, num_cylinders, num_boxes, num_planes);
#if CLOTH_MESHES > 0
        x = collide_meshes(x, colliders + analytic_rows, mesh_geometry, mesh_ints); /* after the planes */
#endif
    }
    x_out[i] = (float4)(x, w);
}
#else
__kernel void self_collision(__global const float *x_in, __global const float *inv_mass,
                             __global float *x_out, __global const ulong *keys, __global const int *order,
                             const float4 c, const int exclude2, __constant float4 *colliders BODY_ARG)
{
    int i = get_global_id(0);
    if (i >= N2)
        return; /* the launch is padded when the work-group size does not divide n*n */
    x_in += PAD, x_out += PAD;
#ifdef CLOTH_PER_STEP
    colliders += step * TABLE_ROWS; /* this step's poses */
#endif
    float w = inv_mass[i];
    float3 x = self_push(i, N, x_in, inv_mass, keys, order, c, exclude2);
    if (w != 0.0f) { /* then the colliders, as the Verlet kernels would have */
        x = collide(x, colliders, CLOTH_SPHERES, CLOTH_CYLINDERS, CLOTH_BOXES, CLOTH_PLANES);
#if CLOTH_MESHES > 0
        x = collide_meshes(x, colliders + ANALYTIC_ROWS, mesh_geometry, mesh_ints); /* after the planes */
#endif
    }
    x_out[i] = x.x, x_out[STATE_STRIDE + i] = x.y, x_out[2 * STATE_STRIDE + i] = x.z;
}
#endif
