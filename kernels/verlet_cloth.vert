// verlet_cloth.vert: one triangle that covers the n x n viewport, so that the fragment
// shader (verlet_cloth.frag) runs once per texel, i.e. once per particle (chapter 22.6).
// No vertex buffer: the corners come from gl_VertexID (0, 1, 2 -> (-1,-1), (3,-1), (-1,3)).
// The host prepends `#version`.

void main()
{
    vec2 corner = vec2(float((gl_VertexID & 1) * 4 - 1), float((gl_VertexID >> 1) * 4 - 1));
    gl_Position = vec4(corner, 0.0, 1.0);
}
