// render_cloth.vert: one vertex per particle of the n x n sheet, drawn as indexed triangles
// (clothbench/reports/render.py). Vertex gl_VertexID is particle (row, col) = (id / n, id % n).
//
// STATE_TEXTURES: position and normal come straight from the `glsl` backend's RGBA32F state
// textures, texel (col, row), as the chapter maps its render target to a vertex buffer:
// no copy, no readback. Otherwise they are vertex attributes: the `glsl-compute` backend's
// storage buffers bound as vertex buffers, or positions another backend read back.

uniform mat4 view_projection;
uniform int n;
#ifdef STATE_TEXTURES
uniform sampler2D positions;  // x(t); w = inverse mass
uniform sampler2D normals;    // the normals of x(t), docs/normals.md
#else
in vec4 position;
in vec4 normal;
#endif

out vec3 world;     // position (m)
out vec3 normal_v;  // the particle's normal, interpolated
out vec2 sheet;     // (col, row) / (n - 1): where on the sheet, for the pattern

void main()
{
    int row = gl_VertexID / n;
    int col = gl_VertexID - row * n;
#ifdef STATE_TEXTURES
    world = texelFetch(positions, ivec2(col, row), 0).xyz;
    normal_v = texelFetch(normals, ivec2(col, row), 0).xyz;
#else
    world = position.xyz;
    normal_v = normal.xyz;
#endif
    sheet = vec2(col, row) / float(n - 1);
    gl_Position = view_projection * vec4(world, 1.0);
}
