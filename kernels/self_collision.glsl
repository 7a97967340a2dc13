// self_collision.glsl: the [self_collision] pass of docs/semantics.md ("Self-collision"),
// operation for operation, for the glsl-compute solvers: the grid's cell keys, one stage of the
// bitonic sort of (cell, index), and self_push, one particle's Jacobi projection over its pairs.
// kernels/self_collision.comp runs the keys and the sort; verlet_cloth.comp (PASS_SELF_COLLISION)
// and pbd_cloth.comp (STAGE_SELF_COLLISION) run the pass and then collide. The host
// (clothbench/backends/gl/self_contact.py) puts this file into a source only where the scene
// has the table. The includer defines SELF_X(j): particle j's vec4 before the pass (w: its
// inverse mass). Host defines, rounded once (kernel_inputs.SelfCollisionConstants):
//   SELF_C_VALUE     vec4(thickness, thickness2, relax, inv_cell), exact float32 literals
//   SELF_EXCLUDE2    pairs closer on the grid (dr^2 + dc^2 < it) are excluded like springs
//   SELF_NEIGHBOURS  bit (dr + R) * (2R + 1) + (dc + R) set for each stencil offset (scene.OFFSETS),
//                    R = SELF_REACH, the stencil's reach (colliders/self_contact.py STENCIL_REACH)
//   SELF_KEY_LIMIT   cell coordinates are clamped to [-SELF_KEY_LIMIT, SELF_KEY_LIMIT - 1] (2^20)
//   SELF_SLOTS       the sort's length: the particle count rounded up to a power of two
//
// The cell id: OpenCL's is one ulong, (x + 2^20) | (y + 2^20) << 21 | (z + 2^20) << 42 (63
// bits); GLSL 4.30 has no 64-bit integer (GL_ARB_gpu_shader_int64 is an extension a driver
// need not have), so here it is the same 63 bits as two uints, (low 32, high 31), compared high
// word first: the same order, so the same sort and the same runs.

#ifdef STRICT
#define SP precise
#else
#define SP
#endif

// bindings: gl/self_contact.py SELF_KEYS, SELF_ORDER
layout(std430, binding = 11) buffer SelfKeys { uvec2 self_keys[]; };  // sorted cell ids
layout(std430, binding = 12) buffer SelfOrder { int self_order[]; };  // the particle of each slot

const vec4 self_c = SELF_C_VALUE;
const uvec2 SELF_NO_CELL = uvec2(0xffffffffu);  // pad slots and non-finite particles: after every id

uvec2 self_cell_id(ivec3 k)
{
    uvec3 s = uvec3(k + SELF_KEY_LIMIT);  // 0 .. 2^21 - 1 per axis
    return uvec2(s.x | (s.y << 21), (s.y >> 11) | (s.z << 10));
}

bool self_id_less(uvec2 a, uvec2 b)
{
    return a.y < b.y || (a.y == b.y && a.x < b.x);
}

// the clamped cell coordinates of a finite position, floor(x * inv_cell) in float32
ivec3 self_cell_of(vec3 x)
{
    SP vec3 scaled = x * self_c.w;
    return ivec3(clamp(floor(scaled), vec3(-SELF_KEY_LIMIT), vec3(SELF_KEY_LIMIT - 1)));
}

bool self_finite(vec3 x)
{
    return !any(isnan(x)) && !any(isinf(x));
}

// slot s: particle s's cell id, or SELF_NO_CELL (a pad slot, a position that is not finite)
void self_cell_key(int s, int count)
{
    uvec2 id = SELF_NO_CELL;
    if (s < count) {
        vec3 x = SELF_X(s).xyz;
        if (self_finite(x))
            id = self_cell_id(self_cell_of(x));
    }
    self_keys[s] = id;
    self_order[s] = s;
}

// one compare-and-exchange stage (block k, distance j) of the bitonic sort by (id, index)
void self_sort_stage(int s, int j, int k)
{
    int t = s ^ j;
    if (t <= s)
        return;
    uvec2 ks = self_keys[s], kt = self_keys[t];
    int os = self_order[s], ot = self_order[t];
    bool later = self_id_less(kt, ks) || (ks == kt && os > ot);  // s after t in (id, index) order
    if (((s & k) == 0) == later) {  // ascending blocks put the smaller first, descending last
        self_keys[s] = kt, self_keys[t] = ks;
        self_order[s] = ot, self_order[t] = os;
    }
}

// the first slot whose id is at least `id` (the keys sorted)
int self_lower_slot(uvec2 id)
{
    int lo = 0, hi = SELF_SLOTS;
    while (lo < hi) {
        int mid = (lo + hi) / 2;
        if (self_id_less(self_keys[mid], id))
            lo = mid + 1;
        else
            hi = mid;
    }
    return lo;
}

// whether particles (dr, dc) apart on the grid are joined by a spring or closer at rest than
// the thickness
bool self_excluded(int dr, int dc)
{
    if (dr * dr + dc * dc < SELF_EXCLUDE2)
        return true;
    const int R = SELF_REACH;
    return abs(dr) <= R && abs(dc) <= R && ((SELF_NEIGHBOURS >> ((dr + R) * (2 * R + 1) + dc + R)) & 1) != 0;
}

// Particle i's position after the pass: x_i plus its pairs' corrections, summed in ascending j:
// the runs of the 27 cells around i's (each distinct cell once, sorted by index) merged by
// smallest j. A pinned particle does not move; one not finite is in no pair.
vec3 self_push(int i, int n)
{
    float thickness = self_c.x, thickness2 = self_c.y, relax = self_c.z;
    vec4 pi = SELF_X(i);
    vec3 xi = pi.xyz;
    float wi = pi.w;
    if (!(wi > 0.0) || !self_finite(xi))
        return xi;
    // The 27 cells as nine rows along x: a row's cells have consecutive ids (x is the id's low
    // field), so one search finds the row's first particle and a scan its cells' runs; a cell
    // clamping made one with its neighbour is one id, met once. Rows are one only at the key's
    // limits, where clamping makes them so: there a row met before is skipped.
    ivec3 k = self_cell_of(xi);
    bool edge = any(lessThanEqual(k, ivec3(-SELF_KEY_LIMIT + 1))) || any(greaterThanEqual(k, ivec3(SELF_KEY_LIMIT - 2)));
    uvec2 rows[9];
    int next[27], end[27];
    int runs = 0, row_count = 0;
    for (int dy = -1; dy <= 1; ++dy)
        for (int dz = -1; dz <= 1; ++dz) {
            uvec2 lo = self_cell_id(clamp(k + ivec3(-1, dy, dz), ivec3(-SELF_KEY_LIMIT), ivec3(SELF_KEY_LIMIT - 1)));
            uvec2 hi = self_cell_id(clamp(k + ivec3(1, dy, dz), ivec3(-SELF_KEY_LIMIT), ivec3(SELF_KEY_LIMIT - 1)));
            bool seen = false;
            for (int r = 0; edge && r < row_count; ++r)
                seen = seen || rows[r] == lo;
            if (seen)
                continue;
            rows[row_count++] = lo;
            int slot = self_lower_slot(lo);
            while (slot < SELF_SLOTS && !self_id_less(hi, self_keys[slot])) {  // each cell of the row: one run
                uvec2 id = self_keys[slot];
                next[runs] = slot;
                while (slot < SELF_SLOTS && self_keys[slot] == id)
                    ++slot;
                end[runs++] = slot;
            }
        }
    int row = i / n, col = i % n;
    SP vec3 corr = vec3(0.0);
    bool pushed = false;
    for (;;) {
        int best = -1, j = 0;
        for (int r = 0; r < runs; ++r)
            if (next[r] < end[r] && (best < 0 || self_order[next[r]] < j)) {
                best = r;
                j = self_order[next[r]];
            }
        if (best < 0)
            break;
        ++next[best];
        vec4 pj = SELF_X(j);
        SP vec3 d = xi - pj.xyz;
        SP float L2 = (d.x * d.x + d.y * d.y) + d.z * d.z;  // not dot(): its order is the driver's
        // j == i has L2 = 0; coincident particles have no direction: nothing added
        if (L2 < thickness2 && L2 > 0.0 && !self_excluded(j / n - row, j % n - col)) {
            SP float L = sqrt(L2);
            SP float share = wi / (wi + pj.w);  // i's part of the shortfall, by inverse mass
            SP float s = relax * (thickness - L);
            s = s * share;
            s = s / L;
            corr = corr + d * s;
            pushed = true;
        }
    }
    SP vec3 out_x = xi + corr;
    return pushed ? out_x : xi;
}
